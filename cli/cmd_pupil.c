/* specklewfs pupil HALO.fits [HALO2.fits ...] -o PUPIL.fits [--pupil MASK.fits] [--bias B] [--weight none|snr]
 * [--keep-resmean]: with more than one halo, the one whose speckles explain the most is used. */
#include "cli.h"

#include "specklewfs/estimate.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs pupil HALO.fits [HALO2.fits ...] -o PUPIL.fits [--pupil MASK.fits] [--method fit|moments]\n"
    "                        [--bias B] [--weight none|snr] [--wiener-k K] [--source lf|halo]\n"
    "                        [--keep-resmean] [--g-radial L]\n"
    "\n"
    "The pupil field and the NCP wavefront (eq:Pupil-field-with-NCP1, eq:NCP-WFE-estimate) from the\n"
    "static halo, inside the pupil with piston removed.\n"
    "\n"
    "With more than one halo (halos of the same science frames from different speckles: the\n"
    "default reconstructor and `speckles --recon learned.fits`, say), each is scored by the\n"
    "self-check (the fraction of the science intensity's variance its speckles explain, over\n"
    "the focal pixels solved in all of them), the table printed, and the best one used.\n"
    "\n"
    "  -o PUPIL.fits      output: FIELD (complex), WFE [m], SURFACE [m] (= WFE/2), AMPLITUDE, PUPIL;\n"
    "                     after a fit also HALO_FIT (complex Psi) and GAIN_FIT (g)\n"
    "  --pupil MASK.fits  pupil transmission (PUPN x PUPN); default: the annulus from TELDIAM, OBSCUR\n"
    "  --method fit       (default when HALO.fits has REGSTATE) fit the pupil field, a smooth g map and\n"
    "                     the unexplained speckle fraction to every focal pixel's regression statistics\n"
    "                     at once; WFE = the fitted phase (docs/estimator.md)\n"
    "  --g-radial L       the fit's g also varies with the distance from the star, on cubic\n"
    "                     B-splines L lambda/D apart (default 3; 0: Legendre terms alone): computed\n"
    "                     speckles hold less of the true field within the loop's control radius\n"
    "                     than beyond it, a step at a radius (docs/estimator.md)\n"
    "  --method moments   inverse MFT of the per-pixel moment estimate (the paper's Sec. 4.6; with\n"
    "                     'estimate --g-smooth 0 --weight none' the paper's formulae exactly). The\n"
    "                     options below apply to it and imply it.\n"
    "  --bias B           add B times the mean pupil field before taking the phase\n"
    "                     (eq:LFBiased-WFE-estimate; the paper used 0.5 on sky); default 0\n"
    "  --weight snr|none  weight each focal pixel by SNR^2/(SNR^2+k^2), SNR = |STAB|/STAB_ERR\n"
    "                     (default snr), or use every pixel at full weight as the paper does\n"
    "  --wiener-k K       k of the weight (default 2)\n"
    "  --source lf|halo   transform HALO_LF (eq:PSI-LowFreq, default) or HALO (eq:TheAnswer)\n"
    "  --keep-resmean     keep the AO residual's time mean in WFE. By default, when HALO.fits carries\n"
    "                     it (RESMEAN: speckles measure it from the telemetry over the same frames),\n"
    "                     what the focal window sees of it is taken out of WFE and FIELD, so WFE is the\n"
    "                     NCP alone; PUPIL.fits then has the map taken out (RESMEAN, RESMRMS)\n"
    "  --truth TRUTH.fits compare with a simulation's injected NCP (extension NCP [m]): prints the\n"
    "                     error rms with piston and tip/tilt removed, and records it (NCPERR); where\n"
    "                     the AO residual's mean was taken out, also the error with it kept in WFE\n"
    "                     (the one --keep-resmean gives), from the same fit\n";

/* The options checked as they come: --method, the fit's --g-radial, and the moments' --bias,
 * --wiener-k, --weight, --source (which imply the moments). */
typedef struct pupil_ctx {
    swfs_pupil_options *opt;
    int moments_opt, fit_opt;
} pupil_ctx;

static int special(void *vctx, int argc, char **argv, int *i)
{
    const char *cmd = "pupil", *a = argv[*i];
    pupil_ctx *ctx = vctx;
    swfs_pupil_options *opt = ctx->opt;
    if (!strcmp(a, "--method")) {
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "fit", SWFS_PUPIL_FIT, "moments", SWFS_PUPIL_MOMENTS,
                             &opt->method))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--g-radial")) {
        ctx->fit_opt = 1;
        if (cli_take_range(cmd, argc, argv, i, &opt->fit.g_radial, 0, 0, 1e3, 0,
                           "--g-radial must be >= 0 (lambda/D; 0: no radial terms)"))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--bias")) {
        ctx->moments_opt = 1;
        if (cli_parse_double(cmd, a, cli_next(argc, argv, i), &opt->bias)) return -CLI_USAGE;
    } else if (!strcmp(a, "--wiener-k")) {
        ctx->moments_opt = 1;
        if (cli_take_range(cmd, argc, argv, i, &opt->wiener_k, 0, 1, 1e6, 0,
                           "--wiener-k must be > 0 and at most 1e6 (k^2 in the weight)"))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--weight")) {
        ctx->moments_opt = 1;
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "snr", SWFS_WEIGHT_SNR, "none", SWFS_WEIGHT_NONE,
                             &opt->weight))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--source")) {
        ctx->moments_opt = 1;
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "lf", SWFS_SOURCE_HALO_LF, "halo", SWFS_SOURCE_HALO,
                             &opt->source))
            return -CLI_USAGE;
    } else {
        return 0;
    }
    return 1;
}

int swfs_cmd_pupil(int argc, char **argv)
{
    const char *cmd = "pupil";
    const char *in = NULL, *out = NULL, *maskfile = NULL, *truthfile = NULL;
    swfs_pupil_options opt;
    swfs_pupil_options_default(&opt);
    pupil_ctx pctx = {&opt, 0, 0};
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &out, "a file name", 0},         {"--pupil", CLI_STRING, &maskfile, "a file name", 0},
        {"--truth", CLI_STRING, &truthfile, "a file name", 0},  {"--keep-resmean", CLI_SET, &opt.keep_resmean, NULL, 1},
    };
    const char **ins = calloc((size_t)argc, sizeof *ins);
    size_t nin = 0;
    if (!ins) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, special, &pctx, ins, &nin};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc || !nin) free(ins);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!nin) return cli_usage_error(cmd, "needs HALO.fits");
    in = ins[0];
    int urc = CLI_OK;
    if (!out) urc = cli_usage_error(cmd, "needs -o PUPIL.fits");
    else if (pctx.moments_opt && opt.method == SWFS_PUPIL_FIT)
        urc = cli_usage_error(cmd, "--bias, --weight, --wiener-k and --source apply to --method moments, not fit");
    else if (pctx.moments_opt && pctx.fit_opt)
        urc = cli_usage_error(cmd, "--g-radial applies to the fit, not to --bias, --weight, --wiener-k or --source");
    else if (pctx.fit_opt && opt.method == SWFS_PUPIL_MOMENTS)
        urc = cli_usage_error(cmd, "--g-radial applies to --method fit, not moments");
    if (urc) { free(ins); return urc; }
    if (pctx.moments_opt) opt.method = SWFS_PUPIL_MOMENTS;

    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    swfs_pupil_run_options o;
    swfs_pupil_run_options_default(&o);
    o.halos = ins;
    o.nhalo = nin;
    o.out = out;
    o.mask = maskfile;
    o.truth = truthfile;
    o.pupil = opt;
    o.prov = prov;
    o.nprov = 1;
    swfs_pupil_run_result res;
    if (swfs_pupil_run(&o, &res)) {
        free(ins);
        return cli_error(cmd);
    }
    const swfs_pupil_result *r = res.pupil;
    const swfs_geom g = res.geom;
    if (nin > 1) {
        printf("pupil: the speckles' self-check over the %zu focal pixels solved in all %zu halos (the fraction of the "
               "science intensity's variance they explain):\n", res.ncommon, nin);
        for (size_t k = 0; k < nin; k++)
            printf("  %-40s %6.2f %%%s\n", ins[k], 100 * res.explained[k], k == res.chosen ? "  <- used" : "");
        printf("pupil: chosen by the self-check among %zu halos: %s (%.2f %% explained)\n", nin, ins[res.chosen],
               100 * res.explained[res.chosen]);
    }
    in = ins[res.chosen];
    printf("pupil: %s\n", out);
    if (r->method == SWFS_PUPIL_FIT) {
        cli_pupil_fit_summary(r, &g, out);
    } else {
        if (opt.method == SWFS_PUPIL_AUTO)
            printf("  note              %s has no regression statistics (REGSTATE): the per-pixel moments are used\n",
                   in);
        printf("  method            moments: source %s, weight %s (k = %g), bias %g\n",
               opt.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF", opt.weight == SWFS_WEIGHT_SNR ? "snr" : "none",
               opt.wiener_k, opt.bias);
    }
    if (r->resmean)
        printf("  AO residual mean  %.1f nm rms taken out (the telemetry's time mean over the same frames, as the "
               "window sees it; RESMEAN): WFE is the NCP alone\n", r->resmean_rms * 1e9);
    else if (res.halo->resmean)
        printf("  AO residual mean  kept (--keep-resmean): WFE is the whole static aberration the camera saw\n");
    printf("  WFE               %.1f nm rms, %.1f nm peak to valley (piston removed)\n", r->wfe_rms * 1e9, r->wfe_pv * 1e9);
    printf("  surface           %.1f nm rms\n", 0.5 * r->wfe_rms * 1e9);
    printf("  Strehl (Marechal) %.3f at %.3g um\n", r->strehl, g.wavelen * 1e6);
    if (res.ran_away)
        fprintf(stderr, "specklewfs pupil: warning: the WFE of %s, %.1f nm rms, is more than half the wavelength "
                "(%.1f nm): a phase of %.1f rad rms, which no image with a core comes from; the fit ran away from its "
                "start and this is not an estimate; more frames, or --method moments, may do\n", out,
                r->wfe_rms * 1e9, 0.5 * g.wavelen * 1e9, 2 * M_PI * r->wfe_rms / g.wavelen);
    if (truthfile)
        printf("  versus truth      injected %.1f nm rms (%.1f nm without tip/tilt); error %.1f nm rms (piston, tip, "
               "tilt removed)\n", res.truth_rms * 1e9, res.truth_rms_ptt * 1e9, res.err * 1e9);
    if (truthfile && r->resmean)
        printf("  mean kept         error %.1f nm rms with the AO residual mean left in WFE (what --keep-resmean "
               "gives from the same fit)\n", res.err_kept * 1e9);
    free(ins);
    swfs_pupil_run_result_free(&res);
    return CLI_OK;
}

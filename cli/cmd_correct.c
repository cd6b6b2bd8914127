/* specklewfs correct: closed-loop NCP correction in simulation (closed_loop.h), and the
 * per-iteration table that `demo` prints too. */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/config.h"
#include "specklewfs/status.h"
#include "specklewfs/sweep.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs correct [CONFIG] [key=value ...] -o DIR [--iterations N] [--gain G] [--sigma S]\n"
    "                          [--actuators ACT.fits | --pitch P] [--influence gauss|cubic] [--coupling C]\n"
    "                          [--modes K] [--method fit|moments] [--weight snr|none]\n"
    "\n"
    "Closes the loop on the paper's Sec. 3 simulation: each iteration simulates the data with\n"
    "the current residual NCP (new turbulence and camera noise every time, as on the sky),\n"
    "estimates the static halo and the pupil WFE, fits the DM offsets (-WFE/2 onto the\n"
    "actuators' influence functions) and applies gain x offsets; the residual wavefront is\n"
    "NCP + 2 x DM surface, so the DM's fitting error stays in it. Prints per iteration the\n"
    "residual NCP [nm rms], the Strehl of the simulated long-exposure PSF, and the raw\n"
    "contrast of the static halo in 2-6 lambda/D; writes DIR/loop.tsv and DIR/loop.fits.\n"
    "\n"
    "  -o DIR              output folder (default correct-out)\n"
    "  --iterations N      corrections to apply (default 5)\n"
    "  --gain G            loop gain (default 0.8)\n"
    "  --sigma S           camera background noise [counts] (default 100)\n"
    "  --actuators ACT.fits  DM actuator positions (2 x nact [m]); default: hexapolar with\n"
    "  --pitch P           ring spacing P [m] (default 0.35: 331 actuators on 6.5 m)\n"
    "  --influence gauss|cubic, --coupling C, --modes K: the DM fit (see 'dmoffsets --help')\n"
    "  --method fit|moments  the pupil step: the joint fit (default) or the per-pixel moments\n"
    "  --weight snr|none   focal-plane weight of the moments' pupil step (default snr; implies moments)\n"
    "  --sweep SETS.txt    a parameter sweep: one closed loop per line of SETS.txt (key=value\n"
    "                      ... over the configuration; also loop_iterations, loop_gain,\n"
    "                      loop_sigma, loop_pitch), one row per set in DIR/sweep.tsv; under\n"
    "                      mpirun the sets are shared out over the processes (docs/cluster.md)\n"
    "CONFIG and key=value set the simulation (config/paper-sec3.conf), e.g. seed=3.\n";

void cli_print_loop_table(const swfs_loop_result *r)
{
    const swfs_loop_params *lp = &r->params;
    char infl[64];
    if (lp->fit.influence == SWFS_INFLUENCE_CUBIC) snprintf(infl, sizeof infl, "cubic influence");
    else snprintf(infl, sizeof infl, "Gaussian influence, coupling %.2f", lp->fit.coupling);
    const char *how = lp->pupil.method == SWFS_PUPIL_MOMENTS
                          ? (lp->pupil.weight == SWFS_WEIGHT_SNR ? "moments, SNR-weighted HALO_LF" : "moments, HALO_LF")
                          : "joint fit";
    printf("  closed loop: gain %.2f, sigma %g counts, %zu actuators (pitch %.3g m, %s), %s\n", lp->gain, lp->sigma,
           r->nact, r->pitch, infl, how);
    if (lp->fit.modes) printf("  modal filter: first %zu Zernikes\n", lp->fit.modes);
    printf("  %4s %8s %8s %7s %8s %10s %10s %8s %7s %7s %6s\n", "iter", "resid", "resid-TT", "Strehl", "Marechal",
           "contrast", "NCP halo", "est.err", "fit", "unfit", "time");
    printf("  %4s %8s %8s %7s %8s %10s %10s %8s %7s %7s %6s\n", "", "[nm]", "[nm]", "", "(NCP)", "2-6 l/D", "2-6 l/D",
           "[nm]", "[nm]", "[nm]", "[s]");
    for (size_t k = 0; k < r->nrows; k++) {
        const swfs_loop_iter *it = &r->rows[k];
        printf("  %4zu %8.1f %8.1f %7.4f %8.4f %10.3e %10.3e", k, it->resid_rms * 1e9, it->resid_rms_ptt * 1e9,
               it->strehl, it->strehl_marechal, it->contrast, it->contrast_ncp);
        if (k + 1 < r->nrows)
            printf(" %8.1f %7.1f %7.1f", it->est_err * 1e9, 2 * it->fit.fit_rms * 1e9, 2 * it->fit.unfit_rms * 1e9);
        else
            printf(" %8s %7s %7s", "-", "-", "-");
        printf(" %6.2f\n", it->seconds);
    }
    const swfs_loop_iter *a = &r->rows[0], *b = &r->rows[r->nrows - 1];
    printf("  no-NCP ceiling: Strehl %.4f, contrast %.3e (the AO residual alone)\n", b->strehl_ao, b->contrast_ao);
    printf("  residual %.1f -> %.1f nm rms, Strehl %.4f -> %.4f, contrast %.3e -> %.3e, NCP halo %.3e -> %.3e (/%.0f)\n",
           a->resid_rms * 1e9, b->resid_rms * 1e9, a->strehl, b->strehl, a->contrast, b->contrast, a->contrast_ncp,
           b->contrast_ncp, a->contrast_ncp / b->contrast_ncp);
    printf("  resid: residual NCP wavefront (piston removed; -TT: tip/tilt also removed) after k corrections.\n"
           "  Strehl: peak of the simulated long-exposure PSF (AO residual included) over the unaberrated peak;\n"
           "  Marechal: exp(-(2 pi resid/lambda)^2), the NCP alone. contrast: mean |static halo|^2 in 2-6 lambda/D\n"
           "  over its peak (AO-attenuated Airy rings included); NCP halo: the same for the static halo minus the\n"
           "  no-NCP one. est.err: estimate - true residual (piston, tip/tilt removed); fit/unfit: wavefront the\n"
           "  DM offsets reproduce / leave out of that iteration's estimate. Total %.2f s.\n", r->seconds);
}

typedef struct corr_args {
    swfs_loop_params *lp;
    swfs_config *cfg;
    const char **cfgfile; /* the CONFIG file given, for the path checks */
} corr_args;

/* The loop's options, checked as they come, the DM fit's, then CONFIG or key=value. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "correct", *a = argv[*i];
    corr_args *d = ctx;
    swfs_loop_params *lp = d->lp;
    if (!strcmp(a, "--iterations")) {
        long k;
        if (cli_take_long(cmd, argc, argv, i, &k)) return -CLI_USAGE;
        if (k < 0 || k > 1000) return -cli_usage_error(cmd, "--iterations must be 0..1000, got %ld", k);
        lp->iterations = (size_t)k;
    } else if (!strcmp(a, "--gain")) {
        if (cli_take_range(cmd, argc, argv, i, &lp->gain, 0, 1, 2, 0, "--gain must be in (0, 2]")) return -CLI_USAGE;
    } else if (!strcmp(a, "--sigma")) {
        if (cli_take_range(cmd, argc, argv, i, &lp->sigma, 0, 0, INFINITY, 0, "--sigma must be >= 0")) return -CLI_USAGE;
    } else if (!strcmp(a, "--pitch")) {
        if (cli_take_range(cmd, argc, argv, i, &lp->act_pitch, 0, 1, INFINITY, 0, "--pitch must be > 0 [m]"))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--method")) {
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "fit", SWFS_PUPIL_FIT, "moments", SWFS_PUPIL_MOMENTS,
                             &lp->pupil.method))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--weight")) {
        lp->pupil.method = SWFS_PUPIL_MOMENTS;
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "snr", SWFS_WEIGHT_SNR, "none", SWFS_WEIGHT_NONE,
                             &lp->pupil.weight))
            return -CLI_USAGE;
    } else {
        int t = cli_dmfit_option(cmd, argc, argv, i, &lp->fit);
        if (t || (a[0] == '-' && a[1] && !strchr(a, '='))) return t; /* 0: an unknown option */
        if (!strchr(a, '=')) *d->cfgfile = a;
        if (cli_config_arg(cmd, d->cfg, a)) return -CLI_FAIL;
    }
    return 1;
}

int swfs_cmd_correct(int argc, char **argv)
{
    const char *cmd = "correct";
    const char *outdir = "correct-out", *actfile = NULL, *sweep = NULL, *cfgfile = NULL;
    swfs_loop_params lp;
    swfs_loop_params_default(&lp);
    swfs_config *cfg = swfs_config_new();
    if (!cfg) return cli_error(cmd);
    int rc = CLI_USAGE;
    double *xy = NULL;
    swfs_loop_result *res = NULL;
    const cli_opt opts[] = {{"-o", CLI_STRING, &outdir, "a folder", 0},
                            {"--actuators", CLI_STRING, &actfile, "a file name", 0},
                            {"--sweep", CLI_STRING, &sweep, "a file of parameter sets", 0}};
    corr_args d = {&lp, cfg, &cfgfile};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, special, &d, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) {
        rc = prc < 0 ? CLI_OK : prc;
        goto done;
    }
    rc = CLI_FAIL;
    if (sweep) {
        if (actfile) {
            if (swfs_actuators_read(actfile, &xy, &lp.nact)) { cli_error(cmd); goto done; }
            lp.act_xy = xy;
            lp.act_name = actfile;
        }
        rc = cli_sweep(cmd, SWFS_SWEEP_CORRECT, cfg, &lp, outdir, sweep, argc, argv);
        goto done;
    }
    swfs_sim_params p;
    if (cli_sim_params(cmd, cfg, &p)) goto done;
    if (actfile) {
        if (swfs_actuators_read(actfile, &xy, &lp.nact)) { cli_error(cmd); goto done; }
        lp.act_xy = xy;
        lp.act_name = actfile;
    }
    if (cli_make_dir(cmd, outdir)) goto done;
    static const char *const products[] = {"loop.tsv", "loop.fits"};
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "config file", cfgfile);
    swfs_paths_input(paths, "--actuators", actfile);
    cli_paths_outputs_in(paths, outdir, products, 2);
    if (cli_paths_check(cmd, paths)) goto done;
    fprintf(stderr, "correct: %zu iterations at gain %g, sigma %g counts (%d screens of %zu^2 each)\n", lp.iterations,
            lp.gain, lp.sigma, p.nscreens, p.screen.n);
    if (swfs_closed_loop_run(&p, &lp, NULL, cli_stage_progress, (void *)"correct:", &res)) {
        rc = cli_error(cmd); /* 128 + the signal where SIGINT/SIGTERM stopped it */
        goto done;
    }
    size_t nprov;
    const char *const *prov = cli_provenance(argc, argv, &nprov);
    swfs_outputs_begin(); /* loop.tsv and loop.fits together (atomic.h) */
    int wrc = swfs_closed_loop_write(res, outdir, prov, nprov);
    if (swfs_outputs_end(wrc == SWFS_OK) || wrc) { cli_error(cmd); goto done; }
    printf("specklewfs correct: Codona & Kenworthy (2013) Sec. 3 simulation in closed loop, %s/loop.{tsv,fits}\n", outdir);
    cli_print_loop_table(res);
    rc = CLI_OK;
done:
    swfs_loop_result_free(res);
    free(xy);
    swfs_config_free(cfg);
    return rc;
}

/* specklewfs pupil HALO.fits -o PUPIL.fits [--pupil MASK.fits] [--bias B] [--weight none|snr] */
#include "cli.h"

#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs pupil HALO.fits -o PUPIL.fits [--pupil MASK.fits] [--bias B] [--weight none|snr]\n"
    "                        [--wiener-k K] [--source lf|halo]\n"
    "\n"
    "Inverse MFT of the static halo to the pupil grid (eq:Pupil-field-with-NCP1) and the NCP\n"
    "wavefront WFE = arg(field) lambda/2pi inside the pupil, piston removed (eq:NCP-WFE-estimate).\n"
    "\n"
    "  -o PUPIL.fits      output: FIELD (complex), WFE [m], SURFACE [m] (= WFE/2), AMPLITUDE, PUPIL\n"
    "  --pupil MASK.fits  pupil transmission (PUPN x PUPN); default: the annulus from TELDIAM, OBSCUR\n"
    "  --bias B           add B times the mean pupil field before taking the phase\n"
    "                     (eq:LFBiased-WFE-estimate; the paper used 0.5 on sky); default 0\n"
    "  --weight snr|none  weight each focal pixel by SNR^2/(SNR^2+k^2), SNR = |STAB|/STAB_ERR\n"
    "                     (default snr), or use every pixel at full weight as the paper does\n"
    "  --wiener-k K       k of the weight (default 2)\n"
    "  --source lf|halo   transform HALO_LF (eq:PSI-LowFreq, default) or HALO (eq:TheAnswer)\n"
    "  --truth TRUTH.fits compare with a simulation's injected NCP (extension NCP [m]): prints the\n"
    "                     error rms with piston and tip/tilt removed, and records it (NCPERR)\n";

int swfs_cmd_pupil(int argc, char **argv)
{
    const char *cmd = "pupil";
    const char *in = NULL, *out = NULL, *maskfile = NULL, *truthfile = NULL;
    swfs_pupil_options opt;
    swfs_pupil_options_default(&opt);
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "-o")) { if (++i >= argc) return cli_usage_error(cmd, "-o needs a file name"); out = argv[i]; }
        else if (!strcmp(a, "--pupil")) { if (++i >= argc) return cli_usage_error(cmd, "--pupil needs a file name"); maskfile = argv[i]; }
        else if (!strcmp(a, "--truth")) { if (++i >= argc) return cli_usage_error(cmd, "--truth needs a file name"); truthfile = argv[i]; }
        else if (!strcmp(a, "--bias")) { if (cli_parse_double(cmd, a, i + 1 < argc ? argv[++i] : NULL, &opt.bias)) return CLI_USAGE; }
        else if (!strcmp(a, "--wiener-k")) {
            if (cli_parse_double(cmd, a, i + 1 < argc ? argv[++i] : NULL, &opt.wiener_k)) return CLI_USAGE;
            if (!(opt.wiener_k > 0)) return cli_usage_error(cmd, "--wiener-k must be > 0");
        } else if (!strcmp(a, "--weight")) {
            const char *v = i + 1 < argc ? argv[++i] : "";
            if (!strcmp(v, "snr")) opt.weight = SWFS_WEIGHT_SNR;
            else if (!strcmp(v, "none")) opt.weight = SWFS_WEIGHT_NONE;
            else return cli_usage_error(cmd, "--weight expects 'snr' or 'none', got '%s'", v);
        } else if (!strcmp(a, "--source")) {
            const char *v = i + 1 < argc ? argv[++i] : "";
            if (!strcmp(v, "lf")) opt.source = SWFS_SOURCE_HALO_LF;
            else if (!strcmp(v, "halo")) opt.source = SWFS_SOURCE_HALO;
            else return cli_usage_error(cmd, "--source expects 'lf' or 'halo', got '%s'", v);
        } else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (!in) in = a;
        else return cli_usage_error(cmd, "unexpected argument '%s'", a);
    }
    if (!in) return cli_usage_error(cmd, "needs HALO.fits");
    if (!out) return cli_usage_error(cmd, "needs -o PUPIL.fits");

    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "halo", in);
    swfs_paths_input(paths, "--pupil mask", maskfile);
    swfs_paths_input(paths, "--truth", truthfile);
    swfs_paths_output(paths, "-o", out);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;

    swfs_halo *h = NULL;
    swfs_real *mask = NULL, *truth = NULL;
    swfs_pupil_result *r = NULL;
    int rc = CLI_FAIL;
    swfs_geom g;
    if (swfs_halo_read(in, &h, &g)) { cli_error(cmd); goto done; }
    if (swfs_geom_require(&g, in)) { cli_error(cmd); goto done; }
    if (maskfile) {
        if (swfs_fits_read_real(maskfile, NULL, &mask, NULL)) { cli_error(cmd); goto done; }
        if (mask->nz != 1 || mask->nx != (size_t)g.pupn || mask->ny != (size_t)g.pupn) {
            fprintf(stderr, "specklewfs %s: %s: mask is %zux%zux%zu but %s says PUPN = %ld (expected a %ldx%ld image)\n",
                    cmd, maskfile, mask->nx, mask->ny, mask->nz, in, g.pupn, g.pupn, g.pupn);
            goto done;
        }
        if (swfs_pupil_mask_check(mask, maskfile)) { cli_error(cmd); goto done; }
    }
    if (swfs_pupil_estimate(h, &g, mask, &opt, &r)) {
        fprintf(stderr, "specklewfs %s: %s: %s\n", cmd, in, swfs_last_error());
        goto done;
    }
    double err = NAN, truth_p = NAN, truth_ptt = NAN;
    if (truthfile) {
        if (swfs_fits_read_real(truthfile, "NCP", &truth, NULL)) { cli_error(cmd); goto done; }
        if (truth->nx != (size_t)g.pupn || truth->ny != (size_t)g.pupn || truth->nz != 1) {
            fprintf(stderr, "specklewfs %s: %s: NCP is %zux%zux%zu but %s says PUPN = %ld\n", cmd, truthfile, truth->nx,
                    truth->ny, truth->nz, in, g.pupn);
            goto done;
        }
        if (swfs_wfe_compare(r->wfe->data, truth->data, r->mask->data, (size_t)g.pupn, &err, &truth_p, &truth_ptt)) {
            cli_error(cmd);
            goto done;
        }
    }
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    char tl[256];
    snprintf(tl, sizeof tl, "compared with %s: NCP error %.4g m rms (piston, tip, tilt removed)", truthfile ? truthfile : "",
             err);
    const char *prov[] = {cl, tl};
    if (swfs_pupil_write(r, out, &g, prov, truthfile ? 2 : 1)) { cli_error(cmd); goto done; }
    printf("pupil: %s\n", out);
    printf("  source            %s, weight %s (k = %g), bias %g\n", opt.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF",
           opt.weight == SWFS_WEIGHT_SNR ? "snr" : "none", opt.wiener_k, opt.bias);
    printf("  WFE               %.1f nm rms, %.1f nm peak to valley (piston removed)\n", r->wfe_rms * 1e9, r->wfe_pv * 1e9);
    printf("  surface           %.1f nm rms\n", 0.5 * r->wfe_rms * 1e9);
    printf("  Strehl (Marechal) %.3f at %.3g um\n", r->strehl, g.wavelen * 1e6);
    if (truthfile)
        printf("  versus truth      injected %.1f nm rms (%.1f nm without tip/tilt); error %.1f nm rms (piston, tip, "
               "tilt removed)\n", truth_p * 1e9, truth_ptt * 1e9, err * 1e9);
    rc = CLI_OK;
done:
    swfs_pupil_result_free(r);
    swfs_real_free(mask);
    swfs_real_free(truth);
    swfs_halo_free(h);
    return rc;
}

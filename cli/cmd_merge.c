/* specklewfs merge A.ckpt.fits B.ckpt.fits ... -o C.ckpt.fits [--halo HALO.fits] */
#include "cli.h"

#include "specklewfs/accum.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs merge A.fits B.fits ... -o C.fits [--halo HALO.fits] [--read-noise SIGMA] [--gain G]\n"
    "                        [--g-smooth L]\n"
    "\n"
    "Combine accumulator checkpoints (written by 'specklewfs stream --checkpoint') of disjoint\n"
    "sets of frames -- a night split into chunks, or run on several machines -- into the\n"
    "checkpoint of their union. The merge is exact (Chan et al.'s pairwise update): the result\n"
    "equals one pass over all frames to rounding, in any order. All inputs must have the same\n"
    "frame size and geometry (WAVELEN, PIXSCALE, ...).\n"
    "\n"
    "  -o C.fits             merged checkpoint (may itself be merged again)\n"
    "  --halo HALO.fits      also run the estimator on the merged accumulators and write\n"
    "                        HALO.fits (same extensions as 'specklewfs estimate')\n"
    "  --read-noise SIGMA    per-frame read noise [counts] for --halo (default 0)\n"
    "  --gain G              detector gain [e-/count] for --halo's photon-noise term\n"
    "                        (default: none)\n"
    "  --g-smooth L          scale-factor regularization [lambda/D] for --halo, as in\n"
    "                        'specklewfs estimate' (default 2; 0 = per-pixel g)\n";

int swfs_cmd_merge(int argc, char **argv)
{
    const char *cmd = "merge";
    const char *out = NULL, *halo_path = NULL;
    double read_noise = 0.0, gain = 0.0, g_smooth = 2.0;
    const char **inputs = calloc((size_t)argc, sizeof *inputs);
    size_t nin = 0;
    if (!inputs) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    int rc = CLI_USAGE;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &out, "a file name", 0},     {"--halo", CLI_STRING, &halo_path, "a file name", 0},
        {"--read-noise", CLI_DOUBLE, &read_noise, NULL, 0}, {"--gain", CLI_DOUBLE, &gain, NULL, 0},
        {"--g-smooth", CLI_DOUBLE, &g_smooth, NULL, 0},
    };
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, NULL, NULL, inputs, &nin};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc < 0) rc = CLI_OK;
    if (prc) goto done;
    if (!nin) { cli_usage_error(cmd, "needs at least one checkpoint file"); goto done; }
    if (!out) { cli_usage_error(cmd, "needs -o C.fits"); goto done; }
    if (read_noise < 0) { cli_usage_error(cmd, "--read-noise must be >= 0, got %g", read_noise); goto done; }
    if (gain < 0) { cli_usage_error(cmd, "--gain must be >= 0, got %g", gain); goto done; }
    if (!(g_smooth >= 0)) { cli_usage_error(cmd, "--g-smooth must be >= 0, got %g", g_smooth); goto done; }
    rc = CLI_FAIL;
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    for (size_t i = 0; i < nin; i++) swfs_paths_input(paths, "checkpoint", inputs[i]);
    swfs_paths_output(paths, "-o", out);
    swfs_paths_output(paths, "--halo", halo_path);
    if (cli_paths_check(cmd, paths)) goto done;
    swfs_accum *acc = NULL;
    swfs_halo *halo = NULL;
    swfs_geom g;
    swfs_real *resmean = NULL;
    size_t rnexp = 0, rmissing = 0;
    if (swfs_accum_merge_files(inputs, nin, &acc, &g)) { cli_error(cmd); goto done; }
    if (swfs_resmean_merge_files(inputs, nin, &resmean, &rnexp, &rmissing)) {
        cli_error(cmd);
        swfs_accum_free(acc);
        goto done;
    }
    if (rmissing && rmissing < nin)
        fprintf(stderr, "specklewfs %s: note: %zu of %zu checkpoints carry no AO residual mean (RESMEAN): the merged "
                "products have none, and pupil keeps it in the wavefront\n", cmd, rmissing, nin);
    /* The halo and the checkpoint are renamed into place together (atomic.h). */
    swfs_outputs_begin();
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    if (halo_path) {
        swfs_noise noise = {read_noise, gain};
        swfs_estimate_options eopt = {0.0};
        if (g_smooth > 0) {
            if (!(g.pixscale > 0)) {
                fprintf(stderr, "specklewfs %s: the checkpoints record no PIXSCALE, so --g-smooth %g lambda/D cannot be "
                        "converted to pixels; use --g-smooth 0\n", cmd, g_smooth);
                goto free_acc;
            }
            eopt.g_smooth = g_smooth / g.pixscale;
        }
        if (swfs_estimate(acc, &noise, &eopt, &halo)) { cli_error(cmd); goto free_acc; }
        if (resmean && !(halo->resmean = swfs_real_copy(resmean))) { cli_error(cmd); goto free_acc; }
        char nl[256];
        snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count", noise.read_noise, noise.gain);
        const char *hprov[] = {cl, nl};
        if (swfs_halo_write(halo, halo_path, &g, hprov, 2)) { cli_error(cmd); goto free_acc; }
        printf("merge: %s: valid pixels %zu of %zu (%.1f %%), median SNR %.3g\n", halo_path, halo->n_valid, halo->npix,
               100.0 * halo->valid_fraction, halo->median_snr);
    }
    if (swfs_accum_save_resmean(acc, resmean, rnexp, out, &g, prov, 1) || swfs_outputs_end(1)) {
        cli_error(cmd);
        goto free_acc;
    }
    printf("merge: %zu checkpoints -> %s: %llu frames, %llu pixel-frames skipped, %zux%zu pixels\n", nin, out,
           (unsigned long long)acc->frames, (unsigned long long)acc->skipped, acc->nx, acc->ny);
    rc = CLI_OK;
free_acc:
    if (rc) swfs_outputs_end(0);
    swfs_halo_free(halo);
    swfs_accum_free(acc);
    swfs_real_free(resmean);
done:
    free(inputs);
    return rc;
}

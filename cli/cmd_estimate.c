/* specklewfs estimate SCIENCE.fits SPECKLES.fits -o HALO.fits [--read-noise S] [--gain G] */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs estimate SCIENCE.fits SPECKLES.fits -o HALO.fits [--read-noise SIGMA] [--gain E_PER_COUNT]\n"
    "\n"
    "Per-pixel random-reference interferometry (Codona & Kenworthy 2013, Sec. 2.2-2.4):\n"
    "the science cube I (real, x, y, frame) and the synchronized speckle cube psi (complex)\n"
    "give the static halo Psi (eq:TheAnswer), its low-frequency form (eq:PSI-LowFreq), the\n"
    "scale factor g (eq:scale-factor), visibility (eq:visibility) and SNR (eq:SNR).\n"
    "\n"
    "  -o HALO.fits          output (extensions HALO, HALO_LF, STAB, GAIN, VISIB, SNR, MEAN_I,\n"
    "                        VAR_I, MEAN_SP, VAR_SP, STAB_ERR, CIRC, VALID, NFRAMES)\n"
    "  --read-noise SIGMA    per-frame background/read noise [counts]; default: the science\n"
    "                        header's RDNOISE, else 0\n"
    "  --gain G              detector gain [e-/count] for the photon-noise variance Phi_I/G;\n"
    "                        default: the science header's GAIN, else no photon term (as 0)\n"
    "  --g-smooth L          regularize the scale factor over Gaussian neighbourhoods whose size\n"
    "                        follows the data, on a ladder L 2^k lambda/D from half a pixel to the\n"
    "                        whole map (default 2; 0 = the paper's per-pixel g; docs/estimator.md)\n"
    "  --frames-per-read N   frames read per block (default 64)\n"
    "\n"
    "Non-finite science pixels are skipped for that frame and counted; the speckle mean over\n"
    "the data set is removed exactly (eq:zeroMean). Under mpirun every process accumulates\n"
    "a share of the frames and rank 0 writes HALO.fits from the merged accumulators\n"
    "(docs/cluster.md).\n";

static int parse(int argc, char **argv, swfs_estimate_run_options *o)
{
    const char *cmd = "estimate";
    long block = (long)o->block;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o->out, "a file name", 0},      {"--read-noise", CLI_DOUBLE, &o->read_noise, NULL, 0},
        {"--gain", CLI_DOUBLE, &o->gain, NULL, 0},          {"--g-smooth", CLI_DOUBLE, &o->g_smooth_lod, NULL, 0},
        {"--frames-per-read", CLI_LONG, &block, NULL, 0},
    };
    const char **const pos[] = {&o->science, &o->speckles};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 2, NULL, NULL, NULL, NULL};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc) return rc;
    if (!o->science || !o->speckles) return cli_usage_error(cmd, "needs SCIENCE.fits and SPECKLES.fits");
    if (!o->out) return cli_usage_error(cmd, "needs -o HALO.fits");
    if (!isnan(o->read_noise) && o->read_noise < 0) return cli_usage_error(cmd, "--read-noise must be >= 0, got %g", o->read_noise);
    if (!isnan(o->gain) && o->gain < 0) return cli_usage_error(cmd, "--gain must be >= 0 (0: no photon noise), got %g", o->gain);
    if (block < 1 || block > (1L << 20)) return cli_usage_error(cmd, "--frames-per-read must be 1..%ld, got %ld", 1L << 20, block);
    if (!(o->g_smooth_lod >= 0)) return cli_usage_error(cmd, "--g-smooth must be >= 0, got %g", o->g_smooth_lod);
    o->block = (size_t)block;
    return 0;
}

static void print_summary(const swfs_estimate_run_options *o, const swfs_estimate_run_result *r, double seconds)
{
    const swfs_halo *h = r->halo;
    printf("estimate: %s\n", o->out);
    printf("  frames            %llu (%llu pixel-frames skipped as non-finite)\n", h->frames, h->skipped);
    printf("  noise model       read noise %.4g counts, gain %.4g e-/count\n", r->noise.read_noise, r->noise.gain);
    printf("  valid pixels      %zu of %zu (%.1f %%); radicand of g <= 0 in %zu, no speckle power in %zu\n",
           h->n_valid, h->npix, 100.0 * h->valid_fraction, h->n_bad_radicand, h->n_no_speckle);
    if (h->g_smooth > 0)
        printf("  scale factor g    regularized over %.3g pixels (GAIN; the paper's per-pixel g is GAIN_PIX), "
               "%zu pixels on the local-median fallback\n", h->g_smooth, h->n_g_fallback);
    else
        printf("  scale factor g    per pixel (eq:scale-factor); %zu invalid pixels use the local median of valid "
               "neighbours\n", h->n_g_fallback);
    if (isfinite(h->median_snr))
        printf("  median SNR        %.3g (eq:SNR, valid pixels)\n", h->median_snr);
    else
        printf("  median SNR        undefined: eq:SNR divides by the camera noise, and the noise model is zero "
               "(give --read-noise or --gain)\n");
    if (isfinite(r->circ_core)) printf("  circularity       mean |<psi^2>|/<|psi|^2> = %.3f inside 4 lambda/D\n", r->circ_core);
    if (h->resmean)
        printf("  AO residual mean  carried from the speckles (RESMEAN, %zux%zu): pupil takes it out of the NCP\n",
               h->resmean->nx, h->resmean->ny);
    printf("  time              %.2f s\n", seconds);
    if (swfs_team_active(o->team)) printf("  processes         %d (frames split evenly, accumulators merged)\n", o->team->size);
}

int swfs_cmd_estimate(int argc, char **argv)
{
    const char *cmd = "estimate";
    swfs_estimate_run_options o;
    swfs_estimate_run_options_default(&o);
    int prc = parse(argc, argv, &o);
    if (prc) return prc < 0 ? CLI_OK : prc;
    const double t0 = cli_now();
    if (cli_team_join(cmd, &o.team)) return CLI_FAIL;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_writer() ? cli_stage_progress : NULL;
    o.progress_ctx = "estimate:";
    swfs_estimate_run_result r;
    if (swfs_estimate_run(&o, &r)) return cli_writer() ? cli_error(cmd) : CLI_FAIL;
    if (!cli_writer()) return CLI_OK;
    if (r.g_smooth_assumed)
        fprintf(stderr, "specklewfs %s: note: %s has no PIXSCALE keyword; --g-smooth %g lambda/D taken as %g pixels (0.25 "
                "lambda/D per pixel)\n", cmd, o.speckles, o.g_smooth_lod, r.halo->g_smooth);
    print_summary(&o, &r, cli_now() - t0);
    const swfs_halo *h = r.halo;
    if (h->n_var_below_noise > h->npix / 50)
        fprintf(stderr, "specklewfs %s: warning: in %zu of %zu pixels the intensity variance is below the noise model alone "
                "(read noise %.4g counts, gain %.4g e-/count) by more than 3 sigma: the noise model looks too large, and "
                "g's radicand (eq:scale-factor) goes negative where the speckle signal is faint; check --read-noise / "
                "RDNOISE\n", cmd, h->n_var_below_noise, h->npix, r.noise.read_noise, r.noise.gain);
    if (isfinite(r.circ_core) && r.circ_core > 0.3)
        fprintf(stderr, "specklewfs %s: warning: the speckles are far from circular near the core (mean |<psi^2>|/<|psi|^2> "
                "= %.2f inside 4 lambda/D, eq:zeroSqMean); tip-tilt vibration left in the speckles or images is the usual "
                "cause: remove the mean slopes and re-centre the images\n", cmd, r.circ_core);
    swfs_halo_free(r.halo);
    return CLI_OK;
}

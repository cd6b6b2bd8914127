/* specklewfs estimate SCIENCE.fits SPECKLES.fits -o HALO.fits [--read-noise S] [--gain G] */
#include "cli.h"

#include "specklewfs/accum.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
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
    "                        default: the science header's GAIN, else no photon term\n"
    "  --g-smooth L          regularize the scale factor over a Gaussian neighbourhood of L lambda/D\n"
    "                        (default 2; 0 = the paper's per-pixel g, see docs/ARCHITECTURE.md)\n"
    "  --frames-per-read N   frames read per block (default 64)\n"
    "\n"
    "Non-finite science pixels are skipped for that frame and counted; the speckle mean over\n"
    "the data set is removed exactly (eq:zeroMean).\n";

int swfs_cmd_estimate(int argc, char **argv)
{
    const char *cmd = "estimate";
    const char *in_sci = NULL, *in_sp = NULL, *out = NULL;
    double read_noise = NAN, gain = NAN, g_smooth_lod = 2.0;
    long block = 64;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "-o")) { if (++i >= argc) return cli_usage_error(cmd, "-o needs a file name"); out = argv[i]; }
        else if (!strcmp(a, "--read-noise")) { if (cli_parse_double(cmd, a, i + 1 < argc ? argv[++i] : NULL, &read_noise)) return CLI_USAGE; }
        else if (!strcmp(a, "--gain")) { if (cli_parse_double(cmd, a, i + 1 < argc ? argv[++i] : NULL, &gain)) return CLI_USAGE; }
        else if (!strcmp(a, "--g-smooth")) { if (cli_parse_double(cmd, a, i + 1 < argc ? argv[++i] : NULL, &g_smooth_lod)) return CLI_USAGE; }
        else if (!strcmp(a, "--frames-per-read")) { if (cli_parse_long(cmd, a, i + 1 < argc ? argv[++i] : NULL, &block)) return CLI_USAGE; }
        else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (!in_sci) in_sci = a;
        else if (!in_sp) in_sp = a;
        else return cli_usage_error(cmd, "unexpected argument '%s'", a);
    }
    if (!in_sci || !in_sp) return cli_usage_error(cmd, "needs SCIENCE.fits and SPECKLES.fits");
    if (!out) return cli_usage_error(cmd, "needs -o HALO.fits");
    if (!isnan(read_noise) && read_noise < 0) return cli_usage_error(cmd, "--read-noise must be >= 0, got %g", read_noise);
    if (!isnan(gain) && gain <= 0) return cli_usage_error(cmd, "--gain must be > 0, got %g", gain);
    if (block < 1) return cli_usage_error(cmd, "--frames-per-read must be >= 1");
    if (!(g_smooth_lod >= 0)) return cli_usage_error(cmd, "--g-smooth must be >= 0, got %g", g_smooth_lod);

    double t0 = cli_now();
    swfs_fits_in *fs = NULL, *fp = NULL;
    swfs_accum *acc = NULL;
    swfs_halo *halo = NULL;
    double *ibuf = NULL;
    double complex *pbuf = NULL;
    int rc = CLI_FAIL;

    if (swfs_fits_in_open(&fs, in_sci, NULL) || swfs_fits_in_open(&fp, in_sp, NULL)) { cli_error(cmd); goto done; }
    const swfs_fits_shape *ss = swfs_fits_in_shape(fs), *sp = swfs_fits_in_shape(fp);
    if (ss->is_complex) {
        fprintf(stderr, "specklewfs %s: %s: science cube is complex; expected real intensities (x, y, frame)\n", cmd, in_sci);
        goto done;
    }
    if (!sp->is_complex) {
        fprintf(stderr, "specklewfs %s: %s: speckle cube is not complex; expected NAXIS1 = 2 with CTYPE1 = 'COMPLEX' "
                "(real, imaginary), then x, y, frame\n", cmd, in_sp);
        goto done;
    }
    if (ss->nx != sp->nx || ss->ny != sp->ny || ss->nz != sp->nz) {
        fprintf(stderr, "specklewfs %s: %s: cube is %zux%zux%zu but %s is %zux%zux%zu (they must match frame for frame)\n",
                cmd, in_sp, sp->nx, sp->ny, sp->nz, in_sci, ss->nx, ss->ny, ss->nz);
        goto done;
    }
    if (ss->nz < 2) {
        fprintf(stderr, "specklewfs %s: %s: only %zu frame; the statistics need at least 2\n", cmd, in_sci, ss->nz);
        goto done;
    }
    /* Noise model: flags win over the science header. */
    swfs_noise noise = {0.0, 0.0};
    {
        double v;
        int found;
        if (swfs_fits_in_key_double_opt(fs, "RDNOISE", &v, &found)) { cli_error(cmd); goto done; }
        if (found) noise.read_noise = v;
        if (swfs_fits_in_key_double_opt(fs, "GAIN", &v, &found)) { cli_error(cmd); goto done; }
        if (found) noise.gain = v;
    }
    if (!isnan(read_noise)) noise.read_noise = read_noise;
    if (!isnan(gain)) noise.gain = gain;
    if (!(noise.read_noise >= 0) || !(noise.gain >= 0)) {
        fprintf(stderr, "specklewfs %s: %s: noise model RDNOISE=%g GAIN=%g is invalid (need >= 0)\n", cmd, in_sci,
                noise.read_noise, noise.gain);
        goto done;
    }
    swfs_geom geom;
    if (swfs_fits_in_geom(fp, &geom)) { cli_error(cmd); goto done; }

    /* The g regularization is given in lambda/D; the library works in pixels. */
    swfs_estimate_options eopt = {0.0};
    if (g_smooth_lod > 0) {
        if (isfinite(geom.pixscale) && geom.pixscale > 0) {
            eopt.g_smooth = g_smooth_lod / geom.pixscale;
        } else {
            /* No sampling known: assume the paper's 0.25 lambda/D per pixel, and say so. */
            eopt.g_smooth = g_smooth_lod / 0.25;
            fprintf(stderr, "specklewfs %s: note: %s has no PIXSCALE keyword; --g-smooth %g lambda/D taken as %g "
                    "pixels (0.25 lambda/D per pixel)\n", cmd, in_sp, g_smooth_lod, eopt.g_smooth);
        }
    }
    const size_t nx = ss->nx, ny = ss->ny, nz = ss->nz, np = nx * ny;
    acc = swfs_accum_create(nx, ny);
    ibuf = malloc((size_t)block * np * sizeof *ibuf);
    pbuf = malloc((size_t)block * np * sizeof *pbuf);
    if (!acc || !ibuf || !pbuf) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    for (size_t k = 0; k < nz; k += (size_t)block) {
        size_t n = nz - k < (size_t)block ? nz - k : (size_t)block;
        if (swfs_fits_in_read_real(fs, k, n, ibuf) || swfs_fits_in_read_cplx(fp, k, n, pbuf)) { cli_error(cmd); goto done; }
        for (size_t j = 0; j < n; j++) {
            if (swfs_accum_add(acc, ibuf + j * np, pbuf + j * np)) {
                swfs_fail_context(SWFS_ERR_VALUE, "%s", in_sp);
                cli_error(cmd);
                goto done;
            }
        }
        cli_progress("estimate: frames", k + n, nz);
    }
    if (swfs_estimate(acc, &noise, &eopt, &halo)) {
        fprintf(stderr, "specklewfs %s: %s + %s: %s\n", cmd, in_sci, in_sp, swfs_last_error());
        goto done;
    }
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    char nl[256];
    snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count", noise.read_noise, noise.gain);
    const char *prov[] = {cl, nl};
    if (swfs_halo_write(halo, out, &geom, prov, 2)) { cli_error(cmd); goto done; }

    /* Assumption check (eq:zeroSqMean): the speckles should be circular near the core. */
    double circ_sum = 0.0;
    size_t circ_n = 0;
    const double pix = isfinite(geom.pixscale) ? geom.pixscale : NAN;
    for (size_t j = 0; j < ny && isfinite(pix); j++)
        for (size_t i = 0; i < nx; i++) {
            double dx = ((double)i - (double)(nx / 2)) * pix, dy = ((double)j - (double)(ny / 2)) * pix;
            double c = halo->circ->data[j * nx + i];
            if (dx * dx + dy * dy <= 16.0 && isfinite(c)) { circ_sum += c; circ_n++; }
        }
    double circ_core = circ_n ? circ_sum / (double)circ_n : NAN;

    printf("estimate: %s\n", out);
    printf("  frames            %llu (%llu pixel-frames skipped as non-finite)\n", halo->frames, halo->skipped);
    printf("  noise model       read noise %.4g counts, gain %.4g e-/count\n", noise.read_noise, noise.gain);
    printf("  valid pixels      %zu of %zu (%.1f %%); radicand of g <= 0 in %zu, no speckle power in %zu\n",
           halo->n_valid, halo->npix, 100.0 * halo->valid_fraction, halo->n_bad_radicand, halo->n_no_speckle);
    if (halo->g_smooth > 0)
        printf("  scale factor g    regularized over %.3g pixels (GAIN; the paper's per-pixel g is GAIN_PIX), "
               "%zu pixels on the local-median fallback\n", halo->g_smooth, halo->n_g_fallback);
    else
        printf("  scale factor g    per pixel (eq:scale-factor); %zu invalid pixels use the local median of valid "
               "neighbours\n", halo->n_g_fallback);
    if (isfinite(halo->median_snr))
        printf("  median SNR        %.3g (eq:SNR, valid pixels)\n", halo->median_snr);
    else
        printf("  median SNR        undefined: eq:SNR divides by the camera noise, and the noise model is zero "
               "(give --read-noise or --gain)\n");
    if (isfinite(circ_core)) printf("  circularity       mean |<psi^2>|/<|psi|^2> = %.3f inside 4 lambda/D\n", circ_core);
    printf("  time              %.2f s\n", cli_now() - t0);
    if (halo->n_var_below_noise > halo->npix / 50)
        fprintf(stderr, "specklewfs %s: warning: in %zu of %zu pixels the intensity variance is below the noise model alone "
                "(read noise %.4g counts, gain %.4g e-/count) by more than 3 sigma: the noise model looks too large, and "
                "g's radicand (eq:scale-factor) goes negative where the speckle signal is faint; check --read-noise / "
                "RDNOISE\n", cmd, halo->n_var_below_noise, halo->npix, noise.read_noise, noise.gain);
    if (isfinite(circ_core) && circ_core > 0.3)
        fprintf(stderr, "specklewfs %s: warning: the speckles are far from circular near the core (mean |<psi^2>|/<|psi|^2> "
                "= %.2f inside 4 lambda/D, eq:zeroSqMean); tip-tilt vibration left in the speckles or images is the usual "
                "cause: remove the mean slopes and re-centre the images\n", cmd, circ_core);
    rc = CLI_OK;
done:
    swfs_halo_free(halo);
    swfs_accum_free(acc);
    free(ibuf);
    free(pbuf);
    swfs_fits_in_close(fs);
    swfs_fits_in_close(fp);
    return rc;
}

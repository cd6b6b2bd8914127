/* specklewfs coherence SPECKLES_WFS.fits -o COH.fits [--exposure T] [--pixel X,Y] [--wind V]
 *                      [--bandwidth FRAC] [--radius R] [--diam D] [--nfit N] */
#include "cli.h"

#include "specklewfs/coherence.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs coherence SPECKLES_WFS.fits -o COH.fits [--exposure T] [--pixel X,Y]\n"
    "                            [--wind V] [--bandwidth FRAC] [--radius R] [--diam D] [--nfit N]\n"
    "       specklewfs coherence --wind V --diam D [--radius R] [--bandwidth FRAC]   (limits only)\n"
    "\n"
    "Speckle coherence diagnostics (Codona & Kenworthy 2013, Sec. 3.3 and 4.4): per pixel the\n"
    "mutual coherence function Gamma(tau) = <psi(t) psi*(t+tau)> (eq:MutualCoh) of a complex\n"
    "speckle cube at the WFS rate, at lags 0..20, 25..100 WFS frames, normalized by Gamma(0),\n"
    "and the maps derived from it.\n"
    "\n"
    "  SPECKLES_WFS.fits  complex cube (NAXIS1 = 2, CTYPE1 = 'COMPLEX', x, y, frame) at the WFS\n"
    "                     rate with FRAMEDT [s] between frames; optional CAMEXP [s] (science\n"
    "                     exposure) or FRATIO (WFS frames per camera frame) and the geometry keywords\n"
    "  -o COH.fits        MEAN_SP (Phi_sp), TAU0 [s] (|Gamma/Gamma0| first below e^-1/2; +Inf\n"
    "                     beyond the largest lag), TROT [s] (phase turns by pi/2, extrapolated\n"
    "                     from lags 1..NFIT), PHRATE [rad/s] (d arg Gamma/d tau; +k theta.v for\n"
    "                     frozen flow), SNR_FACT (eq:MCF-SNReffect, 1 = no loss, at --exposure or\n"
    "                     the header's exposure), MCF (complex, x, y, lag), LAGS [s] (NLAGS x 1)\n"
    "  --exposure T       science camera exposure [s] for SNR_FACT (default: CAMEXP or\n"
    "                     FRATIO*FRAMEDT from the header; none: no SNR_FACT)\n"
    "  --pixel X,Y        also print Gamma(tau)/Gamma(0) of pixel (X, Y) (0-based) as a table\n"
    "  --wind V           print the wind exposure limit (eq:ExpLimit-Wind) for V [m/s] at --radius\n"
    "  --bandwidth FRAC   print the bandwidth radius (lambda/dlambda) lambda/D for dlambda/lambda = FRAC\n"
    "  --radius R         radius [lambda/D] of the wind limit (default 6, the MMT WFS Nyquist radius)\n"
    "  --diam D           telescope diameter [m] (default: TELDIAM of the input)\n"
    "  --nfit N           WFS frames of the phase-rate fit (default 4, as in the paper)\n"
    "Pixels without speckle power (or with non-finite speckles) are NaN in the maps and counted.\n";

static void print_limits(double diam, double wind, double radius, double bw, const swfs_geom *g)
{
    if (wind > 0) {
        double t = swfs_exposure_limit_wind(radius, diam, wind);
        printf("  wind exposure limit    %.1f ms at %g lambda/D along a %g m/s wind, D = %g m (eq:ExpLimit-Wind;\n"
               "                         phase swing pi/2 at the exposure ends; %.1f frames/s)\n",
               1e3 * t, radius, wind, diam, 1 / t);
    }
    if (bw > 0) {
        double r = swfs_bandwidth_radius(bw);
        printf("  bandwidth radius       %.2f lambda/D for dlambda/lambda = %g (speckles blur radially into\n"
               "                         each other beyond it, Sec. 3.3)", r, bw);
        if (g && isfinite(g->wavelen) && isfinite(g->teldiam))
            printf("; %.3f arcsec at %.3g um", r * g->wavelen / g->teldiam * 180 / M_PI * 3600, g->wavelen * 1e6);
        printf("\n");
    }
}

int swfs_cmd_coherence(int argc, char **argv)
{
    const char *cmd = "coherence";
    const char *in = NULL, *out = NULL;
    double exposure = 0, wind = 0, bw = 0, radius = 6, diam = NAN;
    int exp_set = 0, exp_none = 0;
    long px = -1, py = -1, nfit = 4;
    int have_pixel = 0;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &out, "a file name", 0}, {"--wind", CLI_DOUBLE, &wind, NULL, 0},
        {"--bandwidth", CLI_DOUBLE, &bw, NULL, 0},  {"--radius", CLI_DOUBLE, &radius, NULL, 0},
        {"--diam", CLI_DOUBLE, &diam, NULL, 0},     {"--nfit", CLI_LONG, &nfit, NULL, 0},
    };
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        int bad = 0;
        if (cli_is_help(a)) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "--exposure") && i + 1 < argc && !strcmp(argv[i + 1], "none")) { exp_none = 1; i++; }
        else if (!strcmp(a, "--exposure")) { bad = cli_take_double(cmd, argc, argv, &i, &exposure); exp_set = 1; }
        else if (!strcmp(a, "--pixel")) { bad = cli_parse_xy(cmd, a, cli_next(argc, argv, &i), &px, &py); have_pixel = 1; }
        else if ((bad = cli_match(cmd, opts, CLI_NOPTS(opts), argc, argv, &i)) != 0) bad = bad < 0;
        else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (!in) in = a;
        else return cli_usage_error(cmd, "one speckle cube only (got '%s' and '%s')", in, a);
        if (bad) return CLI_USAGE;
    }
    if (exposure < 0 || (exposure == 0 && exp_set))
        return cli_usage_error(cmd, "--exposure must be positive seconds, got %g", exposure);
    if (wind < 0) return cli_usage_error(cmd, "--wind must be a speed >= 0 [m/s], got %g", wind);
    if (bw < 0 || bw >= 1) return cli_usage_error(cmd, "--bandwidth is a fraction dlambda/lambda in (0, 1), got %g", bw);
    if (!(radius > 0)) return cli_usage_error(cmd, "--radius must be > 0 lambda/D, got %g", radius);
    if (!isnan(diam) && !(diam > 0)) return cli_usage_error(cmd, "--diam must be > 0 m, got %g", diam);
    if (nfit < 1 || nfit > 1000) return cli_usage_error(cmd, "--nfit must be 1..1000 frames, got %ld", nfit);

    if (!in) {
        /* Limits only: the analytic numbers for a configured system. */
        if (!(wind > 0) && !(bw > 0)) return cli_usage_error(cmd, "needs a speckle cube (or --wind/--bandwidth for the limits)");
        if (wind > 0 && isnan(diam)) return cli_usage_error(cmd, "--wind without an input cube needs --diam D [m]");
        printf("specklewfs coherence: analytic limits\n");
        print_limits(diam, wind, radius, bw, NULL);
        return CLI_OK;
    }
    if (!out) return cli_usage_error(cmd, "needs -o COH.fits");
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "speckle cube", in);
    swfs_paths_output(paths, "-o", out);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;

    int rc = CLI_FAIL;
    swfs_cplx *cube = NULL;
    swfs_coherence *c = NULL;
    swfs_real *snr2 = NULL;
    double framedt = 0, hdr_exp = 0;
    swfs_geom g;
    double t0 = cli_now();
    if (swfs_coherence_read_input(in, &cube, &framedt, &g, &hdr_exp)) { cli_error(cmd); goto done; }
    if (have_pixel && (px < 0 || py < 0 || (size_t)px >= cube->nx || (size_t)py >= cube->ny)) {
        rc = cli_usage_error(cmd, "--pixel %ld,%ld is outside the %zux%zu image of %s", px, py, cube->nx, cube->ny, in);
        goto done;
    }
    if (isnan(diam)) diam = g.teldiam;

    swfs_coh_options opt;
    swfs_coh_options_default(&opt);
    opt.nfit = (int)nfit;
    if (exp_none) hdr_exp = 0; /* --exposure none: no SNR_FACT */
    opt.exposure = exposure > 0 ? exposure : hdr_exp;
    /* Keep enough lags for the header exposure too, when --exposure overrides it. */
    if (exposure > 0 && hdr_exp > 0) {
        long need = (long)ceil(hdr_exp / framedt - 1e-9);
        if (need <= (long)cube->nz - 1) opt.max_lag = need > 100 ? need : 100;
    }
    if (opt.exposure > 0 && exposure == 0 && opt.exposure / framedt > (double)(cube->nz - 1)) {
        fprintf(stderr, "specklewfs %s: note: the header exposure %g s is longer than the cube (%zu frames of %g s); "
                "no SNR_FACT\n", cmd, hdr_exp, cube->nz, framedt);
        opt.exposure = hdr_exp = 0;
    }
    if (swfs_coherence_compute(cube, framedt, &opt, &c)) { cli_error(cmd); goto done; }
    double tcomp = cli_now() - t0;

    size_t nprov;
    const char *const *prov = cli_provenance(argc, argv, &nprov);
    if (swfs_coherence_write(c, out, &g, prov, nprov)) { cli_error(cmd); goto done; }

    printf("specklewfs coherence: %s: %zu frames of %zux%zu, FRAMEDT %.4g ms; MCF by %s to lag %ld (%.1f ms), %.2f s\n",
           in, c->nframes, c->nx, c->ny, 1e3 * framedt, c->method == SWFS_COH_FFT ? "FFT" : "direct sums", c->max_lag,
           1e3 * (double)c->max_lag * framedt, tcomp);
    printf("  pixels                 %zu with speckle power; NaN: %zu without speckle power, %zu non-finite\n",
           c->n_valid, c->n_nopower, c->n_nonfinite);
    printf("  median tau0            %.2f ms (|Gamma/Gamma0| = e^-1/2; %zu pixels beyond %.1f ms count as +Inf)\n",
           1e3 * swfs_coh_median(c->tau0), c->n_tau0_beyond, 1e3 * (double)c->max_lag * framedt);
    printf("  median TROT            %.2f ms (phase turns by pi/2, from lags 1..%d)\n", 1e3 * swfs_coh_median(c->trot),
           c->nfit);
    if (c->snr_fact)
        printf("  median SNR factor      %.4f at exposure %.4g ms (%s; 1 = no loss)\n", swfs_coh_median(c->snr_fact),
               1e3 * c->exposure, exposure > 0 ? "--exposure" : "header");
    if (exposure > 0 && hdr_exp > 0) {
        snr2 = swfs_real_alloc(c->nx, c->ny, 1);
        if (!snr2 || swfs_coherence_snr_map(c, hdr_exp, snr2)) { cli_error(cmd); goto done; }
        printf("  median SNR factor      %.4f at the actual exposure %.4g ms (header)\n", swfs_coh_median(snr2),
               1e3 * hdr_exp);
    }
    if (!c->snr_fact && exp_none) printf("  SNR factor             none (--exposure none)\n");
    else if (!c->snr_fact) printf("  SNR factor             no exposure known (give --exposure T or CAMEXP/FRATIO in the header)\n");
    double v[2];
    if (c->n_valid > 2 && isfinite(g.pixscale) && isfinite(g.teldiam) && !swfs_coherence_fit_wind(c, &g, v))
        printf("  apparent wind          %.2f m/s toward %.1f deg from +x (frozen-flow fit PHRATE = k theta.v)\n",
               hypot(v[0], v[1]), atan2(v[1], v[0]) * 180 / M_PI);
    swfs_clear_error();
    if (wind > 0 && !isfinite(diam)) {
        fprintf(stderr, "specklewfs %s: %s: --wind needs the telescope diameter: no TELDIAM keyword, give --diam D\n",
                cmd, in);
        goto done;
    }
    print_limits(diam, wind, radius, bw, &g);
    printf("  wrote %s\n", out);

    if (have_pixel) {
        size_t p = (size_t)py * c->nx + (size_t)px;
        printf("\npixel (%ld, %ld): Phi_sp %.6g, tau0 %.3f ms, TROT %.3f ms, PHRATE %.4g rad/s", px, py,
               c->mean_sp->data[p], 1e3 * c->tau0->data[p], 1e3 * c->trot->data[p], c->phrate->data[p]);
        if (c->snr_fact) printf(", SNR factor %.4f", c->snr_fact->data[p]);
        printf("\n%8s %10s %12s %12s %10s %10s\n", "lag", "lag[ms]", "Re", "Im", "|G/G0|", "arg[deg]");
        for (size_t k = 0; k < c->nlags; k++) {
            double complex z = swfs_cplx_frame(c->mcf, k)[p];
            printf("%8ld %10.4f %12.6f %12.6f %10.6f %10.3f\n", c->lag_frames[k], 1e3 * c->lags->data[k], creal(z),
                   cimag(z), cabs(z), carg(z) * 180 / M_PI);
        }
    }
    rc = CLI_OK;
done:
    swfs_real_free(snr2);
    swfs_coherence_free(c);
    swfs_cplx_free(cube);
    return rc;
}

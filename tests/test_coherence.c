/* Speckle coherence diagnostics (include/specklewfs/coherence.h): known decorrelation,
 * frozen-flow phase rotation (eq:MCF-spinningPhase), the SNR factor (eq:MCF-SNReffect)
 * against down-sampled data, the analytic limits, invalid pixels and the file round trip. */
#include "testutil.h"

#include "specklewfs/coherence.h"
#include "specklewfs/fits.h"
#include "specklewfs/mft.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <fftw3.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int cmp_d(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double median(double *v, size_t n)
{
    qsort(v, n, sizeof *v, cmp_d);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* Per pixel p an AR(1) complex Gaussian process psi_{t+1} = rho_p psi_t + sqrt(1-|rho|^2) w_t
 * with rho_p = exp(-1/(2 tau0f)) exp(i omega_p): Gamma(k)/Gamma(0) = conj(rho_p)^k, so
 * |Gamma(tau0f)/Gamma(0)| = e^{-1/2} and arg Gamma(k) = -omega_p k. */
static swfs_cplx *ar1_cube(size_t nx, size_t ny, size_t nt, double tau0f, const double *omega, uint64_t seed)
{
    swfs_cplx *c = swfs_cplx_alloc(nx, ny, nt);
    assert_non_null(c);
    const size_t npix = nx * ny;
    double a = exp(-0.5 / tau0f), s = sqrt(1 - a * a);
    for (size_t p = 0; p < npix; p++) {
        swfs_rng r;
        swfs_rng_seed2(&r, seed, p);
        double complex rho = a * cexp(I * omega[p]);
        double complex x = swfs_rng_cnormal_value(&r);
        for (size_t t = 0; t < nt; t++) {
            c->data[t * npix + p] = x;
            x = rho * x + s * swfs_rng_cnormal_value(&r);
        }
    }
    return c;
}

static void test_defaults_and_limits(void **state)
{
    (void)state;
    long lags[SWFS_COH_DEFAULT_NLAGS];
    swfs_coh_default_lags(lags);
    assert_int_equal(lags[0], 0);
    assert_int_equal(lags[20], 20);
    assert_int_equal(lags[21], 25);
    assert_int_equal(lags[SWFS_COH_DEFAULT_NLAGS - 1], 100);
    /* The paper's number (Sec. 3.3): 6 lambda/D, D = 6.5 m, 10 m/s -> about 54 ms. */
    double t = swfs_exposure_limit_wind(6, 6.5, 10);
    assert_close(t, 6.5 / 120, 1e-15);
    assert_int_equal((long)lround(t * 1e3), 54);
    assert_true(isinf(swfs_exposure_limit_wind(0, 6.5, 10)));
    /* theta < (lambda/dlambda) lambda/D: 20 % bandwidth -> 5 lambda/D; 17 % ~ 6 lambda/D. */
    assert_close(swfs_bandwidth_radius(0.2), 5.0, 1e-12);
    assert_int_equal((long)lround(swfs_bandwidth_radius(0.17)), 6);
    /* SNR factor: a coherent speckle gives 1 at any exposure, integer or not; a white
     * one gives 1/M for M frames (the box average of M independent frames). */
    double complex one[12], white[12];
    for (int k = 0; k < 12; k++) { one[k] = 1; white[k] = k == 0; }
    assert_close(swfs_coh_snr_factor(one, 12, 1e-3, 7e-3), 1.0, 1e-12);
    assert_close(swfs_coh_snr_factor(one, 12, 1e-3, 6.5e-3), 1.0, 1e-12);
    assert_close(swfs_coh_snr_factor(one, 12, 1e-3, 0.3e-3), 1.0, 1e-12);
    assert_close(swfs_coh_snr_factor(white, 12, 1e-3, 8e-3), 1.0 / 8, 1e-12);
    assert_true(isnan(swfs_coh_snr_factor(one, 12, 1e-3, 14e-3))); /* needs lag 13 */
    assert_true(!isnan(swfs_coh_snr_factor(one, 12, 1e-3, 12e-3))); /* lag 12 has weight 0 */
}

/* Exponential decorrelation with a known rotation: tau0, PHRATE and TROT recovered; FFT
 * and direct sums agree. */
static void test_exponential_decorrelation(void **state)
{
    (void)state;
    const size_t nx = 8, ny = 6, nt = 4000, npix = nx * ny;
    const double tau0f = 10, dt = 2e-3;
    double omega[48];
    for (size_t p = 0; p < npix; p++) omega[p] = 0.01 + 0.004 * (double)p; /* rad/frame */
    swfs_cplx *cube = ar1_cube(nx, ny, nt, tau0f, omega, 11);
    swfs_coh_options opt;
    swfs_coh_options_default(&opt);
    opt.method = SWFS_COH_FFT;
    swfs_coherence *c = NULL, *d = NULL;
    assert_ok(swfs_coherence_compute(cube, dt, &opt, &c));
    opt.method = SWFS_COH_DIRECT;
    assert_ok(swfs_coherence_compute(cube, dt, &opt, &d));
    assert_int_equal(c->method, SWFS_COH_FFT);
    assert_int_equal(d->method, SWFS_COH_DIRECT);
    assert_int_equal(c->nlags, SWFS_COH_DEFAULT_NLAGS);
    assert_int_equal(c->n_valid, npix);
    double maxdiff = 0;
    for (size_t i = 0; i < swfs_cplx_size(c->mcf); i++) maxdiff = fmax(maxdiff, cabs(c->mcf->data[i] - d->mcf->data[i]));
    assert_true(maxdiff < 1e-10);

    double t0[48], rerr[48];
    double worst_rate = 0;
    for (size_t p = 0; p < npix; p++) {
        t0[p] = c->tau0->data[p] / dt;
        double expect = -omega[p] / dt;
        rerr[p] = c->phrate->data[p] / expect - 1;
        worst_rate = fmax(worst_rate, fabs(c->phrate->data[p] - expect) * dt);
        assert_close(c->trot->data[p], (M_PI / 2) / fabs(c->phrate->data[p]), 1e-12);
        assert_close(cabs(c->mcf->data[p]), 1.0, 1e-15);
        assert_close(c->lags->data[c->nlags - 1], 100 * dt, 1e-15);
    }
    double med_tau0 = median(t0, npix), med_rerr = median(rerr, npix);
    print_message("AR(1): median tau0 %.3f frames (true %.1f), range %.2f..%.2f; phase rate median rel. err %.4f, "
                  "worst abs err %.4f rad/frame\n", med_tau0, tau0f, t0[0], t0[npix - 1], med_rerr, worst_rate);
    assert_close(med_tau0, tau0f, 0.03 * tau0f);
    assert_true(t0[0] > 0.75 * tau0f && t0[npix - 1] < 1.25 * tau0f);
    assert_true(fabs(med_rerr) < 0.03);
    assert_true(worst_rate < 0.01);
    swfs_coherence_free(c);
    swfs_coherence_free(d);
    swfs_cplx_free(cube);
}

/* The SNR factor integral against direct averaging of down-sampled data: the camera box
 * average of M WFS frames keeps <|psi_cam|^2>/<|psi|^2> = S(M dt) of the coherent signal. */
static void test_snr_factor_downsampling(void **state)
{
    (void)state;
    const size_t nx = 4, ny = 4, nt = 24000, npix = nx * ny;
    const double dt = 1e-3, tau0f = 6;
    double omega[16];
    for (size_t p = 0; p < npix; p++) omega[p] = 0.05 * (double)p; /* up to 0.75 rad/frame */
    swfs_cplx *cube = ar1_cube(nx, ny, nt, tau0f, omega, 5);
    const size_t Ms[3] = {3, 8, 20};
    for (int im = 0; im < 3; im++) {
        const size_t M = Ms[im];
        swfs_coh_options opt;
        swfs_coh_options_default(&opt);
        opt.exposure = (double)M * dt;
        swfs_coherence *c = NULL;
        assert_ok(swfs_coherence_compute(cube, dt, &opt, &c));
        assert_non_null(c->snr_fact);
        double worst = 0, worst_th = 0;
        for (size_t p = 0; p < npix; p++) {
            double complex mean = 0;
            for (size_t t = 0; t < nt; t++) mean += cube->data[t * npix + p];
            mean /= (double)nt;
            double p1 = 0, pm = 0;
            size_t nb = nt / M;
            for (size_t b = 0; b < nb; b++) {
                double complex s = 0;
                for (size_t m = 0; m < M; m++) {
                    double complex z = cube->data[(b * M + m) * npix + p] - mean;
                    s += z;
                    p1 += creal(z) * creal(z) + cimag(z) * cimag(z);
                }
                s /= (double)M;
                pm += creal(s) * creal(s) + cimag(s) * cimag(s);
            }
            double direct = (pm / (double)nb) / (p1 / (double)(nb * M));
            /* Theory for the AR(1): (1/M)[1 + 2 sum_{k<M} (1 - k/M) Re rho^k]. */
            double th = 1;
            double a = exp(-0.5 / tau0f);
            for (size_t k = 1; k < M; k++) th += 2 * (1 - (double)k / (double)M) * pow(a, (double)k) * cos(omega[p] * (double)k);
            th /= (double)M;
            double s = c->snr_fact->data[p];
            worst = fmax(worst, fabs(s - direct));
            worst_th = fmax(worst_th, fabs(s - th));
        }
        print_message("SNR factor M=%zu: worst |integral - downsampled| %.4f, |integral - theory| %.4f\n", M, worst,
                      worst_th);
        assert_true(worst < 0.03);
        assert_true(worst_th < 0.03);
        /* Another exposure from the same MCF: needs no recompute, and too long is an error. */
        swfs_real *map = swfs_real_alloc(nx, ny, 1);
        assert_ok(swfs_coherence_snr_map(c, (double)M * dt, map));
        for (size_t p = 0; p < npix; p++) assert_close(map->data[p], c->snr_fact->data[p], 1e-15);
        assert_int_not_equal(swfs_coherence_snr_map(c, (double)(c->max_lag + 2) * dt, map), 0);
        swfs_real_free(map);
        swfs_coherence_free(c);
    }
    swfs_cplx_free(cube);
}

/* ---- frozen flow --------------------------------------------------------- */

/* A periodic random phase screen (M x M samples of dx), von Karman-like PSD
 * (f^2 + f0^2)^(-11/6), translated by v t exactly (Fourier shift), seen through a circular
 * pupil of N samples, propagated with the MFT; speckles = field minus its time mean. */
typedef struct flow {
    size_t npup, nf, nt;
    double diam, lambda, pixscale, dt, vx, vy;
    double rms;  /* target phase rms [rad] */
    double f0d;  /* f0 in cycles per D */
} flow;

static swfs_cplx *frozen_flow(const flow *fl, uint64_t seed)
{
    const size_t N = fl->npup, M = 2 * N, nf = fl->nf;
    const double dx = fl->diam / (double)N;
    fftw_complex *spec = fftw_malloc(M * M * sizeof *spec), *scr = fftw_malloc(M * M * sizeof *scr);
    double complex *coef = (double complex *)spec, *s = (double complex *)scr;
    fftw_plan plan = fftw_plan_dft_2d((int)M, (int)M, spec, scr, FFTW_BACKWARD, FFTW_ESTIMATE);
    double complex *c0 = malloc(M * M * sizeof *c0), *step = malloc(M * M * sizeof *step);
    double *fx = malloc(M * sizeof *fx);
    swfs_rng r;
    swfs_rng_seed(&r, seed);
    const double f0 = fl->f0d / fl->diam;
    for (size_t k = 0; k < M; k++) fx[k] = ((double)(k < M / 2 ? (long)k : (long)k - (long)M)) / ((double)M * dx);
    for (size_t j = 0; j < M; j++)
        for (size_t i = 0; i < M; i++) {
            double f2 = fx[i] * fx[i] + fx[j] * fx[j];
            c0[j * M + i] = (i || j) ? swfs_rng_cnormal_value(&r) * pow(f2 + f0 * f0, -11.0 / 12.0) : 0;
        }
    /* Normalize to the requested rms (real part of a circular field: half the power). */
    double pw = 0;
    for (size_t k = 0; k < M * M; k++) pw += creal(c0[k]) * creal(c0[k]) + cimag(c0[k]) * cimag(c0[k]);
    double scale = fl->rms / sqrt(0.5 * pw);
    for (size_t k = 0; k < M * M; k++) c0[k] *= scale;

    swfs_cplx *cube = swfs_cplx_alloc(nf, nf, fl->nt);
    double complex *pup = malloc(N * N * sizeof *pup);
    swfs_mft *mft = swfs_mft_create(N, nf, nf, fl->pixscale * dx / fl->diam, SWFS_MFT_DOUBLE);
    assert_non_null(mft);
    /* phi_t(x) = phi_0(x - v t): the coefficients turn by exp(-2 pi i f.v dt) per frame. */
    for (size_t j = 0; j < M; j++)
        for (size_t i = 0; i < M; i++) step[j * M + i] = cexp(-2 * M_PI * I * (fx[i] * fl->vx + fx[j] * fl->vy) * fl->dt);
    for (size_t t = 0; t < fl->nt; t++) {
        memcpy(coef, c0, M * M * sizeof *coef);
        fftw_execute(plan);
        for (size_t q = 0; q < M * M; q++) c0[q] *= step[q];
        for (size_t q = 0; q < N; q++)
            for (size_t p = 0; p < N; p++) {
                double x = ((double)p - 0.5 * (double)(N - 1)), y = ((double)q - 0.5 * (double)(N - 1));
                int in = x * x + y * y <= 0.25 * (double)N * (double)N;
                pup[q * N + p] = in ? cexp(I * creal(s[q * M + p])) : 0;
            }
        assert_ok(swfs_mft_forward(mft, pup, swfs_cplx_frame(cube, t)));
    }
    /* Speckles: the field minus its time mean (eq:zeroMean). */
    const size_t npix = nf * nf;
    for (size_t p = 0; p < npix; p++) {
        double complex m = 0;
        for (size_t t = 0; t < fl->nt; t++) m += cube->data[t * npix + p];
        m /= (double)fl->nt;
        for (size_t t = 0; t < fl->nt; t++) cube->data[t * npix + p] -= m;
    }
    swfs_mft_free(mft);
    free(pup);
    free(fx);
    free(c0);
    free(step);
    fftw_destroy_plan(plan);
    fftw_free(spec);
    fftw_free(scr);
    return cube;
}

static void test_frozen_flow(void **state)
{
    (void)state;
    const double ang = 30.0 * M_PI / 180.0, speed = 10.0;
    flow fl = {.npup = 48, .nf = 48, .nt = 4000, .diam = 6.5, .lambda = 3.8e-6, .pixscale = 0.25, .dt = 2e-3,
               .vx = speed * cos(ang), .vy = speed * sin(ang), .rms = 0.3, .f0d = 20};
    const double pmin = 2.0; /* [lambda/D] along the wind: rates large against the window term */
    swfs_cplx *cube = frozen_flow(&fl, 2026);
    swfs_coherence *c = NULL;
    assert_ok(swfs_coherence_compute(cube, fl.dt, NULL, &c));
    assert_int_equal(c->nfit, 4);
    assert_int_equal(c->n_valid, fl.nf * fl.nf);

    /* Per pixel: PHRATE = +k theta.v (our derivation; the paper's eq:MCF-spinningPhase has 2k). */
    const double k = 2 * M_PI / fl.lambda, lod = fl.lambda / fl.diam;
    const size_t nf = fl.nf, c0 = nf / 2;
    double *rel = malloc(nf * nf * sizeof *rel);
    size_t n = 0, nwithin = 0;
    for (size_t j = 0; j < nf; j++)
        for (size_t i = 0; i < nf; i++) {
            double tx = ((double)i - (double)c0) * fl.pixscale, ty = ((double)j - (double)c0) * fl.pixscale;
            double proj = (tx * fl.vx + ty * fl.vy) / speed; /* [lambda/D] along the wind */
            if (fabs(proj) < pmin || tx * tx + ty * ty > 5.5 * 5.5) continue;
            double expect = k * (tx * fl.vx + ty * fl.vy) * lod;
            rel[n] = c->phrate->data[j * nf + i] / expect - 1;
            nwithin += fabs(rel[n]) < 0.05;
            n++;
        }
    double mrel = median(rel, n);
    double p10 = rel[n / 10], p90 = rel[n - 1 - n / 10];
    print_message("frozen flow: %zu pixels |theta.v^| >= %.1f l/D: median rel. rate error %+.4f, 10-90%% %+.4f..%+.4f, "
                  "%.1f%% within 5%%\n", n, pmin, mrel, p10, p90, 100.0 * (double)nwithin / (double)n);
    /* The sign and factor of eq:MCF-spinningPhase: +k theta.v, not 2k (that would give -0.5). */
    assert_true(fabs(mrel) < 0.05);
    /* Per pixel within 5 %, except where the pupil-window term (random, ~v/D rad/s, see
     * docs/coherence.md) is not small against k theta.v over a 8 s series. */
    assert_true((double)nwithin > 0.85 * (double)n);

    /* The direction of fastest phase rotation is the wind. */
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = fl.lambda; g.teldiam = fl.diam; g.pixscale = fl.pixscale;
    double v[2];
    assert_ok(swfs_coherence_fit_wind(c, &g, v));
    double dang = atan2(v[1], v[0]) - ang;
    dang = atan2(sin(dang), cos(dang)) * 180 / M_PI;
    double sp = hypot(v[0], v[1]);
    print_message("frozen flow: fitted wind %.3f m/s at %.2f deg (true %.1f m/s at 30 deg): direction error %.2f deg, "
                  "speed error %+.2f%%\n", sp, atan2(v[1], v[0]) * 180 / M_PI, speed, dang, 100 * (sp / speed - 1));
    assert_true(fabs(dang) < 10);
    assert_true(fabs(sp / speed - 1) < 0.05);
    free(rel);
    swfs_coherence_free(c);
    swfs_cplx_free(cube);
}

/* Pixels with no speckle power or non-finite speckles are NaN and counted, not an error. */
static void test_invalid_pixels(void **state)
{
    (void)state;
    const size_t nx = 6, ny = 5, nt = 60, npix = nx * ny;
    double omega[30] = {0};
    swfs_cplx *cube = ar1_cube(nx, ny, nt, 5, omega, 3);
    const size_t pz = 3 * nx + 2, pn = 1 * nx + 4, pc = 0;
    for (size_t t = 0; t < nt; t++) {
        cube->data[t * npix + pz] = 0;
        cube->data[t * npix + pc] = 1.5 - 0.5 * I; /* constant: no power once the mean is removed */
    }
    cube->data[17 * npix + pn] = NAN;
    swfs_coh_options opt;
    swfs_coh_options_default(&opt);
    opt.exposure = 4e-3;
    swfs_coherence *c = NULL;
    assert_ok(swfs_coherence_compute(cube, 1e-3, &opt, &c));
    assert_int_equal(c->n_nopower, 2);
    assert_int_equal(c->n_nonfinite, 1);
    assert_int_equal(c->n_valid, npix - 3);
    assert_int_equal(c->nlags, 28); /* lags 0..20, 25, ..., 55 < 60 frames */
    assert_int_equal(c->lag_frames[c->nlags - 1], 55);
    const size_t bad[3] = {pz, pn, pc};
    for (int b = 0; b < 3; b++) {
        size_t p = bad[b];
        assert_true(isnan(c->tau0->data[p]) && isnan(c->trot->data[p]) && isnan(c->phrate->data[p]));
        assert_true(isnan(c->snr_fact->data[p]) && isnan(creal(c->mcf->data[p])));
    }
    assert_true(c->mean_sp->data[pz] == 0 && isnan(c->mean_sp->data[pn]));
    for (size_t p = 0; p < npix; p++)
        if (p != pz && p != pn && p != pc) assert_true(isfinite(c->snr_fact->data[p]) && c->mean_sp->data[p] > 0);
    swfs_coherence_free(c);
    swfs_cplx_free(cube);
}

static void test_bad_arguments(void **state)
{
    (void)state;
    double omega[4] = {0};
    swfs_cplx *cube = ar1_cube(2, 2, 50, 5, omega, 1);
    swfs_coherence *c = NULL;
    swfs_coh_options opt;
    swfs_coh_options_default(&opt);
    opt.exposure = 0.1; /* 100 frames of 1 ms, the cube has 50 */
    assert_int_equal(swfs_coherence_compute(cube, 1e-3, &opt, &c), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "50 frames"));
    assert_null(c);
    swfs_coh_options_default(&opt);
    long lags[3] = {1, 2, 3};
    opt.lags = lags;
    opt.nlags = 3;
    assert_int_equal(swfs_coherence_compute(cube, 1e-3, &opt, &c), SWFS_ERR_ARG);
    assert_int_equal(swfs_coherence_compute(cube, 0, NULL, &c), SWFS_ERR_VALUE);
    swfs_cplx *one = swfs_cplx_alloc(2, 2, 1);
    assert_int_equal(swfs_coherence_compute(one, 1e-3, NULL, &c), SWFS_ERR_SHAPE);
    swfs_cplx_free(one);
    swfs_cplx_free(cube);
}

/* COH.fits round trip and the input reader (FRAMEDT required, CAMEXP / FRATIO optional). */
static void test_files(void **state)
{
    (void)state;
    const size_t nx = 5, ny = 4, nt = 120;
    double omega[20];
    for (int p = 0; p < 20; p++) omega[p] = 0.02 * p;
    swfs_cplx *cube = ar1_cube(nx, ny, nt, 8, omega, 9);
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6; g.teldiam = 6.5; g.obscur = 0.1; g.pixscale = 0.25; g.pupdx = 0.05; g.pupn = 130;

    /* Input without FRAMEDT: a clear error naming the file and keyword. */
    const char *in = test_path("coh_in.fits");
    swfs_fits_out *o;
    assert_ok(swfs_fits_out_create(&o, in));
    assert_ok(swfs_fits_out_cplx(o, NULL, cube, -64));
    assert_ok(swfs_fits_out_geom(o, &g));
    assert_ok(swfs_fits_out_commit(o));
    swfs_cplx *rd = NULL;
    double dt = 0, expo = -1;
    swfs_geom g2;
    assert_int_equal(swfs_coherence_read_input(in, &rd, &dt, &g2, &expo), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "FRAMEDT"));
    assert_non_null(strstr(swfs_last_error(), "coh_in.fits"));
    assert_null(rd);
    /* With FRAMEDT and FRATIO. */
    assert_ok(swfs_fits_out_create(&o, in));
    assert_ok(swfs_fits_out_cplx(o, NULL, cube, -64));
    assert_ok(swfs_fits_out_geom(o, &g));
    assert_ok(swfs_fits_out_key_double(o, "FRAMEDT", 2e-3, "[s]"));
    assert_ok(swfs_fits_out_key_double(o, "FRATIO", 6.5, "WFS frames per camera frame"));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_coherence_read_input(in, &rd, &dt, &g2, &expo));
    assert_close(dt, 2e-3, 0);
    assert_close(expo, 13e-3, 1e-15);
    assert_close(g2.teldiam, 6.5, 0);
    assert_int_equal(rd->nz, nt);

    swfs_coh_options opt;
    swfs_coh_options_default(&opt);
    opt.exposure = expo;
    swfs_coherence *c = NULL;
    assert_ok(swfs_coherence_compute(rd, dt, &opt, &c));
    const char *out = test_path("coh_out.fits");
    const char *prov[1] = {"test_coherence"};
    assert_ok(swfs_coherence_write(c, out, &g2, prov, 1));
    swfs_cplx *mcf = NULL;
    swfs_real *lags = NULL, *tau0 = NULL, *snr = NULL;
    swfs_geom g3;
    assert_ok(swfs_fits_read_cplx(out, "MCF", &mcf, &g3));
    assert_ok(swfs_fits_read_real(out, "LAGS", &lags, NULL));
    assert_ok(swfs_fits_read_real(out, "TAU0", &tau0, NULL));
    assert_ok(swfs_fits_read_real(out, "SNR_FACT", &snr, NULL));
    assert_int_equal(mcf->nx, nx);
    assert_int_equal(mcf->ny, ny);
    assert_int_equal(mcf->nz, c->nlags);
    assert_int_equal(lags->nx, c->nlags);
    assert_int_equal(lags->ny, 1);
    assert_close(g3.pixscale, 0.25, 0);
    for (size_t i = 0; i < c->nlags; i++) assert_close(lags->data[i], (double)c->lag_frames[i] * dt, 0);
    for (size_t i = 0; i < swfs_cplx_size(mcf); i++) assert_close(cabs(mcf->data[i] - c->mcf->data[i]), 0, 1e-6);
    for (size_t p = 0; p < nx * ny; p++) {
        assert_close(tau0->data[p], c->tau0->data[p], 1e-6 * c->tau0->data[p]);
        assert_close(snr->data[p], c->snr_fact->data[p], 1e-6);
    }
    swfs_fits_in *f;
    assert_ok(swfs_fits_in_open(&f, out, "TAU0"));
    double v;
    assert_ok(swfs_fits_in_key_double(f, "FRAMEDT", &v));
    assert_close(v, dt, 0);
    assert_ok(swfs_fits_in_key_double(f, "EXPOSURE", &v));
    assert_close(v, 13e-3, 1e-15);
    swfs_fits_in_close(f);
    swfs_real_free(lags);
    swfs_real_free(tau0);
    swfs_real_free(snr);
    swfs_cplx_free(mcf);
    swfs_coherence_free(c);
    swfs_cplx_free(rd);
    swfs_cplx_free(cube);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_defaults_and_limits),
        cmocka_unit_test(test_exponential_decorrelation),
        cmocka_unit_test(test_snr_factor_downsampling),
        cmocka_unit_test(test_frozen_flow),
        cmocka_unit_test(test_invalid_pixels),
        cmocka_unit_test(test_bad_arguments),
        cmocka_unit_test(test_files),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

/* The modulated pyramid wavefront sensor (pyramid.h): its geometry is the Shack-Hartmann's, a
 * flat wavefront gives no signal, a small tilt a signal of the Shack-Hartmann's sign that is
 * linear in it, a large residual lowers its response (the optical gain), the modulation
 * points' default against twice as many, the signals equal to the model written out directly
 * (whole masks, whole 2-D transforms in double precision) to single precision's rounding,
 * photon noise of the expected size, the push-pull interaction matrix predicting small
 * signals, and bad parameters refused. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/source.h"
#include "specklewfs/pyramid.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

enum { NPUP = 66, NSUB = 12 };
static const double DIAM = 6.5, LAM = 0.85e-6;

/* A random wavefront of rms `rms` [m] on the grid: a sum of cosines of spatial frequencies
 * k0 .. k1 cycles per D with a Kolmogorov-like amplitude. */
static void random_wavefront(double *z, size_t n, double dx, double rms, const double *mask, unsigned seed, double k0,
                             double k1)
{
    swfs_rng rng;
    swfs_rng_seed(&rng, seed);
    enum { NC = 40 };
    double kx[NC], ky[NC], amp[NC], ph[NC];
    for (size_t m = 0; m < NC; m++) {
        const double k = (k0 + (k1 - k0) * swfs_rng_uniform(&rng)) * 2 * M_PI / DIAM, t = 2 * M_PI * swfs_rng_uniform(&rng);
        kx[m] = k * cos(t);
        ky[m] = k * sin(t);
        amp[m] = pow(k * DIAM / (2 * M_PI), -11.0 / 6.0);
        ph[m] = 2 * M_PI * swfs_rng_uniform(&rng);
    }
    double s2 = 0, s = 0, c = 0;
    for (size_t q = 0; q < n; q++)
        for (size_t p = 0; p < n; p++) {
            const double x = ((double)p - 0.5 * (double)(n - 1)) * dx, y = ((double)q - 0.5 * (double)(n - 1)) * dx;
            double v = 0;
            for (size_t m = 0; m < NC; m++) v += amp[m] * cos(kx[m] * x + ky[m] * y + ph[m]);
            z[q * n + p] = v;
            if (mask[q * n + p] > 0) { s += v; s2 += v * v; c++; }
        }
    const double sd = sqrt(s2 / c - (s / c) * (s / c));
    for (size_t g = 0; g < n * n; g++) z[g] = (z[g] - s / c) * rms / sd;
}

static double dot(const double *a, const double *b, size_t n)
{
    double s = 0;
    for (size_t i = 0; i < n; i++) s += a[i] * b[i];
    return s;
}

static void test_geometry_and_flat(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1);
    swfs_pyramid *p = NULL;
    assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0));
    swfs_shwfs *sh = NULL;
    assert_ok(swfs_shwfs_create(&sh, NSUB, DIAM, mask, NPUP, dx, 0.5));
    /* the Shack-Hartmann's subapertures and layout; N a multiple of 4 from 2 npup + 8 */
    assert_int_equal(p->nslopes, sh->nslopes);
    assert_int_equal(p->nvalid, sh->nvalid);
    assert_memory_equal(p->valid, sh->valid, NSUB * NSUB);
    assert_int_equal(p->nfft % 4, 0);
    assert_true(p->nfft >= 2 * NPUP + 8 && p->nfft < 2 * NPUP + 40);
    assert_true(p->sampling >= 2.0);
    assert_int_equal(p->nmod, 40); /* 3 lambda/D: 18.8 lambda/D of circle, two points per lambda/D */
    assert_int_equal(swfs_pyramid_nmod_default(0), 1);
    assert_int_equal(swfs_pyramid_nmod_default(0.1), 4);
    /* a flat wavefront: no signal (the reference), unused subapertures 0 */
    double *z = calloc(NPUP * NPUP, sizeof *z), s[2 * NSUB * NSUB];
    swfs_pyramid_measure(p, z, 0, NULL, s);
    for (size_t i = 0; i < p->nslopes; i++) assert_true(fabs(s[i]) < 1e-6);
    /* a piston neither */
    for (size_t g = 0; g < NPUP * NPUP; g++) z[g] = 0.3 * LAM;
    swfs_pyramid_measure(p, z, 0, NULL, s);
    for (size_t i = 0; i < p->nslopes; i++) assert_true(fabs(s[i]) < 1e-4);
    free(z); free(mask);
    swfs_shwfs_free(sh);
    swfs_pyramid_free(p);
}

/* A tilt of 0.05 lambda/D (well inside the modulation): sx > 0 as the Shack-Hartmann's slope,
 * sy about 0, twice the tilt twice the signal. */
static void test_tilt_sign_and_linearity(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1), *z = malloc(NPUP * NPUP * sizeof *z);
    swfs_pyramid *p = NULL;
    assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0));
    const size_t n2 = NSUB * NSUB;
    double s1[2 * NSUB * NSUB], s2[2 * NSUB * NSUB];
    for (size_t axis = 0; axis < 2; axis++) {
        const double tilt = 0.05 * LAM / DIAM; /* dz/dx [m/m] */
        for (int k = 1; k <= 2; k++) {
            for (size_t q = 0; q < NPUP; q++)
                for (size_t i = 0; i < NPUP; i++) {
                    const double x = ((double)i - 0.5 * (NPUP - 1)) * dx, y = ((double)q - 0.5 * (NPUP - 1)) * dx;
                    z[q * NPUP + i] = k * tilt * (axis ? y : x);
                }
            swfs_pyramid_measure(p, z, 0, NULL, k == 1 ? s1 : s2);
        }
        double on = 0, off = 0, on2 = 0;
        for (size_t a = 0; a < n2; a++)
            if (p->valid[a]) {
                on += s1[axis * n2 + a];
                off += s1[(1 - axis) * n2 + a];
                on2 += s2[axis * n2 + a];
            }
        on /= (double)p->nvalid;
        off /= (double)p->nvalid;
        on2 /= (double)p->nvalid;
        print_message("pyramid: tilt 0.05 lambda/D along %c: mean signal %.4g (%.4g across), twice the tilt %.4g\n",
                      axis ? 'y' : 'x', on, off, on2);
        assert_true(on > 0);
        assert_true(fabs(off) < 0.01 * on);
        assert_close(on2, 2 * on, 0.02 * on);
    }
    free(z); free(mask);
    swfs_pyramid_free(p);
}

/* The response to a small low-order probe about a residual beyond the subapertures' band
 * (a closed loop's fitting error) is lower than about a flat wavefront (the optical gain a
 * closed loop sees), and more so the larger the residual: measured 0.93, 0.76, 0.57, 0.42
 * at 0.05, 0.1, 0.15, 0.2 wave rms. */
static void test_optical_gain(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1);
    const size_t ng = NPUP * NPUP;
    double *probe = malloc(ng * sizeof *probe), *res = malloc(ng * sizeof *res), *z = malloc(ng * sizeof *z);
    swfs_pyramid *p = NULL;
    assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0));
    random_wavefront(probe, NPUP, dx, 0.005 * LAM, mask, 5, 0.3, 5);
    double sp[2 * NSUB * NSUB], sm[2 * NSUB * NSUB], d0[2 * NSUB * NSUB], d1[2 * NSUB * NSUB];
    const double rmss[3] = {0.0, 0.1, 0.2}; /* residual rms [waves] */
    double gain[3];
    for (int c = 0; c < 3; c++) {
        random_wavefront(res, NPUP, dx, rmss[c] * LAM, mask, 9, 6, 30);
        for (size_t g = 0; g < ng; g++) z[g] = res[g] + probe[g];
        swfs_pyramid_measure(p, z, 0, NULL, sp);
        for (size_t g = 0; g < ng; g++) z[g] = res[g] - probe[g];
        swfs_pyramid_measure(p, z, 0, NULL, sm);
        double *d = c ? d1 : d0;
        for (size_t i = 0; i < p->nslopes; i++) d[i] = 0.5 * (sp[i] - sm[i]);
        gain[c] = c ? dot(d1, d0, p->nslopes) / dot(d0, d0, p->nslopes) : 1.0;
        print_message("pyramid: residual %.2f waves rms: response to the probe %.3f of the flat wavefront's\n", rmss[c],
                      gain[c]);
    }
    assert_true(gain[1] < 0.9 && gain[1] > 0.6);
    assert_true(gain[2] < gain[1] - 0.2);
    free(probe); free(res); free(z); free(mask);
    swfs_pyramid_free(p);
}

/* The default modulation points against twice as many on a residual of 0.1 wave rms: the
 * signals agree to 3 % of their rms (measured 1.4 % at 3 lambda/D, 2.3 % at 5; half as many
 * points: 9.6 % off at 3). */
static void test_modulation_points(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1), *z = malloc(NPUP * NPUP * sizeof *z);
    random_wavefront(z, NPUP, dx, 0.1 * LAM, mask, 3, 0.3, 8);
    const double mods[2] = {3.0, 5.0};
    for (int c = 0; c < 2; c++) {
        swfs_pyramid *a = NULL, *b = NULL;
        assert_ok(swfs_pyramid_create(&a, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, mods[c], 0));
        assert_ok(swfs_pyramid_create(&b, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, mods[c], 2 * a->nmod));
        double sa[2 * NSUB * NSUB], sb[2 * NSUB * NSUB], e = 0, r = 0;
        swfs_pyramid_measure(a, z, 0, NULL, sa);
        swfs_pyramid_measure(b, z, 0, NULL, sb);
        for (size_t i = 0; i < a->nslopes; i++) { e += (sa[i] - sb[i]) * (sa[i] - sb[i]); r += sb[i] * sb[i]; }
        print_message("pyramid: modulation %.0f lambda/D, %zu points against %zu: %.2f %% of the signals' rms\n",
                      mods[c], a->nmod, b->nmod, 100 * sqrt(e / r));
        assert_true(sqrt(e / r) < 0.03);
        swfs_pyramid_free(a);
        swfs_pyramid_free(b);
    }
    free(z); free(mask);
}

/* The model of pyramid.h written out directly, in double precision: the padded field's 2-D
 * transform, per modulation point (angle 2 pi (m + 1/2) / nmod) the whole mask
 * exp(i pi/2 (|u + dx| + |v + dy|)) and a whole 2-D inverse transform, the intensities
 * summed over the N x N grid, the four images binned by the subapertures' centres, the
 * signals normalized by the mean total, less a flat wavefront's. signals: 2 nsub^2. */
static void direct_signals(const swfs_pyramid *p, const double *mask, const double *z, double *signals)
{
    const size_t N = p->nfft, n = p->npup, NN = N * N, nsub = p->nsub, n2 = nsub * nsub;
    const size_t off = (N - n) / 2, a = N / 4, lo = off - a, hi = off + a;
    const size_t at[4][2] = {{lo, lo}, {hi, lo}, {hi, hi}, {lo, hi}}; /* A, B, C, D: column, row */
    fftw_complex *e = fftw_alloc_complex(NN), *eh = fftw_alloc_complex(NN), *w = fftw_alloc_complex(NN);
    double *in = calloc(NN, sizeof *in), *cnt = calloc(4 * n2, sizeof *cnt), *ref = calloc(2 * n2, sizeof *ref);
    assert_non_null(e); assert_non_null(eh); assert_non_null(w); assert_non_null(in); assert_non_null(cnt);
    assert_non_null(ref);
    fftw_plan fw = fftw_plan_dft_2d((int)N, (int)N, e, eh, FFTW_FORWARD, FFTW_ESTIMATE);
    fftw_plan bw = fftw_plan_dft_2d((int)N, (int)N, w, w, FFTW_BACKWARD, FFTW_ESTIMATE);
    const double r = p->mod * p->sampling, c0 = 0.5 * (double)(n - 1);
    for (int pass = 0; pass < 2; pass++) { /* the flat wavefront, then z */
        memset(e, 0, NN * sizeof *e);
        memset(in, 0, NN * sizeof *in);
        for (size_t q = 0; q < n; q++)
            for (size_t i = 0; i < n; i++)
                if (mask[q * n + i] > 0) {
                    const double ph = pass ? 2 * M_PI / p->wavelen * z[q * n + i] : 0.0;
                    e[(off + q) * N + off + i] = mask[q * n + i] * cexp(I * ph);
                }
        fftw_execute(fw);
        for (size_t m = 0; m < p->nmod; m++) {
            const double th = 2 * M_PI * ((double)m + 0.5) / (double)p->nmod;
            const double dx = p->mod > 0 ? r * cos(th) : 0.0, dy = p->mod > 0 ? r * sin(th) : 0.0;
            for (size_t v = 0; v < N; v++)
                for (size_t u = 0; u < N; u++) {
                    const double fu = (double)(u < N / 2 ? (long)u : (long)u - (long)N);
                    const double fv = (double)(v < N / 2 ? (long)v : (long)v - (long)N);
                    w[v * N + u] = eh[v * N + u] * cexp(I * 0.5 * M_PI * (fabs(fu + dx) + fabs(fv + dy)));
                }
            fftw_execute(bw);
            for (size_t k = 0; k < NN; k++) in[k] += creal(w[k]) * creal(w[k]) + cimag(w[k]) * cimag(w[k]);
        }
        memset(cnt, 0, 4 * n2 * sizeof *cnt);
        for (size_t q = 0; q < n; q++)
            for (size_t i = 0; i < n; i++) {
                const double x = ((double)i - c0) * p->pupdx, y = ((double)q - c0) * p->pupdx;
                const double ux = (x + 0.5 * p->diam) / p->diam * (double)nsub;
                const double uy = (y + 0.5 * p->diam) / p->diam * (double)nsub;
                if (!(ux >= 0 && ux < (double)nsub && uy >= 0 && uy < (double)nsub)) continue;
                const size_t s = (size_t)floor(uy) * nsub + (size_t)floor(ux);
                if (!p->valid[s]) continue;
                for (int j = 0; j < 4; j++) cnt[(size_t)j * n2 + s] += in[(at[j][1] + q) * N + at[j][0] + i];
            }
        double tot = 0;
        for (size_t k = 0; k < 4 * n2; k++) tot += cnt[k];
        const double nrm = (double)p->nvalid / tot;
        const double *A = cnt, *B = A + n2, *C = B + n2, *D = C + n2;
        for (size_t k = 0; k < n2; k++) {
            const double sx = p->valid[k] ? (A[k] + D[k] - B[k] - C[k]) * nrm : 0.0;
            const double sy = p->valid[k] ? (A[k] + B[k] - C[k] - D[k]) * nrm : 0.0;
            if (!pass) { ref[k] = sx; ref[n2 + k] = sy; }
            else { signals[k] = sx - ref[k]; signals[n2 + k] = sy - ref[n2 + k]; }
        }
    }
    fftw_destroy_plan(fw);
    fftw_destroy_plan(bw);
    fftw_free(e); fftw_free(eh); fftw_free(w);
    free(in); free(cnt); free(ref);
}

/* The sensor's transforms (single precision, the rows' transforms shared by the points of one
 * row factor, the columns and sums only on the images) give the direct model's signals: with
 * the rule's 40 points (all paired), with 5 (the middle one its own mirror image) and without
 * modulation, on a residual of 0.1 wave rms. */
static void test_matches_direct_model(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1), *z = malloc(NPUP * NPUP * sizeof *z);
    assert_non_null(mask); assert_non_null(z);
    random_wavefront(z, NPUP, dx, 0.1 * LAM, mask, 5, 0.3, 12);
    const struct { double mod; size_t nmod; } c[3] = {{3.0, 0}, {3.0, 5}, {0.0, 0}};
    for (int k = 0; k < 3; k++) {
        swfs_pyramid *p = NULL;
        assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, c[k].mod, c[k].nmod));
        double s[2 * NSUB * NSUB], t[2 * NSUB * NSUB], e = 0, r = 0;
        swfs_pyramid_measure(p, z, 0, NULL, s);
        direct_signals(p, mask, z, t);
        for (size_t i = 0; i < p->nslopes; i++) { e += (s[i] - t[i]) * (s[i] - t[i]); r += t[i] * t[i]; }
        print_message("pyramid: %.0f lambda/D, %zu points: the sensor's signals %.2g of the direct model's rms from it\n",
                      c[k].mod, p->nmod, sqrt(e / r));
        assert_true(r > 0 && sqrt(e / r) < 1e-4);
        swfs_pyramid_free(p);
    }
    free(z); free(mask);
}

/* Photon noise: with N photons per subaperture the signals scatter by about 1/sqrt(N)
 * (each is a difference of the four images' counts over their mean total). */
static void test_photon_noise(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1), *z = calloc(NPUP * NPUP, sizeof *z);
    swfs_pyramid *p = NULL;
    assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0));
    swfs_rng rng;
    swfs_rng_seed(&rng, 4);
    const double photons = 1000;
    double s[2 * NSUB * NSUB], v = 0;
    size_t n = 0;
    for (int t = 0; t < 30; t++) {
        swfs_pyramid_measure(p, z, photons, &rng, s);
        for (size_t i = 0; i < p->nslopes; i++)
            if (p->valid[i % (NSUB * NSUB)]) { v += s[i] * s[i]; n++; }
    }
    const double sd = sqrt(v / (double)n);
    print_message("pyramid: %g photons per subaperture: signal noise %.4f rms (1/sqrt(N) = %.4f)\n", photons, sd,
                  1 / sqrt(photons));
    assert_close(sd, 1 / sqrt(photons), 0.15 / sqrt(photons));
    free(z); free(mask);
    swfs_pyramid_free(p);
}

/* The push-pull interaction matrix of a hexapolar DM predicts the signals of a small command
 * vector to a per cent. */
static void test_interaction(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1);
    double *xy = NULL;
    size_t nact = 0, outside = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, DIAM / 12.0, 0.5 * DIAM / 12.0, &xy, &nact));
    swfs_sparse *T = NULL;
    assert_ok(swfs_interp_ct_grid(xy, nact, NPUP, dx, mask, &T, &outside));
    swfs_pyramid *p = NULL;
    assert_ok(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0));
    double *D = NULL;
    assert_ok(swfs_pyramid_interaction(p, T, LAM / 100, &D));
    swfs_rng rng;
    swfs_rng_seed(&rng, 8);
    double *cmd = malloc(nact * sizeof *cmd), *z = malloc(NPUP * NPUP * sizeof *z);
    double s[2 * NSUB * NSUB], pred[2 * NSUB * NSUB], e = 0, r = 0;
    for (size_t a = 0; a < nact; a++) cmd[a] = 0.005 * LAM * swfs_rng_normal(&rng);
    swfs_sparse_apply(T, cmd, z);
    swfs_pyramid_measure(p, z, 0, NULL, s);
    for (size_t i = 0; i < p->nslopes; i++) {
        pred[i] = dot(D + i * nact, cmd, nact);
        e += (pred[i] - s[i]) * (pred[i] - s[i]);
        r += s[i] * s[i];
    }
    print_message("pyramid: %zu actuators, D predicts the signals of a small command to %.2f %%\n", nact,
                  100 * sqrt(e / r));
    assert_true(r > 0 && sqrt(e / r) < 0.01);
    /* refused: a DM interpolation on another grid */
    swfs_sparse *T2 = NULL;
    assert_ok(swfs_interp_ct_grid(xy, nact, NPUP - 2, dx, NULL, &T2, &outside));
    double *D2 = NULL;
    assert_int_equal(swfs_pyramid_interaction(p, T2, LAM / 100, &D2), SWFS_ERR_SHAPE);
    swfs_sparse_free(T2);
    free(cmd); free(z); free(D); free(xy); free(mask);
    swfs_sparse_free(T);
    swfs_pyramid_free(p);
}

/* swfs_telemetry_check_sh: telemetry that names a pyramid is kept from the Shack-Hartmann
 * model; none, or a Shack-Hartmann's name in any spelling, passes. */
static void test_check_sh(void **state)
{
    (void)state;
    const char *types[5] = {NULL, "SH", "Shack-Hartmann", "PYRAMID", "curvature"};
    const int want[5] = {SWFS_OK, SWFS_OK, SWFS_OK, SWFS_ERR_FORMAT, SWFS_ERR_FORMAT};
    double v[8] = {0};
    const swfs_real a = {4, 2, 1, v};
    for (int k = 0; k < 5; k++) {
        const char *path = test_path("pyr_check_sh.fits");
        swfs_fits_out *o = NULL;
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_real(o, NULL, &a, -32));
        if (types[k]) assert_ok(swfs_fits_out_key_string(o, "WFSTYPE", types[k], NULL));
        assert_ok(swfs_fits_out_commit(o));
        assert_int_equal(swfs_telemetry_check_sh(path, "the model"), want[k]);
        if (want[k]) assert_non_null(strstr(swfs_last_error(), "not a Shack-Hartmann's slopes, which the model models"));
    }
}

static void test_refused(void **state)
{
    (void)state;
    const double dx = DIAM / 64.0;
    double *mask = test_annulus(NPUP, dx, DIAM, 0.1);
    swfs_pyramid *p = NULL;
    assert_int_equal(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, 0.0, 3.0, 0), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "sensing wavelength"));
    assert_int_equal(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, -1.0, 0), SWFS_ERR_ARG);
    assert_int_equal(swfs_pyramid_create(&p, NSUB, DIAM, mask, NPUP, dx, NULL, LAM, 40.0, 0), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "beyond a quarter of the focal window"));
    assert_int_equal(swfs_pyramid_create(&p, 48, DIAM, mask, NPUP, dx, NULL, LAM, 3.0, 0), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "pyramid"));
    assert_null(p);
    free(mask);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_geometry_and_flat),  cmocka_unit_test(test_tilt_sign_and_linearity),
        cmocka_unit_test(test_optical_gain),       cmocka_unit_test(test_modulation_points),
        cmocka_unit_test(test_matches_direct_model),
        cmocka_unit_test(test_photon_noise),       cmocka_unit_test(test_interaction),
        cmocka_unit_test(test_check_sh),           cmocka_unit_test(test_refused),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

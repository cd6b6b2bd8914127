/* The modulated pyramid wavefront sensor (pyramid.h): its geometry is the Shack-Hartmann's, a
 * flat wavefront gives no signal, a small tilt a signal of the Shack-Hartmann's sign that is
 * linear in it, a large residual lowers its response (the optical gain), the modulation
 * points' default against twice as many, photon noise of the expected size, the push-pull
 * interaction matrix predicting small signals, and bad parameters refused. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/source.h"
#include "specklewfs/pyramid.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

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
        cmocka_unit_test(test_photon_noise),       cmocka_unit_test(test_interaction),
        cmocka_unit_test(test_check_sh),           cmocka_unit_test(test_refused),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

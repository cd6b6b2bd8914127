/* The MAP (Wiener) reconstructor learned from the telemetry (swfs_recon_map, wfs.h) on the
 * MMT-like geometry (217 hexapolar actuators, 12 x 12 Shack-Hartmann): smooth random
 * actuator patterns seen through D = S T with white slope noise. The slope noise comes
 * back from the slopes outside D's column space; the MAP reconstructor recovers the
 * patterns with less error than the truncated SVD at any of the cuts tried, and its error
 * changes smoothly with a wrong noise level (no cliff).
 * Measured (seed 42): MAP 38.7 nm, SVD 44.5 nm at best (rcond 5e-2), 192 nm at 0.2. */
#include "recon_fixture.h"

#define NTRAIN 1500
#define NTEST 200
#define NWAVE 24

/* A smooth random pattern at the actuators: NWAVE cosines with |f| up to 0.6 cycles/m
 * (the actuator pitch 0.45 m samples up to 1.1), amplitudes ~ 1/|f| [m]. */
static void pattern(const setup *s, swfs_rng *r, double *z)
{
    memset(z, 0, s->nact * sizeof *z);
    for (int w = 0; w < NWAVE; w++) {
        double f = 0.08 + 0.52 * swfs_rng_uniform(r), th = 2 * M_PI * swfs_rng_uniform(r);
        double ph = 2 * M_PI * swfs_rng_uniform(r), amp = 2e-8 / f * swfs_rng_normal(r);
        for (size_t a = 0; a < s->nact; a++)
            z[a] += amp * cos(2 * M_PI * f * (cos(th) * s->xy[2 * a] + sin(th) * s->xy[2 * a + 1]) + ph);
    }
}

static void make_data(const setup *s, swfs_rng *r, size_t n, double sigma, double *z, double *sl)
{
    for (size_t t = 0; t < n; t++) {
        pattern(s, r, z + t * s->nact);
        slopes_of(s, r, z + t * s->nact, sigma, sl + t * s->nslopes);
    }
}

static void test_map_beats_svd(void **state)
{
    (void)state;
    setup s;
    setup_init(&s);

    /* Slope noise: 1/4 of the slopes' rms, enough to make the SVD's noise gain matter. */
    const double sigma = 5e-8;
    double *z = malloc(NTRAIN * s.nact * sizeof *z), *sl = malloc(NTRAIN * s.nslopes * sizeof *sl);
    double *zt = malloc(NTEST * s.nact * sizeof *zt), *st = malloc(NTEST * s.nslopes * sizeof *st);
    swfs_rng r;
    swfs_rng_seed(&r, 42);
    make_data(&s, &r, NTRAIN, sigma, z, sl);
    make_data(&s, &r, NTEST, sigma, zt, st);
    const double srms = slopes_rms(&s, sl, NTRAIN);

    /* The slope noise from the slopes outside D's column space (the patterns lie in it). */
    double nv = 0;
    assert_ok(swfs_slopes_noise_var(s.D, s.nslopes, s.nact, sl, NTRAIN, &nv));
    print_message("slopes rms %.3g rad, noise %.3g rad (true %.3g)\n", srms, sqrt(nv), sigma);
    assert_true(fabs(sqrt(nv) / sigma - 1) < 0.05);

    swfs_recon *map = NULL;
    assert_ok(swfs_recon_map(s.D, s.nslopes, s.nact, sl, NTRAIN, 0, &map));
    assert_true(fabs(sqrt(map->noise_var) / sigma - 1) < 0.05);
    const double emap = test_err(&s, map, zt, st, NTEST), ezero = zero_err(&s, zt, st, NTEST);
    print_message("MAP: %zu modes, %.1f effective, error %.3g nm (signal %.3g nm)\n", map->nmodes, map->dof, emap * 1e9,
                  ezero * 1e9);
    assert_true(emap < 0.35 * ezero);
    const double ebest_svd = best_svd_err(&s, zt, st, NTEST);
    assert_true(emap < 0.9 * ebest_svd);
    /* A noise level off by 2x either way degrades smoothly (measured 1.4x at half the noise),
     * where the SVD's error jumps 4x between rcond 0.1 and 0.2: no cliff. */
    const double fac[] = {0.25, 4};
    for (size_t i = 0; i < 2; i++) {
        swfs_recon *w = NULL;
        assert_ok(swfs_recon_map(s.D, s.nslopes, s.nact, sl, NTRAIN, fac[i] * sigma * sigma, &w));
        double e = test_err(&s, w, zt, st, NTEST);
        print_message("MAP with noise x %.2g: error %.3g nm\n", sqrt(fac[i]), e * 1e9);
        assert_true(e < 1.5 * emap);
        swfs_recon_free(w);
    }
    /* Bad input: too few frames, non-finite slopes. */
    swfs_recon *bad = NULL;
    assert_int_not_equal(swfs_recon_map(s.D, s.nslopes, s.nact, sl, 3, 0, &bad), 0);
    assert_null(bad);
    sl[5] = NAN;
    assert_int_not_equal(swfs_recon_map(s.D, s.nslopes, s.nact, sl, NTRAIN, 0, &bad), 0);
    assert_null(bad);

    swfs_recon_free(map);
    free(z); free(sl); free(zt); free(st);
    setup_free(&s);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_map_beats_svd),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

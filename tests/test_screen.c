/* Von Karman phase screens: the theoretical structure function, and seeded screens whose
 * measured structure function matches it within 10 % from r0/4 to D = 6.5 m. */
#include "testutil.h"

#include "specklewfs/array.h"
#include "specklewfs/rng.h"
#include "specklewfs/screen.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

static void test_theory(void **state)
{
    (void)state;
    const double r0 = 0.15;
    /* Kolmogorov limit: 6.8839 (r/r0)^{5/3}. */
    for (double r = 0.01; r < 20; r *= 3)
        assert_close(swfs_vonkarman_structure(r, r0, INFINITY) / (6.8839 * pow(r / r0, 5.0 / 3.0)), 1.0, 2e-4);
    /* r << L0: von Karman = Kolmogorov (1 - 1.485 (r/L0)^{1/3}); r >> L0: 2 sigma^2 = 0.17253 (L0/r0)^{5/3}. */
    for (double r = 0.001; r <= 0.01; r *= 10)
        assert_close(swfs_vonkarman_structure(r, r0, 30) / swfs_vonkarman_structure(r, r0, INFINITY),
                     1.0 - 1.485 * cbrt(r / 30), 0.002);
    assert_close(swfs_vonkarman_structure(3000, r0, 30) / (0.17253 * pow(30 / r0, 5.0 / 3.0)), 1.0, 0.01);
    /* Finite L0 lowers D at D-scale separations (the paper's 6.5 m pupil, L0 = 30 m). */
    const double ratio = swfs_vonkarman_structure(6.5, r0, 30) / swfs_vonkarman_structure(6.5, r0, INFINITY);
    assert_true(ratio > 0.1 && ratio < 0.4); /* ~0.19: L0 matters a lot at D scales */
    /* PSD: Kolmogorov constant. */
    assert_close(swfs_vonkarman_psd(1.0, 1.0, INFINITY), 0.022896, 2e-6);
}

/* Mean over positions of (z(x + lag) - z(x))^2 along x and y, in rad^2 at 500 nm. */
static double measured_D(const double *z, size_t n, size_t lag)
{
    const double k = 2 * M_PI / SWFS_SCREEN_LAMBDA_REF;
    double s = 0;
    size_t cnt = 0;
    for (size_t q = 0; q + lag < n; q += 2)
        for (size_t p = 0; p + lag < n; p += 2) {
            const double a = z[q * n + p];
            const double dxl = z[q * n + p + lag] - a, dyl = z[(q + lag) * n + p] - a;
            s += dxl * dxl + dyl * dyl;
            cnt += 2;
        }
    return k * k * s / (double)cnt;
}

static void test_structure_function(void **state)
{
    (void)state;
    /* 1024 samples at r0/4 = 3.75 cm: a 38 m screen, with subharmonics for the power below
     * 1/38 m that D(6.5 m) needs at L0 = 30 m. */
    swfs_screen_params p = {.n = 1024, .dx = 0.0375, .r0 = 0.15, .L0 = 30.0, .subharmonics = 1};
    const size_t lags[] = {1, 2, 4, 8, 16, 32, 64, 128, 173}; /* r0/4 ... 6.49 m */
    const size_t nl = sizeof lags / sizeof lags[0], npairs = 5;
    double sum[9] = {0};
    double *a = swfs_malloc(p.n * p.n * sizeof *a), *b = swfs_malloc(p.n * p.n * sizeof *b);
    swfs_screen_gen *g = swfs_screen_gen_create(&p);
    assert_non_null(g);
    swfs_rng rng;
    swfs_rng_seed(&rng, 2013);
    for (size_t k = 0; k < npairs; k++) {
        assert_ok(swfs_screen_gen_draw(g, &rng));
        assert_ok(swfs_screen_gen_finish(g, a, b));
        for (size_t l = 0; l < nl; l++) sum[l] += measured_D(a, p.n, lags[l]) + measured_D(b, p.n, lags[l]);
    }
    for (size_t l = 0; l < nl; l++) {
        const double r = (double)lags[l] * p.dx, dm = sum[l] / (2.0 * (double)npairs);
        const double dt = swfs_vonkarman_structure(r, p.r0, p.L0);
        print_message("r = %6.3f m: D measured %10.3f theory %10.3f ratio %.3f\n", r, dm, dt, dm / dt);
        if (!(fabs(dm / dt - 1) < 0.10)) fail_msg("structure function at r = %.3f m off by %.1f %%", r, 100 * (dm / dt - 1));
    }
    swfs_screen_gen_free(g);
    swfs_free(a);
    swfs_free(b);
}

/* The two screens of one transform are independent: their second differences along x
 * (dominated by the many high-frequency modes) are uncorrelated. And the result does not depend on the thread count. */
static void test_pair_independent_and_thread_invariant(void **state)
{
    (void)state;
    swfs_screen_params p = {.n = 256, .dx = 0.04, .r0 = 0.15, .L0 = 30.0, .subharmonics = 1};
    const size_t nn = p.n * p.n;
    double *a = swfs_malloc(nn * sizeof *a), *b = swfs_malloc(nn * sizeof *b);
    double *c = swfs_malloc(nn * sizeof *c), *d = swfs_malloc(nn * sizeof *d);
    swfs_rng r1, r2;
    swfs_rng_seed(&r1, 5);
    swfs_rng_seed(&r2, 5);
    swfs_screen_gen *g1 = swfs_screen_gen_create(&p), *g2 = swfs_screen_gen_create(&p);
    swfs_screen_gen_set_threads(g1, 1);
    swfs_screen_gen_set_threads(g2, 3);
    assert_ok(swfs_screen_gen_draw(g1, &r1));
    assert_ok(swfs_screen_gen_finish(g1, a, b));
    assert_ok(swfs_screen_gen_draw(g2, &r2));
    assert_ok(swfs_screen_gen_finish(g2, c, d));
    assert_memory_equal(a, c, nn * sizeof *a);
    assert_memory_equal(b, d, nn * sizeof *b);
    double sab = 0, saa = 0, sbb = 0;
    for (size_t q = 0; q < p.n; q++)
        for (size_t i = 1; i + 1 < p.n; i++) {
            const double *pa = a + q * p.n + i, *pb = b + q * p.n + i;
            const double ga = pa[1] - 2 * pa[0] + pa[-1], gb = pb[1] - 2 * pb[0] + pb[-1];
            sab += ga * gb;
            saa += ga * ga;
            sbb += gb * gb;
        }
    print_message("second-difference correlation of the pair: %.4f\n", sab / sqrt(saa * sbb));
    assert_true(fabs(sab) / sqrt(saa * sbb) < 0.02);
    /* The one-shot function draws the same screens from the same seed. */
    swfs_rng_seed(&r1, 5);
    assert_ok(swfs_screen_vonkarman(&p, &r1, c, NULL));
    assert_memory_equal(a, c, nn * sizeof *a);
    /* Bad parameters. */
    swfs_screen_params bad = p;
    bad.r0 = 0;
    assert_int_not_equal(swfs_screen_vonkarman(&bad, &r1, c, NULL), 0);
    swfs_screen_gen_free(g1);
    swfs_screen_gen_free(g2);
    swfs_free(a);
    swfs_free(b);
    swfs_free(c);
    swfs_free(d);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_theory),
        cmocka_unit_test(test_structure_function),
        cmocka_unit_test(test_pair_independent_and_thread_invariant),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

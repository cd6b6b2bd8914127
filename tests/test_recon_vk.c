/* The MAP reconstructor with a von Karman spatial prior (swfs_recon_vk, wfs.h) on the
 * MMT-like geometry (217 hexapolar actuators, 12 x 12 Shack-Hartmann): actuator patterns
 * drawn from the von Karman covariance (VK_L0 = 10 m) seen through D = S T with white slope
 * noise. The vk reconstructor (its scale learned from the slopes, the noise estimated)
 * recovers them with less error than the truncated SVD at the best of the cuts tried.
 * Also: swfs_vk_covariance's normalization and its Kolmogorov r^(5/3) law for r << VK_L0. */
#include "recon_fixture.h"

#include <lapacke.h>

#define NTRAIN 600
#define NTEST 200
#define VK_L0 10.0

/* z = amp L n (n white): von Karman distributed; slopes D z + noise on the valid slopes. */
static void make_data(const setup *s, swfs_rng *r, size_t n, double amp, double sigma, double *z, double *sl)
{
    double *w = malloc(s->nact * sizeof *w);
    for (size_t t = 0; t < n; t++) {
        double *zz = z + t * s->nact;
        for (size_t a = 0; a < s->nact; a++) w[a] = swfs_rng_normal(r);
        for (size_t a = 0; a < s->nact; a++) {
            double v = 0;
            for (size_t b = 0; b <= a; b++) v += s->L[a * s->nact + b] * w[b];
            zz[a] = amp * v;
        }
        slopes_of(s, r, zz, sigma, sl + t * s->nslopes);
    }
    free(w);
}

static void cholesky(double *A, size_t n)
{
    for (size_t j = 0; j < n; j++) {
        double d = A[j * n + j];
        for (size_t k = 0; k < j; k++) d -= A[j * n + k] * A[j * n + k];
        assert_true(d > 0);
        A[j * n + j] = sqrt(d);
        for (size_t i = j + 1; i < n; i++) {
            double v = A[i * n + j];
            for (size_t k = 0; k < j; k++) v -= A[i * n + k] * A[j * n + k];
            A[i * n + j] = v / A[j * n + j];
        }
        for (size_t k = j + 1; k < n; k++) A[j * n + k] = 0;
    }
}

static void test_vk_covariance(void **state)
{
    (void)state;
    /* Three actuators on a line at 0, r, 2r with r << VK_L0: 1 - C(r) ~ r^(5/3). */
    const double r = 0.05, xy[6] = {0, 0, r, 0, 2 * r, 0};
    double C[9];
    assert_ok(swfs_vk_covariance(xy, 3, 1000, C));
    for (int i = 0; i < 3; i++) assert_true(C[i * 3 + i] == 1);
    assert_true(C[1] == C[3] && C[2] == C[6]);
    assert_true(C[1] < 1 && C[2] < C[1] && C[2] > 0.99);
    double ratio = (1 - C[2]) / (1 - C[1]);
    print_message("(1 - C(2r)) / (1 - C(r)) = %.4f (Kolmogorov 2^(5/3) = %.4f)\n", ratio, pow(2, 5.0 / 3));
    assert_true(fabs(ratio / pow(2, 5.0 / 3) - 1) < 0.02);
    /* Far beyond VK_L0 the covariance vanishes; at r = VK_L0 / (2 pi), x = 1: 1 K_5/6(1) / f(0). */
    const double xy2[4] = {0, 0, 50, 0};
    assert_ok(swfs_vk_covariance(xy2, 2, 1, C));
    assert_true(fabs(C[1]) < 1e-20);
    assert_int_not_equal(swfs_vk_covariance(xy2, 2, 0, C), 0);
}

/* The MMT-like geometry with L, the Cholesky factor of the von Karman covariance (VK_L0). */
static void setup_vk(setup *s)
{
    setup_init(s);
    s->L = malloc(s->nact * s->nact * sizeof *s->L);
    assert_ok(swfs_vk_covariance(s->xy, s->nact, VK_L0, s->L));
    for (size_t a = 0; a < s->nact; a++) s->L[a * s->nact + a] += 1e-9;
    cholesky(s->L, s->nact);
}

static void test_vk_beats_svd(void **state)
{
    (void)state;
    setup s;
    setup_vk(&s);

    /* 100 nm rms per actuator; the slope noise 1/3 of the slopes' tip-tilt-free rms. */
    const double amp = 1e-7, sigma = 4e-8;
    double *z = malloc(NTRAIN * s.nact * sizeof *z), *sl = malloc(NTRAIN * s.nslopes * sizeof *sl);
    double *zt = malloc(NTEST * s.nact * sizeof *zt), *st = malloc(NTEST * s.nslopes * sizeof *st);
    swfs_rng r;
    swfs_rng_seed(&r, 7);
    make_data(&s, &r, NTRAIN, amp, sigma, z, sl);
    make_data(&s, &r, NTEST, amp, sigma, zt, st);
    const double srms = slopes_rms(&s, sl, NTRAIN);

    swfs_recon *vk = NULL;
    assert_ok(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, VK_L0, sl, NTRAIN, 0, &vk));
    print_message("slopes rms %.3g rad, noise %.3g rad (true %.3g)\n", srms, sqrt(vk->noise_var), sigma);
    assert_true(fabs(sqrt(vk->noise_var) / sigma - 1) < 0.05);
    const double evk = test_err(&s, vk, zt, st, NTEST), ezero = zero_err(&s, zt, st, NTEST);
    print_message("vk: %.1f effective modes, error %.3g nm (signal %.3g nm)\n", vk->dof, evk * 1e9, ezero * 1e9);
    const double ebest_svd = best_svd_err(&s, zt, st, NTEST);
    swfs_recon *map = NULL;
    assert_ok(swfs_recon_map(s.D, s.nslopes, s.nact, sl, NTRAIN, 0, &map));
    double emap = test_err(&s, map, zt, st, NTEST);
    print_message("MAP (per-mode prior): error %.3g nm\n", emap * 1e9);
    assert_true(evk < 0.5 * ezero);
    assert_true(evk < 0.9 * ebest_svd);
    assert_true(evk < emap);
    /* A wrong outer scale (x 0.5, x 2) costs little. */
    const double l0s[] = {0.5 * VK_L0, 2 * VK_L0};
    for (size_t i = 0; i < 2; i++) {
        swfs_recon *w = NULL;
        assert_ok(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, l0s[i], sl, NTRAIN, 0, &w));
        double e = test_err(&s, w, zt, st, NTEST);
        print_message("vk with L0 %.3g m: error %.3g nm\n", l0s[i], e * 1e9);
        assert_true(e < 1.2 * evk);
        swfs_recon_free(w);
    }
    /* Bad input: too few frames, non-finite slopes, outer scale 0. */
    swfs_recon *bad = NULL;
    assert_int_not_equal(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, VK_L0, sl, 3, 0, &bad), 0);
    assert_null(bad);
    assert_int_not_equal(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, NAN, sl, NTRAIN, 0, &bad), 0);
    assert_null(bad);
    sl[5] = NAN;
    assert_int_not_equal(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, VK_L0, sl, NTRAIN, 0, &bad), 0);
    assert_null(bad);

    swfs_recon_free(vk);
    swfs_recon_free(map);
    free(z); free(sl); free(zt); free(st);
    setup_free(&s);
}

/* A loop that corrects nearly everything its WFS sees: a weak residual in D's column space
 * and a stronger component outside it (what the DM cannot make, aliased into the slopes).
 * The noise estimated from the slopes outside the column space then exceeds the slopes
 * inside it, which used to stop the reconstructor ("nothing to reconstruct"); it now takes
 * the noise from the slopes' likelihood under the prior and still reconstructs the residual. */
static void test_vk_aliasing_beyond_column_space(void **state)
{
    (void)state;
    setup s;
    setup_vk(&s);
    const size_t m = s.nslopes, n = s.nact, k = m < n ? m : n;
    /* U: D's left singular vectors of the non-zero singular values */
    double *A = malloc(m * n * sizeof *A), *U = malloc(m * k * sizeof *U), *sv = malloc(k * sizeof *sv);
    double *VT = malloc(k * n * sizeof *VT), *sup = malloc(k * sizeof *sup);
    memcpy(A, s.D, m * n * sizeof *A);
    assert_int_equal(LAPACKE_dgesvd(LAPACK_ROW_MAJOR, 'S', 'S', (lapack_int)m, (lapack_int)n, A, (lapack_int)n, sv, U,
                                    (lapack_int)k, VT, (lapack_int)n, sup), 0);
    size_t rank = 0;
    while (rank < k && sv[rank] > 1e-10 * sv[0]) rank++;
    const size_t nall = NTRAIN + NTEST;
    double *z = malloc(nall * n * sizeof *z), *sl = malloc(nall * m * sizeof *sl), *q = malloc(m * sizeof *q);
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    make_data(&s, &r, nall, 2e-8, 1e-9, z, sl);
    const double srms = slopes_rms(&s, sl, NTRAIN);
    for (size_t t = 0; t < nall; t++) {
        for (size_t i = 0; i < m; i++) q[i] = s.wfs->valid[i % (m / 2)] ? 1.5 * srms * swfs_rng_normal(&r) : 0;
        for (size_t j = 0; j < rank; j++) { /* q -= U_j (U_j . q) */
            double d = 0;
            for (size_t i = 0; i < m; i++) d += U[i * k + j] * q[i];
            for (size_t i = 0; i < m; i++) q[i] -= d * U[i * k + j];
        }
        for (size_t i = 0; i < m; i++) sl[t * m + i] += q[i];
    }
    swfs_recon *vk = NULL;
    assert_ok(swfs_recon_vk(s.D, m, n, s.xy, VK_L0, sl, NTRAIN, 0, &vk));
    const double *zt = z + NTRAIN * n, *st = sl + NTRAIN * m;
    const double evk = test_err(&s, vk, zt, st, NTEST), ezero = zero_err(&s, zt, st, NTEST);
    print_message("aliasing 1.5x the slopes outside D's column space (%zu of %zu slopes in it): noise %.3g rad, vk error "
                  "%.3g nm of %.3g nm\n", rank, m, sqrt(vk->noise_var), evk * 1e9, ezero * 1e9);
    assert_true(evk < 0.5 * ezero);
    swfs_recon_free(vk);
    free(A); free(U); free(sv); free(VT); free(sup); free(z); free(sl); free(q);
    setup_free(&s);
}

/* swfs_recon_tilt_as_mean_slopes: equal x and y slopes (gx, gy) on the valid subapertures
 * reconstruct exactly the plane gx x + gy y at the actuators, nothing else; slopes with zero
 * mean reconstruct as the projected W does; applying it twice changes nothing. */
static void test_tilt_as_mean_slopes(void **state)
{
    (void)state;
    setup s;
    setup_init(&s);
    swfs_recon *w = NULL;
    assert_ok(swfs_recon_svd(s.D, s.nslopes, s.nact, 5e-2, 0, &w));
    assert_ok(swfs_recon_tilt_as_mean_slopes(w, s.wfs->valid, s.xy));
    const size_t m = s.nslopes, n = s.nact, nsa = m / 2;
    double *sl = calloc(m, sizeof *sl), *z = malloc(n * sizeof *z), *W1 = malloc(n * m * sizeof *W1);
    const double gx = 3e-7, gy = -1.2e-7;
    for (size_t i = 0; i < nsa; i++)
        if (s.wfs->valid[i]) { sl[i] = gx; sl[nsa + i] = gy; }
    swfs_recon_apply(w, sl, z);
    double worst = 0, scale = 0;
    for (size_t a = 0; a < n; a++) {
        const double plane = gx * s.xy[2 * a] + gy * s.xy[2 * a + 1];
        worst = fmax(worst, fabs(z[a] - plane));
        scale = fmax(scale, fabs(plane));
    }
    print_message("mean slopes as a plane: worst %.2g of %.2g m\n", worst, scale);
    assert_true(worst <= 1e-12 * scale);
    memcpy(W1, w->W, n * m * sizeof *W1);
    assert_ok(swfs_recon_tilt_as_mean_slopes(w, s.wfs->valid, s.xy));
    double d = 0, wmax = 0;
    for (size_t k = 0; k < n * m; k++) {
        d = fmax(d, fabs(w->W[k] - W1[k]));
        wmax = fmax(wmax, fabs(W1[k]));
    }
    print_message("applied twice: changes by %.2g of the largest element\n", d / wmax);
    assert_true(d <= 1e-12 * wmax);
    swfs_recon_free(w);
    free(sl); free(z); free(W1);
    setup_free(&s);
}

/* The prior fitted to the slopes by maximum likelihood (swfs_vk_fit_slopes): patterns drawn
 * with outer scales of 3 m and 10 m; the fit must find the outer scale, the prior's scale and
 * the noise, and its reconstructor must do as well as the one given the true outer scale. */
static void test_vk_fit_recovers_prior(void **state)
{
    (void)state;
    const double l0s[2] = {3.0, 10.0};
    for (int q = 0; q < 2; q++) {
        setup s;
        setup_init(&s);
        s.L = malloc(s.nact * s.nact * sizeof *s.L);
        assert_ok(swfs_vk_covariance(s.xy, s.nact, l0s[q], s.L));
        for (size_t a = 0; a < s.nact; a++) s.L[a * s.nact + a] += 1e-9;
        cholesky(s.L, s.nact);
        const double amp = 1e-7, sigma = 4e-8;
        double *z = malloc(NTRAIN * 2 * s.nact * sizeof *z), *sl = malloc(NTRAIN * 2 * s.nslopes * sizeof *sl);
        double *zt = malloc(NTEST * s.nact * sizeof *zt), *st = malloc(NTEST * s.nslopes * sizeof *st);
        swfs_rng r;
        swfs_rng_seed(&r, 11 + (uint64_t)q);
        make_data(&s, &r, NTRAIN * 2, amp, sigma, z, sl);
        make_data(&s, &r, NTEST, amp, sigma, zt, st);
        swfs_vk_fit f;
        assert_ok(swfs_vk_fit_slopes(s.D, s.nslopes, s.nact, s.xy, sl, NTRAIN * 2, &f));
        swfs_recon *ml = NULL, *truth = NULL;
        assert_ok(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, 0, sl, NTRAIN * 2, 0, &ml));
        assert_ok(swfs_recon_vk(s.D, s.nslopes, s.nact, s.xy, l0s[q], sl, NTRAIN * 2, 0, &truth));
        const double eml = test_err(&s, ml, zt, st, NTEST), etrue = test_err(&s, truth, zt, st, NTEST);
        print_message("true L0 %.3g m: fitted L0 %.3g m, prior scale %.3g m^2 (true %.3g), noise %.3g rad (true %.3g); "
                      "error %.3g nm (true L0: %.3g nm)\n",
                      l0s[q], f.L0, f.scale, amp * amp, sqrt(f.noise_var), sigma, eml * 1e9, etrue * 1e9);
        assert_true(f.L0 > l0s[q] / 1.5 && f.L0 < l0s[q] * 1.5);
        assert_true(fabs(f.scale / (amp * amp) - 1) < 0.3);
        assert_true(fabs(sqrt(f.noise_var) / sigma - 1) < 0.05);
        assert_true(ml->l0 == f.L0 && ml->prior_scale == f.scale);
        assert_true(eml < 1.03 * etrue);
        swfs_recon_free(ml);
        swfs_recon_free(truth);
        free(z); free(sl); free(zt); free(st);
        setup_free(&s);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_vk_covariance),
        cmocka_unit_test(test_vk_beats_svd),
        cmocka_unit_test(test_vk_aliasing_beyond_column_space),
        cmocka_unit_test(test_tilt_as_mean_slopes),
        cmocka_unit_test(test_vk_fit_recovers_prior),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

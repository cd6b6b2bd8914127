/* The estimator on per-pixel synthetic data with known Psi and g (paper Sec. 2.2-2.4). */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/estimate.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

static int cmp_d(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

#define NX 6
#define NY 5
#define NP (NX * NY)

/* Known truth per pixel: Psi_p, g_p, speckle rms s_p. */
static void truth(size_t p, double complex *psi0, double *g, double *s)
{
    double a = 0.3 + 0.1 * (double)(p % 7);
    *psi0 = a * cexp(I * (0.37 * (double)p - 2.0));
    *g = 0.8 + 0.05 * (double)(p % 5);
    *s = 0.5 + 0.02 * (double)(p % 11);
}

/* Feed n frames of I = |Psi + g psi|^2 + noise into acc. */
static void feed(swfs_accum *acc, size_t n, double read_noise, uint64_t seed)
{
    swfs_rng r;
    swfs_rng_seed(&r, seed);
    double sci[NP];
    double complex psi[NP];
    for (size_t k = 0; k < n; k++) {
        for (size_t p = 0; p < NP; p++) {
            double complex psi0;
            double g, s;
            truth(p, &psi0, &g, &s);
            psi[p] = s * swfs_rng_cnormal_value(&r);
            double complex tot = psi0 + g * psi[p];
            sci[p] = creal(tot) * creal(tot) + cimag(tot) * cimag(tot) + read_noise * swfs_rng_normal(&r);
        }
        assert_ok(swfs_accum_add(acc, sci, psi));
    }
}

static double halo_rms_error(const swfs_halo *h, double *g_err)
{
    double e2 = 0.0, ge = 0.0;
    for (size_t p = 0; p < NP; p++) {
        double complex psi0;
        double g, s;
        truth(p, &psi0, &g, &s);
        double complex d = h->halo->data[p] - psi0;
        e2 += creal(d) * creal(d) + cimag(d) * cimag(d);
        ge += (h->gain->data[p] - g) * (h->gain->data[p] - g);
    }
    *g_err = sqrt(ge / NP);
    return sqrt(e2 / NP);
}

static void test_recovers_known_halo_and_gain(void **state)
{
    (void)state;
    double err[2], gerr[2];
    const size_t ns[2] = {1000, 16000};
    for (int t = 0; t < 2; t++) {
        /* Average the error over a few seeds so the 1/sqrt(N) check is not luck. */
        double e = 0.0, ge = 0.0;
        for (uint64_t seed = 1; seed <= 4; seed++) {
            swfs_accum *acc = swfs_accum_create(NX, NY);
            assert_non_null(acc);
            feed(acc, ns[t], 0.05, seed * 1000 + (uint64_t)t);
            swfs_halo *h;
            swfs_noise nz = {0.05, 0.0};
            swfs_estimate_options paper = {0.0}; /* g varies pixel to pixel here */
            assert_ok(swfs_estimate(acc, &nz, &paper, &h));
            assert_int_equal(h->n_valid, NP);
            double g1;
            e += halo_rms_error(h, &g1);
            ge += g1;
            swfs_halo_free(h);
            swfs_accum_free(acc);
        }
        err[t] = e / 4;
        gerr[t] = ge / 4;
    }
    print_message("halo rms error: N=1000 %.4g, N=16000 %.4g (ratio %.2f, 1/sqrt(N) predicts 4)\n", err[0], err[1],
                  err[0] / err[1]);
    print_message("g rms error:    N=1000 %.4g, N=16000 %.4g (ratio %.2f)\n", gerr[0], gerr[1], gerr[0] / gerr[1]);
    assert_true(err[1] < 0.02);   /* |Psi| is 0.3 .. 0.9 */
    assert_true(gerr[1] < 0.02);  /* g is 0.8 .. 1.0 */
    assert_true(err[0] / err[1] > 2.8 && err[0] / err[1] < 5.7);
    assert_true(gerr[0] / gerr[1] > 2.8 && gerr[0] / gerr[1] < 5.7);
}

static void test_statistics_match_two_pass(void **state)
{
    (void)state;
    /* Compare the streaming moments with a direct two-pass computation (the paper's
     * Sec. 4.4 sums) on speckles with a deliberately non-zero mean. */
    const size_t n = 500;
    swfs_rng r;
    swfs_rng_seed(&r, 77);
    double *sci = malloc(n * NP * sizeof *sci);
    double complex *psi = malloc(n * NP * sizeof *psi);
    swfs_accum *acc = swfs_accum_create(NX, NY);
    for (size_t k = 0; k < n; k++) {
        for (size_t p = 0; p < NP; p++) {
            psi[k * NP + p] = 0.7 * swfs_rng_cnormal_value(&r) + (0.3 - 0.2 * I);
            double complex t = (0.5 + 0.2 * I) + 1.3 * psi[k * NP + p];
            sci[k * NP + p] = creal(t * conj(t)) + 0.1 * swfs_rng_normal(&r);
        }
        assert_ok(swfs_accum_add(acc, sci + k * NP, psi + k * NP));
    }
    swfs_halo *h;
    swfs_estimate_options paper = {0.0};
    assert_ok(swfs_estimate(acc, NULL, &paper, &h));
    for (size_t p = 0; p < NP; p++) {
        double complex m = 0.0;
        double mi = 0.0;
        for (size_t k = 0; k < n; k++) { m += psi[k * NP + p]; mi += sci[k * NP + p]; }
        m /= (double)n;
        mi /= (double)n;
        double vi = 0.0, phisp = 0.0;
        double complex stab = 0.0, sq = 0.0;
        for (size_t k = 0; k < n; k++) {
            double complex d = psi[k * NP + p] - m;
            vi += (sci[k * NP + p] - mi) * (sci[k * NP + p] - mi);
            phisp += creal(d * conj(d));
            stab += d * sci[k * NP + p];
            sq += d * d;
        }
        vi /= (double)n; phisp /= (double)n; stab /= (double)n; sq /= (double)n;
        double vsp = 0.0;
        for (size_t k = 0; k < n; k++) {
            double complex d = psi[k * NP + p] - m;
            double a = creal(d * conj(d)) - phisp;
            vsp += a * a;
        }
        vsp /= (double)n;
        assert_close(h->mean_i->data[p], mi, 1e-12 * fabs(mi));
        /* VAR_I: the unbiased 1/(N-1) variance (the noise model is removed from it). */
        const double nd = (double)n;
        assert_close(h->var_i->data[p], vi * nd / (nd - 1.0), 1e-10 * vi);
        assert_close(h->mean_sp->data[p], phisp, 1e-10 * phisp);
        assert_close(h->var_sp->data[p], vsp, 1e-9 * vsp);
        assert_close(creal(h->stab->data[p]), creal(stab), 1e-10 * cabs(stab));
        assert_close(cimag(h->stab->data[p]), cimag(stab), 1e-10 * cabs(stab));
        assert_close(h->circ->data[p], cabs(sq) / phisp, 1e-9);
        /* eq:scale-factor and eq:TheAnswer from the direct sums. */
        double rad = vi * nd / (nd - 1.0) / vsp - 2.0 * creal(stab * conj(stab)) / (phisp * vsp);
        assert_true(rad > 0);
        double g = pow(rad, 0.25);
        assert_close(h->gain->data[p], g, 1e-9 * g);
        assert_close(h->gain_pix->data[p], g, 1e-9 * g);
        assert_close(cabs(h->halo->data[p] - stab / (g * phisp)), 0.0, 1e-9);
        /* eq:visibility */
        assert_close(h->visib->data[p], 2.0 * cabs(stab) / (mi * sqrt(phisp)), 1e-9);
    }
    swfs_halo_free(h);
    swfs_accum_free(acc);
    free(sci);
    free(psi);
}

/* Equal to rounding: each field within rel times that field's largest magnitude (a
 * co-moment near zero is the difference of large terms, so its rounding is absolute). */
static void compare_accums(const swfs_accum *a, const swfs_accum *b, double rel)
{
    assert_int_equal(a->frames, b->frames);
    assert_int_equal(a->skipped, b->skipped);
    for (int f = 0; f < SWFS_ACC_NFIELDS; f++) {
        double scale = 0.0;
        for (size_t p = 0; p < a->nx * a->ny; p++) scale = fmax(scale, fabs(a->f[f][p]));
        for (size_t p = 0; p < a->nx * a->ny; p++) assert_close(a->f[f][p], b->f[f][p], rel * scale);
    }
}

static void test_merge_equals_single_pass(void **state)
{
    (void)state;
    swfs_accum *all = swfs_accum_create(NX, NY), *a = swfs_accum_create(NX, NY), *b = swfs_accum_create(NX, NY),
               *c = swfs_accum_create(NX, NY);
    /* Same frames: seed streams per block, fed once into `all` and split into a, b, c. */
    feed(all, 300, 0.1, 11);
    feed(all, 50, 0.1, 12);
    feed(all, 650, 0.1, 13);
    feed(a, 300, 0.1, 11);
    feed(b, 50, 0.1, 12);
    feed(c, 650, 0.1, 13);
    assert_ok(swfs_accum_merge(b, c));
    assert_ok(swfs_accum_merge(a, b));
    compare_accums(all, a, 1e-12);
    swfs_accum *empty = swfs_accum_create(NX, NY);
    assert_ok(swfs_accum_merge(a, empty)); /* merging nothing changes nothing */
    compare_accums(all, a, 1e-12);
    swfs_accum *wrong = swfs_accum_create(NX + 1, NY);
    assert_int_equal(swfs_accum_merge(a, wrong), SWFS_ERR_SHAPE);
    swfs_accum_free(all); swfs_accum_free(a); swfs_accum_free(b); swfs_accum_free(c);
    swfs_accum_free(empty); swfs_accum_free(wrong);
}

static void test_bright_pixel_precision(void **state)
{
    (void)state;
    /* 10^6 frames of a bright pixel: mean 1e7 counts, variance 4. Raw sum-of-squares
     * would lose every digit of the variance (1e20 - 1e20); Welford keeps it. */
    swfs_accum *acc = swfs_accum_create(1, 1);
    swfs_rng r;
    swfs_rng_seed(&r, 5);
    double m = 0.0, m2 = 0.0;
    const size_t n = 1000000;
    for (size_t k = 0; k < n; k++) {
        double v = 1e7 + 2.0 * swfs_rng_normal(&r);
        double complex psi = swfs_rng_cnormal_value(&r);
        assert_ok(swfs_accum_add(acc, &v, &psi));
        double d = v - m;
        m += d / (double)(k + 1);
        m2 += d * (v - m);
    }
    double var = acc->f[SWFS_ACC_CII][0] / (double)n;
    print_message("variance of a 1e7-count pixel over 1e6 frames: %.8f (reference %.8f)\n", var, m2 / (double)n);
    assert_close(var, 4.0, 0.03);
    assert_close(var, m2 / (double)n, 1e-9);
    swfs_accum_free(acc);
}

static void test_nonfinite_science_skipped(void **state)
{
    (void)state;
    swfs_accum *acc = swfs_accum_create(NX, NY);
    swfs_rng r;
    swfs_rng_seed(&r, 9);
    double sci[NP];
    double complex psi[NP];
    for (size_t k = 0; k < 400; k++) {
        for (size_t p = 0; p < NP; p++) {
            psi[p] = swfs_rng_cnormal_value(&r);
            double complex t = 0.5 + psi[p];
            sci[p] = creal(t * conj(t));
        }
        if (k % 10 == 0) sci[3] = NAN;
        if (k % 25 == 0) sci[7] = INFINITY;
        assert_ok(swfs_accum_add(acc, sci, psi));
    }
    assert_int_equal(acc->skipped, 40 + 16);
    swfs_halo *h;
    assert_ok(swfs_estimate(acc, NULL, NULL, &h));
    assert_close(h->nframes->data[3], 360, 0);
    assert_close(h->nframes->data[7], 384, 0);
    for (size_t p = 0; p < NP; p++) assert_true(isfinite(creal(h->halo->data[p])));
    assert_close(cabs(h->halo->data[3] - 0.5), 0.0, 0.1);
    swfs_halo_free(h);

    psi[4] = NAN;
    assert_int_equal(swfs_accum_add(acc, sci, psi), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "(4, 0)"));
    swfs_accum_free(acc);
}

static void test_invalid_pixels_fall_back(void **state)
{
    (void)state;
    swfs_accum *acc = swfs_accum_create(NX, NY);
    swfs_rng r;
    swfs_rng_seed(&r, 21);
    double sci[NP];
    double complex psi[NP];
    for (size_t k = 0; k < 3000; k++) {
        for (size_t p = 0; p < NP; p++) {
            psi[p] = swfs_rng_cnormal_value(&r);
            double complex t = 0.6 + 1.1 * psi[p];
            sci[p] = creal(t * conj(t));
        }
        sci[8] = 2.0;      /* zero-variance science pixel: the radicand of g is negative */
        psi[9] = 0.0;      /* no speckle power */
        assert_ok(swfs_accum_add(acc, sci, psi));
    }
    swfs_halo *h;
    assert_ok(swfs_estimate(acc, NULL, NULL, &h));
    assert_int_equal(h->n_valid, NP - 2);
    assert_int_equal(h->n_bad_radicand, 1);
    assert_int_equal(h->n_no_speckle, 1);
    assert_close(h->valid->data[8], 0.0, 0);
    assert_close(h->gain->data[8], 1.1, 0.05); /* median of valid neighbours */
    assert_true(isfinite(creal(h->halo->data[8])));
    assert_close(cabs(h->halo->data[9]), 0.0, 0.0);
    assert_close(h->valid_fraction, (double)(NP - 2) / NP, 1e-12);
    swfs_halo_free(h);
    swfs_accum_free(acc);
}

static void test_regularized_gain_at_low_snr(void **state)
{
    (void)state;
    /* A faint halo under strong read noise, g = 3 everywhere: the paper's per-pixel g is
     * undefined in many pixels and biased high where it is defined (only upward
     * fluctuations give a positive radicand); the regularized g is close to 3. */
    enum { W = 32, Hh = 32, N = 400 };
    swfs_accum *acc = swfs_accum_create(W, Hh);
    swfs_rng r;
    swfs_rng_seed(&r, 31);
    static double sci[W * Hh];
    static double complex psi[W * Hh];
    const double g = 3.0, rn = 60.0;
    for (int k = 0; k < N; k++) {
        for (int p = 0; p < W * Hh; p++) {
            psi[p] = swfs_rng_cnormal_value(&r);
            double complex t = 2.0 + g * psi[p];
            sci[p] = creal(t * conj(t)) + rn * swfs_rng_normal(&r);
        }
        assert_ok(swfs_accum_add(acc, sci, psi));
    }
    swfs_noise nz = {rn, 0.0};
    swfs_halo *hp, *hr;
    swfs_estimate_options paper = {0.0}, reg = {SWFS_G_SMOOTH_DEFAULT};
    assert_ok(swfs_estimate(acc, &nz, &paper, &hp));
    assert_ok(swfs_estimate(acc, &nz, &reg, &hr));
    double vp[W * Hh], gr = 0.0;
    size_t nv = 0;
    for (int p = 0; p < W * Hh; p++) {
        if (hp->valid->data[p] > 0.5) vp[nv++] = hp->gain_pix->data[p];
        gr += hr->gain->data[p];
        if (hp->valid->data[p] > 0.5) /* the same paper g is kept */
            assert_close(hr->gain_pix->data[p], hp->gain_pix->data[p], 0.0);
        else
            assert_true(isnan(hr->gain_pix->data[p]));
    }
    gr /= W * Hh;
    qsort(vp, nv, sizeof *vp, cmp_d);
    print_message("valid %zu of %d; paper g median %.2f, regularized g mean %.2f (true 3)\n", nv, W * Hh, vp[nv / 2], gr);
    assert_true(nv < W * Hh * 9 / 10);
    assert_true(vp[nv / 2] > 3.3);
    assert_close(gr, 3.0, 0.2);
    swfs_halo_free(hp);
    swfs_halo_free(hr);
    swfs_accum_free(acc);
}

static void test_no_valid_pixel_is_an_error(void **state)
{
    (void)state;
    swfs_accum *acc = swfs_accum_create(2, 2);
    swfs_rng r;
    swfs_rng_seed(&r, 3);
    double sci[4] = {1, 1, 1, 1};
    double complex psi[4];
    for (int k = 0; k < 50; k++) {
        for (int p = 0; p < 4; p++) psi[p] = swfs_rng_cnormal_value(&r);
        assert_ok(swfs_accum_add(acc, sci, psi));
    }
    swfs_halo *h = NULL;
    assert_int_equal(swfs_estimate(acc, NULL, NULL, &h), SWFS_ERR_NUMERIC);
    assert_null(h);
    assert_non_null(strstr(swfs_last_error(), "radicand"));
    swfs_noise bad = {-1.0, 0.0};
    assert_int_equal(swfs_estimate(acc, &bad, NULL, &h), SWFS_ERR_ARG);
    swfs_accum_free(acc);
}

static void test_noise_variance_removed(void **state)
{
    (void)state;
    /* With read noise sigma = 10 counts and photon noise at gain 2 e-/count, removing
     * read^2 + Phi_I/G from sigma_I^2 gives back the noise-free g (eq:scale-factor). */
    const double psi0 = 3.0, g = 5.0, rn = 10.0, gain = 2.0;
    swfs_accum *acc = swfs_accum_create(1, 1);
    swfs_rng r;
    swfs_rng_seed(&r, 17);
    for (int k = 0; k < 200000; k++) {
        double complex psi = swfs_rng_cnormal_value(&r);
        double complex t = psi0 + g * psi;
        double clean = creal(t * conj(t));
        double v = swfs_rng_poisson(&r, clean * gain) / gain + rn * swfs_rng_normal(&r);
        assert_ok(swfs_accum_add(acc, &v, &psi));
    }
    swfs_halo *h;
    swfs_noise nz = {rn, gain};
    assert_ok(swfs_estimate(acc, &nz, NULL, &h));
    print_message("g with noise removed: %.4f (true 5); |Psi| %.4f (true 3)\n", h->gain->data[0], cabs(h->halo->data[0]));
    assert_close(h->gain->data[0], g, 0.05);
    assert_close(cabs(h->halo->data[0]), psi0, 0.05);
    double noise_phi = sqrt(rn * rn + h->mean_i->data[0] / gain);
    assert_close(h->snr->data[0], 2.0 * cabs(h->stab->data[0]) / (noise_phi * sqrt(h->mean_sp->data[0])), 1e-9);
    assert_int_equal(h->n_var_below_noise, 0);
    swfs_halo_free(h);
    /* Without removing the noise g comes out biased high. */
    assert_ok(swfs_estimate(acc, NULL, NULL, &h));
    assert_true(h->gain->data[0] > g + 0.2);
    swfs_halo_free(h);
    swfs_accum_free(acc);
}

static void test_noise_model_too_large_is_flagged(void **state)
{
    (void)state;
    /* Two pixels, read noise 10 counts: a bright one (variance far above the noise) and a
     * faint one (variance ~ the noise). A model of 12 counts exceeds the faint pixel's whole
     * variance: flagged there, not in the bright one. */
    swfs_accum *acc = swfs_accum_create(2, 1);
    swfs_rng r;
    swfs_rng_seed(&r, 8);
    for (int k = 0; k < 20000; k++) {
        double complex psi[2] = {swfs_rng_cnormal_value(&r), swfs_rng_cnormal_value(&r)};
        double complex t0 = 10.0 + 5.0 * psi[0], t1 = 0.5 + 0.5 * psi[1];
        double v[2] = {creal(t0 * conj(t0)) + 10.0 * swfs_rng_normal(&r), creal(t1 * conj(t1)) + 10.0 * swfs_rng_normal(&r)};
        assert_ok(swfs_accum_add(acc, v, psi));
    }
    swfs_halo *h;
    swfs_noise right = {10.0, 0.0}, big = {12.0, 0.0};
    assert_ok(swfs_estimate(acc, &right, NULL, &h));
    assert_int_equal(h->n_var_below_noise, 0);
    swfs_halo_free(h);
    assert_ok(swfs_estimate(acc, &big, NULL, &h));
    assert_int_equal(h->n_var_below_noise, 1);
    swfs_halo_free(h);
    swfs_accum_free(acc);
}

static void test_phase_shifting(void **state)
{
    (void)state;
    const double complex subject = 1.7 * cexp(0.9 * I), ref = 0.8 * cexp(-0.4 * I);
    for (size_t n = 3; n <= 4; n++) {
        double eta[4], inten[4];
        for (size_t k = 0; k < n; k++) {
            eta[k] = 2.0 * M_PI * (double)k / (double)n;
            double complex t = subject + ref * cexp(I * eta[k]);
            inten[k] = creal(t * conj(t));
        }
        swfs_psi_result res;
        assert_ok(swfs_phase_shift(inten, eta, n, carg(ref), &res));
        assert_close(cabs(res.stab - subject * conj(ref)), 0.0, 1e-12); /* eq:stabilizedInterferograms */
        assert_close(remainder(res.subject_phase - 0.9, 2 * M_PI), 0.0, 1e-12);
        /* eq:subjectIntensity: one root is |subject|^2, the other |ref|^2. */
        assert_close(res.intensity_hi, 1.7 * 1.7, 1e-12);
        assert_close(res.intensity_lo, 0.8 * 0.8, 1e-12);
    }
    double eta_bad[3] = {0.0, 0.1, 0.2}, inten[3] = {1, 2, 3};
    swfs_psi_result res;
    assert_int_equal(swfs_phase_shift(inten, eta_bad, 3, 0.0, &res), SWFS_ERR_VALUE);
    assert_int_equal(swfs_phase_shift(inten, eta_bad, 2, 0.0, &res), SWFS_ERR_ARG);
    /* Map version over 2 pixels. */
    double eta4[4] = {0, M_PI / 2, M_PI, 3 * M_PI / 2}, imgs[8];
    for (int k = 0; k < 4; k++)
        for (int p = 0; p < 2; p++) {
            double complex t = (p ? 2.0 * I : 1.0) + 0.5 * cexp(I * eta4[k]);
            imgs[k * 2 + p] = creal(t * conj(t));
        }
    double ph[2];
    assert_ok(swfs_phase_shift_map(imgs, eta4, 4, 2, NULL, NULL, ph, NULL, NULL));
    assert_close(ph[0], 0.0, 1e-12);
    assert_close(ph[1], M_PI / 2, 1e-12);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_recovers_known_halo_and_gain),
        cmocka_unit_test(test_statistics_match_two_pass),
        cmocka_unit_test(test_merge_equals_single_pass),
        cmocka_unit_test(test_bright_pixel_precision),
        cmocka_unit_test(test_nonfinite_science_skipped),
        cmocka_unit_test(test_invalid_pixels_fall_back),
        cmocka_unit_test(test_regularized_gain_at_low_snr),
        cmocka_unit_test(test_no_valid_pixel_is_an_error),
        cmocka_unit_test(test_noise_variance_removed),
        cmocka_unit_test(test_noise_model_too_large_is_flagged),
        cmocka_unit_test(test_phase_shifting),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

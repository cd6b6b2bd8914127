/* Streaming regression statistics (Stage 1 of docs/estimator.md): exact merging with
 * different provisional centres, recovery of a known model, bad inputs. */
#include "testutil.h"

#include "specklewfs/array.h"
#include "specklewfs/estimate.h"
#include "specklewfs/pupil.h"
#include "specklewfs/regress.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { NX = 7, NY = 5, NP = NX * NY, NF = 600 };

typedef struct synth {
    double science[NF][NP];
    double complex psi[NF][NP];
    double complex Psi[NP];
    double g[NP];
} synth;

/* I = |Psi + g psi|^2 + 0.3 |psi2|^2 g^2 (an incoherent speckle) + noise, psi with a
 * non-zero mean so that the centring matters. */
static synth *make_synth(uint64_t seed, double noise)
{
    synth *s = calloc(1, sizeof *s);
    swfs_rng rng;
    swfs_rng_seed(&rng, seed);
    for (size_t k = 0; k < NP; k++) {
        s->Psi[k] = 3.0 * swfs_rng_normal(&rng) + 3.0 * I * swfs_rng_normal(&rng);
        s->g[k] = 20.0 * (1.0 + 0.2 * swfs_rng_normal(&rng));
    }
    for (size_t t = 0; t < NF; t++)
        for (size_t k = 0; k < NP; k++) {
            const double complex ps = 0.4 + 0.1 * I + 0.3 * (swfs_rng_normal(&rng) + I * swfs_rng_normal(&rng));
            const double complex inc = 0.1 * (swfs_rng_normal(&rng) + I * swfs_rng_normal(&rng));
            const double complex e = s->Psi[k] + s->g[k] * ps;
            s->psi[t][k] = ps;
            s->science[t][k] = creal(e * conj(e)) + s->g[k] * s->g[k] * creal(inc * conj(inc)) +
                               noise * swfs_rng_normal(&rng);
        }
    return s;
}

static void add_range(swfs_regress *r, const synth *s, size_t t0, size_t t1)
{
    for (size_t t = t0; t < t1; t++) assert_ok(swfs_regress_add(r, s->science[t], (const double *)s->psi[t], NULL));
}

/* Entry (i, j) of the 4x4 matrix stored as its upper triangle, row by row. */
static size_t tri(size_t i, size_t j)
{
    if (i > j) { size_t t = i; i = j; j = t; }
    return i * 4 - i * (i + 1) / 2 + j;
}

/* Largest difference of two symmetric 4x4 matrix fields (upper-triangle planes starting
 * at a and b, plane stride NP), entry (i, j) relative to sqrt(M_ii M_jj): the natural scale,
 * also for entries that are ~0 (the mean-centred sums of Re p, Im p). */
static double gram_diff(const double *a, const double *b)
{
    double worst = 0.0;
    for (size_t i = 0; i < 4; i++)
        for (size_t j = i; j < 4; j++) {
            double scale = 0.0, d = 0.0;
            for (size_t k = 0; k < NP; k++) {
                scale = fmax(scale, sqrt(b[tri(i, i) * NP + k] * b[tri(j, j) * NP + k]));
                d = fmax(d, fabs(a[tri(i, j) * NP + k] - b[tri(i, j) * NP + k]));
            }
            worst = fmax(worst, d / scale);
        }
    return worst;
}

/* Largest relative difference of planes [f0, f1) of a and b, each relative to its largest value. */
static double plane_diff(const double *a, const double *b, size_t f0, size_t f1)
{
    double worst = 0.0;
    for (size_t f = f0; f < f1; f++) {
        double scale = 0.0, d = 0.0;
        for (size_t k = 0; k < NP; k++) {
            scale = fmax(scale, fabs(b[f * NP + k]));
            d = fmax(d, fabs(a[f * NP + k] - b[f * NP + k]));
        }
        if (scale > 0.0) worst = fmax(worst, d / scale);
    }
    return worst;
}

static double sol_diff(const swfs_regress_sol *a, const swfs_regress_sol *b)
{
    double worst = fmax(plane_diff(a->theta->data, b->theta->data, 0, 4), plane_diff(a->rhs->data, b->rhs->data, 0, 4));
    worst = fmax(worst, gram_diff(a->info->data, b->info->data));
    for (size_t k = 0; k < NP; k++) {
        worst = fmax(worst, fabs(a->s2->data[k] - b->s2->data[k]) / b->s2->data[k]);
        worst = fmax(worst, cabs(a->centre->data[k] - b->centre->data[k]) / cabs(b->centre->data[k]));
    }
    return worst;
}

/* Largest relative difference of two raw states re-centred on their means. */
static double state_diff(swfs_regress *a, swfs_regress *b)
{
    assert_ok(swfs_regress_recenter(a, NULL));
    assert_ok(swfs_regress_recenter(b, NULL));
    double worst = plane_diff(a->state, b->state, SWFS_REG_N, SWFS_REG_SRE);
    worst = fmax(worst, gram_diff(a->state + SWFS_REG_G00 * NP, b->state + SWFS_REG_G00 * NP));
    worst = fmax(worst, plane_diff(a->state, b->state, SWFS_REG_H0, SWFS_REGRESS_NSTATE));
    /* the sums of p are ~0 after centring: compare them with sqrt(n G_22) */
    for (size_t k = 0; k < NP; k++)
        for (size_t f = SWFS_REG_SRE; f <= SWFS_REG_SIM; f++)
            worst = fmax(worst, fabs(a->state[f * NP + k] - b->state[f * NP + k]) /
                                    sqrt(b->state[SWFS_REG_N * NP + k] * b->state[SWFS_REG_G22 * NP + k]));
    return worst;
}

static void test_merge_exact(void **state)
{
    (void)state;
    synth *s = make_synth(3, 2.0);
    swfs_regress *one = swfs_regress_create(NX, NY), *h1 = swfs_regress_create(NX, NY);
    swfs_regress *h2 = swfs_regress_create(NX, NY), *h3 = swfs_regress_create(NX, NY);
    add_range(one, s, 0, NF);
    /* Halves merged both ways: the second half's centres (its first frame) differ from the
     * first half's, so merging into h2 re-centres h1's sums. */
    add_range(h1, s, 0, NF / 2);
    add_range(h2, s, NF / 2, NF);
    /* A third accumulator with a centre set explicitly before any frame, 2.8 sigma off the
     * mean (precision degrades as (|delta|^2 / Phi_sp)^2: a centre 15 sigma off costs 1e-9). */
    double far[2 * NP];
    for (size_t k = 0; k < NP; k++) { far[2 * k] = 1.0; far[2 * k + 1] = -0.5; }
    assert_ok(swfs_regress_recenter(h3, far));
    add_range(h3, s, 0, NF / 3);
    swfs_regress *m3 = swfs_regress_create(NX, NY);
    add_range(m3, s, NF / 3, NF);
    assert_ok(swfs_regress_merge(h3, m3));
    assert_ok(swfs_regress_merge(h2, h1));
    assert_int_equal(h2->frames, NF);
    assert_true(h2->state[SWFS_REG_C0RE * NP] != one->state[SWFS_REG_C0RE * NP]);

    swfs_regress_sol *so, *sm, *s3;
    assert_ok(swfs_regress_solve(one, &so));
    assert_ok(swfs_regress_solve(h2, &sm));
    assert_ok(swfs_regress_solve(h3, &s3));
    assert_int_equal(so->n_valid, NP);
    const double d_sol = sol_diff(sm, so), d_sol3 = sol_diff(s3, so);
    const double d_state = state_diff(h2, one), d_state3 = state_diff(h3, one);
    print_message("merge vs one pass: solution %.2g / %.2g, state %.2g / %.2g (relative)\n", d_sol, d_sol3, d_state,
                  d_state3);
    assert_true(d_sol < 1e-10 && d_sol3 < 1e-10);
    assert_true(d_state < 1e-10 && d_state3 < 1e-10);

    /* Export / import round trip. */
    double *raw = malloc(NP * SWFS_REGRESS_NSTATE * sizeof *raw);
    swfs_regress_export(one, raw);
    swfs_regress *back = swfs_regress_create(NX, NY);
    assert_ok(swfs_regress_import(back, raw));
    assert_memory_equal(back->state, one->state, NP * SWFS_REGRESS_NSTATE * sizeof *raw);
    raw[SWFS_REG_N * NP + 3] = -1.0;
    assert_int_equal(swfs_regress_import(back, raw), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "pixel (3, 0)"));
    free(raw);

    swfs_regress_sol_free(so); swfs_regress_sol_free(sm); swfs_regress_sol_free(s3);
    swfs_regress_free(one); swfs_regress_free(h1); swfs_regress_free(h2); swfs_regress_free(h3);
    swfs_regress_free(m3); swfs_regress_free(back);
    free(s);
}

/* The solution recovers the model it was built from: b = g^2, c = g Psi' (Psi' = Psi + g
 * <psi>, the static field in the frame centred on the mean psi), s^2 the noise. */
static int cmp_double(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static void test_recovers_model(void **state)
{
    (void)state;
    const double noise = 2.0;
    synth *s = make_synth(5, noise);
    swfs_regress *r = swfs_regress_create(NX, NY);
    add_range(r, s, 0, NF);
    swfs_regress_sol *so;
    assert_ok(swfs_regress_solve(r, &so));
    double eb = 0.0, ec = 0.0, es = 0.0;
    for (size_t k = 0; k < NP; k++) {
        const double complex c = so->theta->data[2 * NP + k] + I * so->theta->data[3 * NP + k];
        const double complex Psi1 = s->Psi[k] + s->g[k] * so->centre->data[k];
        eb = fmax(eb, fabs(so->theta->data[NP + k] / (s->g[k] * s->g[k]) - 1.0));
        ec = fmax(ec, cabs(c / (s->g[k] * Psi1) - 1.0));
        /* residual: noise + the incoherent speckle's fluctuation 0.02 g^2 (|inc|^2 is
         * exponential with mean 0.02: variance 0.02^2) */
        const double v = noise * noise + pow(0.02 * s->g[k] * s->g[k], 2);
        es = fmax(es, fabs(so->s2->data[k] / v - 1.0));
    }
    /* The self-check per pixel: 1 - SSE / SST with SSE = (n - 4) s^2 and SST the science's
       variance about its mean, from the frames themselves; its median is explained_median. */
    double er = 0.0, r2[NP];
    for (size_t k = 0; k < NP; k++) {
        double m = 0.0, sst = 0.0;
        for (size_t t = 0; t < NF; t++) m += s->science[t][k] / NF;
        for (size_t t = 0; t < NF; t++) sst += (s->science[t][k] - m) * (s->science[t][k] - m);
        const double want = 1.0 - (NF - 4.0) * so->s2->data[k] / sst;
        er = fmax(er, fabs(so->r2->data[k] - want));
        r2[k] = so->r2->data[k];
        assert_true(r2[k] > 0.0 && r2[k] < 1.0);
    }
    qsort(r2, NP, sizeof r2[0], cmp_double);
    print_message("self-check: explained %.3f, median pixel %.3f (map: %.3f), map error %.2g\n", so->explained,
                  so->explained_median, r2[NP / 2], er);
    assert_true(er < 1e-6);
    assert_true(fabs(so->explained_median - r2[NP / 2]) < 1e-12);
    print_message("max relative error: b %.3f, c %.4f, s^2 %.3f\n", eb, ec, es);
    assert_true(eb < 0.1);
    assert_true(ec < 0.02);
    assert_true(es < 0.35);
    swfs_regress_sol_free(so);
    swfs_regress_free(r);
    free(s);
}

/* The information of a pixel seen in few frames (regress.h): with s^2 estimated on nu = n - 4
 * degrees of freedom, (theta_hat - theta)^T (G / s^2) (theta_hat - theta) has the mean
 * 4 nu / (nu - 2), not 4; the information the solution gives, G / s^2 (nu - 2) / nu, has
 * the mean 4 (Hotelling's T^2, Gaussian noise). 2000 pixels of 12 frames (nu = 8: 5.33
 * without the factor); and a pixel of 6 frames or fewer is not solved. */
static void test_few_frames_information(void **state)
{
    (void)state;
    enum { FX = 50, FY = 40, FP = FX * FY, FN = 12 };
    double *sci = malloc(FP * sizeof *sci);
    double complex *psi = malloc(FN * FP * sizeof *psi), *Psi = malloc(FP * sizeof *Psi);
    double *g = malloc(FP * sizeof *g);
    swfs_rng rng;
    swfs_rng_seed(&rng, 77);
    for (size_t k = 0; k < FP; k++) {
        Psi[k] = 3.0 * swfs_rng_normal(&rng) + 3.0 * I * swfs_rng_normal(&rng);
        g[k] = 5.0 * (1.0 + 0.2 * swfs_rng_normal(&rng));
    }
    swfs_regress *r = swfs_regress_create(FX, FY);
    for (size_t t = 0; t < FN; t++) {
        for (size_t k = 0; k < FP; k++) {
            const double complex ps = 0.4 + 0.1 * I + 0.5 * (swfs_rng_normal(&rng) + I * swfs_rng_normal(&rng));
            const double complex e = Psi[k] + g[k] * ps;
            psi[t * FP + k] = ps;
            sci[k] = creal(e * conj(e)) + 4.0 * swfs_rng_normal(&rng);
            if (k == 0 && t >= 6) sci[k] = NAN; /* pixel 0: 6 frames, not solved */
        }
        assert_ok(swfs_regress_add(r, sci, (const double *)(psi + t * FP), NULL));
    }
    swfs_regress_sol *so;
    assert_ok(swfs_regress_solve(r, &so));
    assert_true(so->valid->data[0] == 0.0);
    double sum = 0.0;
    size_t m = 0;
    for (size_t k = 1; k < FP; k++) {
        if (!(so->valid->data[k] > 0.5)) continue;
        const double complex Psi1 = Psi[k] + g[k] * so->centre->data[k], c = g[k] * Psi1;
        const double want[4] = {creal(Psi1 * conj(Psi1)), g[k] * g[k], creal(c), cimag(c)};
        double d[4], q = 0.0;
        for (int i = 0; i < 4; i++) d[i] = so->theta->data[(size_t)i * FP + k] - want[i];
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) q += d[i] * so->info->data[tri((size_t)i, (size_t)j) * FP + k] * d[j];
        sum += q;
        m++;
    }
    const double mean = sum / (double)m;
    print_message("few frames: %zu pixels of %d frames (nu = %d): mean (theta_hat - theta)^T F (...) = %.3f "
                  "(4 expected; %.2f without the t factor)\n", m, FN, FN - 4, mean, 4.0 * (FN - 4) / (FN - 6.0));
    assert_int_equal(m, FP - 1);
    assert_true(fabs(mean - 4.0) < 0.5);
    swfs_regress_sol_free(so);
    swfs_regress_free(r);
    free(sci); free(psi); free(Psi); free(g);
}

static void test_bad_input(void **state)
{
    (void)state;
    synth *s = make_synth(9, 1.0);
    swfs_regress *r = swfs_regress_create(NX, NY), *other = swfs_regress_create(NX + 1, NY);
    assert_null(swfs_regress_create(0, 3));
    assert_non_null(strstr(swfs_last_error(), "0x3"));
    /* Shape mismatch. */
    assert_int_equal(swfs_regress_merge(r, other), SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "7x5 and 8x5"));
    /* NaN science: skipped and counted. */
    s->science[0][4] = NAN;
    add_range(r, s, 0, 3);
    assert_int_equal(r->skipped, 1);
    assert_true(r->state[SWFS_REG_N * NP + 4] == 2.0 && r->state[SWFS_REG_N * NP + 5] == 3.0);
    /* NaN psi: an error naming pixel and frame, nothing accumulated. */
    double *before = malloc(NP * SWFS_REGRESS_NSTATE * sizeof *before);
    swfs_regress_export(r, before);
    s->psi[3][9] = NAN;
    assert_int_equal(swfs_regress_add(r, s->science[3], (const double *)s->psi[3], NULL), SWFS_ERR_VALUE);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "pixel (2, 1) of frame 3 is not finite"));
    assert_memory_equal(before, r->state, NP * SWFS_REGRESS_NSTATE * sizeof *before);
    assert_int_equal(r->frames, 3);
    /* Too few frames to solve anything. */
    swfs_regress_sol *so = NULL;
    assert_int_equal(swfs_regress_solve(r, &so), SWFS_ERR_NUMERIC);
    assert_null(so);
    free(before);
    swfs_regress_free(r);
    swfs_regress_free(other);
    free(s);
}

/* The self-check as a choice (pupil.h swfs_halo_choose): halos of the same science frames
 * with the exact speckles and with speckles carrying an error; the exact ones explain the
 * most and are chosen, the score equals the regression's own explained fraction when every
 * pixel is solved, and the score falls as the speckles' error grows. Halos of other science
 * frames and a halo without regression statistics are refused by name. */
static void test_choose_speckles(void **state)
{
    (void)state;
    synth *s = make_synth(9, 2.0), *other = make_synth(10, 2.0);
    const double err[3] = {0.0, 0.1, 0.25};
    swfs_regress *r[4];
    swfs_halo h[4];
    const swfs_halo *hp[4];
    swfs_rng rng;
    swfs_rng_seed(&rng, 77);
    static double complex psi[NP];
    for (int c = 0; c < 3; c++) {
        r[c] = swfs_regress_create(NX, NY);
        for (size_t t = 0; t < NF; t++) {
            for (size_t k = 0; k < NP; k++)
                psi[k] = s->psi[t][k] + err[c] * (swfs_rng_normal(&rng) + I * swfs_rng_normal(&rng));
            assert_ok(swfs_regress_add(r[c], s->science[t], (const double *)psi, NULL));
        }
    }
    r[3] = swfs_regress_create(NX, NY);
    add_range(r[3], other, 0, NF);
    for (int c = 0; c < 4; c++) {
        memset(&h[c], 0, sizeof h[c]);
        h[c].reg = r[c];
        hp[c] = &h[c];
    }
    const char *names[4] = {"exact", "err0.1", "err0.25", "other"};
    double ex[4];
    size_t best = 9, nc = 0;
    assert_ok(swfs_halo_choose(hp, names, 3, ex, &best, &nc));
    print_message("choose: explained %.4f %.4f %.4f over %zu pixels, best %zu\n", ex[0], ex[1], ex[2], nc, best);
    assert_int_equal(best, 0);
    assert_int_equal(nc, NP);
    assert_true(ex[0] > ex[1] && ex[1] > ex[2] && ex[2] > 0);
    swfs_regress_sol *so;
    assert_ok(swfs_regress_solve(r[0], &so));
    assert_close(ex[0], so->explained, 1e-9);
    swfs_regress_sol_free(so);
    /* the order of the candidates does not matter */
    const swfs_halo *rev[3] = {hp[2], hp[1], hp[0]};
    assert_ok(swfs_halo_choose(rev, NULL, 3, ex, &best, &nc));
    assert_int_equal(best, 2);
    /* other science frames */
    const swfs_halo *mix[2] = {hp[0], hp[3]};
    const char *mixn[2] = {names[0], names[3]};
    assert_int_equal(swfs_halo_choose(mix, mixn, 2, ex, &best, &nc), SWFS_ERR_VALUE);
    print_message("choose: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "other and exact: the science intensity's variance differs"));
    assert_true(isnan(ex[0]));
    /* speckles of another tip-tilt treatment */
    snprintf(h[0].tiptilt, sizeof h[0].tiptilt, "exposure");
    snprintf(h[1].tiptilt, sizeof h[1].tiptilt, "keep");
    assert_int_equal(swfs_halo_choose(hp, names, 2, ex, &best, &nc), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "err0.1: speckles made with --tiptilt keep where exact has exposure"));
    h[1].tiptilt[0] = 0; /* not known: compared */
    assert_ok(swfs_halo_choose(hp, names, 2, ex, &best, &nc));
    /* no regression statistics */
    swfs_halo bare;
    memset(&bare, 0, sizeof bare);
    const swfs_halo *nb[2] = {hp[0], &bare};
    assert_int_equal(swfs_halo_choose(nb, NULL, 2, ex, &best, &nc), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "candidate 1: no regression statistics"));
    for (int c = 0; c < 4; c++) swfs_regress_free(r[c]);
    free(s);
    free(other);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_merge_exact),
        cmocka_unit_test(test_recovers_model),
        cmocka_unit_test(test_few_frames_information),
        cmocka_unit_test(test_bad_input),
        cmocka_unit_test(test_choose_speckles),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

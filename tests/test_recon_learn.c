/* The learned reconstructor's algebra (wfs.h swfs_recon_learner) on a synthetic linear
 * problem z = W0 s + noise + piston, with one slope that never has signal: the map comes back
 * (piston removed, the dead slope's column 0), the training misfit it reports is the misfit
 * computed frame by frame, and the held-out check of one part equals the map learned on the
 * other part alone applied to the held-out frames; with a prior map, the ridge toward it.
 * Bad input: NaN, too few frames. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include "../src/run/run_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#define NS 7   /* slopes; slope DEAD never has signal */
#define NA 5   /* actuators */
#define DEAD 3
#define NOISE 0.05

static double W0[NA][NS];

/* W0 drawn from seed's stream r (the dead slope's column 0); r goes on to the frames. */
static void draw_map(swfs_rng *r, uint64_t seed)
{
    swfs_rng_seed(r, seed);
    for (size_t a = 0; a < NA; a++)
        for (size_t i = 0; i < NS; i++) W0[a][i] = i == DEAD ? 0.0 : swfs_rng_normal(r);
}

/* n frames of slopes and truth (with a random piston per frame) from the stream rng. */
static void make_frames(swfs_rng *r, size_t n, double *s, double *z)
{
    for (size_t f = 0; f < n; f++) {
        double *sf = s + f * NS, *zf = z + f * NA;
        for (size_t i = 0; i < NS; i++) sf[i] = i == DEAD ? 0.0 : swfs_rng_normal(r);
        const double piston = 3 * swfs_rng_normal(r);
        for (size_t a = 0; a < NA; a++) {
            zf[a] = piston + NOISE * swfs_rng_normal(r);
            for (size_t i = 0; i < NS; i++) zf[a] += W0[a][i] * sf[i];
        }
    }
}

/* Mean square per actuator and frame of (z - piston) - (W s - its piston) over n frames. */
static double misfit2(const swfs_recon *w, const double *s, const double *z, size_t n)
{
    double e2 = 0;
    for (size_t f = 0; f < n; f++) {
        double zh[NA], mz = 0, mh = 0;
        swfs_recon_apply(w, s + f * NS, zh);
        for (size_t a = 0; a < NA; a++) {
            mz += z[f * NA + a] / NA;
            mh += zh[a] / NA;
        }
        for (size_t a = 0; a < NA; a++) {
            const double d = (z[f * NA + a] - mz) - (zh[a] - mh);
            e2 += d * d;
        }
    }
    return e2 / (double)(n * NA);
}

/* The synthetic problem of seed: W0 and n frames of slopes and truth (malloc'd). */
static void draw_problem(uint64_t seed, size_t n, double **s, double **z)
{
    swfs_rng r;
    draw_map(&r, seed);
    *s = malloc(n * NS * sizeof **s);
    *z = malloc(n * NA * sizeof **z);
    assert_non_null(*s);
    assert_non_null(*z);
    make_frames(&r, n, *s, *z);
}

static void test_learner(void **state)
{
    (void)state;
    const size_t na = 400, nb = 300;
    double *s = NULL, *z = NULL;
    draw_problem(7, na + nb, &s, &z);

    swfs_recon_learner *all = NULL, *pa = NULL, *pb = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &all));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &pa));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &pb));
    /* the sums in two calls of different length, as files are read */
    assert_ok(swfs_recon_learner_add(all, s, z, 123));
    assert_ok(swfs_recon_learner_add(all, s + 123 * NS, z + 123 * NA, na + nb - 123));
    assert_ok(swfs_recon_learner_add(pa, s, z, na));
    assert_ok(swfs_recon_learner_add(pb, s + na * NS, z + na * NA, nb));
    assert_int_equal(swfs_recon_learner_frames(all), na + nb);

    swfs_recon *w = NULL;
    swfs_recon_learn_info info;
    assert_ok(swfs_recon_learner_solve(all, SWFS_RECON_LEARN_RIDGE, &w, &info));
    assert_int_equal(info.nframes, na + nb);
    assert_int_equal(info.nslopes_seen, NS - 1);
    /* the map: W0 with the piston of each column taken out, 0 on the dead slope */
    double worst = 0;
    for (size_t i = 0; i < NS; i++) {
        double m = 0;
        for (size_t a = 0; a < NA; a++) m += W0[a][i] / NA;
        for (size_t a = 0; a < NA; a++) {
            const double e = fabs(w->W[a * NS + i] - (W0[a][i] - m));
            if (i == DEAD) assert_true(w->W[a * NS + i] == 0.0);
            worst = fmax(worst, e);
        }
    }
    printf("test_recon_learn: map error %.4f (noise %.2f over %zu frames)\n", worst, NOISE, na + nb);
    assert_true(worst < 0.02);
    /* the reported training misfit is the one computed frame by frame, about the noise. The
     * sums give it as the truth's power less the map's cross term with the truth, summed in
     * single precision (wfs.h): their rounding, below 1e-5 of the truth's power, is what may
     * separate the two (here the misfit is 2 % of the truth's rms, so 1e-5 of the truth's
     * power is 2 % of the misfit's) */
    const double m_all = misfit2(w, s, z, na + nb), rnd = 1e-5 * info.truth_rms * info.truth_rms;
    printf("test_recon_learn: training misfit %.8g from the sums, %.8g frame by frame (truth %.4g rms)\n",
           info.misfit_rms, sqrt(m_all), info.truth_rms);
    assert_true(fabs(info.misfit_rms * info.misfit_rms - m_all) <= rnd);
    assert_true(info.misfit_rms > 0.8 * NOISE * sqrt((NA - 1.0) / NA) && info.misfit_rms < NOISE);

    /* held out: part b left out of all = the map of part a alone applied to b's frames */
    double h2 = 0, t2 = 0;
    assert_ok(swfs_recon_learner_heldout(all, pb, SWFS_RECON_LEARN_RIDGE, &h2, &t2));
    swfs_recon *wa = NULL;
    assert_ok(swfs_recon_learner_solve(pa, SWFS_RECON_LEARN_RIDGE, &wa, NULL));
    const double direct = misfit2(wa, s + na * NS, z + na * NA, nb);
    printf("test_recon_learn: held out %.6g, directly %.6g; training %.6g\n", h2, direct, m_all);
    assert_true(fabs(h2 - direct) <= rnd && fabs(h2 - direct) < 0.2 * direct);
    /* least squares: the map that learned b's frames misses them by no more than one that did
     * not (beyond the cross term's rounding) */
    assert_true(misfit2(w, s + na * NS, z + na * NA, nb) <= direct * (1 + 1e-9));
    assert_true(misfit2(w, s + na * NS, z + na * NA, nb) <= h2 + rnd);
    double tz = 0;
    for (size_t f = na; f < na + nb; f++) {
        double mz = 0;
        for (size_t a = 0; a < NA; a++) mz += z[f * NA + a] / NA;
        for (size_t a = 0; a < NA; a++) tz += (z[f * NA + a] - mz) * (z[f * NA + a] - mz);
    }
    assert_close(t2 / (tz / (double)(nb * NA)), 1.0, 1e-10);

    /* a part that is the whole, or of another shape, is refused */
    assert_int_equal(swfs_recon_learner_heldout(all, all, SWFS_RECON_LEARN_RIDGE, &h2, &t2), SWFS_ERR_ARG);
    assert_true(isnan(h2));
    /* too few frames for the slopes: a clear error, no map */
    swfs_recon_learner_reset(pa);
    assert_int_equal(swfs_recon_learner_frames(pa), 0);
    assert_ok(swfs_recon_learner_add(pa, s, z, 5));
    swfs_recon *wx = NULL;
    assert_int_equal(swfs_recon_learner_solve(pa, SWFS_RECON_LEARN_RIDGE, &wx, NULL), SWFS_ERR_VALUE);
    assert_null(wx);
    printf("test_recon_learn: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "5 frames for 6 slopes"));
    /* a NaN slope: refused, named, nothing added */
    s[2 * NS + 4] = NAN;
    assert_int_equal(swfs_recon_learner_add(pa, s, z, 3), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "slope 4 of frame 2"));
    assert_int_equal(swfs_recon_learner_frames(pa), 5);
    assert_int_equal(swfs_recon_learner_solve(pa, 0.0, &wx, NULL), SWFS_ERR_ARG);

    swfs_recon_free(w);
    swfs_recon_free(wa);
    swfs_recon_learner_free(all);
    swfs_recon_learner_free(pa);
    swfs_recon_learner_free(pb);
    free(s);
    free(z);
}

/* A prior map (swfs_recon_learner_set_prior): from 30 frames, the map with a ridge toward a
 * prior P (W0 perturbed) is the minimum of sum |z - W s|^2 + lam |W - P|^2 (its gradient 0,
 * checked from the frames), a vanishing ridge gives the map without a prior, a huge one P (the
 * piston of each column out; the dead slope's column P's), the training misfit reported is the
 * one computed frame by frame; a prior of other shapes is refused. */
/* The map of the sums less a part's (leave-one-out: learn's held-out miss of the mean) is the
 * map of the other frames alone, with a prior too. */
static void test_learner_solve_without(void **state)
{
    (void)state;
    const size_t na_ = 40, nb = 25;
    double *s = NULL, *z = NULL;
    draw_problem(23, na_ + nb, &s, &z);
    swfs_recon_learner *all = NULL, *part = NULL, *rest = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &all));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &part));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &rest));
    assert_ok(swfs_recon_learner_add(all, s, z, na_ + nb));
    assert_ok(swfs_recon_learner_add(rest, s, z, na_));
    assert_ok(swfs_recon_learner_add(part, s + na_ * NS, z + na_ * NA, nb));
    swfs_recon P = {.nact = NA, .nslopes = NS};
    P.W = malloc(NA * NS * sizeof *P.W);
    assert_non_null(P.W);
    for (size_t k = 0; k < NA * NS; k++) P.W[k] = 0.01 * (double)(k % 7) - 0.02;
    for (int prior = 0; prior < 2; prior++) {
        if (prior) {
            assert_ok(swfs_recon_learner_set_prior(all, &P));
            assert_ok(swfs_recon_learner_set_prior(rest, &P));
        }
        const double ridge = prior ? 0.3 : 1e-6;
        swfs_recon *w1 = NULL, *w2 = NULL, *wall = NULL;
        assert_ok(swfs_recon_learner_solve(rest, ridge, &w1, NULL));
        assert_ok(swfs_recon_learner_solve_without(all, part, ridge, &w2));
        assert_ok(swfs_recon_learner_solve(all, ridge, &wall, NULL));
        double d = 0, dall = 0, mx = 0;
        for (size_t k = 0; k < NA * NS; k++) {
            d = fmax(d, fabs(w1->W[k] - w2->W[k]));
            dall = fmax(dall, fabs(w1->W[k] - wall->W[k]));
            mx = fmax(mx, fabs(w1->W[k]));
        }
        printf("test_recon_learn: without a part (prior %d): %.3g of %.3g from the rest's map, %.3g from all's\n", prior,
               d, mx, dall);
        assert_true(mx > 0 && d < 1e-5 * mx); /* the other frames' map (the sums' rounding apart) */
        assert_true(dall > 1e-3 * mx);        /* not the map of all of them */
        swfs_recon_free(w1);
        swfs_recon_free(w2);
        swfs_recon_free(wall);
    }
    swfs_recon *bad = NULL;
    assert_int_equal(swfs_recon_learner_solve_without(part, all, 1e-6, &bad), SWFS_ERR_ARG); /* more left out than held */
    assert_null(bad);
    free(P.W);
    swfs_recon_learner_free(all);
    swfs_recon_learner_free(part);
    swfs_recon_learner_free(rest);
    free(s);
    free(z);
}

/* A held-out part in sub-parts (swfs_recon_learner_heldout_split): the map solved once from the
 * other frames, its misfit on each sub-part as the map applied frame by frame gives it, their
 * frames' weighted mean the part's misfit (swfs_recon_learner_heldout_on's); sub-parts of more
 * frames than the part are refused. */
static void test_learner_heldout_split(void **state)
{
    (void)state;
    const size_t nr = 60, n1 = 25, n2 = 30;
    double *s = NULL, *z = NULL;
    draw_problem(29, nr + n1 + n2, &s, &z);
    swfs_recon_learner *all = NULL, *part = NULL, *p1 = NULL, *p2 = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &all));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &part));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p1));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p2));
    const double *s1 = s + nr * NS, *z1 = z + nr * NA, *s2 = s1 + n1 * NS, *z2 = z1 + n1 * NA;
    assert_ok(swfs_recon_learner_add(all, s, z, nr + n1 + n2));
    assert_ok(swfs_recon_learner_add(part, s1, z1, n1 + n2));
    assert_ok(swfs_recon_learner_add(p1, s1, z1, n1));
    assert_ok(swfs_recon_learner_add(p2, s2, z2, n2));
    const swfs_recon_learner *subs[2] = {p1, p2};
    double m = 0, t = 0, sc = 0, sub[2] = {0, 0}, mo = 0, to = 0, sco = 0;
    assert_ok(swfs_recon_learner_heldout_split(all, part, subs, 2, SWFS_RECON_LEARN_RIDGE, NULL, &m, &t, &sc, sub));
    assert_ok(swfs_recon_learner_heldout_on(all, part, SWFS_RECON_LEARN_RIDGE, NULL, &mo, &to, &sco));
    swfs_recon *w = NULL;
    assert_ok(swfs_recon_learner_solve_without(all, part, SWFS_RECON_LEARN_RIDGE, &w));
    const double d1 = misfit2(w, s1, z1, n1), d2 = misfit2(w, s2, z2, n2);
    printf("test_recon_learn: held out in two sub-parts: %.6g and %.6g (frame by frame %.6g, %.6g); the part %.6g, "
           "its truth %.4g\n", sub[0], sub[1], d1, d2, m, t);
    /* the sums' misfit is |z|^2 - 2 z.Ws + |Ws|^2 of a truth 3 decades above it: their rounding */
    assert_close(sub[0], d1, 1e-5 * t);
    assert_close(sub[1], d2, 1e-5 * t);
    assert_true(fabs(sub[0] - sub[1]) > 1e-3 * m); /* two different numbers */
    assert_close(m, ((double)n1 * sub[0] + (double)n2 * sub[1]) / (double)(n1 + n2), 1e-5 * t); /* the same rounding */
    assert_true(m == mo && t == to && sc == sco);
    const swfs_recon_learner *over[2] = {part, p1}; /* more frames than the part holds */
    assert_int_equal(swfs_recon_learner_heldout_split(all, part, over, 2, SWFS_RECON_LEARN_RIDGE, NULL, &m, &t, NULL, sub),
                     SWFS_ERR_ARG);
    assert_true(isnan(sub[0]) && isnan(m));
    swfs_recon_free(w);
    swfs_recon_learner_free(all);
    swfs_recon_learner_free(part);
    swfs_recon_learner_free(p1);
    swfs_recon_learner_free(p2);
    free(s);
    free(z);
}

static void test_learner_prior(void **state)
{
    (void)state;
    const size_t n = 30;
    double *s = NULL, *z = NULL;
    draw_problem(11, n, &s, &z);
    swfs_rng r;
    swfs_rng_seed(&r, 99);
    swfs_recon P = {.nact = NA, .nslopes = NS};
    P.W = malloc(NA * NS * sizeof *P.W);
    assert_non_null(P.W);
    for (size_t a = 0; a < NA; a++)
        for (size_t i = 0; i < NS; i++) P.W[a * NS + i] = W0[a][i] + 0.3 * swfs_rng_normal(&r);
    swfs_recon_learner *l = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &l));
    assert_ok(swfs_recon_learner_add(l, s, z, n));
    swfs_recon *w_none = NULL, *w_tiny = NULL, *w_huge = NULL, *w = NULL;
    assert_ok(swfs_recon_learner_solve(l, 1e-12, &w_none, NULL));
    assert_ok(swfs_recon_learner_set_prior(l, &P));
    assert_ok(swfs_recon_learner_solve(l, 1e-12, &w_tiny, NULL));
    assert_ok(swfs_recon_learner_solve(l, 1e8, &w_huge, NULL));
    const double ridge = 0.5;
    swfs_recon_learn_info info;
    assert_ok(swfs_recon_learner_solve(l, ridge, &w, &info));
    double d_tiny = 0, d_huge = 0, g_worst = 0, g_scale = 0;
    /* lam: ridge x the mean diagonal of S^T S over the slopes with signal */
    double tr = 0;
    for (size_t f = 0; f < n; f++)
        for (size_t i = 0; i < NS; i++) tr += s[f * NS + i] * s[f * NS + i];
    const double lam = ridge * tr / (NS - 1);
    for (size_t i = 0; i < NS; i++) {
        double pm = 0;
        for (size_t a = 0; a < NA; a++) pm += P.W[a * NS + i] / NA;
        for (size_t a = 0; a < NA; a++) {
            if (i != DEAD) d_tiny = fmax(d_tiny, fabs(w_tiny->W[a * NS + i] - w_none->W[a * NS + i]));
            d_huge = fmax(d_huge, fabs(w_huge->W[a * NS + i] - (P.W[a * NS + i] - pm)));
            if (i == DEAD) { /* no signal: the prior's column */
                assert_close(w->W[a * NS + i], P.W[a * NS + i] - pm, 1e-12);
                continue;
            }
            /* the gradient: -sum_f (zc - W s)_a s_i + lam (W - Pc)_ai */
            double g = lam * (w->W[a * NS + i] - (P.W[a * NS + i] - pm));
            for (size_t f = 0; f < n; f++) {
                double zm = 0, wsa = 0;
                for (size_t b = 0; b < NA; b++) zm += z[f * NA + b] / NA;
                for (size_t j = 0; j < NS; j++) wsa += w->W[a * NS + j] * s[f * NS + j];
                g -= (z[f * NA + a] - zm - wsa) * s[f * NS + i];
            }
            g_worst = fmax(g_worst, fabs(g));
            g_scale = fmax(g_scale, lam * fabs(w->W[a * NS + i]));
        }
    }
    const double m2 = misfit2(w, s, z, n);
    printf("test_recon_learn: prior: tiny ridge %.2g from no prior, huge %.2g from the prior; gradient %.2g of %.2g; "
           "misfit %.6g from the sums, %.6g by frame\n", d_tiny, d_huge, g_worst, g_scale, info.misfit_rms, sqrt(m2));
    assert_true(d_tiny < 1e-6);
    assert_true(d_huge < 1e-6);
    assert_true(g_worst < 1e-4 * g_scale); /* the truth's sums are single precision (wfs.h) */
    assert_true(fabs(info.misfit_rms * info.misfit_rms - m2) <= 1e-5 * info.truth_rms * info.truth_rms);
    /* the map between the two: nearer the prior than the least squares is, and fits worse */
    assert_true(m2 > misfit2(w_none, s, z, n));
    P.nslopes = NS - 1;
    assert_int_equal(swfs_recon_learner_set_prior(l, &P), SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "prior map of 5 outputs x 6 inputs"));
    swfs_recon_free(w_none);
    swfs_recon_free(w_tiny);
    swfs_recon_free(w_huge);
    swfs_recon_free(w);
    swfs_recon_learner_free(l);
    free(P.W);
    free(s);
    free(z);
}

/* The sums hold only the slopes that ever carried signal (wfs.h): a slope 0 in the first file
 * and live in the second (the sums grow), the files in either order, give the same map; the
 * held-out check of the first file (no signal in that slope) against the whole is the map
 * of the second file alone on the first's frames; a space-time learner grows the same way;
 * a part with signal where the whole has none is refused. */
#define GROW 5
static void test_learner_grows(void **state)
{
    (void)state;
    const size_t n1 = 300, n2 = 400;
    double *s = NULL, *z = NULL;
    draw_problem(11, n1 + n2, &s, &z);
    for (size_t f = 0; f < n1; f++) { /* GROW silent in file 1: its truth without that slope */
        for (size_t a = 0; a < NA; a++) z[f * NA + a] -= W0[a][GROW] * s[f * NS + GROW];
        s[f * NS + GROW] = 0.0;
    }
    const double *s2 = s + n1 * NS, *z2 = z + n1 * NA;
    swfs_recon_learner *l12 = NULL, *l21 = NULL, *p1 = NULL, *p2 = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &l12));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &l21));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p1));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p2));
    assert_ok(swfs_recon_learner_add(l12, s, z, n1));
    assert_ok(swfs_recon_learner_add(l12, s2, z2, n2));
    assert_ok(swfs_recon_learner_add(l21, s2, z2, n2));
    assert_ok(swfs_recon_learner_add(l21, s, z, n1));
    assert_ok(swfs_recon_learner_add(p1, s, z, n1));
    assert_ok(swfs_recon_learner_add(p2, s2, z2, n2));
    swfs_recon *w12 = NULL, *w21 = NULL, *w2 = NULL;
    swfs_recon_learn_info i12, i21;
    assert_ok(swfs_recon_learner_solve(l12, SWFS_RECON_LEARN_RIDGE, &w12, &i12));
    assert_ok(swfs_recon_learner_solve(l21, SWFS_RECON_LEARN_RIDGE, &w21, &i21));
    assert_ok(swfs_recon_learner_solve(p2, SWFS_RECON_LEARN_RIDGE, &w2, NULL));
    assert_int_equal(i12.nslopes_seen, NS - 1);
    double d = 0, wm = 0, g = 0;
    for (size_t q = 0; q < NA * NS; q++) {
        d = fmax(d, fabs(w12->W[q] - w21->W[q]));
        wm = fmax(wm, fabs(w12->W[q]));
    }
    for (size_t a = 0; a < NA; a++) g += W0[a][GROW] / NA;
    printf("test_recon_learn: a slope live from the second file on: maps of either order %.2e apart (largest %.3g); "
           "its column %.4f for %.4f\n", d, wm, w12->W[GROW], W0[0][GROW] - g);
    /* S^T Z is summed in single precision, by SGEMM over the file's inputs: 6 of them, then 7,
     * or 7 both times, whose kernels may block the sums differently (wfs.h: a relative rounding
     * of about 4e-6); the maps agree to that, the misfits to 1e-5 of the truth's power */
    assert_true(d <= 2e-6 * wm);
    assert_true(fabs(i12.misfit_rms * i12.misfit_rms - i21.misfit_rms * i21.misfit_rms) <=
                1e-5 * i12.truth_rms * i12.truth_rms);
    assert_true(fabs(w12->W[GROW] - (W0[0][GROW] - g)) < 0.02);
    /* held out: file 1 (GROW silent) from the whole, and file 2 (GROW live) */
    double h2 = 0, t2 = 0;
    assert_ok(swfs_recon_learner_heldout(l12, p1, SWFS_RECON_LEARN_RIDGE, &h2, &t2));
    const double direct = misfit2(w2, s, z, n1);
    printf("test_recon_learn: file 1 held out %.6g, directly %.6g\n", h2, direct);
    assert_true(fabs(h2 - direct) <= 1e-5 * i12.truth_rms * i12.truth_rms);
    assert_ok(swfs_recon_learner_heldout(l21, p2, SWFS_RECON_LEARN_RIDGE, &h2, &t2));
    assert_true(h2 > 0 && isfinite(h2));
    /* a part with signal in a slope the whole never saw */
    assert_int_equal(swfs_recon_learner_heldout(p1, p2, SWFS_RECON_LEARN_RIDGE, &h2, &t2), SWFS_ERR_ARG);
    /* the space-time learner: stacked sums and lagged sums of the two files agree */
    const long lags[3] = {0, -2, 2};
    swfs_recon_learner *ls = NULL, *ll = NULL;
    assert_ok(swfs_recon_learner_new(3 * NS, NA, 1, &ls));
    assert_ok(swfs_recon_learner_new(3 * NS, NA, 1, &ll));
    double *st = malloc(n2 * 3 * NS * sizeof *st);
    const double *fs[2] = {s, s2}, *fz[2] = {z, z2};
    const size_t fn[2] = {n1, n2};
    for (int k = 0; k < 2; k++) {
        swfs_slopes_stack(fs[k], fn[k], NS, lags, 3, 0, fn[k], st);
        assert_ok(swfs_recon_learner_add(ls, st, fz[k], fn[k]));
        assert_ok(swfs_recon_learner_add_lagged(ll, fs[k], NS, fz[k], fn[k], lags, 3));
    }
    swfs_recon *ws = NULL, *wl = NULL;
    assert_ok(swfs_recon_learner_solve(ls, SWFS_RECON_LEARN_RIDGE, &ws, NULL));
    assert_ok(swfs_recon_learner_solve(ll, SWFS_RECON_LEARN_RIDGE, &wl, NULL));
    d = wm = 0;
    for (size_t q = 0; q < NA * 3 * NS; q++) {
        d = fmax(d, fabs(ws->W[q] - wl->W[q]));
        wm = fmax(wm, fabs(ws->W[q]));
    }
    printf("test_recon_learn: 3 lags, a slope live from the second file on: stacked and lagged %.2e apart\n", d);
    assert_true(d <= 1e-8 * wm);
    for (size_t a = 0; a < NA; a++)
        for (size_t k = 0; k < 3; k++) assert_true(wl->W[a * 3 * NS + k * NS + DEAD] == 0.0);
    /* another lag count after the first file's: refused */
    assert_int_equal(swfs_recon_learner_add(ll, s2, z2, 10), SWFS_ERR_SHAPE);
    /* a first file without any signal: empty sums, no map ("0 slopes with signal"); the
     * next file's slopes grow them from nothing to the map of that file alone */
    double *s0 = calloc(n1 * NS, sizeof *s0);
    swfs_recon_learner *le = NULL;
    swfs_recon *we = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &le));
    assert_ok(swfs_recon_learner_add(le, s0, z, n1));
    assert_int_equal(swfs_recon_learner_solve(le, SWFS_RECON_LEARN_RIDGE, &we, NULL), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "for 0 slopes with signal"));
    assert_ok(swfs_recon_learner_add(le, s2, z2, n2));
    assert_ok(swfs_recon_learner_solve(le, SWFS_RECON_LEARN_RIDGE, &we, NULL));
    d = 0;
    for (size_t q = 0; q < NA * NS; q++) d = fmax(d, fabs(we->W[q] - w2->W[q]));
    printf("test_recon_learn: sums grown from an empty first file: the second file's map to %.2e\n", d);
    assert_true(d <= 1e-10 * wm);
    swfs_recon_free(we);
    swfs_recon_learner_free(le);
    free(s0);
    free(st);
    swfs_recon_free(ws);
    swfs_recon_free(wl);
    swfs_recon_learner_free(ls);
    swfs_recon_learner_free(ll);
    swfs_recon_free(w12);
    swfs_recon_free(w21);
    swfs_recon_free(w2);
    swfs_recon_learner_free(l12);
    swfs_recon_learner_free(l21);
    swfs_recon_learner_free(p1);
    swfs_recon_learner_free(p2);
    free(s);
    free(z);
}

/* The cross product is summed in single precision over at most 4096 frames, then in double
 * (wfs.h): 20000 frames in one call (79 blocks, its float sums flushed five times) give the
 * map the same frames give in calls of 100 frames (flushed every call), within the
 * rounding's 1e-5, and the training misfit within 1e-5 of the truth's power; both maps are
 * W0 to the noise. */
static void test_learner_long_call(void **state)
{
    (void)state;
    const size_t n = 20000;
    double *s = NULL, *z = NULL;
    draw_problem(11, n, &s, &z);
    swfs_recon_learner *one = NULL, *many = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &one));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &many));
    assert_ok(swfs_recon_learner_add(one, s, z, n));
    for (size_t f = 0; f < n; f += 100) assert_ok(swfs_recon_learner_add(many, s + f * NS, z + f * NA, 100));
    swfs_recon *w1 = NULL, *w2 = NULL;
    swfs_recon_learn_info i1, i2;
    assert_ok(swfs_recon_learner_solve(one, SWFS_RECON_LEARN_RIDGE, &w1, &i1));
    assert_ok(swfs_recon_learner_solve(many, SWFS_RECON_LEARN_RIDGE, &w2, &i2));
    double d = 0, wmax = 0, e = 0;
    for (size_t a = 0; a < NA; a++)
        for (size_t i = 0; i < NS; i++) {
            double m = 0;
            for (size_t b = 0; b < NA; b++) m += W0[b][i] / NA;
            d = fmax(d, fabs(w1->W[a * NS + i] - w2->W[a * NS + i]));
            wmax = fmax(wmax, fabs(w1->W[a * NS + i]));
            e = fmax(e, fabs(w1->W[a * NS + i] - (W0[a][i] - m)));
        }
    printf("test_recon_learn: 20000 frames in one call and in calls of 100: maps %.2e apart (largest entry %.3g), "
           "%.4f from W0; misfit %.8g / %.8g\n", d, wmax, e, i1.misfit_rms, i2.misfit_rms);
    assert_true(d <= 1e-5 * wmax && e < 0.01);
    assert_true(fabs(i1.misfit_rms * i1.misfit_rms - i2.misfit_rms * i2.misfit_rms) <= 1e-5 * i1.truth_rms * i1.truth_rms);
    swfs_recon_free(w1);
    swfs_recon_free(w2);
    swfs_recon_learner_free(one);
    swfs_recon_learner_free(many);
    free(s);
    free(z);
}

/* Modal coefficients (remove_mean 0): the truth is taken as it is, so W0 comes back whole,
 * its column means included, where the actuator learner takes them out. */
static void test_learner_modal(void **state)
{
    (void)state;
    swfs_rng r;
    swfs_rng_seed(&r, 8);
    for (size_t a = 0; a < NA; a++)
        for (size_t i = 0; i < NS; i++) W0[a][i] = i == DEAD ? 0.0 : 1.0 + swfs_rng_normal(&r);
    const size_t n = 500;
    double *s = malloc(n * NS * sizeof *s), *z = malloc(n * NA * sizeof *z);
    make_frames(&r, n, s, z);
    /* no piston in modal coefficients: take out the one make_frames drew, keep the map's own mean */
    for (size_t f = 0; f < n; f++) {
        double zm = 0, wm = 0;
        for (size_t a = 0; a < NA; a++) {
            zm += z[f * NA + a] / NA;
            for (size_t i = 0; i < NS; i++) wm += W0[a][i] * s[f * NS + i] / NA;
        }
        for (size_t a = 0; a < NA; a++) z[f * NA + a] += wm - zm;
    }
    swfs_recon_learner *lm = NULL, *la = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 0, &lm));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &la));
    assert_ok(swfs_recon_learner_add(lm, s, z, n));
    assert_ok(swfs_recon_learner_add(la, s, z, n));
    swfs_recon *wm = NULL, *wa = NULL;
    assert_ok(swfs_recon_learner_solve(lm, SWFS_RECON_LEARN_RIDGE, &wm, NULL));
    assert_ok(swfs_recon_learner_solve(la, SWFS_RECON_LEARN_RIDGE, &wa, NULL));
    double em = 0, colmean = 0;
    for (size_t i = 0; i < NS; i++)
        for (size_t a = 0; a < NA; a++) {
            em = fmax(em, fabs(wm->W[a * NS + i] - W0[a][i]));
            colmean = fmax(colmean, fabs(wa->W[a * NS + i] - wm->W[a * NS + i]));
        }
    printf("test_recon_learn: modal map error %.4f; the actuator learner differs by up to %.3f (the means)\n", em,
           colmean);
    assert_true(em < 0.05);
    assert_true(colmean > 0.3);
    swfs_recon_free(wm);
    swfs_recon_free(wa);
    swfs_recon_learner_free(lm);
    swfs_recon_learner_free(la);
    free(s);
    free(z);
}

/* A space-time reconstructor's input: the lags parsed and checked, the slopes of frames
 * t + lags stacked with the frame indices clamped at the data's ends. */
static void test_lags(void **state)
{
    (void)state;
    long lags[SWFS_RECON_MAXLAGS];
    size_t n = 0;
    assert_ok(swfs_lags_parse("0,-2,3", lags, &n, "test"));
    assert_int_equal(n, 3);
    assert_true(lags[0] == 0 && lags[1] == -2 && lags[2] == 3);
    const char *bad[] = {"", "2,5", "0,4,4", "0,x", "0,,1", "0,1,2,3,4,5,6,7,8,9,10,11,12,13,14,15,16", "0,200000"};
    const char *why[] = {"no lags", "no lag 0", "twice", "not a list", "not a list", "more than 16", "within"};
    for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
        assert_int_not_equal(swfs_lags_parse(bad[k], lags, &n, "test"), 0);
        printf("test_recon_learn: \"%s\": %s\n", bad[k], swfs_last_error());
        assert_non_null(strstr(swfs_last_error(), why[k]));
    }
    /* 5 frames of 2 slopes, frame f = (10 f, 10 f + 1) */
    double s[10], out[5 * 3 * 2];
    for (int f = 0; f < 5; f++) { s[2 * f] = 10 * f; s[2 * f + 1] = 10 * f + 1; }
    const long lg[3] = {0, -2, 3};
    swfs_slopes_stack(s, 5, 2, lg, 3, 1, 3, out); /* frames 1, 2, 3 */
    const int want[3][3] = {{1, 0, 4}, {2, 0, 4}, {3, 1, 4}}; /* frame index per lag, clamped to 0..4 */
    for (int t = 0; t < 3; t++)
        for (int k = 0; k < 3; k++) {
            assert_true(out[(t * 3 + k) * 2] == 10.0 * want[t][k]);
            assert_true(out[(t * 3 + k) * 2 + 1] == 10.0 * want[t][k] + 1);
        }
}

/* swfs_recon_learner_add_lagged gives the sums of the stacked input (swfs_slopes_stack, then
 * add): the same map and training misfit to rounding, for lags in any order, a lag set that
 * repeats lag differences (0,-3,3,-6,6), files shorter than the lags' span (every frame
 * clamped) and several files into one learner. Its lag-0 block alone
 * (swfs_recon_learner_solve_lag) is the per-frame map of a learner given the frames
 * unstacked. */
static void test_learner_lagged(void **state)
{
    (void)state;
    enum { S0 = 6, NT = 4 };
    const long sets[4][5] = {{0, -2, 3}, {0, -3, 3, -6, 6}, {5, 0}, {0, -3, 3}};
    const size_t nls[4] = {3, 5, 2, 3};
    const size_t lens[4][2] = {{300, 77}, {400, 13}, {250, 250}, {5, 60}};
    swfs_rng r;
    swfs_rng_seed(&r, 21);
    for (int k = 0; k < 4; k++) {
        const size_t nl = nls[k], ns = S0 * nl;
        swfs_recon_learner *ls = NULL, *ll = NULL, *l1 = NULL;
        assert_ok(swfs_recon_learner_new(ns, NT, 1, &ls));
        assert_ok(swfs_recon_learner_new(ns, NT, 1, &ll));
        assert_ok(swfs_recon_learner_new(S0, NT, 1, &l1));
        for (int file = 0; file < 2; file++) {
            const size_t n = lens[k][file];
            double *s = malloc(n * S0 * sizeof *s), *z = malloc(n * NT * sizeof *z), *st = malloc(n * ns * sizeof *st);
            /* slopes correlated in time (a random walk pulled back), truth linear in them */
            for (size_t i = 0; i < S0; i++) s[i] = swfs_rng_normal(&r);
            for (size_t f = 1; f < n; f++)
                for (size_t i = 0; i < S0; i++) s[f * S0 + i] = 0.9 * s[(f - 1) * S0 + i] + swfs_rng_normal(&r);
            for (size_t f = 0; f < n; f++)
                for (size_t a = 0; a < NT; a++) {
                    double v = 0.1 * swfs_rng_normal(&r);
                    for (size_t i = 0; i < S0; i++) v += ((double)((a + 1) * (i + 2) % 5) - 2.0) * s[f * S0 + i];
                    z[f * NT + a] = v;
                }
            swfs_slopes_stack(s, n, S0, sets[k], nl, 0, n, st);
            assert_ok(swfs_recon_learner_add(ls, st, z, n));
            assert_ok(swfs_recon_learner_add_lagged(ll, s, S0, z, n, sets[k], nl));
            assert_ok(swfs_recon_learner_add(l1, s, z, n));
            free(s);
            free(z);
            free(st);
        }
        assert_int_equal(swfs_recon_learner_frames(ls), swfs_recon_learner_frames(ll));
        swfs_recon *ws = NULL, *wl = NULL;
        swfs_recon_learn_info is, il;
        assert_ok(swfs_recon_learner_solve(ls, SWFS_RECON_LEARN_RIDGE, &ws, &is));
        assert_ok(swfs_recon_learner_solve(ll, SWFS_RECON_LEARN_RIDGE, &wl, &il));
        double dmax = 0, wmax = 0;
        for (size_t q = 0; q < ns * NT; q++) {
            dmax = fmax(dmax, fabs(ws->W[q] - wl->W[q]));
            wmax = fmax(wmax, fabs(ws->W[q]));
        }
        printf("test_recon_learn: %zu lags: stacked and lagged sums give maps %.2e apart (largest entry %.3g), misfit "
               "%.6g / %.6g\n", nl, dmax, wmax, is.misfit_rms, il.misfit_rms);
        assert_true(dmax <= 1e-8 * wmax);
        assert_true(fabs(is.misfit_rms - il.misfit_rms) <= 1e-8 * is.misfit_rms);
        assert_int_equal(is.nslopes_seen, il.nslopes_seen);
        /* the lag-0 block alone against the per-frame learner */
        size_t k0 = 0;
        while (sets[k][k0] != 0) k0++;
        swfs_recon *w0 = NULL, *w1 = NULL;
        swfs_recon_learn_info i0, i1;
        assert_ok(swfs_recon_learner_solve_lag(ll, k0, SWFS_RECON_LEARN_RIDGE, &w0, &i0));
        assert_ok(swfs_recon_learner_solve(l1, SWFS_RECON_LEARN_RIDGE, &w1, &i1));
        assert_int_equal(w0->nslopes, S0);
        assert_int_equal(w0->nact, NT);
        double d0 = 0, w1max = 0;
        for (size_t q = 0; q < S0 * NT; q++) {
            d0 = fmax(d0, fabs(w0->W[q] - w1->W[q]));
            w1max = fmax(w1max, fabs(w1->W[q]));
        }
        printf("test_recon_learn: %zu lags: the lag-0 block's map %.2e from the per-frame learner's (largest entry "
               "%.3g), misfit %.6g / %.6g (all lags %.6g)\n", nl, d0, w1max, i0.misfit_rms, i1.misfit_rms, il.misfit_rms);
        /* the same sums, but S^T Z in single precision over a block of other widths (wfs.h) */
        assert_true(d0 <= 2e-6 * w1max);
        assert_true(fabs(i0.misfit_rms * i0.misfit_rms - i1.misfit_rms * i1.misfit_rms) <=
                    1e-5 * i1.truth_rms * i1.truth_rms);
        assert_int_equal(i0.nslopes_seen, i1.nslopes_seen);
        assert_int_equal(i0.nframes, i1.nframes);
        swfs_recon_free(w0);
        swfs_recon_free(w1);
        assert_int_not_equal(swfs_recon_learner_solve_lag(ll, nl, SWFS_RECON_LEARN_RIDGE, &w0, NULL), 0);
        assert_null(w0);
        swfs_recon_free(ws);
        swfs_recon_free(wl);
        swfs_recon_learner_free(ls);
        swfs_recon_learner_free(ll);
        swfs_recon_learner_free(l1);
    }
    /* a width that is not the learner's */
    swfs_recon_learner *l = NULL;
    double s1[2 * S0] = {0}, z1[2 * NT] = {0};
    assert_ok(swfs_recon_learner_new(S0 * 3, NT, 1, &l));
    assert_int_not_equal(swfs_recon_learner_add_lagged(l, s1, S0, z1, 2, sets[2], 2), 0);
    assert_non_null(strstr(swfs_last_error(), "the learner takes 18 inputs"));
    swfs_recon_learner_free(l);
}

/* Merged sums are the sums of both parts' frames: a learner given file 1 (slope GROW silent)
 * merged with one given file 2 solves to the map of a learner given both files, in either
 * order, and into an empty learner; an empty part adds nothing; other shapes are refused. */
static void test_learner_merge(void **state)
{
    (void)state;
    const size_t n1 = 300, n2 = 400;
    double *s = NULL, *z = NULL;
    draw_problem(11, n1 + n2, &s, &z);
    for (size_t f = 0; f < n1; f++) {
        for (size_t a = 0; a < NA; a++) z[f * NA + a] -= W0[a][GROW] * s[f * NS + GROW];
        s[f * NS + GROW] = 0.0;
    }
    swfs_recon_learner *all = NULL, *p1 = NULL, *p2 = NULL, *m12 = NULL, *m21 = NULL, *e = NULL;
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &all));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p1));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &p2));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &m12));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &m21));
    assert_ok(swfs_recon_learner_new(NS, NA, 1, &e));
    assert_ok(swfs_recon_learner_add(all, s, z, n1));
    assert_ok(swfs_recon_learner_add(all, s + n1 * NS, z + n1 * NA, n2));
    assert_ok(swfs_recon_learner_add(p1, s, z, n1));
    assert_ok(swfs_recon_learner_add(p2, s + n1 * NS, z + n1 * NA, n2));
    assert_ok(swfs_recon_learner_merge(m12, p1)); /* into an empty learner: p1's layout */
    assert_ok(swfs_recon_learner_merge(m12, e));  /* nothing */
    assert_ok(swfs_recon_learner_merge(m12, p2)); /* grows by GROW */
    assert_ok(swfs_recon_learner_merge(m21, p2));
    assert_ok(swfs_recon_learner_merge(m21, p1)); /* p1's inputs a subset of m21's */
    assert_int_equal(swfs_recon_learner_frames(m12), n1 + n2);
    swfs_recon *wa = NULL, *w12 = NULL, *w21 = NULL;
    swfs_recon_learn_info ia, i12, i21;
    assert_ok(swfs_recon_learner_solve(all, SWFS_RECON_LEARN_RIDGE, &wa, &ia));
    assert_ok(swfs_recon_learner_solve(m12, SWFS_RECON_LEARN_RIDGE, &w12, &i12));
    assert_ok(swfs_recon_learner_solve(m21, SWFS_RECON_LEARN_RIDGE, &w21, &i21));
    double d = 0, wm = 0;
    for (size_t q = 0; q < NA * NS; q++) {
        d = fmax(d, fmax(fabs(w12->W[q] - wa->W[q]), fabs(w21->W[q] - wa->W[q])));
        wm = fmax(wm, fabs(wa->W[q]));
    }
    printf("test_recon_learn: merged sums: maps %.2e from the learner given both files (largest %.3g); misfit %.6g / "
           "%.6g / %.6g\n", d, wm, i12.misfit_rms, i21.misfit_rms, ia.misfit_rms);
    assert_true(d <= 1e-10 * wm);
    assert_int_equal(i12.nslopes_seen, NS - 1);
    assert_close(i12.misfit_rms, ia.misfit_rms, 1e-9);
    assert_close(i21.truth_rms, ia.truth_rms, 1e-12);
    /* held out from merged sums: as from the learner given both */
    double h1 = 0, h2 = 0, t1 = 0, t2 = 0;
    assert_ok(swfs_recon_learner_heldout(all, p1, SWFS_RECON_LEARN_RIDGE, &h1, &t1));
    assert_ok(swfs_recon_learner_heldout(m21, p1, SWFS_RECON_LEARN_RIDGE, &h2, &t2));
    assert_close(h2, h1, 1e-9 * t1);
    /* other shapes */
    swfs_recon_learner *o = NULL;
    assert_ok(swfs_recon_learner_new(NS + 1, NA, 1, &o));
    assert_int_equal(swfs_recon_learner_merge(m12, o), SWFS_ERR_SHAPE);
    swfs_recon_learner_free(o);
    swfs_recon_free(wa);
    swfs_recon_free(w12);
    swfs_recon_free(w21);
    swfs_recon_learner_free(all);
    swfs_recon_learner_free(p1);
    swfs_recon_learner_free(p2);
    swfs_recon_learner_free(m12);
    swfs_recon_learner_free(m21);
    swfs_recon_learner_free(e);
    free(s);
    free(z);
}

/* The learning curve (swfs_learn_run with curve): CP inputs, CA outputs, truth = M s + unit
 * noise, NDIR folders of CF frames. With independent frames ordinary least squares misses
 * frames it was not learned on by 1 + p / (n - p - 1) times the noise's variance: through n =
 * N/2 and 3N/4 that is a + b / n with a = 1.00 and b = 44.1 (p = 40, N = 1200), so b / a
 * about 44 and 10 b / a = 441 frames for an excess of 0.1. The same frames each held for
 * HOLD frames (the same slopes and noise: frames correlated in time) are worth 1 / HOLD of
 * theirs: b / a several times larger, and more frames asked for than N. The data sets' sums
 * and the curve's checks run several at once (o.threads 0: the CPUs) and one at a time
 * (o.threads 1) to the same curve and map, bit for bit. */
#define CP 40
#define CA 50
#define NDIR 8
#define CF 150
#define HOLD 4

static void write_set(const char *dir, const double *s, const double *z, size_t n)
{
    mkdir(dir, 0777);
    char f[1100];
    for (int t = 0; t < 2; t++) {
        snprintf(f, sizeof f, "%s/%s_000.fits", dir, t ? "truewf" : "slopes");
        swfs_real a = {t ? CA : CP, n, 1, (double *)(t ? z : s)};
        swfs_fits_out *o = NULL;
        assert_ok(swfs_fits_out_create(&o, f));
        assert_ok(swfs_fits_out_real(o, NULL, &a, -64));
        assert_ok(swfs_fits_out_commit(o));
    }
}

static void curve_of(int hold, int threads, swfs_learn_run_result *r)
{
    static double M[CA][CP];
    swfs_rng g;
    swfs_rng_seed(&g, 77);
    for (size_t a = 0; a < CA; a++)
        for (size_t i = 0; i < CP; i++) M[a][i] = swfs_rng_normal(&g) / sqrt(CP);
    double *s = malloc(CF * CP * sizeof *s), *z = malloc(CF * CA * sizeof *z);
    assert_non_null(s);
    assert_non_null(z);
    char names[NDIR][64];
    const char *dirs[NDIR];
    for (int d = 0; d < NDIR; d++) {
        for (size_t f = 0; f < CF; f++) {
            double *sf = s + f * CP, *zf = z + f * CA;
            if (f % (size_t)hold) { /* held: the frame before's slopes and noise */
                memcpy(sf, sf - CP, CP * sizeof *sf);
                memcpy(zf, zf - CA, CA * sizeof *zf);
                continue;
            }
            for (size_t i = 0; i < CP; i++) sf[i] = swfs_rng_normal(&g);
            for (size_t a = 0; a < CA; a++) {
                zf[a] = swfs_rng_normal(&g);
                for (size_t i = 0; i < CP; i++) zf[a] += M[a][i] * sf[i];
            }
        }
        snprintf(names[d], sizeof names[d], "curve_h%d_%d", hold, d);
        dirs[d] = test_path(names[d]);
        char keep[1024];
        snprintf(keep, sizeof keep, "%s", dirs[d]);
        write_set(keep, s, z, CF);
    }
    for (int d = 0; d < NDIR; d++) dirs[d] = strdup(test_path(names[d]));
    swfs_learn_run_options o;
    swfs_learn_run_options_default(&o);
    o.dirs = dirs;
    o.ndirs = NDIR;
    o.modal = 1; /* the truth as given (no piston to remove) */
    o.no_heldout = 1;
    o.curve = 1;
    o.threads = threads;
    char out[64];
    snprintf(out, sizeof out, "curve_h%d_t%d.fits", hold, threads);
    o.out = test_path(out);
    assert_ok(swfs_learn_run(&o, r));
    for (int d = 0; d < NDIR; d++) free((void *)dirs[d]);
    free(s);
    free(z);
}

static void test_learning_curve(void **state)
{
    (void)state;
    swfs_learn_run_result r1, r4, r4s;
    curve_of(1, 0, &r1);
    curve_of(HOLD, 0, &r4);
    /* the parts' sums and the six checks one at a time: the same curve and map, to the bit */
    curve_of(HOLD, 1, &r4s);
    assert_true(r4s.curve_m2[0] == r4.curve_m2[0] && r4s.curve_m2[1] == r4.curve_m2[1]);
    assert_true(r4s.curve_a == r4.curve_a && r4s.curve_b == r4.curve_b && r4s.curve_frames == r4.curve_frames);
    assert_true(r4s.info.misfit_rms == r4.info.misfit_rms && r4s.info.nframes == r4.info.nframes);
    swfs_real *w0 = NULL, *w1 = NULL;
    assert_ok(swfs_fits_read_real(test_path("curve_h4_t0.fits"), NULL, &w0, NULL));
    assert_ok(swfs_fits_read_real(test_path("curve_h4_t1.fits"), NULL, &w1, NULL));
    assert_int_equal(w0->nx * w0->ny * w0->nz, w1->nx * w1->ny * w1->nz);
    assert_memory_equal(w0->data, w1->data, w0->nx * w0->ny * w0->nz * sizeof *w0->data);
    swfs_real_free(w0);
    swfs_real_free(w1);
    for (int k = 0; k < 2; k++) {
        const swfs_learn_run_result *r = k ? &r4 : &r1;
        printf("test_recon_learn: learning curve, frames held %d: misfit^2 %.4f at %zu, %.4f at %zu frames (fall's "
               "standard error %.4f); a %.4f, b %.1f (b/a %.1f); excess at %zu frames %.3f; %zu frames for 0.1\n",
               k ? HOLD : 1, r->curve_m2[0], r->curve_n[0], r->curve_m2[1], r->curve_n[1], r->curve_fall_se, r->curve_a,
               r->curve_b, r->curve_b / r->curve_a, r->info.nframes, r->curve_excess, r->curve_frames);
    }
    assert_int_equal(r1.curve_n[0], NDIR * CF / 2);
    assert_int_equal(r1.curve_n[1], NDIR * CF * 3 / 4);
    assert_true(r1.curve_m2[0] > r1.curve_m2[1]);
    assert_close(r1.curve_a, 1.0, 0.1);
    assert_true(r1.curve_b / r1.curve_a > 25 && r1.curve_b / r1.curve_a < 70);
    assert_true(r1.curve_frames < (size_t)(NDIR * CF)); /* enough already */
    assert_true(isfinite(r1.curve_fall_se) && r1.curve_fall_se > 0);
    assert_true(swfs_learn_curve_falls(&r1)); /* independent frames: the fall beyond the parts' scatter */
    assert_close(r1.curve_excess, r1.curve_b / (r1.curve_a * NDIR * CF), 1e-12);
    /* held frames: worth a quarter each */
    assert_true(r4.curve_b / r4.curve_a > 3 * r1.curve_b / r1.curve_a);
    assert_true(r4.curve_frames > (size_t)(NDIR * CF));
    /* the map's header carries it */
    swfs_fits_in *f = NULL;
    double v = 0;
    assert_ok(swfs_fits_in_open(&f, test_path("curve_h4_t0.fits"), NULL));
    assert_ok(swfs_fits_in_key_double(f, "LRNCEXC", &v));
    assert_close(v, r4.curve_excess, 1e-6 * r4.curve_excess);
    swfs_fits_in_close(f);
    /* fewer than 4 data sets: no curve, no error */
    swfs_learn_run_options o;
    swfs_learn_run_options_default(&o);
    const char *three[3] = {test_path("curve_h1_0"), test_path("curve_h1_1"), test_path("curve_h1_2")};
    o.dirs = three;
    o.ndirs = 3;
    o.modal = 1;
    o.no_heldout = 1;
    o.curve = 1;
    o.out = test_path("curve_3.fits");
    swfs_learn_run_result r3;
    assert_ok(swfs_learn_run(&o, &r3));
    assert_int_equal(r3.curve_n[0], 0);
    assert_true(isnan(r3.curve_excess));
}

/* Teach's profile misfit (run_internal.h swfs_teach_profile_misfit_) on 300 modes of
 * made-up variances with a ripple of 0.05 dex (the loops' and the observation's seeds):
 * - an observation of a modal loop whose modes are not the DM's (its variances half a decade
 *   up at mode 150, rising to the turbulence's by 200, as the foreign 20 x 20 of 200 modes in
 *   docs/telemetry.md) is nearer a DM-mode loop of 152 modes (a step at 152) than a zonal loop
 *   (flat, a decade below the observation's upper modes): 0.18 against 0.48, where the upper
 *   half's own mean took the zonal loop for the nearer (0.156 against 0.162);
 * - a zonal observation (flat) is nearer the zonal loop than a modal one;
 * - a loop's whole profile scaled (its layers' strength) leaves the misfit as it was. */
static void test_teach_profile_misfit(void **state)
{
    (void)state;
    enum { N = 300 };
    double obs[N], modal[N], zonal[N], flat[N], modal2[N];
    for (size_t j = 0; j < N; j++) {
        const double rip = 0.05 * sin(0.7 * (double)j), rip2 = 0.05 * cos(1.3 * (double)j);
        const double up = j < 150 ? 0 : j < 200 ? 0.5 + 0.5 * (double)(j - 150) / 50.0 : 1.0;
        obs[j] = pow(10.0, -13.5 + up + rip); /* half a decade up at 150, a decade by 200 */
        modal[j] = pow(10.0, (j < 152 ? -13.5 : -12.4) + rip2);
        zonal[j] = pow(10.0, -13.6 + rip2);
        flat[j] = pow(10.0, -13.5 + rip);
        modal2[j] = 2 * modal[j];
    }
    const double mm = swfs_teach_profile_misfit_(modal, N, obs, N), mz = swfs_teach_profile_misfit_(zonal, N, obs, N);
    assert_true(mm < mz);
    assert_true(mz > 0.3);
    /* the upper half's own mean: the zonal loop's flat profile looked nearer */
    double s[2] = {0}, s2[2] = {0};
    const double *lp[2] = {modal, zonal};
    for (size_t k = 0; k < 2; k++) {
        for (size_t j = N / 2; j < N; j++) {
            const double d = log10(lp[k][j] / obs[j]);
            s[k] += d;
            s2[k] += d * d;
        }
        s[k] /= N / 2;
        s2[k] = sqrt(s2[k] / (N / 2) - s[k] * s[k]);
    }
    assert_true(s2[1] < s2[0]);
    assert_true(swfs_teach_profile_misfit_(zonal, N, flat, N) < 0.1);
    assert_true(swfs_teach_profile_misfit_(modal, N, flat, N) > 0.4);
    assert_float_equal(swfs_teach_profile_misfit_(modal2, N, obs, N), mm, 1e-12);
    assert_true(isinf(swfs_teach_profile_misfit_(modal, 2, obs, 2))); /* one mode to compare */
    assert_true(!isinf(swfs_teach_profile_misfit_(modal, 4, obs, 4)));
}

/* Teach's rule for more loops after a learning curve (run_internal.h swfs_teach_more_loops_):
 * a curve that asks for more frames than the loops hold gets as many loops as it asks (at
 * most the budget); one measured that does not fall cannot tell, and doubles them once; no
 * curve, or one that asks for nothing, adds none. */
static void test_teach_more_loops(void **state)
{
    (void)state;
    swfs_learn_run_result lr;
    memset(&lr, 0, sizeof lr);
    lr.info.nframes = 12000; /* 12 loops of 1000 frames */
    lr.curve_fall_se = NAN;  /* the parts' scatter not measured: the fall's sign alone */
    int doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 12); /* no curve */
    lr.curve_n[0] = 6000; lr.curve_n[1] = 9000;
    lr.curve_b = 1.0; lr.curve_a = 1.0; lr.curve_frames = 30500;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 31);
    assert_int_equal(doubled, 0);
    lr.curve_frames = 500000;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 48); /* the budget */
    lr.curve_frames = 9000;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 12); /* enough */
    lr.curve_b = -0.1; lr.curve_frames = 0; /* rose: the held-out parts' scatter */
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 24);
    assert_int_equal(doubled, 1);
    lr.info.nframes = 24000;
    assert_int_equal(swfs_teach_more_loops_(&lr, 24, 48, &doubled), 24); /* flat again: no more */
    doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 30, 48, &doubled), 48); /* doubling capped */
    assert_int_equal(swfs_teach_more_loops_(&lr, 48, 48, &doubled), 48); /* at the budget */
    /* a fall within twice its standard error from the parts' scatter: it cannot tell either,
     * even where its a + b / n asks for nothing more (a fall of 0.23 % as a 14 x 14 zonal
     * observation's first loops gave) */
    lr.info.nframes = 12000;
    lr.curve_m2[0] = 1.0023; lr.curve_m2[1] = 1.0;
    lr.curve_b = 0.0023 / (1.0 / 6000 - 1.0 / 9000); lr.curve_a = 1.0 - lr.curve_b / 9000; lr.curve_frames = 420;
    lr.curve_fall_se = 0.004;
    assert_false(swfs_learn_curve_falls(&lr));
    doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 24);
    assert_int_equal(doubled, 1);
    lr.curve_fall_se = 0.001; /* beyond twice it: enough, as its curve says */
    assert_true(swfs_learn_curve_falls(&lr));
    doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 12);
    assert_int_equal(doubled, 0);
    assert_false(swfs_teach_curve_unbounded_(&lr)); /* a + b / n with a > 0: a bound */
    /* the curve of a 16 x 16 foreign observation's 22 asked-for loops: 239.4 -> 193.2 nm from
     * 18 700 to 27 973 frames, steeper than any a + b / n with a > 0, its fall 10 times its
     * standard error: no bound, and the loops go on to the budget */
    lr.info.nframes = 37400;
    lr.curve_n[0] = 18700; lr.curve_n[1] = 27973;
    lr.curve_m2[0] = 239.4 * 239.4; lr.curve_m2[1] = 193.2 * 193.2;
    lr.curve_b = (lr.curve_m2[0] - lr.curve_m2[1]) / (1.0 / 18700 - 1.0 / 27973);
    lr.curve_a = lr.curve_m2[1] - lr.curve_b / 27973;
    lr.curve_frames = SIZE_MAX;
    lr.curve_fall_se = 2000.0;
    assert_true(lr.curve_a < 0);
    assert_true(swfs_teach_curve_unbounded_(&lr));
    doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 22, 48, &doubled), 48);
    lr.curve_fall_se = 10000.0; /* the same fall within twice its scatter: it cannot tell */
    assert_false(swfs_teach_curve_unbounded_(&lr));
    lr.curve_n[0] = 0; /* no curve */
    assert_false(swfs_teach_curve_unbounded_(&lr));
}

/* teach rule 2026-12-08: the first loops' curve does not end teach, nor ask for fewer than
 * twice them. The first curve of a foreign 14 x 14 observation (12 loops of 1267 frames, the
 * 3-frame delay's `d3` of docs/telemetry.md): 246.1 -> 242.5 nm from 7602 to 11403 frames, 2.6
 * standard errors of its parts, the map 4.8 % above unlimited frames: enough by its own
 * a + b / n, doubled by the rule; the curve over the 24 then decides as any curve. */
static void test_teach_next_loops(void **state)
{
    (void)state;
    swfs_learn_run_result lr;
    memset(&lr, 0, sizeof lr);
    lr.info.nframes = 15204;
    lr.curve_n[0] = 7602; lr.curve_n[1] = 11403;
    lr.curve_m2[0] = 246.1 * 246.1; lr.curve_m2[1] = 242.5 * 242.5;
    lr.curve_b = (lr.curve_m2[0] - lr.curve_m2[1]) / (1.0 / 7602 - 1.0 / 11403);
    lr.curve_a = lr.curve_m2[1] - lr.curve_b / 11403;
    lr.curve_frames = 7226;
    lr.curve_fall_se = (lr.curve_m2[0] - lr.curve_m2[1]) / 2.6;
    assert_true(swfs_learn_curve_falls(&lr));
    assert_true(fabs(lr.curve_b / (lr.curve_a * 15204) - 0.048) < 0.002); /* the excess it printed */
    int doubled = 0;
    assert_int_equal(swfs_teach_more_loops_(&lr, 12, 48, &doubled), 12); /* its own rule: enough */
    assert_int_equal(doubled, 0);
    assert_int_equal(swfs_teach_next_loops_(&lr, 12, 12, 48, &doubled), 24); /* doubled */
    assert_int_equal(doubled, 1);
    doubled = 0; /* asking for a few more than the first loops (18): twice them all the same */
    lr.curve_frames = 22806;
    assert_int_equal(swfs_teach_next_loops_(&lr, 12, 12, 48, &doubled), 24);
    assert_int_equal(doubled, 1);
    doubled = 0; /* asking for more than twice them (36): as the curve asks, not doubled */
    lr.curve_frames = 45612;
    assert_int_equal(swfs_teach_next_loops_(&lr, 12, 12, 48, &doubled), 36);
    assert_int_equal(doubled, 0);
    doubled = 0; /* the budget below twice the first loops: the budget */
    lr.curve_frames = 7226;
    assert_int_equal(swfs_teach_next_loops_(&lr, 12, 12, 16, &doubled), 16);
    assert_int_equal(swfs_teach_next_loops_(&lr, 12, 12, 12, &doubled), 12); /* no budget: no more */
    doubled = 0; /* a later curve (over 24 of 12 first loops) ends teach as its own rule says */
    lr.info.nframes = 30408;
    assert_int_equal(swfs_teach_next_loops_(&lr, 24, 12, 48, &doubled), 24);
    assert_int_equal(doubled, 0);
    doubled = 0; /* too few first loops for a curve (none measured): no more, as before */
    lr.info.nframes = 2534;
    lr.curve_n[0] = 0; lr.curve_frames = 0;
    assert_int_equal(swfs_teach_next_loops_(&lr, 2, 2, 8, &doubled), 2);
    assert_int_equal(doubled, 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_learner), cmocka_unit_test(test_learner_long_call),
                                       cmocka_unit_test(test_learner_prior),
                                       cmocka_unit_test(test_learner_solve_without),
                                       cmocka_unit_test(test_learner_heldout_split),
                                       cmocka_unit_test(test_learner_grows),
                                       cmocka_unit_test(test_learner_modal),
                                       cmocka_unit_test(test_lags), cmocka_unit_test(test_learner_lagged),
                                       cmocka_unit_test(test_learner_merge), cmocka_unit_test(test_learning_curve),
                                       cmocka_unit_test(test_teach_more_loops),
                                       cmocka_unit_test(test_teach_next_loops),
                                       cmocka_unit_test(test_teach_profile_misfit)};
    return cmocka_run_group_tests(tests, NULL, NULL);
}

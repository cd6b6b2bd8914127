/* Accumulator checkpoints: exact FITS round trip, and merged partial results (through
 * files) equal to a single pass over all frames, down to the estimated halo. */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/array.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NX 7
#define NY 5
#define NP (NX * NY)

static swfs_geom test_geom(void)
{
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 1.6e-6;
    g.teldiam = 6.5;
    g.pixscale = 0.25;
    g.pupdx = 0.04;
    g.pupn = 163;
    return g;
}

/* Frame k of a synthetic data set: I = |Psi + g psi|^2 + noise with a known halo; pixel 3
 * is non-finite in frames 40..59 (so one chunk has no data there at all). */
static void frame(size_t k, double *sci, double complex *psi)
{
    swfs_rng r;
    swfs_rng_seed2(&r, 99, k);
    for (size_t p = 0; p < NP; p++) {
        const double complex psi0 = (0.3 + 0.05 * (double)(p % 4)) * cexp(I * 0.7 * (double)p);
        psi[p] = 0.6 * swfs_rng_cnormal_value(&r) + 0.2; /* a non-zero mean: removed exactly (eq:zeroMean) */
        const double complex tot = psi0 + 0.9 * psi[p];
        sci[p] = 1e3 * (creal(tot) * creal(tot) + cimag(tot) * cimag(tot)) + swfs_rng_normal(&r);
        if (p == 3 && k >= 40 && k < 60) sci[p] = NAN;
    }
}

static void feed(swfs_accum *a, size_t k0, size_t k1)
{
    double sci[NP];
    double complex psi[NP];
    for (size_t k = k0; k < k1; k++) {
        frame(k, sci, psi);
        assert_ok(swfs_accum_add(a, sci, psi));
    }
}

static void test_round_trip(void **state)
{
    (void)state;
    swfs_accum *a = swfs_accum_create(NX, NY), *b = NULL;
    assert_non_null(a);
    feed(a, 30, 75);
    swfs_geom g = test_geom(), g2;
    const char *prov[] = {"test_checkpoint round trip"};
    const char *path = test_path("ckpt_roundtrip.fits");
    assert_ok(swfs_accum_save(a, path, &g, prov, 1));
    assert_ok(swfs_accum_load(path, &b, &g2));
    assert_int_equal(b->nx, NX);
    assert_int_equal(b->ny, NY);
    assert_int_equal(b->frames, 45);
    assert_int_equal(b->skipped, 20);
    assert_int_equal(b->frames, a->frames);
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) assert_memory_equal(a->f[k], b->f[k], NP * sizeof(double));
    /* The regression statistics travel too (REGSTATE), bit for bit. */
    assert_true(swfs_accum_has_regress(b));
    assert_int_equal(b->reg->frames, 45);
    assert_memory_equal(a->reg->state, b->reg->state, NP * SWFS_REGRESS_NSTATE * sizeof(double));
    assert_true(g2.wavelen == g.wavelen && g2.pixscale == g.pixscale && g2.pupn == g.pupn);
    assert_true(isnan(g2.obscur)); /* not recorded stays missing */
    swfs_accum_free(a);
    swfs_accum_free(b);
}

/* Three chunks saved separately and merged through files == one pass over all frames. */
static void test_merge_equals_single_pass(void **state)
{
    (void)state;
    const size_t cuts[4] = {0, 40, 60, 137}; /* the middle chunk has no data at pixel 3 */
    swfs_accum *all = swfs_accum_create(NX, NY);
    assert_non_null(all);
    feed(all, 0, cuts[3]);
    swfs_geom g = test_geom();
    const char *paths[3] = {test_path("ckpt_part0.fits"), test_path("ckpt_part1.fits"), test_path("ckpt_part2.fits")};
    char keep[3][1024];
    for (int c = 0; c < 3; c++) {
        swfs_accum *part = swfs_accum_create(NX, NY);
        assert_non_null(part);
        feed(part, cuts[c], cuts[c + 1]);
        strcpy(keep[c], paths[c]);
        /* Only the first part records the pupil sampling: the merge takes the union. */
        swfs_geom gc = g;
        if (c) gc.pupn = 0;
        assert_ok(swfs_accum_save(part, keep[c], &gc, NULL, 0));
        swfs_accum_free(part);
    }
    /* Merge in a different order than time: the result does not depend on it. */
    const char *order[3] = {keep[2], keep[0], keep[1]};
    swfs_accum *m = NULL;
    swfs_geom gm;
    assert_ok(swfs_accum_merge_files(order, 3, &m, &gm));
    assert_int_equal(gm.pupn, 163);
    assert_int_equal(m->frames, all->frames);
    assert_int_equal(m->skipped, all->skipped);
    assert_int_equal((int)m->f[SWFS_ACC_N][3], (int)cuts[3] - 20);
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++)
        for (size_t p = 0; p < NP; p++) {
            const double a = all->f[k][p], b = m->f[k][p];
            assert_close(b, a, 1e-11 * fmax(1.0, fabs(a)));
        }
    /* The regression statistics merge to the single pass too (after both are re-centred on
     * their own means, the merged centres being those of the first file merged). */
    assert_true(swfs_accum_has_regress(m));
    assert_ok(swfs_regress_recenter(all->reg, NULL));
    assert_ok(swfs_regress_recenter(m->reg, NULL));
    for (size_t k = 0; k < (size_t)NP * SWFS_REGRESS_NSTATE; k++) {
        const double a = all->reg->state[k], b = m->reg->state[k];
        assert_close(b, a, 1e-10 * fmax(1.0, fabs(a)));
    }
    /* And the estimator sees the same data set (eq:TheAnswer, eq:scale-factor). */
    swfs_noise noise = {1.0, 0.0};
    swfs_halo *h1 = NULL, *h2 = NULL;
    assert_ok(swfs_estimate(all, &noise, NULL, &h1));
    assert_ok(swfs_estimate(m, &noise, NULL, &h2));
    assert_int_equal(h1->n_valid, h2->n_valid);
    double emax = 0, hmax = 0;
    for (size_t p = 0; p < NP; p++) {
        emax = fmax(emax, cabs(h1->halo->data[p] - h2->halo->data[p]));
        hmax = fmax(hmax, cabs(h1->halo->data[p]));
    }
    assert_true(emax <= 1e-10 * hmax);
    swfs_halo_free(h1);
    swfs_halo_free(h2);
    swfs_accum_free(m);
    swfs_accum_free(all);
}

/* The flat state (for MPI or shared memory): export/import is exact, merging flat states in
 * place equals merging accumulators, and an impossible state is refused. */
static void test_flat_state(void **state)
{
    (void)state;
    swfs_accum *a = swfs_accum_create(NX, NY), *b = swfs_accum_create(NX, NY), *c = swfs_accum_create(NX, NY);
    assert_true(a && b && c);
    feed(a, 0, 50);
    feed(b, 50, 90);
    const size_t len = swfs_accum_state_len(NX, NY);
    assert_int_equal(len, (size_t)(SWFS_ACC_NFIELDS + SWFS_REGRESS_NSTATE) * NP + 4);
    double *sa = malloc(len * sizeof *sa), *sb = malloc(len * sizeof *sb);
    assert_true(sa && sb);
    swfs_accum_export(a, sa);
    swfs_accum_export(b, sb);
    assert_ok(swfs_accum_merge_state(sa, sb, NX, NY));
    assert_ok(swfs_accum_merge(a, b));
    assert_ok(swfs_accum_import(c, sa));
    assert_int_equal(c->frames, 90);
    assert_int_equal(c->skipped, 20);
    assert_true(swfs_accum_has_regress(c));
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) assert_memory_equal(a->f[k], c->f[k], NP * sizeof(double));
    assert_memory_equal(a->reg->state, c->reg->state, NP * SWFS_REGRESS_NSTATE * sizeof(double));
    sa[NP * SWFS_ACC_CXX + 2] = -1.0; /* a negative variance */
    assert_int_equal(swfs_accum_import(c, sa), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "negative variance"));
    free(sa);
    free(sb);
    swfs_accum_free(a);
    swfs_accum_free(b);
    swfs_accum_free(c);
}

static void test_bad_files(void **state)
{
    (void)state;
    swfs_accum *a = swfs_accum_create(NX, NY), *b = swfs_accum_create(NX + 1, NY), *m = NULL;
    assert_true(a && b);
    feed(a, 0, 5);
    swfs_geom g = test_geom(), g2 = test_geom();
    g2.wavelen = 2.2e-6;
    const char *pa = test_path("ckpt_a.fits"), *pb = test_path("ckpt_b.fits"), *pc = test_path("ckpt_c.fits");
    char sa[1024], sb[1024], sc[1024];
    strcpy(sa, pa);
    strcpy(sb, pb);
    strcpy(sc, pc);
    assert_ok(swfs_accum_save(a, sa, &g, NULL, 0));
    assert_ok(swfs_accum_save(a, sb, &g2, NULL, 0));
    assert_ok(swfs_accum_save(b, sc, &g, NULL, 0));
    const char *wl[2] = {sa, sb};
    assert_int_equal(swfs_accum_merge_files(wl, 2, &m, NULL), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "WAVELEN"));
    const char *sh[2] = {sa, sc};
    assert_int_equal(swfs_accum_merge_files(sh, 2, &m, NULL), SWFS_ERR_SHAPE);
    assert_null(m);
    /* A FITS file that is not a checkpoint. */
    swfs_real *img = swfs_real_alloc(NX, NY, 1);
    assert_non_null(img);
    swfs_fits_out *o = NULL;
    const char *pi = test_path("ckpt_not.fits");
    assert_ok(swfs_fits_out_create(&o, pi));
    assert_ok(swfs_fits_out_real(o, "ACCUM", img, -64));
    assert_ok(swfs_fits_out_commit(o));
    assert_int_equal(swfs_accum_load(pi, &m, NULL), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "ckpt_not.fits"));
    assert_int_not_equal(swfs_accum_load(test_path("no_such_checkpoint.fits"), &m, NULL), 0);
    assert_null(m);
    swfs_real_free(img);
    swfs_accum_free(a);
    swfs_accum_free(b);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_round_trip),
        cmocka_unit_test(test_merge_equals_single_pass),
        cmocka_unit_test(test_flat_state),
        cmocka_unit_test(test_bad_files),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

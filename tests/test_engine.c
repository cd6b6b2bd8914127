/* The fast engine (src/sensing/engine.c) against a straightforward double-precision
 * computation: per WFS frame, z = W s, phi = (2 pi/lambda) T z, E = P exp(i phi), one
 * double MFT each, weighted sum over the exposure, core-phase referencing
 * (eq:downsampledHalo). Fractional weights, tip-tilt removal, threads 1 vs 2, the
 * frame-at-a-time stream and the one-MFT-per-WFS-frame mode. */
#include "testutil.h"

#include "specklewfs/engine.h"
#include "specklewfs/mft.h"
#include "specklewfs/rng.h"
#include "specklewfs/sparse.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NPUP 24
#define NFX 16
#define NFY 12
#define NSUB 4
#define NSL (2 * NSUB * NSUB)
#define NACT 25
#define LAMBDA 1.6e-6
#define ALPHA 0.07

typedef struct fixture {
    double *recon, *pupil, *slopes;
    swfs_sparse *interp;
    size_t nwfs;
} fixture;

static void make_fixture(fixture *f, size_t nwfs, uint64_t seed)
{
    swfs_rng r;
    swfs_rng_seed(&r, seed);
    f->nwfs = nwfs;
    f->recon = malloc(NACT * NSL * sizeof(double));
    f->pupil = calloc(NPUP * NPUP, sizeof(double));
    f->slopes = malloc(nwfs * NSL * sizeof(double));
    assert_true(f->recon && f->pupil && f->slopes);
    /* Phases of order 1 rad: z ~ lambda / (2 pi). */
    for (size_t k = 0; k < NACT * NSL; k++) f->recon[k] = LAMBDA / (2.0 * M_PI) * 0.4 * swfs_rng_normal(&r);
    for (size_t k = 0; k < nwfs * NSL; k++) f->slopes[k] = swfs_rng_normal(&r);
    /* Annular pupil with a soft (grey) edge. */
    for (size_t q = 0; q < NPUP; q++)
        for (size_t p = 0; p < NPUP; p++) {
            const double x = (double)p - 0.5 * (NPUP - 1), y = (double)q - 0.5 * (NPUP - 1);
            const double rr = sqrt(x * x + y * y);
            if (rr < 0.5 * NPUP && rr > 2.5) f->pupil[q * NPUP + p] = rr > 0.5 * NPUP - 1.0 ? 0.5 : 1.0;
        }
    /* 1-5 nonzeros per row (some rows empty). */
    f->interp = swfs_sparse_alloc(NPUP * NPUP, NACT, NPUP * NPUP * 5);
    assert_non_null(f->interp);
    size_t q = 0;
    for (size_t row = 0; row < NPUP * NPUP; row++) {
        const size_t nz = (size_t)(swfs_rng_uniform(&r) * 6.0);
        for (size_t k = 0; k < nz; k++) {
            f->interp->col[q] = (size_t)(swfs_rng_uniform(&r) * NACT);
            f->interp->val[q] = swfs_rng_uniform(&r);
            q++;
        }
        f->interp->row_ptr[row + 1] = q;
    }
    f->interp->nnz = q;
}

static void free_fixture(fixture *f)
{
    free(f->recon);
    free(f->pupil);
    free(f->slopes);
    swfs_sparse_free(f->interp);
}

static swfs_engine_config config_of(const fixture *f, int tiptilt, int nthreads)
{
    swfs_engine_config c = {NSL, NACT, NPUP, NFX, NFY, ALPHA, LAMBDA, f->recon, f->interp, f->pupil, tiptilt, nthreads};
    return c;
}

/* Double-precision pupil field of WFS frame k. */
static void ref_field(const fixture *f, size_t k, int tiptilt, double complex *E)
{
    double s[NSL], z[NACT], phi[NPUP * NPUP];
    memcpy(s, f->slopes + k * NSL, sizeof s);
    if (tiptilt) {
        double mx = 0, my = 0;
        for (size_t i = 0; i < NSL / 2; i++) { mx += s[i]; my += s[NSL / 2 + i]; }
        for (size_t i = 0; i < NSL / 2; i++) { s[i] -= mx / (NSL / 2); s[NSL / 2 + i] -= my / (NSL / 2); }
    }
    for (size_t a = 0; a < NACT; a++) {
        z[a] = 0;
        for (size_t i = 0; i < NSL; i++) z[a] += f->recon[a * NSL + i] * s[i];
    }
    swfs_sparse_apply(f->interp, z, phi);
    for (size_t p = 0; p < NPUP * NPUP; p++) E[p] = f->pupil[p] * cexp(I * 2.0 * M_PI / LAMBDA * phi[p]);
}

/* Reference: per-WFS-frame double MFT, weighted sum, core referencing. */
static void ref_exposure(const fixture *f, const swfs_exposure *x, int tiptilt, double complex *out)
{
    swfs_mft *m = swfs_mft_create(NPUP, NFX, NFY, ALPHA, SWFS_MFT_DOUBLE);
    assert_non_null(m);
    double complex E[NPUP * NPUP], h[NFX * NFY];
    memset(out, 0, sizeof h);
    for (size_t k = x->first; k < x->first + x->count; k++) {
        const double w = k == x->first ? x->w_first : k == x->first + x->count - 1 ? x->w_last : 1.0;
        ref_field(f, k, tiptilt, E);
        assert_ok(swfs_mft_forward(m, E, h));
        for (size_t i = 0; i < NFX * NFY; i++) out[i] += w * h[i];
    }
    const double complex core = out[(NFY / 2) * NFX + NFX / 2];
    for (size_t i = 0; i < NFX * NFY; i++) out[i] *= conj(core) / cabs(core);
    swfs_mft_free(m);
}

/* max |a - b| / max |b| over n values. */
static double rel_err(const double complex *a, const double complex *b, size_t n)
{
    double emax = 0, bmax = 0;
    for (size_t i = 0; i < n; i++) {
        emax = fmax(emax, cabs(a[i] - b[i]));
        bmax = fmax(bmax, cabs(b[i]));
    }
    return emax / bmax;
}

static void test_schedule(void **state)
{
    (void)state;
    swfs_exposure s[20];
    const double ratio = 6.48;
    const size_t need = swfs_engine_schedule(ratio, 0.3, 20, s);
    assert_int_equal(need, (size_t)ceil(0.3 + 20 * ratio));
    for (size_t j = 0; j < 20; j++) {
        double sum = s[j].count == 1 ? s[j].w_first : s[j].w_first + s[j].w_last + (double)(s[j].count - 2);
        assert_close(sum, ratio, 1e-12); /* every exposure integrates ratio WFS frames */
        assert_true(s[j].w_first > 0 && s[j].w_first <= 1 && s[j].w_last > 0 && s[j].w_last <= 1);
        if (j) {
            /* A straddling frame's weights add up to 1 over the two exposures. */
            const swfs_exposure *p = &s[j - 1];
            if (p->first + p->count - 1 == s[j].first) assert_close(p->w_last + s[j].w_first, 1.0, 1e-12);
            else assert_int_equal(p->first + p->count, s[j].first);
        }
    }
    /* A camera faster than the WFS: each exposure interpolates the two WFS frames whose
     * centres bracket its own, weights summing to its length; a constant phase field would
     * come out with the exposure's weight. */
    const double r = 0.8;
    const size_t n2 = swfs_engine_schedule(r, 0.3, 20, s);
    assert_int_equal(n2, s[19].first + 2);
    for (size_t j = 0; j < 20; j++) {
        const double centre = 0.3 + ((double)j + 0.5) * r, a = centre - 0.5 - (double)s[j].first;
        assert_int_equal(s[j].count, 2);
        assert_true(a >= 0 && a < 1);
        assert_close(s[j].w_first + s[j].w_last, r, 1e-12);
        assert_close(s[j].w_last / r, a, 1e-12);
    }
    assert_int_equal(swfs_engine_schedule(SWFS_ENGINE_MIN_RATIO / 2, 0, 3, s), 0);
}

/* Batch with fractional weights, tip-tilt removal, several chunks; threads 1 and 2. */
static void test_batch_matches_reference(void **state)
{
    (void)state;
    fixture f;
    enum { NEXP = 26 };
    const double ratio = 3.37;
    swfs_exposure sched[NEXP];
    const size_t need = swfs_engine_schedule(ratio, 0.4, NEXP, sched);
    make_fixture(&f, need, 5);
    /* One long exposure (more WFS frames than a worker chunk spans) in the middle. */
    sched[10].count = 70;
    sched[10].first = 2;
    sched[10].w_first = 0.25;
    sched[10].w_last = 0.5;

    double complex *out1 = malloc(NEXP * NFX * NFY * sizeof *out1);
    double complex *out2 = malloc(NEXP * NFX * NFY * sizeof *out2);
    double complex ref[NFX * NFY];
    assert_true(out1 && out2);
    swfs_engine_config c = config_of(&f, 1, 1);
    swfs_engine *e1 = swfs_engine_create(&c);
    c.nthreads = 2;
    swfs_engine *e2 = swfs_engine_create(&c);
    assert_non_null(e1);
    assert_non_null(e2);
    assert_int_equal(swfs_engine_nthreads(e2), 2);
    assert_ok(swfs_engine_process(e1, f.slopes, f.nwfs, sched, NEXP, out1));
    assert_ok(swfs_engine_process(e2, f.slopes, f.nwfs, sched, NEXP, out2));
    /* The work split is fixed by the schedule: identical results with 1 and 2 threads. */
    assert_memory_equal(out1, out2, NEXP * NFX * NFY * sizeof *out1);
    double emax = 0;
    for (size_t j = 0; j < NEXP; j++) {
        ref_exposure(&f, &sched[j], 1, ref);
        emax = fmax(emax, rel_err(out1 + j * NFX * NFY, ref, NFX * NFY));
        /* Referenced: the core is real and positive. */
        const double complex core = out1[j * NFX * NFY + (NFY / 2) * NFX + NFX / 2];
        assert_true(creal(core) > 0);
        assert_true(fabs(cimag(core)) <= 1e-6 * creal(core));
    }
    print_message("batch vs double reference: max relative error %.3g\n", emax);
    assert_true(emax < 5e-6);
    /* Run again on the same engines: plans reused, same numbers. */
    assert_ok(swfs_engine_process(e2, f.slopes, f.nwfs, sched, NEXP, out2));
    assert_memory_equal(out1, out2, NEXP * NFX * NFY * sizeof *out1);
    swfs_engine_free(e1);
    swfs_engine_free(e2);
    free(out1);
    free(out2);
    free_fixture(&f);
}

/* Tip-tilt removal: adding a constant to every x slope and another to every y slope
 * changes nothing when removal is on, and matters when it is off. */
static void test_tiptilt(void **state)
{
    (void)state;
    fixture f;
    make_fixture(&f, 8, 7);
    swfs_exposure x = {0, 8, 0.5, 0.75};
    double complex a[NFX * NFY], b[NFX * NFY], ref[NFX * NFY];
    swfs_engine_config c = config_of(&f, 1, 1);
    swfs_engine *e = swfs_engine_create(&c);
    assert_non_null(e);
    assert_ok(swfs_engine_process(e, f.slopes, f.nwfs, &x, 1, a));
    for (size_t k = 0; k < f.nwfs; k++)
        for (size_t i = 0; i < NSL; i++) f.slopes[k * NSL + i] += i < NSL / 2 ? 0.8 : -1.3;
    assert_ok(swfs_engine_process(e, f.slopes, f.nwfs, &x, 1, b));
    assert_true(rel_err(a, b, NFX * NFY) < 1e-5);
    swfs_engine_free(e);
    c.remove_tiptilt = 0;
    e = swfs_engine_create(&c);
    assert_non_null(e);
    assert_ok(swfs_engine_process(e, f.slopes, f.nwfs, &x, 1, b));
    ref_exposure(&f, &x, 0, ref);
    assert_true(rel_err(b, ref, NFX * NFY) < 5e-6);
    assert_true(rel_err(a, b, NFX * NFY) > 1e-2);
    swfs_engine_free(e);
    free_fixture(&f);
}

/* The frame-at-a-time stream (buffered 16 at a time) equals the batch. */
static void test_stream_matches_batch(void **state)
{
    (void)state;
    fixture f;
    enum { NEXP = 4 };
    swfs_exposure sched[NEXP];
    const size_t need = swfs_engine_schedule(9.3, 0.0, NEXP, sched);
    make_fixture(&f, need + 30, 9);
    sched[2].count = 37; /* longer than one internal block of 16 */
    double complex *batch = malloc(NEXP * NFX * NFY * sizeof *batch), out[NFX * NFY], ref[NFX * NFY];
    assert_non_null(batch);
    swfs_engine_config c = config_of(&f, 1, 2);
    swfs_engine *e = swfs_engine_create(&c);
    assert_non_null(e);
    assert_ok(swfs_engine_process(e, f.slopes, f.nwfs, sched, NEXP, batch));
    /* Garbage in a dropped exposure must not leak into the next one. */
    assert_ok(swfs_engine_add_wfs(e, f.slopes, 3.0));
    swfs_engine_reset(e);
    for (size_t j = 0; j < NEXP; j++) {
        const swfs_exposure *x = &sched[j];
        for (size_t k = x->first; k < x->first + x->count; k++) {
            const double w = k == x->first ? x->w_first : k == x->first + x->count - 1 ? x->w_last : 1.0;
            assert_ok(swfs_engine_add_wfs(e, f.slopes + k * NSL, w));
        }
        assert_ok(swfs_engine_end_exposure(e, out));
        assert_true(rel_err(out, batch + j * NFX * NFY, NFX * NFY) < 1e-6);
        ref_exposure(&f, x, 1, ref);
        assert_true(rel_err(out, ref, NFX * NFY) < 5e-6);
    }
    swfs_engine_free(e);
    free(batch);
    free_fixture(&f);
}

/* One MFT per WFS frame. */
static void test_per_wfs_frame(void **state)
{
    (void)state;
    fixture f;
    make_fixture(&f, 300, 21); /* more frames than one worker chunk (256) */
    double complex *out = malloc(f.nwfs * NFX * NFY * sizeof *out), ref[NFX * NFY];
    double complex *out1 = malloc(f.nwfs * NFX * NFY * sizeof *out1);
    assert_true(out && out1);
    swfs_engine_config c = config_of(&f, 0, 2);
    swfs_engine *e = swfs_engine_create(&c);
    c.nthreads = 1;
    swfs_engine *e1 = swfs_engine_create(&c);
    assert_non_null(e);
    assert_non_null(e1);
    assert_ok(swfs_engine_process_wfs(e, f.slopes, f.nwfs, out));
    assert_ok(swfs_engine_process_wfs(e1, f.slopes, f.nwfs, out1));
    assert_memory_equal(out, out1, f.nwfs * NFX * NFY * sizeof *out);
    double emax = 0;
    for (size_t k = 0; k < f.nwfs; k++) {
        swfs_exposure x = {k, 1, 1.0, 1.0};
        ref_exposure(&f, &x, 0, ref);
        emax = fmax(emax, rel_err(out + k * NFX * NFY, ref, NFX * NFY));
    }
    print_message("per-WFS-frame vs double reference: max relative error %.3g\n", emax);
    assert_true(emax < 5e-6);
    swfs_engine_free(e);
    swfs_engine_free(e1);
    free(out);
    free(out1);
    free_fixture(&f);
}

static void test_bad_input(void **state)
{
    (void)state;
    fixture f;
    make_fixture(&f, 20, 3);
    swfs_engine_config c = config_of(&f, 1, 2);
    double complex out[2 * NFX * NFY];
    swfs_engine *e = swfs_engine_create(&c);
    assert_non_null(e);
    /* A schedule reaching past the slopes block. */
    swfs_exposure x[2] = {{0, 5, 1, 1}, {15, 6, 1, 1}};
    assert_int_equal(swfs_engine_process(e, f.slopes, f.nwfs, x, 2, out), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "camera frame 1"));
    /* A NaN slope, found in a worker thread, reported by the caller. */
    f.slopes[17 * NSL + 3] = NAN;
    x[1].count = 5;
    assert_int_equal(swfs_engine_process(e, f.slopes, f.nwfs, x, 2, out), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "WFS frame 17"));
    assert_int_equal(swfs_engine_add_wfs(e, f.slopes + 17 * NSL, 1.0), SWFS_ERR_VALUE);
    swfs_engine_free(e);
    /* Interpolation matrix of the wrong shape; odd slope count with tip-tilt removal. */
    c.nact = NACT - 1;
    assert_null(swfs_engine_create(&c));
    assert_non_null(strstr(swfs_last_error(), "interpolation"));
    c.nact = NACT;
    c.nslopes = NSL - 1;
    assert_null(swfs_engine_create(&c));
    swfs_engine_free(NULL);
    free_fixture(&f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_schedule),
        cmocka_unit_test(test_batch_matches_reference),
        cmocka_unit_test(test_tiptilt),
        cmocka_unit_test(test_stream_matches_batch),
        cmocka_unit_test(test_per_wfs_frame),
        cmocka_unit_test(test_bad_input),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

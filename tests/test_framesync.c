/* framesync: timestamped WFS and camera frames -> stream batches. With regular stamps the
 * batches are the file source's (swfs_engine_schedule over the same frames); stamp jitter
 * is absorbed by the clock fits; dropped frames are counted exactly and only complete
 * exposures are used; a restarted writer and a second WFS stream are handled. */
#include "testutil.h"

#include "specklewfs/engine.h"
#include "specklewfs/framesync.h"
#include "specklewfs/rng.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NS 6      /* values per WFS frame */
#define NF2 4     /* camera pixels */
#define RATIO 3.37
#define NCAM 30   /* camera frames per cube */
#define NWFS 320

static const double period = 1.0 / 527.0;
static const int64_t t_origin = (int64_t)1700000000 * 1000000000; /* a Unix time in ns */

/* Value v of WFS frame k (global row k covers [k, k+1) WFS frames). */
static double wfs_val(size_t k, size_t v) { return (double)k + 0.01 * (double)v; }

typedef struct collected {
    size_t nexp, nbatches;
    double w[2 * NCAM][2];       /* w_first, w_last of every exposure used */
    size_t first[2 * NCAM], count[2 * NCAM]; /* global first WFS frame (row) and count */
    double sci[2 * NCAM];        /* the camera frame's first pixel = its global index */
} collected;

/* Take a batch apart into global frame indices (the slopes carry them). */
static void collect(const swfs_batch *b, collected *c)
{
    for (size_t j = 0; j < b->nexp; j++) {
        const swfs_exposure *e = &b->sched[j];
        const size_t row0 = (size_t)llround(b->slopes[e->first * NS]); /* value 0 = global row */
        for (size_t r = 0; r < e->count; r++)
            for (size_t v = 0; v < NS; v++)
                assert_close(b->slopes[(e->first + r) * NS + v], wfs_val(row0 + r, v), 1e-12);
        c->first[c->nexp] = row0;
        c->count[c->nexp] = e->count;
        c->w[c->nexp][0] = e->w_first;
        c->w[c->nexp][1] = e->w_last;
        c->sci[c->nexp] = b->science[j * NF2];
        c->nexp++;
    }
    c->nbatches++;
}

typedef struct feed_opts {
    double jitter;          /* [s] rms of the stamps */
    const int *drop_wfs;    /* global rows not delivered (-1 terminated) */
    const int *drop_cam;    /* global camera indices not delivered (-1 terminated) */
    int restart_at;         /* WFS row at which both writers restart (0: none) */
    int two_streams;        /* split every WFS frame over two streams */
    size_t batch;
} feed_opts;

static int listed(const int *l, int v)
{
    for (; l && *l >= 0; l++)
        if (*l == v) return 1;
    return 0;
}

/* Feed two cubes (starts 10.25 and 150.5 WFS frames, NCAM frames each) in time order and
 * collect what comes out. */
static void feed(const feed_opts *fo, collected *c, swfs_framesync_stats *st)
{
    swfs_framesync_options o;
    swfs_framesync_options_default(&o);
    o.batch = fo->batch;
    o.max_wait = 1e9; /* batches close by size, contiguity or flush only */
    swfs_framesync *f = NULL;
    const size_t nv2[2] = {NS / 2, NS - NS / 2};
    const size_t nv1[1] = {NS};
    assert_ok(swfs_framesync_create(&f, fo->two_streams ? 2 : 1, fo->two_streams ? nv2 : nv1, NF2, &o));
    swfs_rng r;
    swfs_rng_seed(&r, 5);
    const double start[2] = {10.25, 150.5};
    size_t cam = 0; /* next camera frame (global index over both cubes) */
    uint64_t wcnt = 0, ccnt = 0;
    memset(c, 0, sizeof *c);
    double vals[NS], frame[NF2];
    swfs_batch b;
    for (size_t k = 0; k < NWFS; k++) {
        if (fo->restart_at && (int)k == fo->restart_at) {
            wcnt = 0;
            ccnt = 0;
            swfs_framesync_expect(f, 0, 0, 0, 1);
            if (fo->two_streams) swfs_framesync_expect(f, 0, 1, 0, 1);
            swfs_framesync_expect(f, 1, 0, 0, 1);
        }
        /* WFS row k ends at (k + 1) periods. */
        const double tw = (double)(k + 1) * period;
        wcnt++;
        if (!listed(fo->drop_wfs, (int)k)) {
            for (size_t v = 0; v < NS; v++) vals[v] = wfs_val(k, v);
            const int64_t ns = t_origin + llround(1e9 * (tw + fo->jitter * swfs_rng_normal(&r)));
            if (fo->two_streams) {
                const int64_t ns2 = t_origin + llround(1e9 * (tw + fo->jitter * swfs_rng_normal(&r)));
                assert_ok(swfs_framesync_add_wfs(f, 1, wcnt, ns2, vals + NS / 2, 0.0));
                assert_ok(swfs_framesync_add_wfs(f, 0, wcnt, ns, vals, 0.0));
            } else {
                assert_ok(swfs_framesync_add_wfs(f, 0, wcnt, ns, vals, 0.0));
            }
        }
        /* Camera frames that ended during this WFS frame. */
        for (;;) {
            if (cam >= 2 * NCAM) break;
            const size_t cube = cam / NCAM, j = cam % NCAM;
            const double te = (start[cube] + (double)(j + 1) * RATIO) * period;
            if (te > tw) break;
            ccnt++;
            if (!listed(fo->drop_cam, (int)cam)) {
                for (size_t p = 0; p < NF2; p++) frame[p] = (double)cam;
                const int64_t ns = t_origin + llround(1e9 * (te + fo->jitter * swfs_rng_normal(&r)));
                assert_ok(swfs_framesync_add_camera(f, ccnt, ns, frame, 0.0));
            }
            cam++;
        }
        for (;;) {
            assert_ok(swfs_framesync_next(f, 0.0, 0, &b));
            if (!b.nexp) break;
            collect(&b, c);
        }
    }
    for (;;) {
        assert_ok(swfs_framesync_next(f, 0.0, 1, &b));
        if (!b.nexp) break;
        collect(&b, c);
    }
    swfs_framesync_get_stats(f, st);
    swfs_framesync_free(f);
}

/* The exposures of the file source: engine schedule from each cube's start. */
static void expected(swfs_exposure *sched, size_t *base)
{
    const double start[2] = {10.25, 150.5};
    for (int cube = 0; cube < 2; cube++) {
        base[cube] = (size_t)floor(start[cube]);
        swfs_engine_schedule(RATIO, start[cube] - (double)base[cube], NCAM, sched + cube * NCAM);
    }
}

static void test_regular(void **state)
{
    (void)state;
    swfs_exposure ex[2 * NCAM];
    size_t base[2];
    expected(ex, base);
    const size_t batches[] = {1, 8, 64};
    for (size_t bi = 0; bi < 3; bi++) {
        feed_opts fo = {0};
        fo.batch = batches[bi];
        collected c;
        swfs_framesync_stats st;
        feed(&fo, &c, &st);
        assert_int_equal(c.nexp, 2 * NCAM);
        assert_int_equal(st.used, 2 * NCAM);
        assert_int_equal(st.wfs_dropped + st.camera_dropped + st.incomplete + st.no_wfs, 0);
        /* Batches as the file source cuts them: per cube, B at a time. */
        const size_t per_cube = (NCAM + fo.batch - 1) / fo.batch;
        assert_int_equal(c.nbatches, 2 * per_cube);
        assert_int_equal(st.camera_segments, 2);
        assert_int_equal(st.wfs_segments, 1);
        double wmax = 0;
        for (size_t j = 0; j < 2 * NCAM; j++) {
            const swfs_exposure *e = &ex[j];
            assert_close(c.sci[j], (double)j, 0);
            assert_int_equal(c.first[j], base[j / NCAM] + e->first);
            assert_int_equal(c.count[j], e->count);
            wmax = fmax(wmax, fmax(fabs(c.w[j][0] - e->w_first), fabs(c.w[j][1] - e->w_last)));
        }
        /* Stamps are whole nanoseconds: 0.5 ns of a 1.9 ms period. */
        print_message("batch %zu: largest weight difference from the engine schedule %.3g\n", fo.batch, wmax);
        assert_true(wmax < 2e-6);
        assert_close(st.wfs_period, period, 1e-12);
        assert_close(st.camera_period, RATIO * period, 1e-10);
    }
}

static void test_jitter(void **state)
{
    (void)state;
    swfs_exposure ex[2 * NCAM];
    size_t base[2];
    expected(ex, base);
    feed_opts fo = {0};
    fo.batch = 8;
    fo.jitter = 5e-6; /* 5 us rms: 2.6e-3 of a WFS frame */
    collected c;
    swfs_framesync_stats st;
    feed(&fo, &c, &st);
    assert_int_equal(c.nexp, 2 * NCAM);
    double wmax = 0, wsum = 0;
    for (size_t j = 0; j < 2 * NCAM; j++) {
        assert_int_equal(c.first[j], base[j / NCAM] + ex[j].first);
        const double d0 = fabs(c.w[j][0] - ex[j].w_first), d1 = fabs(c.w[j][1] - ex[j].w_last);
        wmax = fmax(wmax, fmax(d0, d1));
        wsum += d0 + d1;
    }
    /* Raw stamps would move each edge of an exposure by sqrt(2) x 2.6e-3 rms (camera and
     * WFS stamp), 3e-3 on average; the clock fits halve that even over these short cubes
     * (the first frames of the first cube, with a period from two stamps, are the worst). */
    const double sig = 5e-6 / period, mean = wsum / (4 * NCAM);
    print_message("5 us jitter (%.3g WFS frames): weight error mean %.3g, largest %.3g\n", sig, mean, wmax);
    assert_true(mean < 0.75 * sig);
    assert_true(wmax < 3 * sig);
    assert_int_equal(st.wfs_segments, 1);
    assert_int_equal(st.camera_segments, 2);
}

/* Exposures that overlap WFS row k (from the engine schedule). */
static int uses_row(const swfs_exposure *ex, const size_t *base, size_t j, size_t k)
{
    const size_t f0 = base[j / NCAM] + ex[j].first;
    return k >= f0 && k < f0 + ex[j].count;
}

static void test_drops(void **state)
{
    (void)state;
    swfs_exposure ex[2 * NCAM];
    size_t base[2];
    expected(ex, base);
    const int dw[] = {20, 21, 57, 160, 300, -1};
    const int dc[] = {3, 40, -1};
    feed_opts fo = {0};
    fo.batch = 8;
    fo.drop_wfs = dw;
    fo.drop_cam = dc;
    collected c;
    swfs_framesync_stats st;
    feed(&fo, &c, &st);
    assert_int_equal(st.wfs_dropped, 5);
    assert_int_equal(st.camera_dropped, 2);
    /* Expected: every delivered camera frame none of whose WFS frames was dropped. */
    size_t want = 0, got = 0;
    for (size_t j = 0; j < 2 * NCAM; j++) {
        if (listed(dc, (int)j)) continue;
        int ok = 1;
        for (const int *d = dw; *d >= 0; d++) ok &= !uses_row(ex, base, j, (size_t)*d);
        if (!ok) continue;
        want++;
        /* It is there, with its exact frames. */
        int found = 0;
        for (size_t i = 0; i < c.nexp; i++)
            if (c.sci[i] == (double)j) {
                found = 1;
                assert_int_equal(c.first[i], base[j / NCAM] + ex[j].first);
                assert_int_equal(c.count[i], ex[j].count);
            }
        assert_true(found);
    }
    got = c.nexp;
    assert_int_equal(got, want);
    assert_int_equal(st.used + st.incomplete, 2 * NCAM - 2);
    print_message("drops: %zu of %d camera frames used, %llu incomplete\n", got, 2 * NCAM,
                  (unsigned long long)st.incomplete);
}

static void test_restart(void **state)
{
    (void)state;
    feed_opts fo = {0};
    fo.batch = 8;
    fo.restart_at = 100; /* between the cubes (cube 0 ends at 111.35, cube 1 starts at 150.5) */
    collected c;
    swfs_framesync_stats st;
    feed(&fo, &c, &st);
    assert_int_equal(st.wfs_restarts, 1);
    assert_int_equal(st.camera_restarts, 1);
    assert_int_equal(st.wfs_dropped + st.camera_dropped, 0);
    assert_int_equal(st.wfs_segments, 2);
    /* The old writer's last frame is row 99, the new one's first row 100: only the
     * exposure of cube 0 that spans the two is skipped (an exposure is never assembled
     * from two writers); those after it map onto the new writer's frames. */
    size_t span = 0;
    for (size_t j = 0; j < NCAM; j++)
        if (10.25 + (double)j * RATIO < 100.0 && 10.25 + (double)(j + 1) * RATIO > 100.0) span++;
    assert_int_equal(span, 1);
    assert_int_equal(c.nexp + span, 2 * NCAM);
    assert_int_equal(st.incomplete + st.no_wfs, span);
    /* The second cube is complete: its frames are the same as without a restart. */
    size_t n1 = 0;
    for (size_t i = 0; i < c.nexp; i++) n1 += c.sci[i] >= NCAM;
    assert_int_equal(n1, NCAM);
}

static void test_two_streams(void **state)
{
    (void)state;
    feed_opts fo = {0};
    fo.batch = 8;
    fo.two_streams = 1;
    fo.jitter = 2e-6;
    collected c;
    swfs_framesync_stats st;
    feed(&fo, &c, &st);
    assert_int_equal(c.nexp, 2 * NCAM); /* collect() checked that every row holds both halves */
    assert_int_equal(st.incomplete + st.no_wfs, 0);
    /* Stream 1's frames can be placed once the master's clock has a period: its first two
     * frames (long before the first exposure) are not. */
    assert_true(st.wfs_late <= 2);
}

static void test_bad_args(void **state)
{
    (void)state;
    swfs_framesync *f = NULL;
    const size_t nv[1] = {4};
    swfs_framesync_options o;
    swfs_framesync_options_default(&o);
    o.batch = 0;
    assert_int_not_equal(swfs_framesync_create(&f, 1, nv, 4, &o), 0);
    assert_null(f);
    swfs_framesync_options_default(&o);
    assert_int_not_equal(swfs_framesync_create(&f, 0, nv, 4, &o), 0);
    assert_ok(swfs_framesync_create(&f, 1, nv, 4, &o));
    /* Non-finite WFS values: the frame is counted bad and its exposures incomplete. */
    double v[4] = {0, NAN, 0, 0}, fr[4] = {0};
    swfs_batch b;
    for (uint64_t k = 1; k <= 40; k++) {
        v[1] = k == 10 ? NAN : 0.0;
        assert_ok(swfs_framesync_add_wfs(f, 0, k, t_origin + (int64_t)k * 1000000, v, 0.0));
        if (k % 4 == 0) assert_ok(swfs_framesync_add_camera(f, k / 4, t_origin + (int64_t)k * 1000000, fr, 0.0));
    }
    assert_ok(swfs_framesync_next(f, 0.0, 1, &b));
    swfs_framesync_stats st;
    swfs_framesync_get_stats(f, &st);
    assert_int_equal(st.wfs_bad, 1);
    assert_int_equal(st.incomplete, 1); /* camera frame 3 covers WFS frames 9..12 */
    swfs_framesync_free(f);
}

/* A space-time reconstructor's lags (0, -2, 3): every row of a batch stacked with the rows 2
 * before and 3 after, clamped to the segment's first and last frames, a missing frame
 * replaced by the row's own values; a batch waits until the frame 3 rows after its last is in
 * (unless flushed). WFS frame k (1 kHz) holds (k, 100 + k); frame 30 never arrives. */
static void test_lags(void **state)
{
    (void)state;
    enum { NV = 2, NL = 3, NK = 60 };
    const long lags[NL] = {0, -2, 3};
    swfs_framesync *f = NULL;
    const size_t nv[1] = {NV};
    swfs_framesync_options o;
    swfs_framesync_options_default(&o);
    o.batch = 4;
    o.max_wait = 1e30;
    o.lags = lags;
    o.nlags = NL;
    assert_ok(swfs_framesync_create(&f, 1, nv, NF2, &o));
    double v[NV], fr[NF2] = {0};
    swfs_batch b;
    size_t batches = 0, rows = 0;
    for (int pass = 0; pass < 2; pass++)
        for (uint64_t k = pass ? NK : 1; k <= NK; k++) {
            const int flush = pass == 1;
            if (!flush) {
                v[0] = (double)k;
                v[1] = 100.0 + (double)k;
                if (k != 30) assert_ok(swfs_framesync_add_wfs(f, 0, k, t_origin + (int64_t)k * 1000000, v, 0.0));
                if (k % 4 == 0) assert_ok(swfs_framesync_add_camera(f, k / 4, t_origin + (int64_t)k * 1000000, fr, 0.0));
            }
            for (;;) {
                assert_ok(swfs_framesync_next(f, 0.0, flush, &b));
                if (!b.nexp) break;
                batches++;
                int64_t last = 0;
                for (size_t r = 0; r < b.nwfs; r++) {
                    const double *row = b.slopes + r * NV * NL;
                    const int64_t g = (int64_t)llround(row[0]);
                    if (g == 0) continue; /* a row no exposure uses (the missing frame's) */
                    last = g;
                    for (size_t l = 0; l < NL; l++) {
                        int64_t t = g + lags[l];
                        t = t < 1 ? 1 : t > NK ? NK : t;
                        if (t == 30) t = g; /* never arrived: the row's own */
                        assert_close(row[l * NV], (double)t, 0);
                        assert_close(row[l * NV + 1], 100.0 + (double)t, 0);
                    }
                    rows++;
                }
                /* not out before the frame its last row needs at lag 3 (unless flushed) */
                if (!flush) assert_true((int64_t)k >= last + 3);
            }
        }
    swfs_framesync_stats st;
    swfs_framesync_get_stats(f, &st);
    print_message("framesync with lags 0,-2,3: %zu batches, %zu rows checked, %llu exposures used, %llu incomplete\n",
                  batches, rows, (unsigned long long)st.used, (unsigned long long)st.incomplete);
    assert_true(batches >= 3 && rows > 40 && st.incomplete >= 1 && st.used + st.incomplete + st.no_wfs == NK / 4);
    swfs_framesync_free(f);
    /* lags without a 0 are refused */
    const long bad[2] = {1, 2};
    o.lags = bad;
    o.nlags = 2;
    assert_int_not_equal(swfs_framesync_create(&f, 1, nv, NF2, &o), 0);
    assert_null(f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_regular),  cmocka_unit_test(test_jitter),      cmocka_unit_test(test_drops),
        cmocka_unit_test(test_restart),  cmocka_unit_test(test_two_streams), cmocka_unit_test(test_bad_args),
        cmocka_unit_test(test_lags),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

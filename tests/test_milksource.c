/* Stream batches from milk logs (milksource.h) on exact synthetic data: two WFS logs (a
 * 3-vector as N x 1 x T cubes in two files, a 2-vector as an N x T image whose stamps trail
 * by 0.1 ms) concatenated into one 5-vector, a camera cube with STAMPS whose clock is offset
 * and drifting (a clock file undoes it), a dropped WFS frame and a dropped camera frame. Every
 * exposure's weighted WFS values equal the exact mean of the frame index over [T - E, T];
 * the drops are counted and the exposure over the dropped WFS frame skipped. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/milklog.h"
#include "specklewfs/milksource.h"
#include "specklewfs/science.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { NW = 400, NC = 40 };
static const int64_t E0 = 1700000000LL * 1000000000LL;
static const double EXPT = 2.5e-3, DRIFT = -5e-5, OFF = 1.7e-3;

/* A value written in place of value BAD_I of frame BAD_K of stream 0 (none: BAD_K = SIZE_MAX). */
static size_t bad_k = SIZE_MAX, bad_i;
static double bad_v;

/* WFS frame k (0-based) ends at E0 + (k + 1) ms; its value is k. */
static void write_wfs(const char *dir, int stream, size_t k0, size_t k1, size_t drop)
{
    const size_t nv = stream ? 2 : 3;
    size_t n = 0;
    swfs_real *a = stream ? swfs_real_alloc(nv, k1 - k0, 1) : swfs_real_alloc(nv, 1, k1 - k0);
    uint64_t cnt[NW];
    int64_t st[NW];
    for (size_t k = k0; k < k1; k++) {
        if (k == drop) continue;
        for (size_t i = 0; i < nv; i++) a->data[n * nv + i] = stream ? -(double)k : (double)k;
        if (!stream && k == bad_k) a->data[n * nv + bad_i] = bad_v;
        cnt[n] = k + 1;
        st[n] = E0 + (int64_t)(k + 1) * 1000000 + (stream ? 100000 : 0);
        n++;
    }
    if (stream) a->ny = n;
    else a->nz = n;
    char stem[256], path[8192], txt[8192];
    swfs_milk_file_stem(stream ? "b" : "a", st[0], stem, sizeof stem);
    snprintf(path, sizeof path, "%s/%s.fits", dir, stem);
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, a, -64));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_milk_txt_path(path, txt, sizeof txt));
    assert_ok(swfs_milk_txt_write(txt, cnt, st, NULL, n, 0));
    swfs_real_free(a);
}

/* Camera frame j's exposure ends at 20 ms + (j + 1) 2.5 ms on the WFS clock; frame 17 dropped.
 * Pixel values: the frame number. */
static void write_camera(const char *path, int64_t *tend)
{
    uint64_t cnt[NC];
    int64_t st[NC];
    double track[4 * NC];
    swfs_real *a = swfs_real_alloc(4, 4, NC - 1);
    size_t n = 0;
    for (size_t j = 0; j < NC; j++) {
        if (j == 17) continue;
        const double tw = 0.020 + (double)(j + 1) * EXPT;
        tend[n] = E0 + llround(1e9 * tw);
        cnt[n] = j + 1;
        st[n] = E0 + llround(1e9 * (tw - OFF) / (1 + DRIFT)); /* the camera's clock */
        for (size_t q = 0; q < 16; q++) a->data[n * 16 + q] = (double)j;
        memset(track + 4 * n, 0, 4 * sizeof *track);
        n++;
    }
    const char *cubes[] = {"cam.fits"};
    swfs_science_meta m = {NAN, 1, NAN, 1, cubes, 0, 1, cnt, st, EXPT / (1 + DRIFT), 0}; /* the camera's clock */
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, a, -64));
    assert_ok(swfs_science_write_meta(o, &m, track, n));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(a);
}

/* The exact mean of floor(x) over [x0, x1). */
static double mean_floor(double x0, double x1)
{
    double s = 0;
    for (double k = floor(x0); k < x1; k++) s += k * (fmin(x1, k + 1) - fmax(x0, k));
    return s / (x1 - x0);
}

/* Two WFS logs (folders a and b, written by the caller) and a camera cube in a fresh folder
 * NAME, with the clock that maps the camera's stamps onto them and the source's options. */
typedef struct {
    char da[4200], db[4200], sci[4200];
    const char *logs[2];
    swfs_clock c;
    swfs_milk_source_options o;
} fixture;

static void fixture_dirs(fixture *f, const char *name)
{
    const char *d = test_path(name);
    char cmd[4200];
    snprintf(cmd, sizeof cmd, "rm -rf '%s' && mkdir -p '%s/a' '%s/b'", d, d, d);
    assert_int_equal(system(cmd), 0);
    snprintf(f->da, sizeof f->da, "%s/a", d);
    snprintf(f->db, sizeof f->db, "%s/b", d);
    snprintf(f->sci, sizeof f->sci, "%s/sci.fits", d);
}

static void fixture_camera(fixture *f)
{
    int64_t tend[NC];
    write_camera(f->sci, tend);
    memset(&f->c, 0, sizeof f->c);
    f->c.epoch = E0;
    f->c.offset = OFF;
    f->c.drift = DRIFT;
    f->c.fit.sign_x = f->c.fit.sign_y = 1;
    f->logs[0] = f->da;
    f->logs[1] = f->db;
    const swfs_milk_source_options o = {f->logs, 2, f->sci, &f->c, 0, 5, 4, 4, 4, NULL, 0};
    f->o = o;
}

static void test_batches(void **state)
{
    (void)state;
    static fixture f;
    fixture_dirs(&f, "msrc");
    write_wfs(f.da, 0, 0, 200, 61);  /* frame 61 dropped: exposures over it are incomplete */
    write_wfs(f.da, 0, 200, NW, NW);
    write_wfs(f.db, 1, 0, NW, NW);
    fixture_camera(&f);
    swfs_milk_source_options o = f.o;
    swfs_milk_source *s = NULL;
    assert_ok(swfs_milk_source_open(&s, &o));
    size_t seen = 0, checked = 0;
    for (;;) {
        swfs_batch b;
        assert_ok(swfs_milk_source_next(s, &b));
        if (!b.nexp) break;
        for (size_t j = 0; j < b.nexp; j++, seen++) {
            const swfs_exposure *e = &b.sched[j];
            const size_t fr = (size_t)b.science[j * 16];
            double sw = 0, sa = 0, sb = 0;
            for (size_t q = 0; q < e->count; q++) {
                const double w = q == 0 ? e->w_first : q + 1 == e->count ? e->w_last : 1.0;
                sw += w;
                sa += w * b.slopes[(e->first + q) * 5];
                sb += w * b.slopes[(e->first + q) * 5 + 3];
            }
            const double x1 = 20.0 + (double)(fr + 1) * 2.5, want = mean_floor(x1 - 2.5, x1);
            assert_close(sw, 2.5, 1e-5); /* WFS frames; 1e-5 = 10 ns: the stamps are whole ns */
            assert_close(sa / sw, want, 1e-5);
            assert_close(sb / sw, -want, 1e-5);
            checked++;
        }
    }
    swfs_milk_source_stats st;
    swfs_milk_source_get_stats(s, &st);
    printf("test_milksource: %zu exposures checked; used %llu, incomplete %llu, dropped WFS %llu camera %llu\n", checked,
           (unsigned long long)st.sync.used, (unsigned long long)st.sync.incomplete,
           (unsigned long long)st.sync.wfs_dropped, (unsigned long long)st.sync.camera_dropped);
    assert_int_equal(st.sync.camera_dropped, 1);
    assert_int_equal(st.sync.wfs_dropped, 1);
    assert_int_equal(st.wfs_dropped_log, 1);
    assert_int_equal(st.camera_dropped_log, 1);
    assert_int_equal(st.sync.incomplete, 1); /* the exposure [60, 62.5) ms over WFS frame 61 ([61, 62) ms) */
    assert_int_equal(seen, NC - 1 - 1);
    swfs_milk_source_close(s);
    /* the reconstructor's width against the logs' 3 + 2 values */
    o.nslopes = 6;
    assert_int_not_equal(swfs_milk_source_open(&s, &o), 0);
    assert_non_null(strstr(swfs_last_error(), "5 values per frame but the reconstructor expects 6"));
}

/* A WFS value that is not finite: named with its file, frame and counter as "not finite (NaN
 * or infinite)", for an infinity too (CFITSIO reads it as NaN: the message said "is nan");
 * one beyond 1e30 with its value. */
static void test_bad_values(void **state)
{
    (void)state;
    const double vals[] = {INFINITY, -INFINITY, NAN, 3e38};
    const char *want[] = {"is not finite (NaN or infinite)", "is not finite (NaN or infinite)",
                          "is not finite (NaN or infinite)", "is 3e+38"};
    for (int t = 0; t < 4; t++) {
        static fixture f;
        fixture_dirs(&f, "msrc_bad");
        bad_k = 30, bad_i = 1, bad_v = vals[t];
        write_wfs(f.da, 0, 0, NW, NW);
        bad_k = SIZE_MAX;
        write_wfs(f.db, 1, 0, NW, NW);
        fixture_camera(&f);
        swfs_milk_source *s = NULL;
        assert_ok(swfs_milk_source_open(&s, &f.o));
        int rc = 0;
        for (int n = 0; n < 1000 && !rc; n++) {
            swfs_batch b;
            rc = swfs_milk_source_next(s, &b);
            assert_true(rc || b.nexp); /* refused before the logs end */
        }
        swfs_milk_source_close(s);
        assert_int_equal(rc, SWFS_ERR_VALUE);
        print_message("%s\n", swfs_last_error());
        char msg[256];
        snprintf(msg, sizeof msg, ".fits: value 1 of frame 30 (cnt0 31) %s; telemetry values must be finite and below "
                 "1e+30 in magnitude", want[t]);
        assert_non_null(strstr(swfs_last_error(), msg));
        assert_non_null(strstr(swfs_last_error(), "msrc_bad/a/"));
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_batches), cmocka_unit_test(test_bad_values)};
    return cmocka_run_group_tests(tests, NULL, NULL);
}

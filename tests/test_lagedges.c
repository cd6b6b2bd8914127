/* A space-time map's lags across telemetry files (run_internal.h swfs_lag_edges_): a series
 * cut into two numbered files that continue each other is stacked as the whole series would
 * be, across the boundary, from either file; where frames were lost between them the
 * telemetry's own check says so and that side is left to the clamping; a neighbour of another
 * width or cut short leaves that side clamped too, its reason kept with the file named. */
#include "testutil.h"

#include "../src/run/run_internal.h"
#include "specklewfs/fits.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#define NS 8     /* slopes per frame */
#define NT 600   /* frames of the whole series */

/* A slowly varying series: frame f, value i = sin(0.03 f (1 + i / 8) + i). */
static double value(size_t f, size_t i) { return sin(0.03 * (double)f * (1.0 + (double)i / 8) + (double)i); }

/* Frames [f0, f1) of the series as telemetry file dir/name (width ns). */
static void write_part(const char *dir, const char *name, size_t f0, size_t f1, size_t ns)
{
    char path[1200];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    swfs_real *a = swfs_real_alloc(ns, f1 - f0, 1);
    for (size_t f = f0; f < f1; f++)
        for (size_t i = 0; i < ns; i++) a->data[(f - f0) * ns + i] = value(f, i % NS);
    swfs_fits_out *o = NULL;
    unlink(path);
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, a, -64));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(a);
}

static swfs_real *read_part(const char *dir, const char *name)
{
    char path[1200];
    snprintf(path, sizeof path, "%s/%s", dir, name);
    swfs_real *s = NULL;
    assert_ok(swfs_telemetry_read(path, NS, &s, NULL));
    return s;
}

/* dir/slopes_000.fits (frames 0..299) and dir/slopes_001.fits (frames from next0 on, of
 * width ns1); the edges of the first loaded into *e with a margin of 15; *s0 its frames. */
static void pair_case(const char *dir, size_t next0, size_t ns1, swfs_lag_edges_ *e, swfs_real **s0)
{
    static const swfs_timing none = {0};
    write_part(dir, "slopes_000.fits", 0, 300, NS);
    write_part(dir, "slopes_001.fits", next0, NT, ns1);
    *s0 = read_part(dir, "slopes_000.fits");
    assert_ok(swfs_lag_edges_load_(e, dir, &none, "slopes_000.fits", *s0, 15));
}

static void test_lag_edges(void **state)
{
    (void)state;
    char dir[1024], lost[1024], wide[1024];
    snprintf(dir, sizeof dir, "%s", test_path("lagedges"));
    snprintf(lost, sizeof lost, "%s", test_path("lagedges_lost"));
    snprintf(wide, sizeof wide, "%s", test_path("lagedges_wide"));
    mkdir(dir, 0755);
    mkdir(lost, 0755);
    mkdir(wide, 0755);
    write_part(dir, "slopes_000.fits", 0, 300, NS);
    write_part(dir, "slopes_001.fits", 300, NT, NS);
    swfs_timing t = {0};
    const long lags[3] = {0, -15, 15};
    double whole[NT * NS], got[20 * 3 * NS], want[20 * 3 * NS];
    for (size_t f = 0; f < NT; f++)
        for (size_t i = 0; i < NS; i++) whole[f * NS + i] = value(f, i);

    /* from the first file: the second's first 15 frames appended, none before */
    swfs_lag_edges_ e = {0};
    swfs_real *s0 = read_part(dir, "slopes_000.fits"), *s1 = read_part(dir, "slopes_001.fits");
    assert_ok(swfs_lag_edges_load_(&e, dir, &t, "slopes_000.fits", s0, 15));
    assert_int_equal(e.pre, 0);
    assert_int_equal(e.post, 15);
    assert_int_equal(e.joined, 1);
    /* frames 280..299 of the whole series (the file's last), lags 0, -15, +15: the same stacked input */
    swfs_slopes_stack(e.ext, e.pre + e.ny + e.post, NS, lags, 3, e.pre + 280, 20, got);
    swfs_slopes_stack(whole, NT, NS, lags, 3, 280, 20, want);
    assert_memory_equal(got, want, sizeof got);
    /* from the second file: the first's last 15 frames prepended; its own end clamps */
    assert_ok(swfs_lag_edges_load_(&e, dir, &t, "slopes_001.fits", s1, 15));
    assert_int_equal(e.pre, 15);
    assert_int_equal(e.post, 0);
    assert_int_equal(e.joined, 2);
    swfs_slopes_stack(e.ext, e.pre + e.ny + e.post, NS, lags, 3, e.pre + 0, 20, got); /* frames 300..319 */
    swfs_slopes_stack(whole, NT, NS, lags, 3, 300, 20, want);
    assert_memory_equal(got, want, sizeof got);
    printf("test_lagedges: contiguous files: %zu boundaries joined, the stacked input as the whole series'\n", e.joined);

    /* ten frames lost between the files: the telemetry says they do not continue each other */
    swfs_lag_edges_ l = {0};
    swfs_real *l0 = NULL;
    pair_case(lost, 310, NS, &l, &l0);
    printf("test_lagedges: ten frames lost between the files: %zu joined, %zu clamped\n", l.joined, l.clamped);
    assert_int_equal(l.post, 0);
    assert_int_equal(l.joined, 0);
    assert_int_equal(l.clamped, 1);
    swfs_slopes_stack(l.ext, l.pre + l.ny + l.post, NS, lags, 3, 290, 10, got); /* clamped to frame 299 */
    for (size_t k = 0; k < NS; k++) assert_true(got[(9 * 3 + 2) * NS + k] == whole[299 * NS + k]);

    /* a neighbour of another width, then one cut short: that side clamps, the reason kept with
     * the file named; the file's own frames stay as they are */
    swfs_lag_edges_ w = {0};
    swfs_real *w0 = NULL;
    pair_case(wide, 300, NS + 2, &w, &w0);
    printf("test_lagedges: a neighbour of another width: %zu unreadable (%s)\n", w.unreadable, w.why);
    assert_int_equal(w.unreadable, 1);
    assert_int_equal(w.post, 0);
    assert_int_equal(w.joined, 0);
    assert_non_null(strstr(w.why, "lagedges_wide/slopes_001.fits"));
    assert_non_null(strstr(w.why, "expected 8 slopes"));
    assert_memory_equal(w.ext, w0->data, 300 * NS * sizeof(double));
    char cut[1200];
    snprintf(cut, sizeof cut, "%s/slopes_001.fits", wide);
    write_part(wide, "slopes_001.fits", 300, NT, NS);
    assert_int_equal(truncate(cut, 4000), 0); /* the header and part of the data */
    assert_ok(swfs_lag_edges_load_(&w, wide, &t, "slopes_000.fits", w0, 15));
    printf("test_lagedges: a neighbour cut short: %zu unreadable (%s)\n", w.unreadable, w.why);
    assert_int_equal(w.unreadable, 2);
    assert_int_equal(w.post, 0);
    assert_non_null(strstr(w.why, "slopes_001.fits"));

    swfs_lag_edges_free_(&e);
    swfs_lag_edges_free_(&l);
    swfs_lag_edges_free_(&w);
    swfs_real_free(s0);
    swfs_real_free(s1);
    swfs_real_free(l0);
    swfs_real_free(w0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_lag_edges)};
    return cmocka_run_group_tests(tests, NULL, NULL);
}

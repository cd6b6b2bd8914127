/* milk / cacao stream logs (milklog.h): exact time stamps from their text, the file layouts
 * (N x 1 x T cubes, N x T images, tile-compressed files), files ordered by their first stamp,
 * drops from cnt0, the acquisition-time fallback, and the errors: row count, stamps back. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/milklog.h"
#include "specklewfs/status.h"

#include <fitsio.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

static const int64_t T0 = 1700000000LL * 1000000000LL;

static void test_time_text(void **state)
{
    (void)state;
    int64_t ns = 0;
    assert_ok(swfs_milk_parse_time("1700000000.123456789", &ns));
    assert_true(ns == 1700000000123456789LL);
    assert_ok(swfs_milk_parse_time("1700000000.1", &ns));
    assert_true(ns == 1700000000100000000LL);
    assert_ok(swfs_milk_parse_time("12.0000000015", &ns)); /* the tenth decimal rounds */
    assert_true(ns == 12000000002LL);
    assert_ok(swfs_milk_parse_time("1.7e9", &ns));
    assert_true(ns == 1700000000000000000LL);
    assert_int_not_equal(swfs_milk_parse_time("-1.5", &ns), 0);
    assert_int_not_equal(swfs_milk_parse_time("17x", &ns), 0);
    char buf[40];
    swfs_milk_format_time(1700000000000000042LL, buf, sizeof buf);
    assert_string_equal(buf, "1700000000.000000042");
    assert_ok(swfs_milk_parse_time(buf, &ns));
    assert_true(ns == 1700000000000000042LL);
    swfs_milk_file_stem("aol0_modeval", T0 + 3723LL * 1000000000LL + 5, buf, sizeof buf); /* 22:13:20 UTC + 1:02:03 + 5 ns */
    assert_string_equal(buf + strlen(buf) - 18, "23:15:23.000000005");
}

/* A log file of n frames of nv values (frame k value i = base + 100 k + i) as N x 1 x T
 * (layout 0), N x T (1) or tile-compressed N x 1 x T (2), and its table. */
static void write_log(const char *dir, size_t n, size_t nv, double base, const uint64_t *cnt, const int64_t *st,
                      int layout, double exptime)
{
    char stem[256], path[4096];
    swfs_milk_file_stem("wfs", st[0], stem, sizeof stem);
    snprintf(path, sizeof path, "%s/%s.fits%s", dir, stem, layout == 2 ? ".fz" : "");
    swfs_real *a = layout == 1 ? swfs_real_alloc(nv, n, 1) : swfs_real_alloc(nv, 1, n);
    for (size_t k = 0; k < n; k++)
        for (size_t i = 0; i < nv; i++) a->data[k * nv + i] = base + 100.0 * (double)k + (double)i;
    if (layout == 2) {
        fitsfile *fp = NULL;
        int s = 0;
        long ax[3] = {(long)nv, 1, (long)n};
        char name[4200];
        snprintf(name, sizeof name, "!%s[compress R]", path);
        fits_create_file(&fp, name, &s);
        fits_create_img(fp, LONG_IMG, 3, ax, &s);
        fits_write_img(fp, TDOUBLE, 1, (LONGLONG)(n * nv), a->data, &s);
        fits_close_file(fp, &s);
        assert_int_equal(s, 0);
    } else {
        swfs_fits_out *o = NULL;
        assert_ok(swfs_fits_out_create(&o, path));
        assert_ok(swfs_fits_out_real(o, NULL, a, -64));
        if (exptime > 0) assert_ok(swfs_fits_out_key_double(o, "EXPTIME", exptime, "[s]"));
        assert_ok(swfs_fits_out_commit(o));
    }
    swfs_real_free(a);
    char txt[4096];
    assert_ok(swfs_milk_txt_path(path, txt, sizeof txt));
    assert_ok(swfs_milk_txt_write(txt, cnt, st, NULL, n, 0));
}

static void fresh_dir(const char *d)
{
    char cmd[4200];
    snprintf(cmd, sizeof cmd, "rm -rf '%s' && mkdir -p '%s'", d, d);
    assert_int_equal(system(cmd), 0);
}

static void test_log_three_files(void **state)
{
    (void)state;
    const char *d = test_path("milk_a");
    fresh_dir(d);
    /* frames every 0.5 ms + 7 ns, counters 10..: one dropped between files 0 and 1, one in file 2 */
    uint64_t c[12];
    int64_t t[12];
    size_t k = 0;
    for (uint64_t cn = 10; k < 12; cn++) {
        if (cn == 14 || cn == 20) continue;
        c[k] = cn;
        t[k] = T0 + (int64_t)(cn - 10) * 500007;
        k++;
    }
    write_log(d, 4, 3, 0, c, t, 0, 2e-4);
    write_log(d, 4, 3, 400, c + 4, t + 4, 1, 0);
    write_log(d, 4, 3, 800, c + 8, t + 8, 2, 0);
    swfs_milklog *l = NULL;
    const char *paths[] = {d};
    assert_ok(swfs_milklog_open(&l, paths, 1));
    const swfs_milklog_info *in = swfs_milklog_get_info(l);
    assert_int_equal(in->nframes, 12);
    assert_int_equal(in->nvals, 3);
    assert_int_equal(in->nfiles, 3);
    assert_int_equal(in->dropped, 2);
    assert_close(in->exptime, 2e-4, 1e-12);
    for (size_t j = 0; j < 12; j++) {
        assert_true(swfs_milklog_counters(l)[j] == c[j]);
        assert_true(swfs_milklog_stamps(l)[j] == t[j]);
    }
    double buf[8 * 3];
    assert_ok(swfs_milklog_read(l, 2, 8, buf)); /* across all three files */
    for (size_t j = 0; j < 8; j++) {
        const size_t g = j + 2, file = g / 4, row = g % 4;
        assert_close(buf[3 * j + 1], 400.0 * (double)file + 100.0 * (double)row + 1, 1e-9);
    }
    swfs_milklog_free(l);
}

static void test_acq_fallback_and_two_columns(void **state)
{
    (void)state;
    const char *d = test_path("milk_b");
    fresh_dir(d);
    char p[4200];
    snprintf(p, sizeof p, "%s/t7.txt", d);
    FILE *f = fopen(p, "w");
    fprintf(f, "# comment\n0 0 0.0 1700000000.000000100 1700000000.000000200 5 5\n"
               "1 1 0.001 1700000000.001000100 0.0 6 6\n");
    fclose(f);
    uint64_t *c = NULL;
    int64_t *t = NULL;
    size_t n = 0;
    assert_ok(swfs_milk_txt_read(p, &c, &t, &n));
    assert_int_equal(n, 2);
    assert_true(t[0] == T0 + 200 && t[1] == T0 + 1000100 && c[1] == 6);
    free(c);
    free(t);
    snprintf(p, sizeof p, "%s/t2.txt", d);
    f = fopen(p, "w");
    fprintf(f, "3 1700000000.5\n4 1700000000.25\n");
    fclose(f);
    assert_int_not_equal(swfs_milk_txt_read(p, &c, &t, &n), 0);
    assert_non_null(strstr(swfs_last_error(), "t2.txt:2"));
    assert_non_null(strstr(swfs_last_error(), "1700000000.250000000"));
    assert_non_null(strstr(swfs_last_error(), "goes back"));
}

static void test_row_count_mismatch(void **state)
{
    (void)state;
    const char *d = test_path("milk_c");
    fresh_dir(d);
    uint64_t c[5] = {1, 2, 3, 4, 5};
    int64_t t[5] = {T0, T0 + 10, T0 + 20, T0 + 30, T0 + 40};
    write_log(d, 5, 2, 0, c, t, 0, 0);
    char stem[256], txt[4200], cmd[8600];
    swfs_milk_file_stem("wfs", T0, stem, sizeof stem);
    snprintf(txt, sizeof txt, "%s/%s.txt", d, stem);
    snprintf(cmd, sizeof cmd, "sed -i '$d' '%s'", txt); /* the table loses its last row */
    assert_int_equal(system(cmd), 0);
    swfs_milklog *l = NULL;
    const char *paths[] = {d};
    assert_int_not_equal(swfs_milklog_open(&l, paths, 1), 0);
    const char *m = swfs_last_error();
    assert_non_null(strstr(m, "holds 5 frames"));
    assert_non_null(strstr(m, "lists 4"));
    assert_non_null(strstr(m, ".txt"));
    assert_non_null(strstr(m, ".fits"));
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_time_text),
        cmocka_unit_test(test_log_three_files),
        cmocka_unit_test(test_acq_fallback_and_two_columns),
        cmocka_unit_test(test_row_count_mismatch),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

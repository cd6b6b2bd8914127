/* FITS round trips (real, complex, integer BITPIX with BZERO/BSCALE) and bad files. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <dirent.h>
#include <fitsio.h>
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static void test_real_and_complex_round_trip(void **state)
{
    (void)state;
    const char *path = test_path("rt.fits");
    remove(path);
    swfs_real *r = swfs_real_alloc(7, 5, 3);
    swfs_cplx *c = swfs_cplx_alloc(7, 5, 3);
    for (size_t k = 0; k < swfs_real_size(r); k++) {
        r->data[k] = sin(0.37 * (double)k) * 1e3;
        c->data[k] = cos(0.11 * (double)k) + I * (double)k;
    }
    r->data[4] = NAN; /* NaN survives as NaN */
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6; g.teldiam = 6.5; g.obscur = 0.1; g.pixscale = 0.25; g.pupdx = 0.04; g.pupn = 163;
    const char *prov[] = {"specklewfs test", "param=1"};
    swfs_fits_out *o;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_set_stamp(o, &g, prov, 2));
    assert_ok(swfs_fits_out_real(o, "R64", r, -64));
    assert_ok(swfs_fits_out_real(o, "R32", r, -32));
    assert_ok(swfs_fits_out_cplx(o, "C64", c, -64));
    assert_ok(swfs_fits_out_begin(o, "C32", 7, 5, 3, 1, -32));
    for (size_t k = 0; k < 3; k++) assert_ok(swfs_fits_out_cplx_frames(o, k, 1, swfs_cplx_frame(c, k)));
    assert_false(test_file_exists(path)); /* nothing at the final name before commit */
    assert_ok(swfs_fits_out_commit(o));
    assert_true(test_file_exists(path));

    swfs_real *r2;
    swfs_geom g2;
    assert_ok(swfs_fits_read_real(path, "R64", &r2, &g2));
    assert_int_equal(r2->nx, 7); assert_int_equal(r2->ny, 5); assert_int_equal(r2->nz, 3);
    for (size_t k = 0; k < swfs_real_size(r); k++) {
        if (k == 4) assert_true(isnan(r2->data[k]));
        else assert_true(r2->data[k] == r->data[k]);
    }
    assert_close(g2.wavelen, 3.8e-6, 0); assert_close(g2.pixscale, 0.25, 0);
    assert_int_equal(g2.pupn, 163);
    assert_ok(swfs_geom_require(&g2, "rt.fits"));
    swfs_real_free(r2);
    assert_ok(swfs_fits_read_real(path, "R32", &r2, NULL));
    for (size_t k = 0; k < swfs_real_size(r); k++)
        if (k != 4) assert_close(r2->data[k], r->data[k], 1e-4);
    swfs_real_free(r2);

    swfs_cplx *c2;
    assert_ok(swfs_fits_read_cplx(path, "C64", &c2, NULL));
    for (size_t k = 0; k < swfs_cplx_size(c); k++) assert_true(c2->data[k] == c->data[k]);
    swfs_cplx_free(c2);
    /* Frame-by-frame read of the single-precision cube. */
    swfs_fits_in *f;
    assert_ok(swfs_fits_in_open(&f, path, "C32"));
    assert_true(swfs_fits_in_shape(f)->is_complex);
    double complex frame[35];
    assert_ok(swfs_fits_in_read_cplx(f, 2, 1, frame));
    for (size_t k = 0; k < 35; k++) assert_close(cabs(frame[k] - c->data[70 + k]), 0, 1e-4 * (1 + cabs(c->data[70 + k])));
    /* A real read of a complex HDU is a format error naming the file. */
    double rb[35];
    assert_int_equal(swfs_fits_in_read_real(f, 0, 1, rb), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "rt.fits"));
    assert_int_equal(swfs_fits_in_read_cplx(f, 3, 1, frame), SWFS_ERR_ARG); /* beyond the cube */
    /* Provenance and version recorded on the extension. */
    char ver[80];
    int found = 0;
    assert_ok(swfs_fits_in_key_string_opt(f, "SWFSVER", ver, sizeof ver, &found));
    assert_true(found);
    assert_int_equal(swfs_fits_in_move(f, "NOPE"), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "NOPE"));
    swfs_fits_in_close(f);
    /* A copy of every HDU with a key added to the primary one: the data and the old keys as
     * they were, the checksums written anew (the reader verifies them), nothing at the copy's
     * name until commit. */
    const char *cp = test_path("rt_copy.fits");
    remove(cp);
    assert_ok(swfs_fits_out_copy(&o, path, cp));
    assert_ok(swfs_fits_out_key_string(o, "ADDED", "yes", "a key of the copy"));
    assert_false(test_file_exists(cp));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_fits_read_cplx(cp, "C64", &c2, NULL));
    for (size_t k = 0; k < swfs_cplx_size(c); k++) assert_true(c2->data[k] == c->data[k]);
    swfs_cplx_free(c2);
    assert_ok(swfs_fits_in_open(&f, cp, NULL));
    char added[16];
    found = 0;
    assert_ok(swfs_fits_in_key_string_opt(f, "ADDED", added, sizeof added, &found));
    assert_true(found);
    assert_string_equal(added, "yes");
    swfs_fits_in_close(f);
    assert_int_equal(swfs_fits_out_copy(&o, test_path("no_such.fits"), cp), SWFS_ERR_IO);
    swfs_real_free(r);
    swfs_cplx_free(c);
}

static void test_integer_bitpix_with_bzero(void **state)
{
    (void)state;
    /* A camera cube as a 16-bit unsigned image (BITPIX 16, BZERO 32768) and a scaled one
     * (BSCALE 0.5, BZERO 100): both come back as physical values. */
    const char *path = test_path("u16.fits");
    remove(path);
    fitsfile *fp;
    int st = 0;
    long naxes[3] = {4, 3, 2};
    fits_create_file(&fp, path, &st);
    fits_create_img(fp, USHORT_IMG, 3, naxes, &st);
    unsigned short v[24];
    for (int k = 0; k < 24; k++) v[k] = (unsigned short)(60000 - 1000 * k);
    fits_write_img(fp, TUSHORT, 1, 24, v, &st);
    fits_create_img(fp, SHORT_IMG, 3, naxes, &st);
    double bscale = 0.5, bzero = 100.0;
    fits_write_key(fp, TDOUBLE, "BSCALE", &bscale, NULL, &st);
    fits_write_key(fp, TDOUBLE, "BZERO", &bzero, NULL, &st);
    fits_write_key(fp, TSTRING, "EXTNAME", "SCALED", NULL, &st);
    fits_set_bscale(fp, 0.5, 100.0, &st);
    short raw[24];
    for (int k = 0; k < 24; k++) raw[k] = (short)(k - 12);
    fits_set_bscale(fp, 1.0, 0.0, &st); /* write raw integers */
    fits_write_img(fp, TSHORT, 1, 24, raw, &st);
    fits_close_file(fp, &st);
    assert_int_equal(st, 0);

    swfs_real *a;
    assert_ok(swfs_fits_read_real(path, NULL, &a, NULL));
    assert_int_equal(a->nz, 2);
    for (int k = 0; k < 24; k++) assert_close(a->data[k], 60000.0 - 1000.0 * k, 0);
    swfs_real_free(a);
    assert_ok(swfs_fits_read_real(path, "SCALED", &a, NULL));
    for (int k = 0; k < 24; k++) assert_close(a->data[k], 100.0 + 0.5 * (k - 12), 0);
    swfs_real_free(a);
}

/* A number's resolution as its header text shows it (swfs_fits_in_key_double_res_opt): half a
 * unit in the last digit written, whatever the exponent letter. */
static void test_key_resolution(void **state)
{
    (void)state;
    const char *path = test_path("keyres.fits");
    remove(path);
    fitsfile *fp;
    int st = 0;
    long naxes[2] = {2, 2};
    fits_create_file(&fp, path, &st);
    fits_create_img(fp, FLOAT_IMG, 2, naxes, &st);
    const char *cards[] = {"EXPA    =               0.0082 / 2 decimals", "EXPB    =             8.189E-3",
                           "EXPC    =                   12", "EXPD    =               1.0D-6",
                           "EXPE    =               -2.5e2", "EXPF    =                  10."};
    for (size_t k = 0; k < sizeof cards / sizeof cards[0]; k++) fits_write_record(fp, cards[k], &st);
    float z[4] = {0};
    fits_write_img(fp, TFLOAT, 1, 4, z, &st);
    fits_close_file(fp, &st);
    assert_int_equal(st, 0);
    const char *keys[] = {"EXPA", "EXPB", "EXPC", "EXPD", "EXPE", "EXPF", "EXPG"};
    const double val[] = {0.0082, 8.189e-3, 12, 1e-6, -250, 10, 0}, res[] = {5e-5, 5e-7, 0.5, 5e-8, 5, 0.5, 0};
    swfs_fits_in *f = NULL;
    assert_ok(swfs_fits_in_open(&f, path, NULL));
    for (size_t k = 0; k < sizeof keys / sizeof keys[0]; k++) {
        double v = -1, r = -1;
        int found = -1;
        assert_ok(swfs_fits_in_key_double_res_opt(f, keys[k], &v, &r, &found));
        assert_int_equal(found, k < 6);
        if (found) assert_close(v, val[k], 1e-15 * fabs(val[k]));
        assert_close(r, res[k], 1e-12 * res[k]);
    }
    swfs_fits_in_close(f);
}

static void test_bad_files(void **state)
{
    (void)state;
    swfs_real *a = NULL;
    /* Missing file. */
    assert_int_equal(swfs_fits_read_real(test_path("does-not-exist.fits"), NULL, &a, NULL), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "does-not-exist.fits"));
    /* Not FITS. */
    const char *txt = test_path("notfits.fits");
    FILE *f = fopen(txt, "w");
    fputs("this is not a FITS file\n", f);
    fclose(f);
    assert_int_not_equal(swfs_fits_read_real(txt, NULL, &a, NULL), SWFS_OK);
    assert_non_null(strstr(swfs_last_error(), "notfits.fits"));
    /* Truncated: a valid cube cut in half. */
    const char *full = test_path("full.fits");
    swfs_real *r = swfs_real_alloc(64, 64, 8);
    swfs_fits_out *o;
    assert_ok(swfs_fits_out_create(&o, full));
    assert_ok(swfs_fits_out_real(o, NULL, r, -32));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(truncate(full, 2880 * 30));
    assert_int_not_equal(swfs_fits_read_real(full, NULL, &a, NULL), SWFS_OK);
    print_message("truncated file: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "full.fits"));
    assert_null(a);
    /* Unwritable output: no file, no .part left behind. */
    assert_int_equal(swfs_fits_out_create(&o, test_path("no/such/dir/out.fits")), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "out.fits"));
    /* Abort removes the partial file. */
    const char *ab = test_path("aborted.fits");
    remove(ab);
    assert_ok(swfs_fits_out_create(&o, ab));
    assert_ok(swfs_fits_out_real(o, NULL, r, -32));
    swfs_fits_out_abort(o);
    assert_false(test_file_exists(ab));
    char part[1100];
    snprintf(part, sizeof part, "%s.part", ab);
    assert_false(test_file_exists(part));
    swfs_real_free(r);
    /* Missing geometry keyword is named. */
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 1e-6;
    assert_int_equal(swfs_geom_require(&g, "x.fits"), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "TELDIAM"));
}

/* Part files of `name` (NAME.part.<pid>.<n>) left in the test folder. */
static int parts_left(const char *name)
{
    char prefix[256];
    snprintf(prefix, sizeof prefix, "%s.part", name);
    DIR *d = opendir(SWFS_TEST_TMPDIR);
    int n = 0;
    for (struct dirent *e; d && (e = readdir(d));) n += strncmp(e->d_name, prefix, strlen(prefix)) == 0;
    if (d) closedir(d);
    return n;
}

/* BITPIX -32: a finite value single precision cannot hold (it would be stored as infinite and
 * read back as NaN) is refused, naming the file, the HDU, the value and its index; nothing is
 * written (a previous file of that name is kept). The frame-by-frame writer (reduce, speckles'
 * --match copies) checks its frames too; NaN, infinities and FLT_MAX itself are written. */
static void test_single_precision_overflow(void **state)
{
    (void)state;
    const char *path = test_path("f32.fits");
    remove(path);
    swfs_real *r = swfs_real_alloc(4, 3, 3);
    for (size_t k = 0; k < swfs_real_size(r); k++) r->data[k] = (double)k;
    swfs_fits_out *o;
    assert_ok(swfs_fits_out_create(&o, path)); /* the file a refused write must leave as it is */
    assert_ok(swfs_fits_out_real(o, NULL, r, -32));
    assert_ok(swfs_fits_out_commit(o));
    r->data[33] = -1e39; /* x 1, y 2, frame 2 */
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_begin(o, "CUBE", 4, 3, 3, 0, -32));
    assert_ok(swfs_fits_out_real_frames(o, 0, 2, r->data));
    assert_int_equal(swfs_fits_out_real_frames(o, 2, 1, swfs_real_frame(r, 2)), SWFS_ERR_VALUE);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "f32.fits: extension CUBE: value 33 (x 1, y 2, frame 2) is -1e+39, beyond "
                                              "single precision's largest 3.40282347e+38 (BITPIX -32 would store it as "
                                              "infinite, read back as NaN); BITPIX -64 holds it"));
    swfs_fits_out_abort(o);
    assert_int_equal(parts_left("f32.fits"), 0);
    swfs_real *back = NULL;
    assert_ok(swfs_fits_read_real(path, NULL, &back, NULL)); /* the earlier file, as it was */
    assert_close(back->data[33], 33.0, 0);
    swfs_real_free(back);
    /* the whole-array writer and complex values: the part named */
    swfs_cplx *c = swfs_cplx_alloc(2, 2, 1);
    c->data[3] = 1.0 + 1e300 * I;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_int_equal(swfs_fits_out_cplx(o, NULL, c, -32), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "f32.fits: the image: the imaginary part of value 3 (x 1, y 1, frame 0) is "
                                              "1e+300"));
    swfs_fits_out_abort(o);
    assert_int_equal(parts_left("f32.fits"), 0);
    /* at -64 the same values are written and read back exactly */
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, r, -64));
    assert_ok(swfs_fits_out_cplx(o, "Z", c, -64));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_fits_read_real(path, NULL, &back, NULL));
    assert_close(back->data[33], -1e39, 0);
    swfs_real_free(back);
    /* NaN, infinities (read back as NaN, as CFITSIO reads them) and the largest values that
     * round to FLT_MAX are written at -32; the first value beyond them is not */
    r->data[0] = NAN; r->data[1] = INFINITY; r->data[2] = -INFINITY; r->data[3] = FLT_MAX;
    r->data[33] = -0x1.fffffefffffffp+127; /* just below FLT_MAX + half its last unit: rounds to -FLT_MAX */
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, r, -32));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_fits_read_real(path, NULL, &back, NULL));
    assert_true(isnan(back->data[0]) && isnan(back->data[1]) && isnan(back->data[2]));
    assert_close(back->data[3], FLT_MAX, 0);
    assert_close(back->data[33], -FLT_MAX, 0);
    swfs_real_free(back);
    r->data[33] = -0x1.ffffffp+127;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_int_equal(swfs_fits_out_real(o, NULL, r, -32), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "value 33 (x 1, y 2, frame 2) is -3.40282357e+38"));
    swfs_fits_out_abort(o);
    swfs_cplx_free(c);
    swfs_real_free(r);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_real_and_complex_round_trip),
        cmocka_unit_test(test_integer_bitpix_with_bzero),
        cmocka_unit_test(test_key_resolution),
        cmocka_unit_test(test_bad_files),
        cmocka_unit_test(test_single_precision_overflow),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

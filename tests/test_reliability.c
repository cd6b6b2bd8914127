/* The reliability layer: the atomic writer (part files, cleanup, groups), the input and
 * output checks (outpaths.h), keywords read from their text, HDU sizes that overflow,
 * checksums, compressed inputs, and the physical ranges of the geometry. */
#include "testutil.h"

#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <dirent.h>
#include <fitsio.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static void write_text(const char *path, const char *text)
{
    FILE *f = fopen(path, "w");
    assert_non_null(f);
    fputs(text, f);
    fclose(f);
}

static int read_text(const char *path, char *buf, size_t cap)
{
    FILE *f = fopen(path, "r");
    if (!f) return -1;
    size_t n = fread(buf, 1, cap - 1, f);
    buf[n] = 0;
    fclose(f);
    return 0;
}

/* Files in dir whose name starts with prefix (part files left behind). */
static int count_prefixed(const char *dir, const char *prefix)
{
    DIR *d = opendir(dir);
    int n = 0;
    struct dirent *e;
    while (d && (e = readdir(d)))
        if (!strncmp(e->d_name, prefix, strlen(prefix))) n++;
    if (d) closedir(d);
    return n;
}

static const char *scratch(const char *name)
{
    static char dir[4096];
    snprintf(dir, sizeof dir, "%s", test_path(name));
    char cmd[8300];
    snprintf(cmd, sizeof cmd, "rm -rf '%s' && mkdir -p '%s'", dir, dir);
    assert_int_equal(system(cmd), 0);
    return dir;
}

static void test_atomic_text(void **state)
{
    (void)state;
    const char *dir = scratch("atomic");
    char path[4300], buf[256];
    snprintf(path, sizeof path, "%s/t.txt", dir);
    write_text(path, "old\n");

    /* Two writers of one name get different part files, next to it. */
    swfs_atomic *a = NULL, *b = NULL;
    assert_ok(swfs_atomic_begin(&a, path, 1));
    assert_ok(swfs_atomic_begin(&b, path, 1));
    assert_string_not_equal(swfs_atomic_part(a), swfs_atomic_part(b));
    assert_int_equal(strncmp(swfs_atomic_part(a), path, strlen(path)), 0);
    assert_int_equal(count_prefixed(dir, "t.txt.part."), 2);
    fputs("new\n", swfs_atomic_stream(a));
    read_text(path, buf, sizeof buf);
    assert_string_equal(buf, "old\n"); /* nothing at the final name before the commit */
    assert_ok(swfs_atomic_commit(a));
    read_text(path, buf, sizeof buf);
    assert_string_equal(buf, "new\n");
    swfs_atomic_abort(b); /* abort removes its part, leaves the file */
    assert_int_equal(count_prefixed(dir, "t.txt.part."), 0);
    read_text(path, buf, sizeof buf);
    assert_string_equal(buf, "new\n");

    /* A commit that cannot rename (the final name is a non-empty folder) removes its part
     * and leaves what was there. */
    char blocker[4400];
    snprintf(path, sizeof path, "%s/blocked", dir);
    snprintf(blocker, sizeof blocker, "%s/inside", path);
    assert_int_equal(mkdir(path, 0777), 0);
    write_text(blocker, "keep");
    assert_ok(swfs_atomic_begin(&a, path, 1));
    fputs("data", swfs_atomic_stream(a));
    assert_int_not_equal(swfs_atomic_commit(a), SWFS_OK);
    assert_non_null(strstr(swfs_last_error(), "blocked"));
    assert_int_equal(count_prefixed(dir, "blocked.part."), 0);
    assert_int_equal(read_text(blocker, buf, sizeof buf), 0);
    assert_string_equal(buf, "keep");

    /* A folder that does not exist: the message names it and the system's reason. */
    snprintf(path, sizeof path, "%s/nodir/x.txt", dir);
    assert_int_equal(swfs_atomic_begin(&a, path, 1), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "No such file or directory"));
}

/* The part files a signal handler removes before the process ends (swfs_atomic_remove_parts):
 * a part being written, and a group's finished parts, go; a product already renamed stays,
 * and so does a part no longer listed (committed, then the process goes on). */
static void test_atomic_parts_on_signal(void **state)
{
    (void)state;
    const char *dir = scratch("signal");
    char p1[4300], p2[4300], p3[4300];
    snprintf(p1, sizeof p1, "%s/done.txt", dir);
    snprintf(p2, sizeof p2, "%s/open.txt", dir);
    snprintf(p3, sizeof p3, "%s/grouped.txt", dir);
    swfs_atomic *a = NULL, *b = NULL, *c = NULL;
    assert_ok(swfs_atomic_begin(&a, p1, 1));
    fputs("1", swfs_atomic_stream(a));
    assert_ok(swfs_atomic_commit(a));
    assert_ok(swfs_atomic_begin(&b, p2, 1));
    fputs("2", swfs_atomic_stream(b));
    fflush(swfs_atomic_stream(b));
    swfs_outputs_begin();
    assert_ok(swfs_atomic_begin(&c, p3, 1));
    fputs("3", swfs_atomic_stream(c));
    assert_ok(swfs_atomic_commit(c));
    assert_int_equal(count_prefixed(dir, "open.txt.part."), 1);
    assert_int_equal(count_prefixed(dir, "grouped.txt.part."), 1);
    swfs_atomic_remove_parts();
    assert_int_equal(count_prefixed(dir, "open.txt.part."), 0);
    assert_int_equal(count_prefixed(dir, "grouped.txt.part."), 0);
    assert_true(test_file_exists(p1));
    /* (the process would end here; the test tidies up: the group's rename now fails) */
    assert_int_equal(swfs_outputs_end(1), SWFS_ERR_IO);
    swfs_atomic_abort(b);
    assert_false(test_file_exists(p2));
    assert_false(test_file_exists(p3));
}

static void test_atomic_groups(void **state)
{
    (void)state;
    const char *dir = scratch("groups");
    char p1[4300], p2[4300], buf[64];
    snprintf(p1, sizeof p1, "%s/a.txt", dir);
    snprintf(p2, sizeof p2, "%s/b.txt", dir);
    swfs_atomic *a = NULL;

    /* Committed inside a group: nothing in place until the group ends; end(0) removes all. */
    swfs_outputs_begin();
    assert_ok(swfs_atomic_begin(&a, p1, 1));
    fputs("1", swfs_atomic_stream(a));
    assert_ok(swfs_atomic_commit(a));
    assert_ok(swfs_atomic_begin(&a, p2, 1));
    fputs("2", swfs_atomic_stream(a));
    assert_ok(swfs_atomic_commit(a));
    assert_false(test_file_exists(p1));
    assert_false(test_file_exists(p2));
    assert_int_equal(count_prefixed(dir, "a.txt.part."), 1);
    assert_ok(swfs_outputs_end(0));
    assert_false(test_file_exists(p1));
    assert_int_equal(count_prefixed(dir, "a.txt.part."), 0);
    assert_int_equal(count_prefixed(dir, "b.txt.part."), 0);

    /* end(1): both in place; a nested group defers to the outer one. */
    swfs_outputs_begin();
    swfs_outputs_begin();
    assert_ok(swfs_atomic_begin(&a, p1, 1));
    fputs("1", swfs_atomic_stream(a));
    assert_ok(swfs_atomic_commit(a));
    assert_ok(swfs_outputs_end(1));
    assert_false(test_file_exists(p1));
    assert_ok(swfs_atomic_begin(&a, p2, 1));
    fputs("2", swfs_atomic_stream(a));
    assert_ok(swfs_atomic_commit(a));
    assert_ok(swfs_outputs_end(1));
    assert_int_equal(read_text(p1, buf, sizeof buf), 0);
    assert_string_equal(buf, "1");
    assert_int_equal(read_text(p2, buf, sizeof buf), 0);
    assert_string_equal(buf, "2");

    /* One rename of the group fails: the group's other new files are removed too. */
    remove(p1);
    remove(p2);
    char p3[4300], inside[4400];
    snprintf(p3, sizeof p3, "%s/c", dir);
    snprintf(inside, sizeof inside, "%s/x", p3);
    assert_int_equal(mkdir(p3, 0777), 0);
    write_text(inside, "x");
    swfs_outputs_begin();
    const char *paths[] = {p1, p3, p2};
    for (int k = 0; k < 3; k++) {
        assert_ok(swfs_atomic_begin(&a, paths[k], 1));
        fputs("v", swfs_atomic_stream(a));
        assert_ok(swfs_atomic_commit(a));
    }
    assert_int_not_equal(swfs_outputs_end(1), SWFS_OK);
    assert_false(test_file_exists(p1));
    assert_false(test_file_exists(p2));
    assert_int_equal(count_prefixed(dir, "a.txt.part."), 0);
    assert_int_equal(count_prefixed(dir, "b.txt.part."), 0);
    assert_int_equal(count_prefixed(dir, "c.part."), 0);
    assert_int_equal(swfs_outputs_end(0), SWFS_ERR_INTERNAL); /* no group open */
}

static swfs_real *small_image(double seed)
{
    swfs_real *r = swfs_real_alloc(6, 5, 1);
    for (size_t k = 0; k < 30; k++) r->data[k] = sin(seed + 0.3 * (double)k);
    return r;
}

static void write_image(const char *path, const swfs_real *r, const swfs_geom *g)
{
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    if (g) assert_ok(swfs_fits_out_set_stamp(o, g, NULL, 0));
    assert_ok(swfs_fits_out_real(o, "IMG", r, -64));
    assert_ok(swfs_fits_out_commit(o));
}

static void test_fits_writer_failures(void **state)
{
    (void)state;
    const char *dir = scratch("fitsw");
    char path[4300];
    snprintf(path, sizeof path, "%s/keep.fits", dir);
    swfs_real *r = small_image(0), *r2 = small_image(1), *back = NULL;
    write_image(path, r, NULL);

    /* An aborted rewrite leaves the previous file and no part. */
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, "IMG", r2, -64));
    swfs_fits_out_abort(o);
    assert_int_equal(count_prefixed(dir, "keep.fits.part"), 0);
    assert_ok(swfs_fits_read_real(path, "IMG", &back, NULL));
    assert_memory_equal(back->data, r->data, 30 * sizeof(double));
    swfs_real_free(back);

    /* A name with brackets is a name, not CFITSIO's extension syntax. */
    snprintf(path, sizeof path, "%s/o[1].fits", dir);
    write_image(path, r, NULL);
    struct stat sb;
    assert_int_equal(stat(path, &sb), 0);
    assert_ok(swfs_fits_read_real(path, "IMG", &back, NULL));
    assert_memory_equal(back->data, r->data, 30 * sizeof(double));
    swfs_real_free(back);

    /* Names CFITSIO or gzip would take for compressed files are refused as outputs. */
    snprintf(path, sizeof path, "%s/x.fits.gz", dir);
    assert_int_equal(swfs_fits_out_create(&o, path), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), ".gz"));
    assert_false(test_file_exists(path));
    swfs_real_free(r);
    swfs_real_free(r2);
}

static void test_checksums(void **state)
{
    (void)state;
    const char *dir = scratch("sums");
    char path[4300], bad[4300], cmd[14000];
    snprintf(path, sizeof path, "%s/good.fits", dir);
    snprintf(bad, sizeof bad, "%s/bad.fits", dir);
    swfs_real *r = small_image(2), *back = NULL;
    write_image(path, r, NULL);
    /* Every HDU carries DATASUM and CHECKSUM, and they verify. */
    fitsfile *fp = NULL;
    int st = 0, nhdu = 0;
    fits_open_diskfile(&fp, path, READONLY, &st);
    fits_get_num_hdus(fp, &nhdu, &st);
    assert_int_equal(nhdu, 2);
    for (int k = 1; k <= nhdu; k++) {
        int ds = 0, hs = 0;
        char v[FLEN_VALUE];
        fits_movabs_hdu(fp, k, NULL, &st);
        fits_read_keyword(fp, "DATASUM", v, NULL, &st);
        fits_verify_chksum(fp, &ds, &hs, &st);
        assert_int_equal(st, 0);
        assert_int_equal(ds, 1);
        assert_int_equal(hs, 1);
    }
    fits_close_file(fp, &st);
    /* One data byte changed: refused, naming file and HDU. */
    snprintf(cmd, sizeof cmd, "cp '%s' '%s' && printf '\\x40' | dd of='%s' bs=1 seek=%d conv=notrunc status=none", path,
             bad, bad, 2 * 2880 + 8 * 7 + 3);
    assert_int_equal(system(cmd), 0);
    assert_int_equal(swfs_fits_read_real(bad, "IMG", &back, NULL), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "bad.fits: HDU 2 (IMG): the data do not match their DATASUM"));
    /* A header edited behind CFITSIO's back: its CHECKSUM no longer matches. */
    snprintf(cmd, sizeof cmd, "cp '%s' '%s' && perl -0777 -pi -e 's/EXTNAME = .IMG     ./EXTNAME = \\x27IMG2    \\x27/' '%s'",
             path, bad, bad);
    assert_int_equal(system(cmd), 0);
    assert_int_equal(swfs_fits_read_real(bad, "IMG2", &back, NULL), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "does not match its CHECKSUM"));
    swfs_real_free(r);
}

/* A one-HDU FITS file with the given extra header cards (raw 80-character records). */
static void write_cards(const char *path, const char *const *cards, size_t n)
{
    remove(path);
    fitsfile *fp = NULL;
    int st = 0;
    long ax[2] = {4, 3};
    float d[12] = {0};
    fits_create_diskfile(&fp, (char *)path, &st);
    fits_create_img(fp, FLOAT_IMG, 2, ax, &st);
    for (size_t k = 0; k < n; k++) fits_write_record(fp, cards[k], &st);
    fits_write_img(fp, TFLOAT, 1, 12, d, &st);
    fits_close_file(fp, &st);
    assert_int_equal(st, 0);
}

static void test_keywords_from_text(void **state)
{
    (void)state;
    const char *path = test_path("keys.fits");
    swfs_fits_in *f = NULL;
    swfs_geom g;
    double v;
    long l;
    int found;
    char card[81];
    /* 69 digits: CFITSIO's integer conversion overflows its buffer on these. */
    snprintf(card, sizeof card, "PUPN    = %069d", 1);
    memset(card + 10, '9', 69);
    const char *const c1[] = {card};
    write_cards(path, c1, 1);
    assert_ok(swfs_fits_in_open(&f, path, NULL));
    assert_int_equal(swfs_fits_in_geom(f, &g), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "keys.fits: PUPN = 1.0000000000000001e+69, expected a whole number"));
    assert_int_equal(swfs_fits_in_key_long_opt(f, "PUPN", 2, 8192, &l, &found), SWFS_ERR_VALUE);
    swfs_fits_in_close(f);

    const char *const c2[] = {"WAVELEN =                    T / a logical", "TELDIAM = '6.5'", "PUPDX   = 4.0D-2",
                              "OBSCUR  =  (0.1, 0.2)", "PIXSCALE=", "RDNOISE =               1E999"};
    write_cards(path, c2, 6);
    assert_ok(swfs_fits_in_open(&f, path, NULL));
    assert_int_equal(swfs_fits_in_key_double_opt(f, "WAVELEN", &v, &found), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "keys.fits: WAVELEN = T is a logical"));
    assert_int_equal(swfs_fits_in_key_double_opt(f, "TELDIAM", &v, &found), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "is a string"));
    assert_ok(swfs_fits_in_key_double_opt(f, "PUPDX", &v, &found)); /* FITS D exponent */
    assert_true(found);
    assert_close(v, 0.04, 1e-15);
    assert_int_equal(swfs_fits_in_key_double_opt(f, "OBSCUR", &v, &found), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "complex"));
    assert_int_equal(swfs_fits_in_key_double_opt(f, "PIXSCALE", &v, &found), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "has no value"));
    assert_int_equal(swfs_fits_in_key_double_opt(f, "RDNOISE", &v, &found), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "not a finite number"));
    assert_ok(swfs_fits_in_key_double_opt(f, "NOSUCHK", &v, &found));
    assert_false(found);
    swfs_fits_in_close(f);
}

static void test_geometry_ranges(void **state)
{
    (void)state;
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6; g.teldiam = 6.5; g.obscur = 0.1; g.pixscale = 0.25; g.pupdx = 0.04; g.pupn = 163;
    assert_ok(swfs_geom_check(&g, "ok"));
    assert_ok(swfs_geom_require(&g, "ok"));
    struct { double *field; double bad; const char *phrase; } cases[] = {
        {&g.wavelen, 1e300, "WAVELEN = 1e+300 is outside its physical range"},
        {&g.wavelen, -1, "WAVELEN = -1"},
        {&g.pixscale, 1e-300, "PIXSCALE = 1e-300"},
        {&g.pixscale, 0, "PIXSCALE = 0 is outside"},
        {&g.pixscale, 1e300, "PIXSCALE = 1e+300"},
        {&g.teldiam, 1e9, "TELDIAM = 1e+09"},
        {&g.pupdx, 1e9, "PUPDX = 1e+09"},
        {&g.obscur, 1, "OBSCUR = 1 is outside"},
        {&g.pupdx, 4.0, "more than half of TELDIAM"},
        {&g.pupdx, 0.01, "does not hold TELDIAM"},
    };
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        const double keep = *cases[k].field;
        *cases[k].field = cases[k].bad;
        assert_int_equal(swfs_geom_check(&g, "x.fits"), SWFS_ERR_VALUE);
        if (!strstr(swfs_last_error(), cases[k].phrase)) fail_msg("case %zu: '%s'", k, swfs_last_error());
        *cases[k].field = keep;
    }
    g.pupn = 2147483647;
    assert_int_equal(swfs_geom_check(&g, "x.fits"), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "PUPN = 2147483647 is outside its range 2 .. 8192"));
}

/* An image extension whose NAXIS1 claims 2^63 - 1 values: refused at once (it used to
 * send the completeness check into an endless walk over HDU headers). */
static void test_huge_naxis(void **state)
{
    (void)state;
    const char *path = test_path("huge.fits");
    swfs_real *r = small_image(3), *back = NULL;
    remove(path);
    write_image(path, r, NULL);
    char cmd[4400];
    snprintf(cmd, sizeof cmd, "perl -0777 -pi -e 's/NAXIS1  =                    6/NAXIS1  =  9223372036854775807/' '%s'",
             path);
    assert_int_equal(system(cmd), 0);
    const clock_t t0 = clock();
    assert_int_equal(swfs_fits_read_real(path, "IMG", &back, NULL), SWFS_ERR_FORMAT);
    assert_true((double)(clock() - t0) / CLOCKS_PER_SEC < 5.0);
    assert_non_null(strstr(swfs_last_error(), "huge.fits: file is truncated or corrupt: HDU 2"));
    swfs_real_free(r);
}

static void test_paths(void **state)
{
    (void)state;
    const char *dir = scratch("paths");
    char in[4300], hard[4300], alias[4300], fifo[4300], sym[4300], out[4300], out2[4300], nodir[4300];
    snprintf(in, sizeof in, "%s/in.fits", dir);
    snprintf(hard, sizeof hard, "%s/hard.fits", dir);
    snprintf(alias, sizeof alias, "%s/./in.fits", dir);
    snprintf(fifo, sizeof fifo, "%s/fifo", dir);
    snprintf(sym, sizeof sym, "%s/sym.fits", dir);
    snprintf(out, sizeof out, "%s/new.fits", dir);
    snprintf(out2, sizeof out2, "%s/../paths/new.fits", dir);
    snprintf(nodir, sizeof nodir, "%s/none/x.fits", dir);
    write_text(in, "x");
    assert_int_equal(link(in, hard), 0);
    assert_int_equal(mkfifo(fifo, 0600), 0);
    assert_int_equal(symlink(in, sym), 0);

    struct { const char *in, *out, *out2; int rc; const char *phrase; } cases[] = {
        {in, out, NULL, SWFS_OK, NULL},
        {in, in, NULL, SWFS_ERR_ARG, "refusing to overwrite an input"},
        {in, alias, NULL, SWFS_ERR_ARG, "is the same file as the input"},
        {in, hard, NULL, SWFS_ERR_ARG, "is the same file as the input"},   /* a hard link */
        {sym, in, NULL, SWFS_ERR_ARG, "is the same file as the input"},    /* input through a link */
        {in, out, out2, SWFS_ERR_ARG, "every output needs its own name"}, /* not yet created */
        {fifo, out, NULL, SWFS_ERR_IO, "is a FIFO, not a regular file"},
        {in, fifo, NULL, SWFS_ERR_ARG, "is a FIFO"},
        {in, sym, NULL, SWFS_ERR_ARG, "is a symbolic link"},
        {in, "/dev/null", NULL, SWFS_ERR_ARG, "is a character device"},
        {"/dev/zero", out, NULL, SWFS_ERR_IO, "is a character device"},
        {in, dir, NULL, SWFS_ERR_ARG, "is a folder"},
        {in, nodir, NULL, SWFS_ERR_IO, "No such file or directory"},
    };
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        swfs_paths *p = NULL;
        assert_ok(swfs_paths_create(&p));
        swfs_paths_input(p, "input", cases[k].in);
        swfs_paths_output(p, "-o", cases[k].out);
        swfs_paths_output(p, "--other", cases[k].out2);
        int rc = swfs_paths_status(p);
        swfs_paths_free(p);
        if (rc != cases[k].rc) fail_msg("case %zu: rc %d, expected %d (%s)", k, rc, cases[k].rc, swfs_last_error());
        if (cases[k].phrase && !strstr(swfs_last_error(), cases[k].phrase))
            fail_msg("case %zu: '%s' lacks '%s'", k, swfs_last_error(), cases[k].phrase);
    }
    /* A reader given a FIFO refuses it instead of blocking. */
    swfs_real *r = NULL;
    assert_int_equal(swfs_fits_read_real(fifo, NULL, &r, NULL), SWFS_ERR_IO);
    assert_non_null(strstr(swfs_last_error(), "is a FIFO"));
}

/* Tile-compressed (Rice, Hcompress-lossless-as-GZIP) and gzip'd files read like plain ones. */
static void test_compressed_inputs(void **state)
{
    (void)state;
    const char *dir = scratch("compressed");
    char plain[4300], name[4400];
    snprintf(plain, sizeof plain, "%s/plain.fits", dir);
    swfs_real *r = swfs_real_alloc(200, 150, 4), *back = NULL;
    for (size_t k = 0; k < swfs_real_size(r); k++) r->data[k] = (double)((k * 7919) % 1000); /* integers: exact */
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6; g.teldiam = 6.5; g.obscur = 0.1; g.pixscale = 0.25; g.pupdx = 0.04; g.pupn = 163;
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, plain));
    assert_ok(swfs_fits_out_set_stamp(o, &g, NULL, 0));
    assert_ok(swfs_fits_out_real(o, NULL, r, 32));
    assert_ok(swfs_fits_out_commit(o));
    const char *const specs[] = {"rice.fits[compress R]", "hcomp.fits[compress H]", "gz.fits[compress G]", "whole.fits.gz"};
    const char *const files[] = {"rice.fits", "hcomp.fits", "gz.fits", "whole.fits.gz"};
    for (size_t s = 0; s < 4; s++) {
        fitsfile *in = NULL, *out = NULL;
        int st = 0;
        snprintf(name, sizeof name, "!%s/%s", dir, specs[s]);
        fits_open_diskfile(&in, plain, READONLY, &st);
        fits_create_file(&out, name, &st);
        if (s < 3) {
            fits_create_img(out, 8, 0, NULL, &st);
            fits_img_compress(in, out, &st);
        } else {
            fits_copy_file(in, out, 1, 1, 1, &st);
        }
        fits_close_file(out, &st);
        fits_close_file(in, &st);
        assert_int_equal(st, 0);
        snprintf(name, sizeof name, "%s/%s", dir, files[s]);
        struct stat a, b;
        assert_int_equal(stat(name, &a), 0);
        assert_int_equal(stat(plain, &b), 0);
        assert_true(a.st_size < b.st_size); /* compressed: smaller than the pixels */
        swfs_geom gb;
        assert_ok(swfs_fits_read_real(name, NULL, &back, &gb));
        assert_int_equal(back->nx, 200);
        assert_int_equal(back->nz, 4);
        assert_memory_equal(back->data, r->data, swfs_real_size(r) * sizeof(double));
        assert_close(gb.wavelen, 3.8e-6, 1e-20);
        swfs_real_free(back);
    }
    /* A gzip'd file cut short is an error, not a crash. */
    snprintf(name, sizeof name, "%s/whole.fits.gz", dir);
    assert_int_equal(truncate(name, 200), 0);
    assert_int_not_equal(swfs_fits_read_real(name, NULL, &back, NULL), SWFS_OK);
    swfs_real_free(r);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_atomic_text),
        cmocka_unit_test(test_atomic_groups),
        cmocka_unit_test(test_atomic_parts_on_signal),
        cmocka_unit_test(test_fits_writer_failures),
        cmocka_unit_test(test_checksums),
        cmocka_unit_test(test_keywords_from_text),
        cmocka_unit_test(test_geometry_ranges),
        cmocka_unit_test(test_huge_naxis),
        cmocka_unit_test(test_paths),
        cmocka_unit_test(test_compressed_inputs),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

/* Geometry the files lack: camera cubes written without the geometry keywords (no camera
 * writes PUPDX or PUPN). reduce says which keywords are missing and from which file; the
 * geometry given to reduce (a file or values) goes into the reduced cube, and speckles then
 * runs; given only to speckles it works too; with none, speckles fails naming the reduced
 * file and the first missing keyword. The given geometry file: FITS header or KEY = VALUE
 * text, bad ones refused with file and line. */
#include "testutil.h"

#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

static char dir[1024];
static swfs_geom truth_geom;

static const char *p(const char *name)
{
    static char buf[32][1200];
    static int k;
    k = (k + 1) % 32;
    snprintf(buf[k], sizeof buf[k], "%s/%s", dir, name);
    return buf[k];
}

/* A raw cube rewritten with no geometry keyword (GAIN kept). */
static void strip(const char *in, const char *out)
{
    swfs_real *a = NULL;
    swfs_geom g;
    assert_ok(swfs_fits_read_real(in, NULL, &a, &g));
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, out));
    assert_ok(swfs_fits_out_real(o, NULL, a, -32));
    assert_ok(swfs_fits_out_key_double(o, "GAIN", 4.9, "[e-/count]"));
    assert_ok(swfs_fits_out_commit(o));
    truth_geom = g;
    swfs_real_free(a);
}

static int setup(void **state)
{
    (void)state;
    snprintf(dir, sizeof dir, "%s", test_path("geometry"));
    mkdir(dir, 0755);
    const char *kv[] = {"pupn=66", "pupdx=0.1", "screen_n=1024", "ncubes=2", "cube_frames=40", "cube_gap=150",
                        "layer_speed=30,40", "vib_amp=0.6", "jitter_amp=0.15", "seed=2"};
    swfs_ts_params tp;
    assert_ok(swfs_ts_params_from_keys(kv, sizeof kv / sizeof kv[0], &tp));
    swfs_ts_summary s;
    const char *prov[] = {"test_geometry"};
    assert_ok(swfs_ts_run(&tp, dir, prov, 1, NULL, NULL, &s));
    /* same names as the handshake log's, in a folder of their own */
    mkdir(p("bare"), 0755);
    strip(p("raw_000.fits"), p("bare/raw_000.fits"));
    strip(p("raw_001.fits"), p("bare/raw_001.fits"));
    return 0;
}

static void reduce(const char *out, const swfs_geom *given, swfs_reduce_run_result *r)
{
    swfs_reduce_run_options ro;
    swfs_reduce_run_options_default(&ro);
    const char *raw[] = {p("bare/raw_000.fits"), p("bare/raw_001.fits")};
    ro.raw = raw;
    ro.nraw = 2;
    ro.dark = p("dark.fits");
    ro.flat = p("flat.fits");
    ro.out = out;
    if (given) ro.geom = *given;
    assert_ok(swfs_reduce_run(&ro, r));
}

static int speckles(const char *science, const swfs_geom *given)
{
    swfs_sync_run_options so;
    swfs_sync_run_options_default(&so);
    so.science = science;
    so.handshake = p("handshake.log");
    so.out = p("timing.txt");
    swfs_sync_run_result sr;
    int rc = swfs_sync_run(&so, &sr);
    if (rc) return rc;
    free(sr.t.cubes);
    swfs_speckles_run_options sp;
    swfs_speckles_run_options_default(&sp);
    sp.timing = p("timing.txt");
    sp.science = science;
    sp.actuators = p("actuators.fits");
    sp.out = p("speckles.fits");
    sp.pipe.recon = SWFS_RECON_VK; /* the geometry's path, not the taught default's */
    if (given) sp.geom = *given;
    swfs_speckles_run_result spr;
    return swfs_speckles_run(&sp, &spr);
}

static void test_missing_geometry_named(void **state)
{
    (void)state;
    swfs_reduce_run_result r;
    remove(p("speckles.fits")); /* the folder of an earlier run */
    reduce(p("sci_bare.fits"), NULL, &r);
    print_message("reduce without geometry: missing '%s'\n", r.missing);
    assert_string_equal(r.missing, "WAVELEN TELDIAM OBSCUR PIXSCALE PUPDX PUPN");
    assert_int_not_equal(speckles(p("sci_bare.fits"), NULL), 0);
    print_message("speckles: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "sci_bare.fits: missing geometry keyword WAVELEN"));
    assert_non_null(strstr(swfs_last_error(), "--geom FILE"));
    assert_false(test_file_exists(p("speckles.fits")));
}

static void test_geometry_given(void **state)
{
    (void)state;
    /* A text file gives four keywords, an option the other two. */
    FILE *f = fopen(p("geom.txt"), "w");
    assert_non_null(f);
    fprintf(f, "# the camera's and the pupil grid's geometry\nWAVELEN = %.10g\nteldiam %.10g\nOBSCUR=%.10g\nPIXSCALE = %.10g\n",
            truth_geom.wavelen, truth_geom.teldiam, truth_geom.obscur, truth_geom.pixscale);
    fclose(f);
    swfs_geom g;
    assert_ok(swfs_geom_read_file(p("geom.txt"), &g));
    char miss[96];
    assert_int_equal(swfs_geom_missing(&g, miss, sizeof miss), 2);
    assert_string_equal(miss, "PUPDX PUPN");
    g.pupdx = truth_geom.pupdx;
    g.pupn = truth_geom.pupn;
    swfs_reduce_run_result r;
    reduce(p("sci_given.fits"), &g, &r);
    assert_string_equal(r.missing, "");
    assert_int_equal(r.overridden, 0);
    swfs_geom out;
    swfs_real *a = NULL;
    assert_ok(swfs_fits_read_real(p("sci_given.fits"), NULL, &a, &out));
    swfs_real_free(a);
    assert_true(out.wavelen == truth_geom.wavelen && out.pupn == truth_geom.pupn && out.pupdx == truth_geom.pupdx);
    assert_ok(speckles(p("sci_given.fits"), NULL));
    /* Or given to speckles alone: the same speckles. */
    assert_ok(speckles(p("sci_bare.fits"), &g));
    /* A FITS header works as the geometry file (here a raw cube that has the keywords). */
    assert_ok(swfs_geom_read_file(p("raw_000.fits"), &g));
    assert_int_equal(swfs_geom_missing(&g, miss, sizeof miss), 0);
}

static void test_bad_geometry_files(void **state)
{
    (void)state;
    swfs_geom g;
    /* each file refused, its message naming the line and what was wrong; a value of nan (the
     * reader's "not given") or in hexadecimal, and a key given twice, are refused naming the
     * line, not dropped or overwritten in silence */
    const struct { const char *name, *text, *want; } bad[] = {
        {"bad1.txt", "WAVELEN = 3.8e-6\nPUPSIZE = 3\n", "bad1.txt:2: unknown key 'PUPSIZE'"},
        {"bad2.txt", "WAVELEN = 3.8\n", "WAVELEN"},
        {"bad3.txt", "# nothing\n", "no geometry keyword"},
        {"bad4.txt", "PUPDX = 0.1\nTELDIAM = nan\n", "bad4.txt:2: TELDIAM = nan: expected a finite decimal number"},
        {"bad5.txt", "PUPDX = 0.1\nteldiam 8\npupdx 0.2\n", "bad5.txt:3: PUPDX given again (line 1 gave it)"},
        {"bad6.txt", "PUPN = 0x40\n", "bad6.txt:1: PUPN = 0x40: expected a finite decimal number"},
    };
    for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
        FILE *f = fopen(p(bad[k].name), "w");
        assert_non_null(f);
        fputs(bad[k].text, f);
        fclose(f);
        assert_int_not_equal(swfs_geom_read_file(p(bad[k].name), &g), 0);
        assert_non_null(strstr(swfs_last_error(), bad[k].want));
    }
    assert_int_not_equal(swfs_geom_read_file(p("none.txt"), &g), 0);
    assert_non_null(strstr(swfs_last_error(), "none.txt"));
}

/* A line longer than the readers' buffer is refused, naming the line: read in pieces, the
 * tail of a long comment would be taken for a setting of its own. */
/* One time series into sub, with extra config settings. */
/* The time-series parameters of ts_into's runs with the extra keys. */
static int ts_params(const char *const *extra, size_t nextra, swfs_ts_params *tp)
{
    swfs_config *c = swfs_config_new();
    const char *kv[] = {"pupn=66", "pupdx=0.1", "screen_n=1024", "ncubes=1", "cube_frames=40", "cube_gap=50",
                        "start_offset=60.3", "layer_speed=30,40", "seed=3", "ao_modes=40"};
    for (size_t i = 0; i < sizeof kv / sizeof kv[0]; i++) assert_ok(swfs_config_set(c, kv[i]));
    for (size_t i = 0; i < nextra; i++) assert_ok(swfs_config_set(c, extra[i]));
    swfs_ts_params_default(tp);
    int rc = swfs_ts_params_from_config(c, tp);
    swfs_config_free(c);
    return rc ? rc : swfs_ts_params_check(tp);
}

/* A short time series into dir/sub with the extra keys, with the shared plans sh (or none). */
static int ts_into_shared(const char *sub, const char *const *extra, size_t nextra, const swfs_ts_shared *sh)
{
    swfs_ts_params tp;
    int rc = ts_params(extra, nextra, &tp);
    mkdir(p(sub), 0755);
    swfs_ts_summary s;
    const char *prov[] = {"test_geometry"};
    if (!rc) rc = swfs_ts_run_shared(&tp, sh, p(sub), prov, 1, NULL, NULL, &s);
    return rc;
}

static int ts_into(const char *sub, const char *const *extra, size_t nextra)
{
    swfs_ts_params tp;
    int rc = ts_params(extra, nextra, &tp);
    mkdir(p(sub), 0755);
    swfs_ts_summary s;
    const char *prov[] = {"test_geometry"};
    if (!rc) rc = swfs_ts_run(&tp, p(sub), prov, 1, NULL, NULL, &s);
    swfs_dm_registration reg;
    size_t nmodes;
    if (!rc && tp.export_modal) rc = swfs_ts_export_modal(&tp, p(sub), prov, 1, &reg, &nmodes);
    return rc;
}

/* A time series that must be refused, with phrase in the message. */
static void refused(const char *sub, const char *const *extra, size_t nextra, const char *phrase)
{
    assert_int_not_equal(ts_into(sub, extra, nextra), SWFS_OK);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), phrase));
}

/* Largest |a - b| over two files' data (same size asserted), and the largest |a|. */
static double file_diff(const char *a, const char *b, double *amax)
{
    swfs_real *x = NULL, *y = NULL;
    assert_ok(swfs_fits_read_real(p(a), NULL, &x, NULL));
    assert_ok(swfs_fits_read_real(p(b), NULL, &y, NULL));
    assert_int_equal(x->nx * x->ny * x->nz, y->nx * y->ny * y->nz);
    double d = 0, m = 0;
    for (size_t i = 0; i < x->nx * x->ny * x->nz; i++) {
        d = fmax(d, fabs(x->data[i] - y->data[i]));
        m = fmax(m, fabs(x->data[i]));
    }
    swfs_real_free(x);
    swfs_real_free(y);
    if (amax) *amax = m;
    return d;
}

/* The files names[0..n) of two runs' folders hold the same nonzero data, to the bit. */
static void same_files(const char *built, const char *given, const char *const *names, size_t n)
{
    for (size_t k = 0; k < n; k++) {
        char a[128], b[128];
        snprintf(a, sizeof a, "%s/%s", built, names[k]);
        snprintf(b, sizeof b, "%s/%s", given, names[k]);
        double m = 0, d = file_diff(a, b, &m);
        print_message("%s: max |given - built| %g of %g\n", names[k], d, m);
        assert_true(m > 0 && d == 0.0);
    }
}

/* The DM given by its actuator positions (actuators = FILE): the hexapolar rings a run built,
 * given back as a file, makes the same loop (slopes and true residual equal to the last bit);
 * so does the loop's reconstructor given (ao_recon = FILE); positions the interpolation
 * cannot use and a reconstructor of another shape are refused, naming the file. */
static void test_actuators_given(void **state)
{
    (void)state;
    const char *sq[] = {"act_pitch=0.5", "export_truth=1"};
    assert_ok(ts_into("dm_built", sq, 2));
    char given[1400];
    snprintf(given, sizeof given, "actuators=%s", p("dm_built/actuators.fits"));
    const char *fromfile[] = {given, "export_truth=1"};
    assert_ok(ts_into("dm_given", fromfile, 2));
    const char *cmp[] = {"slopes_000.fits", "truewf_000.fits", "actuators.fits"};
    same_files("dm_built", "dm_given", cmp, 3);
    /* The loop's reconstructor given (ao_recon): the built run's recon_ao.fits (40 modes) makes
     * its loop again although ao_modes asks for 20; of another DM's shape it is refused. */
    char rec[1400];
    snprintf(rec, sizeof rec, "ao_recon=%s", p("dm_built/recon_ao.fits"));
    const char *withrec[] = {"act_pitch=0.5", "export_truth=1", "ao_modes=20", rec};
    assert_ok(ts_into("rec_given", withrec, 4));
    const char *fewer[] = {"act_pitch=0.5", "ao_modes=20"};
    assert_ok(ts_into("rec_20", fewer, 2));
    swfs_real *x = NULL, *y = NULL, *z = NULL;
    assert_ok(swfs_fits_read_real(p("dm_built/slopes_000.fits"), NULL, &x, NULL));
    assert_ok(swfs_fits_read_real(p("rec_given/slopes_000.fits"), NULL, &y, NULL));
    assert_ok(swfs_fits_read_real(p("rec_20/slopes_000.fits"), NULL, &z, NULL));
    double dg = 0, d20 = 0;
    for (size_t i = 0; i < x->nx * x->ny; i++) {
        dg = fmax(dg, fabs(x->data[i] - y->data[i]));
        d20 = fmax(d20, fabs(x->data[i] - z->data[i]));
    }
    print_message("ao_recon: slopes differ from the 40-mode loop by %g (20 modes: %g)\n", dg, d20);
    assert_true(dg == 0.0 && d20 > 0.0);
    swfs_real_free(x);
    swfs_real_free(y);
    swfs_real_free(z);
    snprintf(rec, sizeof rec, "ao_recon=%s", p("dm_built/recon_ao.fits"));
    const char *otherdm[] = {"act_pitch=0.7", rec};
    refused("rec_bad", otherdm, 2, "the loop's reconstructor is 288 slopes x 169 actuators");
    /* bad layouts */
    double xy[2 * 40];
    size_t n = 0;
    for (int j = 0; j < 6; j++)
        for (int i = 0; i < 6; i++, n++) { xy[2 * n] = (i - 2.5) * 0.7; xy[2 * n + 1] = (j - 2.5) * 0.7; }
    xy[2] = xy[0]; /* actuator 1 on actuator 0 */
    xy[3] = xy[1];
    assert_ok(swfs_actuators_write(xy, n, p("dup.fits")));
    for (size_t k = 0; k < 2 * n; k++) xy[k] *= 100.0; /* centimetres */
    assert_ok(swfs_actuators_write(xy + 4, n - 2, p("cm.fits")));
    assert_ok(swfs_actuators_write(xy + 4, 3, p("three.fits")));
    const struct { const char *file, *phrase; } bad[] = {
        {"dup.fits", "actuators 0 and 1 are at the same place"},
        {"cm.fits", "expected positions in metres"},
        {"three.fits", "3 actuators; the simulated DM needs at least 4"},
        {"nofile.fits", "nofile.fits"},
    };
    for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
        snprintf(given, sizeof given, "actuators=%s", p(bad[k].file));
        const char *kv[] = {given};
        refused("dm_bad", kv, 1, bad[k].phrase);
        if (strcmp(bad[k].file, "nofile.fits")) assert_non_null(strstr(swfs_last_error(), p(bad[k].file)));
    }
}

/* Plans shared by many runs of one system (swfs_ts_shared, as teach's loops share them): the
 * runs write the same files, to the bit, as runs that build their own (another seed and
 * other layers too); a run of another DM, of other truth points, or needing the truth's plan
 * the shared plans lack is refused. */
static void test_shared_plans(void **state)
{
    (void)state;
    double *gxy = NULL;
    size_t ng = 0;
    assert_ok(swfs_actuators_hexapolar(6.5, 0.3, 0.1, &gxy, &ng));
    assert_ok(swfs_actuators_write(gxy, ng, p("grid.fits")));
    free(gxy);
    char tk[1400];
    snprintf(tk, sizeof tk, "truth_actuators=%s", p("grid.fits"));
    const char *sys[] = {"act_pitch=0.5", "export_truth=1", tk};
    swfs_ts_params tp;
    assert_ok(ts_params(sys, 3, &tp));
    swfs_ts_shared *sh = NULL;
    assert_ok(swfs_ts_shared_create(&tp, &sh));
    const char *other[] = {"act_pitch=0.5", "export_truth=1", tk, "seed=8", "layer_speed=12,25", "ao_modes=30"};
    assert_ok(ts_into_shared("sh_own", sys, 3, NULL));
    assert_ok(ts_into_shared("sh_shared", sys, 3, sh));
    assert_ok(ts_into_shared("sh_own8", other, 6, NULL));
    assert_ok(ts_into_shared("sh_shared8", other, 6, sh));
    const char *cmp[] = {"slopes_000.fits", "truewf_000.fits"};
    same_files("sh_own", "sh_shared", cmp, 2);
    same_files("sh_own8", "sh_shared8", cmp, 2);
    swfs_real *o = NULL;
    assert_ok(swfs_fits_read_real(p("sh_shared/truewf_000.fits"), "OUTXY", &o, NULL));
    assert_int_equal(o->ny, ng);
    swfs_real_free(o);
    const char *dm[] = {"act_pitch=0.6", "export_truth=1", tk};
    assert_int_equal(ts_into_shared("sh_bad", dm, 3, sh), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "made for another system"));
    const char *pts[] = {"act_pitch=0.5", "export_truth=1"};
    assert_int_equal(ts_into_shared("sh_bad", pts, 2, sh), SWFS_ERR_ARG);
    swfs_ts_shared_free(sh);
    const char *notruth[] = {"act_pitch=0.5"};
    assert_ok(ts_params(notruth, 1, &tp));
    assert_ok(swfs_ts_shared_create(&tp, &sh));
    assert_ok(ts_into_shared("sh_nt", notruth, 1, sh));
    assert_int_equal(ts_into_shared("sh_bad", pts, 2, sh), SWFS_ERR_ARG);
    swfs_ts_shared_free(sh);
    /* a zonal loop's plans (ao_rcond): its reconstructor made once, the same slopes as a run's
     * own; a modal run with them makes its own, as without them */
    const char *zonal[] = {"act_pitch=0.5", "ao_rcond=0.05"};
    assert_ok(ts_params(zonal, 2, &tp));
    assert_ok(swfs_ts_shared_create(&tp, &sh));
    assert_ok(ts_into_shared("shz_own", zonal, 2, NULL));
    assert_ok(ts_into_shared("shz_shared", zonal, 2, sh));
    assert_ok(ts_into_shared("shz_modal", notruth, 1, sh));
    same_files("shz_own", "shz_shared", cmp, 1);
    same_files("sh_nt", "shz_modal", cmp, 1);
    swfs_ts_shared_free(sh);
}

/* The AO system's valid-subaperture map given (valid = FILE): the simulated Shack-Hartmann
 * uses those subapertures (4 of the half-lit rule's left out: their slopes are 0 in every
 * frame, and valid.fits is the map given); a map of another size is refused naming it. */
static void test_valid_given(void **state)
{
    (void)state;
    const char *src[] = {"export_modal=1"};
    assert_ok(ts_into("valid_src", src, 1));
    swfs_real *v = NULL;
    assert_ok(swfs_fits_read_real(p("valid_src/valid.fits"), NULL, &v, NULL));
    const size_t nsa = v->nx * v->ny;
    size_t dropped[4], nd = 0;
    for (size_t a = 0; a < nsa && nd < 4; a++)
        if (v->data[a] != 0) { v->data[a] = 0; dropped[nd++] = a; }
    assert_int_equal(nd, 4);
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, p("fewer_valid.fits")));
    assert_ok(swfs_fits_out_real(o, NULL, v, 8));
    assert_ok(swfs_fits_out_commit(o));
    char kv[1400];
    snprintf(kv, sizeof kv, "valid=%s", p("fewer_valid.fits"));
    const char *given[] = {"export_modal=1", kv};
    assert_ok(ts_into("valid_given", given, 2));
    swfs_real *w = NULL, *s0 = NULL, *s1 = NULL;
    assert_ok(swfs_fits_read_real(p("valid_given/valid.fits"), NULL, &w, NULL));
    for (size_t a = 0; a < nsa; a++) assert_true((w->data[a] != 0) == (v->data[a] != 0));
    assert_ok(swfs_fits_read_real(p("valid_src/slopes_000.fits"), NULL, &s0, NULL));
    assert_ok(swfs_fits_read_real(p("valid_given/slopes_000.fits"), NULL, &s1, NULL));
    assert_int_equal(s0->nx, 2 * nsa);
    for (size_t k = 0; k < nd; k++) {
        double m0 = 0, m1 = 0;
        for (size_t f = 0; f < s0->ny; f++)
            for (size_t axis = 0; axis < 2; axis++) {
                m0 = fmax(m0, fabs(s0->data[f * s0->nx + axis * nsa + dropped[k]]));
                m1 = fmax(m1, fabs(s1->data[f * s1->nx + axis * nsa + dropped[k]]));
            }
        print_message("subaperture %zu: max |slope| %g with the rule, %g left out by the map\n", dropped[k], m0, m1);
        assert_true(m0 > 0 && m1 == 0);
    }
    swfs_real_free(w);
    swfs_real_free(s0);
    swfs_real_free(s1);
    swfs_real_free(v);
    snprintf(kv, sizeof kv, "valid=%s", p("fewer_valid.fits"));
    const char *other[] = {"nsub=10", kv};
    refused("valid_bad", other, 2, "fewer_valid.fits: a valid-subaperture map of 12 x 12, but nsub = 10");
}

/* The telescope pupil given (pupil_mask = FILE): the spidered pupil a run built, given back
 * as a file without the spider keys, makes the same run to the bit (pupil.fits, slopes, true
 * residual, science frames), and the spiders change the slopes; masks of another size, with
 * values outside 0..1 or light beyond teldiam are refused naming the file. */
static void test_pupil_given(void **state)
{
    (void)state;
    const char *spiders[] = {"nspiders=4", "spider_width=0.3", "export_truth=1"};
    assert_ok(ts_into("pup_built", spiders, 3));
    const char *plain[] = {"export_truth=1"};
    assert_ok(ts_into("pup_plain", plain, 1));
    char kv[1400];
    snprintf(kv, sizeof kv, "pupil_mask=%s", p("pup_built/pupil.fits"));
    const char *given[] = {kv, "export_truth=1"};
    assert_ok(ts_into("pup_given", given, 2));
    const char *cmp[] = {"pupil.fits", "slopes_000.fits", "truewf_000.fits", "raw_000.fits"};
    same_files("pup_built", "pup_given", cmp, 4);
    double m = 0, d = file_diff("pup_built/slopes_000.fits", "pup_plain/slopes_000.fits", &m);
    print_message("slopes: spiders against none differ by %g of %g\n", d, m);
    assert_true(d > 1e-3 * m);
    double dp = file_diff("pup_built/pupil.fits", "pup_plain/pupil.fits", NULL);
    assert_true(dp == 1.0);

    /* bad masks */
    swfs_real *pm = NULL;
    assert_ok(swfs_fits_read_real(p("pup_built/pupil.fits"), NULL, &pm, NULL));
    const size_t n = pm->nx;
    struct { const char *file, *phrase; } bad[] = {
        {"pm_small.fits", "pupil mask is 60x60x1 but the pupil grid is pupn x pupn = 66x66"},
        {"pm_over.fits", "outside 0 .. 1"},
        {"pm_wide.fits", "the telescope (teldiam = 6.5 m) reaches 3.25 m"},
        {"pm_none.fits", "pm_none.fits"},
    };
    swfs_real small = {60, 60, 1, pm->data};
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, p(bad[0].file)));
    assert_ok(swfs_fits_out_real(o, NULL, &small, -32));
    assert_ok(swfs_fits_out_commit(o));
    pm->data[n * n / 2 + n / 2] = 1.5;
    assert_ok(swfs_fits_out_create(&o, p(bad[1].file)));
    assert_ok(swfs_fits_out_real(o, NULL, pm, -32));
    assert_ok(swfs_fits_out_commit(o));
    for (size_t i = 0; i < n * n; i++) pm->data[i] = 1.0; /* the whole grid: 6.6 m across */
    assert_ok(swfs_fits_out_create(&o, p(bad[2].file)));
    assert_ok(swfs_fits_out_real(o, NULL, pm, -32));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(pm);
    for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
        snprintf(kv, sizeof kv, "pupil_mask=%s", p(bad[k].file));
        const char *one[] = {kv};
        refused("pup_bad", one, 1, bad[k].phrase);
        assert_non_null(strstr(swfs_last_error(), p(bad[k].file)));
    }
}

static void test_long_lines(void **state)
{
    (void)state;
    FILE *f = fopen(p("long.txt"), "w");
    fprintf(f, "WAVELEN = 3.8e-6\n#");
    for (int i = 0; i < 1022; i++) fputc('-', f); /* the tail starts the next 1023-byte piece */
    fprintf(f, "PUPN = 7\n");
    fclose(f);
    swfs_geom g;
    assert_int_equal(swfs_geom_read_file(p("long.txt"), &g), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "long.txt:2: line longer than 1022 characters"));
    f = fopen(p("long.conf"), "w");
    fprintf(f, "seed = 1\n#");
    for (int i = 0; i < 1022; i++) fputc('-', f); /* the tail starts the next 1023-byte piece */
    fprintf(f, "seed = 2\n");
    fclose(f);
    swfs_config *c = swfs_config_new();
    assert_non_null(c);
    assert_int_equal(swfs_config_load(c, p("long.conf")), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "long.conf:2: line longer than 1022 characters"));
    swfs_config_free(c);
    /* A last line without its newline that just fills the buffer is read. */
    f = fopen(p("full.conf"), "w");
    fprintf(f, "seed = 1\nseed = 3");
    for (int i = 0; i < 1023 - 8; i++) fputc(' ', f);
    fclose(f);
    c = swfs_config_new();
    long seed = 0;
    assert_ok(swfs_config_load(c, p("full.conf")));
    assert_ok(swfs_config_long(c, "seed", 0, &seed));
    assert_int_equal(seed, 3);
    swfs_config_free(c);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_missing_geometry_named),
        cmocka_unit_test(test_geometry_given),
        cmocka_unit_test(test_bad_geometry_files),
        cmocka_unit_test(test_long_lines),
        cmocka_unit_test(test_actuators_given),
        cmocka_unit_test(test_shared_plans),
        cmocka_unit_test(test_valid_given),
        cmocka_unit_test(test_pupil_given),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}

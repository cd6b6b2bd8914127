/* `specklewfs estimate` end to end on cubes it has never seen, and its bad-input errors. */
#include "testutil.h"

#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#define W 12
#define H 10
#define N 3000

static double complex truth(size_t i, size_t j) { return (1.0 + 0.1 * (double)i) * cexp(I * 0.3 * (double)(i + 2 * j)); }

/* resmean: 0 none; 1 the speckles carry an AO residual mean (RESMEAN, PUPN x PUPN); 2 one with
 * a NaN; 3 one of the wrong size. */
static void write_cubes(const char *sci, const char *sp, size_t nframes, int nan_pixels, int real_speckles, int resmean)
{
    swfs_rng r;
    swfs_rng_seed(&r, 42);
    swfs_real *s = swfs_real_alloc(W, H, nframes);
    swfs_cplx *c = swfs_cplx_alloc(W, H, nframes);
    const double g = 2.0, rn = 0.5;
    for (size_t k = 0; k < nframes; k++)
        for (size_t j = 0; j < H; j++)
            for (size_t i = 0; i < W; i++) {
                size_t q = (k * H + j) * W + i;
                c->data[q] = swfs_rng_cnormal_value(&r);
                double complex t = truth(i, j) + g * c->data[q];
                s->data[q] = creal(t * conj(t)) + rn * swfs_rng_normal(&r);
            }
    if (nan_pixels)
        for (size_t k = 0; k < nframes; k += 7) s->data[(k * H + 3) * W + 4] = NAN;
    swfs_geom g0;
    swfs_geom_init(&g0);
    g0.wavelen = 3.8e-6; g0.teldiam = 6.5; g0.obscur = 0.1; g0.pixscale = 0.25; g0.pupdx = 0.04; g0.pupn = 163;
    swfs_fits_out *o;
    assert_ok(swfs_fits_out_create(&o, sci));
    assert_ok(swfs_fits_out_real(o, NULL, s, -32));
    assert_ok(swfs_fits_out_key_double(o, "RDNOISE", rn, NULL));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_fits_out_create(&o, sp));
    if (real_speckles) {
        assert_ok(swfs_fits_out_real(o, NULL, s, -32));
    } else {
        assert_ok(swfs_fits_out_cplx(o, NULL, c, -32));
    }
    assert_ok(swfs_fits_out_geom(o, &g0));
    if (resmean) {
        const size_t n = resmean == 3 ? 100 : 163;
        swfs_real *m = swfs_real_alloc(n, n, 1);
        for (size_t q = 0; q < n * n; q++) m->data[q] = 1e-8 * sin(0.01 * (double)q);
        if (resmean == 2) m->data[5] = NAN;
        assert_ok(swfs_fits_out_real(o, "RESMEAN", m, -64));
        swfs_real_free(m);
    }
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(s);
    swfs_cplx_free(c);
}

static void test_estimate_recovers_halo(void **state)
{
    (void)state;
    char sci[1024], sp[1024], out[1024], args[4096], text[8192];
    snprintf(sci, sizeof sci, "%s", test_path("e_sci.fits"));
    snprintf(sp, sizeof sp, "%s", test_path("e_sp.fits"));
    snprintf(out, sizeof out, "%s", test_path("e_halo.fits"));
    remove(out);
    write_cubes(sci, sp, N, 1, 0, 1);
    snprintf(args, sizeof args, "estimate %s %s -o %s", sci, sp, out);
    int rc = test_run_cli(NULL, args, text, sizeof text);
    print_message("%s", text);
    assert_int_equal(rc, 0);
    assert_non_null(strstr(text, "pixel-frames skipped"));
    swfs_halo *h;
    swfs_geom g;
    assert_ok(swfs_halo_read(out, &h, &g));
    assert_close(g.wavelen, 3.8e-6, 0); /* geometry carried through */
    double e2 = 0;
    for (size_t j = 0; j < H; j++)
        for (size_t i = 0; i < W; i++) {
            double complex d = h->halo->data[j * W + i] - truth(i, j);
            e2 += creal(d * conj(d));
        }
    double rms = sqrt(e2 / (W * H));
    print_message("halo rms error %.4f (|Psi| 1.0 .. 2.1)\n", rms);
    assert_true(rms < 0.12);
    assert_close(h->nframes->data[3 * W + 4], N - (N + 6) / 7, 0);
    assert_int_equal(h->frames, N);
    for (size_t p = 0; p < W * H; p++) assert_close(h->gain->data[p], 2.0, 0.15);
    /* the speckles' AO residual mean goes with the halo, value for value */
    assert_non_null(h->resmean);
    assert_int_equal(h->resmean->nx, 163);
    for (size_t q = 0; q < 163 * 163; q++) assert_close(h->resmean->data[q], 1e-8 * sin(0.01 * (double)q), 0);
    swfs_halo_free(h);
    /* The read-noise flag overrides the header: a huge one makes g undefined everywhere. */
    snprintf(args, sizeof args, "estimate %s %s -o %s --read-noise 1000", sci, sp, out);
    rc = test_run_cli(NULL, args, text, sizeof text);
    assert_int_equal(rc, 1);
    assert_non_null(strstr(text, "radicand"));
}

/* estimate SCI SP -o OUT fails (status 1) with a message holding a (and b unless NULL), and
 * leaves no OUT. */
static void estimate_refused(const char *sci, const char *sp, const char *out, const char *a, const char *b)
{
    char args[4096], text[8192];
    remove(out);
    snprintf(args, sizeof args, "estimate %s %s -o %s", sci, sp, out);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 1);
    print_message("%s", text);
    assert_non_null(strstr(text, a));
    if (b) assert_non_null(strstr(text, b));
    assert_false(test_file_exists(out));
}

static void test_estimate_bad_inputs(void **state)
{
    (void)state;
    char sci[1024], sp[1024], sp2[1024], spr[1024], out[1024], args[4096], text[8192];
    snprintf(sci, sizeof sci, "%s", test_path("b_sci.fits"));
    snprintf(sp, sizeof sp, "%s", test_path("b_sp.fits"));
    snprintf(sp2, sizeof sp2, "%s", test_path("b_sp_short.fits"));
    snprintf(spr, sizeof spr, "%s", test_path("b_sp_real.fits"));
    snprintf(out, sizeof out, "%s", test_path("b_halo.fits"));
    write_cubes(sci, sp, 60, 0, 0, 0);
    write_cubes(test_path("b_sci_short.fits"), sp2, 50, 0, 0, 0);
    write_cubes(test_path("b_sci_r.fits"), spr, 60, 0, 1, 0);

    /* An AO residual mean with a NaN, or of another size than PUPN: named, no output. */
    char spn[1024], sps[1024];
    snprintf(spn, sizeof spn, "%s", test_path("b_sp_resnan.fits"));
    snprintf(sps, sizeof sps, "%s", test_path("b_sp_ressize.fits"));
    write_cubes(test_path("b_sci_rn.fits"), spn, 60, 0, 0, 2);
    write_cubes(test_path("b_sci_rs.fits"), sps, 60, 0, 0, 3);
    estimate_refused(sci, spn, out, "b_sp_resnan.fits", "RESMEAN sample 5 is not finite (NaN or infinite)");
    estimate_refused(sci, sps, out, "RESMEAN is 100x100 but PUPN = 163", NULL);
    /* Frame counts differ: both files and both shapes are named. */
    estimate_refused(sci, sp2, out, "12x10x50", "12x10x60");
    /* Speckles not complex. */
    snprintf(args, sizeof args, "estimate %s %s -o %s", sci, spr, out);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 1);
    assert_non_null(strstr(text, "not complex"));
    /* Not FITS / missing. */
    snprintf(args, sizeof args, "estimate /dev/null %s -o %s", sp, out);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 1);
    assert_non_null(strstr(text, "/dev/null"));
    /* Truncated speckles. */
    char trunc[1024];
    snprintf(trunc, sizeof trunc, "%s", test_path("b_sp_trunc.fits"));
    snprintf(args, sizeof args, "cp %s %s", sp, trunc);
    assert_int_equal(system(args), 0);
    assert_ok(truncate(trunc, 2880 * 10));
    snprintf(args, sizeof args, "estimate %s %s -o %s", sci, trunc, out);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 1);
    assert_non_null(strstr(text, "truncated"));
    assert_false(test_file_exists(out));
    /* Unwritable output. */
    snprintf(args, sizeof args, "estimate %s %s -o /nonexistent-dir/halo.fits", sci, sp);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 1);
    assert_non_null(strstr(text, "halo.fits"));
    /* Usage errors. */
    assert_int_equal(test_run_cli(NULL, "estimate", text, sizeof text), 2);
    snprintf(args, sizeof args, "estimate %s %s -o %s --gain abc", sci, sp, out);
    assert_int_equal(test_run_cli(NULL, args, text, sizeof text), 2);
    assert_non_null(strstr(text, "abc"));
    assert_int_equal(test_run_cli(NULL, "estimate --help", text, sizeof text), 0);
    assert_non_null(strstr(text, "eq:scale-factor"));
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_estimate_recovers_halo),
        cmocka_unit_test(test_estimate_bad_inputs),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

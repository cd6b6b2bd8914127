/* Camera frame reduction: dark/flat, bad-pixel replacement by the 3x3 median, Gaussian
 * correlation peak, bilinear registration undoing a known shift, noise variance. */
#include "testutil.h"

#include "specklewfs/fits.h"
#include "specklewfs/reduce.h"
#include "specklewfs/rng.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { NX = 48, NY = 44 };

static double star(double x, double y, double x0, double y0)
{
    double s = 2.2;
    return 5000.0 * exp(-0.5 * ((x - x0) * (x - x0) + (y - y0) * (y - y0)) / (s * s));
}

static void test_badpix_median(void **state)
{
    (void)state;
    double img[5 * 5];
    unsigned char bad[25] = {0};
    for (int i = 0; i < 25; i++) img[i] = (double)i;
    double work[25];
    img[12] = 1e6; bad[12] = 1;  /* centre: 7,8,11,13,16,17,18 (6 flagged) -> 13 */
    img[0] = NAN;                /* corner, non-finite raw: 1, 5 (6 flagged) -> 3 */
    bad[6] = 1;
    img[6] = -1e6;               /* 1,2,5,7,10,11 (0 non-finite, 12 flagged) -> 6 */
    swfs_badpix_replace(img, 5, 5, bad, work);
    assert_close(img[12], 13.0, 1e-12);
    assert_close(img[0], 3.0, 1e-12);
    assert_close(img[6], 6.0, 1e-12);
    assert_close(img[24], 24.0, 0);
}

static void test_shift_roundtrip(void **state)
{
    (void)state;
    double *a = malloc(NX * NY * sizeof *a), *b = malloc(NX * NY * sizeof *b);
    /* A plane is reproduced exactly by bilinear interpolation. */
    for (size_t j = 0; j < NY; j++)
        for (size_t i = 0; i < NX; i++) a[j * NX + i] = 2.0 * (double)i - 0.5 * (double)j + 3;
    swfs_shift_bilinear(a, NX, NY, 1.3, -2.6, b);
    for (size_t j = 3; j + 2 < NY; j++)
        for (size_t i = 0; i + 3 < NX; i++)
            assert_close(b[j * NX + i], 2.0 * ((double)i + 1.3) - 0.5 * ((double)j - 2.6) + 3, 1e-9);
    assert_true(isnan(b[(NY - 1) * NX + NX - 1]) || isnan(b[0]));
    assert_true(isnan(b[NX - 1])); /* needs source x = NX + 0.3 */
    free(a); free(b);
}

static void test_reduce_pipeline(void **state)
{
    (void)state;
    size_t n = NX * NY;
    double *dark = malloc(n * sizeof *dark), *flat = malloc(n * sizeof *flat);
    double *raw = malloc(n * sizeof *raw), *out = malloc(n * sizeof *out);
    swfs_rng rng;
    swfs_rng_seed(&rng, 11);
    for (size_t i = 0; i < n; i++) {
        dark[i] = 3700 + 5 * swfs_rng_normal(&rng);
        flat[i] = 1 + 0.05 * swfs_rng_normal(&rng);
    }
    /* Hot and dead pixels in the star's wings (the 3x3 median is a poor guess at the
     * core itself, where it flattens the peak by ~14 %: that is the method, not a bug). */
    size_t hot[] = {33 * NX + 30, 12 * NX + 12, 5 * NX + 5};
    size_t dead[] = {14 * NX + 30, 36 * NX + 14};
    for (size_t k = 0; k < 3; k++) dark[hot[k]] += 4000;
    for (size_t k = 0; k < 2; k++) flat[dead[k]] = 0.02;
    swfs_reduce_params p;
    swfs_reduce_params_default(&p);
    p.gauss_sigma = 2.0;
    swfs_reduce *r = NULL, *r2 = NULL;
    assert_ok(swfs_reduce_create(&r, NX, NY, dark, flat, NULL, &p));
    /* The out-of-band noise estimate: the star (sigma 2.2 px) is band-limited well inside
     * 0.25 cycles/pixel, the noise is white. */
    swfs_reduce_params p2 = p;
    p2.pixscale = 0.25;
    assert_ok(swfs_reduce_create(&r2, NX, NY, dark, flat, NULL, &p2));
    assert_int_equal(swfs_reduce_nbad(r), 5);
    const double noise = 3.0;
    double maxdev = 0;
    for (int f = 0; f < 60; f++) {
        double x0 = 21.0 + 4.0 * sin(0.3 * f) + 0.37, y0 = 23.0 + 3.0 * cos(0.2 * f) - 0.21;
        for (size_t j = 0; j < NY; j++)
            for (size_t i = 0; i < NX; i++) {
                size_t k = j * NX + i;
                double sig = star((double)i, (double)j, x0, y0) + 50 + noise * swfs_rng_normal(&rng);
                raw[k] = flat[k] * sig + dark[k];
            }
        double px, py;
        assert_ok(swfs_reduce_frame(r2, raw, out, &px, &py));
        assert_ok(swfs_reduce_frame(r, raw, out, &px, &py));
        assert_close(px, x0, 0.05);
        assert_close(py, y0, 0.05);
        /* The star now sits at (W/2, H/2): compare with the model at the centre. */
        for (size_t j = NY / 2 - 4; j <= NY / 2 + 4; j++)
            for (size_t i = NX / 2 - 4; i <= NX / 2 + 4; i++) {
                double model = star((double)i, (double)j, NX / 2, NY / 2) + 50;
                maxdev = fmax(maxdev, fabs(out[j * NX + i] - model) / 5000.0);
            }
    }
    /* Bilinear smoothing of a sigma = 2.2 px star plus noise: a few per cent of the peak. */
    print_message("max deviation %.4f of the peak\n", maxdev);
    /* Bilinear interpolation of a Gaussian at a half-pixel shift lowers the peak by about
     * (1/8)(2/sigma^2) = 5 %. */
    assert_true(maxdev < 0.07);
    double nv = swfs_reduce_noise_var(r);
    assert_close(nv, noise * noise, 0.15 * noise * noise);
    double nv2 = swfs_reduce_noise_var(r2);
    print_message("noise variance %.3f (region) %.3f (out of band), true %.3f\n", nv, nv2, noise * noise);
    assert_close(nv2, noise * noise, 0.1 * noise * noise);
    /* Registration by bilinear shifts of arbitrary fractional parts: the variance factor is
     * between 1/4 (half a pixel on both axes) and 1, 4/9 on average. */
    double q = swfs_reduce_noise_factor(r);
    print_message("registration noise variance factor %.3f\n", q);
    assert_true(q > 0.3 && q < 0.65);
    swfs_reduce_free(r);
    swfs_reduce_free(r2);

    /* Bad input: mostly-bad calibration is rejected. */
    for (size_t i = 0; i < n; i++) flat[i] = (i % 3) ? 0.0 : 1.0;
    assert_int_not_equal(swfs_reduce_create(&r, NX, NY, dark, flat, NULL, &p), 0);
    assert_non_null(strstr(swfs_last_error(), "flat"));
    free(dark); free(flat); free(raw); free(out);
}

/* A camera with no read noise: the background variance, measured as the out-of-band power
 * less the photon part the counts and GAIN predict, comes out below 0 on frames without
 * noise. reduce writes 0 (RDNOISE, NOISEVAR: a variance) and returns the measured value;
 * the square root of the negative value used to leave RDNOISE without a value, which
 * speckles then refused. */
static void test_no_read_noise(void **state)
{
    (void)state;
    const size_t n = NX * NY, nf = 12;
    swfs_real *cube = swfs_real_alloc(NX, NY, nf);
    assert_non_null(cube);
    for (size_t f = 0; f < nf; f++)
        for (size_t j = 0; j < NY; j++)
            for (size_t i = 0; i < NX; i++)
                cube->data[f * n + j * NX + i] = star((double)i, (double)j, 22.3 + 0.1 * (double)f, 21.6) + 50;
    char raw[1100], out[1100];
    snprintf(raw, sizeof raw, "%s", test_path("reduce_nonoise_raw.fits"));
    snprintf(out, sizeof out, "%s", test_path("reduce_nonoise_sci.fits"));
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, raw));
    assert_ok(swfs_fits_out_real(o, NULL, cube, -32));
    assert_ok(swfs_fits_out_key_double(o, "GAIN", 2.0, "[e-/count]"));
    assert_ok(swfs_fits_out_key_double(o, "PIXSCALE", 0.25, "[lambda/D] per focal pixel"));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(cube);

    swfs_reduce_run_options ro;
    swfs_reduce_run_options_default(&ro);
    const char *raws[] = {raw};
    ro.raw = raws;
    ro.nraw = 1;
    ro.out = out;
    swfs_reduce_run_result rr;
    assert_ok(swfs_reduce_run(&ro, &rr));
    print_message("measured background variance %.4g counts^2, written %.4g\n", rr.noise_var_measured, rr.noise_var);
    assert_true(rr.noise_var_measured < 0);
    assert_true(rr.noise_var == 0.0);
    swfs_fits_in *f = NULL;
    assert_ok(swfs_fits_in_open(&f, out, NULL));
    double v = -1;
    int found = 0;
    assert_ok(swfs_fits_in_key_double_opt(f, "RDNOISE", &v, &found));
    assert_true(found && v == 0.0);
    v = -1;
    assert_ok(swfs_fits_in_key_double_opt(f, "NOISEVAR", &v, &found));
    assert_true(found && v == 0.0);
    swfs_fits_in_close(f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_badpix_median),
        cmocka_unit_test(test_shift_roundtrip),
        cmocka_unit_test(test_reduce_pipeline),
        cmocka_unit_test(test_no_read_noise),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

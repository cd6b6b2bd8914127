/* The time-series camera with 20 % optical bandwidth: the PSF's features smear radially,
 * so the first dark Airy ring of the mean image fills in, while the total light stays. */
#include "testutil.h"

#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

/* Mean image of raw_000.fits minus the dark, azimuthally averaged: returns the ratio of the
 * darkest annulus near the first dark ring (1.0-1.45 lambda/D) to the brightest near the
 * first bright ring (1.45-1.9 lambda/D), and the total counts. */
static void ring_contrast(const char *dir, double *ratio, double *total)
{
    char path[1024];
    swfs_real *raw, *dark;
    swfs_geom g;
    snprintf(path, sizeof path, "%s/raw_000.fits", dir);
    assert_ok(swfs_fits_read_real(path, NULL, &raw, &g));
    snprintf(path, sizeof path, "%s/dark.fits", dir);
    assert_ok(swfs_fits_read_real(path, NULL, &dark, NULL));
    const size_t nx = raw->nx, ny = raw->ny, np = nx * ny;
    enum { NB = 40 };
    double prof[NB] = {0}, cnt[NB] = {0};
    *total = 0.0;
    for (size_t q = 0; q < np; q++) {
        double m = 0.0;
        for (size_t k = 0; k < raw->nz; k++) m += raw->data[k * np + q];
        m = m / (double)raw->nz - dark->data[q];
        *total += m;
        const double x = ((double)(q % nx) - (double)(nx / 2)) * g.pixscale;
        const double y = ((double)(q / nx) - (double)(ny / 2)) * g.pixscale;
        const size_t b = (size_t)(hypot(x, y) / 0.1); /* 0.1 lambda/D bins */
        if (b < NB) { prof[b] += m; cnt[b] += 1.0; }
    }
    double lo = INFINITY, hi = 0.0;
    for (size_t b = 10; b < 19; b++)
        if (cnt[b] > 0) {
            const double v = prof[b] / cnt[b], r = (double)b * 0.1;
            if (r < 1.45) lo = fmin(lo, v);
            else hi = fmax(hi, v);
        }
    *ratio = lo / hi;
    swfs_real_free(raw);
    swfs_real_free(dark);
}

static void run(const char *dir, double bandwidth)
{
    swfs_config *c = swfs_config_new();
    const char *kv[] = {"pupn=66", "pupdx=0.1", "screen_n=1024", "ncubes=1", "cube_frames=40", "vib_amp=0",
                        "jitter_amp=0", "read_noise=0", "gain=0", "background=0", "flat_rms=0", "nhot=0",
                        "ndead=0", "seed=3"};
    for (size_t k = 0; k < sizeof kv / sizeof kv[0]; k++) assert_ok(swfs_config_set(c, kv[k]));
    char bw[64];
    snprintf(bw, sizeof bw, "bandwidth=%g", bandwidth);
    assert_ok(swfs_config_set(c, bw));
    swfs_ts_params p;
    swfs_ts_params_default(&p);
    assert_ok(swfs_ts_params_from_config(c, &p));
    assert_ok(swfs_config_check_unused(c));
    assert_ok(swfs_ts_params_check(&p));
    swfs_config_free(c);
    char cmd[1200];
    snprintf(cmd, sizeof cmd, "mkdir -p '%s'", dir);
    assert_int_equal(system(cmd), 0);
    swfs_ts_summary sum;
    assert_ok(swfs_ts_run(&p, dir, NULL, 0, NULL, NULL, &sum));
}

static void test_bandwidth_fills_the_dark_ring(void **state)
{
    (void)state;
    char mono[1024], broad[1024];
    snprintf(mono, sizeof mono, "%s", test_path("bw_mono"));
    snprintf(broad, sizeof broad, "%s", test_path("bw_broad"));
    run(mono, 0.0);
    run(broad, 0.2);
    double rm, rb, tm, tb;
    ring_contrast(mono, &rm, &tm);
    ring_contrast(broad, &rb, &tb);
    print_message("dark/bright ring ratio: monochromatic %.3f, 20%% band %.3f; window counts %.4g vs %.4g\n", rm, rb,
                  tm, tb);
    assert_true(rm < 0.8);       /* a visible dark ring at one wavelength */
    assert_true(rb > 1.2 * rm);  /* filled in across the band */
    assert_close(tb, tm, 0.05 * tm);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_bandwidth_fills_the_dark_ring),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

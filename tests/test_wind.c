/* The winds of the frozen-flow layers from the slopes (wind.h): closed-loop time series of one
 * frozen-flow layer at two winds give the layer's speed within 10 % and its direction
 * within 5 deg, and no second layer; a second layer of less power leaves the dominant one's
 * and is found by the stacking, within 10 % and 5 deg; the valid-only layout gives the full
 * layout's answer; white-noise slopes track nothing; bad input is refused by name (too few
 * frames, a non-finite slope, another width). The loop's modal filter as its slopes show it
 * (timeseries.h swfs_ts_mode_variance, swfs_mode_knee): a profile of two power laws gives its
 * break exactly, also with modes of no variance left out; loops controlling 30 and 60 modes
 * give knees near 30 and 60, and so does the 60-mode loop with a valid map that leaves out the
 * pupil's edge ring (its modes beyond the interaction matrix's rank without a variance). The
 * slopes' time correlation along the upper half of the modes (swfs_ts_mode_timecorr). */
#include "testutil.h"

#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/source.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wind.h"
#include "../src/telemetry/wind_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

static char dir[1024];

static const char *p(const char *name)
{
    static char buf[8][1200];
    static int k;
    k = (k + 1) % 8;
    snprintf(buf[k], sizeof buf[k], "%s/%s", dir, name);
    return buf[k];
}

static int setup(void **state)
{
    (void)state;
    snprintf(dir, sizeof dir, "%s", test_path("wind"));
    mkdir(dir, 0755);
    return 0;
}

/* A closed-loop time series of the simulator's defaults and the n settings kv into dir/sub. */
static void series_of(const char *sub, const char *const *kv, size_t n)
{
    swfs_ts_params tp;
    assert_ok(swfs_ts_params_from_keys(kv, n, &tp));
    mkdir(p(sub), 0755);
    swfs_ts_summary s;
    const char *prov[] = {"test_wind"};
    assert_ok(swfs_ts_run(&tp, p(sub), prov, 1, NULL, NULL, &s));
}

/* A closed-loop time series (12 x 12 at 527 Hz on a 6.5 m pupil) into dir/sub. */
static void series(const char *sub, const char *const *extra, size_t nextra)
{
    const char *kv[16] = {"pupn=66", "pupdx=0.1", "screen_n=1024", "ncubes=2", "cube_frames=100", "cube_gap=100",
                          "seed=4"};
    size_t n = 7;
    assert_true(nextra <= 16 - n);
    for (size_t i = 0; i < nextra; i++) kv[n++] = extra[i];
    series_of(sub, kv, n);
}

static void wind_of(const char *sub, swfs_wind_run_result *r)
{
    char f[1300];
    snprintf(f, sizeof f, "%s/slopes_000.fits", p(sub));
    const char *files[] = {f};
    swfs_wind_run_options o = {files, 1, NULL, 0, 6.5, 0};
    assert_ok(swfs_wind_run(&o, r));
    print_message("%s: %zu frames, %.2f m/s toward %.1f deg from %zu lags\n", sub, r->nframes, r->est.speed,
                  r->est.direction, r->est.nused);
    for (size_t k = 0; k < r->est.nlayers; k++)
        print_message("  layer %zu: %.2f m/s toward %.1f deg, %.1f sd (threshold %.1f)\n", k + 1, r->est.layer[k].speed,
                      r->est.layer[k].direction, r->est.layer[k].signif, r->est.threshold);
    print_message("  best other track %.1f sd\n", r->est.next_signif);
}

static double angle_diff(double a, double b)
{
    double d = fmod(a - b + 540.0, 360.0) - 180.0;
    return fabs(d);
}

static void test_wind_of_simulated_loops(void **state)
{
    (void)state;
    const struct { const char *sub, *keys[4]; double speed, dir; size_t nlayers; double speed2, dir2; } cases[] = {
        {"one30", {"nlayers=1", "layer_frac=1", "layer_speed=10", "layer_dir=30"}, 10, 30, 1, 0, 0},
        {"one200", {"nlayers=1", "layer_frac=1", "layer_speed=20", "layer_dir=200"}, 20, 200, 1, 0, 0},
        /* a second, weaker layer (30 % of the turbulence) across the first */
        {"two", {"nlayers=2", "layer_frac=0.7,0.3", "layer_speed=12,6", "layer_dir=300,45"}, 12, 300, 2, 6, 45},
    };
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        series(cases[k].sub, cases[k].keys, 4);
        swfs_wind_run_result r;
        wind_of(cases[k].sub, &r);
        assert_true(r.est.found);
        assert_true(r.est.nused >= 2);
        assert_true(fabs(r.est.speed / cases[k].speed - 1) < 0.10);
        assert_true(angle_diff(r.est.direction, cases[k].dir) < 5.0);
        assert_int_equal(r.nsub, 12);
        assert_true(fabs(r.rate - 527) < 1e-9 && fabs(r.pitch - 6.5 / 12) < 1e-12);
        /* the layers: the tracked one first, to the bit; a second only where there is one */
        assert_int_equal(r.est.nlayers, cases[k].nlayers);
        assert_true(r.est.layer[0].speed == r.est.speed && r.est.layer[0].direction == r.est.direction);
        assert_true(r.est.layer[0].signif >= r.est.threshold);
        assert_true(!r.est.tracked_dropped && r.est.tracked_signif == r.est.layer[0].signif);
        if (cases[k].nlayers == 2) {
            assert_true(fabs(r.est.layer[1].speed / cases[k].speed2 - 1) < 0.10);
            assert_true(angle_diff(r.est.layer[1].direction, cases[k].dir2) < 5.0);
            assert_true(r.est.layer[1].signif >= r.est.threshold);
        }
        assert_true(r.est.next_signif < r.est.threshold);
        assert_true(r.est.threshold > 6 && r.est.threshold < 8); /* 2 sqrt(2 ln bins), 12 x 12 */
    }
}

/* Single-layer zonal loops (ao_rcond 0.05) of the issue-12 matrix's systems, seed 1 (the keys
 * of bench_telemetry --only K --print-keys): one layer each. Before the stacking needed three
 * lags, left the tracked layer out as it stacks too, and dropped a tracked layer standing below
 * the threshold, each gave two: on the 12 x 12 at 800 Hz the tracker's peaks made a layer of
 * 28.5 m/s toward 182 deg (3.8 sd) and the stacking found the true one (18 m/s toward 135); on
 * the 16 x 16 a second copy of the tracked layer (14.2 m/s toward 194, along 2 lags); on the
 * 24 x 24 at 500 Hz a layer of 1490 m/s along lags 1 and 2. */
static void test_wind_zonal_loops(void **state)
{
    (void)state;
    const struct {
        const char *sub, *keys[9];
        double speed, dir;
        int dropped;
    } cases[] = {
        {"z12", {"nsub=12", "act_pitch=0.4496", "ao_modes=56", "wfs_rate=800", "frame_ratio=7.3", "layer_speed=18",
                 "layer_dir=135", "vib_amp=0.2", "read_noise=15"}, 18, 135, 1},
        {"z16", {"nsub=16", "act_pitch=0.3372", "ao_modes=100", "wfs_rate=1000", "frame_ratio=9.7", "layer_speed=14",
                 "layer_dir=200", "vib_amp=0.4", "read_noise=15"}, 14, 200, 0},
        {"z24", {"nsub=24", "act_pitch=0.2248", "ao_modes=225", "wfs_rate=500", "frame_ratio=9", "layer_speed=5",
                 "layer_dir=315", "vib_amp=0", "read_noise=0"}, 5, 315, 0},
    };
    for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
        const char *kv[24] = {"pupn=100", "pupdx=0.065", "screen_n=1024", "nlayers=1", "layer_frac=1", "vib_freq=12",
                              "ncubes=6", "cube_frames=100", "start_offset=300.637", "wfs_file_frames=4000", "seed=1",
                              "ao_rcond=0.05", "camera_light=1"};
        size_t n = 13;
        for (size_t i = 0; i < 9; i++) kv[n++] = cases[k].keys[i];
        series_of(cases[k].sub, kv, n);
        char f0[1300], f1[1300];
        snprintf(f0, sizeof f0, "%s/slopes_000.fits", p(cases[k].sub));
        snprintf(f1, sizeof f1, "%s/slopes_001.fits", p(cases[k].sub));
        const char *files[] = {f0, f1};
        swfs_wind_run_options o = {files, 2, NULL, 0, 6.5, 0};
        swfs_wind_run_result r;
        assert_ok(swfs_wind_run(&o, &r));
        print_message("%s: tracked %.2f m/s toward %.1f deg (%.1f sd), %zu layer(s): %.2f m/s toward %.1f deg, "
                      "%.1f sd; best other %.1f sd (threshold %.1f)\n", cases[k].sub, r.est.speed, r.est.direction,
                      r.est.tracked_signif, r.est.nlayers, r.est.layer[0].speed, r.est.layer[0].direction,
                      r.est.layer[0].signif, r.est.next_signif, r.est.threshold);
        assert_true(r.est.found);
        assert_int_equal(r.est.nlayers, 1);
        assert_true(fabs(r.est.layer[0].speed / cases[k].speed - 1) < 0.10);
        assert_true(angle_diff(r.est.layer[0].direction, cases[k].dir) < 5.0);
        assert_true(r.est.layer[0].signif >= r.est.threshold && r.est.layer[0].nlags >= 3);
        assert_int_equal(r.est.tracked_dropped, cases[k].dropped);
        if (cases[k].dropped)
            assert_true(r.est.tracked_signif < r.est.threshold && angle_diff(r.est.direction, cases[k].dir) > 20.0);
        else
            assert_true(r.est.tracked_signif == r.est.layer[0].signif);
    }
}

/* Two layers of similar speeds in other directions (8 and 12 m/s toward 45 and 300 deg, 0.6 and
 * 0.4 of the turbulence) under a zonal loop on a 16 x 16 at 600 Hz: at 32 frames the map has
 * one peak between the two layers, at 64 none inside the window the prediction allows; the
 * tracker tries the next lag (128) before it gives up, and finds the 12 m/s layer there, the
 * stacking the 8 m/s one. Before, a lag lost after the first kept one ended the track and no
 * layer was found. */
static void test_wind_two_layers_merged(void **state)
{
    (void)state;
    const char *kv[] = {"pupn=100", "pupdx=0.065", "screen_n=1024", "nsub=16", "act_pitch=0.3372", "wfs_rate=600",
                        "frame_ratio=5", "nlayers=2", "layer_frac=0.6,0.4", "layer_speed=8,12", "layer_dir=45,300",
                        "vib_amp=0.2", "vib_freq=25", "read_noise=5", "ncubes=6", "cube_frames=100",
                        "start_offset=300.274", "seed=2", "ao_rcond=0.05", "camera_light=1"};
    series_of("merged", kv, sizeof kv / sizeof kv[0]);
    swfs_wind_run_result r;
    wind_of("merged", &r);
    assert_true(r.est.found);
    assert_int_equal(r.est.nlayers, 2);
    const double sp[2] = {12, 8}, dr[2] = {300, 45};
    for (int k = 0; k < 2; k++) {
        assert_true(fabs(r.est.layer[k].speed / sp[k] - 1) < 0.05);
        assert_true(angle_diff(r.est.layer[k].direction, dr[k]) < 5.0);
    }
    /* the track: a lag lost between the first kept one and the second */
    size_t first = SIZE_MAX, second = SIZE_MAX;
    for (size_t k = 0; k < r.est.nlags; k++)
        if (r.est.lag[k].used) {
            if (first == SIZE_MAX) first = k;
            else if (second == SIZE_MAX) second = k;
        }
    assert_true(first != SIZE_MAX && second != SIZE_MAX && second > first + 1);
}

/* The valid subapertures' slopes alone, with the map, give the same answer to the bit. */
static void test_wind_valid_only(void **state)
{
    (void)state;
    swfs_real *s = NULL;
    assert_ok(swfs_fits_read_real(p("one30/slopes_000.fits"), NULL, &s, NULL));
    const size_t ns = s->nx, T = s->ny, n2 = ns / 2, nsub = 12;
    unsigned char valid[144];
    size_t nv = 0;
    for (size_t a = 0; a < n2; a++) {
        int seen = 0;
        for (size_t t = 0; t < T && !seen; t++) seen = s->data[t * ns + a] != 0;
        valid[a] = (unsigned char)seen;
        nv += (size_t)seen;
    }
    double *c = malloc(T * 2 * nv * sizeof *c);
    for (size_t t = 0; t < T; t++)
        for (size_t a = 0, k = 0; a < n2; a++)
            if (valid[a]) {
                c[t * 2 * nv + k] = s->data[t * ns + a];
                c[t * 2 * nv + nv + k] = s->data[t * ns + n2 + a];
                k++;
            }
    swfs_wind_estimate full, compact;
    assert_ok(swfs_wind_from_slopes(s->data, T, ns, nsub, NULL, 6.5 / 12, 527, &full));
    assert_ok(swfs_wind_from_slopes(c, T, 2 * nv, nsub, valid, 6.5 / 12, 527, &compact));
    print_message("full %.6f m/s %.4f deg, valid-only %.6f m/s %.4f deg (%zu of %zu subapertures)\n", full.speed,
                  full.direction, compact.speed, compact.direction, nv, n2);
    assert_true(full.found && compact.found);
    assert_true(full.speed == compact.speed && full.direction == compact.direction);
    assert_int_equal(full.nlayers, compact.nlayers);
    assert_true(full.next_signif == compact.next_signif);
    assert_int_equal(full.nvalid, nv);
    free(c);
    swfs_real_free(s);
}

static void test_wind_noise_and_refusals(void **state)
{
    (void)state;
    const size_t nsub = 12, ns = 2 * nsub * nsub, T = 2000;
    double *s = malloc(T * ns * sizeof *s);
    swfs_rng rng;
    swfs_rng_seed2(&rng, 5, 0);
    for (size_t i = 0; i < T * ns; i++) s[i] = swfs_rng_normal(&rng);
    swfs_wind_estimate e;
    assert_ok(swfs_wind_from_slopes(s, T, ns, nsub, NULL, 0.5, 500, &e));
    print_message("white noise: found %d, %zu lags tracked of %zu\n", e.found, e.nused, e.nlags);
    assert_false(e.found);
    assert_int_equal(e.nlayers, 0);
    assert_int_equal(swfs_wind_from_slopes(s, 40, ns, nsub, NULL, 0.5, 500, &e), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "40 WFS frames; the displacement needs at least 64"));
    assert_int_equal(swfs_wind_from_slopes(s, T, ns - 2, nsub, NULL, 0.5, 500, &e), SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "286 slopes per frame; expected 2 nsub^2 = 288"));
    s[70 * ns + 3] = NAN;
    assert_int_equal(swfs_wind_from_slopes(s, T, ns, nsub, NULL, 0.5, 500, &e), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "slope 3 of WFS frame 70 is not finite"));
    free(s);
    /* through the run layer: a file named, its WFSRATE missing */
    const char *files[] = {p("one30/actuators.fits")};
    swfs_wind_run_options o = {files, 1, NULL, 12, 6.5, 0};
    swfs_wind_run_result r;
    assert_int_not_equal(swfs_wind_run(&o, &r), SWFS_OK);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "actuators.fits"));
}

/* The configuration of the series test_mode_knee simulates (the system's geometry). */
static void knee_params(swfs_ts_params *tp, const char *valid)
{
    swfs_config *c = swfs_config_new();
    assert_ok(swfs_config_set(c, "pupn=66"));
    assert_ok(swfs_config_set(c, "pupdx=0.1"));
    assert_ok(swfs_config_set(c, "screen_n=1024"));
    if (valid) {
        char kv[1400];
        snprintf(kv, sizeof kv, "valid=%s", valid);
        assert_ok(swfs_config_set(c, kv));
    }
    swfs_ts_params_default(tp);
    assert_ok(swfs_ts_params_from_config(c, tp));
    swfs_config_free(c);
}

/* The used subapertures of full-layout slopes s, less those with a neighbour unused (the
 * pupil's edge ring), as a valid map file. Returns how many are left. */
static size_t write_inner_map(const swfs_real *s, const char *path)
{
    const size_t nsa = s->nx / 2, n = (size_t)llround(sqrt((double)nsa));
    unsigned char used[400] = {0};
    assert_true(nsa <= 400 && n * n == nsa);
    for (size_t a = 0; a < nsa; a++)
        for (size_t t = 0; t < s->ny && !used[a]; t++) used[a] = s->data[t * s->nx + a] != 0;
    swfs_real *v = swfs_real_alloc(n, n, 1);
    assert_non_null(v);
    size_t left = 0;
    for (size_t y = 0; y < n; y++)
        for (size_t x = 0; x < n; x++) {
            const size_t a = y * n + x;
            const int inner = used[a] && x > 0 && y > 0 && x + 1 < n && y + 1 < n && used[a - 1] && used[a + 1] &&
                              used[a - n] && used[a + n];
            v->data[a] = inner;
            left += (size_t)inner;
        }
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, v, 8));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(v);
    return left;
}

static void test_mode_knee(void **state)
{
    (void)state;
    /* two power laws meeting at mode 37 of 120 (rising, then falling): the break exactly; and
     * so with modes of no variance (NaN) among them */
    double v[120];
    for (size_t j = 0; j < 120; j++) v[j] = j < 37 ? pow((double)(j + 1), 1.5) : pow(37.0, 1.5) * pow((double)(j + 1) / 37.0, -0.4);
    assert_int_equal(swfs_mode_knee(v, 120), 37);
    assert_int_equal(swfs_mode_knee(v, 5), 0);
    v[10] = v[36] = NAN;
    for (size_t j = 90; j < 120; j++) v[j] = NAN;
    assert_int_equal(swfs_mode_knee(v, 120), 36); /* the last mode with a variance before the break */
    /* loops controlling 30 and 60 of their DM's modes (one 12 m/s layer): each knee within
     * 15 % of the modes controlled. Then the 60-mode loop with a valid map that leaves out the
     * pupil's edge ring: fewer slopes than DM modes, so the modes beyond the rank of its
     * interaction matrix have no variance (NaN), and the knee is still the filter. */
    const size_t K[3] = {30, 60, 60};
    char ring[1300] = "";
    size_t nring = 0;
    for (int i = 0; i < 3; i++) {
        char modes[32], sub[32], f[1300], vkey[1400];
        snprintf(modes, sizeof modes, "ao_modes=%zu", K[i]);
        snprintf(sub, sizeof sub, "modes%zu%s", K[i], i == 2 ? "_ring" : "");
        snprintf(vkey, sizeof vkey, "valid=%s", ring);
        const char *extra[] = {"nlayers=1", "layer_speed=12", "layer_frac=1", modes, "cube_frames=20", "cube_gap=700",
                               "nfx=16", "nfy=16", vkey};
        series(sub, extra, i == 2 ? 9 : 8);
        snprintf(f, sizeof f, "%s/slopes_000.fits", p(sub));
        swfs_real *s = NULL;
        assert_ok(swfs_telemetry_read(f, 0, &s, NULL));
        swfs_ts_params tp;
        knee_params(&tp, i == 2 ? ring : NULL);
        double *var = NULL;
        size_t n = 0, nnan = 0;
        assert_ok(swfs_ts_mode_variance(&tp, s->data, s->ny, s->nx, &var, &n));
        const size_t knee = swfs_mode_knee(var, n);
        for (size_t j = 0; j < n; j++) {
            nnan += (size_t)isnan(var[j]);
            assert_true(isnan(var[j]) || (isfinite(var[j]) && var[j] >= 0));
        }
        print_message("ao_modes %zu%s: knee at mode %zu of %zu (%zu without a variance)\n", K[i],
                      i == 2 ? " (edge ring left out)" : "", knee, n, nnan);
        assert_true(n > 100 && fabs((double)knee - (double)K[i]) <= 0.15 * (double)K[i]);
        if (i < 2) assert_int_equal(nnan, 0);
        else assert_true(nnan >= n - 2 * nring && nnan < n / 2); /* at least those beyond 2 nvalid slopes */
        free(var);
        if (i == 1) {
            snprintf(ring, sizeof ring, "%s", p("ring_valid.fits"));
            nring = write_inner_map(s, ring);
            assert_true(nring > 50 && 2 * nring < n);
        }
        if (i == 0) {
            /* too few frames: refused */
            assert_int_equal(swfs_ts_mode_variance(&tp, s->data, 1, s->nx, &var, &n), SWFS_ERR_ARG);
            /* another width: refused, naming what was expected */
            assert_int_equal(swfs_ts_mode_variance(&tp, s->data, s->ny / 2, s->nx * 2, &var, &n), SWFS_ERR_SHAPE);
            assert_non_null(strstr(swfs_last_error(), "2 nsub^2 = 288"));
        }
        swfs_real_free(s);
    }
}

/* The slopes' time correlation along the upper half of the DM modes (swfs_ts_mode_timecorr,
 * teach's speed where no layer is tracked): a slower layer's slopes stay correlated longer at
 * every lag; white-noise slopes are uncorrelated; white slopes each held for 8 frames give
 * (8 - lag) / 8; a lag beyond the frames and another width are refused. */
static void test_mode_timecorr(void **state)
{
    (void)state;
    const long lags[5] = {1, 2, 4, 8, 16};
    double rho[2][5];
    const char *speed[2] = {"layer_speed=5", "layer_speed=20"};
    swfs_ts_params tp;
    knee_params(&tp, NULL);
    swfs_real *s = NULL;
    for (int i = 0; i < 2; i++) {
        char sub[32], f[1300];
        snprintf(sub, sizeof sub, "timecorr%d", i);
        const char *extra[] = {"nlayers=1", speed[i], "layer_frac=1", "cube_frames=20", "cube_gap=700", "nfx=16", "nfy=16"};
        series(sub, extra, 7);
        snprintf(f, sizeof f, "%s/slopes_000.fits", p(sub));
        swfs_real_free(s);
        s = NULL;
        assert_ok(swfs_telemetry_read(f, 0, &s, NULL));
        assert_ok(swfs_ts_mode_timecorr(&tp, s->data, s->ny, s->nx, lags, 5, rho[i]));
        print_message("%s: %zu frames, rho %.3f %.3f %.3f %.3f %.3f\n", speed[i], s->ny, rho[i][0], rho[i][1], rho[i][2],
                      rho[i][3], rho[i][4]);
    }
    for (int k = 0; k < 5; k++) assert_true(rho[1][k] < rho[0][k] && rho[0][k] <= 1.0);
    assert_true(rho[0][0] > 0.8 && rho[1][4] < 0.5);
    /* white slopes, then the same held for 8 frames each */
    const size_t nf = s->ny, ns = s->nx;
    swfs_rng g;
    swfs_rng_seed(&g, 11);
    for (size_t t = 0; t < nf; t++)
        for (size_t i = 0; i < ns; i++) s->data[t * ns + i] = swfs_rng_normal(&g);
    double w[5], h[5];
    assert_ok(swfs_ts_mode_timecorr(&tp, s->data, nf, ns, lags, 5, w));
    for (size_t t = 0; t < nf; t++)
        if (t % 8) memcpy(s->data + t * ns, s->data + (t - t % 8) * ns, ns * sizeof *s->data);
    assert_ok(swfs_ts_mode_timecorr(&tp, s->data, nf, ns, lags, 5, h));
    print_message("white: %.3f %.3f %.3f %.3f %.3f; held 8 frames: %.3f %.3f %.3f %.3f %.3f\n", w[0], w[1], w[2], w[3],
                  w[4], h[0], h[1], h[2], h[3], h[4]);
    for (int k = 0; k < 5; k++) {
        assert_true(fabs(w[k]) < 0.02);
        assert_true(fabs(h[k] - (lags[k] < 8 ? (8.0 - (double)lags[k]) / 8.0 : 0.0)) < 0.03);
    }
    const long far[1] = {(long)nf};
    assert_int_equal(swfs_ts_mode_timecorr(&tp, s->data, nf, ns, far, 1, w), SWFS_ERR_ARG);
    assert_int_equal(swfs_ts_mode_timecorr(&tp, s->data, nf / 2, ns * 2, lags, 5, w), SWFS_ERR_SHAPE);
    swfs_real_free(s);
}

/* The lag maps' sums (wind_internal.h swfs_wind_lag_sums_, by FFT) are the pairs' products
 * summed directly: random slopes on 37 of a 7 x 7 grid's subapertures (taken in a shuffled
 * order), 60 frames, lags 0, 1, 5 and 59; the whole spectrum at once and in bands of 4
 * frequencies (a budget of 3 coefficients over the frames: the least band, 4, as the sums run
 * over 4 frequencies side by side; 49 bands of the 14 x 14 padded grid's 196); and a lag as
 * long as the series refused. */
static void test_wind_lag_sums(void **state)
{
    (void)state;
    enum { NS = 7, NV = 37, T = 60, NL = 4, NB = 2 * NS - 1 };
    swfs_rng g;
    swfs_rng_seed(&g, 21);
    size_t pos[NS * NS];
    for (size_t s = 0; s < NS * NS; s++) pos[s] = s;
    for (size_t s = NS * NS - 1; s > 0; s--) {
        const size_t j = (size_t)(swfs_rng_uniform(&g) * (double)(s + 1)) % (s + 1), v = pos[s];
        pos[s] = pos[j];
        pos[j] = v;
    }
    static double x[T * NV], y[T * NV], want[NL * NB * NB], got[NL * NB * NB];
    for (size_t k = 0; k < T * NV; k++) {
        x[k] = swfs_rng_normal(&g);
        y[k] = swfs_rng_normal(&g) + 0.5 * x[k];
    }
    const size_t lag[NL] = {0, 1, 5, T - 1};
    memset(want, 0, sizeof want);
    double scale = 0;
    for (size_t l = 0; l < NL; l++)
        for (size_t p = 0; p < NV; p++)
            for (size_t q = 0; q < NV; q++) {
                const long a = (long)(pos[q] % NS) - (long)(pos[p] % NS), b = (long)(pos[q] / NS) - (long)(pos[p] / NS);
                double v = 0;
                for (size_t t = 0; t + lag[l] < T; t++)
                    v += x[t * NV + p] * x[(t + lag[l]) * NV + q] + y[t * NV + p] * y[(t + lag[l]) * NV + q];
                want[l * NB * NB + (size_t)(b + NS - 1) * NB + (size_t)(a + NS - 1)] += v;
                scale = fmax(scale, fabs(v));
            }
    const size_t budgets[2] = {0, 3 * T * sizeof(double _Complex)};
    for (int k = 0; k < 2; k++) {
        assert_ok(swfs_wind_lag_sums_(x, y, T, NV, pos, NS, lag, NL, budgets[k], got));
        double worst = 0;
        for (size_t i = 0; i < NL * NB * NB; i++) worst = fmax(worst, fabs(got[i] - want[i]));
        print_message("lag sums by FFT (%s): largest difference from the pairs' %.2e (largest pair sum %.1f)\n",
                      k ? "bands of 4 frequencies" : "one band", worst, scale);
        assert_true(worst < 1e-12 * scale);
    }
    const size_t far[1] = {T};
    assert_int_equal(swfs_wind_lag_sums_(x, y, T, NV, pos, NS, far, 1, 0, got), SWFS_ERR_ARG);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_wind_lag_sums),
        cmocka_unit_test(test_wind_of_simulated_loops),
        cmocka_unit_test(test_wind_valid_only),
        cmocka_unit_test(test_wind_two_layers_merged),
        cmocka_unit_test(test_wind_zonal_loops),
        cmocka_unit_test(test_wind_noise_and_refusals),
        cmocka_unit_test(test_mode_knee),
        cmocka_unit_test(test_mode_timecorr),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}

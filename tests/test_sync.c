/* Synchronization: fractional exposure weights, box means, recovery of a planted frame
 * ratio, lag and axis pairing, handshake log and timing table round trips and errors. */
#include "testutil.h"

#include "specklewfs/engine.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static void test_fractional_weights(void **state)
{
    (void)state;
    /* Every exposure's weights sum to its length (the ratio), and consecutive exposures
     * share a straddling frame whose two weights sum to 1. */
    const double ratios[] = {6.48, 1.0, 2.5, 7.0, 3.3333};
    for (size_t t = 0; t < sizeof ratios / sizeof ratios[0]; t++) {
        swfs_exposure sch[100];
        double off = 0.37 * (double)t;
        size_t need = swfs_engine_schedule(ratios[t], off, 100, sch);
        /* Rounding may add a last frame of weight ~1e-13. */
        size_t want = (size_t)ceil(off + 100 * ratios[t] - 1e-9);
        assert_true(need == want || need == want + 1);
        for (size_t j = 0; j < 100; j++) {
            double w = sch[j].count == 1 ? sch[j].w_first
                                         : sch[j].w_first + sch[j].w_last + (double)(sch[j].count - 2);
            assert_close(w, ratios[t], 1e-9);
            double a = off + (double)j * ratios[t];
            assert_int_equal(sch[j].first, (size_t)floor(a));
        }
        /* The box means use the same weights: a ramp m[k] = k has the mean of its
         * piecewise-constant integral. */
        double m[800], out[100];
        for (size_t k = 0; k < 800; k++) m[k] = (double)k;
        assert_ok(swfs_sync_box_means(m, 800, off, ratios[t], 100, out));
        for (size_t j = 0; j < 100; j++) {
            double acc = 0;
            for (size_t k = 0; k < sch[j].count; k++) {
                double w = k == 0 ? sch[j].w_first : (k + 1 == sch[j].count ? sch[j].w_last : 1.0);
                acc += w * m[sch[j].first + k];
            }
            assert_close(out[j], acc / ratios[t], 1e-9);
        }
        assert_int_not_equal(swfs_sync_box_means(m, 100, off, ratios[t], 100, out), 0);
    }
}

/* A residual tip-tilt series: a 20 Hz vibration at 527 Hz plus red noise. */
static void make_tiptilt(double *mx, double *my, size_t n, swfs_rng *rng)
{
    double ax = 0, ay = 0, ph = 2 * M_PI * swfs_rng_uniform(rng);
    for (size_t k = 0; k < n; k++) {
        ax = 0.95 * ax + 0.3 * swfs_rng_normal(rng);
        ay = 0.95 * ay + 0.3 * swfs_rng_normal(rng);
        double v = sin(2 * M_PI * 20.0 / 527.0 * (double)k + ph);
        mx[k] = 1e-7 * (v + ax + 0.2 * swfs_rng_normal(rng));
        my[k] = 1e-7 * (0.7 * cos(2 * M_PI * 20.0 / 527.0 * (double)k + ph) + ay + 0.2 * swfs_rng_normal(rng));
    }
}

/* Six cubes in two telemetry files, the camera's axes swapped and x flipped, the handshake
 * logged `lag` whole frames late; sync over ratios ratio_min-8 and lags [lag_min, lag_max]. */
static void recover(double lag, double lag_min, double lag_max, double ratio_min, swfs_sync_result *r)
{
    enum { NFILE = 2, NWFS = 2600, NCUBE = 6, NF = 100 };
    const double ratio = 6.48;
    swfs_rng rng;
    swfs_rng_seed(&rng, 2024);
    double *mx = malloc(NFILE * NWFS * sizeof *mx), *my = malloc(NFILE * NWFS * sizeof *my);
    for (int f = 0; f < NFILE; f++) make_tiptilt(mx + f * NWFS, my + f * NWFS, NWFS, &rng);
    double tx[NCUBE][NF], ty[NCUBE][NF], bx[NF], by[NF];
    swfs_sync_cube cubes[NCUBE];
    double truth_start[NCUBE];
    for (int c = 0; c < NCUBE; c++) {
        int f = c % NFILE;
        /* True start anywhere inside a frame; the log is late by `lag` whole frames. */
        double start = 100.0 + 700.0 * (c / NFILE) + swfs_rng_uniform(&rng);
        truth_start[c] = start;
        assert_ok(swfs_sync_box_means(mx + f * NWFS, NWFS, start, ratio, NF, bx));
        assert_ok(swfs_sync_box_means(my + f * NWFS, NWFS, start, ratio, NF, by));
        /* Camera axes swapped and x flipped relative to the WFS; 1 rad = 2e6 pixels. */
        for (int j = 0; j < NF; j++) {
            tx[c][j] = 27.0 + c - 2e6 * by[j] + 0.02 * swfs_rng_normal(&rng);
            ty[c][j] = 26.0 + 2e6 * bx[j] + 0.02 * swfs_rng_normal(&rng);
        }
        cubes[c] = (swfs_sync_cube){NF, tx[c], ty[c], mx + f * NWFS, my + f * NWFS, NWFS, floor(start) + lag};
    }
    swfs_sync_params p;
    swfs_sync_params_default(&p);
    p.ratio_min = ratio_min; p.ratio_max = 8;
    p.lag_min = lag_min; p.lag_max = lag_max;
    assert_ok(swfs_sync_estimate(cubes, NCUBE, &p, r));
    print_message("lag %g in [%g, %g]: ratio %.4f +- %.4f lag %.3f (window %g .. %g, %d moves) swap %d signs %d %d "
                  "corr %.3f %.3f, %.1f sigma (needs %.1f)\n", lag, lag_min, lag_max, r->ratio, r->ratio_err, r->lag,
                  r->lag_min, r->lag_max, r->lag_moves, r->swap, r->sign_x, r->sign_y, r->corr_x, r->corr_y, r->z,
                  r->z_need);
    assert_close(r->ratio, ratio, 0.03);
    assert_true(r->ratio_err > 0 && r->ratio_err < 0.03);
    assert_close(r->lag, lag, 1.0);
    assert_int_equal(r->swap, 1);
    assert_int_equal(r->sign_x, -1);
    assert_int_equal(r->sign_y, 1);
    assert_true(r->corr_y > 0.9 && r->corr_x < -0.9);
    assert_true(r->z > r->z_need);
    assert_int_equal(r->ncubes_used, NCUBE);
    /* The estimated start of every cube is within a frame of the truth. */
    for (int c = 0; c < NCUBE; c++) assert_close(cubes[c].logged - r->lag, truth_start[c], 1.0);
    free(mx); free(my);
}

static void test_sync_recovers_ratio_and_lag(void **state)
{
    (void)state;
    swfs_sync_result r;
    recover(3.0, -20, 20, 5, &r);
    assert_int_equal(r.lag_moves, 0);
    /* The refinement stays inside the range searched: a lower bound just above the true 6.48
     * (the refinement once reached two coarse steps below the bound, and found 6.48). */
    recover(3.0, -20, 20, 6.485, &r);
    assert_true(r.ratio >= 6.485);
    /* A handshake logged 25 frames late, beyond the window -3 .. 12: the peak at the window's
     * edge moves it until the peak is inside. */
    recover(25.0, -3, 12, 5, &r);
    assert_true(r.lag_moves >= 1 && r.lag_min < 25 && r.lag_max > 25);
}

/* A cube that crosses from one telemetry file into the next: its part in the next file is
 * found to continue there when the files are contiguous, and not when WFS frames were lost
 * between them or the next file holds other data. */
static void test_continuation(void **state)
{
    (void)state;
    enum { NWFS = 1500, NF = 100, LOST = 3 };
    const double ratio = 6.48, lag = 3.0, start = 1200.37; /* exposures 46.. lie in the next file */
    swfs_rng rng;
    swfs_rng_seed(&rng, 77);
    double *mx = malloc(3 * NWFS * sizeof *mx), *my = malloc(3 * NWFS * sizeof *my);
    make_tiptilt(mx, my, 3 * NWFS, &rng);
    double bx[NF], by[NF], tx[NF], ty[NF];
    assert_ok(swfs_sync_box_means(mx, 3 * NWFS, start, ratio, NF, bx));
    assert_ok(swfs_sync_box_means(my, 3 * NWFS, start, ratio, NF, by));
    for (int j = 0; j < NF; j++) {
        tx[j] = 27.0 - 2e6 * by[j] + 0.02 * swfs_rng_normal(&rng);
        ty[j] = 26.0 + 2e6 * bx[j] + 0.02 * swfs_rng_normal(&rng);
    }
    swfs_sync_result fit;
    memset(&fit, 0, sizeof fit);
    fit.ratio = ratio; fit.lag = lag; fit.swap = 1; fit.sign_x = -1; fit.sign_y = 1;
    swfs_sync_params p;
    swfs_sync_params_default(&p);
    p.lag_min = -3; p.lag_max = 12;
    const size_t j0 = (size_t)ceil((NWFS - start) / ratio);
    const double sb = start - NWFS + (double)j0 * ratio; /* the part's start in the next file if contiguous */
    /* Contiguous: the next file is the series' frames NWFS.. */
    swfs_sync_cube part = {NF - j0, tx + j0, ty + j0, mx + NWFS, my + NWFS, NWFS, sb + lag};
    swfs_sync_continuation cc;
    assert_ok(swfs_sync_continuation_check(&part, &fit, &p, &cc));
    print_message("contiguous: offset %+.3f corr %.3f %.3f over %zu\n", cc.offset, cc.corr_x, cc.corr_y, cc.nexp);
    assert_int_equal(cc.continues, 1);
    assert_true(fabs(cc.offset) < 0.2);
    assert_true(cc.corr_x > 0.9 && cc.corr_y > 0.9);
    assert_int_equal(cc.off_significant, 0); /* where the fit's lag puts it */
    /* LOST frames between the files: the next file starts LOST frames later in the series. */
    part.mx = mx + NWFS + LOST;
    part.my = my + NWFS + LOST;
    assert_ok(swfs_sync_continuation_check(&part, &fit, &p, &cc));
    print_message("%d lost: offset %+.3f, corr %.3f %.3f there, %.3f %.3f at the fit's lag\n", LOST, cc.offset,
                  cc.corr_x, cc.corr_y, cc.corr_x0, cc.corr_y0);
    assert_int_equal(cc.continues, 0);
    assert_close(cc.offset, LOST, 0.3);
    assert_int_equal(cc.off_significant, 1); /* the camera tells it from contiguous */
    /* Other data: a file from elsewhere in the series. */
    part.mx = mx + 2 * NWFS;
    part.my = my + 2 * NWFS;
    assert_ok(swfs_sync_continuation_check(&part, &fit, &p, &cc));
    print_message("unrelated: offset %+.3f corr %.3f %.3f\n", cc.offset, cc.corr_x, cc.corr_y);
    assert_int_equal(cc.continues, 0);

    /* A short part (SHORT exposures) whose camera y sees a weak tilt (the signal scaled by
     * WEAK against the same centroid noise): that axis alone is below 5 sigma, both together
     * above; it continues. The unrelated file stays refused. */
    enum { SHORT = 16 };
    const double WEAK = 0.11;
    double tx2[SHORT], ty2[SHORT];
    for (size_t j = 0; j < SHORT; j++) {
        tx2[j] = tx[j0 + j];
        ty2[j] = 26.0 + WEAK * 2e6 * bx[j0 + j] + 0.02 * swfs_rng_normal(&rng);
    }
    swfs_sync_cube shrt = {SHORT, tx2, ty2, mx + NWFS, my + NWFS, NWFS, sb + lag};
    assert_ok(swfs_sync_continuation_check(&shrt, &fit, &p, &cc));
    const double zs = sqrt(SHORT - 3.0), zx = atanh(cc.corr_x) * zs, zy = atanh(cc.corr_y) * zs;
    print_message("short: offset %+.3f corr %.3f %.3f (%.1f and %.1f sigma)\n", cc.offset, cc.corr_x, cc.corr_y, zx, zy);
    assert_true(fmin(zx, zy) < 5 && (zx + zy) / sqrt(2.0) > 5);
    assert_int_equal(cc.continues, 1);
    shrt.mx = mx + 2 * NWFS;
    shrt.my = my + 2 * NWFS;
    assert_ok(swfs_sync_continuation_check(&shrt, &fit, &p, &cc));
    print_message("short, unrelated: offset %+.3f corr %.3f %.3f\n", cc.offset, cc.corr_x, cc.corr_y);
    assert_int_equal(cc.continues, 0);
    free(mx); free(my);
}

static void test_files_and_errors(void **state)
{
    (void)state;
    swfs_handshake h[2] = {{"raw_000.fits", "slopes_000.fits", 120}, {"raw_001.fits", "slopes_001.fits", 4}};
    assert_ok(swfs_handshake_write(test_path("hs.log"), h, 2));
    swfs_handshake *hr = NULL;
    size_t n = 0;
    assert_ok(swfs_handshake_read(test_path("hs.log"), &hr, &n));
    assert_int_equal(n, 2);
    assert_string_equal(hr[1].slopes, "slopes_001.fits");
    assert_int_equal(hr[0].frame, 120);
    free(hr);
    FILE *f = fopen(test_path("bad.log"), "w");
    fprintf(f, "# comment\nraw_000.fits slopes_000.fits\n");
    fclose(f);
    assert_int_not_equal(swfs_handshake_read(test_path("bad.log"), &hr, &n), 0);
    assert_non_null(strstr(swfs_last_error(), "bad.log:2"));

    swfs_timing_cube tc[2] = {{.camera = "raw_000.fits", .slopes = "slopes_000.fits", .first = 0, .nframes = 100,
                               .start = 117.25, .status = SWFS_CUBE_OK},
                              {.camera = "raw_001.fits", .slopes = "slopes_000.fits", .first = 100, .nframes = 100,
                               .start = 2590.5, .status = SWFS_CUBE_STRADDLES}};
    swfs_timing t;
    memset(&t, 0, sizeof t);
    t.ratio = 6.48; t.ratio_err = 0.01; t.lag = 2.75; t.ncubes = 2; t.cubes = tc;
    t.fit.sign_x = t.fit.sign_y = 1;
    assert_ok(swfs_timing_write(test_path("timing.txt"), &t));
    swfs_timing *tr = NULL;
    assert_ok(swfs_timing_read(test_path("timing.txt"), &tr));
    assert_close(tr->ratio, 6.48, 1e-9);
    assert_close(tr->lag, 2.75, 1e-9);
    assert_int_equal(tr->ncubes, 2);
    assert_int_equal(tr->cubes[1].status, SWFS_CUBE_STRADDLES);
    assert_close(tr->cubes[0].start, 117.25, 1e-9);
    assert_int_equal(tr->cubes[1].first, 100);
    swfs_timing_free(tr);
    /* A negative first frame (which %zu reads as SIZE_MAX, and first + nframes would wrap)
     * and an infinite ratio are refused, naming the file and line. */
    f = fopen(test_path("neg.txt"), "w");
    fprintf(f, "ratio 6.5 0.1\nlag 2\ncube 0 a.fits -1 2 s.fits 10.5 ok\n");
    fclose(f);
    tr = NULL;
    assert_int_equal(swfs_timing_read(test_path("neg.txt"), &tr), SWFS_ERR_FORMAT);
    assert_null(tr);
    assert_non_null(strstr(swfs_last_error(), "neg.txt:3: cube 0: FIRST_FRAME"));
    f = fopen(test_path("inf.txt"), "w");
    fprintf(f, "ratio inf 0.1\nlag 2\ncube 0 a.fits 0 2 s.fits 10.5 ok\n");
    fclose(f);
    assert_int_equal(swfs_timing_read(test_path("inf.txt"), &tr), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "inf.txt: ratio inf: expected a finite number of WFS frames per camera"));
    /* a table without its ratio and lag lines says so; one whose rows time the same science
     * frames twice (each with other telemetry) is refused, naming both rows and the frames */
    f = fopen(test_path("nolines.txt"), "w");
    fprintf(f, "cube 0 a.fits 0 2 s.fits 10.5 ok\n");
    fclose(f);
    assert_int_equal(swfs_timing_read(test_path("nolines.txt"), &tr), SWFS_ERR_FORMAT);
    assert_non_null(strstr(swfs_last_error(), "nolines.txt: the timing table needs 'ratio' and 'lag' lines"));
    f = fopen(test_path("overlap.txt"), "w");
    fprintf(f, "ratio 6.5 0.1\nlag 2\ncube 0 a.fits 0 60 s.fits 10.5 ok\ncube 1 b.fits 60 60 s.fits 500.5 ok\n"
               "cube 2 c.fits 100 60 t.fits 10.5 ok\n");
    fclose(f);
    assert_int_equal(swfs_timing_read(test_path("overlap.txt"), &tr), SWFS_ERR_FORMAT);
    assert_null(tr);
    assert_non_null(strstr(swfs_last_error(), "overlap.txt: cubes 1 (b.fits) and 2 (c.fits) both time science frames "
                                              "100-119 (theirs 60-119 and 100-159)"));

    /* No overlap anywhere in the search range. */
    double m[50] = {0}, tt[10] = {0};
    swfs_sync_cube c = {10, tt, tt, m, m, 50, 5000};
    swfs_sync_params p;
    swfs_sync_params_default(&p);
    swfs_sync_result r;
    assert_int_not_equal(swfs_sync_estimate(&c, 1, &p, &r), 0);
    assert_non_null(strstr(swfs_last_error(), "overlap"));
}

/* The telemetry's own verdict on a file boundary (swfs_sync_boundary_check): a series of
 * 512-value frames that changes slowly from frame to frame (an AR(1) process, rho = 0.995,
 * as an AO loop's residual at a kHz, with white measurement noise a tenth of its step) cut
 * into two files. Contiguous: +1; one frame lost, a frame repeated, a file from elsewhere:
 * -1; a noise-dominated series, where a one-frame step is no smaller than a two-frame one:
 * it cannot tell (0); two frames on a side: 0. */
static void make_ar(double *v, size_t n, size_t nvals, double rho, double noise, swfs_rng *rng)
{
    double *x = calloc(nvals, sizeof *x);
    for (size_t i = 0; i < nvals; i++) x[i] = swfs_rng_normal(rng);
    for (size_t k = 0; k < n; k++)
        for (size_t i = 0; i < nvals; i++) {
            x[i] = rho * x[i] + sqrt(1 - rho * rho) * swfs_rng_normal(rng);
            v[k * nvals + i] = x[i] + noise * swfs_rng_normal(rng);
        }
    free(x);
}

static void test_boundary(void **state)
{
    (void)state;
    enum { NV = 512, N = 600, CUT = 300, K = SWFS_SYNC_EDGE_FRAMES };
    swfs_rng rng;
    swfs_rng_seed(&rng, 5);
    double *v = malloc((size_t)N * NV * sizeof *v), *u = malloc((size_t)N * NV * sizeof *u);
    const double rho = 0.995, step = sqrt(2 * (1 - rho)); /* rms one-frame step per value */
    make_ar(v, N, NV, rho, 0.1 * step, &rng);
    make_ar(u, N, NV, rho, 0.1 * step, &rng);
    const double *tail = v + (size_t)(CUT - K) * NV;
    swfs_sync_boundary b;
    assert_ok(swfs_sync_boundary_check(tail, K, v + (size_t)CUT * NV, K, NV, &b));
    print_message("contiguous: q %.4g, one-frame steps up to %.4g, two-frame from %.4g: %+d\n", b.q, b.q1_max,
                  b.q2_min, b.verdict);
    assert_int_equal(b.verdict, 1);
    assert_int_equal(b.n1, 2 * (K - 1));
    assert_int_equal(b.n2, 2 * (K - 2));
    assert_true(b.q < b.q2_min && b.q <= b.q1_max);
    assert_ok(swfs_sync_boundary_check(tail, K, v + (size_t)(CUT + 1) * NV, K, NV, &b));
    print_message("one frame lost: q %.4g: %+d\n", b.q, b.verdict);
    assert_int_equal(b.verdict, -1);
    assert_ok(swfs_sync_boundary_check(tail, K, v + (size_t)(CUT - 1) * NV, K, NV, &b));
    assert_close(b.q, 0, 0);
    assert_int_equal(b.verdict, -1); /* the last frame repeated */
    assert_ok(swfs_sync_boundary_check(tail, K, u + (size_t)CUT * NV, K, NV, &b));
    assert_int_equal(b.verdict, -1); /* a file from elsewhere */
    /* Contiguous at every cut of the series but the edges: right or undecided. */
    size_t yes = 0, no = 0, cuts = 0;
    for (size_t c = K; c + K <= N; c += 3, cuts++) {
        assert_ok(swfs_sync_boundary_check(v + (c - K) * NV, K, v + c * NV, K, NV, &b));
        yes += b.verdict > 0;
        no += b.verdict < 0;
    }
    print_message("contiguous at %zu cuts: %zu called contiguous, %zu not\n", cuts, yes, no);
    assert_true(yes >= cuts * 9 / 10 && no <= cuts / 50);
    /* White noise: a step over one frame is a step over two; it cannot tell. */
    make_ar(u, N, NV, 0.0, 0.0, &rng);
    yes = no = cuts = 0;
    for (size_t c = K; c + K <= N; c += 3, cuts++) {
        assert_ok(swfs_sync_boundary_check(u + (c - K) * NV, K, u + c * NV, K, NV, &b));
        yes += b.verdict > 0;
        no += b.verdict < 0;
    }
    print_message("white noise at %zu cuts: %zu called contiguous, %zu not\n", cuts, yes, no);
    assert_int_equal(yes, 0);
    assert_true(no <= cuts / 50);
    /* The WFS noise twice the one-frame change (per value): one step against one over two
     * frames cannot tell most cuts; the means of a few frames either side can (the second
     * stage), and a lost frame is called contiguous no more often than before. */
    enum { NW = 1024 };
    double *w = malloc((size_t)N * NW * sizeof *w);
    make_ar(w, N, NW, rho, 2 * step, &rng);
    size_t first = 0, lost_yes = 0, lost_no = 0;
    yes = no = cuts = 0;
    for (size_t c = K; c + 1 + K <= N; c += 3, cuts++) {
        assert_ok(swfs_sync_boundary_check(w + (c - K) * NW, K, w + c * NW, K, NW, &b));
        yes += b.verdict > 0;
        no += b.verdict < 0;
        first += b.verdict > 0 && !b.window;
        if (b.window) assert_true(b.p_lost >= 0 && b.p_lost <= 1 && b.p_contiguous >= 0 && b.p_contiguous <= 1);
        assert_ok(swfs_sync_boundary_check(w + (c - K) * NW, K, w + (c + 1) * NW, K, NW, &b));
        lost_yes += b.verdict > 0;
        lost_no += b.verdict < 0;
    }
    print_message("noisy, contiguous at %zu cuts: %zu called contiguous (%zu by one-frame steps), %zu not; "
                  "one frame lost: %zu contiguous, %zu not\n", cuts, yes, first, no, lost_yes, lost_no);
    assert_true(first <= cuts / 2);
    assert_true(yes >= cuts * 8 / 10 && no <= cuts / 50);
    assert_true(lost_yes <= cuts / 40);
    assert_ok(swfs_sync_boundary_check(w + (size_t)(CUT - K) * NW, K, w + (size_t)CUT * NW, K, NW, &b));
    print_message("noisy cut at %d: window %zu, q_m %.4g, P(lost <= q_m) %.3g, P(contiguous >= q_m) %.3g: %+d\n", CUT,
                  b.window, b.q_window, b.p_lost, b.p_contiguous, b.verdict);
    free(w);
    assert_ok(swfs_sync_boundary_check(v + (size_t)(CUT - 2) * NV, 2, v + (size_t)CUT * NV, K, NV, &b));
    assert_int_equal(b.verdict, 0);
    assert_int_equal(b.window, 0);
    assert_int_equal(swfs_sync_boundary_check(NULL, 0, v, K, NV, &b), SWFS_ERR_ARG);
    free(v);
    free(u);
}

/* The count of frames lost or repeated across a boundary against the telemetry
 * (swfs_sync_boundary_gap), on the AR(1) series of test_boundary: k frames lost (k = 1..6)
 * agree with k at nearly every cut, and a long gap (200 frames lost, another file) with no
 * small count. The count itself is the camera's (to half a frame): k + 1 agrees with the
 * telemetry of k lost more often as k grows (printed), and one lost is told from two. A
 * repeated frame agrees with -1 only where B starts with A's last values; white noise agrees
 * with no count (a step over k + 1 frames is one over many). */
static void test_gap(void **state)
{
    (void)state;
    enum { NV = 512, N = 1200, K = SWFS_SYNC_EDGE_FRAMES };
    swfs_rng rng;
    swfs_rng_seed(&rng, 7);
    double *v = malloc((size_t)N * NV * sizeof *v), *u = malloc((size_t)N * NV * sizeof *u);
    const double rho = 0.995, step = sqrt(2 * (1 - rho));
    make_ar(v, N, NV, rho, 0.1 * step, &rng);
    make_ar(u, N, NV, rho, 0.1 * step, &rng);
    swfs_sync_gap g;
    for (long k = 1; k <= 6; k++) {
        size_t agree = 0, wrong = 0, far = 0, other = 0, cuts = 0;
        for (size_t c = K; c + (size_t)k + 200 + K <= N; c += 7, cuts++) {
            const double *tail = v + (c - K) * NV, *head = v + (c + (size_t)k) * NV;
            assert_ok(swfs_sync_boundary_gap(tail, K, head, K, NV, k, &g));
            if (g.consistent) agree++;
            assert_true(g.separable);
            for (long d = -1; d <= 1; d += 2) { /* the neighbouring counts */
                if (k + d < 1) continue;
                assert_ok(swfs_sync_boundary_gap(tail, K, head, K, NV, k + d, &g));
                if (g.consistent) wrong++;
            }
            assert_ok(swfs_sync_boundary_gap(tail, K, v + (c + 200) * NV, K, NV, k, &g));
            if (g.consistent) far++;
            assert_ok(swfs_sync_boundary_gap(tail, K, u + c * NV, K, NV, k, &g));
            if (g.consistent) other++;
        }
        print_message("%ld frames lost at %zu cuts: the count agrees at %zu, k +- 1 at %zu, a gap of 200 at %zu, "
                      "another file at %zu\n", k, cuts, agree, wrong, far, other);
        assert_true(agree >= cuts * 9 / 10);
        if (k == 1) assert_true(wrong <= cuts / 20);
        assert_int_equal(far, 0);
        assert_int_equal(other, 0);
    }
    /* one frame repeated: B's first frame is A's last */
    const double *tail = v + (size_t)(300 - K) * NV;
    assert_ok(swfs_sync_boundary_gap(tail, K, v + (size_t)299 * NV, K, NV, -1, &g));
    assert_true(g.consistent);
    assert_ok(swfs_sync_boundary_gap(tail, K, v + (size_t)298 * NV, K, NV, -2, &g));
    assert_true(g.consistent);
    assert_ok(swfs_sync_boundary_gap(tail, K, v + (size_t)299 * NV, K, NV, -2, &g));
    assert_false(g.consistent);
    assert_ok(swfs_sync_boundary_gap(tail, K, v + (size_t)301 * NV, K, NV, -1, &g));
    assert_false(g.consistent);
    /* white noise: no count */
    make_ar(u, N, NV, 0.0, 0.0, &rng);
    size_t agree = 0;
    for (size_t c = K; c + 3 + K <= N; c += 7) {
        assert_ok(swfs_sync_boundary_gap(u + (c - K) * NV, K, u + (c + 2) * NV, K, NV, 2, &g));
        if (g.consistent) agree++;
        assert_false(g.separable);
    }
    assert_int_equal(agree, 0);
    assert_int_equal(swfs_sync_boundary_gap(tail, K, v, K, NV, 0, &g), SWFS_ERR_ARG);
    free(v);
    free(u);
}

/* The camera's orientation told by the speckles (swfs_orient_acc): frames |Psi + psi|^2 + noise
 * of independent speckles psi in the model's frame, seen by a camera transposed and mirrored in
 * x; the speckles' |psi|^2 against the camera's frames pick that pairing out of the 8, beyond
 * any other by many standard errors, whichever pairing the table had; frames not square leave
 * the swapped pairings out. */
static void test_orient_from_speckles(void **state)
{
    (void)state;
    enum { N = 32, NF = 200 };
    swfs_rng rng;
    swfs_rng_seed(&rng, 77);
    swfs_sync_result truth = {0}, ident = {0};
    truth.swap = 1; truth.sign_x = -1; truth.sign_y = 1;
    ident.sign_x = ident.sign_y = 1;
    swfs_orient_acc *a = NULL, *ar = NULL;
    assert_ok(swfs_orient_acc_new(N, N, &a));
    assert_ok(swfs_orient_acc_new(N, N / 2, &ar)); /* not square */
    static double model[N * N], cam[N * N], psi2[N * N];
    const long c = N / 2;
    for (int f = 0; f < NF; f++) {
        for (size_t j = 0; j < N; j++)
            for (size_t i = 0; i < N; i++) {
                const double r2 = (double)((long)i - c) * (double)((long)i - c) + (double)((long)j - c) * (double)((long)j - c);
                const double P = 3.0 * exp(-r2 / 8.0) + 0.3;  /* the static field, real */
                const double pr = swfs_rng_normal(&rng), pi = swfs_rng_normal(&rng);
                psi2[j * N + i] = pr * pr + pi * pi;
                model[j * N + i] = (P + pr) * (P + pr) + pi * pi + 0.5 * swfs_rng_normal(&rng);
            }
        /* the camera's pixel (c + a, c + b) shows model pixel (c + u, c + v): swfs_orient_frame's map */
        for (size_t k = 0; k < N * N; k++) cam[k] = NAN;
        for (long v = -c; v < c; v++)
            for (long u = -c; u < c; u++) {
                const long x = c + truth.sign_x * v, y = c + truth.sign_y * u; /* swapped */
                if (x >= 0 && y >= 0 && x < N && y < N) cam[y * N + x] = model[(c + v) * N + (c + u)];
            }
        swfs_orient_acc_add(a, cam, psi2);
        swfs_orient_acc_add(ar, model, psi2); /* the first N / 2 rows: a camera as the model */
    }
    swfs_orient_check_result r, ri, rr;
    assert_ok(swfs_orient_acc_result(a, &truth, 1.0, &r));
    assert_ok(swfs_orient_acc_result(a, &ident, 1.0, &ri));
    assert_ok(swfs_orient_acc_result(ar, &ident, 1.0, &rr));
    print_message("orientation from the speckles: %zu pixels, corr by pairing %.3f %.3f %.3f %.3f %.3f %.3f %.3f "
                  "%.3f; best %d, against the identity %.3f +- %.4f\n", ri.npix, ri.corr[0], ri.corr[1], ri.corr[2],
                  ri.corr[3], ri.corr[4], ri.corr[5], ri.corr[6], ri.corr[7], ri.best, ri.diff, ri.diff_se);
    assert_int_equal(r.best, 6); /* swap 1, sign_x -1, sign_y +1 */
    assert_int_equal(r.ref, 6);
    assert_float_equal(r.diff, 0.0, 0.0);
    assert_int_equal(ri.best, 6);
    assert_int_equal(ri.ref, 0);
    assert_true(ri.corr[6] > 0.3 && fabs(ri.corr[0]) < 0.05);
    assert_true(ri.diff > 10 * ri.diff_se);
    assert_int_equal(ri.nframes, NF);
    assert_int_equal(rr.best, 0);
    for (int k = 4; k < 8; k++) assert_true(isnan(rr.corr[k]));
    swfs_sync_result p;
    swfs_orient_pairing(6, &p);
    assert_true(p.swap == 1 && p.sign_x == -1 && p.sign_y == 1);
    /* too few frames: refused, nothing told */
    swfs_orient_acc *e = NULL;
    assert_ok(swfs_orient_acc_new(N, N, &e));
    swfs_orient_acc_add(e, cam, psi2);
    assert_int_equal(swfs_orient_acc_result(e, &ident, 1.0, &r), SWFS_ERR_VALUE);
    swfs_orient_acc_free(e);
    swfs_orient_acc_free(a);
    swfs_orient_acc_free(ar);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_fractional_weights),
        cmocka_unit_test(test_sync_recovers_ratio_and_lag),
        cmocka_unit_test(test_continuation),
        cmocka_unit_test(test_boundary),
        cmocka_unit_test(test_gap),
        cmocka_unit_test(test_orient_from_speckles),
        cmocka_unit_test(test_files_and_errors),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

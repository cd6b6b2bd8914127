/* The real-data path through the library alone (run.h, stream.h, pipeline.h; no
 * subprocess): a small time-series simulation -> swfs_reduce_run -> swfs_sync_run ->
 * swfs_speckles_run -> swfs_estimate_run -> the pupil step, asserting the recovered frame
 * ratio and lag and the NCP error; then the stream (file source + stream object) against
 * speckles + estimate, and the stream object fed in different batch sizes. */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/stream.h"
#include "specklewfs/timeseries.h"

#include <fitsio.h>
#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <dirent.h>
#include <sys/stat.h>
#include <unistd.h>

static char dir[1024];

static const char *p(const char *name)
{
    static char buf[64][1200]; /* a ring: the options below keep these pointers */
    static int k;
    k = (k + 1) % 64;
    snprintf(buf[k], sizeof buf[k], "%s/%s", dir, name);
    return buf[k];
}

/* The small system's parameters (3 cubes x 60 frames), the keys kv on top of its base. */
static void small_params(const char *const *kv, size_t nkv, swfs_ts_params *tp)
{
    swfs_config *c = swfs_config_new();
    const char *base[] = {"pupn=66", "pupdx=0.1", "screen_n=1024", "ncubes=3", "cube_frames=60", "cube_gap=150"};
    for (size_t i = 0; i < sizeof base / sizeof base[0]; i++) assert_ok(swfs_config_set(c, base[i]));
    for (size_t i = 0; i < nkv; i++) assert_ok(swfs_config_set(c, kv[i]));
    swfs_ts_params_default(tp);
    assert_ok(swfs_ts_params_from_config(c, tp));
    assert_ok(swfs_ts_params_check(tp));
    swfs_config_free(c);
}

static void run_small(const char *where, const swfs_ts_params *tp)
{
    mkdir(where, 0755);
    swfs_ts_summary sm;
    const char *prov[] = {"test_runs"};
    assert_ok(swfs_ts_run(tp, where, prov, 1, NULL, NULL, &sm));
}

/* A time series of the small system (3 cubes x 60 frames) into the folder `where`, the keys
 * kv on top of its base. */
static void simulate_small(const char *where, const char *const *kv, size_t nkv)
{
    swfs_ts_params tp;
    small_params(kv, nkv, &tp);
    run_small(where, &tp);
}

/* speckles on the test data (timing.txt, science.fits, actuators.fits) with the reconstructor
 * file `recon`, into `out`. */
static void given_recon_options(swfs_speckles_run_options *sp, const char *recon, const char *out)
{
    swfs_speckles_run_options_default(sp);
    sp->timing = p("timing.txt");
    sp->science = p("science.fits");
    sp->actuators = p("actuators.fits");
    sp->pipe.recon = SWFS_RECON_GIVEN;
    sp->recon = recon;
    sp->out = out;
}

/* The small system of tests/cli_telemetry.sh (3 cubes x 60 frames at 6.48 WFS frames per
 * camera frame, lag 3) simulated into the folder `where` with telemetry files of
 * `file_frames` WFS frames, then reduced to where/science.fits. */
static void make_data(const char *where, const char *file_frames, swfs_reduce_run_result *rr)
{
    const char *kv[] = {"layer_speed=30,40", "vib_amp=0.6", "jitter_amp=0.15", "seed=1", file_frames};
    simulate_small(where, kv, sizeof kv / sizeof kv[0]);

    char f[6][1300];
    const char *names[6] = {"raw_000.fits", "raw_001.fits", "raw_002.fits", "dark.fits", "flat.fits", "science.fits"};
    for (int k = 0; k < 6; k++) snprintf(f[k], sizeof f[k], "%s/%s", where, names[k]);
    swfs_reduce_run_options ro;
    swfs_reduce_run_options_default(&ro);
    const char *raw[] = {f[0], f[1], f[2]};
    ro.raw = raw;
    ro.nraw = 3;
    ro.dark = f[3];
    ro.flat = f[4];
    ro.out = f[5];
    assert_ok(swfs_reduce_run(&ro, rr));
}

/* Telemetry files of 1000 WFS frames: cube 1 crosses from the first into the second. */
static int setup(void **state)
{
    (void)state;
    snprintf(dir, sizeof dir, "%s", test_path("runs"));
    swfs_reduce_run_result rr;
    make_data(dir, "wfs_file_frames=1000", &rr);
    assert_int_equal(rr.nframes, 180);
    /* The simulated read noise is 19 counts. */
    assert_true(sqrt(rr.noise_var) > 18 && sqrt(rr.noise_var) < 20.5);
    return 0;
}

/* speckles (the default pipeline, the science cube matched to sci_out) then estimate: the
 * CLI's documented path through the library, on the timing table, science cube and actuators
 * given (NULL: those of dir). */
static void speckles_estimate_with(swfs_speckles_run_options *sp, const char *sci_out, const char *halo_out,
                                   swfs_speckles_run_result *spr, swfs_estimate_run_result *er)
{
    const char *min[] = {sp->science}, *mout[] = {sci_out};
    sp->match_in = min;
    sp->match_out = mout;
    sp->nmatch = 1;
    assert_ok(swfs_speckles_run(sp, spr));
    swfs_estimate_run_options eo;
    swfs_estimate_run_options_default(&eo);
    eo.science = sci_out;
    eo.speckles = sp->out;
    eo.out = halo_out;
    assert_ok(swfs_estimate_run(&eo, er));
}

static void speckles_estimate_on(const char *timing, const char *science, const char *actuators, const char *sp_out,
                                 const char *sci_out, const char *halo_out, const char *write_recon,
                                 swfs_speckles_run_result *spr, swfs_estimate_run_result *er)
{
    swfs_speckles_run_options sp;
    swfs_speckles_run_options_default(&sp);
    sp.timing = timing ? timing : p("timing.txt");
    sp.science = science ? science : p("science.fits");
    sp.actuators = actuators ? actuators : p("actuators.fits");
    sp.out = sp_out;
    sp.write_recon = write_recon;
    sp.pipe.recon = SWFS_RECON_VK; /* the run layer's behaviour, not the taught default's (cli_learn.sh) */
    speckles_estimate_with(&sp, sci_out, halo_out, spr, er);
}

static void speckles_estimate(const char *sp_out, const char *sci_out, const char *halo_out, const char *write_recon,
                              swfs_speckles_run_result *spr, swfs_estimate_run_result *er)
{
    speckles_estimate_on(NULL, NULL, NULL, sp_out, sci_out, halo_out, write_recon, spr, er);
}

static void test_sync_speckles_estimate(void **state)
{
    (void)state;
    swfs_sync_run_options so;
    swfs_sync_run_options_default(&so);
    so.science = p("science.fits");
    so.handshake = p("handshake.log");
    so.out = p("timing.txt");
    so.params.ratio_min = 5;
    so.params.ratio_max = 8;
    swfs_sync_run_result sr;
    assert_ok(swfs_sync_run(&so, &sr));
    assert_true(fabs(sr.t.ratio - 6.48) <= 0.03);
    assert_true(fabs(sr.t.lag - 3) <= 1);
    /* Cube 1 crosses from slopes_000 into slopes_001, which continue each other: its
       exposures in either file are used (rows 1 and 3), only the one across the boundary
       (row 2) is not. */
    assert_int_equal(sr.t.ncubes, 5);
    assert_int_equal(sr.nok, 4);
    assert_int_equal(sr.ncontinued, 1);
    assert_int_equal(sr.nexp, 180);
    assert_int_equal(sr.nexp_ok, 179);
    assert_int_equal(sr.t.cubes[2].status, SWFS_CUBE_STRADDLES);
    assert_int_equal(sr.t.cubes[2].nframes, 1);
    assert_true(sr.t.cubes[3].joined && fabs(sr.t.cubes[3].join_offset) < 0.5);
    assert_non_null(strstr(sr.t.cubes[3].slopes, "slopes_001.fits"));
    assert_string_equal(sr.t.cubes[3].camera, "raw_001.fits");
    assert_int_equal(sr.t.cubes[1].first + sr.t.cubes[1].nframes + 1, sr.t.cubes[3].first);
    /* The part in slopes_001 starts where the cube's exposures reach past slopes_000's 1000 frames. */
    const size_t j = sr.t.cubes[3].first - 60;
    assert_close(sr.t.cubes[3].start, sr.t.cubes[1].start + (double)j * sr.t.ratio - 1000, 1e-9);
    assert_int_equal(sr.t.cubes[3].join_lost, 0);
    /* the simulated files' FRAME0 (0, 1000) agree with the telemetry's verdict */
    assert_true(sr.t.cubes[3].join_verdict > 0 && sr.t.cubes[3].join_frame0);
    const swfs_timing_cube whole = sr.t.cubes[3];
    const double whole_ratio = sr.t.ratio;
    free(sr.t.cubes);

    /* WFS frames lost or repeated between slopes_000 and slopes_001: the files no longer
       continue each other, and the telemetry across the boundary says so. The camera finds the
       part k frames off; where the telemetry shows that count too, the part is placed there:
       the same frames of slopes_001 as with the whole file. One frame lost (slopes_000 cut by
       one) or one repeated (slopes_001's first frame appended to slopes_000): placed. Three
       lost: on this loop a step over four frames is not told from a long gap (the residual
       decorrelates within four frames at 30-40 m/s and 527 Hz), so the part stays out. */
    swfs_real *s0 = NULL, *s1 = NULL;
    assert_ok(swfs_fits_read_real(p("slopes_000.fits"), NULL, &s0, NULL));
    assert_ok(swfs_fits_read_real(p("slopes_001.fits"), NULL, &s1, NULL));
    mkdir(p("lost"), 0755);
    const long cases[3] = {1, -1, 3};
    for (int ic = 0; ic < 3; ic++) {
        const long lost = cases[ic];
        swfs_real *mod = swfs_real_alloc(s0->nx, s0->ny + 1, 1);
        assert_non_null(mod);
        memcpy(mod->data, s0->data, s0->nx * s0->ny * sizeof *mod->data);
        if (lost < 0) memcpy(mod->data + s0->nx * s0->ny, s1->data, s0->nx * sizeof *mod->data);
        mod->ny = lost < 0 ? s0->ny + 1 : s0->ny - (size_t)lost;
        unlink(p("lost/slopes_000.fits"));
        swfs_fits_out *fo = NULL;
        assert_ok(swfs_fits_out_create(&fo, p("lost/slopes_000.fits")));
        assert_ok(swfs_fits_out_real(fo, NULL, mod, -32));
        assert_ok(swfs_fits_out_commit(fo));
        /* the telemetry's own account of the boundary, on the edges sync reads */
        const size_t e = SWFS_SYNC_EDGE_FRAMES, nv = s0->nx;
        swfs_sync_boundary bd;
        swfs_sync_gap gp;
        assert_ok(swfs_sync_boundary_check(mod->data + (mod->ny - e) * nv, e, s1->data, e, nv, &bd));
        assert_ok(swfs_sync_boundary_gap(mod->data + (mod->ny - e) * nv, e, s1->data, e, nv, lost, &gp));
        swfs_real_free(mod);
        unlink(p("lost/slopes_001.fits"));
        unlink(p("lost/handshake.log"));
        assert_ok(symlink(p("slopes_001.fits"), p("lost/slopes_001.fits")));
        assert_ok(symlink(p("handshake.log"), p("lost/handshake.log")));
        so.handshake = p("lost/handshake.log");
        so.out = p("lost/timing.txt");
        assert_ok(swfs_sync_run(&so, &sr));
        const swfs_timing_cube *r3 = sr.t.ncubes > 3 ? &sr.t.cubes[3] : NULL;
        printf("test_runs: %ld frame%s %s between the files: telemetry verdict %d, that count %s (q %.3g among "
               "%.3g..%.3g, long-lag steps from %.3g); %zu of %zu exposures usable, %zu continued, %ld frames counted "
               "lost; the part starts at %.4f (%.4f with the whole file)\n", labs(lost), labs(lost) == 1 ? "" : "s",
               lost > 0 ? "lost" : "repeated", bd.verdict, gp.consistent ? "agrees" : "does not agree", gp.q, gp.qk_min,
               gp.qk_max, gp.qfar_min, sr.nexp_ok, sr.nexp, sr.ncontinued, r3 && r3->joined ? r3->join_lost : 0,
               r3 && r3->joined ? r3->start : NAN, whole.start);
        assert_int_equal(bd.verdict, -1);
        if (lost != 3) {
            assert_true(gp.consistent);
            assert_int_equal(sr.ncontinued, 1);
            assert_int_equal(sr.nexp_ok, 179);
            assert_true(r3->joined && r3->join_verdict == -1);
            assert_int_equal(r3->join_lost, lost);
            assert_int_equal(r3->first, whole.first);
            assert_int_equal(r3->nframes, whole.nframes);
            /* placed where the whole file puts it, to the ratio's uncertainty over the exposures */
            assert_true(fabs(r3->start - whole.start) < 0.1);
            assert_true(fabs(sr.t.ratio - whole_ratio) < 0.002);
        } else {
            assert_false(gp.separable);
            assert_false(gp.consistent);
            assert_int_equal(sr.ncontinued, 0);
            assert_int_equal(sr.nok, 3);
            assert_true(sr.nexp_ok < 160 && sr.nexp_ok > 120);
            for (size_t k = 0; k < sr.t.ncubes; k++) assert_false(sr.t.cubes[k].joined);
        }
        free(sr.t.cubes);
    }
    /* A count the telemetry does not show is refused: one repeated where one was lost. */
    swfs_sync_gap gp;
    assert_ok(swfs_sync_boundary_gap(s0->data + (s0->ny - 1 - SWFS_SYNC_EDGE_FRAMES) * s0->nx, SWFS_SYNC_EDGE_FRAMES,
                                     s1->data, SWFS_SYNC_EDGE_FRAMES, s0->nx, -1, &gp));
    assert_false(gp.consistent); /* one lost is not one repeated */

    /* The files' own frame counters (FRAME0, which simulate writes: 0 and 1000 here). Three
       frames cut from slopes_000's end, FRAME0 kept in both: the counters say three lost, which
       the telemetry does not contradict (not continuous) and could not count itself (above),
       so the part is placed by them where the whole file puts it. One frame cut from the end
       of slopes_000 and slopes_001's FRAME0 written as 999 (counters that lie): they say
       contiguous, the telemetry not continuous, and the data decide as without counters (the
       camera's count of 1, shown by the telemetry). */
    for (int ic = 0; ic < 2; ic++) {
        const size_t cut = ic == 0 ? 3 : 1;
        swfs_real *a = swfs_real_alloc(s0->nx, s0->ny - cut, 1);
        swfs_real *b = swfs_real_alloc(s1->nx, s1->ny, 1);
        assert_true(a && b);
        memcpy(a->data, s0->data, a->nx * a->ny * sizeof *a->data);
        memcpy(b->data, s1->data, b->nx * b->ny * sizeof *b->data);
        const swfs_real *ab[2] = {a, b};
        const char *names[2] = {"lost/slopes_000.fits", "lost/slopes_001.fits"};
        for (int k = 0; k < 2; k++) {
            unlink(p(names[k]));
            swfs_fits_out *fo = NULL;
            assert_ok(swfs_fits_out_create(&fo, p(names[k])));
            assert_ok(swfs_fits_out_real(fo, NULL, ab[k], -32));
            assert_ok(swfs_fits_out_key_long(fo, "FRAME0", k ? (ic ? 999 : 1000) : 0, "global WFS frame of row 0"));
            assert_ok(swfs_fits_out_commit(fo));
        }
        swfs_real_free(a);
        swfs_real_free(b);
        assert_ok(swfs_sync_run(&so, &sr));
        const swfs_timing_cube *r3 = sr.t.ncubes > 3 ? &sr.t.cubes[3] : NULL;
        char how[160] = "";
        if (r3 && r3->joined) swfs_timing_join_verdict(r3, how, sizeof how);
        printf("test_runs: %zu frame%s cut from slopes_000's end, FRAME0 %s: %zu of %zu exposures usable; the part "
               "starts at %.4f (%.4f with the whole files), the boundary %s\n", cut, cut == 1 ? "" : "s",
               ic ? "saying contiguous" : "kept", sr.nexp_ok, sr.nexp, r3 ? r3->start : NAN, whole.start, how);
        assert_int_equal(sr.ncontinued, 1);
        assert_int_equal(sr.nexp_ok, 179);
        assert_true(r3->joined && r3->join_verdict == -1);
        assert_int_equal(r3->first, whole.first);
        assert_int_equal(r3->nframes, whole.nframes);
        if (ic == 0) {
            assert_true(r3->join_frame0);
            assert_int_equal(r3->join_lost, 3);
            assert_true(fabs(r3->start - whole.start) < 0.1);
            assert_non_null(strstr(how, "3 WFS frames lost there by the files' FRAME0"));
        } else {
            assert_false(r3->join_frame0);
            assert_int_equal(r3->join_lost, 1);
            assert_true(fabs(r3->start - whole.start) < 0.1);
            assert_non_null(strstr(how, "(the camera's count)"));
        }
        free(sr.t.cubes);
    }
    swfs_real_free(s0);
    swfs_real_free(s1);

    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate(p("speckles.fits"), p("sci_m.fits"), p("halo.fits"), NULL, &spr, &er);
    assert_int_equal(spr.nout, 179);
    assert_int_equal(spr.nok, 4);
    assert_true(spr.info.ntrain > 0 && spr.info.noise_var > 0);
    assert_int_equal(er.halo->frames, 179);

    /* NCP error against the injected map (piston, tip, tilt removed): < 50 nm, as the CLI test. */
    swfs_real *ncp = NULL;
    swfs_geom g;
    assert_ok(swfs_fits_read_real(p("truth.fits"), "NCP", &ncp, &g));
    swfs_pupil_options po;
    swfs_pupil_options_default(&po);
    po.method = SWFS_PUPIL_MOMENTS;
    po.source = SWFS_SOURCE_HALO;
    swfs_pupil_result *pr = NULL, *pf = NULL;
    assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, &po, &pr));
    double err = NAN, errf = NAN;
    assert_ok(swfs_wfe_compare(pr->wfe->data, ncp->data, pr->mask->data, ncp->nx, &err, NULL, NULL));
    /* The default pupil step: the joint fit of the regression statistics the estimate kept. */
    assert_non_null(er.halo->reg);
    assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, NULL, &pf));
    assert_int_equal(pf->method, SWFS_PUPIL_FIT);
    assert_ok(swfs_wfe_compare(pf->wfe->data, ncp->data, pf->mask->data, ncp->nx, &errf, NULL, NULL));
    printf("test_runs: ratio, lag ok; NCP error %.1f nm (moments, HALO), %.1f nm (joint fit)\n", 1e9 * err, 1e9 * errf);
    assert_true(err > 0 && err < 50e-9);
    assert_true(errf > 0 && errf < 35e-9 && errf < err); /* 25.5 vs 41.8 nm */
    swfs_pupil_result_free(pr);
    swfs_pupil_result_free(pf);
    swfs_real_free(ncp);
    swfs_halo_free(er.halo);

    /* Bad input: a reconstructor whose length does not match the slopes. */
    swfs_speckles_run_options sp;
    given_recon_options(&sp, p("actuators.fits"), p("x.fits"));
    assert_int_not_equal(swfs_speckles_run(&sp, &spr), 0);
    printf("test_runs: bad reconstructor: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "expects"));
    assert_false(test_file_exists(p("x.fits")));
}

/* stream on the test data (timing.txt, science.fits, actuators.fits) with the reconstructor
 * file `recon`, into `out`. */
static void stream_file_options(swfs_stream_run_options *so, const char *recon, const char *out)
{
    swfs_stream_run_options_default(so);
    so->timing = p("timing.txt");
    so->science = p("science.fits");
    so->recon = recon;
    so->actuators = p("actuators.fits");
    so->out = out;
}

/* The stream's halo file against speckles + estimate's halo: max |dPsi| / the peak of ref
 * (pixels finite in both). *out: the stream's halo (caller frees). */
static double stream_halo_diff(const char *path, const swfs_halo *ref, swfs_halo **out)
{
    assert_ok(swfs_halo_read(path, out, NULL));
    const swfs_halo *hs = *out;
    double peak = 0, d = 0;
    for (size_t k = 0; k < hs->halo->nx * hs->halo->ny; k++) {
        peak = fmax(peak, cabs(ref->halo->data[k]));
        if (isfinite(creal(hs->halo->data[k])) && isfinite(creal(ref->halo->data[k])))
            d = fmax(d, cabs(hs->halo->data[k] - ref->halo->data[k]));
    }
    return d / peak;
}

/* stream (file source -> pipeline -> stream) = speckles + estimate with the same reconstructor. */
static void test_stream_equals_speckles(void **state)
{
    (void)state;
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate(p("speckles_s.fits"), p("sci_s.fits"), p("halo_s.fits"), p("recon.fits"), &spr, &er);

    swfs_stream_run_options so;
    stream_file_options(&so, p("recon.fits"), p("halo_stream.fits"));
    so.batch = 17;
    so.stream.static_mode = SWFS_STATIC_NONE; /* the data-set mean is removed exactly either way */
    swfs_stream_run_result sr;
    assert_ok(swfs_stream_run_files(&so, &sr));
    assert_int_equal(sr.camera_frames, 179);
    swfs_halo *hs = NULL;
    const double d = stream_halo_diff(p("halo_stream.fits"), er.halo, &hs);
    printf("test_runs: stream vs speckles + estimate: max |dPsi| / peak = %.2g\n", d);
    /* The speckle cube is stored in single precision; the stream keeps double. */
    assert_true(d < 1e-4);
    /* The regression statistics travel with both halos, and the joint fit agrees. */
    assert_true(hs->reg && er.halo->reg);
    assert_int_equal(hs->reg->frames, er.halo->reg->frames);
    swfs_pupil_result *p1 = NULL, *p2 = NULL;
    assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, NULL, &p1));
    assert_ok(swfs_pupil_estimate(hs, &er.geom, NULL, NULL, &p2));
    double dw = 0;
    for (size_t q = 0; q < p1->wfe->nx * p1->wfe->ny; q++) dw = fmax(dw, fabs(p1->wfe->data[q] - p2->wfe->data[q]));
    printf("test_runs: stream vs speckles + estimate, joint fit: max |dWFE| = %.2g nm (WFE %.1f nm rms)\n", dw * 1e9,
           p1->wfe_rms * 1e9);
    assert_true(dw < 1e-3 * p1->wfe_rms + 1e-12);
    swfs_pupil_result_free(p1);
    swfs_pupil_result_free(p2);
    swfs_halo_free(hs);
    swfs_halo_free(er.halo);
}

/* The stream object alone: the accumulators do not depend on how the source cuts batches. */
static void test_stream_batches(void **state)
{
    (void)state;
    swfs_accum *acc[2] = {NULL, NULL};
    const size_t batches[2] = {7, 64};
    for (int t = 0; t < 2; t++) {
        swfs_file_source *src = NULL;
        swfs_recon *rec = NULL;
        double *xy = NULL;
        size_t nact = 0;
        swfs_geom g;
        assert_ok(swfs_recon_read(p("recon.fits"), &rec));
        assert_ok(swfs_actuators_read(p("actuators.fits"), &xy, &nact));
        swfs_real *one = NULL;
        assert_ok(swfs_fits_read_real(p("science.fits"), NULL, &one, &g));
        swfs_pipeline_options po;
        swfs_pipeline_options_default(&po);
        po.recon = SWFS_RECON_GIVEN;
        swfs_pipeline *pl = NULL;
        assert_ok(swfs_pipeline_create(&pl, &g, one->nx, one->ny, xy, nact, NULL, rec->nslopes, rec, NULL, 0, &po));
        assert_ok(swfs_file_source_open(&src, p("timing.txt"), p("science.fits"), NULL, rec->nslopes, batches[t]));
        swfs_stream_options so;
        swfs_stream_options_default(&so);
        so.static_mode = SWFS_STATIC_NONE;
        swfs_stream *s = NULL;
        assert_ok(swfs_stream_create(&s, pl, &so));
        assert_ok(swfs_stream_run(s, swfs_file_source_next, src, NULL, NULL));
        assert_int_equal(swfs_stream_camera_frames(s), 179);
        acc[t] = swfs_accum_create(one->nx, one->ny);
        assert_ok(swfs_accum_merge(acc[t], swfs_stream_accum(s)));
        swfs_stream_free(s);
        swfs_file_source_close(src);
        swfs_pipeline_free(pl);
        swfs_real_free(one);
        swfs_recon_free(rec);
        free(xy);
    }
    /* Every statistic, to rounding (the automatic static halo would take its scale from
     * the first batch: a constant offset of psi, which the estimate removes exactly but
     * the raw co-moments of |psi|^2 do not). */
    /* Relative to each field's peak: the engine is single precision (engine.h: ~1e-6 of the
     * peak), and a batch size re-slices the frames one GEMM reconstructs, so a co-moment that
     * nearly cancels in one pixel differs by rounding relative to itself (measured 1.4 on this
     * machine class), not relative to its field: co-moments are products of psi, measured
     * 2.3e-6 of the peak, so 1e-5 is the engine's precision with a margin. */
    const size_t np = acc[0]->nx * acc[0]->ny;
    double worst = 0;
    for (int f = SWFS_ACC_MI; f < SWFS_ACC_NFIELDS; f++) {
        double peak = 0;
        for (size_t k = 0; k < np; k++) peak = fmax(peak, fmax(fabs(acc[0]->f[f][k]), fabs(acc[1]->f[f][k])));
        for (size_t k = 0; peak > 0 && k < np; k++)
            worst = fmax(worst, fabs(acc[0]->f[f][k] - acc[1]->f[f][k]) / peak);
    }
    printf("test_runs: batch 7 vs 64: worst co-moment difference %.2g of its field's peak\n", worst);
    assert_true(worst < 1e-5);
    swfs_accum_free(acc[0]);
    swfs_accum_free(acc[1]);
}

/* speckles on the shared data set with default options but the von Karman map. */
static void speckles_opts(swfs_speckles_run_options *sp, const char *actuators, const char *out)
{
    swfs_speckles_run_options_default(sp);
    sp->timing = p("timing.txt");
    sp->science = p("science.fits");
    sp->actuators = actuators;
    sp->out = out;
    sp->pipe.recon = SWFS_RECON_VK; /* the run layer's behaviour, not the taught default's (cli_learn.sh) */
    remove(out);
}

/* A run that must fail: its message holds `pattern`, and it left no output. */
static void assert_refused(int rc, const char *what, const char *pattern, const char *out)
{
    printf("test_runs: %s: %s\n", what, swfs_last_error());
    assert_int_not_equal(rc, 0);
    assert_non_null(strstr(swfs_last_error(), pattern));
    assert_false(test_file_exists(out));
}

/* The AO system's own reconstructor given to speckles: the simulated loop's (recon_ao.fits,
 * z [m of wavefront] = W s) has a gain near 1 on the model's interaction matrix and is used;
 * the same matrix in the DM-command convention (-1/2 W: a correction of the surface) is
 * refused with the scale that would fix it, and works with that scale. */
static void test_given_reconstructor(void **state)
{
    (void)state;
    swfs_recon *r = NULL;
    assert_ok(swfs_recon_read(p("recon_ao.fits"), &r));
    for (size_t i = 0; i < r->nact * r->nslopes; i++) r->W[i] *= -0.5;
    assert_ok(swfs_recon_write(r, p("recon_dm.fits")));
    swfs_recon_free(r);
    const char *files[3] = {"recon_ao.fits", "recon_dm.fits", "recon_dm.fits"};
    const double scale[3] = {1.0, 1.0, -2.0};
    for (int k = 0; k < 3; k++) {
        swfs_speckles_run_options sp;
        speckles_opts(&sp, p("actuators.fits"), p("speckles_given.fits"));
        sp.pipe.recon = SWFS_RECON_GIVEN;
        sp.recon = p(files[k]);
        sp.pipe.recon_scale = scale[k];
        swfs_speckles_run_result spr;
        const int rc = swfs_speckles_run(&sp, &spr);
        if (k == 1) {
            assert_refused(rc, "DM-command convention", "gain -0.5", sp.out);
            assert_non_null(strstr(swfs_last_error(), "a scale of -2 "));
            continue;
        }
        assert_ok(rc);
        printf("test_runs: given reconstructor %s x %g: gain %.3f\n", files[k], scale[k], spr.info.recon_gain);
        assert_true(spr.info.recon_gain > 0.9 && spr.info.recon_gain < 1.1);
    }
}

/* A zonal loop (ao_rcond): its reconstructor, written as recon_ao.fits, is a truncated
 * pseudo-inverse: W's singular values are 1 / s_i of the interaction matrix's kept modes, so
 * their spread is at most 1 / ao_rcond and, the cut falling between two of D's, close to it;
 * it keeps more modes than the default filter (56) and fewer than the actuators; the loop
 * closes (tip-tilt held as the modal loop holds it). ao_rcond with ao_recon, or >= 1, is
 * refused. */
static void test_zonal_loop(void **state)
{
    (void)state;
    const char *kv[] = {"ao_rcond=0.05"};
    swfs_ts_params tp;
    small_params(kv, 1, &tp);
    swfs_ts_summary zs, ms;
    const char *prov[] = {"test_runs"};
    mkdir(p("zonal"), 0755);
    assert_ok(swfs_ts_run(&tp, p("zonal"), prov, 1, NULL, NULL, &zs));
    small_params(NULL, 0, &tp);
    tp.ncubes = 1; /* the modal loop's tip-tilt only */
    mkdir(p("modal_tt"), 0755);
    assert_ok(swfs_ts_run(&tp, p("modal_tt"), prov, 1, NULL, NULL, &ms));
    swfs_recon *r = NULL;
    assert_ok(swfs_recon_read(p("zonal/recon_ao.fits"), &r));
    const size_t k = r->nact < r->nslopes ? r->nact : r->nslopes;
    double *sv = malloc(k * sizeof *sv);
    assert_non_null(sv);
    assert_int_equal(LAPACKE_dgesdd(LAPACK_ROW_MAJOR, 'N', (lapack_int)r->nact, (lapack_int)r->nslopes, r->W,
                                    (lapack_int)r->nslopes, sv, NULL, (lapack_int)k, NULL, (lapack_int)r->nslopes), 0);
    size_t rank = 0;
    while (rank < k && sv[rank] > 1e-9 * sv[0]) rank++;
    const double spread = sv[0] / sv[rank - 1];
    printf("test_runs: zonal loop: %zu modes of %zu actuators (reported %zu), spread of W's singular values %.2f; "
           "tip-tilt %.3f lambda/D (modal loop %.3f), residual %.1f nm without tip-tilt\n", rank, r->nact,
           zs.ao_modes, spread, zs.tt_rms, ms.tt_rms, zs.residual_rms_nott * 1e9);
    assert_int_equal(rank, zs.ao_modes);
    assert_true(rank > 56 && rank < r->nact - 1);
    assert_true(spread <= 1 / 0.05 * (1 + 1e-9) && spread > 0.8 / 0.05);
    assert_true(zs.tt_rms < 1.3 * ms.tt_rms);
    free(sv);
    swfs_recon_free(r);
    small_params(kv, 1, &tp);
    snprintf(tp.ao_recon, sizeof tp.ao_recon, "%s", p("zonal/recon_ao.fits"));
    assert_refused(swfs_ts_params_check(&tp), "ao_rcond and ao_recon", "ao_rcond=0.05 and ao_recon=", p("zonal/none"));
    small_params(NULL, 0, &tp);
    tp.ao_rcond = 1;
    assert_refused(swfs_ts_params_check(&tp), "ao_rcond 1", "ao_rcond=1: must be in [0, 1)", p("zonal/none"));
}

/* A DM of Gaussian influence functions (dm_coupling, interp.h swfs_influence_gauss_grid): the
 * loop closes on it as on the interpolated surface (its tip-tilt as well held, its residual
 * within 1.6x), the key reaches the loop (another residual, other slopes), out of range is
 * refused. */
static void test_gauss_dm_loop(void **state)
{
    (void)state;
    swfs_ts_params tp;
    swfs_ts_summary gs, cs;
    const char *prov[] = {"test_runs"};
    const char *kv[] = {"dm_coupling=0.15"};
    small_params(kv, 1, &tp);
    tp.ncubes = 1;
    mkdir(p("gauss_dm"), 0755);
    assert_ok(swfs_ts_run(&tp, p("gauss_dm"), prov, 1, NULL, NULL, &gs));
    small_params(NULL, 0, &tp);
    tp.ncubes = 1;
    mkdir(p("ct_dm"), 0755);
    assert_ok(swfs_ts_run(&tp, p("ct_dm"), prov, 1, NULL, NULL, &cs));
    printf("test_runs: Gaussian DM (coupling 0.15): residual %.1f nm without tip-tilt, tip-tilt %.3f lambda/D; "
           "interpolated surface %.1f nm, %.3f\n", gs.residual_rms_nott * 1e9, gs.tt_rms, cs.residual_rms_nott * 1e9,
           cs.tt_rms);
    assert_true(gs.residual_rms_nott < 1.6 * cs.residual_rms_nott && gs.residual_rms_nott > 0.8 * cs.residual_rms_nott);
    assert_true(fabs(gs.residual_rms_nott / cs.residual_rms_nott - 1) > 1e-3);
    assert_true(gs.tt_rms < 1.2 * cs.tt_rms);
    swfs_real *a = NULL, *b = NULL;
    assert_ok(swfs_telemetry_read(p("gauss_dm/slopes_000.fits"), 0, &a, NULL));
    assert_ok(swfs_telemetry_read(p("ct_dm/slopes_000.fits"), 0, &b, NULL));
    assert_int_equal(a->nx * a->ny, b->nx * b->ny);
    double d = 0, s = 0;
    for (size_t k = 0; k < a->nx * a->ny; k++) {
        d += (a->data[k] - b->data[k]) * (a->data[k] - b->data[k]);
        s += b->data[k] * b->data[k];
    }
    assert_true(d > 0.01 * s);
    swfs_real_free(a);
    swfs_real_free(b);
    /* the DM's functions from each loop's own control matrix (recon_ao.fits), the files
     * describing the system otherwise (ts_coupling.c): the Gaussian coupling to 1 % and the
     * interpolated surface told apart both ways */
    swfs_ts_coupling cc;
    small_params(NULL, 0, &tp);
    snprintf(tp.ao_recon, sizeof tp.ao_recon, "%s", p("gauss_dm/recon_ao.fits"));
    assert_ok(swfs_ts_coupling_from_recon(&tp, &cc));
    printf("test_runs: the Gaussian DM's control matrix (rank %zu): coupling %.4f, misfit %.2e; the interpolated "
           "surface %.3f\n", cc.rank, cc.coupling, cc.misfit, cc.misfit_interp);
    assert_true(cc.gaussian && fabs(cc.coupling - 0.15) < 0.0015 && cc.misfit < 1e-3 && cc.misfit_interp > 0.05);
    snprintf(tp.ao_recon, sizeof tp.ao_recon, "%s", p("ct_dm/recon_ao.fits"));
    assert_ok(swfs_ts_coupling_from_recon(&tp, &cc));
    printf("test_runs: the interpolated DM's control matrix (rank %zu): the surface's misfit %.2e; coupling %.4f "
           "%.3f\n", cc.rank, cc.misfit_interp, cc.coupling, cc.misfit);
    assert_true(!cc.gaussian && cc.misfit_interp < 1e-3 && cc.misfit > 0.05);
    small_params(NULL, 0, &tp);
    tp.dm_coupling = 1;
    assert_refused(swfs_ts_params_check(&tp), "dm_coupling 1", "dm_coupling=1: must be in [0, 1)", p("gauss_dm/none"));
}

/* Actuators that do not cover the pupil rim: the outer ring of the simulated DM left out of
 * the actuator file given to speckles (a rim gap of ~0.1 m, a quarter of the pitch) is
 * extrapolated and the NCP comes out close to the full layout's; two rings left out (a gap
 * beyond one pitch) are refused, naming the coverage. */
static void test_rim_coverage(void **state)
{
    (void)state;
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_read(p("actuators.fits"), &xy, &nact));
    double rmax = 0;
    for (size_t a = 0; a < nact; a++) rmax = fmax(rmax, hypot(xy[2 * a], xy[2 * a + 1]));
    double err[2] = {0, 0};
    const double cut[3] = {INFINITY, rmax - 0.2, rmax - 0.65};
    for (int k = 0; k < 3; k++) {
        size_t n = 0;
        double *keep = malloc(2 * nact * sizeof *keep);
        for (size_t a = 0; a < nact; a++)
            if (hypot(xy[2 * a], xy[2 * a + 1]) < cut[k]) { keep[2 * n] = xy[2 * a]; keep[2 * n + 1] = xy[2 * a + 1]; n++; }
        assert_ok(swfs_actuators_write(keep, n, p("act_cut.fits")));
        free(keep);
        swfs_speckles_run_options sp;
        speckles_opts(&sp, p("act_cut.fits"), p("speckles_cut.fits"));
        const char *min[] = {p("science.fits")}, *mout[] = {p("sci_cut.fits")};
        sp.match_in = min;
        sp.match_out = mout;
        sp.nmatch = 1;
        swfs_speckles_run_result spr;
        const int rc = swfs_speckles_run(&sp, &spr);
        if (k == 2) {
            assert_refused(rc, "two rings left out", "do not cover the pupil", sp.out);
            break;
        }
        assert_ok(rc);
        swfs_estimate_run_options eo;
        swfs_estimate_run_options_default(&eo);
        eo.science = p("sci_cut.fits");
        eo.speckles = sp.out;
        eo.out = p("halo_cut.fits");
        swfs_estimate_run_result er;
        assert_ok(swfs_estimate_run(&eo, &er));
        swfs_real *ncp = NULL;
        assert_ok(swfs_fits_read_real(p("truth.fits"), "NCP", &ncp, NULL));
        swfs_pupil_result *pf = NULL;
        assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, NULL, &pf));
        assert_ok(swfs_wfe_compare(pf->wfe->data, ncp->data, pf->mask->data, ncp->nx, &err[k], NULL, NULL));
        printf("test_runs: %zu actuators (%zu pupil samples outside their hull, extrapolated): NCP error %.1f nm\n", n,
               spr.info.n_outside, err[k] * 1e9);
        if (k == 0) assert_int_equal(spr.info.n_outside, 0);
        else assert_true(spr.info.n_outside > 0);
        swfs_pupil_result_free(pf);
        swfs_real_free(ncp);
        swfs_halo_free(er.halo);
    }
    assert_true(err[1] < 1.25 * err[0]);
    free(xy);
}

/* The small system simulated and reduced into dir/<name> with telemetry files of
 * `file_frames` (make_data), and sync's options for it (paths kept in the caller's buffers). */
typedef struct sync_case {
    char sub[1200], sci[1300], hs[1300], tim[1300];
    swfs_sync_run_options so;
} sync_case;

static void sync_case_make(sync_case *c, const char *name, const char *file_frames)
{
    snprintf(c->sub, sizeof c->sub, "%s/%s", dir, name);
    swfs_reduce_run_result rr;
    make_data(c->sub, file_frames, &rr);
    snprintf(c->sci, sizeof c->sci, "%s/science.fits", c->sub);
    snprintf(c->hs, sizeof c->hs, "%s/handshake.log", c->sub);
    snprintf(c->tim, sizeof c->tim, "%s/timing.txt", c->sub);
    swfs_sync_run_options_default(&c->so);
    c->so.science = c->sci;
    c->so.handshake = c->hs;
    c->so.out = c->tim;
    c->so.params.ratio_min = 5;
    c->so.params.ratio_max = 8;
}

/* A cube that starts less than one exposure before the end of its telemetry file: no whole
 * exposure lies in the file the handshake log names, and all but the one across the boundary
 * lie in the next file, which continues it. */
static void test_sync_cube_at_file_end(void **state)
{
    (void)state;
    /* files of 843 WFS frames: cube 1 starts at WFS frame 839.2 (logged 842) */
    sync_case c;
    sync_case_make(&c, "edge", "wfs_file_frames=843");
    swfs_sync_run_result sr;
    assert_ok(swfs_sync_run(&c.so, &sr));
    size_t in_own = 0, in_next = 0;
    for (size_t k = 0; k < sr.t.ncubes; k++) {
        const swfs_timing_cube *row = &sr.t.cubes[k];
        if (strcmp(row->camera, "raw_001.fits") || row->status != SWFS_CUBE_OK) continue;
        if (strstr(row->slopes, "slopes_001.fits")) in_next += row->nframes, assert_true(row->joined);
        else in_own += row->nframes;
    }
    printf("test_runs: a cube starting %.2f WFS frames before its file's end: %zu exposures in that file, %zu in "
           "the next\n", 843 - (sr.t.cubes[1].start), in_own, in_next);
    assert_int_equal(in_own, 0);
    assert_int_equal(in_next, 59);
    free(sr.t.cubes);
}

/* The rows sync makes of camera cube `cam` (its exposures used, and whether a row joined the
 * file `joined_in`). */
static size_t used_rows(const swfs_timing *t, const char *cam, const char *joined_in, int *joined)
{
    size_t used = 0;
    *joined = 0;
    for (size_t k = 0; k < t->ncubes; k++) {
        const swfs_timing_cube *row = &t->cubes[k];
        if (strcmp(row->camera, cam) || row->status != SWFS_CUBE_OK) continue;
        used += row->nframes;
        if (row->joined && strstr(row->slopes, joined_in)) *joined = 1;
    }
    return used;
}

/* A telemetry file the handshake log names that cannot be read (cut short, then gone): sync
 * leaves the cubes that start in it out, as rows marked missing, fits the timing on the
 * others and writes the table, which reads back with those rows; speckles skips them. With no
 * readable file at all it stops with the first file's message and writes no table. */
static void test_sync_unreadable_file(void **state)
{
    (void)state;
    sync_case c;
    sync_case_make(&c, "unreadable", "wfs_file_frames=1000");
    swfs_sync_run_result a, b;
    assert_ok(swfs_sync_run(&c.so, &a));
    /* the file cube 2 starts in (its first row in the table: the own file's) */
    char own[SWFS_SYNC_NAME] = "";
    for (size_t k = 0; k < a.t.ncubes && !own[0]; k++)
        if (!strcmp(a.t.cubes[k].camera, "raw_002.fits")) snprintf(own, sizeof own, "%s", a.t.cubes[k].slopes);
    assert_true(own[0] != 0);
    char keep[SWFS_SYNC_NAME + 8];
    snprintf(keep, sizeof keep, "%s.keep", own);
    assert_int_equal(rename(own, keep), 0);
    FILE *in = fopen(keep, "rb"), *out = fopen(own, "wb");
    assert_non_null(in);
    assert_non_null(out);
    char buf[4000];
    assert_int_equal(fread(buf, 1, sizeof buf, in), sizeof buf);
    fwrite(buf, 1, sizeof buf, out); /* the header and a little of the data */
    fclose(in);
    fclose(out);
    assert_ok(swfs_sync_run(&c.so, &b));
    printf("test_runs: cube 2's telemetry file cut short: %zu of %zu exposures usable (%zu with it), ratio %.4f "
           "(%.4f), %zu cube left out: %s\n", b.nexp_ok, b.nexp, a.nexp_ok, b.t.ratio, a.t.ratio, b.nmissing,
           b.missing_reason);
    assert_int_equal(b.nmissing, 1);
    assert_int_equal(b.nexp_missing, 60);
    assert_non_null(strstr(b.missing_reason, strrchr(own, '/') + 1));
    assert_int_equal(b.nexp, a.nexp);
    int dummy;
    assert_int_equal(used_rows(&b.t, "raw_002.fits", "", &dummy), 0);
    for (int k = 0; k < 2; k++) { /* the other cubes as before, unless they ran into that file */
        char cam[32];
        snprintf(cam, sizeof cam, "raw_%03d.fits", k);
        const size_t ua = used_rows(&a.t, cam, "", &dummy), ub = used_rows(&b.t, cam, "", &dummy);
        assert_true(ub <= ua && ub > 0);
    }
    assert_true(fabs(b.t.ratio - 6.48) < 0.01);
    swfs_timing *rt = NULL;
    assert_ok(swfs_timing_read(c.tim, &rt));
    size_t nmiss = 0;
    for (size_t k = 0; k < rt->ncubes; k++)
        if (rt->cubes[k].status == SWFS_CUBE_MISSING) {
            nmiss++;
            assert_string_equal(rt->cubes[k].camera, "raw_002.fits");
            assert_int_equal(rt->cubes[k].nframes, 60);
        }
    assert_int_equal(nmiss, 1);
    swfs_timing_free(rt);
    /* speckles on that table: the usable rows' frames only */
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    char spo[1300], scm[1300], hal[1300];
    snprintf(spo, sizeof spo, "%s/speckles.fits", c.sub);
    snprintf(scm, sizeof scm, "%s/sci_m.fits", c.sub);
    snprintf(hal, sizeof hal, "%s/halo.fits", c.sub);
    char act[1300];
    snprintf(act, sizeof act, "%s/actuators.fits", c.sub);
    speckles_estimate_on(c.tim, c.sci, act, spo, scm, hal, NULL, &spr, &er);
    assert_int_equal(spr.nout, b.nexp_ok);
    swfs_halo_free(er.halo);
    /* no readable file: an error naming the first, and no table */
    unlink(own);
    for (int k = 0; k < 8; k++) {
        char f[1400];
        snprintf(f, sizeof f, "%s/slopes_%03d.fits", c.sub, k);
        unlink(f);
    }
    unlink(c.tim);
    swfs_sync_run_result z;
    assert_int_equal(swfs_sync_run(&c.so, &z), SWFS_ERR_IO);
    printf("test_runs: no telemetry file: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "no telemetry file of the 3 cubes can be read"));
    assert_false(test_file_exists(c.tim));
    free(z.t.cubes);
    free(a.t.cubes);
    free(b.t.cubes);
}

/* Time-stamped telemetry files (names that differ in digits only, not consecutive numbers):
 * cube 0 runs from the first file into the second, in which no cube starts (the handshake log
 * does not name it); sync finds it among the folder's files named like the first, and the
 * table is the numbered files' table. */
static void test_sync_timestamped_files(void **state)
{
    (void)state;
    sync_case c;
    sync_case_make(&c, "stamps", "wfs_file_frames=400");
    const char *sub = c.sub, *hs = c.hs;
    swfs_sync_run_result a, b;
    assert_ok(swfs_sync_run(&c.so, &a));
    int ja, jb;
    const size_t ua = used_rows(&a.t, "raw_000.fits", "slopes_001.fits", &ja);
    assert_true(ja); /* the numbered neighbour */
    /* the same files renamed by time stamps (slopes_k -> ..._0100SS with irregular seconds) */
    const int sec[8] = {0, 7, 13, 21, 34, 40, 52, 59};
    char from[1400], to[1900], stamp[8][64];
    size_t nf = 0;
    for (; nf < 8; nf++) {
        snprintf(from, sizeof from, "%s/slopes_%03zu.fits", sub, nf);
        snprintf(stamp[nf], sizeof stamp[nf], "slopes_20261126T0100%02d.fits", sec[nf]);
        snprintf(to, sizeof to, "%s/%s", sub, stamp[nf]);
        if (rename(from, to)) break;
    }
    assert_true(nf >= 3);
    FILE *in = fopen(hs, "r");
    snprintf(to, sizeof to, "%s/handshake_stamps.log", sub);
    FILE *out = fopen(to, "w");
    assert_non_null(in);
    assert_non_null(out);
    char line[2048];
    int names_second = 0;
    while (fgets(line, sizeof line, in)) {
        char cam[256], sl[256];
        long fr;
        if (line[0] == '#' || sscanf(line, "%255s %255s %ld", cam, sl, &fr) != 3) {
            fputs(line, out);
            continue;
        }
        const size_t k = (size_t)atoi(sl + 7); /* slopes_NNN.fits */
        names_second |= k == 1;
        fprintf(out, "%s %s %ld\n", cam, stamp[k], fr);
    }
    fclose(in);
    fclose(out);
    assert_false(names_second); /* no cube starts in the second file */
    c.so.handshake = to;
    assert_ok(swfs_sync_run(&c.so, &b));
    const size_t ub = used_rows(&b.t, "raw_000.fits", stamp[1], &jb);
    printf("test_runs: cube 0 into an unnamed time-stamped file: %zu exposures used (%zu with numbered files)\n", ub,
           ua);
    assert_true(jb);
    assert_int_equal(ub, ua);
    assert_int_equal(b.t.ncubes, a.t.ncubes);
    free(a.t.cubes);
    free(b.t.cubes);
}

/* A copy of the science cube `src` at `dst` whose primary EXPTIME is exptime [s] (<= 0: none). */
static void science_with_exptime(const char *src, const char *dst, double exptime)
{
    fitsfile *in, *fp;
    int st = 0;
    remove(dst);
    fits_open_file(&in, src, READONLY, &st);
    fits_create_file(&fp, dst, &st);
    fits_copy_file(in, fp, 1, 1, 1, &st);
    fits_close_file(in, &st);
    fits_movabs_hdu(fp, 1, NULL, &st);
    if (exptime > 0) fits_update_key(fp, TDOUBLE, "EXPTIME", &exptime, NULL, &st);
    else fits_delete_key(fp, "EXPTIME", &st);
    fits_write_chksum(fp, &st);
    fits_close_file(fp, &st);
    assert_int_equal(st, 0);
}

/* sync's ratio range by default: from the camera's EXPTIME x WFSRATE (an exposure lasts at most
 * its frame period; 5 coarse steps below it) up to the handshake log's bound, a cube of 60
 * frames ending before the next cube of its telemetry file starts; the same fit as the
 * explicit range 5-8, significant. Without EXPTIME from 0.1 (a camera faster than the WFS);
 * with an EXPTIME longer than the frames' period the best ratio lies at its bound and the
 * search is made again from 0.1. A range without the true ratio is refused: no table. */
static void test_sync_ratio_from_log(void **state)
{
    (void)state;
    swfs_handshake *hs = NULL;
    size_t nhs = 0;
    assert_ok(swfs_handshake_read(p("handshake.log"), &hs, &nhs));
    double bound = 0;
    for (size_t k = 0; k + 1 < nhs; k++)
        if (!strcmp(hs[k].slopes, hs[k + 1].slopes)) {
            const double q = (double)(hs[k + 1].frame - hs[k].frame + 1) / 60.0;
            if (bound == 0 || q < bound) bound = q;
        }
    free(hs);
    assert_true(bound > 6.48);
    swfs_sync_run_options so;
    swfs_sync_run_options_default(&so);
    so.science = p("science.fits");
    so.handshake = p("handshake.log");
    so.out = p("timing_auto.txt");
    swfs_sync_run_result sr;
    assert_ok(swfs_sync_run(&so, &sr));
    printf("test_runs: ratios searched %g .. %g (log's bound %g), fit %.4f at %.1f sigma (needs %.1f)\n", sr.ratio_min,
           sr.ratio_max, sr.ratio_bound, sr.t.ratio, sr.t.fit.z, sr.t.fit.z_need);
    assert_int_equal(sr.ratio_auto, 1);
    assert_close(sr.ratio_bound, bound, 1e-12);
    assert_close(sr.ratio_max, bound, 1e-12);
    /* the simulator's camera writes EXPTIME = 6.48 WFS frames at 527 Hz, without dead time */
    assert_true(sr.exptime_used && !sr.exptime_widened);
    assert_close(sr.exptime_ratio, 6.48, 1e-9);
    assert_close(sr.ratio_min, 6.48 - SWFS_SYNC_EXPTIME_STEPS * so.params.ratio_step, 1e-9);
    assert_true(fabs(sr.t.ratio - 6.48) <= 0.03);
    assert_true(sr.t.fit.z > sr.t.fit.z_need && sr.t.fit.neff > 10 && sr.t.fit.neff <= 180);
    const double ratio = sr.t.ratio, lag = sr.t.lag, z_need = sr.t.fit.z_need;
    free(sr.t.cubes);
    /* no EXPTIME: from 0.1, the same fit, a search that needs more */
    science_with_exptime(p("science.fits"), p("science_noexp.fits"), 0);
    so.science = p("science_noexp.fits");
    assert_ok(swfs_sync_run(&so, &sr));
    assert_close(sr.ratio_min, 0.1, 0);
    assert_true(!sr.exptime_used && !sr.exptime_widened && sr.exptime_ratio == 0);
    assert_close(sr.t.ratio, ratio, 1e-12);
    assert_close(sr.t.lag, lag, 1e-12);
    assert_true(sr.t.fit.z_need > z_need);
    printf("test_runs: without EXPTIME from %g, the fit needs %.2f sigma (%.2f from EXPTIME's bound)\n", sr.ratio_min,
           sr.t.fit.z_need, z_need);
    free(sr.t.cubes);
    /* an EXPTIME of 6.6 frames for frames 6.48 apart: the best ratio at its bound, searched again */
    science_with_exptime(p("science.fits"), p("science_longexp.fits"), 6.6 / 527.0);
    so.science = p("science_longexp.fits");
    assert_ok(swfs_sync_run(&so, &sr));
    assert_true(sr.exptime_widened && !sr.exptime_used);
    assert_close(sr.exptime_ratio, 6.6, 1e-9);
    assert_close(sr.ratio_min, 0.1, 0);
    assert_close(sr.t.ratio, ratio, 1e-12);
    assert_close(sr.t.lag, lag, 1e-12);
    free(sr.t.cubes);
    so.science = p("science.fits");
    so.params.ratio_min = 2;
    so.params.ratio_max = 4;
    so.out = p("timing_narrow.txt");
    assert_int_equal(swfs_sync_run(&so, &sr), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "nowhere in the search"));
    assert_false(test_file_exists(p("timing_narrow.txt")));
    free(sr.t.cubes);
}

/* The documented path in folder sub with default options (sync over ratios 5-8 as the sync
 * cases, speckles with the science cube matched, estimate, the default pupil step): the NCP
 * error against sub/truth.fits [m], and the exposures used. */
/* The telemetry file `path` moved to `keep`, and written again without its last ncut frames. */
static void cut_file_end(const char *path, const char *keep, size_t ncut)
{
    assert_ok(rename(path, keep));
    swfs_real *s = NULL;
    assert_ok(swfs_fits_read_real(keep, NULL, &s, NULL));
    swfs_real cut = *s;
    cut.ny -= ncut;
    swfs_fits_out *fo = NULL;
    assert_ok(swfs_fits_out_create(&fo, path));
    assert_ok(swfs_fits_out_real(fo, NULL, &cut, -32));
    assert_ok(swfs_fits_out_commit(fo));
    swfs_real_free(s);
}

static double ncp_error_in(const char *sub, size_t *nused)
{
    char sci[1300], hs[1300], tim[1300], act[1300], sp[1300], scm[1300], halo[1300], truth[1300];
    snprintf(sci, sizeof sci, "%s/science.fits", sub);
    snprintf(hs, sizeof hs, "%s/handshake.log", sub);
    snprintf(tim, sizeof tim, "%s/timing_ncp.txt", sub);
    snprintf(act, sizeof act, "%s/actuators.fits", sub);
    snprintf(sp, sizeof sp, "%s/speckles_ncp.fits", sub);
    snprintf(scm, sizeof scm, "%s/sci_ncp.fits", sub);
    snprintf(halo, sizeof halo, "%s/halo_ncp.fits", sub);
    snprintf(truth, sizeof truth, "%s/truth.fits", sub);
    swfs_sync_run_options so;
    swfs_sync_run_options_default(&so);
    so.science = sci;
    so.handshake = hs;
    so.out = tim;
    so.params.ratio_min = 5;
    so.params.ratio_max = 8;
    swfs_sync_run_result sr;
    assert_ok(swfs_sync_run(&so, &sr));
    free(sr.t.cubes);
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate_on(tim, sci, act, sp, scm, halo, NULL, &spr, &er);
    swfs_real *ncp = NULL;
    assert_ok(swfs_fits_read_real(truth, "NCP", &ncp, NULL));
    swfs_pupil_result *pf = NULL;
    assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, NULL, &pf));
    double err = NAN;
    assert_ok(swfs_wfe_compare(pf->wfe->data, ncp->data, pf->mask->data, ncp->nx, &err, NULL, NULL));
    *nused = spr.nout;
    swfs_pupil_result_free(pf);
    swfs_real_free(ncp);
    swfs_halo_free(er.halo);
    return err;
}

/* Telemetry files shorter than a camera cube (150 WFS frames against a cube's 389): each cube
 * runs through three or four files and holds a part of 23 exposures at most in each. The
 * chains of contiguous files are followed file by file, the fit made again over the cubes
 * joined across them, and all but the exposures across a boundary (and parts too short to
 * check) used; the rows of each file start where contiguity puts them. Three WFS frames lost
 * at the end of one file stop the chains that cross it. */
static void test_sync_files_shorter_than_cube(void **state)
{
    (void)state;
    sync_case c;
    sync_case_make(&c, "short", "wfs_file_frames=150");
    swfs_sync_run_result sr;
    assert_ok(swfs_sync_run(&c.so, &sr));
    size_t maxfiles = 0;
    for (size_t k = 0; k < sr.t.ncubes; k++) {
        const swfs_timing_cube *row = &sr.t.cubes[k];
        /* The camera's lag and the telemetry itself both say the files continue each other. */
        if (row->joined) assert_true(fabs(row->join_offset) < 0.5 && row->join_verdict == 1);
    }
    for (int cube = 0; cube < 3; cube++) {
        char cam[32];
        snprintf(cam, sizeof cam, "raw_%03d.fits", cube);
        const char *files[16];
        size_t nf = 0;
        const swfs_timing_cube *prev = NULL;
        for (size_t k = 0; k < sr.t.ncubes; k++) {
            const swfs_timing_cube *row = &sr.t.cubes[k];
            if (strcmp(row->camera, cam) || row->status != SWFS_CUBE_OK) continue;
            /* Contiguity: a row's start is its predecessor's carried over that file's 150 frames. */
            if (prev && strcmp(prev->slopes, row->slopes)) {
                const double carried = prev->start + (double)(row->first - prev->first) * sr.t.ratio - 150;
                assert_close(row->start, carried, 1e-9);
            }
            int seen = 0;
            for (size_t q = 0; q < nf; q++) seen |= !strcmp(files[q], row->slopes);
            if (!seen && nf < 16) files[nf++] = row->slopes;
            prev = row;
        }
        if (nf > maxfiles) maxfiles = nf;
    }
    printf("test_runs: files of 150 WFS frames: ratio %.4f (own files alone %.4f) after %d refit%s, %zu of %zu "
           "exposures in %zu rows, %zu parts continued, cubes over up to %zu files\n", sr.t.ratio, sr.ratio_first,
           sr.refits, sr.refits == 1 ? "" : "s", sr.nexp_ok, sr.nexp, sr.nok, sr.ncontinued, maxfiles);
    assert_true(fabs(sr.t.ratio - 6.48) <= 0.01);
    assert_true(sr.refits >= 1);
    assert_true(maxfiles >= 3);
    assert_true(sr.ncontinued >= 6);
    /* Each boundary a cube crosses costs the exposure across it, and the parts too short to
       check: at least 90 % of the exposures are used. */
    assert_true(sr.nexp_ok >= 162);
    const size_t used = sr.nexp_ok;
    free(sr.t.cubes);
    /* The same simulated series (seed, timing) in files of 1000 frames, where only one cube
       crosses a boundary: the NCP error from the short files is that of the long ones (17.3
       and 17.0 nm; sync before it followed cubes file by file used 115 exposures: 22.6 nm). */
    size_t n_short = 0, n_long = 0;
    const double e_short = ncp_error_in(c.sub, &n_short), e_long = ncp_error_in(dir, &n_long);
    printf("test_runs: NCP error %.1f nm from files of 150 frames (%zu exposures), %.1f nm from files of 1000 (%zu)\n",
           1e9 * e_short, n_short, 1e9 * e_long, n_long);
    assert_int_equal(n_short, used);
    assert_true(e_short > 0 && e_short < 1.15 * e_long);

    /* A logger that loses the last frame of every file it closes: each boundary one frame
       short. Where the telemetry says not contiguous, it and the camera count the frame and
       the parts are placed one frame on (where it cannot tell, 0 and 1 lost stay undecided
       and a part a frame off stays out: 146 of the 173 exposures); the whole path gives the
       contiguous files' NCP error (17.3 nm; without the count 49 exposures and 34.5 nm). */
    char fk[1400], keep[1400];
    size_t nfiles = 0;
    for (;; nfiles++) {
        snprintf(fk, sizeof fk, "%s/slopes_%03zu.fits", c.sub, nfiles);
        snprintf(keep, sizeof keep, "%s/slopes_%03zu.whole", c.sub, nfiles);
        if (access(fk, F_OK)) break;
        cut_file_end(fk, keep, 1);
    }
    size_t n_drop = 0;
    const double e_drop = ncp_error_in(c.sub, &n_drop);
    printf("test_runs: one frame lost at the end of each of the %zu files: NCP error %.1f nm from %zu exposures\n",
           nfiles, 1e9 * e_drop, n_drop);
    assert_true(nfiles >= 10);
    assert_true(n_drop * 5 >= used * 4);
    assert_true(e_drop > 0 && e_drop < 1.15 * e_long);
    for (size_t k = 0; k < nfiles; k++) { /* the whole files again */
        snprintf(fk, sizeof fk, "%s/slopes_%03zu.fits", c.sub, k);
        snprintf(keep, sizeof keep, "%s/slopes_%03zu.whole", c.sub, k);
        assert_ok(rename(keep, fk));
    }

    /* Cube 1 runs from slopes_005 through slopes_006 and slopes_007 into slopes_008: cut three
       frames off the end of slopes_006; its chain stops there (three lost frames are not told
       from a long gap on this loop: test_sync_speckles_estimate), and no cube joins slopes_007
       or slopes_008 (no cube starts in them). */
    char f6[1400], lost[1400];
    snprintf(f6, sizeof f6, "%s/slopes_006.fits", c.sub);
    snprintf(lost, sizeof lost, "%s/slopes_006.full", c.sub);
    cut_file_end(f6, lost, 3);
    assert_ok(swfs_sync_run(&c.so, &sr));
    /* The telemetry alone sees the frames lost: the step from slopes_006 to slopes_007 is one
       over four frames. */
    char f7[1400];
    snprintf(f7, sizeof f7, "%s/slopes_007.fits", c.sub);
    swfs_real *a = NULL, *b = NULL;
    assert_ok(swfs_fits_read_real(f6, NULL, &a, NULL));
    assert_ok(swfs_fits_read_real(f7, NULL, &b, NULL));
    swfs_sync_boundary bd;
    assert_ok(swfs_sync_boundary_check(a->data + (a->ny - 64) * a->nx, 64, b->data, 64, a->nx, &bd));
    assert_int_equal(bd.verdict, -1);
    swfs_real_free(a);
    swfs_real_free(b);
    int crosses = 0;
    for (size_t k = 0; k < sr.t.ncubes; k++)
        if (sr.t.cubes[k].joined &&
            (strstr(sr.t.cubes[k].slopes, "slopes_007.fits") || strstr(sr.t.cubes[k].slopes, "slopes_008.fits")))
            crosses = 1;
    printf("test_runs: 3 frames lost at the end of slopes_006: %zu of %zu exposures (%zu before)\n", sr.nexp_ok,
           sr.nexp, used);
    assert_false(crosses);
    assert_true(sr.nexp_ok < used);
    free(sr.t.cubes);

    /* slopes_006 whole again and slopes_007 gone: 150 frames lost between slopes_006 and
       slopes_008 (the folder's next file). The files' FRAME0 (900, 1200) count them, the
       telemetry says not continuous, and raw_001's part in slopes_008 is placed by the count,
       where the camera finds it. */
    char f7k[1400], f8[1400], f8k[1400];
    snprintf(f7k, sizeof f7k, "%s/slopes_007.keep", c.sub);
    snprintf(f8, sizeof f8, "%s/slopes_008.fits", c.sub);
    snprintf(f8k, sizeof f8k, "%s/slopes_008.keep", c.sub);
    assert_ok(rename(f7, f7k));
    assert_ok(rename(lost, f6));
    assert_ok(swfs_sync_run(&c.so, &sr));
    const swfs_timing_cube *in8 = NULL;
    for (size_t k = 0; k < sr.t.ncubes; k++)
        if (sr.t.cubes[k].joined && strstr(sr.t.cubes[k].slopes, "slopes_008.fits")) in8 = &sr.t.cubes[k];
    printf("test_runs: slopes_007 gone: %zu of %zu exposures; %s\n", sr.nexp_ok, sr.nexp,
           in8 ? "a part placed in slopes_008 by the files' FRAME0" : "none in slopes_008");
    assert_non_null(in8);
    assert_true(in8->join_frame0 && in8->join_lost == 150 && in8->join_verdict == -1 && fabs(in8->join_offset) < 0.5);
    assert_true(sr.nexp_ok < used);
    const size_t with_frame0 = sr.nexp_ok;
    free(sr.t.cubes);
    /* Without FRAME0 in slopes_008 the data alone decide: the camera's tip-tilt, periodic with
       the 20 Hz vibration, matches there at the gap less six periods (4 frames "repeated"); the
       telemetry does not show that count, and the chain stops at slopes_006. */
    cut_file_end(f8, f8k, 0);
    assert_ok(swfs_sync_run(&c.so, &sr));
    crosses = 0;
    for (size_t k = 0; k < sr.t.ncubes; k++)
        if (sr.t.cubes[k].joined && strstr(sr.t.cubes[k].slopes, "slopes_008.fits")) crosses = 1;
    printf("test_runs: slopes_007 gone, no FRAME0 in slopes_008: %zu of %zu exposures\n", sr.nexp_ok, sr.nexp);
    assert_false(crosses);
    assert_true(sr.nexp_ok < with_frame0);
    free(sr.t.cubes);
}

/* A time series of the small system into `where` with the true residual beside the slopes
 * (export_truth), at the conditions kv; no camera reduction. Its camera is not used, so it
 * runs camera_light: the same WFS frames as the small system's camera keys make it run. */
static void simulate_truth(const char *where, const char *const *kv, size_t nkv)
{
    const char *all[8] = {"export_truth=1"};
    assert_true(nkv < 7);
    for (size_t i = 0; i < nkv; i++) all[1 + i] = kv[i];
    swfs_ts_params tp, heavy;
    small_params(all, nkv + 1, &heavy);
    all[nkv + 1] = "camera_light=1";
    small_params(all, nkv + 2, &tp);
    assert_int_equal(tp.ncubes, 2);
    assert_int_equal(tp.cube_frames, 20);
    assert_int_equal(swfs_ts_nframes(&tp), swfs_ts_nframes(&heavy));
    run_small(where, &tp);
}

/* camera_light: the test data's own conditions run camera-light (simulate_truth) give its
 * slopes value for value, every file, though the camera integrated 40 frames instead of 180. */
static void test_camera_light_same_slopes(void **state)
{
    (void)state;
    const char *kv[] = {"layer_speed=30,40", "vib_amp=0.6", "jitter_amp=0.15", "seed=1", "wfs_file_frames=1000"};
    const char *where = p("light");
    simulate_truth(where, kv, sizeof kv / sizeof kv[0]);
    size_t nfiles = 0;
    for (int k = 0;; k++, nfiles++) {
        char a[1400], b[1400];
        snprintf(a, sizeof a, "%s/slopes_%03d.fits", dir, k);
        snprintf(b, sizeof b, "%s/slopes_%03d.fits", where, k);
        if (access(a, F_OK)) {
            assert_true(access(b, F_OK) != 0); /* no file more than the test data has */
            break;
        }
        swfs_real *sa = NULL, *sb = NULL;
        assert_ok(swfs_fits_read_real(a, NULL, &sa, NULL));
        assert_ok(swfs_fits_read_real(b, NULL, &sb, NULL));
        assert_int_equal(sa->nx, sb->nx);
        assert_int_equal(sa->ny, sb->ny);
        assert_memory_equal(sa->data, sb->data, sa->nx * sa->ny * sizeof *sa->data);
        swfs_real_free(sa);
        swfs_real_free(sb);
    }
    assert_true(nfiles >= 2);
}

/* rms over the frames of truth (piston removed) - W slopes, and of the truth. */
static double recon_error(const swfs_recon *w, const char *where, double *truth_rms)
{
    char sp[1400], tp[1400];
    snprintf(sp, sizeof sp, "%s/slopes_000.fits", where);
    snprintf(tp, sizeof tp, "%s/truewf_000.fits", where);
    swfs_real *s = NULL, *z = NULL;
    assert_ok(swfs_fits_read_real(sp, NULL, &s, NULL));
    assert_ok(swfs_fits_read_real(tp, NULL, &z, NULL));
    const size_t nl = w->nlags ? w->nlags : 1;
    assert_int_equal(s->nx * nl, w->nslopes);
    assert_int_equal(z->nx, w->nact);
    double *zh = malloc(w->nact * sizeof *zh), *st = malloc(w->nslopes * sizeof *st), e2 = 0, t2 = 0;
    for (size_t f = 0; f < s->ny; f++) {
        const double *zf = z->data + f * z->nx;
        double m = 0;
        for (size_t a = 0; a < w->nact; a++) m += zf[a];
        m /= (double)w->nact;
        swfs_slopes_stack(s->data, s->ny, s->nx, w->nlags ? w->lags : (const long[]){0}, nl, f, 1, st);
        swfs_recon_apply(w, st, zh);
        double mh = 0;
        for (size_t a = 0; a < w->nact; a++) mh += zh[a];
        mh /= (double)w->nact;
        for (size_t a = 0; a < w->nact; a++) {
            e2 += (zf[a] - m - zh[a] + mh) * (zf[a] - m - zh[a] + mh);
            t2 += (zf[a] - m) * (zf[a] - m);
        }
    }
    const double n = (double)(s->ny * w->nact);
    *truth_rms = sqrt(t2 / n);
    free(zh);
    free(st);
    swfs_real_free(s);
    swfs_real_free(z);
    return sqrt(e2 / n);
}

/* speckles with the reconstructor file `recon` (in dir), the science cube matched, then
 * estimate and pupil: the NCP error against ncp [m]. Files speckles_TAG, sci_TAG, halo_TAG;
 * er->halo is the caller's. */
static double given_path_error(const char *recon, const char *tag, const swfs_real *ncp, swfs_speckles_run_result *spr,
                               swfs_estimate_run_result *er)
{
    char f[3][64];
    snprintf(f[0], sizeof f[0], "speckles_%s.fits", tag);
    snprintf(f[1], sizeof f[1], "sci_%s.fits", tag);
    snprintf(f[2], sizeof f[2], "halo_%s.fits", tag);
    swfs_speckles_run_options sp;
    given_recon_options(&sp, p(recon), p(f[0]));
    speckles_estimate_with(&sp, p(f[1]), p(f[2]), spr, er);
    swfs_pupil_result *pf = NULL;
    double e = NAN;
    assert_ok(swfs_pupil_estimate(er->halo, &er->geom, NULL, NULL, &pf));
    assert_ok(swfs_wfe_compare(pf->wfe->data, ncp->data, pf->mask->data, ncp->nx, &e, NULL, NULL));
    swfs_pupil_result_free(pf);
    return e;
}

/* learn: a reconstructor from three simulated closed loops of the test system's geometry
 * under other winds, vibration and seeds. On a fourth simulation (the test data's conditions,
 * another seed) it misses the true residual per frame by less than the default von Karman
 * reconstructor does, and through the whole path on the test data it is no worse than the
 * default. Bad input: a folder without truth, data of another geometry. */
static void test_learn_reconstructor(void **state)
{
    (void)state;
    const char *conds[3][3] = {{"layer_speed=8,12", "vib_amp=0", "seed=21"},
                               {"layer_speed=20,25", "vib_amp=0.3", "seed=22"},
                               {"layer_speed=45,55", "vib_amp=0.6", "seed=23"}};
    const char *tdir[3] = {p("learn_a"), p("learn_b"), p("learn_c")};
    for (int k = 0; k < 3; k++) simulate_truth(tdir[k], conds[k], 3);
    const char *held[] = {"layer_speed=30,40", "vib_amp=0.6", "jitter_amp=0.15", "seed=9"};
    const char *hdir = p("learn_held");
    simulate_truth(hdir, held, 4);

    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = tdir;
    lo.ndirs = 3;
    lo.out = p("recon_learned.fits");
    double hratio[3];
    lo.heldout_ratio = hratio;
    swfs_learn_run_result lr;
    assert_ok(swfs_learn_run(&lo, &lr));
    printf("test_runs: learned from %zu frames (%zu files): %zu slopes (%zu with signal) -> %zu actuators, training misfit "
           "%.1f of %.1f nm\n", lr.info.nframes, lr.nfiles, lr.nslopes, lr.info.nslopes_seen, lr.nact,
           1e9 * lr.info.misfit_rms, 1e9 * lr.info.truth_rms);
    assert_true(lr.info.misfit_rms < lr.info.truth_rms);
    /* each loop left out in turn: the others' map misses it by more than the training misfit
     * (other winds and vibration); the middle condition is covered by the two around it */
    printf("test_runs: held out in turn: %.1f of %.1f nm; each set %.2f %.2f %.2f, the worst %zu at %.2f\n",
           1e9 * lr.heldout_misfit_rms, 1e9 * lr.heldout_truth_rms, hratio[0], hratio[1], hratio[2],
           lr.heldout_worst_set, lr.heldout_worst);
    assert_int_equal(lr.nheldout, 3);
    assert_true(lr.heldout_misfit_rms > lr.info.misfit_rms);
    assert_true(hratio[1] < 1 && hratio[1] > lr.info.misfit_rms / lr.info.truth_rms);
    assert_close(lr.heldout_worst, fmax(hratio[0], fmax(hratio[1], hratio[2])), 1e-12);
    double hk = 0;
    swfs_fits_in *fin = NULL;
    assert_ok(swfs_fits_in_open(&fin, lo.out, NULL));
    assert_ok(swfs_fits_in_key_double(fin, "LRNHMISF", &hk));
    swfs_fits_in_close(fin);
    assert_close(hk, lr.heldout_misfit_rms, 1e-6 * hk);

    /* the default reconstructor of the test data (the same geometry) */
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate(p("speckles_lv.fits"), p("sci_lv.fits"), p("halo_lv.fits"), p("recon_vk.fits"), &spr, &er);
    swfs_real *ncp = NULL;
    assert_ok(swfs_fits_read_real(p("truth.fits"), "NCP", &ncp, NULL));
    swfs_pupil_result *pf = NULL;
    double e_vk = NAN, e_learn = NAN;
    assert_ok(swfs_pupil_estimate(er.halo, &er.geom, NULL, NULL, &pf));
    assert_ok(swfs_wfe_compare(pf->wfe->data, ncp->data, pf->mask->data, ncp->nx, &e_vk, NULL, NULL));
    swfs_pupil_result_free(pf);
    swfs_halo_free(er.halo);

    swfs_recon *wl = NULL, *wv = NULL;
    assert_ok(swfs_recon_read(p("recon_learned.fits"), &wl));
    assert_ok(swfs_recon_read(p("recon_vk.fits"), &wv));
    double t_rms = 0;
    const double err_l = recon_error(wl, hdir, &t_rms), err_v = recon_error(wv, hdir, &t_rms);
    printf("test_runs: per frame on a held-out simulation: learned misses the residual by %.1f nm, vk by %.1f nm "
           "(residual %.1f nm per actuator)\n", 1e9 * err_l, 1e9 * err_v, 1e9 * t_rms);
    assert_true(err_l < 0.9 * err_v);
    swfs_recon_free(wl);
    swfs_recon_free(wv);

    /* the whole path on the test data with the learned reconstructor */
    e_learn = given_path_error("recon_learned.fits", "learned", ncp, &spr, &er);
    printf("test_runs: NCP error with the learned reconstructor %.1f nm, with the default %.1f nm\n", 1e9 * e_learn,
           1e9 * e_vk);
    assert_string_equal(er.halo->tiptilt, "exposure"); /* SPECKLES.fits TIPTILT carried into the halo */
    swfs_halo *hl = NULL;
    assert_ok(swfs_halo_read(p("halo_learned.fits"), &hl, NULL));
    assert_string_equal(hl->tiptilt, "exposure"); /* and through HALO.fits */
    swfs_halo_free(hl);
    assert_true(e_learn > 0 && e_learn < 1.05 * e_vk);
    swfs_halo_free(er.halo);
    swfs_real_free(ncp);

    /* bad input: a folder of slopes without truth; data of another geometry */
    const char *bad1[] = {p("runs_no_truth")};
    mkdir(bad1[0], 0755);
    char sp0[1400];
    snprintf(sp0, sizeof sp0, "%s/slopes_000.fits", bad1[0]);
    unlink(sp0);
    swfs_real *s0 = NULL;
    assert_ok(swfs_fits_read_real(p("slopes_000.fits"), NULL, &s0, NULL));
    swfs_fits_out *fo = NULL;
    assert_ok(swfs_fits_out_create(&fo, sp0));
    assert_ok(swfs_fits_out_real(fo, NULL, s0, -32));
    assert_ok(swfs_fits_out_commit(fo));
    swfs_real_free(s0);
    lo.dirs = bad1;
    lo.ndirs = 1;
    lo.heldout_ratio = NULL;
    lo.out = p("recon_bad.fits");
    assert_int_equal(swfs_learn_run(&lo, &lr), SWFS_ERR_IO);
    printf("test_runs: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "truewf_000.fits"));
    const char *other[] = {tdir[0], p("learn_nsub8")};
    const char *k8[] = {"nsub=8", "act_pitch=0.7", "seed=24"};
    simulate_truth(other[1], k8, 3);
    lo.dirs = other;
    lo.ndirs = 2;
    assert_int_equal(swfs_learn_run(&lo, &lr), SWFS_ERR_SHAPE);
    printf("test_runs: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "one geometry"));
    assert_false(test_file_exists(p("recon_bad.fits")));
}

/* A map with output points of its own (simulate's truth_actuators, teach's grid finer than the
 * DM): learn gives the map the points the loops' truth was fitted on (OUTXY), the pipeline
 * builds its model on them in place of the DM's actuators given, computes the speckles within
 * their sampling band D / (2 pitch) by default, and --write-recon keeps them. Refused: the
 * points without export_truth, training sets on different points, an OUTXY of another size. */
/* A progress callback that asks the run to stop at its `at`-th report. */
typedef struct stopper {
    int calls, at;
} stopper;

static int stop_at(void *ctx, const char *stage, size_t done, size_t total)
{
    (void)stage, (void)done, (void)total;
    stopper *s = ctx;
    return ++s->calls >= s->at;
}

/* Entries of folder d (not . and ..), part files included. */
static size_t entries_in(const char *d)
{
    DIR *dp = opendir(d);
    assert_non_null(dp);
    size_t n = 0;
    for (struct dirent *e; (e = readdir(dp));) n += strcmp(e->d_name, ".") && strcmp(e->d_name, "..");
    closedir(dp);
    return n;
}

/* A run whose progress callback asks to stop: SWFS_ERR_STOPPED, the stage named, nothing
 * written (no output, no part file) -- the time series, reduce, speckles, estimate, and learn
 * read in turn and by its four parts' workers (the learning curve). */
static void test_stopped_by_progress(void **state)
{
    (void)state;
    swfs_ts_params tp;
    small_params(NULL, 0, &tp);
    const char *ts = p("stopped_ts");
    mkdir(ts, 0755);
    stopper s = {0, 3}; /* the screens, then the WFS frames */
    swfs_ts_summary sm;
    assert_int_equal(swfs_ts_run(&tp, ts, NULL, 0, stop_at, &s, &sm), SWFS_ERR_STOPPED);
    assert_non_null(strstr(swfs_last_error(), "WFS frames: stopped by the caller at "));
    assert_int_equal(s.calls, 3);
    assert_int_equal(entries_in(ts), 0);

    const char *out = p("stopped_out");
    mkdir(out, 0755);
    swfs_reduce_run_options ro;
    swfs_reduce_run_options_default(&ro);
    const char *raw[] = {p("raw_000.fits"), p("raw_001.fits"), p("raw_002.fits")};
    ro.raw = raw;
    ro.nraw = 3;
    ro.out = p("stopped_out/science.fits");
    ro.progress = stop_at;
    ro.progress_ctx = &(stopper){0, 2};
    swfs_reduce_run_result rr;
    assert_int_equal(swfs_reduce_run(&ro, &rr), SWFS_ERR_STOPPED);
    assert_string_equal(swfs_last_error(), "cubes: stopped by the caller at 2 of 3");

    swfs_speckles_run_options sp;
    given_recon_options(&sp, p("recon_vk.fits"), p("stopped_out/speckles.fits"));
    sp.progress = stop_at;
    sp.progress_ctx = &(stopper){0, 1};
    swfs_speckles_run_result spr;
    assert_int_equal(swfs_speckles_run(&sp, &spr), SWFS_ERR_STOPPED);
    assert_non_null(strstr(swfs_last_error(), "cubes: stopped by the caller at 1 of 4"));

    swfs_estimate_run_options eo;
    swfs_estimate_run_options_default(&eo);
    eo.science = p("sci_lv.fits");
    eo.speckles = p("speckles_lv.fits");
    eo.out = p("stopped_out/halo.fits");
    eo.block = 16;
    eo.progress = stop_at;
    eo.progress_ctx = &(stopper){0, 2};
    swfs_estimate_run_result er;
    assert_int_equal(swfs_estimate_run(&eo, &er), SWFS_ERR_STOPPED);
    assert_non_null(strstr(swfs_last_error(), "frames: stopped by the caller at 32 of"));

    const char *dirs[] = {p("learn_a"), p("learn_b"), p("learn_c"), p("learn_held")};
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = dirs;
    lo.ndirs = 3;
    lo.out = p("stopped_out/W.fits");
    lo.progress = stop_at;
    lo.progress_ctx = &(stopper){0, 2};
    swfs_learn_run_result lr;
    assert_int_equal(swfs_learn_run(&lo, &lr), SWFS_ERR_STOPPED);
    assert_string_equal(swfs_last_error(), "read: stopped by the caller at 2 of 3");
    lo.ndirs = 4;
    lo.curve = 1;
    lo.threads = 2;
    lo.progress_ctx = &(stopper){0, 2};
    assert_int_equal(swfs_learn_run(&lo, &lr), SWFS_ERR_STOPPED);
    assert_non_null(strstr(swfs_last_error(), "read: stopped by the caller after "));
    assert_int_equal(entries_in(out), 0);
}

static void test_learn_output_points(void **state)
{
    (void)state;
    swfs_recon *dm = NULL;
    double *axy = NULL, *gxy = NULL;
    size_t na = 0, ng = 0;
    assert_ok(swfs_actuators_read(p("actuators.fits"), &axy, &na));
    const double dm_pitch = swfs_points_pitch(axy, na);
    assert_ok(swfs_actuators_hexapolar(6.5, 0.5 * dm_pitch, 0.1, &gxy, &ng));
    assert_true(ng > 3 * na);
    assert_ok(swfs_actuators_write(gxy, ng, p("grid_fine.fits")));
    char key[1400];
    snprintf(key, sizeof key, "truth_actuators=%s", p("grid_fine.fits"));
    const char *ka[] = {"layer_speed=8,12", "seed=31", key}, *kb[] = {"layer_speed=20,25", "seed=32", key};
    const char *dirs[] = {p("learn_fa"), p("learn_fb")};
    simulate_truth(dirs[0], ka, 3);
    simulate_truth(dirs[1], kb, 3);
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = dirs;
    lo.ndirs = 2;
    lo.no_heldout = 1;
    lo.out = p("recon_fine.fits");
    swfs_learn_run_result lr;
    assert_ok(swfs_learn_run(&lo, &lr));
    assert_int_equal(lr.nact, ng);
    assert_ok(swfs_recon_read(lo.out, &dm));
    assert_int_equal(dm->nact, ng);
    assert_non_null(dm->oxy);
    assert_memory_equal(dm->oxy, gxy, 2 * ng * sizeof *gxy);
    swfs_recon_free(dm);
    dm = NULL;

    /* the whole path: the model on the map's points, the band theirs, the points kept */
    swfs_speckles_run_options sp;
    given_recon_options(&sp, p("recon_fine.fits"), p("speckles_fine.fits"));
    sp.write_recon = p("recon_fine_w.fits");
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate_with(&sp, p("sci_fine.fits"), p("halo_fine.fits"), &spr, &er);
    printf("test_runs: a map on %zu points of pitch %.3f m (the DM: %zu of %.3f m): speckles within %.2f lambda/D\n",
           spr.info.nact, spr.info.out_pitch, na, dm_pitch, spr.info.band);
    assert_int_equal(spr.info.nact, ng);
    assert_close(spr.info.out_pitch, swfs_points_pitch(gxy, ng), 1e-12);
    assert_close(spr.info.band, er.geom.teldiam / (2 * spr.info.out_pitch), 1e-9);
    assert_true(spr.info.band > 0.5 * (double)spr.info.nsub);
    assert_true(spr.nout > 170); /* of 180: every exposure the timing table keeps */
    swfs_halo_free(er.halo);
    assert_ok(swfs_recon_read(sp.write_recon, &dm));
    assert_non_null(dm->oxy);
    assert_memory_equal(dm->oxy, gxy, 2 * ng * sizeof *gxy);
    swfs_recon_free(dm);
    dm = NULL;

    /* refused: truth_actuators without export_truth */
    swfs_config *c = swfs_config_new();
    assert_ok(swfs_config_set(c, key));
    swfs_ts_params tp;
    swfs_ts_params_default(&tp);
    assert_ok(swfs_ts_params_from_config(c, &tp));
    swfs_config_free(c);
    assert_refused(swfs_ts_params_check(&tp), "truth_actuators without export_truth", "needs export_truth=1", p("never.fits"));
    /* refused: one set on the DM's actuators (another count); one on as many other points
     * (learn_fb's files, its truth's OUTXY mirrored) */
    const char *mixed[] = {dirs[0], p("learn_a")};
    lo.dirs = mixed;
    lo.out = p("recon_mixed.fits");
    assert_refused(swfs_learn_run(&lo, &lr), "learn, sets on the DM's actuators and a grid", "one geometry", lo.out);
    char from[1400], to[1400];
    mkdir(p("learn_fc"), 0755);
    for (int t = 0; t < 2; t++) {
        snprintf(from, sizeof from, "%s/%s_000.fits", dirs[1], t ? "truewf" : "slopes");
        snprintf(to, sizeof to, "%s/%s_000.fits", p("learn_fc"), t ? "truewf" : "slopes");
        swfs_real *a = NULL;
        assert_ok(swfs_fits_read_real(from, NULL, &a, NULL));
        swfs_fits_out *f = NULL;
        assert_ok(swfs_fits_out_create(&f, to));
        assert_ok(swfs_fits_out_real(f, NULL, a, -32));
        for (size_t i = 0; t && i < ng; i++) gxy[2 * i] = -gxy[2 * i];
        if (t) assert_ok(swfs_fits_out_real(f, "OUTXY", &(swfs_real){2, ng, 1, gxy}, -64));
        for (size_t i = 0; t && i < ng; i++) gxy[2 * i] = -gxy[2 * i];
        assert_ok(swfs_fits_out_commit(f));
        swfs_real_free(a);
    }
    const char *moved[] = {dirs[0], p("learn_fc")};
    lo.dirs = moved;
    assert_refused(swfs_learn_run(&lo, &lr), "learn, sets on other points", "one geometry", lo.out);
    assert_non_null(strstr(swfs_last_error(), "on other points (OUTXY) than"));
    /* refused: a map whose OUTXY has another count than its outputs */
    assert_ok(swfs_recon_read(p("recon_vk.fits"), &dm));
    dm->oxy = malloc(2 * dm->nact * sizeof *dm->oxy);
    memcpy(dm->oxy, gxy, 2 * dm->nact * sizeof *dm->oxy);
    assert_ok(swfs_recon_write(dm, p("recon_badxy.fits")));
    swfs_recon_free(dm);
    swfs_real *w = NULL;
    assert_ok(swfs_fits_read_real(p("recon_badxy.fits"), NULL, &w, NULL));
    swfs_fits_out *fo = NULL;
    assert_ok(swfs_fits_out_create(&fo, p("recon_badxy.fits")));
    assert_ok(swfs_fits_out_real(fo, NULL, w, -64));
    assert_ok(swfs_fits_out_real(fo, "OUTXY", &(swfs_real){2, 5, 1, gxy}, -64));
    assert_ok(swfs_fits_out_commit(fo));
    swfs_real_free(w);
    dm = NULL;
    assert_int_equal(swfs_recon_read(p("recon_badxy.fits"), &dm), SWFS_ERR_SHAPE);
    printf("test_runs: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "OUTXY is 2 x 5 x 1"));
    assert_null(dm);
    free(axy);
    free(gxy);
}

/* The speckle cube of `path` (every frame) and its RESMEAN. */
static swfs_cplx *read_speckles(const char *path, swfs_real **resmean)
{
    swfs_cplx *c = NULL;
    assert_ok(swfs_fits_read_cplx(path, NULL, &c, NULL));
    assert_ok(swfs_fits_read_real(path, "RESMEAN", resmean, NULL));
    return c;
}

/* A space-time reconstructor (learn --lags; a cube of one map per lag given to speckles).
 * A cube whose lag-0 plane is the default's map and whose other planes are 0 gives the
 * default's speckles and residual mean (the stacking, the margins and the tip-tilt treatment
 * of the lag blocks leave a per-frame map alone); learned with lags, the map fits its
 * training frames better than the per-frame one (a least squares with more inputs), and the
 * whole path runs with it. Refused: a stream or an AO loop given one, a cube without its
 * lags, lags without 0, lags with a modal map. */
static void test_spacetime_reconstructor(void **state)
{
    (void)state;
    swfs_speckles_run_result spr;
    swfs_estimate_run_result er;
    speckles_estimate(p("speckles_st.fits"), p("sci_st.fits"), p("halo_st.fits"), p("recon_st_vk.fits"), &spr, &er);
    swfs_halo_free(er.halo);
    assert_int_equal(spr.info.nlags, 0);
    swfs_recon *w = NULL, *back = NULL;
    assert_ok(swfs_recon_read(p("recon_st_vk.fits"), &w));
    const size_t ns = w->nslopes, na = w->nact;
    swfs_recon st = {.nact = na, .nslopes = 3 * ns, .W = calloc(3 * ns * na, sizeof(double)), .nlags = 3,
                     .lags = {40, 0, -40}};
    for (size_t a = 0; a < na; a++) memcpy(st.W + a * st.nslopes + ns, w->W + a * ns, ns * sizeof(double));
    assert_ok(swfs_recon_write(&st, p("recon_st3.fits")));
    assert_ok(swfs_recon_read(p("recon_st3.fits"), &back));
    assert_int_equal(back->nlags, 3);
    assert_int_equal(back->nslopes, 3 * ns);
    assert_true(back->lags[0] == 40 && back->lags[1] == 0 && back->lags[2] == -40);
    assert_memory_equal(back->W, st.W, 3 * ns * na * sizeof(double));
    swfs_recon_free(back);

    const char *files[2] = {"recon_st_vk.fits", "recon_st3.fits"}, *outs[2] = {"speckles_g1.fits", "speckles_g3.fits"};
    for (int k = 0; k < 2; k++) {
        swfs_speckles_run_options sp;
        given_recon_options(&sp, p(files[k]), p(outs[k]));
        assert_ok(swfs_speckles_run(&sp, &spr));
        assert_int_equal(spr.info.nlags, k ? 3 : 0);
        assert_int_equal(spr.info.nslopes, k ? 3 * ns : ns);
        assert_false(spr.st_found); /* no training wind in a hand-made cube */
    }
    swfs_real *m1 = NULL, *m3 = NULL;
    swfs_cplx *c1 = read_speckles(p(outs[0]), &m1), *c3 = read_speckles(p(outs[1]), &m3);
    assert_int_equal(c1->nz, c3->nz);
    double d = 0, peak = 0, dm = 0, mp = 0;
    for (size_t i = 0; i < c1->nx * c1->ny * c1->nz; i++) {
        peak = fmax(peak, cabs(c1->data[i]));
        d = fmax(d, cabs(c1->data[i] - c3->data[i]));
    }
    for (size_t i = 0; i < m1->nx * m1->ny; i++) {
        mp = fmax(mp, fabs(m1->data[i]));
        dm = fmax(dm, fabs(m1->data[i] - m3->data[i]));
    }
    printf("test_runs: space-time cube [0, W, 0] against W: max |d psi| / peak %.2g, max |d RESMEAN| / peak %.2g\n",
           d / peak, dm / mp);
    assert_true(d <= 1e-5 * peak && dm <= 1e-9 * mp); /* the cube is single precision */
    swfs_cplx_free(c1);
    swfs_cplx_free(c3);
    swfs_real_free(m1);
    swfs_real_free(m3);
    free(st.W);
    swfs_recon_free(w);

    /* Learned with lags on loops of other winds (those of test_learn_reconstructor): the
     * held-out check sees the lags carry over worse than the per-frame map. */
    const char *tdir[3] = {p("learn_a"), p("learn_b"), p("learn_c")};
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = tdir;
    lo.ndirs = 3;
    lo.out = p("recon_l1.fits");
    swfs_learn_run_result l1, l3;
    assert_ok(swfs_learn_run(&lo, &l1));
    const long lags[3] = {0, -4, 4};
    lo.lags = lags;
    lo.nlags = 3;
    lo.out = p("recon_l3.fits");
    assert_ok(swfs_learn_run(&lo, &l3));
    printf("test_runs: other winds, per frame: misfit %.1f, held out %.1f of %.1f nm; lags 0,-4,4: %.1f, held out "
           "%.1f nm\n", 1e9 * l1.info.misfit_rms, 1e9 * l1.heldout_misfit_rms, 1e9 * l1.info.truth_rms,
           1e9 * l3.info.misfit_rms, 1e9 * l3.heldout_misfit_rms);
    assert_int_equal(l3.nslopes, l1.nslopes);
    assert_true(l3.info.nslopes_seen == 3 * l1.info.nslopes_seen);
    assert_true(l3.info.misfit_rms < 0.99 * l1.info.misfit_rms); /* more inputs, the same frames */
    assert_int_equal(l3.nheldout, 3);
    assert_true(l3.heldout_misfit_rms > l1.heldout_misfit_rms && l3.heldout_worst >= 1);
    const double spread_other = l3.wind_spread;
    printf("test_runs: other winds: %zu training winds, the farthest %.4f subapertures per frame from their mean\n",
           l3.nwind, spread_other);
    assert_int_equal(l3.nwind, 3);
    assert_int_equal(l1.nwind, 0); /* per frame: not measured */

    /* Learned on loops of the test data's own conditions (other seeds): on a held-out loop of
     * them the space-time map misses the residual by less than the per-frame one. */
    const char *same[3] = {p("learn_s1"), p("learn_s2"), p("learn_s3")};
    for (int k = 0; k < 3; k++) {
        char seed[32];
        snprintf(seed, sizeof seed, "seed=%d", 31 + k);
        const char *kv[] = {"layer_speed=30,40", "vib_amp=0.6", "jitter_amp=0.15", seed};
        simulate_truth(same[k], kv, 4);
    }
    lo.dirs = same;
    lo.no_heldout = 1;
    lo.nlags = 0;
    lo.out = p("recon_s1.fits");
    assert_ok(swfs_learn_run(&lo, &l1));
    lo.nlags = 3;
    lo.out = p("recon_s3.fits");
    assert_ok(swfs_learn_run(&lo, &l3));
    printf("test_runs: the data's conditions: %zu training winds (%.4f, %.4f), the farthest %.4f from their mean\n",
           l3.nwind, l3.wind_vx, l3.wind_vy, l3.wind_spread);
    assert_int_equal(l3.nwind, 3);
    assert_true(l3.wind_spread < 0.25 * spread_other);
    swfs_recon *wl = NULL, *wp = NULL;
    assert_ok(swfs_recon_read(p("recon_s3.fits"), &wl));
    assert_ok(swfs_recon_read(p("recon_s1.fits"), &wp));
    assert_int_equal(wl->nlags, 3);
    double t_rms = 0;
    const double e3 = recon_error(wl, p("learn_held"), &t_rms), e1 = recon_error(wp, p("learn_held"), &t_rms);
    printf("test_runs: the data's own conditions, on a held-out loop per frame: space-time %.1f nm, per frame %.1f nm "
           "(residual %.1f nm)\n", 1e9 * e3, 1e9 * e1, 1e9 * t_rms);
    assert_true(e3 < 0.97 * e1);
    swfs_recon_free(wl);
    swfs_recon_free(wp);

    /* the whole path with each */
    double e_path[2];
    const char *maps[2] = {"recon_s1.fits", "recon_s3.fits"};
    swfs_real *ncp = NULL;
    assert_ok(swfs_fits_read_real(p("truth.fits"), "NCP", &ncp, NULL));
    for (int k = 0; k < 2; k++) {
        e_path[k] = given_path_error(maps[k], "lrn", ncp, &spr, &er);
        swfs_halo_free(er.halo);
        if (k) { /* the map's training wind against the test data's own, at the largest lag */
            printf("test_runs: space-time map: trained at (%.4f, %.4f), the data at (%.4f, %.4f) subapertures per frame: "
                   "%.3f subapertures apart at lag 4 (layers: the data %zu, the loops %zu)\n", spr.st_train_vx,
                   spr.st_train_vy, spr.st_obs_vx, spr.st_obs_vy, spr.st_mismatch, spr.st_obs_nlayers,
                   spr.st_train_nlayers);
            assert_true(spr.st_found && spr.st_mismatch < SWFS_SPACETIME_MISMATCH_WARN);
            assert_int_equal(spr.st_train_nlayers, l3.nwlayers);
            /* its lags run on across the test data's file boundaries, which continue each other */
            printf("test_runs: the lags across %zu file boundaries, clamped at %zu\n", spr.st_edges_joined,
                   spr.st_edges_clamped);
            assert_true(spr.st_edges_joined >= 1 && spr.st_edges_clamped == 0);
            assert_true(spr.st_obs_nlayers >= 1 && l3.nwlayers >= 1);
            printf("test_runs: its slopes' correlation at lag 4: the data %.3f, the loops %.3f +- %.3f\n",
                   spr.st_corr_obs[1], spr.st_corr_train[1], spr.st_corr_spread[1]);
            assert_true(spr.st_corr_worst == 1 || spr.st_corr_worst == 2);
            assert_false(spr.st_corr_excess > 0);
        }
    }
    printf("test_runs: NCP error, maps learned at the data's conditions: per frame %.1f nm, space-time %.1f nm\n",
           1e9 * e_path[0], 1e9 * e_path[1]);
    assert_true(e_path[1] > 0 && e_path[1] < 1.1 * e_path[0]);
    swfs_real_free(ncp);

    /* Learned on one loop of faster winds (45 and 55 m/s): speckles sees both the wind and the
     * slopes' correlation apart from the data's. */
    lo.dirs = tdir + 2;
    lo.ndirs = 1;
    lo.out = p("recon_fast3.fits");
    assert_ok(swfs_learn_run(&lo, &l3));
    swfs_speckles_run_options spf;
    given_recon_options(&spf, p("recon_fast3.fits"), p("speckles_fast3.fits"));
    assert_ok(swfs_speckles_run(&spf, &spr));
    printf("test_runs: a map of faster winds: %.3f subapertures apart at lag 4; slopes' correlation at lag 4 the data "
           "%.3f, the loop %.3f\n", spr.st_mismatch, spr.st_corr_obs[1], spr.st_corr_train[1]);
    assert_true(spr.st_found && spr.st_mismatch > 0.15); /* 0.001 for the loops of its own conditions */
    assert_true(spr.st_corr_excess > 0 && spr.st_corr_obs[1] > spr.st_corr_train[1]);

    /* stream from files with the space-time map learned at the data's conditions: each
     * batch's slopes stacked at the lags, across the same file boundaries as speckles, in
     * batches of 17 camera frames; the halo of speckles + estimate with the same map */
    swfs_speckles_run_options sps;
    given_recon_options(&sps, p("recon_s3.fits"), p("speckles_s3.fits"));
    speckles_estimate_with(&sps, p("sci_s3.fits"), p("halo_s3.fits"), &spr, &er);
    swfs_stream_run_options so;
    stream_file_options(&so, p("recon_s3.fits"), p("halo_stream_st.fits"));
    so.batch = 17;
    so.stream.static_mode = SWFS_STATIC_NONE; /* the data-set mean is removed exactly either way */
    swfs_stream_run_result sr;
    assert_ok(swfs_stream_run_files(&so, &sr));
    assert_int_equal(sr.info.nlags, 3);
    assert_true(sr.st_lags[0] == 0 && sr.st_lags[1] == -4 && sr.st_lags[2] == 4);
    printf("test_runs: stream with the space-time map: lags across %zu file boundaries (speckles %zu), clamped at %zu\n",
           sr.st_edges_joined, spr.st_edges_joined, sr.st_edges_clamped);
    assert_true(sr.st_edges_joined >= 1 && sr.st_edges_joined == spr.st_edges_joined && sr.st_edges_clamped == 0);
    swfs_halo *hst = NULL;
    const double dd = stream_halo_diff(p("halo_stream_st.fits"), er.halo, &hst);
    printf("test_runs: stream vs speckles + estimate, space-time map: max |dPsi| / peak = %.2g\n", dd);
    assert_true(dd < 1e-4); /* the speckle cube is stored in single precision; the stream keeps double */
    swfs_halo_free(hst);
    swfs_halo_free(er.halo);
    swfs_real *cube = NULL;
    assert_ok(swfs_fits_read_real(p("recon_st3.fits"), NULL, &cube, NULL));
    swfs_fits_out *fo = NULL;
    assert_ok(swfs_fits_out_create(&fo, p("recon_nolags.fits")));
    assert_ok(swfs_fits_out_real(fo, NULL, cube, -64));
    assert_ok(swfs_fits_out_commit(fo));
    swfs_real_free(cube);
    assert_int_equal(swfs_recon_read(p("recon_nolags.fits"), &w), SWFS_ERR_FORMAT);
    printf("test_runs: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "NLAGS"));
    const long nozero[2] = {5, 10};
    lo.dirs = tdir;
    lo.lags = nozero;
    lo.nlags = 2;
    lo.out = p("recon_bad_lags.fits");
    assert_refused(swfs_learn_run(&lo, &l3), "learn, no lag 0", "no lag 0", lo.out);
    lo.lags = lags;
    lo.nlags = 3;
    lo.modal = 1;
    assert_refused(swfs_learn_run(&lo, &l3), "learn, lags and modal", "--modal", lo.out);
}

/* The options checks every caller of the runs gets (run.h, live.h), before any file is
 * opened: each value out of range or option out of place is refused with the message the
 * command line prints, and the run writes nothing; the defaults with their inputs pass. */
static void test_options_checks(void **state)
{
    (void)state;
    swfs_speckles_run_options sp;
    swfs_speckles_run_result spr;
    static const char *pattern[] = {
        "--teach-loops must be 2..64, got 1", "--batch must be 1..100000, got 200000", "--threads must be 1..64, got 0",
        "--rcond and --modes go with --recon svd", "--rcond must be in [0, 1), got 1", "--slope-noise goes with --recon vk",
        "--recon-scale goes with --recon W.fits", "--teach-work, --teach-seed, --teach-again", "--wfs-hz goes with --wfs-rate",
        "--match pairs camera frames", "--vk-l0 must be an outer scale", "takes no --actuators",
        "needs TIMING.txt", "--teach-again and --teach-set go with --recon teach", "teach_again must be 0 or 1, got 2",
        "--teach-max-loops must be --teach-loops (12) to 64", "--teach-max-loops and --teach-keep-loops go with",
        "--teach-set go with --recon teach", "--teach-set: unknown setting 'bogus_key'", "--teach-set takes key=value",
        "--teach-set: time-series parameter dm_coupling=1.5: must be in [0, 1)",
        "--mean-loop teach goes with the linear model", "--mean-teach-loops must be 2..16",
        "--mean-loop takes loops' folders or teach, not both",
        "a --control map is its own file, and without either there is no map",
        "loops_map must be 0, 1 or SWFS_LOOPS_MAP_AUTO (-1), got 3",
        "--loops-map choose goes with the linear model's --imat (the map it is chosen against) and mean loops",
        "--mean-teach-max-loops must be --mean-teach-loops (4)..16, got 3",
        "--mean-teach-max-loops must be --mean-teach-loops (4)..16, got 17",
    };
    const char *two[2] = {"loop_a", "loop_b"};
    const char *tk_ok[1] = {"dm_coupling=0.15"}, *tk_bogus[1] = {"bogus_key=1"}, *tk_noeq[1] = {"dm_coupling"},
               *tk_range[1] = {"dm_coupling=1.5"};
    const size_t npat = sizeof pattern / sizeof pattern[0];
    const char *min[1] = {"in.fits"}, *mout[1] = {"out_match.fits"};
    for (size_t k = 0; k <= npat; k++) {
        swfs_speckles_run_options_default(&sp);
        sp.timing = p("checks_timing.txt");
        sp.science = p("checks_science.fits");
        sp.actuators = p("checks_act.fits");
        sp.out = p("checks_speckles.fits");
        switch (k) {
        case 0: sp.teach_loops = 1; break;
        case 1: sp.batch = 200000; break;
        case 2: sp.pipe.threads = 0; break;
        case 3: sp.pipe.recon = SWFS_RECON_VK; sp.pipe.max_modes = 20; break;
        case 4: sp.pipe.recon = SWFS_RECON_SVD; sp.pipe.rcond = 1; break;
        case 5: sp.pipe.slope_noise = 0.1; break;
        case 6: sp.pipe.recon_scale = -2; break;
        case 7: sp.pipe.recon = SWFS_RECON_MAP; sp.teach_seed = 7; break;
        case 8: sp.wfs_hz = 1000; break;
        case 9: sp.pipe.wfs_rate = 1; sp.match_in = min; sp.match_out = mout; sp.nmatch = 1; break;
        case 10: sp.pipe.recon = SWFS_RECON_VK; sp.pipe.vk_l0 = NAN; break;
        case 11: sp.lin.basis = p("checks_basis.fits"); break;
        case 12: sp.out = NULL; break;
        case 13: sp.pipe.recon = SWFS_RECON_VK; sp.teach_again = 1; break;
        case 14: sp.teach_again = 2; break;
        case 15: sp.teach_max_loops = 8; break;
        case 16: sp.pipe.recon = SWFS_RECON_VK; sp.teach_max_loops = 24; break;
        case 17: sp.pipe.recon = SWFS_RECON_VK; sp.teach_keys = tk_ok; sp.nteach_keys = 1; break;
        case 18: sp.teach_keys = tk_bogus; sp.nteach_keys = 1; break;
        case 19: sp.teach_keys = tk_noeq; sp.nteach_keys = 1; break;
        case 20: sp.teach_keys = tk_range; sp.nteach_keys = 1; break;
        case 21: sp.mean_teach = 1; break;
        case 22: sp.actuators = NULL; sp.lin.basis = p("checks_basis.fits"); sp.mean_teach = 1; sp.mean_teach_loops = 1; break;
        case 23:
            sp.actuators = NULL;
            sp.lin.basis = p("checks_basis.fits");
            sp.mean_teach = 1;
            sp.mean_loops = two;
            sp.nmean_loops = 2;
            break;
        case 24: sp.actuators = NULL; sp.lin.basis = p("checks_basis.fits"); sp.write_recon = p("checks_w.fits"); break;
        case 25: sp.loops_map = 3; break;
        case 26: /* loops but no interaction matrix to choose against */
            sp.actuators = NULL;
            sp.lin.basis = p("checks_basis.fits");
            sp.lin.control = p("checks_recon.fits");
            sp.mean_loops = two;
            sp.nmean_loops = 2;
            sp.loops_map = 1;
            break;
        case 27: sp.mean_teach_max_loops = 3; break; /* below the first loops */
        case 28: sp.mean_teach_max_loops = 17; break; /* beyond SWFS_MEAN_TEACH_MAX */
        default: sp.teach_keys = tk_ok; sp.nteach_keys = 1; break; /* the defaults, and a key teach takes */
        }
        if (k == npat) {
            assert_int_equal(swfs_speckles_run_options_check(&sp), 0);
            continue;
        }
        assert_refused(swfs_speckles_run(&sp, &spr), "speckles options", pattern[k], p("checks_speckles.fits"));
    }

    swfs_stream_run_options so;
    swfs_stream_run_result sr;
    for (int k = 0; k <= 5; k++) {
        swfs_stream_run_options_default(&so);
        so.timing = p("checks_timing.txt");
        so.science = p("checks_science.fits");
        so.recon = p("checks_recon.fits");
        so.actuators = p("checks_act.fits");
        so.out = p("checks_halo.fits");
        static const char *spat[] = {"--batch must be 1..100000, got 0", "--read-noise must be >= 0", "--clock and --exptime go with --wfs-log",
                                     "--g-smooth must be >= 0", "--static FILE: no file given"};
        switch (k) {
        case 0: so.batch = 0; break;
        case 1: so.read_noise = -1; break;
        case 2: so.exptime = 0.01; break;
        case 3: so.g_smooth_lod = INFINITY; break;
        case 4: so.stream.static_mode = SWFS_STATIC_GIVEN; break;
        default: break;
        }
        if (k == 5) assert_int_equal(swfs_stream_run_options_check(&so), 0);
        else assert_refused(swfs_stream_run_files(&so, &sr), "stream options", spat[k], so.out);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sync_speckles_estimate),
        cmocka_unit_test(test_sync_ratio_from_log),
        cmocka_unit_test(test_given_reconstructor),
        cmocka_unit_test(test_zonal_loop),
        cmocka_unit_test(test_gauss_dm_loop),
        cmocka_unit_test(test_rim_coverage),
        cmocka_unit_test(test_stream_equals_speckles),
        cmocka_unit_test(test_stream_batches),
        cmocka_unit_test(test_sync_cube_at_file_end),
        cmocka_unit_test(test_sync_timestamped_files),
        cmocka_unit_test(test_sync_files_shorter_than_cube),
        cmocka_unit_test(test_sync_unreadable_file),
        cmocka_unit_test(test_camera_light_same_slopes),
        cmocka_unit_test(test_learn_reconstructor),
        cmocka_unit_test(test_stopped_by_progress),
        cmocka_unit_test(test_learn_output_points),
        cmocka_unit_test(test_spacetime_reconstructor),
        cmocka_unit_test(test_options_checks),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}

/* `specklewfs replay` -> `specklewfs live` through shared-memory streams on this machine:
 * with nothing dropped live's halo equals stream's on the same files (and, on milk logs
 * replayed with their own stamps, jitter and drops, `stream --wfs-log`'s); with injected
 * drops the drops are counted exactly and only complete exposures are used; a writer
 * restart is survived; SIGINT ends the run with final products and checkpoint; bad
 * streams (version, size, type, a stream that disappears) give clear errors and leave
 * no partial product and an intact checkpoint. */
#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/engine.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/science.h"
#include "specklewfs/shm.h"
#include "specklewfs/speckles.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <spawn.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

extern char **environ;

#define NPUP 24
#define NF 14
#define NSUB 4
#define NSL (2 * NSUB * NSUB)
#define NCAM 30
#define NWFS 400
#define RATIO 3.37
#define DIAM 6.5
#define LAMBDA 3.8e-6
#define PIXSCALE 0.5

static char dir[1024], shm[1100];
static const double start[2] = {10.25, 150.5};

static const char *in_dir(const char *name)
{
    static char buf[8][1200];
    static int k = 0;
    char *b = buf[k++ % 8];
    snprintf(b, sizeof buf[0], "%s/%s", dir, name);
    return b;
}

/* Two cubes of NCAM camera frames over one telemetry file of NWFS frames (WFSRATE 527),
 * science = |Psi + 0.8 psi|^2 + noise with psi from the engine, so the estimate is sound. */
static void make_data(void)
{
    swfs_rng r;
    swfs_rng_seed(&r, 77);
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = LAMBDA;
    g.teldiam = DIAM;
    g.obscur = 0.1;
    g.pixscale = PIXSCALE;
    g.pupdx = DIAM / (NPUP - 1.0);
    g.pupn = NPUP;
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, 1.2, 0.6, &xy, &nact));
    swfs_recon rec = {.nact = nact, .nslopes = NSL, .W = malloc(nact * NSL * sizeof(double))};
    assert_non_null(rec.W);
    /* slopes of a physical size (~0.3 rad of phase per subaperture; their mean, the tilt, a
     * fraction of lambda/D: the exposure tip-tilt model takes it as the image's motion) and a
     * random reconstructor giving phases of order 1 rad */
    const double s1 = 0.3 * LAMBDA / (2 * M_PI) / (DIAM / NSUB);
    for (size_t k = 0; k < nact * NSL; k++) rec.W[k] = LAMBDA / (2 * M_PI) * 0.3 * swfs_rng_normal(&r) / s1;
    assert_ok(swfs_recon_write(&rec, in_dir("recon.fits")));
    /* a space-time map of lags 0, -2 and 3: the same map at lag 0, a third of another random
     * one at each other lag */
    swfs_recon st = {.nact = nact, .nslopes = 3 * NSL, .W = calloc(3 * nact * NSL, sizeof(double)), .nlags = 3,
                     .lags = {0, -2, 3}};
    assert_non_null(st.W);
    for (size_t a = 0; a < nact; a++) {
        memcpy(st.W + a * 3 * NSL, rec.W + a * NSL, NSL * sizeof(double));
        for (size_t i = NSL; i < 3 * NSL; i++) st.W[a * 3 * NSL + i] = rec.W[a * NSL + i % NSL] * 0.3 * swfs_rng_normal(&r);
    }
    assert_ok(swfs_recon_write(&st, in_dir("recon_st.fits")));
    free(st.W);
    assert_ok(swfs_actuators_write(xy, nact, in_dir("act.fits")));
    swfs_real *sl = swfs_real_alloc(NSL, NWFS, 1);
    assert_non_null(sl);
    for (size_t k = 0; k < NWFS; k++)
        for (size_t i = 0; i < NSL; i++) sl->data[k * NSL + i] = s1 * (swfs_rng_normal(&r) + (i < NSL / 2 ? 0.5 : -0.2));
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, in_dir("slopes.fits")));
    assert_ok(swfs_fits_out_real(o, NULL, sl, -64));
    assert_ok(swfs_fits_out_key_double(o, "WFSRATE", 527.0, "[Hz]"));
    assert_ok(swfs_fits_out_commit(o));
    swfs_timing t;
    memset(&t, 0, sizeof t);
    swfs_timing_cube c[2];
    memset(c, 0, sizeof c);
    t.ratio = RATIO;
    t.ncubes = 2;
    t.cubes = c;
    t.fit.sign_x = t.fit.sign_y = 1;
    for (int k = 0; k < 2; k++) {
        snprintf(c[k].camera, sizeof c[k].camera, "raw_%d.fits", k);
        snprintf(c[k].slopes, sizeof c[k].slopes, "slopes.fits");
        c[k].first = (size_t)k * NCAM;
        c[k].nframes = NCAM;
        c[k].start = start[k];
        c[k].status = SWFS_CUBE_OK;
    }
    assert_ok(swfs_timing_write(in_dir("timing.txt"), &t));

    double mask[NPUP * NPUP];
    assert_ok(swfs_aperture_make(mask, NPUP, g.pupdx, DIAM, g.obscur, 0, 0.0));
    swfs_speckle_model *model = NULL;
    assert_ok(swfs_speckle_model_create(&model, xy, nact, mask, NPUP, g.pupdx, DIAM, NSUB, &rec, 0.0, 0, 1));
    swfs_engine_config ec = {NSL, nact, NPUP, NF, NF, PIXSCALE * g.pupdx / DIAM, LAMBDA, model->recon->W, model->T, mask,
                             0, 1};
    swfs_engine *e = swfs_engine_create(&ec);
    assert_non_null(e);
    swfs_real *sci = swfs_real_alloc(NF, NF, 2 * NCAM);
    double complex *h = malloc(NCAM * NF * NF * sizeof *h);
    swfs_exposure sched[NCAM];
    assert_true(sci && h);
    for (int k = 0; k < 2; k++) {
        const size_t base = (size_t)floor(start[k]);
        swfs_engine_schedule(RATIO, start[k] - (double)base, NCAM, sched);
        assert_ok(swfs_engine_process(e, sl->data + base * NSL, NWFS - base, sched, NCAM, h));
        for (size_t j = 0; j < NCAM; j++) {
            double *frame = swfs_real_frame(sci, (size_t)k * NCAM + j);
            for (size_t p = 0; p < NF * NF; p++) {
                const double complex Psi = 30.0 * cexp(I * 0.4 * (double)p) / (1.0 + 0.05 * (double)p);
                const double complex tot = Psi + 0.8 * h[j * NF * NF + p];
                frame[p] = creal(tot * conj(tot)) + 2.0 * swfs_rng_normal(&r);
            }
        }
    }
    assert_ok(swfs_fits_out_create(&o, in_dir("sci.fits")));
    assert_ok(swfs_fits_out_set_stamp(o, &g, NULL, 0));
    assert_ok(swfs_fits_out_real(o, NULL, sci, -64));
    assert_ok(swfs_fits_out_key_double(o, "RDNOISE", 2.0, "[counts]"));
    assert_ok(swfs_fits_out_commit(o));
    free(h);
    free(rec.W);
    free(xy);
    swfs_real_free(sci);
    swfs_real_free(sl);
    swfs_engine_free(e);
    swfs_speckle_model_free(model);
}

/* Start `specklewfs ARGS` in dir with output to dir/LOG, with this process's kernels; returns the PID. */
static pid_t spawn_cli(const char *args, const char *log)
{
    char cmd[8192];
    snprintf(cmd, sizeof cmd, "cd '%s' && exec %s %s > '%s' 2>&1", dir, SWFS_CLI_BIN, args, log);
    char *argv[] = {"sh", "-c", cmd, NULL};
    test_cli_same_kernels();
    pid_t pid;
    assert_int_equal(posix_spawn(&pid, "/bin/sh", NULL, NULL, argv, environ), 0);
    return pid;
}

static int wait_cli(pid_t pid)
{
    int st = 0;
    assert_int_equal(waitpid(pid, &st, 0), pid);
    return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static void slurp(const char *name, char *out, size_t cap)
{
    FILE *f = fopen(in_dir(name), "r");
    out[0] = '\0';
    if (!f) return;
    const size_t n = fread(out, 1, cap - 1, f);
    out[n] = '\0';
    fclose(f);
}

/* The number after `key` in text (-1 if absent). */
static long number_after(const char *text, const char *key)
{
    const char *p = strstr(text, key);
    return p ? strtol(p + strlen(key), NULL, 10) : -1;
}

static double halo_diff(const char *a, const char *b, double *peak)
{
    swfs_halo *ha = NULL, *hb = NULL;
    assert_ok(swfs_halo_read(in_dir(a), &ha, NULL));
    assert_ok(swfs_halo_read(in_dir(b), &hb, NULL));
    double d = 0, m = 0;
    assert_int_equal(ha->halo->nx * ha->halo->ny, hb->halo->nx * hb->halo->ny);
    for (size_t p = 0; p < ha->halo->nx * ha->halo->ny; p++) {
        d = fmax(d, cabs(ha->halo->data[p] - hb->halo->data[p]));
        m = fmax(m, cabs(ha->halo->data[p]));
    }
    swfs_halo_free(ha);
    swfs_halo_free(hb);
    *peak = m;
    return d;
}

static const char *common = "--geom sci.fits --recon recon.fits --actuators act.fits";
static const char *live_common = "--geom sci.fits --recon recon.fits --actuators act.fits"; /* replay_live's */

/* live in the background, replay in the foreground; returns live's exit status and
 * leaves both outputs in out. */
static int replay_live(const char *live_args, const char *replay_args, char *out, size_t cap, int *replay_rc)
{
    char args[4096];
    snprintf(args, sizeof args, "live --shm-dir %s --wfs w --camera c %s %s", shm, live_common, live_args);
    const pid_t pid = spawn_cli(args, "live.log");
    snprintf(args, sizeof args, "replay --shm-dir %s --wfs-name w --camera-name c --timing timing.txt --science sci.fits "
             "--wait-reader 30 %s", shm, replay_args);
    char rout[4096];
    *replay_rc = test_run_cli(dir, args, rout, sizeof rout);
    const int rc = wait_cli(pid);
    char lout[8192];
    slurp("live.log", lout, sizeof lout);
    snprintf(out, cap, "%s%s", rout, lout);
    print_message("%s", out);
    return rc;
}

static void setup_dirs(void)
{
    snprintf(dir, sizeof dir, "%s", test_path("cli_live"));
    snprintf(shm, sizeof shm, "%s/shm", dir);
    char mk[2400];
    snprintf(mk, sizeof mk, "rm -rf '%s' && mkdir -p '%s'", dir, shm);
    assert_int_equal(system(mk), 0);
}

static void test_equal_to_stream(void **state)
{
    (void)state;
    setup_dirs();
    make_data();
    char out[16384];
    int rrc;
    assert_int_equal(test_run_cli(dir, "stream --timing timing.txt --science sci.fits --recon recon.fits --actuators "
                                       "act.fits --batch 8 -o halo_stream.fits", out, sizeof out), 0);
    /* At 1 kHz the stamps are whole nanoseconds: the same batches, the same weights. */
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_live.fits --checkpoint ck.fits",
                                 "--depth 64 --remove --wfs-rate 1000", out, sizeof out, &rrc), 0);
    assert_int_equal(rrc, 0);
    assert_int_equal(number_after(out, "halo_live.fits: "), 2 * NCAM);
    assert_non_null(strstr(out, "(0 dropped, 0 restarts)"));
    double peak, d = halo_diff("halo_stream.fits", "halo_live.fits", &peak);
    print_message("live vs stream, 1 kHz: max |HALO difference| %.3g of the peak\n", d / peak);
    assert_true(d <= 1e-8 * peak);
    swfs_accum *a = NULL;
    assert_ok(swfs_accum_load(in_dir("ck.fits"), &a, NULL));
    assert_int_equal(a->frames, 2 * NCAM);
    swfs_accum_free(a);

    /* At the data's own 527 Hz a period is 1897533.2 ns: stamps rounded to the nanosecond
     * move the exposure edges by up to 2.6e-7 WFS frames (fitted clocks shrink that). */
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_live527.fits", "--depth 64 --remove",
                                 out, sizeof out, &rrc), 0);
    d = halo_diff("halo_stream.fits", "halo_live527.fits", &peak);
    print_message("live vs stream, 527 Hz: max |HALO difference| %.3g of the peak\n", d / peak);
    assert_true(d <= 2e-7 * peak);

    /* Writer restarts after WFS rows 130, 260 and 390 (the first between the cubes, the
     * others after the last exposure): survived, every exposure still used and (exact
     * stamps again) the same halo. The camera restart shows with its next frame. */
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_rs.fits",
                                 "--depth 64 --remove --wfs-rate 1000 --restart-after 130", out, sizeof out, &rrc), 0);
    assert_int_equal(rrc, 0);
    assert_non_null(strstr(out, "3 restarts"));
    assert_non_null(strstr(out, "(0 dropped, 3 restarts) and 60 camera frames (0 dropped, 1 restarts)"));
    assert_int_equal(number_after(out, "halo_rs.fits: "), 2 * NCAM);
    d = halo_diff("halo_stream.fits", "halo_rs.fits", &peak);
    print_message("live vs stream across a writer restart: %.3g of the peak\n", d / peak);
    assert_true(d <= 1e-8 * peak);

    /* Restarts every 60 rows, three inside cubes: the exposures that span them are
     * skipped, the run goes on. */
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_rs2.fits",
                                 "--depth 64 --remove --wfs-rate 1000 --restart-after 60", out, sizeof out, &rrc), 0);
    const long used = number_after(out, "halo_rs2.fits: ");
    assert_true(used >= 2 * NCAM - 8 && used < 2 * NCAM);

    /* A space-time map (lags 0, -2, 3): live stacks each batch's rows as its frames arrive,
     * waiting for the frames 3 rows on; stream stacks them from the file: the same halo. */
    assert_int_equal(test_run_cli(dir, "stream --timing timing.txt --science sci.fits --recon recon_st.fits --actuators "
                                       "act.fits --batch 8 -o halo_stream_st.fits", out, sizeof out), 0);
    live_common = "--geom sci.fits --recon recon_st.fits --actuators act.fits";
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_live_st.fits",
                                 "--depth 64 --remove --wfs-rate 1000", out, sizeof out, &rrc), 0);
    live_common = common;
    assert_int_equal(rrc, 0);
    assert_int_equal(number_after(out, "halo_live_st.fits: "), 2 * NCAM);
    assert_non_null(strstr(out, "space-time reconstructor of 3 lags (0,-2,3 WFS frames): each batch waited for the WFS "
                                "frames 3 after its last"));
    d = halo_diff("halo_stream_st.fits", "halo_live_st.fits", &peak);
    const double dp = halo_diff("halo_stream.fits", "halo_stream_st.fits", &peak);
    print_message("live vs stream, space-time map: max |HALO difference| %.3g of the peak (the per-frame map's halo "
                  "%.3g away)\n", d / peak, dp / peak);
    assert_true(d <= 1e-8 * peak && dp > 1e-3 * peak);
}

/* stream --wfs-log on the simulation's milk logs into halo_stream_milk<tag>.fits, and live fed
 * by replay --wfs-log of the same logs into halo_live_milk<tag>.fits, with the map options
 * `model`; live's log in out. */
static void milk_stream_and_live(const char *model, const char *tag, double exptime, char *out, size_t cap)
{
    char args[4096];
    snprintf(args, sizeof args, "stream --wfs-log sim/milk/wfs --science sci.fits %s -o halo_stream_milk%s.fits", model,
             tag);
    assert_int_equal(test_run_cli(dir, args, out, cap), 0);
    snprintf(args, sizeof args, "live --shm-dir %s --wfs w --camera c --geom sci.fits %s --exptime %.17g --max-wait 60 "
             "--idle-exit 0.5 -o halo_live_milk%s.fits", shm, model, exptime, tag);
    const pid_t pid = spawn_cli(args, "live.log");
    snprintf(args, sizeof args, "replay --shm-dir %s --wfs-name w --camera-name c --wfs-log sim/milk/wfs --science "
             "sci.fits --speed 3 --depth 64 --wait-reader 30 --remove", shm);
    const int rrc = test_run_cli(dir, args, out, cap);
    print_message("%s", out);
    assert_int_equal(rrc, 0);
    assert_int_equal(wait_cli(pid), 0);
    slurp("live.log", out, cap);
    print_message("%s", out);
}

/* Logged telemetry: the time-series simulation's milk logs (3 us stamp jitter, a camera clock
 * that drifts, dropped frames, several files per stream) at the data's 527 Hz, published by
 * `replay --wfs-log` with their own stamps: live's halo equals `stream --wfs-log`'s on the
 * same logs, the drops counted as the logs have them. */
static void test_equal_to_stream_milk(void **state)
{
    (void)state;
    setup_dirs();
    char out[16384];
    assert_int_equal(test_run_cli(dir, "simulate mode=timeseries --quiet -o sim pupn=66 pupdx=0.1 screen_n=1024 "
                                       "ncubes=2 cube_frames=40 cube_gap=100 seed=2 milk=1 milk_file_frames=400",
                                  out, sizeof out), 0);
    assert_int_equal(test_run_cli(dir, "reduce sim/milk/cam/*.fits --dark sim/dark.fits --flat sim/flat.fits -o sci.fits", out,
                                  sizeof out), 0);
    uint64_t *cnt = NULL;
    int64_t *st = NULL;
    size_t n = 0;
    double exptime = 0;
    assert_ok(swfs_science_stamps_read(in_dir("sci.fits"), &cnt, &st, &n, &exptime));
    assert_true(n == 80 - 3 && exptime > 0); /* 3 camera frames lost in the log */
    free(cnt);
    free(st);
    milk_stream_and_live("--recon sim/recon_ao.fits --actuators sim/actuators.fits --batch 8", "", exptime, out,
                         sizeof out);
    assert_non_null(strstr(out, "(5 dropped, 0 restarts) and 77 camera frames (3 dropped, 0 restarts)"));
    double peak, d = halo_diff("halo_stream_milk.fits", "halo_live_milk.fits", &peak);
    print_message("live vs stream --wfs-log on the same milk logs, 527 Hz: max |HALO difference| %.3g of the peak\n",
                  d / peak);
    assert_true(d <= 1e-8 * peak);

    /* A space-time map (lags 0, -3, 3; the loop's map at lag 0, a fifth of it at the others):
     * the milk source's batches stacked as live's, across the logs' dropped frames */
    swfs_recon *w = NULL;
    assert_ok(swfs_recon_read(in_dir("sim/recon_ao.fits"), &w));
    const size_t ns = w->nslopes;
    swfs_recon stm = {.nact = w->nact, .nslopes = 3 * ns, .W = calloc(3 * ns * w->nact, sizeof(double)), .nlags = 3,
                      .lags = {0, -3, 3}};
    assert_non_null(stm.W);
    for (size_t a = 0; a < w->nact; a++)
        for (size_t i = 0; i < 3 * ns; i++) stm.W[a * 3 * ns + i] = (i < ns ? 1.0 : 0.2) * w->W[a * ns + i % ns];
    assert_ok(swfs_recon_write(&stm, in_dir("recon_st_milk.fits")));
    free(stm.W);
    swfs_recon_free(w);
    milk_stream_and_live("--recon recon_st_milk.fits --actuators sim/actuators.fits --batch 8", "_st", exptime, out,
                         sizeof out);
    d = halo_diff("halo_stream_milk_st.fits", "halo_live_milk_st.fits", &peak);
    const double dp = halo_diff("halo_stream_milk.fits", "halo_stream_milk_st.fits", &peak);
    print_message("live vs stream --wfs-log, space-time map: max |HALO difference| %.3g of the peak (the per-frame "
                  "map's %.3g away)\n", d / peak, dp / peak);
    assert_true(d <= 1e-8 * peak && dp > 1e-3 * peak);
}

/* The WFS rows and camera frames of the drop log. */
static void read_log(int *wfs_rows, size_t *nw, int *cam, size_t *nc)
{
    FILE *f = fopen(in_dir("drops.txt"), "r");
    assert_non_null(f);
    char line[256];
    *nw = *nc = 0;
    while (fgets(line, sizeof line, f)) {
        long a, b;
        if (sscanf(line, "wfs %ld", &a) == 1) wfs_rows[(*nw)++] = (int)a;
        else if (sscanf(line, "camera %ld %ld", &a, &b) == 2) cam[(*nc)++] = (int)(a * NCAM + b);
    }
    fclose(f);
}

static void test_drops(void **state)
{
    (void)state;
    char out[16384];
    int rrc;
    assert_int_equal(replay_live("--batch 8 --max-wait 60 --idle-exit 0.5 -o halo_drop.fits --checkpoint ckd.fits",
                                 "--depth 64 --remove --speed 2 --drop-wfs 0.03 --drop-camera 0.05 --seed 3 "
                                 "--drop-log drops.txt", out, sizeof out, &rrc), 0);
    assert_int_equal(rrc, 0);
    int rows[NWFS], cam[2 * NCAM];
    size_t nw, nc;
    read_log(rows, &nw, cam, &nc);
    assert_true(nw >= 3 && nc >= 1);
    char key[128];
    snprintf(key, sizeof key, "received %d WFS frames (%zu dropped", NWFS - (int)nw, nw);
    assert_non_null(strstr(out, key));
    snprintf(key, sizeof key, "and %d camera frames (%zu dropped", 2 * NCAM - (int)nc, nc);
    assert_non_null(strstr(out, key));
    /* The complete exposures: delivered camera frames none of whose WFS frames was lost. */
    size_t want = 0;
    for (int k = 0; k < 2; k++) {
        const size_t base = (size_t)floor(start[k]);
        swfs_exposure sched[NCAM];
        swfs_engine_schedule(RATIO, start[k] - (double)base, NCAM, sched);
        for (int j = 0; j < NCAM; j++) {
            int ok = 1;
            for (size_t q = 0; q < nc; q++) ok &= cam[q] != k * NCAM + j;
            const int f0 = (int)(base + sched[j].first), f1 = f0 + (int)sched[j].count;
            for (size_t q = 0; q < nw; q++) ok &= !(rows[q] >= f0 && rows[q] < f1);
            want += (size_t)ok;
        }
    }
    print_message("drops: %zu WFS, %zu camera; %zu complete exposures expected\n", nw, nc, want);
    assert_int_equal(number_after(out, "halo_drop.fits: "), (long)want);
    swfs_accum *a = NULL;
    assert_ok(swfs_accum_load(in_dir("ckd.fits"), &a, NULL));
    assert_int_equal(a->frames, want);
    swfs_accum_free(a);
}

/* DM offsets into a stream, as `dmoffsets` computes them from the pupil product. */
static void test_dm_offsets(void **state)
{
    (void)state;
    char out[16384];
    int rrc;
    assert_int_equal(replay_live("--batch 8 --idle-exit 0.5 -o halo_dm.fits --pupil-out pupil_dm.fits --dm-out dm "
                                 "--dm-final --dm-tiptilt --dm-gain 1",
                                 "--depth 64 --remove --speed 2", out, sizeof out, &rrc), 0);
    assert_non_null(strstr(out, "1 DM updates to dm"));
    assert_int_equal(test_run_cli(dir, "dmoffsets pupil_dm.fits --actuators act.fits -o off.fits", out, sizeof out), 0);
    swfs_real *off = NULL;
    assert_ok(swfs_fits_read_real(in_dir("off.fits"), "OFFSETS", &off, NULL));
    swfs_shm *dm = NULL;
    assert_ok(swfs_shm_open(&dm, shm, "dm"));
    const size_t nact = swfs_shm_frame_values(dm);
    assert_int_equal(nact, off->nx * off->ny);
    double *v = malloc(nact * sizeof *v);
    swfs_shm_frame fm;
    size_t n = 0;
    assert_ok(swfs_shm_read_latest(dm, v, &fm, &n));
    assert_int_equal(n, 1);
    double omax = 0, dmax = 0;
    for (size_t a = 0; a < nact; a++) {
        omax = fmax(omax, fabs(off->data[a]));
        dmax = fmax(dmax, fabs(v[a] - off->data[a]));
    }
    print_message("DM stream vs dmoffsets: largest difference %.3g m of %.3g m (float32 stream)\n", dmax, omax);
    assert_true(omax > 0 && dmax <= 1e-6 * omax);
    swfs_shm_close(dm, 0);
    /* A second run adds to what the stream holds, each step limited to 1 nm per actuator. */
    assert_int_equal(replay_live("--batch 8 --idle-exit 0.5 -o halo_dm2.fits --pupil-out pupil_dm2.fits --dm-out dm "
                                 "--dm-final --dm-tiptilt --dm-gain 1 --dm-max-step 1e-9",
                                 "--depth 64 --remove --speed 2", out, sizeof out, &rrc), 0);
    assert_ok(swfs_shm_open(&dm, shm, "dm"));
    double *v2 = malloc(nact * sizeof *v2);
    assert_ok(swfs_shm_read_latest(dm, v2, &fm, &n));
    double smax = 0;
    for (size_t a = 0; a < nact; a++) smax = fmax(smax, fabs(v2[a] - v[a]));
    print_message("second run: largest step %.4g m\n", smax);
    assert_close(smax, 1e-9, 1e-12); /* float32 of the total */
    swfs_shm_close(dm, 1);
    free(v);
    free(v2);
    swfs_real_free(off);
}

static int no_part_files(void)
{
    DIR *d = opendir(dir);
    assert_non_null(d);
    int ok = 1;
    struct dirent *e;
    while ((e = readdir(d)))
        if (strstr(e->d_name, ".part")) ok = 0;
    closedir(d);
    return ok;
}

static void test_signal_and_errors(void **state)
{
    (void)state;
    char out[16384], args[4096];
    /* SIGINT after the data: a clean end with the final products and checkpoint. */
    snprintf(args, sizeof args, "live --shm-dir %s --wfs w --camera c %s --batch 4 -o halo_int.fits --checkpoint cki.fits "
             "--pupil-out pupil_int.fits", shm, common);
    pid_t pid = spawn_cli(args, "live_int.log");
    snprintf(args, sizeof args, "replay --shm-dir %s --wfs-name w --camera-name c --timing timing.txt --science sci.fits "
             "--wait-reader 30 --depth 64 --speed 2", shm);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    struct timespec ts = {0, 300000000};
    nanosleep(&ts, NULL);
    assert_int_equal(kill(pid, SIGINT), 0);
    assert_int_equal(wait_cli(pid), 0);
    slurp("live_int.log", out, sizeof out);
    print_message("%s", out);
    assert_int_equal(number_after(out, "halo_int.fits: "), 2 * NCAM);
    swfs_accum *a = NULL;
    assert_ok(swfs_accum_load(in_dir("cki.fits"), &a, NULL));
    assert_int_equal(a->frames, 2 * NCAM);
    swfs_accum_free(a);
    assert_true(test_file_exists(in_dir("pupil_int.fits")));

    /* The streams disappear (replay --remove) and do not come back: an error naming the
     * stream; the checkpoint of the last update is intact, no partial file is left. */
    snprintf(args, sizeof args, "live --shm-dir %s --wfs w --camera c %s --batch 4 --every 20 --timeout 1 "
             "-o halo_gone.fits --checkpoint ckg.fits", shm, common);
    pid = spawn_cli(args, "live_gone.log");
    snprintf(args, sizeof args, "replay --shm-dir %s --wfs-name w --camera-name c --timing timing.txt --science sci.fits "
             "--wait-reader 30 --depth 64 --speed 2 --remove", shm);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    assert_int_equal(wait_cli(pid), 1);
    slurp("live_gone.log", out, sizeof out);
    print_message("%s", out);
    assert_non_null(strstr(out, "disappeared and did not come back"));
    assert_non_null(strstr(out, "stream 'w'") ? strstr(out, "stream 'w'") : strstr(out, "stream 'c'"));
    assert_ok(swfs_accum_load(in_dir("ckg.fits"), &a, NULL));
    assert_true(a->frames >= 20 && a->frames < 2 * NCAM); /* the last update's, as it was */
    swfs_accum_free(a);
    assert_true(test_file_exists(in_dir("halo_gone.fits")));
    assert_true(no_part_files());

    /* Streams of another version, size or type: refused by name, nothing written. */
    swfs_shm *w = NULL, *c = NULL;
    swfs_shm_shape ws = {SWFS_SHM_F32, NSL, 1, 1, 0, 0}, cs = {SWFS_SHM_F32, 10, 10, 1, 0, 0};
    assert_ok(swfs_shm_create(&w, shm, "bw", &ws));
    assert_ok(swfs_shm_create(&c, shm, "bc", &cs));
    snprintf(args, sizeof args, "live --shm-dir %s --wfs bw --camera bc %s --timeout 1 -o halo_bad.fits", shm, common);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 1);
    print_message("%s", out);
    assert_non_null(strstr(out, "bc.im.shm: frames of 10x10"));
    assert_non_null(strstr(out, "needs 14x14"));
    swfs_shm_close(c, 1);
    swfs_shm_shape ws2 = {SWFS_SHM_F32, NSL + 2, 1, 1, 0, 0}, cs2 = {SWFS_SHM_F32, NF, NF, 1, 0, 0};
    swfs_shm_close(w, 1);
    assert_ok(swfs_shm_create(&w, shm, "bw", &ws2));
    assert_ok(swfs_shm_create(&c, shm, "bc", &cs2));
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 1);
    print_message("%s", out);
    assert_non_null(strstr(out, "34 values per frame but the reconstructor expects 32 slopes"));
    swfs_shm_close(w, 0);
    char path[4200];
    assert_ok(swfs_shm_path(shm, "bw", path, sizeof path));
    FILE *f = fopen(path, "r+b");
    assert_non_null(f);
    fwrite("1.00", 1, 4, f); /* an ImageStreamIO 1.x stream */
    fclose(f);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 1);
    assert_non_null(strstr(out, "version '1.00'"));
    unlink(path);
    assert_ok(swfs_shm_create(&w, shm, "bw", &ws));
    f = fopen(path, "r+b");
    assert_non_null(f);
    const unsigned char cplx = 11;
    fseek(f, 136, SEEK_SET);
    fwrite(&cplx, 1, 1, f); /* complex float32 */
    fclose(f);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 1);
    assert_non_null(strstr(out, "complex float32"));
    swfs_shm_close(w, 1);
    swfs_shm_close(c, 1);
    /* A stream that never appears. */
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 1);
    print_message("%s", out);
    assert_non_null(strstr(out, "WFS stream 'bw'"));
    assert_false(test_file_exists(in_dir("halo_bad.fits")));
    assert_true(no_part_files());
    /* Usage. */
    assert_int_equal(test_run_cli(dir, "live --wfs w -o x.fits", out, sizeof out), 2);
    assert_int_equal(test_run_cli(dir, "replay --timing timing.txt", out, sizeof out), 2);
    assert_int_equal(test_run_cli(dir, "replay --timing timing.txt --science sci.fits --drop-wfs 1", out, sizeof out), 2);
}

/* Streams that go away after the data ended (no frame for `idle` seconds) end the data
 * cleanly however late the consumer asks for them: a live run far behind its streams (a
 * loaded machine) got "disappeared and did not come back" for streams whose every frame it
 * held. Where frames were still arriving within `idle`, the error stays. */
static void gone_after(double idle, double timeout, int expect_error)
{
    char d[1200];
    snprintf(d, sizeof d, "%s", test_path("cli_live_gone"));
    assert_int_equal(mkdir(d, 0777) == 0 || errno == EEXIST, 1);
    swfs_shm *w = NULL, *c = NULL;
    const swfs_shm_shape ws = {SWFS_SHM_F32, NSL, 1, 1, 0, 0}, cs = {SWFS_SHM_F32, NF, NF, 1, 0, 0};
    assert_ok(swfs_shm_create(&w, d, "gw", &ws));
    assert_ok(swfs_shm_create(&c, d, "gc", &cs));
    swfs_shm_source_options o;
    swfs_shm_source_options_default(&o);
    const char *wn[] = {"gw"};
    o.dir = d;
    o.wfs = wn;
    o.nwfs = 1;
    o.camera = "gc";
    o.idle = idle;
    o.timeout = timeout;
    o.sync.batch = 2;
    swfs_shm_source *src = NULL;
    assert_ok(swfs_shm_source_open(&src, &o));
    double wf[NSL] = {0}, cf[NF * NF] = {0};
    for (int k = 0; k < 12; k++) {
        wf[0] = k;
        assert_ok(swfs_shm_write(w, wf, swfs_shm_now_ns()));
        if (k % 3 == 2) assert_ok(swfs_shm_write(c, cf, swfs_shm_now_ns()));
        nanosleep(&(struct timespec){0, 2000000}, NULL);
    }
    nanosleep(&(struct timespec){0, 100000000}, NULL); /* the readers take the frames */
    swfs_shm_close(w, 1);
    swfs_shm_close(c, 1);
    /* the consumer behind by longer than idle + timeout */
    const double behind = idle + timeout + 0.5;
    nanosleep(&(struct timespec){(time_t)behind, (long)((behind - floor(behind)) * 1e9)}, NULL);
    swfs_batch b;
    int rc = SWFS_OK;
    size_t batches = 0;
    for (int guard = 0; guard < 100; guard++) {
        if ((rc = swfs_shm_source_next(src, &b)) || !b.nexp) break;
        batches++;
    }
    print_message("idle %g s, timeout %g s: %zu batches, %s\n", idle, timeout, batches,
                  rc ? swfs_last_error() : "ended cleanly");
    if (expect_error) {
        assert_int_equal(rc, SWFS_ERR_IO);
        assert_non_null(strstr(swfs_last_error(), "disappeared and did not come back"));
    } else {
        assert_ok(rc);
        assert_int_equal(b.nexp, 0);
    }
    swfs_shm_source_close(src);
}

static void test_gone_after_idle(void **state)
{
    (void)state;
    gone_after(0.2, 0.4, 0); /* the data had ended: every frame, no error */
    gone_after(0.0, 0.4, 1); /* no idle end: the streams' absence is the error */
    gone_after(2.0, 0.4, 1); /* gone before idle would end the data: the error */
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_equal_to_stream),
        cmocka_unit_test(test_drops),
        cmocka_unit_test(test_dm_offsets),
        cmocka_unit_test(test_signal_and_errors),
        cmocka_unit_test(test_gone_after_idle),
        cmocka_unit_test(test_equal_to_stream_milk), /* last: it makes its own folder */
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

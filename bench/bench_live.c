/* `live` keeping up with an AO system through shared-memory streams, in one process: a
 * writer thread publishes WFS slopes and camera frames into ImageStreamIO streams at the
 * real rates, with acquisition stamps; the library's live path reads them (shm source:
 * reader threads, framesync), runs the pipeline of `specklewfs stream` (given
 * reconstructor, Clough-Tocher interpolation, exposure tip-tilt model, float engine on
 * 2 threads) and accumulates. Two AO systems, as bench/bench_engine.c:
 *   MMT-like:  12x12 SH (288 slopes), hexapolar DM, 163^2 pupil, 60x60 window at
 *              0.25 lambda/D, 6.48 WFS frames per camera frame, WFS at 527 Hz;
 *   ExAO-like: 45x45 SH (4050 slopes), ~2000 actuators, 256^2 pupil, 128x128 window,
 *              20 WFS frames per camera frame, WFS at 2000 Hz;
 * for two batch sizes (1 camera frame: the lowest lag; 8: the throughput setting).
 * Printed per run: the frames received and used, drops and skipped exposures (keeping up
 * = none), the processing capacity (WFS frames per second of processing time, i.e. how
 * many times real time the path could run) and the lag from a camera frame's time stamp
 * (the end of its exposure) to the end of its accumulation: median, 99th percentile, max.
 * The lag includes waiting for the WFS frames that end after the exposure, for the batch
 * to fill and for the batch ahead of it. "per CPU second": WFS frames per second of the
 * whole process's CPU time (engine, readers, writer), the figure least sensitive to other
 * jobs on the machine.
 *
 * Run:  ./build/bench/bench_live                (about 50 s: 10 s per run)
 *       ./build/bench/bench_live --seconds T    (per run)
 *       ./build/bench/bench_live --depth N      (rolling-buffer streams of N frames; default 2-D)
 *       ./build/bench/bench_live --lags 0,-6,6,-12,12   (a space-time map of those lags, as teach's:
 *                                        each batch's rows stacked, waiting for the largest lag) */
#include "specklewfs/aperture.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/rng.h"
#include "specklewfs/shm.h"
#include "specklewfs/status.h"
#include "specklewfs/stream.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

typedef struct system_def {
    const char *name;
    size_t nsub, npup, nf;
    double diam, obscur, wavelen, pixscale, ratio, wfs_hz, act_rings;
} system_def;

static int die(const char *what)
{
    fprintf(stderr, "bench_live: %s: %s\n", what, swfs_last_error());
    exit(1);
}

typedef struct writer {
    const system_def *d;
    const char *dir;
    size_t nslopes, depth;
    double seconds;
    volatile sig_atomic_t *stop;
    double *slopes;   /* K frames cycled */
    double *science;  /* 4 frames cycled */
    size_t K;
    size_t wfs_sent, cam_sent;
    double late_max;
    swfs_shm *w, *c;
} writer;

/* Publish for `seconds` at the real rates, then let the reader drain and stop it. */
static void *writer_main(void *arg)
{
    writer *w = arg;
    const system_def *d = w->d;
    const double per = 1.0 / d->wfs_hz;
    const double mono0 = swfs_wall_seconds() + 0.05;
    const int64_t tai0 = swfs_shm_now_ns() + 50000000;
    const size_t nwfs = (size_t)(w->seconds * d->wfs_hz);
    size_t k = 0, j = 0;
    while (k < nwfs) {
        const double uw = (double)(k + 1), uc = 0.3 + (double)(j + 1) * d->ratio;
        const int is_wfs = uw <= uc;
        const double when = (is_wfs ? uw : uc) * per;
        swfs_sleep_until(mono0 + when);
        const int64_t stamp = tai0 + llround(when * 1e9);
        if (is_wfs) {
            swfs_shm_write(w->w, w->slopes + (k % w->K) * w->nslopes, stamp);
            k++;
        } else {
            swfs_shm_write(w->c, w->science + (j % 4) * d->nf * d->nf, stamp);
            j++;
        }
        const double late = swfs_wall_seconds() - (mono0 + when);
        if (late > w->late_max) w->late_max = late;
    }
    w->wfs_sent = k;
    w->cam_sent = j;
    swfs_sleep_until(swfs_wall_seconds() + 1.0);
    *w->stop = 1;
    return NULL;
}

/* [rad] a slope of 0.3 rad of phase across one subaperture */
static double slope_scale(const system_def *d) { return 0.3 * d->wavelen / (2.0 * M_PI) / (d->diam / (double)d->nsub); }

static const long *g_lags; /* --lags (NULL: per frame) */
static size_t g_nlags;

static void run_case(const system_def *d, swfs_pipeline *p, size_t nslopes, size_t nact, size_t batch, double seconds,
                     size_t depth, const char *dir)
{
    (void)nact;
    static volatile sig_atomic_t stop;
    stop = 0;
    writer w;
    memset(&w, 0, sizeof w);
    w.d = d;
    w.dir = dir;
    w.nslopes = nslopes;
    w.depth = depth;
    w.seconds = seconds;
    w.stop = &stop;
    w.K = 64;
    w.slopes = malloc(w.K * nslopes * sizeof(double));
    w.science = malloc(4 * d->nf * d->nf * sizeof(double));
    if (!w.slopes || !w.science) die("memory");
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    /* slopes of a physical size: about 0.3 rad of phase across a subaperture (the tip-tilt
     * model puts their mean back as the plane it measures; slopes of 0.3 rad of wavefront
     * tilt made phases of 1e6 rad, whose sines glibc reduces the slow way) */
    const double s1 = slope_scale(d);
    for (size_t q = 0; q < w.K * nslopes; q++) w.slopes[q] = s1 * swfs_rng_normal(&r);
    for (size_t q = 0; q < 4 * d->nf * d->nf; q++) w.science[q] = 100.0 + 10.0 * swfs_rng_uniform(&r);
    swfs_shm_shape ws = {SWFS_SHM_F32, nslopes, 1, depth > 1 ? depth : 1, depth > 1, 0};
    swfs_shm_shape cs = {SWFS_SHM_F32, d->nf, d->nf, depth > 1 ? depth : 1, depth > 1, 0};
    if (swfs_shm_create(&w.w, dir, "bench_wfs", &ws) || swfs_shm_create(&w.c, dir, "bench_cam", &cs)) die("streams");

    swfs_shm_source_options so;
    swfs_shm_source_options_default(&so);
    const char *names[1] = {"bench_wfs"};
    so.dir = dir;
    so.wfs = names;
    so.nwfs = 1;
    so.camera = "bench_cam";
    so.nslopes = nslopes;
    so.nfx = so.nfy = d->nf;
    so.sync.batch = batch;
    so.sync.max_wait = 0.5;
    so.sync.lags = g_lags;
    so.sync.nlags = g_nlags;
    so.stop = &stop;
    swfs_shm_source *src = NULL;
    if (swfs_shm_source_open(&src, &so)) die("shm source");
    swfs_stream_options sto;
    swfs_stream_options_default(&sto);
    sto.static_mode = SWFS_STATIC_NONE;
    sto.noise.read_noise = 1.0;
    swfs_stream *s = NULL;
    if (swfs_stream_create(&s, p, &sto)) die("stream");
    pthread_t th;
    if (pthread_create(&th, NULL, writer_main, &w)) die("writer thread");
    struct timespec cp0, cp1;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cp0);
    int rc = swfs_stream_run(s, swfs_shm_source_next, src, NULL, NULL);
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &cp1);
    const double cpu = (double)(cp1.tv_sec - cp0.tv_sec) + 1e-9 * (double)(cp1.tv_nsec - cp0.tv_nsec);
    pthread_join(th, NULL);
    if (rc) die("live run");
    swfs_shm_source_stats st;
    swfs_shm_source_get_stats(src, &st);
    const swfs_framesync_stats *y = &st.sync;
    const double wfs = swfs_stream_wfs_frames(s), proc = swfs_stream_seconds(s);
    const uint64_t skipped = y->incomplete + y->no_wfs + y->overrun;
    printf("%-9s %5zu %8.0f %9zu %9llu %9llu %6llu/%-6llu %8llu %10.0f %7.2f %8.0f %8.1f %8.1f %8.1f   %.1f\n", d->name, batch,
           d->wfs_hz, w.cam_sent, (unsigned long long)y->camera_received, (unsigned long long)y->used,
           (unsigned long long)y->wfs_dropped, (unsigned long long)y->camera_dropped, (unsigned long long)skipped,
           wfs / proc, wfs / proc / d->wfs_hz, wfs / cpu, 1e3 * st.lag_median, 1e3 * st.lag_p99, 1e3 * st.lag_max,
           1e3 * w.late_max);
    fflush(stdout);
    swfs_stream_free(s);
    swfs_shm_source_close(src);
    swfs_shm_close(w.w, 1);
    swfs_shm_close(w.c, 1);
    free(w.slopes);
    free(w.science);
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    swfs_blas_set_threads(1);
    double seconds = 10.0;
    size_t depth = 0;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--seconds") && i + 1 < argc) seconds = atof(argv[++i]);
        else if (!strcmp(argv[i], "--depth") && i + 1 < argc) depth = (size_t)atol(argv[++i]);
        else if (!strcmp(argv[i], "--lags") && i + 1 < argc) {
            static long lv[SWFS_RECON_MAXLAGS];
            if (swfs_lags_parse(argv[++i], lv, &g_nlags, "--lags")) die("--lags");
            g_lags = g_nlags > 1 ? lv : NULL;
            if (g_nlags < 2) g_nlags = 0;
        } else {
            fprintf(stderr, "usage: bench_live [--seconds T] [--depth N] [--lags L,L,...]\n");
            return 2;
        }
    }
    if (!(seconds > 0)) return 2;
    char dir[] = "/dev/shm/swfs_bench_XXXXXX";
    char tdir[] = "/tmp/swfs_bench_XXXXXX";
    const char *d0 = mkdtemp(dir);
    if (!d0) d0 = mkdtemp(tdir);
    if (!d0) {
        perror("bench_live: temporary stream folder");
        return 1;
    }
    static const system_def defs[2] = {
        {"MMT-like", 12, 163, 60, 6.5, 0.1, 1.6e-6, 0.25, 6.48, 527.0, 9.5},
        {"ExAO-like", 45, 256, 128, 8.0, 0.14, 1.6e-6, 0.5, 20.0, 2000.0, 25.0},
    };
    printf("streams in %s (%s), %.0f s per run, 2 engine threads", d0, depth > 1 ? "rolling buffers" : "2-D", seconds);
    for (size_t k = 0; k < g_nlags; k++) printf("%s%ld", k ? "," : "; a space-time map of lags ", g_lags[k]);
    printf("\n");
    printf("%-9s %5s %8s %9s %9s %9s %13s %8s %10s %7s %8s %8s %8s %8s   %s\n", "system", "batch", "WFS Hz", "cam sent",
           "received", "used", "drop wfs/cam", "skipped", "capacity", "x real", "per CPU", "lag med", "lag 99%", "lag max",
           "writer late max [ms]");
    printf("%-9s %5s %8s %9s %9s %9s %13s %8s %10s %7s %8s %8s %8s %8s\n", "", "", "", "", "", "", "", "", "WFS fr/s", "",
           "second", "[ms]", "[ms]", "[ms]");
    for (int i = 0; i < 2; i++) {
        const system_def *d = &defs[i];
        const double t0 = swfs_wall_seconds();
        swfs_geom g;
        swfs_geom_init(&g);
        g.wavelen = d->wavelen;
        g.teldiam = d->diam;
        g.obscur = d->obscur;
        g.pixscale = d->pixscale;
        g.pupdx = d->diam / ((double)d->npup - 0.5);
        g.pupn = (long)d->npup;
        const double pitch = 0.5 * d->diam / d->act_rings;
        double *xy = NULL;
        size_t nact = 0;
        if (swfs_actuators_hexapolar(d->diam, pitch, 0.5 * pitch, &xy, &nact)) die("actuators");
        const size_t nslopes = 2 * d->nsub * d->nsub;
        swfs_recon rec = {.nact = nact, .nslopes = nslopes, .W = malloc(nact * nslopes * sizeof(double))};
        if (!rec.W) die("memory");
        swfs_rng r;
        swfs_rng_seed(&r, 42);
        const double scale = 0.3 * d->wavelen / (2.0 * M_PI) / sqrt((double)nslopes) / slope_scale(d); /* ~0.3 rad */
        for (size_t k = 0; k < nact * nslopes; k++) rec.W[k] = scale * swfs_rng_normal(&r);
        if (g_nlags > 1) { /* a space-time map: the same map at lag 0, a third of it at the others */
            const size_t nl = g_nlags, w = nl * nslopes;
            double *st = malloc(nact * w * sizeof *st);
            if (!st) die("memory");
            for (size_t a = 0; a < nact; a++)
                for (size_t q = 0; q < w; q++)
                    st[a * w + q] = (g_lags[q / nslopes] == 0 ? 1.0 : 0.3) * rec.W[a * nslopes + q % nslopes];
            free(rec.W);
            rec.W = st;
            rec.nslopes = w;
            rec.nlags = nl;
            memcpy(rec.lags, g_lags, nl * sizeof *g_lags);
        }
        swfs_pipeline_options po;
        swfs_pipeline_options_default(&po);
        po.recon = SWFS_RECON_GIVEN;
        po.threads = 2;
        swfs_pipeline *p = NULL;
        if (swfs_pipeline_create(&p, &g, d->nf, d->nf, xy, nact, NULL, nslopes, &rec, NULL, 0, &po)) die("pipeline");
        fprintf(stderr, "%s: %zu slopes, %zu actuators: pipeline built in %.1f s\n", d->name, nslopes, nact,
                swfs_wall_seconds() - t0);
        const size_t batches[2] = {1, 8};
        for (int b = 0; b < 2; b++) run_case(d, p, nslopes, nact, batches[b], seconds, depth, d0);
        swfs_pipeline_free(p);
        free(rec.W);
        free(xy);
    }
    rmdir(d0);
    return 0;
}

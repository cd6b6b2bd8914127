/* End-to-end throughput of the real-time path: slopes -> reconstruction -> interpolation ->
 * exp(i phi) -> pupil-field sums -> MFT -> core referencing -> minus the static halo ->
 * per-pixel accumulators against a science frame. Two AO systems (issue 6):
 *   MMT-like:  12x12 SH (288 slopes), ~300 actuators, 163^2 pupil, 60x60 window at
 *              0.25 lambda/D, 6.48 WFS frames per camera frame, real time 527 Hz;
 *   ExAO-like: 50x50 SH (~4000 slopes), ~2000 actuators, 256^2 pupil, 128x128 window,
 *              20 WFS frames per camera frame, real time 2000 Hz;
 * each with one MFT per camera frame (the halo estimate) and one MFT per WFS frame (what
 * the coherence maps need), on 1 and 2 threads. Inputs are synthetic but shaped like real
 * ones: random slopes and a dense random reconstructor of the right size, the project's
 * Clough-Tocher interpolation matrix for a hexapolar actuator grid (qhull), an annular pupil.
 * Then peak RSS after 10^3, 10^4 and 10^5 camera frames of the MMT-like pipeline (flat =
 * memory does not grow with time).
 *
 * Run:  ./build/bench/bench_engine            (about a minute)
 *       ./build/bench/bench_engine --quick    (shorter timings, memory to 10^4 frames) */
#include "specklewfs/accum.h"
#include "specklewfs/aperture.h"
#include "specklewfs/engine.h"
#include "specklewfs/interp.h"
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/sparse.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>

typedef struct system_def {
    const char *name;
    size_t nsub, nslopes, npup, nf;
    double diam, obscur, wavelen, pixscale, ratio, realtime_hz;
    double act_rings; /* hexapolar rings across the radius */
} system_def;

typedef struct ao_system {
    const system_def *def;
    double *recon, *pupil, *act;
    size_t nact;
    swfs_sparse *interp;
    double alpha, build_s, nnz_per_row;
} ao_system;

static double peak_rss_mb(void)
{
    struct rusage ru;
    getrusage(RUSAGE_SELF, &ru);
    return (double)ru.ru_maxrss / 1024.0; /* Linux: kilobytes */
}

static int die(const char *what)
{
    fprintf(stderr, "bench_engine: %s: %s\n", what, swfs_last_error());
    exit(1);
}

static void build_system(ao_system *s, const system_def *d)
{
    const double t0 = swfs_wall_seconds();
    s->def = d;
    const double pupdx = d->diam / ((double)d->npup - 0.5);
    s->alpha = d->pixscale * pupdx / d->diam;
    s->pupil = malloc(d->npup * d->npup * sizeof(double));
    if (!s->pupil) die("memory");
    if (swfs_aperture_make(s->pupil, d->npup, pupdx, d->diam, d->obscur, 0, 0.0)) die("pupil");
    const double pitch = 0.5 * d->diam / d->act_rings;
    if (swfs_actuators_hexapolar(d->diam, pitch, 0.5 * pitch, &s->act, &s->nact)) die("actuators");
    if (swfs_interp_ct_grid(s->act, s->nact, d->npup, pupdx, s->pupil, &s->interp, NULL)) die("interpolation");
    size_t rows = 0;
    for (size_t p = 0; p < d->npup * d->npup; p++) rows += s->pupil[p] > 0;
    s->nnz_per_row = (double)s->interp->nnz / (double)rows;
    /* Dense reconstructor of the right shape, scaled for ~1 rad rms phase. */
    swfs_rng r;
    swfs_rng_seed(&r, 42);
    s->recon = malloc(s->nact * d->nslopes * sizeof(double));
    if (!s->recon) die("memory");
    const double scale = d->wavelen / (2.0 * M_PI) / sqrt((double)d->nslopes);
    for (size_t k = 0; k < s->nact * d->nslopes; k++) s->recon[k] = scale * swfs_rng_normal(&r);
    s->build_s = swfs_wall_seconds() - t0;
}

static void free_system(ao_system *s)
{
    free(s->recon);
    free(s->pupil);
    free(s->act);
    swfs_sparse_free(s->interp);
}

static swfs_engine *make_engine(const ao_system *s, int nthreads)
{
    const system_def *d = s->def;
    swfs_engine_config c = {d->nslopes, s->nact, d->npup, d->nf, d->nf, s->alpha, d->wavelen, s->recon,
                            s->interp, s->pupil, 1, nthreads};
    swfs_engine *e = swfs_engine_create(&c);
    if (!e) die("engine");
    return e;
}

typedef struct run_result {
    double wfs_per_s, engine_wfs_per_s;
    double wfs_per_cpu_s; /* per second of CPU time, all threads: insensitive to other load */
} run_result;

static double cpu_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* The pipeline for at least `seconds`: per batch of camera frames, the engine, then the
 * static-halo subtraction and accumulation (eq:computedSpeckleField, eq:stabilized).
 * per_wfs: one MFT (and one accumulation) per WFS frame instead of per camera frame. */
static run_result run(const ao_system *s, int nthreads, int per_wfs, double seconds, size_t max_cam,
                      double *mem_checkpoints, const size_t *mem_at, size_t n_mem)
{
    const system_def *d = s->def;
    const size_t nf2 = d->nf * d->nf;
    /* Enough work per call for both workers: chunks of <= 256 WFS frames (engine.c). */
    const size_t batch = per_wfs ? 512 : (d->npup > 200 ? 128 : 512);
    swfs_exposure *sched = malloc(batch * sizeof *sched);
    const size_t nwfs = per_wfs ? batch : swfs_engine_schedule(d->ratio, 0.0, batch, sched);
    const double wfs_per_batch = per_wfs ? (double)batch : d->ratio * (double)batch;
    double *slopes = malloc(nwfs * d->nslopes * sizeof(double));
    double complex *out = malloc(batch * nf2 * sizeof *out);
    double complex *stat = calloc(nf2, sizeof *stat);
    double *science = malloc(nf2 * sizeof *science);
    swfs_accum *acc = swfs_accum_create(d->nf, d->nf);
    if (!sched || !slopes || !out || !stat || !science || !acc) die("memory");
    swfs_rng r;
    swfs_rng_seed(&r, 7);
    for (size_t k = 0; k < nwfs * d->nslopes; k++) slopes[k] = swfs_rng_normal(&r);
    for (size_t k = 0; k < nf2; k++) {
        science[k] = 100.0 + 10.0 * swfs_rng_uniform(&r);
        stat[k] = 0.1 * swfs_rng_cnormal_value(&r);
    }
    swfs_engine *e = make_engine(s, nthreads);

    double t_engine = 0.0, wfs_done = 0.0;
    size_t cam_done = 0, next_mem = 0;
    const double t0 = swfs_wall_seconds(), c0 = cpu_now();
    while ((max_cam ? cam_done < max_cam : swfs_wall_seconds() - t0 < seconds)) {
        const double t1 = swfs_wall_seconds();
        int rc = per_wfs ? swfs_engine_process_wfs(e, slopes, nwfs, out)
                         : swfs_engine_process(e, slopes, nwfs, sched, batch, out);
        if (rc) die("engine run");
        t_engine += swfs_wall_seconds() - t1;
        for (size_t j = 0; j < batch; j++) {
            double complex *psi = out + j * nf2;
            for (size_t k = 0; k < nf2; k++) psi[k] -= stat[k];
            if (swfs_accum_add(acc, science, psi)) die("accumulate");
        }
        wfs_done += wfs_per_batch;
        cam_done += batch;
        while (next_mem < n_mem && cam_done >= mem_at[next_mem]) mem_checkpoints[next_mem++] = peak_rss_mb();
    }
    const double elapsed = swfs_wall_seconds() - t0;
    run_result res = {wfs_done / elapsed, wfs_done / t_engine, wfs_done / (cpu_now() - c0)};
    swfs_engine_free(e);
    swfs_accum_free(acc);
    free(sched); free(slopes); free(out); free(stat); free(science);
    return res;
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    /* As the command line: the library parallelizes over frames, BLAS stays single-threaded
     * (parallel.h). */
    swfs_blas_set_threads(1);
    int quick = argc > 1 && !strcmp(argv[1], "--quick");
    /* --case SYSTEM MODE THREADS (0/1 each, threads 1..): one timing only, for profiling. */
    int only = argc == 5 && !strcmp(argv[1], "--case");
    if (argc > 1 && !quick && !only) {
        fprintf(stderr, "usage: bench_engine [--quick | --case SYSTEM(0|1) PER_WFS(0|1) THREADS]\n");
        return 2;
    }
    const double seconds = quick ? 0.6 : 2.5;
    static const system_def defs[2] = {
        {"MMT-like", 12, 288, 163, 60, 6.5, 0.1, 1.6e-6, 0.25, 6.48, 527.0, 9.5},
        {"ExAO-like", 50, 4000, 256, 128, 8.0, 0.14, 1.6e-6, 0.5, 20.0, 2000.0, 25.0},
    };
    ao_system sys[2];
    for (int i = 0; i < 2; i++) {
        build_system(&sys[i], &defs[i]);
        printf("%-9s  %zu slopes, %zu actuators, %zu^2 pupil, %zux%zu window, %.2f WFS frames per camera frame, "
               "interpolation %.1f nonzeros per illuminated sample; plans built in %.2f s\n",
               defs[i].name, defs[i].nslopes, sys[i].nact, defs[i].npup, defs[i].nf, defs[i].nf, defs[i].ratio,
               sys[i].nnz_per_row, sys[i].build_s);
        fflush(stdout);
        if (i == 0 && !only) {
            /* Memory versus time, before the larger configuration raises the peak. */
            const size_t mem_at[3] = {1000, 10000, 100000};
            double mem[3] = {0, 0, 0};
            const size_t n_mem = quick ? 2 : 3;
            const double rss0 = peak_rss_mb(), tm = swfs_wall_seconds();
            run(&sys[0], 2, 0, 0.0, mem_at[n_mem - 1], mem, mem_at, n_mem);
            printf("\npeak RSS, MMT-like, 2 threads, one MFT per camera frame, batches of 512 camera frames "
                   "(%.1f s for %zu camera frames); %.1f MB before the run (inputs and plans):\n",
                   swfs_wall_seconds() - tm, mem_at[n_mem - 1], rss0);
            for (size_t k = 0; k < n_mem; k++) printf("  after %6zu camera frames: %7.1f MB\n", mem_at[k], mem[k]);
            printf("\n");
            fflush(stdout);
        }
    }
    if (only) {
        const int i = atoi(argv[2]) != 0, per_wfs = atoi(argv[3]) != 0, nt = atoi(argv[4]);
        run_result rr = run(&sys[i], nt < 1 ? 1 : nt, per_wfs, 3.0, 0, NULL, NULL, 0);
        printf("%s %s %d threads: %.0f WFS frames/s (%.2f x real time), engine only %.0f/s, %.0f per CPU second\n",
               defs[i].name, per_wfs ? "MFT per WFS frame" : "MFT per camera frame", nt, rr.wfs_per_s,
               rr.wfs_per_s / defs[i].realtime_hz, rr.engine_wfs_per_s, rr.wfs_per_cpu_s);
        for (int k = 0; k < 2; k++) free_system(&sys[k]);
        return 0;
    }

    printf("\n%-9s %-22s %7s %14s %12s %16s\n", "system", "mode", "threads", "WFS frames/s", "x real time",
           "engine only /s");
    for (int i = 0; i < 2; i++)
        for (int per_wfs = 0; per_wfs < 2; per_wfs++)
            for (int nt = 1; nt <= 2; nt++) {
                run_result rr = run(&sys[i], nt, per_wfs, seconds, 0, NULL, NULL, 0);
                printf("%-9s %-22s %7d %14.0f %12.2f %16.0f\n", defs[i].name,
                       per_wfs ? "MFT per WFS frame" : "MFT per camera frame", nt, rr.wfs_per_s,
                       rr.wfs_per_s / defs[i].realtime_hz, rr.engine_wfs_per_s);
                fflush(stdout);
            }
    printf("\npeak RSS of the whole benchmark: %.1f MB\n", peak_rss_mb());
    for (int i = 0; i < 2; i++) free_system(&sys[i]);
    return 0;
}

/* Throughput of the generic linear model (pipeline.h swfs_pipeline_create_linear): modal
 * coefficients per WFS frame (cacao's modevalWFS) on mode shapes given on the DM's grid,
 * through the same engine as the Shack-Hartmann path. Two systems:
 *   MMT-like:  220 modes on a 30 x 30 DM grid, 163^2 pupil, 60 x 60 window, 6.48 WFS frames
 *              per camera frame, real time 527 Hz;
 *   ExAO-like: 1200 modes on a 50 x 50 DM grid, 256^2 pupil, 128 x 128 window, 20 WFS frames
 *              per camera frame, real time 2000 Hz;
 * each with the basis in factored form (the grid's cubic interpolation onto the pupil and the
 * modes' grid values: one small GEMM per frame batch and a sparse product, what `speckles
 * --basis` builds) and resampled dense onto the pupil (one GEMM over every illuminated
 * sample and mode), on 1 and 2 threads. Inputs are random (mode values, coefficients); the
 * cost does not depend on them.
 *
 * Run: ./build/bench/bench_modal [--quick] */
#include "specklewfs/aperture.h"
#include "specklewfs/lmodel.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct sys_def {
    const char *name;
    size_t nmodes, ngrid, npup, nf;
    double diam, obscur, wavelen, pixscale, ratio, realtime_hz;
} sys_def;

static void die(const char *what)
{
    fprintf(stderr, "bench_modal: %s: %s\n", what, swfs_last_error());
    exit(1);
}

/* WFS frames per second through swfs_pipeline_process for at least `seconds`. */
static double run(const sys_def *d, int factored, int threads, double seconds, double *build_s, size_t *nnz)
{
    const size_t np = d->npup, gn = d->ngrid * d->ngrid, nk = d->nmodes;
    const double pupdx = d->diam / ((double)np - 0.5);
    swfs_geom g = {d->wavelen, d->diam, d->obscur, d->pixscale, pupdx, (long)np};
    double *mask = malloc(np * np * sizeof *mask), *cube = malloc(gn * nk * sizeof *cube);
    double *shapes = malloc(gn * nk * sizeof *shapes);
    if (!mask || !cube || !shapes) die("memory");
    if (swfs_aperture_make(mask, np, pupdx, d->diam, d->obscur, 0, 0.0)) die("pupil");
    swfs_rng r;
    swfs_rng_seed(&r, 5);
    for (size_t k = 0; k < gn * nk; k++) cube[k] = swfs_rng_normal(&r);
    for (size_t q = 0; q < gn; q++)
        for (size_t k = 0; k < nk; k++) shapes[q * nk + k] = cube[k * gn + q];
    /* the grid spans the pupil with a step to spare */
    const swfs_dm_registration reg = {1.05 * d->diam / (double)(d->ngrid - 1), 0, 0, 0, 0};
    const double t0 = swfs_wall_seconds();
    swfs_sparse *B = NULL;
    size_t nout = 0;
    if (factored ? swfs_grid_interp(&B, d->ngrid, d->ngrid, &reg, mask, np, pupdx, &nout)
                 : swfs_basis_from_grid(&B, cube, d->ngrid, d->ngrid, nk, &reg, mask, np, pupdx, &nout))
        die("basis");
    *nnz = B->nnz;
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.threads = threads;
    swfs_linear_input in = {nk, B, NULL, NULL, 1e-9, factored ? shapes : NULL, factored ? nk : 0, 0};
    swfs_pipeline *p = NULL;
    if (swfs_pipeline_create_linear(&p, &g, d->nf, d->nf, mask, &in, NULL, 0, &o)) die("pipeline");
    *build_s = swfs_wall_seconds() - t0;
    const size_t nexp = threads > 1 ? 16 : 8;
    swfs_exposure *sched = malloc(nexp * sizeof *sched);
    const size_t nwfs = swfs_engine_schedule(d->ratio, 0.0, nexp, sched);
    double *v = malloc(nwfs * nk * sizeof *v);
    swfs_complex *out = malloc(nexp * d->nf * d->nf * sizeof *out);
    if (!sched || !v || !out) die("memory");
    for (size_t k = 0; k < nwfs * nk; k++) v[k] = swfs_rng_normal(&r);
    if (swfs_pipeline_process(p, v, nwfs, sched, nexp, out)) die("process"); /* warm up */
    double wfs = 0;
    const double t1 = swfs_wall_seconds();
    while (swfs_wall_seconds() - t1 < seconds) {
        if (swfs_pipeline_process(p, v, nwfs, sched, nexp, out)) die("process");
        wfs += d->ratio * (double)nexp;
    }
    const double rate = wfs / (swfs_wall_seconds() - t1);
    swfs_pipeline_free(p);
    swfs_sparse_free(B);
    free(mask); free(cube); free(shapes); free(sched); free(v); free(out);
    return rate;
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    swfs_blas_set_threads(1); /* as the command line: the engine parallelizes over frames */
    const int quick = argc > 1 && !strcmp(argv[1], "--quick");
    if (argc > 1 && !quick) {
        fprintf(stderr, "usage: bench_modal [--quick]\n");
        return 2;
    }
    static const sys_def defs[2] = {
        {"MMT-like", 220, 30, 163, 60, 6.5, 0.1, 3.8e-6, 0.25, 6.48, 527.0},
        {"ExAO-like", 1200, 50, 256, 128, 8.0, 0.14, 1.6e-6, 0.5, 20.0, 2000.0},
    };
    printf("%-9s %6s %-9s %7s %12s %12s %10s %12s\n", "system", "modes", "basis", "threads", "WFS frames/s",
           "x real time", "build [s]", "nonzeros");
    for (int i = 0; i < 2; i++)
        for (int factored = 1; factored >= 0; factored--)
            for (int nt = 1; nt <= 2; nt++) {
                double build;
                size_t nnz;
                const double rate = run(&defs[i], factored, nt, quick ? 0.5 : 2.5, &build, &nnz);
                printf("%-9s %6zu %-9s %7d %12.0f %12.2f %10.2f %12zu\n", defs[i].name, defs[i].nmodes,
                       factored ? "factored" : "dense", nt, rate, rate / defs[i].realtime_hz, build, nnz);
                fflush(stdout);
            }
    return 0;
}

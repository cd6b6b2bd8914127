/* The wind from the slopes (wind.h swfs_wind_from_slopes): its time on frozen-flow slopes of
 * an N x N Shack-Hartmann, against the lagged covariances of every subaperture pair by DGEMM
 * (two per lag, x and y: T nv^2 multiply-adds each), which the lag maps were made of before
 * they were made by FFT (wind.c swfs_wind_lag_sums_).
 * usage: bench_wind [NFRAMES [NSUB...]]   (default 4000 frames of 12, 24 and 40 across) */
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wind.h"

#include <cblas.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

/* A smooth random field on an m x m grid (white noise averaged over 5 x 5 twice). */
static double *field(size_t m, swfs_rng *g)
{
    double *a = malloc(m * m * sizeof *a), *b = malloc(m * m * sizeof *b);
    for (size_t i = 0; i < m * m; i++) a[i] = swfs_rng_normal(g);
    for (int pass = 0; pass < 2; pass++) {
        for (size_t j = 0; j < m; j++)
            for (size_t i = 0; i < m; i++) {
                double s = 0;
                for (size_t d = 0; d < 5; d++) s += a[j * m + (i + m + d - 2) % m];
                b[j * m + i] = s / 5;
            }
        for (size_t j = 0; j < m; j++)
            for (size_t i = 0; i < m; i++) {
                double s = 0;
                for (size_t d = 0; d < 5; d++) s += b[((j + m + d - 2) % m) * m + i];
                a[j * m + i] = s / 5;
            }
    }
    free(b);
    return a;
}

/* f at (x, y) in grid units, bilinear, periodic. */
static double at(const double *f, size_t m, double x, double y)
{
    const double fx = floor(x), fy = floor(y), u = x - fx, v = y - fy;
    const double dm = (double)m;
    const size_t i = (size_t)fmod(fmod(fx, dm) + dm, dm), j = (size_t)fmod(fmod(fy, dm) + dm, dm), i1 = (i + 1) % m,
                 j1 = (j + 1) % m;
    return (1 - u) * (1 - v) * f[j * m + i] + u * (1 - v) * f[j * m + i1] + (1 - u) * v * f[j1 * m + i] + u * v * f[j1 * m + i1];
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    const size_t T = argc > 1 ? (size_t)atol(argv[1]) : 4000;
    size_t nsubs[8] = {12, 24, 40}, nn = 3;
    if (argc > 2) {
        nn = 0;
        for (int a = 2; a < argc && nn < 8; a++) nsubs[nn++] = (size_t)atol(argv[a]);
    }
    printf("bench_wind: %zu WFS frames of one frozen-flow layer (0.13, 0.07 subapertures per frame) and white noise\n", T);
    printf("%6s %6s %12s %10s %14s %14s %8s\n", "nsub", "valid", "wind [s]", "frames/s", "DGEMM maps [s]",
           "(their lags)", "ratio");
    for (size_t c = 0; c < nn; c++) {
        const size_t n = nsubs[c], ns = 2 * n * n, m = 8 * n;
        swfs_rng g;
        swfs_rng_seed(&g, 7 + n);
        double *f = field(m, &g), *s = malloc(T * ns * sizeof *s);
        unsigned char *valid = malloc(n * n);
        size_t nv = 0;
        for (size_t j = 0; j < n; j++)
            for (size_t i = 0; i < n; i++) {
                const double r = hypot((double)i + 0.5 - 0.5 * (double)n, (double)j + 0.5 - 0.5 * (double)n) / (0.5 * (double)n);
                valid[j * n + i] = r <= 1.0 && r >= 0.15;
                nv += valid[j * n + i];
            }
        for (size_t t = 0; t < T; t++)
            for (size_t j = 0; j < n; j++)
                for (size_t i = 0; i < n; i++) {
                    const double x = 2.0 * (double)i - 0.13 * 2.0 * (double)t + (double)m, y = 2.0 * (double)j - 0.07 * 2.0 * (double)t + (double)m;
                    const size_t k = j * n + i;
                    s[t * ns + k] = valid[k] ? at(f, m, x + 1, y) - at(f, m, x - 1, y) + 0.1 * swfs_rng_normal(&g) : 0;
                    s[t * ns + n * n + k] = valid[k] ? at(f, m, x, y + 1) - at(f, m, x, y - 1) + 0.1 * swfs_rng_normal(&g) : 0;
                }
        swfs_wind_estimate e;
        double t0 = swfs_wall_seconds();
        if (swfs_wind_from_slopes(s, T, ns, n, valid, 1.0, 1.0, &e)) {
            fprintf(stderr, "bench_wind: %s\n", swfs_last_error());
            return 1;
        }
        const double tw = swfs_wall_seconds() - t0;
        /* the maps' lags (2^k and 3 x 2^k up to T / 4), two DGEMMs each over the valid
         * subapertures' x and y */
        size_t lags[64], nl = 0;
        for (size_t p2 = 1; p2 <= T / 4 && nl + 2 <= 64; p2 *= 2) {
            lags[nl++] = p2;
            if (p2 > 1 && 3 * p2 / 2 <= T / 4) lags[nl++] = 3 * p2 / 2;
        }
        double *x = malloc(2 * T * nv * sizeof *x), *y = x + T * nv, *cv = malloc(nv * nv * sizeof *cv);
        for (size_t t = 0; t < T; t++)
            for (size_t k = 0, q = 0; k < n * n; k++)
                if (valid[k]) {
                    x[t * nv + q] = s[t * ns + k];
                    y[t * nv + q++] = s[t * ns + n * n + k];
                }
        t0 = swfs_wall_seconds();
        for (size_t l = 0; l < nl; l++)
            for (int axis = 0; axis < 2; axis++) {
                const double *a = axis ? y : x;
                cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)nv, (int)nv, (int)(T - lags[l]), 1.0, a, (int)nv,
                            a + lags[l] * nv, (int)nv, axis ? 1.0 : 0.0, cv, (int)nv);
            }
        const double td = swfs_wall_seconds() - t0;
        printf("%6zu %6zu %12.3f %10.0f %14.3f %14zu %8.1f   (%.2f subapertures per frame found, %.2f true)\n", n, nv, tw,
               (double)T / tw, td, nl, td / tw, hypot(e.vx, e.vy), hypot(0.13, 0.07));
        free(x);
        free(cv);
        free(f);
        free(s);
        free(valid);
    }
    return 0;
}

/* The modulated pyramid's cost (pyramid.h): WFS frames per second of swfs_pyramid_measure on
 * the pupil grids of the CI's series (66 samples), the benchmark matrix's (100) and an MMT-like
 * one (163), at 3 lambda/D (its rule's 40 points) and without modulation, and the push-pull
 * interaction matrix of a hexapolar DM (docs/telemetry.md, "A pyramid wavefront sensor").
 *
 *   ./build/bench/bench_pyramid [--frames N]
 *
 * One thread (the simulator's loop runs one sensor per run; teach runs loops side by side). */
#include "specklewfs/interp.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pyramid.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static double *annulus(size_t n, double dx, double diam, double obs)
{
    double *m = malloc(n * n * sizeof *m);
    for (size_t q = 0; m && q < n; q++)
        for (size_t p = 0; p < n; p++) {
            const double x = ((double)p - 0.5 * (double)(n - 1)) * dx, y = ((double)q - 0.5 * (double)(n - 1)) * dx;
            const double r = sqrt(x * x + y * y);
            m[q * n + p] = (r <= 0.5 * diam && r >= 0.5 * obs * diam) ? 1.0 : 0.0;
        }
    return m;
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv);
    long frames = 200;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--frames") && i + 1 < argc) frames = atol(argv[++i]);
        else {
            fprintf(stderr, "usage: bench_pyramid [--frames N]\n");
            return 2;
        }
    }
    if (frames < 1) frames = 1;
    const struct { const char *name; size_t npup, nsub; double dx; } grids[3] = {
        {"CI series", 66, 12, 0.1}, {"bench matrix", 100, 16, 0.065}, {"MMT-like", 163, 12, 0.04}};
    const double D = 6.5, lam = 0.85e-6;
    printf("modulated pyramid (one thread): WFS frames per second of swfs_pyramid_measure\n");
    printf("%-13s %5s %5s %5s %6s %9s %9s | %s\n", "pupil", "npup", "N", "nsub", "points", "ms/frame", "frames/s",
           "interaction matrix");
    for (int g = 0; g < 3; g++) {
        double *mask = annulus(grids[g].npup, grids[g].dx, D, 0.1);
        const size_t ng = grids[g].npup * grids[g].npup;
        double *z = malloc(ng * sizeof *z), *s = malloc(2 * grids[g].nsub * grids[g].nsub * sizeof *s);
        if (!mask || !z || !s) return 1;
        swfs_rng rng;
        swfs_rng_seed(&rng, 1);
        for (size_t k = 0; k < ng; k++) z[k] = 30e-9 * swfs_rng_normal(&rng);
        for (int mod = 0; mod < 2; mod++) {
            swfs_pyramid *p = NULL;
            if (swfs_pyramid_create(&p, grids[g].nsub, D, mask, grids[g].npup, grids[g].dx, NULL, lam, mod ? 3.0 : 0.0,
                                    0)) {
                fprintf(stderr, "bench_pyramid: %s\n", swfs_last_error());
                return 1;
            }
            const double t0 = swfs_wall_seconds();
            for (long f = 0; f < frames; f++) swfs_pyramid_measure(p, z, 1000, &rng, s);
            const double dt = (swfs_wall_seconds() - t0) / (double)frames;
            char im[96] = "";
            if (mod) { /* the interaction matrix of a hexapolar DM of 0.83 subapertures' pitch */
                double *xy = NULL, *Dm = NULL;
                size_t nact = 0, out = 0;
                swfs_sparse *T = NULL;
                const double pitch = 0.83 * D / (double)grids[g].nsub;
                if (!swfs_actuators_hexapolar(D, pitch, 0.5 * pitch, &xy, &nact) &&
                    !swfs_interp_ct_grid(xy, nact, grids[g].npup, grids[g].dx, mask, &T, &out)) {
                    const double t1 = swfs_wall_seconds();
                    if (!swfs_pyramid_interaction(p, T, lam / 100, &Dm))
                        snprintf(im, sizeof im, "%zu actuators, %.1f s", nact, swfs_wall_seconds() - t1);
                }
                free(xy); free(Dm);
                swfs_sparse_free(T);
            }
            printf("%-13s %5zu %5zu %5zu %6zu %9.2f %9.0f | %s\n", grids[g].name, grids[g].npup, p->nfft, grids[g].nsub,
                   p->nmod, 1e3 * dt, 1.0 / dt, im);
            fflush(stdout);
            swfs_pyramid_free(p);
        }
        free(mask); free(z); free(s);
    }
    return 0;
}

/* The communication of a distributed run (docs/cluster.md), measured on this machine:
 * per focal-plane size, the bytes one rank sends in the accumulator reduction, the time of
 * one exact merge of two states (swfs_accum_merge_state) and of the whole reduction over
 * the ranks of this launch (the team's MPI_Reduce with the merge operation), the median of
 * REPS runs. Run as `mpirun -n 1 bench_mpi` and `mpirun -n 2 bench_mpi`; the model in
 * docs/cluster.md takes its numbers from here.
 *
 * usage: [mpirun -n P] bench_mpi [REPS (20)] */
#include "specklewfs/accum.h"
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/team_mpi.h"

#include <mpi.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int cmp(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double median(double *v, int n)
{
    qsort(v, (size_t)n, sizeof *v, cmp);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* An accumulator of nx x ny pixels that has seen `frames` random frames. */
static swfs_accum *filled(size_t n, int frames, uint64_t seed)
{
    swfs_accum *a = swfs_accum_create(n, n);
    double *sci = malloc(n * n * sizeof *sci);
    swfs_complex *psi = malloc(n * n * sizeof *psi);
    swfs_rng r;
    swfs_rng_seed(&r, seed);
    for (int f = 0; f < frames; f++) {
        for (size_t p = 0; p < n * n; p++) {
            psi[p] = swfs_rng_normal(&r) + I * swfs_rng_normal(&r);
            sci[p] = 100.0 + 10.0 * swfs_rng_normal(&r);
        }
        swfs_accum_add(a, sci, psi);
    }
    free(sci);
    free(psi);
    return a;
}

int main(int argc, char **argv)
{
    int provided;
    MPI_Init_thread(&argc, &argv, MPI_THREAD_FUNNELED, &provided);
    const int reps = argc > 1 ? atoi(argv[1]) : 20;
    swfs_team *t = NULL;
    if (swfs_mpi_team_create(MPI_COMM_WORLD, &t) || reps < 1) {
        fprintf(stderr, "bench_mpi: cannot create the team or bad REPS\n");
        MPI_Abort(MPI_COMM_WORLD, 1);
    }
    const size_t sizes[] = {60, 127, 128, 255, 256};
    if (t->rank == 0)
        printf("bench_mpi: %d rank(s), median of %d\n%8s %12s %12s %14s %14s\n", t->size, reps, "pixels", "state [MB]",
               "merge [ms]", "reduce [ms]", "reduce-merge");
    for (size_t k = 0; k < sizeof sizes / sizeof sizes[0]; k++) {
        const size_t n = sizes[k], len = swfs_accum_state_len(n, n);
        swfs_accum *a = filled(n, 8, 1 + (uint64_t)t->rank), *b = filled(n, 8, 1000);
        double *sa = malloc(len * sizeof *sa), *sb = malloc(len * sizeof *sb), *st = malloc(len * sizeof *st);
        double *tm = malloc((size_t)reps * sizeof *tm), *tr = malloc((size_t)reps * sizeof *tr);
        swfs_accum_export(a, sa);
        swfs_accum_export(b, sb);
        for (int r = 0; r < reps; r++) {
            memcpy(st, sa, len * sizeof *st);
            const double t0 = swfs_wall_seconds();
            swfs_accum_merge_state(st, sb, n, n);
            tm[r] = swfs_wall_seconds() - t0;
        }
        for (int r = 0; r < reps; r++) {
            memcpy(st, sa, len * sizeof *st);
            MPI_Barrier(MPI_COMM_WORLD);
            double bytes, sec;
            t->merge_accum(t->ctx, st, n, n);
            swfs_mpi_team_last_reduce(t, &bytes, &sec);
            /* the reduction ends when the root has the union: its time is the one that counts */
            MPI_Bcast(&sec, 1, MPI_DOUBLE, 0, MPI_COMM_WORLD);
            tr[r] = sec;
        }
        const double m = median(tm, reps), red = median(tr, reps);
        if (t->rank == 0)
            printf("%5zux%-3zu %12.2f %12.3f %14.3f %14.3f\n", n, n, (double)len * 8 / 1e6, 1e3 * m, 1e3 * red,
                   1e3 * (red - m * (t->size > 1)));
        swfs_accum_free(a);
        swfs_accum_free(b);
        free(sa); free(sb); free(st); free(tm); free(tr);
    }
    swfs_mpi_team_free(t);
    MPI_Finalize();
    return 0;
}

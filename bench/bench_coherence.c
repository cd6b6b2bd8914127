/* Speckle coherence: FFT along time against direct sums for a WFS-rate cube.
 * usage: bench_coherence [NFRAMES [NPIX]]   (default 650 frames of 60 x 60) */
#include "specklewfs/coherence.h"
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <stdlib.h>

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    /* As the command line: the library parallelizes over frames, BLAS stays single-threaded
     * (parallel.h). */
    swfs_blas_set_threads(1);
    size_t nt = argc > 1 ? (size_t)atol(argv[1]) : 650, n = argc > 2 ? (size_t)atol(argv[2]) : 60;
    swfs_cplx *c = swfs_cplx_alloc(n, n, nt);
    if (!c) { fprintf(stderr, "%s\n", swfs_last_error()); return 1; }
    swfs_rng r;
    swfs_rng_seed(&r, 1);
    for (size_t i = 0; i < swfs_cplx_size(c); i++) c->data[i] = swfs_rng_cnormal_value(&r);
    const int methods[3] = {SWFS_COH_AUTO, SWFS_COH_FFT, SWFS_COH_DIRECT};
    const char *names[3] = {"auto", "fft", "direct"};
    for (int m = 0; m < 3; m++) {
        swfs_coh_options o;
        swfs_coh_options_default(&o);
        o.method = methods[m];
        o.exposure = 6.5e-3;
        double best = 1e30;
        int used = 0;
        long maxlag = 0;
        for (int rep = 0; rep < 5; rep++) {
            swfs_coherence *co = NULL;
            double t = swfs_wall_seconds();
            if (swfs_coherence_compute(c, 1e-3, &o, &co)) { fprintf(stderr, "%s\n", swfs_last_error()); return 1; }
            t = swfs_wall_seconds() - t;
            if (t < best) best = t;
            used = co->method;
            maxlag = co->max_lag;
            swfs_coherence_free(co);
        }
        printf("%-6s (%s): %8.1f ms best of 5, %zu frames of %zux%zu, lags 0..%ld\n", names[m],
               used == SWFS_COH_FFT ? "fft" : "direct", 1e3 * best, nt, n, n, maxlag);
    }
    swfs_cplx_free(c);
    return 0;
}

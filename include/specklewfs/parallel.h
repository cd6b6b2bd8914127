/* A minimal parallel for-loop over chunks with pthreads, for the simulators' bulk work
 * (screen FFT rows/columns, spectrum draws, frames). Chunk c covers items
 * [c*chunk, min((c+1)*chunk, n)); worker w runs chunks w, w + T, w + 2T, ... (the caller's
 * thread is worker 0). Results are independent of the number of threads as long as each
 * chunk writes only its own outputs. */
#ifndef SWFS_PARALLEL_H
#define SWFS_PARALLEL_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef void (*swfs_parallel_fn)(void *ctx, size_t begin, size_t end, int worker);

/* requested <= 0: online CPUs; the result is clamped to [1, max_useful] (max_useful 0: no cap). */
int swfs_parallel_threads(int requested, size_t max_useful);
/* Run fn over [0, n) in chunks on nthreads workers. If a thread cannot be started its
 * chunks run on the caller's thread, so this always completes; returns SWFS_OK. */
int swfs_parallel_for(int nthreads, size_t n, size_t chunk, swfs_parallel_fn fn, void *ctx);

/* The library parallelizes over frames with its own workers (engine, simulators) and
 * never changes BLAS's thread count itself: that is process-wide state, the
 * application's to choose. Its workers run best with a single-threaded BLAS (a threaded
 * BLAS inside every small GEMM only adds contention); the command line sets 1 at start.
 * These set and read OpenBLAS's thread count for applications that want the same. */
/* Seconds on the monotonic clock since an arbitrary epoch (for rates and timings). */
double swfs_wall_seconds(void);
/* Sleep until swfs_wall_seconds() reaches mono (at once if it has; signals do not cut it short). */
void swfs_sleep_until(double mono);

void swfs_blas_set_threads(int n);
int swfs_blas_threads(void);

SWFS_END_DECLS

#endif

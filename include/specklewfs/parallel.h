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

/* The bytes of memory the system can give without swapping: /proc/meminfo's MemAvailable
 * (the free memory and the page cache it can drop), else the free pages; -1 if neither is
 * known. For runs that choose how many large solves to hold at once. */
double swfs_mem_available(void);
/* Seconds on the monotonic clock since an arbitrary epoch (for rates and timings). */
double swfs_wall_seconds(void);
/* Sleep until swfs_wall_seconds() reaches mono (at once if it has; signals do not cut it short). */
void swfs_sleep_until(double mono);

/* The library parallelizes over frames with its own workers (engine, simulators) and
 * never changes BLAS's thread count itself: that is process-wide state, the
 * application's to choose. Its workers run best with a single-threaded BLAS (a threaded
 * BLAS inside every small GEMM only adds contention); the command line sets 1 at start.
 * These set and read OpenBLAS's thread count for applications that want the same. */
void swfs_blas_set_threads(int n);
int swfs_blas_threads(void);

/* OpenBLAS picks its kernels when it is loaded, from the CPU's model number. A CPU newer
 * than the OpenBLAS build gets its generic fallback: Debian 12's OpenBLAS 0.3.21 runs its
 * SSE3 "Prescott" kernels on a Xeon of model 207, which has AVX-512, and the GEMMs of teach,
 * learn and pupil's joint fit then take 2-3 times as long (docs/ARCHITECTURE.md, "BLAS
 * kernels"). OPENBLAS_CORETYPE, read when OpenBLAS is loaded, names the kernels instead.
 * swfs_blas_kernel fills `core` with the kernels in use ("Prescott", "SkylakeX", ...;
 * "unknown" without OpenBLAS's corename) and `better` with the kernels this CPU can run
 * when those in use are older than AVX2 on a CPU with AVX2 and FMA ("SkylakeX" with
 * AVX-512 F/CD/BW/DQ/VL, else "Haswell"), else "". `fallback` is the core OpenBLAS chose by
 * itself when swfs_blas_reexec switched it (else ""). */
typedef struct swfs_blas_kernel {
    char core[32];
    char better[16];
    char fallback[32];
} swfs_blas_kernel_info;
void swfs_blas_kernel(swfs_blas_kernel_info *k);
/* For programs (the command line, the benchmarks; call it first in main): when the kernels
 * are older than the CPU and OPENBLAS_CORETYPE is not set, sets it to `better` and runs the
 * program again from its start (execv of /proc/self/exe with the same argv), so OpenBLAS
 * loads the right kernels. Returns only when nothing was done (0) or the execv failed (-1:
 * the program goes on with the old kernels). A library cannot do this for its caller:
 * Python's package warns at import instead (python/specklewfs/__init__.py). */
int swfs_blas_reexec(char *const argv[]);

SWFS_END_DECLS

#endif

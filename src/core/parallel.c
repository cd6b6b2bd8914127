/* Parallel for-loop over chunks: see include/specklewfs/parallel.h. */
#include "specklewfs/parallel.h"

#include <cblas.h>
#include "specklewfs/status.h"

#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <time.h>
#include <unistd.h>

int swfs_parallel_threads(int requested, size_t max_useful)
{
    long t = requested;
    if (t <= 0) {
        t = sysconf(_SC_NPROCESSORS_ONLN);
        if (t < 1) t = 1;
    }
    if (t > 256) t = 256;
    if (max_useful && (size_t)t > max_useful) t = (long)max_useful;
    return t < 1 ? 1 : (int)t;
}

struct pf_job {
    swfs_parallel_fn fn;
    void *ctx;
    size_t n, chunk, nchunks;
    int worker, stride;
    pthread_t thread;
};

static void *pf_main(void *arg)
{
    const struct pf_job *j = arg;
    for (size_t c = (size_t)j->worker; c < j->nchunks; c += (size_t)j->stride) {
        const size_t b = c * j->chunk, e = b + j->chunk < j->n ? b + j->chunk : j->n;
        j->fn(j->ctx, b, e, j->worker);
    }
    return NULL;
}

int swfs_parallel_for(int nthreads, size_t n, size_t chunk, swfs_parallel_fn fn, void *ctx)
{
    if (!n) return SWFS_OK;
    if (!chunk) chunk = 1;
    const size_t nchunks = (n + chunk - 1) / chunk;
    int nt = nthreads < 1 ? 1 : nthreads;
    if ((size_t)nt > nchunks) nt = (int)nchunks;
    struct pf_job local[8] = {{0}}, *jobs = nt <= 8 ? local : malloc((size_t)nt * sizeof *jobs);
    if (!jobs) { /* no memory for job records: run serially */
        struct pf_job one = {fn, ctx, n, chunk, nchunks, 0, 1, 0};
        pf_main(&one);
        return SWFS_OK;
    }
    int started = 0; /* workers 1..started are running */
    for (int w = 0; w < nt; w++) {
        jobs[w] = (struct pf_job){fn, ctx, n, chunk, nchunks, w, nt, 0};
        if (w > 0 && started == w - 1 && pthread_create(&jobs[w].thread, NULL, pf_main, &jobs[w]) == 0) started = w;
    }
    for (int w = started + 1; w < nt; w++) pf_main(&jobs[w]); /* workers that did not start */
    pf_main(&jobs[0]);
    for (int w = 1; w <= started; w++) pthread_join(jobs[w].thread, NULL);
    if (jobs != local) free(jobs);
    return SWFS_OK;
}

double swfs_mem_available(void)
{
    FILE *f = fopen("/proc/meminfo", "r");
    char line[256];
    double kb = -1;
    while (f && fgets(line, sizeof line, f))
        if (sscanf(line, "MemAvailable: %lf kB", &kb) == 1) break;
    if (f) fclose(f);
    if (kb >= 0) return 1024.0 * kb;
    const long pages = sysconf(_SC_AVPHYS_PAGES), psize = sysconf(_SC_PAGESIZE);
    return pages > 0 && psize > 0 ? (double)pages * (double)psize : -1.0;
}

void swfs_blas_set_threads(int n) { openblas_set_num_threads(n < 1 ? 1 : n); }
int swfs_blas_threads(void) { return openblas_get_num_threads(); }

/* OpenBLAS's x86 kernels that use AVX2 and FMA (a name not here is older, or not x86) */
static int blas_core_modern(const char *core)
{
    static const char *const modern[] = {"Haswell", "Zen", "SkylakeX", "Cooperlake", "SapphireRapids"};
    for (size_t i = 0; i < sizeof modern / sizeof modern[0]; i++)
        if (!strcasecmp(core, modern[i])) return 1;
    return 0;
}

void swfs_blas_kernel(swfs_blas_kernel_info *k)
{
    memset(k, 0, sizeof *k);
    const char *core = openblas_get_corename();
    snprintf(k->core, sizeof k->core, "%s", core && *core ? core : "unknown");
    const char *fb = getenv("SWFS_BLAS_FALLBACK");
    if (fb) snprintf(k->fallback, sizeof k->fallback, "%s", fb);
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    if (!core || blas_core_modern(core)) return;
    __builtin_cpu_init();
    if (!(__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))) return;
    const int avx512 = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512cd") &&
                       __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq") &&
                       __builtin_cpu_supports("avx512vl");
    snprintf(k->better, sizeof k->better, "%s", avx512 ? "SkylakeX" : "Haswell");
#endif
}

int swfs_blas_reexec(char *const argv[])
{
    if (getenv("OPENBLAS_CORETYPE")) return 0; /* chosen by the user, or by the run before this */
    swfs_blas_kernel_info k;
    swfs_blas_kernel(&k);
    if (!k.better[0] || !argv || !argv[0]) return 0;
    if (setenv("OPENBLAS_CORETYPE", k.better, 1) || setenv("SWFS_BLAS_FALLBACK", k.core, 1)) return -1;
    execv("/proc/self/exe", argv);
    unsetenv("OPENBLAS_CORETYPE"); /* no /proc: go on with the kernels loaded */
    unsetenv("SWFS_BLAS_FALLBACK");
    return -1;
}

double swfs_wall_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

void swfs_sleep_until(double mono)
{
    for (;;) {
        const double dt = mono - swfs_wall_seconds();
        if (dt <= 0) return;
        struct timespec ts = {(time_t)dt, (long)((dt - (double)(time_t)dt) * 1e9)};
        nanosleep(&ts, NULL); /* an interrupted sleep goes round again */
    }
}

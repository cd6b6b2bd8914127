/* Vectorized sin/cos and exp(i phi): see include/specklewfs/kernels.h.
 *
 * This is the one file compiled with -ffast-math -fopenmp-simd -fno-finite-math-only
 * (CMakeLists.txt): with them glibc's <math.h> declares sinf/cosf/sin/cos as SIMD
 * functions and gcc calls libmvec's vector variants. Keep this file to simple loops over
 * finite inputs; anything that needs IEEE NaN/Inf semantics belongs elsewhere. Outputs
 * are produced in chunks through small stack buffers so that no call allocates. */
#include "specklewfs/kernels.h"

#include <math.h>

enum { CHUNK = 512 };

void swfs_sincos_f(const float *restrict x, float *restrict s, float *restrict c, size_t n)
{
    /* Two separate loops: one fused loop becomes a scalar sincosf call. */
#pragma omp simd
    for (size_t k = 0; k < n; k++) s[k] = sinf(x[k]);
#pragma omp simd
    for (size_t k = 0; k < n; k++) c[k] = cosf(x[k]);
}

void swfs_sincos_d(const double *restrict x, double *restrict s, double *restrict c, size_t n)
{
#pragma omp simd
    for (size_t k = 0; k < n; k++) s[k] = sin(x[k]);
#pragma omp simd
    for (size_t k = 0; k < n; k++) c[k] = cos(x[k]);
}

void swfs_expi_f(const float *restrict phi, const float *restrict amp, float complex *restrict out, size_t n)
{
    float s[CHUNK], c[CHUNK];
    float *o = (float *)out;
    for (size_t k0 = 0; k0 < n; k0 += CHUNK) {
        const size_t m = n - k0 < CHUNK ? n - k0 : CHUNK;
        swfs_sincos_f(phi + k0, s, c, m);
        if (amp) {
            for (size_t k = 0; k < m; k++) {
                o[2 * (k0 + k)] = amp[k0 + k] * c[k];
                o[2 * (k0 + k) + 1] = amp[k0 + k] * s[k];
            }
        } else {
            for (size_t k = 0; k < m; k++) {
                o[2 * (k0 + k)] = c[k];
                o[2 * (k0 + k) + 1] = s[k];
            }
        }
    }
}

void swfs_expi_d(const double *restrict phi, const double *restrict amp, double complex *restrict out, size_t n)
{
    double s[CHUNK], c[CHUNK];
    double *o = (double *)out;
    for (size_t k0 = 0; k0 < n; k0 += CHUNK) {
        const size_t m = n - k0 < CHUNK ? n - k0 : CHUNK;
        swfs_sincos_d(phi + k0, s, c, m);
        if (amp) {
            for (size_t k = 0; k < m; k++) {
                o[2 * (k0 + k)] = amp[k0 + k] * c[k];
                o[2 * (k0 + k) + 1] = amp[k0 + k] * s[k];
            }
        } else {
            for (size_t k = 0; k < m; k++) {
                o[2 * (k0 + k)] = c[k];
                o[2 * (k0 + k) + 1] = s[k];
            }
        }
    }
}

/* Vectorized elementwise kernels for the per-frame path.
 *
 * exp(i phi) is the inner loop of the speckle computation (one per pupil sample per WFS
 * frame). glibc's cexp/sincos do not vectorize and would dominate the frame time
 * (docs/PERFORMANCE: 912 us for 163^2 points with cexp, ~17 us vectorized). These kernels
 * live in src/optics/kernels_fastmath.c, the one file compiled with the math flags that
 * let gcc call glibc's libmvec (_ZGV*_sinf / _ZGV*_cosf); sin and cos are separate simple
 * loops because gcc otherwise fuses them into a scalar sincos call. Accuracy is that of
 * libmvec: ~1e-7 absolute in float, ~1e-15 in double (tests/test_kernels.c). Inputs must
 * be finite. Nothing allocates. */
#ifndef SWFS_KERNELS_H
#define SWFS_KERNELS_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

/* s[k] = sin(x[k]), c[k] = cos(x[k]); x, s, c must not overlap. */
void swfs_sincos_f(const float *x, float *s, float *c, size_t n);
void swfs_sincos_d(const double *x, double *s, double *c, size_t n);

/* out[k] = amp[k] * exp(i phi[k]) (amp NULL: 1). */
void swfs_expi_f(const float *phi, const float *amp, swfs_complexf *out, size_t n);
void swfs_expi_d(const double *phi, const double *amp, swfs_complex *out, size_t n);

SWFS_END_DECLS

#endif

/* Real and complex 2-D maps and 3-D cubes in FITS order: x (NAXIS1) fastest, then y,
 * then frame. A map is a cube with nz = 1. Buffers are 64-byte aligned and owned by
 * the struct; swfs_*_free(NULL) is a no-op. */
#ifndef SWFS_ARRAY_H
#define SWFS_ARRAY_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_real {
    size_t nx, ny, nz;
    double *data;
} swfs_real;

typedef struct swfs_cplx {
    size_t nx, ny, nz;
    swfs_complex *data;
} swfs_cplx;

/* Zero-filled; NULL (with swfs_last_error set) on failure or on a zero dimension. */
swfs_real *swfs_real_alloc(size_t nx, size_t ny, size_t nz);
swfs_cplx *swfs_cplx_alloc(size_t nx, size_t ny, size_t nz);
void swfs_real_free(swfs_real *a);
void swfs_cplx_free(swfs_cplx *a);
swfs_real *swfs_real_copy(const swfs_real *a);
swfs_cplx *swfs_cplx_copy(const swfs_cplx *a);

static inline size_t swfs_real_size(const swfs_real *a) { return a->nx * a->ny * a->nz; }
static inline size_t swfs_cplx_size(const swfs_cplx *a) { return a->nx * a->ny * a->nz; }
/* Pointer to frame k. */
static inline double *swfs_real_frame(const swfs_real *a, size_t k) { return a->data + k * a->nx * a->ny; }
static inline swfs_complex *swfs_cplx_frame(const swfs_cplx *a, size_t k) { return a->data + k * a->nx * a->ny; }

/* Aligned raw buffers for work arrays (free with swfs_free). */
void *swfs_malloc(size_t bytes);
void *swfs_calloc(size_t n, size_t size);
void swfs_free(void *p);

SWFS_END_DECLS

#endif

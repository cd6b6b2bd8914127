/* Compressed sparse row (CSR) matrices: built once (e.g. the actuator -> pupil-grid
 * interpolation), applied every frame without allocation. */
#ifndef SWFS_SPARSE_H
#define SWFS_SPARSE_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_sparse {
    size_t nrows, ncols, nnz;
    size_t *row_ptr;  /* nrows + 1 */
    size_t *col;      /* nnz */
    double *val;      /* nnz */
} swfs_sparse;

/* Empty matrix with room for nnz entries (row_ptr zeroed). */
swfs_sparse *swfs_sparse_alloc(size_t nrows, size_t ncols, size_t nnz);
void swfs_sparse_free(swfs_sparse *s);
/* y = S x  (x: ncols, y: nrows). */
void swfs_sparse_apply(const swfs_sparse *s, const double *x, double *y);
/* y[r] = (S x)[r] for the nr rows listed in rows only (the other entries of y untouched): the
 * DM surface on the pupil's samples alone, for instance. */
void swfs_sparse_apply_rows(const swfs_sparse *s, const double *x, const size_t *rows, size_t nr, double *y);
/* Y = S X for m column vectors stored row-major (X: ncols x m, Y: nrows x m). */
void swfs_sparse_apply_multi(const swfs_sparse *s, const double *X, double *Y, size_t m);

SWFS_END_DECLS

#endif

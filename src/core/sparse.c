#include "specklewfs/sparse.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <stdlib.h>
#include <string.h>

swfs_sparse *swfs_sparse_alloc(size_t nrows, size_t ncols, size_t nnz)
{
    swfs_sparse *s = calloc(1, sizeof *s);
    if (!s) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    s->nrows = nrows; s->ncols = ncols; s->nnz = nnz;
    s->row_ptr = swfs_calloc(nrows + 1, sizeof *s->row_ptr);
    s->col = swfs_calloc(nnz ? nnz : 1, sizeof *s->col);
    s->val = swfs_calloc(nnz ? nnz : 1, sizeof *s->val);
    if (!s->row_ptr || !s->col || !s->val) { swfs_sparse_free(s); return NULL; }
    return s;
}

void swfs_sparse_free(swfs_sparse *s)
{
    if (!s) return;
    swfs_free(s->row_ptr); swfs_free(s->col); swfs_free(s->val);
    free(s);
}

/* (S x)[r] */
static inline double row_dot(const swfs_sparse *s, size_t r, const double *x)
{
    double acc = 0.0;
    for (size_t k = s->row_ptr[r]; k < s->row_ptr[r + 1]; k++) acc += s->val[k] * x[s->col[k]];
    return acc;
}

void swfs_sparse_apply(const swfs_sparse *s, const double *x, double *y)
{
    for (size_t r = 0; r < s->nrows; r++) y[r] = row_dot(s, r, x);
}

void swfs_sparse_apply_rows(const swfs_sparse *s, const double *x, const size_t *rows, size_t nr, double *y)
{
    for (size_t i = 0; i < nr; i++) y[rows[i]] = row_dot(s, rows[i], x);
}

void swfs_sparse_apply_multi(const swfs_sparse *s, const double *X, double *Y, size_t m)
{
    for (size_t r = 0; r < s->nrows; r++) {
        double *yr = Y + r * m;
        memset(yr, 0, m * sizeof *yr);
        for (size_t k = s->row_ptr[r]; k < s->row_ptr[r + 1]; k++) {
            const double v = s->val[k];
            const double *xr = X + s->col[k] * m;
            for (size_t j = 0; j < m; j++) yr[j] += v * xr[j];
        }
    }
}

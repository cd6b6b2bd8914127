#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

void *swfs_malloc(size_t bytes)
{
    void *p = NULL;
    if (bytes == 0) bytes = 1;
    if (posix_memalign(&p, 64, bytes) != 0) {
        swfs_fail(SWFS_ERR_NOMEM, "out of memory allocating %zu bytes", bytes);
        return NULL;
    }
    return p;
}

void *swfs_calloc(size_t n, size_t size)
{
    if (size && n > SIZE_MAX / size) {
        swfs_fail(SWFS_ERR_NOMEM, "allocation of %zu x %zu bytes overflows", n, size);
        return NULL;
    }
    void *p = swfs_malloc(n * size);
    if (p) memset(p, 0, n * size);
    return p;
}

void swfs_free(void *p) { free(p); }

static int dims_ok(size_t nx, size_t ny, size_t nz, size_t elem)
{
    if (nx == 0 || ny == 0 || nz == 0) {
        swfs_fail(SWFS_ERR_ARG, "array dimensions %zux%zux%zu contain a zero", nx, ny, nz);
        return 0;
    }
    if (nx > SIZE_MAX / ny || nx * ny > SIZE_MAX / nz || nx * ny * nz > SIZE_MAX / elem) {
        swfs_fail(SWFS_ERR_NOMEM, "array %zux%zux%zu is too large", nx, ny, nz);
        return 0;
    }
    return 1;
}

swfs_real *swfs_real_alloc(size_t nx, size_t ny, size_t nz)
{
    if (!dims_ok(nx, ny, nz, sizeof(double))) return NULL;
    swfs_real *a = malloc(sizeof *a);
    if (!a) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    a->nx = nx; a->ny = ny; a->nz = nz;
    a->data = swfs_calloc(nx * ny * nz, sizeof(double));
    if (!a->data) { free(a); return NULL; }
    return a;
}

swfs_cplx *swfs_cplx_alloc(size_t nx, size_t ny, size_t nz)
{
    if (!dims_ok(nx, ny, nz, sizeof(double complex))) return NULL;
    swfs_cplx *a = malloc(sizeof *a);
    if (!a) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    a->nx = nx; a->ny = ny; a->nz = nz;
    a->data = swfs_calloc(nx * ny * nz, sizeof(double complex));
    if (!a->data) { free(a); return NULL; }
    return a;
}

void swfs_real_free(swfs_real *a) { if (a) { swfs_free(a->data); free(a); } }
void swfs_cplx_free(swfs_cplx *a) { if (a) { swfs_free(a->data); free(a); } }

swfs_real *swfs_real_copy(const swfs_real *a)
{
    swfs_real *b = swfs_real_alloc(a->nx, a->ny, a->nz);
    if (b) memcpy(b->data, a->data, swfs_real_size(a) * sizeof(double));
    return b;
}

swfs_cplx *swfs_cplx_copy(const swfs_cplx *a)
{
    swfs_cplx *b = swfs_cplx_alloc(a->nx, a->ny, a->nz);
    if (b) memcpy(b->data, a->data, swfs_cplx_size(a) * sizeof(double complex));
    return b;
}

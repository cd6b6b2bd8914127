/* The generic linear speckle model's basis on the pupil grid: see include/specklewfs/lmodel.h. */
#include "specklewfs/lmodel.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

void swfs_dm_registration_default(swfs_dm_registration *r)
{
    memset(r, 0, sizeof *r);
}

void swfs_dm_to_pupil(const swfs_dm_registration *r, size_t gx, size_t gy, double u, double v, double *x, double *y)
{
    double dx = (u - 0.5 * (double)(gx - 1)) * r->pitch, dy = (v - 0.5 * (double)(gy - 1)) * r->pitch;
    if (r->flip_x) dx = -dx;
    const double c = cos(r->rot), s = sin(r->rot);
    *x = r->x0 + c * dx - s * dy;
    *y = r->y0 + s * dx + c * dy;
}

void swfs_pupil_to_dm(const swfs_dm_registration *r, size_t gx, size_t gy, double x, double y, double *u, double *v)
{
    const double c = cos(r->rot), s = sin(r->rot), X = x - r->x0, Y = y - r->y0;
    double dx = c * X + s * Y, dy = -s * X + c * Y;
    if (r->flip_x) dx = -dx;
    *u = dx / r->pitch + 0.5 * (double)(gx - 1);
    *v = dy / r->pitch + 0.5 * (double)(gy - 1);
}

/* Keys' cubic convolution kernel, a = -1/2: interpolates, C1, reproduces quadratics. */
static double keys(double t)
{
    t = fabs(t);
    if (t < 1) return (1.5 * t - 2.5) * t * t + 1;
    if (t < 2) return ((-0.5 * t + 2.5) * t - 4) * t + 2;
    return 0;
}

/* A CSR matrix built row by row (rows in order), growing as needed. */
typedef struct builder {
    swfs_sparse *s;
    size_t cap;
} builder;

static int grow(builder *b, size_t need)
{
    if (need <= b->cap) return SWFS_OK;
    size_t cap = b->cap ? b->cap : 1024;
    while (cap < need) {
        if (cap > SIZE_MAX / 2 / sizeof(double)) return swfs_fail(SWFS_ERR_NOMEM, "basis: too many nonzeros");
        cap *= 2;
    }
    size_t *c = realloc(b->s->col, cap * sizeof *c);
    if (c) b->s->col = c;
    double *v = c ? realloc(b->s->val, cap * sizeof *v) : NULL;
    if (v) b->s->val = v;
    if (!c || !v) return swfs_fail(SWFS_ERR_NOMEM, "basis: out of memory for %zu nonzeros", cap);
    b->cap = cap;
    return SWFS_OK;
}

/* Append the nonzeros of the dense row `row` (nk values) as the next row. */
static int push_row(builder *b, size_t r, const double *row, size_t nk)
{
    size_t nz = 0;
    for (size_t k = 0; k < nk; k++) nz += row[k] != 0.0;
    int rc = grow(b, b->s->nnz + nz);
    if (rc) return rc;
    for (size_t k = 0; k < nk; k++)
        if (row[k] != 0.0) {
            b->s->col[b->s->nnz] = k;
            b->s->val[b->s->nnz++] = row[k];
        }
    b->s->row_ptr[r + 1] = b->s->nnz;
    return SWFS_OK;
}

static int begin(builder *b, size_t nrows, size_t nk)
{
    b->cap = 0;
    /* swfs_sparse_alloc's arrays are aligned allocations; this builder owns plain ones. */
    b->s = calloc(1, sizeof *b->s);
    if (b->s) b->s->row_ptr = calloc(nrows + 1, sizeof *b->s->row_ptr);
    if (!b->s || !b->s->row_ptr) {
        if (b->s) free(b->s);
        b->s = NULL;
        return swfs_fail(SWFS_ERR_NOMEM, "basis: out of memory");
    }
    b->s->nrows = nrows;
    b->s->ncols = nk;
    return grow(b, 1024);
}

static void discard(builder *b)
{
    if (!b->s) return;
    free(b->s->row_ptr); free(b->s->col); free(b->s->val); free(b->s);
    b->s = NULL;
}

/* Hand the builder's matrix over as an swfs_sparse (whose arrays swfs_sparse_free frees). */
static int finish(builder *b, swfs_sparse **out)
{
    swfs_sparse *s = swfs_sparse_alloc(b->s->nrows, b->s->ncols, b->s->nnz);
    if (!s) { discard(b); return swfs_fail_context(SWFS_ERR_NOMEM, "basis"); }
    memcpy(s->row_ptr, b->s->row_ptr, (s->nrows + 1) * sizeof *s->row_ptr);
    if (s->nnz) {
        memcpy(s->col, b->s->col, s->nnz * sizeof *s->col);
        memcpy(s->val, b->s->val, s->nnz * sizeof *s->val);
    }
    discard(b);
    *out = s;
    return SWFS_OK;
}

/* Sizes that do not wrap, and finite values (a NaN would reach every speckle). */
static int check_cube(const double *cube, size_t a, size_t b, size_t nk, const char *what)
{
    if (!a || !b || !nk) return swfs_fail(SWFS_ERR_SHAPE, "basis: empty %s (%zu x %zu x %zu)", what, a, b, nk);
    if (a > SIZE_MAX / b || a * b > SIZE_MAX / nk / sizeof(double))
        return swfs_fail(SWFS_ERR_VALUE, "basis: %s %zu x %zu x %zu is too large", what, a, b, nk);
    const size_t n = a * b * nk;
    char val[48];
    for (size_t k = 0; k < n; k++)
        if (!isfinite(cube[k]))
            return swfs_fail(SWFS_ERR_VALUE, "basis: %s value %zu (x %zu, y %zu, function %zu) %s; expected finite",
                             what, k, k % a, k / a % b, k / (a * b), swfs_value_words(cube[k], val, sizeof val));
    return SWFS_OK;
}

int swfs_basis_from_grid(swfs_sparse **B, const double *cube, size_t gx, size_t gy, size_t nk,
                         const swfs_dm_registration *reg, const double *mask, size_t npup, double pupdx,
                         size_t *n_outside)
{
    *B = NULL;
    *n_outside = 0;
    int rc = check_cube(cube, gx, gy, nk, "DM grid");
    swfs_sparse *T = NULL;
    if (!rc) rc = swfs_grid_interp(&T, gx, gy, reg, mask, npup, pupdx, n_outside);
    if (rc) return rc;
    /* row r of B = row r of T times the cube's grid values */
    const size_t gn = gx * gy;
    double *row = malloc(nk * sizeof *row);
    builder b = {0};
    rc = row ? begin(&b, npup * npup, nk) : swfs_fail(SWFS_ERR_NOMEM, "basis: out of memory");
    for (size_t r = 0; r < T->nrows && !rc; r++) {
        memset(row, 0, nk * sizeof *row);
        for (size_t z = T->row_ptr[r]; z < T->row_ptr[r + 1]; z++) {
            const double w = T->val[z], *src = cube + T->col[z];
            for (size_t k = 0; k < nk; k++) row[k] += w * src[k * gn];
        }
        rc = push_row(&b, r, row, nk);
    }
    free(row);
    swfs_sparse_free(T);
    if (rc) { discard(&b); return rc; }
    return finish(&b, B);
}

int swfs_grid_interp(swfs_sparse **T, size_t gx, size_t gy, const swfs_dm_registration *reg, const double *mask,
                     size_t npup, double pupdx, size_t *n_outside)
{
    *T = NULL;
    *n_outside = 0;
    if (!gx || !gy || gx > SIZE_MAX / gy) return swfs_fail(SWFS_ERR_SHAPE, "basis: DM grid %zu x %zu", gx, gy);
    if (!(reg->pitch > 0) || !isfinite(reg->pitch) || !isfinite(reg->x0) || !isfinite(reg->y0) || !isfinite(reg->rot))
        return swfs_fail(SWFS_ERR_VALUE, "basis: the DM registration needs a finite pitch > 0 [m] and finite offset "
                         "and rotation (pitch %g, offset %g, %g m, rotation %g rad)", reg->pitch, reg->x0, reg->y0,
                         reg->rot);
    const size_t gn = gx * gy;
    double *row = calloc(gn, sizeof *row);
    size_t *touched = malloc(16 * sizeof *touched);
    builder b = {0};
    int rc = row && touched ? begin(&b, npup * npup, gn) : swfs_fail(SWFS_ERR_NOMEM, "basis: out of memory");
    const double c0 = 0.5 * (double)(npup - 1);
    for (size_t q = 0; q < npup && !rc; q++)
        for (size_t i = 0; i < npup && !rc; i++) {
            const size_t r = q * npup + i;
            size_t nt = 0;
            if (mask[r] > 0) {
                double u, v;
                swfs_pupil_to_dm(reg, gx, gy, ((double)i - c0) * pupdx, ((double)q - c0) * pupdx, &u, &v);
                if (u < -1 || v < -1 || u > (double)gx || v > (double)gy) (*n_outside)++;
                const double fu = floor(u), fv = floor(v);
                for (int dj = -1; dj <= 2; dj++) {
                    const double wv = keys(v - (fv + dj)), jj = fv + dj;
                    if (wv == 0) continue;
                    const size_t j = jj < 0 ? 0 : jj > (double)(gy - 1) ? gy - 1 : (size_t)jj;
                    for (int di = -1; di <= 2; di++) {
                        const double w = wv * keys(u - (fu + di)), ii = fu + di;
                        if (w == 0) continue;
                        const size_t col = j * gx + (ii < 0 ? 0 : ii > (double)(gx - 1) ? gx - 1 : (size_t)ii);
                        size_t a = 0;
                        while (a < nt && touched[a] != col) a++;
                        if (a == nt) touched[nt++] = col;
                        row[col] += w;
                    }
                }
            }
            /* the row's entries in column order (the stencil clamped at an edge may repeat a point) */
            for (size_t a = 1; a < nt; a++)
                for (size_t c = a; c > 0 && touched[c - 1] > touched[c]; c--) {
                    const size_t t = touched[c];
                    touched[c] = touched[c - 1];
                    touched[c - 1] = t;
                }
            rc = grow(&b, b.s->nnz + nt);
            for (size_t a = 0; a < nt && !rc; a++) {
                if (row[touched[a]] != 0) {
                    b.s->col[b.s->nnz] = touched[a];
                    b.s->val[b.s->nnz++] = row[touched[a]];
                }
                row[touched[a]] = 0;
            }
            if (!rc) b.s->row_ptr[r + 1] = b.s->nnz;
        }
    free(row);
    free(touched);
    if (rc) { discard(&b); return rc; }
    return finish(&b, T);
}

int swfs_basis_from_pupil(swfs_sparse **B, const double *cube, size_t npup, size_t nk, const double *mask)
{
    *B = NULL;
    int rc = check_cube(cube, npup, npup, nk, "pupil-grid basis");
    if (rc) return rc;
    const size_t ng = npup * npup;
    double *row = malloc(nk * sizeof *row);
    builder b = {0};
    if (!row) return swfs_fail(SWFS_ERR_NOMEM, "basis: out of memory");
    if ((rc = begin(&b, ng, nk))) { free(row); return rc; }
    for (size_t r = 0; r < ng && !rc; r++) {
        for (size_t k = 0; k < nk; k++) row[k] = mask[r] > 0 ? cube[k * ng + r] : 0.0;
        rc = push_row(&b, r, row, nk);
    }
    free(row);
    if (rc) { discard(&b); return rc; }
    return finish(&b, B);
}

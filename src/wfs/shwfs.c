/* Actuator geometry, the Shack-Hartmann slope operator and the interaction matrix
 * (see wfs.h). */
#include "specklewfs/wfs.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <lapacke.h>

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

int swfs_actuators_square(double diam, double pitch, double margin, double **xy, size_t *nact)
{
    *xy = NULL;
    *nact = 0;
    if (!(diam > 0) || !(pitch > 0) || !(margin >= 0) || pitch > diam)
        return swfs_fail(SWFS_ERR_ARG, "actuator layout: diameter %g m, pitch %g m, margin %g m out of range",
                         diam, pitch, margin);
    const double r = 0.5 * diam + margin;
    if (!(r / pitch <= 2.0 * SWFS_HEXAPOLAR_MAX_RINGS))
        return swfs_fail(SWFS_ERR_ARG, "actuator layout: a square grid of pitch %g m over a radius of %g m has more "
                         "than %d actuators across", pitch, r, 4 * SWFS_HEXAPOLAR_MAX_RINGS);
    /* The grid is centred on the pupil, actuators on (i, j) pitch: an odd count across, the
     * layout of most square-grid DMs. */
    const long m = (long)floor(r / pitch);
    double *p = malloc(2 * (size_t)(2 * m + 1) * (size_t)(2 * m + 1) * sizeof *p);
    if (!p) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    size_t n = 0;
    for (long j = -m; j <= m; j++)
        for (long i = -m; i <= m; i++) {
            const double x = (double)i * pitch, y = (double)j * pitch;
            if (hypot(x, y) > r) continue;
            p[2 * n] = x;
            p[2 * n + 1] = y;
            n++;
        }
    *xy = p;
    *nact = n;
    return SWFS_OK;
}

int swfs_actuators_hexapolar(double diam, double pitch, double margin, double **xy, size_t *nact)
{
    *xy = NULL;
    *nact = 0;
    if (!(diam > 0) || !(pitch > 0) || !(margin >= 0) || pitch > diam)
        return swfs_fail(SWFS_ERR_ARG, "actuator layout: diameter %g m, pitch %g m, margin %g m out of range",
                         diam, pitch, margin);
    double need = 0.5 * diam + margin;
    /* Each ring adds 6k actuators: 200 rings are 120,601 of them, beyond any DM. */
    if (!(need / pitch <= SWFS_HEXAPOLAR_MAX_RINGS))
        return swfs_fail(SWFS_ERR_ARG, "actuator layout: covering radius %g m (diameter %g m / 2 + margin %g m) at a "
                         "pitch of %g m needs %.3g rings of actuators; at most %d (%d actuators)", need, diam, margin,
                         pitch, ceil(need / pitch), SWFS_HEXAPOLAR_MAX_RINGS,
                         1 + 3 * SWFS_HEXAPOLAR_MAX_RINGS * (SWFS_HEXAPOLAR_MAX_RINGS + 1));
    size_t nring = 1;
    /* The ring-k polygon (6k sides) covers radius k pitch cos(pi / 6k). */
    while ((double)nring * pitch * cos(M_PI / (6.0 * (double)nring)) < need) nring++;
    size_t n = 1 + 3 * nring * (nring + 1);
    double *p = malloc(2 * n * sizeof *p);
    if (!p) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    p[0] = p[1] = 0;
    size_t k = 1;
    for (size_t r = 1; r <= nring; r++) {
        size_t m = 6 * r;
        /* Stagger alternate rings by half a step: a "modified" hexapolar pattern that
         * avoids radial rows of actuators (and co-circular Delaunay ties along them). */
        double off = (r % 2) ? 0.0 : M_PI / (double)m;
        for (size_t j = 0; j < m; j++) {
            double th = off + 2 * M_PI * (double)j / (double)m;
            p[2 * k] = (double)r * pitch * cos(th);
            p[2 * k + 1] = (double)r * pitch * sin(th);
            k++;
        }
    }
    *xy = p;
    *nact = n;
    return SWFS_OK;
}

void swfs_shwfs_free(swfs_shwfs *w)
{
    if (!w) return;
    swfs_sparse_free(w->S);
    free(w->valid);
    free(w);
}

/* Subaperture index along one axis of a coordinate, or -1 outside. */
static long sub_index(double x, double diam, size_t nsub)
{
    double u = (x + 0.5 * diam) / diam * (double)nsub;
    if (!(u >= 0) || u >= (double)nsub) return -1;
    return (long)floor(u);
}

int swfs_shwfs_create(swfs_shwfs **out, size_t nsub, double diam, const double *mask, size_t npup, double pupdx,
                      double min_illum)
{
    *out = NULL;
    if (nsub == 0 || npup < 2 || !(diam > 0) || !(pupdx > 0))
        return swfs_fail(SWFS_ERR_ARG, "Shack-Hartmann: %zu subapertures, %zu pupil samples of %g m, D = %g m",
                         nsub, npup, pupdx, diam);
    if (diam / (double)nsub < 2 * pupdx)
        return swfs_fail(SWFS_ERR_ARG, "Shack-Hartmann: subaperture %g m spans fewer than 2 pupil samples of %g m",
                         diam / (double)nsub, pupdx);
    swfs_shwfs *w = calloc(1, sizeof *w);
    if (!w) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    w->nsub = nsub; w->nslopes = 2 * nsub * nsub; w->npup = npup; w->pupdx = pupdx; w->diam = diam;
    size_t nsa = nsub * nsub;
    w->valid = calloc(nsa, 1);
    size_t *cnt = calloc(2 * nsa, sizeof *cnt);
    if (!w->valid || !cnt) { free(cnt); swfs_shwfs_free(w); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    const double c0 = 0.5 * (double)(npup - 1);
    /* Pass 1: count pairs per slope (axis 0 = x pairs, 1 = y pairs). */
    for (int pass = 0; pass < 2; pass++) {
        size_t *fill = NULL;
        if (pass == 1) {
            size_t nnz = 0;
            for (size_t s = 0; s < 2 * nsa; s++) nnz += 2 * cnt[s];
            w->S = swfs_sparse_alloc(w->nslopes, npup * npup, nnz);
            fill = calloc(2 * nsa, sizeof *fill);
            if (!w->S || !fill) { free(cnt); free(fill); swfs_shwfs_free(w); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
            /* Full subaperture: pairs a fully illuminated one holds (either axis). */
            double d = diam / (double)nsub;
            double full = (d / pupdx) * (d / pupdx);
            size_t pos = 0;
            for (size_t s = 0; s < 2 * nsa; s++) {
                w->S->row_ptr[s] = pos;
                pos += 2 * cnt[s];
            }
            w->S->row_ptr[2 * nsa] = pos;
            for (size_t sa = 0; sa < nsa; sa++) {
                size_t m = cnt[sa] < cnt[nsa + sa] ? cnt[sa] : cnt[nsa + sa];
                if ((double)m >= min_illum * full && m > 0) { w->valid[sa] = 1; w->nvalid++; }
            }
        }
        for (int axis = 0; axis < 2; axis++)
            for (size_t q = 0; q + (axis == 1) < npup; q++)
                for (size_t p = 0; p + (axis == 0) < npup; p++) {
                    size_t k0 = q * npup + p, k1 = axis == 0 ? k0 + 1 : k0 + npup;
                    if (!(mask[k0] > 0.5) || !(mask[k1] > 0.5)) continue;
                    double mx = ((double)p - c0 + (axis == 0 ? 0.5 : 0.0)) * pupdx;
                    double my = ((double)q - c0 + (axis == 1 ? 0.5 : 0.0)) * pupdx;
                    long a = sub_index(mx, diam, nsub), b = sub_index(my, diam, nsub);
                    if (a < 0 || b < 0) continue;
                    size_t s = (size_t)axis * nsa + (size_t)b * nsub + (size_t)a;
                    if (pass == 0) { cnt[s]++; continue; }
                    size_t sa = (size_t)b * nsub + (size_t)a;
                    if (!w->valid[sa]) continue;
                    size_t at = w->S->row_ptr[s] + 2 * fill[s]++;
                    double v = 1.0 / ((double)cnt[s] * pupdx);
                    w->S->col[at] = k0; w->S->val[at] = -v;
                    w->S->col[at + 1] = k1; w->S->val[at + 1] = v;
                }
        if (pass == 1) {
            /* Invalid subapertures: empty rows (compact the CSR). */
            size_t pos = 0;
            for (size_t s = 0; s < 2 * nsa; s++) {
                size_t b = w->S->row_ptr[s], n = 2 * fill[s];
                w->S->row_ptr[s] = pos;
                memmove(w->S->col + pos, w->S->col + b, n * sizeof *w->S->col);
                memmove(w->S->val + pos, w->S->val + b, n * sizeof *w->S->val);
                pos += n;
            }
            w->S->row_ptr[2 * nsa] = pos;
            w->S->nnz = pos;
            free(fill);
        }
    }
    free(cnt);
    if (w->nvalid == 0) {
        swfs_shwfs_free(w);
        return swfs_fail(SWFS_ERR_VALUE, "Shack-Hartmann: no subaperture is illuminated (check the pupil mask)");
    }
    *out = w;
    return SWFS_OK;
}

int swfs_shwfs_create_valid(swfs_shwfs **out, size_t nsub, double diam, const double *mask, size_t npup,
                            double pupdx, const unsigned char *valid)
{
    if (!valid) return swfs_shwfs_create(out, nsub, diam, mask, npup, pupdx, 0.5);
    /* Every subaperture with a pair of illuminated samples first, then only the map's. */
    int rc = swfs_shwfs_create(out, nsub, diam, mask, npup, pupdx, 0.0);
    if (rc) return rc;
    swfs_shwfs *w = *out;
    const size_t nsa = nsub * nsub;
    for (size_t sa = 0; sa < nsa; sa++)
        if (valid[sa] && !w->valid[sa]) {
            swfs_shwfs_free(w);
            *out = NULL;
            return swfs_fail(SWFS_ERR_VALUE, "valid-subaperture map: subaperture (%zu, %zu) (x, y; index %zu) is used but "
                             "no illuminated pupil sample pair lies in it (expected the map's orientation: x along "
                             "NAXIS1, subaperture (a, b) at b nsub + a, and the pupil of TELDIAM/OBSCUR or --pupil)",
                             sa % nsub, sa / nsub, sa);
        }
    /* Unused subapertures: empty rows, compacted. */
    swfs_sparse *S = w->S;
    size_t pos = 0;
    for (size_t s = 0; s < 2 * nsa; s++) {
        const size_t b = S->row_ptr[s], n = S->row_ptr[s + 1] - b;
        const int keep = valid[s % nsa] != 0;
        S->row_ptr[s] = pos;
        if (keep) {
            memmove(S->col + pos, S->col + b, n * sizeof *S->col);
            memmove(S->val + pos, S->val + b, n * sizeof *S->val);
            pos += n;
        }
    }
    S->row_ptr[2 * nsa] = pos;
    S->nnz = pos;
    w->nvalid = 0;
    for (size_t sa = 0; sa < nsa; sa++) w->nvalid += (w->valid[sa] = valid[sa] != 0);
    if (!w->nvalid) {
        swfs_shwfs_free(w);
        *out = NULL;
        return swfs_fail(SWFS_ERR_VALUE, "valid-subaperture map: no subaperture is used");
    }
    return SWFS_OK;
}

void swfs_shwfs_measure(const swfs_shwfs *w, const double *z, double *slopes)
{
    swfs_sparse_apply(w->S, z, slopes);
}

int swfs_interaction_matrix(const swfs_shwfs *w, const swfs_sparse *T, double **D)
{
    *D = NULL;
    if (T->nrows != w->npup * w->npup)
        return swfs_fail(SWFS_ERR_SHAPE, "interaction matrix: interpolation has %zu rows, pupil grid has %zu samples",
                         T->nrows, w->npup * w->npup);
    size_t nact = T->ncols;
    double *d = calloc(w->nslopes * nact, sizeof *d);
    if (!d) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    /* Row s of D = sum over the pairs of S's row s of val * T[grid row]. */
    for (size_t s = 0; s < w->nslopes; s++) {
        double *ds = d + s * nact;
        for (size_t k = w->S->row_ptr[s]; k < w->S->row_ptr[s + 1]; k++) {
            size_t g = w->S->col[k];
            double v = w->S->val[k];
            for (size_t j = T->row_ptr[g]; j < T->row_ptr[g + 1]; j++) ds[T->col[j]] += v * T->val[j];
        }
    }
    *D = d;
    return SWFS_OK;
}

int swfs_slopes_used_cols(const unsigned char *valid, size_t nsub, size_t **cols, size_t *ncols)
{
    const size_t nsa = nsub * nsub;
    size_t nv = 0, k = 0;
    for (size_t i = 0; i < nsa; i++) nv += valid[i] != 0;
    size_t *c = malloc((nv ? 2 * nv : 1) * sizeof *c);
    if (!c) return swfs_fail(SWFS_ERR_NOMEM, "slopes' layout: out of memory");
    for (int axis = 0; axis < 2; axis++)
        for (size_t i = 0; i < nsa; i++)
            if (valid[i]) c[k++] = (size_t)axis * nsa + i;
    *cols = c;
    *ncols = k;
    return SWFS_OK;
}

double *swfs_slopes_expand_cols(const double *a, size_t rows, size_t nc, const size_t *cols, size_t nfull)
{
    if (rows > SIZE_MAX / sizeof(double) / nfull) return NULL;
    double *b = calloc(rows * nfull, sizeof *b);
    if (b)
        for (size_t r = 0; r < rows; r++)
            for (size_t k = 0; k < nc; k++) b[r * nfull + cols[k]] = a[r * nc + k];
    return b;
}

void swfs_slopes_remove_tiptilt(double *s, size_t nslopes, const unsigned char *valid)
{
    size_t nsa = nslopes / 2;
    for (int axis = 0; axis < 2; axis++) {
        double *v = s + (size_t)axis * nsa;
        double sum = 0;
        size_t n = 0;
        for (size_t i = 0; i < nsa; i++)
            if (!valid || valid[i]) { sum += v[i]; n++; }
        if (!n) continue;
        double mean = sum / (double)n;
        for (size_t i = 0; i < nsa; i++)
            if (!valid || valid[i]) v[i] -= mean;
    }
}

/* The last system's DM modes, for the next call on the same interpolation and mask: teach
 * asks for one system's modes about twenty times (each calibration loop's mode profile, each
 * batch of loops; 20 on a 16 x 16 system), and LAPACK's generalized eigensolver is O(nact^3)
 * with a large constant (its QR iteration: 0.08 s at 331 actuators, 4.6 s at 1261). A call
 * whose inputs equal the kept ones bit for bit gets a copy of the kept result, which is what
 * the same routine on the same inputs returns; the lock also makes concurrent callers for one
 * system (teach's loops at once) wait for the first one's result instead of each solving it. */
static struct {
    pthread_mutex_t lock;
    swfs_sparse *T;
    double *mask, *modes; /* mask: T's rows long (npup^2, checked by the caller) */
} dm_memo = {PTHREAD_MUTEX_INITIALIZER, NULL, NULL, NULL};

static int dm_memo_matches(const swfs_sparse *T, const double *mask)
{
    const swfs_sparse *K = dm_memo.T;
    const size_t ng = T->nrows;
    return K && K->nrows == T->nrows && K->ncols == T->ncols && K->nnz == T->nnz &&
           !memcmp(K->row_ptr, T->row_ptr, (T->nrows + 1) * sizeof *T->row_ptr) &&
           !memcmp(K->col, T->col, T->nnz * sizeof *T->col) && !memcmp(K->val, T->val, T->nnz * sizeof *T->val) &&
           !memcmp(dm_memo.mask, mask, ng * sizeof *mask);
}

/* Keeps a copy of the inputs and of the result (a failed copy keeps nothing: the next call
 * solves again). */
static void dm_memo_keep(const swfs_sparse *T, const double *mask, const double *modes)
{
    const size_t ng = T->nrows, nact = T->ncols;
    swfs_sparse_free(dm_memo.T);
    free(dm_memo.mask);
    free(dm_memo.modes);
    dm_memo.T = swfs_sparse_alloc(T->nrows, T->ncols, T->nnz);
    dm_memo.mask = malloc(ng * sizeof *mask);
    dm_memo.modes = malloc(nact * nact * sizeof *modes);
    if (!dm_memo.T || !dm_memo.mask || !dm_memo.modes) {
        swfs_sparse_free(dm_memo.T);
        free(dm_memo.mask);
        free(dm_memo.modes);
        dm_memo.T = NULL;
        dm_memo.mask = dm_memo.modes = NULL;
        return;
    }
    memcpy(dm_memo.T->row_ptr, T->row_ptr, (T->nrows + 1) * sizeof *T->row_ptr);
    memcpy(dm_memo.T->col, T->col, T->nnz * sizeof *T->col);
    memcpy(dm_memo.T->val, T->val, T->nnz * sizeof *T->val);
    memcpy(dm_memo.mask, mask, ng * sizeof *mask);
    memcpy(dm_memo.modes, modes, nact * nact * sizeof *modes);
}

static int dm_modes_solve(const swfs_sparse *T, const double *mask, size_t npup, double **modes)
{
    *modes = NULL;
    size_t nact = T->ncols;
    double *B = calloc(nact * nact, sizeof *B), *M = calloc(nact * nact, sizeof *M), *w = malloc(nact * sizeof *w);
    double *row = calloc(nact, sizeof *row);
    size_t *idx = malloc(nact * sizeof *idx);
    unsigned char *in = calloc(nact, 1);
    if (!B || !M || !w || !row || !idx || !in) {
        free(B); free(M); free(w); free(row); free(idx); free(in);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t q = 0; q < npup; q++)
        for (size_t p = 0; p < npup; p++) {
            size_t g = q * npup + p;
            if (!(mask[g] > 0)) continue;
            /* Mass: the row of T itself. */
            for (size_t k = T->row_ptr[g]; k < T->row_ptr[g + 1]; k++)
                for (size_t j = T->row_ptr[g]; j < T->row_ptr[g + 1]; j++) M[T->col[k] * nact + T->col[j]] += T->val[k] * T->val[j];
            /* Bending: the 5-point Laplacian where all neighbours are in the pupil. */
            if (p == 0 || q == 0 || p + 1 == npup || q + 1 == npup) continue;
            size_t nb[5] = {g, g - 1, g + 1, g - npup, g + npup};
            double cf[5] = {-4, 1, 1, 1, 1};
            int ok = 1;
            for (int t = 1; t < 5; t++) ok &= mask[nb[t]] > 0;
            if (!ok) continue;
            size_t n = 0;
            for (int t = 0; t < 5; t++)
                for (size_t k = T->row_ptr[nb[t]]; k < T->row_ptr[nb[t] + 1]; k++) {
                    size_t a = T->col[k];
                    if (!in[a]) { in[a] = 1; idx[n++] = a; }
                    row[a] += cf[t] * T->val[k];
                }
            for (size_t i = 0; i < n; i++)
                for (size_t j = 0; j < n; j++) B[idx[i] * nact + idx[j]] += row[idx[i]] * row[idx[j]];
            for (size_t i = 0; i < n; i++) { row[idx[i]] = 0; in[idx[i]] = 0; }
        }
    /* Regularize so actuators outside the pupil (zero rows of T) sort to the top. */
    double bd = 0, md = 0;
    for (size_t a = 0; a < nact; a++) { bd += B[a * nact + a]; md += M[a * nact + a]; }
    bd /= (double)nact; md /= (double)nact;
    for (size_t a = 0; a < nact; a++) { B[a * nact + a] += 1e-6 * bd; M[a * nact + a] += 1e-10 * md; }
    lapack_int info = LAPACKE_dsygv(LAPACK_ROW_MAJOR, 1, 'V', 'U', (lapack_int)nact, B, (lapack_int)nact, M,
                                    (lapack_int)nact, w);
    free(M); free(w); free(row); free(idx); free(in);
    if (info != 0) { free(B); return swfs_fail(SWFS_ERR_NUMERIC, "DM modes: generalized eigenproblem failed (%d)", (int)info); }
    *modes = B; /* eigenvectors in the columns, ascending eigenvalues */
    return SWFS_OK;
}

int swfs_dm_modes(const swfs_sparse *T, const double *mask, size_t npup, double **modes)
{
    *modes = NULL;
    if (T->nrows != npup * npup)
        return swfs_fail(SWFS_ERR_SHAPE, "DM modes: interpolation has %zu rows, grid %zu", T->nrows, npup * npup);
    const size_t nact = T->ncols;
    pthread_mutex_lock(&dm_memo.lock);
    int rc = SWFS_OK;
    if (dm_memo_matches(T, mask)) {
        if ((*modes = malloc(nact * nact * sizeof **modes))) memcpy(*modes, dm_memo.modes, nact * nact * sizeof **modes);
        else rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    } else if (!(rc = dm_modes_solve(T, mask, npup, modes))) {
        dm_memo_keep(T, mask, *modes);
    }
    pthread_mutex_unlock(&dm_memo.lock);
    return rc;
}

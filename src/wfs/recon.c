/* Regularized SVD reconstructor and the telemetry FITS files (see wfs.h). */
#include "specklewfs/wfs.h"
#include "specklewfs/array.h"
#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <lapacke.h>

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_recon_free(swfs_recon *r)
{
    if (!r) return;
    free(r->W);
    free(r->sv);
    free(r);
}

int swfs_recon_svd(const double *D, size_t nslopes, size_t nact, double rcond, size_t max_modes, swfs_recon **out)
{
    *out = NULL;
    if (nslopes == 0 || nact == 0) return swfs_fail(SWFS_ERR_ARG, "reconstructor: empty interaction matrix");
    if (!(rcond >= 0 && rcond < 1)) return swfs_fail(SWFS_ERR_ARG, "reconstructor: rcond %g must be in [0, 1)", rcond);
    size_t m = nslopes, n = nact, k = m < n ? m : n;
    double *A = malloc(m * n * sizeof *A);
    double *U = malloc(m * k * sizeof *U);
    double *VT = malloc(k * n * sizeof *VT);
    double *sv = malloc(k * sizeof *sv);
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = calloc(n * m, sizeof *r->W);
    if (!A || !U || !VT || !sv || !r || !r->W) {
        free(A); free(U); free(VT); free(sv); swfs_recon_free(r);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t i = 0; i < m * n; i++) {
        if (!isfinite(D[i])) {
            free(A); free(U); free(VT); free(sv); swfs_recon_free(r);
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor: interaction matrix entry %zu is not finite", i);
        }
        A[i] = D[i];
    }
    lapack_int info = LAPACKE_dgesdd(LAPACK_ROW_MAJOR, 'S', (lapack_int)m, (lapack_int)n, A, (lapack_int)n, sv, U,
                                     (lapack_int)k, VT, (lapack_int)n);
    free(A);
    if (info != 0) {
        free(U); free(VT); free(sv); swfs_recon_free(r);
        return swfs_fail(SWFS_ERR_NUMERIC, "reconstructor: SVD of the %zu x %zu interaction matrix failed (%d)", m, n,
                         (int)info);
    }
    size_t keep = 0;
    while (keep < k && sv[keep] > rcond * sv[0] && sv[keep] > 0 && (max_modes == 0 || keep < max_modes)) keep++;
    if (keep == 0) {
        free(U); free(VT); free(sv); swfs_recon_free(r);
        return swfs_fail(SWFS_ERR_NUMERIC, "reconstructor: no singular value survives the cut");
    }
    /* W = V diag(1/s) U^T over the kept modes: scale U's columns, then one GEMM. */
    for (size_t i = 0; i < m; i++)
        for (size_t j = 0; j < keep; j++) U[i * k + j] /= sv[j];
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasTrans, (int)n, (int)m, (int)keep, 1.0, VT, (int)n, U, (int)k, 0.0,
                r->W, (int)m);
    free(U); free(VT);
    r->nact = n; r->nslopes = m; r->nmodes = keep; r->sv = sv; r->nsv = k;
    *out = r;
    return SWFS_OK;
}

int swfs_recon_modal(const double *D, size_t nslopes, size_t nact, const double *modes, size_t first, size_t K,
                     swfs_recon **out)
{
    *out = NULL;
    if (K == 0 || first + K > nact)
        return swfs_fail(SWFS_ERR_ARG, "modal reconstructor: modes %zu..%zu of %zu", first, first + K, nact);
    double *VK = malloc(nact * K * sizeof *VK), *DV = malloc(nslopes * K * sizeof *DV);
    if (!VK || !DV) { free(VK); free(DV); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t a = 0; a < nact; a++)
        for (size_t k = 0; k < K; k++) VK[a * K + k] = modes[a * nact + first + k];
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nslopes, (int)K, (int)nact, 1.0, D, (int)nact, VK,
                (int)K, 0.0, DV, (int)K);
    swfs_recon *rk = NULL;
    int rc = swfs_recon_svd(DV, nslopes, K, 1e-6, 0, &rk);
    free(DV);
    if (rc) { free(VK); return rc; }
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = malloc(nact * nslopes * sizeof *r->W);
    if (!r || !r->W) { free(VK); swfs_recon_free(rk); swfs_recon_free(r); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nact, (int)nslopes, (int)K, 1.0, VK, (int)K, rk->W,
                (int)nslopes, 0.0, r->W, (int)nslopes);
    r->nact = nact; r->nslopes = nslopes; r->nmodes = rk->nmodes;
    r->sv = rk->sv; r->nsv = rk->nsv;
    rk->sv = NULL;
    swfs_recon_free(rk);
    free(VK);
    *out = r;
    return SWFS_OK;
}

int swfs_recon_project_tiptilt(swfs_recon *r, const unsigned char *valid)
{
    size_t nsa = r->nslopes / 2;
    if (r->nslopes % 2) return swfs_fail(SWFS_ERR_SHAPE, "reconstructor: %zu slopes is not x + y", r->nslopes);
    size_t nv = 0;
    for (size_t i = 0; i < nsa; i++) nv += !valid || valid[i];
    if (!nv) return swfs_fail(SWFS_ERR_ARG, "reconstructor: no valid subaperture for tip-tilt removal");
    /* (W (I - M))_{a,s} = W_{a,s} - [s valid] mean_{valid s' on the same axis} W_{a,s'}. */
    for (size_t a = 0; a < r->nact; a++)
        for (int axis = 0; axis < 2; axis++) {
            double *w = r->W + a * r->nslopes + (size_t)axis * nsa;
            double sum = 0;
            for (size_t i = 0; i < nsa; i++)
                if (!valid || valid[i]) sum += w[i];
            double mean = sum / (double)nv;
            for (size_t i = 0; i < nsa; i++)
                if (!valid || valid[i]) w[i] -= mean;
        }
    return SWFS_OK;
}

void swfs_recon_apply(const swfs_recon *r, const double *slopes, double *z)
{
    cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)r->nact, (int)r->nslopes, 1.0, r->W, (int)r->nslopes, slopes, 1,
                0.0, z, 1);
}

int swfs_recon_write(const swfs_recon *r, const char *path)
{
    swfs_real a = {r->nslopes, r->nact, 1, r->W};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_real(o, NULL, &a, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m/rad", "actuator displacement per slope");
    if (!rc) rc = swfs_fits_out_key_long(o, "NMODES", (long)r->nmodes, "SVD modes kept");
    if (!rc) rc = swfs_fits_out_history(o, "specklewfs reconstructor: z_act = W s, NAXIS1 = slopes, NAXIS2 = actuators");
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

int swfs_recon_read(const char *path, swfs_recon **out)
{
    *out = NULL;
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nz != 1) {
        size_t nz = a->nz;
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_FORMAT, "%s: reconstructor must be a 2-D image (nslopes x nact), got %zu planes", path, nz);
    }
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = malloc(a->nx * a->ny * sizeof *r->W);
    if (!r || !r->W) { swfs_real_free(a); swfs_recon_free(r); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    r->nslopes = a->nx; r->nact = a->ny;
    for (size_t i = 0; i < a->nx * a->ny; i++) {
        if (!isfinite(a->data[i])) {
            swfs_real_free(a); swfs_recon_free(r);
            return swfs_fail(SWFS_ERR_VALUE, "%s: reconstructor entry %zu is not finite", path, i);
        }
        r->W[i] = a->data[i];
    }
    r->nmodes = 0;
    swfs_real_free(a);
    *out = r;
    return SWFS_OK;
}

int swfs_actuators_write(const double *xy, size_t nact, const char *path)
{
    swfs_real a = {2, nact, 1, (double *)xy};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_real(o, NULL, &a, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "actuator (x, y) in the pupil frame");
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

int swfs_actuators_read(const char *path, double **xy, size_t *nact)
{
    *xy = NULL;
    *nact = 0;
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nx != 2 || a->nz != 1) {
        size_t nx = a->nx;
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_FORMAT, "%s: actuator positions must be a 2 x nact image, NAXIS1 is %zu", path, nx);
    }
    double *p = malloc(2 * a->ny * sizeof *p);
    if (!p) { swfs_real_free(a); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    memcpy(p, a->data, 2 * a->ny * sizeof *p);
    *nact = a->ny;
    *xy = p;
    swfs_real_free(a);
    return SWFS_OK;
}

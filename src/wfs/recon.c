/* Regularized SVD reconstructor and the telemetry FITS files (see wfs.h). */
#include "specklewfs/numeric.h"
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
    free(r->oxy);
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

/* Thin SVD of D (m x n, row-major): U m x k, sv k, VT k x n, k = min(m, n). */
static int svd_thin(const double *D, size_t m, size_t n, double **U, double **sv, double **VT)
{
    size_t k = m < n ? m : n;
    double *A = malloc(m * n * sizeof *A);
    *U = malloc(m * k * sizeof **U);
    *sv = malloc(k * sizeof **sv);
    *VT = malloc(k * n * sizeof **VT);
    if (!A || !*U || !*sv || !*VT) {
        free(A); free(*U); free(*sv); free(*VT);
        *U = *sv = *VT = NULL;
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t i = 0; i < m * n; i++) {
        if (!isfinite(D[i])) {
            free(A); free(*U); free(*sv); free(*VT);
            *U = *sv = *VT = NULL;
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor: interaction matrix entry %zu is not finite", i);
        }
        A[i] = D[i];
    }
    lapack_int info = LAPACKE_dgesdd(LAPACK_ROW_MAJOR, 'S', (lapack_int)m, (lapack_int)n, A, (lapack_int)n, *sv, *U,
                                     (lapack_int)k, *VT, (lapack_int)n);
    free(A);
    if (info != 0) {
        free(*U); free(*sv); free(*VT);
        *U = *sv = *VT = NULL;
        return swfs_fail(SWFS_ERR_NUMERIC, "reconstructor: SVD of the %zu x %zu interaction matrix failed (%d)", m, n,
                         (int)info);
    }
    return SWFS_OK;
}

/* Numerical rank: singular values above 1e-10 of the largest. */
static size_t svd_rank(const double *sv, size_t k)
{
    size_t r = 0;
    while (r < k && sv[r] > 1e-10 * sv[0]) r++;
    return r;
}

/* For the modes i < rank of D = U S V^T: P[i] = mean square of y_i = u_i^T s over the
 * frames, N[i] = (2 d(1) - d(2)) / 2 from the temporal structure function of y_i. */
static int mode_stats(const double *U, size_t m, size_t k, size_t rank, const double *slopes, size_t nframes, double *P,
                      double *N)
{
    for (size_t i = 0; i < m * nframes; i++)
        if (!isfinite(slopes[i]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor: slope %zu of frame %zu is not finite", i % m, i / m);
    double *Y = malloc(nframes * rank * sizeof *Y);
    if (!Y) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    /* Y (nframes x rank) = slopes (nframes x m) U[:, :rank]. */
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nframes, (int)rank, (int)m, 1.0, slopes, (int)m, U,
                (int)k, 0.0, Y, (int)rank);
    for (size_t i = 0; i < rank; i++) {
        double p = 0, d1 = 0, d2 = 0;
        for (size_t t = 0; t < nframes; t++) {
            double y = Y[t * rank + i];
            p += y * y;
            if (t + 1 < nframes) { double d = Y[(t + 1) * rank + i] - y; d1 += d * d; }
            if (t + 2 < nframes) { double d = Y[(t + 2) * rank + i] - y; d2 += d * d; }
        }
        P[i] = p / (double)nframes;
        N[i] = 0.5 * (2 * d1 / (double)(nframes - 1) - d2 / (double)(nframes - 2));
    }
    free(Y);
    return SWFS_OK;
}

/* The effective slope noise variance per slope (see wfs.h): the mean square of the slopes
 * outside the column space of D over the valid slopes (rows of D not all 0), per degree of
 * freedom; if D spans every valid slope, the structure-function median of the modes. */
static double noise_estimate(const double *D, size_t m, size_t n, size_t rank, const double *slopes, size_t nframes,
                             const double *P, double *N)
{
    size_t nvs = 0;
    for (size_t i = 0; i < m; i++) {
        int nz = 0;
        for (size_t j = 0; j < n && !nz; j++) nz = D[i * n + j] != 0;
        nvs += (size_t)nz;
    }
    if (nvs > rank) {
        double tot = 0, in = 0;
        for (size_t t = 0; t < nframes; t++)
            for (size_t i = 0; i < m; i++) tot += slopes[t * m + i] * slopes[t * m + i];
        for (size_t i = 0; i < rank; i++) in += P[i];
        double v = (tot / (double)nframes - in) / (double)(nvs - rank);
        if (v > 0) return v;
    }
    double med = swfs_median_inplace(N, rank);
    return med > 0 ? med : 0;
}

int swfs_slopes_noise_var(const double *D, size_t nslopes, size_t nact, const double *slopes, size_t nframes,
                          double *noise_var)
{
    *noise_var = 0;
    if (nslopes == 0 || nact == 0) return swfs_fail(SWFS_ERR_ARG, "reconstructor: empty interaction matrix");
    if (nframes < 8) return swfs_fail(SWFS_ERR_ARG, "slope noise: %zu frames, expected at least 8", nframes);
    double *U, *sv, *VT;
    int rc = svd_thin(D, nslopes, nact, &U, &sv, &VT);
    if (rc) return rc;
    size_t k = nslopes < nact ? nslopes : nact, rank = svd_rank(sv, k);
    double *P = malloc((rank + 1) * sizeof *P), *N = malloc((rank + 1) * sizeof *N);
    if (!P || !N) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    else if (!rank) rc = swfs_fail(SWFS_ERR_NUMERIC, "reconstructor: the interaction matrix is zero");
    else rc = mode_stats(U, nslopes, k, rank, slopes, nframes, P, N);
    if (!rc) *noise_var = noise_estimate(D, nslopes, nact, rank, slopes, nframes, P, N);
    free(U); free(sv); free(VT); free(P); free(N);
    return rc;
}

int swfs_recon_map(const double *D, size_t nslopes, size_t nact, const double *slopes, size_t nframes,
                   double noise_var, swfs_recon **out)
{
    *out = NULL;
    if (nslopes == 0 || nact == 0) return swfs_fail(SWFS_ERR_ARG, "reconstructor: empty interaction matrix");
    if (!(noise_var <= 0) && !isfinite(noise_var))
        return swfs_fail(SWFS_ERR_ARG, "reconstructor: slope noise variance %g is not finite", noise_var);
    if (nframes < 8)
        return swfs_fail(SWFS_ERR_ARG, "MAP reconstructor: %zu frames to learn the prior from, expected at least 8", nframes);
    const size_t m = nslopes, n = nact, k = m < n ? m : n;
    double *U, *sv, *VT;
    int rc = svd_thin(D, m, n, &U, &sv, &VT);
    if (rc) return rc;
    const size_t rank = svd_rank(sv, k);
    double *P = malloc((rank + 1) * sizeof *P), *N = malloc((rank + 1) * sizeof *N);
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = calloc(n * m, sizeof *r->W);
    if (!P || !N || !r || !r->W) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    else if (!rank) rc = swfs_fail(SWFS_ERR_NUMERIC, "reconstructor: the interaction matrix is zero");
    else rc = mode_stats(U, m, k, rank, slopes, nframes, P, N);
    if (!rc && noise_var <= 0) noise_var = noise_estimate(D, m, n, rank, slopes, nframes, P, N);
    if (!rc && !(noise_var > 0))
        rc = swfs_fail(SWFS_ERR_NUMERIC, "MAP reconstructor: the slope noise estimate is 0 (noise-free slopes?); give it");
    if (rc) { free(U); free(sv); free(VT); free(P); free(N); swfs_recon_free(r); return rc; }
    /* Prior variances a_i = (P_i - sigma^2)_+ / s_i^2, capped at the largest one among the
     * well-sensed modes (s_i >= 0.1 s_0): in a poorly sensed mode P_i - sigma^2 is mostly
     * the scatter of the noise estimate, and 1 / s_i^2 would turn it into an implausible
     * prior (and a huge gain). */
    double amax = 0;
    for (size_t j = 0; j < rank; j++)
        if (sv[j] >= 0.1 * sv[0] && P[j] > noise_var) {
            double a = (P[j] - noise_var) / (sv[j] * sv[j]);
            if (a > amax) amax = a;
        }
    /* W = V diag(g_i) U^T, g_i = s_i a_i / (s_i^2 a_i + sigma^2): the MAP / Wiener gain of
     * mode i, (1 - sigma^2 / P_i) / s_i when the cap is not reached. */
    size_t kept = 0;
    double dof = 0;
    for (size_t j = 0; j < k; j++) {
        double a = j < rank && P[j] > noise_var ? (P[j] - noise_var) / (sv[j] * sv[j]) : 0;
        if (a > amax) a = amax;
        double g = a > 0 ? sv[j] * a / (sv[j] * sv[j] * a + noise_var) : 0;
        if (g > 0) kept++;
        dof += g * sv[j];
        for (size_t i = 0; i < m; i++) U[i * k + j] *= g;
    }
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasTrans, (int)n, (int)m, (int)k, 1.0, VT, (int)n, U, (int)k, 0.0, r->W,
                (int)m);
    free(U); free(VT); free(P); free(N);
    r->nact = n; r->nslopes = m; r->nmodes = kept; r->sv = sv; r->nsv = k;
    r->noise_var = noise_var; r->dof = dof;
    *out = r;
    return SWFS_OK;
}

int swfs_recon_modal_factors(const double *D, size_t nslopes, size_t nact, const double *modes, size_t first, size_t K,
                             double **VKo, swfs_recon **P)
{
    *VKo = NULL;
    *P = NULL;
    if (K == 0 || first + K > nact)
        return swfs_fail(SWFS_ERR_ARG, "modal reconstructor: modes %zu..%zu of %zu", first, first + K, nact);
    double *VK = malloc(nact * K * sizeof *VK), *DV = malloc(nslopes * K * sizeof *DV);
    if (!VK || !DV) { free(VK); free(DV); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t a = 0; a < nact; a++)
        for (size_t k = 0; k < K; k++) VK[a * K + k] = modes[a * nact + first + k];
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nslopes, (int)K, (int)nact, 1.0, D, (int)nact, VK,
                (int)K, 0.0, DV, (int)K);
    int rc = swfs_recon_svd(DV, nslopes, K, 1e-6, 0, P);
    free(DV);
    if (rc) { free(VK); return rc; }
    *VKo = VK;
    return SWFS_OK;
}

int swfs_recon_modal_compose(const double *VK, const swfs_recon *P, size_t nact, swfs_recon **out)
{
    *out = NULL;
    const size_t K = P->nact, nslopes = P->nslopes;
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = malloc(nact * nslopes * sizeof *r->W);
    if (r && P->sv) r->sv = malloc(P->nsv * sizeof *r->sv);
    if (!r || !r->W || (P->sv && !r->sv)) { swfs_recon_free(r); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nact, (int)nslopes, (int)K, 1.0, VK, (int)K, P->W,
                (int)nslopes, 0.0, r->W, (int)nslopes);
    r->nact = nact; r->nslopes = nslopes; r->nmodes = P->nmodes;
    if (P->sv) memcpy(r->sv, P->sv, P->nsv * sizeof *r->sv);
    r->nsv = P->nsv;
    *out = r;
    return SWFS_OK;
}

int swfs_recon_modal(const double *D, size_t nslopes, size_t nact, const double *modes, size_t first, size_t K,
                     swfs_recon **out)
{
    *out = NULL;
    double *VK = NULL;
    swfs_recon *P = NULL;
    int rc = swfs_recon_modal_factors(D, nslopes, nact, modes, first, K, &VK, &P);
    if (!rc) rc = swfs_recon_modal_compose(VK, P, nact, out);
    free(VK);
    swfs_recon_free(P);
    return rc;
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

int swfs_recon_tilt_as_mean_slopes(swfs_recon *r, const unsigned char *valid, const double *xy)
{
    int rc = swfs_recon_project_tiptilt(r, valid);
    if (rc) return rc;
    const size_t nsa = r->nslopes / 2;
    size_t nv = 0;
    for (size_t i = 0; i < nsa; i++) nv += !valid || valid[i];
    for (size_t a = 0; a < r->nact; a++)
        for (size_t axis = 0; axis < 2; axis++) {
            double *w = r->W + a * r->nslopes + axis * nsa;
            const double c = xy[2 * a + axis] / (double)nv;
            for (size_t i = 0; i < nsa; i++)
                if (!valid || valid[i]) w[i] += c;
        }
    return SWFS_OK;
}

void swfs_recon_apply(const swfs_recon *r, const double *slopes, double *z)
{
    cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)r->nact, (int)r->nslopes, 1.0, r->W, (int)r->nslopes, slopes, 1,
                0.0, z, 1);
}

/* K_nu(x) for x > 0 by the integral K_nu(x) = int_0^inf exp(-x cosh t) cosh(nu t) dt: the
 * integrand is analytic and decays doubly exponentially, so the trapezoid rule with step
 * 0.05 is accurate to ~1e-12 (checked against the x -> 0 limit in the unit test). */
static double bessel_k(double nu, double x)
{
    const double h = 0.05;
    double sum = 0.5 * exp(-x);
    for (int j = 1; j < 4000; j++) {
        double t = h * j, e = x * cosh(t);
        if (e > 60) break;
        sum += exp(-e) * cosh(nu * t);
    }
    return h * sum;
}

int swfs_vk_covariance(const double *xy, size_t nact, double L0, double *C)
{
    if (!(L0 > 0) || !isfinite(L0)) return swfs_fail(SWFS_ERR_ARG, "von Karman covariance: outer scale %g m must be > 0", L0);
    const double nu = 5.0 / 6.0, f0 = 0.5 * tgamma(nu) * pow(2, nu); /* x^nu K_nu(x) -> 2^(nu-1) Gamma(nu) */
    for (size_t a = 0; a < nact; a++) {
        C[a * nact + a] = 1;
        for (size_t b = a + 1; b < nact; b++) {
            double dx = xy[2 * a] - xy[2 * b], dy = xy[2 * a + 1] - xy[2 * b + 1];
            double x = 2 * M_PI * sqrt(dx * dx + dy * dy) / L0;
            double c = x > 0 ? pow(x, nu) * bessel_k(nu, x) / f0 : 1;
            C[a * nact + b] = C[b * nact + a] = c;
        }
    }
    return SWFS_OK;
}

int swfs_recon_vk(const double *D, size_t nslopes, size_t nact, const double *xy, double L0, const double *slopes,
                  size_t nframes, double noise_var, swfs_recon **out)
{
    *out = NULL;
    const size_t m = nslopes, n = nact, nsa = m / 2;
    if (m == 0 || n == 0 || m % 2) return swfs_fail(SWFS_ERR_ARG, "vk reconstructor: %zu slopes x %zu actuators", m, n);
    if (!(noise_var <= 0) && !isfinite(noise_var))
        return swfs_fail(SWFS_ERR_ARG, "reconstructor: slope noise variance %g is not finite", noise_var);
    if (nframes < 8)
        return swfs_fail(SWFS_ERR_ARG, "vk reconstructor: %zu frames to scale the prior with, expected at least 8", nframes);
    for (size_t i = 0; i < m * nframes; i++)
        if (!isfinite(slopes[i]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor: slope %zu of frame %zu is not finite", i % m, i / m);
    if (isnan(L0) || isinf(L0)) return swfs_fail(SWFS_ERR_ARG, "vk reconstructor: outer scale %g: expected a length [m], or 0 to fit it", L0);
    int rc = SWFS_OK;
    swfs_vk_fit fit = {0};
    const int ml = !(L0 > 0), ml_noise = ml && noise_var <= 0;
    if (ml) {
        if ((rc = swfs_vk_fit_slopes(D, m, n, xy, slopes, nframes, &fit))) return rc;
        L0 = fit.L0;
        if (ml_noise) noise_var = fit.noise_var;
    }
    const int noise_estimated = noise_var <= 0;
    if (noise_var <= 0 && (rc = swfs_slopes_noise_var(D, m, n, slopes, nframes, &noise_var))) return rc;
    /* No slopes outside D's column space (at least as many actuators as valid slopes, the
     * MMT's own case) and a temporal extrapolation that found nothing: the noise from the
     * slopes' likelihood under the prior, which separates noise from signal by their
     * spatial spectra (vkfit.c). */
    if (!(noise_var > 0) && !ml) {
        if ((rc = swfs_vk_fit_slopes(D, m, n, xy, slopes, nframes, &fit))) return rc;
        noise_var = fit.noise_var;
    }
    if (!(noise_var > 0))
        return swfs_fail(SWFS_ERR_NUMERIC, "vk reconstructor: the slope noise estimate is 0 from %zu frames of %zu "
                         "slopes (noise-free slopes?); give it (--slope-noise)", nframes, m);
    double *C = malloc(n * n * sizeof *C), *PD = malloc(m * n * sizeof *PD), *B = malloc(m * n * sizeof *B);
    double *M = malloc(m * m * sizeof *M);
    unsigned char *valid = malloc(m);
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = malloc(n * m * sizeof *r->W);
    if (!C || !PD || !B || !M || !valid || !r || !r->W) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    if ((rc = swfs_vk_covariance(xy, n, L0, C))) goto done;
    size_t nv[2] = {0, 0};
    for (size_t i = 0; i < m; i++) {
        int nz = 0;
        for (size_t j = 0; j < n && !nz; j++) nz = D[i * n + j] != 0;
        valid[i] = (unsigned char)nz;
        nv[i / nsa] += (size_t)nz;
    }
    if (nv[0] < 2 || nv[1] < 2) { rc = swfs_fail(SWFS_ERR_ARG, "vk reconstructor: fewer than 2 valid x or y slopes"); goto done; }
    /* PD: D with the mean over the valid slopes of each axis removed from every column. */
    memcpy(PD, D, m * n * sizeof *PD);
    for (size_t ax = 0; ax < 2; ax++)
        for (size_t j = 0; j < n; j++) {
            double s = 0;
            for (size_t i = ax * nsa; i < (ax + 1) * nsa; i++) s += valid[i] ? D[i * n + j] : 0;
            s /= (double)nv[ax];
            for (size_t i = ax * nsa; i < (ax + 1) * nsa; i++) if (valid[i]) PD[i * n + j] -= s;
        }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)m, (int)n, (int)n, 1.0, PD, (int)n, C, (int)n, 0.0, B,
                (int)n);
    double pred = 0, meas = 0;
    for (size_t i = 0; i < m * n; i++) pred += PD[i] * B[i];
    for (size_t t = 0; t < nframes; t++) {
        const double *s = slopes + t * m;
        for (size_t ax = 0; ax < 2; ax++) {
            double mu = 0, q = 0;
            for (size_t i = ax * nsa; i < (ax + 1) * nsa; i++) if (valid[i]) { mu += s[i]; q += s[i] * s[i]; }
            meas += q - mu * mu / (double)nv[ax];
        }
    }
    meas /= (double)nframes;
    double sig = meas - (double)(nv[0] + nv[1] - 2) * noise_var;
    if (pred > 0 && !(sig > 0) && noise_estimated && !ml) {
        /* The slopes outside D's column space hold more than noise: a loop that controls
         * nearly every mode its WFS sees leaves little in the space it measures, while what
         * the DM cannot make aliases outside it. The noise from the slopes' likelihood under
         * the prior instead (vkfit.c), which tells noise from signal by their spatial spectra. */
        if ((rc = swfs_vk_fit_slopes(D, m, n, xy, slopes, nframes, &fit))) goto done;
        if (fit.noise_var > 0 && fit.noise_var < noise_var) noise_var = fit.noise_var;
        sig = meas - (double)(nv[0] + nv[1] - 2) * noise_var;
    }
    if (!(pred > 0) || !(sig > 0)) {
        rc = swfs_fail(SWFS_ERR_NUMERIC, "vk reconstructor: the slopes' mean square, tip-tilt removed (%.3g rad^2 per frame "
                       "over %zu slopes), is no more than their noise (%.3g rad^2 per frame: %.3g per slope, estimated "
                       "from the slopes outside the interaction matrix's column space, or given): nothing to "
                       "reconstruct -- a loop that controls nearly every mode its WFS sees leaves the slopes little "
                       "but noise; give the slope noise (--slope-noise) or a reconstructor", meas, nv[0] + nv[1],
                       (double)(nv[0] + nv[1] - 2) * noise_var, noise_var);
        goto done;
    }
    /* The prior's scale: the maximum-likelihood one with the fitted noise, else from the
     * slopes' mean square given the noise. */
    const double c = ml_noise ? fit.scale : sig / pred;
    /* B = D C_z (m x n); M = D C_z D^T + sigma^2 I; solve M X = B, W = X^T. */
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)m, (int)n, (int)n, c, D, (int)n, C, (int)n, 0.0, B,
                (int)n);
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)m, (int)m, (int)n, 1.0, B, (int)n, D, (int)n, 0.0, M,
                (int)m);
    for (size_t i = 0; i < m; i++) M[i * m + i] += noise_var;
    lapack_int info = LAPACKE_dposv(LAPACK_ROW_MAJOR, 'U', (lapack_int)m, (lapack_int)n, M, (lapack_int)m, B, (lapack_int)n);
    if (info != 0) {
        rc = swfs_fail(SWFS_ERR_NUMERIC, "vk reconstructor: D C D^T + sigma^2 I is not positive definite (%d)", (int)info);
        goto done;
    }
    double dof = 0;
    for (size_t a = 0; a < n; a++)
        for (size_t s = 0; s < m; s++) r->W[a * m + s] = B[s * n + a];
    for (size_t a = 0; a < n; a++)
        for (size_t s = 0; s < m; s++) dof += r->W[a * m + s] * D[s * n + a];
    r->nact = n; r->nslopes = m; r->nmodes = n; r->noise_var = noise_var; r->dof = dof;
    r->l0 = L0; r->prior_scale = c;
    *out = r;
    r = NULL;
done:
    free(C); free(PD); free(B); free(M); free(valid);
    swfs_recon_free(r);
    return rc;
}

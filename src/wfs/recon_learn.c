/* A reconstructor learned from simulated closed loops: the least-squares map from a frame's
 * slopes to the true residual wavefront on the actuators (wfs.h swfs_recon_learner;
 * docs/telemetry.md, "A reconstructor learned from simulated closed loops"). */
#include "specklewfs/wfs.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <lapacke.h>
#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Frames per block of the H update; blocks summed in single precision before they go into
 * the double sums (add_cross). */
#define LEARN_BLOCK 256
#define LEARN_FLUSH 16
#define MIN2(a, b) ((a) < (b) ? (a) : (b))

struct swfs_recon_learner {
    size_t nslopes, nact, nframes;
    int remove_mean; /* 1: z's mean over its values is piston (actuator values) and comes out */
    double *G;    /* nslopes x nslopes: sum of s s^T (upper triangle, row-major) */
    double *H;    /* nslopes x nact: sum of s z^T, z with its mean removed when remove_mean */
    double zz;    /* sum of |z|^2, mean removed */
    float *Sf;    /* LEARN_BLOCK x nslopes: a block of inputs in single precision */
    float *Zf;    /* LEARN_BLOCK x nact: its truth, mean removed */
    float *Hf;    /* nslopes x nact: one add call's S^T Zc, summed in single precision */
};

int swfs_recon_learner_new(size_t nslopes, size_t nact, int remove_mean, swfs_recon_learner **out)
{
    *out = NULL;
    if (!nslopes || !nact) return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: %zu slopes, %zu actuators", nslopes, nact);
    swfs_recon_learner *l = calloc(1, sizeof *l);
    if (l) {
        l->nslopes = nslopes;
        l->nact = nact;
        l->remove_mean = remove_mean != 0;
        l->G = calloc(nslopes * nslopes, sizeof *l->G);
        l->H = calloc(nslopes * nact, sizeof *l->H);
        l->Sf = malloc(LEARN_BLOCK * nslopes * sizeof *l->Sf);
        l->Zf = malloc(LEARN_BLOCK * nact * sizeof *l->Zf);
        l->Hf = malloc(nslopes * nact * sizeof *l->Hf);
    }
    if (!l || !l->G || !l->H || !l->Sf || !l->Zf || !l->Hf) {
        swfs_recon_learner_free(l);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu slopes x %zu actuators", nslopes,
                         nact);
    }
    *out = l;
    return SWFS_OK;
}

void swfs_recon_learner_free(swfs_recon_learner *l)
{
    if (!l) return;
    free(l->G);
    free(l->H);
    free(l->Sf);
    free(l->Zf);
    free(l->Hf);
    free(l);
}

size_t swfs_recon_learner_frames(const swfs_recon_learner *l) { return l->nframes; }

static int check_finite(const double *slopes, size_t ns, const double *truth, size_t na, size_t nframes)
{
    for (size_t k = 0; k < nframes * ns; k++)
        if (!isfinite(slopes[k]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: slope %zu of frame %zu is not finite", k % ns, k / ns);
    for (size_t k = 0; k < nframes * na; k++)
        if (!isfinite(truth[k]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: actuator %zu of frame %zu of the truth is not finite",
                             k % na, k / na);
    return SWFS_OK;
}

/* H += S^T Zc for block blk of at most LEARN_BLOCK frames (S: nb x nslopes, the inputs), with
 * Zc = Z - m 1^T (m the frames' means: piston, which nothing sees; modal coefficients carry
 * none and are taken as they are), by one SGEMM into Hf, which goes into H after every
 * LEARN_FLUSH blocks and after an add call's last (last); and zz (in double). Single
 * precision: the cross product only scales the map linearly (no inverse amplifies its
 * rounding, as (G + lam)^-1 would G's, which stays double), and its relative rounding over at
 * most 4096 frames, about sqrt(4096) 2^-24 = 4e-6, is far below the statistical error of a
 * map of 10 frames per input (about 1 / sqrt(10)). SGEMM takes half DGEMM's time: the cross
 * product is the largest product of a map of many outputs (teach's grid; docs/telemetry.md). */
static void add_cross(swfs_recon_learner *l, const double *S, const double *Z, size_t nb, size_t blk, int last)
{
    const size_t ns = l->nslopes, na = l->nact;
    for (size_t f = 0; f < nb; f++) {
        const double *z = Z + f * na;
        float *zf = l->Zf + f * na;
        double m = 0;
        if (l->remove_mean) {
            for (size_t a = 0; a < na; a++) m += z[a];
            m /= (double)na;
        }
        for (size_t a = 0; a < na; a++) {
            const double c = z[a] - m;
            l->zz += c * c;
            zf[a] = (float)c;
        }
    }
    for (size_t k = 0; k < nb * ns; k++) l->Sf[k] = (float)S[k];
    cblas_sgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)ns, (int)na, (int)nb, 1.0f, l->Sf, (int)ns, l->Zf, (int)na,
                blk % LEARN_FLUSH ? 1.0f : 0.0f, l->Hf, (int)na);
    if (last || blk % LEARN_FLUSH == LEARN_FLUSH - 1)
        for (size_t i = 0; i < ns * na; i++) l->H[i] += (double)l->Hf[i];
}

int swfs_recon_learner_add(swfs_recon_learner *l, const double *slopes, const double *truth, size_t nframes)
{
    const size_t ns = l->nslopes, na = l->nact;
    int rc = check_finite(slopes, ns, truth, na, nframes);
    if (rc) return rc;
    /* G += S^T S (one rank-k update); H block by block. */
    cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)ns, (int)nframes, 1.0, slopes, (int)ns, 1.0, l->G, (int)ns);
    for (size_t f0 = 0; f0 < nframes; f0 += LEARN_BLOCK) {
        const size_t nb = nframes - f0 < LEARN_BLOCK ? nframes - f0 : LEARN_BLOCK;
        add_cross(l, slopes + f0 * ns, truth + f0 * na, nb, f0 / LEARN_BLOCK, f0 + nb == nframes);
    }
    l->nframes += nframes;
    return SWFS_OK;
}

/* C += alpha S[a..a+m)^T S[a+d..a+d+m) (ns0 x ns0, row-major), S: frames x ns0. */
static void lag_product(const double *S, size_t ns0, size_t a, size_t d, size_t m, double alpha, double *C)
{
    if (!m) return;
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)ns0, (int)ns0, (int)m, alpha, S + a * ns0, (int)ns0,
                S + (a + d) * ns0, (int)ns0, 1.0, C, (int)ns0);
}

int swfs_recon_learner_add_lagged(swfs_recon_learner *l, const double *s, size_t ns0, const double *truth, size_t n,
                                  const long *lags, size_t nl)
{
    const size_t ns = l->nslopes, na = l->nact;
    if (!nl || nl > SWFS_RECON_MAXLAGS || ns0 * nl != ns)
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: %zu slopes x %zu lags, but the learner takes %zu inputs",
                         ns0, nl, ns);
    int rc = check_finite(s, ns0, truth, na, n);
    if (rc || !n) return rc;
    long lmin = 0, lmax = 0;
    for (size_t k = 0; k < nl; k++) {
        lmin = lags[k] < lmin ? lags[k] : lmin;
        lmax = lags[k] > lmax ? lags[k] : lmax;
    }
    /* The frames t whose every lag falls inside the file: [ta, tb]; the others are clamped. */
    const long ta = -lmin, tb = (long)n - 1 - lmax;
    const size_t nedge = ta <= tb ? n - (size_t)(tb - ta + 1) : n;
    const size_t rows = nedge > LEARN_BLOCK ? nedge : LEARN_BLOCK;
    double *X = malloc(rows * ns * sizeof *X), *Q = malloc(ns0 * ns0 * sizeof *Q), *T = malloc(ns0 * ns0 * sizeof *T);
    if (!X || !Q || !T) {
        free(X); free(Q); free(T);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu lags of %zu slopes", nl, ns0);
    }
    /* H and zz from the stacked input, a block at a time. */
    for (size_t f0 = 0; f0 < n; f0 += LEARN_BLOCK) {
        const size_t nb = n - f0 < LEARN_BLOCK ? n - f0 : LEARN_BLOCK;
        swfs_slopes_stack(s, n, ns0, lags, nl, f0, nb, X);
        add_cross(l, X, truth + f0 * na, nb, f0 / LEARN_BLOCK, f0 + nb == n);
    }
    /* G: block (i, j) of the inner frames is sum_t s(t + L_i) s(t + L_j)^T, a product of the
     * file with itself d = |L_j - L_i| frames apart, over a range that depends on i only by a
     * shift. One GEMM per distinct d over a reference range (the pairs' smallest leading
     * lag), and for each pair the frames its own range adds and leaves out at the ends: about
     * (distinct d) / (nl (nl + 1) / 2) of the stacked DSYRK's work. */
    if (ta <= tb) {
        const size_t m = (size_t)(tb - ta + 1);
        int done[SWFS_RECON_MAXLAGS * SWFS_RECON_MAXLAGS] = {0};
        for (size_t i = 0; i < nl; i++)
            for (size_t j = i; j < nl; j++) {
                if (done[i * nl + j]) continue;
                const long ad = labs(lags[j] - lags[i]);
                /* the pairs at this distance; a pair's range starts at its smaller lag (the
                 * leading one), the reference at the smallest of those */
                long lref = LONG_MAX;
                for (size_t i2 = 0; i2 < nl; i2++)
                    for (size_t j2 = i2; j2 < nl; j2++)
                        if (labs(lags[j2] - lags[i2]) == ad && MIN2(lags[i2], lags[j2]) < lref)
                            lref = MIN2(lags[i2], lags[j2]);
                memset(Q, 0, ns0 * ns0 * sizeof *Q);
                lag_product(s, ns0, (size_t)(ta + lref), (size_t)ad, m, 1.0, Q);
                for (size_t i2 = 0; i2 < nl; i2++)
                    for (size_t j2 = i2; j2 < nl; j2++) {
                        if (labs(lags[j2] - lags[i2]) != ad) continue;
                        done[i2 * nl + j2] = 1;
                        const size_t sh = (size_t)(MIN2(lags[i2], lags[j2]) - lref);
                        memcpy(T, Q, ns0 * ns0 * sizeof *T);
                        /* the range [ta + lead, tb + lead] = the reference's less its first
                         * sh frames, plus sh frames beyond its end */
                        lag_product(s, ns0, (size_t)(ta + lref), (size_t)ad, sh, -1.0, T);
                        lag_product(s, ns0, (size_t)(tb + lref + 1), (size_t)ad, sh, 1.0, T);
                        /* T[r][c] = sum s(u)_r s(u + ad)_c, u = t + lead: rows at the leading
                         * lag's slopes; G's block (i2, j2) has rows at lag i2's (transposed
                         * when lag j2 leads). */
                        const int flip = lags[j2] < lags[i2];
                        for (size_t r = 0; r < ns0; r++) {
                            double *g = l->G + (i2 * ns0 + r) * ns + j2 * ns0;
                            for (size_t c = i2 == j2 ? r : 0; c < ns0; c++) g[c] += flip ? T[c * ns0 + r] : T[r * ns0 + c];
                        }
                    }
            }
    }
    /* The clamped frames, stacked, by one rank-k update. */
    size_t k = 0;
    for (size_t t = 0; t < n; t++) {
        if (ta <= tb && (long)t >= ta && (long)t <= tb) continue;
        swfs_slopes_stack(s, n, ns0, lags, nl, t, 1, X + k * ns);
        k++;
    }
    if (k)
        cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)ns, (int)k, 1.0, X, (int)ns, 1.0, l->G, (int)ns);
    l->nframes += n;
    free(X);
    free(Q);
    free(T);
    return SWFS_OK;
}

void swfs_recon_learner_reset(swfs_recon_learner *l)
{
    memset(l->G, 0, l->nslopes * l->nslopes * sizeof *l->G);
    memset(l->H, 0, l->nslopes * l->nact * sizeof *l->H);
    l->zz = 0;
    l->nframes = 0;
}

/* G's element (a, b) of the sums l less m (m NULL: none); G holds the upper triangle. */
static double gsum(const swfs_recon_learner *l, const swfs_recon_learner *m, size_t a, size_t b)
{
    const size_t i = a < b ? a : b, j = a < b ? b : a, ns = l->nslopes;
    return l->G[i * ns + j] - (m ? m->G[i * ns + j] : 0.0);
}

/* The normal equations of the sums l less m solved over the slopes with signal in them:
 * A = (G + lam I)^-1 H (nu x na) in *A, those slopes in idx (ns long), nu of them. */
static int solve_sums(const swfs_recon_learner *l, const swfs_recon_learner *m, double ridge, size_t *idx, size_t *nu_out,
                      double **A_out, double *lam_out)
{
    *A_out = NULL;
    const size_t ns = l->nslopes, na = l->nact, nf = l->nframes - (m ? m->nframes : 0);
    if (!(ridge > 0) || !isfinite(ridge))
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: the ridge must be a finite fraction > 0, got %g", ridge);
    /* The slopes seen: those with any signal over the frames (unilluminated ones are 0). */
    size_t nu = 0;
    double tr = 0;
    for (size_t i = 0; i < ns; i++) {
        const double d = gsum(l, m, i, i);
        if (d > 1e-12 * l->G[i * ns + i] && d > 0) {
            idx[nu++] = i;
            tr += d;
        }
    }
    if (nu == 0 || nf < 2 * nu)
        return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: %zu frames for %zu slopes with signal; a map needs at "
                         "least twice as many frames as slopes (more simulated frames, or more data sets)", nf, nu);
    double *M = malloc(nu * nu * sizeof *M), *B = malloc(nu * na * sizeof *B);
    if (!M || !B) {
        free(M); free(B);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu slopes", nu);
    }
    const double lam = ridge * tr / (double)nu;
    for (size_t i = 0; i < nu; i++) {
        for (size_t j = 0; j < nu; j++) M[i * nu + j] = gsum(l, m, idx[i], idx[j]);
        M[i * nu + i] += lam;
        for (size_t a = 0; a < na; a++) B[i * na + a] = l->H[idx[i] * na + a] - (m ? m->H[idx[i] * na + a] : 0.0);
    }
    lapack_int info = LAPACKE_dposv(LAPACK_ROW_MAJOR, 'U', (lapack_int)nu, (lapack_int)na, M, (lapack_int)nu, B,
                                    (lapack_int)na);
    free(M);
    if (info != 0) {
        free(B);
        return swfs_fail(SWFS_ERR_NUMERIC, "reconstructor learning: the normal equations are not positive definite "
                         "(LAPACK dposv info %d) with a ridge of %g", (int)info, ridge);
    }
    *nu_out = nu;
    *A_out = B;
    *lam_out = lam;
    return SWFS_OK;
}

int swfs_recon_learner_solve(const swfs_recon_learner *l, double ridge, swfs_recon **out, swfs_recon_learn_info *info)
{
    *out = NULL;
    const size_t ns = l->nslopes, na = l->nact;
    size_t *idx = malloc(ns * sizeof *idx), nu = 0;
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = calloc(na * ns, sizeof *r->W);
    if (!idx || !r || !r->W) {
        free(idx);
        swfs_recon_free(r);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    }
    double *A = NULL, lam = 0;
    int rc = solve_sums(l, NULL, ridge, idx, &nu, &A, &lam);
    if (rc) {
        free(idx);
        swfs_recon_free(r);
        return rc;
    }
    /* W = A^T on the seen slopes. */
    for (size_t i = 0; i < nu; i++)
        for (size_t a = 0; a < na; a++) r->W[a * ns + idx[i]] = A[i * na + a];
    r->nact = na;
    r->nslopes = ns;
    r->nmodes = 0;
    if (info) {
        /* The training misfit: sum |z - W s|^2 = zz - 2 tr(A^T H) + tr(A^T G A), and
         * (G + lam) A = H makes tr(A^T G A) = tr(A^T H) - lam |A|^2. */
        double cross = 0, aa = 0;
        for (size_t i = 0; i < nu; i++)
            for (size_t a = 0; a < na; a++) {
                cross += A[i * na + a] * l->H[idx[i] * na + a];
                aa += A[i * na + a] * A[i * na + a];
            }
        info->nframes = l->nframes;
        info->nslopes_seen = nu;
        info->truth_rms = sqrt(l->zz / (double)(l->nframes * na));
        info->misfit_rms = sqrt(fmax(0.0, l->zz - cross - lam * aa) / (double)(l->nframes * na));
    }
    free(idx);
    free(A);
    *out = r;
    return SWFS_OK;
}

int swfs_recon_learner_heldout(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                               double *misfit2, double *truth2)
{
    *misfit2 = *truth2 = NAN;
    const size_t ns = all->nslopes, na = all->nact;
    if (part->nslopes != ns || part->nact != na || part->nframes == 0 || part->nframes >= all->nframes)
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: a held-out part of %zu frames (%zu slopes, %zu "
                         "actuators) of sums over %zu frames (%zu, %zu)", part->nframes, part->nslopes, part->nact,
                         all->nframes, ns, na);
    size_t *idx = malloc(ns * sizeof *idx), nu = 0;
    if (!idx) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    double *A = NULL, lam = 0;
    int rc = solve_sums(all, part, ridge, idx, &nu, &A, &lam);
    double *Gp = NULL, *C = NULL;
    if (!rc) {
        Gp = malloc(nu * nu * sizeof *Gp);
        C = malloc(nu * na * sizeof *C);
        if (!Gp || !C) rc = swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    }
    if (!rc) {
        /* On the part's frames: sum |z - A^T s|^2 = zz - 2 tr(A^T H) + tr(A^T G A), its sums. */
        for (size_t i = 0; i < nu; i++)
            for (size_t j = 0; j < nu; j++) Gp[i * nu + j] = gsum(part, NULL, idx[i], idx[j]);
        cblas_dsymm(CblasRowMajor, CblasLeft, CblasUpper, (int)nu, (int)na, 1.0, Gp, (int)nu, A, (int)na, 0.0, C,
                    (int)na);
        double cross = 0, quad = 0;
        for (size_t i = 0; i < nu; i++)
            for (size_t a = 0; a < na; a++) {
                cross += A[i * na + a] * part->H[idx[i] * na + a];
                quad += A[i * na + a] * C[i * na + a];
            }
        const double n = (double)(part->nframes * na);
        *misfit2 = fmax(0.0, part->zz - 2 * cross + quad) / n;
        *truth2 = part->zz / n;
    }
    free(idx);
    free(A);
    free(Gp);
    free(C);
    return rc;
}

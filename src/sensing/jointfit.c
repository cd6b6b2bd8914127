/* The joint pupil-domain fit: see include/specklewfs/jointfit.h and docs/estimator.md. */
#include "specklewfs/jointfit.h"
#include "jointfit_basis.h"
#include "specklewfs/aperture.h"
#include "specklewfs/mft.h"
#include "specklewfs/parallel.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

void swfs_jointfit_options_default(swfs_jointfit_options *o)
{
    o->knot_factor = 1.0;
    o->legendre_order = 4;
    o->fit_kappa = 1;
    o->max_iter = 40;
    o->gls_iter = 1;
    o->tol = 0.5;
    o->g_prior_sigma = 0.5;
    o->lambda_phi = 0.0;
    o->lambda_alpha = 0.0;
    o->alpha_ratio = 10.0;
    o->alpha_ratio_max = 1000.0;
    o->prior = SWFS_JF_PRIOR_CURVATURE;
    o->intercept = SWFS_JF_INTERCEPT_AUTO;
    o->threads = 0;
    o->g_radial = 3.0;
}

void swfs_jointfit_result_free(swfs_jointfit_result *r)
{
    if (!r) return;
    swfs_cplx_free(r->field);
    swfs_real_free(r->wfe);
    swfs_real_free(r->mask);
    swfs_cplx_free(r->halo);
    swfs_real_free(r->gain);
    free(r);
}

/* 4x4 symmetric matrix entry (i, j) from the upper-triangle planes of the regression. */
/* Symmetric positive definite n x n systems, kept row-major in their upper triangle: the
 * same memory is the column-major lower triangle, so LAPACK works on it in place. (The
 * row-major LAPACKE wrappers transpose a copy in and out on every call: with np ~ 600 that
 * was a fifth of a `pupil` run under the sanitizers, and the copies' page faults more.)
 * Each returns LAPACK's info (0: done). */
static int potrf(double *A, size_t n)
{
    return (int)LAPACKE_dpotrf_work(LAPACK_COL_MAJOR, 'L', (lapack_int)n, A, (lapack_int)n);
}
static int potri(double *A, size_t n)
{
    return (int)LAPACKE_dpotri_work(LAPACK_COL_MAJOR, 'L', (lapack_int)n, A, (lapack_int)n);
}
/* b <- A^-1 b with A factored by potrf. */
static void potrs(const double *A, size_t n, double *b)
{
    LAPACKE_dpotrs_work(LAPACK_COL_MAJOR, 'L', (lapack_int)n, 1, A, (lapack_int)n, b, (lapack_int)n);
}
/* b <- A^-1 b, A factored in place. */
static int posv(double *A, size_t n, double *b)
{
    return (int)LAPACKE_dposv_work(LAPACK_COL_MAJOR, 'L', (lapack_int)n, 1, A, (lapack_int)n, b, (lapack_int)n);
}

static inline size_t tri(size_t i, size_t j)
{
    if (i > j) { size_t t = i; i = j; j = t; }
    return i * 4 - i * (i + 1) / 2 + j;
}

/* Where the valid pixels lie (the regression's solved pixels), once per fit. span: the width in
 * pixels of their span about the star (floor(nx/2), floor(ny/2)), 2 E + 1 with E the largest
 * offset along either axis of a valid pixel, at most the window's larger side (its width when
 * every pixel is valid); 1 when none is. box: their bounding box {x0, x1, y0, y1} (inclusive),
 * across which log g's Legendre terms run. rmax: the farthest one's distance from the star
 * [pixels], to which the radial terms reach. With every pixel valid, box and rmax are the
 * window's (its corner is the farthest pixel), so such a fit is the one before. */
typedef struct jf_extent {
    size_t span, box[4];
    double rmax;
} jf_extent;

static jf_extent jf_valid_extent(const swfs_regress_sol *s, size_t nfx, size_t nfy)
{
    const size_t cx = nfx / 2, cy = nfy / 2, wmax = nfx > nfy ? nfx : nfy;
    jf_extent x = { 0, { nfx, 0, nfy, 0 }, 0.0 };
    size_t e = 0, nvalid = 0;
    for (size_t y = 0; y < nfy; y++)
        for (size_t i = 0; i < nfx; i++) {
            if (!(s->valid->data[y * nfx + i] > 0.5)) continue;
            const size_t dx = i > cx ? i - cx : cx - i, dy = y > cy ? y - cy : cy - y;
            if (dx > e) e = dx;
            if (dy > e) e = dy;
            if (i < x.box[0]) x.box[0] = i;
            if (i > x.box[1]) x.box[1] = i;
            if (y < x.box[2]) x.box[2] = y;
            if (y > x.box[3]) x.box[3] = y;
            x.rmax = fmax(x.rmax, hypot((double)dx, (double)dy));
            nvalid++;
        }
    x.span = 2 * e + 1 < wmax ? 2 * e + 1 : wmax;
    if (!nvalid) {
        x.box[0] = 0; x.box[1] = nfx - 1; x.box[2] = 0; x.box[3] = nfy - 1;
        x.rmax = hypot((double)cx, (double)cy);
    }
    return x;
}

/* AUTO's two fits at once: the free fit's thread posts the model fit's rejection level here
 * when it ends (ok 0: it failed, and the model fit stops), the model fit waits for it where
 * its early stop first needs it. */
typedef struct reject_gate {
    pthread_mutex_t mu;
    pthread_cond_t cv;
    int posted, ok;
    double chi2_reject;
} reject_gate;

typedef struct fit {
    const swfs_jointfit_options *o;
    size_t n, nfx, nfy, nf, nb, nl, np;
    jf_basis *B;
    swfs_mft *mft;
    const double *mask;
    double *leg;            /* nl x nf: log g's terms, the Legendre ones then the radial ones */
    /* per pixel (pixel-major): F 16 (full 4x4), f 4, Phi_sp, marginal c-information 3 */
    double *F, *f, *phi, *mc, *chat, *konst;
    unsigned char *use;
    double g0;
    int stage;              /* 0: linear GLS start (constant g0, c-part only); 1: joint */
    int warm;               /* 1: the prior weights held (no evidence rule) */
    /* state */
    double *x, *xt;         /* parameters, trial */
    double complex *z, *Z, *W, *psi;
    double *g;
    double lam_phi, lam_alpha, gam_phi, gam_alpha, rank;
    double beta_prec;       /* 1 / g_prior_sigma^2 on the non-constant log g terms */
    double noise_scale;     /* the data's weight by the evidence: (ndata - gamma) / chi2 */
    double ndata;           /* data rows: 4 (intercept modelled) or 3 (free) per pixel used */
    int iters;
    /* AUTO's intercept-model fit: the chi2 above which the test rejects it (the free fit's
     * chi2 + limit / its beta; +inf otherwise), and 1 once the fit stopped on that ground */
    double chi2_reject;
    int rejected;
    reject_gate *gate;      /* with the free fit running beside this one: chi2_reject comes
                               from here (NULL once read, and for every other fit) */
    /* work */
    double *yt, *H, *A, *grad, *step, *et, *C, *Rx;
    double *lw;             /* 3 nf + nl nf: per pixel sqrt Q_gg, Q_g kappa, e_g; log g's rows
                               scaled by sqrt Q_gg */
    float *ytf, *hf;        /* single-precision copy of the scaled Jacobian, field block of H */
    int evals;
} fit;

static void fit_free(fit *ft)
{
    jf_basis_free(ft->B);
    swfs_mft_free(ft->mft);
    swfs_free(ft->leg); swfs_free(ft->F); swfs_free(ft->f); swfs_free(ft->phi); swfs_free(ft->mc);
    swfs_free(ft->chat); swfs_free(ft->konst); free(ft->use);
    swfs_free(ft->x); swfs_free(ft->xt); swfs_free(ft->z); swfs_free(ft->Z); swfs_free(ft->W); swfs_free(ft->psi);
    swfs_free(ft->g); swfs_free(ft->yt); swfs_free(ft->H); swfs_free(ft->A); swfs_free(ft->grad);
    swfs_free(ft->step); swfs_free(ft->et); swfs_free(ft->C); swfs_free(ft->Rx); swfs_free(ft->lw);
    swfs_free(ft->ytf); swfs_free(ft->hf);
}

/* phi^T R phi and alpha^T R alpha; Rx = R x for both blocks. */
static void prior_terms(fit *ft, const double *x, double *pa, double *pp)
{
    const size_t nb = ft->nb;
    cblas_dsymv(CblasRowMajor, CblasUpper, (int)nb, 1.0, ft->B->R, (int)nb, x, 1, 0.0, ft->Rx, 1);
    cblas_dsymv(CblasRowMajor, CblasUpper, (int)nb, 1.0, ft->B->R, (int)nb, x + nb, 1, 0.0, ft->Rx + nb, 1);
    *pa = cblas_ddot((int)nb, x, 1, ft->Rx, 1);
    *pp = cblas_ddot((int)nb, x + nb, 1, ft->Rx + nb, 1);
}

/* The model at x: W, Psi, g; returns the chi-square (sum over pixels). */
static double model_chi2(fit *ft, const double *x)
{
    const size_t nb = ft->nb, n = ft->n, nf = ft->nf;
    for (size_t j = 0; j < nb; j++) ft->z[j] = x[j] + I * x[nb + j];
    jf_basis_eval(ft->B, ft->z, ft->Z);
    for (size_t k = 0; k < n * n; k++) ft->W[k] = ft->mask[k] > 0.0 ? ft->mask[k] * cexp(ft->Z[k]) : 0.0;
    swfs_mft_forward(ft->mft, ft->W, ft->psi);
    ft->evals++;
    double chi2 = 0.0;
    const double kappa = x[2 * nb + ft->nl];
    for (size_t k = 0; k < nf; k++) {
        double lg = 0.0;
        for (size_t m = 0; m < ft->nl; m++) lg += x[2 * nb + m] * ft->leg[m * nf + k];
        ft->g[k] = exp(lg);
        if (!ft->use[k]) continue;
        const double pr = creal(ft->psi[k]), pi = cimag(ft->psi[k]);
        if (ft->stage == 0) {
            const double *M = ft->mc + 3 * k;
            const double dr = ft->g0 * pr - ft->chat[2 * k], di = ft->g0 * pi - ft->chat[2 * k + 1];
            chi2 += M[0] * dr * dr + 2.0 * M[1] * dr * di + M[2] * di * di;
            continue;
        }
        const double g = ft->g[k], g2 = g * g;
        const double th[4] = {pr * pr + pi * pi + kappa * g2 * ft->phi[k], g2, g * pr, g * pi};
        const double *F = ft->F + 16 * k, *f = ft->f + 4 * k;
        double q = 0.0;
        for (int i = 0; i < 4; i++) {
            double fi = 0.0;
            for (int j = 0; j < 4; j++) fi += F[4 * i + j] * th[j];
            q += th[i] * (fi - 2.0 * f[i]);
        }
        chi2 += q + ft->konst[k];
    }
    return chi2;
}

/* Gauss-Newton normal matrix H (np x np, full) and gradient grad of chi2/2 at the current
 * model (model_chi2 must have been called at x). */
static void build_normal(fit *ft, const double *x)
{
    const size_t nb = ft->nb, nf = ft->nf, nl = ft->nl, np = ft->np, nz = 2 * nb, nc = nl + 1;
    const double kappa = x[2 * nb + nl];
    jf_jacobian(ft->B, ft->W, ft->yt);
    double *Hc = ft->H; /* row-major np x np */
    memset(Hc, 0, np * np * sizeof *Hc);
    memset(ft->grad, 0, np * sizeof *ft->grad);
    double *Rk = ft->C + 2 * nf * nc; /* 3 per pixel: the 2x2 Cholesky factor of Q_psi,psi */
    double *qgg = ft->lw, *qgk = qgg + nf, *eg = qgk + nf, *ls = eg + nf;
    for (size_t k = 0; k < nf; k++) {
        double Q[4][4] = {{0}}, e[4] = {0};
        if (ft->use[k]) {
            const double pr = creal(ft->psi[k]), pi = cimag(ft->psi[k]);
            if (ft->stage == 0) {
                const double *M = ft->mc + 3 * k, g0 = ft->g0;
                const double dr = g0 * pr - ft->chat[2 * k], di = g0 * pi - ft->chat[2 * k + 1];
                Q[0][0] = g0 * g0 * M[0]; Q[0][1] = Q[1][0] = g0 * g0 * M[1]; Q[1][1] = g0 * g0 * M[2];
                e[0] = g0 * (M[0] * dr + M[1] * di);
                e[1] = g0 * (M[1] * dr + M[2] * di);
            } else {
                const double g = ft->g[k], g2 = g * g, ph = ft->phi[k];
                const double th[4] = {pr * pr + pi * pi + kappa * g2 * ph, g2, g * pr, g * pi};
                /* D = d theta / d (Re Psi, Im Psi, log g, kappa) */
                const double D[4][4] = {{2 * pr, 2 * pi, 2 * kappa * g2 * ph, g2 * ph},
                                        {0, 0, 2 * g2, 0},
                                        {g, 0, g * pr, 0},
                                        {0, g, g * pi, 0}};
                const double *F = ft->F + 16 * k, *f = ft->f + 4 * k;
                double FD[4][4], r[4];
                for (int i = 0; i < 4; i++) {
                    r[i] = -f[i];
                    for (int j = 0; j < 4; j++) {
                        r[i] += F[4 * i + j] * th[j];
                        double s = 0.0;
                        for (int l = 0; l < 4; l++) s += F[4 * i + l] * D[l][j];
                        FD[i][j] = s;
                    }
                }
                for (int i = 0; i < 4; i++) {
                    for (int l = 0; l < 4; l++) e[i] += D[l][i] * r[l];
                    for (int j = 0; j < 4; j++) {
                        double s = 0.0;
                        for (int l = 0; l < 4; l++) s += D[l][i] * FD[l][j];
                        Q[i][j] = s;
                    }
                }
            }
        }
        ft->et[2 * k] = e[0];
        ft->et[2 * k + 1] = e[1];
        /* Cholesky of the 2x2 Psi block (positive semi-definite) */
        const double r00 = Q[0][0] > 0.0 ? sqrt(Q[0][0]) : 0.0;
        const double r01 = r00 > 0.0 ? Q[0][1] / r00 : 0.0;
        const double r11 = sqrt(fmax(Q[1][1] - r01 * r01, 0.0));
        Rk[3 * k] = r00; Rk[3 * k + 1] = r01; Rk[3 * k + 2] = r11;
        if (ft->stage == 1) {
            for (size_t m = 0; m < nl; m++) {
                const double L = ft->leg[m * nf + k];
                ft->C[(2 * k) * nc + m] = Q[0][2] * L;
                ft->C[(2 * k + 1) * nc + m] = Q[1][2] * L;
            }
            ft->C[(2 * k) * nc + nl] = Q[0][3];
            ft->C[(2 * k + 1) * nc + nl] = Q[1][3];
            qgg[k] = sqrt(fmax(Q[2][2], 0.0)); /* Q is an information matrix's congruence: Q_gg >= 0 */
            qgk[k] = Q[2][3];
            eg[k] = e[2];
            ft->grad[nz + nl] += e[3];
            Hc[(nz + nl) * np + nz + nl] += Q[3][3];
        }
    }
    if (ft->stage == 1) {
        /* the log g block over the pixels: sum_k Q_gg L_k L_k^T (one rank-nf update of the
         * log g's rows scaled by sqrt Q_gg), its coupling to kappa and its gradient */
        for (size_t m = 0; m < nl; m++)
            for (size_t k = 0; k < nf; k++) ls[m * nf + k] = ft->leg[m * nf + k] * qgg[k];
        cblas_dsyrk(CblasRowMajor, CblasUpper, CblasNoTrans, (int)nl, (int)nf, 1.0, ls, (int)nf, 0.0,
                    Hc + nz * np + nz, (int)np);
        cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nl, (int)nf, 1.0, ft->leg, (int)nf, qgk, 1, 0.0,
                    Hc + nz * np + nz + nl, (int)np); /* the kappa column of the log g rows */
        cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nl, (int)nf, 1.0, ft->leg, (int)nf, eg, 1, 0.0, ft->grad + nz, 1);
    }
    const int nfd = (int)(2 * nf);
    /* gradient of the field block: Y^T e */
    cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nz, nfd, 1.0, ft->yt, nfd, ft->et, 1, 0.0, ft->grad, 1);
    if (ft->stage == 1) {
        /* cross terms field x (log g, kappa): Y^T C, into rows 0..nz-1, columns nz.. */
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nz, (int)nc, nfd, 1.0, ft->yt, nfd, ft->C,
                    (int)nc, 0.0, Hc + nz, (int)np);
    }
    /* Field block: (R_k Y_k)^T (R_k Y_k), one rank-k update, the fit's largest cost. It is
     * done in single precision (SSYRK, twice the speed of DSYRK): the normal matrix only
     * steers the steps (gradient and cost stay in double, so the minimum found is the
     * double-precision one) and 1e-6 relative errors in it are far below the prior's
     * regularization of its weakest directions. */
    for (size_t r = 0; r < nz; r++) {
        const double *y = ft->yt + r * 2 * nf;
        float *yf = ft->ytf + r * 2 * nf;
        for (size_t k = 0; k < nf; k++) {
            const double y0 = y[2 * k], y1 = y[2 * k + 1];
            yf[2 * k] = (float)(Rk[3 * k] * y0 + Rk[3 * k + 1] * y1);
            yf[2 * k + 1] = (float)(Rk[3 * k + 2] * y1);
        }
    }
    cblas_ssyrk(CblasRowMajor, CblasUpper, CblasNoTrans, (int)nz, nfd, 1.0f, ft->ytf, nfd, 0.0f, ft->hf, (int)nz);
    for (size_t i = 0; i < nz; i++)
        for (size_t j = i; j < nz; j++) Hc[i * np + j] = (double)ft->hf[i * nz + j];
    if (ft->stage == 0 || !ft->o->fit_kappa) {
        /* frozen parameters: identity rows, no coupling */
        const size_t f0 = ft->stage == 0 ? nz : nz + nl;
        for (size_t i = f0; i < np; i++) {
            for (size_t j = 0; j < np; j++) Hc[j * np + i] = Hc[i * np + j] = 0.0;
            Hc[i * np + i] = 1.0;
            ft->grad[i] = 0.0;
        }
    }
    for (size_t i = 0; i < np; i++)
        for (size_t j = 0; j < i; j++) Hc[i * np + j] = Hc[j * np + i];
}

/* A = H + prior (+ mu diag(H)) in A. */
static void assemble(fit *ft, double mu)
{
    const size_t nb = ft->nb, np = ft->np;
    memcpy(ft->A, ft->H, np * np * sizeof *ft->A);
    for (size_t i = 0; i < nb; i++)
        for (size_t j = 0; j < nb; j++) {
            ft->A[i * np + j] += ft->lam_alpha * ft->B->R[i * nb + j];
            ft->A[(nb + i) * np + nb + j] += ft->lam_phi * ft->B->R[i * nb + j];
        }
    for (size_t m = 1; m < ft->nl; m++) ft->A[(2 * nb + m) * np + 2 * nb + m] += ft->beta_prec;
    if (mu > 0.0)
        for (size_t i = 0; i < np; i++) ft->A[i * np + i] += mu * (ft->H[i * np + i] > 0.0 ? ft->H[i * np + i] : 1.0);
}

/* The Gauss-Newton step of the quadratic model at x with the current prior weights (no
 * damping): step = -(H + lambda R)^-1 (grad + lambda R x), xt = x + step. With update set,
 * then MacKay's evidence rule on the same model: gamma = rank(R) - lambda tr(Sigma R),
 * lambda = gamma / (xt^T R xt), Sigma = (H + lambda R)^-1. *dl: the largest relative change
 * of the weights. Returns 0 if H + lambda R is not positive definite. */
static int newton_evidence(fit *ft, int update, double *dl)
{
    const size_t nb = ft->nb, np = ft->np;
    *dl = 0.0;
    assemble(ft, 0.0);
    if (potrf(ft->A, np) != 0) return 0;
    prior_terms(ft, ft->x, &(double){0}, &(double){0}); /* Rx at x */
    for (size_t i = 0; i < np; i++) ft->step[i] = -ft->grad[i];
    for (size_t i = 0; i < nb; i++) {
        ft->step[i] -= ft->lam_alpha * ft->Rx[i];
        ft->step[nb + i] -= ft->lam_phi * ft->Rx[nb + i];
    }
    for (size_t m = 1; m < ft->nl; m++) ft->step[2 * nb + m] -= ft->beta_prec * ft->x[2 * nb + m];
    potrs(ft->A, np, ft->step);
    for (size_t i = 0; i < np; i++) ft->xt[i] = ft->x[i] + ft->step[i];
    if (ft->xt[np - 1] < 0.0) ft->xt[np - 1] = 0.0; /* kappa >= 0 */
    if (!update) return 1;
    if (potri(ft->A, np) != 0) return 0;
    double tra = 0.0, trp = 0.0;
    for (size_t i = 0; i < nb; i++)
        for (size_t j = 0; j < nb; j++) {
            const size_t a = i < j ? i : j, b = i < j ? j : i;
            tra += ft->A[a * np + b] * ft->B->R[i * nb + j];
            trp += ft->A[(nb + a) * np + nb + b] * ft->B->R[i * nb + j];
        }
    double pa, pp;
    prior_terms(ft, ft->xt, &pa, &pp);
    const double rank = ft->rank;
    double ga = rank - ft->lam_alpha * tra, gp = rank - ft->lam_phi * trp;
    ga = fmin(fmax(ga, 1.0), rank);
    gp = fmin(fmax(gp, 1.0), rank);
    ft->gam_alpha = ga;
    ft->gam_phi = gp;
    /* With the data weighted by beta (noise_scale), the cost beta chi2 + lambda x^T R x is
     * chi2 + (lambda / beta) x^T R x: the weights kept here are lambda / beta. */
    const double bs = ft->noise_scale;
    double lp = ft->o->lambda_phi > 0.0 ? ft->o->lambda_phi : (pp > 0.0 ? gp / (bs * pp) : ft->lam_phi);
    double la = ft->o->lambda_alpha > 0.0 ? ft->o->lambda_alpha : (pa > 0.0 ? ga / (bs * pa) : ft->lam_alpha);
    if (ft->o->lambda_alpha <= 0.0) la = fmin(fmax(la, ft->o->alpha_ratio * lp), ft->o->alpha_ratio_max * lp);
    *dl = fmax(fabs(lp / ft->lam_phi - 1.0), fabs(la / ft->lam_alpha - 1.0));
    ft->lam_phi = lp;
    ft->lam_alpha = la;
    return 1;
}

static double total_cost(fit *ft, const double *x, double *chi2)
{
    double pa, pp;
    *chi2 = model_chi2(ft, x);
    prior_terms(ft, x, &pa, &pp);
    double pb = 0.0;
    for (size_t m = 1; m < ft->nl; m++) pb += x[2 * ft->nb + m] * x[2 * ft->nb + m];
    return *chi2 + ft->lam_alpha * pa + ft->lam_phi * pp + ft->beta_prec * pb;
}

/* The intercept a as a free nuisance per pixel: the quadratic form minimized over a, i.e. the
 * Schur complement F_rr - F_r0 F_0r / F_00, f_r - F_r0 f_0 / F_00 on (b, Re c, Im c), with a's
 * row and column zero (the model's a then has no weight). konst stays theta_hat_r^T f_r. */
static void marginalize_a(double *F, double *f, const swfs_regress_sol *s, size_t k, size_t nf, double *konst)
{
    const double F00 = F[0];
    double Fn[16] = {0}, fn[4] = {0};
    for (size_t i = 1; i < 4; i++) {
        fn[i] = f[i] - F[4 * i] * f[0] / F00;
        for (size_t j = 1; j < 4; j++) Fn[4 * i + j] = F[4 * i + j] - F[4 * i] * F[j] / F00;
    }
    memcpy(F, Fn, sizeof Fn);
    memcpy(f, fn, sizeof fn);
    double kk = 0.0;
    for (size_t i = 1; i < 4; i++) kk += s->theta->data[i * nf + k] * f[i];
    *konst = kk;
}

/* Per-pixel data from the regression: full F, f, the marginal information of c (Schur
 * complement, for the linear start), theta_hat^T f (so chi2 >= 0 at the truth), g0. */
static int load_pixels(fit *ft, const swfs_regress_sol *s)
{
    const size_t nf = ft->nf;
    double wsum = 0.0, bsum = 0.0;
    for (size_t k = 0; k < nf; k++) {
        if (!(s->valid->data[k] > 0.5)) continue;
        double *F = ft->F + 16 * k, Fi[16];
        for (size_t i = 0; i < 4; i++) {
            ft->f[4 * k + i] = s->rhs->data[i * nf + k];
            for (size_t j = 0; j < 4; j++) F[4 * i + j] = Fi[4 * i + j] = s->info->data[tri(i, j) * nf + k];
        }
        if (!(F[0] > 0.0) || !isfinite(F[0])) continue;
        if (potrf(Fi, 4) != 0) continue;
        if (potri(Fi, 4) != 0) continue;
        /* covariance of theta_hat = F^-1; marginal information of c = (cov_cc)^-1 */
        const double c22 = Fi[10], c23 = Fi[11], c33 = Fi[15], det = c22 * c33 - c23 * c23;
        if (!(det > 0.0) || !(Fi[5] > 0.0)) continue;
        ft->mc[3 * k] = c33 / det;
        ft->mc[3 * k + 1] = -c23 / det;
        ft->mc[3 * k + 2] = c22 / det;
        ft->chat[2 * k] = s->theta->data[2 * nf + k];
        ft->chat[2 * k + 1] = s->theta->data[3 * nf + k];
        ft->phi[k] = s->phi_sp->data[k];
        double kk = 0.0;
        for (size_t i = 0; i < 4; i++) kk += s->theta->data[i * nf + k] * ft->f[4 * k + i];
        ft->konst[k] = kk;
        if (ft->o->intercept == SWFS_JF_INTERCEPT_FREE) marginalize_a(F, ft->f + 4 * k, s, k, nf, &ft->konst[k]);
        ft->use[k] = 1;
        /* g0^2: information-weighted mean of b_hat */
        wsum += 1.0 / Fi[5];
        bsum += s->theta->data[nf + k] / Fi[5];
    }
    if (!(wsum > 0.0) || !(bsum > 0.0))
        return swfs_fail(SWFS_ERR_NUMERIC, "joint fit: no pixel with a usable regression (scale factor undefined)");
    ft->g0 = sqrt(bsum / wsum);
    return SWFS_OK;
}

/* Linear start: constant field w0 P with the best complex w0 (2 x 2 GLS on the c-part). */
static void start_constant(fit *ft)
{
    const size_t nb = ft->nb, nf = ft->nf;
    for (size_t k = 0; k < ft->n * ft->n; k++) ft->W[k] = ft->mask[k];
    swfs_mft_forward(ft->mft, ft->W, ft->psi);
    double N00 = 0, N01 = 0, N11 = 0, r0 = 0, r1 = 0;
    for (size_t k = 0; k < nf; k++) {
        if (!ft->use[k]) continue;
        const double *M = ft->mc + 3 * k, a = ft->g0 * creal(ft->psi[k]), b = ft->g0 * cimag(ft->psi[k]);
        /* model c = A u, A = [[a, -b], [b, a]] */
        const double A[2][2] = {{a, -b}, {b, a}};
        const double Mm[2][2] = {{M[0], M[1]}, {M[1], M[2]}};
        double MA[2][2];
        for (int i = 0; i < 2; i++)
            for (int j = 0; j < 2; j++) MA[i][j] = Mm[i][0] * A[0][j] + Mm[i][1] * A[1][j];
        N00 += A[0][0] * MA[0][0] + A[1][0] * MA[1][0];
        N01 += A[0][0] * MA[0][1] + A[1][0] * MA[1][1];
        N11 += A[0][1] * MA[0][1] + A[1][1] * MA[1][1];
        const double mc0 = Mm[0][0] * ft->chat[2 * k] + Mm[0][1] * ft->chat[2 * k + 1];
        const double mc1 = Mm[1][0] * ft->chat[2 * k] + Mm[1][1] * ft->chat[2 * k + 1];
        r0 += A[0][0] * mc0 + A[1][0] * mc1;
        r1 += A[0][1] * mc0 + A[1][1] * mc1;
    }
    const double det = N00 * N11 - N01 * N01;
    double complex w0 = det > 0.0 ? ((N11 * r0 - N01 * r1) + I * (N00 * r1 - N01 * r0)) / det : 1.0;
    if (!(cabs(w0) > 0.0) || !isfinite(cabs(w0))) w0 = 1.0;
    const double complex lw = clog(w0);
    for (size_t j = 0; j < nb; j++) {
        ft->x[j] = creal(lw);
        ft->x[nb + j] = cimag(lw);
    }
    ft->x[2 * nb] = log(ft->g0); /* P_0 P_0 = 1 */
}

/* One Levenberg-Marquardt iteration at x (model evaluated at x, cost cur). Returns 1 if a
 * step was accepted (x, cur updated, model left at the new x), 0 if none lowered the cost. */
static int lm_step(fit *ft, double *mu, double *cur, double *chi2)
{
    const size_t np = ft->np, nb = ft->nb;
    for (int tries = 0; tries < 12; tries++) {
        assemble(ft, *mu);
        for (size_t i = 0; i < np; i++) ft->step[i] = -ft->grad[i];
        for (size_t i = 0; i < nb; i++) {
            ft->step[i] -= ft->lam_alpha * ft->Rx[i];
            ft->step[nb + i] -= ft->lam_phi * ft->Rx[nb + i];
        }
        for (size_t m = 1; m < ft->nl; m++) ft->step[2 * nb + m] -= ft->beta_prec * ft->x[2 * nb + m];
        int prc = posv(ft->A, np, ft->step);
        if (prc != 0) {
            *mu = *mu > 0.0 ? *mu * 10.0 : 1e-6;
            continue;
        }
        for (size_t i = 0; i < np; i++) ft->xt[i] = ft->x[i] + ft->step[i];
        double *kap = ft->xt + np - 1;
        if (*kap < 0.0) *kap = 0.0;
        double c2;
        const double c = total_cost(ft, ft->xt, &c2);
        if (c < *cur) {
            memcpy(ft->x, ft->xt, np * sizeof *ft->x);
            *cur = c;
            *chi2 = c2;
            *mu = fmax(*mu / 3.0, 1e-9);
            return 1;
        }
        *mu = *mu > 0.0 ? *mu * 4.0 : 1e-6;
    }
    return 0;
}

/* Iterations of one stage from ft->x (model evaluated there, unless fresh is 0: then the
 * caller has just built the normal equations at x). Each iteration: normal equations at x;
 * the evidence fixed point on that quadratic model (cheap: no new Jacobian), then the
 * step, accepted if the true cost falls, else Levenberg-Marquardt damping. Returns the cost. */
static double run_stage(fit *ft, int maxit, int built, double *chi2)
{
    const int evid = !ft->warm && (ft->o->lambda_phi <= 0.0 || ft->o->lambda_alpha <= 0.0);
    double mu = 1e-3, cur = total_cost(ft, ft->x, chi2), dl = 0.0;
    double drops[3] = {0, 0, 0}; /* the last iterations' falls of chi2 (or of the cost) */
    for (int it = 0; it < maxit; it++) {
        const double chi2_at = *chi2;
        if (!built) build_normal(ft, ft->x);
        built = 0;
        /* MacKay's rule for the data's own weight: beta = (rows - well-determined
         * parameters) / chi2. The information matrices take every frame as independent;
         * frames correlated in time (slow wind, several camera frames per speckle
         * lifetime) or computed speckles with errors of their own make the data look more
         * certain than they are, chi2 per degree of freedom rises above 1, and without
         * this the prior weights followed the over-confident data into a rough phase
         * that ran away at the pupil rim (docs/estimator.md). */
        if (evid && ft->stage == 1 && *chi2 > 0.0) {
            const double gtot = (double)ft->np - (ft->rank - ft->gam_phi) - (ft->rank - ft->gam_alpha);
            const double b = (ft->ndata - gtot) / *chi2;
            ft->noise_scale = fmin(fmax(b, SWFS_JF_NOISE_SCALE_MIN), 1.0 / SWFS_JF_NOISE_SCALE_MIN);
        }
        /* The evidence fixed point lambda = T(lambda) converges slowly where gamma is small;
         * a secant step on log lambda - log T(lambda) (per weight) finds it in a few passes. */
        double lp[2] = {0, 0}, fp[2] = {0, 0};
        const double lam0[2] = {ft->lam_phi, ft->lam_alpha};
        for (int inner = 0; inner < (it < 2 ? 12 : 3) && evid; inner++) {
            const double l[2] = {log(ft->lam_phi), log(ft->lam_alpha)};
            if (!newton_evidence(ft, 1, &dl)) break;
            if (dl < 1e-2) break;
            const double f[2] = {log(ft->lam_phi) - l[0], log(ft->lam_alpha) - l[1]};
            double ln[2];
            for (int c = 0; c < 2; c++) {
                ln[c] = l[c] + f[c];
                if (inner > 0 && f[c] != fp[c]) {
                    const double sec = l[c] - f[c] * (l[c] - lp[c]) / (f[c] - fp[c]);
                    ln[c] = fmin(fmax(sec, l[c] - 3.0), l[c] + 3.0);
                }
                lp[c] = l[c];
                fp[c] = f[c];
            }
            if (ft->o->lambda_phi <= 0.0) ft->lam_phi = exp(ln[0]);
            if (ft->o->lambda_alpha <= 0.0)
                ft->lam_alpha = fmin(fmax(exp(ln[1]), ft->o->alpha_ratio * ft->lam_phi), ft->o->alpha_ratio_max * ft->lam_phi);
        }
        /* Where the evidence is flat (gamma ~ 1: alpha, when the amplitude is uniform) the
         * fixed point moves between outer iterations and can cycle; from the third
         * iteration on, each weight moves only half-way (geometrically). */
        if (evid && it >= 2) {
            ft->lam_phi = sqrt(ft->lam_phi * lam0[0]);
            ft->lam_alpha = sqrt(ft->lam_alpha * lam0[1]);
        }
        if (evid) dl = fmax(fabs(ft->lam_phi / lam0[0] - 1.0), fabs(ft->lam_alpha / lam0[1] - 1.0));
        if (!newton_evidence(ft, 0, &(double){0})) break;
        const double before = total_cost(ft, ft->x, chi2); /* the prior weights may have moved */
        double c2;
        double c = total_cost(ft, ft->xt, &c2);
        int ok = c < before;
        if (ok) {
            memcpy(ft->x, ft->xt, ft->np * sizeof *ft->x);
            *chi2 = c2;
        } else {
            cur = total_cost(ft, ft->x, chi2);
            ok = lm_step(ft, &mu, &cur, chi2);
            c = cur;
        }
        cur = ok ? c : before;
        if (ft->stage == 1) ft->iters++;
        if (!ok || (before - c < ft->o->tol && dl < 0.05)) break;
        /* A rejected intercept model (AUTO): the model's chi2 must fall below chi2_reject to be
         * kept. Once it is further above it than twice the largest fall of the last three
         * iterations for every iteration left could take it, the test's outcome within
         * max_iter is settled and the rest of the fit (up to max_iter iterations of a model
         * that does not fit, the slowest part of a `pupil` run) would be thrown away. */
        if (ft->stage == 1 && !ft->warm && (ft->gate || isfinite(ft->chi2_reject))) {
            drops[it % 3] = fmax(chi2_at - *chi2, ok ? before - c : 0.0);
            const double fall = fmax(drops[0], fmax(drops[1], drops[2]));
            if (it >= 2 && ft->gate) { /* the free fit's level, once it has one */
                reject_gate *gt = ft->gate;
                pthread_mutex_lock(&gt->mu);
                while (!gt->posted) pthread_cond_wait(&gt->cv, &gt->mu);
                const int free_ok = gt->ok; /* 0: the free fit failed; this fit's result is unused */
                ft->chi2_reject = free_ok ? gt->chi2_reject : NAN;
                pthread_mutex_unlock(&gt->mu);
                ft->gate = NULL;
                if (!free_ok) break; /* with no finite level the test below never stops the fit */
            }
            if (it >= 2 && *chi2 - ft->chi2_reject > 2.0 * fall * (double)(maxit - it - 1)) {
                ft->rejected = 1;
                break;
            }
        }
    }
    return cur;
}

/* The prior weights and the data's weight the evidence rule moves, saved and restored between
 * the two runs of stage 1. */
typedef struct fit_weights {
    double lam_phi, lam_alpha, noise_scale, gam_phi, gam_alpha;
} fit_weights;
static fit_weights weights_get(const fit *ft)
{
    return (fit_weights){ft->lam_phi, ft->lam_alpha, ft->noise_scale, ft->gam_phi, ft->gam_alpha};
}
static void weights_set(fit *ft, const fit_weights *w)
{
    ft->lam_phi = w->lam_phi;
    ft->lam_alpha = w->lam_alpha;
    ft->noise_scale = w->noise_scale;
    ft->gam_phi = w->gam_phi;
    ft->gam_alpha = w->gam_alpha;
}

/* The log evidence of the fit at x (Laplace's approximation, constants dropped): with the data
 * weighted by beta and the priors by beta lambda (the weights kept are lambda / beta),
 * -beta C / 2 + N/2 log beta + rank/2 (log beta lambda_phi + log beta lambda_alpha)
 * - 1/2 log det beta (H + lambda R). Leaves the model at x. -inf where H + lambda R is not
 * positive definite. */
static double log_evidence(fit *ft)
{
    double chi2;
    const double c = total_cost(ft, ft->x, &chi2);
    build_normal(ft, ft->x);
    assemble(ft, 0.0);
    const size_t np = ft->np;
    if (potrf(ft->A, np) != 0) return -INFINITY;
    double ld = 0.0;
    for (size_t i = 0; i < np; i++) ld += 2.0 * log(ft->A[i * np + i]);
    const double b = ft->noise_scale, r = ft->rank;
    const double le = -0.5 * b * c + 0.5 * ft->ndata * log(b) + 0.5 * r * (log(b * ft->lam_phi) + log(b * ft->lam_alpha)) -
                      0.5 * (double)np * log(b) - 0.5 * ld;
    return le; /* (build_normal reads the model at x, it does not move it) */
}

/* chi2_reject: the intercept model's rejection level in chi2 (AUTO's second fit), or +inf. */
static int jointfit_one(const swfs_regress_sol *sol, const swfs_geom *geo, const swfs_real *mask_in,
                        const swfs_jointfit_options *opt, double chi2_reject, reject_gate *gate,
                        swfs_jointfit_result **out)
{
    *out = NULL;
    struct timespec t0, t1;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    swfs_jointfit_options o = *opt;
    if (o.intercept == SWFS_JF_INTERCEPT_FREE) o.fit_kappa = 0; /* kappa lives only in a */
    int rc = swfs_geom_require(geo, "joint fit");
    if (rc) return rc;
    if (!(o.knot_factor > 0.0) || o.legendre_order < 0 || o.legendre_order > 8 || o.max_iter < 0 || o.gls_iter < 0 ||
        !(o.alpha_ratio >= 0.0) || !(o.alpha_ratio_max >= o.alpha_ratio) || !(o.tol >= 0.0) || !isfinite(o.g_radial) ||
        (o.prior != SWFS_JF_PRIOR_GRADIENT && o.prior != SWFS_JF_PRIOR_CURVATURE))
        return swfs_fail(SWFS_ERR_ARG, "joint fit: invalid options (knot_factor %g, legendre_order %d, max_iter %d, "
                                       "gls_iter %d, alpha_ratio %g, tol %g, g_radial %g)",
                         o.knot_factor, o.legendre_order, o.max_iter, o.gls_iter, o.alpha_ratio, o.tol, o.g_radial);
    const size_t n = (size_t)geo->pupn, nfx = sol->nx, nfy = sol->ny, nf = nfx * nfy;
    if (nfx < 2 || nfy < 2) return swfs_fail(SWFS_ERR_SHAPE, "joint fit: the focal window %zux%zu is too small", nfx, nfy);
    if (mask_in && (mask_in->nx != n || mask_in->ny != n))
        return swfs_fail(SWFS_ERR_SHAPE, "joint fit: pupil mask is %zux%zu but the geometry says PUPN = %zu", mask_in->nx,
                         mask_in->ny, n);
    swfs_jointfit_result *res = calloc(1, sizeof *res);
    fit ft;
    memset(&ft, 0, sizeof ft);
    ft.noise_scale = 1.0;
    ft.chi2_reject = chi2_reject;
    ft.gate = gate;
    if (!res) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    res->mask = mask_in ? swfs_real_copy(mask_in) : swfs_real_alloc(n, n, 1);
    if (!res->mask) { rc = SWFS_ERR_NOMEM; goto done; }
    if (!mask_in && (rc = swfs_aperture_make(res->mask->data, n, geo->pupdx, geo->teldiam, geo->obscur, 0, 0.0))) goto done;

    /* Knots: the pixels the regression holds span +-E pixels from the star (E the largest
     * offset along either axis of a valid one: the window's half-width when all are), so they
     * constrain pupil-field structure up to E PIXSCALE cycles per D; a cubic B-spline grid
     * resolves up to about one cycle per two intervals, hence intervals across D = their
     * width, 2 E + 1 pixels, in lambda/D (the window's width when every pixel is valid).
     * Speckles computed only within a band (the sampling band of a reconstructor's points)
     * leave the pixels beyond it invalid; structure beyond them would be unconstrained
     * unknowns that the fit trades with the constrained ones (docs/estimator.md). */
    const jf_extent ext = jf_valid_extent(sol, nfx, nfy);
    const double width = (double)ext.span * geo->pixscale;
    size_t nint = (size_t)ceil(o.knot_factor * width - 1e-9);
    if (nint < 2) nint = 2;
    const double alpha = geo->pixscale * geo->pupdx / geo->teldiam;
    ft.o = &o;
    ft.n = n; ft.nfx = nfx; ft.nfy = nfy; ft.nf = nf;
    ft.mask = res->mask->data;
    ft.B = jf_basis_create(ft.mask, n, geo->teldiam / geo->pupdx, nint, nfx, nfy, alpha);
    if (!ft.B) { rc = SWFS_ERR_NOMEM; goto done; }
    if (ft.B->nb < 2) { rc = swfs_fail(SWFS_ERR_VALUE, "joint fit: the pupil mask is empty"); goto done; }
    ft.mft = swfs_mft_create(n, nfx, nfy, alpha, SWFS_MFT_DOUBLE);
    ft.nb = ft.B->nb;
    ft.beta_prec = o.g_prior_sigma > 0.0 ? 1.0 / (o.g_prior_sigma * o.g_prior_sigma) : 0.0;
    if (o.prior == SWFS_JF_PRIOR_CURVATURE) jf_basis_penalty(ft.B, ft.mask, 1);
    /* R's null space: constants (gradient), constants and tilts (curvature) */
    ft.rank = (double)ft.nb - (o.prior == SWFS_JF_PRIOR_CURVATURE ? 3.0 : 1.0);
    /* log g's terms: the 2-D Legendre ones across the valid pixels' box, then the radial
     * B-splines out to the farthest valid pixel (their spacing in pixels: g_radial lambda/D,
     * at least one pixel) */
    const double hrad = o.g_radial > 0.0 ? fmax(o.g_radial / geo->pixscale, 1.0) : 0.0;
    const size_t nleg = jf_legendre_count(o.legendre_order);
    ft.nl = nleg + jf_radial_count(hrad, ext.rmax);
    ft.np = 2 * ft.nb + ft.nl + 1;
    const size_t np = ft.np, nb = ft.nb, nc = ft.nl + 1;
    ft.leg = swfs_malloc(ft.nl * nf * sizeof *ft.leg);
    ft.F = swfs_calloc(16 * nf, sizeof *ft.F);
    ft.f = swfs_calloc(4 * nf, sizeof *ft.f);
    ft.phi = swfs_calloc(nf, sizeof *ft.phi);
    ft.mc = swfs_calloc(3 * nf, sizeof *ft.mc);
    ft.chat = swfs_calloc(2 * nf, sizeof *ft.chat);
    ft.konst = swfs_calloc(nf, sizeof *ft.konst);
    ft.use = calloc(nf, 1);
    ft.x = swfs_calloc(np, sizeof *ft.x);
    ft.xt = swfs_calloc(np, sizeof *ft.xt);
    ft.z = swfs_malloc(nb * sizeof *ft.z);
    ft.Z = swfs_malloc(n * n * sizeof *ft.Z);
    ft.W = swfs_malloc(n * n * sizeof *ft.W);
    ft.psi = swfs_malloc(nf * sizeof *ft.psi);
    ft.g = swfs_malloc(nf * sizeof *ft.g);
    ft.yt = swfs_malloc(2 * nb * 2 * nf * sizeof *ft.yt);
    ft.H = swfs_malloc(np * np * sizeof *ft.H);
    ft.A = swfs_malloc(np * np * sizeof *ft.A);
    ft.grad = swfs_malloc(np * sizeof *ft.grad);
    ft.step = swfs_malloc(np * sizeof *ft.step);
    ft.et = swfs_malloc(2 * nf * sizeof *ft.et);
    ft.C = swfs_calloc(2 * nf * nc + 3 * nf, sizeof *ft.C);
    ft.Rx = swfs_malloc(2 * nb * sizeof *ft.Rx);
    ft.lw = swfs_malloc((3 + ft.nl) * nf * sizeof *ft.lw);
    ft.ytf = swfs_malloc(2 * nb * 2 * nf * sizeof *ft.ytf);
    ft.hf = swfs_malloc(4 * nb * nb * sizeof *ft.hf);
    if (!ft.mft || !ft.leg || !ft.F || !ft.f || !ft.phi || !ft.mc || !ft.chat || !ft.konst || !ft.use || !ft.x ||
        !ft.xt || !ft.z || !ft.Z || !ft.W || !ft.psi || !ft.g || !ft.yt || !ft.H || !ft.A || !ft.grad || !ft.step ||
        !ft.et || !ft.C || !ft.Rx || !ft.lw || !ft.ytf || !ft.hf) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory (joint fit, %zu parameters)", np);
        goto done;
    }
    jf_legendre(o.legendre_order, nfx, nfy, ext.box, ft.leg);
    if (ft.nl > nleg) jf_radial(hrad, ext.rmax, nfx, nfy, ft.leg + nleg * nf);
    if ((rc = load_pixels(&ft, sol))) goto done;
    start_constant(&ft);

    /* Stage 0: the linear GLS start (constant g0, the c-part's marginal information), then
     * stage 1: the joint fit. First prior weights: 1e-3 of the data's mean curvature per
     * phase parameter relative to R's; the evidence rule takes over at once or after the
     * fit has converged at them (below). */
    double chi2 = 0.0, cur;
    ft.stage = 0;
    cur = total_cost(&ft, ft.x, &chi2);
    build_normal(&ft, ft.x);
    {
        double hz = 0.0, rz = 0.0;
        for (size_t i = 0; i < nb; i++) { hz += ft.H[(nb + i) * np + nb + i]; rz += ft.B->R[i * nb + i]; }
        ft.lam_phi = o.lambda_phi > 0.0 ? o.lambda_phi : 1e-3 * hz / rz;
        ft.lam_alpha = o.lambda_alpha > 0.0 ? o.lambda_alpha : o.alpha_ratio * ft.lam_phi;
    }
    cur = run_stage(&ft, o.gls_iter, 1, &chi2);
    ft.stage = 1;
    {
        size_t nu = 0;
        for (size_t k = 0; k < nf; k++) nu += ft.use[k];
        ft.ndata = (o.intercept == SWFS_JF_INTERCEPT_FREE ? 3.0 : 4.0) * (double)nu;
        ft.gam_phi = ft.gam_alpha = ft.rank; /* until the first evidence pass */
    }
    /* Two fixed points of the evidence rule. From the constant-field start the rule's first
     * passes read that start's misfit as noise (beta = (rows - gamma) / chi2 small) and weight
     * the prior up, and on some data settle at a flat phase (a foreign 10 x 10 observation:
     * FITLPHI 2.8e7 against 180, WFE 33 nm rms for an 80 nm NCP); run first to convergence at
     * the start's weak prior weights, the phase can run rough and the rule land elsewhere (a
     * 14 x 14 zonal one at 80 photons). So both are run, the rule at once and after that warm
     * start, and the one of the larger log evidence is kept (docs/estimator.md, "Two starts,
     * one evidence"). An intercept model stopped early (AUTO) is not run twice: its result
     * is not used; nor is a fit whose prior weights are given (no rule to start). */
    double *xa = swfs_malloc(np * sizeof *xa), *x0 = swfs_malloc(np * sizeof *x0);
    if (!xa || !x0) {
        free(xa);
        free(x0);
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory (joint fit, %zu parameters)", np);
        goto done;
    }
    memcpy(x0, ft.x, np * sizeof *x0);
    const fit_weights w0 = weights_get(&ft);
    cur = run_stage(&ft, o.max_iter, 0, &chi2);
    res->log_evidence = res->log_evidence_alt = NAN;
    if (!ft.rejected && (o.lambda_phi <= 0.0 || o.lambda_alpha <= 0.0)) {
        const double le_a = log_evidence(&ft);
        const fit_weights wa = weights_get(&ft);
        memcpy(xa, ft.x, np * sizeof *xa);
        memcpy(ft.x, x0, np * sizeof *x0);
        weights_set(&ft, &w0);
        ft.warm = 1;
        run_stage(&ft, o.max_iter, 0, &chi2);
        ft.warm = 0;
        run_stage(&ft, o.max_iter, 0, &chi2);
        const double le_b = ft.rejected ? -INFINITY : log_evidence(&ft);
        ft.rejected = 0;
        res->warm_start = le_b > le_a;
        res->log_evidence = res->warm_start ? le_b : le_a;
        res->log_evidence_alt = res->warm_start ? le_a : le_b;
        if (!res->warm_start) {
            memcpy(ft.x, xa, np * sizeof *xa);
            weights_set(&ft, &wa);
        }
    }
    free(xa);
    free(x0);
    cur = total_cost(&ft, ft.x, &chi2); /* leaves the model at x */

    res->field = swfs_cplx_alloc(n, n, 1);
    res->wfe = swfs_real_alloc(n, n, 1);
    res->halo = swfs_cplx_alloc(nfx, nfy, 1);
    res->gain = swfs_real_alloc(nfx, nfy, 1);
    if (!res->field || !res->wfe || !res->halo || !res->gain) { rc = SWFS_ERR_NOMEM; goto done; }
    memcpy(res->field->data, ft.W, n * n * sizeof *ft.W);
    memcpy(res->halo->data, ft.psi, nf * sizeof *ft.psi);
    memcpy(res->gain->data, ft.g, nf * sizeof *ft.g);
    /* eq:NCP-WFE-estimate without a wrapped arg: lambda/(2 pi) Im log W, piston removed */
    const double k2m = geo->wavelen / (2.0 * M_PI);
    double wsum = 0.0, mean = 0.0, s2 = 0.0;
    for (size_t k = 0; k < n * n; k++)
        if (ft.mask[k] > 0.0) { wsum += ft.mask[k]; mean += ft.mask[k] * cimag(ft.Z[k]); }
    mean /= wsum;
    for (size_t k = 0; k < n * n; k++) {
        const double w = ft.mask[k] > 0.0 ? k2m * (cimag(ft.Z[k]) - mean) : 0.0;
        res->wfe->data[k] = w;
        s2 += ft.mask[k] * w * w;
    }
    res->wfe_rms = sqrt(s2 / wsum);
    res->kappa = ft.x[np - 1];
    res->lambda_phi = ft.lam_phi;
    res->noise_scale = ft.noise_scale;
    res->lambda_alpha = ft.lam_alpha;
    res->gamma_phi = ft.gam_phi;
    res->gamma_alpha = ft.gam_alpha;
    res->chi2 = chi2;
    res->cost = cur;
    for (size_t k = 0; k < nf; k++) res->npix += ft.use[k];
    res->nintervals = nint;
    res->nbasis = nb;
    res->nparams = np;
    res->iterations = ft.iters;
    res->evaluations = ft.evals;
    res->model_stopped = ft.rejected;
done:
    fit_free(&ft);
    if (rc) { swfs_jointfit_result_free(res); return rc; }
    clock_gettime(CLOCK_MONOTONIC, &t1);
    res->seconds = (double)(t1.tv_sec - t0.tv_sec) + 1e-9 * (double)(t1.tv_nsec - t0.tv_nsec);
    *out = res;
    return SWFS_OK;
}

/* AUTO's likelihood-ratio test (below): the rejection threshold of the chi-square difference
 * for npix pixels, and the model fit's chi2 beyond which the test rejects it. In units of the
 * free fit's calibrated noise (its evidence data weight beta): frames that are not
 * independent inflate both chi-squares by 1/beta, and the test must not read that as light
 * the model cannot explain. */
static double model_limit(size_t npix)
{
    const double dof = (double)npix - 1.0;
    return dof + SWFS_JF_INTERCEPT_Z * sqrt(2.0 * (dof > 1.0 ? dof : 1.0));
}

static double model_reject(const swfs_jointfit_result *rf)
{
    return rf->chi2 + model_limit(rf->npix) / rf->noise_scale; /* beta >= SWFS_JF_NOISE_SCALE_MIN */
}

/* AUTO's free fit on a thread of its own: its result, and the model fit's level posted. */
typedef struct free_job {
    const swfs_regress_sol *sol;
    const swfs_geom *geo;
    const swfs_real *mask;
    const swfs_jointfit_options *o;
    reject_gate *gate;
    swfs_jointfit_result *res;
    int rc;
    char why[1024];
} free_job;

static void *free_worker(void *arg)
{
    free_job *j = arg;
    j->rc = jointfit_one(j->sol, j->geo, j->mask, j->o, INFINITY, NULL, &j->res);
    if (j->rc) snprintf(j->why, sizeof j->why, "%s", swfs_last_error());
    reject_gate *g = j->gate;
    pthread_mutex_lock(&g->mu);
    g->ok = !j->rc;
    if (!j->rc) g->chi2_reject = model_reject(j->res);
    g->posted = 1;
    pthread_cond_broadcast(&g->cv);
    pthread_mutex_unlock(&g->mu);
    return NULL;
}

/* SWFS_JF_INTERCEPT_AUTO: both fits, and a likelihood-ratio test of the intercept model. With a
 * free intercept per pixel the data term is the profile chi-square over a; the model adds one
 * constraint per pixel (less kappa), so when the model is right the difference of the two
 * minimized chi-squares is chi-square distributed with npix - 1 degrees of freedom once it is
 * put in units of the calibrated noise (times the free fit's noise_scale). The model is kept
 * unless the difference exceeds its mean by SWFS_JF_INTERCEPT_Z standard deviations. */
int swfs_jointfit(const swfs_regress_sol *sol, const swfs_geom *geo, const swfs_real *mask,
                  const swfs_jointfit_options *opt, swfs_jointfit_result **out)
{
    *out = NULL;
    swfs_jointfit_options o;
    swfs_jointfit_options_default(&o);
    if (opt) o = *opt;
    if (o.intercept != SWFS_JF_INTERCEPT_AUTO) {
        if (o.intercept != SWFS_JF_INTERCEPT_MODEL && o.intercept != SWFS_JF_INTERCEPT_FREE)
            return swfs_fail(SWFS_ERR_ARG, "joint fit: intercept %d: expected model, free or auto", o.intercept);
        int rc = jointfit_one(sol, geo, mask, &o, INFINITY, NULL, out);
        if (!rc) {
            (*out)->intercept = o.intercept;
            (*out)->delta_chi2 = (*out)->delta_chi2_limit = NAN;
        }
        return rc;
    }
    swfs_jointfit_result *rf = NULL, *rm = NULL;
    swfs_jointfit_options of = o, om = o;
    of.intercept = SWFS_JF_INTERCEPT_FREE;
    om.intercept = SWFS_JF_INTERCEPT_MODEL;
    const double t0 = swfs_wall_seconds();
    /* With two threads the two fits run at once: the model fit waits for the free fit's
     * level only where its early stop first asks for it (its third iteration), so its
     * steps, and the result, are those of the fits one after the other. */
    reject_gate gate = {.posted = 0};
    free_job fj = {sol, geo, mask, &of, &gate, NULL, 0, ""};
    pthread_t th;
    int concurrent = 0;
    if (swfs_parallel_threads(o.threads, 2) >= 2 && pthread_mutex_init(&gate.mu, NULL) == 0) {
        if (pthread_cond_init(&gate.cv, NULL) == 0) {
            concurrent = pthread_create(&th, NULL, free_worker, &fj) == 0;
            if (!concurrent) pthread_cond_destroy(&gate.cv);
        }
        if (!concurrent) pthread_mutex_destroy(&gate.mu);
    }
    int rc;
    if (concurrent) {
        jointfit_one(sol, geo, mask, &om, INFINITY, &gate, &rm); /* a failure leaves rm NULL, as below */
        pthread_join(th, NULL);
        pthread_cond_destroy(&gate.cv);
        pthread_mutex_destroy(&gate.mu);
        rf = fj.res;
        if (fj.rc) {
            swfs_jointfit_result_free(rm);
            return swfs_fail(fj.rc, "%s", fj.why);
        }
    } else {
        if ((rc = jointfit_one(sol, geo, mask, &of, INFINITY, NULL, &rf))) return rc;
        jointfit_one(sol, geo, mask, &om, model_reject(rf), NULL, &rm);
    }
    const double limit = model_limit(rf->npix);
    const double delta = rm ? rf->noise_scale * (rm->chi2 - rf->chi2) : NAN;
    swfs_jointfit_result *keep = rf, *drop = rm;
    if (rm && delta <= limit) { keep = rm; drop = rf; }
    keep->intercept = keep == rm ? SWFS_JF_INTERCEPT_MODEL : SWFS_JF_INTERCEPT_FREE;
    keep->delta_chi2 = delta;
    keep->delta_chi2_limit = limit;
    keep->model_stopped = rm ? rm->model_stopped : 0;
    keep->seconds = swfs_wall_seconds() - t0;
    swfs_jointfit_result_free(drop);
    *out = keep;
    return SWFS_OK;
}

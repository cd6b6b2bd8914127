/* Bases of the joint fit: cubic B-splines on the pupil, their gradient penalty, the
 * focal-field Jacobian by local MFTs, 2-D Legendre polynomials. See jointfit_basis.h. */
#include "jointfit_basis.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Uniform cubic B-spline, support (-2, 2). */
static double bspline3(double t)
{
    t = fabs(t);
    if (t < 1.0) return 2.0 / 3.0 - t * t + 0.5 * t * t * t;
    if (t < 2.0) { const double u = 2.0 - t; return u * u * u / 6.0; }
    return 0.0;
}

void jf_basis_free(jf_basis *b)
{
    if (!b) return;
    free(b->b1); free(b->lo); free(b->len); free(b->idx); free(b->ja); free(b->jb);
    swfs_free(b->R); swfs_free(b->axa); swfs_free(b->ayb); free(b->off); swfs_free(b->xa);
    free(b);
}

/* Roughness penalty R = sum over stencils s placed on the pupil (all samples inside) of
 * (sum_t w_t B(s_t)) (sum_t w_t B(s_t))^T. Gradient: first differences along x and y;
 * curvature (thin plate): second differences xx, yy and twice the squared mixed one. */
typedef struct stencil {
    int np;
    int dp[4], dq[4];
    double w[4];
} stencil;

static void add_stencil(jf_basis *b, const double *mask, const stencil *st)
{
    const size_t n = b->n, na = b->na, nb = b->nb;
    size_t jl[128];
    double dv[128];
    int pmin = 0, pmax = 0, qmin = 0, qmax = 0;
    for (int t = 0; t < st->np; t++) {
        if (st->dp[t] < pmin) pmin = st->dp[t];
        if (st->dp[t] > pmax) pmax = st->dp[t];
        if (st->dq[t] < qmin) qmin = st->dq[t];
        if (st->dq[t] > qmax) qmax = st->dq[t];
    }
    for (size_t q = (size_t)-qmin; q + (size_t)qmax < n; q++)
        for (size_t p = (size_t)-pmin; p + (size_t)pmax < n; p++) {
            int inside = 1;
            for (int t = 0; t < st->np && inside; t++)
                inside = mask[(q + (size_t)st->dq[t]) * n + p + (size_t)st->dp[t]] > 0.0;
            if (!inside) continue;
            size_t m = 0;
            for (size_t a = 0; a < na; a++) {
                if (b->lo[a] > p + (size_t)pmax || b->lo[a] + b->len[a] + (size_t)(-pmin) <= p) continue;
                for (size_t c = 0; c < na; c++) {
                    if (b->lo[c] > q + (size_t)qmax || b->lo[c] + b->len[c] + (size_t)(-qmin) <= q) continue;
                    const long j = b->idx[c * na + a];
                    if (j < 0 || m >= 128) continue;
                    double d = 0.0;
                    for (int t = 0; t < st->np; t++)
                        d += st->w[t] * b->b1[a * n + p + (size_t)st->dp[t]] * b->b1[c * n + q + (size_t)st->dq[t]];
                    if (d == 0.0) continue;
                    jl[m] = (size_t)j;
                    dv[m++] = d;
                }
            }
            for (size_t u = 0; u < m; u++)
                for (size_t v = 0; v < m; v++) b->R[jl[u] * nb + jl[v]] += dv[u] * dv[v];
        }
}

void jf_basis_penalty(jf_basis *b, const double *mask, int curvature)
{
    memset(b->R, 0, b->nb * b->nb * sizeof *b->R);
    if (!curvature) {
        const stencil dx = {2, {0, 1}, {0, 0}, {-1, 1}}, dy = {2, {0, 0}, {0, 1}, {-1, 1}};
        add_stencil(b, mask, &dx);
        add_stencil(b, mask, &dy);
    } else {
        const double r2 = sqrt(2.0);
        const stencil dxx = {3, {-1, 0, 1}, {0, 0, 0}, {1, -2, 1}}, dyy = {3, {0, 0, 0}, {-1, 0, 1}, {1, -2, 1}};
        const stencil dxy = {4, {0, 1, 0, 1}, {0, 0, 1, 1}, {r2, -r2, -r2, r2}};
        add_stencil(b, mask, &dxx);
        add_stencil(b, mask, &dyy);
        add_stencil(b, mask, &dxy);
    }
}

jf_basis *jf_basis_create(const double *mask, size_t n, double diam_samples, size_t nint, size_t nfx, size_t nfy,
                          double alpha)
{
    jf_basis *b = calloc(1, sizeof *b);
    if (!b) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    b->n = n; b->nfx = nfx; b->nfy = nfy; b->nint = nint;
    b->na = nint + 3;
    b->h = diam_samples / (double)nint;
    const size_t na = b->na;
    b->b1 = calloc(na * n, sizeof *b->b1);
    b->lo = calloc(na, sizeof *b->lo);
    b->len = calloc(na, sizeof *b->len);
    b->idx = malloc(na * na * sizeof *b->idx);
    b->ja = calloc(na * na, sizeof *b->ja);
    b->jb = calloc(na * na, sizeof *b->jb);
    b->off = calloc(na + 1, sizeof *b->off);
    if (!b->b1 || !b->lo || !b->len || !b->idx || !b->ja || !b->jb || !b->off) goto nomem;
    /* Function a is centred at -D/2 + (a - 1) h (pupil sample coordinates, centre of the
     * grid at (n - 1)/2): the functions a = 0 .. nint + 2 are all that touch [-D/2, D/2]. */
    const double cp = 0.5 * (double)(n - 1);
    for (size_t a = 0; a < na; a++) {
        const double c = -0.5 * diam_samples + ((double)a - 1.0) * b->h;
        size_t lo = n, hi = 0;
        for (size_t p = 0; p < n; p++) {
            const double v = bspline3(((double)p - cp - c) / b->h);
            b->b1[a * n + p] = v;
            if (v > 0.0) { if (p < lo) lo = p; hi = p + 1; }
        }
        b->lo[a] = lo < hi ? lo : 0;
        b->len[a] = lo < hi ? hi - lo : 0;
    }
    /* Keep (a, b) when some pupil sample sees it. */
    b->nb = 0;
    for (size_t c = 0; c < na; c++)
        for (size_t a = 0; a < na; a++) {
            int seen = 0;
            for (size_t q = b->lo[c]; q < b->lo[c] + b->len[c] && !seen; q++)
                for (size_t p = b->lo[a]; p < b->lo[a] + b->len[a]; p++)
                    if (mask[q * n + p] > 0.0) { seen = 1; break; }
            if (seen) {
                b->idx[c * na + a] = (long)b->nb;
                b->ja[b->nb] = a;
                b->jb[b->nb] = c;
                b->nb++;
            } else {
                b->idx[c * na + a] = -1;
            }
        }
    b->R = swfs_calloc(b->nb * b->nb, sizeof *b->R);
    for (size_t a = 0; a < na; a++) b->off[a + 1] = b->off[a] + b->len[a];
    const size_t nf = nfx > nfy ? nfx : nfy;
    b->axa = swfs_malloc(nfx * b->off[na] * sizeof *b->axa);
    b->ayb = swfs_malloc(nfy * b->off[na] * sizeof *b->ayb);
    b->xa = swfs_malloc(n * nf * sizeof *b->xa);
    if (!b->R || !b->axa || !b->ayb || !b->xa) goto nomem;
    jf_basis_penalty(b, mask, 0);
    /* The MFT matrices of mft.h, A(i, p) = exp(-2 pi i alpha (i - nf/2)(p - cp)), restricted
     * to each function's support and multiplied by it. */
    for (int axis = 0; axis < 2; axis++) {
        const size_t nfa = axis ? nfy : nfx;
        double complex *dst = axis ? b->ayb : b->axa;
        const double cf = (double)(nfa / 2);
        for (size_t a = 0; a < na; a++)
            for (size_t i = 0; i < nfa; i++)
                for (size_t t = 0; t < b->len[a]; t++) {
                    const size_t p = b->lo[a] + t;
                    const double ph = -2.0 * M_PI * alpha * ((double)i - cf) * ((double)p - cp);
                    dst[nfa * b->off[a] + i * b->len[a] + t] = b->b1[a * n + p] * (cos(ph) + I * sin(ph));
                }
    }
    return b;
nomem:
    jf_basis_free(b);
    swfs_fail(SWFS_ERR_NOMEM, "out of memory (joint-fit basis)");
    return NULL;
}

void jf_basis_eval(const jf_basis *b, const double complex *z, double complex *Z)
{
    const size_t n = b->n, na = b->na;
    memset(Z, 0, n * n * sizeof *Z);
    for (size_t j = 0; j < b->nb; j++) {
        const size_t a = b->ja[j], c = b->jb[j];
        const double *bx = b->b1 + a * n, *by = b->b1 + c * n;
        for (size_t q = b->lo[c]; q < b->lo[c] + b->len[c]; q++) {
            const double complex zy = z[j] * by[q];
            double complex *row = Z + q * n;
            for (size_t p = b->lo[a]; p < b->lo[a] + b->len[a]; p++) row[p] += zy * bx[p];
        }
    }
    (void)na;
}

void jf_jacobian(jf_basis *b, const double complex *W, double *yt)
{
    /* dPsi/dz_j = MFT(W B_j) = Ay diag(by) W diag(bx) Ax^T restricted to the support of B_j.
     * For each x-function a: X_a = W[:, supp a] (Ax[:, supp a] bx_a)^T (n x nfx); then for
     * each y-function c with (a, c) kept: J = (Ay[:, supp c] by_c) X_a[supp c, :]. */
    const size_t n = b->n, na = b->na, nfx = b->nfx, nfy = b->nfy, nf = nfx * nfy, nb = b->nb;
    const double complex one = 1.0, zero = 0.0;
    for (size_t a = 0; a < na; a++) {
        int any = 0;
        for (size_t c = 0; c < na; c++) any |= b->idx[c * na + a] >= 0;
        if (!any) continue;
        /* rows of X_a actually needed: the union of the kept y-supports */
        size_t q0 = n, q1 = 0;
        for (size_t c = 0; c < na; c++)
            if (b->idx[c * na + a] >= 0) {
                if (b->lo[c] < q0) q0 = b->lo[c];
                if (b->lo[c] + b->len[c] > q1) q1 = b->lo[c] + b->len[c];
            }
        cblas_zgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)(q1 - q0), (int)nfx, (int)b->len[a], &one,
                    W + q0 * n + b->lo[a], (int)n, b->axa + nfx * b->off[a], (int)b->len[a], &zero,
                    b->xa + q0 * nfx, (int)nfx);
        for (size_t c = 0; c < na; c++) {
            const long j = b->idx[c * na + a];
            if (j < 0) continue;
            double complex *row = (double complex *)(yt + (size_t)j * 2 * nf);
            cblas_zgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nfy, (int)nfx, (int)b->len[c], &one,
                        b->ayb + nfy * b->off[c], (int)b->len[c], b->xa + b->lo[c] * nfx, (int)nfx, &zero, row,
                        (int)nfx);
            double *ri = yt + ((size_t)j + nb) * 2 * nf;
            const double *rr = (const double *)row;
            for (size_t k = 0; k < nf; k++) {
                ri[2 * k] = -rr[2 * k + 1];
                ri[2 * k + 1] = rr[2 * k];
            }
        }
    }
}

size_t jf_legendre_count(int order) { return (size_t)(order + 1) * (size_t)(order + 2) / 2; }

static double legendre(int p, double u)
{
    double p0 = 1.0, p1 = u;
    if (p == 0) return p0;
    for (int k = 1; k < p; k++) {
        const double p2 = ((2.0 * k + 1.0) * u * p1 - k * p0) / (k + 1.0);
        p0 = p1;
        p1 = p2;
    }
    return p1;
}

void jf_legendre(int order, size_t nfx, size_t nfy, double *out)
{
    const size_t nf = nfx * nfy;
    size_t m = 0;
    for (int t = 0; t <= order; t++)
        for (int p = t; p >= 0; p--) {
            const int q = t - p;
            for (size_t j = 0; j < nfy; j++) {
                const double v = nfy > 1 ? (2.0 * (double)j - (double)(nfy - 1)) / (double)(nfy - 1) : 0.0;
                const double lq = legendre(q, v);
                for (size_t i = 0; i < nfx; i++) {
                    const double u = nfx > 1 ? (2.0 * (double)i - (double)(nfx - 1)) / (double)(nfx - 1) : 0.0;
                    out[m * nf + j * nfx + i] = legendre(p, u) * lq;
                }
            }
            m++;
        }
}

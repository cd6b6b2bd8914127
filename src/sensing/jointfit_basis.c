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
    free(b->b1); free(b->lo); free(b->len); free(b->near); free(b->pw); free(b->idx); free(b->ja); free(b->jb);
    swfs_free(b->R); swfs_free(b->axa); swfs_free(b->ayb); free(b->off); swfs_free(b->xa);
    free(b);
}

/* Roughness penalty R = sum over stencils s placed on the pupil (all samples inside) of
 * (sum_t w_t B(s_t)) (sum_t w_t B(s_t))^T. Gradient: first differences along x and y;
 * curvature (thin plate): second differences xx, yy and twice the squared mixed one. Every
 * stencil is a product of a 1-D stencil along x and one along y, and so is its response to a
 * tensor-product function B_a(p) B_c(q): u_a(p) v_c(q), u and v the 1-D stencils applied to
 * the 1-D functions. Row q's share of R is then S_q (x) v(q) v(q)^T, with S_q the sum of
 * u(p) u(p)^T over the row's samples whose stencil lies inside the pupil: a few 1-D products
 * per sample, where the 2-D outer product per sample would be hundreds. */
typedef struct stencil1 {
    int n;
    int d[3];
    double w[3];
} stencil1;

/* The 1-D stencil s applied to the functions meeting it at sample p: their list into fl,
 * values into fv; the count returned. */
static size_t stencil_row(const jf_basis *b, const stencil1 *s, size_t p, int dmin, int dmax, size_t *fl, double *fv)
{
    size_t k = 0;
    for (size_t a = 0; a < b->na; a++) {
        if (b->lo[a] > p + (size_t)dmax || b->lo[a] + b->len[a] + (size_t)(-dmin) <= p) continue;
        double v = 0.0;
        for (int t = 0; t < s->n; t++) v += s->w[t] * b->b1[a * b->n + p + (size_t)s->d[t]];
        fl[k] = a;
        fv[k++] = v;
    }
    return k;
}

static void stencil_extent(const stencil1 *s, int *mn, int *mx)
{
    *mn = *mx = 0;
    for (int t = 0; t < s->n; t++) {
        if (s->d[t] < *mn) *mn = s->d[t];
        if (s->d[t] > *mx) *mx = s->d[t];
    }
}

static void add_stencil(jf_basis *b, const double *mask, const stencil1 *sx, const stencil1 *sy)
{
    const size_t n = b->n, na = b->na, nb = b->nb;
    size_t *cl = b->near, *al = b->near + na;
    double *S = b->pw, *vc = S + na * na, *ua = vc + na;
    int pmin, pmax, qmin, qmax;
    stencil_extent(sx, &pmin, &pmax);
    stencil_extent(sy, &qmin, &qmax);
    for (size_t q = (size_t)-qmin; q + (size_t)qmax < n; q++) {
        const size_t ncl = stencil_row(b, sy, q, qmin, qmax, cl, vc);
        memset(S, 0, na * na * sizeof *S);
        size_t amin = na, amax = 0;
        for (size_t p = (size_t)-pmin; p + (size_t)pmax < n; p++) {
            int inside = 1;
            for (int j = 0; j < sy->n && inside; j++)
                for (int i = 0; i < sx->n && inside; i++)
                    inside = mask[(q + (size_t)sy->d[j]) * n + p + (size_t)sx->d[i]] > 0.0;
            if (!inside) continue;
            const size_t nal = stencil_row(b, sx, p, pmin, pmax, al, ua);
            for (size_t i = 0; i < nal; i++)
                for (size_t k = 0; k < nal; k++) S[al[i] * na + al[k]] += ua[i] * ua[k];
            if (nal && al[0] < amin) amin = al[0];
            if (nal && al[nal - 1] + 1 > amax) amax = al[nal - 1] + 1;
        }
        for (size_t a = amin; a < amax; a++)
            for (size_t a2 = amin; a2 < amax; a2++) {
                const double sv = S[a * na + a2];
                if (sv == 0.0) continue;
                for (size_t i = 0; i < ncl; i++) {
                    const long j = b->idx[cl[i] * na + a];
                    if (j < 0) continue;
                    for (size_t k = 0; k < ncl; k++) {
                        const long j2 = b->idx[cl[k] * na + a2];
                        if (j2 >= 0) b->R[(size_t)j * nb + (size_t)j2] += sv * vc[i] * vc[k];
                    }
                }
            }
    }
}

void jf_basis_penalty(jf_basis *b, const double *mask, int curvature)
{
    memset(b->R, 0, b->nb * b->nb * sizeof *b->R);
    const stencil1 one = {1, {0}, {1}}, d1 = {2, {0, 1}, {-1, 1}}, d2 = {3, {-1, 0, 1}, {1, -2, 1}};
    if (!curvature) {
        add_stencil(b, mask, &d1, &one); /* d/dx */
        add_stencil(b, mask, &one, &d1); /* d/dy */
    } else {
        const double r2 = sqrt(2.0);
        const stencil1 d1r2 = {2, {0, 1}, {-r2, r2}};
        add_stencil(b, mask, &d2, &one);  /* d2/dx2 */
        add_stencil(b, mask, &one, &d2);  /* d2/dy2 */
        add_stencil(b, mask, &d1, &d1r2); /* sqrt 2 d2/dxdy */
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
    b->near = calloc(2 * na, sizeof *b->near);
    b->pw = calloc(na * na + 2 * na, sizeof *b->pw);
    b->idx = malloc(na * na * sizeof *b->idx);
    b->ja = calloc(na * na, sizeof *b->ja);
    b->jb = calloc(na * na, sizeof *b->jb);
    b->off = calloc(na + 1, sizeof *b->off);
    if (!b->b1 || !b->lo || !b->len || !b->near || !b->pw || !b->idx || !b->ja || !b->jb || !b->off) goto nomem;
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

/* The coordinate of pixel i across [a, b] in [-1, 1], held at the ends beyond them. */
static double box_coord(size_t i, size_t a, size_t b)
{
    if (b <= a) return 0.0;
    const double u = (2.0 * (double)i - (double)a - (double)b) / (double)(b - a);
    return u < -1.0 ? -1.0 : u > 1.0 ? 1.0 : u;
}

void jf_legendre(int order, size_t nfx, size_t nfy, const size_t box[4], double *out)
{
    const size_t nf = nfx * nfy;
    size_t m = 0;
    for (int t = 0; t <= order; t++)
        for (int p = t; p >= 0; p--) {
            const int q = t - p;
            for (size_t j = 0; j < nfy; j++) {
                const double lq = legendre(q, box_coord(j, box[2], box[3]));
                for (size_t i = 0; i < nfx; i++)
                    out[m * nf + j * nfx + i] = legendre(p, box_coord(i, box[0], box[1])) * lq;
            }
            m++;
        }
}

size_t jf_radial_count(double h, double rmax)
{
    if (!(h > 0.0)) return 0;
    return (size_t)ceil(fmax(rmax, 0.0) / h - 1e-9) + 2;
}

void jf_radial(double h, double rmax, size_t nfx, size_t nfy, double *out)
{
    const size_t nr = jf_radial_count(h, rmax), nf = nfx * nfy;
    const double cx = (double)(nfx / 2), cy = (double)(nfy / 2);
    for (size_t j = 0; j < nfy; j++)
        for (size_t i = 0; i < nfx; i++) {
            const double u = hypot((double)i - cx, (double)j - cy) / h;
            for (size_t m = 0; m < nr; m++) out[m * nf + j * nfx + i] = bspline3(u - (double)m);
        }
}

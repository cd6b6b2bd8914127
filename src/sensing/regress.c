/* Streaming per-pixel regression statistics: see include/specklewfs/regress.h and
 * docs/estimator.md (Stage 1). */
#include "specklewfs/regress.h"
#include "specklewfs/numeric.h"
#include "specklewfs/status.h"

#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NS SWFS_REGRESS_NSTATE

swfs_regress *swfs_regress_create(size_t nx, size_t ny)
{
    if (!nx || !ny) {
        swfs_fail(SWFS_ERR_ARG, "regression accumulator of size %zux%zu", nx, ny);
        return NULL;
    }
    swfs_regress *r = calloc(1, sizeof *r);
    if (!r) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    r->nx = nx;
    r->ny = ny;
    r->state = swfs_calloc(nx * ny * NS, sizeof(double));
    if (!r->state) { free(r); swfs_fail(SWFS_ERR_NOMEM, "out of memory (regression accumulator %zux%zu)", nx, ny); return NULL; }
    return r;
}

void swfs_regress_free(swfs_regress *r)
{
    if (!r) return;
    swfs_free(r->state);
    free(r);
}

void swfs_regress_reset(swfs_regress *r)
{
    memset(r->state, 0, r->nx * r->ny * NS * sizeof(double));
    r->frames = r->skipped = 0;
}

int swfs_regress_add(swfs_regress *r, const double *science, const double *psi, const double *weights)
{
    const size_t np = r->nx * r->ny;
    double *restrict s = r->state;
    for (size_t k = 0; k < np; k++)
        if (!isfinite(psi[2 * k]) || !isfinite(psi[2 * k + 1]))
            return swfs_fail(SWFS_ERR_VALUE, "speckle value at pixel (%zu, %zu) of frame %llu is not finite (%g%+gi)",
                             k % r->nx, k / r->nx, (unsigned long long)r->frames, psi[2 * k], psi[2 * k + 1]);
    double *restrict n = s + SWFS_REG_N * np, *restrict cset = s + SWFS_REG_CSET * np;
    double *restrict c0r = s + SWFS_REG_C0RE * np, *restrict c0i = s + SWFS_REG_C0IM * np;
    double *restrict sr = s + SWFS_REG_SRE * np, *restrict si = s + SWFS_REG_SIM * np;
    double *restrict g00 = s + SWFS_REG_G00 * np, *restrict g01 = s + SWFS_REG_G01 * np;
    double *restrict g02 = s + SWFS_REG_G02 * np, *restrict g03 = s + SWFS_REG_G03 * np;
    double *restrict g11 = s + SWFS_REG_G11 * np, *restrict g12 = s + SWFS_REG_G12 * np;
    double *restrict g13 = s + SWFS_REG_G13 * np, *restrict g22 = s + SWFS_REG_G22 * np;
    double *restrict g23 = s + SWFS_REG_G23 * np, *restrict g33 = s + SWFS_REG_G33 * np;
    double *restrict h0 = s + SWFS_REG_H0 * np, *restrict h1 = s + SWFS_REG_H1 * np;
    double *restrict h2 = s + SWFS_REG_H2 * np, *restrict h3 = s + SWFS_REG_H3 * np;
    double *restrict yy = s + SWFS_REG_YY * np;
    uint64_t skipped = 0;
    for (size_t k = 0; k < np; k++) {
        const double Iv = science[k], w = weights ? weights[k] : 1.0;
        if (!isfinite(Iv) || !(w > 0.0) || !isfinite(w)) { skipped++; continue; }
        if (cset[k] == 0.0) { c0r[k] = psi[2 * k]; c0i[k] = psi[2 * k + 1]; cset[k] = 1.0; }
        const double pr = psi[2 * k] - c0r[k], pi = psi[2 * k + 1] - c0i[k];
        /* x = (1, |p|^2, 2 Re p, 2 Im p) */
        const double x1 = pr * pr + pi * pi, x2 = 2.0 * pr, x3 = 2.0 * pi;
        const double wx1 = w * x1, wx2 = w * x2, wx3 = w * x3, wI = w * Iv;
        n[k] += 1.0; sr[k] += pr; si[k] += pi;
        g00[k] += w; g01[k] += wx1; g02[k] += wx2; g03[k] += wx3;
        g11[k] += wx1 * x1; g12[k] += wx1 * x2; g13[k] += wx1 * x3;
        g22[k] += wx2 * x2; g23[k] += wx2 * x3; g33[k] += wx3 * x3;
        h0[k] += wI; h1[k] += wI * x1; h2[k] += wI * x2; h3[k] += wI * x3;
        yy[k] += wI * Iv;
    }
    r->frames++;
    r->skipped += skipped;
    return SWFS_OK;
}

/* ---- one pixel's state as a vector v[NS] -------------------------------- */

static void gather(const double *s, size_t np, size_t k, double *v)
{
    for (int f = 0; f < NS; f++) v[f] = s[(size_t)f * np + k];
}

static void scatter(double *s, size_t np, size_t k, const double *v)
{
    for (int f = 0; f < NS; f++) s[(size_t)f * np + k] = v[f];
}

static void unpack_g(const double *v, double G[4][4])
{
    const double *g = v + SWFS_REG_G00;
    int t = 0;
    for (int i = 0; i < 4; i++)
        for (int j = i; j < 4; j++) G[i][j] = G[j][i] = g[t++];
}

static void pack_g(double G[4][4], double *v)
{
    double *g = v + SWFS_REG_G00;
    int t = 0;
    for (int i = 0; i < 4; i++)
        for (int j = i; j < 4; j++) g[t++] = G[i][j];
}

/* Move the centre of one pixel's state by delta (c_new = c_old + delta): with
 * x_old = T(delta) x_new, G_new = T(-delta) G T(-delta)^T and h_new = T(-delta) h. */
static void recenter_px(double *v, double dr, double di)
{
    if (dr == 0.0 && di == 0.0) return;
    const double M[4][4] = {{1, 0, 0, 0}, {dr * dr + di * di, 1, -dr, -di}, {-2 * dr, 0, 1, 0}, {-2 * di, 0, 0, 1}};
    double G[4][4], MG[4][4], Gn[4][4], h[4];
    unpack_g(v, G);
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            double a = 0.0;
            for (int l = 0; l < 4; l++) a += M[i][l] * G[l][j];
            MG[i][j] = a;
        }
    for (int i = 0; i < 4; i++)
        for (int j = i; j < 4; j++) {
            double a = 0.0;
            for (int l = 0; l < 4; l++) a += MG[i][l] * M[j][l];
            Gn[i][j] = Gn[j][i] = a;
        }
    pack_g(Gn, v);
    for (int i = 0; i < 4; i++) {
        double a = 0.0;
        for (int l = 0; l < 4; l++) a += M[i][l] * v[SWFS_REG_H0 + l];
        h[i] = a;
    }
    for (int i = 0; i < 4; i++) v[SWFS_REG_H0 + i] = h[i];
    v[SWFS_REG_SRE] -= v[SWFS_REG_N] * dr;
    v[SWFS_REG_SIM] -= v[SWFS_REG_N] * di;
    v[SWFS_REG_C0RE] += dr;
    v[SWFS_REG_C0IM] += di;
}

int swfs_regress_merge(swfs_regress *dst, const swfs_regress *src)
{
    if (dst->nx != src->nx || dst->ny != src->ny)
        return swfs_fail(SWFS_ERR_SHAPE, "cannot merge regression accumulators of %zux%zu and %zux%zu pixels", dst->nx,
                         dst->ny, src->nx, src->ny);
    const size_t np = dst->nx * dst->ny;
    double a[NS], b[NS];
    for (size_t k = 0; k < np; k++) {
        gather(src->state, np, k, b);
        if (b[SWFS_REG_N] == 0.0) continue;
        gather(dst->state, np, k, a);
        if (a[SWFS_REG_N] == 0.0) { scatter(dst->state, np, k, b); continue; }
        recenter_px(b, a[SWFS_REG_C0RE] - b[SWFS_REG_C0RE], a[SWFS_REG_C0IM] - b[SWFS_REG_C0IM]);
        b[SWFS_REG_C0RE] = a[SWFS_REG_C0RE]; /* exactly dst's centre, not dst + rounding */
        b[SWFS_REG_C0IM] = a[SWFS_REG_C0IM];
        for (int f = 0; f < NS; f++)
            if (f != SWFS_REG_C0RE && f != SWFS_REG_C0IM && f != SWFS_REG_CSET) a[f] += b[f];
        scatter(dst->state, np, k, a);
    }
    dst->frames += src->frames;
    dst->skipped += src->skipped;
    return SWFS_OK;
}

int swfs_regress_recenter(swfs_regress *r, const double *centre)
{
    const size_t np = r->nx * r->ny;
    if (centre)
        for (size_t k = 0; k < np; k++)
            if (!isfinite(centre[2 * k]) || !isfinite(centre[2 * k + 1]))
                return swfs_fail(SWFS_ERR_VALUE, "re-centring: centre at pixel (%zu, %zu) is not finite", k % r->nx, k / r->nx);
    double v[NS];
    for (size_t k = 0; k < np; k++) {
        gather(r->state, np, k, v);
        const double n = v[SWFS_REG_N];
        double cr, ci;
        if (centre) { cr = centre[2 * k]; ci = centre[2 * k + 1]; }
        else if (n > 0.0) { cr = v[SWFS_REG_C0RE] + v[SWFS_REG_SRE] / n; ci = v[SWFS_REG_C0IM] + v[SWFS_REG_SIM] / n; }
        else continue;
        if (n == 0.0) {
            v[SWFS_REG_C0RE] = cr; v[SWFS_REG_C0IM] = ci; v[SWFS_REG_CSET] = 1.0;
            scatter(r->state, np, k, v);
            continue;
        }
        recenter_px(v, cr - v[SWFS_REG_C0RE], ci - v[SWFS_REG_C0IM]);
        v[SWFS_REG_C0RE] = cr;
        v[SWFS_REG_C0IM] = ci;
        scatter(r->state, np, k, v);
    }
    return SWFS_OK;
}

void swfs_regress_export(const swfs_regress *r, double *state)
{
    memcpy(state, r->state, r->nx * r->ny * NS * sizeof(double));
}

int swfs_regress_import(swfs_regress *r, const double *state)
{
    const size_t np = r->nx * r->ny;
    static const int diag[4] = {SWFS_REG_G00, SWFS_REG_G11, SWFS_REG_G22, SWFS_REG_G33};
    for (size_t k = 0; k < np; k++) {
        const double n = state[SWFS_REG_N * np + k];
        if (!isfinite(n) || n < 0.0 || n != floor(n))
            return swfs_fail(SWFS_ERR_VALUE, "regression state: frame count %g at pixel (%zu, %zu) is not a count", n,
                             k % r->nx, k / r->nx);
        for (int d = 0; d < 4; d++) {
            const double g = state[(size_t)diag[d] * np + k];
            if (!isfinite(g) || g < 0.0)
                return swfs_fail(SWFS_ERR_VALUE, "regression state: Gram diagonal %d is %g at pixel (%zu, %zu)", d, g,
                                 k % r->nx, k / r->nx);
        }
    }
    memcpy(r->state, state, np * NS * sizeof(double));
    return SWFS_OK;
}

/* ---- solution ------------------------------------------------------------ */

void swfs_regress_sol_free(swfs_regress_sol *s)
{
    if (!s) return;
    swfs_real_free(s->theta); swfs_real_free(s->info); swfs_real_free(s->rhs);
    swfs_real_free(s->s2); swfs_real_free(s->phi_sp); swfs_cplx_free(s->centre); swfs_real_free(s->valid);
    swfs_real_free(s->r2);
    free(s);
}

int swfs_regress_solve(const swfs_regress *r, swfs_regress_sol **out)
{
    *out = NULL;
    const size_t nx = r->nx, ny = r->ny, np = nx * ny;
    swfs_regress_sol *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    s->nx = nx; s->ny = ny;
    s->theta = swfs_real_alloc(nx, ny, 4);
    s->info = swfs_real_alloc(nx, ny, 10);
    s->rhs = swfs_real_alloc(nx, ny, 4);
    s->s2 = swfs_real_alloc(nx, ny, 1);
    s->phi_sp = swfs_real_alloc(nx, ny, 1);
    s->centre = swfs_cplx_alloc(nx, ny, 1);
    s->valid = swfs_real_alloc(nx, ny, 1);
    s->r2 = swfs_real_alloc(nx, ny, 1);
    if (!s->theta || !s->info || !s->rhs || !s->s2 || !s->phi_sp || !s->centre || !s->valid || !s->r2) {
        swfs_regress_sol_free(s);
        return SWFS_ERR_NOMEM;
    }
    double v[NS], sst_sum = 0, sse_sum = 0;
    for (size_t k = 0; k < np; k++) s->r2->data[k] = NAN;
    for (size_t k = 0; k < np; k++) {
        gather(r->state, np, k, v);
        const double n = v[SWFS_REG_N];
        if (!(n > 0.0)) continue;
        /* The paper's frame: psi' = psi - <psi> (eq:zeroMean). */
        const double mr = v[SWFS_REG_SRE] / n, mi = v[SWFS_REG_SIM] / n;
        recenter_px(v, mr, mi);
        s->centre->data[k] = (v[SWFS_REG_C0RE]) + I * (v[SWFS_REG_C0IM]);
        double G[4][4], A[16], b[4];
        unpack_g(v, G);
        if (G[0][0] > 0.0) s->phi_sp->data[k] = G[0][1] / G[0][0];
        /* s^2 has nu = n - 4 degrees of freedom. theta's distribution with s^2 estimated is a
         * Student t of nu degrees of freedom, whose covariance is the Gaussian's (G / s^2)^-1
         * times nu / (nu - 2), and infinite for nu <= 2: the information is the t's,
         * G / s^2 (nu - 2) / nu, and a pixel with nu <= 2 gives none. A pixel the science
         * frames cover in a few frames only (at the detector's edge, a registration's shift)
         * otherwise carried the information of its 1-dof s^2, which can be near 0: one such
         * pixel of 2916, 5 frames among 599, drove a joint fit to a 93 nm wavefront error
         * (9.7 without it; docs/estimator.md). */
        if (!(n > 6.0)) continue;
        const double nu = n - 4.0, tcov = (nu - 2.0) / nu;
        const double ridge = SWFS_REGRESS_RIDGE * (G[2][2] + G[3][3]);
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) A[4 * j + i] = G[i][j] + (i == j && i >= 2 ? ridge : 0.0);
        for (int i = 0; i < 4; i++) b[i] = v[SWFS_REG_H0 + i];
        if (LAPACKE_dposv_work(LAPACK_COL_MAJOR, 'U', 4, 1, A, 4, b, 4) != 0) continue;
        double th = 0.0;
        for (int i = 0; i < 4; i++) th += b[i] * v[SWFS_REG_H0 + i];
        const double s2 = (v[SWFS_REG_YY] - th) / nu;
        if (!(s2 > 0.0) || !isfinite(s2)) continue;
        s->s2->data[k] = s2;
        for (int i = 0; i < 4; i++) {
            s->theta->data[(size_t)i * np + k] = b[i];
            s->rhs->data[(size_t)i * np + k] = tcov * v[SWFS_REG_H0 + i] / s2;
        }
        for (int t = 0; t < 10; t++) s->info->data[(size_t)t * np + k] = tcov * v[SWFS_REG_G00 + t] / s2;
        s->valid->data[k] = 1.0;
        s->n_valid++;
        /* the self-check: variance about the mean (the intercept alone) against what is left */
        const double sst = v[SWFS_REG_YY] - v[SWFS_REG_H0] * v[SWFS_REG_H0] / G[0][0], sse = v[SWFS_REG_YY] - th;
        if (sst > 0) {
            sst_sum += sst;
            sse_sum += sse;
            s->r2->data[k] = 1 - sse / sst;
        }
    }
    s->explained = sst_sum > 0 ? 1 - sse_sum / sst_sum : NAN;
    /* the median pixel's, from the map's finite values (a copy: the median sorts) */
    double *r2 = malloc(np * sizeof *r2);
    size_t nr2 = 0;
    for (size_t k = 0; r2 && k < np; k++)
        if (isfinite(s->r2->data[k])) r2[nr2++] = s->r2->data[k];
    s->explained_median = nr2 ? swfs_median_inplace(r2, nr2) : NAN;
    free(r2);
    if (!s->n_valid) {
        swfs_regress_sol_free(s);
        return swfs_fail(SWFS_ERR_NUMERIC, "regression: no pixel has more than 6 usable frames (4 parameters and a noise "
                         "estimate of more than 2 degrees of freedom) and a solvable Gram matrix");
    }
    *out = s;
    return SWFS_OK;
}

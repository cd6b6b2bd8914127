/* Clough-Tocher interpolation matrix on a qhull Delaunay triangulation (see interp.h). */
#include "specklewfs/interp.h"
#include "specklewfs/array.h"
#include "specklewfs/numeric.h"
#include "specklewfs/status.h"

#include <libqhull_r/qhull_ra.h>
#include <lapacke.h>

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct tri_mesh {
    size_t npts, ntri;
    const double *pts;
    int *tri;      /* 3 per triangle, counter-clockwise */
    size_t *nbr_ptr; /* CSR adjacency of the vertices (npts + 1) */
    size_t *nbr;
} tri_mesh;

static void mesh_free(tri_mesh *m)
{
    free(m->tri); free(m->nbr_ptr); free(m->nbr);
    memset(m, 0, sizeof *m);
}

/* Delaunay triangles from qhull ("d Qt Qbb Qc Qz Q12", as scipy does: Qz adds a point at
 * infinity so cocircular rings -- every hexapolar actuator layout -- triangulate). */
static int delaunay(const double *pts, size_t npts, tri_mesh *m)
{
    if (npts < 3) return swfs_fail(SWFS_ERR_ARG, "interpolation needs at least 3 points, got %zu", npts);
    memset(m, 0, sizeof *m);
    m->pts = pts; m->npts = npts;
    coordT *coords = malloc(2 * npts * sizeof *coords);
    if (!coords) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t i = 0; i < 2 * npts; i++) coords[i] = pts[i];

    char *errbuf = NULL;
    size_t errlen = 0;
    FILE *err = open_memstream(&errbuf, &errlen);
    qhT qh_qh;
    qhT *qh = &qh_qh;
    qh_zero(qh, err);
    char opts[] = "qhull d Qt Qbb Qc Qz Q12";
    int exitcode = qh_new_qhull(qh, 2, (int)npts, coords, False, opts, NULL, err);
    int rc = SWFS_OK;
    if (exitcode) {
        if (err) fflush(err);
        rc = swfs_fail(SWFS_ERR_NUMERIC, "Delaunay triangulation of %zu points failed (qhull %d): %.200s",
                       npts, exitcode, errbuf ? errbuf : "");
    } else {
        size_t cap = 0;
        facetT *facet;
        FORALLfacets { if (!facet->upperdelaunay) cap++; }
        m->tri = malloc((cap ? cap : 1) * 3 * sizeof *m->tri);
        if (!m->tri) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        else {
            FORALLfacets {
                if (facet->upperdelaunay) continue;
                vertexT *vertex, **vertexp;
                int v[3], k = 0;
                FOREACHvertex_(facet->vertices) {
                    if (k < 3) v[k] = qh_pointid(qh, vertex->point);
                    k++;
                }
                if (k != 3 || v[0] < 0 || v[1] < 0 || v[2] < 0 || (size_t)v[0] >= npts ||
                    (size_t)v[1] >= npts || (size_t)v[2] >= npts)
                    continue;
                const double *a = pts + 2 * v[0], *b = pts + 2 * v[1], *c = pts + 2 * v[2];
                double area2 = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
                double scale = fabs(b[0] - a[0]) + fabs(b[1] - a[1]) + fabs(c[0] - a[0]) + fabs(c[1] - a[1]);
                if (fabs(area2) <= 1e-12 * scale * scale) continue; /* degenerate sliver from Qt */
                if (area2 < 0) { int t = v[1]; v[1] = v[2]; v[2] = t; }
                memcpy(m->tri + 3 * m->ntri, v, sizeof v);
                m->ntri++;
            }
        }
    }
    qh_freeqhull(qh, !qh_ALL);
    int curlong, totlong;
    qh_memfreeshort(qh, &curlong, &totlong);
    if (err) fclose(err);
    free(errbuf);
    free(coords);
    if (rc == SWFS_OK && m->ntri == 0)
        rc = swfs_fail(SWFS_ERR_NUMERIC, "Delaunay triangulation of %zu points has no triangles (collinear points?)", npts);
    if (rc) { mesh_free(m); return rc; }

    /* Vertex adjacency from the triangle edges (deduplicated). */
    size_t *deg = calloc(npts + 1, sizeof *deg);
    size_t *tmp = malloc(6 * m->ntri * sizeof *tmp);
    if (!deg || !tmp) { free(deg); free(tmp); mesh_free(m); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t t = 0; t < m->ntri; t++)
        for (size_t e = 0; e < 3; e++) deg[m->tri[3 * t + e]] += 2;
    m->nbr_ptr = calloc(npts + 1, sizeof *m->nbr_ptr);
    m->nbr = malloc(6 * m->ntri * sizeof *m->nbr);
    if (!m->nbr_ptr || !m->nbr) { free(deg); free(tmp); mesh_free(m); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    size_t *fill = calloc(npts, sizeof *fill);
    size_t *start = calloc(npts + 1, sizeof *start);
    if (!fill || !start) { free(deg); free(tmp); free(fill); free(start); mesh_free(m); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t i = 0; i < npts; i++) start[i + 1] = start[i] + deg[i];
    for (size_t t = 0; t < m->ntri; t++)
        for (size_t e = 0; e < 3; e++) {
            int a = m->tri[3 * t + e], b = m->tri[3 * t + (e + 1) % 3];
            tmp[start[a] + fill[a]++] = (size_t)b;
            tmp[start[b] + fill[b]++] = (size_t)a;
        }
    size_t n = 0;
    for (size_t i = 0; i < npts; i++) {
        m->nbr_ptr[i] = n;
        for (size_t k = start[i]; k < start[i] + fill[i]; k++) {
            int dup = 0;
            for (size_t j = m->nbr_ptr[i]; j < n; j++) if (m->nbr[j] == tmp[k]) { dup = 1; break; }
            if (!dup) m->nbr[n++] = tmp[k];
        }
    }
    m->nbr_ptr[npts] = n;
    free(deg); free(tmp); free(fill); free(start);
    return SWFS_OK;
}

/* Gradient weights at every vertex: grad f(v) = sum_k G[v][k] f(idx[v][k]). Local
 * least-squares quadratic through f(v): unknowns (gx, gy, a, b, c) of
 * f(u) - f(v) = gx dx + gy dy + a dx^2 + b dx dy + c dy^2, so exact for quadratics. */
typedef struct grad_ops {
    size_t *ptr;   /* npts + 1 */
    size_t *idx;   /* points used */
    double *gx, *gy;
} grad_ops;

static void grad_free(grad_ops *g) { free(g->ptr); free(g->idx); free(g->gx); free(g->gy); }

/* The points within `rings` Delaunay rings of v (v excluded) into set; mark is all 0 on
 * entry and exit. */
static size_t collect(const tri_mesh *m, size_t v, int rings, unsigned char *mark, size_t *set)
{
    size_t ns = 0, lo = 0;
    mark[v] = 1;
    for (size_t k = m->nbr_ptr[v]; k < m->nbr_ptr[v + 1]; k++)
        if (!mark[m->nbr[k]]) { mark[m->nbr[k]] = 1; set[ns++] = m->nbr[k]; }
    for (int r = 1; r < rings; r++) {
        const size_t hi = ns;
        for (size_t s = lo; s < hi; s++)
            for (size_t k = m->nbr_ptr[set[s]]; k < m->nbr_ptr[set[s] + 1]; k++)
                if (!mark[m->nbr[k]]) { mark[m->nbr[k]] = 1; set[ns++] = m->nbr[k]; }
        lo = hi;
    }
    mark[v] = 0;
    for (size_t s = 0; s < ns; s++) mark[set[s]] = 0;
    return ns;
}

/* Least squares of f(u) - f(v) on nterm terms (5: dx, dy, dx^2, dx dy, dy^2; 2: dx, dy) over
 * the ns points of set; the gradient rows go to g at `used` (ns + 1 entries, v last) when
 * the fit has full rank. *rank: the rank found. */
static int fit_gradient(const tri_mesh *m, size_t v, const size_t *set, size_t ns, int nterm, grad_ops *g,
                        size_t used, size_t *rank_out)
{
    const double *p0 = m->pts + 2 * v;
    double h = 0;
    for (size_t s = 0; s < ns; s++)
        h = fmax(h, hypot(m->pts[2 * set[s]] - p0[0], m->pts[2 * set[s] + 1] - p0[1]));
    const size_t nt = (size_t)nterm, rows = ns > nt ? ns : nt;
    double *A = calloc(rows * nt, sizeof *A), *B = calloc(rows * ns, sizeof *B), *sv = malloc(nt * sizeof *sv);
    if (!A || !B || !sv) { free(A); free(B); free(sv); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t s = 0; s < ns; s++) {
        const double dx = (m->pts[2 * set[s]] - p0[0]) / h, dy = (m->pts[2 * set[s] + 1] - p0[1]) / h;
        const double t[5] = {dx, dy, dx * dx, dx * dy, dy * dy};
        for (size_t c = 0; c < nt; c++) A[s * nt + c] = t[c];
        B[s * ns + s] = 1.0;
    }
    lapack_int rank = 0;
    lapack_int info = LAPACKE_dgelss(LAPACK_ROW_MAJOR, (lapack_int)ns, (lapack_int)nt, (lapack_int)ns, A,
                                     (lapack_int)nt, B, (lapack_int)ns, sv, 1e-10, &rank);
    *rank_out = info == 0 ? (size_t)rank : 0;
    if (*rank_out == nt) {
        /* B rows 0, 1 = pinv rows for gx, gy (in units of 1/h). */
        double sx = 0, sy = 0;
        for (size_t s = 0; s < ns; s++) {
            g->idx[used + s] = set[s];
            g->gx[used + s] = B[0 * ns + s] / h;
            g->gy[used + s] = B[1 * ns + s] / h;
            sx += g->gx[used + s];
            sy += g->gy[used + s];
        }
        g->idx[used + ns] = v; g->gx[used + ns] = -sx; g->gy[used + ns] = -sy;
        *rank_out = nterm == 2 ? 2 : 5;
    } else if (nterm == 2) {
        *rank_out = 0;
    }
    free(A); free(B); free(sv);
    return SWFS_OK;
}

static int gradients(const tri_mesh *m, grad_ops *g)
{
    size_t npts = m->npts;
    memset(g, 0, sizeof *g);
    size_t cap = 0;
    for (size_t v = 0; v < npts; v++) {
        size_t d = m->nbr_ptr[v + 1] - m->nbr_ptr[v];
        cap += 1 + d + d * 8 + (npts < 128 ? npts : 128); /* up to 4 rings (about 60 points on a lattice) */
    }
    g->ptr = calloc(npts + 1, sizeof *g->ptr);
    g->idx = malloc(cap * sizeof *g->idx);
    g->gx = malloc(cap * sizeof *g->gx);
    g->gy = malloc(cap * sizeof *g->gy);
    unsigned char *mark = calloc(npts, 1);
    size_t *set = malloc(npts * sizeof *set);
    if (!g->ptr || !g->idx || !g->gx || !g->gy || !mark || !set) {
        free(mark); free(set); grad_free(g);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    size_t used = 0;
    int rc = SWFS_OK;
    for (size_t v = 0; v < npts && rc == SWFS_OK; v++) {
        g->ptr[v] = used;
        /* The Delaunay ring, then wider rings until the points determine a quadratic: on a
         * square grid (a DM's actuators clipped to a circle) a vertex's neighbours can lie
         * on two lines, which leave the dx dy term undetermined. */
        size_t ns = 0, rank = 0;
        for (int rings = 1; rings <= 4 && rank < 5; rings++) {
            ns = collect(m, v, rings, mark, set);
            if ((rings == 1 && ns < 6) || ns < 5) continue; /* fewer than 6: the 2-ring, as always */
            if (used + ns + 1 > cap) { rc = swfs_fail(SWFS_ERR_INTERNAL, "gradient stencil overflow"); break; }
            if ((rc = fit_gradient(m, v, set, ns, 5, g, used, &rank))) break;
        }
        /* Still not (collinear stretches of a boundary): the gradient of a plane fit, exact
         * for linear functions, so the tip/tilt contract of speckles.h still holds. */
        if (!rc && rank < 5 && ns >= 2 && used + ns + 1 <= cap) rc = fit_gradient(m, v, set, ns, 2, g, used, &rank);
        if (rc) break;
        if (rank < 2) {
            rc = swfs_fail(SWFS_ERR_NUMERIC, "actuator %zu at (%g, %g) m: its neighbours are collinear, its gradient is "
                           "undetermined (a degenerate layout?)", v, m->pts[2 * v], m->pts[2 * v + 1]);
            break;
        }
        used += ns + 1;
    }
    g->ptr[npts] = used;
    free(mark); free(set);
    if (rc) grad_free(g);
    return rc;
}

/* Clough-Tocher value at (x, y) inside triangle P (ccw), from vertex values f and
 * gradients gr, via the cubic Bezier net on the three micro-triangles (P_i, P_i+1, C).
 * Bezier ordinates: vertex c_i = f_i; edge c_{i,j} = f_i + g_i.(P_j - P_i)/3; toward the
 * centroid d_i = f_i + g_i.(C - P_i)/3; edge-interior e_i from the linear-normal-derivative
 * condition on edge (P_i, P_i+1); one step from C: m_i = (d_i + e_{i-1} + e_i)/3;
 * centroid c = mean(m_i) -- the C1 conditions across the inner edges (Farin 1986). */
static double ct_eval(const double P[3][2], const double f[3], const double gr[3][2], double x, double y)
{
    double C[2] = {(P[0][0] + P[1][0] + P[2][0]) / 3, (P[0][1] + P[1][1] + P[2][1]) / 3};
    double cij[3][3]; /* cij[i][j]: ordinate next to vertex i toward vertex j */
    double d[3], e[3], mm[3];
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++)
            cij[i][j] = (i == j) ? f[i]
                                 : f[i] + (gr[i][0] * (P[j][0] - P[i][0]) + gr[i][1] * (P[j][1] - P[i][1])) / 3;
        d[i] = f[i] + (gr[i][0] * (C[0] - P[i][0]) + gr[i][1] * (C[1] - P[i][1])) / 3;
    }
    for (int i = 0; i < 3; i++) {
        int j = (i + 1) % 3;
        /* micro-triangle (P_i, P_j, C): b300 = f_i, b210 = cij[i][j], b120 = cij[j][i],
         * b030 = f_j, b201 = d_i, b021 = d_j, b111 = e_i. */
        double ex = P[j][0] - P[i][0], ey = P[j][1] - P[i][1];
        double e0 = 3 * (cij[i][j] - f[i]), e1 = 3 * (cij[j][i] - cij[i][j]), e2 = 3 * (f[j] - cij[j][i]);
        double q0 = 3 * (d[i] - f[i]), q2 = 3 * (d[j] - cij[j][i]);
        double ratio = ((C[0] - P[i][0]) * ex + (C[1] - P[i][1]) * ey) / (ex * ex + ey * ey);
        double q1 = 0.5 * (q0 + q2) + ratio * (e1 - 0.5 * (e0 + e2));
        e[i] = cij[i][j] + q1 / 3;
    }
    for (int i = 0; i < 3; i++) mm[i] = (d[i] + e[(i + 2) % 3] + e[i]) / 3;
    double cc = (mm[0] + mm[1] + mm[2]) / 3;

    /* Barycentrics in the macro triangle decide the micro-triangle: the one opposite
     * the vertex with the smallest weight. */
    double det = (P[1][0] - P[0][0]) * (P[2][1] - P[0][1]) - (P[2][0] - P[0][0]) * (P[1][1] - P[0][1]);
    double l1 = ((x - P[0][0]) * (P[2][1] - P[0][1]) - (P[2][0] - P[0][0]) * (y - P[0][1])) / det;
    double l2 = ((P[1][0] - P[0][0]) * (y - P[0][1]) - (x - P[0][0]) * (P[1][1] - P[0][1])) / det;
    double lam[3] = {1 - l1 - l2, l1, l2};
    int k = 0;
    if (lam[1] < lam[k]) k = 1;
    if (lam[2] < lam[k]) k = 2;
    int i = (k + 1) % 3, j = (k + 2) % 3; /* micro-triangle (P_i, P_j, C) */
    /* Barycentrics in (P_i, P_j, C): point = lam_i P_i + lam_j P_j + lam_k P_k with
     * P_k = 3C - P_i - P_j. */
    double u = lam[i] - lam[k], v = lam[j] - lam[k], w = 3 * lam[k];
    double b300 = f[i], b030 = f[j], b003 = cc;
    double b210 = cij[i][j], b120 = cij[j][i];
    double b201 = d[i], b021 = d[j], b111 = e[i];
    double b102 = mm[i], b012 = mm[j];
    return b300 * u * u * u + b030 * v * v * v + b003 * w * w * w + 3 * b210 * u * u * v + 3 * b120 * u * v * v +
           3 * b201 * u * u * w + 3 * b021 * v * v * w + 3 * b102 * u * w * w + 3 * b012 * v * w * w +
           6 * b111 * u * v * w;
}

int swfs_interp_ct_points(const double *pts, size_t npts, const double *qx, const double *qy, size_t nq,
                          swfs_sparse **out, size_t *n_outside)
{
    *out = NULL;
    if (n_outside) *n_outside = 0;
    for (size_t i = 0; i < 2 * npts; i++)
        if (!isfinite(pts[i])) return swfs_fail(SWFS_ERR_VALUE, "interpolation point %zu is not finite", i / 2);
    tri_mesh m;
    int rc = delaunay(pts, npts, &m);
    if (rc) return rc;
    grad_ops g;
    rc = gradients(&m, &g);
    if (rc) { mesh_free(&m); return rc; }

    /* Triangle bounding boxes for the point location. */
    double *bb = malloc(4 * m.ntri * sizeof *bb);
    size_t *tri_of = malloc((nq ? nq : 1) * sizeof *tri_of);
    double *wval = calloc(npts, sizeof *wval);
    size_t *wlist = malloc(npts * sizeof *wlist);
    unsigned char *inlist = calloc(npts, 1);
    if (!bb || !tri_of || !wval || !wlist || !inlist) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    double diam = 0;
    for (size_t t = 0; t < m.ntri; t++) {
        double *b = bb + 4 * t;
        b[0] = b[2] = pts[2 * m.tri[3 * t]];
        b[1] = b[3] = pts[2 * m.tri[3 * t] + 1];
        for (size_t k = 1; k < 3; k++) {
            double x = pts[2 * m.tri[3 * t + k]], y = pts[2 * m.tri[3 * t + k] + 1];
            b[0] = fmin(b[0], x); b[2] = fmax(b[2], x);
            b[1] = fmin(b[1], y); b[3] = fmax(b[3], y);
        }
        diam = fmax(diam, fmax(b[2] - b[0], b[3] - b[1]));
    }
    const double eps = 1e-10;
    size_t nnz = 0, outside = 0;
    for (size_t q = 0; q < nq; q++) {
        tri_of[q] = (size_t)-1;
        if (isnan(qx[q])) continue; /* masked out by the caller */
        double tol = eps * (diam > 0 ? diam : 1);
        for (size_t t = 0; t < m.ntri; t++) {
            const double *b = bb + 4 * t;
            if (qx[q] < b[0] - tol || qx[q] > b[2] + tol || qy[q] < b[1] - tol || qy[q] > b[3] + tol) continue;
            const double *a = pts + 2 * m.tri[3 * t], *bp = pts + 2 * m.tri[3 * t + 1], *c = pts + 2 * m.tri[3 * t + 2];
            double det = (bp[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (bp[1] - a[1]);
            double l1 = ((qx[q] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (qy[q] - a[1])) / det;
            double l2 = ((bp[0] - a[0]) * (qy[q] - a[1]) - (qx[q] - a[0]) * (bp[1] - a[1])) / det;
            if (l1 >= -eps && l2 >= -eps && 1 - l1 - l2 >= -eps) { tri_of[q] = t; break; }
        }
        if (tri_of[q] == (size_t)-1) { outside++; continue; }
        /* Upper bound of the row length: the 3 vertices' stencils. */
        for (size_t k = 0; k < 3; k++) {
            size_t v = (size_t)m.tri[3 * tri_of[q] + k];
            nnz += g.ptr[v + 1] - g.ptr[v] + 1;
        }
    }
    swfs_sparse *T = swfs_sparse_alloc(nq, npts, nnz);
    if (!T) { rc = SWFS_ERR_NOMEM; goto done; }
    size_t pos = 0;
    for (size_t q = 0; q < nq; q++) {
        T->row_ptr[q] = pos;
        size_t t = tri_of[q];
        if (t == (size_t)-1) continue;
        double P[3][2];
        for (size_t k = 0; k < 3; k++) { P[k][0] = pts[2 * m.tri[3 * t + k]]; P[k][1] = pts[2 * m.tri[3 * t + k] + 1]; }
        /* The element is linear in its 9 degrees of freedom: evaluate each unit one. */
        double wdof[9];
        for (int dof = 0; dof < 9; dof++) {
            double f[3] = {0, 0, 0}, gr[3][2] = {{0, 0}, {0, 0}, {0, 0}};
            if (dof < 3) f[dof] = 1;
            else gr[(dof - 3) / 2][(dof - 3) % 2] = 1;
            wdof[dof] = ct_eval((const double(*)[2])P, f, (const double(*)[2])gr, qx[q], qy[q]);
        }
        size_t nl = 0;
        for (size_t k = 0; k < 3; k++) {
            size_t v = (size_t)m.tri[3 * t + k];
            if (!inlist[v]) { inlist[v] = 1; wlist[nl++] = v; }
            wval[v] += wdof[k];
            for (size_t s = g.ptr[v]; s < g.ptr[v + 1]; s++) {
                size_t u = g.idx[s];
                if (!inlist[u]) { inlist[u] = 1; wlist[nl++] = u; }
                wval[u] += wdof[3 + 2 * k] * g.gx[s] + wdof[4 + 2 * k] * g.gy[s];
            }
        }
        for (size_t l = 0; l < nl; l++) {
            size_t u = wlist[l];
            T->col[pos] = u;
            T->val[pos] = wval[u];
            pos++;
            wval[u] = 0;
            inlist[u] = 0;
        }
    }
    T->row_ptr[nq] = pos;
    T->nnz = pos;
    *out = T;
    if (n_outside) *n_outside = outside;
done:
    free(bb); free(tri_of); free(wval); free(wlist); free(inlist);
    grad_free(&g);
    mesh_free(&m);
    return rc;
}

int swfs_interp_ct_grid(const double *pts, size_t npts, size_t npup, double pupdx, const double *mask,
                        swfs_sparse **out, size_t *n_outside)
{
    *out = NULL;
    if (npup == 0 || !(pupdx > 0)) return swfs_fail(SWFS_ERR_ARG, "pupil grid %zu x %g m is empty", npup, pupdx);
    size_t n = npup * npup;
    double *qx = malloc(n * sizeof *qx), *qy = malloc(n * sizeof *qy);
    if (!qx || !qy) { free(qx); free(qy); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    for (size_t q = 0; q < npup; q++)
        for (size_t p = 0; p < npup; p++) {
            size_t k = q * npup + p;
            if (mask && !(mask[k] > 0)) { qx[k] = NAN; qy[k] = NAN; continue; }
            qx[k] = ((double)p - 0.5 * (double)(npup - 1)) * pupdx;
            qy[k] = ((double)q - 0.5 * (double)(npup - 1)) * pupdx;
        }
    int rc = swfs_interp_ct_points(pts, npts, qx, qy, n, out, n_outside);
    free(qx); free(qy);
    return rc;
}

double swfs_points_pitch(const double *pts, size_t npts)
{
    if (npts < 2) return NAN;
    double *d = malloc(npts * sizeof *d);
    if (!d) return NAN;
    for (size_t a = 0; a < npts; a++) {
        double best = INFINITY;
        for (size_t b = 0; b < npts; b++)
            if (b != a) best = fmin(best, hypot(pts[2 * a] - pts[2 * b], pts[2 * a + 1] - pts[2 * b + 1]));
        d[a] = best;
    }
    const double m = swfs_median_inplace(d, npts);
    free(d);
    return m;
}

int swfs_interp_extend_rim(swfs_sparse **Tp, size_t npup, double pupdx, const double *mask, double reach,
                           size_t *n_extrap, size_t *n_far)
{
    swfs_sparse *T = *Tp;
    const size_t n = npup * npup;
    *n_extrap = *n_far = 0;
    if (T->nrows != n) return swfs_fail(SWFS_ERR_SHAPE, "rim extension: %zu rows for a %zux%zu grid", T->nrows, npup, npup);
    size_t *src = malloc(n * sizeof *src);
    if (!src) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    const long R = (long)ceil(reach / pupdx);
    size_t nnz = 0;
    for (size_t k = 0; k < n; k++) {
        src[k] = k;
        const int empty = T->row_ptr[k + 1] == T->row_ptr[k];
        if (!empty || !mask || !(mask[k] > 0)) { nnz += T->row_ptr[k + 1] - T->row_ptr[k]; continue; }
        /* the nearest sample with a row, within reach */
        const long p = (long)(k % npup), q = (long)(k / npup);
        double best = INFINITY;
        for (long dq = -R; dq <= R; dq++)
            for (long dp = -R; dp <= R; dp++) {
                const long pp = p + dp, qq = q + dq;
                if (pp < 0 || qq < 0 || pp >= (long)npup || qq >= (long)npup) continue;
                const size_t j = (size_t)qq * npup + (size_t)pp;
                const double d = hypot((double)dp, (double)dq) * pupdx;
                if (T->row_ptr[j + 1] > T->row_ptr[j] && d <= reach && d < best) { best = d; src[k] = j; }
            }
        if (src[k] == k) (*n_far)++;
        else { (*n_extrap)++; nnz += T->row_ptr[src[k] + 1] - T->row_ptr[src[k]]; }
    }
    if (!*n_extrap) { free(src); return SWFS_OK; }
    swfs_sparse *E = swfs_sparse_alloc(T->nrows, T->ncols, nnz);
    if (!E) { free(src); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    size_t w = 0;
    for (size_t k = 0; k < n; k++) {
        E->row_ptr[k] = w;
        for (size_t e = T->row_ptr[src[k]]; e < T->row_ptr[src[k] + 1]; e++, w++) {
            E->col[w] = T->col[e];
            E->val[w] = T->val[e];
        }
    }
    E->row_ptr[n] = w;
    free(src);
    swfs_sparse_free(T);
    *Tp = E;
    return SWFS_OK;
}

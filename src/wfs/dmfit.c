/* Deformable-mirror offsets: least-squares fit of a surface onto actuator influence
 * functions, optionally through a Zernike modal filter. See include/specklewfs/dmfit.h. */
#include "specklewfs/dmfit.h"
#include "specklewfs/aperture.h"
#include "specklewfs/array.h"
#include "specklewfs/interp.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

struct swfs_dmfit {
    swfs_dmfit_options opt;
    size_t nact, npup, npix, nactive;
    double pitch;
    double *xy;      /* 2 nact */
    double *mask;    /* npup^2 */
    size_t *pix;     /* npix indices of the samples inside the pupil */
    swfs_sparse *A;  /* npup^2 x nact influence (empty rows outside the pupil) */
    double *pinv;    /* nact x nact: (A^T W A + mu)^+ */
    double *Z;       /* npix x K Zernike values (K = opt.modes), row-major */
    double *zpinv;   /* K x K: (Z^T W Z)^+ */
    unsigned char *active; /* nact: 1 when the influence reaches the pupil */
    /* work space */
    double *b, *a, *proj, *modal, *surf; /* nact, K, K, npup^2, npup^2 */
    double *pv;                          /* npix (with the modal filter) */
};

void swfs_dmfit_options_default(swfs_dmfit_options *o)
{
    o->influence = SWFS_INFLUENCE_GAUSS;
    o->coupling = 0.2;
    o->pitch = 0.0;
    o->modes = 0;
    o->reg = 1e-3;
    o->rcond = 1e-9;
    o->rim = 0;
}

void swfs_dmfit_free(swfs_dmfit *f)
{
    if (!f) return;
    free(f->xy);
    free(f->mask);
    free(f->pix);
    swfs_sparse_free(f->A);
    free(f->pinv);
    free(f->Z);
    free(f->zpinv);
    free(f->b);
    free(f->a);
    free(f->proj);
    free(f->pv);
    free(f->active);
    free(f->modal);
    free(f->surf);
    free(f);
}

size_t swfs_dmfit_npup(const swfs_dmfit *f) { return f->npup; }
const double *swfs_dmfit_xy(const swfs_dmfit *f) { return f->xy; }
size_t swfs_dmfit_nact(const swfs_dmfit *f) { return f->nact; }
double swfs_dmfit_pitch(const swfs_dmfit *f) { return f->pitch; }
size_t swfs_dmfit_active(const swfs_dmfit *f) { return f->nactive; }
size_t swfs_dmfit_npix(const swfs_dmfit *f) { return f->npix; }
const size_t *swfs_dmfit_pix(const swfs_dmfit *f) { return f->pix; }
const swfs_sparse *swfs_dmfit_influence(const swfs_dmfit *f) { return f->A; }
const double *swfs_dmfit_mask(const swfs_dmfit *f) { return f->mask; }
const swfs_dmfit_options *swfs_dmfit_opts(const swfs_dmfit *f) { return &f->opt; }

/* Gaussian influence matrix: f_a(x) = coupling^(r^2/pitch^2), cut below 1e-5. */
static int gauss_influence(swfs_dmfit *f, double pupdx, swfs_sparse **out)
{
    const size_t np = f->npup, nact = f->nact;
    const double c = 0.5 * (double)(np - 1), lnc = log(f->opt.coupling);
    const double rmax2 = f->pitch * f->pitch * log(1e-5) / lnc;
    size_t nnz = 0;
    for (size_t k = 0; k < f->npix; k++) {
        const size_t s = f->pix[k];
        const double x = ((double)(s % np) - c) * pupdx, y = ((double)(s / np) - c) * pupdx;
        for (size_t a = 0; a < nact; a++) {
            const double dx = x - f->xy[2 * a], dy = y - f->xy[2 * a + 1];
            if (dx * dx + dy * dy < rmax2) nnz++;
        }
    }
    swfs_sparse *A = swfs_sparse_alloc(np * np, nact, nnz ? nnz : 1);
    if (!A) return swfs_fail(SWFS_ERR_NOMEM, "DM fit: out of memory for %zu influence values", nnz);
    size_t e = 0, k = 0;
    const double inv_p2 = 1.0 / (f->pitch * f->pitch);
    for (size_t s = 0; s < np * np; s++) {
        A->row_ptr[s] = e;
        if (k < f->npix && f->pix[k] == s) {
            const double x = ((double)(s % np) - c) * pupdx, y = ((double)(s / np) - c) * pupdx;
            for (size_t a = 0; a < nact; a++) {
                const double dx = x - f->xy[2 * a], dy = y - f->xy[2 * a + 1], r2 = dx * dx + dy * dy;
                if (r2 < rmax2) {
                    A->col[e] = a;
                    A->val[e] = exp(lnc * r2 * inv_p2);
                    e++;
                }
            }
            k++;
        }
    }
    A->row_ptr[np * np] = e;
    A->nnz = e;
    *out = A;
    return SWFS_OK;
}

/* P = (G + mu)^+ of a symmetric n x n matrix (overwritten), eigenvalues below rcond * max
 * dropped. */
static int sym_pinv(double *G, size_t n, double mu, double rcond, double **P)
{
    double *w = malloc(n * sizeof *w), *vd = malloc(n * n * sizeof *vd);
    *P = malloc(n * n * sizeof **P);
    if (!w || !vd || !*P) {
        free(w); free(vd); free(*P); *P = NULL;
        return swfs_fail(SWFS_ERR_NOMEM, "DM fit: out of memory for a %zux%zu matrix", n, n);
    }
    lapack_int info = LAPACKE_dsyevd(LAPACK_ROW_MAJOR, 'V', 'U', (lapack_int)n, G, (lapack_int)n, w);
    if (info != 0) {
        free(w); free(vd); free(*P); *P = NULL;
        return swfs_fail(SWFS_ERR_NUMERIC, "DM fit: eigen-decomposition failed (LAPACK info %d)", (int)info);
    }
    const double wmax = w[n - 1]; /* ascending */
    for (size_t j = 0; j < n; j++) {
        const double d = w[j] > rcond * wmax && w[j] > 0 ? 1.0 / (w[j] + mu) : 0.0;
        for (size_t i = 0; i < n; i++) vd[i * n + j] = G[i * n + j] * d;
    }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)n, (int)n, (int)n, 1.0, vd, (int)n, G, (int)n, 0.0, *P,
                (int)n);
    free(w);
    free(vd);
    return SWFS_OK;
}

int swfs_dmfit_create(swfs_dmfit **out, const double *xy, size_t nact, const swfs_geom *g, const double *mask,
                      const swfs_dmfit_options *opt)
{
    *out = NULL;
    swfs_dmfit_options o;
    swfs_dmfit_options_default(&o);
    if (opt) o = *opt;
    if (!(g->pupn > 1) || !(g->pupdx > 0) || !(g->teldiam > 0))
        return swfs_fail(SWFS_ERR_FORMAT, "DM fit: the pupil geometry needs PUPN, PUPDX and TELDIAM");
    if (nact < 3) return swfs_fail(SWFS_ERR_ARG, "DM fit: %zu actuators (at least 3 needed)", nact);
    if (o.influence != SWFS_INFLUENCE_GAUSS && o.influence != SWFS_INFLUENCE_CUBIC)
        return swfs_fail(SWFS_ERR_ARG, "DM fit: unknown influence function %d", o.influence);
    if (o.influence == SWFS_INFLUENCE_GAUSS && !(o.coupling > 0 && o.coupling < 1))
        return swfs_fail(SWFS_ERR_ARG, "DM fit: coupling must be in (0, 1), got %g", o.coupling);
    if (!(o.reg >= 0) || !(o.rcond >= 0) || !isfinite(o.pitch))
        return swfs_fail(SWFS_ERR_ARG, "DM fit: regularization and rcond must be >= 0, pitch finite");
    for (size_t a = 0; a < 2 * nact; a++)
        if (!isfinite(xy[a])) return swfs_fail(SWFS_ERR_VALUE, "DM fit: actuator %zu has a non-finite position", a / 2);

    const size_t np = (size_t)g->pupn, n2 = np * np;
    swfs_dmfit *f = calloc(1, sizeof *f);
    if (!f) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    f->opt = o;
    f->nact = nact;
    f->npup = np;
    int rc = SWFS_OK;
    swfs_sparse *T = NULL;
    double *G = NULL;
    f->xy = malloc(2 * nact * sizeof *f->xy);
    f->mask = malloc(n2 * sizeof *f->mask);
    f->pix = malloc(n2 * sizeof *f->pix);
    f->b = calloc(nact, sizeof *f->b);
    f->active = calloc(nact, 1);
    f->modal = calloc(n2, sizeof *f->modal);
    f->surf = calloc(n2, sizeof *f->surf);
    if (!f->xy || !f->mask || !f->pix || !f->b || !f->active || !f->modal || !f->surf) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    memcpy(f->xy, xy, 2 * nact * sizeof *xy);
    if (mask) {
        memcpy(f->mask, mask, n2 * sizeof *mask);
    } else {
        if (!isfinite(g->obscur)) { rc = swfs_fail(SWFS_ERR_FORMAT, "DM fit: no pupil mask and no OBSCUR keyword"); goto done; }
        if ((rc = swfs_aperture_make(f->mask, np, g->pupdx, g->teldiam, g->obscur, 0, 0.0))) goto done;
    }
    for (size_t s = 0; s < n2; s++) {
        if (!isfinite(f->mask[s]) || f->mask[s] < 0) f->mask[s] = 0.0;
        if (f->mask[s] > 0) f->pix[f->npix++] = s;
    }
    if (f->npix == 0) { rc = swfs_fail(SWFS_ERR_VALUE, "DM fit: the pupil mask is empty"); goto done; }

    /* Coverage: the pupil inside the actuators' convex hull (the Clough-Tocher operator
     * finds the samples outside it). */
    size_t nout = 0;
    if ((rc = swfs_interp_ct_grid(xy, nact, np, g->pupdx, f->mask, &T, &nout))) {
        rc = swfs_fail_context(rc, "DM fit: actuator triangulation");
        goto done;
    }
    const double spacing = swfs_points_pitch(xy, nact); /* the actuators' median nearest-neighbour distance */
    size_t nfar = nout;
    if (nout > 0 && o.rim) {
        size_t next = 0;
        if ((rc = swfs_interp_extend_rim(&T, np, g->pupdx, f->mask, spacing, &next, &nfar))) goto done;
    }
    if (nfar > 0) {
        double rmax = 0.0, pr = 0.0;
        const double c = 0.5 * (double)(np - 1);
        for (size_t a = 0; a < nact; a++) rmax = fmax(rmax, hypot(xy[2 * a], xy[2 * a + 1]));
        for (size_t k = 0; k < f->npix; k++)
            pr = fmax(pr, hypot(((double)(f->pix[k] % np) - c) * g->pupdx, ((double)(f->pix[k] / np) - c) * g->pupdx));
        rc = swfs_fail(SWFS_ERR_VALUE,
                       "the actuators do not cover the pupil: %zu of %zu pupil samples lie outside their convex hull%s "
                       "(actuators reach r = %.3g m from the centre, the pupil reaches %.3g m)",
                       nfar, f->npix, o.rim ? " by more than one actuator pitch" : "", rmax, pr);
        goto done;
    }
    f->pitch = o.pitch > 0 ? o.pitch : spacing;
    if (!(f->pitch > 0)) { rc = swfs_fail(SWFS_ERR_VALUE, "DM fit: actuators coincide (pitch %g m)", f->pitch); goto done; }
    if (o.influence == SWFS_INFLUENCE_CUBIC) {
        f->A = T;
        T = NULL;
    } else if ((rc = gauss_influence(f, g->pupdx, &f->A))) {
        goto done;
    }

    /* Normal equations G = A^T W A. */
    G = calloc(nact * nact, sizeof *G);
    if (!G) { rc = swfs_fail(SWFS_ERR_NOMEM, "DM fit: out of memory for %zu actuators", nact); goto done; }
    const swfs_sparse *A = f->A;
    for (size_t k = 0; k < f->npix; k++) {
        const size_t s = f->pix[k];
        const double w = f->mask[s];
        for (size_t e = A->row_ptr[s]; e < A->row_ptr[s + 1]; e++) {
            const double v = w * A->val[e];
            double *row = G + A->col[e] * nact;
            for (size_t e2 = A->row_ptr[s]; e2 < A->row_ptr[s + 1]; e2++) row[A->col[e2]] += v * A->val[e2];
        }
    }
    double tr = 0.0;
    for (size_t a = 0; a < nact; a++) {
        tr += G[a * nact + a];
        if (G[a * nact + a] > 0) {
            f->active[a] = 1;
            f->nactive++;
        }
    }
    if (f->nactive == 0) { rc = swfs_fail(SWFS_ERR_VALUE, "DM fit: no actuator influences the pupil"); goto done; }
    if ((rc = sym_pinv(G, nact, o.reg * tr / (double)f->nactive, o.rcond, &f->pinv))) goto done;

    /* Zernike modal filter. */
    if (o.modes > 0) {
        const size_t K = o.modes;
        const double c = 0.5 * (double)(np - 1), rad = 0.5 * g->teldiam;
        f->Z = malloc(f->npix * K * sizeof *f->Z);
        f->a = calloc(K, sizeof *f->a);
        f->proj = calloc(K, sizeof *f->proj);
        f->pv = calloc(f->npix, sizeof *f->pv);
        double *zg = calloc(K * K, sizeof *zg);
        if (!f->Z || !f->a || !f->proj || !f->pv || !zg) { free(zg); rc = swfs_fail(SWFS_ERR_NOMEM, "DM fit: out of memory for %zu modes", K); goto done; }
        for (size_t j = 0; j < K; j++) {
            int zn, zm;
            if ((rc = swfs_zernike_noll((int)j + 1, &zn, &zm))) { free(zg); goto done; }
            for (size_t k = 0; k < f->npix; k++) {
                const size_t s = f->pix[k];
                const double x = ((double)(s % np) - c) * g->pupdx, y = ((double)(s / np) - c) * g->pupdx;
                f->Z[k * K + j] = swfs_zernike(zn, zm, hypot(x, y) / rad, atan2(y, x));
            }
        }
        for (size_t k = 0; k < f->npix; k++) {
            const double w = f->mask[f->pix[k]];
            const double *z = f->Z + k * K;
            for (size_t i = 0; i < K; i++)
                for (size_t j = 0; j < K; j++) zg[i * K + j] += w * z[i] * z[j];
        }
        rc = sym_pinv(zg, K, 0.0, 1e-12, &f->zpinv);
        free(zg);
        if (rc) goto done;
    }

done:
    swfs_sparse_free(T);
    free(G);
    if (rc) {
        swfs_dmfit_free(f);
        return rc;
    }
    *out = f;
    return SWFS_OK;
}

void swfs_dmfit_surface(const swfs_dmfit *f, const double *cmd, double *surface)
{
    /* on the pupil's samples only (pix: mask > 0), 0 elsewhere */
    memset(surface, 0, f->npup * f->npup * sizeof *surface);
    swfs_sparse_apply_rows(f->A, cmd, f->pix, f->npix, surface);
}

/* Mask-weighted rms with the weighted mean removed, over the plan's pupil samples of
 * u - v (v may be NULL). */
static double rms_diff(const swfs_dmfit *f, const double *u, const double *v)
{
    double s = 0.0, s1 = 0.0, s2 = 0.0;
    for (size_t k = 0; k < f->npix; k++) {
        const size_t p = f->pix[k];
        const double w = f->mask[p], d = u[p] - (v ? v[p] : 0.0);
        s += w;
        s1 += w * d;
        s2 += w * d * d;
    }
    const double m = s1 / s, var = s2 / s - m * m;
    return var > 0 ? sqrt(var) : 0.0;
}

/* b = A^T W t over the pupil's samples (nact values). */
static void rhs_of(const swfs_dmfit *f, const double *t, double *b)
{
    const swfs_sparse *A = f->A;
    memset(b, 0, f->nact * sizeof *b);
    for (size_t k = 0; k < f->npix; k++) {
        const size_t s = f->pix[k];
        const double wt = f->mask[s] * t[s];
        for (size_t e = A->row_ptr[s]; e < A->row_ptr[s + 1]; e++) b[A->col[e]] += wt * A->val[e];
    }
}

/* The target finite on the pupil's samples. */
static int check_target(const swfs_dmfit *f, const double *target)
{
    for (size_t k = 0; k < f->npix; k++)
        if (!isfinite(target[f->pix[k]]))
            return swfs_fail(SWFS_ERR_VALUE, "DM fit: the target surface is not finite at pupil sample %zu", f->pix[k]);
    return SWFS_OK;
}

int swfs_dmfit_rhs(const swfs_dmfit *f, const double *target, double *b)
{
    if (f->opt.modes > 0)
        return swfs_fail(SWFS_ERR_ARG, "DM fit: the two-step fit takes a plan without a modal restriction (modes %zu)",
                         f->opt.modes);
    const int rc = check_target(f, target);
    if (!rc) rhs_of(f, target, b);
    return rc;
}

int swfs_dmfit_rhs_many(const swfs_dmfit *f, const double *R, size_t ld, size_t n, double *bt)
{
    if (f->opt.modes > 0)
        return swfs_fail(SWFS_ERR_ARG, "DM fit: the two-step fit takes a plan without a modal restriction (modes %zu)",
                         f->opt.modes);
    if (n > ld) return swfs_fail(SWFS_ERR_ARG, "DM fit: %zu targets in rows of %zu", n, ld);
    for (size_t k = 0; k < f->npix; k++)
        for (size_t j = 0; j < n; j++)
            if (!isfinite(R[k * ld + j]))
                return swfs_fail(SWFS_ERR_VALUE, "DM fit: target %zu of %zu is not finite at pupil sample %zu", j, n,
                                 f->pix[k]);
    const swfs_sparse *A = f->A;
    memset(bt, 0, f->nact * n * sizeof *bt);
    for (size_t k = 0; k < f->npix; k++) {
        const size_t s = f->pix[k];
        const double w = f->mask[s], *r = R + k * ld;
        for (size_t e = A->row_ptr[s]; e < A->row_ptr[s + 1]; e++) {
            double *o = bt + A->col[e] * n;
            const double v = A->val[e];
            for (size_t j = 0; j < n; j++) o[j] += (w * r[j]) * v; /* rhs_of's (mask t) val, per target */
        }
    }
    return SWFS_OK;
}

int swfs_dmfit_rhs_matrix(const swfs_dmfit *f, const swfs_sparse *T, double **G)
{
    *G = NULL;
    if (f->opt.modes > 0)
        return swfs_fail(SWFS_ERR_ARG, "DM fit: the two-step fit takes a plan without a modal restriction (modes %zu)",
                         f->opt.modes);
    if (T->nrows != f->npup * f->npup)
        return swfs_fail(SWFS_ERR_SHAPE, "DM fit: surfaces of %zu samples, the plan's pupil has %zu", T->nrows,
                         f->npup * f->npup);
    const size_t nc = T->ncols;
    double *g = calloc(f->nact * (nc ? nc : 1), sizeof *g);
    if (!g) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    const swfs_sparse *A = f->A;
    for (size_t k = 0; k < f->npix; k++) {
        const size_t s = f->pix[k];
        const double w = f->mask[s];
        for (size_t e = A->row_ptr[s]; e < A->row_ptr[s + 1]; e++) {
            double *ga = g + A->col[e] * nc;
            const double v = w * A->val[e];
            for (size_t q = T->row_ptr[s]; q < T->row_ptr[s + 1]; q++) ga[T->col[q]] += v * T->val[q];
        }
    }
    *G = g;
    return SWFS_OK;
}

void swfs_dmfit_solve_many(const swfs_dmfit *f, const double *b, size_t n, double *cmd)
{
    const int na = (int)f->nact;
    if (n) cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)n, na, na, 1.0, b, na, f->pinv, na, 0.0, cmd, na);
}

int swfs_dmfit_apply(swfs_dmfit *f, const double *target, double *cmd, double *fitted, swfs_dmfit_stats *st)
{
    const size_t nact = f->nact, K = f->opt.modes;
    const int crc = check_target(f, target);
    if (crc) return crc;
    /* Modal projection (least squares over the pupil). */
    const double *t = target;
    if (K > 0) {
        /* proj = Z^T W t, a = (Z^T W Z)^+ proj, modal = Z a on the pupil's samples */
        const int np = (int)f->npix, k2 = (int)K;
        for (size_t k = 0; k < f->npix; k++) f->pv[k] = f->mask[f->pix[k]] * target[f->pix[k]];
        cblas_dgemv(CblasRowMajor, CblasTrans, np, k2, 1.0, f->Z, k2, f->pv, 1, 0.0, f->proj, 1);
        cblas_dgemv(CblasRowMajor, CblasNoTrans, k2, k2, 1.0, f->zpinv, k2, f->proj, 1, 0.0, f->a, 1);
        cblas_dgemv(CblasRowMajor, CblasNoTrans, np, k2, 1.0, f->Z, k2, f->a, 1, 0.0, f->pv, 1);
        memset(f->modal, 0, f->npup * f->npup * sizeof *f->modal);
        for (size_t k = 0; k < f->npix; k++) f->modal[f->pix[k]] = f->pv[k];
        t = f->modal;
    }
    /* b = A^T W t, cmd = P b. */
    rhs_of(f, t, f->b);
    cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nact, (int)nact, 1.0, f->pinv, (int)nact, f->b, 1, 0.0, cmd, 1);
    if (fitted || st) {
        double *surf = fitted ? fitted : f->surf;
        swfs_dmfit_surface(f, cmd, surf);
        if (st) {
            st->target_rms = rms_diff(f, target, NULL);
            st->modal_rms = rms_diff(f, t, NULL);
            st->filtered_rms = K > 0 ? rms_diff(f, target, t) : 0.0;
            st->fit_rms = rms_diff(f, surf, NULL);
            st->fiterr_rms = rms_diff(f, t, surf);
            st->unfit_rms = rms_diff(f, target, surf);
            double s2 = 0.0, lo = INFINITY, hi = -INFINITY;
            size_t n = 0;
            for (size_t a = 0; a < nact; a++) {
                if (!f->active[a]) continue;
                s2 += cmd[a] * cmd[a];
                lo = fmin(lo, cmd[a]);
                hi = fmax(hi, cmd[a]);
                n++;
            }
            st->cmd_rms = n ? sqrt(s2 / (double)n) : 0.0;
            st->cmd_min = n ? lo : 0.0;
            st->cmd_max = n ? hi : 0.0;
        }
    }
    return SWFS_OK;
}

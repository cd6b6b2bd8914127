/* The loop's controlled modes as residual slopes show them (timeseries.h): the slopes'
 * variance along the DM modes' slope patterns, and the profile's knee. `teach` uses it to
 * give its loops the observation's modal filter when the system's description has none. */
#include "specklewfs/status.h"
#include "specklewfs/interp.h"
#include "specklewfs/pyramid.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wfs.h"
#include "sim_internal.h"

#include <cblas.h>
#include <float.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

int swfs_ts_dm_layout(const swfs_ts_params *p, double **xy, size_t *nact)
{
    const double D = p->base.teldiam, dx = p->base.pupdx;
    return p->act_square ? swfs_actuators_square(D, p->act_pitch, dx, xy, nact)
                         : swfs_actuators_hexapolar(D, p->act_pitch, dx, xy, nact);
}

int swfs_ts_loop_model(const swfs_ts_params *p, const double *mask, const unsigned char *vmap, double **xy,
                       size_t *nact, swfs_sparse **T, swfs_shwfs **sh)
{
    const swfs_sim_params *b = &p->base;
    const size_t np = (size_t)b->pupn;
    const double D = b->teldiam, dx = b->pupdx;
    *T = NULL;
    *sh = NULL;
    int rc = *xy ? SWFS_OK : swfs_ts_dm_layout(p, xy, nact);
    if (!rc) rc = p->dm_coupling > 0 ? swfs_influence_gauss_grid(*xy, *nact, np, dx, mask, p->dm_coupling, T)
                                     : swfs_interp_ct_grid(*xy, *nact, np, dx, mask, T, NULL);
    if (!rc && (rc = vmap ? swfs_shwfs_create_valid(sh, (size_t)p->nsub, D, mask, np, dx, vmap)
                          : swfs_shwfs_create(sh, (size_t)p->nsub, D, mask, np, dx, 0.5)))
        if (vmap) swfs_fail_context(rc, "%s", p->valid);
    if (rc) {
        swfs_sparse_free(*T);
        *T = NULL;
    }
    return rc;
}

/* The DM modes after piston through the system's interaction matrix, orthonormalized in
 * their order (QR), as rows of the slopes given (ns: the full layout 2 nsub^2, or the used
 * subapertures' 2 nvalid): *A (ns x *m, malloc'd), *dep (m flags, malloc'd: 1 where the
 * mode's pattern has no direction of its own). */
static int mode_basis(const swfs_ts_params *p, size_t ns, const char *what, double **Aout, size_t *mout,
                      unsigned char **dep)
{
    *Aout = NULL;
    *dep = NULL;
    *mout = 0;
    const size_t np = (size_t)p->base.pupn;
    double *mask = malloc(np * np * sizeof *mask), *xy = NULL, *Dm = NULL, *modes = NULL, *A = NULL, *tau = NULL;
    double *cn = NULL;
    swfs_sparse *T = NULL;
    swfs_shwfs *sh = NULL;
    swfs_recon *rao = NULL;
    unsigned char *vmap = NULL, *flag = NULL;
    size_t nact = 0;
    int rc = mask ? swfs_sim_pupil(&p->base, mask) : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = swfs_ts_read_given(p, p->base.teldiam, &xy, &nact, &rao, &vmap);
    if (!rc) rc = swfs_ts_loop_model(p, mask, vmap, &xy, &nact, &T, &sh);
    if (!rc && p->wfs_pyramid) {
        /* a pyramid's signals: its interaction matrix as the loop's own (push-pull of each
         * actuator by a hundredth of the sensing wavelength, on the Shack-Hartmann's layout) */
        const double lw = p->wfs_wavelen > 0 ? p->wfs_wavelen : p->base.wavelen;
        swfs_pyramid *pyr = NULL;
        rc = swfs_pyramid_create(&pyr, (size_t)p->nsub, p->base.teldiam, mask, np, p->base.pupdx, sh->valid, lw,
                                 p->pyr_mod, (size_t)p->pyr_nmod);
        if (!rc) rc = swfs_pyramid_interaction(pyr, T, lw / 100, &Dm);
        swfs_pyramid_free(pyr);
    } else if (!rc) {
        rc = swfs_interaction_matrix(sh, T, &Dm);
    }
    if (!rc) rc = swfs_dm_modes(T, mask, np, &modes);
    if (rc) goto done;
    /* The modes after piston through D (2 nsub^2 x m, the full layout), orthonormalized in
     * their order (QR): column j is the part of mode j's slope pattern that the lower modes
     * do not explain. */
    const size_t nfull = sh->nslopes, nsa = nfull / 2, m0 = nact - 1, m = m0 < nfull ? m0 : nfull;
    if (ns != nfull && ns != 2 * sh->nvalid) {
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu slopes per frame, but the system's %ld x %ld Shack-Hartmann "
                       "has 2 nsub^2 = %zu (the full layout, unused subapertures 0) or 2 x %zu (its used "
                       "subapertures')", what, ns, p->nsub, p->nsub, nfull, sh->nvalid);
        goto done;
    }
    A = malloc(nfull * m * sizeof *A);
    tau = malloc(m * sizeof *tau);
    cn = calloc(m, sizeof *cn);
    flag = calloc(m, 1);
    if (!A || !tau || !cn || !flag) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nfull, (int)m, (int)nact, 1.0, Dm, (int)nact, modes + 1,
                (int)nact, 0.0, A, (int)m);
    for (size_t r = 0; r < nfull; r++)
        for (size_t j = 0; j < m; j++) cn[j] += A[r * m + j] * A[r * m + j];
    lapack_int info = LAPACKE_dgeqrf(LAPACK_ROW_MAJOR, (lapack_int)nfull, (lapack_int)m, A, (lapack_int)m, tau);
    /* A mode whose pattern the lower ones' explain to working precision (|R_jj| at most
     * sqrt(eps) of its norm; more modes than the used subapertures' slopes, or patterns a
     * valid map leaves dependent) has no direction of its own: NaN, not the variance along
     * the arbitrary column QR completes it with. Measured: such columns at 1e-13 or less,
     * every other at 6e-4 or more (docs/telemetry.md). */
    for (size_t j = 0; j < m; j++) flag[j] = fabs(A[j * m + j]) <= sqrt(DBL_EPSILON) * sqrt(cn[j]);
    if (!info) info = LAPACKE_dorgqr(LAPACK_ROW_MAJOR, (lapack_int)nfull, (lapack_int)m, (lapack_int)m, A, (lapack_int)m, tau);
    if (info) { rc = swfs_fail(SWFS_ERR_NUMERIC, "%s: QR of the modes' slope patterns failed (%d)", what, (int)info); goto done; }
    /* Slopes of the used subapertures only: the basis's rows of those slopes (x then y,
     * row-major), moved up in place. The same as the full layout with the unused
     * subapertures' slopes 0, which meet only the rows dropped here. */
    if (ns != nfull)
        for (size_t r = 0, k = 0; r < nfull; r++)
            if (sh->valid[r % nsa] && k++ != r) memcpy(A + (k - 1) * m, A + r * m, m * sizeof *A);
    *Aout = A;
    *dep = flag;
    *mout = m;
    A = NULL;
    flag = NULL;
done:
    free(mask); free(xy); free(Dm); free(modes); free(A); free(tau); free(cn); free(flag);
    free(vmap);
    swfs_sparse_free(T);
    swfs_shwfs_free(sh);
    swfs_recon_free(rao);
    return rc;
}

/* Each slope's time mean (ns values, malloc'd). */
static double *slope_means(const double *slopes, size_t nframes, size_t ns)
{
    double *mean = calloc(ns, sizeof *mean);
    if (!mean) return NULL;
    for (size_t t = 0; t < nframes; t++)
        for (size_t i = 0; i < ns; i++) mean[i] += slopes[t * ns + i];
    for (size_t i = 0; i < ns; i++) mean[i] /= (double)nframes;
    return mean;
}

#define MODE_BLOCK 256 /* frames per GEMM */

/* The coefficients along the basis of frames t0 .. t0 + nb (nb <= MODE_BLOCK), each slope's
 * time mean removed: q (nb x m); blk, MODE_BLOCK x ns of scratch. */
static void mode_block(const double *slopes, const double *mean, size_t t0, size_t nb, size_t ns, const double *A,
                       size_t m, double *blk, double *q)
{
    for (size_t t = 0; t < nb; t++)
        for (size_t i = 0; i < ns; i++) blk[t * ns + i] = slopes[(t0 + t) * ns + i] - mean[i];
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nb, (int)m, (int)ns, 1.0, blk, (int)ns, A, (int)m, 0.0, q,
                (int)m);
}

int swfs_ts_mode_variance(const swfs_ts_params *p, const double *slopes, size_t nframes, size_t nslopes,
                          double **var, size_t *nmodes)
{
    *var = NULL;
    *nmodes = 0;
    if (nframes < 2) return swfs_fail(SWFS_ERR_ARG, "mode variance: %zu frames (at least 2)", nframes);
    double *A = NULL, *mean = NULL, *blk = NULL, *q = NULL, *v = NULL;
    unsigned char *dep = NULL;
    size_t m = 0;
    int rc = mode_basis(p, nslopes, "mode variance", &A, &m, &dep);
    if (!rc && (!(mean = slope_means(slopes, nframes, nslopes)) || !(blk = malloc(MODE_BLOCK * nslopes * sizeof *blk)) ||
                !(q = malloc(MODE_BLOCK * m * sizeof *q)) || !(v = calloc(m, sizeof *v))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t t0 = 0; !rc && t0 < nframes; t0 += MODE_BLOCK) {
        const size_t nb = nframes - t0 < MODE_BLOCK ? nframes - t0 : MODE_BLOCK;
        mode_block(slopes, mean, t0, nb, nslopes, A, m, blk, q);
        for (size_t t = 0; t < nb; t++)
            for (size_t j = 0; j < m; j++) v[j] += q[t * m + j] * q[t * m + j];
    }
    if (!rc) {
        for (size_t j = 0; j < m; j++) v[j] = dep[j] ? NAN : v[j] / (double)(nframes - 1);
        *var = v;
        *nmodes = m;
        v = NULL;
    }
    free(A); free(mean); free(blk); free(q); free(v); free(dep);
    return rc;
}

int swfs_ts_mode_timecorr(const swfs_ts_params *p, const double *slopes, size_t nframes, size_t nslopes,
                          const long *lags, size_t nlags, double *rho)
{
    for (size_t k = 0; k < nlags; k++)
        if (lags[k] < 1 || (size_t)lags[k] >= nframes)
            return swfs_fail(SWFS_ERR_ARG, "mode time correlation: lag %ld of %zu frames (1 to frames - 1)", lags[k],
                             nframes);
    double *A = NULL, *q = NULL;
    unsigned char *dep = NULL;
    size_t m = 0;
    double *mean = NULL, *blk = NULL;
    int rc = mode_basis(p, nslopes, "mode time correlation", &A, &m, &dep);
    if (!rc && (!(mean = slope_means(slopes, nframes, nslopes)) || !(blk = malloc(MODE_BLOCK * nslopes * sizeof *blk)) ||
                !(q = malloc(nframes * m * sizeof *q))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t t0 = 0; !rc && t0 < nframes; t0 += MODE_BLOCK) /* every frame's coefficients: the lags pair them */
        mode_block(slopes, mean, t0, nframes - t0 < MODE_BLOCK ? nframes - t0 : MODE_BLOCK, nslopes, A, m, blk,
                   q + t0 * m);
    if (!rc) {
        double c0 = 0;
        for (size_t t = 0; t < nframes; t++)
            for (size_t j = m / 2; j < m; j++) c0 += dep[j] ? 0 : q[t * m + j] * q[t * m + j];
        c0 /= (double)nframes;
        for (size_t k = 0; k < nlags; k++) {
            const size_t L = (size_t)lags[k];
            double s = 0;
            for (size_t t = 0; t + L < nframes; t++)
                for (size_t j = m / 2; j < m; j++) s += dep[j] ? 0 : q[t * m + j] * q[(t + L) * m + j];
            rho[k] = c0 > 0 ? s / (double)(nframes - L) / c0 : NAN;
        }
    }
    free(A); free(q); free(dep); free(mean); free(blk);
    return rc;
}

size_t swfs_mode_knee(const double *var, size_t n)
{
    /* Two least-squares lines in (log j, log var_j), modes 1..K and K+1..n, each at least 3
     * modes: the K of the smallest total squared misfit, from running sums. Modes without a
     * variance (NaN: no direction of their own) are left out. */
    double sx = 0, sy = 0, sxx = 0, sxy = 0, syy = 0;
    double *cs = malloc(5 * (n + 1) * sizeof *cs);
    size_t *idx = malloc((n + 1) * sizeof *idx);
    if (!cs || !idx) { free(cs); free(idx); return 0; }
    memset(cs, 0, 5 * sizeof *cs);
    size_t nf = 0; /* the modes with a variance; idx[i]: the i-th one's mode number */
    for (size_t j = 0; j < n; j++) {
        if (isnan(var[j])) continue;
        const double x = log((double)(j + 1)), y = log(fmax(var[j], 1e-300));
        sx += x; sy += y; sxx += x * x; sxy += x * y; syy += y * y;
        double *c = cs + 5 * ++nf;
        c[0] = sx; c[1] = sy; c[2] = sxx; c[3] = sxy; c[4] = syy;
        idx[nf] = j + 1;
    }
    size_t best = 0;
    double bsse = INFINITY;
    for (size_t K = 3; K + 3 <= nf; K++) {
        double sse = 0;
        for (int part = 0; part < 2; part++) {
            const double *a = cs + 5 * (part ? K : 0), *b = cs + 5 * (part ? nf : K);
            const double N = (double)(part ? nf - K : K), X = b[0] - a[0], Y = b[1] - a[1], XX = b[2] - a[2],
                         XY = b[3] - a[3], YY = b[4] - a[4];
            const double vx = XX - X * X / N, cxy = XY - X * Y / N, vy = YY - Y * Y / N;
            sse += vx > 0 ? vy - cxy * cxy / vx : vy;
        }
        if (sse < bsse) { bsse = sse; best = idx[K]; }
    }
    free(cs);
    free(idx);
    return best;
}

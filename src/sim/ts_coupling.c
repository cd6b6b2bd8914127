/* The DM's influence functions a loop's given reconstructor says (timeseries.h
 * swfs_ts_coupling_from_recon; docs/telemetry.md, "The DM's functions from the loop's control
 * matrix"). A control matrix W (actuators x slopes) is a pseudo-inverse of the interaction
 * matrix the system measured through its own DM; within W's row and column spaces (its rank r)
 * its pseudo-inverse gives that matrix back: with W = U S V^T, V_r^T pinv(W) U_r = S_r^-1. The
 * model's interaction matrix D(c) of Gaussian functions of coupling c, or of the interpolated
 * surface, is compared there, A = V_r^T D U_r, after the best single scale k (a centre of
 * gravity reads less than a gradient): the relative misfit |S^-1 - k A| / |S^-1|. */
#include "sim_internal.h"
#include "specklewfs/status.h"
#include "specklewfs/interp.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wfs.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct cfit {
    const swfs_ts_params *p;
    const double *mask, *xy;
    size_t nact, ns, r;
    const swfs_shwfs *sh;
    const double *U, *VT, *S; /* U: nact x k (first r columns used), VT: k x ns, S: k */
    size_t k;
    double *tmp, *A;         /* r x nact, r x r */
} cfit;

/* The misfit of the DM T's interaction matrix in *e. */
static int misfit_of(cfit *f, const swfs_sparse *T, double *e)
{
    double *D = NULL;
    const int rc = swfs_interaction_matrix(f->sh, T, &D);
    if (rc) return rc;
    const size_t r = f->r, nact = f->nact, ns = f->ns;
    /* A = V_r^T D U_r: (r x ns)(ns x nact) then (r x nact)(nact x r, the first r columns of U) */
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)r, (int)nact, (int)ns, 1.0, f->VT, (int)ns, D, (int)nact,
                0.0, f->tmp, (int)nact);
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)r, (int)r, (int)nact, 1.0, f->tmp, (int)nact, f->U,
                (int)f->k, 0.0, f->A, (int)r);
    free(D);
    double aa = 0, da = 0, dd = 0;
    for (size_t i = 0; i < r; i++) {
        for (size_t j = 0; j < r; j++) aa += f->A[i * r + j] * f->A[i * r + j];
        da += f->A[i * r + i] / f->S[i];
        dd += 1.0 / (f->S[i] * f->S[i]);
    }
    const double kk = aa > 0 ? da / aa : 0.0;
    /* |S^-1 - k A|^2 = dd - 2 k da + k^2 aa */
    *e = sqrt(fmax(dd - 2.0 * kk * da + kk * kk * aa, 0.0) / dd);
    return SWFS_OK;
}

/* The misfit of Gaussian functions of coupling c in *e. */
static int misfit(cfit *f, double c, double *e)
{
    swfs_sparse *T = NULL;
    int rc = swfs_influence_gauss_grid(f->xy, f->nact, (size_t)f->p->base.pupn, f->p->base.pupdx, f->mask, c, &T);
    if (!rc) rc = misfit_of(f, T, e);
    swfs_sparse_free(T);
    return rc;
}

int swfs_ts_coupling_from_recon(const swfs_ts_params *p, swfs_ts_coupling *out)
{
    memset(out, 0, sizeof *out);
    if (!p->ao_recon[0]) return swfs_fail(SWFS_ERR_ARG, "the DM's coupling from the loop's reconstructor: no ao_recon given");
    const size_t np = (size_t)p->base.pupn;
    double *mask = malloc(np * np * sizeof *mask), *xy = NULL, *a = NULL, *U = NULL, *VT = NULL, *S = NULL;
    swfs_recon *rao = NULL;
    unsigned char *vmap = NULL;
    swfs_sparse *T = NULL;
    swfs_shwfs *sh = NULL;
    size_t nact = 0;
    cfit f = {0};
    /* the sensor, the layout and the interpolated surface (the loop model at dm_coupling 0) */
    swfs_ts_params q = *p;
    q.dm_coupling = 0.0;
    int rc = mask ? swfs_sim_pupil(&p->base, mask) : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = swfs_ts_read_given(p, p->base.teldiam, &xy, &nact, &rao, &vmap);
    if (!rc) rc = swfs_ts_loop_model(&q, mask, vmap, &xy, &nact, &T, &sh);
    if (!rc) rc = swfs_ts_check_given_recon(p->ao_recon, rao, sh, nact); /* the loop's own checks and rank */
    if (rc) goto done;
    const size_t ns = sh->nslopes, r = rao->nmodes;
    const size_t k = nact < ns ? nact : ns;
    a = malloc(nact * ns * sizeof *a);
    U = malloc(nact * k * sizeof *U);
    VT = malloc(k * ns * sizeof *VT);
    S = malloc(k * sizeof *S);
    if (!a || !U || !VT || !S) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    memcpy(a, rao->W, nact * ns * sizeof *a);
    lapack_int info = LAPACKE_dgesdd(LAPACK_ROW_MAJOR, 'S', (lapack_int)nact, (lapack_int)ns, a, (lapack_int)ns, S, U,
                                     (lapack_int)k, VT, (lapack_int)ns);
    if (info) { rc = swfs_fail(SWFS_ERR_NUMERIC, "%s: SVD of the loop's reconstructor failed (%d)", p->ao_recon, (int)info); goto done; }
    f = (cfit){p, mask, xy, nact, ns, r, sh, U, VT, S, k, malloc(r * nact * sizeof *f.tmp), malloc(r * r * sizeof *f.A)};
    if (!f.tmp || !f.A) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    out->rank = r;
    if ((rc = misfit_of(&f, T, &out->misfit_interp))) goto done;
    /* the Gaussian coupling: a grid log-spaced over the couplings a continuous facesheet can have
     * (SWFS_TS_COUPLING_MIN .. MAX), then golden-section search in the best point's bracket */
    double cg[SWFS_TS_COUPLING_GRID], eg[SWFS_TS_COUPLING_GRID];
    size_t best = 0;
    for (size_t j = 0; j < SWFS_TS_COUPLING_GRID; j++) {
        cg[j] = SWFS_TS_COUPLING_MIN * pow(SWFS_TS_COUPLING_MAX / SWFS_TS_COUPLING_MIN,
                                           (double)j / (double)(SWFS_TS_COUPLING_GRID - 1));
        if ((rc = misfit(&f, cg[j], eg + j))) goto done;
        if (eg[j] < eg[best]) best = j;
    }
    double lo = log(cg[best ? best - 1 : 0]), hi = log(cg[best + 1 < SWFS_TS_COUPLING_GRID ? best + 1 : best]);
    const double g = 0.5 * (sqrt(5.0) - 1.0);
    double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo), e1, e2;
    if ((rc = misfit(&f, exp(x1), &e1)) || (rc = misfit(&f, exp(x2), &e2))) goto done;
    while (hi - lo > 1e-3) { /* 0.1 % in c */
        if (e1 < e2) { hi = x2; x2 = x1; e2 = e1; x1 = hi - g * (hi - lo); rc = misfit(&f, exp(x1), &e1); }
        else { lo = x1; x1 = x2; e1 = e2; x2 = lo + g * (hi - lo); rc = misfit(&f, exp(x2), &e2); }
        if (rc) goto done;
    }
    out->coupling = e1 < e2 ? exp(x1) : exp(x2);
    out->misfit = fmin(e1, e2);
    if (eg[best] < out->misfit) { out->coupling = cg[best]; out->misfit = eg[best]; }
    out->gaussian = out->misfit < out->misfit_interp;
done:
    free(f.tmp);
    free(f.A);
    free(mask);
    free(xy);
    free(a);
    free(U);
    free(VT);
    free(S);
    free(vmap);
    swfs_sparse_free(T);
    swfs_recon_free(rao);
    swfs_shwfs_free(sh);
    return rc;
}

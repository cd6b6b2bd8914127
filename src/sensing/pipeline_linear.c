/* The speckle pipeline over the generic linear model z = scale B (A v) (lmodel.h,
 * pipeline.h): the same engine, tip-tilt treatment and batches as the Shack-Hartmann
 * pipeline, with the basis in place of the actuators' interpolation. */
#include "specklewfs/pipeline.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"
#include "pipeline_internal.h"

#include <cblas.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Everything the build holds, freed in one place. */
typedef struct lin {
    size_t nmeas, nk, ng, npin, nrows, ncols;
    double *A;        /* nk x nmeas: scale x the control matrix [m of wavefront per telemetry unit] */
    double *f;        /* 2 x ng: the Z-tilt functionals */
    double *R;        /* 2 x nmeas: the Z-tilt of the model's wavefront */
    double *Aext;     /* nrows x ncols (speckles.h: the tilt rows and columns) */
    double *W;        /* the engine's matrix: Aext, or composed with the basis */
    swfs_sparse *B;   /* ng x (nk + 2): the basis and the two unit tilt planes */
    swfs_sparse *T;   /* the engine's interpolation: B, or the selection of the illuminated samples */
} lin;

static void lin_free(lin *l)
{
    free(l->A); free(l->f); free(l->R); free(l->Aext);
    if (l->W != l->Aext) free(l->W);
    swfs_sparse_free(l->B);
    if (l->T != l->B) swfs_sparse_free(l->T);
}

/* The basis functions the coefficients refer to. */
static size_t nfunctions(const swfs_linear_input *in) { return in->shapes ? in->nshapes : in->basis->ncols; }

static int check_input(const swfs_linear_input *in, size_t ng)
{
    if (!in->basis || !in->nmeas || !in->basis->ncols || (in->shapes && !in->nshapes))
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: the linear model needs a basis and telemetry values (%zu)", in->nmeas);
    if (in->basis->nrows != ng)
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: the basis has %zu rows but the pupil grid %zu samples",
                         in->basis->nrows, ng);
    if (in->control && in->imat)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: give a control matrix or an interaction matrix, not both");
    if (!in->control && !in->imat && in->nmeas != nfunctions(in))
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: %zu telemetry values per frame taken as the coefficients of %zu basis "
                         "functions; expected as many (or give a control or interaction matrix)", in->nmeas,
                         nfunctions(in));
    if (in->nlags > 1 && (in->imat || in->nmeas % in->nlags))
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: a space-time control matrix of %zu lags needs a control matrix and "
                         "a multiple of %zu telemetry values (got %zu%s)", in->nlags, in->nlags, in->nmeas,
                         in->imat ? ", and an interaction matrix" : "");
    if (!isfinite(in->scale) || in->scale == 0)
        return swfs_fail(SWFS_ERR_VALUE, "pipeline: the linear model's scale must be finite and non-zero, got %g",
                         in->scale);
    return SWFS_OK;
}

/* A = scale x (the control matrix | the identity | a reconstructor of the interaction matrix). */
static int build_control(lin *l, const swfs_linear_input *in, const double *training, size_t ntrain,
                         const swfs_pipeline_options *o, swfs_pipeline_info *info, swfs_recon **map)
{
    const size_t nk = nfunctions(in), nm = l->nmeas;
    if (nk > SIZE_MAX / sizeof(double) / nm || !(l->A = calloc(nk * nm, sizeof *l->A)))
        return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    if (in->control) {
        for (size_t k = 0; k < nk * nm; k++) {
            char val[48];
            if (!isfinite(in->control[k]))
                return swfs_fail(SWFS_ERR_VALUE, "pipeline: control matrix element (%zu, %zu) %s; expected finite",
                                 k / nm, k % nm, swfs_value_words(in->control[k], val, sizeof val));
            l->A[k] = in->scale * in->control[k];
        }
    } else if (!in->imat) {
        for (size_t k = 0; k < nk; k++) l->A[k * nm + k] = in->scale;
    } else {
        swfs_recon *r = NULL;
        int rc;
        if (o->recon == SWFS_RECON_SVD) rc = swfs_recon_svd(in->imat, nm, nk, o->rcond, o->max_modes, &r);
        else if (!training || ntrain < 8)
            rc = swfs_fail(SWFS_ERR_ARG, "pipeline: the MAP reconstructor of an interaction matrix learns its prior from "
                           "the telemetry; it needs at least 8 training frames (got %zu)", ntrain);
        else rc = swfs_recon_map(in->imat, nm, nk, training, ntrain, o->slope_noise * o->slope_noise, &r);
        if (rc) return rc;
        for (size_t k = 0; k < nk * nm; k++) l->A[k] = in->scale * r->W[k];
        info->recon_modes = r->nmodes;
        info->imat_rank = 0;
        for (size_t k = 0; r->sv && k < r->nsv; k++)
            info->imat_rank += r->sv[k] > (double)(nm > nk ? nm : nk) * DBL_EPSILON * r->sv[0];
        info->recon_dof = r->dof;
        info->noise_var = r->noise_var;
        info->noise_given = o->slope_noise > 0;
        info->ntrain = o->recon == SWFS_RECON_SVD ? 0 : ntrain;
        *map = r;
    }
    if (!in->shapes) return SWFS_OK;
    /* the factored basis: the functions' values at the basis' nq points times A */
    const size_t nq = l->nk;
    double *QA = calloc(nq * nm, sizeof *QA);
    if (!QA) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t k = 0; k < nq * nk; k++)
        if (!isfinite(in->shapes[k])) {
            char val[48];
            free(QA);
            return swfs_fail(SWFS_ERR_VALUE, "pipeline: basis shape value (%zu, %zu) %s; expected finite", k / nk,
                             k % nk, swfs_value_words(in->shapes[k], val, sizeof val));
        }
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nq, (int)nm, (int)nk, 1.0, in->shapes, (int)nk, l->A,
                (int)nm, 0.0, QA, (int)nm);
    free(l->A);
    l->A = QA;
    return SWFS_OK;
}

/* B: the basis and two more columns, the unit tilt planes x and y on the illuminated samples. */
static int extend_basis(lin *l, const swfs_sparse *b, const double *mask, size_t np, double pupdx)
{
    const size_t nk = l->nk;
    if (!(l->B = swfs_sparse_alloc(l->ng, nk + 2, b->nnz + 2 * l->npin))) return swfs_fail_context(SWFS_ERR_NOMEM, "pipeline");
    size_t z = 0;
    for (size_t r = 0; r < l->ng; r++) {
        for (size_t k = b->row_ptr[r]; k < b->row_ptr[r + 1]; k++) {
            l->B->col[z] = b->col[k];
            l->B->val[z++] = b->val[k];
        }
        if (mask[r] > 0) {
            const double c0 = 0.5 * (double)(np - 1);
            l->B->col[z] = nk;
            l->B->val[z++] = ((double)(r % np) - c0) * pupdx;
            l->B->col[z] = nk + 1;
            l->B->val[z++] = ((double)(r / np) - c0) * pupdx;
        }
        l->B->row_ptr[r + 1] = z;
    }
    l->B->nnz = z;
    return SWFS_OK;
}

/* R = (f B) A: the Z-tilt of the wavefront per telemetry value; then Aext by the tip-tilt mode
 * (speckles.h): EXPOSURE [[A, 0], [-R, I]] on [v, t - tbar] (the exposure-mean tilt removed),
 * FRAME [[A], [-R]] (each frame's own tilt removed), KEEP [[A], [0]]. */
static int tilt_rows(lin *l, int tt)
{
    const size_t nk = l->nk, nm = l->nmeas, ng = l->ng;
    double *fB = calloc(2 * nk, sizeof *fB);
    l->R = calloc(2 * nm, sizeof *l->R);
    l->ncols = nm + (tt == SWFS_TT_EXPOSURE ? 2 : 0);
    l->nrows = nk + 2;
    l->Aext = calloc(l->nrows * l->ncols, sizeof *l->Aext);
    if (!fB || !l->R || !l->Aext) { free(fB); return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory"); }
    for (size_t r = 0; r < ng; r++)
        for (size_t k = l->B->row_ptr[r]; k < l->B->row_ptr[r + 1]; k++)
            if (l->B->col[k] < nk)
                for (int t = 0; t < 2; t++) fB[(size_t)t * nk + l->B->col[k]] += l->f[(size_t)t * ng + r] * l->B->val[k];
    for (int t = 0; t < 2; t++)
        for (size_t k = 0; k < nk; k++) {
            const double c = fB[(size_t)t * nk + k];
            if (c != 0)
                for (size_t m = 0; m < nm; m++) l->R[(size_t)t * nm + m] += c * l->A[k * nm + m];
        }
    free(fB);
    for (size_t k = 0; k < nk; k++) memcpy(l->Aext + k * l->ncols, l->A + k * nm, nm * sizeof *l->A);
    for (size_t t = 0; t < 2 && tt != SWFS_TT_KEEP; t++) {
        double *row = l->Aext + (nk + t) * l->ncols;
        for (size_t m = 0; m < nm; m++) row[m] = -l->R[t * nm + m];
        if (tt == SWFS_TT_EXPOSURE) row[nm + t] = 1.0;
    }
    return SWFS_OK;
}

/* The engine's pair: the basis after the (small) control matrix, or, when that is cheaper
 * per frame (a dense modal basis: one GEMM instead of a sparse product as large), the two
 * folded into one matrix per illuminated sample with a selection as the interpolation.
 * The sparse product is costed at 4 GEMM operations per nonzero (engine.h: it runs 16
 * frames per nonzero against the GEMM's blocked kernels). */
static int choose_engine_form(lin *l)
{
    const double fold = (double)l->npin * (double)l->ncols;
    const double two = (double)l->nrows * (double)l->ncols + 4.0 * (double)l->B->nnz;
    if (fold > two || fold * sizeof(double) > (double)(1ULL << 31)) {
        l->W = l->Aext;
        l->T = l->B;
        return SWFS_OK;
    }
    const size_t nc = l->ncols;
    if (!(l->W = calloc(l->npin * nc, sizeof *l->W))) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    if (!(l->T = swfs_sparse_alloc(l->ng, l->npin, l->npin))) return swfs_fail_context(SWFS_ERR_NOMEM, "pipeline");
    size_t pi = 0;
    for (size_t r = 0; r < l->ng; r++) {
        const size_t k0 = l->B->row_ptr[r], k1 = l->B->row_ptr[r + 1];
        if (k0 < k1) {
            double *w = l->W + pi * nc;
            for (size_t k = k0; k < k1; k++) {
                const double v = l->B->val[k], *a = l->Aext + l->B->col[k] * nc;
                for (size_t m = 0; m < nc; m++) w[m] += v * a[m];
            }
            l->T->col[pi] = pi;
            l->T->val[pi] = 1.0;
            pi++;
        }
        l->T->row_ptr[r + 1] = pi;
    }
    l->T->nnz = pi;
    l->nrows = pi;
    return SWFS_OK;
}

/* The tip-tilt-free rms of the training frames' wavefront (up to 64 frames spread over
 * them), against what any AO residual can be. */
static int check_residual(const lin *l, const swfs_linear_input *in, const double *train, size_t ntrain,
                          const double *mask, double wavelen, swfs_pipeline_info *info)
{
    if (!train || !ntrain) return SWFS_OK;
    const size_t nk = l->nk, nm = l->nmeas, ng = l->ng, nf = ntrain < 64 ? ntrain : 64;
    double *c = calloc(nk + 2, sizeof *c), *z = malloc(ng * sizeof *z);
    if (!c || !z) { free(c); free(z); return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory"); }
    double ss = 0;
    for (size_t j = 0; j < nf; j++) {
        const double *v = train + (j * ntrain / nf) * nm;
        for (size_t k = 0; k < nk; k++) {
            double a = 0;
            for (size_t m = 0; m < nm; m++) a += l->A[k * nm + m] * v[m];
            c[k] = a;
        }
        double tx = 0, ty = 0;
        for (size_t m = 0; m < nm; m++) { tx += l->R[m] * v[m]; ty += l->R[nm + m] * v[m]; }
        c[nk] = -tx;
        c[nk + 1] = -ty;
        swfs_sparse_apply(l->B, c, z);
        double s = 0, s2 = 0;
        for (size_t r = 0; r < ng; r++)
            if (mask[r] > 0) { s += z[r]; s2 += z[r] * z[r]; }
        const double var = s2 / (double)l->npin - (s / (double)l->npin) * (s / (double)l->npin);
        ss += var > 0 ? var : 0; /* a flat wavefront's rounding: 0, not the root of a negative */
    }
    free(c);
    free(z);
    info->resid_rms = sqrt(ss / (double)nf);
    const double waves = info->resid_rms / wavelen;
    char rank[160] = "";
    if (info->imat_rank && info->imat_rank < nfunctions(in))
        snprintf(rank, sizeof rank, "; the interaction matrix senses only %zu combinations of its %zu basis functions' "
                 "coefficients (its rank)", info->imat_rank, nfunctions(in));
    if (!(waves <= SWFS_LINEAR_MAX_RMS_WAVES) || !(waves >= SWFS_LINEAR_MIN_RMS_WAVES))
        return swfs_fail(SWFS_ERR_VALUE, "pipeline: the linear model's wavefront is %.4g nm rms (tip-tilt removed) = %.3g "
                         "waves at %.4g um; expected %g..%g waves of an AO residual: are the basis x coefficients x scale "
                         "(%g) metres of wavefront? (cacao: unit-rms modes of DM surface, coefficients in um: scale 2e-6)%s",
                         info->resid_rms * 1e9, waves, wavelen * 1e6, SWFS_LINEAR_MIN_RMS_WAVES,
                         SWFS_LINEAR_MAX_RMS_WAVES, in->scale, rank);
    return SWFS_OK;
}

static int build(swfs_pipeline *p, lin *l, const swfs_geom *g, const swfs_linear_input *in, const double *training,
                 size_t ntrain)
{
    const size_t np = (size_t)g->pupn;
    l->nmeas = in->nmeas;
    l->nk = in->basis->ncols;
    l->ng = np * np;
    for (size_t r = 0; r < l->ng; r++) l->npin += p->mask[r] > 0;
    if (!(l->f = malloc(2 * l->ng * sizeof *l->f))) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    int rc = swfs_ztilt_functionals(p->mask, np, g->pupdx, l->f);
    if (!rc) rc = build_control(l, in, training, ntrain, &p->opt, &p->info, &p->lin_map);
    if (!rc) rc = extend_basis(l, in->basis, p->mask, np, g->pupdx);
    if (!rc) rc = tilt_rows(l, p->opt.tiptilt);
    if (!rc) rc = check_residual(l, in, training, ntrain, p->mask, g->wavelen, &p->info);
    if (!rc) rc = choose_engine_form(l);
    if (!rc) rc = swfs_pipeline_engine_(p, g, l->nrows, l->ncols, l->W, l->T);
    if (!rc) rc = swfs_pipeline_band_(p, g, 0);
    if (rc) return rc;
    p->info.nslopes = l->nmeas;
    p->info.nlags = in->nlags > 1 ? in->nlags : 0;
    p->info.nact = l->nrows;
    p->info.nbasis = nfunctions(in);
    p->info.basis_nnz = in->basis->nnz;
    p->info.composed = l->T != l->B;
    if (p->opt.tiptilt == SWFS_TT_EXPOSURE) {
        p->Rtilt = l->R;
        l->R = NULL;
    }
    return SWFS_OK;
}

int swfs_pipeline_create_linear(swfs_pipeline **out, const swfs_geom *g, size_t nfx, size_t nfy, const double *mask,
                                const swfs_linear_input *in, const double *training, size_t ntrain,
                                const swfs_pipeline_options *opt)
{
    *out = NULL;
    swfs_pipeline_options def;
    if (!opt) {
        swfs_pipeline_options_default(&def);
        opt = &def;
    }
    swfs_pipeline *p;
    int rc = swfs_pipeline_begin_(&p, g, nfx, nfy, mask, opt, NULL, training, ntrain, 0);
    if (rc) return rc;
    lin l = {0};
    rc = check_input(in, (size_t)g->pupn * (size_t)g->pupn);
    if (!rc) rc = build(p, &l, g, in, training, ntrain);
    lin_free(&l);
    if (rc) {
        swfs_pipeline_free(p);
        return rc;
    }
    *out = p;
    return SWFS_OK;
}

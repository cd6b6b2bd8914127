/* The speckle pipeline: see include/specklewfs/pipeline.h. */
#include "specklewfs/pipeline.h"
#include "specklewfs/aperture.h"
#include "specklewfs/interp.h"
#include "specklewfs/status.h"
#include "pipeline_internal.h"
#include "specklewfs/pupil.h"

#include <cblas.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

void swfs_pipeline_options_default(swfs_pipeline_options *o)
{
    memset(o, 0, sizeof *o);
    o->recon = SWFS_RECON_VK; /* better than svd in 4 of 4 cases (docs/telemetry.md) */
    o->rcond = 5e-2;          /* 1e-2 amplified the WFS noise (docs/telemetry.md) */
    o->max_modes = 0;
    o->slope_noise = 0.0;
    o->vk_l0 = 10.0;          /* an effective outer scale of the AO residual (docs/telemetry.md: a
                                 plateau at 5-20 m over four cases; the maximum-likelihood fit
                                 to the slopes, vk_l0 = 0, reconstructs worse) */
    o->tiptilt = SWFS_TT_EXPOSURE;
    o->threads = 1;
    o->wfs_rate = 0;
    o->recon_scale = 1.0;
}

void swfs_pipeline_free(swfs_pipeline *p)
{
    if (!p) return;
    swfs_speckle_model_free(p->model);
    swfs_recon_free(p->lin_map);
    swfs_engine_free(p->engine);
    free(p->W_ext);
    free(p->Rtilt);
    free(p->mask);
    free(p->xslopes);
    free(p->xsched);
    free(p->macc);
    free(p->moff);
    free(p->band_idx);
    free(p);
}

/* recon_checks: the Shack-Hartmann model's reconstructor choices (a linear model checks its own). */
static int check_options(const swfs_pipeline_options *o, const swfs_recon *recon, const double *training,
                         size_t ntrain, int recon_checks)
{
    if (o->recon < SWFS_RECON_VK || o->recon > SWFS_RECON_GIVEN)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: unknown reconstructor choice %d", o->recon);
    if (recon_checks && o->recon == SWFS_RECON_GIVEN && !recon)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: SWFS_RECON_GIVEN needs a reconstructor matrix");
    if (recon_checks && (o->recon == SWFS_RECON_VK || o->recon == SWFS_RECON_MAP) && (!training || ntrain < 2))
        return swfs_fail(SWFS_ERR_ARG, "pipeline: the %s reconstructor learns from the telemetry: it needs training "
                         "slopes (got %zu frames)", o->recon == SWFS_RECON_VK ? "von Karman MAP" : "MAP", ntrain);
    if (!(o->rcond >= 0 && o->rcond < 1))
        return swfs_fail(SWFS_ERR_ARG, "pipeline: rcond must be in [0, 1), got %g", o->rcond);
    if (!(o->slope_noise >= 0) || !isfinite(o->slope_noise))
        return swfs_fail(SWFS_ERR_ARG, "pipeline: slope noise must be a finite rms >= 0 [rad], got %g", o->slope_noise);
    if (!(o->vk_l0 >= 0) || !isfinite(o->vk_l0))
        return swfs_fail(SWFS_ERR_ARG, "pipeline: the von Karman outer scale must be >= 0 [m] (0: fitted), got %g",
                         o->vk_l0);
    if (o->tiptilt < SWFS_TT_EXPOSURE || o->tiptilt > SWFS_TT_KEEP)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: unknown tip-tilt mode %d", o->tiptilt);
    if (o->wfs_rate && o->tiptilt == SWFS_TT_EXPOSURE)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: at the WFS rate there is no exposure to take a mean tip-tilt over; "
                         "use SWFS_TT_FRAME or SWFS_TT_KEEP");
    if (o->threads < 1 || o->threads > SWFS_ENGINE_MAX_THREADS)
        return swfs_fail(SWFS_ERR_ARG, "pipeline: threads must be 1..%d, got %d", SWFS_ENGINE_MAX_THREADS, o->threads);
    return SWFS_OK;
}

/* A given reconstructor W (z [m of wavefront] = W s [rad]), times scale, against the model's
 * interaction matrix D: the eigenvalue of W D of largest magnitude. Any reconstructor of D
 * makes W D a projector onto the modes it keeps (eigenvalues 0 and 1, oblique for a modal
 * one): 1 whatever its rank. A Wiener-type one (MAP: W D is similar to a symmetric matrix
 * with eigenvalues in [0, 1), its modal Wiener factors) has its best-measured mode's factor,
 * close to 1 however many noisy modes it shrinks -- where the trace ratio tr((W D)^2) /
 * tr(W D) it replaces fell to 0.39 for the library's own vk reconstructor of a loop
 * controlling 120 modes. A matrix to DM commands is a correction of the surface: -1/2. */
static double dominant_eigenvalue(const double *M, size_t n)
{
    double *x = malloc(n * sizeof *x), *y = malloc(n * sizeof *y), lam = 0.0;
    if (!x || !y) { free(x); free(y); return NAN; }
    for (size_t i = 0; i < n; i++) x[i] = 1.0 + 0.5 * sin(1.7 * (double)i); /* no mode left out */
    for (int it = 0; it < 500; it++) {
        cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)n, (int)n, 1.0, M, (int)n, x, 1, 0.0, y, 1);
        double xy = 0.0, xx = 0.0, yy = 0.0;
        for (size_t i = 0; i < n; i++) { xy += x[i] * y[i]; xx += x[i] * x[i]; yy += y[i] * y[i]; }
        const double l = xx > 0.0 ? xy / xx : 0.0;
        if (!(yy > 0.0)) { lam = 0.0; break; }
        const double inv = 1.0 / sqrt(yy);
        for (size_t i = 0; i < n; i++) x[i] = y[i] * inv;
        const int done = it > 5 && fabs(l - lam) <= 1e-6 * fabs(l);
        lam = l;
        if (done) break;
    }
    free(x);
    free(y);
    return lam;
}
static int check_given(swfs_pipeline *p, double scale)
{
    swfs_recon *r = p->model->recon;
    const size_t na = r->nact, ns = r->nslopes;
    for (size_t i = 0; i < na * ns; i++) r->W[i] *= scale;
    double *D = NULL, *M = malloc(na * na * sizeof *M);
    int rc = M ? swfs_interaction_matrix(p->model->wfs, p->model->T, &D) : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) {
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)na, (int)na, (int)ns, 1.0, r->W, (int)ns, D,
                    (int)na, 0.0, M, (int)na);
        p->info.recon_gain = dominant_eigenvalue(M, na);
    }
    free(D);
    free(M);
    return rc;
}

/* The slopes' layout. Without a valid-subaperture map: 2 nsub^2 values (x then y, unused
 * subapertures 0). With one (opt->valid, nsub = opt->valid_nsub): the same full layout, or
 * the used subapertures only, 2 nvalid values (the x slopes of the used subapertures in
 * index order, then their y slopes); *cols then receives their full-layout indices. */
static int slopes_layout(const swfs_pipeline_options *o, size_t nslopes, size_t *nsub, size_t **cols)
{
    *cols = NULL;
    if (!o->valid) {
        *nsub = (size_t)llround(sqrt((double)nslopes / 2));
        if (2 * *nsub * *nsub != nslopes)
            return swfs_fail(SWFS_ERR_SHAPE, "%zu slopes per frame is not 2 nsub^2 (x then y slopes of a square "
                             "Shack-Hartmann, unused subapertures 0); slopes of the used subapertures only need "
                             "their valid-subaperture map", nslopes);
        return SWFS_OK;
    }
    const size_t n = o->valid_nsub, nsa = n * n;
    size_t nv = 0;
    if (!n || n > 4096) return swfs_fail(SWFS_ERR_ARG, "valid-subaperture map: %zu subapertures across", n);
    for (size_t i = 0; i < nsa; i++) nv += o->valid[i] != 0;
    *nsub = n;
    if (nslopes == 2 * nsa) return SWFS_OK;
    if (nslopes != 2 * nv)
        return swfs_fail(SWFS_ERR_SHAPE, "%zu slopes per frame, but the valid-subaperture map (%zu x %zu, %zu used) "
                         "expects %zu (the used subapertures) or %zu (all, unused ones 0)", nslopes, n, n, nv, 2 * nv,
                         2 * nsa);
    size_t nc = 0;
    return swfs_slopes_used_cols(o->valid, n, cols, &nc);
}

/* In place: rows x (nb blocks of nfull + extra) -> rows x (nb blocks of nc + extra), each
 * block keeping cols (nb > 1: a space-time reconstructor's lag blocks). cols ascending and
 * nc <= nfull: every write lands at or before the value it copies, before any value still
 * to be read. */
static void compress_blocks(double *a, size_t rows, size_t nfull, size_t nb, size_t extra, size_t nc, const size_t *cols)
{
    for (size_t r = 0; r < rows; r++) {
        const double *src = a + r * (nb * nfull + extra);
        double *dst = a + r * (nb * nc + extra);
        for (size_t b = 0; b < nb; b++)
            for (size_t k = 0; k < nc; k++) dst[b * nc + k] = src[b * nfull + cols[k]];
        for (size_t e = 0; e < extra; e++) dst[nb * nc + e] = src[nb * nfull + e];
    }
}

/* A space-time reconstructor's lag blocks summed: its response to a static wavefront, a
 * per-frame reconstructor (nact x ns) that the model, the gain check and the layout take. */
static int sum_blocks(const swfs_recon *st, swfs_recon *sum)
{
    const size_t nl = st->nlags, ns = st->nslopes / nl;
    *sum = *st;
    sum->nslopes = ns;
    sum->nlags = 0;
    sum->sv = NULL;
    if (!(sum->W = calloc(st->nact * ns, sizeof *sum->W))) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t a = 0; a < st->nact; a++)
        for (size_t k = 0; k < nl; k++)
            for (size_t i = 0; i < ns; i++) sum->W[a * ns + i] += st->W[a * st->nslopes + k * ns + i];
    return SWFS_OK;
}

/* The space-time reconstructor st (its blocks in the telemetry's layout: cols, or the full
 * one) as the model's, in the full layout (nfull per block), times scale, with the tip-tilt
 * treatment acting on the lag-0 block as on a per-frame reconstructor (exposure: the tilt is
 * that block's mean slopes; frame: the mean slopes out of it) and the other blocks' mean
 * slopes projected out (the frame's tilt is its own slopes'). */
static int spacetime_model(swfs_pipeline *p, const swfs_recon *st, const size_t *cols, size_t nfull, const double *xy)
{
    swfs_recon *r = p->model->recon;
    const size_t nl = st->nlags, ns = st->nslopes / nl, na = st->nact, w = nl * nfull;
    const int full = !cols || ns == nfull;
    double *W = calloc(na * w, sizeof *W);
    swfs_recon blk = *r;
    blk.nslopes = nfull;
    blk.nlags = 0;
    blk.W = malloc(na * nfull * sizeof *blk.W);
    int rc = W && blk.W ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t k = 0; !rc && k < nl; k++) {
        for (size_t a = 0; a < na; a++) {
            const double *src = st->W + a * st->nslopes + k * ns;
            double *dst = blk.W + a * nfull;
            if (full) memcpy(dst, src, nfull * sizeof *dst);
            else {
                memset(dst, 0, nfull * sizeof *dst);
                for (size_t i = 0; i < ns; i++) dst[cols[i]] = src[i];
            }
            for (size_t i = 0; i < nfull; i++) dst[i] *= p->opt.recon_scale;
        }
        if (p->opt.tiptilt == SWFS_TT_EXPOSURE && st->lags[k] == 0)
            rc = swfs_recon_tilt_as_mean_slopes(&blk, p->model->wfs->valid, xy);
        else if (p->opt.tiptilt != SWFS_TT_KEEP)
            rc = swfs_recon_project_tiptilt(&blk, p->model->wfs->valid);
        for (size_t a = 0; !rc && a < na; a++) memcpy(W + a * w + k * nfull, blk.W + a * nfull, nfull * sizeof *W);
    }
    free(blk.W);
    if (rc) { free(W); return rc; }
    free(r->W);
    r->W = W;
    r->nslopes = w;
    r->nlags = nl;
    memcpy(r->lags, st->lags, sizeof r->lags);
    return SWFS_OK;
}

/* The model and its reconstructor: given, SVD, or learned from the training slopes; built in
 * the full slopes layout, then narrowed to the used subapertures' columns when the
 * telemetry holds only those. */
static int build_model(swfs_pipeline *p, const swfs_geom *g, const double *xy, size_t nact, size_t nslopes,
                       const swfs_recon *recon, const double *training, size_t ntrain)
{
    const swfs_pipeline_options *o = &p->opt;
    size_t nsub = 0, *cols = NULL;
    int rc = slopes_layout(o, nslopes, &nsub, &cols);
    if (rc) return rc;
    const size_t nfull = 2 * nsub * nsub;
    /* A space-time reconstructor: the model, its layout and its gain from the sum of its lag
     * blocks; its blocks replace the model's reconstructor below. */
    const swfs_recon *st = recon && recon->nlags > 1 ? recon : NULL;
    swfs_recon rsum = {0};
    if (st && (rc = sum_blocks(st, &rsum))) { free(cols); return rc; }
    if (st) recon = &rsum;
    /* A given reconstructor takes the telemetry's layout, or the full one when the telemetry
     * holds the used subapertures only (e.g. `learn` on simulated full-layout slopes). */
    const int recon_full = recon && cols && recon->nslopes == nfull;
    if (recon && recon->nslopes != nslopes && !recon_full) {
        free(cols);
        free(rsum.W);
        if (cols)
            return swfs_fail(SWFS_ERR_SHAPE, "%zu slopes per frame but the reconstructor expects %zu (expected %zu, the "
                             "used subapertures', or %zu, the full layout's)", nslopes, recon->nslopes, nslopes, nfull);
        return swfs_fail(SWFS_ERR_SHAPE, "%zu slopes per frame but the reconstructor expects %zu", nslopes,
                         recon->nslopes);
    }
    double *train_full = NULL;
    swfs_recon rfull;
    if (cols && training && !(training = train_full = swfs_slopes_expand_cols(training, ntrain, nslopes, cols, nfull)))
        rc = swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory for %zu training frames", ntrain);
    if (!rc && cols && recon && !recon_full) {
        rfull = *recon;
        rfull.nslopes = nfull;
        rfull.sv = NULL;
        if (!(rfull.W = swfs_slopes_expand_cols(recon->W, nact, nslopes, cols, nfull)))
            rc = swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
        recon = &rfull;
    }
    /* --tiptilt frame projects the mean slopes out of W; exposure needs W whole (its tilt
     * is taken out as the Z-tilt by swfs_speckles_recon_tilt); keep uses it as it is. */
    const int project = o->tiptilt == SWFS_TT_FRAME;
    if (!rc)
        rc = swfs_speckle_model_create_valid(&p->model, xy, nact, p->mask, (size_t)g->pupn, g->pupdx, g->teldiam, nsub,
                                             o->valid, o->recon == SWFS_RECON_GIVEN ? recon : NULL, o->rcond,
                                             o->max_modes, project);
    if (cols && recon && !recon_full) free(rfull.W);
    if (!rc && o->recon == SWFS_RECON_GIVEN) rc = check_given(p, o->recon_scale);
    const double nv = o->slope_noise * o->slope_noise;
    if (!rc && o->recon == SWFS_RECON_MAP) rc = swfs_speckle_model_set_map(p->model, training, ntrain, nv, project);
    else if (!rc && o->recon == SWFS_RECON_VK)
        rc = swfs_speckle_model_set_vk(p->model, xy, o->vk_l0, training, ntrain, nv, project);
    free(train_full);
    /* The frames' tilt is their mean slopes (plus the Z-tilt of the rest): a MAP reconstructor
     * whose prior was scaled on the tip-tilt-free slopes otherwise spreads the large vibration
     * and jitter tilt into its correlated higher-order patterns. In a loop controlling 120 of
     * 217 modes the speckles from the slopes gave 21.6 nm against 16.9 with this (ideal 10.8);
     * nothing moved by more than 0.1 nm over bench_telemetry's 24 runs (docs/telemetry.md).
     * Idempotent, so a reconstructor written by --write-recon and given back is unchanged. */
    if (!rc && st) rc = spacetime_model(p, st, cols && !recon_full ? cols : NULL, nfull, xy);
    else if (!rc && o->tiptilt == SWFS_TT_EXPOSURE)
        rc = swfs_recon_tilt_as_mean_slopes(p->model->recon, p->model->wfs->valid, xy);
    free(rsum.W);
    if (!rc && o->tiptilt == SWFS_TT_EXPOSURE) rc = swfs_speckles_recon_tilt(p->model, xy, &p->W_ext, &p->Rtilt);
    if (!rc) {
        swfs_pipeline_info *in = &p->info;
        in->recon_modes = p->model->recon->nmodes;
        in->recon_dof = p->model->recon->dof;
        in->noise_var = p->model->recon->noise_var;
        in->vk_l0 = o->recon == SWFS_RECON_VK ? p->model->recon->l0 : 0.0;
        in->noise_given = o->slope_noise > 0;
        in->ntrain = (o->recon == SWFS_RECON_VK || o->recon == SWFS_RECON_MAP) ? ntrain : 0;
        in->n_outside = p->model->n_outside;
        in->nsub = nsub;
        in->nvalid = p->model->wfs->nvalid;
    }
    const size_t nl = st ? st->nlags : 1;
    if (!rc && cols) {
        /* The reconstructor (and what --write-recon saves) in the telemetry's own layout. */
        swfs_recon *r = p->model->recon;
        compress_blocks(r->W, nact, nfull, nl, 0, nslopes, cols);
        r->nslopes = nslopes * nl;
        if (p->W_ext) compress_blocks(p->W_ext, nact, nfull, nl, 2, nslopes, cols);
        if (p->Rtilt) compress_blocks(p->Rtilt, 2, nfull, nl, 0, nslopes, cols);
    }
    if (!rc) p->info.nlags = st ? nl : 0;
    free(cols);
    return rc;
}

/* The part every pipeline shares: options, geometry, window, the pupil mask. */
int swfs_pipeline_begin_(swfs_pipeline **out, const swfs_geom *g, size_t nfx, size_t nfy, const double *mask,
                         const swfs_pipeline_options *opt, const swfs_recon *recon, const double *training,
                         size_t ntrain, int sh)
{
    *out = NULL;
    int rc = check_options(opt, recon, training, ntrain, sh);
    if (rc) return rc;
    if ((rc = swfs_geom_require(g, "pipeline geometry"))) return rc;
    if (!nfx || !nfy) return swfs_fail(SWFS_ERR_SHAPE, "pipeline: empty focal window (%zux%zu)", nfx, nfy);
    if (g->pupn > 100000) return swfs_fail(SWFS_ERR_VALUE, "pipeline: PUPN = %ld is beyond any pupil grid", g->pupn);
    swfs_pipeline *p = calloc(1, sizeof *p);
    if (!p) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    p->opt = *opt;
    const size_t npup = (size_t)g->pupn;
    p->info = (swfs_pipeline_info){0, 0, npup, nfx, nfy, 0, 0.0, 0.0, 0, 0, 0, 0.0, NAN, 0, 0, 0, NAN, 0, 0, 0.0, 0, 0, 0.0, 0};
    p->mask = malloc(npup * npup * sizeof *p->mask);
    if (!p->mask) { swfs_pipeline_free(p); return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory"); }
    if (mask) memcpy(p->mask, mask, npup * npup * sizeof *p->mask);
    else if ((rc = swfs_aperture_make(p->mask, npup, g->pupdx, g->teldiam, g->obscur, 0, 0))) {
        swfs_pipeline_free(p);
        return rc;
    }
    *out = p;
    return SWFS_OK;
}

/* The engine over the reconstructor W (nrows x ncols: ncols = the telemetry values, + 2
 * tilt values for SWFS_TT_EXPOSURE) and the interpolation T (npup^2 x nrows). */
int swfs_pipeline_engine_(swfs_pipeline *p, const swfs_geom *g, size_t nrows, size_t ncols, const double *W,
                          const swfs_sparse *T)
{
    swfs_engine_config ec = {ncols, nrows, p->info.npup, p->info.nfx, p->info.nfy, g->pixscale * g->pupdx / g->teldiam,
                             g->wavelen, W, T, p->mask, 0, p->opt.threads};
    if (!(p->engine = swfs_engine_create(&ec))) return swfs_fail_context(SWFS_ERR_NOMEM, "pipeline");
    if (!(p->macc = calloc(ncols, sizeof *p->macc))) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    p->mcols = ncols;
    p->mexp = 0;
    return SWFS_OK;
}

int swfs_pipeline_band_(swfs_pipeline *p, const swfs_geom *g, size_t nsub)
{
    const double dflt = p->info.out_pitch > 0.0 ? g->teldiam / (2.0 * p->info.out_pitch) : 0.5 * (double)nsub;
    const double b = p->opt.band > 0.0 ? p->opt.band : (p->opt.band == 0.0 && nsub ? dflt : 0.0);
    if (!isfinite(b)) return swfs_fail(SWFS_ERR_ARG, "pipeline: speckle band %g lambda/D", p->opt.band);
    p->info.band = b;
    p->info.band_out = 0;
    if (b <= 0.0) return SWFS_OK;
    const size_t nfx = p->info.nfx, nfy = p->info.nfy;
    size_t n = 0;
    for (int pass = 0; pass < 2; pass++) {
        n = 0;
        for (size_t j = 0; j < nfy; j++)
            for (size_t i = 0; i < nfx; i++) {
                const double r = hypot((double)i - (double)(nfx / 2), (double)j - (double)(nfy / 2)) * g->pixscale;
                if (r > b * (1.0 + 1e-12)) {
                    if (pass) p->band_idx[n] = j * nfx + i;
                    n++;
                }
            }
        if (!pass && n && !(p->band_idx = malloc(n * sizeof *p->band_idx)))
            return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
        if (!n) break;
    }
    p->info.band_out = n;
    return SWFS_OK;
}

/* The fields beyond the band set to 0 (nf frames). */
static void band_apply(const swfs_pipeline *p, swfs_complex *out, size_t nf)
{
    const size_t np = p->info.nfx * p->info.nfy;
    for (size_t f = 0; f < nf; f++)
        for (size_t k = 0; k < p->info.band_out; k++) out[f * np + p->band_idx[k]] = 0;
}

/* The engine's weight of frame f of exposure x: w_first on the first, w_last on the last, 1 in
 * between (count 1: w_first). */
static double frame_weight(const swfs_exposure *x, size_t f)
{
    return f == 0 ? x->w_first : (f + 1 == x->count ? x->w_last : 1.0);
}

/* Each exposure's weighted mean engine input into the running sum. */
static void mean_add(swfs_pipeline *p, const double *v, const swfs_exposure *sched, size_t nexp)
{
    const size_t nc = p->mcols;
    for (size_t i = 0; i < nexp; i++) {
        const swfs_exposure *x = sched + i;
        double wsum = 0.0;
        for (size_t f = 0; f < x->count; f++) wsum += frame_weight(x, f);
        if (!(wsum > 0.0)) continue;
        for (size_t f = 0; f < x->count; f++) {
            const double w = frame_weight(x, f) / wsum;
            const double *s = v + (x->first + f) * nc;
            for (size_t k = 0; k < nc; k++) p->macc[k] += w * s[k];
        }
        p->mexp++;
    }
}

void swfs_pipeline_mean_reset(swfs_pipeline *p)
{
    memset(p->macc, 0, p->mcols * sizeof *p->macc);
    p->mexp = 0;
}

void swfs_pipeline_mean_state(swfs_pipeline *p, double **sum, size_t *n, size_t *nexp)
{
    *sum = p->macc;
    *n = p->mcols;
    *nexp = p->mexp;
}

void swfs_pipeline_mean_set_count(swfs_pipeline *p, size_t nexp) { p->mexp = nexp; }

int swfs_pipeline_mean_reconstruction(const swfs_pipeline *p, double *out)
{
    const size_t n = p->info.npup;
    if (!p->mexp) return swfs_fail(SWFS_ERR_VALUE, "pipeline: no exposure processed, so no time mean");
    double *v = malloc(p->mcols * sizeof *v);
    if (!v) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t k = 0; k < p->mcols; k++) v[k] = p->macc[k] / (double)p->mexp;
    int rc = swfs_engine_wavefront(p->engine, v, out);
    free(v);
    if (!rc) swfs_wfe_remove_ptt(out, p->mask, n);
    return rc;
}

int swfs_pipeline_mean_wavefront(const swfs_pipeline *p, double *out, size_t *nexp, double *rms)
{
    const size_t n = p->info.npup;
    if (nexp) *nexp = p->mexp;
    int rc = swfs_pipeline_mean_reconstruction(p, out);
    for (size_t i = 0; !rc && p->moff && i < n * n; i++) out[i] += p->moff[i];
    if (!rc) {
        const double r = swfs_wfe_remove_ptt(out, p->mask, n);
        if (rms) *rms = r;
    }
    return rc;
}

int swfs_pipeline_wavefront_of_mean(const swfs_pipeline *p, const double *mean, size_t n, double *out)
{
    const size_t np = p->info.npup, nc = p->mcols, nl = p->info.nlags > 1 ? p->info.nlags : 1;
    /* the engine's input for a mean: the mean itself, at every lag of a space-time map, and 0
     * for the exposure-relative tilt columns (their mean over an exposure is 0) */
    if (!n || !(nc == nl * n || nc == nl * n + 2))
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: a mean of %zu telemetry values, but the engine takes %zu (%zu lags)",
                         n, nc, nl);
    double *v = calloc(nc, sizeof *v);
    if (!v) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t k = 0; k < nl * n; k++) v[k] = mean[k % n];
    int rc = swfs_engine_wavefront(p->engine, v, out);
    free(v);
    if (!rc) swfs_wfe_remove_ptt(out, p->mask, np);
    return rc;
}

int swfs_pipeline_set_mean_offset(swfs_pipeline *p, const double *map)
{
    const size_t n = p->info.npup;
    if (!map) {
        free(p->moff);
        p->moff = NULL;
        return SWFS_OK;
    }
    for (size_t i = 0; i < n * n; i++) /* checked before anything changes: a refused offset leaves the one set */
        if (p->mask[i] > 0 && !isfinite(map[i]))
            return swfs_fail(SWFS_ERR_VALUE, "pipeline: mean offset sample %zu (x %zu, y %zu) is not finite", i, i % n,
                             i / n);
    if (!p->moff && !(p->moff = malloc(n * n * sizeof *p->moff))) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    for (size_t i = 0; i < n * n; i++) p->moff[i] = p->mask[i] > 0 ? map[i] : 0.0;
    return SWFS_OK;
}

int swfs_pipeline_create(swfs_pipeline **out, const swfs_geom *g, size_t nfx, size_t nfy, const double *xy,
                         size_t nact, const double *mask, size_t nslopes, const swfs_recon *recon,
                         const double *training, size_t ntrain, const swfs_pipeline_options *opt)
{
    *out = NULL;
    swfs_pipeline_options def;
    if (!opt) {
        swfs_pipeline_options_default(&def);
        opt = &def;
    }
    if (!nact || !nslopes)
        return swfs_fail(SWFS_ERR_SHAPE, "pipeline: no actuators (%zu) or slopes (%zu)", nact, nslopes);
    /* A given map with output points of its own writes the wavefront there, not on the DM's
     * actuators: the model is built on its points. */
    const int own = opt->recon == SWFS_RECON_GIVEN && recon && recon->oxy;
    if (own) {
        xy = recon->oxy;
        nact = recon->nact;
    }
    swfs_pipeline *p;
    int rc = swfs_pipeline_begin_(&p, g, nfx, nfy, mask, opt, recon, training, ntrain, 1);
    if (rc) return rc;
    if (own) p->info.out_pitch = swfs_points_pitch(xy, nact);
    p->info.nact = nact;
    p->info.nslopes = nslopes;
    const int xt = opt->tiptilt == SWFS_TT_EXPOSURE;
    if (!(rc = build_model(p, g, xy, nact, nslopes, recon, training, ntrain)) && own) {
        /* the model's map keeps its points (what --write-recon saves) */
        swfs_recon *mr = p->model->recon;
        free(mr->oxy);
        if (!(mr->oxy = malloc(2 * nact * sizeof *mr->oxy))) rc = swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
        else memcpy(mr->oxy, xy, 2 * nact * sizeof *mr->oxy);
    }
    if (!rc) {
        p->info.nslopes = p->model->recon->nslopes; /* a space-time reconstructor's stacked input */
        rc = swfs_pipeline_engine_(p, g, nact, p->info.nslopes + (xt ? 2 : 0), xt ? p->W_ext : p->model->recon->W,
                                   p->model->T);
    }
    if (!rc) rc = swfs_pipeline_band_(p, g, p->model->wfs->nsub);
    p->opt.valid = NULL; /* the caller's map: read at creation only */
    if (rc) {
        swfs_pipeline_free(p);
        return rc;
    }
    *out = p;
    return SWFS_OK;
}

/* Grow the expansion work space to hold nx frames and nexp exposures (only when a batch
 * larger than any before arrives). */
static int reserve(swfs_pipeline *p, size_t nx, size_t nexp)
{
    const size_t w = p->info.nslopes + 2;
    if (nx > p->xcap) {
        if (nx > SIZE_MAX / sizeof(double) / w) return swfs_fail(SWFS_ERR_VALUE, "pipeline: batch too large");
        double *t = realloc(p->xslopes, nx * w * sizeof *t);
        if (!t) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory for %zu expanded frames", nx);
        p->xslopes = t;
        p->xcap = nx;
    }
    if (nexp > p->xscap) {
        swfs_exposure *t = realloc(p->xsched, nexp * sizeof *t);
        if (!t) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory for %zu exposures", nexp);
        p->xsched = t;
        p->xscap = nexp;
    }
    return SWFS_OK;
}

int swfs_pipeline_process(swfs_pipeline *p, const double *slopes, size_t nwfs, const swfs_exposure *sched, size_t nexp,
                          swfs_complex *out)
{
    if (p->opt.wfs_rate) return swfs_fail(SWFS_ERR_ARG, "pipeline: made for the WFS rate; use swfs_pipeline_process_wfs");
    if (p->opt.tiptilt != SWFS_TT_EXPOSURE) {
        int rc = swfs_engine_process(p->engine, slopes, nwfs, sched, nexp, out);
        if (!rc) mean_add(p, slopes, sched, nexp);
        if (!rc) band_apply(p, out, nexp);
        return rc;
    }
    /* Tip-tilt relative to each exposure's mean, as two extra slopes (speckles.h); the schedule
     * checked first, before its counts size the expanded frames */
    for (size_t j = 0; j < nexp; j++)
        if (sched[j].count == 0 || sched[j].first >= nwfs || sched[j].count > nwfs - sched[j].first)
            return swfs_fail(SWFS_ERR_VALUE, "speckles: exposure %zu needs %zu WFS frames from frame %zu of %zu", j,
                             sched[j].count, sched[j].first, nwfs);
    const size_t nx = swfs_speckles_expand_frames(sched, nexp);
    int rc = reserve(p, nx, nexp);
    if (!rc) rc = swfs_speckles_expand(slopes, p->info.nslopes, nwfs, p->Rtilt, sched, nexp, p->xslopes, p->xsched);
    if (!rc) rc = swfs_engine_process(p->engine, p->xslopes, nx, p->xsched, nexp, out);
    if (!rc) mean_add(p, p->xslopes, p->xsched, nexp);
    if (!rc) band_apply(p, out, nexp);
    return rc;
}

int swfs_pipeline_process_wfs(swfs_pipeline *p, const double *slopes, size_t nwfs, swfs_complex *out)
{
    if (!p->opt.wfs_rate) return swfs_fail(SWFS_ERR_ARG, "pipeline: made for camera exposures; use swfs_pipeline_process");
    int rc = swfs_engine_process_wfs(p->engine, slopes, nwfs, out);
    if (!rc) band_apply(p, out, nwfs);
    for (size_t f = 0; !rc && f < nwfs; f++) {
        const double *s = slopes + f * p->mcols;
        for (size_t k = 0; k < p->mcols; k++) p->macc[k] += s[k];
        p->mexp++;
    }
    return rc;
}

int swfs_pipeline_flat_halo(swfs_pipeline *p, swfs_complex *out)
{
    double *zero = calloc(p->info.nslopes + 2, sizeof *zero);
    if (!zero) return swfs_fail(SWFS_ERR_NOMEM, "pipeline: out of memory");
    int rc = swfs_engine_add_wfs(p->engine, zero, 1.0);
    if (!rc) rc = swfs_engine_end_exposure(p->engine, out);
    if (!rc) band_apply(p, out, 1);
    free(zero);
    return rc;
}

void swfs_pipeline_get_info(const swfs_pipeline *p, swfs_pipeline_info *info) { *info = p->info; }
const swfs_recon *swfs_pipeline_recon(const swfs_pipeline *p) { return p->model ? p->model->recon : NULL; }
const swfs_recon *swfs_pipeline_linear_map(const swfs_pipeline *p) { return p->lin_map; }
const swfs_speckle_model *swfs_pipeline_model(const swfs_pipeline *p) { return p->model; }
const double *swfs_pipeline_mask(const swfs_pipeline *p) { return p->mask; }
const double *swfs_pipeline_tilt_rows(const swfs_pipeline *p) { return p->Rtilt; }
const swfs_pipeline_options *swfs_pipeline_opts(const swfs_pipeline *p) { return &p->opt; }

/* Speckle-cube helpers around the engine (see speckles.h). */
#include "specklewfs/speckles.h"
#include "specklewfs/interp.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <stdlib.h>
#include <string.h>

int swfs_speckles_subtract_static(swfs_cplx *halo, const size_t *first, const size_t *n, size_t ncubes, int mode)
{
    size_t np = halo->nx * halo->ny, nz = halo->nz;
    for (size_t c = 0; c < ncubes; c++)
        if (first[c] + n[c] > nz || n[c] == 0)
            return swfs_fail(SWFS_ERR_SHAPE, "speckles: cube %zu (frames %zu..%zu) is empty or outside the %zu frames", c,
                             first[c], first[c] + n[c], nz);
    double complex *m = calloc(np, sizeof *m);
    if (!m) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (mode == SWFS_MEAN_CUBE) {
        for (size_t c = 0; c < ncubes; c++) {
            memset(m, 0, np * sizeof *m);
            for (size_t k = first[c]; k < first[c] + n[c]; k++) {
                const double complex *h = swfs_cplx_frame(halo, k);
                for (size_t i = 0; i < np; i++) m[i] += h[i];
            }
            for (size_t i = 0; i < np; i++) m[i] /= (double)n[c];
            for (size_t k = first[c]; k < first[c] + n[c]; k++) {
                double complex *h = swfs_cplx_frame(halo, k);
                for (size_t i = 0; i < np; i++) h[i] -= m[i];
            }
        }
    } else {
        size_t tot = 0;
        for (size_t c = 0; c < ncubes; c++)
            for (size_t k = first[c]; k < first[c] + n[c]; k++, tot++) {
                const double complex *h = swfs_cplx_frame(halo, k);
                for (size_t i = 0; i < np; i++) m[i] += h[i];
            }
        for (size_t i = 0; i < np; i++) m[i] /= (double)tot;
        for (size_t c = 0; c < ncubes; c++)
            for (size_t k = first[c]; k < first[c] + n[c]; k++) {
                double complex *h = swfs_cplx_frame(halo, k);
                for (size_t i = 0; i < np; i++) h[i] -= m[i];
            }
    }
    free(m);
    return SWFS_OK;
}

void swfs_speckle_model_free(swfs_speckle_model *m)
{
    if (!m) return;
    free(m->mask);
    swfs_sparse_free(m->T);
    swfs_shwfs_free(m->wfs);
    swfs_recon_free(m->recon);
    free(m);
}

int swfs_speckle_model_create(swfs_speckle_model **out, const double *xy, size_t nact, const double *mask,
                              size_t npup, double pupdx, double teldiam, size_t nsub, const swfs_recon *recon,
                              double rcond, size_t max_modes, int remove_tiptilt)
{
    *out = NULL;
    size_t ng = npup * npup;
    swfs_speckle_model *m = calloc(1, sizeof *m);
    if (!m) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    m->npup = npup; m->nact = nact; m->nslopes = 2 * nsub * nsub;
    m->mask = malloc(ng * sizeof *m->mask);
    if (!m->mask) { swfs_speckle_model_free(m); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    memcpy(m->mask, mask, ng * sizeof *mask);
    int rc;
    if ((rc = swfs_interp_ct_grid(xy, nact, npup, pupdx, mask, &m->T, &m->n_outside))) goto fail;
    if ((rc = swfs_shwfs_create(&m->wfs, nsub, teldiam, mask, npup, pupdx, 0.5))) goto fail;
    if (recon) {
        if (recon->nact != nact || recon->nslopes != m->nslopes) {
            rc = swfs_fail(SWFS_ERR_SHAPE, "reconstructor is %zu actuators x %zu slopes but the geometry has %zu actuators "
                           "and %zu slopes (%zu x %zu subapertures)", recon->nact, recon->nslopes, nact, m->nslopes, nsub, nsub);
            goto fail;
        }
        m->recon = calloc(1, sizeof *m->recon);
        if (m->recon) m->recon->W = malloc(nact * m->nslopes * sizeof *m->recon->W);
        if (!m->recon || !m->recon->W) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto fail; }
        m->recon->nact = nact; m->recon->nslopes = m->nslopes; m->recon->nmodes = recon->nmodes;
        memcpy(m->recon->W, recon->W, nact * m->nslopes * sizeof *recon->W);
    } else {
        double *D = NULL;
        if ((rc = swfs_interaction_matrix(m->wfs, m->T, &D))) goto fail;
        rc = swfs_recon_svd(D, m->nslopes, nact, rcond, max_modes, &m->recon);
        free(D);
        if (rc) goto fail;
    }
    if (remove_tiptilt && (rc = swfs_recon_project_tiptilt(m->recon, m->wfs->valid))) goto fail;
    *out = m;
    return SWFS_OK;
fail:
    swfs_speckle_model_free(m);
    return rc;
}

int swfs_speckles_recon_tilt(const swfs_recon *recon, const double *xy, double **W_ext)
{
    *W_ext = NULL;
    size_t na = recon->nact, ns = recon->nslopes, ne = ns + 2;
    double *w = malloc(na * ne * sizeof *w);
    if (!w) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t a = 0; a < na; a++) {
        memcpy(w + a * ne, recon->W + a * ns, ns * sizeof *w);
        w[a * ne + ns] = xy[2 * a];
        w[a * ne + ns + 1] = xy[2 * a + 1];
    }
    *W_ext = w;
    return SWFS_OK;
}

size_t swfs_speckles_expand_frames(const swfs_exposure *sched, size_t nexp)
{
    size_t n = 0;
    for (size_t j = 0; j < nexp; j++) n += sched[j].count;
    return n;
}

int swfs_speckles_expand(const double *slopes, size_t nslopes, size_t nwfs, const unsigned char *valid,
                         const swfs_exposure *sched, size_t nexp, double *out, swfs_exposure *sched_out)
{
    const size_t ne = nslopes + 2;
    size_t k = 0;
    for (size_t j = 0; j < nexp; j++) {
        const swfs_exposure *x = sched + j;
        if (x->count == 0 || x->first + x->count > nwfs)
            return swfs_fail(SWFS_ERR_VALUE, "speckles: exposure %zu needs WFS frames %zu..%zu of %zu", j, x->first,
                             x->first + x->count, nwfs);
        double sw = 0, tx = 0, ty = 0;
        for (size_t r = 0; r < x->count; r++) {
            double w = r == 0 ? x->w_first : (r + 1 == x->count ? x->w_last : 1.0), mx, my;
            swfs_slopes_mean_xy(slopes + (x->first + r) * nslopes, nslopes, 1, valid, &mx, &my);
            double *o = out + (k + r) * ne;
            memcpy(o, slopes + (x->first + r) * nslopes, nslopes * sizeof *o);
            o[nslopes] = mx;
            o[nslopes + 1] = my;
            sw += w; tx += w * mx; ty += w * my;
        }
        if (sw > 0) { tx /= sw; ty /= sw; }
        for (size_t r = 0; r < x->count; r++) {
            out[(k + r) * ne + nslopes] -= tx;
            out[(k + r) * ne + nslopes + 1] -= ty;
        }
        sched_out[j] = (swfs_exposure){k, x->count, x->w_first, x->w_last};
        k += x->count;
    }
    return SWFS_OK;
}

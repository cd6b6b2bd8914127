/* Speckle-cube helpers around the engine (see speckles.h). */
#include "specklewfs/speckles.h"
#include "specklewfs/interp.h"
#include "specklewfs/status.h"

#include <math.h>
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
    return swfs_speckle_model_create_valid(out, xy, nact, mask, npup, pupdx, teldiam, nsub, NULL, recon, rcond,
                                           max_modes, remove_tiptilt);
}

int swfs_speckle_model_create_valid(swfs_speckle_model **out, const double *xy, size_t nact, const double *mask,
                                    size_t npup, double pupdx, double teldiam, size_t nsub, const unsigned char *valid,
                                    const swfs_recon *recon, double rcond, size_t max_modes, int remove_tiptilt)
{
    *out = NULL;
    size_t ng = npup * npup;
    swfs_speckle_model *m = calloc(1, sizeof *m);
    if (!m) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    m->npup = npup; m->nact = nact; m->pupdx = pupdx; m->nslopes = 2 * nsub * nsub;
    m->mask = malloc(ng * sizeof *m->mask);
    if (!m->mask) { swfs_speckle_model_free(m); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    memcpy(m->mask, mask, ng * sizeof *mask);
    int rc;
    if ((rc = swfs_interp_ct_grid(xy, nact, npup, pupdx, mask, &m->T, &m->n_outside))) goto fail;
    if (m->n_outside) {
        /* Illuminated samples outside the actuators' hull (a rim the outer ring does not
         * quite reach) continue the wavefront of the nearest sample inside, within one
         * actuator pitch; farther out the actuators do not describe the pupil. */
        const double pitch = swfs_points_pitch(xy, nact);
        size_t next = 0, nfar = 0;
        if ((rc = swfs_interp_extend_rim(&m->T, npup, pupdx, mask, pitch, &next, &nfar))) goto fail;
        if (nfar) {
            rc = swfs_fail(SWFS_ERR_VALUE, "%zu of the %zu illuminated pupil samples outside the actuators' hull lie more "
                           "than one actuator pitch (%.3g m) from it: the actuator positions do not cover the pupil "
                           "(units, a partial list, or the DM's registration?)", nfar, m->n_outside, pitch);
            goto fail;
        }
    }
    if ((rc = swfs_shwfs_create_valid(&m->wfs, nsub, teldiam, mask, npup, pupdx, valid))) goto fail;
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

int swfs_speckle_model_set_map(swfs_speckle_model *m, const double *slopes, size_t nframes, double noise_var,
                               int remove_tiptilt)
{
    double *D = NULL;
    swfs_recon *r = NULL;
    int rc = swfs_interaction_matrix(m->wfs, m->T, &D);
    if (!rc) rc = swfs_recon_map(D, m->nslopes, m->nact, slopes, nframes, noise_var, &r);
    free(D);
    if (!rc && remove_tiptilt) rc = swfs_recon_project_tiptilt(r, m->wfs->valid);
    if (rc) { swfs_recon_free(r); return rc; }
    swfs_recon_free(m->recon);
    m->recon = r;
    return SWFS_OK;
}

int swfs_speckle_model_set_vk(swfs_speckle_model *m, const double *xy, double L0, const double *slopes, size_t nframes,
                              double noise_var, int remove_tiptilt)
{
    double *D = NULL;
    swfs_recon *r = NULL;
    int rc = swfs_interaction_matrix(m->wfs, m->T, &D);
    if (!rc) rc = swfs_recon_vk(D, m->nslopes, m->nact, xy, L0, slopes, nframes, noise_var, &r);
    free(D);
    if (!rc && remove_tiptilt) rc = swfs_recon_project_tiptilt(r, m->wfs->valid);
    if (rc) { swfs_recon_free(r); return rc; }
    swfs_recon_free(m->recon);
    m->recon = r;
    return SWFS_OK;
}

int swfs_ztilt_functionals(const double *mask, size_t np, double pupdx, double *f)
{
    /* The least-squares fit p + cx x + cy y over the illuminated samples (the Z-tilt, as
     * the simulator's ideal speckles and a peak-registered frame have it): c = G^-1 b with
     * G the 3 x 3 normal matrix of (1, x, y), so the tilt of a grid phase z is the linear
     * functional f_x . z, f_y . z. */
    const size_t ng = np * np;
    double G[3][3] = {{0}}, Gi[3][3];
    for (size_t q = 0; q < np; q++)
        for (size_t i = 0; i < np; i++) {
            if (!(mask[q * np + i] > 0)) continue;
            double v[3] = {1, ((double)i - 0.5 * (double)(np - 1)) * pupdx, ((double)q - 0.5 * (double)(np - 1)) * pupdx};
            for (int r = 0; r < 3; r++)
                for (int c = 0; c < 3; c++) G[r][c] += v[r] * v[c];
        }
    double det = G[0][0] * (G[1][1] * G[2][2] - G[1][2] * G[2][1]) - G[0][1] * (G[1][0] * G[2][2] - G[1][2] * G[2][0]) +
                 G[0][2] * (G[1][0] * G[2][1] - G[1][1] * G[2][0]);
    if (!(fabs(det) > 0)) return swfs_fail(SWFS_ERR_VALUE, "speckles: the pupil has too few illuminated samples for a tilt fit");
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            int r1 = (c + 1) % 3, r2 = (c + 2) % 3, c1 = (r + 1) % 3, c2 = (r + 2) % 3;
            Gi[r][c] = (G[r1][c1] * G[r2][c2] - G[r1][c2] * G[r2][c1]) / det;
        }
    for (size_t q = 0; q < np; q++)
        for (size_t i = 0; i < np; i++) {
            const size_t k = q * np + i;
            const double x = ((double)i - 0.5 * (double)(np - 1)) * pupdx, y = ((double)q - 0.5 * (double)(np - 1)) * pupdx;
            const int in = mask[k] > 0;
            for (int t = 0; t < 2; t++) f[(size_t)t * ng + k] = in ? Gi[t + 1][0] + Gi[t + 1][1] * x + Gi[t + 1][2] * y : 0.0;
        }
    return SWFS_OK;
}

int swfs_speckles_recon_tilt(const swfs_speckle_model *m, const double *xy, double **W_ext, double **R_out)
{
    *W_ext = NULL;
    if (R_out) *R_out = NULL;
    const swfs_recon *recon = m->recon;
    const size_t na = recon->nact, ns = recon->nslopes, ne = ns + 2, np = m->npup, ng = np * np;
    double *w = malloc(na * ne * sizeof *w), *R = calloc(2 * ns, sizeof *R), *F = calloc(2 * na, sizeof *F);
    double *e = calloc(na, sizeof *e), *z = malloc(ng * sizeof *z), *f = malloc(2 * ng * sizeof *f);
    int rc = w && R && F && e && z && f ? swfs_ztilt_functionals(m->mask, np, m->pupdx, f)
                                        : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (rc) {
        free(w); free(R); free(F); free(e); free(z); free(f);
        return rc;
    }
    /* F (2 x nact): the tilt of T e_a for every actuator a (nact sparse applies, once). */
    for (size_t a = 0; a < na; a++) {
        e[a] = 1;
        swfs_sparse_apply(m->T, e, z);
        e[a] = 0;
        for (size_t k = 0; k < ng; k++)
            if (z[k] != 0)
                for (int t = 0; t < 2; t++) F[(size_t)t * na + a] += f[(size_t)t * ng + k] * z[k];
    }
    free(f);
    /* The tilt columns: the actuator coordinates, whose interpolation is the exact plane
     * inside the hull; A = F [x_a y_a] is then the identity, and A^-1 keeps a unit extra
     * value a unit tilt even with samples outside the hull. */
    double A[2][2] = {{0, 0}, {0, 0}};
    for (size_t a = 0; a < na; a++)
        for (int t = 0; t < 2; t++) { A[t][0] += F[(size_t)t * na + a] * xy[2 * a]; A[t][1] += F[(size_t)t * na + a] * xy[2 * a + 1]; }
    double dA = A[0][0] * A[1][1] - A[0][1] * A[1][0];
    if (!(fabs(dA) > 0)) {
        free(w); free(R); free(F); free(e); free(z);
        return swfs_fail(SWFS_ERR_VALUE, "speckles: the actuators' tilts are degenerate on the pupil");
    }
    const double Ai[2][2] = {{A[1][1] / dA, -A[0][1] / dA}, {-A[1][0] / dA, A[0][0] / dA}};
    /* R = F W: the tilt of the reconstructed wavefront as a function of the slopes. */
    for (size_t a = 0; a < na; a++)
        for (int t = 0; t < 2; t++) {
            double fa = F[(size_t)t * na + a];
            if (fa == 0) continue;
            for (size_t s = 0; s < ns; s++) R[(size_t)t * ns + s] += fa * recon->W[a * ns + s];
        }
    /* W_ext = [W - C R | C] with C = [x_a y_a] A^-1: the first block reconstructs no tilt,
     * the two columns add exactly the tilt they are given. */
    for (size_t a = 0; a < na; a++) {
        double cx = xy[2 * a] * Ai[0][0] + xy[2 * a + 1] * Ai[1][0], cy = xy[2 * a] * Ai[0][1] + xy[2 * a + 1] * Ai[1][1];
        for (size_t s = 0; s < ns; s++) w[a * ne + s] = recon->W[a * ns + s] - cx * R[s] - cy * R[ns + s];
        w[a * ne + ns] = cx;
        w[a * ne + ns + 1] = cy;
    }
    free(F); free(e); free(z);
    *W_ext = w;
    if (R_out) *R_out = R;
    else free(R);
    return SWFS_OK;
}

size_t swfs_speckles_expand_frames(const swfs_exposure *sched, size_t nexp)
{
    size_t n = 0;
    for (size_t j = 0; j < nexp; j++) n += sched[j].count;
    return n;
}

int swfs_speckles_expand(const double *slopes, size_t nslopes, size_t nwfs, const double *R,
                         const swfs_exposure *sched, size_t nexp, double *out, swfs_exposure *sched_out)
{
    const size_t ne = nslopes + 2;
    size_t k = 0;
    for (size_t j = 0; j < nexp; j++) {
        const swfs_exposure *x = sched + j;
        if (x->count == 0 || x->first >= nwfs || x->count > nwfs - x->first) /* (no sum that could wrap) */
            return swfs_fail(SWFS_ERR_VALUE, "speckles: exposure %zu needs %zu WFS frames from frame %zu of %zu", j,
                             x->count, x->first, nwfs);
        double sw = 0, tx = 0, ty = 0;
        for (size_t r = 0; r < x->count; r++) {
            double w = r == 0 ? x->w_first : (r + 1 == x->count ? x->w_last : 1.0), mx = 0, my = 0;
            const double *s = slopes + (x->first + r) * nslopes;
            for (size_t i = 0; i < nslopes; i++) { mx += R[i] * s[i]; my += R[nslopes + i] * s[i]; }
            double *o = out + (k + r) * ne;
            memcpy(o, s, nslopes * sizeof *o);
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

const char *swfs_tiptilt_name(int mode)
{
    switch (mode) {
    case SWFS_TT_EXPOSURE: return "exposure";
    case SWFS_TT_FRAME: return "frame";
    case SWFS_TT_KEEP: return "keep";
    default: return "unknown";
    }
}

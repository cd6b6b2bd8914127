/* The time-series simulation's telemetry in the modal form of cacao-based systems: see
 * swfs_ts_export_modal in include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/source.h"
#include "specklewfs/table.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wfs.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

typedef struct exp_work {
    double *xy, *train, *Vinv, *Q, *cube, *rms, *qx, *qy;
    size_t nact, nfiles, ntrain, nslopes, nk, gx, gy;
    swfs_pipeline *p;
    double *modes;
    swfs_sparse *Tq;
} exp_work;

static void exp_free(exp_work *w)
{
    free(w->xy); free(w->train); free(w->Vinv); free(w->Q); free(w->cube); free(w->rms); free(w->qx); free(w->qy);
    free(w->modes);
    swfs_pipeline_free(w->p);
    swfs_sparse_free(w->Tq);
}

/* Every slopes_NNN.fits of the folder, concatenated (the vk reconstructor's training). */
static int load_slopes(const char *dir, exp_work *w)
{
    char path[4200];
    for (;; w->nfiles++) {
        struct stat st;
        snprintf(path, sizeof path, "%s/slopes_%03zu.fits", dir, w->nfiles);
        if (stat(path, &st)) break;
        swfs_real *s = NULL;
        int rc = swfs_telemetry_read(path, w->nslopes, &s, NULL);
        if (rc) return rc;
        w->nslopes = s->nx;
        double *t = realloc(w->train, (w->ntrain + s->ny) * s->nx * sizeof *t);
        if (!t) { swfs_real_free(s); return swfs_fail(SWFS_ERR_NOMEM, "export: out of memory"); }
        w->train = t;
        memcpy(t + w->ntrain * s->nx, s->data, s->nx * s->ny * sizeof *t);
        w->ntrain += s->ny;
        swfs_real_free(s);
    }
    if (!w->nfiles) return swfs_fail(SWFS_ERR_IO, "%s: no slopes_000.fits to export", dir);
    return SWFS_OK;
}

/* Q ((nact-1) x nslopes): the coefficients of the DM's modes 1.. (piston dropped) of the
 * default speckle reconstructor's wavefront, V^-1 W without V^-1's first row. */
static int modal_reconstructor(const swfs_geom *g, exp_work *w, const unsigned char *valid, size_t valid_nsub)
{
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.tiptilt = SWFS_TT_KEEP;
    o.valid = valid; /* the simulation's own map (timeseries valid = FILE), or NULL: the half-lit rule */
    o.valid_nsub = valid_nsub;
    int rc = swfs_pipeline_create(&w->p, g, 8, 8, w->xy, w->nact, NULL, w->nslopes, NULL, w->train, w->ntrain, &o);
    if (rc) return rc;
    const swfs_speckle_model *m = swfs_pipeline_model(w->p);
    if ((rc = swfs_dm_modes(m->T, m->mask, m->npup, &w->modes))) return rc;
    const size_t na = w->nact, ns = w->nslopes;
    lapack_int *ipiv = malloc(na * sizeof *ipiv);
    w->Vinv = malloc(na * na * sizeof *w->Vinv);
    w->Q = calloc((na - 1) * ns, sizeof *w->Q);
    if (!ipiv || !w->Vinv || !w->Q) { free(ipiv); return swfs_fail(SWFS_ERR_NOMEM, "export: out of memory"); }
    memcpy(w->Vinv, w->modes, na * na * sizeof *w->Vinv);
    lapack_int info = LAPACKE_dgetrf(LAPACK_ROW_MAJOR, (lapack_int)na, (lapack_int)na, w->Vinv, (lapack_int)na, ipiv);
    if (!info) info = LAPACKE_dgetri(LAPACK_ROW_MAJOR, (lapack_int)na, w->Vinv, (lapack_int)na, ipiv);
    free(ipiv);
    if (info) return swfs_fail(SWFS_ERR_NUMERIC, "export: the DM's modes are singular (LAPACK info %d)", (int)info);
    const double *W = swfs_pipeline_recon(w->p)->W;
    for (size_t k = 1; k < na; k++)
        for (size_t a = 0; a < na; a++) {
            const double v = w->Vinv[k * na + a];
            for (size_t s = 0; s < ns; s++) w->Q[(k - 1) * ns + s] += v * W[a * ns + s];
        }
    w->nk = na - 1;
    return SWFS_OK;
}

/* The mode surfaces on a DM grid (a quarter of the actuator pitch, rotated and mirrored on the
 * pupil), each normalized to unit rms over the grid points inside the actuators' hull. */
static int mode_cube(const swfs_geom *g, const swfs_dm_registration *reg, exp_work *w)
{
    const double R = g->teldiam / 2 + 2 * reg->pitch;
    w->gx = w->gy = 2 * (size_t)ceil(R / reg->pitch) + 1;
    const size_t nq = w->gx * w->gy, na = w->nact;
    w->qx = malloc(nq * sizeof *w->qx);
    w->qy = malloc(nq * sizeof *w->qy);
    w->cube = calloc(nq * w->nk, sizeof *w->cube);
    w->rms = calloc(w->nk, sizeof *w->rms);
    if (!w->qx || !w->qy || !w->cube || !w->rms) return swfs_fail(SWFS_ERR_NOMEM, "export: out of memory");
    for (size_t j = 0; j < w->gy; j++)
        for (size_t i = 0; i < w->gx; i++)
            swfs_dm_to_pupil(reg, w->gx, w->gy, (double)i, (double)j, w->qx + j * w->gx + i, w->qy + j * w->gx + i);
    size_t nout = 0;
    int rc = swfs_interp_ct_points(w->xy, na, w->qx, w->qy, nq, &w->Tq, &nout);
    if (rc) return rc;
    double *v = malloc(na * sizeof *v), *s = malloc(nq * sizeof *s);
    if (!v || !s) { free(v); free(s); return swfs_fail(SWFS_ERR_NOMEM, "export: out of memory"); }
    for (size_t k = 0; k < w->nk; k++) {
        for (size_t a = 0; a < na; a++) v[a] = w->modes[a * na + k + 1];
        swfs_sparse_apply(w->Tq, v, s);
        double ss = 0;
        size_t n = 0;
        for (size_t q = 0; q < nq; q++)
            if (w->Tq->row_ptr[q + 1] > w->Tq->row_ptr[q]) { ss += s[q] * s[q]; n++; }
        w->rms[k] = n ? sqrt(ss / (double)n) : 0;
        for (size_t q = 0; q < nq && w->rms[k] > 0; q++) w->cube[k * nq + q] = s[q] / w->rms[k];
    }
    free(v);
    free(s);
    return SWFS_OK;
}

/* modal_NNN.fits: per WFS frame the coefficients in um of DM surface (cacao's units: a
 * coefficient a on the unit-rms mode is a wavefront of 2 a um times the mode). */
static int write_modal(const char *dir, exp_work *w, const char *const *prov, size_t nprov)
{
    char path[4200];
    size_t f0 = 0;
    const size_t ns = w->nslopes, nk = w->nk;
    int rc = SWFS_OK;
    for (size_t f = 0; f < w->nfiles && !rc; f++) {
        snprintf(path, sizeof path, "%s/slopes_%03zu.fits", dir, f);
        double rate = 0;
        swfs_real *s = NULL;
        if ((rc = swfs_telemetry_read(path, ns, &s, &rate))) break;
        swfs_real *c = swfs_real_alloc(nk, s->ny, 1);
        if (!c) { swfs_real_free(s); return swfs_fail(SWFS_ERR_NOMEM, "export: out of memory"); }
        for (size_t t = 0; t < s->ny; t++)
            for (size_t k = 0; k < nk; k++) {
                double a = 0;
                for (size_t i = 0; i < ns; i++) a += w->Q[k * ns + i] * s->data[t * ns + i];
                c->data[t * nk + k] = a * w->rms[k] / 2 * 1e6;
            }
        snprintf(path, sizeof path, "%s/modal_%03zu.fits", dir, f);
        swfs_fits_out *o = NULL;
        if (!(rc = swfs_fits_out_create(&o, path))) {
            if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, c, -32)) ||
                (rc = swfs_fits_out_key_string(o, "BUNIT", "um", "DM surface on the unit-rms modes of dm_modes.fits")) ||
                (rc = swfs_fits_out_key_double(o, "WFSRATE", rate, "[Hz]")) ||
                (rc = swfs_fits_out_key_long(o, "FRAME0", (long)f0, "global WFS frame of row 0")))
                swfs_fits_out_abort(o);
            else rc = swfs_fits_out_commit(o);
        }
        /* the same frames as valid-only slopes (x of the valid subapertures, then y) */
        const swfs_shwfs *wfs = swfs_pipeline_model(w->p)->wfs;
        const size_t n2 = wfs->nsub * wfs->nsub, nv = wfs->nvalid;
        swfs_real *vs = rc ? NULL : swfs_real_alloc(2 * nv, s->ny, 1);
        if (!rc && !vs) rc = swfs_fail(SWFS_ERR_NOMEM, "export: out of memory");
        for (size_t t = 0; !rc && t < s->ny; t++)
            for (size_t a = 0, j = 0; a < n2; a++)
                if (wfs->valid[a]) {
                    vs->data[t * 2 * nv + j] = s->data[t * ns + a];
                    vs->data[t * 2 * nv + nv + j++] = s->data[t * ns + n2 + a];
                }
        snprintf(path, sizeof path, "%s/slopes_valid_%03zu.fits", dir, f);
        if (!rc && !(rc = swfs_fits_out_create(&o, path))) {
            if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, vs, -32)) ||
                (rc = swfs_fits_out_key_string(o, "BUNIT", "rad", "x then y slopes of the valid subapertures")) ||
                (rc = swfs_fits_out_key_double(o, "WFSRATE", rate, "[Hz]")) ||
                (rc = swfs_fits_out_key_long(o, "FRAME0", (long)f0, "global WFS frame of row 0")))
                swfs_fits_out_abort(o);
            else rc = swfs_fits_out_commit(o);
        }
        swfs_real_free(vs);
        f0 += s->ny;
        swfs_real_free(s);
        swfs_real_free(c);
    }
    return rc;
}

/* control.fits (the default speckle reconstructor on the valid slopes: NAXIS1 = 2 nvalid,
 * NAXIS2 = nact), influence.fits (each actuator's influence on the pupil grid, the
 * Clough-Tocher interpolation of a unit value: PUPN x PUPN x nact), valid.fits (the
 * valid-subaperture map of the slopes_valid files, nsub x nsub, 1 = used) and cm_modes.fits
 * (the modal control matrix that made modal_NNN.fits from the valid slopes: NAXIS1 = 2 nvalid,
 * NAXIS2 = the modes; `modal-slopes --cm` takes it) and rm_modes.fits (the modal response
 * matrix: each mode's valid slopes per um of coefficient, what poking the modes on the DM and
 * reading the WFS gives, NAXIS1 = the modes, NAXIS2 = 2 nvalid; `modal-slopes --imat`). */
static int write_control(const char *dir, exp_work *w, const char *const *prov, size_t nprov)
{
    const swfs_speckle_model *m = swfs_pipeline_model(w->p);
    const swfs_shwfs *wfs = m->wfs;
    const size_t n2 = wfs->nsub * wfs->nsub, nv = wfs->nvalid, na = w->nact, ns = w->nslopes, ng = m->npup * m->npup;
    const double *W = swfs_pipeline_recon(w->p)->W;
    swfs_real *C = swfs_real_alloc(2 * nv, na, 1), *F = swfs_real_alloc(m->npup, m->npup, na);
    swfs_real *V = swfs_real_alloc(wfs->nsub, wfs->nsub, 1);
    double *e = calloc(na, sizeof *e), *z = malloc(ng * sizeof *z);
    int rc = C && F && V && e && z ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "export: out of memory");
    for (size_t a = 0; !rc && a < n2; a++) V->data[a] = wfs->valid[a] ? 1.0 : 0.0;
    for (size_t r = 0; !rc && r < na; r++)
        for (size_t a = 0, j = 0; a < n2; a++)
            if (wfs->valid[a]) {
                C->data[r * 2 * nv + j] = W[r * ns + a];
                C->data[r * 2 * nv + nv + j++] = W[r * ns + n2 + a];
            }
    for (size_t a = 0; !rc && a < na; a++) {
        e[a] = 1;
        swfs_sparse_apply(m->T, e, z);
        e[a] = 0;
        memcpy(F->data + a * ng, z, ng * sizeof *z);
    }
    /* cm_modes.fits: the modal control matrix, valid slopes -> modal_NNN's coefficients (um):
     * Q's valid columns scaled as write_modal scales the coefficients (cacao's CMmodesWFS) */
    swfs_real *M = rc ? NULL : swfs_real_alloc(2 * nv, w->nk, 1);
    if (!rc && !M) rc = swfs_fail(SWFS_ERR_NOMEM, "export: out of memory");
    for (size_t k = 0; !rc && k < w->nk; k++)
        for (size_t a = 0, j = 0; a < n2; a++)
            if (wfs->valid[a]) {
                const double f = w->rms[k] / 2 * 1e6;
                M->data[k * 2 * nv + j] = f * w->Q[k * ns + a];
                M->data[k * 2 * nv + nv + j++] = f * w->Q[k * ns + n2 + a];
            }
    /* rm_modes.fits: D (S T: the model's slopes of each actuator's influence) times each mode's
     * actuator vector at a coefficient of 1 um (2 um of wavefront over the mode's rms) */
    double *D = NULL, *DV = NULL;
    swfs_real *R = rc ? NULL : swfs_real_alloc(w->nk, 2 * nv, 1);
    if (!rc && (!R || !(DV = malloc(ns * na * sizeof *DV)))) rc = swfs_fail(SWFS_ERR_NOMEM, "export: out of memory");
    if (!rc) rc = swfs_interaction_matrix(wfs, m->T, &D);
    if (!rc) /* D V: every slope's response to every mode (column k + 1: mode k of the export) */
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)ns, (int)na, (int)na, 1.0, D, (int)na, w->modes,
                    (int)na, 0.0, DV, (int)na);
    for (size_t a = 0, j = 0; !rc && a < n2; a++)
        if (wfs->valid[a]) {
            for (size_t k = 0; k < w->nk; k++) {
                const double f = w->rms[k] > 0 ? 2e-6 / w->rms[k] : 0; /* a mode off the grid: no coefficient */
                R->data[j * w->nk + k] = DV[a * na + k + 1] * f;
                R->data[(nv + j) * w->nk + k] = DV[(n2 + a) * na + k + 1] * f;
            }
            j++;
        }
    free(D);
    free(DV);
    char path[4200];
    const swfs_real *arr[5] = {C, F, V, M, R};
    const char *names[5] = {"control.fits", "influence.fits", "valid.fits", "cm_modes.fits", "rm_modes.fits"};
    const char *units[5] = {"m/rad", "m/m", "", "um/rad", "rad/um"};
    for (int k = 0; k < 5 && !rc; k++) {
        swfs_fits_out *o = NULL;
        snprintf(path, sizeof path, "%s/%s", dir, names[k]);
        if ((rc = swfs_fits_out_create(&o, path))) break;
        if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) ||
            (rc = swfs_fits_out_real(o, NULL, arr[k], k == 2 ? 8 : -64)) ||
            (units[k][0] && (rc = swfs_fits_out_key_string(o, "BUNIT", units[k], NULL))))
            swfs_fits_out_abort(o);
        else rc = swfs_fits_out_commit(o);
    }
    swfs_real_free(C); swfs_real_free(F); swfs_real_free(V); swfs_real_free(M); swfs_real_free(R); free(e); free(z);
    return rc;
}

int swfs_ts_export_modal(const struct swfs_ts_params *p, const char *dir, const char *const *prov, size_t nprov,
                         swfs_dm_registration *reg_out, size_t *nmodes)
{
    const swfs_sim_params *b = &p->base;
    const swfs_geom g = {b->wavelen, b->teldiam, b->obscur, b->pixscale, b->pupdx, (long)b->pupn};
    exp_work w;
    memset(&w, 0, sizeof w);
    char path[4200];
    snprintf(path, sizeof path, "%s/actuators.fits", dir);
    int rc = swfs_actuators_read(path, &w.xy, &w.nact);
    if (!rc) rc = load_slopes(dir, &w);
    unsigned char *vmap = NULL;
    size_t vn = 0, nv = 0;
    if (!rc && p->valid[0]) rc = swfs_valid_map_read(p->valid, &vmap, &vn, &nv);
    if (!rc) rc = modal_reconstructor(&g, &w, vmap, vn);
    free(vmap);
    /* A registration a real DM could have: a quarter of the actuator pitch per grid step (half
     * the pitch resampled the highest modes too coarsely: on 24 x 24 the joint fit then landed
     * at 29.3 nm instead of 10.9, docs/telemetry.md), the grid's
     * centre off the pupil's, turned by 10 degrees and mirrored. */
    swfs_dm_registration reg = {swfs_points_pitch(w.xy, w.nact) / 4, 0.03, -0.02, 10 * M_PI / 180, 1};
    if (!rc) rc = mode_cube(&g, &reg, &w);
    if (!rc) rc = write_modal(dir, &w, prov, nprov);
    if (!rc) rc = write_control(dir, &w, prov, nprov);
    if (!rc) {
        swfs_real c = {w.gx, w.gy, w.nk, w.cube};
        swfs_fits_out *o = NULL;
        snprintf(path, sizeof path, "%s/dm_modes.fits", dir);
        if (!(rc = swfs_fits_out_create(&o, path))) {
            if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, &c, -32)) ||
                (rc = swfs_fits_out_key_double(o, "DMPITCH", reg.pitch, "[m] on the pupil per grid step")) ||
                (rc = swfs_fits_out_key_double(o, "DMOFFX", reg.x0, "[m] grid centre on the pupil")) ||
                (rc = swfs_fits_out_key_double(o, "DMOFFY", reg.y0, "[m] grid centre on the pupil")) ||
                (rc = swfs_fits_out_key_double(o, "DMROT", 10.0, "[deg] counter-clockwise")) ||
                (rc = swfs_fits_out_key_long(o, "DMFLIPX", 1, "grid x mirrored before the rotation")))
                swfs_fits_out_abort(o);
            else rc = swfs_fits_out_commit(o);
        }
    }
    if (!rc) {
        *reg_out = reg;
        *nmodes = w.nk;
    }
    exp_free(&w);
    return rc;
}

/* The generic linear speckle model from files: see include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/pupil.h"
#include "specklewfs/sparse.h"
#include "run_internal.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_linear_paths(swfs_paths *p, const swfs_linear_files *lf)
{
    swfs_paths_input(p, "basis (--basis)", lf->basis);
    swfs_paths_input(p, "control matrix (--control)", lf->control);
    swfs_paths_input(p, "interaction matrix (--imat)", lf->imat);
}

void swfs_linear_files_default(swfs_linear_files *lf)
{
    memset(lf, 0, sizeof *lf);
    swfs_dm_registration_default(&lf->reg);
    lf->scale = 1.0;
}

/* Every element of a matrix file finite and below 1e30 in magnitude (a fill value, or a
 * corrupt file: the products through it would overflow), the file and element named. */
static int matrix_values(const char *path, const char *what, const swfs_real *m)
{
    const size_t n = m->nx * m->ny * m->nz;
    char val[48];
    for (size_t q = 0; q < n; q++)
        if (!(fabs(m->data[q]) < 1e30))
            return swfs_fail(SWFS_ERR_VALUE, "%s: element (%zu, %zu%s%.0zu) of the %s %s; expected finite and below "
                             "1e30 in magnitude (a fill value, or a corrupt file?)", path, q % m->nx + 1,
                             q / m->nx % m->ny + 1, m->nz > 1 ? ", " : "", m->nz > 1 ? q / (m->nx * m->ny) + 1 : 0,
                             what, swfs_value_words(m->data[q], val, sizeof val));
    return SWFS_OK;
}

/* A 2-D matrix file of ncols x nrows (either may be 0: taken from the file). */
static int read_matrix(const char *path, const char *what, size_t *ncols, size_t *nrows, swfs_real **m)
{
    int rc = swfs_fits_read_real(path, NULL, m, NULL);
    if (!rc) rc = matrix_values(path, "matrix", *m);
    if (rc) return rc;
    if ((*m)->nz != 1 || (*ncols && (*m)->nx != *ncols) || (*nrows && (*m)->ny != *nrows))
        return swfs_fail(SWFS_ERR_SHAPE, "%s: the %s is %zu x %zu x %zu; expected NAXIS1 = %zu%s, NAXIS2 = %zu%s", path,
                         what, (*m)->nx, (*m)->ny, (*m)->nz, *ncols, *ncols ? "" : " (any)", *nrows,
                         *nrows ? "" : " (any)");
    *ncols = (*m)->nx;
    *nrows = (*m)->ny;
    return SWFS_OK;
}

/* A control matrix file: an image (NAXIS1 = telemetry values per frame, NAXIS2 = basis
 * functions), or a space-time one's cube of them, one plane per lag (NLAGS, LAGk: `learn
 * --lags`, speckles' loops' map), read into lag blocks (nk x nl nm: swfs_slopes_stack's layout of
 * the input). *nm, *nk: expected (0: any), then the file's; *nl its lags (1: per frame). */
static int read_control(const char *path, size_t *nm, size_t *nk, swfs_real **m, long *lags, size_t *nl)
{
    *nl = 1;
    int rc = swfs_fits_read_real(path, NULL, m, NULL);
    if (!rc) rc = matrix_values(path, "control matrix", *m);
    if (rc) return rc;
    const swfs_real *a = *m;
    if ((*nm && a->nx != *nm) || (*nk && a->ny != *nk) || a->nz > SWFS_RECON_MAXLAGS)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: the control matrix (telemetry values x basis functions) is %zu x %zu x %zu; "
                         "expected NAXIS1 = %zu%s, NAXIS2 = %zu%s (and NAXIS3 one plane per lag of a space-time map, at "
                         "most %d)", path, a->nx, a->ny, a->nz, *nm, *nm ? "" : " (any)", *nk, *nk ? "" : " (any)",
                         SWFS_RECON_MAXLAGS);
    if (a->nz > 1) {
        if ((rc = swfs_lags_read(path, a->nz, lags))) return rc;
        swfs_real *b = swfs_real_alloc(a->nz * a->nx, a->ny, 1);
        if (!b) return swfs_fail_context(SWFS_ERR_NOMEM, "%s", path);
        for (size_t k = 0; k < a->nz; k++)
            for (size_t j = 0; j < a->ny; j++)
                memcpy(b->data + j * b->nx + k * a->nx, a->data + (k * a->ny + j) * a->nx, a->nx * sizeof *b->data);
        *nl = a->nz;
        swfs_real_free(*m);
        *m = b;
        *nm = b->nx / *nl;
    } else {
        lags[0] = 0;
        *nm = a->nx;
    }
    *nk = (*m)->ny;
    return SWFS_OK;
}

int swfs_linear_control_lags(const swfs_linear_files *lf, long *lags, size_t *nl)
{
    *nl = 0;
    if (!lf->control) return SWFS_OK;
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, lf->control, NULL);
    const size_t nz = rc ? 0 : swfs_fits_in_shape(f)->nz;
    swfs_fits_in_close(f);
    if (!rc && nz > SWFS_RECON_MAXLAGS)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the control matrix has %zu planes; a space-time one has one per lag, at most %d",
                       lf->control, nz, SWFS_RECON_MAXLAGS);
    if (!rc && nz > 1 && !(rc = swfs_lags_read(lf->control, nz, lags))) *nl = nz;
    return rc;
}

int swfs_points_basis_(const double *xy, size_t n, const swfs_geom *g, const double *mask, swfs_sparse **B)
{
    *B = NULL;
    const size_t np = (size_t)g->pupn;
    size_t nout = 0, next = 0, nfar = 0;
    int rc = swfs_interp_ct_grid(xy, n, np, g->pupdx, mask, B, &nout);
    const double pitch = swfs_points_pitch(xy, n);
    if (!rc && nout) rc = swfs_interp_extend_rim(B, np, g->pupdx, mask, pitch, &next, &nfar);
    if (!rc && nfar)
        rc = swfs_fail(SWFS_ERR_VALUE, "%zu of the %zu illuminated pupil samples outside the output points' hull lie "
                       "more than one pitch (%.3g m) from it: the points do not cover the pupil", nfar, nout, pitch);
    if (rc) {
        swfs_sparse_free(*B);
        *B = NULL;
    }
    return rc;
}

int swfs_points_functions_(const double *xy, size_t n, const swfs_geom *g, const double *mask, double **F)
{
    *F = NULL;
    const size_t n2 = (size_t)g->pupn * (size_t)g->pupn;
    swfs_sparse *B = NULL;
    double *eye = NULL;
    int rc = swfs_points_basis_(xy, n, g, mask, &B);
    if (!rc && (!(eye = calloc(n, sizeof *eye)) || !(*F = malloc(n2 * n * sizeof **F))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory for %zu points' functions", n);
    for (size_t k = 0; !rc && k < n; k++) { /* function k: the interpolation of point k alone */
        eye[k] = 1.0;
        swfs_sparse_apply(B, eye, *F + k * n2);
        eye[k] = 0.0;
    }
    if (rc) {
        free(*F);
        *F = NULL;
    }
    free(eye);
    swfs_sparse_free(B);
    return rc;
}

/* The basis of a control matrix with output points of its own (its file's OUTXY: a map learned
 * on a grid finer than the DM, run_loops_map.c): their interpolation on the pupil grid
 * (swfs_points_basis_), *nk of them; *B NULL where the file has none. */
static int control_points_basis(const char *control, const swfs_geom *g, const double *mask, swfs_sparse **B,
                                size_t *nk)
{
    *B = NULL;
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, control, NULL);
    const int has = !rc && swfs_fits_in_has_ext(f, "OUTXY");
    const size_t n = has ? swfs_fits_in_shape(f)->ny : 0;
    swfs_fits_in_close(f);
    if (rc || !has) {
        swfs_clear_error(); /* the control file itself is read, and named, where it is read as the map */
        return SWFS_OK;
    }
    double *xy = NULL;
    rc = swfs_outxy_read(control, n, &xy);
    if (!rc && xy) rc = swfs_points_basis_(xy, n, g, mask, B);
    if (rc) swfs_fail_context(rc, "%s: the basis on its output points (OUTXY)", control);
    if (!rc && *B) *nk = n;
    free(xy);
    return rc;
}

/* The basis: on the pupil grid, resampled as it is; on a DM grid, in factored form (the
 * grid's interpolation onto the pupil, *shapes = the cube's values at the grid points,
 * gx gy x nk: pipeline.h swfs_linear_input.shapes); a control matrix with output points of its
 * own, their interpolation (that map writes the wavefront there, not on the basis given). *nk:
 * the basis functions. */
static int load_basis(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, swfs_sparse **B,
                      double **shapes, size_t *nk)
{
    if (lf->control) {
        const int prc = control_points_basis(lf->control, g, mask, B, nk);
        if (prc || *B) return prc;
    }
    swfs_real *c = NULL;
    int rc = swfs_fits_read_real(lf->basis, NULL, &c, NULL);
    if (rc) return rc;
    const size_t np = (size_t)g->pupn;
    *nk = c->nz;
    if (!(lf->reg.pitch > 0)) {
        if (c->nx != np || c->ny != np)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the basis is %zu x %zu x %zu but the pupil grid is PUPN = %zu; a basis on "
                           "the DM's own grid needs its registration (--dm-pitch, --dm-offset, --dm-rot, --dm-flip)",
                           lf->basis, c->nx, c->ny, c->nz, np);
        else if ((rc = swfs_basis_from_pupil(B, c->data, np, c->nz, mask))) swfs_fail_context(rc, "%s", lf->basis);
        swfs_real_free(c);
        return rc;
    }
    size_t nout = 0;
    const size_t gn = c->nx * c->ny;
    char val[48];
    for (size_t k = 0; !rc && k < gn * c->nz; k++)
        if (!isfinite(c->data[k]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: value %zu (x %zu, y %zu, function %zu) %s; expected finite", lf->basis, k,
                           k % c->nx, k / c->nx % c->ny, k / gn, swfs_value_words(c->data[k], val, sizeof val));
    if (!rc && (rc = swfs_grid_interp(B, c->nx, c->ny, &lf->reg, mask, np, g->pupdx, &nout)))
        swfs_fail_context(rc, "%s", lf->basis);
    else if (!rc && nout)
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: the registration (pitch %g m, centre %g, %g m, rotation %g deg%s) puts %zu "
                       "illuminated pupil samples more than one grid step beyond the %zu x %zu DM grid: it does not "
                       "describe the pupil (pitch units, offset?)", lf->basis, lf->reg.pitch, lf->reg.x0, lf->reg.y0,
                       lf->reg.rot * 180 / M_PI, lf->reg.flip_x ? ", mirrored in x" : "", nout, c->nx, c->ny);
    if (!rc && !(*shapes = malloc(gn * c->nz * sizeof **shapes))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t q = 0; !rc && q < gn; q++)
        for (size_t k = 0; k < c->nz; k++) (*shapes)[q * c->nz + k] = c->data[k * gn + q];
    swfs_real_free(c);
    return rc;
}

int swfs_linear_wavefront_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, const double *coef,
                           size_t nk, double *out)
{
    const size_t np = (size_t)g->pupn;
    swfs_sparse *B = NULL;
    double *shapes = NULL, *u = NULL;
    size_t n = 0;
    int rc = load_basis(lf, g, mask, &B, &shapes, &n);
    if (!rc && n != nk)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu basis functions, but %zu values to put on them", lf->basis, n, nk);
    if (!rc && shapes) { /* on the DM grid: the grid values, then their interpolation */
        const size_t gn = B->ncols;
        if (!(u = calloc(gn, sizeof *u))) rc = swfs_fail(SWFS_ERR_NOMEM, "linear model: out of memory");
        for (size_t q = 0; !rc && q < gn; q++)
            for (size_t k = 0; k < nk; k++) u[q] += shapes[q * nk + k] * coef[k];
    }
    if (!rc) {
        swfs_sparse_apply(B, shapes ? u : coef, out);
        for (size_t i = 0; i < np * np; i++) out[i] *= lf->scale;
    }
    free(u);
    free(shapes);
    swfs_sparse_free(B);
    return rc;
}

/* lf's basis on the pupil grid, dense (*full: n2 x *k, row-major): the grid's interpolation times
 * the grid values, or the pupil-grid basis applied to the identity (unscaled) */
static int basis_dense(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, double **full, size_t *k)
{
    *full = NULL;
    const size_t np = (size_t)g->pupn, n2 = np * np;
    swfs_sparse *B = NULL;
    double *shapes = NULL, *eye = NULL;
    int rc = load_basis(lf, g, mask, &B, &shapes, k);
    if (!rc && !shapes && !(eye = calloc(*k * *k, sizeof *eye))) rc = swfs_fail(SWFS_ERR_NOMEM, "linear fit: out of memory");
    for (size_t j = 0; eye && j < *k; j++) eye[j * *k + j] = 1.0;
    if (!rc && !(*full = malloc(n2 * *k * sizeof **full))) rc = swfs_fail(SWFS_ERR_NOMEM, "linear fit: out of memory");
    if (!rc) swfs_sparse_apply_multi(B, shapes ? shapes : eye, *full, *k);
    free(eye);
    free(shapes);
    swfs_sparse_free(B);
    return rc;
}

int swfs_linear_functions_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, double **F, size_t *nk)
{
    *F = NULL;
    const size_t n2 = (size_t)g->pupn * (size_t)g->pupn;
    double *full = NULL;
    int rc = basis_dense(lf, g, mask, &full, nk);
    if (!rc && !(*F = malloc(n2 * *nk * sizeof **F))) rc = swfs_fail(SWFS_ERR_NOMEM, "linear model: out of memory");
    for (size_t i = 0; !rc && i < n2; i++)
        for (size_t j = 0; j < *nk; j++) (*F)[j * n2 + i] = lf->scale * full[i * *nk + j];
    free(full);
    return rc;
}

int swfs_linear_fit_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, const double *wf, size_t m,
                     double **coef, size_t *nk, double *resid)
{
    *coef = NULL;
    const size_t np = (size_t)g->pupn, n2 = np * np;
    double *full = NULL, *A = NULL, *G = NULL, *R = NULL, *E = NULL;
    size_t k = 0, nil = 0;
    int rc = basis_dense(lf, g, mask, &full, &k);
    *nk = k;
    for (size_t i = 0; !rc && i < n2; i++) nil += mask[i] > 0;
    if (!rc && !nil) rc = swfs_fail(SWFS_ERR_VALUE, "linear fit: no illuminated pupil sample");
    if (!rc && (!(A = malloc(nil * k * sizeof *A)) || !(E = malloc(nil * m * sizeof *E)) ||
                !(G = calloc(k * k, sizeof *G)) || !(R = calloc(k * m, sizeof *R))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "linear fit: out of memory for %zu samples x %zu functions", nil, k);
    for (size_t i = 0, r = 0; !rc && i < n2; i++) {
        if (!(mask[i] > 0)) continue;
        for (size_t j = 0; j < k; j++) A[r * k + j] = lf->scale * full[i * k + j];
        for (size_t j = 0; j < m; j++) E[r * m + j] = wf[j * n2 + i];
        r++;
    }
    double diag = 0, w2 = 0;
    if (!rc) {
        cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)k, (int)nil, 1.0, A, (int)k, 0.0, G, (int)k);
        cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)k, (int)m, (int)nil, 1.0, A, (int)k, E, (int)m, 0.0, R,
                    (int)m);
        for (size_t j = 0; j < k; j++) diag += G[j * k + j];
        diag /= (double)(k ? k : 1);
        if (!(diag > 0)) rc = swfs_fail(SWFS_ERR_VALUE, "%s: the basis is zero on the pupil", lf->basis);
    }
    if (!rc) {
        for (size_t j = 0; j < k; j++) G[j * k + j] += SWFS_LINEAR_FIT_RIDGE * diag;
        const lapack_int info = LAPACKE_dposv(LAPACK_ROW_MAJOR, 'U', (lapack_int)k, (lapack_int)m, G, (lapack_int)k, R,
                                              (lapack_int)m);
        if (info) rc = swfs_fail(SWFS_ERR_NUMERIC, "%s: the basis's normal equations on the pupil (%zu functions) "
                                 "are not positive definite (LAPACK dposv info %d)", lf->basis, k, (int)info);
    }
    if (!rc && resid) {
        for (size_t i = 0; i < nil * m; i++) w2 += E[i] * E[i];
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nil, (int)m, (int)k, 1.0, A, (int)k, R, (int)m, -1.0,
                    E, (int)m);
        double e2 = 0;
        for (size_t i = 0; i < nil * m; i++) e2 += E[i] * E[i];
        *resid = w2 > 0 ? sqrt(e2 / w2) : 0.0;
    }
    if (!rc) {
        *coef = R;
        R = NULL;
    }
    free(R);
    free(G);
    free(E);
    free(A);
    free(full);
    return rc;
}

int swfs_map_has_meanmiss_(const char *path)
{
    if (!path) return 0;
    swfs_fits_in *f = NULL;
    const int has = !swfs_fits_in_open(&f, path, NULL) && swfs_fits_in_has_ext(f, "MEANMISS");
    swfs_fits_in_close(f);
    swfs_clear_error(); /* a file that cannot be read says so where it is read as the map */
    return has;
}

int swfs_map_meanmiss_attach(swfs_pipeline *p, const char *path, const swfs_linear_files *lin, const swfs_geom *g,
                             double *rms)
{
    *rms = 0;
    if (!swfs_map_has_meanmiss_(path)) return SWFS_OK; /* (the map itself was read by the pipeline) */
    const size_t n = (size_t)g->pupn;
    swfs_real *m = NULL;
    double *map = calloc(n * n, sizeof *map);
    if (!map) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    int rc = swfs_fits_read_real(path, "MEANMISS", &m, NULL);
    const size_t nk = rc ? 0 : m->nx * m->ny * m->nz;
    for (size_t k = 0; !rc && k < nk; k++)
        if (!isfinite(m->data[k])) rc = swfs_fail(SWFS_ERR_VALUE, "%s: MEANMISS value %zu is not finite", path, k);
    const double *mask = swfs_pipeline_mask(p);
    if (!rc && m->ny > 1) { /* an image: the miss on the pupil grid itself (speckles' loops_map) */
        if (m->nx != n || m->ny != n || m->nz != 1)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: MEANMISS is a %zu x %zu x %zu image; expected the pupil grid, %zu x %zu "
                           "(or one value per output)", path, m->nx, m->ny, m->nz, n, n);
        else
            memcpy(map, m->data, n * n * sizeof *map);
    } else if (!rc && lin && lin->basis) {
        rc = swfs_linear_wavefront_(lin, g, mask, m->data, nk, map);
    } else if (!rc) {
        const swfs_speckle_model *mod = swfs_pipeline_model(p);
        if (!mod || mod->T->ncols != nk)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: MEANMISS holds %zu values, but the map's model has %zu outputs", path, nk,
                           mod ? mod->T->ncols : 0);
        else
            swfs_sparse_apply(mod->T, m->data, map);
    }
    if (!rc) rc = swfs_pipeline_set_mean_offset(p, map);
    if (!rc) *rms = swfs_wfe_remove_ptt(map, mask, n);
    swfs_real_free(m);
    free(map);
    if (rc) return swfs_fail_context(rc, "the residual mean's miss that %s was learned with", path);
    return SWFS_OK;
}

int swfs_linear_pipeline(swfs_pipeline **p, const swfs_linear_files *lf, const swfs_geom *g, size_t nfx, size_t nfy,
                         const double *mask, size_t nmeas, const double *train, size_t ntrain,
                         const swfs_pipeline_options *po)
{
    *p = NULL;
    if (!lf->basis) return swfs_fail(SWFS_ERR_ARG, "linear model: no basis file");
    if (lf->control && lf->imat) return swfs_fail(SWFS_ERR_ARG, "linear model: a control matrix or an interaction matrix, not both");
    int rc = swfs_geom_require(g, "linear model");
    if (rc) return rc;
    const size_t np = (size_t)g->pupn;
    double *annulus = NULL;
    if (!mask) {
        if (!(annulus = malloc(np * np * sizeof *annulus))) return swfs_fail(SWFS_ERR_NOMEM, "linear model: out of memory");
        if ((rc = swfs_aperture_make(annulus, np, g->pupdx, g->teldiam, g->obscur, 0, 0))) { free(annulus); return rc; }
        mask = annulus;
    }
    swfs_sparse *B = NULL;
    swfs_real *m = NULL;
    double *shapes = NULL, *stacked = NULL;
    size_t nk = 0, nm = nmeas, nl = 1;
    long lags[SWFS_RECON_MAXLAGS];
    rc = load_basis(lf, g, mask, &B, &shapes, &nk);
    if (!rc && !nmeas) nmeas = nm = lf->control || lf->imat ? 0 : nk; /* taken from the files */
    if (!rc && lf->control) rc = read_control(lf->control, &nm, &nk, &m, lags, &nl);
    if (!rc && lf->imat) rc = read_matrix(lf->imat, "interaction matrix (basis functions x telemetry values)", &nk, &nm, &m);
    if (!rc && !nmeas) nmeas = nm;
    /* a space-time control matrix: its input, and the training frames checked through it, are
     * the values of frames t + lags stacked (swfs_slopes_stack, clamped at the frames' ends) */
    if (!rc && nl > 1 && train && ntrain) {
        if (!(stacked = malloc(ntrain * nl * nmeas * sizeof *stacked)))
            rc = swfs_fail(SWFS_ERR_NOMEM, "linear model: out of memory for %zu stacked training frames", ntrain);
        else {
            swfs_slopes_stack(train, ntrain, nmeas, lags, nl, 0, ntrain, stacked);
            train = stacked;
        }
    }
    if (!rc && !lf->control && !lf->imat && nmeas != nk)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu basis functions but the telemetry has %zu values per frame, taken as their "
                       "coefficients; give the control matrix (--control) or the interaction matrix (--imat) to map "
                       "other telemetry", lf->basis, nk, nmeas);
    if (!rc) {
        swfs_linear_input in = {nl * nmeas, B, lf->control ? m->data : NULL, lf->imat ? m->data : NULL, lf->scale, shapes,
                                shapes ? nk : 0, nl > 1 ? nl : 0};
        rc = swfs_pipeline_create_linear(p, g, nfx, nfy, mask, &in, train, ntrain, po);
        if (rc) swfs_fail_context(rc, "the linear model of %s", lf->basis);
    }
    swfs_real_free(m);
    swfs_sparse_free(B);
    free(shapes);
    free(stacked);
    free(annulus);
    return rc;
}

int swfs_linear_tilt_rows(const swfs_linear_files *lf, const char *science, size_t nmeas, double **R)
{
    *R = NULL;
    swfs_geom g;
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, science, NULL);
    if (!rc) rc = swfs_fits_in_geom(f, &g);
    swfs_fits_in_close(f);
    if (!rc) rc = swfs_geom_require(&g, science);
    if (rc) return rc;
    swfs_pipeline_options po;
    swfs_pipeline_options_default(&po);
    po.recon = SWFS_RECON_SVD; /* an interaction matrix without telemetry to learn from */
    swfs_pipeline *p = NULL;
    if ((rc = swfs_linear_pipeline(&p, lf, &g, 2, 2, NULL, nmeas, NULL, 0, &po))) return rc;
    const double *r = swfs_pipeline_tilt_rows(p);
    swfs_pipeline_info in;
    swfs_pipeline_get_info(p, &in);
    /* a space-time control matrix: its response to a tilt held over its lags, their blocks summed */
    const size_t nl = in.nlags > 1 ? in.nlags : 1;
    if (!(*R = calloc(2 * nmeas, sizeof **R))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t t = 0; !rc && t < 2; t++)
        for (size_t k = 0; k < nl; k++)
            for (size_t i = 0; i < nmeas; i++) (*R)[t * nmeas + i] += r[t * nl * nmeas + k * nmeas + i];
    swfs_pipeline_free(p);
    return rc;
}

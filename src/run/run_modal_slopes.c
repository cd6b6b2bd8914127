/* modal-slopes: a modal system's coefficients turned back into its Shack-Hartmann's slopes,
 * s' = CM+ c (run.h swfs_modal_slopes_run; docs/telemetry.md, "The modal input kind"). */
#include "specklewfs/run.h"
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <cblas.h>
#include <float.h>
#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The input's FRAME0 (absent: none written). */
static int frame0_of(const char *path, long *frame0, int *found)
{
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_long_opt(f, "FRAME0", 0, LONG_MAX, frame0, found);
    swfs_fits_in_close(f);
    return rc;
}

/* CM (coefficients x slopes, from its file, checked) and its pseudo-inverse at the numerical
 * rank (singular values above max(rows, cols) x DBL_EPSILON of the largest). */
static int cm_pinv(const char *path, swfs_real **cm, swfs_recon **pinv)
{
    *pinv = NULL;
    int rc = swfs_fits_read_real(path, NULL, cm, NULL);
    if (!rc && ((*cm)->nz != 1 || (*cm)->nx < 1 || (*cm)->ny < 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the control matrix is %zux%zux%zu; expected slopes x coefficients (2-D)",
                       path, (*cm)->nx, (*cm)->ny, (*cm)->nz);
    for (size_t i = 0; !rc && i < (*cm)->nx * (*cm)->ny; i++)
        if (!isfinite((*cm)->data[i]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: value %zu (coefficient %zu, slope %zu) is not finite", path, i,
                           i / (*cm)->nx, i % (*cm)->nx);
    if (!rc) {
        /* CM+ (slopes x coefficients): swfs_recon_svd inverts a matrix of rows x columns */
        const double tol = (double)((*cm)->nx > (*cm)->ny ? (*cm)->nx : (*cm)->ny) * DBL_EPSILON;
        if ((rc = swfs_recon_svd((*cm)->data, (*cm)->ny, (*cm)->nx, tol, 0, pinv))) rc = swfs_fail_context(rc, "%s", path);
    }
    return rc;
}

int swfs_modal_projector_(const char *cm_path, double **P, size_t *ns, size_t *rank)
{
    *P = NULL;
    swfs_real *cm = NULL;
    swfs_recon *pinv = NULL;
    int rc = cm_pinv(cm_path, &cm, &pinv);
    if (!rc && !(*P = malloc(cm->nx * cm->nx * sizeof **P))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) { /* P = CM+ CM (slopes x slopes) */
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)cm->nx, (int)cm->nx, (int)cm->ny, 1.0, pinv->W,
                    (int)cm->ny, cm->data, (int)cm->nx, 0.0, *P, (int)cm->nx);
        *ns = cm->nx;
        *rank = pinv->nmodes;
    }
    swfs_recon_free(pinv);
    swfs_real_free(cm);
    return rc;
}

int swfs_modal_project_(const double *P, size_t n, swfs_real *s, const char *what)
{
    if (s->nx != n)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: %zu slopes per frame; the projection the map is for acts on %zu", what, s->nx,
                         n);
    double *t = malloc(s->nx * s->ny * sizeof *t);
    if (!t) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)s->ny, (int)s->nx, (int)s->nx, 1.0, s->data, (int)s->nx,
                P, (int)s->nx, 0.0, t, (int)s->nx);
    memcpy(s->data, t, s->nx * s->ny * sizeof *t);
    free(t);
    return SWFS_OK;
}

int swfs_modal_slopes_run(const swfs_modal_slopes_options *o, swfs_modal_slopes_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->nfiles || !o->cm || !o->outdir)
        return swfs_fail(SWFS_ERR_ARG, "modal-slopes: needs coefficient files, the control matrix and an output folder");
    char od[PATH_MAX], id[PATH_MAX], dir[4200];
    if (!realpath(o->outdir, od))
        return swfs_fail(SWFS_ERR_IO, "modal-slopes: %s: not an existing folder", o->outdir);
    for (size_t k = 0; k < o->nfiles; k++) {
        swfs_path_dir(o->files[k], dir, sizeof dir);
        if (realpath(dir, id) && !strcmp(id, od))
            return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s is in the output folder %s: the slopes are written under "
                             "the inputs' names, so the output folder must be another", o->files[k], o->outdir);
        const char *bk = strrchr(o->files[k], '/'), *bc = strrchr(o->cm, '/');
        if (!strcmp(bk ? bk + 1 : o->files[k], bc ? bc + 1 : o->cm))
            return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s has the name of the control matrix %s, whose copy the "
                             "output folder holds beside the slopes", o->files[k], o->cm);
        for (size_t j = 0; j < k; j++) {
            const char *bj = strrchr(o->files[j], '/');
            if (!strcmp(bk ? bk + 1 : o->files[k], bj ? bj + 1 : o->files[j]))
                return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s and %s have one name, which the output folder holds "
                                 "once", o->files[j], o->files[k]);
        }
    }
    swfs_real *cm = NULL;
    swfs_recon *pinv = NULL;
    int rc = cm_pinv(o->cm, &cm, &pinv);
    if (!rc) {
        r->ncoef = cm->ny;
        r->nslopes = cm->nx;
    }
    /* the control matrix copied beside the slopes, which name it (MODALCM, relative to their
     * folder): teach finds it wherever the folder goes */
    const char *cmbase = strrchr(o->cm, '/') ? strrchr(o->cm, '/') + 1 : o->cm;
    if (!rc) {
        r->rank = pinv->nmodes;
        r->cond = pinv->sv[0] / pinv->sv[pinv->nmodes - 1];
    }
    double rss = 0, css = 0;
    swfs_outputs_begin(); /* all files or none */
    if (!rc) {
        char path[8400];
        snprintf(path, sizeof path, "%s/%s", o->outdir, cmbase);
        swfs_fits_out *f = NULL;
        char hist[4200];
        snprintf(hist, sizeof hist, "specklewfs modal-slopes: a copy of %s", o->cm);
        const char *prov[] = {hist};
        if (!(rc = swfs_fits_out_create(&f, path))) {
            if ((rc = swfs_fits_out_set_stamp(f, NULL, prov, 1)) || (rc = swfs_fits_out_real(f, NULL, cm, -64)) ||
                (rc = swfs_fits_out_key_string(f, "BUNIT", "coefficient/rad", "the modal control matrix: slopes -> coefficients")))
                swfs_fits_out_abort(f);
            else rc = swfs_fits_out_commit(f);
        }
    }
    for (size_t k = 0; !rc && k < o->nfiles; k++) {
        swfs_real *c = NULL, *s = NULL;
        double rate = 0;
        long frame0 = 0;
        int has0 = 0;
        rc = swfs_telemetry_read(o->files[k], 0, &c, &rate);
        if (!rc && c->nx != r->ncoef)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu coefficients per WFS frame; %s maps %zu slopes to %zu", o->files[k],
                           c->nx, o->cm, r->nslopes, r->ncoef);
        for (size_t i = 0; !rc && i < c->nx * c->ny; i++)
            if (!isfinite(c->data[i]))
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: frame %zu, coefficient %zu is not finite", o->files[k], i / c->nx,
                               i % c->nx);
        if (!rc) rc = frame0_of(o->files[k], &frame0, &has0);
        if (!rc && !(s = swfs_real_alloc(r->nslopes, c->ny, 1))) rc = swfs_fail(SWFS_ERR_NOMEM, "modal-slopes: out of memory");
        double *back = NULL;
        if (!rc && !(back = malloc(c->nx * c->ny * sizeof *back))) rc = swfs_fail(SWFS_ERR_NOMEM, "modal-slopes: out of memory");
        if (!rc) {
            const int nf = (int)c->ny, nc = (int)r->ncoef, ns = (int)r->nslopes;
            /* s' = c CM+^T per frame (rows), and c again from it, c CM+^T CM^T */
            cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, nf, ns, nc, 1.0, c->data, nc, pinv->W, nc, 0.0, s->data, ns);
            cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, nf, nc, ns, 1.0, s->data, ns, cm->data, ns, 0.0, back, nc);
            for (size_t i = 0; i < c->nx * c->ny; i++) {
                rss += (c->data[i] - back[i]) * (c->data[i] - back[i]);
                css += c->data[i] * c->data[i];
            }
            r->nframes += c->ny;
        }
        free(back);
        if (!rc) {
            const char *base = strrchr(o->files[k], '/');
            char path[8400];
            snprintf(path, sizeof path, "%s/%s", o->outdir, base ? base + 1 : o->files[k]);
            swfs_fits_out *f = NULL;
            if (!(rc = swfs_fits_out_create(&f, path))) {
                char hist[8400];
                snprintf(hist, sizeof hist, "specklewfs modal-slopes: %s through the pseudo-inverse of %s", o->files[k], o->cm);
                const char *prov[] = {hist};
                if ((rc = swfs_fits_out_set_stamp(f, NULL, prov, 1)) || (rc = swfs_fits_out_real(f, NULL, s, -32)) ||
                    (rc = swfs_fits_out_key_string(f, "BUNIT", "rad", "slopes: the modal coefficients through CM+")) ||
                    (rate > 0 && (rc = swfs_fits_out_key_double(f, "WFSRATE", rate, "[Hz]"))) ||
                    (has0 && (rc = swfs_fits_out_key_long(f, "FRAME0", frame0, "global WFS frame of row 0"))) ||
                    (rc = swfs_fits_out_key_string(f, "MODALCM", cmbase, "CM these slopes came through, in their folder")))
                    swfs_fits_out_abort(f);
                else rc = swfs_fits_out_commit(f);
            }
        }
        swfs_real_free(c);
        swfs_real_free(s);
    }
    const int erc = swfs_outputs_end(rc == SWFS_OK);
    if (!rc) rc = erc;
    r->resid = css > 0 ? sqrt(rss / css) : 0;
    swfs_recon_free(pinv);
    swfs_real_free(cm);
    return rc;
}

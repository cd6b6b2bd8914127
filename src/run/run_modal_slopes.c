/* modal-slopes: a modal system's coefficients turned back into its Shack-Hartmann's slopes,
 * s' = CM+ c, or RM c from the modal response matrix (run.h swfs_modal_slopes_run;
 * docs/telemetry.md, "The modal input kind"). */
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

/* A matrix from its file, 2-D and finite (what: its role in the messages). */
static int read_matrix(const char *path, const char *what, const char *axes, const char *rows, const char *cols,
                       swfs_real **m)
{
    int rc = swfs_fits_read_real(path, NULL, m, NULL);
    if (!rc && ((*m)->nz != 1 || (*m)->nx < 1 || (*m)->ny < 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the %s is %zux%zux%zu; expected %s (2-D)", path, what, (*m)->nx, (*m)->ny,
                       (*m)->nz, axes);
    for (size_t i = 0; !rc && i < (*m)->nx * (*m)->ny; i++)
        if (!isfinite((*m)->data[i]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: value %zu (%s %zu, %s %zu) is not finite", path, i, rows, i / (*m)->nx, cols,
                           i % (*m)->nx);
    return rc;
}

/* The pseudo-inverse of a rows x cols matrix (row-major) at the numerical rank: singular values
 * above max(rows, cols) x DBL_EPSILON of the largest. */
static int pinv_at_rank(const double *A, size_t rows, size_t cols, swfs_recon **pinv)
{
    const double tol = (double)(rows > cols ? rows : cols) * DBL_EPSILON;
    return swfs_recon_svd(A, rows, cols, tol, 0, pinv);
}

/* CM (coefficients x slopes, from its file, checked) and its pseudo-inverse at the numerical
 * rank. */
static int cm_pinv(const char *path, swfs_real **cm, swfs_recon **pinv)
{
    *pinv = NULL;
    int rc = read_matrix(path, "control matrix", "slopes x coefficients", "coefficient", "slope", cm);
    /* CM+ (slopes x coefficients): swfs_recon_svd inverts a matrix of rows x columns */
    if (!rc && (rc = pinv_at_rank((*cm)->data, (*cm)->ny, (*cm)->nx, pinv))) rc = swfs_fail_context(rc, "%s", path);
    return rc;
}

/* From the modal response matrix RM (slopes x coefficients: NAXIS1 = coefficients, NAXIS2 =
 * slopes, what poking each mode gives), the control matrix the slopes are taken to have gone
 * through, CM = RM+ (least squares; coefficients x slopes), and CM+ (= RM at its numerical
 * rank), so that s' = CM+ c = RM c and teach's projection CM+ CM = RM RM+: exact for any
 * control matrix that inverts RM on its modes. */
static int rm_cm_pinv(const char *path, swfs_real **cm, swfs_recon **pinv)
{
    *cm = NULL;
    *pinv = NULL;
    swfs_real *rm = NULL;
    swfs_recon *rmp = NULL;
    int rc = read_matrix(path, "modal response matrix", "coefficients x slopes", "slope", "coefficient", &rm);
    if (!rc && (rc = pinv_at_rank(rm->data, rm->ny, rm->nx, &rmp))) rc = swfs_fail_context(rc, "%s", path);
    if (!rc && !(*cm = swfs_real_alloc(rm->ny, rm->nx, 1))) rc = swfs_fail(SWFS_ERR_NOMEM, "modal-slopes: out of memory");
    if (!rc) {
        memcpy((*cm)->data, rmp->W, rm->nx * rm->ny * sizeof *rmp->W);
        if ((rc = pinv_at_rank((*cm)->data, (*cm)->ny, (*cm)->nx, pinv)))
            rc = swfs_fail_context(rc, "%s: the pseudo-inverse of its pseudo-inverse", path);
    }
    swfs_recon_free(rmp);
    swfs_real_free(rm);
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

/* --imat's check that the coefficients came through a control matrix that inverts RM. A
 * least-squares CM carries the slopes' white noise (variance s2, the same in every slope) into
 * coefficient k with variance s2 A_k, A_k = (RM^T RM)^-1_kk = the k-th row of RM+ squared; a
 * regularizing CM (a MAP, a truncated or filtered SVD) carries less into the modes it damps.
 * Each coefficient's white variance is its lag-0 autocovariance less the quadratic through lags
 * 1, 2, 3 extrapolated to 0 (the residual's part is smooth in the lag); the check compares
 * r_k = white_k / A_k over the half of the modes with the larger A_k (the poorly sensed ones)
 * with the other half, by their medians: 1 for a least-squares CM, 0 where the poorly sensed
 * half shows no white noise (a CM that damps it; also coefficients of noise-free slopes, which no
 * WFS gives). Sums over files, each file's mean removed. */
#define LSQ_LAGS 4
typedef struct lsq_sums {
    double *ac;     /* ncoef x LSQ_LAGS: sum over frames of c_t c_(t+l) */
    size_t *n;      /* LSQ_LAGS: the products summed */
} lsq_sums;

static void lsq_add(lsq_sums *q, const swfs_real *c, double *mean)
{
    const size_t nc = c->nx, nf = c->ny;
    for (size_t k = 0; k < nc; k++) mean[k] = 0;
    for (size_t t = 0; t < nf; t++)
        for (size_t k = 0; k < nc; k++) mean[k] += c->data[t * nc + k] / (double)nf;
    for (size_t l = 0; l < LSQ_LAGS && l < nf; l++) {
        for (size_t t = 0; t + l < nf; t++)
            for (size_t k = 0; k < nc; k++)
                q->ac[k * LSQ_LAGS + l] += (c->data[t * nc + k] - mean[k]) * (c->data[(t + l) * nc + k] - mean[k]);
        q->n[l] += nf - l;
    }
}

static int cmp_double(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The ratio of the medians (NAN with fewer than 64 frames at lag 3 or 8 coefficients). */
static double lsq_ratio(const lsq_sums *q, const swfs_real *cm, double *work)
{
    const size_t nc = cm->ny, ns = cm->nx;
    if (q->n[LSQ_LAGS - 1] < 64 || nc < 8) return NAN;
    double *A = work, *r = work + nc, *lo = work + 2 * nc;
    for (size_t k = 0; k < nc; k++) {
        double a = 0;
        for (size_t i = 0; i < ns; i++) a += cm->data[k * ns + i] * cm->data[k * ns + i];
        double g[LSQ_LAGS];
        for (size_t l = 0; l < LSQ_LAGS; l++) g[l] = q->ac[k * LSQ_LAGS + l] / (double)q->n[l];
        A[k] = a;
        r[k] = a > 0 ? (g[0] - (3 * g[1] - 3 * g[2] + g[3])) / a : NAN;
    }
    /* the halves by A: the median of A splits them */
    memcpy(lo, A, nc * sizeof *A);
    qsort(lo, nc, sizeof *lo, cmp_double);
    const double amed = lo[nc / 2];
    size_t nl = 0, nu = 0;
    double *up = lo + nc; /* work holds 4 nc */
    for (size_t k = 0; k < nc; k++) {
        if (!isfinite(r[k])) continue;
        if (A[k] < amed) lo[nl++] = r[k];
        else up[nu++] = r[k];
    }
    if (nl < 4 || nu < 4) return NAN;
    qsort(lo, nl, sizeof *lo, cmp_double);
    qsort(up, nu, sizeof *up, cmp_double);
    const double ml = lo[nl / 2], mu = up[nu / 2];
    /* none found where a least-squares CM of noisy slopes puts the most: 0; found there but not
     * in the well-sensed half: no finite ratio */
    return mu <= 0 ? 0.0 : ml <= 0 ? INFINITY : mu / ml;
}

/* One coefficient file, its width ncoef and its values finite (src: the matrix, nslopes its
 * slopes, for the message). */
static int read_coefs(const char *path, size_t ncoef, const char *src, size_t nslopes, swfs_real **c, double *rate)
{
    int rc = swfs_telemetry_read(path, 0, c, rate);
    if (!rc && (*c)->nx != ncoef)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu coefficients per WFS frame; %s maps %zu slopes to %zu", path, (*c)->nx, src,
                       nslopes, ncoef);
    for (size_t i = 0; !rc && i < (*c)->nx * (*c)->ny; i++)
        if (!isfinite((*c)->data[i]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: frame %zu, coefficient %zu is not finite", path, i / (*c)->nx, i % (*c)->nx);
    return rc;
}

int swfs_modal_slopes_run(const swfs_modal_slopes_options *o, swfs_modal_slopes_result *r)
{
    memset(r, 0, sizeof *r);
    r->lsq_ratio = NAN;
    if (!o->nfiles || (!o->cm == !o->imat) || !o->outdir)
        return swfs_fail(SWFS_ERR_ARG, "modal-slopes: needs coefficient files, the control matrix or (not and) the modal "
                         "response matrix, and an output folder");
    /* the control matrix copied beside the slopes (with a response matrix, its pseudo-inverse),
     * which name it (MODALCM, relative to their folder): teach finds it wherever the folder goes */
    const char *src = o->cm ? o->cm : o->imat;
    char cmbase[1100];
    snprintf(cmbase, sizeof cmbase, "%s%s", o->cm ? "" : "pinv_", strrchr(src, '/') ? strrchr(src, '/') + 1 : src);
    char od[PATH_MAX], id[PATH_MAX], dir[4200];
    if (!realpath(o->outdir, od))
        return swfs_fail(SWFS_ERR_IO, "modal-slopes: %s: not an existing folder", o->outdir);
    swfs_path_dir(src, dir, sizeof dir);
    if (realpath(dir, id) && !strcmp(id, od) && !strcmp(strrchr(src, '/') ? strrchr(src, '/') + 1 : src, cmbase))
        return swfs_fail(SWFS_ERR_ARG, "modal-slopes: the control matrix %s is in the output folder %s, where its copy "
                         "beside the slopes is written under its name: the output folder must be another", src,
                         o->outdir);
    for (size_t k = 0; k < o->nfiles; k++) {
        swfs_path_dir(o->files[k], dir, sizeof dir);
        if (realpath(dir, id) && !strcmp(id, od))
            return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s is in the output folder %s: the slopes are written under "
                             "the inputs' names, so the output folder must be another", o->files[k], o->outdir);
        const char *bk = strrchr(o->files[k], '/');
        if (!strcmp(bk ? bk + 1 : o->files[k], cmbase))
            return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s has the name of the control matrix %s, which the output "
                             "folder holds beside the slopes", o->files[k], cmbase);
        for (size_t j = 0; j < k; j++) {
            const char *bj = strrchr(o->files[j], '/');
            if (!strcmp(bk ? bk + 1 : o->files[k], bj ? bj + 1 : o->files[j]))
                return swfs_fail(SWFS_ERR_ARG, "modal-slopes: %s and %s have one name, which the output folder holds "
                                 "once", o->files[j], o->files[k]);
        }
    }
    swfs_real *cm = NULL;
    swfs_recon *pinv = NULL;
    int rc = o->cm ? cm_pinv(o->cm, &cm, &pinv) : rm_cm_pinv(o->imat, &cm, &pinv);
    if (!rc) {
        r->ncoef = cm->ny;
        r->nslopes = cm->nx;
    }
    if (!rc) {
        r->rank = pinv->nmodes;
        r->cond = pinv->sv[0] / pinv->sv[pinv->nmodes - 1];
    }
    double rss = 0, css = 0;
    lsq_sums q = {NULL, NULL};
    double *qwork = NULL;
    if (!rc && o->imat &&
        (!(q.ac = calloc(r->ncoef * LSQ_LAGS, sizeof *q.ac)) || !(q.n = calloc(LSQ_LAGS, sizeof *q.n)) ||
         !(qwork = malloc(4 * r->ncoef * sizeof *qwork))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "modal-slopes: out of memory");
    /* --imat: the check first (a pass over the files), so that the slopes carry its verdict */
    for (size_t k = 0; !rc && o->imat && k < o->nfiles; k++) {
        swfs_real *c = NULL;
        double rate = 0;
        if (!(rc = read_coefs(o->files[k], r->ncoef, src, r->nslopes, &c, &rate))) lsq_add(&q, c, qwork);
        swfs_real_free(c);
    }
    if (!rc && o->imat) {
        r->lsq_ratio = lsq_ratio(&q, cm, qwork);
        r->lsq_warns = r->lsq_ratio < SWFS_MODAL_LSQ_RATIO_MIN || r->lsq_ratio > 1 / SWFS_MODAL_LSQ_RATIO_MIN;
    }
    swfs_outputs_begin(); /* all files or none */
    if (!rc) {
        char path[8400];
        snprintf(path, sizeof path, "%s/%s", o->outdir, cmbase);
        swfs_fits_out *f = NULL;
        char hist[4200];
        snprintf(hist, sizeof hist, "specklewfs modal-slopes: %s %s", o->cm ? "a copy of" : "the pseudo-inverse of", src);
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
        rc = read_coefs(o->files[k], r->ncoef, src, r->nslopes, &c, &rate);
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
                if (o->cm) snprintf(hist, sizeof hist, "specklewfs modal-slopes: %s through the pseudo-inverse of %s", o->files[k], src);
                else snprintf(hist, sizeof hist, "specklewfs modal-slopes: %s through the modal response matrix %s", o->files[k], src);
                const char *prov[] = {hist};
                if ((rc = swfs_fits_out_set_stamp(f, NULL, prov, 1)) || (rc = swfs_fits_out_real(f, NULL, s, -32)) ||
                    (rc = swfs_fits_out_key_string(f, "BUNIT", "rad", "slopes: the modal coefficients through CM+")) ||
                    (rate > 0 && (rc = swfs_fits_out_key_double(f, "WFSRATE", rate, "[Hz]"))) ||
                    (has0 && (rc = swfs_fits_out_key_long(f, "FRAME0", frame0, "global WFS frame of row 0"))) ||
                    (rc = swfs_fits_out_key_string(f, "MODALCM", cmbase, "CM these slopes came through, in their folder")) ||
                    (isfinite(r->lsq_ratio) &&
                     (rc = swfs_fits_out_key_double(f, "MODALLSQ", r->lsq_ratio, "coefficients' white noise / least squares'"))) ||
                    (o->imat && !isnan(r->lsq_ratio) &&
                     (rc = swfs_fits_out_key_long(f, "MODALRGW", r->lsq_warns, "1: CM regularizes; RM c not the slopes"))))
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
    free(q.ac);
    free(q.n);
    free(qwork);
    swfs_recon_free(pinv);
    swfs_real_free(cm);
    return rc;
}

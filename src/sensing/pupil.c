/* Pupil field and NCP wavefront from the static halo: see include/specklewfs/pupil.h. */
#include "specklewfs/pupil.h"
#include "specklewfs/aperture.h"
#include "specklewfs/mft.h"
#include "specklewfs/numeric.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_pupil_options_default(swfs_pupil_options *o)
{
    o->weight = SWFS_WEIGHT_SNR;
    o->wiener_k = 2.0;
    o->bias = 0.0;
    o->source = SWFS_SOURCE_HALO_LF;
    o->method = SWFS_PUPIL_AUTO;
    swfs_jointfit_options_default(&o->fit);
    o->keep_resmean = 0;
}

void swfs_pupil_result_free(swfs_pupil_result *r)
{
    if (!r) return;
    swfs_cplx_free(r->field);
    swfs_real_free(r->wfe);
    swfs_real_free(r->surface);
    swfs_real_free(r->amplitude);
    swfs_real_free(r->mask);
    swfs_jointfit_result_free(r->fit);
    swfs_real_free(r->explained_map);
    swfs_real_free(r->resmean);
    free(r);
}

size_t swfs_pupil_explained_nrings(const swfs_real *map, double pixscale)
{
    const double edge = ceil(0.5 * (double)map->nx * pixscale);
    return edge > 0 && isfinite(edge) ? (size_t)edge : 0;
}

void swfs_pupil_explained_rings(const swfs_real *map, double pixscale, double *out, size_t nrings)
{
    const size_t nx = map->nx, ny = map->ny, np = nx * ny;
    double *v = malloc((np ? np : 1) * sizeof *v);
    for (size_t k = 0; k < nrings; k++) {
        size_t n = 0;
        for (size_t j = 0; v && j < ny; j++)
            for (size_t i = 0; i < nx; i++) {
                const double r = hypot((double)i - (double)(nx / 2), (double)j - (double)(ny / 2)) * pixscale;
                const double x = map->data[j * nx + i];
                if (r >= (double)k && r < (double)(k + 1) && isfinite(x)) v[n++] = x;
            }
        out[k] = n ? swfs_median_inplace(v, n) : NAN;
    }
    free(v);
}

/* Piston-removed rms, peak to valley and Marechal Strehl of r->wfe over r->mask. */
static int wfe_stats(swfs_pupil_result *r, double wavelen)
{
    const size_t np = r->wfe->nx * r->wfe->ny;
    double wsum = 0.0, mean = 0.0;
    for (size_t q = 0; q < np; q++)
        if (r->mask->data[q] > 0.0) { wsum += r->mask->data[q]; mean += r->mask->data[q] * r->wfe->data[q]; }
    if (!(wsum > 0.0)) return swfs_fail(SWFS_ERR_VALUE, "pupil mask is empty");
    mean /= wsum;
    double s2 = 0.0, lo = INFINITY, hi = -INFINITY;
    for (size_t q = 0; q < np; q++) {
        if (r->mask->data[q] > 0.0) {
            const double w = r->wfe->data[q] -= mean;
            s2 += r->mask->data[q] * w * w;
            if (w < lo) lo = w;
            if (w > hi) hi = w;
        } else {
            r->wfe->data[q] = 0.0;
        }
        r->surface->data[q] = 0.5 * r->wfe->data[q];
    }
    r->wfe_rms = sqrt(s2 / wsum);
    r->wfe_pv = hi - lo;
    const double sig = 2.0 * M_PI * r->wfe_rms / wavelen;
    r->strehl = exp(-sig * sig);
    return SWFS_OK;
}

/* The joint fit (docs/estimator.md): regression statistics -> per-pixel information ->
 * one pupil field; WFE = its phase. */
static int pupil_fit(const swfs_halo *h, const swfs_geom *g, const swfs_real *mask, const swfs_pupil_options *o,
                     swfs_pupil_result **out)
{
    if (!h->reg)
        return swfs_fail(SWFS_ERR_FORMAT, "halo product has no regression statistics (REGSTATE): it was made by "
                         "a specklewfs before the joint fit or merged with an old checkpoint; use the moments");
    swfs_regress_sol *sol = NULL;
    swfs_pupil_result *r = calloc(1, sizeof *r);
    if (!r) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    r->opt = *o;
    r->method = SWFS_PUPIL_FIT;
    int rc = swfs_regress_solve(h->reg, &sol);
    if (!rc) {
        r->explained = sol->explained;
        r->explained_median = sol->explained_median;
        r->explained_map = sol->r2;
        sol->r2 = NULL;
        rc = swfs_jointfit(sol, g, mask, &o->fit, &r->fit);
    }
    swfs_regress_sol_free(sol);
    if (rc) goto fail;
    const size_t n = (size_t)g->pupn;
    r->field = swfs_cplx_copy(r->fit->field);
    r->wfe = swfs_real_copy(r->fit->wfe);
    r->mask = swfs_real_copy(r->fit->mask);
    r->surface = swfs_real_alloc(n, n, 1);
    r->amplitude = swfs_real_alloc(n, n, 1);
    if (!r->field || !r->wfe || !r->mask || !r->surface || !r->amplitude) { rc = SWFS_ERR_NOMEM; goto fail; }
    for (size_t q = 0; q < n * n; q++) r->amplitude->data[q] = cabs(r->field->data[q]);
    if ((rc = wfe_stats(r, g->wavelen))) goto fail;
    *out = r;
    return SWFS_OK;
fail:
    swfs_pupil_result_free(r);
    return rc;
}

static int pupil_moments(const swfs_halo *h, const swfs_geom *g, const swfs_real *mask, const swfs_pupil_options *opt,
                         swfs_pupil_result **out);

int swfs_pupil_estimate(const swfs_halo *h, const swfs_geom *g, const swfs_real *mask, const swfs_pupil_options *opt,
                        swfs_pupil_result **out)
{
    *out = NULL;
    swfs_pupil_options o;
    swfs_pupil_options_default(&o);
    if (opt) o = *opt;
    int rc = swfs_geom_require(g, "halo product");
    if (rc) return rc;
    const size_t n = (size_t)g->pupn;
    if (mask && (mask->nx != n || mask->ny != n))
        return swfs_fail(SWFS_ERR_SHAPE, "pupil mask is %zux%zu but the geometry says PUPN = %zu", mask->nx, mask->ny, n);
    if (h->resmean && !o.keep_resmean && (h->resmean->nx != n || h->resmean->ny != n))
        return swfs_fail(SWFS_ERR_SHAPE, "the halo's AO residual mean (RESMEAN) is %zux%zu but the geometry says "
                         "PUPN = %zu", h->resmean->nx, h->resmean->ny, n);
    if (o.method == SWFS_PUPIL_FIT) {
        rc = pupil_fit(h, g, mask, &o, out);
    } else {
        rc = SWFS_ERR_NUMERIC;
        if (o.method == SWFS_PUPIL_AUTO && h->reg) {
            /* AUTO: the fit when the statistics allow one; too few frames or pixels for any
             * regression (e.g. the first update of a live run) fall back to the moments. */
            rc = pupil_fit(h, g, mask, &o, out);
            if (rc != SWFS_ERR_NUMERIC) goto done;
        }
        if (o.method != SWFS_PUPIL_AUTO && o.method != SWFS_PUPIL_MOMENTS)
            return swfs_fail(SWFS_ERR_ARG, "pupil method %d: expected auto, fit or moments", o.method);
        rc = pupil_moments(h, g, mask, &o, out);
    }
done:
    /* WFE = the NCP alone: the residual's time mean that the telemetry measured goes out. */
    if (!rc && h->resmean && !o.keep_resmean) {
        rc = swfs_pupil_remove_resmean(*out, h->resmean, g, h->nx, h->ny);
        if (!rc) rc = wfe_stats(*out, g->wavelen);
        if (rc) {
            swfs_pupil_result_free(*out);
            *out = NULL;
        }
    }
    return rc;
}

/* The per-pixel moments transformed (paper Sec. 4.6 with the weighting above). */
static int pupil_moments(const swfs_halo *h, const swfs_geom *g, const swfs_real *mask, const swfs_pupil_options *opt,
                         swfs_pupil_result **out)
{
    const swfs_pupil_options o = *opt;
    int rc;
    const swfs_cplx *src = o.source == SWFS_SOURCE_HALO ? h->halo : h->halo_lf;
    if (!src) return swfs_fail(SWFS_ERR_FORMAT, "halo product has no %s", o.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF");
    if (o.weight == SWFS_WEIGHT_SNR && (!h->stab || !h->stab_err))
        return swfs_fail(SWFS_ERR_FORMAT, "SNR weighting needs the STAB and STAB_ERR extensions of the halo product");
    if (!(o.wiener_k > 0.0 && o.wiener_k <= 1e6))
        return swfs_fail(SWFS_ERR_ARG, "Wiener k must be > 0 and at most 1e6, got %g", o.wiener_k);
    if (!isfinite(o.bias)) return swfs_fail(SWFS_ERR_ARG, "bias must be finite");
    const size_t n = (size_t)g->pupn, nx = h->nx, ny = h->ny, nf = nx * ny;
    if (mask && (mask->nx != n || mask->ny != n))
        return swfs_fail(SWFS_ERR_SHAPE, "pupil mask is %zux%zu but the geometry says PUPN = %zu", mask->nx, mask->ny, n);

    swfs_pupil_result *r = calloc(1, sizeof *r);
    if (!r) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    r->explained = r->explained_median = NAN;
    r->opt = o;
    r->method = SWFS_PUPIL_MOMENTS;
    r->field = swfs_cplx_alloc(n, n, 1);
    r->wfe = swfs_real_alloc(n, n, 1);
    r->surface = swfs_real_alloc(n, n, 1);
    r->amplitude = swfs_real_alloc(n, n, 1);
    r->mask = mask ? swfs_real_copy(mask) : swfs_real_alloc(n, n, 1);
    double complex *focal = swfs_malloc(nf * sizeof *focal);
    const double alpha = g->pixscale * g->pupdx / g->teldiam;
    swfs_mft *m = swfs_mft_create(n, nx, ny, alpha, SWFS_MFT_DOUBLE);
    if (!r->field || !r->wfe || !r->surface || !r->amplitude || !r->mask || !focal || !m) {
        rc = SWFS_ERR_NOMEM;
        goto fail;
    }
    if (!mask && (rc = swfs_aperture_make(r->mask->data, n, g->pupdx, g->teldiam, g->obscur, 0, 0.0))) goto fail;

    /* Wiener weight per focal pixel (beyond the paper): SNR^2 / (SNR^2 + k^2). */
    size_t nused = 0;
    for (size_t p = 0; p < nf; p++) {
        double complex v = src->data[p];
        if (!isfinite(creal(v)) || !isfinite(cimag(v))) v = 0.0;
        double w = 1.0;
        if (o.weight == SWFS_WEIGHT_SNR) {
            const double e = h->stab_err->data[p], s2 = cabs(h->stab->data[p]);
            double snr2 = 0.0;
            if (e > 0.0 && isfinite(e) && isfinite(s2)) snr2 = (s2 / e) * (s2 / e);
            w = snr2 / (snr2 + o.wiener_k * o.wiener_k);
        }
        focal[p] = w * v;
        nused += focal[p] != 0.0;
    }
    /* Nothing to transform is an error, not a flat wavefront of 0 nm and Strehl 1. */
    if (!nused) {
        rc = swfs_fail(SWFS_ERR_VALUE, "no focal-plane pixel has a finite, non-zero %s%s: nothing to transform to the "
                       "pupil", o.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF",
                       o.weight == SWFS_WEIGHT_SNR ? " with a positive SNR weight (STAB / STAB_ERR)" : "");
        goto fail;
    }
    if ((rc = swfs_mft_inverse(m, focal, r->field->data))) goto fail;

    const size_t np = n * n;
    for (size_t q = 0; q < np; q++) {
        r->field->data[q] *= alpha * alpha;
        if (!isfinite(creal(r->field->data[q])) || !isfinite(cimag(r->field->data[q]))) {
            rc = swfs_fail(SWFS_ERR_VALUE, "the pupil field overflows (sample %zu is not finite): the %s values are "
                           "too large to be a halo", q, o.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF");
            goto fail;
        }
    }
    double complex mean = 0.0;
    double wsum = 0.0;
    for (size_t q = 0; q < np; q++) {
        mean += r->mask->data[q] * r->field->data[q];
        wsum += r->mask->data[q];
    }
    if (!(wsum > 0.0)) {
        rc = swfs_fail(SWFS_ERR_VALUE, "the pupil mask is empty (no sample > 0)%s", mask ? "" : ": TELDIAM, PUPDX, "
                       "OBSCUR leave no illuminated sample");
        goto fail;
    }
    mean /= wsum;
    /* eq:LFBiased-WFE-estimate: a constant field restores the missing low frequencies. */
    if (o.bias != 0.0)
        for (size_t q = 0; q < np; q++) r->field->data[q] += o.bias * mean;
    if (o.bias != 0.0) mean *= 1.0 + o.bias;
    /* eq:NCP-WFE-estimate. The phase is taken relative to the mean field so that a
     * global phase offset never wraps; piston is then removed exactly. */
    const double k2m = g->wavelen / (2.0 * M_PI);
    const double complex ref = cabs(mean) > 0.0 ? conj(mean) / cabs(mean) : 1.0;
    for (size_t q = 0; q < np; q++) {
        r->amplitude->data[q] = cabs(r->field->data[q]);
        if (r->mask->data[q] > 0.0) {
            double ph = carg(r->field->data[q] * ref);
            r->wfe->data[q] = ph * k2m;
        }
    }
    if ((rc = wfe_stats(r, g->wavelen))) goto fail;
    swfs_mft_free(m);
    swfs_free(focal);
    *out = r;
    return SWFS_OK;
fail:
    swfs_mft_free(m);
    swfs_free(focal);
    swfs_pupil_result_free(r);
    return rc;
}

/* Least-squares fit of a + b x + c y over the mask (normal equations, 3x3). */
int swfs_pupil_mask_check(const swfs_real *mask, const char *what)
{
    size_t lit = 0;
    for (size_t q = 0; q < mask->nx * mask->ny * mask->nz; q++) {
        const double v = mask->data[q];
        if (!(v >= 0 && v <= 1))
            return swfs_fail(SWFS_ERR_VALUE, "%s: pupil mask value %g at sample (%zu, %zu) is outside 0 .. 1 (a "
                             "transmission)", what, v, q % mask->nx, q / mask->nx % mask->ny);
        lit += v > 0;
    }
    if (!lit) return swfs_fail(SWFS_ERR_VALUE, "%s: the pupil mask is empty (every sample is 0)", what);
    return SWFS_OK;
}

static void fit_ptt(const double *w, const double *mask, size_t n, double coef[3])
{
    double A[3][3] = {{0}}, b[3] = {0};
    const double c = 0.5 * (double)(n - 1);
    for (size_t j = 0; j < n; j++)
        for (size_t i = 0; i < n; i++) {
            double m = mask[j * n + i];
            if (!(m > 0.0)) continue;
            double v[3] = {1.0, (double)i - c, (double)j - c};
            for (int r = 0; r < 3; r++) {
                b[r] += m * v[r] * w[j * n + i];
                for (int s = 0; s < 3; s++) A[r][s] += m * v[r] * v[s];
            }
        }
    /* Gaussian elimination with partial pivoting. */
    for (int k = 0; k < 3; k++) {
        int piv = k;
        for (int r = k + 1; r < 3; r++)
            if (fabs(A[r][k]) > fabs(A[piv][k])) piv = r;
        for (int s = 0; s < 3; s++) { double t = A[k][s]; A[k][s] = A[piv][s]; A[piv][s] = t; }
        double t = b[k]; b[k] = b[piv]; b[piv] = t;
        if (A[k][k] == 0.0) { coef[0] = coef[1] = coef[2] = 0.0; return; }
        for (int r = k + 1; r < 3; r++) {
            double f = A[r][k] / A[k][k];
            for (int s = k; s < 3; s++) A[r][s] -= f * A[k][s];
            b[r] -= f * b[k];
        }
    }
    for (int k = 2; k >= 0; k--) {
        double s = b[k];
        for (int r = k + 1; r < 3; r++) s -= A[k][r] * coef[r];
        coef[k] = s / A[k][k];
    }
}

double swfs_wfe_remove_ptt(double *w, const double *mask, size_t n)
{
    double coef[3];
    fit_ptt(w, mask, n, coef);
    const double c = 0.5 * (double)(n - 1);
    double s2 = 0.0, ws = 0.0;
    for (size_t j = 0; j < n; j++)
        for (size_t i = 0; i < n; i++) {
            double m = mask[j * n + i];
            if (!(m > 0.0)) continue;
            double *v = &w[j * n + i];
            *v -= coef[0] + coef[1] * ((double)i - c) + coef[2] * ((double)j - c);
            s2 += m * *v * *v;
            ws += m;
        }
    return ws > 0.0 ? sqrt(s2 / ws) : NAN;
}

int swfs_wfe_compare(const double *est, const double *truth, const double *mask, size_t n, double *err_rms,
                     double *truth_rms_piston, double *truth_rms_ptt)
{
    double *d = swfs_malloc(n * n * sizeof *d);
    if (!d) return SWFS_ERR_NOMEM;
    if (err_rms) {
        for (size_t q = 0; q < n * n; q++) d[q] = est[q] - truth[q];
        *err_rms = swfs_wfe_remove_ptt(d, mask, n);
    }
    double mean = 0.0, ws = 0.0, s2 = 0.0;
    for (size_t q = 0; q < n * n; q++)
        if (mask[q] > 0.0) { mean += mask[q] * truth[q]; ws += mask[q]; }
    mean /= ws;
    for (size_t q = 0; q < n * n; q++)
        if (mask[q] > 0.0) s2 += mask[q] * (truth[q] - mean) * (truth[q] - mean);
    if (truth_rms_piston) *truth_rms_piston = sqrt(s2 / ws);
    if (truth_rms_ptt) {
        memcpy(d, truth, n * n * sizeof *d);
        *truth_rms_ptt = swfs_wfe_remove_ptt(d, mask, n);
    }
    swfs_free(d);
    return SWFS_OK;
}

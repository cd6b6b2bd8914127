/* The product files of the method modules: PUPIL.fits (pupil.h), COH.fits and the
 * coherence input (coherence.h), OFFSETS.fits (dmfit.h), reconstructor and actuator files
 * (wfs.h), the closed-loop folder (closed_loop.h). The method code computes arrays; only
 * this layer reads and writes files. */
#include "specklewfs/atomic.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/coherence.h"
#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int swfs_pupil_write(const swfs_pupil_result *r, const char *path, const swfs_geom *g, const char *const *prov,
                     size_t nprov)
{
    swfs_fits_out *o;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_set_stamp(o, g, prov, nprov);
    if (!rc) rc = swfs_fits_out_geom(o, g);
    if (!rc) rc = swfs_fits_out_provenance(o, prov, nprov);
    if (!rc) rc = swfs_fits_out_key_double(o, "WFERMS", r->wfe_rms, "[m] WFE rms in the pupil, piston removed");
    if (!rc) rc = swfs_fits_out_key_double(o, "WFEPV", r->wfe_pv, "[m] WFE peak to valley in the pupil");
    if (!rc) rc = swfs_fits_out_key_double(o, "STREHL", r->strehl, "Marechal estimate from WFERMS");
    const swfs_jointfit_result *f = r->method == SWFS_PUPIL_FIT ? r->fit : NULL;
    if (!rc) rc = swfs_fits_out_key_string(o, "METHOD", f ? "FIT" : "MOMENTS",
                                           f ? "joint pupil-domain fit (docs/estimator.md)" : "per-pixel moments");
    if (!rc && !f) rc = swfs_fits_out_key_string(o, "SOURCE", r->opt.source == SWFS_SOURCE_HALO ? "HALO" : "HALO_LF",
                                                 "halo extension transformed");
    if (!rc && !f) rc = swfs_fits_out_key_string(o, "WEIGHT", r->opt.weight == SWFS_WEIGHT_SNR ? "snr" : "none",
                                                 "focal-plane weighting");
    if (!rc && !f) rc = swfs_fits_out_key_double(o, "WIENERK", r->opt.wiener_k, "k in SNR^2/(SNR^2+k^2)");
    if (!rc && !f) rc = swfs_fits_out_key_double(o, "BIAS", r->opt.bias, "constant field / mean pupil field");
    if (!rc && f) rc = swfs_fits_out_key_double(o, "FITKAPPA", f->kappa, "unexplained speckle power fraction");
    if (!rc && f && isfinite(r->explained))
        rc = swfs_fits_out_key_double(o, "SPKEXPL", r->explained, "science variance the speckles explain");
    if (!rc && f && isfinite(r->explained_median))
        rc = swfs_fits_out_key_double(o, "SPKEXPLM", r->explained_median, "the same, median pixel");
    if (!rc && f) rc = swfs_fits_out_key_double(o, "FITCHI2", f->chi2, "chi-square of the fit to the statistics");
    if (!rc && f) rc = swfs_fits_out_key_long(o, "FITNPIX", (long)f->npix, "focal pixels fitted");
    if (!rc && f) rc = swfs_fits_out_key_long(o, "FITNPAR", (long)f->nparams, "parameters fitted");
    if (!rc && f) rc = swfs_fits_out_key_long(o, "FITNSPL", (long)f->nintervals, "B-spline intervals across D");
    if (!rc && f) rc = swfs_fits_out_key_double(o, "FITLPHI", f->lambda_phi, "phase prior weight (evidence)");
    if (!rc && f) rc = swfs_fits_out_key_double(o, "FITLAMP", f->lambda_alpha, "log-amplitude prior weight");
    if (!rc && f) rc = swfs_fits_out_key_double(o, "FITNSCL", f->noise_scale, "data weight (evidence): dof / chi2");
    if (!rc && f) rc = swfs_fits_out_key_long(o, "FITITER", (long)f->iterations, "Levenberg-Marquardt steps");
    if (!rc && f && isfinite(f->log_evidence))
        rc = swfs_fits_out_key_long(o, "FITWARM", (long)f->warm_start, "1: the warm start's evidence fixed point kept");
    if (!rc && f && isfinite(f->log_evidence))
        rc = swfs_fits_out_key_double(o, "FITLEVD", f->log_evidence, "log evidence of the kept fixed point");
    if (!rc && f && isfinite(f->log_evidence) && !isnan(f->log_evidence_alt))
        rc = swfs_fits_out_key_double(o, "FITLEVA", isfinite(f->log_evidence_alt) ? f->log_evidence_alt : -1e300,
                                      "log evidence of the other start's");
    if (!rc && f) rc = swfs_fits_out_key_string(o, "FITICPT", f->intercept == SWFS_JF_INTERCEPT_FREE ? "FREE" : "MODEL",
                                                "mean intensity: modelled or free per pixel");
    if (!rc && f && isfinite(f->delta_chi2))
        rc = swfs_fits_out_key_double(o, "FITDCHI2", f->delta_chi2, "(chi2(model) - chi2(free)) x noise scale");
    if (!rc && f && isfinite(f->delta_chi2_limit))
        rc = swfs_fits_out_key_double(o, "FITDCLIM", f->delta_chi2_limit, "the model is kept below this");
    if (!rc && f && isfinite(f->delta_chi2))
        rc = swfs_fits_out_key_long(o, "FITDCSTP", (long)f->model_stopped,
                                    "1: model's fit stopped once out of the limit's reach");
    if (!rc) rc = swfs_fits_out_key_double(o, "RESMRMS", r->resmean_rms,
                                           "[m] AO residual's time mean taken out of WFE");
    if (!rc) rc = swfs_fits_out_cplx(o, "FIELD", r->field, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "EQUATION", "eq:Pupil-field-with-NCP1", NULL);
    if (!rc) rc = swfs_fits_out_real(o, "WFE", r->wfe, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "eq:NCP-WFE-estimate, piston removed");
    if (!rc) rc = swfs_fits_out_real(o, "SURFACE", r->surface, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "WFE/2 for a reflective DM");
    if (!rc) rc = swfs_fits_out_real(o, "AMPLITUDE", r->amplitude, -64);
    if (!rc) rc = swfs_fits_out_real(o, "PUPIL", r->mask, -32);
    if (!rc && f) rc = swfs_fits_out_cplx(o, "HALO_FIT", f->halo, -64);
    if (!rc && f) rc = swfs_fits_out_key_string(o, "COMMENT", "Psi of the joint fit, frame of psi - <psi>", NULL);
    if (!rc && f) rc = swfs_fits_out_real(o, "GAIN_FIT", f->gain, -64);
    if (!rc && f) rc = swfs_fits_out_key_string(o, "COMMENT", "g of the joint fit (smooth log-g map)", NULL);
    if (!rc && r->resmean) rc = swfs_fits_out_real(o, "RESMEAN", r->resmean, -64);
    if (!rc && r->resmean)
        rc = swfs_fits_out_key_string(o, "BUNIT", "m", "AO residual's time mean taken out (band-limited)");
    if (!rc && f && r->explained_map) rc = swfs_fits_out_real(o, "EXPLAINED", r->explained_map, -32);
    if (!rc && f && r->explained_map)
        rc = swfs_fits_out_key_string(o, "COMMENT", "self-check: science variance the speckles explain, per pixel", NULL);
    if (rc) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

int swfs_pupil_mask_read(const char *path, size_t n, swfs_real **out)
{
    *out = NULL;
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc && swfs_fits_in_has_ext(f, "PUPIL")) rc = swfs_fits_in_move(f, "PUPIL");
    if (!rc) rc = swfs_fits_in_read_real_all(f, out);
    swfs_fits_in_close(f);
    if (!rc && ((*out)->nx != n || (*out)->ny != n || (*out)->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: pupil mask is %zux%zux%zu but the pupil grid is pupn x pupn = %zux%zu", path,
                       (*out)->nx, (*out)->ny, (*out)->nz, n, n);
    if (!rc) rc = swfs_pupil_mask_check(*out, path);
    if (rc) {
        swfs_real_free(*out);
        *out = NULL;
    }
    return rc;
}

/* The lag keywords of a space-time reconstructor (NLAGS, LAG1 .. LAGn). */
static int lag_keys(swfs_fits_out *o, const swfs_recon *r)
{
    int rc = swfs_fits_out_key_long(o, "NLAGS", (long)r->nlags, "space-time: planes = slopes of frame t + LAGk");
    for (size_t k = 0; !rc && k < r->nlags; k++) {
        char key[32];
        snprintf(key, sizeof key, "LAG%zu", k + 1);
        rc = swfs_fits_out_key_long(o, key, r->lags[k], "[WFS frames] plane's frame offset");
    }
    return rc;
}

int swfs_recon_write_hdu(swfs_fits_out *o, const swfs_recon *r)
{
    const size_t nl = r->nlags ? r->nlags : 1, ns = r->nslopes / nl;
    double *cube = NULL;
    if (r->nlags) { /* W (nact x ns nl, lag blocks) -> planes of ns x nact */
        if (!(cube = malloc(r->nslopes * r->nact * sizeof *cube)))
            return swfs_fail(SWFS_ERR_NOMEM, "reconstructor: out of memory");
        for (size_t k = 0; k < nl; k++)
            for (size_t a = 0; a < r->nact; a++)
                memcpy(cube + (k * r->nact + a) * ns, r->W + a * r->nslopes + k * ns, ns * sizeof *cube);
    }
    swfs_real a = {ns, r->nact, nl, cube ? cube : r->W};
    int rc = swfs_fits_out_real(o, NULL, &a, -64);
    if (!rc && r->nlags) rc = lag_keys(o, r);
    free(cube);
    return rc;
}

int swfs_outxy_write(swfs_fits_out *o, const double *xy, size_t n, const char *what)
{
    int rc = swfs_fits_out_real(o, "OUTXY", &(swfs_real){2, n, 1, (double *)xy}, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", what);
    return rc;
}

int swfs_recon_write_outxy(swfs_fits_out *o, const swfs_recon *r)
{
    return r->oxy ? swfs_outxy_write(o, r->oxy, r->nact, "the map's output points (x, y), pupil frame") : SWFS_OK;
}

int swfs_outxy_read(const char *path, size_t n, double **xy)
{
    *xy = NULL;
    swfs_fits_in *f = NULL;
    swfs_real *a = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (rc || !swfs_fits_in_has_ext(f, "OUTXY")) {
        swfs_fits_in_close(f);
        return rc;
    }
    if (!(rc = swfs_fits_in_move(f, "OUTXY"))) rc = swfs_fits_in_read_real_all(f, &a);
    swfs_fits_in_close(f);
    if (rc) return rc;
    if (a->nx != 2 || a->ny != n || a->nz != 1)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: extension OUTXY is %zu x %zu x %zu; expected 2 x %zu (the %zu output points "
                       "of the primary image, x and y [m])", path, a->nx, a->ny, a->nz, n, n);
    for (size_t i = 0; !rc && i < 2 * n; i++)
        if (!isfinite(a->data[i])) rc = swfs_fail(SWFS_ERR_VALUE, "%s: OUTXY entry %zu is not finite", path, i);
    if (!rc && !(*xy = malloc(2 * n * sizeof **xy))) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    if (!rc) memcpy(*xy, a->data, 2 * n * sizeof **xy);
    swfs_real_free(a);
    return rc;
}

int swfs_recon_write(const swfs_recon *r, const char *path)
{
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (!rc) rc = swfs_recon_write_hdu(o, r);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m/rad", "actuator displacement per slope");
    if (!rc) rc = swfs_fits_out_key_long(o, "NMODES", (long)r->nmodes, "SVD modes kept");
    if (!rc) rc = swfs_fits_out_history(o, "specklewfs reconstructor: z_act = W s, NAXIS1 = slopes, NAXIS2 = actuators");
    if (!rc) rc = swfs_recon_write_outxy(o, r);
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

int swfs_lags_read(const char *path, size_t nz, long *lags)
{
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    long n = 0;
    int found = 0;
    if (!rc) rc = swfs_fits_in_key_long_opt(f, "NLAGS", 1, SWFS_RECON_MAXLAGS, &n, &found);
    if (!rc && (!found || (size_t)n != nz))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: a space-time reconstructor of %zu planes needs NLAGS = %zu and LAG1 .. LAG%zu "
                       "(found %s)", path, nz, nz, nz, found ? "another NLAGS" : "no NLAGS");
    for (long k = 0; !rc && k < n; k++) {
        char key[32];
        snprintf(key, sizeof key, "LAG%ld", k + 1);
        rc = swfs_fits_in_key_long_opt(f, key, LONG_MIN, LONG_MAX, &lags[k], &found); /* checked below */
        if (!rc && !found) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: NLAGS = %ld but no %s", path, n, key);
    }
    swfs_fits_in_close(f);
    if (!rc) rc = swfs_lags_check(lags, nz, path);
    return rc;
}

int swfs_recon_read(const char *path, swfs_recon **out)
{
    *out = NULL;
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nz < 1 || a->nz > SWFS_RECON_MAXLAGS || a->nx < 2 || a->nx % 2) {
        size_t nx = a->nx, ny = a->ny, nz = a->nz;
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_FORMAT, "%s: a reconstructor is an image of nslopes (even: x then y slopes) x nact, or "
                         "a space-time one's cube of them (at most %d lags), got %zux%zux%zu", path, SWFS_RECON_MAXLAGS,
                         nx, ny, nz);
    }
    const size_t ns = a->nx, na = a->ny, nl = a->nz;
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = malloc(ns * na * nl * sizeof *r->W);
    if (!r || !r->W) { swfs_real_free(a); swfs_recon_free(r); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    r->nslopes = ns * nl; r->nact = na;
    for (size_t i = 0; i < ns * na * nl; i++) {
        if (!isfinite(a->data[i])) {
            swfs_real_free(a); swfs_recon_free(r);
            return swfs_fail(SWFS_ERR_VALUE, "%s: reconstructor entry %zu is not finite", path, i);
        }
    }
    /* planes of ns x nact -> W (nact x ns nl, lag blocks) */
    for (size_t k = 0; k < nl; k++)
        for (size_t j = 0; j < na; j++)
            memcpy(r->W + j * r->nslopes + k * ns, a->data + (k * na + j) * ns, ns * sizeof *r->W);
    r->nmodes = 0;
    swfs_real_free(a);
    if (nl > 1 && !(rc = swfs_lags_read(path, nl, r->lags))) r->nlags = nl;
    if (rc || (rc = swfs_outxy_read(path, r->nact, &r->oxy))) {
        swfs_recon_free(r);
        return rc;
    }
    *out = r;
    return SWFS_OK;
}

int swfs_actuators_write(const double *xy, size_t nact, const char *path)
{
    swfs_real a = {2, nact, 1, (double *)xy};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_real(o, NULL, &a, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "actuator (x, y) in the pupil frame");
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

int swfs_valid_map_read(const char *path, unsigned char **map, size_t *nsub, size_t *nvalid)
{
    *map = NULL;
    *nsub = *nvalid = 0;
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nx != a->ny || a->nz != 1 || a->nx < 1 || a->nx > 4096) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: a valid-subaperture map is a square nsub x nsub image (nonzero = used), "
                       "got %zu x %zu x %zu", path, a->nx, a->ny, a->nz);
        swfs_real_free(a);
        return rc;
    }
    const size_t n = a->nx, nsa = n * n;
    unsigned char *m = malloc(nsa);
    if (!m) {
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    size_t nv = 0;
    for (size_t i = 0; i < nsa; i++) {
        const double v = a->data[i];
        if (!isfinite(v)) {
            char val[48];
            free(m);
            swfs_real_free(a);
            return swfs_fail(SWFS_ERR_VALUE, "%s: subaperture (%zu, %zu) %s; expected 0 (unused) or nonzero (used)",
                             path, i % n, i / n, swfs_value_words(v, val, sizeof val));
        }
        nv += (m[i] = v != 0);
    }
    swfs_real_free(a);
    if (!nv) {
        free(m);
        return swfs_fail(SWFS_ERR_VALUE, "%s: no subaperture is used (all %zu values are 0)", path, nsa);
    }
    *map = m;
    *nsub = n;
    *nvalid = nv;
    return SWFS_OK;
}

int swfs_actuators_read(const char *path, double **xy, size_t *nact)
{
    *xy = NULL;
    *nact = 0;
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nx != 2 || a->nz != 1) {
        size_t nx = a->nx;
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_FORMAT, "%s: actuator positions must be a 2 x nact image, NAXIS1 is %zu", path, nx);
    }
    /* Positions in the pupil frame [m]: finite, within a kilometre, at least three. */
    for (size_t i = 0; i < 2 * a->ny; i++)
        if (!isfinite(a->data[i]) || fabs(a->data[i]) > 1e3) {
            double v = a->data[i];
            size_t k = i / 2;
            swfs_real_free(a);
            return swfs_fail(SWFS_ERR_VALUE, "%s: actuator %zu has %c = %g m; positions must be finite and within "
                             "1 km of the pupil centre", path, k, i % 2 ? 'y' : 'x', v);
        }
    if (a->ny < 3) {
        size_t n = a->ny;
        swfs_real_free(a);
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %zu actuator(s); the interpolation needs at least 3", path, n);
    }
    double *p = malloc(2 * a->ny * sizeof *p);
    if (!p) { swfs_real_free(a); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    memcpy(p, a->data, 2 * a->ny * sizeof *p);
    *nact = a->ny;
    *xy = p;
    swfs_real_free(a);
    return SWFS_OK;
}

static int write_map(swfs_fits_out *o, const char *ext, const swfs_real *a, const char *bunit, const char *what)
{
    int rc = swfs_fits_out_real(o, ext, a, -32);
    if (!rc && bunit) rc = swfs_fits_out_key_string(o, "BUNIT", bunit, NULL);
    if (!rc && what) rc = swfs_fits_out_key_string(o, "CONTENTS", what, NULL);
    return rc;
}

int swfs_coherence_write(const swfs_coherence *c, const char *path, const swfs_geom *g,
                         const char *const *prov, size_t nprov)
{
    swfs_fits_out *o;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_set_stamp(o, g, prov, nprov);
    /* Primary: the summary. */
    if (!rc) rc = swfs_fits_out_key_double(o, "FRAMEDT", c->framedt, "[s] between WFS frames");
    if (!rc && g) rc = swfs_fits_out_geom(o, g);
    if (!rc) rc = swfs_fits_out_provenance(o, prov, nprov);
    if (!rc) rc = swfs_fits_out_key_long(o, "NFRAMES", (long)c->nframes, "WFS frames used");
    if (!rc) rc = swfs_fits_out_key_long(o, "NLAGS", (long)c->nlags, "lags in MCF and LAGS");
    if (!rc) rc = swfs_fits_out_key_long(o, "MAXLAG", c->max_lag, "[frames] largest lag computed");
    if (!rc) rc = swfs_fits_out_key_long(o, "NFIT", c->nfit, "[frames] phase-rate fit over lags 1..NFIT");
    if (!rc) rc = swfs_fits_out_key_double(o, "EXPOSURE", c->exposure, "[s] camera exposure of SNR_FACT (0: none)");
    if (!rc) rc = swfs_fits_out_key_long(o, "NVALID", (long)c->n_valid, "pixels with speckle power");
    if (!rc) rc = swfs_fits_out_key_long(o, "NNOPOWER", (long)c->n_nopower, "pixels without speckle power (NaN)");
    if (!rc) rc = swfs_fits_out_key_long(o, "NNONFIN", (long)c->n_nonfinite, "pixels with non-finite speckles (NaN)");
    if (!rc) rc = swfs_fits_out_key_long(o, "NTAU0INF", (long)c->n_tau0_beyond, "pixels with TAU0 beyond MAXLAG (+Inf)");
    if (!rc) rc = swfs_fits_out_key_string(o, "COHMETH", c->method == SWFS_COH_FFT ? "FFT" : "DIRECT",
                                           "autocorrelation by FFT along time or direct sums");
    if (!rc) rc = write_map(o, "MEAN_SP", c->mean_sp, NULL, "Phi_sp = Gamma(0), mean speckle power");
    if (!rc) rc = write_map(o, "TAU0", c->tau0, "s", "|Gamma(tau)/Gamma(0)| first below exp(-1/2); +Inf: beyond MAXLAG");
    if (!rc) rc = write_map(o, "TROT", c->trot, "s", "(pi/2)/|PHRATE|: time for the phase to turn by pi/2");
    if (!rc) rc = write_map(o, "PHRATE", c->phrate, "rad/s", "d arg Gamma(tau)/d tau; frozen flow: +k theta.v");
    if (!rc && c->snr_fact) {
        rc = write_map(o, "SNR_FACT", c->snr_fact, NULL, "eq:MCF-SNReffect x2 (1 = coherent) at EXPOSURE");
        if (!rc) rc = swfs_fits_out_key_double(o, "EXPOSURE", c->exposure, "[s] camera exposure");
    }
    if (!rc) rc = swfs_fits_out_cplx(o, "MCF", c->mcf, -32);
    if (!rc) rc = swfs_fits_out_key_string(o, "CONTENTS", "Gamma(tau)/Gamma(0), lag along the last axis (see LAGS)", NULL);
    if (!rc) rc = swfs_fits_out_real(o, "LAGS", c->lags, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "s", NULL);
    if (!rc) rc = swfs_fits_out_key_string(o, "CONTENTS", "lags of the MCF planes (NLAGS x 1 image)", NULL);
    if (!rc) rc = swfs_fits_out_key_double(o, "FRAMEDT", c->framedt, "[s] between WFS frames");
    if (rc) {
        swfs_fits_out_abort(o);
        return swfs_fail_context(rc, "writing %s", path);
    }
    return swfs_fits_out_commit(o);
}

int swfs_coherence_read_input(const char *path, swfs_cplx **cube, double *framedt, swfs_geom *g, double *exposure)
{
    *cube = NULL;
    if (exposure) *exposure = 0;
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (rc) return rc;
    int found = 0;
    double dt = NAN;
    rc = swfs_fits_in_key_double_opt(f, "FRAMEDT", &dt, &found);
    if (!rc && !found)
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: missing keyword FRAMEDT (seconds between WFS frames); the "
                       "coherence needs a WFS-rate cube", path);
    /* (a WFS frame of more than a minute is no AO loop's: a corrupt header) */
    if (!rc && !(dt > 0 && dt <= 60))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: FRAMEDT = %g, expected a positive number of seconds (at most 60)", path, dt);
    if (!rc && !swfs_fits_in_shape(f)->is_complex)
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: expected a complex speckle cube (NAXIS1 = 2, CTYPE1 = 'COMPLEX')", path);
    if (!rc && g) rc = swfs_fits_in_geom(f, g);
    if (!rc && exposure) {
        double v = 0;
        rc = swfs_fits_in_key_double_opt(f, "CAMEXP", &v, &found);
        if (!rc && found && !(v > 0 && isfinite(v)))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: CAMEXP = %g, expected the camera's exposure, a positive number of "
                           "seconds", path, v);
        if (!rc && found) *exposure = v;
        if (!rc && !found) {
            rc = swfs_fits_in_key_double_opt(f, "FRATIO", &v, &found);
            if (!rc && found && !(v > 0 && isfinite(v)))
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: FRATIO = %g, expected WFS frames per camera frame, a positive "
                               "number", path, v);
            if (!rc && found) *exposure = v * dt;
        }
    }
    if (!rc) rc = swfs_fits_in_read_cplx_all(f, cube);
    swfs_fits_in_close(f);
    if (!rc) *framedt = dt;
    return rc;
}

int swfs_dmfit_write(const swfs_dmfit *f, const double *cmd, const double *target, const swfs_dmfit_stats *st,
                     const char *path, const swfs_geom *g, const char *const *prov, size_t nprov)
{
    const size_t np = swfs_dmfit_npup(f), nact = swfs_dmfit_nact(f);
    const swfs_dmfit_options *fo = swfs_dmfit_opts(f);
    const double *fmask = swfs_dmfit_mask(f);
    swfs_real *off = swfs_real_alloc(nact, 1, 1), *act = swfs_real_alloc(2, nact, 1);
    swfs_real *surf = swfs_real_alloc(np, np, 1), *unfit = swfs_real_alloc(np, np, 1), *pm = swfs_real_alloc(np, np, 1);
    swfs_fits_out *o = NULL;
    int rc = SWFS_OK;
    if (!off || !act || !surf || !unfit || !pm) { rc = SWFS_ERR_NOMEM; goto done; }
    memcpy(off->data, cmd, nact * sizeof *cmd);
    memcpy(act->data, swfs_dmfit_xy(f), 2 * nact * sizeof(double));
    memcpy(pm->data, fmask, np * np * sizeof *fmask);
    swfs_dmfit_surface(f, cmd, surf->data);
    for (size_t s = 0; s < np * np; s++) unfit->data[s] = fmask[s] > 0 ? target[s] - surf->data[s] : 0.0;
    if ((rc = swfs_fits_out_create(&o, path))) goto done;
    if ((rc = swfs_fits_out_set_stamp(o, g, prov, nprov))) goto done;
    if ((rc = swfs_fits_out_real(o, "OFFSETS", off, -64))) goto done;
    rc = swfs_fits_out_key_string(o, "BUNIT", "m", "DM surface offset per actuator (wavefront change = 2x)");
    if (!rc) rc = swfs_fits_out_key_string(o, "INFLUENC", fo->influence == SWFS_INFLUENCE_CUBIC ? "cubic" : "gauss",
                                           "influence functions: gauss or cubic (Clough-Tocher)");
    if (!rc && fo->influence == SWFS_INFLUENCE_GAUSS)
        rc = swfs_fits_out_key_double(o, "COUPLING", fo->coupling, "Gaussian influence at one pitch");
    if (!rc) rc = swfs_fits_out_key_double(o, "ACTPITCH", swfs_dmfit_pitch(f), "[m] actuator pitch used");
    if (!rc) rc = swfs_fits_out_key_long(o, "NACT", (long)nact, "actuators");
    if (!rc) rc = swfs_fits_out_key_long(o, "NACTIVE", (long)swfs_dmfit_active(f), "actuators reaching the pupil");
    if (!rc) rc = swfs_fits_out_key_long(o, "NMODES", (long)fo->modes, "Noll Zernikes kept (0 = no modal filter)");
    if (!rc) rc = swfs_fits_out_key_double(o, "DMREG", fo->reg, "Tikhonov mu relative to the mean diagonal");
    if (!rc && st) {
        rc = swfs_fits_out_key_double(o, "TGTRMS", st->target_rms, "[m] target surface rms (-WFE/2)");
        if (!rc) rc = swfs_fits_out_key_double(o, "MODERMS", st->modal_rms, "[m] its part in the kept modes");
        if (!rc) rc = swfs_fits_out_key_double(o, "FILTRMS", st->filtered_rms, "[m] left out by the modal filter");
        if (!rc) rc = swfs_fits_out_key_double(o, "FITRMS", st->fit_rms, "[m] fitted DM surface rms");
        if (!rc) rc = swfs_fits_out_key_double(o, "FITERRMS", st->fiterr_rms, "[m] DM fitting error");
        if (!rc) rc = swfs_fits_out_key_double(o, "UNFITRMS", st->unfit_rms, "[m] target - fitted surface rms");
    }
    if (rc) goto done;
    if ((rc = swfs_fits_out_real(o, "ACTUATORS", act, -64))) goto done;
    if ((rc = swfs_fits_out_key_string(o, "BUNIT", "m", "actuator (x, y) in the pupil frame"))) goto done;
    if ((rc = swfs_fits_out_real(o, "SURFACE", surf, -64))) goto done;
    if ((rc = swfs_fits_out_key_string(o, "BUNIT", "m", "DM surface made by OFFSETS"))) goto done;
    if ((rc = swfs_fits_out_real(o, "UNFIT", unfit, -64))) goto done;
    if ((rc = swfs_fits_out_key_string(o, "BUNIT", "m", "target - SURFACE inside the pupil"))) goto done;
    if ((rc = swfs_fits_out_real(o, "PUPIL", pm, -32))) goto done;
    rc = swfs_fits_out_commit(o);
    o = NULL;
done:
    swfs_fits_out_abort(o);
    swfs_real_free(off);
    swfs_real_free(act);
    swfs_real_free(surf);
    swfs_real_free(unfit);
    swfs_real_free(pm);
    if (rc == SWFS_ERR_NOMEM) swfs_fail(rc, "%s: out of memory", path);
    return rc;
}

int swfs_closed_loop_write(const swfs_loop_result *r, const char *dir, const char *const *prov, size_t nprov)
{
    char path[4096];
    if (snprintf(path, sizeof path, "%s/loop.tsv", dir) >= (int)sizeof path)
        return swfs_fail(SWFS_ERR_ARG, "%s: folder name too long", dir);
    swfs_atomic *tsv = NULL;
    int rc = swfs_atomic_begin(&tsv, path, 1);
    if (rc) return rc;
    FILE *fp = swfs_atomic_stream(tsv);
    /* Table columns: also the METRICS image rows below. */
    static const char *cols[] = {"iter", "resid_nm", "resid_ptt_nm", "strehl", "strehl_ao", "strehl_marechal",
                                 "contrast", "contrast_ao", "contrast_ncp", "est_nm", "est_err_nm", "median_snr", "fit_nm",
                                 "unfit_nm", "fiterr_nm", "filtered_nm", "cmd_rms_nm", "seconds"};
    enum { NCOL = sizeof cols / sizeof cols[0] };
    swfs_real *met = swfs_real_alloc(NCOL, r->nrows, 1);
    if (!met) { swfs_atomic_abort(tsv); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    for (size_t c = 0; c < NCOL; c++) fprintf(fp, "%s%s", c ? "\t" : "# ", cols[c]);
    fputc('\n', fp);
    for (size_t k = 0; k < r->nrows; k++) {
        const swfs_loop_iter *it = &r->rows[k];
        const double v[NCOL] = {(double)k, it->resid_rms * 1e9, it->resid_rms_ptt * 1e9, it->strehl, it->strehl_ao,
                                it->strehl_marechal, it->contrast, it->contrast_ao, it->contrast_ncp, it->est_rms * 1e9, it->est_err * 1e9,
                                it->median_snr, it->fit.fit_rms * 1e9, it->fit.unfit_rms * 1e9, it->fit.fiterr_rms * 1e9,
                                it->fit.filtered_rms * 1e9, it->fit.cmd_rms * 1e9, it->seconds};
        for (size_t c = 0; c < NCOL; c++) {
            fprintf(fp, c ? "\t%.6g" : "%.0f", v[c]);
            met->data[k * NCOL + c] = v[c];
        }
        fputc('\n', fp);
    }
    if ((rc = swfs_atomic_commit(tsv))) {
        swfs_real_free(met);
        return rc;
    }

    snprintf(path, sizeof path, "%s/loop.fits", dir);
    swfs_fits_out *o = NULL;
    rc = swfs_fits_out_create(&o, path);
    if (!rc) rc = swfs_fits_out_set_stamp(o, &r->geom, prov, nprov);
    if (!rc) rc = swfs_fits_out_real(o, "METRICS", met, -64);
    for (size_t c = 0; !rc && c < NCOL; c++) {
        char key[16];
        snprintf(key, sizeof key, "TTYPE%zu", c + 1);
        rc = swfs_fits_out_key_string(o, key, cols[c], "column of METRICS (row = state after k corrections)");
    }
    if (!rc) rc = swfs_fits_out_key_long(o, "NITER", (long)(r->nrows - 1), "corrections applied");
    if (!rc) rc = swfs_fits_out_key_double(o, "LOOPGAIN", r->params.gain, "loop gain");
    if (!rc) rc = swfs_fits_out_key_double(o, "NOISESIG", r->params.sigma, "[counts] camera background noise");
    if (!rc) rc = swfs_fits_out_key_double(o, "ACTPITCH", r->pitch, "[m] influence pitch");
    if (!rc) rc = swfs_fits_out_key_string(o, "INFLUENC", r->params.fit.influence == SWFS_INFLUENCE_CUBIC ? "cubic" : "gauss",
                                           "influence functions");
    if (!rc) rc = swfs_fits_out_key_double(o, "COUPLING", r->params.fit.coupling, "Gaussian influence at one pitch");
    if (!rc) rc = swfs_fits_out_key_long(o, "NMODES", (long)r->params.fit.modes, "Zernike modal filter (0 = none)");
    if (!rc) rc = swfs_fits_out_real(o, "RESIDUAL", r->residual, -32);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "residual NCP wavefront after k corrections");
    if (!rc) rc = swfs_fits_out_real(o, "ESTIMATE", r->estimate, -32);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "estimated WFE in state k");
    if (!rc) rc = swfs_fits_out_real(o, "DMSURF", r->dm_surface, -32);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "accumulated DM surface in state k");
    if (!rc) rc = swfs_fits_out_real(o, "COMMANDS", r->commands, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "accumulated actuator commands in state k");
    if (!rc) rc = swfs_fits_out_real(o, "ACTUATORS", r->actuators, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "actuator (x, y)");
    if (!rc) rc = swfs_fits_out_real(o, "PUPIL", r->pupil, -32);
    if (!rc) {
        rc = swfs_fits_out_commit(o);
        o = NULL;
    }
    swfs_fits_out_abort(o);
    swfs_real_free(met);
    return rc;
}

/* The random-reference estimator: per-pixel statistics -> Psi, g, V, SNR.
 * See include/specklewfs/estimate.h and paper Sec. 2.2-2.4. */
#include "specklewfs/numeric.h"
#include "specklewfs/estimate.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_halo_free(swfs_halo *h)
{
    if (!h) return;
    swfs_cplx_free(h->halo); swfs_cplx_free(h->halo_lf); swfs_cplx_free(h->stab);
    swfs_real_free(h->gain); swfs_real_free(h->gain_pix); swfs_real_free(h->visib); swfs_real_free(h->snr);
    swfs_real_free(h->mean_i); swfs_real_free(h->var_i); swfs_real_free(h->mean_sp);
    swfs_real_free(h->var_sp); swfs_real_free(h->stab_err); swfs_real_free(h->circ);
    swfs_real_free(h->valid); swfs_real_free(h->nframes);
    swfs_regress_free(h->reg);
    swfs_real_free(h->resmean);
    free(h);
}

/* The regression statistics travel with the halo (HALO.fits REGSTATE) when they cover the
 * same frames as the moments; otherwise the halo has none (h->reg = NULL). */
static int copy_regress(const swfs_accum *acc, swfs_regress **out)
{
    *out = NULL;
    if (!swfs_accum_has_regress(acc)) return SWFS_OK;
    swfs_regress *r = swfs_regress_create(acc->nx, acc->ny);
    if (!r) return SWFS_ERR_NOMEM;
    int rc = swfs_regress_merge(r, acc->reg);
    if (rc) { swfs_regress_free(r); return rc; }
    *out = r;
    return SWFS_OK;
}

/* Median of the valid per-pixel g in the smallest square window around (i, j) that holds
 * at least SWFS_G_FALLBACK_MIN of them (or all of them). */
static double fallback_g(const swfs_halo *h, size_t i, size_t j, double *scratch)
{
    const size_t nx = h->nx, ny = h->ny;
    const size_t hmax = nx > ny ? nx : ny;
    size_t cnt = 0;
    for (size_t r = 1; r <= hmax; r++) {
        cnt = 0;
        size_t x0 = i >= r ? i - r : 0, x1 = i + r < nx ? i + r : nx - 1;
        size_t y0 = j >= r ? j - r : 0, y1 = j + r < ny ? j + r : ny - 1;
        for (size_t y = y0; y <= y1; y++)
            for (size_t x = x0; x <= x1; x++)
                if (h->valid->data[y * nx + x] > 0.5) scratch[cnt++] = h->gain_pix->data[y * nx + x];
        if (cnt >= SWFS_G_FALLBACK_MIN || (x0 == 0 && y0 == 0 && x1 == nx - 1 && y1 == ny - 1)) break;
    }
    return swfs_median_inplace(scratch, cnt);
}

/* Separable Gaussian smoothing (sigma in pixels, truncated at 4 sigma) of v into out,
 * zero outside the map; tmp is nx*ny scratch. */
static void gauss_smooth(const double *v, size_t nx, size_t ny, double sigma, double *tmp, double *out)
{
    const long r = (long)ceil(4.0 * sigma);
    double kern[512];
    const long rr = r < 255 ? r : 255;
    for (long k = -rr; k <= rr; k++) kern[k + rr] = exp(-0.5 * (double)(k * k) / (sigma * sigma));
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            double s = 0.0;
            for (long k = -rr; k <= rr; k++) {
                long x = (long)i + k;
                if (x >= 0 && x < (long)nx) s += kern[k + rr] * v[j * nx + (size_t)x];
            }
            tmp[j * nx + i] = s;
        }
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            double s = 0.0;
            for (long k = -rr; k <= rr; k++) {
                long y = (long)j + k;
                if (y >= 0 && y < (long)ny) s += kern[k + rr] * tmp[(size_t)y * nx + i];
            }
            out[j * nx + i] = s;
        }
}

/* The regularized scale factor (see estimate.h). rdb: debiased radicands (NaN where the
 * pixel has no speckles); g: in, the starting g per pixel; out, the regularized g where the
 * chosen average of the radicand is positive, the map-wide mean elsewhere. noise_var:
 * per-pixel camera noise; sigma: the ladder's reference scale [pixels].
 *
 * The average is an inverse-variance weighted mean over a Gaussian neighbourhood. Its scale
 * is chosen per pixel by the intersection of confidence intervals (Goldenshluger &
 * Nemirovski; Katkovnik's LPA-ICI): on a ladder of scales growing by 2 from half a pixel
 * (sigma 2^k, k in Z), the interval [r_s - G se_s, r_s + G se_s] of each scale is intersected
 * with those of all smaller scales, and the largest scale whose running intersection is not
 * empty is kept. A larger scale only lowers the variance; it is refused once its estimate
 * leaves what the smaller, less biased scales allow, i.e. where the radicand really varies
 * beyond the noise. So at high SNR g follows a varying gain pixel by pixel, and at low SNR
 * the scale grows until the noise is averaged down (to the whole map if need be): the
 * smoothing follows the information (docs/estimator.md has the measurements). */
static int regularize_g(swfs_halo *h, const double *rdb, const double *noise_var, double sigma, double *g)
{
    const size_t nx = h->nx, ny = h->ny, np = nx * ny;
    const double largest = (double)(nx > ny ? nx : ny);
    double *buf = swfs_calloc(10 * np, sizeof *buf);
    if (!buf) return SWFS_ERR_NOMEM;
    double *w = buf, *wr = buf + np, *k1 = buf + 2 * np, *k1r = buf + 3 * np, *k2 = buf + 4 * np;
    double *tmp = buf + 5 * np, *g_start = buf + 6 * np, *lo = buf + 7 * np, *hi = buf + 8 * np, *rch = buf + 9 * np;
    memcpy(g_start, g, np * sizeof *g);
    /* the ladder sigma 2^k from its first rung at or below half a pixel (one pixel's weight
       dominates there) up to beyond the map, where every pixel gets the map-wide mean */
    double s0 = sigma;
    while (s0 > 0.5) s0 *= 0.5;
    for (int it = 0; it < 3; it++) {
        double W = 0.0, WR = 0.0;
        for (size_t p = 0; p < np; p++) {
            w[p] = wr[p] = 0.0;
            if (!isfinite(rdb[p]) || !(g[p] > 0.0)) continue;
            /* A pixel whose intensity does not fluctuate at all (dead, saturated, a
             * constant fill) carries no information on the speckle modulation: no weight,
             * its g comes from its neighbours. */
            if (!(h->var_i->data[p] + noise_var[p] > 0.0)) continue;
            /* Model variance of I from the intensity model (eq:betterVariance) and the
             * noise: sigma_I^2 = noise + 2 g^2 |Psi|^2 Phi_sp + g^4 sigma_sp^2, |Psi|^2 from
             * eq:betterMean. Var of a sample variance ~ 2 sigma^4 / N. The weights use
             * only well-measured quantities, so they do not follow the radicand's noise. */
            const double g2 = g[p] * g[p], phi_sp = h->mean_sp->data[p], vsp = h->var_sp->data[p];
            const double psi2 = fmax(h->mean_i->data[p] - g2 * phi_sp, 0.0);
            const double s2 = noise_var[p] + 2.0 * g2 * psi2 * phi_sp + g2 * g2 * vsp;
            const double var_r = 2.0 * s2 * s2 / (h->nframes->data[p] * vsp * vsp);
            if (!(var_r > 0.0) || !isfinite(var_r)) continue;
            w[p] = 1.0 / var_r;
            wr[p] = w[p] * rdb[p];
            W += w[p];
            WR += wr[p];
        }
        const double r_global = W > 0.0 ? WR / W : NAN;
        memcpy(g, g_start, np * sizeof *g);
        if (!(r_global > 0.0)) continue; /* nothing to regularize towards: keep the fallback */
        for (size_t p = 0; p < np; p++) {
            lo[p] = -INFINITY;
            hi[p] = INFINITY;
            rch[p] = NAN;
        }
        for (double sg = s0; sg < 4.0 * largest; sg *= 2.0) {
            gauss_smooth(w, nx, ny, sg, tmp, k1);
            gauss_smooth(wr, nx, ny, sg, tmp, k1r);
            /* sum K^2 w for the standard error: K^2 of a Gaussian of sigma sg is a Gaussian
             * of sg / sqrt(2). */
            gauss_smooth(w, nx, ny, sg / M_SQRT2, tmp, k2);
            for (size_t p = 0; p < np; p++) {
                if (!(lo[p] <= hi[p]) || !isfinite(rdb[p]) || !(k1[p] > 0.0)) continue;
                const double r = k1r[p] / k1[p], se = sqrt(k2[p]) / k1[p];
                lo[p] = fmax(lo[p], r - SWFS_G_ICI_GAMMA * se);
                hi[p] = fmin(hi[p], r + SWFS_G_ICI_GAMMA * se);
                if (lo[p] <= hi[p]) rch[p] = r;
            }
        }
        for (size_t p = 0; p < np; p++)
            if (isfinite(rdb[p])) g[p] = sqrt(sqrt(rch[p] > 0.0 ? rch[p] : r_global));
    }
    swfs_free(buf);
    return SWFS_OK;
}

/* The halo with every map allocated (NULL when out of memory). */
static swfs_halo *halo_alloc(const swfs_accum *acc, const swfs_noise *nz, double g_smooth)
{
    const size_t nx = acc->nx, ny = acc->ny;
    swfs_halo *h = calloc(1, sizeof *h);
    if (!h) return NULL;
    h->nx = nx; h->ny = ny; h->npix = nx * ny; h->noise = *nz; h->g_smooth = g_smooth;
    h->frames = acc->frames; h->skipped = acc->skipped;
    h->halo = swfs_cplx_alloc(nx, ny, 1); h->halo_lf = swfs_cplx_alloc(nx, ny, 1);
    h->stab = swfs_cplx_alloc(nx, ny, 1);
    h->gain = swfs_real_alloc(nx, ny, 1); h->gain_pix = swfs_real_alloc(nx, ny, 1);
    h->visib = swfs_real_alloc(nx, ny, 1);
    h->snr = swfs_real_alloc(nx, ny, 1); h->mean_i = swfs_real_alloc(nx, ny, 1);
    h->var_i = swfs_real_alloc(nx, ny, 1); h->mean_sp = swfs_real_alloc(nx, ny, 1);
    h->var_sp = swfs_real_alloc(nx, ny, 1); h->stab_err = swfs_real_alloc(nx, ny, 1);
    h->circ = swfs_real_alloc(nx, ny, 1); h->valid = swfs_real_alloc(nx, ny, 1);
    h->nframes = swfs_real_alloc(nx, ny, 1);
    if (!h->halo || !h->halo_lf || !h->stab || !h->gain || !h->gain_pix || !h->visib || !h->snr || !h->mean_i ||
        !h->var_i || !h->mean_sp || !h->var_sp || !h->stab_err || !h->circ || !h->valid || !h->nframes) {
        swfs_halo_free(h);
        return NULL;
    }
    return h;
}

/* Pass 1 at pixel p: the moments and the paper's per-pixel g; rdb[p] the debiased
 * radicand (NaN without speckles), nvar[p] the camera noise variance. */
static void pixel_moments(swfs_halo *h, double *const *f, size_t p, double *rdb, double *nvar)
{
    const swfs_noise nz = h->noise;
    const double n = f[SWFS_ACC_N][p];
    h->nframes->data[p] = n;
    rdb[p] = NAN;
    h->gain_pix->data[p] = NAN;
    if (n < 2.0) {
        h->n_no_frames++;
        h->gain->data[p] = h->visib->data[p] = h->snr->data[p] = NAN;
        h->mean_i->data[p] = h->var_i->data[p] = h->mean_sp->data[p] = h->var_sp->data[p] = NAN;
        h->stab_err->data[p] = h->circ->data[p] = NAN;
        nvar[p] = NAN;
        return;
    }
    const double r = 1.0 / n; /* the paper's 1/N statistics (Sec. 4.4) */
    const double phi_i = f[SWFS_ACC_MI][p];
    const double var_raw = f[SWFS_ACC_CII][p] * r;
    const double noise_var = nz.read_noise * nz.read_noise + (nz.gain > 0.0 ? fmax(phi_i, 0.0) / nz.gain : 0.0);
    /* Sec. 2.3: remove the noise variance. The sample variance with 1/N (the paper's
     * convention) is low by sigma^2/N, which against a noise variance much larger than
     * the speckle signal (faint halo, bright background) is a real bias; the noise is
     * removed from the unbiased 1/(N-1) variance instead. */
    const double var_i = f[SWFS_ACC_CII][p] / (n - 1.0) - noise_var;
    /* A variance below the noise alone, beyond its 3-sigma scatter (a sample variance
     * scatters by sqrt(2/(N-1)) of itself), means the noise model is too large. */
    if (noise_var > 0.0 && var_i < -3.0 * noise_var * sqrt(2.0 / (n - 1.0))) h->n_var_below_noise++;
    const double complex stab = (f[SWFS_ACC_CIX][p] + I * f[SWFS_ACC_CIY][p]) * r;
    const double vxx = f[SWFS_ACC_CXX][p] * r, vyy = f[SWFS_ACC_CYY][p] * r, vxy = f[SWFS_ACC_CXY][p] * r;
    const double phi_sp = vxx + vyy;
    /* Var |psi - m|^2 with |psi - m|^2 = A - 2 (x mx + y my) + |m|^2. */
    const double mx = f[SWFS_ACC_MX][p], my = f[SWFS_ACC_MY][p];
    const double var_sp = (f[SWFS_ACC_CAA][p] + 4.0 * (mx * mx * f[SWFS_ACC_CXX][p] + my * my * f[SWFS_ACC_CYY][p]) +
                           8.0 * mx * my * f[SWFS_ACC_CXY][p] - 4.0 * (mx * f[SWFS_ACC_CXA][p] + my * f[SWFS_ACC_CYA][p])) * r;
    const double s2 = creal(stab) * creal(stab) + cimag(stab) * cimag(stab);
    /* Standard error of <psi' I>: for circular complex Gaussian psi' jointly Gaussian
     * with I', Isserlis gives Var(psi' I') = Phi_sp sigma_I,raw^2 + |<psi' I'>|^2. */
    const double e2 = (phi_sp * var_raw + s2) * r;

    nvar[p] = noise_var;
    h->mean_i->data[p] = phi_i;
    h->var_i->data[p] = var_i;
    h->mean_sp->data[p] = phi_sp;
    h->var_sp->data[p] = var_sp;
    h->stab->data[p] = stab;
    h->stab_err->data[p] = sqrt(e2);
    h->circ->data[p] = phi_sp > 0.0 ? cabs((vxx - vyy) + 2.0 * I * vxy) / phi_sp : NAN; /* eq:zeroSqMean */
    h->visib->data[p] = phi_i > 0.0 && phi_sp > 0.0 ? 2.0 * sqrt(s2) / (phi_i * sqrt(phi_sp)) : NAN; /* eq:visibility */
    h->snr->data[p] = noise_var > 0.0 && phi_sp > 0.0 ? 2.0 * sqrt(s2) / (sqrt(noise_var) * sqrt(phi_sp)) : NAN; /* eq:SNR */

    if (!(phi_sp > 0.0) || !(var_sp > 0.0)) {
        h->n_no_speckle++;
        h->gain->data[p] = NAN;
        return;
    }
    /* eq:scale-factor */
    const double radicand = var_i / var_sp - 2.0 * s2 / (phi_sp * var_sp);
    /* The same with |<psi' I>|^2 debiased by its noise power, for the regularized g. */
    rdb[p] = var_i / var_sp - 2.0 * (s2 - e2) / (phi_sp * var_sp);
    if (radicand < h->radicand_min) h->radicand_min = radicand;
    if (radicand > 0.0 && isfinite(radicand)) {
        h->gain_pix->data[p] = sqrt(sqrt(radicand));
        h->valid->data[p] = 1.0;
        h->n_valid++;
    } else {
        h->n_bad_radicand++;
    }
}

/* Pass 2: g for every pixel with speckles. Start from the paper's g where it is defined
 * and the local median of valid neighbours elsewhere; then regularize. */
static int scale_factor(swfs_halo *h, const double *rdb, const double *nvar, double g_smooth, double *scratch)
{
    const size_t nx = h->nx, np = h->npix;
    for (size_t p = 0; p < np; p++) {
        if (!isfinite(rdb[p])) continue;
        if (h->valid->data[p] > 0.5) {
            h->gain->data[p] = h->gain_pix->data[p];
        } else {
            h->gain->data[p] = fallback_g(h, p % nx, p / nx, scratch);
            h->n_g_fallback++;
        }
    }
    if (g_smooth > 0.0) {
        memcpy(scratch, h->gain->data, np * sizeof(double));
        int rc = regularize_g(h, rdb, nvar, g_smooth, h->gain->data);
        if (rc) return rc;
        h->n_g_fallback = 0;
        for (size_t p = 0; p < np; p++)
            if (isfinite(rdb[p]) && h->valid->data[p] < 0.5 && h->gain->data[p] == scratch[p]) h->n_g_fallback++;
    }
    return SWFS_OK;
}

/* Pass 3: the halo (eq:TheAnswer) and its low-frequency form (eq:PSI-LowFreq), the median
 * SNR over valid pixels and the valid fraction. */
static void halo_maps(swfs_halo *h, double *scratch)
{
    const size_t np = h->npix;
    size_t nsnr = 0;
    for (size_t p = 0; p < np; p++) {
        const double g = h->gain->data[p], phi_sp = h->mean_sp->data[p];
        if (!(g > 0.0) || !(phi_sp > 0.0) || !(h->var_sp->data[p] > 0.0)) {
            h->halo->data[p] = 0.0;
            h->halo_lf->data[p] = 0.0;
            continue;
        }
        const double complex stab = h->stab->data[p];
        h->halo->data[p] = stab / (g * phi_sp);
        const double amp2 = h->mean_i->data[p] - g * g * phi_sp;
        const double amp = amp2 > 0.0 ? sqrt(amp2) : 0.0;
        h->halo_lf->data[p] = cabs(stab) > 0.0 ? amp * stab / cabs(stab) : 0.0;
        if (h->valid->data[p] > 0.5 && isfinite(h->snr->data[p])) scratch[nsnr++] = h->snr->data[p];
    }
    h->median_snr = swfs_median_inplace(scratch, nsnr);
    h->valid_fraction = (double)h->n_valid / (double)np;
}

int swfs_estimate(const swfs_accum *acc, const swfs_noise *noise, const swfs_estimate_options *opt, swfs_halo **out)
{
    *out = NULL;
    const size_t np = acc->nx * acc->ny;
    swfs_noise nz = {0.0, 0.0};
    if (noise) nz = *noise;
    swfs_estimate_options o = {SWFS_G_SMOOTH_DEFAULT};
    if (opt) o = *opt;
    if (!(nz.read_noise >= 0.0) || !(nz.gain >= 0.0) || !isfinite(nz.read_noise) || !isfinite(nz.gain))
        return swfs_fail(SWFS_ERR_ARG, "noise model: read noise %g counts and gain %g e-/count must be finite "
                         "and >= 0", nz.read_noise, nz.gain);
    if (!(o.g_smooth >= 0.0) || o.g_smooth > 60.0)
        return swfs_fail(SWFS_ERR_ARG, "g smoothing %g pixels: expected 0 (per-pixel) to 60", o.g_smooth);

    swfs_halo *h = halo_alloc(acc, &nz, o.g_smooth);
    double *scratch = swfs_malloc(np * sizeof(double));
    double *rdb = swfs_malloc(np * sizeof(double));  /* debiased radicand, NaN without speckles */
    double *nvar = swfs_malloc(np * sizeof(double)); /* camera noise variance per pixel */
    int rc = SWFS_OK;
    if (!h || !scratch || !rdb || !nvar) {
        rc = h ? SWFS_ERR_NOMEM : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        goto fail;
    }
    h->radicand_min = INFINITY;
    for (size_t p = 0; p < np; p++) pixel_moments(h, acc->f, p, rdb, nvar);
    if (h->n_valid == 0 && h->n_no_frames == np) {
        rc = swfs_fail(SWFS_ERR_VALUE, "no pixel has 2 frames with finite values (science or speckles NaN or Inf "
                       "everywhere but in at most one frame of each pixel): nothing to estimate from");
        goto fail;
    }
    if (h->n_valid == 0) {
        rc = swfs_fail(SWFS_ERR_NUMERIC,
                       "no pixel has a defined scale factor g: the radicand of eq:scale-factor is <= 0 in %zu "
                       "pixels (most negative %.3g), %zu pixels have no speckle power and %zu fewer than 2 "
                       "frames; is the noise model (read noise %g, gain %g) too large, or are the science and "
                       "speckle cubes unrelated?", h->n_bad_radicand, h->radicand_min, h->n_no_speckle,
                       h->n_no_frames, nz.read_noise, nz.gain);
        goto fail;
    }
    if ((rc = scale_factor(h, rdb, nvar, o.g_smooth, scratch))) goto fail;
    halo_maps(h, scratch);
    swfs_free(scratch);
    swfs_free(rdb);
    swfs_free(nvar);
    if ((rc = copy_regress(acc, &h->reg))) goto fail_late;
    *out = h;
    return SWFS_OK;
fail_late:
    swfs_halo_free(h);
    return rc;
fail:
    swfs_free(scratch);
    swfs_free(rdb);
    swfs_free(nvar);
    swfs_halo_free(h);
    return rc;
}

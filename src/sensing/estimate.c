/* The random-reference estimator: per-pixel statistics -> Psi, g, V, SNR.
 * See include/specklewfs/estimate.h and paper Sec. 2.2-2.4. */
#include "specklewfs/estimate.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_halo_free(swfs_halo *h)
{
    if (!h) return;
    swfs_cplx_free(h->halo); swfs_cplx_free(h->halo_lf); swfs_cplx_free(h->stab);
    swfs_real_free(h->gain); swfs_real_free(h->visib); swfs_real_free(h->snr);
    swfs_real_free(h->mean_i); swfs_real_free(h->var_i); swfs_real_free(h->mean_sp);
    swfs_real_free(h->var_sp); swfs_real_free(h->stab_err); swfs_real_free(h->circ);
    swfs_real_free(h->valid); swfs_real_free(h->nframes);
    free(h);
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* Median of the valid g values in the smallest square window around (i, j) that holds
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
                if (h->valid->data[y * nx + x] > 0.5) scratch[cnt++] = h->gain->data[y * nx + x];
        if (cnt >= SWFS_G_FALLBACK_MIN || (x0 == 0 && y0 == 0 && x1 == nx - 1 && y1 == ny - 1)) break;
    }
    if (!cnt) return NAN;
    qsort(scratch, cnt, sizeof *scratch, cmp_double);
    return cnt % 2 ? scratch[cnt / 2] : 0.5 * (scratch[cnt / 2 - 1] + scratch[cnt / 2]);
}

int swfs_estimate(const swfs_accum *acc, const swfs_noise *noise, swfs_halo **out)
{
    *out = NULL;
    const size_t nx = acc->nx, ny = acc->ny, np = nx * ny;
    swfs_noise nz = {0.0, 0.0};
    if (noise) nz = *noise;
    if (!(nz.read_noise >= 0.0) || !(nz.gain >= 0.0) || !isfinite(nz.read_noise) || !isfinite(nz.gain))
        return swfs_fail(SWFS_ERR_ARG, "noise model: read noise %g counts and gain %g e-/count must be finite "
                         "and >= 0", nz.read_noise, nz.gain);

    swfs_halo *h = calloc(1, sizeof *h);
    if (!h) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    h->nx = nx; h->ny = ny; h->npix = np; h->noise = nz;
    h->frames = acc->frames; h->skipped = acc->skipped;
    h->halo = swfs_cplx_alloc(nx, ny, 1); h->halo_lf = swfs_cplx_alloc(nx, ny, 1);
    h->stab = swfs_cplx_alloc(nx, ny, 1);
    h->gain = swfs_real_alloc(nx, ny, 1); h->visib = swfs_real_alloc(nx, ny, 1);
    h->snr = swfs_real_alloc(nx, ny, 1); h->mean_i = swfs_real_alloc(nx, ny, 1);
    h->var_i = swfs_real_alloc(nx, ny, 1); h->mean_sp = swfs_real_alloc(nx, ny, 1);
    h->var_sp = swfs_real_alloc(nx, ny, 1); h->stab_err = swfs_real_alloc(nx, ny, 1);
    h->circ = swfs_real_alloc(nx, ny, 1); h->valid = swfs_real_alloc(nx, ny, 1);
    h->nframes = swfs_real_alloc(nx, ny, 1);
    double *scratch = swfs_malloc(np * sizeof(double));
    if (!h->halo || !h->halo_lf || !h->stab || !h->gain || !h->visib || !h->snr || !h->mean_i || !h->var_i ||
        !h->mean_sp || !h->var_sp || !h->stab_err || !h->circ || !h->valid || !h->nframes || !scratch) {
        swfs_free(scratch);
        swfs_halo_free(h);
        return SWFS_ERR_NOMEM;
    }

    double *const *f = acc->f;
    h->radicand_min = INFINITY;
    /* Pass 1: moments, g where defined. */
    for (size_t p = 0; p < np; p++) {
        const double n = f[SWFS_ACC_N][p];
        h->nframes->data[p] = n;
        if (n < 2.0) {
            h->n_no_frames++;
            h->gain->data[p] = h->visib->data[p] = h->snr->data[p] = NAN;
            h->mean_i->data[p] = h->var_i->data[p] = h->mean_sp->data[p] = h->var_sp->data[p] = NAN;
            h->stab_err->data[p] = h->circ->data[p] = NAN;
            continue;
        }
        const double r = 1.0 / n; /* the paper's 1/N statistics (Sec. 4.4) */
        const double phi_i = f[SWFS_ACC_MI][p];
        const double var_raw = f[SWFS_ACC_CII][p] * r;
        const double noise_var = nz.read_noise * nz.read_noise + (nz.gain > 0.0 ? fmax(phi_i, 0.0) / nz.gain : 0.0);
        const double var_i = var_raw - noise_var;
        const double complex stab = (f[SWFS_ACC_CIX][p] + I * f[SWFS_ACC_CIY][p]) * r;
        const double vxx = f[SWFS_ACC_CXX][p] * r, vyy = f[SWFS_ACC_CYY][p] * r, vxy = f[SWFS_ACC_CXY][p] * r;
        const double phi_sp = vxx + vyy;
        /* Var |psi - m|^2 with |psi - m|^2 = A - 2 (x mx + y my) + |m|^2. */
        const double mx = f[SWFS_ACC_MX][p], my = f[SWFS_ACC_MY][p];
        const double var_sp = (f[SWFS_ACC_CAA][p] + 4.0 * (mx * mx * f[SWFS_ACC_CXX][p] + my * my * f[SWFS_ACC_CYY][p]) +
                               8.0 * mx * my * f[SWFS_ACC_CXY][p] - 4.0 * (mx * f[SWFS_ACC_CXA][p] + my * f[SWFS_ACC_CYA][p])) * r;
        const double s2 = creal(stab) * creal(stab) + cimag(stab) * cimag(stab);

        h->mean_i->data[p] = phi_i;
        h->var_i->data[p] = var_i;
        h->mean_sp->data[p] = phi_sp;
        h->var_sp->data[p] = var_sp;
        h->stab->data[p] = stab;
        /* Standard error of <psi' I>: for circular complex Gaussian psi' jointly Gaussian
         * with I', Isserlis gives Var(psi' I') = Phi_sp sigma_I,raw^2 + |<psi' I'>|^2. */
        h->stab_err->data[p] = sqrt((phi_sp * var_raw + s2) * r);
        h->circ->data[p] = phi_sp > 0.0 ? cabs((vxx - vyy) + 2.0 * I * vxy) / phi_sp : NAN;
        h->visib->data[p] = phi_i > 0.0 && phi_sp > 0.0 ? 2.0 * sqrt(s2) / (phi_i * sqrt(phi_sp)) : NAN; /* eq:visibility */
        h->snr->data[p] = noise_var > 0.0 && phi_sp > 0.0 ? 2.0 * sqrt(s2) / (sqrt(noise_var) * sqrt(phi_sp)) : NAN; /* eq:SNR */

        if (!(phi_sp > 0.0) || !(var_sp > 0.0)) {
            h->n_no_speckle++;
            h->gain->data[p] = NAN;
            continue;
        }
        /* eq:scale-factor */
        const double radicand = var_i / var_sp - 2.0 * s2 / (phi_sp * var_sp);
        if (radicand < h->radicand_min) h->radicand_min = radicand;
        if (radicand > 0.0 && isfinite(radicand)) {
            h->gain->data[p] = sqrt(sqrt(radicand));
            h->valid->data[p] = 1.0;
            h->n_valid++;
        } else {
            h->n_bad_radicand++;
            h->gain->data[p] = NAN;
        }
    }
    if (h->n_valid == 0) {
        int rc = swfs_fail(SWFS_ERR_NUMERIC,
                           "no pixel has a defined scale factor g: the radicand of eq:scale-factor is <= 0 in %zu "
                           "pixels (most negative %.3g), %zu pixels have no speckle power and %zu fewer than 2 "
                           "frames; is the noise model (read noise %g, gain %g) too large, or are the science and "
                           "speckle cubes unrelated?", h->n_bad_radicand, h->radicand_min, h->n_no_speckle,
                           h->n_no_frames, nz.read_noise, nz.gain);
        swfs_free(scratch);
        swfs_halo_free(h);
        return rc;
    }
    /* Pass 2: fallback g where undefined but speckles exist. It reads only valid pixels
     * and writes to a copy, so the order of filling does not matter. */
    double *gfb = swfs_malloc(np * sizeof(double));
    if (!gfb) { swfs_free(scratch); swfs_halo_free(h); return SWFS_ERR_NOMEM; }
    for (size_t p = 0; p < np; p++) {
        gfb[p] = h->gain->data[p];
        if (h->valid->data[p] < 0.5 && h->mean_sp->data[p] > 0.0 && h->var_sp->data[p] > 0.0)
            gfb[p] = fallback_g(h, p % nx, p / nx, scratch);
    }
    memcpy(h->gain->data, gfb, np * sizeof(double));
    swfs_free(gfb);

    /* Pass 3: the halo (eq:TheAnswer) and its low-frequency form (eq:PSI-LowFreq). */
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
    if (nsnr) {
        qsort(scratch, nsnr, sizeof *scratch, cmp_double);
        h->median_snr = nsnr % 2 ? scratch[nsnr / 2] : 0.5 * (scratch[nsnr / 2 - 1] + scratch[nsnr / 2]);
    } else {
        h->median_snr = NAN;
    }
    h->valid_fraction = (double)h->n_valid / (double)np;
    swfs_free(scratch);
    *out = h;
    return SWFS_OK;
}

/* Science-camera frame reduction (paper Sec. 4.3), see reduce.h. */
#include "../core/planner.h"
#include "specklewfs/numeric.h"
#include "specklewfs/reduce.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <fftw3.h>

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_reduce_params_default(swfs_reduce_params *p)
{
    p->hot_sigma = 8;
    p->flat_min = 0.5;
    p->flat_max = 1.5;
    p->gauss_sigma = 2;
    p->do_register = 1;
    p->bg_radius = 0;
    p->pixscale = 0;
    p->gain = 0;
}

struct swfs_reduce {
    size_t nx, ny;
    swfs_reduce_params p;
    double *dark, *flat;
    unsigned char *bad;
    size_t nbad;
    double *work;        /* 2 nx ny */
    double *frame;       /* nx ny */
    size_t *bg;          /* indices of the source-free pixels */
    size_t nbg;
    double *bg_mean, *bg_m2; /* Welford per source-free pixel */
    size_t nframes;
    /* Out-of-band noise estimate. */
    fftw_plan plan;
    double *fin, *hann;
    fftw_complex *fout;
    unsigned char *oob;      /* (nx/2+1) * ny: 1 where |f| is beyond the cutoff */
    double hann2;            /* sum of the window squared */
    size_t noob;
    double spec_sum;         /* sum over frames of the per-frame estimates */
    size_t spec_n;
    double q_sum;            /* sum over registered frames of the interpolation's variance factor */
    size_t q_n;
};


void swfs_reduce_free(swfs_reduce *r)
{
    if (!r) return;
    free(r->dark); free(r->flat); free(r->bad); free(r->work); free(r->frame);
    free(r->bg); free(r->bg_mean); free(r->bg_m2);
    if (r->plan) {
        swfs_planner_lock();
        fftw_destroy_plan(r->plan);
        swfs_planner_unlock();
    }
    fftw_free(r->fin); fftw_free(r->fout);
    free(r->hann); free(r->oob);
    free(r);
}

size_t swfs_reduce_nbad(const swfs_reduce *r) { return r->nbad; }
const unsigned char *swfs_reduce_badmap(const swfs_reduce *r) { return r->bad; }

int swfs_reduce_create(swfs_reduce **out, size_t nx, size_t ny, const double *dark, const double *flat,
                       const double *badmap, const swfs_reduce_params *p)
{
    *out = NULL;
    if (nx < 3 || ny < 3) return swfs_fail(SWFS_ERR_ARG, "reduce: frame %zux%zu is too small (at least 3x3)", nx, ny);
    if (!(p->gauss_sigma > 0 && p->gauss_sigma <= 1e4))
        return swfs_fail(SWFS_ERR_ARG, "reduce: reference peak sigma %g pixels, expected 0 < sigma <= 1e4", p->gauss_sigma);
    if (!(p->hot_sigma > 0 && p->hot_sigma <= 1e6))
        return swfs_fail(SWFS_ERR_ARG, "reduce: hot-pixel threshold %g sigma, expected 0 < threshold <= 1e6", p->hot_sigma);
    if (!(p->flat_min < p->flat_max))
        return swfs_fail(SWFS_ERR_ARG, "reduce: flat range [%g, %g], expected min < max", p->flat_min, p->flat_max);
    if (!(p->bg_radius >= 0 && p->bg_radius <= 1e7))
        return swfs_fail(SWFS_ERR_ARG, "reduce: background radius %g pixels, expected 0 .. 1e7", p->bg_radius);
    size_t n = nx * ny;
    swfs_reduce *r = calloc(1, sizeof *r);
    if (!r) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    r->nx = nx; r->ny = ny; r->p = *p;
    r->dark = malloc(n * sizeof *r->dark);
    r->flat = malloc(n * sizeof *r->flat);
    r->bad = calloc(n, 1);
    r->work = malloc(2 * n * sizeof *r->work);
    r->frame = malloc(n * sizeof *r->frame);
    r->bg = malloc(n * sizeof *r->bg);
    if (!r->dark || !r->flat || !r->bad || !r->work || !r->frame || !r->bg) {
        swfs_reduce_free(r);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t i = 0; i < n; i++) {
        r->dark[i] = dark ? dark[i] : 0.0;
        r->flat[i] = flat ? flat[i] : 1.0;
        if (badmap && badmap[i] != 0) r->bad[i] = 1;
        if (!isfinite(r->dark[i]) || !isfinite(r->flat[i])) r->bad[i] = 1;
    }
    /* Hot pixels: robust (median, 1.4826 MAD) outliers of the dark. */
    if (dark) {
        size_t m = 0;
        for (size_t i = 0; i < n; i++) if (!r->bad[i]) r->work[m++] = r->dark[i];
        if (m > 0) {
            double med = swfs_median_inplace(r->work, m);
            m = 0;
            for (size_t i = 0; i < n; i++) if (!r->bad[i]) r->work[m++] = fabs(r->dark[i] - med);
            double sig = 1.4826 * swfs_median_inplace(r->work, m);
            if (sig > 0)
                for (size_t i = 0; i < n; i++)
                    if (fabs(r->dark[i] - med) > p->hot_sigma * sig) r->bad[i] = 1;
        }
    }
    /* Dead or hot flat pixels, relative to the flat's median. */
    if (flat) {
        size_t m = 0;
        for (size_t i = 0; i < n; i++) if (!r->bad[i]) r->work[m++] = r->flat[i];
        double med = m ? swfs_median_inplace(r->work, m) : 1.0;
        if (!(med > 0)) { swfs_reduce_free(r); return swfs_fail(SWFS_ERR_VALUE, "reduce: flat field median %g is not positive", med); }
        for (size_t i = 0; i < n; i++) {
            if (r->bad[i]) continue;
            double f = r->flat[i] / med;
            if (!(f >= p->flat_min && f <= p->flat_max)) r->bad[i] = 1;
        }
    }
    for (size_t i = 0; i < n; i++) {
        r->nbad += r->bad[i];
        if (!(r->flat[i] > 0)) r->flat[i] = 1.0; /* flagged anyway: avoid dividing by 0 */
        if (!isfinite(r->dark[i])) r->dark[i] = 0.0; /* flagged: keep the raw value finite */
    }
    if (r->nbad * 2 > n) {
        size_t nb = r->nbad;
        swfs_reduce_free(r);
        return swfs_fail(SWFS_ERR_VALUE, "reduce: %zu of %zu pixels are bad (dark/flat do not match the frames?)", nb, n);
    }
    double rad = p->bg_radius > 0 ? p->bg_radius : 0.45 * (double)(nx < ny ? nx : ny);
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            double dx = (double)i - (double)(nx / 2), dy = (double)j - (double)(ny / 2);
            if (sqrt(dx * dx + dy * dy) > rad && !r->bad[j * nx + i]) r->bg[r->nbg++] = j * nx + i;
        }
    if (r->nbg == 0 && !(p->pixscale > 0 && p->pixscale < 0.45)) {
        swfs_reduce_free(r);
        return swfs_fail(SWFS_ERR_ARG, "reduce: background radius %g pixels leaves no good pixel for the noise estimate in a "
                         "%zux%zu frame (expected a radius below the frame's half-diagonal)", rad, nx, ny);
    }
    if (p->pixscale > 0 && p->pixscale < 0.45) {
        size_t nh = nx / 2 + 1;
        r->fin = fftw_malloc(n * sizeof *r->fin);
        r->fout = fftw_malloc(nh * ny * sizeof *r->fout);
        r->hann = malloc(n * sizeof *r->hann);
        r->oob = calloc(nh * ny, 1);
        if (!r->fin || !r->fout || !r->hann || !r->oob) { swfs_reduce_free(r); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
        swfs_planner_lock();
        r->plan = fftw_plan_dft_r2c_2d((int)ny, (int)nx, r->fin, r->fout, FFTW_ESTIMATE);
        swfs_planner_unlock();
        if (!r->plan) { swfs_reduce_free(r); return swfs_fail(SWFS_ERR_INTERNAL, "reduce: FFTW plan failed"); }
        for (size_t j = 0; j < ny; j++)
            for (size_t i = 0; i < nx; i++) {
                double w = (0.5 - 0.5 * cos(2 * M_PI * ((double)i + 0.5) / (double)nx)) *
                           (0.5 - 0.5 * cos(2 * M_PI * ((double)j + 0.5) / (double)ny));
                r->hann[j * nx + i] = w;
                r->hann2 += w * w;
            }
        /* Beyond the optical cutoff PIXSCALE cycles/pixel by 2 bins (the window's width). */
        for (size_t j = 0; j < ny; j++)
            for (size_t i = 0; i < nh; i++) {
                double fx = (double)i / (double)nx, fy = (double)swfs_fft_freq_index(j, ny) / (double)ny;
                double fmargin = 2.0 / (double)(nx < ny ? nx : ny);
                if (sqrt(fx * fx + fy * fy) > p->pixscale + fmargin) { r->oob[j * nh + i] = 1; r->noob++; }
            }
        if (r->noob < 8) {
            swfs_reduce_free(r);
            return swfs_fail(SWFS_ERR_ARG, "reduce: PIXSCALE %g leaves no spatial frequency beyond the optical cutoff in a "
                             "%zux%zu frame", p->pixscale, nx, ny);
        }
    }
    r->bg_mean = calloc(r->nbg ? r->nbg : 1, sizeof *r->bg_mean);
    r->bg_m2 = calloc(r->nbg ? r->nbg : 1, sizeof *r->bg_m2);
    if (!r->bg_mean || !r->bg_m2) { swfs_reduce_free(r); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    *out = r;
    return SWFS_OK;
}

void swfs_badpix_replace(double *img, size_t nx, size_t ny, const unsigned char *bad, double *work)
{
    /* Medians are taken from the unflagged, finite neighbours of the input (a copy in
     * work), so replacements do not feed each other. */
    memcpy(work, img, nx * ny * sizeof *work);
    const double *src = work;
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            size_t k = j * nx + i;
            if (!bad[k] && isfinite(src[k])) continue;
            double v[8];
            size_t m = 0;
            for (long dj = -1; dj <= 1; dj++)
                for (long di = -1; di <= 1; di++) {
                    long ii = (long)i + di, jj = (long)j + dj;
                    if ((di == 0 && dj == 0) || ii < 0 || jj < 0 || ii >= (long)nx || jj >= (long)ny) continue;
                    size_t kk = (size_t)jj * nx + (size_t)ii;
                    if (!bad[kk] && isfinite(src[kk])) v[m++] = src[kk];
                }
            if (m) img[k] = swfs_median_inplace(v, m);
        }
}

/* Sub-pixel vertex of three samples: log-parabola (exact for a Gaussian) when all are
 * positive, else a parabola. */
static double vertex3(double a, double b, double c)
{
    double den;
    if (a > 0 && b > 0 && c > 0) {
        double la = log(a), lb = log(b), lc = log(c);
        den = la - 2 * lb + lc;
        if (den < 0) return 0.5 * (la - lc) / den;
    }
    den = a - 2 * b + c;
    if (den < 0) {
        double v = 0.5 * (a - c) / den;
        return v > 0.5 ? 0.5 : (v < -0.5 ? -0.5 : v);
    }
    return 0;
}

int swfs_peak_gauss(const double *img, size_t nx, size_t ny, double sigma, double *work, double *px, double *py)
{
    /* Separable correlation with a unit Gaussian: rows into work, then columns into
     * work + nx ny. */
    /* Clamped before the conversion: (long) of 3e300 is undefined. */
    const double r3 = ceil(3 * sigma);
    const long rad = r3 > 128 ? 128 : (r3 > 0 ? (long)r3 : 0);
    double kern[257];
    for (long t = -rad; t <= rad; t++) kern[t + rad] = exp(-0.5 * (double)(t * t) / (sigma * sigma));
    double *tmp = work, *cor = work + nx * ny;
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            double s = 0;
            for (long t = -rad; t <= rad; t++) {
                long ii = (long)i + t;
                if (ii < 0 || ii >= (long)nx) continue;
                double v = img[j * nx + (size_t)ii];
                if (isfinite(v)) s += kern[t + rad] * v;
            }
            tmp[j * nx + i] = s;
        }
    size_t best = 0;
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            double s = 0;
            for (long t = -rad; t <= rad; t++) {
                long jj = (long)j + t;
                if (jj < 0 || jj >= (long)ny) continue;
                s += kern[t + rad] * tmp[(size_t)jj * nx + i];
            }
            cor[j * nx + i] = s;
            if (s > cor[best]) best = j * nx + i;
        }
    size_t bi = best % nx, bj = best / nx;
    if (!(cor[best] > 0)) return swfs_fail(SWFS_ERR_NUMERIC, "registration: no positive peak in the frame");
    double fx = 0, fy = 0;
    if (bi > 0 && bi + 1 < nx) fx = vertex3(cor[best - 1], cor[best], cor[best + 1]);
    if (bj > 0 && bj + 1 < ny) fy = vertex3(cor[best - nx], cor[best], cor[best + nx]);
    *px = (double)bi + fx;
    *py = (double)bj + fy;
    return SWFS_OK;
}

void swfs_shift_bilinear(const double *img, size_t nx, size_t ny, double sx, double sy, double *out)
{
    double fx0 = floor(sx), fy0 = floor(sy);
    double ax = sx - fx0, ay = sy - fy0;
    long ox = (long)fx0, oy = (long)fy0;
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            long x0 = (long)i + ox, y0 = (long)j + oy;
            /* Exact integer shifts need only one source pixel. */
            long x1 = ax > 0 ? x0 + 1 : x0, y1 = ay > 0 ? y0 + 1 : y0;
            if (x0 < 0 || y0 < 0 || x1 >= (long)nx || y1 >= (long)ny) { out[j * nx + i] = NAN; continue; }
            double v00 = img[(size_t)y0 * nx + (size_t)x0], v10 = img[(size_t)y0 * nx + (size_t)x1];
            double v01 = img[(size_t)y1 * nx + (size_t)x0], v11 = img[(size_t)y1 * nx + (size_t)x1];
            out[j * nx + i] = (1 - ay) * ((1 - ax) * v00 + ax * v10) + ay * ((1 - ax) * v01 + ax * v11);
        }
}

int swfs_reduce_frame(swfs_reduce *r, const double *raw, double *out, double *px, double *py)
{
    size_t n = r->nx * r->ny;
    double *f = r->frame;
    for (size_t i = 0; i < n; i++) f[i] = (raw[i] - r->dark[i]) / r->flat[i];
    swfs_badpix_replace(f, r->nx, r->ny, r->bad, r->work);
    /* Noise variance: Welford over frames on the source-free pixels. */
    r->nframes++;
    for (size_t b = 0; b < r->nbg; b++) {
        double v = f[r->bg[b]];
        if (!isfinite(v)) continue;
        double d = v - r->bg_mean[b];
        r->bg_mean[b] += d / (double)r->nframes;
        r->bg_m2[b] += d * (v - r->bg_mean[b]);
    }
    if (r->plan) {
        /* Out-of-band power of the Hann-windowed, mean-removed frame: white noise only.
         * Each r2c bin stands for itself and its conjugate, so the mean over the half
         * plane is the mean over the full plane. (A bad pixel replaced by its 3x3 median
         * next to the bright core leaves a sharp error that counts here as noise: see
         * docs/telemetry.md.) */
        /* Pixels still non-finite (no finite neighbour to take the median of) count as the mean. */
        double m = 0;
        size_t nf = 0;
        for (size_t i = 0; i < n; i++)
            if (isfinite(f[i])) { m += f[i]; nf++; }
        m = nf ? m / (double)nf : 0.0;
        for (size_t i = 0; i < n; i++) r->fin[i] = isfinite(f[i]) ? (f[i] - m) * r->hann[i] : 0.0;
        fftw_execute(r->plan);
        size_t nh = r->nx / 2 + 1;
        double s = 0;
        for (size_t k = 0; k < nh * r->ny; k++)
            if (r->oob[k]) s += creal(r->fout[k]) * creal(r->fout[k]) + cimag(r->fout[k]) * cimag(r->fout[k]);
        /* White noise of per-pixel variance v_i gives sum_i hann_i^2 v_i / hann2 here: the
         * photon part of v_i is the frame's own counts / gain (its window-weighted mean is
         * dominated by the bright centre), the rest is the read noise. */
        double ph = 0;
        if (r->p.gain > 0) {
            for (size_t i = 0; i < n; i++) ph += r->hann[i] * r->hann[i] * (f[i] > 0 ? f[i] : 0.0);
            ph /= r->p.gain * r->hann2;
        }
        r->spec_sum += s / (double)r->noob / r->hann2 - ph;
        r->spec_n++;
    }
    double cx = 0, cy = 0;
    int rc = swfs_peak_gauss(f, r->nx, r->ny, r->p.gauss_sigma, r->work, &cx, &cy);
    if (rc) return rc;
    if (px) *px = cx;
    if (py) *py = cy;
    if (r->p.do_register) {
        double sx = cx - (double)(r->nx / 2), sy = cy - (double)(r->ny / 2);
        swfs_shift_bilinear(f, r->nx, r->ny, sx, sy, out);
        /* White noise through the bilinear weights (1-a, a) x (1-b, b): its per-pixel
         * variance is multiplied by ((1-a)^2 + a^2) ((1-b)^2 + b^2) (1/2 at half a pixel
         * per axis, 4/9 on average over uniform shifts). */
        double ax = sx - floor(sx), ay = sy - floor(sy);
        r->q_sum += ((1 - ax) * (1 - ax) + ax * ax) * ((1 - ay) * (1 - ay) + ay * ay);
        r->q_n++;
    } else
        memmove(out, f, n * sizeof *out);
    return SWFS_OK;
}

double swfs_reduce_noise_factor(const swfs_reduce *r)
{
    return r->q_n ? r->q_sum / (double)r->q_n : 1.0;
}

double swfs_reduce_noise_var(const swfs_reduce *r)
{
    if (r->plan) return r->spec_n ? r->spec_sum / (double)r->spec_n : NAN;
    if (r->nframes < 2 || r->nbg == 0) return NAN;
    double s = 0, m = 0;
    for (size_t b = 0; b < r->nbg; b++) { s += r->bg_m2[b] / (double)(r->nframes - 1); m += r->bg_mean[b]; }
    return (s - (r->p.gain > 0 && m > 0 ? m / r->p.gain : 0.0)) / (double)r->nbg;
}

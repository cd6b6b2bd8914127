/* Science-camera frame reduction (paper Sec. 4.3): dark and flat, bad pixels replaced by
 * the median of their 3 x 3 neighbourhood, the star located by correlation with a
 * Gaussian reference peak, the frame shifted with bilinear interpolation so the peak sits
 * on the fixed centre (W/2, H/2) of docs/conventions.md, and the background noise variance from a
 * source-free region (fed to estimate as RDNOISE).
 *
 * Plan once (dark, flat, bad-pixel map, Gaussian kernel, work buffers), then one
 * allocation-free call per frame. */
#ifndef SWFS_REDUCE_H
#define SWFS_REDUCE_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_reduce_params {
    double hot_sigma;    /* dark pixels more than this many robust sigmas from the median
                            are bad (8) */
    double flat_min, flat_max; /* flat outside [min, max] (relative to its median) is bad (0.5, 1.5) */
    double gauss_sigma;  /* [pixels] reference peak for the registration (0.45 lambda/D in pixels; 2) */
    int do_register;     /* shift each frame so the peak is at (W/2, H/2) (1) */
    double bg_radius;    /* [pixels] pixels farther than this from the centre are the
                            source-free region for the noise variance (0: 0.45 min(W, H)) */
    double pixscale;     /* [lambda/D per pixel] when in (0, 0.45): the noise variance comes
                            instead from the spatial frequencies the telescope cannot pass
                            (|f| > PIXSCALE cycles/pixel, the optical cutoff D/lambda, plus a
                            margin of 2 frequency bins) of each Hann-windowed frame: white
                            noise is there, the star's halo is not -- robust where no pixel
                            is free of the halo. 0: use the source-free region (default 0) */
    double gain;         /* [e-/count] when > 0: the photon noise I/gain of the frame itself is
                            removed from the noise estimate, which is then the signal-independent
                            (read) part: estimate models the photon part per pixel as
                            Phi_I/GAIN. The Hann window weights the bright centre, so leaving
                            the photon noise in biased the estimate 17 % high for the faint
                            halo (docs/telemetry.md). 0: unknown, kept (default 0) */
} swfs_reduce_params;

void swfs_reduce_params_default(swfs_reduce_params *p);

typedef struct swfs_reduce swfs_reduce;

/* dark, flat (may be NULL: 0 and 1) and badmap (may be NULL; nonzero = bad) are nx*ny.
 * Bad pixels = badmap | hot dark | flat out of range | non-finite dark or flat. */
int swfs_reduce_create(swfs_reduce **out, size_t nx, size_t ny, const double *dark, const double *flat,
                       const double *badmap, const swfs_reduce_params *p);
void swfs_reduce_free(swfs_reduce *r);
size_t swfs_reduce_nbad(const swfs_reduce *r);
const unsigned char *swfs_reduce_badmap(const swfs_reduce *r);

/* Calibrate (dark, flat), replace bad pixels (also non-finite raw values), locate the
 * peak (*px, *py in pixels, sub-pixel) and, if registering, shift it to (W/2, H/2):
 * pixels whose source falls outside the frame are NaN (the estimator skips them).
 * raw and out are nx*ny and may alias. The calibrated, unshifted frame's source-free
 * pixels feed the noise-variance accumulator. */
int swfs_reduce_frame(swfs_reduce *r, const double *raw, double *out, double *px, double *py);

/* Background noise variance per pixel [counts^2] of the calibrated, unshifted frames: the
 * mean over the frames of the out-of-band spectral estimate (pixscale set), else the mean
 * over the source-free pixels of their variance over the frames reduced so far (NaN before
 * two frames); with gain > 0, less the photon noise of the frames' own counts. */
double swfs_reduce_noise_var(const swfs_reduce *r);

/* Mean over the registered frames of the factor by which the bilinear shift multiplies the
 * per-pixel variance of white noise, ((1-a)^2 + a^2) ((1-b)^2 + b^2) for fractional shifts
 * (a, b) (4/9 for uniform shifts); 1 without registration. The registered frames' noise
 * variance is swfs_reduce_noise_var * this factor: what the estimator must remove
 * (measured: removing the unshifted frames' variance instead over-subtracts, the radicand
 * of eq:scale-factor goes negative in 94 % of the pixels and the time-series NCP error
 * doubles, docs/telemetry.md). */
double swfs_reduce_noise_factor(const swfs_reduce *r);

/* Building blocks (tests): 3 x 3 median replacement in place of flagged or non-finite
 * pixels (median of the unflagged finite neighbours of the input; a pixel with none keeps
 * its value; work: nx*ny), and the Gaussian correlation peak of an image (work: 2 nx ny). */
void swfs_badpix_replace(double *img, size_t nx, size_t ny, const unsigned char *bad, double *work);
int swfs_peak_gauss(const double *img, size_t nx, size_t ny, double sigma, double *work, double *px, double *py);
/* out(i, j) = img(i + sx, j + sy), bilinear; NaN where the source is outside. */
void swfs_shift_bilinear(const double *img, size_t nx, size_t ny, double sx, double sy, double *out);

SWFS_END_DECLS

#endif

/* A modulated pyramid wavefront sensor on the pupil grid (docs/telemetry.md, "A pyramid
 * wavefront sensor"): Fourier optics, not a geometric model, so its response is what a real
 * pyramid's is, linear only for small residuals and falling as they grow (the "optical gain"
 * a closed loop sees against its calibration).
 *
 * The pupil field E = mask exp(2 pi i z / lambda) (z the wavefront displacement [m] on the
 * npup x npup grid of pupdx) is zero-padded to N x N and Fourier transformed: the focal
 * plane, N pupdx / D samples per lambda/D (at least 2). There the pyramid's four facets
 * multiply it by exp(i (pi/2)(|u| + |v|)) (u, v in focal samples from the optical axis): each
 * facet tilts its quarter of the light so that the inverse transform re-images the pupil
 * four times, a quarter of the grid apart. The beam circles the apex (modulation) at
 * mod lambda/D: the intensities of nmod points on the circle are averaged, each the pyramid
 * moved by the opposite offset (the same relative geometry: one forward transform per frame
 * and one inverse per point; the mask, separable, kept as its row and column factors, the
 * rows' transforms shared by the two points of one row factor, the columns transformed
 * only where the images lie). The
 * four images are binned on the Shack-Hartmann's subaperture grid (subaperture (a, b)
 * covers x in [-D/2 + a d, -D/2 + (a+1) d), d = D/nsub, by the pixel centres, wfs.h),
 * facets A (u >= 0, v >= 0), B (u < 0, v >= 0), C (u < 0, v < 0), D (u >= 0, v < 0), and
 * give per used subaperture
 *
 *   sx = (A + D - B - C) / n,   sy = (A + B - C - D) / n,
 *
 * n the mean of A + B + C + D over the used subapertures (global normalization), less the
 * same of a flat wavefront (the reference). The layout is the Shack-Hartmann's: all nsub^2
 * sx then all sy, 0 for unused subapertures, so the telemetry, valid maps and reconstructors
 * of the Shack-Hartmann kind fit it; the signals are dimensionless, their sign that of the
 * wavefront's tilt (a tilt dz/dx > 0 gives sx > 0, as a Shack-Hartmann's slope). */
#ifndef SWFS_PYRAMID_H
#define SWFS_PYRAMID_H

#include <stddef.h>

#include "specklewfs/rng.h"
#include "specklewfs/sparse.h"

SWFS_BEGIN_DECLS

typedef struct swfs_pyramid_work swfs_pyramid_work;

typedef struct swfs_pyramid {
    size_t nsub;          /* subapertures across the diameter */
    size_t nslopes;       /* 2 nsub^2 */
    size_t npup;          /* pupil grid */
    double pupdx, diam;   /* [m] */
    double wavelen;       /* [m] the sensing wavelength */
    double mod;           /* modulation radius [lambda/D] (0: none) */
    size_t nmod;          /* modulation points */
    size_t nfft;          /* N, the transforms' size */
    double sampling;      /* focal samples per lambda/D, N pupdx / D */
    unsigned char *valid; /* nsub^2: the subapertures used */
    size_t nvalid;
    swfs_pyramid_work *w; /* transforms, masks and buffers (private) */
} swfs_pyramid;

/* The modulation points a radius needs when nmod is 0: two per lambda/D of the circle's
 * length, rounded up to a multiple of 4 (the four facets see the same path), at least 4;
 * 1 without modulation. Measured (3 lambda/D, a residual of 0.1 wave rms, against 320
 * points): 20 points 9.6 % of the signals' rms off, 40 (this rule) 1.5 %, 80 0.3 %
 * (docs/telemetry.md, tests/test_pyramid.c). */
size_t swfs_pyramid_nmod_default(double mod);

/* valid: the subapertures used (nsub^2 flags, (a, b) at b nsub + a) or NULL for the
 * Shack-Hartmann's rule (those with at least half the illuminated sample pairs of a full
 * one: the same map as swfs_shwfs_create's). mod >= 0 [lambda/D], nmod 0 = the default.
 * N is the smallest multiple of 4 of factors 2, 3, 5, 7 from 2 npup + 8 (the four images
 * apart), at least 2 D / pupdx (two focal samples per lambda/D). SWFS_ERR_ARG names what is
 * out of range (a subaperture under 2 samples, a modulation beyond the focal window). */
int swfs_pyramid_create(swfs_pyramid **out, size_t nsub, double diam, const double *mask, size_t npup, double pupdx,
                        const unsigned char *valid, double wavelen, double mod, size_t nmod);
void swfs_pyramid_free(swfs_pyramid *p);

/* The signals (nslopes) of the displacement z (npup^2) [m]. photons > 0: each used
 * subaperture receives that many photons per frame on average, the four images' counts
 * with Poisson noise (its normal approximation, from rng), the normalization from the noisy
 * counts; photons <= 0 (rng may be NULL): noiseless. No allocation. Not thread-safe on one
 * sensor (its buffers); separate sensors are. */
void swfs_pyramid_measure(swfs_pyramid *p, const double *z, double photons, swfs_rng *rng, double *signals);

/* The interaction matrix D (nslopes x nact, row-major) [per m]: push-pull of each column of
 * T (npup^2 x nact, the DM's surface per unit command) by +-amp [m], noiseless. */
int swfs_pyramid_interaction(swfs_pyramid *p, const swfs_sparse *T, double amp, double **D);

SWFS_END_DECLS

#endif

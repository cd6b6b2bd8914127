/* The winds of the frozen-flow layers, the dominant one tracked, from the Shack-Hartmann
 * slopes alone.
 *
 * A layer carried by the wind at v moves its phase pattern by v tau in tau seconds. The AO
 * residual of a linear loop is a time-invariant filter of that pattern (plus the loop's
 * spatial filter and noise), so the residual slopes move with it too: the slopes of
 * subaperture p at frame t correlate best with those of the subaperture displaced by
 * v tau / pitch at frame t + tau. For lags tau = 1, 2, 4, ... frames (up to a quarter of the
 * series): the lagged covariances of every pair of valid subapertures (x and y slopes summed,
 * each frame's mean x/y slope and each subaperture's mean taken out), summed over the pairs
 * of each grid displacement (within +-(nsub/2 - 1) subapertures; the slope grids' lagged
 * cross-correlation, by FFT) and normalized by their zero-lag standard deviations, and the
 * peak of that correlation map, refined by a parabola through its neighbours on each axis, is
 * the displacement at that lag.
 *
 * Which lags count: the displacement is resolved once it reaches one subaperture (shorter
 * lags see the correlation's width, not its shift). From the first lag whose peak lies at
 * least one subaperture out and inside the map, each longer lag is kept while the highest
 * bin within half the predicted displacement of v tau (v the least-squares fit through the
 * origin of the lags kept so far) is a local maximum inside the map (so that another
 * layer's peak elsewhere in the map does not take over the track); the first lag that does
 * not stops the tracking (the layer has decorrelated or left the map), and so does a lag
 * whose predicted displacement would leave the map less its outer ring (the peak needs its
 * neighbours, and enough overlapping pairs, to be placed). v is the fit over
 * the lags kept, so the longest lag dominates: its sub-subaperture error divided by many
 * subapertures of displacement. With two layers the tracked one is the layer whose
 * pattern dominates the slopes at the lags that resolve it.
 *
 * Directions are the subaperture grid's: +x along increasing subaperture column, +y along
 * increasing row (the pupil grid's, docs/conventions.md), the direction in degrees
 * counter-clockwise from +x toward which the pattern moves (the time-series simulator's
 * layer_dir). Measured over the issue-12 matrix in docs/telemetry.md.
 *
 * Further layers (layer[1..]): once one is tracked, the lagged correlation maps over every
 * displacement on the grid (+-(nsub - 1), bins of at least nsub/2 pairs; made with the
 * tracker's, in one pass) at lags of 2^k and 3 x 2^(k-1) frames (1, 2, 3, 4, 6, 8, 12, ..., up
 * to a quarter of the series), and each candidate velocity u [subapertures per frame] is scored
 * by stacking the maps along its track: the sum over lags of the map's correlation at u tau
 * (bilinear), over sqrt(the lags counted). A lag counts where u tau lies inside the map, at
 * least 1.5 subapertures from the centre and from every layer already found at that lag (the
 * zero-lag correlation of the slopes is non-zero out to the first ring of neighbours only: -0.2
 * at one subaperture, |0.1| or less at two, over the matrix), and a score needs three lags (a
 * track counts at two only where it moves a third of the map per frame or more, so slowly that
 * the longest lags alone take it off the centre, or alongside a layer found: on the matrix's
 * zonal loops such tracks gave a layer at 1490 m/s and second copies of found ones). A layer's
 * pattern adds up along its own track; a static feature of the maps (the loop's side lobes)
 * adds at one lag per velocity, and noise at random. The tracked layer is left out both as
 * tracked and as the stacking places it (refined on the grid below): the tracker's few lags can
 * put it a few degrees off its stacked track, which would then stand out again. The candidates
 * are every map bin over every lag (u = bin / tau); the best is refined on a grid around it,
 * and counts as a layer when its score lies more than twice the expected maximum of Gaussian
 * noise over the map's bins, 2 sqrt(2 ln bins), robust standard deviations (1.4826 x the median
 * absolute deviation over all candidates) above the candidates' median. Then that track is
 * excluded too and the search repeats. A tracked layer whose own track stands below that
 * threshold where a further one stands above it is left out of layer[] (tracked_dropped): its
 * peaks were another layer's. Over the matrix's 48 loops (modal and zonal, two seeds) the
 * layers found stood 8-93 such deviations out, the best of the rest 3.3-7.2, against thresholds
 * of 6.8-7.7 (docs/telemetry.md). */
#ifndef SWFS_WIND_H
#define SWFS_WIND_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

#define SWFS_WIND_MAXLAGS 32
#define SWFS_WIND_MAXLAYERS 4

typedef struct swfs_wind_layer {
    double vx, vy;          /* [m/s] */
    double speed;           /* [m/s] */
    double direction;       /* [deg] in [0, 360) */
    double corr;            /* the mean correlation along its track */
    double signif;          /* its stacked score above the candidates' median [robust sd] */
    size_t nlags;           /* lags on its track that counted */
} swfs_wind_layer;

typedef struct swfs_wind_lag {
    size_t lag;       /* [WFS frames] */
    double dx, dy;    /* peak displacement [subapertures] */
    double corr;      /* normalized correlation at the peak */
    int inside;       /* the peak lies inside the map (not on its edge) */
    int used;         /* kept for the fit */
} swfs_wind_lag;

typedef struct swfs_wind_estimate {
    int found;                      /* 1: a displacement tracked over two lags or more */
    double vx, vy;                  /* [m/s] */
    double speed;                   /* [m/s] */
    double direction;               /* [deg] in [0, 360), toward which the pattern moves */
    size_t nused;                   /* lags used in the fit */
    size_t nlags;                   /* lags examined (lag[0..nlags)) */
    swfs_wind_lag lag[SWFS_WIND_MAXLAGS];
    size_t nvalid;                  /* subapertures used */
    size_t radius;                  /* the correlation map's half width [subapertures] */
    /* Every layer found: layer[0] the tracked one (vx, vy as above, its stacked score for
     * comparison), layer[1..nlayers) the further ones, in the order found (wind.h); without
     * the tracked one where tracked_dropped. 0 when none was tracked. */
    size_t nlayers;
    swfs_wind_layer layer[SWFS_WIND_MAXLAYERS];
    double threshold;               /* the detection threshold [robust sd] */
    double next_signif;             /* the best candidate not taken as a layer [robust sd] */
    size_t nstack;                  /* lags of the further layers' search */
    double tracked_signif;          /* the tracked layer's standing [robust sd] (NAN: not scored) */
    int tracked_dropped;            /* 1: it stood below the threshold where a further layer stood
                                       above it, and layer[] holds the further ones only (vx, vy,
                                       speed, direction stay the tracker's) */
} swfs_wind_estimate;

/* slopes: nframes rows of nslopes, either the full layout (2 nsub^2: x of every subaperture
 * row-major, then y) or, with valid given, the valid subapertures' only (2 nvalid, in the
 * map's row-major order). valid: nsub x nsub (nonzero = used), or NULL: the subapertures
 * whose slopes are not all 0. pitch: the subaperture size on the pupil [m]; rate: WFS
 * frames per second. Refused: fewer than 64 frames, nsub < 4, a non-finite slope (frame and
 * index named), fewer than 8 valid subapertures. found = 0 (not an error) when fewer than
 * two lags track a displacement: a layer too slow for the series, or no frozen flow (one
 * lag alone, which white noise can give, does not show a steady motion). */
int swfs_wind_from_slopes(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                          const unsigned char *valid, double pitch, double rate, swfs_wind_estimate *out);

SWFS_END_DECLS

#endif

/* Shared between wind.c (the lagged correlation maps, the tracked layer) and wind_stack.c
 * (further layers by stacking the maps along candidate tracks); include/specklewfs/wind.h. */
#ifndef SWFS_WIND_INTERNAL_H
#define SWFS_WIND_INTERNAL_H

#include "specklewfs/wind.h"

#include <stddef.h>

/* The lags whose maps are made: 2^k and 3 x 2^(k-1) frames up to a quarter of the series (the
 * tracker takes the powers of two, the stacking every one). */
#define SWFS_WIND_MAXMAPS 48

typedef struct {
    size_t nsub;           /* subapertures across */
    size_t R, nb;          /* the whole grid's displacements: +-R = nsub - 1, nb = 2 R + 1 bins per side */
    size_t nmaps;          /* maps made */
    size_t lag[SWFS_WIND_MAXMAPS];
    const double *map;     /* nmaps x nb x nb normalized correlations; NAN in a bin of no pair */
    const size_t *count;   /* nb x nb: pairs of subapertures per bin */
} swfs_wind_maps_;

/* Parabola through three samples: the vertex's offset from the middle one, in [-0.5, 0.5]
 * (0 where they do not bend down). The tracker's and the stacking's peaks alike. */
double swfs_wind_vertex_(double l, double c, double r);

/* The slopes' lagged covariance summed over the pairs of subapertures at each displacement, for
 * each of nlags lags: sums[l][(b + R) nb + a + R] = sum over frames t < T - lag[l] and pairs
 * (p, q) with pos[q] - pos[p] = (a, b) on the nsub x nsub grid (R = nsub - 1, nb = 2 R + 1) of
 * x_p(t) x_q(t + lag) + y_p(t) y_q(t + lag); x, y: T x nv. By FFT (the grid's lagged
 * cross-correlation: O(T nsub^2 (log nsub + nlags)), where the pairs' products cost T nv^2 a
 * lag), the frames' spectra held a band of frequencies at a time, in at most budget bytes (0:
 * twice x and y's size, at least 256 MB and at most 1 GB). */
int swfs_wind_lag_sums_(const double *x, const double *y, size_t T, size_t nv, const size_t *pos, size_t nsub,
                        const size_t *lag, size_t nlags, size_t budget, double *sums);

/* The further layers into e->layer[1..] (e->layer[0] and e->found set by the tracker; wind.h). */
int swfs_wind_stack_layers_(const swfs_wind_maps_ *m, double pitch, double rate, swfs_wind_estimate *e);

#endif

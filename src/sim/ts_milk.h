/* Private to src/sim/: the time-series simulator's milk logs (timeseries.h, milk=1). */
#ifndef SWFS_TS_MILK_H
#define SWFS_TS_MILK_H

#include <stddef.h>

#include "specklewfs/geom.h"
#include "specklewfs/timeseries.h"

struct swfs_paths;

/* The milk_* keys in range (SWFS_ERR_VALUE naming the key otherwise). */
int swfs_ts_milk_check(const swfs_ts_params *p);
/* Every file of the logs as an output of paths: nwfs WFS frames, cube starts tstart
 * (ncubes) [global WFS frames]. */
int swfs_ts_milk_outputs(const swfs_ts_params *p, const char *dir, size_t nwfs, const double *tstart,
                         struct swfs_paths *paths);
/* Write the logs into dir/milk/{wfs,cam} (existing folders) and dir/milk/truth.txt: slopes
 * (nwfs x ns), raw camera frames (ncubes * cube_frames frames of nfx x nfy). */
int swfs_ts_milk_write(const swfs_ts_params *p, const char *dir, const double *slopes, size_t nwfs, size_t ns,
                       const double *raw, size_t nfx, size_t nfy, const double *tstart, const swfs_geom *g,
                       const char *const *prov, size_t nprov, double gain);

#endif

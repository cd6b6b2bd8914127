/* Stream batches from milk/cacao logs (offline): WFS logs (milklog.h; slopes or any
 * per-frame measurement vector, several logs concatenated into one vector in the order
 * given) and the reduced science cube whose STAMPS extension holds each camera frame's
 * counter and stamp (`reduce` of camera logs, science.h), fed in time order through
 * framesync (framesync.h: clock fits, exposure windows [T_j - exptime, T_j] mapped onto the
 * WFS frames with fractional weights, drops from counter jumps, only complete exposures,
 * segments at gaps) -- the offline counterpart of shm_source (shm.h), with the same
 * batches. The camera stamps are first put on the WFS clock (clocksync.h: offset and drift
 * from `sync --wfs-log`), and the camera frames are turned into the model's orientation
 * by the clock's pairing (sync.h: swfs_orient_frame).
 *
 * Nothing is allocated per frame: one frame per stream is read at a time (a log's next
 * file is opened when the data reach it). */
#ifndef SWFS_MILKSOURCE_H
#define SWFS_MILKSOURCE_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/clocksync.h"
#include "specklewfs/framesync.h"
#include "specklewfs/stream.h"

SWFS_BEGIN_DECLS

typedef struct swfs_milk_source_options {
    const char *const *wfs;   /* nwfs WFS logs: each a folder or one file (milklog.h) */
    size_t nwfs;
    const char *science;      /* reduced science cube with STAMPS */
    const swfs_clock *clock;  /* camera clock -> WFS clock and the pairing (NULL: one clock, the camera as the model) */
    double exptime;           /* [s] camera exposure; 0: STAMPS' EXPTIME, else the camera's frame period */
    size_t nslopes;           /* values per WFS frame over the logs the reconstructor expects (0: any) */
    size_t nfx, nfy;          /* expected camera frame size (0: any) */
    size_t batch;             /* camera frames per batch */
    const long *lags;         /* a space-time reconstructor's lags (nlags), or NULL: the batches'
                                 rows stacked at them (framesync.h, "Lags") */
    size_t nlags;
} swfs_milk_source_options;

typedef struct swfs_milk_source swfs_milk_source;

/* Opens and checks everything before the first batch: the logs' tables and frame sizes, the
 * values per frame against nslopes, STAMPS, the orientation, and that the camera's exposures
 * overlap each WFS log in time (SWFS_ERR_VALUE naming both files and both time spans). */
int swfs_milk_source_open(swfs_milk_source **out, const swfs_milk_source_options *o);
void swfs_milk_source_close(swfs_milk_source *s);
/* The swfs_source_fn of stream.h (ctx = the swfs_milk_source). */
int swfs_milk_source_next(void *ctx, swfs_batch *b);

typedef struct swfs_milk_source_stats {
    swfs_framesync_stats sync;  /* framesync's counts (drops, incomplete, no WFS data, ...) */
    uint64_t wfs_dropped_log, camera_dropped_log; /* counter jumps in the files */
    double exptime;             /* [s] the exposure used (camera clock) */
} swfs_milk_source_stats;

void swfs_milk_source_get_stats(const swfs_milk_source *s, swfs_milk_source_stats *st);

SWFS_END_DECLS

#endif

/* Timestamped frames -> stream batches: the live counterpart of the timing table.
 *
 * Live data arrive as frames with a counter and a time stamp (shared-memory streams,
 * shm.h): WFS frames (one or more WFS streams whose values are concatenated into one
 * slope vector) and camera frames. This module turns them into the batches of stream.h:
 * B camera frames, the block of WFS frames they integrate and the exposure schedule
 * (engine.h) with fractional weights. It takes and returns arrays; reading the streams
 * is io's (shm_source in shm.h).
 *
 * Time. Every stream has a clock model, stamp = alpha + beta * counter, fitted by least
 * squares with exponential forgetting (clock_memory frames): stamps jitter (a few us on
 * real systems), the frame clock does not. A stamp off the model by more than half a
 * period starts a new segment (a gap: the camera between cubes, a paused loop), and so
 * does a counter that goes back (a restarted writer). A stamp marks the END of its
 * frame (FORMATS.md: the acquisition time marks the end of the exposure), so WFS frame
 * k covers [t_k - beta, t_k] and camera frame j covers [T_j - exptime, T_j], exptime the
 * given exposure time or the camera's frame period. In WFS-frame units x(t) = (t -
 * alpha) / beta, frame k covers [k - 1, k) and an exposure [x0, x1) integrates the frames
 * it overlaps with their overlap as weight: exactly swfs_engine_schedule's schedule when
 * the stamps are regular.
 *
 * Completeness. A camera frame is used only when every WFS frame of its exposure arrived
 * from every WFS stream, in one WFS segment, with finite values; otherwise it is
 * skipped and counted (incomplete). Dropped frames are counted from the counters: a
 * jump of more than one within a segment (after a restart the counter starts at 1
 * again). Frames are used in time order; nothing is guessed or interpolated.
 *
 * Batches. A batch closes when it holds `batch` camera frames, when the next frame is
 * not contiguous with it (a dropped or skipped camera frame, a new segment) or when its
 * oldest frame has waited max_wait seconds; flush closes it now. With regular stamps and
 * no drops the batches are those of the file source with the same batch size (one cube
 * = one contiguous camera segment), so `live` reproduces `stream`. When a batch closes
 * its exposures are evaluated again with the clock fits of the frames up to its last
 * camera frame and its last WFS frame (snapshots kept with each frame), not with frames
 * that arrived since: the batches depend on the stamps alone, not on how the streams'
 * frames interleaved, so `live` fed by `replay --wfs-log` gives `stream --wfs-log`'s
 * results exactly.
 *
 * Lags. With a space-time reconstructor's lags (options lags, nlags > 1) each row of a
 * batch's slopes is the frame's values stacked with those of the frames at the lags
 * (swfs_slopes_stack's layout: nlags blocks of the WFS streams' values), as the file source's
 * run stacks them from the telemetry files: a batch waits until every WFS stream has
 * delivered the frame of its last row plus the largest lag (the delay: that lag's frames), or
 * until its segment has ended, or a flush; a lag beyond the segment's frames is clamped to
 * its first or last (as at a telemetry file's ends), and a frame of the window that did not
 * arrive whole and finite (or left the history) is replaced by the row's own values.
 *
 * Nothing is allocated per frame after create (the batch work space grows to the
 * largest batch seen, as the pipeline's does). One thread at a time. */
#ifndef SWFS_FRAMESYNC_H
#define SWFS_FRAMESYNC_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/stream.h"

SWFS_BEGIN_DECLS

#define SWFS_FRAMESYNC_MAX_WFS 8

typedef struct swfs_framesync_options {
    size_t batch;          /* camera frames per batch (16) */
    double max_wait;       /* [s] longest wait of a ready camera frame for its batch to fill (0.5) */
    double exptime;        /* [s] camera exposure time; 0: the camera's frame period (default) */
    double clock_memory;   /* [frames] memory of the clock fits (4096) */
    size_t wfs_history;    /* WFS frames kept (0: 8192, at most 256 MB) */
    size_t camera_queue;   /* camera frames waiting for their WFS frames (0: 4 batches + 64, at most 256 MB) */
    const long *lags;      /* a space-time reconstructor's lags [WFS frames] (nlags of them, one 0;
                              copied), or NULL: see "Lags" above */
    size_t nlags;
} swfs_framesync_options;

void swfs_framesync_options_default(swfs_framesync_options *o);

typedef struct swfs_framesync_stats {
    uint64_t wfs_received, camera_received;
    uint64_t wfs_dropped, camera_dropped;   /* counter jumps: frames lost before they were read */
    uint64_t wfs_restarts, camera_restarts; /* streams that started counting again */
    uint64_t wfs_segments, camera_segments; /* clock segments (gaps, restarts) */
    uint64_t used;         /* camera frames handed over in batches */
    uint64_t incomplete;   /* skipped: a WFS frame of the exposure missing, late or not finite */
    uint64_t no_wfs;       /* skipped: no WFS data around the exposure (before the first, in a gap) */
    uint64_t unsettled;    /* skipped: the exposure began before the settle time */
    uint64_t overrun;      /* skipped: the camera queue was full (the consumer fell behind) */
    uint64_t wfs_bad;      /* WFS frames with non-finite values */
    uint64_t wfs_late;     /* WFS frames too old for the history when they arrived */
    uint64_t batches;
    double wfs_period, camera_period; /* [s] the current clock fits (0: not known yet) */
} swfs_framesync_stats;

typedef struct swfs_framesync swfs_framesync;

/* nwfs WFS streams of nvals[i] values each (concatenated in this order into the slope
 * vector), camera frames of nf2 pixels. */
int swfs_framesync_create(swfs_framesync **out, size_t nwfs, const size_t *nvals, size_t nf2,
                          const swfs_framesync_options *o);
void swfs_framesync_free(swfs_framesync *f);

/* A frame of WFS stream i / of the camera: counter, stamp [ns, the writers' clock], values
 * (copied). now: the monotonic time [s] for max_wait. */
int swfs_framesync_add_wfs(swfs_framesync *f, size_t i, uint64_t cnt, int64_t stamp_ns, const double *vals, double now);
int swfs_framesync_add_camera(swfs_framesync *f, uint64_t cnt, int64_t stamp_ns, const double *frame, double now);
/* The counter of WFS stream i (camera = 0) or of the camera (camera = 1) stood at `last`
 * when it was opened: the frames after it that do not arrive count as dropped. restarted:
 * the writer restarted (a new segment; its counter started again from 0). */
void swfs_framesync_expect(swfs_framesync *f, int camera, size_t i, uint64_t last, int restarted);
/* Skip camera exposures that begin before stamp_ns (e.g. until a DM change has settled). */
void swfs_framesync_settle(swfs_framesync *f, int64_t stamp_ns);

/* The next batch if one is ready (b->nexp = 0 otherwise); flush: close the batch being
 * filled now and skip frames that cannot be completed (end of the data). The arrays stay
 * valid until the next call. b->cube counts the batches. */
int swfs_framesync_next(swfs_framesync *f, double now, int flush, swfs_batch *b);
/* The camera stamps [ns] of the frames of the last batch (its nexp values). */
const int64_t *swfs_framesync_batch_stamps(const swfs_framesync *f);
void swfs_framesync_get_stats(const swfs_framesync *f, swfs_framesync_stats *s);
size_t swfs_framesync_nslopes(const swfs_framesync *f); /* values per WFS frame (before stacking) */

SWFS_END_DECLS

#endif

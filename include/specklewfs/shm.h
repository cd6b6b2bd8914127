/* Shared-memory image streams in the ImageStreamIO 2.00 layout (milk / cacao), read and
 * written without any milk library: the live link to a running AO system. The layout and
 * the reader/writer protocol are in ../shared/FORMATS.md and docs/live.md; in short:
 *
 *   <dir>/<name>.im.shm = 384 bytes of metadata (version "2.00", name, naxis, size[3],
 *   datatype, imagetype, times, inode, semaphore count, frame counters cnt0/cnt1, the
 *   write flag, ...) then, each padded to 8 bytes: the data, the keywords, the
 *   process-shared semaphores, semlog, the reader/writer PIDs per semaphore, semctrl,
 *   semstatus, the process traces and, for a temporal circular buffer, the per-slice
 *   acquisition times, write times and counters.
 *
 * A writer raises `write`, copies the frame, stamps writetime (CLOCK_TAI) and atime (the
 * acquisition time), increments cnt0 (and points cnt1 at the slice of a 3-D rolling
 * buffer), lowers `write` and posts every semaphore. A reader claims one semaphore
 * through semReadPID, waits on it with a timeout and copies the new frames; a jump of
 * cnt0 by more than one is a lost frame, a new inode at the path a restarted writer.
 *
 * Anything else is refused with a message naming the file and the value: another
 * version, a size that is not the sum of the blocks (another build of the struct), an
 * unsupported datatype, a GPU stream. Only this module (src/io/shm.c) touches the
 * mapping; it never prints and never allocates per frame after open/create.
 *
 *   swfs_shm *s;  swfs_shm_open(&s, dir, "aol1_wfs");           // reader
 *   swfs_shm_claim(s);  while (...) { swfs_shm_wait(s, 0.05, &posted);
 *                                     swfs_shm_read(s, buf, meta, cap, &n, &lost); }
 *   swfs_shm_create(&w, dir, "dm_offsets", &shape);  swfs_shm_write(w, frame, &atime);
 */
#ifndef SWFS_SHM_H
#define SWFS_SHM_H

#include "specklewfs/defs.h"

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

#include "specklewfs/framesync.h"

SWFS_BEGIN_DECLS

/* ImageStreamIO datatype codes this module reads and writes. */
enum {
    SWFS_SHM_U16 = 3,
    SWFS_SHM_I16 = 4,
    SWFS_SHM_F32 = 9,
    SWFS_SHM_F64 = 10
};

/* imagetype bits: a circular buffer whose z axis is time (per-slice times and counters). */
#define SWFS_SHM_CIRCULAR 0x0001u
#define SWFS_SHM_ZTEMPORAL 0x20000u
#define SWFS_SHM_TYPEMASK 0xF000Fu

#define SWFS_SHM_METADATA_BYTES 384
#define SWFS_SHM_MAX_SEM 10

/* What a stream holds: size[] = nx, ny, nz (ny = nz = 1 for a vector). With temporal = 1
 * (imagetype: circular buffer, z axis time) it is a rolling buffer of nz frames of
 * nx * ny (cnt1 = the slice last written, per-slice times and counters); otherwise a frame
 * is the whole nx * ny * nz array. */
typedef struct swfs_shm_shape {
    int datatype;        /* SWFS_SHM_* */
    size_t nx, ny, nz;
    int temporal;        /* 1: circular buffer of nz frames (nz >= 2) */
    int nsem;            /* semaphores (1..10; create: 0 means 10) */
} swfs_shm_shape;

typedef struct swfs_shm swfs_shm;

/* One frame read: the writer's counter (cnt0 after the frame was written), its acquisition
 * and write times [ns] on the writer's clock (CLOCK_TAI for milk and specklewfs writers);
 * a writer that leaves atime at 0 gets writetime, and with both 0 the reader's own clock
 * at the read (stamped = 1). */
typedef struct swfs_shm_frame {
    uint64_t cnt;
    int64_t atime_ns, wtime_ns;
    int stamped;
} swfs_shm_frame;

/* The folder of the streams: dir when given (non-NULL, non-empty), else $MILK_SHM_DIR,
 * else /milk/shm, /dev/shm or /tmp, the first that is a folder. */
void swfs_shm_dir(const char *dir, char *out, size_t cap);
/* <folder>/<name>.im.shm; SWFS_ERR_ARG when the name is empty, has a '/', is longer than
 * 79 characters, or the path does not fit. */
int swfs_shm_path(const char *dir, const char *name, char *out, size_t cap);

/* ---- writer ---------------------------------------------------------------------- */

/* Create (or replace: a new file, hence a new inode, as a restarted writer does) the
 * stream `name` in dir (swfs_shm_dir). The file is built under a temporary name and
 * renamed, so a reader never maps a half-initialized stream. */
int swfs_shm_create(swfs_shm **out, const char *dir, const char *name, const swfs_shm_shape *shape);
/* Publish one frame (swfs_shm_frame_values doubles, converted to the stream's type: integers rounded
 * and clamped). atime_ns: the acquisition time [ns, CLOCK_TAI], or 0 for the write time.
 * Works on a created stream and on one opened with swfs_shm_open (writing into a stream
 * another program created, e.g. a DM channel). */
int swfs_shm_write(swfs_shm *s, const double *frame, int64_t atime_ns);
/* A lost frame: cnt0 moves on without data (what a reader sees when a frame is missed). */
void swfs_shm_skip(swfs_shm *s);
/* Readers holding a semaphore now (semReadPID of a live process). */
int swfs_shm_reader_count(const swfs_shm *s);
/* Unmap and close; with unlink = 1 also remove the file (a writer that is done). */
void swfs_shm_close(swfs_shm *s, int unlink_file);

/* ---- reader ---------------------------------------------------------------------- */

/* Map an existing stream and check it: version "2.00", the block sizes summing to the
 * file size, a supported datatype, CPU location, at least one semaphore. */
int swfs_shm_open(swfs_shm **out, const char *dir, const char *name);
/* Claim a semaphore for this process (one already ours, else one whose reader PID is 0
 * or dead) and flush its pending posts. SWFS_ERR_VALUE when every semaphore is taken. */
int swfs_shm_claim(swfs_shm *s);
/* Release the claimed semaphore (semReadPID back to 0); also done by close. */
void swfs_shm_release(swfs_shm *s);
/* Wait up to timeout seconds for a post on the claimed semaphore; *posted = 1 when
 * posted (further pending posts are absorbed: one wake-up per burst of frames). */
int swfs_shm_wait(swfs_shm *s, double timeout, int *posted);
/* The frames written since the last read (after swfs_shm_open: since the counter then):
 * up to cap frames into buf (swfs_shm_frame_values doubles each) with their meta, oldest first. A 2-D
 * stream gives the newest frame only; a rolling buffer every frame still in it. *lost
 * (may be NULL) receives the frames counted by cnt0 that could not be read (skipped by
 * the writer or overwritten before they were read). A counter that went backwards is
 * SWFS_ERR_VALUE (a writer restarted in place: reopen). */
int swfs_shm_read(swfs_shm *s, double *buf, swfs_shm_frame *meta, size_t cap, size_t *n, uint64_t *lost);
/* The newest frame whatever was read before (n = 0 when nothing was ever written). */
int swfs_shm_read_latest(swfs_shm *s, double *frame, swfs_shm_frame *meta, size_t *n);
/* Is the file at the path still this stream? *state: 0 = yes, 1 = replaced (another
 * inode: the writer restarted), 2 = gone. */
int swfs_shm_check(const swfs_shm *s, int *state);
/* Start reading at the current counter (skip what is already there). */
void swfs_shm_skip_to_now(swfs_shm *s);
/* Read next the frames after counter `last` (0: everything the stream still holds). */
void swfs_shm_set_last(swfs_shm *s, uint64_t last);

/* ---- the stream source: shared-memory streams -> stream.h batches --------------------- */

/* One reader thread per stream waits on its semaphore and copies every new frame
 * (converted to double) into a ring; the consumer (swfs_shm_source_next, the
 * swfs_source_fn of stream.h) drains the rings into a framesync (framesync.h), which maps
 * the WFS frames onto the camera exposures by their time stamps and hands out batches.
 * A stream that is missing waits up to `timeout`; a writer that restarts (a new file at
 * the path) is re-opened and its frames continue (the exposures that span the restart
 * are skipped); a stream that disappears for longer than `timeout`, or comes back with
 * another frame size, ends the run with an error naming it. Setting *stop (e.g. from a
 * signal handler), `idle` seconds without a frame, or the end of the caller's frame
 * budget end the data cleanly: the batch being filled is handed over first. Streams that
 * disappear after the data have ended so (no frame from any for `idle` seconds) end them
 * cleanly however far the consumer is behind: its frames are all handed over. */
typedef struct swfs_shm_source_options {
    const char *dir;             /* stream folder (swfs_shm_dir rules) */
    const char *const *wfs;      /* nwfs WFS stream names, values concatenated in this order */
    size_t nwfs;
    const char *camera;          /* camera stream name */
    size_t nslopes;              /* values the WFS streams must give together (0: any) */
    size_t nfx, nfy;             /* camera frame size required (0: any) */
    swfs_framesync_options sync; /* batch size, max_wait, exptime, clock memory, history */
    double poll;                 /* [s] semaphore wait timeout and health-check period (0.02) */
    double timeout;              /* [s] longest wait for a missing or vanished stream (10) */
    double idle;                 /* [s] end when no frame arrived for this long after the first (0: never) */
    volatile sig_atomic_t *stop; /* end cleanly when it becomes non-zero (may be NULL) */
    size_t ring;                 /* frames buffered per stream (0: ~64 MB, 256..16384 frames) */
} swfs_shm_source_options;

void swfs_shm_source_options_default(swfs_shm_source_options *o);

typedef struct swfs_shm_source swfs_shm_source;

typedef struct swfs_shm_source_stats {
    swfs_framesync_stats sync;   /* frames, drops, restarts, skipped exposures, batches */
    uint64_t ring_overruns;      /* frames lost because the consumer fell behind the readers */
    uint64_t reopens;            /* streams re-opened after their writer restarted */
    size_t lag_count;            /* camera frames whose lag was measured */
    double lag_median, lag_p99, lag_max; /* [s] camera stamp -> accumulated (next batch asked for) */
    double seconds;              /* from the first frame to the end */
} swfs_shm_source_stats;

/* Opens (waiting up to timeout for) every stream, checks the frame sizes, starts the
 * readers. Frames already in the streams are not used: the data start now. */
int swfs_shm_source_open(swfs_shm_source **out, const swfs_shm_source_options *o);
void swfs_shm_source_close(swfs_shm_source *s);
/* The swfs_source_fn of stream.h (ctx = the swfs_shm_source). Blocks until a batch is
 * ready or the data end (b->nexp = 0). */
int swfs_shm_source_next(void *ctx, swfs_batch *b);
/* Skip camera exposures that begin before now + seconds (a DM change settling). */
void swfs_shm_source_settle(swfs_shm_source *s, double seconds);
/* Record a failure to end the run with at the next batch (e.g. from an update callback
 * that cannot return a status): code and the current swfs_last_error(). */
void swfs_shm_source_fail(swfs_shm_source *s, int code);
void swfs_shm_source_get_stats(const swfs_shm_source *s, swfs_shm_source_stats *st);
/* Frame values of WFS stream i and of the camera (as opened). */
size_t swfs_shm_source_wfs_values(const swfs_shm_source *s, size_t i);
size_t swfs_shm_source_camera_values(const swfs_shm_source *s);

/* ---- both -------------------------------------------------------------------------- */

const swfs_shm_shape *swfs_shm_get_shape(const swfs_shm *s);
const char *swfs_shm_get_path(const swfs_shm *s);
size_t swfs_shm_frame_values(const swfs_shm *s);  /* nx * ny (temporal) or nx * ny * nz */
uint64_t swfs_shm_counter(const swfs_shm *s);      /* cnt0 now */
uint64_t swfs_shm_inode(const swfs_shm *s);
/* A readable name of a datatype code ("float32", ...; "code N" for others). */
const char *swfs_shm_type_name(int datatype);
/* Now on the streams' clock (CLOCK_TAI where defined, else CLOCK_REALTIME) [ns]. */
int64_t swfs_shm_now_ns(void);

SWFS_END_DECLS

#endif

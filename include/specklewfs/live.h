/* Live at the telescope: the NCP estimate beside a running AO system, through
 * ImageStreamIO shared-memory streams (shm.h), and the replay that feeds such streams
 * from files for tests and demos. Design, protocol and measurements: docs/live.md.
 *
 *   live:   WFS stream(s) + camera stream -> shm source (reader threads, framesync: the
 *           time stamps map WFS frames onto camera exposures) -> the stream of
 *           `specklewfs stream` (pipeline, accumulators) -> HALO.fits / PUPIL.fits /
 *           checkpoint every K frames or T seconds -> optionally DM offsets (as
 *           `dmoffsets` computes them: -WFE/2 fitted onto the actuators) written to an
 *           output stream, with a gain, a largest step and a largest total rms.
 *   replay: a timing table + telemetry files + reduced science cube (the inputs of
 *           `stream`) published into streams at the WFS rate (or faster), with time
 *           stamps from the timing table and optional drops, jitter and writer restarts.
 *
 * With regular stamps, no drops and the same batch size, `live` on a replay hands the
 * stream the same batches as `stream` on the files (tests/test_cli_live.c). */
#ifndef SWFS_LIVE_H
#define SWFS_LIVE_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/dmfit.h"
#include "specklewfs/run.h"
#include "specklewfs/shm.h"
#include "specklewfs/timeseries.h"

SWFS_BEGIN_DECLS

/* ---- live --------------------------------------------------------------------------- */

typedef struct swfs_live_options {
    /* The streaming run (run.h): run.science is a FITS file with the geometry keywords,
     * the camera frame size and the noise model (RDNOISE, GAIN), e.g. a reduced science
     * cube; recon, actuators, out, pupil_out, checkpoint, static, mask, tiptilt, threads,
     * read_noise, gain, g_smooth_lod, stream.every / every_seconds / max_frames as for
     * `stream`. run.timing, run.slopes and run.batch are not used. */
    swfs_stream_run_options run;
    /* The streams (shm.h): names, folder, batch size (src.sync.batch), max_wait,
     * exptime, timeouts, idle end, the stop flag. nslopes/nfx/nfy are set here. */
    swfs_shm_source_options src;
    /* DM offsets: after every update (the final one too with dm_final) the correction -WFE/2 of the
     * pupil product fitted onto the actuators (dmfit.h, as `dmoffsets`), times dm_gain,
     * scaled down to at most dm_max_step per actuator, added to the total, which is
     * scaled down to at most dm_max_rms, and written to stream dm_out (nact values in
     * metres of surface x dm_scale; created as nact x 1 float32 unless a stream of nact
     * values exists; an existing stream's current offsets are the starting total). Needs
     * run.pupil_out; on AO telemetry (closed-loop residuals) take the pupil from HALO
     * (run.pupil_source = SWFS_SOURCE_HALO, docs/telemetry.md). */
    const char *dm_out;         /* stream name (NULL: no offsets) */
    const char *dm_file;        /* also OFFSETS.fits of the total (dmfit_write) at every update (NULL: no) */
    swfs_dmfit_options dmfit;   /* influence functions, modes, regularization */
    double dm_gain;             /* (0.5) */
    double dm_max_step;         /* [m] largest change of one actuator per update (0: no limit) */
    double dm_max_rms;          /* [m] largest rms of the total over the active actuators (0: no limit) */
    double dm_scale;            /* stream units per metre (1) */
    double dm_settle;           /* [s] skip exposures that begin earlier than this after a write (0.1) */
    int dm_keep;                /* 1: keep accumulating across offsets; 0 (default): start anew */
    int dm_final;               /* 1: also correct at the final update (the end of the data) */
    int dm_tiptilt;             /* 1: correct tip and tilt too; 0 (default): piston, tip and tilt are
                                   removed from the WFE first -- registered camera frames do not
                                   see them, and pointing is the AO loop's */
} swfs_live_options;

void swfs_live_options_default(swfs_live_options *o);

/* Whether o's options fit together and lie in range (run.h swfs_stream_run_options_check's
 * ranges for o->run, and the streams', the source's times, the DM offsets' gain, limits,
 * scale and fit); swfs_live_run calls it first. SWFS_ERR_ARG and a message that names the
 * option as `specklewfs live` spells it. */
int swfs_live_options_check(const swfs_live_options *o);

typedef struct swfs_live_result {
    swfs_stream_run_result run;     /* frames, rate, noise model, pipeline */
    swfs_shm_source_stats src;      /* drops, restarts, skipped exposures, lag */
    size_t dm_updates;
    double dm_step_rms, dm_total_rms; /* [m] of the last update */
    size_t dm_fixed;                /* pupil samples of the last update taken off a phase wrap or noise */
} swfs_live_result;

/* Runs until the data end (the stop flag, idle, max_frames). On an error after the first
 * update the last products and checkpoint written stay as they were (all writes are
 * atomic). */
int swfs_live_run(const swfs_live_options *o, swfs_live_result *r);

/* ---- replay ------------------------------------------------------------------------- */

typedef struct swfs_replay_options {
    const char *timing, *science, *slopes; /* as `stream` (slopes: folder or one file; NULL: the table's folder) */
    const char *dir;            /* stream folder (shm.h rules) */
    const char *wfs_name, *camera_name; /* ("swfs_wfs", "swfs_camera") */
    double wfs_rate;            /* [Hz] (0: WFSRATE of the telemetry) */
    double speed;               /* 1: real time; 2: twice as fast */
    double drop_wfs, drop_camera; /* probability of losing each frame (never the last of a stream) */
    double jitter;              /* [s] rms added to the time stamps and publication times */
    uint64_t seed;
    size_t depth;               /* slices of a temporal rolling buffer (0 or 1: 2-D streams) */
    int wfs_type, camera_type;  /* SWFS_SHM_* (0: float64 for BITPIX -64 files, else float32; 16-bit
                                   camera cubes keep their int16/uint16) */
    double wait_reader;         /* [s] before publishing (and after a restart) wait up to this long
                                   for a reader on every stream (0: do not wait) */
    size_t restart_after;       /* re-create the streams after this many WFS frames (0: never) */
    const char *drop_log;       /* text file of the frames lost (NULL: none) */
    int remove;                 /* remove the streams at the end (0: leave them, as a writer does) */
    swfs_progress_fn progress;
    void *progress_ctx;
    const char *wfs_log;        /* instead of timing/slopes: a WFS milk log (milklog.h) published with its
                                   own stamps and lost frames, the camera frames of `science` at their
                                   STAMPS (run_replay_milk.c); drops, jitter, restarts and wfs_rate do
                                   not apply */
} swfs_replay_options;

void swfs_replay_options_default(swfs_replay_options *o);

typedef struct swfs_replay_result {
    size_t wfs_frames, camera_frames;   /* frames of each stream (published + lost) */
    size_t wfs_dropped, camera_dropped; /* lost on purpose */
    size_t restarts;
    double wfs_rate, ratio;             /* [Hz] as published (x speed); WFS frames per camera frame */
    double seconds;                     /* wall time of the publication */
    double late_max;                    /* [s] latest publication after its scheduled time */
} swfs_replay_result;

int swfs_replay_run(const swfs_replay_options *o, swfs_replay_result *r);

/* ---- a closed loop in simulation through the streams ------------------------------ */

#define SWFS_LIVE_LOOP_MAX 32

/* Iteration k: the time-series simulator (timeseries.h; seed + k) with the NCP plus twice
 * the DM surface of the offsets it read from the DM stream -> reduce -> sync -> replay
 * into streams -> live (its estimate at the end of the data corrected onto the DM stream)
 * -> the simulator reads the DM stream for iteration k + 1. The reconstructor is the one
 * `speckles` builds from iteration 0's telemetry (written to DIR/recon.fits). */
typedef struct swfs_live_loop_options {
    swfs_ts_params sim;
    const char *dir;            /* output folder (must exist): iter_K/, recon.fits, dm_K.fits, shm/ */
    size_t iterations;          /* corrections (3, at most SWFS_LIVE_LOOP_MAX) */
    double speed;               /* replay speed (2) */
    size_t batch;               /* live batch (16) */
    swfs_dmfit_options dmfit;   /* (SWFS_INFLUENCE_CUBIC: the simulator's DM is the Clough-Tocher surface) */
    double gain, max_step, max_rms; /* as live's dm_gain (0.5), dm_max_step, dm_max_rms */
    int pupil_source;           /* (SWFS_SOURCE_HALO) */
    int tiptilt;                /* live's dm_tiptilt (0) */
    volatile sig_atomic_t *stop;
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
} swfs_live_loop_options;

void swfs_live_loop_options_default(swfs_live_loop_options *o);

typedef struct swfs_live_loop_state {
    double residual_rms;        /* [m] NCP + 2 x DM surface, piston, tip and tilt removed */
    double estimate_err;        /* [m] live's WFE against it (piston, tip, tilt removed); NaN after the last */
    double dm_rms;              /* [m] rms of the offsets over the pupil's actuators */
    size_t frames_used;         /* camera frames live accumulated */
    double lag_median, lag_p99; /* [s] */
} swfs_live_loop_state;

typedef struct swfs_live_loop_result {
    size_t nstates;             /* iterations + 1: the state before each correction and after the last */
    swfs_live_loop_state s[SWFS_LIVE_LOOP_MAX + 1];
    double seconds;
} swfs_live_loop_result;

int swfs_live_loop_run(const swfs_live_loop_options *o, swfs_live_loop_result *r);

SWFS_END_DECLS

#endif

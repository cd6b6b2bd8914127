/* The stream: batches of WFS slopes and camera frames in time order -> per-pixel
 * accumulators (accum.h) -> the static-halo estimate, updated as the data arrive (the
 * real-time path; design in docs/streaming.md).
 *
 * Data come from a source, a callback that hands over one batch at a time: B camera
 * frames, the block of WFS slopes they integrate and the exposure schedule within that
 * block (engine.h). The file source (source.h: a timing table, its telemetry files and a
 * reduced science cube) is one; a shared-memory stream or an MPI rank implement the same
 * callback. Downstream of the source everything is arrays: the pipeline (pipeline.h)
 * turns the batch into core-referenced focal fields, the static halo is subtracted
 * (eq:computedSpeckleField) and every frame pair goes into the accumulators.
 *
 *   swfs_stream *s;  swfs_stream_create(&s, pipeline, &opt);
 *   swfs_stream_run(s, source_next, source_ctx, on_update, update_ctx);   // or push() batches
 *   swfs_stream_estimate(s, &halo);  ...  swfs_stream_free(s);
 *
 * Nothing is allocated per frame or per batch once the first batch has been seen. */
#ifndef SWFS_STREAM_H
#define SWFS_STREAM_H

#include <stddef.h>

#include "specklewfs/accum.h"
#include "specklewfs/engine.h"
#include "specklewfs/estimate.h"
#include "specklewfs/pipeline.h"

SWFS_BEGIN_DECLS

/* One batch: nexp camera frames (science: nexp frames of nfx x nfy, time order) and the
 * WFS frames they integrate (slopes: nwfs frames of nslopes; sched[j] the exposure of
 * camera frame j as indices into slopes). nexp = 0 marks the end of the data. */
typedef struct swfs_batch {
    const double *slopes;
    size_t nwfs;
    const swfs_exposure *sched;
    const double *science;
    size_t nexp;
    size_t cube;         /* the source's own label for messages (e.g. the camera cube index) */
} swfs_batch;

/* A source: fill *b with the next batch (b->nexp = 0 at the end); the arrays stay valid
 * until the next call. Returns a status; on failure the message says what and where. */
typedef int (*swfs_source_fn)(void *ctx, swfs_batch *b);

enum { SWFS_STATIC_AUTO = 0, SWFS_STATIC_NONE = 1, SWFS_STATIC_GIVEN = 2 };

typedef struct swfs_stream_options {
    int static_mode;           /* SWFS_STATIC_AUTO (default): S^1/2 Psi_0, the unaberrated halo
                                  scaled by the first batch's mean core amplitude (the paper's
                                  choice); NONE: no subtraction; GIVEN: static_halo */
    const swfs_complex *static_halo; /* nfx x nfy for SWFS_STATIC_GIVEN (copied) */
    swfs_noise noise;          /* camera noise model for the estimates */
    swfs_estimate_options est; /* estimator options (g_smooth in pixels) */
    size_t every;              /* update after every `every` camera frames (0: only at the end) */
    double every_seconds;      /* update when this many seconds have passed (0: never) */
    size_t max_frames;         /* stop after this many camera frames (0: all) */
} swfs_stream_options;

void swfs_stream_options_default(swfs_stream_options *o);

typedef struct swfs_stream swfs_stream;

/* Called at every update and once at the end (final = 1); a non-zero return stops the run
 * with that status. */
typedef int (*swfs_stream_update_fn)(void *ctx, const swfs_stream *s, int final);

/* The pipeline is borrowed (the caller frees it after the stream). */
int swfs_stream_create(swfs_stream **out, swfs_pipeline *p, const swfs_stream_options *opt);
void swfs_stream_free(swfs_stream *s);
/* Process one batch (nexp > 0). */
int swfs_stream_push(swfs_stream *s, const swfs_batch *b);
/* Pull batches from the source until it ends (or max_frames), calling update (may be
 * NULL) as the options say and once at the end. SWFS_ERR_NUMERIC if no frame arrived. */
int swfs_stream_run(swfs_stream *s, swfs_source_fn next, void *src_ctx, swfs_stream_update_fn update, void *upd_ctx);

/* Start a new accumulation (e.g. after the NCP was corrected): the accumulators and the
 * frame counts go back to zero; the static halo in use is kept. */
void swfs_stream_reset(swfs_stream *s);

/* The estimate from what has been accumulated (estimate.h); caller frees *out. */
int swfs_stream_estimate(const swfs_stream *s, swfs_halo **out);
/* h->resmean = the AO residual's time mean over the exposures pushed so far, from the
 * stream's pipeline (swfs_pipeline_mean_wavefront); swfs_stream_estimate attaches it. */
int swfs_stream_attach_resmean(const swfs_stream *s, swfs_halo *h);
const swfs_accum *swfs_stream_accum(const swfs_stream *s);
/* The static halo in use (nfx x nfy); NULL until the first batch with SWFS_STATIC_AUTO. */
const swfs_complex *swfs_stream_static(const swfs_stream *s);
size_t swfs_stream_camera_frames(const swfs_stream *s);
double swfs_stream_wfs_frames(const swfs_stream *s); /* exposure weights summed */
double swfs_stream_seconds(const swfs_stream *s);    /* processing time so far */
double swfs_stream_static_scale(const swfs_stream *s); /* S^1/2 of SWFS_STATIC_AUTO (NaN otherwise) */

SWFS_END_DECLS

#endif

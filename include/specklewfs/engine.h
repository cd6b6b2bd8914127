/* The fast per-frame engine: WFS slopes -> reconstructed wavefront -> pupil field ->
 * focal-plane speckle field at the camera rate, with core-phase referencing.
 *
 * Per WFS frame k (weight w_k inside a camera exposure):
 *   z_k   = W s_k                                  (reconstructor, [m] at the actuators)
 *   phi_k = (2 pi / lambda) T z_k                  (interpolation to the pupil grid)
 *   E    += w_k P exp(i phi_k)                     (pupil-field sum over the exposure)
 * and per camera frame, by linearity of the propagation (sum of MFTs = MFT of the sum):
 *   h     = MFT(E)                                 (mft.h, sign and sampling of docs/conventions.md)
 *   out   = h exp(-i arg h(core))                  (eq:downsampledHalo: the core phase is
 *                                                   the reference; core = (nfx/2, nfy/2))
 * If h(core) = 0 (e.g. an empty exposure) no phase is removed.
 *
 * How it is fast (docs/streaming.md): the plans are built once; slopes are reconstructed
 * up to 256 frames at a time by one single-precision GEMM; the interpolation is applied to
 * 16 frames at once (each nonzero is one 16-wide vector FMA); exp(i phi) uses the vectorized
 * sin/cos of kernels.h; only illuminated pupil samples are computed; the MFT is two cgemms
 * in single precision per camera frame. Nothing allocates after swfs_engine_create.
 * Batches run on nthreads cores, parallel over camera frames, each worker with its own
 * MFT plan and buffers and OpenBLAS single-threaded inside. Results do not depend on the
 * number of threads (the work split is fixed by the schedule alone).
 *
 * Precision: single-precision propagation (relative error ~1e-6 of the peak), double
 * output; the accumulators downstream are double. */
#ifndef SWFS_ENGINE_H
#define SWFS_ENGINE_H

#include <stddef.h>

#include "specklewfs/sparse.h"

/* Engine workers at most (speckles --threads, stream --threads, the pipeline). */
#define SWFS_ENGINE_MAX_THREADS 64
/* Fewest WFS frames per camera frame a schedule takes: a camera up to 10x faster than the WFS
 * (today's fastest pairs are ~1.25x: a 2.5 kHz science camera on a 2 kHz WFS). */
#define SWFS_ENGINE_MIN_RATIO 0.1

SWFS_BEGIN_DECLS

typedef struct swfs_engine_config {
    size_t nslopes, nact, npup, nfx, nfy;
    double alpha;              /* PIXSCALE * PUPDX / TELDIAM (mft.h) */
    double wavelen;            /* [m] */
    const double *recon;       /* nact x nslopes row-major, z [m] = W s */
    const swfs_sparse *interp; /* npup*npup x nact */
    const double *pupil;       /* npup*npup transmission; samples <= 0 are skipped */
    int remove_tiptilt;        /* subtract the mean of the x slopes (first half) and of the
                                  y slopes (second half) of every frame. The mean runs over
                                  all slopes: if unilluminated subapertures report 0, project
                                  the reconstructor instead (swfs_recon_project_tiptilt, as
                                  speckles.h and 'specklewfs stream' do) and leave this 0 */
    int nthreads;              /* workers for the batch calls (0 or 1: the calling thread) */
} swfs_engine_config;

typedef struct swfs_engine swfs_engine;

/* Copies what it needs from c (the caller may free recon/interp/pupil afterwards). */
swfs_engine *swfs_engine_create(const swfs_engine_config *c);
void swfs_engine_free(swfs_engine *e);
int swfs_engine_nthreads(const swfs_engine *e);
/* Illuminated pupil samples (those computed per frame). */
size_t swfs_engine_npin(const swfs_engine *e);
/* The wavefront [m] on the npup x npup grid (0 outside the illuminated samples) that the
 * engine reconstructs from one vector v of nslopes telemetry values, with its own
 * (single-precision) reconstructor and interpolation: the phase of the pupil field it
 * forms, times lambda / (2 pi). Not on the per-frame path (it allocates nact values). */
int swfs_engine_wavefront(const swfs_engine *e, const double *v, double *out);

/* ---- one frame at a time (a stream) ---------------------------------------- */

/* Add weight * P exp(2 pi i z / lambda) of one WFS frame (nslopes values, must be finite)
 * to the current exposure's pupil-field sum. Frames are buffered internally and
 * processed 256 at a time (or at end_exposure); allocation-free. */
int swfs_engine_add_wfs(swfs_engine *e, const double *slopes, double weight);
/* One MFT of the summed field, core-phase referencing, nfx*nfy complex to halo_out;
 * then start a new exposure. */
int swfs_engine_end_exposure(swfs_engine *e, swfs_complex *halo_out);
/* Drop the current exposure (frames added since the last end_exposure). */
void swfs_engine_reset(swfs_engine *e);

/* ---- batches (files, or a stream read in blocks) ------------------------- */

/* Camera exposure j integrates WFS frames first .. first+count-1 of the slopes block with
 * weight w_first on the first, w_last on the last and 1 in between (count = 1: w_first).
 * Fractional end weights describe a WFS frame that straddles two exposures; exposures
 * may share a frame. Keep the schedule in time order: a worker reconstructs the span of
 * frames its exposures cover. */
typedef struct swfs_exposure {
    size_t first, count;
    double w_first, w_last;
} swfs_exposure;

/* slopes: nwfs frames of nslopes (frame-major, as a FITS cube NAXIS1 = nslopes).
 * halo_out: nexp frames of nfx*nfy. Independent of the add_wfs stream state. */
int swfs_engine_process(swfs_engine *e, const double *slopes, size_t nwfs, const swfs_exposure *sched,
                        size_t nexp, swfs_complex *halo_out);
/* One MFT per WFS frame (weight 1), each core-referenced: the speckle field at the WFS
 * rate that the coherence maps need. halo_out: nwfs frames of nfx*nfy. */
int swfs_engine_process_wfs(swfs_engine *e, const double *slopes, size_t nwfs, swfs_complex *halo_out);

/* Helper for the common schedule: camera frame j integrates the WFS-time interval
 * [offset + j ratio, offset + (j+1) ratio) (in WFS frames, not necessarily an integer;
 * frame k covers [k, k+1)), so straddling frames get their fractional overlap as weight.
 * A camera faster than the WFS (SWFS_ENGINE_MIN_RATIO <= ratio < 1): each exposure is
 * the field interpolated linearly in time between the two WFS frames whose centres bracket
 * its centre (count 2, weights summing to ratio). Fills sched[0..nexp) and returns the
 * number of WFS frames needed, or 0 for invalid arguments. */
size_t swfs_engine_schedule(double ratio, double offset, size_t nexp, swfs_exposure *sched);

SWFS_END_DECLS

#endif

/* Speckle cubes from WFS telemetry (paper Sec. 4.4): the pieces around the per-frame
 * engine (engine.h) that turn a reconstructor, actuator positions and a timing table into
 * the speckle field psi matching the science frames (eq:downsampledHalo,
 * eq:computedSpeckleField). The CLI `specklewfs speckles` drives them. */
#ifndef SWFS_SPECKLES_H
#define SWFS_SPECKLES_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/engine.h"
#include "specklewfs/sparse.h"
#include "specklewfs/wfs.h"

SWFS_BEGIN_DECLS

enum { SWFS_MEAN_ENSEMBLE = 0, SWFS_MEAN_CUBE = 1 };

/* eq:computedSpeckleField: psi = down-sampled halo - static halo. The static halo is the
 * ensemble average over every frame of the cube (the paper's choice: its estimation
 * error is a constant across the pupil) or, with SWFS_MEAN_CUBE, the mean of each
 * camera cube (frames [first[c], first[c] + n[c]) of the array). In place. */
int swfs_speckles_subtract_static(swfs_cplx *halo, const size_t *first, const size_t *n, size_t ncubes, int mode);

/* Everything the engine needs on the pupil grid, built from the actuator positions:
 * the Clough-Tocher interpolation T (interp.h), the Shack-Hartmann model for nsub x nsub
 * subapertures, and the reconstructor -- loaded (recon != NULL, checked against nact
 * and 2 nsub^2 slopes) or built as the truncated SVD pseudo-inverse of D = S T (rcond,
 * max_modes: the "better reconstructor" of Sec. 4.4). With remove_tiptilt the
 * reconstructor is projected to ignore the mean x/y slopes over the valid subapertures
 * (swfs_recon_project_tiptilt), exactly the paper's tip-tilt removal. */
typedef struct swfs_speckle_model {
    size_t npup, nact, nslopes;
    double pupdx;          /* [m] */
    double *mask;          /* npup^2 */
    swfs_sparse *T;        /* npup^2 x nact */
    swfs_shwfs *wfs;
    swfs_recon *recon;     /* nact x nslopes */
    size_t n_outside;      /* illuminated samples outside the actuators' hull: within one actuator
                              pitch of it they continue the nearest inside sample's wavefront
                              (swfs_interp_extend_rim); farther is an error */
} swfs_speckle_model;

/* ---- tip-tilt as the registered science frames have it ----------------------------
 *
 * reduce re-centres every science frame on its peak: that removes the exposure's mean
 * image position, not the motion within the exposure, which stays in the frame as blur.
 * The speckles must match: remove from every WFS frame the weighted mean tip-tilt of its
 * exposure (the same weights as the exposure sum) and keep the rest. Removing each WFS
 * frame's own tip-tilt instead (the paper's Sec. 4.4, fine when the image wander within an
 * exposure is << lambda/D) drops the blur from the model: with 0.2 lambda/D rms of wander
 * within the exposures the NCP estimate failed (158 nm error from 105 nm injected, vs 34
 * nm with this model; docs/telemetry.md).
 *
 * The tip-tilt goes through the engine as two extra "slopes" per frame: an extended
 * reconstructor [W - C R | C] and frames [s_k, t_k - tbar]. t_k = R s_k is the tilt of
 * frame k's reconstructed wavefront T W s_k, the least-squares plane over the illuminated
 * pupil (the Z-tilt: what the simulator's ideal speckles remove, and what a peak
 * registration follows, the peak of a PSF with coma sits at the Z-tilt, not at the mean
 * gradient); tbar its exposure's weighted mean; C = the actuators' own coordinates (the
 * Clough-Tocher interpolation is exact for linear functions inside the hull), normalized
 * so a unit extra value is a unit tilt. W - C R reconstructs no tilt at all.
 *
 * Why not the mean slopes (the G-tilt), as the paper's Sec. 4.4 removes per frame: a
 * reconstructor projected to ignore the mean slopes still reconstructs the Z-tilt of the
 * coma-like part of the wavefront (Z - G: 0.031 lambda/D rms per exposure on the MMT-like
 * time series), which then stayed in every exposure as a mean offset the registered frames
 * do not have. Near the core that first-order error outweighs the second-order blur of
 * the real motion within the exposure when the image barely moves: with 0.5 lambda/D of
 * vibration the speckles had 6x the core power of the ideal ones and the NCP estimate
 * failed (244 nm error from 105 nm injected; docs/telemetry.md).
 *
 * W must not simply be projected (remove_tiptilt = 0 in swfs_speckle_model_create): R needs
 * the reconstructed tilt. The pipeline (pipeline.c) gives it W (I - M) + C G instead: the
 * mean slopes G out of the higher orders, and back as the plane they measure. */
enum { SWFS_TT_EXPOSURE = 0, SWFS_TT_FRAME = 1, SWFS_TT_KEEP = 2 };
/* "exposure", "frame", "keep" (the command line's spelling, SPECKLES.fits TIPTILT); "unknown" otherwise. */
const char *swfs_tiptilt_name(int mode);

/* W_ext: m->nact rows of m->nslopes + 2 (row-major) = [W - C R | C] from the model's
 * reconstructor m->recon (unprojected), interpolation and mask; xy the nact actuator
 * positions (x, y) [m]. R (if R != NULL): 2 rows of nslopes, the x then y tilt [rad] of
 * T W s. Caller frees *W_ext and *R. */
int swfs_speckles_recon_tilt(const swfs_speckle_model *m, const double *xy, double **W_ext, double **R);

/* The Z-tilt as linear functionals of a pupil-grid wavefront: the least-squares plane
 * p + tx x + ty y over the illuminated samples (mask > 0) of z (np x np, [m]) has
 * tx = f[0..np^2) . z and ty = f[np^2..2 np^2) . z. f: 2 np^2 values. */
int swfs_ztilt_functionals(const double *mask, size_t np, double pupdx, double *f);

/* Frames needed by swfs_speckles_expand: the sum of the exposures' counts. */
size_t swfs_speckles_expand_frames(const swfs_exposure *sched, size_t nexp);

/* For the exposures sched[0..nexp) of slopes (nwfs frames of nslopes), every exposure gets
 * its own copy of its WFS frames (a frame shared by two exposures is copied into both),
 * each followed by its tilt t = R s (R: 2 x nslopes, from swfs_speckles_recon_tilt) minus
 * the exposure's weighted mean: out has swfs_speckles_expand_frames() frames of
 * nslopes + 2, sched_out[j] the same weights over exposure j's copies (exposures no longer
 * share frames). SWFS_ERR_VALUE if an exposure leaves [0, nwfs). */
int swfs_speckles_expand(const double *slopes, size_t nslopes, size_t nwfs, const double *R,
                         const swfs_exposure *sched, size_t nexp, double *out, swfs_exposure *sched_out);

int swfs_speckle_model_create(swfs_speckle_model **out, const double *xy, size_t nact, const double *mask,
                              size_t npup, double pupdx, double teldiam, size_t nsub, const swfs_recon *recon,
                              double rcond, size_t max_modes, int remove_tiptilt);
/* The same with the AO system's valid-subaperture map (nsub^2 flags, swfs_shwfs_create_valid;
 * NULL: the illumination rule). */
int swfs_speckle_model_create_valid(swfs_speckle_model **out, const double *xy, size_t nact, const double *mask,
                                    size_t npup, double pupdx, double teldiam, size_t nsub, const unsigned char *valid,
                                    const swfs_recon *recon, double rcond, size_t max_modes, int remove_tiptilt);
void swfs_speckle_model_free(swfs_speckle_model *m);
/* Replace the model's reconstructor by the MAP (Wiener) reconstructor of D = S T learned
 * from the telemetry (swfs_recon_map: slopes nframes x nslopes, consecutive WFS frames;
 * noise_var [rad^2] > 0 fixes the slope noise, <= 0 estimates it), projected like
 * swfs_speckle_model_create when remove_tiptilt. */
int swfs_speckle_model_set_map(swfs_speckle_model *m, const double *slopes, size_t nframes, double noise_var,
                               int remove_tiptilt);
/* Same with the spatial-prior MAP reconstructor swfs_recon_vk (wfs.h): von Karman
 * covariance of the actuators xy (2 x nact [m]) with outer scale L0 [m], scaled to the
 * tip-tilt-free mean square of the slopes. */
int swfs_speckle_model_set_vk(swfs_speckle_model *m, const double *xy, double L0, const double *slopes, size_t nframes,
                              double noise_var, int remove_tiptilt);

SWFS_END_DECLS

#endif

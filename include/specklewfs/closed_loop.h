/* Closing the loop in simulation: the paper's Sec. 3 data set measured, corrected with a
 * deformable mirror, and measured again.
 *
 * Iteration k = 0, 1, ..., iterations-1:
 *   1. simulate the Sec. 3 data with the current residual NCP (swfs_sim_paper_run_ncp),
 *      a new seed per iteration (p->seed + k: new turbulence, as on the sky) and camera
 *      noise sigma (seed stream (p->seed + k, 0x100p));
 *   2. estimate the static halo (eq:scale-factor, eq:TheAnswer, eq:PSI-LowFreq) and the
 *      pupil WFE (default: the joint fit of pupil.h; moments one option away);
 *   3. fit the correction surface -WFE/2 onto the DM (dmfit.h) -> commands c_k;
 *   4. apply gain x c_k: DM commands C_{k+1} = C_k + gain c_k, and the residual wavefront
 *      becomes NCP + 2 A C_{k+1} (reflective DM; A the influence functions), so the
 *      residual keeps the DM's fitting error.
 * A last simulation measures the state after the final correction (no estimate).
 *
 * Per state k (after k corrections) the loop reports the residual NCP rms, the Strehl of
 * the simulated long-exposure PSF (peak of the mean noise-free science image over the
 * unaberrated peak C S^2 with the same counts; it includes the AO residual), the
 * Marechal estimate of the residual NCP alone, and the raw contrast of the static halo:
 * mean |halo_true|^2 in the annulus annulus_in..annulus_out lambda/D over its peak. That
 * coherent halo holds the (AO-attenuated) Airy rings, which no NCP correction removes, so
 * the loop also reports the NCP's own static speckles: the same mean of |halo_true -
 * halo_ao|^2, halo_ao = sqrt(C) S speckle_mean the static halo of the same frames without
 * NCP (same reference phases).
 * Design notes: docs/closed-loop.md. */
#ifndef SWFS_CLOSED_LOOP_H
#define SWFS_CLOSED_LOOP_H

#include <stddef.h>

#include "specklewfs/dmfit.h"
#include "specklewfs/pupil.h"
#include "specklewfs/sim.h"

SWFS_BEGIN_DECLS

typedef struct swfs_loop_params {
    size_t iterations;        /* corrections applied, 5 */
    double gain;              /* loop gain, 0.8 */
    double sigma;             /* camera background noise [counts], 100 */
    double act_pitch;         /* [m] hexapolar DM built when act_xy is NULL: 0.35 m gives 331
                                 actuators over 6.5 m (the MMT's DM has 336) */
    const double *act_xy;     /* optional actuator positions, nact (x, y) pairs [m] */
    size_t nact;
    const char *act_name;     /* where act_xy came from (e.g. ACT.fits), for messages; may be NULL */
    swfs_dmfit_options fit;   /* influence functions, modal filter (dmfit.h defaults) */
    swfs_pupil_options pupil; /* wavefront estimate (pupil.h defaults) */
    double annulus_in, annulus_out; /* [lambda/D] raw-contrast annulus, 2 and 6 */
} swfs_loop_params;

void swfs_loop_params_default(swfs_loop_params *lp);

/* State after k corrections (row k = 0 .. iterations). Fields marked (*) describe the
 * measurement made in that state and are NaN in the last row. */
typedef struct swfs_loop_iter {
    double resid_rms;       /* [m] residual NCP wavefront, piston removed over the pupil */
    double resid_rms_ptt;   /* [m] the same with tip/tilt also removed */
    double strehl;          /* long-exposure Strehl of the simulated science PSF */
    double strehl_ao;       /* the same without any NCP (the ceiling: perfect correction) */
    double strehl_marechal; /* exp(-(2 pi resid_rms / lambda)^2), the NCP alone */
    double contrast;        /* raw contrast of the static halo in the annulus */
    double contrast_ao;     /* the same for the no-NCP static halo (the floor) */
    double contrast_ncp;    /* mean |halo_true - halo_ao|^2 in the annulus over max |halo_true|^2:
                               the static speckles the NCP adds to the diffraction pattern */
    double est_rms;         /* (*) [m] estimated WFE, piston removed */
    double est_err;         /* (*) [m] estimate - residual, piston and tip/tilt removed */
    double median_snr;      /* (*) eq:SNR over valid pixels */
    swfs_dmfit_stats fit;   /* (*) fit of -WFE/2 (surface units [m]) */
    double seconds;         /* wall time of this row (simulation + estimate + fit) */
} swfs_loop_iter;

typedef struct swfs_loop_result {
    swfs_loop_params params;
    swfs_sim_params sim;   /* simulation parameters (seed of row 0) */
    swfs_geom geom;
    size_t nrows;          /* iterations + 1 */
    size_t nact;
    double pitch;          /* [m] influence pitch used */
    swfs_loop_iter *rows;  /* nrows */
    swfs_real *residual;   /* pupn x pupn x nrows: residual NCP [m] (piston removed) */
    swfs_real *estimate;   /* pupn x pupn x iterations: estimated WFE [m] */
    swfs_real *dm_surface; /* pupn x pupn x nrows: accumulated DM surface [m] */
    swfs_real *commands;   /* nact x nrows: accumulated actuator commands [m] */
    swfs_real *actuators;  /* 2 x nact [m] */
    swfs_real *pupil;      /* pupn x pupn mask */
    double seconds;        /* total wall time */
} swfs_loop_result;

/* p: the Sec. 3 simulation (its NCP terms give the initial NCP). first (may be NULL): an
 * existing swfs_sim_paper_run(p) result to use as the row-0 simulation (it must have been
 * made with p, e.g. by `demo`), which saves one simulation. progress (may be NULL) is
 * called with stage "loop" after each row. */
int swfs_closed_loop_run(const swfs_sim_params *p, const swfs_loop_params *lp, const swfs_sim_result *first,
                         swfs_progress_fn progress, void *ctx, swfs_loop_result **out);
void swfs_loop_result_free(swfs_loop_result *r);

/* Raw contrast of a static halo (nfx x nfy, star at (nfx/2, nfy/2), pixscale lambda/D per
 * pixel): mean |h|^2 over rin <= r <= rout [lambda/D] divided by max |h|^2. NaN when the
 * annulus holds no pixel. */
double swfs_halo_contrast(const swfs_cplx *h, double pixscale, double rin, double rout);

/* DIR/loop.fits (RESIDUAL, ESTIMATE, DMSURF cubes, COMMANDS, ACTUATORS, PUPIL, METRICS:
 * one row of the table per state) and DIR/loop.tsv (the table as text). */
int swfs_closed_loop_write(const swfs_loop_result *r, const char *dir, const char *const *prov, size_t nprov);

SWFS_END_DECLS

#endif

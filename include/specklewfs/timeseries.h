/* Time-series simulation of the real-data path (paper Sec. 4): frozen-flow von Karman
 * layers blown across the pupil, a closed AO loop at the WFS rate (Shack-Hartmann slopes
 * with noise, integrator with gain and delay, a DM of a few hundred actuators driven
 * through a modal filter keeping K modes), tip-tilt vibration, and a science camera whose
 * exposures integrate the instantaneous PSF (with the NCP) over a non-integer number of
 * WFS frames, in cubes with gaps, started at an offset and logged by a handshake that is
 * late by an unknown lag. Design notes: docs/telemetry.md.
 *
 * Everything shared with the Sec. 3 simulator (telescope, wavelength, focal window,
 * counts, camera noise, NCP, r0, L0, screen size, seed) comes from swfs_sim_params and
 * its config keys; the keys below are the time-series ones (config/mmt-clio.conf).
 *
 * Written to DIR:
 *   slopes_NNN.fits   telemetry files, NAXIS1 = 2 nsub^2 slopes [rad] (x then y),
 *                     NAXIS2 = WFS frames (wfs_file_frames per file)
 *   actuators.fits    2 x nact [m];  recon_ao.fits  the loop's K-mode reconstructor [m/rad]
 *   handshake.log     CAMERA_FILE SLOPES_FILE WFS_FRAME per cube (late by handshake_lag)
 *   raw_NNN.fits      raw camera cubes [counts]: flat * (signal + background + noise) + dark,
 *                     with the geometry keywords and GAIN
 *   dark.fits, flat.fits          calibration frames (hot / dead pixels inside)
 *   speckles_ideal.fits           the ideal speckles (true residual without NCP, same
 *                     exposure sums and core-phase referencing as the slopes path,
 *                     ensemble mean removed), one frame per camera frame; from every WFS
 *                     frame the weighted mean tip-tilt of its exposure is removed and the
 *                     motion within the exposure kept, as in a registered science frame
 *                     (speckles --tiptilt exposure)
 *   speckles_ideal_tt.fits        the same with the tip-tilt left in
 *   truth.fits        NCP [m] (piston removed), PUPIL, RESMEAN (time-mean residual [m]);
 *                     keys RATIO, HSLAG, residual rms, STATRMS
 *   truth_timing.txt  the true exposure start of every cube (global WFS frames)
 *
 * With milk=1 also the same WFS slopes and raw camera frames as milk/cacao stream logs
 * (milklog.h, ../shared/FORMATS.md), the worked example of that format:
 *   milk/wfs/wfs_hh:mm:ss.sssssssss.fits + .txt   slopes as N x 1 x T cubes, milk_file_frames
 *                     WFS frames per file; stamp of WFS frame k (0-based) = milk_epoch + (k+1)
 *                     / wfs_rate (the END of the frame) + jitter, cnt0 = k + 1
 *   milk/cam/cam_hh:mm:ss.sssssssss.fits + .txt   raw camera frames, each cube cut into files
 *                     of milk_cam_file_frames, EXPTIME, GAIN and the geometry in the header;
 *                     cnt0 counts exposures over the cubes (1, 2, ...); the stamp is the
 *                     exposure's end read on the camera clock: t_cam - epoch = (t_wfs - epoch
 *                     - milk_offset) / (1 + milk_drift), + jitter
 *   milk/truth.txt    epoch, drift, offset, jitter, dropped frames, exposure time
 * milk_drop_wfs / milk_drop_cam frames are left out of the files (counter jumps). */
#ifndef SWFS_TIMESERIES_H
#define SWFS_TIMESERIES_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/config.h"
#include "specklewfs/sim.h"

SWFS_BEGIN_DECLS

#define SWFS_TS_MAX_LAYERS 3

typedef struct swfs_ts_params {
    swfs_sim_params base;      /* shared keys (teldiam, pupn, pupdx, wavelen, nfx, ...) */
    /* turbulence layers (lists of nlayers values) */
    int nlayers;               /* 2 */
    double layer_frac[SWFS_TS_MAX_LAYERS];  /* fraction of the turbulence (sum 1) */
    double layer_speed[SWFS_TS_MAX_LAYERS]; /* [m/s] */
    double layer_dir[SWFS_TS_MAX_LAYERS];   /* [deg] from +x */
    /* AO loop */
    double wfs_rate;           /* [Hz] 527 */
    long nsub;                 /* 12 */
    double act_pitch;          /* [m] hexapolar ring spacing, 0.45 (217 actuators on 6.5 m) */
    double ao_gain;            /* 0.4 */
    long ao_delay;             /* [frames] 1 or 2 (2) */
    long ao_modes;             /* K modes kept by the modal filter (56) */
    double ao_rcond;           /* > 0: the loop reconstructs with the truncated SVD pseudo-inverse of its
                                  interaction matrix, keeping the modes whose singular value exceeds
                                  ao_rcond times the largest (a zonal loop: its modes the interaction
                                  matrix's, not the DM's lowest-energy ones; ao_modes unused); 0
                                  (default): the ao_modes modal filter */
    double slope_noise;        /* [rad] rms per slope (3e-8; the Shack-Hartmann's) */
    /* wfs=pyramid: a modulated pyramid (pyramid.h) on the Shack-Hartmann's subaperture grid
       senses instead; its signals are the telemetry (slopes_NNN.fits, the same layout) */
    long wfs_pyramid;          /* 1: the key wfs=pyramid; 0: wfs=sh (default) */
    double pyr_mod;            /* [lambda_wfs/D] modulation radius (3) */
    long pyr_nmod;             /* modulation points (0: pyramid.h's rule, two per lambda/D of circle) */
    double wfs_wavelen;        /* [m] the sensing wavelength (0: wavelen) */
    double pyr_photons;        /* photons per used subaperture per WFS frame, Poisson noise (1000; 0:
                                  noiseless) */
    /* tip-tilt vibration added upstream of the loop */
    double vib_amp;            /* [lambda/D at wavelen] amplitude (0.5) */
    double vib_freq;           /* [Hz] 20 */
    double vib_angle;          /* [deg] 30 */
    double jitter_amp;         /* [lambda/D] rms per axis of broadband pointing jitter (0.05):
                                  first-order low-pass white noise, corner jitter_freq */
    double jitter_freq;        /* [Hz] 30 */
    /* science camera */
    double frame_ratio;        /* <t_sci/t_wfs> 6.48 */
    long ncubes, cube_frames;  /* 6 x 100 */
    double cube_gap;           /* [WFS frames] dead time between cubes (200) */
    double start_offset;       /* [WFS frames] first cube start (300.4: loop settled) */
    long handshake_lag;        /* [WFS frames] 3 */
    long wfs_file_frames;      /* frames per telemetry file (0: one file) */
    double bandwidth;          /* fractional optical bandwidth (0; 0.2 for 20 %) */
    long nlambda;              /* wavelengths across the band when bandwidth > 0 (5) */
    double background;         /* [counts per pixel per exposure] 20 */
    double dark_level;         /* [counts] bias 3700 */
    double flat_rms;           /* 0.02 */
    long nhot, ndead;          /* bad pixels (5, 5) */
    /* the science camera's orientation on the sky: the detector shows the focal plane
       transposed (camera_swap), then mirrored along its x and/or y axis (0, 0, 0) */
    long camera_swap, camera_flip_x, camera_flip_y;
    long act_square;           /* the DM's actuators on a square grid of pitch act_pitch clipped to
                                  a circle (1), or hexapolar rings (0, default) */
    double dm_coupling;        /* 0 < c < 1: the DM's surface from Gaussian influence functions of
                                  coupling c (a command's surface at the neighbouring actuator, a
                                  fraction of its own; interp.h swfs_influence_gauss_grid), as a
                                  continuous facesheet's; 0 (default): the Clough-Tocher surface
                                  through the commands (the paper's interpolation) */
    long export_modal;         /* 1: also the telemetry in cacao's modal form, modal_NNN.fits and
                                  dm_modes.fits, and as valid-only slopes, slopes_valid_NNN.fits with
                                  control.fits, influence.fits and valid.fits, and the modal control
                                  matrix cm_modes.fits (swfs_ts_export_modal
                                  in run.h; `simulate` runs it) */
    long export_truth;         /* 1: also truewf_NNN.fits beside slopes_NNN.fits, the same WFS frames:
                                  the true residual wavefront each frame's slopes measured [m],
                                  least-squares fitted on the actuators (NAXIS1 = nact, the order of
                                  actuators.fits), and extension DM the commands the loop applied
                                  in that frame [m of wavefront at the actuators: the residual is the
                                  turbulence less the DM's surface from them (their interpolation,
                                  or the influence functions with dm_coupling), so truth + that
                                  surface is the open-loop wavefront] (0) */
    long camera_light;         /* 1: the camera integrates two cubes of 20 frames at one WFS frame
                                  each, placed so that the run holds the WFS frames the camera keys
                                  as given would make it run: training loops whose camera is not
                                  used (export_truth) get the same slopes and truth for a fraction
                                  of the time; the camera draws its noise from a stream of its own.
                                  swfs_ts_params_from_config applies it (swfs_ts_camera_light) (0) */
    /* milk logs (above) */
    long milk;                 /* 1: also write them (0) */
    double milk_epoch;         /* [s] Unix time of the start of WFS frame 0, whole seconds (1.7e9) */
    double milk_jitter;        /* [s] rms of every stamp (3e-6) */
    double milk_drift;         /* camera clock rate error relative to the WFS clock (1e-4) */
    double milk_offset;        /* [s] camera clock offset: t_wfs = epoch + (t_cam - epoch)(1 + drift) + offset (2.5e-3) */
    long milk_drop_wfs, milk_drop_cam; /* frames dropped from each stream (5, 3) */
    long milk_file_frames;     /* WFS frames per file (400) */
    long milk_cam_file_frames; /* camera frames per file (40) */
    char actuators[1024];      /* the DM's actuator positions from a file in the layout of actuators.fits
                                  (NAXIS1 = 2: x, y; NAXIS2 = nact [m]), e.g. an AO system's own, so
                                  that `learn` can be taught on its DM; "" (default): built from
                                  act_pitch and act_square */
    char ao_recon[1024];       /* the loop's reconstructor from a file (recon_ao.fits layout: NAXIS1 = slopes,
                                  NAXIS2 = actuators [m/rad]), e.g. the AO system's own control matrix in
                                  this convention; "" (default): the ao_modes lowest-energy DM modes */
    char valid[1024];          /* the AO system's valid-subaperture map (nsub x nsub, nonzero = used, as
                                  `speckles --valid` takes): the simulated Shack-Hartmann uses those
                                  subapertures; "" (default): those at least half lit */
    char truth_actuators[1024]; /* export_truth's points (actuators.fits layout): the true residual is
                                  fitted there instead of on the DM's actuators, e.g. teach's grid finer
                                  than the DM's (docs/telemetry.md); truewf_NNN.fits then carry them as
                                  extension OUTXY and `learn` gives its map those output points;
                                  "" (default): the DM's actuators */
} swfs_ts_params;

void swfs_ts_params_default(swfs_ts_params *p);
/* The DM's positions the simulator lays out when no actuators file is given: act_pitch,
 * square (act_square) or hexapolar, over teldiam (*xy: 2 nact doubles, free()). */
int swfs_ts_dm_layout(const swfs_ts_params *p, double **xy, size_t *nact);
/* The shared keys via swfs_sim_params_from_config, then the time-series keys. */
int swfs_ts_params_from_config(swfs_config *c, swfs_ts_params *p);
/* Whether the configuration gives the loop's filter (ao_modes, ao_recon or ao_rcond): `teach`
 * takes it from the observation's slopes otherwise. */
int swfs_ts_config_gives_filter(const swfs_config *c);
int swfs_ts_params_check(const swfs_ts_params *p);
/* The defaults with n "key=value" settings (`simulate mode=timeseries` keys), read and checked:
 * an unknown key, a value that does not parse and one out of range are refused by name. */
int swfs_ts_params_from_keys(const char *const *kv, size_t n, swfs_ts_params *p);

typedef struct swfs_ts_summary {
    size_t nwfs;               /* WFS frames simulated */
    size_t nact, nvalid;       /* actuators, valid subapertures */
    size_t ao_modes;
    double residual_rms;       /* [m] mean piston-removed pupil rms during the exposures */
    double residual_rms_nott;  /* [m] the same with tip-tilt removed */
    double tt_rms;             /* [lambda/D] residual tip-tilt (2-axis rms) */
    double strehl;             /* mean short-exposure-field Strehl with NCP */
    double static_rms;         /* [m] rms of the time-mean residual (tip-tilt removed) over the
                                  exposures: a static aberration not in the speckles */
    double ncp_rms;            /* [m] */
    double seconds;
} swfs_ts_summary;

/* The progress callback of status.h, under the name this module had first. */
typedef swfs_progress_fn swfs_ts_progress_fn;

/* The WFS frames swfs_ts_run simulates for p: up to the last exposure's last frame, plus the
 * handshake lag and 10 (0: out of memory). */
size_t swfs_ts_nframes(const swfs_ts_params *p);

/* camera_light: the camera keys replaced by two cubes of 20 frames at one WFS frame each, with
 * the gap between them set so that swfs_ts_nframes is unchanged; kept as they are where they
 * already need fewer frames. */
void swfs_ts_camera_light(swfs_ts_params *p);

/* Every file swfs_ts_run writes into dir, as outputs of `paths` (outpaths.h): the
 * command checks them before simulating. Returns the paths' status. */
struct swfs_paths;
int swfs_ts_add_outputs(const swfs_ts_params *p, const char *dir, struct swfs_paths *paths);

/* The loop's controlled modes as its residual slopes show them (`teach`). The slopes'
 * variance along each DM mode's slope pattern: the system's modes after piston (the
 * lowest-energy modes its loop filters with, ao_modes) through its interaction matrix,
 * orthonormalized in that order (QR), so that mode j counts only what the lower modes do not
 * explain. slopes: nframes x nslopes, the full layout (2 nsub^2, unused subapertures 0) or
 * the used subapertures' only (x then y, row-major; the valid map p->valid, else the
 * simulator's), with the same variances; another width is SWFS_ERR_SHAPE. var: nmodes
 * values (malloc'd; nmodes = min(nact - 1, 2 nsub^2)); NaN for a mode whose slope pattern the
 * lower modes' explain (no direction of its own: e.g. beyond the rank of a valid map's
 * interaction matrix). A pyramid's signals (p->wfs_pyramid) along its own interaction
 * matrix's patterns (pyramid.h, as the loop calibrates it). The loop attenuates the modes it controls: var rises over them and
 * falls from about the last one on (docs/telemetry.md). */
int swfs_ts_mode_variance(const swfs_ts_params *p, const double *slopes, size_t nframes, size_t nslopes,
                          double **var, size_t *nmodes);
/* The slopes' time correlation along the same modes (`teach`, where the slopes show no
 * frozen-flow layer: the speed of its loops' layers): the coefficients along the upper half
 * of the modes (each slope's time mean removed; the modes without a direction left out), and
 * rho[k] their lag-lags[k] products over their lag-0 ones, summed over those modes, per frame
 * pair. The upper half: modes many and independent, decorrelating as a layer moves across a
 * fraction of a subaperture, and clear of the tip-tilt and its DM-fitted ripple that vibration
 * drives (measured: docs/telemetry.md, "Slopes without a frozen-flow layer"). lags: 1 to
 * nframes - 1. */
int swfs_ts_mode_timecorr(const swfs_ts_params *p, const double *slopes, size_t nframes, size_t nslopes,
                          const long *lags, size_t nlags, double *rho);
/* The knee of such a profile: the mode K that best splits log var_j against log j into two
 * least-squares lines, modes 1..K and K+1..n, each of at least 3 modes with a variance (NaN
 * ones left out). 0 when fewer than 6 have one, or out of memory. */
size_t swfs_mode_knee(const double *var, size_t n);

/* The DM's influence functions the loop's given reconstructor (p->ao_recon: actuators x
 * slopes, the full layout or the used subapertures' only) says: a pseudo-inverse of the
 * interaction matrix the system measured, compared within its row and column spaces with the
 * mean-gradient interaction matrix of the described sensor and DM (p's pupil, valid map and
 * actuators) after the best single scale, for Gaussian functions of coupling c
 * (swfs_influence_gauss_grid; c by a log-spaced grid over SWFS_TS_COUPLING_MIN..MAX, then
 * golden-section search) and for the interpolated surface (dm_coupling 0). gaussian: 1 where
 * the best c's misfit (relative, Frobenius) is below the surface's (docs/telemetry.md, "The
 * DM's functions from the loop's control matrix"). */
typedef struct swfs_ts_coupling {
    double coupling;        /* the best Gaussian coupling */
    double misfit;          /* its relative misfit */
    double misfit_interp;   /* the interpolated surface's */
    size_t rank;            /* the reconstructor's numerical rank (singular values above 1e-9 of the largest) */
    int gaussian;
} swfs_ts_coupling;
#define SWFS_TS_COUPLING_MIN 0.02  /* the couplings searched: a facesheet whose neighbour moves by */
#define SWFS_TS_COUPLING_MAX 0.8   /* 2 % of a command up to one that barely separates them */
#define SWFS_TS_COUPLING_GRID 12
int swfs_ts_coupling_from_recon(const swfs_ts_params *p, swfs_ts_coupling *out);

/* DIR and, for milk=1, its milk/wfs and milk/cam folders, created where missing (what
 * swfs_ts_run writes into; a command calls it before checking the outputs). */
int swfs_ts_make_dirs(const swfs_ts_params *p, const char *dir);

/* Simulate and write DIR (its folders made by swfs_ts_make_dirs where missing): its files
 * as one output group (atomic.h), none of them left by a run that fails or is stopped. */
int swfs_ts_run(const swfs_ts_params *p, const char *dir, const char *const *prov, size_t nprov,
                swfs_ts_progress_fn progress, void *ctx, swfs_ts_summary *sum);

/* What swfs_ts_run builds from the system alone, made once for many runs of one system (as
 * teach's loops are: they differ in seeds, layers, lengths and ao_modes): the DM's modes
 * (unless ao_recon gives the loop) and, with export_truth, the truth's fit plan on its points
 * (an eigen-decomposition of as many points squared, the largest set-up cost of a run on a
 * fine truth_actuators grid). Read only by the runs, so runs on several threads may share
 * one. */
typedef struct swfs_ts_shared swfs_ts_shared;
int swfs_ts_shared_create(const swfs_ts_params *p, swfs_ts_shared **out);
void swfs_ts_shared_free(swfs_ts_shared *s);
/* swfs_ts_run with the shared plans s (NULL: its own): the same files, bit for bit. A run
 * whose pupil, DM positions or truth's points differ from those s was made for, or that needs
 * what s lacks (the modes; the truth's plan with export_truth), is SWFS_ERR_ARG. */
int swfs_ts_run_shared(const swfs_ts_params *p, const swfs_ts_shared *s, const char *dir, const char *const *prov,
                       size_t nprov, swfs_ts_progress_fn progress, void *ctx, swfs_ts_summary *sum);

SWFS_END_DECLS

#endif

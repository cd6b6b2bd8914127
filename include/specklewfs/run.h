/* The file-driven runs: each command of the data flow as one library call that reads its
 * inputs, runs the method on arrays and writes its products (atomically: a failed run
 * leaves no file that looks complete). `specklewfs <command>` parses its options, calls
 * one of these and prints the summary; an application can do the same without the CLI.
 *
 * Every run takes provenance lines (prov, nprov: e.g. the command line) recorded in the
 * products, and an optional progress callback (status.h). Messages name the file, the
 * value and what was expected.
 *
 * estimate, speckles and stream also run as a team (team.h; `mpirun`, docs/cluster.md):
 * with `team` set, every member calls the run with the same options, processes its share
 * of the frames (balanced by frames; a member may take part of a cube) and member 0 writes
 * the products, equal to the single-process run's to rounding. Only member 0's result
 * holds the estimate; the counts in every member's result are the whole data set's. */
#ifndef SWFS_RUN_H
#define SWFS_RUN_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/clocksync.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/estimate.h"
#include "specklewfs/lmodel.h"
#include "specklewfs/milksource.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/pupil.h"
#include "specklewfs/recovery.h"
#include "specklewfs/reduce.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wind.h"
#include "specklewfs/stream.h"
#include "specklewfs/sync.h"
#include "specklewfs/team.h"

SWFS_BEGIN_DECLS

/* ---- the camera noise model ------------------------------------------------------ */

/* RDNOISE [counts] and GAIN [e-/count] from the header of `path`'s primary HDU (0 where
 * absent), then the explicit values where they are not NaN. SWFS_ERR_VALUE naming the
 * file unless RDNOISE is in 0 .. 1e6 counts and GAIN is 0 (no photon noise) or in
 * 1e-4 .. 1e6 e-/count. */
int swfs_noise_from_header(const char *path, double read_noise, double gain, swfs_noise *out);
/* The g regularization length in pixels from lambda/D: g_smooth_lod / PIXSCALE, or with no
 * PIXSCALE the paper's 0.25 lambda/D per pixel (*assumed = 1 then). */
double swfs_g_smooth_pixels(double g_smooth_lod, double pixscale, int *assumed);

/* ---- the generic linear speckle model from files (lmodel.h, docs/telemetry.md) ------ */

/* Any AO system's telemetry: a basis of mode shapes or influence functions instead of the
 * actuator positions and the Shack-Hartmann model. */
typedef struct swfs_linear_files {
    const char *basis;       /* NULL: the Shack-Hartmann model. A cube PUPN x PUPN x nk on the
                                pupil grid, or gx x gy x nk on the DM's grid placed by reg */
    const char *control;     /* NAXIS1 = telemetry values per frame, NAXIS2 = nk: the
                                coefficients = C v; NULL (and no imat): v are the coefficients.
                                A cube of them, one plane per lag (NLAGS, LAGk): a space-time
                                control matrix of the values of frames t + LAGk */
    const char *imat;        /* NAXIS1 = nk, NAXIS2 = telemetry values: the interaction matrix,
                                inverted by the telemetry-learned MAP reconstructor (or SVD) */
    swfs_dm_registration reg;/* reg.pitch 0: the basis is on the pupil grid */
    double scale;            /* metres of wavefront per unit of basis x coefficient (1) */
} swfs_linear_files;

void swfs_linear_files_default(swfs_linear_files *lf);
/* The tip-tilt sync correlates, for telemetry of nmeas values per frame: the Z-tilt of lf's
 * wavefront per value (2 x nmeas, caller frees; swfs_pipeline_tilt_rows) on the geometry of
 * the science cube `science`. */
int swfs_linear_tilt_rows(const swfs_linear_files *lf, const char *science, size_t nmeas, double **R);
/* The lags of lf's control matrix where it is a space-time one (a cube of one plane per lag,
 * NLAGS and LAGk: `learn --lags`, speckles' loops' map): *nl of them into lags
 * (SWFS_RECON_MAXLAGS long); *nl = 0 for a per-frame matrix or none. Its input is then the
 * telemetry of frames t + lags[k] stacked (swfs_slopes_stack), which speckles, stream and live
 * stack as they do for a Shack-Hartmann's space-time map. */
int swfs_linear_control_lags(const swfs_linear_files *lf, long *lags, size_t *nl);
/* The pipeline over lf's model (swfs_pipeline_create_linear) for telemetry of nmeas values
 * per frame (0: as many as the control matrix takes, or the basis functions): the files read, their shapes checked against each other, nmeas and PUPN, each
 * message naming the file. mask: PUPN^2 or NULL (the annulus of g). *n_outside: illuminated
 * pupil samples beyond the DM grid (refused when any lies there). */
int swfs_linear_pipeline(swfs_pipeline **p, const swfs_linear_files *lf, const swfs_geom *g, size_t nfx, size_t nfy,
                         const double *mask, size_t nmeas, const double *train, size_t ntrain,
                         const swfs_pipeline_options *po);
/* A learned map's miss of the residual's time mean: where the map file `path` (a --recon map,
 * or with lin->basis a --control matrix; NULL: none) has the extension MEANMISS (learn's, one
 * value per output; or, from speckles' loops_map, an image on the pupil grid), its wavefront on
 * the pupil grid (the Shack-Hartmann model's interpolation of the map's outputs, the linear
 * model's basis, or the image itself) becomes p's mean offset
 * (swfs_pipeline_set_mean_offset); *rms its rms in the pupil, piston, tip and tilt removed (0:
 * none). speckles and stream call it on the pipeline they built (Python: Pipeline.from_files). */
int swfs_map_meanmiss_attach(swfs_pipeline *p, const char *path, const swfs_linear_files *lin, const swfs_geom *g,
                             double *rms);
/* The Shack-Hartmann pipeline (swfs_pipeline_create) with the valid-subaperture map of the
 * file `valid` (NULL: po's own, normally none; swfs_valid_map_read), then the NSUB keyword of
 * the telemetry file `telemetry` (NULL or "": none) checked against the model it made.
 * `model` (NULL: none) names what the model is built from: the context of a failure to build
 * it (an NSUB mismatch names the telemetry file itself). */
int swfs_sh_pipeline(swfs_pipeline **p, const char *model, const char *valid, const char *telemetry, const swfs_geom *g,
                     size_t nfx, size_t nfy, const double *xy, size_t nact, const double *mask, size_t nslopes,
                     const swfs_recon *recon, const double *train, size_t ntrain, const swfs_pipeline_options *po);

/* The time-series simulation's telemetry (dir holds simulate mode=timeseries' files) in the
 * modal form of cacao-based systems, the worked example of --basis: modal_NNN.fits (per WFS
 * frame the coefficients of the DM's modes 1.. (swfs_dm_modes; piston dropped) of the
 * default speckle reconstructor's wavefront, in um of DM surface on unit-rms modes, as
 * cacao's modevalWFS) and dm_modes.fits (the mode cube on a DM grid of a quarter of the actuator
 * pitch, offset, turned by 10 degrees and mirrored on the pupil; the registration in its
 * keys DMPITCH, DMOFFX, DMOFFY, DMROT, DMFLIPX and in *reg), and cm_modes.fits (the modal
 * control matrix from the valid slopes to those coefficients, for swfs_modal_slopes_run). */
struct swfs_ts_params;
int swfs_ts_export_modal(const struct swfs_ts_params *p, const char *dir, const char *const *prov, size_t nprov,
                         swfs_dm_registration *reg, size_t *nmodes);

/* ---- estimate: science + speckle cubes -> HALO.fits ------------------------------ */

typedef struct swfs_estimate_run_options {
    const char *science, *speckles, *out;
    double read_noise, gain;  /* NaN: from the science header (RDNOISE, GAIN; else 0) */
    double g_smooth_lod;      /* scale-factor regularization [lambda/D] (2; 0 = the paper's g) */
    size_t block;             /* frames read at a time (64) */
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
    const swfs_team *team;    /* NULL: alone; else this member's share of the frames */
} swfs_estimate_run_options;

void swfs_estimate_run_options_default(swfs_estimate_run_options *o);

typedef struct swfs_estimate_run_result {
    swfs_halo *halo;          /* the estimate (caller frees with swfs_halo_free); NULL on members > 0 */
    swfs_geom geom;           /* of the speckle cube */
    swfs_noise noise;         /* the noise model used */
    double circ_core;         /* mean |<psi^2>|/<|psi|^2> inside 4 lambda/D (NaN without PIXSCALE) */
    int g_smooth_assumed;     /* 1: no PIXSCALE, 0.25 lambda/D per pixel assumed */
} swfs_estimate_run_result;

int swfs_estimate_run(const swfs_estimate_run_options *o, swfs_estimate_run_result *r);

/* ---- speckles: timing table + telemetry -> the speckle cube ---------------------- */

/* speckles' default reconstructor choice (pipe.recon; the run layer's own, next to
 * pipeline.h's SWFS_RECON_*): a map taught for the observation, as `teach` from its own files
 * (swfs_teach_run with swfs_teach_describe: the science cube's geometry, the actuators, the
 * pupil mask, the valid map, the timing table's telemetry files), then applied as
 * SWFS_RECON_GIVEN. Where teach cannot (no frozen-flow layer in the slopes, too few DM modes,
 * a rate the files lack, ...) the run says why (teach_fallback) and uses SWFS_RECON_VK. The
 * linear model (lin.basis) has its own reconstructor and ignores it. docs/telemetry.md, "The
 * default path: a map taught for each observation": within 1.3x of the ideal speckles on 45
 * of the matrix's 48 runs (bench_telemetry, seeds 1-4), where SWFS_RECON_VK was on 23. */
#define SWFS_RECON_TEACH 4
struct swfs_teach_run_result;

typedef struct swfs_speckles_run_options {
    const char *timing;       /* timing table (sync); relative telemetry names are taken from its folder */
    const char *science;      /* reduced science cube: geometry keywords and the focal window */
    const char *actuators;    /* 2 x nact [m] */
    const char *out;          /* the speckle cube */
    const char *recon;        /* reconstructor file for SWFS_RECON_GIVEN (nslopes x nact image) */
    const char *mask;         /* pupil mask PUPN x PUPN, NULL = annulus */
    const char *write_recon;  /* also write the reconstructor in use, NULL = no */
    swfs_pipeline_options pipe; /* with pipe.wfs_rate, tiptilt SWFS_TT_EXPOSURE (the default) is
                                   SWFS_TT_FRAME: at the WFS rate there is no exposure to take a
                                   mean tip-tilt over */
    int mean_mode;            /* SWFS_MEAN_ENSEMBLE (default) or SWFS_MEAN_CUBE (speckles.h) */
    double wfs_hz;            /* pipe.wfs_rate: WFS rate [Hz] when the telemetry has no WFSRATE */
    const char *const *match_in, *const *match_out; /* nmatch pairs: OUT = the usable frames of IN */
    size_t nmatch;
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
    size_t batch;             /* frames per pipeline call (128; 0 = 128): a cube goes through the
                                 pipeline in pieces of `batch` frames from its start, as the
                                 stream's batches do, so the fields do not depend on how the
                                 cubes are shared out (the float engine's sums do depend on the
                                 frames of a call) */
    const swfs_team *team;    /* NULL: alone; else this member's share of the output frames, cut
                                 at multiples of batch (each member builds the same reconstructor
                                 from the files) */
    swfs_geom geom;           /* given geometry: fills or replaces the science header's */
    swfs_linear_files lin;    /* lin.basis: the generic linear model instead of the actuators */
    const char *valid;        /* the Shack-Hartmann model's valid-subaperture map (swfs_valid_map_read),
                                 NULL = the illumination rule; the telemetry may then hold only the
                                 used subapertures' slopes (pipeline.h) */
    /* SWFS_RECON_TEACH (the default): */
    const char *teach_work;   /* folder for teach's loops and maps, created if missing (NULL: beside
                                 out, its name without .fits and with .teach); the map is
                                 taught.fits in it, for --recon in later runs */
    size_t teach_loops;       /* loops per set (12) */
    size_t teach_max_loops;   /* the space-time map's loops at most (teach's max_loops; 0: 4
                                 teach_loops, at most 64) */
    uint64_t teach_seed;      /* loop k's seed is teach_seed + k (101) */
    int teach_keep_loops;     /* 1: keep the loops' folders (0: removed once the map is taught, the
                                 maps, modes.tsv and modes.png kept: 0.2-0.4 GB per observation
                                 on the matrix's 16 x 16 and 24 x 24 systems otherwise) */
    struct swfs_teach_run_result *teach; /* teach's own result (layers, filter, choice), or NULL */
    int teach_again;          /* 1: teach even when the work folder's taught.fits was taught for the
                                 same inputs (0: reused then: its TEACHFPR, the fingerprint of the
                                 telemetry's and the system files' contents, the description teach
                                 is given, the loops, the seed, SWFS_VERSION and SWFS_TEACH_RULE,
                                 is this run's; teach_keep_loops teaches too, to keep the loops) */
    const char *const *teach_keys; /* nteach_keys "key=value": what the files do not say of the
                                 system teach's loops simulate, in `simulate mode=timeseries` keys
                                 (e.g. dm_coupling, ao_gain, ao_delay, r0; as `teach`'s key=value:
                                 they win over the files' description, a filter or slope_noise
                                 given is not taken from the slopes, the layers and the seed are
                                 teach's); part of the fingerprint */
    size_t nteach_keys;
    const char *const *mean_loops; /* folders of simulated closed loops of the same system
                                 (`simulate mode=timeseries`: slopes_NNN.fits and truth.fits'
                                 RESMEAN), nmean_loops of them (at least 2): the miss of the
                                 residual's time mean by this run's own reconstruction, each
                                 loop's true mean less the pipeline's reconstruction of its mean
                                 telemetry, checked held out as learn's MEANMISS and, where the
                                 others' mean predicts each loop's, added to RESMEAN (then it
                                 takes the place of a map's MEANMISS); docs/telemetry.md */
    size_t nmean_loops;
    int mean_teach;           /* the mean loops simulated by speckles itself, mean_teach_loops of them
                                 (4; 2..SWFS_MEAN_TEACH_MAX; more where the loops' map's learning
                                 curve asks, mean_teach_max_loops), of the system the observation's files
                                 describe (swfs_mean_teach_result below), in the teach folder
                                 (teach_work) as mean_NN, seeds teach_seed + k, and reused while
                                 their fingerprint is this run's (teach_again: anew).
                                 SWFS_MEAN_TEACH_AUTO (the default): for a pyramid's telemetry
                                 (WFSTYPE) through the linear model, without mean_loops, at camera
                                 exposures and alone (not in a team); where the files do not
                                 describe the loops, without them and saying why (fallback).
                                 1 (--mean-loop teach): with the linear model, whatever the sensor,
                                 failing where the files do not describe the loops; not with
                                 mean_loops. 0 (--mean-loop none): never */
    size_t mean_teach_loops;
    int loops_map;            /* with the linear model's --imat and mean loops (simulated or given:
                                 their truewf_NNN.fits and influence.fits needed), also the map
                                 learned from the loops, carried onto the basis, and the self-check's
                                 choice between the two sets of speckles (swfs_loops_map_result).
                                 SWFS_LOOPS_MAP_AUTO: where speckles simulated the mean loops
                                 (mean_teach) of a pyramid (by default for a pyramid's telemetry);
                                 1: with any mean loops; 0: never */
    const char *resmean_from; /* NULL, or a SPECKLES.fits of the same frames whose residual mean
                                 (RESMEAN) this run writes instead of its own reconstruction's
                                 (loops_map: the interaction matrix's, corrected by the loops'
                                 shared miss, where the loops' map's miss is not shared) */
    size_t mean_teach_max_loops; /* where the loops' map will be learned from the mean loops
                                 speckles simulates (loops_map with --imat): more loops than
                                 mean_teach_loops where that map's learning curve over the first
                                 ones asks for more frames (swfs_learn_run_result.curve_frames,
                                 teach's rule), up to this many (0: 4 mean_teach_loops, at most
                                 SWFS_MEAN_TEACH_MAX); mean_teach_loops..SWFS_MEAN_TEACH_MAX */
    const char *mean_rec_out; /* NULL, or a file this run writes (extension RESMEAN) with its own
                                 reconstruction of the residual's mean, no miss added nor
                                 resmean_from's (swfs_pipeline_mean_reconstruction): loops_map's
                                 misses, RESMEAN less it, for the maps stream and live take */
    int pairing_table;        /* 1: the timing table's pairing is kept whatever the speckles'
                                 orientation check finds (it warns); 0 (the default): a pairing
                                 that beats the table's by SWFS_ORIENT_WARN_SE standard errors is
                                 the one the products take (orient_adopted). Appended in 0.9.0 */
} swfs_speckles_run_options;

#define SWFS_LOOPS_MAP_AUTO (-1)

/* speckles' second map, learned from the mean loops (run_loops_map.c; docs/telemetry.md, "The
 * loops' own map, chosen by the self-check"): the loops' telemetry to their true residual on
 * their DM's functions (learn), carried onto the observation's basis (least squares over the
 * pupil of the loops' influence functions, loops[0]/influence.fits), applied to the
 * observation with its own miss of the residual's mean (each loop's by the map of the others,
 * where the loops share it: MEANMISS carried onto the basis); both speckle
 * sets, and those of the two maps mixed at quarters, estimated on the same science frames and
 * the one whose speckles explain most of them (swfs_halo_choose_files) written to the output
 * (and --write-recon's map with it). */
#define SWFS_LOOPS_MAP_NMIX 3

typedef struct swfs_loops_map_result {
    int tried;                /* both sets scored */
    int chosen;               /* 1: the loops' map's speckles or a mix of the two maps written
                                 (weight); 0: the interaction matrix's */
    double explained[2];      /* the self-check's score: the interaction matrix's, the loops' map's */
    size_t ncommon;           /* focal pixels scored */
    size_t nframes, inputs;   /* the loops' frames learned from, the map's inputs (telemetry values
                                 with signal): tried only where nframes >= inputs /
                                 SWFS_LEARN_CURVE_EXCESS (teach's floor) */
    double misfit_rms, truth_rms; /* [m] learn's training misfit and truth per output */
    double carry_resid;       /* the loops' DM functions on the basis: rms residual / rms (LOOPFIT) */
    double meanmiss_heldout;  /* the loops' map's miss of the mean, each loop's by the map of the
                                 others (learn's mean_miss_heldout), checked held out (< 1: added)
                                 on the wavefront the misses make in the pupil, piston, tip and
                                 tilt out (learn's meanmiss_metric from the loops' DM functions) */
    double meanmiss_rms;      /* [m] that miss as added to RESMEAN, its rms in the pupil (piston,
                                 tip, tilt removed; 0: none added) */
    int mean_from_imat;       /* 1: the loops' map's miss is not shared (held out >= 1) while the
                                 interaction matrix's is: its speckles carry the interaction
                                 matrix's corrected mean (resmean_from) */
    double seconds;
    char work[4200];          /* its files: loops_learned.fits, loops_map.fits, halo_imat.fits,
                                 halo_loops.fits */
    char map[4400];           /* the loops' map on the basis (a --control matrix) */
    char fallback[1024];      /* why it was not tried ("" otherwise): the --imat speckles stay */
    /* the two maps mixed, C_w = w C_imat + (1 - w) C_loops (their speckles' mean RESMEAN mixed
     * alike), scored with the two: w on the grid of quarters between them */
    double mix_weight[SWFS_LOOPS_MAP_NMIX];    /* w of each mix: 0.75, 0.5, 0.25 */
    double explained_mix[SWFS_LOOPS_MAP_NMIX]; /* their self-check scores (NAN: not scored) */
    double weight;            /* w of the written speckles' map: 1 the interaction matrix's, 0 the
                                 loops' map's, else their mix (mix_NN.fits, NN = 100 w) */
    char mix_note[1024];      /* why the maps were not mixed ("" otherwise): the two ends scored */
    /* the loops' map is a space-time one (docs/telemetry.md, "A space-time loops' map"): frame
     * t's residual from the telemetry of frames t + lags[k], teach's rule (swfs_loops_map_lags_) */
    size_t nlags;             /* 0: per frame */
    long lags[SWFS_RECON_MAXLAGS];
    double lag_speed;         /* [subapertures per WFS frame] the fastest layer `wind` tracked in the
                                 first loop's telemetry (0: none, or not a Shack-Hartmann layout) */
    size_t st_frames;         /* the frames the space-time map needed (SWFS_LEARN_CURVE_EXCESS of its
                                 inputs) where the loops held fewer: the per-frame map instead (0 else) */
    double pf_meanmiss_heldout; /* a space-time map whose miss of the mean the loops do not share:
                                 the per-frame map of the same loops', held out alike (NaN: not
                                 learned); below 1 its mean goes with the space-time speckles */
    int mean_from_perframe;   /* 1: that per-frame map's mean (its reconstruction of the telemetry's
                                 mean plus its shared miss) is the written speckles' RESMEAN */
} swfs_loops_map_result;

#define SWFS_MEAN_TEACH_MAX 16

/* The miss of the AO residual's time mean by p's own reconstruction, from simulated closed
 * loops of the same system (`speckles`/`stream`/`live --mean-loop DIR...`: folders of
 * `simulate mode=timeseries`, slopes_NNN.fits of the observation's telemetry kind and
 * truth.fits' RESMEAN; at least 2, e.g. the mean_NN that `speckles --mean-loop teach` left in
 * its teach folder): each loop's true mean less p's reconstruction of its mean telemetry,
 * checked held out as learn's MEANMISS (each against the others' mean) and, where the others'
 * mean predicts each loop's (*heldout < 1), their mean set as p's mean offset
 * (swfs_pipeline_set_mean_offset; *rms its rms in the pupil, piston, tip and tilt removed),
 * else none (*rms 0). heldout, rms may be NULL. docs/telemetry.md. */
int swfs_pipeline_mean_loops(swfs_pipeline *p, const char *const *loops, size_t nloops, double *heldout, double *rms);
#define SWFS_MEAN_TEACH_AUTO (-1)

/* What `speckles --mean-loop teach` read from the observation's files for the loops it
 * simulates (docs/telemetry.md, "The mean's miss from loops speckles simulates"); each item
 * the user gives (teach_keys) is taken as given and marked 0 / NAN here. */
typedef struct swfs_mean_teach_result {
    int done, reused;         /* the loops made (or reused: their fingerprint is this run's) */
    int automatic;            /* SWFS_MEAN_TEACH_AUTO chose them (a pyramid's telemetry) */
    char fallback[1024];      /* SWFS_MEAN_TEACH_AUTO on a pyramid's telemetry: why there are no
                                 loops (the files do not describe them, a team), "" otherwise */
    size_t nloops, loop_frames; /* nloops: all of them (nloops_first, then those the curve asked for) */
    int pyramid;              /* the loops sense with a pyramid (WFSTYPE, or wfs= given) */
    double noise_rms;         /* the telemetry's white noise per value (its curl, wfs.h) */
    double photons;           /* pyramid: photons per subaperture and frame, 1 / noise_rms^2; NAN: given */
    double slope_noise;       /* Shack-Hartmann: [rad] the loops' slope noise; NAN: given */
    size_t knee;              /* the loops' modal filter (ao_modes): the knee of the telemetry's
                                 variances along the DM's modes through the sensor's own
                                 interaction matrix; 0: a filter given */
    size_t nlayers;           /* the layers `wind` tracked in the telemetry (0: given) */
    double speed[SWFS_WIND_MAXLAYERS], direction[SWFS_WIND_MAXLAYERS]; /* [m/s], [deg] */
    double act_pitch;         /* [m] the DM's pitch from the basis (its registration's pitch on a
                                 DM grid; the median spacing of its functions' centroids on the
                                 pupil grid); 0: given */
    double r0;                /* [m] the loops' r0: fitted so that the first two loops' signals
                                 carry the telemetry's residual power (r0_pairs > 0), or given /
                                 the simulator's default (r0_pairs 0) */
    size_t r0_pairs;          /* pairs of loops simulated for the fit (the last pair kept as loops
                                 0 and 1); 0: r0 given (--teach-set r0=) */
    double power, power_ratio; /* the telemetry's residual power per value (each value's variance,
                                 tip-tilt and white noise removed: swfs_slopes_white_noise), and
                                 the kept pair's over it */
    size_t nloops_first;      /* the loops simulated first (mean_teach_loops); nloops more where
                                 the loops' map's learning curve over them asked for more frames */
    double curve_excess;      /* that curve over the first loops (swfs_learn_run_result): the map of
                                 their frames above unlimited frames' misfit^2, a fraction; NaN:
                                 not measured (no loops' map to follow, or fewer than 4 loops) */
    size_t curve_frames;      /* the frames it asked for (SWFS_LEARN_CURVE_EXCESS), times the space-time
                                 loops' map's lags (its inputs that many times the per-frame map's);
                                 0: none */
    double seconds;
    char work[4200];          /* the folder holding mean_NN and mean_loops.conf (their description) */
} swfs_mean_teach_result;

void swfs_speckles_run_options_default(swfs_speckles_run_options *o);

typedef struct swfs_speckles_run_result {
    size_t nout;              /* frames written (camera frames, or WFS frames with wfs_rate) */
    size_t ncubes, nok;       /* cubes in the table, usable cubes */
    double ratio, lag, wfs_hz;
    swfs_pipeline_info info;
    double resmean_rms;       /* [m] the reconstructed residual's time mean over the frames written
                                 (SPECKLES.fits RESMEAN, swfs_pipeline_mean_wavefront), rms in the pupil */
    double wavelen;           /* [m] the science cube's wavelength (swfs_speckles_resmean_warns) */
    int taught;               /* SWFS_RECON_TEACH: 1 when the map was taught (teach_map); 0 when teach
                                 could not, and teach_fallback says why (SWFS_RECON_VK was used) */
    char teach_map[4200];
    char teach_fallback[1024];
    /* A space-time reconstructor (info.nlags > 0) whose file holds its training loops' winds
     * (learn --lags: the layers LRNNLAY, LRNLkX, LRNLkY; a file without them: the mean wind
     * LRNVX, LRNVY as one layer) against the layers of the first telemetry file's slopes
     * (wind.h), in subapertures per WFS frame (st_found: both known). Each observed layer is
     * matched to the nearest training layer; st_mismatch = the largest such distance x the
     * largest |lag| [subapertures]: how far apart the pattern the map was taught and the
     * observed one have moved by the farthest frame it reads (NaN when unknown), and
     * st_obs_v*, st_train_v* that pair. st_obs_nlayers, st_train_nlayers: the layers each
     * side has. docs/telemetry.md measures what a mismatch costs. */
    int st_found;
    double st_train_vx, st_train_vy, st_obs_vx, st_obs_vy, st_mismatch;
    size_t st_obs_nlayers, st_train_nlayers;
    /* And the slopes' temporal correlation at the map's lags (wfs.h
     * swfs_slopes_lag_correlation): the training loops' (LRNCORk) with their spread over the
     * loops (LRNCSPk), the first telemetry file's, and the lag where the two differ most
     * beyond three times that spread (st_corr_worst, a LAGk index; st_corr_excess =
     * |obs - train| - 3 spread there, > 0: a layer or a speed the loops lack). NaN /
     * SIZE_MAX when the file holds none. */
    double st_corr_train[SWFS_RECON_MAXLAGS], st_corr_spread[SWFS_RECON_MAXLAGS], st_corr_obs[SWFS_RECON_MAXLAGS];
    double st_corr_excess;
    size_t st_corr_worst;
    long st_lags[SWFS_RECON_MAXLAGS]; /* the map's lags (info.nlags of them) */
    /* Its lags run on into the neighbour telemetry files: the file boundaries (of the files
     * this process read) across which the telemetry showed the files contiguous and the
     * stacking went on, and those it clamped at (a neighbour the check calls not contiguous
     * or cannot tell); a file without a neighbour counts in neither. Neighbours that could not
     * be read (another width, a non-finite slope, a truncated file) leave that side clamped
     * too: st_edges_unreadable of them, the last one's reason in st_edges_why. */
    size_t st_edges_joined, st_edges_clamped, st_edges_unreadable;
    char st_edges_why[512];
    int teach_reused;         /* taught = 1 by reusing teach_map, taught earlier for the same inputs
                                 (teach_again 0): the teach result then holds only chosen and
                                 nloops, from its TEACHSEL and TEACHLOO */
    char teach_fingerprint[17]; /* SWFS_RECON_TEACH: the inputs' fingerprint (TEACHFPR), hex */
    double curl_noise;        /* [rad] vk / MAP on slopes modal-slopes made (MODALCM): the effective
                                 slope noise taken from their curl (swfs_slopes_curl_noise, total)
                                 and used, since the projection leaves no slope outside the modes
                                 to estimate it from; 0 otherwise (also when slope_noise was given) */
    int modal_regularized;    /* the telemetry came through modal-slopes --imat from coefficients its
                                 check found regularized (MODALRGW = 1): RM c is not the slopes'
                                 projection, and neither teach's map nor vk fits them */
    double modal_lsq;         /* that check's ratio (MODALLSQ), NAN where the files carry none */
    double meanmiss_heldout;  /* mean_loops: the held-out check's ratio (< 1: added); NAN otherwise */
    swfs_mean_teach_result mean_teach; /* mean_teach: the loops' description from the files */
    double meanmiss_rms;      /* [m] the map's miss of the residual's time mean (learn's MEANMISS:
                                 a --recon or --control map learned from loops whose misses agree),
                                 added to RESMEAN, its rms in the pupil (piston, tip, tilt removed);
                                 0: the map carries none */
    swfs_loops_map_result loops_map; /* loops_map: the second map and the choice */
    /* The camera's orientation told by the speckles (sync.h swfs_orient_acc_result): the
     * science frames of the usable cubes against the speckles' |psi|^2, in all 8 pairings;
     * orient_done 0 where it did not run (too few frames; a run of several processes before
     * 0.11.0, now member 0's check on the gathered cube). A
     * pairing better than the timing table's by SWFS_ORIENT_WARN_SE standard errors makes
     * swfs_speckles_orient_warns true: the table's pairing is likely wrong. Appended in 0.8.0.
     * The check runs before the products are written; unless pairing_table, such a pairing is
     * the one they take: the speckle cube's CAMORIEN, the --match copies turned by it, the
     * --tiptilt frame shifts (orient_adopted 1; the timing table itself is not changed: replay
     * and stream take its pairing line). Appended in 0.9.0. */
    int orient_done;
    swfs_orient_check_result orient;
    int orient_adopted;
    /* The DM's influence functions of teach's loops, chosen by the science frames (0.11.0).
     * The files do not say what a DM's functions are; where teach is told neither them
     * (dm_coupling) nor the control matrix it would take them from (ao_recon), speckles teaches
     * a second map, its loops' DM Gaussian functions of coupling SWFS_TEACH_DM_GAUSS, computes
     * the speckles of both, and keeps the Gaussian's where its |psi|^2 follows the science
     * frames better by more than SWFS_TEACH_DM_SE standard errors (else the interpolated
     * surface's): per pixel the correlation of intensity and |psi|^2 over the frames (the
     * orientation check's, at the pairing it found), the mean per-pixel difference and its
     * standard error (the pixels counted in speckles). Camera frames and a taught map only
     * (dm_choice_done 0 otherwise, or where the orientation check could not run); a team's
     * member 0 teaches the second map and decides, every member computes both (the others'
     * dm_* fields but dm_gauss_chosen are not filled). */
    int dm_choice_done;
    int dm_gauss_chosen;       /* 1: the Gaussian functions' map (teach_map, teach's result are its) */
    double dm_gauss_coupling;  /* the coupling of the second map's functions (SWFS_TEACH_DM_GAUSS) */
    double dm_corr[2];         /* mean correlation: [0] the interpolated surface's speckles, [1] the Gaussian's */
    double dm_corr_diff, dm_corr_se; /* mean per-pixel [1] - [0] and its standard error */
    size_t dm_npix;            /* the pixels both have a correlation at */
    char dm_other_map[4200];   /* the map not kept */
    char dm_fallback[1024];    /* the second map could not be taught or compared: why (the first kept) */
} swfs_speckles_run_result;

/* The coupling of the Gaussian influence functions (timeseries.h dm_coupling: a neighbour's
 * share of an actuator's command) speckles' second map is taught with: the middle, on a log
 * scale, of continuous-facesheet DMs' 0.05-0.4; docs/telemetry.md ("The DM's functions chosen
 * by the science frames") measures the maps of 0.08-0.3 on observations of 0.15-0.2 and of
 * the interpolated surface. SWFS_TEACH_DM_DIR: its teach folder, inside the first's. */
#define SWFS_TEACH_DM_GAUSS 0.15
#define SWFS_TEACH_DM_DIR "dm-gauss"
/* How many standard errors the Gaussian functions' map must beat the interpolated surface's by
 * to be kept: the surface stays unless the frames tell otherwise, at the significance teach
 * asks of a learning curve's fall (SWFS_LEARN_CURVE_FALL_SE). docs/telemetry.md: the Gaussian
 * maps kept on the observations measured were 2.2-40 standard errors ahead; on a 24 x 24 of
 * the surface the two were level (0.0), and the Gaussian's, kept, cost 0.9 nm. */
#define SWFS_TEACH_DM_SE 2.0

/* How many standard errors a pairing must beat the timing table's by for the speckles'
 * orientation check to warn and (by default) to be taken instead of the table's: the
 * significance sync asks of its own fits' parts. */
#define SWFS_ORIENT_WARN_SE 5.0
int swfs_speckles_orient_warns(const swfs_speckles_run_result *r);
/* The warning's words where swfs_speckles_orient_warns (what the products took, the numbers for
 * the table's pairing line); "" otherwise. Added in 0.9.0. */
void swfs_speckles_orient_warning(const swfs_speckles_run_result *r, char *buf, size_t cap);

/* The space-time map's wind mismatch (swfs_speckles_run_result.st_mismatch) beyond which
 * `speckles` warns: a quarter subaperture at the largest lag (docs/telemetry.md: on the
 * slowest system measured the map beat the per-frame one up to about 0.15 and lost to the
 * default at 0.5). */
#define SWFS_SPACETIME_MISMATCH_WARN 0.25

/* Which of the two checks warn on r (0: neither, or no space-time map): the winds beyond
 * SWFS_SPACETIME_MISMATCH_WARN at the largest lag, the slopes' correlation beyond three of
 * the training loops' spreads at a lag (st_corr_excess > 0). */
#define SWFS_SPACETIME_WARN_WIND 1
#define SWFS_SPACETIME_WARN_CORR 2
int swfs_spacetime_warns(const swfs_speckles_run_result *r);

/* 1 when r's reconstructed residual mean is beyond one wave (resmean_rms > wavelen). A
 * closed loop holds its measured residual's mean near its reference, so that is no loop's,
 * but a reconstructor that amplifies slope patterns D does not make, which its gain on D
 * does not show (docs/telemetry.md); the command and Python warn. */
int swfs_speckles_resmean_warns(const swfs_speckles_run_result *r);

/* Whether o's options fit together and lie in range (SWFS_ERR_ARG and the message
 * otherwise), before any file is opened; swfs_speckles_run calls it first. The messages name
 * the options as the command line spells them (Python's keywords are those names with '_'):
 * --teach-loops 2..64, --batch up to 100000 (0: 128), --threads 1..SWFS_ENGINE_MAX_THREADS,
 * --rcond/--modes (a value other than the default's) only with SWFS_RECON_SVD, --slope-noise
 * only with vk or map, --recon-scale only with a given map, the teach options only with
 * SWFS_RECON_TEACH and no basis, --wfs-hz and no --match only with wfs_rate, the basis
 * without actuators, a given map, write_recon or valid. */
int swfs_speckles_run_options_check(const swfs_speckles_run_options *o);

int swfs_speckles_run(const swfs_speckles_run_options *o, swfs_speckles_run_result *r);

/* ---- stream: the whole real-time path from files ---------------------------------- */

typedef struct swfs_stream_run_options {
    const char *timing, *science, *slopes, *recon, *actuators, *out;
    const char *pupil_out;    /* also the pupil field at every update (NULL: no) */
    int pupil_method;         /* its method: SWFS_PUPIL_AUTO (0, the joint fit when possible),
                                 SWFS_PUPIL_FIT or SWFS_PUPIL_MOMENTS (pupil.h) */
    const char *checkpoint;   /* the accumulators at every update (NULL: no) */
    const char *static_file;  /* SWFS_STATIC_GIVEN: a complex image */
    const char *static_out;   /* write the static halo in use (NULL: no) */
    const char *mask;         /* pupil mask (its PUPIL extension if it has one), NULL = annulus */
    int tiptilt, threads;
    size_t batch;             /* camera frames per batch (128) */
    double read_noise, gain;  /* NaN: from the science header */
    double g_smooth_lod;      /* (2) */
    swfs_stream_options stream; /* static_mode, every, every_seconds, max_frames (noise, est set here) */
    const char *const *prov;
    size_t nprov;
    /* Called after every product update (final = 1 at the end); may be NULL. */
    void (*on_update)(void *ctx, const swfs_stream *s, const swfs_halo *h, const swfs_pupil_result *pupil, int final);
    void *update_ctx;
    /* NULL: alone. A team (team.h) splits the camera frames at batch boundaries, so every
     * member's batches are the single-process run's; the automatic static halo is member
     * 0's first batch, sent to the others; the products are written once, at the end
     * (stream.every and every_seconds must be 0), by member 0, which alone calls on_update. */
    const swfs_team *team;
    int pupil_source;         /* the pupil product's source: SWFS_SOURCE_HALO_LF (default) or SWFS_SOURCE_HALO (pupil.h) */
    swfs_geom geom;           /* given geometry: fills or replaces the science header's */
    swfs_linear_files lin;    /* lin.basis: the generic linear model instead of recon + actuators
                                 (an interaction matrix learns from the first telemetry file) */
    /* Time-stamped input instead of the timing table (milksource.h): nwfs_logs WFS milk logs
     * (each a folder or one file; their values concatenated in this order), the science cube's
     * STAMPS, the clock file of `sync --wfs-log` (NULL: the camera on the WFS clock, oriented
     * as the model) and the exposure time [s] (0: STAMPS' EXPTIME, else the frame period). */
    const char *const *wfs_logs;
    size_t nwfs_logs;
    const char *clock;
    double exptime;
    const char *valid;        /* the Shack-Hartmann model's valid-subaperture map (swfs_valid_map_read),
                                 NULL = the illumination rule; the telemetry may then hold only the
                                 used subapertures' slopes (pipeline.h) */
    double band;              /* the speckles' focal radius [lambda/D] (pipeline.h options.band; 0: the
                                 Shack-Hartmann's nsub/2, none for a linear model; < 0: none) */
    const char *const *mean_loops; /* folders of simulated loops of the same system, nmean_loops of
                                 them (0, or at least 2): their miss of the residual's time mean
                                 by this run's reconstruction, added to RESMEAN where they share it
                                 (swfs_pipeline_mean_loops; as speckles' mean_loops) */
    size_t nmean_loops;
    int mean_teach;           /* as speckles' mean_teach, for a run from files with a timing table
                                 (--timing): SWFS_MEAN_TEACH_AUTO (default) simulates, for a
                                 pyramid's telemetry through the linear model and without
                                 mean_loops, mean_teach_loops loops of the system the files describe
                                 in teach_work (NULL: OUT.teach), reused while their description is
                                 the same (teach_again: anew), and takes their miss; 1: whatever
                                 the sensor; 0: never. A live or milk-log run never simulates them */
    size_t mean_teach_loops;  /* 4; 2..SWFS_MEAN_TEACH_MAX */
    const char *teach_work;
    int teach_again;
    size_t mean_teach_max_loops; /* speckles' (0: its default): the same loops as speckles makes
                                 for the same files, more where the loops' map's curve asks */
    /* Progress after every batch, stage "camera frames": the frames taken so far of the run's
     * (the timing table's usable frames up to max_frames; 0 for time-stamped input, whose
     * count is known only at its end); before them the stages of the mean loops the run
     * simulates (mean_teach), as speckles reports them. A request to stop ends the run with SWFS_ERR_STOPPED
     * and removes the updates it had put in place (status.h). Not called in a team, nor for a
     * live source (live's own stop flag ends those). */
    swfs_progress_fn progress;
    void *progress_ctx;
} swfs_stream_run_options;

void swfs_stream_run_options_default(swfs_stream_run_options *o);

typedef struct swfs_stream_run_result {
    size_t camera_frames;
    double wfs_frames, seconds, wfs_rate; /* wfs_rate: WFSRATE of the telemetry [Hz], 0 if unknown */
    double static_scale;      /* S^1/2 of the automatic static halo (NaN otherwise) */
    double ratio;             /* WFS frames per camera frame (the timing table's) */
    swfs_noise noise;
    swfs_pipeline_info info;
    int stamped;              /* 1: a run over milk logs; stamps holds its counts */
    swfs_milk_source_stats stamps;
    /* a space-time reconstructor (info.nlags > 1): its lags, and the telemetry file
     * boundaries its lags ran on across (joined), were clamped at, or whose neighbour could
     * not be read (the last reason in st_edges_why); a team member counts its own share's */
    long st_lags[SWFS_RECON_MAXLAGS];
    size_t st_edges_joined, st_edges_clamped, st_edges_unreadable;
    char st_edges_why[512];
    double meanmiss_rms;      /* [m] a learned map's MEANMISS, or the mean loops' shared miss, added
                                 to RESMEAN (as speckles'); 0: none */
    double meanmiss_heldout;  /* mean_loops: the held-out check's ratio (< 1: added); NAN otherwise */
    swfs_mean_teach_result mean_teach; /* mean_teach: the loops' description from the files */
} swfs_stream_run_result;

/* The same for a stream run from files (swfs_stream_run_files calls it first): the timing
 * table or milk logs (one of them), the science cube, recon and actuators or a basis, out;
 * --clock and --exptime only with milk logs; --batch 1..100000, --threads
 * 1..SWFS_ENGINE_MAX_THREADS, read_noise and gain NaN or >= 0, g_smooth_lod and every_seconds
 * >= 0, the pupil method and source, static_file with SWFS_STATIC_GIVEN. */
int swfs_stream_run_options_check(const swfs_stream_run_options *o);

int swfs_stream_run_files(const swfs_stream_run_options *o, swfs_stream_run_result *r);

/* ---- reduce: raw camera cubes -> the reduced science cube (science.h) -----------
 * Raw cubes that are milk log files (a timestamp table X.txt beside X.fits or X.fits.fz,
 * milklog.h) carry their frames' counters and stamps into the STAMPS extension: all of the
 * raw cubes or none, each table's rows equal to its cube's frames, stamps in the order the
 * cubes are given. */

typedef struct swfs_reduce_run_options {
    const char *const *raw;   /* nraw raw camera cubes, concatenated in this order */
    size_t nraw;
    const char *dark, *flat, *badpix, *out; /* calibration frames (NULL: 0, 1, none) */
    swfs_reduce_params params; /* reduce.h; pixscale and gain are filled from the raw header */
    int sigma_given;          /* 1: keep params.gauss_sigma; 0: 1 lambda/D when PIXSCALE is known */
    int noise_region;         /* 1: noise from the source-free region even when PIXSCALE is known */
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
    swfs_geom geom;           /* given geometry: its keywords fill or replace the raw header's and
                                 go into the reduced cube (swfs_geom_init: none given) */
} swfs_reduce_run_options;

void swfs_reduce_run_options_default(swfs_reduce_run_options *o);

typedef struct swfs_reduce_run_result {
    size_t nframes, nbad;
    double noise_var, noise_fac; /* raw background variance [counts^2] and the registration's factor */
    double noise_var_measured; /* the estimate itself: it may come out below 0 when the frames have
                                 no read noise to measure (the photon part's subtraction and the
                                 estimate's scatter); noise_var and the keywords are then 0 */
    char missing[96];         /* geometry keywords the reduced cube still lacks ("" if none): the
                                 first raw cube's header and the given geometry had no value */
    int overridden;           /* keywords of the raw header the given geometry replaced */
    int stamped;              /* 1: every raw cube had a milk timestamp table (X.txt beside X.fits):
                                 the STAMPS extension was written (science.h) */
    uint64_t dropped;         /* camera counter jumps > 1 over the raw cubes (stamped only) */
    double exptime;           /* [s] the least EXPTIME of the raw cubes' headers (0: a cube has none),
                                 written with the resolution its header shows (EXPTIME, EXPTRES) */
} swfs_reduce_run_result;

int swfs_reduce_run(const swfs_reduce_run_options *o, swfs_reduce_run_result *r);

/* ---- sync: reduced science + handshake log -> the timing table -------------------- */

typedef struct swfs_sync_run_options {
    const char *science, *handshake, *out;
    swfs_sync_params params;  /* search ranges (sync.h); lag -3..12 WFS frames by default; ratio from
                                 ratio_min = 0: the camera's EXPTIME x the telemetry's WFSRATE (an
                                 exposure lasts at most its frame period), less EXPTIME's resolution and
                                 SWFS_SYNC_EXPTIME_STEPS coarse steps, where the science cube (reduce
                                 copies the raw headers' EXPTIME) and the telemetry have both; else
                                 SWFS_ENGINE_MIN_RATIO (0.1: a camera up to ten times faster than the
                                 WFS) -- to ratio_max = 0: the handshake log's bound
                                 (a cube ends before the next one of its file starts),
                                 SWFS_SYNC_RATIO_MAX_FALLBACK when no two cubes start in one file. The fit
                                 is refused (SWFS_ERR_VALUE, nothing written) when its correlations
                                 are not significant over the search (sync.h z, z_need) */
    swfs_linear_files lin;    /* lin.basis: the telemetry is the linear model's (modal coefficients, any
                                 WFS signal with a control matrix): its tip-tilt is the Z-tilt of the
                                 model's wavefront (geometry from the science cube), not mean slopes */
} swfs_sync_run_options;

void swfs_sync_run_options_default(swfs_sync_run_options *o);

/* r->t: the timing table written (the caller frees r->t.cubes, also on failure). A cube's
 * exposures that lie wholly in its telemetry file make one row; a cube that crosses into the
 * files before or after it (numbered, time-stamped or in the handshake log's order) makes a row
 * of each such file, file by file outwards, while the data show the files contiguous there
 * (swfs_sync_continuation_check on the camera's lag, swfs_sync_boundary_check on the telemetry
 * across the boundary), or where frames were lost or repeated between them by a count the
 * camera's lag and the telemetry both show (swfs_sync_boundary_gap; the row's join_lost);
 * the rest are rows marked straddles. When any file continues
 * another, the fit is made again over the cubes joined across those files, and the
 * continuations are checked again at it (r->refits). A cube whose telemetry file cannot be
 * read (missing, truncated, NaN values, another shape) is left out of the fit and makes one
 * row marked missing (r->nmissing, the first file's message in r->missing_reason); when no
 * cube's file can be read, SWFS_ERR_IO with that message. SWFS_ERR_VALUE (after writing the
 * table) when no exposure is usable. */
typedef struct swfs_sync_run_result {
    swfs_timing t;
    size_t nok;               /* usable rows */
    size_t nexp, nexp_ok;     /* exposures in all, usable */
    size_t ncontinued;        /* cube parts found to continue in an adjacent telemetry file */
    double ratio_min, ratio_max; /* the ratios searched */
    double ratio_bound;       /* the handshake log's upper bound on the ratio (0: none: no two cubes
                                 start in one telemetry file) */
    int ratio_auto;           /* 1: ratio_max came from that bound (params.ratio_max <= 0, the default) */
    int refits;               /* times the fit was made again over cubes joined across contiguous files
                                 (0: the table is the fit over each cube's own file) */
    double ratio_first, lag_first; /* that first fit's ratio and lag */
    size_t nmissing, nexp_missing; /* cubes (exposures) left out: their telemetry file cannot be read */
    char missing_reason[1024]; /* the first such file's message */
    double exptime_ratio;     /* EXPTIME x WFSRATE, EXPTIME less its resolution (0: the science cube or
                                 the telemetry has none) */
    int exptime_used;         /* 1: the search started SWFS_SYNC_EXPTIME_STEPS coarse steps below it */
    int exptime_widened;      /* 1: the best ratio lay at that start (a header whose exposure is longer
                                 than the frames' period): the search was made again from
                                 SWFS_ENGINE_MIN_RATIO, and ratio_min is that */
} swfs_sync_run_result;

int swfs_sync_run(const swfs_sync_run_options *o, swfs_sync_run_result *r);

/* ---- dmoffsets: the pupil product's NCP -> deformable-mirror offsets (dmfit.h) ------------- */

typedef struct swfs_dmoffsets_run_options {
    const char *pupil;        /* a pupil product (`pupil`'s output: WFE [m], PUPIL, the geometry) */
    const char *actuators;    /* the actuators' positions (2 x nact [m], pupil frame), or NULL with: */
    double hexapolar;         /* [m] > 0: a hexapolar layout of rings this far apart covering the pupil */
    const char *out;          /* OFFSETS.fits (swfs_dmfit_write's layout) */
    swfs_dmfit_options fit;   /* influence, coupling, pitch, modes, reg (swfs_dmfit_options_default) */
    const char *const *prov;
    size_t nprov;
} swfs_dmoffsets_run_options;

void swfs_dmoffsets_run_options_default(swfs_dmoffsets_run_options *o);

typedef struct swfs_dmoffsets_run_result {
    size_t nact, active;      /* actuators, those whose influence reaches the pupil */
    double pitch;             /* [m] the pitch the fit used */
    swfs_dmfit_stats stats;   /* the correction -WFE/2 of surface and what the fit did with it [m] */
} swfs_dmoffsets_run_result;

/* The correction surface -WFE/2 (a reflective DM changes the wavefront by twice its surface)
 * fitted by least squares over the pupil onto the actuators' influence functions, written to
 * out. Refused, naming the file: a product without WFE or its geometry, a WFE not finite or
 * beyond 10 wavelengths inside the pupil, actuators that do not cover the pupil. */
int swfs_dmoffsets_run(const swfs_dmoffsets_run_options *o, swfs_dmoffsets_run_result *r);

/* ---- sync --wfs-log: time-stamped frames -> the clock file (clocksync.h) ------------- */

typedef struct swfs_clock_run_options {
    const char *science;      /* reduced science cube with TRACK and STAMPS (reduce of milk camera logs) */
    const char *const *wfs;   /* one WFS log (milklog.h: a folder, or its files): Shack-Hartmann slopes,
                                 x then y, whose mean gives the tip-tilt */
    size_t nwfs;
    const char *out;          /* the clock file */
    double exptime;           /* [s] camera exposure time; 0: STAMPS' EXPTIME, else the frame period */
    swfs_linear_files lin;    /* lin.basis: the log is the linear model's (as swfs_sync_run_options.lin) */
    swfs_clock_params params;
    const char *const *prov;
    size_t nprov;
} swfs_clock_run_options;

void swfs_clock_run_options_default(swfs_clock_run_options *o);

typedef struct swfs_clock_run_result {
    swfs_clock clock;
    uint64_t wfs_dropped, cam_dropped; /* counter jumps of the WFS log and of STAMPS */
    size_t wfs_frames, wfs_files;
} swfs_clock_run_result;

int swfs_clock_run(const swfs_clock_run_options *o, swfs_clock_run_result *r);

/* ---- pupil A.fits B.fits ...: the self-check as a choice among halo files ---------------- */

/* The HALO.fits files read and scored by swfs_halo_choose (pupil.h): explained[n], the index
 * of the best in *best, the focal pixels scored in *ncommon; when chosen is given, the best
 * halo (the caller frees it) and, when geom is given, its file's geometry. Messages name the
 * files. */
int swfs_halo_choose_files(const char *const *paths, size_t n, double *explained, size_t *best, size_t *ncommon,
                           swfs_halo **chosen, swfs_geom *geom);

/* ---- pupil: HALO.fits -> PUPIL.fits ------------------------------------------------- */

typedef struct swfs_pupil_run_options {
    const char *const *halos; /* HALO.fits; with more than one (halos of the same frames from
                                 different speckles) the self-check chooses the halo used */
    size_t nhalo;
    const char *out;          /* PUPIL.fits (swfs_pupil_write) */
    const char *mask;         /* pupil mask file (swfs_pupil_mask_read); NULL: the annulus of the
                                 halo's geometry */
    const char *truth;        /* a simulation's truth file: its NCP compared with the WFE (NULL: none) */
    swfs_pupil_options pupil; /* swfs_pupil_options_default */
    const char *const *prov;
    size_t nprov;
} swfs_pupil_run_options;

void swfs_pupil_run_options_default(swfs_pupil_run_options *o);

typedef struct swfs_pupil_run_result {
    swfs_pupil_result *pupil; /* the estimate written */
    swfs_halo *halo;          /* the halo it was made from */
    swfs_geom geom;           /* that halo's geometry */
    size_t chosen;            /* its index in halos */
    double *explained;        /* with nhalo > 1: each halo's self-check score (nhalo); else NULL */
    size_t ncommon;           /* with nhalo > 1: the focal pixels scored */
    double err, truth_rms, truth_rms_ptt; /* with truth: swfs_wfe_compare's three [m]; else NaN */
    int ran_away;             /* 1: the WFE exceeds half the wavelength (a phase above pi rad rms,
                                 which no image with a core comes from): the fit ran away from
                                 its start, and the map is no estimate */
    double err_kept;          /* with truth: the error with the AO residual's time mean left in
                                 WFE [m], what `--keep-resmean` gives from the same fit (WFE +
                                 the RESMEAN taken out, piston, tip and tilt removed; err where
                                 none was taken out); else NaN */
} swfs_pupil_run_result;

/* The pupil step as `specklewfs pupil` runs it: the halo read (or chosen), its geometry
 * required, the mask read, the estimate, the truth compared, PUPIL.fits written (its
 * provenance: prov, what was chosen, the truth's comparison). Nothing is written on failure. */
int swfs_pupil_run(const swfs_pupil_run_options *o, swfs_pupil_run_result *r);
void swfs_pupil_run_result_free(swfs_pupil_run_result *r);

/* ---- learn: a reconstructor from simulated closed loops (wfs.h swfs_recon_learner) ------ */

typedef struct swfs_learn_run_options {
    const char *const *dirs;  /* folders of `simulate mode=timeseries export_truth=1` (or any
                                 simulation writing the same files): slopes_NNN.fits with
                                 truewf_NNN.fits, NNN from 000, the same geometry in all */
    size_t ndirs;
    double ridge;             /* SWFS_RECON_LEARN_RIDGE */
    const char *out;          /* the reconstructor file (swfs_recon_write's layout; speckles --recon) */
    int modal;                /* 1: truewf_NNN.fits hold coefficients on a basis without piston
                                 (any AO system's modes): learned as they are, for speckles
                                 --basis B --control W; 0: actuator values, piston removed */
    int no_heldout;           /* 1: skip the held-out check (it reads every file twice) */
    double *heldout_ratio;    /* optional, ndirs long (the caller's): each data set's held-out
                                 rms misfit / rms truth, NaN where it was not checked */
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
    const long *lags;         /* NULL, or nlags lags [WFS frames] (one of them 0): a space-time
                                 map from the slopes of frames t + lags[k] of each file, clamped
                                 at its ends (swfs_slopes_stack), written as a cube (wfs.h
                                 swfs_recon_write); not with modal */
    size_t nlags;
    const char *perframe_out; /* with lags, or NULL: also the per-frame map of the same frames
                                 (the lag-0 block of the same sums solved alone,
                                 swfs_recon_learner_solve_lag) into this file, for runs that
                                 take one frame's slopes (live); both files or neither */
    int curve;                /* 1 (with at least 4 data sets): the learning curve (below) */
    double curve_radius[2];   /* [m] the curve and the held-out check over the outputs at radii
                                 from curve_radius[0] to [1] only: the pupil's annulus, the points
                                 whose wavefront makes the speckles (the truth beyond it is the
                                 fit's extrapolation); the outputs' positions: the truth's own
                                 points (OUTXY), else the first folder's actuators.fits (one per
                                 output; not with modal); {0, 0}: all outputs */
    const double *project;    /* NULL, or nproject x nproject (symmetric): each file's slopes s
                                 (rows) taken as s P, the projection the telemetry the map is for
                                 went through (teach on modal-slopes' output: P = CM+ CM) */
    size_t nproject;
    int threads;              /* the data sets' sums and the learning curve's checks: at most
                                 this many at once (<= 0: the online CPUs); the same map and
                                 curve at any count */
    int mean_miss;            /* 1: the map's miss of the residual's time mean (below), written
                                 as the map's extension MEANMISS where it is systematic; the
                                 learn command's default, not teach's */
    const char *prior;        /* NULL, or a map file (swfs_recon_read's: NAXIS1 = the slopes, NAXIS2
                                 = the outputs, per frame) the learned map shrinks toward
                                 (swfs_recon_learner_set_prior): the frames move it as far as
                                 the ridge lets them, so give a ridge that counts (e.g. 0.1);
                                 for a map made another way (speckles --write-recon: a linear
                                 model's MAP) corrected by a few loops. Not with lags */
    int mean_miss_heldout;    /* with mean_miss: each data set's miss taken with the map of the
                                 other sets (their sums, the set's left out), not the map of all:
                                 a map learned from few sets fits their means in-sample, and its
                                 miss there is smaller than on new frames (speckles' loops_map) */
    const double *meanmiss_metric; /* with mean_miss: NULL, or nact x nact (symmetric, positive
                                 semi-definite, row-major; nact the truth's outputs) M: the check of
                                 the misses weighs a miss m as m^T M m instead of its sum of
                                 squares over the outputs. speckles' loops_map gives the mean
                                 square over the pupil of the wavefront the outputs make (their
                                 influence functions, piston, tip and tilt removed: what the NCP
                                 error counts), where a DM's actuators beyond the pupil, whose
                                 truth is its fit's extrapolation, count for what they put in it
                                 (docs/telemetry.md, "The mean's miss over the pupil") */
    size_t meanmiss_metric_n; /* its side: the truth's outputs (a run whose truth has another
                                 count fails, naming both) */
} swfs_learn_run_options;

void swfs_learn_run_options_default(swfs_learn_run_options *o);
/* learn's meanmiss_metric from the outputs' functions on the pupil grid: funcs a FITS cube
 * (NAXIS1 = NAXIS2 = n, NAXIS3 = the truth's outputs: a DM's influence functions, the
 * simulator's influence.fits; n 0: the file's own), over the pupil given as mask (n x n
 * weights) or, with mask NULL, the file pupil (swfs_pupil_mask_read): M_ab = the
 * mask-weighted mean over the pupil of f_a f_b, each f with piston, tip and tilt removed over
 * the mask (what pupil --truth counts of a wavefront). *M malloc'd, *nf x *nf; the file named
 * where a shape does not fit. */
int swfs_meanmiss_metric(const char *funcs, size_t n, const double *mask, const char *pupil, double **M, size_t *nf);

#define SWFS_LEARN_MAXWLAYERS 8

typedef struct swfs_learn_run_result {
    swfs_recon_learn_info info;
    size_t nfiles, nslopes, nact; /* nslopes: per frame (a space-time map's input is nlags times that) */
    /* The held-out check (more than one data set): each data set in turn left out, the map of
     * the others' frames applied to its frames. rms misfit and rms truth over all the frames
     * checked, the worst data set's misfit / truth and its index; NaN when none was checked
     * (one data set, or too few frames without any one). */
    size_t nheldout;
    double heldout_misfit_rms, heldout_truth_rms, heldout_worst;
    size_t heldout_worst_set;
    /* With lags: the wind of the training loops' slopes (wind.h, in subapertures per WFS
     * frame: no pitch or rate needed), the mean over the data sets whose first file shows
     * one (nwind of them), and the largest distance of one from that mean; written into the
     * map (LRNWINDN, LRNVX, LRNVY, LRNVSPRD) for speckles to compare with the observation's. */
    size_t nwind;
    double wind_vx, wind_vy, wind_spread;
    /* With lags: every frozen-flow layer the data sets' slopes show (wind.h: the tracked one
     * and those the stacking finds), grouped over the sets where two lie within
     * SWFS_SPACETIME_MISMATCH_WARN subaperture of each other at the largest lag: each group's
     * mean velocity [subapertures per WFS frame], the data sets holding it, and the farthest
     * member's distance from that mean; written as LRNNLAY, LRNLkX, LRNLkY, LRNLkN, LRNLkS
     * (k = 1 ... LRNNLAY) for speckles to match the observation's layers against. */
    size_t nwlayers;
    double wlayer_vx[SWFS_LEARN_MAXWLAYERS], wlayer_vy[SWFS_LEARN_MAXWLAYERS], wlayer_spread[SWFS_LEARN_MAXWLAYERS];
    size_t wlayer_n[SWFS_LEARN_MAXWLAYERS];
    /* With lags: the training slopes' temporal correlation at each lag (wfs.h
     * swfs_slopes_lag_correlation on each data set's first file), its mean over the data sets
     * and the largest distance of one from it; written as LRNCORk, LRNCSPk (k as LAGk). */
    double corr[SWFS_RECON_MAXLAGS], corr_spread[SWFS_RECON_MAXLAGS];
    swfs_recon_learn_info perframe_info; /* with perframe_out: that map's fit (else zero) */
    /* With curve: the map's held-out misfit against the frames it is learned from. The data
     * sets dealt into 4 parts (set d to part d mod 4); a map of 2 parts checked on the other 2
     * (both ways) and of 3 on the fourth (each in turn) give the mean square misfit per output
     * and frame m2[0] at curve_n[0] training frames (about N/2) and m2[1] at curve_n[1]
     * (3N/4) (s2[0], s2[1]: the same with each check's map output scaled by the factor that
     * fits best, wfs.h swfs_recon_learner_heldout_on: what a scale fitted downstream, the
     * estimator's g, leaves; reported, not used). m2(n) = a + b / n through them (the form of
     * a least-squares map's held-out misfit, b = a p for p independent frames' inputs; frames
     * correlated in time raise b):
     * curve_excess = b / (a N), the excess of the map of all N frames over a map of unlimited
     * frames, as a fraction of a; curve_frames = b / (SWFS_LEARN_CURVE_EXCESS a), the frames
     * that bring it to that fraction (0 when the misfit does not fall: b <= 0). NaN / 0 when
     * not checked (fewer than 4 data sets, or a part too small for a map). */
    size_t curve_n[2];
    double curve_m2[2], curve_s2[2], curve_a, curve_b, curve_excess;
    size_t curve_frames;
    size_t curve_outputs;     /* the outputs it was measured on (curve_radius) */
    /* With mean_miss (at least 2 data sets): each data set's miss of the residual's time mean,
     * its true residual's mean over its frames less the map applied to its mean slopes (piston
     * removed from both unless modal). A sensor whose mean signal is not linear in the
     * residual's mean (a pyramid under the loop's residual: docs/telemetry.md) leaves a miss
     * that is the same from set to set; a linear one leaves each set its own. The check: each
     * set's miss against the mean of the others' (held out), over the sum of the misses'
     * squares: meanmiss_heldout < 1 means the others' mean predicts a set's miss, and their
     * mean over all sets (meanmiss_rms its rms) is written as MEANMISS, which speckles adds to
     * the residual's reconstructed mean (RESMEAN); otherwise none is written. NaN / 0 when not
     * checked. With meanmiss_metric the squares are that metric's, and meanmiss_set_rms is
     * sqrt(m^T M m) over the sets (the pupil's rms for speckles' metric). */
    double meanmiss_heldout, meanmiss_rms, meanmiss_set_rms; /* meanmiss_set_rms: the sets' own, rms */
    int meanmiss_kept;
    /* The held-out check's outputs: those within curve_radius (the pupil's annulus: a truth on
     * the DM's actuators has many beyond it, where the truth is the fit's extrapolation), all
     * without it; heldout_scaled_rms the held-out misfit with each check's map output scaled
     * by the one factor that fits the held-out truth best over them (what the estimator's g
     * leaves; wfs.h swfs_recon_learner_heldout_on). */
    size_t heldout_outputs;
    double heldout_scaled_rms;
    /* With curve: the standard error of the curve's fall curve_m2[0] - curve_m2[1], from its four
     * parts' own falls (each part's misfit under the map of two parts less that under the map
     * of the other three: the same frames) and their scatter; NaN when not measured. A fall
     * within twice it the curve cannot tell from the parts' scatter (teach then measures the
     * curve again over twice the loops, as where it does not fall). Appended in 0.8.0. */
    double curve_fall_se;
} swfs_learn_run_result;

/* The excess of a learned map's held-out misfit over unlimited data that is enough: 10 % of
 * its variance (ordinary least squares on p independent inputs reaches it at n = 10 p frames,
 * teach's floor on its loops; docs/telemetry.md, "Loops as long as the map's learning curve
 * asks"). */
#define SWFS_LEARN_CURVE_EXCESS 0.1
/* A learning curve tells its fall where the fall is more than this many standard errors
 * (curve_fall_se): a one-sided test at about 93 % with the four parts' three degrees of
 * freedom. */
#define SWFS_LEARN_CURVE_FALL_SE 2.0
/* Whether r's learning curve falls beyond its parts' scatter: measured, curve_b > 0 and, where
 * curve_fall_se was measured, the fall more than SWFS_LEARN_CURVE_FALL_SE of it. Where it does
 * not, the curve cannot tell whether more frames would help. */
int swfs_learn_curve_falls(const swfs_learn_run_result *r);

int swfs_learn_run(const swfs_learn_run_options *o, swfs_learn_run_result *r);

/* ---- wind: the dominant layer's wind from telemetry files (wind.h) ------------------------ */

typedef struct swfs_wind_run_options {
    const char *const *files; /* consecutive telemetry files of one series (slopes x WFS frames) */
    size_t nfiles;
    const char *valid;        /* valid-subaperture map (swfs_valid_map_read), or NULL */
    long nsub;                /* subapertures across; 0: the files' NSUB, else the map's size */
    double teldiam;           /* [m] the pupil the nsub subapertures span (pitch = teldiam / nsub) */
    double rate;              /* [Hz] 0: the files' WFSRATE */
} swfs_wind_run_options;

typedef struct swfs_wind_run_result {
    swfs_wind_estimate est;
    size_t nframes, nsub;
    double pitch, rate;
} swfs_wind_run_result;

int swfs_wind_run(const swfs_wind_run_options *o, swfs_wind_run_result *r);

/* ---- modal-slopes: a modal system's coefficients back to its Shack-Hartmann's slopes ------ */

/* A modal system logs coefficients c = CM s of its WFS's slopes s (cacao's modevalWFS through
 * CMmodesWFS). Where that WFS is a Shack-Hartmann and CM is known, s' = CM+ c (the minimum-norm
 * slopes that give c: s projected onto CM's row space) is telemetry the Shack-Hartmann path
 * takes, its default teach included (docs/telemetry.md, "The modal input kind"). CM+ by an SVD,
 * its rank the numerical one (singular values above max(rows, cols) x DBL_EPSILON of the
 * largest); each file by one GEMM. Each input file is written under its own name into outdir
 * (not the input's folder), with BUNIT 'rad' and the input's WFSRATE and FRAME0, and CM is
 * copied beside them under its own name, which their MODALCM key gives (teach learns its loops'
 * slopes on the same projection); all files or none (one swfs_outputs group, atomic.h). With
 * imat, a first pass over the files checks how the coefficients were made (lsq_ratio below), and
 * the slopes carry the verdict: MODALLSQ (the ratio, where finite) and MODALRGW (1: it warned),
 * which speckles reports (swfs_speckles_run_result.modal_regularized). */
typedef struct swfs_modal_slopes_options {
    const char *const *files; /* modal coefficient files: coefficients x WFS frames */
    size_t nfiles;
    const char *cm;           /* the modal control matrix: NAXIS1 = slopes, NAXIS2 = coefficients */
    const char *outdir;       /* an existing folder other than the inputs' */
    const char *imat;         /* instead of cm: the modal response matrix RM (NAXIS1 = coefficients,
                                 NAXIS2 = slopes: each mode's slopes per unit coefficient); then
                                 s' = RM c and the copy beside the slopes is RM+ (pinv_NAME), the
                                 control matrix of least squares (docs/telemetry.md, "Modal
                                 coefficients with their response matrix") */
} swfs_modal_slopes_options;

typedef struct swfs_modal_slopes_result {
    size_t ncoef, nslopes, rank, nframes;
    double cond;              /* largest / smallest singular value kept */
    double resid;             /* rms of c - CM s' over rms of c: what CM cannot have made (0 up to
                                 rounding where its rank is its number of coefficients) */
    double lsq_ratio;         /* --imat: the coefficients' white noise over what a least-squares CM
                                 of RM gives them, the poorly sensed half of the modes against the
                                 well-sensed half, by medians (1 for a least-squares CM; 0: none in
                                 the poorly sensed half; NAN: fewer than 64 frames or 8
                                 coefficients, or cm given) */
    int lsq_warns;            /* lsq_ratio outside [SWFS_MODAL_LSQ_RATIO_MIN, its inverse]: the
                                 system's CM does not invert RM on its modes (it regularizes them),
                                 s' = RM c is not the slopes' projection: use --cm */
} swfs_modal_slopes_result;

/* A factor 2 either way: the check's convention, not a tuned value (least-squares coefficients
 * give 0.98-1.03, a von Karman MAP's below 0.2 or negative; docs/telemetry.md). */
#define SWFS_MODAL_LSQ_RATIO_MIN 0.5

int swfs_modal_slopes_run(const swfs_modal_slopes_options *o, swfs_modal_slopes_result *r);

/* ---- teach: a learned map for one observation from simulated loops of your system ------- */

/* The rule docs/telemetry.md measured over the matrix ("The rule with the layers `wind`
 * finds"), as one run: the layers `wind` finds in the observation's slopes; nloops simulated
 * closed loops of the described system (sim: its telescope, WFS, DM, loop, vibration, noise
 * and camera timing) with those layers, the first's share of the turbulence spread over
 * 0.3-0.7 across the loops when there are more (wind does not measure the shares); the
 * space-time map with lags 0, +-L1, +-2 L1, L1 = round(pitch rate / (2 v)) frames, v the
 * fastest layer found (half a subaperture); its two checks against the observation
 * (swfs_spacetime_warns). Where neither warns it is the map; otherwise the per-frame map of
 * the same loops (more than one layer found), or of nloops further loops of the measured
 * layer (a share of 0.5-0.8) and a second drawn at random (8-30 m/s, any direction). */
typedef struct swfs_teach_run_options {
    swfs_ts_params sim;         /* your system (`simulate mode=timeseries` keys); its layers, seed and
                                   exports are set per loop; the loops run sim.base.threads at a
                                   time (0: one per core), each loop then on one thread: the
                                   same loops, to the bit, however many run at once */
    const char *const *files;   /* the observation's telemetry: consecutive files of one series,
                                   2 nsub^2 slopes per WFS frame (the simulator's layout), or with
                                   the system's valid map (sim.valid) the used subapertures' only
                                   (x then y); the map is learned in the full layout, which
                                   speckles --valid applies to either */
    size_t nfiles;
    const char *out;            /* the chosen map (speckles --recon), with TEACHSEL (spacetime,
                                   perframe, perframe_mixed), TEACHLOO, TEACHLAY, TEACHWRN,
                                   TEACHMIS, TEACHCEX: the choice, loops, layers and checks */
    const char *work;           /* an existing folder: the loops (loop_NN/, mixed_NN/) and the maps
                                   tried (spacetime.fits, perframe.fits), kept for reuse by learn */
    size_t nloops;              /* loops per set (12; at least 2) */
    size_t max_loops;           /* the space-time map's loops at most (0: 4 nloops, at most 64; else
                                   nloops to 64): more loops than nloops where the map's learning
                                   curve asks for them (swfs_learn_run_result.curve_frames), a
                                   budget of at most 4 times the first loops' simulation by
                                   default; nloops: never more */
    uint64_t seed;              /* loop k's seed is seed + k (101); the random second layers' too */
    int modes_from_slopes;      /* 1: the loops' modal filter (sim.ao_modes) from the observation
                                   (the knee of its slopes' mode variances, swfs_ts_mode_variance,
                                   calibrated by simulated loops: ao_modes = K where a loop of K
                                   modes shows the observation's knee); for a description without
                                   ao_modes. Not with sim.ao_recon (0) */
    int noise_from_slopes;      /* 1: the loops' slope noise (sim.slope_noise) is the observation's
                                   white slope noise (noise_rms); for a description without
                                   slope_noise (docs/telemetry.md, "The loops' slope noise from
                                   the slopes") */
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;
    void *progress_ctx;
    const char *fingerprint;    /* NULL, or written into out as TEACHFPR: what the map was taught
                                   for (speckles' default reuses a map whose TEACHFPR is its own) */
    int coupling_from_recon;    /* 1: where sim.ao_recon gives the loops the system's control
                                   matrix, the DM's functions (sim.dm_coupling) from it
                                   (timeseries.h swfs_ts_coupling_from_recon); for a description
                                   without dm_coupling (0.10.0) */
} swfs_teach_run_options;

/* The version of teach's rule, hashed into speckles' fingerprint of a taught map's inputs
 * (TEACHFPR): a change to what teach makes of the same inputs (its loops, lags, choice, the
 * learner) bumps it, so that maps taught before are taught again rather than reused
 * (2026-12-01: more loops where the space-time map's learning curve asks for them;
 * 2026-12-02: a zonal calibration loop beside the modal ones; 2026-12-03: where no layer is
 * tracked, the space-time map at lags of 1 and 2 frames instead of the per-frame map;
 * 2026-12-03b: the loops' layers each at a speed within a factor sqrt 2 of the one found;
 * 2026-12-06: a first curve that does not fall doubles the loops and is measured again;
 * 2026-12-06b: the loops a curve asks for are the last, as before 2026-12-06;
 * 2026-12-07: the profile misfit about the whole profile's mean; 2026-12-07b: a first curve
 * whose fall is within twice its standard error doubles the loops as one that does not fall;
 * 2026-12-07d: the loops a curve asked for are followed to the budget where their own curve
 * falls without a bound; 2026-12-07e: with the system's control matrix (ao_recon) and no
 * dm_coupling, the DM's functions from that matrix; 2026-12-08: a first curve that falls
 * and asks for no more than twice the first loops doubles them too). */
#define SWFS_TEACH_RULE "teach rule 2026-12-08"

/* The zonal calibration loops' ao_rcond (timeseries.h: the truncated pseudo-inverse's cut
 * relative to the largest singular value), 0.02, 0.03, 0.05, 0.07, 0.1, 0.2: a factor of 1.4
 * to 2 apart (docs/telemetry.md, "A zonal loop": the taught maps' NCP error over observations
 * of cuts on and between them). */
#define SWFS_TEACH_NZONAL 6
extern const double swfs_teach_zonal_rcond[SWFS_TEACH_NZONAL];

void swfs_teach_run_options_default(swfs_teach_run_options *o);

#define SWFS_TEACH_SPACETIME 0     /* the space-time map: neither check warned */
#define SWFS_TEACH_PERFRAME 1      /* the per-frame map of the same loops */
#define SWFS_TEACH_PERFRAME_MIXED 2 /* the per-frame map of the measured layer and random seconds */
#define SWFS_TEACH_PERFRAME_PRIOR 3 /* the per-frame map of loops at a speed from the slopes'
                                       time correlation, as teach chose where `wind` tracked no
                                       layer until 2026-12-03 (a map's TEACHSEL; no longer chosen) */
#define SWFS_TEACH_SPACETIME_PRIOR 4 /* `wind` tracked no frozen-flow layer: the space-time map at
                                        lags 0, -1, 1, -2, 2 frames of loops at a speed from the
                                        slopes' time correlation */
/* Where `wind` tracks no layer: the speed of the loops' layers from the slopes' time
 * correlation at lags 1, 2, 4, ... frames (at most SWFS_TEACH_NTCORR, each under a quarter of
 * the frames), matched by calibration loops of one layer at speeds a factor 2 apart from 4 to
 * 32 m/s, extended by factors of 2 (1-64 m/s) while the closest is at an end, then a parabola
 * in log speed through the closest and its neighbours (docs/telemetry.md, "Slopes without a
 * frozen-flow layer"). At most SWFS_TEACH_NSPEED calibration loops. */
#define SWFS_TEACH_NTCORR 8
#define SWFS_TEACH_NSPEED 8

typedef struct swfs_teach_run_result {
    swfs_wind_run_result wind;  /* the observation's layers (wind.est.layer[]) */
    size_t nlayers;             /* layers the loops were given (the first SWFS_TS_MAX_LAYERS found) */
    long lags[5];               /* 0, -L1, L1, -2 L1, 2 L1 (L1 = 1 where no layer was tracked) */
    size_t nlags;
    size_t nloops;              /* loops simulated in all */
    size_t map_inputs;          /* the space-time map's inputs: 5 lags x the slopes the observation uses */
    size_t loop_frames;         /* WFS frames of each loop: the description's (loop_frames_described),
                                   lengthened where fewer than 10 map_inputs frames in all */
    size_t loop_frames_described;
    double st_misfit_rms, st_truth_rms; /* the space-time map's training misfit and truth [m] */
    swfs_speckles_run_result check; /* its checks on the observation's first file (st_*; info.nlags) */
    int warns;                  /* swfs_spacetime_warns(&check) */
    int chosen;                 /* SWFS_TEACH_* */
    size_t ao_modes;            /* the modal filter the loops were given (sim.ao_modes, or from the slopes) */
    size_t knee_obs;            /* modes_from_slopes: the observation's knee (swfs_mode_knee) */
    size_t ncal;                /* the calibration loops simulated (modes_NN/) */
    size_t cal_modes[4], cal_knee[4]; /* each one's ao_modes and knee */
    double seconds;
    size_t out_points;          /* the map's output points: a hexapolar grid of out_pitch (outgrid.fits) */
    double dm_pitch, out_pitch; /* [m] the DM's pitch and the grid's (each the median nearest-neighbour
                                   distance of its points): the grid is laid out at half the DM's
                                   pitch, at least two pupil samples (docs/telemetry.md) */
    double noise_rms;           /* [rad] the observation's white slope noise (swfs_slopes_white_noise
                                   of its first file), measured with or without noise_from_slopes */
    size_t noise_cells;         /* the 2 x 2 cells of used subapertures it was measured over */
    double noise_share;         /* noise_rms^2 over the slopes' variance per used slope (each slope's
                                   time mean and each frame's mean x / y slope removed): where it
                                   is about a third no map here holds (docs/telemetry.md) */
    double slope_noise;         /* [rad] the loops' slope noise: noise_rms (noise_from_slopes) or
                                   the description's */
    /* The space-time map's learning curve (run.h swfs_learn_run_result.curve_*) over the nloops
     * first loops (curve_first) and over all the space-time loops (curve, st_loops of them:
     * more than nloops when the first curve asked for more frames than they hold, up to
     * max_loops). curve_doubled: where the first curve did not fall, or fell and asked for at
     * most twice the first loops (teach rule 2026-12-08: a first curve does not end teach),
     * the curve over twice the first loops, which then asked for the last ones (curve itself where it asked for none),
     * unless the curve over those falls without a bound (asked_loops, curve_asked, below).
     * curve_n[0] == 0: not measured. */
    size_t st_loops;
    size_t max_loops;           /* the budget in effect (max_loops, or its default); the curve is
                                   measured only where it exceeds nloops */
    swfs_learn_run_result curve_first, curve, curve_doubled;
    size_t project_rank;        /* the telemetry is modal-slopes' projection (its MODALCM key): the
                                   loops' slopes projected the same way, P = CM+ CM of this rank */
    size_t project_slopes;      /* over this many slopes; 0: no projection */
    /* modes_from_slopes: the zonal calibration loops (zonal_NN/, one per swfs_teach_zonal_rcond):
     * each one's profile misfit (the rms of log10 of the loop's mode variances over the
     * observation's along the upper half of the modes, about its mean over all of them: teach
     * rule 2026-12-07; before, about the upper half's own mean), the closest one (its index), the modal loop's misfit (the
     * calibration loop whose knee came closest), and whether the loops are zonal
     * (zonal_misfit[zonal_best] < misfit_modal: ao_rcond = swfs_teach_zonal_rcond[zonal_best],
     * ao_modes then 0) */
    double zonal_misfit[SWFS_TEACH_NZONAL];
    size_t zonal_best;
    double misfit_modal;
    int zonal;
    /* chosen == SWFS_TEACH_SPACETIME_PRIOR (no layer tracked): the observation's slopes' time
     * correlation along the upper half of the DM modes (tcorr at tcorr_lags, ntcorr of them;
     * timeseries.h swfs_ts_mode_timecorr), the speed calibration loops (speed_NN/, nspeed: each
     * one's speed [m/s] and misfit, the rms of its correlation less the observation's), and the
     * speed the loops' layers were given (prior_speed: each loop's two layers within a factor
     * sqrt 2 of it, any direction). Their map's loops: st_loops, its learning curve
     * curve_first / curve, its training misfit st_misfit_rms of st_truth_rms. */
    double tcorr[SWFS_TEACH_NTCORR];
    long tcorr_lags[SWFS_TEACH_NTCORR];
    size_t ntcorr, nspeed;
    double speed_cal[SWFS_TEACH_NSPEED], speed_misfit[SWFS_TEACH_NSPEED];
    double prior_speed;
    /* The loops a curve asked for (asked_loops of them) whose own curve (curve_asked) fell, beyond
     * twice its parts' scatter, faster than any a + b / n allows: more loops followed, to the
     * budget (st_loops, curve over them). asked_loops 0: that did not happen (0.10.0). */
    size_t asked_loops;
    swfs_learn_run_result curve_asked;
    /* coupling_from_recon with ao_recon: the DM's functions its control matrix says (coupling_done
     * 1), and the loops' dm_coupling then: coupling.coupling where coupling.gaussian, else 0 (the
     * interpolated surface) (0.10.0) */
    int coupling_done;
    swfs_ts_coupling coupling;
} swfs_teach_run_result;

int swfs_teach_run(const swfs_teach_run_options *o, swfs_teach_run_result *r);

/* The default work folder of a teach whose map (or whose speckles' cube) is out: beside it,
 * its name without .fits and with .teach (`teach -o W.fits`: W.teach; `speckles -o S.fits`:
 * S.teach). Fails, naming out, when the name does not fit in cap. */
int swfs_teach_work_default(const char *out, char *work, size_t cap);

/* The system a teach simulates, described by the observation's own files, the ones
 * `speckles` takes, as `simulate mode=timeseries` keys set into c (keys already in c are
 * kept: the caller's own description wins):
 *   science    the reduced science cube: its geometry (pupn, pupdx = screen_dx, teldiam,
 *              wavelen, pixscale, obscur);
 *   actuators  the DM's positions (actuators=);
 *   pupil      the telescope's pupil mask, or NULL (pupil_mask=);
 *   valid      the valid-subaperture map, or NULL (valid=; nsub is its size);
 *   telemetry  the observation's first telemetry file: nsub (2 nsub^2 slopes, without a
 *              valid map), wfs_rate (WFSRATE) and the loops' length (wfs_file_frames and
 *              one short cube at each end, frame_ratio 1, a 16 x 16 focal window: the loops'
 *              camera is not used).
 * The rest stays the simulator's: loop gain and delay, r0, vibration, whose effect on
 * teach's map docs/telemetry.md measured; the modal filter comes from the slopes
 * (modes_from_slopes) unless c gives ao_modes or ao_recon, and so does the slope noise
 * (noise_from_slopes) unless c gives slope_noise. The files are named in any
 * failure (a science cube without its geometry, telemetry without WFSRATE or of a width
 * that is no square Shack-Hartmann's). */
int swfs_teach_describe(swfs_config *c, const char *science, const char *actuators, const char *pupil,
                        const char *valid, const char *telemetry);

/* ---- demo: the paper's Sec. 3 simulation end to end ---------------------------------- */

typedef struct swfs_demo_run_options {
    const char *outdir;       /* the demo folder: sigma<level>/ (simulate's four files, halo.fits,
                                 wavefront.fits), recovery.tsv, loop/ and report/ */
    swfs_sim_params sim;      /* the simulation (swfs_sim_params_default or a config file) */
    const double *levels;     /* camera background noise levels [counts], nlevels of them */
    size_t nlevels;
    swfs_loop_params loop;    /* the closed loop that follows (swfs_loop_params_default);
                                 loop.iterations = 0: none */
    int report;               /* 1: one page of figures, OUTDIR/report/index.html */
    const char *config;       /* the config file sim came from (NULL: none): refused as an output */
    const char *const *prov;  /* provenance lines of every product */
    size_t nprov;
    swfs_progress_fn progress; /* stages "simulate" (0 of 1 before it starts), "simulate screens",
                                  "simulate frames", "noise levels" (k of nlevels done, before
                                  each level and after the last), "closed loop" (0 before it starts,
                                  then each row) */
    void *progress_ctx;
} swfs_demo_run_options;

/* The defaults of `specklewfs demo`: folder "demo-out", the paper's simulation, levels
 * 0, 10, 100, 1000 counts, the loop's defaults, the report. */
void swfs_demo_run_options_default(swfs_demo_run_options *o);

typedef struct swfs_demo_run_result {
    swfs_sim_result *sim;     /* the noise-free simulation every level was made from */
    size_t nlevels;
    swfs_recovery *levels;    /* one recovery per noise level (recovery.h), as in recovery.tsv */
    double *level_seconds;    /* wall time of each level */
    swfs_loop_result *loop;   /* the closed loop (NULL with loop.iterations = 0) */
    double ncp_rms_ptt;       /* [m] the injected NCP with piston, tip and tilt removed */
    double sim_seconds, seconds; /* the simulation's and the whole run's wall time */
    char html[4096];          /* the report's index.html ("" without it) */
} swfs_demo_run_result;

/* `specklewfs demo`: the folders made and every product checked against the config file
 * and each other, the simulation, each noise level's recovery (swfs_recovery_run, seed
 * sim.seed * 1000003 + level), recovery.tsv, the closed loop (swfs_closed_loop_run with the
 * simulation as its first row, swfs_closed_loop_write into loop/), all renamed into place
 * together (atomic.h: a failure leaves none under its final name), then the figures. */
int swfs_demo_run(const swfs_demo_run_options *o, swfs_demo_run_result *r);
void swfs_demo_run_result_free(swfs_demo_run_result *r);

SWFS_END_DECLS

#endif

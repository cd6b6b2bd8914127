/* The speckle pipeline: WFS telemetry arrays -> the complex speckle field psi that matches
 * the science camera frames (paper Sec. 4.4, eq:downsampledHalo, eq:computedSpeckleField).
 *
 * One object owns every step that `specklewfs speckles`, `specklewfs stream` and any
 * embedding application share: the speckle model on the pupil grid (Clough-Tocher
 * interpolation from the actuators, the Shack-Hartmann model), the reconstructor (given,
 * or built here: von Karman MAP, telemetry-learned MAP, truncated SVD), the tip-tilt
 * treatment (speckles.h explains the three modes) and the per-frame engine (engine.h).
 * It takes and returns arrays only; files are the io layer's (source.h, run.h).
 *
 *   swfs_pipeline_options o;  swfs_pipeline_options_default(&o);
 *   swfs_pipeline *p;         swfs_pipeline_create(&p, &geom, nfx, nfy, xy, nact, NULL, nslopes,
 *                                                  NULL, training, ntrain, &o);
 *   swfs_pipeline_process(p, slopes, nwfs, sched, nexp, psi);   // per batch, no allocation
 *   swfs_pipeline_free(p);
 *
 * An object is used by one thread at a time; independent objects may run concurrently. */
#ifndef SWFS_PIPELINE_H
#define SWFS_PIPELINE_H

#include <stddef.h>

#include "specklewfs/engine.h"
#include "specklewfs/geom.h"
#include "specklewfs/sparse.h"
#include "specklewfs/speckles.h"
#include "specklewfs/wfs.h"

SWFS_BEGIN_DECLS

/* A given reconstructor's gain on the model's D (swfs_pipeline_info.recon_gain: the dominant
 * eigenvalue of W D, 1 for any reconstructor of D and about 1 for a Wiener-type one, whose
 * best-measured mode keeps nearly all of itself) is accepted in [SWFS_RECON_GAIN_MIN,
 * 1 / SWFS_RECON_GAIN_MIN]: the model's D differs from a real system's by calibration errors
 * of tens of percent, while a convention error is a sign or a factor 2 (docs/telemetry.md).
 * speckles checks only the sign of a space-time map learn or teach made (RECON = 'learned'):
 * its lag blocks' sum on a still wavefront is no convention's gain. */
#define SWFS_RECON_GAIN_MIN 0.5

/* Reconstructor choices. */
enum {
    SWFS_RECON_VK = 0,    /* MAP with a von Karman prior on the actuators (default) */
    SWFS_RECON_MAP = 1,   /* per-mode Wiener gain, prior learned from the training slopes */
    SWFS_RECON_SVD = 2,   /* truncated pseudo-inverse (rcond, max_modes) */
    SWFS_RECON_GIVEN = 3  /* the caller's matrix (swfs_pipeline_create's recon) */
};

typedef struct swfs_pipeline_options {
    int recon;          /* SWFS_RECON_* (default SWFS_RECON_VK) */
    double rcond;       /* SWFS_RECON_SVD: singular values kept above rcond x the largest (5e-2) */
    size_t max_modes;   /* SWFS_RECON_SVD: at most this many modes, 0 = no limit */
    double slope_noise; /* SWFS_RECON_VK|MAP: slope noise rms [rad]; 0 = estimated from the training slopes */
    double vk_l0;       /* SWFS_RECON_VK: effective outer scale [m] (10); 0: fitted to the
                           training slopes by maximum likelihood, with the prior's scale and the
                           slope noise (swfs_vk_fit_slopes; docs/telemetry.md) */
    int tiptilt;        /* SWFS_TT_EXPOSURE (default), SWFS_TT_FRAME, SWFS_TT_KEEP (speckles.h) */
    int threads;        /* engine workers (1) */
    int wfs_rate;       /* 1: one focal field per WFS frame (swfs_pipeline_process_wfs), 0: per exposure */
    double recon_scale; /* SWFS_RECON_GIVEN: the given matrix is multiplied by this first (1); e.g. -2
                           for a matrix to DM commands (a correction, of the surface) */
    const unsigned char *valid; /* NULL, or the AO system's valid-subaperture map (valid_nsub^2 flags,
                                   subaperture (a, b) at b nsub + a): the subapertures used, whatever
                                   their illumination; the telemetry may then hold only theirs
                                   (2 nvalid values: x, then y, in index order). Read at creation only */
    size_t valid_nsub;
    double band;        /* [lambda/D] the focal radius inside which speckles are computed; the field
                           beyond is set to 0, so the estimator takes no reference there. 0
                           (default): the Shack-Hartmann's sampling band, nsub/2 (a spatial
                           frequency beyond it reaches the slopes only as an alias, and the
                           reconstruction's field there is not the residual's; docs/telemetry.md),
                           none for a linear model, and for a given map with its own output
                           points (swfs_recon oxy) their sampling band D / (2 pitch): such a map
                           was taught the residual out to there; > 0: this radius; < 0: none */
} swfs_pipeline_options;

void swfs_pipeline_options_default(swfs_pipeline_options *o);

typedef struct swfs_pipeline swfs_pipeline;

/* What the pipeline was built with, for summaries and provenance. */
typedef struct swfs_pipeline_info {
    size_t nact, nslopes, npup, nfx, nfy;
    size_t recon_modes;  /* modes the reconstructor keeps (SVD / MAP), 0 for a given matrix */
    double recon_dof;    /* effective degrees of freedom (MAP / vk) */
    double noise_var;    /* slope noise variance used [rad^2] (MAP / vk) */
    int noise_given;     /* 1 if noise_var came from the options */
    size_t ntrain;       /* training WFS frames (MAP / vk) */
    size_t n_outside;    /* illuminated pupil samples outside the actuators' hull */
    double vk_l0;        /* SWFS_RECON_VK: the outer scale used [m] */
    double recon_gain;   /* SWFS_RECON_GIVEN: the matrix's gain on the model's interaction matrix D,
                            the eigenvalue of W D of largest magnitude: 1 for a reconstructor of D
                            on whatever modes it keeps, its best-measured mode's Wiener factor for
                            a MAP one, negative for the opposite sign (see swfs_pipeline_create) */
    /* The generic linear model (swfs_pipeline_create_linear; 0 for the Shack-Hartmann one): */
    size_t nbasis;       /* basis functions */
    size_t basis_nnz;    /* their nonzeros on the pupil grid */
    int composed;        /* 1: basis x control folded into one matrix per illuminated sample */
    double resid_rms;    /* rms over the pupil of the training frames' wavefront, tip-tilt
                            removed [m] (NaN: no training frames) */
    size_t nsub, nvalid; /* Shack-Hartmann: subapertures across, and used (0 for a linear model) */
    double band;         /* [lambda/D] the radius speckles are computed within (options.band); 0: none */
    size_t band_out;     /* focal pixels beyond it, set to 0 in every field */
    size_t nlags;        /* a space-time reconstructor's lags (0: one frame's slopes); nslopes is
                            then the stacked input's width (swfs_slopes_stack) */
    double out_pitch;    /* [m] a given map's own output points (swfs_recon oxy, e.g. teach's grid
                            finer than the DM): their pitch, and the default band is their sampling
                            band D / (2 out_pitch); 0: the outputs are the actuators given */
    size_t imat_rank;    /* the linear model's interaction matrix: its numerical rank (singular
                            values above max(rows, columns) x machine epsilon x the largest, LAPACK's
                            rule), the coefficients' combinations its telemetry senses; below
                            nbasis, the others are never reconstructed. 0 without one */
} swfs_pipeline_info;

/* The generic linear model (lmodel.h): z = scale B (A v) per WFS frame. */
typedef struct swfs_linear_input {
    size_t nmeas;              /* telemetry values per WFS frame */
    const swfs_sparse *basis;  /* npup^2 x nk: the basis on the pupil grid (swfs_basis_from_grid or _pupil) */
    const double *control;     /* nk x nmeas (row-major) into the coefficients, or NULL */
    const double *imat;        /* instead of control: nmeas x nk interaction matrix (the telemetry of a
                                  unit coefficient), inverted here by the MAP reconstructor learned from
                                  the training frames (swfs_recon_map; the default) or, with
                                  opt->recon = SWFS_RECON_SVD, the truncated SVD */
    double scale;              /* metres of wavefront per unit of basis x coefficient */
    const double *shapes;      /* NULL, or the basis in factored form: nq x nshapes (row-major), basis
                                  function k = basis (npup^2 x nq, e.g. swfs_grid_interp) times column k
                                  (e.g. a mode cube's values at the DM-grid points); control, imat and
                                  the coefficients then refer to the nshapes functions */
    size_t nshapes;
    size_t nlags;              /* 0 or 1: one frame's values; more: a space-time control matrix, each
                                  frame's input the values of frames t + lags[k] stacked (the caller
                                  stacks them, wfs.h swfs_slopes_stack): nmeas = nlags x the values
                                  per frame, control in lag blocks (imat: not with lags) */
} swfs_linear_input;

/* The wavefront of a linear model's frame [m] beyond this rms is no residual of a working AO
 * loop at any wavelength it is sensed at (a units error: um taken as m, ...); below the
 * minimum the speckles vanish. Both are refused, naming the rms and the scale. */
#define SWFS_LINEAR_MAX_RMS_WAVES 4.0
#define SWFS_LINEAR_MIN_RMS_WAVES 1e-5

/* A given reconstructor (SWFS_RECON_GIVEN, times recon_scale) is measured against the
 * model's own interaction matrix D (info.recon_gain): W D is a projector (gain 1) for any
 * reconstructor of D, whatever modes it keeps; a matrix to DM commands gives about -1/2
 * (swfs_speckles_run refuses a gain outside [1/2, 2]).
 * geom: WAVELEN, TELDIAM, OBSCUR, PIXSCALE, PUPDX, PUPN all required; nfx x nfy: the
 * focal window (the science frames); xy: nact actuator positions (x, y) [m]; mask: PUPN^2
 * pupil transmission, or NULL for the annulus of TELDIAM/OBSCUR; nslopes: 2 nsub^2 (x then
 * y slopes of a square Shack-Hartmann); recon: the reconstructor for SWFS_RECON_GIVEN
 * (nact x nslopes, z_act [m] = W s [rad]; a space-time one, recon->nlags > 1, nact x nslopes
 * nlags: its lag-0 block takes the tip-tilt treatment, the others' mean slopes are projected
 * out, and its gain is that of the blocks' sum), else NULL; training: ntrain consecutive WFS
 * frames of nslopes for SWFS_RECON_VK/MAP (NULL otherwise). Copies what it keeps. */
int swfs_pipeline_create(swfs_pipeline **out, const swfs_geom *geom, size_t nfx, size_t nfy, const double *xy,
                         size_t nact, const double *mask, size_t nslopes, const swfs_recon *recon,
                         const double *training, size_t ntrain, const swfs_pipeline_options *opt);
void swfs_pipeline_free(swfs_pipeline *p);
/* The same pipeline over the generic linear model: no actuators, no Shack-Hartmann. With
 * neither control nor imat the telemetry values are the coefficients (nmeas = nk). The
 * tip-tilt modes are those of the Shack-Hartmann pipeline (speckles.h), the tilt being the
 * Z-tilt of the model's wavefront; opt->recon matters only with imat (VK, which needs
 * actuator positions, means MAP here). training (ntrain frames of nmeas) is needed with imat
 * and MAP; when given, the residual's rms is checked against SWFS_LINEAR_*_RMS_WAVES. */
int swfs_pipeline_create_linear(swfs_pipeline **out, const swfs_geom *geom, size_t nfx, size_t nfy, const double *mask,
                                const swfs_linear_input *in, const double *training, size_t ntrain,
                                const swfs_pipeline_options *opt);

/* The nexp camera exposures sched[0..nexp) over slopes (nwfs frames of nslopes, the
 * exposures' indices into them): out = nexp core-referenced focal fields nfx x nfy
 * (eq:downsampledHalo), before the static halo is subtracted. Work space grows to the
 * largest batch seen and is then reused: nothing is allocated in the steady state.
 * With a space-time reconstructor (recon->nlags > 1) each frame is the stacked slopes of
 * frames t + lags[k] (swfs_slopes_stack; info.nslopes values): the caller, who holds the
 * telemetry around the batch, stacks them. */
int swfs_pipeline_process(swfs_pipeline *p, const double *slopes, size_t nwfs, const swfs_exposure *sched, size_t nexp,
                          swfs_complex *out);
/* One focal field per WFS frame (the WFS-rate speckles `coherence` needs). */
int swfs_pipeline_process_wfs(swfs_pipeline *p, const double *slopes, size_t nwfs, swfs_complex *out);
/* Psi_0 of eq:computedSpeckleField: the referenced focal field of flat slopes (the
 * unaberrated pupil, unit exposure weight), nfx x nfy. */
int swfs_pipeline_flat_halo(swfs_pipeline *p, swfs_complex *out);

void swfs_pipeline_get_info(const swfs_pipeline *p, swfs_pipeline_info *info);

/* The time mean of the reconstructed residual wavefront. Every exposure that
 * swfs_pipeline_process (or every WFS frame that swfs_pipeline_process_wfs) turns into a
 * focal field also adds its frames' weighted mean telemetry to a running sum; the mean over
 * those exposures, reconstructed as the engine reconstructs a frame, is the AO residual's
 * time mean as the telemetry measures it [m], on the PUPN x PUPN grid, 0 outside the pupil,
 * piston, tip and tilt removed (the science frames are registered: a mean tilt is not in
 * them). The science camera sees it as a static aberration beside the NCP; `pupil`
 * subtracts it (pupil.h, docs/telemetry.md). nexp, rms (may be NULL): the exposures averaged,
 * and the map's rms in the pupil [m]. SWFS_ERR_VALUE before any exposure. */
int swfs_pipeline_mean_wavefront(const swfs_pipeline *p, double *out, size_t *nexp, double *rms);
/* The same mean as the engine reconstructs it alone, without the offset set by
 * swfs_pipeline_set_mean_offset (a map's or loops' miss of it): what a miss is measured against. */
int swfs_pipeline_mean_reconstruction(const swfs_pipeline *p, double *out);
/* A map [m] (PUPN x PUPN, kept inside the pupil) that swfs_pipeline_mean_wavefront adds to the
 * reconstructed mean before piston, tip and tilt come out: a map's own miss of the residual's
 * time mean (learn's MEANMISS, or the MEANMISS image of the map speckles' choice among the
 * loops' maps writes; simulated loops' shared miss, docs/telemetry.md). NULL: none (the
 * default). A sample inside the pupil that is not finite is refused, and the offset set
 * before stays. */
int swfs_pipeline_set_mean_offset(swfs_pipeline *p, const double *map);
/* The wavefront [m] (PUPN x PUPN, piston, tip and tilt removed; no mean offset) that the
 * pipeline reconstructs from a mean of n telemetry values per WFS frame, as
 * swfs_pipeline_mean_wavefront does from the exposures' (other data's mean: a simulated
 * loop's). */
int swfs_pipeline_wavefront_of_mean(const swfs_pipeline *p, const double *mean, size_t n, double *out);
void swfs_pipeline_mean_reset(swfs_pipeline *p);
/* The running sum itself (n values, owned by p, writable) and its exposure count, for
 * members of a team to add up (team.h sum); swfs_pipeline_mean_set_count then sets the
 * count that goes with a summed state. */
void swfs_pipeline_mean_state(swfs_pipeline *p, double **sum, size_t *n, size_t *nexp);
void swfs_pipeline_mean_set_count(swfs_pipeline *p, size_t nexp);
/* SWFS_TT_EXPOSURE: the Z-tilt of the model's wavefront per telemetry value, 2 rows (x, y)
 * of nslopes [rad per unit]; NULL in the other tip-tilt modes. */
const double *swfs_pipeline_tilt_rows(const swfs_pipeline *p);
/* The Shack-Hartmann model's reconstructor and model (NULL for a linear model). */
const swfs_recon *swfs_pipeline_recon(const swfs_pipeline *p);
/* A linear model's map from a frame's telemetry values to its basis coefficients, before
 * the model's scale (nact = the coefficients, nslopes = the values): the MAP (or SVD)
 * reconstructor of the interaction matrix made from the telemetry, in the form `--control`
 * reads. NULL for the Shack-Hartmann model, a control matrix given (the map is its file) and
 * where the telemetry are the coefficients themselves. */
const swfs_recon *swfs_pipeline_linear_map(const swfs_pipeline *p);
const swfs_speckle_model *swfs_pipeline_model(const swfs_pipeline *p);
/* The pupil mask the pipeline was made with (PUPN^2; the annulus where none was given). */
const double *swfs_pipeline_mask(const swfs_pipeline *p);
const swfs_pipeline_options *swfs_pipeline_opts(const swfs_pipeline *p);

SWFS_END_DECLS

#endif

/* Deformable-mirror offsets from an NCP wavefront estimate (closing the loop the paper
 * leaves open: "all that remains is to apply the corrections to the DM").
 *
 * The correction is the surface that cancels the measured wavefront error on a reflective
 * DM: a surface change dz changes the wavefront by 2 dz, so the target surface is
 * -WFE/2 (eq:NCP-WFE-estimate gives WFE; the paper's z = phi lambda / 4 pi). It is fitted
 * in the least-squares sense over the pupil onto the actuators' influence functions:
 *
 *   surface(x) = sum_a c_a f_a(x),   c = (A^T W A + mu tr(A^T W A)/nact 1)^+ A^T W t,
 *
 * A the influence matrix on the pupil grid, W the pupil mask (weights), t the target,
 * mu a small Tikhonov term that keeps actuators barely touching the pupil from running
 * away, and + a pseudo-inverse that drops eigenvalues below rcond times the largest
 * (actuators that do not see the pupil at all get 0).
 *
 * Influence functions:
 *  - SWFS_INFLUENCE_GAUSS (default): f_a(x) = coupling^(|x - x_a|^2 / pitch^2), i.e. a
 *    Gaussian whose value at one actuator pitch is `coupling` (0.15-0.30 for typical
 *    continuous-facesheet DMs; default 0.2), truncated where it falls below 1e-5;
 *  - SWFS_INFLUENCE_CUBIC: the Clough-Tocher interpolation of the actuator values
 *    (interp.h), the surface model the AO reconstruction in wfs.h uses.
 * pitch: given, or the median nearest-neighbour distance of the actuators.
 *
 * Modal restriction (--modes K): the target is first projected (least squares over the
 * pupil) onto Noll Zernikes j = 1..K (aperture.h, rho = 2r/D), so that estimation noise
 * is not driven into the high orders; the projection is then fitted onto the actuators.
 *
 * Coverage: every pupil sample must lie inside the convex hull of the actuators, or the
 * plan fails with SWFS_ERR_VALUE naming how many samples are uncovered.
 * Units: metres (surface and commands), actuator positions in the pupil frame of
 * docs/conventions.md. Design notes: docs/closed-loop.md. */
#ifndef SWFS_DMFIT_H
#define SWFS_DMFIT_H

#include <stddef.h>

#include "specklewfs/fits.h"
#include "specklewfs/sparse.h"

SWFS_BEGIN_DECLS

enum { SWFS_INFLUENCE_GAUSS = 0, SWFS_INFLUENCE_CUBIC = 1 };

typedef struct swfs_dmfit_options {
    int influence;   /* SWFS_INFLUENCE_GAUSS (default) or SWFS_INFLUENCE_CUBIC */
    double coupling; /* Gaussian influence at one pitch, in (0, 1); default 0.2 */
    double pitch;    /* [m] Gaussian width reference; <= 0: median nearest-neighbour distance */
    size_t modes;    /* 0: fit the full target; K: its projection on Noll Zernikes 1..K */
    double reg;      /* Tikhonov mu (relative to the mean diagonal), default 1e-3 */
    double rcond;    /* eigenvalue cut relative to the largest, default 1e-9 */
    int rim;         /* 0 (default): pupil samples outside the actuators' convex hull are refused
                        (a DM cannot correct there); 1: within one actuator pitch of it they take
                        the nearest inside sample's row, as the speckle model does
                        (swfs_interp_extend_rim), so a fit represents what that model reads back
                        (the time-series simulator's export_truth); farther is still refused */
} swfs_dmfit_options;

void swfs_dmfit_options_default(swfs_dmfit_options *o);

/* What one fit did, over the pupil (mask-weighted, piston removed) [m rms]. */
typedef struct swfs_dmfit_stats {
    double target_rms;   /* the target surface */
    double modal_rms;    /* its projection on the K modes (= target_rms when modes = 0) */
    double filtered_rms; /* target - projection: left out on purpose (0 when modes = 0) */
    double fit_rms;      /* the fitted DM surface */
    double fiterr_rms;   /* projection - fitted: what the DM cannot reproduce */
    double unfit_rms;    /* target - fitted: everything the offsets leave uncorrected */
    double cmd_rms, cmd_min, cmd_max; /* commands [m] over the active actuators */
} swfs_dmfit_stats;

typedef struct swfs_dmfit swfs_dmfit; /* plan: create once, apply many times */

/* xy: nact (x, y) pairs [m]; g: PUPN, PUPDX, TELDIAM (and OBSCUR when mask is NULL);
 * mask: PUPN x PUPN pupil transmission or NULL for the annulus of g. */
int swfs_dmfit_create(swfs_dmfit **out, const double *xy, size_t nact, const swfs_geom *g, const double *mask,
                      const swfs_dmfit_options *opt);
void swfs_dmfit_free(swfs_dmfit *f);

/* target: PUPN x PUPN surface [m] (only samples inside the pupil are used). cmd: nact
 * commands [m]. fitted (may be NULL): the DM surface the commands make on the grid (0
 * outside the pupil). st may be NULL. Uses the plan's work space: not thread-safe on
 * one plan. */
int swfs_dmfit_apply(swfs_dmfit *f, const double *target, double *cmd, double *fitted, swfs_dmfit_stats *st);
/* The fit in two halves, for many targets at once (a plan without a modal restriction):
 * rhs writes b = A^T W t of one target (nact values; it only reads the plan); solve_many
 * turns n of them (n x nact, row-major) into their commands with one GEMM (cmd, n x nact,
 * not overlapping b). The commands equal swfs_dmfit_apply's to rounding (the GEMM sums in
 * another order than the GEMV): a GEMM reads the nact x nact solve once per block of
 * targets where the GEMV reads it once per target. */
int swfs_dmfit_rhs(const swfs_dmfit *f, const double *target, double *b);
/* rhs for n targets at once, vectorized over them: R holds the targets on the plan's pupil
 * samples, sample-major (R[k ld + j]: target j < n <= ld at sample swfs_dmfit_pix(f)[k]); bt
 * (nact x n, row-major: bt[a n + j]) receives their right-hand sides. Each value is summed in
 * the order swfs_dmfit_rhs sums it. A non-finite value is refused, naming its target and
 * sample. */
int swfs_dmfit_rhs_many(const swfs_dmfit *f, const double *R, size_t ld, size_t n, double *bt);
/* The right-hand sides of surfaces that are linear in commands c: for the surface T c (T:
 * PUPN^2 x nc, sparse; only its rows at the plan's samples are read), rhs(T c) = G c with G =
 * A^T W T (nact x nc, row-major, allocated into *G). A loop whose residual is turbulence
 * minus a DM surface T c then takes the fit's right-hand sides as rhs(turbulence) - G c. */
int swfs_dmfit_rhs_matrix(const swfs_dmfit *f, const swfs_sparse *T, double **G);
/* The pupil samples a plan reads (mask > 0), npix of them, as indices into PUPN x PUPN. */
size_t swfs_dmfit_npix(const swfs_dmfit *f);
const size_t *swfs_dmfit_pix(const swfs_dmfit *f);
void swfs_dmfit_solve_many(const swfs_dmfit *f, const double *b, size_t n, double *cmd);
/* surface = sum_a cmd_a f_a on the grid (0 outside the pupil). */
void swfs_dmfit_surface(const swfs_dmfit *f, const double *cmd, double *surface);

size_t swfs_dmfit_nact(const swfs_dmfit *f);
size_t swfs_dmfit_npup(const swfs_dmfit *f);        /* PUPN */
const double *swfs_dmfit_xy(const swfs_dmfit *f);    /* 2 x nact actuator positions [m] */
double swfs_dmfit_pitch(const swfs_dmfit *f);        /* [m] the pitch used */
size_t swfs_dmfit_active(const swfs_dmfit *f);       /* actuators whose influence reaches the pupil */
const swfs_sparse *swfs_dmfit_influence(const swfs_dmfit *f); /* PUPN^2 x nact */
const double *swfs_dmfit_mask(const swfs_dmfit *f);  /* PUPN^2 */
const swfs_dmfit_options *swfs_dmfit_opts(const swfs_dmfit *f);

/* OFFSETS.fits: OFFSETS (nact x 1 [m], the commands), ACTUATORS (2 x nact [m]), SURFACE
 * (the DM surface of the commands [m]), UNFIT (target - surface [m], inside the pupil),
 * PUPIL (mask); geometry keywords, INFLUENC, COUPLING, ACTPITCH, NMODES, DMREG and the
 * stats (TGTRMS, MODERMS, FILTRMS, FITRMS, FITERRMS, UNFITRMS [m]) plus provenance on
 * every HDU. */
int swfs_dmfit_write(const swfs_dmfit *f, const double *cmd, const double *target, const swfs_dmfit_stats *st,
                     const char *path, const swfs_geom *g, const char *const *prov, size_t nprov);

SWFS_END_DECLS

#endif

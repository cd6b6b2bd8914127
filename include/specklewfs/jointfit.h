/* The joint pupil-domain fit (docs/estimator.md, Stage 2): one global model of the
 * per-pixel regression statistics of regress.h.
 *
 * Unknowns: the pupil field W = P exp(sum_j z_j B_j), z_j = alpha_j + i phi_j on tensor
 * cubic B-splines B_j restricted to the pupil P; log g = sum_m beta_m P_p(u) P_q(v) (2-D
 * Legendre, p + q <= order, u, v in [-1, 1] across the solved pixels' bounding box) +
 * sum_r gamma_r b_r(rho) (cubic B-splines of the distance rho from the star, g_radial apart, out
 * to the farthest solved pixel); kappa >= 0, the fraction
 * of speckle power the computed speckles do not explain. Model per focal pixel k:
 *
 *   Psi = MFT(W)  (mft.h, the docs/conventions.md conventions),
 *   theta_k = (|Psi_k|^2 + kappa g_k^2 Phi_sp,k,  g_k^2,  g_k Re Psi_k,  g_k Im Psi_k)
 *
 * (eq:betterIModel, eq:betterMean, eq:betterStabilized with an incoherent term). Cost:
 *
 *   S = sum_k (theta_k^T F_k theta_k - 2 theta_k^T f_k) + lambda_phi phi^T R phi + lambda_alpha alpha^T R alpha
 *
 * (plus sum_{m>=1} beta_m^2 / g_prior_sigma^2, and the same over the radial gamma_r). F_k,
 * f_k from swfs_regress_solve (so the first sum is the chi-square of the model up to a
 * constant); R a roughness penalty of the
 * B-spline expansion over the pupil samples: thin-plate second differences by default,
 * first differences as an option. Levenberg-Marquardt from the linear GLS solution with a
 * constant g; the prior weights follow MacKay's evidence rule every iteration
 * (alpha_ratio lambda_phi <= lambda_alpha <= alpha_ratio_max lambda_phi), and so does the
 * data's own weight beta (the noise scale, MacKay's second rule): the prior weights reported
 * are lambda / beta. Geometry-derived
 * knots and every constant: docs/estimator.md. NCP wavefront = lambda / (2 pi) sum_j phi_j B_j, piston removed: no phase
 * unwrapping is ever needed. */
#ifndef SWFS_JOINTFIT_H
#define SWFS_JOINTFIT_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/geom.h"
#include "specklewfs/regress.h"

SWFS_BEGIN_DECLS

enum { SWFS_JF_PRIOR_GRADIENT = 0, SWFS_JF_PRIOR_CURVATURE = 1 };
enum { SWFS_JF_INTERCEPT_MODEL = 0, SWFS_JF_INTERCEPT_FREE = 1, SWFS_JF_INTERCEPT_AUTO = 2 };
/* The rejection level of the intercept model's likelihood-ratio test (standard deviations of
 * the chi-square difference under the model): a significance level, not a fitted constant. */
#define SWFS_JF_INTERCEPT_Z 5.0
/* The evidence's data weight beta = (rows - well-determined parameters) / chi2 is kept within
 * [SWFS_JF_NOISE_SCALE_MIN, 1 / SWFS_JF_NOISE_SCALE_MIN]: a guard against a degenerate chi2,
 * never reached on the cases of docs/estimator.md (0.14 - 0.95). */
#define SWFS_JF_NOISE_SCALE_MIN 1e-3

typedef struct swfs_jointfit_options {
    double knot_factor;    /* B-spline intervals across D = knot_factor * (the width in
                              lambda/D of the valid pixels' span about the star: 2 E + 1
                              pixels, E the largest offset of a valid pixel along either
                              axis; the window's width when every pixel is valid), rounded
                              up; 1 (see docs/estimator.md) */
    int legendre_order;    /* p + q <= order for log g; 4 */
    double g_prior_sigma;  /* Gaussian prior of this standard deviation on each non-constant
                              log g coefficient (keeps g finite where no pixel constrains it);
                              0.5; <= 0: none */
    int fit_kappa;         /* 1: fit kappa >= 0; 0: kappa = 0 */
    int max_iter;          /* Levenberg-Marquardt iterations, 40 */
    int gls_iter;          /* Gauss-Newton iterations of the linear (constant g) start, 1 */
    double tol;            /* stop when an accepted step lowers the cost by less than tol
                              (chi-square units) and the prior weights move < 5%; 0.5 */
    double lambda_phi;     /* > 0: fixed prior weight on phi; <= 0: evidence rule (default) */
    double lambda_alpha;   /* > 0: fixed prior weight on alpha; <= 0: evidence rule (default) */
    double alpha_ratio;    /* lambda_alpha >= alpha_ratio * lambda_phi; 10 */
    double alpha_ratio_max; /* lambda_alpha <= alpha_ratio_max * lambda_phi; 1000 (where the
                              amplitude is uniform its evidence has no finite maximum) */
    int prior;             /* R: SWFS_JF_PRIOR_CURVATURE (thin-plate second differences,
                              default) or SWFS_JF_PRIOR_GRADIENT (first differences) */
    int intercept;         /* SWFS_JF_INTERCEPT_MODEL: the mean intensity a = |Psi|^2 + kappa g^2
                              Phi_sp is fitted; SWFS_JF_INTERCEPT_FREE: a is a free nuisance per
                              pixel (marginalized), so light the computed speckles do not model
                              (an uncorrected halo, stray light) cannot bias Psi; kappa is then 0;
                              SWFS_JF_INTERCEPT_AUTO (default): both, and the model is kept unless
                              a likelihood-ratio test rejects it (chi-square difference above
                              npix - 1 + SWFS_JF_INTERCEPT_Z sqrt(2 (npix - 1))) */
    int threads;           /* AUTO: with 2 or more, the two fits run at once (the model fit waits
                              for the free fit's chi-square only where its early stop needs it:
                              the same result as one after the other); <= 0 (default): the
                              online CPUs; 1: one after the other */
    double g_radial;       /* log g also holds radial terms: cubic B-splines of the distance
                              from the star, centred every g_radial lambda/D (at least one
                              pixel), each with the Legendre terms' prior s_beta. The share of
                              the true speckle field a computed one holds changes at circles
                              (the loop's control radius, the sensor's band edge) a low-order
                              polynomial cannot follow; 3 (docs/estimator.md: the table over
                              the matrix, the foreign observations and the paper's case; at
                              1 the terms resolve the Airy rings and trade with Psi); <= 0:
                              none (Legendre terms alone, the fit before 0.3.0) */
} swfs_jointfit_options;

void swfs_jointfit_options_default(swfs_jointfit_options *o);

typedef struct swfs_jointfit_result {
    swfs_cplx *field;      /* pupil field W, PUPN x PUPN, 0 outside the pupil */
    swfs_real *wfe;        /* [m] lambda/(2 pi) phi, piston removed in the pupil, 0 outside */
    swfs_real *mask;       /* pupil used */
    swfs_cplx *halo;       /* Psi = MFT(W) over the window [sqrt(counts)] in the frame of the
                              regression (psi centred on its mean, eq:zeroMean) */
    swfs_real *gain;       /* g per pixel, exp(sum beta_m P_p P_q) */
    double kappa;
    double lambda_phi, lambda_alpha; /* final prior weights */
    double gamma_phi, gamma_alpha;   /* well-determined parameter counts (evidence) */
    double chi2;           /* sum_k (theta - theta_hat)^T F (theta - theta_hat) at the end */
    double cost;           /* chi2 + prior terms */
    size_t npix;           /* focal pixels used (valid in the regression) */
    size_t nintervals;     /* B-spline intervals across D */
    size_t nbasis;         /* B-splines kept (support meets the pupil) */
    size_t nparams;        /* 2 nbasis + Legendre terms + 1 */
    int iterations;        /* Levenberg-Marquardt iterations (accepted steps) */
    int evaluations;       /* model evaluations */
    double seconds;        /* wall time of swfs_jointfit */
    double wfe_rms;        /* [m] piston removed */
    int intercept;         /* SWFS_JF_INTERCEPT_MODEL or _FREE: the one this result used */
    double delta_chi2;     /* AUTO: (chi2(model) - chi2(free intercept)) x the free fit's
                              noise_scale; NaN otherwise */
    double delta_chi2_limit; /* AUTO: the test's rejection threshold; NaN otherwise */
    double noise_scale;    /* beta: the data's weight by the evidence, (rows - gamma) / chi2;
                              1 = the statistics' own errors; 1 with fixed prior weights */
    int model_stopped;     /* AUTO: 1 if the intercept model's fit was stopped once its chi2
                              could no longer come within the limit in the iterations left
                              (delta_chi2 is then where it stopped, above its converged value,
                              and the free intercept is kept); 0 otherwise */
    /* Stage 1 is run twice, the evidence rule from the start and after a run to convergence at
     * the start's prior weights (a warm start), and the fixed point of the larger log evidence
     * (Laplace's approximation, constants dropped) is kept. Appended in 0.9.0. */
    int warm_start;          /* 1: the warm start's fixed point was kept */
    double log_evidence;     /* the kept fixed point's; NaN for a model fit stopped early and
                                where both prior weights are given (run once) */
    double log_evidence_alt; /* the other's (-inf where its H + lambda R was not positive definite) */
} swfs_jointfit_result;

/* sol: swfs_regress_solve over the focal window of the geometry g (PIXSCALE, PUPDX, TELDIAM,
 * PUPN, WAVELEN); mask: PUPN x PUPN pupil, or NULL for the annulus of TELDIAM/OBSCUR. */
int swfs_jointfit(const swfs_regress_sol *sol, const swfs_geom *g, const swfs_real *mask,
                  const swfs_jointfit_options *opt, swfs_jointfit_result **out);
void swfs_jointfit_result_free(swfs_jointfit_result *r);

SWFS_END_DECLS

#endif

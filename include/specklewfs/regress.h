/* Streaming per-pixel regression statistics for the random-reference estimator
 * (docs/estimator.md, Stage 1).
 *
 * Per pixel and frame the science intensity I is regressed on the computed speckle field
 * psi with the model of eq:betterIModel plus an intercept:
 *
 *   I = a + b |p|^2 + 2 Re(c^* p) + noise,   p = psi - c0,
 *   a = |Psi|^2 + incoherent power,  b = g^2,  c = g Psi       (in the frame c0 = <psi>)
 *
 * i.e. regressors x = (1, |p|^2, 2 Re p, 2 Im p). We keep the weighted Gram matrix
 * G = sum w x x^T (10 unique entries), h = sum w x I, yy = sum w I^2, the plain sum of p
 * and the frame count n. These are plain sums: chunks merge by addition. c0 is a
 * provisional centre per pixel (the first frame's psi, or whatever swfs_regress_recenter
 * set); two accumulators with different centres are reconciled exactly by the change of
 * variables x_old = T(delta) x_new, delta = c_new - c_old,
 *
 *   T(delta) = [[1,0,0,0], [|delta|^2,1,Re delta,Im delta], [2 Re delta,0,1,0], [2 Im delta,0,0,1]]
 *
 * so G_new = T^-1 G T^-T, h_new = T^-1 h, T^-1 = T(-delta). Memory: SWFS_REGRESS_NSTATE
 * doubles per pixel whatever the number of frames; nothing is allocated per frame.
 *
 * The solution (swfs_regress_solve) is expressed in the frame centred on the sample mean
 * of psi, which is the paper's psi' = psi - <psi> (eq:zeroMean): theta = (a, b, Re c, Im c),
 * s^2 = (yy - theta^T h) / nu with nu = n - 4, information F = G / s^2 (nu - 2) / nu,
 * f = h / s^2 (nu - 2) / nu (so that theta^T F theta - 2 theta^T f is, up to a constant, the
 * chi-square of a model theta): (nu - 2) / nu makes F the inverse of the covariance of the
 * Student t that theta follows with s^2 estimated, so a pixel seen in few frames does not
 * carry the information of a noise estimate it does not have; pixels with n <= 6 are not
 * solved.
 *
 * Non-finite science values skip that pixel-frame (counted); non-finite psi is an error
 * (the accumulator is left unchanged). */
#ifndef SWFS_REGRESS_H
#define SWFS_REGRESS_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/array.h"

SWFS_BEGIN_DECLS

/* The raw state: plane f of pixel k is state[f * nx * ny + k] (FITS order: a checkpoint is
 * an nx x ny x SWFS_REGRESS_NSTATE cube). G entries are the upper triangle row by row. */
enum {
    SWFS_REG_N,                  /* frames used (finite science) */
    SWFS_REG_CSET,               /* 1 once the centre is set (first frame or recenter) */
    SWFS_REG_C0RE, SWFS_REG_C0IM, /* provisional centre c0 (meaningful when n > 0) */
    SWFS_REG_SRE, SWFS_REG_SIM,  /* sum of p = psi - c0 (unweighted) */
    SWFS_REG_G00, SWFS_REG_G01, SWFS_REG_G02, SWFS_REG_G03, /* sum w x x^T */
    SWFS_REG_G11, SWFS_REG_G12, SWFS_REG_G13,
    SWFS_REG_G22, SWFS_REG_G23,
    SWFS_REG_G33,
    SWFS_REG_H0, SWFS_REG_H1, SWFS_REG_H2, SWFS_REG_H3, /* sum w x I */
    SWFS_REG_YY,                 /* sum w I^2 */
    SWFS_REGRESS_NSTATE
};

typedef struct swfs_regress {
    size_t nx, ny;
    double *state;     /* SWFS_REGRESS_NSTATE planes of nx*ny (see the enum) */
    uint64_t frames;   /* frames offered */
    uint64_t skipped;  /* pixel-frames skipped for non-finite science */
} swfs_regress;

swfs_regress *swfs_regress_create(size_t nx, size_t ny);
void swfs_regress_free(swfs_regress *r);
void swfs_regress_reset(swfs_regress *r);

/* One synchronized frame. science: nx*ny counts; psi: nx*ny complex values as interleaved
 * (re, im) doubles (a swfs_complex array cast to const double *); weights: nx*ny
 * weights w > 0 (e.g. 1 / (read_noise^2 + max(mu, 0)/gain) from a previous fit), or NULL
 * for w = 1. A pixel whose weight is not finite and > 0 is skipped like a bad science value. */
int swfs_regress_add(swfs_regress *r, const double *science, const double *psi, const double *weights);
/* dst += src (disjoint frame sets): exactly the statistics of the union, re-centring src
 * onto dst's centres where they differ (pixels empty in dst take src's centre). */
int swfs_regress_merge(swfs_regress *dst, const swfs_regress *src);
/* Move every pixel's provisional centre to centre (nx*ny interleaved complex), or to the
 * pixel's own mean psi when centre is NULL. Exact (the change of variables above). */
int swfs_regress_recenter(swfs_regress *r, const double *centre);

/* Raw state as one flat array of nx*ny*SWFS_REGRESS_NSTATE doubles (layout above); frames
 * and skipped travel separately (they are public fields). Import checks that counts are
 * finite and >= 0 and that G's diagonal is >= 0. */
void swfs_regress_export(const swfs_regress *r, double *state);
int swfs_regress_import(swfs_regress *r, const double *state);

/* Relative ridge added to the c-block diagonal: keeps the phase-reference pixel (Im psi = 0
 * in every frame) solvable without changing well-conditioned pixels. */
#define SWFS_REGRESS_RIDGE 1e-9

/* Per-pixel solution, in the frame centred on each pixel's mean psi. */
typedef struct swfs_regress_sol {
    size_t nx, ny;
    swfs_real *theta;   /* nx x ny x 4: a, b, Re c, Im c */
    swfs_real *info;    /* nx x ny x 10: F = G / s^2 (nu - 2) / nu, upper triangle row by row */
    swfs_real *rhs;     /* nx x ny x 4: f = h / s^2 (nu - 2) / nu */
    swfs_real *s2;      /* residual variance per unit weight */
    swfs_real *phi_sp;  /* weighted mean of |psi - <psi>|^2 (Phi_sp of eq:betterMean) */
    swfs_cplx *centre;  /* <psi>, the frame of theta */
    swfs_real *valid;   /* 1 where solved (n > 6, G positive definite, s^2 > 0) */
    size_t n_valid;
    /* The self-check of the computed speckles: the fraction of the science intensity's
     * variance about its mean that the regression on them explains, 1 - SSE / SST, summed
     * over the valid pixels (dominated by the bright ones) and the median pixel's. */
    double explained, explained_median;
    swfs_real *r2;      /* per pixel 1 - SSE / SST, NaN where not solved or the intensity is constant */
} swfs_regress_sol;

int swfs_regress_solve(const swfs_regress *r, swfs_regress_sol **out);
void swfs_regress_sol_free(swfs_regress_sol *s);

SWFS_END_DECLS

#endif

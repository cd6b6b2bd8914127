/* Streaming, mergeable per-pixel accumulators for the random-reference estimator.
 *
 * Per pixel and per frame we see the science intensity I and the computed speckle field
 * psi = x + i y. We keep, per pixel, the count n, the means of v = (I, x, y, A = |psi|^2)
 * and the co-moment matrix C_ab = sum (v_a - mean_a)(v_b - mean_b), updated with Welford's
 * centered recurrence and merged with Chan et al.'s pairwise formula. Every statistic of
 * the paper follows exactly from these, with the reference-beam mean removed over the
 * data set (eq:zeroMean): with psi' = psi - <psi>,
 *   <psi' I>      = Cov(x, I) + i Cov(y, I)                       (eq:stabilized)
 *   Phi_sp        = <|psi'|^2> = Var x + Var y
 *   sigma_sp^2    = Var |psi'|^2, a quadratic form in C(A, x, y) and the mean of psi
 *   <psi'^2>      = Var x - Var y + 2i Cov(x, y)                  (eq:zeroSqMean)
 * Memory is 15 doubles per pixel whatever the number of frames. Two accumulators over
 * disjoint frame sets merge into the accumulator of their union (to rounding).
 * Non-finite science values skip that pixel-frame (counted); speckles must be finite.
 *
 * Every accumulator also carries the regression statistics of regress.h (reg, 21 doubles per
 * pixel), updated by the same add and merged by the same merge, so that the joint fit
 * (jointfit.h) is available wherever the moments are: estimate, stream, merge, checkpoints.
 * reg->frames == frames says the two saw the same frames (a checkpoint from before the
 * regression statistics existed loads with reg empty, and merging it makes them differ). */
#ifndef SWFS_ACCUM_H
#define SWFS_ACCUM_H

#include "specklewfs/defs.h"
#include "specklewfs/regress.h"

#include <stddef.h>
#include <stdint.h>

SWFS_BEGIN_DECLS

enum {
    SWFS_ACC_N, /* count */
    SWFS_ACC_MI, SWFS_ACC_MX, SWFS_ACC_MY, SWFS_ACC_MA, /* means */
    SWFS_ACC_CII, SWFS_ACC_CIX, SWFS_ACC_CIY, SWFS_ACC_CIA, /* co-moments */
    SWFS_ACC_CXX, SWFS_ACC_CXY, SWFS_ACC_CXA, SWFS_ACC_CYY, SWFS_ACC_CYA, SWFS_ACC_CAA,
    SWFS_ACC_NFIELDS
};

typedef struct swfs_accum {
    size_t nx, ny;
    /* Structure of arrays: field f of pixel p is f_[f][p]; npix = nx * ny. */
    double *f[SWFS_ACC_NFIELDS];
    uint64_t frames;        /* frames offered */
    uint64_t skipped;       /* pixel-frames skipped for non-finite science values */
    swfs_regress *reg;      /* regression statistics of the same frames (owned) */
} swfs_accum;

swfs_accum *swfs_accum_create(size_t nx, size_t ny);
void swfs_accum_free(swfs_accum *a);
void swfs_accum_reset(swfs_accum *a);

/* One synchronized frame: science (nx*ny counts) and psi (nx*ny complex). Allocation-free. */
int swfs_accum_add(swfs_accum *a, const double *science, const swfs_complex *psi);
/* dst += src (disjoint frame sets), exactly the accumulator of the union. */
int swfs_accum_merge(swfs_accum *dst, const swfs_accum *src);
/* 1 when the regression statistics cover exactly the frames the moments do. */
int swfs_accum_has_regress(const swfs_accum *a);

/* The whole state as one flat array of doubles, for transport (MPI, shared memory, files):
 * the 15 moment planes, then the SWFS_REGRESS_NSTATE regression planes (each nx*ny, FITS
 * order), then frames, skipped, reg->frames, reg->skipped (exact as doubles below 2^53). */
size_t swfs_accum_state_len(size_t nx, size_t ny);
void swfs_accum_export(const swfs_accum *a, double *state);
/* Import a state exported by an accumulator of the same size; checks that counts are
 * whole, >= 0 and at most the frames offered, and variances >= 0. */
int swfs_accum_import(swfs_accum *a, const double *state);
/* dst_state += src_state on flat states of nx x ny pixels (exactly swfs_accum_merge),
 * without allocating: usable as a reduction operator. */
int swfs_accum_merge_state(double *dst_state, const double *src_state, size_t nx, size_t ny);

SWFS_END_DECLS

#endif

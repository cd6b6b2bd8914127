/* The generic linear speckle model: any AO system's telemetry (paper Sec. 4.4 without the
 * Shack-Hartmann).
 *
 * Per WFS frame the residual wavefront on the pupil grid is a linear function of the
 * frame's telemetry vector v:
 *
 *     z = scale * B (A v)                       [m of wavefront OPD]
 *
 * with B the nk basis functions on the pupil grid (mode shapes, e.g. cacao's DMmodes, or
 * one influence function per actuator) and A the nk x nmeas control matrix into their
 * coefficients (pyramid signals, Shack-Hartmann slopes in any layout, ... times the
 * system's control matrix), or no A at all when v already holds the coefficients (cacao's
 * WFS-measured residual modal coefficients, modevalWFS). scale turns the coefficients into
 * metres of wavefront: cacao's modes are unit rms of DM surface and its coefficients are
 * in um, so scale = 2e-6 (a reflective DM changes the wavefront by twice its surface).
 *
 * The basis is given on the pupil grid itself (PUPN x PUPN x nk) or on the DM's own grid
 * (gx x gy x nk), which the registration below places on the pupil; the DM grid is
 * resampled onto the pupil grid by cubic convolution (Keys, a = -1/2: exact for quadratics,
 * continuous slopes). swfs_pipeline_create_linear (pipeline.h) turns the model into
 * focal-plane speckles. */
#ifndef SWFS_LMODEL_H
#define SWFS_LMODEL_H

#include <stddef.h>

#include "specklewfs/sparse.h"

SWFS_BEGIN_DECLS

/* Where the DM grid lies on the pupil (a site-specific calibration). The DM grid point
 * (i, j), 0-based, i along FITS NAXIS1, sits at
 *     d = ((i - (gx-1)/2) pitch, (j - (gy-1)/2) pitch), mirrored in x first when flip_x,
 *     x = (x0, y0) + Rot(rot) d
 * in the pupil frame of docs/conventions.md. */
typedef struct swfs_dm_registration {
    double pitch;   /* [m] on the pupil per DM-grid step (> 0) */
    double x0, y0;  /* [m] the pupil position of the grid's centre */
    double rot;     /* [rad] counter-clockwise */
    int flip_x;     /* 1: the grid's x axis mirrored before the rotation */
} swfs_dm_registration;

/* A pitch of 0 marks "not given". */
void swfs_dm_registration_default(swfs_dm_registration *r);
/* The pupil position (x, y) [m] of DM grid point (u, v) (fractional allowed), and back. */
void swfs_dm_to_pupil(const swfs_dm_registration *r, size_t gx, size_t gy, double u, double v, double *x, double *y);
void swfs_pupil_to_dm(const swfs_dm_registration *r, size_t gx, size_t gy, double x, double y, double *u, double *v);

/* The basis from a cube on the DM grid: B (npup^2 x nk, CSR, exact zeros dropped) holds
 * basis function k at every illuminated pupil sample (mask > 0; other rows are empty),
 * interpolated from cube[k gx gy + j gx + i] by cubic convolution. A sample whose stencil
 * leaves the grid takes the grid's edge values; an illuminated sample more than one grid
 * step outside the grid is counted in *n_outside (the caller decides: the registration or
 * the grid does not describe the pupil). */
int swfs_basis_from_grid(swfs_sparse **B, const double *cube, size_t gx, size_t gy, size_t nk,
                         const swfs_dm_registration *reg, const double *mask, size_t npup, double pupdx,
                         size_t *n_outside);
/* The same resampling as an operator: T (npup^2 x gx gy, CSR) interpolates values on the DM
 * grid (point (i, j) at column j gx + i) onto the illuminated pupil samples, at most 16
 * nonzeros per row, so basis function k on the pupil is T times its grid values. A linear
 * model keeps the basis in this factored form (swfs_linear_input.shapes): per frame one small
 * GEMM on the grid and a sparse product, instead of a dense product per pupil sample and mode.
 * *n_outside as swfs_basis_from_grid. */
int swfs_grid_interp(swfs_sparse **T, size_t gx, size_t gy, const swfs_dm_registration *reg, const double *mask,
                     size_t npup, double pupdx, size_t *n_outside);
/* The basis given on the pupil grid itself (npup x npup x nk). */
int swfs_basis_from_pupil(swfs_sparse **B, const double *cube, size_t npup, size_t nk, const double *mask);

SWFS_END_DECLS

#endif

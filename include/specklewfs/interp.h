/* Scattered-point -> grid interpolation: Delaunay triangulation (qhull) with the
 * Clough-Tocher C1 piecewise-cubic element (Farin's modified form, the normal
 * derivative linear along every edge), precomputed once as a sparse matrix.
 *
 * Paper Sec. 4.4: the wavefront displacements reconstructed at the actuators are
 * "interpolated ... to a 4 cm square grid using Delaunay triangularization and cubic
 * interpolation". Each frame is then one sparse product z_grid = T z_act.
 *
 * Vertex gradients come from a local least-squares quadratic fit over the vertex's
 * Delaunay neighbours (1-ring, widened to the 2-ring when it holds fewer than 6 points),
 * so the whole operator is linear in the point values and exact for every quadratic
 * polynomial inside the convex hull (planes included). Query points outside the hull get
 * an empty row (value 0). */
#ifndef SWFS_INTERP_H
#define SWFS_INTERP_H

#include <stddef.h>

#include "specklewfs/sparse.h"

SWFS_BEGIN_DECLS

/* T: nq x npts, row q = weights of the data points for query point (qx[q], qy[q]).
 * pts: npts (x, y) pairs [m]. *n_outside (may be NULL): query points outside the hull. */
int swfs_interp_ct_points(const double *pts, size_t npts, const double *qx, const double *qy,
                          size_t nq, swfs_sparse **out, size_t *n_outside);

/* The same on the square pupil grid of docs/conventions.md, x = (p - (npup-1)/2) * pupdx, rows in
 * FITS order (p fastest). mask (npup*npup, may be NULL): rows where mask <= 0 are left
 * empty and do not count as outside. */
int swfs_interp_ct_grid(const double *pts, size_t npts, size_t npup, double pupdx,
                        const double *mask, swfs_sparse **out, size_t *n_outside);

/* Illuminated samples outside the points' hull (empty rows of T from swfs_interp_ct_grid, mask
 * > 0) take the row of the nearest sample inside it when that lies within `reach` [m]: the
 * wavefront continued flat across a rim the actuators do not quite cover. *n_extrap: rows
 * filled; *n_far: samples farther than reach, left empty. T is replaced. */
int swfs_interp_extend_rim(swfs_sparse **T, size_t npup, double pupdx, const double *mask, double reach,
                           size_t *n_extrap, size_t *n_far);
/* A DM of Gaussian influence functions on the same grid: row k holds exp(-ln(1/c) r^2 / d^2)
 * of each actuator within reach of sample k, r its distance, d the actuators' pitch
 * (swfs_points_pitch) and c the coupling (0 < c < 1: the surface one actuator's command makes
 * at its neighbour; weights under 1e-3 left out). Unlike swfs_interp_ct_grid the surface does
 * not pass through the commands: a command moves its neighbours too, as a continuous
 * facesheet's actuators do. mask as above. */
int swfs_influence_gauss_grid(const double *pts, size_t npts, size_t npup, double pupdx, const double *mask,
                              double coupling, swfs_sparse **out);
/* The median distance from each point to its nearest neighbour (the actuator pitch). */
double swfs_points_pitch(const double *pts, size_t npts);

SWFS_END_DECLS

#endif

/* Telescope pupil masks and Zernike polynomials on the pupil grid of docs/conventions.md:
 * sample (p, q) sits at x = (p - (n-1)/2) dx, y = (q - (n-1)/2) dx, x fastest. */
#ifndef SWFS_APERTURE_H
#define SWFS_APERTURE_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

/* Binary (0/1) annular pupil with optional spiders, evaluated at the sample centres:
 *   1 where obscur*diam/2 <= r <= diam/2 and the sample is not under a spider.
 * Spider k (k = 0 .. nspiders-1) is a vane of full width spider_width [m] from the centre
 * outward at angle 2 pi k / nspiders from +x (toward +y); a sample is blocked when its
 * distance to the vane's half-line is <= spider_width/2. mask is n*n.
 * Binary rather than grey so that the pupil is exactly the set the NCP map and the
 * estimator's pupil products are evaluated on. */
int swfs_aperture_make(double *mask, size_t n, double dx, double diam, double obscur, int nspiders,
                       double spider_width);

/* Zernike polynomial, NOT Noll-normalized: Z_n^m(rho, theta) = R_n^|m|(rho) cos(m theta) for
 * m >= 0 and R_n^|m|(rho) sin(|m| theta) for m < 0, with R_n^m(1) = 1, so the peak value on
 * the unit circle is 1. E.g. trefoil Z_3^3 = rho^3 cos 3 theta (paper Sec. 3:
 * dz = Z_3^3(2r/D, theta) lambda/16). n >= |m|, n - |m| even; otherwise NaN.
 * rho > 1 is evaluated as the polynomial (no clipping). */
double swfs_zernike(int n, int m, double rho, double theta);

/* Noll index j >= 1 -> (n, m) with the sign convention above (even j: cos, odd j: sin,
 * m = 0 for the radial terms). Returns 0, or SWFS_ERR_ARG for j < 1. */
int swfs_zernike_noll(int j, int *n, int *m);

SWFS_END_DECLS

#endif

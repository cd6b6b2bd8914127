/* Internal to the joint fit (jointfit.c): the cubic B-spline basis on the pupil grid, its
 * gradient penalty, the Jacobian of the focal field with respect to the log-field
 * coefficients, and the 2-D Legendre basis of log g over the window. */
#ifndef SWFS_JOINTFIT_BASIS_H
#define SWFS_JOINTFIT_BASIS_H

#include <complex.h>
#include <stddef.h>

typedef struct jf_basis {
    size_t n;            /* pupil samples across */
    size_t nfx, nfy;     /* focal window */
    size_t nint;         /* intervals across D */
    size_t na;           /* 1-D functions per axis (nint + 3) */
    double h;            /* knot spacing [pupil samples] */
    double *b1;          /* na x n: 1-D B-spline values on the pupil samples (x and y alike) */
    size_t *lo, *len;    /* support of each 1-D function: samples [lo, lo + len) */
    size_t *near;        /* 2 na work: the 1-D functions a stencil at a sample meets (penalty) */
    double *pw;          /* na^2 + 2 na work: a row's 1-D sums and stencil values (penalty) */
    size_t nb;           /* 2-D functions kept (support meets the pupil) */
    long *idx;           /* na x na (b * na + a, a along x): index of (a, b) or -1 */
    size_t *ja, *jb;     /* per kept function: its a and b */
    double *R;           /* nb x nb gradient penalty */
    double complex *axa; /* per a: nfx x len[a], Ax(i, p) b1[a][p] (exp(-) MFT matrix) */
    double complex *ayb; /* per b: nfy x len[b] */
    size_t *off;         /* offset of function a's block in axa/ayb */
    double complex *xa;  /* n x nfx work */
} jf_basis;

/* mask: n x n pupil; alpha = PIXSCALE * PUPDX / TELDIAM; diam_samples = TELDIAM / PUPDX. */
jf_basis *jf_basis_create(const double *mask, size_t n, double diam_samples, size_t nint, size_t nfx, size_t nfy,
                          double alpha);
void jf_basis_free(jf_basis *b);
/* Fill R: gradient (curvature = 0) or thin-plate curvature (1) penalty. */
void jf_basis_penalty(jf_basis *b, const double *mask, int curvature);
/* Z(p, q) = sum_j z_j B_j on the n x n grid. */
void jf_basis_eval(const jf_basis *b, const double complex *z, double complex *Z);
/* Least-squares projection is never needed: the basis is a partition of unity, so a
 * constant field is z_j = const. */

/* Jacobian rows for the field W (n x n): row j (0 <= j < nb) of yt holds dPsi/d alpha_j as
 * nfx*nfy interleaved complex values, row nb + j holds dPsi/d phi_j = i dPsi/d alpha_j.
 * yt is (2 nb) x (2 nfx nfy) doubles, row-major. */
void jf_jacobian(jf_basis *b, const double complex *W, double *yt);

/* 2-D Legendre values: nl = (order + 1)(order + 2)/2 terms, out is nl x (nfx nfy). u and v
 * run over [-1, 1] across box = {x0, x1, y0, y1} (pixels, inclusive; the whole window is
 * {0, nfx - 1, 0, nfy - 1}) and are held at +-1 beyond it. */
size_t jf_legendre_count(int order);
void jf_legendre(int order, size_t nfx, size_t nfy, const size_t box[4], double *out);

/* Radial terms: uniform cubic B-splines of the distance from the star's pixel (floor(nfx/2),
 * floor(nfy/2)), centred every h pixels from 0 to rmax (pixels; the farthest pixel fitted)
 * and one beyond; jf_radial_count gives their number, jf_radial fills out
 * (count x (nfx nfy)). */
size_t jf_radial_count(double h, double rmax);
void jf_radial(double h, double rmax, size_t nfx, size_t nfy, double *out);

#endif

/* Matrix Fourier transform (Soummer et al. 2007) between a square pupil grid and a
 * small focal window, with the sign and sampling conventions of docs/conventions.md:
 *
 *   focal(i, j) = sum_{p,q} pupil(p, q) exp(-2 pi i alpha [(i - nfx/2) u_p + (j - nfy/2) u_q])
 *   u_p = p - (npup - 1)/2,   alpha = PIXSCALE * PUPDX / TELDIAM
 *
 * (integer division nfx/2 = floor(W/2): the star sits on pixel (W/2, H/2)). alpha is the
 * number of cycles across one pupil sample per focal pixel; 1/alpha is the equivalent
 * FFT size. Two GEMMs per transform (CBLAS cgemm in single precision, zgemm in double):
 * focal = Ay * pupil * Ax^T in row-major terms. A plan owns its matrices and one work
 * buffer, so it is not shared between threads: create one per worker.
 *
 * The inverse is the adjoint (exp(+...)) without normalization:
 *   pupil(p, q) = sum_{i,j} focal(i, j) exp(+2 pi i alpha [...])
 * Multiply by alpha^2 to undo a forward transform whose window covers the full field. */
#ifndef SWFS_MFT_H
#define SWFS_MFT_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

enum { SWFS_MFT_DOUBLE = 0, SWFS_MFT_SINGLE = 1 };

typedef struct swfs_mft swfs_mft;

swfs_mft *swfs_mft_create(size_t npup, size_t nfx, size_t nfy, double alpha, int precision);
void swfs_mft_free(swfs_mft *m);
size_t swfs_mft_npup(const swfs_mft *m);
size_t swfs_mft_nfx(const swfs_mft *m);
size_t swfs_mft_nfy(const swfs_mft *m);

/* Double-precision interface (a SINGLE plan converts internally). */
int swfs_mft_forward(swfs_mft *m, const swfs_complex *pupil, swfs_complex *focal);
int swfs_mft_inverse(swfs_mft *m, const swfs_complex *focal, swfs_complex *pupil);
/* Single-precision interface (SINGLE plans only): no conversion, the fast path. */
int swfs_mft_forward_f(swfs_mft *m, const swfs_complexf *pupil, swfs_complexf *focal);

SWFS_END_DECLS

#endif

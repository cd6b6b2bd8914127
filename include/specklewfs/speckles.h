/* Speckle cubes from WFS telemetry (paper Sec. 4.4): the pieces around the per-frame
 * engine (engine.h) that turn a reconstructor, actuator positions and a timing table into
 * the speckle field psi matching the science frames (eq:downsampledHalo,
 * eq:computedSpeckleField). The CLI `specklewfs speckles` drives them. */
#ifndef SWFS_SPECKLES_H
#define SWFS_SPECKLES_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/sparse.h"
#include "specklewfs/wfs.h"

enum { SWFS_MEAN_ENSEMBLE = 0, SWFS_MEAN_CUBE = 1 };

/* eq:computedSpeckleField: psi = down-sampled halo - static halo. The static halo is the
 * ensemble average over every frame of the cube (the paper's choice: its estimation
 * error is a constant across the pupil) or, with SWFS_MEAN_CUBE, the mean of each
 * camera cube (frames [first[c], first[c] + n[c]) of the array). In place. */
int swfs_speckles_subtract_static(swfs_cplx *halo, const size_t *first, const size_t *n, size_t ncubes, int mode);

/* Everything the engine needs on the pupil grid, built from the actuator positions:
 * the Clough-Tocher interpolation T (interp.h), the Shack-Hartmann model for nsub x nsub
 * subapertures, and the reconstructor -- loaded (recon != NULL, checked against nact
 * and 2 nsub^2 slopes) or built as the truncated SVD pseudo-inverse of D = S T (rcond,
 * max_modes: the "better reconstructor" of Sec. 4.4). With remove_tiptilt the
 * reconstructor is projected to ignore the mean x/y slopes over the valid subapertures
 * (swfs_recon_project_tiptilt), exactly the paper's tip-tilt removal. */
typedef struct swfs_speckle_model {
    size_t npup, nact, nslopes;
    double *mask;          /* npup^2 */
    swfs_sparse *T;        /* npup^2 x nact */
    swfs_shwfs *wfs;
    swfs_recon *recon;     /* nact x nslopes */
    size_t n_outside;      /* illuminated samples outside the actuators' hull (left at 0) */
} swfs_speckle_model;

int swfs_speckle_model_create(swfs_speckle_model **out, const double *xy, size_t nact, const double *mask,
                              size_t npup, double pupdx, double teldiam, size_t nsub, const swfs_recon *recon,
                              double rcond, size_t max_modes, int remove_tiptilt);
void swfs_speckle_model_free(swfs_speckle_model *m);

#endif

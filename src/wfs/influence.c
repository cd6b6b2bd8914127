/* A DM of Gaussian influence functions on the pupil grid (interp.h): the surface a command
 * vector makes, as the sparse operator the simulator's loop applies each frame. */
#include "specklewfs/interp.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>

/* Weights below this fraction of an influence function's peak are left out (its support then
 * reaches sqrt(ln(1/SWFS_INFL_TAIL) / ln(1/c)) pitches: 1.9 at a coupling of 0.15). */
#define SWFS_INFL_TAIL 1e-3

int swfs_influence_gauss_grid(const double *pts, size_t npts, size_t npup, double pupdx, const double *mask,
                              double coupling, swfs_sparse **out)
{
    *out = NULL;
    if (npup == 0 || !(pupdx > 0)) return swfs_fail(SWFS_ERR_ARG, "pupil grid %zu x %g m is empty", npup, pupdx);
    if (!(coupling > 0 && coupling < 1))
        return swfs_fail(SWFS_ERR_VALUE, "Gaussian influence functions: coupling %g; expected 0 < c < 1 (the surface "
                         "one actuator's command makes at its neighbour, a fraction of its own)", coupling);
    if (npts < 2) return swfs_fail(SWFS_ERR_ARG, "Gaussian influence functions: %zu actuators (at least 2)", npts);
    const double pitch = swfs_points_pitch(pts, npts);
    if (!(pitch > 0)) return swfs_fail(SWFS_ERR_VALUE, "Gaussian influence functions: the actuators' pitch is %g m "
                                       "(two actuators at one place?)", pitch);
    const double a = log(1.0 / coupling) / (pitch * pitch), r2max = log(1.0 / SWFS_INFL_TAIL) / a;
    const size_t n = npup * npup;
    /* two passes over the samples in the pupil: count, then fill */
    size_t nnz = 0;
    for (int pass = 0; pass < 2; pass++) {
        swfs_sparse *T = pass ? swfs_sparse_alloc(n, npts, nnz) : NULL;
        if (pass && !T) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        size_t e = 0;
        for (size_t k = 0; k < n; k++) {
            if (!mask || mask[k] > 0) {
                const double x = ((double)(k % npup) - 0.5 * (double)(npup - 1)) * pupdx,
                             y = ((double)(k / npup) - 0.5 * (double)(npup - 1)) * pupdx;
                for (size_t j = 0; j < npts; j++) {
                    const double dx = x - pts[2 * j], dy = y - pts[2 * j + 1], r2 = dx * dx + dy * dy;
                    if (r2 > r2max) continue;
                    if (pass) {
                        T->col[e] = j;
                        T->val[e] = exp(-a * r2);
                    }
                    e++;
                }
            }
            if (pass) T->row_ptr[k + 1] = e;
        }
        if (pass) *out = T;
        else nnz = e;
    }
    return SWFS_OK;
}

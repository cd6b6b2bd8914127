/* The camera's orientation relative to the model's focal plane (sync.h): the pairing `sync`
 * finds by correlating the star's track with the mean slopes says which camera axis follows
 * which slope axis and with which sign. The speckles are computed in the model's frame
 * (docs/conventions.md's sign and sampling); the science frames are brought into that frame, so the
 * halo, the pupil field and the DM offsets are all in the frame of the WFS and the DM.
 *
 * Model pixel (cx + u, cy + v), (cx, cy) = (nx/2, ny/2) the star, shows what the camera has
 * at (cx + a, cy + b): a = sx u, b = sy v (straight), a = sx v, b = sy u (swapped, a
 * transposed camera: square frames only). Pixels the camera did not see are NaN, which the
 * estimator skips. */
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <math.h>
#include <stdio.h>

int swfs_orient_is_identity(const swfs_sync_result *p)
{
    return !p->swap && p->sign_x >= 0 && p->sign_y >= 0;
}

int swfs_orient_check(const swfs_sync_result *p, size_t nx, size_t ny, const char *what)
{
    if ((p->sign_x != 1 && p->sign_x != -1) || (p->sign_y != 1 && p->sign_y != -1) || (p->swap != 0 && p->swap != 1))
        return swfs_fail(SWFS_ERR_VALUE, "%s: camera pairing swap %d, signs %d %d: expected swap 0 or 1 and signs +-1",
                         what, p->swap, p->sign_x, p->sign_y);
    if (p->swap && nx != ny)
        return swfs_fail(SWFS_ERR_SHAPE,
                         "%s: the camera is transposed relative to the model (its x follows the y slopes) but its "
                         "frames are %zux%zu; re-orienting them needs square frames (crop the science cube square)",
                         what, nx, ny);
    return SWFS_OK;
}

void swfs_orient_describe(const swfs_sync_result *p, char *buf, size_t cap)
{
    snprintf(buf, cap, "SWAP=%d SX=%+d SY=%+d", p->swap, p->sign_x, p->sign_y);
}

void swfs_orient_frame(const swfs_sync_result *p, size_t nx, size_t ny, size_t comps, const double *cam, double *model)
{
    const long cx = (long)(nx / 2), cy = (long)(ny / 2);
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            const long u = (long)i - cx, v = (long)j - cy;
            const long a = cx + p->sign_x * (p->swap ? v : u), b = cy + p->sign_y * (p->swap ? u : v);
            double *o = model + (j * nx + i) * comps;
            if (a < 0 || b < 0 || a >= (long)nx || b >= (long)ny) {
                for (size_t c = 0; c < comps; c++) o[c] = NAN;
                continue;
            }
            const double *s = cam + ((size_t)b * nx + (size_t)a) * comps;
            for (size_t c = 0; c < comps; c++) o[c] = s[c];
        }
}

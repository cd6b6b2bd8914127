/* pupil A.fits B.fits ...: halo files scored by the self-check (run.h swfs_halo_choose_files,
 * pupil.h swfs_halo_choose; docs/telemetry.md, "The self-check as the choice"). */
#include "specklewfs/run.h"
#include "specklewfs/pupil.h"

#include <stdlib.h>

int swfs_halo_choose_files(const char *const *paths, size_t n, double *explained, size_t *best, size_t *ncommon,
                           swfs_halo **chosen, swfs_geom *geom)
{
    if (chosen) *chosen = NULL;
    swfs_halo **hs = calloc(n ? n : 1, sizeof *hs);
    swfs_geom *gs = calloc(n ? n : 1, sizeof *gs);
    int rc = hs && gs ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "choosing speckles: out of memory for %zu halos", n);
    for (size_t k = 0; !rc && k < n; k++) rc = swfs_halo_read(paths[k], &hs[k], &gs[k]);
    /* halos of the same frames share their geometry: one of the same window that says another
     * wavelength or sampling is not of these frames, and its pupil would be another's (another
     * window: swfs_halo_choose says so) */
    for (size_t k = 1; !rc && k < n; k++)
        if (hs[k]->nx == hs[0]->nx && hs[k]->ny == hs[0]->ny)
            rc = swfs_geom_check_same(&gs[0], paths[0], &gs[k], paths[k]);
    if (!rc) rc = swfs_halo_choose((const swfs_halo *const *)hs, paths, n, explained, best, ncommon);
    if (!rc && chosen) { /* the caller keeps the chosen halo, read once */
        *chosen = hs[*best];
        if (geom) *geom = gs[*best];
        hs[*best] = NULL;
    }
    for (size_t k = 0; hs && k < n; k++) swfs_halo_free(hs[k]);
    free(hs);
    free(gs);
    return rc;
}

/* The self-check of the computed speckles as a choice among candidate halos (pupil.h
 * swfs_halo_choose; docs/telemetry.md, "The self-check as the choice"). */
#include "specklewfs/pupil.h"
#include "specklewfs/regress.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *nm(const char *const *names, size_t i, char *buf, size_t cap)
{
    if (names && names[i]) return names[i];
    snprintf(buf, cap, "candidate %zu", i);
    return buf;
}

int swfs_halo_choose(const swfs_halo *const *h, const char *const *names, size_t n, double *explained, size_t *best,
                     size_t *ncommon)
{
    *best = 0;
    *ncommon = 0;
    for (size_t i = 0; i < n; i++) explained[i] = NAN;
    if (n == 0) return swfs_fail(SWFS_ERR_ARG, "choosing speckles: no candidate halo");
    char b0[32], b1[32];
    const swfs_regress *r0 = h[0]->reg;
    for (size_t i = 0; i < n; i++) {
        if (!h[i]->reg)
            return swfs_fail(SWFS_ERR_VALUE, "%s: no regression statistics (REGSTATE): the self-check needs the halo "
                             "of `estimate` (not a moments-only halo)", nm(names, i, b0, sizeof b0));
        if (h[i]->tiptilt[0] && h[0]->tiptilt[0] && strcmp(h[i]->tiptilt, h[0]->tiptilt))
            return swfs_fail(SWFS_ERR_VALUE, "%s: speckles made with --tiptilt %s where %s has %s: the self-check "
                             "compares speckles of one tip-tilt treatment (with the image motion left in, the "
                             "speckles explain the frames' motion, which says nothing of the halo's)",
                             nm(names, i, b0, sizeof b0), h[i]->tiptilt, nm(names, 0, b1, sizeof b1), h[0]->tiptilt);
        if (h[i]->reg->nx != r0->nx || h[i]->reg->ny != r0->ny)
            return swfs_fail(SWFS_ERR_SHAPE, "%s: a %zux%zu window where %s has %zux%zu: candidates must be halos of "
                             "the same science frames", nm(names, i, b0, sizeof b0), h[i]->reg->nx, h[i]->reg->ny,
                             nm(names, 0, b1, sizeof b1), r0->nx, r0->ny);
    }
    const size_t np = r0->nx * r0->ny;
    swfs_regress_sol **sol = calloc(n, sizeof *sol);
    double *sst = calloc(n, sizeof *sst), *sse = calloc(n, sizeof *sse);
    int rc = (!sol || !sst || !sse) ? swfs_fail(SWFS_ERR_NOMEM, "choosing speckles: out of memory") : SWFS_OK;
    for (size_t i = 0; !rc && i < n; i++)
        if ((rc = swfs_regress_solve(h[i]->reg, &sol[i]))) rc = swfs_fail_context(rc, "%s", nm(names, i, b0, sizeof b0));
    if (!rc) {
        /* the pixels solved (finite 1 - SSE/SST) in every candidate */
        for (size_t k = 0; k < np; k++) {
            int all = 1;
            for (size_t i = 0; all && i < n; i++) all = isfinite(sol[i]->r2->data[k]);
            if (!all) continue;
            (*ncommon)++;
            for (size_t i = 0; i < n; i++) {
                const double *v = h[i]->reg->state;
                const double g00 = v[(size_t)SWFS_REG_G00 * np + k], h0 = v[(size_t)SWFS_REG_H0 * np + k];
                const double t = v[(size_t)SWFS_REG_YY * np + k] - h0 * h0 / g00;
                sst[i] += t;
                sse[i] += t * (1 - sol[i]->r2->data[k]);
            }
        }
        if (*ncommon == 0)
            rc = swfs_fail(SWFS_ERR_VALUE, "choosing speckles: no focal pixel is solved in all %zu candidates", n);
    }
    for (size_t i = 1; !rc && i < n; i++)
        if (!(fabs(sst[i] - sst[0]) <= 1e-6 * fabs(sst[0])))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s and %s: the science intensity's variance differs (%.9g against %.9g "
                           "over %zu pixels): candidates must be halos of the same science frames",
                           nm(names, i, b0, sizeof b0), nm(names, 0, b1, sizeof b1), sst[i], sst[0], *ncommon);
    if (!rc)
        for (size_t i = 0; i < n; i++) {
            explained[i] = 1 - sse[i] / sst[i];
            if (explained[i] > explained[*best]) *best = i;
        }
    for (size_t i = 0; sol && i < n; i++) swfs_regress_sol_free(sol[i]);
    free(sol);
    free(sst);
    free(sse);
    return rc;
}

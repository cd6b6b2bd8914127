/* Shares of a data set and the team helpers: see include/specklewfs/team.h. */
#include "specklewfs/team.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>

int swfs_team_active(const swfs_team *t) { return t && t->size > 1; }
int swfs_team_writer(const swfs_team *t) { return !swfs_team_active(t) || t->rank == 0; }

/* The allowed cut nearest to item `target` (ties: the lower one): a segment boundary, or
 * a multiple of grain from the start of the segment holding target. */
static size_t nearest_cut(const size_t *len, size_t nseg, size_t grain, size_t target)
{
    size_t b = 0;
    for (size_t s = 0; s < nseg; s++) {
        const size_t e = b + len[s];
        if (target < e) {
            const size_t lo = b + (target - b) / grain * grain;
            size_t hi = lo + grain;
            if (hi > e) hi = e;
            return target - lo <= hi - target ? lo : hi;
        }
        b = e;
    }
    return b;
}

/* Cut k of size: the allowed cut nearest to k N / size, at least the first allowed cut
 * after 0 (member 0 is never empty) and at most N. */
static size_t cut(const size_t *len, size_t nseg, size_t grain, size_t total, int k, int size)
{
    if (k <= 0) return 0;
    if (k >= size) return total;
    /* k N / size rounded, without overflowing for any N below 2^64 / size. */
    const size_t q = total / (size_t)size, r = total % (size_t)size;
    const size_t target = q * (size_t)k + (r * (size_t)k + (size_t)size / 2) / (size_t)size;
    size_t c = nearest_cut(len, nseg, grain, target);
    /* Member 0 takes at least the first batch: the segments before the first non-empty
     * one are empty, so its end is min(len, grain) items from the start. */
    size_t first = 0;
    for (size_t s = 0; s < nseg && !first; s++)
        if (len[s]) first = len[s] < grain ? len[s] : grain;
    return c < first ? first : c;
}

void swfs_team_share(const size_t *len, size_t nseg, size_t grain, int rank, int size, size_t *first,
                     size_t *count)
{
    size_t total = 0;
    for (size_t s = 0; s < nseg; s++) total += len[s];
    if (size <= 1) {
        *first = 0;
        *count = total;
        return;
    }
    if (grain < 1) grain = 1;
    const size_t a = cut(len, nseg, grain, total, rank, size), b = cut(len, nseg, grain, total, rank + 1, size);
    *first = a;
    *count = b > a ? b - a : 0;
}

int swfs_team_bcast0(const swfs_team *t, void *v, size_t bytes)
{
    return swfs_team_active(t) ? t->bcast(t->ctx, v, bytes, 0) : SWFS_OK;
}

int swfs_team_agree(const swfs_team *t, int status)
{
    return swfs_team_active(t) ? t->agree(t->ctx, status) : status;
}

int swfs_team_merge_accum(const swfs_team *t, const swfs_accum *mine, swfs_accum *out)
{
    const int team = swfs_team_active(t);
    const size_t n = swfs_accum_state_len(mine->nx, mine->ny);
    if (!team && out == mine) return SWFS_OK;
    double *state = malloc(n * sizeof *state);
    int rc = state ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory for the %zu-double accumulator state", n);
    /* Every member must take part in the reduction: one that could not allocate says so at
     * the agreement, before anyone reduces. */
    if (team) rc = t->agree(t->ctx, rc);
    if (!rc) {
        swfs_accum_export(mine, state);
        if (team) rc = t->merge_accum(t->ctx, state, mine->nx, mine->ny);
        if (!rc && swfs_team_writer(t)) {
            if (out->nx != mine->nx || out->ny != mine->ny)
                rc = swfs_fail(SWFS_ERR_SHAPE, "merged accumulators of %zux%zu into one of %zux%zu", mine->nx, mine->ny,
                               out->nx, out->ny);
            else rc = swfs_accum_import(out, state);
        }
    }
    free(state);
    return rc;
}

int swfs_team_sum_pipeline_mean(const swfs_team *t, swfs_pipeline *p)
{
    if (!swfs_team_active(t)) return SWFS_OK;
    double *sum, cnt;
    size_t n, nexp;
    swfs_pipeline_mean_state(p, &sum, &n, &nexp);
    cnt = (double)nexp;
    int rc = t->sum(t->ctx, sum, n);
    if (!rc) rc = t->sum(t->ctx, &cnt, 1);
    if (!rc) swfs_pipeline_mean_set_count(p, (size_t)llround(cnt));
    return rc;
}

/* The miss of the AO residual's time mean by a pipeline's own reconstruction, from simulated
 * closed loops of the same system (`speckles`, `stream`, `live` --mean-loop DIR...; the loops
 * `speckles --mean-loop teach` simulates, run_mean_teach.c): run.h swfs_pipeline_mean_loops,
 * docs/telemetry.md. */
#include "specklewfs/fits.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "run_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

/* run_internal.h: a simulated loop's first WFS frame in an exposure. */
size_t swfs_loop_first_frame_(const char *dir)
{
    char path[4300], line[512];
    snprintf(path, sizeof path, "%.4000s/truth_timing.txt", dir);
    FILE *f = fopen(path, "r");
    if (!f) return 0;
    double first = INFINITY, v = 0;
    unsigned c = 0;
    while (fgets(line, sizeof line, f))
        if (line[0] != '#' && sscanf(line, "%u %lf", &c, &v) == 2 && v >= 0 && v < first) first = v;
    fclose(f);
    return isfinite(first) ? (size_t)floor(first) : 0;
}

/* Each loop's true mean (truth.fits RESMEAN) less the pipeline's reconstruction of its mean
 * telemetry (every slopes_NNN.fits frame from the first exposure's start on,
 * swfs_loop_first_frame_), piston, tip and tilt removed from both; held out as learn's
 * MEANMISS (the others' mean against each loop's, over the pupil's samples), and their mean
 * the pipeline's mean offset where it predicts (ratio < 1). */
int swfs_pipeline_mean_loops(swfs_pipeline *p, const char *const *loops, size_t nl, double *heldout, double *rms)
{
    if (heldout) *heldout = NAN;
    if (rms) *rms = 0;
    if (nl < 2 || !loops)
        return swfs_fail(SWFS_ERR_ARG, "mean loops: at least 2 folders of simulated loops (each is checked against "
                         "the others'), got %zu", loops ? nl : 0);
    swfs_pipeline_info info;
    swfs_pipeline_get_info(p, &info);
    const size_t n = info.npup, ns = info.nslopes / (info.nlags ? info.nlags : 1);
    const double *mask = swfs_pipeline_mask(p);
    double *miss = calloc(nl * n * n, sizeof *miss), *rec = malloc(n * n * sizeof *rec), *ms = malloc(ns * sizeof *ms);
    int rc = miss && rec && ms ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t d = 0; !rc && d < nl; d++) {
        char path[4200];
        size_t nf = 0, at = 0;
        const size_t first = swfs_loop_first_frame_(loops[d]);
        memset(ms, 0, ns * sizeof *ms);
        for (size_t k = 0; !rc; k++) {
            snprintf(path, sizeof path, "%.4000s/slopes_%03zu.fits", loops[d], k);
            if (access(path, F_OK) != 0) break;
            swfs_real *s = NULL;
            if ((rc = swfs_telemetry_read(path, ns, &s, NULL))) {
                rc = swfs_fail_context(rc, "the loop %s (its telemetry is the observation's kind: %zu values per frame)",
                                       loops[d], ns);
                break;
            }
            for (size_t t = at < first ? first - at : 0; t < s->ny; t++, nf++)
                for (size_t i = 0; i < ns; i++) ms[i] += s->data[t * ns + i];
            at += s->ny;
            swfs_real_free(s);
        }
        if (!rc && !nf) rc = swfs_fail(SWFS_ERR_IO, "%s: %s: expected a folder of `simulate mode=timeseries`", loops[d],
                                       at ? "no telemetry frame after its first exposure's start" : "no slopes_000.fits");
        for (size_t i = 0; !rc && i < ns; i++) ms[i] /= (double)nf;
        if (!rc) rc = swfs_pipeline_wavefront_of_mean(p, ms, ns, rec);
        swfs_real *t = NULL;
        snprintf(path, sizeof path, "%.4000s/truth.fits", loops[d]);
        if (!rc) rc = swfs_fits_read_real(path, "RESMEAN", &t, NULL);
        if (!rc && (t->nx != n || t->ny != n || t->nz != 1))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: RESMEAN is %zux%zux%zu; the observation's pupil grid is %zu x %zu", path,
                           t->nx, t->ny, t->nz, n, n);
        if (!rc) {
            double *m = miss + d * n * n;
            memcpy(m, t->data, n * n * sizeof *m);
            swfs_wfe_remove_ptt(m, mask, n);
            for (size_t i = 0; i < n * n; i++) m[i] = mask[i] > 0 ? m[i] - rec[i] : 0.0;
        }
        swfs_real_free(t);
    }
    const double ratio = rc ? NAN : swfs_heldout_mean_(miss, nl, n * n, mask, NULL, NULL, rec, NULL);
    if (!rc && isfinite(ratio)) {
        if (heldout) *heldout = ratio;
        if (ratio < 1) {
            rc = swfs_pipeline_set_mean_offset(p, rec);
            if (!rc && rms) *rms = swfs_wfe_remove_ptt(rec, mask, n);
        } else {
            rc = swfs_pipeline_set_mean_offset(p, NULL);
        }
    }
    free(miss);
    free(rec);
    free(ms);
    return rc;
}

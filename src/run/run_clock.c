/* sync --wfs-log: a WFS milk log + the reduced science cube (TRACK, STAMPS) -> the clock
 * file (clocksync.h). See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "run_internal.h"
#include "specklewfs/milklog.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_clock_run_options_default(swfs_clock_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_clock_params_default(&o->params);
    swfs_linear_files_default(&o->lin);
}

/* The tip-tilt of every frame of the log, read in blocks: the mean x / y slope, or through
 * the linear model's tilt rows R (2 x nvals) when R is given. */
static int mean_slopes(swfs_milklog *l, const double *R, double *mx, double *my)
{
    const swfs_milklog_info *in = swfs_milklog_get_info(l);
    if (!R && (in->nvals < 2 || in->nvals % 2))
        return swfs_fail(SWFS_ERR_SHAPE, "%s: frames of %zu values; the WFS log sync correlates must hold "
                         "Shack-Hartmann slopes (an even count: x slopes, then y slopes)", in->source, in->nvals);
    enum { BLOCK = 256 };
    double *buf = malloc(BLOCK * in->nvals * sizeof *buf);
    if (!buf) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", in->source);
    int rc = SWFS_OK;
    for (size_t k = 0; k < in->nframes && !rc; k += BLOCK) {
        const size_t n = in->nframes - k < BLOCK ? in->nframes - k : BLOCK;
        if ((rc = swfs_milklog_read(l, k, n, buf))) break;
        for (size_t i = 0; i < n * in->nvals && !rc; i++)
            if (!isfinite(buf[i]) || fabs(buf[i]) > SWFS_TELEMETRY_MAX) {
                char val[48];
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: value %zu of frame %zu %s; telemetry values must be finite and "
                               "below %g in magnitude", swfs_milklog_file_of(l, k + i / in->nvals), i % in->nvals,
                               k + i / in->nvals, swfs_value_words(buf[i], val, sizeof val), SWFS_TELEMETRY_MAX);
            }
        if (!rc && R) swfs_tilt_rows_apply(R, buf, in->nvals, n, mx + k, my + k);
        else if (!rc) swfs_slopes_mean_xy(buf, in->nvals, n, NULL, mx + k, my + k);
    }
    free(buf);
    return rc;
}

int swfs_clock_run(const swfs_clock_run_options *o, swfs_clock_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->science || !o->nwfs || !o->out) return swfs_fail(SWFS_ERR_ARG, "sync --wfs-log: needs a WFS log, the "
                                                            "science cube and an output");
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    swfs_paths_input(paths, "science cube", o->science);
    for (size_t k = 0; k < o->nwfs; k++) swfs_paths_input_or_dir(paths, "WFS log", o->wfs[k]);
    swfs_linear_paths(paths, &o->lin);
    if (!rc) rc = swfs_paths_output(paths, "output clock file", o->out);
    swfs_paths_free(paths);
    if (rc) return rc;
    swfs_science_track *tr = NULL;
    swfs_milklog *l = NULL;
    uint64_t *ccnt = NULL;
    int64_t *cst = NULL;
    double *mx = NULL, *my = NULL, exptime = 0;
    size_t nst = 0;
    rc = swfs_science_track_read(o->science, &tr);
    if (!rc) rc = swfs_science_stamps_read(o->science, &ccnt, &cst, &nst, &exptime);
    if (!rc) rc = swfs_milklog_open(&l, o->wfs, o->nwfs);
    const swfs_milklog_info *in = rc ? NULL : swfs_milklog_get_info(l);
    if (!rc && (!(mx = malloc(in->nframes * sizeof *mx)) || !(my = malloc(in->nframes * sizeof *my))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", in->source);
    double *R = NULL;
    if (!rc && o->lin.basis) rc = swfs_linear_tilt_rows(&o->lin, o->science, in->nvals, &R);
    if (!rc) rc = mean_slopes(l, R, mx, my);
    free(R);
    if (!rc) {
        r->wfs_dropped = in->dropped;
        r->wfs_frames = in->nframes;
        r->wfs_files = in->nfiles;
        for (size_t j = 1; j < nst; j++)
            if (ccnt[j] > ccnt[j - 1] + 1) r->cam_dropped += ccnt[j] - ccnt[j - 1] - 1;
        const swfs_clock_data d = {in->nframes, swfs_milklog_counters(l), swfs_milklog_stamps(l), mx, my, nst, ccnt,
                                   cst, tr->x, tr->y, o->exptime > 0 ? o->exptime : exptime};
        rc = swfs_clock_estimate(&d, &o->params, &r->clock);
        if (rc) swfs_fail_context(rc, "%s with %s", o->science, in->source);
    }
    if (!rc) {
        char note[8400];
        snprintf(note, sizeof note, "WFS log %s (%zu frames, %zu files), science cube %s", in->source, in->nframes,
                 in->nfiles, o->science);
        rc = swfs_clock_write(o->out, &r->clock, note);
    }
    swfs_science_track_free(tr);
    swfs_milklog_free(l);
    free(ccnt);
    free(cst);
    free(mx);
    free(my);
    return rc;
}

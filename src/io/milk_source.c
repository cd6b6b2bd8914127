/* Stream batches from milk logs through framesync: see include/specklewfs/milksource.h. */
#include "specklewfs/milksource.h"
#include "specklewfs/fits.h"
#include "specklewfs/milklog.h"
#include "specklewfs/numeric.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* WFS frames fed between two looks for a batch when no camera frame comes in between. */
enum { POLL_WFS = 256 };

struct swfs_milk_source {
    size_t nwfs;
    swfs_milklog *log[SWFS_FRAMESYNC_MAX_WFS];
    size_t wnext[SWFS_FRAMESYNC_MAX_WFS];
    double *wbuf;              /* one frame of the largest log */
    swfs_fits_in *sci;
    size_t nx, ny, nf2, ncam, cnext;
    uint64_t *ccnt;
    int64_t *cst;              /* camera stamps on the WFS clock [ns] */
    double *raw, *frame;       /* one camera frame as read / turned into the model's orientation */
    swfs_sync_result orient;
    int turn;
    swfs_framesync *fs;
    size_t since;              /* WFS frames fed since the last look */
    int flushing;
    swfs_milk_source_stats st;
};

void swfs_milk_source_close(swfs_milk_source *s)
{
    if (!s) return;
    for (size_t i = 0; i < s->nwfs; i++) swfs_milklog_free(s->log[i]);
    swfs_fits_in_close(s->sci);
    swfs_framesync_free(s->fs);
    free(s->wbuf);
    free(s->ccnt);
    free(s->cst);
    free(s->raw);
    free(s->frame);
    free(s);
}

/* The camera cube: frames, STAMPS (put on the WFS clock), exposure, orientation. */
static int open_camera(swfs_milk_source *s, const swfs_milk_source_options *o)
{
    int rc = swfs_fits_in_open(&s->sci, o->science, NULL);
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(s->sci);
    if (sh->is_complex) return swfs_fail(SWFS_ERR_FORMAT, "%s: science cube is complex; expected real intensities", o->science);
    if (o->nfx && o->nfy && (sh->nx != o->nfx || sh->ny != o->nfy))
        return swfs_fail(SWFS_ERR_SHAPE, "%s: frames of %zux%zu but the geometry needs %zux%zu", o->science, sh->nx,
                         sh->ny, o->nfx, o->nfy);
    char orien[80];
    int found = 0;
    if ((rc = swfs_fits_in_key_string_opt(s->sci, "CAMORIEN", orien, sizeof orien, &found))) return rc;
    if (found)
        return swfs_fail(SWFS_ERR_VALUE, "%s: a copy already turned into the model's orientation (CAMORIEN = '%s'); give "
                         "the reduced science cube with STAMPS", o->science, orien);
    s->nx = sh->nx;
    s->ny = sh->ny;
    s->nf2 = sh->nx * sh->ny;
    double e = 0;
    if ((rc = swfs_science_stamps_read(o->science, &s->ccnt, &s->cst, &s->ncam, &e))) return rc;
    s->st.exptime = o->exptime > 0 ? o->exptime : e;
    for (size_t j = 1; j < s->ncam; j++)
        if (s->ccnt[j] > s->ccnt[j - 1] + 1) s->st.camera_dropped_log += s->ccnt[j] - s->ccnt[j - 1] - 1;
    if (o->clock)
        for (size_t j = 0; j < s->ncam; j++) s->cst[j] = swfs_clock_to_wfs(o->clock, s->cst[j]);
    memset(&s->orient, 0, sizeof s->orient);
    s->orient.sign_x = s->orient.sign_y = 1;
    if (o->clock) s->orient = o->clock->fit;
    if ((rc = swfs_orient_check(&s->orient, s->nx, s->ny, "the clock file's pairing"))) return rc;
    s->turn = !swfs_orient_is_identity(&s->orient);
    s->raw = malloc(s->nf2 * sizeof *s->raw);
    s->frame = malloc(s->nf2 * sizeof *s->frame);
    if (!s->raw || !s->frame) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
    return SWFS_OK;
}

/* Every WFS log must overlap the camera's exposures in time. */
static int check_overlap(const swfs_milk_source *s, const swfs_milk_source_options *o, double exptime)
{
    const int64_t c0 = s->cst[0] - (int64_t)llround(1e9 * exptime), c1 = s->cst[s->ncam - 1];
    for (size_t i = 0; i < s->nwfs; i++) {
        const swfs_milklog_info *in = swfs_milklog_get_info(s->log[i]);
        const int64_t *w = swfs_milklog_stamps(s->log[i]), w0 = w[0], w1 = w[in->nframes - 1];
        if (w1 >= c0 && w0 <= c1) continue;
        char a[40], b[40], x[40], y[40];
        swfs_time_format_ns(c0, a, sizeof a);
        swfs_time_format_ns(c1, b, sizeof b);
        swfs_time_format_ns(w0, x, sizeof x);
        swfs_time_format_ns(w1, y, sizeof y);
        return swfs_fail(SWFS_ERR_VALUE, "WFS log %s (stamps %s .. %s s) does not overlap in time with the camera "
                         "exposures of %s (%s .. %s s on the WFS clock%s)", in->source, x, y, o->science, a, b,
                         o->clock ? ", after the clock file's offset and drift" : "");
    }
    return SWFS_OK;
}

int swfs_milk_source_open(swfs_milk_source **out, const swfs_milk_source_options *o)
{
    *out = NULL;
    if (!o->nwfs || o->nwfs > SWFS_FRAMESYNC_MAX_WFS || !o->science || !o->batch)
        return swfs_fail(SWFS_ERR_ARG, "milk source: needs 1..%d WFS logs, a science cube and a batch >= 1",
                         SWFS_FRAMESYNC_MAX_WFS);
    swfs_milk_source *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "milk source: out of memory");
    s->nwfs = o->nwfs;
    size_t nv[SWFS_FRAMESYNC_MAX_WFS], total = 0, maxv = 0;
    int rc = SWFS_OK;
    char names[2048] = "";
    for (size_t i = 0; i < o->nwfs && !rc; i++) {
        if ((rc = swfs_milklog_open(&s->log[i], &o->wfs[i], 1))) break;
        const swfs_milklog_info *in = swfs_milklog_get_info(s->log[i]);
        total += nv[i] = in->nvals;
        if (in->nvals > maxv) maxv = in->nvals;
        s->st.wfs_dropped_log += in->dropped;
        const size_t l = strlen(names);
        snprintf(names + l, sizeof names - l, "%s%s (%zu)", i ? " + " : "", in->source, in->nvals);
    }
    if (!rc && o->nslopes && total != o->nslopes)
        rc = swfs_fail(SWFS_ERR_SHAPE, "WFS log%s %s: %zu values per frame but the reconstructor expects %zu slopes",
                       o->nwfs > 1 ? "s" : "", names, total, o->nslopes);
    if (!rc) rc = open_camera(s, o);
    const double drift = o->clock ? o->clock->drift : 0.0;
    if (!rc) rc = check_overlap(s, o, s->st.exptime > 0 ? s->st.exptime : 0.0);
    if (!rc) {
        swfs_framesync_options fo;
        swfs_framesync_options_default(&fo);
        fo.batch = o->batch;
        fo.max_wait = 1e30; /* offline: batches close when full, at a gap or at the end */
        fo.exptime = s->st.exptime * (1.0 + drift);
        fo.lags = o->lags;
        fo.nlags = o->nlags;
        rc = swfs_framesync_create(&s->fs, o->nwfs, nv, s->nf2, &fo);
    }
    if (!rc && !(s->wbuf = malloc(maxv * sizeof *s->wbuf))) rc = swfs_fail(SWFS_ERR_NOMEM, "milk source: out of memory");
    if (rc) {
        swfs_milk_source_close(s);
        return rc;
    }
    *out = s;
    return SWFS_OK;
}

/* The next frame in time order into framesync: 1 fed a camera frame, 0 a WFS frame, -1
 * nothing left; a status < -1 is not used (errors are returned through rc). */
static int feed_one(swfs_milk_source *s, int *rc)
{
    size_t best = SIZE_MAX;
    int64_t bt = INT64_MAX;
    for (size_t i = 0; i < s->nwfs; i++) {
        const swfs_milklog_info *in = swfs_milklog_get_info(s->log[i]);
        if (s->wnext[i] < in->nframes && swfs_milklog_stamps(s->log[i])[s->wnext[i]] < bt) {
            bt = swfs_milklog_stamps(s->log[i])[s->wnext[i]];
            best = i;
        }
    }
    const int cam = s->cnext < s->ncam && s->cst[s->cnext] <= bt;
    if (cam) {
        const size_t j = s->cnext++;
        if ((*rc = swfs_fits_in_read_real(s->sci, j, 1, s->raw))) return -1;
        if (s->turn) swfs_orient_frame(&s->orient, s->nx, s->ny, 1, s->raw, s->frame);
        *rc = swfs_framesync_add_camera(s->fs, s->ccnt[j], s->cst[j], s->turn ? s->frame : s->raw, 0.0);
        return 1;
    }
    if (best == SIZE_MAX) return -1;
    const size_t k = s->wnext[best]++;
    swfs_milklog *l = s->log[best];
    if ((*rc = swfs_milklog_read(l, k, 1, s->wbuf))) return -1;
    const double *v = s->wbuf;
    const size_t nv = swfs_milklog_get_info(l)->nvals;
    for (size_t i = 0; i < nv; i++)
        if (!isfinite(v[i]) || fabs(v[i]) > SWFS_TELEMETRY_MAX) {
            char val[48];
            *rc = swfs_fail(SWFS_ERR_VALUE, "%s: value %zu of frame %zu (cnt0 %llu) %s; telemetry values must be "
                            "finite and below %g in magnitude", swfs_milklog_file_of(l, k), i, k,
                            (unsigned long long)swfs_milklog_counters(l)[k], swfs_value_words(v[i], val, sizeof val),
                            SWFS_TELEMETRY_MAX);
            return -1;
        }
    *rc = swfs_framesync_add_wfs(s->fs, best, swfs_milklog_counters(l)[k], swfs_milklog_stamps(l)[k], v, 0.0);
    return 0;
}

int swfs_milk_source_next(void *ctx, swfs_batch *b)
{
    swfs_milk_source *s = ctx;
    memset(b, 0, sizeof *b);
    for (;;) {
        int rc = swfs_framesync_next(s->fs, 0.0, s->flushing, b);
        if (rc || b->nexp || s->flushing) return rc;
        /* Feed until a camera frame went in (or enough WFS frames), then look again. */
        for (;;) {
            rc = SWFS_OK;
            const int what = feed_one(s, &rc);
            if (rc) return rc;
            if (what < 0) {
                s->flushing = 1;
                break;
            }
            if (what == 1 || ++s->since >= POLL_WFS) {
                s->since = 0;
                break;
            }
        }
    }
}

void swfs_milk_source_get_stats(const swfs_milk_source *s, swfs_milk_source_stats *st)
{
    *st = s->st;
    swfs_framesync_get_stats(s->fs, &st->sync);
}

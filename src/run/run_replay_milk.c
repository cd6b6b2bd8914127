/* replay --wfs-log: a WFS milk log (milklog.h) and the science cube's STAMPS published as
 * they were logged. Every frame goes out with its own stamp moved by one whole number of
 * nanoseconds onto the present (so `live` sees exactly the stamp differences `stream
 * --wfs-log` reads from the files, and real lags), in stamp order
 * (a camera frame before a WFS frame of the same stamp, as the offline source feeds them),
 * at the logged pace or --speed times faster; counter jumps in the log and in STAMPS (frames
 * the logger lost) are published as skipped frames, so the readers count them as drops. */
#include "specklewfs/fits.h"
#include "specklewfs/live.h"
#include "specklewfs/milklog.h"
#include "specklewfs/parallel.h"
#include "specklewfs/science.h"
#include "specklewfs/shm.h"
#include "specklewfs/status.h"
#include "run_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct mreplay {
    swfs_milklog *log;
    swfs_fits_in *sci;
    uint64_t *ccnt;
    int64_t *cst;
    size_t ncam, nf2;
    swfs_shm *w, *c;
    double *buf;
} mreplay;

static int open_inputs(const swfs_replay_options *o, mreplay *m)
{
    int rc = swfs_milklog_open(&m->log, &o->wfs_log, 1);
    if (!rc) rc = swfs_fits_in_open(&m->sci, o->science, NULL);
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(m->sci);
    if (sh->is_complex) return swfs_fail(SWFS_ERR_FORMAT, "%s: complex; expected camera frames", o->science);
    double exptime = 0;
    if ((rc = swfs_science_stamps_read(o->science, &m->ccnt, &m->cst, &m->ncam, &exptime))) return rc;
    m->nf2 = sh->nx * sh->ny;
    const swfs_milklog_info *in = swfs_milklog_get_info(m->log);
    const size_t n = in->nvals > m->nf2 ? in->nvals : m->nf2;
    if (!(m->buf = malloc(n * sizeof *m->buf))) return swfs_fail(SWFS_ERR_NOMEM, "replay: out of memory");
    /* Doubles in, doubles out: the readers get the files' values exactly. */
    swfs_shm_shape ws = {SWFS_SHM_F64, in->nvals, 1, 1, 0, 0}, cs = {SWFS_SHM_F64, sh->nx, sh->ny, 1, 0, 0};
    if (o->depth > 1) {
        ws.nz = cs.nz = o->depth;
        ws.temporal = cs.temporal = 1;
    }
    rc = swfs_shm_create(&m->w, o->dir, o->wfs_name, &ws);
    if (!rc) rc = swfs_shm_create(&m->c, o->dir, o->camera_name, &cs);
    return rc;
}

static int cmp_i64(const void *a, const void *b)
{
    const int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return x < y ? -1 : x > y;
}

/* The camera's frame period [ns]: the median stamp step between consecutive counters
 * (the log may pause between cubes); 0 when there is none. */
static double camera_period_ns(const mreplay *m)
{
    int64_t *d = m->ncam > 1 ? malloc((m->ncam - 1) * sizeof *d) : NULL;
    size_t n = 0;
    for (size_t j = 1; d && j < m->ncam; j++)
        if (m->ccnt[j] == m->ccnt[j - 1] + 1) d[n++] = m->cst[j] - m->cst[j - 1];
    double p = 0;
    if (n) {
        qsort(d, n, sizeof *d, cmp_i64);
        p = (double)d[n / 2];
    }
    free(d);
    return p;
}

/* The frames a counter jump skips (none after a counter that went back: a new writer). */
static void skip_lost(swfs_shm *s, const uint64_t *cnt, size_t k, size_t *lost)
{
    if (!k || cnt[k] <= cnt[k - 1] + 1) return;
    for (uint64_t n = cnt[k] - cnt[k - 1] - 1; n; n--) swfs_shm_skip(s);
    *lost += (size_t)(cnt[k] - cnt[k - 1] - 1);
}

int swfs_replay_milk_run_(const swfs_replay_options *o, swfs_replay_result *r)
{
    memset(r, 0, sizeof *r);
    if (o->timing || o->slopes)
        return swfs_fail(SWFS_ERR_ARG, "replay: --wfs-log publishes a milk log with its own stamps; it takes no timing "
                         "table or slopes files");
    if (o->drop_wfs > 0 || o->drop_camera > 0 || o->jitter > 0 || o->restart_after || o->wfs_rate > 0)
        return swfs_fail(SWFS_ERR_ARG, "replay: --wfs-log publishes the log as it was (its own stamps, rate and lost "
                         "frames); drops, jitter, restarts and a WFS rate apply to a timing table's data");
    if (!(o->speed > 0)) return swfs_fail(SWFS_ERR_ARG, "replay: speed %g; expected > 0", o->speed);
    mreplay m;
    memset(&m, 0, sizeof m);
    int rc = open_inputs(o, &m);
    if (!rc) rc = swfs_replay_wait_readers_(o, m.w, m.c, &(double){0});
    if (!rc) {
        const swfs_milklog_info *in = swfs_milklog_get_info(m.log);
        const uint64_t *wc = swfs_milklog_counters(m.log);
        const int64_t *ws = swfs_milklog_stamps(m.log);
        const int64_t s0 = m.ncam && m.cst[0] < ws[0] ? m.cst[0] : ws[0];
        const double mono0 = swfs_wall_seconds() + 0.02, t_start = swfs_wall_seconds();
        const int64_t shift = swfs_shm_now_ns() + 20000000 - s0;
        size_t i = 0, j = 0;
        while (!rc && (i < in->nframes || j < m.ncam)) {
            const int cam = j < m.ncam && (i >= in->nframes || m.cst[j] <= ws[i]);
            const int64_t stamp = cam ? m.cst[j] : ws[i];
            const double when = 1e-9 * (double)(stamp - s0) / o->speed;
            swfs_sleep_until(mono0 + when);
            if (cam) {
                skip_lost(m.c, m.ccnt, j, &r->camera_dropped);
                rc = swfs_fits_in_read_real(m.sci, j, 1, m.buf);
                if (!rc) rc = swfs_shm_write(m.c, m.buf, stamp + shift);
                j++;
            } else {
                skip_lost(m.w, wc, i, &r->wfs_dropped);
                rc = swfs_milklog_read(m.log, i, 1, m.buf);
                if (!rc) rc = swfs_shm_write(m.w, m.buf, stamp + shift);
                i++;
            }
            r->late_max = fmax(r->late_max, swfs_wall_seconds() - (mono0 + when));
            if (!rc && (i + j) % 1024 == 0)
                rc = swfs_progress_report(o->progress, o->progress_ctx, "frames", i + j, in->nframes + m.ncam);
        }
        r->seconds = swfs_wall_seconds() - t_start;
        r->wfs_frames = i + r->wfs_dropped;
        r->camera_frames = j + r->camera_dropped;
        if (in->nframes > 1 && ws[in->nframes - 1] > ws[0])
            r->wfs_rate = o->speed * 1e9 * (double)(wc[in->nframes - 1] - wc[0]) / (double)(ws[in->nframes - 1] - ws[0]);
        r->ratio = 1e-9 * camera_period_ns(&m) * r->wfs_rate / o->speed;
    }
    swfs_shm_close(m.w, o->remove);
    swfs_shm_close(m.c, o->remove);
    swfs_fits_in_close(m.sci);
    swfs_milklog_free(m.log);
    free(m.ccnt);
    free(m.cst);
    free(m.buf);
    return rc;
}

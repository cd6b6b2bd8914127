/* stream --wfs-log: milk logs and the science cube's STAMPS -> the streaming run (the source
 * is milksource.h: framesync over time-stamped frames). See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/milksource.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"
#include "run_internal.h"

#include <math.h>
#include <string.h>

typedef struct milk_ctx {
    const swfs_stream_run_options *o;
    swfs_clock clock;
    int have_clock;
    swfs_milk_source *src;
} milk_ctx;

static int milk_next(void *ctx, swfs_batch *b)
{
    milk_ctx *m = ctx;
    return swfs_milk_source_next(m->src, b);
}

/* The pipeline is built: open the logs with the sizes it needs. */
static int milk_prepare(void *ctx, const swfs_pipeline_info *info, const long *lags)
{
    milk_ctx *m = ctx;
    const swfs_stream_run_options *o = m->o;
    /* a space-time map (lags): the logs give one frame's slopes, the batches stack them */
    const swfs_milk_source_options so = {o->wfs_logs, o->nwfs_logs, o->science, m->have_clock ? &m->clock : NULL,
                                         o->exptime, info->nslopes / (lags ? info->nlags : 1), info->nfx, info->nfy,
                                         o->batch, lags, lags ? info->nlags : 0};
    return swfs_milk_source_open(&m->src, &so);
}

static int check_paths(const swfs_stream_run_options *o)
{
    swfs_paths *p = NULL;
    int rc = swfs_paths_create(&p);
    for (size_t k = 0; k < o->nwfs_logs; k++) swfs_paths_input_or_dir(p, "WFS log (--wfs-log)", o->wfs_logs[k]);
    swfs_paths_input(p, "clock file", o->clock);
    swfs_stream_paths_inputs(p, o);
    swfs_stream_paths_outputs(p, o);
    if (!rc) rc = swfs_paths_status(p);
    swfs_paths_free(p);
    return rc;
}

int swfs_stream_run_milk(const swfs_stream_run_options *o, swfs_stream_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->static_scale = NAN;
    if (o->nwfs_logs > SWFS_FRAMESYNC_MAX_WFS || !o->science || !o->recon || !o->actuators || !o->out)
        return swfs_fail(SWFS_ERR_ARG, "stream --wfs-log: needs 1..%d WFS logs, a science cube with STAMPS, a "
                         "reconstructor, actuators and an output", SWFS_FRAMESYNC_MAX_WFS);
    if (o->timing)
        return swfs_fail(SWFS_ERR_ARG, "stream: a timing table (%s) and WFS logs (%s): the logs' time stamps give the "
                         "timing; give one or the other", o->timing, o->wfs_logs[0]);
    if (swfs_team_active(o->team))
        return swfs_fail(SWFS_ERR_ARG, "stream --wfs-log runs as one process (a team shares the timing table's cubes)");
    if (!(o->exptime >= 0) || !isfinite(o->exptime))
        return swfs_fail(SWFS_ERR_ARG, "stream: exposure time %g s; expected >= 0 (0: from STAMPS)", o->exptime);
    milk_ctx m;
    memset(&m, 0, sizeof m);
    m.o = o;
    int rc = check_paths(o);
    if (!rc && o->clock) {
        rc = swfs_clock_read(o->clock, &m.clock);
        m.have_clock = !rc;
    }
    swfs_run_hooks hk = {milk_next, &m, milk_prepare, NULL, &m, 1};
    if (!rc) rc = swfs_stream_run_hooked(o, &hk, r);
    if (m.src) {
        swfs_milk_source_get_stats(m.src, &r->stamps);
        r->stamped = 1;
        if (r->stamps.sync.wfs_period > 0 && r->stamps.exptime > 0)
            r->ratio = r->stamps.exptime * (1.0 + m.clock.drift) / r->stamps.sync.wfs_period;
    }
    if (rc == SWFS_ERR_VALUE && m.src && !r->camera_frames && !strstr(swfs_last_error(), "overlap"))
        swfs_fail_context(rc, "%s: %llu camera frames without WFS data around their exposure, %llu incomplete", o->science,
                          (unsigned long long)r->stamps.sync.no_wfs, (unsigned long long)r->stamps.sync.incomplete);
    swfs_milk_source_close(m.src);
    return rc;
}

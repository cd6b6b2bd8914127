/* live: shared-memory streams -> the streaming run -> products and DM offsets. See
 * include/specklewfs/live.h and docs/live.md. */
#include "specklewfs/live.h"
#include "specklewfs/fits.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

void swfs_live_options_default(swfs_live_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_stream_run_options_default(&o->run);
    swfs_shm_source_options_default(&o->src);
    swfs_dmfit_options_default(&o->dmfit);
    o->dm_gain = 0.5;
    o->dm_scale = 1.0;
    o->dm_settle = 0.1;
}

typedef struct live_ctx {
    const swfs_live_options *o;
    swfs_shm_source *src;
    swfs_geom g;
    double *xy;
    size_t nact;
    swfs_dmfit *fit;
    swfs_shm *dm;
    double *target, *cmd, *total, *out, *fitted;
    swfs_live_result *r;
} live_ctx;

static int live_next(void *ctx, swfs_batch *b)
{
    live_ctx *l = ctx;
    return swfs_shm_source_next(l->src, b);
}

/* The pipeline is built: open the streams with the sizes it needs. */
static int live_prepare(void *ctx, const swfs_pipeline_info *info, const long *lags)
{
    live_ctx *l = ctx;
    swfs_shm_source_options so = l->o->src;
    /* a space-time map: the streams give one frame's slopes, the batches stack them */
    so.nslopes = info->nslopes / (lags ? info->nlags : 1);
    so.sync.lags = lags;
    so.sync.nlags = lags ? info->nlags : 0;
    so.nfx = info->nfx;
    so.nfy = info->nfy;
    return swfs_shm_source_open(&l->src, &so);
}

/* The DM output stream: an existing one of nact values, or a new nact x 1 float32. */
static int open_dm(live_ctx *l)
{
    const swfs_live_options *o = l->o;
    swfs_shm *m = NULL;
    if (swfs_shm_open(&m, o->src.dir, o->dm_out) == SWFS_OK) {
        if (swfs_shm_frame_values(m) != l->nact) {
            const int rc = swfs_fail(SWFS_ERR_SHAPE, "DM stream %s has %zu values per frame but %s has %zu actuators",
                                     swfs_shm_get_path(m), swfs_shm_frame_values(m), o->run.actuators, l->nact);
            swfs_shm_close(m, 0);
            return rc;
        }
        l->dm = m;
        /* Offsets are added to what the DM channel holds now. */
        size_t n = 0;
        swfs_shm_frame fm;
        int rc = swfs_shm_read_latest(m, l->out, &fm, &n);
        if (rc) return rc;
        for (size_t a = 0; a < l->nact && n; a++) l->total[a] = l->out[a] / o->dm_scale;
        return SWFS_OK;
    }
    swfs_shm_shape sh = {SWFS_SHM_F32, l->nact, 1, 1, 0, 0};
    return swfs_shm_create(&l->dm, o->src.dir, o->dm_out, &sh);
}

/* The fit of the correction surface, robust to the phase ambiguity of the pupil step: a
 * WFE sample is known modulo the wavelength (a surface modulo lambda/2), and where the
 * pupil field is faint (e.g. along the central obstruction) its phase is noise. A DM
 * cannot make a step of lambda/4 between neighbours, so samples farther than lambda/4 of
 * surface from the fitted surface are moved by whole lambda/2 onto the branch nearest to
 * it, those still farther than lambda/8 take the fitted value, and the fit is repeated
 * (at most three times; in the normal case, residuals of tens of nm, nothing changes). */
static int fit_robust(live_ctx *l, swfs_dmfit_stats *st, size_t *nfixed)
{
    const size_t n2 = (size_t)l->g.pupn * (size_t)l->g.pupn;
    const double *mask = swfs_dmfit_mask(l->fit), half = 0.5 * l->g.wavelen;
    *nfixed = 0;
    int rc = swfs_dmfit_apply(l->fit, l->target, l->cmd, l->fitted, st);
    for (int pass = 0; pass < 3 && !rc; pass++) {
        size_t changed = 0;
        for (size_t k = 0; k < n2; k++) {
            if (!(mask[k] > 0)) continue;
            double d = l->target[k] - l->fitted[k];
            if (fabs(d) > 0.5 * half) {
                l->target[k] -= half * round(d / half);
                d = l->target[k] - l->fitted[k];
                changed++;
            }
            if (fabs(d) > 0.25 * half) {
                l->target[k] = l->fitted[k];
                changed++;
            }
        }
        if (!changed) break;
        *nfixed += changed;
        rc = swfs_dmfit_apply(l->fit, l->target, l->cmd, l->fitted, st);
    }
    return rc;
}

static double rms_active(const double *c, size_t n, size_t nactive)
{
    double s = 0;
    for (size_t a = 0; a < n; a++) s += c[a] * c[a];
    return nactive ? sqrt(s / (double)nactive) : 0.0;
}

/* After every product update: DM offsets from the pupil WFE, then a new accumulation. */
static int live_after(void *ctx, swfs_stream *s, const swfs_halo *h, const swfs_pupil_result *pr, int final)
{
    live_ctx *l = ctx;
    const swfs_live_options *o = l->o;
    (void)h;
    if (!o->dm_out || (final && !o->dm_final) || !pr) return SWFS_OK;
    int rc = SWFS_OK;
    const size_t n2 = (size_t)l->g.pupn * (size_t)l->g.pupn;
    if (!l->fit) {
        if ((rc = swfs_dmfit_create(&l->fit, l->xy, l->nact, &l->g, pr->mask ? pr->mask->data : NULL, &o->dmfit)))
            return swfs_fail_context(rc, "%s", o->run.actuators);
        l->target = malloc(n2 * sizeof *l->target);
        l->cmd = malloc(l->nact * sizeof *l->cmd);
        l->total = calloc(l->nact, sizeof *l->total);
        l->out = malloc(l->nact * sizeof *l->out);
        l->fitted = malloc(n2 * sizeof *l->fitted);
        if (!l->target || !l->cmd || !l->total || !l->out || !l->fitted) return swfs_fail(SWFS_ERR_NOMEM, "live: out of memory");
        if ((rc = open_dm(l))) return rc;
    }
    /* dmoffsets: the correction surface -WFE/2 (reflective DM) fitted onto the actuators. */
    for (size_t k = 0; k < n2; k++) l->target[k] = -0.5 * pr->wfe->data[k];
    if (!o->dm_tiptilt) swfs_wfe_remove_ptt(l->target, swfs_dmfit_mask(l->fit), (size_t)l->g.pupn);
    swfs_dmfit_stats st;
    size_t nfixed = 0;
    if ((rc = fit_robust(l, &st, &nfixed))) return rc;
    l->r->dm_fixed = nfixed;
    double amax = 0;
    for (size_t a = 0; a < l->nact; a++) {
        l->cmd[a] *= o->dm_gain;
        amax = fmax(amax, fabs(l->cmd[a]));
    }
    if (o->dm_max_step > 0 && amax > o->dm_max_step)
        for (size_t a = 0; a < l->nact; a++) l->cmd[a] *= o->dm_max_step / amax;
    for (size_t a = 0; a < l->nact; a++) l->total[a] += l->cmd[a];
    const size_t nactive = swfs_dmfit_active(l->fit);
    const double trms = rms_active(l->total, l->nact, nactive);
    if (o->dm_max_rms > 0 && trms > o->dm_max_rms)
        for (size_t a = 0; a < l->nact; a++) l->total[a] *= o->dm_max_rms / trms;
    for (size_t a = 0; a < l->nact; a++) l->out[a] = l->total[a] * o->dm_scale;
    if ((rc = swfs_shm_write(l->dm, l->out, 0))) return rc;
    l->r->dm_updates++;
    l->r->dm_step_rms = rms_active(l->cmd, l->nact, nactive);
    l->r->dm_total_rms = rms_active(l->total, l->nact, nactive);
    if (o->dm_file) {
        swfs_dmfit_stats ts = st; /* the file holds the total: its statistics */
        ts.cmd_rms = l->r->dm_total_rms;
        ts.cmd_min = ts.cmd_max = l->total[0];
        for (size_t a = 1; a < l->nact; a++) {
            ts.cmd_min = fmin(ts.cmd_min, l->total[a]);
            ts.cmd_max = fmax(ts.cmd_max, l->total[a]);
        }
        if ((rc = swfs_dmfit_write(l->fit, l->total, l->target, &ts, o->dm_file, &l->g, o->run.prov, o->run.nprov)))
            return rc;
    }
    /* The frames after this point see the new DM: skip those that began before it had
     * settled and start a new accumulation (the estimate of a changed NCP must not mix
     * the two states). */
    swfs_shm_source_settle(l->src, o->dm_settle);
    if (!o->dm_keep) swfs_stream_reset(s);
    return SWFS_OK;
}

int swfs_live_run(const swfs_live_options *o, swfs_live_result *r)
{
    memset(r, 0, sizeof *r);
    const int crc = swfs_live_options_check(o);
    if (crc) return crc;
    live_ctx l;
    memset(&l, 0, sizeof l);
    l.o = o;
    l.r = r;
    int rc = SWFS_OK;
    if (o->dm_out) {
        swfs_fits_in *f = NULL;
        rc = o->run.science ? swfs_fits_in_open(&f, o->run.science, NULL)
                            : swfs_fail(SWFS_ERR_ARG, "live: needs a geometry file");
        if (!rc) rc = swfs_fits_in_geom(f, &l.g);
        swfs_fits_in_close(f);
        if (!rc && o->run.actuators) rc = swfs_actuators_read(o->run.actuators, &l.xy, &l.nact);
    }
    swfs_run_hooks hk = {live_next, &l, live_prepare, live_after, &l, 0};
    if (!rc) rc = swfs_stream_run_hooked(&o->run, &hk, &r->run);
    if (l.src) swfs_shm_source_get_stats(l.src, &r->src);
    swfs_shm_source_close(l.src);
    swfs_shm_close(l.dm, 0);
    swfs_dmfit_free(l.fit);
    free(l.xy);
    free(l.target);
    free(l.cmd);
    free(l.total);
    free(l.out);
    free(l.fitted);
    return rc;
}

/* The stream: see include/specklewfs/stream.h. */
#include "specklewfs/parallel.h"
#include "specklewfs/stream.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

struct swfs_stream {
    swfs_stream_options opt;
    swfs_pipeline *p;
    size_t nfx, nfy, nf2;
    swfs_accum *acc;
    swfs_complex *stat; /* nf2 */
    int stat_pending;   /* SWFS_STATIC_AUTO before the first batch: stat holds Psi_0 */
    double stat_scale;
    swfs_complex *out;  /* focal fields of the current batch */
    size_t outcap;      /* camera frames out holds */
    swfs_complex *psi;  /* nf2 */
    size_t cam;
    double wfs, seconds;
};

void swfs_stream_options_default(swfs_stream_options *o)
{
    memset(o, 0, sizeof *o);
    o->static_mode = SWFS_STATIC_AUTO;
    o->est.g_smooth = 0.0;
}

void swfs_stream_free(swfs_stream *s)
{
    if (!s) return;
    swfs_accum_free(s->acc);
    free(s->stat);
    free(s->out);
    free(s->psi);
    free(s);
}

int swfs_stream_create(swfs_stream **out, swfs_pipeline *p, const swfs_stream_options *opt)
{
    *out = NULL;
    swfs_stream_options def;
    if (!opt) {
        swfs_stream_options_default(&def);
        opt = &def;
    }
    if (swfs_pipeline_opts(p)->wfs_rate)
        return swfs_fail(SWFS_ERR_ARG, "stream: the pipeline is made for the WFS rate; a stream pairs camera exposures");
    if (opt->static_mode < SWFS_STATIC_AUTO || opt->static_mode > SWFS_STATIC_GIVEN)
        return swfs_fail(SWFS_ERR_ARG, "stream: unknown static-halo mode %d", opt->static_mode);
    if (opt->static_mode == SWFS_STATIC_GIVEN && !opt->static_halo)
        return swfs_fail(SWFS_ERR_ARG, "stream: SWFS_STATIC_GIVEN needs the static halo");
    if (!(opt->every_seconds >= 0) || !(opt->noise.read_noise >= 0) || !(opt->noise.gain >= 0))
        return swfs_fail(SWFS_ERR_ARG, "stream: every_seconds, read noise and gain must be >= 0 (got %g, %g, %g)",
                         opt->every_seconds, opt->noise.read_noise, opt->noise.gain);
    swfs_pipeline_info in;
    swfs_pipeline_get_info(p, &in);
    swfs_stream *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory");
    s->opt = *opt;
    s->opt.static_halo = NULL;
    s->p = p;
    s->nfx = in.nfx;
    s->nfy = in.nfy;
    s->nf2 = in.nfx * in.nfy;
    s->stat_scale = NAN;
    s->acc = swfs_accum_create(s->nfx, s->nfy);
    s->stat = calloc(s->nf2, sizeof *s->stat);
    s->psi = malloc(s->nf2 * sizeof *s->psi);
    if (!s->acc || !s->stat || !s->psi) {
        swfs_stream_free(s);
        return swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory for %zux%zu accumulators", s->nfx, s->nfy);
    }
    int rc = SWFS_OK;
    if (opt->static_mode == SWFS_STATIC_GIVEN) memcpy(s->stat, opt->static_halo, s->nf2 * sizeof *s->stat);
    else if (opt->static_mode == SWFS_STATIC_AUTO) {
        /* eq:computedSpeckleField with S^1/2 Psi_0: Psi_0 now, S^1/2 from the first batch. */
        rc = swfs_pipeline_flat_halo(p, s->stat);
        s->stat_pending = 1;
    }
    if (rc) {
        swfs_stream_free(s);
        return rc;
    }
    *out = s;
    return SWFS_OK;
}

int swfs_stream_push(swfs_stream *s, const swfs_batch *b)
{
    if (!b->nexp) return SWFS_OK;
    const double t0 = swfs_wall_seconds();
    if (b->nexp > s->outcap) {
        if (b->nexp > SIZE_MAX / sizeof(swfs_complex) / s->nf2)
            return swfs_fail(SWFS_ERR_VALUE, "stream: batch of %zu frames is too large", b->nexp);
        swfs_complex *t = realloc(s->out, b->nexp * s->nf2 * sizeof *t);
        if (!t) return swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory for a batch of %zu frames", b->nexp);
        s->out = t;
        s->outcap = b->nexp;
    }
    int rc = swfs_pipeline_process(s->p, b->slopes, b->nwfs, b->sched, b->nexp, s->out);
    if (rc) return rc;
    const size_t nf2 = s->nf2;
    if (s->stat_pending) {
        /* S^1/2 Psi_0: the referenced cores are real; scale Psi_0 to their mean. */
        const size_t core = (s->nfy / 2) * s->nfx + s->nfx / 2;
        double m = 0.0;
        for (size_t j = 0; j < b->nexp; j++) m += creal(s->out[j * nf2 + core]);
        m /= (double)b->nexp * creal(s->stat[core]);
        for (size_t k = 0; k < nf2; k++) s->stat[k] *= m;
        s->stat_scale = m;
        s->stat_pending = 0;
    }
    for (size_t j = 0; j < b->nexp; j++) {
        for (size_t k = 0; k < nf2; k++) s->psi[k] = s->out[j * nf2 + k] - s->stat[k];
        if ((rc = swfs_accum_add(s->acc, b->science + j * nf2, s->psi))) return rc;
        const swfs_exposure *e = &b->sched[j];
        s->wfs += e->count == 1 ? e->w_first : e->w_first + e->w_last + (double)(e->count - 2);
    }
    s->cam += b->nexp;
    s->seconds += swfs_wall_seconds() - t0;
    return SWFS_OK;
}

int swfs_stream_run(swfs_stream *s, swfs_source_fn next, void *src_ctx, swfs_stream_update_fn update, void *upd_ctx)
{
    size_t since = 0;
    double t_last = swfs_wall_seconds();
    for (;;) {
        swfs_batch b;
        memset(&b, 0, sizeof b);
        int rc = next(src_ctx, &b);
        if (rc) return rc;
        if (!b.nexp) break;
        if (s->opt.max_frames && s->cam + b.nexp > s->opt.max_frames) b.nexp = s->opt.max_frames - s->cam;
        if ((rc = swfs_stream_push(s, &b))) return swfs_fail_context(rc, "batch of cube %zu", b.cube);
        since += b.nexp;
        const double now = swfs_wall_seconds();
        if (update && ((s->opt.every && since >= s->opt.every) ||
                       (s->opt.every_seconds > 0 && now - t_last >= s->opt.every_seconds))) {
            if ((rc = update(upd_ctx, s, 0))) return rc;
            since = 0;
            t_last = swfs_wall_seconds();
        }
        if (s->opt.max_frames && s->cam >= s->opt.max_frames) break;
    }
    if (!s->cam) return swfs_fail(SWFS_ERR_NUMERIC, "stream: the source gave no camera frame");
    return update ? update(upd_ctx, s, 1) : SWFS_OK;
}

void swfs_stream_reset(swfs_stream *s)
{
    swfs_accum_reset(s->acc);
    s->cam = 0;
    s->wfs = 0.0;
}

int swfs_stream_attach_resmean(const swfs_stream *s, swfs_halo *h)
{
    swfs_pipeline_info in;
    swfs_pipeline_get_info(s->p, &in);
    swfs_real *m = swfs_real_alloc(in.npup, in.npup, 1);
    if (!m) return swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory");
    int rc = swfs_pipeline_mean_wavefront(s->p, m->data, NULL, NULL);
    if (rc) {
        swfs_real_free(m);
        return rc;
    }
    swfs_real_free(h->resmean);
    h->resmean = m;
    return SWFS_OK;
}

int swfs_stream_estimate(const swfs_stream *s, swfs_halo **out)
{
    int rc = swfs_estimate(s->acc, &s->opt.noise, &s->opt.est, out);
    if (!rc && (rc = swfs_stream_attach_resmean(s, *out))) {
        swfs_halo_free(*out);
        *out = NULL;
    }
    return rc;
}

const swfs_accum *swfs_stream_accum(const swfs_stream *s) { return s->acc; }
const swfs_complex *swfs_stream_static(const swfs_stream *s) { return s->stat_pending ? NULL : s->stat; }
size_t swfs_stream_camera_frames(const swfs_stream *s) { return s->cam; }
double swfs_stream_wfs_frames(const swfs_stream *s) { return s->wfs; }
double swfs_stream_seconds(const swfs_stream *s) { return s->seconds; }
double swfs_stream_static_scale(const swfs_stream *s) { return s->stat_scale; }

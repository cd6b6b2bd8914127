/* The time-series simulator's telemetry as milk/cacao stream logs: see ts_milk.h and
 * include/specklewfs/timeseries.h (milk=1). */
#include "ts_milk.h"
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/milklog.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The logger writes a frame's line after it was acquired: the logging time (column 4)
 * trails the acquisition time (column 5, the one to use) by this much. */
static const int64_t LOG_LATENCY_NS = 20000;

static int badv(const char *key, double v, const char *what)
{
    return swfs_fail(SWFS_ERR_VALUE, "time-series parameter %s=%g: %s", key, v, what);
}

int swfs_ts_milk_check(const swfs_ts_params *p)
{
    const double period = 1.0 / p->wfs_rate, exposure = p->frame_ratio * period;
    if (p->milk != 0 && p->milk != 1) return badv("milk", (double)p->milk, "must be 0 or 1");
    if (!(p->milk_epoch >= 0 && p->milk_epoch < 4e9) || p->milk_epoch != floor(p->milk_epoch))
        return badv("milk_epoch", p->milk_epoch, "must be whole seconds of the Unix epoch in [0, 4e9)");
    /* Stamps must stay in order: the jitter well below the shorter frame period. */
    if (!(p->milk_jitter >= 0 && p->milk_jitter <= 0.1 * fmin(period, exposure)))
        return badv("milk_jitter", p->milk_jitter, "must be in [0, 0.1 x the shorter frame period]");
    if (!(fabs(p->milk_drift) <= 0.01)) return badv("milk_drift", p->milk_drift, "must be in [-0.01, 0.01]");
    if (!(fabs(p->milk_offset) <= 100)) return badv("milk_offset", p->milk_offset, "must be within 100 s");
    if (p->milk_drop_wfs < 0 || p->milk_drop_cam < 0)
        return badv("milk_drop_wfs", (double)(p->milk_drop_wfs < 0 ? p->milk_drop_wfs : p->milk_drop_cam),
                    "dropped frames must be >= 0");
    if (p->milk_drop_cam * 10 > p->ncubes * p->cube_frames)
        return badv("milk_drop_cam", (double)p->milk_drop_cam, "at most a tenth of the camera frames");
    if (p->milk_file_frames < 1 || p->milk_cam_file_frames < 1)
        return badv("milk_file_frames", (double)(p->milk_file_frames < 1 ? p->milk_file_frames : p->milk_cam_file_frames),
                    "frames per file must be >= 1");
    return SWFS_OK;
}

typedef struct plan {
    size_t nwfs, nexp, nf;
    int64_t *wst, *cst;            /* stamps [ns] */
    unsigned char *wdrop, *cdrop;  /* 1: left out of the files */
} plan;

static void plan_free(plan *pl)
{
    free(pl->wst);
    free(pl->cst);
    free(pl->wdrop);
    free(pl->cdrop);
}

/* want distinct frames among 1 .. n - 2 (a first or last frame lost shows no counter jump). */
static void pick_drops(swfs_rng *r, size_t n, long want, unsigned char *drop)
{
    if (n < 3) return;
    for (long got = 0; got < want && (size_t)got < n - 2;) {
        size_t k = 1 + (size_t)(swfs_rng_uniform(r) * (double)(n - 2));
        if (k > n - 2) k = n - 2;
        if (!drop[k]) {
            drop[k] = 1;
            got++;
        }
    }
}

static int make_plan(const swfs_ts_params *p, size_t nwfs, const double *tstart, plan *pl)
{
    memset(pl, 0, sizeof *pl);
    pl->nwfs = nwfs;
    pl->nf = (size_t)p->cube_frames;
    pl->nexp = pl->nf * (size_t)p->ncubes;
    pl->wst = malloc(nwfs * sizeof *pl->wst);
    pl->cst = malloc(pl->nexp * sizeof *pl->cst);
    pl->wdrop = calloc(nwfs, 1);
    pl->cdrop = calloc(pl->nexp, 1);
    if (!pl->wst || !pl->cst || !pl->wdrop || !pl->cdrop) {
        plan_free(pl);
        return swfs_fail(SWFS_ERR_NOMEM, "milk logs: out of memory for %zu WFS and %zu camera stamps", nwfs, pl->nexp);
    }
    swfs_rng r;
    swfs_rng_seed2(&r, p->base.seed, 0x6d696c6bu); /* a stream of its own: the simulation is unchanged */
    const int64_t epoch = (int64_t)p->milk_epoch * 1000000000LL;
    for (size_t k = 0; k < nwfs; k++)
        pl->wst[k] = epoch + llround(1e9 * ((double)(k + 1) / p->wfs_rate + p->milk_jitter * swfs_rng_normal(&r)));
    for (size_t e = 0; e < pl->nexp; e++) {
        const size_t c = e / pl->nf, j = e % pl->nf;
        const double tw = (tstart[c] + (double)(j + 1) * p->frame_ratio) / p->wfs_rate; /* the exposure's end */
        const double tc = (tw - p->milk_offset) / (1.0 + p->milk_drift) + p->milk_jitter * swfs_rng_normal(&r);
        pl->cst[e] = epoch + llround(1e9 * tc);
    }
    pick_drops(&r, nwfs, p->milk_drop_wfs, pl->wdrop);
    pick_drops(&r, pl->nexp, p->milk_drop_cam, pl->cdrop);
    return SWFS_OK;
}

/* The files: WFS chunks of milk_file_frames frames; camera chunks of milk_cam_file_frames
 * within each cube. File f of a stream covers frames [*a, *b); 0 when there is no file f. */
static int chunk(const swfs_ts_params *p, const plan *pl, int cam, size_t f, size_t *a, size_t *b)
{
    if (!cam) {
        const size_t F = (size_t)p->milk_file_frames;
        if (f * F >= pl->nwfs) return 0;
        *a = f * F;
        *b = *a + F < pl->nwfs ? *a + F : pl->nwfs;
        return 1;
    }
    const size_t F = (size_t)p->milk_cam_file_frames, per = (pl->nf + F - 1) / F, c = f / per, q = f % per;
    if (c >= (size_t)p->ncubes) return 0;
    *a = c * pl->nf + q * F;
    *b = q * F + F < pl->nf ? *a + F : (c + 1) * pl->nf;
    return 1;
}

/* dir/milk/<wfs|cam>/<stem> of the chunk [a, b) (stem from its first kept frame); 0: every
 * frame of the chunk was dropped. */
static int chunk_path(const char *dir, const plan *pl, int cam, size_t a, size_t b, const char *ext, char *path,
                      size_t cap)
{
    const unsigned char *drop = cam ? pl->cdrop : pl->wdrop;
    const int64_t *st = cam ? pl->cst : pl->wst;
    size_t k = a;
    while (k < b && drop[k]) k++;
    if (k == b) return 0;
    char stem[256];
    swfs_milk_file_stem(cam ? "cam" : "wfs", st[k], stem, sizeof stem);
    snprintf(path, cap, "%s/milk/%s/%s%s", dir, cam ? "cam" : "wfs", stem, ext);
    return 1;
}

int swfs_ts_milk_outputs(const swfs_ts_params *p, const char *dir, size_t nwfs, const double *tstart, swfs_paths *paths)
{
    if (!p->milk) return swfs_paths_status(paths);
    plan pl;
    int rc = make_plan(p, nwfs, tstart, &pl);
    if (rc) return rc;
    char path[8192];
    size_t a, b;
    for (int cam = 0; cam < 2; cam++)
        for (size_t f = 0; chunk(p, &pl, cam, f, &a, &b); f++)
            for (int t = 0; t < 2; t++)
                if (chunk_path(dir, &pl, cam, a, b, t ? ".txt" : ".fits", path, sizeof path))
                    swfs_paths_output(paths, "milk log output", path);
    snprintf(path, sizeof path, "%s/milk/truth.txt", dir);
    swfs_paths_output(paths, "milk log output", path);
    plan_free(&pl);
    return swfs_paths_status(paths);
}

typedef struct wctx {
    const swfs_ts_params *p;
    const char *dir;
    const plan *pl;
    const swfs_geom *g;
    const char *const *prov;
    size_t nprov;
    double gain;
    double *buf;
    uint64_t *cnt;
    int64_t *acq, *logt;
} wctx;

/* One file: the kept frames of [a, b) (nv values each: a vector N x 1, or an nfx x nfy image). */
static int write_chunk(const wctx *w, int cam, size_t a, size_t b, const double *data, size_t nx, size_t ny)
{
    const plan *pl = w->pl;
    char fits[8192], txt[8192];
    if (!chunk_path(w->dir, pl, cam, a, b, ".fits", fits, sizeof fits)) return SWFS_OK;
    chunk_path(w->dir, pl, cam, a, b, ".txt", txt, sizeof txt);
    const unsigned char *drop = cam ? pl->cdrop : pl->wdrop;
    const int64_t *st = cam ? pl->cst : pl->wst;
    const size_t nv = nx * ny;
    size_t n = 0;
    for (size_t k = a; k < b; k++) {
        if (drop[k]) continue;
        memcpy(w->buf + n * nv, data + k * nv, nv * sizeof *w->buf);
        w->cnt[n] = k + 1;
        w->acq[n] = st[k];
        w->logt[n] = st[k] + LOG_LATENCY_NS;
        n++;
    }
    swfs_real arr = {nx, ny, n, w->buf};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, fits);
    if (rc) return rc;
    if ((rc = swfs_fits_out_set_stamp(o, cam ? w->g : NULL, w->prov, w->nprov)) ||
        (rc = swfs_fits_out_real(o, NULL, &arr, -32)) ||
        (cam && w->gain > 0 && (rc = swfs_fits_out_key_double(o, "GAIN", w->gain, "[e-/count]"))) ||
        (cam && (rc = swfs_fits_out_key_double(o, "EXPTIME", w->p->frame_ratio / w->p->wfs_rate, "[s] exposure time"))) ||
        (!cam && (rc = swfs_fits_out_key_string(o, "BUNIT", "rad", "wavefront tilt: x slopes then y slopes")))) {
        swfs_fits_out_abort(o);
        return rc;
    }
    if ((rc = swfs_fits_out_commit(o))) return rc;
    return swfs_milk_txt_write(txt, w->cnt, w->acq, w->logt, n, a);
}

static int write_truth(const swfs_ts_params *p, const char *dir, const plan *pl)
{
    char path[8192];
    snprintf(path, sizeof path, "%s/milk/truth.txt", dir);
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    FILE *f = swfs_atomic_stream(a);
    size_t dw = 0, dc = 0;
    for (size_t k = 0; k < pl->nwfs; k++) dw += pl->wdrop[k];
    for (size_t k = 0; k < pl->nexp; k++) dc += pl->cdrop[k];
    fprintf(f, "# the simulated milk logs: t_wfs = epoch + (t_cam - epoch) (1 + drift) + offset\n");
    fprintf(f, "epoch %.0f\ndrift %.9g\noffset %.9g\njitter %.9g\n", p->milk_epoch, p->milk_drift, p->milk_offset,
            p->milk_jitter);
    fprintf(f, "wfs_dropped %zu\ncam_dropped %zu\nexptime %.9g\nwfs_period %.9g\n", dw, dc,
            p->frame_ratio / p->wfs_rate, 1.0 / p->wfs_rate);
    return swfs_atomic_commit(a);
}

int swfs_ts_milk_write(const swfs_ts_params *p, const char *dir, const double *slopes, size_t nwfs, size_t ns,
                       const double *raw, size_t nfx, size_t nfy, const double *tstart, const swfs_geom *g,
                       const char *const *prov, size_t nprov, double gain)
{
    plan pl;
    int rc = make_plan(p, nwfs, tstart, &pl);
    if (rc) return rc;
    const size_t fw = (size_t)p->milk_file_frames, fc = (size_t)p->milk_cam_file_frames;
    const size_t rows = fw > fc ? fw : fc, vals = ns * fw > nfx * nfy * fc ? ns * fw : nfx * nfy * fc;
    wctx w = {p, dir, &pl, g, prov, nprov, gain, malloc(vals * sizeof(double)), malloc(rows * sizeof(uint64_t)),
              malloc(rows * sizeof(int64_t)), malloc(rows * sizeof(int64_t))};
    if (!w.buf || !w.cnt || !w.acq || !w.logt) rc = swfs_fail(SWFS_ERR_NOMEM, "milk logs: out of memory");
    size_t a, b;
    for (size_t f = 0; !rc && chunk(p, &pl, 0, f, &a, &b); f++) rc = write_chunk(&w, 0, a, b, slopes, ns, 1);
    for (size_t f = 0; !rc && chunk(p, &pl, 1, f, &a, &b); f++) rc = write_chunk(&w, 1, a, b, raw, nfx, nfy);
    if (!rc) rc = write_truth(p, dir, &pl);
    free(w.buf);
    free(w.cnt);
    free(w.acq);
    free(w.logt);
    plan_free(&pl);
    return rc;
}

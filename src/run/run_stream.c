/* stream: the whole real-time path from files. See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/source.h"
#include "run_internal.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

void swfs_stream_run_options_default(swfs_stream_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_geom_init(&o->geom);
    swfs_linear_files_default(&o->lin);
    o->tiptilt = SWFS_TT_EXPOSURE;
    o->threads = 2;
    o->batch = 128;
    o->read_noise = o->gain = NAN;
    o->g_smooth_lod = 2.0;
    swfs_stream_options_default(&o->stream);
    o->mean_teach = SWFS_MEAN_TEACH_AUTO;
    o->mean_teach_loops = 4;
}

/* --mean-loop teach (and a pyramid's default), as speckles': the loops of the system the
 * files describe, simulated or reused by run_mean_teach.c with the run's files (its timing
 * table, their folder or --slopes DIR, the geometry, the linear model); dirs their folders. */
static int stream_mean_teach(const swfs_stream_run_options *o, const swfs_geom *g, size_t nslopes,
                             swfs_stream_run_result *r, char (*dirs)[4400], const char **loops)
{
    swfs_speckles_run_options so;
    swfs_speckles_run_options_default(&so);
    so.timing = o->timing;
    so.science = o->science;
    so.out = o->out;
    so.lin = o->lin;
    so.mask = o->mask;
    so.mean_teach = o->mean_teach;
    so.mean_teach_loops = o->mean_teach_loops;
    so.mean_teach_max_loops = o->mean_teach_max_loops; /* speckles' loops for the same files */
    so.teach_work = o->teach_work;
    so.teach_again = o->teach_again;
    so.prov = o->prov;
    so.nprov = o->nprov;
    so.team = o->team;
    if (!o->team) { /* the loops' simulation stops as the stream would (a team's members run them alike) */
        so.progress = o->progress;
        so.progress_ctx = o->progress_ctx;
    }
    char tdir[4096];
    struct stat st;
    if (o->slopes && !stat(o->slopes, &st) && S_ISDIR(st.st_mode)) snprintf(tdir, sizeof tdir, "%s", o->slopes);
    else swfs_path_dir(o->timing, tdir, sizeof tdir);
    swfs_timing *t = NULL;
    int rc = swfs_timing_read(o->timing, &t);
    if (!rc) rc = swfs_speckles_mean_teach_(&so, t, tdir, g, nslopes, &r->mean_teach, dirs, loops);
    swfs_timing_free(t);
    return rc;
}

/* Pupil mask: a file (its PUPIL extension if it has one) or the annulus of the geometry. */
static int load_mask(const char *path, const swfs_geom *g, swfs_real **out)
{
    *out = NULL;
    return path ? swfs_pupil_mask_read(path, (size_t)g->pupn, out) : SWFS_OK;
}

static int write_static(const char *path, const swfs_complex *stat, size_t nfx, size_t nfy, const swfs_geom *g,
                        const char *const *prov, size_t nprov)
{
    swfs_cplx a = {nfx, nfy, 1, (swfs_complex *)stat};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    if ((rc = swfs_fits_out_set_stamp(o, g, prov, nprov)) || (rc = swfs_fits_out_cplx(o, NULL, &a, -64)) ||
        (rc = swfs_fits_out_history(o, "static halo subtracted from the speckle fields (eq:computedSpeckleField)"))) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

typedef struct run_ctx {
    const swfs_stream_run_options *o;
    const swfs_stream_options *so;
    const swfs_accum *merged; /* a team's union of the accumulators (member 0, at the end), else NULL */
    swfs_geom g;
    swfs_real *mask;
    const char **prov;
    size_t nprov;
    int static_written;
    const swfs_run_hooks *hk;
    swfs_stream *stream;
    int updated;              /* products of an update are in place */
    size_t nlags;             /* a space-time reconstructor's lags (0: per frame) */
    long lags[SWFS_RECON_MAXLAGS];
} run_ctx;

/* The file source's batches for a space-time reconstructor: each WFS frame's slopes stacked
 * with those of frames t + lags, as `speckles` stacks them (swfs_lag_stacker_: across the
 * neighbour files the telemetry shows contiguous, clamped beyond; one file for every cube,
 * stream --slopes FILE, has no neighbours). Per-frame reconstructors get the source's
 * batches as they are. */
typedef struct stacked_src {
    swfs_file_source *src;
    const swfs_timing *t;
    size_t nlags;
    const long *lags;
    swfs_lag_stacker_ stk;
} stacked_src;

static int stacked_next(void *ctx, swfs_batch *b)
{
    stacked_src *st = ctx;
    int rc = swfs_file_source_next(st->src, b);
    if (rc || !b->nexp || st->nlags < 2) return rc;
    swfs_file_source_pos pos;
    if (!(rc = swfs_file_source_last(st->src, &pos)))
        rc = swfs_lag_stacker_rows_(&st->stk, pos.dir, st->t, pos.name, pos.path, pos.tel, st->lags, st->nlags, pos.base,
                                    b->nwfs, &b->slopes);
    return rc;
}

/* The products already under the run's output names (out, pupil_out, checkpoint, static_out),
 * kept aside by a hard link until the run ends, so that a run from files that fails or is
 * stopped after its first update puts them back rather than leaving none. */
typedef struct kept {
    const char *name[4];
    char prev[4][4200];
    int have[4];
} kept;

/* A copy of file `from` as the new file `to` (where a hard link is not allowed: a
 * filesystem without them, or protected_hardlinks on another user's file); 0 on success. */
static int copy_file(const char *from, const char *to)
{
    FILE *in = fopen(from, "rb");
    if (!in) return -1;
    const int fd = open(to, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    FILE *out = fd >= 0 ? fdopen(fd, "wb") : NULL;
    if (!out && fd >= 0) close(fd);
    char buf[65536];
    size_t n;
    int bad = !out;
    while (!bad && (n = fread(buf, 1, sizeof buf, in)) > 0) bad = fwrite(buf, 1, n, out) != n;
    bad = bad || ferror(in);
    fclose(in);
    if (out && fclose(out) != 0) bad = 1;
    if (bad && out) unlink(to);
    return bad ? -1 : 0;
}

static void keep_previous(kept *k, const swfs_stream_run_options *o)
{
    const char *const names[4] = {o->out, o->pupil_out, o->checkpoint, o->static_out};
    for (int i = 0; i < 4; i++) {
        k->name[i] = names[i];
        k->have[i] = 0;
        struct stat st;
        if (!names[i] || stat(names[i], &st) || !S_ISREG(st.st_mode)) continue; /* nothing to put back */
        /* a name of its own: NAME.prev.<pid>.<n>, the first free (one left by a run killed
         * outright may hold an earlier pid's) */
        for (int n = 0; n < 100 && !k->have[i]; n++) {
            if (snprintf(k->prev[i], sizeof k->prev[i], "%s.prev.%ld.%d", names[i], (long)getpid(), n) >=
                (int)sizeof k->prev[i])
                break;
            if (link(names[i], k->prev[i]) == 0) k->have[i] = 1;
            else if (errno != EEXIST) k->have[i] = copy_file(names[i], k->prev[i]) == 0;
        }
    }
}

/* The run failed: its own products removed (wrote[i]), the kept ones put back; or it
 * succeeded (restore 0): the kept ones dropped. (A kept link to a file the run never
 * replaced is the same file: the rename does nothing, and the unlink removes the link.) */
static void kept_end(kept *k, int restore, const int wrote[4])
{
    for (int i = 0; i < 4; i++) {
        if (restore && k->have[i] && rename(k->prev[i], k->name[i]) != 0) continue; /* left beside, to recover */
        if (restore && !k->have[i] && wrote[i] && k->name[i]) unlink(k->name[i]);
        if (k->have[i]) unlink(k->prev[i]);
    }
}

/* A source whose batches are reported to the caller's progress (swfs_stream_run_options). */
typedef struct progress_src {
    swfs_source_fn next;
    void *ctx;
    const swfs_stream_run_options *o;
    size_t done, total;
} progress_src;

static int progress_next(void *ctx, swfs_batch *b)
{
    progress_src *p = ctx;
    const int rc = p->next(p->ctx, b);
    if (rc || !b->nexp) return rc;
    p->done += b->nexp;
    if (p->total && p->done > p->total) p->done = p->total; /* the last batch cut at max_frames */
    return swfs_progress_report(p->o->progress, p->o->progress_ctx, "camera frames", p->done, p->total);
}

/* The camera frames a run from a timing table takes: its usable cubes', the first max_frames
 * (0: all); len (if not NULL): each cube's share of them. */
static size_t usable_frames(const swfs_timing *t, size_t max_frames, size_t *len)
{
    size_t total = 0;
    for (size_t c = 0; t && c < t->ncubes; c++) {
        size_t n = t->cubes[c].status == SWFS_CUBE_OK ? t->cubes[c].nframes : 0;
        if (max_frames && total + n > max_frames) n = max_frames - total;
        if (len) len[c] = n;
        total += n;
    }
    return total;
}

/* Estimate from the accumulators and write the products. Before the end a failed estimate
 * (too few frames yet) is not an error: the next update tries again. */
static int update(void *ctx, const swfs_stream *s, int final)
{
    run_ctx *u = ctx;
    const swfs_stream_run_options *o = u->o;
    swfs_halo *h = NULL;
    swfs_pupil_result *pr = NULL;
    int rc = SWFS_OK;
    const swfs_accum *acc = u->merged ? u->merged : swfs_stream_accum(s);
    if (o->static_out && !u->static_written && swfs_stream_static(s)) {
        if ((rc = write_static(o->static_out, swfs_stream_static(s), acc->nx, acc->ny, &u->g, u->prov, u->nprov)))
            return rc;
        u->static_written = 1;
    }
    if (u->merged) {
        rc = swfs_estimate(acc, &u->so->noise, &u->so->est, &h);
        if (!rc && (rc = swfs_stream_attach_resmean(s, h))) {
            swfs_halo_free(h);
            h = NULL;
        }
    } else {
        rc = swfs_stream_estimate(s, &h);
    }
    if (rc) {
        if (final) return rc;
        if (o->on_update) o->on_update(o->update_ctx, s, NULL, NULL, 0);
        return SWFS_OK;
    }
    /* One update's products are renamed into place together (atomic.h). */
    swfs_outputs_begin();
    rc = swfs_halo_write(h, o->out, &u->g, u->prov, u->nprov);
    if (!rc && o->pupil_out) {
        swfs_pupil_options po;
        swfs_pupil_options_default(&po);
        po.method = u->o->pupil_method;
        if (o->pupil_source) po.source = o->pupil_source;
        rc = swfs_pupil_estimate(h, &u->g, u->mask, &po, &pr);
        if (!rc) rc = swfs_pupil_write(pr, o->pupil_out, &u->g, u->prov, u->nprov);
    }
    if (!rc && o->checkpoint)
        rc = swfs_accum_save_resmean(acc, h->resmean, (size_t)acc->frames, o->checkpoint, &u->g, u->prov, u->nprov);
    int erc = swfs_outputs_end(rc == SWFS_OK);
    if (!rc) rc = erc;
    if (!rc) u->updated = 1;
    if (!rc && o->on_update) o->on_update(o->update_ctx, s, h, pr, final);
    if (!rc && u->hk && u->hk->after) rc = u->hk->after(u->hk->ctx, u->stream, h, pr, final);
    swfs_pupil_result_free(pr);
    swfs_halo_free(h);
    return rc;
}

void swfs_stream_paths_inputs(swfs_paths *p, const swfs_stream_run_options *o)
{
    swfs_paths_input(p, "science cube", o->science);
    swfs_paths_input(p, "reconstructor", o->recon);
    swfs_paths_input(p, "actuator file", o->actuators);
    if (o->valid) swfs_paths_input(p, "valid-subaperture map", o->valid);
    swfs_linear_paths(p, &o->lin);
    swfs_paths_input(p, "pupil mask", o->mask);
    swfs_paths_input(p, "static halo", o->static_file);
}

void swfs_stream_paths_outputs(swfs_paths *p, const swfs_stream_run_options *o)
{
    swfs_paths_output(p, "output halo", o->out);
    swfs_paths_output(p, "pupil output", o->pupil_out);
    swfs_paths_output(p, "checkpoint output", o->checkpoint);
    swfs_paths_output(p, "static-halo output", o->static_out);
}

/* Every input (the telemetry files of the timing table too) and output, before the work. */
static int check_paths(const swfs_stream_run_options *o, char *first_tel, size_t cap)
{
    swfs_paths *p = NULL;
    swfs_timing *t = NULL;
    char path[8192];
    int rc = swfs_paths_create(&p);
    swfs_paths_input(p, "timing table", o->timing);
    swfs_paths_input_or_dir(p, "telemetry (--slopes)", o->slopes);
    swfs_stream_paths_inputs(p, o);
    if (!rc) rc = swfs_paths_status(p);
    if (!rc) rc = swfs_timing_read(o->timing, &t);
    first_tel[0] = 0;
    for (size_t c = 0; !rc && c < t->ncubes; c++)
        if (!(rc = swfs_file_source_telemetry_path(o->timing, o->slopes, t->cubes[c].slopes, path, sizeof path))) {
            rc = swfs_paths_input(p, "telemetry file of the timing table", path);
            if (!first_tel[0] && t->cubes[c].status == SWFS_CUBE_OK) snprintf(first_tel, cap, "%s", path);
        }
    swfs_stream_paths_outputs(p, o);
    if (!rc) rc = swfs_paths_status(p);
    swfs_timing_free(t);
    swfs_paths_free(p);
    return rc;
}

/* The generic linear model's pipeline (run.h swfs_linear_files): the first telemetry file
 * (none for a live source) trains an interaction matrix's reconstructor and checks the
 * residual's size. */
static int setup_linear(const swfs_stream_run_options *o, const char *first_tel, run_ctx *u, swfs_pipeline **p,
                        size_t nfx, size_t nfy, swfs_stream_run_result *r)
{
    swfs_real *tr = NULL;
    int rc = load_mask(o->mask, &u->g, &u->mask);
    if (!rc && first_tel[0]) rc = swfs_telemetry_read(first_tel, 0, &tr, NULL);
    if (!rc && !tr && o->lin.imat)
        rc = swfs_fail(SWFS_ERR_ARG, "stream: an interaction matrix (%s) needs telemetry to learn its reconstructor from; "
                       "give a control matrix", o->lin.imat);
    if (!rc) {
        swfs_pipeline_options po;
        swfs_pipeline_options_default(&po);
        po.recon = SWFS_RECON_MAP;
        po.tiptilt = o->tiptilt;
        po.threads = o->threads;
        po.band = o->band;
        rc = swfs_linear_pipeline(p, &o->lin, &u->g, nfx, nfy, u->mask ? u->mask->data : NULL, tr ? tr->nx : 0,
                                  tr ? tr->data : NULL, tr ? tr->ny : 0, &po);
        if (rc) swfs_fail_context(rc, "with %s", tr ? first_tel : "the live telemetry");
        else swfs_pipeline_get_info(*p, &r->info);
        /* a space-time control matrix: its input stacked at its lags, as a reconstructor's below */
        size_t nl = 0;
        if (!rc) rc = swfs_linear_control_lags(&o->lin, u->lags, &nl);
        if (!rc && nl > 1) u->nlags = nl;
        if (!rc) rc = swfs_map_meanmiss_attach(*p, o->lin.control, &o->lin, &u->g, &r->meanmiss_rms);
    }
    swfs_real_free(tr);
    return rc;
}

/* Geometry and noise model of the science cube, the reconstructor and actuators -> the pipeline. */
static int setup(const swfs_stream_run_options *o, const char *first_tel, run_ctx *u, swfs_pipeline **p, size_t *nfx,
                 size_t *nfy, swfs_stream_run_result *r)
{
    swfs_fits_in *fs = NULL;
    swfs_recon *rec = NULL;
    double *act = NULL;
    size_t nact = 0;
    int rc = swfs_fits_in_open(&fs, o->science, NULL);
    if (!rc) rc = swfs_fits_in_geom(fs, &u->g);
    if (!rc) swfs_geom_overlay(&u->g, &o->geom);
    if (!rc) rc = swfs_science_tiptilt_check(fs, o->science, o->tiptilt);
    if (!rc) {
        *nfx = swfs_fits_in_shape(fs)->nx;
        *nfy = swfs_fits_in_shape(fs)->ny;
    }
    swfs_fits_in_close(fs);
    if (!rc) rc = swfs_geom_require(&u->g, o->science);
    if (!rc) rc = swfs_noise_from_header(o->science, o->read_noise, o->gain, &r->noise);
    if (!rc && o->lin.basis) return setup_linear(o, first_tel, u, p, *nfx, *nfy, r);
    if (!rc) rc = swfs_recon_read(o->recon, &rec);
    /* A space-time reconstructor reads the slopes of later WFS frames: a stream from files
     * has them (the file in memory and its neighbours, stacked per batch by stacked_next);
     * a live or milk-log source stacks them as its frames arrive (framesync.h, "Lags"). */
    const size_t nl = !rc && rec->nlags > 1 ? rec->nlags : 1, per = rc ? 0 : rec->nslopes / nl;
    if (!rc && nl > 1) {
        u->nlags = nl;
        memcpy(u->lags, rec->lags, sizeof u->lags);
    }
    /* The reconstructor's width against the telemetry now, not after the first frames:
     * a wrong --recon is named as such. */
    if (!rc && first_tel[0]) {
        swfs_fits_in *ft = NULL;
        rc = swfs_fits_in_open(&ft, first_tel, NULL);
        if (!rc && swfs_fits_in_shape(ft)->nx != per)
            rc = nl > 1 ? swfs_fail(SWFS_ERR_SHAPE, "%s: the space-time reconstructor takes %zu slopes per WFS frame "
                                    "(%zu lags of %zu) but the telemetry %s has %zu; --recon needs the reconstructor "
                                    "in the telemetry's layout (`speckles --write-recon` writes it so)", o->recon,
                                    per, nl, per, first_tel, swfs_fits_in_shape(ft)->nx)
                        : swfs_fail(SWFS_ERR_SHAPE, "%s: the reconstructor takes %zu slopes per WFS frame but the "
                                    "telemetry %s has %zu; --recon needs the reconstructor (nslopes x nact image)",
                                    o->recon, rec->nslopes, first_tel, swfs_fits_in_shape(ft)->nx);
        swfs_fits_in_close(ft);
    }
    if (!rc) rc = swfs_actuators_read(o->actuators, &act, &nact);
    /* (a map with output points of its own, OUTXY, writes the wavefront there: pipeline.h) */
    if (!rc && !rec->oxy && rec->nact != nact)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s has %zu actuators but the reconstructor %s has %zu rows", o->actuators, nact,
                       o->recon, rec->nact);
    if (!rc) rc = load_mask(o->mask, &u->g, &u->mask);
    if (!rc) {
        swfs_pipeline_options po;
        swfs_pipeline_options_default(&po);
        po.recon = SWFS_RECON_GIVEN;
        po.rcond = 0.0;
        po.tiptilt = o->tiptilt;
        po.threads = o->threads;
        po.band = o->band;
        char model[8400];
        snprintf(model, sizeof model, "%s with %s", o->recon, o->actuators);
        rc = swfs_sh_pipeline(p, model, o->valid, first_tel, &u->g, *nfx, *nfy, act, nact,
                              u->mask ? u->mask->data : NULL, per, rec, NULL, 0, &po);
        if (!rc) swfs_pipeline_get_info(*p, &r->info);
        if (!rc) rc = swfs_map_meanmiss_attach(*p, o->recon, NULL, &u->g, &r->meanmiss_rms);
    }
    swfs_recon_free(rec);
    free(act);
    return rc;
}

/* A team's share: the usable camera frames (the first max_frames of them), cut at batch
 * boundaries within a cube so that every member's batches are the single-process run's. */
static int plan_share(const swfs_stream_run_options *o, const swfs_file_source *src, size_t *first, size_t *count)
{
    const swfs_timing *t = swfs_file_source_timing(src);
    size_t *len = calloc(t->ncubes ? t->ncubes : 1, sizeof *len);
    if (!len) return swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory");
    const size_t total = usable_frames(t, o->stream.max_frames, len);
    swfs_team_share(len, t->ncubes, o->batch, o->team->rank, o->team->size, first, count);
    free(len);
    if (!total) return swfs_fail(SWFS_ERR_VALUE, "%s: no usable cube (all straddle their telemetry files?)", o->timing);
    return SWFS_OK;
}

/* Member 0's first batch (the data set's first) through the stream: the automatic static
 * halo, as the single-process run makes it. */
static int first_batch(swfs_stream *s, stacked_src *src)
{
    swfs_batch b;
    memset(&b, 0, sizeof b);
    int rc = stacked_next(src, &b);
    if (!rc && !b.nexp) rc = swfs_fail(SWFS_ERR_INTERNAL, "stream: the first member's share is empty");
    if (!rc && (rc = swfs_stream_push(s, &b))) swfs_fail_context(rc, "batch of cube %zu", b.cube);
    return rc;
}

/* The team's run after setup (rc: this member's status so far): the share, the static
 * halo, the share through the stream, then the union of the accumulators to member 0, who
 * writes the products. Every member reaches every agreement. */
static int run_team(const swfs_stream_run_options *o, run_ctx *u, swfs_pipeline *p, swfs_file_source *src,
                    stacked_src *ss, swfs_stream_options *so, size_t nf2, swfs_stream **sp, swfs_accum **merged,
                    swfs_stream_run_result *r, int rc)
{
    const swfs_team *t = o->team;
    size_t first = 0, count = 0;
    if (!rc) rc = plan_share(o, src, &first, &count);
    if (!rc) rc = swfs_file_source_set_range(src, first, count);
    /* A missing or truncated telemetry file of any share stops every member now, not
     * after the others' work. */
    if (!rc) rc = swfs_file_source_check(src);
    so->max_frames = 0; /* the shares end at max_frames */
    const int autostat = so->static_mode == SWFS_STATIC_AUTO;
    swfs_complex *stat = NULL;
    double scale = NAN, sums[2] = {0, 0};
    if (!rc && autostat && !(stat = malloc(nf2 * sizeof *stat))) rc = swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory");
    if (!rc && (t->rank == 0 || !autostat)) rc = swfs_stream_create(sp, p, so);
    if (!rc && autostat && t->rank == 0 && !(rc = first_batch(*sp, ss))) {
        memcpy(stat, swfs_stream_static(*sp), nf2 * sizeof *stat);
        scale = swfs_stream_static_scale(*sp);
    }
    rc = swfs_team_agree(t, rc);
    if (!rc && autostat) {
        rc = t->bcast(t->ctx, stat, nf2 * sizeof *stat, 0);
        if (!rc) rc = t->bcast(t->ctx, &scale, sizeof scale, 0);
        if (!rc && t->rank > 0) {
            swfs_stream_options given = *so;
            given.static_mode = SWFS_STATIC_GIVEN;
            given.static_halo = stat;
            rc = swfs_stream_create(sp, p, &given);
        }
    }
    free(stat);
    if (rc) return rc;
    /* The share through the stream; a failure (a truncated telemetry file) stops every
     * member at the agreement that follows. */
    if (count > swfs_stream_camera_frames(*sp)) rc = swfs_stream_run(*sp, stacked_next, ss, NULL, NULL);
    rc = swfs_team_agree(t, rc);
    if (rc) return rc;
    sums[0] = (double)swfs_stream_camera_frames(*sp);
    sums[1] = swfs_stream_wfs_frames(*sp);
    if ((rc = t->sum(t->ctx, sums, 2))) return rc;
    if ((rc = swfs_team_sum_pipeline_mean(t, p))) return rc; /* the time mean over every member's exposures */
    const swfs_accum *mine = swfs_stream_accum(*sp);
    if (t->rank == 0 && !(*merged = swfs_accum_create(mine->nx, mine->ny)))
        rc = swfs_fail(SWFS_ERR_NOMEM, "stream: out of memory for the merged accumulators");
    rc = swfs_team_agree(t, rc);
    if (!rc) rc = swfs_team_merge_accum(t, mine, *merged);
    if (!rc && t->rank == 0) {
        u->merged = *merged;
        rc = update(u, *sp, 1);
    }
    r->camera_frames = (size_t)sums[0];
    r->wfs_frames = sums[1];
    r->static_scale = autostat ? scale : NAN;
    return swfs_team_agree(t, rc);
}

int swfs_stream_run_files(const swfs_stream_run_options *o, swfs_stream_run_result *r)
{
    const int crc = swfs_stream_run_options_check(o);
    if (crc) {
        memset(r, 0, sizeof *r);
        return crc;
    }
    if (o->nwfs_logs) return swfs_stream_run_milk(o, r);
    return swfs_stream_run_hooked(o, NULL, r);
}

int swfs_stream_run_hooked(const swfs_stream_run_options *o, const swfs_run_hooks *hk, swfs_stream_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->static_scale = NAN;
    r->meanmiss_heldout = NAN;
    if (hk && !hk->source) hk = NULL;
    if ((!o->timing && !hk) || !o->science || !((o->recon && o->actuators) || o->lin.basis) || !o->out)
        return swfs_fail(SWFS_ERR_ARG, "stream: needs a timing table, a science cube, a reconstructor and actuators (or "
                         "a basis) and an output");
    const int team = swfs_team_active(o->team);
    if (team && hk) return swfs_fail(SWFS_ERR_ARG, "stream: a live source runs alone, not as a team of processes");
    if (team && (o->stream.every || o->stream.every_seconds > 0))
        return swfs_fail(SWFS_ERR_ARG, "stream: a run of %d processes writes its products once, at the end, from the "
                         "merged accumulators; periodic updates (every %zu camera frames / %g s) would not be the "
                         "single-process run's intermediate products: leave them out (docs/cluster.md)",
                         o->team->size, o->stream.every, o->stream.every_seconds);
    run_ctx u;
    memset(&u, 0, sizeof u);
    u.o = o;
    swfs_accum *merged = NULL;
    u.hk = hk;
    swfs_pipeline *p = NULL;
    swfs_stream *s = NULL;
    swfs_file_source *src = NULL;
    swfs_cplx *stat_c = NULL;
    size_t nfx = 0, nfy = 0;
    char first_tel[8192];
    int rc = hk ? SWFS_OK : check_paths(o, first_tel, sizeof first_tel);
    if (hk) first_tel[0] = 0;
    if (!rc) rc = setup(o, first_tel, &u, &p, &nfx, &nfy, r);
    kept prev;
    memset(&prev, 0, sizeof prev);
    if (!rc && (!hk || hk->offline) && swfs_team_writer(o->team)) keep_previous(&prev, o);
    /* the loops' miss of the residual's mean takes the place of a map's MEANMISS, as in speckles;
     * from files with a timing table the loops may be simulated here, as speckles does */
    const int mteach = !hk && o->timing && swfs_mean_teach_wanted_(o->mean_teach, &o->lin, o->nmean_loops, 0);
    char (*dirs)[4400] = mteach ? calloc(SWFS_MEAN_TEACH_MAX, sizeof *dirs) : NULL;
    if (!rc && mteach && !dirs) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    const char *mt[SWFS_MEAN_TEACH_MAX];
    if (!rc && mteach) rc = stream_mean_teach(o, &u.g, r->info.nslopes / (u.nlags ? u.nlags : 1), r, dirs, mt);
    if (!rc && mteach && r->mean_teach.done)
        rc = swfs_pipeline_mean_loops(p, mt, r->mean_teach.nloops, &r->meanmiss_heldout, &r->meanmiss_rms);
    free(dirs);
    if (!rc && o->nmean_loops)
        rc = swfs_pipeline_mean_loops(p, o->mean_loops, o->nmean_loops, &r->meanmiss_heldout, &r->meanmiss_rms);
    if (!rc && hk) rc = hk->prepare ? hk->prepare(hk->ctx, &r->info, u.nlags ? u.lags : NULL) : SWFS_OK;
    else if (!rc) rc = swfs_file_source_open(&src, o->timing, o->science, o->slopes,
                                             r->info.nslopes / (u.nlags ? u.nlags : 1), o->batch);
    stacked_src ss = {.src = src, .t = src ? swfs_file_source_timing(src) : NULL, .nlags = u.nlags, .lags = u.lags};
    swfs_stream_options so = o->stream;
    u.so = &so;
    so.noise = r->noise;
    int assumed;
    so.est.g_smooth = swfs_g_smooth_pixels(o->g_smooth_lod, u.g.pixscale, &assumed);
    if (!rc && so.static_mode == SWFS_STATIC_GIVEN) {
        rc = swfs_fits_read_cplx(o->static_file, NULL, &stat_c, NULL);
        if (!rc && (stat_c->nx != nfx || stat_c->ny != nfy || stat_c->nz != 1))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: static halo is %zux%zux%zu but the science frames are %zux%zu: expected "
                           "one complex image of their size (a halo's, not a speckle cube)", o->static_file, stat_c->nx,
                           stat_c->ny, stat_c->nz, nfx, nfy);
        for (size_t q = 0; !rc && q < nfx * nfy * stat_c->nz; q++)
            if (!isfinite(creal(stat_c->data[q])) || !isfinite(cimag(stat_c->data[q])))
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: static halo value at pixel (%zu, %zu) is not finite", o->static_file,
                               q % nfx, q / nfx % nfy);
        if (!rc) so.static_halo = stat_c->data;
    }
    char nl[256];
    snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count; ratio %.6g WFS frames per camera "
             "frame", r->noise.read_noise, r->noise.gain, src ? swfs_file_source_timing(src)->ratio : NAN);
    if (hk) snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count; timing from the frames' "
                     "time stamps", r->noise.read_noise, r->noise.gain);
    if (!rc && !(u.prov = swfs_prov_plus(o->prov, o->nprov, nl))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    u.nprov = o->nprov + 1;
    if (team) {
        rc = run_team(o, &u, p, src, &ss, &so, nfx * nfy, &s, &merged, r, rc);
    } else {
        if (!rc) rc = swfs_stream_create(&s, p, &so);
        u.stream = s;
        if (!rc && so.static_mode != SWFS_STATIC_AUTO && o->static_out) {
            rc = write_static(o->static_out, swfs_stream_static(s), nfx, nfy, &u.g, u.prov, u.nprov);
            u.static_written = 1;
        }
        progress_src ps = {hk ? hk->source : stacked_next, hk ? hk->source_ctx : (void *)&ss, o, 0,
                           hk ? 0 : usable_frames(ss.t, o->stream.max_frames, NULL)};
        const int report = o->progress && (!hk || hk->offline);
        if (!rc) rc = report ? swfs_stream_run(s, progress_next, &ps, update, &u) : swfs_stream_run(s, ps.next, ps.ctx, update, &u);
        if (rc == SWFS_ERR_NUMERIC && s && !swfs_stream_camera_frames(s))
            rc = hk ? swfs_fail(SWFS_ERR_VALUE, "no complete camera exposure arrived")
                    : swfs_fail(SWFS_ERR_VALUE, "%s: no usable cube (all straddle their telemetry files?)", o->timing);
    }
    /* (A live run keeps them: its products and checkpoint are the complete state of the
     * frames that arrived before the streams failed, the point a restart resumes from.) */
    const int offline = !hk || hk->offline;
    if (offline) {
        /* A failed run leaves no product that looks complete: the updates it had put in
         * place describe only the frames before the failure; earlier products of the same
         * names are put back. */
        const int wrote[4] = {u.updated, u.updated, u.updated, u.static_written};
        kept_end(&prev, rc != SWFS_OK, wrote);
        if (rc && (u.updated || u.static_written))
            swfs_fail_context(rc, "%s: the run failed after %zu camera frames and removed the products it had written%s",
                              o->out, s ? swfs_stream_camera_frames(s) : (size_t)0,
                              prev.have[0] || prev.have[1] || prev.have[2] || prev.have[3]
                                  ? " (the earlier files of those names put back)" : "");
    }
    if (s && !team) {
        r->camera_frames = swfs_stream_camera_frames(s);
        r->wfs_frames = swfs_stream_wfs_frames(s);
        r->seconds = swfs_stream_seconds(s);
        r->static_scale = swfs_stream_static_scale(s);
    }
    if (u.nlags) {
        memcpy(r->st_lags, u.lags, sizeof r->st_lags);
        r->st_edges_joined = ss.stk.edges.joined;
        r->st_edges_clamped = ss.stk.edges.clamped;
        r->st_edges_unreadable = ss.stk.edges.unreadable;
        snprintf(r->st_edges_why, sizeof r->st_edges_why, "%s", ss.stk.edges.why);
    }
    if (src) {
        r->wfs_rate = swfs_file_source_wfs_rate(src);
        r->ratio = swfs_file_source_timing(src)->ratio;
    }
    if (s && team) r->seconds = swfs_stream_seconds(s);
    swfs_accum_free(merged);
    swfs_stream_free(s);
    swfs_pipeline_free(p);
    swfs_file_source_close(src);
    swfs_lag_stacker_free_(&ss.stk);
    swfs_cplx_free(stat_c);
    swfs_real_free(u.mask);
    free(u.prov);
    return rc;
}

/* replay: the inputs of `stream` published into shared-memory streams at the WFS rate.
 * See include/specklewfs/live.h and docs/live.md. */
#include "specklewfs/fits.h"
#include "specklewfs/live.h"
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "run_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

void swfs_replay_options_default(swfs_replay_options *o)
{
    memset(o, 0, sizeof *o);
    o->wfs_name = "swfs_wfs";
    o->camera_name = "swfs_camera";
    o->speed = 1.0;
    o->seed = 1;
}

/* A telemetry file and the global WFS frames it holds: rows [off, off + rows). */
typedef struct tfile {
    char path[8192];
    int64_t off;
    size_t rows;
    int bitpix;
} tfile;

typedef struct replay {
    const swfs_replay_options *o;
    swfs_timing *t;
    tfile *files;
    size_t nfiles, nslopes;
    double rate;
    swfs_fits_in *sci;
    size_t nfx, nfy;
    double *cube_g;            /* global exposure start of every cube (WFS frames) */
    size_t *order;             /* cubes in time order (usable ones) */
    size_t norder;
    swfs_shm *w, *c;
    swfs_shm_shape ws, cs;
    FILE *log;
} replay;

static int cmp_off(const void *a, const void *b)
{
    const tfile *x = a, *y = b;
    return x->off < y->off ? -1 : x->off > y->off;
}

static const replay *g_sort; /* qsort has no context argument */
static int cmp_cube(const void *a, const void *b)
{
    const double x = g_sort->cube_g[*(const size_t *)a], y = g_sort->cube_g[*(const size_t *)b];
    return x < y ? -1 : x > y;
}

/* The telemetry files the table names, where they sit in global WFS frames. */
static int scan_files(replay *p)
{
    const swfs_replay_options *o = p->o;
    const swfs_timing *t = p->t;
    char dir[4096];
    swfs_path_dir(o->timing, dir, sizeof dir);
    const char *sl = o->slopes ? o->slopes : dir;
    struct stat sb;
    const int sl_dir = stat(sl, &sb) == 0 && S_ISDIR(sb.st_mode);
    p->files = calloc(t->ncubes ? t->ncubes : 1, sizeof *p->files);
    if (!p->files) return swfs_fail(SWFS_ERR_NOMEM, "replay: out of memory");
    int all_frame0 = 1, rc = SWFS_OK;
    for (size_t c = 0; c < t->ncubes && !rc; c++) {
        char path[8192];
        if (sl_dir) rc = swfs_telemetry_path(sl, t->cubes[c].slopes, path, sizeof path);
        else snprintf(path, sizeof path, "%s", sl);
        int seen = 0;
        for (size_t f = 0; f < p->nfiles && !seen; f++) seen = !strcmp(p->files[f].path, path);
        if (rc || seen) continue;
        tfile *tf = &p->files[p->nfiles++];
        snprintf(tf->path, sizeof tf->path, "%s", path);
        swfs_fits_in *f = NULL;
        double frame0 = 0, wr = 0;
        int found = 0, fr = 0;
        rc = swfs_fits_in_open(&f, path, NULL);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, "FRAME0", &frame0, &found);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, "WFSRATE", &wr, &fr);
        if (!rc) {
            const swfs_fits_shape *sh = swfs_fits_in_shape(f);
            tf->rows = sh->ny;
            tf->bitpix = sh->bitpix;
            if (sh->nz != 1 || (p->nslopes && sh->nx != p->nslopes))
                rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames", path,
                               sh->nx, sh->ny, sh->nz, p->nslopes ? p->nslopes : sh->nx);
            p->nslopes = sh->nx;
        }
        swfs_fits_in_close(f);
        if (fr && wr > 0 && !(p->rate > 0)) p->rate = wr;
        if (!found) all_frame0 = 0;
        tf->off = (int64_t)llround(frame0);
    }
    if (rc) return rc;
    if (!p->nfiles) return swfs_fail(SWFS_ERR_VALUE, "%s: no cube names a telemetry file", o->timing);
    if (!all_frame0) { /* consecutive in the order the table first names them */
        int64_t off = 0;
        for (size_t f = 0; f < p->nfiles; f++) {
            p->files[f].off = off;
            off += (int64_t)p->files[f].rows;
        }
    }
    /* Each cube's exposure start in global WFS frames (before sorting the files). */
    p->cube_g = malloc(t->ncubes * sizeof *p->cube_g);
    p->order = malloc(t->ncubes * sizeof *p->order);
    if (!p->cube_g || !p->order) return swfs_fail(SWFS_ERR_NOMEM, "replay: out of memory");
    for (size_t c = 0; c < t->ncubes; c++) {
        char path[8192];
        if (sl_dir) swfs_telemetry_path(sl, t->cubes[c].slopes, path, sizeof path);
        else snprintf(path, sizeof path, "%s", sl);
        int64_t off = 0;
        for (size_t f = 0; f < p->nfiles; f++)
            if (!strcmp(p->files[f].path, path)) off = p->files[f].off;
        p->cube_g[c] = (double)off + t->cubes[c].start;
        if (t->cubes[c].nframes) p->order[p->norder++] = c;
    }
    qsort(p->files, p->nfiles, sizeof *p->files, cmp_off);
    for (size_t f = 1; f < p->nfiles; f++)
        if (p->files[f].off < p->files[f - 1].off + (int64_t)p->files[f - 1].rows)
            return swfs_fail(SWFS_ERR_VALUE, "%s and %s overlap in WFS frames (FRAME0 %lld + %zu rows > %lld)",
                             p->files[f - 1].path, p->files[f].path, (long long)p->files[f - 1].off,
                             p->files[f - 1].rows, (long long)p->files[f].off);
    g_sort = p;
    qsort(p->order, p->norder, sizeof *p->order, cmp_cube);
    for (size_t k = 1; k < p->norder; k++) {
        const size_t a = p->order[k - 1], b = p->order[k];
        if (p->cube_g[a] + (double)t->cubes[a].nframes * t->ratio > p->cube_g[b] + 1e-9)
            return swfs_fail(SWFS_ERR_VALUE, "%s: cubes %zu and %zu overlap in time", o->timing, a, b);
    }
    return SWFS_OK;
}

static int make_streams(replay *p)
{
    const swfs_replay_options *o = p->o;
    int rc = swfs_shm_create(&p->w, o->dir, o->wfs_name, &p->ws);
    if (!rc) rc = swfs_shm_create(&p->c, o->dir, o->camera_name, &p->cs);
    return rc;
}

int swfs_replay_wait_readers_(const swfs_replay_options *o, const swfs_shm *w, const swfs_shm *c, double *waited)
{
    const double t0 = swfs_wall_seconds();
    *waited = 0;
    if (!(o->wait_reader > 0)) return SWFS_OK;
    while (swfs_shm_reader_count(w) < 1 || swfs_shm_reader_count(c) < 1) {
        if (swfs_wall_seconds() - t0 > o->wait_reader)
            return swfs_fail(SWFS_ERR_IO, "replay: no reader claimed %s and %s within %.3g s", swfs_shm_get_path(w),
                             swfs_shm_get_path(c), o->wait_reader);
        swfs_sleep_until(swfs_wall_seconds() + 0.002);
    }
    *waited = swfs_wall_seconds() - t0;
    return SWFS_OK;
}

static int wait_readers(replay *p, double *waited) { return swfs_replay_wait_readers_(p->o, p->w, p->c, waited); }

static int choose_types(replay *p)
{
    const swfs_replay_options *o = p->o;
    int any64 = 0;
    for (size_t f = 0; f < p->nfiles; f++) any64 |= p->files[f].bitpix == -64;
    memset(&p->ws, 0, sizeof p->ws);
    p->ws.datatype = o->wfs_type ? o->wfs_type : (any64 ? SWFS_SHM_F64 : SWFS_SHM_F32);
    p->ws.nx = p->nslopes;
    p->ws.ny = 1;
    memset(&p->cs, 0, sizeof p->cs);
    const int bp = swfs_fits_in_shape(p->sci)->bitpix;
    int ct = bp == -64 ? SWFS_SHM_F64 : bp == -32 ? SWFS_SHM_F32 : bp == 16 ? SWFS_SHM_I16 : SWFS_SHM_F64;
    if (bp == 16) {
        double bz = 0;
        int found = 0;
        int rc = swfs_fits_in_key_double_opt(p->sci, "BZERO", &bz, &found);
        if (rc) return rc;
        if (found && bz == 32768.0) ct = SWFS_SHM_U16;
    }
    p->cs.datatype = o->camera_type ? o->camera_type : ct;
    p->cs.nx = p->nfx;
    p->cs.ny = p->nfy;
    if (o->depth > 1) {
        p->ws.nz = p->cs.nz = o->depth;
        p->ws.temporal = p->cs.temporal = 1;
    } else {
        p->ws.nz = p->cs.nz = 1;
    }
    return SWFS_OK;
}

int swfs_replay_run(const swfs_replay_options *o, swfs_replay_result *r)
{
    memset(r, 0, sizeof *r);
    if (o->wfs_log && o->science) return swfs_replay_milk_run_(o, r);
    if (!o->timing || !o->science)
        return swfs_fail(SWFS_ERR_ARG, "replay: needs a timing table (or a WFS milk log) and a science cube");
    if (!(o->speed > 0) || !(o->drop_wfs >= 0 && o->drop_wfs < 1) || !(o->drop_camera >= 0 && o->drop_camera < 1) ||
        !(o->jitter >= 0) || !(o->wfs_rate >= 0) || !(o->wait_reader >= 0))
        return swfs_fail(SWFS_ERR_ARG, "replay: speed %g, drop probabilities %g %g, jitter %g, WFS rate %g, reader wait %g "
                         "(expected > 0, [0, 1), [0, 1), >= 0, >= 0, >= 0)", o->speed, o->drop_wfs, o->drop_camera,
                         o->jitter, o->wfs_rate, o->wait_reader);
    replay p;
    memset(&p, 0, sizeof p);
    p.o = o;
    swfs_real *tel = NULL;
    double *frame = NULL;
    int rc = swfs_timing_read(o->timing, &p.t);
    if (!rc && !(p.t->ratio >= SWFS_ENGINE_MIN_RATIO))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: frame-rate ratio %g; expected >= %g", o->timing, p.t->ratio,
                       SWFS_ENGINE_MIN_RATIO);
    if (!rc) rc = scan_files(&p);
    if (!rc && o->wfs_rate > 0) p.rate = o->wfs_rate;
    if (!rc && !(p.rate > 0))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: no WFSRATE in the telemetry; give the WFS rate", p.files[0].path);
    if (!rc) rc = swfs_fits_in_open(&p.sci, o->science, NULL);
    if (!rc) {
        const swfs_fits_shape *sh = swfs_fits_in_shape(p.sci);
        p.nfx = sh->nx;
        p.nfy = sh->ny;
        if (sh->is_complex) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: complex; expected camera frames", o->science);
        for (size_t k = 0; k < p.norder && !rc; k++) {
            const swfs_timing_cube *tc = &p.t->cubes[p.order[k]];
            if (tc->first + tc->nframes > sh->nz)
                rc = swfs_fail(SWFS_ERR_SHAPE, "%s: cube %zu needs frames %zu..%zu but %s holds %zu", o->timing,
                               p.order[k], tc->first, tc->first + tc->nframes - 1, o->science, sh->nz);
        }
    }
    if (!rc) rc = choose_types(&p);
    if (!rc && !(frame = malloc((p.nfx * p.nfy > p.nslopes ? p.nfx * p.nfy : p.nslopes) * sizeof *frame)))
        rc = swfs_fail(SWFS_ERR_NOMEM, "replay: out of memory");
    if (!rc && o->drop_log && !(p.log = fopen(o->drop_log, "w")))
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot write the drop log", o->drop_log);
    if (!rc) rc = make_streams(&p);
    double waited = 0;
    if (!rc) rc = wait_readers(&p, &waited);
    if (rc) goto done;
    if (p.log) fprintf(p.log, "# frames lost on purpose: wfs GLOBAL_ROW COUNTER | camera CUBE FRAME COUNTER\n");

    swfs_rng rng;
    swfs_rng_seed(&rng, o->seed);
    const swfs_timing *t = p.t;
    const int64_t g_lo = p.files[0].off, g_hi = p.files[p.nfiles - 1].off + (int64_t)p.files[p.nfiles - 1].rows;
    size_t ncam = 0;
    for (size_t k = 0; k < p.norder; k++) ncam += t->cubes[p.order[k]].nframes;
    /* Time: u in WFS frames (row k covers [k, k + 1)); u0 the first event. */
    const double per = 1.0 / (p.rate * o->speed);
    double u0 = (double)(g_lo + 1);
    if (p.norder) u0 = fmin(u0, p.cube_g[p.order[0]] + t->ratio);
    double mono0 = swfs_wall_seconds() + 0.02;
    int64_t tai0 = swfs_shm_now_ns() + 20000000;
    int64_t row = g_lo;
    size_t fi = 0, loaded = (size_t)-1, ck = 0, cj = 0, nw = 0, nc = 0, since_restart = 0;
    const double t_start = swfs_wall_seconds();
    for (;;) {
        const double uw = row < g_hi ? (double)(row + 1) : INFINITY;
        const double uc = ck < p.norder ? p.cube_g[p.order[ck]] + (double)(cj + 1) * t->ratio : INFINITY;
        if (isinf(uw) && isinf(uc)) break;
        const int is_wfs = uw <= uc;
        const double u = is_wfs ? uw : uc;
        const double jit = o->jitter > 0 ? o->jitter * swfs_rng_normal(&rng) : 0.0;
        const double when = (u - u0) * per + jit;
        const int64_t stamp = tai0 + llround(when * 1e9);
        swfs_sleep_until(mono0 + when);
        if (is_wfs) {
            while (fi < p.nfiles && row >= p.files[fi].off + (int64_t)p.files[fi].rows) fi++;
            const int logged = fi < p.nfiles && row >= p.files[fi].off;
            if (logged && loaded != fi) {
                swfs_real_free(tel);
                tel = NULL;
                if ((rc = swfs_telemetry_read(p.files[fi].path, p.nslopes, &tel, NULL))) goto done;
                loaded = fi;
            }
            const int drop = !logged || (o->drop_wfs > 0 && row + 1 < g_hi && swfs_rng_uniform(&rng) < o->drop_wfs);
            if (drop) {
                swfs_shm_skip(p.w);
                r->wfs_dropped++;
                if (p.log) fprintf(p.log, "wfs %lld %llu%s\n", (long long)row, (unsigned long long)swfs_shm_counter(p.w),
                                   logged ? "" : " (no telemetry)");
            } else {
                memcpy(frame, tel->data + (size_t)(row - p.files[fi].off) * p.nslopes, p.nslopes * sizeof *frame);
                if ((rc = swfs_shm_write(p.w, frame, stamp))) goto done;
            }
            row++;
            nw++;
            since_restart++;
        } else {
            const size_t c = p.order[ck];
            const int last = ck + 1 == p.norder && cj + 1 == t->cubes[c].nframes;
            const int drop = o->drop_camera > 0 && !last && swfs_rng_uniform(&rng) < o->drop_camera;
            if (drop) {
                swfs_shm_skip(p.c);
                r->camera_dropped++;
                if (p.log) fprintf(p.log, "camera %zu %zu %llu\n", c, cj, (unsigned long long)swfs_shm_counter(p.c));
            } else {
                if ((rc = swfs_fits_in_read_real(p.sci, t->cubes[c].first + cj, 1, frame))) goto done;
                if ((rc = swfs_shm_write(p.c, frame, stamp))) goto done;
            }
            nc++;
            if (++cj == t->cubes[c].nframes) {
                cj = 0;
                ck++;
            }
        }
        r->late_max = fmax(r->late_max, swfs_wall_seconds() - (mono0 + when));
        if ((nw + nc) % 1024 == 0 &&
            (rc = swfs_progress_report(o->progress, o->progress_ctx, "frames", nw + nc, (size_t)(g_hi - g_lo) + ncam)))
            goto done;
        if (o->restart_after && since_restart >= o->restart_after && row < g_hi) {
            /* The writer restarts: new files (new inodes), counters from 0. */
            since_restart = 0;
            swfs_shm_close(p.w, 1);
            swfs_shm_close(p.c, 1);
            p.w = p.c = NULL;
            if ((rc = make_streams(&p))) goto done;
            r->restarts++;
            if ((rc = wait_readers(&p, &waited))) goto done;
            mono0 += waited; /* the data go on after the pause */
            tai0 += llround(waited * 1e9);
        }
    }
    r->seconds = swfs_wall_seconds() - t_start;
    r->wfs_frames = nw;
    r->camera_frames = nc;
    r->wfs_rate = p.rate * o->speed;
    r->ratio = t->ratio;
done:
    if (p.log) fclose(p.log);
    swfs_shm_close(p.w, o->remove);
    swfs_shm_close(p.c, o->remove);
    swfs_fits_in_close(p.sci);
    swfs_timing_free(p.t);
    swfs_real_free(tel);
    free(frame);
    free(p.files);
    free(p.cube_g);
    free(p.order);
    return rc;
}

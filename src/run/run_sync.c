/* sync: reduced science + handshake log -> the timing table (Sec. 4.2). See include/specklewfs/run.h. */
#include "specklewfs/engine.h"
#include "specklewfs/run.h"
#include "run_internal.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <dirent.h>
#include <unistd.h>

void swfs_sync_run_options_default(swfs_sync_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_sync_params_default(&o->params);
    swfs_linear_files_default(&o->lin);
    o->params.lag_min = -3;
    o->params.lag_max = 12;
    o->params.ratio_min = SWFS_ENGINE_MIN_RATIO; /* a camera faster than the WFS included */
    o->params.ratio_max = 0; /* from the handshake log (ratio_bound) */
}

/* The mean x/y slopes of one telemetry file, loaded once however many cubes use it. */
typedef struct slopes_file {
    char name[SWFS_SYNC_NAME];
    size_t nwfs;
    double *mx, *my;
} slopes_file;

typedef struct work {
    const swfs_sync_run_options *o;
    double *R;                /* the linear model's tilt rows (o->lin.basis), built at the first file */
    swfs_science_track *tr;
    swfs_handshake *hs;
    size_t nhs, nfiles, nwfs_slopes;
    slopes_file *files;
    swfs_sync_cube *cubes;
    size_t *cube_file;
    long *cube_hs;
    char logdir[4096];
    swfs_sync_params params;  /* o->params with the ratio range resolved (ratio_bound) */
} work;

static int load_file(work *w, const char *name, size_t *fi)
{
    for (*fi = 0; *fi < w->nfiles; (*fi)++)
        if (!strcmp(w->files[*fi].name, name)) return SWFS_OK;
    char path[8192];
    int rc = swfs_telemetry_path(w->logdir, name, path, sizeof path);
    swfs_real *s = NULL;
    if (!rc) rc = swfs_fits_read_real(path, NULL, &s, NULL);
    if (rc) return rc;
    const int lin = w->o->lin.basis != NULL;
    if (s->nz != 1 || (!lin && s->nx % 2) || (w->nwfs_slopes && s->nx != w->nwfs_slopes))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %s must be a 2-D image %s x N_WFS, got %zux%zux%zu", path,
                       lin ? "telemetry" : "slopes", lin ? (w->nwfs_slopes ? "NVALUES (the same in every file)" : "NVALUES")
                       : (w->nwfs_slopes ? "NSLOPES (even, the same in every file)" : "NSLOPES (even)"), s->nx, s->ny, s->nz);
    if (!rc) rc = swfs_telemetry_check_values(path, s);
    slopes_file *f = &w->files[*fi];
    if (!rc && (!(f->mx = malloc(s->ny * sizeof(double))) || !(f->my = malloc(s->ny * sizeof(double))))) {
        free(f->mx);
        f->mx = NULL;
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    if (!rc) {
        w->nwfs_slopes = s->nx;
        snprintf(f->name, sizeof f->name, "%s", name);
        f->nwfs = s->ny;
        if (lin && !w->R) rc = swfs_linear_tilt_rows(&w->o->lin, w->o->science, s->nx, &w->R);
        if (lin && !rc) swfs_tilt_rows_apply(w->R, s->data, s->nx, s->ny, f->mx, f->my);
        else if (!lin) swfs_slopes_mean_xy(s->data, s->nx, s->ny, NULL, f->mx, f->my);
        w->nfiles++;
    }
    swfs_real_free(s);
    return rc;
}

/* Cube ci: its handshake entry, its telemetry file's mean slopes, its timing-table row. */
static int setup_cube(const swfs_sync_run_options *o, work *w, size_t ci, swfs_timing_cube *tc)
{
    const char *cam = w->tr->camera[ci];
    size_t h = w->nhs, fi;
    for (size_t k = 0; k < w->nhs; k++)
        if (!strcmp(w->hs[k].camera, cam)) { h = k; break; }
    if (h == w->nhs) return swfs_fail(SWFS_ERR_VALUE, "%s: the handshake log does not cover cube %zu (%s)", o->handshake, ci, cam);
    int rc = load_file(w, w->hs[h].slopes, &fi);
    if (rc) return rc;
    const size_t first = w->tr->first[ci], n = w->tr->n[ci];
    w->cube_file[ci] = fi;
    w->cube_hs[ci] = w->hs[h].frame;
    w->cubes[ci] = (swfs_sync_cube){n, w->tr->x + first, w->tr->y + first, w->files[fi].mx, w->files[fi].my,
                                    w->files[fi].nwfs, (double)w->hs[h].frame};
    snprintf(tc->camera, sizeof tc->camera, "%s", cam);
    tc->first = first;
    tc->nframes = n;
    return SWFS_OK;
}

/* The timing table may live elsewhere: it records the telemetry file's absolute path. */
static int table_path(const work *w, const char *name, char *out, size_t cap)
{
    char rel[8192], *abs = NULL;
    int rc = swfs_telemetry_path(w->logdir, name, rel, sizeof rel);
    if (rc) return rc;
    abs = realpath(rel, NULL);
    int len = snprintf(out, cap, "%s", abs ? abs : rel);
    free(abs);
    if (len < 0 || (size_t)len >= cap) return swfs_fail(SWFS_ERR_ARG, "%s: telemetry path too long", rel);
    return SWFS_OK;
}

/* Exposures [*j0, *j1) of n that lie wholly in a file of nwfs WFS frames when the cube starts
 * at s there: s + j ratio >= 0 and s + (j + 1) ratio <= nwfs. */
static void inside(double s, double ratio, size_t n, size_t nwfs, size_t *j0, size_t *j1)
{
    double lo = fmax(ceil(-s / ratio), 0), hi = fmin(floor(((double)nwfs - s) / ratio), (double)n);
    *j0 = lo > (double)n ? n : (size_t)lo;
    *j1 = hi > lo ? (size_t)hi : *j0;
}

/* The name with its last run of digits (in the base name) moved by dir, keeping its width:
 * slopes_009.fits -> slopes_010.fits; 0 when there is none or it would go below zero. */
static int numbered_neighbour(const char *name, int dir, char *out, size_t cap)
{
    const char *base = strrchr(name, '/');
    base = base ? base + 1 : name;
    const char *end = NULL;
    for (const char *q = base; *q; q++)
        if (*q >= '0' && *q <= '9' && !(q[1] >= '0' && q[1] <= '9')) end = q + 1;
    if (!end) return 0;
    const char *beg = end;
    while (beg > base && beg[-1] >= '0' && beg[-1] <= '9') beg--;
    if (end - beg > 18) return 0;
    long long v = strtoll(beg, NULL, 10) + dir;
    if (v < 0) return 0;
    int len = snprintf(out, cap, "%.*s%0*lld%s", (int)(beg - name), name, (int)(end - beg), v, end);
    return len > 0 && (size_t)len < cap;
}

/* Two file names that differ in digits only (the same length, the same other characters):
 * the files of one logger, numbered or time-stamped (slopes_20261126T010000.fits). */
static int same_pattern(const char *a, const char *b)
{
    if (strlen(a) != strlen(b)) return 0;
    for (; *a; a++, b++) {
        const int da = *a >= '0' && *a <= '9', db = *b >= '0' && *b <= '9';
        if (da != db || (!da && *a != *b)) return 0;
    }
    return 1;
}

static int cmp_names(const void *a, const void *b) { return strcmp(*(char *const *)a, *(char *const *)b); }

/* name's neighbour (dir -1 or +1) among the files of its folder that share its pattern, in the
 * order of their names (for fixed-width numbers and time stamps, the order they were written):
 * the file after slopes_20261126T010000.fits may be slopes_20261126T010640.fits. 1 with buf
 * set (name's folder part + the neighbour's name), 0 if none. */
static int listed_neighbour(const work *w, const char *name, int dir, char *buf, size_t cap)
{
    char path[8192], folder[8192];
    if (swfs_telemetry_path(w->logdir, name, path, sizeof path)) return 0;
    const char *base = strrchr(path, '/');
    const size_t fl = base ? (size_t)(base - path) : 0;
    snprintf(folder, sizeof folder, "%.*s", (int)(fl ? fl : 1), fl ? path : ".");
    base = base ? base + 1 : path;
    DIR *d = opendir(folder);
    if (!d) return 0;
    char **names = NULL;
    size_t n = 0, capn = 0;
    int ok = 1;
    for (struct dirent *e; ok && (e = readdir(d));) {
        if (!same_pattern(e->d_name, base)) continue;
        if (n == capn) {
            char **t = realloc(names, (capn ? 2 * capn : 16) * sizeof *t);
            if (!t) { ok = 0; break; }
            names = t;
            capn = capn ? 2 * capn : 16;
        }
        if (!(names[n] = strdup(e->d_name))) { ok = 0; break; }
        n++;
    }
    closedir(d);
    int found = 0;
    if (ok && n) {
        qsort(names, n, sizeof *names, cmp_names);
        for (size_t k = 0; k < n; k++) {
            if (strcmp(names[k], base)) continue;
            const size_t j = dir > 0 ? k + 1 : k - 1; /* k = 0, dir < 0: wraps to SIZE_MAX */
            if (j < n) {
                const char *slash = strrchr(name, '/');
                const int len = snprintf(buf, cap, "%.*s%s", slash ? (int)(slash - name + 1) : 0, name, names[j]);
                found = len > 0 && (size_t)len < cap;
            }
            break;
        }
    }
    for (size_t k = 0; k < n; k++) free(names[k]);
    free(names);
    return found;
}

/* The telemetry file just before (dir -1) or after (+1) name: the numbered neighbour in the
 * same folder when it exists (slopes_004.fits -> slopes_005.fits), else the neighbour among
 * the folder's files named like it (listed_neighbour: time-stamped names), else the next or
 * previous one in the order the handshake log first names them; NULL if none. sync's check
 * on the data (split_cube) decides whether it really continues name. */
static const char *adjacent_file(const work *w, const char *name, int dir, char *buf, size_t cap)
{
    char path[8192];
    if (numbered_neighbour(name, dir, buf, cap) && !swfs_telemetry_path(w->logdir, buf, path, sizeof path) &&
        access(path, R_OK) == 0)
        return buf;
    if (listed_neighbour(w, name, dir, buf, cap)) return buf;
    const char *prev = NULL;
    int found = 0;
    for (size_t k = 0; k < w->nhs; k++) {
        const char *f = w->hs[k].slopes;
        int seen = 0;
        for (size_t q = 0; q < k && !seen; q++) seen = !strcmp(w->hs[q].slopes, f);
        if (seen) continue;
        if (found) return dir > 0 ? f : prev;
        if (!strcmp(f, name)) found = 1;
        else prev = f;
    }
    return found && dir < 0 ? prev : NULL;
}

/* One row of the table: exposures [j0, j1) of the cube, starting at s in the file name. */
static int add_row(const work *w, const swfs_timing_cube *c, size_t j0, size_t j1, const char *name, double s,
                   int status, swfs_timing *t)
{
    if (j1 <= j0) return SWFS_OK;
    swfs_timing_cube *row = &t->cubes[t->ncubes++];
    *row = *c;
    row->first = c->first + j0;
    row->nframes = j1 - j0;
    row->start = s;
    row->status = status;
    return table_path(w, name, row->slopes, sizeof row->slopes);
}

/* Cube ci at the fit's timing -> its rows: the exposures wholly inside its own telemetry file,
 * those wholly inside the file before or after it when sync's check on the data says that the
 * files are contiguous there (swfs_sync_continuation_check), and the rest marked straddles. */
static int split_cube(const swfs_sync_run_options *o, work *w, const swfs_timing_cube *c, size_t ci, swfs_timing *t,
                      swfs_sync_run_result *r)
{
    const swfs_timing *fit = t;
    const slopes_file *fa = &w->files[w->cube_file[ci]];
    const double R = fit->ratio, s = (double)w->cube_hs[ci] - fit->lag;
    const size_t n = c->nframes;
    size_t a0, a1, p0 = 0, p1 = 0, b0 = n, b1 = n;
    inside(s, R, n, fa->nwfs, &a0, &a1);
    r->nexp += n;
    if (a1 <= a0) { /* no whole exposure in its own file: the parts before and after meet at its edge */
        const double e = s >= 0 ? floor(((double)fa->nwfs - s) / R) : ceil(-s / R);
        a0 = a1 = e <= 0 ? 0 : e >= (double)n ? n : (size_t)e;
    }
    const char *pname = NULL, *bname = NULL;
    double ps = 0, bs = 0;
    swfs_sync_continuation join[2];
    char nbuf[2][SWFS_SYNC_NAME];
    for (int dir = -1; dir <= 1; dir += 2) {
        if (dir < 0 ? a0 == 0 : a1 == n) continue;
        const char *name = adjacent_file(w, fa->name, dir, nbuf[dir > 0], sizeof nbuf[0]);
        size_t fi;
        int rc = name ? load_file(w, name, &fi) : SWFS_OK;
        if (rc == SWFS_ERR_NOMEM) return rc;
        if (rc || !name) continue; /* a neighbour that is not telemetry of this kind continues nothing */
        const slopes_file *fb = &w->files[fi];
        const double sb = dir < 0 ? s + (double)fb->nwfs : s - (double)fa->nwfs;
        size_t j0, j1;
        inside(sb, R, n, fb->nwfs, &j0, &j1);
        if (dir < 0 && j1 > a0) j1 = a0;
        if (dir > 0 && j0 < a1) j0 = a1;
        if (j1 <= j0) continue;
        const double st = sb + (double)j0 * R;
        swfs_sync_cube part = {j1 - j0, w->tr->x + c->first + j0, w->tr->y + c->first + j0, fb->mx, fb->my, fb->nwfs,
                               st + fit->lag};
        swfs_sync_continuation cc;
        if ((rc = swfs_sync_continuation_check(&part, &fit->fit, &w->params, &cc))) return rc;
        if (!cc.continues) continue;
        r->ncontinued++;
        join[dir > 0] = cc;
        if (dir < 0) p0 = j0, p1 = j1, pname = name, ps = st;
        else b0 = j0, b1 = j1, bname = name, bs = st;
    }
    /* Rows in exposure order: [0, p0) straddles, [p0, p1) before, [p1, a0) straddles, [a0, a1)
       its own file, [a1, b0) straddles, [b0, b1) after, [b1, n) straddles. */
    const char *own = fa->name;
    int rc = SWFS_OK;
    const size_t cut[8] = {0, p0, p1, a0, a1, b0, b1, n}; /* 0 <= p0 <= p1 <= a0 <= a1 <= b0 <= b1 <= n */
    for (int k = 0; k < 7 && !rc; k++) {
        const size_t j0 = cut[k], j1 = cut[k + 1];
        const int ok = k == 1 || k == 3 || k == 5;
        const char *name = k == 1 ? pname : k == 5 ? bname : own;
        const double st = k == 1 ? ps : k == 5 ? bs : s + (double)j0 * R;
        if (ok && j1 > j0) r->nexp_ok += j1 - j0, r->nok++;
        rc = add_row(w, c, j0, j1, name, st, ok ? SWFS_CUBE_OK : SWFS_CUBE_STRADDLES, t);
        if (!rc && j1 > j0 && (k == 1 || k == 5)) {
            const swfs_sync_continuation *cc = &join[k == 5];
            swfs_timing_cube *row = &t->cubes[t->ncubes - 1];
            row->joined = 1;
            row->join_offset = cc->offset;
            row->join_corr_x = cc->corr_x;
            row->join_corr_y = cc->corr_y;
        }
    }
    return rc;
}

/* The ratio's upper bound from the handshake log: a camera cube of N frames that starts at
 * WFS frame h of a file, followed by the next cube at h' of the same file, lasts at most
 * (h' - h + 1) / N WFS frames per camera frame (the lag is common to both, the logged frames
 * are whole). The smallest over such pairs, or 0 when no two cubes share a file. */
static double ratio_bound(const work *w, const swfs_timing *t)
{
    double b = 0;
    for (size_t ci = 0; ci + 1 < t->ncubes; ci++) {
        if (w->cube_file[ci] != w->cube_file[ci + 1] || w->cube_hs[ci + 1] <= w->cube_hs[ci] || !t->cubes[ci].nframes)
            continue;
        const double q = (double)(w->cube_hs[ci + 1] - w->cube_hs[ci] + 1) / (double)t->cubes[ci].nframes;
        if (b == 0 || q < b) b = q;
    }
    return b;
}

/* ratio_max <= 0: the search's ratios end at ratio_bound (SWFS_SYNC_RATIO_MAX_FALLBACK when the
 * log gives none) and are cut to the largest grid params_check allows; a ratio_min above the
 * bound is refused. */
static int resolve_ratio_range(work *w, const swfs_timing *t, swfs_sync_run_result *r)
{
    swfs_sync_params *p = &w->params;
    r->ratio_bound = ratio_bound(w, t);
    if (p->ratio_max > 0) return SWFS_OK;
    r->ratio_auto = 1;
    p->ratio_max = r->ratio_bound > 0 ? r->ratio_bound : SWFS_SYNC_RATIO_MAX_FALLBACK;
    if (p->ratio_max < p->ratio_min)
        return swfs_fail(SWFS_ERR_ARG, "%s: the handshake log bounds the ratio at %g WFS frames per camera frame (a "
                         "camera cube ends before the next cube of its telemetry file starts), below the search's "
                         "least ratio %g: give --ratio-max, or check the log", w->o->handshake, p->ratio_max,
                         p->ratio_min);
    double nr, nl;
    swfs_sync_grid_size(p, &nr, &nl);
    const double nr_max = floor((double)SWFS_SYNC_MAX_GRID / nl);
    if (p->ratio_max > p->ratio_min + (nr_max - 1) * p->ratio_step) p->ratio_max = p->ratio_min + (nr_max - 1) * p->ratio_step;
    return SWFS_OK;
}

int swfs_sync_run(const swfs_sync_run_options *o, swfs_sync_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->science || !o->handshake || !o->out) return swfs_fail(SWFS_ERR_ARG, "sync: needs science, handshake, out");
    work w;
    memset(&w, 0, sizeof w);
    w.o = o;
    swfs_timing *t = &r->t;
    swfs_paths *paths = NULL;
    /* The ranges checked now; a ratio_max from the log (<= 0) is resolved once the cubes are read. */
    w.params = o->params;
    swfs_sync_params chk = o->params;
    if (chk.ratio_max <= 0) chk.ratio_max = fmax(chk.ratio_min, SWFS_SYNC_RATIO_MAX_FALLBACK);
    int rc = swfs_sync_params_check(&chk);
    if (rc) return rc;
    rc = swfs_paths_create(&paths);
    swfs_paths_input(paths, "science cube", o->science);
    swfs_linear_paths(paths, &o->lin);
    swfs_paths_input(paths, "handshake log", o->handshake);
    if (!rc) rc = swfs_paths_output(paths, "output timing table", o->out);
    if (!rc) rc = swfs_science_track_read(o->science, &w.tr);
    if (!rc) rc = swfs_handshake_read(o->handshake, &w.hs, &w.nhs);
    /* The telemetry files the log names are inputs too. */
    for (size_t k = 0; !rc && k < w.nhs; k++) {
        char dir[4096], path[8192];
        swfs_path_dir(o->handshake, dir, sizeof dir);
        if (!(rc = swfs_telemetry_path(dir, w.hs[k].slopes, path, sizeof path)))
            rc = swfs_paths_input(paths, "telemetry file named by the handshake log", path);
    }
    swfs_paths_free(paths);
    if (!rc) {
        const size_t nc = w.tr->ncubes;
        swfs_path_dir(o->handshake, w.logdir, sizeof w.logdir);
        t->ncubes = nc;
        t->cubes = calloc(nc, sizeof *t->cubes);
        w.cubes = calloc(nc, sizeof *w.cubes);
        w.files = calloc(w.nhs + 3 * nc, sizeof *w.files); /* the log's files, and two neighbours a cube */
        w.cube_file = calloc(nc, sizeof *w.cube_file);
        w.cube_hs = calloc(nc, sizeof *w.cube_hs);
        if (!t->cubes || !w.cubes || !w.files || !w.cube_file || !w.cube_hs) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
    }
    for (size_t ci = 0; !rc && ci < t->ncubes; ci++) rc = setup_cube(o, &w, ci, &t->cubes[ci]);
    if (!rc) {
        rc = resolve_ratio_range(&w, t, r);
        r->ratio_min = w.params.ratio_min;
        r->ratio_max = w.params.ratio_max;
        if (!rc) rc = swfs_sync_estimate(w.cubes, t->ncubes, &w.params, &t->fit);
        /* The continuations search the window the fit ended in. */
        if (!rc) {
            w.params.lag_min = t->fit.lag_min;
            w.params.lag_max = t->fit.lag_max;
        }
    }
    if (!rc && !(t->fit.z >= t->fit.z_need)) {
        const swfs_sync_result *f = &t->fit;
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: the camera's tip-tilt matches the telemetry's nowhere in the search: the "
                       "best ratio %.4f WFS frames per camera frame, lag %.2f, has correlations %.3f and %.3f over %.0f "
                       "independent exposures, %.1f sigma together, where a search of ratios %g to %g and lags %g to %g "
                       "needs %.1f. Check that the cubes and the handshake log %s belong together, or narrow the "
                       "search to the known ratio (--ratio-min/--ratio-max: the WFS rate over the camera's frame "
                       "rate) and lag (--lag-min/--lag-max)", o->science, f->ratio, f->lag, f->corr_x, f->corr_y,
                       f->neff, f->z, w.params.ratio_min, w.params.ratio_max, w.params.lag_min, w.params.lag_max,
                       f->z_need, o->handshake);
    }
    if (!rc) {
        t->ratio = t->fit.ratio;
        t->ratio_err = t->fit.ratio_err;
        t->lag = t->fit.lag;
        /* Each cube becomes up to 7 rows (split_cube). */
        swfs_timing_cube *cubes = t->cubes;
        const size_t nc = t->ncubes;
        t->cubes = calloc(7 * nc, sizeof *t->cubes);
        t->ncubes = 0;
        if (!t->cubes) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
        for (size_t ci = 0; !rc && ci < nc; ci++) rc = split_cube(o, &w, &cubes[ci], ci, t, r);
        free(cubes);
        if (!rc) rc = swfs_timing_write(o->out, t);
    }
    if (!rc && !r->nok) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no exposure lies inside a telemetry file", o->science);
    swfs_science_track_free(w.tr);
    free(w.hs);
    for (size_t k = 0; w.files && k < w.nfiles; k++) { free(w.files[k].mx); free(w.files[k].my); }
    free(w.files); free(w.cubes); free(w.cube_file); free(w.cube_hs); free(w.R);
    return rc;
}

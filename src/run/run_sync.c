/* sync: reduced science + handshake log -> the timing table (Sec. 4.2). See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "run_internal.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"

#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_sync_run_options_default(swfs_sync_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_sync_params_default(&o->params);
    swfs_linear_files_default(&o->lin);
    o->params.lag_min = -3;
    o->params.lag_max = 12;
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
    if (!rc && (!(f->mx = malloc(s->ny * sizeof(double))) || !(f->my = malloc(s->ny * sizeof(double)))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
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
    /* The timing table may live elsewhere: record the telemetry file's absolute path. */
    char rel[8192], *abs = NULL;
    if ((rc = swfs_telemetry_path(w->logdir, w->hs[h].slopes, rel, sizeof rel))) return rc;
    abs = realpath(rel, NULL);
    int len = snprintf(tc->slopes, sizeof tc->slopes, "%s", abs ? abs : rel);
    free(abs);
    if (len < 0 || (size_t)len >= sizeof tc->slopes) return swfs_fail(SWFS_ERR_ARG, "%s: telemetry path too long", rel);
    tc->first = first;
    tc->nframes = n;
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
    int rc = swfs_sync_params_check(&o->params);
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
        w.files = calloc(nc, sizeof *w.files);
        w.cube_file = calloc(nc, sizeof *w.cube_file);
        w.cube_hs = calloc(nc, sizeof *w.cube_hs);
        if (!t->cubes || !w.cubes || !w.files || !w.cube_file || !w.cube_hs) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
    }
    for (size_t ci = 0; !rc && ci < t->ncubes; ci++) rc = setup_cube(o, &w, ci, &t->cubes[ci]);
    if (!rc) rc = swfs_sync_estimate(w.cubes, t->ncubes, &o->params, &t->fit);
    if (!rc) {
        t->ratio = t->fit.ratio;
        t->ratio_err = t->fit.ratio_err;
        t->lag = t->fit.lag;
        for (size_t ci = 0; ci < t->ncubes; ci++) {
            double start = (double)w.cube_hs[ci] - t->lag;
            t->cubes[ci].start = start;
            int inside = start >= 0 && start + (double)w.tr->n[ci] * t->ratio <= (double)w.files[w.cube_file[ci]].nwfs;
            t->cubes[ci].status = inside ? SWFS_CUBE_OK : SWFS_CUBE_STRADDLES;
            r->nok += inside ? 1u : 0u;
        }
        rc = swfs_timing_write(o->out, t);
    }
    if (!rc && !r->nok) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no cube lies inside its telemetry file", o->science);
    swfs_science_track_free(w.tr);
    free(w.hs);
    for (size_t k = 0; w.files && k < w.nfiles; k++) { free(w.files[k].mx); free(w.files[k].my); }
    free(w.files); free(w.cubes); free(w.cube_file); free(w.cube_hs); free(w.R);
    return rc;
}

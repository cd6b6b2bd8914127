/* --tiptilt frame: the peak-registered science frames re-centred on the tilt the slopes
 * measure (see run_internal.h). */
#include "run_internal.h"
#include "specklewfs/engine.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Exposure-mean mean x / y slope of camera frames [first, first + n) of one cube. */
static int cube_tilts(const char *path, const swfs_timing *t, const swfs_timing_cube *tc, double *tx, double *ty)
{
    swfs_real *s = NULL;
    double rate;
    int rc = swfs_telemetry_read(path, 0, &s, &rate);
    if (rc) return rc;
    double *mx = malloc(s->ny * sizeof *mx), *my = malloc(s->ny * sizeof *my);
    swfs_exposure *sched = malloc(tc->nframes * sizeof *sched);
    if (!mx || !my || !sched) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    const size_t f0 = (size_t)floor(tc->start);
    const size_t need = rc ? 0 : swfs_engine_schedule(t->ratio, tc->start - (double)f0, tc->nframes, sched);
    if (!rc && (!need || f0 + need > s->ny))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: cube %s needs WFS frames %zu..%zu of %zu", path, tc->camera, f0, f0 + need,
                       s->ny);
    if (!rc) swfs_slopes_mean_xy(s->data, s->nx, s->ny, NULL, mx, my);
    for (size_t j = 0; !rc && j < tc->nframes; j++) {
        const swfs_exposure *x = sched + j;
        double sw = 0, sx = 0, sy = 0;
        for (size_t r = 0; r < x->count; r++) {
            const double w = r == 0 ? x->w_first : (r + 1 == x->count ? x->w_last : 1.0);
            sw += w;
            sx += w * mx[f0 + x->first + r];
            sy += w * my[f0 + x->first + r];
        }
        tx[j] = sw > 0 ? sx / sw : 0;
        ty[j] = sw > 0 ? sy / sw : 0;
    }
    free(mx); free(my); free(sched);
    swfs_real_free(s);
    return rc;
}

int swfs_frame_recentre_shifts(const char *tdir, const swfs_timing *t, const char *science, const swfs_geom *g,
                               double *dx, double *dy)
{
    swfs_science_track *tr = NULL;
    int rc = swfs_science_track_read(science, &tr);
    if (rc) return rc;
    /* wavefront tilt [rad] -> image displacement [pixels]: theta / (PIXSCALE lambda / D) */
    const double k = g->teldiam / (g->wavelen * g->pixscale);
    const swfs_sync_result *p = &t->fit;
    double mean[2] = {0, 0};
    size_t n = 0;
    char path[8192];
    for (size_t c = 0; !rc && c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        if (tc->first + tc->nframes > tr->nframes) {
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the TRACK has %zu frames; the timing table's cube %zu needs %zu", science,
                           tr->nframes, c, tc->first + tc->nframes);
            break;
        }
        if ((rc = swfs_telemetry_path(tdir, tc->slopes, path, sizeof path)) ||
            (rc = cube_tilts(path, t, tc, dx + n, dy + n)))
            break;
        for (size_t j = 0; j < tc->nframes; j++, n++) {
            /* the displacement sync's pairing predicts for the camera, against the peak found */
            const double a = k * (p->swap ? dy[n] : dx[n]), b = k * (p->swap ? dx[n] : dy[n]);
            dx[n] = tr->x[tc->first + j] - p->sign_x * a;
            dy[n] = tr->y[tc->first + j] - p->sign_y * b;
            mean[0] += dx[n];
            mean[1] += dy[n];
        }
    }
    for (size_t j = 0; !rc && j < n; j++) {
        dx[j] -= mean[0] / (double)n;
        dy[j] -= mean[1] / (double)n;
    }
    swfs_science_track_free(tr);
    return rc;
}

int swfs_science_tiptilt_check(swfs_fits_in *fs, const char *path, int tiptilt)
{
    long reg = 0;
    int found = 0;
    int rc = swfs_fits_in_key_long_opt(fs, "REGISTER", 0, 1, &reg, &found);
    if (!rc && found && reg == 1 && tiptilt == SWFS_TT_KEEP)
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: REGISTER = 1 (frames re-centred on their peak), but --tiptilt keep makes "
                       "speckles that keep the image motion; expected frames from 'reduce --no-register', or "
                       "--tiptilt exposure", path);
    return rc;
}

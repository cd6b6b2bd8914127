/* A space-time reconstructor's lags across telemetry files: the file in memory extended by
 * its neighbours' edge frames where the telemetry shows the files continue each other
 * (run_internal.h swfs_lag_edges_). A neighbour that cannot be read leaves that side clamped:
 * this run's own cubes do not need it. */
#include "specklewfs/fits.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "run_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Frames [first, first + n) of telemetry file path (nslopes each, finite) into a new buffer;
 * *got: the frames it holds (n cut to the file). The file named on failure. */
static int read_frames(const char *path, size_t nslopes, int tail, size_t n, double **out, size_t *got)
{
    swfs_fits_in *f = NULL;
    *out = NULL;
    *got = 0;
    int rc = swfs_fits_in_open(&f, path, NULL);
    const swfs_fits_shape *sh = rc ? NULL : swfs_fits_in_shape(f);
    if (!rc && (sh->is_complex || sh->nz != 1 || sh->nx != nslopes))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames like its "
                       "neighbour's", path, sh->nx, sh->ny, sh->nz, nslopes);
    const size_t k = rc ? 0 : (n < sh->ny ? n : sh->ny);
    if (!rc && k && !(*out = malloc(k * nslopes * sizeof **out)))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for %zu WFS frames", path, k);
    if (!rc && k) rc = swfs_fits_in_read_rows(f, tail ? sh->ny - k : 0, k, *out);
    for (size_t i = 0; !rc && i < k * nslopes; i++)
        if (!isfinite((*out)[i]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: slope %zu of WFS frame %zu is not finite", path, i % nslopes,
                           (tail ? sh->ny - k : 0) + i / nslopes);
    swfs_fits_in_close(f);
    if (rc) {
        free(*out);
        *out = NULL;
        return rc;
    }
    *got = k;
    return SWFS_OK;
}

/* One side: the neighbour's `margin` frames next to the file in memory, when the telemetry
 * says the two continue each other; *n 0 otherwise (*joined says which). */
static int side(swfs_lag_edges_ *e, const char *tdir, const swfs_timing *t, const char *name, const swfs_real *s,
                size_t margin, int step, double **frames, size_t *n)
{
    char nb[SWFS_SYNC_NAME], path[8192];
    *frames = NULL;
    *n = 0;
    /* the logger's series, else the timing table's own order of its files */
    if (!swfs_telemetry_neighbour_(tdir, name, step, t->ncubes ? t->cubes[0].slopes : NULL, sizeof *t->cubes,
                                   t->ncubes, nb, sizeof nb))
        return SWFS_OK;
    int rc = swfs_telemetry_path(tdir, nb, path, sizeof path);
    const size_t ns = s->nx, want = margin > SWFS_SYNC_EDGE_FRAMES ? margin : SWFS_SYNC_EDGE_FRAMES;
    double *edge = NULL;
    size_t got = 0;
    if (!rc && read_frames(path, ns, step < 0, want, &edge, &got)) {
        /* a neighbour this run does not need cannot stop it: that side clamps, and says why */
        e->unreadable++;
        snprintf(e->why, sizeof e->why, "%s", swfs_last_error());
        return SWFS_OK;
    }
    if (rc || !got) return rc;
    /* the telemetry's own verdict across the boundary (sync.h), on the edges either side */
    const size_t own = s->ny < SWFS_SYNC_EDGE_FRAMES ? s->ny : SWFS_SYNC_EDGE_FRAMES;
    const size_t ne = got < SWFS_SYNC_EDGE_FRAMES ? got : SWFS_SYNC_EDGE_FRAMES;
    swfs_sync_boundary b;
    rc = step < 0 ? swfs_sync_boundary_check(edge + (got - ne) * ns, ne, s->data, own, ns, &b)
                  : swfs_sync_boundary_check(s->data + (s->ny - own) * ns, own, edge, ne, ns, &b);
    if (rc || b.verdict != 1) {
        free(edge);
        if (!rc) e->clamped++;
        return rc;
    }
    e->joined++;
    *n = got < margin ? got : margin;
    if (step < 0) memmove(edge, edge + (got - *n) * ns, *n * ns * sizeof *edge);
    *frames = edge;
    return SWFS_OK;
}

int swfs_lag_edges_load_(swfs_lag_edges_ *e, const char *tdir, const swfs_timing *t, const char *name,
                         const swfs_real *s, size_t margin)
{
    e->pre = e->post = 0;
    e->ny = s->ny;
    double *before = NULL, *after = NULL;
    size_t nb = 0, na = 0;
    int rc = margin ? side(e, tdir, t, name, s, margin, -1, &before, &nb) : SWFS_OK;
    if (!rc && margin) rc = side(e, tdir, t, name, s, margin, +1, &after, &na);
    const size_t ns = s->nx, total = nb + s->ny + na;
    if (!rc && total > e->cap) {
        double *g = realloc(e->ext, total * ns * sizeof *g);
        if (!g) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory for %zu WFS frames of %zu slopes", total, ns);
        else {
            e->ext = g;
            e->cap = total;
        }
    }
    if (!rc) {
        if (nb) memcpy(e->ext, before, nb * ns * sizeof *e->ext);
        memcpy(e->ext + nb * ns, s->data, s->ny * ns * sizeof *e->ext);
        if (na) memcpy(e->ext + (nb + s->ny) * ns, after, na * ns * sizeof *e->ext);
        e->pre = nb;
        e->post = na;
    }
    free(before);
    free(after);
    return rc;
}

void swfs_lag_edges_free_(swfs_lag_edges_ *e)
{
    free(e->ext);
    memset(e, 0, sizeof *e);
}

int swfs_lag_stacker_rows_(swfs_lag_stacker_ *st, const char *tdir, const swfs_timing *t, const char *name,
                           const char *path, const swfs_real *s, const long *lags, size_t nl, size_t k0, size_t n,
                           const double **out)
{
    int rc = SWFS_OK;
    if (strcmp(st->edges_for, path)) {
        st->edges_for[0] = 0;
        const size_t margin = tdir ? (size_t)swfs_lags_max_abs(lags, nl) : 0;
        if ((rc = swfs_lag_edges_load_(&st->edges, tdir ? tdir : ".", t, name, s, margin))) return rc;
        if (snprintf(st->edges_for, sizeof st->edges_for, "%s", path) >= (int)sizeof st->edges_for)
            return swfs_fail(SWFS_ERR_ARG, "telemetry path %s is too long", path);
    }
    const size_t width = s->nx * nl;
    if (n > st->cap) {
        double *g = realloc(st->buf, n * width * sizeof *g);
        if (!g) return swfs_fail(SWFS_ERR_NOMEM, "out of memory for %zu frames of %zu lags", n, nl);
        st->buf = g;
        st->cap = n;
    }
    const swfs_lag_edges_ *e = &st->edges;
    swfs_slopes_stack(e->ext, e->pre + e->ny + e->post, s->nx, lags, nl, e->pre + k0, n, st->buf);
    *out = st->buf;
    return SWFS_OK;
}

void swfs_lag_stacker_free_(swfs_lag_stacker_ *st)
{
    swfs_lag_edges_free_(&st->edges);
    free(st->buf);
    memset(st, 0, sizeof *st);
}

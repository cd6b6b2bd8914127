/* The reduced science cube's layout: see include/specklewfs/science.h. */
#include "specklewfs/science.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *base_name(const char *p)
{
    const char *s = strrchr(p, '/');
    return s ? s + 1 : p;
}

static int write_stamps(swfs_fits_out *o, const swfs_science_meta *m, size_t nframes)
{
    swfs_real *st = swfs_real_alloc(3, nframes, 1);
    if (!st) return swfs_fail(SWFS_ERR_NOMEM, "out of memory for the STAMPS of %zu frames", nframes);
    for (size_t k = 0; k < nframes; k++) {
        st->data[3 * k] = (double)m->cnt[k];
        st->data[3 * k + 1] = (double)(m->stamp[k] / 1000000000LL);
        st->data[3 * k + 2] = (double)(m->stamp[k] % 1000000000LL);
    }
    int rc = swfs_fits_out_real(o, "STAMPS", st, -64);
    swfs_real_free(st);
    if (!rc) rc = swfs_fits_out_key_string(o, "COLUMNS", "cnt0 seconds nanoseconds", "stamp = end of the exposure");
    if (!rc && m->exptime > 0) rc = swfs_fits_out_key_double(o, "EXPTIME", m->exptime, "[s] from the raw header");
    return rc;
}

int swfs_science_write_meta(swfs_fits_out *o, const swfs_science_meta *m, const double *track, size_t nframes)
{
    /* The bilinear registration averages neighbouring pixels: the registered frames carry
     * NOISEFAC times the raw per-pixel noise variance (read and photon alike), which is
     * what estimate must remove (the raw variance over-subtracts: docs/telemetry.md). */
    const double nv = m->noise_var, q = m->noise_fac;
    int rc = SWFS_OK;
    if (isfinite(nv) &&
        ((rc = swfs_fits_out_key_double(o, "NOISEVAR", q * nv, "noise variance of the output frames [counts^2]")) ||
         (rc = swfs_fits_out_key_double(o, "RDNOISE", sqrt(q * nv), "sqrt(NOISEVAR) [counts], for estimate")) ||
         (rc = swfs_fits_out_key_double(o, "NOISERAW", nv, "noise variance before registration [counts^2]"))))
        return rc;
    if ((rc = swfs_fits_out_key_double(o, "NOISEFAC", q, "variance factor of the registration's interpolation"))) return rc;
    if (isfinite(m->gain_raw) &&
        ((rc = swfs_fits_out_key_double(o, "GAIN", m->gain_raw / q, "[e-/count] raw GAIN / NOISEFAC: photon noise")) ||
         (rc = swfs_fits_out_key_double(o, "GAINRAW", m->gain_raw, "[e-/count] from the raw cube"))))
        return rc;
    /* The exposure time and the resolution the raw header wrote it to: sync's least frame
     * ratio (an exposure lasts at most its frame period) */
    if (m->exptime > 0 &&
        ((rc = swfs_fits_out_key_double(o, "EXPTIME", m->exptime, "[s] from the raw headers (the least)")) ||
         (rc = swfs_fits_out_key_double(o, "EXPTRES", m->exptime_res, "[s] EXPTIME's resolution in the raw header"))))
        return rc;
    if ((rc = swfs_fits_out_key_long(o, "NCUBES", (long)m->ncubes, "raw cubes concatenated")) ||
        (rc = swfs_fits_out_key_long(o, "NBADPIX", (long)m->nbad, "pixels replaced by the 3x3 median")) ||
        (rc = swfs_fits_out_key_long(o, "REGISTER", m->registered, "1: peak shifted to (W/2, H/2)")))
        return rc;
    for (size_t c = 0; c < m->ncubes; c++) {
        char key[32];
        snprintf(key, sizeof key, "CUBE%04u", (unsigned)(c % 10000));
        if ((rc = swfs_fits_out_key_string(o, key, base_name(m->cubes[c]), "raw cube file"))) return rc;
    }
    swfs_real tr = {4, nframes, 1, (double *)track};
    if ((rc = swfs_fits_out_real(o, "TRACK", &tr, -64))) return rc;
    if ((rc = swfs_fits_out_key_string(o, "COLUMNS", "peak_x peak_y cube frame", "pixels before the shift"))) return rc;
    return m->cnt && m->stamp ? write_stamps(o, m, nframes) : SWFS_OK;
}

int swfs_science_stamps_read(const char *path, uint64_t **cnt, int64_t **stamp, size_t *n, double *exptime)
{
    *cnt = NULL;
    *stamp = NULL;
    *n = 0;
    *exptime = 0;
    swfs_fits_in *f = NULL;
    swfs_real *a = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL), found = 0;
    const size_t nz = rc ? 0 : swfs_fits_in_shape(f)->nz;
    if (!rc && !swfs_fits_in_has_ext(f, "STAMPS"))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no STAMPS extension (frame counters and time stamps): reduce raw cubes "
                       "that have their milk timestamp table (.txt) beside them", path);
    if (!rc) rc = swfs_fits_in_move(f, "STAMPS");
    if (!rc) rc = swfs_fits_in_read_real_all(f, &a);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "EXPTIME", exptime, &found);
    if (!rc && !found) *exptime = 0;
    if (!rc && (a->nx != 3 || a->ny != nz || a->nz != 1))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: STAMPS is %zux%zux%zu; expected 3 x %zu (cnt0, seconds, nanoseconds per "
                       "frame)", path, a->nx, a->ny, a->nz, nz);
    if (!rc && (!(*cnt = malloc(nz * sizeof **cnt)) || !(*stamp = malloc(nz * sizeof **stamp))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    for (size_t k = 0; !rc && k < nz; k++) {
        const double c = a->data[3 * k], s = a->data[3 * k + 1], ns = a->data[3 * k + 2];
        if (!(c >= 0 && c < 9e15 && c == floor(c) && s >= 0 && s < 9.2e9 && s == floor(s) && ns >= 0 && ns < 1e9 &&
              ns == floor(ns)))
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: STAMPS row %zu (%g, %g, %g) is not a counter, whole seconds and "
                           "nanoseconds", path, k, c, s, ns);
        else {
            (*cnt)[k] = (uint64_t)c;
            (*stamp)[k] = (int64_t)s * 1000000000LL + (int64_t)ns;
        }
    }
    swfs_real_free(a);
    swfs_fits_in_close(f);
    if (rc) {
        free(*cnt);
        free(*stamp);
        *cnt = NULL;
        *stamp = NULL;
        return rc;
    }
    *n = nz;
    return SWFS_OK;
}

void swfs_science_track_free(swfs_science_track *t)
{
    if (!t) return;
    free(t->x); free(t->y); free(t->first); free(t->n);
    if (t->camera)
        for (size_t c = 0; c < t->ncubes; c++) free(t->camera[c]);
    free(t->camera);
    free(t);
}

/* Frames of each cube (TRACK column 2 = cube index, in order). */
static int split_cubes(const char *path, const swfs_real *track, swfs_science_track *t)
{
    for (size_t k = 0; k < t->nframes; k++) {
        double c = track->data[4 * k + 2];
        if (!(c >= 0) || c >= (double)t->ncubes)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: TRACK frame %zu names cube %g of %zu", path, k, c, t->ncubes);
        size_t ci = (size_t)c;
        if (t->n[ci] == 0) t->first[ci] = k;
        else if (t->first[ci] + t->n[ci] != k)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: frames of cube %zu are not contiguous", path, ci);
        t->n[ci]++;
        t->x[k] = track->data[4 * k];
        t->y[k] = track->data[4 * k + 1];
    }
    return SWFS_OK;
}

static int read_names(swfs_fits_in *fs, const char *path, swfs_science_track *t)
{
    for (size_t ci = 0; ci < t->ncubes; ci++) {
        char key[32], cam[1024];
        int found = 0;
        snprintf(key, sizeof key, "CUBE%04u", (unsigned)(ci % 10000));
        int rc = swfs_fits_in_key_string_opt(fs, key, cam, sizeof cam, &found);
        if (rc) return rc;
        if (!found) return swfs_fail(SWFS_ERR_FORMAT, "%s: missing keyword %s (camera file of cube %zu)", path, key, ci);
        if (t->n[ci] == 0) return swfs_fail(SWFS_ERR_FORMAT, "%s: cube %zu (%s) has no frames", path, ci, cam);
        if (!(t->camera[ci] = strdup(cam))) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    return SWFS_OK;
}

int swfs_science_track_read(const char *path, swfs_science_track **out)
{
    *out = NULL;
    swfs_fits_in *fs = NULL;
    swfs_real *track = NULL;
    swfs_science_track *t = calloc(1, sizeof *t);
    if (!t) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    double v = NAN;
    int found = 0;
    int rc = swfs_fits_in_open(&fs, path, NULL);
    if (!rc) {
        t->nframes = swfs_fits_in_shape(fs)->nz;
        rc = swfs_fits_in_key_double_opt(fs, "NCUBES", &v, &found);
    }
    if (!rc && (!found || !(v >= 1) || v > (double)t->nframes))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no NCUBES keyword between 1 and the %zu frames; run `specklewfs reduce` on "
                       "the raw cubes first", path, t->nframes);
    if (!rc && !swfs_fits_in_has_ext(fs, "TRACK"))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no TRACK extension; run `specklewfs reduce` on the raw cubes first", path);
    if (!rc) rc = swfs_fits_read_real(path, "TRACK", &track, NULL);
    if (!rc && (track->nx != 4 || track->ny != t->nframes))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: TRACK is %zux%zu, expected 4 x %zu (frames)", path, track->nx, track->ny,
                       t->nframes);
    if (!rc) {
        t->ncubes = (size_t)v;
        t->x = malloc(t->nframes * sizeof *t->x);
        t->y = malloc(t->nframes * sizeof *t->y);
        t->first = calloc(t->ncubes, sizeof *t->first);
        t->n = calloc(t->ncubes, sizeof *t->n);
        t->camera = calloc(t->ncubes, sizeof *t->camera);
        if (!t->x || !t->y || !t->first || !t->n || !t->camera) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    if (!rc) rc = split_cubes(path, track, t);
    if (!rc) rc = read_names(fs, path, t);
    /* EXPTIME to the coarser of the resolution its own text shows and the raw header's (EXPTRES) */
    double res = 0, raw_res = 0;
    if (!rc) rc = swfs_fits_in_key_double_res_opt(fs, "EXPTIME", &v, &res, &found);
    if (!rc && found && v > 0 && isfinite(v)) {
        t->exptime = v;
        t->exptime_res = res;
        if (!(rc = swfs_fits_in_key_double_opt(fs, "EXPTRES", &raw_res, &found)) && found && raw_res > res && raw_res < v)
            t->exptime_res = raw_res;
    }
    swfs_fits_in_close(fs);
    swfs_real_free(track);
    if (rc) swfs_science_track_free(t);
    else *out = t;
    return rc;
}

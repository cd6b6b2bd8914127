/* Batches from files for the stream, and the telemetry helpers: see include/specklewfs/source.h. */
#include "specklewfs/source.h"
#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <ctype.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

struct swfs_file_source {
    swfs_timing *timing;
    swfs_fits_in *sci;
    char *slopes_arg;
    int slopes_is_dir;
    size_t nslopes, nf2, bmax;
    size_t cube, j;        /* next camera frame: cube index, frame within the cube */
    char *loaded;          /* telemetry file currently in memory ("" if none) */
    swfs_real *tel;
    double wfs_rate;       /* [Hz] from the telemetry header (WFSRATE), 0 if unknown */
    swfs_exposure *sched;
    double *science;
    double *raw;           /* the camera's frames before re-orientation (NULL: as the model) */
    size_t nx, ny;
    int limited;           /* swfs_file_source_set_range: serve `left` more frames */
    size_t left;
    size_t last_base, last_cube; /* the last batch: its first WFS frame in tel, its cube */
    int served;                  /* a batch has been served */
};

void swfs_path_dir(const char *path, char *dir, size_t cap)
{
    const char *slash = strrchr(path, '/');
    if (!slash) snprintf(dir, cap, ".");
    else if (slash == path) snprintf(dir, cap, "/");
    else snprintf(dir, cap, "%.*s", (int)(slash - path), path);
}

int swfs_telemetry_path(const char *dir, const char *name, char *path, size_t cap)
{
    int n = name[0] == '/' ? snprintf(path, cap, "%s", name) : snprintf(path, cap, "%s/%s", dir, name);
    if (n < 0 || (size_t)n >= cap) return swfs_fail(SWFS_ERR_ARG, "telemetry path %s/%s is too long", dir, name);
    return SWFS_OK;
}

int swfs_telemetry_check_values(const char *path, const swfs_real *s)
{
    const size_t n = s->nx * s->ny * s->nz;
    for (size_t i = 0; i < n; i++)
        if (!isfinite(s->data[i]) || fabs(s->data[i]) > SWFS_TELEMETRY_MAX) {
            char val[48];
            return swfs_fail(SWFS_ERR_VALUE, "%s: slope %zu of WFS frame %zu %s; telemetry values must be finite and "
                             "below %g in magnitude (a fill value, or a corrupt file?)", path, i % s->nx, i / s->nx,
                             swfs_value_words(s->data[i], val, sizeof val), SWFS_TELEMETRY_MAX);
        }
    return SWFS_OK;
}

int swfs_telemetry_check_nsub(const char *path, size_t nsub)
{
    swfs_fits_in *f = NULL;
    int found = 0;
    long v = 0;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_long_opt(f, "NSUB", 1, 1L << 20, &v, &found);
    swfs_fits_in_close(f);
    if (!rc && found && (size_t)v != nsub)
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: NSUB = %ld subapertures across, but the slopes' width (and the valid map, "
                       "if given) make a %zu x %zu Shack-Hartmann", path, v, nsub, nsub);
    return rc;
}

int swfs_telemetry_sensor(const char *path, int *kind, char *type, size_t cap)
{
    swfs_fits_in *f = NULL;
    int found = 0;
    char t[72] = "", up[72];
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_string_opt(f, "WFSTYPE", t, sizeof t, &found);
    swfs_fits_in_close(f);
    size_t n = 0;
    for (; t[n] && n + 1 < sizeof up; n++) up[n] = (char)toupper((unsigned char)t[n]);
    up[n] = 0;
    *kind = rc || !found ? SWFS_WFS_UNNAMED
            : !strncmp(up, "SH", 2) || strstr(up, "HARTMANN") ? SWFS_WFS_SH
            : strstr(up, "PYR") ? SWFS_WFS_PYRAMID : SWFS_WFS_OTHER;
    if (type && cap) snprintf(type, cap, "%s", t);
    return rc;
}

int swfs_telemetry_check_sh(const char *path, const char *what)
{
    int kind = 0;
    char type[72];
    int rc = swfs_telemetry_sensor(path, &kind, type, sizeof type);
    if (!rc && kind != SWFS_WFS_UNNAMED && kind != SWFS_WFS_SH)
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: WFSTYPE = '%s': not a Shack-Hartmann's slopes, which %s models; a "
                       "pyramid's (or any sensor's) signals go through the linear model: --basis INFLUENCE.fits with "
                       "--imat D.fits (the interaction matrix) or --control C.fits, with which speckles simulates loops of "
                       "the system for the residual mean's miss (--mean-loop teach, its default for a pyramid; "
                       "docs/telemetry.md, \"A pyramid wavefront sensor\")", path, type, what);
    return rc;
}

int swfs_telemetry_read(const char *path, size_t nslopes, swfs_real **out, double *rate)
{
    *out = NULL;
    swfs_fits_in *f = NULL;
    int found = 0;
    double r = 0;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "WFSRATE", &r, &found);
    if (!rc) rc = swfs_fits_in_read_real_all(f, out);
    swfs_fits_in_close(f);
    if (!rc && nslopes && ((*out)->nz != 1 || (*out)->nx != nslopes))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes per frame (the "
                       "reconstructor's width) x WFS frames", path, (*out)->nx, (*out)->ny, (*out)->nz, nslopes);
    else if (!rc && (*out)->nz != 1)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected a 2-D image of slopes per frame x WFS "
                       "frames", path, (*out)->nx, (*out)->ny, (*out)->nz);
    if (!rc) rc = swfs_telemetry_check_values(path, *out);
    if (rc) {
        swfs_real_free(*out);
        *out = NULL;
        return rc;
    }
    if (rate) *rate = found && r > 0 && isfinite(r) ? r : 0;
    return SWFS_OK;
}

int swfs_telemetry_check(const char *path, size_t nslopes, size_t *nframes)
{
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    const swfs_fits_shape *sh = rc ? NULL : swfs_fits_in_shape(f);
    if (!rc && (sh->is_complex || sh->nz != 1 || (nslopes && sh->nx != nslopes)))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames", path, sh->nx,
                       sh->ny, sh->nz, nslopes);
    if (!rc && nframes) *nframes = sh->ny;
    swfs_fits_in_close(f);
    return rc;
}

int swfs_telemetry_load_training(const char *dir, const swfs_timing *t, size_t nslopes, double **out,
                                 size_t *nframes)
{
    char path[8192];
    double *buf = NULL;
    size_t n = 0;
    *out = NULL;
    *nframes = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        if (t->cubes[c].status != SWFS_CUBE_OK) continue;
        int seen = 0;
        for (size_t d = 0; d < c && !seen; d++)
            seen = t->cubes[d].status == SWFS_CUBE_OK && !strcmp(t->cubes[d].slopes, t->cubes[c].slopes);
        if (seen) continue;
        swfs_real *s = NULL;
        int rc = swfs_telemetry_path(dir, t->cubes[c].slopes, path, sizeof path);
        if (!rc) rc = swfs_telemetry_read(path, nslopes, &s, NULL);
        double *tmp = rc ? NULL : realloc(buf, (n + s->ny) * nslopes * sizeof *tmp);
        if (!rc && !tmp) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for the training slopes", path);
        if (rc) {
            swfs_real_free(s);
            free(buf);
            return rc;
        }
        buf = tmp;
        memcpy(buf + n * nslopes, s->data, s->ny * nslopes * sizeof *buf);
        n += s->ny;
        swfs_real_free(s);
    }
    *out = buf;
    *nframes = n;
    return SWFS_OK;
}

void swfs_file_source_close(swfs_file_source *s)
{
    if (!s) return;
    swfs_timing_free(s->timing);
    swfs_fits_in_close(s->sci);
    swfs_real_free(s->tel);
    free(s->slopes_arg);
    free(s->loaded);
    free(s->sched);
    free(s->science);
    free(s->raw);
    free(s);
}

int swfs_file_source_open(swfs_file_source **out, const char *timing, const char *science, const char *slopes,
                          size_t nslopes, size_t batch)
{
    *out = NULL;
    if (!batch) return swfs_fail(SWFS_ERR_ARG, "file source: batch must be >= 1 camera frame");
    swfs_file_source *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "file source: out of memory");
    int rc = swfs_timing_read(timing, &s->timing);
    if (!rc && !(s->timing->ratio >= SWFS_ENGINE_MIN_RATIO))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: frame-rate ratio %g; expected >= %g WFS frames per camera frame", timing,
                       s->timing->ratio, SWFS_ENGINE_MIN_RATIO);
    if (!rc) rc = swfs_fits_in_open(&s->sci, science, NULL);
    const swfs_fits_shape *ss = rc ? NULL : swfs_fits_in_shape(s->sci);
    if (!rc && ss->is_complex)
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: science cube is complex; expected real intensities", science);
    /* The camera's orientation (sync's pairing): frames are turned into the model's as they
     * are read. A copy already turned (speckles --match) no longer matches the table. */
    if (!rc) rc = swfs_orient_check(&s->timing->fit, ss->nx, ss->ny, timing);
    if (!rc) {
        char o[80];
        int found = 0;
        rc = swfs_fits_in_key_string_opt(s->sci, "CAMORIEN", o, sizeof o, &found);
        if (!rc && found)
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: a copy already turned into the model's orientation (CAMORIEN = '%s'); "
                           "give the reduced science cube that %s refers to", science, o, timing);
    }
    for (size_t c = 0; !rc && c < s->timing->ncubes; c++) {
        const swfs_timing_cube *tc = &s->timing->cubes[c];
        if (tc->status == SWFS_CUBE_OK && tc->first + tc->nframes > ss->nz)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: cube %zu needs frames %zu..%zu but %s holds %zu", timing, c, tc->first,
                           tc->first + tc->nframes - 1, science, ss->nz);
    }
    if (rc) {
        swfs_file_source_close(s);
        return rc;
    }
    char dir[4096];
    swfs_path_dir(timing, dir, sizeof dir);
    s->slopes_arg = strdup(slopes ? slopes : dir);
    s->loaded = calloc(1, 1);
    struct stat sb;
    s->slopes_is_dir = s->slopes_arg && stat(s->slopes_arg, &sb) == 0 && S_ISDIR(sb.st_mode);
    s->nslopes = nslopes;
    s->nf2 = ss->nx * ss->ny;
    s->bmax = batch;
    s->sched = malloc(batch * sizeof *s->sched);
    s->nx = ss->nx;
    s->ny = ss->ny;
    s->science = batch <= SIZE_MAX / sizeof(double) / s->nf2 ? malloc(batch * s->nf2 * sizeof *s->science) : NULL;
    if (s->science && !swfs_orient_is_identity(&s->timing->fit)) s->raw = malloc(batch * s->nf2 * sizeof *s->raw);
    if (!s->slopes_arg || !s->loaded || !s->sched || !s->science || (!swfs_orient_is_identity(&s->timing->fit) && !s->raw)) {
        swfs_file_source_close(s);
        return swfs_fail(SWFS_ERR_NOMEM, "file source: out of memory for batches of %zu frames", batch);
    }
    *out = s;
    return SWFS_OK;
}

int swfs_file_source_telemetry_path(const char *timing, const char *slopes, const char *name, char *path, size_t cap)
{
    char dir[4096];
    struct stat sb;
    swfs_path_dir(timing, dir, sizeof dir);
    if (!slopes) slopes = dir;
    if (stat(slopes, &sb) == 0 && S_ISDIR(sb.st_mode)) return swfs_telemetry_path(slopes, name, path, cap);
    snprintf(path, cap, "%s", slopes);
    return SWFS_OK;
}

/* Make the telemetry file of the current cube the one in memory. */
static int load_telemetry(swfs_file_source *s, const swfs_timing_cube *c, char *path, size_t cap)
{
    int rc = SWFS_OK;
    if (s->slopes_is_dir) rc = swfs_telemetry_path(s->slopes_arg, c->slopes, path, cap);
    else snprintf(path, cap, "%s", s->slopes_arg);
    if (rc || !strcmp(path, s->loaded)) return rc;
    swfs_real_free(s->tel);
    s->tel = NULL;
    s->loaded[0] = '\0';
    double rate;
    if ((rc = swfs_telemetry_read(path, s->nslopes, &s->tel, &rate))) return rc;
    if (rate > 0) s->wfs_rate = rate;
    char *t = strdup(path);
    if (!t) return swfs_fail(SWFS_ERR_NOMEM, "file source: out of memory");
    free(s->loaded);
    s->loaded = t;
    return SWFS_OK;
}

int swfs_file_source_next(void *ctx, swfs_batch *b)
{
    swfs_file_source *s = ctx;
    b->nexp = 0;
    const swfs_timing *t = s->timing;
    while (s->cube < t->ncubes &&
           (t->cubes[s->cube].status != SWFS_CUBE_OK || s->j >= t->cubes[s->cube].nframes)) {
        s->cube++;
        s->j = 0;
    }
    if (s->cube >= t->ncubes) return SWFS_OK;
    const swfs_timing_cube *c = &t->cubes[s->cube];
    char path[8192];
    int rc = load_telemetry(s, c, path, sizeof path);
    if (rc) return rc;
    const size_t nwfs_file = s->tel->ny;
    size_t n = c->nframes - s->j < s->bmax ? c->nframes - s->j : s->bmax;
    if (s->limited) {
        if (!s->left) return SWFS_OK;
        if (n > s->left) n = s->left;
    }
    const double t0 = c->start + (double)s->j * t->ratio;
    if (!(t0 >= 0))
        return swfs_fail(SWFS_ERR_VALUE, "cube %zu (%s) starts at WFS frame %g, before the start of %s", s->cube,
                         c->camera, t0, path);
    const size_t base = (size_t)floor(t0);
    const size_t need = swfs_engine_schedule(t->ratio, t0 - (double)base, n, s->sched);
    if (!need || base + need > nwfs_file)
        return swfs_fail(SWFS_ERR_VALUE, "cube %zu (%s) frames %zu..%zu need WFS frames up to %zu but %s holds %zu",
                         s->cube, c->camera, s->j, s->j + n - 1, base + need, path, nwfs_file);
    if ((rc = swfs_fits_in_read_real(s->sci, c->first + s->j, n, s->raw ? s->raw : s->science))) return rc;
    for (size_t k = 0; s->raw && k < n; k++)
        swfs_orient_frame(&t->fit, s->nx, s->ny, 1, s->raw + k * s->nf2, s->science + k * s->nf2);
    b->slopes = s->tel->data + base * s->nslopes;
    b->nwfs = need;
    b->sched = s->sched;
    b->science = s->science;
    b->nexp = n;
    b->cube = s->cube;
    s->last_base = base;
    s->last_cube = s->cube;
    s->served = 1;
    s->j += n;
    if (s->limited) s->left -= n;
    return SWFS_OK;
}

int swfs_file_source_last(const swfs_file_source *s, swfs_file_source_pos *pos)
{
    memset(pos, 0, sizeof *pos);
    if (!s->served || !s->tel)
        return swfs_fail(SWFS_ERR_ARG, "file source: no batch has been served yet");
    pos->tel = s->tel;
    pos->path = s->loaded;
    pos->dir = s->slopes_is_dir ? s->slopes_arg : NULL;
    pos->name = s->timing->cubes[s->last_cube].slopes;
    pos->base = s->last_base;
    return SWFS_OK;
}

int swfs_file_source_check(const swfs_file_source *s)
{
    const swfs_timing *t = s->timing;
    size_t cube = s->cube, j = s->j, left = s->left;
    char path[8192], last[8192] = "";
    size_t nwfs = 0;
    for (; cube < t->ncubes && (!s->limited || left); cube++, j = 0) {
        const swfs_timing_cube *c = &t->cubes[cube];
        if (c->status != SWFS_CUBE_OK || j >= c->nframes) continue;
        size_t n = c->nframes - j;
        if (s->limited && n > left) n = left;
        left -= s->limited ? n : 0;
        int rc = SWFS_OK;
        if (s->slopes_is_dir) rc = swfs_telemetry_path(s->slopes_arg, c->slopes, path, sizeof path);
        else snprintf(path, sizeof path, "%s", s->slopes_arg);
        if (!rc && strcmp(path, last)) rc = swfs_telemetry_check(path, s->nslopes, &nwfs);
        if (rc) return rc;
        snprintf(last, sizeof last, "%s", path);
        /* the last WFS frame the exposures of frames j .. j + n - 1 reach */
        const double end = c->start + (double)(j + n) * t->ratio;
        if (!(c->start >= 0) || ceil(end) > (double)nwfs)
            return swfs_fail(SWFS_ERR_VALUE, "cube %zu (%s) frames %zu..%zu need WFS frames up to %.0f but %s holds %zu",
                             cube, c->camera, j, j + n - 1, ceil(end), path, nwfs);
    }
    return SWFS_OK;
}

int swfs_file_source_set_range(swfs_file_source *s, size_t first, size_t count)
{
    const swfs_timing *t = s->timing;
    size_t skip = first;
    s->cube = t->ncubes;
    s->j = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        if (t->cubes[c].status != SWFS_CUBE_OK) continue;
        if (skip < t->cubes[c].nframes) {
            s->cube = c;
            s->j = skip;
            skip = 0;
            break;
        }
        skip -= t->cubes[c].nframes;
    }
    if (count && s->cube == t->ncubes)
        return swfs_fail(SWFS_ERR_ARG, "file source: frames %zu..%zu are beyond the %zu usable frames of the data set",
                         first, first + count - 1, first - skip);
    s->limited = 1;
    s->left = count;
    return SWFS_OK;
}

const swfs_timing *swfs_file_source_timing(const swfs_file_source *s) { return s->timing; }
double swfs_file_source_wfs_rate(const swfs_file_source *s) { return s->wfs_rate; }

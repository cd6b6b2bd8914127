/* specklewfs wind: the telemetry files of one series, their geometry, and the wind of the
 * dominant frozen-flow layer (include/specklewfs/wind.h). */
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* The files' slopes one after the other (swfs_telemetry_read: the values checked, the file
 * named; the same width in all), NSUB and WFSRATE of the first that has them (*nsub, *rate: 0
 * when none). The files each once and in order: the same file twice (by device and inode)
 * would be read as frames that follow themselves, and a file whose FRAME0 (the WFS frame of its
 * first row, where it and the one before have it) does not come after the previous file's last
 * frame repeats frames or runs backwards; either inflates the time correlations the winds are
 * read from. */
static int read_series(const swfs_wind_run_options *o, double **out, size_t *nframes, size_t *nslopes, long *nsub,
                       double *rate)
{
    double *all = NULL;
    size_t n = 0, w = 0;
    int rc = SWFS_OK;
    long prev_end = -1; /* the WFS frame after the previous file's last, from its FRAME0 (-1: none) */
    *nsub = 0;
    *rate = 0;
    for (size_t k = 0; k < o->nfiles && !rc; k++) {
        struct stat a, b;
        for (size_t j = 0; j < k && !rc && !stat(o->files[k], &a); j++)
            if (!stat(o->files[j], &b) && a.st_dev == b.st_dev && a.st_ino == b.st_ino)
                rc = swfs_fail(SWFS_ERR_ARG, "%s and %s are the same file: the series' files are given once each, in "
                               "time order", o->files[j], o->files[k]);
        if (rc) break;
        swfs_real *s = NULL;
        double wr = 0;
        if ((rc = swfs_telemetry_read(o->files[k], 0, &s, &wr))) break;
        if (w && s->nx != w)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames as in %s",
                           o->files[k], s->nx, s->ny, s->nz, w, o->files[0]);
        double *grown = NULL;
        if (!rc && !(grown = realloc(all, (n + s->ny) * s->nx * sizeof *all)))
            rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for %zu WFS frames", o->files[k], n + s->ny);
        if (grown) all = grown;
        if (!rc) {
            memcpy(all + n * s->nx, s->data, s->nx * s->ny * sizeof *all);
            w = s->nx;
            n += s->ny;
            if (*rate == 0.0) *rate = wr;
        }
        const size_t rows = s->ny;
        swfs_real_free(s);
        if (!rc) { /* NSUB, when the file has it, and FRAME0 */
            swfs_fits_in *f = NULL;
            int found = 0;
            long f0 = 0;
            rc = swfs_fits_in_open(&f, o->files[k], NULL);
            if (!rc && !*nsub) rc = swfs_fits_in_key_long_opt(f, "NSUB", 1, 100000, nsub, &found);
            if (!rc) rc = swfs_fits_in_key_long_opt(f, "FRAME0", 0, (long)1 << 50, &f0, &found);
            swfs_fits_in_close(f);
            if (!rc && found && prev_end >= 0 && f0 < prev_end)
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: FRAME0 = %ld, but %s ends at WFS frame %ld: the series' files are "
                               "given in time order, without repeated frames", o->files[k], f0, o->files[k - 1],
                               prev_end - 1);
            prev_end = found ? f0 + (long)rows : -1;
        }
    }
    if (rc) { free(all); return rc; }
    *out = all;
    *nframes = n;
    *nslopes = w;
    return SWFS_OK;
}

int swfs_wind_run(const swfs_wind_run_options *o, swfs_wind_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->nfiles) return swfs_fail(SWFS_ERR_ARG, "wind: no telemetry files");
    if (!(o->teldiam > 0) || !isfinite(o->teldiam))
        return swfs_fail(SWFS_ERR_VALUE, "wind: the telescope diameter %g m must be > 0 (the subapertures' pitch is "
                         "teldiam / nsub)", o->teldiam);
    unsigned char *vmap = NULL;
    size_t vn = 0, nv = 0;
    int rc = o->valid ? swfs_valid_map_read(o->valid, &vmap, &vn, &nv) : SWFS_OK;
    double *s = NULL, rate = 0;
    size_t nframes = 0, nslopes = 0;
    long fnsub = 0;
    if (!rc) rc = read_series(o, &s, &nframes, &nslopes, &fnsub, &rate);
    long nsub = o->nsub ? o->nsub : fnsub ? fnsub : (long)vn;
    if (!rc && !nsub)
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: no NSUB keyword and no valid-subaperture map: give the subapertures "
                       "across", o->files[0]);
    if (!rc && vmap && (size_t)nsub != vn)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: a valid-subaperture map of %zu x %zu, but %ld subapertures across", o->valid,
                       vn, vn, nsub);
    if (o->rate > 0) rate = o->rate;
    if (!rc && !(rate > 0))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: no WFSRATE keyword; give the WFS frame rate", o->files[0]);
    if (!rc) {
        r->nframes = nframes;
        r->nsub = (size_t)nsub;
        r->pitch = o->teldiam / (double)nsub;
        r->rate = rate;
        rc = swfs_wind_from_slopes(s, nframes, nslopes, (size_t)nsub, vmap, r->pitch, rate, &r->est);
        if (rc) swfs_fail_context(rc, "%s", o->nfiles == 1 ? o->files[0] : "the telemetry files");
    }
    free(s);
    free(vmap);
    return rc;
}

int swfs_spacetime_stats_(const double *s, size_t nframes, size_t nslopes, size_t nsub, const unsigned char *valid,
                          const long *lags, size_t nlags, swfs_wind_estimate *wind, double *corr)
{
    if (wind) {
        wind->found = 0;
        /* a series too short or too coarse for a wind has none: not an error here */
        if ((valid || nslopes == 2 * nsub * nsub) && swfs_wind_from_slopes(s, nframes, nslopes, nsub, valid, 1.0, 1.0, wind))
            wind->found = 0;
    }
    return corr ? swfs_slopes_lag_correlation(s, nframes, nslopes, lags, nlags, corr) : SWFS_OK;
}

/* specklewfs wind: the telemetry files of one series, their geometry, and the wind of the
 * dominant frozen-flow layer (include/specklewfs/wind.h). */
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* The files' slopes one after the other (the same width in all), NSUB and WFSRATE of the
 * first that has them (*nsub, *rate: 0 when none). */
static int read_series(const swfs_wind_run_options *o, double **out, size_t *nframes, size_t *nslopes, long *nsub,
                       double *rate)
{
    double *all = NULL;
    size_t n = 0, w = 0;
    int rc = SWFS_OK;
    *nsub = 0;
    *rate = 0;
    for (size_t k = 0; k < o->nfiles && !rc; k++) {
        swfs_fits_in *f = NULL;
        double wr = 0;
        long ns = 0;
        int has_rate = 0, has_nsub = 0;
        if ((rc = swfs_fits_in_open(&f, o->files[k], NULL))) break;
        rc = swfs_fits_in_key_double_opt(f, "WFSRATE", &wr, &has_rate);
        if (!rc) rc = swfs_fits_in_key_long_opt(f, "NSUB", 1, 100000, &ns, &has_nsub);
        const swfs_fits_shape *sh = swfs_fits_in_shape(f);
        if (!rc && (sh->nz != 1 || (w && sh->nx != w)))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames as in %s",
                           o->files[k], sh->nx, sh->ny, sh->nz, w ? w : sh->nx, o->files[0]);
        double *grown = NULL;
        if (!rc && !(grown = realloc(all, (n + sh->ny) * sh->nx * sizeof *all)))
            rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for %zu WFS frames", o->files[k], n + sh->ny);
        if (grown) all = grown;
        if (!rc) rc = swfs_fits_in_read_rows(f, 0, sh->ny, all + n * sh->nx);
        if (!rc) {
            w = sh->nx;
            n += sh->ny;
            if (has_rate && !*rate) *rate = wr;
            if (has_nsub && !*nsub) *nsub = ns;
        }
        swfs_fits_in_close(f);
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

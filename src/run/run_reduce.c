/* reduce: raw camera cubes -> the reduced science cube. See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/fits.h"
#include "specklewfs/milklog.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/science.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_reduce_run_options_default(swfs_reduce_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_reduce_params_default(&o->params);
    swfs_geom_init(&o->geom);
}

static int read_map(const char *path, size_t nx, size_t ny, double **out)
{
    swfs_real *a = NULL;
    int rc = swfs_fits_read_real(path, NULL, &a, NULL);
    if (rc) return rc;
    if (a->nx != nx || a->ny != ny || a->nz != 1)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: calibration frame is %zux%zux%zu but the camera frames are %zux%zu", path,
                       a->nx, a->ny, a->nz, nx, ny);
    else {
        *out = a->data;
        a->data = NULL;
    }
    swfs_real_free(a);
    return rc;
}

/* Open every raw cube: real, one frame size. *exptime: the least EXPTIME of their headers
 * (0: a cube has none), *exptime_res the resolution that one was written to. */
static int open_raw(const swfs_reduce_run_options *o, swfs_fits_in **in, size_t *nx, size_t *ny, size_t *ntot,
                    double *exptime, double *exptime_res)
{
    *ntot = 0;
    *exptime = *exptime_res = 0;
    for (size_t c = 0; c < o->nraw; c++) {
        int rc = swfs_fits_in_open(&in[c], o->raw[c], NULL);
        if (rc) return rc;
        int found = 0;
        double e = 0, res = 0;
        if ((rc = swfs_fits_in_key_double_res_opt(in[c], "EXPTIME", &e, &res, &found))) return rc;
        if (found && !(e > 0 && e < 1e4))
            return swfs_fail(SWFS_ERR_VALUE, "%s: EXPTIME = %g s; expected a positive exposure time", o->raw[c], e);
        if (!found) *exptime = -1; /* a cube without: none */
        else if (*exptime == 0 || (*exptime > 0 && e < *exptime)) { *exptime = e; *exptime_res = res; }
        const swfs_fits_shape *s = swfs_fits_in_shape(in[c]);
        if (s->is_complex)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: camera cube is complex; expected real counts (x, y, frame)", o->raw[c]);
        if (c == 0) { *nx = s->nx; *ny = s->ny; }
        else if (s->nx != *nx || s->ny != *ny)
            return swfs_fail(SWFS_ERR_SHAPE, "%s: frames are %zux%zu but %s has %zux%zu (all cubes must have the same "
                             "frame size)", o->raw[c], s->nx, s->ny, o->raw[0], *nx, *ny);
        *ntot += s->nz;
    }
    if (*exptime < 0) *exptime = *exptime_res = 0;
    return SWFS_OK;
}

/* Parameters that follow from the raw header: the sampling and the photon gain. */
static int header_params(const swfs_reduce_run_options *o, swfs_fits_in *f, swfs_geom *geom, swfs_reduce_params *p,
                         double *gainv, swfs_reduce_run_result *r)
{
    int found = 0;
    int rc = swfs_fits_in_geom(f, geom);
    if (rc) return rc;
    /* The given geometry over the header's, checked; what is still missing is reported. */
    r->overridden = swfs_geom_overlay(geom, &o->geom);
    if ((rc = swfs_geom_check(geom, o->raw[0]))) return rc;
    swfs_geom_missing(geom, r->missing, sizeof r->missing);
    /* The out-of-band noise estimate needs the sampling (PIXSCALE). */
    if (!o->noise_region && isfinite(geom->pixscale) && geom->pixscale > 0 && geom->pixscale < 0.45)
        p->pixscale = geom->pixscale;
    /* The reference peak: 1 lambda/D (sigma) when the sampling is known. Narrower
     * references follow the speckled core's fine structure and bias the per-frame
     * centre (measured: 2 px at 0.25 lambda/D triples the NCP error). */
    if (!o->sigma_given && isfinite(geom->pixscale) && geom->pixscale > 0) p->gauss_sigma = 1.0 / geom->pixscale;
    if ((rc = swfs_fits_in_key_double_opt(f, "GAIN", gainv, &found))) return rc;
    if (!found) *gainv = NAN;
    /* Photon noise is modelled per pixel by estimate (Phi_I / GAIN): measure the rest. */
    if (isfinite(*gainv) && *gainv > 0) p->gain = *gainv;
    return SWFS_OK;
}

/* The milk timestamp tables beside the raw cubes (all or none) -> counters and stamps of
 * every frame, in the order the cubes are given. */
static int raw_stamps(const swfs_reduce_run_options *o, swfs_fits_in **in, size_t ntot, uint64_t **cnt,
                      int64_t **stamp, swfs_reduce_run_result *r)
{
    char txt[8192];
    size_t have = 0, k = 0;
    const char *without = NULL, *with = NULL;
    for (size_t c = 0; c < o->nraw; c++) {
        FILE *f = swfs_milk_txt_path(o->raw[c], txt, sizeof txt) ? NULL : fopen(txt, "r");
        swfs_clear_error();
        if (f) { fclose(f); have++; with = o->raw[c]; }
        else without = o->raw[c];
    }
    if (!have) return SWFS_OK;
    if (have < o->nraw)
        return swfs_fail(SWFS_ERR_VALUE, "%s has a milk timestamp table beside it but %s has none: give raw cubes that "
                         "all have one (their stamps go into STAMPS) or none", with, without);
    if (!(*cnt = malloc(ntot * sizeof **cnt)) || !(*stamp = malloc(ntot * sizeof **stamp)))
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory for the stamps of %zu frames", ntot);
    for (size_t c = 0; c < o->nraw; c++) {
        uint64_t *cc = NULL;
        int64_t *tt = NULL;
        size_t n = 0, nz = swfs_fits_in_shape(in[c])->nz;
        int rc = swfs_milk_txt_path(o->raw[c], txt, sizeof txt);
        if (!rc) rc = swfs_milk_txt_read(txt, &cc, &tt, &n);
        if (!rc && n != nz)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s holds %zu frames but its timestamp table %s lists %zu", o->raw[c], nz,
                           txt, n);
        if (!rc && k && tt[0] < (*stamp)[k - 1])
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: its first stamp is before the last one of %s: give the raw cubes in "
                           "time order", o->raw[c], o->raw[c - 1]);
        for (size_t j = 0; !rc && j < n; j++, k++) {
            (*cnt)[k] = cc[j];
            (*stamp)[k] = tt[j];
            if (k && cc[j] > (*cnt)[k - 1] + 1) r->dropped += cc[j] - (*cnt)[k - 1] - 1;
        }
        free(cc);
        free(tt);
        if (rc) return rc;
    }
    r->stamped = 1;
    return SWFS_OK;
}

int swfs_reduce_run(const swfs_reduce_run_options *o, swfs_reduce_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->nraw || !o->out) return swfs_fail(SWFS_ERR_ARG, "reduce: needs raw camera cubes and an output");
    swfs_paths *paths = NULL;
    int prc = swfs_paths_create(&paths);
    for (size_t c = 0; !prc && c < o->nraw; c++) prc = swfs_paths_input(paths, "raw camera cube", o->raw[c]);
    if (!prc) swfs_paths_input(paths, "dark frame", o->dark);
    if (!prc) swfs_paths_input(paths, "flat field", o->flat);
    if (!prc) swfs_paths_input(paths, "bad-pixel map", o->badpix);
    if (!prc) prc = swfs_paths_output(paths, "output science cube", o->out);
    swfs_paths_free(paths);
    if (prc) return prc;
    swfs_fits_in **in = calloc(o->nraw, sizeof *in);
    double *dark = NULL, *flat = NULL, *bad = NULL, *buf = NULL, *track = NULL;
    uint64_t *cnt = NULL;
    int64_t *stamp = NULL;
    swfs_reduce *red = NULL;
    swfs_fits_out *out = NULL;
    swfs_reduce_params p = o->params;
    swfs_geom geom;
    double gainv = NAN;
    size_t nx = 0, ny = 0, ntot = 0;
    double exptime_res = 0;
    int rc = in ? open_raw(o, in, &nx, &ny, &ntot, &r->exptime, &exptime_res)
                : swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->out);
    if (!rc) rc = raw_stamps(o, in, ntot, &cnt, &stamp, r);
    if (!rc && o->dark) rc = read_map(o->dark, nx, ny, &dark);
    if (!rc && o->flat) rc = read_map(o->flat, nx, ny, &flat);
    if (!rc && o->badpix) rc = read_map(o->badpix, nx, ny, &bad);
    if (!rc) rc = header_params(o, in[0], &geom, &p, &gainv, r);
    if (!rc) rc = swfs_reduce_create(&red, nx, ny, dark, flat, bad, &p);
    if (!rc && (!(buf = malloc(nx * ny * sizeof *buf)) || !(track = malloc(4 * ntot * sizeof *track))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->out);
    if (!rc) rc = swfs_fits_out_create(&out, o->out);
    if (!rc) rc = swfs_fits_out_begin(out, NULL, nx, ny, ntot, 0, -32);
    for (size_t c = 0, k = 0; !rc && c < o->nraw; c++) {
        size_t nz = swfs_fits_in_shape(in[c])->nz;
        for (size_t f = 0; !rc && f < nz; f++, k++) {
            double px, py;
            if ((rc = swfs_fits_in_read_real(in[c], f, 1, buf))) break;
            if ((rc = swfs_reduce_frame(red, buf, buf, &px, &py))) { swfs_fail_context(rc, "%s frame %zu", o->raw[c], f); break; }
            rc = swfs_fits_out_real_frames(out, k, 1, buf);
            track[4 * k] = px; track[4 * k + 1] = py; track[4 * k + 2] = (double)c; track[4 * k + 3] = (double)f;
        }
        if (!rc) rc = swfs_progress_report(o->progress, o->progress_ctx, "cubes", c + 1, o->nraw);
    }
    if (!rc) {
        r->nframes = ntot;
        r->nbad = swfs_reduce_nbad(red);
        /* A variance: an estimate below 0 is one consistent with no read noise. */
        r->noise_var_measured = swfs_reduce_noise_var(red);
        r->noise_var = r->noise_var_measured < 0 ? 0.0 : r->noise_var_measured;
        r->noise_fac = swfs_reduce_noise_factor(red);
        swfs_science_meta m = {r->noise_var, r->noise_fac, gainv, o->nraw,   o->raw,
                               r->nbad,      p.do_register, cnt,   stamp, r->exptime, exptime_res};
        if (!(rc = swfs_fits_out_geom(out, &geom)) && !(rc = swfs_fits_out_provenance(out, o->prov, o->nprov)) &&
            !(rc = swfs_science_write_meta(out, &m, track, ntot))) {
            rc = swfs_fits_out_commit(out);
            out = NULL;
        }
    }
    swfs_fits_out_abort(out);
    for (size_t c = 0; in && c < o->nraw; c++) swfs_fits_in_close(in[c]);
    free(in); free(dark); free(flat); free(bad); free(buf); free(track); free(cnt); free(stamp);
    swfs_reduce_free(red);
    return rc;
}

/* Accumulator checkpoints: see include/specklewfs/checkpoint.h. */
#include "specklewfs/checkpoint.h"
#include "specklewfs/estimate.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const field_names = "N MI MX MY MA CII CIX CIY CIA CXX CXY CXA CYY CYA CAA";

int swfs_accum_save(const swfs_accum *a, const char *path, const swfs_geom *g, const char *const *prov,
                    size_t nprov)
{
    return swfs_accum_save_resmean(a, NULL, 0, path, g, prov, nprov);
}

int swfs_accum_save_resmean(const swfs_accum *a, const swfs_real *resmean, size_t nexp, const char *path,
                            const swfs_geom *g, const char *const *prov, size_t nprov)
{
    if (!a || !path) return swfs_fail(SWFS_ERR_ARG, "checkpoint: missing accumulator or path");
    swfs_geom none;
    swfs_geom_init(&none);
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    rc = swfs_fits_out_set_stamp(o, g ? g : &none, prov, nprov);
    if (!rc) rc = swfs_fits_out_begin(o, "ACCUM", a->nx, a->ny, SWFS_ACC_NFIELDS, 0, -64);
    for (int k = 0; k < SWFS_ACC_NFIELDS && !rc; k++) rc = swfs_fits_out_real_frames(o, (size_t)k, 1, a->f[k]);
    if (!rc) rc = swfs_fits_out_key_long(o, "ACCVER", SWFS_CHECKPOINT_VERSION, "specklewfs accumulator layout");
    if (!rc) rc = swfs_fits_out_key_string(o, "ACCFLDS", field_names, "planes: count, means of I x y |psi|^2, co-moments");
    if (!rc) rc = swfs_fits_out_key_long(o, "FRAMES", (long)a->frames, "frames offered");
    if (!rc) rc = swfs_fits_out_key_long(o, "SKIPPED", (long)a->skipped, "pixel-frames skipped (non-finite science)");
    if (!rc) rc = swfs_regress_write_ext(o, a->reg);
    if (!rc && resmean && nexp) {
        rc = swfs_fits_out_real(o, "RESMEAN", resmean, -64);
        if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "AO residual's time mean (telemetry)");
        if (!rc) rc = swfs_fits_out_key_long(o, "RESMNEXP", (long)nexp, "exposures it averages");
    }
    if (rc) {
        swfs_fits_out_abort(o);
        return swfs_fail_context(rc, "%s", path);
    }
    return swfs_fits_out_commit(o);
}

int swfs_resmean_merge_files(const char *const *paths, size_t n, swfs_real **out, size_t *nexp, size_t *nmissing)
{
    *out = NULL;
    *nexp = 0;
    *nmissing = 0;
    swfs_real *sum = NULL;
    int rc = SWFS_OK;
    for (size_t i = 0; i < n && !rc; i++) {
        swfs_fits_in *f = NULL;
        if ((rc = swfs_fits_in_open(&f, paths[i], NULL))) break;
        if (!swfs_fits_in_has_ext(f, "RESMEAN")) {
            (*nmissing)++;
            swfs_fits_in_close(f);
            continue;
        }
        swfs_real *m = NULL;
        double k = 0.0;
        int found = 0;
        rc = swfs_resmean_read_ext(f, paths[i], &m);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, "RESMNEXP", &k, &found);
        if (!rc && (!found || !(k >= 1.0) || k != floor(k)))
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: RESMEAN without a whole number of exposures (RESMNEXP %g)", paths[i],
                           found ? k : NAN);
        if (!rc && sum && (m->nx != sum->nx || m->ny != sum->ny))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: RESMEAN is %zux%zu but %s's is %zux%zu", paths[i], m->nx, m->ny,
                           paths[0], sum->nx, sum->ny);
        if (!rc && !sum && !(sum = swfs_real_alloc(m->nx, m->ny, 1))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        for (size_t q = 0; !rc && q < m->nx * m->ny; q++) sum->data[q] += k * m->data[q];
        if (!rc) *nexp += (size_t)k;
        swfs_real_free(m);
        swfs_fits_in_close(f);
    }
    if (rc || *nmissing || !sum) {
        swfs_real_free(sum);
        *nexp = 0;
        return rc;
    }
    for (size_t q = 0; q < sum->nx * sum->ny; q++) sum->data[q] /= (double)*nexp;
    *out = sum;
    return SWFS_OK;
}

#define REGSTATE_VERSION 1

int swfs_regress_write_ext(swfs_fits_out *o, const swfs_regress *r)
{
    const size_t np = r->nx * r->ny;
    int rc = swfs_fits_out_begin(o, "REGSTATE", r->nx, r->ny, SWFS_REGRESS_NSTATE, 0, -64);
    for (int k = 0; k < SWFS_REGRESS_NSTATE && !rc; k++)
        rc = swfs_fits_out_real_frames(o, (size_t)k, 1, r->state + (size_t)k * np);
    if (!rc) rc = swfs_fits_out_key_long(o, "REGVER", REGSTATE_VERSION, "specklewfs regression statistics layout");
    if (!rc) rc = swfs_fits_out_key_string(o, "COMMENT", "planes: n, centre set, centre (re, im), sum p (re, im), "
                                           "G (10, upper triangle), h (4), sum I^2 (regress.h)", NULL);
    if (!rc) rc = swfs_fits_out_key_long(o, "FRAMES", (long)r->frames, "frames offered");
    if (!rc) rc = swfs_fits_out_key_long(o, "SKIPPED", (long)r->skipped, "pixel-frames skipped (non-finite science)");
    return rc;
}

static int count_key(swfs_fits_in *f, const char *path, const char *key, uint64_t *out);

int swfs_regress_read_ext(swfs_fits_in *f, const char *path, size_t nx, size_t ny, swfs_regress **out)
{
    *out = NULL;
    int rc = swfs_fits_in_move(f, "REGSTATE");
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(f);
    if (sh->is_complex || sh->nx != nx || sh->ny != ny || sh->nz != SWFS_REGRESS_NSTATE)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: REGSTATE is %zux%zux%zu%s; expected a real cube %zux%zux%d", path, sh->nx,
                         sh->ny, sh->nz, sh->is_complex ? " complex" : "", nx, ny, SWFS_REGRESS_NSTATE);
    double ver;
    if ((rc = swfs_fits_in_key_double(f, "REGVER", &ver))) return swfs_fail_context(rc, "%s: REGSTATE", path);
    if (ver != REGSTATE_VERSION)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: REGSTATE layout version %g, this program reads version %d", path, ver,
                         REGSTATE_VERSION);
    swfs_regress *r = swfs_regress_create(nx, ny);
    double *state = r ? malloc(nx * ny * SWFS_REGRESS_NSTATE * sizeof *state) : NULL;
    if (!state) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for REGSTATE", path);
    if (!rc) rc = count_key(f, path, "FRAMES", &r->frames);
    if (!rc) rc = count_key(f, path, "SKIPPED", &r->skipped);
    if (!rc) rc = swfs_fits_in_read_real(f, 0, SWFS_REGRESS_NSTATE, state);
    if (!rc && (rc = swfs_regress_import(r, state)))
        swfs_fail_context(rc, "%s: REGSTATE (a damaged file, or lossy compression of its floating-point data?)", path);
    free(state);
    if (rc) { swfs_regress_free(r); return rc; }
    *out = r;
    return SWFS_OK;
}

/* A count key: a non-negative integer. */
static int count_key(swfs_fits_in *f, const char *path, const char *key, uint64_t *out)
{
    double v;
    int rc = swfs_fits_in_key_double(f, key, &v);
    if (rc) return swfs_fail_context(rc, "%s: not a specklewfs checkpoint", path);
    if (!(v >= 0) || v != floor(v) || v > 9.0e15)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %g is not a frame count", path, key, v);
    *out = (uint64_t)v;
    return SWFS_OK;
}

int swfs_accum_load(const char *path, swfs_accum **out, swfs_geom *g)
{
    *out = NULL;
    swfs_fits_in *f = NULL;
    swfs_accum *a = NULL;
    int rc = swfs_fits_in_open(&f, path, "ACCUM");
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(f);
    double ver;
    char names[128];
    int found = 0;
    if ((rc = swfs_fits_in_require_float(f, "an accumulator checkpoint"))) goto done;
    if (sh->is_complex || sh->nz != SWFS_ACC_NFIELDS) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: ACCUM is %zux%zux%zu%s; a checkpoint holds a real cube of %d planes", path,
                       sh->nx, sh->ny, sh->nz, sh->is_complex ? " complex" : "", SWFS_ACC_NFIELDS);
        goto done;
    }
    if ((rc = swfs_fits_in_key_double(f, "ACCVER", &ver))) {
        swfs_fail_context(rc, "%s: not a specklewfs checkpoint", path);
        goto done;
    }
    if (ver != 1 && ver != SWFS_CHECKPOINT_VERSION) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: checkpoint layout version %g, this program reads versions 1 to %d", path, ver,
                       SWFS_CHECKPOINT_VERSION);
        goto done;
    }
    if ((rc = swfs_fits_in_key_string_opt(f, "ACCFLDS", names, sizeof names, &found))) goto done;
    if (found && strcmp(names, field_names)) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: ACCFLDS = '%s', expected '%s'", path, names, field_names);
        goto done;
    }
    if (!(a = swfs_accum_create(sh->nx, sh->ny))) { rc = SWFS_ERR_NOMEM; goto done; }
    if ((rc = count_key(f, path, "FRAMES", &a->frames)) || (rc = count_key(f, path, "SKIPPED", &a->skipped))) goto done;
    for (int k = 0; k < SWFS_ACC_NFIELDS && !rc; k++) rc = swfs_fits_in_read_real(f, (size_t)k, 1, a->f[k]);
    if (rc) goto done;
    /* The state must be one an accumulator can be in. */
    const size_t np = a->nx * a->ny;
    static const int diag[4] = {SWFS_ACC_CII, SWFS_ACC_CXX, SWFS_ACC_CYY, SWFS_ACC_CAA};
    for (size_t p = 0; p < np && !rc; p++) {
        const double n = a->f[SWFS_ACC_N][p];
        if (!(n >= 0) || n != floor(n) || n > (double)a->frames)
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: pixel (%zu, %zu) has count %g with FRAMES = %llu", path, p % a->nx,
                           p / a->nx, n, (unsigned long long)a->frames);
        for (int k = 1; k < SWFS_ACC_NFIELDS && !rc; k++)
            if (!isfinite(a->f[k][p]))
                rc = swfs_fail(SWFS_ERR_FORMAT, "%s: plane %d of pixel (%zu, %zu) is not finite", path, k, p % a->nx,
                               p / a->nx);
        for (int k = 0; k < 4 && !rc; k++)
            if (a->f[diag[k]][p] < 0)
                rc = swfs_fail(SWFS_ERR_FORMAT, "%s: negative variance in plane %d at pixel (%zu, %zu)", path, diag[k],
                               p % a->nx, p / a->nx);
    }
    if (!rc && g) rc = swfs_fits_in_geom(f, g);
    if (!rc && ver >= 2) {
        swfs_regress *r = NULL;
        if (!(rc = swfs_regress_read_ext(f, path, a->nx, a->ny, &r))) {
            swfs_regress_free(a->reg);
            a->reg = r;
        }
    }
done:
    swfs_fits_in_close(f);
    if (rc) {
        swfs_accum_free(a);
        return rc;
    }
    *out = a;
    return SWFS_OK;
}

int swfs_accum_merge_files(const char *const *paths, size_t n, swfs_accum **out, swfs_geom *g)
{
    *out = NULL;
    if (!n) return swfs_fail(SWFS_ERR_ARG, "merge: no checkpoint files");
    swfs_accum *acc = NULL, *part = NULL;
    swfs_geom gacc, gpart;
    int rc = swfs_accum_load(paths[0], &acc, &gacc);
    for (size_t i = 1; i < n && !rc; i++) {
        rc = swfs_accum_load(paths[i], &part, &gpart);
        if (rc) break;
        if (part->nx != acc->nx || part->ny != acc->ny)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: accumulators are %zux%zu pixels but %s has %zux%zu", paths[i], part->nx,
                           part->ny, paths[0], acc->nx, acc->ny);
        if (!rc) rc = swfs_geom_check_same(&gacc, paths[0], &gpart, paths[i]);
        if (!rc) rc = swfs_accum_merge(acc, part);
        swfs_geom_union(&gacc, &gpart);
        swfs_accum_free(part);
        part = NULL;
    }
    if (rc) {
        swfs_accum_free(acc);
        return rc;
    }
    if (g) *g = gacc;
    *out = acc;
    return SWFS_OK;
}

/* HALO.fits writer and reader (layout in include/specklewfs/estimate.h, docs/conventions.md). */
#include "specklewfs/estimate.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stddef.h>
#include <stdlib.h>

struct real_ext { const char *name; size_t off; };

#define REAL_EXT(field, name) {name, offsetof(swfs_halo, field)}
static const struct real_ext real_exts[] = {
    REAL_EXT(gain, "GAIN"), REAL_EXT(visib, "VISIB"), REAL_EXT(snr, "SNR"),
    REAL_EXT(mean_i, "MEAN_I"), REAL_EXT(var_i, "VAR_I"), REAL_EXT(mean_sp, "MEAN_SP"),
    REAL_EXT(var_sp, "VAR_SP"), REAL_EXT(stab_err, "STAB_ERR"), REAL_EXT(circ, "CIRC"),
    REAL_EXT(valid, "VALID"), REAL_EXT(nframes, "NFRAMES"), REAL_EXT(gain_pix, "GAIN_PIX"),
};
#define NREAL (sizeof real_exts / sizeof real_exts[0])

static swfs_real **real_slot(swfs_halo *h, size_t k) { return (swfs_real **)((char *)h + real_exts[k].off); }

int swfs_halo_write(const swfs_halo *h, const char *path, const swfs_geom *g, const char *const *prov, size_t nprov)
{
    swfs_fits_out *o;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    swfs_geom none;
    swfs_geom_init(&none);
    rc = swfs_fits_out_set_stamp(o, g ? g : &none, prov, nprov);
    /* Primary HDU: the summary, geometry and provenance; the stamp repeats geometry and
     * provenance on every extension. */
    if (!rc) rc = swfs_fits_out_key_long(o, "NFRAMES", (long)h->frames, "frames accumulated");
    if (!rc) rc = swfs_fits_out_geom(o, g ? g : &none);
    if (!rc) rc = swfs_fits_out_provenance(o, prov, nprov);
    if (!rc) rc = swfs_fits_out_key_long(o, "SKIPPED", (long)h->skipped, "pixel-frames skipped (non-finite science)");
    if (!rc) rc = swfs_fits_out_key_long(o, "NPIX", (long)h->npix, "pixels");
    if (!rc) rc = swfs_fits_out_key_long(o, "NVALID", (long)h->n_valid, "pixels where g is defined");
    if (!rc) rc = swfs_fits_out_key_double(o, "VALIDFR", h->valid_fraction, "fraction of pixels where g is defined");
    if (!rc) rc = swfs_fits_out_key_long(o, "NBADRAD", (long)h->n_bad_radicand, "pixels with radicand of g <= 0");
    if (!rc) rc = swfs_fits_out_key_long(o, "NNOSP", (long)h->n_no_speckle, "pixels without speckle power");
    if (!rc) rc = swfs_fits_out_key_long(o, "NNOFRM", (long)h->n_no_frames, "pixels with < 2 usable frames");
    if (!rc) rc = swfs_fits_out_key_long(o, "NVARLOW", (long)h->n_var_below_noise, "pixels with variance < noise model");
    if (!rc) rc = swfs_fits_out_key_double(o, "MEDSNR", h->median_snr, "median eq:SNR over valid pixels");
    if (!rc) rc = swfs_fits_out_key_double(o, "RDNOISE", h->noise.read_noise, "[counts] read noise removed");
    if (!rc) rc = swfs_fits_out_key_double(o, "GAIN", h->noise.gain, "[e-/count] 0 = no photon-noise term");
    if (!rc) rc = swfs_fits_out_key_double(o, "GSMOOTH", h->g_smooth, "[pixels] g regularization (0 = paper)");
    if (!rc) rc = swfs_fits_out_key_long(o, "NGFALLBK", (long)h->n_g_fallback, "pixels with local-median fallback g");
    if (!rc && h->tiptilt[0]) rc = swfs_fits_out_key_string(o, "TIPTILT", h->tiptilt, "the speckles' tip-tilt treatment");
    if (!rc) rc = swfs_fits_out_cplx(o, "HALO", h->halo, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "EQUATION", "eq:TheAnswer", "Psi = <psi I>/(g Phi_sp)");
    if (!rc) rc = swfs_fits_out_cplx(o, "HALO_LF", h->halo_lf, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "EQUATION", "eq:PSI-LowFreq", NULL);
    if (!rc) rc = swfs_fits_out_cplx(o, "STAB", h->stab, -64);
    if (!rc) rc = swfs_fits_out_key_string(o, "EQUATION", "eq:betterStabilized", "<psi' I>, psi' = psi - <psi>");
    for (size_t k = 0; k < NREAL && !rc; k++) {
        const swfs_real *a = *real_slot((swfs_halo *)h, k);
        if (a) rc = swfs_fits_out_real(o, real_exts[k].name, a, -64);
    }
    if (!rc && h->reg) rc = swfs_regress_write_ext(o, h->reg);
    if (!rc && h->resmean) rc = swfs_fits_out_real(o, "RESMEAN", h->resmean, -64);
    if (!rc && h->resmean) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "AO residual's time mean (telemetry)");
    if (rc) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

int swfs_resmean_read_ext(swfs_fits_in *f, const char *path, swfs_real **out)
{
    *out = NULL;
    int rc = swfs_fits_in_move(f, "RESMEAN");
    if (!rc) rc = swfs_fits_in_require_float(f, "the AO residual's time mean (RESMEAN)");
    if (!rc) rc = swfs_fits_in_read_real_all(f, out);
    if (!rc && ((*out)->nx != (*out)->ny || (*out)->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: extension RESMEAN is %zux%zux%zu; expected one PUPN x PUPN map [m]", path,
                       (*out)->nx, (*out)->ny, (*out)->nz);
    char val[48];
    for (size_t k = 0; !rc && k < (*out)->nx * (*out)->ny; k++)
        if (!isfinite((*out)->data[k]))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: RESMEAN sample %zu %s; expected a finite wavefront [m]", path, k,
                           swfs_value_words((*out)->data[k], val, sizeof val));
    if (rc) {
        swfs_real_free(*out);
        *out = NULL;
    }
    return rc;
}

int swfs_halo_read(const char *path, swfs_halo **out, swfs_geom *g)
{
    *out = NULL;
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, path, "HALO");
    if (rc) return rc;
    swfs_halo *h = calloc(1, sizeof *h);
    if (!h) { swfs_fits_in_close(f); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    rc = swfs_fits_in_read_cplx_all(f, &h->halo);
    if (!rc && g) rc = swfs_fits_in_geom(f, g);
    if (!rc) { h->nx = h->halo->nx; h->ny = h->halo->ny; h->npix = h->nx * h->ny; }
    if (!rc) rc = swfs_fits_in_move(f, "HALO_LF");
    if (!rc) rc = swfs_fits_in_read_cplx_all(f, &h->halo_lf);
    if (!rc && swfs_fits_in_has_ext(f, "STAB")) {
        rc = swfs_fits_in_move(f, "STAB");
        if (!rc) rc = swfs_fits_in_read_cplx_all(f, &h->stab);
    }
    for (size_t k = 0; k < NREAL && !rc; k++) {
        if (!swfs_fits_in_has_ext(f, real_exts[k].name)) continue;
        rc = swfs_fits_in_move(f, real_exts[k].name);
        if (!rc) rc = swfs_fits_in_require_float(f, "a HALO.fits product");
        if (!rc) rc = swfs_fits_in_read_real_all(f, real_slot(h, k));
        if (!rc) {
            const swfs_real *a = *real_slot(h, k);
            if (a->nx != h->nx || a->ny != h->ny)
                rc = swfs_fail(SWFS_ERR_SHAPE, "%s: extension %s is %zux%zu but HALO is %zux%zu", path,
                               real_exts[k].name, a->nx, a->ny, h->nx, h->ny);
        }
    }
    if (!rc && (h->halo_lf->nx != h->nx || h->halo_lf->ny != h->ny))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: HALO_LF is %zux%zu but HALO is %zux%zu", path, h->halo_lf->nx,
                       h->halo_lf->ny, h->nx, h->ny);
    if (!rc) {
        double v;
        int found;
        if (!swfs_fits_in_key_double_opt(f, "NFRAMES", &v, &found) && found) h->frames = (unsigned long long)v;
        if (!swfs_fits_in_key_double_opt(f, "VALIDFR", &v, &found) && found) h->valid_fraction = v;
        if (!swfs_fits_in_key_double_opt(f, "MEDSNR", &v, &found) && found) h->median_snr = v;
        rc = swfs_fits_in_key_string_opt(f, "TIPTILT", h->tiptilt, sizeof h->tiptilt, &found);
    }
    if (!rc && swfs_fits_in_has_ext(f, "REGSTATE")) rc = swfs_regress_read_ext(f, path, h->nx, h->ny, &h->reg);
    if (!rc && swfs_fits_in_has_ext(f, "RESMEAN")) rc = swfs_resmean_read_ext(f, path, &h->resmean);
    swfs_fits_in_close(f);
    if (rc) { swfs_halo_free(h); return rc; }
    *out = h;
    return SWFS_OK;
}

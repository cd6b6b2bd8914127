/* dmoffsets: the NCP wavefront of a pupil product -> deformable-mirror offsets (run.h
 * swfs_dmoffsets_run over dmfit.h): the correction surface -WFE/2 (a reflective DM changes
 * the wavefront by twice its surface) fitted onto the actuators' influence functions, and
 * OFFSETS.fits written (swfs_dmfit_write). */
#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_dmoffsets_run_options_default(swfs_dmoffsets_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_dmfit_options_default(&o->fit);
}

/* The WFE and the pupil mask (NULL where the product has none: the annulus of OBSCUR) of a
 * pupil product, with its geometry, checked: a pupil WFE is finite and within 10 waves. */
static int read_pupil(const char *in, swfs_real **wfe, swfs_real **mask, swfs_geom *g)
{
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, in, NULL);
    if (!rc && !swfs_fits_in_has_ext(f, "WFE"))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no WFE extension (expected a pupil product written by 'specklewfs pupil')", in);
    if (!rc) rc = swfs_fits_in_move(f, "WFE");
    if (!rc) rc = swfs_fits_in_require_float(f, "a pupil product");
    if (!rc) rc = swfs_fits_in_read_real_all(f, wfe);
    if (!rc) rc = swfs_fits_in_geom(f, g);
    if (!rc && (!(g->pupn > 0) || !(g->pupdx > 0) || !(g->teldiam > 0) || !isfinite(g->wavelen)))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the WFE extension lacks the pupil geometry (PUPN, PUPDX, TELDIAM, WAVELEN)",
                       in);
    if (!rc && ((*wfe)->nx != (size_t)g->pupn || (*wfe)->ny != (size_t)g->pupn || (*wfe)->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: WFE is %zux%zux%zu but PUPN = %ld (expected a %ldx%ld image)", in, (*wfe)->nx,
                       (*wfe)->ny, (*wfe)->nz, g->pupn, g->pupn, g->pupn);
    if (!rc && swfs_fits_in_has_ext(f, "PUPIL")) {
        rc = swfs_fits_in_move(f, "PUPIL");
        if (!rc) rc = swfs_fits_in_read_real_all(f, mask);
        if (!rc && ((*mask)->nx != (*wfe)->nx || (*mask)->ny != (*wfe)->ny || (*mask)->nz != 1))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: PUPIL is %zux%zu but WFE is %zux%zu", in, (*mask)->nx, (*mask)->ny,
                           (*wfe)->nx, (*wfe)->ny);
    } else if (!rc && !isfinite(g->obscur)) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no PUPIL extension and no OBSCUR keyword to build the pupil", in);
    }
    swfs_fits_in_close(f);
    const double *m = !rc && *mask ? (*mask)->data : NULL;
    char val[48];
    for (size_t s = 0; !rc && s < (*wfe)->nx * (*wfe)->ny; s++)
        if ((!m || m[s] > 0) && (!isfinite((*wfe)->data[s]) || fabs((*wfe)->data[s]) > 10 * g->wavelen))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: WFE [m] at pupil sample (%zu, %zu) %s; a pupil WFE is finite and within "
                           "10 wavelengths (%g m)", in, s % (*wfe)->nx, s / (*wfe)->nx,
                           swfs_value_words((*wfe)->data[s], val, sizeof val), 10 * g->wavelen);
    return rc;
}

int swfs_dmoffsets_run(const swfs_dmoffsets_run_options *o, swfs_dmoffsets_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->pupil || !o->out) return swfs_fail(SWFS_ERR_ARG, "dmoffsets: needs a pupil product and an output");
    if (!o->actuators == !(o->hexapolar > 0))
        return swfs_fail(SWFS_ERR_ARG, "dmoffsets: give the actuators' file or a hexapolar pitch > 0 [m], one of them");
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    if (!rc) rc = swfs_paths_input(paths, "pupil product", o->pupil);
    if (!rc) rc = swfs_paths_input(paths, "--actuators", o->actuators);
    if (!rc) rc = swfs_paths_output(paths, "-o", o->out);
    if (!rc) rc = swfs_paths_status(paths);
    swfs_paths_free(paths);
    if (rc) return rc;
    swfs_real *wfe = NULL, *mask = NULL;
    double *xy = NULL, *target = NULL, *cmd = NULL;
    swfs_dmfit *fit = NULL;
    swfs_geom g;
    rc = read_pupil(o->pupil, &wfe, &mask, &g);
    if (!rc) rc = o->actuators ? swfs_actuators_read(o->actuators, &xy, &r->nact)
                               : swfs_actuators_hexapolar(g.teldiam, o->hexapolar, g.pupdx, &xy, &r->nact);
    if (!rc && (rc = swfs_dmfit_create(&fit, xy, r->nact, &g, mask ? mask->data : NULL, &o->fit)))
        swfs_fail_context(rc, "%s", o->actuators ? o->actuators : "hexapolar actuators");
    const size_t n2 = (size_t)g.pupn * (size_t)g.pupn;
    if (!rc && (!(target = malloc(n2 * sizeof *target)) || !(cmd = malloc(r->nact * sizeof *cmd))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "dmoffsets: out of memory");
    /* The correction: -WFE/2 of surface (reflective: z = phi lambda / 4 pi). */
    for (size_t s = 0; !rc && s < n2; s++) target[s] = -0.5 * wfe->data[s];
    if (!rc && (rc = swfs_dmfit_apply(fit, target, cmd, NULL, &r->stats))) swfs_fail_context(rc, "%s", o->pupil);
    char src[1200];
    snprintf(src, sizeof src, "dmoffsets: correction -WFE/2 of %s", o->pupil);
    const char *prov[16];
    size_t np = 0;
    for (size_t k = 0; k < o->nprov && np < 15; k++) prov[np++] = o->prov[k];
    prov[np++] = src;
    if (!rc) rc = swfs_dmfit_write(fit, cmd, target, &r->stats, o->out, &g, prov, np);
    if (!rc) {
        r->active = swfs_dmfit_active(fit);
        r->pitch = swfs_dmfit_pitch(fit);
    }
    swfs_real_free(wfe);
    swfs_real_free(mask);
    swfs_dmfit_free(fit);
    free(xy);
    free(target);
    free(cmd);
    return rc;
}

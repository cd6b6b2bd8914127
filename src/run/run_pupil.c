/* pupil: HALO.fits (or several, the self-check choosing) -> PUPIL.fits (run.h swfs_pupil_run;
 * the command line's `specklewfs pupil` and Python's pupil_files). */
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_pupil_run_options_default(swfs_pupil_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_pupil_options_default(&o->pupil);
}

void swfs_pupil_run_result_free(swfs_pupil_run_result *r)
{
    if (!r) return;
    swfs_pupil_result_free(r->pupil);
    swfs_halo_free(r->halo);
    free(r->explained);
    memset(r, 0, sizeof *r);
}

/* The truth file's NCP on the halo's pupil grid, compared with the estimate. */
static int compare_truth(const char *path, const swfs_pupil_result *p, const swfs_geom *g, const char *halo,
                         swfs_pupil_run_result *r)
{
    swfs_real *t = NULL;
    int rc = swfs_fits_read_real(path, "NCP", &t, NULL);
    if (!rc && (t->nx != (size_t)g->pupn || t->ny != (size_t)g->pupn || t->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: NCP is %zux%zux%zu but %s says PUPN = %ld", path, t->nx, t->ny, t->nz, halo,
                       g->pupn);
    if (!rc) rc = swfs_wfe_compare(p->wfe->data, t->data, p->mask->data, (size_t)g->pupn, &r->err, &r->truth_rms,
                                   &r->truth_rms_ptt);
    /* the residual's mean put back: what --keep-resmean's run of the same fit compares */
    if (!rc) rc = swfs_pupil_compare_kept(p, t->data, &r->err_kept);
    swfs_real_free(t);
    return rc;
}

int swfs_pupil_run(const swfs_pupil_run_options *o, swfs_pupil_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->err = r->truth_rms = r->truth_rms_ptt = r->err_kept = NAN;
    if (!o->halos || !o->nhalo || !o->out) return swfs_fail(SWFS_ERR_ARG, "pupil: needs a halo file and an output");
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    for (size_t k = 0; k < o->nhalo; k++) swfs_paths_input(paths, "halo", o->halos[k]);
    swfs_paths_input(paths, "pupil mask", o->mask);
    swfs_paths_input(paths, "truth", o->truth);
    if (!rc) rc = swfs_paths_output(paths, "output pupil", o->out);
    swfs_paths_free(paths);
    if (rc) return rc;
    char chosen[1400] = "", tl[1400] = "";
    if (o->nhalo > 1) {
        if (!(r->explained = calloc(o->nhalo, sizeof *r->explained))) return swfs_fail(SWFS_ERR_NOMEM, "pupil: out of memory");
        rc = swfs_halo_choose_files(o->halos, o->nhalo, r->explained, &r->chosen, &r->ncommon, &r->halo, &r->geom);
        if (!rc)
            snprintf(chosen, sizeof chosen, "chosen by the self-check among %zu halos: %.1000s (%.2f %% explained)",
                     o->nhalo, o->halos[r->chosen], 100 * r->explained[r->chosen]);
    } else {
        rc = swfs_halo_read(o->halos[0], &r->halo, &r->geom);
    }
    const char *in = o->halos[r->chosen];
    if (!rc) rc = swfs_geom_require(&r->geom, in);
    swfs_real *mask = NULL;
    if (!rc && o->mask) rc = swfs_pupil_mask_read(o->mask, (size_t)r->geom.pupn, &mask);
    if (!rc && (rc = swfs_pupil_estimate(r->halo, &r->geom, mask, &o->pupil, &r->pupil))) swfs_fail_context(rc, "%s", in);
    swfs_real_free(mask);
    if (!rc && o->truth) {
        rc = compare_truth(o->truth, r->pupil, &r->geom, in, r);
        if (!rc)
            snprintf(tl, sizeof tl, "compared with %.1000s: NCP error %.4g m rms (piston, tip, tilt removed)", o->truth,
                     r->err);
    }
    const char **prov = NULL;
    if (!rc) {
        const size_t np = o->nprov + (chosen[0] ? 1 : 0) + (tl[0] ? 1 : 0);
        prov = calloc(np ? np : 1, sizeof *prov);
        if (!prov) rc = swfs_fail(SWFS_ERR_NOMEM, "pupil: out of memory");
        size_t k = 0;
        for (size_t i = 0; prov && i < o->nprov; i++) prov[k++] = o->prov[i];
        if (prov && chosen[0]) prov[k++] = chosen;
        if (prov && tl[0]) prov[k++] = tl;
        if (!rc) rc = swfs_pupil_write(r->pupil, o->out, &r->geom, prov, k);
    }
    if (!rc) r->ran_away = r->pupil->wfe_rms > 0.5 * r->geom.wavelen;
    free(prov);
    if (rc) {
        swfs_pupil_run_result_free(r);
        r->err = r->truth_rms = r->truth_rms_ptt = r->err_kept = NAN;
    }
    return rc;
}

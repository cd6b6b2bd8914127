/* One noise level of the Sec. 3 experiment end to end: see include/specklewfs/recovery.h. */
#include "specklewfs/recovery.h"
#include "specklewfs/accum.h"
#include "specklewfs/estimate.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <string.h>

int swfs_recovery_run(const swfs_sim_result *sim, double sigma, uint64_t seed, const char *dir,
                      const char *const *prov, size_t nprov, swfs_recovery *out)
{
    memset(out, 0, sizeof *out);
    out->sigma = sigma;
    const swfs_sim_params *p = &sim->params;
    swfs_real *noisy = swfs_real_copy(sim->science);
    swfs_accum *acc = noisy ? swfs_accum_create(noisy->nx, noisy->ny) : NULL;
    swfs_halo *h = NULL, *hp = NULL;
    swfs_pupil_result *pr[5] = {NULL, NULL, NULL, NULL, NULL};
    char path[4096];
    int rc = SWFS_OK;
    if (!noisy || !acc) { rc = SWFS_ERR_NOMEM; goto done; }
    if ((rc = swfs_sim_camera(sim->science, sigma, p->gain, seed, noisy))) goto done;
    if (dir && (rc = swfs_sim_write(sim, noisy, sigma, p->gain, dir, prov, nprov))) goto done;

    const size_t np = noisy->nx * noisy->ny;
    for (size_t k = 0; k < noisy->nz; k++)
        if ((rc = swfs_accum_add(acc, noisy->data + k * np, sim->speckles->data + k * np))) goto done;
    const swfs_noise nz = {sigma, p->gain > 0 ? p->gain : 0.0};
    if ((rc = swfs_estimate(acc, &nz, NULL, &h))) goto done;
    const swfs_estimate_options paper = {0.0};
    if ((rc = swfs_estimate(acc, &nz, &paper, &hp))) goto done;
    if (dir) {
        if (snprintf(path, sizeof path, "%s/halo.fits", dir) >= (int)sizeof path) {
            rc = swfs_fail(SWFS_ERR_ARG, "%s: folder name too long", dir);
            goto done;
        }
        if ((rc = swfs_halo_write(h, path, &sim->geom, prov, nprov))) goto done;
    }
    /* The moments at full weight (HALO, HALO_LF), the SNR-weighted HALO_LF (the default before
     * the joint fit), the paper's estimator end to end (per-pixel g, HALO_LF, full weight) and
     * the joint fit that `specklewfs pupil` uses by default. */
    swfs_pupil_options o[5];
    for (int k = 0; k < 5; k++) {
        swfs_pupil_options_default(&o[k]);
        o[k].method = SWFS_PUPIL_MOMENTS;
    }
    o[0].source = SWFS_SOURCE_HALO; o[0].weight = SWFS_WEIGHT_NONE;
    o[1].source = SWFS_SOURCE_HALO_LF; o[1].weight = SWFS_WEIGHT_NONE;
    o[2].source = SWFS_SOURCE_HALO_LF; o[2].weight = SWFS_WEIGHT_SNR;
    o[3] = o[1];
    o[4].method = SWFS_PUPIL_FIT;
    double err[5];
    for (int k = 0; k < 5; k++) {
        swfs_pupil_result **slot = &pr[k];
        if ((rc = swfs_pupil_estimate(k == 3 ? hp : h, &sim->geom, sim->pupil, &o[k], slot))) goto done;
        if ((rc = swfs_wfe_compare((*slot)->wfe->data, sim->ncp->data, sim->pupil->data, (size_t)sim->geom.pupn, &err[k],
                                   NULL, NULL))) goto done;
    }
    if (dir) {
        snprintf(path, sizeof path, "%s/wavefront.fits", dir);
        if ((rc = swfs_pupil_write(pr[4], path, &sim->geom, prov, nprov))) goto done;
    }
    out->valid_fraction = h->valid_fraction;
    out->bad_radicand = (double)h->n_bad_radicand / (double)h->npix;
    out->median_snr = h->median_snr;
    out->err_paper = err[3];
    out->err_halo = err[0];
    out->err_lf = err[1];
    out->err_lf_snr = err[2];
    out->err_fit = err[4];
    out->wfe_rms = pr[4]->wfe_rms;
    out->wfe_pv = pr[4]->wfe_pv;
    out->strehl = pr[4]->strehl;
    out->fit_kappa = pr[4]->fit->kappa;
done:
    for (int k = 0; k < 5; k++) swfs_pupil_result_free(pr[k]);
    swfs_halo_free(h);
    swfs_halo_free(hp);
    swfs_accum_free(acc);
    swfs_real_free(noisy);
    return rc;
}

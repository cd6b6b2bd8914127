/* Closed-loop NCP correction in simulation: measure (Sec. 3 simulation + estimator +
 * pupil step), fit DM offsets, apply with a gain, measure again. See
 * include/specklewfs/closed_loop.h and docs/closed-loop.md. */
#include "specklewfs/parallel.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/accum.h"
#include "specklewfs/aperture.h"
#include "specklewfs/estimate.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

void swfs_loop_params_default(swfs_loop_params *lp)
{
    memset(lp, 0, sizeof *lp);
    lp->iterations = 5;
    lp->gain = 0.8;
    lp->sigma = 100.0;
    lp->act_pitch = 0.35;
    swfs_dmfit_options_default(&lp->fit);
    swfs_pupil_options_default(&lp->pupil);
    lp->annulus_in = 2.0;
    lp->annulus_out = 6.0;
}

void swfs_loop_result_free(swfs_loop_result *r)
{
    if (!r) return;
    free(r->rows);
    swfs_real_free(r->residual);
    swfs_real_free(r->estimate);
    swfs_real_free(r->dm_surface);
    swfs_real_free(r->commands);
    swfs_real_free(r->actuators);
    swfs_real_free(r->pupil);
    free(r);
}

double swfs_halo_contrast(const swfs_cplx *h, double pixscale, double rin, double rout)
{
    const size_t nx = h->nx, ny = h->ny;
    double peak = 0.0, s = 0.0;
    size_t n = 0;
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            const double complex v = h->data[j * nx + i];
            const double a = creal(v) * creal(v) + cimag(v) * cimag(v);
            if (a > peak) peak = a;
            const double r = hypot((double)i - (double)(nx / 2), (double)j - (double)(ny / 2)) * pixscale;
            if (r >= rin && r <= rout) {
                s += a;
                n++;
            }
        }
    return n && peak > 0 ? s / (double)n / peak : NAN;
}

/* Long-exposure Strehl: peak of the mean noise-free science image over the unaberrated
 * peak with the same counts. With the star on pixel (nfx/2, nfy/2), theta = 0 there and
 * the MFT of the bare pupil is exactly sum P = field_scale, so that peak is C S^2 (sim.h). */
static double sim_strehl(const swfs_sim_result *s)
{
    const size_t nf = s->science->nx * s->science->ny, nt = s->science->nz;
    double best = 0.0;
    for (size_t k = 0; k < nf; k++) {
        double m = 0.0;
        for (size_t t = 0; t < nt; t++) m += s->science->data[t * nf + k];
        if (m > best) best = m;
    }
    return best / (double)nt / (s->counts_scale * s->field_scale * s->field_scale);
}

/* Contrast of the no-NCP static halo (speckle_mean is E e^{-i p_t} / S averaged, so the
 * halo in sqrt(counts) is sqrt(C) S speckle_mean), and of the NCP's own static speckles
 * halo_true - that halo, both relative to the peak of |halo_true|^2. */
static double abs2(double complex z) { return creal(z) * creal(z) + cimag(z) * cimag(z); }

static void ao_contrast(const swfs_sim_result *s, const swfs_loop_params *lp, swfs_cplx *work, double *c_ao,
                        double *c_ncp)
{
    const size_t nf = work->nx * work->ny;
    const double sc = sqrt(s->counts_scale) * s->field_scale;
    for (size_t k = 0; k < nf; k++) work->data[k] = sc * s->speckle_mean->data[k];
    *c_ao = swfs_halo_contrast(work, s->params.pixscale, lp->annulus_in, lp->annulus_out);
    double peak = 0.0, dpeak = 0.0;
    for (size_t k = 0; k < nf; k++) {
        const double complex h = s->halo_true->data[k];
        work->data[k] = h - work->data[k];
        peak = fmax(peak, abs2(h));
        dpeak = fmax(dpeak, abs2(work->data[k]));
    }
    /* swfs_halo_contrast divides by the difference's own peak: rescale to max |halo_true|^2. */
    *c_ncp = dpeak > 0 && peak > 0
                 ? swfs_halo_contrast(work, s->params.pixscale, lp->annulus_in, lp->annulus_out) * dpeak / peak
                 : 0.0;
}

/* Piston-removed rms over the mask (np x np), and with tip/tilt also removed. */
static double masked_rms(const double *w, const double *mask, size_t np, double *ptt, double *scratch)
{
    const size_t n2 = np * np;
    double s = 0.0, s1 = 0.0, s2 = 0.0;
    for (size_t k = 0; k < n2; k++) {
        s += mask[k];
        s1 += mask[k] * w[k];
        s2 += mask[k] * w[k] * w[k];
    }
    const double m = s1 / s, var = s2 / s - m * m;
    memcpy(scratch, w, n2 * sizeof *w);
    *ptt = swfs_wfe_remove_ptt(scratch, mask, np);
    return var > 0 ? sqrt(var) : 0.0;
}

/* Estimate the pupil WFE from one simulated data set with camera noise. */
static int measure(const swfs_sim_result *sim, const swfs_loop_params *lp, uint64_t seed, swfs_real *noisy,
                   swfs_accum *acc, const swfs_real *mask, swfs_pupil_result **pr, double *median_snr)
{
    const swfs_sim_params *p = &sim->params;
    int rc = swfs_sim_camera(sim->science, lp->sigma, p->gain, seed, noisy);
    if (rc) return rc;
    swfs_accum_reset(acc);
    const size_t nf = noisy->nx * noisy->ny;
    for (size_t t = 0; t < noisy->nz; t++)
        if ((rc = swfs_accum_add(acc, noisy->data + t * nf, sim->speckles->data + t * nf))) return rc;
    const swfs_noise nz = {lp->sigma, p->gain > 0 ? p->gain : 0.0};
    swfs_halo *h = NULL;
    if ((rc = swfs_estimate(acc, &nz, NULL, &h))) return rc;
    *median_snr = h->median_snr;
    rc = swfs_pupil_estimate(h, &sim->geom, mask, &lp->pupil, pr);
    swfs_halo_free(h);
    return rc;
}

static int check_loop_params(const swfs_loop_params *lp)
{
    if (!(lp->gain > 0 && lp->gain <= 2))
        return swfs_fail(SWFS_ERR_ARG, "closed loop: gain must be in (0, 2], got %g", lp->gain);
    if (!(lp->sigma >= 0)) return swfs_fail(SWFS_ERR_ARG, "closed loop: noise sigma must be >= 0, got %g", lp->sigma);
    if (!lp->act_xy && !(lp->act_pitch > 0))
        return swfs_fail(SWFS_ERR_ARG, "closed loop: actuator pitch must be > 0, got %g m", lp->act_pitch);
    if (!(lp->annulus_in >= 0 && lp->annulus_out > lp->annulus_in))
        return swfs_fail(SWFS_ERR_ARG, "closed loop: contrast annulus %g..%g lambda/D is empty", lp->annulus_in,
                         lp->annulus_out);
    if (lp->iterations > 1000) return swfs_fail(SWFS_ERR_ARG, "closed loop: %zu iterations (at most 1000)", lp->iterations);
    return SWFS_OK;
}

int swfs_closed_loop_run(const swfs_sim_params *p, const swfs_loop_params *lp, const swfs_sim_result *first,
                         swfs_progress_fn progress, void *ctx, swfs_loop_result **out)
{
    const double t0 = swfs_wall_seconds();
    *out = NULL;
    int rc = swfs_sim_params_check(p);
    if (rc) return rc;
    if ((rc = check_loop_params(lp))) return rc;
    const size_t np = (size_t)p->pupn, n2 = np * np, K = lp->iterations, nrows = K + 1;
    const size_t nfx = (size_t)p->nfx, nfy = (size_t)p->nfy;

    swfs_loop_result *r = calloc(1, sizeof *r);
    if (!r) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    r->params = *lp;
    r->params.act_xy = NULL; /* the positions are kept in r->actuators */
    r->params.act_name = NULL;
    r->sim = *p;
    r->nrows = nrows;
    swfs_geom_init(&r->geom);
    r->geom.wavelen = p->wavelen;
    r->geom.teldiam = p->teldiam;
    r->geom.obscur = p->obscur;
    r->geom.pixscale = p->pixscale;
    r->geom.pupdx = p->pupdx;
    r->geom.pupn = p->pupn;

    double *xy = NULL, *ncp0 = NULL, *target = NULL, *cmd = NULL, *scratch = NULL;
    size_t nact = 0;
    swfs_dmfit *fit = NULL;
    swfs_sim_result *sim = NULL;
    swfs_real *noisy = NULL;
    swfs_accum *acc = NULL;
    swfs_cplx *hwork = NULL;
    swfs_pupil_result *pr = NULL;

    r->rows = calloc(nrows, sizeof *r->rows);
    r->pupil = swfs_real_alloc(np, np, 1);
    r->residual = swfs_real_alloc(np, np, nrows);
    r->estimate = swfs_real_alloc(np, np, K ? K : 1);
    r->dm_surface = swfs_real_alloc(np, np, nrows);
    ncp0 = malloc(n2 * sizeof *ncp0);
    target = malloc(n2 * sizeof *target);
    scratch = malloc(n2 * sizeof *scratch);
    noisy = swfs_real_alloc(nfx, nfy, 1); /* resized below once the frame count is known */
    acc = swfs_accum_create(nfx, nfy);
    hwork = swfs_cplx_alloc(nfx, nfy, 1);
    if (!r->rows || !r->pupil || !r->residual || !r->estimate || !r->dm_surface || !ncp0 || !target || !scratch ||
        !noisy || !acc || !hwork) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "closed loop: out of memory");
        goto done;
    }

    /* The pupil and the initial NCP exactly as the simulator makes them. */
    if ((rc = swfs_sim_pupil(p, r->pupil->data))) goto done;
    if ((rc = swfs_sim_ncp_map(p, r->pupil->data, ncp0, NULL, NULL))) goto done;

    /* The DM. */
    if (lp->act_xy) {
        nact = lp->nact;
        xy = malloc(2 * nact * sizeof *xy);
        if (!xy) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
        memcpy(xy, lp->act_xy, 2 * nact * sizeof *xy);
    } else if ((rc = swfs_actuators_hexapolar(p->teldiam, lp->act_pitch, p->pupdx, &xy, &nact))) {
        goto done;
    }
    if ((rc = swfs_dmfit_create(&fit, xy, nact, &r->geom, r->pupil->data, &lp->fit))) {
        if (lp->act_xy) rc = swfs_fail_context(rc, "%s", lp->act_name ? lp->act_name : "DM actuators");
        goto done;
    }
    r->nact = nact;
    r->pitch = swfs_dmfit_pitch(fit);
    r->actuators = swfs_real_alloc(2, nact, 1);
    r->commands = swfs_real_alloc(nact, nrows, 1);
    cmd = calloc(nact, sizeof *cmd);
    if (!r->actuators || !r->commands || !cmd) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    memcpy(r->actuators->data, xy, 2 * nact * sizeof *xy);

    for (size_t k = 0; k < nrows; k++) {
        const double t1 = swfs_wall_seconds();
        swfs_loop_iter *row = &r->rows[k];
        double *resid = swfs_real_frame(r->residual, k), *surf = swfs_real_frame(r->dm_surface, k);
        double *ck = r->commands->data + k * nact;
        /* Residual wavefront = NCP + 2 x DM surface (reflective), the DM surface made by the
         * accumulated commands through the influence functions (fitting error kept). */
        swfs_dmfit_surface(fit, ck, surf);
        for (size_t s = 0; s < n2; s++) resid[s] = r->pupil->data[s] > 0 ? ncp0[s] + 2.0 * surf[s] : 0.0;

        const swfs_sim_result *cur = NULL;
        if (k == 0 && first) {
            if (first->geom.pupn != p->pupn || first->science->nx != nfx || first->science->ny != nfy)
                { rc = swfs_fail(SWFS_ERR_SHAPE, "closed loop: the given first simulation does not match the parameters"); goto done; }
            cur = first;
        } else {
            swfs_sim_params pk = *p;
            pk.seed = p->seed + k; /* new turbulence every iteration, as on the sky */
            swfs_sim_result_free(sim);
            sim = NULL;
            if ((rc = swfs_sim_paper_run_ncp(&pk, resid, NULL, NULL, &sim))) goto done;
            cur = sim;
        }
        /* The simulator removed piston; keep its copy as the residual of record. */
        memcpy(resid, cur->ncp->data, n2 * sizeof *resid);
        row->resid_rms = masked_rms(resid, r->pupil->data, np, &row->resid_rms_ptt, scratch);
        row->strehl = sim_strehl(cur);
        row->strehl_ao = cur->strehl_ao;
        const double ph = 2.0 * M_PI * row->resid_rms / p->wavelen;
        row->strehl_marechal = exp(-ph * ph);
        row->contrast = swfs_halo_contrast(cur->halo_true, p->pixscale, lp->annulus_in, lp->annulus_out);
        ao_contrast(cur, lp, hwork, &row->contrast_ao, &row->contrast_ncp);
        row->est_rms = row->est_err = row->median_snr = NAN;
        row->fit.target_rms = row->fit.modal_rms = row->fit.filtered_rms = row->fit.fit_rms = NAN;
        row->fit.fiterr_rms = row->fit.unfit_rms = row->fit.cmd_rms = row->fit.cmd_min = row->fit.cmd_max = NAN;

        if (k < K) {
            if (noisy->nz != cur->science->nz) {
                swfs_real_free(noisy);
                noisy = swfs_real_alloc(nfx, nfy, cur->science->nz);
                if (!noisy) { rc = swfs_fail(SWFS_ERR_NOMEM, "closed loop: out of memory"); goto done; }
            }
            const uint64_t noise_seed = (p->seed + k) * 0x9E3779B97F4A7C15ULL + 0x100;
            swfs_pupil_result_free(pr);
            pr = NULL;
            if ((rc = measure(cur, lp, noise_seed, noisy, acc, r->pupil, &pr, &row->median_snr))) goto done;
            memcpy(swfs_real_frame(r->estimate, k), pr->wfe->data, n2 * sizeof *target);
            row->est_rms = pr->wfe_rms;
            if ((rc = swfs_wfe_compare(pr->wfe->data, resid, r->pupil->data, np, &row->est_err, NULL, NULL))) goto done;
            /* Correction surface: -WFE/2 (a surface change dz changes the wavefront by 2 dz). */
            for (size_t s = 0; s < n2; s++) target[s] = -0.5 * pr->wfe->data[s];
            if ((rc = swfs_dmfit_apply(fit, target, cmd, NULL, &row->fit))) goto done;
            double *cn = r->commands->data + (k + 1) * nact;
            for (size_t a = 0; a < nact; a++) cn[a] = ck[a] + lp->gain * cmd[a];
        }
        row->seconds = swfs_wall_seconds() - t1;
        if ((rc = swfs_progress_report(progress, ctx, "loop", k + 1, nrows))) goto done;
    }
    r->seconds = swfs_wall_seconds() - t0;

done:
    swfs_pupil_result_free(pr);
    swfs_sim_result_free(sim);
    swfs_dmfit_free(fit);
    swfs_real_free(noisy);
    swfs_accum_free(acc);
    swfs_cplx_free(hwork);
    free(xy);
    free(ncp0);
    free(target);
    free(scratch);
    free(cmd);
    if (rc) {
        swfs_loop_result_free(r);
        return rc;
    }
    *out = r;
    return SWFS_OK;
}

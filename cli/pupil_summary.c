/* pupil's lines on its joint fit (the method, the self-check and its rings, the mean intensity's
 * model, a fit that took no step), kept apart from its option parsing. */
#include "cli.h"
#include "specklewfs/jointfit.h"
#include "specklewfs/numeric.h"
#include "specklewfs/pupil.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

void cli_pupil_fit_summary(const swfs_pupil_result *r, const swfs_geom *g, const char *out)
{
    const swfs_jointfit_result *f = r->fit;
    printf("  method            joint fit of %zu focal pixels, %zu parameters (%zu B-spline intervals across D),\n"
           "                    %d steps, %.2f s; unexplained speckle fraction %.3f\n", f->npix, f->nparams,
           f->nintervals, f->iterations, f->seconds, f->kappa);
    printf("  self-check        the speckles explain %.1f %% of the science intensity's variance (median pixel "
           "%.1f %%)\n", 100 * r->explained, 100 * r->explained_median);
    if (r->explained_map && g->pixscale > 0) {
        double ring[32];
        const size_t nr = (size_t)fmin(32, (double)swfs_pupil_explained_nrings(r->explained_map, g->pixscale));
        swfs_pupil_explained_rings(r->explained_map, g->pixscale, ring, nr);
        printf("  by ring [l/D]    ");
        for (size_t k = 0; k < nr; k++)
            if (isfinite(ring[k])) printf(" %zu-%zu %.0f%%", k, k + 1, 100 * ring[k]);
        printf(" (median pixel; EXPLAINED)\n");
    }
    if (f->gain && g->pixscale > 0) {
        /* the fitted g by ring over its median: lower where the speckles hold less of the true
         * field (within the loop's control radius, say) */
        double ring[32];
        const size_t nr = (size_t)fmin(32, (double)swfs_pupil_explained_nrings(f->gain, g->pixscale));
        swfs_pupil_explained_rings(f->gain, g->pixscale, ring, nr);
        const size_t np = f->gain->nx * f->gain->ny;
        double *v = malloc(np * sizeof *v), med = NAN;
        size_t n = 0;
        for (size_t k = 0; v && k < np; k++)
            if (isfinite(f->gain->data[k])) v[n++] = f->gain->data[k];
        if (n) med = swfs_median_inplace(v, n);
        free(v);
        if (med > 0) {
            printf("  g by ring [l/D]  ");
            for (size_t k = 0; k < nr; k++)
                if (isfinite(ring[k])) printf(" %zu-%zu %.2f", k, k + 1, ring[k] / med);
            printf(" (over its median; GAIN_FIT)\n");
        }
    }
    if (isfinite(f->log_evidence))
        printf("  evidence          the fixed point of %s kept: log evidence %.1f, the other's %.1f (two starts)\n",
               f->warm_start ? "the warm start" : "the rule from the start", f->log_evidence, f->log_evidence_alt);
    if (isfinite(f->delta_chi2))
        printf("  mean intensity    %s (chi-square of the intercept model %.0f above the free one%s; limit %.0f)\n",
               f->intercept == SWFS_JF_INTERCEPT_FREE ? "free per pixel: light the speckles do not model"
                                                      : "modelled as |Psi|^2 + kappa g^2 Phi_sp",
               f->delta_chi2, f->model_stopped ? " where its fit stopped, out of the limit's reach" : "",
               f->delta_chi2_limit);
    if (f->iterations == 0)
        fprintf(stderr, "specklewfs pupil: warning: the joint fit took no step from its flat start (its normal "
                "equations were not positive definite there): the WFE of %s is the start, not an estimate; "
                "more frames, or --method moments, may do (FITITER = 0)\n", out);
}

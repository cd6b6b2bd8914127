/* The estimator issue's table (docs/estimator.md): the paper's Sec. 3 simulation (swfs_sim
 * defaults: 980 frames, 163^2 pupil, 60x60 window at 0.25 lambda/D) for seeds 1-3 and camera
 * noise sigma = 0 / 10 / 100 / 1000 counts, added exactly as `specklewfs demo` does (read
 * noise sigma, Poisson at the default gain, noise seed = seed * 1000003 + sigma). NCP error
 * [nm rms, piston + tip/tilt removed, swfs_wfe_compare] of
 *   paper   the paper's formulae (per-pixel g, eq:PSI-LowFreq, full weight; err_paper)
 *   old     the moments' default, the default before the joint fit (regularized g, HALO_LF,
 *           Wiener weight; err_lf_snr)
 *   joint   swfs_regress + swfs_jointfit with its defaults (curvature prior, intercept chosen
 *           by the likelihood-ratio test): what `specklewfs pupil` does by default
 *   j-free  the same with the intercept free per pixel (what the test falls back to)
 * then the accumulation cost per pixel-frame: swfs_accum_add (moments + regression
 * statistics, what every path now does) against the moments alone (the cost before the
 * regression statistics: swfs_accum_add minus swfs_regress_add), and the joint fit's wall time.
 *
 * Run:  ./build/bench/bench_estimator              (3 seeds x 4 levels, about a minute)
 *       ./build/bench/bench_estimator SEEDS SIGMA... (e.g. "1 100 1000": seed 1 only) */
#include "specklewfs/accum.h"
#include "specklewfs/jointfit.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "specklewfs/recovery.h"
#include "specklewfs/regress.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

static int die(const char *what)
{
    fprintf(stderr, "bench_estimator: %s: %s\n", what, swfs_last_error());
    return 1;
}

/* Joint-fit NCP error for one noisy cube; fills the fit time and the |Psi| error. */
static int joint_error(const swfs_sim_result *sim, const swfs_real *noisy, const swfs_jointfit_options *o, double *err,
                       double *fit_s, double *psi_err)
{
    const size_t np = noisy->nx * noisy->ny;
    swfs_regress *r = swfs_regress_create(noisy->nx, noisy->ny);
    if (!r) return 1;
    for (size_t t = 0; t < noisy->nz; t++)
        if (swfs_regress_add(r, noisy->data + t * np, (const double *)(sim->speckles->data + t * np), NULL)) return 1;
    swfs_regress_sol *s;
    if (swfs_regress_solve(r, &s)) return 1;
    swfs_jointfit_result *j;
    if (swfs_jointfit(s, &sim->geom, sim->pupil, o, &j)) return 1;
    if (swfs_wfe_compare(j->wfe->data, sim->ncp->data, sim->pupil->data, (size_t)sim->geom.pupn, err, NULL, NULL))
        return 1;
    *fit_s = j->seconds;
    /* median relative |Psi - Psi_true| over the window */
    double *rel = malloc(np * sizeof *rel);
    for (size_t k = 0; k < np; k++) rel[k] = cabs(j->halo->data[k] - sim->halo_true->data[k]) / cabs(sim->halo_true->data[k]);
    for (size_t a = 1; a < np; a++)
        for (size_t b = a; b > 0 && rel[b - 1] > rel[b]; b--) { double t = rel[b]; rel[b] = rel[b - 1]; rel[b - 1] = t; }
    *psi_err = rel[np / 2];
    free(rel);
    swfs_jointfit_result_free(j);
    swfs_regress_sol_free(s);
    swfs_regress_free(r);
    return 0;
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    /* As the command line: the library parallelizes over frames, BLAS stays single-threaded
     * (parallel.h). */
    swfs_blas_set_threads(1);
    int nseeds = 3;
    double sigmas[8] = {0, 10, 100, 1000};
    int nsig = 4;
    if (argc > 1) nseeds = atoi(argv[1]);
    if (argc > 2) {
        nsig = 0;
        for (int k = 2; k < argc && nsig < 8; k++) sigmas[nsig++] = atof(argv[k]);
    }
    double err[3][8][4], tfit[3][8], perr[3][8];
    double acc_ns = 0.0, reg_ns = 0.0, fit_threads[2] = {0.0, 0.0};
    for (int s = 0; s < nseeds; s++) {
        swfs_sim_params p;
        swfs_sim_params_default(&p);
        p.seed = (uint64_t)(s + 1);
        swfs_sim_result *sim;
        if (swfs_sim_paper_run(&p, NULL, NULL, &sim)) return die("simulation");
        fprintf(stderr, "seed %d: %zu frames simulated in %.1f s\n", s + 1, sim->nframes, sim->seconds);
        for (int k = 0; k < nsig; k++) {
            const uint64_t nseed = p.seed * 1000003ULL + (uint64_t)sigmas[k];
            swfs_recovery rec;
            if (swfs_recovery_run(sim, sigmas[k], nseed, NULL, NULL, 0, &rec)) return die("recovery");
            swfs_real *noisy = swfs_real_copy(sim->science);
            if (!noisy || swfs_sim_camera(sim->science, sigmas[k], p.gain, nseed, noisy)) return die("camera noise");
            double ej, eg, tg, pg;
            swfs_jointfit_options og;
            swfs_jointfit_options_default(&og);
            og.intercept = SWFS_JF_INTERCEPT_FREE;
            if (joint_error(sim, noisy, NULL, &ej, &tfit[s][k], &perr[s][k])) return die("joint fit");
            if (joint_error(sim, noisy, &og, &eg, &tg, &pg)) return die("joint fit (free intercept)");
            err[s][k][3] = eg * 1e9;
            err[s][k][0] = rec.err_paper * 1e9;
            err[s][k][1] = rec.err_lf_snr * 1e9;
            err[s][k][2] = ej * 1e9;
            fprintf(stderr, "  sigma %5g: paper %6.1f  old %6.1f  joint %6.1f nm  (|Psi| err %.2f%%, fit %.2f s)\n",
                    sigmas[k], err[s][k][0], err[s][k][1], err[s][k][2], 100 * perr[s][k], tfit[s][k]);
            if (s == 0 && k == 0) {
                /* the default fit (both intercept fits) with 1 and 2 BLAS threads: the fit is
                   one dense problem, the only step that BLAS's own threads speed up */
                for (int th = 1; th <= 2; th++) {
                    swfs_blas_set_threads(th);
                    double best = 1e30, e_, p_, t_;
                    for (int rep = 0; rep < 3; rep++) {
                        if (joint_error(sim, noisy, NULL, &e_, &t_, &p_)) return die("joint fit (timing)");
                        best = fmin(best, t_);
                    }
                    fit_threads[th - 1] = best;
                }
                swfs_blas_set_threads(1);
                /* accumulation cost per pixel-frame, best of 3 passes over the cube */
                const size_t np = noisy->nx * noisy->ny, nt = noisy->nz;
                swfs_accum *a = swfs_accum_create(noisy->nx, noisy->ny);
                swfs_regress *r = swfs_regress_create(noisy->nx, noisy->ny);
                double ba = 1e30, br = 1e30;
                for (int rep = 0; rep < 3; rep++) {
                    swfs_accum_reset(a);
                    swfs_regress_reset(r);
                    double t0 = swfs_wall_seconds();
                    for (size_t t = 0; t < nt; t++) swfs_accum_add(a, noisy->data + t * np, sim->speckles->data + t * np);
                    double t1 = swfs_wall_seconds();
                    for (size_t t = 0; t < nt; t++)
                        swfs_regress_add(r, noisy->data + t * np, (const double *)(sim->speckles->data + t * np), NULL);
                    double t2 = swfs_wall_seconds();
                    ba = fmin(ba, t1 - t0);
                    br = fmin(br, t2 - t1);
                }
                acc_ns = 1e9 * ba / (double)(np * nt);
                reg_ns = 1e9 * br / (double)(np * nt);
                swfs_accum_free(a);
                swfs_regress_free(r);
            }
            swfs_real_free(noisy);
        }
        swfs_sim_result_free(sim);
    }
    printf("NCP error [nm rms, piston+tip/tilt removed], paper Sec. 3 case, 980 frames\n");
    printf("%-6s %-7s", "seed", "method");
    for (int k = 0; k < nsig; k++) printf(" %8g", sigmas[k]);
    printf("\n");
    static const char *names[4] = {"paper", "old", "joint", "j-free"};
    for (int m = 0; m < 4; m++)
        for (int s = 0; s <= nseeds; s++) {
            if (s < nseeds) printf("%-6d %-7s", s + 1, names[m]);
            else printf("%-6s %-7s", "mean", names[m]);
            for (int k = 0; k < nsig; k++) {
                double v = 0.0;
                if (s < nseeds) v = err[s][k][m];
                else { for (int q = 0; q < nseeds; q++) v += err[q][k][m]; v /= nseeds; }
                printf(" %8.1f", v);
            }
            printf("\n");
        }
    printf("%-14s", "|Psi| err [%]");
    for (int k = 0; k < nsig; k++) {
        double v = 0.0;
        for (int q = 0; q < nseeds; q++) v += perr[q][k];
        printf(" %8.2f", 100 * v / nseeds);
    }
    printf("   (median relative |Psi - Psi_true|, mean over seeds)\n");
    double tmax = 0.0, tsum = 0.0;
    for (int s = 0; s < nseeds; s++)
        for (int k = 0; k < nsig; k++) { tmax = fmax(tmax, tfit[s][k]); tsum += tfit[s][k]; }
    printf("joint fit wall time: mean %.2f s, max %.2f s (1 BLAS thread)\n", tsum / (nseeds * nsig), tmax);
    printf("joint fit, seed 1, sigma %g, best of 3: %.2f s with 1 BLAS thread, %.2f s with 2\n", sigmas[0],
           fit_threads[0], fit_threads[1]);
    printf("accumulation per pixel-frame: swfs_accum_add %.2f ns (moments + regression statistics), of which\n"
           "  swfs_regress_add %.2f ns; moments alone %.2f ns; cost now / before the regression statistics: %.2fx\n",
           acc_ns, reg_ns, acc_ns - reg_ns, acc_ns / (acc_ns - reg_ns));
    return 0;
}

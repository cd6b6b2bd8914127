/* specklewfs learn DIR... -o W.fits [--ridge R]: a reconstructor from simulated closed loops. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int swfs_cmd_learn(int argc, char **argv)
{
    const char *cmd = "learn";
    swfs_learn_run_options o;
    swfs_learn_run_options_default(&o);
    const char **dirs = calloc((size_t)argc, sizeof *dirs);
    size_t nd = 0;
    if (!dirs) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const char *lags = NULL, *cradius = NULL, *over = NULL;
    long lagv[SWFS_RECON_MAXLAGS], threads = 0;
    int no_mean_miss = 0;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o.out, "a file name", 0},
        {"--lags", CLI_STRING, &lags, "a list of WFS-frame lags (e.g. 0,-25,25)", 0},
        {"--ridge", CLI_DOUBLE, &o.ridge, NULL, 0},
        {"--prior", CLI_STRING, &o.prior, "a map file", 0},
        {"--no-heldout", CLI_SET, &o.no_heldout, NULL, 1},
        {"--no-mean-miss", CLI_SET, &no_mean_miss, NULL, 1},
        {"--mean-miss-heldout", CLI_SET, &o.mean_miss_heldout, NULL, 1},
        {"--mean-miss-over", CLI_STRING, &over, "FUNCS.fits,PUPIL.fits", 0},
        {"--modal", CLI_SET, &o.modal, NULL, 1},
        {"--perframe-out", CLI_STRING, &o.perframe_out, "a file name", 0},
        {"--curve", CLI_SET, &o.curve, NULL, 1},
        {"--curve-radius", CLI_STRING, &cradius, "radii R0,R1 [m]", 0},
        {"--threads", CLI_LONG, &threads, NULL, 0},
    };
    const cli_args args = {cmd, cli_usage_learn(), opts, CLI_NOPTS(opts), NULL, 0, NULL, NULL, dirs, &nd};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc) { free(dirs); return rc < 0 ? CLI_OK : rc; }
    if (!nd) rc = cli_usage_error(cmd, "needs at least one simulated data set (a folder)");
    else if (!o.out) rc = cli_usage_error(cmd, "needs -o W.fits");
    else if (!(o.ridge > 0) || !(o.ridge <= 1e30))
        rc = cli_usage_error(cmd, "--ridge must be a fraction > 0 and at most 1e30 (of the normal equations' mean "
                             "diagonal: beyond, the map is the prior, or 0), got %g", o.ridge);
    else if (threads < 0 || threads > 4096) rc = cli_usage_error(cmd, "--threads must be 0 (the CPUs) to 4096, got %ld", threads);
    if (!rc && lags && swfs_lags_parse(lags, lagv, &o.nlags, "--lags")) rc = cli_error(cmd);
    if (!rc && cradius) {
        char end = 0;
        if (sscanf(cradius, "%lf,%lf%c", &o.curve_radius[0], &o.curve_radius[1], &end) != 2 ||
            !(o.curve_radius[0] >= 0) || !(o.curve_radius[1] > o.curve_radius[0]) || !isfinite(o.curve_radius[1]))
            rc = cli_usage_error(cmd, "--curve-radius takes R0,R1 [m], 0 <= R0 < R1 (the pupil's annulus), got '%s'",
                                 cradius);
        else if (!o.curve && (o.no_heldout || nd < 2))
            rc = cli_usage_error(cmd, "--curve-radius is where the checks are measured: it goes with --curve or "
                                 "with the held-out check (two or more folders, without --no-heldout)");
    }
    if (!rc && no_mean_miss && (o.mean_miss_heldout || over))
        rc = cli_usage_error(cmd, "--no-mean-miss and --mean-miss-%s: one or the other", over ? "over" : "heldout");
    char funcs[4096] = "";
    const char *comma = over ? strchr(over, ',') : NULL;
    if (!rc && over && (!comma || comma == over || !comma[1] || (size_t)(comma - over) >= sizeof funcs))
        rc = cli_usage_error(cmd, "--mean-miss-over takes FUNCS.fits,PUPIL.fits, got '%s'", over);
    if (!rc && over) memcpy(funcs, over, (size_t)(comma - over));
    double *metric = NULL;
    if (!rc && over && swfs_meanmiss_metric(funcs, 0, NULL, comma + 1, &metric, &o.meanmiss_metric_n)) rc = cli_error(cmd);
    o.meanmiss_metric = metric;
    if (!rc && o.perframe_out && o.nlags < 2)
        rc = cli_usage_error(cmd, "--perframe-out goes with --lags (without them the map is per frame already)");
    if (rc) { free(dirs); free(metric); return rc; }
    o.lags = lagv;
    o.threads = (int)threads;
    o.mean_miss = !no_mean_miss;
    o.dirs = dirs;
    o.ndirs = nd;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_writer() ? cli_stage_progress : NULL;
    o.progress_ctx = "learn:";
    double *ratio = calloc(nd, sizeof *ratio);
    if (!ratio) { free(dirs); free(metric); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    o.heldout_ratio = ratio;
    swfs_learn_run_result r;
    rc = swfs_learn_run(&o, &r) ? cli_error(cmd) : CLI_OK;
    free(metric);
    if (rc) { free(dirs); free(ratio); return rc; }
    printf("learn: %zu WFS frames from %zu files in %zu data set%s: %zu slopes", r.info.nframes, r.nfiles, nd,
           nd == 1 ? "" : "s", r.nslopes);
    if (o.nlags > 1) {
        printf(" x %zu lags (", o.nlags);
        for (size_t k = 0; k < o.nlags; k++) printf("%s%ld", k ? "," : "", lagv[k]);
        printf(")");
    }
    printf(" (%zu with signal) -> %zu %s\n", r.info.nslopes_seen, r.nact, o.modal ? "coefficients" : "actuators");
    if (o.modal)
        printf("learn: the simulated coefficients %.4g rms; the map misses them by %.4g on the training frames -> %s "
               "(a control matrix)\n", r.info.truth_rms, r.info.misfit_rms, o.out);
    else
        printf("learn: the simulated residual %.1f nm rms per actuator; the map misses it by %.1f nm on the training "
               "frames -> %s\n", 1e9 * r.info.truth_rms, 1e9 * r.info.misfit_rms, o.out);
    if (o.perframe_out && o.nlags > 1)
        printf("learn: the per-frame map of the same frames (the lag-0 block) misses the residual by %.1f nm -> %s\n",
               1e9 * r.perframe_info.misfit_rms, o.perframe_out);
    if (o.nlags > 1) cli_learn_wind_summary(&r, nd);
    if (o.curve) cli_curve_line(stdout, "learn:", &r, o.modal ? 1 : 1e9, o.modal ? "" : " nm");
    if (r.nheldout) {
        printf("learn: each data set held out in turn, the map of the others applied to it (misfit / residual; "
               "training %.2f):\n", r.info.misfit_rms / r.info.truth_rms);
        for (size_t d = 0; d < nd; d++) {
            if (isnan(ratio[d])) printf("  %-40s not checked (too few frames in the others)\n", dirs[d]);
            else printf("  %-40s %.2f%s\n", dirs[d], ratio[d], ratio[d] >= 1 ? "  not covered: worse than no map" : "");
        }
        const double u = o.modal ? 1 : 1e9;
        printf("learn: held out, all %zu: %.4g%s of %.4g (%.2f; each check's map scaled best: %.2f) over %zu of %zu "
               "outputs%s\n", r.nheldout, u * r.heldout_misfit_rms, o.modal ? "" : " nm", u * r.heldout_truth_rms,
               r.heldout_misfit_rms / r.heldout_truth_rms, r.heldout_scaled_rms / r.heldout_truth_rms,
               r.heldout_outputs, r.nact, r.heldout_outputs < r.nact ? " (--curve-radius)" : "");
        if (r.heldout_worst >= 1)
            printf("learn: a data set at >= 1 is one the others do not cover: its conditions lie outside theirs, or "
                   "they hold too few frames for %zu slopes (%.1f frames per slope in all; simulate more, or more "
                   "conditions between)\n", r.info.nslopes_seen, (double)r.info.nframes / (double)r.info.nslopes_seen);
    } else if (nd > 1 && !o.no_heldout) {
        printf("learn: held-out check: no data set could be left out (too few frames in the others)\n");
    }
    if (isfinite(r.meanmiss_heldout)) {
        const double u = o.modal ? 1.0 : 1e9;
        printf("learn: the map's miss of the residual's time mean: %.4g%s rms per data set%s; the others' mean "
               "predicts each set's to %.2f of its own square (held out)", (over ? 1e9 : u) * r.meanmiss_set_rms,
               over || !o.modal ? " nm" : "", over ? " in the pupil" : "", r.meanmiss_heldout);
        if (r.meanmiss_kept)
            printf(": the sensor's, the same in every loop; their mean (%.4g%s rms) -> %s, extension MEANMISS, which "
                   "speckles adds to the residual's mean\n", u * r.meanmiss_rms, o.modal ? "" : " nm", o.out);
        else
            printf(": each loop's own; none written\n");
    }
    free(dirs);
    free(ratio);
    return CLI_OK;
}

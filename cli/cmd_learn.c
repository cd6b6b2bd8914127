/* specklewfs learn DIR... -o W.fits [--ridge R]: a reconstructor from simulated closed loops. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

static const char *usage_text =
    "usage: specklewfs learn SIMDIR... -o W.fits [--modal] [--ridge R] [--prior W0.fits] [--no-heldout]\n"
    "                        [--no-mean-miss | --mean-miss-heldout]\n"
    "                        [--lags L,L,...]\n"
    "                        [--perframe-out W1.fits] [--curve] [--curve-radius R0,R1] [--threads N]\n"
    "\n"
    "A reconstructor learned from simulated closed loops of your system's geometry: the\n"
    "least-squares map from one WFS frame's slopes to the true residual wavefront on the\n"
    "actuators, over every frame of the folders given (`specklewfs simulate mode=timeseries\n"
    "export_truth=1 ...`: slopes_NNN.fits beside truewf_NNN.fits; any simulation writing\n"
    "those files will do). Give it to `specklewfs speckles --recon W.fits`, or to the linear\n"
    "model as `--basis B.fits --control W.fits`. Simulate the same WFS, actuators and\n"
    "controlled modes as the data (simulate's actuators=, ao_recon=, valid= and pupil_mask=FILE\n"
    "take your DM's positions, your loop's reconstructor, your valid subapertures and your\n"
    "telescope's pupil; another modal filter lost to the default, another gain, delay or\n"
    "slope noise did not), under winds like the data's (`specklewfs wind` gives the layer\n"
    "that dominates your slopes; give the rest of the profile a spread): trained on other\n"
    "systems of one geometry it beat the default von Karman reconstructor on 22 of the 24\n"
    "runs measured and lost by 0.1-0.2 nm on two (docs/telemetry.md); trained on one\n"
    "condition alone it can lose to it.\n"
    "\n"
    "  -o W.fits     the reconstructor (NAXIS1 = slopes, NAXIS2 = actuators, m/rad); when the\n"
    "                truth was fitted on points of its own (simulate's truth_actuators=FILE:\n"
    "                truewf's extension OUTXY, the same in every folder) the map's outputs are\n"
    "                those points, written as W.fits' extension OUTXY, and speckles\n"
    "                interpolates the wavefront from them\n"
    "  --modal       truewf_NNN.fits hold the residual's coefficients on a basis without\n"
    "                piston (any AO system: modes, or any WFS signal in slopes_NNN.fits):\n"
    "                learned as they are, and W.fits is a control matrix for speckles\n"
    "                --basis B.fits --control W.fits (default: actuator values, whose mean\n"
    "                is piston and is taken out)\n"
    "  --ridge R     ridge of the normal equations, a fraction of their mean diagonal\n"
    "                (default 1e-6; it only conditions the solve)\n"
    "  --prior W0.fits  the map shrinks toward W0 (the same slopes and outputs; e.g. the MAP\n"
    "                `speckles --basis B --imat D --write-recon W0.fits` wrote): the frames move\n"
    "                it from W0 as far as the ridge lets them, so give --ridge a weight (0.1:\n"
    "                a tenth of the slopes' mean power per frame); for loops too few for a\n"
    "                map of their own (not with --lags)\n"
    "  --no-mean-miss  no MEANMISS: the map's miss of the residual's time mean where the\n"
    "                folders share it (a pyramid's), which speckles adds to RESMEAN\n"
    "  --mean-miss-heldout  each folder's miss of the mean taken with the map of the other\n"
    "                folders (their sums, its own left out), not with the map of all: with few\n"
    "                folders the map fits their means in-sample and misses new frames' more\n"
    "  --no-heldout  skip the held-out check: with more than one folder each is left out in\n"
    "                turn and the map of the others applied to its frames (against the\n"
    "                training misfit: do the conditions cover each other? every file read twice)\n"
    ;
/* the options from --lags on (one string literal would pass the length C99 guarantees) */
static const char *usage_lags =
    "  --lags L,...  a space-time map: the input of frame t is the slopes of frames t + L for\n"
    "                every L given (WFS frames, one of them 0, at most 16; clamped at each\n"
    "                file's ends), and W.fits a cube of one map per lag (NLAGS, LAGk) that\n"
    "                `speckles --recon` applies the same way. Frames far enough apart for the\n"
    "                wind to move the screen by a fraction of a subaperture tell an alias from\n"
    "                the frequency it hides: 0,+-L,+-2L with L = round(D/nsub rate / (2 v))\n"
    "                frames (half a subaperture; v from `specklewfs wind`) is the rule measured\n"
    "                (bench/spacetime.sh). It pays only when the simulated loops hold the\n"
    "                observation's own wind and whole profile; trained at another wind it can\n"
    "                be far worse than the default (docs/telemetry.md, \"A space-time learned\n"
    "                map\")\n"
    "  --perframe-out W1.fits  with --lags, also the per-frame map of the same frames (the\n"
    "                lag-0 block of the same sums solved alone, no second pass): for\n"
    "                `specklewfs live`, which takes one frame's slopes\n"
    "  --curve       the learning curve (4+ folders): maps of half and of three quarters of\n"
    "                the folders checked on the rest; how far the map is from one of\n"
    "                unlimited frames, and the frames for 10 % (LRNCEXC, LRNCFRM);\n"
    "                --threads N: its sums and checks N at once (0: the CPUs; same map)\n"
    "  --curve-radius R0,R1  the checks (the curve and the held-out check) over the outputs at\n"
    "                R0..R1 m from the centre only, e.g. the pupil's annulus (the truth beyond\n"
    "                it, on a DM's outer actuators, is the fit's extrapolation): the truth's\n"
    "                points (OUTXY), else the first folder's actuators.fits\n";

int swfs_cmd_learn(int argc, char **argv)
{
    const char *cmd = "learn";
    swfs_learn_run_options o;
    swfs_learn_run_options_default(&o);
    const char **dirs = calloc((size_t)argc, sizeof *dirs);
    size_t nd = 0;
    if (!dirs) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const char *lags = NULL, *cradius = NULL;
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
        {"--modal", CLI_SET, &o.modal, NULL, 1},
        {"--perframe-out", CLI_STRING, &o.perframe_out, "a file name", 0},
        {"--curve", CLI_SET, &o.curve, NULL, 1},
        {"--curve-radius", CLI_STRING, &cradius, "radii R0,R1 [m]", 0},
        {"--threads", CLI_LONG, &threads, NULL, 0},
    };
    static char usage[8192];
    snprintf(usage, sizeof usage, "%s%s", usage_text, usage_lags);
    const cli_args args = {cmd, usage, opts, CLI_NOPTS(opts), NULL, 0, NULL, NULL, dirs, &nd};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc) { free(dirs); return rc < 0 ? CLI_OK : rc; }
    if (!nd) rc = cli_usage_error(cmd, "needs at least one simulated data set (a folder)");
    else if (!o.out) rc = cli_usage_error(cmd, "needs -o W.fits");
    else if (!(o.ridge > 0) || !isfinite(o.ridge)) rc = cli_usage_error(cmd, "--ridge must be a finite fraction > 0, got %g", o.ridge);
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
    if (!rc && no_mean_miss && o.mean_miss_heldout)
        rc = cli_usage_error(cmd, "--no-mean-miss and --mean-miss-heldout: one or the other");
    if (!rc && o.perframe_out && o.nlags < 2)
        rc = cli_usage_error(cmd, "--perframe-out goes with --lags (without them the map is per frame already)");
    if (rc) { free(dirs); return rc; }
    o.lags = lagv;
    o.threads = (int)threads;
    o.mean_miss = !no_mean_miss;
    o.dirs = dirs;
    o.ndirs = nd;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_writer() ? cli_stage_progress : NULL;
    o.progress_ctx = "learn:";
    double *ratio = calloc(nd, sizeof *ratio);
    if (!ratio) { free(dirs); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    o.heldout_ratio = ratio;
    swfs_learn_run_result r;
    if (swfs_learn_run(&o, &r)) { free(dirs); free(ratio); return cli_error(cmd); }
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
        printf("learn: the map's miss of the residual's time mean: %.4g%s rms per data set; the others' mean predicts "
               "each set's to %.2f of its own square (held out)", u * r.meanmiss_set_rms, o.modal ? "" : " nm",
               r.meanmiss_heldout);
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

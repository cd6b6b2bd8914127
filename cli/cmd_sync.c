/* specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt: frame-rate ratio and handshake
 * lag by tip-tilt cross-correlation (Sec. 4.2). The work is the library's (run.h: swfs_sync_run). */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt [--ratio-min R] [--ratio-max R]\n"
    "                       [--lag-min L] [--lag-max L] [--ratio-step S] [--lag-step S]\n"
    "       specklewfs sync --wfs-log DIR|FILE SCIENCE.fits -o CLOCK.txt [--exptime T]\n"
    "                       [--offset-min S] [--offset-max S] [--drift-max D]\n"
    "\n"
    "Synchronize the science cubes with the WFS telemetry (Codona & Kenworthy 2013, Sec. 4.2).\n"
    "The star's track (TRACK extension written by `specklewfs reduce`) is cross-correlated\n"
    "with the mean x/y WFS slopes averaged over each exposure, over all four pairings of\n"
    "camera and slope axes, while the frame-rate ratio <t_sci/t_wfs> and the handshake lag\n"
    "are varied. A cube that runs out of the telemetry file the handshake names is followed\n"
    "file by file while the files continue each other (the camera's lag over the part, and\n"
    "the telemetry's own frame-to-frame steps across the boundary), or while both count the\n"
    "frames lost or repeated between them; the fit is made again over the files so joined.\n"
    "Exposures across a boundary, or in a file that does not continue, are marked\n"
    "straddles and not used by `specklewfs speckles`. A cube whose\n"
    "telemetry file cannot be read (missing, truncated, another shape) is left out with a\n"
    "warning and marked missing; only when no file can be read does sync stop.\n"
    "\n"
    "  SCIENCE.fits     reduced science cube with TRACK and CUBEnnnn keywords\n"
    "  HANDSHAKE.log    lines \"CAMERA_FILE SLOPES_FILE WFS_FRAME\" (docs/telemetry.md); slopes\n"
    "                   files are found relative to the log's folder\n"
    "  -o TIMING.txt    timing table: ratio +- error, lag, axis pairing, one line per cube\n"
    "  --ratio-min/max  search range of <t_sci/t_wfs> (default: from EXPTIME x WFSRATE, the\n"
    "                   science cube's exposure time by the telemetry's frame rate (an exposure\n"
    "                   lasts at most its frame period), less 5 coarse steps, else 0.1, a camera\n"
    "                   ten times faster than the WFS; a best ratio at that start searches again\n"
    "                   from 0.1 .. the handshake log's bound: a cube ends before the next cube\n"
    "                   of its file starts; 12 when no two cubes start in one file). A fit whose\n"
    "                   correlations are not significant over the search is refused\n"
    "  --lag-min/max    search range of the lag [WFS frames] (default -3 .. 12: the log is written\n"
    "                   after the camera starts). Keep it narrower than the period of a dominant\n"
    "                   vibration: a pure sinusoid makes the lag ambiguous by half periods\n"
    "  --ratio-step, --lag-step  coarse grid (0.01, 0.5), refined 100x around the peak\n"
    "\n"
    "Time-stamped data (milk/cacao logs, docs/telemetry.md): the camera clock against the WFS\n"
    "clock, t_wfs = epoch + (t_cam - epoch) (1 + drift) + offset, by the same correlation\n"
    "over (offset, drift); every stamp marks the end of its frame.\n"
    "  --wfs-log DIR|FILE  the WFS slopes' log (a folder of NAME_hh:mm:ss.s.fits[.fz] + .txt, or\n"
    "                   one such file); SCIENCE.fits must have STAMPS ('reduce' of camera logs)\n"
    "  -o CLOCK.txt     offset, drift (with their errors), pairing, correlation, residual\n"
    "  --exptime T      camera exposure [s] (default: EXPTIME of the raw header, else the period)\n"
    "  --offset-min/max search range of the offset [s] (default -0.01 .. 0.01); keep it within\n"
    "                   half the period of a dominant vibration (a sinusoid repeats)\n"
    "  --drift-max D    |drift| searched (default 5e-4)\n"
    "\n"
    "Telemetry that is not Shack-Hartmann slopes (modal coefficients, any WFS signal with a control\n"
    "matrix): give its linear model as `speckles` takes it (--basis, --control or --imat, --dm-pitch,\n"
    "--dm-offset, --dm-rot, --dm-flip, --coef-scale; geometry from SCIENCE.fits): the tip-tilt\n"
    "correlated with the star's track is then the Z-tilt of the model's wavefront.\n";

/* The linear model's options (the telemetry's tip-tilt through its wavefront). */
static int lin_special(void *ctx, int argc, char **argv, int *i)
{
    return cli_linear_option("sync", argc, argv, i, ctx);
}

/* sync --wfs-log: the clock file. */
static int sync_clock(int argc, char **argv)
{
    const char *cmd = "sync";
    swfs_clock_run_options o;
    swfs_clock_run_options_default(&o);
    const char *wfs = NULL;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o.out, "a file name", 0},          {"--wfs-log", CLI_STRING, &wfs, "a folder or file", 0},
        {"--exptime", CLI_DOUBLE, &o.exptime, NULL, 0},        {"--offset-min", CLI_DOUBLE, &o.params.offset_min, NULL, 0},
        {"--offset-max", CLI_DOUBLE, &o.params.offset_max, NULL, 0}, {"--drift-max", CLI_DOUBLE, &o.params.drift_max, NULL, 0},
    };
    const char **const pos[] = {&o.science};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 1, lin_special, &o.lin, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!o.science || !o.out) return cli_usage_error(cmd, "--wfs-log needs SCIENCE.fits and -o CLOCK.txt");
    if (!(o.exptime >= 0)) return cli_usage_error(cmd, "--exptime must be >= 0 s, got %g", o.exptime);
    o.wfs = &wfs;
    o.nwfs = 1;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    swfs_clock_run_result r;
    if (swfs_clock_run(&o, &r)) return cli_error(cmd);
    const swfs_clock *c = &r.clock;
    printf("sync: WFS log %zu frames in %zu files (%llu dropped), period %.6g ms, stamp jitter %.3g us; camera %zu "
           "frames (%llu dropped), period %.6g ms, jitter %.3g us, exposure %.6g ms\n", r.wfs_frames, r.wfs_files,
           (unsigned long long)r.wfs_dropped, 1e3 * c->wfs_period, 1e6 * c->wfs_jitter, c->ncam,
           (unsigned long long)r.cam_dropped, 1e3 * c->cam_period, 1e6 * c->cam_jitter, 1e3 * c->exptime);
    printf("sync: clock offset %.4f +- %.4f ms, drift %.3e +- %.1e (t_wfs = epoch + (t_cam - epoch)(1 + drift) + "
           "offset)\n", 1e3 * c->offset, 1e3 * c->offset_err, c->drift, c->drift_err);
    printf("sync: pairing camera x <- %s slopes (sign %+d, corr %.3f), camera y <- %s slopes (sign %+d, corr %.3f); "
           "track residual %.3g px rms over %zu frames in %zu segments -> %s\n", c->fit.swap ? "y" : "x",
           c->fit.sign_x, c->fit.corr_x, c->fit.swap ? "x" : "y", c->fit.sign_y, c->fit.corr_y, c->resid, c->nused,
           c->nsegments, o.out);
    return CLI_OK;
}

int swfs_cmd_sync(int argc, char **argv)
{
    const char *cmd = "sync";
    for (int i = 1; i < argc; i++)
        if (!strcmp(argv[i], "--wfs-log")) return sync_clock(argc, argv);
    swfs_sync_run_options o;
    swfs_sync_run_options_default(&o);
    swfs_sync_params *p = &o.params;
    p->ratio_min = NAN; /* not given: 0, from EXPTIME (the library's default) */
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o.out, "a file name", 0},         {"--ratio-min", CLI_DOUBLE, &p->ratio_min, NULL, 0},
        {"--ratio-max", CLI_DOUBLE, &p->ratio_max, NULL, 0},  {"--lag-min", CLI_DOUBLE, &p->lag_min, NULL, 0},
        {"--lag-max", CLI_DOUBLE, &p->lag_max, NULL, 0},      {"--ratio-step", CLI_DOUBLE, &p->ratio_step, NULL, 0},
        {"--lag-step", CLI_DOUBLE, &p->lag_step, NULL, 0},
    };
    const char **const pos[] = {&o.science, &o.handshake};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 2, lin_special, &o.lin, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!o.science || !o.handshake) return cli_usage_error(cmd, "needs SCIENCE.fits and HANDSHAKE.log");
    if (!o.out) return cli_usage_error(cmd, "needs -o TIMING.txt");
    if (isnan(p->ratio_min)) p->ratio_min = 0;
    else if (!(p->ratio_min > 0)) return cli_usage_error(cmd, "--ratio-min must be > 0, got %g", p->ratio_min);
    swfs_sync_run_result r;
    int rc = swfs_sync_run(&o, &r);
    const swfs_timing *t = &r.t;
    if (t->cubes && t->ratio > 0) { /* the fit was made (also when no cube turned out usable) */
        printf("sync: <t_sci/t_wfs> = %.4f +- %.4f, lag = %.2f WFS frames (handshake frame - lag = exposure start)\n",
               t->ratio, t->ratio_err, t->lag);
        printf("sync: pairing camera x <- %s slopes (sign %+d, corr %.3f), camera y <- %s slopes (sign %+d, corr %.3f)\n",
               t->fit.swap ? "y" : "x", t->fit.sign_x, t->fit.corr_x, t->fit.swap ? "x" : "y", t->fit.sign_y,
               t->fit.corr_y);
        printf("sync: |corr| tx-mx %.3f tx-my %.3f ty-mx %.3f ty-my %.3f\n", t->fit.corr4[0], t->fit.corr4[1],
               t->fit.corr4[2], t->fit.corr4[3]);
        printf("sync: ratios searched %g .. %g%s; the fit %.1f sigma over %.0f independent exposures (the search "
               "needs %.1f)\n", r.ratio_min, r.ratio_max, r.ratio_auto ? (r.ratio_bound > 0 ? " (to the handshake "
               "log's bound: a cube ends before the next one of its file starts)" : " (no two cubes start in one "
               "telemetry file: no bound from the log)") : "", t->fit.z, t->fit.neff, t->fit.z_need);
        if (r.exptime_used)
            printf("sync: the least ratio from the camera's exposure: EXPTIME x WFSRATE = %.4f WFS frames (an exposure "
                   "lasts at most its frame period), searched from %d coarse steps below\n", r.exptime_ratio,
                   SWFS_SYNC_EXPTIME_STEPS);
        if (r.exptime_widened)
            printf("sync: the best ratio lay at the least one EXPTIME x WFSRATE = %.4f gives: the header's exposure is "
                   "longer than the frames' period; searched again from %g\n", r.exptime_ratio, r.ratio_min);
        if (t->fit.lag_moves)
            printf("sync: the best lag lay at the edge of the lag window %g .. %g: the window moved %d time%s, to %g .. "
                   "%g\n", p->lag_min, p->lag_max, t->fit.lag_moves, t->fit.lag_moves == 1 ? "" : "s", t->fit.lag_min,
                   t->fit.lag_max);
        if (r.refits)
            printf("sync: refitted over the cubes joined across contiguous telemetry files (%d round%s): ratio %.4f "
                   "(own files alone %.4f), lag %.2f (%.2f)\n", r.refits, r.refits == 1 ? "" : "s", t->ratio,
                   r.ratio_first, t->lag, r.lag_first);
        printf("sync: %zu of %zu exposures usable in %zu rows; %zu cube part%s continue%s in the next or previous "
               "telemetry file (checked on the data), %zu exposures straddle a file boundary -> %s\n", r.nexp_ok,
               r.nexp, r.nok, r.ncontinued, r.ncontinued == 1 ? "" : "s", r.ncontinued == 1 ? "s" : "",
               r.nexp - r.nexp_ok - r.nexp_missing, o.out);
        if (r.nmissing)
            fprintf(stderr, "sync: warning: %zu cube%s (%zu exposures) left out, %s telemetry file cannot be read (rows "
                    "marked missing); the first: %s\n", r.nmissing, r.nmissing == 1 ? "" : "s", r.nexp_missing,
                    r.nmissing == 1 ? "its" : "their", r.missing_reason);
    }
    for (size_t i = 0; t->cubes && i < t->ncubes; i++) {
        const swfs_timing_cube *c = &t->cubes[i];
        if (!c->joined) continue;
        char across[160];
        swfs_timing_join_verdict(c, across, sizeof across);
        printf("sync: %s frames %zu-%zu continue in %s: lag offset %+.3f WFS frames, correlations %.3f %.3f, "
               "telemetry across the boundary %s\n", c->camera, c->first, c->first + c->nframes - 1, c->slopes,
               c->join_offset, c->join_corr_x, c->join_corr_y, across);
    }
    free(r.t.cubes);
    return rc ? cli_error(cmd) : CLI_OK;
}

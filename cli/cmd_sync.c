/* specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt: frame-rate ratio and handshake
 * lag by tip-tilt cross-correlation (Sec. 4.2). The work is the library's (run.h: swfs_sync_run). */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt [--ratio-min R] [--ratio-max R]\n"
    "                       [--lag-min L] [--lag-max L] [--ratio-step S] [--lag-step S]\n"
    "\n"
    "Synchronize the science cubes with the WFS telemetry (Codona & Kenworthy 2013, Sec. 4.2).\n"
    "The star's track (TRACK extension written by `specklewfs reduce`) is cross-correlated\n"
    "with the mean x/y WFS slopes averaged over each exposure, over all four pairings of\n"
    "camera and slope axes, while the frame-rate ratio <t_sci/t_wfs> and the handshake lag\n"
    "are varied. Cubes whose exposures leave the telemetry file the handshake names\n"
    "(straddling a file boundary) are marked and not used by `specklewfs speckles`.\n"
    "\n"
    "  SCIENCE.fits     reduced science cube with TRACK and CUBEnnnn keywords\n"
    "  HANDSHAKE.log    lines \"CAMERA_FILE SLOPES_FILE WFS_FRAME\" (docs/telemetry.md); slopes\n"
    "                   files are found relative to the log's folder\n"
    "  -o TIMING.txt    timing table: ratio +- error, lag, axis pairing, one line per cube\n"
    "  --ratio-min/max  search range of <t_sci/t_wfs> (default 2 .. 12)\n"
    "  --lag-min/max    search range of the lag [WFS frames] (default -3 .. 12: the log is written\n"
    "                   after the camera starts). Keep it narrower than the period of a dominant\n"
    "                   vibration: a pure sinusoid makes the lag ambiguous by half periods\n"
    "  --ratio-step, --lag-step  coarse grid (0.01, 0.5), refined 100x around the peak\n";

int swfs_cmd_sync(int argc, char **argv)
{
    const char *cmd = "sync";
    swfs_sync_run_options o;
    swfs_sync_run_options_default(&o);
    swfs_sync_params *p = &o.params;
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o.out, "a file name", 0},         {"--ratio-min", CLI_DOUBLE, &p->ratio_min, NULL, 0},
        {"--ratio-max", CLI_DOUBLE, &p->ratio_max, NULL, 0},  {"--lag-min", CLI_DOUBLE, &p->lag_min, NULL, 0},
        {"--lag-max", CLI_DOUBLE, &p->lag_max, NULL, 0},      {"--ratio-step", CLI_DOUBLE, &p->ratio_step, NULL, 0},
        {"--lag-step", CLI_DOUBLE, &p->lag_step, NULL, 0},
    };
    const char **const pos[] = {&o.science, &o.handshake};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 2, NULL, NULL, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!o.science || !o.handshake) return cli_usage_error(cmd, "needs SCIENCE.fits and HANDSHAKE.log");
    if (!o.out) return cli_usage_error(cmd, "needs -o TIMING.txt");
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
        printf("sync: %zu of %zu cubes usable, %zu straddle a telemetry-file boundary -> %s\n", r.nok, t->ncubes,
               t->ncubes - r.nok, o.out);
    }
    free(r.t.cubes);
    return rc ? cli_error(cmd) : CLI_OK;
}

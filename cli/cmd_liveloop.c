/* specklewfs liveloop: the NCP loop closed in simulation through shared-memory streams
 * (live.h: swfs_live_loop_run): the time-series simulator publishes through `replay`,
 * `live` writes DM offsets into a stream, the simulator reads it for the next data set. */
#include "cli.h"

#include "specklewfs/config.h"
#include "specklewfs/live.h"
#include "specklewfs/status.h"

#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs liveloop [CONFIG] [key=value ...] -o DIR [--iterations N] [--speed F] [--batch B]\n"
    "                           [--gain G] [--max-step M] [--max-rms R] [--influence cubic|gauss]\n"
    "                           [--coupling C] [--modes K] [--pupil-source halo|halo_lf]\n"
    "\n"
    "Closes the NCP loop in simulation through ImageStreamIO streams, as at the telescope:\n"
    "each iteration simulates the AO time series (simulate mode=timeseries; seed + iteration)\n"
    "with its NCP plus twice the DM surface of the offsets in the DM stream, reduces and\n"
    "synchronizes it, publishes it with 'replay' and runs 'live' on the streams, which adds\n"
    "gain x (-WFE/2 fitted onto the actuators) to the DM stream at the end of the data. The\n"
    "reconstructor is built once by 'speckles' from the first iteration. Prints per state the\n"
    "residual NCP (NCP + 2 x DM surface, piston, tip and tilt removed), live's estimate error,\n"
    "the offsets' rms, the frames used and the lag.\n"
    "\n"
    "  -o DIR              output folder (iter_NN/ per iteration, recon.fits, dm_NN.fits)\n"
    "  --iterations N      corrections (default 3)\n"
    "  --speed F           replay F times faster than real time (default 2)\n"
    "  --batch B           live's camera frames per batch (default 16)\n"
    "  --gain G, --max-step M, --max-rms R   as live's --dm-gain (0.5), --dm-max-step, --dm-max-rms\n"
    "  --influence cubic|gauss, --coupling C, --modes K   the DM fit (default cubic: the\n"
    "                      simulator's DM is the Clough-Tocher surface of its actuators)\n"
    "  --pupil-source      live's pupil product from HALO (default) or HALO_LF\n"
    "CONFIG and key=value set the simulation (config/mmt-clio.conf; mode=timeseries implied).\n";

static volatile sig_atomic_t stop_flag = 0;
static void on_signal(int sig)
{
    (void)sig;
    stop_flag = 1;
}

static int parse(int argc, char **argv, swfs_config *cfg, swfs_live_loop_options *o, const char **cfgfile)
{
    const char *cmd = "liveloop";
    long iters = (long)o->iterations, batch = (long)o->batch, modes = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        double *dv = NULL;
        long *lv = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return -1; }
        else if (!strcmp(a, "-o")) { if (!v) return cli_usage_error(cmd, "-o needs a folder"); o->dir = v; i++; continue; }
        else if (!strcmp(a, "--iterations")) lv = &iters;
        else if (!strcmp(a, "--batch")) lv = &batch;
        else if (!strcmp(a, "--modes")) lv = &modes;
        else if (!strcmp(a, "--speed")) dv = &o->speed;
        else if (!strcmp(a, "--gain")) dv = &o->gain;
        else if (!strcmp(a, "--max-step")) dv = &o->max_step;
        else if (!strcmp(a, "--max-rms")) dv = &o->max_rms;
        else if (!strcmp(a, "--coupling")) dv = &o->dmfit.coupling;
        else if (!strcmp(a, "--influence") || !strcmp(a, "--pupil-source")) {
            const char *x = v ? v : "";
            i++;
            if (!strcmp(a, "--influence") && !strcmp(x, "gauss")) o->dmfit.influence = SWFS_INFLUENCE_GAUSS;
            else if (!strcmp(a, "--influence") && !strcmp(x, "cubic")) o->dmfit.influence = SWFS_INFLUENCE_CUBIC;
            else if (!strcmp(a, "--pupil-source") && !strcmp(x, "halo")) o->pupil_source = SWFS_SOURCE_HALO;
            else if (!strcmp(a, "--pupil-source") && !strcmp(x, "halo_lf")) o->pupil_source = SWFS_SOURCE_HALO_LF;
            else return cli_usage_error(cmd, "%s: unknown value '%s'", a, x);
            continue;
        } else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (strchr(a, '=')) {
            if (swfs_config_set(cfg, a)) return cli_error(cmd);
            continue;
        } else if (!*cfgfile) {
            *cfgfile = a;
            continue;
        } else return cli_usage_error(cmd, "more than one config file ('%s')", a);
        if (lv ? cli_parse_long(cmd, a, v, lv) : cli_parse_double(cmd, a, v, dv)) return CLI_USAGE;
        i++;
    }
    if (!o->dir) return cli_usage_error(cmd, "needs -o DIR");
    if (iters < 1 || iters > SWFS_LIVE_LOOP_MAX) return cli_usage_error(cmd, "--iterations must be 1..%d", SWFS_LIVE_LOOP_MAX);
    if (batch < 1 || batch > 100000) return cli_usage_error(cmd, "--batch must be 1..100000");
    if (modes < 0 || modes > 5000) return cli_usage_error(cmd, "--modes must be 0..5000");
    if (!(o->speed > 0) || !(o->gain > 0 && o->gain <= 1) || !(o->max_step >= 0) || !(o->max_rms >= 0) ||
        !(o->dmfit.coupling > 0 && o->dmfit.coupling < 1))
        return cli_usage_error(cmd, "--speed > 0, --gain in (0, 1], --max-step and --max-rms >= 0, --coupling in (0, 1)");
    o->iterations = (size_t)iters;
    o->batch = (size_t)batch;
    o->dmfit.modes = (size_t)modes;
    return 0;
}

int swfs_cmd_liveloop(int argc, char **argv)
{
    const char *cmd = "liveloop", *cfgfile = NULL;
    swfs_live_loop_options o;
    swfs_live_loop_options_default(&o);
    swfs_config *cfg = swfs_config_new();
    if (!cfg) return cli_error(cmd);
    int rc = parse(argc, argv, cfg, &o, &cfgfile);
    if (rc) {
        swfs_config_free(cfg);
        return rc < 0 ? CLI_OK : rc;
    }
    if (!rc) rc = cli_ts_params(cmd, cfgfile, cfg, &o.sim, NULL, NULL, NULL, NULL);
    if (!rc) rc = cli_make_dir(cmd, o.dir);
    if (rc) {
        swfs_config_free(cfg);
        return rc;
    }
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.stop = &stop_flag;
    o.progress = cli_stage_progress;
    o.progress_ctx = (void *)"liveloop:";
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    swfs_live_loop_result r;
    rc = swfs_live_loop_run(&o, &r);
    swfs_config_free(cfg);
    if (rc) return cli_error(cmd);
    printf("liveloop: %s: %zu corrections through streams (gain %.2f, %s influence, replay x%.3g, batch %zu) in %.1f s\n",
           o.dir, r.nstates - 1, o.gain, o.dmfit.influence == SWFS_INFLUENCE_CUBIC ? "cubic" : "Gaussian", o.speed,
           o.batch, r.seconds);
    printf("  %4s %12s %12s %10s %8s %10s %10s\n", "iter", "residual", "est. error", "DM rms", "frames", "lag med",
           "lag 99%");
    printf("  %4s %12s %12s %10s %8s %10s %10s\n", "", "[nm, -PTT]", "[nm, -PTT]", "[nm]", "used", "[ms]", "[ms]");
    for (size_t k = 0; k < r.nstates; k++) {
        const swfs_live_loop_state *s = &r.s[k];
        printf("  %4zu %12.1f", k, 1e9 * s->residual_rms);
        if (isfinite(s->estimate_err))
            printf(" %12.1f %10.1f %8zu %10.1f %10.1f\n", 1e9 * s->estimate_err, 1e9 * s->dm_rms, s->frames_used,
                   1e3 * s->lag_median, 1e3 * s->lag_p99);
        else
            printf(" %12s %10.1f %8s %10s %10s\n", "-", 1e9 * s->dm_rms, "-", "-", "-");
    }
    return CLI_OK;
}

/* specklewfs live: WFS and camera shared-memory streams in, HALO/PUPIL products (and DM
 * offsets into a stream) out, beside a running AO system. The whole path is the
 * library's (live.h: swfs_live_run); this file parses the options, installs the
 * SIGINT/SIGTERM handlers that end the run cleanly and prints the summary. */
#include "cli.h"

#include "specklewfs/live.h"
#include "specklewfs/status.h"

#include <math.h>
#include <limits.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>

static volatile sig_atomic_t stop_flag = 0;
static void on_signal(int sig)
{
    (void)sig;
    stop_flag = 1;
}

static int parse(int argc, char **argv, swfs_live_options *o, const char **wfs, size_t *nwfs)
{
    const char *cmd = "live", *stat = "auto";
    long every = 0, threads = o->run.threads, batch = (long)o->src.sync.batch, max_frames = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], **str = NULL;
        long *lv = NULL;
        double *dv = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { cli_help_live(); return -1; }
        const int lk = cli_linear_option(cmd, argc, argv, &i, &o->run.lin);
        if (lk) { if (lk < 0) return -lk; continue; }
        const int bk = cli_band_option(cmd, argc, argv, &i, &o->run.band);
        if (bk) { if (bk < 0) return -bk; continue; }
        else if (!strcmp(a, "--wfs")) {
            if (*nwfs >= SWFS_FRAMESYNC_MAX_WFS) return cli_usage_error(cmd, "at most %d --wfs streams", SWFS_FRAMESYNC_MAX_WFS);
            str = &wfs[(*nwfs)++];
        }
        else if (!strcmp(a, "--camera")) str = &o->src.camera;
        else if (!strcmp(a, "--shm-dir")) str = &o->src.dir;
        else if (!strcmp(a, "--geom")) str = &o->run.science;
        else if (!strcmp(a, "--recon")) str = &o->run.recon;
        else if (!strcmp(a, "--actuators")) str = &o->run.actuators;
        else if (!strcmp(a, "-o")) str = &o->run.out;
        else if (!strcmp(a, "--pupil-out")) str = &o->run.pupil_out;
        else if (!strcmp(a, "--checkpoint")) str = &o->run.checkpoint;
        else if (!strcmp(a, "--static")) str = &stat;
        else if (!strcmp(a, "--static-out")) str = &o->run.static_out;
        else if (!strcmp(a, "--pupil")) str = &o->run.mask;
        else if (!strcmp(a, "--valid")) str = &o->run.valid;
        else if (!strcmp(a, "--dm-out")) str = &o->dm_out;
        else if (!strcmp(a, "--dm-file")) str = &o->dm_file;
        else if (!strcmp(a, "--every")) lv = &every;
        else if (!strcmp(a, "--threads")) lv = &threads;
        else if (!strcmp(a, "--batch")) lv = &batch;
        else if (!strcmp(a, "--max-frames")) lv = &max_frames;
        else if (!strcmp(a, "--every-seconds")) dv = &o->run.stream.every_seconds;
        else if (!strcmp(a, "--read-noise")) dv = &o->run.read_noise;
        else if (!strcmp(a, "--gain")) dv = &o->run.gain;
        else if (!strcmp(a, "--g-smooth")) dv = &o->run.g_smooth_lod;
        else if (!strcmp(a, "--max-wait")) dv = &o->src.sync.max_wait;
        else if (!strcmp(a, "--exptime")) dv = &o->src.sync.exptime;
        else if (!strcmp(a, "--timeout")) dv = &o->src.timeout;
        else if (!strcmp(a, "--idle-exit")) dv = &o->src.idle;
        else if (!strcmp(a, "--poll")) dv = &o->src.poll;
        else if (!strcmp(a, "--dm-gain")) dv = &o->dm_gain;
        else if (!strcmp(a, "--dm-max-step")) dv = &o->dm_max_step;
        else if (!strcmp(a, "--dm-max-rms")) dv = &o->dm_max_rms;
        else if (!strcmp(a, "--dm-scale")) dv = &o->dm_scale;
        else if (!strcmp(a, "--dm-settle")) dv = &o->dm_settle;
        else if (!strcmp(a, "--coupling")) dv = &o->dmfit.coupling;
        else if (!strcmp(a, "--pitch")) dv = &o->dmfit.pitch;
        else if (!strcmp(a, "--reg")) dv = &o->dmfit.reg;
        else if (!strcmp(a, "--mean-loop")) {
            static const char *loops[CLI_MAX_MEAN_LOOPS];
            if (i + 1 >= argc) return cli_usage_error(cmd, "--mean-loop needs a folder of a simulated loop");
            if (!strcmp(argv[i + 1], "none")) { o->run.mean_teach = 0; ++i; continue; }
            if (!strcmp(argv[i + 1], "teach")) { o->run.mean_teach = 1; ++i; continue; } /* refused: no files */
            if (o->run.nmean_loops == CLI_MAX_MEAN_LOOPS) return cli_usage_error(cmd, "at most %d --mean-loop", CLI_MAX_MEAN_LOOPS);
            loops[o->run.nmean_loops++] = argv[++i];
            o->run.mean_loops = loops;
            continue;
        }
        else if (!strcmp(a, "--dm-keep")) { o->dm_keep = 1; continue; }
        else if (!strcmp(a, "--dm-final")) { o->dm_final = 1; continue; }
        else if (!strcmp(a, "--dm-tiptilt")) { o->dm_tiptilt = 1; continue; }
        else if (!strcmp(a, "--pupil-source")) {
            const char *v = i + 1 < argc ? argv[++i] : "";
            if (!strcmp(v, "halo")) o->run.pupil_source = SWFS_SOURCE_HALO;
            else if (!strcmp(v, "halo_lf")) o->run.pupil_source = SWFS_SOURCE_HALO_LF;
            else return cli_usage_error(cmd, "--pupil-source expects 'halo' or 'halo_lf', got '%s'", v);
            continue;
        }
        else if (!strcmp(a, "--modes")) {
            long k;
            if (cli_parse_long(cmd, a, i + 1 < argc ? argv[++i] : NULL, &k)) return CLI_USAGE;
            if (k < 0 || k > 5000) return cli_usage_error(cmd, "--modes must be 0..5000, got %ld", k);
            o->dmfit.modes = (size_t)k;
            continue;
        } else if (!strcmp(a, "--influence")) {
            const char *v = i + 1 < argc ? argv[++i] : "";
            if (!strcmp(v, "gauss")) o->dmfit.influence = SWFS_INFLUENCE_GAUSS;
            else if (!strcmp(v, "cubic")) o->dmfit.influence = SWFS_INFLUENCE_CUBIC;
            else return cli_usage_error(cmd, "--influence expects 'gauss' or 'cubic', got '%s'", v);
            continue;
        } else if (!strcmp(a, "--tiptilt")) {
            if (cli_parse_tiptilt(cmd, i + 1 < argc ? argv[++i] : NULL, &o->run.tiptilt)) return CLI_USAGE;
            continue;
        } else return cli_usage_error(cmd, "unknown argument '%s'", a);
        const char *v = i + 1 < argc ? argv[++i] : NULL;
        if (str) {
            if (!v) return cli_usage_error(cmd, "%s needs a value", a);
            *str = v;
        } else if (lv ? cli_parse_long(cmd, a, v, lv) : cli_parse_double(cmd, a, v, dv)) {
            return CLI_USAGE;
        }
    }
    /* Signs here; the library checks the rest (live.h swfs_live_options_check). */
    const cli_min mins[] = {{"--every", every, 0}, {"--max-frames", max_frames, 0}, {"--threads", threads, 1},
                            {"--batch", batch, 1}};
    if (cli_check_mins(cmd, mins, CLI_NOPTS(mins))) return CLI_USAGE;
    o->run.stream.every = (size_t)every;
    o->run.stream.max_frames = (size_t)max_frames;
    o->run.threads = threads > INT_MAX ? INT_MAX : (int)threads;
    o->src.sync.batch = (size_t)batch;
    o->run.stream.static_mode = !strcmp(stat, "auto") ? SWFS_STATIC_AUTO : (!strcmp(stat, "none") ? SWFS_STATIC_NONE : SWFS_STATIC_GIVEN);
    o->run.static_file = o->run.stream.static_mode == SWFS_STATIC_GIVEN ? stat : NULL;
    o->src.wfs = wfs;
    o->src.nwfs = *nwfs;
    return cli_check(cmd, swfs_live_options_check(o));
}

static void on_update(void *ctx, const swfs_stream *s, const swfs_halo *h, const swfs_pupil_result *pr, int final)
{
    (void)ctx;
    (void)final;
    const size_t cam = swfs_stream_camera_frames(s);
    if (!h) {
        fprintf(stderr, "live: %zu camera frames: no estimate yet (%s)\n", cam, swfs_last_error());
        return;
    }
    fprintf(stderr, "live: %zu camera frames (%.0f WFS frames): valid %.1f %%, median SNR %.3g", cam,
            swfs_stream_wfs_frames(s), 100.0 * h->valid_fraction, h->median_snr);
    if (pr) fprintf(stderr, ", pupil WFE rms %.1f nm", 1e9 * pr->wfe_rms);
    fputc('\n', stderr);
}

int swfs_cmd_live(int argc, char **argv)
{
    const char *cmd = "live";
    swfs_live_options o;
    swfs_live_options_default(&o);
    const char *wfs[SWFS_FRAMESYNC_MAX_WFS];
    size_t nwfs = 0;
    int prc = parse(argc, argv, &o, wfs, &nwfs);
    if (prc < 0) return CLI_OK;
    if (prc) return prc;
    o.src.stop = &stop_flag;
    o.run.prov = cli_provenance(argc, argv, &o.run.nprov);
    o.run.on_update = on_update;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal;
    sigaction(SIGINT, &sa, NULL);
    sigaction(SIGTERM, &sa, NULL);
    swfs_live_result r;
    const int rc = swfs_live_run(&o, &r);
    const swfs_framesync_stats *y = &r.src.sync;
    if (y->camera_received || y->wfs_received)
        fprintf(stderr, "live: received %llu WFS frames (%llu dropped, %llu restarts) and %llu camera frames (%llu dropped, "
                "%llu restarts); skipped exposures: %llu incomplete, %llu without WFS data, %llu settling, %llu overrun\n",
                (unsigned long long)y->wfs_received, (unsigned long long)y->wfs_dropped,
                (unsigned long long)y->wfs_restarts, (unsigned long long)y->camera_received,
                (unsigned long long)y->camera_dropped, (unsigned long long)y->camera_restarts,
                (unsigned long long)y->incomplete, (unsigned long long)y->no_wfs, (unsigned long long)y->unsettled,
                (unsigned long long)y->overrun);
    if (rc) return cli_error(cmd);
    if (r.run.info.nlags > 1) {
        const long lmax = cli_spacetime_lags(cmd, r.run.st_lags, r.run.info.nlags);
        fprintf(stderr, ": each batch waited for the WFS frames %ld after its last\n", lmax);
    }
    cli_meanmiss_summary(cmd, o.run.nmean_loops, r.run.meanmiss_heldout, r.run.meanmiss_rms);
    printf("live: %s: %llu camera frames used in %llu batches, %.0f WFS frames; %.2f s of data; WFS %.1f Hz, camera %.2f Hz",
           o.run.out, (unsigned long long)y->used, (unsigned long long)y->batches, r.run.wfs_frames, r.src.seconds,
           y->wfs_period > 0 ? 1.0 / y->wfs_period : 0.0, y->camera_period > 0 ? 1.0 / y->camera_period : 0.0);
    if (r.src.lag_count)
        printf("; lag median %.1f ms, 99%% %.1f ms, max %.1f ms", 1e3 * r.src.lag_median, 1e3 * r.src.lag_p99,
               1e3 * r.src.lag_max);
    printf("; processing %.0f WFS frames/s\n", r.run.seconds > 0 ? r.run.wfs_frames / r.run.seconds : 0.0);
    if (o.dm_out)
        printf("live: %zu DM updates to %s (last step %.2f nm rms, total %.2f nm rms of surface)\n", r.dm_updates,
               o.dm_out, 1e9 * r.dm_step_rms, 1e9 * r.dm_total_rms);
    return CLI_OK;
}

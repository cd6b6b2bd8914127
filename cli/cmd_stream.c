/* specklewfs stream: WFS slopes + camera frames in time order -> HALO.fits updated as
 * the data arrive (the real-time path; design in docs/streaming.md). The whole path is the
 * library's (run.h: swfs_stream_run_files over stream.h, pipeline.h and the file source of
 * source.h); this file parses the options and prints the progress lines. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The tip-tilt options; anything else left over is an unknown argument. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    swfs_stream_run_options *o = ctx;
    const char *a = argv[*i];
    const int gk = cli_geom_option("stream", argc, argv, i, &o->geom);
    if (gk) return gk;
    const int lk = cli_linear_option("stream", argc, argv, i, &o->lin);
    if (lk) return lk;
    const int bk = cli_band_option("stream", argc, argv, i, &o->band);
    if (bk) return bk;
    static const char *logs[SWFS_FRAMESYNC_MAX_WFS];
    if (!strcmp(a, "--wfs-log")) {
        const char *v = cli_next(argc, argv, i);
        if (!v) return -cli_usage_error("stream", "--wfs-log needs a folder or file");
        if (o->nwfs_logs == SWFS_FRAMESYNC_MAX_WFS) return -cli_usage_error("stream", "at most %d --wfs-log", SWFS_FRAMESYNC_MAX_WFS);
        logs[o->nwfs_logs++] = v;
        o->wfs_logs = logs;
    } else if (!strcmp(a, "--mean-loop")) {
        static const char *loops[CLI_MAX_MEAN_LOOPS];
        const char *v = cli_next(argc, argv, i);
        if (!v) return -cli_usage_error("stream", "--mean-loop needs a folder of a simulated loop, teach or none");
        if (!strcmp(v, "teach")) { o->mean_teach = 1; return 1; } /* loops stream simulates itself */
        if (!strcmp(v, "none")) { o->mean_teach = 0; return 1; }  /* not even a pyramid's default */
        if (o->nmean_loops == CLI_MAX_MEAN_LOOPS) return -cli_usage_error("stream", "at most %d --mean-loop", CLI_MAX_MEAN_LOOPS);
        loops[o->nmean_loops++] = v;
        o->mean_loops = loops;
    } else if (!strcmp(a, "--teach-again")) o->teach_again = 1;
    else if (!strcmp(a, "--keep-tiptilt")) o->tiptilt = SWFS_TT_KEEP;
    else if (!strcmp(a, "--tiptilt")) { if (cli_parse_tiptilt("stream", cli_next(argc, argv, i), &o->tiptilt)) return -CLI_USAGE; }
    else if (!strcmp(a, "--pupil-method")) {
        if (cli_parse_choice("stream", a, cli_next(argc, argv, i), "fit", SWFS_PUPIL_FIT, "moments", SWFS_PUPIL_MOMENTS,
                             &o->pupil_method))
            return -CLI_USAGE;
    } else return -cli_usage_error("stream", "unknown argument '%s'", a);
    return 1;
}

static int parse(int argc, char **argv, swfs_stream_run_options *o)
{
    const char *cmd = "stream";
    const char *stat = "auto";
    long every = 0, threads = o->threads, batch = (long)o->batch, max_frames = 0, mloops = (long)o->mean_teach_loops,
         mmax = (long)o->mean_teach_max_loops;
    const char *v = "a value";
    const cli_opt opts[] = {
        {"--timing", CLI_STRING, &o->timing, v, 0},       {"--science", CLI_STRING, &o->science, v, 0},
        {"--slopes", CLI_STRING, &o->slopes, v, 0},       {"--recon", CLI_STRING, &o->recon, v, 0},
        {"--actuators", CLI_STRING, &o->actuators, v, 0}, {"-o", CLI_STRING, &o->out, v, 0},
        {"--pupil-out", CLI_STRING, &o->pupil_out, v, 0}, {"--checkpoint", CLI_STRING, &o->checkpoint, v, 0},
        {"--static", CLI_STRING, &stat, v, 0},            {"--pupil", CLI_STRING, &o->mask, v, 0},
        {"--static-out", CLI_STRING, &o->static_out, v, 0}, {"--every", CLI_LONG, &every, NULL, 0},
        {"--threads", CLI_LONG, &threads, NULL, 0},       {"--batch", CLI_LONG, &batch, NULL, 0},
        {"--max-frames", CLI_LONG, &max_frames, NULL, 0}, {"--every-seconds", CLI_DOUBLE, &o->stream.every_seconds, NULL, 0},
        {"--read-noise", CLI_DOUBLE, &o->read_noise, NULL, 0}, {"--gain", CLI_DOUBLE, &o->gain, NULL, 0},
        {"--g-smooth", CLI_DOUBLE, &o->g_smooth_lod, NULL, 0}, {"--clock", CLI_STRING, &o->clock, v, 0},
        {"--exptime", CLI_DOUBLE, &o->exptime, NULL, 0}, {"--valid", CLI_STRING, &o->valid, v, 0},
        {"--teach-work", CLI_STRING, &o->teach_work, v, 0}, {"--mean-teach-loops", CLI_LONG, &mloops, NULL, 0},
        {"--mean-teach-max-loops", CLI_LONG, &mmax, NULL, 0},
    };
    for (int i = 1; i < argc; i++)
        if (cli_is_help(argv[i])) {
            cli_help_stream();
            return -1;
        }
    const cli_args args = {cmd, NULL, opts, CLI_NOPTS(opts), NULL, 0, special, o, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc;
    /* Signs here; the library checks the rest (run.h swfs_stream_run_options_check). */
    const cli_min mins[] = {{"--every", every, 0}, {"--max-frames", max_frames, 0}, {"--threads", threads, 1},
                            {"--batch", batch, 1}, {"--mean-teach-loops", mloops, 0}, {"--mean-teach-max-loops", mmax, 0}};
    if (cli_check_mins(cmd, mins, CLI_NOPTS(mins))) return CLI_USAGE;
    o->mean_teach_loops = (size_t)mloops;
    o->mean_teach_max_loops = (size_t)mmax;
    o->stream.every = (size_t)every;
    o->stream.max_frames = (size_t)max_frames;
    o->threads = threads > INT_MAX ? INT_MAX : (int)threads;
    o->batch = (size_t)batch;
    o->stream.static_mode = !strcmp(stat, "auto") ? SWFS_STATIC_AUTO : (!strcmp(stat, "none") ? SWFS_STATIC_NONE : SWFS_STATIC_GIVEN);
    o->static_file = o->stream.static_mode == SWFS_STATIC_GIVEN ? stat : NULL;
    return cli_check(cmd, swfs_stream_run_options_check(o));
}

/* One line per product update on stderr. */
static void on_update(void *ctx, const swfs_stream *s, const swfs_halo *h, const swfs_pupil_result *pr, int final)
{
    const double t0 = *(const double *)ctx, elapsed = cli_now() - t0, wfs = swfs_stream_wfs_frames(s);
    /* A team's one update holds the merged accumulators: its frames are the whole data set's. */
    const size_t cam = h ? (size_t)h->frames : swfs_stream_camera_frames(s);
    (void)final;
    if (!h) {
        fprintf(stderr, "stream: %zu camera frames: no estimate yet (%s)\n", cam, swfs_last_error());
        return;
    }
    if (cam == swfs_stream_camera_frames(s))
        fprintf(stderr, "stream: %zu camera frames (%.0f WFS frames, %.0f/s): valid %.1f %%, median SNR %.3g", cam, wfs,
                elapsed > 0 ? wfs / elapsed : 0.0, 100.0 * h->valid_fraction, h->median_snr);
    else /* this process saw only its share: the rate is in the summary */
        fprintf(stderr, "stream: %zu camera frames of all processes: valid %.1f %%, median SNR %.3g", cam,
                100.0 * h->valid_fraction, h->median_snr);
    if (pr) fprintf(stderr, ", pupil WFE rms %.1f nm", 1e9 * pr->wfe_rms);
    if (pr && pr->resmean) fprintf(stderr, " (AO residual mean %.1f nm out)", 1e9 * pr->resmean_rms);
    fputc('\n', stderr);
}

int swfs_cmd_stream(int argc, char **argv)
{
    const char *cmd = "stream";
    swfs_stream_run_options o;
    swfs_stream_run_options_default(&o);
    int prc = parse(argc, argv, &o);
    if (prc < 0) return CLI_OK;
    if (prc) return prc;
    const double t_start = cli_now();
    if (cli_team_join(cmd, &o.team)) return CLI_FAIL;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    double t0 = cli_now();
    o.on_update = cli_writer() ? on_update : NULL;
    o.update_ctx = &t0;
    o.progress = cli_stop_check; /* SIGINT/SIGTERM stop a run from files (its updates removed) */
    swfs_stream_run_result r;
    if (swfs_stream_run_files(&o, &r)) return cli_writer() ? cli_error(cmd) : CLI_FAIL;
    if (!cli_writer()) return CLI_OK;
    if (o.lin.basis) cli_linear_summary(cmd, &o.lin, &r.info);
    cli_band_summary(cmd, &r.info, o.band > 0);
    if (r.info.n_outside)
        fprintf(stderr, "specklewfs %s: warning: %zu illuminated pupil samples lie outside the actuators' hull (phase 0 "
                "there)\n", cmd, r.info.n_outside);
    if (r.info.nlags > 1) {
        cli_spacetime_lags(cmd, r.st_lags, r.info.nlags);
        fprintf(stderr, ": each frame's slopes stacked with those at the lags\n");
        cli_spacetime_edges(cmd, r.st_edges_joined, r.st_edges_clamped, r.st_edges_unreadable, r.st_edges_why);
    }
    cli_mean_teach_summary(cmd, &r.mean_teach);
    cli_meanmiss_summary(cmd, r.mean_teach.done ? r.mean_teach.nloops : o.nmean_loops, r.meanmiss_heldout,
                         r.meanmiss_rms);
    if (isfinite(r.static_scale))
        fprintf(stderr, "stream: static halo S^1/2 Psi_0 with S^1/2 = %.4g (per unit exposure weight %.4g)\n",
                r.static_scale, r.static_scale / r.ratio);
    const double total = cli_now() - t_start, rate = r.wfs_frames / total;
    printf("stream: %s: %zu camera frames, %.0f WFS frames in %.2f s; processing %.0f WFS frames/s on %d threads", o.out,
           r.camera_frames, r.wfs_frames, total, rate, o.threads);
    if (swfs_team_active(o.team)) printf(" x %d processes", o.team->size);
    if (r.wfs_rate > 0) printf(" = %.1f x real time (WFSRATE %.0f Hz)", rate / r.wfs_rate, r.wfs_rate);
    printf("\n");
    const swfs_framesync_stats *f = &r.stamps.sync;
    if (r.stamped)
        printf("stream: time stamps: %llu camera frames used of %llu, exposure %.6g ms; dropped %llu camera and %llu WFS "
               "frames; skipped %llu incomplete, %llu outside the WFS data\n", (unsigned long long)f->used,
               (unsigned long long)f->camera_received, 1e3 * r.stamps.exptime, (unsigned long long)f->camera_dropped,
               (unsigned long long)f->wfs_dropped, (unsigned long long)f->incomplete, (unsigned long long)f->no_wfs);
    return CLI_OK;
}

/* specklewfs stream: WFS slopes + camera frames in time order -> HALO.fits updated as
 * the data arrive (the real-time path; design in docs/streaming.md). The whole path is the
 * library's (run.h: swfs_stream_run_files over stream.h, pipeline.h and the file source of
 * source.h); this file parses the options and prints the progress lines. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs stream --timing TIMING.txt --science SCIENCE.fits [--slopes DIR|FILE]\n"
    "                         | --wfs-log DIR|FILE [--wfs-log ...] [--clock CLOCK.txt] [--exptime T]\n"
    "                         --recon RECON.fits --actuators ACT.fits -o HALO.fits\n"
    "                         [--pupil-out PUPIL.fits] [--every K] [--every-seconds T]\n"
    "                         [--threads N] [--checkpoint FILE] [--static auto|none|HALO0.fits]\n"
    "                         [--static-out FILE] [--pupil MASK.fits] [--tiptilt exposure|frame|keep]\n"
    "                         [--batch B]\n"
    "                         [--max-frames N]\n"
    "                         [--read-noise SIGMA] [--gain G] [--g-smooth L]\n"
    "\n"
    "The whole real-time path in one pass (Codona & Kenworthy 2013, Sec. 4): WFS slopes ->\n"
    "reconstructed wavefront -> pupil field summed over each camera exposure -> focal field\n"
    "(one MFT per camera frame), core-phase referenced (eq:downsampledHalo), minus a static\n"
    "halo (eq:computedSpeckleField) -> per-pixel accumulators against the camera frames.\n"
    "HALO.fits is rewritten (atomically) every K camera frames and/or T seconds and at the\n"
    "end; progress, valid fraction and median SNR go to stderr. Memory does not grow with\n"
    "the number of frames (one telemetry file and one batch are held at a time).\n"
    "\n"
    "  --timing TIMING.txt   ratio and per-cube exposure starts from 'specklewfs sync'; cubes\n"
    "                        marked 'straddles' are skipped\n"
    "  --science FILE        reduced science cube ('specklewfs reduce'): frames, geometry\n"
    "                        keywords, RDNOISE / GAIN\n"
    "  --slopes DIR|FILE     folder holding the telemetry files the timing table names, or\n"
    "                        one telemetry file used for every cube (default: the timing\n"
    "                        table's folder; absolute names in the table are used as they are)\n"
    "  --recon, --actuators  reconstructor (nact x nslopes [m/rad]) and actuator positions\n"
    "  -o HALO.fits          the estimate (extensions as 'specklewfs estimate')\n"
    "  --pupil-out FILE      also the pupil field / NCP map at every update ('specklewfs pupil')\n"
    "  --pupil-method M      fit (the default when possible) or moments, as 'pupil --method'\n"
    "  --every K             update after every K camera frames (default: only at the end)\n"
    "  --every-seconds T     update when T seconds have passed since the last one\n"
    "  --threads N           engine workers (default 2)\n"
    "  --checkpoint FILE     save the accumulators at every update ('specklewfs merge')\n"
    "  --static auto         (default) the paper's choice: S^1/2 Psi_0, the unaberrated halo\n"
    "                        scaled by the mean core amplitude of the first batch, fixed\n"
    "                        from then on; none: no subtraction; or a complex image file\n"
    "                        (e.g. the HALO extension of an earlier run). A constant offset\n"
    "                        does not bias the estimate: the accumulators remove the\n"
    "                        data-set mean of psi exactly (eq:zeroMean) -- but runs whose\n"
    "                        checkpoints will be merged must share it: save it from the\n"
    "                        first with --static-out and give it to the others\n"
    "  --static-out FILE     write the static halo used (complex image)\n"
    "  --pupil MASK.fits     pupil transmission (PUPN x PUPN; default: annulus from TELDIAM,\n"
    "                        OBSCUR)\n"
    "  --tiptilt MODE        as in 'specklewfs speckles': exposure (default) removes from every\n"
    "                        WFS frame the weighted mean x/y slope of its exposure and keeps\n"
    "                        the motion within it, as registered science frames have it;\n"
    "                        frame removes every frame's own mean slopes (the paper's Sec.\n"
    "                        4.4); keep removes nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt        same as --tiptilt keep\n"
    "  --batch B             camera frames per batch (default 128)\n"
    "  --max-frames N        stop after N camera frames\n"
    "  --read-noise, --gain  noise model for the estimate (default: science header)\n";
static const char *usage_mpi =
    "  --valid MAP.fits      the valid-subaperture map the reconstructor was made with\n"
    "                        ('speckles --valid'): slopes of the used subapertures only\n"
    "  --g-smooth L          scale-factor regularization [lambda/D] as in 'specklewfs estimate'\n"
    "                        (default 2; 0 = the paper's per-pixel g)\n"
    "  --wfs-log DIR|FILE    instead of --timing: a WFS milk log (folder of NAME_hh:mm:ss.s.fits[.fz]\n"
    "                        + .txt, or one file); several are concatenated into one slope vector.\n"
    "                        The science cube's STAMPS (reduce of camera logs) place every exposure\n"
    "                        [stamp - T, stamp] on the WFS frames (docs/telemetry.md)\n"
    "  --clock CLOCK.txt     camera clock offset, drift and pairing from 'sync --wfs-log'\n"
    "  --exptime T           camera exposure [s] (default: STAMPS' EXPTIME, else the frame period)\n"
    CLI_GEOM_HELP
    CLI_BAND_HELP
    CLI_LINEAR_HELP
    "\n"
    "Under mpirun (srun) every process streams a share of the camera frames (cut at --batch\n"
    "boundaries) and rank 0 writes the products once, at the end, from the merged\n"
    "accumulators: the single-process products. --every/--every-seconds do not apply.\n"
    "See docs/cluster.md.\n";

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
    } else if (!strcmp(a, "--keep-tiptilt")) o->tiptilt = SWFS_TT_KEEP;
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
    long every = 0, threads = o->threads, batch = (long)o->batch, max_frames = 0;
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
    };
    for (int i = 1; i < argc; i++)
        if (cli_is_help(argv[i])) { /* the usage is two strings */
            fputs(usage_text, stdout);
            fputs(usage_mpi, stdout);
            return -1;
        }
    const cli_args args = {cmd, NULL, opts, CLI_NOPTS(opts), NULL, 0, special, o, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc;
    if ((!o->timing == !o->nwfs_logs) || !o->science || !((o->recon && o->actuators) || o->lin.basis) || !o->out)
        return cli_usage_error(cmd, "needs --timing or --wfs-log (one of them), --science, --recon and --actuators (or "
                               "--basis) and -o");
    if (o->lin.basis && (o->recon || o->actuators || o->valid))
        return cli_usage_error(cmd, "--basis (the linear model) takes no --recon, --actuators or --valid");
    if ((o->clock || o->exptime != 0) && !o->nwfs_logs) return cli_usage_error(cmd, "--clock and --exptime go with --wfs-log");
    if (!(o->exptime >= 0)) return cli_usage_error(cmd, "--exptime must be >= 0 s, got %g", o->exptime);
    if (every < 0) return cli_usage_error(cmd, "--every must be >= 0, got %ld", every);
    if (o->stream.every_seconds < 0) return cli_usage_error(cmd, "--every-seconds must be >= 0, got %g", o->stream.every_seconds);
    if (threads < 1 || threads > SWFS_ENGINE_MAX_THREADS)
        return cli_usage_error(cmd, "--threads must be 1..%d, got %ld", SWFS_ENGINE_MAX_THREADS, threads);
    if (batch < 1 || batch > 100000) return cli_usage_error(cmd, "--batch must be 1..100000, got %ld", batch);
    if (max_frames < 0) return cli_usage_error(cmd, "--max-frames must be >= 0");
    if (!isnan(o->read_noise) && o->read_noise < 0) return cli_usage_error(cmd, "--read-noise must be >= 0");
    if (!isnan(o->gain) && o->gain < 0) return cli_usage_error(cmd, "--gain must be >= 0");
    if (!(o->g_smooth_lod >= 0)) return cli_usage_error(cmd, "--g-smooth must be >= 0, got %g", o->g_smooth_lod);
    o->stream.every = (size_t)every;
    o->stream.max_frames = (size_t)max_frames;
    o->threads = (int)threads;
    o->batch = (size_t)batch;
    o->stream.static_mode = !strcmp(stat, "auto") ? SWFS_STATIC_AUTO : (!strcmp(stat, "none") ? SWFS_STATIC_NONE : SWFS_STATIC_GIVEN);
    o->static_file = o->stream.static_mode == SWFS_STATIC_GIVEN ? stat : NULL;
    return 0;
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
    swfs_stream_run_result r;
    if (swfs_stream_run_files(&o, &r)) return cli_writer() ? cli_error(cmd) : CLI_FAIL;
    if (!cli_writer()) return CLI_OK;
    if (o.lin.basis) cli_linear_summary(cmd, &o.lin, &r.info);
    cli_band_summary(cmd, &r.info, o.band > 0);
    if (r.info.n_outside)
        fprintf(stderr, "specklewfs %s: warning: %zu illuminated pupil samples lie outside the actuators' hull (phase 0 "
                "there)\n", cmd, r.info.n_outside);
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

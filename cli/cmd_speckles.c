/* specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits:
 * the speckle cube from WFS slopes that matches the reduced science cube frame for frame
 * (Sec. 4.4, eq:downsampledHalo, eq:computedSpeckleField); with --wfs-rate, the same
 * speckles at the WFS rate (one MFT per WFS frame) for `specklewfs coherence`. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits\n"
    "                           [--recon teach|vk|map|svd | --recon W.fits] [--teach-work DIR] [--rcond R]\n"
    "                           [--modes K] [--slope-noise RAD]\n"
    "                           [--vk-l0 M] [--write-recon W.fits] [--tiptilt exposure|frame|keep]\n"
    "                           [--mean ensemble|cube] [--wfs-rate [--wfs-hz HZ]]\n"
    "                           [--match IN.fits OUT.fits]... [--pupil MASK.fits] [--threads N] [--batch B]\n"
    "       specklewfs speckles TIMING.txt --science SCIENCE.fits --basis CUBE.fits [--control C.fits | --imat D.fits]\n"
    "                           [--dm-pitch M --dm-offset X,Y --dm-rot DEG --dm-flip] [--coef-scale S] -o SPECKLES.fits\n"
    "\n"
    "Complex speckles from WFS slopes (Codona & Kenworthy 2013, Sec. 4.4). For every camera\n"
    "exposure of the usable cubes of TIMING.txt (from `specklewfs sync`): z = W s at the\n"
    "actuators (tip-tilt: see --tiptilt), Clough-Tocher interpolation to the pupil grid,\n"
    "P exp(2 pi i z / lambda) summed over the exposure's WFS frames with fractional end\n"
    "weights, one MFT, core-phase referencing (eq:downsampledHalo); then the ensemble-average\n"
    "static halo is subtracted (eq:computedSpeckleField).\n"
    "\n"
    "  TIMING.txt          timing table; relative slopes paths are taken from its folder\n"
    "  --science FILE      reduced science cube (reduce): geometry keywords WAVELEN, TELDIAM,\n"
    "                      OBSCUR, PIXSCALE, PUPDX, PUPN and the focal window size\n"
    "  --actuators FILE    actuator positions, 2 x nact [m]\n"
    "  -o SPECKLES.fits    complex cube, one frame per science frame of the usable cubes\n"
    "  --recon teach       (default) a map taught for this observation, as `specklewfs teach\n"
    "                      SLOPES... --science --actuators [--pupil --valid]` makes it: closed\n"
    "                      loops of the system its files describe, at the winds its slopes show,\n"
    "                      with the modal filter its slopes show (docs/telemetry.md: within 1.3x\n"
    "                      of the ideal speckles on 45 of 48 matrix runs, vk on 23). Minutes per\n"
    "                      observation; the loops and the map (taught.fits: --recon taught.fits\n"
    "                      uses it again) in --teach-work DIR (default: beside -o, its name with\n"
    "                      .teach; the loops' folders removed unless --teach-keep-loops);\n"
    "                      --teach-loops N (12), --teach-seed S (101). Where teach cannot\n"
    "                      (no frozen-flow layer in the slopes, ...) it says why and uses vk\n"
    "  --recon W.fits      reconstructor (NAXIS1 = slopes, NAXIS2 = actuators): the residual\n"
    "                      wavefront [m of OPD, not DM surface] at the actuators = W slopes [rad];\n"
    "                      its gain on the model's D must be 0.5..2 (--recon-scale S multiplies it:\n"
    "                      -2 for a matrix to DM commands, a correction of the surface); or built\n"
    "                      here from the Shack-Hartmann interaction matrix D = U S V^T:\n"
    "  --recon vk          MAP, von Karman prior C of the actuators (--vk-l0 M: 10;\n"
    "                      0: the outer scale, the prior's scale and the slope noise fitted to\n"
    "                      the slopes by maximum likelihood)\n"
    "                      scaled to the slopes: W = C D^T (D C D^T + sigma^2 I)^-1\n"
    "  --recon map         MAP / Wiener reconstructor with the prior learned from the\n"
    "                      slopes of the usable cubes' telemetry files: mode i of D gets the\n"
    "                      gain (1 - sigma^2 / P_i)_+ / s_i, P_i the mean square of the slopes\n"
    "                      on u_i, sigma^2 the slope noise\n"
    ;
static const char *usage_text2 =
    "  --recon svd         truncated pseudo-inverse: singular values above\n"
    "                      --rcond (5e-2) x the largest, at most --modes K (0 = no limit)\n"
    "  --slope-noise RAD   effective slope noise rms [rad] for --recon vk|map (default: estimated\n"
    "                      from the slopes outside D's column space: noise + aliasing)\n"
    "  --write-recon FILE  also write the reconstructor in use (e.g. for `specklewfs stream`)\n"
    CLI_GEOM_HELP
    CLI_BAND_HELP
    "  --tiptilt MODE      exposure (default): remove from every WFS frame the weighted mean x/y\n"
    "                      slope of its exposure and keep the motion within it, as registered\n"
    "                      science frames have it (reduce re-centres, it cannot de-blur);\n"
    "                      frame: remove every frame's own mean slopes (the paper's Sec. 4.4), and\n"
    "                      re-centre the --match copies on the exposure-mean tilt the slopes\n"
    "                      measure instead of the image peak (docs/telemetry.md);\n"
    "                      keep: remove nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt      same as --tiptilt keep\n"
    "  --mean MODE         static halo: ensemble (all frames, default) or cube (each cube)\n"
    "  --match IN OUT      write OUT = the frames of IN (a cube aligned with SCIENCE.fits, e.g.\n"
    "                      SCIENCE.fits itself) of the usable cubes, so it matches SPECKLES.fits\n"
    "  --pupil MASK.fits   pupil mask PUPN x PUPN (default: annulus from TELDIAM, OBSCUR)\n"
    "  --valid MAP.fits    the AO system's valid-subaperture map, nsub x nsub (nonzero = used):\n"
    "                      those subapertures whatever their illumination (default: >= 50 % lit);\n"
    "                      the slopes may then be the used subapertures' only (2 nvalid: x, then y)\n"
    "  --threads N         engine workers (default 1)\n"
    "  --batch B           frames per pipeline call (default 128); under mpirun the cubes are\n"
    "                      shared out in pieces of B frames (docs/cluster.md)\n"
    "  --wfs-rate          write the speckles at the WFS rate instead, for `specklewfs coherence`:\n"
    "                      one frame per WFS frame covered by the usable cubes (cube after cube,\n"
    "                      each cube's frames contiguous), each propagated alone and core-phase\n"
    "                      referenced, the static halo (--mean) subtracted; tip-tilt removed per\n"
    "                      WFS frame (default; or --tiptilt keep). Header: FRAMEDT = 1/WFSRATE [s],\n"
    "                      FRATIO (camera exposure = FRATIO x FRAMEDT), NSEGS (cubes). --match and\n"
    "                      --tiptilt exposure do not apply\n"
    "  --wfs-hz HZ         WFS frame rate [Hz] when the slopes files have no WFSRATE keyword\n";

/* Options into o; returns -1 after --help, CLI_USAGE on a bad option, 0 otherwise. */
typedef struct spk_args {
    swfs_speckles_run_options *o;
    const char **min, **mout;
    double rcond;
    long modes;
    int rcond_given, tt_given;
    int help; /* -h/--help seen (the usage is two strings) */
} spk_args;

/* --recon (a name or a file), --rcond and --modes (SVD only), the tip-tilt, --mean, --match. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "speckles", *a = argv[*i], *v = *i + 1 < argc ? argv[*i + 1] : NULL;
    spk_args *d = ctx;
    swfs_speckles_run_options *o = d->o;
    const int gk = cli_geom_option(cmd, argc, argv, i, &o->geom);
    if (gk) return gk;
    const int lk = cli_linear_option(cmd, argc, argv, i, &o->lin);
    if (lk) return lk;
    const int bk = cli_band_option(cmd, argc, argv, i, &o->pipe.band);
    if (bk) return bk;
    if (cli_is_help(a)) {
        d->help = 1;
    } else if (!strcmp(a, "--recon")) {
        if (cli_take_string(cmd, argc, argv, i, "a file name", &v)) return -CLI_USAGE;
        o->recon = NULL;
        if (!strcmp(v, "teach")) o->pipe.recon = SWFS_RECON_TEACH;
        else if (!strcmp(v, "map")) o->pipe.recon = SWFS_RECON_MAP;
        else if (!strcmp(v, "vk")) o->pipe.recon = SWFS_RECON_VK;
        else if (!strcmp(v, "svd")) o->pipe.recon = SWFS_RECON_SVD;
        else { o->pipe.recon = SWFS_RECON_GIVEN; o->recon = v; }
    } else if (!strcmp(a, "--rcond") || !strcmp(a, "--modes")) {
        d->rcond_given = 1;
        if (a[2] == 'r' ? cli_take_double(cmd, argc, argv, i, &d->rcond) : cli_take_long(cmd, argc, argv, i, &d->modes))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--keep-tiptilt")) {
        o->pipe.tiptilt = SWFS_TT_KEEP;
        d->tt_given = 1;
    } else if (!strcmp(a, "--tiptilt")) {
        if (cli_parse_tiptilt(cmd, cli_next(argc, argv, i), &o->pipe.tiptilt)) return -CLI_USAGE;
        d->tt_given = 1;
    } else if (!strcmp(a, "--mean")) {
        if (!v || (strcmp(v, "ensemble") && strcmp(v, "cube"))) return -cli_usage_error(cmd, "--mean needs ensemble or cube");
        o->mean_mode = strcmp(v, "cube") ? SWFS_MEAN_ENSEMBLE : SWFS_MEAN_CUBE;
        ++*i;
    } else if (!strcmp(a, "--match")) {
        if (*i + 2 >= argc) return -cli_usage_error(cmd, "--match needs IN.fits OUT.fits");
        d->min[o->nmatch] = argv[*i + 1];
        d->mout[o->nmatch++] = argv[*i + 2];
        *i += 2;
    } else {
        return 0;
    }
    return 1;
}

static int parse(int argc, char **argv, swfs_speckles_run_options *o, const char **min, const char **mout)
{
    const char *cmd = "speckles";
    double slope_noise = 0;
    long threads = 1, batch = (long)o->batch, tloops = (long)o->teach_loops, tseed = (long)o->teach_seed;
    spk_args d = {o, min, mout, o->pipe.rcond, 0, 0, 0, 0};
    const char *fn = "a file name";
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o->out, fn, 0},           {"--science", CLI_STRING, &o->science, fn, 0},
        {"--actuators", CLI_STRING, &o->actuators, fn, 0}, {"--pupil", CLI_STRING, &o->mask, fn, 0},
        {"--valid", CLI_STRING, &o->valid, fn, 0},
        {"--write-recon", CLI_STRING, &o->write_recon, fn, 0}, {"--vk-l0", CLI_DOUBLE, &o->pipe.vk_l0, NULL, 0},
        {"--recon-scale", CLI_DOUBLE, &o->pipe.recon_scale, NULL, 0},
        {"--slope-noise", CLI_DOUBLE, &slope_noise, NULL, 0}, {"--threads", CLI_LONG, &threads, NULL, 0},
        {"--wfs-hz", CLI_DOUBLE, &o->wfs_hz, NULL, 0}, {"--wfs-rate", CLI_SET, &o->pipe.wfs_rate, NULL, 1},
        {"--batch", CLI_LONG, &batch, NULL, 0},       {"--teach-work", CLI_STRING, &o->teach_work, "a folder", 0},
        {"--teach-loops", CLI_LONG, &tloops, NULL, 0}, {"--teach-seed", CLI_LONG, &tseed, NULL, 0},
        {"--teach-keep-loops", CLI_SET, &o->teach_keep_loops, NULL, 1},
    };
    const char **const pos[] = {&o->timing};
    const cli_args args = {cmd, NULL, opts, CLI_NOPTS(opts), pos, 1, special, &d, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc;
    if (d.help) {
        fputs(usage_text, stdout);
        fputs(usage_text2, stdout);
        fputs(CLI_LINEAR_HELP, stdout);
        return -1;
    }
    const int rcond_given = d.rcond_given, tt_given = d.tt_given;
    const double rcond = d.rcond;
    const long modes = d.modes;
    if (!o->timing || !o->science || !(o->actuators || o->lin.basis) || !o->out)
        return cli_usage_error(cmd, "needs TIMING.txt, --science, --actuators (or --basis) and -o");
    if (o->lin.basis && (o->actuators || o->pipe.recon == SWFS_RECON_GIVEN || o->write_recon || o->valid))
        return cli_usage_error(cmd, "--basis (the linear model) takes no --actuators, --recon W.fits, --write-recon or "
                               "--valid (its control or interaction matrix takes the telemetry as it is)");
    if (!o->lin.basis && (o->lin.control || o->lin.imat || o->lin.reg.pitch > 0 || o->lin.scale != 1))
        return cli_usage_error(cmd, "--control, --imat, --dm-* and --coef-scale go with --basis");
    if (!(rcond >= 0 && rcond < 1) || modes < 0 || threads < 1) return cli_usage_error(cmd, "--rcond must be in [0, 1), --modes >= 0, --threads >= 1");
    if (!(slope_noise >= 0) || !isfinite(slope_noise)) return cli_usage_error(cmd, "--slope-noise must be a finite rms >= 0 [rad], got %g", slope_noise);
    if (rcond_given && o->pipe.recon != SWFS_RECON_SVD) return cli_usage_error(cmd, "--rcond and --modes go with --recon svd");
    if (slope_noise > 0 && o->pipe.recon != SWFS_RECON_MAP && o->pipe.recon != SWFS_RECON_VK) return cli_usage_error(cmd, "--slope-noise goes with --recon vk or map");
    if (!(o->pipe.vk_l0 >= 0) || !isfinite(o->pipe.vk_l0)) return cli_usage_error(cmd, "--vk-l0 must be an outer scale > 0 [m] (0: fitted), got %g", o->pipe.vk_l0);
    if (!(o->wfs_hz >= 0)) return cli_usage_error(cmd, "--wfs-hz must be a rate > 0 [Hz], got %g", o->wfs_hz);
    if (!isfinite(o->pipe.recon_scale) || o->pipe.recon_scale == 0)
        return cli_usage_error(cmd, "--recon-scale must be a finite, non-zero factor, got %g", o->pipe.recon_scale);
    if (o->pipe.recon_scale != 1 && o->pipe.recon != SWFS_RECON_GIVEN)
        return cli_usage_error(cmd, "--recon-scale goes with --recon W.fits");
    if (threads > SWFS_ENGINE_MAX_THREADS)
        return cli_usage_error(cmd, "--threads must be 1..%d, got %ld", SWFS_ENGINE_MAX_THREADS, threads);
    if (batch < 1 || batch > 100000) return cli_usage_error(cmd, "--batch must be 1..100000, got %ld", batch);
    o->batch = (size_t)batch;
    if (tloops < 2 || tloops > 64) return cli_usage_error(cmd, "--teach-loops must be 2..64, got %ld", tloops);
    if (tseed < 0) return cli_usage_error(cmd, "--teach-seed must be >= 0, got %ld", tseed);
    if ((o->teach_work || tloops != (long)o->teach_loops || tseed != (long)o->teach_seed || o->teach_keep_loops) &&
        (o->pipe.recon != SWFS_RECON_TEACH || o->lin.basis))
        return cli_usage_error(cmd, "--teach-work, --teach-loops, --teach-seed and --teach-keep-loops go with --recon "
                               "teach (the default with --actuators)");
    o->teach_loops = (size_t)tloops;
    o->teach_seed = (uint64_t)tseed;
    if (o->pipe.wfs_rate) {
        /* The run removes the tip-tilt per WFS frame there (run.h); asked for by name, the
         * exposure mean is refused. */
        if (tt_given && o->pipe.tiptilt == SWFS_TT_EXPOSURE) return cli_usage_error(cmd, "--wfs-rate removes the tip-tilt per WFS frame (or --tiptilt keep); --tiptilt exposure does not apply");
        if (o->nmatch) return cli_usage_error(cmd, "--match pairs camera frames; it does not apply with --wfs-rate");
    } else if (o->wfs_hz > 0) return cli_usage_error(cmd, "--wfs-hz goes with --wfs-rate");
    o->pipe.rcond = rcond;
    o->pipe.max_modes = (size_t)modes;
    o->pipe.slope_noise = slope_noise;
    o->pipe.threads = (int)threads;
    return 0;
}

int swfs_cmd_speckles(int argc, char **argv)
{
    const char *cmd = "speckles";
    swfs_speckles_run_options o;
    swfs_speckles_run_options_default(&o);
    const char **min = calloc((size_t)argc, sizeof *min), **mout = calloc((size_t)argc, sizeof *mout);
    if (!min || !mout) { free(min); free(mout); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    int rc = parse(argc, argv, &o, min, mout);
    if (rc) {
        free(min);
        free(mout);
        return rc < 0 ? CLI_OK : rc;
    }
    o.match_in = min;
    o.match_out = mout;
    if (cli_team_join(cmd, &o.team)) {
        free(min);
        free(mout);
        return CLI_FAIL;
    }
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_writer() ? cli_stage_progress : NULL;
    o.progress_ctx = "speckles:";
    swfs_speckles_run_result r;
    swfs_teach_run_result tr;
    o.teach = &tr;
    rc = swfs_speckles_run(&o, &r) ? (cli_writer() ? cli_error(cmd) : CLI_FAIL) : CLI_OK;
    if (!cli_writer()) {
        free(min);
        free(mout);
        return rc;
    }
    if (!rc) cli_speckles_summary(cmd, &o, &r, &tr);
    free(min);
    free(mout);
    return rc;
}

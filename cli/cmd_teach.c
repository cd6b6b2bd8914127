/* specklewfs teach SLOPES.fits... --system CONFIG -o W.fits [--work DIR]: a learned map for one
 * observation from simulated loops of the described system at the layers its slopes show
 * (run.h swfs_teach_run). */
#include "cli.h"

#include "specklewfs/config.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

static const char *usage_text =
    "usage: specklewfs teach SLOPES.fits... --science SCI.fits --actuators ACT.fits [--pupil P.fits]\n"
    "                        [--valid V.fits] [key=value ...] -o W.fits [--work DIR] [--loops N] [--seed S]\n"
    "                        [--max-loops M]\n"
    "       specklewfs teach SLOPES.fits... --system CONFIG [key=value ...] -o W.fits ...\n"
    "\n"
    "A reconstructor for this observation, learned from simulated closed loops of your system\n"
    "at the winds its own slopes show: the rule docs/telemetry.md measured over the matrix of\n"
    "systems (within 1.3x of the ideal speckles' NCP error on 47 of 48 runs, where the von\n"
    "Karman reconstructor was on 11 of 24). In one run:\n"
    "  1. the frozen-flow layers of the observation's slopes (as `specklewfs wind`);\n"
    "  2. N loops of the system (`simulate mode=timeseries` with CONFIG and key=value: your\n"
    "     telescope, WFS, DM, loop, vibration, noise and camera timing) with those layers, the\n"
    "     first one's share of the turbulence spread over 0.3-0.7 across the loops when there\n"
    "     are more (the slopes do not tell the shares). Without ao_modes (or ao_recon,\n"
    "     ao_rcond) the loops' filter comes from the slopes: the knee of their variances along\n"
    "     the DM modes, matched by up to four calibration loops (modes_NN/; TEACHMOD,\n"
    "     TEACHKNE), or a zonal loop's cut (ao_rcond 0.02-0.2, zonal_NN/; TEACHRCO) where a\n"
    "     zonal loop's variances come nearer the observation's (TEACHMMF, TEACHZMF);\n"
    "     Without slope_noise the loops' slope noise is the observation's white slope noise,\n"
    "     measured from its slopes' curl (TEACHNOI; TEACHSNO the loops');\n"
    "  3. the space-time map (`learn --lags 0,-L,L,-2L,2L`, L the frames in which the fastest\n"
    "     layer moves half a subaperture; more loops where its `learn --curve` asks) and\n"
    "     its two checks against the observation (as\n"
    "     `speckles` prints them). The map writes the wavefront on a grid of half the DM's\n"
    "     pitch (at least two pupil samples; DIR/outgrid.fits, W.fits' extension OUTXY): the\n"
    "     loops' truth is fitted there, so the lagged slopes also tell the residual the DM\n"
    "     cannot hold, which frozen flow carries across the subapertures (docs/telemetry.md;\n"
    "     truth_actuators=FILE gives other points);\n"
    "  4. where a check warns, the per-frame map: of the same loops when more than one layer\n"
    "     was found, else of N more loops of the measured layer and a random second layer.\n"
    "Where `wind` tracks no frozen-flow layer (slopes mostly noise, turbulence that does not\n"
    "flow): the speed whose one-layer calibration loops (speed_NN/) match the slopes' time\n"
    "correlation (TEACHPSP), loops of two layers near it in any direction (prior_NN/; more\n"
    "where the map's learning curve asks), and their space-time map at lags of 1 and 2 frames\n"
    "(TEACHSEL 'spacetime_prior').\n"
    "Give W.fits to `specklewfs speckles --recon W.fits`. It takes minutes: each loop (and\n"
    "each calibration loop that waits for no other's result) is a simulation as long as\n"
    "CONFIG's cubes, one per core at a time (threads=N: N at a time).\n";

static const char *usage_opts =
    "\n"
    "  SLOPES.fits   the observation's telemetry, consecutive files of one series (2 nsub^2\n"
    "                slopes per WFS frame, as the simulator writes them; or, with the system's\n"
    "                valid=MAP, the used subapertures' only: give speckles the same --valid)\n"
    "  --science SCI.fits --actuators ACT.fits [--pupil P.fits] [--valid V.fits]\n"
    "                the system from the observation's own files, the ones `speckles` takes:\n"
    "                the science cube's geometry, the DM's positions, the telescope's pupil,\n"
    "                the valid subapertures; nsub, wfs_rate and the loops' length from the\n"
    "                first telemetry file; the loop's gain and delay, r0 and vibration the\n"
    "                simulator's (key=value to set them); the modal filter and the slope\n"
    "                noise from the slopes (docs/telemetry.md); keys of --system or\n"
    "                key=value win\n"
    "  --system CONFIG, key=value   the system, in `simulate mode=timeseries` keys (config/\n"
    "                mmt-clio.conf documents them); nsub, wfs_rate and teldiam must be the\n"
    "                observation's; the layers and the seed are teach's to set\n"
    "  -o W.fits     the chosen map; its header says which (TEACHSEL) and why (TEACHWRN:\n"
    "                the checks that warned, TEACHMIS, TEACHCEX: their numbers)\n"
    "  --work DIR    folder for the loops (loop_NN/, mixed_NN/), the output grid (outgrid.fits)\n"
    "                and both maps tried (spacetime.fits, perframe.fits); created if missing (default: W.teach\n"
    "                beside W.fits, its name without .fits)\n"
    "  --loops N     loops per set (default 12)\n"
    "  --max-loops M loops at most where the learning curve asks for more than N\n"
    "                (default 4 N, at most 64: the cost of the first N four times over)\n"
    "  --seed S      loop k's seed is S + k (default 101)\n";

typedef struct from_files {
    const char *science, *actuators, *pupil, *valid, *telemetry;
} from_files;

/* The keys the observation's files give, where the user's description has none. */
static int describe(swfs_config *c, void *ctx)
{
    const from_files *f = ctx;
    return swfs_teach_describe(c, f->science, f->actuators, f->pupil, f->valid, f->telemetry);
}

static int parse(int argc, char **argv, swfs_config *cfg, swfs_teach_run_options *o, const char **files, size_t *nf,
                 const char **cfgfile, from_files *ff)
{
    const char *cmd = "teach";
    long loops = (long)o->nloops, seed = (long)o->seed, maxl = -1;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        long *lv = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); fputs(usage_opts, stdout); return -1; }
        else if (!strcmp(a, "-o") || !strcmp(a, "--work") || !strcmp(a, "--system") || !strcmp(a, "--science") ||
                 !strcmp(a, "--actuators") || !strcmp(a, "--pupil") || !strcmp(a, "--valid")) {
            if (!v) return cli_usage_error(cmd, "%s needs a %s", a, strcmp(a, "--work") ? "file name" : "folder");
            if (!strcmp(a, "-o")) o->out = v;
            else if (!strcmp(a, "--work")) o->work = v;
            else if (!strcmp(a, "--science")) ff->science = v;
            else if (!strcmp(a, "--actuators")) ff->actuators = v;
            else if (!strcmp(a, "--pupil")) ff->pupil = v;
            else if (!strcmp(a, "--valid")) ff->valid = v;
            else *cfgfile = v;
            i++;
            continue;
        } else if (!strcmp(a, "--loops")) lv = &loops;
        else if (!strcmp(a, "--max-loops")) lv = &maxl;
        else if (!strcmp(a, "--seed")) lv = &seed;
        else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (strchr(a, '=')) {
            if (swfs_config_set(cfg, a)) return cli_error(cmd);
            continue;
        } else {
            files[(*nf)++] = a;
            continue;
        }
        if (cli_parse_long(cmd, a, v, lv)) return CLI_USAGE;
        i++;
    }
    if (!*nf) return cli_usage_error(cmd, "needs the observation's telemetry files (SLOPES.fits...)");
    if (!o->out) return cli_usage_error(cmd, "needs -o W.fits");
    if (!ff->science != !ff->actuators)
        return cli_usage_error(cmd, "the system from the observation's files needs both --science and --actuators");
    if ((ff->pupil || ff->valid) && !ff->science)
        return cli_usage_error(cmd, "--pupil and --valid describe the system with --science and --actuators "
                               "(with --system, give pupil_mask= and valid=)");
    if (!ff->science && !*cfgfile && !swfs_config_count(cfg))
        return cli_usage_error(cmd, "needs the system: --science SCI.fits --actuators ACT.fits (from the "
                               "observation's files), or --system CONFIG / key=value");
    if (loops < 2 || loops > 64) return cli_usage_error(cmd, "--loops must be 2..64, got %ld", loops);
    if (seed < 0) return cli_usage_error(cmd, "--seed must be >= 0, got %ld", seed);
    if (maxl >= 0 && maxl && (maxl < loops || maxl > 64))
        return cli_usage_error(cmd, "--max-loops must be --loops (%ld) to 64 (0: 4 times --loops, at most 64), got %ld",
                               loops, maxl);
    o->nloops = (size_t)loops;
    o->max_loops = maxl > 0 ? (size_t)maxl : 0;
    o->seed = (uint64_t)seed;
    return 0;
}

int swfs_cmd_teach(int argc, char **argv)
{
    const char *cmd = "teach", *cfgfile = NULL;
    swfs_teach_run_options o;
    swfs_teach_run_options_default(&o);
    swfs_config *cfg = swfs_config_new();
    const char **files = calloc((size_t)argc, sizeof *files);
    size_t nf = 0;
    if (!cfg || !files) {
        swfs_config_free(cfg);
        free(files);
        fprintf(stderr, "specklewfs %s: out of memory\n", cmd);
        return CLI_FAIL;
    }
    from_files ff = {0};
    int rc = parse(argc, argv, cfg, &o, files, &nf, &cfgfile, &ff);
    if (!rc) rc = swfs_config_set_kv(cfg, "mode", "timeseries") ? cli_error(cmd) : 0;
    ff.telemetry = files[0];
    int filter_given = 0, noise_given = 0;
    if (!rc) rc = cli_ts_params(cmd, cfgfile, cfg, &o.sim, &filter_given, &noise_given, ff.science ? describe : NULL, &ff);
    o.modes_from_slopes = !filter_given;
    o.noise_from_slopes = !noise_given;
    char work[4200];
    if (!rc && !o.work) { /* W.teach beside W.fits */
        rc = swfs_teach_work_default(o.out, work, sizeof work) ? cli_usage_error(cmd, "%s (--work)", swfs_last_error()) : 0;
        o.work = work;
    }
    struct stat st;
    const int made = !rc && stat(o.work, &st) != 0; /* the folder is this run's to remove if teach refuses */
    if (!rc) rc = cli_make_dir(cmd, o.work);
    swfs_config_free(cfg);
    if (rc) {
        free(files);
        return rc < 0 ? CLI_OK : rc;
    }
    o.files = files;
    o.nfiles = nf;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_stage_progress;
    o.progress_ctx = (void *)"teach:";
    swfs_teach_run_result r;
    rc = swfs_teach_run(&o, &r);
    free(files);
    if (rc) {
        rc = cli_error(cmd);
        if (made) (void)rmdir(o.work); /* only if teach left it empty (refused before its loops) */
        return rc;
    }
    cli_teach_summary(stdout, cmd, &r, o.modes_from_slopes, o.out, o.work, 1);
    return CLI_OK;
}

/* specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits:
 * the speckle cube from WFS slopes that matches the reduced science cube frame for frame
 * (Sec. 4.4, eq:downsampledHalo, eq:computedSpeckleField); with --wfs-rate, the same
 * speckles at the WFS rate (one MFT per WFS frame) for `specklewfs coherence`. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Options into o; returns -1 after --help, CLI_USAGE on a bad option, 0 otherwise. */
typedef struct spk_args {
    swfs_speckles_run_options *o;
    const char **min, **mout, **tkeys, **mloops; /* --match pairs; --teach-set keys; --mean-loop folders */
    double rcond;
    long modes;
    int rcond_given, tt_given;
    int help; /* -h/--help seen */
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
    } else if (!strcmp(a, "--teach-set")) {
        if (cli_take_string(cmd, argc, argv, i, "key=value", &v)) return -CLI_USAGE;
        d->tkeys[o->nteach_keys++] = v;
    } else if (!strcmp(a, "--mean-loop")) {
        if (cli_take_string(cmd, argc, argv, i, "a folder (or teach, none)", &v)) return -CLI_USAGE;
        if (!strcmp(v, "teach")) o->mean_teach = 1; /* loops speckles simulates itself */
        else if (!strcmp(v, "none")) o->mean_teach = 0; /* not even a pyramid's default */
        else d->mloops[o->nmean_loops++] = v;
    } else if (!strcmp(a, "--loops-map")) {
        if (cli_take_string(cmd, argc, argv, i, "auto, choose or none", &v)) return -CLI_USAGE;
        if (!strcmp(v, "auto")) o->loops_map = SWFS_LOOPS_MAP_AUTO;
        else if (!strcmp(v, "choose")) o->loops_map = 1;
        else if (!strcmp(v, "none")) o->loops_map = 0;
        else return -cli_usage_error(cmd, "--loops-map takes auto, choose or none, got '%s'", v);
    } else if (!strcmp(a, "--pairing")) {
        if (cli_take_string(cmd, argc, argv, i, "speckles or table", &v)) return -CLI_USAGE;
        if (!strcmp(v, "table")) o->pairing_table = 1;
        else if (!strcmp(v, "speckles")) o->pairing_table = 0;
        else return -cli_usage_error(cmd, "--pairing takes speckles or table, got '%s'", v);
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

static int parse(int argc, char **argv, swfs_speckles_run_options *o, const char **min, const char **mout,
                 const char **tkeys, const char **mloops)
{
    const char *cmd = "speckles";
    double slope_noise = 0;
    long threads = 1, batch = (long)o->batch, tloops = (long)o->teach_loops, tseed = (long)o->teach_seed,
         tmax = (long)o->teach_max_loops, mtloops = (long)o->mean_teach_loops, mtmax = (long)o->mean_teach_max_loops;
    spk_args d = {o, min, mout, tkeys, mloops, o->pipe.rcond, 0, 0, 0, 0};
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
        {"--teach-max-loops", CLI_LONG, &tmax, NULL, 0},
        {"--teach-keep-loops", CLI_SET, &o->teach_keep_loops, NULL, 1},
        {"--teach-again", CLI_SET, &o->teach_again, NULL, 1},
        {"--mean-teach-loops", CLI_LONG, &mtloops, NULL, 0}, {"--mean-teach-max-loops", CLI_LONG, &mtmax, NULL, 0},
    };
    const char **const pos[] = {&o->timing};
    const cli_args args = {cmd, NULL, opts, CLI_NOPTS(opts), pos, 1, special, &d, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc;
    if (d.help) {
        cli_help_speckles();
        return -1;
    }
    /* Signs and the one check that depends on what was typed; the library checks the rest
     * (run.h swfs_speckles_run_options_check), with the same messages for every caller. */
    if (d.rcond_given && o->pipe.recon != SWFS_RECON_SVD) return cli_usage_error(cmd, "--rcond and --modes go with --recon svd");
    const cli_min mins[] = {{"--modes", d.modes, 0}, {"--threads", threads, 1}, {"--batch", batch, 1},
                            {"--teach-loops", tloops, 0}, {"--teach-seed", tseed, 0}, {"--teach-max-loops", tmax, 0},
                            {"--mean-teach-loops", mtloops, 0}, {"--mean-teach-max-loops", mtmax, 0}};
    if (cli_check_mins(cmd, mins, CLI_NOPTS(mins))) return CLI_USAGE;
    if (o->pipe.wfs_rate && d.tt_given && o->pipe.tiptilt == SWFS_TT_EXPOSURE) /* asked for by name: refused */
        return cli_usage_error(cmd, "--wfs-rate removes the tip-tilt per WFS frame (or --tiptilt keep); --tiptilt exposure "
                               "does not apply");
    o->batch = (size_t)batch;
    o->teach_loops = (size_t)tloops;
    o->teach_max_loops = (size_t)tmax;
    o->mean_teach_loops = (size_t)mtloops;
    o->mean_teach_max_loops = (size_t)mtmax;
    o->teach_seed = (uint64_t)tseed;
    o->pipe.rcond = d.rcond;
    o->pipe.max_modes = (size_t)d.modes;
    o->pipe.slope_noise = slope_noise;
    o->pipe.threads = threads > INT_MAX ? INT_MAX : (int)threads;
    o->match_in = min;
    o->match_out = mout;
    o->teach_keys = tkeys;
    o->mean_loops = mloops;
    return cli_check(cmd, swfs_speckles_run_options_check(o));
}

/* The camera's orientation told by the speckles (sync.h swfs_orient_acc), and the warning where
 * another pairing beats the timing table's (run.h swfs_speckles_orient_warning). */
static void orient_summary(const char *cmd, const swfs_speckles_run_result *r)
{
    if (!r->orient_done) return;
    char line[1024];
    swfs_orient_check_describe(&r->orient, line, sizeof line);
    fprintf(stderr, "%s: the camera's orientation by the speckles: %s\n", cmd, line);
    swfs_speckles_orient_warning(r, line, sizeof line);
    if (line[0]) fprintf(stderr, "specklewfs %s: warning: %s\n", cmd, line);
}

int swfs_cmd_speckles(int argc, char **argv)
{
    const char *cmd = "speckles";
    swfs_speckles_run_options o;
    swfs_speckles_run_options_default(&o);
    /* --match's IN and OUT names, --teach-set's keys and --mean-loop's folders: at most argc of
     * each, in one block */
    const char **names = calloc(4 * (size_t)argc, sizeof *names);
    if (!names) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    int rc = parse(argc, argv, &o, names, names + argc, names + 2 * argc, names + 3 * (size_t)argc);
    if (rc) rc = rc < 0 ? CLI_OK : rc;
    else if (cli_team_join(cmd, &o.team)) rc = CLI_FAIL;
    else {
        o.prov = cli_provenance(argc, argv, &o.nprov);
        o.progress = cli_writer() ? cli_stage_progress : NULL;
        o.progress_ctx = "speckles:";
        swfs_speckles_run_result r;
        swfs_teach_run_result tr;
        o.teach = &tr;
        rc = swfs_speckles_run(&o, &r) ? (cli_writer() ? cli_error(cmd) : CLI_FAIL) : CLI_OK;
        if (!rc && cli_writer()) {
            cli_speckles_summary(cmd, &o, &r, &tr);
            orient_summary(cmd, &r);
        }
    }
    free(names);
    return rc;
}

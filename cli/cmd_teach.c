/* specklewfs teach SLOPES.fits... --system CONFIG -o W.fits [--work DIR]: a learned map for one
 * observation from simulated loops of the described system at the layers its slopes show
 * (run.h swfs_teach_run). */
#include "cli.h"

#include "specklewfs/config.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

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
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { cli_help_teach(); return -1; }
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
    /* the files only this command reads (the library checks the telemetry and the system's) */
    swfs_paths *pp = NULL;
    int prc = swfs_paths_create(&pp);
    if (!prc) prc = swfs_paths_input(pp, "science cube (--science)", ff->science);
    if (!prc) prc = swfs_paths_input(pp, "system description (--system)", *cfgfile);
    if (!prc) prc = swfs_paths_output(pp, "the taught map (-o)", o->out);
    swfs_paths_free(pp);
    if (prc) return cli_error(cmd);
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
    o.coupling_from_recon = !swfs_config_has(cfg, "dm_coupling");
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

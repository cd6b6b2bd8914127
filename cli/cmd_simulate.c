/* specklewfs simulate: the paper's Sec. 3 data set (science, speckles, truth, pupil). */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/config.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"
#include "specklewfs/sweep.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs simulate [CONFIG] [key=value ...] -o DIR [--seed N] [--quiet]\n\n"
    "Simulate the Sec. 3 data set of Codona & Kenworthy (2013): post-AO residual wavefronts\n"
    "cut from von Karman screens, a static NCP aberration, science images with photon and\n"
    "read noise, and the WFS-side complex speckle cube (no NCP, peak-phase referenced).\n\n"
    "Writes DIR/science.fits  science cube [counts], keywords RDNOISE, GAIN (the noise model)\n"
    "       DIR/speckles.fits complex speckle cube psi (field / unaberrated peak, mean removed)\n"
    "       DIR/truth.fits    NCP (injected wavefront [m]), PUPIL, HALO (true static halo)\n"
    "       DIR/pupil.fits    pupil mask\n\n"
    "CONFIG is a key=value file (see config/paper-sec3.conf, which documents every key);\n"
    "key=value arguments override it; without CONFIG the paper's values are used.\n"
    "Noise: read_noise=SIGMA [counts], gain=E_PER_COUNT (<= 0: no photon noise).\n"
    "Unknown keys are an error.\n\n"
    "options:\n"
    "  -o DIR       output folder (created if needed)\n"
    "  --seed N     random seed (same as seed=N)\n"
    "  --quiet      no progress on stderr\n"
    "  --sweep SETS.txt  a parameter sweep: every line of SETS.txt (key=value ...) over\n"
    "               the configuration is simulated and estimated end to end; one row per\n"
    "               set (AO residual, Strehl, NCP recovery errors) in DIR/sweep.tsv; under\n"
    "               mpirun the sets are shared out over the processes (docs/cluster.md)\n"
    "  -h, --help   this help\n";

typedef struct sim_args {
    swfs_config *cfg;
    int have_file;
    const char **cfgfile; /* the CONFIG file given, for the path checks */
} sim_args;

/* key=value, or the CONFIG file: its settings must not override command-line ones given
 * before it, so it is loaded into a fresh config and the overrides are re-applied. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "simulate", *a = argv[*i];
    sim_args *d = ctx;
    if (a[0] == '-' && a[1]) return 0; /* an unknown option */
    if (strchr(a, '=')) return swfs_config_set(d->cfg, a) ? -cli_error(cmd) : 1;
    if (d->have_file) return -cli_usage_error(cmd, "more than one config file ('%s')", a);
    swfs_config *f = swfs_config_new();
    int bad = !f || swfs_config_load(f, a);
    for (size_t k = 0; !bad && k < swfs_config_count(d->cfg); k++)
        bad = swfs_config_set_kv(f, swfs_config_key(d->cfg, k), swfs_config_value(d->cfg, k)) != 0;
    if (bad) {
        swfs_config_free(f);
        return -cli_error(cmd);
    }
    swfs_config_free(d->cfg);
    d->cfg = f;
    d->have_file = 1;
    *d->cfgfile = a;
    return 1;
}

int swfs_cmd_simulate(int argc, char **argv)
{
    const char *cmd = "simulate", *outdir = NULL, *seed_arg = NULL, *sweep = NULL, *cfgfile = NULL;
    int quiet = 0, rc;
    sim_args d = {swfs_config_new(), 0, &cfgfile};
    if (!d.cfg) return cli_error(cmd);
    const cli_opt opts[] = {{"-o", CLI_STRING, &outdir, "an output folder", 0},
                            {"--seed", CLI_STRING, &seed_arg, "a value", 0}, {"--quiet", CLI_SET, &quiet, NULL, 1},
                            {"--sweep", CLI_STRING, &sweep, "a file of parameter sets", 0}};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, special, &d, NULL, NULL};
    rc = cli_parse_args(&args, argc, argv);
    swfs_config *cfg = d.cfg;
    if (rc) {
        swfs_config_free(cfg);
        return rc < 0 ? CLI_OK : rc;
    }
    if (!outdir) {
        swfs_config_free(cfg);
        return cli_usage_error(cmd, "missing -o DIR");
    }
    if (seed_arg && swfs_config_set_kv(cfg, "seed", seed_arg)) {
        swfs_config_free(cfg);
        return cli_error(cmd);
    }
    if (sweep) {
        rc = cli_sweep(cmd, SWFS_SWEEP_SIMULATE, cfg, NULL, outdir, sweep, argc, argv);
        swfs_config_free(cfg);
        return rc;
    }
    /* mode=timeseries: the real-data-path simulator (cli/cmd_simulate_ts.c). */
    {
        const char *mode = NULL;
        if (swfs_config_string(cfg, "mode", "paper", &mode)) {
            swfs_config_free(cfg);
            return cli_error(cmd);
        }
        if (!strcmp(mode, "timeseries")) {
            rc = swfs_cmd_simulate_ts(cfg, cfgfile, outdir, quiet, argc, argv);
            swfs_config_free(cfg);
            return rc;
        }
        if (strcmp(mode, "paper")) {
            cli_usage_error(cmd, "mode=%s: expected paper or timeseries", mode); /* before mode is freed */
            swfs_config_free(cfg);
            return CLI_USAGE;
        }
    }
    swfs_sim_params p;
    rc = cli_sim_params(cmd, cfg, &p);
    swfs_config_free(cfg);
    if (rc) return rc;
    if ((rc = cli_make_dir(cmd, outdir))) return rc;
    static const char *const products[] = {"science.fits", "speckles.fits", "truth.fits", "pupil.fits"};
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "config file", cfgfile);
    if (p.pupil_mask[0]) swfs_paths_input(paths, "pupil mask", p.pupil_mask);
    if (p.ncp_map[0]) swfs_paths_input(paths, "NCP map", p.ncp_map);
    cli_paths_outputs_in(paths, outdir, products, 4);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;

    const double t0 = cli_now();
    swfs_sim_result *r = NULL;
    if (swfs_sim_paper_run(&p, quiet ? cli_stop_check : cli_stage_progress, NULL, &r)) return cli_error(cmd);
    swfs_real *noisy = swfs_real_copy(r->science);
    /* The camera stream is independent of the screen streams (seed2(seed, pair)). */
    if (!noisy || swfs_sim_camera(r->science, p.read_noise, p.gain, p.seed ^ 0x5eed0fca3e7aULL, noisy)) {
        swfs_real_free(noisy);
        swfs_sim_result_free(r);
        return cli_error(cmd);
    }
    size_t nprov;
    const char *const *prov = cli_provenance(argc, argv, &nprov);
    /* The four files come as a set (atomic.h): all renamed into place, or none. */
    swfs_outputs_begin();
    int wrc = swfs_sim_write(r, noisy, p.read_noise, p.gain, outdir, prov, nprov);
    int erc = swfs_outputs_end(wrc == SWFS_OK);
    if (wrc || erc) {
        swfs_real_free(noisy);
        swfs_sim_result_free(r);
        return cli_error(cmd);
    }
    printf("simulate: %zu frames (%d screens x %zu x %zu sub-grids) of %ldx%ld pixels at %.3g lambda/D, lambda = %.3g um\n",
           r->nframes, p.nscreens, r->per_screen, r->per_screen, p.nfx, p.nfy, p.pixscale, p.wavelen * 1e6);
    printf("  AO residual: %.1f nm rms achieved (target %.1f, model %.1f, lag floor %.1f), kernel sigma %.1f cm\n",
           r->residual_rms * 1e9, p.target_rms * 1e9, r->expected_rms * 1e9, r->lag_floor_rms * 1e9,
           r->kernel_sigma * 100);
    printf("  Strehl: %.3f with NCP, %.3f without; window holds %.1f%% of %.0f counts\n", r->strehl, r->strehl_ao,
           100 * r->window_fraction, p.total_counts);
    printf("  NCP: %.1f nm rms, %.1f nm PV; noise: read %.3g counts, gain %.3g e-/count\n", r->ncp_rms * 1e9,
           r->ncp_pv * 1e9, p.read_noise, p.gain);
    printf("  wrote %s/{science,speckles,truth,pupil}.fits in %.2f s (simulation %.2f s)\n", outdir, cli_now() - t0,
           r->seconds);
    swfs_real_free(noisy);
    swfs_sim_result_free(r);
    return CLI_OK;
}

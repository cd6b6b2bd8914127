/* specklewfs simulate: the paper's Sec. 3 data set (science, speckles, truth, pupil). */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/config.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static void help(FILE *out)
{
    fprintf(out,
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
            "  -h, --help   this help\n");
}

int swfs_cmd_simulate(int argc, char **argv)
{
    const char *cmd = "simulate", *outdir = NULL, *seed_arg = NULL, *cfgfile = NULL;
    int quiet = 0, rc;
    swfs_config *cfg = swfs_config_new();
    if (!cfg) return cli_error(cmd);
    int have_file = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) {
            help(stdout);
            swfs_config_free(cfg);
            return CLI_OK;
        } else if (!strcmp(a, "-o")) {
            if (++i >= argc) {
                swfs_config_free(cfg);
                return cli_usage_error(cmd, "-o needs an output folder");
            }
            outdir = argv[i];
        } else if (!strcmp(a, "--seed")) {
            if (++i >= argc) {
                swfs_config_free(cfg);
                return cli_usage_error(cmd, "--seed needs a value");
            }
            seed_arg = argv[i];
        } else if (!strcmp(a, "--quiet")) {
            quiet = 1;
        } else if (a[0] == '-' && a[1]) {
            swfs_config_free(cfg);
            return cli_usage_error(cmd, "unknown option '%s'", a);
        } else if (strchr(a, '=')) {
            if (swfs_config_set(cfg, a)) {
                swfs_config_free(cfg);
                return cli_error(cmd);
            }
        } else {
            if (have_file) {
                swfs_config_free(cfg);
                return cli_usage_error(cmd, "more than one config file ('%s')", a);
            }
            /* A file's settings must not override command-line ones given before it:
             * load into a fresh config, then re-apply the overrides. */
            swfs_config *f = swfs_config_new();
            if (!f || swfs_config_load(f, a)) {
                swfs_config_free(f);
                swfs_config_free(cfg);
                return cli_error(cmd);
            }
            for (size_t k = 0; k < swfs_config_count(cfg); k++)
                if (swfs_config_set_kv(f, swfs_config_key(cfg, k), swfs_config_value(cfg, k))) {
                    swfs_config_free(f);
                    swfs_config_free(cfg);
                    return cli_error(cmd);
                }
            swfs_config_free(cfg);
            cfg = f;
            have_file = 1;
            cfgfile = a;
        }
    }
    if (!outdir) {
        swfs_config_free(cfg);
        return cli_usage_error(cmd, "missing -o DIR");
    }
    if (seed_arg && swfs_config_set_kv(cfg, "seed", seed_arg)) {
        swfs_config_free(cfg);
        return cli_error(cmd);
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
    swfs_sim_params_default(&p);
    if (swfs_sim_params_from_config(cfg, &p) || swfs_config_check_unused(cfg) || swfs_sim_params_check(&p)) {
        swfs_config_free(cfg);
        return cli_error(cmd);
    }
    swfs_config_free(cfg);
    if ((rc = cli_make_dir(cmd, outdir))) return rc;
    static const char *const products[] = {"science.fits", "speckles.fits", "truth.fits", "pupil.fits"};
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "config file", cfgfile);
    cli_paths_outputs_in(paths, outdir, products, 4);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;

    const double t0 = cli_now();
    swfs_sim_result *r = NULL;
    if (swfs_sim_paper_run(&p, quiet ? NULL : cli_stage_progress, NULL, &r)) return cli_error(cmd);
    swfs_real *noisy = swfs_real_copy(r->science);
    /* The camera stream is independent of the screen streams (seed2(seed, pair)). */
    if (!noisy || swfs_sim_camera(r->science, p.read_noise, p.gain, p.seed ^ 0x5eed0fca3e7aULL, noisy)) {
        swfs_real_free(noisy);
        swfs_sim_result_free(r);
        return cli_error(cmd);
    }
    char cmdline[2048];
    cli_command_line(argc, argv, cmdline, sizeof cmdline);
    const char *prov[1] = {cmdline};
    /* The four files come as a set (atomic.h): all renamed into place, or none. */
    swfs_outputs_begin();
    int wrc = swfs_sim_write(r, noisy, p.read_noise, p.gain, outdir, prov, 1);
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

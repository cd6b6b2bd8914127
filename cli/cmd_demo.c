/* specklewfs demo: the paper's Sec. 3 simulation end to end at four noise levels. */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/config.h"
#include "specklewfs/pupil.h"
#include "specklewfs/recovery.h"
#include "specklewfs/report.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"
#include "specklewfs/table.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs demo [-o DIR] [CONFIG] [key=value ...] [--levels S1,S2,...] [--no-report]\n"
    "                       [--loop-iterations N] [--loop-gain G] [--loop-sigma S]\n"
    "\n"
    "The paper's Sec. 3 simulation (980 AO-residual wavefronts, trefoil + Gaussian NCP,\n"
    "157,000 counts per exposure) end to end: simulate once, add camera noise at each\n"
    "background level (default 0,10,100,1000 counts), estimate the static halo, transform to\n"
    "the pupil and compare the recovered NCP wavefront with the injected one. Prints the\n"
    "recovery table (also DIR/recovery.tsv) and leaves the FITS products in DIR/sigma<level>/\n"
    "(default DIR: demo-out); one page of figures for the whole demo, DIR/report/index.html\n"
    "(unless --no-report; 'specklewfs report DIR' draws it again).\n"
    "Then closes the loop (as 'specklewfs correct'): N iterations (default 5; 0 skips it) of\n"
    "estimate -> DM offsets -> apply gain G (default 0.8) at noise S (default 100 counts), new\n"
    "turbulence every iteration; prints residual NCP, Strehl and contrast per iteration and\n"
    "writes DIR/loop/loop.{tsv,fits}.\n"
    "CONFIG and key=value override the simulation (see config/paper-sec3.conf).\n";

typedef struct demo_args {
    const char *outdir;
    double levels[16];
    size_t nlevels;
    int want_report;
    swfs_loop_params lp;
    const char *cfgfile; /* the CONFIG file given, for the path checks */
} demo_args;

/* The options into d and cfg; -1 to go on, else the exit code (help or a usage error). */
static int parse_args(const char *cmd, int argc, char **argv, swfs_config *cfg, demo_args *d)
{
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (cli_is_help(a)) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "-o")) {
            if (cli_take_string(cmd, argc, argv, &i, "a folder", &d->outdir)) return CLI_USAGE;
        } else if (!strcmp(a, "--levels")) {
            if (++i >= argc) return cli_usage_error(cmd, "--levels needs a list");
            if (swfs_config_set_kv(cfg, "demo.levels", argv[i])) return cli_error(cmd);
            d->nlevels = sizeof d->levels / sizeof d->levels[0];
            if (swfs_config_doubles(cfg, "demo.levels", d->levels, &d->nlevels) || d->nlevels == 0)
                return cli_usage_error(cmd, "--levels expects numbers like 0,10,100,1000, got '%s'", argv[i]);
            for (size_t k = 0; k < d->nlevels; k++)
                if (!(d->levels[k] >= 0)) return cli_usage_error(cmd, "noise levels must be >= 0");
        } else if (!strcmp(a, "--no-report")) {
            d->want_report = 0;
        } else if (!strcmp(a, "--loop-iterations")) {
            long n;
            if (cli_take_long(cmd, argc, argv, &i, &n)) return CLI_USAGE;
            if (n < 0 || n > 1000) return cli_usage_error(cmd, "--loop-iterations must be 0..1000");
            d->lp.iterations = (size_t)n;
        } else if (!strcmp(a, "--loop-gain")) {
            if (cli_take_range(cmd, argc, argv, &i, &d->lp.gain, 0, 1, 2, 0, "--loop-gain must be in (0, 2]"))
                return CLI_USAGE;
        } else if (!strcmp(a, "--loop-sigma")) {
            if (cli_take_range(cmd, argc, argv, &i, &d->lp.sigma, 0, 0, INFINITY, 0, "--loop-sigma must be >= 0"))
                return CLI_USAGE;
        } else if (a[0] == '-' && a[1] && !strchr(a, '=')) {
            return cli_usage_error(cmd, "unknown option '%s'", a);
        } else {
            if (!strchr(a, '=')) d->cfgfile = a;
            if (cli_config_arg(cmd, cfg, a)) return CLI_FAIL;
        }
    }
    return -1;
}

int swfs_cmd_demo(int argc, char **argv)
{
    const char *cmd = "demo";
    demo_args d = {"demo-out", {0, 10, 100, 1000}, 4, 1, {0}, NULL};
    swfs_loop_params_default(&d.lp);
    swfs_loop_params lp;
    swfs_loop_result *loop = NULL;
    swfs_config *cfg = swfs_config_new();
    swfs_sim_result *sim = NULL;
    int rc = CLI_FAIL, in_group = 0;
    if (!cfg) return cli_error(cmd);
    if ((rc = parse_args(cmd, argc, argv, cfg, &d)) >= 0) goto done;
    rc = CLI_FAIL;
    const char *outdir = d.outdir;
    const double *levels = d.levels;
    const size_t nlevels = d.nlevels;
    const int want_report = d.want_report;
    lp = d.lp;
    const char *cfgfile = d.cfgfile;
    swfs_sim_params p;
    if (cli_sim_params(cmd, cfg, &p)) goto done;
    if (cli_make_dir(cmd, outdir)) goto done;
    /* Every product of every level and of the loop, checked before the simulation. */
    {
        static const char *const level_products[] = {"science.fits", "speckles.fits", "truth.fits", "pupil.fits",
                                                      "halo.fits", "wavefront.fits"};
        static const char *const loop_products[] = {"loop.tsv", "loop.fits"};
        swfs_paths *paths = NULL;
        swfs_paths_create(&paths);
        swfs_paths_input(paths, "config file", cfgfile);
        for (size_t k = 0; k < nlevels; k++) {
            char dir[4096];
            snprintf(dir, sizeof dir, "%s/sigma%g", outdir, levels[k]);
            if (cli_make_dir(cmd, dir)) { swfs_paths_free(paths); goto done; }
            cli_paths_outputs_in(paths, dir, level_products, 6);
        }
        if (lp.iterations > 0) {
            char dir[4096];
            snprintf(dir, sizeof dir, "%s/loop", outdir);
            if (cli_make_dir(cmd, dir)) { swfs_paths_free(paths); goto done; }
            cli_paths_outputs_in(paths, dir, loop_products, 2);
        }
        if (cli_paths_check(cmd, paths)) goto done;
    }
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    /* The products of all levels and of the loop are renamed into place together when all
     * are written (atomic.h); the figures are made from them afterwards. */
    swfs_outputs_begin();
    in_group = 1;

    double t0 = cli_now();
    fprintf(stderr, "demo: simulating the paper's Sec. 3 data set (%d screens of %zu^2, %ld^2 pupil, %ldx%ld window)\n",
            p.nscreens, p.screen.n, p.pupn, p.nfx, p.nfy);
    if (swfs_sim_paper_run(&p, cli_stage_progress, (void *)"demo: simulate", &sim)) { cli_error(cmd); goto done; }
    double t_sim = cli_now() - t0;

    swfs_recovery res[16];
    double secs[16];
    for (size_t k = 0; k < nlevels; k++) {
        char dir[4096], noise_line[160];
        snprintf(dir, sizeof dir, "%s/sigma%g", outdir, levels[k]);
        fprintf(stderr, "demo: noise level %g counts -> %s\n", levels[k], dir);
        snprintf(noise_line, sizeof noise_line, "demo noise level: read noise %g counts, gain %g e-/count", levels[k],
                 p.gain);
        const char *prov[] = {cl, noise_line};
        double t1 = cli_now();
        if (swfs_recovery_run(sim, levels[k], p.seed * 1000003ULL + (uint64_t)levels[k], dir, prov, 2, &res[k])) {
            cli_error(cmd);
            goto done;
        }
        secs[k] = cli_now() - t1;
    }
    char tsv[4096];
    snprintf(tsv, sizeof tsv, "%s/recovery.tsv", outdir);
    if (swfs_recovery_table_write(tsv, res, secs, nlevels)) { cli_error(cmd); goto done; }
    if (lp.iterations > 0) {
        /* The open-loop simulation above is the loop's first measurement (same parameters). */
        char dir[4096];
        snprintf(dir, sizeof dir, "%s/loop", outdir);
        fprintf(stderr, "demo: closed loop, %zu iterations at gain %g, noise %g counts -> %s\n", lp.iterations, lp.gain,
                lp.sigma, dir);
        const char *prov[] = {cl};
        if (swfs_closed_loop_run(&p, &lp, sim, cli_stage_progress, (void *)"demo: closed", &loop) ||
            swfs_closed_loop_write(loop, dir, prov, 1)) {
            cli_error(cmd);
            goto done;
        }
    }
    in_group = 0;
    if (swfs_outputs_end(1)) { cli_error(cmd); goto done; }
    static swfs_report_summary rs; /* one page for the whole demo: the table, each level, the loop */
    if (want_report && swfs_report_run(outdir, NULL, NULL, &rs)) { cli_error(cmd); goto done; }
    double total = cli_now() - t0;

    printf("specklewfs demo: Codona & Kenworthy (2013) Sec. 3 simulation, %zu frames, %.0f counts/exposure\n",
           sim->nframes, p.total_counts);
    printf("  AO residual %.1f nm rms (target %.0f), kernel sigma %.1f cm, Strehl %.3f at %.2f um (with NCP %.3f)\n",
           sim->residual_rms * 1e9, p.target_rms * 1e9, sim->kernel_sigma * 100, sim->strehl_ao, p.wavelen * 1e6,
           sim->strehl);
    double ncp_ptt;
    swfs_wfe_compare(sim->ncp->data, sim->ncp->data, sim->pupil->data, (size_t)sim->geom.pupn, NULL, NULL, &ncp_ptt);
    printf("  injected NCP %.1f nm rms (piston removed; %.1f nm with tip/tilt also removed), %.0f nm peak to valley\n",
           sim->ncp_rms * 1e9, ncp_ptt * 1e9, sim->ncp_pv * 1e9);
    printf("  simulation %.2f s; products in %s/sigma<level>/\n\n", t_sim, outdir);
    printf("  recovered NCP error [nm rms inside the pupil, piston and tip/tilt removed]\n");
    printf("  %8s %8s %9s %8s | %8s %8s %12s | %9s %9s %7s\n", "sigma", "valid", "g undef.", "paper", "HALO", "HALO_LF",
           "HALO_LF+SNR", "joint fit", "med.SNR", "time");
    for (size_t k = 0; k < nlevels; k++)
        printf("  %8g %7.1f%% %8.1f%% %8.1f | %8.1f %8.1f %12.1f | %9.1f %9.3g %6.2fs\n", res[k].sigma,
               100 * res[k].valid_fraction, 100 * res[k].bad_radicand, res[k].err_paper * 1e9, res[k].err_halo * 1e9,
               res[k].err_lf * 1e9, res[k].err_lf_snr * 1e9, res[k].err_fit * 1e9, res[k].median_snr, secs[k]);
    printf("\n  paper: the paper's formulae end to end (per-pixel g of eq:scale-factor, eq:PSI-LowFreq, every pixel at\n"
           "  full weight). Middle: specklewfs' per-pixel moments with the regularized g; HALO = eq:TheAnswer, HALO_LF =\n"
           "  eq:PSI-LowFreq, both at full weight; HALO_LF+SNR adds the Wiener weight SNR^2/(SNR^2+4) -- the previous\n"
           "  default ('pupil --method moments'). joint fit: the pupil field, a smooth g map and the unexplained speckle\n"
           "  fraction fitted to every pixel's regression statistics at once -- the default of 'specklewfs pupil'\n"
           "  (docs/estimator.md). valid / g undef.: pixels where the radicand of the per-pixel g is positive / not.\n");
    if (want_report) printf("  figures: %s\n", rs.html);
    if (loop) {
        printf("\n  closing the loop (specklewfs correct): products in %s/loop/\n", outdir);
        cli_print_loop_table(loop);
    }
    printf("  total %.2f s\n", total);
    rc = CLI_OK;
done:
    if (in_group) swfs_outputs_end(0);
    swfs_loop_result_free(loop);
    swfs_sim_result_free(sim);
    swfs_config_free(cfg);
    return rc;
}

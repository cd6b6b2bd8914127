/* specklewfs demo: the paper's Sec. 3 simulation end to end at four noise levels. */
#include "cli.h"

#include "specklewfs/closed_loop.h"
#include "specklewfs/config.h"
#include "specklewfs/run.h"
#include "specklewfs/sim.h"

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

/* The run's stages as the demo's lines on stderr: what starts, and the progress bars. */
static int demo_progress(void *ctx, const char *stage, size_t done, size_t total)
{
    const swfs_demo_run_options *o = ctx;
    if (!strcmp(stage, "simulate"))
        fprintf(stderr, "demo: simulating the paper's Sec. 3 data set (%d screens of %zu^2, %ld^2 pupil, %ldx%ld window)\n",
                o->sim.nscreens, o->sim.screen.n, o->sim.pupn, o->sim.nfx, o->sim.nfy);
    else if (!strcmp(stage, "noise levels")) {
        if (done < total)
            fprintf(stderr, "demo: noise level %g counts -> %s/sigma%g\n", o->levels[done], o->outdir, o->levels[done]);
    }
    else if (!strcmp(stage, "closed loop") && done == 0)
        fprintf(stderr, "demo: closed loop, %zu iterations at gain %g, noise %g counts -> %s/loop\n", o->loop.iterations,
                o->loop.gain, o->loop.sigma, o->outdir);
    else
        return cli_stage_progress((void *)"demo:", stage, done, total);
    return cli_stop_requested();
}

int swfs_cmd_demo(int argc, char **argv)
{
    const char *cmd = "demo";
    demo_args d = {"demo-out", {0, 10, 100, 1000}, 4, 1, {0}, NULL};
    swfs_loop_params_default(&d.lp);
    swfs_config *cfg = swfs_config_new();
    swfs_demo_run_result r = {0};
    int rc = CLI_FAIL;
    if (!cfg) return cli_error(cmd);
    if ((rc = parse_args(cmd, argc, argv, cfg, &d)) >= 0) goto done;
    rc = CLI_FAIL;
    swfs_demo_run_options o;
    swfs_demo_run_options_default(&o);
    if (cli_sim_params(cmd, cfg, &o.sim)) goto done;
    o.outdir = d.outdir;
    o.levels = d.levels;
    o.nlevels = d.nlevels;
    o.loop = d.lp;
    o.report = d.want_report;
    o.config = d.cfgfile;
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    o.prov = prov;
    o.nprov = 1;
    o.progress = demo_progress;
    o.progress_ctx = &o;
    if (swfs_demo_run(&o, &r)) { rc = cli_error(cmd); goto done; }

    const swfs_sim_params *p = &o.sim;
    const swfs_sim_result *sim = r.sim;
    printf("specklewfs demo: Codona & Kenworthy (2013) Sec. 3 simulation, %zu frames, %.0f counts/exposure\n",
           sim->nframes, p->total_counts);
    printf("  AO residual %.1f nm rms (target %.0f), kernel sigma %.1f cm, Strehl %.3f at %.2f um (with NCP %.3f)\n",
           sim->residual_rms * 1e9, p->target_rms * 1e9, sim->kernel_sigma * 100, sim->strehl_ao, p->wavelen * 1e6,
           sim->strehl);
    printf("  injected NCP %.1f nm rms (piston removed; %.1f nm with tip/tilt also removed), %.0f nm peak to valley\n",
           sim->ncp_rms * 1e9, r.ncp_rms_ptt * 1e9, sim->ncp_pv * 1e9);
    printf("  simulation %.2f s; products in %s/sigma<level>/\n\n", r.sim_seconds, o.outdir);
    printf("  recovered NCP error [nm rms inside the pupil, piston and tip/tilt removed]\n");
    printf("  %8s %8s %9s %8s | %8s %8s %12s | %9s %9s %7s\n", "sigma", "valid", "g undef.", "paper", "HALO", "HALO_LF",
           "HALO_LF+SNR", "joint fit", "med.SNR", "time");
    for (size_t k = 0; k < r.nlevels; k++) {
        const swfs_recovery *e = &r.levels[k];
        printf("  %8g %7.1f%% %8.1f%% %8.1f | %8.1f %8.1f %12.1f | %9.1f %9.3g %6.2fs\n", e->sigma,
               100 * e->valid_fraction, 100 * e->bad_radicand, e->err_paper * 1e9, e->err_halo * 1e9, e->err_lf * 1e9,
               e->err_lf_snr * 1e9, e->err_fit * 1e9, e->median_snr, r.level_seconds[k]);
    }
    printf("\n  paper: the paper's formulae end to end (per-pixel g of eq:scale-factor, eq:PSI-LowFreq, every pixel at\n"
           "  full weight). Middle: specklewfs' per-pixel moments with the regularized g; HALO = eq:TheAnswer, HALO_LF =\n"
           "  eq:PSI-LowFreq, both at full weight; HALO_LF+SNR adds the Wiener weight SNR^2/(SNR^2+4) -- the previous\n"
           "  default ('pupil --method moments'). joint fit: the pupil field, a smooth g map and the unexplained speckle\n"
           "  fraction fitted to every pixel's regression statistics at once -- the default of 'specklewfs pupil'\n"
           "  (docs/estimator.md). valid / g undef.: pixels where the radicand of the per-pixel g is positive / not.\n");
    if (o.report) printf("  figures: %s\n", r.html);
    if (r.loop) {
        printf("\n  closing the loop (specklewfs correct): products in %s/loop/\n", o.outdir);
        cli_print_loop_table(r.loop);
    }
    printf("  total %.2f s\n", r.seconds);
    rc = CLI_OK;
done:
    swfs_demo_run_result_free(&r);
    swfs_config_free(cfg);
    return rc;
}

/* specklewfs correct: closed-loop NCP correction in simulation (closed_loop.h), and the
 * per-iteration table that `demo` prints too. */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/closed_loop.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/config.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs correct [CONFIG] [key=value ...] -o DIR [--iterations N] [--gain G] [--sigma S]\n"
    "                          [--actuators ACT.fits | --pitch P] [--influence gauss|cubic] [--coupling C]\n"
    "                          [--modes K] [--weight snr|none]\n"
    "\n"
    "Closes the loop on the paper's Sec. 3 simulation: each iteration simulates the data with\n"
    "the current residual NCP (new turbulence and camera noise every time, as on the sky),\n"
    "estimates the static halo and the pupil WFE, fits the DM offsets (-WFE/2 onto the\n"
    "actuators' influence functions) and applies gain x offsets; the residual wavefront is\n"
    "NCP + 2 x DM surface, so the DM's fitting error stays in it. Prints per iteration the\n"
    "residual NCP [nm rms], the Strehl of the simulated long-exposure PSF, and the raw\n"
    "contrast of the static halo in 2-6 lambda/D; writes DIR/loop.tsv and DIR/loop.fits.\n"
    "\n"
    "  -o DIR              output folder (default correct-out)\n"
    "  --iterations N      corrections to apply (default 5)\n"
    "  --gain G            loop gain (default 0.8)\n"
    "  --sigma S           camera background noise [counts] (default 100)\n"
    "  --actuators ACT.fits  DM actuator positions (2 x nact [m]); default: hexapolar with\n"
    "  --pitch P           ring spacing P [m] (default 0.35: 331 actuators on 6.5 m)\n"
    "  --influence gauss|cubic, --coupling C, --modes K: the DM fit (see 'dmoffsets --help')\n"
    "  --weight snr|none   focal-plane weight of the pupil step (default snr)\n"
    "CONFIG and key=value set the simulation (config/paper-sec3.conf), e.g. seed=3.\n";

void cli_print_loop_table(const swfs_loop_result *r)
{
    const swfs_loop_params *lp = &r->params;
    char infl[64];
    if (lp->fit.influence == SWFS_INFLUENCE_CUBIC) snprintf(infl, sizeof infl, "cubic influence");
    else snprintf(infl, sizeof infl, "Gaussian influence, coupling %.2f", lp->fit.coupling);
    printf("  closed loop: gain %.2f, sigma %g counts, %zu actuators (pitch %.3g m, %s), %s\n", lp->gain, lp->sigma,
           r->nact, r->pitch, infl, lp->pupil.weight == SWFS_WEIGHT_SNR ? "SNR-weighted HALO_LF" : "HALO_LF");
    if (lp->fit.modes) printf("  modal filter: first %zu Zernikes\n", lp->fit.modes);
    printf("  %4s %8s %8s %7s %8s %10s %10s %8s %7s %7s %6s\n", "iter", "resid", "resid-TT", "Strehl", "Marechal",
           "contrast", "NCP halo", "est.err", "fit", "unfit", "time");
    printf("  %4s %8s %8s %7s %8s %10s %10s %8s %7s %7s %6s\n", "", "[nm]", "[nm]", "", "(NCP)", "2-6 l/D", "2-6 l/D",
           "[nm]", "[nm]", "[nm]", "[s]");
    for (size_t k = 0; k < r->nrows; k++) {
        const swfs_loop_iter *it = &r->rows[k];
        printf("  %4zu %8.1f %8.1f %7.4f %8.4f %10.3e %10.3e", k, it->resid_rms * 1e9, it->resid_rms_ptt * 1e9,
               it->strehl, it->strehl_marechal, it->contrast, it->contrast_ncp);
        if (k + 1 < r->nrows)
            printf(" %8.1f %7.1f %7.1f", it->est_err * 1e9, 2 * it->fit.fit_rms * 1e9, 2 * it->fit.unfit_rms * 1e9);
        else
            printf(" %8s %7s %7s", "-", "-", "-");
        printf(" %6.2f\n", it->seconds);
    }
    const swfs_loop_iter *a = &r->rows[0], *b = &r->rows[r->nrows - 1];
    printf("  no-NCP ceiling: Strehl %.4f, contrast %.3e (the AO residual alone)\n", b->strehl_ao, b->contrast_ao);
    printf("  residual %.1f -> %.1f nm rms, Strehl %.4f -> %.4f, contrast %.3e -> %.3e, NCP halo %.3e -> %.3e (/%.0f)\n",
           a->resid_rms * 1e9, b->resid_rms * 1e9, a->strehl, b->strehl, a->contrast, b->contrast, a->contrast_ncp,
           b->contrast_ncp, a->contrast_ncp / b->contrast_ncp);
    printf("  resid: residual NCP wavefront (piston removed; -TT: tip/tilt also removed) after k corrections.\n"
           "  Strehl: peak of the simulated long-exposure PSF (AO residual included) over the unaberrated peak;\n"
           "  Marechal: exp(-(2 pi resid/lambda)^2), the NCP alone. contrast: mean |static halo|^2 in 2-6 lambda/D\n"
           "  over its peak (AO-attenuated Airy rings included); NCP halo: the same for the static halo minus the\n"
           "  no-NCP one. est.err: estimate - true residual (piston, tip/tilt removed); fit/unfit: wavefront the\n"
           "  DM offsets reproduce / leave out of that iteration's estimate. Total %.2f s.\n", r->seconds);
}

int swfs_cmd_correct(int argc, char **argv)
{
    const char *cmd = "correct";
    const char *outdir = "correct-out", *actfile = NULL, *cfgfile = NULL;
    swfs_loop_params lp;
    swfs_loop_params_default(&lp);
    swfs_config *cfg = swfs_config_new();
    if (!cfg) return cli_error(cmd);
    int rc = CLI_USAGE;
    double *xy = NULL;
    swfs_loop_result *res = NULL;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); rc = CLI_OK; goto done; }
        else if (!strcmp(a, "-o")) {
            if (!v) { cli_usage_error(cmd, "-o needs a folder"); goto done; }
            outdir = argv[++i];
        } else if (!strcmp(a, "--iterations")) {
            long k;
            if (cli_parse_long(cmd, a, v, &k)) goto done;
            if (k < 0 || k > 1000) { cli_usage_error(cmd, "--iterations must be 0..1000, got %ld", k); goto done; }
            lp.iterations = (size_t)k;
            i++;
        } else if (!strcmp(a, "--gain")) {
            if (cli_parse_double(cmd, a, v, &lp.gain)) goto done;
            if (!(lp.gain > 0 && lp.gain <= 2)) { cli_usage_error(cmd, "--gain must be in (0, 2]"); goto done; }
            i++;
        } else if (!strcmp(a, "--sigma")) {
            if (cli_parse_double(cmd, a, v, &lp.sigma)) goto done;
            if (!(lp.sigma >= 0)) { cli_usage_error(cmd, "--sigma must be >= 0"); goto done; }
            i++;
        } else if (!strcmp(a, "--actuators")) {
            if (!v) { cli_usage_error(cmd, "--actuators needs a file name"); goto done; }
            actfile = argv[++i];
        } else if (!strcmp(a, "--pitch")) {
            if (cli_parse_double(cmd, a, v, &lp.act_pitch)) goto done;
            if (!(lp.act_pitch > 0)) { cli_usage_error(cmd, "--pitch must be > 0 [m]"); goto done; }
            i++;
        } else if (!strcmp(a, "--influence")) {
            if (v && !strcmp(v, "gauss")) lp.fit.influence = SWFS_INFLUENCE_GAUSS;
            else if (v && !strcmp(v, "cubic")) lp.fit.influence = SWFS_INFLUENCE_CUBIC;
            else { cli_usage_error(cmd, "--influence expects 'gauss' or 'cubic', got '%s'", v ? v : ""); goto done; }
            i++;
        } else if (!strcmp(a, "--coupling")) {
            if (cli_parse_double(cmd, a, v, &lp.fit.coupling)) goto done;
            if (!(lp.fit.coupling > 0 && lp.fit.coupling < 1)) { cli_usage_error(cmd, "--coupling must be in (0, 1)"); goto done; }
            i++;
        } else if (!strcmp(a, "--modes")) {
            long k;
            if (cli_parse_long(cmd, a, v, &k)) goto done;
            if (k < 0 || k > 5000) { cli_usage_error(cmd, "--modes must be 0..5000, got %ld", k); goto done; }
            lp.fit.modes = (size_t)k;
            i++;
        } else if (!strcmp(a, "--weight")) {
            if (v && !strcmp(v, "snr")) lp.pupil.weight = SWFS_WEIGHT_SNR;
            else if (v && !strcmp(v, "none")) lp.pupil.weight = SWFS_WEIGHT_NONE;
            else { cli_usage_error(cmd, "--weight expects 'snr' or 'none', got '%s'", v ? v : ""); goto done; }
            i++;
        } else if (strchr(a, '=')) {
            if (swfs_config_set(cfg, a)) { rc = cli_error(cmd); goto done; }
        } else if (a[0] == '-' && a[1]) {
            cli_usage_error(cmd, "unknown option '%s'", a);
            goto done;
        } else if (swfs_config_load(cfg, a)) {
            rc = cli_error(cmd);
            goto done;
        } else {
            cfgfile = a;
        }
    }
    rc = CLI_FAIL;
    swfs_sim_params p;
    swfs_sim_params_default(&p);
    if (swfs_sim_params_from_config(cfg, &p) || swfs_config_check_unused(cfg) || swfs_sim_params_check(&p)) {
        cli_error(cmd);
        goto done;
    }
    if (actfile) {
        if (swfs_actuators_read(actfile, &xy, &lp.nact)) { cli_error(cmd); goto done; }
        lp.act_xy = xy;
        lp.act_name = actfile;
    }
    if (cli_make_dir(cmd, outdir)) goto done;
    static const char *const products[] = {"loop.tsv", "loop.fits"};
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "config file", cfgfile);
    swfs_paths_input(paths, "--actuators", actfile);
    cli_paths_outputs_in(paths, outdir, products, 2);
    if (cli_paths_check(cmd, paths)) goto done;
    fprintf(stderr, "correct: %zu iterations at gain %g, sigma %g counts (%d screens of %zu^2 each)\n", lp.iterations,
            lp.gain, lp.sigma, p.nscreens, p.screen.n);
    if (swfs_closed_loop_run(&p, &lp, NULL, cli_stage_progress, (void *)"correct:", &res)) {
        cli_error(cmd);
        goto done;
    }
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    swfs_outputs_begin(); /* loop.tsv and loop.fits together (atomic.h) */
    int wrc = swfs_closed_loop_write(res, outdir, prov, 1);
    if (swfs_outputs_end(wrc == SWFS_OK) || wrc) { cli_error(cmd); goto done; }
    printf("specklewfs correct: Codona & Kenworthy (2013) Sec. 3 simulation in closed loop, %s/loop.{tsv,fits}\n", outdir);
    cli_print_loop_table(res);
    rc = CLI_OK;
done:
    swfs_loop_result_free(res);
    free(xy);
    swfs_config_free(cfg);
    return rc;
}

/* specklewfs report RUN_DIR|DEMO_DIR [-o REPORT_DIR] [--pixel I J] */
#include "cli.h"

#include "specklewfs/report.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs report RUN_DIR [-o REPORT_DIR] [--pixel I J] [--percentiles LO HI]\n"
    "       specklewfs report DEMO_DIR [-o REPORT_DIR]\n"
    "\n"
    "Draw the run's products as PNG figures (PLplot, cairo) and write REPORT_DIR/index.html with\n"
    "the key numbers (frames, valid fraction, median SNR, WFE rms/PV, Strehl, recovery error).\n"
    "Reads whatever RUN_DIR holds: science.fits, speckles.fits, truth.fits, pupil.fits,\n"
    "halo.fits, wavefront.fits, coherence.fits; figures whose products are missing are skipped\n"
    "with a note in the page; a folder with none of them is an error.\n"
    "On the folder 'specklewfs demo -o DEMO_DIR' writes: one page for the whole demo, with the\n"
    "recovery table (recovery.tsv), each noise level's numbers and figures (sigma<level>/) and\n"
    "the closed loop (loop/loop.tsv).\n"
    "\n"
    "  -o REPORT_DIR        output folder (default RUN_DIR/report), created if needed\n"
    "  --pixel I J          focal pixel for the intensity-vs-speckle-phase and MCF plots\n"
    "                       (default: the highest-SNR valid pixel in the first Airy ring)\n"
    "  --percentiles LO HI  robust colour-range percentiles in % (default 1 99.5)\n"
    "\n"
    "figures: halo.png, focal.png, pixel.png, pupil.png, coherence.png; loop.png (demo)\n";

/* --pixel I J and --percentiles LO HI, checked as they come. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "report", *a = argv[*i];
    swfs_report_options *opt = ctx;
    if (!strcmp(a, "--pixel")) {
        if (cli_parse_long(cmd, a, cli_next(argc, argv, i), &opt->pixel_i) ||
            cli_parse_long(cmd, a, cli_next(argc, argv, i), &opt->pixel_j))
            return -CLI_USAGE;
        if (opt->pixel_i < 0 || opt->pixel_j < 0) return -cli_usage_error(cmd, "--pixel needs two indices >= 0");
    } else if (!strcmp(a, "--percentiles")) {
        if (cli_parse_double(cmd, a, cli_next(argc, argv, i), &opt->pct_lo) ||
            cli_parse_double(cmd, a, cli_next(argc, argv, i), &opt->pct_hi))
            return -CLI_USAGE;
        if (!(opt->pct_lo >= 0 && opt->pct_hi <= 100 && opt->pct_lo < opt->pct_hi))
            return -cli_usage_error(cmd, "--percentiles needs 0 <= LO < HI <= 100");
    } else {
        return 0;
    }
    return 1;
}

int swfs_cmd_report(int argc, char **argv)
{
    const char *cmd = "report";
    const char *run = NULL, *out = NULL;
    swfs_report_options opt;
    swfs_report_options_default(&opt);
    const cli_opt opts[] = {{"-o", CLI_STRING, &out, "a folder name", 0}};
    const char **const pos[] = {&run};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 1, special, &opt, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!run) return cli_usage_error(cmd, "needs RUN_DIR");
    double t0 = cli_now();
    swfs_report_summary s;
    if (swfs_report_run(run, out, &opt, &s)) return cli_error(cmd);
    for (size_t k = 0; k < s.nnotes; k++) fprintf(stderr, "specklewfs report: note: %s\n", s.notes[k]);
    printf("report: %zu figure%s", s.nfigures, s.nfigures == 1 ? "" : "s");
    for (size_t k = 0; k < s.nfigures; k++) printf("%s%s", k ? ", " : " (", s.figures[k].file);
    printf("%s in %.2f s\n", s.nfigures ? ")" : "", cli_now() - t0);
    if (isfinite(s.wfe_rms)) printf("  WFE %.1f nm rms, %.1f nm PV, Strehl %.3f\n", 1e9 * s.wfe_rms, 1e9 * s.wfe_pv, s.strehl);
    if (isfinite(s.err_rms))
        printf("  recovery error %.1f nm rms (true NCP %.1f nm rms; piston and tip/tilt removed)\n", 1e9 * s.err_rms,
               1e9 * s.ncp_rms);
    if (s.demo)
        printf("  demo: recovery table %zu rows, closed loop %zu rows, %zu noise levels\n", s.recovery_rows, s.loop_rows,
               s.nlevels);
    for (size_t k = 0; k < s.nlevels; k++)
        printf("  sigma %g: %zu figures, recovery error %.1f nm rms\n", s.levels[k].sigma, s.levels[k].nfigures,
               1e9 * s.levels[k].err_rms);
    printf("open %s\n", s.html);
    return CLI_OK;
}

/* specklewfs dmoffsets PUPIL.fits -o OFFSETS.fits --actuators ACT.fits [--influence gauss|cubic]
 *                      [--coupling C] [--pitch P] [--modes K] [--reg MU] */
#include "cli.h"

#include "specklewfs/dmfit.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs dmoffsets PUPIL.fits -o OFFSETS.fits (--actuators ACT.fits | --hexapolar PITCH)\n"
    "                            [--influence gauss|cubic] [--coupling C] [--pitch P] [--modes K] [--reg MU]\n"
    "\n"
    "Deformable-mirror offsets that cancel the NCP wavefront of PUPIL.fits (the WFE extension\n"
    "written by 'specklewfs pupil'): the correction surface -WFE/2 (reflective DM: the wavefront\n"
    "changes by twice the surface) fitted by least squares over the pupil onto the actuators'\n"
    "influence functions. Prints the fitted and the unfittable parts [nm rms].\n"
    "\n"
    "  -o OFFSETS.fits     output: OFFSETS (nact x 1, metres of DM surface per actuator, to ADD\n"
    "                      to the current DM shape), ACTUATORS, SURFACE (the DM surface they\n"
    "                      make), UNFIT (target - SURFACE), PUPIL, with the geometry and the fit\n"
    "                      statistics as keywords\n"
    "  --actuators ACT.fits actuator positions: 2 x nact image [m] in the pupil frame (x, y)\n"
    "  --hexapolar PITCH   instead: a hexapolar layout with rings every PITCH metres covering\n"
    "                      the pupil (0.35 m gives 331 actuators on 6.5 m)\n"
    "  --influence gauss|cubic  Gaussian influence functions (default), or the Clough-Tocher\n"
    "                      interpolation of the actuator values (the AO reconstruction's model)\n"
    "  --coupling C        Gaussian influence at one pitch (default 0.2; 0.15-0.30 is typical)\n"
    "  --pitch P           [m] pitch for the Gaussian width (default: median nearest-neighbour\n"
    "                      distance of the actuators)\n"
    "  --modes K           fit only the projection of the correction on Noll Zernikes 1..K, so\n"
    "                      estimation noise is not driven into high orders (default: all)\n"
    "  --reg MU            Tikhonov damping relative to the mean diagonal (default 1e-3)\n";

/* The options checked as they come, into the run's options. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "dmoffsets", *a = argv[*i];
    swfs_dmoffsets_run_options *o = ctx;
    int bad;
    if (!strcmp(a, "--hexapolar"))
        bad = cli_take_range(cmd, argc, argv, i, &o->hexapolar, 0, 1, INFINITY, 0, "--hexapolar needs a pitch > 0 [m]");
    else if (!strcmp(a, "--pitch"))
        bad = cli_take_range(cmd, argc, argv, i, &o->fit.pitch, 0, 1, INFINITY, 0, "--pitch must be > 0 [m]");
    else if (!strcmp(a, "--reg"))
        bad = cli_take_range(cmd, argc, argv, i, &o->fit.reg, 0, 0, INFINITY, 0, "--reg must be >= 0");
    else
        return cli_dmfit_option(cmd, argc, argv, i, &o->fit);
    return bad ? -CLI_USAGE : 1;
}

int swfs_cmd_dmoffsets(int argc, char **argv)
{
    const char *cmd = "dmoffsets";
    swfs_dmoffsets_run_options o;
    swfs_dmoffsets_run_options_default(&o);
    const cli_opt opts[] = {{"-o", CLI_STRING, &o.out, "a file name", 0},
                            {"--actuators", CLI_STRING, &o.actuators, "a file name", 0}};
    const char **const pos[] = {&o.pupil};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 1, special, &o, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    if (!o.pupil) return cli_usage_error(cmd, "needs PUPIL.fits");
    if (!o.out) return cli_usage_error(cmd, "needs -o OFFSETS.fits");
    if (!o.actuators && !(o.hexapolar > 0)) return cli_usage_error(cmd, "needs --actuators ACT.fits or --hexapolar PITCH");
    if (o.actuators && o.hexapolar > 0) return cli_usage_error(cmd, "give --actuators or --hexapolar, not both");
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    o.prov = prov;
    o.nprov = 1;
    swfs_dmoffsets_run_result r;
    if (swfs_dmoffsets_run(&o, &r)) return cli_error(cmd);
    const swfs_dmfit_stats st = r.stats;
    printf("dmoffsets: %s\n", o.out);
    printf("  actuators         %zu (%zu reach the pupil), pitch %.3g m, %s influence", r.nact, r.active, r.pitch,
           o.fit.influence == SWFS_INFLUENCE_CUBIC ? "cubic (Clough-Tocher)" : "Gaussian");
    if (o.fit.influence == SWFS_INFLUENCE_GAUSS) printf(", coupling %.2f", o.fit.coupling);
    printf("\n");
    printf("  correction        %.1f nm rms of surface (-WFE/2; WFE %.1f nm rms)\n", st.target_rms * 1e9,
           2 * st.target_rms * 1e9);
    if (o.fit.modes > 0)
        printf("  modal filter      first %zu Zernikes keep %.1f nm, leave out %.1f nm rms\n", o.fit.modes,
               st.modal_rms * 1e9, st.filtered_rms * 1e9);
    printf("  fitted            %.1f nm rms of surface (%.1f nm of wavefront)\n", st.fit_rms * 1e9, 2 * st.fit_rms * 1e9);
    printf("  unfittable        %.1f nm rms of surface (%.1f nm of wavefront); DM fitting error %.1f nm\n",
           st.unfit_rms * 1e9, 2 * st.unfit_rms * 1e9, st.fiterr_rms * 1e9);
    printf("  offsets           %.1f nm rms, %.1f .. %.1f nm\n", st.cmd_rms * 1e9, st.cmd_min * 1e9, st.cmd_max * 1e9);
    return CLI_OK;
}

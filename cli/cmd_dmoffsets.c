/* specklewfs dmoffsets PUPIL.fits -o OFFSETS.fits --actuators ACT.fits [--influence gauss|cubic]
 *                      [--coupling C] [--pitch P] [--modes K] [--reg MU] */
#include "cli.h"

#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
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

typedef struct dm_args {
    swfs_dmfit_options opt;
    double hexpitch;
} dm_args;

/* The options checked as they come. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "dmoffsets", *a = argv[*i];
    dm_args *d = ctx;
    int bad;
    if (!strcmp(a, "--hexapolar"))
        bad = cli_take_range(cmd, argc, argv, i, &d->hexpitch, 0, 1, INFINITY, 0, "--hexapolar needs a pitch > 0 [m]");
    else if (!strcmp(a, "--pitch"))
        bad = cli_take_range(cmd, argc, argv, i, &d->opt.pitch, 0, 1, INFINITY, 0, "--pitch must be > 0 [m]");
    else if (!strcmp(a, "--reg"))
        bad = cli_take_range(cmd, argc, argv, i, &d->opt.reg, 0, 0, INFINITY, 0, "--reg must be >= 0");
    else
        return cli_dmfit_option(cmd, argc, argv, i, &d->opt);
    return bad ? -CLI_USAGE : 1;
}

int swfs_cmd_dmoffsets(int argc, char **argv)
{
    const char *cmd = "dmoffsets";
    const char *in = NULL, *out = NULL, *actfile = NULL;
    dm_args d = {.hexpitch = 0.0};
    swfs_dmfit_options_default(&d.opt);
    const cli_opt opts[] = {{"-o", CLI_STRING, &out, "a file name", 0},
                            {"--actuators", CLI_STRING, &actfile, "a file name", 0}};
    const char **const pos[] = {&in};
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), pos, 1, special, &d, NULL, NULL};
    int prc = cli_parse_args(&args, argc, argv);
    if (prc) return prc < 0 ? CLI_OK : prc;
    const swfs_dmfit_options opt = d.opt;
    const double hexpitch = d.hexpitch;
    if (!in) return cli_usage_error(cmd, "needs PUPIL.fits");
    if (!out) return cli_usage_error(cmd, "needs -o OFFSETS.fits");
    if (!actfile && !(hexpitch > 0)) return cli_usage_error(cmd, "needs --actuators ACT.fits or --hexapolar PITCH");
    if (actfile && hexpitch > 0) return cli_usage_error(cmd, "give --actuators or --hexapolar, not both");
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "pupil product", in);
    swfs_paths_input(paths, "--actuators", actfile);
    swfs_paths_output(paths, "-o", out);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;

    int rc = CLI_FAIL;
    swfs_fits_in *f = NULL;
    swfs_real *wfe = NULL, *mask = NULL;
    double *xy = NULL, *target = NULL, *cmdv = NULL;
    size_t nact = 0;
    swfs_dmfit *fit = NULL;
    swfs_geom g;
    if (swfs_fits_in_open(&f, in, NULL)) { cli_error(cmd); goto done; }
    if (!swfs_fits_in_has_ext(f, "WFE")) {
        fprintf(stderr, "specklewfs %s: %s: no WFE extension (expected a pupil product written by 'specklewfs pupil')\n",
                cmd, in);
        goto done;
    }
    if (swfs_fits_in_move(f, "WFE") || swfs_fits_in_require_float(f, "a pupil product") ||
        swfs_fits_in_read_real_all(f, &wfe) || swfs_fits_in_geom(f, &g)) {
        cli_error(cmd);
        goto done;
    }
    if (!(g.pupn > 0) || !(g.pupdx > 0) || !(g.teldiam > 0) || !isfinite(g.wavelen)) {
        fprintf(stderr, "specklewfs %s: %s: the WFE extension lacks the pupil geometry (PUPN, PUPDX, TELDIAM, WAVELEN)\n",
                cmd, in);
        goto done;
    }
    if (wfe->nx != (size_t)g.pupn || wfe->ny != (size_t)g.pupn || wfe->nz != 1) {
        fprintf(stderr, "specklewfs %s: %s: WFE is %zux%zux%zu but PUPN = %ld (expected a %ldx%ld image)\n", cmd, in,
                wfe->nx, wfe->ny, wfe->nz, g.pupn, g.pupn, g.pupn);
        goto done;
    }
    if (swfs_fits_in_has_ext(f, "PUPIL")) {
        if (swfs_fits_in_move(f, "PUPIL") || swfs_fits_in_read_real_all(f, &mask)) { cli_error(cmd); goto done; }
        if (mask->nx != wfe->nx || mask->ny != wfe->ny || mask->nz != 1) {
            fprintf(stderr, "specklewfs %s: %s: PUPIL is %zux%zu but WFE is %zux%zu\n", cmd, in, mask->nx, mask->ny,
                    wfe->nx, wfe->ny);
            goto done;
        }
    } else if (!isfinite(g.obscur)) {
        fprintf(stderr, "specklewfs %s: %s: no PUPIL extension and no OBSCUR keyword to build the pupil\n", cmd, in);
        goto done;
    }
    swfs_fits_in_close(f);
    f = NULL;
    /* The WFE of a pupil product is a phase times lambda/2 pi: finite, within a few waves. */
    for (size_t s = 0; s < wfe->nx * wfe->ny; s++)
        if ((!mask || mask->data[s] > 0) && (!isfinite(wfe->data[s]) || fabs(wfe->data[s]) > 10 * g.wavelen)) {
            fprintf(stderr, "specklewfs %s: %s: WFE at pupil sample (%zu, %zu) is %g m; a pupil WFE is finite and within "
                    "10 wavelengths (%g m)\n", cmd, in, s % wfe->nx, s / wfe->nx, wfe->data[s], 10 * g.wavelen);
            goto done;
        }

    if (actfile) {
        if (swfs_actuators_read(actfile, &xy, &nact)) { cli_error(cmd); goto done; }
    } else if (swfs_actuators_hexapolar(g.teldiam, hexpitch, g.pupdx, &xy, &nact)) {
        cli_error(cmd);
        goto done;
    }
    if (swfs_dmfit_create(&fit, xy, nact, &g, mask ? mask->data : NULL, &opt)) {
        fprintf(stderr, "specklewfs %s: %s: %s\n", cmd, actfile ? actfile : "hexapolar actuators", swfs_last_error());
        goto done;
    }
    const size_t n2 = (size_t)g.pupn * (size_t)g.pupn;
    target = malloc(n2 * sizeof *target);
    cmdv = malloc(nact * sizeof *cmdv);
    if (!target || !cmdv) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    /* The correction: -WFE/2 of surface (reflective: z = phi lambda / 4 pi). */
    for (size_t s = 0; s < n2; s++) target[s] = -0.5 * wfe->data[s];
    swfs_dmfit_stats st;
    if (swfs_dmfit_apply(fit, target, cmdv, NULL, &st)) {
        fprintf(stderr, "specklewfs %s: %s: %s\n", cmd, in, swfs_last_error());
        goto done;
    }
    char cl[2048], src[1200];
    cli_command_line(argc, argv, cl, sizeof cl);
    snprintf(src, sizeof src, "dmoffsets: correction -WFE/2 of %s", in);
    const char *prov[] = {cl, src};
    if (swfs_dmfit_write(fit, cmdv, target, &st, out, &g, prov, 2)) { cli_error(cmd); goto done; }

    printf("dmoffsets: %s\n", out);
    printf("  actuators         %zu (%zu reach the pupil), pitch %.3g m, %s influence", nact, swfs_dmfit_active(fit),
           swfs_dmfit_pitch(fit), opt.influence == SWFS_INFLUENCE_CUBIC ? "cubic (Clough-Tocher)" : "Gaussian");
    if (opt.influence == SWFS_INFLUENCE_GAUSS) printf(", coupling %.2f", opt.coupling);
    printf("\n");
    printf("  correction        %.1f nm rms of surface (-WFE/2; WFE %.1f nm rms)\n", st.target_rms * 1e9,
           2 * st.target_rms * 1e9);
    if (opt.modes > 0)
        printf("  modal filter      first %zu Zernikes keep %.1f nm, leave out %.1f nm rms\n", opt.modes,
               st.modal_rms * 1e9, st.filtered_rms * 1e9);
    printf("  fitted            %.1f nm rms of surface (%.1f nm of wavefront)\n", st.fit_rms * 1e9, 2 * st.fit_rms * 1e9);
    printf("  unfittable        %.1f nm rms of surface (%.1f nm of wavefront); DM fitting error %.1f nm\n",
           st.unfit_rms * 1e9, 2 * st.unfit_rms * 1e9, st.fiterr_rms * 1e9);
    printf("  offsets           %.1f nm rms, %.1f .. %.1f nm\n", st.cmd_rms * 1e9, st.cmd_min * 1e9, st.cmd_max * 1e9);
    rc = CLI_OK;
done:
    swfs_fits_in_close(f);
    swfs_real_free(wfe);
    swfs_real_free(mask);
    swfs_dmfit_free(fit);
    free(xy);
    free(target);
    free(cmdv);
    return rc;
}

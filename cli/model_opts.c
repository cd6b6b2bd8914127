/* Options and summaries shared by the commands that build a model: configuration and
 * simulation parameters, the DM fit, the geometry, the linear model's files, the
 * reconstructor's summary (cli.h). */
#include "cli.h"
#include "specklewfs/config.h"
#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/sim.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int cli_config_arg(const char *cmd, swfs_config *cfg, const char *a)
{
    if (strchr(a, '=') ? swfs_config_set(cfg, a) : swfs_config_load(cfg, a)) return cli_error(cmd);
    return 0;
}

int cli_sim_params(const char *cmd, swfs_config *cfg, swfs_sim_params *p)
{
    swfs_sim_params_default(p);
    if (swfs_sim_params_from_config(cfg, p) || swfs_config_check_unused(cfg) || swfs_sim_params_check(p))
        return cli_error(cmd);
    return 0;
}

int cli_dmfit_option(const char *cmd, int argc, char **argv, int *i, swfs_dmfit_options *fo)
{
    const char *a = argv[*i];
    if (!strcmp(a, "--influence")) {
        if (cli_parse_choice(cmd, a, cli_next(argc, argv, i), "gauss", SWFS_INFLUENCE_GAUSS, "cubic",
                             SWFS_INFLUENCE_CUBIC, &fo->influence))
            return -CLI_USAGE;
    } else if (!strcmp(a, "--coupling")) {
        if (cli_take_range(cmd, argc, argv, i, &fo->coupling, 0, 1, 1, 1, "--coupling must be in (0, 1)")) return -CLI_USAGE;
    } else if (!strcmp(a, "--modes")) {
        long k;
        if (cli_take_long(cmd, argc, argv, i, &k)) return -CLI_USAGE;
        if (k < 0 || k > 5000) return -cli_usage_error(cmd, "--modes must be 0..5000, got %ld", k);
        fo->modes = (size_t)k;
    } else {
        return 0;
    }
    return 1;
}

int cli_band_option(const char *cmd, int argc, char **argv, int *i, double *band)
{
    if (strcmp(argv[*i], "--band")) return 0;
    const char *v = cli_next(argc, argv, i);
    if (!v) return -cli_usage_error(cmd, "--band needs auto, none or a radius > 0 [lambda/D]");
    if (!strcmp(v, "auto")) *band = 0.0;
    else if (!strcmp(v, "none")) *band = -1.0;
    else if (cli_parse_double(cmd, "--band", v, band)) return -CLI_USAGE;
    else if (!(*band > 0.0) || !isfinite(*band))
        return -cli_usage_error(cmd, "--band needs auto, none or a radius > 0 [lambda/D], got %s", v);
    return 1;
}

int cli_geom_option(const char *cmd, int argc, char **argv, int *i, swfs_geom *g)
{
    const char *a = argv[*i];
    static const char *const names[5] = {"--wavelen", "--teldiam", "--obscur", "--pixscale", "--pupdx"};
    double *const dst[5] = {&g->wavelen, &g->teldiam, &g->obscur, &g->pixscale, &g->pupdx};
    for (int k = 0; k < 5; k++)
        if (!strcmp(a, names[k])) return cli_take_double(cmd, argc, argv, i, dst[k]) ? -CLI_USAGE : 1;
    if (!strcmp(a, "--pupn")) {
        if (cli_take_long(cmd, argc, argv, i, &g->pupn)) return -CLI_USAGE;
        /* (0 is the geometry's "not given": it would be dropped in silence) */
        if (g->pupn < 2 || g->pupn > 8192) return -cli_usage_error(cmd, "--pupn must be 2 to 8192 pupil samples, got %ld", g->pupn);
        return 1;
    }
    if (strcmp(a, "--geom")) return 0;
    const char *path = NULL;
    if (cli_take_string(cmd, argc, argv, i, "a geometry file (FITS header or KEY = VALUE lines)", &path)) return -CLI_USAGE;
    swfs_geom f;
    if (swfs_geom_read_file(path, &f)) return -cli_error(cmd);
    swfs_geom_overlay(g, &f); /* options after --geom still win */
    return 1;
}

int cli_linear_option(const char *cmd, int argc, char **argv, int *i, swfs_linear_files *lf)
{
    const char *a = argv[*i], *fn = "a file name";
    if (!strcmp(a, "--basis")) return cli_take_string(cmd, argc, argv, i, fn, &lf->basis) ? -CLI_USAGE : 1;
    if (!strcmp(a, "--control")) return cli_take_string(cmd, argc, argv, i, fn, &lf->control) ? -CLI_USAGE : 1;
    if (!strcmp(a, "--imat")) return cli_take_string(cmd, argc, argv, i, fn, &lf->imat) ? -CLI_USAGE : 1;
    if (!strcmp(a, "--dm-flip")) { lf->reg.flip_x = 1; return 1; }
    double v;
    if (!strcmp(a, "--dm-pitch") || !strcmp(a, "--dm-rot") || !strcmp(a, "--coef-scale")) {
        if (cli_take_double(cmd, argc, argv, i, &v)) return -CLI_USAGE;
        if (!isfinite(v) || (a[2] != 'd' && v == 0) || (a[5] == 'p' && !(v > 0)))
            return -cli_usage_error(cmd, "%s must be finite%s, got %g", a, a[5] == 'p' ? " and > 0 [m]" : a[2] == 'c' ?
                                    " and non-zero" : " [deg]", v);
        if (a[5] == 'p') lf->reg.pitch = v;
        else if (a[5] == 'r') lf->reg.rot = v * M_PI / 180;
        else lf->scale = v;
        return 1;
    }
    if (strcmp(a, "--dm-offset")) return 0;
    const char *s = cli_next(argc, argv, i);
    char *end;
    double x = s ? strtod(s, &end) : 0, y = 0;
    if (!s || end == s || *end != ',' || (y = strtod(end + 1, &end), *end) || !isfinite(x) || !isfinite(y))
        return -cli_usage_error(cmd, "--dm-offset expects X,Y [m], got '%s'", s ? s : "");
    lf->reg.x0 = x;
    lf->reg.y0 = y;
    return 1;
}

void cli_recon_summary(const char *cmd, const swfs_pipeline_options *o, const char *path, const char *valid,
                       const swfs_pipeline_info *in, const char *noise_how)
{
    const size_t ns = in->nslopes / (in->nlags ? in->nlags : 1); /* per frame */
    if (in->nsub)
        fprintf(stderr, "%s: Shack-Hartmann %zu x %zu, %zu subapertures used (%s%s), %zu slopes per frame%s\n", cmd,
                in->nsub, in->nsub, in->nvalid, valid ? "the map " : ">= 50 % illuminated", valid ? valid : "",
                ns, ns == 2 * in->nvalid && in->nvalid < in->nsub * in->nsub ? " (the used ones')" : "");
    if (o->recon == SWFS_RECON_MAP || o->recon == SWFS_RECON_VK)
        fprintf(stderr, "%s: %s reconstructor from %zu WFS frames: slope noise %.3g rad rms (%s), %zu modes, %.1f "
                "effective\n", cmd, o->recon == SWFS_RECON_MAP ? "MAP" : "vk (von Karman prior)", in->ntrain,
                sqrt(in->noise_var), noise_how ? noise_how : in->noise_given ? "given" : "estimated", in->recon_modes, in->recon_dof);
    if (o->recon == SWFS_RECON_GIVEN && in->nlags)
        fprintf(stderr, "%s: given space-time reconstructor %s: %zu slopes x %zu lags x %zu %s, scale %g, gain "
                "%.3g of the lags' sum on the model's interaction matrix (1: a reconstructor of it)\n", cmd, path, ns,
                in->nlags, in->nact, in->out_pitch > 0 ? "output points of its own" : "actuators", o->recon_scale,
                in->recon_gain);
    else if (o->recon == SWFS_RECON_GIVEN)
        fprintf(stderr, "%s: given reconstructor %s: %zu slopes x %zu %s, scale %g, gain %.3g on the model's "
                "interaction matrix (1: a reconstructor of it)\n", cmd, path, in->nslopes, in->nact,
                in->out_pitch > 0 ? "output points of its own" : "actuators", o->recon_scale,
                in->recon_gain);
    if (o->recon == SWFS_RECON_VK)
        fprintf(stderr, "%s: von Karman outer scale %.3g m (%s)\n", cmd, in->vk_l0,
                o->vk_l0 > 0 ? "given" : "maximum likelihood from the slopes");
    cli_band_summary(cmd, in, o->band > 0);
}

void cli_band_summary(const char *cmd, const swfs_pipeline_info *in, int given)
{
    const char *why = given ? "--band"
                      : in->out_pitch > 0 ? "the sampling band D / (2 pitch) of the map's output points"
                                          : "the subapertures' sampling band nsub/2";
    if (in->band > 0)
        fprintf(stderr, "%s: speckles computed within %.3g lambda/D (%s), 0 in the %zu focal pixels beyond\n", cmd,
                in->band, why, in->band_out);
}

void cli_linear_summary(const char *cmd, const swfs_linear_files *lf, const swfs_pipeline_info *in)
{
    char st[120] = "control matrix";
    if (in->nlags > 1)
        snprintf(st, sizeof st, "space-time control matrix of %zu lags (the telemetry of %zu frames stacked)", in->nlags,
                 in->nlags);
    fprintf(stderr, "%s: linear model %s: %zu basis functions (%zu nonzeros on the pupil%s), %s, scale %g; residual "
            "%.1f nm rms (tip-tilt removed)%s\n", cmd, lf->basis, in->nbasis, in->basis_nnz,
            lf->reg.pitch > 0 ? ", from the DM grid" : "", lf->control ? st : lf->imat ?
            (in->ntrain ? "interaction matrix, MAP reconstructor" : "interaction matrix, SVD reconstructor") :
            "the telemetry as coefficients", lf->scale, in->resid_rms * 1e9,
            in->composed ? "; basis and control folded into one matrix" : "");
    if (lf->imat && in->imat_rank && in->imat_rank < in->nbasis)
        fprintf(stderr, "%s: note: the interaction matrix %s has rank %zu of its %zu basis functions: the telemetry "
                "senses %zu combinations of their coefficients, and the other %zu are never reconstructed (a column "
                "that repeats another, or a mode the sensor cannot see, such as piston)\n", cmd, lf->imat,
                in->imat_rank, in->nbasis, in->imat_rank, in->nbasis - in->imat_rank);
}

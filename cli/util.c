#include "cli.h"
#include "specklewfs/run.h"

#include "specklewfs/config.h"
#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/sim.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/speckles.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

int cli_error(const char *cmd)
{
    /* Library messages of a module named like the command ("report: ...") would read
     * "specklewfs report: report: ..."; say the command once. */
    const char *msg = swfs_last_error();
    size_t n = strlen(cmd);
    if (!strncmp(msg, cmd, n) && msg[n] == ':' && msg[n + 1] == ' ') msg += n + 2;
    fprintf(stderr, "specklewfs %s: %s\n", cmd, msg);
    return CLI_FAIL;
}

int cli_usage_error(const char *cmd, const char *fmt, ...)
{
    va_list ap;
    fprintf(stderr, "specklewfs %s: ", cmd);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fprintf(stderr, " (see 'specklewfs %s --help')\n", cmd);
    return CLI_USAGE;
}

int cli_parse_double(const char *cmd, const char *opt, const char *s, double *out)
{
    if (!s) return cli_usage_error(cmd, "%s needs a value", opt);
    char *end;
    errno = 0;
    double v = strtod(s, &end);
    if (end == s || *end || errno == ERANGE || !isfinite(v))
        return cli_usage_error(cmd, "%s expects a finite number, got '%s'", opt, s);
    *out = v;
    return 0;
}

int cli_parse_long(const char *cmd, const char *opt, const char *s, long *out)
{
    if (!s) return cli_usage_error(cmd, "%s needs a value", opt);
    char *end;
    errno = 0;
    long v = strtol(s, &end, 10);
    if (end == s || *end || errno == ERANGE) return cli_usage_error(cmd, "%s expects an integer, got '%s'", opt, s);
    *out = v;
    return 0;
}

void cli_command_line(int argc, char **argv, char *buf, size_t cap)
{
    size_t len = 0;
    buf[0] = '\0';
    len += (size_t)snprintf(buf, cap, "specklewfs");
    for (int i = 0; i < argc && len < cap; i++) len += (size_t)snprintf(buf + len, cap - len, " %s", argv[i]);
}

double cli_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

void cli_progress(const char *label, size_t k, size_t n)
{
    static int tty = -1;
    if (tty < 0) tty = isatty(fileno(stderr));
    if (tty) {
        fprintf(stderr, "\r%s %zu/%zu", label, k, n);
        if (k == n) fputc('\n', stderr);
    } else if (k == n || (n >= 10 && k % (n / 10 ? n / 10 : 1) == 0)) {
        fprintf(stderr, "%s %zu/%zu\n", label, k, n);
    }
    fflush(stderr);
}

void cli_stage_progress(void *ctx, const char *stage, size_t done, size_t total)
{
    char label[128];
    if (ctx) snprintf(label, sizeof label, "%s %s", (const char *)ctx, stage);
    else snprintf(label, sizeof label, "%s", stage);
    cli_progress(label, done, total);
}

int cli_make_dir(const char *cmd, const char *path)
{
    char tmp[4096];
    if (strlen(path) >= sizeof tmp) return cli_usage_error(cmd, "output folder name too long");
    strcpy(tmp, path);
    for (char *p = tmp + 1; *p; p++) {
        if (*p == '/') {
            *p = '\0';
            if (mkdir(tmp, 0777) != 0 && errno != EEXIST) goto fail;
            *p = '/';
        }
    }
    if (mkdir(tmp, 0777) != 0 && errno != EEXIST) goto fail;
    struct stat sb;
    if (stat(tmp, &sb) != 0 || !S_ISDIR(sb.st_mode)) goto fail;
    return 0;
fail:
    fprintf(stderr, "specklewfs %s: cannot create output folder %s: %s\n", cmd, path, strerror(errno));
    return CLI_FAIL;
}

int cli_paths_check(const char *cmd, swfs_paths *p)
{
    int rc = swfs_paths_status(p);
    swfs_paths_free(p);
    return rc ? cli_error(cmd) : CLI_OK;
}

void cli_paths_outputs_in(swfs_paths *p, const char *dir, const char *const *names, size_t n)
{
    char path[8192];
    for (size_t k = 0; k < n; k++) {
        snprintf(path, sizeof path, "%s/%s", dir, names[k]);
        swfs_paths_output(p, "output", path);
    }
}

void cli_dir_of(const char *path, char *dir, size_t cap)
{
    const char *s = strrchr(path, '/');
    if (!s) { snprintf(dir, cap, "."); return; }
    size_t n = (size_t)(s - path);
    if (n >= cap) n = cap - 1;
    memcpy(dir, path, n);
    dir[n] = 0;
    if (n == 0) snprintf(dir, cap, "/");
}

int cli_parse_tiptilt(const char *cmd, const char *v, int *mode)
{
    if (v && !strcmp(v, "exposure")) *mode = SWFS_TT_EXPOSURE;
    else if (v && !strcmp(v, "frame")) *mode = SWFS_TT_FRAME;
    else if (v && !strcmp(v, "keep")) *mode = SWFS_TT_KEEP;
    else return cli_usage_error(cmd, "--tiptilt needs exposure, frame or keep");
    return 0;
}

const char *const *cli_provenance(int argc, char **argv, size_t *n)
{
    static char line[2048];
    static const char *lines[1] = {line};
    cli_command_line(argc, argv, line, sizeof line);
    *n = 1;
    return lines;
}

int cli_is_help(const char *a) { return !strcmp(a, "-h") || !strcmp(a, "--help"); }

const char *cli_next(int argc, char **argv, int *i) { return *i + 1 < argc ? argv[++*i] : NULL; }

int cli_take_string(const char *cmd, int argc, char **argv, int *i, const char *what, const char **out)
{
    const char *opt = argv[*i], *v = cli_next(argc, argv, i);
    if (!v) return cli_usage_error(cmd, "%s needs %s", opt, what);
    *out = v;
    return 0;
}

int cli_take_double(const char *cmd, int argc, char **argv, int *i, double *out)
{
    const char *opt = argv[*i];
    return cli_parse_double(cmd, opt, cli_next(argc, argv, i), out);
}

int cli_take_range(const char *cmd, int argc, char **argv, int *i, double *out, double lo, int lo_open, double hi,
                   int hi_open, const char *msg)
{
    if (cli_take_double(cmd, argc, argv, i, out)) return CLI_USAGE;
    const double v = *out;
    if (lo_open ? !(v > lo) : !(v >= lo)) return cli_usage_error(cmd, "%s", msg);
    if (hi_open ? !(v < hi) : !(v <= hi)) return cli_usage_error(cmd, "%s", msg);
    return 0;
}

int cli_take_long(const char *cmd, int argc, char **argv, int *i, long *out)
{
    const char *opt = argv[*i];
    return cli_parse_long(cmd, opt, cli_next(argc, argv, i), out);
}

int cli_parse_choice(const char *cmd, const char *opt, const char *v, const char *a, int va, const char *b, int vb,
                     int *out)
{
    if (v && !strcmp(v, a)) *out = va;
    else if (v && !strcmp(v, b)) *out = vb;
    else return cli_usage_error(cmd, "%s expects '%s' or '%s', got '%s'", opt, a, b, v ? v : "");
    return 0;
}

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

int cli_match(const char *cmd, const cli_opt *opts, size_t n, int argc, char **argv, int *i)
{
    const char *a = argv[*i];
    for (size_t k = 0; k < n; k++) {
        const cli_opt *o = &opts[k];
        if (strcmp(a, o->name)) continue;
        int bad = 0;
        switch (o->kind) {
        case CLI_STRING: bad = cli_take_string(cmd, argc, argv, i, o->what, (const char **)o->dst); break;
        case CLI_DOUBLE: bad = cli_take_double(cmd, argc, argv, i, (double *)o->dst); break;
        case CLI_LONG: bad = cli_take_long(cmd, argc, argv, i, (long *)o->dst); break;
        case CLI_SET: *(int *)o->dst = o->value; break;
        }
        return bad ? -1 : (int)k + 1;
    }
    return 0;
}

static int positional(const cli_args *c, const char *a)
{
    if (a[0] == '-' && a[1]) return cli_usage_error(c->cmd, "unknown option '%s'", a);
    for (size_t k = 0; k < c->npos; k++)
        if (!*c->pos[k]) {
            *c->pos[k] = a;
            return 0;
        }
    if (c->rest) {
        c->rest[(*c->nrest)++] = a;
        return 0;
    }
    return cli_usage_error(c->cmd, "unexpected argument '%s'", a);
}

int cli_parse_args(const cli_args *c, int argc, char **argv)
{
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        if (c->usage && cli_is_help(a)) {
            fputs(c->usage, stdout);
            return -1;
        }
        int m = cli_match(c->cmd, c->opts, c->nopts, argc, argv, &i);
        if (m < 0) return CLI_USAGE;
        if (m > 0) continue;
        int t = c->special ? c->special(c->ctx, argc, argv, &i) : 0;
        if (t < 0) return -t;
        if (t == 0 && positional(c, a)) return CLI_USAGE;
    }
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

int cli_geom_option(const char *cmd, int argc, char **argv, int *i, swfs_geom *g)
{
    const char *a = argv[*i];
    static const char *const names[5] = {"--wavelen", "--teldiam", "--obscur", "--pixscale", "--pupdx"};
    double *const dst[5] = {&g->wavelen, &g->teldiam, &g->obscur, &g->pixscale, &g->pupdx};
    for (int k = 0; k < 5; k++)
        if (!strcmp(a, names[k])) return cli_take_double(cmd, argc, argv, i, dst[k]) ? -CLI_USAGE : 1;
    if (!strcmp(a, "--pupn")) return cli_take_long(cmd, argc, argv, i, &g->pupn) ? -CLI_USAGE : 1;
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
                       const swfs_pipeline_info *in)
{
    if (in->nsub)
        fprintf(stderr, "%s: Shack-Hartmann %zu x %zu, %zu subapertures used (%s%s), %zu slopes per frame%s\n", cmd,
                in->nsub, in->nsub, in->nvalid, valid ? "the map " : ">= 50 % illuminated", valid ? valid : "",
                in->nslopes, in->nslopes == 2 * in->nvalid && in->nvalid < in->nsub * in->nsub ? " (the used ones')" : "");
    if (o->recon == SWFS_RECON_MAP || o->recon == SWFS_RECON_VK)
        fprintf(stderr, "%s: %s reconstructor from %zu WFS frames: slope noise %.3g rad rms (%s), %zu modes, %.1f "
                "effective\n", cmd, o->recon == SWFS_RECON_MAP ? "MAP" : "vk (von Karman prior)", in->ntrain,
                sqrt(in->noise_var), in->noise_given ? "given" : "estimated", in->recon_modes, in->recon_dof);
    if (o->recon == SWFS_RECON_GIVEN)
        fprintf(stderr, "%s: given reconstructor %s: %zu slopes x %zu actuators, scale %g, gain %.3g on the model's "
                "interaction matrix (1: a reconstructor of it)\n", cmd, path, in->nslopes, in->nact, o->recon_scale,
                in->recon_gain);
    if (o->recon == SWFS_RECON_VK)
        fprintf(stderr, "%s: von Karman outer scale %.3g m (%s)\n", cmd, in->vk_l0,
                o->vk_l0 > 0 ? "given" : "maximum likelihood from the slopes");
}

void cli_linear_summary(const char *cmd, const swfs_linear_files *lf, const swfs_pipeline_info *in)
{
    fprintf(stderr, "%s: linear model %s: %zu basis functions (%zu nonzeros on the pupil%s), %s, scale %g; residual "
            "%.1f nm rms (tip-tilt removed)%s\n", cmd, lf->basis, in->nbasis, in->basis_nnz,
            lf->reg.pitch > 0 ? ", from the DM grid" : "", lf->control ? "control matrix" : lf->imat ?
            (in->ntrain ? "interaction matrix, MAP reconstructor" : "interaction matrix, SVD reconstructor") :
            "the telemetry as coefficients", lf->scale, in->resid_rms * 1e9,
            in->composed ? "; basis and control folded into one matrix" : "");
}

int cli_parse_xy(const char *cmd, const char *opt, const char *s, long *x, long *y)
{
    if (!s) return cli_usage_error(cmd, "%s needs X,Y", opt);
    char *end;
    errno = 0;
    *x = strtol(s, &end, 10);
    if (end == s || *end != ',') return cli_usage_error(cmd, "%s expects X,Y (integers), got '%s'", opt, s);
    const char *t = end + 1;
    *y = strtol(t, &end, 10);
    if (end == t || *end || errno) return cli_usage_error(cmd, "%s expects X,Y (integers), got '%s'", opt, s);
    return 0;
}

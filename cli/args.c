/* The command line's argument parsing: numbers, choices, option tables (cli.h). */
#include "cli.h"
#include "specklewfs/speckles.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int cli_parse_double(const char *cmd, const char *opt, const char *s, double *out)
{
    if (!s) return cli_usage_error(cmd, "%s needs a value", opt);
    char *end;
    errno = 0;
    double v = strtod(s, &end);
    /* (strtod reads C's hexadecimal numbers too: 0x10 would be 16) */
    if (end == s || *end || errno == ERANGE || !isfinite(v) || strpbrk(s, "xX"))
        return cli_usage_error(cmd, "%s expects a finite decimal number, got '%s'", opt, s);
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

int cli_parse_tiptilt(const char *cmd, const char *v, int *mode)
{
    for (int m = SWFS_TT_EXPOSURE; v && m <= SWFS_TT_KEEP; m++) /* the library's spelling (TIPTILT) */
        if (!strcmp(v, swfs_tiptilt_name(m))) { *mode = m; return 0; }
    return cli_usage_error(cmd, "--tiptilt needs exposure, frame or keep");
}

int cli_is_help(const char *a) { return !strcmp(a, "-h") || !strcmp(a, "--help"); }

const char *cli_next(int argc, char **argv, int *i) { return *i + 1 < argc ? argv[++*i] : NULL; }

int cli_take_string(const char *cmd, int argc, char **argv, int *i, const char *what, const char **out)
{
    const char *opt = argv[*i], *v = cli_next(argc, argv, i);
    if (!v) return cli_usage_error(cmd, "%s needs %s", opt, what);
    /* "-o --gain": the next option, not a name (a file whose name starts so: ./--name) */
    if (v[0] == '-' && v[1] == '-' && v[2])
        return cli_usage_error(cmd, "%s needs %s, got the option '%s' (a file of that name: write ./%s)", opt, what, v, v);
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

int cli_check_mins(const char *cmd, const cli_min *m, size_t n)
{
    for (size_t k = 0; k < n; k++)
        if (m[k].value < m[k].min)
            return cli_usage_error(cmd, "%s must be >= %ld, got %ld", m[k].name, m[k].min, m[k].value);
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

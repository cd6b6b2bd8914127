/* The page of a `specklewfs demo -o DIR` folder: the recovery table as the demo wrote it
 * (DIR/recovery.tsv, whatever its columns), one section per noise level DIR/sigma<level>/
 * with its key numbers and figures, and the closed loop (DIR/loop/loop.tsv). */
#include "report_internal.h"

#include "specklewfs/status.h"
#include "specklewfs/table.h"

#include <dirent.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct level {
    double sigma;
    char name[256]; /* the folder: sigma<level> */
} level;

/* "sigma<number>" -> the number; 0 if name is not one. */
static int level_name(const char *name, double *sigma)
{
    if (strncmp(name, "sigma", 5) || !name[5]) return 0;
    char *end;
    *sigma = strtod(name + 5, &end);
    return !*end && isfinite(*sigma) && *sigma >= 0 && strlen(name) < 256;
}

static int cmp_level(const void *a, const void *b)
{
    double x = ((const level *)a)->sigma, y = ((const level *)b)->sigma;
    return (x > y) - (x < y);
}

/* The sigma<level>/ folders of dir holding halo.fits or wavefront.fits, by level. */
static int find_levels(const char *dir, level *lv, size_t cap, size_t *n)
{
    *n = 0;
    DIR *d = opendir(dir);
    if (!d) return swfs_fail(SWFS_ERR_IO, "%s: cannot list the folder", dir);
    struct dirent *e;
    int rc = SWFS_OK;
    while ((e = readdir(d))) {
        double s;
        char sub[REP_PATHMAX], p1[REP_PATHMAX], p2[REP_PATHMAX];
        if (!level_name(e->d_name, &s) || rep_join(sub, dir, e->d_name) || !rep_dir_exists(sub)) continue;
        if (rep_join(p1, sub, "halo.fits") || rep_join(p2, sub, "wavefront.fits")) continue;
        if (!rep_file_exists(p1) && !rep_file_exists(p2)) continue;
        if (*n == cap) {
            rc = swfs_fail(SWFS_ERR_ARG, "%s: more than %zu noise-level folders", dir, cap);
            break;
        }
        lv[*n].sigma = s;
        snprintf(lv[*n].name, sizeof lv[*n].name, "%s", e->d_name);
        (*n)++;
    }
    closedir(d);
    swfs_clear_error();
    if (!rc) qsort(lv, *n, sizeof *lv, cmp_level);
    return rc;
}

static int table_at(const char *dir, const char *name, swfs_table **t)
{
    char path[REP_PATHMAX];
    *t = NULL;
    int rc = rep_join(path, dir, name);
    if (!rc && rep_file_exists(path)) rc = swfs_table_read(path, t);
    return rc;
}

int rep_is_demo(const char *dir)
{
    char path[REP_PATHMAX];
    level lv[SWFS_REPORT_MAX_LEVELS];
    size_t n = 0;
    if ((!rep_join(path, dir, "recovery.tsv") && rep_file_exists(path)) ||
        (!rep_join(path, dir, "loop/loop.tsv") && rep_file_exists(path)))
        return 1;
    int rc = find_levels(dir, lv, SWFS_REPORT_MAX_LEVELS, &n);
    swfs_clear_error();
    return rc || n > 0; /* too many levels is still a demo folder: the run says so */
}

/* One noise level: its figures into out_dir/sigma<level>/, its section into body. */
static int level_section(rep_ctx *d, const level *lv, rep_strbuf *body, swfs_report_level *kn)
{
    char run[REP_PATHMAX], out[REP_PATHMAX], label[320], href[300];
    swfs_report_summary *sum = malloc(sizeof *sum);
    rep_ctx c;
    int rc = sum ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "report: out of memory");
    if (!rc) rc = rep_join(run, d->run_dir, lv->name);
    if (!rc) rc = rep_join(out, d->out_dir, lv->name);
    if (rc) {
        free(sum);
        return rc;
    }
    rep_summary_init(sum);
    snprintf(label, sizeof label, "σ = %g counts: ", lv->sigma);
    snprintf(href, sizeof href, "%s/", lv->name);
    size_t nfig0 = d->top->nfigures;
    rc = rep_ctx_init(&c, run, out, &d->opt, sum, d->top);
    c.href = href;
    c.label = label;
    c.in_demo = 1;
    if (!rc) rc = rep_make_dirs(out);
    if (!rc) rc = rep_run_folder(&c);
    if (!rc) {
        char id[300];
        snprintf(id, sizeof id, "%s-", lv->name);
        rep_printf(body, "<section id=\"%s\">\n<h2>Noise level σ = %g counts</h2>\n", lv->name, lv->sigma);
        rep_key_numbers(body, sum, id);
        if (c.figs.len) rep_printf(body, "%s", c.figs.s);
        rep_printf(body, "</section>\n");
        *kn = (swfs_report_level){lv->sigma, sum->valid_fraction, sum->median_snr, sum->wfe_rms, sum->strehl,
                                  sum->ncp_rms, sum->err_rms, d->top->nfigures - nfig0};
    }
    rep_ctx_free(&c);
    free(sum);
    return rc;
}

/* The recovery table, and a note for each level it lists without a folder. */
static void recovery_section(rep_ctx *d, const swfs_table *t, const level *lv, size_t nlv, rep_strbuf *b)
{
    rep_printf(b, "<h2>NCP recovery</h2>\n");
    if (!t) {
        rep_printf(b, "<p>No recovery.tsv in the folder (written by <code>specklewfs demo</code>).</p>\n");
        return;
    }
    rep_table(b, t, "recovery");
    rep_printf(b, "<p>The table <code>specklewfs demo</code> printed (recovery.tsv): for each camera noise level "
                  "σ [counts], the pixels where the paper's per-pixel g is defined (valid) or not, the error of the "
                  "recovered NCP wavefront against the injected one [nm rms inside the pupil, piston and tip/tilt "
                  "removed] for each estimator column, and the median SNR. <code>paper</code> is the paper's "
                  "formulae end to end; the others use specklewfs' regularized g (HALO = eq:TheAnswer, HALO_LF = "
                  "eq:PSI-LowFreq, +SNR the Wiener weight that <code>specklewfs pupil</code> uses by default, the "
                  "estimate whose figures follow).</p>\n");
    long cs = swfs_table_col(t, "sigma");
    for (size_t r = 0; cs >= 0 && r < t->nrows; r++) {
        double s = t->v[r * t->ncols + (size_t)cs];
        size_t k = 0;
        while (k < nlv && lv[k].sigma != s) k++;
        if (k == nlv) rep_note(d, "recovery.tsv lists σ = %g counts but sigma%g/ has no products", s, s);
    }
    for (size_t k = 0; cs >= 0 && k < nlv; k++) {
        size_t r = 0;
        while (r < t->nrows && t->v[r * t->ncols + (size_t)cs] != lv[k].sigma) r++;
        if (r == t->nrows) rep_note(d, "%s/ is not in recovery.tsv (left from an earlier demo?)", lv[k].name);
    }
}

/* The closed loop: its table and loop.png. */
static int loop_section(rep_ctx *d, const swfs_table *t, rep_strbuf *b)
{
    rep_printf(b, "<section id=\"loop\">\n<h2>Closed loop</h2>\n");
    rep_table(b, t, "loop-table");
    rep_printf(b, "<p>loop/loop.tsv: row k is the state after k corrections (estimate → DM offsets → gain, new "
                  "turbulence each iteration). resid: residual NCP wavefront [nm rms]; strehl: peak of the "
                  "simulated long-exposure PSF; contrast: mean static-halo intensity in 2-6 λ/D over its peak; "
                  "est_err: the estimate's error against the true residual (docs/closed-loop.md).</p>\n");
    int drawn = 0, rc = swfs_plot_available() ? rep_fig_loop(t, d->out_dir, &drawn) : SWFS_OK;
    if (!rc && drawn)
        rep_add_figure(d, "loop.png", REP_W_ROW2, REP_H_ROW2, "Closing the loop",
                       "Residual NCP wavefront (piston removed, and with tip/tilt also removed) and the error of "
                       "each iteration's estimate against the number of corrections applied; the Strehl ratio of "
                       "the simulated long-exposure PSF with its no-NCP ceiling.");
    if (d->figs.len) rep_printf(b, "%s", d->figs.s);
    rep_printf(b, "</section>\n");
    return rc;
}

int rep_demo_run(const char *dir, const char *out_dir, const swfs_report_options *opt, swfs_report_summary *s)
{
    level lv[SWFS_REPORT_MAX_LEVELS];
    size_t nlv = 0;
    swfs_table *rec = NULL, *loop = NULL;
    rep_strbuf levels = {0}, body = {0};
    rep_ctx d;
    int rc = rep_ctx_init(&d, dir, out_dir, opt, s, s);
    if (!rc) rc = find_levels(dir, lv, SWFS_REPORT_MAX_LEVELS, &nlv);
    if (!rc) rc = table_at(dir, "recovery.tsv", &rec);
    if (!rc) rc = table_at(dir, "loop/loop.tsv", &loop);
    if (!rc) rc = rep_make_dirs(d.out_dir);
    if (rc) goto done;
    s->demo = 1;
    if (!swfs_plot_available()) rep_note(&d, "no figures: this build has no PLplot pngcairo device");
    for (size_t k = 0; k < nlv && !rc; k++) rc = level_section(&d, &lv[k], &levels, &s->levels[s->nlevels++]);
    if (rc) goto done;
    rep_printf(&body, "<p id=\"contents\">");
    for (size_t k = 0; k < nlv; k++)
        rep_printf(&body, "%s<a href=\"#%s\">σ = %g counts</a>", k ? " · " : "Noise levels: ", lv[k].name, lv[k].sigma);
    if (loop) rep_printf(&body, "%s<a href=\"#loop\">closed loop</a>", nlv ? " · " : "");
    rep_printf(&body, "</p>\n");
    recovery_section(&d, rec, lv, nlv, &body);
    s->recovery_rows = rec ? rec->nrows : 0;
    if (!nlv) rep_note(&d, "no sigma<level>/ folder with halo.fits or wavefront.fits: no figures per noise level");
    if (!loop) rep_note(&d, "loop/loop.tsv not found: no closed-loop section (demo --loop-iterations 0?)");
    rep_notes(&body, s);
    if (levels.len) rep_printf(&body, "%s", levels.s);
    if (loop) {
        s->loop_rows = loop->nrows;
        rc = loop_section(&d, loop, &body);
    }
    char title[REP_PATHMAX + 64];
    if (opt->title) snprintf(title, sizeof title, "%s", opt->title);
    else snprintf(title, sizeof title, "specklewfs demo: %s", dir);
    if (!rc) rc = rep_write_page(d.out_dir, title, dir, &body, s);
done:
    swfs_table_free(rec);
    swfs_table_free(loop);
    free(levels.s);
    free(body.s);
    rep_ctx_free(&d);
    return rc;
}

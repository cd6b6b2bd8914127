/* loop.png: the closed loop of a demo (or `specklewfs correct`) folder from its table
 * loop.tsv: the residual NCP, the estimate's error and the Strehl ratio against the
 * number of corrections applied (docs/closed-loop.md). */
#include "report_internal.h"

#include "specklewfs/status.h"
#include "specklewfs/table.h"

#include <math.h>
#include <stdlib.h>

typedef struct curve {
    const char *col, *label;
    swfs_color color;
    swfs_linestyle style;
} curve;

/* The curves of one panel that the table has; returns how many were drawn. */
static int curves_panel(swfs_plot *p, int panel, const swfs_table *t, const double *x, double *y, const curve *cv,
                        size_t ncv, const char *title, const char *ylabel, int from_zero, int *drawn)
{
    double lo = INFINITY, hi = -INFINITY;
    *drawn = 0;
    for (size_t k = 0; k < ncv; k++) {
        long c = swfs_table_col(t, cv[k].col);
        for (size_t r = 0; c >= 0 && r < t->nrows; r++) {
            double v = t->v[r * t->ncols + (size_t)c];
            if (isfinite(v)) lo = fmin(lo, v), hi = fmax(hi, v);
        }
    }
    if (!(hi >= lo)) return SWFS_OK;
    if (from_zero) lo = fmin(lo, 0.0);
    double pad = hi > lo ? 0.08 * (hi - lo) : 0.05 * fabs(hi) + 1e-12;
    swfs_plot_axes_spec a = {title, "corrections applied", ylabel, -0.3, x[t->nrows - 1] + 0.3,
                             from_zero ? lo : lo - pad, hi + 3.0 * pad, 0};
    int rc = swfs_plot_panel(p, panel);
    if (!rc) rc = swfs_plot_axes(p, &a);
    swfs_plot_legend_entry e[8];
    size_t ne = 0;
    for (size_t k = 0; k < ncv && !rc && ne < 8; k++) {
        long c = swfs_table_col(t, cv[k].col);
        if (c < 0) continue;
        size_t m = 0;
        double xs[1024];
        for (size_t r = 0; r < t->nrows && m < 1024; r++) {
            double v = t->v[r * t->ncols + (size_t)c];
            if (!isfinite(v)) continue;
            xs[m] = x[r];
            y[m++] = v;
        }
        rc = swfs_plot_line(p, xs, y, m, cv[k].color, cv[k].style, 2.0);
        if (!rc) rc = swfs_plot_points(p, xs, y, m, cv[k].color, 0.9);
        e[ne++] = (swfs_plot_legend_entry){cv[k].label, cv[k].color, 0, cv[k].style};
    }
    if (!rc && ne) rc = swfs_plot_legend(p, e, ne);
    *drawn = (int)ne;
    return rc;
}

int rep_fig_loop(const swfs_table *t, const char *out_dir, int *drawn)
{
    static const curve wf[] = {
        {"resid_nm", "residual NCP (piston removed)", SWFS_COLOR_BLUE, SWFS_LINE_SOLID},
        {"resid_ptt_nm", "residual NCP (tip/tilt also removed)", SWFS_COLOR_GRAY, SWFS_LINE_DASHED},
        {"est_err_nm", "error of the estimate", SWFS_COLOR_ORANGE, SWFS_LINE_SOLID},
    };
    static const curve st[] = {
        {"strehl", "Strehl of the long-exposure PSF", SWFS_COLOR_BLUE, SWFS_LINE_SOLID},
        {"strehl_ao", "no-NCP ceiling (AO residual alone)", SWFS_COLOR_GRAY, SWFS_LINE_DASHED},
    };
    *drawn = 0;
    long ci = swfs_table_col(t, "iter");
    if (t->nrows == 0 || t->nrows > 1024) return SWFS_OK;
    double *x = malloc(t->nrows * sizeof *x), *y = malloc(t->nrows * sizeof *y);
    char path[REP_PATHMAX];
    swfs_plot *p = NULL;
    int rc = x && y ? rep_join(path, out_dir, "loop.png") : swfs_fail(SWFS_ERR_NOMEM, "loop figure: out of memory");
    for (size_t r = 0; !rc && r < t->nrows; r++) x[r] = ci >= 0 ? t->v[r * t->ncols + (size_t)ci] : (double)r;
    if (!rc) rc = swfs_plot_create(&p, path, REP_W_ROW2, REP_H_ROW2, 2, 1);
    int d1 = 0, d2 = 0;
    if (!rc) rc = curves_panel(p, 0, t, x, y, wf, 3, "residual NCP wavefront", "rms [nm]", 1, &d1);
    if (!rc) rc = curves_panel(p, 1, t, x, y, st, 2, "Strehl ratio", "Strehl", 0, &d2);
    if (!rc && d1 + d2 > 0) {
        rc = swfs_plot_commit(p);
        p = NULL;
        *drawn = !rc;
    }
    swfs_plot_abort(p);
    free(x);
    free(y);
    return rc;
}

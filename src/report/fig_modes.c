/* modes.png: the slopes' variances along the DM modes (timeseries.h swfs_ts_mode_variance)
 * of an observation and of the loops simulated to match it, on log-log axes, each knee
 * marked (swfs_mode_knee): what `teach` read the loop's modal filter from. */
#include "specklewfs/plot.h"
#include "specklewfs/report.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

int swfs_fig_modes(const char *png, const double *const *var, const size_t *n, const size_t *knee,
                   const char *const *label, size_t ncurves)
{
    if (!ncurves || ncurves > 6) return swfs_fail(SWFS_ERR_ARG, "modes figure: %zu curves (1 to 6)", ncurves);
    double xmax = 0, lo = INFINITY, hi = -INFINITY;
    size_t nmax = 0;
    for (size_t c = 0; c < ncurves; c++) {
        nmax = n[c] > nmax ? n[c] : nmax;
        for (size_t j = 0; j < n[c]; j++)
            if (var[c][j] > 0) lo = fmin(lo, log10(var[c][j])), hi = fmax(hi, log10(var[c][j]));
    }
    if (!(hi >= lo) || nmax < 2) return swfs_fail(SWFS_ERR_VALUE, "modes figure: no positive variance to draw");
    xmax = log10((double)nmax);
    double *x = malloc(nmax * sizeof *x), *y = malloc(nmax * sizeof *y);
    if (!x || !y) { free(x); free(y); return swfs_fail(SWFS_ERR_NOMEM, "modes figure: out of memory"); }
    swfs_plot *p = NULL;
    int rc = swfs_plot_create(&p, png, 900, 600, 1, 1);
    const double pad = 0.05 * (hi - lo) + 1e-3;
    swfs_plot_axes_spec a = {"slopes' variance along the DM modes (each mode less the lower ones)",
                             "log10 mode (after piston)", "log10 variance [rad^2]", 0.0, xmax, lo - pad,
                             hi + 4 * pad, 0};
    if (!rc) rc = swfs_plot_panel(p, 0);
    if (!rc) rc = swfs_plot_axes(p, &a);
    static const swfs_color col[6] = {SWFS_COLOR_BLACK, SWFS_COLOR_RED, SWFS_COLOR_BLUE, SWFS_COLOR_ORANGE,
                                      SWFS_COLOR_GREEN, SWFS_COLOR_GRAY};
    swfs_plot_legend_entry e[6];
    char text[6][96];
    for (size_t c = 0; !rc && c < ncurves; c++) {
        size_t m = 0;
        for (size_t j = 0; j < n[c]; j++)
            if (var[c][j] > 0) { x[m] = log10((double)(j + 1)); y[m++] = log10(var[c][j]); }
        rc = swfs_plot_line(p, x, y, m, col[c], SWFS_LINE_SOLID, c ? 1.5 : 2.5);
        if (!rc && knee[c]) {
            const double kx[2] = {log10((double)knee[c]), log10((double)knee[c])}, ky[2] = {lo - pad, hi + 4 * pad};
            rc = swfs_plot_line(p, kx, ky, 2, col[c], SWFS_LINE_DASHED, 1.0);
        }
        snprintf(text[c], sizeof text[c], "%s: knee at mode %zu", label[c], knee[c]);
        e[c] = (swfs_plot_legend_entry){text[c], col[c], 0, SWFS_LINE_SOLID};
    }
    if (!rc) rc = swfs_plot_legend(p, e, ncurves);
    free(x);
    free(y);
    if (rc) { swfs_plot_abort(p); return rc; }
    return swfs_plot_commit(p);
}

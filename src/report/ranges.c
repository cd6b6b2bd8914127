/* Colour ranges from robust percentiles of the displayed pixels (docs/report.md), and the
 * focal-plane panel geometry (docs/conventions.md sampling) shared by the focal figures. */
#include "report_internal.h"

#include "specklewfs/numeric.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

double swfs_report_percentile(const double *v, size_t n, const unsigned char *mask, double pct)
{
    double *w = malloc((n ? n : 1) * sizeof *w);
    if (!w) return NAN;
    size_t m = 0;
    for (size_t k = 0; k < n; k++)
        if (isfinite(v[k]) && (!mask || mask[k])) w[m++] = v[k];
    double r = NAN;
    if (m) {
        swfs_sort_doubles(w, m);
        double pos = fmin(fmax(pct, 0.0), 100.0) / 100.0 * (double)(m - 1);
        size_t k = (size_t)floor(pos);
        double f = pos - (double)k;
        r = k + 1 < m ? w[k] + f * (w[k + 1] - w[k]) : w[k];
    }
    free(w);
    return r;
}

const swfs_report_range *swfs_report_find_range(const swfs_report_summary *s, const char *name)
{
    for (size_t k = 0; k < s->nranges; k++)
        if (!strcmp(s->ranges[k].name, name)) return &s->ranges[k];
    return NULL;
}

swfs_report_range rep_prepare(rep_ctx *c, const char *name, const double *v, size_t n, const unsigned char *mask,
                              enum rep_range_kind kind, double scale, double flo, double fhi, double *z)
{
    const double plo = c->opt.pct_lo, phi = c->opt.pct_hi, dec = c->opt.log_decades;
    swfs_report_range r;
    memset(&r, 0, sizeof r);
    snprintf(r.name, sizeof r.name, "%s", name);
    for (size_t k = 0; k < n; k++) z[k] = (!mask || mask[k]) && isfinite(v[k]) ? v[k] * scale : NAN;
    if (kind == R_AUTO) {
        r.lo = swfs_report_percentile(z, n, NULL, plo);
        r.hi = swfs_report_percentile(z, n, NULL, phi);
        if (r.lo > 0 && r.hi / r.lo > 100.0) kind = R_LOG;
    }
    if (kind == R_LOG || kind == R_LOG_FIXED) {
        for (size_t k = 0; k < n; k++) z[k] = z[k] > 0 ? log10(z[k]) : NAN;
        r.log = 1;
        r.hi = swfs_report_percentile(z, n, NULL, phi);
        r.lo = kind == R_LOG ? fmax(swfs_report_percentile(z, n, NULL, plo), r.hi - dec) : r.hi - dec;
    } else if (kind == R_SYM) {
        double *a = malloc((n ? n : 1) * sizeof *a);
        double m = NAN;
        if (a) {
            for (size_t k = 0; k < n; k++) a[k] = fabs(z[k]);
            m = swfs_report_percentile(a, n, NULL, phi);
            free(a);
        }
        r.lo = -m;
        r.hi = m;
    } else if (kind == R_FIXED) {
        r.lo = flo;
        r.hi = fhi;
    }
    if (!isfinite(r.lo) || !isfinite(r.hi)) r.lo = 0.0, r.hi = 1.0; /* nothing to show */
    swfs_report_summary *s = c->top;
    if (s->nranges < SWFS_REPORT_MAX_RANGES) s->ranges[s->nranges++] = r;
    return r;
}

void rep_apply_range(swfs_plot_image_spec *s, const swfs_report_range *r)
{
    s->zmin = r->lo;
    s->zmax = r->hi;
    s->zlog = r->log;
}

int rep_image_panel(swfs_plot *p, int panel, swfs_plot_image_spec *s, const swfs_report_range *r, const char *title,
                    const char *zlabel, swfs_cmap cmap, const double *z, size_t nx, size_t ny)
{
    s->title = title;
    s->zlabel = zlabel;
    s->cmap = cmap;
    rep_apply_range(s, r);
    int rc = swfs_plot_panel(p, panel);
    return rc ? rc : swfs_plot_image(p, z, nx, ny, s);
}

unsigned char *rep_mask_from(const swfs_real *valid, size_t n)
{
    if (!valid) return NULL;
    unsigned char *m = malloc(n ? n : 1);
    if (m)
        for (size_t k = 0; k < n; k++) m[k] = valid->data[k] > 0.5;
    return m;
}

int rep_have_pixscale(const rep_ctx *c) { return isfinite(c->geom.pixscale) && c->geom.pixscale > 0; }

double rep_focal_x(const rep_ctx *c, double i, size_t n)
{
    double ps = rep_have_pixscale(c) ? c->geom.pixscale : 1.0;
    return (i - (double)(n / 2)) * ps;
}

void rep_focal_spec(const rep_ctx *c, swfs_plot_image_spec *s)
{
    memset(s, 0, sizeof *s);
    s->xlabel = rep_have_pixscale(c) ? "x [λ/D]" : "x [pixel]";
    s->ylabel = rep_have_pixscale(c) ? "y [λ/D]" : "y [pixel]";
    s->x0 = rep_focal_x(c, 0, c->nx);
    s->x1 = rep_focal_x(c, (double)c->nx - 1, c->nx);
    s->y0 = rep_focal_x(c, 0, c->ny);
    s->y1 = rep_focal_x(c, (double)c->ny - 1, c->ny);
}

int rep_best_pixel(const rep_ctx *c, const double *score, const unsigned char *ok, double rmin, double rmax,
                   long *bi, long *bj)
{
    double best = -INFINITY;
    *bi = *bj = -1;
    for (size_t j = 0; j < c->ny; j++)
        for (size_t i = 0; i < c->nx; i++) {
            size_t k = j * c->nx + i;
            if (ok && !ok[k]) continue;
            if (!isfinite(score[k])) continue;
            if (rep_have_pixscale(c)) {
                double r = hypot(rep_focal_x(c, (double)i, c->nx), rep_focal_x(c, (double)j, c->ny));
                if (r < rmin || r > rmax) continue;
            }
            if (score[k] > best) {
                best = score[k];
                *bi = (long)i;
                *bj = (long)j;
            }
        }
    return *bi >= 0;
}

int rep_check_focal_shape(rep_ctx *c, const char *path, size_t nx, size_t ny)
{
    if (c->nx == 0) {
        c->nx = nx;
        c->ny = ny;
        return SWFS_OK;
    }
    if (nx != c->nx || ny != c->ny)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: focal grid is %zux%zu but the run's other products are %zux%zu", path,
                         nx, ny, c->nx, c->ny);
    return SWFS_OK;
}

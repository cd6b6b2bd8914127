/* PNG figures through PLplot (pngcairo). See include/specklewfs/plot.h: not thread-safe. */
#include "specklewfs/plot.h"

#include "specklewfs/array.h"
#include "specklewfs/atomic.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifdef SWFS_HAVE_PLPLOT
#include <plplot.h>

#define SWFS_PLOT_DPI 90.0

struct swfs_plot {
    PLINT strm;
    int ended;
    int ncols, nrows;
    int width, height;
    double chr_mm; /* character height */
    double px0, px1, py0, py1; /* current panel, normalized page coordinates */
    char path[4096];
    swfs_atomic *atom;     /* the figure's part file (atomic.h: unique name, fsync, rename) */
    PLINT errcode;
    char errmsg[1024];
    /* Layout of the last image, for contours. */
    double img_x0, img_x1, img_y0, img_y1;
    size_t img_nx, img_ny;
};

static int plot_check(swfs_plot *p, const char *what)
{
    if (p->errcode) {
        char msg[1024];
        snprintf(msg, sizeof msg, "%s", p->errmsg);
        for (char *c = msg; *c; c++)
            if (*c == '\n') *c = ' ';
        p->errcode = 0;
        p->errmsg[0] = '\0';
        return swfs_fail(SWFS_ERR_INTERNAL, "%s: PLplot failed in %s:%s", p->path, what, msg);
    }
    return SWFS_OK;
}

int swfs_plot_available(void)
{
    static int cached = -1;
    if (cached >= 0) return cached;
    const char **menu = NULL, **names = NULL;
    int n = 64;
    menu = calloc((size_t)n, sizeof *menu);
    names = calloc((size_t)n, sizeof *names);
    cached = 0;
    if (menu && names) {
        plgFileDevs(&menu, &names, &n);
        for (int i = 0; i < n; i++)
            if (names[i] && !strcmp(names[i], "pngcairo")) cached = 1;
    }
    free(menu);
    free(names);
    return cached;
}

/* Our line colours (cmap0). Index 0 is the white background. */
static const PLINT pal_r[] = {255, 0, 200, 30, 128, 235, 20, 255, 200};
static const PLINT pal_g[] = {255, 0, 30, 80, 128, 130, 140, 255, 200};
static const PLINT pal_b[] = {255, 0, 30, 200, 128, 0, 60, 255, 200};

int swfs_plot_create(swfs_plot **out, const char *path, int width, int height, int ncols, int nrows)
{
    *out = NULL;
    if (!path || width < 64 || height < 64 || width > 20000 || height > 20000 || ncols < 1 || nrows < 1)
        return swfs_fail(SWFS_ERR_ARG, "plot: need a path, 64..20000 pixels and at least one panel");
    if (strlen(path) >= 4096) return swfs_fail(SWFS_ERR_ARG, "plot: path too long");
    if (!swfs_plot_available())
        return swfs_fail(SWFS_ERR_ARG, "%s: PLplot's pngcairo device is not installed (Debian: plplot-driver-cairo)",
                         path);
    swfs_plot *p = calloc(1, sizeof *p);
    if (!p) return swfs_fail(SWFS_ERR_NOMEM, "plot: out of memory");
    snprintf(p->path, sizeof p->path, "%s", path);
    p->ncols = ncols;
    p->nrows = nrows;
    /* The one atomic writer of every product (a unique part name per process, fsync, then
     * rename). Preflight: PLplot exits the process if it cannot open its output file. */
    int arc = swfs_atomic_begin(&p->atom, path, 0);
    if (arc) {
        free(p);
        return arc;
    }
    FILE *f = fopen(swfs_atomic_part(p->atom), "wb");
    if (!f) {
        swfs_atomic_abort(p->atom);
        free(p);
        return swfs_fail(SWFS_ERR_IO, "%s: cannot create the figure file", path);
    }
    fclose(f);

    plmkstrm(&p->strm);
    if (p->strm < 0) {
        swfs_atomic_abort(p->atom);
        free(p);
        return swfs_fail(SWFS_ERR_INTERNAL, "%s: PLplot has no free stream", path);
    }
    plsError(&p->errcode, p->errmsg);
    plsdev("pngcairo");
    plsfnam(swfs_atomic_part(p->atom));
    p->width = width;
    p->height = height;
    plspage(SWFS_PLOT_DPI, SWFS_PLOT_DPI, width, height, 0, 0);
    plscmap0(pal_r, pal_g, pal_b, (PLINT)(sizeof pal_r / sizeof pal_r[0]));
    /* One page; panels are viewports we place ourselves (PLplot's subpages misplace
     * colorbars after the first subpage). */
    plssub(1, 1);
    plinit();
    pladv(0);
    /* Text height from the panel size: ~3.2 % of the smaller side, within 2.6 .. 4.8 mm. */
    double panel_mm = fmin((double)height / (double)nrows, (double)width / (double)ncols) / SWFS_PLOT_DPI * 25.4;
    p->chr_mm = fmin(4.8, fmax(2.6, 0.032 * panel_mm));
    int rc = plot_check(p, "plinit");
    if (rc) {
        swfs_plot_abort(p);
        return rc;
    }
    *out = p;
    return SWFS_OK;
}

static void plot_end(swfs_plot *p)
{
    if (!p->ended) {
        plsstrm(p->strm);
        plend1();
        p->ended = 1;
    }
}

int swfs_plot_commit(swfs_plot *p)
{
    if (!p) return swfs_fail(SWFS_ERR_ARG, "plot: commit of a NULL figure");
    plsstrm(p->strm);
    int rc = plot_check(p, "drawing");
    plot_end(p);
    /* cairo's write errors (a full disk) do not reach PLplot's error state: check the file. */
    if (!rc && (rc = swfs_plot_png_check(swfs_atomic_part(p->atom)))) swfs_fail_context(rc, "writing %s", p->path);
    if (!rc) rc = swfs_atomic_commit(p->atom); /* fsync, rename; removes the part on failure */
    else swfs_atomic_abort(p->atom);
    free(p);
    return rc;
}

void swfs_plot_abort(swfs_plot *p)
{
    if (!p) return;
    plot_end(p);
    swfs_atomic_abort(p->atom);
    free(p);
}

int swfs_plot_panel(swfs_plot *p, int k)
{
    if (k < 0 || k >= p->ncols * p->nrows)
        return swfs_fail(SWFS_ERR_ARG, "%s: panel %d outside the %dx%d layout", p->path, k, p->ncols, p->nrows);
    plsstrm(p->strm);
    int col = k % p->ncols, row = k / p->ncols;
    p->px0 = (double)col / p->ncols;
    p->px1 = (double)(col + 1) / p->ncols;
    p->py1 = 1.0 - (double)row / p->nrows;
    p->py0 = 1.0 - (double)(row + 1) / p->nrows;
    plschr(p->chr_mm, 1.0);
    plwidth(1.0);
    plcol0(SWFS_COLOR_BLACK);
    pllsty(1);
    return plot_check(p, "pladv");
}

/* Viewport given in panel-relative coordinates. */
static void panel_vpor(const swfs_plot *p, double x0, double x1, double y0, double y1)
{
    double w = p->px1 - p->px0, h = p->py1 - p->py0;
    plvpor(p->px0 + x0 * w, p->px0 + x1 * w, p->py0 + y0 * h, p->py0 + y1 * h);
}

/* The largest viewport of the given aspect (y length / x length on the page) inside
 * the panel-relative box, centred. */
static void panel_vpas(const swfs_plot *p, double x0, double x1, double y0, double y1, double aspect)
{
    double w = (x1 - x0) * (p->px1 - p->px0) * p->width, h = (y1 - y0) * (p->py1 - p->py0) * p->height;
    if (h / w > aspect) {
        double nh = w * aspect / ((p->py1 - p->py0) * p->height), c = 0.5 * (y0 + y1);
        y0 = c - 0.5 * nh;
        y1 = c + 0.5 * nh;
    } else {
        double nw = h / aspect / ((p->px1 - p->px0) * p->width), c = 0.5 * (x0 + x1);
        x0 = c - 0.5 * nw;
        x1 = c + 0.5 * nw;
    }
    panel_vpor(p, x0, x1, y0, y1);
}

/* Colour maps as RGB control points (interpolated in RGB by PLplot). */
static void set_cmap(swfs_cmap cmap)
{
    static const double gray[][4] = {{0, 0, 0, 0}, {1, 1, 1, 1}};
    static const double magma[][4] = {{0.00, 0.001, 0.000, 0.014}, {0.25, 0.316, 0.072, 0.485},
                                      {0.50, 0.716, 0.215, 0.475}, {0.75, 0.987, 0.536, 0.382},
                                      {1.00, 0.987, 0.991, 0.750}};
    static const double viridis[][4] = {{0.00, 0.267, 0.005, 0.329}, {0.25, 0.229, 0.322, 0.546},
                                        {0.50, 0.128, 0.567, 0.551}, {0.75, 0.369, 0.789, 0.383},
                                        {1.00, 0.993, 0.906, 0.144}};
    /* Cyclic: light -> blue -> dark -> red -> light, so -pi and +pi look the same. */
    static const double phase[][4] = {{0.00, 0.89, 0.85, 0.89}, {0.25, 0.37, 0.47, 0.75},
                                      {0.50, 0.19, 0.08, 0.24}, {0.75, 0.70, 0.30, 0.25},
                                      {1.00, 0.89, 0.85, 0.89}};
    static const double diverging[][4] = {{0.0, 0.23, 0.30, 0.75}, {0.5, 0.87, 0.87, 0.87}, {1.0, 0.71, 0.02, 0.15}};
    const double(*t)[4];
    size_t n;
    switch (cmap) {
    case SWFS_CMAP_MAGMA: t = magma, n = 5; break;
    case SWFS_CMAP_VIRIDIS: t = viridis, n = 5; break;
    case SWFS_CMAP_PHASE: t = phase, n = 5; break;
    case SWFS_CMAP_DIVERGING: t = diverging, n = 3; break;
    default: t = gray, n = 2; break;
    }
    PLFLT pos[8], r[8], g[8], b[8], a[8];
    for (size_t i = 0; i < n; i++) {
        pos[i] = t[i][0];
        r[i] = t[i][1];
        g[i] = t[i][2];
        b[i] = t[i][3];
        a[i] = 1.0;
    }
    plscmap1n(256);
    plscmap1la(1, (PLINT)n, pos, r, g, b, a, NULL);
}

static void labels(const swfs_plot *p, const char *title, const char *xlabel, const char *ylabel, double yoff)
{
    plcol0(SWFS_COLOR_BLACK);
    if (xlabel) plmtex("b", 3.0, 0.5, 0.5, xlabel);
    if (ylabel) plmtex("l", yoff, 0.5, 0.5, ylabel);
    if (title) {
        plschr(p->chr_mm, 1.15);
        plmtex("t", 1.6, 0.5, 0.5, title);
        plschr(p->chr_mm, 1.0);
    }
}

int swfs_plot_image(swfs_plot *p, const double *z, size_t nx, size_t ny, const swfs_plot_image_spec *s)
{
    if (!z || !s || nx < 1 || ny < 1) return swfs_fail(SWFS_ERR_ARG, "%s: image needs data and a spec", p->path);
    double lo = s->zmin, hi = s->zmax;
    if (!isfinite(lo) || !isfinite(hi)) return swfs_fail(SWFS_ERR_VALUE, "%s: colour range is not finite", p->path);
    if (!(hi > lo)) {
        double d = fabs(lo) > 0 ? 1e-3 * fabs(lo) : 1.0;
        lo -= d;
        hi += d;
    }
    /* Pixel edges in physical units. */
    double dx = nx > 1 ? (s->x1 - s->x0) / (double)(nx - 1) : 1.0;
    double dy = ny > 1 ? (s->y1 - s->y0) / (double)(ny - 1) : 1.0;
    double xe0 = s->x0 - 0.5 * dx, xe1 = s->x1 + 0.5 * dx;
    double ye0 = s->y0 - 0.5 * dy, ye1 = s->y1 + 0.5 * dy;
    if (!(xe1 > xe0) || !(ye1 > ye0)) return swfs_fail(SWFS_ERR_ARG, "%s: image extent must increase", p->path);

    PLFLT **rows = malloc(nx * sizeof *rows);
    PLFLT *buf = malloc(nx * ny * sizeof *buf);
    if (!rows || !buf) {
        free(rows);
        free(buf);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", p->path);
    }
    /* Values outside [zlo, zhi] are not drawn by plimagefr: that is our mask. */
    const double hidden = lo - (hi - lo) - 1.0;
    for (size_t i = 0; i < nx; i++) {
        rows[i] = buf + i * ny;
        for (size_t j = 0; j < ny; j++) {
            double v = z[j * nx + i];
            if (!isfinite(v) || (s->mask && !s->mask[j * nx + i])) v = hidden;
            else if (v < lo) v = lo;
            else if (v > hi) v = hi;
            rows[i][j] = v;
        }
    }

    plsstrm(p->strm);
    panel_vpas(p, 0.17, 0.78, 0.12, 0.88, (ye1 - ye0) / (xe1 - xe0));
    plwind(xe0, xe1, ye0, ye1);
    set_cmap(s->cmap);
    plimagefr((PLFLT_MATRIX)rows, (PLINT)nx, (PLINT)ny, xe0, xe1, ye0, ye1, lo, hi, lo, hi, NULL, NULL);
    free(rows);
    free(buf);
    plcol0(SWFS_COLOR_BLACK);
    plbox("bcnst", 0.0, 0, "bcnstv", 0.0, 0);
    labels(p, s->title, s->xlabel, s->ylabel, 3.8);

    /* Colorbar on the right of the image, as tall as the image. */
    int logaxis = s->zlog && (hi - lo) >= 1.0;
    const char *axis_opts[] = {logaxis ? "bcvtml" : "bcvtm"};
    PLINT label_opts[] = {PL_COLORBAR_LABEL_RIGHT};
    const char *lab[] = {s->zlabel ? s->zlabel : ""};
    PLFLT ticks[] = {0.0};
    PLINT sub_ticks[] = {0};
    PLINT n_values[] = {2};
    PLFLT vals[] = {lo, hi};
    const PLFLT *values[] = {vals};
    PLFLT cw, ch;
    plcolorbar(&cw, &ch, PL_COLORBAR_IMAGE, PL_POSITION_RIGHT | PL_POSITION_OUTSIDE | PL_POSITION_VIEWPORT, 0.03,
               0.0, 0.05, 1.0, 0, SWFS_COLOR_BLACK, 1, 0.0, 0.0, 0, 0.0, 1, label_opts, lab, 1, axis_opts, ticks,
               sub_ticks, n_values, (PLFLT_MATRIX)values);
    p->img_x0 = s->x0;
    p->img_x1 = s->x1;
    p->img_y0 = s->y0;
    p->img_y1 = s->y1;
    p->img_nx = nx;
    p->img_ny = ny;
    return plot_check(p, "image");
}

int swfs_plot_circles(swfs_plot *p, double cx, double cy, const double *r, size_t n, swfs_color c,
                      swfs_linestyle style, double width)
{
    enum { NSEG = 181 };
    PLFLT x[NSEG], y[NSEG];
    plsstrm(p->strm);
    plcol0(c);
    pllsty(style);
    plwidth(width > 0 ? width : 1.0);
    for (size_t k = 0; k < n; k++) {
        for (int i = 0; i < NSEG; i++) {
            double t = 2.0 * M_PI * i / (NSEG - 1);
            x[i] = cx + r[k] * cos(t);
            y[i] = cy + r[k] * sin(t);
        }
        plline(NSEG, x, y);
    }
    pllsty(1);
    plwidth(1.0);
    plcol0(SWFS_COLOR_BLACK);
    return plot_check(p, "circles");
}

int swfs_plot_contour(swfs_plot *p, const double *z, size_t nx, size_t ny, double level, swfs_color c,
                      double width)
{
    if (nx != p->img_nx || ny != p->img_ny || nx < 2 || ny < 2)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: contour map is %zux%zu but the image is %zux%zu", p->path, nx, ny,
                         p->img_nx, p->img_ny);
    /* Padded with one sample of zeros so that outlines touching the border close. */
    size_t mx = nx + 2, my = ny + 2;
    PLFLT **rows = malloc(mx * sizeof *rows);
    PLFLT *buf = calloc(mx * my, sizeof *buf);
    PLFLT *xg = malloc(mx * sizeof *xg), *yg = malloc(my * sizeof *yg);
    if (!rows || !buf || !xg || !yg) {
        free(rows);
        free(buf);
        free(xg);
        free(yg);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", p->path);
    }
    double dx = (p->img_x1 - p->img_x0) / (double)(nx - 1), dy = (p->img_y1 - p->img_y0) / (double)(ny - 1);
    for (size_t i = 0; i < mx; i++) {
        rows[i] = buf + i * my;
        xg[i] = p->img_x0 + dx * ((double)i - 1.0);
        if (i == 0 || i == mx - 1) continue;
        for (size_t j = 1; j + 1 < my; j++) {
            double v = z[(j - 1) * nx + (i - 1)];
            rows[i][j] = isfinite(v) ? v : 0.0;
        }
    }
    for (size_t j = 0; j < my; j++) yg[j] = p->img_y0 + dy * ((double)j - 1.0);
    PLcGrid grid = {xg, yg, NULL, (PLINT)mx, (PLINT)my, 0};
    PLFLT clevel[] = {level};
    plsstrm(p->strm);
    plcol0(c);
    plwidth(width > 0 ? width : 1.0);
    plcont((PLFLT_MATRIX)rows, (PLINT)mx, (PLINT)my, 1, (PLINT)mx, 1, (PLINT)my, clevel, 1, pltr1, &grid);
    plwidth(1.0);
    plcol0(SWFS_COLOR_BLACK);
    free(rows);
    free(buf);
    free(xg);
    free(yg);
    return plot_check(p, "contour");
}

int swfs_plot_axes(swfs_plot *p, const swfs_plot_axes_spec *s)
{
    if (!(s->xmax > s->xmin) || !(s->ymax > s->ymin) || !isfinite(s->xmin + s->xmax + s->ymin + s->ymax))
        return swfs_fail(SWFS_ERR_VALUE, "%s: axis ranges must be finite and increasing", p->path);
    plsstrm(p->strm);
    if (s->equal_aspect)
        panel_vpas(p, 0.17, 0.95, 0.12, 0.88, (s->ymax - s->ymin) / (s->xmax - s->xmin));
    else
        panel_vpor(p, 0.15, 0.95, 0.12, 0.88);
    plwind(s->xmin, s->xmax, s->ymin, s->ymax);
    plcol0(SWFS_COLOR_LIGHTGRAY);
    plbox("g", 0.0, 0, "g", 0.0, 0);
    plcol0(SWFS_COLOR_BLACK);
    plbox("bcnst", 0.0, 0, "bcnstv", 0.0, 0);
    labels(p, s->title, s->xlabel, s->ylabel, s->equal_aspect ? 4.2 : 5.2);
    return plot_check(p, "axes");
}

int swfs_plot_points(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c, double size)
{
    if (n == 0) return SWFS_OK;
    plsstrm(p->strm);
    plcol0(c);
    plschr(p->chr_mm, size > 0 ? 0.5 * size : 0.5);
    plstring((PLINT)n, x, y, "●");
    plschr(p->chr_mm, 1.0);
    plcol0(SWFS_COLOR_BLACK);
    return plot_check(p, "points");
}

int swfs_plot_line(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c,
                   swfs_linestyle style, double width)
{
    if (n < 2) return SWFS_OK;
    plsstrm(p->strm);
    plcol0(c);
    pllsty(style);
    plwidth(width > 0 ? width : 1.0);
    plline((PLINT)n, x, y);
    pllsty(1);
    plwidth(1.0);
    plcol0(SWFS_COLOR_BLACK);
    return plot_check(p, "line");
}

int swfs_plot_text(swfs_plot *p, double x, double y, double just, swfs_color c, const char *text)
{
    plsstrm(p->strm);
    plcol0(c);
    plptex(x, y, 1.0, 0.0, just, text);
    plcol0(SWFS_COLOR_BLACK);
    return plot_check(p, "text");
}

int swfs_plot_legend(swfs_plot *p, const swfs_plot_legend_entry *e, size_t n)
{
    enum { MAXL = 8 };
    if (n == 0) return SWFS_OK;
    if (n > MAXL) n = MAXL;
    PLINT opt[MAXL], tcol[MAXL], lcol[MAXL], lsty[MAXL], scol[MAXL], snum[MAXL];
    PLINT bcol[MAXL], bpat[MAXL];
    PLFLT lw[MAXL], ssc[MAXL], bsc[MAXL], blw[MAXL];
    const char *text[MAXL], *sym[MAXL];
    for (size_t i = 0; i < n; i++) {
        opt[i] = e[i].is_marker ? PL_LEGEND_SYMBOL : PL_LEGEND_LINE;
        tcol[i] = SWFS_COLOR_BLACK;
        lcol[i] = scol[i] = bcol[i] = (PLINT)e[i].color;
        lsty[i] = e[i].style ? (PLINT)e[i].style : 1;
        lw[i] = 2.0;
        ssc[i] = 0.6;
        snum[i] = 1;
        bpat[i] = 0;
        bsc[i] = 0.0;
        blw[i] = 0.0;
        text[i] = e[i].text;
        sym[i] = "●";
    }
    PLFLT w, h;
    plsstrm(p->strm);
    plschr(p->chr_mm, 0.9);
    pllegend(&w, &h, PL_LEGEND_BACKGROUND | PL_LEGEND_BOUNDING_BOX,
             PL_POSITION_TOP | PL_POSITION_RIGHT | PL_POSITION_INSIDE | PL_POSITION_VIEWPORT, 0.02, 0.02, 0.08,
             0 /* white */, SWFS_COLOR_BLACK, 1, 0, 0, (PLINT)n, opt, 1.0, 1.0, 1.8, 0.0, tcol, text, bcol, bpat,
             bsc, blw, lcol, lsty, lw, scol, ssc, snum, sym);
    plschr(p->chr_mm, 1.0);
    return plot_check(p, "legend");
}

#else /* no PLplot */

int swfs_plot_available(void) { return 0; }

int swfs_plot_create(swfs_plot **out, const char *path, int width, int height, int ncols, int nrows)
{
    (void)width, (void)height, (void)ncols, (void)nrows;
    *out = NULL;
    return swfs_fail(SWFS_ERR_ARG, "%s: specklewfs was built without PLplot (Debian: libplplot-dev, "
                                   "plplot-driver-cairo)", path ? path : "figure");
}
int swfs_plot_commit(swfs_plot *p)
{
    (void)p;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
void swfs_plot_abort(swfs_plot *p) { (void)p; }
int swfs_plot_panel(swfs_plot *p, int k)
{
    (void)p, (void)k;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_image(swfs_plot *p, const double *z, size_t nx, size_t ny, const swfs_plot_image_spec *s)
{
    (void)p, (void)z, (void)nx, (void)ny, (void)s;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_circles(swfs_plot *p, double cx, double cy, const double *r, size_t n, swfs_color c,
                      swfs_linestyle style, double width)
{
    (void)p, (void)cx, (void)cy, (void)r, (void)n, (void)c, (void)style, (void)width;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_contour(swfs_plot *p, const double *z, size_t nx, size_t ny, double level, swfs_color c,
                      double width)
{
    (void)p, (void)z, (void)nx, (void)ny, (void)level, (void)c, (void)width;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_axes(swfs_plot *p, const swfs_plot_axes_spec *s)
{
    (void)p, (void)s;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_points(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c, double size)
{
    (void)p, (void)x, (void)y, (void)n, (void)c, (void)size;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_line(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c,
                   swfs_linestyle style, double width)
{
    (void)p, (void)x, (void)y, (void)n, (void)c, (void)style, (void)width;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_text(swfs_plot *p, double x, double y, double just, swfs_color c, const char *text)
{
    (void)p, (void)x, (void)y, (void)just, (void)c, (void)text;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}
int swfs_plot_legend(swfs_plot *p, const swfs_plot_legend_entry *e, size_t n)
{
    (void)p, (void)e, (void)n;
    return swfs_fail(SWFS_ERR_ARG, "built without PLplot");
}

#endif

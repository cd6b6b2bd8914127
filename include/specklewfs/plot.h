/* PNG figures through PLplot's C API and its cairo driver ("pngcairo"): images with a
 * colorbar and axes in physical units, circle and contour overlays, scatter plots and
 * curves, complex-plane plots. All text, antialiasing and PNG encoding are PLplot's and
 * cairo's; nothing here rasterizes.
 *
 * A figure is a page of ncols x nrows panels written to "<path>.part" and renamed on
 * commit, so a failed run never leaves a PNG that looks complete. Drawing calls act on
 * the current panel (swfs_plot_panel). Coordinates are the caller's physical units.
 *
 * NOT THREAD-SAFE. PLplot keeps process-wide state (the current stream, the driver
 * table, the exit handler). Draw one figure at a time per process; figures may be
 * created one after another freely (each gets its own PLplot stream, ended on
 * commit/abort). PLplot reports argument errors to us (plsError), which come back as
 * SWFS_ERR_INTERNAL; its rare fatal errors (out of memory inside PLplot) still call
 * exit() from within PLplot -- we preflight the device and the output file so that
 * foreseeable failures are returned as errors instead. PLplot may also print warnings
 * on stderr on its own.
 *
 * Built without PLplot (SWFS_HAVE_PLPLOT undefined), swfs_plot_available() is 0 and
 * swfs_plot_create() fails with SWFS_ERR_ARG. */
#ifndef SWFS_PLOT_H
#define SWFS_PLOT_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_plot swfs_plot;

/* Colour maps for images. */
typedef enum swfs_cmap {
    SWFS_CMAP_GRAY = 0,  /* black -> white */
    SWFS_CMAP_MAGMA,     /* black -> purple -> orange -> pale yellow: intensities, log scales */
    SWFS_CMAP_VIRIDIS,   /* dark blue -> green -> yellow: bounded quantities, times */
    SWFS_CMAP_PHASE,     /* cyclic (same colour at both ends): phases in [-pi, pi] */
    SWFS_CMAP_DIVERGING  /* blue -> light gray -> red: signed quantities around 0 */
} swfs_cmap;

/* Line and marker colours. */
typedef enum swfs_color {
    SWFS_COLOR_BLACK = 1,
    SWFS_COLOR_RED,
    SWFS_COLOR_BLUE,
    SWFS_COLOR_GRAY,
    SWFS_COLOR_ORANGE,
    SWFS_COLOR_GREEN,
    SWFS_COLOR_WHITE,
    SWFS_COLOR_LIGHTGRAY
} swfs_color;

typedef enum swfs_linestyle { SWFS_LINE_SOLID = 1, SWFS_LINE_DASHED = 3, SWFS_LINE_DOTTED = 2 } swfs_linestyle;

/* 1 if PLplot and its pngcairo device are usable in this build and installation. */
int swfs_plot_available(void);

/* A width x height pixel PNG at `path` with ncols x nrows panels (panel 0 top left,
 * row-major). Nothing appears at `path` until swfs_plot_commit(). */
int swfs_plot_create(swfs_plot **out, const char *path, int width, int height, int ncols, int nrows);
/* Finish the page, check PLplot's error state, rename the PNG into place, free. On
 * failure the partial file is removed. */
int swfs_plot_commit(swfs_plot *p);
/* End the stream, remove the partial file, free. Safe on NULL. */
void swfs_plot_abort(swfs_plot *p);
/* SWFS_OK if path is a complete PNG: the signature, an IHDR chunk first, every chunk
 * within the file and an intact IEND chunk that ends it; else SWFS_ERR_FORMAT naming the
 * file and where it breaks off. swfs_plot_commit checks every figure with it before the
 * rename (a PNG cut short by a full disk is not put in place). Works without PLplot. */
int swfs_plot_png_check(const char *path);

/* Make panel k current (drawing goes there until the next call). */
int swfs_plot_panel(swfs_plot *p, int k);

/* An image panel. z is nx*ny in FITS order (x fastest); (x0, y0) and (x1, y1) are the
 * physical coordinates of the centres of the first and last pixel, so axes read in
 * the caller's units (lambda/D, m). Values are clipped to [zmin, zmax] for colouring;
 * non-finite values and pixels where mask is 0 are left as background (white).
 * zlog: z holds log10 of the quantity and the colorbar is labelled in powers of ten.
 * The panel keeps equal x/y scales. Overlays (circles, contour, markers) drawn after it
 * use the same coordinates. */
typedef struct swfs_plot_image_spec {
    const char *title, *xlabel, *ylabel;
    const char *zlabel; /* colorbar label, with units */
    double x0, x1, y0, y1;
    double zmin, zmax;
    int zlog;
    swfs_cmap cmap;
    const unsigned char *mask; /* NULL or nx*ny */
} swfs_plot_image_spec;
int swfs_plot_image(swfs_plot *p, const double *z, size_t nx, size_t ny, const swfs_plot_image_spec *s);

/* Circles of radii r[k] around (cx, cy) in the current panel's coordinates. */
int swfs_plot_circles(swfs_plot *p, double cx, double cy, const double *r, size_t n, swfs_color c,
                      swfs_linestyle style, double width);
/* The contour z = level of an nx*ny map laid out like the last image (e.g. a pupil
 * outline from its mask at level 0.5). */
int swfs_plot_contour(swfs_plot *p, const double *z, size_t nx, size_t ny, double level, swfs_color c,
                      double width);

/* An x-y panel with the given ranges. equal_aspect: one unit is the same length on both
 * axes (complex-plane plots). */
typedef struct swfs_plot_axes_spec {
    const char *title, *xlabel, *ylabel;
    double xmin, xmax, ymin, ymax;
    int equal_aspect;
} swfs_plot_axes_spec;
int swfs_plot_axes(swfs_plot *p, const swfs_plot_axes_spec *s);

/* Markers (filled dots, size relative to the default; 0: default) and polylines in the
 * current panel's coordinates. */
int swfs_plot_points(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c, double size);
int swfs_plot_line(swfs_plot *p, const double *x, const double *y, size_t n, swfs_color c,
                   swfs_linestyle style, double width);
/* Text at (x, y); just = 0 left, 0.5 centred, 1 right. */
int swfs_plot_text(swfs_plot *p, double x, double y, double just, swfs_color c, const char *text);
/* A legend box in the panel's top-right corner: one entry per line or marker. */
typedef struct swfs_plot_legend_entry {
    const char *text;
    swfs_color color;
    int is_marker;         /* 1: a dot; 0: a line of `style` */
    swfs_linestyle style;
} swfs_plot_legend_entry;
int swfs_plot_legend(swfs_plot *p, const swfs_plot_legend_entry *e, size_t n);

SWFS_END_DECLS

#endif

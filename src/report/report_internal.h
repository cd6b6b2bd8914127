/* Private to src/report/: the state of one report page and the helpers its files share.
 *
 *   report.c         entry point, run-folder products (through src/io readers), reference pixel
 *   ranges.c         colour ranges (robust percentiles) and focal-plane panel geometry
 *   fig_halo.c       halo.png and focal.png: the estimate's maps
 *   fig_pixel.c      pixel.png: one pixel's intensity against the speckle phase
 *   fig_pupil.c      pupil.png and the WFE key numbers (diag metrics: swfs_wfe_compare)
 *   fig_coherence.c  coherence.png
 *   fig_loop.c       loop.png: the closed loop of a demo folder
 *   demo.c           the page of a `specklewfs demo` folder
 *   html.c           the HTML text, tables and the page writer */
#ifndef SWFS_REPORT_INTERNAL_H
#define SWFS_REPORT_INTERNAL_H

#include "specklewfs/array.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/geom.h"
#include "specklewfs/plot.h"
#include "specklewfs/report.h"

#include <stddef.h>

#define REP_PATHMAX 4096

/* Figure sizes [pixels]. */
enum {
    REP_W_HALO = 1500, REP_H_HALO = 440,
    REP_W_GRID = 1100, REP_H_GRID = 880, /* 2 x 2 panels */
    REP_W_ROW2 = 1100, REP_H_ROW2 = 440, /* 2 x 1 panels */
    REP_W_PIXEL = 900, REP_H_PIXEL = 600
};

/* First and second Airy rings of a (lightly obstructed) circular pupil [lambda/D]. */
#define REP_RING1_MIN 1.3
#define REP_RING1_MAX 1.9
#define REP_RING2_MIN 2.2
#define REP_RING2_MAX 3.2

/* ---- a growing string (html.c) ------------------------------------------ */

typedef struct rep_strbuf {
    char *s;
    size_t len, cap;
    int oom;
} rep_strbuf;

#if defined(__GNUC__)
__attribute__((format(printf, 2, 3)))
#endif
void rep_printf(rep_strbuf *b, const char *fmt, ...);
/* Text with the HTML special characters escaped. */
void rep_text(rep_strbuf *b, const char *t);

/* ---- one run folder ---------------------------------------------------- */

enum rep_product { P_SCIENCE, P_SPECKLES, P_TRUTH, P_PUPIL, P_HALO, P_WAVEFRONT, P_COHERENCE, P_COUNT };
extern const char *const rep_product_file[P_COUNT];

typedef struct rep_ctx {
    const char *run_dir;
    char out_dir[REP_PATHMAX];
    const char *href;          /* prefix of the figures' links in the page: "" or "sigma100/" */
    const char *label;         /* prefix of the notes: "" or "σ = 100 counts: " */
    int in_demo;               /* one noise level of a demo page: no note for coherence.fits */
    swfs_report_options opt;
    swfs_report_summary *sum;  /* this run's key numbers */
    swfs_report_summary *top;  /* the page's figures, ranges and notes (== sum for a run folder) */
    rep_strbuf figs;           /* HTML of the figure sections */

    char path[P_COUNT][REP_PATHMAX];
    int has[P_COUNT];

    swfs_geom geom; /* focal geometry (halo, else science, else speckles) */
    size_t nx, ny;  /* focal grid; 0 until known */

    swfs_halo *halo_file; /* halo.fits (swfs_halo_read), or NULL */
    swfs_real *cube_mean_i, *cube_var_i, *cube_mean_sp; /* without halo.fits: from the cubes */
    /* Views of the maps drawn (NULL where absent); owned by halo_file or the cube_* maps. */
    const swfs_cplx *halo;
    const swfs_real *gain, *visib, *snr, *mean_i, *var_i, *mean_sp, *valid;
    int moments_from_cubes;

    long ref_i, ref_j; /* first-ring reference pixel, -1 if none */
} rep_ctx;

int rep_join(char *dst, const char *dir, const char *name);
/* The image extension `ext` of f as a real array, or *out = NULL when f has none. */
int rep_read_real_opt(swfs_fits_in *f, const char *ext, swfs_real **out);
int rep_file_exists(const char *path);
int rep_dir_exists(const char *path);
int rep_make_dirs(const char *path);
#if defined(__GNUC__)
__attribute__((format(printf, 2, 3)))
#endif
void rep_note(rep_ctx *c, const char *fmt, ...);
/* Record file (relative to c->out_dir) in the summary and its section in c->figs. */
void rep_add_figure(rep_ctx *c, const char *file, int w, int h, const char *heading, const char *caption);
/* Commit *p (then NULL) and, when it is written, add it with rep_add_figure. */
int rep_commit(rep_ctx *c, swfs_plot **p, const char *file, int w, int h, const char *heading, const char *caption);
void rep_summary_init(swfs_report_summary *s);

/* Set up c for run_dir -> out_dir (products found, options checked by the caller). */
int rep_ctx_init(rep_ctx *c, const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                 swfs_report_summary *sum, swfs_report_summary *top);
void rep_ctx_free(rep_ctx *c);
/* Number of products in c that give a figure or a key number. */
int rep_ctx_reportable(const rep_ctx *c);
/* Load the products, choose the pixels, draw every figure into c->out_dir. */
int rep_run_folder(rep_ctx *c);

/* ---- colour ranges and focal panels (ranges.c) ---------------------------- */

enum rep_range_kind {
    R_AUTO,      /* linear [P_lo, P_hi], log10 if positive with P_hi/P_lo > 100 */
    R_LOG,       /* log10, [max(log P_lo, log P_hi - decades), log P_hi] over positive values */
    R_LOG_FIXED, /* log10, exactly [log P_hi - decades, log P_hi] */
    R_SYM,       /* [-P_hi(|v|), P_hi(|v|)] */
    R_FIXED      /* the given [lo, hi] */
};

/* Scale v by `scale` into z (display units), choose the range, convert z to log10 where
 * the range is logarithmic, and record the range under `name`. */
swfs_report_range rep_prepare(rep_ctx *c, const char *name, const double *v, size_t n, const unsigned char *mask,
                              enum rep_range_kind kind, double scale, double flo, double fhi, double *z);
void rep_apply_range(swfs_plot_image_spec *s, const swfs_report_range *r);
/* One colour-mapped panel: labels, the range r, then the image z (nx x ny). */
int rep_image_panel(swfs_plot *p, int panel, swfs_plot_image_spec *s, const swfs_report_range *r, const char *title,
                    const char *zlabel, swfs_cmap cmap, const double *z, size_t nx, size_t ny);
/* 1 where valid > 0.5; NULL when valid is NULL (or out of memory: check valid). */
unsigned char *rep_mask_from(const swfs_real *valid, size_t n);

int rep_have_pixscale(const rep_ctx *c);
/* Focal pixel -> theta [lambda/D] (pixels if PIXSCALE is unknown), docs/conventions.md convention. */
double rep_focal_x(const rep_ctx *c, double i, size_t n);
void rep_focal_spec(const rep_ctx *c, swfs_plot_image_spec *s);
/* The pixel with the largest score among ok pixels at radius [rmin, rmax] lambda/D
 * (anywhere if PIXSCALE is unknown). */
int rep_best_pixel(const rep_ctx *c, const double *score, const unsigned char *ok, double rmin, double rmax,
                   long *bi, long *bj);
/* The first focal product fixes the grid; the others must match it. */
int rep_check_focal_shape(rep_ctx *c, const char *path, size_t nx, size_t ny);

/* ---- figures ------------------------------------------------------------ */

int rep_fig_halo(rep_ctx *c);
int rep_fig_focal(rep_ctx *c);
int rep_fig_pixel(rep_ctx *c);
int rep_fig_pupil(rep_ctx *c);
int rep_fig_coherence(rep_ctx *c);
int rep_fig_registration(rep_ctx *c);

/* ---- the page (html.c) ---------------------------------------------------- */

/* The key numbers of s as a table; ids are prefixed by id_prefix ("" or "sigma100-"). */
void rep_key_numbers(rep_strbuf *b, const swfs_report_summary *s, const char *id_prefix);
/* The notes of s as a list (nothing when there are none). */
void rep_notes(rep_strbuf *b, const swfs_report_summary *s);
/* A TSV table (swfs_table) as an HTML table with the given id; headings from its column
 * names ("_nm" -> " [nm]", "_pct" -> " [%]", "_s" -> " [s]"). */
struct swfs_table;
void rep_table(rep_strbuf *b, const struct swfs_table *t, const char *id);
/* index.html in out_dir: the title, body and a footer, written via .part + rename; the
 * path goes to s->html. */
int rep_write_page(const char *out_dir, const char *title, const char *run_dir, const rep_strbuf *body,
                   swfs_report_summary *s);

/* ---- a demo folder (demo.c, fig_loop.c) ----------------------------------- */

/* 1 if dir looks like the folder `specklewfs demo -o DIR` writes. */
int rep_is_demo(const char *dir);
int rep_demo_run(const char *dir, const char *out_dir, const swfs_report_options *opt, swfs_report_summary *s);
/* loop.png from the closed-loop table into out_dir; *drawn = 0 if the table has none of
 * the columns drawn. */
int rep_fig_loop(const struct swfs_table *t, const char *out_dir, int *drawn);

#endif

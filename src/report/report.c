/* The report: figures of a run's products and index.html (see include/specklewfs/report.h
 * and docs/report.md). Reads products through the FITS layer, chooses colour ranges from
 * robust percentiles, draws through plot.h (PLplot), writes HTML via .part + rename. */
#include "specklewfs/numeric.h"
#include "specklewfs/report.h"

#include "specklewfs/array.h"
#include "specklewfs/fits.h"
#include "specklewfs/plot.h"
#include "specklewfs/status.h"
#include "specklewfs/version.h"

#include <complex.h>
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#define PATHMAX 4096

/* Figure sizes [pixels]. */
enum {
    W_HALO = 1500, H_HALO = 440,
    W_GRID = 1100, H_GRID = 880,  /* 2 x 2 panels */
    W_ROW2 = 1100, H_ROW2 = 440,  /* 2 x 1 panels */
    W_PIXEL = 900, H_PIXEL = 600
};

/* First and second Airy rings of a (lightly obstructed) circular pupil [lambda/D]. */
#define RING1_MIN 1.3
#define RING1_MAX 1.9
#define RING2_MIN 2.2
#define RING2_MAX 3.2

/* ---- a growing string for the HTML ------------------------------------ */

typedef struct strbuf {
    char *s;
    size_t len, cap;
    int oom;
} strbuf;

#if defined(__GNUC__)
__attribute__((format(printf, 2, 3)))
#endif
static void sb_printf(strbuf *b, const char *fmt, ...)
{
    if (b->oom) return;
    for (;;) {
        size_t room = b->cap - b->len;
        va_list ap;
        va_start(ap, fmt);
        int n = vsnprintf(b->s ? b->s + b->len : NULL, b->s ? room : 0, fmt, ap);
        va_end(ap);
        if (n < 0) {
            b->oom = 1;
            return;
        }
        if (b->s && (size_t)n < room) {
            b->len += (size_t)n;
            return;
        }
        size_t cap = b->cap ? b->cap : 4096;
        while (cap - b->len <= (size_t)n) cap *= 2;
        char *s = realloc(b->s, cap);
        if (!s) {
            b->oom = 1;
            return;
        }
        b->s = s;
        b->cap = cap;
    }
}

/* Text with HTML special characters escaped. */
static void sb_text(strbuf *b, const char *t)
{
    for (; *t; t++) {
        switch (*t) {
        case '&': sb_printf(b, "&amp;"); break;
        case '<': sb_printf(b, "&lt;"); break;
        case '>': sb_printf(b, "&gt;"); break;
        case '"': sb_printf(b, "&quot;"); break;
        default: sb_printf(b, "%c", *t);
        }
    }
}

/* ---- the run ----------------------------------------------------------- */

typedef struct ctx {
    const char *run_dir;
    char out_dir[PATHMAX];
    swfs_report_options opt;
    swfs_report_summary *sum;
    strbuf figs; /* HTML of the figure sections */

    char p_science[PATHMAX], p_speckles[PATHMAX], p_truth[PATHMAX], p_pupil[PATHMAX];
    char p_halo[PATHMAX], p_wavefront[PATHMAX], p_coherence[PATHMAX];
    int has_science, has_speckles, has_truth, has_pupil, has_halo, has_wavefront, has_coherence;

    swfs_geom geom; /* focal geometry (halo, else science, else speckles) */
    size_t nx, ny;  /* focal grid; 0 until known */

    /* halo.fits (any may be NULL) */
    swfs_cplx *halo;
    swfs_real *gain, *visib, *snr, *mean_i, *var_i, *mean_sp, *valid;
    int moments_from_cubes; /* mean_i, var_i, mean_sp computed here (no halo.fits) */

    long ref_i, ref_j; /* first-ring reference pixel, -1 if none */
} ctx;

static int file_exists(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0 && S_ISREG(sb.st_mode);
}

static int join(char *dst, const char *dir, const char *name)
{
    int n = snprintf(dst, PATHMAX, "%s/%s", dir, name);
    if (n < 0 || n >= PATHMAX) return swfs_fail(SWFS_ERR_ARG, "%s: path too long", dir);
    return SWFS_OK;
}

static int make_dirs(const char *path)
{
    char tmp[PATHMAX];
    if (strlen(path) >= sizeof tmp) return swfs_fail(SWFS_ERR_ARG, "%s: path too long", path);
    strcpy(tmp, path);
    for (char *p = tmp + 1; *p; p++) {
        if (*p != '/') continue;
        *p = '\0';
        if (mkdir(tmp, 0777) != 0 && errno != EEXIST)
            return swfs_fail(SWFS_ERR_IO, "%s: cannot create folder: %s", tmp, strerror(errno));
        *p = '/';
    }
    if (mkdir(tmp, 0777) != 0 && errno != EEXIST)
        return swfs_fail(SWFS_ERR_IO, "%s: cannot create folder: %s", tmp, strerror(errno));
    struct stat sb;
    if (stat(tmp, &sb) != 0 || !S_ISDIR(sb.st_mode)) return swfs_fail(SWFS_ERR_IO, "%s: not a folder", tmp);
    return SWFS_OK;
}

#if defined(__GNUC__)
__attribute__((format(printf, 2, 3)))
#endif
static void note(ctx *c, const char *fmt, ...)
{
    if (c->sum->nnotes >= SWFS_REPORT_MAX_NOTES) return;
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(c->sum->notes[c->sum->nnotes++], sizeof c->sum->notes[0], fmt, ap);
    va_end(ap);
}

static void add_figure(ctx *c, const char *file, int w, int h, const char *heading, const char *caption)
{
    swfs_report_summary *s = c->sum;
    if (s->nfigures < SWFS_REPORT_MAX_FIGURES) {
        swfs_report_figure *f = &s->figures[s->nfigures++];
        snprintf(f->file, sizeof f->file, "%s", file);
        f->width = w;
        f->height = h;
    }
    sb_printf(&c->figs, "<section>\n<h2>");
    sb_text(&c->figs, heading);
    sb_printf(&c->figs, "</h2>\n<figure><img src=\"%s\" width=\"%d\" height=\"%d\" alt=\"", file, w, h);
    sb_text(&c->figs, heading);
    sb_printf(&c->figs, "\"><figcaption>");
    sb_text(&c->figs, caption);
    sb_printf(&c->figs, "</figcaption></figure>\n</section>\n");
}

/* ---- robust ranges ----------------------------------------------------- */

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

enum range_kind {
    R_AUTO,      /* linear [P_lo, P_hi], log10 if positive with P_hi/P_lo > 100 */
    R_LOG,       /* log10, [max(log P_lo, log P_hi - decades), log P_hi] over positive values */
    R_LOG_FIXED, /* log10, exactly [log P_hi - decades, log P_hi] */
    R_SYM,       /* [-P_hi(|v|), P_hi(|v|)] */
    R_FIXED      /* the given [lo, hi] */
};

/* Scale v by `scale` into z (display units), choose the range, convert z to log10 where
 * the range is logarithmic, and record the range under `name`. */
static swfs_report_range prepare(ctx *c, const char *name, const double *v, size_t n, const unsigned char *mask,
                                 enum range_kind kind, double scale, double flo, double fhi, double *z)
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
    if (c->sum->nranges < SWFS_REPORT_MAX_RANGES) c->sum->ranges[c->sum->nranges++] = r;
    return r;
}

/* ---- geometry helpers ------------------------------------------------- */

static int have_pixscale(const ctx *c) { return isfinite(c->geom.pixscale) && c->geom.pixscale > 0; }

/* Focal pixel -> theta [lambda/D] (pixels if PIXSCALE is unknown), DESIGN.md convention. */
static double focal_x(const ctx *c, double i, size_t n)
{
    double ps = have_pixscale(c) ? c->geom.pixscale : 1.0;
    return (i - (double)(n / 2)) * ps;
}

static void focal_spec(const ctx *c, swfs_plot_image_spec *s)
{
    memset(s, 0, sizeof *s);
    s->xlabel = have_pixscale(c) ? "x [λ/D]" : "x [pixel]";
    s->ylabel = have_pixscale(c) ? "y [λ/D]" : "y [pixel]";
    s->x0 = focal_x(c, 0, c->nx);
    s->x1 = focal_x(c, (double)c->nx - 1, c->nx);
    s->y0 = focal_x(c, 0, c->ny);
    s->y1 = focal_x(c, (double)c->ny - 1, c->ny);
}

static void apply_range(swfs_plot_image_spec *s, const swfs_report_range *r)
{
    s->zmin = r->lo;
    s->zmax = r->hi;
    s->zlog = r->log;
}

/* One colour-mapped panel: labels, the range r, then the image z (nx x ny). */
static int image_panel(swfs_plot *p, int panel, swfs_plot_image_spec *s, const swfs_report_range *r, const char *title,
                       const char *zlabel, swfs_cmap cmap, const double *z, size_t nx, size_t ny)
{
    s->title = title;
    s->zlabel = zlabel;
    s->cmap = cmap;
    apply_range(s, r);
    int rc = swfs_plot_panel(p, panel);
    return rc ? rc : swfs_plot_image(p, z, nx, ny, s);
}

/* The pixel with the largest score among ok pixels at radius [rmin, rmax] lambda/D
 * (anywhere if PIXSCALE is unknown). */
static int best_pixel(const ctx *c, const double *score, const unsigned char *ok, double rmin, double rmax,
                      long *bi, long *bj)
{
    double best = -INFINITY;
    *bi = *bj = -1;
    for (size_t j = 0; j < c->ny; j++)
        for (size_t i = 0; i < c->nx; i++) {
            size_t k = j * c->nx + i;
            if (ok && !ok[k]) continue;
            if (!isfinite(score[k])) continue;
            if (have_pixscale(c)) {
                double r = hypot(focal_x(c, (double)i, c->nx), focal_x(c, (double)j, c->ny));
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

static int check_focal_shape(ctx *c, const char *path, size_t nx, size_t ny)
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

/* ---- loading ----------------------------------------------------------- */

static int read_real_opt(swfs_fits_in *f, const char *ext, swfs_real **out)
{
    *out = NULL;
    if (!swfs_fits_in_has_ext(f, ext)) return SWFS_OK;
    int rc = swfs_fits_in_move(f, ext);
    if (!rc) rc = swfs_fits_in_read_real_all(f, out);
    return rc;
}

static int load_halo(ctx *c)
{
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, c->p_halo, NULL);
    if (rc) return rc;
    swfs_real **dst[] = {&c->gain, &c->visib, &c->snr, &c->mean_i, &c->var_i, &c->mean_sp, &c->valid};
    const char *names[] = {"GAIN", "VISIB", "SNR", "MEAN_I", "VAR_I", "MEAN_SP", "VALID"};
    if (swfs_fits_in_has_ext(f, "HALO")) {
        rc = swfs_fits_in_move(f, "HALO");
        if (!rc) rc = swfs_fits_in_read_cplx_all(f, &c->halo);
        if (!rc) rc = check_focal_shape(c, c->p_halo, c->halo->nx, c->halo->ny);
    }
    for (size_t k = 0; !rc && k < sizeof names / sizeof names[0]; k++) {
        rc = read_real_opt(f, names[k], dst[k]);
        if (!rc && *dst[k]) rc = check_focal_shape(c, c->p_halo, (*dst[k])->nx, (*dst[k])->ny);
    }
    if (!rc && c->nx == 0) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no HALO or map extensions", c->p_halo);
    int found;
    double v;
    if (!rc) rc = swfs_fits_in_geom(f, &c->geom);
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "NFRAMES", &v, &found)) && found) c->sum->frames = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "VALIDFR", &v, &found)) && found) c->sum->valid_fraction = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "MEDSNR", &v, &found)) && found) c->sum->median_snr = v;
    swfs_fits_in_close(f);
    return rc;
}

/* Mean and variance of a real cube, or mean |psi|^2 of a complex one, frame by frame. */
static int cube_moments(ctx *c, const char *path, int want_complex, swfs_real **mean, swfs_real **var)
{
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(f);
    size_t npix = sh->nx * sh->ny, nz = sh->nz;
    double *buf = NULL;
    double complex *cbuf = NULL;
    if (sh->is_complex != want_complex) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: expected a %s cube", path, want_complex ? "complex" : "real");
        goto done;
    }
    if ((rc = check_focal_shape(c, path, sh->nx, sh->ny))) goto done;
    *mean = swfs_real_alloc(sh->nx, sh->ny, 1);
    if (var) *var = swfs_real_alloc(sh->nx, sh->ny, 1);
    buf = want_complex ? NULL : malloc(npix * sizeof *buf);
    cbuf = want_complex ? malloc(npix * sizeof *cbuf) : NULL;
    if (!*mean || (var && !*var) || (!buf && !cbuf)) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
        goto done;
    }
    double *m = (*mean)->data, *s2 = var ? (*var)->data : NULL;
    for (size_t k = 0; k < nz && !rc; k++) {
        if (want_complex) {
            rc = swfs_fits_in_read_cplx(f, k, 1, cbuf);
            for (size_t p = 0; !rc && p < npix; p++) {
                double a = creal(cbuf[p]) * creal(cbuf[p]) + cimag(cbuf[p]) * cimag(cbuf[p]);
                m[p] += a;
            }
        } else {
            rc = swfs_fits_in_read_real(f, k, 1, buf);
            /* Welford's update keeps the variance exact for large means. */
            for (size_t p = 0; !rc && p < npix; p++) {
                double d = buf[p] - m[p];
                m[p] += d / (double)(k + 1);
                if (s2) s2[p] += d * (buf[p] - m[p]);
            }
        }
    }
    if (!rc) {
        for (size_t p = 0; p < npix; p++) {
            if (want_complex) m[p] /= (double)(nz ? nz : 1);
            if (s2) s2[p] = nz > 1 ? s2[p] / (double)(nz - 1) : NAN;
        }
    }
done:
    free(buf);
    free(cbuf);
    swfs_fits_in_close(f);
    return rc;
}

/* ---- figures ----------------------------------------------------------- */

static unsigned char *mask_from(const swfs_real *valid, size_t n)
{
    if (!valid) return NULL;
    unsigned char *m = malloc(n);
    if (m)
        for (size_t k = 0; k < n; k++) m[k] = valid->data[k] > 0.5;
    return m;
}

/* halo.png: log10 |Psi| normalized to the reference pixel, arg Psi, visibility. */
static int fig_halo(ctx *c)
{
    if (!c->halo) return SWFS_OK;
    size_t n = c->nx * c->ny;
    double *amp = calloc(n, sizeof *amp), *z = calloc(n, sizeof *z);
    unsigned char *vmask = mask_from(c->valid, n);
    swfs_plot *p = NULL;
    char path[PATHMAX];
    int rc = join(path, c->out_dir, "halo.png");
    if (!rc && (!amp || !z || (c->valid && !vmask))) rc = swfs_fail(SWFS_ERR_NOMEM, "halo figure: out of memory");
    if (rc) goto done;
    double ref = NAN;
    if (c->ref_i >= 0) ref = cabs(c->halo->data[(size_t)c->ref_j * c->nx + (size_t)c->ref_i]);
    if (!(ref > 0)) {
        for (size_t k = 0; k < n; k++) amp[k] = cabs(c->halo->data[k]);
        ref = swfs_report_percentile(amp, n, NULL, 100.0);
    }
    if (!(ref > 0)) ref = 1.0;
    for (size_t k = 0; k < n; k++) amp[k] = cabs(c->halo->data[k]) / ref;

    int npanel = c->visib ? 3 : 2;
    if ((rc = swfs_plot_create(&p, path, npanel == 3 ? W_HALO : W_ROW2, H_HALO, npanel, 1))) goto done;
    swfs_plot_image_spec s;
    focal_spec(c, &s);

    swfs_report_range r = prepare(c, "halo_amp", amp, n, NULL, R_LOG, 1.0, 0, 0, z);
    if ((rc = image_panel(p, 0, &s, &r, "static halo: log₁₀ |Ψ|",
                          c->ref_i >= 0 ? "|Ψ| / |Ψ| at the first-ring pixel" : "|Ψ| / max |Ψ|", SWFS_CMAP_MAGMA, z,
                          c->nx, c->ny)))
        goto done;
    if (c->ref_i >= 0) {
        double x = focal_x(c, (double)c->ref_i, c->nx), y = focal_x(c, (double)c->ref_j, c->ny);
        double rr = have_pixscale(c) ? 0.6 : 1.5;
        if ((rc = swfs_plot_circles(p, x, y, &rr, 1, SWFS_COLOR_GREEN, SWFS_LINE_SOLID, 2.0))) goto done;
    }

    for (size_t k = 0; k < n; k++) amp[k] = carg(c->halo->data[k]);
    r = prepare(c, "halo_phase", amp, n, vmask, R_FIXED, 1.0, -M_PI, M_PI, z);
    if ((rc = image_panel(p, 1, &s, &r, vmask ? "static halo: arg Ψ (valid pixels)" : "static halo: arg Ψ",
                          "phase [rad]", SWFS_CMAP_PHASE, z, c->nx, c->ny)))
        goto done;

    if (c->visib) {
        r = prepare(c, "visib", c->visib->data, n, NULL, R_FIXED, 1.0, 0.0, 1.0, z);
        if ((rc = image_panel(p, 2, &s, &r, "visibility (lighter is better)", "visibility", SWFS_CMAP_GRAY, z, c->nx,
                              c->ny)))
            goto done;
    }
    rc = swfs_plot_commit(p);
    p = NULL;
    if (!rc)
        add_figure(c, "halo.png", npanel == 3 ? W_HALO : W_ROW2, H_HALO, "Static halo",
                   "Left: base-10 log of the static halo amplitude |Ψ| (eq:TheAnswer), normalized to the "
                   "first-Airy-ring pixel circled in green. Centre: its phase, shown where the scale factor is "
                   "defined. Right: the visibility (eq:visibility); lighter is better.");
done:
    swfs_plot_abort(p);
    free(amp);
    free(z);
    free(vmask);
    return rc;
}

/* focal.png: g with circles at 1..6 lambda/D, mean science image, variance (4 decades),
 * mean speckle power. */
static int fig_focal(ctx *c)
{
    const swfs_real *maps[4] = {c->gain, c->mean_i, c->var_i, c->mean_sp};
    int count = 0;
    for (int k = 0; k < 4; k++) count += maps[k] != NULL;
    if (!count) return SWFS_OK;
    size_t n = c->nx * c->ny;
    double *z = malloc(n * sizeof *z);
    unsigned char *vmask = mask_from(c->valid, n);
    swfs_plot *p = NULL;
    char path[PATHMAX];
    int rc = join(path, c->out_dir, "focal.png");
    if (!rc && (!z || (c->valid && !vmask))) rc = swfs_fail(SWFS_ERR_NOMEM, "focal figure: out of memory");
    if (rc) goto done;
    int rows = count > 2 ? 2 : 1, h = rows == 2 ? H_GRID : H_ROW2;
    if ((rc = swfs_plot_create(&p, path, W_GRID, h, 2, rows))) goto done;
    swfs_plot_image_spec s;
    focal_spec(c, &s);
    static const double circles[] = {1, 2, 3, 4, 5, 6};
    const char *cnt = c->moments_from_cubes ? " (from the cube, noise included)" : "";
    char t_mean[96], t_var[96];
    snprintf(t_mean, sizeof t_mean, "mean science image Φ#dI#u%s", c->moments_from_cubes ? " (from the cube)" : "");
    snprintf(t_var, sizeof t_var, "science variance σ#u2#d#dI#u%s", cnt);
    int panel = 0;
    for (int k = 0; k < 4 && !rc; k++) {
        if (!maps[k]) continue;
        swfs_report_range r;
        switch (k) {
        case 0:
            r = prepare(c, "gain", maps[k]->data, n, vmask, R_AUTO, 1.0, 0, 0, z);
            s.title = "scale factor g (circles: 1-6 λ/D)";
            s.zlabel = "g";
            s.cmap = SWFS_CMAP_VIRIDIS;
            break;
        case 1:
            r = prepare(c, "mean_i", maps[k]->data, n, NULL, R_AUTO, 1.0, 0, 0, z);
            s.title = t_mean;
            s.zlabel = "mean intensity [counts]";
            s.cmap = SWFS_CMAP_MAGMA;
            break;
        case 2:
            r = prepare(c, "var_i", maps[k]->data, n, NULL, R_LOG_FIXED, 1.0, 0, 0, z);
            s.title = t_var;
            s.zlabel = "variance [counts²]";
            s.cmap = SWFS_CMAP_MAGMA;
            break;
        default:
            r = prepare(c, "mean_sp", maps[k]->data, n, NULL, R_AUTO, 1.0, 0, 0, z);
            s.title = "mean speckle power Φ#dsp#u";
            s.zlabel = "⟨|ψ|²⟩ [counts]";
            s.cmap = SWFS_CMAP_MAGMA;
            break;
        }
        apply_range(&s, &r);
        if ((rc = swfs_plot_panel(p, panel++)) || (rc = swfs_plot_image(p, z, c->nx, c->ny, &s))) break;
        if (k == 0 && have_pixscale(c))
            rc = swfs_plot_circles(p, 0.0, 0.0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (rc) goto done;
    rc = swfs_plot_commit(p);
    p = NULL;
    if (!rc)
        add_figure(c, "focal.png", W_GRID, h, "Focal-plane statistics",
                   "Scale factor g (eq:scale-factor) with circles at 1-6 λ/D, shown where it is defined; the "
                   "mean science image Φ_I; the science image variance σ²_I on a 4-decade log scale (noise "
                   "variance removed when it comes from halo.fits); the mean speckle power Φ_sp. Colour ranges "
                   "are robust percentiles of the data.");
done:
    swfs_plot_abort(p);
    free(z);
    free(vmask);
    return rc;
}

/* Least-squares I ~ a + b cos(phi) + c sin(phi). */
static void fit_sinusoid(const double *ph, const double *iv, size_t n, double coef[3])
{
    double m[3][4] = {{0}};
    for (size_t k = 0; k < n; k++) {
        double f[3] = {1.0, cos(ph[k]), sin(ph[k])};
        for (int a = 0; a < 3; a++) {
            for (int b = 0; b < 3; b++) m[a][b] += f[a] * f[b];
            m[a][3] += f[a] * iv[k];
        }
    }
    /* Gaussian elimination with partial pivoting. */
    for (int col = 0; col < 3; col++) {
        int piv = col;
        for (int r = col + 1; r < 3; r++)
            if (fabs(m[r][col]) > fabs(m[piv][col])) piv = r;
        for (int k = 0; k < 4; k++) {
            double t = m[col][k];
            m[col][k] = m[piv][k];
            m[piv][k] = t;
        }
        if (m[col][col] == 0.0) {
            coef[0] = coef[1] = coef[2] = NAN;
            return;
        }
        for (int r = 0; r < 3; r++) {
            if (r == col) continue;
            double f = m[r][col] / m[col][col];
            for (int k = col; k < 4; k++) m[r][k] -= f * m[col][k];
        }
    }
    for (int a = 0; a < 3; a++) coef[a] = m[a][3] / m[a][a];
}

/* pixel.png: one pixel's intensity against the speckle phase (fig:MMT-example-data). */
static int fig_pixel(ctx *c)
{
    if (!c->has_science || !c->has_speckles) return SWFS_OK;
    long pi = c->opt.pixel_i, pj = c->opt.pixel_j;
    if (pi < 0 || pj < 0) pi = c->ref_i, pj = c->ref_j;
    if (pi < 0 || pj < 0) {
        note(c, "pixel.png skipped: no pixel with a measurable halo in the first Airy ring");
        return SWFS_OK;
    }
    if ((size_t)pi >= c->nx || (size_t)pj >= c->ny)
        return swfs_fail(SWFS_ERR_ARG, "report: pixel (%ld, %ld) is outside the %zux%zu focal grid", pi, pj, c->nx,
                         c->ny);
    swfs_fits_in *fs = NULL, *fp = NULL;
    double *iv = NULL, *ph = NULL, *buf = NULL, *xs = NULL, *ys = NULL, *ym = NULL;
    double complex *cbuf = NULL;
    swfs_plot *p = NULL;
    char path[PATHMAX];
    int rc = join(path, c->out_dir, "pixel.png");
    if (!rc) rc = swfs_fits_in_open(&fs, c->p_science, NULL);
    if (!rc) rc = swfs_fits_in_open(&fp, c->p_speckles, NULL);
    if (rc) goto done;
    const swfs_fits_shape *ss = swfs_fits_in_shape(fs), *sp = swfs_fits_in_shape(fp);
    if (ss->is_complex || !sp->is_complex) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s / %s: expected a real science cube and a complex speckle cube",
                       c->p_science, c->p_speckles);
        goto done;
    }
    if ((rc = check_focal_shape(c, c->p_science, ss->nx, ss->ny)) ||
        (rc = check_focal_shape(c, c->p_speckles, sp->nx, sp->ny)))
        goto done;
    size_t nz = ss->nz < sp->nz ? ss->nz : sp->nz;
    if (ss->nz != sp->nz)
        note(c, "pixel.png uses the first %zu frames: science.fits has %zu, speckles.fits %zu", nz, ss->nz, sp->nz);
    size_t npix = c->nx * c->ny, chunk = 64, pk = (size_t)pj * c->nx + (size_t)pi;
    enum { NCURVE = 361 };
    iv = malloc((nz ? nz : 1) * sizeof *iv);
    ph = malloc((nz ? nz : 1) * sizeof *ph);
    buf = malloc(npix * chunk * sizeof *buf);
    cbuf = malloc(npix * chunk * sizeof *cbuf);
    xs = malloc(NCURVE * sizeof *xs);
    ys = malloc(NCURVE * sizeof *ys);
    ym = malloc(NCURVE * sizeof *ym);
    if (!iv || !ph || !buf || !cbuf || !xs || !ys || !ym) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "pixel figure: out of memory");
        goto done;
    }
    double sum_abs = 0.0;
    for (size_t k0 = 0; k0 < nz && !rc; k0 += chunk) {
        size_t m = nz - k0 < chunk ? nz - k0 : chunk;
        if ((rc = swfs_fits_in_read_real(fs, k0, m, buf)) || (rc = swfs_fits_in_read_cplx(fp, k0, m, cbuf))) break;
        for (size_t k = 0; k < m; k++) {
            iv[k0 + k] = buf[k * npix + pk];
            ph[k0 + k] = carg(cbuf[k * npix + pk]);
            sum_abs += cabs(cbuf[k * npix + pk]);
        }
    }
    if (rc) goto done;
    if (nz < 3) {
        note(c, "pixel.png skipped: fewer than 3 frames");
        goto done;
    }
    double coef[3];
    fit_sinusoid(ph, iv, nz, coef);
    double fit_phase = atan2(coef[2], coef[1]), fit_amp = hypot(coef[1], coef[2]);
    double halo_phase = c->halo ? carg(c->halo->data[pk]) : NAN;
    double imin = INFINITY, imax = -INFINITY, mean = 0.0;
    for (size_t k = 0; k < nz; k++) {
        if (isfinite(iv[k])) {
            imin = fmin(imin, iv[k]);
            imax = fmax(imax, iv[k]);
        }
        mean += iv[k] / (double)nz;
    }
    if (!(imax > imin)) imin -= 1.0, imax += 1.0;
    double pad = 0.06 * (imax - imin);
    /* Model curve: <I> + 2 g |Psi| <|psi|> cos(phi - arg Psi), the mean of
     * |Psi + g psi|^2 at fixed speckle phase when |psi| is independent of it. */
    int have_model = c->halo && c->gain;
    double g = have_model ? c->gain->data[pk] : NAN, habs = c->halo ? cabs(c->halo->data[pk]) : NAN;
    double mabs = sum_abs / (double)nz;
    for (int k = 0; k < NCURVE; k++) {
        xs[k] = -M_PI + 2.0 * M_PI * k / (NCURVE - 1);
        ys[k] = coef[0] + coef[1] * cos(xs[k]) + coef[2] * sin(xs[k]);
        ym[k] = mean + 2.0 * g * habs * mabs * cos(xs[k] - halo_phase);
    }

    if ((rc = swfs_plot_create(&p, path, W_PIXEL, H_PIXEL, 1, 1))) goto done;
    char title[200];
    if (have_pixscale(c))
        snprintf(title, sizeof title, "pixel (%ld, %ld) at θ = (%.2f, %.2f) λ/D, %zu frames", pi, pj,
                 focal_x(c, (double)pi, c->nx), focal_x(c, (double)pj, c->ny), nz);
    else
        snprintf(title, sizeof title, "pixel (%ld, %ld), %zu frames", pi, pj, nz);
    swfs_plot_axes_spec a = {title, "speckle phase arg ψ [rad]", "science intensity I [counts]", -M_PI, M_PI,
                             imin - pad, imax + 3.5 * pad, 0};
    if ((rc = swfs_plot_panel(p, 0)) || (rc = swfs_plot_axes(p, &a))) goto done;
    if ((rc = swfs_plot_points(p, ph, iv, nz, SWFS_COLOR_BLUE, 0.7))) goto done;
    if ((rc = swfs_plot_line(p, xs, ys, NCURVE, SWFS_COLOR_BLACK, SWFS_LINE_SOLID, 2.5))) goto done;
    swfs_plot_legend_entry e[4];
    size_t ne = 0;
    e[ne++] = (swfs_plot_legend_entry){"frames", SWFS_COLOR_BLUE, 1, SWFS_LINE_SOLID};
    e[ne++] = (swfs_plot_legend_entry){"least-squares sinusoid", SWFS_COLOR_BLACK, 0, SWFS_LINE_SOLID};
    if (have_model && isfinite(g) && isfinite(habs)) {
        if ((rc = swfs_plot_line(p, xs, ym, NCURVE, SWFS_COLOR_ORANGE, SWFS_LINE_DASHED, 2.5))) goto done;
        e[ne++] = (swfs_plot_legend_entry){"model ⟨I⟩ + 2g|Ψ|⟨|ψ|⟩ cos(φ − arg Ψ)", SWFS_COLOR_ORANGE, 0,
                                           SWFS_LINE_DASHED};
    }
    if (isfinite(halo_phase)) {
        double vx[2] = {halo_phase, halo_phase}, vy[2] = {imin - pad, imax + 3.5 * pad};
        if ((rc = swfs_plot_line(p, vx, vy, 2, SWFS_COLOR_RED, SWFS_LINE_DASHED, 2.0))) goto done;
        e[ne++] = (swfs_plot_legend_entry){"arg Ψ (estimated halo phase)", SWFS_COLOR_RED, 0, SWFS_LINE_DASHED};
    }
    if ((rc = swfs_plot_legend(p, e, ne))) goto done;
    rc = swfs_plot_commit(p);
    p = NULL;
    if (rc) goto done;
    c->sum->pixel_i = pi;
    c->sum->pixel_j = pj;
    c->sum->pixel_halo_phase = halo_phase;
    c->sum->pixel_fit_phase = fit_phase;
    char cap[600];
    snprintf(cap, sizeof cap,
             "Science intensity of one first-Airy-ring pixel against the speckle phase computed from the WFS "
             "(the paper's first figure). When the speckle phase matches the halo phase the intensity rises. "
             "Fitted sinusoid: amplitude %.4g counts, peak at %.2f rad; estimated halo phase arg Ψ = %.2f rad.",
             fit_amp, fit_phase, halo_phase);
    add_figure(c, "pixel.png", W_PIXEL, H_PIXEL, "Intensity against speckle phase", cap);
done:
    swfs_plot_abort(p);
    swfs_fits_in_close(fs);
    swfs_fits_in_close(fp);
    free(iv);
    free(ph);
    free(buf);
    free(cbuf);
    free(xs);
    free(ys);
    free(ym);
    return rc;
}

/* pupil.png: amplitude and WFE [nm] with the pupil outline; truth NCP and the error. */
static int fig_pupil(ctx *c)
{
    if (!c->has_wavefront) return SWFS_OK;
    swfs_fits_in *f = NULL;
    swfs_real *amp = NULL, *wfe = NULL, *pup = NULL, *ncp = NULL;
    double *z = NULL, *outline = NULL, *err = NULL;
    unsigned char *mask = NULL;
    swfs_plot *p = NULL;
    swfs_geom pg;
    char path[PATHMAX];
    int rc = join(path, c->out_dir, "pupil.png");
    if (!rc) rc = swfs_fits_in_open(&f, c->p_wavefront, NULL);
    if (!rc) rc = read_real_opt(f, "AMPLITUDE", &amp);
    if (!rc) rc = read_real_opt(f, "WFE", &wfe);
    if (!rc) rc = read_real_opt(f, "PUPIL", &pup);
    if (!rc) rc = swfs_fits_in_geom(f, &pg);
    double key_rms = NAN, key_pv = NAN, key_strehl = NAN, v;
    int found;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "WFERMS", &v, &found)) && found) key_rms = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "WFEPV", &v, &found)) && found) key_pv = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "STREHL", &v, &found)) && found) key_strehl = v;
    if (rc) goto done;
    if (!wfe) {
        note(c, "pupil.png skipped: wavefront.fits has no WFE extension");
        goto done;
    }
    size_t nx = wfe->nx, ny = wfe->ny, n = nx * ny;
    if (amp && (amp->nx != nx || amp->ny != ny)) {
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: AMPLITUDE is %zux%zu but WFE is %zux%zu", c->p_wavefront, amp->nx,
                       amp->ny, nx, ny);
        goto done;
    }
    if (!pup && c->has_pupil && (rc = swfs_fits_read_real(c->p_pupil, NULL, &pup, NULL))) goto done;
    if (pup && (pup->nx != nx || pup->ny != ny)) {
        note(c, "pupil mask is %zux%zu but WFE is %zux%zu: drawn without the pupil outline", pup->nx, pup->ny, nx, ny);
        swfs_real_free(pup);
        pup = NULL;
    }
    z = malloc(n * sizeof *z);
    outline = malloc(n * sizeof *outline);
    err = malloc(n * sizeof *err);
    mask = malloc(n);
    if (!z || !outline || !err || !mask) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
        goto done;
    }
    for (size_t k = 0; k < n; k++) {
        mask[k] = pup ? pup->data[k] > 0.5 : 1;
        outline[k] = mask[k];
    }
    /* WFE statistics inside the pupil, piston removed. */
    double s1 = 0, s2 = 0, mn = INFINITY, mx = -INFINITY;
    size_t cnt = 0;
    for (size_t k = 0; k < n; k++)
        if (mask[k] && isfinite(wfe->data[k])) {
            s1 += wfe->data[k];
            cnt++;
        }
    double piston = cnt ? s1 / (double)cnt : 0.0;
    for (size_t k = 0; k < n; k++)
        if (mask[k] && isfinite(wfe->data[k])) {
            double d = wfe->data[k] - piston;
            s2 += d * d;
            mn = fmin(mn, wfe->data[k]);
            mx = fmax(mx, wfe->data[k]);
        }
    c->sum->wfe_rms = isfinite(key_rms) ? key_rms : (cnt ? sqrt(s2 / (double)cnt) : NAN);
    c->sum->wfe_pv = isfinite(key_pv) ? key_pv : (cnt ? mx - mn : NAN);
    double lambda = isfinite(pg.wavelen) ? pg.wavelen : c->geom.wavelen;
    c->sum->strehl = isfinite(key_strehl) ? key_strehl
                     : isfinite(lambda) && lambda > 0
                         ? exp(-pow(2.0 * M_PI * c->sum->wfe_rms / lambda, 2.0))
                         : NAN;

    /* Truth: NCP on the same grid, piston removed inside the pupil. */
    if (c->has_truth) {
        swfs_fits_in *t = NULL;
        rc = swfs_fits_in_open(&t, c->p_truth, NULL);
        if (!rc) rc = read_real_opt(t, "NCP", &ncp);
        swfs_fits_in_close(t);
        if (rc) goto done;
        if (!ncp) note(c, "truth.fits has no NCP extension: no error map");
        else if (ncp->nx != nx || ncp->ny != ny) {
            note(c, "truth NCP is %zux%zu but WFE is %zux%zu: no error map", ncp->nx, ncp->ny, nx, ny);
            swfs_real_free(ncp);
            ncp = NULL;
        }
    }
    if (ncp) {
        /* Both piston-free inside the pupil: the error is what a user would correct. */
        double t1 = 0, e1 = 0, t2 = 0, e2 = 0;
        size_t tc = 0;
        for (size_t k = 0; k < n; k++)
            if (mask[k] && isfinite(ncp->data[k])) t1 += ncp->data[k], tc++;
        double tp = tc ? t1 / (double)tc : 0.0;
        for (size_t k = 0; k < n; k++) {
            ncp->data[k] -= tp;
            err[k] = wfe->data[k] - piston - ncp->data[k];
            if (mask[k] && isfinite(err[k])) e1 += err[k];
        }
        double ep = tc ? e1 / (double)tc : 0.0;
        for (size_t k = 0; k < n; k++) {
            err[k] -= ep;
            if (mask[k] && isfinite(err[k]) && isfinite(ncp->data[k])) {
                t2 += ncp->data[k] * ncp->data[k];
                e2 += err[k] * err[k];
            }
        }
        c->sum->ncp_rms = tc ? sqrt(t2 / (double)tc) : NAN;
        c->sum->err_rms = tc ? sqrt(e2 / (double)tc) : NAN;
    }

    int npanel = (amp ? 1 : 0) + 1 + (ncp ? 2 : 0);
    int rows = npanel > 2 ? 2 : 1, h = rows == 2 ? H_GRID : H_ROW2, cols = npanel > 1 ? 2 : 1;
    int w = cols == 2 ? W_GRID : W_PIXEL;
    if ((rc = swfs_plot_create(&p, path, w, h, cols, rows))) goto done;
    int havedx = isfinite(pg.pupdx) && pg.pupdx > 0;
    double dx = havedx ? pg.pupdx : 1.0;
    swfs_plot_image_spec s;
    memset(&s, 0, sizeof s);
    s.xlabel = havedx ? "x [m]" : "x [pupil sample]";
    s.ylabel = havedx ? "y [m]" : "y [pupil sample]";
    s.x0 = -0.5 * (double)(nx - 1) * dx;
    s.x1 = 0.5 * (double)(nx - 1) * dx;
    s.y0 = -0.5 * (double)(ny - 1) * dx;
    s.y1 = 0.5 * (double)(ny - 1) * dx;
    s.mask = mask;
    int panel = 0;
    swfs_report_range r;
    if (amp) {
        r = prepare(c, "amplitude", amp->data, n, mask, R_AUTO, 1.0, 0, 0, z);
        if ((rc = image_panel(p, panel++, &s, &r, "pupil amplitude |A|", "amplitude [arbitrary units]", SWFS_CMAP_GRAY,
                              z, nx, ny)))
            goto done;
        if (pup && (rc = swfs_plot_contour(p, outline, nx, ny, 0.5, SWFS_COLOR_RED, 1.5))) goto done;
    }
    /* One symmetric range for the WFE, the truth and the error, so they compare by eye. */
    double *wfe0 = malloc(n * sizeof *wfe0);
    if (!wfe0) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
        goto done;
    }
    for (size_t k = 0; k < n; k++) wfe0[k] = wfe->data[k] - piston;
    r = prepare(c, "wfe", wfe0, n, mask, R_SYM, 1e9, 0, 0, z);
    if (ncp) {
        double *tz = malloc(n * sizeof *tz);
        if (!tz) {
            free(wfe0);
            rc = swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
            goto done;
        }
        swfs_report_range rt = prepare(c, "ncp", ncp->data, n, mask, R_SYM, 1e9, 0, 0, tz);
        free(tz);
        if (rt.hi > r.hi) r.lo = rt.lo, r.hi = rt.hi;
        /* Record the shared range under every name. */
        for (size_t k = 0; k < c->sum->nranges; k++)
            if (!strcmp(c->sum->ranges[k].name, "wfe") || !strcmp(c->sum->ranges[k].name, "ncp")) {
                c->sum->ranges[k].lo = r.lo;
                c->sum->ranges[k].hi = r.hi;
            }
    }
    char t_wfe[160];
    snprintf(t_wfe, sizeof t_wfe, "estimated WFE: %.1f nm rms, %.0f nm PV", 1e9 * c->sum->wfe_rms,
             1e9 * c->sum->wfe_pv);
    s.title = t_wfe;
    s.zlabel = "wavefront error [nm]";
    s.cmap = SWFS_CMAP_DIVERGING;
    apply_range(&s, &r);
    rc = swfs_plot_panel(p, panel++);
    if (!rc) rc = swfs_plot_image(p, z, nx, ny, &s);
    if (!rc && pup) rc = swfs_plot_contour(p, outline, nx, ny, 0.5, SWFS_COLOR_BLACK, 1.5);
    if (!rc && ncp) {
        char t_ncp[160], t_err[160];
        snprintf(t_ncp, sizeof t_ncp, "true NCP (simulation): %.1f nm rms", 1e9 * c->sum->ncp_rms);
        snprintf(t_err, sizeof t_err, "error WFE − NCP: %.1f nm rms", 1e9 * c->sum->err_rms);
        for (size_t k = 0; k < n; k++) z[k] = mask[k] && isfinite(ncp->data[k]) ? 1e9 * ncp->data[k] : NAN;
        s.title = t_ncp;
        rc = swfs_plot_panel(p, panel++);
        if (!rc) rc = swfs_plot_image(p, z, nx, ny, &s);
        if (!rc && pup) rc = swfs_plot_contour(p, outline, nx, ny, 0.5, SWFS_COLOR_BLACK, 1.5);
        swfs_report_range re = prepare(c, "err", err, n, mask, R_FIXED, 1e9, r.lo, r.hi, z);
        s.title = t_err;
        apply_range(&s, &re);
        if (!rc) rc = swfs_plot_panel(p, panel++);
        if (!rc) rc = swfs_plot_image(p, z, nx, ny, &s);
        if (!rc && pup) rc = swfs_plot_contour(p, outline, nx, ny, 0.5, SWFS_COLOR_BLACK, 1.5);
    }
    free(wfe0);
    if (rc) goto done;
    rc = swfs_plot_commit(p);
    p = NULL;
    if (!rc)
        add_figure(c, "pupil.png", w, h, "Pupil field and wavefront",
                   ncp ? "Pupil amplitude and the estimated wavefront error (eq:NCP-WFE-estimate) in nm with the "
                         "pupil outline; the true non-common-path aberration of the simulation and the error map "
                         "(estimate minus truth, piston removed), all on one colour scale."
                       : "Pupil amplitude and the estimated wavefront error (eq:NCP-WFE-estimate) in nm, piston "
                         "removed, with the pupil outline.");
done:
    swfs_plot_abort(p);
    swfs_fits_in_close(f);
    swfs_real_free(amp);
    swfs_real_free(wfe);
    swfs_real_free(pup);
    swfs_real_free(ncp);
    free(z);
    free(outline);
    free(err);
    free(mask);
    return rc;
}

/* coherence.png: tau0, phase-rotation time, SNR factor, Gamma(tau)/Gamma(0) of a pixel. */
static int fig_coherence(ctx *c)
{
    if (!c->has_coherence) return SWFS_OK;
    swfs_fits_in *f = NULL;
    swfs_real *tau0 = NULL, *trot = NULL, *sf = NULL, *msp = NULL, *lags = NULL;
    swfs_cplx *mcf = NULL;
    double *z = NULL, *gx = NULL, *gy = NULL;
    swfs_plot *p = NULL;
    char path[PATHMAX];
    int rc = join(path, c->out_dir, "coherence.png");
    if (!rc) rc = swfs_fits_in_open(&f, c->p_coherence, NULL);
    if (!rc) rc = read_real_opt(f, "TAU0", &tau0);
    if (!rc) rc = read_real_opt(f, "TROT", &trot);
    if (!rc) rc = read_real_opt(f, "SNR_FACT", &sf);
    if (!rc) rc = read_real_opt(f, "MEAN_SP", &msp);
    if (!rc) rc = read_real_opt(f, "LAGS", &lags);
    if (!rc && swfs_fits_in_has_ext(f, "MCF")) {
        rc = swfs_fits_in_move(f, "MCF");
        if (!rc) rc = swfs_fits_in_read_cplx_all(f, &mcf);
    }
    if (!rc && c->nx == 0) {
        swfs_geom g;
        if (!(rc = swfs_fits_in_geom(f, &g))) c->geom = g;
    }
    if (rc) goto done;
    swfs_real *maps[3] = {tau0, trot, sf};
    for (int k = 0; k < 3 && !rc; k++)
        if (maps[k]) rc = check_focal_shape(c, c->p_coherence, maps[k]->nx, maps[k]->ny);
    if (!rc && mcf) rc = check_focal_shape(c, c->p_coherence, mcf->nx, mcf->ny);
    if (rc) goto done;
    if (!tau0 && !trot && !sf && !mcf) {
        note(c, "coherence.png skipped: coherence.fits has none of TAU0, TROT, SNR_FACT, MCF");
        goto done;
    }
    size_t n = c->nx * c->ny;
    z = malloc(n * sizeof *z);
    if (!z) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "coherence figure: out of memory");
        goto done;
    }
    int npanel = (tau0 != NULL) + (trot != NULL) + (sf != NULL) + (mcf != NULL);
    int rows = npanel > 2 ? 2 : 1, cols = npanel > 1 ? 2 : 1, h = rows == 2 ? H_GRID : H_ROW2;
    int w = cols == 2 ? W_GRID : W_PIXEL;
    if ((rc = swfs_plot_create(&p, path, w, h, cols, rows))) goto done;
    swfs_plot_image_spec s;
    focal_spec(c, &s);
    static const double circles[] = {1, 2, 3, 4, 5, 6};
    int panel = 0;
    swfs_report_range r;
    if (tau0) {
        c->sum->tau0_median = swfs_report_percentile(tau0->data, n, NULL, 50.0);
        r = prepare(c, "tau0", tau0->data, n, NULL, R_AUTO, 1e3, 0, 0, z);
        rc = image_panel(p, panel++, &s, &r, "coherence time τ₀ (|Γ(τ)/Γ(0)| = e#u-1/2#d)", "τ₀ [ms]",
                         SWFS_CMAP_VIRIDIS, z, c->nx, c->ny);
        if (!rc && have_pixscale(c))
            rc = swfs_plot_circles(p, 0, 0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (!rc && trot) {
        r = prepare(c, "trot", trot->data, n, NULL, R_AUTO, 1e3, 0, 0, z);
        rc = image_panel(p, panel++, &s, &r, "phase-rotation time (±π/2)", "time [ms]", SWFS_CMAP_VIRIDIS, z, c->nx,
                         c->ny);
        if (!rc && have_pixscale(c))
            rc = swfs_plot_circles(p, 0, 0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (!rc && sf) {
        r = prepare(c, "snr_fact", sf->data, n, NULL, R_AUTO, 1.0, 0, 0, z);
        rc = image_panel(p, panel++, &s, &r, "SNR factor of the exposure time", "SNR / ideal short-exposure SNR",
                         SWFS_CMAP_GRAY, z, c->nx, c->ny);
    }
    if (!rc && mcf) {
        size_t nl = mcf->nz;
        long bi = c->opt.pixel_i, bj = c->opt.pixel_j;
        if (bi < 0 || bj < 0 || (size_t)bi >= c->nx || (size_t)bj >= c->ny) {
            /* The paper shows a pixel in the second Airy ring: the one with most speckle power. */
            double *score = malloc(n * sizeof *score);
            if (!score) {
                rc = swfs_fail(SWFS_ERR_NOMEM, "coherence figure: out of memory");
                goto done;
            }
            for (size_t k = 0; k < n; k++) score[k] = msp ? msp->data[k] : cabs(mcf->data[k]);
            if (!best_pixel(c, score, NULL, RING2_MIN, RING2_MAX, &bi, &bj)) best_pixel(c, score, NULL, 0, 1e9, &bi, &bj);
            free(score);
        }
        gx = malloc((nl + 1) * sizeof *gx);
        gy = malloc((nl + 1) * sizeof *gy);
        if (!gx || !gy) {
            rc = swfs_fail(SWFS_ERR_NOMEM, "coherence figure: out of memory");
            goto done;
        }
        size_t pk = (size_t)bj * c->nx + (size_t)bi;
        double complex g0 = mcf->data[pk];
        size_t ng = 0;
        for (size_t l = 0; l < nl && cabs(g0) > 0; l++) {
            double complex gl = mcf->data[l * n + pk] / g0;
            if (!isfinite(creal(gl)) || !isfinite(cimag(gl))) continue;
            gx[ng] = creal(gl);
            gy[ng] = cimag(gl);
            ng++;
        }
        char title[160];
        if (have_pixscale(c))
            snprintf(title, sizeof title, "Γ(τ)/Γ(0) at pixel (%ld, %ld), |θ| = %.2f λ/D", bi, bj,
                     hypot(focal_x(c, (double)bi, c->nx), focal_x(c, (double)bj, c->ny)));
        else
            snprintf(title, sizeof title, "Γ(τ)/Γ(0) at pixel (%ld, %ld)", bi, bj);
        swfs_plot_axes_spec a = {title, "Re Γ(τ)/Γ(0)", "Im Γ(τ)/Γ(0)", -1.1, 1.1, -1.1, 1.1, 1};
        double one = 1.0, e12 = exp(-0.5);
        rc = swfs_plot_panel(p, panel++);
        if (!rc) rc = swfs_plot_axes(p, &a);
        if (!rc) rc = swfs_plot_circles(p, 0, 0, &one, 1, SWFS_COLOR_GRAY, SWFS_LINE_DOTTED, 1.0);
        if (!rc) rc = swfs_plot_circles(p, 0, 0, &e12, 1, SWFS_COLOR_RED, SWFS_LINE_DASHED, 2.0);
        if (!rc) rc = swfs_plot_line(p, gx, gy, ng, SWFS_COLOR_BLUE, SWFS_LINE_SOLID, 1.5);
        if (!rc) rc = swfs_plot_points(p, gx, gy, ng, SWFS_COLOR_BLUE, 1.0);
        if (!rc && ng > 0) {
            char lab[64];
            double tl = lags && lags->nx * lags->ny * lags->nz >= nl ? lags->data[nl - 1] : NAN;
            if (isfinite(tl)) snprintf(lab, sizeof lab, "τ = %.0f ms", 1e3 * tl);
            else snprintf(lab, sizeof lab, "lag %zu", nl - 1);
            rc = swfs_plot_text(p, gx[ng - 1], gy[ng - 1] - 0.12, 0.5, SWFS_COLOR_BLUE, lab);
        }
        swfs_plot_legend_entry e[2] = {{"Γ(τ)/Γ(0)", SWFS_COLOR_BLUE, 0, SWFS_LINE_SOLID},
                                       {"radius e#u-1/2#d (defines τ₀)", SWFS_COLOR_RED, 0, SWFS_LINE_DASHED}};
        if (!rc) rc = swfs_plot_legend(p, e, 2);
    }
    if (rc) goto done;
    rc = swfs_plot_commit(p);
    p = NULL;
    if (!rc)
        add_figure(c, "coherence.png", w, h, "Speckle coherence",
                   "Speckle coherence time τ₀ where |Γ(τ)/Γ(0)| falls to e^-1/2, the time for the speckle phase "
                   "to rotate by ±π/2 (dashed circles at 1-6 λ/D), the SNR factor of the science exposure time, "
                   "and the normalized mutual coherence function Γ(τ)/Γ(0) of one second-ring pixel in the "
                   "complex plane with the e^-1/2 circle.");
done:
    swfs_plot_abort(p);
    swfs_fits_in_close(f);
    swfs_real_free(tau0);
    swfs_real_free(trot);
    swfs_real_free(sf);
    swfs_real_free(msp);
    swfs_real_free(lags);
    swfs_cplx_free(mcf);
    free(z);
    free(gx);
    free(gy);
    return rc;
}

/* ---- index.html -------------------------------------------------------- */

static void row(strbuf *b, const char *key, const char *val, const char *id)
{
    sb_printf(b, "<tr><th>%s</th><td id=\"%s\">%s</td></tr>\n", key, id, val);
}

static int write_html(ctx *c)
{
    swfs_report_summary *s = c->sum;
    char path[PATHMAX], part[PATHMAX + 8];
    int rc = join(path, c->out_dir, "index.html");
    if (rc) return rc;
    snprintf(part, sizeof part, "%s.part", path);
    strbuf b = {0};
    char title[PATHMAX + 64];
    if (c->opt.title) snprintf(title, sizeof title, "%s", c->opt.title);
    else snprintf(title, sizeof title, "specklewfs report: %s", c->run_dir);
    sb_printf(&b, "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>");
    sb_text(&b, title);
    sb_printf(&b,
              "</title>\n<style>\n"
              "body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em;color:#222}\n"
              "table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #ccc;padding:.3em .8em;"
              "text-align:left}th{background:#f4f4f4}\n"
              "img{max-width:100%%;height:auto;border:1px solid #ddd}figcaption{color:#444;margin:.4em 0 1.5em}\n"
              ".notes li{color:#7a4b00}\n</style>\n"
              "<script>\n"
              "window.addEventListener('load', function () {\n"
              "  var imgs = document.images, ok = 0;\n"
              "  for (var i = 0; i < imgs.length; i++) if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++;\n"
              "  document.body.setAttribute('data-images-ok', String(ok));\n"
              "  document.body.setAttribute('data-images-total', String(imgs.length));\n"
              "});\n</script>\n</head>\n<body>\n<h1>");
    sb_text(&b, title);
    sb_printf(&b, "</h1>\n<p>Focal-plane wavefront sensing with residual AO speckles (Codona &amp; Kenworthy 2013). "
                  "specklewfs %s.</p>\n<h2>Key numbers</h2>\n<table id=\"key-numbers\">\n", SWFS_VERSION);
    char v[256];
    if (isfinite(s->frames)) snprintf(v, sizeof v, "%.0f", s->frames);
    else snprintf(v, sizeof v, "n/a");
    row(&b, "frames", v, "frames");
    if (isfinite(s->valid_fraction)) snprintf(v, sizeof v, "%.1f %%", 100.0 * s->valid_fraction);
    else snprintf(v, sizeof v, "n/a");
    row(&b, "valid fraction (g defined)", v, "valid-fraction");
    if (isfinite(s->median_snr)) snprintf(v, sizeof v, "%.2f", s->median_snr);
    else snprintf(v, sizeof v, "n/a");
    row(&b, "median SNR (valid pixels)", v, "median-snr");
    if (isfinite(s->wfe_rms)) snprintf(v, sizeof v, "%.1f nm rms / %.1f nm PV", 1e9 * s->wfe_rms, 1e9 * s->wfe_pv);
    else snprintf(v, sizeof v, "n/a");
    row(&b, "estimated WFE", v, "wfe");
    if (isfinite(s->strehl)) snprintf(v, sizeof v, "%.3f", s->strehl);
    else snprintf(v, sizeof v, "n/a");
    row(&b, "Strehl estimate (Maréchal)", v, "strehl");
    if (isfinite(s->err_rms)) {
        snprintf(v, sizeof v, "%.1f nm rms (true NCP %.1f nm rms, residual %.0f %%)", 1e9 * s->err_rms,
                 1e9 * s->ncp_rms, s->ncp_rms > 0 ? 100.0 * s->err_rms / s->ncp_rms : NAN);
        row(&b, "recovery error WFE − true NCP", v, "recovered-error");
    }
    if (isfinite(s->tau0_median)) {
        snprintf(v, sizeof v, "%.1f ms", 1e3 * s->tau0_median);
        row(&b, "median speckle coherence time τ₀", v, "tau0");
    }
    if (s->pixel_i >= 0) {
        snprintf(v, sizeof v, "pixel (%ld, %ld): fitted %.2f rad, arg Ψ %.2f rad", s->pixel_i, s->pixel_j,
                 s->pixel_fit_phase, s->pixel_halo_phase);
        row(&b, "halo phase check", v, "pixel-phase");
    }
    sb_printf(&b, "</table>\n");
    if (s->nnotes) {
        sb_printf(&b, "<h2>Notes</h2>\n<ul class=\"notes\">\n");
        for (size_t k = 0; k < s->nnotes; k++) {
            sb_printf(&b, "<li>");
            sb_text(&b, s->notes[k]);
            sb_printf(&b, "</li>\n");
        }
        sb_printf(&b, "</ul>\n");
    }
    if (c->figs.len) sb_printf(&b, "%s", c->figs.s);
    else sb_printf(&b, "<p>No figures: the run folder holds no products to draw.</p>\n");
    time_t now = time(NULL);
    char date[64];
    strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S UTC", gmtime(&now));
    sb_printf(&b, "<hr><p><small>Products read from <code>");
    sb_text(&b, c->run_dir);
    sb_printf(&b, "</code> on %s by specklewfs %s.</small></p>\n</body>\n</html>\n", date, SWFS_VERSION);
    if (b.oom) {
        free(b.s);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    FILE *f = fopen(part, "wb");
    if (!f) {
        free(b.s);
        return swfs_fail(SWFS_ERR_IO, "%s: cannot create: %s", part, strerror(errno));
    }
    size_t wr = fwrite(b.s, 1, b.len, f);
    int bad = wr != b.len;
    if (fclose(f) != 0) bad = 1;
    free(b.s);
    if (bad) {
        remove(part);
        return swfs_fail(SWFS_ERR_IO, "%s: write failed", part);
    }
    if (rename(part, path) != 0) {
        remove(part);
        return swfs_fail(SWFS_ERR_IO, "%s: cannot rename into place: %s", path, strerror(errno));
    }
    snprintf(s->html, sizeof s->html, "%s", path);
    return SWFS_OK;
}

/* ---- entry point ------------------------------------------------------- */

void swfs_report_options_default(swfs_report_options *o)
{
    memset(o, 0, sizeof *o);
    o->pct_lo = 1.0;
    o->pct_hi = 99.5;
    o->log_decades = 4.0;
    o->pixel_i = o->pixel_j = -1;
    o->title = NULL;
}

static void summary_init(swfs_report_summary *s)
{
    memset(s, 0, sizeof *s);
    s->frames = s->valid_fraction = s->median_snr = NAN;
    s->wfe_rms = s->wfe_pv = s->strehl = s->ncp_rms = s->err_rms = s->tau0_median = NAN;
    s->pixel_i = s->pixel_j = -1;
    s->pixel_halo_phase = s->pixel_fit_phase = NAN;
}

static void ctx_free(ctx *c)
{
    swfs_cplx_free(c->halo);
    swfs_real *r[] = {c->gain, c->visib, c->snr, c->mean_i, c->var_i, c->mean_sp, c->valid};
    for (size_t k = 0; k < sizeof r / sizeof r[0]; k++) swfs_real_free(r[k]);
    free(c->figs.s);
}

int swfs_report_run(const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                    swfs_report_summary *summary)
{
    if (!run_dir || !*run_dir) return swfs_fail(SWFS_ERR_ARG, "report: no run folder given");
    struct stat sb;
    if (stat(run_dir, &sb) != 0 || !S_ISDIR(sb.st_mode))
        return swfs_fail(SWFS_ERR_IO, "%s: not a folder", run_dir);
    swfs_report_summary local;
    ctx c;
    memset(&c, 0, sizeof c);
    c.run_dir = run_dir;
    c.sum = summary ? summary : &local;
    summary_init(c.sum);
    if (opt) c.opt = *opt;
    else swfs_report_options_default(&c.opt);
    if (!(c.opt.pct_lo >= 0 && c.opt.pct_hi <= 100 && c.opt.pct_lo < c.opt.pct_hi))
        return swfs_fail(SWFS_ERR_ARG, "report: percentiles must satisfy 0 <= lo < hi <= 100, got %g, %g",
                         c.opt.pct_lo, c.opt.pct_hi);
    if (!(c.opt.log_decades > 0)) return swfs_fail(SWFS_ERR_ARG, "report: log_decades must be positive");
    c.ref_i = c.ref_j = -1;
    swfs_geom_init(&c.geom);
    int rc;
    if (out_dir) {
        if (strlen(out_dir) >= PATHMAX) return swfs_fail(SWFS_ERR_ARG, "report: output path too long");
        snprintf(c.out_dir, sizeof c.out_dir, "%s", out_dir);
    } else if ((rc = join(c.out_dir, run_dir, "report"))) {
        return rc;
    }
    if ((rc = make_dirs(c.out_dir))) return rc;

    struct { char *dst; const char *name; int *has; } prod[] = {
        {c.p_science, "science.fits", &c.has_science},     {c.p_speckles, "speckles.fits", &c.has_speckles},
        {c.p_truth, "truth.fits", &c.has_truth},           {c.p_pupil, "pupil.fits", &c.has_pupil},
        {c.p_halo, "halo.fits", &c.has_halo},              {c.p_wavefront, "wavefront.fits", &c.has_wavefront},
        {c.p_coherence, "coherence.fits", &c.has_coherence},
    };
    for (size_t k = 0; k < sizeof prod / sizeof prod[0]; k++) {
        if ((rc = join(prod[k].dst, run_dir, prod[k].name))) return rc;
        *prod[k].has = file_exists(prod[k].dst);
    }

    if (!swfs_plot_available()) note(&c, "no figures: this build has no PLplot pngcairo device");

    /* Focal products: halo.fits, or the raw cubes' moments. */
    if (c.has_halo) rc = load_halo(&c);
    if (!rc && c.has_science && !isfinite(c.sum->frames)) {
        swfs_fits_in *f;
        if (!(rc = swfs_fits_in_open(&f, c.p_science, NULL))) {
            c.sum->frames = (double)swfs_fits_in_shape(f)->nz;
            if (c.nx == 0 || !have_pixscale(&c)) rc = swfs_fits_in_geom(f, &c.geom);
            swfs_fits_in_close(f);
        }
    }
    if (!rc && !c.has_halo) {
        note(&c, "halo.fits not found: static halo figure skipped (run 'specklewfs estimate')");
        if (c.has_science) {
            c.moments_from_cubes = 1;
            rc = cube_moments(&c, c.p_science, 0, &c.mean_i, &c.var_i);
        }
        if (!rc && c.has_speckles) {
            c.moments_from_cubes = 1;
            rc = cube_moments(&c, c.p_speckles, 1, &c.mean_sp, NULL);
        }
    }
    if (rc) goto done;

    /* Reference pixel: user's, else the best-SNR valid pixel in the first Airy ring. */
    if (c.nx) {
        long oi = c.opt.pixel_i, oj = c.opt.pixel_j;
        if (oi >= 0 && oj >= 0) {
            if ((size_t)oi >= c.nx || (size_t)oj >= c.ny) {
                rc = swfs_fail(SWFS_ERR_ARG, "report: pixel (%ld, %ld) is outside the %zux%zu focal grid", oi, oj,
                               c.nx, c.ny);
                goto done;
            }
            c.ref_i = oi;
            c.ref_j = oj;
        } else {
            size_t n = c.nx * c.ny;
            double *score = malloc(n * sizeof *score);
            unsigned char *ok = mask_from(c.valid, n);
            if (!score || (c.valid && !ok)) {
                free(score);
                free(ok);
                rc = swfs_fail(SWFS_ERR_NOMEM, "report: out of memory");
                goto done;
            }
            for (size_t k = 0; k < n; k++)
                score[k] = c.snr ? c.snr->data[k] : c.halo ? cabs(c.halo->data[k]) : c.mean_sp ? c.mean_sp->data[k] : NAN;
            best_pixel(&c, score, ok, RING1_MIN, RING1_MAX, &c.ref_i, &c.ref_j);
            free(score);
            free(ok);
        }
    }

    if (swfs_plot_available()) {
        if ((rc = fig_halo(&c)) || (rc = fig_focal(&c)) || (rc = fig_pixel(&c)) || (rc = fig_pupil(&c)) ||
            (rc = fig_coherence(&c)))
            goto done;
    }
    if (!c.has_science || !c.has_speckles)
        note(&c, "science.fits and speckles.fits needed for the intensity-against-phase figure");
    if (!c.has_wavefront) note(&c, "wavefront.fits not found: pupil figure skipped (run 'specklewfs pupil')");
    if (!c.has_coherence)
        note(&c, "coherence.fits not found: coherence figure skipped (run 'specklewfs coherence')");
    rc = write_html(&c);
done:
    ctx_free(&c);
    return rc;
}

/* The report (include/specklewfs/report.h, docs/report.md): the entry point and one run
 * folder's products. halo.fits comes through io's reader (swfs_halo_read); without it the
 * maps are the moments of the cubes through the estimator's own accumulators (accum.h).
 * The figures are in fig_*.c, the page in html.c, a demo folder in demo.c. */
#include "report_internal.h"

#include "specklewfs/accum.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

const char *const rep_product_file[P_COUNT] = {"science.fits", "speckles.fits", "truth.fits", "pupil.fits",
                                               "halo.fits", "wavefront.fits", "coherence.fits"};

/* ---- small helpers ------------------------------------------------------ */

int rep_file_exists(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0 && S_ISREG(sb.st_mode);
}

int rep_dir_exists(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0 && S_ISDIR(sb.st_mode);
}

int rep_join(char *dst, const char *dir, const char *name)
{
    int n = snprintf(dst, REP_PATHMAX, "%s/%s", dir, name);
    if (n < 0 || n >= REP_PATHMAX) return swfs_fail(SWFS_ERR_ARG, "%s: path too long", dir);
    return SWFS_OK;
}

int rep_make_dirs(const char *path)
{
    char tmp[REP_PATHMAX];
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
    if (!rep_dir_exists(tmp)) return swfs_fail(SWFS_ERR_IO, "%s: not a folder", tmp);
    return SWFS_OK;
}

void rep_note(rep_ctx *c, const char *fmt, ...)
{
    swfs_report_summary *s = c->top;
    if (s->nnotes >= SWFS_REPORT_MAX_NOTES) return;
    char msg[sizeof s->notes[0]];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(msg, sizeof msg, fmt, ap);
    va_end(ap);
    snprintf(s->notes[s->nnotes++], sizeof s->notes[0], "%s%s", c->label, msg);
}

void rep_add_figure(rep_ctx *c, const char *file, int w, int h, const char *heading, const char *caption)
{
    swfs_report_summary *s = c->top;
    if (s->nfigures < SWFS_REPORT_MAX_FIGURES) {
        swfs_report_figure *f = &s->figures[s->nfigures++];
        snprintf(f->file, sizeof f->file, "%s%s", c->href, file);
        f->width = w;
        f->height = h;
    }
    rep_printf(&c->figs, "<section>\n<h3>");
    rep_text(&c->figs, heading);
    rep_printf(&c->figs, "</h3>\n<figure><img src=\"%s%s\" width=\"%d\" height=\"%d\" alt=\"", c->href, file, w, h);
    rep_text(&c->figs, heading);
    rep_printf(&c->figs, "\"><figcaption>");
    rep_text(&c->figs, caption);
    rep_printf(&c->figs, "</figcaption></figure>\n</section>\n");
}

int rep_commit(rep_ctx *c, swfs_plot **p, const char *file, int w, int h, const char *heading, const char *caption)
{
    int rc = swfs_plot_commit(*p);
    *p = NULL;
    if (!rc) rep_add_figure(c, file, w, h, heading, caption);
    return rc;
}

int rep_read_real_opt(swfs_fits_in *f, const char *ext, swfs_real **out)
{
    *out = NULL;
    if (!swfs_fits_in_has_ext(f, ext)) return SWFS_OK;
    int rc = swfs_fits_in_move(f, ext);
    if (!rc) rc = swfs_fits_in_read_real_all(f, out);
    return rc;
}

void swfs_report_options_default(swfs_report_options *o)
{
    memset(o, 0, sizeof *o);
    o->pct_lo = 1.0;
    o->pct_hi = 99.5;
    o->log_decades = 4.0;
    o->pixel_i = o->pixel_j = -1;
    o->title = NULL;
}

void rep_summary_init(swfs_report_summary *s)
{
    memset(s, 0, sizeof *s);
    s->frames = s->valid_fraction = s->median_snr = NAN;
    s->wfe_rms = s->wfe_pv = s->strehl = s->ncp_rms = s->err_rms = s->tau0_median = NAN;
    s->pixel_i = s->pixel_j = -1;
    s->pixel_halo_phase = s->pixel_fit_phase = NAN;
}

/* ---- the run folder ------------------------------------------------------ */

int rep_ctx_init(rep_ctx *c, const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                 swfs_report_summary *sum, swfs_report_summary *top)
{
    memset(c, 0, sizeof *c);
    c->run_dir = run_dir;
    c->href = "";
    c->label = "";
    c->opt = *opt;
    c->sum = sum;
    c->top = top;
    c->ref_i = c->ref_j = -1;
    swfs_geom_init(&c->geom);
    if (strlen(out_dir) >= sizeof c->out_dir) return swfs_fail(SWFS_ERR_ARG, "report: output path too long");
    snprintf(c->out_dir, sizeof c->out_dir, "%s", out_dir);
    for (int k = 0; k < P_COUNT; k++) {
        int rc = rep_join(c->path[k], run_dir, rep_product_file[k]);
        if (rc) return rc;
        c->has[k] = rep_file_exists(c->path[k]);
    }
    return SWFS_OK;
}

void rep_ctx_free(rep_ctx *c)
{
    swfs_halo_free(c->halo_file);
    swfs_real_free(c->cube_mean_i);
    swfs_real_free(c->cube_var_i);
    swfs_real_free(c->cube_mean_sp);
    free(c->figs.s);
}

int rep_ctx_reportable(const rep_ctx *c)
{
    return c->has[P_SCIENCE] + c->has[P_SPECKLES] + c->has[P_HALO] + c->has[P_WAVEFRONT] + c->has[P_COHERENCE];
}

static int load_halo(rep_ctx *c)
{
    swfs_halo *h = NULL;
    int rc = swfs_halo_read(c->path[P_HALO], &h, &c->geom);
    if (rc) return rc;
    c->halo_file = h;
    c->nx = h->nx;
    c->ny = h->ny;
    c->halo = h->halo;
    c->gain = h->gain, c->visib = h->visib, c->snr = h->snr, c->valid = h->valid;
    c->mean_i = h->mean_i, c->var_i = h->var_i, c->mean_sp = h->mean_sp;
    if (h->frames > 0) c->sum->frames = (double)h->frames;
    c->sum->valid_fraction = h->valid_fraction;
    c->sum->median_snr = h->median_snr;
    return SWFS_OK;
}

/* Open a cube of the expected kind on the run's focal grid. */
static int open_cube(rep_ctx *c, int product, swfs_fits_in **f)
{
    const char *path = c->path[product];
    const int want_complex = product == P_SPECKLES;
    int rc = swfs_fits_in_open(f, path, NULL);
    if (rc) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(*f);
    if (sh->is_complex != want_complex)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: expected a %s cube", path, want_complex ? "complex" : "real");
    return rep_check_focal_shape(c, path, sh->nx, sh->ny);
}

/* Phi_I, sigma_I^2 (unbiased, noise included) and Phi_sp of the cubes through the
 * estimator's accumulators; a missing cube is fed as zeros. */
static int cube_moments(rep_ctx *c)
{
    swfs_fits_in *fs = NULL, *fp = NULL;
    swfs_accum *acc = NULL;
    double *buf = NULL;
    swfs_complex *cbuf = NULL;
    int rc = SWFS_OK;
    if (c->has[P_SCIENCE]) rc = open_cube(c, P_SCIENCE, &fs);
    if (!rc && c->has[P_SPECKLES]) rc = open_cube(c, P_SPECKLES, &fp);
    if (rc || (!fs && !fp)) goto done;
    size_t nz = fs ? swfs_fits_in_shape(fs)->nz : SIZE_MAX;
    if (fp && swfs_fits_in_shape(fp)->nz < nz) nz = swfs_fits_in_shape(fp)->nz;
    const size_t np = c->nx * c->ny, block = 64;
    acc = swfs_accum_create(c->nx, c->ny);
    buf = calloc(np * block, sizeof *buf);
    cbuf = calloc(np * block, sizeof *cbuf);
    if (!acc || !buf || !cbuf) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", c->run_dir);
        goto done;
    }
    for (size_t k0 = 0; k0 < nz && !rc; k0 += block) {
        size_t m = nz - k0 < block ? nz - k0 : block;
        if ((fs && (rc = swfs_fits_in_read_real(fs, k0, m, buf))) || (fp && (rc = swfs_fits_in_read_cplx(fp, k0, m, cbuf))))
            break;
        for (size_t j = 0; j < m && !rc; j++)
            if ((rc = swfs_accum_add(acc, buf + j * np, cbuf + j * np)))
                swfs_fail_context(rc, "%s, frame %zu", c->path[P_SPECKLES], k0 + j);
    }
    if (rc) goto done;
    double *const *f = acc->f;
    if (fs && (c->cube_mean_i = swfs_real_alloc(c->nx, c->ny, 1)) && (c->cube_var_i = swfs_real_alloc(c->nx, c->ny, 1)))
        for (size_t p = 0; p < np; p++) {
            double n = f[SWFS_ACC_N][p];
            c->cube_mean_i->data[p] = n > 0 ? f[SWFS_ACC_MI][p] : NAN;
            c->cube_var_i->data[p] = n > 1 ? f[SWFS_ACC_CII][p] / (n - 1.0) : NAN;
        }
    if (fp && (c->cube_mean_sp = swfs_real_alloc(c->nx, c->ny, 1)))
        for (size_t p = 0; p < np; p++) { /* Phi_sp = Var x + Var y, the estimator's */
            double n = f[SWFS_ACC_N][p];
            c->cube_mean_sp->data[p] = n > 0 ? (f[SWFS_ACC_CXX][p] + f[SWFS_ACC_CYY][p]) / n : NAN;
        }
    if ((fs && (!c->cube_mean_i || !c->cube_var_i)) || (fp && !c->cube_mean_sp))
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", c->run_dir);
    c->mean_i = c->cube_mean_i, c->var_i = c->cube_var_i, c->mean_sp = c->cube_mean_sp;
    c->moments_from_cubes = 1;
done:
    swfs_fits_in_close(fs);
    swfs_fits_in_close(fp);
    swfs_accum_free(acc);
    free(buf);
    free(cbuf);
    return rc;
}

/* The focal maps: halo.fits, else the cubes' moments; frames and geometry. */
static int load_focal(rep_ctx *c)
{
    int rc = SWFS_OK;
    if (c->has[P_HALO]) rc = load_halo(c);
    if (!rc && c->has[P_SCIENCE] && !isfinite(c->sum->frames)) {
        swfs_fits_in *f;
        if (!(rc = swfs_fits_in_open(&f, c->path[P_SCIENCE], NULL))) {
            c->sum->frames = (double)swfs_fits_in_shape(f)->nz;
            if (c->nx == 0 || !rep_have_pixscale(c)) rc = swfs_fits_in_geom(f, &c->geom);
            swfs_fits_in_close(f);
        }
    }
    if (!rc && !c->has[P_HALO]) {
        rep_note(c, "halo.fits not found: static halo figure skipped (run 'specklewfs estimate')");
        rc = cube_moments(c);
    }
    return rc;
}

/* The user's pixel, else the best-SNR valid pixel in the first Airy ring. */
static int choose_ref_pixel(rep_ctx *c)
{
    if (!c->nx) return SWFS_OK;
    long oi = c->opt.pixel_i, oj = c->opt.pixel_j;
    if (oi >= 0 && oj >= 0) {
        if ((size_t)oi >= c->nx || (size_t)oj >= c->ny)
            return swfs_fail(SWFS_ERR_ARG, "report: pixel (%ld, %ld) is outside the %zux%zu focal grid", oi, oj, c->nx,
                             c->ny);
        c->ref_i = oi;
        c->ref_j = oj;
        return SWFS_OK;
    }
    size_t n = c->nx * c->ny;
    double *score = malloc(n * sizeof *score);
    unsigned char *ok = rep_mask_from(c->valid, n);
    int rc = SWFS_OK;
    if (!score || (c->valid && !ok)) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "report: out of memory");
    } else {
        for (size_t k = 0; k < n; k++)
            score[k] = c->snr ? c->snr->data[k] : c->halo ? cabs(c->halo->data[k]) : c->mean_sp ? c->mean_sp->data[k] : NAN;
        rep_best_pixel(c, score, ok, REP_RING1_MIN, REP_RING1_MAX, &c->ref_i, &c->ref_j);
    }
    free(score);
    free(ok);
    return rc;
}

int rep_run_folder(rep_ctx *c)
{
    int rc = load_focal(c);
    if (!rc) rc = choose_ref_pixel(c);
    if (!rc && swfs_plot_available()) {
        if (!(rc = rep_fig_halo(c)) && !(rc = rep_fig_focal(c))) rc = rep_fig_pixel(c);
    }
    /* Pupil and coherence give key numbers even where nothing can be drawn. */
    if (!rc) rc = rep_fig_pupil(c);
    if (!rc) rc = rep_fig_coherence(c);
    if (!rc) rc = rep_fig_registration(c);
    if (rc) return rc;
    if (!c->has[P_SCIENCE] || !c->has[P_SPECKLES])
        rep_note(c, "science.fits and speckles.fits needed for the intensity-against-phase figure");
    if (!c->has[P_WAVEFRONT]) rep_note(c, "wavefront.fits not found: pupil figure skipped (run 'specklewfs pupil')");
    if (!c->has[P_COHERENCE] && !c->in_demo)
        rep_note(c, "coherence.fits not found: coherence figure skipped (run 'specklewfs coherence')");
    return SWFS_OK;
}

/* ---- entry point ------------------------------------------------------- */

static int report_folder(const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                         swfs_report_summary *s)
{
    rep_ctx c;
    rep_strbuf body = {0};
    int rc = rep_ctx_init(&c, run_dir, out_dir, opt, s, s);
    if (!rc && !rep_ctx_reportable(&c))
        rc = swfs_fail(SWFS_ERR_IO,
                       "%s: nothing to report: none of science.fits, speckles.fits, halo.fits, wavefront.fits or "
                       "coherence.fits (a run folder), nor recovery.tsv or sigma<level>/ folders (a demo folder)",
                       run_dir);
    if (!rc) rc = rep_make_dirs(c.out_dir);
    if (!rc && !swfs_plot_available()) rep_note(&c, "no figures: this build has no PLplot pngcairo device");
    if (!rc) rc = rep_run_folder(&c);
    if (!rc) {
        char title[REP_PATHMAX + 64];
        if (opt->title) snprintf(title, sizeof title, "%s", opt->title);
        else snprintf(title, sizeof title, "specklewfs report: %s", run_dir);
        rep_printf(&body, "<h2>Key numbers</h2>\n");
        rep_key_numbers(&body, s, "");
        rep_notes(&body, s);
        if (c.figs.len) rep_printf(&body, "%s", c.figs.s);
        else rep_printf(&body, "<p>No figures: the run folder holds no products to draw.</p>\n");
        rc = rep_write_page(c.out_dir, title, run_dir, &body, s);
    }
    free(body.s);
    rep_ctx_free(&c);
    return rc;
}

/* The report's files checked before any work (outpaths.h), as every command's: an output
 * folder that exists must be a folder, and the page must not be a special file, a link or
 * one of the run's own files. The figures' names are the page's siblings and go through
 * the same atomic writer. */
static int check_paths(const char *run_dir, const char *out)
{
    struct stat sb;
    if (lstat(out, &sb) == 0 && !S_ISDIR(sb.st_mode))
        return swfs_fail(SWFS_ERR_IO, "%s: the report's output exists and is not a folder (a file, a link or a special "
                         "file); give a folder", out);
    if (!rep_dir_exists(out)) return SWFS_OK; /* created when the first figure is written */
    char page[REP_PATHMAX];
    int rc = rep_join(page, out, "index.html");
    swfs_paths *p = NULL;
    if (!rc) rc = swfs_paths_create(&p);
    if (!rc) swfs_paths_input_or_dir(p, "run folder", run_dir);
    if (!rc) rc = swfs_paths_output(p, "report page", page);
    swfs_paths_free(p);
    return rc;
}

int swfs_report_run(const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                    swfs_report_summary *summary)
{
    if (!run_dir || !*run_dir) return swfs_fail(SWFS_ERR_ARG, "report: no run folder given");
    if (!rep_dir_exists(run_dir)) return swfs_fail(SWFS_ERR_IO, "%s: not a folder", run_dir);
    swfs_report_summary *local = NULL;
    if (!summary && !(summary = local = malloc(sizeof *local))) return swfs_fail(SWFS_ERR_NOMEM, "report: out of memory");
    rep_summary_init(summary);
    swfs_report_options o;
    if (opt) o = *opt;
    else swfs_report_options_default(&o);
    int rc = SWFS_OK;
    char out[REP_PATHMAX];
    if (!(o.pct_lo >= 0 && o.pct_hi <= 100 && o.pct_lo < o.pct_hi))
        rc = swfs_fail(SWFS_ERR_ARG, "report: percentiles must satisfy 0 <= lo < hi <= 100, got %g, %g", o.pct_lo,
                       o.pct_hi);
    else if (!(o.log_decades > 0))
        rc = swfs_fail(SWFS_ERR_ARG, "report: log_decades must be positive");
    else if (out_dir && strlen(out_dir) >= sizeof out)
        rc = swfs_fail(SWFS_ERR_ARG, "report: output path too long");
    else if (out_dir)
        snprintf(out, sizeof out, "%s", out_dir);
    else
        rc = rep_join(out, run_dir, "report");
    if (!rc) rc = check_paths(run_dir, out);
    if (!rc) rc = rep_is_demo(run_dir) ? rep_demo_run(run_dir, out, &o, summary) : report_folder(run_dir, out, &o, summary);
    free(local);
    return rc;
}

/* pixel.png: one pixel's science intensity against the speckle phase computed from the
 * WFS, with a least-squares sinusoid, the model and arg Psi (fig:MMT-example-data). */
#include "report_internal.h"

#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

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

/* The time series of pixel pk: intensity iv and speckle phase ph (nz frames, the shorter
 * cube's), and the mean speckle amplitude <|psi|>. */
typedef struct series {
    double *iv, *ph;
    size_t nz;
    double mean_abs;
} series;

static int read_series(rep_ctx *c, size_t pk, series *t)
{
    swfs_fits_in *fs = NULL, *fp = NULL;
    double *buf = NULL;
    double complex *cbuf = NULL;
    const char *psci = c->path[P_SCIENCE], *pspk = c->path[P_SPECKLES];
    int rc = swfs_fits_in_open(&fs, psci, NULL);
    if (!rc) rc = swfs_fits_in_open(&fp, pspk, NULL);
    if (rc) goto done;
    const swfs_fits_shape *ss = swfs_fits_in_shape(fs), *sp = swfs_fits_in_shape(fp);
    if (ss->is_complex || !sp->is_complex) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s / %s: expected a real science cube and a complex speckle cube", psci, pspk);
        goto done;
    }
    if ((rc = rep_check_focal_shape(c, psci, ss->nx, ss->ny)) || (rc = rep_check_focal_shape(c, pspk, sp->nx, sp->ny)))
        goto done;
    size_t nz = ss->nz < sp->nz ? ss->nz : sp->nz;
    if (ss->nz != sp->nz)
        rep_note(c, "pixel.png uses the first %zu frames: science.fits has %zu, speckles.fits %zu", nz, ss->nz, sp->nz);
    const size_t npix = c->nx * c->ny, chunk = 64;
    t->iv = malloc((nz ? nz : 1) * sizeof *t->iv);
    t->ph = malloc((nz ? nz : 1) * sizeof *t->ph);
    buf = malloc(npix * chunk * sizeof *buf);
    cbuf = malloc(npix * chunk * sizeof *cbuf);
    if (!t->iv || !t->ph || !buf || !cbuf) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "pixel figure: out of memory");
        goto done;
    }
    double sum_abs = 0.0;
    for (size_t k0 = 0; k0 < nz && !rc; k0 += chunk) {
        size_t m = nz - k0 < chunk ? nz - k0 : chunk;
        if ((rc = swfs_fits_in_read_real(fs, k0, m, buf)) || (rc = swfs_fits_in_read_cplx(fp, k0, m, cbuf))) break;
        for (size_t k = 0; k < m; k++) {
            t->iv[k0 + k] = buf[k * npix + pk];
            t->ph[k0 + k] = carg(cbuf[k * npix + pk]);
            sum_abs += cabs(cbuf[k * npix + pk]);
        }
    }
    t->nz = nz;
    t->mean_abs = sum_abs / (double)nz;
done:
    swfs_fits_in_close(fs);
    swfs_fits_in_close(fp);
    free(buf);
    free(cbuf);
    return rc;
}

enum { NCURVE = 361 };

/* The page: the frames, the fitted sinusoid coef, the model (when the halo and g are
 * known) and the halo phase. */
static int draw(rep_ctx *c, const char *path, long pi, long pj, const series *t, const double coef[3])
{
    const size_t pk = (size_t)pj * c->nx + (size_t)pi, nz = t->nz;
    const double *iv = t->iv;
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
    double xs[NCURVE], ys[NCURVE], ym[NCURVE];
    for (int k = 0; k < NCURVE; k++) {
        xs[k] = -M_PI + 2.0 * M_PI * k / (NCURVE - 1);
        ys[k] = coef[0] + coef[1] * cos(xs[k]) + coef[2] * sin(xs[k]);
        ym[k] = mean + 2.0 * g * habs * t->mean_abs * cos(xs[k] - halo_phase);
    }
    swfs_plot *p = NULL;
    int rc = swfs_plot_create(&p, path, REP_W_PIXEL, REP_H_PIXEL, 1, 1);
    if (rc) return rc;
    char title[200];
    if (rep_have_pixscale(c))
        snprintf(title, sizeof title, "pixel (%ld, %ld) at θ = (%.2f, %.2f) λ/D, %zu frames", pi, pj,
                 rep_focal_x(c, (double)pi, c->nx), rep_focal_x(c, (double)pj, c->ny), nz);
    else
        snprintf(title, sizeof title, "pixel (%ld, %ld), %zu frames", pi, pj, nz);
    swfs_plot_axes_spec a = {title, "speckle phase arg ψ [rad]", "science intensity I [counts]", -M_PI, M_PI,
                             imin - pad, imax + 3.5 * pad, 0};
    swfs_plot_legend_entry e[4];
    size_t ne = 0;
    e[ne++] = (swfs_plot_legend_entry){"frames", SWFS_COLOR_BLUE, 1, SWFS_LINE_SOLID};
    e[ne++] = (swfs_plot_legend_entry){"least-squares sinusoid", SWFS_COLOR_BLACK, 0, SWFS_LINE_SOLID};
    if (!rc) rc = swfs_plot_panel(p, 0);
    if (!rc) rc = swfs_plot_axes(p, &a);
    if (!rc) rc = swfs_plot_points(p, t->ph, iv, nz, SWFS_COLOR_BLUE, 0.7);
    if (!rc) rc = swfs_plot_line(p, xs, ys, NCURVE, SWFS_COLOR_BLACK, SWFS_LINE_SOLID, 2.5);
    if (!rc && have_model && isfinite(g) && isfinite(habs)) {
        rc = swfs_plot_line(p, xs, ym, NCURVE, SWFS_COLOR_ORANGE, SWFS_LINE_DASHED, 2.5);
        e[ne++] = (swfs_plot_legend_entry){"model ⟨I⟩ + 2g|Ψ|⟨|ψ|⟩ cos(φ − arg Ψ)", SWFS_COLOR_ORANGE, 0,
                                           SWFS_LINE_DASHED};
    }
    if (!rc && isfinite(halo_phase)) {
        double vx[2] = {halo_phase, halo_phase}, vy[2] = {imin - pad, imax + 3.5 * pad};
        rc = swfs_plot_line(p, vx, vy, 2, SWFS_COLOR_RED, SWFS_LINE_DASHED, 2.0);
        e[ne++] = (swfs_plot_legend_entry){"arg Ψ (estimated halo phase)", SWFS_COLOR_RED, 0, SWFS_LINE_DASHED};
    }
    if (!rc) rc = swfs_plot_legend(p, e, ne);
    if (rc) {
        swfs_plot_abort(p);
        return rc;
    }
    return swfs_plot_commit(p);
}

/* pixel.png: one pixel's intensity against the speckle phase (fig:MMT-example-data). */
int rep_fig_pixel(rep_ctx *c)
{
    if (!c->has[P_SCIENCE] || !c->has[P_SPECKLES]) return SWFS_OK;
    long pi = c->opt.pixel_i, pj = c->opt.pixel_j;
    if (pi < 0 || pj < 0) pi = c->ref_i, pj = c->ref_j;
    if (pi < 0 || pj < 0) {
        rep_note(c, "pixel.png skipped: no pixel with a measurable halo in the first Airy ring");
        return SWFS_OK;
    }
    if ((size_t)pi >= c->nx || (size_t)pj >= c->ny)
        return swfs_fail(SWFS_ERR_ARG, "report: pixel (%ld, %ld) is outside the %zux%zu focal grid", pi, pj, c->nx,
                         c->ny);
    series t = {0};
    char path[REP_PATHMAX];
    const size_t pk = (size_t)pj * c->nx + (size_t)pi;
    int rc = rep_join(path, c->out_dir, "pixel.png");
    if (!rc) rc = read_series(c, pk, &t);
    if (!rc && t.nz < 3) rep_note(c, "pixel.png skipped: fewer than 3 frames");
    if (rc || t.nz < 3) goto done;
    double coef[3];
    fit_sinusoid(t.ph, t.iv, t.nz, coef);
    if ((rc = draw(c, path, pi, pj, &t, coef))) goto done;
    double fit_phase = atan2(coef[2], coef[1]), fit_amp = hypot(coef[1], coef[2]);
    double halo_phase = c->halo ? carg(c->halo->data[pk]) : NAN;
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
    rep_add_figure(c, "pixel.png", REP_W_PIXEL, REP_H_PIXEL, "Intensity against speckle phase", cap);
done:
    free(t.iv);
    free(t.ph);
    return rc;
}

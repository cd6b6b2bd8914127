/* coherence.png: tau0, phase-rotation time and SNR-factor maps and Gamma(tau)/Gamma(0) of
 * one pixel in the complex plane (fig:Halo-tau0, fig:Speckles-MCF-4panel1). */
#include "report_internal.h"

#include "specklewfs/fits.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct coh_maps {
    swfs_real *tau0, *trot, *sf, *msp, *lags;
    swfs_cplx *mcf;
} coh_maps;

static void maps_free(coh_maps *m)
{
    swfs_real_free(m->tau0);
    swfs_real_free(m->trot);
    swfs_real_free(m->sf);
    swfs_real_free(m->msp);
    swfs_real_free(m->lags);
    swfs_cplx_free(m->mcf);
}

static int load(rep_ctx *c, coh_maps *m)
{
    const char *path = c->path[P_COHERENCE];
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = rep_read_real_opt(f, "TAU0", &m->tau0);
    if (!rc) rc = rep_read_real_opt(f, "TROT", &m->trot);
    if (!rc) rc = rep_read_real_opt(f, "SNR_FACT", &m->sf);
    if (!rc) rc = rep_read_real_opt(f, "MEAN_SP", &m->msp);
    if (!rc) rc = rep_read_real_opt(f, "LAGS", &m->lags);
    if (!rc && swfs_fits_in_has_ext(f, "MCF")) {
        rc = swfs_fits_in_move(f, "MCF");
        if (!rc) rc = swfs_fits_in_read_cplx_all(f, &m->mcf);
    }
    if (!rc && c->nx == 0) {
        swfs_geom g;
        if (!(rc = swfs_fits_in_geom(f, &g))) c->geom = g;
    }
    swfs_fits_in_close(f);
    const swfs_real *maps[3] = {m->tau0, m->trot, m->sf};
    for (int k = 0; k < 3 && !rc; k++)
        if (maps[k]) rc = rep_check_focal_shape(c, path, maps[k]->nx, maps[k]->ny);
    if (!rc && m->mcf) rc = rep_check_focal_shape(c, path, m->mcf->nx, m->mcf->ny);
    if (!rc && m->tau0) c->sum->tau0_median = swfs_report_percentile(m->tau0->data, c->nx * c->ny, NULL, 50.0);
    return rc;
}

/* The map panels from `panel` on; *next receives the next free panel. */
static int map_panels(rep_ctx *c, const coh_maps *m, swfs_plot *p, double *z, int panel, int *next)
{
    static const double circles[] = {1, 2, 3, 4, 5, 6};
    const size_t n = c->nx * c->ny;
    swfs_plot_image_spec s;
    rep_focal_spec(c, &s);
    swfs_report_range r;
    int rc = SWFS_OK;
    if (m->tau0) {
        r = rep_prepare(c, "tau0", m->tau0->data, n, NULL, R_AUTO, 1e3, 0, 0, z);
        rc = rep_image_panel(p, panel++, &s, &r, "coherence time τ₀ (|Γ(τ)/Γ(0)| = e#u-1/2#d)", "τ₀ [ms]",
                             SWFS_CMAP_VIRIDIS, z, c->nx, c->ny);
        if (!rc && rep_have_pixscale(c))
            rc = swfs_plot_circles(p, 0, 0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (!rc && m->trot) {
        r = rep_prepare(c, "trot", m->trot->data, n, NULL, R_AUTO, 1e3, 0, 0, z);
        rc = rep_image_panel(p, panel++, &s, &r, "phase-rotation time (±π/2)", "time [ms]", SWFS_CMAP_VIRIDIS, z,
                             c->nx, c->ny);
        if (!rc && rep_have_pixscale(c))
            rc = swfs_plot_circles(p, 0, 0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (!rc && m->sf) {
        r = rep_prepare(c, "snr_fact", m->sf->data, n, NULL, R_AUTO, 1.0, 0, 0, z);
        rc = rep_image_panel(p, panel++, &s, &r, "SNR factor of the exposure time", "SNR / ideal short-exposure SNR",
                             SWFS_CMAP_GRAY, z, c->nx, c->ny);
    }
    *next = panel;
    return rc;
}

/* Gamma(tau)/Gamma(0) of the --pixel, else of the second-ring pixel with the most speckle
 * power (the paper shows one in the second Airy ring), in the complex plane. */
static int mcf_panel(rep_ctx *c, const coh_maps *m, swfs_plot *p, double *z, int panel)
{
    const size_t n = c->nx * c->ny, nl = m->mcf->nz;
    long bi = c->opt.pixel_i, bj = c->opt.pixel_j;
    if (bi < 0 || bj < 0 || (size_t)bi >= c->nx || (size_t)bj >= c->ny) {
        for (size_t k = 0; k < n; k++) z[k] = m->msp ? m->msp->data[k] : cabs(m->mcf->data[k]);
        if (!rep_best_pixel(c, z, NULL, REP_RING2_MIN, REP_RING2_MAX, &bi, &bj))
            rep_best_pixel(c, z, NULL, 0, 1e9, &bi, &bj);
    }
    double *gx = malloc((nl + 1) * sizeof *gx), *gy = malloc((nl + 1) * sizeof *gy);
    int rc = gx && gy ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "coherence figure: out of memory");
    size_t pk = (size_t)bj * c->nx + (size_t)bi, ng = 0;
    double complex g0 = m->mcf->data[pk];
    for (size_t l = 0; !rc && l < nl && cabs(g0) > 0; l++) {
        double complex gl = m->mcf->data[l * n + pk] / g0;
        if (!isfinite(creal(gl)) || !isfinite(cimag(gl))) continue;
        gx[ng] = creal(gl);
        gy[ng] = cimag(gl);
        ng++;
    }
    char title[160];
    if (rep_have_pixscale(c))
        snprintf(title, sizeof title, "Γ(τ)/Γ(0) at pixel (%ld, %ld), |θ| = %.2f λ/D", bi, bj,
                 hypot(rep_focal_x(c, (double)bi, c->nx), rep_focal_x(c, (double)bj, c->ny)));
    else
        snprintf(title, sizeof title, "Γ(τ)/Γ(0) at pixel (%ld, %ld)", bi, bj);
    swfs_plot_axes_spec a = {title, "Re Γ(τ)/Γ(0)", "Im Γ(τ)/Γ(0)", -1.1, 1.1, -1.1, 1.1, 1};
    double one = 1.0, e12 = exp(-0.5);
    if (!rc) rc = swfs_plot_panel(p, panel);
    if (!rc) rc = swfs_plot_axes(p, &a);
    if (!rc) rc = swfs_plot_circles(p, 0, 0, &one, 1, SWFS_COLOR_GRAY, SWFS_LINE_DOTTED, 1.0);
    if (!rc) rc = swfs_plot_circles(p, 0, 0, &e12, 1, SWFS_COLOR_RED, SWFS_LINE_DASHED, 2.0);
    if (!rc) rc = swfs_plot_line(p, gx, gy, ng, SWFS_COLOR_BLUE, SWFS_LINE_SOLID, 1.5);
    if (!rc) rc = swfs_plot_points(p, gx, gy, ng, SWFS_COLOR_BLUE, 1.0);
    if (!rc && ng > 0) {
        char lab[64];
        const swfs_real *lags = m->lags;
        double tl = lags && lags->nx * lags->ny * lags->nz >= nl ? lags->data[nl - 1] : NAN;
        if (isfinite(tl)) snprintf(lab, sizeof lab, "τ = %.0f ms", 1e3 * tl);
        else snprintf(lab, sizeof lab, "lag %zu", nl - 1);
        rc = swfs_plot_text(p, gx[ng - 1], gy[ng - 1] - 0.12, 0.5, SWFS_COLOR_BLUE, lab);
    }
    swfs_plot_legend_entry e[2] = {{"Γ(τ)/Γ(0)", SWFS_COLOR_BLUE, 0, SWFS_LINE_SOLID},
                                   {"radius e#u-1/2#d (defines τ₀)", SWFS_COLOR_RED, 0, SWFS_LINE_DASHED}};
    if (!rc) rc = swfs_plot_legend(p, e, 2);
    free(gx);
    free(gy);
    return rc;
}

int rep_fig_coherence(rep_ctx *c)
{
    if (!c->has[P_COHERENCE]) return SWFS_OK;
    coh_maps m;
    memset(&m, 0, sizeof m);
    double *z = NULL;
    swfs_plot *p = NULL;
    char path[REP_PATHMAX];
    int rc = rep_join(path, c->out_dir, "coherence.png");
    if (!rc) rc = load(c, &m);
    if (rc || !swfs_plot_available()) goto done;
    if (!m.tau0 && !m.trot && !m.sf && !m.mcf) {
        rep_note(c, "coherence.png skipped: coherence.fits has none of TAU0, TROT, SNR_FACT, MCF");
        goto done;
    }
    if (!(z = malloc(c->nx * c->ny * sizeof *z))) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "coherence figure: out of memory");
        goto done;
    }
    int npanel = (m.tau0 != NULL) + (m.trot != NULL) + (m.sf != NULL) + (m.mcf != NULL);
    int rows = npanel > 2 ? 2 : 1, cols = npanel > 1 ? 2 : 1, h = rows == 2 ? REP_H_GRID : REP_H_ROW2;
    int w = cols == 2 ? REP_W_GRID : REP_W_PIXEL, panel = 0;
    if ((rc = swfs_plot_create(&p, path, w, h, cols, rows)) || (rc = map_panels(c, &m, p, z, 0, &panel))) goto done;
    if (m.mcf && (rc = mcf_panel(c, &m, p, z, panel))) goto done;
    rc = rep_commit(c, &p, "coherence.png", w, h, "Speckle coherence",
                    "Speckle coherence time τ₀ where |Γ(τ)/Γ(0)| falls to e^-1/2, the time for the speckle phase "
                    "to rotate by ±π/2 (dashed circles at 1-6 λ/D), the SNR factor of the science exposure time, "
                    "and the normalized mutual coherence function Γ(τ)/Γ(0) of one second-ring pixel in the "
                    "complex plane with the e^-1/2 circle.");
done:
    swfs_plot_abort(p);
    maps_free(&m);
    free(z);
    return rc;
}

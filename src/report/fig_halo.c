/* The estimate's focal-plane maps: halo.png (log10 |Psi|, arg Psi, visibility;
 * fig:Sim-PSI-Vis) and focal.png (g, Phi_I, sigma_I^2, Phi_sp; fig:Gain-map,
 * fig:Sim-PSF-Sigma2, fig:Sim-SpeckleHaloMeanPower). */
#include "report_internal.h"

#include "specklewfs/status.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

/* halo.png: log10 |Psi| normalized to the reference pixel, arg Psi, visibility. */
int rep_fig_halo(rep_ctx *c)
{
    if (!c->halo) return SWFS_OK;
    size_t n = c->nx * c->ny;
    double *amp = calloc(n, sizeof *amp), *z = calloc(n, sizeof *z);
    unsigned char *vmask = rep_mask_from(c->valid, n);
    swfs_plot *p = NULL;
    char path[REP_PATHMAX];
    int rc = rep_join(path, c->out_dir, "halo.png");
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
    if ((rc = swfs_plot_create(&p, path, npanel == 3 ? REP_W_HALO : REP_W_ROW2, REP_H_HALO, npanel, 1))) goto done;
    swfs_plot_image_spec s;
    rep_focal_spec(c, &s);

    swfs_report_range r = rep_prepare(c, "halo_amp", amp, n, NULL, R_LOG, 1.0, 0, 0, z);
    if ((rc = rep_image_panel(p, 0, &s, &r, "static halo: log₁₀ |Ψ|",
                          c->ref_i >= 0 ? "|Ψ| / |Ψ| at the first-ring pixel" : "|Ψ| / max |Ψ|", SWFS_CMAP_MAGMA, z,
                          c->nx, c->ny)))
        goto done;
    if (c->ref_i >= 0) {
        double x = rep_focal_x(c, (double)c->ref_i, c->nx), y = rep_focal_x(c, (double)c->ref_j, c->ny);
        double rr = rep_have_pixscale(c) ? 0.6 : 1.5;
        if ((rc = swfs_plot_circles(p, x, y, &rr, 1, SWFS_COLOR_GREEN, SWFS_LINE_SOLID, 2.0))) goto done;
    }

    for (size_t k = 0; k < n; k++) amp[k] = carg(c->halo->data[k]);
    r = rep_prepare(c, "halo_phase", amp, n, vmask, R_FIXED, 1.0, -M_PI, M_PI, z);
    if ((rc = rep_image_panel(p, 1, &s, &r, vmask ? "static halo: arg Ψ (valid pixels)" : "static halo: arg Ψ",
                          "phase [rad]", SWFS_CMAP_PHASE, z, c->nx, c->ny)))
        goto done;

    if (c->visib) {
        r = rep_prepare(c, "visib", c->visib->data, n, NULL, R_FIXED, 1.0, 0.0, 1.0, z);
        if ((rc = rep_image_panel(p, 2, &s, &r, "visibility (lighter is better)", "visibility", SWFS_CMAP_GRAY, z, c->nx,
                              c->ny)))
            goto done;
    }
    rc = rep_commit(c, &p, "halo.png", npanel == 3 ? REP_W_HALO : REP_W_ROW2, REP_H_HALO, "Static halo",
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
int rep_fig_focal(rep_ctx *c)
{
    const swfs_real *maps[4] = {c->gain, c->mean_i, c->var_i, c->mean_sp};
    int count = 0;
    for (int k = 0; k < 4; k++) count += maps[k] != NULL;
    if (!count) return SWFS_OK;
    size_t n = c->nx * c->ny;
    double *z = malloc(n * sizeof *z);
    unsigned char *vmask = rep_mask_from(c->valid, n);
    swfs_plot *p = NULL;
    char path[REP_PATHMAX];
    int rc = rep_join(path, c->out_dir, "focal.png");
    if (!rc && (!z || (c->valid && !vmask))) rc = swfs_fail(SWFS_ERR_NOMEM, "focal figure: out of memory");
    if (rc) goto done;
    int rows = count > 2 ? 2 : 1, h = rows == 2 ? REP_H_GRID : REP_H_ROW2;
    if ((rc = swfs_plot_create(&p, path, REP_W_GRID, h, 2, rows))) goto done;
    swfs_plot_image_spec s;
    rep_focal_spec(c, &s);
    static const double circles[] = {1, 2, 3, 4, 5, 6};
    const char *cnt = c->moments_from_cubes ? " (from the cube, noise included)" : "";
    char t_mean[96], t_var[96];
    snprintf(t_mean, sizeof t_mean, "mean science image Φ#dI#u%s", c->moments_from_cubes ? " (from the cube)" : "");
    snprintf(t_var, sizeof t_var, "science variance σ#u2#d#dI#u%s", cnt);
    /* g on valid pixels (fig:Gain-map), Phi_I, sigma_I^2 on exactly 4 decades
     * (fig:Sim-PSF-Sigma2), Phi_sp. */
    const struct {
        const char *name, *title, *zlabel;
        enum rep_range_kind kind;
        swfs_cmap cmap;
    } panels[4] = {
        {"gain", "scale factor g (circles: 1-6 λ/D)", "g", R_AUTO, SWFS_CMAP_VIRIDIS},
        {"mean_i", t_mean, "mean intensity [counts]", R_AUTO, SWFS_CMAP_MAGMA},
        {"var_i", t_var, "variance [counts²]", R_LOG_FIXED, SWFS_CMAP_MAGMA},
        {"mean_sp", "mean speckle power Φ#dsp#u", "⟨|ψ|²⟩ [counts]", R_AUTO, SWFS_CMAP_MAGMA},
    };
    int panel = 0;
    for (int k = 0; k < 4 && !rc; k++) {
        if (!maps[k]) continue;
        swfs_report_range r = rep_prepare(c, panels[k].name, maps[k]->data, n, k == 0 ? vmask : NULL, panels[k].kind,
                                          1.0, 0, 0, z);
        rc = rep_image_panel(p, panel++, &s, &r, panels[k].title, panels[k].zlabel, panels[k].cmap, z, c->nx, c->ny);
        if (!rc && k == 0 && rep_have_pixscale(c))
            rc = swfs_plot_circles(p, 0.0, 0.0, circles, 6, SWFS_COLOR_WHITE, SWFS_LINE_DASHED, 1.0);
    }
    if (!rc)
        rc = rep_commit(c, &p, "focal.png", REP_W_GRID, h, "Focal-plane statistics",
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


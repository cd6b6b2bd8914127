/* pupil.png and the wavefront key numbers: pupil amplitude and WFE [nm] with the pupil
 * outline; for simulations the true NCP and the error map (fig:Sim-NCP, fig:Sim-PField).
 * The recovery error is the diag metric swfs_wfe_compare (piston and tip/tilt removed),
 * the number `specklewfs demo` and `pupil --truth` print. */
#include "report_internal.h"

#include "specklewfs/fits.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct pupil_maps {
    swfs_real *amp, *wfe, *pup, *ncp; /* AMPLITUDE, WFE, the pupil mask, the true NCP (any but wfe may be NULL) */
    swfs_real *resm;                  /* RESMEAN: the AO residual's time mean taken out of WFE (may be NULL) */
    double resm_rms;                  /* RESMRMS [m] */
    swfs_geom g;                      /* of wavefront.fits */
    double key_rms, key_pv, key_strehl;
    size_t nx, ny, n;
    double *w;       /* 1 inside the pupil where the maps are finite, else 0 (the metrics' weights) */
    unsigned char *mask;
    double *outline; /* the pupil mask as a map for the contour */
    double *wfe0;    /* WFE, piston removed inside the pupil */
    double *ncp0;    /* NCP, piston removed inside the pupil */
    double *err;     /* WFE - NCP, piston and tip/tilt removed */
} pupil_maps;

static void maps_free(pupil_maps *m)
{
    swfs_real_free(m->amp);
    swfs_real_free(m->wfe);
    swfs_real_free(m->pup);
    swfs_real_free(m->ncp);
    swfs_real_free(m->resm);
    free(m->w);
    free(m->mask);
    free(m->outline);
    free(m->wfe0);
    free(m->ncp0);
    free(m->err);
}

/* The truth's NCP when truth.fits has one on the WFE's grid (a note otherwise). */
static int load_truth(rep_ctx *c, pupil_maps *m)
{
    if (!c->has[P_TRUTH]) return SWFS_OK;
    swfs_fits_in *t = NULL;
    int rc = swfs_fits_in_open(&t, c->path[P_TRUTH], NULL);
    if (!rc) rc = rep_read_real_opt(t, "NCP", &m->ncp);
    swfs_fits_in_close(t);
    if (rc) return rc;
    if (!m->ncp) {
        rep_note(c, "truth.fits has no NCP extension: no error map");
    } else if (m->ncp->nx != m->nx || m->ncp->ny != m->ny) {
        rep_note(c, "truth NCP is %zux%zu but WFE is %zux%zu: no error map", m->ncp->nx, m->ncp->ny, m->nx, m->ny);
        swfs_real_free(m->ncp);
        m->ncp = NULL;
    }
    return SWFS_OK;
}

/* wavefront.fits (AMPLITUDE, WFE, PUPIL, WFERMS/WFEPV/STREHL), the pupil mask (its own
 * extension, else pupil.fits) and the truth. *drawable = 0 when there is no WFE. */
static int load(rep_ctx *c, pupil_maps *m, int *drawable)
{
    swfs_fits_in *f = NULL;
    const char *path = c->path[P_WAVEFRONT];
    double v;
    int found;
    *drawable = 0;
    m->key_rms = m->key_pv = m->key_strehl = NAN;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = rep_read_real_opt(f, "AMPLITUDE", &m->amp);
    if (!rc) rc = rep_read_real_opt(f, "WFE", &m->wfe);
    if (!rc) rc = rep_read_real_opt(f, "PUPIL", &m->pup);
    if (!rc) rc = rep_read_real_opt(f, "RESMEAN", &m->resm);
    m->resm_rms = NAN;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "RESMRMS", &v, &found)) && found) m->resm_rms = v;
    if (!rc) rc = swfs_fits_in_geom(f, &m->g);
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "WFERMS", &v, &found)) && found) m->key_rms = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "WFEPV", &v, &found)) && found) m->key_pv = v;
    if (!rc && !(rc = swfs_fits_in_key_double_opt(f, "STREHL", &v, &found)) && found) m->key_strehl = v;
    swfs_fits_in_close(f);
    if (rc) return rc;
    if (!m->wfe) {
        rep_note(c, "pupil.png skipped: wavefront.fits has no WFE extension");
        return SWFS_OK;
    }
    m->nx = m->wfe->nx, m->ny = m->wfe->ny, m->n = m->nx * m->ny;
    if (m->nx != m->ny)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: WFE is %zux%zu, expected a square pupil grid", path, m->nx, m->ny);
    if (m->amp && (m->amp->nx != m->nx || m->amp->ny != m->ny))
        return swfs_fail(SWFS_ERR_SHAPE, "%s: AMPLITUDE is %zux%zu but WFE is %zux%zu", path, m->amp->nx, m->amp->ny,
                         m->nx, m->ny);
    if (m->resm && (m->resm->nx != m->nx || m->resm->ny != m->ny)) {
        rep_note(c, "RESMEAN is %zux%zu but WFE is %zux%zu: not drawn", m->resm->nx, m->resm->ny, m->nx, m->ny);
        swfs_real_free(m->resm);
        m->resm = NULL;
    }
    if (!m->pup && c->has[P_PUPIL] && (rc = swfs_fits_read_real(c->path[P_PUPIL], NULL, &m->pup, NULL))) return rc;
    if (m->pup && (m->pup->nx != m->nx || m->pup->ny != m->ny)) {
        rep_note(c, "pupil mask is %zux%zu but WFE is %zux%zu: drawn without the pupil outline", m->pup->nx,
                 m->pup->ny, m->nx, m->ny);
        swfs_real_free(m->pup);
        m->pup = NULL;
    }
    if ((rc = load_truth(c, m))) return rc;
    *drawable = 1;
    return SWFS_OK;
}

/* Weighted mean of v over w. */
static double piston(const double *v, const double *w, size_t n)
{
    double s = 0.0, ws = 0.0;
    for (size_t k = 0; k < n; k++)
        if (w[k] > 0.0) s += w[k] * v[k], ws += w[k];
    return ws > 0.0 ? s / ws : 0.0;
}

/* The maps drawn and the key numbers: WFE rms (WFERMS, else piston removed) and PV,
 * Strehl (STREHL, else Marechal), and for simulations the true NCP rms and the error. */
static int derive(rep_ctx *c, pupil_maps *m)
{
    const size_t n = m->n, side = m->nx;
    const double *wfe = m->wfe->data, *ncp = m->ncp ? m->ncp->data : NULL;
    m->w = malloc(n * sizeof *m->w);
    m->mask = malloc(n);
    m->outline = malloc(n * sizeof *m->outline);
    m->wfe0 = malloc(n * sizeof *m->wfe0);
    m->ncp0 = ncp ? malloc(n * sizeof *m->ncp0) : NULL;
    m->err = ncp ? malloc(n * sizeof *m->err) : NULL;
    if (!m->w || !m->mask || !m->outline || !m->wfe0 || (ncp && (!m->ncp0 || !m->err)))
        return swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
    double mn = INFINITY, mx = -INFINITY;
    size_t cnt = 0;
    for (size_t k = 0; k < n; k++) {
        m->mask[k] = m->pup ? m->pup->data[k] > 0.5 : 1;
        m->outline[k] = m->mask[k];
        int ok = m->mask[k] && isfinite(wfe[k]) && (!ncp || isfinite(ncp[k]));
        m->w[k] = ok;
        if (ok) mn = fmin(mn, wfe[k]), mx = fmax(mx, wfe[k]), cnt++;
    }
    const double pw = piston(wfe, m->w, n);
    for (size_t k = 0; k < n; k++) m->wfe0[k] = wfe[k] - pw;
    double rms = NAN;
    if (cnt && swfs_wfe_compare(wfe, wfe, m->w, side, NULL, &rms, NULL))
        return swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
    swfs_report_summary *s = c->sum;
    s->wfe_rms = isfinite(m->key_rms) ? m->key_rms : rms;
    s->wfe_pv = isfinite(m->key_pv) ? m->key_pv : (cnt ? mx - mn : NAN);
    double lambda = isfinite(m->g.wavelen) ? m->g.wavelen : c->geom.wavelen;
    s->strehl = isfinite(m->key_strehl)      ? m->key_strehl
                : isfinite(lambda) && lambda > 0 ? exp(-pow(2.0 * M_PI * s->wfe_rms / lambda, 2.0))
                                                 : NAN;
    if (!ncp || !cnt) return SWFS_OK;
    /* The demo's number: estimate - truth with piston and tip/tilt removed. */
    if (swfs_wfe_compare(wfe, ncp, m->w, side, &s->err_rms, &s->ncp_rms, NULL))
        return swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
    const double pn = piston(ncp, m->w, n);
    for (size_t k = 0; k < n; k++) {
        m->ncp0[k] = ncp[k] - pn;
        m->err[k] = m->w[k] > 0.0 ? wfe[k] - ncp[k] : NAN;
    }
    swfs_wfe_remove_ptt(m->err, m->w, side); /* the map whose rms err_rms is */
    return SWFS_OK;
}

/* One wavefront panel [nm] on the shared range r, with the pupil outline. */
static int wave_panel(swfs_plot *p, int panel, swfs_plot_image_spec *s, const pupil_maps *m, const double *z)
{
    int rc = swfs_plot_panel(p, panel);
    if (!rc) rc = swfs_plot_image(p, z, m->nx, m->ny, s);
    if (!rc && m->pup) rc = swfs_plot_contour(p, m->outline, m->nx, m->ny, 0.5, SWFS_COLOR_BLACK, 1.5);
    return rc;
}

/* The panels: amplitude, WFE, and for simulations the true NCP and the error, the three
 * wavefronts on one symmetric range so that they compare by eye. */
static int draw(rep_ctx *c, const pupil_maps *m, swfs_plot *p, double *z)
{
    const size_t n = m->n, nx = m->nx, ny = m->ny;
    int havedx = isfinite(m->g.pupdx) && m->g.pupdx > 0;
    double dx = havedx ? m->g.pupdx : 1.0;
    swfs_plot_image_spec s;
    memset(&s, 0, sizeof s);
    s.xlabel = havedx ? "x [m]" : "x [pupil sample]";
    s.ylabel = havedx ? "y [m]" : "y [pupil sample]";
    s.x0 = -0.5 * (double)(nx - 1) * dx;
    s.x1 = 0.5 * (double)(nx - 1) * dx;
    s.y0 = -0.5 * (double)(ny - 1) * dx;
    s.y1 = 0.5 * (double)(ny - 1) * dx;
    s.mask = m->mask;
    int panel = 0, rc = SWFS_OK;
    swfs_report_range r;
    if (m->amp) {
        r = rep_prepare(c, "amplitude", m->amp->data, n, m->mask, R_AUTO, 1.0, 0, 0, z);
        rc = rep_image_panel(p, panel++, &s, &r, "pupil amplitude |A|", "amplitude [arbitrary units]", SWFS_CMAP_GRAY,
                             z, nx, ny);
        if (!rc && m->pup) rc = swfs_plot_contour(p, m->outline, nx, ny, 0.5, SWFS_COLOR_RED, 1.5);
        if (rc) return rc;
    }
    swfs_report_summary *top = c->top;
    if (m->ncp) { /* the NCP's range first, into z, then the WFE's; the larger one is used for all */
        const size_t k0 = top->nranges;
        swfs_report_range rt = rep_prepare(c, "ncp", m->ncp0, n, m->mask, R_SYM, 1e9, 0, 0, z);
        r = rep_prepare(c, "wfe", m->wfe0, n, m->mask, R_SYM, 1e9, 0, 0, z);
        if (rt.hi > r.hi) r.lo = rt.lo, r.hi = rt.hi;
        for (size_t k = k0; k < top->nranges; k++) top->ranges[k].lo = r.lo, top->ranges[k].hi = r.hi;
    } else {
        r = rep_prepare(c, "wfe", m->wfe0, n, m->mask, R_SYM, 1e9, 0, 0, z);
    }
    char t_wfe[160], t_ncp[160], t_err[200];
    snprintf(t_wfe, sizeof t_wfe, "estimated WFE: %.1f nm rms, %.0f nm PV", 1e9 * c->sum->wfe_rms, 1e9 * c->sum->wfe_pv);
    s.title = t_wfe;
    s.zlabel = "wavefront error [nm]";
    s.cmap = SWFS_CMAP_DIVERGING;
    rep_apply_range(&s, &r);
    if ((rc = wave_panel(p, panel++, &s, m, z))) return rc;
    if (m->resm) { /* on the WFE's scale: how much of the static aberration was the AO residual's */
        char t_res[200];
        snprintf(t_res, sizeof t_res, "AO residual's time mean taken out: %.1f nm rms", 1e9 * m->resm_rms);
        for (size_t k = 0; k < n; k++) z[k] = m->mask[k] && isfinite(m->resm->data[k]) ? 1e9 * m->resm->data[k] : NAN;
        s.title = t_res;
        if ((rc = wave_panel(p, panel++, &s, m, z))) return rc;
    }
    if (!m->ncp) return rc;
    snprintf(t_ncp, sizeof t_ncp, "true NCP (simulation): %.1f nm rms", 1e9 * c->sum->ncp_rms);
    snprintf(t_err, sizeof t_err, "error WFE − NCP (piston, tip/tilt removed): %.1f nm rms", 1e9 * c->sum->err_rms);
    for (size_t k = 0; k < n; k++) z[k] = m->mask[k] && isfinite(m->ncp0[k]) ? 1e9 * m->ncp0[k] : NAN;
    s.title = t_ncp;
    if ((rc = wave_panel(p, panel++, &s, m, z))) return rc;
    swfs_report_range re = rep_prepare(c, "err", m->err, n, m->mask, R_FIXED, 1e9, r.lo, r.hi, z);
    s.title = t_err;
    rep_apply_range(&s, &re);
    return wave_panel(p, panel++, &s, m, z);
}

int rep_fig_pupil(rep_ctx *c)
{
    if (!c->has[P_WAVEFRONT]) return SWFS_OK;
    pupil_maps m;
    memset(&m, 0, sizeof m);
    swfs_plot *p = NULL;
    double *z = NULL;
    char path[REP_PATHMAX];
    int drawable = 0;
    int rc = rep_join(path, c->out_dir, "pupil.png");
    if (!rc) rc = load(c, &m, &drawable);
    if (!rc && drawable) rc = derive(c, &m);
    if (rc || !drawable || !swfs_plot_available()) goto done;
    int npanel = (m.amp ? 1 : 0) + 1 + (m.resm ? 1 : 0) + (m.ncp ? 2 : 0);
    int rows = (npanel + 1) / 2, h = rows >= 2 ? REP_H_GRID * rows / 2 : REP_H_ROW2, cols = npanel > 1 ? 2 : 1;
    int w = cols == 2 ? REP_W_GRID : REP_W_PIXEL;
    if (!(z = malloc(m.n * sizeof *z))) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "pupil figure: out of memory");
        goto done;
    }
    if ((rc = swfs_plot_create(&p, path, w, h, cols, rows)) || (rc = draw(c, &m, p, z))) goto done;
    char cap[1200];
    snprintf(cap, sizeof cap, "%s%s",
             m.ncp ? "Pupil amplitude and the estimated wavefront error (eq:NCP-WFE-estimate) in nm with the pupil "
                     "outline; the true non-common-path aberration of the simulation (piston removed) and the error "
                     "map (estimate minus truth, piston and tip/tilt removed, as the demo's table), all on one colour "
                     "scale."
                   : "Pupil amplitude and the estimated wavefront error (eq:NCP-WFE-estimate) in nm, piston removed, "
                     "with the pupil outline.",
             m.resm ? " The AO residual's time mean that the telemetry measured, band-limited to the focal window, "
                      "was taken out of the wavefront (its panel, on the same scale)."
                    : "");
    rc = rep_commit(c, &p, "pupil.png", w, h, "Pupil field and wavefront", cap);
done:
    swfs_plot_abort(p);
    maps_free(&m);
    free(z);
    return rc;
}

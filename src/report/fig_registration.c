/* The linear model's registration check (docs/report.md): when speckles.fits was made with
 * --basis (its keys BASIS, COEFSCL and, for a DM grid, DMPITCH, DMOFFX, DMOFFY, DMROT,
 * DMFLIPX), the first basis functions as the pipeline sees them on the pupil grid, and the
 * DM grid's points and axes over the pupil outline: a wrong scale, offset, rotation or
 * mirror shows as modes cut by the pupil edge or grid axes pointing the wrong way. */
#include "report_internal.h"

#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/lmodel.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct reg_maps {
    char basis[REP_PATHMAX];
    swfs_dm_registration reg;
    swfs_real *cube;
    swfs_sparse *B;
    double *mask, *z;
    unsigned char *in;
    size_t np;
} reg_maps;

static void reg_free(reg_maps *m)
{
    swfs_real_free(m->cube);
    swfs_sparse_free(m->B);
    free(m->mask); free(m->z); free(m->in);
}

/* The keys of speckles.fits; *found = 0 when the speckles are not the linear model's. */
static int read_keys(rep_ctx *c, reg_maps *m, int *found)
{
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, c->path[P_SPECKLES], NULL), have = 0;
    if (!rc) rc = swfs_fits_in_key_string_opt(f, "BASIS", m->basis, sizeof m->basis, found);
    if (!rc && *found) rc = swfs_fits_in_key_double_opt(f, "DMPITCH", &m->reg.pitch, &have);
    if (!rc && have) {
        double rot = 0;
        long flip = 0;
        int h2 = 0;
        if (!(rc = swfs_fits_in_key_double_opt(f, "DMOFFX", &m->reg.x0, &h2)) &&
            !(rc = swfs_fits_in_key_double_opt(f, "DMOFFY", &m->reg.y0, &h2)) &&
            !(rc = swfs_fits_in_key_double_opt(f, "DMROT", &rot, &h2)))
            rc = swfs_fits_in_key_long_opt(f, "DMFLIPX", 0, 1, &flip, &h2);
        m->reg.rot = rot * M_PI / 180;
        m->reg.flip_x = (int)flip;
    }
    swfs_fits_in_close(f);
    return rc;
}

static int load(rep_ctx *c, reg_maps *m, int *drawable)
{
    *drawable = 0;
    int found = 0, rc = read_keys(c, m, &found);
    if (rc || !found) return rc;
    const swfs_geom *g = &c->geom;
    if (!(g->pupn > 1) || !(g->pupdx > 0) || !(g->teldiam > 0)) {
        rep_note(c, "speckles.fits records a linear model but no pupil geometry: registration figure skipped");
        return SWFS_OK;
    }
    if (!rep_file_exists(m->basis)) {
        rep_note(c, "the basis %s that speckles.fits names is not readable: registration figure skipped", m->basis);
        return SWFS_OK;
    }
    m->np = (size_t)g->pupn;
    const size_t n = m->np * m->np;
    size_t nout = 0;
    m->mask = malloc(n * sizeof *m->mask);
    m->z = malloc(n * sizeof *m->z);
    m->in = malloc(n);
    if (!m->mask || !m->z || !m->in) return swfs_fail(SWFS_ERR_NOMEM, "registration figure: out of memory");
    if ((rc = swfs_aperture_make(m->mask, m->np, g->pupdx, g->teldiam, isfinite(g->obscur) ? g->obscur : 0, 0, 0)))
        return rc;
    if ((rc = swfs_fits_read_real(m->basis, NULL, &m->cube, NULL))) return rc;
    if (m->reg.pitch > 0)
        rc = swfs_basis_from_grid(&m->B, m->cube->data, m->cube->nx, m->cube->ny, m->cube->nz, &m->reg, m->mask, m->np,
                                  g->pupdx, &nout);
    else if (m->cube->nx == m->np && m->cube->ny == m->np)
        rc = swfs_basis_from_pupil(&m->B, m->cube->data, m->np, m->cube->nz, m->mask);
    else return SWFS_OK;
    for (size_t k = 0; k < n; k++) m->in[k] = m->mask[k] > 0;
    *drawable = !rc;
    return rc;
}

/* Basis function k on the pupil grid, as an image panel. */
static int mode_panel(rep_ctx *c, swfs_plot *p, int panel, reg_maps *m, size_t k, swfs_plot_image_spec *s)
{
    const size_t n = m->np * m->np;
    double *e = calloc(m->B->ncols, sizeof *e);
    if (!e) return swfs_fail(SWFS_ERR_NOMEM, "registration figure: out of memory");
    e[k] = 1;
    swfs_sparse_apply(m->B, e, m->z);
    free(e);
    char title[96], name[32];
    snprintf(title, sizeof title, "basis function %zu on the pupil grid", k);
    snprintf(name, sizeof name, "basis%zu", k);
    double *zz = malloc(n * sizeof *zz);
    if (!zz) return swfs_fail(SWFS_ERR_NOMEM, "registration figure: out of memory");
    swfs_report_range r = rep_prepare(c, name, m->z, n, m->in, R_SYM, 1.0, 0, 0, zz);
    int rc = rep_image_panel(p, panel, s, &r, title, "value [basis units]", SWFS_CMAP_DIVERGING, zz, m->np, m->np);
    free(zz);
    const double rr[2] = {0.5 * c->geom.teldiam, 0.5 * c->geom.teldiam * (isfinite(c->geom.obscur) ? c->geom.obscur : 0)};
    if (!rc) rc = swfs_plot_circles(p, 0, 0, rr, rr[1] > 0 ? 2 : 1, SWFS_COLOR_BLACK, SWFS_LINE_SOLID, 1.0);
    return rc;
}

/* The DM grid's points over the pupil, and its +x (red) and +y (blue) axes from the centre. */
static int grid_panel(rep_ctx *c, swfs_plot *p, int panel, const reg_maps *m)
{
    const double R = 0.5 * c->geom.teldiam, L = 1.15 * R;
    const swfs_plot_axes_spec a = {"DM grid on the pupil: points, +x (red), +y (blue)", "x [m]", "y [m]", -L, L, -L, L, 1};
    int rc = swfs_plot_panel(p, panel);
    if (!rc) rc = swfs_plot_axes(p, &a);
    const size_t gx = m->cube->nx, gy = m->cube->ny;
    double *x = malloc(gx * gy * sizeof *x), *y = malloc(gx * gy * sizeof *y);
    size_t n = 0;
    if (!x || !y) rc = rc ? rc : swfs_fail(SWFS_ERR_NOMEM, "registration figure: out of memory");
    for (size_t j = 0; !rc && j < gy; j++)
        for (size_t i = 0; i < gx; i++) {
            swfs_dm_to_pupil(&m->reg, gx, gy, (double)i, (double)j, x + n, y + n);
            if (fabs(x[n]) <= L && fabs(y[n]) <= L) n++;
        }
    if (!rc) rc = swfs_plot_points(p, x, y, n, SWFS_COLOR_GRAY, 0.3);
    const double rr[2] = {R, R * (isfinite(c->geom.obscur) ? c->geom.obscur : 0)};
    if (!rc) rc = swfs_plot_circles(p, 0, 0, rr, rr[1] > 0 ? 2 : 1, SWFS_COLOR_BLACK, SWFS_LINE_SOLID, 1.5);
    const double cu = 0.5 * (double)(gx - 1), cv = 0.5 * (double)(gy - 1), steps = 0.4 * R / m->reg.pitch;
    const double ends[2][2] = {{cu + steps, cv}, {cu, cv + steps}};
    for (int k = 0; k < 2 && !rc; k++) {
        double lx[2], ly[2];
        swfs_dm_to_pupil(&m->reg, gx, gy, cu, cv, lx, ly);
        swfs_dm_to_pupil(&m->reg, gx, gy, ends[k][0], ends[k][1], lx + 1, ly + 1);
        rc = swfs_plot_line(p, lx, ly, 2, k ? SWFS_COLOR_BLUE : SWFS_COLOR_RED, SWFS_LINE_SOLID, 3.0);
    }
    free(x);
    free(y);
    return rc;
}

int rep_fig_registration(rep_ctx *c)
{
    if (!c->has[P_SPECKLES] || !swfs_plot_available()) return SWFS_OK;
    reg_maps m;
    memset(&m, 0, sizeof m);
    swfs_plot *p = NULL;
    int drawable = 0;
    char path[REP_PATHMAX];
    int rc = rep_join(path, c->out_dir, "registration.png");
    if (!rc) rc = load(c, &m, &drawable);
    if (rc || !drawable) goto done;
    const int grid = m.reg.pitch > 0, nmodes = (int)(m.B->ncols < 3 ? m.B->ncols : 3), npanel = nmodes + grid;
    const int cols = npanel > 1 ? 2 : 1, rows = npanel > 2 ? 2 : 1;
    const int w = cols == 2 ? REP_W_GRID : REP_W_PIXEL, h = rows == 2 ? REP_H_GRID : REP_H_ROW2;
    swfs_plot_image_spec s;
    memset(&s, 0, sizeof s);
    const double half = 0.5 * (double)(m.np - 1) * c->geom.pupdx;
    s.xlabel = "x [m]";
    s.ylabel = "y [m]";
    s.x0 = s.y0 = -half;
    s.x1 = s.y1 = half;
    s.mask = m.in;
    if ((rc = swfs_plot_create(&p, path, w, h, cols, rows))) goto done;
    int panel = 0;
    if (grid) rc = grid_panel(c, p, panel++, &m);
    for (size_t k = 0; !rc && k < (size_t)nmodes; k++) rc = mode_panel(c, p, panel++, &m, k, &s);
    if (!rc)
        rc = rep_commit(c, &p, "registration.png", w, h, "The linear model's registration",
                        "The first basis functions of the speckles' linear model (--basis) resampled onto the pupil "
                        "grid as the pipeline uses them, with the pupil outline; for a basis on the DM's own grid, "
                        "the grid's points and its +x (red) and +y (blue) axes placed on the pupil by the registration "
                        "(--dm-pitch, --dm-offset, --dm-rot, --dm-flip). A mode cut by the pupil edge or axes turned "
                        "or mirrored against the DM's known layout mean a wrong registration.");
done:
    swfs_plot_abort(p);
    reg_free(&m);
    return rc;
}

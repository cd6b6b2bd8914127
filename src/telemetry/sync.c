/* WFS / science-camera synchronization by tip-tilt cross-correlation (Sec. 4.2), the
 * handshake log and the timing table (see sync.h). */
#include "specklewfs/sync.h"
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_sync_params_default(swfs_sync_params *p)
{
    p->ratio_min = 2;
    p->ratio_max = 12;
    p->lag_min = -20;
    p->lag_max = 20;
    p->ratio_step = 0.01;
    p->lag_step = 0.5;
}

void swfs_tilt_rows_apply(const double *R, const double *v, size_t nvals, size_t nwfs, double *mx, double *my)
{
    for (size_t k = 0; k < nwfs; k++) {
        const double *s = v + k * nvals;
        double sx = 0, sy = 0;
        for (size_t i = 0; i < nvals; i++) { sx += R[i] * s[i]; sy += R[nvals + i] * s[i]; }
        mx[k] = sx;
        my[k] = sy;
    }
}

void swfs_slopes_mean_xy(const double *slopes, size_t nslopes, size_t nwfs, const unsigned char *valid, double *mx,
                         double *my)
{
    size_t nsa = nslopes / 2;
    for (size_t k = 0; k < nwfs; k++) {
        const double *s = slopes + k * nslopes;
        double sx = 0, sy = 0;
        size_t n = 0;
        for (size_t i = 0; i < nsa; i++) {
            int use = valid ? valid[i] != 0 : (s[i] != 0 || s[nsa + i] != 0);
            if (!use) continue;
            sx += s[i]; sy += s[nsa + i]; n++;
        }
        mx[k] = n ? sx / (double)n : 0;
        my[k] = n ? sy / (double)n : 0;
    }
}

/* Integral of the piecewise-constant series over [0, t) from its prefix sums C. */
static inline double cum_at(const double *C, const double *m, double t)
{
    double fl = floor(t);
    size_t k = (size_t)fl;
    return C[k] + (t - fl) * m[k];
}

int swfs_sync_box_means(const double *m, size_t n, double start, double ratio, size_t nexp, double *out)
{
    if (!(ratio > 0)) return swfs_fail(SWFS_ERR_ARG, "sync: frame ratio %g must be positive", ratio);
    if (!(start >= 0) || start + (double)nexp * ratio > (double)n)
        return swfs_fail(SWFS_ERR_VALUE, "sync: exposures [%g, %g) leave the %zu telemetry frames", start,
                         start + (double)nexp * ratio, n);
    double *C = malloc((n + 1) * sizeof *C);
    if (!C) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    C[0] = 0;
    for (size_t k = 0; k < n; k++) C[k + 1] = C[k] + m[k];
    for (size_t j = 0; j < nexp; j++) {
        double a = start + (double)j * ratio, b = a + ratio;
        double cb = b >= (double)n ? C[n] : cum_at(C, m, b);
        out[j] = (cb - cum_at(C, m, a)) / ratio;
    }
    free(C);
    return SWFS_OK;
}

typedef struct prep_cube {
    const swfs_sync_cube *c;
    double *Cx, *Cy; /* prefix sums, nwfs + 1 */
} prep_cube;

/* Pooled correlations of the four pairings at (ratio, lag) over the cubes in [c0, c1):
 * per cube the means are removed (each cube has its own pointing offset). */
typedef struct corr_acc {
    double s[4], vt[2], vp[2];
    size_t nexp;
} corr_acc;

/* The exposures [*j0, *j1) of cube c that lie wholly inside its file at (ratio, lag); 0 when
 * fewer than two do. */
static int exposure_range(const swfs_sync_cube *c, double ratio, double lag, size_t *j0, size_t *j1)
{
    const double start = c->logged - lag;
    double jlo = ceil(-start / ratio);
    if (jlo < 0) jlo = 0;
    double jhi = floor(((double)c->nwfs - start) / ratio) - 1; /* last j with end <= nwfs */
    if (jhi > (double)c->nframes - 1) jhi = (double)c->nframes - 1;
    if (jhi < jlo + 1) return 0;
    *j0 = (size_t)jlo;
    *j1 = (size_t)jhi + 1;
    return 1;
}

/* Sums of the mean x and y slopes over the WFS-time interval [a, b) of the cube's file. */
static inline void box_sums(const prep_cube *pc, double a, double b, double *px, double *py)
{
    const swfs_sync_cube *c = pc->c;
    double cbx = b >= (double)c->nwfs ? pc->Cx[c->nwfs] : cum_at(pc->Cx, c->mx, b);
    double cby = b >= (double)c->nwfs ? pc->Cy[c->nwfs] : cum_at(pc->Cy, c->my, b);
    *px = cbx - cum_at(pc->Cx, c->mx, a);
    *py = cby - cum_at(pc->Cy, c->my, a);
}

static void score_cubes(const prep_cube *pc, size_t c0, size_t c1, double ratio, double lag, corr_acc *acc)
{
    memset(acc, 0, sizeof *acc);
    for (size_t ci = c0; ci < c1; ci++) {
        const swfs_sync_cube *c = pc[ci].c;
        const double start = c->logged - lag;
        size_t j0, j1;
        if (!exposure_range(c, ratio, lag, &j0, &j1)) continue;
        const size_t nj = j1 - j0;
        /* Two passes: means, then co-moments. */
        double mtx = 0, mty = 0, mpx = 0, mpy = 0;
        for (size_t j = j0; j < j1; j++) {
            double a = start + (double)j * ratio, px, py;
            box_sums(&pc[ci], a, a + ratio, &px, &py);
            mtx += c->tx[j]; mty += c->ty[j]; mpx += px; mpy += py;
        }
        mtx /= (double)nj; mty /= (double)nj; mpx /= (double)nj; mpy /= (double)nj;
        for (size_t j = j0; j < j1; j++) {
            double a = start + (double)j * ratio, px, py;
            box_sums(&pc[ci], a, a + ratio, &px, &py);
            px -= mpx;
            py -= mpy;
            double tx = c->tx[j] - mtx, ty = c->ty[j] - mty;
            acc->s[0] += tx * px; acc->s[1] += tx * py; acc->s[2] += ty * px; acc->s[3] += ty * py;
            acc->vt[0] += tx * tx; acc->vt[1] += ty * ty;
            acc->vp[0] += px * px; acc->vp[1] += py * py;
        }
        acc->nexp += nj;
    }
}

/* Lag-1 autocorrelations (pooled over the cubes, each cube's mean removed) of the camera's
 * tx, ty and of the exposures' mean x, y slopes at (ratio, lag): rho[0..3]. */
static void lag1_cubes(const prep_cube *pc, size_t ncubes, double ratio, double lag, double rho[4])
{
    double s1[4] = {0}, s0[4] = {0};
    for (size_t ci = 0; ci < ncubes; ci++) {
        const swfs_sync_cube *c = pc[ci].c;
        const double start = c->logged - lag;
        size_t j0, j1;
        if (!exposure_range(c, ratio, lag, &j0, &j1)) continue;
        const size_t nj = j1 - j0;
        double m[4] = {0}, prev[4] = {0};
        for (size_t j = j0; j < j1; j++) {
            double a = start + (double)j * ratio, px, py;
            box_sums(&pc[ci], a, a + ratio, &px, &py);
            m[0] += c->tx[j]; m[1] += c->ty[j]; m[2] += px; m[3] += py;
        }
        for (int k = 0; k < 4; k++) m[k] /= (double)nj;
        for (size_t j = j0; j < j1; j++) {
            double a = start + (double)j * ratio, v[4];
            box_sums(&pc[ci], a, a + ratio, &v[2], &v[3]);
            v[0] = c->tx[j];
            v[1] = c->ty[j];
            for (int k = 0; k < 4; k++) {
                v[k] -= m[k];
                s0[k] += v[k] * v[k];
                if (j > j0) s1[k] += v[k] * prev[k];
                prev[k] = v[k];
            }
        }
    }
    for (int k = 0; k < 4; k++) rho[k] = s0[k] > 0 ? s1[k] / s0[k] : 0.0;
}

/* The standard normal's upper quantile: z with P(Z > z) = p (bisection on erfc). */
static double normal_upper_quantile(double p)
{
    double lo = 0, hi = 40;
    for (int it = 0; it < 200; it++) {
        double mid = 0.5 * (lo + hi);
        if (0.5 * erfc(mid / sqrt(2.0)) > p) lo = mid;
        else hi = mid;
    }
    return 0.5 * (lo + hi);
}

static void corr4(const corr_acc *a, double c[4])
{
    for (int t = 0; t < 2; t++)
        for (int p = 0; p < 2; p++) {
            double den = sqrt(a->vt[t] * a->vp[p]);
            c[2 * t + p] = den > 0 ? a->s[2 * t + p] / den : 0;
        }
}

/* Best of the straight (tx-mx, ty-my) and swapped (tx-my, ty-mx) pairings. */
static double best_score(const double c[4], int *swap)
{
    double straight = fabs(c[0]) + fabs(c[3]), swapped = fabs(c[1]) + fabs(c[2]);
    if (swap) *swap = swapped > straight;
    return swapped > straight ? swapped : straight;
}

/* Grid search of (ratio, lag) over [r0, r1] x [l0, l1]; keeps the best. */
static void grid(const prep_cube *pc, size_t c0, size_t c1, double r0, double r1, double dr, double l0, double l1,
                 double dl, double *best_r, double *best_l, double *best_s)
{
    size_t nr = (size_t)floor((r1 - r0) / dr + 1e-9) + 1, nl = (size_t)floor((l1 - l0) / dl + 1e-9) + 1;
    for (size_t ir = 0; ir < nr; ir++) {
        double r = r0 + (double)ir * dr;
        if (!(r > 0)) continue;
        for (size_t il = 0; il < nl; il++) {
            double l = l0 + (double)il * dl;
            corr_acc acc;
            score_cubes(pc, c0, c1, r, l, &acc);
            if (acc.nexp < 4) continue;
            double c[4];
            corr4(&acc, c);
            double s = best_score(c, NULL);
            if (s > *best_s) { *best_s = s; *best_r = r; *best_l = l; }
        }
    }
}

/* Points of a grid lo, lo + step, ... <= hi, as grid() visits them. */
static double grid_points(double lo, double hi, double step)
{
    return floor((hi - lo) / step + 1e-9) + 1;
}

void swfs_sync_grid_size(const swfs_sync_params *p, double *nratios, double *nlags)
{
    *nratios = grid_points(p->ratio_min, p->ratio_max, p->ratio_step);
    *nlags = grid_points(p->lag_min, p->lag_max, p->lag_step);
}

int swfs_sync_params_check(const swfs_sync_params *p)
{
    if (!(p->ratio_min > 0 && p->ratio_max >= p->ratio_min && p->ratio_step > 0 && p->lag_max >= p->lag_min &&
          p->lag_step > 0) || !isfinite(p->ratio_max) || !isfinite(p->lag_min) || !isfinite(p->lag_max))
        return swfs_fail(SWFS_ERR_ARG, "sync: search range ratio [%g, %g] step %g, lag [%g, %g] step %g is invalid",
                         p->ratio_min, p->ratio_max, p->ratio_step, p->lag_min, p->lag_max, p->lag_step);
    /* The coarse grid is searched exhaustively: bound it (the default is 1,000 x 31). */
    double nr, nl;
    swfs_sync_grid_size(p, &nr, &nl);
    if (!(nr * nl <= SWFS_SYNC_MAX_GRID))
        return swfs_fail(SWFS_ERR_ARG, "sync: the search grid has %.3g points (%.3g ratios x %.3g lags); at most %.0f: "
                         "use a larger --ratio-step / --lag-step or narrower ranges", nr * nl, nr, nl,
                         (double)SWFS_SYNC_MAX_GRID);
    return SWFS_OK;
}

int swfs_sync_estimate(const swfs_sync_cube *cubes, size_t ncubes, const swfs_sync_params *p, swfs_sync_result *r)
{
    memset(r, 0, sizeof *r);
    if (ncubes == 0) return swfs_fail(SWFS_ERR_ARG, "sync: no camera cube to synchronize");
    int prc = swfs_sync_params_check(p);
    if (prc) return prc;
    prep_cube *pc = calloc(ncubes, sizeof *pc);
    if (!pc) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    int rc = SWFS_OK;
    for (size_t i = 0; i < ncubes && rc == SWFS_OK; i++) {
        const swfs_sync_cube *c = cubes + i;
        pc[i].c = c;
        pc[i].Cx = malloc((c->nwfs + 1) * sizeof *pc[i].Cx);
        pc[i].Cy = malloc((c->nwfs + 1) * sizeof *pc[i].Cy);
        if (!pc[i].Cx || !pc[i].Cy) { rc = swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory"); break; }
        pc[i].Cx[0] = pc[i].Cy[0] = 0;
        for (size_t k = 0; k < c->nwfs; k++) {
            if (!isfinite(c->mx[k]) || !isfinite(c->my[k])) { rc = swfs_fail(SWFS_ERR_VALUE, "sync: cube %zu: slope mean of WFS frame %zu is not finite", i, k); break; }
            pc[i].Cx[k + 1] = pc[i].Cx[k] + c->mx[k];
            pc[i].Cy[k + 1] = pc[i].Cy[k] + c->my[k];
        }
        for (size_t j = 0; j < c->nframes && rc == SWFS_OK; j++)
            if (!isfinite(c->tx[j]) || !isfinite(c->ty[j]))
                rc = swfs_fail(SWFS_ERR_VALUE, "sync: cube %zu: star position of frame %zu is not finite", i, j);
    }
    if (rc) goto done;

    double br = NAN, bl = NAN, bs = -1;
    grid(pc, 0, ncubes, p->ratio_min, p->ratio_max, p->ratio_step, p->lag_min, p->lag_max, p->lag_step, &br, &bl, &bs);
    if (!(bs > 0)) { rc = swfs_fail(SWFS_ERR_NUMERIC, "sync: no overlap between the camera cubes and the telemetry anywhere in the search range"); goto done; }
    /* A peak at the lag window's edge lies beyond it: the window (its width kept) moves to be
     * centred there and is searched again, until the peak is inside (at most 16 moves). A
     * handshake logged 20 frames late was otherwise fitted at the edge of -3..12 with a
     * ratio off by 1 % that made up for it (docs/telemetry.md). */
    double wl0 = p->lag_min, wl1 = p->lag_max;
    for (int it = 0; it < 16 && wl1 > wl0; it++) {
        const int lo = bl < wl0 + 0.5 * p->lag_step, hi = bl > wl1 - 0.5 * p->lag_step;
        if (!lo && !hi) break;
        const double half = floor(0.5 * (wl1 - wl0) / p->lag_step) * p->lag_step;
        wl0 = bl - half;
        wl1 = bl + half;
        grid(pc, 0, ncubes, p->ratio_min, p->ratio_max, p->ratio_step, wl0, wl1, p->lag_step, &br, &bl, &bs);
        r->lag_moves++;
    }
    r->lag_min = wl0;
    r->lag_max = wl1;
    /* Refine twice, 10x finer each time, around the peak and inside the range searched (a
     * peak at a bound is refined on its inner side only). */
    double dr = p->ratio_step, dl = p->lag_step;
    for (int it = 0; it < 2; it++) {
        const double r0 = fmax(br - 2 * dr, p->ratio_min), r1 = fmin(br + 2 * dr, p->ratio_max);
        const double l0 = fmax(bl - 2 * dl, wl0), l1 = fmin(bl + 2 * dl, wl1);
        dr /= 10; dl /= 10;
        grid(pc, 0, ncubes, r0, r1, dr, l0, l1, dl, &br, &bl, &bs);
    }
    corr_acc acc;
    score_cubes(pc, 0, ncubes, br, bl, &acc);
    double c[4];
    corr4(&acc, c);
    int swap = 0;
    best_score(c, &swap);
    r->ratio = br;
    r->lag = bl;
    r->swap = swap;
    r->corr_x = swap ? c[1] : c[0];
    r->corr_y = swap ? c[2] : c[3];
    r->sign_x = r->corr_x >= 0 ? 1 : -1;
    r->sign_y = r->corr_y >= 0 ? 1 : -1;
    for (int k = 0; k < 4; k++) r->corr4[k] = fabs(c[k]);
    /* Significance: each pairing correlation's Fisher z over its effective number of
     * exposures (Bartlett: n (1 - rho_t rho_p) / (1 + rho_t rho_p), rho the lag-1
     * autocorrelations of the camera's and the slopes' series, their product taken >= 0),
     * the two together (z_x + z_y) / sqrt 2, against the Bonferroni bound of the search:
     * a 1 % false-alarm probability over 2 pairings x the coarse grid's points. */
    {
        double rho[4];
        lag1_cubes(pc, ncubes, br, bl, rho);
        const double n = (double)acc.nexp;
        const double px = fmax(0.0, rho[0] * rho[swap ? 3 : 2]), py = fmax(0.0, rho[1] * rho[swap ? 2 : 3]);
        const double nx = n * (1 - fmin(px, 0.999)) / (1 + fmin(px, 0.999)),
                     ny = n * (1 - fmin(py, 0.999)) / (1 + fmin(py, 0.999));
        const double zx = atanh(fmin(fabs(r->corr_x), 1 - 1e-12)) * sqrt(fmax(nx - 3, 0)),
                     zy = atanh(fmin(fabs(r->corr_y), 1 - 1e-12)) * sqrt(fmax(ny - 3, 0));
        double nr, nl;
        swfs_sync_grid_size(p, &nr, &nl);
        nl += (double)r->lag_moves * grid_points(wl0, wl1, p->lag_step);
        r->neff = 0.5 * (nx + ny);
        r->nexp = acc.nexp;
        r->z = (zx + zy) / sqrt(2.0);
        r->z_need = normal_upper_quantile(0.01 / (2 * nr * nl));
    }
    /* Uncertainty: scatter of per-cube ratio estimates at the common lag. */
    size_t nuse = 0;
    double s1 = 0, s2 = 0;
    for (size_t i = 0; i < ncubes; i++) {
        corr_acc a1;
        score_cubes(pc, i, i + 1, br, bl, &a1);
        if (a1.nexp * 2 < cubes[i].nframes) continue;
        double cr = br, cl = bl, cs = -1;
        grid(pc, i, i + 1, br - 5 * p->ratio_step, br + 5 * p->ratio_step, p->ratio_step / 20, bl, bl, 1, &cr, &cl, &cs);
        nuse++;
        s1 += cr; s2 += cr * cr;
    }
    r->ncubes_used = nuse;
    if (nuse >= 3) {
        double m = s1 / (double)nuse, var = (s2 - (double)nuse * m * m) / (double)(nuse - 1);
        r->ratio_err = sqrt(fmax(var, 0) / (double)nuse);
        if (r->ratio_err < dr) r->ratio_err = dr;
    } else {
        r->ratio_err = p->ratio_step;
    }
done:
    for (size_t i = 0; i < ncubes; i++) { free(pc[i].Cx); free(pc[i].Cy); }
    free(pc);
    return rc;
}

/* The fit's pairing's correlations (signs applied) of one prepared cube at (ratio, lag). */
static size_t paired_corr(const prep_cube *pc, const swfs_sync_result *fit, double lag, double *cx, double *cy)
{
    corr_acc acc;
    score_cubes(pc, 0, 1, fit->ratio, lag, &acc);
    double c[4];
    corr4(&acc, c);
    *cx = fit->sign_x * (fit->swap ? c[1] : c[0]);
    *cy = fit->sign_y * (fit->swap ? c[2] : c[3]);
    return acc.nexp;
}

int swfs_sync_continuation_check(const swfs_sync_cube *part, const swfs_sync_result *fit, const swfs_sync_params *p,
                                 swfs_sync_continuation *out)
{
    memset(out, 0, sizeof *out);
    int rc = swfs_sync_params_check(p);
    if (rc) return rc;
    if (!(fit->ratio > 0) || !isfinite(fit->lag)) return swfs_fail(SWFS_ERR_ARG, "sync: continuation check without a fit");
    prep_cube pc = {part, malloc((part->nwfs + 1) * sizeof(double)), malloc((part->nwfs + 1) * sizeof(double))};
    if (!pc.Cx || !pc.Cy) {
        free(pc.Cx);
        free(pc.Cy);
        return swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory");
    }
    pc.Cx[0] = pc.Cy[0] = 0;
    for (size_t k = 0; k < part->nwfs; k++) {
        pc.Cx[k + 1] = pc.Cx[k] + part->mx[k];
        pc.Cy[k + 1] = pc.Cy[k] + part->my[k];
    }
    /* The lag over the search range, then twice 10x finer around the best, as the fit. */
    double best = NAN, bs = -INFINITY, l0 = p->lag_min, l1 = p->lag_max, dl = p->lag_step;
    for (int it = 0; it < 3; it++) {
        const size_t nl = (size_t)floor((l1 - l0) / dl + 1e-9) + 1;
        for (size_t il = 0; il < nl; il++) {
            double l = l0 + (double)il * dl, cx, cy;
            if (paired_corr(&pc, fit, l, &cx, &cy) < 4) continue;
            if (cx + cy > bs) { bs = cx + cy; best = l; }
        }
        if (!isfinite(best)) break;
        l0 = best - 2 * dl;
        dl /= 10;
        l1 = l0 + 40 * dl;
    }
    if (isfinite(best)) {
        out->nexp = paired_corr(&pc, fit, best, &out->corr_x, &out->corr_y);
        out->offset = best - fit->lag;
        /* Fisher z of each correlation against 0 over the part's effective number of exposures
         * (its exposures at the fit's share of independent ones, as the fit's significance
         * counts them: series correlated from exposure to exposure hold fewer independent
         * exposures than they have, and Fisher's z assumes independent ones), both positive and
         * together 5 sigma: (z_x + z_y) / sqrt 2 is N(0, 1) for a file that does not continue
         * the cube. (Each axis alone at 5 sigma refused a 16-exposure part at offset -0.02
         * with correlations 0.99 / 0.87, 9.5 and 4.8 sigma: bench_telemetry sh24-base seed 6.) */
        const double share = fit->nexp > 0 && fit->neff > 0 ? fmin(1.0, fit->neff / (double)fit->nexp) : 1.0,
                     ne = share * (double)out->nexp, zs = sqrt(ne > 3 ? ne - 3 : 0);
        const double zx = atanh(fmin(out->corr_x, 1 - 1e-12)) * zs, zy = atanh(fmin(out->corr_y, 1 - 1e-12)) * zs;
        out->significant = out->corr_x > 0 && out->corr_y > 0 && (zx + zy) / sqrt(2.0) > 5;
        /* Whether the camera tells the best lag from the fit's at all: where the tilt's
         * correlation with the track is a flat ridge along lag (centre-of-gravity slopes of a
         * large residual: flat within 0.005 over 2 frames, docs/telemetry.md), a part's best
         * lag wanders a frame or two from where contiguous files put it. */
        paired_corr(&pc, fit, fit->lag, &out->corr_x0, &out->corr_y0);
        const double c0x = fmin(fmax(out->corr_x0, -1 + 1e-12), 1 - 1e-12),
                     c0y = fmin(fmax(out->corr_y0, -1 + 1e-12), 1 - 1e-12);
        const double dz = zx + zy - (atanh(c0x) + atanh(c0y)) * zs; /* sum of the two rises, each var 2 */
        out->off_significant = dz / 2 > 5;
        out->continues = out->significant && fabs(out->offset) < 0.5;
    }
    free(pc.Cx);
    free(pc.Cy);
    return SWFS_OK;
}

/* Squared norms of the steps over lag frames inside n frames; their max or min into *ext. */
static size_t step_extreme(const double *v, size_t n, size_t nvals, size_t lag, int want_max, double *ext)
{
    size_t m = 0;
    for (size_t k = 0; k + lag < n; k++, m++) {
        const double *a = v + k * nvals, *b = a + lag * nvals;
        double q = 0;
        for (size_t i = 0; i < nvals; i++) q += (b[i] - a[i]) * (b[i] - a[i]);
        if (m == 0 || (want_max ? q > *ext : q < *ext)) *ext = q;
    }
    return m;
}

/* The windows of the check's second stage [frames] (sync.h), and the tail probability it calls
 * a boundary by: 0.5 %, the first stage's wrong-call rate (docs/telemetry.md). */
static const size_t boundary_windows[] = {1, 2, 3, 4, 6, 8, 12, 16};
#define BOUNDARY_ALPHA 0.005

/* Mean and variance of the squared norms |B - A|^2 inside n frames, A the mean of m frames and B
 * the mean of the m frames that start `gap` frames after A's end, at every place the two fit
 * (running sums: nvals values each in sa, sb). Adds to s[0..2] (count, sum, sum of squares). */
static void window_steps(const double *v, size_t n, size_t nvals, size_t m, size_t gap, double *sa, double *sb,
                         double s[3])
{
    if (n < 2 * m + gap) return;
    memset(sa, 0, nvals * sizeof *sa);
    memset(sb, 0, nvals * sizeof *sb);
    for (size_t k = 0; k < m; k++)
        for (size_t i = 0; i < nvals; i++) {
            sa[i] += v[k * nvals + i];
            sb[i] += v[(m + gap + k) * nvals + i];
        }
    for (size_t t = 0;; t++) { /* A = frames [t, t + m), B = [t + m + gap, t + 2m + gap) */
        double q = 0;
        for (size_t i = 0; i < nvals; i++) q += (sb[i] - sa[i]) * (sb[i] - sa[i]);
        q /= (double)(m * m);
        s[0] += 1;
        s[1] += q;
        s[2] += q * q;
        if (t + 2 * m + gap >= n) break;
        const double *a0 = v + t * nvals, *a1 = v + (t + m) * nvals, *b0 = v + (t + m + gap) * nvals,
                     *b1 = v + (t + 2 * m + gap) * nvals;
        for (size_t i = 0; i < nvals; i++) {
            sa[i] += a1[i] - a0[i];
            sb[i] += b1[i] - b0[i];
        }
    }
}

/* z of x under a scaled chi-square of mean mu and variance var (Wilson-Hilferty). */
static double wh_z(double x, double mu, double var)
{
    const double k = 2 * mu * mu / var, c = 2 / (9 * k);
    return (cbrt(x / mu) - (1 - c)) / sqrt(c);
}

/* The second stage of swfs_sync_boundary_check (sync.h): window means of m frames either side
 * of the boundary, m the window that best parts the contiguous steps from those over a lost
 * frame inside the edges; contiguous when q_m is in the contiguous steps' bulk and below
 * what a lost frame makes at BOUNDARY_ALPHA. */
static int boundary_windowed(const double *tail, size_t ntail, const double *head, size_t nhead, size_t nvals,
                             swfs_sync_boundary *out)
{
    double *sa = malloc(2 * nvals * sizeof *sa);
    if (!sa) return swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory for a boundary check of %zu values", nvals);
    double *sb = sa + nvals, best = -INFINITY, bc[2] = {0, 0}, bg[2] = {0, 0};
    size_t bm = 0;
    for (size_t w = 0; w < sizeof boundary_windows / sizeof *boundary_windows; w++) {
        const size_t m = boundary_windows[w];
        if (16 * m > ntail || 16 * m > nhead) continue; /* fewer than 16 disjoint windows a side */
        double c[3] = {0, 0, 0}, g[3] = {0, 0, 0};
        window_steps(tail, ntail, nvals, m, 0, sa, sb, c);
        window_steps(head, nhead, nvals, m, 0, sa, sb, c);
        window_steps(tail, ntail, nvals, m, 1, sa, sb, g);
        window_steps(head, nhead, nvals, m, 1, sa, sb, g);
        const double mc = c[1] / c[0], vc = c[2] / c[0] - mc * mc, mg = g[1] / g[0], vg = g[2] / g[0] - mg * mg;
        if (!(mc > 0) || !(mg > 0) || !(vc > 0) || !(vg > 0)) continue;
        const double d = -wh_z(mc, mg, vg); /* the contiguous steps' mean, in sd of the lost frame's */
        if (d > best) {
            best = d;
            bm = m;
            bc[0] = mc, bc[1] = vc, bg[0] = mg, bg[1] = vg;
        }
    }
    /* only where the data part the two kinds at all: the contiguous steps' mean itself beyond
     * what a lost frame makes at BOUNDARY_ALPHA (white noise, where a step over one frame is
     * one over two, called 2 of 115 cuts contiguous without this) */
    if (bm && 0.5 * erfc(best / sqrt(2.0)) < BOUNDARY_ALPHA) {
        double q = 0;
        for (size_t i = 0; i < nvals; i++) {
            double a = 0, b = 0;
            for (size_t k = 0; k < bm; k++) {
                a += tail[(ntail - bm + k) * nvals + i];
                b += head[k * nvals + i];
            }
            q += (b - a) * (b - a);
        }
        q /= (double)(bm * bm);
        out->window = bm;
        out->q_window = q;
        out->p_lost = 0.5 * erfc(-wh_z(q, bg[0], bg[1]) / sqrt(2.0)); /* P(a lost frame's step <= q) */
        out->p_contiguous = 0.5 * erfc(wh_z(q, bc[0], bc[1]) / sqrt(2.0)); /* P(a contiguous step >= q) */
        if (out->p_lost < BOUNDARY_ALPHA && out->p_contiguous >= BOUNDARY_ALPHA) out->verdict = 1;
    }
    free(sa);
    return SWFS_OK;
}

int swfs_sync_boundary_check(const double *tail, size_t ntail, const double *head, size_t nhead, size_t nvals,
                             swfs_sync_boundary *out)
{
    memset(out, 0, sizeof *out);
    out->q_window = out->p_lost = out->p_contiguous = NAN;
    if (!tail || !head || !ntail || !nhead || !nvals)
        return swfs_fail(SWFS_ERR_ARG, "sync: boundary check without frames on both sides");
    const double *a = tail + (ntail - 1) * nvals;
    for (size_t i = 0; i < nvals; i++) out->q += (head[i] - a[i]) * (head[i] - a[i]);
    double e1a = 0, e1b = 0, e2a = 0, e2b = 0;
    const size_t n1a = step_extreme(tail, ntail, nvals, 1, 1, &e1a), n1b = step_extreme(head, nhead, nvals, 1, 1, &e1b);
    const size_t n2a = step_extreme(tail, ntail, nvals, 2, 0, &e2a), n2b = step_extreme(head, nhead, nvals, 2, 0, &e2b);
    out->n1 = n1a + n1b;
    out->n2 = n2a + n2b;
    if (!n1a || !n1b || !n2a || !n2b) return SWFS_OK; /* too few frames on a side: cannot tell */
    out->q1_max = fmax(e1a, e1b);
    out->q2_min = fmin(e2a, e2b);
    const double q = out->q;
    if (!isfinite(q) || !isfinite(out->q1_max) || !isfinite(out->q2_min)) return SWFS_OK;
    if (q == 0) out->verdict = out->q1_max > 0 ? -1 : 0; /* a frame repeated, unless nothing moves */
    else if (q < out->q2_min && q <= out->q1_max) out->verdict = 1;
    else if (q > out->q1_max && q >= out->q2_min) out->verdict = -1;
    else return boundary_windowed(tail, ntail, head, nhead, nvals, out);
    return SWFS_OK;
}

/* The extremes of the squared step norms over `lag` frames inside n frames (none: unchanged). */
static void step_range(const double *v, size_t n, size_t nvals, size_t lag, double *mn, double *mx)
{
    for (size_t k = 0; k + lag < n; k++) {
        const double *a = v + k * nvals, *b = a + lag * nvals;
        double q = 0;
        for (size_t i = 0; i < nvals; i++) q += (b[i] - a[i]) * (b[i] - a[i]);
        *mn = fmin(*mn, q);
        *mx = fmax(*mx, q);
    }
}

/* The smallest squared step norm over lags n/2 .. n-1 inside n frames (none: *mn unchanged).
 * Those steps pair frame k of the first m = n - n/2 with frame n/2 + j, j >= k, of the last m:
 * |a|^2 + |b|^2 - 2 a.b, the products by one GEMM of the two blocks (m^2 nvals, the check's
 * whole cost; a step over half an edge is far larger than the rounding of that difference). */
static int step_far_min(const double *v, size_t n, size_t nvals, double *mn)
{
    const size_t h = n / 2, m = n - h;
    double *G = malloc(m * m * sizeof *G), *nrm = malloc(n * sizeof *nrm);
    if (!G || !nrm) {
        free(G);
        free(nrm);
        return swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory for a gap check of %zu frames", n);
    }
    for (size_t k = 0; k < n; k++) nrm[k] = cblas_ddot((int)nvals, v + k * nvals, 1, v + k * nvals, 1);
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)m, (int)m, (int)nvals, 1.0, v, (int)nvals,
                v + h * nvals, (int)nvals, 0.0, G, (int)m);
    for (size_t k = 0; k < m; k++)
        for (size_t j = k; j < m; j++) {
            double q = nrm[k] + nrm[h + j] - 2.0 * G[k * m + j];
            if (q < 0.0) q = 0.0; /* rounding; a NaN stays one, which fmin passes over as the loop did */
            *mn = fmin(*mn, q);
        }
    free(G);
    free(nrm);
    return SWFS_OK;
}

int swfs_sync_boundary_gap(const double *tail, size_t ntail, const double *head, size_t nhead, size_t nvals,
                           long lost, swfs_sync_gap *out)
{
    memset(out, 0, sizeof *out);
    out->lost = lost;
    out->qk_min = out->qfar_min = INFINITY;
    out->qk_max = -INFINITY;
    if (!tail || !head || !ntail || !nhead || !nvals || !lost)
        return swfs_fail(SWFS_ERR_ARG, "sync: gap check without frames on both sides or without frames lost");
    const double *a = tail + (ntail - 1) * nvals;
    for (size_t i = 0; i < nvals; i++) out->q += (head[i] - a[i]) * (head[i] - a[i]);
    if (lost < 0) { /* repeated frames: B's first |lost| are A's last, value for value */
        const size_t r = (size_t)(-lost);
        if (r > ntail || r > nhead) return SWFS_OK;
        double moves = 0;
        step_extreme(tail, ntail, nvals, 1, 1, &moves);
        out->consistent = moves > 0 && !memcmp(head, tail + (ntail - r) * nvals, r * nvals * sizeof *head);
        return SWFS_OK;
    }
    const size_t L = (size_t)lost + 1;
    /* Steps over L frames on both sides, and over the longest lags each side holds (its second
     * half: lags n/2 .. n-1), which stand for a gap of many frames. */
    step_range(tail, ntail, nvals, L, &out->qk_min, &out->qk_max);
    step_range(head, nhead, nvals, L, &out->qk_min, &out->qk_max);
    int rc = SWFS_OK;
    if (ntail / 2 > L) rc = step_far_min(tail, ntail, nvals, &out->qfar_min);
    if (!rc && nhead / 2 > L) rc = step_far_min(head, nhead, nvals, &out->qfar_min);
    if (rc) return rc;
    const double q = out->q;
    out->separable = isfinite(out->qk_max) && isfinite(out->qfar_min) && out->qk_max < out->qfar_min;
    out->consistent = out->separable && isfinite(q) && q >= out->qk_min && q <= out->qk_max;
    return SWFS_OK;
}

/* ---- handshake log ----------------------------------------------------------- */

static char *trim(char *s)
{
    char *h = strchr(s, '#');
    if (h) *h = 0;
    while (*s == ' ' || *s == '\t') s++;
    size_t n = strlen(s);
    while (n && (s[n - 1] == '\n' || s[n - 1] == '\r' || s[n - 1] == ' ' || s[n - 1] == '\t')) s[--n] = 0;
    return s;
}

int swfs_handshake_read(const char *path, swfs_handshake **out, size_t *n)
{
    *out = NULL;
    *n = 0;
    if (swfs_input_check(path, "handshake log")) return SWFS_ERR_IO;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the handshake log: %s", path, strerror(errno));
    size_t cap = 16, cnt = 0;
    swfs_handshake *h = malloc(cap * sizeof *h);
    char line[4096];
    long lineno = 0;
    int rc = SWFS_OK;
    if (!h) { fclose(f); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    while (swfs_text_line(f, line, sizeof line, path, ++lineno, &rc)) {
        char *s = trim(line);
        if (!*s) continue;
        if (cnt == cap) {
            swfs_handshake *t = realloc(h, 2 * cap * sizeof *h);
            if (!t) { rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); break; }
            h = t; cap *= 2;
        }
        char cam[SWFS_SYNC_NAME], slo[SWFS_SYNC_NAME], extra[8];
        long fr;
        int k = sscanf(s, "%511s %511s %ld %7s", cam, slo, &fr, extra);
        if (k != 3 || fr < 0) {
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: expected \"CAMERA_FILE SLOPES_FILE WFS_FRAME\" (frame >= 0), got \"%.80s\"",
                           path, lineno, s);
            break;
        }
        snprintf(h[cnt].camera, sizeof h[cnt].camera, "%s", cam);
        snprintf(h[cnt].slopes, sizeof h[cnt].slopes, "%s", slo);
        h[cnt].frame = fr;
        cnt++;
    }
    fclose(f);
    if (rc == SWFS_OK && cnt == 0) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the handshake log has no entries", path);
    if (rc) { free(h); return rc; }
    *out = h;
    *n = cnt;
    return SWFS_OK;
}

int swfs_handshake_write(const char *path, const swfs_handshake *h, size_t n)
{
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    FILE *f = swfs_atomic_stream(a);
    fprintf(f, "# specklewfs handshake log: one camera cube per line\n# CAMERA_FILE SLOPES_FILE WFS_FRAME "
               "(frame of SLOPES_FILE logged when the cube started, late by an unknown lag)\n");
    for (size_t i = 0; i < n; i++) fprintf(f, "%s %s %ld\n", h[i].camera, h[i].slopes, h[i].frame);
    return swfs_atomic_commit(a);
}

/* ---- timing table ---------------------------------------------------------------- */

/* The largest frame number or count a timing table may give (2^40: more than any file). */
#define MAX_FRAMES ((size_t)1 << 40)

void swfs_timing_free(swfs_timing *t)
{
    if (!t) return;
    free(t->cubes);
    free(t);
}

void swfs_timing_join_verdict(const swfs_timing_cube *c, char *buf, size_t cap)
{
    char v[96];
    if (c->join_verdict > 0 && c->join_window)
        snprintf(v, sizeof v, "continuous (the means of %zu frames either side)", c->join_window);
    else
        snprintf(v, sizeof v, "%s", c->join_verdict > 0 ? "continuous" : c->join_verdict < 0 ? "not continuous" : "undecided");
    const long n = labs(c->join_lost);
    const char *what = c->join_lost > 0 ? "lost" : "repeated", *s = n == 1 ? "" : "s";
    if (c->join_lost && c->join_frame0)
        snprintf(buf, cap, "%ld WFS frame%s %s there by the files' FRAME0; the telemetry %s", n, s, what, v);
    else if (c->join_lost)
        snprintf(buf, cap, "not continuous: %ld WFS frame%s %s there (the camera's count)", n, s, what);
    else if (c->join_frame0)
        snprintf(buf, cap, "%s; the files' FRAME0 %s", v, c->join_verdict > 0 ? "agree" : "say contiguous");
    else
        snprintf(buf, cap, "%s", v);
}

int swfs_timing_write(const char *path, const swfs_timing *t)
{
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    FILE *f = swfs_atomic_stream(a);
    fprintf(f, "# specklewfs timing table (specklewfs sync): WFS time in frames of each slopes file\n");
    fprintf(f, "# camera exposure j of a cube covers [start + j ratio, start + (j+1) ratio)\n");
    fprintf(f, "ratio %.6f %.6f\n", t->ratio, t->ratio_err);
    fprintf(f, "lag %.4f\n", t->lag);
    fprintf(f, "# pairing SWAP SIGN_X SIGN_Y CORR_X CORR_Y  (SWAP 1: camera x follows the y slopes)\n");
    fprintf(f, "pairing %d %d %d %.4f %.4f\n", t->fit.swap, t->fit.sign_x, t->fit.sign_y, t->fit.corr_x, t->fit.corr_y);
    fprintf(f, "# cube INDEX CAMERA_FILE FIRST_FRAME NFRAMES SLOPES_FILE START STATUS\n");
    for (size_t i = 0; i < t->ncubes; i++) {
        const swfs_timing_cube *c = t->cubes + i;
        if (c->joined) {
            char how[160];
            swfs_timing_join_verdict(c, how, sizeof how);
            fprintf(f, "# %s frames %zu-%zu continue in the next or previous telemetry file: lag offset %+.3f WFS "
                    "frames, correlations %.3f %.3f; the telemetry across the boundary %s\n", c->camera, c->first,
                    c->first + c->nframes - 1, c->join_offset, c->join_corr_x, c->join_corr_y, how);
        }
        if (c->status == SWFS_CUBE_MISSING)
            fprintf(f, "# %s frames %zu-%zu: the telemetry file cannot be read (sync's message says why)\n",
                    c->camera, c->first, c->first + c->nframes - 1);
        fprintf(f, "cube %zu %s %zu %zu %s %.6f %s\n", i, c->camera, c->first, c->nframes, c->slopes, c->start,
                c->status == SWFS_CUBE_OK ? "ok" : c->status == SWFS_CUBE_MISSING ? "missing" : "straddles");
    }
    return swfs_atomic_commit(a);
}

int swfs_timing_read(const char *path, swfs_timing **out)
{
    *out = NULL;
    if (swfs_input_check(path, "timing table")) return SWFS_ERR_IO;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the timing table: %s", path, strerror(errno));
    swfs_timing *t = calloc(1, sizeof *t);
    size_t cap = 16;
    if (t) t->cubes = malloc(cap * sizeof *t->cubes);
    if (!t || !t->cubes) { fclose(f); swfs_timing_free(t); return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); }
    t->ratio = NAN;
    t->lag = NAN;
    t->fit.sign_x = t->fit.sign_y = 1; /* a table without a pairing line: the camera as the model */
    char line[4096];
    long lineno = 0;
    int rc = SWFS_OK;
    while (swfs_text_line(f, line, sizeof line, path, ++lineno, &rc)) {
        char *s = trim(line);
        if (!*s) continue;
        int ok = 1;
        if (!strncmp(s, "ratio ", 6)) ok = sscanf(s + 6, "%lf %lf", &t->ratio, &t->ratio_err) == 2;
        else if (!strncmp(s, "lag ", 4)) ok = sscanf(s + 4, "%lf", &t->lag) == 1;
        else if (!strncmp(s, "pairing ", 8))
            ok = sscanf(s + 8, "%d %d %d %lf %lf", &t->fit.swap, &t->fit.sign_x, &t->fit.sign_y, &t->fit.corr_x,
                        &t->fit.corr_y) == 5;
        else if (!strncmp(s, "cube ", 5)) {
            if (t->ncubes == cap) {
                swfs_timing_cube *nc = realloc(t->cubes, 2 * cap * sizeof *nc);
                if (!nc) { rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path); break; }
                t->cubes = nc; cap *= 2;
            }
            swfs_timing_cube *c = t->cubes + t->ncubes;
            size_t idx;
            char status[32];
            ok = sscanf(s + 5, "%zu %511s %zu %zu %511s %lf %31s", &idx, c->camera, &c->first, &c->nframes, c->slopes,
                        &c->start, status) == 7 && idx == t->ncubes && isfinite(c->start);
            /* %zu takes "-1" for SIZE_MAX: frame numbers are bounded so that first + nframes,
             * which the users compare with the science cube's length, cannot wrap. */
            if (ok && (c->first > MAX_FRAMES || c->nframes > MAX_FRAMES)) {
                rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: cube %zu: FIRST_FRAME %zu, NFRAMES %zu; expected whole numbers "
                               "from 0 to %zu", path, lineno, idx, c->first, c->nframes, MAX_FRAMES);
                break;
            }
            if (ok) {
                if (!strcmp(status, "ok")) c->status = SWFS_CUBE_OK;
                else if (!strcmp(status, "straddles")) c->status = SWFS_CUBE_STRADDLES;
                else if (!strcmp(status, "missing")) c->status = SWFS_CUBE_MISSING;
                else ok = 0;
            }
            if (ok) t->ncubes++;
        } else ok = 0;
        if (!ok) { rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: cannot parse \"%.80s\" (see docs/telemetry.md)", path, lineno, s); break; }
    }
    fclose(f);
    if (rc == SWFS_OK && (isnan(t->ratio) && isnan(t->lag)))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the timing table needs 'ratio' and 'lag' lines", path);
    else if (rc == SWFS_OK && (!(t->ratio > 0) || !isfinite(t->ratio)))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: ratio %g: expected a finite number of WFS frames per camera frame > 0 "
                       "(a 'ratio' line)", path, t->ratio);
    else if (rc == SWFS_OK && !isfinite(t->lag))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: lag %g: expected a finite number of WFS frames (a 'lag' line)", path, t->lag);
    if (rc == SWFS_OK && t->ncubes == 0) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the timing table lists no cube", path);
    /* each science frame timed once: two rows whose frames of the reduced science file overlap
     * would take those frames twice, each with other telemetry, and leave others out */
    for (size_t i = 0; rc == SWFS_OK && i < t->ncubes; i++)
        for (size_t j = 0; rc == SWFS_OK && j < i; j++) {
            const swfs_timing_cube *a = t->cubes + j, *b = t->cubes + i;
            if (!a->nframes || !b->nframes || a->first >= b->first + b->nframes || b->first >= a->first + a->nframes)
                continue;
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: cubes %zu (%s) and %zu (%s) both time science frames %zu-%zu (theirs "
                           "%zu-%zu and %zu-%zu): expected each frame of the reduced science file in one row", path, j,
                           a->camera, i, b->camera, a->first > b->first ? a->first : b->first,
                           (a->first + a->nframes < b->first + b->nframes ? a->first + a->nframes : b->first + b->nframes) - 1,
                           a->first, a->first + a->nframes - 1, b->first, b->first + b->nframes - 1);
        }
    if (rc) { swfs_timing_free(t); return rc; }
    *out = t;
    return SWFS_OK;
}

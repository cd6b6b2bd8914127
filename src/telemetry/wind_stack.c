/* Further frozen-flow layers from the slopes: the lagged correlation maps stacked along
 * candidate tracks, a layer where a track stands out of the candidates' scatter
 * (include/specklewfs/wind.h). */
#include "wind_internal.h"

#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Within this distance [subapertures] of the map's centre, or of a layer already found, a
 * lag does not count: the slopes' own zero-lag correlation reaches the first ring of
 * neighbours (wind.h). */
#define STACK_EXCLUDE 1.5

/* The lags a track must count to be scored (wind.h): a track counts at two lags only where
 * it moves a third of the map or more per frame (lags 1 and 2 inside, 3 out), so slowly that
 * only the longest lags take it off the centre, or alongside a layer already found; over
 * the matrix's 48 loops (docs/telemetry.md, "On zonal loops' slopes") every two-lag layer was such
 * a one, none a layer of the simulation. */
#define STACK_MIN_LAGS 3

typedef struct {
    const swfs_wind_maps_ *m;
    size_t minc;                           /* pairs a bin needs */
    double ex[SWFS_WIND_MAXLAYERS + 1][2]; /* the layers found [subapertures per frame]; the tracked one
                                              twice, as tracked and as stacked */
    size_t nex;
} stack_ctx;

/* The map at displacement (x, y) [subapertures], bilinear; NAN outside the map or where a
 * corner bin has fewer than minc pairs. */
static double at(const stack_ctx *s, const double *map, double x, double y)
{
    const swfs_wind_maps_ *m = s->m;
    const double fx = x + (double)m->R, fy = y + (double)m->R;
    if (!(fx >= 0) || !(fy >= 0) || fx >= (double)(m->nb - 1) || fy >= (double)(m->nb - 1)) return NAN;
    const size_t i = (size_t)fx, j = (size_t)fy, b = j * m->nb + i;
    const size_t c[4] = {b, b + 1, b + m->nb, b + m->nb + 1};
    for (int k = 0; k < 4; k++)
        if (m->count[c[k]] < s->minc) return NAN;
    const double ax = fx - (double)i, ay = fy - (double)j;
    return (1 - ax) * (1 - ay) * map[c[0]] + ax * (1 - ay) * map[c[1]] + (1 - ax) * ay * map[c[2]] +
           ax * ay * map[c[3]];
}

/* The map of lag m.lag[l] at (px, py) when that lag counts for a track there (off the centre
 * and the layers found, inside the map); NAN otherwise. */
static double score_lag(const stack_ctx *s, size_t l, double px, double py)
{
    const double tau = (double)s->m->lag[l];
    if (hypot(px, py) < STACK_EXCLUDE) return NAN;
    for (size_t k = 0; k < s->nex; k++)
        if (hypot(px - s->ex[k][0] * tau, py - s->ex[k][1] * tau) < STACK_EXCLUDE) return NAN;
    return at(s, s->m->map + l * s->m->nb * s->m->nb, px, py);
}

/* The stacked score of velocity (ux, uy) [subapertures per frame]: the sum of the maps along
 * its track over sqrt(lags counted); NAN below STACK_MIN_LAGS lags. *nl, *mean, *taumax: the lags
 * counted, the mean correlation, the longest lag counted. */
static double score(const stack_ctx *s, double ux, double uy, size_t *nl, double *mean, size_t *taumax)
{
    const swfs_wind_maps_ *m = s->m;
    double sum = 0;
    size_t n = 0, tmax = 0;
    for (size_t l = 0; l < m->nmaps; l++) {
        const double tau = (double)m->lag[l];
        const double v = score_lag(s, l, ux * tau, uy * tau);
        if (isnan(v)) continue;
        sum += v;
        n++;
        tmax = m->lag[l];
    }
    if (nl) *nl = n;
    if (mean) *mean = n ? sum / (double)n : NAN;
    if (taumax) *taumax = tmax;
    return n >= STACK_MIN_LAGS ? sum / sqrt((double)n) : NAN;
}

/* The best score about (*ux, *uy) (its score *bs) on a grid of +-1/tau (tau the longest lag
 * its track counts), then of +-0.1/tau, each of 21 x 21 points; moved to the best found. */
static void refine(const stack_ctx *s, double *ux, double *uy, double *bs)
{
    size_t tmax;
    score(s, *ux, *uy, NULL, NULL, &tmax);
    const double t = (double)(tmax ? tmax : 1);
    for (double h = 1.0 / t; h > 0.05 / t; h *= 0.1) {
        const double cx = *ux, cy = *uy;
        for (int j = -10; j <= 10; j++)
            for (int i = -10; i <= 10; i++) {
                const double v = score(s, cx + 0.1 * h * i, cy + 0.1 * h * j, NULL, NULL, NULL);
                if (v > *bs) { *bs = v; *ux = cx + 0.1 * h * i; *uy = cy + 0.1 * h * j; }
            }
    }
}

/* The track's velocity to a fraction of a bin, as the tracker places its own: on each lag
 * that counts, the highest bin within one of the predicted u tau, when it is a local
 * maximum, refined by a parabola on each axis; the least-squares velocity through the origin
 * of those peaks (the longest lags weigh most). Unchanged where fewer than two lags give a
 * peak. */
static void polish(const stack_ctx *s, double *ux, double *uy)
{
    const swfs_wind_maps_ *m = s->m;
    const long nb = (long)m->nb, R = (long)m->R;
    double stt = 0, sx = 0, sy = 0;
    size_t n = 0;
    for (size_t l = 0; l < m->nmaps; l++) {
        const double tau = (double)m->lag[l], px = *ux * tau, py = *uy * tau;
        if (isnan(score_lag(s, l, px, py))) continue;
        const double *map = m->map + l * m->nb * m->nb;
        long bi = -1, bj = -1;
        for (long j = (long)floor(py) - 1; j <= (long)floor(py) + 2; j++)
            for (long i = (long)floor(px) - 1; i <= (long)floor(px) + 2; i++) {
                if (i + R < 1 || j + R < 1 || i + R >= nb - 1 || j + R >= nb - 1) continue;
                if (hypot((double)i - px, (double)j - py) > 1) continue;
                const size_t b = (size_t)((j + R) * nb + i + R);
                if (m->count[b] < s->minc) continue;
                if (bi < 0 || map[b] > map[(size_t)((bj + R) * nb + bi + R)]) { bi = i; bj = j; }
            }
        if (bi < 0) continue;
        const size_t b = (size_t)((bj + R) * nb + bi + R), nbh[4] = {b - 1, b + 1, b - m->nb, b + m->nb};
        int peak = 1;
        for (int k = 0; k < 4 && peak; k++) peak = m->count[nbh[k]] >= s->minc && !(map[nbh[k]] > map[b]);
        if (!peak) continue;
        const double dx = (double)bi + swfs_wind_vertex_(map[b - 1], map[b], map[b + 1]);
        const double dy = (double)bj + swfs_wind_vertex_(map[b - m->nb], map[b], map[b + m->nb]);
        stt += tau * tau;
        sx += tau * dx;
        sy += tau * dy;
        n++;
    }
    if (n < 2) return;
    *ux = sx / stt;
    *uy = sy / stt;
}

static int cmp_double(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The median and the robust standard deviation (1.4826 MAD) of v[0..n), sorted in place
 * (and then overwritten by the deviations). */
static void robust(double *v, size_t n, double *med, double *sd)
{
    qsort(v, n, sizeof *v, cmp_double);
    *med = n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
    for (size_t k = 0; k < n; k++) v[k] = fabs(v[k] - *med);
    qsort(v, n, sizeof *v, cmp_double);
    *sd = 1.4826 * (n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]));
}

static void set_layer(swfs_wind_layer *L, double ux, double uy, double pitch, double rate, double mean, double z,
                      size_t nl)
{
    L->vx = ux * pitch * rate;
    L->vy = uy * pitch * rate;
    L->speed = hypot(L->vx, L->vy);
    const double dir = atan2(L->vy, L->vx) * 180.0 / M_PI;
    L->direction = dir < 0 ? dir + 360.0 : dir;
    L->corr = mean;
    L->signif = z;
    L->nlags = nl;
}

int swfs_wind_stack_layers_(const swfs_wind_maps_ *m, double pitch, double rate, swfs_wind_estimate *e)
{
    if (!e->found) return SWFS_OK;
    stack_ctx s = {m, m->nsub / 2 > 3 ? m->nsub / 2 : 3, {{0}}, 0};
    const size_t nb2 = m->nb * m->nb;
    size_t ncell = 0;
    for (size_t b = 0; b < nb2; b++) ncell += m->count[b] >= s.minc;
    e->threshold = 2 * sqrt(2 * log((double)(ncell > 2 ? ncell : 2)));
    e->nstack = m->nmaps;
    double *cu = malloc(m->nmaps * nb2 * 3 * sizeof *cu); /* candidates: ux, uy; scores */
    if (!cu) return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory for %zu candidate velocities", m->nmaps * nb2);
    double *cs = cu + 2 * m->nmaps * nb2;
    size_t nc = 0;
    const double R = (double)m->R;
    for (size_t l = 0; l < m->nmaps; l++)
        for (size_t b = 0; b < nb2; b++) {
            const double dx = (double)(b % m->nb) - R, dy = (double)(b / m->nb) - R;
            if (m->count[b] < s.minc || hypot(dx, dy) < STACK_EXCLUDE) continue;
            cu[2 * nc] = dx / (double)m->lag[l];
            cu[2 * nc + 1] = dy / (double)m->lag[l];
            nc++;
        }
    const double u1x = e->vx / (pitch * rate), u1y = e->vy / (pitch * rate);
    e->nlayers = 1; /* the tracked layer as the tracker fitted it; its standing from the first pass */
    e->layer[0] = (swfs_wind_layer){e->vx, e->vy, e->speed, e->direction, NAN, NAN, 0};
    e->next_signif = NAN;
    for (int first = 1; e->nlayers < SWFS_WIND_MAXLAYERS; first = 0) {
        size_t nv = 0, best = SIZE_MAX;
        for (size_t c = 0; c < nc; c++) {
            const double v = score(&s, cu[2 * c], cu[2 * c + 1], NULL, NULL, NULL);
            if (isnan(v)) continue;
            if (best == SIZE_MAX || v > cs[best]) best = nv;
            cs[nv] = v;
            cu[2 * nv] = cu[2 * c]; /* compacted: the candidates that score stay in order */
            cu[2 * nv + 1] = cu[2 * c + 1];
            nv++;
        }
        nc = nv;
        if (best == SIZE_MAX || nv < 16) break;
        const double bx = cu[2 * best], by = cu[2 * best + 1];
        double bs = cs[best];
        double *tmp = malloc(nv * sizeof *tmp);
        if (!tmp) { free(cu); return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory"); }
        memcpy(tmp, cs, nv * sizeof *tmp);
        double med, sd;
        robust(tmp, nv, &med, &sd);
        free(tmp);
        if (!(sd > 0)) break;
        if (first) { /* the tracked layer's own standing, for comparison */
            size_t nl;
            double mean;
            const double v = score(&s, u1x, u1y, &nl, &mean, NULL);
            e->layer[0].corr = mean;
            e->layer[0].signif = (v - med) / sd;
            e->layer[0].nlags = nl;
            /* left out as tracked and as the stacking places it: the tracker fits its
             * velocity from a few lags' peaks, and the stacked track a few degrees off it
             * would otherwise stand out again as a layer of its own (docs/telemetry.md) */
            double rx = u1x, ry = u1y, rs = v;
            refine(&s, &rx, &ry, &rs);
            polish(&s, &rx, &ry);
            s.ex[s.nex][0] = u1x;
            s.ex[s.nex][1] = u1y;
            s.ex[s.nex + 1][0] = rx;
            s.ex[s.nex + 1][1] = ry;
            s.nex += 2;
            continue; /* score again without the tracked layer's track */
        }
        double ux = bx, uy = by;
        refine(&s, &ux, &uy, &bs);
        const double z = (bs - med) / sd;
        if (!(z >= e->threshold)) { e->next_signif = z; break; }
        polish(&s, &ux, &uy);
        size_t nl;
        double mean;
        score(&s, ux, uy, &nl, &mean, NULL);
        set_layer(&e->layer[e->nlayers++], ux, uy, pitch, rate, mean, z, nl);
        s.ex[s.nex][0] = ux;
        s.ex[s.nex][1] = uy;
        s.nex++;
    }
    free(cu);
    /* A tracked layer that does not stand out of the candidates where a further one does: the
     * tracker's peaks were another layer's or the loop's (docs/telemetry.md) */
    e->tracked_signif = e->layer[0].signif;
    if (e->nlayers > 1 && isfinite(e->layer[0].signif) && e->layer[0].signif < e->threshold) {
        memmove(&e->layer[0], &e->layer[1], (e->nlayers - 1) * sizeof e->layer[0]);
        e->nlayers--;
        e->tracked_dropped = 1;
    }
    return SWFS_OK;
}

/* The dominant layer's wind from the slopes: lagged covariances by DGEMM, binned by the
 * subapertures' displacement, peak tracked over doubling lags (include/specklewfs/wind.h). */
#include "specklewfs/wind.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    size_t nv, T, R, nb;   /* valid subapertures, frames, map half width, bins per side */
    double *x, *y;         /* T x nv, means taken out */
    double *c;             /* nv x nv lagged covariance */
    int *bin;              /* nv x nv: the pair's bin, -1 outside the map */
    double *num, *den;     /* nb x nb; den 0: no pair of subapertures in that bin */
} wind_work;

/* Each frame's mean x / y slope (tip-tilt) and each subaperture's mean out of the copies. */
static void centre(double *a, size_t T, size_t nv)
{
    for (size_t t = 0; t < T; t++) {
        double m = 0;
        for (size_t p = 0; p < nv; p++) m += a[t * nv + p];
        m /= (double)nv;
        for (size_t p = 0; p < nv; p++) a[t * nv + p] -= m;
    }
    for (size_t p = 0; p < nv; p++) {
        double m = 0;
        for (size_t t = 0; t < T; t++) m += a[t * nv + p];
        m /= (double)T;
        for (size_t t = 0; t < T; t++) a[t * nv + p] -= m;
    }
}

/* Parabola through three samples: the vertex's offset from the middle one, in [-0.5, 0.5]. */
static double vertex(double l, double c, double r)
{
    const double d = l - 2 * c + r;
    if (!(d < 0)) return 0;
    const double o = 0.5 * (l - r) / d;
    return o < -0.5 ? -0.5 : o > 0.5 ? 0.5 : o;
}

/* The correlation map at one lag and its peak into *L: the highest bin, or while tracking
 * (tol > 0) the highest within tol subapertures of the predicted (px, py); inside when it is
 * a local maximum off the map's edge (while tracking, another layer's peak elsewhere in the
 * map is not this one's). */
static void lag_map(wind_work *w, size_t tau, double px, double py, double tol, swfs_wind_lag *L)
{
    const size_t nv = w->nv, n = w->T - tau, nb = w->nb;
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)nv, (int)nv, (int)n, 1.0, w->x, (int)nv,
                w->x + tau * nv, (int)nv, 0.0, w->c, (int)nv);
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)nv, (int)nv, (int)n, 1.0, w->y, (int)nv,
                w->y + tau * nv, (int)nv, 1.0, w->c, (int)nv);
    memset(w->num, 0, nb * nb * sizeof *w->num);
    for (size_t k = 0; k < nv * nv; k++)
        if (w->bin[k] >= 0) w->num[w->bin[k]] += w->c[k];
    const double R = (double)w->R;
    size_t best = SIZE_MAX;
    for (size_t b = 0; b < nb * nb; b++) {
        if (!(w->den[b] > 0)) continue;
        w->num[b] /= w->den[b];
        if (tol > 0 && hypot((double)(b % nb) - R - px, (double)(b / nb) - R - py) > tol) continue;
        if (best == SIZE_MAX || w->num[b] > w->num[best]) best = b;
    }
    L->lag = tau;
    L->inside = 0;
    L->dx = L->dy = NAN;
    L->corr = best == SIZE_MAX ? NAN : w->num[best];
    if (best == SIZE_MAX) return;
    const size_t i = best % nb, j = best / nb;
    L->dx = (double)i - (double)w->R;
    L->dy = (double)j - (double)w->R;
    if (i == 0 || j == 0 || i + 1 == nb || j + 1 == nb) return;
    const size_t nbh[4] = {best - 1, best + 1, best - nb, best + nb};
    for (int k = 0; k < 4; k++)
        if (!(w->den[nbh[k]] > 0) || w->num[nbh[k]] > w->num[best]) return;
    L->inside = 1;
    L->dx += vertex(w->num[best - 1], w->num[best], w->num[best + 1]);
    L->dy += vertex(w->num[best - nb], w->num[best], w->num[best + nb]);
}

/* The least-squares velocity through the origin [subapertures per frame] of the lags used. */
static void fit_velocity(const swfs_wind_estimate *e, double *ux, double *uy)
{
    double stt = 0, sx = 0, sy = 0;
    for (size_t k = 0; k < e->nlags; k++) {
        if (!e->lag[k].used) continue;
        const double t = (double)e->lag[k].lag;
        stt += t * t;
        sx += t * e->lag[k].dx;
        sy += t * e->lag[k].dy;
    }
    *ux = stt > 0 ? sx / stt : 0;
    *uy = stt > 0 ? sy / stt : 0;
}

static void work_free(wind_work *w)
{
    free(w->x); free(w->y); free(w->c); free(w->bin); free(w->num); free(w->den);
}

int swfs_wind_from_slopes(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                          const unsigned char *valid, double pitch, double rate, swfs_wind_estimate *out)
{
    if (!slopes || !out) return swfs_fail(SWFS_ERR_ARG, "wind: no slopes or no result");
    memset(out, 0, sizeof *out);
    if (nsub < 4) return swfs_fail(SWFS_ERR_VALUE, "wind: %zu x %zu subapertures; need at least 4 x 4", nsub, nsub);
    if (nframes < 64)
        return swfs_fail(SWFS_ERR_VALUE, "wind: %zu WFS frames; the displacement needs at least 64", nframes);
    if (!(pitch > 0) || !isfinite(pitch) || !(rate > 0) || !isfinite(rate))
        return swfs_fail(SWFS_ERR_VALUE, "wind: subaperture pitch %g m and rate %g Hz must be > 0", pitch, rate);
    const size_t n2 = nsub * nsub;
    /* The valid subapertures and where each one's x slope sits in a row. */
    size_t *col = malloc(2 * n2 * sizeof *col), *pos = col + n2, nv = 0, nmap = 0;
    if (!col) return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory");
    if (valid)
        for (size_t s = 0; s < n2; s++) nmap += valid[s] != 0;
    const int compact = valid && nslopes == 2 * nmap;
    if (!compact && nslopes != 2 * n2) {
        free(col);
        return swfs_fail(SWFS_ERR_SHAPE, "wind: %zu slopes per frame; expected 2 nsub^2 = %zu%s", nslopes, 2 * n2,
                         valid ? " or twice the valid subapertures" : "");
    }
    for (size_t s = 0, k = 0; s < n2; s++) {
        if (valid && !valid[s]) continue;
        const size_t c = compact ? k++ : s;
        int seen = valid != NULL;
        for (size_t t = 0; !seen && t < nframes; t++)
            seen = slopes[t * nslopes + c] != 0 || slopes[t * nslopes + nslopes / 2 + c] != 0;
        if (seen) {
            col[nv] = c; /* where its x slope sits in a row */
            pos[nv++] = s; /* where it sits on the grid */
        }
    }
    if (nv < 8) {
        free(col);
        return swfs_fail(SWFS_ERR_VALUE, "wind: %zu valid subapertures with signal; need at least 8", nv);
    }
    for (size_t t = 0; t < nframes; t++)
        for (size_t k = 0; k < nslopes; k++)
            if (!isfinite(slopes[t * nslopes + k])) {
                free(col);
                return swfs_fail(SWFS_ERR_VALUE, "wind: slope %zu of WFS frame %zu is not finite", k, t);
            }
    wind_work w = {0};
    w.nv = nv;
    w.T = nframes;
    w.R = nsub / 2 - 1;
    w.nb = 2 * w.R + 1;
    w.x = malloc(nframes * nv * sizeof *w.x);
    w.y = malloc(nframes * nv * sizeof *w.y);
    w.c = malloc(nv * nv * sizeof *w.c);
    w.bin = malloc(nv * nv * sizeof *w.bin);
    w.num = malloc(w.nb * w.nb * sizeof *w.num);
    w.den = calloc(w.nb * w.nb, sizeof *w.den);
    if (!w.x || !w.y || !w.c || !w.bin || !w.num || !w.den) {
        free(col);
        work_free(&w);
        return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory for %zu frames of %zu subapertures", nframes, nv);
    }
    for (size_t t = 0; t < nframes; t++)
        for (size_t p = 0; p < nv; p++) {
            w.x[t * nv + p] = slopes[t * nslopes + col[p]];
            w.y[t * nv + p] = slopes[t * nslopes + nslopes / 2 + col[p]];
        }
    centre(w.x, nframes, nv);
    centre(w.y, nframes, nv);
    /* Each pair's bin and the bins' normalization: the zero-lag standard deviations. */
    double *sd = w.c; /* the first nv entries, before the covariances use it */
    for (size_t p = 0; p < nv; p++) {
        double s = 0;
        for (size_t t = 0; t < nframes; t++) s += w.x[t * nv + p] * w.x[t * nv + p] + w.y[t * nv + p] * w.y[t * nv + p];
        sd[p] = sqrt(s);
    }
    const long R = (long)w.R;
    for (size_t p = 0; p < nv; p++)
        for (size_t q = 0; q < nv; q++) {
            const size_t sp = pos[p], sq = pos[q];
            const long a = (long)(sq % nsub) - (long)(sp % nsub), b = (long)(sq / nsub) - (long)(sp / nsub);
            int bi = -1;
            if (labs(a) <= R && labs(b) <= R) {
                bi = (int)((size_t)(b + R) * w.nb + (size_t)(a + R));
                w.den[bi] += sd[p] * sd[q];
            }
            w.bin[p * nv + q] = bi;
        }
    free(col);
    out->nvalid = nv;
    out->radius = w.R;
    /* Doubling lags; tracking from the first resolved displacement (wind.h). */
    double ux = 0, uy = 0;
    for (size_t tau = 1; tau <= nframes / 4 && out->nlags < SWFS_WIND_MAXLAGS; tau *= 2) {
        /* Tracking stops where the predicted peak would leave the inner map: its neighbours
         * and enough overlapping pairs are needed to place it. */
        const double px = ux * (double)tau, py = uy * (double)tau;
        if (out->nused && (fabs(px) > (double)(w.R - 1) || fabs(py) > (double)(w.R - 1))) break;
        swfs_wind_lag *L = &out->lag[out->nlags++];
        lag_map(&w, tau, px, py, out->nused ? 0.5 * hypot(px, py) : 0.0, L);
        if (!L->inside) {
            if (out->nused) break;
            continue;
        }
        if (!out->nused && hypot(L->dx, L->dy) < 1) continue;
        if (out->nused && hypot(L->dx - px, L->dy - py) > 0.5 * hypot(px, py)) break; /* the vertex moved out */
        L->used = 1;
        out->nused++;
        fit_velocity(out, &ux, &uy);
    }
    work_free(&w);
    if (out->nused < 2) return SWFS_OK; /* one lag alone does not show a steady motion */
    out->found = 1;
    out->vx = ux * pitch * rate;
    out->vy = uy * pitch * rate;
    out->speed = hypot(out->vx, out->vy);
    double dir = atan2(out->vy, out->vx) * 180.0 / M_PI;
    out->direction = dir < 0 ? dir + 360.0 : dir;
    return SWFS_OK;
}

/* The dominant layer's wind from the slopes: lagged covariances binned by the subapertures'
 * displacement (the slope grids' lagged cross-correlation, by FFT), peak tracked over doubling
 * lags; further layers by stacking the same maps (wind_stack.c; include/specklewfs/wind.h). */
#include "specklewfs/wind.h"
#include "specklewfs/status.h"
#include "../core/planner.h"
#include "wind_internal.h"

#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    size_t nv, T, R, nb;   /* valid subapertures, frames; the tracker's map: +-R, nb bins per side */
    double *x, *y;         /* T x nv, means taken out */
    double *den;           /* whole grid's bins: the pairs' zero-lag deviations' products summed */
    size_t *count;         /* whole grid's bins: pairs */
    double *maps;          /* one whole-grid map per lag of m.lag, all made at once (lag_maps) */
    swfs_wind_maps_ m;     /* the whole grid's maps (wind_internal.h) */
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

double swfs_wind_vertex_(double l, double c, double r)
{
    const double d = l - 2 * c + r;
    if (!(d < 0)) return 0;
    const double o = 0.5 * (l - r) / d;
    return o < -0.5 ? -0.5 : o > 0.5 ? 0.5 : o;
}

/* the frequencies whose series over the frames sit side by side (band: for each block of
 * LAG_KB, each frame's LAG_KB real parts, then their imaginary parts) */
#define LAG_KB 4
/* frames transformed before their spectra go into the band (its writes then run along the frames) */
#define LAG_TB 16

int swfs_wind_lag_sums_(const double *x, const double *y, size_t T, size_t nv, const size_t *pos, size_t nsub,
                        const size_t *lag, size_t nlags, size_t budget, double *sums)
{
    const size_t P = 2 * nsub, PP = P * P, R = nsub - 1, nb = 2 * R + 1;
    for (size_t l = 0; l < nlags; l++)
        if (lag[l] >= T) return swfs_fail(SWFS_ERR_ARG, "wind: lag %zu of a series of %zu frames", lag[l], T);
    /* the spectra of every frame for a band of kc frequencies at a time, each frequency's
     * series over the frames contiguous (every lag's sum then reads it from the cache): by
     * default twice the slopes' own size (x and y), at least 256 MB and at most 1 GB (a 24 x
     * 24's 3700 frames: one band of 136 MB; each further band costs every frame's FFT again) */
    if (!budget) {
        budget = 2 * 2 * T * nv * sizeof(double);
        budget = budget < ((size_t)256 << 20) ? (size_t)256 << 20 : budget > ((size_t)1 << 30) ? (size_t)1 << 30 : budget;
    }
    size_t kc = budget / (T * sizeof(fftw_complex)) / LAG_KB * LAG_KB;
    kc = kc < LAG_KB ? LAG_KB : kc > PP ? PP : kc;
    fftw_complex *grid = fftw_alloc_complex(PP), *spec = fftw_alloc_complex(PP * LAG_TB);
    double *band = malloc(2 * T * kc * sizeof *band); /* (PP = 4 nsub^2 and kc: whole blocks of LAG_KB) */
    fftw_complex *acc = calloc(nlags * PP + 1, sizeof *acc);
    if (!grid || !spec || !band || !acc) {
        fftw_free(grid); fftw_free(spec); free(band); free(acc);
        return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory for the spectra of %zu frames", T);
    }
    swfs_planner_lock();
    /* the forward 2-D FFT as the nsub rows that hold slopes (the others are 0), then every column */
    const int len = (int)P;
    fftw_plan rows = fftw_plan_many_dft(1, &len, (int)nsub, grid, NULL, 1, len, spec, NULL, 1, len, FFTW_FORWARD,
                                        FFTW_ESTIMATE);
    fftw_plan cols = fftw_plan_many_dft(1, &len, len, spec, NULL, len, 1, spec, NULL, len, 1, FFTW_FORWARD, FFTW_ESTIMATE);
    fftw_plan inv = fftw_plan_dft_2d((int)P, (int)P, spec, grid, FFTW_BACKWARD, FFTW_ESTIMATE);
    swfs_planner_unlock();
    int rc = rows && cols && inv ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "wind: no FFT plan of %zu x %zu", P, P);
    /* z = x + i y on the grid (0 off the nv subapertures, and in the padding, which keeps the
     * displacements' +-(nsub - 1) from wrapping): Re sum_s conj z_t(s) z_(t+tau)(s + d) is
     * sum over the pairs at displacement d of x x' + y y', the pairs' lagged covariance */
    memset(grid, 0, PP * sizeof *grid); /* (the transforms out of it leave it as it is) */
    for (size_t k0 = 0; !rc && k0 < PP; k0 += kc) {
        const size_t nk = PP - k0 < kc ? PP - k0 : kc;
        for (size_t t0 = 0; t0 < T; t0 += LAG_TB) { /* LAG_TB frames' spectra, then into the band */
            const size_t nt = T - t0 < LAG_TB ? T - t0 : LAG_TB;
            for (size_t i = 0; i < nt; i++) {
                const size_t t = t0 + i;
                fftw_complex *sp = spec + i * PP;
                for (size_t p = 0; p < nv; p++) {
                    const size_t s = pos[p];
                    grid[(s / nsub) * P + s % nsub] = x[t * nv + p] + I * y[t * nv + p];
                }
                fftw_execute_dft(rows, grid, sp);
                memset(sp + nsub * P, 0, (PP - nsub * P) * sizeof *sp);
                fftw_execute_dft(cols, sp, sp);
            }
            for (size_t k = 0; k < nk; k++) {
                double *b = band + 2 * LAG_KB * ((k / LAG_KB) * T + t0) + k % LAG_KB;
                for (size_t i = 0; i < nt; i++) {
                    const double *sp = (const double *)(spec + i * PP + k0 + k);
                    b[2 * LAG_KB * i] = sp[0];
                    b[2 * LAG_KB * i + LAG_KB] = sp[1];
                }
            }
        }
        /* sum_t conj(z_t) z_(t+lag) per frequency and lag, in real arithmetic (C's complex
         * product checks for infinities), LAG_KB frequencies side by side (one vector) */
        for (size_t kb = 0; kb * LAG_KB < nk; kb++) {
            const double *z = band + 2 * LAG_KB * kb * T;
            for (size_t l = 0; l < nlags; l++) {
                const double *v = z + 2 * LAG_KB * lag[l];
                double re[LAG_KB] = {0}, im[LAG_KB] = {0};
                for (size_t t = 0; t < T - lag[l]; t++) {
                    const double *a = z + 2 * LAG_KB * t, *b = v + 2 * LAG_KB * t;
                    for (size_t j = 0; j < LAG_KB; j++) {
                        re[j] += a[j] * b[j] + a[LAG_KB + j] * b[LAG_KB + j];
                        im[j] += a[j] * b[LAG_KB + j] - a[LAG_KB + j] * b[j];
                    }
                }
                for (size_t j = 0; j < LAG_KB; j++) acc[l * PP + k0 + kb * LAG_KB + j] = re[j] + I * im[j];
            }
        }
    }
    for (size_t l = 0; !rc && l < nlags; l++) {
        memcpy(spec, acc + l * PP, PP * sizeof *spec);
        fftw_execute_dft(inv, spec, grid);
        for (size_t b = 0; b < nb; b++)
            for (size_t a = 0; a < nb; a++)
                sums[l * nb * nb + b * nb + a] = creal(grid[((b + P - R) % P) * P + (a + P - R) % P]) / (double)PP;
    }
    swfs_planner_lock();
    if (rows) fftw_destroy_plan(rows);
    if (cols) fftw_destroy_plan(cols);
    if (inv) fftw_destroy_plan(inv);
    swfs_planner_unlock();
    fftw_free(grid);
    fftw_free(spec);
    free(band);
    free(acc);
    return rc;
}

/* The whole grid's correlation maps at every lag of m.lag (swfs_wind_lag_sums_, normalized by
 * the bins' zero-lag deviations; NAN in a bin of no pair). */
static int lag_maps(wind_work *w, const size_t *pos)
{
    const size_t nbb = w->m.nb * w->m.nb;
    int rc = swfs_wind_lag_sums_(w->x, w->y, w->T, w->nv, pos, w->m.nsub, w->m.lag, w->m.nmaps, 0, w->maps);
    for (size_t l = 0; !rc && l < w->m.nmaps; l++)
        for (size_t b = 0; b < nbb; b++) {
            double *v = w->maps + l * nbb + b;
            *v = w->den[b] > 0 ? *v / w->den[b] : NAN;
        }
    return rc;
}

/* The tracker's peak at lag m.lag[l] into *L, on the map's inner +-R: the highest bin, or
 * while tracking (tol > 0) the highest within tol subapertures of the predicted (px, py);
 * inside when it is a local maximum off that window's edge (while tracking, another layer's
 * peak elsewhere in the map is not this one's). */
static void track_lag(wind_work *w, size_t l, double px, double py, double tol, swfs_wind_lag *L)
{
    const double *map = w->maps + l * w->m.nb * w->m.nb;
    const size_t nb = w->nb, nbb = w->m.nb, off = w->m.R - w->R;
    const double R = (double)w->R;
    size_t best = SIZE_MAX, bi = 0, bj = 0;
    for (size_t j = 0; j < nb; j++)
        for (size_t i = 0; i < nb; i++) {
            const size_t b = (j + off) * nbb + i + off;
            if (isnan(map[b])) continue;
            if (tol > 0 && hypot((double)i - R - px, (double)j - R - py) > tol) continue;
            if (best == SIZE_MAX || map[b] > map[best]) { best = b; bi = i; bj = j; }
        }
    L->lag = w->m.lag[l];
    L->inside = 0;
    L->dx = L->dy = NAN;
    L->corr = best == SIZE_MAX ? NAN : map[best];
    if (best == SIZE_MAX) return;
    L->dx = (double)bi - R;
    L->dy = (double)bj - R;
    if (bi == 0 || bj == 0 || bi + 1 == nb || bj + 1 == nb) return;
    const size_t nbh[4] = {best - 1, best + 1, best - nbb, best + nbb};
    for (int k = 0; k < 4; k++)
        if (isnan(map[nbh[k]]) || map[nbh[k]] > map[best]) return;
    L->inside = 1;
    L->dx += swfs_wind_vertex_(map[best - 1], map[best], map[best + 1]);
    L->dy += swfs_wind_vertex_(map[best - nbb], map[best], map[best + nbb]);
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
    free(w->x); free(w->y); free(w->den); free(w->count); free(w->maps);
}

int swfs_wind_from_slopes(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                          const unsigned char *valid, double pitch, double rate, swfs_wind_estimate *out)
{
    if (!slopes || !out) return swfs_fail(SWFS_ERR_ARG, "wind: no slopes or no result");
    memset(out, 0, sizeof *out);
    out->tracked_signif = NAN;
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
    w.m.nsub = nsub;
    w.m.R = nsub - 1;
    w.m.nb = 2 * w.m.R + 1;
    /* the lags: 2^k and 3 x 2^k up to a quarter of the series (wind_internal.h) */
    for (size_t p2 = 1; p2 <= nframes / 4 && w.m.nmaps < SWFS_WIND_MAXMAPS; p2 *= 2) {
        w.m.lag[w.m.nmaps++] = p2;
        if (p2 > 1 && 3 * p2 / 2 <= nframes / 4 && w.m.nmaps < SWFS_WIND_MAXMAPS) w.m.lag[w.m.nmaps++] = 3 * p2 / 2;
    }
    const size_t nbb = w.m.nb * w.m.nb;
    w.x = malloc(nframes * nv * sizeof *w.x);
    w.y = malloc(nframes * nv * sizeof *w.y);
    double *sd = malloc(nv * sizeof *sd);
    w.den = calloc(nbb, sizeof *w.den);
    w.count = calloc(nbb, sizeof *w.count);
    w.maps = malloc((w.m.nmaps ? w.m.nmaps : 1) * nbb * sizeof *w.maps);
    if (!w.x || !w.y || !sd || !w.den || !w.count || !w.maps) {
        free(col);
        free(sd);
        work_free(&w);
        return swfs_fail(SWFS_ERR_NOMEM, "wind: out of memory for %zu frames of %zu subapertures", nframes, nv);
    }
    w.m.map = w.maps;
    w.m.count = w.count;
    for (size_t t = 0; t < nframes; t++)
        for (size_t p = 0; p < nv; p++) {
            w.x[t * nv + p] = slopes[t * nslopes + col[p]];
            w.y[t * nv + p] = slopes[t * nslopes + nslopes / 2 + col[p]];
        }
    centre(w.x, nframes, nv);
    centre(w.y, nframes, nv);
    /* The bins' normalization: the pairs' zero-lag standard deviations. */
    for (size_t p = 0; p < nv; p++) {
        double s = 0;
        for (size_t t = 0; t < nframes; t++) s += w.x[t * nv + p] * w.x[t * nv + p] + w.y[t * nv + p] * w.y[t * nv + p];
        sd[p] = sqrt(s);
    }
    size_t nvary = 0; /* (on the slopes as given: centring leaves a constant's rounding) */
    for (size_t p = 0; p < nv; p++) {
        const double x0 = slopes[col[p]], y0 = slopes[nslopes / 2 + col[p]];
        int varies = 0;
        for (size_t t = 1; !varies && t < nframes; t++)
            varies = slopes[t * nslopes + col[p]] != x0 || slopes[t * nslopes + nslopes / 2 + col[p]] != y0;
        nvary += (size_t)varies;
    }
    if (nvary < 8) {
        free(col);
        free(sd);
        work_free(&w);
        return swfs_fail(SWFS_ERR_VALUE, "wind: the slopes of %zu of the %zu subapertures with signal vary in time; need "
                         "at least 8 (constant slopes carry no flow)", nvary, nv);
    }
    const long R = (long)w.m.R;
    for (size_t p = 0; p < nv; p++)
        for (size_t q = 0; q < nv; q++) {
            const size_t sp = pos[p], sq = pos[q];
            const long a = (long)(sq % nsub) - (long)(sp % nsub), b = (long)(sq / nsub) - (long)(sp / nsub);
            const size_t bi = (size_t)(b + R) * w.m.nb + (size_t)(a + R);
            w.den[bi] += sd[p] * sd[q];
            w.count[bi]++;
        }
    free(sd);
    /* every lag's map at once (the tracker takes the powers of two, the stacking every one) */
    int rc = lag_maps(&w, pos);
    free(col);
    if (rc) {
        work_free(&w);
        return rc;
    }
    out->nvalid = nv;
    out->radius = w.R;
    /* Doubling lags; tracking from the first resolved displacement (wind.h). */
    double ux = 0, uy = 0;
    for (size_t l = 0; l < w.m.nmaps && out->nlags < SWFS_WIND_MAXLAGS; l++) {
        const size_t tau = w.m.lag[l];
        if (tau & (tau - 1)) continue; /* the tracker takes the powers of two */
        /* Tracking stops where the predicted peak would leave the inner map: its neighbours
         * and enough overlapping pairs are needed to place it. */
        const double px = ux * (double)tau, py = uy * (double)tau;
        if (out->nused && (fabs(px) > (double)(w.R - 1) || fabs(py) > (double)(w.R - 1))) break;
        swfs_wind_lag *L = &out->lag[out->nlags++];
        track_lag(&w, l, px, py, out->nused ? 0.5 * hypot(px, py) : 0.0, L);
        /* A lag whose peak is lost (not a maximum off the window's edge, or the vertex moved
         * out of the window) ends the tracking once two lags give the velocity; with one, the
         * next lag is tried from the same prediction: two layers of similar speeds in other
         * directions make one peak between them at the short lags, which the longer ones part
         * (docs/telemetry.md, "The wind from the slopes"). */
        if (!L->inside) {
            if (out->nused >= 2) break;
            continue;
        }
        if (!out->nused && hypot(L->dx, L->dy) < 1) continue;
        if (out->nused && hypot(L->dx - px, L->dy - py) > 0.5 * hypot(px, py)) {
            if (out->nused >= 2) break; /* the vertex moved out */
            continue;
        }
        L->used = 1;
        out->nused++;
        fit_velocity(out, &ux, &uy);
    }
    if (out->nused >= 2) {
        out->found = 1;
        out->vx = ux * pitch * rate;
        out->vy = uy * pitch * rate;
        out->speed = hypot(out->vx, out->vy);
        double dir = atan2(out->vy, out->vx) * 180.0 / M_PI;
        out->direction = dir < 0 ? dir + 360.0 : dir;
        rc = swfs_wind_stack_layers_(&w.m, pitch, rate, out);
    }
    work_free(&w);
    return rc;
}

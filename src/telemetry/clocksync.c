/* The camera clock against the WFS clock by tip-tilt cross-correlation (Sec. 4.2): see
 * include/specklewfs/clocksync.h. */
#include "specklewfs/clocksync.h"
#include "specklewfs/atomic.h"
#include "specklewfs/numeric.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_clock_params_default(swfs_clock_params *p)
{
    p->offset_min = -0.01;
    p->offset_max = 0.01;
    p->drift_max = 5e-4;
}

int64_t swfs_clock_to_wfs(const swfs_clock *c, int64_t cam_ns)
{
    const double t = 1e-9 * (double)(cam_ns - c->epoch);
    return c->epoch + (int64_t)llround(1e9 * (t * (1.0 + c->drift) + c->offset));
}

/* A linear clock segment of a stream: frames [k0, k1) of the input, t = a + P (cnt - c0). */
typedef struct cseg {
    size_t k0, k1;
    uint64_t c0, c1;
    double a, P;
    double *C[2], *m[2]; /* WFS: prefix sums and dense per-frame means over cnt c0 .. c1 */
} cseg;

typedef struct ctx {
    const swfs_clock_data *d;
    double *tw, *tc;      /* stamps [s] from the epoch */
    cseg *ws, *cs;
    size_t nws, ncs;
    double exptime;
    double *px, *py;      /* exposure means of the camera frames (scratch) */
    unsigned char *in;
} ctx;

/* Median frame period of stamps t over counters c (pairs with increasing counters). */
static double median_period(const uint64_t *c, const double *t, size_t n)
{
    double *v = malloc((n ? n : 1) * sizeof *v);
    size_t m = 0;
    if (!v) return NAN;
    for (size_t k = 1; k < n; k++)
        if (c[k] > c[k - 1]) v[m++] = (t[k] - t[k - 1]) / (double)(c[k] - c[k - 1]);
    const double p = m ? swfs_median_inplace(v, m) : NAN;
    free(v);
    return p;
}

/* Segments: a new one where the counter goes back or a stamp is off the period by more than
 * half a period; each fitted by least squares. *jitter: rms residual. */
static int segments(const uint64_t *c, const double *t, size_t n, cseg **out, size_t *nseg, double *period,
                    double *jitter)
{
    const double P = median_period(c, t, n);
    if (!(P > 0)) return swfs_fail(SWFS_ERR_VALUE, "no two frames with increasing counters and stamps");
    cseg *s = calloc(n, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    size_t ns = 0;
    double r2 = 0;
    for (size_t k = 0; k < n; k++) {
        const int fresh = k == 0 || c[k] <= c[k - 1] ||
                          fabs(t[k] - t[k - 1] - (double)(c[k] - c[k - 1]) * P) > 0.5 * P;
        if (fresh) s[ns++] = (cseg){.k0 = k, .c0 = c[k]};
        s[ns - 1].k1 = k + 1;
        s[ns - 1].c1 = c[k];
    }
    for (size_t q = 0; q < ns; q++) {
        cseg *g = &s[q];
        const size_t m = g->k1 - g->k0;
        double mx = 0, mt = 0, sxx = 0, sxt = 0;
        for (size_t k = g->k0; k < g->k1; k++) { mx += (double)(c[k] - g->c0); mt += t[k]; }
        mx /= (double)m;
        mt /= (double)m;
        for (size_t k = g->k0; k < g->k1; k++) {
            const double x = (double)(c[k] - g->c0) - mx;
            sxx += x * x;
            sxt += x * (t[k] - mt);
        }
        g->P = m >= 2 && sxx > 0 ? sxt / sxx : P;
        g->a = mt - g->P * mx;
        for (size_t k = g->k0; k < g->k1; k++) {
            const double e = t[k] - g->a - g->P * (double)(c[k] - g->c0);
            r2 += e * e;
        }
    }
    *out = s;
    *nseg = ns;
    *period = P;
    *jitter = sqrt(r2 / (double)n);
    return SWFS_OK;
}

/* The WFS segments' dense mean slopes (a dropped frame repeats the previous one) and prefix sums. */
static int wfs_sums(ctx *x)
{
    for (size_t q = 0; q < x->nws; q++) {
        cseg *g = &x->ws[q];
        const size_t n = (size_t)(g->c1 - g->c0) + 1;
        for (int a = 0; a < 2; a++) {
            g->m[a] = malloc(n * sizeof(double));
            g->C[a] = malloc((n + 1) * sizeof(double));
            if (!g->m[a] || !g->C[a]) return swfs_fail(SWFS_ERR_NOMEM, "clock fit: out of memory for %zu WFS frames", n);
            const double *src = a ? x->d->my : x->d->mx;
            size_t k = g->k0;
            double last = src[k];
            g->C[a][0] = 0;
            for (size_t i = 0; i < n; i++) {
                if (k < g->k1 && x->d->wcnt[k] == g->c0 + i) last = src[k++];
                g->m[a][i] = last;
                g->C[a][i + 1] = g->C[a][i] + last;
            }
        }
    }
    return SWFS_OK;
}

static double cum(const cseg *g, int a, double u)
{
    const double fl = floor(u);
    const size_t i = (size_t)fl;
    const size_t n = (size_t)(g->c1 - g->c0) + 1;
    return i >= n ? g->C[a][n] : g->C[a][i] + (u - fl) * g->m[a][i];
}

/* Exposure-mean slopes of camera frame j at (offset, drift); 0 when it is not inside one WFS segment. */
static int exposure_mean(const ctx *x, size_t j, double off, double drift, double *px, double *py)
{
    const double t1 = x->tc[j] * (1.0 + drift) + off, t0 = t1 - x->exptime * (1.0 + drift);
    for (size_t q = 0; q < x->nws; q++) {
        const cseg *g = &x->ws[q];
        const double u0 = (t0 - g->a) / g->P + 1.0, u1 = (t1 - g->a) / g->P + 1.0;
        const double n = (double)(g->c1 - g->c0) + 1.0;
        if (u0 < 0 || u1 > n) continue;
        *px = (cum(g, 0, u1) - cum(g, 0, u0)) / (u1 - u0);
        *py = (cum(g, 1, u1) - cum(g, 1, u0)) / (u1 - u0);
        return 1;
    }
    return 0;
}

typedef struct acc4 {
    double s[4], vt[2], vp[2];
    size_t n;
} acc4;

/* Pooled co-moments of (track, exposure means) over camera segments [s0, s1), each
 * segment's means removed. */
static void score(ctx *x, size_t s0, size_t s1, double off, double drift, acc4 *a)
{
    memset(a, 0, sizeof *a);
    const double *tx = x->d->tx, *ty = x->d->ty;
    for (size_t q = s0; q < s1; q++) {
        const cseg *g = &x->cs[q];
        double m[4] = {0, 0, 0, 0};
        size_t n = 0;
        for (size_t j = g->k0; j < g->k1; j++) {
            x->in[j] = (unsigned char)exposure_mean(x, j, off, drift, &x->px[j], &x->py[j]);
            if (!x->in[j]) continue;
            m[0] += tx[j]; m[1] += ty[j]; m[2] += x->px[j]; m[3] += x->py[j];
            n++;
        }
        if (n < 2) continue;
        for (int k = 0; k < 4; k++) m[k] /= (double)n;
        for (size_t j = g->k0; j < g->k1; j++) {
            if (!x->in[j]) continue;
            const double a0 = tx[j] - m[0], a1 = ty[j] - m[1], p0 = x->px[j] - m[2], p1 = x->py[j] - m[3];
            a->s[0] += a0 * p0; a->s[1] += a0 * p1; a->s[2] += a1 * p0; a->s[3] += a1 * p1;
            a->vt[0] += a0 * a0; a->vt[1] += a1 * a1; a->vp[0] += p0 * p0; a->vp[1] += p1 * p1;
        }
        a->n += n;
    }
}

static void corr4(const acc4 *a, double c[4])
{
    for (int t = 0; t < 2; t++)
        for (int p = 0; p < 2; p++) {
            const double den = sqrt(a->vt[t] * a->vp[p]);
            c[2 * t + p] = den > 0 ? a->s[2 * t + p] / den : 0;
        }
}

/* The better of the straight and the swapped pairing (as sync.c). */
static double best(const double c[4], int *swap)
{
    const double straight = fabs(c[0]) + fabs(c[3]), swapped = fabs(c[1]) + fabs(c[2]);
    if (swap) *swap = swapped > straight;
    return swapped > straight ? swapped : straight;
}

typedef struct opt {
    double off, drift, score;
} opt;

static void grid(ctx *x, size_t s0, size_t s1, double o0, double o1, double dO, double d0, double d1, double dd, opt *b)
{
    const size_t no = (size_t)floor((o1 - o0) / dO + 1e-9) + 1, nd = dd > 0 ? (size_t)floor((d1 - d0) / dd + 1e-9) + 1 : 1;
    for (size_t i = 0; i < no; i++)
        for (size_t k = 0; k < nd; k++) {
            const double o = o0 + (double)i * dO, d = d0 + (double)k * dd;
            acc4 a;
            score(x, s0, s1, o, d, &a);
            if (a.n < 4) continue;
            double c[4];
            corr4(&a, c);
            const double s = best(c, NULL);
            if (s > b->score) *b = (opt){o, d, s};
        }
}

/* The fit's uncertainty from the camera segments' own best offsets at the fitted drift. */
static void segment_errors(ctx *x, swfs_clock *c)
{
    double so = 0, st = 0, stt = 0, sto = 0, soo = 0;
    size_t n = 0;
    const double P = c->wfs_period;
    for (size_t q = 0; q < x->ncs; q++) {
        opt b = {c->offset, c->drift, -1};
        grid(x, q, q + 1, c->offset - 0.5 * P, c->offset + 0.5 * P, P / 200, c->drift, c->drift, 0, &b);
        if (!(b.score > 0)) continue;
        double tau = 0;
        for (size_t j = x->cs[q].k0; j < x->cs[q].k1; j++) tau += x->tc[j];
        tau /= (double)(x->cs[q].k1 - x->cs[q].k0);
        so += b.off; st += tau; stt += tau * tau; sto += tau * b.off; soo += b.off * b.off;
        n++;
    }
    c->offset_err = c->drift_err = NAN;
    if (n < 3) return;
    const double mt = st / (double)n, mo = so / (double)n, Stt = stt - (double)n * mt * mt,
                 Sto = sto - (double)n * mt * mo, Soo = soo - (double)n * mo * mo;
    if (!(Stt > 0)) return;
    const double s2 = fmax(Soo - Sto * Sto / Stt, 0) / (double)(n - 2);
    c->drift_err = sqrt(s2 / Stt);
    c->offset_err = sqrt(s2 * (1.0 / (double)n + mt * mt / Stt));
}

/* Pairing, correlations and the track's residual at the fitted clock. */
static void finish(ctx *x, swfs_clock *c)
{
    acc4 a;
    score(x, 0, x->ncs, c->offset, c->drift, &a);
    double r[4];
    corr4(&a, r);
    int swap = 0;
    best(r, &swap);
    swfs_sync_result *f = &c->fit;
    f->swap = swap;
    f->corr_x = swap ? r[1] : r[0];
    f->corr_y = swap ? r[2] : r[3];
    f->sign_x = f->corr_x >= 0 ? 1 : -1;
    f->sign_y = f->corr_y >= 0 ? 1 : -1;
    for (int k = 0; k < 4; k++) f->corr4[k] = fabs(r[k]);
    const int px = swap ? 1 : 0, py = swap ? 0 : 1;
    const double sx = a.s[swap ? 1 : 0], sy = a.s[swap ? 2 : 3];
    const double rx = a.vt[0] - (a.vp[px] > 0 ? sx * sx / a.vp[px] : 0);
    const double ry = a.vt[1] - (a.vp[py] > 0 ? sy * sy / a.vp[py] : 0);
    c->resid = a.n ? sqrt(fmax(rx + ry, 0) / (double)(2 * a.n)) : NAN;
    c->nused = a.n;
    size_t ns = 0;
    for (size_t q = 0; q < x->ncs; q++) {
        size_t m = 0;
        for (size_t j = x->cs[q].k0; j < x->cs[q].k1; j++) m += x->in[j];
        ns += m >= 2;
    }
    c->nsegments = ns;
}

static void ctx_free(ctx *x)
{
    for (size_t q = 0; x->ws && q < x->nws; q++)
        for (int a = 0; a < 2; a++) {
            free(x->ws[q].m[a]);
            free(x->ws[q].C[a]);
        }
    free(x->ws);
    free(x->cs);
    free(x->tw);
    free(x->tc);
    free(x->px);
    free(x->py);
    free(x->in);
}

static int setup(ctx *x, const swfs_clock_data *d, swfs_clock *c)
{
    x->d = d;
    c->epoch = d->cst[0] / 1000000000LL * 1000000000LL;
    x->tw = malloc(d->nwfs * sizeof *x->tw);
    x->tc = malloc(d->ncam * sizeof *x->tc);
    x->px = malloc(d->ncam * sizeof *x->px);
    x->py = malloc(d->ncam * sizeof *x->py);
    x->in = calloc(d->ncam, 1);
    if (!x->tw || !x->tc || !x->px || !x->py || !x->in) return swfs_fail(SWFS_ERR_NOMEM, "clock fit: out of memory");
    for (size_t k = 0; k < d->nwfs; k++) x->tw[k] = 1e-9 * (double)(d->wst[k] - c->epoch);
    for (size_t j = 0; j < d->ncam; j++) x->tc[j] = 1e-9 * (double)(d->cst[j] - c->epoch);
    for (size_t j = 0; j < d->ncam; j++)
        if (!isfinite(d->tx[j]) || !isfinite(d->ty[j]))
            return swfs_fail(SWFS_ERR_VALUE, "clock fit: star position of camera frame %zu is not finite", j);
    for (size_t k = 0; k < d->nwfs; k++)
        if (!isfinite(d->mx[k]) || !isfinite(d->my[k]))
            return swfs_fail(SWFS_ERR_VALUE, "clock fit: mean slope of WFS frame %zu is not finite", k);
    int rc = segments(d->wcnt, x->tw, d->nwfs, &x->ws, &x->nws, &c->wfs_period, &c->wfs_jitter);
    if (rc) return swfs_fail_context(rc, "WFS stamps");
    if ((rc = segments(d->ccnt, x->tc, d->ncam, &x->cs, &x->ncs, &c->cam_period, &c->cam_jitter)))
        return swfs_fail_context(rc, "camera stamps");
    x->exptime = c->exptime = d->exptime > 0 ? d->exptime : c->cam_period;
    return wfs_sums(x);
}

int swfs_clock_estimate(const swfs_clock_data *d, const swfs_clock_params *p, swfs_clock *c)
{
    memset(c, 0, sizeof *c);
    if (d->nwfs < 2 || d->ncam < 4)
        return swfs_fail(SWFS_ERR_ARG, "clock fit: %zu WFS and %zu camera frames (needs >= 2 and >= 4)", d->nwfs, d->ncam);
    if (!(p->offset_max >= p->offset_min) || !isfinite(p->offset_min) || !isfinite(p->offset_max) ||
        !(p->drift_max >= 0 && p->drift_max < 0.1))
        return swfs_fail(SWFS_ERR_ARG, "clock fit: offset range [%g, %g] s and drift range +-%g are invalid (min <= "
                         "max, |drift| < 0.1)", p->offset_min, p->offset_max, p->drift_max);
    c->ncam = d->ncam;
    ctx x;
    memset(&x, 0, sizeof x);
    int rc = setup(&x, d, c);
    if (rc) {
        ctx_free(&x);
        return rc;
    }
    /* Coarse grid: at most ~40 steps per axis, a quarter of a WFS period (in offset, and in
     * the drift's shift across the camera data) where the range allows; then refined 10x
     * around the best until both steps are 100x finer than that. */
    const double P = c->wfs_period, T = x.tc[d->ncam - 1] - x.tc[0];
    double dO = fmax(0.25 * P, (p->offset_max - p->offset_min) / 40), dd = 0;
    if (p->drift_max > 0 && T > 0) dd = fmax(0.25 * P / T, 2 * p->drift_max / 40);
    opt b = {NAN, NAN, -1};
    grid(&x, 0, x.ncs, p->offset_min, p->offset_max, dO, dd > 0 ? -p->drift_max : 0, dd > 0 ? p->drift_max : 0, dd,
         &b);
    if (!(b.score > 0)) {
        char a0[40], a1[40], w0[40], w1[40];
        swfs_time_format_ns(d->cst[0], a0, sizeof a0);
        swfs_time_format_ns(d->cst[d->ncam - 1], a1, sizeof a1);
        swfs_time_format_ns(d->wst[0], w0, sizeof w0);
        swfs_time_format_ns(d->wst[d->nwfs - 1], w1, sizeof w1);
        ctx_free(&x);
        return swfs_fail(SWFS_ERR_VALUE, "no camera exposure (stamps %s .. %s s) lies inside the WFS data (%s .. %s s) "
                         "for any clock offset in [%g, %g] s and drift within +-%g: the logs do not overlap in time",
                         a0, a1, w0, w1, p->offset_min, p->offset_max, p->drift_max);
    }
    while (dO > 0.0025 * P || dd > 0.0025 * P / T) {
        const double o0 = b.off - 2 * dO, d0 = b.drift - 2 * dd;
        dO /= 10;
        dd /= 10;
        grid(&x, 0, x.ncs, o0, o0 + 40 * dO, dO, d0, d0 + 40 * dd, dd, &b);
    }
    c->offset = b.off;
    c->drift = b.drift;
    finish(&x, c);
    segment_errors(&x, c);
    ctx_free(&x);
    return SWFS_OK;
}

int swfs_clock_write(const char *path, const swfs_clock *c, const char *note)
{
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    FILE *f = swfs_atomic_stream(a);
    char ep[40];
    swfs_time_format_ns(c->epoch, ep, sizeof ep);
    fprintf(f, "# specklewfs clock (sync --wfs-log): t_wfs = epoch + (t_cam - epoch) (1 + drift) + offset [s]\n");
    if (note) fprintf(f, "# %s\n", note);
    fprintf(f, "epoch %s\noffset %.9e %.3e\ndrift %.9e %.3e\nexptime %.9e\n", ep, c->offset, c->offset_err, c->drift,
            c->drift_err, c->exptime);
    fprintf(f, "# pairing SWAP SIGN_X SIGN_Y CORR_X CORR_Y  (SWAP 1: camera x follows the y slopes)\n");
    fprintf(f, "pairing %d %d %d %.4f %.4f\n", c->fit.swap, c->fit.sign_x, c->fit.sign_y, c->fit.corr_x, c->fit.corr_y);
    fprintf(f, "# resid: rms of the track about the exposure-mean slopes [pixels]; periods, jitter [s]: WFS camera\n");
    fprintf(f, "resid %.6g\nperiods %.9e %.9e\njitter %.3e %.3e\nframes %zu %zu %zu\n", c->resid, c->wfs_period,
            c->cam_period, c->wfs_jitter, c->cam_jitter, c->nused, c->ncam, c->nsegments);
    return swfs_atomic_commit(a);
}

int swfs_clock_read(const char *path, swfs_clock *c)
{
    memset(c, 0, sizeof *c);
    c->fit.sign_x = c->fit.sign_y = 1;
    if (swfs_input_check(path, "clock file")) return SWFS_ERR_IO;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the clock file: %s", path, strerror(errno));
    char line[1024], key[32], v1[64];
    long lineno = 0;
    int rc = SWFS_OK, have = 0;
    while (!rc && fgets(line, sizeof line, f)) {
        lineno++;
        char *s = line;
        while (*s == ' ' || *s == '\t') s++;
        if (*s == '#' || *s == '\n' || !*s) continue;
        int ok = sscanf(s, "%31s %63s", key, v1) == 2;
        const char *rest = s + strlen(key);
        if (ok && !strcmp(key, "epoch")) { ok = swfs_time_parse_ns(v1, &c->epoch) == 0; have |= 1; }
        else if (ok && !strcmp(key, "offset")) { ok = sscanf(rest, "%lf %lf", &c->offset, &c->offset_err) >= 1 && isfinite(c->offset); have |= 2; }
        else if (ok && !strcmp(key, "drift")) { ok = sscanf(rest, "%lf %lf", &c->drift, &c->drift_err) >= 1 && fabs(c->drift) < 0.1; have |= 4; }
        else if (ok && !strcmp(key, "exptime")) ok = sscanf(rest, "%lf", &c->exptime) == 1 && c->exptime >= 0;
        else if (ok && !strcmp(key, "pairing"))
            ok = sscanf(rest, "%d %d %d %lf %lf", &c->fit.swap, &c->fit.sign_x, &c->fit.sign_y, &c->fit.corr_x,
                        &c->fit.corr_y) == 5;
        else if (ok && (!strcmp(key, "resid") || !strcmp(key, "periods") || !strcmp(key, "jitter") || !strcmp(key, "frames")))
            ok = 1; /* informational */
        else ok = 0;
        if (!ok) rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: cannot parse \"%.80s\" (a clock file of sync --wfs-log)", path,
                                lineno, s);
    }
    fclose(f);
    if (!rc && have != 7)
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: a clock file needs 'epoch', 'offset' and 'drift' lines (sync --wfs-log)", path);
    return rc;
}

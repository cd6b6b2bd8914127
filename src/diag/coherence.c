/* Speckle coherence diagnostics: see include/specklewfs/coherence.h and docs/coherence.md. */
#include "../core/planner.h"
#include "specklewfs/numeric.h"
#include "specklewfs/coherence.h"
#include "specklewfs/status.h"

#include <fftw3.h>
#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Pixels per batch: the time series of BLOCK neighbouring pixels are gathered interleaved
 * (stride BLOCK), so the gather from the frame-major cube reads BLOCK contiguous values per
 * frame and one FFTW "many" plan transforms the whole batch. */
#define BLOCK 32

void swfs_coh_default_lags(long *lags)
{
    size_t n = 0;
    for (long k = 0; k <= 20; k++) lags[n++] = k;
    for (long k = 25; k <= 100; k += 5) lags[n++] = k;
}

void swfs_coh_options_default(swfs_coh_options *o)
{
    memset(o, 0, sizeof *o);
    o->nfit = 4;
    o->min_power_rel = 1e-20;
    o->method = SWFS_COH_AUTO;
}

void swfs_coherence_free(swfs_coherence *c)
{
    if (!c) return;
    free(c->lag_frames);
    swfs_real_free(c->lags);
    swfs_real_free(c->mean_sp);
    swfs_real_free(c->tau0);
    swfs_real_free(c->trot);
    swfs_real_free(c->phrate);
    swfs_real_free(c->snr_fact);
    swfs_cplx_free(c->mcf);
    swfs_free(c->dense);
    free(c);
}

/* Smallest n >= m whose only prime factors are 2, 3, 5, 7 (fast FFTW sizes). */
static size_t good_fft_size(size_t m)
{
    for (size_t n = m;; n++) {
        size_t r = n;
        while (r % 2 == 0) r /= 2;
        while (r % 3 == 0) r /= 3;
        while (r % 5 == 0) r /= 5;
        while (r % 7 == 0) r /= 7;
        if (r == 1) return n;
    }
}

/* f(j) = (1 - j/m) Re gamma_j, zero at and beyond the exposure end m. */
static double snr_integrand(const double complex *gamma, size_t j, double m)
{
    double t = (double)j;
    return t >= m ? 0.0 : (1 - t / m) * creal(gamma[j]);
}

double swfs_coh_snr_factor(const double complex *gamma, size_t nlag, double framedt, double exposure)
{
    if (!(exposure > 0) || !(framedt > 0) || nlag == 0 || !isfinite(creal(gamma[0]))) return NAN;
    double m = exposure / framedt; /* exposure in WFS frames */
    double mr = nearbyint(m);
    if (mr >= 1 && fabs(m - mr) <= 1e-9 * mr) m = mr; /* an integer number of frames, to rounding */
    size_t full = (size_t)floor(m);
    double frac = m - (double)full;
    size_t need = frac > 0 ? full : full - 1; /* highest lag with a non-zero weight */
    if (need >= nlag) return NAN;
    /* Trapezoid on f(tau) = (1 - tau/T) Re gamma(tau) at the frame lags. For T = M frames
     * this is exactly (1/M)[1 + 2 sum_{0<k<M} (1 - k/M) Re gamma_k] = <|box mean of M
     * frames|^2> / <|psi|^2>: what an exposure of M WFS frames does to <psi I>. */
    double sum = 0;
    for (size_t k = 0; k < full; k++) sum += 0.5 * (snr_integrand(gamma, k, m) + snr_integrand(gamma, k + 1, m));
    if (frac > 0) sum += 0.5 * frac * snr_integrand(gamma, full, m); /* [full, m], f(m) = 0 */
    /* eq:MCF-SNReffect is (1/T) int ...; the factor 2 makes a fully coherent speckle give 1. */
    return 2 * sum / m;
}

double swfs_coh_median(const swfs_real *map)
{
    size_t n = swfs_real_size(map), m = 0;
    double *v = malloc((n ? n : 1) * sizeof *v);
    if (!v) return NAN;
    for (size_t i = 0; i < n; i++)
        if (!isnan(map->data[i])) v[m++] = map->data[i];
    double med = NAN;
    if (m) {
        swfs_sort_doubles(v, m);
        med = (m % 2) ? v[m / 2] : 0.5 * (v[m / 2 - 1] + v[m / 2]);
        if (isnan(med)) med = v[m / 2]; /* -Inf and +Inf in the middle: cannot happen here, but be safe */
    }
    free(v);
    return med;
}

/* ---- the per-pixel autocorrelation ----------------------------------- */

typedef struct coh_work {
    size_t nt, npix, L;       /* frames, pixels, max lag */
    size_t nfft;              /* FFT length (0: direct sums) */
    double complex *buf;      /* FFT: nfft x BLOCK; direct: nt x BLOCK */
    double complex *acc;      /* direct: (L + 1) x BLOCK */
    fftw_plan fwd, bwd;
} coh_work;

static void work_free(coh_work *w)
{
    swfs_planner_lock();
    if (w->fwd) fftw_destroy_plan(w->fwd);
    if (w->bwd) fftw_destroy_plan(w->bwd);
    swfs_planner_unlock();
    if (w->buf) fftw_free(w->buf);
    swfs_free(w->acc);
}

/* Raw autocorrelation sums R_k = sum_{t < nt-k} psi_t psi*_{t+k}, k = 0..L, for the BLOCK
 * series in w->buf (interleaved, zero beyond nt), into out[b * (L + 1) + k]. */
static void block_autocorr(coh_work *w, size_t nb, double complex *out)
{
    const size_t L = w->L;
    if (w->nfft) {
        /* Wiener-Khinchin: IFFT(|FFT(x)|^2)_k = n sum_t x_{t+k} x*_t, no wrap since
         * nfft >= nt + L; we want sum_t x_t x*_{t+k}, its conjugate. */
        fftw_execute(w->fwd);
        const size_t n = w->nfft * BLOCK;
        for (size_t i = 0; i < n; i++) {
            double re = creal(w->buf[i]), im = cimag(w->buf[i]);
            w->buf[i] = re * re + im * im;
        }
        fftw_execute(w->bwd);
        const double inv = 1.0 / (double)w->nfft;
        for (size_t b = 0; b < nb; b++)
            for (size_t k = 0; k <= L; k++) out[b * (L + 1) + k] = conj(w->buf[k * BLOCK + b]) * inv;
    } else {
        memset(w->acc, 0, (L + 1) * BLOCK * sizeof *w->acc);
        for (size_t t = 0; t < w->nt; t++) {
            const double complex *x = w->buf + t * BLOCK;
            size_t kmax = w->nt - 1 - t < L ? w->nt - 1 - t : L;
            for (size_t k = 0; k <= kmax; k++) {
                /* x y* written out on (re, im) pairs: C's complex multiply carries NaN/Inf
                 * recovery (__muldc3) that stops vectorization; the data here are finite. */
                const double *y = (const double *)(w->buf + (t + k) * BLOCK);
                const double *xr = (const double *)x;
                double *a = (double *)(w->acc + k * BLOCK);
                for (size_t b = 0; b < 2 * BLOCK; b += 2) {
                    a[b] += xr[b] * y[b] + xr[b + 1] * y[b + 1];
                    a[b + 1] += xr[b + 1] * y[b] - xr[b] * y[b + 1];
                }
            }
        }
        for (size_t b = 0; b < nb; b++)
            for (size_t k = 0; k <= L; k++) out[b * (L + 1) + k] = w->acc[k * BLOCK + b];
    }
}

static int work_init(coh_work *w, size_t nt, size_t npix, size_t L, int method)
{
    memset(w, 0, sizeof *w);
    w->nt = nt;
    w->npix = npix;
    w->L = L;
    size_t nfft = good_fft_size(nt + L);
    /* Operation counts per pixel: direct sums ~ 8 flops per (t, k) pair; two FFTs
     * ~ 5 n log2 n flops each plus the squared modulus. */
    double direct = 8.0 * (double)nt * (double)(L + 1) - 4.0 * (double)L * (double)(L + 1);
    double fft = 10.0 * (double)nfft * log2((double)nfft) + 3.0 * (double)nfft;
    int use_fft = method == SWFS_COH_FFT || (method == SWFS_COH_AUTO && fft < direct);
    if (use_fft) {
        w->nfft = nfft;
        w->buf = fftw_malloc(nfft * BLOCK * sizeof *w->buf);
        if (!w->buf) return swfs_fail(SWFS_ERR_NOMEM, "coherence: out of memory for FFT buffers (%zu x %d)", nfft, BLOCK);
        int n = (int)nfft;
        /* FFTW_ESTIMATE: planning is instant and deterministic and never touches the data. */
        swfs_planner_lock();
        w->fwd = fftw_plan_many_dft(1, &n, BLOCK, (fftw_complex *)w->buf, NULL, BLOCK, 1,
                                    (fftw_complex *)w->buf, NULL, BLOCK, 1, FFTW_FORWARD, FFTW_ESTIMATE);
        w->bwd = fftw_plan_many_dft(1, &n, BLOCK, (fftw_complex *)w->buf, NULL, BLOCK, 1,
                                    (fftw_complex *)w->buf, NULL, BLOCK, 1, FFTW_BACKWARD, FFTW_ESTIMATE);
        swfs_planner_unlock();
        if (!w->fwd || !w->bwd) return swfs_fail(SWFS_ERR_INTERNAL, "coherence: FFTW could not plan length %zu", nfft);
    } else {
        w->buf = fftw_malloc(nt * BLOCK * sizeof *w->buf);
        w->acc = swfs_malloc((L + 1) * BLOCK * sizeof *w->acc);
        if (!w->buf || !w->acc) return swfs_fail(SWFS_ERR_NOMEM, "coherence: out of memory for work buffers");
    }
    return SWFS_OK;
}

/* ---- per-pixel maps from the normalized MCF -------------------------- */

/* First crossing of |gamma| below e^{-1/2}, linear between frames; +Inf if none. */
static double pixel_tau0(const double complex *g, size_t L)
{
    const double level = exp(-0.5);
    double prev = cabs(g[0]);
    for (size_t k = 1; k <= L; k++) {
        double a = cabs(g[k]);
        if (a < level) return (double)(k - 1) + (prev - level) / (prev - a);
        prev = a;
    }
    return INFINITY;
}

/* Least-squares slope through the origin of the unwrapped phase over lags 1..nfit [rad/frame]. */
static double pixel_phase_rate(const double complex *g, int nfit)
{
    double ph = 0, num = 0, den = 0;
    for (int k = 1; k <= nfit; k++) {
        ph += carg(g[k] * conj(g[k - 1])); /* unwrap frame to frame: |step| < pi */
        num += k * ph;
        den += (double)k * k;
    }
    return num / den;
}

static int check_lags(const long *lags, size_t nlags)
{
    if (nlags == 0) return swfs_fail(SWFS_ERR_ARG, "coherence: the lag list is empty");
    if (lags[0] != 0) return swfs_fail(SWFS_ERR_ARG, "coherence: the first lag must be 0, not %ld", lags[0]);
    for (size_t i = 1; i < nlags; i++)
        if (lags[i] <= lags[i - 1])
            return swfs_fail(SWFS_ERR_ARG, "coherence: lags must increase strictly (lag %zu is %ld after %ld)", i,
                             lags[i], lags[i - 1]);
    return SWFS_OK;
}

int swfs_coherence_compute(const swfs_cplx *cube, double framedt, const swfs_coh_options *opt_in,
                           swfs_coherence **out)
{
    *out = NULL;
    swfs_coh_options opt;
    if (opt_in) opt = *opt_in;
    else swfs_coh_options_default(&opt);
    long deflags[SWFS_COH_DEFAULT_NLAGS];
    if (!opt.lags) {
        swfs_coh_default_lags(deflags);
        opt.lags = deflags;
        opt.nlags = SWFS_COH_DEFAULT_NLAGS;
    }
    if (!cube || !cube->data) return swfs_fail(SWFS_ERR_ARG, "coherence: no speckle cube");
    const size_t nx = cube->nx, ny = cube->ny, nt = cube->nz, npix = nx * ny;
    if (nt < 2) return swfs_fail(SWFS_ERR_SHAPE, "coherence: the speckle cube has %zu frame(s); at least 2 are needed", nt);
    if (!(framedt > 0) || !isfinite(framedt))
        return swfs_fail(SWFS_ERR_VALUE, "coherence: FRAMEDT must be a positive number of seconds, not %g", framedt);
    if (opt.nfit < 1) return swfs_fail(SWFS_ERR_ARG, "coherence: nfit must be at least 1, not %d", opt.nfit);
    if (opt.exposure < 0 || !isfinite(opt.exposure))
        return swfs_fail(SWFS_ERR_VALUE, "coherence: exposure must be >= 0 s, not %g", opt.exposure);
    if (opt.max_lag < 0) return swfs_fail(SWFS_ERR_ARG, "coherence: max_lag must be >= 0, not %ld", opt.max_lag);
    if (opt.method < SWFS_COH_AUTO || opt.method > SWFS_COH_DIRECT)
        return swfs_fail(SWFS_ERR_ARG, "coherence: unknown method %d", opt.method);
    int rc = check_lags(opt.lags, opt.nlags);
    if (rc) return rc;

    /* Lags: output lags beyond the cube are dropped; the dense range covers the output
     * lags, the phase fit and the exposure. */
    const long maxavail = (long)nt - 1;
    size_t nlags = 0;
    while (nlags < opt.nlags && opt.lags[nlags] <= maxavail) nlags++;
    long L = opt.max_lag ? opt.max_lag : opt.lags[nlags - 1];
    if (L < opt.lags[nlags - 1]) L = opt.lags[nlags - 1];
    if (L < opt.nfit) L = opt.nfit;
    if (opt.exposure > 0) {
        double m = opt.exposure / framedt;
        long need = (long)ceil(m - 1e-9 * m);
        if (need > maxavail)
            return swfs_fail(SWFS_ERR_ARG, "coherence: an exposure of %g s is %.4g WFS frames but the cube has "
                             "only %zu frames", opt.exposure, m, nt);
        if (L < need) L = need;
    }
    if (L > maxavail) L = maxavail;
    const size_t Ld = (size_t)L;

    swfs_coherence *c = calloc(1, sizeof *c);
    if (!c) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    c->nx = nx; c->ny = ny; c->nframes = nt; c->framedt = framedt;
    c->nlags = nlags;
    c->max_lag = L;
    c->nfit = opt.nfit < L ? opt.nfit : (int)L;
    c->exposure = opt.exposure;
    c->lag_frames = malloc(nlags * sizeof *c->lag_frames);
    c->lags = swfs_real_alloc(nlags, 1, 1);
    c->mean_sp = swfs_real_alloc(nx, ny, 1);
    c->tau0 = swfs_real_alloc(nx, ny, 1);
    c->trot = swfs_real_alloc(nx, ny, 1);
    c->phrate = swfs_real_alloc(nx, ny, 1);
    if (opt.exposure > 0) c->snr_fact = swfs_real_alloc(nx, ny, 1);
    c->mcf = swfs_cplx_alloc(nx, ny, nlags);
    if (npix > ((size_t)-1) / sizeof(double complex) / (Ld + 1)) {
        swfs_coherence_free(c);
        return swfs_fail(SWFS_ERR_NOMEM, "coherence: %zu pixels x %zu lags is too large", npix, Ld + 1);
    }
    c->dense = swfs_malloc(npix * (Ld + 1) * sizeof *c->dense);
    double complex *mean = swfs_calloc(npix, sizeof *mean);
    unsigned char *bad = calloc(npix, 1);
    coh_work w;
    memset(&w, 0, sizeof w);
    if (!c->lag_frames || !c->lags || !c->mean_sp || !c->tau0 || !c->trot || !c->phrate || !c->mcf || !c->dense ||
        !mean || !bad || (opt.exposure > 0 && !c->snr_fact)) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "coherence: out of memory for %zux%zu pixels x %zu lags", nx, ny, Ld + 1);
        goto done;
    }
    for (size_t i = 0; i < nlags; i++) {
        c->lag_frames[i] = opt.lags[i];
        c->lags->data[i] = (double)opt.lags[i] * framedt;
    }

    /* Per-pixel time mean (eq:zeroMean: the speckles are zero-mean by construction; we
     * subtract what remains) and non-finite values, in one pass over the frame-major cube. */
    for (size_t t = 0; t < nt; t++) {
        const double complex *f = cube->data + t * npix;
        for (size_t p = 0; p < npix; p++) {
            if (!isfinite(creal(f[p])) || !isfinite(cimag(f[p]))) bad[p] = 1;
            else mean[p] += f[p];
        }
    }
    for (size_t p = 0; p < npix; p++) mean[p] /= (double)nt;

    if ((rc = work_init(&w, nt, npix, Ld, opt.method))) goto done;
    c->method = w.nfft ? SWFS_COH_FFT : SWFS_COH_DIRECT;
    const size_t tfill = w.nfft ? w.nfft : nt;
    for (size_t p0 = 0; p0 < npix; p0 += BLOCK) {
        size_t nb = npix - p0 < BLOCK ? npix - p0 : BLOCK;
        for (size_t t = 0; t < nt; t++) {
            const double complex *f = cube->data + t * npix + p0;
            double complex *dst = w.buf + t * BLOCK;
            for (size_t b = 0; b < nb; b++) dst[b] = bad[p0 + b] ? 0 : f[b] - mean[p0 + b];
            for (size_t b = nb; b < BLOCK; b++) dst[b] = 0;
        }
        if (tfill > nt) memset(w.buf + nt * BLOCK, 0, (tfill - nt) * BLOCK * sizeof *w.buf);
        block_autocorr(&w, nb, c->dense + p0 * (Ld + 1));
    }

    /* Unbiased in count: Gamma_k = R_k / (nt - k); then normalize by Gamma_0. */
    double gmax = 0;
    for (size_t p = 0; p < npix; p++) {
        double g0 = creal(c->dense[p * (Ld + 1)]) / (double)nt;
        if (!bad[p] && g0 > gmax) gmax = g0;
    }
    const double pmin = opt.min_power_rel * gmax;
    for (size_t p = 0; p < npix; p++) {
        double complex *g = c->dense + p * (Ld + 1);
        double g0 = creal(g[0]) / (double)nt;
        if (bad[p] || !(g0 > pmin) || !(g0 > 0)) {
            if (bad[p]) c->n_nonfinite++;
            else c->n_nopower++;
            for (size_t k = 0; k <= Ld; k++) g[k] = NAN;
            c->mean_sp->data[p] = bad[p] ? NAN : 0.0;
            c->tau0->data[p] = c->trot->data[p] = c->phrate->data[p] = NAN;
            if (c->snr_fact) c->snr_fact->data[p] = NAN;
            continue;
        }
        c->n_valid++;
        for (size_t k = 0; k <= Ld; k++) g[k] = g[k] / (double)(nt - k) / g0;
        g[0] = 1.0;
        c->mean_sp->data[p] = g0;
        double tau0 = pixel_tau0(g, Ld);
        if (isinf(tau0)) c->n_tau0_beyond++;
        c->tau0->data[p] = tau0 * framedt;
        double rate = pixel_phase_rate(g, c->nfit) / framedt;
        c->phrate->data[p] = rate;
        /* no rotation, or one slower than single precision spans (TROT is written at BITPIX
         * -32, which refuses a finite value it would store as infinite): +Inf */
        const double trot = (M_PI / 2) / fabs(rate);
        c->trot->data[p] = rate != 0 && trot <= FLT_MAX ? trot : INFINITY;
        if (c->snr_fact) c->snr_fact->data[p] = swfs_coh_snr_factor(g, Ld + 1, framedt, opt.exposure);
    }
    for (size_t i = 0; i < nlags; i++) {
        double complex *m = swfs_cplx_frame(c->mcf, i);
        for (size_t p = 0; p < npix; p++) m[p] = c->dense[p * (Ld + 1) + (size_t)c->lag_frames[i]];
    }
    /* a cube without one pixel to measure gives maps of NaN only: said, not written */
    rc = c->n_valid ? SWFS_OK
                    : swfs_fail(SWFS_ERR_VALUE, "coherence: no pixel of the %zu x %zu speckle cube has speckle power to "
                                "measure (%zu with a non-finite value in some frame, %zu without power)", nx, ny,
                                c->n_nonfinite, c->n_nopower);
done:
    work_free(&w);
    swfs_free(mean);
    free(bad);
    if (rc) swfs_coherence_free(c);
    else *out = c;
    return rc;
}

int swfs_coherence_snr_map(const swfs_coherence *c, double exposure, swfs_real *out)
{
    if (!c || !out || out->nx != c->nx || out->ny != c->ny)
        return swfs_fail(SWFS_ERR_SHAPE, "coherence: SNR map must be %zux%zu", c ? c->nx : 0, c ? c->ny : 0);
    if (!(exposure > 0) || !isfinite(exposure))
        return swfs_fail(SWFS_ERR_VALUE, "coherence: exposure must be a positive number of seconds, not %g", exposure);
    double m = exposure / c->framedt;
    if ((long)ceil(m - 1e-9 * m) > c->max_lag)
        return swfs_fail(SWFS_ERR_ARG, "coherence: an exposure of %g s is %.4g WFS frames but the MCF was computed "
                         "to %ld frames (raise max_lag; the cube has %zu frames)", exposure, m, c->max_lag, c->nframes);
    const size_t npix = c->nx * c->ny, nl = (size_t)c->max_lag + 1;
    for (size_t p = 0; p < npix; p++) out->data[p] = swfs_coh_snr_factor(c->dense + p * nl, nl, c->framedt, exposure);
    return SWFS_OK;
}

int swfs_coherence_fit_wind(const swfs_coherence *c, const swfs_geom *g, double v[2])
{
    v[0] = v[1] = NAN;
    if (!g || !(g->pixscale > 0) || !(g->teldiam > 0))
        return swfs_fail(SWFS_ERR_FORMAT, "coherence: the wind fit needs the PIXSCALE and TELDIAM keywords");
    /* PHRATE = k theta.v with theta = (i - nx/2, j - ny/2) PIXSCALE lambda/D, so in units of
     * pixels PHRATE = a.(i - cx, j - cy) with a = 2 pi PIXSCALE v / D. */
    double sxx = 0, sxy = 0, syy = 0, bx = 0, by = 0;
    const long cx = (long)(c->nx / 2), cy = (long)(c->ny / 2);
    for (size_t j = 0; j < c->ny; j++)
        for (size_t i = 0; i < c->nx; i++) {
            size_t p = j * c->nx + i;
            double r = c->phrate->data[p], wgt = c->mean_sp->data[p];
            double x = (double)((long)i - cx), y = (double)((long)j - cy);
            if (!isfinite(r) || !(wgt > 0) || (x == 0 && y == 0)) continue;
            sxx += wgt * x * x; sxy += wgt * x * y; syy += wgt * y * y;
            bx += wgt * x * r; by += wgt * y * r;
        }
    double det = sxx * syy - sxy * sxy;
    if (!(det > 1e-12 * (sxx * syy)) || !(det > 0))
        return swfs_fail(SWFS_ERR_NUMERIC, "coherence: too few valid pixels off the star to fit a wind");
    double ax = (syy * bx - sxy * by) / det, ay = (sxx * by - sxy * bx) / det;
    double s = g->teldiam / (2 * M_PI * g->pixscale);
    v[0] = ax * s;
    v[1] = ay * s;
    return SWFS_OK;
}

/* ---- files ------------------------------------------------------------- */

double swfs_exposure_limit_wind(double theta_lod, double diam, double wind)
{
    double proj = fabs(theta_lod * wind);
    if (proj == 0) return INFINITY;
    return diam / (2 * proj);
}

double swfs_bandwidth_radius(double frac_bw)
{
    return frac_bw > 0 ? 1.0 / frac_bw : INFINITY;
}

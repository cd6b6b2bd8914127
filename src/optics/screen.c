/* Von Karman phase screens by FFT with subharmonics: see include/specklewfs/screen.h. */
#include "../core/planner.h"
#include "specklewfs/screen.h"
#include "specklewfs/array.h"
#include "specklewfs/parallel.h"
#include "specklewfs/status.h"

#include <fftw3.h>
#include <math.h>
#include <stdlib.h>
#include <stdint.h>
#include <string.h>

/* Gamma(11/6)^2 / (2 pi^{11/3}) * (24/5 Gamma(6/5))^{5/6}: the Kolmogorov PSD constant
 * that makes D(r) = 6.8839 (r/r0)^{5/3}. Computed once from tgamma. */
static double psd_constant(void)
{
    const double g = tgamma(11.0 / 6.0);
    return g * g / (2.0 * pow(M_PI, 11.0 / 3.0)) * pow(24.0 / 5.0 * tgamma(6.0 / 5.0), 5.0 / 6.0);
}

static double inv_L0_sq(double L0) { return (L0 > 0 && isfinite(L0)) ? 1.0 / (L0 * L0) : 0.0; }

/* The PSD's scale at Fried parameter r0: psd_constant() r0^{-5/3}. */
static double psd_scale(double r0) { return psd_constant() * pow(r0, -5.0 / 3.0); }

/* The PSD at f given c = psd_scale(r0) and q = 1/L0^2: swfs_vonkarman_psd's value
 * to the bit, for loops over many frequencies that compute c and q once. */
static double psd_at(double f, double c, double q)
{
    const double f2 = f * f + q;
    if (!(f2 > 0)) return 0.0;
    return c * pow(f2, -11.0 / 6.0);
}

double swfs_vonkarman_psd(double f, double r0, double L0)
{
    return psd_at(f, psd_scale(r0), inv_L0_sq(L0));
}

double swfs_vonkarman_structure(double r, double r0, double L0)
{
    if (!(r > 0)) return 0.0;
    /* Simpson's rule in u = ln f on [1e-6/r, 1e5/r] of f^2 Phi(f) (1 - J0(2 pi f r)).
     * Below flo, 1 - J0(x) = x^2/4 and the piece is added in closed form:
     *   pi^2 r^2 c int_0^flo f^3 (f^2 + q)^{-11/6} df = pi^2 r^2 c [F(flo^2 + q) - F(q)] / 2,
     *   F(s) = 6 s^{1/6} + (6/5) q s^{-5/6}
     * (for Kolmogorov it is 3 pi^2 r^2 c flo^{1/3}: 1 % of D at flo r = 1e-6, so it matters).
     * Above fhi the tail ~ f^{-8/3} is added analytically with J0 averaged to zero. */
    const double c = psd_scale(r0), q = inv_L0_sq(L0);
    const double flo = 1e-6 / r, fhi = 1e5 / r;
    const int n = 20000; /* even */
    const double a = log(flo), h = (log(fhi) - a) / n;
    double sum = 0.0;
    for (int k = 0; k <= n; k++) {
        double f = exp(a + h * k);
        double v = f * f * c * pow(f * f + q, -11.0 / 6.0) * (1.0 - j0(2.0 * M_PI * f * r));
        sum += v * ((k == 0 || k == n) ? 1.0 : (k % 2 ? 4.0 : 2.0));
    }
    double integral = sum * h / 3.0;
    const double shi = flo * flo + q;
    const double fup = 6.0 * pow(shi, 1.0 / 6.0) + 1.2 * q * pow(shi, -5.0 / 6.0);
    const double fdn = q > 0 ? 6.0 * pow(q, 1.0 / 6.0) + 1.2 * pow(q, 1.0 / 6.0) : 0.0;
    integral += M_PI * M_PI * r * r * c * 0.5 * (fup - fdn);
    /* tail: int_fhi^inf c f^{-8/3} df = c * 3/5 fhi^{-5/3} (q negligible there) */
    integral += c * 0.6 * pow(fhi, -5.0 / 3.0);
    return 4.0 * M_PI * integral;
}

#define CHUNK 32 /* rows/columns per task: fixed, so results do not depend on the thread count */

struct swfs_screen_gen {
    swfs_screen_params p;
    int threads;
    double complex *spec; /* n*n, FFTW order */
    fftw_plan rows, rows_last, cols, cols_last; /* CHUNK transforms; the remainder */
    double *amp;          /* n*n: sqrt(2 Phi) df * lambda_ref / (2 pi) [m] */
    swfs_screen_wave waves[SWFS_SCREEN_NSUB];
    size_t nwaves;
    double complex *ex, *ey; /* waves: per level, 3 x n each */
    uint64_t row_seed;
    double *out1, *out2;     /* finish() targets */
};

static fftw_plan plan_rows(double complex *a, size_t n, size_t howmany)
{
    const int len = (int)n;
    swfs_planner_lock();
    fftw_plan p = fftw_plan_many_dft(1, &len, (int)howmany, (fftw_complex *)a, NULL, 1, len, (fftw_complex *)a, NULL,
                                     1, len, FFTW_BACKWARD, FFTW_ESTIMATE);
    swfs_planner_unlock();
    return p;
}

static fftw_plan plan_cols(double complex *a, size_t n, size_t howmany)
{
    const int len = (int)n;
    swfs_planner_lock();
    fftw_plan p = fftw_plan_many_dft(1, &len, (int)howmany, (fftw_complex *)a, NULL, len, 1, (fftw_complex *)a, NULL,
                                     len, 1, FFTW_BACKWARD, FFTW_ESTIMATE);
    swfs_planner_unlock();
    return p;
}

static void amp_rows(void *ctx, size_t b, size_t e, int worker)
{
    swfs_screen_gen *g = ctx;
    const size_t n = g->p.n;
    const double df = 1.0 / ((double)n * g->p.dx), scale = SWFS_SCREEN_LAMBDA_REF / (2.0 * M_PI);
    const double c = psd_scale(g->p.r0), q = inv_L0_sq(g->p.L0);
    (void)worker;
    for (size_t ky = b; ky < e; ky++) {
        const double fy = (double)swfs_fft_freq_index(ky, n) * df;
        /* the PSD is even in fx: columns kx and n - kx (frequencies +-kx df) take one value */
        for (size_t kx = 0; kx <= n / 2; kx++) {
            const double fx = (double)swfs_fft_freq_index(kx, n) * df;
            const double f = hypot(fx, fy);
            /* f = 0 is the piston: no physical meaning, and infinite for Kolmogorov. */
            const double a = f > 0 ? sqrt(2.0 * psd_at(f, c, q)) * df * scale : 0.0;
            g->amp[ky * n + kx] = a;
            if (kx > 0 && n - kx > n / 2) g->amp[ky * n + (n - kx)] = a;
        }
    }
}

swfs_screen_gen *swfs_screen_gen_create(const swfs_screen_params *p)
{
    if (!p || p->n < 2 || !(p->dx > 0) || !(p->r0 > 0) || isnan(p->L0)) {
        swfs_fail(SWFS_ERR_ARG, "phase screen: need n >= 2, dx > 0, r0 > 0 and an outer scale L0 (got n=%zu dx=%g r0=%g L0=%g)",
                  p ? p->n : 0, p ? p->dx : 0.0, p ? p->r0 : 0.0, p ? p->L0 : 0.0);
        return NULL;
    }
    if (p->n > 65536) {
        swfs_fail(SWFS_ERR_ARG, "phase screen: n=%zu is too large (max 65536)", p->n);
        return NULL;
    }
    swfs_screen_gen *g = calloc(1, sizeof *g);
    if (!g) {
        swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        return NULL;
    }
    g->p = *p;
    g->threads = swfs_parallel_threads(0, 0);
    const size_t n = p->n;
    g->spec = fftw_malloc(n * n * sizeof *g->spec);
    g->amp = swfs_malloc(n * n * sizeof *g->amp);
    g->ex = swfs_malloc(9 * n * sizeof *g->ex);
    g->ey = swfs_malloc(9 * n * sizeof *g->ey);
    if (!g->spec || !g->amp || !g->ex || !g->ey) {
        swfs_fail(SWFS_ERR_NOMEM, "phase screen: out of memory for a %zux%zu screen", n, n);
        swfs_screen_gen_free(g);
        return NULL;
    }
    /* FFTW_ESTIMATE: planning a 2048^2 transform with MEASURE costs seconds, more than
     * the handful of transforms a simulation runs. The 2-D transform is split into
     * batches of CHUNK rows, then CHUNK columns, run in parallel. Chunk offsets are
     * multiples of CHUNK * 16 bytes, so one plan serves every full chunk
     * (fftw_execute_dft needs the planning alignment). */
    const size_t full = n / CHUNK, rem = n % CHUNK;
    int ok = 1;
    if (full) {
        g->rows = plan_rows(g->spec, n, CHUNK);
        g->cols = plan_cols(g->spec, n, CHUNK);
        ok = g->rows && g->cols;
    }
    if (ok && rem) {
        g->rows_last = plan_rows(g->spec + full * CHUNK * n, n, rem);
        g->cols_last = plan_cols(g->spec + full * CHUNK, n, rem);
        ok = g->rows_last && g->cols_last;
    }
    if (!ok) {
        swfs_fail(SWFS_ERR_INTERNAL, "phase screen: FFTW could not plan a %zux%zu transform", n, n);
        swfs_screen_gen_free(g);
        return NULL;
    }
    swfs_parallel_for(g->threads, n, CHUNK, amp_rows, g);
    return g;
}

void swfs_screen_gen_free(swfs_screen_gen *g)
{
    if (!g) return;
    swfs_planner_lock();
    if (g->rows) fftw_destroy_plan(g->rows);
    if (g->cols) fftw_destroy_plan(g->cols);
    if (g->rows_last) fftw_destroy_plan(g->rows_last);
    if (g->cols_last) fftw_destroy_plan(g->cols_last);
    swfs_planner_unlock();
    fftw_free(g->spec);
    swfs_free(g->amp);
    swfs_free(g->ex);
    swfs_free(g->ey);
    free(g);
}

void swfs_screen_gen_set_threads(swfs_screen_gen *g, int threads) { g->threads = swfs_parallel_threads(threads, 0); }
const swfs_screen_params *swfs_screen_gen_params(const swfs_screen_gen *g) { return &g->p; }
double complex *swfs_screen_gen_spectrum(swfs_screen_gen *g) { return g->spec; }
const double *swfs_screen_gen_amplitude(const swfs_screen_gen *g) { return g->amp; }

swfs_screen_wave *swfs_screen_gen_waves(swfs_screen_gen *g, size_t *count)
{
    if (count) *count = g->nwaves;
    return g->waves;
}

static void fft_rows(void *ctx, size_t b, size_t e, int worker)
{
    swfs_screen_gen *g = ctx;
    (void)worker;
    double complex *a = g->spec + b * g->p.n;
    fftw_execute_dft(e - b == CHUNK ? g->rows : g->rows_last, (fftw_complex *)a, (fftw_complex *)a);
}

static void fft_cols(void *ctx, size_t b, size_t e, int worker)
{
    swfs_screen_gen *g = ctx;
    (void)worker;
    double complex *a = g->spec + b;
    fftw_execute_dft(e - b == CHUNK ? g->cols : g->cols_last, (fftw_complex *)a, (fftw_complex *)a);
}

void swfs_screen_gen_execute(swfs_screen_gen *g)
{
    swfs_parallel_for(g->threads, g->p.n, CHUNK, fft_rows, g);
    swfs_parallel_for(g->threads, g->p.n, CHUNK, fft_cols, g);
}

/* Row ky of the spectrum draws from its own stream (row_seed, ky): the screen depends on
 * the caller's rng only, not on the thread count. */
static void draw_rows(void *ctx, size_t b, size_t e, int worker)
{
    swfs_screen_gen *g = ctx;
    const size_t n = g->p.n;
    (void)worker;
    for (size_t ky = b; ky < e; ky++) {
        swfs_rng r;
        swfs_rng_seed2(&r, g->row_seed, ky);
        for (size_t kx = 0; kx < n; kx++) g->spec[ky * n + kx] = g->amp[ky * n + kx] * swfs_rng_cnormal_value(&r);
    }
}

int swfs_screen_gen_draw(swfs_screen_gen *g, swfs_rng *rng)
{
    g->row_seed = swfs_rng_u64(rng);
    swfs_parallel_for(g->threads, g->p.n, CHUNK, draw_rows, g);
    g->nwaves = 0;
    if (g->p.subharmonics) {
        const double df = 1.0 / ((double)g->p.n * g->p.dx), scale = SWFS_SCREEN_LAMBDA_REF / (2.0 * M_PI);
        double dfl = df;
        for (int level = 1; level <= 3; level++) {
            dfl /= 3.0;
            for (int j = -1; j <= 1; j++)
                for (int i = -1; i <= 1; i++) {
                    if (!i && !j) continue;
                    swfs_screen_wave *w = &g->waves[g->nwaves++];
                    w->fx = i * dfl;
                    w->fy = j * dfl;
                    const double a = sqrt(2.0 * swfs_vonkarman_psd(hypot(w->fx, w->fy), g->p.r0, g->p.L0)) * dfl * scale;
                    w->coef = a * swfs_rng_cnormal_value(rng);
                }
        }
    }
    return SWFS_OK;
}

/* Subharmonic tables: per level, the 3x3 frequency grid factorizes as
 * sum_j ey_j(y) [sum_i c_ji ex_i(x)], so each pixel costs 3 complex products per level.
 * ex[(level*3 + j)*n + p] = sum_i c_ji e^{2 pi i (i-1) dfl x_p}, ey[(level*3 + j)*n + q] =
 * e^{2 pi i (j-1) dfl y_q}. */
static void wave_tables(swfs_screen_gen *g)
{
    const size_t n = g->p.n;
    for (size_t level = 0; level * 8 < g->nwaves; level++) {
        const swfs_screen_wave *w = &g->waves[level * 8];
        /* waves of a level in order (j,i) = (-1,-1) (-1,0) (-1,1) (0,-1) (0,1) (1,-1) (1,0) (1,1) */
        const double dfl = fabs(w[0].fx);
        double complex c[3][3] = {{0}};
        for (int m = 0, idx = 0; m < 9; m++) {
            if (m == 4) continue;
            c[m / 3][m % 3] = w[idx++].coef;
        }
        double complex *ex = g->ex + level * 3 * n, *ey = g->ey + level * 3 * n;
        for (size_t p = 0; p < n; p++) {
            const double ph = 2.0 * M_PI * dfl * (double)p * g->p.dx;
            const double complex e[3] = {cos(ph) - I * sin(ph), 1.0, cos(ph) + I * sin(ph)};
            for (int j = 0; j < 3; j++) ex[(size_t)j * n + p] = c[j][0] * e[0] + c[j][1] * e[1] + c[j][2] * e[2];
            for (int j = 0; j < 3; j++) ey[(size_t)j * n + p] = e[j];
        }
    }
}

static void finish_rows(void *ctx, size_t b, size_t e, int worker)
{
    swfs_screen_gen *g = ctx;
    const size_t n = g->p.n, nlev = g->nwaves / 8;
    (void)worker;
    for (size_t q = b; q < e; q++) {
        double complex *row = g->spec + q * n;
        for (size_t level = 0; level < nlev; level++) {
            const double complex *ex = g->ex + level * 3 * n, *ey = g->ey + level * 3 * n;
            const double complex e0 = ey[q], e1 = ey[n + q], e2 = ey[2 * n + q];
            for (size_t p = 0; p < n; p++) row[p] += e0 * ex[p] + e1 * ex[n + p] + e2 * ex[2 * n + p];
        }
        for (size_t p = 0; p < n; p++) g->out1[q * n + p] = creal(row[p]);
        if (g->out2)
            for (size_t p = 0; p < n; p++) g->out2[q * n + p] = cimag(row[p]);
    }
}

int swfs_screen_gen_finish(swfs_screen_gen *g, double *out1, double *out2)
{
    if (!out1) return swfs_fail(SWFS_ERR_ARG, "phase screen: no output buffer");
    swfs_screen_gen_execute(g);
    wave_tables(g);
    g->out1 = out1;
    g->out2 = out2;
    swfs_parallel_for(g->threads, g->p.n, CHUNK, finish_rows, g);
    g->out1 = g->out2 = NULL;
    return SWFS_OK;
}

int swfs_screen_vonkarman(const swfs_screen_params *p, swfs_rng *rng, double *out1, double *out2)
{
    if (!rng || !out1) return swfs_fail(SWFS_ERR_ARG, "phase screen: missing rng or output");
    swfs_screen_gen *g = swfs_screen_gen_create(p);
    if (!g) return SWFS_ERR_ARG;
    int rc = swfs_screen_gen_draw(g, rng);
    if (!rc) rc = swfs_screen_gen_finish(g, out1, out2);
    swfs_screen_gen_free(g);
    return rc;
}

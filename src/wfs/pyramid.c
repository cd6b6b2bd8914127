/* The modulated pyramid wavefront sensor (pyramid.h): one forward FFT of the padded pupil
 * field per frame, inverse FFTs per modulation point (single precision: the signals are
 * differences of binned intensities of order 1e-3 of them, far above float's rounding), the
 * four pupil images binned on the Shack-Hartmann's subaperture grid.
 *
 * Each 2-D transform is FFTW's batched 1-D transforms, the rows then the columns, out of
 * place (FFTW_ESTIMATE, so the same plan and the same numbers on every run): FFTW's 2-D plan
 * of the sizes with a factor 7 that fast_size picks (140 for a 66-sample pupil) allocated
 * a buffer per row at every execution (140 per transform, 41 transforms a frame) and took
 * 118 us against 76 us for the two batches (measured on this machine class, single
 * precision); the forward transform's rows are only the pupil's, the padding's being zero.
 *
 * The inverse transforms do only what the images need. A point's mask is a row factor times
 * a column factor (the facets' phase is separable), so the rows' transforms of the field
 * times the row factor serve every point of the same row factor, the column factor
 * multiplying their result: the points on the circle at angles th and -th move the pyramid
 * by the same x, so the rows are transformed once for two points (the points' offsets are
 * made mirror images exactly, so that they pair). The columns are then transformed only
 * where an image lies (2 npup of the N), and the intensity summed only on the images. */
#include "specklewfs/pyramid.h"
#include "specklewfs/wfs.h"
#include "specklewfs/status.h"
#include "../core/planner.h"

#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* re + i im, exactly (C11 6.2.5: a complex is an array of its two real parts). glibc's
 * CMPLXF exists only for GCC (it needs __builtin_complex), not for clang, which the
 * fuzzing and sanitizer builds may use. */
static inline float complex cplxf(float re, float im)
{
    float complex z;
    float *p = (float *)&z;
    p[0] = re;
    p[1] = im;
    return z;
}

struct swfs_pyramid_work {
    fftwf_complex *field, *ehat, *work; /* N x N: the padded pupil field, its transform, one point's */
    fftwf_complex *frows, *rows;        /* N x N: the forward's and the inverse's rows transformed
                                           (the columns next; frows' padding rows stay zero) */
    fftwf_complex *cin, *cout;          /* N x 2 npup: the images' columns of rows times a point's
                                           column factor, and their transforms */
    fftwf_complex *mx, *my;             /* nmod x N each: the pyramid moved to each modulation point,
                                           exp(i pi/2 |u + dx|) and exp(i pi/2 |v + dy|), whose product
                                           is its mask (the facets' phase is separable) */
    float *inten;                       /* 2 npup x 2 npup: the modulation-averaged intensity on the
                                           images' rows and columns (below) */
    fftwf_plan fwd_rows, fwd_cols;      /* field's pupil rows -> frows, frows' columns -> ehat */
    fftwf_plan bwd_rows, bwd_cols;      /* work's rows -> rows, cin's columns -> cout */
    long *sub;                          /* npup^2: the used subaperture (its index among them) of each
                                           pupil sample, -1 elsewhere */
    size_t off;                         /* the pupil's first row and column in the padded grid */
    size_t lo, hi;                      /* the images' first rows and columns in the N x N grid
                                           (A at (lo, lo), B at (hi, lo), C at (hi, hi), D at (lo, hi),
                                           column first); in inten at 0 and npup alike */
    double *counts;                     /* 4 x nvalid */
    double *ref;                        /* nslopes: the flat wavefront's signals */
    size_t *vidx;                       /* nvalid: each used subaperture's index a + b nsub */
    double *mask;                       /* npup^2: the pupil's transmission */
};

size_t swfs_pyramid_nmod_default(double mod)
{
    if (!(mod > 0)) return 1;
    size_t n = 4 * (size_t)ceil(2.0 * 2.0 * M_PI * mod / 4.0);
    return n < 4 ? 4 : n;
}

/* The smallest multiple of 4 >= n whose factors are 2, 3, 5 and 7 (FFTW's fast sizes). */
static size_t fast_size(size_t n)
{
    for (size_t m = (n + 3) / 4 * 4;; m += 4) {
        size_t r = m;
        const size_t f[4] = {2, 3, 5, 7};
        for (int i = 0; i < 4; i++)
            while (r % f[i] == 0) r /= f[i];
        if (r == 1) return m;
    }
}

void swfs_pyramid_free(swfs_pyramid *p)
{
    if (!p) return;
    swfs_pyramid_work *w = p->w;
    if (w) {
        swfs_planner_lock();
        fftwf_plan pl[4] = {w->fwd_rows, w->fwd_cols, w->bwd_rows, w->bwd_cols};
        for (int k = 0; k < 4; k++)
            if (pl[k]) fftwf_destroy_plan(pl[k]);
        swfs_planner_unlock();
        fftwf_free(w->field); fftwf_free(w->ehat); fftwf_free(w->work); fftwf_free(w->frows); fftwf_free(w->rows);
        fftwf_free(w->cin); fftwf_free(w->cout); fftwf_free(w->mx); fftwf_free(w->my); fftwf_free(w->inten);
        free(w->sub); free(w->counts); free(w->ref); free(w->vidx); free(w->mask);
        free(w);
    }
    free(p->valid);
    free(p);
}

/* The four images' binned intensities into w->counts (4 x nvalid), from w->inten. */
static void bin_images(const swfs_pyramid *p)
{
    swfs_pyramid_work *w = p->w;
    const size_t n = p->npup, nv = p->nvalid;
    const size_t at[4][2] = {{0, 0}, {n, 0}, {n, n}, {0, n}}; /* A, B, C, D in inten: column, row */
    memset(w->counts, 0, 4 * nv * sizeof *w->counts);
    for (int j = 0; j < 4; j++) {
        double *c = w->counts + (size_t)j * nv;
        for (size_t q = 0; q < n; q++) {
            const float *row = w->inten + (at[j][1] + q) * 2 * n + at[j][0];
            const long *s = w->sub + q * n;
            for (size_t i = 0; i < n; i++)
                if (s[i] >= 0) c[s[i]] += row[i];
        }
    }
}

/* The signals of w->counts (after the noise, if any), less ref when ref is given. */
static void signals_of(const swfs_pyramid *p, const double *ref, double *out)
{
    const swfs_pyramid_work *w = p->w;
    const size_t nv = p->nvalid, n2 = p->nsub * p->nsub;
    const double *A = w->counts, *B = A + nv, *C = B + nv, *D = C + nv;
    double tot = 0;
    for (size_t v = 0; v < nv; v++) tot += A[v] + B[v] + C[v] + D[v];
    const double inv = tot > 0 ? (double)nv / tot : 0.0;
    memset(out, 0, 2 * n2 * sizeof *out);
    for (size_t v = 0; v < nv; v++) {
        const size_t k = w->vidx[v];
        out[k] = (A[v] + D[v] - B[v] - C[v]) * inv - (ref ? ref[k] : 0.0);
        out[n2 + k] = (A[v] + B[v] - C[v] - D[v]) * inv - (ref ? ref[n2 + k] : 0.0);
    }
}

/* The modulation-averaged intensity of the displacement z (NULL: flat) into w->inten. */
static void intensity(swfs_pyramid *p, const double *z)
{
    swfs_pyramid_work *w = p->w;
    const size_t n = p->npup, N = p->nfft, NN = N * N;
    const double k = 2.0 * M_PI / p->wavelen;
    for (size_t q = 0; q < n; q++) {
        fftwf_complex *row = w->field + (w->off + q) * N + w->off;
        for (size_t i = 0; i < n; i++) {
            const double a = w->mask[q * n + i];
            if (a > 0) {
                const double ph = z ? k * z[q * n + i] : 0.0;
                row[i] = cplxf((float)(a * cos(ph)), (float)(a * sin(ph)));
            } else {
                row[i] = 0.0f;
            }
        }
    }
    fftwf_execute(w->fwd_rows);
    fftwf_execute(w->fwd_cols);
    const size_t n2 = 2 * n;
    memset(w->inten, 0, n2 * n2 * sizeof *w->inten);
    const float scale = 1.0f / ((float)p->nmod * (float)NN * (float)NN);
    /* the products and intensities on the real and imaginary parts (C11 6.2.5: a complex is
     * an array of its two real parts), which the compiler vectorizes (C's complex product
     * would check every result for NaN) */
    const float *eh = (const float *)w->ehat, *rw = (const float *)w->rows, *co = (const float *)w->cout;
    float *wk = (float *)w->work, *ci = (float *)w->cin, *in = w->inten;
    const size_t cols[2] = {w->lo, w->hi};
    for (size_t m = 0; 2 * m < p->nmod; m++) {
        /* the field times the row factor of points m and nmod - 1 - m (one point where they
         * are the same), its rows transformed */
        const float *mx = (const float *)(w->mx + m * N);
        for (size_t v = 0; v < N; v++) {
            const float *ev = eh + 2 * v * N;
            float *wv = wk + 2 * v * N;
            for (size_t u = 0; u < N; u++) {
                const float ar = ev[2 * u], ai = ev[2 * u + 1], br = mx[2 * u], bi = mx[2 * u + 1];
                wv[2 * u] = ar * br - ai * bi;
                wv[2 * u + 1] = ar * bi + ai * br;
            }
        }
        fftwf_execute(w->bwd_rows);
        const size_t pts[2] = {m, p->nmod - 1 - m};
        for (int t = 0; t < (pts[1] == m ? 1 : 2); t++) {
            /* the images' columns times the point's column factor, transformed */
            const float *my = (const float *)(w->my + pts[t] * N);
            for (size_t v = 0; v < N; v++) {
                const float cr = my[2 * v], cim = my[2 * v + 1];
                for (int h = 0; h < 2; h++) {
                    const float *r = rw + 2 * (v * N + cols[h]);
                    float *o = ci + 2 * (v * n2 + (size_t)h * n);
                    for (size_t i = 0; i < n; i++) {
                        const float ar = r[2 * i], ai = r[2 * i + 1];
                        o[2 * i] = ar * cr - ai * cim;
                        o[2 * i + 1] = ar * cim + ai * cr;
                    }
                }
            }
            fftwf_execute(w->bwd_cols);
            /* the intensity on the images' rows */
            for (int h = 0; h < 2; h++)
                for (size_t q = 0; q < n; q++) {
                    const float *c = co + 2 * (cols[h] + q) * n2;
                    float *row = in + ((size_t)h * n + q) * n2;
                    for (size_t e = 0; e < n2; e++) {
                        const float re = c[2 * e], im = c[2 * e + 1];
                        row[e] += scale * (re * re + im * im);
                    }
                }
        }
    }
}

int swfs_pyramid_create(swfs_pyramid **out, size_t nsub, double diam, const double *mask, size_t npup, double pupdx,
                        const unsigned char *valid, double wavelen, double mod, size_t nmod)
{
    *out = NULL;
    if (!(wavelen > 0) || !isfinite(wavelen))
        return swfs_fail(SWFS_ERR_ARG, "pyramid: sensing wavelength %g m, expected > 0", wavelen);
    if (!(mod >= 0) || !isfinite(mod))
        return swfs_fail(SWFS_ERR_ARG, "pyramid: modulation radius %g lambda/D, expected >= 0", mod);
    /* the geometry and the used subapertures as the Shack-Hartmann's (its checks, its rule) */
    swfs_shwfs *sh = NULL;
    int rc = valid ? swfs_shwfs_create_valid(&sh, nsub, diam, mask, npup, pupdx, valid)
                   : swfs_shwfs_create(&sh, nsub, diam, mask, npup, pupdx, 0.5);
    if (rc) return swfs_fail_context(rc, "pyramid");
    swfs_pyramid *p = calloc(1, sizeof *p);
    if (!p) { swfs_shwfs_free(sh); return swfs_fail(SWFS_ERR_NOMEM, "out of memory"); }
    p->nsub = nsub;
    p->nslopes = 2 * nsub * nsub;
    p->npup = npup;
    p->pupdx = pupdx;
    p->diam = diam;
    p->wavelen = wavelen;
    p->mod = mod;
    p->nmod = nmod ? nmod : swfs_pyramid_nmod_default(mod);
    p->valid = sh->valid;
    p->nvalid = sh->nvalid;
    sh->valid = NULL;
    swfs_shwfs_free(sh);
    size_t N = fast_size(2 * npup + 8);
    const double dN = ceil(2.0 * diam / pupdx);
    if ((double)N < dN) N = fast_size((size_t)dN);
    p->nfft = N;
    p->sampling = (double)N * pupdx / diam;
    if (mod * p->sampling > 0.25 * (double)N) {
        const double lim = 0.25 * (double)N / p->sampling;
        swfs_pyramid_free(p);
        return swfs_fail(SWFS_ERR_ARG, "pyramid: modulation radius %g lambda/D beyond a quarter of the focal window "
                         "(%g lambda/D)", mod, lim);
    }
    if (!p->nvalid) {
        swfs_pyramid_free(p);
        return swfs_fail(SWFS_ERR_VALUE, "pyramid: no subaperture used");
    }
    swfs_pyramid_work *w = calloc(1, sizeof *w);
    p->w = w;
    const size_t NN = N * N, nv = p->nvalid, n2 = nsub * nsub;
    if (w) {
        w->field = fftwf_alloc_complex(NN);
        w->ehat = fftwf_alloc_complex(NN);
        w->work = fftwf_alloc_complex(NN);
        w->frows = fftwf_alloc_complex(NN);
        w->rows = fftwf_alloc_complex(NN);
        w->cin = fftwf_alloc_complex(N * 2 * npup);
        w->cout = fftwf_alloc_complex(N * 2 * npup);
        w->mx = fftwf_alloc_complex(p->nmod * N);
        w->my = fftwf_alloc_complex(p->nmod * N);
        w->inten = fftwf_alloc_real(4 * npup * npup);
        w->sub = malloc(npup * npup * sizeof *w->sub);
        w->counts = malloc(4 * nv * sizeof *w->counts);
        w->ref = calloc(2 * n2, sizeof *w->ref);
        w->vidx = malloc(nv * sizeof *w->vidx);
        w->mask = malloc(npup * npup * sizeof *w->mask);
    }
    if (!w || !w->field || !w->ehat || !w->work || !w->frows || !w->rows || !w->cin || !w->cout || !w->mx || !w->my ||
        !w->inten || !w->sub || !w->counts || !w->ref || !w->vidx || !w->mask) {
        swfs_pyramid_free(p);
        return swfs_fail(SWFS_ERR_NOMEM, "pyramid: out of memory for %zu x %zu transforms and %zu modulation points",
                         N, N, p->nmod);
    }
    memset(w->field, 0, NN * sizeof *w->field);
    memset(w->frows, 0, NN * sizeof *w->frows);
    memcpy(w->mask, mask, npup * npup * sizeof *mask);
    w->off = (N - npup) / 2;
    const int n1[1] = {(int)N}, iN = (int)N, i2n = 2 * (int)npup;
    fftwf_complex *fr = w->field + w->off * N, *rr = w->frows + w->off * N;
    swfs_planner_lock();
    w->fwd_rows = fftwf_plan_many_dft(1, n1, (int)npup, fr, NULL, 1, iN, rr, NULL, 1, iN, FFTW_FORWARD, FFTW_ESTIMATE);
    w->fwd_cols = fftwf_plan_many_dft(1, n1, iN, w->frows, NULL, iN, 1, w->ehat, NULL, iN, 1, FFTW_FORWARD,
                                      FFTW_ESTIMATE);
    w->bwd_rows = fftwf_plan_many_dft(1, n1, iN, w->work, NULL, 1, iN, w->rows, NULL, 1, iN, FFTW_BACKWARD,
                                      FFTW_ESTIMATE);
    w->bwd_cols = fftwf_plan_many_dft(1, n1, i2n, w->cin, NULL, i2n, 1, w->cout, NULL, i2n, 1, FFTW_BACKWARD,
                                      FFTW_ESTIMATE);
    swfs_planner_unlock();
    if (!w->fwd_rows || !w->fwd_cols || !w->bwd_rows || !w->bwd_cols) {
        swfs_pyramid_free(p);
        return swfs_fail(SWFS_ERR_NUMERIC, "pyramid: FFTW could not plan %zu x %zu transforms", N, N);
    }
    /* each used subaperture's index among them; each pupil sample's subaperture by its centre */
    long *vi = malloc(n2 * sizeof *vi);
    if (!vi) {
        swfs_pyramid_free(p);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t k = 0, v = 0; k < n2; k++) {
        vi[k] = p->valid[k] ? (long)v : -1;
        if (p->valid[k]) w->vidx[v++] = k;
    }
    const double c0 = 0.5 * (double)(npup - 1);
    for (size_t q = 0; q < npup; q++)
        for (size_t i = 0; i < npup; i++) {
            const double x = ((double)i - c0) * pupdx, y = ((double)q - c0) * pupdx;
            const double ux = (x + 0.5 * diam) / diam * (double)nsub, uy = (y + 0.5 * diam) / diam * (double)nsub;
            long s = -1;
            if (ux >= 0 && ux < (double)nsub && uy >= 0 && uy < (double)nsub)
                s = vi[(size_t)floor(uy) * nsub + (size_t)floor(ux)];
            w->sub[q * npup + i] = s;
        }
    free(vi);
    /* The facets' tilt a = N/4 samples puts facet u >= 0's image a to the left of the pupil's
     * place (the inverse transform of exp(2 pi i a u / N) E^ is E(x + a)), u < 0's a to the
     * right; the same in y. */
    const size_t a = N / 4;
    w->lo = w->off - a;
    w->hi = w->off + a; /* N >= 2 npup + 8: the images do not overlap */
    /* the masks: the pyramid moved to minus each modulation point (angles offset by half a
     * step, so that no point sits on a ridge and the path is the same seen by each facet);
     * the points at th and 2 pi - th (m and nmod - 1 - m) made mirror images to the bit, the
     * same dx and opposite dy, so that they share their row factor */
    const double r = mod * p->sampling;
    for (size_t m = 0; m < p->nmod; m++) {
        const size_t mm = m < p->nmod - 1 - m ? m : p->nmod - 1 - m;
        const double th = 2.0 * M_PI * ((double)mm + 0.5) / (double)p->nmod, sg = mm == m ? 1.0 : -1.0;
        const double dx = mod > 0 ? r * cos(th) : 0.0, dy = mod > 0 ? sg * r * sin(th) : 0.0;
        for (size_t i = 0; i < N; i++) {
            const double f = (double)(i < N / 2 ? (long)i : (long)i - (long)N);
            const double px = 0.5 * M_PI * fabs(f + dx), py = 0.5 * M_PI * fabs(f + dy);
            w->mx[m * N + i] = cplxf((float)cos(px), (float)sin(px));
            w->my[m * N + i] = cplxf((float)cos(py), (float)sin(py));
        }
    }
    /* the reference: a flat wavefront's signals */
    intensity(p, NULL);
    bin_images(p);
    signals_of(p, NULL, w->ref);
    *out = p;
    return SWFS_OK;
}

void swfs_pyramid_measure(swfs_pyramid *p, const double *z, double photons, swfs_rng *rng, double *signals)
{
    swfs_pyramid_work *w = p->w;
    intensity(p, z);
    bin_images(p);
    if (photons > 0 && rng) {
        const size_t nv = p->nvalid;
        double tot = 0;
        for (size_t e = 0; e < 4 * nv; e++) tot += w->counts[e];
        const double s = tot > 0 ? photons * (double)nv / tot : 0.0;
        for (size_t e = 0; e < 4 * nv; e++) {
            const double c = s * w->counts[e];
            w->counts[e] = c + (c > 0 ? sqrt(c) * swfs_rng_normal(rng) : 0.0);
        }
    }
    signals_of(p, w->ref, signals);
}

int swfs_pyramid_interaction(swfs_pyramid *p, const swfs_sparse *T, double amp, double **D)
{
    *D = NULL;
    const size_t ng = p->npup * p->npup, ns = p->nslopes, na = T->ncols;
    if (T->nrows != ng)
        return swfs_fail(SWFS_ERR_SHAPE, "pyramid: the DM's interpolation has %zu rows, the pupil grid %zu samples",
                         T->nrows, ng);
    if (!(amp > 0) || !isfinite(amp)) return swfs_fail(SWFS_ERR_ARG, "pyramid: push-pull amplitude %g m", amp);
    double *d = malloc(ns * na * sizeof *d), *e = calloc(na, sizeof *e), *z = malloc(ng * sizeof *z);
    double *sp = malloc(2 * ns * sizeof *sp), *sm = sp ? sp + ns : NULL;
    if (!d || !e || !z || !sp) {
        free(d); free(e); free(z); free(sp);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t a = 0; a < na; a++) {
        e[a] = amp;
        swfs_sparse_apply(T, e, z);
        e[a] = 0;
        swfs_pyramid_measure(p, z, 0, NULL, sp);
        for (size_t g = 0; g < ng; g++) z[g] = -z[g];
        swfs_pyramid_measure(p, z, 0, NULL, sm);
        for (size_t i = 0; i < ns; i++) d[i * na + a] = (sp[i] - sm[i]) / (2.0 * amp);
    }
    free(e); free(z); free(sp);
    *D = d;
    return SWFS_OK;
}

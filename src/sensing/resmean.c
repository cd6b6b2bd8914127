/* The AO residual's time mean in the pupil product: band-limited to what the focal window
 * constrains, then taken out of the static wavefront (include/specklewfs/pupil.h,
 * docs/telemetry.md "The residual's time mean"). */
#include "../core/planner.h"
#include "specklewfs/pupil.h"
#include "specklewfs/status.h"

#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* (fftw_complex is C99's double complex here: complex.h comes first.) Both maps (n x n, zero
 * outside) low-passed in place: an FFT on a 2n x 2n grid (no
 * wrap-around of the pupil onto itself), the frequencies |fx| <= fxmax and |fy| <= fymax
 * [cycles per metre] kept, the rest zeroed. */
static int lowpass2(double *a, double *b, size_t n, double pupdx, double fxmax, double fymax)
{
    const size_t m = 2 * n, mm = m * m;
    fftw_complex *x = fftw_alloc_complex(mm);
    if (!x) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    swfs_planner_lock();
    fftw_plan fw = fftw_plan_dft_2d((int)m, (int)m, x, x, FFTW_FORWARD, FFTW_ESTIMATE);
    fftw_plan bw = fftw_plan_dft_2d((int)m, (int)m, x, x, FFTW_BACKWARD, FFTW_ESTIMATE);
    swfs_planner_unlock();
    int rc = fw && bw ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "FFTW could not plan a %zu x %zu transform", m, m);
    double *maps[2] = {a, b};
    for (int t = 0; t < 2 && !rc; t++) {
        memset(x, 0, mm * sizeof *x);
        for (size_t j = 0; j < n; j++)
            for (size_t i = 0; i < n; i++) x[j * m + i] = maps[t][j * n + i];
        fftw_execute(fw);
        for (size_t j = 0; j < m; j++) {
            const double fy = (double)(j <= m / 2 ? (long)j : (long)j - (long)m) / ((double)m * pupdx);
            for (size_t i = 0; i < m; i++) {
                const double fx = (double)(i <= m / 2 ? (long)i : (long)i - (long)m) / ((double)m * pupdx);
                if (fabs(fx) > fxmax || fabs(fy) > fymax) x[j * m + i] = 0.0;
            }
        }
        fftw_execute(bw);
        for (size_t j = 0; j < n; j++)
            for (size_t i = 0; i < n; i++) maps[t][j * n + i] = creal(x[j * m + i]) / (double)mm;
    }
    swfs_planner_lock();
    if (fw) fftw_destroy_plan(fw);
    if (bw) fftw_destroy_plan(bw);
    swfs_planner_unlock();
    fftw_free(x);
    return rc;
}

int swfs_resmean_bandlimit(const double *map, const double *mask, size_t n, const swfs_geom *g, size_t nfx,
                           size_t nfy, double *out, double *rms)
{
    /* The window's pixel (i, j) sits at (i - floor(W/2)) PIXSCALE lambda/D: a ripple of f
     * cycles per D puts its speckles at +-f lambda/D, inside the window up to floor(W/2)
     * PIXSCALE on each axis. */
    const double fx = (double)(nfx / 2) * g->pixscale / g->teldiam, fy = (double)(nfy / 2) * g->pixscale / g->teldiam;
    double *a = malloc(2 * n * n * sizeof *a);
    if (!a) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    double *b = a + n * n;
    for (size_t k = 0; k < n * n; k++) {
        b[k] = mask[k] > 0.0 ? mask[k] : 0.0;
        a[k] = b[k] * map[k];
    }
    int rc = lowpass2(a, b, n, g->pupdx, fx, fy);
    /* Normalized convolution: the low-passed wavefront over the low-passed mask, so that the
     * samples near the rim, whose neighbourhood is half outside, keep their level (a sharp
     * edge low-passes to one half there; the floor only guards the division). */
    for (size_t k = 0; !rc && k < n * n; k++) out[k] = mask[k] > 0.0 ? a[k] / fmax(b[k], 0.5) : 0.0;
    free(a);
    if (!rc) {
        const double r = swfs_wfe_remove_ptt(out, mask, n);
        if (rms) *rms = r;
    }
    return rc;
}

int swfs_pupil_remove_resmean(swfs_pupil_result *r, const swfs_real *resmean, const swfs_geom *g, size_t nfx,
                              size_t nfy)
{
    const size_t n = (size_t)g->pupn;
    if (resmean->nx != n || resmean->ny != n)
        return swfs_fail(SWFS_ERR_SHAPE, "the AO residual's time mean (RESMEAN) is %zux%zu but PUPN = %zu", resmean->nx,
                         resmean->ny, n);
    swfs_real *b = swfs_real_alloc(n, n, 1);
    if (!b) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    double rms = 0.0;
    int rc = swfs_resmean_bandlimit(resmean->data, r->mask->data, n, g, nfx, nfy, b->data, &rms);
    if (rc) {
        swfs_real_free(b);
        return rc;
    }
    const double k = 2.0 * M_PI / g->wavelen;
    for (size_t q = 0; q < n * n; q++) {
        if (!(r->mask->data[q] > 0.0)) continue;
        r->wfe->data[q] -= b->data[q];
        r->field->data[q] *= cexp(-I * k * b->data[q]);
    }
    swfs_real_free(r->resmean);
    r->resmean = b;
    r->resmean_rms = rms;
    return SWFS_OK;
}

int swfs_pupil_compare_kept(const swfs_pupil_result *r, const double *truth, double *err_rms)
{
    const size_t n = r->wfe->nx, np = n * n;
    if (!r->resmean) return swfs_wfe_compare(r->wfe->data, truth, r->mask->data, n, err_rms, NULL, NULL);
    double *kept = malloc(np * sizeof *kept);
    if (!kept) return swfs_fail(SWFS_ERR_NOMEM, "pupil: out of memory");
    for (size_t q = 0; q < np; q++) kept[q] = r->wfe->data[q] + r->resmean->data[q];
    const int rc = swfs_wfe_compare(kept, truth, r->mask->data, n, err_rms, NULL, NULL);
    free(kept);
    return rc;
}

/* The white measurement noise of a Shack-Hartmann's slopes, from the slopes alone (wfs.h
 * swfs_slopes_white_noise; docs/telemetry.md, "The loops' slope noise").
 *
 * Over each 2 x 2 cell of used subapertures the circulation of the slopes,
 *   c = (sx[i+1][j] + sx[i+1][j+1] - sx[i][j] - sx[i][j+1])
 *     - (sy[i][j+1] + sy[i+1][j+1] - sy[i][j] - sy[i+1][j]),
 * is a sum of eight slopes with signs +-1: white noise of variance s^2 per slope gives it the
 * variance 8 s^2. A wavefront's gradient gives it almost none: what remains is the part of the
 * residual the subapertures average unevenly (aliasing), which no DM makes, so the loop never
 * feeds it (nor the noise in it) back. That part moves with the wind and changes smoothly from
 * one WFS frame to the next; the noise is new every frame. The temporal structure function
 * d(k) = <(c(t + k) - c(t))^2> is therefore 16 s^2 + f(k), f(k) = 2 (C(0) - C(k)) of the
 * pattern's autocovariance C, which is even and smooth in k: f = a k^2 + b k^4 + ... A
 * quadratic in k^2 through d(1), d(2), d(3) (k^2 = 1, 4, 9) extrapolated to k = 0,
 *   16 s^2 = 1.5 d(1) - 0.6 d(2) + 0.1 d(3),
 * is exact to the k^6 term. (A straight line through d(1), d(2), as the mode statistics of
 * swfs_slopes_noise_var take it, is short by 2 a: on the matrix's telemetry it found 20-45 %
 * of the noise variance; docs/telemetry.md, "The loops' slope noise".) */
#include "specklewfs/wfs.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>

static int curl_noise(const double *slopes, size_t nframes, size_t nslopes, size_t nsub, const unsigned char *valid,
                      double *var, size_t *ncells, double *slope_var, double *curl_var)
{
    *var = 0;
    if (curl_var) *curl_var = 0;
    if (ncells) *ncells = 0;
    if (slope_var) *slope_var = 0;
    if (nsub < 2) return swfs_fail(SWFS_ERR_ARG, "slope noise: %zu x %zu subapertures, at least 2 x 2", nsub, nsub);
    if (nframes < 16) return swfs_fail(SWFS_ERR_ARG, "slope noise: %zu WFS frames, at least 16", nframes);
    const size_t n2 = nsub * nsub, h = nslopes / 2;
    size_t nmap = 0;
    for (size_t k = 0; valid && k < n2; k++) nmap += valid[k] != 0;
    const int compact = valid && nslopes == 2 * nmap;
    if (!compact && nslopes != 2 * n2)
        return swfs_fail(SWFS_ERR_SHAPE, "slope noise: %zu slopes per frame; expected 2 nsub^2 = %zu%s", nslopes, 2 * n2,
                         valid ? " or twice the valid subapertures" : "");
    for (size_t i = 0; i < nframes * nslopes; i++)
        if (!isfinite(slopes[i]))
            return swfs_fail(SWFS_ERR_VALUE, "slope noise: slope %zu of WFS frame %zu is not finite", i % nslopes,
                             i / nslopes);
    /* each subaperture's x slope's place in a row (its y slope h further), or SIZE_MAX
     * unused: the map's, else those whose slopes vary over the frames; the 2 x 2 cells of used
     * subapertures by their first (lowest) one */
    size_t *xc = malloc(2 * n2 * sizeof *xc), *cell = xc + n2, nc = 0;
    double *ring = malloc(4 * n2 * sizeof *ring), *acc = calloc(6 * n2, sizeof *acc); /* slope_var's sums, then
                                                                                      the curl's (curl_var) */
    if (!xc || !ring || !acc) {
        free(xc); free(ring); free(acc);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    for (size_t k = 0, u = 0; k < n2; k++) {
        int used = valid ? valid[k] != 0 : 0;
        for (size_t t = 1; !valid && t < nframes && !used; t++)
            used = slopes[t * nslopes + k] != slopes[k] || slopes[t * nslopes + h + k] != slopes[h + k];
        xc[k] = used ? (compact ? u : k) : SIZE_MAX;
        u += valid && valid[k];
    }
    for (size_t i = 0; i + 1 < nsub; i++)
        for (size_t j = 0; j + 1 < nsub; j++) {
            const size_t a = i * nsub + j;
            if (xc[a] != SIZE_MAX && xc[a + 1] != SIZE_MAX && xc[a + nsub] != SIZE_MAX && xc[a + nsub + 1] != SIZE_MAX)
                cell[nc++] = a;
        }
    if (!nc) {
        free(xc); free(ring); free(acc);
        return swfs_fail(SWFS_ERR_VALUE, "slope noise: no 2 x 2 cell of used subapertures among the %zu x %zu", nsub, nsub);
    }
    /* the curl of the last four frames (a ring), each frame's differences summed as it comes */
    double d[4] = {0};
    size_t nu = 0;
    for (size_t k = 0; k < n2; k++) nu += xc[k] != SIZE_MAX;
    for (size_t t = 0; t < nframes; t++) {
        const double *sx = slopes + t * nslopes, *sy = sx + h;
        double *c = ring + (t % 4) * nc;
        for (size_t q = 0; q < nc; q++) { /* (i,j) (i,j+1) (i+1,j) (i+1,j+1) */
            const size_t a = xc[cell[q]], b = xc[cell[q] + 1], u = xc[cell[q] + nsub], v = xc[cell[q] + nsub + 1];
            c[q] = (sx[u] + sx[v] - sx[a] - sx[b]) - (sy[b] + sy[v] - sy[a] - sy[u]);
            acc[4 * n2 + q] += c[q];
            acc[5 * n2 + q] += c[q] * c[q];
        }
        /* the frame's slopes less its mean x and y slope over the used subapertures (tip-tilt),
         * summed per slope with their squares: each slope's time mean comes off at the end */
        for (size_t ax = 0; ax < 2; ax++) {
            const double *x = ax ? sy : sx;
            double mean = 0;
            for (size_t k = 0; k < n2; k++)
                if (xc[k] != SIZE_MAX) mean += x[xc[k]];
            mean /= (double)nu;
            for (size_t k = 0; k < n2; k++)
                if (xc[k] != SIZE_MAX) {
                    const double e = x[xc[k]] - mean;
                    acc[ax * n2 + k] += e;
                    acc[2 * n2 + ax * n2 + k] += e * e;
                }
        }
        for (size_t k = 1; k <= 3 && k <= t; k++) {
            const double *p = ring + ((t - k) % 4) * nc;
            double sum = 0;
            for (size_t q = 0; q < nc; q++) sum += (c[q] - p[q]) * (c[q] - p[q]);
            d[k] += sum;
        }
    }
    for (size_t k = 1; k <= 3; k++) d[k] /= (double)((nframes - k) * nc);
    const double v0 = (1.5 * d[1] - 0.6 * d[2] + 0.1 * d[3]) / 16.0;
    *var = v0 > 0 ? v0 : 0;
    if (ncells) *ncells = nc;
    if (slope_var) {
        double ss = 0;
        for (size_t i = 0; i < 2 * n2; i++) ss += acc[2 * n2 + i] - acc[i] * acc[i] / (double)nframes;
        *slope_var = ss > 0 ? ss / (double)(nframes * 2 * nu) : 0;
    }
    if (curl_var) {
        double cs = 0;
        for (size_t q = 0; q < nc; q++) cs += acc[5 * n2 + q] - acc[4 * n2 + q] * acc[4 * n2 + q] / (double)nframes;
        *curl_var = cs > 0 ? cs / (double)(nframes * nc) / 8.0 : 0;
    }
    free(xc); free(ring); free(acc);
    return SWFS_OK;
}

int swfs_slopes_white_noise(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                            const unsigned char *valid, double *var, size_t *ncells, double *slope_var)
{
    return curl_noise(slopes, nframes, nslopes, nsub, valid, var, ncells, slope_var, NULL);
}

int swfs_slopes_curl_noise(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                           const unsigned char *valid, double *white, double *total)
{
    return curl_noise(slopes, nframes, nslopes, nsub, valid, white, NULL, NULL, total);
}

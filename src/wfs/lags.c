/* The input of a space-time reconstructor: the slopes of frames t + lags[k] stacked
 * (wfs.h swfs_slopes_stack; docs/telemetry.md, "A space-time learned map"). */
#include "specklewfs/wfs.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#define LAG_MAX 100000L /* WFS frames: minutes of telemetry at any loop rate */

int swfs_lags_check(const long *lags, size_t nlags, const char *what)
{
    if (nlags < 1 || nlags > SWFS_RECON_MAXLAGS)
        return swfs_fail(SWFS_ERR_ARG, "%s: %zu lags; expected 1 to %d", what, nlags, SWFS_RECON_MAXLAGS);
    int zero = 0;
    for (size_t k = 0; k < nlags; k++) {
        if (lags[k] < -LAG_MAX || lags[k] > LAG_MAX)
            return swfs_fail(SWFS_ERR_ARG, "%s: lag %ld WFS frames; expected within +-%ld", what, lags[k], LAG_MAX);
        for (size_t j = 0; j < k; j++)
            if (lags[j] == lags[k]) return swfs_fail(SWFS_ERR_ARG, "%s: lag %ld given twice", what, lags[k]);
        zero |= lags[k] == 0;
    }
    if (!zero)
        return swfs_fail(SWFS_ERR_ARG, "%s: no lag 0: the map of frame t must see frame t's own slopes (its tilt is "
                         "the frame's)", what);
    return SWFS_OK;
}

long swfs_lags_max_abs(const long *lags, size_t nlags)
{
    long m = 0;
    for (size_t k = 0; k < nlags; k++) m = labs(lags[k]) > m ? labs(lags[k]) : m;
    return m;
}

int swfs_lags_parse(const char *text, long *lags, size_t *nlags, const char *what)
{
    *nlags = 0;
    const char *p = text;
    if (!p || !*p) return swfs_fail(SWFS_ERR_ARG, "%s: no lags given (e.g. 0,-25,25)", what);
    for (;;) {
        char *end;
        errno = 0;
        const long v = strtol(p, &end, 10);
        if (end == p || errno || (*end && *end != ','))
            return swfs_fail(SWFS_ERR_ARG, "%s: \"%s\" is not a list of whole WFS frames (e.g. 0,-25,25)", what, text);
        if (*nlags == SWFS_RECON_MAXLAGS)
            return swfs_fail(SWFS_ERR_ARG, "%s: more than %d lags in \"%s\"", what, SWFS_RECON_MAXLAGS, text);
        lags[(*nlags)++] = v;
        if (!*end) break;
        p = end + 1;
    }
    return swfs_lags_check(lags, *nlags, what);
}

void swfs_slopes_stack(const double *s, size_t nframes, size_t nslopes, const long *lags, size_t nlags, size_t first,
                       size_t count, double *out)
{
    const long last = (long)nframes - 1;
    for (size_t t = 0; t < count; t++)
        for (size_t k = 0; k < nlags; k++) {
            long f = (long)(first + t) + lags[k];
            f = f < 0 ? 0 : (f > last ? last : f);
            memcpy(out + (t * nlags + k) * nslopes, s + (size_t)f * nslopes, nslopes * sizeof *out);
        }
}

int swfs_slopes_lag_correlation(const double *s, size_t nframes, size_t nslopes, const long *lags, size_t nlags,
                                double *r)
{
    const size_t h = nslopes / 2;
    if (nslopes % 2 || !nframes) return swfs_fail(SWFS_ERR_SHAPE, "lag correlation: %zu frames of %zu slopes", nframes, nslopes);
    size_t *used = malloc(nslopes * sizeof *used), nu[2] = {0, 0};
    double *c = malloc(nframes * nslopes * sizeof *c), *mean = calloc(nslopes, sizeof *mean);
    if (!used || !c || !mean) {
        free(used); free(c); free(mean);
        return swfs_fail(SWFS_ERR_NOMEM, "lag correlation: out of memory for %zu frames", nframes);
    }
    size_t nc = 0;
    for (int axis = 0; axis < 2; axis++)
        for (size_t i = (size_t)axis * h; i < (size_t)(axis + 1) * h; i++) {
            int any = 0;
            for (size_t t = 0; t < nframes && !any; t++) any = s[t * nslopes + i] != 0.0;
            if (any) { used[nc++] = i; nu[axis]++; }
        }
    /* the used slopes, each frame's mean x and y out, then each slope's time mean */
    for (size_t t = 0; t < nframes; t++) {
        double *ct = c + t * nc;
        for (size_t k = 0; k < nc; k++) ct[k] = s[t * nslopes + used[k]];
        for (int axis = 0; axis < 2; axis++) {
            const size_t k0 = axis ? nu[0] : 0, k1 = axis ? nc : nu[0];
            double m = 0;
            for (size_t k = k0; k < k1; k++) m += ct[k];
            m = k1 > k0 ? m / (double)(k1 - k0) : 0.0;
            for (size_t k = k0; k < k1; k++) ct[k] -= m;
        }
        for (size_t k = 0; k < nc; k++) mean[k] += ct[k] / (double)nframes;
    }
    double v = 0;
    for (size_t t = 0; t < nframes; t++)
        for (size_t k = 0; k < nc; k++) {
            c[t * nc + k] -= mean[k];
            v += c[t * nc + k] * c[t * nc + k];
        }
    v /= (double)nframes;
    for (size_t j = 0; j < nlags; j++) {
        const size_t L = (size_t)labs(lags[j]);
        if (L >= nframes || !(v > 0)) { r[j] = NAN; continue; }
        double a = 0;
        for (size_t t = 0; t + L < nframes; t++)
            for (size_t k = 0; k < nc; k++) a += c[t * nc + k] * c[(t + L) * nc + k];
        r[j] = a / (double)(nframes - L) / v;
    }
    free(used);
    free(c);
    free(mean);
    return SWFS_OK;
}

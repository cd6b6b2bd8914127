/* A space-time reconstructor against an observation's slopes: what `learn --lags` wrote of its
 * training loops (their layers, their slopes' correlation at the lags) against the same
 * measured on the observation (run.h swfs_speckles_run_result st_*; speckles and teach). */
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int swfs_spacetime_warns(const swfs_speckles_run_result *r)
{
    int w = 0;
    if (r->st_found && r->st_mismatch > SWFS_SPACETIME_MISMATCH_WARN) w |= SWFS_SPACETIME_WARN_WIND;
    if (r->st_corr_worst < SWFS_RECON_MAXLAGS && r->st_corr_excess > 0) w |= SWFS_SPACETIME_WARN_CORR;
    return w;
}

int swfs_spacetime_check_(const char *recon, const long *lags, size_t nl, const double *s, size_t nframes,
                          size_t nslopes, size_t nsub, const char *valid, swfs_speckles_run_result *r)
{
    r->st_found = 0;
    r->st_train_vx = r->st_train_vy = r->st_obs_vx = r->st_obs_vy = r->st_mismatch = r->st_corr_excess = NAN;
    r->st_corr_worst = SIZE_MAX;
    for (size_t k = 0; k < SWFS_RECON_MAXLAGS; k++) r->st_corr_train[k] = r->st_corr_spread[k] = r->st_corr_obs[k] = NAN;
    if (!recon || nl < 2 || nl > SWFS_RECON_MAXLAGS) return SWFS_OK;
    memset(r->st_lags, 0, sizeof r->st_lags);
    memcpy(r->st_lags, lags, nl * sizeof *lags);
    swfs_fits_in *f = NULL;
    int fx = 0, fy = 0, fc = 1, fl = 0;
    long nlay = 0;
    double lx[SWFS_LEARN_MAXWLAYERS], ly[SWFS_LEARN_MAXWLAYERS];
    int rc = swfs_fits_in_open(&f, recon, NULL);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "LRNVX", &r->st_train_vx, &fx);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "LRNVY", &r->st_train_vy, &fy);
    if (!rc) rc = swfs_fits_in_key_long_opt(f, "LRNNLAY", 0, SWFS_LEARN_MAXWLAYERS, &nlay, &fl);
    for (long k = 0; !rc && k < nlay; k++) {
        char kx[32], ky[32];
        snprintf(kx, sizeof kx, "LRNL%ldX", k + 1);
        snprintf(ky, sizeof ky, "LRNL%ldY", k + 1);
        rc = swfs_fits_in_key_double(f, kx, &lx[k]);
        if (!rc) rc = swfs_fits_in_key_double(f, ky, &ly[k]);
    }
    for (size_t k = 0; !rc && k < nl && fc; k++) {
        char key[32];
        int f1 = 0, f2 = 0;
        snprintf(key, sizeof key, "LRNCOR%zu", k + 1);
        rc = swfs_fits_in_key_double_opt(f, key, &r->st_corr_train[k], &f1);
        snprintf(key, sizeof key, "LRNCSP%zu", k + 1);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, key, &r->st_corr_spread[k], &f2);
        fc = f1 && f2;
    }
    swfs_fits_in_close(f);
    if (!fx || !fy) r->st_train_vx = r->st_train_vy = NAN;
    if (rc || (!(fx && fy) && !fc) || !s) return rc;
    unsigned char *map = NULL;
    size_t mn = 0, mv = 0;
    if (fx && fy && valid && nslopes != 2 * nsub * nsub && (rc = swfs_valid_map_read(valid, &map, &mn, &mv))) return rc;
    swfs_wind_estimate e;
    e.found = 0;
    rc = swfs_spacetime_stats_(s, nframes, nslopes, nsub, map, lags, nl, fx && fy ? &e : NULL,
                               fc ? r->st_corr_obs : NULL);
    free(map);
    for (size_t k = 0; !rc && fc && k < nl; k++) {
        const double x = fabs(r->st_corr_obs[k] - r->st_corr_train[k]) - 3.0 * r->st_corr_spread[k];
        if (isfinite(x) && lags[k] && (r->st_corr_worst == SIZE_MAX || x > r->st_corr_excess)) {
            r->st_corr_excess = x;
            r->st_corr_worst = k;
        }
    }
    if (rc || !e.found) return rc;
    const long lmax = swfs_lags_max_abs(lags, nl);
    if (!nlay) { /* a map from before the layers: its mean wind against the tracked layer */
        lx[0] = r->st_train_vx;
        ly[0] = r->st_train_vy;
        nlay = 1;
        e.nlayers = 1;
        e.layer[0].vx = e.vx;
        e.layer[0].vy = e.vy;
    }
    r->st_found = 1;
    r->st_obs_nlayers = e.nlayers;
    r->st_train_nlayers = fl ? (size_t)nlay : 0;
    r->st_mismatch = -1;
    for (size_t j = 0; j < e.nlayers; j++) { /* each observed layer against the nearest taught */
        size_t best = 0;
        for (long k = 1; k < nlay; k++)
            if (hypot(e.layer[j].vx - lx[k], e.layer[j].vy - ly[k]) < hypot(e.layer[j].vx - lx[best], e.layer[j].vy - ly[best]))
                best = (size_t)k;
        const double d = hypot(e.layer[j].vx - lx[best], e.layer[j].vy - ly[best]) * (double)lmax;
        if (d > r->st_mismatch) {
            r->st_mismatch = d;
            r->st_obs_vx = e.layer[j].vx;
            r->st_obs_vy = e.layer[j].vy;
            r->st_train_vx = lx[best];
            r->st_train_vy = ly[best];
        }
    }
    return SWFS_OK;
}

/* Parameters of the Sec. 3 simulation: defaults (the paper's values), config keys,
 * checks and provenance text. Keys are documented in config/paper-sec3.conf. */
#include "sim_internal.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

void swfs_sim_params_default(swfs_sim_params *p)
{
    memset(p, 0, sizeof *p);
    p->screen.n = 2048;
    p->screen.dx = 0.04;
    p->screen.r0 = 0.15;
    p->screen.L0 = 30.0;
    p->screen.subharmonics = 1;
    p->nscreens = 5;
    p->teldiam = 6.5;
    p->pupn = 163;
    p->pupdx = 0.04;
    p->obscur = 0.1;
    p->wavelen = 3.8e-6;
    p->spacing = 0.85;
    p->target_rms = 250e-9;
    p->lag_shift = 1.0;
    p->nfx = p->nfy = 60;
    p->pixscale = 0.25;
    p->total_counts = 157000.0;
    p->gain = 1.0;
    p->ncp_trefoil = 3.8e-6 / 16.0;
    p->ncp_gauss_depth = 3.8e-6 / 8.0;
    p->ncp_gauss_radius = 1.0;
    p->ncp_gauss_x = -1.0;
    p->ncp_gauss_y = 2.0;
    p->seed = 1;
}

#define GET_D(key, field)                                                                                              \
    do {                                                                                                               \
        if ((rc = swfs_config_double(c, key, p->field, &p->field))) return rc;                                        \
    } while (0)

static int get_long(swfs_config *c, const char *key, long *v)
{
    return swfs_config_long(c, key, *v, v);
}

static int get_int(swfs_config *c, const char *key, int *v)
{
    long l = *v;
    int rc = swfs_config_long(c, key, l, &l);
    if (rc) return rc;
    if (l < -1000000 || l > 1000000) return swfs_fail(SWFS_ERR_VALUE, "setting %s=%ld: out of range", key, l);
    *v = (int)l;
    return SWFS_OK;
}

/* A file name setting into dst[cap] (kept when the key is absent). */
int swfs_sim_config_path(swfs_config *c, const char *key, char *dst, size_t cap)
{
    const char *v = NULL;
    int rc = swfs_config_string(c, key, dst, &v);
    if (rc) return rc;
    if (strlen(v) >= cap)
        return swfs_fail(SWFS_ERR_VALUE, "setting %s: a path of %zu characters; at most %zu", key, strlen(v), cap - 1);
    if (v != dst) snprintf(dst, cap, "%s", v);
    return SWFS_OK;
}

int swfs_sim_params_from_config(swfs_config *c, swfs_sim_params *p)
{
    int rc;
    long n = (long)p->screen.n;
    if ((rc = get_long(c, "screen_n", &n))) return rc;
    if (n < 2) return swfs_fail(SWFS_ERR_VALUE, "setting screen_n=%ld: need at least 2 samples", n);
    p->screen.n = (size_t)n;
    /* screen_dx and pupdx are one quantity (the pupil is cut from the screen grid). */
    double dx1 = p->screen.dx, dx2 = p->pupdx;
    if ((rc = swfs_config_double(c, "screen_dx", p->screen.dx, &dx1))) return rc;
    if ((rc = swfs_config_double(c, "pupdx", p->pupdx, &dx2))) return rc;
    if (swfs_config_has(c, "screen_dx") && swfs_config_has(c, "pupdx") && dx1 != dx2)
        return swfs_fail(SWFS_ERR_VALUE, "settings screen_dx=%g and pupdx=%g differ: the pupil is sampled on the screen grid",
                         dx1, dx2);
    if (swfs_config_has(c, "screen_dx")) dx2 = dx1;
    else dx1 = dx2;
    p->screen.dx = dx1;
    p->pupdx = dx2;
    GET_D("r0", screen.r0);
    GET_D("L0", screen.L0);
    if ((rc = get_int(c, "subharmonics", &p->screen.subharmonics))) return rc;
    if ((rc = get_int(c, "nscreens", &p->nscreens))) return rc;
    GET_D("teldiam", teldiam);
    if ((rc = get_long(c, "pupn", &p->pupn))) return rc;
    GET_D("obscur", obscur);
    if ((rc = get_int(c, "nspiders", &p->nspiders))) return rc;
    GET_D("spider_width", spider_width);
    GET_D("wavelen", wavelen);
    GET_D("spacing", spacing);
    if ((rc = get_long(c, "per_screen", &p->per_screen))) return rc;
    GET_D("target_rms", target_rms);
    GET_D("lag_shift", lag_shift);
    GET_D("lag_angle", lag_angle);
    if ((rc = get_long(c, "nfx", &p->nfx))) return rc;
    if ((rc = get_long(c, "nfy", &p->nfy))) return rc;
    GET_D("pixscale", pixscale);
    GET_D("total_counts", total_counts);
    GET_D("read_noise", read_noise);
    GET_D("gain", gain);
    GET_D("ncp_trefoil", ncp_trefoil);
    GET_D("ncp_gauss_depth", ncp_gauss_depth);
    GET_D("ncp_gauss_radius", ncp_gauss_radius);
    GET_D("ncp_gauss_x", ncp_gauss_x);
    GET_D("ncp_gauss_y", ncp_gauss_y);
    if (swfs_config_has(c, "ncp_zernike")) {
        size_t k = 3 * SWFS_SIM_MAX_ZERNIKE;
        if ((rc = swfs_config_doubles(c, "ncp_zernike", p->ncp_zernike, &k))) return rc;
        if (k % 3)
            return swfs_fail(SWFS_ERR_VALUE, "setting ncp_zernike: expected triples 'n m coefficient', got %zu numbers", k);
        p->ncp_nzernike = k / 3;
    }
    if ((rc = swfs_sim_config_path(c, "ncp_map", p->ncp_map, sizeof p->ncp_map))) return rc;
    if ((rc = swfs_sim_config_path(c, "pupil_mask", p->pupil_mask, sizeof p->pupil_mask))) return rc;
    long seed = (long)(p->seed & 0x7fffffffffffffffULL);
    if ((rc = get_long(c, "seed", &seed))) return rc;
    if (seed < 0) return swfs_fail(SWFS_ERR_VALUE, "setting seed=%ld: must be >= 0", seed);
    p->seed = (uint64_t)seed;
    if ((rc = get_int(c, "threads", &p->threads))) return rc;
    return SWFS_OK;
}

static int bad(const char *key, double v, const char *what)
{
    return swfs_fail(SWFS_ERR_VALUE, "simulation parameter %s=%g: %s", key, v, what);
}

int swfs_sim_params_check(const swfs_sim_params *p)
{
    if (p->screen.n < 2 || p->screen.n > 16384) return bad("screen_n", (double)p->screen.n, "must be 2..16384");
    if (!(p->screen.dx > 0) || !isfinite(p->screen.dx)) return bad("screen_dx", p->screen.dx, "must be > 0");
    if (fabs(p->pupdx - p->screen.dx) > 1e-12 * p->screen.dx)
        return bad("pupdx", p->pupdx, "must equal screen_dx (the pupil is cut from the screen grid)");
    if (!(p->screen.r0 > 0) || !isfinite(p->screen.r0)) return bad("r0", p->screen.r0, "must be > 0");
    if (!(p->screen.L0 > 0)) return bad("L0", p->screen.L0, "must be > 0 (inf for Kolmogorov)");
    if (p->nscreens < 1 || p->nscreens > 100000) return bad("nscreens", p->nscreens, "must be >= 1");
    if (!(p->teldiam > 0) || !isfinite(p->teldiam)) return bad("teldiam", p->teldiam, "must be > 0");
    if (p->pupn < 2 || (size_t)p->pupn > p->screen.n) return bad("pupn", (double)p->pupn, "must be 2..screen_n");
    if ((double)p->pupn * p->pupdx < p->teldiam * (1 - 1e-9))
        return bad("pupn", (double)p->pupn, "pupn * pupdx must cover teldiam");
    if (!(p->obscur >= 0 && p->obscur < 1)) return bad("obscur", p->obscur, "must be in [0, 1)");
    if (p->nspiders < 0 || p->nspiders > 64) return bad("nspiders", p->nspiders, "must be 0..64");
    if (!(p->spider_width >= 0) || p->spider_width >= p->teldiam) return bad("spider_width", p->spider_width, "must be in [0, teldiam)");
    if (!(p->wavelen > 0) || !isfinite(p->wavelen)) return bad("wavelen", p->wavelen, "must be > 0");
    if (!(p->spacing > 0) || !isfinite(p->spacing)) return bad("spacing", p->spacing, "must be > 0");
    if (p->per_screen < 0) return bad("per_screen", (double)p->per_screen, "must be >= 0 (0: as many as fit)");
    if (!(p->target_rms > 0) || !isfinite(p->target_rms)) return bad("target_rms", p->target_rms, "must be > 0");
    if (!(p->lag_shift >= 0) || !isfinite(p->lag_shift)) return bad("lag_shift", p->lag_shift, "must be >= 0");
    if (!isfinite(p->lag_angle)) return bad("lag_angle", p->lag_angle, "must be finite");
    if (p->nfx < 1 || p->nfx > 8192) return bad("nfx", (double)p->nfx, "must be 1..8192");
    if (p->nfy < 1 || p->nfy > 8192) return bad("nfy", (double)p->nfy, "must be 1..8192");
    if (!(p->pixscale > 0) || !isfinite(p->pixscale)) return bad("pixscale", p->pixscale, "must be > 0");
    if (!(p->total_counts > 0) || !isfinite(p->total_counts)) return bad("total_counts", p->total_counts, "must be > 0");
    if (!(p->read_noise >= 0) || !isfinite(p->read_noise)) return bad("read_noise", p->read_noise, "must be >= 0");
    if (!isfinite(p->gain)) return bad("gain", p->gain, "must be finite (<= 0: no photon noise)");
    if (!isfinite(p->ncp_trefoil)) return bad("ncp_trefoil", p->ncp_trefoil, "must be finite");
    if (!isfinite(p->ncp_gauss_depth)) return bad("ncp_gauss_depth", p->ncp_gauss_depth, "must be finite");
    if (p->ncp_gauss_depth != 0 && !(p->ncp_gauss_radius > 0))
        return bad("ncp_gauss_radius", p->ncp_gauss_radius, "must be > 0");
    if (!isfinite(p->ncp_gauss_x) || !isfinite(p->ncp_gauss_y)) return bad("ncp_gauss_x/y", p->ncp_gauss_x, "must be finite");
    if (p->ncp_nzernike > SWFS_SIM_MAX_ZERNIKE) return bad("ncp_zernike", (double)p->ncp_nzernike, "too many terms");
    for (size_t k = 0; k < p->ncp_nzernike; k++) {
        const double n = p->ncp_zernike[3 * k], m = p->ncp_zernike[3 * k + 1], a = p->ncp_zernike[3 * k + 2];
        if (n != floor(n) || m != floor(m) || n < 0 || fabs(m) > n || fmod(n - fabs(m), 2.0) != 0 || n > 40 ||
            !isfinite(a))
            return swfs_fail(SWFS_ERR_VALUE,
                             "simulation parameter ncp_zernike: term %zu (n=%g m=%g coef=%g) is not a Zernike "
                             "(need integers n >= |m|, n - |m| even, n <= 40)",
                             k + 1, n, m, a);
    }
    if (p->threads < 0 || p->threads > 256) return bad("threads", p->threads, "must be 0..256 (0: all CPUs)");
    /* The sub-grids must fit in the screen. */
    const long step = lround(p->spacing * p->teldiam / p->screen.dx);
    if (step < 1) return bad("spacing", p->spacing, "sub-grid step is below one sample");
    const long fit = ((long)p->screen.n - p->pupn) / step + 1;
    if (p->per_screen > fit)
        return swfs_fail(SWFS_ERR_VALUE,
                         "simulation parameter per_screen=%ld: only %ld sub-grids of %ld samples at a step of %ld fit "
                         "across a %zu-sample screen",
                         p->per_screen, fit, p->pupn, step, p->screen.n);
    return SWFS_OK;
}

static size_t append(char *buf, size_t cap, size_t len, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 4, 5)))
#endif
    ;

static size_t append(char *buf, size_t cap, size_t len, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int k = vsnprintf(len < cap ? buf + len : NULL, len < cap ? cap - len : 0, fmt, ap);
    va_end(ap);
    return len + (k > 0 ? (size_t)k : 0);
}

size_t swfs_sim_params_format(const swfs_sim_params *p, char *buf, size_t cap)
{
    size_t len = 0;
    if (cap) buf[0] = '\0';
    len = append(buf, cap, len, "screen_n=%zu\nscreen_dx=%.15g\nr0=%.15g\nL0=%.15g\nsubharmonics=%d\nnscreens=%d\n",
                 p->screen.n, p->screen.dx, p->screen.r0, p->screen.L0, p->screen.subharmonics, p->nscreens);
    len = append(buf, cap, len, "teldiam=%.15g\npupn=%ld\nobscur=%.15g\nnspiders=%d\nspider_width=%.15g\nwavelen=%.15g\n",
                 p->teldiam, p->pupn, p->obscur, p->nspiders, p->spider_width, p->wavelen);
    len = append(buf, cap, len, "spacing=%.15g\nper_screen=%ld\ntarget_rms=%.15g\nlag_shift=%.15g\nlag_angle=%.15g\n",
                 p->spacing, p->per_screen, p->target_rms, p->lag_shift, p->lag_angle);
    len = append(buf, cap, len, "nfx=%ld\nnfy=%ld\npixscale=%.15g\ntotal_counts=%.15g\nread_noise=%.15g\ngain=%.15g\n",
                 p->nfx, p->nfy, p->pixscale, p->total_counts, p->read_noise, p->gain);
    len = append(buf, cap, len,
                 "ncp_trefoil=%.15g\nncp_gauss_depth=%.15g\nncp_gauss_radius=%.15g\nncp_gauss_x=%.15g\nncp_gauss_y=%.15g\n",
                 p->ncp_trefoil, p->ncp_gauss_depth, p->ncp_gauss_radius, p->ncp_gauss_x, p->ncp_gauss_y);
    if (p->ncp_nzernike) {
        len = append(buf, cap, len, "ncp_zernike=");
        for (size_t k = 0; k < p->ncp_nzernike && k < SWFS_SIM_MAX_ZERNIKE; k++)
            len = append(buf, cap, len, "%s%g %g %.15g", k ? ", " : "", p->ncp_zernike[3 * k], p->ncp_zernike[3 * k + 1],
                         p->ncp_zernike[3 * k + 2]);
        len = append(buf, cap, len, "\n");
    }
    if (p->ncp_map[0]) len = append(buf, cap, len, "ncp_map=%s\n", p->ncp_map);
    if (p->pupil_mask[0]) len = append(buf, cap, len, "pupil_mask=%s\n", p->pupil_mask);
    len = append(buf, cap, len, "seed=%llu\nthreads=%d\n", (unsigned long long)p->seed, p->threads);
    return len;
}

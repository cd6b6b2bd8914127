/* speckles --mean-loop teach: the loops whose residual means speckles' --mean-loop compares
 * with this run's reconstruction of them, simulated by speckles itself from what the
 * observation's files say of the system (run.h swfs_mean_teach_result; docs/telemetry.md,
 * "The mean's miss from loops speckles simulates"). The pyramid's miss of the residual's time
 * mean is mostly the sensor's response under any residual of the loop's statistics (a pattern
 * at the pupil's rim, the same in every loop of the system), so loops of the described system
 * give it without the observation's own truth. */
#include "specklewfs/aperture.h"
#include "specklewfs/atomic.h"
#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/table.h"
#include "specklewfs/team.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/version.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <errno.h>
#include <inttypes.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* What the description's rule is: part of the loops' fingerprint (a change of it makes them
 * anew). */
#define MEAN_TEACH_RULE "mean-teach 6: sensor keys, noise, wind layers, knee, DM pitch from the files; r0 fitted to the power; " \
                        "more loops where the space-time loops' map's learning curve asks; twice the first where it does not fall"

/* r0's fit: at most this many pairs of loops checked against the telemetry's power (then one
 * more at the last prediction, unchecked), and the step below which the fit stops whatever the
 * power's scatter: loops at r0 50 % and 32 % off cost a 12 x 12 pyramid's NCP error 3.8 and
 * 4.0 nm, so 5 % about 0.5 nm, within the seeds' scatter (docs/telemetry.md, "The loops' r0
 * fitted to the signals' power"). */
#define R0_PAIRS 3
#define R0_STEP 0.05

/* The sensor from the telemetry's header, into c unless given: WFSTYPE (a pyramid where it
 * names one, a Shack-Hartmann where it names that), PYRMOD, PYRNMOD and WFSLAM for a
 * pyramid. *pyr: the loops sense with a pyramid. */
static int sensor_keys(const char *path, swfs_config *c, int *pyr)
{
    swfs_fits_in *f = NULL;
    char type[72] = "";
    int kind = 0, fm = 0, fn = 0, fl = 0;
    double mod = 0, lam = 0;
    long nmod = 0;
    int rc = swfs_telemetry_sensor(path, &kind, type, sizeof type);
    if (!rc) rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "PYRMOD", &mod, &fm);
    if (!rc) rc = swfs_fits_in_key_long_opt(f, "PYRNMOD", 0, 4096, &nmod, &fn);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "WFSLAM", &lam, &fl);
    swfs_fits_in_close(f);
    if (rc) return rc;
    if (!swfs_config_has(c, "wfs")) {
        if (kind != SWFS_WFS_PYRAMID && kind != SWFS_WFS_SH)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: %s%s%s: the loops need the sensor; give it (--teach-set wfs=pyramid or "
                             "wfs=sh)", path, kind ? "WFSTYPE = '" : "no WFSTYPE keyword", kind ? type : "",
                             kind ? "'" : "");
        rc = swfs_config_set_kv(c, "wfs", kind == SWFS_WFS_PYRAMID ? "pyramid" : "sh");
    }
    const char *wfs = NULL;
    if (!rc) rc = swfs_config_string(c, "wfs", "sh", &wfs);
    if (rc) return rc;
    *pyr = !strcmp(wfs, "pyramid");
    if (!*pyr) return SWFS_OK;
    if (!swfs_config_has(c, "pyr_mod") && !fm)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: no PYRMOD keyword: the loops' pyramid needs its modulation radius "
                         "(give --teach-set pyr_mod=R, in lambda/D at the sensing wavelength)", path);
    if (!swfs_config_has(c, "wfs_wavelen") && !(fl && lam > 0))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: no WFSLAM keyword: the loops' pyramid needs its sensing wavelength "
                         "(give --teach-set wfs_wavelen=M, in metres)", path);
    rc = swfs_config_put_(c, "pyr_mod", "%.17g", mod);
    if (!rc && fn) rc = swfs_config_put_(c, "pyr_nmod", "%ld", nmod);
    if (!rc) rc = swfs_config_put_(c, "wfs_wavelen", "%.17g", lam);
    return rc;
}

/* A layout's actuators at pitch p (hexapolar or square, as the simulator lays them out). */
static int layout_count(int square, double p, const swfs_geom *g, size_t *n, double *nn)
{
    double *xy = NULL;
    const int rc = square ? swfs_actuators_square(g->teldiam, p, g->pupdx, &xy, n)
                          : swfs_actuators_hexapolar(g->teldiam, p, g->pupdx, &xy, n);
    if (nn) *nn = rc ? 0 : swfs_points_pitch(xy, *n);
    free(xy);
    return rc;
}

/* The loops' truth on a grid of half their DM's pitch (teach's output grid, swfs_outgrid_make_:
 * work/outgrid.fits, its path put as truth_actuators into c), where their own map is learned
 * from them: a map on the DM's actuators cannot write the residual beyond the DM's cutoff,
 * which the lagged signals of frozen flow partly tell (docs/telemetry.md, "The loops' map on a
 * grid finer than the DM"). Beside it work/outfuncs.fits, the points' functions on the pupil
 * grid (swfs_points_basis_ over the observation's pupil; NAXIS3 = the points, float32): the
 * functions learn --mean-miss-over takes for these loops. */
static int loops_outgrid(const swfs_speckles_run_options *o, const swfs_geom *g, swfs_config *c, const char *work)
{
    swfs_ts_params p;
    swfs_ts_params_default(&p);
    int rc = swfs_ts_params_from_config(c, &p);
    char path[4400], fpath[4400];
    double pitch = 0, *xy = NULL, *mask = NULL, *F = NULL;
    size_t n = 0;
    const size_t np = (size_t)g->pupn, n2 = np * np;
    if (!rc) rc = swfs_outgrid_make_(&p, work, path, sizeof path, &pitch, &xy, &n);
    if (!rc) rc = swfs_config_put_(c, "truth_actuators", "%s", path);
    swfs_real *pm = NULL;
    if (!rc && o->mask) {
        if (!(rc = swfs_pupil_mask_read(o->mask, np, &pm))) mask = pm->data;
    } else if (!rc) {
        if (!(mask = malloc(n2 * sizeof *mask))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        else rc = swfs_aperture_make(mask, np, g->pupdx, g->teldiam, g->obscur, 0, 0);
    }
    if (!rc) rc = swfs_points_functions_(xy, n, g, mask, &F);
    swfs_fits_out *f = NULL;
    if (!rc && snprintf(fpath, sizeof fpath, "%.4300s/outfuncs.fits", work) < (int)sizeof fpath) {
        swfs_outputs_begin();
        rc = swfs_fits_out_create(&f, fpath);
        if (!rc) rc = swfs_fits_out_real(f, NULL, &(swfs_real){np, np, n, F}, -32);
        if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "", "the output points' (outgrid.fits) interpolation on the "
                                               "pupil grid, one plane per point");
        if (rc) swfs_fits_out_abort(f);
        else rc = swfs_fits_out_commit(f);
        const int erc = swfs_outputs_end(rc == SWFS_OK);
        if (!rc) rc = erc;
    }
    free(F);
    if (pm) swfs_real_free(pm);
    else free(mask);
    free(xy);
    return rc ? swfs_fail_context(rc, "the loops' output grid") : SWFS_OK;
}

/* The DM's pitch from the linear model's basis (act_pitch, unless the DM is given): the
 * registration's pitch for a basis on the DM's grid (a square grid). On the pupil grid: the
 * median distance m between the centroids (of their positive part) of the functions within 0.7
 * of the pupil's radius (an actuator beyond the edge has its centroid pulled inward), the
 * pitch of a hexapolar and of a square layout whose own median distance is m, and then within
 * 10 % of it the pitch whose layout has the count nearest the functions' (the simulator's
 * layouts: exact where the DM is one of them), the layout of the nearer count. A basis whose
 * count neither comes within a quarter of (modes, not influence functions) is refused. */
static int dm_pitch(const swfs_speckles_run_options *o, const swfs_geom *g, swfs_config *c, double *pitch)
{
    *pitch = 0;
    if (swfs_config_has(c, "actuators") || swfs_config_has(c, "act_pitch")) return SWFS_OK;
    if (o->lin.reg.pitch > 0) {
        *pitch = o->lin.reg.pitch;
        int rc = swfs_config_put_(c, "act_pitch", "%.17g", *pitch);
        return rc ? rc : swfs_config_put_(c, "act_square", "1");
    }
    swfs_real *b = NULL;
    int rc = swfs_fits_read_real(o->lin.basis, NULL, &b, NULL);
    if (rc) return rc;
    const size_t n = (size_t)g->pupn, nk = b->nz;
    if (b->nx != n || b->ny != n) {
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the basis is %zu x %zu, not the pupil grid's %zu x %zu: the loops' DM needs "
                       "its pitch (--dm-pitch for a basis on the DM's grid, or --teach-set act_pitch=M)", o->lin.basis,
                       b->nx, b->ny, n, n);
        swfs_real_free(b);
        return rc;
    }
    double *xy = malloc(2 * (nk ? nk : 1) * sizeof *xy), *in = malloc(2 * (nk ? nk : 1) * sizeof *in), m = 0;
    size_t k2 = 0, ki = 0;
    if (!xy || !in) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    const double c0 = 0.5 * (double)(n - 1), dx = g->pupdx, R = 0.5 * g->teldiam;
    for (size_t k = 0; !rc && k < nk; k++) {
        const double *v = b->data + k * n * n;
        double sw = 0, sx = 0, sy = 0;
        for (size_t j = 0; j < n; j++)
            for (size_t i = 0; i < n; i++) {
                const double w = v[j * n + i] > 0 ? v[j * n + i] : 0;
                sw += w;
                sx += w * ((double)i - c0) * dx;
                sy += w * ((double)j - c0) * dx;
            }
        if (sw > 0) {
            xy[2 * k2] = sx / sw;
            xy[2 * k2 + 1] = sy / sw;
            k2++;
        }
    }
    swfs_real_free(b);
    /* the inner functions' own median distance (among themselves: their neighbours are inner
     * too but for the ring at 0.7 R, which the median leaves aside) */
    for (size_t k = 0; !rc && k < k2; k++)
        if (hypot(xy[2 * k], xy[2 * k + 1]) < 0.7 * R) {
            in[2 * ki] = xy[2 * k];
            in[2 * ki + 1] = xy[2 * k + 1];
            ki++;
        }
    if (!rc && k2 < 2) rc = swfs_fail(SWFS_ERR_VALUE, "%s: %zu functions with a positive part: no DM pitch from them "
                                      "(give --teach-set act_pitch=M)", o->lin.basis, k2);
    if (!rc) m = ki >= 8 ? swfs_points_pitch(in, ki) : swfs_points_pitch(xy, k2);
    free(xy);
    free(in);
    if (!rc && !(m > 0 && isfinite(m))) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no DM pitch from its functions' centroids "
                                                       "(give --teach-set act_pitch=M)", o->lin.basis);
    double best = INFINITY, bp = 0;
    int bsq = 0;
    size_t bn = 0, near[2] = {0, 0};
    for (int sq = 0; !rc && sq < 2; sq++) {
        /* the layout's pitch of median distance m (its points along a ring sit closer than
         * its pitch, or farther) */
        double p = m, q = 0;
        size_t cnt = 0;
        for (int it = 0; it < 8 && !rc; it++) {
            rc = layout_count(sq, p, g, &cnt, &q);
            if (rc || !(q > 0) || fabs(q - m) <= 1e-4 * m) break;
            p *= m / q;
        }
        /* within 10 % of it, the count nearest the functions' (ties: the pitch nearer p) */
        double lbest = INFINITY;
        for (int s = -100; !rc && s <= 100; s++) {
            const double ps = p * (1.0 + 0.001 * s);
            if ((rc = layout_count(sq, ps, g, &cnt, NULL))) break;
            const double d = fabs((double)cnt - (double)nk) + 1e-3 * fabs((double)s);
            if (d < lbest) { lbest = d; near[sq] = cnt; }
            if (d < best) { best = d; bp = ps; bsq = sq; bn = cnt; }
        }
    }
    if (rc) return rc;
    if (fabs((double)bn - (double)nk) > 0.25 * (double)nk)
        return swfs_fail(SWFS_ERR_VALUE, "%s: %zu functions, their centroids %.4g m apart, but a DM of about that pitch "
                         "has at most %zu (hexapolar) or %zu (square) actuators near that: not one DM's influence "
                         "functions? Give the loops' DM (--teach-set act_pitch=M or actuators=FILE)", o->lin.basis, nk, m,
                         near[0], near[1]);
    *pitch = bp;
    rc = swfs_config_put_(c, "act_pitch", "%.17g", *pitch);
    if (!rc && bsq) rc = swfs_config_put_(c, "act_square", "1");
    return rc;
}

/* The layers `wind` tracks in the telemetry (nlayers, layer_speed, layer_dir, equal shares),
 * unless given. */
static int layers(char *const *names, size_t n, const swfs_geom *g, size_t nsub, double rate, swfs_config *c,
                  swfs_mean_teach_result *r)
{
    if (swfs_config_has(c, "nlayers") || swfs_config_has(c, "layer_speed")) return SWFS_OK;
    swfs_wind_run_options wo = {(const char *const *)names, n, NULL, (long)nsub, g->teldiam, rate};
    swfs_wind_run_result wr;
    int rc = swfs_wind_run(&wo, &wr);
    if (rc) return swfs_fail_context(rc, "the loops' layers from the telemetry (wind)");
    const swfs_wind_estimate *e = &wr.est;
    if (!e->found || !e->nlayers)
        return swfs_fail(SWFS_ERR_VALUE, "%s: `wind` tracked no frozen-flow layer in the telemetry (%zu subapertures with "
                         "signal): give the loops' layers (--teach-set nlayers=N layer_speed=V,... layer_dir=DEG,...)",
                         names[0], e->nvalid);
    const size_t nl = e->nlayers < SWFS_TS_MAX_LAYERS ? e->nlayers : SWFS_TS_MAX_LAYERS;
    char sp[256] = "", dir[256] = "", fr[256] = "";
    size_t a = 0, b = 0, d = 0;
    for (size_t l = 0; l < nl; l++) {
        r->speed[l] = e->layer[l].speed;
        r->direction[l] = e->layer[l].direction;
        a += (size_t)snprintf(sp + a, sizeof sp - a, "%s%.6g", l ? "," : "", r->speed[l]);
        b += (size_t)snprintf(dir + b, sizeof dir - b, "%s%.6g", l ? "," : "", r->direction[l]);
        d += (size_t)snprintf(fr + d, sizeof fr - d, "%s%.6g", l ? "," : "", 1.0 / (double)nl);
    }
    r->nlayers = nl;
    rc = swfs_config_put_(c, "nlayers", "%zu", nl);
    if (!rc) rc = swfs_config_put_(c, "layer_speed", "%s", sp);
    if (!rc) rc = swfs_config_put_(c, "layer_dir", "%s", dir);
    if (!rc) rc = swfs_config_put_(c, "layer_frac", "%s", fr);
    return rc;
}

/* The sensor's white noise (the telemetry's curl, wfs.h) as the loops' noise: a pyramid's
 * photons per subaperture and frame, 1 / var (its signals' noise with N photons is 1 / sqrt N:
 * the four images' Poisson counts over their sum), or a Shack-Hartmann's slope noise, unless
 * given; then the loops' modal filter (ao_modes) from the knee of the telemetry's variances
 * along the DM's modes through the loops' own sensor, unless a filter is given. *white,
 * *slope_var: the same call's white and whole variance per value (residual_power's). */
static int noise_and_knee(const char *path, const swfs_real *s, size_t nsub, int pyr, swfs_config *c,
                          swfs_mean_teach_result *r, double *white, double *slope_var)
{
    double var = 0;
    int rc = swfs_slopes_white_noise(s->data, s->ny, s->nx, nsub, NULL, &var, NULL, slope_var);
    *white = var;
    if (rc) return swfs_fail_context(rc, "the white noise of %s", path);
    r->noise_rms = sqrt(var);
    r->photons = r->slope_noise = NAN;
    if (pyr && !swfs_config_has(c, "pyr_photons")) {
        if (!(var > 0)) return swfs_fail(SWFS_ERR_VALUE, "%s: no white noise in the pyramid's signals: the loops' photons "
                                         "cannot come from it (give --teach-set pyr_photons=N)", path);
        r->photons = 1.0 / var;
        rc = swfs_config_put_(c, "pyr_photons", "%.6g", r->photons);
    } else if (!pyr && !swfs_config_has(c, "slope_noise")) {
        r->slope_noise = r->noise_rms;
        rc = swfs_config_put_(c, "slope_noise", "%.6g", r->slope_noise);
    }
    if (rc || swfs_ts_config_gives_filter(c)) return rc;
    /* the description so far, read as the loops will be (a copy: reading marks keys used) */
    swfs_config *cc = swfs_config_new();
    swfs_ts_params p;
    double *v = NULL;
    size_t nv = 0;
    rc = cc ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t k = 0; !rc && k < swfs_config_count(c); k++) rc = swfs_config_set_kv(cc, swfs_config_key(c, k), swfs_config_value(c, k));
    if (!rc) swfs_ts_params_default(&p);
    if (!rc) rc = swfs_ts_params_from_config(cc, &p);
    if (!rc) rc = swfs_ts_mode_variance(&p, s->data, s->ny, s->nx, &v, &nv);
    if (!rc) r->knee = swfs_mode_knee(v, nv);
    if (!rc && !r->knee)
        rc = swfs_fail(SWFS_ERR_NUMERIC, "%s: %zu DM modes after piston, too few for the knee of their variances (at least "
                       "6); give the loops' filter (--teach-set ao_modes=K)", path, nv);
    if (!rc) rc = swfs_config_put_(c, "ao_modes", "%zu", r->knee);
    free(v);
    swfs_config_free(cc);
    return rc ? swfs_fail_context(rc, "the loops' modal filter from %s", path) : SWFS_OK;
}

/* The residual's power per value: each value's variance over the frames, its time mean and
 * each frame's tip-tilt taken out (where a telescope's vibration sits, which the loops do not
 * simulate), less the white noise (swfs_slopes_white_noise's slope_var less its var: the loops'
 * noise is the telemetry's already). */
static int power_above_noise(const char *path, double var, double white, double *pw)
{
    *pw = var - white;
    if (!(*pw > 0))
        return swfs_fail(SWFS_ERR_VALUE, "%s: no residual power above the white noise (variance %.3g, white %.3g per value): "
                         "the loops' r0 cannot be fitted to it (give --teach-set r0=R)", path, var, white);
    return SWFS_OK;
}

/* The residual's power (power_above_noise) in frames first.. of s. */
static int residual_power(const char *path, const swfs_real *s, size_t first, size_t nsub, double *pw)
{
    double white = 0, var = 0;
    if (s->ny < first + 16)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: %zu frames, %zu after the loop's first exposure: too few for its power (16)",
                         path, s->ny, s->ny > first ? s->ny - first : 0);
    const int rc = swfs_slopes_white_noise(s->data + first * s->nx, s->ny - first, s->nx, nsub, NULL, &white, NULL, &var);
    return rc ? swfs_fail_context(rc, "the residual power of %s", path) : power_above_noise(path, var, white, pw);
}

/* The power of loop k (work/mean_KK/slopes_000.fits, from its first exposure on). */
static int loop_power(const char *work, size_t k, size_t nslopes, size_t nsub, double *pw)
{
    char dir[4300], path[4400];
    snprintf(dir, sizeof dir, "%.4000s/mean_%02zu", work, k);
    snprintf(path, sizeof path, "%s/slopes_000.fits", dir);
    swfs_real *s = NULL;
    int rc = swfs_telemetry_read(path, nslopes, &s, NULL);
    if (!rc) rc = residual_power(path, s, swfs_loop_first_frame_(dir), nsub, pw);
    swfs_real_free(s);
    return rc;
}

/* The loops, r0 fitted unless given: the residual's rms scales as r0^(-5/6) (fitting and servo
 * lag both), so its power as r0^(-5/3) for a linear sensor; a pyramid's optical gain falls as
 * the residual grows, so its power grows more slowly, and the slope in log-log is taken from
 * the pairs simulated (a secant) once there are two. A pair of loops (0 and 1) at r0; their
 * mean power against the telemetry's gives the next r0; the fit stops where that step is
 * within the scatter (the pair's two powers' ratio gives one loop's; the observation's and the
 * pair mean's combined are sqrt(3/4) of that ratio's log) or under R0_STEP; after R0_PAIRS a
 * last pair at the prediction. Then loops 2.. at the kept pair's r0. */
static int loops_fitted(swfs_teach_run_options *to, int given, double pobs, size_t nl, size_t nslopes, size_t nsub,
                        swfs_mean_teach_result *r)
{
    const char *what = "simulating the loops of the residual's mean (--mean-loop teach)";
    double r0 = to->sim.base.screen.r0, lr = 0, lv = 0; /* the previous pair's log r0 and log power */
    int rc = SWFS_OK;
    for (size_t p = 0; !given && !rc; p++) {
        to->sim.base.screen.r0 = r0;
        double pa = 0, pb = 0;
        rc = swfs_teach_loops_(to, "mean", 0, 2, "fitting the loops' r0 to the telemetry's residual power (a pair of loops)");
        if (!rc) rc = loop_power(to->work, 0, nslopes, nsub, &pa);
        if (!rc) rc = loop_power(to->work, 1, nslopes, nsub, &pb);
        if (rc) break;
        r->r0_pairs = p + 1;
        r->power_ratio = 0.5 * (pa + pb) / pobs;
        if (p == R0_PAIRS) break; /* the last prediction's pair, kept unchecked */
        const double lr1 = log(r0), lv1 = log(0.5 * (pa + pb));
        double b = p ? (lv1 - lv) / (lr1 - lr) : -5.0 / 3.0;
        if (!(b < -0.1) || !isfinite(b)) b = -5.0 / 3.0; /* the pairs' scatter hid the slope */
        const double step = (log(pobs) - lv1) / b, scatter = fabs(log(pa / pb)) * sqrt(0.75) / fabs(b);
        if (fabs(step) < fmax(log1p(R0_STEP), scatter)) break;
        lr = lr1;
        lv = lv1;
        r0 = exp(lr1 + fmax(-M_LN2, fmin(M_LN2, step))); /* a factor 2 a pair at most: a secant
                                                           through two pairs' scatter can throw far */
    }
    r->r0 = r0;
    const size_t first = given ? 0 : 2;
    if (!rc && nl > first) rc = swfs_teach_loops_(to, "mean", first, nl - first, what);
    return rc;
}

/* mean_loops.conf's line of the loops' count, written and read back (made_for) */
#define LOOPS_LINE "# loops %zu (the first %zu; more where the loops' map's learning curve asked: "

/* The description's text (mean_loops.conf): the fingerprint first, then key = value. */
static int write_description(const char *path, const swfs_config *c, const char *fpr, const swfs_mean_teach_result *r)
{
    size_t cap = 512;
    for (size_t k = 0; k < swfs_config_count(c); k++) cap += strlen(swfs_config_key(c, k)) + strlen(swfs_config_value(c, k)) + 8;
    char *buf = malloc(cap);
    if (!buf) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    size_t len = (size_t)snprintf(buf, cap, "# fingerprint %s\n# the loops of speckles --mean-loop teach (simulate "
                                  "mode=timeseries keys; seeds in the fingerprint)\n" LOOPS_LINE "%.3g excess, %zu "
                                  "frames)\n", fpr,
                                  r->nloops, r->nloops_first, r->curve_excess, r->curve_frames);
    for (size_t k = 0; k < swfs_config_count(c) && len < cap; k++)
        len += (size_t)snprintf(buf + len, cap - len, "%s = %s\n", swfs_config_key(c, k), swfs_config_value(c, k));
    const int rc = len < cap ? swfs_text_write(path, buf, len) : swfs_fail(SWFS_ERR_INTERNAL, "mean_loops.conf overflow");
    free(buf);
    return rc;
}

/* 1 when path's first line is the fingerprint fpr and every loop's truth.fits is there (the
 * description's count, at least n, at most SWFS_MEAN_TEACH_MAX); then the loops' r0 as the
 * description wrote it (r->r0; r0_pairs 0: not fitted by this run) and the count (r->nloops,
 * with the curve's figures). */
static int made_for(const char *path, const char *fpr, char (*dirs)[4400], size_t n, swfs_mean_teach_result *r)
{
    FILE *f = fopen(path, "r");
    if (!f) return 0;
    char line[4500] = "", want[64];
    int ok = fgets(line, sizeof line, f) != NULL;
    snprintf(want, sizeof want, "# fingerprint %s\n", fpr);
    ok = ok && !strcmp(line, want);
    size_t nl = 0, first = 0, frames = 0;
    double excess = NAN;
    while (ok && fgets(line, sizeof line, f)) {
        (void)sscanf(line, "r0 = %lf", &r->r0);
        (void)sscanf(line, LOOPS_LINE "%lf excess, %zu", &nl, &first, &excess, &frames);
    }
    fclose(f);
    if (!ok || nl < n || nl > SWFS_MEAN_TEACH_MAX) return 0;
    r->nloops = nl;
    r->nloops_first = first;
    r->curve_excess = excess;
    r->curve_frames = frames;
    for (size_t k = 0; k < nl; k++) {
        char t[4500];
        snprintf(t, sizeof t, "%s/truth.fits", dirs[k]);
        if (access(t, R_OK)) return 0;
    }
    return 1;
}

/* The description's fingerprint: the library's version and the rule, its keys and values in
 * order, the loops and their seed, and the contents of the files it names. */
static int fingerprint(const swfs_config *c, size_t nloops, size_t max_loops, uint64_t seed, char out[17])
{
    uint64_t h = 0xcbf29ce484222325ULL;
    h = swfs_fnv_text_(swfs_fnv_text_(h, "specklewfs " SWFS_VERSION), MEAN_TEACH_RULE);
    for (size_t k = 0; k < swfs_config_count(c); k++)
        h = swfs_fnv_text_(swfs_fnv_text_(h, swfs_config_key(c, k)), swfs_config_value(c, k));
    char v[64];
    snprintf(v, sizeof v, "loops %zu max %zu seed %" PRIu64, nloops, max_loops, seed);
    h = swfs_fnv_text_(h, v);
    int rc = SWFS_OK;
    for (size_t i = 0; !rc && i < swfs_config_count(c); i++) {
        const char *k = swfs_config_key(c, i);
        if (!strcmp(k, "actuators") || !strcmp(k, "pupil_mask") || !strcmp(k, "valid"))
            rc = swfs_fnv_file_(&h, k, swfs_config_value(c, i));
    }
    if (!rc) snprintf(out, 17, "%016" PRIx64, h);
    return rc;
}

/* More loops where the map the loops' map step learns from them asks for more frames
 * (run_loops_map.c): learn's learning curve of the per-frame map over the first nl loops, over
 * the pupil's annulus
 * (the points whose wavefront makes the speckles), gives the frames that bring the map within
 * SWFS_LEARN_CURVE_EXCESS of unlimited frames' misfit (teach's rule for its own loops,
 * run_teach.c); loops nl.. of the same description up to that many, at most max. */
static int loops_as_curve_asks(const swfs_speckles_run_options *o, const swfs_teach_run_options *to, const swfs_geom *g,
                               char (*dirs)[4400], size_t nl, size_t max, swfs_mean_teach_result *r)
{
    const char *d[SWFS_MEAN_TEACH_MAX];
    for (size_t k = 0; k < nl; k++) d[k] = dirs[k];
    char out[4500];
    snprintf(out, sizeof out, "%.4300s/loops_curve.fits", r->work);
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = d;
    lo.ndirs = nl;
    lo.out = out;
    lo.no_heldout = 1;
    lo.mean_miss = 0;
    lo.curve = 1;
    lo.curve_radius[0] = 0.5 * g->obscur * g->teldiam;
    lo.curve_radius[1] = 0.5 * g->teldiam;
    lo.prov = o->prov;
    lo.nprov = o->nprov;
    lo.progress = o->progress;
    lo.progress_ctx = o->progress_ctx;
    swfs_learn_run_result lr;
    int rc = swfs_learn_run(&lo, &lr);
    (void)remove(out); /* the map of the first loops: the loops' map step learns from all */
    if (rc == SWFS_ERR_STOPPED) return rc; /* the caller asked the run to stop */
    if (rc) { /* no curve: the first loops stay, and the loops' map step says what it cannot learn */
        swfs_clear_error();
        return SWFS_OK;
    }
    /* the space-time map the step learns where the frames allow (swfs_loops_map_lags_) has its
     * lags' times the inputs, and a least-squares map's excess over its floor goes as its inputs
     * over its frames (run_loops_map.c): its lags' times the frames */
    const size_t nlags = SWFS_SPACETIME_NLAGS;
    r->curve_excess = lr.curve_excess;
    r->curve_frames = lr.curve_frames > SIZE_MAX / nlags ? SIZE_MAX : lr.curve_frames * nlags;
    /* teach's rule (run_teach.c): as many as the curve asks, or, where it does not fall and
     * so cannot tell, twice the first loops; at most max */
    swfs_learn_run_result lq = lr;
    lq.curve_frames = r->curve_frames;
    int doubled = 0;
    const size_t want = swfs_teach_more_loops_(&lq, nl, max, &doubled);
    if (want > nl)
        rc = swfs_teach_loops_(to, "mean", nl, want - nl, "simulating more loops (the loops' map's learning curve)");
    if (!rc) r->nloops = want;
    return rc;
}

static int mean_teach(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir, const swfs_geom *g,
                      size_t nslopes, swfs_mean_teach_result *r, char (*dirs)[4400])
{
    const double t0 = swfs_wall_seconds();
    const size_t nl = o->mean_teach_loops;
    char **names = calloc(t->ncubes ? t->ncubes : 1, sizeof *names);
    size_t n = 0, total = 0;
    int made = 0;
    swfs_config *c = swfs_config_new();
    swfs_real *obs = NULL;
    double rate = 0;
    int rc = names && c ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = swfs_speckles_table_files_(t, tdir, names, &n);
    if (!rc && !n) rc = swfs_fail(SWFS_ERR_VALUE, "%s: names no telemetry file", o->timing);
    if (!rc) rc = swfs_speckles_work_folder_(o, r->work, sizeof r->work, &made);
    /* the observation's length: the loops as long (their camera over all of it but the loop's
     * first 300 frames), at least 1000 frames */
    for (size_t k = 0; !rc && k < n; k++) {
        swfs_fits_in *f = NULL;
        if (!(rc = swfs_fits_in_open(&f, names[k], NULL))) total += swfs_fits_in_shape(f)->ny;
        swfs_fits_in_close(f);
    }
    if (!rc) rc = swfs_telemetry_read(names[0], nslopes, &obs, &rate);
    if (!rc && o->wfs_hz > 0) rate = o->wfs_hz;
    if (!rc && !(rate > 0))
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: no WFSRATE keyword: the loops need the WFS frame rate (give --wfs-hz)", names[0]);
    if (!rc) rc = swfs_config_set_kv(c, "mode", "timeseries");
    for (size_t k = 0; !rc && k < o->nteach_keys; k++) rc = swfs_config_set(c, o->teach_keys[k]);
    const size_t loop_frames = total > 1000 ? total : 1000;
    if (!rc) rc = swfs_config_put_(c, "wfs_rate", "%.17g", rate);
    if (!rc) rc = swfs_config_put_(c, "frame_ratio", "10");
    if (!rc) rc = swfs_config_put_(c, "ncubes", "1");
    if (!rc) rc = swfs_config_put_(c, "cube_frames", "%zu", (loop_frames - 300) / 10);
    if (!rc) rc = swfs_config_put_(c, "cube_gap", "0");
    if (!rc) rc = swfs_config_put_(c, "wfs_file_frames", "%zu", loop_frames + 20);
    /* the true residual per frame, for the map learned from the loops (run_loops_map.c) */
    if (!rc) rc = swfs_config_put_(c, "export_truth", "1");
    int pyr = 0;
    if (!rc) rc = sensor_keys(names[0], c, &pyr);
    r->pyramid = pyr;
    if (!rc) rc = swfs_teach_describe_geom_(c, g, NULL, o->mask, NULL, names[0]);
    if (!rc) rc = dm_pitch(o, g, c, &r->act_pitch);
    const size_t nsub = (size_t)llround(sqrt((double)nslopes / 2.0));
    if (!rc) rc = layers(names, n, g, nsub, rate, c, r);
    double white = 0, svar = 0;
    if (!rc) rc = noise_and_knee(names[0], obs, nsub, pyr, c, r, &white, &svar);
    const int r0_given = swfs_config_has(c, "r0");
    if (!rc && !r0_given) rc = power_above_noise(names[0], svar, white, &r->power);
    swfs_real_free(obs);
    if (!rc && swfs_loops_map_wanted_(o, pyr) && !swfs_config_has(c, "truth_actuators"))
        rc = loops_outgrid(o, g, c, r->work);
    /* more loops where the loops' map will be learned from them (swfs_loops_map_wanted_,
     * speckles' own condition: the interaction matrix, a pyramid's loops by default) and its
     * curve asks; the curve needs 4 data sets */
    size_t max = o->mean_teach_max_loops ? o->mean_teach_max_loops : 4 * nl;
    if (max > SWFS_MEAN_TEACH_MAX) max = SWFS_MEAN_TEACH_MAX;
    if (!swfs_loops_map_wanted_(o, pyr) || nl < 4) max = nl;
    char fpr[17] = "", conf[4500];
    snprintf(conf, sizeof conf, "%s/mean_loops.conf", r->work);
    if (!rc) rc = fingerprint(c, nl, max, o->teach_seed, fpr);
    for (size_t k = 0; !rc && k < SWFS_MEAN_TEACH_MAX; k++)
        if (snprintf(dirs[k], sizeof dirs[k], "%.4000s/mean_%02zu", r->work, k) >= (int)sizeof dirs[k])
            rc = swfs_fail(SWFS_ERR_ARG, "speckles: the teach folder's name %s is too long", r->work);
    r->nloops = r->nloops_first = nl;
    r->curve_excess = NAN;
    r->curve_frames = 0;
    if (!rc && !o->teach_again && made_for(conf, fpr, dirs, nl, r)) {
        r->reused = r->done = 1;
    } else if (!rc) {
        swfs_teach_run_options to;
        swfs_teach_run_options_default(&to);
        (void)remove(conf); /* the loops below are not those it describes */
        rc = swfs_ts_params_from_config(c, &to.sim);
        if (!rc) rc = swfs_ts_params_check(&to.sim);
        if (!rc) {
            to.work = r->work;
            to.seed = o->teach_seed;
            to.prov = o->prov;
            to.nprov = o->nprov;
            to.progress = o->progress;
            to.progress_ctx = o->progress_ctx;
            rc = loops_fitted(&to, r0_given, r->power, nl, nslopes, nsub, r);
        }
        if (!rc && max > nl) rc = loops_as_curve_asks(o, &to, g, dirs, nl, max, r);
        if (!rc) rc = swfs_config_put_(c, "r0", "%.6g", r->r0);
        if (!rc) rc = write_description(conf, c, fpr, r);
        r->done = !rc;
    }
    if (!rc) r->loop_frames = loop_frames;
    if (rc && made) (void)rmdir(r->work);
    swfs_config_free(c);
    for (size_t k = 0; names && k < n; k++) free(names[k]);
    free(names);
    r->seconds = swfs_wall_seconds() - t0;
    return rc ? swfs_fail_context(rc, "speckles --mean-loop teach") : SWFS_OK;
}

/* 1 when the loops' sensor is a pyramid: given (--teach-set wfs=pyramid), else the first
 * telemetry file's WFSTYPE names one. */
static int pyramid_telemetry(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir)
{
    /* the last wfs= given wins, as in the loops' description (the config's set) */
    swfs_config *c = swfs_config_new();
    int given = 0, pyr = 0;
    for (size_t k = 0; c && k < o->nteach_keys; k++)
        if (swfs_config_set(c, o->teach_keys[k])) swfs_clear_error();
    if (c && swfs_config_has(c, "wfs")) {
        const char *v = NULL;
        given = !swfs_config_string(c, "wfs", "sh", &v);
        pyr = given && !strcmp(v, "pyramid");
    }
    swfs_config_free(c);
    if (given) return pyr;
    char path[8192];
    int kind = 0;
    if (!t->ncubes || swfs_telemetry_path(tdir, t->cubes[0].slopes, path, sizeof path) ||
        swfs_telemetry_sensor(path, &kind, NULL, 0)) {
        swfs_clear_error(); /* the run itself names what it cannot read */
        return 0;
    }
    return kind == SWFS_WFS_PYRAMID;
}

/* The default's choice and its fallback; swfs_speckles_mean_teach_ adds the folders' pointers. */
static int mean_teach_auto(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                           const swfs_geom *g, size_t nslopes, swfs_mean_teach_result *r, char (*dirs)[4400])
{
    memset(r, 0, sizeof *r);
    r->photons = r->slope_noise = r->power = r->power_ratio = NAN;
    if (o->mean_teach != SWFS_MEAN_TEACH_AUTO) return mean_teach(o, t, tdir, g, nslopes, r, dirs);
    /* the default: a pyramid's telemetry only; where the loops cannot be made, without them,
     * saying why */
    if (!pyramid_telemetry(o, t, tdir)) return SWFS_OK;
    r->automatic = 1;
    if (o->team && o->team->size > 1) {
        snprintf(r->fallback, sizeof r->fallback, "speckles in a team of %d runs without them (each member would "
                 "simulate them); --mean-loop DIR... with loops simulated once", o->team->size);
        return SWFS_OK;
    }
    const int rc = mean_teach(o, t, tdir, g, nslopes, r, dirs);
    if (rc == SWFS_ERR_STOPPED) return rc; /* the caller asked the whole run to stop: no fallback */
    if (rc) {
        snprintf(r->fallback, sizeof r->fallback, "%s", swfs_last_error());
        swfs_clear_error();
        r->done = 0;
    }
    return SWFS_OK;
}

int swfs_mean_teach_wanted_(int mean_teach, const swfs_linear_files *lin, size_t nmean_loops, int per_wfs_frame)
{
    return mean_teach == 1 || (mean_teach == SWFS_MEAN_TEACH_AUTO && lin->basis && !nmean_loops && !per_wfs_frame &&
                               !swfs_map_has_meanmiss_(lin->control));
}

int swfs_speckles_mean_teach_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                              const swfs_geom *g, size_t nslopes, swfs_mean_teach_result *r, char (*dirs)[4400],
                              const char **loops)
{
    const int rc = mean_teach_auto(o, t, tdir, g, nslopes, r, dirs);
    for (size_t k = 0; !rc && r->done && k < r->nloops; k++) loops[k] = dirs[k];
    return rc;
}

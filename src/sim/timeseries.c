/* Time-series simulation with a closed AO loop, telemetry and raw camera cubes
 * (see include/specklewfs/timeseries.h and docs/telemetry.md). */
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/timeseries.h"
#include "ts_milk.h"
#include "sim_internal.h"
#include "specklewfs/aperture.h"
#include "specklewfs/array.h"
#include "specklewfs/dmfit.h"
#include "specklewfs/engine.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/kernels.h"
#include "specklewfs/mft.h"
#include "specklewfs/pyramid.h"
#include "specklewfs/rng.h"
#include "specklewfs/screen.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/wfs.h"

#include <cblas.h>
#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

void swfs_ts_params_default(swfs_ts_params *p)
{
    memset(p, 0, sizeof *p);
    swfs_sim_params_default(&p->base);
    p->base.screen.n = 1024;
    p->base.screen.subharmonics = 0; /* periodic screens: frozen flow wraps around */
    p->base.nfx = p->base.nfy = 54;  /* Clio's 54 x 54 sub-stamp at 0.25 lambda/D */
    p->base.read_noise = 19;         /* Clio: 19 dn read noise, 4.9 e-/dn */
    p->base.gain = 4.9;
    p->nlayers = 2;
    p->layer_frac[0] = 0.6; p->layer_speed[0] = 10; p->layer_dir[0] = 0;
    p->layer_frac[1] = 0.4; p->layer_speed[1] = 15; p->layer_dir[1] = 110;
    p->layer_frac[2] = 0.0; p->layer_speed[2] = 5; p->layer_dir[2] = 250;
    p->wfs_rate = 527;
    p->nsub = 12;
    p->act_pitch = 0.45;
    p->ao_gain = 0.4;
    p->ao_delay = 2;
    p->ao_modes = 56;
    p->slope_noise = 3e-8;
    p->pyr_mod = 3;
    p->pyr_photons = 1000;
    p->vib_amp = 0.5;
    p->vib_freq = 20;
    p->vib_angle = 30;
    p->jitter_amp = 0.05;
    p->jitter_freq = 30;
    p->frame_ratio = 6.48;
    p->ncubes = 6;
    p->cube_frames = 100;
    p->cube_gap = 200;
    p->start_offset = 300.4;
    p->handshake_lag = 3;
    p->wfs_file_frames = 0;
    p->milk = 0;
    p->milk_epoch = 1.7e9;
    p->milk_jitter = 3e-6;
    p->milk_drift = 1e-4;
    p->milk_offset = 2.5e-3;
    p->milk_drop_wfs = 5;
    p->milk_drop_cam = 3;
    p->milk_file_frames = 400;
    p->milk_cam_file_frames = 40;
    p->bandwidth = 0;
    p->nlambda = 5;
    p->background = 20;
    p->dark_level = 3700;
    p->flat_rms = 0.02;
    p->nhot = 5;
    p->ndead = 5;
}

int swfs_ts_config_gives_filter(const swfs_config *c)
{
    return swfs_config_has(c, "ao_modes") || swfs_config_has(c, "ao_recon") || swfs_config_has(c, "ao_rcond");
}

int swfs_ts_params_from_config(swfs_config *c, swfs_ts_params *p)
{
    int rc;
    if ((rc = swfs_sim_params_from_config(c, &p->base))) return rc;
    long nl = p->nlayers;
    if ((rc = swfs_config_long(c, "nlayers", nl, &nl))) return rc;
    if (nl < 1 || nl > SWFS_TS_MAX_LAYERS)
        return swfs_fail(SWFS_ERR_VALUE, "setting nlayers=%ld: must be 1..%d", nl, SWFS_TS_MAX_LAYERS);
    p->nlayers = (int)nl;
    const char *lists[3] = {"layer_frac", "layer_speed", "layer_dir"};
    double *dst[3] = {p->layer_frac, p->layer_speed, p->layer_dir};
    for (int k = 0; k < 3; k++) {
        if (!swfs_config_has(c, lists[k])) continue;
        double v[SWFS_TS_MAX_LAYERS + 1];
        size_t n = SWFS_TS_MAX_LAYERS + 1;
        if ((rc = swfs_config_doubles(c, lists[k], v, &n))) return rc;
        if (n != (size_t)p->nlayers)
            return swfs_fail(SWFS_ERR_VALUE, "setting %s: %zu values for nlayers=%d", lists[k], n, p->nlayers);
        memcpy(dst[k], v, n * sizeof *v);
    }
#define D_(key, f) if ((rc = swfs_config_double(c, key, p->f, &p->f))) return rc
#define L_(key, f) if ((rc = swfs_config_long(c, key, p->f, &p->f))) return rc
    D_("wfs_rate", wfs_rate); L_("nsub", nsub); D_("act_pitch", act_pitch); D_("ao_gain", ao_gain);
    L_("ao_delay", ao_delay); L_("ao_modes", ao_modes); D_("ao_rcond", ao_rcond); D_("slope_noise", slope_noise);
    D_("vib_amp", vib_amp); D_("vib_freq", vib_freq); D_("vib_angle", vib_angle);
    D_("jitter_amp", jitter_amp); D_("jitter_freq", jitter_freq);
    D_("frame_ratio", frame_ratio); L_("ncubes", ncubes); L_("cube_frames", cube_frames); D_("cube_gap", cube_gap);
    D_("start_offset", start_offset); L_("handshake_lag", handshake_lag); L_("wfs_file_frames", wfs_file_frames);
    D_("bandwidth", bandwidth); L_("nlambda", nlambda); D_("background", background); D_("dark_level", dark_level);
    D_("flat_rms", flat_rms); L_("nhot", nhot); L_("ndead", ndead);
    L_("camera_swap", camera_swap); L_("camera_flip_x", camera_flip_x); L_("camera_flip_y", camera_flip_y);
    L_("act_square", act_square); D_("dm_coupling", dm_coupling); L_("export_modal", export_modal); L_("export_truth", export_truth);
    L_("camera_light", camera_light);
    D_("pyr_mod", pyr_mod); L_("pyr_nmod", pyr_nmod); D_("wfs_wavelen", wfs_wavelen); D_("pyr_photons", pyr_photons);
    L_("milk", milk); D_("milk_epoch", milk_epoch); D_("milk_jitter", milk_jitter); D_("milk_drift", milk_drift);
    D_("milk_offset", milk_offset); L_("milk_drop_wfs", milk_drop_wfs); L_("milk_drop_cam", milk_drop_cam);
    L_("milk_file_frames", milk_file_frames); L_("milk_cam_file_frames", milk_cam_file_frames);
#undef D_
#undef L_
    if ((rc = swfs_sim_config_path(c, "ao_recon", p->ao_recon, sizeof p->ao_recon))) return rc;
    if ((rc = swfs_sim_config_path(c, "actuators", p->actuators, sizeof p->actuators))) return rc;
    if ((rc = swfs_sim_config_path(c, "valid", p->valid, sizeof p->valid))) return rc;
    if ((rc = swfs_sim_config_path(c, "truth_actuators", p->truth_actuators, sizeof p->truth_actuators))) return rc;
    const char *wfs = NULL;
    if ((rc = swfs_config_string(c, "wfs", p->wfs_pyramid ? "pyramid" : "sh", &wfs))) return rc;
    if (strcmp(wfs, "sh") && strcmp(wfs, "pyramid"))
        return swfs_fail(SWFS_ERR_VALUE, "setting wfs=%s: expected sh (a Shack-Hartmann) or pyramid", wfs);
    p->wfs_pyramid = !strcmp(wfs, "pyramid");
    /* mode=timeseries selects this simulator; it is not a parameter of it. */
    const char *mode = NULL;
    if ((rc = swfs_config_string(c, "mode", "timeseries", &mode))) return rc;
    if (p->camera_light) swfs_ts_camera_light(p);
    return SWFS_OK;
}

/* A reconstructor of the used subapertures' slopes only (2 nvalid columns: their x slopes in
 * the full layout's order, then their y slopes), as most AO systems keep theirs, put in the
 * simulated Shack-Hartmann's full layout (the unused subapertures' columns 0). */
static int embed_valid_recon(const char *path, swfs_recon *r, const swfs_shwfs *sh)
{
    size_t *cols = NULL, nc = 0;
    int rc = swfs_slopes_used_cols(sh->valid, sh->nsub, &cols, &nc);
    double *W = rc ? NULL : swfs_slopes_expand_cols(r->W, r->nact, nc, cols, sh->nslopes);
    free(cols);
    if (rc) return rc;
    if (!W) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    free(r->W);
    r->W = W;
    r->nslopes = sh->nslopes;
    return SWFS_OK;
}

/* The loop's reconstructor from a file: its shape must be the simulated Shack-Hartmann's
 * slopes (the full layout, or the used subapertures' only) by the DM's actuators; the modes
 * it keeps are its numerical rank. */
int swfs_ts_check_given_recon(const char *path, swfs_recon *r, const swfs_shwfs *sh, size_t nact)
{
    const size_t nslopes = sh->nslopes;
    int rc = SWFS_OK;
    if (r->nslopes == 2 * sh->nvalid && r->nslopes != nslopes && r->nact == nact &&
        (rc = embed_valid_recon(path, r, sh)))
        return rc;
    if (r->nslopes != nslopes || r->nact != nact)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: the loop's reconstructor is %zu slopes x %zu actuators, but the simulated "
                         "Shack-Hartmann gives %zu slopes (%zu used subapertures: %zu with the used ones' only) and the "
                         "DM has %zu actuators (recon_ao.fits layout: NAXIS1 = slopes, NAXIS2 = actuators [m/rad])",
                         path, r->nslopes, r->nact, nslopes, sh->nvalid, 2 * sh->nvalid, nact);
    const size_t k = nact < nslopes ? nact : nslopes;
    double *a = malloc(nact * nslopes * sizeof *a), *sv = malloc(k * sizeof *sv);
    if (!a || !sv) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    if (!rc) {
        memcpy(a, r->W, nact * nslopes * sizeof *a);
        lapack_int info = LAPACKE_dgesdd(LAPACK_ROW_MAJOR, 'N', (lapack_int)nact, (lapack_int)nslopes, a,
                                         (lapack_int)nslopes, sv, NULL, (lapack_int)k, NULL, (lapack_int)nslopes);
        if (info) rc = swfs_fail(SWFS_ERR_NUMERIC, "%s: SVD of the loop's reconstructor failed (%d)", path, (int)info);
    }
    size_t rank = 0;
    for (size_t i = 0; !rc && i < k; i++) rank += sv[i] > 1e-9 * sv[0];
    if (!rc && rank == 0) rc = swfs_fail(SWFS_ERR_VALUE, "%s: the loop's reconstructor is zero", path);
    r->nmodes = rank;
    free(a);
    free(sv);
    return rc;
}

/* Actuator positions from a file: enough of them to span the pupil, none at the same place
 * (the interpolation's triangulation needs distinct points, and the pupil inside their hull). */
static int check_given_actuators(const char *path, const double *xy, size_t nact, double D)
{
    if (nact < 4) return swfs_fail(SWFS_ERR_VALUE, "%s: %zu actuators; the simulated DM needs at least 4", path, nact);
    double rmax = 0;
    for (size_t a = 0; a < nact; a++) {
        rmax = fmax(rmax, hypot(xy[2 * a], xy[2 * a + 1]));
        for (size_t b = 0; b < a; b++)
            if (hypot(xy[2 * a] - xy[2 * b], xy[2 * a + 1] - xy[2 * b + 1]) < 1e-6 * D)
                return swfs_fail(SWFS_ERR_VALUE, "%s: actuators %zu and %zu are at the same place (%g, %g) m", path, b, a,
                                 xy[2 * a], xy[2 * a + 1]);
    }
    if (rmax < 0.4 * D || rmax > 2.0 * D)
        return swfs_fail(SWFS_ERR_VALUE, "%s: the actuators reach %g m from the centre, the pupil %g m; expected positions "
                         "in metres on the pupil, centred on it", path, rmax, D / 2);
    return SWFS_OK;
}

/* The files the run is given, read before any work: the DM's positions (*xy, *nact), the
 * loop's reconstructor (*rao; its shape is checked against the Shack-Hartmann later) and the
 * valid-subaperture map (*vmap); each left NULL when not given. */
int swfs_ts_read_given(const swfs_ts_params *p, double D, double **xy, size_t *nact, swfs_recon **rao,
                       unsigned char **vmap)
{
    int rc = SWFS_OK;
    if (p->actuators[0] && ((rc = swfs_actuators_read(p->actuators, xy, nact)) ||
                            (rc = check_given_actuators(p->actuators, *xy, *nact, D))))
        return rc;
    if (p->ao_recon[0] && (rc = swfs_recon_read(p->ao_recon, rao))) return rc;
    if (p->ao_recon[0] && (*rao)->nlags > 1)
        return swfs_fail(SWFS_ERR_ARG, "%s: a space-time reconstructor (%zu lags) is no AO loop's: ao_recon takes the "
                         "matrix the loop applies to one frame's slopes", p->ao_recon, (*rao)->nlags);
    size_t vn = 0, nv = 0;
    if (p->valid[0] && (rc = swfs_valid_map_read(p->valid, vmap, &vn, &nv))) return rc;
    if (p->valid[0] && vn != (size_t)p->nsub)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: a valid-subaperture map of %zu x %zu, but nsub = %ld", p->valid, vn, vn,
                         p->nsub);
    return SWFS_OK;
}

static int badv(const char *key, double v, const char *what)
{
    return swfs_fail(SWFS_ERR_VALUE, "time-series parameter %s=%g: %s", key, v, what);
}

int swfs_ts_params_from_keys(const char *const *kv, size_t n, swfs_ts_params *p)
{
    swfs_ts_params_default(p);
    swfs_config *c = swfs_config_new();
    if (!c) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    int rc = swfs_config_set_kv(c, "mode", "timeseries");
    for (size_t k = 0; !rc && k < n; k++) rc = swfs_config_set(c, kv[k]);
    if (!rc) rc = swfs_ts_params_from_config(c, p);
    if (!rc) rc = swfs_config_check_unused(c);
    swfs_config_free(c);
    return rc ? rc : swfs_ts_params_check(p);
}

int swfs_ts_params_check(const swfs_ts_params *p)
{
    const swfs_sim_params *b = &p->base;
    if (b->pupn < 8 || (size_t)b->pupn > b->screen.n) return badv("pupn", (double)b->pupn, "must be 8..screen_n");
    if (!(b->pupdx > 0) || fabs(b->pupdx - b->screen.dx) > 1e-12 * b->pupdx) return badv("pupdx", b->pupdx, "must be > 0 and equal screen_dx");
    if (!(b->teldiam > 0) || b->teldiam > (double)b->pupn * b->pupdx + 1e-9)
        return badv("teldiam", b->teldiam, "must be > 0 and fit in pupn * pupdx");
    if (!(b->wavelen > 0)) return badv("wavelen", b->wavelen, "must be > 0");
    if (b->nfx < 4 || b->nfy < 4) return badv("nfx", (double)b->nfx, "focal window must be at least 4 x 4");
    if (!(b->pixscale > 0)) return badv("pixscale", b->pixscale, "must be > 0");
    if (!(b->screen.r0 > 0)) return badv("r0", b->screen.r0, "must be > 0");
    double fs = 0;
    for (int l = 0; l < p->nlayers; l++) {
        if (!(p->layer_frac[l] >= 0)) return badv("layer_frac", p->layer_frac[l], "must be >= 0");
        if (!(p->layer_speed[l] >= 0)) return badv("layer_speed", p->layer_speed[l], "must be >= 0");
        fs += p->layer_frac[l];
    }
    if (fabs(fs - 1) > 1e-6) return badv("layer_frac", fs, "must sum to 1");
    {
        /* Infinite values pass the range checks below but make no physical sense here. */
        const struct { const char *key; double v; } fin[] = {
            {"wfs_rate", p->wfs_rate},       {"act_pitch", p->act_pitch},     {"slope_noise", p->slope_noise},
            {"vib_amp", p->vib_amp},         {"vib_freq", p->vib_freq},       {"jitter_amp", p->jitter_amp},
            {"jitter_freq", p->jitter_freq}, {"frame_ratio", p->frame_ratio}, {"cube_gap", p->cube_gap},
            {"start_offset", p->start_offset}, {"background", p->background}, {"flat_rms", p->flat_rms},
            {"pyr_mod", p->pyr_mod},         {"wfs_wavelen", p->wfs_wavelen}, {"pyr_photons", p->pyr_photons}};
        for (size_t k = 0; k < sizeof fin / sizeof fin[0]; k++)
            if (!isfinite(fin[k].v)) return badv(fin[k].key, fin[k].v, "must be finite");
        for (int l = 0; l < p->nlayers; l++)
            if (!isfinite(p->layer_speed[l])) return badv("layer_speed", p->layer_speed[l], "must be finite");
    }
    if (!(p->wfs_rate > 0)) return badv("wfs_rate", p->wfs_rate, "must be > 0");
    if (p->nsub < 2 || b->teldiam / (double)p->nsub < 2 * b->pupdx) return badv("nsub", (double)p->nsub, "subapertures must span >= 2 pupil samples");
    /* the pitch makes the DM's grid; a DM from a file (actuators=) has its own */
    if (!p->actuators[0] && !(p->act_pitch > 2 * b->pupdx))
        return badv("act_pitch", p->act_pitch, "must exceed 2 pupil samples");
    if (!(p->ao_gain >= 0 && p->ao_gain < 2)) return badv("ao_gain", p->ao_gain, "must be in [0, 2)");
    if (p->ao_delay < 1 || p->ao_delay > 8) return badv("ao_delay", (double)p->ao_delay, "must be 1..8 frames");
    if (p->ao_modes < 1) return badv("ao_modes", (double)p->ao_modes, "must be >= 1");
    if (!(p->ao_rcond >= 0 && p->ao_rcond < 1)) return badv("ao_rcond", p->ao_rcond, "must be in [0, 1) (0: the ao_modes filter)");
    if (p->ao_rcond > 0 && p->ao_recon[0])
        return swfs_fail(SWFS_ERR_ARG, "time-series parameters ao_rcond=%g and ao_recon=%s: the loop's reconstructor is "
                         "either the file's or the truncated pseudo-inverse of its interaction matrix, not both",
                         p->ao_rcond, p->ao_recon);
    if (!(p->slope_noise >= 0)) return badv("slope_noise", p->slope_noise, "must be >= 0");
    if (p->wfs_pyramid & ~1L) return badv("wfs_pyramid", (double)p->wfs_pyramid, "must be 0 or 1");
    if (!(p->pyr_mod >= 0)) return badv("pyr_mod", p->pyr_mod, "must be >= 0 lambda/D");
    if (p->pyr_nmod < 0 || p->pyr_nmod > 4096) return badv("pyr_nmod", (double)p->pyr_nmod, "must be 0 (the rule) .. 4096");
    if (!(p->wfs_wavelen >= 0)) return badv("wfs_wavelen", p->wfs_wavelen, "must be >= 0 (0: wavelen)");
    if (!(p->pyr_photons >= 0)) return badv("pyr_photons", p->pyr_photons, "must be >= 0 (0: noiseless)");
    if (p->wfs_pyramid && p->export_modal)
        return swfs_fail(SWFS_ERR_ARG, "time-series parameters wfs=pyramid and export_modal=1: the export's modal "
                         "coefficients are a Shack-Hartmann's reconstruction; a pyramid run writes its own linear-model "
                         "files (influence.fits, imat_ao.fits, recon_ao.fits: docs/telemetry.md)");
    if (!(p->vib_amp >= 0) || !(p->vib_freq >= 0)) return badv("vib_amp", p->vib_amp, "vibration must be >= 0");
    if (!(p->jitter_amp >= 0) || !(p->jitter_freq > 0)) return badv("jitter_amp", p->jitter_amp, "jitter must be >= 0 with jitter_freq > 0");
    if (!(p->frame_ratio >= SWFS_ENGINE_MIN_RATIO))
        return badv("frame_ratio", p->frame_ratio, "must be >= 0.1 WFS frame per exposure (a camera up to 10x faster)");
    if (p->ncubes < 1) return badv("ncubes", (double)p->ncubes, "need >= 1 cube");
    if (p->cube_frames < 2) return badv("cube_frames", (double)p->cube_frames, "need >= 2 frames per cube");
    if (!(p->cube_gap >= 0) || !(p->start_offset >= 0)) return badv("cube_gap", p->cube_gap, "gap and start_offset must be >= 0");
    if (p->handshake_lag < 0) return badv("handshake_lag", (double)p->handshake_lag, "must be >= 0");
    if (p->wfs_file_frames < 0) return badv("wfs_file_frames", (double)p->wfs_file_frames, "must be >= 0");
    if (!(p->bandwidth >= 0 && p->bandwidth < 1)) return badv("bandwidth", p->bandwidth, "must be in [0, 1)");
    if (p->nlambda < 1 || p->nlambda > 64) return badv("nlambda", (double)p->nlambda, "must be 1..64");
    if (!(p->background >= 0) || !(p->flat_rms >= 0)) return badv("background", p->background, "background and flat_rms must be >= 0");
    if (p->nhot < 0 || p->ndead < 0) return badv("nhot", (double)p->nhot, "bad-pixel counts must be >= 0");
    const int mrc = swfs_ts_milk_check(p);
    if (mrc) return mrc;
    if (p->act_square & ~1L) return badv("act_square", (double)p->act_square, "must be 0 or 1");
    if (!(p->dm_coupling >= 0 && p->dm_coupling < 1))
        return badv("dm_coupling", p->dm_coupling, "must be in [0, 1): 0 the interpolated surface, else the Gaussian "
                    "influence functions' coupling at the neighbouring actuator (0.1-0.3 for most DMs)");
    if (p->export_modal & ~1L) return badv("export_modal", (double)p->export_modal, "must be 0 or 1");
    if (p->export_truth & ~1L) return badv("export_truth", (double)p->export_truth, "must be 0 or 1");
    if (p->truth_actuators[0] && !p->export_truth)
        return swfs_fail(SWFS_ERR_ARG, "time-series parameter truth_actuators=%s: the points export_truth fits the "
                         "truth on; it needs export_truth=1", p->truth_actuators);
    if ((p->camera_swap | p->camera_flip_x | p->camera_flip_y) & ~1L)
        return badv("camera_swap", (double)(p->camera_swap + 10 * p->camera_flip_x + 100 * p->camera_flip_y),
                    "camera_swap, camera_flip_x and camera_flip_y must each be 0 or 1");
    if (p->camera_swap && b->nfx != b->nfy) return badv("camera_swap", 1.0, "a transposed camera needs nfx = nfy");
    return SWFS_OK;
}

/* A layer's shift for one frame, split once into whole samples (ox, oy in [0, n)) and the
 * bilinear weights' fractions (ax, ay): the same for every pupil sample, whose own position
 * is whole samples, so the per-sample work is two wrapped additions and four loads. */
typedef struct { size_t ox, oy; double ax, ay; } screen_shift;

static screen_shift screen_shift_of(size_t n, double u, double v)
{
    const double nn = (double)n;
    u -= nn * floor(u / nn);
    v -= nn * floor(v / nn);
    screen_shift h = {(size_t)u, (size_t)v, 0, 0};
    if (h.ox >= n) h.ox = n - 1;
    if (h.oy >= n) h.oy = n - 1;
    h.ax = u - (double)h.ox;
    h.ay = v - (double)h.oy;
    return h;
}

/* out[t] += the periodic screen s (n x n) moved by h at whole samples (gx + t, gy), t < len
 * (gx, gy in [0, n)): a run of pupil samples along a row of the grid. The screen's two rows
 * are read contiguously up to the column where the run wraps, so the loop vectorizes. */
static void screen_add_run(const double *s, size_t n, size_t gx, size_t gy, size_t len, const screen_shift *h,
                           double *out)
{
    size_t i = gx + h->ox, j0 = gy + h->oy;
    if (i >= n) i -= n;
    if (j0 >= n) j0 -= n;
    const size_t j1 = j0 + 1 == n ? 0 : j0 + 1;
    const double a = h->ax, b = h->ay;
    const double *r0 = s + j0 * n, *r1 = s + j1 * n;
    for (size_t t = 0; t < len;) {
        size_t span = n - 1 - i; /* columns i .. n - 2 have their right neighbour in the row */
        if (span > len - t) span = len - t;
        double *o = out + t;
        const double *p0 = r0 + i, *p1 = r1 + i;
        for (size_t q = 0; q < span; q++)
            o[q] += (1 - b) * ((1 - a) * p0[q] + a * p0[q + 1]) + b * ((1 - a) * p1[q] + a * p1[q + 1]);
        t += span;
        i += span;
        if (t < len) { /* column n - 1, whose right neighbour is column 0 */
            out[t] += (1 - b) * ((1 - a) * r0[n - 1] + a * r0[0]) + b * ((1 - a) * r1[n - 1] + a * r1[0]);
            t++;
            i = 0;
        }
    }
}

static void core_reference(double complex *h, size_t nfx, size_t nfy)
{
    double complex c = h[(nfy / 2) * nfx + nfx / 2];
    double a = cabs(c);
    if (!(a > 0)) return;
    double complex ph = conj(c) / a;
    for (size_t i = 0; i < nfx * nfy; i++) h[i] *= ph;
}

/* The pupil-field sum of one exposure for the ideal speckles (eq:downsampledHalo before the
 * MFT): frame r has the tip-tilt-free residual ph[r] [m] over the illuminated samples, the
 * weight w[3r] and the tip and tilt w[3r+1], w[3r+2] [rad]; the weighted mean tip-tilt of
 * the exposure is removed, the motion within it kept. Registering the science frame on
 * its peak removes exactly that mean: the frames are re-centred, not de-blurred. */
static void ideal_exposure(const double *ph, const double *w, size_t n, const size_t *pin, size_t npin, const double *xs,
                           const double *ys, const double *mask, double lam, double *phi, double complex *cpin,
                           double complex *ei)
{
    double sw = 0, tx = 0, ty = 0;
    for (size_t r = 0; r < n; r++) { sw += w[3 * r]; tx += w[3 * r] * w[3 * r + 1]; ty += w[3 * r] * w[3 * r + 2]; }
    if (sw > 0) { tx /= sw; ty /= sw; }
    for (size_t r = 0; r < n; r++) {
        const double *p = ph + r * npin;
        double dx = w[3 * r + 1] - tx, dy = w[3 * r + 2] - ty;
        for (size_t m = 0; m < npin; m++) phi[m] = 2 * M_PI * (p[m] + dx * xs[pin[m]] + dy * ys[pin[m]]) / lam;
        swfs_expi_d(phi, NULL, cpin, npin);
        for (size_t m = 0; m < npin; m++) ei[pin[m]] += w[3 * r] * mask[pin[m]] * cpin[m];
    }
}

/* A speckle cube; with resmean (the true residual's time mean over the same frames) also
 * its RESMEAN extension, as `speckles` writes the reconstructed one. */
static int write_cplx_cube(const char *path, const swfs_cplx *c, const swfs_geom *g, const char *const *prov, size_t nprov,
                           const char *what, const swfs_real *resmean, double resmean_rms)
{
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    if (!(rc = swfs_fits_out_set_stamp(o, g, prov, nprov)) && !(rc = swfs_fits_out_cplx(o, NULL, c, -32)))
        rc = swfs_fits_out_history(o, what);
    if (!rc && resmean && !(rc = swfs_fits_out_real(o, "RESMEAN", resmean, -64)) &&
        !(rc = swfs_fits_out_key_string(o, "BUNIT", "m", "true AO residual's time mean (simulation)")))
        rc = swfs_fits_out_key_double(o, "RESMRMS", resmean_rms, "[m] rms of the residual's time mean (PTT removed)");
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

/* exptime > 0: a camera cube's EXPTIME [s], as a camera's header has it */
static int write_real(const char *path, const swfs_real *a, const swfs_geom *g, const char *const *prov, size_t nprov,
                      double gain, double exptime)
{
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    if (!(rc = swfs_fits_out_set_stamp(o, g, prov, nprov)) && !(rc = swfs_fits_out_real(o, NULL, a, -32)) && gain > 0)
        rc = swfs_fits_out_key_double(o, "GAIN", gain, "[e-/count]");
    if (!rc && exptime > 0) rc = swfs_fits_out_key_double(o, "EXPTIME", exptime, "[s] exposure time");
    if (rc) { swfs_fits_out_abort(o); return rc; }
    return swfs_fits_out_commit(o);
}

/* Detector pixel (i, j) sees focal pixel (i', j'): transposed first (camera_swap), then
 * i' = nx - 1 - i and/or j' = ny - 1 - j (a mirror of the whole detector: the star moves off
 * the centre pixel by one for even sizes, as on a real camera; reduce re-centres it). */
static int camera_turn(const swfs_ts_params *p, swfs_real *cube)
{
    const size_t nx = cube->nx, ny = cube->ny, np = nx * ny;
    double *f = malloc(np * sizeof *f);
    if (!f) return swfs_fail(SWFS_ERR_NOMEM, "time series: out of memory for the camera's orientation");
    for (size_t e = 0; e < cube->nz; e++) {
        double *d = cube->data + e * np;
        memcpy(f, d, np * sizeof *f);
        for (size_t j = 0; j < ny; j++)
            for (size_t i = 0; i < nx; i++) {
                const size_t a = p->camera_flip_x ? nx - 1 - i : i, b = p->camera_flip_y ? ny - 1 - j : j;
                d[j * nx + i] = p->camera_swap ? f[a * nx + b] : f[b * nx + a];
            }
    }
    free(f);
    return SWFS_OK;
}

/* Cube c's first exposure starts at this global WFS frame. */
static double cube_start(const swfs_ts_params *p, size_t c)
{
    return p->start_offset + (double)c * ((double)p->cube_frames * p->frame_ratio + p->cube_gap);
}

/* The camera's schedule (eq:downsampledHalo's exposures): cube c starts at tstart[c] (global
 * WFS frames); its exposures into sched + c * cube_frames, or all into the one cube's worth
 * sched holds when all = 0. The WFS frames the simulation runs: the last exposure's end, the
 * handshake's lag and 10 more. */
static size_t ts_schedule(const swfs_ts_params *p, swfs_exposure *sched, int all, double *tstart)
{
    const size_t ncub = (size_t)p->ncubes, nf = (size_t)p->cube_frames;
    size_t nwfs = 0;
    for (size_t c = 0; c < ncub; c++) {
        const double t = cube_start(p, c);
        if (tstart) tstart[c] = t;
        const size_t need = swfs_engine_schedule(p->frame_ratio, t, nf, sched + (all ? c * nf : 0));
        if (need > nwfs) nwfs = need;
    }
    return nwfs + (size_t)p->handshake_lag + 10;
}

size_t swfs_ts_nframes(const swfs_ts_params *p)
{
    const size_t nf = (size_t)p->cube_frames;
    swfs_exposure *sched = malloc((nf ? nf : 1) * sizeof *sched);
    if (!sched) return 0;
    const size_t nwfs = ts_schedule(p, sched, 0, NULL);
    free(sched);
    return nwfs;
}

void swfs_ts_camera_light(swfs_ts_params *p)
{
    /* keys swfs_ts_params_check refuses are left for it to name */
    if (p->ncubes < 1 || p->cube_frames < 1 || !(p->frame_ratio > 0) || !(p->cube_gap >= 0) || !(p->start_offset >= 0))
        return;
    const size_t nwfs = swfs_ts_nframes(p);
    swfs_ts_params l = *p;
    l.frame_ratio = 1;
    l.ncubes = 2;
    l.cube_frames = 20;
    l.cube_gap = 0;
    const size_t light = swfs_ts_nframes(&l);
    if (!nwfs || !light || light > nwfs) return;
    l.cube_gap = (double)(nwfs - light);
    if (swfs_ts_nframes(&l) == nwfs) *p = l;
}

int swfs_ts_make_dirs(const swfs_ts_params *p, const char *dir)
{
    int rc = swfs_make_dirs(dir);
    char sub[4200];
    for (int k = 0; !rc && k < 2 && p->milk; k++) { /* the milk logs' stream folders */
        if (snprintf(sub, sizeof sub, "%s/milk/%s", dir, k ? "cam" : "wfs") >= (int)sizeof sub)
            return swfs_fail(SWFS_ERR_ARG, "output folder name too long: %.200s...", dir);
        rc = swfs_make_dirs(sub);
    }
    return rc;
}

int swfs_ts_add_outputs(const swfs_ts_params *p, const char *dir, swfs_paths *paths)
{
    static const char *fixed[] = {"actuators.fits", "pupil.fits", "recon_ao.fits", "handshake.log", "dark.fits", "flat.fits",
                                  "speckles_ideal.fits", "speckles_ideal_tt.fits", "truth.fits", "truth_timing.txt"};
    char path[8192];
    const size_t ncub = (size_t)p->ncubes;
    const size_t nwfs = swfs_ts_nframes(p);
    if (!nwfs) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    const size_t ffr = p->wfs_file_frames > 0 ? (size_t)p->wfs_file_frames : nwfs;
    if (p->actuators[0]) swfs_paths_input(paths, "actuators", p->actuators);
    if (p->ao_recon[0]) swfs_paths_input(paths, "the loop's reconstructor (ao_recon)", p->ao_recon);
    if (p->valid[0]) swfs_paths_input(paths, "valid-subaperture map", p->valid);
    if (p->truth_actuators[0]) swfs_paths_input(paths, "the truth's points (truth_actuators)", p->truth_actuators);
    if (p->base.pupil_mask[0]) swfs_paths_input(paths, "pupil mask", p->base.pupil_mask);
    if (p->base.ncp_map[0]) swfs_paths_input(paths, "NCP map", p->base.ncp_map);
    for (size_t k = 0; k < sizeof fixed / sizeof fixed[0]; k++) {
        snprintf(path, sizeof path, "%s/%s", dir, fixed[k]);
        swfs_paths_output(paths, "simulation output", path);
    }
    static const char *pyr[] = {"influence.fits", "imat_ao.fits"};
    for (size_t k = 0; p->wfs_pyramid && k < 2; k++) {
        snprintf(path, sizeof path, "%s/%s", dir, pyr[k]);
        swfs_paths_output(paths, "simulation output", path);
    }
    for (size_t f = 0; f * ffr < nwfs; f++) {
        snprintf(path, sizeof path, "%s/slopes_%03zu.fits", dir, f);
        swfs_paths_output(paths, "simulation output", path);
        snprintf(path, sizeof path, "%s/modal_%03zu.fits", dir, f);
        if (p->export_modal) swfs_paths_output(paths, "simulation output (export_modal)", path);
        snprintf(path, sizeof path, "%s/slopes_valid_%03zu.fits", dir, f);
        if (p->export_modal) swfs_paths_output(paths, "simulation output (export_modal)", path);
        snprintf(path, sizeof path, "%s/truewf_%03zu.fits", dir, f);
        if (p->export_truth) swfs_paths_output(paths, "simulation output (export_truth)", path);
    }
    static const char *modal_files[] = {"dm_modes.fits", "control.fits", "influence.fits", "valid.fits", "cm_modes.fits"};
    for (size_t k = 0; p->export_modal && k < sizeof modal_files / sizeof modal_files[0]; k++) {
        snprintf(path, sizeof path, "%s/%s", dir, modal_files[k]);
        swfs_paths_output(paths, "simulation output (export_modal)", path);
    }
    for (size_t c = 0; c < ncub; c++) {
        snprintf(path, sizeof path, "%s/raw_%03zu.fits", dir, c);
        swfs_paths_output(paths, "simulation output", path);
    }
    if (!p->milk) return swfs_paths_status(paths);
    double *tstart = malloc(ncub * sizeof *tstart);
    if (!tstart) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t c = 0; c < ncub; c++) tstart[c] = cube_start(p, c);
    const int rc = swfs_ts_milk_outputs(p, dir, nwfs, tstart, paths);
    free(tstart);
    return rc;
}

/* export_truth: the frames' residuals gathered on the fit plan's pupil samples TRUTH_BLK at a
 * time (R: npix x TRUTH_BLK, sample-major) and turned into their right-hand sides by one pass
 * vectorized over the block (dmfit.h swfs_dmfit_rhs_many; the sums of swfs_dmfit_rhs, in its
 * order), written as n rows of tb. bt: ntr x TRUTH_BLK scratch. */
#define TRUTH_BLK 32
static int truth_rhs_block(const swfs_dmfit *f, const double *R, size_t n, double *bt, double *rows, size_t ntr)
{
    const int rc = swfs_dmfit_rhs_many(f, R, TRUTH_BLK, n, bt);
    for (size_t j = 0; !rc && j < n; j++)
        for (size_t a = 0; a < ntr; a++) rows[j * ntr + a] = bt[a * n + j];
    return rc;
}

/* export_truth: the frames' right-hand sides in tb (nwfs x ntr) replaced by their fits, a
 * block of frames per GEMM (dmfit.h swfs_dmfit_solve_many). */
static int solve_truth(const swfs_dmfit *f, double *tb, size_t nwfs, size_t ntr)
{
    const size_t blk = 256;
    double *b = malloc(blk * ntr * sizeof *b);
    if (!b) return swfs_fail(SWFS_ERR_NOMEM, "out of memory for the truth's fit");
    for (size_t k = 0; k < nwfs; k += blk) {
        const size_t n = nwfs - k < blk ? nwfs - k : blk;
        memcpy(b, tb + k * ntr, n * ntr * sizeof *b);
        swfs_dmfit_solve_many(f, b, n, tb + k * ntr);
    }
    free(b);
    return SWFS_OK;
}

/* export_truth: truewf_NNN.fits, per WFS frame the true residual fitted on the actuators
 * (tz, ntr per frame, from the DM fit plan; on truth_actuators' points txy when given, then
 * also extension OUTXY) and extension DM the commands of the frame (nact). */
static int write_truth(const char *dir, size_t ntr, const double *txy, size_t nact, size_t nwfs, size_t ffr,
                       double rate, double *tz, const double *tdm, const char *const *prov, size_t nprov)
{
    char path[4200];
    int rc = SWFS_OK;
    for (size_t f = 0; f * ffr < nwfs && !rc; f++) {
        const size_t n = nwfs - f * ffr < ffr ? nwfs - f * ffr : ffr;
        swfs_real z = {ntr, n, 1, tz + f * ffr * ntr}, c = {nact, n, 1, (double *)tdm + f * ffr * nact};
        snprintf(path, sizeof path, "%s/truewf_%03zu.fits", dir, f);
        swfs_fits_out *o = NULL;
        if ((rc = swfs_fits_out_create(&o, path))) break;
        if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, &z, -32)) ||
            (rc = swfs_fits_out_key_string(o, "BUNIT", "m", "true residual wavefront fitted on the actuators")) ||
            (rc = swfs_fits_out_key_double(o, "WFSRATE", rate, "[Hz]")) ||
            (rc = swfs_fits_out_key_long(o, "FRAME0", (long)(f * ffr), "global WFS frame of row 0")) ||
            (rc = swfs_fits_out_real(o, "DM", &c, -32)) ||
            (rc = swfs_fits_out_key_string(o, "BUNIT", "m", "loop's commands in the frame, wavefront at the actuators")) ||
            (txy && (rc = swfs_outxy_write(o, txy, ntr, "the truth's points (x, y), pupil frame"))))
            swfs_fits_out_abort(o);
        else
            rc = swfs_fits_out_commit(o);
    }
    return rc;
}

/* export_truth's plan: the least-squares fit of the project's DM fit (dmfit.h) through the
 * DM's own interpolation, with its default ridge (1e-3 of the mean diagonal). Directions of
 * the actuators the pupil barely sees (under a central obstruction, outside the rim) carry
 * less than that share of an actuator's pupil energy, so the ridge leaves the wavefront on
 * the pupil as it is and keeps them from taking values no slope can predict: with a ridge
 * of 1e-9, 120 um rms at the central actuator under a 0.3 obstruction, where the median
 * actuator's is 1 um, and teach's map 3.25x the ideal speckles on that system
 * (docs/telemetry.md). On truth_actuators' points (*txy, *ntr) when given, else on the
 * DM's (xy, nact; *txy NULL). */
static int truth_plan(const swfs_ts_params *p, const double *mask, const double *xy, size_t nact, swfs_dmfit **tfit,
                      double **txy, size_t *ntr)
{
    const swfs_sim_params *b = &p->base;
    swfs_dmfit_options fo;
    swfs_dmfit_options_default(&fo);
    fo.influence = SWFS_INFLUENCE_CUBIC;
    fo.rim = 1; /* a rim the actuators' hull misses continued as the speckle model reads it */
    const swfs_geom tg = {b->wavelen, b->teldiam, b->obscur, b->pixscale, b->pupdx, b->pupn};
    *ntr = nact;
    int rc = p->truth_actuators[0] ? swfs_actuators_read(p->truth_actuators, txy, ntr) : SWFS_OK;
    if (!rc) rc = swfs_dmfit_create(tfit, *txy ? *txy : xy, *ntr, &tg, mask, &fo);
    return rc;
}

/* What a run builds from the system alone (swfs_ts_shared_create). */
struct swfs_ts_shared {
    size_t ng, nact;
    double *mask, *xy; /* the pupil (pupn^2) and the DM's positions (2 nact) it was made for */
    double *modes;     /* the DM's modes (swfs_dm_modes), NULL with ao_recon */
    swfs_dmfit *tfit;  /* export_truth's plan, NULL without export_truth */
    double *txy;       /* its points when truth_actuators gives them */
    size_t ntr;
    double *Dm;        /* the loop's interaction matrix (ns x nact), NULL with ao_recon */
    size_t ns, raoK;   /* its slopes; the modes the loop's modal reconstructor rao keeps (0: zonal) */
    double rcond;      /* > 0: rao is the zonal one at this ao_rcond */
    swfs_recon *rao;   /* the loop's reconstructor: modal at ao_modes (raoK) or zonal at ao_rcond
                          (rcond), NULL with ao_recon */
    double *raoV;      /* a modal one's factors, rao = raoV raoP (swfs_recon_modal_factors) */
    swfs_recon *raoP;
};

void swfs_ts_shared_free(swfs_ts_shared *s)
{
    if (!s) return;
    free(s->mask);
    free(s->xy);
    free(s->modes);
    free(s->Dm);
    swfs_recon_free(s->rao);
    free(s->raoV);
    swfs_recon_free(s->raoP);
    swfs_dmfit_free(s->tfit);
    free(s->txy);
    free(s);
}

int swfs_ts_shared_create(const swfs_ts_params *p, swfs_ts_shared **out)
{
    *out = NULL;
    int rc = swfs_ts_params_check(p);
    if (rc) return rc;
    const size_t np = (size_t)p->base.pupn;
    swfs_ts_shared *s = calloc(1, sizeof *s);
    swfs_recon *rao = NULL;
    unsigned char *vmap = NULL;
    swfs_sparse *T = NULL;
    swfs_shwfs *sh = NULL;
    if (s) s->mask = malloc(np * np * sizeof *s->mask);
    if (!s || !s->mask) {
        swfs_ts_shared_free(s);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    s->ng = np * np;
    rc = swfs_sim_pupil(&p->base, s->mask);
    if (!rc) rc = swfs_ts_read_given(p, p->base.teldiam, &s->xy, &s->nact, &rao, &vmap);
    if (!rc) rc = swfs_ts_loop_model(p, s->mask, vmap, &s->xy, &s->nact, &T, &sh);
    if (!rc && !p->ao_recon[0]) rc = swfs_dm_modes(T, s->mask, np, &s->modes);
    if (!rc && !p->ao_recon[0]) { /* the loop's reconstructor, for the runs of the same filter */
        s->ns = sh->nslopes;
        rc = swfs_interaction_matrix(sh, T, &s->Dm);
        if (!rc && p->ao_rcond > 0) {
            s->rcond = p->ao_rcond;
            rc = swfs_recon_svd(s->Dm, s->ns, s->nact, p->ao_rcond, 0, &s->rao);
        } else if (!rc) {
            s->raoK = (size_t)p->ao_modes < s->nact - 1 ? (size_t)p->ao_modes : s->nact - 1;
            rc = swfs_recon_modal_factors(s->Dm, s->ns, s->nact, s->modes, 1, s->raoK, &s->raoV, &s->raoP);
            if (!rc) rc = swfs_recon_modal_compose(s->raoV, s->raoP, s->nact, &s->rao);
        }
    }
    if (!rc && p->export_truth) rc = truth_plan(p, s->mask, s->xy, s->nact, &s->tfit, &s->txy, &s->ntr);
    swfs_recon_free(rao);
    free(vmap);
    swfs_sparse_free(T);
    swfs_shwfs_free(sh);
    if (rc) {
        swfs_ts_shared_free(s);
        return rc;
    }
    *out = s;
    return SWFS_OK;
}

/* The shared plans' loop reconstructor is this run's: made from the same interaction matrix
 * (ns x nact) with the same filter (K modes, or the zonal cut rcond). */
static int shared_rao_fits(const swfs_ts_shared *s, const double *Dm, size_t ns, size_t nact, size_t K, double rcond)
{
    return s && s->rao && s->raoK == K && s->rcond == rcond && s->ns == ns &&
           !memcmp(s->Dm, Dm, ns * nact * sizeof *Dm);
}

/* The shared plans s made for this run's system: its pupil and DM, its modes (unless
 * ao_recon gives the loop) and its truth's plan (with export_truth), on the same points. */
static int shared_fits(const swfs_ts_shared *s, const swfs_ts_params *p, const double *mask, const double *xy,
                       size_t nact)
{
    int ok = s->ng == (size_t)p->base.pupn * (size_t)p->base.pupn && !memcmp(s->mask, mask, s->ng * sizeof *mask) &&
             s->nact == nact && !memcmp(s->xy, xy, 2 * nact * sizeof *xy) && (p->ao_recon[0] || s->modes) &&
             (!p->export_truth || s->tfit);
    if (ok && p->export_truth) {
        double *txy = NULL;
        size_t ntr = nact;
        const int rc = p->truth_actuators[0] ? swfs_actuators_read(p->truth_actuators, &txy, &ntr) : SWFS_OK;
        if (rc) return rc;
        ok = ntr == s->ntr && (txy ? s->txy && !memcmp(txy, s->txy, 2 * ntr * sizeof *txy) : !s->txy);
        free(txy);
    }
    return ok ? SWFS_OK : swfs_fail(SWFS_ERR_ARG, "time-series run: the shared plans were made for another system "
                                    "(pupil, DM, modes or the truth's points)");
}

/* T with its rows outside the pupil (mask <= 0) emptied: the DM surface where the loop reads
 * its residual, so that the slopes and the truth's right-hand sides can be taken from the
 * commands through S T and A^T W T (the same sums as on the surface itself). */
static swfs_sparse *pupil_rows(const swfs_sparse *T, const double *mask)
{
    size_t nnz = 0;
    for (size_t r = 0; r < T->nrows; r++)
        if (mask[r] > 0) nnz += T->row_ptr[r + 1] - T->row_ptr[r];
    swfs_sparse *P = swfs_sparse_alloc(T->nrows, T->ncols, nnz);
    if (!P) return NULL;
    size_t e = 0;
    for (size_t r = 0; r < T->nrows; r++) {
        if (mask[r] > 0)
            for (size_t q = T->row_ptr[r]; q < T->row_ptr[r + 1]; q++, e++) {
                P->col[e] = T->col[q];
                P->val[e] = T->val[q];
            }
        P->row_ptr[r + 1] = e;
    }
    return P;
}

/* wfs=pyramid: the linear model's files of the run (docs/telemetry.md, "Any AO system"):
 * influence.fits, each actuator's surface on the pupil grid (PUPN x PUPN x nact, the columns
 * of T: `speckles --basis`), and imat_ao.fits, the loop's interaction matrix (NAXIS1 = nact,
 * NAXIS2 = the signals: `--imat`); recon_ao.fits is the loop's control matrix (`--control`). */
static int write_pyramid_model(const char *dir, const swfs_sparse *T, size_t np, const double *Dm, size_t ns,
                               size_t nact, const swfs_geom *geom, const char *const *prov, size_t nprov)
{
    const size_t ng = np * np;
    swfs_real *F = swfs_real_alloc(np, np, nact);
    double *e = calloc(nact, sizeof *e);
    int rc = F && e ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t a = 0; !rc && a < nact; a++) {
        e[a] = 1;
        swfs_sparse_apply(T, e, F->data + a * ng);
        e[a] = 0;
    }
    char path[4200];
    const swfs_real Dr = {nact, ns, 1, (double *)Dm};
    const swfs_real *arr[2] = {F, &Dr};
    const char *names[2] = {"influence.fits", "imat_ao.fits"}, *units[2] = {"m/m", "1/m"};
    for (int k = 0; k < 2 && !rc; k++) {
        swfs_fits_out *o = NULL;
        snprintf(path, sizeof path, "%s/%s", dir, names[k]);
        if ((rc = swfs_fits_out_create(&o, path))) break;
        if ((rc = swfs_fits_out_set_stamp(o, k ? NULL : geom, prov, nprov)) ||
            (rc = swfs_fits_out_real(o, NULL, arr[k], k ? -64 : -32)) ||
            (rc = swfs_fits_out_key_string(o, "BUNIT", units[k], k ? "pyramid signal per m of actuator wavefront"
                                                                      : "wavefront per unit actuator value")))
            swfs_fits_out_abort(o);
        else rc = swfs_fits_out_commit(o);
    }
    swfs_real_free(F);
    free(e);
    return rc;
}

int swfs_ts_run(const swfs_ts_params *p, const char *dir, const char *const *prov, size_t nprov,
                swfs_ts_progress_fn progress, void *ctx, swfs_ts_summary *sum)
{
    return swfs_ts_run_shared(p, NULL, dir, prov, nprov, progress, ctx, sum);
}

static int ts_run(const swfs_ts_params *p, const swfs_ts_shared *shared, const char *dir, const char *const *prov,
                  size_t nprov, swfs_ts_progress_fn progress, void *ctx, swfs_ts_summary *sum);

/* The run's files as one output group (atomic.h): a run that fails or is stopped half way
 * leaves none of them. */
int swfs_ts_run_shared(const swfs_ts_params *p, const swfs_ts_shared *shared, const char *dir,
                       const char *const *prov, size_t nprov, swfs_ts_progress_fn progress, void *ctx,
                       swfs_ts_summary *sum)
{
    swfs_outputs_begin();
    const int rc = ts_run(p, shared, dir, prov, nprov, progress, ctx, sum);
    const int erc = swfs_outputs_end(rc == SWFS_OK);
    return rc ? rc : erc;
}

static int ts_run(const swfs_ts_params *p, const swfs_ts_shared *shared, const char *dir, const char *const *prov,
                  size_t nprov, swfs_ts_progress_fn progress, void *ctx, swfs_ts_summary *sum)
{
    memset(sum, 0, sizeof *sum);
    int rc = swfs_ts_params_check(p);
    if (!rc) rc = swfs_ts_make_dirs(p, dir);
    if (rc) return rc;
    struct timespec ts0;
    clock_gettime(CLOCK_MONOTONIC, &ts0);
    const swfs_sim_params *b = &p->base;
    const size_t np = (size_t)b->pupn, ng = np * np, nfx = (size_t)b->nfx, nfy = (size_t)b->nfy, nfp = nfx * nfy;
    const double dx = b->pupdx, D = b->teldiam, lam0 = b->wavelen;
    const size_t nlam = p->bandwidth > 0 ? (size_t)p->nlambda : 1;
    const size_t nf = (size_t)p->cube_frames, ncub = (size_t)p->ncubes, nexp = nf * ncub;
    const size_t nsn = b->screen.n;
    char path[4096];

    double *mask = NULL, *ncp = NULL, *screens = NULL, *xy = NULL, *Dm = NULL, *act = NULL, *dmz = NULL, *res = NULL;
    double *resn = NULL, *slopes = NULL, *phi = NULL, *iacc = NULL, *absq = NULL, *xs = NULL, *ys = NULL;
    size_t *rstart = NULL, *rlen = NULL;
    double *sbuf = NULL, *rmean = NULL, *xph = NULL, *xw = NULL, *tb = NULL, *tdm = NULL, *tR = NULL, *tbt = NULL;
    double *Dp = NULL, *tG = NULL; /* S Tp (the slopes of the DM's surface), A^T W Tp (export_truth) */
    swfs_sparse *Tp = NULL;        /* T on the pupil's samples (pupil_rows) */
    /* Exposures open at once: two when an exposure spans at least a WFS frame; a camera
     * faster than the WFS has each frame in up to ceil(2 / ratio) + 1 exposures (engine.h). */
    const size_t nslot = p->frame_ratio >= 1.0 ? 2 : (size_t)ceil(2.0 / p->frame_ratio) + 1;
    size_t xn[32] = {0}, xcap = 0;
    size_t *pin = NULL;
    swfs_sparse *T = NULL;
    swfs_dmfit *tfit = NULL; /* export_truth */
    double *txy = NULL;      /* export_truth's own points (truth_actuators) */
    const double *txy_out = NULL; /* those the truth files carry: txy or the shared plans' */
    size_t ntr = 0;          /* export_truth's points */
    swfs_shwfs *sh = NULL;
    swfs_pyramid *pyr = NULL; /* wfs=pyramid: the sensor (sh then gives its subapertures) */
    swfs_recon *rao = NULL;
    const swfs_recon *rao_shared = NULL; /* the shared plans' reconstructor, when this run's is the same */
    double *raoV_own = NULL;     /* the modal reconstructor's factors (rao = V P), this run's own */
    swfs_recon *raoP_own = NULL;
    double *fk = NULL;           /* their product's middle vector (K) */
    swfs_mft **mft = NULL;
    double complex *fld = NULL, *efoc = NULL, *eid = NULL, *eidtt = NULL, *cpin = NULL;
    swfs_exposure *sched = NULL;
    swfs_real *clean = NULL, *dark = NULL, *flat = NULL;
    swfs_cplx *spk = NULL, *spktt = NULL;
    swfs_handshake *hs = NULL;
    unsigned char *vmap = NULL;
    size_t nact = 0;
    if ((rc = swfs_ts_read_given(p, D, &xy, &nact, &rao, &vmap))) goto done;

    /* Pupil, NCP. */
    mask = malloc(ng * sizeof *mask);
    ncp = malloc(ng * sizeof *ncp);
    if (!mask || !ncp) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    if ((rc = swfs_sim_pupil(b, mask))) goto done;
    if ((rc = swfs_sim_ncp_map(b, mask, ncp, &sum->ncp_rms, NULL))) goto done;
    size_t npin = 0;
    double S = 0;
    pin = malloc(ng * sizeof *pin);
    xs = malloc(ng * sizeof *xs);
    ys = malloc(ng * sizeof *ys);
    if (!pin || !xs || !ys) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    double sxx = 0, syy = 0;
    for (size_t q = 0; q < np; q++)
        for (size_t i = 0; i < np; i++) {
            size_t k = q * np + i;
            xs[k] = ((double)i - 0.5 * (double)(np - 1)) * dx;
            ys[k] = ((double)q - 0.5 * (double)(np - 1)) * dx;
            if (mask[k] > 0) { pin[npin++] = k; S += mask[k]; sxx += xs[k] * xs[k]; syy += ys[k] * ys[k]; }
        }
    /* the pupil samples as runs along the grid's rows (consecutive in pin, in the grid and on
     * the periodic screens, where sample g sits at whole samples ((g % np) % nsn, (g / np) %
     * nsn)), each starting at pin[rstart[r]], rlen[r] long */
    rstart = malloc((npin ? npin : 1) * sizeof *rstart);
    rlen = malloc((npin ? npin : 1) * sizeof *rlen);
    if (!rstart || !rlen) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    size_t nrun = 0;
    for (size_t m = 0; m < npin; m++) {
        if (nrun && pin[m] == pin[m - 1] + 1 && pin[m] / np == pin[m - 1] / np && (pin[m] % np) % nsn != 0) {
            rlen[nrun - 1]++;
        } else {
            rstart[nrun] = m;
            rlen[nrun++] = 1;
        }
    }

    /* Frozen-flow layers: periodic von Karman screens, scaled to their share of r0^{-5/3}. */
    screens = malloc((size_t)p->nlayers * nsn * nsn * sizeof *screens);
    if (!screens) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    for (int l = 0; l < p->nlayers; l++) {
        swfs_screen_params sp = b->screen;
        sp.subharmonics = 0;
        swfs_rng rng;
        swfs_rng_seed2(&rng, b->seed, 1000 + (uint64_t)l);
        double *s = screens + (size_t)l * nsn * nsn;
        if ((rc = swfs_screen_vonkarman(&sp, &rng, s, NULL))) goto done;
        double sc = sqrt(p->layer_frac[l]);
        for (size_t k = 0; k < nsn * nsn; k++) s[k] *= sc;
        if ((rc = swfs_progress_report(progress, ctx, "screens", (size_t)l + 1, (size_t)p->nlayers))) goto done;
    }

    /* DM, WFS, the loop's reconstructor. */
    /* A DM given by its positions (read above) has the same loop, interpolation and modal filter. */
    if ((rc = swfs_ts_loop_model(p, mask, vmap, &xy, &nact, &T, &sh))) goto done;
    if (shared && (rc = shared_fits(shared, p, mask, xy, nact))) goto done;
    if (p->wfs_pyramid) {
        /* the pyramid on the Shack-Hartmann's subapertures; its interaction matrix by
         * push-pull of each actuator by a hundredth of its wavelength */
        const double lw = p->wfs_wavelen > 0 ? p->wfs_wavelen : lam0;
        if ((rc = swfs_pyramid_create(&pyr, (size_t)p->nsub, D, mask, np, dx, sh->valid, lw, p->pyr_mod,
                                      (size_t)p->pyr_nmod)))
            goto done;
        if ((rc = swfs_progress_report(progress, ctx, "pyramid interaction matrix", 0, nact))) goto done;
        if ((rc = swfs_pyramid_interaction(pyr, T, lw / 100, &Dm))) goto done;
        if ((rc = swfs_progress_report(progress, ctx, "pyramid interaction matrix", nact, nact))) goto done;
    } else if ((rc = swfs_interaction_matrix(sh, T, &Dm))) {
        goto done;
    }
    if (!(Tp = pupil_rows(T, mask))) { rc = SWFS_ERR_NOMEM; goto done; }
    /* The slopes of the DM's surface by S Tp a (dense, ns x nact) where that reads no more
     * memory than the surface itself (Tp's nonzeros: a value, a column index and the gathered
     * command each, 3 words against the dense product's 1 per element): the loop then builds
     * the surface only for the frames the camera sees. Either way the same sums to rounding. */
    const int lin = !pyr && sh->nslopes * nact <= 3 * Tp->nnz; /* a pyramid is not linear */
    if (lin && (rc = swfs_interaction_matrix(sh, Tp, &Dp))) goto done;
    if (p->ao_recon[0]) {
        /* The loop's own reconstructor (its modal filter and gains), as recon_ao.fits holds one. */
        if ((rc = swfs_ts_check_given_recon(p->ao_recon, rao, sh, nact))) goto done;
    } else if (p->ao_rcond > 0) {
        /* A zonal loop: the pseudo-inverse of its own interaction matrix, the modes of small
         * singular value (piston, waffle, what the sensor barely sees) left out; the shared
         * plans' when made from the same matrix and cut (teach's loops: one SVD for all). */
        if (shared_rao_fits(shared, Dm, sh->nslopes, nact, 0, p->ao_rcond)) rao_shared = shared->rao;
        else if ((rc = swfs_recon_svd(Dm, sh->nslopes, nact, p->ao_rcond, 0, &rao))) goto done;
    } else {
        /* The loop's modal filter: the K lowest-energy DM modes after piston (Sec. 4.1); the
         * shared plans' reconstructor when it was made from the same interaction matrix and K
         * (teach's loops: one SVD for all of them). */
        size_t K = (size_t)p->ao_modes < nact - 1 ? (size_t)p->ao_modes : nact - 1;
        if (shared_rao_fits(shared, Dm, sh->nslopes, nact, K, 0)) {
            rao_shared = shared->rao;
        } else {
            double *modes = NULL;
            if (!shared && (rc = swfs_dm_modes(T, mask, np, &modes))) goto done;
            rc = swfs_recon_modal_factors(Dm, sh->nslopes, nact, shared ? shared->modes : modes, 1, K, &raoV_own,
                                          &raoP_own);
            free(modes);
            if (!rc) rc = swfs_recon_modal_compose(raoV_own, raoP_own, nact, &rao);
            if (rc) goto done;
        }
    }
    const swfs_recon *ra = rao_shared ? rao_shared : rao; /* the loop's reconstructor */
    /* applied as its two factors where they cost less per frame than W (K (nact + ns) against
     * nact ns: the modal filter keeps fewer modes than half the smaller side), the same to
     * rounding */
    const double *raoV = rao_shared ? shared->raoV : raoV_own;
    const swfs_recon *raoP = rao_shared ? shared->raoP : raoP_own;
    const size_t rK = raoP ? raoP->nact : 0;
    if (raoP && rK * (nact + sh->nslopes) >= nact * sh->nslopes) raoP = NULL;
    if (raoP && !(fk = malloc(rK * sizeof *fk))) { rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    sum->nact = nact;
    sum->nvalid = sh->nvalid;
    sum->ao_modes = ra->nmodes;
    const size_t ns = sh->nslopes;

    /* Camera schedule: cube c starts at t_c (global WFS frames). */
    sched = malloc(nexp * sizeof *sched);
    hs = calloc(ncub, sizeof *hs);
    double *tstart = malloc(ncub * sizeof *tstart);
    if (!sched || !hs || !tstart) { free(tstart); rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    const size_t nwfs = ts_schedule(p, sched, 1, tstart);
    sum->nwfs = nwfs;
    const size_t ffr = p->wfs_file_frames > 0 ? (size_t)p->wfs_file_frames : nwfs;
    for (size_t c = 0; c < ncub; c++) {
        size_t logged = (size_t)floor(tstart[c]) + (size_t)p->handshake_lag;
        snprintf(hs[c].camera, sizeof hs[c].camera, "raw_%03zu.fits", c);
        snprintf(hs[c].slopes, sizeof hs[c].slopes, "slopes_%03zu.fits", logged / ffr);
        hs[c].frame = (long)(logged % ffr);
    }

    /* Work buffers. */
    act = calloc(nact, sizeof *act);
    dmz = calloc(ng, sizeof *dmz);
    res = calloc(ng, sizeof *res);
    resn = calloc(ng, sizeof *resn);
    slopes = calloc(nwfs * ns, sizeof *slopes);
    phi = malloc(npin * sizeof *phi);
    cpin = malloc(npin * sizeof *cpin);
    fld = calloc(ng, sizeof *fld);
    efoc = malloc(nfp * sizeof *efoc);
    absq = malloc(nfp * sizeof *absq);
    iacc = calloc(nslot * nfp, sizeof *iacc);
    eid = calloc(nslot * ng, sizeof *eid);
    /* Per exposure slot (e % nslot): the tip-tilt-free phases [m] of its WFS frames and their
     * (weight, tip, tilt), so the exposure-mean tip-tilt can be put back into the frames
     * once the exposure is complete (the ideal speckles keep the motion within it). */
    for (size_t e = 0; e < nexp; e++)
        if (sched[e].count > xcap) xcap = sched[e].count;
    xph = malloc(nslot * xcap * npin * sizeof *xph);
    xw = malloc(nslot * xcap * 3 * sizeof *xw);
    eidtt = calloc(nslot * ng, sizeof *eidtt);
    sbuf = calloc(ns, sizeof *sbuf);
    rmean = calloc(ng, sizeof *rmean);
    mft = calloc(nlam, sizeof *mft);
    clean = swfs_real_alloc(nfx, nfy, nexp);
    spk = swfs_cplx_alloc(nfx, nfy, nexp);
    spktt = swfs_cplx_alloc(nfx, nfy, nexp);
    if (!act || !dmz || !res || !resn || !slopes || !phi || !cpin || !fld || !efoc || !absq || !iacc || !eid || !eidtt ||
        !sbuf || !rmean || !xph || !xw || !mft || !clean || !spk || !spktt) {
        free(tstart);
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        goto done;
    }
    double lam[64];
    for (size_t l = 0; l < nlam; l++) {
        lam[l] = nlam == 1 ? lam0 : lam0 * (1 + p->bandwidth * ((double)l / (double)(nlam - 1) - 0.5));
        /* Pixels are fixed in angle: PIXSCALE lambda0/D per pixel = PIXSCALE (lambda0/lambda) lambda/D. */
        mft[l] = swfs_mft_create(np, nfx, nfy, b->pixscale * dx / D * lam0 / lam[l], SWFS_MFT_SINGLE);
        if (!mft[l]) { free(tstart); rc = SWFS_ERR_NOMEM; goto done; }
    }
    swfs_mft *mft0 = nlam == 1 ? mft[0] : swfs_mft_create(np, nfx, nfy, b->pixscale * dx / D, SWFS_MFT_SINGLE);
    if (!mft0) { free(tstart); rc = SWFS_ERR_NOMEM; goto done; }
    const double alpha0 = b->pixscale * dx / D;
    double S2 = 0;
    for (size_t k = 0; k < npin; k++) S2 += mask[pin[k]] * mask[pin[k]];
    const double C = b->total_counts * alpha0 * alpha0 / S2 / p->frame_ratio;

    /* The loop. Commands a act on frame k; the slopes of frame k - delay + 1 update them
     * for frame k + 1 (delay 1: the classic one-frame integrator). */
    swfs_rng nrng;
    swfs_rng_seed2(&nrng, b->seed, 7);
    const double vib = p->vib_amp * lam0 / D, va = p->vib_angle * M_PI / 180;
    const double jrho = exp(-2 * M_PI * p->jitter_freq / p->wfs_rate);
    const double jsig = p->jitter_amp * lam0 / D * sqrt(1 - jrho * jrho);
    double jx = 0, jy = 0;
    size_t e_lo = 0, ninexp = 0;
    double sres2 = 0, sres2n = 0, stt2 = 0, sstrehl = 0;
    double *dact = malloc(nact * sizeof *dact);
    const swfs_dmfit *tplan = NULL; /* export_truth's plan: the shared one, or tfit */
    if (p->export_truth) {
        if (shared) {
            tplan = shared->tfit;
            ntr = shared->ntr;
            txy_out = shared->txy;
        } else if ((rc = truth_plan(p, mask, xy, nact, &tfit, &txy, &ntr))) {
            free(dact); free(tstart); goto done;
        } else {
            tplan = tfit;
            txy_out = txy;
        }
        tb = malloc(nwfs * ntr * sizeof *tb);
        tdm = malloc(nwfs * nact * sizeof *tdm);
        tR = malloc(swfs_dmfit_npix(tplan) * TRUTH_BLK * sizeof *tR);
        tbt = malloc(ntr * TRUTH_BLK * sizeof *tbt);
        if (!tb || !tdm || !tR || !tbt) { free(dact); dact = NULL; }
        else if (lin && (rc = swfs_dmfit_rhs_matrix(tplan, Tp, &tG))) { free(dact); free(tstart); goto done; }
    }
    if (!dact) { free(tstart); rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory"); goto done; }
    /* Each frame's residual is turbulence + tip-tilt - the DM's surface T a. The slopes and the
     * truth's right-hand sides are linear in it: with lin they are taken from the turbulence
     * and the commands (S Tp a, A^T W Tp a: one small GEMV per frame, one GEMM per block of
     * frames), and the surface itself is made only for the frames the camera sees. */
    for (size_t k = 0; k < nwfs; k++) {
        double t = (double)k / p->wfs_rate;
        /* Camera: exposures containing frame k (at most nslot, consecutive). */
        while (e_lo < nexp && sched[e_lo].first + sched[e_lo].count <= k) e_lo++;
        int any = 0;
        for (size_t e = e_lo; e < nexp && e < e_lo + nslot; e++)
            if (sched[e].first <= k && k < sched[e].first + sched[e].count) any = 1;
        if (any || !lin) swfs_sparse_apply_rows(Tp, act, pin, npin, dmz); /* the surface where the residual is read */
        double th = vib * sin(2 * M_PI * p->vib_freq * t);
        /* Broadband jitter: AR(1) low-pass white noise per axis (breaks the half-period
         * ambiguity a pure sinusoid leaves in the synchronization). */
        jx = jrho * jx + jsig * swfs_rng_normal(&nrng);
        jy = jrho * jy + jsig * swfs_rng_normal(&nrng);
        double tvx = th * cos(va) + jx, tvy = th * sin(va) + jy;
        /* each layer's shift of this frame [samples], once per frame (not per sample) */
        screen_shift lsh[SWFS_TS_MAX_LAYERS];
        for (int l = 0; l < p->nlayers; l++) {
            double ang = p->layer_dir[l] * M_PI / 180, sh_ = p->layer_speed[l] * t / dx;
            lsh[l] = screen_shift_of(nsn, -sh_ * cos(ang), -sh_ * sin(ang));
        }
        for (size_t m = 0; m < npin; m++) { /* tip-tilt and turbulence (with lin: res before the DM) */
            size_t g = pin[m];
            res[g] = tvx * xs[g] + tvy * ys[g] - (lin ? 0.0 : dmz[g]);
        }
        for (int l = 0; l < p->nlayers; l++)
            for (size_t r = 0; r < nrun; r++) {
                const size_t g = pin[rstart[r]];
                screen_add_run(screens + (size_t)l * nsn * nsn, nsn, (g % np) % nsn, (g / np) % nsn, rlen[r], lsh + l,
                               res + g);
            }
        if (tplan) { /* export_truth: the fit's right-hand side (solved after the loop), and the commands */
            const size_t jj = k % TRUTH_BLK, npx = swfs_dmfit_npix(tplan);
            const size_t *px = swfs_dmfit_pix(tplan);
            for (size_t q = 0; q < npx; q++) tR[q * TRUTH_BLK + jj] = res[px[q]];
            memcpy(tdm + k * nact, act, nact * sizeof *act);
            if (jj + 1 == TRUTH_BLK || k + 1 == nwfs) {
                if ((rc = truth_rhs_block(tplan, tR, jj + 1, tbt, tb + (k - jj) * ntr, ntr))) {
                    free(tstart); free(dact); goto done;
                }
                /* minus the DM surfaces' right-hand sides, A^T W Tp a, for the block's frames */
                if (lin)
                    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)(jj + 1), (int)ntr, (int)nact, -1.0,
                                tdm + (k - jj) * nact, (int)nact, tG, (int)nact, 1.0, tb + (k - jj) * ntr, (int)ntr);
            }
        }
        /* WFS: slopes with noise (of the turbulence, minus those of the DM's surface). */
        double *sk = slopes + k * ns;
        if (pyr) {
            swfs_pyramid_measure(pyr, res, p->pyr_photons, &nrng, sk);
        } else {
            swfs_shwfs_measure(sh, res, sk);
            if (lin) cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)ns, (int)nact, -1.0, Dp, (int)nact, act, 1, 1.0, sk, 1);
            for (size_t i = 0; i < ns; i++)
                if (sh->valid[i % (ns / 2)]) sk[i] += p->slope_noise * swfs_rng_normal(&nrng);
        }
        /* Controller. */
        if (k + 1 >= (size_t)p->ao_delay) {
            const double *sd = slopes + (k + 1 - (size_t)p->ao_delay) * ns;
            if (raoP) {
                swfs_recon_apply(raoP, sd, fk);
                cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nact, (int)rK, 1.0, raoV, (int)rK, fk, 1, 0.0, dact, 1);
            } else {
                swfs_recon_apply(ra, sd, dact);
            }
            for (size_t a = 0; a < nact; a++) act[a] += p->ao_gain * dact[a];
        }
        if (!any) continue;
        /* The residual (with lin: minus the DM's surface of this frame's commands, made above). */
        double mean = 0;
        for (size_t m = 0; m < npin; m++) {
            const size_t g = pin[m];
            if (lin) res[g] -= dmz[g];
            mean += res[g];
        }
        mean /= (double)npin;
        /* Statistics and the tip-tilt-free residual. */
        double v2 = 0, cx = 0, cy = 0;
        for (size_t m = 0; m < npin; m++) {
            size_t g = pin[m];
            res[g] -= mean;
            v2 += res[g] * res[g];
            cx += res[g] * xs[g];
            cy += res[g] * ys[g];
        }
        cx /= sxx; cy /= syy;
        double v2n = 0;
        for (size_t m = 0; m < npin; m++) {
            size_t g = pin[m];
            resn[g] = res[g] - cx * xs[g] - cy * ys[g];
            v2n += resn[g] * resn[g];
        }
        ninexp++;
        for (size_t m = 0; m < npin; m++) rmean[pin[m]] += resn[pin[m]];
        sres2 += v2 / (double)npin;
        sres2n += v2n / (double)npin;
        stt2 += (cx * cx + cy * cy) / ((lam0 / D) * (lam0 / D));
        /* Science intensity (with NCP) at each wavelength. */
        for (size_t i = 0; i < nfp; i++) absq[i] = 0;
        for (size_t l = 0; l < nlam; l++) {
            for (size_t m = 0; m < npin; m++) phi[m] = 2 * M_PI * (res[pin[m]] + ncp[pin[m]]) / lam[l];
            swfs_expi_d(phi, NULL, cpin, npin);
            double complex core = 0;
            for (size_t m = 0; m < npin; m++) { fld[pin[m]] = mask[pin[m]] * cpin[m]; core += fld[pin[m]]; }
            if (l == nlam / 2) sstrehl += creal(core * conj(core)) / (S * S);
            if ((rc = swfs_mft_forward(mft[l], fld, efoc))) { free(tstart); free(dact); goto done; }
            for (size_t i = 0; i < nfp; i++) absq[i] += creal(efoc[i] * conj(efoc[i])) / (double)nlam;
        }
        /* Ideal speckle fields at lambda0 (no NCP): the frames of each exposure are kept
         * (tip-tilt-free phase, tip, tilt) and summed with the exposure-mean tip-tilt
         * removed when it is complete (ideal_exposure); and with all of the tip-tilt kept. */
        for (size_t e = e_lo; e < nexp && e < e_lo + nslot; e++) {
            const swfs_exposure *x = sched + e;
            if (!(x->first <= k && k < x->first + x->count)) continue;
            double w = k == x->first ? x->w_first : (k + 1 == x->first + x->count ? x->w_last : 1.0);
            double *ia = iacc + (e % nslot) * nfp;
            for (size_t i = 0; i < nfp; i++) ia[i] += w * absq[i];
            size_t sl = e % nslot, r = xn[sl]++;
            double *ph = xph + (sl * xcap + r) * npin, *wt = xw + (sl * xcap + r) * 3;
            for (size_t m = 0; m < npin; m++) ph[m] = resn[pin[m]];
            wt[0] = w; wt[1] = cx; wt[2] = cy;
        }
        for (size_t m = 0; m < npin; m++) phi[m] = 2 * M_PI * res[pin[m]] / lam0;
        swfs_expi_d(phi, NULL, cpin, npin);
        for (size_t e = e_lo; e < nexp && e < e_lo + nslot; e++) {
            const swfs_exposure *x = sched + e;
            if (!(x->first <= k && k < x->first + x->count)) continue;
            double w = k == x->first ? x->w_first : (k + 1 == x->first + x->count ? x->w_last : 1.0);
            double complex *et = eidtt + (e % nslot) * ng;
            for (size_t m = 0; m < npin; m++) et[pin[m]] += w * mask[pin[m]] * cpin[m];
            /* Exposure complete: finalize (eq:downsampledHalo for the ideal fields). */
            if (k + 1 == x->first + x->count) {
                double *ia = iacc + (e % nslot) * nfp;
                double complex *ei = eid + (e % nslot) * ng;
                ideal_exposure(xph + (e % nslot) * xcap * npin, xw + (e % nslot) * xcap * 3, xn[e % nslot], pin, npin, xs, ys, mask,
                               lam0, phi, cpin, ei);
                xn[e % nslot] = 0;
                double *dst = swfs_real_frame(clean, e);
                for (size_t i = 0; i < nfp; i++) { dst[i] = C * ia[i] + p->background; ia[i] = 0; }
                double complex *h = swfs_cplx_frame(spk, e);
                if ((rc = swfs_mft_forward(mft0, ei, h))) { free(tstart); free(dact); goto done; }
                core_reference(h, nfx, nfy);
                h = swfs_cplx_frame(spktt, e);
                if ((rc = swfs_mft_forward(mft0, et, h))) { free(tstart); free(dact); goto done; }
                core_reference(h, nfx, nfy);
                memset(ei, 0, ng * sizeof *ei);
                memset(et, 0, ng * sizeof *et);
            }
        }
        if ((k % 256 == 0 || k + 1 == nwfs) && (rc = swfs_progress_report(progress, ctx, "WFS frames", k + 1, nwfs))) {
            free(tstart);
            free(dact);
            goto done;
        }
    }
    free(dact);
    if (nlam > 1) swfs_mft_free(mft0);
    {
        /* The time-mean residual (tip-tilt removed): a static aberration the speckles do
         * not carry, so the NCP estimate sees it too. */
        double s1 = 0, s2 = 0;
        for (size_t m = 0; m < npin; m++) {
            double v = rmean[pin[m]] / (double)(ninexp ? ninexp : 1);
            rmean[pin[m]] = v;
            s1 += v; s2 += v * v;
        }
        sum->static_rms = sqrt(fmax(s2 / (double)npin - (s1 / (double)npin) * (s1 / (double)npin), 0));
    }
    sum->residual_rms = sqrt(sres2 / (double)(ninexp ? ninexp : 1));
    sum->residual_rms_nott = sqrt(sres2n / (double)(ninexp ? ninexp : 1));
    sum->tt_rms = sqrt(stt2 / (double)(ninexp ? ninexp : 1));
    sum->strehl = sstrehl / (double)(ninexp ? ninexp : 1);

    /* Ideal speckles: minus the ensemble mean (eq:computedSpeckleField). */
    swfs_cplx *cubes2[2] = {spk, spktt};
    for (int w = 0; w < 2; w++)
        for (size_t i = 0; i < nfp; i++) {
            double complex m = 0;
            for (size_t e = 0; e < nexp; e++) m += cubes2[w]->data[e * nfp + i];
            m /= (double)nexp;
            for (size_t e = 0; e < nexp; e++) cubes2[w]->data[e * nfp + i] -= m;
        }

    /* The camera's orientation: the detector sees the focal plane turned (the flat, dark and
     * bad pixels below belong to the detector). */
    if ((p->camera_swap || p->camera_flip_x || p->camera_flip_y) && (rc = camera_turn(p, clean))) {
        free(tstart);
        goto done;
    }
    /* Raw camera: noise on the photons, then flat and dark (hot and dead pixels). */
    swfs_real *noisy = swfs_real_copy(clean);
    dark = swfs_real_alloc(nfx, nfy, 1);
    flat = swfs_real_alloc(nfx, nfy, 1);
    if (!noisy || !dark || !flat) { swfs_real_free(noisy); free(tstart); rc = SWFS_ERR_NOMEM; goto done; }
    if ((rc = swfs_sim_camera(clean, b->read_noise, b->gain, b->seed ^ 0xca3e7aULL, noisy))) { swfs_real_free(noisy); free(tstart); goto done; }
    swfs_rng crng;
    swfs_rng_seed2(&crng, b->seed, 11);
    for (size_t i = 0; i < nfp; i++) {
        dark->data[i] = p->dark_level + 2 * swfs_rng_normal(&crng);
        flat->data[i] = 1 + p->flat_rms * swfs_rng_normal(&crng);
    }
    for (long h = 0; h < p->nhot + p->ndead; h++) {
        size_t i = (size_t)(swfs_rng_uniform(&crng) * (double)nfp);
        if (h < p->nhot) dark->data[i] += 2000 + 3000 * swfs_rng_uniform(&crng);
        else flat->data[i] = 0.02;
    }
    for (size_t e = 0; e < nexp; e++)
        for (size_t i = 0; i < nfp; i++) noisy->data[e * nfp + i] = flat->data[i] * noisy->data[e * nfp + i] + dark->data[i];

    /* Files. */
    swfs_geom geom = {lam0, D, b->obscur, b->pixscale, dx, (long)np};
    for (size_t f = 0; f * ffr < nwfs && rc == SWFS_OK; f++) {
        size_t n = nwfs - f * ffr < ffr ? nwfs - f * ffr : ffr;
        swfs_real sa = {ns, n, 1, slopes + f * ffr * ns};
        snprintf(path, sizeof path, "%s/slopes_%03zu.fits", dir, f);
        swfs_fits_out *o = NULL;
        if ((rc = swfs_fits_out_create(&o, path))) break;
        if ((rc = swfs_fits_out_set_stamp(o, NULL, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, &sa, -32)) ||
            (pyr ? (rc = swfs_fits_out_key_string(o, "BUNIT", "", "pyramid signals: x then y, normalized")) ||
                       (rc = swfs_fits_out_key_string(o, "WFSTYPE", "PYRAMID", "modulated pyramid (pyramid.h)")) ||
                       (rc = swfs_fits_out_key_double(o, "PYRMOD", p->pyr_mod, "[lambda/D] modulation radius")) ||
                       (rc = swfs_fits_out_key_long(o, "PYRNMOD", (long)pyr->nmod, "modulation points")) ||
                       (rc = swfs_fits_out_key_double(o, "WFSLAM", pyr->wavelen, "[m] sensing wavelength"))
                 : (rc = swfs_fits_out_key_string(o, "BUNIT", "rad", "wavefront tilt: x slopes then y slopes"))) ||
            (rc = swfs_fits_out_key_double(o, "WFSRATE", p->wfs_rate, "[Hz]")) ||
            (rc = swfs_fits_out_key_long(o, "NSUB", p->nsub, "subapertures across")) ||
            (rc = swfs_fits_out_key_long(o, "FRAME0", (long)(f * ffr), "global WFS frame of row 0"))) {
            swfs_fits_out_abort(o);
            break;
        }
        rc = swfs_fits_out_commit(o);
    }
    if (!rc && tb) rc = solve_truth(tplan, tb, nwfs, ntr);
    if (!rc && tb) rc = write_truth(dir, ntr, txy_out, nact, nwfs, ffr, p->wfs_rate, tb, tdm, prov, nprov);
    if (rc) { swfs_real_free(noisy); free(tstart); goto done; }
    snprintf(path, sizeof path, "%s/actuators.fits", dir);
    if ((rc = swfs_actuators_write(xy, nact, path))) { swfs_real_free(noisy); free(tstart); goto done; }
    snprintf(path, sizeof path, "%s/pupil.fits", dir);
    if ((rc = write_real(path, &(swfs_real){np, np, 1, mask}, &geom, prov, nprov, 0, 0))) {
        swfs_real_free(noisy); free(tstart); goto done;
    }
    snprintf(path, sizeof path, "%s/recon_ao.fits", dir);
    if ((rc = swfs_recon_write(ra, path))) { swfs_real_free(noisy); free(tstart); goto done; }
    if (pyr && (rc = write_pyramid_model(dir, T, np, Dm, ns, nact, &geom, prov, nprov))) {
        swfs_real_free(noisy); free(tstart); goto done;
    }
    snprintf(path, sizeof path, "%s/handshake.log", dir);
    if ((rc = swfs_handshake_write(path, hs, ncub))) { swfs_real_free(noisy); free(tstart); goto done; }
    for (size_t c = 0; c < ncub && rc == SWFS_OK; c++) {
        swfs_real cube = {nfx, nfy, nf, noisy->data + c * nf * nfp};
        snprintf(path, sizeof path, "%s/raw_%03zu.fits", dir, c);
        rc = write_real(path, &cube, &geom, prov, nprov, b->gain, p->frame_ratio / p->wfs_rate);
    }
    if (!rc && p->milk) /* the same telemetry and frames as milk logs */
        rc = swfs_ts_milk_write(p, dir, slopes, nwfs, ns, noisy->data, nfx, nfy, tstart, &geom, prov, nprov, b->gain);
    swfs_real_free(noisy);
    if (!rc) { snprintf(path, sizeof path, "%s/dark.fits", dir); rc = write_real(path, dark, &geom, prov, nprov, 0, 0); }
    if (!rc) { snprintf(path, sizeof path, "%s/flat.fits", dir); rc = write_real(path, flat, &geom, prov, nprov, 0, 0); }
    const swfs_real rmap = {np, np, 1, rmean};
    if (!rc) {
        snprintf(path, sizeof path, "%s/speckles_ideal.fits", dir);
        rc = write_cplx_cube(path, spk, &geom, prov, nprov, "ideal speckles: true residual, no NCP, exposure-mean tip-tilt removed",
                             &rmap, sum->static_rms);
    }
    if (!rc) {
        snprintf(path, sizeof path, "%s/speckles_ideal_tt.fits", dir);
        rc = write_cplx_cube(path, spktt, &geom, prov, nprov, "ideal speckles: true residual, no NCP, tip-tilt kept",
                             &rmap, sum->static_rms);
    }
    if (!rc) {
        snprintf(path, sizeof path, "%s/truth.fits", dir);
        swfs_fits_out *o = NULL;
        swfs_real nm = {np, np, 1, ncp}, pm = {np, np, 1, mask}, rm = {np, np, 1, rmean};
        if (!(rc = swfs_fits_out_create(&o, path))) {
            if ((rc = swfs_fits_out_set_stamp(o, &geom, prov, nprov)) || (rc = swfs_fits_out_real(o, "NCP", &nm, -64)) ||
                (rc = swfs_fits_out_key_double(o, "RATIO", p->frame_ratio, "true <t_sci/t_wfs>")) ||
                (rc = swfs_fits_out_key_long(o, "HSLAG", p->handshake_lag, "true handshake lag [WFS frames]")) ||
                (rc = swfs_fits_out_key_double(o, "RESRMS", sum->residual_rms, "[m] AO residual rms")) ||
                (rc = swfs_fits_out_key_double(o, "RESRMSNT", sum->residual_rms_nott, "[m] same, tip-tilt removed")) ||
                (rc = swfs_fits_out_key_double(o, "TTRMS", sum->tt_rms, "[lambda/D] residual tip-tilt")) ||
                (rc = swfs_fits_out_key_double(o, "NCPRMS", sum->ncp_rms, "[m]")) ||
                (rc = swfs_fits_out_key_double(o, "STATRMS", sum->static_rms, "[m] time-mean AO residual, tip-tilt removed")) ||
                (rc = swfs_fits_out_real(o, "PUPIL", &pm, -32)) ||
                (rc = swfs_fits_out_real(o, "RESMEAN", &rm, -64)))
                swfs_fits_out_abort(o);
            else
                rc = swfs_fits_out_commit(o);
        }
    }
    if (!rc) {
        snprintf(path, sizeof path, "%s/truth_timing.txt", dir);
        swfs_atomic *a = NULL;
        if (!(rc = swfs_atomic_begin(&a, path, 1))) {
            FILE *f = swfs_atomic_stream(a);
            fprintf(f, "# true timing: ratio %.6f, handshake lag %ld WFS frames, file length %zu\n", p->frame_ratio,
                    p->handshake_lag, ffr);
            fprintf(f, "# cube  start (global WFS frame)  slopes file  start in file\n");
            for (size_t c = 0; c < ncub; c++)
                fprintf(f, "%zu %.6f slopes_%03zu.fits %.6f\n", c, tstart[c], (size_t)floor(tstart[c]) / ffr,
                        tstart[c] - (double)(((size_t)floor(tstart[c]) / ffr) * ffr));
            rc = swfs_atomic_commit(a);
        }
    }
    free(tstart);
    struct timespec ts1;
    clock_gettime(CLOCK_MONOTONIC, &ts1);
    sum->seconds = (double)(ts1.tv_sec - ts0.tv_sec) + 1e-9 * (double)(ts1.tv_nsec - ts0.tv_nsec);
done:
    if (mft)
        for (size_t l = 0; l < nlam; l++) swfs_mft_free(mft[l]);
    free(mft);
    free(mask); free(ncp); free(screens); free(xy); free(Dm); free(act); free(dmz); free(res); free(resn); free(slopes);
    free(phi); free(iacc); free(absq); free(xs); free(ys); free(sbuf); free(pin); free(fld); free(efoc); free(eid);
    free(rstart); free(rlen); free(eidtt); free(cpin); free(sched); free(hs); free(rmean); free(xph); free(xw); free(tb); free(tdm); free(tR); free(tbt);
    swfs_sparse_free(T);
    swfs_sparse_free(Tp);
    free(Dp); free(tG);
    swfs_dmfit_free(tfit);
    free(txy);
    swfs_shwfs_free(sh);
    swfs_pyramid_free(pyr);
    swfs_recon_free(rao);
    free(raoV_own);
    swfs_recon_free(raoP_own);
    free(fk);
    free(vmap);
    swfs_real_free(clean); swfs_real_free(dark); swfs_real_free(flat);
    swfs_cplx_free(spk); swfs_cplx_free(spktt);
    return rc;
}

/* speckles: timing table + telemetry -> the speckle cube. See include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/fits.h"
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/pupil.h"
#include "specklewfs/source.h"
#include "specklewfs/speckles.h"
#include "specklewfs/reduce.h"
#include "run_internal.h"

#include <complex.h>
#include <limits.h>
#include <stdint.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_speckles_run_options_default(swfs_speckles_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_pipeline_options_default(&o->pipe);
    swfs_geom_init(&o->geom);
    swfs_linear_files_default(&o->lin);
    o->mean_mode = SWFS_MEAN_ENSEMBLE;
    o->batch = 128;
    o->pipe.recon = SWFS_RECON_TEACH;
    o->teach_loops = 12;
    o->teach_seed = 101;
    o->mean_teach_loops = 4;
    o->mean_teach = SWFS_MEAN_TEACH_AUTO;
    o->loops_map = SWFS_LOOPS_MAP_AUTO;
}

static size_t piece(const swfs_speckles_run_options *o) { return o->batch ? o->batch : 128; }

/* Everything the run holds, freed in one place. */
typedef struct work {
    swfs_timing *t;
    swfs_geom g;
    size_t nfx, nfy, nsci, nslopes, maxn;
    double *xy, *mask, *train;
    size_t nact, ntrain;
    double curl_noise; /* [rad] the slope noise from the curl (projected_noise), or 0 */
    swfs_recon *rin;
    swfs_pipeline *p;
    swfs_cplx *halo;
    swfs_real *resmean; /* the reconstructed residual's time mean (PUPN x PUPN) [m] */
    swfs_real *slopes;
    swfs_lag_stacker_ stk; /* a space-time reconstructor's input, piece by piece of the file in memory */
    long lags[SWFS_RECON_MAXLAGS]; /* a space-time map's (the reconstructor's, or the linear */
    size_t nlags;                  /* model's control matrix's): its input stacked; 0: per frame */
    swfs_exposure *sched;
    size_t *cfirst, *cn;
    char tdir[4096], path[8192], loaded[8192];
} work;

static void work_free(work *w)
{
    swfs_timing_free(w->t);
    free(w->xy); free(w->mask); free(w->train); free(w->sched); free(w->cfirst); free(w->cn);
    swfs_recon_free(w->rin);
    swfs_pipeline_free(w->p);
    swfs_cplx_free(w->halo);
    swfs_real_free(w->resmean);
    swfs_real_free(w->slopes);
    swfs_lag_stacker_free_(&w->stk);
}

/* Science geometry and window, the actuators, the pupil mask. */
static int load_inputs(const swfs_speckles_run_options *o, work *w)
{
    swfs_fits_in *fs = NULL;
    int rc = swfs_timing_read(o->timing, &w->t);
    if (!rc) rc = swfs_fits_in_open(&fs, o->science, NULL);
    if (!rc) rc = swfs_fits_in_geom(fs, &w->g);
    if (!rc) swfs_geom_overlay(&w->g, &o->geom);
    if (!rc) rc = swfs_geom_require(&w->g, o->science);
    if (!rc) rc = swfs_science_tiptilt_check(fs, o->science, o->pipe.tiptilt);
    if (!rc) {
        const swfs_fits_shape *ss = swfs_fits_in_shape(fs);
        w->nfx = ss->nx;
        w->nfy = ss->ny;
        w->nsci = ss->nz;
    }
    swfs_fits_in_close(fs);
    /* The camera's orientation (sync's pairing) must be one the --match copies can undo. */
    if (!rc) rc = swfs_orient_check(&w->t->fit, w->nfx, w->nfy, o->timing);
    if (!rc && !o->lin.basis) rc = swfs_actuators_read(o->actuators, &w->xy, &w->nact);
    if (rc || !o->mask) return rc;
    const size_t npup = (size_t)w->g.pupn;
    swfs_real *pm = NULL;
    if ((rc = swfs_pupil_mask_read(o->mask, npup, &pm))) return rc;
    if (!(w->mask = malloc(npup * npup * sizeof *w->mask))) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->timing);
    if (!rc) memcpy(w->mask, pm->data, npup * npup * sizeof *w->mask);
    swfs_real_free(pm);
    return rc;
}

/* Every input (also the telemetry files the timing table names) and output, checked
 * before the work (outpaths.h). */
static int check_paths(const swfs_speckles_run_options *o, const work *w)
{
    swfs_paths *p = NULL;
    char path[8192];
    int rc = swfs_paths_create(&p);
    swfs_paths_input(p, "timing table", o->timing);
    swfs_paths_input(p, "science cube", o->science);
    swfs_paths_input(p, "actuator file", o->actuators);
    if (o->valid) swfs_paths_input(p, "valid-subaperture map", o->valid);
    swfs_linear_paths(p, &o->lin);
    if (o->pipe.recon == SWFS_RECON_GIVEN) swfs_paths_input(p, "reconstructor", o->recon);
    swfs_paths_input(p, "pupil mask", o->mask);
    for (size_t k = 0; k < o->nmatch; k++) swfs_paths_input(p, "--match input", o->match_in[k]);
    for (size_t c = 0; !rc && c < w->t->ncubes; c++)
        if (!(rc = swfs_telemetry_path(w->tdir, w->t->cubes[c].slopes, path, sizeof path)))
            rc = swfs_paths_input(p, "telemetry file named by the timing table", path);
    swfs_paths_output(p, "output speckle cube", o->out);
    swfs_paths_output(p, "reconstructor output", o->write_recon);
    for (size_t k = 0; k < o->nmatch; k++) swfs_paths_output(p, "--match output", o->match_out[k]);
    if (!rc) rc = swfs_paths_status(p);
    swfs_paths_free(p);
    return rc;
}

/* Usable cubes and their place in the output: their camera frames, or at the WFS rate
 * the WFS frames their exposures cover (floor(START) .. end of the last exposure). */
static int plan_cubes(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r)
{
    const swfs_timing *t = w->t;
    w->cfirst = calloc(t->ncubes, sizeof *w->cfirst);
    w->cn = calloc(t->ncubes, sizeof *w->cn);
    if (!w->cfirst || !w->cn) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->timing);
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->first + tc->nframes > w->nsci)
            return swfs_fail(SWFS_ERR_SHAPE, "%s: cube %zu (frames %zu..%zu) is beyond the %zu frames of %s", o->timing, c,
                             tc->first, tc->first + tc->nframes, w->nsci, o->science);
        if (tc->status == SWFS_CUBE_OK && tc->nframes > w->maxn) w->maxn = tc->nframes;
    }
    if (!w->maxn) return swfs_fail(SWFS_ERR_VALUE, "%s: no usable cube (all straddle telemetry files)", o->timing);
    if (!(w->sched = malloc(w->maxn * sizeof *w->sched))) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->timing);
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        size_t need = tc->start >= 0 ? swfs_engine_schedule(t->ratio, tc->start - floor(tc->start), tc->nframes, w->sched) : 0;
        if (!need)
            return swfs_fail(SWFS_ERR_VALUE, "%s: cube %zu starts at WFS frame %g with ratio %g; expected a start >= 0 "
                             "and a ratio >= %g WFS frames per camera frame", o->timing, c, tc->start, t->ratio,
                             SWFS_ENGINE_MIN_RATIO);
        /* the cube's telemetry file holds those frames (its header read): checked here, before
         * anything is taught or built for the run, as process_cubes checks each piece */
        char path[4200];
        size_t nfr = 0;
        int rc = swfs_telemetry_path(w->tdir, tc->slopes, path, sizeof path);
        if (!rc) rc = swfs_telemetry_check(path, 0, &nfr);
        if (rc) return rc;
        if ((size_t)floor(tc->start) + need > nfr)
            return swfs_fail(SWFS_ERR_VALUE, "%s: cube %zu needs WFS frames %.2f..%.2f but %s has %zu", o->timing, c,
                             tc->start, tc->start + (double)tc->nframes * t->ratio, path, nfr);
        w->cfirst[r->nok] = r->nout;
        w->cn[r->nok] = o->pipe.wfs_rate ? need : tc->nframes;
        r->nout += w->cn[r->nok];
        r->nok++;
    }
    return SWFS_OK;
}

/* One WFS rate per run: a telemetry file's WFSRATE (0: none) against the rate in use. */
static int check_rate(const char *path, double rate, double wfs_hz)
{
    if (rate > 0 && fabs(rate - wfs_hz) > 1e-9 * wfs_hz)
        return swfs_fail(SWFS_ERR_VALUE, "%s: WFSRATE %g Hz but the WFS rate in use is %g Hz; one rate per run", path,
                         rate, wfs_hz);
    return SWFS_OK;
}

/* The slopes length and, at the WFS rate, the rate: from the first usable cube's file,
 * which stays loaded for the first cube. */
static int peek_telemetry(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r)
{
    const swfs_timing *t = w->t;
    int rc = SWFS_OK;
    for (size_t c = 0; c < t->ncubes; c++)
        if (t->cubes[c].status == SWFS_CUBE_OK) {
            rc = swfs_telemetry_path(w->tdir, t->cubes[c].slopes, w->path, sizeof w->path);
            break;
        }
    double rate = 0;
    if (!rc) rc = swfs_telemetry_read(w->path, 0, &w->slopes, &rate);
    if (!rc && !o->lin.basis) rc = swfs_telemetry_check_sh(w->path, "speckles' default model (--actuators)");
    if (rc) return rc;
    w->nslopes = w->slopes->nx;
    snprintf(w->loaded, sizeof w->loaded, "%s", w->path);
    /* slopes modal-slopes --imat made: its check of how the coefficients were made (modal_lsq
     * NAN from the run's start where they carry none) */
    if (!o->lin.basis) {
        swfs_fits_in *f = NULL;
        long rgw = 0;
        int found = 0, lfound = 0;
        rc = swfs_fits_in_open(&f, w->path, NULL);
        if (!rc) rc = swfs_fits_in_key_long_opt(f, "MODALRGW", 0, 1, &rgw, &found);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, "MODALLSQ", &r->modal_lsq, &lfound);
        swfs_fits_in_close(f);
        if (rc) return rc;
        if (!lfound) r->modal_lsq = NAN;
        r->modal_regularized = found && rgw == 1;
    }
    if (!o->pipe.wfs_rate) return SWFS_OK;
    r->wfs_hz = o->wfs_hz > 0 ? o->wfs_hz : rate;
    if (!(r->wfs_hz > 0))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: no WFSRATE keyword; the WFS-rate speckles need the WFS frame rate: give "
                         "it", w->path);
    return check_rate(w->path, rate, r->wfs_hz);
}

/* --write-recon: the Shack-Hartmann model's reconstructor, or the linear model's reconstructor
 * of its interaction matrix, the map to its coefficients (what --control reads back). */
static int write_map(const swfs_speckles_run_options *o, const swfs_pipeline *p)
{
    const swfs_recon *r = swfs_pipeline_recon(p);
    if (r) return swfs_recon_write(r, o->write_recon);
    if (!(r = swfs_pipeline_linear_map(p)))
        return swfs_fail(SWFS_ERR_ARG, "speckles: no map from the telemetry to write (--write-recon %s)", o->write_recon);
    swfs_fits_out *f = NULL;
    int rc = swfs_fits_out_create(&f, o->write_recon);
    if (rc) return rc;
    rc = swfs_recon_write_hdu(f, r);
    if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "", "basis coefficient per telemetry value");
    if (!rc) rc = swfs_fits_out_key_string(f, "RECON", o->pipe.recon == SWFS_RECON_SVD ? "SVD" : "MAP",
                                           "of the interaction matrix (--imat)");
    if (!rc) rc = swfs_fits_out_key_long(f, "NMODES", (long)r->nmodes, "modes of the interaction matrix");
    if (!rc) rc = swfs_fits_out_history(f, "specklewfs linear model's map: coefficients = W values, NAXIS1 = telemetry "
                                        "values, NAXIS2 = basis functions (speckles --basis B --control this)");
    if (rc) {
        swfs_fits_out_abort(f);
        return rc;
    }
    return swfs_fits_out_commit(f);
}

/* The generic linear model: every usable cube's telemetry trains the interaction matrix's
 * MAP reconstructor and the check of the residual's size. */
static int build_linear(const swfs_speckles_run_options *o, work *w)
{
    int rc = swfs_telemetry_load_training(w->tdir, w->t, w->nslopes, &w->train, &w->ntrain);
    if (!rc) rc = swfs_linear_pipeline(&w->p, &o->lin, &w->g, w->nfx, w->nfy, w->mask, w->nslopes, w->train, w->ntrain,
                                       &o->pipe);
    if (!rc) rc = swfs_linear_control_lags(&o->lin, w->lags, &w->nlags);
    if (rc) return swfs_fail_context(rc, "with %s", w->path);
    free(w->train);
    w->train = NULL;
    if (o->write_recon && !swfs_team_active(o->team)) rc = write_map(o, w->p);
    return rc;
}

int swfs_sh_pipeline(swfs_pipeline **p, const char *model, const char *valid, const char *telemetry, const swfs_geom *g,
                     size_t nfx, size_t nfy, const double *xy, size_t nact, const double *mask, size_t nslopes,
                     const swfs_recon *recon, const double *train, size_t ntrain, const swfs_pipeline_options *po)
{
    *p = NULL;
    swfs_pipeline_options o = *po;
    unsigned char *map = NULL;
    size_t nvalid = 0;
    int rc = telemetry && telemetry[0] ? swfs_telemetry_check_sh(telemetry, "the Shack-Hartmann model") : SWFS_OK;
    if (rc) return rc;
    if (valid && (rc = swfs_valid_map_read(valid, &map, &o.valid_nsub, &nvalid)))
        return swfs_fail_context(rc, "the valid-subaperture map %s", valid);
    if (map) o.valid = map;
    rc = swfs_pipeline_create(p, g, nfx, nfy, xy, nact, mask, nslopes, recon, train, ntrain, &o);
    free(map);
    /* The pipeline's own failure (a reconstructor's or a valid map's width against the
     * telemetry) names its cause; the context names the inputs it was built from, blaming none. */
    if (rc && valid) return swfs_fail_context(rc, "%s%sthe valid-subaperture map %s", model ? model : "",
                                              model ? " and " : "", valid);
    if (rc) return model ? swfs_fail_context(rc, "%s", model) : rc;
    swfs_pipeline_info in;
    swfs_pipeline_get_info(*p, &in);
    if (telemetry && telemetry[0] && (rc = swfs_telemetry_check_nsub(telemetry, in.nsub))) {
        swfs_pipeline_free(*p);
        *p = NULL;
    }
    return rc;
}

/* *learned: the reconstructor file says learn or teach made it (RECON = 'learned'). */
static int learned_map(const char *path, int *learned)
{
    swfs_fits_in *f = NULL;
    char kind[72] = "";
    int found = 0, rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_string_opt(f, "RECON", kind, sizeof kind, &found);
    swfs_fits_in_close(f);
    *learned = !rc && found && !strcmp(kind, "learned");
    return rc;
}

/* Slopes modal-slopes made (their first file names the control matrix: MODALCM) lie in the
 * span of its modes: the vk and MAP maps' noise estimate, the slopes' power outside the
 * model's span (white noise and aliasing: the "effective" noise), finds next to nothing there
 * (on cli_modal's data a map without noise, 297 nm). The same power is their curl's, which the
 * projection keeps (swfs_slopes_curl_noise, total), over the training frames; *rms stays 0
 * for any other telemetry. */
static int projected_noise(const swfs_speckles_run_options *o, work *w, double *rms)
{
    *rms = 0;
    swfs_fits_in *f = NULL;
    char name[4096];
    int found = 0, rc = swfs_fits_in_open(&f, w->path, NULL);
    if (!rc) rc = swfs_fits_in_key_string_opt(f, "MODALCM", name, sizeof name, &found);
    swfs_fits_in_close(f);
    if (rc || !found) return rc;
    unsigned char *vm = NULL;
    size_t nsub = 0, nv = 0;
    if (o->valid) rc = swfs_valid_map_read(o->valid, &vm, &nsub, &nv);
    else nsub = (size_t)llround(sqrt(0.5 * (double)w->nslopes));
    double var = 0, white = 0;
    if (!rc && (o->valid ? w->nslopes == 2 * nv : w->nslopes == 2 * nsub * nsub))
        rc = swfs_slopes_curl_noise(w->train, w->ntrain, w->nslopes, nsub, vm, &white, &var);
    free(vm);
    if (rc) return swfs_fail_context(rc, "%s: the curl power of slopes made by modal-slopes (MODALCM = '%s')", w->path, name);
    *rms = w->curl_noise = sqrt(var);
    return SWFS_OK;
}

static int build_pipeline(const swfs_speckles_run_options *o, work *w)
{
    if (o->lin.basis) return build_linear(o, w);
    int rc = SWFS_OK;
    if (o->pipe.recon == SWFS_RECON_GIVEN) {
        if ((rc = swfs_recon_read(o->recon, &w->rin))) return rc;
        /* With a valid map the telemetry may hold the used subapertures only and the
         * reconstructor the full layout of the map's nsub (e.g. learned on simulations). */
        const size_t nl = w->rin->nlags ? w->rin->nlags : 1, per = w->rin->nslopes / nl;
        w->nlags = w->rin->nlags > 1 ? w->rin->nlags : 0;
        memcpy(w->lags, w->rin->lags, sizeof w->lags);
        size_t vn = 0, vv = 0;
        unsigned char *vm = NULL;
        if (per != w->nslopes && o->valid && (rc = swfs_valid_map_read(o->valid, &vm, &vn, &vv))) return rc;
        free(vm);
        if (per != w->nslopes && !(o->valid && per == 2 * vn * vn))
            return swfs_fail(SWFS_ERR_SHAPE, "%s: %zu slopes per frame but the reconstructor %s expects %zu%s", w->path,
                             w->nslopes, o->recon, per, o->valid ? " (nor is it the full layout of the valid map's "
                                                                   "subapertures)" : "");
    }
    swfs_pipeline_options po = o->pipe;
    if (o->pipe.recon == SWFS_RECON_VK || o->pipe.recon == SWFS_RECON_MAP) {
        rc = swfs_telemetry_load_training(w->tdir, w->t, w->nslopes, &w->train, &w->ntrain);
        if (!rc && !(po.slope_noise > 0)) rc = projected_noise(o, w, &po.slope_noise);
    }
    char model[8400];
    snprintf(model, sizeof model, "%s with %s", o->actuators, w->path);
    if (!rc) rc = swfs_sh_pipeline(&w->p, model, o->valid, w->path, &w->g, w->nfx, w->nfy, w->xy, w->nact, w->mask,
                                   w->nslopes, w->rin, w->train, w->ntrain, &po);
    if (rc) return rc;
    swfs_pipeline_info pinfo;
    swfs_pipeline_get_info(w->p, &pinfo);
    /* A given matrix in another convention (DM commands: a correction of the surface, about
     * -1/2; slopes in other units) would give speckles of the wrong sign or size: refused.
     * Not a space-time map that learn or teach made: its gain is its lag blocks' sum on a
     * wavefront held still over the lags, which frozen flow never is, and a map learned from
     * slopes of little noise spreads its response over the lags (2.03 on a bright star's
     * 14 x 14 Shack-Hartmann, 0.496 at 1e-8 rad: docs/telemetry.md); its units are the
     * library's by construction, so only a sign (a scale given to it) is refused. */
    const double gain = pinfo.recon_gain;
    int learned_st = 0;
    if (o->pipe.recon == SWFS_RECON_GIVEN && w->nlags > 1 && (rc = learned_map(o->recon, &learned_st))) return rc;
    const int in_range = learned_st ? gain > 0 : gain >= SWFS_RECON_GAIN_MIN && gain <= 1.0 / SWFS_RECON_GAIN_MIN;
    if (o->pipe.recon == SWFS_RECON_GIVEN && !in_range)
        return swfs_fail(SWFS_ERR_VALUE, "%s: gain %.3g on the model's interaction matrix%s (expected about 1: the "
                         "residual wavefront [m of OPD] at the actuators = W slopes [rad]); a matrix to DM commands is a "
                         "correction of the surface (about -0.5), slopes in other units scale it; a scale of %.3g "
                         "(--recon-scale) would make it 1", o->recon, gain,
                         o->pipe.recon_scale != 1.0 ? " after the scale given" : "",
                         gain != 0.0 ? o->pipe.recon_scale / gain : 0.0);
    free(w->train);
    w->train = NULL;
    /* (a team writes it with the other products, once every member has succeeded) */
    if (o->write_recon && !swfs_team_active(o->team)) rc = write_map(o, w->p);
    return rc;
}

/* Make cube c's telemetry file the one in memory (checked against the first one's shape and rate). */
static int load_cube_slopes(const swfs_speckles_run_options *o, work *w, const swfs_timing_cube *tc, double wfs_hz)
{
    int rc = swfs_telemetry_path(w->tdir, tc->slopes, w->path, sizeof w->path);
    if (!rc && strcmp(w->loaded, w->path)) {
        swfs_real_free(w->slopes);
        w->slopes = NULL;
        w->loaded[0] = 0;
        double r;
        if ((rc = swfs_telemetry_read(w->path, w->nslopes, &w->slopes, &r))) return rc;
        snprintf(w->loaded, sizeof w->loaded, "%s", w->path);
        rc = o->pipe.wfs_rate ? check_rate(w->path, r, wfs_hz) : SWFS_OK;
    }
    return rc;
}

/* A space-time reconstructor's checks against the observation (run_stcheck.c): the first
 * usable cube's telemetry file against what the map's file says of its training loops. */
static int spacetime_check(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r)
{
    if (!w->rin || w->rin->nlags < 2) return swfs_spacetime_check_(NULL, NULL, 0, NULL, 0, 0, 0, NULL, r);
    const swfs_timing_cube *tc = NULL;
    for (size_t c = 0; c < w->t->ncubes && !tc; c++)
        if (w->t->cubes[c].status == SWFS_CUBE_OK) tc = w->t->cubes + c;
    int rc = tc ? load_cube_slopes(o, w, tc, r->wfs_hz) : SWFS_OK;
    if (rc) return rc;
    swfs_pipeline_info in;
    swfs_pipeline_get_info(w->p, &in);
    return swfs_spacetime_check_(o->recon, w->rin->lags, w->rin->nlags, tc ? w->slopes->data : NULL,
                                 tc ? w->slopes->ny : 0, w->nslopes, in.nsub, o->valid, r);
}

/* The output frames [first, first + count) (all of them alone; a member's share in a team)
 * through the pipeline, into w->halo, whose frame 0 is output frame `first`. A cube goes in
 * pieces of `batch` frames from its start (a share starts on a piece): a piece from camera
 * frame j starts at WFS frame START + j ratio, as the stream's file source schedules it (at
 * the WFS rate: WFS frame floor(START) + j). */
static int process_cubes(const swfs_speckles_run_options *o, work *w, const swfs_speckles_run_result *r, size_t first,
                         size_t count)
{
    const swfs_timing *t = w->t;
    const size_t P = piece(o);
    size_t ok_i = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        const size_t c0 = w->cfirst[ok_i], c1 = c0 + w->cn[ok_i];
        ok_i++;
        const size_t lo = c0 > first ? c0 : first, hi = c1 < first + count ? c1 : first + count;
        if (lo >= hi) continue;
        int rc = load_cube_slopes(o, w, tc, r->wfs_hz);
        if (rc) return rc;
        for (size_t a = lo - c0; a < hi - c0; a += P) {
            const size_t n = hi - c0 - a < P ? hi - c0 - a : P;
            const double t0 = o->pipe.wfs_rate ? floor(tc->start) + (double)a : tc->start + (double)a * t->ratio;
            const double k0 = floor(t0);
            const size_t need = o->pipe.wfs_rate ? n : swfs_engine_schedule(t->ratio, t0 - k0, n, w->sched);
            if (!(tc->start >= 0) || need == 0 || (size_t)k0 + need > w->slopes->ny)
                return swfs_fail(SWFS_ERR_VALUE, "%s: cube %zu needs WFS frames %.2f..%.2f but %s has %zu", o->timing, c,
                                 tc->start, tc->start + (double)tc->nframes * t->ratio, w->path, w->slopes->ny);
            const double *sp = w->slopes->data + (size_t)k0 * w->nslopes;
            /* a space-time reconstructor: the lags run on into contiguous neighbour files */
            if (w->nlags > 1 && (rc = swfs_lag_stacker_rows_(&w->stk, w->tdir, t, tc->slopes, w->path, w->slopes,
                                                              w->lags, w->nlags, (size_t)k0, need, &sp)))
                return rc;
            swfs_complex *dst = swfs_cplx_frame(w->halo, c0 + a - first);
            rc = o->pipe.wfs_rate ? swfs_pipeline_process_wfs(w->p, sp, n, dst)
                                  : swfs_pipeline_process(w->p, sp, need, w->sched, n, dst);
            if (rc) return swfs_fail_context(rc, "%s cube %zu", w->path, c);
        }
        if ((rc = swfs_progress_report(o->progress, o->progress_ctx, "cubes", ok_i, r->nok))) return rc;
    }
    return SWFS_OK;
}

/* A team: this member's output frames, processed into a buffer of their own (member 0's
 * at the start of the whole cube), then gathered in rank order into member 0's cube. */
static int process_team(const swfs_speckles_run_options *o, work *w, const swfs_speckles_run_result *r, int rc)
{
    const swfs_team *t = o->team;
    const size_t nf2 = w->nfx * w->nfy;
    size_t *counts = calloc((size_t)t->size, sizeof *counts), first = 0, count = 0;
    if (!rc && !counts) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (int k = 0; !rc && k < t->size; k++) {
        size_t f, n;
        swfs_team_share(w->cn, r->nok, piece(o), k, t->size, &f, &n);
        counts[k] = n * nf2 * sizeof(swfs_complex);
        if (k == t->rank) { first = f; count = n; }
    }
    /* A missing or truncated telemetry file of any share stops every member before the work. */
    size_t ok_i = 0;
    for (size_t c = 0; !rc && c < w->t->ncubes; c++) {
        const swfs_timing_cube *tc = w->t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        const size_t c0 = w->cfirst[ok_i], c1 = c0 + w->cn[ok_i++];
        if (c1 > first && c0 < first + count && !(rc = swfs_telemetry_path(w->tdir, tc->slopes, w->path, sizeof w->path)))
            rc = swfs_telemetry_check(w->path, w->nslopes, NULL);
    }
    rc = swfs_team_agree(t, rc);
    if (!rc && !(w->halo = swfs_cplx_alloc(w->nfx, w->nfy, t->rank ? (count ? count : 1) : r->nout)))
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory for %zu frames of %zux%zu", t->rank ? count : r->nout, w->nfx, w->nfy);
    if (!rc) rc = process_cubes(o, w, r, first, count);
    rc = swfs_team_agree(t, rc);
    if (!rc) rc = t->gather(t->ctx, w->halo->data, counts[t->rank], t->rank ? NULL : w->halo->data, t->rank ? NULL : counts);
    free(counts);
    return rc;
}

/* The reconstructed residual's time mean over every frame written (a team's members add
 * their sums first): the static aberration of the science frames that the telemetry measures
 * (swfs_pipeline_mean_wavefront), written beside the speckles for `pupil` to take out. */
static int residual_mean(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r)
{
    const size_t n = (size_t)w->g.pupn;
    int rc = swfs_team_sum_pipeline_mean(o->team, w->p);
    if (rc) return rc;
    if (!(w->resmean = swfs_real_alloc(n, n, 1))) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    r->wavelen = w->g.wavelen;
    if (o->mean_rec_out) { /* its own reconstruction, for loops_map's misses */
        swfs_real *rec = swfs_real_alloc(n, n, 1);
        swfs_fits_out *f = NULL;
        rc = rec ? swfs_pipeline_mean_reconstruction(w->p, rec->data) : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        if (!rc) rc = swfs_fits_out_create(&f, o->mean_rec_out);
        if (!rc) rc = swfs_fits_out_real(f, "RESMEAN", rec, -64);
        if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "m", "the run's own reconstruction of the residual's mean");
        if (f && rc) swfs_fits_out_abort(f);
        else if (f) rc = swfs_fits_out_commit(f);
        swfs_real_free(rec);
        if (rc) return rc;
    }
    if (!o->resmean_from) return swfs_pipeline_mean_wavefront(w->p, w->resmean->data, NULL, &r->resmean_rms);
    /* another run's mean of the same frames (loops_map: the interaction matrix's, corrected) */
    swfs_real *m = NULL;
    rc = swfs_fits_read_real(o->resmean_from, "RESMEAN", &m, NULL);
    if (!rc && (m->nx != n || m->ny != n || m->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: RESMEAN is %zu x %zu x %zu; expected the pupil grid, %zu x %zu",
                       o->resmean_from, m->nx, m->ny, m->nz, n, n);
    double *tmp = rc ? NULL : malloc(n * n * sizeof *tmp);
    if (!rc && !tmp) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) {
        memcpy(w->resmean->data, m->data, n * n * sizeof *tmp);
        memcpy(tmp, m->data, n * n * sizeof *tmp);
        r->resmean_rms = swfs_wfe_remove_ptt(tmp, swfs_pipeline_mask(w->p), n);
    }
    free(tmp);
    swfs_real_free(m);
    return rc;
}

/* OUT = the frames of IN (a cube aligned with the science cube) of the usable cubes, with
 * the noise keywords, so it matches the speckle cube frame for frame, and brought into the
 * model's orientation when sync found the camera flipped or transposed (CAMORIEN). */
static int write_match(const char *in, const char *out, const work *w, const double *shx, const double *shy,
                       const char *const *prov, size_t nprov)
{
    swfs_fits_in *f = NULL;
    swfs_fits_out *fo = NULL;
    double *buf = NULL;
    int rc = swfs_fits_in_open(&f, in, NULL);
    if (rc) return rc;
    const swfs_fits_shape *s = swfs_fits_in_shape(f);
    size_t nout = 0, np = s->nx * s->ny;
    const size_t comps = s->is_complex ? 2 : 1;
    const int turn = !swfs_orient_is_identity(&w->t->fit);
    for (size_t c = 0; c < w->t->ncubes; c++)
        if (w->t->cubes[c].status == SWFS_CUBE_OK) nout += w->t->cubes[c].nframes;
    if (s->nz != w->nsci)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu frames but the science cube has %zu; a matched copy needs a cube aligned "
                       "with it", in, s->nz, w->nsci);
    else if (turn && (s->nx != w->nfx || s->ny != w->nfy))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: frames of %zux%zu but the science cube's are %zux%zu; a matched copy is "
                       "re-oriented like the science frames", in, s->nx, s->ny, w->nfx, w->nfy);
    else if (!(buf = malloc(2 * np * comps * sizeof *buf))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = swfs_fits_out_create(&fo, out);
    if (!rc) rc = swfs_fits_out_set_stamp(fo, &w->g, prov, nprov);
    if (!rc) rc = swfs_fits_out_begin(fo, NULL, s->nx, s->ny, nout, s->is_complex, -32);
    if (!rc && turn) {
        char d[64];
        swfs_orient_describe(&w->t->fit, d, sizeof d);
        rc = swfs_fits_out_key_string(fo, "CAMORIEN", d, "camera frames turned into the model's orientation");
    }
    const char *keys[] = {"RDNOISE", "GAIN", "NOISEVAR"};
    for (size_t k = 0; !rc && k < 3; k++) {
        double v;
        int found = 0;
        rc = swfs_fits_in_key_double_opt(f, keys[k], &v, &found);
        if (!rc && found) rc = swfs_fits_out_key_double(fo, keys[k], v, "copied from the input");
    }
    for (size_t c = 0, k = 0; !rc && c < w->t->ncubes; c++) {
        if (w->t->cubes[c].status != SWFS_CUBE_OK) continue;
        for (size_t j = 0; !rc && j < w->t->cubes[c].nframes; j++, k++) {
            size_t src = w->t->cubes[c].first + j;
            double *rd = turn ? buf + np * comps : buf;
            rc = s->is_complex ? swfs_fits_in_read_cplx(f, src, 1, (swfs_complex *)rd) : swfs_fits_in_read_real(f, src, 1, rd);
            if (!rc && shx && !s->is_complex) { /* re-centred on the slopes' tilt (--tiptilt frame) */
                double *tmp = turn ? buf : buf + np;
                swfs_shift_bilinear(rd, s->nx, s->ny, -shx[k], -shy[k], tmp);
                memcpy(rd, tmp, np * sizeof *rd);
            }
            if (!rc && turn) swfs_orient_frame(&w->t->fit, s->nx, s->ny, comps, rd, buf);
            if (!rc) rc = s->is_complex ? swfs_fits_out_cplx_frames(fo, k, 1, (swfs_complex *)buf)
                                        : swfs_fits_out_real_frames(fo, k, 1, buf);
        }
    }
    if (!rc) {
        rc = swfs_fits_out_commit(fo);
        fo = NULL;
    }
    swfs_fits_out_abort(fo);
    swfs_fits_in_close(f);
    free(buf);
    return rc;
}

int swfs_speckles_orient_warns(const swfs_speckles_run_result *r)
{
    const swfs_orient_check_result *c = &r->orient;
    return r->orient_done && c->best != c->ref && c->diff > SWFS_ORIENT_WARN_SE * c->diff_se;
}

void swfs_speckles_orient_warning(const swfs_speckles_run_result *r, char *buf, size_t cap)
{
    if (cap) buf[0] = '\0';
    if (!swfs_speckles_orient_warns(r)) return;
    swfs_sync_result pb;
    swfs_orient_pairing(r->orient.best, &pb);
    if (r->orient_adopted)
        snprintf(buf, cap, "the science frames follow the speckles in another orientation than the timing table's "
                 "pairing (the star's track can pair the axes wrongly where a vibration moves them alike): the speckle "
                 "cube and the --match copies take the speckles' pairing; replay and stream take the table's, so set "
                 "the first three numbers of its 'pairing' line to '%d %d %d' for them (docs/telemetry.md, \"The "
                 "camera's orientation\")", pb.swap, pb.sign_x, pb.sign_y);
    else
        snprintf(buf, cap, "the science frames follow the speckles in another orientation than the timing table's "
                 "pairing, which was kept (--pairing table): the star's track can pair the axes wrongly where a "
                 "vibration moves them alike; if the camera is oriented so, set the first three numbers of the table's "
                 "'pairing' line to '%d %d %d' or run speckles without --pairing table (docs/telemetry.md, \"The "
                 "camera's orientation\")", pb.swap, pb.sign_x, pb.sign_y);
}

/* The camera's orientation from the speckles (sync.h swfs_orient_acc): the science frames of
 * the usable cubes, as read, against |psi|^2 of the speckle cube (w->halo, in the model's
 * frame), once before the products are written. Too few frames or nothing that varies: not
 * run, no error. */
static int orient_check(const swfs_speckles_run_options *o, const work *w, swfs_speckles_run_result *r, double *pix,
                        int pair)
{
    swfs_fits_in *f = NULL;
    swfs_orient_acc *a = NULL;
    double *cam = NULL, *p2 = NULL;
    const size_t np = w->nfx * w->nfy;
    int rc = swfs_fits_in_open(&f, o->science, NULL);
    if (!rc) rc = swfs_orient_acc_new(w->nfx, w->nfy, &a);
    if (!rc && (!(cam = malloc(np * sizeof *cam)) || !(p2 = malloc(np * sizeof *p2))))
        rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t c = 0, k = 0; !rc && c < w->t->ncubes; c++) {
        if (w->t->cubes[c].status != SWFS_CUBE_OK) continue;
        for (size_t j = 0; !rc && j < w->t->cubes[c].nframes && k < w->halo->nz; j++, k++) {
            rc = swfs_fits_in_read_real(f, w->t->cubes[c].first + j, 1, cam);
            const swfs_complex *h = swfs_cplx_frame(w->halo, k);
            for (size_t q = 0; !rc && q < np; q++) p2[q] = creal(h[q]) * creal(h[q]) + cimag(h[q]) * cimag(h[q]);
            if (!rc) swfs_orient_acc_add(a, cam, p2);
        }
    }
    const double pps = w->g.pixscale > 0 ? 1.0 / (w->g.pixscale * w->g.pixscale) : 1.0;
    if (!rc) {
        rc = swfs_orient_acc_result(a, &w->t->fit, pps, &r->orient);
        r->orient_done = rc == SWFS_OK;
        if (pix) swfs_orient_acc_pixel_corrs(a, pair >= 0 ? pair : r->orient.best, pix);
        if (rc == SWFS_ERR_VALUE) { /* nothing to tell it by: not run */
            swfs_clear_error();
            rc = SWFS_OK;
        }
    }
    swfs_orient_acc_free(a);
    swfs_fits_in_close(f);
    free(cam);
    free(p2);
    return rc;
}

/* The camera's orientation on the speckle cube: the science frames it goes with must have
 * been turned the same way (--match does it; estimate checks). */
static int speckles_orient_key(swfs_fits_out *f, const work *w)
{
    char d[64];
    swfs_orient_describe(&w->t->fit, d, sizeof d);
    return swfs_fits_out_key_string(f, "CAMORIEN", d, "the science camera's orientation (sync)");
}

/* The linear model the speckles were computed with (the report draws its registration). */
static int linear_keys(swfs_fits_out *f, const swfs_linear_files *lf)
{
    char abs[PATH_MAX];
    const char *b = realpath(lf->basis, abs) ? abs : lf->basis;
    int rc = swfs_fits_out_key_string(f, "BASIS", b, "the linear model's basis (--basis)");
    if (!rc) rc = swfs_fits_out_key_double(f, "COEFSCL", lf->scale, "[m] of wavefront per unit basis x coefficient");
    if (!rc && lf->reg.pitch > 0) {
        if (!(rc = swfs_fits_out_key_double(f, "DMPITCH", lf->reg.pitch, "[m] on the pupil per DM-grid step")) &&
            !(rc = swfs_fits_out_key_double(f, "DMOFFX", lf->reg.x0, "[m] DM-grid centre on the pupil")) &&
            !(rc = swfs_fits_out_key_double(f, "DMOFFY", lf->reg.y0, "[m] DM-grid centre on the pupil")) &&
            !(rc = swfs_fits_out_key_double(f, "DMROT", lf->reg.rot * 180 / M_PI, "[deg] counter-clockwise")))
            rc = swfs_fits_out_key_long(f, "DMFLIPX", lf->reg.flip_x, "DM-grid x mirrored before the rotation");
    }
    return rc;
}

static int write_speckles(const swfs_speckles_run_options *o, const work *w, const swfs_speckles_run_result *r,
                          const char *const *prov, size_t nprov)
{
    swfs_fits_out *f = NULL;
    int rc = swfs_fits_out_create(&f, o->out);
    if (rc) return rc;
    if ((rc = swfs_fits_out_set_stamp(f, &w->g, prov, nprov)) || (rc = swfs_fits_out_cplx(f, NULL, w->halo, -32)) ||
        (rc = swfs_fits_out_key_double(f, "FRATIO", w->t->ratio, "<t_sci/t_wfs> from sync")) ||
        (rc = swfs_fits_out_key_double(f, "HSLAG", w->t->lag, "handshake lag [WFS frames] from sync")) ||
        (rc = swfs_fits_out_key_double(f, "SPKBAND", r->info.band, "[lambda/D] speckles computed within (0: all)")) ||
        (rc = swfs_fits_out_key_string(f, "TIPTILT", swfs_tiptilt_name(o->pipe.tiptilt), "--tiptilt: tip-tilt treatment")) ||
        (!swfs_orient_is_identity(&w->t->fit) && (rc = speckles_orient_key(f, w))) ||
        (o->lin.basis && (rc = linear_keys(f, &o->lin))) ||
        (o->pipe.wfs_rate && ((rc = swfs_fits_out_key_double(f, "FRAMEDT", 1 / r->wfs_hz, "[s] between frames (WFS rate)")) ||
                              (rc = swfs_fits_out_key_double(f, "WFSRATE", r->wfs_hz, "[Hz]")) ||
                              (rc = swfs_fits_out_key_long(f, "NSEGS", (long)r->nok, "contiguous segments (usable cubes)")))) ||
        (w->resmean && ((rc = swfs_fits_out_real(f, "RESMEAN", w->resmean, -64)) ||
                        (rc = swfs_fits_out_key_string(f, "BUNIT", "m", "wavefront (OPD)")) ||
                        (rc = swfs_fits_out_key_double(f, "RESMRMS", r->resmean_rms,
                                                       "[m] rms of the residual's time mean (PTT removed)"))))) {
        swfs_fits_out_abort(f);
        return rc;
    }
    return swfs_fits_out_commit(f);
}

int swfs_speckles_resmean_warns(const swfs_speckles_run_result *r) { return r->resmean_rms > r->wavelen; }

/* The speckles of o's reconstructor into w (rc: the run's status so far, which a team's
 * members agree on): the pipeline, every usable frame, the residual's mean, the static part
 * out, and the camera's orientation by the speckles (before the products that depend on it:
 * a pairing that beats the table's by SWFS_ORIENT_WARN_SE standard errors is theirs unless
 * the table's is kept, pairing_table); pix (the window's pixels, or NULL): the check's
 * per-pixel correlations at pairing `pair` (< 0: the best it found). */
static int compute(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r, int rc, double *pix,
                   int pair)
{
    if (!rc) rc = build_pipeline(o, w);
    /* a learned map's own miss of the residual's mean (learn's MEANMISS), added to RESMEAN */
    const char *map = o->lin.basis ? o->lin.control : o->pipe.recon == SWFS_RECON_GIVEN ? o->recon : NULL;
    if (!rc) rc = swfs_map_meanmiss_attach(w->p, map, &o->lin, &w->g, &r->meanmiss_rms);
    if (!rc && o->nmean_loops)
        rc = swfs_pipeline_mean_loops(w->p, o->mean_loops, o->nmean_loops, &r->meanmiss_heldout, &r->meanmiss_rms);
    if (!rc) rc = spacetime_check(o, w, r);
    const int team = swfs_team_active(o->team), writer = swfs_team_writer(o->team);
    if (team) {
        rc = process_team(o, w, r, rc);
    } else {
        if (!rc && !(w->halo = swfs_cplx_alloc(w->nfx, w->nfy, r->nout)))
            rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory for %zu frames of %zux%zu", r->nout, w->nfx, w->nfy);
        if (!rc) rc = process_cubes(o, w, r, 0, r->nout);
    }
    r->st_edges_joined = w->stk.edges.joined;
    r->st_edges_clamped = w->stk.edges.clamped;
    r->st_edges_unreadable = w->stk.edges.unreadable;
    snprintf(r->st_edges_why, sizeof r->st_edges_why, "%s", w->stk.edges.why);
    if (!rc) rc = residual_mean(o, w, r);
    if (!rc && writer) rc = swfs_speckles_subtract_static(w->halo, w->cfirst, w->cn, r->nok, o->mean_mode);
    if (!rc && writer && !o->pipe.wfs_rate && w->halo) rc = orient_check(o, w, r, pix, pair);
    return rc;
}


/* speckles' second taught map, its loops' DM Gaussian functions (dm_choose). */
typedef struct dm_second {
    int taught;
    char map[4200];
    swfs_teach_run_result tr;
    char fpr[17];
    int reused;
} dm_second;

/* The second map taught before the products' group (teach's loops are their own groups), where
 * the choice is wanted: d->taught, or r->dm_fallback says why not. */
static int dm_teach(const swfs_speckles_run_options *o, const work *w, swfs_speckles_run_result *r, dm_second *d)
{
    r->dm_gauss_coupling = SWFS_TEACH_DM_GAUSS;
    r->dm_corr[0] = r->dm_corr[1] = r->dm_corr_diff = r->dm_corr_se = NAN;
    char why[sizeof r->dm_fallback - 40];
    const int rc = swfs_speckles_teach_dm_(o, w->t, w->tdir, &w->g, d->map, sizeof d->map, &d->tr, d->fpr, &d->reused,
                                           &d->taught, why, sizeof why);
    if (!rc && !d->taught) snprintf(r->dm_fallback, sizeof r->dm_fallback, "the second map could not be taught: %s", why);
    return rc;
}

/* What compute makes of one reconstructor, held aside while another's is computed. */
typedef struct made {
    swfs_recon *rin;
    swfs_pipeline *p;
    swfs_cplx *halo;
    swfs_real *resmean;
    swfs_lag_stacker_ stk;
    long lags[SWFS_RECON_MAXLAGS];
    size_t nlags;
} made;

static void made_swap(work *w, made *m)
{
    made t = {w->rin, w->p, w->halo, w->resmean, w->stk, {0}, w->nlags};
    memcpy(t.lags, w->lags, sizeof t.lags);
    w->rin = m->rin; w->p = m->p; w->halo = m->halo; w->resmean = m->resmean; w->stk = m->stk; w->nlags = m->nlags;
    memcpy(w->lags, m->lags, sizeof w->lags);
    *m = t;
}

static void made_free(made *m)
{
    swfs_recon_free(m->rin);
    swfs_pipeline_free(m->p);
    swfs_cplx_free(m->halo);
    swfs_real_free(m->resmean);
    swfs_lag_stacker_free_(&m->stk);
    memset(m, 0, sizeof *m);
}

/* The DM's functions of teach's loops, chosen by the science frames (run.h dm_choice_done):
 * w and r hold the first map's speckles (the interpolated surface's), pix its per-pixel
 * correlations; the second map's, of Gaussian functions, are computed, and kept in w and r,
 * with its teach result in o->teach, where their |psi|^2 follows the frames better by more
 * than SWFS_TEACH_DM_SE standard errors (the mean per-pixel difference at the pairing the
 * first check found). A
 * second map that cannot be taught or compared leaves the first (dm_fallback says why). */
static int dm_choose(const swfs_speckles_run_options *o, work *w, swfs_speckles_run_result *r, const double *pix,
                     const dm_second *d)
{
    const size_t np = w->nfx * w->nfy;
    /* (a team: member 0 holds the frames' correlations and decides; every member computes) */
    int can = r->orient_done;
    int rc = swfs_team_bcast0(o->team, &can, sizeof can);
    if (rc) return rc;
    if (!can) {
        snprintf(r->dm_fallback, sizeof r->dm_fallback, "the speckles' correlation with the frames could not be "
                 "measured (too few frames, or nothing varies)");
        return SWFS_OK;
    }
    swfs_speckles_run_result *r2 = malloc(sizeof *r2);
    double *pix2 = malloc(np * sizeof *pix2);
    made m1;
    memset(&m1, 0, sizeof m1);
    rc = r2 && pix2 ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (swfs_team_active(o->team)) rc = swfs_team_agree(o->team, rc);
    swfs_speckles_run_options o2 = *o;
    o2.recon = d->map;
    o2.write_recon = NULL; /* the kept one's, by the caller */
    if (!rc) {
        *r2 = *r;
        made_swap(w, &m1); /* the first's aside */
        rc = compute(&o2, w, r2, rc, pix2, r->orient.best); /* at the first's pairing */
        if (rc && rc != SWFS_ERR_STOPPED) { /* the first stands */
            snprintf(r->dm_fallback, sizeof r->dm_fallback, "the second map's speckles: %s", swfs_last_error());
            swfs_clear_error();
            rc = SWFS_OK;
            made_swap(w, &m1);
            goto done;
        }
    }
    int can2 = !rc && r2->orient_done;
    if (!rc) rc = swfs_team_bcast0(o->team, &can2, sizeof can2);
    if (!rc && !can2) {
        snprintf(r->dm_fallback, sizeof r->dm_fallback, "the second map's speckles' correlation with the frames "
                 "could not be measured");
        made_swap(w, &m1);
        goto done;
    }
    if (!rc) {
        const int k = r->orient.best;
        const double pps = w->g.pixscale > 0 ? 1.0 / (w->g.pixscale * w->g.pixscale) : 1.0;
        double m = NAN, se = NAN;
        const size_t n = swfs_team_writer(o->team) ? swfs_orient_corr_diff(pix, pix2, np, pps, &m, &se) : 0;
        const double c0 = r->orient.corr[k], c1 = r2->orient.corr[k];
        int gauss = n && m > SWFS_TEACH_DM_SE * se; /* (the surface unless the frames tell) */
        if ((rc = swfs_team_bcast0(o->team, &gauss, sizeof gauss))) goto done;
        if (gauss) { /* the second's: m1 (the first's) freed below */
            snprintf(r2->dm_other_map, sizeof r2->dm_other_map, "%s", r->teach_map);
            snprintf(r2->teach_map, sizeof r2->teach_map, "%s", d->map);
            snprintf(r2->teach_fingerprint, sizeof r2->teach_fingerprint, "%s", d->fpr);
            r2->teach_reused = d->reused;
            *r = *r2;
            if (o->teach) *o->teach = d->tr;
        } else {
            made_swap(w, &m1); /* the first's back; m1 the second's */
            snprintf(r->dm_other_map, sizeof r->dm_other_map, "%s", d->map);
        }
        r->dm_choice_done = n > 0; /* (member 0's: the others hold no correlations) */
        r->dm_gauss_chosen = gauss;
        r->dm_corr[0] = c0;
        r->dm_corr[1] = c1;
        r->dm_corr_diff = m;
        r->dm_corr_se = se;
        r->dm_npix = n;
        if (!n && swfs_team_writer(o->team))
            snprintf(r->dm_fallback, sizeof r->dm_fallback, "no pixel where both speckle cubes vary");
    }
done:
    made_free(&m1);
    free(r2);
    free(pix2);
    return rc;
}

int swfs_speckles_run(const swfs_speckles_run_options *o, swfs_speckles_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->modal_lsq = r->meanmiss_heldout = NAN;
    const int crc = swfs_speckles_run_options_check(o);
    if (crc) return crc;
    /* At the WFS rate there is no exposure to take a mean tip-tilt over: the coherence of
     * the speckles, not of the image motion, is what is measured; the default becomes the
     * tip-tilt removed per WFS frame. */
    swfs_speckles_run_options at_rate;
    if (o->pipe.wfs_rate && o->pipe.tiptilt == SWFS_TT_EXPOSURE) {
        at_rate = *o;
        at_rate.pipe.tiptilt = SWFS_TT_FRAME;
        o = &at_rate;
    }
    work w;
    memset(&w, 0, sizeof w);
    swfs_path_dir(o->timing, w.tdir, sizeof w.tdir);
    int rc = load_inputs(o, &w);
    if (!rc) rc = check_paths(o, &w);
    if (!rc) rc = plan_cubes(o, &w, r);
    if (!rc) rc = peek_telemetry(o, &w, r);
    /* The default: a map taught for this observation (run_speckles_teach.c), before the
     * products' group (teach's own files are in place as it writes them). */
    swfs_speckles_run_options oo = *o;
    if (o->pipe.recon == SWFS_RECON_TEACH) {
        oo.pipe.recon = SWFS_RECON_VK;
        if (!rc && !o->lin.basis) rc = swfs_speckles_teach_(o, w.t, w.tdir, &w.g, r);
        if (!rc && r->taught) {
            oo.pipe.recon = SWFS_RECON_GIVEN;
            oo.recon = r->teach_map;
        }
    }
    /* the second map, of a DM of Gaussian functions, for the choice by the science frames */
    dm_second *dm = NULL;
    if (!rc && oo.pipe.recon == SWFS_RECON_GIVEN && o->pipe.recon == SWFS_RECON_TEACH &&
        swfs_speckles_dm_choice_wanted_(o, r)) {
        if (!(dm = calloc(1, sizeof *dm))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        else rc = dm_teach(o, &w, r, dm);
    }
    /* --mean-loop teach: the loops of the system the files describe, simulated (or reused) as
     * the mean loops (run_mean_teach.c) */
    const char *mt_ptr[SWFS_MEAN_TEACH_MAX];
    /* (a --control map that carries its own miss of the mean, MEANMISS, needs no loops for it) */
    const int mteach = swfs_mean_teach_wanted_(o->mean_teach, &o->lin, o->nmean_loops, o->pipe.wfs_rate);
    char (*dirs)[4400] = mteach ? calloc(SWFS_MEAN_TEACH_MAX, sizeof *dirs) : NULL;
    if (!rc && mteach && !dirs) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc && mteach) rc = swfs_speckles_mean_teach_(o, w.t, w.tdir, &w.g, w.nslopes, &r->mean_teach, dirs, mt_ptr);
    if (!rc && r->mean_teach.done) {
        oo.mean_loops = mt_ptr;
        oo.nmean_loops = r->mean_teach.nloops;
    }
    o = &oo;
    /* The speckle cube, the reconstructor and the --match copies come as a set (atomic.h). */
    int group = !rc;
    if (group) swfs_outputs_begin();
    const int team = swfs_team_active(o->team), writer = swfs_team_writer(o->team);
    const int dm_choice = !rc && dm && dm->taught;
    double *pix = NULL;
    if (dm_choice && !(pix = malloc(w.nfx * w.nfy * sizeof *pix))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    swfs_speckles_run_options o1 = *o;
    if (dm_choice) o1.write_recon = NULL; /* the kept map's, once chosen */
    rc = compute(&o1, &w, r, rc, pix, -1);
    /* the loops' DM: the interpolated surface's speckles against a Gaussian DM's */
    if (!rc && dm_choice) rc = dm_choose(o, &w, r, pix, dm);
    if (!rc && dm_choice && o->write_recon) rc = write_map(o, w.p);
    free(pix);
    free(dm);
    if (!rc && swfs_speckles_orient_warns(r) && !o->pairing_table) {
        swfs_orient_pairing(r->orient.best, &w.t->fit);
        r->orient_adopted = 1;
    }
    if (!rc) {
        r->ncubes = w.t->ncubes;
        r->ratio = w.t->ratio;
        r->lag = w.t->lag;
        swfs_pipeline_get_info(w.p, &r->info);
        r->curl_noise = w.curl_noise;
        char info[800], band[64];
        if (r->info.band > 0) snprintf(band, sizeof band, "%.3g lambda/D", r->info.band);
        else snprintf(band, sizeof band, "the whole window");
        const int tt = o->pipe.tiptilt;
        char model[160];
        int n;
        if (o->lin.basis)
            n = snprintf(model, sizeof model, "linear model: %zu basis functions x %g, %s", r->info.nbasis, o->lin.scale,
                         o->lin.control ? (w.nlags ? "space-time control matrix of lags" : "control matrix")
                                        : o->lin.imat ? "interaction matrix" : "modal coefficients");
        else
            n = snprintf(model, sizeof model, "%zu %s%s", r->info.nact, r->info.out_pitch > 0 ? "output points" : "actuators",
                         w.nlags ? ", space-time reconstructor of lags" : "");
        for (size_t k = 0; k < w.nlags && n > 0 && (size_t)n < sizeof model; k++) /* (0 per frame) */
            n += snprintf(model + n, sizeof model - (size_t)n, "%s%ld", k ? "," : " ", w.lags[k]);
        snprintf(info, sizeof info, "speckles%s: ratio %.6f, lag %.4f, %s, %zu telemetry values, %zu reconstructor "
                 "modes, tip-tilt %s, static halo %s, speckles within %s", o->pipe.wfs_rate ? " at the WFS rate" : "", r->ratio, r->lag,
                 model, w.nslopes, r->info.recon_modes, tt == SWFS_TT_KEEP ? "kept" : (tt == SWFS_TT_EXPOSURE ?
                 "exposure mean removed" : "removed per WFS frame"), o->mean_mode == SWFS_MEAN_CUBE ? "per cube" : "ensemble",
                 band);
        if (r->orient_adopted) {
            char d[64];
            swfs_orient_describe(&w.t->fit, d, sizeof d);
            const size_t len = strlen(info);
            snprintf(info + len, sizeof info - len, ", camera %s by the speckles (the timing table's pairing beaten by "
                     "%.1f standard errors)", d, r->orient.diff / r->orient.diff_se);
        }
        const char **prov = writer ? swfs_prov_plus(o->prov, o->nprov, info) : NULL;
        if (writer && !prov) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        if (!rc && writer) rc = write_speckles(o, &w, r, prov, o->nprov + 1);
        if (!rc && writer && team && o->write_recon) rc = write_map(o, w.p);
        /* --tiptilt frame: the matched copies re-centred on the slopes' tilt (run_internal.h) */
        double *shx = NULL, *shy = NULL;
        const int recentre = writer && o->nmatch && o->pipe.tiptilt == SWFS_TT_FRAME && !o->pipe.wfs_rate &&
                             !o->lin.basis;
        if (!rc && recentre) {
            shx = malloc(r->nout * sizeof *shx);
            shy = malloc(r->nout * sizeof *shy);
            rc = shx && shy ? swfs_frame_recentre_shifts(w.tdir, w.t, o->science, &w.g, shx, shy)
                            : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        }
        for (size_t k = 0; !rc && writer && k < o->nmatch; k++)
            rc = write_match(o->match_in[k], o->match_out[k], &w, shx, shy, prov, o->nprov + 1);
        free(shx);
        free(shy);
        free(prov);
    }
    if (group) {
        int erc = swfs_outputs_end(rc == SWFS_OK);
        if (!rc) rc = erc;
    }
    /* the loops' own map and the self-check's choice (run_loops_map.c): with the interaction
     * matrix and mean loops, where speckles simulated them of a pyramid or it is asked for */
    const int lmap = swfs_loops_map_wanted_(o, r->mean_teach.done && r->mean_teach.pyramid);
    if (!rc && !team && lmap && o->nmean_loops)
        rc = swfs_speckles_loops_map_(o, &w.g, swfs_pipeline_mask(w.p), r->meanmiss_heldout, w.p, &r->loops_map);
    /* Every member ends with member 0's writing status. */
    if (team) rc = swfs_team_agree(o->team, rc);
    work_free(&w);
    free(dirs);
    return rc;
}

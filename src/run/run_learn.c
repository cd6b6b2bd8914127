/* learn: a reconstructor from simulated closed loops (run.h swfs_learn_run, wfs.h
 * swfs_recon_learner; docs/telemetry.md). */
#include "specklewfs/run.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "run_internal.h"

#include <cblas.h>
#include <dirent.h>
#include <limits.h>
#include <math.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

void swfs_learn_run_options_default(swfs_learn_run_options *o)
{
    memset(o, 0, sizeof *o);
    o->ridge = SWFS_RECON_LEARN_RIDGE;
}

/* What a training data set's first file says of the loops' time behaviour, for speckles to
 * compare with the observation's: its wind and its slopes' correlation at the lags. */
typedef struct set_stats {
    swfs_wind_estimate wind;
    double corr[SWFS_RECON_MAXLAGS];
} set_stats;

/* One pair of files: the slopes and the truth of the same frames, added to the learner (made
 * at the first pair, from its shapes); with lags, each frame's input is the slopes of frames
 * t + lags stacked, clamped at the file's ends (swfs_slopes_stack), which
 * swfs_recon_learner_add_lagged sums without stacking the file. */
static int add_pair(const swfs_learn_run_options *o, const char *sp, const char *tp, swfs_recon_learner **l,
                    swfs_learn_run_result *r, set_stats *stats)
{
    const int modal = o->modal;
    const size_t nl = o->nlags > 1 ? o->nlags : 1;
    swfs_real *s = NULL, *z = NULL;
    int rc = swfs_fits_read_real(sp, NULL, &s, NULL);
    if (!rc) rc = swfs_fits_read_real(tp, NULL, &z, NULL);
    if (!rc && (s->nz != 1 || z->nz != 1 || s->ny != z->ny || s->nx % 2))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s (%zux%zux%zu) and %s (%zux%zux%zu): expected NSLOPES (even) x N and NACT x N "
                       "images of the same N frames", sp, s->nx, s->ny, s->nz, tp, z->nx, z->ny, z->nz);
    /* a file of zeros (a loop that never ran, a fill) would teach the map nothing but weight */
    for (int k = 0; !rc && k < 2; k++) {
        const swfs_real *a = k ? z : s;
        size_t q = 0;
        while (q < a->nx * a->ny && a->data[q] == 0) q++;
        if (q == a->nx * a->ny)
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: every value is 0: a data set holds a loop's %s", k ? tp : sp,
                           k ? "true residual" : "telemetry");
    }
    /* the slopes as the telemetry's own projection left them */
    if (!rc && o->project) rc = swfs_modal_project_(o->project, o->nproject, s, sp);
    if (!rc && r->nslopes && (s->nx != r->nslopes || z->nx != r->nact))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu slopes and %zu actuators; the first data set has %zu and %zu: the "
                       "training data must share one geometry", sp, s->nx, z->nx, r->nslopes, r->nact);
    if (!rc && !*l) {
        r->nslopes = s->nx;
        r->nact = z->nx;
        rc = swfs_recon_learner_new(s->nx * nl, z->nx, !modal, l);
    }
    if (!rc && (rc = nl > 1 ? swfs_recon_learner_add_lagged(*l, s->data, s->nx, z->data, s->ny, o->lags, nl)
                            : swfs_recon_learner_add(*l, s->data, z->data, s->ny)))
        rc = swfs_fail_context(rc, "%s / %s", sp, tp);
    if (!rc && nl > 1 && stats) /* the full layout's nsub; other layouts give no wind (no map here) */
        rc = swfs_spacetime_stats_(s->data, s->ny, s->nx, (size_t)llround(sqrt((double)s->nx / 2)), NULL, o->lags, nl,
                                   &stats->wind, stats->corr);
    swfs_real_free(s);
    swfs_real_free(z);
    return rc;
}

/* The map w into path: the space-time (or per-frame) map learned, or (lag0) the lag-0 block of
 * a space-time learn's sums alone, the per-frame map of the same frames, whose file carries
 * that map's own fit and none of the lags' keys. */
static int write_recon(const swfs_learn_run_options *o, const char *path, const swfs_recon *w,
                       const swfs_learn_run_result *r, int lag0, const double *meanmiss)
{
    swfs_fits_out *f = NULL;
    const swfs_recon_learn_info *in = lag0 ? &r->perframe_info : &r->info;
    int rc = swfs_fits_out_create(&f, path);
    if (rc) return rc;
    rc = swfs_recon_write_hdu(f, w);
    if (!rc && !o->modal) rc = swfs_fits_out_key_string(f, "BUNIT", "m/rad", "actuator displacement per slope");
    if (!rc) rc = swfs_fits_out_key_long(f, "NMODES", 0, "learned, not an SVD");
    if (!rc) rc = swfs_fits_out_key_long(f, "LRNMODAL", o->modal ? 1 : 0, o->modal ? "truth: modal coefficients as given"
                                                                                  : "truth: actuators, piston removed");
    if (!rc) rc = swfs_fits_out_key_string(f, "RECON", "learned", "least squares slopes -> simulated residual");
    if (!rc) rc = swfs_fits_out_key_long(f, "LRNFRAME", (long)in->nframes, "WFS frames learned from");
    if (!rc) rc = swfs_fits_out_key_long(f, "LRNSETS", (long)o->ndirs, "simulated data sets");
    if (!rc) rc = swfs_fits_out_key_double(f, "LRNRIDGE", o->ridge, "ridge [mean diagonal of S^T S]");
    if (!rc && o->prior) rc = swfs_fits_out_key_string(f, "LRNPRIOR", strrchr(o->prior, '/') ? strrchr(o->prior, '/') + 1
                                                          : o->prior, "the map shrunk toward");
    if (!rc) rc = swfs_fits_out_key_double(f, "LRNTRUTH", in->truth_rms, "rms truth per value [m, or the coefficients' unit]");
    if (!rc) rc = swfs_fits_out_key_double(f, "LRNMISF", in->misfit_rms, "[m] rms training misfit");
    if (!rc && lag0)
        rc = swfs_fits_out_history(f, "the per-frame map of the same frames: the lag-0 block of a space-time learn's "
                                   "sums solved alone (swfs_recon_learner_solve_lag)");
    for (size_t k = 0; !rc && !lag0 && o->nlags > 1 && k < o->nlags; k++) {
        char key[32];
        snprintf(key, sizeof key, "LRNCOR%zu", k + 1);
        rc = swfs_fits_out_key_double(f, key, r->corr[k], "training slopes' correlation at LAGk");
        snprintf(key, sizeof key, "LRNCSP%zu", k + 1);
        if (!rc) rc = swfs_fits_out_key_double(f, key, r->corr_spread[k], "largest set's distance from it");
    }
    if (!rc && !lag0 && r->nwind) {
        rc = swfs_fits_out_key_long(f, "LRNWINDN", (long)r->nwind, "training sets whose slopes show a wind");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNVX", r->wind_vx, "[subap/frame] their mean wind, x");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNVY", r->wind_vy, "[subap/frame] their mean wind, y");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNVSPRD", r->wind_spread, "[subap/frame] largest from the mean");
        if (!rc) rc = swfs_fits_out_key_long(f, "LRNNLAY", (long)r->nwlayers, "frozen-flow layers in their slopes");
    }
    for (size_t k = 0; !rc && !lag0 && k < r->nwlayers; k++) {
        char key[4][32];
        snprintf(key[0], sizeof key[0], "LRNL%zuX", k + 1);
        snprintf(key[1], sizeof key[1], "LRNL%zuY", k + 1);
        snprintf(key[2], sizeof key[2], "LRNL%zuN", k + 1);
        snprintf(key[3], sizeof key[3], "LRNL%zuS", k + 1);
        rc = swfs_fits_out_key_double(f, key[0], r->wlayer_vx[k], "[subap/frame] layer k's mean wind, x");
        if (!rc) rc = swfs_fits_out_key_double(f, key[1], r->wlayer_vy[k], "[subap/frame] layer k's mean wind, y");
        if (!rc) rc = swfs_fits_out_key_long(f, key[2], (long)r->wlayer_n[k], "training sets that show it");
        if (!rc) rc = swfs_fits_out_key_double(f, key[3], r->wlayer_spread[k], "[subap/frame] largest from the mean");
    }
    if (!rc && !lag0 && r->nheldout) {
        rc = swfs_fits_out_key_long(f, "LRNHSETS", (long)r->nheldout, "data sets held out in turn");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNHMISF", r->heldout_misfit_rms, "[m] rms misfit, held out");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNHTRUT", r->heldout_truth_rms, "[m] rms truth, held out");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNHWRST", r->heldout_worst, "worst set's misfit / truth");
        if (!rc) rc = swfs_fits_out_key_long(f, "LRNHOUT", (long)r->heldout_outputs, "outputs checked (--curve-radius)");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNHSCAL", r->heldout_scaled_rms, "[m] held out, map scaled best");
    }
    if (!rc && !lag0 && r->curve_n[0]) {
        rc = swfs_fits_out_key_long(f, "LRNCN1", (long)r->curve_n[0], "learning curve: frames of a half map");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNCM1", sqrt(r->curve_m2[0]), "[m] its rms misfit, held out");
        if (!rc) rc = swfs_fits_out_key_long(f, "LRNCN2", (long)r->curve_n[1], "frames of a three-quarter map");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNCM2", sqrt(r->curve_m2[1]), "[m] its rms misfit, held out");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNCEXC", isfinite(r->curve_excess) ? r->curve_excess : -1.0,
                                                  "misfit^2 excess at LRNFRAME, b/(aN) (-1: unbounded)");
        if (!rc) rc = swfs_fits_out_key_long(f, "LRNCFRM", r->curve_frames > (size_t)LONG_MAX ? -1 : (long)r->curve_frames,
                                             "frames for an excess of 0.1 (0 flat, -1 unbounded)");
        if (!rc && isfinite(r->curve_fall_se))
            rc = swfs_fits_out_key_double(f, "LRNCFSE", r->curve_fall_se, "[m^2] std error of LRNCM1^2 - LRNCM2^2");
    }
    if (!rc && !lag0 && isfinite(r->meanmiss_heldout)) {
        rc = swfs_fits_out_key_double(f, "LRNMMHO", r->meanmiss_heldout, "mean's miss, held out / its own (<1: kept)");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNMMSET", r->meanmiss_set_rms, "rms of the sets' mean's misses");
        if (!rc) rc = swfs_fits_out_key_double(f, "LRNMMRMS", r->meanmiss_kept ? r->meanmiss_rms : 0.0,
                                              "rms of MEANMISS (0: none written)");
    }
    for (size_t d = 0; !rc && d < o->ndirs; d++) {
        char h[4200];
        snprintf(h, sizeof h, "learned from %.4000s", o->dirs[d]);
        rc = swfs_fits_out_history(f, h);
    }
    if (!rc)
        rc = swfs_fits_out_history(f, o->modal ? "specklewfs control matrix: coefficients = W v, NAXIS1 = telemetry values, "
                                                 "NAXIS2 = basis functions (speckles --basis --control)"
                                               : "specklewfs reconstructor: z_act = W s, NAXIS1 = slopes, NAXIS2 = actuators");
    if (!rc) rc = swfs_fits_out_provenance(f, o->prov, o->nprov);
    if (!rc) rc = swfs_recon_write_outxy(f, w);
    if (!rc && !lag0 && meanmiss) { /* the miss of the residual's mean, per output: speckles adds it to RESMEAN */
        swfs_real m = {w->nact, 1, 1, (double *)meanmiss};
        rc = swfs_fits_out_real(f, "MEANMISS", &m, -64);
        if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", o->modal ? "" : "m", "the map's miss of the residual's "
                                               "time mean, per output");
    }
    if (rc) { swfs_fits_out_abort(f); return rc; }
    return swfs_fits_out_commit(f);
}

/* The number of a data set's file name: "slopes_NNN.fits" or "truewf_NNN.fits" as add_dir
 * names them (%03zu), else -1; *truth 1 for a truewf file. */
static long series_index(const char *name, int *truth)
{
    const char *p = !strncmp(name, "slopes_", 7) ? name + 7 : !strncmp(name, "truewf_", 7) ? name + 7 : NULL;
    if (!p) return -1;
    char *end = NULL;
    const unsigned long k = strtoul(p, &end, 10);
    if (end == p || end - p < 3 || strcmp(end, ".fits") || (*p == '0' && end - p > 3) || k > 100000) return -1;
    *truth = name[0] == 't';
    return (long)k;
}

/* A data set's files as inputs of the paths' check (an output named as one of them would
 * overwrite it), and their numbers: slopes_000.fits on, one after the other, each beside its
 * truewf (add_dir reads the series up to its first missing number: a gap would leave the
 * files after it unread, in silence). */
static int dir_inputs(swfs_paths *paths, const char *dir)
{
    DIR *d = opendir(dir);
    if (!d) return SWFS_OK; /* not a folder, or unreadable: add_dir names it */
    long last[2] = {-1, -1};
    size_t count[2] = {0, 0};
    int rc = SWFS_OK;
    char path[4400];
    for (struct dirent *e; !rc && (e = readdir(d));) {
        int t = 0;
        const long k = series_index(e->d_name, &t);
        if (k < 0) continue;
        count[t]++;
        if (k > last[t]) last[t] = k;
        if (snprintf(path, sizeof path, "%s/%s", dir, e->d_name) >= (int)sizeof path)
            rc = swfs_fail(SWFS_ERR_ARG, "learn: %s: a path too long", dir);
        else
            rc = swfs_paths_input(paths, t ? "true residual" : "telemetry", path);
    }
    closedir(d);
    for (int t = 0; !rc && t < 2; t++)
        if (count[t] && count[t] != (size_t)last[t] + 1) {
            const char *what = t ? "truewf" : "slopes";
            size_t k = 0;
            for (; k < (size_t)last[t]; k++) {
                snprintf(path, sizeof path, "%.4000s/%s_%03zu.fits", dir, what, k);
                if (access(path, F_OK) != 0) break;
            }
            rc = swfs_fail(SWFS_ERR_IO, "%s: %zu %s files numbered up to %03ld, but no %s_%03zu.fits: a data set's "
                           "files are numbered from 000 without a gap (the series would end there, the rest unread)",
                           dir, count[t], what, last[t], what, k);
        }
    if (!rc && count[1] > count[0])
        rc = swfs_fail(SWFS_ERR_IO, "%s: %zu truewf files for %zu slopes files: every true residual needs the slopes "
                       "of its frames (slopes_NNN.fits beside truewf_NNN.fits)", dir, count[1], count[0]);
    return rc;
}

/* Every slopes_NNN.fits / truewf_NNN.fits pair of the folder `dir` added to *l (*nfiles
 * counts them when given). */
static int add_dir(const swfs_learn_run_options *o, const char *dir, swfs_recon_learner **l, swfs_learn_run_result *r,
                   size_t *nfiles, set_stats *st)
{
    size_t k = 0;
    for (;; k++) {
        char sp[4200], tp[4200];
        snprintf(sp, sizeof sp, "%.4000s/slopes_%03zu.fits", dir, k);
        snprintf(tp, sizeof tp, "%.4000s/truewf_%03zu.fits", dir, k);
        if (access(sp, F_OK) != 0) break;
        if (access(tp, F_OK) != 0)
            return swfs_fail(SWFS_ERR_IO, "%s: no %s beside it: the training data need the true residual of every "
                             "slopes file (simulate mode=timeseries export_truth=1)", sp, tp);
        int rc = add_pair(o, sp, tp, l, r, k == 0 ? st : NULL);
        if (rc) return rc;
        if (nfiles) (*nfiles)++;
    }
    if (k == 0)
        return swfs_fail(SWFS_ERR_IO, "%s: no slopes_000.fits: expected a folder of `simulate mode=timeseries "
                         "export_truth=1`", dir);
    return SWFS_OK;
}

/* The data sets dealt into the four parts' sums of the learning curve: set d into part d % 4,
 * each part's sets in their order. The first set is read first (its shapes make every part's
 * learner); then the four parts at once, as many as o->threads allow (each part's sums are
 * the same whatever runs beside them: its own learner, its sets in order, BLAS inside
 * single-threaded). */
typedef struct parts_ctx {
    const swfs_learn_run_options *o;
    swfs_recon_learner *const *q;
    const swfs_learn_run_result *r; /* nslopes, nact: read only (every part's learner made) */
    set_stats *sets;
    size_t nfiles[4];
    int rc[4];
    char why[4][1024];
    atomic_size_t done;
    size_t shown; /* the last count worker 0 reported */
    atomic_int stop; /* the caller's progress asked to stop: no set is read after it */
} parts_ctx;

static void parts_worker(void *ctx, size_t begin, size_t end, int worker)
{
    parts_ctx *c = ctx;
    swfs_learn_run_result r = *c->r;
    for (size_t k = begin; k < end; k++) {
        swfs_recon_learner *l = c->q[k];
        for (size_t d = k ? k : 4; !c->rc[k] && !atomic_load(&c->stop) && d < c->o->ndirs; d += 4) {
            c->rc[k] = add_dir(c->o, c->o->dirs[d], &l, &r, &c->nfiles[k], c->sets ? c->sets + d : NULL);
            const size_t done = atomic_fetch_add(&c->done, 1) + 1;
            if (!worker && c->o->progress && c->o->progress(c->o->progress_ctx, "read", c->shown = done, c->o->ndirs))
                atomic_store(&c->stop, 1);
        }
        if (c->rc[k]) snprintf(c->why[k], sizeof c->why[k], "%s", swfs_last_error());
    }
}

static int add_parts(const swfs_learn_run_options *o, swfs_recon_learner *q[4], swfs_learn_run_result *r,
                     set_stats *sets)
{
    const size_t nl = o->nlags > 1 ? o->nlags : 1;
    int rc = add_dir(o, o->dirs[0], &q[0], r, &r->nfiles, sets);
    for (int k = 1; !rc && k < 4; k++) rc = swfs_recon_learner_new(r->nslopes * nl, r->nact, !o->modal, &q[k]);
    if (rc) return rc;
    parts_ctx c = {.o = o, .q = q, .r = r, .sets = sets, .done = 1, .shown = 1};
    if ((rc = swfs_progress_report(o->progress, o->progress_ctx, "read", 1, o->ndirs))) return rc;
    swfs_parallel_for(swfs_parallel_threads(o->threads, 4), 4, 1, parts_worker, &c);
    for (int k = 0; k < 4; k++) {
        if (c.rc[k]) return swfs_fail(c.rc[k], "%s", c.why[k]);
        r->nfiles += c.nfiles[k];
    }
    if (atomic_load(&c.stop))
        return swfs_fail(SWFS_ERR_STOPPED, "read: stopped by the caller after %zu of %zu data sets", atomic_load(&c.done),
                         o->ndirs);
    if (c.shown != o->ndirs) return swfs_progress_report(o->progress, o->progress_ctx, "read", o->ndirs, o->ndirs);
    return SWFS_OK;
}

/* --prior: the map read and set on the learner of all the frames (its shapes checked). */
static int set_prior(const swfs_learn_run_options *o, swfs_recon_learner *l)
{
    if (!o->prior) return SWFS_OK;
    swfs_recon *w0 = NULL;
    int rc = swfs_recon_read(o->prior, &w0);
    if (!rc && w0->nlags)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: a space-time map (NLAGS %zu); --prior takes a per-frame map", o->prior,
                       w0->nlags);
    if (!rc) rc = swfs_recon_learner_set_prior(l, w0);
    swfs_recon_free(w0);
    return rc ? swfs_fail_context(rc, "learn: the prior map %s (expected NAXIS1 = the data sets' slopes, NAXIS2 = their "
                                  "truth's values)", o->prior) : SWFS_OK;
}

/* Leave one data set out in turn: each folder's frames read again into a learner of their
 * own, the map of the others' sums checked on them. A folder whose removal leaves too few
 * frames for a map is not checked. */
static int heldout(const swfs_learn_run_options *o, const swfs_recon_learner *all, const unsigned char *keep,
                   swfs_learn_run_result *r)
{
    swfs_recon_learner *part = NULL;
    const size_t nl = o->nlags > 1 ? o->nlags : 1;
    int rc = swfs_recon_learner_new(r->nslopes * nl, r->nact, !o->modal, &part);
    for (size_t d = 0; o->heldout_ratio && d < o->ndirs; d++) o->heldout_ratio[d] = NAN;
    double m2 = 0, t2 = 0, s2 = 0;
    size_t nf = 0;
    for (size_t d = 0; !rc && d < o->ndirs; d++) {
        swfs_recon_learner_reset(part);
        if ((rc = add_dir(o, o->dirs[d], &part, r, NULL, NULL))) break;
        double md = 0, td = 0, sd = 0;
        rc = swfs_recon_learner_heldout_on(all, part, o->ridge, keep, &md, &td, &sd);
        const int skip = rc == SWFS_ERR_VALUE; /* too few frames without it: no ratio */
        if (skip) rc = SWFS_OK;
        if (!rc) rc = swfs_progress_report(o->progress, o->progress_ctx, "held out", d + 1, o->ndirs);
        if (rc) break;
        if (skip) continue;
        const size_t n = swfs_recon_learner_frames(part);
        m2 += md * (double)n;
        t2 += td * (double)n;
        s2 += sd * (double)n;
        nf += n;
        const double ratio = sqrt(md / td);
        if (o->heldout_ratio) o->heldout_ratio[d] = ratio;
        if (r->nheldout == 0 || ratio > r->heldout_worst) {
            r->heldout_worst = ratio;
            r->heldout_worst_set = d;
        }
        r->nheldout++;
    }
    if (!rc && nf) {
        r->heldout_misfit_rms = sqrt(m2 / (double)nf);
        r->heldout_truth_rms = sqrt(t2 / (double)nf);
        r->heldout_scaled_rms = sqrt(s2 / (double)nf);
    }
    swfs_recon_learner_free(part);
    return rc;
}

/* One check of the learning curve: c = 0, 1 hold parts {0, 2} then {1, 3} out (a half map);
 * c = 2..5 part c - 2 (a three-quarter map). */
typedef struct curve_check {
    double md, td, sd; /* the held-out part's misfit, truth and scaled misfit (mean squares) */
    double sub_md[2];  /* of a check holding out two parts: the misfit on each alone */
    size_t n;          /* its frames */
    int rc;
    char why[1024];
} curve_check;

typedef struct curve_ctx {
    const swfs_learn_run_options *o;
    const swfs_recon_learner *all;
    swfs_recon_learner *const *q;
    const unsigned char *keep;
    size_t nin, nact; /* the learners' inputs and outputs */
    curve_check ck[6];
    atomic_size_t done;
    size_t shown; /* the last count worker 0 reported */
    atomic_int stop; /* the caller's progress asked to stop: no check starts after it */
} curve_ctx;

static void curve_worker(void *ctx, size_t begin, size_t end, int worker)
{
    curve_ctx *c = ctx;
    swfs_recon_learner *h = NULL;
    int rc = swfs_recon_learner_new(c->nin, c->nact, !c->o->modal, &h);
    for (size_t k = begin; k < end; k++) {
        curve_check *ck = c->ck + k;
        if (!rc && atomic_load(&c->stop)) rc = SWFS_ERR_STOPPED;
        if (!rc) {
            swfs_recon_learner_reset(h);
            rc = swfs_recon_learner_merge(h, c->q[k < 2 ? k : k - 2]);
            if (!rc && k < 2) rc = swfs_recon_learner_merge(h, c->q[k + 2]);
            ck->n = rc ? 0 : swfs_recon_learner_frames(h);
            /* a check of two parts tells each one's misfit too: the curve's fall part by part */
            const swfs_recon_learner *subs[2] = {k < 2 ? c->q[k] : NULL, k < 2 ? c->q[k + 2] : NULL};
            if (!rc) rc = swfs_recon_learner_heldout_split(c->all, h, subs, k < 2 ? 2 : 0, c->o->ridge, c->keep, &ck->md,
                                                           &ck->td, &ck->sd, k < 2 ? ck->sub_md : NULL);
        }
        ck->rc = rc;
        if (rc) snprintf(ck->why, sizeof ck->why, "%s", swfs_last_error());
        rc = rc == SWFS_ERR_VALUE ? SWFS_OK : rc; /* a part too small: the next check may still run */
        const size_t done = atomic_fetch_add(&c->done, 1) + 1;
        if (!worker && c->o->progress && c->o->progress(c->o->progress_ctx, "learning curve", c->shown = done, 6))
            atomic_store(&c->stop, 1);
    }
    swfs_recon_learner_free(h);
}

/* The bytes one check holds at once: its learner's sums (G, H) and the solve's normal
 * matrices, right-hand sides and products (solve_sums, swfs_recon_learner_heldout_on). */
static double curve_check_bytes(size_t nin, size_t nact)
{
    const double ni = (double)nin, na = (double)nact;
    return 8.0 * (3.0 * ni * ni + 3.0 * ni * na);
}

/* The learning curve (run.h swfs_learn_run_result.curve_*) from the sums of the four parts q
 * and of all their frames: each check's misfit weighted by the frames it is checked on. The
 * six checks are independent solves of the same size (each its own learner; BLAS inside
 * single-threaded): as many at once as o->threads and the free memory allow, the same sums
 * whatever ran beside them, added up in the checks' order. */
static int learning_curve(const swfs_learn_run_options *o, const swfs_recon_learner *all,
                          swfs_recon_learner *const q[4], const unsigned char *keep, swfs_learn_run_result *r)
{
    const size_t N = swfs_recon_learner_frames(all), nl = o->nlags > 1 ? o->nlags : 1;
    curve_ctx c = {.o = o, .all = all, .q = q, .keep = keep, .nin = r->nslopes * nl, .nact = r->nact};
    const double avail = swfs_mem_available(), fit = avail > 0 ? avail / curve_check_bytes(c.nin, c.nact) : 6.0;
    const size_t cap = fit >= 6.0 ? 6 : fit >= 1.0 ? (size_t)fit : 1;
    swfs_parallel_for(swfs_parallel_threads(o->threads, cap), 6, 1, curve_worker, &c);
    if (atomic_load(&c.stop)) return swfs_fail(SWFS_ERR_STOPPED, "learning curve: stopped by the caller");
    if (c.shown != 6) {
        const int rc = swfs_progress_report(o->progress, o->progress_ctx, "learning curve", 6, 6);
        if (rc) return rc;
    }
    double m2[2] = {0, 0}, s2[2] = {0, 0}, nt[2] = {0, 0}, ne[2] = {0, 0};
    for (size_t k = 0; k < 6; k++) {
        const curve_check *ck = c.ck + k;
        if (ck->rc == SWFS_ERR_VALUE) { /* a part too small for a map without it: no curve */
            swfs_clear_error();
            return SWFS_OK;
        }
        if (ck->rc) return swfs_fail(ck->rc, "%s", ck->why);
        const int h = k < 2 ? 0 : 1;
        m2[h] += ck->md * (double)ck->n;
        s2[h] += ck->sd * (double)ck->n;
        nt[h] += (double)(N - ck->n) * (double)ck->n;
        ne[h] += (double)ck->n;
    }
    for (int k = 0; k < 2; k++) {
        r->curve_m2[k] = m2[k] / ne[k];
        r->curve_s2[k] = s2[k] / ne[k];
        r->curve_n[k] = (size_t)llround(nt[k] / ne[k]);
    }
    /* The fall m2[0] - m2[1] part by part: each part's misfit under the map of two parts (the
     * check holding it out with the part two on) less that under the map of the other three,
     * the same frames; their scatter over the four parts (loops dealt 3 and more to a part
     * differ in their layers' mix) gives the fall's standard error. */
    double d[4], dm = 0, dv = 0;
    for (int p = 0; p < 4; p++) dm += (d[p] = c.ck[p % 2].sub_md[p / 2] - c.ck[2 + p].md) / 4.0;
    for (int p = 0; p < 4; p++) dv += (d[p] - dm) * (d[p] - dm) / 3.0;
    r->curve_fall_se = sqrt(dv / 4.0);
    const double n0 = (double)r->curve_n[0], n1 = (double)r->curve_n[1];
    if (!(n1 > n0)) return SWFS_OK;
    r->curve_b = (r->curve_m2[0] - r->curve_m2[1]) / (1.0 / n0 - 1.0 / n1);
    r->curve_a = r->curve_m2[1] - r->curve_b / n1;
    if (r->curve_b <= 0) {
        r->curve_excess = 0;
        r->curve_frames = 0;
    } else if (r->curve_a > 0) {
        r->curve_excess = r->curve_b / (r->curve_a * (double)N);
        const double need = ceil(r->curve_b / (SWFS_LEARN_CURVE_EXCESS * r->curve_a));
        r->curve_frames = need < 1e15 ? (size_t)need : SIZE_MAX;
    } else { /* steeper than any a + b / n with a > 0: more frames without a bound */
        r->curve_excess = INFINITY;
        r->curve_frames = SIZE_MAX;
    }
    return SWFS_OK;
}

int swfs_learn_curve_falls(const swfs_learn_run_result *r)
{
    if (!r->curve_n[0] || !(r->curve_b > 0)) return 0;
    return !isfinite(r->curve_fall_se) || r->curve_m2[0] - r->curve_m2[1] > SWFS_LEARN_CURVE_FALL_SE * r->curve_fall_se;
}

/* The data sets' winds (those found: nwind) and slope correlations: their means and the
 * largest distance of one from them. */
static void training_stats(const set_stats *st, const swfs_learn_run_options *o, swfs_learn_run_result *r)
{
    double mx = 0, my = 0, sp = 0;
    for (size_t d = 0; d < o->ndirs; d++)
        if (st[d].wind.found) { mx += st[d].wind.vx; my += st[d].wind.vy; r->nwind++; }
    if (r->nwind) {
        mx /= (double)r->nwind;
        my /= (double)r->nwind;
        for (size_t d = 0; d < o->ndirs; d++)
            if (st[d].wind.found) sp = fmax(sp, hypot(st[d].wind.vx - mx, st[d].wind.vy - my));
        r->wind_vx = mx;
        r->wind_vy = my;
        r->wind_spread = sp;
    }
    /* every set's layers, grouped: one within SWFS_SPACETIME_MISMATCH_WARN subaperture at the
     * largest lag of a group's mean joins it (the first such), others start a group */
    const long lmax = swfs_lags_max_abs(o->lags, o->nlags);
    const double tol = SWFS_SPACETIME_MISMATCH_WARN / (double)(lmax ? lmax : 1);
    double sx[SWFS_LEARN_MAXWLAYERS] = {0}, sy[SWFS_LEARN_MAXWLAYERS] = {0};
    for (size_t d = 0; d < o->ndirs; d++)
        for (size_t j = 0; st[d].wind.found && j < st[d].wind.nlayers; j++) {
            const swfs_wind_layer *L = &st[d].wind.layer[j];
            size_t g = 0;
            while (g < r->nwlayers && hypot(L->vx - r->wlayer_vx[g], L->vy - r->wlayer_vy[g]) > tol) g++;
            if (g == SWFS_LEARN_MAXWLAYERS) continue;
            if (g == r->nwlayers) r->nwlayers++;
            sx[g] += L->vx;
            sy[g] += L->vy;
            r->wlayer_n[g]++;
            r->wlayer_vx[g] = sx[g] / (double)r->wlayer_n[g];
            r->wlayer_vy[g] = sy[g] / (double)r->wlayer_n[g];
        }
    for (size_t g = 0; g < r->nwlayers; g++) {
        r->wlayer_spread[g] = 0;
        for (size_t d = 0; d < o->ndirs; d++)
            for (size_t j = 0; st[d].wind.found && j < st[d].wind.nlayers; j++) {
                const double dist = hypot(st[d].wind.layer[j].vx - r->wlayer_vx[g], st[d].wind.layer[j].vy - r->wlayer_vy[g]);
                if (dist <= tol) r->wlayer_spread[g] = fmax(r->wlayer_spread[g], dist);
            }
    }
    for (size_t k = 0; k < o->nlags; k++) {
        double m = 0, dev = 0;
        for (size_t d = 0; d < o->ndirs; d++) m += st[d].corr[k] / (double)o->ndirs;
        for (size_t d = 0; d < o->ndirs; d++) dev = fmax(dev, fabs(st[d].corr[k] - m));
        r->corr[k] = m;
        r->corr_spread[k] = dev;
    }
}

/* The points the truth was fitted on (truewf's OUTXY, simulate's truth_actuators), the same in
 * every data set, become the map's output points (*xy); none: the DM's actuators (NULL). */
static int truth_points(const swfs_learn_run_options *o, size_t nact, double **xy)
{
    *xy = NULL;
    int rc = SWFS_OK;
    for (size_t d = 0; !rc && d < o->ndirs; d++) {
        char tp[4200];
        snprintf(tp, sizeof tp, "%.4000s/truewf_000.fits", o->dirs[d]);
        double *p = NULL;
        if ((rc = swfs_outxy_read(tp, nact, &p))) break;
        if (d == 0) *xy = p;
        else if (p && *xy && memcmp(p, *xy, 2 * nact * sizeof *p))
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: its truth is on other points (OUTXY) than %s/truewf_000.fits': the "
                           "training data must share one geometry", tp, o->dirs[0]);
        else if (!p != !*xy)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: its truth is on %s, %s/truewf_000.fits' on %s: the training data must "
                           "share one geometry", tp, p ? "points of its own (OUTXY)" : "the DM's actuators", o->dirs[0],
                           *xy ? "points of its own (OUTXY)" : "the DM's actuators");
        if (d > 0) free(p);
    }
    if (!rc && *xy && o->modal)
        rc = swfs_fail(SWFS_ERR_ARG, "learn: --modal learns modal coefficients, but the truth of %s is on points "
                       "(extension OUTXY)", o->dirs[0]);
    if (rc) { free(*xy); *xy = NULL; }
    return rc;
}

/* The outputs' positions [m] on the pupil for the checks' annulus: the truth's own points
 * (OUTXY), else the DM's actuators of the first folder (actuators.fits, one per output). */
static int output_positions(const swfs_learn_run_options *o, size_t nact, double **xy)
{
    int rc = truth_points(o, nact, xy);
    if (rc || *xy) return rc;
    if (o->modal)
        return swfs_fail(SWFS_ERR_ARG, "learn: the checks' annulus (--curve-radius) needs the outputs' positions, "
                         "but --modal's outputs are coefficients of a basis");
    char ap[4200];
    snprintf(ap, sizeof ap, "%.4000s/actuators.fits", o->dirs[0]);
    size_t n = 0;
    rc = swfs_actuators_read(ap, xy, &n);
    if (!rc && n != nact) {
        free(*xy);
        *xy = NULL;
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu actuators, but the truth (truewf_000.fits) has %zu values per frame: "
                       "the checks' annulus (--curve-radius) needs one position per output", ap, n, nact);
    }
    return rc ? swfs_fail_context(rc, "learn: the outputs' positions for --curve-radius") : SWFS_OK;
}

/* keep[a] for the outputs within curve_radius (NULL: no annulus given, all), counted in
 * curve_outputs and heldout_outputs. */
static int check_outputs(const swfs_learn_run_options *o, swfs_learn_run_result *r, unsigned char **keep)
{
    *keep = NULL;
    r->curve_outputs = r->heldout_outputs = r->nact;
    if (!(o->curve_radius[1] > 0)) return SWFS_OK;
    double *xy = NULL;
    int rc = output_positions(o, r->nact, &xy);
    if (!rc && !(*keep = malloc(r->nact ? r->nact : 1))) rc = swfs_fail(SWFS_ERR_NOMEM, "learn: out of memory");
    size_t n = 0;
    for (size_t a = 0; !rc && a < r->nact; a++) {
        const double rad = hypot(xy[2 * a], xy[2 * a + 1]);
        (*keep)[a] = rad >= o->curve_radius[0] && rad <= o->curve_radius[1];
        n += (*keep)[a];
    }
    if (!rc && !n)
        rc = swfs_fail(SWFS_ERR_VALUE, "learn: no output within %g to %g m of the centre for the checks "
                       "(--curve-radius; %zu outputs)", o->curve_radius[0], o->curve_radius[1], r->nact);
    free(xy);
    if (rc) {
        free(*keep);
        *keep = NULL;
        return rc;
    }
    r->curve_outputs = r->heldout_outputs = n;
    return SWFS_OK;
}

double swfs_heldout_mean_(const double *x, size_t nsets, size_t n, const double *mask, const double *M, double *work,
                          double *mean, double *own)
{
    double eho = 0, e0 = 0;
    for (size_t i = 0; i < n; i++) {
        mean[i] = 0;
        if (mask && !(mask[i] > 0)) continue;
        double sum = 0;
        for (size_t d = 0; d < nsets; d++) sum += x[d * n + i];
        mean[i] = sum / (double)nsets;
        for (size_t d = 0; !M && d < nsets; d++) {
            const double v = x[d * n + i], others = (sum - v) / (double)(nsets - 1);
            eho += (v - others) * (v - others);
            e0 += v * v;
        }
    }
    /* the metric's form: each set's x_d and x_d less the others' mean, (nsets mean - x_d) /
     * (nsets - 1), weighed by M */
    double *e = work, *Me = work ? work + n : NULL;
    for (size_t d = 0; M && nsets > 1 && d < nsets; d++) {
        const double *v = x + d * n;
        cblas_dsymv(CblasRowMajor, CblasUpper, (int)n, 1.0, M, (int)n, v, 1, 0.0, Me, 1);
        e0 += cblas_ddot((int)n, v, 1, Me, 1);
        for (size_t i = 0; i < n; i++) e[i] = v[i] - ((double)nsets * mean[i] - v[i]) / (double)(nsets - 1);
        cblas_dsymv(CblasRowMajor, CblasUpper, (int)n, 1.0, M, (int)n, e, 1, 0.0, Me, 1);
        eho += cblas_ddot((int)n, e, 1, Me, 1);
    }
    if (own) *own = e0;
    return nsets > 1 && e0 > 0 ? eho / e0 : NAN;
}

int swfs_meanmiss_metric_data_(double *inf, size_t na, size_t n, const double *mask, const char *what, double **M)
{
    *M = NULL;
    const size_t nq = n * n;
    int rc = SWFS_OK;
    for (size_t a = 0; !rc && a < na; a++)
        for (size_t q = 0; q < nq; q++)
            if (mask[q] > 0 && !isfinite(inf[a * nq + q])) {
                char val[48];
                rc = swfs_fail(SWFS_ERR_VALUE, "%s: output %zu's function at sample (%zu, %zu) inside the pupil %s; "
                               "expected finite values", what, a, q % n, q / n, swfs_value_words(inf[a * nq + q], val, sizeof val));
                break;
            }
    double ws = 0;
    for (size_t q = 0; !rc && q < nq; q++) ws += mask[q] > 0 ? mask[q] : 0;
    if (!rc && !(ws > 0)) rc = swfs_fail(SWFS_ERR_VALUE, "%s: an empty pupil mask", what);
    /* each function's piston, tip and tilt out over the mask, then blocks of NB samples, each
     * weighted by sqrt(mask / its sum), into M by rank-NB updates */
    for (size_t a = 0; !rc && a < na; a++) swfs_wfe_remove_ptt(inf + a * nq, mask, n);
    enum { NB = 2048 };
    double *m = rc ? NULL : calloc(na * na, sizeof *m), *blk = rc ? NULL : malloc(na * NB * sizeof *blk);
    if (!rc && (!m || !blk)) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t q = 0; !rc && q < nq;) {
        size_t nb = 0;
        for (; q < nq && nb < NB; q++) {
            if (!(mask[q] > 0)) continue;
            const double w = sqrt(mask[q] / ws);
            for (size_t a = 0; a < na; a++) blk[a * NB + nb] = w * inf[a * nq + q];
            nb++;
        }
        if (nb) cblas_dsyrk(CblasRowMajor, CblasUpper, CblasNoTrans, (int)na, (int)nb, 1.0, blk, NB, 1.0, m, (int)na);
    }
    for (size_t a = 0; !rc && a < na; a++)
        for (size_t b = 0; b < a; b++) m[a * na + b] = m[b * na + a];
    free(blk);
    if (rc) {
        free(m);
        return rc;
    }
    *M = m;
    return SWFS_OK;
}

int swfs_meanmiss_metric(const char *funcs, size_t n, const double *mask, const char *pupil, double **M, size_t *nf)
{
    *M = NULL;
    *nf = 0;
    if (!funcs || (!mask && !pupil))
        return swfs_fail(SWFS_ERR_ARG, "the mean's miss's metric: needs the outputs' functions and a pupil mask");
    swfs_real *inf = NULL, *pm = NULL;
    int rc = swfs_fits_read_real(funcs, NULL, &inf, NULL);
    if (!rc && n == 0) n = inf->nx;
    if (!rc && (inf->nx != n || inf->ny != n || inf->nz < 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the outputs' functions are %zu x %zu x %zu; expected %zu x %zu (the pupil "
                       "grid) per output", funcs, inf->nx, inf->ny, inf->nz, n, n);
    if (!rc && !mask && !(rc = swfs_pupil_mask_read(pupil, n, &pm))) mask = pm->data;
    double ws = 0;
    for (size_t q = 0; !rc && q < n * n; q++) ws += mask[q] > 0 ? mask[q] : 0;
    if (!rc && !(ws > 0)) rc = swfs_fail(SWFS_ERR_VALUE, "%s: an empty pupil mask", pupil ? pupil : "the mean's miss's metric");
    if (!rc) rc = swfs_meanmiss_metric_data_(inf->data, inf->nz, n, mask, funcs, M);
    if (!rc) *nf = inf->nz;
    swfs_real_free(inf);
    swfs_real_free(pm);
    return rc;
}

/* The map's miss of the residual's time mean (swfs_learn_run_result.meanmiss_*): each data
 * set's mean slopes (as the map takes them: projected) and mean truth, summed over its files;
 * the miss is the truth's mean less the map applied to the slopes' mean at every lag (the
 * stacked mean input), piston removed unless modal. *off: their mean over the sets where the
 * held-out check keeps it, else NULL. */
static int mean_miss(const swfs_learn_run_options *o, const swfs_recon *w, const swfs_recon_learner *all,
                     swfs_learn_run_result *r, double **off)
{
    *off = NULL;
    const size_t ns = r->nslopes, na = r->nact, nd = o->ndirs, nl = o->nlags > 1 ? o->nlags : 1;
    double *ms = malloc(ns * nl * sizeof *ms), *mt = malloc(na * sizeof *mt), *miss = calloc(nd * na, sizeof *miss);
    int rc = ms && mt && miss ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "learn: out of memory");
    /* mean_miss_heldout: each set's miss by the map of the others (its sums left out) */
    swfs_recon_learner *part = NULL;
    if (!rc && o->mean_miss_heldout) rc = swfs_recon_learner_new(ns * nl, na, !o->modal, &part);
    for (size_t d = 0; !rc && d < nd; d++) {
        swfs_recon *wd = NULL;
        if (part) {
            swfs_recon_learner_reset(part);
            rc = add_dir(o, o->dirs[d], &part, r, NULL, NULL);
            if (!rc) rc = swfs_recon_learner_solve_without(all, part, o->ridge, &wd);
            if (rc) break;
        }
        const swfs_recon *wm = wd ? wd : w;
        memset(ms, 0, ns * sizeof *ms);
        memset(mt, 0, na * sizeof *mt);
        size_t nf = 0;
        for (size_t k = 0; !rc; k++) {
            char sp[4200], tp[4200];
            snprintf(sp, sizeof sp, "%.4000s/slopes_%03zu.fits", o->dirs[d], k);
            snprintf(tp, sizeof tp, "%.4000s/truewf_%03zu.fits", o->dirs[d], k);
            if (access(sp, F_OK) != 0) break;
            swfs_real *s = NULL, *z = NULL;
            rc = swfs_fits_read_real(sp, NULL, &s, NULL);
            if (!rc) rc = swfs_fits_read_real(tp, NULL, &z, NULL);
            if (!rc && (s->nx != ns || z->nx != na || s->ny != z->ny))
                rc = swfs_fail(SWFS_ERR_SHAPE, "%s / %s: changed since they were learned from", sp, tp);
            if (!rc && o->project) rc = swfs_modal_project_(o->project, o->nproject, s, sp);
            for (size_t t = 0; !rc && t < s->ny; t++) {
                for (size_t i = 0; i < ns; i++) ms[i] += s->data[t * ns + i];
                for (size_t a = 0; a < na; a++) mt[a] += z->data[t * na + a];
            }
            if (!rc) nf += s->ny;
            swfs_real_free(s);
            swfs_real_free(z);
        }
        if (rc || !nf) {
            swfs_recon_free(wd);
            continue;
        }
        /* the stacked input: the mean at every lag; m = (truth's sum - W input) / nf */
        for (size_t k = 1; k < nl; k++) memcpy(ms + k * ns, ms, ns * sizeof *ms);
        double *m = miss + d * na, pm = 0;
        memcpy(m, mt, na * sizeof *m);
        cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)na, (int)(ns * nl), -1.0, wm->W, (int)(ns * nl), ms, 1, 1.0, m, 1);
        swfs_recon_free(wd);
        for (size_t a = 0; a < na; a++) {
            m[a] /= (double)nf;
            pm += m[a] / (double)na;
        }
        for (size_t a = 0; !o->modal && a < na; a++) m[a] -= pm;
    }
    double e0 = 0;
    double *work = !rc && o->meanmiss_metric ? malloc(2 * na * sizeof *work) : NULL;
    if (!rc && o->meanmiss_metric && !work) rc = swfs_fail(SWFS_ERR_NOMEM, "learn: out of memory");
    const double ratio = rc ? NAN : swfs_heldout_mean_(miss, nd, na, NULL, o->meanmiss_metric, work, mt, &e0);
    free(work);
    if (!rc && isfinite(ratio)) {
        double ss = 0;
        for (size_t a = 0; a < na; a++) ss += mt[a] * mt[a];
        r->meanmiss_heldout = ratio;
        r->meanmiss_set_rms = sqrt(e0 / (double)(o->meanmiss_metric ? nd : nd * na));
        r->meanmiss_rms = sqrt(ss / (double)na);
        r->meanmiss_kept = r->meanmiss_heldout < 1;
        if (r->meanmiss_kept) { *off = mt; mt = NULL; }
    }
    swfs_recon_learner_free(part);
    free(ms);
    free(mt);
    free(miss);
    return rc;
}

int swfs_learn_run(const swfs_learn_run_options *o, swfs_learn_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->heldout_misfit_rms = r->heldout_truth_rms = r->heldout_worst = r->heldout_scaled_rms = NAN;
    r->curve_m2[0] = r->curve_m2[1] = r->curve_s2[0] = r->curve_s2[1] = r->curve_a = r->curve_b = r->curve_excess = NAN;
    r->curve_fall_se = NAN;
    r->wind_vx = r->wind_vy = r->wind_spread = NAN;
    r->meanmiss_heldout = r->meanmiss_rms = r->meanmiss_set_rms = NAN;
    for (size_t k = 0; k < SWFS_RECON_MAXLAGS; k++) r->corr[k] = r->corr_spread[k] = NAN;
    if (!o->ndirs || !o->dirs || !o->out) return swfs_fail(SWFS_ERR_ARG, "learn: needs simulated data sets and an output");
    if (o->nlags && (!o->lags || o->nlags > SWFS_RECON_MAXLAGS))
        return swfs_fail(SWFS_ERR_ARG, "learn: %zu lags (at most %d)", o->nlags, SWFS_RECON_MAXLAGS);
    int rc = o->nlags ? swfs_lags_check(o->lags, o->nlags, "learn: --lags") : SWFS_OK;
    if (!rc && o->nlags > 1 && o->modal)
        rc = swfs_fail(SWFS_ERR_ARG, "learn: --lags makes a space-time map for the Shack-Hartmann model (speckles "
                       "--recon); a modal control matrix (--modal) acts on one frame");
    if (!rc && o->prior && o->nlags > 1)
        rc = swfs_fail(SWFS_ERR_ARG, "learn: --prior is a per-frame map; a space-time learn (--lags) takes none");
    if (!rc && !(o->ridge > 0 && o->ridge <= 1e30))
        rc = swfs_fail(SWFS_ERR_ARG, "learn: ridge %g; expected a fraction > 0 and at most 1e30 of the normal equations' "
                       "mean diagonal", o->ridge);
    if (rc) return rc;
    swfs_paths *paths = NULL;
    rc = swfs_paths_create(&paths);
    if (!rc && o->prior) rc = swfs_paths_input(paths, "prior map (--prior)", o->prior);
    for (size_t d = 0; !rc && d < o->ndirs; d++) {
        rc = swfs_paths_input_or_dir(paths, "simulated data set", o->dirs[d]);
        if (!rc) rc = dir_inputs(paths, o->dirs[d]);
    }
    if (!rc) rc = swfs_paths_output(paths, "output reconstructor", o->out);
    if (!rc && o->perframe_out && o->nlags > 1) rc = swfs_paths_output(paths, "output per-frame reconstructor", o->perframe_out);
    swfs_paths_free(paths);
    /* the mean's miss's metric against the first truth file's outputs, before the sums (every
     * data set has that many: add_pair) */
    if (!rc && o->meanmiss_metric) {
        char tp[4200];
        snprintf(tp, sizeof tp, "%.4000s/truewf_000.fits", o->dirs[0]);
        swfs_fits_in *f = NULL;
        if (swfs_fits_in_open(&f, tp, NULL)) {
            swfs_clear_error(); /* an unreadable file is add_dir's to name */
        } else if (swfs_fits_in_shape(f)->nx != o->meanmiss_metric_n) {
            rc = swfs_fail(SWFS_ERR_SHAPE, "learn: the mean's miss's metric is %zu x %zu; the truth has %zu outputs "
                           "(%s; a metric from functions takes one per output)", o->meanmiss_metric_n,
                           o->meanmiss_metric_n, swfs_fits_in_shape(f)->nx, tp);
        }
        swfs_fits_in_close(f);
    }
    if (rc) return rc;
    swfs_recon_learner *l = NULL;
    set_stats *sets = o->nlags > 1 ? calloc(o->ndirs, sizeof *sets) : NULL;
    if (o->nlags > 1 && !sets) rc = swfs_fail(SWFS_ERR_NOMEM, "learn: out of memory");
    /* with the curve, the sets dealt into four parts' sums, then merged */
    const int curve = o->curve && o->ndirs >= 4;
    swfs_recon_learner *q[4] = {NULL, NULL, NULL, NULL};
    if (curve) {
        if (!rc) rc = add_parts(o, q, r, sets);
    } else {
        for (size_t d = 0; !rc && d < o->ndirs; d++) {
            rc = add_dir(o, o->dirs[d], &l, r, &r->nfiles, sets ? sets + d : NULL);
            if (!rc) rc = swfs_progress_report(o->progress, o->progress_ctx, "read", d + 1, o->ndirs);
        }
        if (!rc) rc = set_prior(o, l);
    }
    /* the outputs the checks (curve and held out) are measured on: those within the annulus */
    unsigned char *keep = NULL;
    if (!rc) rc = check_outputs(o, r, &keep);
    if (!rc && curve) {
        rc = swfs_recon_learner_new(r->nslopes * (o->nlags > 1 ? o->nlags : 1), r->nact, !o->modal, &l);
        for (int k = 0; !rc && k < 4; k++) rc = swfs_recon_learner_merge(l, q[k]);
        if (!rc) rc = set_prior(o, l);
        if (!rc) rc = learning_curve(o, l, q, keep, r);
    }
    for (int k = 0; k < 4; k++) swfs_recon_learner_free(q[k]);
    if (!rc && sets) training_stats(sets, o, r);
    free(sets);
    swfs_recon *w = NULL;
    if (!rc) rc = swfs_recon_learner_solve(l, o->ridge, &w, &r->info);
    if (!rc && o->nlags > 1) {
        w->nlags = o->nlags;
        memcpy(w->lags, o->lags, o->nlags * sizeof *o->lags);
    }
    if (!rc) rc = truth_points(o, r->nact, &w->oxy);
    /* with lags, the per-frame map of the same frames from the lag-0 block of the same sums */
    swfs_recon *w0 = NULL;
    size_t k0 = 0;
    while (o->nlags > 1 && k0 + 1 < o->nlags && o->lags[k0] != 0) k0++;
    if (!rc && o->perframe_out && o->nlags > 1) rc = swfs_recon_learner_solve_lag(l, k0, o->ridge, &w0, &r->perframe_info);
    if (!rc && w0 && w->oxy) {
        if (!(w0->oxy = malloc(2 * w->nact * sizeof *w0->oxy))) rc = swfs_fail(SWFS_ERR_NOMEM, "learn: out of memory");
        else memcpy(w0->oxy, w->oxy, 2 * w->nact * sizeof *w0->oxy);
    }
    if (!rc && o->ndirs > 1 && !o->no_heldout) rc = heldout(o, l, keep, r);
    free(keep);
    double *meanmiss = NULL;
    if (!rc && o->mean_miss && o->ndirs > 1) rc = mean_miss(o, w, l, r, &meanmiss);
    if (!rc && w0) rc = write_recon(o, o->perframe_out, w0, r, 1, NULL);
    if (!rc) {
        rc = write_recon(o, o->out, w, r, 0, meanmiss);
        if (rc && w0) unlink(o->perframe_out); /* both maps or neither */
    }
    free(meanmiss);
    swfs_recon_free(w0);
    swfs_recon_free(w);
    swfs_recon_learner_free(l);
    return rc;
}

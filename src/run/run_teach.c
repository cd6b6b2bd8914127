/* teach: a learned map for one observation from simulated closed loops of the described
 * system at the layers its slopes show, chosen by the space-time map's checks (run.h). */
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/interp.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/parallel.h"
#include "specklewfs/plot.h"
#include "specklewfs/report.h"
#include "specklewfs/rng.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/table.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <dirent.h>
#include <errno.h>
#include <stdarg.h>
#include <math.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

void swfs_teach_run_options_default(swfs_teach_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_ts_params_default(&o->sim);
    o->nloops = 12;
    o->seed = 101;
}

void swfs_spacetime_lags_(double frames, long *lags)
{
    long l1 = frames > 0 ? lround(frames) : 1;
    if (l1 < 1) l1 = 1;
    const long l[SWFS_SPACETIME_NLAGS] = {0, -l1, l1, -2 * l1, 2 * l1};
    memcpy(lags, l, sizeof l);
}

static int stage(const swfs_teach_run_options *o, const char *what, size_t done, size_t total)
{
    return swfs_progress_report(o->progress, o->progress_ctx, what, done, total);
}

/* One loop: work/name_NN, the system with these layers and this seed, the truth exported. */
typedef struct loop_job {
    char name[8];
    size_t k;
    uint64_t seed;
    int nl;
    double frac[SWFS_TS_MAX_LAYERS], speed[SWFS_TS_MAX_LAYERS], dir[SWFS_TS_MAX_LAYERS];
    double rcond;        /* > 0: a zonal loop at this cut (simulate's ao_rcond); 0: the description's */
    char path[4200];
    int rc;
    char why[1024];      /* the failure's message (a worker's own thread holds it) */
} loop_job;

typedef struct loops_ctx {
    const swfs_teach_run_options *o;
    loop_job *jobs;
    int inner;           /* each simulation's own threads */
    const swfs_ts_shared *shared; /* the plans every loop's system shares, or NULL */
    const char *stage;
    size_t njobs;
    atomic_size_t done;  /* loops finished, over the workers */
    int truth;           /* simulate_loop's truth */
    atomic_int stop;     /* the caller's progress asked to stop: every loop ends at its next report */
} loops_ctx;

/* A loop simulation's own progress (every 256 WFS frames): on the caller's thread (worker 0)
 * the caller's callback is shown the loops' count again, so that a request to stop is seen
 * within a loop, not only between loops; on every worker the answer is whether to stop. */
typedef struct loop_poll {
    loops_ctx *c;
    int worker;
} loop_poll;

static int loop_progress(void *ctx, const char *stage, size_t done, size_t total)
{
    (void)stage, (void)done, (void)total;
    const loop_poll *lp = ctx;
    loops_ctx *c = lp->c;
    if (!lp->worker && c->o->progress && c->o->progress(c->o->progress_ctx, c->stage, atomic_load(&c->done), c->njobs))
        atomic_store(&c->stop, 1);
    return atomic_load(&c->stop);
}

/* A loop's folder from an earlier teach in the same work folder (`speckles` teaches into
 * OUT.teach each run) may hold more slopes / truewf files than this loop writes, and learn
 * reads every pair it finds: every slopes_NNN.fits and truewf_NNN.fits the new loop does not
 * replace goes, whatever its number (a gap in the numbers included) -- once the new loop's
 * files are in place, so that a loop that fails or is stopped leaves the earlier one whole.
 * The files there before the loop, by name and inode (the atomic writer's rename gives a
 * replaced file a new one). */
typedef struct loop_files {
    char (*name)[16];
    ino_t *ino;
    size_t n;
} loop_files;

static int loop_files_list(const char *path, loop_files *lf)
{
    memset(lf, 0, sizeof *lf);
    DIR *d = opendir(path);
    if (!d) return errno == ENOENT ? SWFS_OK : swfs_fail(SWFS_ERR_IO, "teach: cannot read %s: %s", path, strerror(errno));
    int rc = SWFS_OK;
    size_t cap = 0;
    for (struct dirent *e; !rc && (e = readdir(d));) {
        unsigned k = 0;
        char tail[8] = "", f[4400];
        struct stat st;
        if ((sscanf(e->d_name, "slopes_%3u%7s", &k, tail) != 2 && sscanf(e->d_name, "truewf_%3u%7s", &k, tail) != 2) ||
            strcmp(tail, ".fits") || strlen(e->d_name) != 15)
            continue;
        snprintf(f, sizeof f, "%s/%s", path, e->d_name);
        if (stat(f, &st)) continue; /* gone meanwhile */
        if (lf->n == cap) {
            cap = cap ? 2 * cap : 64;
            char(*nn)[16] = realloc(lf->name, cap * sizeof *nn);
            if (nn) lf->name = nn;
            ino_t *ni = nn ? realloc(lf->ino, cap * sizeof *ni) : NULL;
            if (ni) lf->ino = ni;
            if (!nn || !ni) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        }
        if (!rc) {
            memcpy(lf->name[lf->n], e->d_name, 16);
            lf->ino[lf->n++] = st.st_ino;
        }
    }
    closedir(d);
    return rc;
}

/* lf's files that the new loop did not replace (still the same inode), removed. */
static int loop_files_drop_stale(const char *path, const loop_files *lf)
{
    int rc = SWFS_OK;
    for (size_t i = 0; !rc && i < lf->n; i++) {
        char f[4400];
        struct stat st;
        snprintf(f, sizeof f, "%s/%s", path, lf->name[i]);
        if (stat(f, &st) || st.st_ino != lf->ino[i]) continue;
        if (remove(f) && errno != ENOENT) rc = swfs_fail(SWFS_ERR_IO, "teach: cannot remove %s: %s", f, strerror(errno));
    }
    return rc;
}

/* One loop of the description at job j's layers and seed into work/NAME_NN; truth: with the
 * true residual (export_truth: the maps' training target), which the calibration loops, read
 * for their slopes only, go without (the slopes are the same either way). */
static int simulate_loop(const swfs_teach_run_options *o, loop_job *j, int threads, const swfs_ts_shared *shared,
                         int truth, loop_poll *poll)
{
    swfs_ts_params p = o->sim;
    p.nlayers = j->nl;
    for (int l = 0; l < j->nl; l++) {
        p.layer_frac[l] = j->frac[l];
        p.layer_speed[l] = j->speed[l];
        p.layer_dir[l] = j->dir[l];
    }
    if (j->rcond > 0) p.ao_rcond = j->rcond;
    p.base.seed = j->seed;
    p.base.threads = threads;
    p.export_truth = truth;
    p.export_modal = 0;
    p.milk = 0;
    if (snprintf(j->path, sizeof j->path, "%.4000s/%s_%02zu", o->work, j->name, j->k) >= (int)sizeof j->path)
        return swfs_fail(SWFS_ERR_ARG, "teach: %s: the folder's name is too long", o->work);
    const int made = mkdir(j->path, 0777) == 0;
    if (!made && errno != EEXIST)
        return swfs_fail(SWFS_ERR_IO, "teach: cannot create %s: %s", j->path, strerror(errno));
    loop_files before = {NULL, NULL, 0};
    int rc = swfs_ts_params_check(&p);
    if (!rc) rc = loop_files_list(j->path, &before);
    swfs_ts_summary sum;
    swfs_outputs_begin(); /* the loop's files all renamed into place, or none (atomic.h) */
    if (!rc) rc = swfs_ts_run_shared(&p, shared, j->path, o->prov, o->nprov, loop_progress, poll, &sum);
    int erc = swfs_outputs_end(rc == SWFS_OK);
    if (!rc && !erc) erc = loop_files_drop_stale(j->path, &before);
    free(before.name);
    free(before.ino);
    if ((rc || erc) && made) (void)rmdir(j->path); /* the folder this loop made, left empty */
    if (rc || erc) return swfs_fail_context(rc ? rc : erc, "teach: the loop in %s", j->path);
    return SWFS_OK;
}

/* Workers over the loops (parallel.h: worker 0 is the caller's thread, which reports the
 * loops finished by all of them). */
static void loops_worker(void *ctx, size_t begin, size_t end, int worker)
{
    loops_ctx *c = ctx;
    loop_poll poll = {c, worker};
    for (size_t i = begin; i < end; i++) {
        loop_job *j = c->jobs + i;
        if (atomic_load(&c->stop)) {
            j->rc = SWFS_ERR_STOPPED;
            snprintf(j->why, sizeof j->why, "%s: stopped by the caller at %zu of %zu", c->stage, atomic_load(&c->done),
                     c->njobs);
            continue;
        }
        j->rc = simulate_loop(c->o, j, c->inner, c->shared, c->truth, &poll);
        if (j->rc) snprintf(j->why, sizeof j->why, "%s", swfs_last_error());
        if (j->rc == SWFS_ERR_STOPPED) continue;
        const size_t done = atomic_fetch_add(&c->done, 1) + 1;
        if (!worker && swfs_progress_report(c->o->progress, c->o->progress_ctx, c->stage, done, c->njobs))
            atomic_store(&c->stop, 1);
    }
}

/* The jobs' loops, as many at once as the simulator's threads allow (sim.base.threads; each
 * loop's own simulation then single-threaded): every loop is the same whatever runs beside
 * it. The first failure's message, with its loop named. */
static int simulate_loops(const swfs_teach_run_options *o, const swfs_ts_shared *shared, loop_job *jobs, size_t n,
                          const char *stage, size_t *nrun, int truth)
{
    const int nt = swfs_parallel_threads(o->sim.base.threads, n);
    loops_ctx c = {o, jobs, nt > 1 ? 1 : o->sim.base.threads, shared, stage, n, 0, truth, 0};
    int rc = swfs_progress_report(o->progress, o->progress_ctx, stage, 0, n);
    if (rc) return rc;
    swfs_parallel_for(nt, n, 1, loops_worker, &c);
    /* the first loop that failed on its own, else the request to stop */
    for (size_t i = 0; i < n; i++)
        if (jobs[i].rc && jobs[i].rc != SWFS_ERR_STOPPED) return swfs_fail(jobs[i].rc, "%s", jobs[i].why);
    if (atomic_load(&c.stop))
        return swfs_fail(SWFS_ERR_STOPPED, "%s: stopped by the caller after %zu of %zu loops", stage, atomic_load(&c.done), n);
    *nrun += n;
    return SWFS_OK;
}

/* run_internal.h: loops first..first+n-1 of the description as it is (speckles --mean-loop
 * teach; with its true residual where the description exports it). */
int swfs_teach_loops_(const swfs_teach_run_options *o, const char *name, size_t first, size_t n, const char *what)
{
    loop_job *jobs = calloc(n ? n : 1, sizeof *jobs);
    if (!jobs) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t k = 0; k < n; k++) {
        loop_job *j = jobs + k;
        snprintf(j->name, sizeof j->name, "%s", name);
        j->k = first + k;
        j->seed = o->seed + first + k;
        j->nl = o->sim.nlayers;
        for (int l = 0; l < j->nl; l++) {
            j->frac[l] = o->sim.layer_frac[l];
            j->speed[l] = o->sim.layer_speed[l];
            j->dir[l] = o->sim.layer_dir[l];
        }
    }
    size_t nrun = 0;
    const int rc = simulate_loops(o, NULL, jobs, n, what, &nrun, o->sim.export_truth ? 1 : 0);
    free(jobs);
    return rc;
}

/* A loop layer's speed about v: within a factor sqrt 2 of it, log-uniform (one draw of g). The
 * loops of both paths take their speeds so: a map learned from loops of one speed fits that
 * speed's frames too closely (docs/telemetry.md, "Loops at speeds about the layers'"). */
static double speed_about(double v, swfs_rng *g)
{
    return v * pow(2.0, swfs_rng_uniform(g) - 0.5);
}

/* Loop k of the space-time set: the layers found, each at a speed about the one found
 * (speed_about, drawn for the loop), the first one's share 0.3 + 0.4 u (u in [0, 1]; the
 * others share the rest), seed o->seed + k. */
static void loop_init(loop_job *j, const swfs_teach_run_options *o, size_t k, double u, int nl, const double *speed,
                      const double *dir)
{
    snprintf(j->name, sizeof j->name, "loop");
    j->k = k;
    j->seed = o->seed + k;
    j->nl = nl;
    j->frac[0] = nl > 1 ? 0.3 + 0.4 * u : 1.0;
    swfs_rng g;
    swfs_rng_seed2(&g, o->seed, 3000 + k);
    for (int l = 0; l < nl; l++) {
        if (l) j->frac[l] = (1.0 - j->frac[0]) / (double)(nl - 1);
        j->speed[l] = speed_about(speed[l], &g);
        j->dir[l] = dir[l];
    }
}

/* Loop k where no layer was tracked: two layers, the first one's share 0.3-0.7, each at a
 * speed about v (speed_about) in any direction, seed o->seed + k. */
static void prior_init(loop_job *j, const swfs_teach_run_options *o, size_t k, double v)
{
    swfs_rng g;
    swfs_rng_seed2(&g, o->seed, 2000 + k);
    snprintf(j->name, sizeof j->name, "prior");
    j->k = k;
    j->seed = o->seed + k;
    j->nl = 2;
    j->frac[0] = 0.3 + 0.4 * swfs_rng_uniform(&g);
    j->frac[1] = 1.0 - j->frac[0];
    for (int l = 0; l < 2; l++) {
        j->speed[l] = speed_about(v, &g);
        j->dir[l] = 360.0 * swfs_rng_uniform(&g);
    }
}

/* The projection the observation's slopes went through (modal-slopes' MODALCM), applied to the
 * loops' slopes as they are learned: P (ns x ns) or NULL. */
typedef struct projection {
    double *P;
    size_t n;
} projection;

static int learn(const swfs_teach_run_options *o, const projection *pj, const loop_job *jobs, size_t n,
                 const long *lags, size_t nlags, const char *out, const char *perframe_out, int curve,
                 swfs_learn_run_result *lr)
{
    const char *d[64];
    for (size_t k = 0; k < n; k++) d[k] = jobs[k].path;
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = d;
    lo.ndirs = n;
    lo.out = out;
    lo.no_heldout = 1;
    lo.lags = nlags > 1 ? lags : NULL;
    lo.nlags = nlags > 1 ? nlags : 0;
    lo.perframe_out = perframe_out;
    lo.curve = curve;
    /* the curve over the points in the pupil (the truth outside it is the fit's extrapolation) */
    lo.curve_radius[0] = 0.5 * o->sim.base.obscur * o->sim.base.teldiam;
    lo.curve_radius[1] = 0.5 * o->sim.base.teldiam;
    lo.prov = o->prov;
    lo.nprov = o->nprov;
    lo.project = pj->P;
    lo.nproject = pj->n;
    lo.threads = o->sim.base.threads;
    const int rc = swfs_learn_run(&lo, lr);
    return rc ? swfs_fail_context(rc, "teach: the %s map of %zu loops (more loops: --loops; or longer ones: ncubes, cube_gap)",
                                  nlags > 1 ? "space-time" : "per-frame", n) : SWFS_OK;
}

/* The chosen map onto o->out (atomic.h: the whole file or none), with what chose it. */
const char *const swfs_teach_chosen_names_[5] = {"spacetime", "perframe", "perframe_mixed", "perframe_prior",
                                                  "spacetime_prior"};

static int write_chosen(const char *from, const swfs_teach_run_options *o, const swfs_teach_run_result *r)
{
    swfs_fits_out *f = NULL;
    int rc = swfs_fits_out_copy(&f, from, o->out);
    if (!rc) rc = swfs_fits_out_key_string(f, "TEACHSEL", swfs_teach_chosen_names_[r->chosen], "teach chose: spacetime(_prior), perframe(_mixed)");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHLOO", (long)r->nloops, "teach: loops simulated");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHLAY", (long)r->nlayers, "teach: layers found and given to the loops");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHSTL", (long)r->st_loops, "teach: the chosen kind of map's loops");
    if (!rc && r->curve_first.curve_n[0])
        rc = swfs_fits_out_key_double(f, "TEACHLC1", isfinite(r->curve_first.curve_excess) ? r->curve_first.curve_excess
                                      : -1.0, "learning curve excess, first loops (-1: unbounded)");
    if (!rc && r->curve_doubled.curve_n[0])
        rc = swfs_fits_out_key_double(f, "TEACHLCD", isfinite(r->curve_doubled.curve_excess)
                                      ? r->curve_doubled.curve_excess : -1.0,
                                      "learning curve excess, doubled loops (-1: unbounded)");
    if (!rc && r->coupling_done)
        rc = swfs_fits_out_key_double(f, "TEACHCPL", r->coupling.gaussian ? r->coupling.coupling : 0.0,
                                      "teach: the loops' DM coupling from ao_recon (0: surface)");
    if (!rc && r->asked_loops)
        rc = swfs_fits_out_key_long(f, "TEACHASK", (long)r->asked_loops,
                                    "teach: loops a curve asked for, whose own had no bound");
    if (!rc && r->curve.curve_n[0])
        rc = swfs_fits_out_key_double(f, "TEACHLCE", isfinite(r->curve.curve_excess) ? r->curve.curve_excess : -1.0,
                                      "learning curve excess, all loops (-1: unbounded)");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHWRN", r->warns, "teach: checks warned (1 wind, 2 corr.)");
    if (!rc) rc = swfs_fits_out_key_double(f, "TEACHMIS", r->check.st_mismatch, "[subap] layers apart at the largest lag");
    if (!rc) rc = swfs_fits_out_key_double(f, "TEACHCEX", r->check.st_corr_excess, "correlation beyond 3 spreads (> 0 warns)");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHMOD", (long)r->ao_modes, "teach: the loops' controlled modes (ao_modes)");
    if (!rc) rc = swfs_fits_out_key_string(f, "TEACHMSR", o->sim.ao_recon[0] ? "ao_recon" : r->zonal ? "zonal" :
                                           o->sim.ao_rcond > 0 ? "ao_rcond" : o->modes_from_slopes ? "slopes" : "given",
                                           "filter: ao_modes given, knee, ao_recon, zonal, ao_rcond");
    const double zmf = r->zonal_misfit[r->zonal_best];
    if (!rc && r->zonal) rc = swfs_fits_out_key_double(f, "TEACHRCO", o->sim.ao_rcond, "the zonal loops' ao_rcond");
    if (!rc && o->modes_from_slopes && isfinite(r->misfit_modal) && isfinite(zmf) &&
        !(rc = swfs_fits_out_key_double(f, "TEACHMMF", r->misfit_modal, "modal loop's profile misfit (rms log10)")))
        rc = swfs_fits_out_key_double(f, "TEACHZMF", zmf, "zonal loop's profile misfit (rms log10)");
    if (!rc && o->modes_from_slopes)
        rc = swfs_fits_out_key_long(f, "TEACHKNE", (long)r->knee_obs, "the observation's mode-variance knee");
    if (!rc && r->chosen == SWFS_TEACH_SPACETIME_PRIOR)
        rc = swfs_fits_out_key_double(f, "TEACHPSP", r->prior_speed, "[m/s] loops' speed from the slopes' time corr.");
    if (!rc) rc = swfs_fits_out_key_double(f, "TEACHNOI", r->noise_rms, "[rad] the observation's white slope noise");
    if (!rc) rc = swfs_fits_out_key_double(f, "TEACHSNO", r->slope_noise, "[rad] the loops' slope_noise");
    if (!rc) rc = swfs_fits_out_key_long(f, "TEACHNOP", (long)r->out_points, "teach: the map's output points (OUTXY)");
    if (!rc) rc = swfs_fits_out_key_double(f, "TEACHOPI", r->out_pitch, "[m] their pitch");
    if (!rc && r->dm_pitch > 0) rc = swfs_fits_out_key_double(f, "TEACHDMP", r->dm_pitch, "[m] the DM's pitch");
    if (!rc && o->fingerprint)
        rc = swfs_fits_out_key_string(f, "TEACHFPR", o->fingerprint, "the inputs taught for (speckles reuses)");
    if (rc) { swfs_fits_out_abort(f); return rc; }
    return swfs_fits_out_commit(f);
}

static int check_options(const swfs_teach_run_options *o)
{
    if (!o->nfiles || !o->files) return swfs_fail(SWFS_ERR_ARG, "teach: no telemetry files of the observation");
    if (!o->out || !o->work) return swfs_fail(SWFS_ERR_ARG, "teach: no output map or no work folder");
    if (o->nloops < 2 || o->nloops > 64) return swfs_fail(SWFS_ERR_VALUE, "teach: %zu loops; expected 2 to 64", o->nloops);
    if (o->max_loops && (o->max_loops < o->nloops || o->max_loops > 64))
        return swfs_fail(SWFS_ERR_VALUE, "teach: at most %zu loops for %zu first ones; expected %zu to 64 (0: 4 times "
                         "the first, at most 64)", o->max_loops, o->nloops, o->nloops);
    if (o->modes_from_slopes && o->sim.ao_recon[0])
        return swfs_fail(SWFS_ERR_ARG, "teach: the modal filter from the slopes, but the loop's reconstructor %s is "
                         "given (ao_recon): one or the other", o->sim.ao_recon);
    if (o->modes_from_slopes && o->sim.ao_rcond > 0)
        return swfs_fail(SWFS_ERR_ARG, "teach: the loop's filter from the slopes, but a zonal loop is given "
                         "(ao_rcond=%g): one or the other", o->sim.ao_rcond);
    return swfs_ts_params_check(&o->sim);
}

/* The map's name against every file teach reads (the telemetry, the system's files): an output
 * that is one of them would overwrite it. */
static int check_paths(const swfs_teach_run_options *o)
{
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    for (size_t k = 0; !rc && k < o->nfiles; k++) rc = swfs_paths_input(paths, "telemetry", o->files[k]);
    const swfs_ts_params *sp = &o->sim;
    const struct { const char *role, *path; } sys[] = {
        {"the DM's actuators (actuators=)", sp->actuators}, {"the loop's reconstructor (ao_recon=)", sp->ao_recon},
        {"the valid-subaperture map (valid=)", sp->valid}, {"the pupil (pupil_mask=)", sp->base.pupil_mask},
        {"the truth's points (truth_actuators=)", sp->truth_actuators}};
    for (size_t k = 0; !rc && k < sizeof sys / sizeof sys[0]; k++)
        if (sys[k].path[0]) rc = swfs_paths_input(paths, sys[k].role, sys[k].path);
    if (!rc) rc = swfs_paths_output(paths, "the taught map (-o)", o->out);
    swfs_paths_free(paths);
    return rc ? swfs_fail_context(rc, "teach") : SWFS_OK;
}

/* The mode variances of the slopes s (nf frames of ns: the full layout, or the used
 * subapertures' with the system's valid map) and their knee. */
static int knee_of(const swfs_ts_params *p, const swfs_real *s, const char *what, double **v, size_t *n, size_t *knee)
{
    int rc = swfs_ts_mode_variance(p, s->data, s->ny, s->nx, v, n);
    if (rc) return swfs_fail_context(rc, "teach: the mode variances of %s", what);
    *knee = swfs_mode_knee(*v, *n);
    if (!*knee) return swfs_fail(SWFS_ERR_NUMERIC, "teach: %s: %zu DM modes after piston, too few for the knee of "
                                 "their variances (at least 6); give ao_modes", what, *n);
    return SWFS_OK;
}

/* A mode-variance profile written to modes.tsv and modes.png: its values, knee (0: none),
 * column name and legend. */
typedef struct profile {
    const double *v;
    size_t n, knee;
    char col[32], label[48];
} profile;

/* work/modes.tsv (mode, then each profile's variance: the observation's, each calibration
 * loop's, modal and zonal) and, where PLplot is, work/modes.png of the profiles plot[0..np):
 * what the loops' filter was read from. */
static int write_profiles(const char *work, const profile *p, size_t nc, const size_t *plot, size_t np)
{
    char path[4200];
    size_t len = 0, cap = 64 + 40 * nc + p[0].n * (24 + 16 * nc); /* "%.6e" is at most 13 characters */
    char *buf = malloc(cap);
    if (!buf) return swfs_fail(SWFS_ERR_NOMEM, "teach: out of memory");
    len += (size_t)snprintf(buf + len, cap - len, "# mode");
    for (size_t c = 0; c < nc; c++) len += (size_t)snprintf(buf + len, cap - len, "\t%s", p[c].col);
    len += (size_t)snprintf(buf + len, cap - len, "\n");
    for (size_t j = 0; j < p[0].n; j++) {
        len += (size_t)snprintf(buf + len, cap - len, "%zu", j + 1);
        for (size_t c = 0; c < nc; c++)
            len += (size_t)snprintf(buf + len, cap - len, j < p[c].n ? "\t%.6e" : "\tnan", j < p[c].n ? p[c].v[j] : 0.0);
        len += (size_t)snprintf(buf + len, cap - len, "\n");
    }
    snprintf(path, sizeof path, "%.4000s/modes.tsv", work);
    int rc = len < cap ? swfs_text_write(path, buf, len) : swfs_fail(SWFS_ERR_INTERNAL, "teach: modes.tsv overflow");
    free(buf);
    if (rc || !swfs_plot_available()) return rc;
    const double *v[6];
    const char *labels[6];
    size_t n[6], knee[6], k = 0;
    for (; k < np && k < 6; k++) {
        v[k] = p[plot[k]].v;
        n[k] = p[plot[k]].n;
        knee[k] = p[plot[k]].knee;
        labels[k] = p[plot[k]].label;
    }
    snprintf(path, sizeof path, "%.4000s/modes.png", work);
    return swfs_fig_modes(path, v, n, knee, labels, k);
}

const double swfs_teach_zonal_rcond[SWFS_TEACH_NZONAL] = {0.02, 0.03, 0.05, 0.07, 0.1, 0.2};

/* How far a calibration loop's mode variances (a, na) are from the observation's (b, nb)
 * where the filters differ: over the upper half of the modes (where both are positive and
 * finite), the rms of log10 a / b about its mean over all the modes. A modal filter of K
 * modes leaves the modes above K to the turbulence where a zonal loop controls them; the zonal
 * cuts differ in the highest modes only (265 to 323 of 330 kept on a 16 x 16 system from 0.2
 * to 0.02). The lower half differs between loops by their seeds and layers, and the level of
 * the whole profile by the layers' shares and speeds, which the slopes tell only roughly: on
 * one observation loops of one layer instead of its two raised every cut's profile by 0.3 in
 * log10, the plain rms then 0.30-0.33 for every cut from 0.02 to 0.07 (no choice left), the
 * rms about the mean still least at 0.05-0.07. The mean is the whole profile's: the level of
 * the upper half against the lower is what tells a filter that leaves the upper modes to the
 * turbulence from one that controls them (a zonal loop's flat profile a factor 10 below a
 * 200-mode observation's upper half was 0.139 from its own half's mean, below the 152-mode
 * loop's 0.147; from the whole profile's 0.42 against 0.149; docs/telemetry.md, "A zonal
 * loop"). */
double swfs_teach_profile_misfit_(const double *a, size_t na, const double *b, size_t nb)
{
    const size_t n = na < nb ? na : nb;
    double s = 0, s2 = 0, all = 0;
    size_t m = 0, mall = 0;
    for (size_t j = 0; j < n; j++)
        if (a[j] > 0 && b[j] > 0 && isfinite(a[j]) && isfinite(b[j])) {
            const double d = log10(a[j] / b[j]);
            all += d;
            mall++;
            if (j < nb / 2) continue;
            s += d;
            s2 += d * d;
            m++;
        }
    if (m < 2) return INFINITY;
    /* the upper half's mean square about the whole profile's mean c: var + (mean - c)^2 */
    const double mean = s / (double)m, c = all / (double)mall, ms = s2 / (double)m - 2 * c * mean + c * c;
    return sqrt(ms > 0 ? ms : 0);
}

/* A calibration loop's job: tmpl's layers (and zonal cut), work/NAME_NN, teach's seed. */
static void calibration_job(const swfs_teach_run_options *o, const loop_job *tmpl, const char *name, size_t k,
                            loop_job *j)
{
    *j = *tmpl;
    snprintf(j->name, sizeof j->name, "%s", name);
    j->k = k;
    j->seed = o->seed;
}

/* The slopes of a calibration loop simulated (calibration_job), projected as the
 * observation's were; f their file's path. */
static int calibration_read(const loop_job *j, const projection *pj, swfs_real **ls, char *f, size_t cap)
{
    *ls = NULL;
    snprintf(f, cap, "%s/slopes_000.fits", j->path);
    int rc = swfs_telemetry_read(f, 0, ls, NULL);
    if (!rc && pj && pj->P) rc = swfs_modal_project_(pj->P, pj->n, *ls, f);
    if (rc) {
        swfs_real_free(*ls);
        *ls = NULL;
    }
    return rc;
}

/* Calibration loops that do not wait for each other's results (the first modal loop and the
 * zonal cuts, the first speeds): simulated as the space-time set's loops are, as many at once
 * as the simulator's threads allow (simulate_loops; a loop is the same whatever runs beside
 * it: the files of a small-loop.conf simulation at threads=1 and threads=2 equal by
 * tests/tools/fitsdiff), read afterwards in their order. */
static int calibration_batch(const swfs_teach_run_options *o, loop_job *jobs, size_t n, const char *what)
{
    size_t nrun = 0;
    return simulate_loops(o, NULL, jobs, n, what, &nrun, 0);
}

/* A calibration loop simulated (calibration_job): its slopes' mode variances and knee. */
static int calibration_knee(const swfs_teach_run_options *o, const loop_job *j, double **v, size_t *n, size_t *knee)
{
    swfs_real *ls = NULL;
    char f[4300];
    int rc = calibration_read(j, NULL, &ls, f, sizeof f);
    if (!rc) rc = knee_of(&o->sim, ls, f, v, n, knee);
    swfs_real_free(ls);
    return rc;
}

/* One modal calibration loop of the description as o->sim has it now (work/modes_NN, tmpl's
 * layers, teach's seed; read for its slopes only): their mode variances and knee. A batch of
 * one (the simulator's threads inside the loop). */
static int calibration_loop(const swfs_teach_run_options *o, const loop_job *tmpl, size_t k, double **v, size_t *n,
                            size_t *knee)
{
    loop_job j;
    calibration_job(o, tmpl, "modes", k, &j);
    const int rc = calibration_batch(o, &j, 1, "the loop's modal filter (calibration loops)");
    return rc ? rc : calibration_knee(o, &j, v, n, knee);
}

/* The loops' modal filter from the observation (modes_from_slopes). The knee of its slopes'
 * mode variances can sit off the last controlled mode (the loop attenuating the modes near it
 * only partly, aliases); the system's own loop shows by how much. So: simulate a loop of K
 * modes (K first the knee), and take K times the observation's knee over the loop's until the
 * loop shows the observation's knee, K repeats, or four loops ran (then the K whose knee came
 * closest). On every system measured the first loop confirmed the knee (docs/telemetry.md).
 * A zonal loop (every mode the sensor sees controlled: the truncated pseudo-inverse of the
 * interaction matrix, simulate's ao_rcond) has no knee: its profile is flat, and the knee
 * found is anywhere. So zonal loops too, one per cut of swfs_teach_zonal_rcond, and the loops
 * get the filter whose loop's profile is the closest to the observation's (swfs_teach_profile_misfit_;
 * docs/telemetry.md, "A zonal loop"). tmpl: the loop's layers. */
static int modes_from_slopes(swfs_teach_run_options *o, const swfs_real *s, const loop_job *tmpl,
                             swfs_teach_run_result *r)
{
    double *v[5 + SWFS_TEACH_NZONAL] = {NULL}; /* the observation's profile, each modal calibration loop's,
                                                  each zonal loop's */
    size_t nv[5 + SWFS_TEACH_NZONAL] = {0}, zknee[SWFS_TEACH_NZONAL] = {0}, bi = 0;
    int rc = knee_of(&o->sim, s, o->files[0], &v[0], &nv[0], &r->knee_obs);
    long K = (long)r->knee_obs, best = K;
    size_t bdist = (size_t)-1;
    /* The first modal loop (K the knee) and the zonal loops, one per cut, at once
     * (calibration_batch): a zonal loop does not read ao_modes (the cut's pseudo-inverse of
     * the interaction matrix is its reconstructor; its files the same at any ao_modes). */
    loop_job bj[1 + SWFS_TEACH_NZONAL];
    calibration_job(o, tmpl, "modes", 0, &bj[0]);
    for (size_t z = 0; z < SWFS_TEACH_NZONAL; z++) {
        calibration_job(o, tmpl, "zonal", z, &bj[1 + z]);
        bj[1 + z].rcond = swfs_teach_zonal_rcond[z];
    }
    o->sim.ao_modes = K;
    if (!rc) rc = calibration_batch(o, bj, 1 + SWFS_TEACH_NZONAL, "the loop's filter (calibration loops)");
    for (size_t it = 0; !rc && it < 4; it++) {
        o->sim.ao_modes = K;
        size_t knee = 0;
        rc = it ? calibration_loop(o, tmpl, it, &v[it + 1], &nv[it + 1], &knee)
                : calibration_knee(o, &bj[0], &v[1], &nv[1], &knee);
        if (rc) break;
        r->cal_modes[it] = (size_t)K;
        r->cal_knee[it] = knee;
        r->ncal = it + 1;
        const size_t dist = knee > r->knee_obs ? knee - r->knee_obs : r->knee_obs - knee;
        if (dist < bdist) { bdist = dist; best = K; bi = it + 1; }
        if (!dist) break;
        long next = lround((double)K * (double)r->knee_obs / (double)knee);
        if (next < 1) next = 1;
        int seen = 0;
        for (size_t i = 0; i <= it; i++) seen |= (long)r->cal_modes[i] == next;
        if (seen) break;
        K = next;
    }
    o->sim.ao_modes = best;
    if (!rc) r->misfit_modal = swfs_teach_profile_misfit_(v[bi], nv[bi], v[0], nv[0]);
    for (size_t z = 0; !rc && z < SWFS_TEACH_NZONAL; z++) {
        if ((rc = calibration_knee(o, &bj[1 + z], &v[5 + z], &nv[5 + z], &zknee[z]))) break;
        r->zonal_misfit[z] = swfs_teach_profile_misfit_(v[5 + z], nv[5 + z], v[0], nv[0]);
        if (r->zonal_misfit[z] < r->zonal_misfit[r->zonal_best]) r->zonal_best = z;
    }
    const size_t zb = r->zonal_best;
    r->zonal = !rc && r->zonal_misfit[zb] < r->misfit_modal;
    o->sim.ao_rcond = r->zonal ? swfs_teach_zonal_rcond[zb] : 0;
    if (!rc) { /* the table: the observation, the modal loops, each zonal one; the plot: the
                  observation, the modal loops, the closest zonal one */
        profile p[5 + SWFS_TEACH_NZONAL] = {{v[0], nv[0], r->knee_obs, "observation", "observation"}};
        size_t plot[6], np = 0;
        plot[np++] = 0;
        for (size_t c = 0; c < r->ncal; c++) {
            p[c + 1] = (profile){v[c + 1], nv[c + 1], r->cal_knee[c], "", ""};
            snprintf(p[c + 1].col, sizeof p[c + 1].col, "loop_%zu", r->cal_modes[c]);
            snprintf(p[c + 1].label, sizeof p[c + 1].label, "loop of %zu modes", r->cal_modes[c]);
            plot[np++] = c + 1;
        }
        for (size_t z = 0; z < SWFS_TEACH_NZONAL; z++) {
            profile *pz = &p[1 + r->ncal + z];
            *pz = (profile){v[5 + z], nv[5 + z], zknee[z], "", ""};
            snprintf(pz->col, sizeof pz->col, "zonal_%g", swfs_teach_zonal_rcond[z]);
            snprintf(pz->label, sizeof pz->label, "zonal loop (ao_rcond %g)", swfs_teach_zonal_rcond[z]);
        }
        plot[np++] = 1 + r->ncal + zb;
        rc = write_profiles(o->work, p, 1 + r->ncal + SWFS_TEACH_NZONAL, plot, np);
    }
    for (size_t c = 0; c < 5 + SWFS_TEACH_NZONAL; c++) free(v[c]);
    return rc;
}

/* The slopes' time correlation along the upper half of the system's DM modes
 * (swfs_ts_mode_timecorr) at lags 1, 2, 4, ... under a quarter of the frames (at most
 * SWFS_TEACH_NTCORR). */
static int time_corr(const swfs_ts_params *p, const swfs_real *s, const char *what, double *rho, long *lag, size_t *nl)
{
    *nl = 0;
    for (long L = 1; *nl < SWFS_TEACH_NTCORR && (size_t)(4 * L) < s->ny; L *= 2) lag[(*nl)++] = L;
    const int rc = *nl ? swfs_ts_mode_timecorr(p, s->data, s->ny, s->nx, lag, *nl, rho) : SWFS_OK;
    if (rc) return swfs_fail_context(rc, "teach: the time correlation of %s", what);
    for (size_t k = 0; k < *nl; k++)
        if (!isfinite(rho[k]))
            return swfs_fail(SWFS_ERR_VALUE, "teach: %s: the slopes do not vary along the upper half of the DM modes "
                             "(no time correlation to match)", what);
    return SWFS_OK;
}

/* The rms of a loop's time correlation (a) less the observation's (b), over the lags both have. */
static double tcorr_misfit(const double *a, size_t na, const double *b, size_t nb)
{
    const size_t n = na < nb ? na : nb;
    double s = 0;
    for (size_t k = 0; k < n; k++) s += (a[k] - b[k]) * (a[k] - b[k]);
    return n ? sqrt(s / (double)n) : INFINITY;
}

/* The speed calibration loops' first speeds [m/s], a factor 2 apart. */
static const double speed_grid[4] = {4, 8, 16, 32};

/* A speed calibration loop's job: speed_NN/ (NN = r->nspeed + i), one layer at sp toward 0 deg. */
static void speed_job(const swfs_teach_run_options *o, const swfs_teach_run_result *r, size_t i, double sp,
                      loop_job *j)
{
    const loop_job t = {.nl = 1, .frac = {1.0}, .speed = {sp}, .dir = {0.0}};
    calibration_job(o, &t, "speed", r->nspeed + i, j);
}

/* A speed loop simulated (speed_job): its slopes' misfit to the observation's time
 * correlation, appended to r->speed_cal, r->speed_misfit. */
static int speed_result(const swfs_teach_run_options *o, const projection *pj, const loop_job *j,
                        swfs_teach_run_result *r)
{
    swfs_real *ls = NULL;
    char f[4300];
    double rho[SWFS_TEACH_NTCORR];
    long lag[SWFS_TEACH_NTCORR];
    size_t nl = 0;
    int rc = calibration_read(j, pj, &ls, f, sizeof f);
    if (!rc) rc = time_corr(&o->sim, ls, f, rho, lag, &nl);
    swfs_real_free(ls);
    if (rc) return rc;
    r->speed_cal[r->nspeed] = j->speed[0];
    r->speed_misfit[r->nspeed++] = tcorr_misfit(rho, nl, r->tcorr, r->ntcorr);
    return SWFS_OK;
}

/* One speed calibration loop more, at sp (speed_job, a batch of one, speed_result). */
static int speed_loop(const swfs_teach_run_options *o, const projection *pj, double sp, swfs_teach_run_result *r)
{
    loop_job j;
    speed_job(o, r, 0, sp, &j);
    const int rc = calibration_batch(o, &j, 1, "the loops' speed (calibration loops)");
    return rc ? rc : speed_result(o, pj, &j, r);
}

/* The speed loop of speed v, or r->nspeed. */
static size_t speed_at(const swfs_teach_run_result *r, double v)
{
    size_t k = 0;
    while (k < r->nspeed && r->speed_cal[k] != v) k++;
    return k;
}

/* The closest speed loop so far. */
static size_t speed_best(const swfs_teach_run_result *r)
{
    size_t b = 0;
    for (size_t k = 1; k < r->nspeed; k++)
        if (r->speed_misfit[k] < r->speed_misfit[b]) b = k;
    return b;
}

/* No layer tracked: the speed of the loops' layers from the slopes' time correlation
 * (run.h SWFS_TEACH_NTCORR): calibration loops of one layer (toward 0 deg: the correlation
 * along the upper half of the modes is that of slopes along and across the motion together)
 * at speed_grid, of the same seed, one more a factor 2 beyond the end (1-64 m/s) while the
 * closest is there, then the vertex of a parabola in log2 speed through the closest and its
 * two neighbours, kept between them (docs/telemetry.md, "Slopes without a frozen-flow layer":
 * within 15 % of the layer's speed on the matrix's six one-layer systems). */
static int speed_from_corr(const swfs_teach_run_options *o, const projection *pj, const swfs_real *obs,
                           swfs_teach_run_result *r)
{
    int rc = time_corr(&o->sim, obs, o->files[0], r->tcorr, r->tcorr_lags, &r->ntcorr);
    if (!rc && r->ntcorr < 2)
        rc = swfs_fail(SWFS_ERR_VALUE, "teach: %s: %zu WFS frames, too few for the slopes' time correlation (at least 9)",
                       o->files[0], obs->ny);
    loop_job sj[4]; /* the grid's loops, from the fastest, at once (calibration_batch) */
    for (size_t i = 0; i < 4; i++) speed_job(o, r, i, speed_grid[3 - i], &sj[i]);
    if (!rc) rc = calibration_batch(o, sj, 4, "the loops' speed (calibration loops)");
    for (size_t i = 0; !rc && i < 4; i++) rc = speed_result(o, pj, &sj[i], r);
    while (!rc && r->nspeed < SWFS_TEACH_NSPEED) {
        double lo = r->speed_cal[0], hi = lo;
        for (size_t k = 1; k < r->nspeed; k++) {
            lo = fmin(lo, r->speed_cal[k]);
            hi = fmax(hi, r->speed_cal[k]);
        }
        const double vb = r->speed_cal[speed_best(r)];
        if (vb == lo && lo / 2 >= 1.0) rc = speed_loop(o, pj, lo / 2, r);
        else if (vb == hi && hi * 2 <= 64.0) rc = speed_loop(o, pj, hi * 2, r);
        else break;
    }
    if (rc) return rc;
    const size_t b = speed_best(r), l = speed_at(r, r->speed_cal[b] / 2), h = speed_at(r, r->speed_cal[b] * 2);
    r->prior_speed = r->speed_cal[b];
    if (l < r->nspeed && h < r->nspeed) { /* equal steps in log2 speed: the vertex of the parabola through three */
        const double *m = r->speed_misfit, den = m[l] - 2 * m[b] + m[h];
        if (den > 0) {
            double d = 0.5 * (m[l] - m[h]) / den;
            d = d < -1 ? -1 : d > 1 ? 1 : d;
            r->prior_speed *= pow(2.0, d);
        }
    }
    return SWFS_OK;
}

/* The observation's white slope noise and its share of the slopes' variance
 * (swfs_slopes_white_noise) over the frames of its first file, s: the full layout, or the used
 * subapertures' with the system's valid map vm (nsub x nsub; the caller checked the width). */
static int noise_of(const swfs_ts_params *p, const swfs_real *s, const char *what, const unsigned char *vm,
                    size_t vn, swfs_teach_run_result *r)
{
    const size_t nsub = (size_t)p->nsub;
    int rc = vm && vn != nsub ? swfs_fail(SWFS_ERR_SHAPE, "teach: the valid map %s is %zu x %zu, the system %zu x %zu",
                                          p->valid, vn, vn, nsub, nsub) : SWFS_OK;
    double var = 0, svar = 0;
    if (!rc) rc = swfs_slopes_white_noise(s->data, s->ny, s->nx, nsub, vm, &var, &r->noise_cells, &svar);
    r->noise_rms = sqrt(var);
    r->noise_share = svar > 0 ? var / svar : 0;
    return rc ? swfs_fail_context(rc, "teach: the white slope noise of %s", what) : SWFS_OK;
}

int swfs_config_put_(swfs_config *c, const char *key, const char *fmt, ...)
{
    if (swfs_config_has(c, key)) return SWFS_OK;
    char v[4200];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(v, sizeof v, fmt, ap);
    va_end(ap);
    return swfs_config_set_kv(c, key, v);
}

int swfs_teach_describe(swfs_config *c, const char *science, const char *actuators, const char *pupil,
                        const char *valid, const char *telemetry)
{
    if (!c || !science || !actuators || !telemetry)
        return swfs_fail(SWFS_ERR_ARG, "teach: the system from files needs the science cube, the actuators and the "
                         "telemetry");
    swfs_geom g;
    int rc = swfs_geom_read_file(science, &g);
    if (!rc) rc = swfs_geom_require(&g, science);
    if (!rc) rc = swfs_teach_describe_geom_(c, &g, actuators, pupil, valid, telemetry);
    return rc ? swfs_fail_context(rc, "teach: the system from %s, %s and %s", science, actuators, telemetry) : rc;
}

int swfs_teach_describe_geom_(swfs_config *c, const swfs_geom *gp, const char *actuators, const char *pupil,
                              const char *valid, const char *telemetry)
{
    const swfs_geom g = *gp;
    int rc;
    /* the telemetry's header: its shape and rate (its values are read, and checked, by teach) */
    swfs_fits_in *t = NULL;
    double rate = 0;
    int found = 0;
    if ((rc = swfs_fits_in_open(&t, telemetry, NULL))) return rc;
    const swfs_fits_shape *sh = swfs_fits_in_shape(t);
    const size_t nframes = sh->ny, width = sh->nx;
    rc = swfs_fits_in_key_double_opt(t, "WFSRATE", &rate, &found);
    swfs_fits_in_close(t);
    if (rc) return rc;
    if (!found || !(rate > 0) || !isfinite(rate))
        return swfs_fail(SWFS_ERR_FORMAT, "teach: %s: no WFSRATE keyword; the loops need the WFS frame rate "
                         "(give wfs_rate=)", telemetry);
    size_t nsub = 0, nv = 0;
    if (valid) {
        unsigned char *vm = NULL;
        if ((rc = swfs_valid_map_read(valid, &vm, &nsub, &nv))) return rc;
        free(vm);
        if (width != 2 * nsub * nsub && width != 2 * nv)
            return swfs_fail(SWFS_ERR_SHAPE, "teach: the valid map %s is %zu x %zu (%zu used), but %s has %zu slopes per "
                             "WFS frame: expected 2 nsub^2 = %zu (the full layout) or twice the used subapertures, %zu",
                             valid, nsub, nsub, nv, telemetry, width, 2 * nsub * nsub, 2 * nv);
    } else {
        nsub = (size_t)llround(sqrt((double)width / 2.0));
        if (2 * nsub * nsub != width)
            return swfs_fail(SWFS_ERR_SHAPE, "teach: %s: %zu slopes per WFS frame is not 2 nsub^2 (a square "
                             "Shack-Hartmann's x then y slopes); slopes of the used subapertures need their valid map",
                             telemetry, width);
    }
    size_t sn = 1024;
    while (sn < 2 * (size_t)g.pupn) sn *= 2;
    /* the loops: as long as the observation's file, its camera one short cube at each end */
    const long gap = (long)nframes > 700 ? (long)nframes - 360 : 340;
    if (!rc) rc = swfs_config_put_(c, "pupn", "%ld", g.pupn);
    if (!rc) rc = swfs_config_put_(c, "pupdx", "%.17g", g.pupdx);
    if (!rc) rc = swfs_config_put_(c, "screen_dx", "%.17g", g.pupdx);
    if (!rc) rc = swfs_config_put_(c, "screen_n", "%zu", sn);
    if (!rc) rc = swfs_config_put_(c, "teldiam", "%.17g", g.teldiam);
    if (!rc) rc = swfs_config_put_(c, "wavelen", "%.17g", g.wavelen);
    if (!rc) rc = swfs_config_put_(c, "pixscale", "%.17g", g.pixscale);
    if (!rc && isfinite(g.obscur)) rc = swfs_config_put_(c, "obscur", "%.17g", g.obscur);
    if (!rc && actuators) rc = swfs_config_put_(c, "actuators", "%s", actuators); /* else act_pitch, from the caller */
    if (!rc && pupil) rc = swfs_config_put_(c, "pupil_mask", "%s", pupil);
    if (!rc && valid) rc = swfs_config_put_(c, "valid", "%s", valid);
    if (!rc) rc = swfs_config_put_(c, "nsub", "%zu", nsub);
    if (!rc) rc = swfs_config_put_(c, "wfs_rate", "%.17g", rate);
    if (!rc) rc = swfs_config_put_(c, "wfs_file_frames", "%zu", nframes > 700 ? nframes : 700);
    if (!rc) rc = swfs_config_put_(c, "frame_ratio", "1");
    if (!rc) rc = swfs_config_put_(c, "ncubes", "2");
    if (!rc) rc = swfs_config_put_(c, "cube_frames", "20");
    if (!rc) rc = swfs_config_put_(c, "cube_gap", "%ld", gap);
    if (!rc) rc = swfs_config_put_(c, "start_offset", "300.5");
    if (!rc) rc = swfs_config_put_(c, "nfx", "16");
    if (!rc) rc = swfs_config_put_(c, "nfy", "16");
    return rc;
}

/* The map's output points: a hexapolar grid of half the DM's pitch (at least two pupil
 * samples), written to WORK/outgrid.fits and given to the loops as the points their truth is
 * fitted on (truth_actuators). Frozen flow carries the residual the DM cannot hold, the
 * fitting error beyond its cutoff, across the subapertures between the map's lags, so the
 * lagged slopes tell part of it; on the DM's own actuators the map could not write it. The
 * grid's cutoff is twice the DM's: with the residual's spectrum beyond the DM's cutoff
 * falling as f^-11/3, the octave it adds holds 1 - 2^-5/3 = 69 % of the fitting error's
 * variance (docs/telemetry.md, "A map finer than the DM"). */
int swfs_outgrid_make_(const swfs_ts_params *sp, const char *work, char *path, size_t cap, double *dm_pitch,
                       double **xy, size_t *n)
{
    *xy = NULL;
    *n = 0;
    const double D = sp->base.teldiam, dx = sp->base.pupdx;
    /* the DM's positions: the file's, or the loops' own layout */
    double *dm = NULL;
    size_t nd = 0;
    int rc = sp->actuators[0] ? swfs_actuators_read(sp->actuators, &dm, &nd) : swfs_ts_dm_layout(sp, &dm, &nd);
    if (rc) return rc;
    *dm_pitch = swfs_points_pitch(dm, nd);
    free(dm);
    const double pitch = fmax(0.5 * *dm_pitch, 2.0 * dx);
    if (!(pitch > 0.0 && isfinite(pitch)))
        return swfs_fail(SWFS_ERR_VALUE, "the DM's pitch %g m gives no output grid", *dm_pitch);
    if (snprintf(path, cap, "%.1000s/outgrid.fits", work) >= (int)cap || strlen(work) > 1000)
        return swfs_fail(SWFS_ERR_ARG, "%.200s: the folder's name is too long for the output grid's file "
                         "(at most 1000 characters)", work);
    if ((rc = swfs_actuators_hexapolar(D, pitch, dx, xy, n))) return rc;
    swfs_outputs_begin();
    rc = swfs_actuators_write(*xy, *n, path);
    const int erc = swfs_outputs_end(rc == SWFS_OK);
    if (rc || erc) {
        free(*xy);
        *xy = NULL;
        *n = 0;
    }
    return rc ? rc : erc;
}

static int output_grid(swfs_teach_run_options *o, swfs_teach_run_result *r)
{
    swfs_ts_params *sp = &o->sim;
    double *xy = NULL;
    size_t n = 0;
    int rc = SWFS_OK;
    if (sp->truth_actuators[0]) { /* the caller's own points (truth_actuators=FILE) */
        if (!(rc = swfs_actuators_read(sp->truth_actuators, &xy, &n))) r->out_pitch = swfs_points_pitch(xy, n);
        free(xy);
        r->out_points = rc ? 0 : n;
        return rc;
    }
    char path[sizeof sp->truth_actuators];
    rc = swfs_outgrid_make_(sp, o->work, path, sizeof path, &r->dm_pitch, &xy, &n);
    if (rc) return swfs_fail_context(rc, "teach");
    r->out_pitch = swfs_points_pitch(xy, n);
    free(xy);
    r->out_points = n;
    memcpy(sp->truth_actuators, path, sizeof path);
    return SWFS_OK;
}

int swfs_teach_work_default(const char *out, char *work, size_t cap)
{
    const size_t n = strlen(out), cut = n > 5 && !strcmp(out + n - 5, ".fits") ? n - 5 : n;
    if (cut > 4000 || cut + sizeof ".teach" > cap)
        return swfs_fail(SWFS_ERR_ARG, "the teach folder beside %.200s%s: the name is too long (%zu characters); give "
                         "its folder", out, n > 200 ? "..." : "", n);
    snprintf(work, cap, "%.*s.teach", (int)cut, out);
    return SWFS_OK;
}

/* The loops a curve over `have` of them (have > 0) asks for, before any budget caps them: as
 * many as hold the frames it asks for, have where it asks for no more than they hold. */
static double curve_asks(const swfs_learn_run_result *lr, size_t have)
{
    if (!(lr->curve_frames > lr->info.nframes)) return (double)have;
    return ceil((double)lr->curve_frames / ((double)lr->info.nframes / (double)have));
}

size_t swfs_teach_more_loops_(const swfs_learn_run_result *lr, size_t have, size_t max_loops, int *doubled)
{
    if (!have || max_loops <= have) return have;
    const int flat = lr->curve_n[0] > 0 && !swfs_learn_curve_falls(lr);
    if (!(lr->curve_frames > lr->info.nframes) && !(flat && !*doubled)) return have;
    const double want = flat ? 2.0 * (double)have : curve_asks(lr, have);
    *doubled |= flat;
    return want < (double)max_loops ? (want > (double)have ? (size_t)want : have) : max_loops;
}

/* The first loops' curve does not end teach, nor ask for fewer than twice them: its held-out
 * parts are a quarter of the first loops each (three of 12), too few to say what more loops
 * give. On a foreign 14 x 14 observation its curve fell by 2.6 standard errors and put the 12
 * loops' map 4.8 % above unlimited frames; 24 loops took the NCP error 32.4 -> 24.9 nm, 48 to
 * 22.1 (docs/telemetry.md, "A first curve that falls does not end teach either"). So, within
 * the budget, the loops are doubled as where the first curve does not fall, and the curve over
 * them decides; where the first loops are too few for a curve none is measured, and none of
 * this applies. */
size_t swfs_teach_next_loops_(const swfs_learn_run_result *lr, size_t have, size_t first, size_t max_loops,
                              int *doubled)
{
    const size_t n = swfs_teach_more_loops_(lr, have, max_loops, doubled);
    /* (a curve that asks for more than twice the first loops: followed as before) */
    if (have != first || *doubled || !lr->curve_n[0] || max_loops <= have || curve_asks(lr, have) > 2.0 * (double)have)
        return n;
    *doubled = 1;
    return 2 * have < max_loops ? 2 * have : max_loops;
}

int swfs_teach_curve_unbounded_(const swfs_learn_run_result *lr)
{
    return lr->curve_n[0] > 0 && lr->curve_b > 0 && !(lr->curve_a > 0) && swfs_learn_curve_falls(lr);
}

int swfs_teach_run(const swfs_teach_run_options *o, swfs_teach_run_result *r)
{
    memset(r, 0, sizeof *r);
    const double t0 = swfs_wall_seconds();
    int rc = check_options(o);
    if (!rc) rc = check_paths(o);
    if (rc) return rc;
    const swfs_ts_params *sp = &o->sim;
    const char *valid = sp->valid[0] ? sp->valid : NULL;
    /* The observation: its first file for the checks, its geometry and rate against the system's. */
    swfs_real *obs = NULL;
    double orate = 0;
    if ((rc = swfs_telemetry_check_sh(o->files[0], "teach (its loops simulate a Shack-Hartmann)"))) return rc;
    if ((rc = swfs_telemetry_read(o->files[0], 0, &obs, &orate))) return rc;
    /* slopes modal-slopes made from modal coefficients (MODALCM: the control matrix) lie in
     * CM's row space; the loops' slopes are learned on the same projection */
    projection pj = {NULL, 0};
    {
        char cmp[4096];
        int found = 0;
        swfs_fits_in *f = NULL;
        rc = swfs_fits_in_open(&f, o->files[0], NULL);
        char name[4096];
        if (!rc) rc = swfs_fits_in_key_string_opt(f, "MODALCM", name, sizeof name, &found);
        swfs_fits_in_close(f);
        if (!rc && found) { /* a name relative to the telemetry file's folder, as modal-slopes writes it */
            char dir[4096];
            swfs_path_dir(o->files[0], dir, sizeof dir);
            rc = swfs_telemetry_path(dir, name, cmp, sizeof cmp);
        }
        if (!rc && found) {
            if ((rc = swfs_modal_projector_(cmp, &pj.P, &pj.n, &r->project_rank)))
                rc = swfs_fail_context(rc, "teach: %s was made by modal-slopes through %s (MODALCM)", o->files[0], cmp);
            else if (pj.n != obs->nx)
                rc = swfs_fail(SWFS_ERR_SHAPE, "teach: %s: %zu slopes per frame, but its MODALCM %s acts on %zu", o->files[0],
                               obs->nx, cmp, pj.n);
            r->project_slopes = pj.n;
        }
        if (rc) { free(pj.P); swfs_real_free(obs); return rc; }
    }
    const size_t nsub = (size_t)sp->nsub;
    size_t vn = 0, nv = 0;
    unsigned char *vmap = NULL;
    if (valid && (rc = swfs_valid_map_read(valid, &vmap, &vn, &nv))) { free(pj.P); swfs_real_free(obs); return rc; }
    if (obs->nx != 2 * nsub * nsub && !(valid && obs->nx == 2 * nv))
        rc = swfs_fail(SWFS_ERR_SHAPE, "teach: %s: %zu slopes per WFS frame; the system's %zu x %zu Shack-Hartmann "
                       "(nsub) writes 2 nsub^2 = %zu%s", o->files[0], obs->nx, nsub, nsub, 2 * nsub * nsub,
                       valid ? ", and its valid map's used subapertures give twice their count" : "");
    /* the file's own NSUB, as speckles and stream check it on their model: refused here,
     * before the loops (which would take minutes for telemetry the pipeline then refuses) */
    else rc = swfs_telemetry_check_nsub(o->files[0], nsub);
    /* the loops write every subaperture's slopes (x of the nsub^2, then y); a projection of the
     * used ones' (valid-only telemetry) acts on those places, the others set to 0 as the
     * telemetry has none */
    if (!rc && pj.P && valid && vn == nsub && pj.n == 2 * nv && 2 * nsub * nsub != pj.n) {
        const size_t n2 = nsub * nsub, nf = 2 * n2;
        size_t *at = malloc(pj.n * sizeof *at);
        double *F = calloc(nf * nf, sizeof *F);
        if (!at || !F) rc = swfs_fail(SWFS_ERR_NOMEM, "teach: out of memory");
        for (size_t a = 0, j = 0; !rc && a < n2 && j < nv; a++)
            if (vmap[a]) {
                at[j] = a;
                at[nv + j++] = n2 + a;
            }
        for (size_t i = 0; !rc && i < pj.n; i++)
            for (size_t j = 0; j < pj.n; j++) F[at[i] * nf + at[j]] = pj.P[i * pj.n + j];
        free(at);
        if (!rc) {
            free(pj.P);
            pj.P = F;
            pj.n = nf;
        } else {
            free(F);
        }
    }
    if (!rc && orate > 0 && fabs(orate - sp->wfs_rate) > 1e-6 * sp->wfs_rate)
        rc = swfs_fail(SWFS_ERR_VALUE, "teach: %s: WFSRATE %g Hz, but the system runs at wfs_rate = %g Hz", o->files[0],
                       orate, sp->wfs_rate);
    /* its white slope noise (given to the loops below, without slope_noise) */
    if (!rc) rc = noise_of(sp, obs, o->files[0], vmap, vn, r);
    free(vmap);
    /* 1. the layers */
    if (!rc) rc = stage(o, "the observation's layers (wind)", 0, 1);
    swfs_wind_run_options wo = {o->files, o->nfiles, valid, sp->nsub, sp->base.teldiam, sp->wfs_rate};
    if (!rc) rc = swfs_wind_run(&wo, &r->wind);
    const swfs_wind_estimate *e = &r->wind.est;
    if (!rc && !e->found && e->nvalid < 8)
        rc = swfs_fail(SWFS_ERR_VALUE, "teach: %s: `wind` found %zu subapertures with signal in the observation's slopes "
                       "(at least 8 expected); use the von Karman map (speckles --recon vk)",
                       o->nfiles == 1 ? o->files[0] : "the telemetry files", e->nvalid);
    if (rc) { free(pj.P); swfs_real_free(obs); return rc; }
    /* no frozen-flow layer tracked (slopes mostly noise, or turbulence that does not flow):
     * the loops at a speed their slopes' time correlation gives instead, in any direction, and
     * the space-time map of them at the loop's own time scale, lags of 1 and 2 frames, which
     * need no wind (docs/telemetry.md, "Slopes without a frozen-flow layer") */
    const int prior = !e->found;
    const int nl = prior ? 2 : (int)(e->nlayers < SWFS_TS_MAX_LAYERS ? e->nlayers : SWFS_TS_MAX_LAYERS);
    r->nlayers = prior ? 0 : (size_t)nl;
    double speed[SWFS_TS_MAX_LAYERS], dir[SWFS_TS_MAX_LAYERS], vmax = 0;
    for (int j = 0; j < nl; j++) {
        /* the filter's calibration loops (before the speed; their profile's level aside, which
         * the speed sets, they depend on it little): two layers, the middle of the speed
         * loops' 4-32 m/s, apart */
        speed[j] = prior ? sqrt(speed_grid[0] * speed_grid[3]) : e->layer[j].speed;
        dir[j] = prior ? 90.0 * j : e->layer[j].direction;
        vmax = fmax(vmax, speed[j]);
    }
    /* the lags: the fastest layer moves half a subaperture in L1 frames. Without a layer, the
     * frames next to each one: the closed loop's residual stays correlated over its integrator's
     * few frames, its sensor's noise does not, so they average the noise and show the DM's
     * response to the slopes just before (docs/telemetry.md, "Slopes without a frozen-flow
     * layer": on noise-dominated slopes the per-frame map was worse than von Karman's) */
    swfs_spacetime_lags_(prior ? 0.0 : r->wind.pitch * r->wind.rate / (2.0 * vmax), r->lags);
    r->nlags = SWFS_SPACETIME_NLAGS;
    /* 2. the loops' slope noise and modal filter: given, or from the observation's slopes.
     * Loops of less noise than the observation's give a map that amplifies its noise
     * (docs/telemetry.md, "The loops' slope noise from the slopes"). */
    swfs_teach_run_options oo = *o;
    /* no loop's camera is used: a described camera (cubes of many frames) integrates two short
     * cubes over the same WFS frames instead, the same slopes (timeseries.h camera_light) */
    swfs_ts_camera_light(&oo.sim);
    /* the DM's functions from the system's control matrix, where the loops are given it and the
     * description does not say them (docs/telemetry.md, "The DM's functions from the loop's
     * control matrix") */
    if (o->coupling_from_recon && oo.sim.ao_recon[0]) {
        if ((rc = stage(o, "the DM's functions from the control matrix", 0, 1)) ||
            (rc = swfs_ts_coupling_from_recon(&oo.sim, &r->coupling))) {
            free(pj.P);
            swfs_real_free(obs);
            return swfs_fail_context(rc, "teach");
        }
        r->coupling_done = 1;
        oo.sim.dm_coupling = r->coupling.gaussian ? r->coupling.coupling : 0.0;
    }
    if (o->noise_from_slopes) oo.sim.slope_noise = r->noise_rms;
    r->slope_noise = oo.sim.slope_noise;
    if (o->modes_from_slopes) {
        loop_job tmpl = {.nl = nl};
        for (int l = 0; l < nl; l++) {
            tmpl.frac[l] = 1.0 / nl; /* equal shares: the middle of the loops' spread for two layers */
            tmpl.speed[l] = speed[l];
            tmpl.dir[l] = dir[l];
        }
        rc = modes_from_slopes(&oo, obs, &tmpl, r);
    }
    if (!rc && prior) rc = speed_from_corr(&oo, &pj, obs, r);
    o = &oo;
    r->ao_modes = o->sim.ao_recon[0] || o->sim.ao_rcond > 0 ? 0 : (size_t)o->sim.ao_modes;
    if (rc) { free(pj.P); swfs_real_free(obs); return rc; }
    /* 3. the loops. Enough frames for the map: a least-squares map of p inputs learned from
     * n frames misses frames it was not learned on by sqrt(1 + p / (n - p - 1)) times its
     * noise (the excess of ordinary least squares over the best linear map); n >= 10 p keeps
     * that under 6 %. p: the lags times the slopes the observation uses (x and y of the
     * subapertures `wind` found with signal). Loops shorter than that (short telemetry files:
     * the description makes each loop as long as one) start their cubes later, the camera's
     * frames being the same, and stay one file. */
    r->map_inputs = r->nlags * 2 * e->nvalid;
    r->loop_frames = swfs_ts_nframes(&oo.sim);
    if (!r->loop_frames) { free(pj.P); swfs_real_free(obs); return swfs_fail(SWFS_ERR_NOMEM, "teach: out of memory"); }
    r->loop_frames_described = r->loop_frames;
    const size_t need = (10 * r->map_inputs + o->nloops - 1) / o->nloops;
    if (r->loop_frames < need) {
        oo.sim.start_offset += (double)(need - r->loop_frames);
        r->loop_frames = swfs_ts_nframes(&oo.sim);
        /* each loop one file still, as the description has it */
        if (oo.sim.wfs_file_frames > 0 && (size_t)oo.sim.wfs_file_frames < r->loop_frames)
            oo.sim.wfs_file_frames = (long)r->loop_frames;
    }
    if ((rc = output_grid(&oo, r))) { free(pj.P); swfs_real_free(obs); return rc; }
    const size_t max_loops = o->max_loops ? o->max_loops : 4 * o->nloops < 64 ? 4 * o->nloops : 64;
    loop_job *jobs = calloc(max_loops, sizeof *jobs);
    if (!jobs) { free(pj.P); swfs_real_free(obs); return swfs_fail(SWFS_ERR_NOMEM, "teach: out of memory"); }
    for (size_t k = 0; k < o->nloops; k++) {
        if (prior) prior_init(jobs + k, o, k, r->prior_speed);
        else loop_init(jobs + k, o, k, (double)k / (double)(o->nloops - 1), nl, speed, dir);
    }
    char st[4200], pf[4200];
    snprintf(st, sizeof st, "%.4000s/spacetime.fits", o->work);
    snprintf(pf, sizeof pf, "%.4000s/perframe.fits", o->work);
    swfs_learn_run_result lr;
    /* what every loop's run would build again from the system alone (the DM's modes, the
     * truth's fit plan on the grid: an eigen-decomposition of its points squared), once */
    swfs_ts_shared *shared = NULL;
    swfs_ts_params sys = oo.sim;
    sys.export_truth = 1;
    rc = swfs_ts_shared_create(&sys, &shared);
    /* 4. the space-time map (with the per-frame map of the same loops from the same sums:
     * perframe.fits, what a run taking one frame's slopes, live, is given) and its learning
     * curve where more loops may follow (six more solves of the map's normal equations:
     * minutes for a 24 x 24's 4440 inputs, not spent when max_loops allows no more); where no
     * layer was tracked the same, at lags of 1 and 2 frames */
    if (!rc) rc = simulate_loops(o, shared, jobs, o->nloops, prior ? "simulating loops at the slopes' speed"
                                 : "simulating the loops", &r->nloops, 1);
    r->st_loops = o->nloops;
    r->max_loops = max_loops;
    if (!rc) {
        rc = stage(o, "learning the space-time map", 0, 1);
        if (!rc) rc = learn(o, &pj, jobs, o->nloops, r->lags, r->nlags, st, pf, max_loops > o->nloops, &lr);
        r->curve_first = r->curve = lr;
    }
    /* 4b. more loops where the curve asks for more frames than the loops hold: as many as
     * bring the map's excess over unlimited frames to SWFS_LEARN_CURVE_EXCESS (at most
     * max_loops: by default 4 times the first loops' cost), their layer shares spread over
     * the first loops' range; then the map again. Frames correlated in time count for less
     * than the independent ones the 10 frames per input above assume: the curve measures what
     * they are worth (docs/telemetry.md, "Loops as the map's learning curve asks"). A curve
     * that does not fall from its first point to its second cannot tell (more frames never
     * raise the expected held-out misfit: a rise is the few held-out loops' scatter): once,
     * the loops are doubled and the curve measured again over all of them, which then asks
     * as above (once: the loops a curve asks for are the last, unless their own curve falls
     * without a bound, swfs_teach_curve_unbounded_: then the budget). 12 loops of a short
     * observation's length rose 304.5 -> 311.7 nm; doubled, their curve asked for the
     * budget's 48 (NCP 36.9 -> 22.4 nm, docs/telemetry.md). */
    size_t have = o->nloops;
    int doubled = 0;
    while (!rc) {
        const int was_doubled = doubled;
        const size_t n = swfs_teach_next_loops_(&lr, have, o->nloops, max_loops, &doubled);
        if (n <= have) break;
        for (size_t k = have; k < n; k++) {
            if (prior) prior_init(jobs + k, o, k, r->prior_speed);
            else loop_init(jobs + k, o, k, ((double)(k - have) + 0.5) / (double)(n - have), nl, speed, dir);
        }
        rc = simulate_loops(o, shared, jobs + have, n - have, "simulating more loops (learning curve)", &r->nloops, 1);
        r->st_loops = have = n;
        if (!rc) {
            rc = stage(o, "learning the space-time map again", 0, 1);
            if (!rc) rc = learn(o, &pj, jobs, n, r->lags, r->nlags, st, pf, 1, &lr);
            r->curve = lr;
            if (doubled != was_doubled) r->curve_doubled = lr;
        }
        /* the loops the curve asked for: the last step, unless their own curve has no bound
         * (then the budget: a 16 x 16 foreign observation's 22 asked-for loops fell 239.4 ->
         * 193.2 nm from N/2 to 3N/4 frames; docs/telemetry.md) */
        if (doubled == was_doubled) {
            if (!swfs_teach_curve_unbounded_(&lr) || r->asked_loops || have >= max_loops) break;
            r->asked_loops = have;
            r->curve_asked = lr;
        }
    }
    if (!rc) {
        r->st_misfit_rms = lr.info.misfit_rms;
        r->st_truth_rms = lr.info.truth_rms;
    }
    if (!rc && !prior) { /* none where no layer was tracked: they compare the loops' layers with the slopes' */
        r->check.info.nlags = r->nlags;
        rc = swfs_spacetime_check_(st, r->lags, r->nlags, obs->data, obs->ny, obs->nx, nsub, valid, &r->check);
    }
    swfs_real_free(obs);
    if (!rc && !prior) r->warns = swfs_spacetime_warns(&r->check);
    /* 5. where it warns, the per-frame map: of the same loops, or with one layer found, of
     * loops of that layer and a second drawn at random */
    const char *chosen = st;
    if (prior) r->chosen = SWFS_TEACH_SPACETIME_PRIOR;
    if (!rc && r->warns && nl == 1) {
        r->chosen = SWFS_TEACH_PERFRAME_MIXED;
        for (size_t k = 0; k < o->nloops; k++) {
            loop_job *j = jobs + k;
            swfs_rng g;
            swfs_rng_seed2(&g, o->seed, 1000 + k);
            snprintf(j->name, sizeof j->name, "mixed");
            j->seed = o->seed + r->st_loops + k;
            j->nl = 2;
            j->frac[0] = 0.5 + 0.3 * swfs_rng_uniform(&g);
            j->frac[1] = 1.0 - j->frac[0];
            j->speed[1] = 8.0 + 22.0 * swfs_rng_uniform(&g);
            j->dir[1] = 360.0 * swfs_rng_uniform(&g);
        }
        rc = simulate_loops(o, shared, jobs, o->nloops, "simulating loops of a random second layer", &r->nloops, 1);
    } else if (!rc && r->warns) {
        r->chosen = SWFS_TEACH_PERFRAME;
    }
    if (!rc && r->chosen == SWFS_TEACH_PERFRAME_MIXED) { /* other loops: their own map */
        rc = stage(o, "learning the per-frame map", 0, 1);
        if (!rc) rc = learn(o, &pj, jobs, o->nloops, NULL, 0, pf, NULL, 0, &lr);
    }
    if (!rc && r->warns) chosen = pf; /* of the same loops: learned with the space-time map */
    free(jobs);
    free(pj.P);
    swfs_ts_shared_free(shared);
    if (!rc) rc = write_chosen(chosen, o, r);
    r->seconds = swfs_wall_seconds() - t0;
    return rc;
}

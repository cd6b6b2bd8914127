/* The NCP loop closed in simulation through shared-memory streams: see
 * include/specklewfs/live.h (swfs_live_loop_run) and docs/live.md. */
#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/live.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

void swfs_live_loop_options_default(swfs_live_loop_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_ts_params_default(&o->sim);
    o->iterations = 3;
    o->speed = 2.0;
    o->batch = 16;
    swfs_dmfit_options_default(&o->dmfit);
    o->dmfit.influence = SWFS_INFLUENCE_CUBIC;
    o->gain = 0.5;
    o->pupil_source = SWFS_SOURCE_HALO;
}

typedef struct replay_job {
    swfs_replay_options o;
    swfs_replay_result r;
    int rc;
    char err[2048];
} replay_job;

static void *replay_main(void *arg)
{
    replay_job *j = arg;
    j->rc = swfs_replay_run(&j->o, &j->r);
    if (j->rc) snprintf(j->err, sizeof j->err, "%s", swfs_last_error());
    return NULL;
}

static int write_map(const char *path, const double *v, size_t n, const swfs_geom *g, const char *const *prov,
                     size_t nprov)
{
    swfs_real a = {n, n, 1, (double *)v};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    if ((rc = swfs_fits_out_set_stamp(o, g, prov, nprov)) || (rc = swfs_fits_out_real(o, NULL, &a, -64)) ||
        (rc = swfs_fits_out_history(o, "NCP map: the wavefront the DM offsets add (2 x DM surface) [m]"))) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

/* rms of w inside the mask with piston, tip and tilt removed. */
static double ptt_rms(const double *w, const double *mask, size_t n, double *zeros)
{
    double e = NAN;
    swfs_wfe_compare(w, zeros, mask, n, &e, NULL, NULL);
    return e;
}

static int stage(const swfs_live_loop_options *o, size_t k, const char *what)
{
    if (!o->progress) return SWFS_OK;
    char s[128];
    snprintf(s, sizeof s, "iteration %zu: %s", k, what);
    return swfs_progress_report(o->progress, o->progress_ctx, s, k, o->iterations + 1);
}

int swfs_live_loop_run(const swfs_live_loop_options *o, swfs_live_loop_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->dir || !o->iterations || o->iterations > SWFS_LIVE_LOOP_MAX || !(o->speed > 0) || !o->batch ||
        !(o->gain > 0 && o->gain <= 1))
        return swfs_fail(SWFS_ERR_ARG, "live loop: needs a folder, 1..%d iterations, speed > 0, batch >= 1 and a gain in "
                         "(0, 1] (got %zu, %g, %zu, %g)", SWFS_LIVE_LOOP_MAX, o->iterations, o->speed, o->batch, o->gain);
    int rc = swfs_ts_params_check(&o->sim);
    if (rc) return rc;
    const swfs_sim_params *b = &o->sim.base;
    const size_t np = (size_t)b->pupn, n2 = np * np;
    const swfs_geom g = {b->wavelen, b->teldiam, b->obscur, b->pixscale, b->pupdx, b->pupn};
    char shm[4200], path[4400], rdir[4300], recon[4300], act[4400];
    snprintf(shm, sizeof shm, "%s/shm", o->dir);
    snprintf(recon, sizeof recon, "%s/recon.fits", o->dir);
    mkdir(shm, 0777);
    double *mask = malloc(n2 * sizeof *mask), *ncp0 = malloc(n2 * sizeof *ncp0), *user = calloc(n2, sizeof *user);
    double *surf = calloc(n2, sizeof *surf), *res = malloc(n2 * sizeof *res), *zeros = calloc(n2, sizeof *zeros);
    double *map = malloc(n2 * sizeof *map), *xy = NULL, *cmd = NULL;
    size_t nact = 0;
    swfs_dmfit *fit = NULL;
    swfs_shm *dm = NULL;
    swfs_real *wfe = NULL, *truth = NULL;
    const double t0 = swfs_wall_seconds();
    if (!mask || !ncp0 || !user || !surf || !res || !zeros || !map) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "live loop: out of memory");
        goto done;
    }
    /* The simulator's pupil and its NCP without any correction (the user's map included). */
    if ((rc = swfs_sim_pupil(b, mask))) goto done;
    if ((rc = swfs_sim_ncp_map(b, mask, ncp0, NULL, NULL))) goto done;
    if (b->ncp_map[0]) {
        swfs_real *u = NULL;
        if ((rc = swfs_fits_read_real(b->ncp_map, NULL, &u, NULL))) goto done;
        if (u->nx * u->ny == n2) memcpy(user, u->data, n2 * sizeof *user);
        swfs_real_free(u);
    }
    for (size_t k = 0; k <= o->iterations; k++) {
        swfs_live_loop_state *st = &r->s[k];
        r->nstates = k + 1;
        for (size_t i = 0; i < n2; i++) res[i] = mask[i] > 0 ? ncp0[i] + 2.0 * surf[i] : 0.0;
        st->residual_rms = ptt_rms(res, mask, np, zeros);
        st->estimate_err = NAN;
        st->lag_median = st->lag_p99 = NAN;
        if (k == o->iterations || (o->stop && *o->stop)) break;
        /* The simulator with the NCP the DM has left: its own plus twice the DM surface. */
        swfs_ts_params p = o->sim;
        p.base.seed = o->sim.base.seed + (uint64_t)k;
        if (k) {
            snprintf(path, sizeof path, "%s/dm_%02zu.fits", o->dir, k);
            for (size_t i = 0; i < n2; i++) map[i] = user[i] + 2.0 * surf[i];
            if ((rc = write_map(path, map, np, &g, o->prov, o->nprov))) goto done;
            if (strlen(path) >= sizeof p.base.ncp_map) {
                rc = swfs_fail(SWFS_ERR_ARG, "live loop: %s: path too long for the simulator's ncp_map", path);
                goto done;
            }
            memcpy(p.base.ncp_map, path, strlen(path) + 1);
        }
        snprintf(rdir, sizeof rdir, "%s/iter_%02zu", o->dir, k);
        mkdir(rdir, 0777);
        if ((rc = stage(o, k, "simulate"))) goto done;
        swfs_ts_summary sum;
        if ((rc = swfs_ts_run(&p, rdir, o->prov, o->nprov, NULL, NULL, &sum))) goto done;
        /* The real-data path: reduce, sync (and the reconstructor once). */
        if ((rc = stage(o, k, "reduce + sync"))) goto done;
        char sci[4400], tim[4400], raw[64][4400], dark[4400], flat[4400], hs[4400];
        const char *rawp[64];
        const size_t ncub = (size_t)p.ncubes < 64 ? (size_t)p.ncubes : 64;
        for (size_t c = 0; c < ncub; c++) {
            snprintf(raw[c], sizeof raw[c], "%s/raw_%03zu.fits", rdir, c);
            rawp[c] = raw[c];
        }
        snprintf(sci, sizeof sci, "%s/science.fits", rdir);
        snprintf(tim, sizeof tim, "%s/timing.txt", rdir);
        snprintf(dark, sizeof dark, "%s/dark.fits", rdir);
        snprintf(flat, sizeof flat, "%s/flat.fits", rdir);
        snprintf(hs, sizeof hs, "%s/handshake.log", rdir);
        snprintf(act, sizeof act, "%s/actuators.fits", rdir);
        swfs_reduce_run_options ro;
        swfs_reduce_run_options_default(&ro);
        ro.raw = rawp;
        ro.nraw = ncub;
        ro.dark = dark;
        ro.flat = flat;
        ro.out = sci;
        ro.prov = o->prov;
        ro.nprov = o->nprov;
        swfs_reduce_run_result rr;
        if ((rc = swfs_reduce_run(&ro, &rr))) goto done;
        swfs_sync_run_options so;
        swfs_sync_run_options_default(&so);
        so.science = sci;
        so.handshake = hs;
        so.out = tim;
        so.params.ratio_min = fmax(1.0, 0.7 * p.frame_ratio);
        so.params.ratio_max = 1.3 * p.frame_ratio;
        swfs_sync_run_result sr;
        memset(&sr, 0, sizeof sr);
        rc = swfs_sync_run(&so, &sr);
        free(sr.t.cubes);
        if (rc) goto done;
        if (k == 0) {
            swfs_speckles_run_options sp;
            swfs_speckles_run_options_default(&sp);
            snprintf(path, sizeof path, "%s/speckles.fits", rdir);
            sp.timing = tim;
            sp.science = sci;
            sp.actuators = act;
            sp.out = path;
            sp.write_recon = recon;
            sp.pipe.recon = SWFS_RECON_VK; /* the live stream applies a per-frame map (a taught one may have lags) */
            sp.prov = o->prov;
            sp.nprov = o->nprov;
            swfs_speckles_run_result spr;
            if ((rc = swfs_speckles_run(&sp, &spr))) goto done;
            if ((rc = swfs_actuators_read(act, &xy, &nact))) goto done;
            if ((rc = swfs_dmfit_create(&fit, xy, nact, &g, mask, &o->dmfit))) goto done;
            if (!(cmd = malloc(nact * sizeof *cmd))) {
                rc = swfs_fail(SWFS_ERR_NOMEM, "live loop: out of memory");
                goto done;
            }
        }
        /* The AO system publishes (replay, its own thread); live listens and corrects the
         * DM stream at the end of the data. */
        if ((rc = stage(o, k, "replay -> live"))) goto done;
        replay_job job;
        memset(&job, 0, sizeof job);
        swfs_replay_options_default(&job.o);
        job.o.timing = tim;
        job.o.science = sci;
        job.o.dir = shm;
        job.o.wfs_name = "wfs";
        job.o.camera_name = "cam";
        job.o.speed = o->speed;
        job.o.depth = 256;
        job.o.wait_reader = 60;
        job.o.remove = 1;
        pthread_t th;
        if (pthread_create(&th, NULL, replay_main, &job)) {
            rc = swfs_fail(SWFS_ERR_INTERNAL, "live loop: cannot start the replay");
            goto done;
        }
        swfs_live_options lo;
        swfs_live_options_default(&lo);
        char out[4400], pup[4400], ck[4400];
        snprintf(out, sizeof out, "%s/halo.fits", rdir);
        snprintf(pup, sizeof pup, "%s/pupil.fits", rdir);
        snprintf(ck, sizeof ck, "%s/checkpoint.fits", rdir);
        const char *wfs[1] = {"wfs"};
        lo.run.science = sci;
        lo.run.recon = recon;
        lo.run.actuators = act;
        lo.run.out = out;
        lo.run.pupil_out = pup;
        lo.run.checkpoint = ck;
        lo.run.pupil_source = o->pupil_source;
        lo.run.prov = o->prov;
        lo.run.nprov = o->nprov;
        lo.src.dir = shm;
        lo.src.wfs = wfs;
        lo.src.nwfs = 1;
        lo.src.camera = "cam";
        lo.src.sync.batch = o->batch;
        lo.src.idle = 1.0;
        lo.src.timeout = 60;
        lo.src.stop = o->stop;
        lo.dm_out = "dm";
        lo.dm_final = 1;
        lo.dmfit = o->dmfit;
        lo.dm_gain = o->gain;
        lo.dm_max_step = o->max_step;
        lo.dm_max_rms = o->max_rms;
        lo.dm_tiptilt = o->tiptilt;
        swfs_live_result lr;
        rc = swfs_live_run(&lo, &lr);
        pthread_join(th, NULL);
        if (rc) goto done;
        if (job.rc) {
            rc = swfs_fail(job.rc, "%s", job.err);
            goto done;
        }
        st->frames_used = (size_t)lr.src.sync.used;
        st->lag_median = lr.src.lag_median;
        st->lag_p99 = lr.src.lag_p99;
        /* live's estimate against the truth of this iteration. */
        snprintf(path, sizeof path, "%s/truth.fits", rdir);
        if ((rc = swfs_fits_read_real(pup, "WFE", &wfe, NULL)) || (rc = swfs_fits_read_real(path, "NCP", &truth, NULL)))
            goto done;
        swfs_wfe_compare(wfe->data, truth->data, mask, np, &st->estimate_err, NULL, NULL);
        swfs_real_free(wfe);
        swfs_real_free(truth);
        wfe = truth = NULL;
        /* The simulator reads the DM stream: the surface its offsets make. */
        if ((rc = swfs_shm_open(&dm, shm, "dm"))) goto done;
        size_t got = 0;
        swfs_shm_frame fm;
        if ((rc = swfs_shm_read_latest(dm, cmd, &fm, &got))) goto done;
        if (!got || swfs_shm_frame_values(dm) != nact) {
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: no offsets of %zu actuators after iteration %zu", swfs_shm_get_path(dm),
                           nact, k);
            goto done;
        }
        swfs_shm_close(dm, 0);
        dm = NULL;
        swfs_dmfit_surface(fit, cmd, surf);
        double s2 = 0;
        for (size_t a = 0; a < nact; a++) s2 += cmd[a] * cmd[a];
        r->s[k + 1].dm_rms = swfs_dmfit_active(fit) ? sqrt(s2 / (double)swfs_dmfit_active(fit)) : 0.0;
    }
    r->seconds = swfs_wall_seconds() - t0;
done:;
    char saved[4096];
    snprintf(saved, sizeof saved, "%s", swfs_last_error());
    swfs_shm_close(dm, 0);
    if (swfs_shm_open(&dm, shm, "dm") == SWFS_OK) swfs_shm_close(dm, 1); /* the demo's own DM channel */
    if (rc) swfs_fail(rc, "%s", saved);
    free(mask); free(ncp0); free(user); free(surf); free(res); free(zeros); free(map); free(xy); free(cmd);
    swfs_dmfit_free(fit);
    swfs_real_free(wfe);
    swfs_real_free(truth);
    return rc;
}

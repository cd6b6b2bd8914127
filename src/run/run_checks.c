/* Whether a run's options fit together and lie in range, before any file is opened: the
 * checks every caller gets (the command line, Python, an application), with the messages
 * the command line prints. See include/specklewfs/run.h and live.h. */
#include "specklewfs/run.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/live.h"
#include "specklewfs/engine.h"
#include "specklewfs/pupil.h"
#include "specklewfs/speckles.h"
#include "specklewfs/stream.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <math.h>
#include <stdint.h>
#include <string.h>

#define FAIL(...) return swfs_fail(SWFS_ERR_ARG, __VA_ARGS__)

/* The ranges of the batch size, shared by the runs (frames per call; 100000 is far beyond
 * any camera's frames per update and keeps a call's buffers within memory). */
#define BATCH_MAX 100000

/* The mean loops' options that speckles and stream share: folders (at least 2) or the loops the
 * run simulates (mean_teach: 0, 1 or AUTO; mean_teach_loops of them; with the linear model,
 * not with folders, not in a team); what --mean-loop teach goes with otherwise is the caller's. */
static int mean_loop_checks(const char *const *loops, size_t nloops, int mean_teach, size_t mean_teach_loops,
                            size_t max_loops, int basis, const char *basis_why, const swfs_team *team)
{
    if (nloops == 1 || (nloops && !loops))
        FAIL("--mean-loop: the residual mean's miss needs at least 2 simulated loops (each is checked against the "
             "others'), got %zu", nloops);
    for (size_t k = 0; k < nloops; k++)
        if (!loops[k]) FAIL("--mean-loop %zu: no folder given", k + 1);
    if (mean_teach != 0 && mean_teach != 1 && mean_teach != SWFS_MEAN_TEACH_AUTO)
        FAIL("mean_teach must be 0, 1 or SWFS_MEAN_TEACH_AUTO (-1), got %d", mean_teach);
    if (mean_teach_loops < 2 || mean_teach_loops > SWFS_MEAN_TEACH_MAX)
        FAIL("--mean-teach-loops must be 2..%d (each loop is checked against the others'), got %zu",
             SWFS_MEAN_TEACH_MAX, mean_teach_loops);
    if (max_loops && (max_loops < mean_teach_loops || max_loops > SWFS_MEAN_TEACH_MAX))
        FAIL("--mean-teach-max-loops must be --mean-teach-loops (%zu)..%d, got %zu", mean_teach_loops,
             SWFS_MEAN_TEACH_MAX, max_loops);
    if (mean_teach == 1) {
        if (!basis) FAIL("--mean-loop teach goes with the linear model (--basis); %s", basis_why);
        if (nloops) FAIL("--mean-loop takes loops' folders or teach, not both");
        if (team && team->size > 1) FAIL("--mean-loop teach runs in one process, not in a team");
    }
    return SWFS_OK;
}

int swfs_speckles_run_options_check(const swfs_speckles_run_options *o)
{
    swfs_speckles_run_options d;
    swfs_speckles_run_options_default(&d);
    const swfs_pipeline_options *p = &o->pipe;
    const int recon = p->recon, basis = o->lin.basis != NULL;
    if (!o->timing || !o->science || !(o->actuators || basis) || !o->out)
        FAIL("needs TIMING.txt, --science, --actuators (or --basis) and -o");
    if (basis && (o->actuators || recon == SWFS_RECON_GIVEN || o->valid))
        FAIL("--basis (the linear model) takes no --actuators, --recon W.fits or --valid (its control or interaction "
             "matrix takes the telemetry as it is)");
    if (basis && o->write_recon && !o->lin.imat)
        FAIL("--write-recon with --basis writes the reconstructor made from --imat (the map from the telemetry to the "
             "basis coefficients); a --control map is its own file, and without either there is no map");
    if (!basis && (o->lin.control || o->lin.imat || o->lin.reg.pitch > 0 || o->lin.scale != 1))
        FAIL("--control, --imat, --dm-* and --coef-scale go with --basis");
    if (recon != SWFS_RECON_TEACH && recon != SWFS_RECON_VK && recon != SWFS_RECON_MAP && recon != SWFS_RECON_SVD &&
        recon != SWFS_RECON_GIVEN)
        FAIL("--recon: unknown reconstructor %d (expected teach, vk, map, svd or a file)", recon);
    if (recon == SWFS_RECON_GIVEN && !o->recon) FAIL("--recon W.fits: no file given");
    if (!(p->rcond >= 0 && p->rcond < 1)) FAIL("--rcond must be in [0, 1), got %g", p->rcond);
    if ((p->rcond != d.pipe.rcond || p->max_modes != d.pipe.max_modes) && recon != SWFS_RECON_SVD)
        FAIL("--rcond and --modes go with --recon svd");
    if (!(p->slope_noise >= 0) || !isfinite(p->slope_noise))
        FAIL("--slope-noise must be a finite rms >= 0 [rad], got %g", p->slope_noise);
    if (p->slope_noise > 0 && recon != SWFS_RECON_MAP && recon != SWFS_RECON_VK)
        FAIL("--slope-noise goes with --recon vk or map");
    if (!(p->vk_l0 >= 0) || !isfinite(p->vk_l0))
        FAIL("--vk-l0 must be an outer scale > 0 [m] (0: fitted), got %g", p->vk_l0);
    if (!isfinite(p->recon_scale) || p->recon_scale == 0)
        FAIL("--recon-scale must be a finite, non-zero factor, got %g", p->recon_scale);
    if (p->recon_scale != 1 && recon != SWFS_RECON_GIVEN) FAIL("--recon-scale goes with --recon W.fits");
    if (p->threads < 1 || p->threads > SWFS_ENGINE_MAX_THREADS)
        FAIL("--threads must be 1..%d, got %d", SWFS_ENGINE_MAX_THREADS, p->threads);
    if (o->batch > BATCH_MAX) FAIL("--batch must be 1..%d, got %zu", BATCH_MAX, o->batch);
    const int mrc = mean_loop_checks(o->mean_loops, o->nmean_loops, o->mean_teach, o->mean_teach_loops,
                                     o->mean_teach_max_loops, basis,
                                     "with --actuators the default teaches its map from loops of the system already",
                                     o->team);
    if (mrc) return mrc;
    if ((o->nmean_loops || o->mean_teach == 1) && p->wfs_rate) FAIL("--mean-loop goes with camera exposures, not --wfs-rate");
    if (o->loops_map != 0 && o->loops_map != 1 && o->loops_map != SWFS_LOOPS_MAP_AUTO)
        FAIL("loops_map must be 0, 1 or SWFS_LOOPS_MAP_AUTO (-1), got %d", o->loops_map);
    if (o->loops_map == 1 && !(basis && o->lin.imat && (o->nmean_loops || o->mean_teach == 1)))
        FAIL("--loops-map choose goes with the linear model's --imat (the map it is chosen against) and mean loops "
             "(--mean-loop DIR... or teach)");
    const int taught = recon == SWFS_RECON_TEACH && !basis;
    if ((o->teach_loops != d.teach_loops || o->teach_max_loops != d.teach_max_loops || o->teach_keep_loops) && !taught)
        FAIL("--teach-loops, --teach-max-loops and --teach-keep-loops go with --recon teach (the default with "
             "--actuators)");
    if ((o->teach_work || o->teach_seed != d.teach_seed || o->teach_again || o->nteach_keys) && !taught &&
        !(basis && o->mean_teach))
        FAIL("--teach-work, --teach-seed, --teach-again and --teach-set go with --recon teach (the default with "
             "--actuators) or --mean-loop teach");
    for (size_t k = 0; k < o->nteach_keys; k++)
        if (!o->teach_keys || !o->teach_keys[k] || !strchr(o->teach_keys[k], '=') || o->teach_keys[k][0] == '=')
            FAIL("--teach-set takes key=value (simulate mode=timeseries keys), got '%s'",
                 o->teach_keys && o->teach_keys[k] ? o->teach_keys[k] : "(null)");
    /* known keys with values in range, on the simulator's default system (the files' description
     * then replaces its geometry): refused here, before anything is read, rather than taken for a
     * reason teach could not teach (which falls back to the von Karman map) */
    if (o->nteach_keys) {
        swfs_ts_params tp;
        const int rc = swfs_ts_params_from_keys(o->teach_keys, o->nteach_keys, &tp);
        if (rc) return swfs_fail_context(rc, "--teach-set");
    }
    if (o->teach_again & ~1) FAIL("teach_again must be 0 or 1, got %d", o->teach_again);
    if (o->teach_loops < 2 || o->teach_loops > 64) FAIL("--teach-loops must be 2..64, got %zu", o->teach_loops);
    if (o->teach_max_loops && (o->teach_max_loops < o->teach_loops || o->teach_max_loops > 64))
        FAIL("--teach-max-loops must be --teach-loops (%zu) to 64 (0: 4 times --teach-loops, at most 64), got %zu",
             o->teach_loops, o->teach_max_loops);
    if (o->teach_seed > (uint64_t)INT64_MAX) FAIL("--teach-seed must be >= 0 and below 2^63");
    if (!(o->wfs_hz >= 0) || !isfinite(o->wfs_hz)) FAIL("--wfs-hz must be a rate > 0 [Hz], got %g", o->wfs_hz);
    if (p->wfs_rate && o->nmatch) FAIL("--match pairs camera frames; it does not apply with --wfs-rate");
    if (!p->wfs_rate && o->wfs_hz > 0) FAIL("--wfs-hz goes with --wfs-rate");
    if (o->mean_mode != SWFS_MEAN_ENSEMBLE && o->mean_mode != SWFS_MEAN_CUBE)
        FAIL("--mean: unknown mode %d (expected ensemble or cube)", o->mean_mode);
    for (size_t k = 0; k < o->nmatch; k++)
        if (!o->match_in || !o->match_out || !o->match_in[k] || !o->match_out[k])
            FAIL("--match %zu: needs IN.fits and OUT.fits", k + 1);
    return SWFS_OK;
}

/* What stream and live share: the run's numbers and choices. */
static int stream_ranges(const swfs_stream_run_options *o)
{
    if (o->threads < 1 || o->threads > SWFS_ENGINE_MAX_THREADS)
        FAIL("--threads must be 1..%d, got %d", SWFS_ENGINE_MAX_THREADS, o->threads);
    if (!(o->stream.every_seconds >= 0)) FAIL("--every-seconds must be >= 0, got %g", o->stream.every_seconds);
    if (!isnan(o->read_noise) && !(o->read_noise >= 0 && isfinite(o->read_noise)))
        FAIL("--read-noise must be >= 0 [counts] (NaN: from the science header), got %g", o->read_noise);
    if (!isnan(o->gain) && !(o->gain >= 0 && isfinite(o->gain)))
        FAIL("--gain must be >= 0 [e-/count] (NaN: from the science header), got %g", o->gain);
    if (!(o->g_smooth_lod >= 0) || !isfinite(o->g_smooth_lod))
        FAIL("--g-smooth must be >= 0 [lambda/D], got %g", o->g_smooth_lod);
    if (o->pupil_method != SWFS_PUPIL_AUTO && o->pupil_method != SWFS_PUPIL_FIT && o->pupil_method != SWFS_PUPIL_MOMENTS)
        FAIL("--pupil-method: unknown method %d (expected fit or moments)", o->pupil_method);
    if (o->pupil_source != SWFS_SOURCE_HALO_LF && o->pupil_source != SWFS_SOURCE_HALO)
        FAIL("--pupil-source: unknown source %d (expected halo_lf or halo)", o->pupil_source);
    if (o->stream.static_mode != SWFS_STATIC_AUTO && o->stream.static_mode != SWFS_STATIC_NONE &&
        o->stream.static_mode != SWFS_STATIC_GIVEN)
        FAIL("--static: unknown mode %d (expected auto, none or a file)", o->stream.static_mode);
    if (o->stream.static_mode == SWFS_STATIC_GIVEN && !o->static_file) FAIL("--static FILE: no file given");
    const int mrc = mean_loop_checks(o->mean_loops, o->nmean_loops, o->mean_teach, o->mean_teach_loops,
                                     o->mean_teach_max_loops, o->lin.basis != NULL, "with --recon and --actuators give the map speckles "
                                     "taught from loops of the system", o->team);
    if (mrc) return mrc;
    if (o->mean_teach == 1 && !o->timing)
        FAIL("--mean-loop teach describes the system from the files of a timing table (--timing)");
    if ((o->teach_work || o->teach_again) && o->mean_teach == 0)
        FAIL("--teach-work and --teach-again go with the loops stream simulates (--mean-loop teach, a pyramid's "
             "default)");
    return SWFS_OK;
}

int swfs_stream_run_options_check(const swfs_stream_run_options *o)
{
    const int basis = o->lin.basis != NULL;
    if (!o->timing == !o->nwfs_logs || !o->science || !((o->recon && o->actuators) || basis) || !o->out)
        FAIL("needs --timing or --wfs-log (one of them), --science, --recon and --actuators (or --basis) and -o");
    if (basis && (o->recon || o->actuators || o->valid))
        FAIL("--basis (the linear model) takes no --recon, --actuators or --valid");
    if ((o->clock || o->exptime != 0) && !o->nwfs_logs) FAIL("--clock and --exptime go with --wfs-log");
    if (!(o->exptime >= 0) || !isfinite(o->exptime)) FAIL("--exptime must be >= 0 s, got %g", o->exptime);
    if (o->batch < 1 || o->batch > BATCH_MAX) FAIL("--batch must be 1..%d, got %zu", BATCH_MAX, o->batch);
    for (size_t k = 0; k < o->nwfs_logs; k++)
        if (!o->wfs_logs || !o->wfs_logs[k]) FAIL("--wfs-log %zu: no folder or file given", k + 1);
    return stream_ranges(o);
}

int swfs_live_options_check(const swfs_live_options *o)
{
    const swfs_stream_run_options *r = &o->run;
    if (r->mean_teach == 1 || r->teach_work || r->teach_again)
        FAIL("--mean-loop teach describes the system from recorded files; a live run takes the loops speckles or "
             "stream made (--mean-loop DIR --mean-loop DIR ...)");
    if (!o->src.nwfs || !o->src.camera || !r->science || !((r->recon && r->actuators) || r->lin.basis) || !r->out)
        FAIL("needs --wfs, --camera, --geom, --recon and --actuators (or --basis) and -o");
    if (r->lin.basis && (r->recon || r->valid)) FAIL("--basis (the linear model) takes no --recon or --valid");
    if (o->dm_out && !r->actuators) FAIL("--dm-out fits the offsets onto --actuators");
    if (o->dm_out && !r->pupil_out) FAIL("--dm-out needs --pupil-out (the WFE it corrects)");
    if (o->src.sync.batch < 1 || o->src.sync.batch > BATCH_MAX)
        FAIL("--batch must be 1..%d, got %zu", BATCH_MAX, o->src.sync.batch);
    const struct { const char *name; double v; } nonneg[] = {
        {"--max-wait", o->src.sync.max_wait}, {"--exptime", o->src.sync.exptime}, {"--timeout", o->src.timeout},
        {"--idle-exit", o->src.idle},         {"--dm-max-step", o->dm_max_step},  {"--dm-max-rms", o->dm_max_rms},
        {"--dm-settle", o->dm_settle},
    };
    for (size_t k = 0; k < sizeof nonneg / sizeof nonneg[0]; k++)
        if (!(nonneg[k].v >= 0)) FAIL("%s must be >= 0, got %g", nonneg[k].name, nonneg[k].v);
    if (!(o->src.poll > 0)) FAIL("--poll must be > 0 [s], got %g", o->src.poll);
    if (!(o->dm_gain > 0) || !isfinite(o->dm_gain)) FAIL("--dm-gain must be > 0, got %g", o->dm_gain);
    if (!isfinite(o->dm_scale) || o->dm_scale == 0) FAIL("--dm-scale must be finite and non-zero, got %g", o->dm_scale);
    if (!(o->dmfit.coupling > 0 && o->dmfit.coupling < 1)) FAIL("--coupling must be in (0, 1), got %g", o->dmfit.coupling);
    if (!(o->dmfit.reg >= 0)) FAIL("--reg must be >= 0, got %g", o->dmfit.reg);
    if (o->dmfit.modes > 5000) FAIL("--modes must be 0..5000, got %zu", o->dmfit.modes);
    return stream_ranges(r);
}

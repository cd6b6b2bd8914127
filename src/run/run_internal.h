/* Private to src/run/. */
#ifndef SWFS_RUN_INTERNAL_H
#define SWFS_RUN_INTERNAL_H

#include <stddef.h>

#include "specklewfs/live.h"
#include "specklewfs/run.h"
#include "specklewfs/wind.h"

/* The caller's provenance lines followed by `extra` (a new array the caller frees; the
 * strings are not copied). NULL when out of memory. */
const char **swfs_prov_plus(const char *const *prov, size_t nprov, const char *extra);

/* The streaming run of swfs_stream_run_files with another source of batches than the
 * timing table's files (live: shared-memory streams, run_live.c). With hooks, o->timing
 * is not used and o->science only gives the geometry, the frame size and the noise model.
 * prepare (may be NULL) is called once the pipeline is built (its info says the slopes
 * and the frame size) and before the first batch; after (may be NULL) after every product
 * update with the stream itself, the estimate and the pupil product (NULL when not
 * written); a non-zero return of either stops the run with that status. */
typedef struct swfs_run_hooks {
    swfs_source_fn source;
    void *source_ctx;
    int (*prepare)(void *ctx, const swfs_pipeline_info *info, const long *lags); /* lags: a space-time map's
                                                                            info.nlags; NULL: per frame */
    int (*after)(void *ctx, swfs_stream *s, const swfs_halo *h, const swfs_pupil_result *pupil, int final);
    void *ctx;
    int offline;  /* 1: files as the source (milk logs): a failed run removes the products it
                     wrote, as the timing table's run does; 0 (live) keeps them */
} swfs_run_hooks;

/* Wait up to o->wait_reader for a reader on both streams; *waited = the seconds waited. */
int swfs_replay_wait_readers_(const swfs_replay_options *o, const swfs_shm *w, const swfs_shm *c, double *waited);
/* replay --wfs-log: a WFS milk log and the science cube's STAMPS, as logged (run_replay_milk.c). */
int swfs_replay_milk_run_(const swfs_replay_options *o, swfs_replay_result *r);

/* stream --wfs-log: milk logs + STAMPS of the science cube through framesync (run_stream_milk.c). */
int swfs_stream_run_milk(const swfs_stream_run_options *o, swfs_stream_run_result *r);

int swfs_stream_run_hooked(const swfs_stream_run_options *o, const swfs_run_hooks *hk, swfs_stream_run_result *r);

/* The telemetry file just before (step -1) or after (+1) name (relative to dir, as a timing
 * table or handshake log names it): the numbered neighbour when it exists (slopes_004.fits ->
 * slopes_005.fits, the same width), else the neighbour among the folder's files named like it
 * (the same length, differing in digits only: time stamps) in the order of their names, else
 * the one before or after it in the order a list first names them: the n names at order,
 * order + stride, ... (a name field of an array of structs: the handshake log's or the timing
 * table's rows; order NULL: none). 1 with buf set, 0 if none. Whether it continues name is
 * the data's to say (sync.h swfs_sync_boundary_check). */
int swfs_telemetry_neighbour_(const char *dir, const char *name, int step, const char *order, size_t stride, size_t n,
                              char *buf, size_t cap);

/* A space-time reconstructor's input stacked across telemetry files: the file in memory with
 * up to `margin` (its largest |lag|) frames of the file before it prepended and of the file
 * after it appended, each only where the telemetry says the two continue each other
 * (swfs_sync_boundary_check on their edges: contiguous; a file without a neighbour, or one the
 * check calls not contiguous or cannot tell, leaves that side to the clamping of
 * swfs_slopes_stack). ext holds pre + ny + post frames; joined / clamped count the boundaries
 * so decided over the calls. A neighbour that cannot be read (another width, a non-finite
 * slope, a truncated file) leaves that side clamped too, counted in unreadable, the last
 * reason in why: the run's own cubes do not need it. */
typedef struct swfs_lag_edges_ {
    double *ext;
    size_t cap, pre, post, ny;
    size_t joined, clamped, unreadable;
    char why[512];
} swfs_lag_edges_;
int swfs_lag_edges_load_(swfs_lag_edges_ *e, const char *tdir, const swfs_timing *t, const char *name,
                         const swfs_real *s, size_t margin);
void swfs_lag_edges_free_(swfs_lag_edges_ *e);

/* A space-time reconstructor's input, piece by piece of a telemetry file (speckles and
 * stream): the file's edges (swfs_lag_edges_) loaded when the file changes, the piece's frames
 * stacked at the lags (wfs.h swfs_slopes_stack) into a buffer that grows to the largest piece
 * once. */
typedef struct swfs_lag_stacker_ {
    swfs_lag_edges_ edges;
    char edges_for[8192];   /* the telemetry file the edges are of ("" none) */
    double *buf;
    size_t cap;             /* frames buf holds */
} swfs_lag_stacker_;
/* Frames [k0, k0 + n) of the telemetry file `path` (s: its frames, nslopes x WFS frames;
 * name: the timing table's name for it in tdir, where its neighbours are looked up; tdir
 * NULL: none, clamped at its ends) stacked at the nl lags, in *out (valid until the next
 * call). */
int swfs_lag_stacker_rows_(swfs_lag_stacker_ *st, const char *tdir, const swfs_timing *t, const char *name,
                           const char *path, const swfs_real *s, const long *lags, size_t nl, size_t k0, size_t n,
                           const double **out);
void swfs_lag_stacker_free_(swfs_lag_stacker_ *st);

/* What a telemetry series does in time, for a space-time map's checks (learn records it of
 * its training loops, speckles measures it on the observation). wind (may be NULL): its wind
 * in subapertures per WFS frame (wind.h with pitch and rate 1: nothing the files lack);
 * found = 0 when none is tracked, or when the slopes are the used subapertures' only and no
 * map says which. corr (may be NULL): the slopes' correlation at each lag
 * (swfs_slopes_lag_correlation). */
int swfs_spacetime_stats_(const double *s, size_t nframes, size_t nslopes, size_t nsub, const unsigned char *valid,
                          const long *lags, size_t nlags, swfs_wind_estimate *wind, double *corr);

/* A space-time reconstructor's checks (run.h swfs_speckles_run_result st_*): the keys `learn
 * --lags` wrote into the file recon (its training loops' layers and slopes' correlation at
 * the nl lags) against the same measured on the observation's slopes s (nframes x nslopes;
 * the Shack-Hartmann's nsub across; valid: its map when the slopes are the used
 * subapertures' only). The st_* fields are reset first; recon NULL or nl < 2: only that; s
 * NULL: the file's keys only. A file or series without them is no error. */
int swfs_spacetime_check_(const char *recon, const long *lags, size_t nl, const double *s, size_t nframes,
                          size_t nslopes, size_t nsub, const char *valid, swfs_speckles_run_result *r);

/* --tiptilt frame (speckles.h): the speckles lose every WFS frame's mean-slope tilt, while
 * reduce centred every science frame on its peak, which follows the Z-tilt and the NCP's own
 * tilt. (dx[k], dy[k]) [camera pixels] for the usable cubes' frames k of the timing table t
 * (telemetry names relative to tdir): the registered frame k is to be taken at p - (dx, dy),
 * which centres it on the exposure-mean mean slopes (mapped by sync's pairing, tilt [rad] /
 * (PIXSCALE lambda / D) pixels) instead of its peak (science's TRACK); mean shift 0. */
int swfs_frame_recentre_shifts(const char *tdir, const swfs_timing *t, const char *science, const swfs_geom *g,
                               double *dx, double *dy);

/* The speckles' tip-tilt treatment against the science frames' registration (science.h
 * REGISTER, of the open cube fs at path): speckles that keep the image motion (--tiptilt
 * keep) describe frames that kept it; on frames re-centred on their peak (reduce's default)
 * their halo's NCP fails by an order of magnitude (docs/telemetry.md), so that pairing is
 * SWFS_ERR_VALUE naming the file. speckles and stream check it. */
int swfs_science_tiptilt_check(swfs_fits_in *fs, const char *path, int tiptilt);

/* The linear model's files as inputs of a command's path check (outpaths.h). */
struct swfs_paths;
void swfs_linear_paths(struct swfs_paths *p, const swfs_linear_files *lf);
/* The inputs (science cube, reconstructor, actuators, the linear model's files, mask, static
 * halo) and the outputs every stream run checks, whatever its source (run_stream.c). */
void swfs_stream_paths_inputs(struct swfs_paths *p, const swfs_stream_run_options *o);
void swfs_stream_paths_outputs(struct swfs_paths *p, const swfs_stream_run_options *o);

/* One key into c unless it is there (printf's format for its value): what the files say of a
 * system adds only the keys the user did not give. */
int swfs_config_put_(swfs_config *c, const char *key, const char *fmt, ...);

/* The telemetry files the timing table names, each once, in the table's order (names: at
 * least t->ncubes slots; each strdup'd). */
int swfs_speckles_table_files_(const swfs_timing *t, const char *tdir, char **names, size_t *n);
/* speckles' teach folder: o->teach_work, or beside o->out (swfs_teach_work_default); created
 * (*made = 1 when this call made it). */
int swfs_speckles_work_folder_(const swfs_speckles_run_options *o, char *work, size_t cap, int *made);
/* FNV-1a (64 bits) of a text with its NUL, and of a file's contents after its label and with
 * its length (speckles' fingerprints of what teach's products depend on). */
uint64_t swfs_fnv_text_(uint64_t h, const char *s);
int swfs_fnv_file_(uint64_t *h, const char *label, const char *path);

/* A simulated loop's first WFS frame in an exposure (DIR/truth_timing.txt: the earliest cube's
 * start), 0 without the file: the frames before it (the loop closing from a flat DM) are not in
 * its truth's mean, nor then in its telemetry's. */
size_t swfs_loop_first_frame_(const char *dir);
/* Loops k = first..first+n-1 of o->sim as described (its layers), seeds o->seed + k, into
 * o->work/NAME_NN (NAME at most 7 characters), as many at once as its threads allow, with the
 * true residual (truewf_NNN.fits) where o->sim.export_truth; what: the progress's stage. */
int swfs_teach_loops_(const swfs_teach_run_options *o, const char *name, size_t first, size_t n, const char *what);
/* Teach's space-time loops after a learning curve lr over `have` of them (run_teach.c, 4b):
 * the count to simulate up to, at most max_loops (have: no more). As many as bring the map
 * to SWFS_LEARN_CURVE_EXCESS where the curve asks for more frames than they hold; where it was
 * measured and does not fall it cannot tell, and the loops are doubled once (*doubled set). */
size_t swfs_teach_more_loops_(const swfs_learn_run_result *lr, size_t have, size_t max_loops, int *doubled);
/* teach's loops after a curve over `have` of them (the first loops: `first`): as
 * swfs_teach_more_loops_, but a measured first curve that asks for at most twice the first
 * loops doubles them (*doubled set), so that the curve over them decides (teach rule 2026-12-08). */
size_t swfs_teach_next_loops_(const swfs_learn_run_result *lr, size_t have, size_t first, size_t max_loops,
                              int *doubled);
/* 1 where a learning curve falls, beyond twice its parts' scatter, faster than any a + b / n
 * with a > 0 allows (its two points put the map of unlimited frames at or below zero misfit:
 * more frames help without a bound it can name). The loops a curve asked for are the last
 * unless their own curve says this; then teach goes on to its budget, max_loops. */
int swfs_teach_curve_unbounded_(const swfs_learn_run_result *lr);
/* How far a calibration loop's mode variances (a, na) are from the observation's (b, nb)
 * (run_teach.c): the rms of log10 a / b over the upper half of the modes, about its mean over
 * all of them; INFINITY with fewer than 2 modes to compare. */
double swfs_teach_profile_misfit_(const double *a, size_t na, const double *b, size_t nb);

/* Whether a run simulates the mean loops (run_mean_teach.c): --mean-loop teach, or the default
 * (SWFS_MEAN_TEACH_AUTO) for the linear model where no loops are given, the output is per
 * camera exposure (not per_wfs_frame, speckles --wfs-rate) and the --control map carries no
 * miss of its own (MEANMISS). */
int swfs_mean_teach_wanted_(int mean_teach, const swfs_linear_files *lin, size_t nmean_loops, int per_wfs_frame);

/* speckles --mean-loop teach (run_mean_teach.c): the loops of the system the observation's
 * files describe, simulated (or reused) into r->work/mean_NN; dirs[k] their folders and, where
 * r->done, loops[k] pointing at them (r->nloops of them, SWFS_MEAN_TEACH_MAX long): what
 * swfs_pipeline_mean_loops takes. nslopes: the telemetry's values per frame. */
int swfs_speckles_mean_teach_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                              const swfs_geom *g, size_t nslopes, swfs_mean_teach_result *r, char (*dirs)[4400],
                              const char **loops);

/* run_loops_map.c: the loops' own map and the self-check's choice (run.h loops_map), after o's
 * run wrote o->out from the interaction matrix with the mean loops o->mean_loops (its miss
 * held out: imat_heldout) through its pipeline p (its map, swfs_pipeline_linear_map, and the
 * telemetry's mean over the exposures, for the misses the written maps carry); g, mask: the
 * run's geometry and pupil (swfs_pipeline_mask). Always
 * SWFS_OK: where it cannot, r->fallback says why and o->out stays. */
int swfs_speckles_loops_map_(const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask,
                             double imat_heldout, swfs_pipeline *p, swfs_loops_map_result *r);
/* run_loops_map.c: 1 where o's run learns the loops' own map from its mean loops (the linear
 * model's interaction matrix; --loops-map choose, or auto where the loops are of a pyramid):
 * speckles' condition for swfs_speckles_loops_map_, and the mean loops' for more loops where
 * that map's learning curve asks (run_mean_teach.c) */
int swfs_loops_map_wanted_(const swfs_speckles_run_options *o, int pyramid_loops);
/* Teach's space-time lags (run_teach.c): 0, -L1, L1, -2 L1, 2 L1 with L1 = round(frames), the
 * WFS frames in which the fastest layer moves half a subaperture (at least 1; frames <= 0, no
 * layer tracked: 1, the loop's own time scale), into lags (SWFS_SPACETIME_NLAGS of them). */
#define SWFS_SPACETIME_NLAGS 5
void swfs_spacetime_lags_(double frames, long *lags);
/* The loops' map's lags by that rule: the fastest layer `wind` tracks in the loop folder
 * loop0's telemetry (slopes_000.fits; *speed [subapertures per WFS frame], 0 where none is
 * tracked or the values are not a Shack-Hartmann layout of 2 nsub^2); *nl = SWFS_SPACETIME_NLAGS. */
int swfs_loops_map_lags_(const char *loop0, long *lags, size_t *nl, double *speed);

/* swfs_teach_describe with the science cube's geometry already in hand (g: read, overlaid
 * with what the caller gives, required): the keys it and the other files give, into c. */
int swfs_teach_describe_geom_(swfs_config *c, const swfs_geom *g, const char *actuators, const char *pupil,
                              const char *valid, const char *telemetry);

/* TEACHSEL of a taught map: the names of SWFS_TEACH_SPACETIME, _PERFRAME, _PERFRAME_MIXED,
 * _PERFRAME_PRIOR (maps taught before 2026-12-03), _SPACETIME_PRIOR (run_teach.c writes them,
 * run_speckles_teach.c reads them back when it reuses a map). */
extern const char *const swfs_teach_chosen_names_[5];

/* speckles' taught reconstructor (SWFS_RECON_TEACH, run_speckles_teach.c): teach from the
 * timing table t's telemetry files (in tdir) and the run's own files, g the science cube's
 * geometry. SWFS_OK with r->taught = 1 and r->teach_map the taught file; or SWFS_OK with
 * r->taught = 0 and r->teach_fallback saying why teach could not (the caller uses the von
 * Karman map); an error only for a team's failure to agree. */
int swfs_speckles_teach_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                         const swfs_geom *g, swfs_speckles_run_result *r);
/* Whether speckles compares the loops' DM models (run.h dm_choice_done): a taught map, one
 * process, camera frames, and teach told neither dm_coupling nor ao_recon. */
int swfs_speckles_dm_choice_wanted_(const swfs_speckles_run_options *o, const swfs_speckles_run_result *r);
/* The second map, its loops' DM Gaussian functions of SWFS_TEACH_DM_GAUSS, taught (or reused)
 * in the teach folder's SWFS_TEACH_DM_DIR as swfs_speckles_teach_ teaches the first (a team's
 * member 0, the others take its map): map, teach's result, the fingerprint, reused, *taught
 * or fallback saying why not; an error only for a request to stop or a team's failure to agree. */
int swfs_speckles_teach_dm_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                            const swfs_geom *g, char *map, size_t cap, struct swfs_teach_run_result *tr,
                            char fpr[17], int *reused, int *taught, char *fallback, size_t fcap);

/* run_modal_slopes.c: P = CM+ CM (ns x ns, malloc'd), the projection modal-slopes' output went
 * through, from the control matrix file; *rank: CM's numerical rank. */
int swfs_modal_projector_(const char *cm_path, double **P, size_t *ns, size_t *rank);
/* Slopes s (frames x n) as that projection leaves them: s P (P symmetric), in place, one GEMM;
 * another width is SWFS_ERR_SHAPE, naming what. learn applies it to its data sets, teach to
 * its speed calibration loops. */
int swfs_modal_project_(const double *P, size_t n, swfs_real *s, const char *what);

/* run_learn.c: nsets vectors x (sets x n, row-major) of one quantity, each held out against the
 * mean of the others: returns sum (x_d - mean of the others)^2 over sum x_d^2 (NAN for fewer
 * than 2 sets or all zero; < 1: the others' mean predicts each set's), over the samples where
 * mask > 0 (NULL: all); mean = the sets' mean there (0 elsewhere); *own (may be NULL) = sum
 * x_d^2. With M (n x n, symmetric; mask NULL) each square is weighed by it instead, v^T M v
 * (work: 2 n doubles). The check of learn's MEANMISS (M: learn's meanmiss_metric) and of
 * speckles' --mean-loop. */
double swfs_heldout_mean_(const double *x, size_t nsets, size_t n, const double *mask, const double *M, double *work,
                          double *mean, double *own);

/* run_linear.c: the wavefront [m] on the PUPN x PUPN grid of lf's basis at the coefficients
 * coef (nk of them, the basis's count; scaled by lf->scale), 0 outside the illuminated samples
 * of mask (the pipeline's, swfs_pipeline_mask): what speckles adds to the residual's mean from
 * a learned control matrix's MEANMISS. */
int swfs_linear_wavefront_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, const double *coef,
                           size_t nk, double *out);
/* run_linear.c: the coefficients on lf's basis of m wavefronts given on the PUPN x PUPN grid
 * (wf: a cube's layout, wavefront j's samples at wf + j npup^2) by least squares over the
 * illuminated samples of mask: c = (A^T A + mu I)^-1 A^T w, A = scale x the basis there, mu =
 * SWFS_LINEAR_FIT_RIDGE x the mean diagonal of A^T A (a basis function that barely touches the
 * pupil is kept from running away, as the DM fit's default, dmfit.h). coef: nk x m row-major
 * (*nk the basis's count; the caller frees); *resid (may be NULL): the rms of A c - w over
 * the rms of w there. */
#define SWFS_LINEAR_FIT_RIDGE 1e-3
int swfs_linear_fit_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, const double *wf, size_t m,
                     double **coef, size_t *nk, double *resid);
/* run_learn.c: swfs_meanmiss_metric on functions in memory: inf (na functions of n x n samples,
 * function a's at inf + a n^2; each has its piston, tip and tilt removed over mask in place),
 * mask (n x n weights); `what` names them in a message. *M malloc'd, na x na. */
int swfs_meanmiss_metric_data_(double *inf, size_t na, size_t n, const double *mask, const char *what, double **M);
/* run_teach.c: a map's output grid finer than the DM (teach's, docs/telemetry.md "A map finer
 * than the DM"): a hexapolar grid of half the DM's pitch (sp's DM: its actuators file or its
 * own layout; at least two pupil samples) over sp's telescope, written to work/outgrid.fits
 * (its path into path), the points into *xy (*n, malloc'd), the DM's pitch into *dm_pitch. */
int swfs_outgrid_make_(const swfs_ts_params *sp, const char *work, char *path, size_t cap, double *dm_pitch,
                       double **xy, size_t *n);
/* run_linear.c: output points xy (n of them [m]) as a basis on the PUPN x PUPN grid (*B: PUPN^2
 * x n), their Clough-Tocher interpolation over the illuminated samples of mask, a rim beyond
 * their hull continued from the nearest sample inside within one pitch, as the
 * Shack-Hartmann's speckle model interpolates a map's own points (speckles.c); refused where
 * the points do not cover the pupil. */
int swfs_points_basis_(const double *xy, size_t n, const swfs_geom *g, const double *mask, struct swfs_sparse **B);
/* run_linear.c: the same points' functions, dense (*F: n functions, point k's at F + k PUPN^2;
 * the caller frees). */
int swfs_points_functions_(const double *xy, size_t n, const swfs_geom *g, const double *mask, double **F);
/* run_linear.c: lf's basis functions on the PUPN x PUPN grid, times lf->scale (*F: *nk
 * functions, function k's samples at F + k PUPN^2; the caller frees): a control matrix with
 * output points of its own (OUTXY) gives their interpolation, as every linear-model step does. */
int swfs_linear_functions_(const swfs_linear_files *lf, const swfs_geom *g, const double *mask, double **F, size_t *nk);
/* 1 where the map file `path` has a MEANMISS extension (its own miss of the mean: the default's
 * mean loops are not simulated for it, run_speckles.c, run_stream.c); 0 otherwise or NULL */
int swfs_map_has_meanmiss_(const char *path);

#endif

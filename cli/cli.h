/* The command line: the only place that prints or exits. Each subcommand lives in
 * cli/cmd_<name>.c as `int swfs_cmd_<name>(int argc, char **argv)` (argv[0] is the
 * subcommand name) and returns the process exit code. Register it in cli/main.c. */
#ifndef SWFS_CLI_H
#define SWFS_CLI_H

#include <stddef.h>
#include <stdio.h>

int swfs_cmd_estimate(int argc, char **argv);
int swfs_cmd_pupil(int argc, char **argv);
int swfs_cmd_simulate(int argc, char **argv);
int swfs_cmd_demo(int argc, char **argv);
int swfs_cmd_report(int argc, char **argv);
int swfs_cmd_reduce(int argc, char **argv);
int swfs_cmd_sync(int argc, char **argv);
int swfs_cmd_speckles(int argc, char **argv);
int swfs_cmd_merge(int argc, char **argv);
int swfs_cmd_stream(int argc, char **argv);
/* mode=timeseries of `simulate` (cli/cmd_simulate_ts.c), called from cmd_simulate.c. */
struct swfs_config;
int swfs_cmd_simulate_ts(struct swfs_config *cfg, const char *cfgfile, const char *outdir, int quiet, int argc,
                         char **argv);
int swfs_cmd_coherence(int argc, char **argv);
int swfs_cmd_dmoffsets(int argc, char **argv);
int swfs_cmd_correct(int argc, char **argv);
int swfs_cmd_live(int argc, char **argv);
int swfs_cmd_replay(int argc, char **argv);
int swfs_cmd_liveloop(int argc, char **argv);
int swfs_cmd_learn(int argc, char **argv);
int swfs_cmd_wind(int argc, char **argv);
int swfs_cmd_modal_slopes(int argc, char **argv);
int swfs_cmd_teach(int argc, char **argv);
/* The closed-loop table (cli/cmd_correct.c), also printed by `demo`. */
struct swfs_loop_result;
void cli_print_loop_table(const struct swfs_loop_result *r);

/* Exit codes. */
enum { CLI_OK = 0, CLI_FAIL = 1, CLI_USAGE = 2 };

/* Print "specklewfs <cmd>: <library message>" to stderr; return CLI_FAIL (128 + the signal
 * when SIGINT/SIGTERM stopped the run: cli_stage_progress). */
int cli_error(const char *cmd);
/* Print "specklewfs <cmd>: <formatted message>" to stderr; return CLI_USAGE. */
int cli_usage_error(const char *cmd, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;
/* A library options check (run.h *_options_check): 0 when rc is 0, else its message printed as
 * a usage error (CLI_USAGE). */
int cli_check(const char *cmd, int rc);
/* The usage texts of speckles, stream and live (help_speckles.c, help_stream.c), and of teach (help_teach.c),
 * printed to stdout. */
void cli_help_speckles(void);
void cli_help_stream(void);
void cli_help_live(void);
void cli_help_teach(void);
/* learn's usage text (help_learn.c) */
const char *cli_usage_learn(void);
/* Strict number parsing for option values; on failure prints and returns non-zero. */
int cli_parse_double(const char *cmd, const char *opt, const char *s, double *out);
int cli_parse_long(const char *cmd, const char *opt, const char *s, long *out);
/* The command line joined into one string, for provenance (HISTORY) cards. */
void cli_command_line(int argc, char **argv, char *buf, size_t cap);
/* The command line as the provenance lines of a library run (static storage: one command
 * runs per process); *n receives their count. */
const char *const *cli_provenance(int argc, char **argv, size_t *n);
/* Seconds since an arbitrary epoch (monotonic). */
double cli_now(void);
/* Progress on stderr: "\r<label> k/n" when stderr is a terminal, sparse lines otherwise. */
void cli_progress(const char *label, size_t k, size_t n);
/* The folder part of a path ("." when there is none). */
void cli_dir_of(const char *path, char *dir, size_t cap);
/* A progress callback for the library's long runs: ctx is a label prefix (const char *,
 * or NULL for none) put before the stage name. It returns non-zero once SIGINT or SIGTERM
 * asked the run to stop (cli_stop_catch), and cli_error then says which signal and returns
 * 128 + its number. */
int cli_stage_progress(void *ctx, const char *stage, size_t done, size_t total);
/* (cli/signals.c) The check inside cli_stage_progress: non-zero once SIGINT/SIGTERM asked
 * to stop, for a command's own progress callback; cli_stop_signal says which (0: none). */
int cli_stop_requested(void);
int cli_stop_signal(void);
/* Catch SIGINT and SIGTERM (where their disposition is the default) from now on, before a
 * stoppable command's first progress report: main does so for those commands, so that a
 * signal in the run's first moments stops it at that report rather than killing it. */
void cli_stop_catch(void);
/* For a command that does not stop at progress reports: SIGINT and SIGTERM (where their
 * disposition is the default) still end it at once, its part files removed first. */
void cli_end_catch(void);
/* A progress callback that prints nothing, only asks cli_stop_requested (a command whose
 * own lines show its progress: stream's updates). */
int cli_stop_check(void *ctx, const char *stage, size_t done, size_t total);
/* --tiptilt exposure|frame|keep -> SWFS_TT_* (speckles.h); prints and returns CLI_USAGE otherwise. */
int cli_parse_tiptilt(const char *cmd, const char *v, int *mode);
/* mkdir -p for an output folder; prints and returns non-zero on failure. */
int cli_make_dir(const char *cmd, const char *path);
/* The time-series simulator's parameters from CONFIG (NULL: none) with the key=value
 * overrides applied after it, checked (unused keys refused); prints and returns non-zero on
 * failure. filter_given, noise_given (or NULL): 1 where the keys give the modal filter
 * (ao_modes, ao_recon) or slope_noise, before describe adds the rest. */
struct swfs_ts_params;
int cli_ts_params(const char *cmd, const char *cfgfile, struct swfs_config *over, struct swfs_ts_params *p,
                  int *filter_given, int *noise_given, int (*describe)(struct swfs_config *, void *), void *ctx);
/* A command's files, checked before any work (specklewfs/outpaths.h): the paths' status,
 * printed as the command's error (CLI_FAIL) when it is a failure; frees p. */
struct swfs_paths;
int cli_paths_check(const char *cmd, struct swfs_paths *p);
/* DIR/name for each of the n names, as outputs of p. */
void cli_paths_outputs_in(struct swfs_paths *p, const char *dir, const char *const *names, size_t n);

/* Option parsing. Every helper prints its usage error and returns non-zero on failure. */
/* -h or --help. */
int cli_is_help(const char *a);
/* The value after the option argv[*i] (advancing *i), or NULL when there is none. */
const char *cli_next(int argc, char **argv, int *i);
/* The value of option argv[*i] as a string ("<option> needs <what>" when missing), a finite
 * number or an integer (cli_parse_double/long's messages); *i is advanced past it. */
int cli_take_string(const char *cmd, int argc, char **argv, int *i, const char *what, const char **out);
int cli_take_double(const char *cmd, int argc, char **argv, int *i, double *out);
int cli_take_long(const char *cmd, int argc, char **argv, int *i, long *out);
/* Integer options' lower bounds: the first below its bound named, with its value
 * ("<name> must be >= <min>, got <value>"), else 0. */
typedef struct cli_min {
    const char *name;
    long value, min;
} cli_min;
int cli_check_mins(const char *cmd, const cli_min *m, size_t n);
/* A number in [lo, hi] (an end excluded where its *_open is 1), else the usage error msg. */
int cli_take_range(const char *cmd, int argc, char **argv, int *i, double *out, double lo, int lo_open, double hi,
                   int hi_open, const char *msg);
/* An integer pair "X,Y" ("<opt> needs X,Y" / "<opt> expects X,Y (integers), got '<s>'"). */
int cli_parse_xy(const char *cmd, const char *opt, const char *s, long *x, long *y);
/* v is word a (-> va) or b (-> vb), else "<opt> expects 'a' or 'b', got 'v'". */
int cli_parse_choice(const char *cmd, const char *opt, const char *v, const char *a, int va, const char *b, int vb,
                     int *out);
/* A table of a command's plain options: a string, a number, an integer or a flag that sets
 * an int to `value`. */
typedef enum { CLI_STRING, CLI_DOUBLE, CLI_LONG, CLI_SET } cli_kind;
typedef struct cli_opt {
    const char *name; /* "-o", "--gain" */
    cli_kind kind;
    void *dst;        /* const char **, double *, long * or int * */
    const char *what; /* CLI_STRING: "<name> needs <what>" when the value is missing */
    int value;        /* CLI_SET: *(int *)dst = value */
} cli_opt;
/* argv[*i] against opts: 0 if it is none of them, 1 + the index of the one it is (value
 * parsed into dst, *i advanced past it), or -1 after printing the usage error. */
int cli_match(const char *cmd, const cli_opt *opts, size_t n, int argc, char **argv, int *i);
#define CLI_NOPTS(opts) (sizeof(opts) / sizeof((opts)[0]))
/* A command's arguments: -h/--help prints usage (when not NULL), the options of the table,
 * then special (may be NULL: returns 1 when it took argv[*i], 0 when not, -exit code after
 * printing an error), then positional arguments: "unknown option '<a>'" for anything else
 * starting with '-', the first empty slot *pos[k], then the list rest (argc entries; NULL:
 * "unexpected argument '<a>'"). Returns 0, -1 after the help, or the exit code of a
 * printed error. */
typedef struct cli_args {
    const char *cmd, *usage;
    const cli_opt *opts;
    size_t nopts;
    const char **const *pos;
    size_t npos;
    int (*special)(void *ctx, int argc, char **argv, int *i);
    void *ctx;
    const char **rest;
    size_t *nrest;
} cli_args;
int cli_parse_args(const cli_args *c, int argc, char **argv);
/* The DM fit's --influence, --coupling and --modes (dmoffsets, correct), a cli_args special:
 * 1 taken, 0 not one of them, -CLI_USAGE after the message. */
struct swfs_dmfit_options;
struct swfs_geom;
int cli_dmfit_option(const char *cmd, int argc, char **argv, int *i, struct swfs_dmfit_options *fo);
/* The given geometry (reduce, speckles, stream): --geom FILE (swfs_geom_read_file) and
 * --wavelen, --teldiam, --obscur, --pixscale, --pupdx, --pupn into g (later ones win); the
 * run checks the values. 1 when it took argv[*i], 0 when not, -exit code after an error. */
int cli_geom_option(const char *cmd, int argc, char **argv, int *i, struct swfs_geom *g);
/* --band auto|none|R (pipeline.h options.band: 0, -1, R > 0 [lambda/D]); same returns. */
int cli_band_option(const char *cmd, int argc, char **argv, int *i, double *band);
#define CLI_BAND_HELP \
    "  --band auto|none|R  the focal radius [lambda/D] the speckles are computed within, 0 beyond (no\n" \
    "                      reference there): auto (default) the Shack-Hartmann's sampling band\n" \
    "                      nsub/2; for a map with output points of its own (teach's: OUTXY)\n" \
    "                      their band D / (2 pitch); none for a linear model; none: everywhere\n" \
    "                      (docs/telemetry.md)\n"
#define CLI_GEOM_HELP \
    "  --geom FILE         geometry the files lack (no camera writes PUPDX, PUPN): a FITS header or\n" \
    "                      KEY = VALUE lines of WAVELEN [m], TELDIAM [m], OBSCUR, PIXSCALE [lambda/D\n" \
    "                      per pixel], PUPDX [m], PUPN; --wavelen, --teldiam, --obscur, --pixscale,\n" \
    "                      --pupdx, --pupn X give one (they replace the header's values)\n"
/* The generic linear model's options (run.h swfs_linear_files): --basis, --control, --imat,
 * --dm-pitch, --dm-offset X,Y, --dm-rot DEG, --dm-flip, --coef-scale; same returns as
 * cli_geom_option. cli_linear_summary prints what the model was built with. */
struct swfs_linear_files;
struct swfs_pipeline_info;
int cli_linear_option(const char *cmd, int argc, char **argv, int *i, struct swfs_linear_files *lf);
void cli_linear_summary(const char *cmd, const struct swfs_linear_files *lf, const struct swfs_pipeline_info *info);
/* The Shack-Hartmann model: its subapertures (valid: the map's file or NULL) and what the
 * reconstructor learned or was given. */
struct swfs_pipeline_options;
/* noise_how: how the vk / MAP slope noise was found (NULL: "given" or "estimated") */
void cli_recon_summary(const char *cmd, const struct swfs_pipeline_options *o, const char *path, const char *valid,
                       const struct swfs_pipeline_info *info, const char *noise_how);
/* The focal radius the speckles were computed within, when there is one (given: --band). */
void cli_band_summary(const char *cmd, const struct swfs_pipeline_info *in, int given);
struct swfs_speckles_run_result;
struct swfs_mean_teach_result;
/* A space-time reconstructor's checks against the observation (run.h st_*), with their warnings
 * (spacetime_summary.c). */
void cli_spacetime_summary(const char *cmd, const struct swfs_speckles_run_result *r);
/* The residual mean's miss added to RESMEAN: nloops simulated loops' (--mean-loop; heldout
 * their check's ratio) or, with none, a map's own MEANMISS; rms [m] (0: nothing added). */
void cli_meanmiss_summary(const char *cmd, size_t nloops, double heldout, double rms);
/* The loops `--mean-loop teach` (a pyramid's default) simulated or reused: their description
 * from the files, or why there are none. */
void cli_mean_teach_summary(const char *cmd, const struct swfs_mean_teach_result *m);
struct swfs_loops_map_result;
/* The loops' own map (--loops-map): what was learned, the self-check's scores of the two sets
 * and their mixes, and what was written, or why it was not tried (nml: the loops). */
void cli_loops_map_summary(const char *cmd, const struct swfs_loops_map_result *lm, size_t nml);
/* --mean-loop folders a stream or live run takes at most */
#define CLI_MAX_MEAN_LOOPS 64
/* Where a space-time map's lags ran on across telemetry files and were clamped (speckles,
 * stream). */
void cli_spacetime_edges(const char *cmd, size_t joined, size_t clamped, size_t unreadable, const char *why);
/* "cmd: space-time reconstructor of N lags (l1,l2,... WFS frames)" on stderr, without the line's
 * end (stream and live go on with what they did with them); returns the largest |lag|. */
long cli_spacetime_lags(const char *cmd, const long *lags, size_t n);
struct swfs_learn_run_result;
/* "cmd learning curve: ..." on f: the map's held-out misfit at the curve's two points,
 * its excess over unlimited frames and the frames for 10 % (or why there is no curve);
 * u, unit: the misfit's scale and unit. */
void cli_curve_line(FILE *f, const char *cmd, const struct swfs_learn_run_result *r, double u, const char *unit);
/* learn --lags: the wind its training loops' slopes show (the tracked layers), or that none
 * was found; nd the data sets (on stdout) */
void cli_learn_wind_summary(const struct swfs_learn_run_result *r, size_t nd);
/* pupil --method fit: the joint fit's lines (method, self-check, its rings, the mean
 * intensity's model; a warning on stderr where it took no step from its start) for out */
struct swfs_pupil_result;
void cli_pupil_fit_summary(const struct swfs_pupil_result *r, const struct swfs_geom *g, const char *out);
struct swfs_teach_run_result;
struct swfs_speckles_run_options;
/* What a successful `speckles` run prints: the reconstructor in use (for the taught default
 * what teach found and chose, or why it could not), the frames written, the residual's mean
 * and its warning, a space-time map's checks (spacetime_summary.c). */
void cli_speckles_summary(const char *cmd, const struct swfs_speckles_run_options *o,
                          const struct swfs_speckles_run_result *r, const struct swfs_teach_run_result *tr);
/* What teach found and chose (`teach`, and `speckles` teaching its default map; teach_summary.c),
 * each line starting with "cmd:"; out is the map, work its folder; checks: also the chosen map's
 * checks against the observation (speckles prints its own). */
void cli_teach_summary(FILE *f, const char *cmd, const struct swfs_teach_run_result *r, int modes_from_slopes,
                       const char *out, const char *work, int checks);
/* speckles' choice of the loops' DM by the science frames (run.h dm_choice_done), one line. */
void cli_dm_choice_summary(const char *cmd, const struct swfs_speckles_run_result *r);
/* The map teach chose (SWFS_TEACH_*), in words with why (teach_summary.c). */
const char *cli_teach_chosen(int chosen);
#define CLI_LINEAR_HELP \
    "Any AO system (the generic linear model, docs/telemetry.md): instead of --actuators,\n" \
    "  --basis CUBE.fits   mode shapes or influence functions, one plane each: PUPN x PUPN on the\n" \
    "                      pupil grid, or the DM's own grid placed by --dm-pitch M [m on the pupil\n" \
    "                      per grid step], --dm-offset X,Y [m] (the grid centre's position),\n" \
    "                      --dm-rot DEG (counter-clockwise), --dm-flip (x mirrored first)\n" \
    "  --control C.fits    control matrix, NAXIS1 = telemetry values, NAXIS2 = basis functions:\n" \
    "                      coefficients = C v for any WFS signal (pyramid, SH in any layout, ...);\n" \
    "                      without it the telemetry values are the coefficients (cacao modevalWFS);\n" \
    "                      a cube of them with NLAGS, LAG1..: a space-time one (`learn --lags`,\n" \
    "                      speckles --loops-map), on the telemetry of frames t + LAGk stacked;\n" \
    "                      with extension OUTXY (output points [m], as speckles' loops' map on a\n" \
    "                      grid finer than the DM) its basis is their interpolation, not --basis\n" \
    "  --imat D.fits       instead of --control: the interaction matrix (NAXIS1 = basis functions,\n" \
    "                      NAXIS2 = telemetry values), inverted by the MAP reconstructor learned from\n" \
    "                      the telemetry (--recon svd: the truncated SVD)\n" \
    "  --coef-scale S      metres of wavefront OPD per unit of basis x coefficient (1; cacao: unit-rms\n" \
    "                      modes of DM surface with coefficients in um: 2e-6); the residual must come\n" \
    "                      out 1e-5..4 waves rms, else it is refused naming its size\n"
/* The simulation commands' CONFIG file or key=value argument; the library's message on failure. */
struct swfs_sim_params;
int cli_config_arg(const char *cmd, struct swfs_config *cfg, const char *a);
/* Simulation parameters: the defaults, then cfg (unknown keys refused), then their checks. */
int cli_sim_params(const char *cmd, struct swfs_config *cfg, struct swfs_sim_params *p);
/* Distributed runs (cli/team.c, docs/cluster.md). Started by an MPI launcher, join the
 * team of its processes (*t; NULL when alone); prints and returns CLI_FAIL when that is
 * impossible (e.g. a build without MPI started as several processes). */
struct swfs_team;
int cli_team_join(const char *cmd, const struct swfs_team **t);
/* 1 on the process that prints summaries and writes products (rank 0, or alone). */
int cli_writer(void);
/* Leave the team and MPI (main(), after the command). */
void cli_team_end(void);
/* --sweep SETS.txt of simulate / correct (cli/sweep.c; kind: SWFS_SWEEP_* of sweep.h):
 * the sets over the base configuration, DIR/sweep.tsv, the table on stdout. */
struct swfs_loop_params;
int cli_sweep(const char *cmd, int kind, const struct swfs_config *base, const struct swfs_loop_params *loop,
              const char *outdir, const char *sets, int argc, char **argv);

#endif

/* The command line: the only place that prints or exits. Each subcommand lives in
 * cli/cmd_<name>.c as `int swfs_cmd_<name>(int argc, char **argv)` (argv[0] is the
 * subcommand name) and returns the process exit code. Register it in cli/main.c. */
#ifndef SWFS_CLI_H
#define SWFS_CLI_H

#include <stddef.h>

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
/* The closed-loop table (cli/cmd_correct.c), also printed by `demo`. */
struct swfs_loop_result;
void cli_print_loop_table(const struct swfs_loop_result *r);

/* Exit codes. */
enum { CLI_OK = 0, CLI_FAIL = 1, CLI_USAGE = 2 };

/* Print "specklewfs <cmd>: <library message>" to stderr; return CLI_FAIL. */
int cli_error(const char *cmd);
/* Print "specklewfs <cmd>: <formatted message>" to stderr; return CLI_USAGE. */
int cli_usage_error(const char *cmd, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;
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
 * or NULL for none) put before the stage name. */
void cli_stage_progress(void *ctx, const char *stage, size_t done, size_t total);
/* --tiptilt exposure|frame|keep -> SWFS_TT_* (speckles.h); prints and returns CLI_USAGE otherwise. */
int cli_parse_tiptilt(const char *cmd, const char *v, int *mode);
/* mkdir -p for an output folder; prints and returns non-zero on failure. */
int cli_make_dir(const char *cmd, const char *path);
/* A command's files, checked before any work (specklewfs/outpaths.h): the paths' status,
 * printed as the command's error (CLI_FAIL) when it is a failure; frees p. */
struct swfs_paths;
int cli_paths_check(const char *cmd, struct swfs_paths *p);
/* DIR/name for each of the n names, as outputs of p. */
void cli_paths_outputs_in(struct swfs_paths *p, const char *dir, const char *const *names, size_t n);

#endif

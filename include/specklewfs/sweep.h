/* Parameter sweeps: a design study as a list of parameter sets, each run end to end
 * (`specklewfs simulate|correct --sweep SETS.txt`, docs/cluster.md).
 *
 * The sets file has one set per line: whitespace-separated key=value assignments that
 * override the base configuration (the CONFIG file and key=value arguments of the
 * command), '#' starts a comment, blank lines are skipped. A set of `correct` may also set
 * the loop: loop_iterations, loop_gain, loop_sigma (camera noise [counts]), loop_pitch
 * (actuator pitch [m]).
 *
 * Each set gives one row of numbers; the rows, in the file's order, make one table
 * (TSV). With a team (team.h) set i runs on member i mod size and member 0 writes the
 * table; alone, every set in turn. The simulations do not depend on the thread count or
 * the member that runs them, so the table (but for its timing column) is the same for any
 * number of processes. Every set is checked (keys, values) before any runs. */
#ifndef SWFS_SWEEP_H
#define SWFS_SWEEP_H

#include <stddef.h>

#include "specklewfs/closed_loop.h"
#include "specklewfs/config.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

SWFS_BEGIN_DECLS

typedef struct swfs_sweep {
    size_t nsets;
    char **sets;     /* each set's assignments, separated by single spaces */
    size_t *line;    /* its line in the file */
    char *path;
} swfs_sweep;

/* Read a sets file; SWFS_ERR_FORMAT naming the file and line for a token that is not
 * key=value, SWFS_ERR_VALUE for a file without sets. */
int swfs_sweep_read(const char *path, swfs_sweep **out);
void swfs_sweep_free(swfs_sweep *s);
/* Set i's assignments into cfg (they win over what cfg holds). */
int swfs_sweep_apply(const swfs_sweep *s, size_t i, swfs_config *cfg);

enum { SWFS_SWEEP_SIMULATE = 0, SWFS_SWEEP_CORRECT = 1 };

typedef struct swfs_sweep_run_options {
    int kind;                   /* SWFS_SWEEP_SIMULATE or SWFS_SWEEP_CORRECT */
    const swfs_config *base;    /* the base configuration (not modified) */
    const swfs_sweep *sweep;
    swfs_loop_params loop;      /* SWFS_SWEEP_CORRECT: the loop (closed_loop.h defaults) */
    const char *out;            /* the table (TSV), written by member 0 */
    const char *const *prov;
    size_t nprov;
    swfs_progress_fn progress;  /* stage "sets": this member's sets done */
    void *progress_ctx;
    const swfs_team *team;      /* NULL: alone */
} swfs_sweep_run_options;

void swfs_sweep_run_options_default(swfs_sweep_run_options *o);

/* SWFS_SWEEP_SIMULATE: the Sec. 3 simulation of the set, its camera noise (read_noise,
 * gain; the seed `simulate` uses), the default estimate and pupil step, against the
 * injected NCP (recovery.h). SWFS_SWEEP_CORRECT: the closed loop (closed_loop.h).
 * Columns: swfs_sweep_columns(kind); the last is the set's wall time [s]. */
const char *const *swfs_sweep_columns(int kind, size_t *ncols);

typedef struct swfs_sweep_run_result {
    size_t nsets, ncols;
    double *rows;      /* nsets x ncols (member 0; NULL on the others); free() it */
    size_t mine;       /* sets this member ran */
} swfs_sweep_run_result;

int swfs_sweep_run(const swfs_sweep_run_options *o, swfs_sweep_run_result *r);

/* The table: a comment line per provenance line, the header (set, params, columns), one
 * row per set (%.10g). Atomic (.part + rename). */
int swfs_sweep_write(const char *path, const swfs_sweep *s, const char *const *cols, size_t ncols,
                     const double *rows, const char *const *prov, size_t nprov);

SWFS_END_DECLS

#endif

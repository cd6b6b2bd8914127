/* `specklewfs simulate|correct ... --sweep SETS.txt -o DIR`: the parameter sweep of
 * sweep.h, shared out over the processes of an MPI launch (docs/cluster.md), one table
 * DIR/sweep.tsv; also alone. Called by cmd_simulate.c and cmd_correct.c. */
#include "cli.h"

#include "specklewfs/status.h"
#include "specklewfs/sweep.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

int cli_sweep(const char *cmd, int kind, const swfs_config *base, const swfs_loop_params *loop, const char *outdir,
              const char *sets, int argc, char **argv)
{
    swfs_sweep_run_options o;
    swfs_sweep_run_options_default(&o);
    o.kind = kind;
    o.base = base;
    if (loop) o.loop = *loop;
    char path[4096];
    if (snprintf(path, sizeof path, "%s/sweep.tsv", outdir) >= (int)sizeof path)
        return cli_usage_error(cmd, "output folder name too long");
    o.out = path;
    swfs_sweep *sw = NULL;
    if (swfs_sweep_read(sets, &sw)) return cli_error(cmd);
    o.sweep = sw;
    /* Every process, before the team meets: all fail alike or none does. */
    if (cli_make_dir(cmd, outdir) || cli_team_join(cmd, &o.team)) {
        swfs_sweep_free(sw);
        return CLI_FAIL;
    }
    const int writer = cli_writer();
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = writer ? cli_stage_progress : NULL;
    o.progress_ctx = (void *)(kind == SWFS_SWEEP_CORRECT ? "correct sweep:" : "simulate sweep:");
    const double t0 = cli_now();
    swfs_sweep_run_result r;
    int rc = swfs_sweep_run(&o, &r) ? (writer ? cli_error(cmd) : CLI_FAIL) : CLI_OK;
    if (!rc && writer) {
        size_t ncols;
        const char *const *cols = swfs_sweep_columns(kind, &ncols);
        printf("%s sweep: %zu parameter sets from %s -> %s (%.2f s)\n", cmd, r.nsets, sets, path, cli_now() - t0);
        printf("  %4s", "set");
        for (size_t c = 0; c < ncols; c++) printf(" %12s", cols[c]);
        printf("  params\n");
        for (size_t i = 0; i < r.nsets; i++) {
            printf("  %4zu", i);
            for (size_t c = 0; c < ncols; c++) printf(" %12.5g", r.rows[i * ncols + c]);
            printf("  %s\n", sw->sets[i]);
        }
    }
    free(r.rows);
    swfs_sweep_free(sw);
    return rc;
}

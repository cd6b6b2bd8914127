/* demo: the paper's Sec. 3 simulation end to end (run.h swfs_demo_run; `specklewfs demo`
 * and Python's demo()): simulate once, recover at each camera noise level, close the loop,
 * draw the page. */
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/parallel.h"
#include "specklewfs/report.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/table.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const double default_levels[] = {0, 10, 100, 1000};

void swfs_demo_run_options_default(swfs_demo_run_options *o)
{
    memset(o, 0, sizeof *o);
    o->outdir = "demo-out";
    swfs_sim_params_default(&o->sim);
    o->levels = default_levels;
    o->nlevels = sizeof default_levels / sizeof default_levels[0];
    swfs_loop_params_default(&o->loop);
    o->report = 1;
}

void swfs_demo_run_result_free(swfs_demo_run_result *r)
{
    if (!r) return;
    swfs_sim_result_free(r->sim);
    free(r->levels);
    free(r->level_seconds);
    swfs_loop_result_free(r->loop);
    memset(r, 0, sizeof *r);
}

/* A stage of the simulation or of the loop passed on under the demo's own name. */
typedef struct relay {
    const swfs_demo_run_options *o;
    const char *prefix;
} relay;

static int relay_progress(void *ctx, const char *stage, size_t done, size_t total)
{
    const relay *rl = ctx;
    char s[96];
    if (!strcmp(stage, "loop")) snprintf(s, sizeof s, "%s", rl->prefix);
    else snprintf(s, sizeof s, "%s %s", rl->prefix, stage);
    return rl->o->progress(rl->o->progress_ctx, s, done, total);
}

static int stage(const swfs_demo_run_options *o, const char *name, size_t done, size_t total)
{
    return swfs_progress_report(o->progress, o->progress_ctx, name, done, total);
}

/* Folder dir made and its products (names, n) added as outputs. */
static int outputs_in(swfs_paths *paths, const char *dir, const char *const *names, size_t n)
{
    char path[8192];
    int rc = swfs_make_dirs(dir);
    for (size_t i = 0; !rc && i < n; i++) {
        snprintf(path, sizeof path, "%s/%s", dir, names[i]);
        rc = swfs_paths_output(paths, "output", path);
    }
    return rc;
}

/* Every folder made and every product checked (against the config file and each other)
 * before the simulation. */
static int prepare(const swfs_demo_run_options *o)
{
    static const char *const level_products[] = {"science.fits", "speckles.fits", "truth.fits",
                                                 "pupil.fits",   "halo.fits",     "wavefront.fits"};
    static const char *const loop_products[] = {"loop.tsv", "loop.fits"};
    static const char *const table[] = {"recovery.tsv"};
    char dir[4096];
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    if (!rc) rc = swfs_paths_input(paths, "config file", o->config);
    if (!rc) rc = outputs_in(paths, o->outdir, table, 1);
    for (size_t k = 0; !rc && k < o->nlevels; k++) {
        snprintf(dir, sizeof dir, "%s/sigma%g", o->outdir, o->levels[k]);
        rc = outputs_in(paths, dir, level_products, sizeof level_products / sizeof *level_products);
    }
    if (!rc && o->loop.iterations > 0) {
        snprintf(dir, sizeof dir, "%s/loop", o->outdir);
        rc = outputs_in(paths, dir, loop_products, sizeof loop_products / sizeof *loop_products);
    }
    swfs_paths_free(paths);
    return rc;
}

/* The simulation, the levels, the table and the loop: products in the open output group. */
static int run_products(const swfs_demo_run_options *o, swfs_demo_run_result *r)
{
    const swfs_sim_params *p = &o->sim;
    char dir[4096], noise_line[160];
    relay rl = {o, "simulate"};
    double t0 = swfs_wall_seconds();
    int rc = stage(o, "simulate", 0, 1);
    if (rc) return rc;
    rc = swfs_sim_paper_run(p, o->progress ? relay_progress : NULL, &rl, &r->sim);
    if (rc) return rc;
    r->sim_seconds = swfs_wall_seconds() - t0;
    rc = swfs_wfe_compare(r->sim->ncp->data, r->sim->ncp->data, r->sim->pupil->data, (size_t)r->sim->geom.pupn, NULL,
                          NULL, &r->ncp_rms_ptt);
    const size_t np = o->nprov + 1;
    const char **prov = calloc(np, sizeof *prov);
    r->levels = calloc(o->nlevels, sizeof *r->levels);
    r->level_seconds = calloc(o->nlevels, sizeof *r->level_seconds);
    if (!rc && (!prov || !r->levels || !r->level_seconds)) rc = swfs_fail(SWFS_ERR_NOMEM, "demo: out of memory");
    for (size_t i = 0; prov && i < o->nprov; i++) prov[i] = o->prov[i];
    for (size_t k = 0; !rc && k < o->nlevels; k++) {
        if ((rc = stage(o, "noise levels", k, o->nlevels))) break;
        snprintf(dir, sizeof dir, "%s/sigma%g", o->outdir, o->levels[k]);
        snprintf(noise_line, sizeof noise_line, "demo noise level: read noise %g counts, gain %g e-/count",
                 o->levels[k], p->gain);
        prov[o->nprov] = noise_line;
        const double t1 = swfs_wall_seconds();
        rc = swfs_recovery_run(r->sim, o->levels[k], p->seed * 1000003ULL + (uint64_t)o->levels[k], dir, prov, np,
                               &r->levels[k]);
        r->level_seconds[k] = swfs_wall_seconds() - t1;
        r->nlevels = k + 1;
    }
    if (!rc) rc = stage(o, "noise levels", o->nlevels, o->nlevels);
    if (!rc) {
        snprintf(dir, sizeof dir, "%s/recovery.tsv", o->outdir);
        rc = swfs_recovery_table_write(dir, r->levels, r->level_seconds, o->nlevels);
    }
    if (!rc && o->loop.iterations > 0) {
        /* The simulation above is the loop's first measurement (the same parameters). */
        rl.prefix = "closed loop";
        snprintf(dir, sizeof dir, "%s/loop", o->outdir);
        rc = stage(o, "closed loop", 0, o->loop.iterations + 1);
        if (!rc) rc = swfs_closed_loop_run(p, &o->loop, r->sim, o->progress ? relay_progress : NULL, &rl, &r->loop);
        if (!rc) rc = swfs_closed_loop_write(r->loop, dir, o->prov, o->nprov);
    }
    free(prov);
    return rc;
}

int swfs_demo_run(const swfs_demo_run_options *o, swfs_demo_run_result *r)
{
    memset(r, 0, sizeof *r);
    r->ncp_rms_ptt = NAN;
    if (!o->outdir || !*o->outdir) return swfs_fail(SWFS_ERR_ARG, "demo: needs an output folder");
    if (!o->levels || !o->nlevels) return swfs_fail(SWFS_ERR_ARG, "demo: needs at least one noise level");
    for (size_t k = 0; k < o->nlevels; k++)
        if (!(o->levels[k] >= 0) || !isfinite(o->levels[k]))
            return swfs_fail(SWFS_ERR_ARG, "demo: noise level %zu is %g counts; expected a finite value >= 0", k + 1,
                             o->levels[k]);
    const double t0 = swfs_wall_seconds();
    int rc = prepare(o);
    if (rc) return rc;
    /* The products of all levels and of the loop are renamed into place together when all
     * are written; the figures are drawn from them afterwards. */
    swfs_outputs_begin();
    rc = run_products(o, r);
    const int end = swfs_outputs_end(!rc);
    if (!rc) rc = end;
    if (!rc && o->report) {
        swfs_report_summary *rs = calloc(1, sizeof *rs);
        if (!rs) rc = swfs_fail(SWFS_ERR_NOMEM, "demo: out of memory");
        if (!rc) rc = swfs_report_run(o->outdir, NULL, NULL, rs);
        if (!rc) snprintf(r->html, sizeof r->html, "%s", rs->html);
        free(rs);
    }
    r->seconds = swfs_wall_seconds() - t0;
    if (rc) {
        const int keep = rc;
        swfs_demo_run_result_free(r);
        r->ncp_rms_ptt = NAN;
        return keep;
    }
    return SWFS_OK;
}

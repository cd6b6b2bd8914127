/* Parameter sweeps over the Sec. 3 simulation and the closed loop: see include/specklewfs/sweep.h. */
#include "specklewfs/sweep.h"
#include "specklewfs/parallel.h"
#include "specklewfs/recovery.h"
#include "specklewfs/sim.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* The camera-noise seed of `specklewfs simulate` (cli/cmd_simulate.c): a set's row is the
 * recovery from the very science cube `simulate` would write for it. */
#define SIMULATE_CAMERA_SEED 0x5eed0fca3e7aULL

static const char *const sim_cols[] = {"residual_nm", "strehl", "strehl_ao", "valid", "median_snr", "err_paper_nm",
                                       "err_halo_nm", "err_lf_nm", "err_nm", "wfe_rms_nm", "seconds"};
static const char *const loop_cols[] = {"iterations", "resid0_nm", "resid_nm", "resid_ptt_nm", "strehl0", "strehl",
                                        "contrast0", "contrast", "contrast_ncp0", "contrast_ncp", "est_err0_nm",
                                        "seconds"};

void swfs_sweep_run_options_default(swfs_sweep_run_options *o)
{
    memset(o, 0, sizeof *o);
    o->kind = SWFS_SWEEP_SIMULATE;
    swfs_loop_params_default(&o->loop);
}

const char *const *swfs_sweep_columns(int kind, size_t *ncols)
{
    if (kind == SWFS_SWEEP_CORRECT) {
        *ncols = sizeof loop_cols / sizeof loop_cols[0];
        return loop_cols;
    }
    *ncols = sizeof sim_cols / sizeof sim_cols[0];
    return sim_cols;
}

/* The loop settings a set of `correct` may change. */
static int loop_keys(swfs_config *cfg, swfs_loop_params *lp)
{
    long it = (long)lp->iterations;
    int rc = swfs_config_long(cfg, "loop_iterations", it, &it);
    if (!rc) rc = swfs_config_double(cfg, "loop_gain", lp->gain, &lp->gain);
    if (!rc) rc = swfs_config_double(cfg, "loop_sigma", lp->sigma, &lp->sigma);
    if (!rc) rc = swfs_config_double(cfg, "loop_pitch", lp->act_pitch, &lp->act_pitch);
    if (rc) return rc;
    if (it < 0 || it > 1000) return swfs_fail(SWFS_ERR_VALUE, "loop_iterations=%ld: expected 0..1000", it);
    if (!(lp->gain > 0 && lp->gain <= 2)) return swfs_fail(SWFS_ERR_VALUE, "loop_gain=%g: expected (0, 2]", lp->gain);
    if (!(lp->sigma >= 0)) return swfs_fail(SWFS_ERR_VALUE, "loop_sigma=%g: expected >= 0 counts", lp->sigma);
    if (!(lp->act_pitch > 0)) return swfs_fail(SWFS_ERR_VALUE, "loop_pitch=%g: expected > 0 m", lp->act_pitch);
    lp->iterations = (size_t)it;
    return SWFS_OK;
}

/* Set i's parameters: the base configuration, the set over it, every key used. */
static int prepare(const swfs_sweep_run_options *o, size_t i, swfs_sim_params *p, swfs_loop_params *lp)
{
    swfs_config *cfg = swfs_config_new();
    if (!cfg) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    int rc = SWFS_OK;
    for (size_t k = 0; !rc && o->base && k < swfs_config_count(o->base); k++)
        rc = swfs_config_set_kv(cfg, swfs_config_key(o->base, k), swfs_config_value(o->base, k));
    if (!rc) rc = swfs_sweep_apply(o->sweep, i, cfg);
    const char *mode = NULL;
    if (!rc) rc = swfs_config_string(cfg, "mode", "paper", &mode);
    if (!rc && strcmp(mode, "paper"))
        rc = swfs_fail(SWFS_ERR_VALUE, "mode=%s: a sweep runs the Sec. 3 simulation (mode=paper)", mode);
    swfs_sim_params_default(p);
    *lp = o->loop;
    if (!rc) rc = swfs_sim_params_from_config(cfg, p);
    if (!rc && o->kind == SWFS_SWEEP_CORRECT) rc = loop_keys(cfg, lp);
    if (!rc) rc = swfs_config_check_unused(cfg);
    if (!rc) rc = swfs_sim_params_check(p);
    swfs_config_free(cfg);
    if (rc) swfs_fail_context(rc, "%s:%zu (set %zu)", o->sweep->path, o->sweep->line[i], i);
    return rc;
}

static int run_simulate(const swfs_sim_params *p, double *row)
{
    swfs_sim_result *sim = NULL;
    swfs_recovery rec;
    int rc = swfs_sim_paper_run(p, NULL, NULL, &sim);
    if (!rc) rc = swfs_recovery_run(sim, p->read_noise, p->seed ^ SIMULATE_CAMERA_SEED, NULL, NULL, 0, &rec);
    if (!rc) {
        const double v[] = {sim->residual_rms * 1e9, sim->strehl, sim->strehl_ao, rec.valid_fraction, rec.median_snr,
                            rec.err_paper * 1e9, rec.err_halo * 1e9, rec.err_lf * 1e9, rec.err_lf_snr * 1e9,
                            rec.wfe_rms * 1e9};
        memcpy(row, v, sizeof v);
    }
    swfs_sim_result_free(sim);
    return rc;
}

static int run_correct(const swfs_sim_params *p, const swfs_loop_params *lp, double *row)
{
    swfs_loop_result *res = NULL;
    int rc = swfs_closed_loop_run(p, lp, NULL, NULL, NULL, &res);
    if (!rc) {
        const swfs_loop_iter *a = &res->rows[0], *b = &res->rows[res->nrows - 1];
        const double v[] = {(double)lp->iterations, a->resid_rms * 1e9, b->resid_rms * 1e9, b->resid_rms_ptt * 1e9,
                            a->strehl, b->strehl, a->contrast, b->contrast, a->contrast_ncp, b->contrast_ncp,
                            a->est_err * 1e9};
        memcpy(row, v, sizeof v);
    }
    swfs_loop_result_free(res);
    return rc;
}

/* Sets of member r: r, r + size, r + 2 size, ... */
static size_t sets_of(size_t nsets, int r, int size) { return nsets > (size_t)r ? (nsets - (size_t)r + (size_t)size - 1) / (size_t)size : 0; }

int swfs_sweep_run(const swfs_sweep_run_options *o, swfs_sweep_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->sweep || !o->out || (o->kind != SWFS_SWEEP_SIMULATE && o->kind != SWFS_SWEEP_CORRECT))
        return swfs_fail(SWFS_ERR_ARG, "sweep: needs the sets, a table to write and a kind (simulate or correct)");
    const swfs_team *t = o->team;
    const int rank = swfs_team_active(t) ? t->rank : 0, size = swfs_team_active(t) ? t->size : 1;
    const size_t nsets = o->sweep->nsets;
    size_t ncols;
    const char *const *cols = swfs_sweep_columns(o->kind, &ncols);
    r->nsets = nsets;
    r->ncols = ncols;
    r->mine = sets_of(nsets, rank, size);
    /* Every set is checked before any runs (the same checks on every member). */
    swfs_sim_params p;
    swfs_loop_params lp;
    int rc = SWFS_OK;
    for (size_t i = 0; i < nsets && !rc; i++) rc = prepare(o, i, &p, &lp);
    /* Member 0 holds the whole table; its own rows come first. */
    double *rows = malloc((rank ? (r->mine ? r->mine : 1) : nsets) * ncols * sizeof *rows);
    if (!rc && !rows) rc = swfs_fail(SWFS_ERR_NOMEM, "sweep: out of memory");
    for (size_t j = 0; j < r->mine && !rc; j++) {
        const size_t i = (size_t)rank + j * (size_t)size;
        const double t0 = swfs_wall_seconds();
        if (!(rc = prepare(o, i, &p, &lp))) {
            rc = o->kind == SWFS_SWEEP_CORRECT ? run_correct(&p, &lp, rows + j * ncols) : run_simulate(&p, rows + j * ncols);
            if (rc) swfs_fail_context(rc, "%s:%zu (set %zu: %s)", o->sweep->path, o->sweep->line[i], i, o->sweep->sets[i]);
        }
        rows[j * ncols + ncols - 1] = swfs_wall_seconds() - t0;
        if (!rc) rc = swfs_progress_report(o->progress, o->progress_ctx, "sets", j + 1, r->mine);
    }
    rc = swfs_team_agree(t, rc);
    size_t *counts = NULL;
    if (!rc && swfs_team_active(t)) {
        counts = calloc((size_t)size, sizeof *counts);
        rc = swfs_team_agree(t, counts ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "sweep: out of memory"));
        for (int k = 0; !rc && k < size; k++) counts[k] = sets_of(nsets, k, size) * ncols * sizeof(double);
        if (!rc) rc = t->gather(t->ctx, rows, counts[rank], rank ? NULL : rows, rank ? NULL : counts);
    }
    double *table = NULL;
    if (!rc && rank == 0) {
        /* member k's j-th row is set k + j size */
        if (!(table = malloc(nsets * ncols * sizeof *table))) rc = swfs_fail(SWFS_ERR_NOMEM, "sweep: out of memory");
        size_t at = 0;
        for (int k = 0; !rc && k < size; k++)
            for (size_t j = 0; j < sets_of(nsets, k, size); j++, at++)
                memcpy(table + ((size_t)k + j * (size_t)size) * ncols, rows + at * ncols, ncols * sizeof *table);
        if (!rc) rc = swfs_sweep_write(o->out, o->sweep, cols, ncols, table, o->prov, o->nprov);
    }
    rc = swfs_team_agree(t, rc);
    if (!rc) r->rows = table;
    else free(table);
    free(counts);
    free(rows);
    return rc;
}

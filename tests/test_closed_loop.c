/* Closed-loop NCP correction in simulation (closed_loop.h) on a reduced, seeded Sec. 3
 * data set, the simulator's NCP-map hook, and the raw-contrast measure. */
#include "testutil.h"

#include "specklewfs/closed_loop.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>

/* 1024^2 screens, 3 of them: 147 frames of the paper's pupil and focal plane. */
static void small_params(swfs_sim_params *p)
{
    swfs_sim_params_default(p);
    p->screen.n = 1024;
    p->nscreens = 3;
    p->seed = 1;
}

/* swfs_sim_paper_run_ncp with the map swfs_sim_ncp_map makes == swfs_sim_paper_run. */
static void test_ncp_hook(void **state)
{
    (void)state;
    swfs_sim_params p;
    small_params(&p);
    p.nscreens = 1;
    p.per_screen = 2;
    swfs_sim_result *a = NULL, *b = NULL;
    assert_ok(swfs_sim_paper_run(&p, NULL, NULL, &a));
    double *ncp = malloc(a->ncp->nx * a->ncp->ny * sizeof *ncp);
    memcpy(ncp, a->ncp->data, a->ncp->nx * a->ncp->ny * sizeof *ncp);
    for (size_t k = 0; k < a->ncp->nx * a->ncp->ny; k++) ncp[k] += 1e-7; /* piston: removed again */
    p.ncp_trefoil = 0; /* ignored when a map is given */
    assert_ok(swfs_sim_paper_run_ncp(&p, ncp, NULL, NULL, &b));
    assert_close(b->ncp_rms, a->ncp_rms, 1e-15);
    double dmax = 0;
    for (size_t k = 0; k < swfs_real_size(a->science); k++)
        dmax = fmax(dmax, fabs(a->science->data[k] - b->science->data[k]) / (1 + a->science->data[k]));
    assert_true(dmax < 1e-5); /* single-precision MFT of an identical phasor up to rounding */
    ncp[5] = NAN;
    ncp[81 * a->ncp->nx + 81 + 40] = NAN; /* inside the pupil */
    swfs_sim_result *c = NULL;
    assert_int_equal(swfs_sim_paper_run_ncp(&p, ncp, NULL, NULL, &c), SWFS_ERR_VALUE);
    assert_null(c);
    free(ncp);
    swfs_sim_result_free(a);
    swfs_sim_result_free(b);
}

static void test_contrast(void **state)
{
    (void)state;
    swfs_cplx *h = swfs_cplx_alloc(40, 40, 1);
    for (size_t k = 0; k < 1600; k++) h->data[k] = 0.1;
    h->data[20 * 40 + 20] = 1.0; /* peak 1, flat 0.01 elsewhere */
    assert_close(swfs_halo_contrast(h, 0.25, 2, 6), 0.01, 1e-15);
    assert_true(isnan(swfs_halo_contrast(h, 0.25, 20, 30))); /* outside the window */
    swfs_cplx_free(h);
}

static void test_loop(void **state)
{
    (void)state;
    swfs_sim_params p;
    small_params(&p);
    swfs_loop_params lp;
    swfs_loop_params_default(&lp);
    lp.iterations = 2;
    lp.gain = 0.8;
    lp.sigma = 100;
    swfs_loop_result *r = NULL;
    assert_ok(swfs_closed_loop_run(&p, &lp, NULL, NULL, NULL, &r));
    assert_int_equal(r->nrows, 3);
    const swfs_loop_iter *it = r->rows;
    for (size_t k = 0; k < r->nrows; k++)
        fprintf(stderr, "  iter %zu: resid %.1f nm, Strehl %.4f (ceiling %.4f), contrast %.3e NCP halo %.3e, est.err %.1f nm\n",
                k, it[k].resid_rms * 1e9, it[k].strehl, it[k].strehl_ao, it[k].contrast, it[k].contrast_ncp,
                it[k].est_err * 1e9);
    /* Row 0 is the paper's NCP: 105.5 nm rms. */
    assert_close(it[0].resid_rms, 105.5e-9, 0.5e-9);
    /* The residual falls at least 3x in two iterations (measured: 105.5 -> 37.2 -> 25.3). */
    assert_true(it[2].resid_rms * 3 <= it[0].resid_rms);
    assert_true(it[1].resid_rms < 0.5 * it[0].resid_rms);
    /* The science PSF gains Strehl, approaching the no-NCP ceiling, and the NCP's static
     * speckles in 2-6 lambda/D fall. */
    assert_true(it[2].strehl > it[0].strehl + 0.01);
    assert_true(it[2].strehl <= it[2].strehl_ao + 0.005);
    assert_true(it[2].contrast < it[0].contrast);
    assert_true(it[2].contrast_ncp < 0.25 * it[0].contrast_ncp);
    assert_true(it[2].contrast >= 0.95 * it[2].contrast_ao);
    /* Long-exposure Strehl ~ no-NCP Strehl x Marechal of the NCP. */
    assert_close(it[0].strehl, it[0].strehl_ao * it[0].strehl_marechal, 0.01);
    /* Bookkeeping: residual_k = NCP + 2 x DM surface_k up to the piston every simulation
     * removes, so residual_2 - residual_0 - 2 (surface_2 - surface_0) is a constant. */
    const size_t n2 = r->residual->nx * r->residual->ny;
    double lo = INFINITY, hi = -INFINITY;
    for (size_t s = 0; s < n2; s++) {
        if (!(r->pupil->data[s] > 0)) continue;
        const double d = r->residual->data[2 * n2 + s] - r->residual->data[s] -
                         2 * (r->dm_surface->data[2 * n2 + s] - r->dm_surface->data[s]);
        lo = fmin(lo, d);
        hi = fmax(hi, d);
    }
    assert_true(hi - lo < 1e-15);
    assert_true(isnan(it[2].est_err));
    assert_true(it[0].est_err < 0.5 * it[0].resid_rms);
    /* Files. */
    const char *prov[] = {"test_closed_loop"};
    const char *dir = test_path("loop");
    char path[2048];
    snprintf(path, sizeof path, "mkdir -p %s", dir);
    assert_int_equal(system(path), 0);
    assert_ok(swfs_closed_loop_write(r, dir, prov, 1));
    snprintf(path, sizeof path, "%s/loop.fits", dir);
    swfs_real *res = NULL, *met = NULL;
    assert_ok(swfs_fits_read_real(path, "RESIDUAL", &res, NULL));
    assert_int_equal(res->nz, 3);
    assert_ok(swfs_fits_read_real(path, "METRICS", &met, NULL));
    assert_int_equal(met->ny, 3);
    assert_close(met->data[1], it[0].resid_rms * 1e9, 1e-9);
    snprintf(path, sizeof path, "%s/loop.tsv", dir);
    assert_true(test_file_exists(path));
    swfs_real_free(res);
    swfs_real_free(met);
    swfs_loop_result_free(r);
}

static void test_bad(void **state)
{
    (void)state;
    swfs_sim_params p;
    small_params(&p);
    swfs_loop_params lp;
    swfs_loop_params_default(&lp);
    swfs_loop_result *r = NULL;
    lp.gain = 0;
    assert_int_equal(swfs_closed_loop_run(&p, &lp, NULL, NULL, NULL, &r), SWFS_ERR_ARG);
    assert_non_null(strstr(swfs_last_error(), "gain"));
    /* A DM smaller than the pupil. */
    swfs_loop_params_default(&lp);
    double xy[] = {0, 0, 2, 0, 1, 1.7, -1, 1.7, -2, 0, -1, -1.7, 1, -1.7};
    lp.act_xy = xy;
    lp.nact = 7;
    assert_int_equal(swfs_closed_loop_run(&p, &lp, NULL, NULL, NULL, &r), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "do not cover the pupil"));
    assert_null(r);
}

/* `specklewfs correct` end to end on a tiny data set, and its bad-input errors. */
static void test_cli(void **state)
{
    (void)state;
    char dir[1024], act[1024], args[4096], out[16384], path[2048];
    snprintf(dir, sizeof dir, "%s", test_path("correct_cli"));
    snprintf(act, sizeof act, "%s", test_path("correct_small_act.fits"));
    snprintf(args, sizeof args, "correct -o %s --iterations 1 --gain 0.5 screen_n=1024 nscreens=1 seed=4", dir);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "closed loop: gain 0.50"));
    snprintf(path, sizeof path, "%s/loop.tsv", dir);
    assert_true(test_file_exists(path));
    snprintf(path, sizeof path, "%s/loop.fits", dir);
    assert_true(test_file_exists(path));
    /* a DM 4 m across for the 6.5 m pupil */
    double xy[2 * 7] = {0, 0, 2, 0, 1, 1.7, -1, 1.7, -2, 0, -1, -1.7, 1, -1.7};
    assert_ok(swfs_actuators_write(xy, 7, act));
    snprintf(args, sizeof args, "correct -o %s --iterations 1 --actuators %s screen_n=1024 nscreens=1", dir, act);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 1);
    assert_non_null(strstr(out, "correct_small_act.fits"));
    assert_non_null(strstr(out, "do not cover the pupil"));
    snprintf(args, sizeof args, "correct -o %s --gain 0", dir);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 2);
    assert_non_null(strstr(out, "--gain"));
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_contrast),
        cmocka_unit_test(test_ncp_hook),
        cmocka_unit_test(test_bad),
        cmocka_unit_test(test_loop),
        cmocka_unit_test(test_cli),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

/* The paper's Sec. 3 experiment end to end: simulate -> camera noise -> estimate ->
 * pupil -> recovered NCP error against the injected one. */
#include "testutil.h"

#include "specklewfs/config.h"
#include "specklewfs/recovery.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>

static swfs_sim_result *simulate(const char *const *overrides, size_t n)
{
    swfs_config *c = swfs_config_new();
    for (size_t k = 0; k < n; k++) assert_ok(swfs_config_set(c, overrides[k]));
    swfs_sim_params p;
    swfs_sim_params_default(&p);
    assert_ok(swfs_sim_params_from_config(c, &p));
    assert_ok(swfs_config_check_unused(c));
    swfs_config_free(c);
    swfs_sim_result *r;
    assert_ok(swfs_sim_paper_run(&p, NULL, NULL, &r));
    return r;
}

static void test_reduced_size(void **state)
{
    (void)state;
    /* 3 screens of 1024^2 -> 147 frames: the same physics, a fraction of the data. */
    const char *ov[] = {"screen_n=1024", "nscreens=3", "seed=7"};
    swfs_sim_result *sim = simulate(ov, 3);
    swfs_recovery r0, r100;
    assert_ok(swfs_recovery_run(sim, 0.0, 11, NULL, NULL, 0, &r0));
    assert_ok(swfs_recovery_run(sim, 100.0, 12, NULL, NULL, 0, &r100));
    print_message("%zu frames, NCP %.1f nm: sigma 0 -> %.1f nm (HALO %.1f), sigma 100 -> %.1f nm, valid %.0f%% / %.0f%%\n",
                  sim->nframes, sim->ncp_rms * 1e9, r0.err_lf_snr * 1e9, r0.err_halo * 1e9, r100.err_lf_snr * 1e9,
                  100 * r0.valid_fraction, 100 * r100.valid_fraction);
    assert_true(sim->nframes < 200);
    assert_true(r0.err_lf_snr < 0.3 * sim->ncp_rms);
    assert_true(r100.err_lf_snr < 0.5 * sim->ncp_rms);
    assert_true(r0.err_lf < r0.err_halo);            /* eq:PSI-LowFreq restores the low frequencies */
    assert_true(r0.valid_fraction > r100.valid_fraction);
    swfs_sim_result_free(sim);
}

static void test_paper_numbers(void **state)
{
    (void)state;
    /* The paper's parameters (980 frames, 157,000 counts): the targets. */
    swfs_sim_result *sim = simulate(NULL, 0);
    const double sigma[3] = {0, 10, 100}, limit[3] = {17e-9, 17e-9, 21e-9};
    const double valid_lo[3] = {0.95, 0.7, 0.35}, valid_hi[3] = {1.0, 0.95, 0.65};
    assert_close(sim->ncp_rms, 105.5e-9, 1e-9);
    assert_close(sim->residual_rms, 250e-9, 5e-9);
    for (int k = 0; k < 3; k++) {
        swfs_recovery r;
        assert_ok(swfs_recovery_run(sim, sigma[k], 100 + (uint64_t)k, NULL, NULL, 0, &r));
        print_message("sigma %4g: NCP error %.1f nm (paper formulae: HALO %.1f, HALO_LF %.1f), valid %.1f%%\n", sigma[k],
                      r.err_lf_snr * 1e9, r.err_halo * 1e9, r.err_lf * 1e9, 100 * r.valid_fraction);
        assert_true(r.err_lf_snr <= limit[k]);
        assert_true(r.valid_fraction >= valid_lo[k] && r.valid_fraction <= valid_hi[k]);
    }
    swfs_sim_result_free(sim);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_reduced_size),
        cmocka_unit_test(test_paper_numbers),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

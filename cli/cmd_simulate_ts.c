/* `specklewfs simulate mode=timeseries ...`: the time-series simulator of the real-data
 * path (include/specklewfs/timeseries.h), dispatched from cmd_simulate.c. */
#include "cli.h"

#include "specklewfs/atomic.h"
#include "specklewfs/config.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

int swfs_cmd_simulate_ts(struct swfs_config *cfg, const char *cfgfile, const char *outdir, int quiet, int argc,
                         char **argv)
{
    const char *cmd = "simulate";
    swfs_ts_params p;
    swfs_ts_params_default(&p);
    if (swfs_ts_params_from_config(cfg, &p) || swfs_config_check_unused(cfg) || swfs_ts_params_check(&p))
        return cli_error(cmd);
    if (swfs_ts_make_dirs(&p, outdir)) return cli_error(cmd);
    swfs_paths *paths = NULL;
    swfs_paths_create(&paths);
    swfs_paths_input(paths, "config file", cfgfile);
    swfs_ts_add_outputs(&p, outdir, paths);
    if (cli_paths_check(cmd, paths)) return CLI_FAIL;
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl, "specklewfs time-series simulation (mode=timeseries)"};
    swfs_ts_summary s;
    /* All files renamed into place at the end, or none (atomic.h). */
    swfs_outputs_begin();
    int rc = swfs_ts_run(&p, outdir, prov, 2, quiet ? cli_stop_check : cli_stage_progress, (void *)"simulate:", &s);
    int erc = swfs_outputs_end(rc == SWFS_OK);
    if (rc || erc) return cli_error(cmd);
    swfs_dm_registration reg;
    size_t nmodes = 0;
    if (p.export_modal) {
        swfs_outputs_begin();
        rc = swfs_ts_export_modal(&p, outdir, prov, 2, &reg, &nmodes);
        erc = swfs_outputs_end(rc == SWFS_OK);
        if (rc || erc) return cli_error(cmd);
    }
    printf("simulate (timeseries): %zu WFS frames at %.0f Hz, %ld cubes x %ld frames at <t_sci/t_wfs> = %.4f, "
           "handshake lag %ld\n", s.nwfs, p.wfs_rate, p.ncubes, p.cube_frames, p.frame_ratio, p.handshake_lag);
    if (p.camera_light)
        printf("  camera_light=1: the WFS frames of the camera keys as given, the camera integrating the cubes above\n");
    printf("  AO: %zu actuators%s%s%s, %zu valid subapertures, %zu modes%s%s%s, gain %.2f, delay %ld\n", s.nact,
           p.actuators[0] ? " (from " : "", p.actuators, p.actuators[0] ? ")" : "", s.nvalid, s.ao_modes,
           p.ao_recon[0] ? " (the reconstructor " : "", p.ao_recon, p.ao_recon[0] ? ")" : "", p.ao_gain, p.ao_delay);
    if (p.wfs_pyramid)
        printf("  WFS: a pyramid modulated at %g lambda/D (%s points), sensing at %.3g um, %g photons per subaperture "
               "and frame; its signals are the telemetry: speckles --basis %s/influence.fits --imat %s/imat_ao.fits "
               "(or --control %s/recon_ao.fits, the loop's own)\n", p.pyr_mod, p.pyr_nmod ? "given" : "the rule's",
               1e6 * (p.wfs_wavelen > 0 ? p.wfs_wavelen : p.base.wavelen), p.pyr_photons, outdir, outdir, outdir);
    if (p.base.pupil_mask[0])
        printf("  pupil from %s (pupil.fits: give it to speckles --pupil)\n", p.base.pupil_mask);
    printf("  residual %.1f nm rms (%.1f nm without tip-tilt), residual tip-tilt %.3f lambda/D rms, Strehl %.3f\n",
           1e9 * s.residual_rms, 1e9 * s.residual_rms_nott, s.tt_rms, s.strehl);
    printf("  time-mean residual (static, not in the speckles) %.1f nm rms\n", 1e9 * s.static_rms);
    printf("  NCP %.1f nm rms; %.1f s -> %s/\n", 1e9 * s.ncp_rms, s.seconds, outdir);
    if (p.export_modal)
        printf("  modal telemetry: %zu modes in um of DM surface (modal_NNN.fits) on dm_modes.fits: --basis with "
               "--dm-pitch %.6g --dm-offset %g,%g --dm-rot %g --dm-flip --coef-scale 2e-6; its control matrix "
               "cm_modes.fits (modal-slopes --cm), its response matrix rm_modes.fits (modal-slopes --imat)\n", nmodes, reg.pitch, reg.x0,
               reg.y0, reg.rot * 180 / M_PI);
    if (p.export_truth)
        printf("  truth per WFS frame (truewf_NNN.fits): the true residual least-squares fitted on %s [m], "
               "extension DM the loop's commands%s\n",
               p.truth_actuators[0] ? "truth_actuators' points" : "the actuators",
               p.truth_actuators[0] ? ", extension OUTXY the points" : "");
    if (p.milk)
        printf("  milk logs in %s/milk/{wfs,cam}: stamp jitter %.3g s, camera clock drift %.3g and offset %.3g s, %ld "
               "WFS and %ld camera frames dropped (milk/truth.txt)\n", outdir, p.milk_jitter, p.milk_drift,
               p.milk_offset, p.milk_drop_wfs, p.milk_drop_cam);
    return CLI_OK;
}

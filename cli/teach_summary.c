/* What `teach` prints, and `speckles` where it teaches its default map: the layers, noise and
 * filter teach found, its loops, the map's learning curve and the choice (cli.h). */
#include "cli.h"
#include "specklewfs/run.h"

#include <stdio.h>

const char *cli_teach_chosen(int c)
{
    return c == SWFS_TEACH_SPACETIME    ? "the space-time map (neither check warned)"
           : c == SWFS_TEACH_PERFRAME   ? "the per-frame map of the same loops (a check warned)"
           : c == SWFS_TEACH_SPACETIME_PRIOR
               ? "the space-time map of loops at the slopes' speed (no frozen-flow layer to give them)"
           : c == SWFS_TEACH_PERFRAME_PRIOR
               ? "the per-frame map of loops at the slopes' speed (no frozen-flow layer to give them)"
               : "the per-frame map of the measured layer and random second layers (a check warned)";
}

void cli_teach_summary(FILE *f, const char *cmd, const struct swfs_teach_run_result *r, int modes_from_slopes,
                       const char *out, const char *work, int checks)
{
    const swfs_wind_estimate *e = &r->wind.est;
    fprintf(f, "%s: %zu WFS frames of %zu x %zu subapertures at %.6g Hz; %zu frozen-flow layer%s:\n", cmd,
            r->wind.nframes, r->wind.nsub, r->wind.nsub, r->wind.rate, e->nlayers, e->nlayers == 1 ? "" : "s");
    if (r->chosen == SWFS_TEACH_SPACETIME_PRIOR) {
        fprintf(f, "%s:   none tracked: the slopes' time correlation at lags", cmd);
        for (size_t k = 0; k < r->ntcorr; k++) fprintf(f, "%s %ld", k ? "," : "", r->tcorr_lags[k]);
        fprintf(f, " frames:");
        for (size_t k = 0; k < r->ntcorr; k++) fprintf(f, "%s %.3f", k ? "," : "", r->tcorr[k]);
        fprintf(f, "; speed calibration loops (m/s -> rms misfit):");
        for (size_t k = 0; k < r->nspeed; k++) fprintf(f, "%s %g -> %.3f", k ? "," : "", r->speed_cal[k], r->speed_misfit[k]);
        fprintf(f, "; the loops get two layers within a factor 1.41 of %.1f m/s in any direction, and the space-time "
                "map at lags of 1 and 2 frames is learned from them\n", r->prior_speed);
    }
    for (size_t k = 0; k < e->nlayers; k++)
        fprintf(f, "%s:   layer %zu: %.2f m/s toward %.1f deg%s\n", cmd, k + 1, e->layer[k].speed, e->layer[k].direction,
                k < r->nlayers ? "" : " (beyond the simulator's layers: not given to the loops)");
    fprintf(f, "%s: the slopes' white noise %.3g rad rms per slope (the lag-0 excess of their curl over %zu cells of "
            "2 x 2 subapertures; %.1f %% of the slopes' variance); the loops' slope_noise %.3g rad%s\n", cmd, r->noise_rms,
            r->noise_cells, 100 * r->noise_share, r->slope_noise, r->slope_noise == r->noise_rms ? ", the same" : ", as given");
    if (r->coupling_done)
        fprintf(f, "%s: the DM's functions from the loops' control matrix (ao_recon, rank %zu): %s; Gaussian functions "
                "of coupling %.3f miss its interaction matrix by %.1f %%, the interpolated surface by %.1f %%\n", cmd,
                r->coupling.rank, r->coupling.gaussian ? "Gaussian, the loops' dm_coupling that" : "the interpolated "
                "surface (dm_coupling 0)", r->coupling.coupling, 100 * r->coupling.misfit, 100 * r->coupling.misfit_interp);
    if (r->project_slopes)
        fprintf(f, "%s: the slopes are modal-slopes' projection (MODALCM): the loops' slopes learned on the same "
                "projection, rank %zu of %zu\n", cmd, r->project_rank, r->project_slopes);
    if (modes_from_slopes) {
        fprintf(f, "%s: the loop's modal filter from the slopes: their mode variances' knee at mode %zu; calibration "
                "loops (ao_modes -> knee):", cmd, r->knee_obs);
        for (size_t k = 0; k < r->ncal; k++) fprintf(f, "%s %zu -> %zu", k ? "," : "", r->cal_modes[k], r->cal_knee[k]);
        fprintf(f, "; profile misfit (rms log10) %.3f, zonal loops (ao_rcond:", r->misfit_modal);
        for (size_t z = 0; z < SWFS_TEACH_NZONAL; z++)
            fprintf(f, "%s %g %.3f", z ? "," : "", swfs_teach_zonal_rcond[z], r->zonal_misfit[z]);
        if (r->zonal) fprintf(f, "); the loops are zonal, ao_rcond = %g\n", swfs_teach_zonal_rcond[r->zonal_best]);
        else fprintf(f, "); ao_modes = %zu\n", r->ao_modes);
    } else if (r->ao_modes) {
        fprintf(f, "%s: the loops' modal filter: ao_modes = %zu, as given\n", cmd, r->ao_modes);
    }
    if (r->out_points && r->dm_pitch > 0)
        fprintf(f, "%s: the map's output points: %zu on a hexapolar grid of pitch %.4g m (the DM's %.4g m)\n", cmd,
                r->out_points, r->out_pitch, r->dm_pitch);
    else if (r->out_points)
        fprintf(f, "%s: the map's output points: %zu, as given (truth_actuators; pitch %.4g m)\n", cmd, r->out_points,
                r->out_pitch);
    fprintf(f, "%s: %zu loops simulated", cmd, r->nloops);
    if (r->loop_frames > r->loop_frames_described)
        fprintf(f, " of %zu WFS frames (lengthened from %zu: the map's %zu inputs need 10 frames each)", r->loop_frames,
                r->loop_frames_described, r->map_inputs);
    const char *maps = "the space-time map's";
    fprintf(f, "; lags %ld,%ld,%ld,%ld,%ld WFS frames; the space-time map misses the loops' residual by %.1f of %.1f nm "
            "on their frames\n", r->lags[0], r->lags[1], r->lags[2], r->lags[3], r->lags[4], 1e9 * r->st_misfit_rms,
            1e9 * r->st_truth_rms);
    if (r->curve.info.nframes > r->curve_first.info.nframes) { /* more loops, as the first curve asked */
        fprintf(f, "%s: over the first loops, ", cmd);
        cli_curve_line(f, maps, &r->curve_first, 1e9, " nm");
        if (r->curve_doubled.curve_n[0] && r->curve_doubled.info.nframes < r->curve.info.nframes) {
            fprintf(f, "%s: so twice the first loops%s; over them, ", cmd,
                    swfs_learn_curve_falls(&r->curve_first) ? " (a first curve does not end teach: its held-out parts "
                    "are a quarter of the first loops each)" : "");
            cli_curve_line(f, "the map's", &r->curve_doubled, 1e9, " nm");
        }
        if (r->asked_loops) {
            fprintf(f, "%s: so %zu loops; over them, ", cmd, r->asked_loops);
            cli_curve_line(f, "the map's", &r->curve_asked, 1e9, " nm");
        }
        fprintf(f, "%s: so %zu loops in all%s; over them, ", cmd, r->st_loops, r->asked_loops ? " (the budget)" : "");
        cli_curve_line(f, "the map's", &r->curve, 1e9, " nm");
    } else if (r->max_loops <= r->st_loops) {
        fprintf(f, "%s: %s learning curve: not measured (at most %zu loops: no more to add)\n", cmd, maps, r->max_loops);
    } else {
        fprintf(f, "%s: ", cmd);
        cli_curve_line(f, maps, &r->curve, 1e9, " nm");
    }
    if (r->chosen == SWFS_TEACH_SPACETIME_PRIOR) checks = 0; /* they compare the loops' layers with the slopes' */
    if (checks) cli_spacetime_summary(cmd, &r->check);
    fprintf(f, "%s: chose %s -> %s (%.0f s; the loops and maps in %s)\n", cmd, cli_teach_chosen(r->chosen), out, r->seconds,
            work);
}

void cli_dm_choice_summary(const char *cmd, const struct swfs_speckles_run_result *r)
{
    if (r->dm_choice_done)
        fprintf(stderr, "%s: the loops' DM by the science frames: %s kept (mean correlation of intensity and |psi|^2: "
                "Gaussian influence functions of coupling %.3g %.3f, the interpolated surface %.3f; per pixel %+.4f +- "
                "%.4f over %zu pixels; the Gaussian's kept beyond %.0f standard errors); the other map %s (--teach-set "
                "dm_coupling= says the DM)\n", cmd,
                r->dm_gauss_chosen ? "the Gaussian functions' map" : "the interpolated surface's map",
                r->dm_gauss_coupling, r->dm_corr[1], r->dm_corr[0], r->dm_corr_diff, r->dm_corr_se, r->dm_npix,
                SWFS_TEACH_DM_SE, r->dm_other_map);
    else if (r->dm_fallback[0])
        fprintf(stderr, "%s: the loops' DM: the interpolated surface's map kept; no Gaussian DM's to compare (%s)\n", cmd,
                r->dm_fallback);
}

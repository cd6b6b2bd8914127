/* What `speckles` prints after its run, a space-time reconstructor's checks against the
 * observation among it (cli.h); what teach found and chose is teach_summary.c's, the mean loops
 * and the loops' map mean_loops_summary.c's. */
#include "cli.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>

/* A space-time reconstructor's two checks against the observation (run.h st_*): the winds'
 * distance at the largest lag and the slopes' correlation at the lags, each with its warning. */
void cli_spacetime_summary(const char *cmd, const struct swfs_speckles_run_result *r)
{
    const int warns = swfs_spacetime_warns(r);
    if (r->info.nlags && !isnan(r->st_train_vx) && r->st_found) {
        if (r->st_train_nlayers)
            fprintf(stderr, "%s: space-time map: this telemetry's slopes show %zu frozen-flow layer%s, its training "
                    "loops' %zu; the layer here farthest from the loops' nearest moves (%.4f, %.4f) subapertures per WFS "
                    "frame, that one (%.4f, %.4f): %.2f subapertures apart at the largest lag\n", cmd, r->st_obs_nlayers,
                    r->st_obs_nlayers == 1 ? "" : "s", r->st_train_nlayers, r->st_obs_vx, r->st_obs_vy, r->st_train_vx,
                    r->st_train_vy, r->st_mismatch);
        else
            fprintf(stderr, "%s: space-time map: its training loops' slopes move (%.4f, %.4f) subapertures per WFS "
                    "frame, this telemetry's (%.4f, %.4f): %.2f subapertures apart at the largest lag\n", cmd,
                    r->st_train_vx, r->st_train_vy, r->st_obs_vx, r->st_obs_vy, r->st_mismatch);
        if (warns & SWFS_SPACETIME_WARN_WIND)
            fprintf(stderr, "%s: warning: the map was taught at another wind than this telemetry's (%s more than %.2f "
                    "subaperture apart at its largest lag): a space-time map taught at the wrong wind can be far worse "
                    "than the default; simulate the loops with the layers `specklewfs wind` gives (docs/telemetry.md)\n",
                    cmd, r->st_train_nlayers ? "a layer here and every layer of its loops" : "the two",
                    SWFS_SPACETIME_MISMATCH_WARN);
    } else if (r->info.nlags) {
        fprintf(stderr, "%s: space-time map: %s; its wind cannot be checked against this telemetry's\n", cmd,
                isnan(r->st_train_vx) ? "no training wind in its file (LRNVX, LRNVY)" : "no wind found in the telemetry");
    }
    if (r->info.nlags && r->st_corr_worst < SWFS_RECON_MAXLAGS) {
        const size_t k = r->st_corr_worst;
        const long *lags = r->st_lags;
        fprintf(stderr, "%s: space-time map: the slopes' correlation, this telemetry's against the training "
                "loops' (mean +- the farthest loop's distance), at", cmd);
        for (size_t j = 0; j < r->info.nlags; j++) {
            int seen = lags[j] == 0;
            for (size_t i = 0; i < j && !seen; i++) seen = labs(lags[i]) == labs(lags[j]);
            if (!seen)
                fprintf(stderr, " %ld frames %.3f / %.3f +- %.3f;", labs(lags[j]), r->st_corr_obs[j], r->st_corr_train[j],
                        r->st_corr_spread[j]);
        }
        fprintf(stderr, "\n");
        if (warns & SWFS_SPACETIME_WARN_CORR)
            fprintf(stderr, "%s: warning: %ld frames apart this telemetry's slopes correlate at %.3f where the "
                    "training loops' did at %.3f +- %.3f (more than three times that apart): a layer or a speed the loops "
                    "lack, or a system simulated otherwise (noise, loop gain); a space-time map taught without the observation's whole profile can be worse than the "
                    "default (docs/telemetry.md)\n", cmd, labs(lags[k]), r->st_corr_obs[k], r->st_corr_train[k],
                    r->st_corr_spread[k]);
    }
    if (r->info.nlags)
        cli_spacetime_edges(cmd, r->st_edges_joined, r->st_edges_clamped, r->st_edges_unreadable, r->st_edges_why);
}

void cli_spacetime_edges(const char *cmd, size_t joined, size_t clamped, size_t unreadable, const char *why)
{
    if (joined || clamped)
        fprintf(stderr, "%s: space-time map: its lags run on into the neighbour telemetry file across %zu file "
                "boundar%s the telemetry shows contiguous; clamped at %zu it does not\n", cmd, joined,
                joined == 1 ? "y" : "ies", clamped);
    if (unreadable)
        fprintf(stderr, "%s: space-time map: clamped at %zu file boundar%s whose neighbour file could not be read (%s)\n",
                cmd, unreadable, unreadable == 1 ? "y" : "ies", why);
}

long cli_spacetime_lags(const char *cmd, const long *lags, size_t n)
{
    long lmax = 0;
    fprintf(stderr, "%s: space-time reconstructor of %zu lags (", cmd, n);
    for (size_t k = 0; k < n; k++) {
        fprintf(stderr, "%s%ld", k ? "," : "", lags[k]);
        if (labs(lags[k]) > lmax) lmax = labs(lags[k]);
    }
    fprintf(stderr, " WFS frames)");
    return lmax;
}

void cli_speckles_summary(const char *cmd, const struct swfs_speckles_run_options *o,
                          const struct swfs_speckles_run_result *r, const struct swfs_teach_run_result *tr)
{
    /* the reconstructor in use: the taught map, or vk where teach could not */
    swfs_pipeline_options used = o->pipe;
    const char *used_file = o->recon;
    if (!o->lin.basis && o->pipe.recon == SWFS_RECON_TEACH) {
        used.recon = r->taught ? SWFS_RECON_GIVEN : SWFS_RECON_VK;
        used_file = r->taught ? r->teach_map : NULL;
        if (r->taught && r->teach_reused) {
            fprintf(stderr, "%s: reused %s, taught by an earlier run for the same telemetry, system files and teach "
                    "options (TEACHFPR = '%s'; %zu loops): %s (--teach-again teaches anew)\n", cmd, r->teach_map,
                    r->teach_fingerprint, tr->nloops, cli_teach_chosen(tr->chosen));
        } else if (r->taught) {
            char work[4200];
            swfs_path_dir(r->teach_map, work, sizeof work);
            if (o->nteach_keys) {
                fprintf(stderr, "%s: the loops' system as its files describe it, with", cmd);
                for (size_t k = 0; k < o->nteach_keys; k++) fprintf(stderr, "%s %s", k ? "," : "", o->teach_keys[k]);
                fprintf(stderr, " (--teach-set)\n");
            }
            /* the filter from the slopes unless --teach-set gave one (then no knee was sought) */
            cli_teach_summary(stderr, cmd, tr, tr->knee_obs > 0, r->teach_map, work, 0);
        }
        if (r->taught) {
            cli_dm_choice_summary(cmd, r);
        } else {
            fprintf(stderr, "specklewfs %s: warning: no map could be taught for this observation (%s); the von Karman "
                    "map (--recon vk) instead\n", cmd, r->teach_fallback);
        }
    }
    if (r->modal_regularized)
        fprintf(stderr, "specklewfs %s: warning: these slopes came through modal-slopes --imat from coefficients whose "
                "white noise is not what a least-squares control matrix gives them (MODALLSQ %.3g; 1 for one): the "
                "system's control matrix regularizes its modes, so the slopes are not its WFS's and no map fits them; give "
                "modal-slopes the system's control matrix (--cm), or take the coefficients through the linear model "
                "(--basis)\n", cmd, isfinite(r->modal_lsq) ? r->modal_lsq : INFINITY);
    if (!o->lin.basis) {
        cli_recon_summary(cmd, &used, used_file, o->valid, &r->info,
                          r->curl_noise > 0 ? "the slopes' curl power: modal-slopes' projection (MODALCM) leaves no "
                                              "slope outside the modes to estimate it from" : NULL);
    } else {
        cli_linear_summary(cmd, &o->lin, &r->info);
        if (!o->lin.control && !o->lin.imat && o->pipe.recon == SWFS_RECON_TEACH)
            fprintf(stderr, "%s: note: no map is taught for a linear model (the coefficients are the wavefront as "
                    "given); if the WFS is a Shack-Hartmann whose modal control matrix you have, `specklewfs "
                    "modal-slopes` turns the coefficients back into its slopes, for which the default teaches one "
                    "(docs/telemetry.md, \"The modal input kind\")\n", cmd);
    }
    fprintf(stderr, "%s: %zu %sframes from %zu of %zu timing-table rows (%zu reconstructor modes, %zu pupil samples "
            "outside the actuator hull, extrapolated) -> %s\n", cmd, r->nout, o->pipe.wfs_rate ? "WFS " : "", r->nok,
            r->ncubes, r->info.recon_modes, r->info.n_outside, o->out);
    fprintf(stderr, "%s: the AO residual's time mean over these frames %.1f nm rms (RESMEAN; pupil takes it out of the "
            "NCP)\n", cmd, r->resmean_rms * 1e9);
    const swfs_mean_teach_result *m = &r->mean_teach;
    const size_t nml = m->done ? m->nloops : o->nmean_loops;
    cli_mean_teach_summary(cmd, m);
    cli_meanmiss_summary(cmd, nml, r->meanmiss_heldout, r->meanmiss_rms);
    cli_loops_map_summary(cmd, &r->loops_map, nml);
    if (swfs_speckles_resmean_warns(r))
        fprintf(stderr, "specklewfs %s: warning: that mean is more than the wavelength (%.0f nm), which no closed loop's "
                "is: the reconstructor amplifies slope patterns the model's D does not make\n", cmd, r->wavelen * 1e9);
    cli_spacetime_summary(cmd, r);
}

void cli_curve_line(FILE *f, const char *cmd, const swfs_learn_run_result *r, double u, const char *unit)
{
    if (!r->curve_n[0]) {
        fprintf(f, "%s learning curve: not measured (it takes at least 4 data sets, each part large enough for a map "
               "without it)\n", cmd);
        return;
    }
    fprintf(f, "%s learning curve: held-out misfit %.4g%s from %zu frames, %.4g%s from %zu (scaled best: %.4g%s, "
            "%.4g%s; over %zu outputs); ", cmd, u * sqrt(r->curve_m2[0]), unit, r->curve_n[0], u * sqrt(r->curve_m2[1]),
            unit, r->curve_n[1], u * sqrt(r->curve_s2[0]), unit, u * sqrt(r->curve_s2[1]), unit, r->curve_outputs);
    if (!(r->curve_b > 0))
        fprintf(f, "no fall from %zu to %zu frames: the curve cannot tell whether more would help (the held-out "
                "parts' scatter is larger than the fall)\n", r->curve_n[0], r->curve_n[1]);
    else if (!swfs_learn_curve_falls(r))
        fprintf(f, "a fall of %.2g %% in misfit^2 from %zu to %zu frames, within %.0f times its standard error from "
                "the four held-out parts (%.2g %%): the curve cannot tell whether more would help\n",
                100 * (r->curve_m2[0] - r->curve_m2[1]) / r->curve_m2[1], r->curve_n[0], r->curve_n[1],
                SWFS_LEARN_CURVE_FALL_SE, 100 * r->curve_fall_se / r->curve_m2[1]);
    else if (isinf(r->curve_excess))
        fprintf(f, "steeper than a + b/n: more frames would still help (no bound)\n");
    else
        fprintf(f, "the map of all %zu is %.1f %% above unlimited frames' (%.4g%s) in misfit^2; %zu frames would bring it "
               "to %.0f %%\n", r->info.nframes, 100 * r->curve_excess, u * sqrt(r->curve_a), unit, r->curve_frames,
               100 * SWFS_LEARN_CURVE_EXCESS);
}

void cli_learn_wind_summary(const swfs_learn_run_result *r, size_t nd)
{
    if (r->nwind)
        printf("learn: the training loops' slopes move (%.4f, %.4f) subapertures per WFS frame (%zu of %zu data sets; "
               "the farthest %.4f from that; the tracked layers), and their layers:\n", r->wind_vx, r->wind_vy,
               r->nwind, nd, r->wind_spread);
    for (size_t k = 0; k < r->nwlayers; k++)
        printf("learn: layer %zu of the training loops' slopes: (%.4f, %.4f) subapertures per WFS frame, in %zu data "
               "set%s (the farthest %.4f from that)\n", k + 1, r->wlayer_vx[k], r->wlayer_vy[k], r->wlayer_n[k],
               r->wlayer_n[k] == 1 ? "" : "s", r->wlayer_spread[k]);
    if (!r->nwind)
        printf("learn: no wind found in the training loops' slopes (full layout needed): speckles cannot check the "
               "observation's against it\n");
}

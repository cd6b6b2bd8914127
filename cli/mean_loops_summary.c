/* What `speckles` prints of its mean loops (--mean-loop teach), their miss of the residual's
 * mean, and the loops' own map with the self-check's choice (cli.h). */
#include "cli.h"
#include "specklewfs/run.h"

#include <math.h>
#include <stdio.h>

void cli_mean_teach_summary(const char *cmd, const swfs_mean_teach_result *m)
{
    if (m->fallback[0])
        fprintf(stderr, "%s: note: a pyramid's telemetry, but no loops of the system for the residual mean's miss "
                "(--mean-loop teach, the default for it): %s; the mean as the reconstruction gives it\n", cmd, m->fallback);
    if (m->done) {
        fprintf(stderr, "%s: --mean-loop teach%s: %zu loops of %zu WFS frames %s (%s, %.0f s): a %s", cmd,
                m->automatic ? " (the default for a pyramid's telemetry; --mean-loop none: without)" : "", m->nloops,
                m->loop_frames, m->reused ? "reused, made for the same description" : "simulated", m->work, m->seconds,
                m->pyramid ? "pyramid" : "Shack-Hartmann");
        if (isfinite(m->photons)) fprintf(stderr, ", %.0f photons per subaperture and frame (its noise %.3g)", m->photons,
                                          m->noise_rms);
        if (isfinite(m->slope_noise)) fprintf(stderr, ", slope noise %.3g rad", m->slope_noise);
        if (m->knee) fprintf(stderr, ", %zu modes controlled (the knee)", m->knee);
        for (size_t l = 0; l < m->nlayers; l++)
            fprintf(stderr, "%s %.1f m/s toward %.0f deg", l ? "," : ", layers", m->speed[l], m->direction[l]);
        if (m->act_pitch > 0) fprintf(stderr, ", DM pitch %.4g m (the basis)", m->act_pitch);
        if (m->nloops > m->nloops_first || isfinite(m->curve_excess))
            fprintf(stderr, ", %zu loops where the loops' map's learning curve over the first %zu (%.0f %% above "
                    "unlimited frames) asked for %zu frames", m->nloops, m->nloops_first, 100 * m->curve_excess,
                    m->curve_frames);
        if (m->r0_pairs)
            fprintf(stderr, ", r0 %.4g m fitted to the telemetry's residual power (%zu pair%s of loops; the kept pair's "
                    "%.2f of it)", m->r0, m->r0_pairs, m->r0_pairs > 1 ? "s" : "", m->power_ratio);
        else if (m->r0 > 0)
            fprintf(stderr, ", r0 %.4g m (%s)", m->r0, m->reused ? "mean_loops.conf" : "given");
        fprintf(stderr, "; the rest as given or the simulator's defaults (mean_loops.conf)\n");
    }
}

void cli_meanmiss_summary(const char *cmd, size_t nloops, double heldout, double rms)
{
    if (nloops && isfinite(heldout))
        fprintf(stderr, "%s: this reconstruction's miss of the AO residual's mean in %zu simulated loops (--mean-loop): "
                "held out, the others' mean leaves %.2f of each loop's own square: %s\n", cmd, nloops, heldout,
                heldout < 1 ? "shared, their mean added" : "each loop's own, nothing added");
    if (rms > 0)
        fprintf(stderr, "%s: with the %s miss of it added, %.1f nm rms\n", cmd,
                nloops ? "loops' shared" : "map's own (MEANMISS: from the loops it was made with, by learn or speckles' "
                "choice)", rms * 1e9);
}

void cli_loops_map_summary(const char *cmd, const swfs_loops_map_result *lm, size_t nml)
{
    if (lm->fallback[0])
        fprintf(stderr, "%s: note: no map from the loops to choose against the interaction matrix's (--loops-map): %s; "
                "its speckles as written\n", cmd, lm->fallback);
    char mmw[300] = "", pf[120] = "";
    if (isfinite(lm->pf_meanmiss_heldout))
        snprintf(pf, sizeof pf, "; the per-frame map's of the same loops %.2f%s", lm->pf_meanmiss_heldout,
                 lm->mean_from_perframe ? ": its mean instead" : "");
    if (isfinite(lm->meanmiss_heldout))
        snprintf(mmw, sizeof mmw, "(each loop's by the map of the others, held out %.2f: %s%s)", lm->meanmiss_heldout,
                 lm->mean_from_perframe ? "not shared" : lm->mean_from_imat ? "not shared; the interaction matrix's "
                 "corrected mean instead" : lm->meanmiss_rms > 0 ? "added" : "none added", pf);
    if (lm->mix_note[0])
        fprintf(stderr, "%s: note: the two maps not mixed (--loops-map): %s; the two scored alone\n", cmd, lm->mix_note);
    char wr[160];
    if (lm->weight == 1) snprintf(wr, sizeof wr, "the interaction matrix's kept");
    else if (lm->weight == 0) snprintf(wr, sizeof wr, "the loops' map's speckles written");
    else snprintf(wr, sizeof wr, "the mix at %.2f of the interaction matrix's map written", lm->weight);
    char mix[400] = "";
    for (int k = 0, n = 0; k < SWFS_LOOPS_MAP_NMIX && isfinite(lm->explained_mix[k]) && n >= 0 && n < (int)sizeof mix; k++)
        n += snprintf(mix + n, sizeof mix - (size_t)n, "%s%.2f: %.2f %%", k ? ", " : ", the two mixed at ",
                      lm->mix_weight[k], 100 * lm->explained_mix[k]);
    if (lm->tried && lm->nlags) {
        char lg[200] = "";
        for (size_t k = 0, n = 0; k < lm->nlags && n < sizeof lg; k++)
            n += (size_t)snprintf(lg + n, sizeof lg - n, "%s%ld", k ? "," : "", lm->lags[k]);
        char why[160];
        if (lm->lag_speed > 0)
            snprintf(why, sizeof why, "the loops' fastest layer %.4f subapertures per WFS frame: half a subaperture in "
                     "%ld frames", lm->lag_speed, lm->lags[2]);
        else
            snprintf(why, sizeof why, "no layer tracked in the loops: the frames next to each");
        fprintf(stderr, "%s: --loops-map: a space-time map, the loops' telemetry at lags %s (%s)\n", cmd, lg, why);
    } else if (lm->tried && lm->st_frames)
        fprintf(stderr, "%s: --loops-map: a per-frame map (a space-time one's inputs need %zu frames; the loops hold "
                "%zu)\n", cmd, lm->st_frames, lm->nframes);
    char carried[120];
    if (lm->carry_resid == 0) /* (exactly 0: the map stays on the loops' own output points) */
        snprintf(carried, sizeof carried, "on the loops' output grid, finer than the DM");
    else
        snprintf(carried, sizeof carried, "their DM on the basis within %.2g", lm->carry_resid);
    if (lm->tried)
        fprintf(stderr, "%s: --loops-map: a map learned from the %zu loops' %zu frames for %zu inputs (misfit %.1f of "
                "%.1f nm per output; %s), its miss of the mean %s: "
                "the self-check over %zu pixels, the interaction matrix's %.2f %% explained, the loops' map's %.2f %%%s "
                "-> %s (%.0f s; %s)\n", cmd, nml, lm->nframes, lm->inputs, 1e9 * lm->misfit_rms, 1e9 * lm->truth_rms,
                carried, mmw, lm->ncommon, 100 * lm->explained[0], 100 * lm->explained[1], mix, wr, lm->seconds,
                lm->work);
}

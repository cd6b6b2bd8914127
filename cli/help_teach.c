/* The usage text of `teach`, kept apart from its option parsing (cmd_teach.c). */
#include "cli.h"

#include <stdio.h>

static const char *usage_text =
    "usage: specklewfs teach SLOPES.fits... --science SCI.fits --actuators ACT.fits [--pupil P.fits]\n"
    "                        [--valid V.fits] [key=value ...] -o W.fits [--work DIR] [--loops N] [--seed S]\n"
    "                        [--max-loops M]\n"
    "       specklewfs teach SLOPES.fits... --system CONFIG [key=value ...] -o W.fits ...\n"
    "\n"
    "A reconstructor for this observation, learned from simulated closed loops of your system\n"
    "at the winds its own slopes show: the rule docs/telemetry.md measured over the matrix of\n"
    "systems (within 1.3x of the ideal speckles' NCP error on 47 of 48 runs, where the von\n"
    "Karman reconstructor was on 11 of 24). In one run:\n"
    "  1. the frozen-flow layers of the observation's slopes (as `specklewfs wind`);\n"
    "  2. N loops of the system (`simulate mode=timeseries` with CONFIG and key=value: your\n"
    "     telescope, WFS, DM, loop, vibration, noise and camera timing) with those layers, each\n"
    "     at a speed within a factor 1.41 of the one found, the first one's share of the\n"
    "     turbulence spread over 0.3-0.7 across the loops when there are more (the slopes do\n"
    "     not tell the shares). Without ao_modes (or ao_recon, ao_rcond) the loops' filter\n"
    "     comes from the slopes: the knee of their variances along the DM modes, matched by\n"
    "     up to four calibration loops (modes_NN/; TEACHMOD, TEACHKNE), or a zonal loop's\n"
    "     cut (ao_rcond 0.02-0.2, zonal_NN/; TEACHRCO) where a zonal loop's variances come\n"
    "     nearer the observation's (TEACHMMF, TEACHZMF);\n"
    "     Without slope_noise the loops' slope noise is the observation's white slope noise,\n"
    "     measured from its slopes' curl (TEACHNOI; TEACHSNO the loops');\n"
    "  3. the space-time map (`learn --lags 0,-L,L,-2L,2L`, L the frames in which the fastest\n"
    "     layer moves half a subaperture; more loops where its `learn --curve` asks) and\n"
    "     its two checks against the observation (as\n"
    "     `speckles` prints them). The map writes the wavefront on a grid of half the DM's\n"
    "     pitch (at least two pupil samples; DIR/outgrid.fits, W.fits' extension OUTXY): the\n"
    "     loops' truth is fitted there, so the lagged slopes also tell the residual the DM\n"
    "     cannot hold, which frozen flow carries across the subapertures (docs/telemetry.md;\n"
    "     truth_actuators=FILE gives other points);\n"
    "  4. where a check warns, the per-frame map: of the same loops when more than one layer\n"
    "     was found, else of N more loops of the measured layer and a random second layer.\n"
    "Where `wind` tracks no frozen-flow layer (slopes mostly noise, turbulence that does not\n"
    "flow): the speed whose one-layer calibration loops (speed_NN/) match the slopes' time\n"
    "correlation (TEACHPSP), loops of two layers near it in any direction (prior_NN/; more\n"
    "where the map's learning curve asks), and their space-time map at lags of 1 and 2 frames\n"
    "(TEACHSEL 'spacetime_prior').\n"
    "Give W.fits to `specklewfs speckles --recon W.fits`. It takes minutes: each loop (and\n"
    "each calibration loop that waits for no other's result) is a simulation as long as\n"
    "CONFIG's cubes, one per core at a time (threads=N: N at a time).\n";

static const char *usage_opts =
    "\n"
    "  SLOPES.fits   the observation's telemetry, consecutive files of one series (2 nsub^2\n"
    "                slopes per WFS frame, as the simulator writes them; or, with the system's\n"
    "                valid=MAP, the used subapertures' only: give speckles the same --valid)\n"
    "  --science SCI.fits --actuators ACT.fits [--pupil P.fits] [--valid V.fits]\n"
    "                the system from the observation's own files, the ones `speckles` takes:\n"
    "                the science cube's geometry, the DM's positions, the telescope's pupil,\n"
    "                the valid subapertures; nsub, wfs_rate and the loops' length from the\n"
    "                first telemetry file; the loop's gain and delay, r0 and vibration the\n"
    "                simulator's (key=value to set them); the modal filter and the slope\n"
    "                noise from the slopes (docs/telemetry.md); keys of --system or\n"
    "                key=value win\n"
    "  --system CONFIG, key=value   the system, in `simulate mode=timeseries` keys (config/\n"
    "                mmt-clio.conf documents them); nsub, wfs_rate and teldiam must be the\n"
    "                observation's; the layers and the seed are teach's to set\n"
    "  -o W.fits     the chosen map; its header says which (TEACHSEL) and why (TEACHWRN:\n"
    "                the checks that warned, TEACHMIS, TEACHCEX: their numbers)\n"
    "  --work DIR    folder for the loops (loop_NN/, mixed_NN/), the output grid (outgrid.fits)\n"
    "                and both maps tried (spacetime.fits, perframe.fits); created if missing (default: W.teach\n"
    "                beside W.fits, its name without .fits)\n"
    "  --loops N     loops per set (default 12)\n"
    "  --max-loops M loops at most where the learning curve asks for more than N\n"
    "                (default 4 N, at most 64: the cost of the first N four times over)\n"
    "  --seed S      loop k's seed is S + k (default 101)\n";

void cli_help_teach(void)
{
    fputs(usage_text, stdout);
    fputs(usage_opts, stdout);
}

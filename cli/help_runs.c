/* The usage texts of the three longest commands (speckles, stream, live), kept apart from
 * their option parsing. */
#include "cli.h"

#include <stdio.h>

static const char *speckles_usage_text =
    "usage: specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits\n"
    "                           [--recon teach|vk|map|svd | --recon W.fits] [--teach-work DIR] [--rcond R]\n"
    "                           [--teach-set KEY=VALUE]... [--modes K] [--slope-noise RAD]\n"
    "                           [--vk-l0 M] [--write-recon W.fits] [--tiptilt exposure|frame|keep]\n"
    "                           [--mean ensemble|cube] [--wfs-rate [--wfs-hz HZ]]\n"
    "                           [--match IN.fits OUT.fits]... [--pupil MASK.fits] [--threads N] [--batch B]\n"
    "                           [--mean-loop DIR... | teach | none]\n"
    "       specklewfs speckles TIMING.txt --science SCIENCE.fits --basis CUBE.fits [--control C.fits | --imat D.fits]\n"
    "                           [--dm-pitch M --dm-offset X,Y --dm-rot DEG --dm-flip] [--coef-scale S] -o SPECKLES.fits\n"
    "\n"
    "Complex speckles from WFS slopes (Codona & Kenworthy 2013, Sec. 4.4). For every camera\n"
    "exposure of the usable cubes of TIMING.txt (from `specklewfs sync`): z = W s at the\n"
    "actuators (tip-tilt: see --tiptilt), Clough-Tocher interpolation to the pupil grid,\n"
    "P exp(2 pi i z / lambda) summed over the exposure's WFS frames with fractional end\n"
    "weights, one MFT, core-phase referencing (eq:downsampledHalo); then the ensemble-average\n"
    "static halo is subtracted (eq:computedSpeckleField).\n"
    "\n"
    "  TIMING.txt          timing table; relative slopes paths are taken from its folder\n"
    "  --science FILE      reduced science cube (reduce): geometry keywords WAVELEN, TELDIAM,\n"
    "                      OBSCUR, PIXSCALE, PUPDX, PUPN and the focal window size\n"
    "  --actuators FILE    actuator positions, 2 x nact [m]\n"
    "  -o SPECKLES.fits    complex cube, one frame per science frame of the usable cubes\n"
    "  --recon teach       (default) a map taught for this observation, as `specklewfs teach\n"
    "                      SLOPES... --science --actuators [--pupil --valid]` makes it: closed\n"
    "                      loops of the system its files describe, at the winds its slopes show,\n"
    "                      with the modal filter its slopes show (docs/telemetry.md: within 1.3x\n"
    "                      of the ideal speckles on 47 of 48 matrix runs, vk on 23). Minutes per\n"
    "                      observation; the loops and the map (taught.fits: --recon taught.fits\n"
    "                      uses it again) in --teach-work DIR (default: beside -o, its name with\n"
    "                      .teach; the loops' folders removed unless --teach-keep-loops);\n"
    "                      --teach-loops N (12), --teach-seed S (101); more loops, up to\n"
    "                      --teach-max-loops M (4 N, at most 64), where the map's learning\n"
    "                      curve asks (teach --max-loops). A later run whose\n"
    "                      telemetry, system files and teach options are the same (to the byte)\n"
    "                      reuses that map at once (its TEACHFPR; --teach-again teaches anew).\n"
    "                      --teach-set KEY=VALUE (repeatable): what the files do not say of\n"
    "                      the system, in simulate's keys (e.g. dm_coupling=0.15 for a DM of\n"
    "                      Gaussian influence functions, ao_gain, ao_delay), as `teach\n"
    "                      key=value`.\n"
    "                      Slopes without a frozen-flow layer are taught from loops at\n"
    "                      the speed of their time correlation; where teach cannot (no\n"
    "                      WFSRATE, too few DM modes, ...) it says why and uses vk\n"
    ;

/* (split: ISO C's string literals are at most 4095 characters) */
static const char *speckles_usage_recon =
    "  --recon W.fits      reconstructor (NAXIS1 = slopes, NAXIS2 = actuators): the residual\n"
    "                      wavefront [m of OPD, not DM surface] at the actuators = W slopes [rad];\n"
    "                      its gain on the model's D must be 0.5..2 (--recon-scale S multiplies it:\n"
    "                      -2 for a matrix to DM commands, a correction of the surface); or built\n"
    "                      here from the Shack-Hartmann interaction matrix D = U S V^T:\n"
    "  --recon vk          MAP, von Karman prior C of the actuators (--vk-l0 M: 10;\n"
    "                      0: the outer scale, the prior's scale and the slope noise fitted to\n"
    "                      the slopes by maximum likelihood)\n"
    "                      scaled to the slopes: W = C D^T (D C D^T + sigma^2 I)^-1\n"
    "  --recon map         MAP / Wiener reconstructor with the prior learned from the\n"
    "                      slopes of the usable cubes' telemetry files: mode i of D gets the\n"
    "                      gain (1 - sigma^2 / P_i)_+ / s_i, P_i the mean square of the slopes\n"
    "                      on u_i, sigma^2 the slope noise\n"
    ;

static const char *speckles_usage_text2 =
    "  --recon svd         truncated pseudo-inverse: singular values above\n"
    "                      --rcond (5e-2) x the largest, at most --modes K (0 = no limit)\n"
    "  --slope-noise RAD   effective slope noise rms [rad] for --recon vk|map (default: estimated\n"
    "                      from the slopes outside D's column space: noise + aliasing)\n"
    "  --write-recon FILE  also write the reconstructor in use (e.g. for `specklewfs stream`;\n"
    "                      with --basis --imat the map to its coefficients, for --control)\n"
    CLI_GEOM_HELP
    CLI_BAND_HELP
    "  --tiptilt MODE      exposure (default): remove from every WFS frame the weighted mean x/y\n"
    "                      slope of its exposure and keep the motion within it, as registered\n"
    "                      science frames have it (reduce re-centres, it cannot de-blur);\n"
    "                      frame: remove every frame's own mean slopes (the paper's Sec. 4.4), and\n"
    "                      re-centre the --match copies on the exposure-mean tilt the slopes\n"
    "                      measure instead of the image peak (docs/telemetry.md);\n"
    "                      keep: remove nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt      same as --tiptilt keep\n"
    "  --mean MODE         static halo: ensemble (all frames, default) or cube (each cube)\n"
    "  --match IN OUT      write OUT = the frames of IN (a cube aligned with SCIENCE.fits, e.g.\n"
    "                      SCIENCE.fits itself) of the usable cubes, so it matches SPECKLES.fits\n"
    "  --pupil MASK.fits   pupil mask PUPN x PUPN (default: annulus from TELDIAM, OBSCUR)\n"
    "  --valid MAP.fits    the AO system's valid-subaperture map, nsub x nsub (nonzero = used):\n"
    "                      those subapertures whatever their illumination (default: >= 50 % lit);\n"
    "                      the slopes may then be the used subapertures' only (2 nvalid: x, then y)\n"
    "  --threads N         engine workers (default 1)\n"
    "  --batch B           frames per pipeline call (default 128); under mpirun the cubes are\n"
    "                      shared out in pieces of B frames (docs/cluster.md)\n"
    "  --wfs-rate          write the speckles at the WFS rate instead, for `specklewfs coherence`:\n"
    "                      one frame per WFS frame covered by the usable cubes (cube after cube,\n"
    "                      each cube's frames contiguous), each propagated alone and core-phase\n"
    "                      referenced, the static halo (--mean) subtracted; tip-tilt removed per\n"
    "                      WFS frame (default; or --tiptilt keep). Header: FRAMEDT = 1/WFSRATE [s],\n"
    "                      FRATIO (camera exposure = FRATIO x FRAMEDT), NSEGS (cubes). --match and\n"
    "                      --tiptilt exposure do not apply\n"
    "  --wfs-hz HZ         WFS frame rate [Hz] when the slopes files have no WFSRATE keyword\n"
    ;

static const char *speckles_usage_mean =
    "  --mean-loop DIR     (repeatable, at least 2) simulated closed loops of the same system\n"
    "                      (`simulate mode=timeseries`: slopes_NNN.fits of this telemetry's kind,\n"
    "                      truth.fits): this run's reconstruction's miss of the residual's time\n"
    "                      mean in each, checked against the others'; where they share it (a\n"
    "                      pyramid's, at the pupil's rim) their mean is added to RESMEAN.\n"
    "                      A map made by `learn` may carry its own (MEANMISS), added likewise\n"
    "  --mean-loop teach   the same from loops speckles simulates of the system the files\n"
    "                      describe (the sensor from WFSTYPE, PYRMOD, WFSLAM; the noise, layers\n"
    "                      and modal filter from the telemetry; the DM's pitch from --basis;\n"
    "                      --teach-set KEY=VALUE for the rest), --mean-teach-loops N (4) of\n"
    "                      them, in --teach-work (OUT.teach) and reused while the description\n"
    "                      is the same (--teach-again: anew). The default for a pyramid's\n"
    "                      telemetry (WFSTYPE) with --basis: where the files do not describe\n"
    "                      the loops, a note says why and the run goes on without them\n"
    "  --mean-loop none    no loops, not even a pyramid's default\n";

void cli_help_speckles(void)
{
    fputs(speckles_usage_text, stdout);
    fputs(speckles_usage_recon, stdout);
    fputs(speckles_usage_text2, stdout);
    fputs(speckles_usage_mean, stdout);
    fputs(CLI_LINEAR_HELP, stdout);
}

static const char *stream_usage_text =
    "usage: specklewfs stream --timing TIMING.txt --science SCIENCE.fits [--slopes DIR|FILE]\n"
    "                         | --wfs-log DIR|FILE [--wfs-log ...] [--clock CLOCK.txt] [--exptime T]\n"
    "                         --recon RECON.fits --actuators ACT.fits -o HALO.fits\n"
    "                         [--pupil-out PUPIL.fits] [--every K] [--every-seconds T]\n"
    "                         [--threads N] [--checkpoint FILE] [--static auto|none|HALO0.fits]\n"
    "                         [--static-out FILE] [--pupil MASK.fits] [--tiptilt exposure|frame|keep]\n"
    "                         [--batch B]\n"
    "                         [--max-frames N]\n"
    "                         [--read-noise SIGMA] [--gain G] [--g-smooth L]\n"
    "\n"
    "The whole real-time path in one pass (Codona & Kenworthy 2013, Sec. 4): WFS slopes ->\n"
    "reconstructed wavefront -> pupil field summed over each camera exposure -> focal field\n"
    "(one MFT per camera frame), core-phase referenced (eq:downsampledHalo), minus a static\n"
    "halo (eq:computedSpeckleField) -> per-pixel accumulators against the camera frames.\n"
    "HALO.fits is rewritten (atomically) every K camera frames and/or T seconds and at the\n"
    "end; progress, valid fraction and median SNR go to stderr. Memory does not grow with\n"
    "the number of frames (one telemetry file and one batch are held at a time).\n"
    "\n"
    "  --timing TIMING.txt   ratio and per-cube exposure starts from 'specklewfs sync'; cubes\n"
    "                        marked 'straddles' are skipped\n"
    "  --science FILE        reduced science cube ('specklewfs reduce'): frames, geometry\n"
    "                        keywords, RDNOISE / GAIN\n"
    "  --slopes DIR|FILE     folder holding the telemetry files the timing table names, or\n"
    "                        one telemetry file used for every cube (default: the timing\n"
    "                        table's folder; absolute names in the table are used as they are)\n"
    "  --recon, --actuators  reconstructor (nact x nslopes [m/rad]) and actuator positions;\n"
    "                        a space-time map (learn --lags; speckles' taught.fits) gets each\n"
    "                        frame's slopes stacked with those at its lags, across the\n"
    "                        telemetry files that continue each other, as in 'speckles'\n"
    "                        (with --wfs-log: within the logs' segments, as 'live')\n"
    "  -o HALO.fits          the estimate (extensions as 'specklewfs estimate')\n"
    ;

static const char *stream_usage_text2 =
    "  --pupil-out FILE      also the pupil field / NCP map at every update ('specklewfs pupil')\n"
    "  --pupil-method M      fit (the default when possible) or moments, as 'pupil --method'\n"
    "  --every K             update after every K camera frames (default: only at the end)\n"
    "  --every-seconds T     update when T seconds have passed since the last one\n"
    "  --threads N           engine workers (default 2)\n"
    "  --checkpoint FILE     save the accumulators at every update ('specklewfs merge')\n"
    "  --static auto         (default) the paper's choice: S^1/2 Psi_0, the unaberrated halo\n"
    "                        scaled by the mean core amplitude of the first batch, fixed\n"
    "                        from then on; none: no subtraction; or a complex image file\n"
    "                        (e.g. the HALO extension of an earlier run). A constant offset\n"
    "                        does not bias the estimate: the accumulators remove the\n"
    "                        data-set mean of psi exactly (eq:zeroMean) -- but runs whose\n"
    "                        checkpoints will be merged must share it: save it from the\n"
    "                        first with --static-out and give it to the others\n"
    "  --static-out FILE     write the static halo used (complex image)\n"
    "  --pupil MASK.fits     pupil transmission (PUPN x PUPN; default: annulus from TELDIAM,\n"
    "                        OBSCUR)\n"
    "  --tiptilt MODE        as in 'specklewfs speckles': exposure (default) removes from every\n"
    "                        WFS frame the weighted mean x/y slope of its exposure and keeps\n"
    "                        the motion within it, as registered science frames have it;\n"
    "                        frame removes every frame's own mean slopes (the paper's Sec.\n"
    "                        4.4); keep removes nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt        same as --tiptilt keep\n"
    "  --batch B             camera frames per batch (default 128)\n"
    "  --max-frames N        stop after N camera frames\n"
    "  --read-noise, --gain  noise model for the estimate (default: science header)\n";

static const char *stream_usage_mpi =
    "  --valid MAP.fits      the valid-subaperture map the reconstructor was made with\n"
    "                        ('speckles --valid'): slopes of the used subapertures only\n"
    "  --g-smooth L          scale-factor regularization [lambda/D] as in 'specklewfs estimate'\n"
    "                        (default 2; 0 = the paper's per-pixel g)\n"
    "  --mean-loop DIR|teach|none   as 'specklewfs speckles': DIR (repeatable, at least 2)\n"
    "                        simulated loops of the same system, their shared miss of the\n"
    "                        residual's time mean added to RESMEAN; teach (the default for a\n"
    "                        pyramid's telemetry with --basis and --timing) loops of the system\n"
    "                        the files describe, --mean-teach-loops N (4) in --teach-work\n"
    "                        (OUT.teach), reused while the description is the same (speckles'\n"
    "                        too, given its --teach-work; --teach-again: anew); none: without\n"
    "  --wfs-log DIR|FILE    instead of --timing: a WFS milk log (folder of NAME_hh:mm:ss.s.fits[.fz]\n"
    "                        + .txt, or one file); several are concatenated into one slope vector.\n"
    "                        The science cube's STAMPS (reduce of camera logs) place every exposure\n"
    "                        [stamp - T, stamp] on the WFS frames (docs/telemetry.md)\n"
    "  --clock CLOCK.txt     camera clock offset, drift and pairing from 'sync --wfs-log'\n"
    "  --exptime T           camera exposure [s] (default: STAMPS' EXPTIME, else the frame period)\n"
    CLI_GEOM_HELP
    CLI_BAND_HELP
    CLI_LINEAR_HELP
    "\n"
    "Under mpirun (srun) every process streams a share of the camera frames (cut at --batch\n"
    "boundaries) and rank 0 writes the products once, at the end, from the merged\n"
    "accumulators: the single-process products. --every/--every-seconds do not apply.\n"
    "See docs/cluster.md.\n";

void cli_help_stream(void)
{
    fputs(stream_usage_text, stdout);
    fputs(stream_usage_text2, stdout);
    fputs(stream_usage_mpi, stdout);
}

static const char *live_usage_text =
    "usage: specklewfs live --wfs NAME [--wfs NAME ...] --camera NAME --geom GEOM.fits\n"
    "                       --recon RECON.fits --actuators ACT.fits -o HALO.fits [options]\n"
    "\n"
    "The NCP estimate beside a running AO system: WFS slopes and camera frames from\n"
    "ImageStreamIO 2.00 shared-memory streams (milk/cacao), the WFS frames mapped onto each\n"
    "camera exposure by their time stamps, the path of 'specklewfs stream', HALO.fits (and\n"
    "PUPIL.fits, the checkpoint) rewritten every K frames or T seconds, optionally DM offsets\n"
    "written to a stream. SIGINT/SIGTERM (or --idle-exit, --max-frames) end the run cleanly\n"
    "with the final products and checkpoint. Design and protocol: docs/live.md.\n"
    "\n"
    "  --wfs NAME            WFS stream (slopes, x then y); repeat to concatenate several\n"
    "  --camera NAME         camera stream (reduced frames of the geometry's size)\n"
    "  --shm-dir DIR         stream folder (default $MILK_SHM_DIR, /milk/shm, /dev/shm, /tmp)\n"
    "  --geom FILE           FITS with the geometry keywords, the frame size and RDNOISE/GAIN\n"
    "                        (e.g. a reduced science cube)\n"
    "  --recon, --actuators, -o, --pupil-out, --checkpoint, --every, --every-seconds,\n"
    "  --threads, --static, --static-out, --pupil, --tiptilt, --read-noise, --gain,\n"
    "  --g-smooth, --max-frames, --valid, --band, --mean-loop DIR   as for 'specklewfs stream'\n"
    "                        (loops speckles or stream made: a live run has no files to\n"
    "                        describe the system from); with a\n"
    "                        space-time --recon (speckles' taught.fits) a batch waits for the\n"
    "                        WFS frames of its largest lag\n"
    "  --batch B             camera frames per batch (default 16; 'stream' with the same B\n"
    "                        gives the same result)\n"
    "  --max-wait T          longest wait [s] of a ready frame for its batch to fill (0.5)\n"
    "  --exptime T           camera exposure [s] (default: the camera's frame period)\n"
    "  --timeout T           longest wait [s] for a missing or vanished stream (10)\n"
    "  --idle-exit T         end when no frame arrived for T seconds (default: never)\n"
    "  --poll T              semaphore wait and stream check period [s] (0.02)\n"
    "  --dm-out NAME         write DM offsets (metres of surface per actuator, to add to the\n"
    "                        DM) to this stream after every update, added to what it holds;\n"
    "                        needs --pupil-out\n"
    "  --dm-file FILE        also the total offsets as OFFSETS.fits ('dmoffsets' layout)\n"
    "  --dm-gain G           fraction of the measured correction applied per update (0.5)\n"
    "  --dm-max-step M       largest change of one actuator per update [m] (default: none)\n"
    "  --dm-max-rms R        largest rms of the total offsets [m] (default: none)\n"
    "  --dm-scale S          stream units per metre (1; 1e6 for micrometres)\n"
    "  --dm-settle T         skip exposures that begin within T s of a DM write (0.1)\n"
    "  --dm-keep             keep accumulating across DM updates (default: start anew)\n"
    "  --dm-final            also correct at the end of the data (default: only at updates)\n"
    "  --dm-tiptilt          correct tip and tilt too (default: piston, tip and tilt are removed\n"
    "                        from the WFE first: registered frames do not see them)\n"
    "  --pupil-source halo_lf|halo   the pupil product from HALO_LF (default, as 'pupil') or\n"
    "                        HALO (better on closed-loop AO telemetry: docs/telemetry.md)\n"
    "  --influence, --coupling, --pitch, --modes, --reg   the fit, as 'specklewfs dmoffsets'\n";

void cli_help_live(void)
{
    fputs(live_usage_text, stdout);
    fputs(CLI_LINEAR_HELP, stdout);
}

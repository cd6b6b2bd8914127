/* The usage texts of stream and live, kept apart from their option parsing. */
#include "cli.h"

#include <stdio.h>

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
    "                        too, given its --teach-work, and as many: --mean-teach-max-loops\n"
    "                        M as speckles'; --teach-again: anew); none: without\n"
    "  --wfs-log DIR|FILE    instead of --timing: a WFS milk log (folder of NAME_hh:mm:ss.s.fits[.fz]\n"
    "                        + .txt, or one file); several are concatenated into one slope vector.\n"
    "                        The science cube's STAMPS (reduce of camera logs) place every exposure\n"
    "                        [stamp - T, stamp] on the WFS frames (docs/telemetry.md)\n"
    "  --clock CLOCK.txt     camera clock offset, drift and pairing from 'sync --wfs-log'\n"
    "  --exptime T           camera exposure [s] (default: STAMPS' EXPTIME, else the frame period)\n"
    CLI_GEOM_HELP
    CLI_BAND_HELP;
static const char *stream_usage_linear_mpi =
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
    fputs(stream_usage_linear_mpi, stdout);
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

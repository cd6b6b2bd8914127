/* specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits:
 * the speckle cube from WFS slopes that matches the reduced science cube frame for frame
 * (Sec. 4.4, eq:downsampledHalo, eq:computedSpeckleField); with --wfs-rate, the same
 * speckles at the WFS rate (one MFT per WFS frame) for `specklewfs coherence`. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits\n"
    "                           [--recon W.fits | --recon vk|map|svd] [--rcond R] [--modes K] [--slope-noise RAD]\n"
    "                           [--vk-l0 M] [--write-recon W.fits] [--tiptilt exposure|frame|keep]\n"
    "                           [--mean ensemble|cube] [--wfs-rate [--wfs-hz HZ]]\n"
    "                           [--match IN.fits OUT.fits]... [--pupil MASK.fits] [--threads N]\n"
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
    "  --recon W.fits      reconstructor (NAXIS1 = slopes, NAXIS2 = actuators) [m/rad]; or built\n"
    "                      here from the Shack-Hartmann interaction matrix D = U S V^T:\n"
    "  --recon vk          (default) MAP, von Karman prior C of the actuators (--vk-l0 M: 10)\n"
    "                      scaled to the slopes: W = C D^T (D C D^T + sigma^2 I)^-1\n"
    "  --recon map         MAP / Wiener reconstructor with the prior learned from the\n"
    "                      slopes of the usable cubes' telemetry files: mode i of D gets the\n"
    "                      gain (1 - sigma^2 / P_i)_+ / s_i, P_i the mean square of the slopes\n"
    "                      on u_i, sigma^2 the slope noise\n"
    "  --recon svd         truncated pseudo-inverse: singular values above\n"
    "                      --rcond (5e-2) x the largest, at most --modes K (0 = no limit)\n"
    "  --slope-noise RAD   effective slope noise rms [rad] for --recon vk|map (default: estimated\n"
    "                      from the slopes outside D's column space: noise + aliasing)\n"
    "  --write-recon FILE  also write the reconstructor in use (e.g. for `specklewfs stream`)\n"
    "  --tiptilt MODE      exposure (default): remove from every WFS frame the weighted mean x/y\n"
    "                      slope of its exposure and keep the motion within it, as registered\n"
    "                      science frames have it (reduce re-centres, it cannot de-blur);\n"
    "                      frame: remove every frame's own mean slopes (the paper's Sec. 4.4;\n"
    "                      fine only when the image moves << lambda/D within an exposure);\n"
    "                      keep: remove nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt      same as --tiptilt keep\n"
    "  --mean MODE         static halo: ensemble (all frames, default) or cube (each cube)\n"
    "  --match IN OUT      write OUT = the frames of IN (a cube aligned with SCIENCE.fits, e.g.\n"
    "                      SCIENCE.fits itself) of the usable cubes, so it matches SPECKLES.fits\n"
    "  --pupil MASK.fits   pupil mask PUPN x PUPN (default: annulus from TELDIAM, OBSCUR)\n"
    "  --threads N         engine workers (default 1)\n"
    "  --wfs-rate          write the speckles at the WFS rate instead, for `specklewfs coherence`:\n"
    "                      one frame per WFS frame covered by the usable cubes (cube after cube,\n"
    "                      each cube's frames contiguous), each propagated alone and core-phase\n"
    "                      referenced, the static halo (--mean) subtracted; tip-tilt removed per\n"
    "                      WFS frame (default; or --tiptilt keep). Header: FRAMEDT = 1/WFSRATE [s],\n"
    "                      FRATIO (camera exposure = FRATIO x FRAMEDT), NSEGS (cubes). --match and\n"
    "                      --tiptilt exposure do not apply\n"
    "  --wfs-hz HZ         WFS frame rate [Hz] when the slopes files have no WFSRATE keyword\n";

/* Options into o; returns -1 after --help, CLI_USAGE on a bad option, 0 otherwise. */
static int parse(int argc, char **argv, swfs_speckles_run_options *o, const char **min, const char **mout)
{
    const char *cmd = "speckles";
    double rcond = o->pipe.rcond, slope_noise = 0;
    long modes = 0, threads = 1;
    int rcond_given = 0, tt_given = 0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        int bad = 0;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return -1; }
        else if (!strcmp(a, "-o") || !strcmp(a, "--science") || !strcmp(a, "--actuators") || !strcmp(a, "--recon") ||
                 !strcmp(a, "--pupil") || !strcmp(a, "--write-recon")) {
            if (!v) return cli_usage_error(cmd, "%s needs a file name", a);
            if (!strcmp(a, "-o")) o->out = v;
            else if (!strcmp(a, "--science")) o->science = v;
            else if (!strcmp(a, "--actuators")) o->actuators = v;
            else if (!strcmp(a, "--recon")) {
                o->recon = NULL;
                if (!strcmp(v, "map")) o->pipe.recon = SWFS_RECON_MAP;
                else if (!strcmp(v, "vk")) o->pipe.recon = SWFS_RECON_VK;
                else if (!strcmp(v, "svd")) o->pipe.recon = SWFS_RECON_SVD;
                else { o->pipe.recon = SWFS_RECON_GIVEN; o->recon = v; }
            } else if (!strcmp(a, "--write-recon")) o->write_recon = v;
            else o->mask = v;
            i++;
        } else if (!strcmp(a, "--rcond")) { bad = cli_parse_double(cmd, a, v, &rcond); rcond_given = 1; i++; }
        else if (!strcmp(a, "--modes")) { bad = cli_parse_long(cmd, a, v, &modes); rcond_given = 1; i++; }
        else if (!strcmp(a, "--vk-l0")) { bad = cli_parse_double(cmd, a, v, &o->pipe.vk_l0); i++; }
        else if (!strcmp(a, "--slope-noise")) { bad = cli_parse_double(cmd, a, v, &slope_noise); i++; }
        else if (!strcmp(a, "--threads")) { bad = cli_parse_long(cmd, a, v, &threads); i++; }
        else if (!strcmp(a, "--wfs-hz")) { bad = cli_parse_double(cmd, a, v, &o->wfs_hz); i++; }
        else if (!strcmp(a, "--wfs-rate")) o->pipe.wfs_rate = 1;
        else if (!strcmp(a, "--keep-tiptilt")) { o->pipe.tiptilt = SWFS_TT_KEEP; tt_given = 1; }
        else if (!strcmp(a, "--tiptilt")) {
            if (cli_parse_tiptilt(cmd, v, &o->pipe.tiptilt)) return CLI_USAGE;
            tt_given = 1;
            i++;
        } else if (!strcmp(a, "--mean")) {
            if (!v || (strcmp(v, "ensemble") && strcmp(v, "cube"))) return cli_usage_error(cmd, "--mean needs ensemble or cube");
            o->mean_mode = strcmp(v, "cube") ? SWFS_MEAN_ENSEMBLE : SWFS_MEAN_CUBE;
            i++;
        } else if (!strcmp(a, "--match")) {
            if (i + 2 >= argc) return cli_usage_error(cmd, "--match needs IN.fits OUT.fits");
            min[o->nmatch] = argv[i + 1];
            mout[o->nmatch++] = argv[i + 2];
            i += 2;
        } else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (!o->timing) o->timing = a;
        else return cli_usage_error(cmd, "unexpected argument '%s'", a);
        if (bad) return CLI_USAGE;
    }
    if (!o->timing || !o->science || !o->actuators || !o->out) return cli_usage_error(cmd, "needs TIMING.txt, --science, --actuators and -o");
    if (!(rcond >= 0 && rcond < 1) || modes < 0 || threads < 1) return cli_usage_error(cmd, "--rcond must be in [0, 1), --modes >= 0, --threads >= 1");
    if (!(slope_noise >= 0) || !isfinite(slope_noise)) return cli_usage_error(cmd, "--slope-noise must be a finite rms >= 0 [rad], got %g", slope_noise);
    if (rcond_given && o->pipe.recon != SWFS_RECON_SVD) return cli_usage_error(cmd, "--rcond and --modes go with --recon svd");
    if (slope_noise > 0 && o->pipe.recon != SWFS_RECON_MAP && o->pipe.recon != SWFS_RECON_VK) return cli_usage_error(cmd, "--slope-noise goes with --recon vk or map");
    if (!(o->pipe.vk_l0 > 0) || !isfinite(o->pipe.vk_l0)) return cli_usage_error(cmd, "--vk-l0 must be an outer scale > 0 [m], got %g", o->pipe.vk_l0);
    if (!(o->wfs_hz >= 0)) return cli_usage_error(cmd, "--wfs-hz must be a rate > 0 [Hz], got %g", o->wfs_hz);
    if (threads > SWFS_ENGINE_MAX_THREADS)
        return cli_usage_error(cmd, "--threads must be 1..%d, got %ld", SWFS_ENGINE_MAX_THREADS, threads);
    if (o->pipe.wfs_rate) {
        /* At the WFS rate there is no exposure to take a mean tip-tilt over: the coherence
         * of the speckles, not of the image motion, is what is measured. */
        if (tt_given && o->pipe.tiptilt == SWFS_TT_EXPOSURE) return cli_usage_error(cmd, "--wfs-rate removes the tip-tilt per WFS frame (or --tiptilt keep); --tiptilt exposure does not apply");
        if (o->nmatch) return cli_usage_error(cmd, "--match pairs camera frames; it does not apply with --wfs-rate");
        if (!tt_given) o->pipe.tiptilt = SWFS_TT_FRAME;
    } else if (o->wfs_hz > 0) return cli_usage_error(cmd, "--wfs-hz goes with --wfs-rate");
    o->pipe.rcond = rcond;
    o->pipe.max_modes = (size_t)modes;
    o->pipe.slope_noise = slope_noise;
    o->pipe.threads = (int)threads;
    return 0;
}

int swfs_cmd_speckles(int argc, char **argv)
{
    const char *cmd = "speckles";
    swfs_speckles_run_options o;
    swfs_speckles_run_options_default(&o);
    const char **min = calloc((size_t)argc, sizeof *min), **mout = calloc((size_t)argc, sizeof *mout);
    if (!min || !mout) { free(min); free(mout); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    int rc = parse(argc, argv, &o, min, mout);
    if (rc) {
        free(min);
        free(mout);
        return rc < 0 ? CLI_OK : rc;
    }
    o.match_in = min;
    o.match_out = mout;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_stage_progress;
    o.progress_ctx = "speckles:";
    swfs_speckles_run_result r;
    rc = swfs_speckles_run(&o, &r) ? cli_error(cmd) : CLI_OK;
    if (!rc && (o.pipe.recon == SWFS_RECON_MAP || o.pipe.recon == SWFS_RECON_VK))
        fprintf(stderr, "speckles: %s reconstructor from %zu WFS frames: slope noise %.3g rad rms (%s), %zu modes, "
                "%.1f effective\n", o.pipe.recon == SWFS_RECON_MAP ? "MAP" : "vk (von Karman prior)", r.info.ntrain,
                sqrt(r.info.noise_var), r.info.noise_given ? "given" : "estimated", r.info.recon_modes, r.info.recon_dof);
    if (!rc)
        fprintf(stderr, "speckles: %zu %sframes from %zu of %zu cubes (%zu reconstructor modes, %zu pupil samples outside "
                "the actuator hull) -> %s\n", r.nout, o.pipe.wfs_rate ? "WFS " : "", r.nok, r.ncubes, r.info.recon_modes,
                r.info.n_outside, o.out);
    free(min);
    free(mout);
    return rc;
}

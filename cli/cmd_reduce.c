/* specklewfs reduce RAW.fits... --dark DARK.fits [--flat FLAT.fits] [--badpix BAD.fits] -o SCIENCE.fits */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs reduce RAW.fits [RAW2.fits ...] -o SCIENCE.fits [--dark DARK.fits] [--flat FLAT.fits]\n"
    "                         [--badpix BAD.fits] [--gauss-sigma PIX] [--no-register] [--bg-radius PIX]\n"
    "\n"
    "Camera frame reduction (Codona & Kenworthy 2013, Sec. 4.3): dark subtraction, flat field,\n"
    "bad pixels (BAD.fits nonzero, hot in the dark, dead in the flat, non-finite) replaced by\n"
    "the median of their 3x3 neighbourhood, the star located by correlation with a Gaussian\n"
    "reference peak and shifted (bilinear) to the fixed centre (W/2, H/2).\n"
    "\n"
    "  RAW.fits ...        raw camera cubes (x, y, frame), all of the same frame size, in time\n"
    "                      order; they are concatenated into SCIENCE.fits. milk log files\n"
    "                      (X.fits or X.fits.fz with its timestamp table X.txt) carry every\n"
    "                      frame's cnt0 and stamp into the extension STAMPS (and EXPTIME), for\n"
    "                      'sync --wfs-log' and 'stream --wfs-log'\n"
    "  -o SCIENCE.fits     reduced cube (primary HDU) with RDNOISE = sqrt(background noise\n"
    "                      variance of the output frames) for estimate (the bilinear shift\n"
    "                      scales the raw variance NOISERAW by NOISEFAC, ~4/9; GAIN becomes\n"
    "                      GAINRAW / NOISEFAC likewise), NCUBES, CUBEnnnn = raw file names,\n"
    "                      EXPTIME (the raw headers' least) and EXPTRES (the resolution its\n"
    "                      header wrote it to) for sync's least frame ratio, and the\n"
    "                      extension TRACK (4 x nframes: peak x, peak y [pixels, before the\n"
    "                      shift], cube index, frame within the cube) that sync uses\n"
    "  --dark, --flat      calibration frames (default: 0 and 1)\n"
    "  --badpix BAD.fits   extra bad-pixel map (nonzero = bad)\n"
    "  --gauss-sigma PIX   reference peak sigma [pixels] (default 1 lambda/D = 1/PIXSCALE from the\n"
    "                      raw header, else 2)\n"
    "  --hot-sigma K       dark outliers beyond K robust sigmas are bad (default 8)\n"
    "  --bg-radius PIX     source-free region: farther than PIX from the centre (default\n"
    "                      0.45 min(W, H))\n"
    "  --noise-region      take the noise variance from that region even when the raw header\n"
    "                      has PIXSCALE; by default (PIXSCALE < 0.45) it comes from the spatial\n"
    "                      frequencies beyond the optical cutoff, where only white noise lives\n"
    "  --no-register       keep the frames where they are (the track is still measured)\n"
    CLI_GEOM_HELP
    "Geometry keywords of the first raw cube are copied, the given ones over them.\n";

/* The positive numbers, checked as they come: --gauss-sigma, --hot-sigma, --bg-radius. */
static int special(void *ctx, int argc, char **argv, int *i)
{
    const char *cmd = "reduce", *a = argv[*i], *v = *i + 1 < argc ? argv[*i + 1] : NULL;
    swfs_reduce_run_options *o = ctx;
    double *dst = !strcmp(a, "--gauss-sigma") ? &o->params.gauss_sigma
                  : !strcmp(a, "--hot-sigma") ? &o->params.hot_sigma
                  : !strcmp(a, "--bg-radius") ? &o->params.bg_radius
                                              : NULL;
    double x;
    if (!dst) return cli_geom_option(cmd, argc, argv, i, &o->geom);
    if (cli_take_double(cmd, argc, argv, i, &x)) return -CLI_USAGE;
    if (!(x > 0)) return -cli_usage_error(cmd, "%s expects a positive number, got %s", a, v);
    *dst = x;
    if (dst == &o->params.gauss_sigma) o->sigma_given = 1;
    return 1;
}

int swfs_cmd_reduce(int argc, char **argv)
{
    const char *cmd = "reduce";
    swfs_reduce_run_options o;
    swfs_reduce_run_options_default(&o);
    const char **raws = calloc((size_t)argc + 1, sizeof *raws);
    if (!raws) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const char *fn = "a file name";
    const cli_opt opts[] = {
        {"-o", CLI_STRING, &o.out, fn, 0},         {"--dark", CLI_STRING, &o.dark, fn, 0},
        {"--flat", CLI_STRING, &o.flat, fn, 0},    {"--badpix", CLI_STRING, &o.badpix, fn, 0},
        {"--no-register", CLI_SET, &o.params.do_register, NULL, 0}, {"--noise-region", CLI_SET, &o.noise_region, NULL, 1},
    };
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, special, &o, raws, &o.nraw};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc < 0) { free(raws); return CLI_OK; }
    if (rc == CLI_OK && !o.nraw) rc = cli_usage_error(cmd, "needs at least one raw camera cube");
    if (rc == CLI_OK && !o.out) rc = cli_usage_error(cmd, "needs -o SCIENCE.fits");
    if (rc != CLI_OK) { free(raws); return rc; }
    o.raw = raws;
    o.prov = cli_provenance(argc, argv, &o.nprov);
    o.progress = cli_stage_progress;
    o.progress_ctx = "reduce:";
    swfs_reduce_run_result r;
    rc = swfs_reduce_run(&o, &r) ? cli_error(cmd) : CLI_OK;
    if (rc == CLI_OK && r.overridden)
        fprintf(stderr, "reduce: note: the given geometry replaced %d keyword(s) of %s's header\n", r.overridden, raws[0]);
    if (rc == CLI_OK && r.missing[0])
        fprintf(stderr, "reduce: note: %s has no %s and none was given; speckles, stream and pupil need them "
                "(--geom FILE, or --wavelen, --teldiam, --obscur, --pixscale, --pupdx, --pupn: here, or to speckles "
                "and stream)\n", raws[0], r.missing);
    if (rc == CLI_OK)
        fprintf(stderr, "reduce: %zu frames from %zu cubes, %zu bad pixels, background noise %.4g counts rms (%.4g after "
                "registration) -> %s\n", r.nframes, o.nraw, r.nbad, sqrt(r.noise_var), sqrt(r.noise_fac * r.noise_var), o.out);
    if (rc == CLI_OK && r.noise_var_measured < 0)
        fprintf(stderr, "reduce: note: the background noise variance came out at %.4g counts^2, below 0: no read noise "
                "above the photon noise the frames' counts predict (GAIN); 0 written (RDNOISE, NOISEVAR)\n",
                r.noise_var_measured);
    if (rc == CLI_OK && r.exptime > 0 && !r.stamped)
        fprintf(stderr, "reduce: EXPTIME %.6g s, the least of the raw headers (EXPTIME, EXPTRES: sync's least frame "
                "ratio)\n", r.exptime);
    if (rc == CLI_OK && r.stamped)
        fprintf(stderr, "reduce: milk time stamps of every frame in STAMPS: %llu camera frames dropped (counter jumps), "
                "EXPTIME %s\n", (unsigned long long)r.dropped, r.exptime > 0 ? "from the raw header" : "absent");
    free(raws);
    return rc;
}

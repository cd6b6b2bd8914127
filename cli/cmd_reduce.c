/* specklewfs reduce RAW.fits... --dark DARK.fits [--flat FLAT.fits] [--badpix BAD.fits] -o SCIENCE.fits */
#include "cli.h"

#include "specklewfs/fits.h"
#include "specklewfs/reduce.h"
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
    "                      order; they are concatenated into SCIENCE.fits\n"
    "  -o SCIENCE.fits     reduced cube (primary HDU) with RDNOISE = sqrt(background noise\n"
    "                      variance of the output frames) for estimate (the bilinear shift\n"
    "                      scales the raw variance NOISERAW by NOISEFAC, ~4/9; GAIN becomes\n"
    "                      GAINRAW / NOISEFAC likewise), NCUBES, CUBEnnnn = raw file names, and the\n"
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
    "Geometry keywords of the first raw cube are copied.\n";

static int read_map(const char *cmd, const char *path, size_t nx, size_t ny, double **out)
{
    swfs_real *a = NULL;
    if (swfs_fits_read_real(path, NULL, &a, NULL)) return cli_error(cmd);
    if (a->nx != nx || a->ny != ny || a->nz != 1) {
        fprintf(stderr, "specklewfs %s: %s: calibration frame is %zux%zux%zu but the camera frames are %zux%zu\n", cmd,
                path, a->nx, a->ny, a->nz, nx, ny);
        swfs_real_free(a);
        return CLI_FAIL;
    }
    *out = a->data;
    a->data = NULL;
    swfs_real_free(a);
    return CLI_OK;
}

static const char *base_name(const char *p)
{
    const char *s = strrchr(p, '/');
    return s ? s + 1 : p;
}

int swfs_cmd_reduce(int argc, char **argv)
{
    const char *cmd = "reduce";
    const char *out = NULL, *darkf = NULL, *flatf = NULL, *badf = NULL;
    const char **raws = calloc((size_t)argc + 1, sizeof *raws);
    size_t nraw = 0;
    swfs_reduce_params p;
    swfs_reduce_params_default(&p);
    int bg_region = 0, sigma_set = 0;
    if (!raws) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char *v = i + 1 < argc ? argv[i + 1] : NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); free(raws); return CLI_OK; }
        else if (!strcmp(a, "-o") || !strcmp(a, "--dark") || !strcmp(a, "--flat") || !strcmp(a, "--badpix")) {
            if (!v) { free(raws); return cli_usage_error(cmd, "%s needs a file name", a); }
            if (!strcmp(a, "-o")) out = v;
            else if (!strcmp(a, "--dark")) darkf = v;
            else if (!strcmp(a, "--flat")) flatf = v;
            else badf = v;
            i++;
        } else if (!strcmp(a, "--gauss-sigma") || !strcmp(a, "--hot-sigma") || !strcmp(a, "--bg-radius")) {
            double x;
            if (cli_parse_double(cmd, a, v, &x)) { free(raws); return CLI_USAGE; }
            if (!(x > 0)) { free(raws); return cli_usage_error(cmd, "%s expects a positive number, got %s", a, v); }
            if (!strcmp(a, "--gauss-sigma")) { p.gauss_sigma = x; sigma_set = 1; }
            else if (!strcmp(a, "--hot-sigma")) p.hot_sigma = x;
            else p.bg_radius = x;
            i++;
        }
        else if (!strcmp(a, "--no-register")) p.do_register = 0;
        else if (!strcmp(a, "--noise-region")) bg_region = 1;
        else if (a[0] == '-' && a[1]) { free(raws); return cli_usage_error(cmd, "unknown option '%s'", a); }
        else raws[nraw++] = a;
    }
    if (!nraw) { free(raws); return cli_usage_error(cmd, "needs at least one raw camera cube"); }
    if (!out) { free(raws); return cli_usage_error(cmd, "needs -o SCIENCE.fits"); }

    int rc = CLI_FAIL;
    swfs_fits_in **in = calloc(nraw, sizeof *in);
    double *dark = NULL, *flat = NULL, *bad = NULL, *buf = NULL, *track = NULL;
    swfs_reduce *red = NULL;
    swfs_fits_out *o = NULL;
    if (!in) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    size_t nx = 0, ny = 0, ntot = 0;
    for (size_t c = 0; c < nraw; c++) {
        if (swfs_fits_in_open(&in[c], raws[c], NULL)) { cli_error(cmd); goto done; }
        const swfs_fits_shape *s = swfs_fits_in_shape(in[c]);
        if (s->is_complex) {
            fprintf(stderr, "specklewfs %s: %s: camera cube is complex; expected real counts (x, y, frame)\n", cmd, raws[c]);
            goto done;
        }
        if (c == 0) { nx = s->nx; ny = s->ny; }
        else if (s->nx != nx || s->ny != ny) {
            fprintf(stderr, "specklewfs %s: %s: frames are %zux%zu but %s has %zux%zu (all cubes must have the same "
                    "frame size)\n", cmd, raws[c], s->nx, s->ny, raws[0], nx, ny);
            goto done;
        }
        ntot += s->nz;
    }
    if (darkf && read_map(cmd, darkf, nx, ny, &dark)) goto done;
    if (flatf && read_map(cmd, flatf, nx, ny, &flat)) goto done;
    if (badf && read_map(cmd, badf, nx, ny, &bad)) goto done;
    swfs_geom geom;
    double gainv = NAN;
    {
        int found = 0;
        if (swfs_fits_in_geom(in[0], &geom)) { cli_error(cmd); goto done; }
        /* The out-of-band noise estimate needs the sampling (PIXSCALE). */
        if (!bg_region && isfinite(geom.pixscale) && geom.pixscale > 0 && geom.pixscale < 0.45) p.pixscale = geom.pixscale;
        /* The reference peak: 1 lambda/D (sigma) when the sampling is known. Narrower
         * references follow the speckled core's fine structure and bias the per-frame
         * centre (measured: 2 px at 0.25 lambda/D triples the NCP error). */
        if (!sigma_set && isfinite(geom.pixscale) && geom.pixscale > 0) p.gauss_sigma = 1.0 / geom.pixscale;
        if (swfs_fits_in_key_double_opt(in[0], "GAIN", &gainv, &found)) { cli_error(cmd); goto done; }
        if (!found) gainv = NAN;
        /* Photon noise is modelled per pixel by estimate (Phi_I / GAIN): measure the rest. */
        if (isfinite(gainv) && gainv > 0) p.gain = gainv;
    }
    if (swfs_reduce_create(&red, nx, ny, dark, flat, bad, &p)) { cli_error(cmd); goto done; }
    size_t np = nx * ny;
    buf = malloc(np * sizeof *buf);
    track = malloc(4 * ntot * sizeof *track);
    if (!buf || !track) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    if (swfs_fits_out_create(&o, out) || swfs_fits_out_begin(o, NULL, nx, ny, ntot, 0, -32)) { cli_error(cmd); goto done; }
    size_t k = 0;
    for (size_t c = 0; c < nraw; c++) {
        size_t nz = swfs_fits_in_shape(in[c])->nz;
        for (size_t f = 0; f < nz; f++, k++) {
            double px, py;
            if (swfs_fits_in_read_real(in[c], f, 1, buf)) { cli_error(cmd); goto done; }
            if (swfs_reduce_frame(red, buf, buf, &px, &py)) {
                fprintf(stderr, "specklewfs %s: %s frame %zu: %s\n", cmd, raws[c], f, swfs_last_error());
                goto done;
            }
            if (swfs_fits_out_real_frames(o, k, 1, buf)) { cli_error(cmd); goto done; }
            track[4 * k] = px; track[4 * k + 1] = py; track[4 * k + 2] = (double)c; track[4 * k + 3] = (double)f;
        }
        cli_progress("reduce: cubes", c + 1, nraw);
    }
    double nv = swfs_reduce_noise_var(red);
    char cl[2048];
    cli_command_line(argc, argv, cl, sizeof cl);
    const char *prov[] = {cl};
    if (swfs_fits_out_geom(o, &geom) || swfs_fits_out_provenance(o, prov, 1)) { cli_error(cmd); goto done; }
    /* The bilinear registration averages neighbouring pixels: the registered frames carry
     * NOISEFAC times the raw per-pixel noise variance (read and photon alike), which is
     * what estimate must remove (the raw variance over-subtracts: docs/telemetry.md). */
    const double q = swfs_reduce_noise_factor(red);
    if (isfinite(nv) && (swfs_fits_out_key_double(o, "NOISEVAR", q * nv, "noise variance of the output frames [counts^2]") ||
                         swfs_fits_out_key_double(o, "RDNOISE", sqrt(q * nv), "sqrt(NOISEVAR) [counts], for estimate") ||
                         swfs_fits_out_key_double(o, "NOISERAW", nv, "noise variance before registration [counts^2]"))) {
        cli_error(cmd);
        goto done;
    }
    if (swfs_fits_out_key_double(o, "NOISEFAC", q, "variance factor of the registration's interpolation")) { cli_error(cmd); goto done; }
    if (isfinite(gainv) && (swfs_fits_out_key_double(o, "GAIN", gainv / q, "[e-/count] raw GAIN / NOISEFAC: photon noise") ||
                            swfs_fits_out_key_double(o, "GAINRAW", gainv, "[e-/count] from the raw cube"))) {
        cli_error(cmd);
        goto done;
    }
    if (swfs_fits_out_key_long(o, "NCUBES", (long)nraw, "raw cubes concatenated") ||
        swfs_fits_out_key_long(o, "NBADPIX", (long)swfs_reduce_nbad(red), "pixels replaced by the 3x3 median") ||
        swfs_fits_out_key_long(o, "REGISTER", p.do_register, "1: peak shifted to (W/2, H/2)")) {
        cli_error(cmd);
        goto done;
    }
    for (size_t c = 0; c < nraw; c++) {
        char key[32];
        snprintf(key, sizeof key, "CUBE%04u", (unsigned)(c % 10000));
        if (swfs_fits_out_key_string(o, key, base_name(raws[c]), "raw cube file")) { cli_error(cmd); goto done; }
    }
    swfs_real tr = {4, ntot, 1, track};
    if (swfs_fits_out_real(o, "TRACK", &tr, -64) ||
        swfs_fits_out_key_string(o, "COLUMNS", "peak_x peak_y cube frame", "pixels before the shift")) {
        cli_error(cmd);
        goto done;
    }
    int crc = swfs_fits_out_commit(o);
    o = NULL;
    if (crc) { cli_error(cmd); goto done; }
    fprintf(stderr, "reduce: %zu frames from %zu cubes, %zu bad pixels, background noise %.4g counts rms (%.4g after "
            "registration) -> %s\n", ntot, nraw, swfs_reduce_nbad(red), sqrt(nv), sqrt(q * nv), out);
    rc = CLI_OK;
done:
    swfs_fits_out_abort(o);
    if (in)
        for (size_t c = 0; c < nraw; c++) swfs_fits_in_close(in[c]);
    free(in); free(raws); free(dark); free(flat); free(bad); free(buf); free(track);
    swfs_reduce_free(red);
    return rc;
}

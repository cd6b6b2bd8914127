/* specklewfs speckles TIMING.txt --science SCIENCE.fits --actuators ACT.fits -o SPECKLES.fits:
 * the speckle cube from WFS slopes that matches the reduced science cube frame for frame
 * (Sec. 4.4, eq:downsampledHalo, eq:computedSpeckleField); with --wfs-rate, the same
 * speckles at the WFS rate (one MFT per WFS frame) for `specklewfs coherence`. */
#include "cli.h"

#include "specklewfs/aperture.h"
#include "specklewfs/engine.h"
#include "specklewfs/fits.h"
#include "specklewfs/speckles.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/wfs.h"

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

typedef struct match_pair { const char *in, *out; } match_pair;

/* WFSRATE [Hz] of a telemetry file (*rate = 0 if the keyword is absent). */
static int slopes_rate(const char *path, double *rate)
{
    swfs_fits_in *f = NULL;
    int found = 0, rc = swfs_fits_in_open(&f, path, NULL);
    *rate = 0;
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "WFSRATE", rate, &found);
    swfs_fits_in_close(f);
    if (!rc && (!found || !(*rate > 0) || !isfinite(*rate))) *rate = 0;
    return rc;
}

static void slopes_path(const char *tdir, const char *name, char *path, size_t cap)
{
    if (name[0] == '/') snprintf(path, cap, "%s", name);
    else snprintf(path, cap, "%s/%s", tdir, name);
}

enum { RECON_MAP = 0, RECON_SVD = 1, RECON_FILE = 2, RECON_VK = 3 };

/* The training set of --recon map: every telemetry file the usable cubes use, in the
 * order they first appear, concatenated (nslopes per frame). */
static int load_training(const char *cmd, const char *tdir, const swfs_timing *t, size_t nslopes, double **out,
                         size_t *nframes)
{
    char path[8192];
    double *buf = NULL;
    size_t n = 0;
    *out = NULL;
    *nframes = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        if (t->cubes[c].status != SWFS_CUBE_OK) continue;
        int seen = 0;
        for (size_t d = 0; d < c && !seen; d++)
            seen = t->cubes[d].status == SWFS_CUBE_OK && !strcmp(t->cubes[d].slopes, t->cubes[c].slopes);
        if (seen) continue;
        slopes_path(tdir, t->cubes[c].slopes, path, sizeof path);
        swfs_real *s = NULL;
        if (swfs_fits_read_real(path, NULL, &s, NULL)) { free(buf); return cli_error(cmd); }
        if (s->nz != 1 || s->nx != nslopes) {
            fprintf(stderr, "specklewfs %s: %s: %zu slopes per frame, expected %zu\n", cmd, path, s->nx, nslopes);
            swfs_real_free(s);
            free(buf);
            return CLI_FAIL;
        }
        double *tmp = realloc(buf, (n + s->ny) * nslopes * sizeof *tmp);
        if (!tmp) { swfs_real_free(s); free(buf); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
        buf = tmp;
        memcpy(buf + n * nslopes, s->data, s->ny * nslopes * sizeof *buf);
        n += s->ny;
        swfs_real_free(s);
    }
    *out = buf;
    *nframes = n;
    return CLI_OK;
}

/* Copy the frames of the usable cubes of IN to OUT, with its keywords that matter. */
static int write_match(const char *cmd, const char *in, const char *out, const swfs_timing *t, size_t nsci,
                       const swfs_geom *g, const char *const *prov, size_t nprov)
{
    swfs_fits_in *f = NULL;
    swfs_fits_out *o = NULL;
    double *buf = NULL;
    int rc = CLI_FAIL;
    if (swfs_fits_in_open(&f, in, NULL)) return cli_error(cmd);
    const swfs_fits_shape *s = swfs_fits_in_shape(f);
    if (s->nz != nsci) {
        fprintf(stderr, "specklewfs %s: %s: %zu frames but the science cube has %zu; --match needs a cube aligned "
                "with it\n", cmd, in, s->nz, nsci);
        goto done;
    }
    size_t nout = 0, np = s->nx * s->ny;
    for (size_t c = 0; c < t->ncubes; c++)
        if (t->cubes[c].status == SWFS_CUBE_OK) nout += t->cubes[c].nframes;
    buf = malloc(np * (s->is_complex ? 2 : 1) * sizeof *buf);
    if (!buf) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    if (swfs_fits_out_create(&o, out) || swfs_fits_out_set_stamp(o, g, prov, nprov) ||
        swfs_fits_out_begin(o, NULL, s->nx, s->ny, nout, s->is_complex, -32)) {
        cli_error(cmd);
        goto done;
    }
    const char *keys[] = {"RDNOISE", "GAIN", "NOISEVAR"};
    for (size_t k = 0; k < 3; k++) {
        double v;
        int found = 0;
        if (swfs_fits_in_key_double_opt(f, keys[k], &v, &found)) { cli_error(cmd); goto done; }
        if (found && swfs_fits_out_key_double(o, keys[k], v, "copied from the input")) { cli_error(cmd); goto done; }
    }
    size_t k = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        if (t->cubes[c].status != SWFS_CUBE_OK) continue;
        for (size_t j = 0; j < t->cubes[c].nframes; j++, k++) {
            size_t src = t->cubes[c].first + j;
            int r1 = s->is_complex ? swfs_fits_in_read_cplx(f, src, 1, (double complex *)buf) : swfs_fits_in_read_real(f, src, 1, buf);
            int r2 = r1 ? r1
                        : (s->is_complex ? swfs_fits_out_cplx_frames(o, k, 1, (double complex *)buf)
                                         : swfs_fits_out_real_frames(o, k, 1, buf));
            if (r2) { cli_error(cmd); goto done; }
        }
    }
    int crc = swfs_fits_out_commit(o);
    o = NULL;
    if (crc) { cli_error(cmd); goto done; }
    rc = CLI_OK;
done:
    swfs_fits_out_abort(o);
    swfs_fits_in_close(f);
    free(buf);
    return rc;
}

int swfs_cmd_speckles(int argc, char **argv)
{
    const char *cmd = "speckles";
    const char *timing = NULL, *sci = NULL, *actf = NULL, *out = NULL, *reconf = NULL, *pupf = NULL, *wrecon = NULL;
    double rcond = 5e-2, wfs_hz = 0; /* 1e-2 amplified the WFS noise (docs/telemetry.md) */
    double slope_noise = 0, vk_l0 = 10; /* an effective outer scale of the AO residual (docs/telemetry.md) */
    int recon_kind = RECON_VK, rcond_given = 0; /* vk: better than svd in 4 of 4 cases (docs/telemetry.md) */
    long modes = 0, threads = 1;
    int tt_mode = SWFS_TT_EXPOSURE, mean_mode = SWFS_MEAN_ENSEMBLE, wfs_mode = 0, tt_given = 0;
    match_pair *match = calloc((size_t)argc, sizeof *match);
    size_t nmatch = 0;
    if (!match) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        int bad = 0;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); free(match); return CLI_OK; }
        else if (!strcmp(a, "-o") || !strcmp(a, "--science") || !strcmp(a, "--actuators") || !strcmp(a, "--recon") ||
                 !strcmp(a, "--pupil") || !strcmp(a, "--write-recon")) {
            if (!v) { free(match); return cli_usage_error(cmd, "%s needs a file name", a); }
            if (!strcmp(a, "-o")) out = v;
            else if (!strcmp(a, "--science")) sci = v;
            else if (!strcmp(a, "--actuators")) actf = v;
            else if (!strcmp(a, "--recon")) {
                if (!strcmp(v, "map")) { recon_kind = RECON_MAP; reconf = NULL; }
                else if (!strcmp(v, "vk")) { recon_kind = RECON_VK; reconf = NULL; }
                else if (!strcmp(v, "svd")) { recon_kind = RECON_SVD; reconf = NULL; }
                else { recon_kind = RECON_FILE; reconf = v; }
            } else if (!strcmp(a, "--write-recon")) wrecon = v;
            else pupf = v;
            i++;
        } else if (!strcmp(a, "--rcond")) { bad = cli_parse_double(cmd, a, v, &rcond); rcond_given = 1; i++; }
        else if (!strcmp(a, "--modes")) { bad = cli_parse_long(cmd, a, v, &modes); rcond_given = 1; i++; }
        else if (!strcmp(a, "--vk-l0")) { bad = cli_parse_double(cmd, a, v, &vk_l0); i++; }
        else if (!strcmp(a, "--slope-noise")) { bad = cli_parse_double(cmd, a, v, &slope_noise); i++; }
        else if (!strcmp(a, "--threads")) { bad = cli_parse_long(cmd, a, v, &threads); i++; }
        else if (!strcmp(a, "--wfs-hz")) { bad = cli_parse_double(cmd, a, v, &wfs_hz); i++; }
        else if (!strcmp(a, "--wfs-rate")) wfs_mode = 1;
        else if (!strcmp(a, "--keep-tiptilt")) { tt_mode = SWFS_TT_KEEP; tt_given = 1; }
        else if (!strcmp(a, "--tiptilt")) {
            if (!v || (strcmp(v, "exposure") && strcmp(v, "frame") && strcmp(v, "keep"))) {
                free(match);
                return cli_usage_error(cmd, "--tiptilt needs exposure, frame or keep");
            }
            tt_mode = !strcmp(v, "exposure") ? SWFS_TT_EXPOSURE : (!strcmp(v, "frame") ? SWFS_TT_FRAME : SWFS_TT_KEEP);
            tt_given = 1;
            i++;
        }
        else if (!strcmp(a, "--mean")) {
            if (!v || (strcmp(v, "ensemble") && strcmp(v, "cube"))) { free(match); return cli_usage_error(cmd, "--mean needs ensemble or cube"); }
            mean_mode = strcmp(v, "cube") ? SWFS_MEAN_ENSEMBLE : SWFS_MEAN_CUBE;
            i++;
        } else if (!strcmp(a, "--match")) {
            if (i + 2 >= argc) { free(match); return cli_usage_error(cmd, "--match needs IN.fits OUT.fits"); }
            match[nmatch].in = argv[i + 1];
            match[nmatch].out = argv[i + 2];
            nmatch++;
            i += 2;
        } else if (a[0] == '-' && a[1]) { free(match); return cli_usage_error(cmd, "unknown option '%s'", a); }
        else if (!timing) timing = a;
        else { free(match); return cli_usage_error(cmd, "unexpected argument '%s'", a); }
        if (bad) { free(match); return CLI_USAGE; }
    }
    if (!timing || !sci || !actf || !out) { free(match); return cli_usage_error(cmd, "needs TIMING.txt, --science, --actuators and -o"); }
    if (!(rcond >= 0 && rcond < 1) || modes < 0 || threads < 1) { free(match); return cli_usage_error(cmd, "--rcond must be in [0, 1), --modes >= 0, --threads >= 1"); }
    if (!(slope_noise >= 0) || !isfinite(slope_noise)) { free(match); return cli_usage_error(cmd, "--slope-noise must be a finite rms >= 0 [rad], got %g", slope_noise); }
    if (rcond_given && recon_kind != RECON_SVD) { free(match); return cli_usage_error(cmd, "--rcond and --modes go with --recon svd"); }
    if (slope_noise > 0 && recon_kind != RECON_MAP && recon_kind != RECON_VK) { free(match); return cli_usage_error(cmd, "--slope-noise goes with --recon vk or map"); }
    if (!(vk_l0 > 0) || !isfinite(vk_l0)) { free(match); return cli_usage_error(cmd, "--vk-l0 must be an outer scale > 0 [m], got %g", vk_l0); }
    if (!(wfs_hz >= 0)) { free(match); return cli_usage_error(cmd, "--wfs-hz must be a rate > 0 [Hz], got %g", wfs_hz); }
    if (wfs_mode) {
        /* At the WFS rate there is no exposure to take a mean tip-tilt over: the coherence
         * of the speckles, not of the image motion, is what is measured. */
        if (tt_given && tt_mode == SWFS_TT_EXPOSURE) { free(match); return cli_usage_error(cmd, "--wfs-rate removes the tip-tilt per WFS frame (or --tiptilt keep); --tiptilt exposure does not apply"); }
        if (nmatch) { free(match); return cli_usage_error(cmd, "--match pairs camera frames; it does not apply with --wfs-rate"); }
        if (!tt_given) tt_mode = SWFS_TT_FRAME;
    } else if (wfs_hz > 0) { free(match); return cli_usage_error(cmd, "--wfs-hz goes with --wfs-rate"); }

    int rc = CLI_FAIL;
    swfs_timing *t = NULL;
    swfs_fits_in *fs = NULL;
    double *xy = NULL, *mask = NULL;
    swfs_recon *rin = NULL;
    swfs_speckle_model *m = NULL;
    swfs_engine *eng = NULL;
    swfs_cplx *halo = NULL;
    swfs_real *slopes = NULL;
    swfs_exposure *sched = NULL, *sched_x = NULL;
    double *W_ext = NULL, *Rtilt = NULL, *xslopes = NULL;
    size_t *cfirst = NULL, *cn = NULL;
    char cur_slopes[SWFS_SYNC_NAME] = "";

    if (swfs_timing_read(timing, &t)) { cli_error(cmd); goto done; }
    if (swfs_fits_in_open(&fs, sci, NULL)) { cli_error(cmd); goto done; }
    const swfs_fits_shape *ss = swfs_fits_in_shape(fs);
    swfs_geom g;
    if (swfs_fits_in_geom(fs, &g) || swfs_geom_require(&g, sci)) { cli_error(cmd); goto done; }
    const size_t nfx = ss->nx, nfy = ss->ny, npup = (size_t)g.pupn, nsci = ss->nz;
    size_t nact = 0;
    if (swfs_actuators_read(actf, &xy, &nact)) { cli_error(cmd); goto done; }
    mask = malloc(npup * npup * sizeof *mask);
    if (!mask) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    if (pupf) {
        swfs_real *pm = NULL;
        if (swfs_fits_read_real(pupf, NULL, &pm, NULL)) { cli_error(cmd); goto done; }
        if (pm->nx != npup || pm->ny != npup || pm->nz != 1) {
            fprintf(stderr, "specklewfs %s: %s: pupil mask is %zux%zu but PUPN = %zu\n", cmd, pupf, pm->nx, pm->ny, npup);
            swfs_real_free(pm);
            goto done;
        }
        memcpy(mask, pm->data, npup * npup * sizeof *mask);
        swfs_real_free(pm);
    } else if (swfs_aperture_make(mask, npup, g.pupdx, g.teldiam, g.obscur, 0, 0)) { cli_error(cmd); goto done; }

    /* Usable cubes and their place in the output: their camera frames, or with --wfs-rate
     * the WFS frames their exposures cover (floor(START) .. end of the last exposure). */
    size_t nout = 0, nok = 0, maxn = 0;
    cfirst = calloc(t->ncubes, sizeof *cfirst);
    cn = calloc(t->ncubes, sizeof *cn);
    if (!cfirst || !cn) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->first + tc->nframes > nsci) {
            fprintf(stderr, "specklewfs %s: %s: cube %zu (frames %zu..%zu) is beyond the %zu frames of %s\n", cmd, timing,
                    c, tc->first, tc->first + tc->nframes, nsci, sci);
            goto done;
        }
        if (tc->status == SWFS_CUBE_OK && tc->nframes > maxn) maxn = tc->nframes;
    }
    if (!maxn) { fprintf(stderr, "specklewfs %s: %s: no usable cube (all straddle telemetry files)\n", cmd, timing); goto done; }
    sched = malloc(maxn * sizeof *sched);
    sched_x = malloc(maxn * sizeof *sched_x);
    if (!sched || !sched_x) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        size_t need = tc->start >= 0 ? swfs_engine_schedule(t->ratio, tc->start - floor(tc->start), tc->nframes, sched) : 0;
        if (!need) {
            fprintf(stderr, "specklewfs %s: %s: cube %zu starts at WFS frame %g with ratio %g; expected a start >= 0 and a "
                    "ratio >= 1\n", cmd, timing, c, tc->start, t->ratio);
            goto done;
        }
        cfirst[nok] = nout;
        cn[nok] = wfs_mode ? need : tc->nframes;
        nout += cn[nok];
        nok++;
    }

    /* The slopes length fixes the Shack-Hartmann geometry: 2 nsub^2. Peek at the first file. */
    char tdir[4096], path[8192];
    cli_dir_of(timing, tdir, sizeof tdir);
    size_t nslopes = 0;
    {
        swfs_fits_in *f = NULL;
        for (size_t c = 0; c < t->ncubes; c++)
            if (t->cubes[c].status == SWFS_CUBE_OK) { slopes_path(tdir, t->cubes[c].slopes, path, sizeof path); break; }
        if (swfs_fits_in_open(&f, path, NULL)) { cli_error(cmd); goto done; }
        nslopes = swfs_fits_in_shape(f)->nx;
        swfs_fits_in_close(f);
        if (wfs_mode) {
            double r;
            if (slopes_rate(path, &r)) { cli_error(cmd); goto done; }
            if (wfs_hz == 0) wfs_hz = r;
            if (!(wfs_hz > 0)) {
                fprintf(stderr, "specklewfs %s: %s: no WFSRATE keyword; --wfs-rate needs the WFS frame rate: give --wfs-hz HZ\n",
                        cmd, path);
                goto done;
            }
        }
    }
    size_t nsub = (size_t)llround(sqrt((double)nslopes / 2));
    if (reconf) {
        if (swfs_recon_read(reconf, &rin)) { cli_error(cmd); goto done; }
        if (rin->nslopes != nslopes) {
            fprintf(stderr, "specklewfs %s: %s: %zu slopes per frame but the reconstructor %s expects %zu\n", cmd, path,
                    nslopes, reconf, rin->nslopes);
            goto done;
        }
    }
    if (2 * nsub * nsub != nslopes) {
        fprintf(stderr, "specklewfs %s: %s: %zu slopes per frame is not 2 nsub^2 (x then y slopes of a square "
                "Shack-Hartmann)\n", cmd, path, nslopes);
        goto done;
    }
    /* --tiptilt frame projects the mean slopes out of W; exposure needs W whole (its tilt
     * is taken out as the Z-tilt by swfs_speckles_recon_tilt); keep uses it as it is. */
    if (swfs_speckle_model_create(&m, xy, nact, mask, npup, g.pupdx, g.teldiam, nsub, rin, rcond, (size_t)modes,
                                  tt_mode == SWFS_TT_FRAME)) {
        cli_error(cmd);
        goto done;
    }
    if (recon_kind == RECON_MAP || recon_kind == RECON_VK) {
        double *train = NULL;
        size_t ntrain = 0;
        if (load_training(cmd, tdir, t, nslopes, &train, &ntrain)) goto done;
        int mrc = recon_kind == RECON_MAP
                      ? swfs_speckle_model_set_map(m, train, ntrain, slope_noise * slope_noise, tt_mode == SWFS_TT_FRAME)
                      : swfs_speckle_model_set_vk(m, xy, vk_l0, train, ntrain, slope_noise * slope_noise,
                                                  tt_mode == SWFS_TT_FRAME);
        free(train);
        if (mrc) { cli_error(cmd); goto done; }
        fprintf(stderr, "speckles: %s reconstructor from %zu WFS frames: slope noise %.3g rad rms (%s), %zu modes, "
                "%.1f effective\n", recon_kind == RECON_MAP ? "MAP" : "vk (von Karman prior)", ntrain, sqrt(m->recon->noise_var), slope_noise > 0 ? "given" : "estimated",
                m->recon->nmodes, m->recon->dof);
    }
    if (wrecon && swfs_recon_write(m->recon, wrecon)) { cli_error(cmd); goto done; }
    /* SWFS_TT_EXPOSURE: two extra columns carry each frame's tip-tilt minus its exposure's
     * mean as exact tilts (speckles.h). */
    const int xt = tt_mode == SWFS_TT_EXPOSURE;
    if (xt && swfs_speckles_recon_tilt(m, xy, &W_ext, &Rtilt)) { cli_error(cmd); goto done; }
    swfs_engine_config ec = {nslopes + (xt ? 2 : 0), nact, npup, nfx, nfy, g.pixscale * g.pupdx / g.teldiam, g.wavelen,
                             xt ? W_ext : m->recon->W, m->T, mask, 0, (int)threads};
    eng = swfs_engine_create(&ec);
    if (!eng) { cli_error(cmd); goto done; }
    halo = swfs_cplx_alloc(nfx, nfy, nout);
    if (!halo) {
        fprintf(stderr, "specklewfs %s: out of memory for %zu frames of %zux%zu\n", cmd, nout, nfx, nfy);
        goto done;
    }

    size_t ok_i = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        const swfs_timing_cube *tc = t->cubes + c;
        if (tc->status != SWFS_CUBE_OK) continue;
        slopes_path(tdir, tc->slopes, path, sizeof path);
        if (strcmp(cur_slopes, tc->slopes)) {
            swfs_real_free(slopes);
            slopes = NULL;
            cur_slopes[0] = 0;
            if (swfs_fits_read_real(path, NULL, &slopes, NULL)) { cli_error(cmd); goto done; }
            if (slopes->nz != 1 || slopes->nx != nslopes) {
                fprintf(stderr, "specklewfs %s: %s: %zu slopes per frame but the reconstructor expects %zu\n", cmd, path,
                        slopes->nx, nslopes);
                goto done;
            }
            snprintf(cur_slopes, sizeof cur_slopes, "%s", tc->slopes);
            double r;
            if (wfs_mode && slopes_rate(path, &r)) { cli_error(cmd); goto done; }
            if (wfs_mode && r > 0 && fabs(r - wfs_hz) > 1e-9 * wfs_hz) {
                fprintf(stderr, "specklewfs %s: %s: WFSRATE %g Hz but the WFS rate in use is %g Hz; one rate per run\n",
                        cmd, path, r, wfs_hz);
                goto done;
            }
        }
        double k0 = floor(tc->start);
        size_t need = swfs_engine_schedule(t->ratio, tc->start - k0, tc->nframes, sched);
        if (!(tc->start >= 0) || need == 0 || (size_t)k0 + need > slopes->ny) {
            fprintf(stderr, "specklewfs %s: %s: cube %zu needs WFS frames %.2f..%.2f but %s has %zu\n", cmd, timing, c,
                    tc->start, tc->start + (double)tc->nframes * t->ratio, path, slopes->ny);
            goto done;
        }
        const double *sp = slopes->data + (size_t)k0 * nslopes;
        size_t nsp = need;
        const swfs_exposure *sc = sched;
        if (wfs_mode) {
            /* One MFT per WFS frame: the speckles at the WFS rate. */
            if (swfs_engine_process_wfs(eng, sp, need, swfs_cplx_frame(halo, cfirst[ok_i]))) {
                swfs_fail_context(SWFS_ERR_VALUE, "%s cube %zu", path, c);
                cli_error(cmd);
                goto done;
            }
            ok_i++;
            cli_progress("speckles: cubes", ok_i, nok);
            continue;
        }
        if (xt) {
            size_t nx = swfs_speckles_expand_frames(sched, tc->nframes);
            double *tmp = realloc(xslopes, nx * (nslopes + 2) * sizeof *tmp);
            if (!tmp) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
            xslopes = tmp;
            if (swfs_speckles_expand(sp, nslopes, need, Rtilt, sched, tc->nframes, xslopes, sched_x)) {
                swfs_fail_context(SWFS_ERR_VALUE, "%s cube %zu", path, c);
                cli_error(cmd);
                goto done;
            }
            sp = xslopes;
            nsp = nx;
            sc = sched_x;
        }
        if (swfs_engine_process(eng, sp, nsp, sc, tc->nframes, swfs_cplx_frame(halo, cfirst[ok_i]))) {
            swfs_fail_context(SWFS_ERR_VALUE, "%s cube %zu", path, c);
            cli_error(cmd);
            goto done;
        }
        ok_i++;
        cli_progress("speckles: cubes", ok_i, nok);
    }
    if (swfs_speckles_subtract_static(halo, cfirst, cn, nok, mean_mode)) { cli_error(cmd); goto done; }

    char cl[2048], info[512];
    cli_command_line(argc, argv, cl, sizeof cl);
    snprintf(info, sizeof info, "speckles%s: ratio %.6f, lag %.4f, %zu actuators, %zu slopes, %zu reconstructor modes, "
             "tip-tilt %s, static halo %s", wfs_mode ? " at the WFS rate" : "", t->ratio, t->lag, nact, nslopes, m->recon->nmodes,
             tt_mode == SWFS_TT_KEEP ? "kept" : (xt ? "exposure mean removed" : "removed per WFS frame"), mean_mode == SWFS_MEAN_CUBE ? "per cube" : "ensemble");
    const char *prov[] = {cl, info};
    {
        swfs_fits_out *o = NULL;
        if (swfs_fits_out_create(&o, out)) { cli_error(cmd); goto done; }
        if (swfs_fits_out_set_stamp(o, &g, prov, 2) || swfs_fits_out_cplx(o, NULL, halo, -32) ||
            swfs_fits_out_key_double(o, "FRATIO", t->ratio, "<t_sci/t_wfs> from sync") ||
            swfs_fits_out_key_double(o, "HSLAG", t->lag, "handshake lag [WFS frames] from sync") ||
            (wfs_mode && (swfs_fits_out_key_double(o, "FRAMEDT", 1 / wfs_hz, "[s] between frames (WFS rate)") ||
                          swfs_fits_out_key_double(o, "WFSRATE", wfs_hz, "[Hz]") ||
                          swfs_fits_out_key_long(o, "NSEGS", (long)nok, "contiguous segments (usable cubes)")))) {
            swfs_fits_out_abort(o);
            cli_error(cmd);
            goto done;
        }
        if (swfs_fits_out_commit(o)) { cli_error(cmd); goto done; }
    }
    for (size_t k = 0; k < nmatch; k++)
        if (write_match(cmd, match[k].in, match[k].out, t, nsci, &g, prov, 2)) goto done;
    fprintf(stderr, "speckles: %zu %sframes from %zu of %zu cubes (%zu reconstructor modes, %zu pupil samples outside the "
            "actuator hull) -> %s\n", nout, wfs_mode ? "WFS " : "", nok, t->ncubes, m->recon->nmodes, m->n_outside, out);
    rc = CLI_OK;
done:
    swfs_timing_free(t);
    swfs_fits_in_close(fs);
    free(xy); free(mask); free(sched); free(sched_x); free(W_ext); free(Rtilt); free(xslopes); free(cfirst); free(cn); free(match);
    swfs_recon_free(rin);
    swfs_speckle_model_free(m);
    swfs_engine_free(eng);
    swfs_cplx_free(halo);
    swfs_real_free(slopes);
    return rc;
}

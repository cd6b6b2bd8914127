/* specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt: frame-rate ratio and handshake
 * lag by tip-tilt cross-correlation (Sec. 4.2). */
#include "cli.h"

#include "specklewfs/fits.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *usage_text =
    "usage: specklewfs sync SCIENCE.fits HANDSHAKE.log -o TIMING.txt [--ratio-min R] [--ratio-max R]\n"
    "                       [--lag-min L] [--lag-max L] [--ratio-step S] [--lag-step S]\n"
    "\n"
    "Synchronize the science cubes with the WFS telemetry (Codona & Kenworthy 2013, Sec. 4.2).\n"
    "The star's track (TRACK extension written by `specklewfs reduce`) is cross-correlated\n"
    "with the mean x/y WFS slopes averaged over each exposure, over all four pairings of\n"
    "camera and slope axes, while the frame-rate ratio <t_sci/t_wfs> and the handshake lag\n"
    "are varied. Cubes whose exposures leave the telemetry file the handshake names\n"
    "(straddling a file boundary) are marked and not used by `specklewfs speckles`.\n"
    "\n"
    "  SCIENCE.fits     reduced science cube with TRACK and CUBEnnnn keywords\n"
    "  HANDSHAKE.log    lines \"CAMERA_FILE SLOPES_FILE WFS_FRAME\" (docs/telemetry.md); slopes\n"
    "                   files are found relative to the log's folder\n"
    "  -o TIMING.txt    timing table: ratio +- error, lag, axis pairing, one line per cube\n"
    "  --ratio-min/max  search range of <t_sci/t_wfs> (default 2 .. 12)\n"
    "  --lag-min/max    search range of the lag [WFS frames] (default -3 .. 12: the log is written\n"
    "                   after the camera starts). Keep it narrower than the period of a dominant\n"
    "                   vibration: a pure sinusoid makes the lag ambiguous by half periods\n"
    "  --ratio-step, --lag-step  coarse grid (0.01, 0.5), refined 100x around the peak\n";

typedef struct slopes_file {
    char name[SWFS_SYNC_NAME];
    size_t nwfs;
    double *mx, *my;
} slopes_file;

int swfs_cmd_sync(int argc, char **argv)
{
    const char *cmd = "sync";
    const char *sci = NULL, *logf = NULL, *out = NULL;
    swfs_sync_params p;
    swfs_sync_params_default(&p);
    p.lag_min = -3;
    p.lag_max = 12;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i], *v = i + 1 < argc ? argv[i + 1] : NULL;
        double *dst = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return CLI_OK; }
        else if (!strcmp(a, "-o")) { if (!v) return cli_usage_error(cmd, "-o needs a file name"); out = v; i++; continue; }
        else if (!strcmp(a, "--ratio-min")) dst = &p.ratio_min;
        else if (!strcmp(a, "--ratio-max")) dst = &p.ratio_max;
        else if (!strcmp(a, "--lag-min")) dst = &p.lag_min;
        else if (!strcmp(a, "--lag-max")) dst = &p.lag_max;
        else if (!strcmp(a, "--ratio-step")) dst = &p.ratio_step;
        else if (!strcmp(a, "--lag-step")) dst = &p.lag_step;
        else if (a[0] == '-' && a[1]) return cli_usage_error(cmd, "unknown option '%s'", a);
        else if (!sci) { sci = a; continue; }
        else if (!logf) { logf = a; continue; }
        else return cli_usage_error(cmd, "unexpected argument '%s'", a);
        if (cli_parse_double(cmd, a, v, dst)) return CLI_USAGE;
        i++;
    }
    if (!sci || !logf) return cli_usage_error(cmd, "needs SCIENCE.fits and HANDSHAKE.log");
    if (!out) return cli_usage_error(cmd, "needs -o TIMING.txt");

    int rc = CLI_FAIL;
    swfs_fits_in *fs = NULL;
    swfs_real *track = NULL;
    swfs_handshake *hs = NULL;
    size_t nhs = 0, ncubes = 0, nfiles = 0;
    slopes_file *files = NULL;
    swfs_sync_cube *cubes = NULL;
    double *tx = NULL, *ty = NULL;
    swfs_timing t;
    memset(&t, 0, sizeof t);
    size_t *cube_file = NULL, *cube_first = NULL, *cube_n = NULL;
    long *cube_hs = NULL;

    if (swfs_fits_in_open(&fs, sci, NULL)) { cli_error(cmd); goto done; }
    size_t nsci = swfs_fits_in_shape(fs)->nz;
    {
        double v;
        int found = 0;
        if (swfs_fits_in_key_double_opt(fs, "NCUBES", &v, &found)) { cli_error(cmd); goto done; }
        if (!found || !(v >= 1)) {
            fprintf(stderr, "specklewfs %s: %s: no NCUBES keyword; run `specklewfs reduce` on the raw cubes first\n", cmd, sci);
            goto done;
        }
        ncubes = (size_t)v;
    }
    if (!swfs_fits_in_has_ext(fs, "TRACK")) {
        fprintf(stderr, "specklewfs %s: %s: no TRACK extension; run `specklewfs reduce` on the raw cubes first\n", cmd, sci);
        goto done;
    }
    if (swfs_fits_read_real(sci, "TRACK", &track, NULL)) { cli_error(cmd); goto done; }
    if (track->nx != 4 || track->ny != nsci) {
        fprintf(stderr, "specklewfs %s: %s: TRACK is %zux%zu, expected 4 x %zu (frames)\n", cmd, sci, track->nx, track->ny, nsci);
        goto done;
    }
    if (swfs_handshake_read(logf, &hs, &nhs)) { cli_error(cmd); goto done; }
    char logdir[4096];
    cli_dir_of(logf, logdir, sizeof logdir);

    t.ncubes = ncubes;
    t.cubes = calloc(ncubes, sizeof *t.cubes);
    cubes = calloc(ncubes, sizeof *cubes);
    files = calloc(ncubes, sizeof *files);
    cube_file = calloc(ncubes, sizeof *cube_file);
    cube_first = calloc(ncubes, sizeof *cube_first);
    cube_n = calloc(ncubes, sizeof *cube_n);
    cube_hs = calloc(ncubes, sizeof *cube_hs);
    tx = malloc(nsci * sizeof *tx);
    ty = malloc(nsci * sizeof *ty);
    if (!t.cubes || !cubes || !files || !cube_file || !cube_first || !cube_n || !cube_hs || !tx || !ty) {
        fprintf(stderr, "specklewfs %s: out of memory\n", cmd);
        goto done;
    }
    /* Frames of each cube (TRACK column 2 = cube index, in order). */
    for (size_t k = 0; k < nsci; k++) {
        double c = track->data[4 * k + 2];
        if (!(c >= 0) || (size_t)c >= ncubes) {
            fprintf(stderr, "specklewfs %s: %s: TRACK frame %zu names cube %g of %zu\n", cmd, sci, k, c, ncubes);
            goto done;
        }
        size_t ci = (size_t)c;
        if (cube_n[ci] == 0) cube_first[ci] = k;
        else if (cube_first[ci] + cube_n[ci] != k) {
            fprintf(stderr, "specklewfs %s: %s: frames of cube %zu are not contiguous\n", cmd, sci, ci);
            goto done;
        }
        cube_n[ci]++;
        tx[k] = track->data[4 * k];
        ty[k] = track->data[4 * k + 1];
    }
    size_t nwfs_slopes = 0;
    for (size_t ci = 0; ci < ncubes; ci++) {
        char key[32], cam[SWFS_SYNC_NAME];
        int found = 0;
        snprintf(key, sizeof key, "CUBE%04u", (unsigned)(ci % 10000));
        if (swfs_fits_in_key_string_opt(fs, key, cam, sizeof cam, &found)) { cli_error(cmd); goto done; }
        if (!found) { fprintf(stderr, "specklewfs %s: %s: missing keyword %s (camera file of cube %zu)\n", cmd, sci, key, ci); goto done; }
        if (cube_n[ci] == 0) { fprintf(stderr, "specklewfs %s: %s: cube %zu (%s) has no frames\n", cmd, sci, ci, cam); goto done; }
        size_t h = nhs;
        for (size_t k = 0; k < nhs; k++)
            if (!strcmp(hs[k].camera, cam)) { h = k; break; }
        if (h == nhs) {
            fprintf(stderr, "specklewfs %s: %s: the handshake log does not cover cube %zu (%s)\n", cmd, logf, ci, cam);
            goto done;
        }
        /* Load each telemetry file once. */
        size_t fi = nfiles;
        for (size_t k = 0; k < nfiles; k++)
            if (!strcmp(files[k].name, hs[h].slopes)) { fi = k; break; }
        if (fi == nfiles) {
            char path[8192];
            snprintf(path, sizeof path, "%s/%s", logdir, hs[h].slopes);
            swfs_real *s = NULL;
            if (swfs_fits_read_real(path, NULL, &s, NULL)) { cli_error(cmd); goto done; }
            if (s->nz != 1 || s->nx % 2 || (nwfs_slopes && s->nx != nwfs_slopes)) {
                fprintf(stderr, "specklewfs %s: %s: slopes must be a 2-D image NSLOPES (even%s) x N_WFS, got %zux%zux%zu\n",
                        cmd, path, nwfs_slopes ? ", same in every file" : "", s->nx, s->ny, s->nz);
                swfs_real_free(s);
                goto done;
            }
            nwfs_slopes = s->nx;
            snprintf(files[fi].name, sizeof files[fi].name, "%s", hs[h].slopes);
            files[fi].nwfs = s->ny;
            files[fi].mx = malloc(s->ny * sizeof(double));
            files[fi].my = malloc(s->ny * sizeof(double));
            if (!files[fi].mx || !files[fi].my) { swfs_real_free(s); fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
            swfs_slopes_mean_xy(s->data, s->nx, s->ny, NULL, files[fi].mx, files[fi].my);
            swfs_real_free(s);
            nfiles++;
        }
        cube_file[ci] = fi;
        cube_hs[ci] = hs[h].frame;
        cubes[ci] = (swfs_sync_cube){cube_n[ci], tx + cube_first[ci], ty + cube_first[ci], files[fi].mx, files[fi].my,
                                     files[fi].nwfs, (double)hs[h].frame};
        snprintf(t.cubes[ci].camera, sizeof t.cubes[ci].camera, "%s", cam);
        /* The timing table may live elsewhere: record the telemetry file's absolute path. */
        {
            char rel[8192], *abs = NULL;
            snprintf(rel, sizeof rel, "%s/%s", logdir, hs[h].slopes);
            abs = realpath(rel, NULL);
            int len = snprintf(t.cubes[ci].slopes, sizeof t.cubes[ci].slopes, "%s", abs ? abs : rel);
            free(abs);
            if (len < 0 || (size_t)len >= sizeof t.cubes[ci].slopes) {
                fprintf(stderr, "specklewfs %s: %s: telemetry path too long\n", cmd, rel);
                goto done;
            }
        }
        t.cubes[ci].first = cube_first[ci];
        t.cubes[ci].nframes = cube_n[ci];
    }
    if (swfs_sync_estimate(cubes, ncubes, &p, &t.fit)) { cli_error(cmd); goto done; }
    t.ratio = t.fit.ratio;
    t.ratio_err = t.fit.ratio_err;
    t.lag = t.fit.lag;
    size_t nok = 0;
    for (size_t ci = 0; ci < ncubes; ci++) {
        double start = (double)cube_hs[ci] - t.lag;
        t.cubes[ci].start = start;
        int inside = start >= 0 && start + (double)cube_n[ci] * t.ratio <= (double)files[cube_file[ci]].nwfs;
        t.cubes[ci].status = inside ? SWFS_CUBE_OK : SWFS_CUBE_STRADDLES;
        nok += inside ? 1u : 0u;
    }
    if (swfs_timing_write(out, &t)) { cli_error(cmd); goto done; }
    printf("sync: <t_sci/t_wfs> = %.4f +- %.4f, lag = %.2f WFS frames (handshake frame - lag = exposure start)\n",
           t.ratio, t.ratio_err, t.lag);
    printf("sync: pairing camera x <- %s slopes (sign %+d, corr %.3f), camera y <- %s slopes (sign %+d, corr %.3f)\n",
           t.fit.swap ? "y" : "x", t.fit.sign_x, t.fit.corr_x, t.fit.swap ? "x" : "y", t.fit.sign_y, t.fit.corr_y);
    printf("sync: |corr| tx-mx %.3f tx-my %.3f ty-mx %.3f ty-my %.3f\n", t.fit.corr4[0], t.fit.corr4[1], t.fit.corr4[2],
           t.fit.corr4[3]);
    printf("sync: %zu of %zu cubes usable, %zu straddle a telemetry-file boundary -> %s\n", nok, ncubes, ncubes - nok, out);
    if (nok == 0) {
        fprintf(stderr, "specklewfs %s: no cube lies inside its telemetry file\n", cmd);
        goto done;
    }
    rc = CLI_OK;
done:
    swfs_fits_in_close(fs);
    swfs_real_free(track);
    free(hs);
    if (files)
        for (size_t k = 0; k < nfiles; k++) { free(files[k].mx); free(files[k].my); }
    free(files); free(cubes); free(tx); free(ty); free(t.cubes);
    free(cube_file); free(cube_first); free(cube_n); free(cube_hs);
    return rc;
}

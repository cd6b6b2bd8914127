/* estimate from cubes, and the camera noise model: see include/specklewfs/run.h. */
#include "specklewfs/run.h"
#include "specklewfs/accum.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "run_internal.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int swfs_noise_from_header(const char *path, double read_noise, double gain, swfs_noise *out)
{
    swfs_fits_in *f = NULL;
    swfs_noise n = {0.0, 0.0};
    double v;
    int found = 0;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "RDNOISE", &v, &found);
    if (!rc && found) n.read_noise = v;
    if (!rc) rc = swfs_fits_in_key_double_opt(f, "GAIN", &v, &found);
    if (!rc && found) n.gain = v;
    swfs_fits_in_close(f);
    if (rc) return rc;
    /* Explicit values win over the header. */
    if (!isnan(read_noise)) n.read_noise = read_noise;
    if (!isnan(gain)) n.gain = gain;
    /* Physical ranges: a camera's read noise is at most 1e6 counts rms; a gain is 0 (no
     * photon-noise term) or 1e-4 .. 1e6 e-/count -- a 1E-300 gain would turn Phi_I/GAIN
     * into a noise variance of 1E300. */
    if (!(n.read_noise >= 0 && n.read_noise <= 1e6)) {
        if (!isnan(read_noise))
            return swfs_fail(SWFS_ERR_VALUE, "the read noise given (--read-noise) %g counts is outside 0 .. 1e6", n.read_noise);
        return swfs_fail(SWFS_ERR_VALUE, "%s: read noise RDNOISE = %g counts is outside 0 .. 1e6", path, n.read_noise);
    }
    if (!(n.gain == 0 || (n.gain >= 1e-4 && n.gain <= 1e6))) {
        if (!isnan(gain))
            return swfs_fail(SWFS_ERR_VALUE, "the gain given (--gain) %g e-/count is outside 1e-4 .. 1e6 (or 0: no photon "
                             "noise)", n.gain);
        return swfs_fail(SWFS_ERR_VALUE, "%s: GAIN = %g e-/count is outside 1e-4 .. 1e6 (or 0: no photon noise)", path,
                         n.gain);
    }
    *out = n;
    return SWFS_OK;
}

double swfs_g_smooth_pixels(double g_smooth_lod, double pixscale, int *assumed)
{
    *assumed = 0;
    if (!(g_smooth_lod > 0)) return 0.0;
    if (isfinite(pixscale) && pixscale > 0) return g_smooth_lod / pixscale;
    /* No sampling known: the paper's 0.25 lambda/D per pixel. */
    *assumed = 1;
    return g_smooth_lod / 0.25;
}

void swfs_estimate_run_options_default(swfs_estimate_run_options *o)
{
    memset(o, 0, sizeof *o);
    o->read_noise = o->gain = NAN;
    o->g_smooth_lod = 2.0;
    o->block = 64;
}

/* Shapes of the two cubes: real science, complex speckles, frame for frame, >= 2 frames. */
static int check_cubes(const swfs_estimate_run_options *o, const swfs_fits_shape *ss, const swfs_fits_shape *sp)
{
    if (ss->is_complex)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: science cube is complex; expected real intensities (x, y, frame)",
                         o->science);
    if (!sp->is_complex)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: speckle cube is not complex; expected NAXIS1 = 2 with CTYPE1 = "
                         "'COMPLEX' (real, imaginary), then x, y, frame", o->speckles);
    if (ss->nx != sp->nx || ss->ny != sp->ny || ss->nz != sp->nz)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: cube is %zux%zux%zu but %s is %zux%zux%zu (they must match frame for "
                         "frame)", o->speckles, sp->nx, sp->ny, sp->nz, o->science, ss->nx, ss->ny, ss->nz);
    if (ss->nz < 2)
        return swfs_fail(SWFS_ERR_SHAPE, "%s: only %zu frame; the statistics need at least 2", o->science, ss->nz);
    return SWFS_OK;
}

/* Speckles computed for a flipped or transposed camera (CAMORIEN on the speckle cube, from
 * sync's pairing) go with science frames turned the same way (speckles --match writes them,
 * with the same CAMORIEN): the camera's own frames would interfere with the mirror image of
 * their speckles and give a wrong halo without any other sign. */
static int check_orientation(const swfs_estimate_run_options *o, swfs_fits_in *fs, swfs_fits_in *fp)
{
    char a[80] = "", b[80] = "";
    int fa = 0, fb = 0;
    int rc = swfs_fits_in_key_string_opt(fp, "CAMORIEN", a, sizeof a, &fa);
    if (!rc && fa) rc = swfs_fits_in_key_string_opt(fs, "CAMORIEN", b, sizeof b, &fb);
    if (!rc && fa && (!fb || strcmp(a, b)))
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: the speckles are for a camera oriented %s relative to the model, but %s %s%s%s; "
                       "use the science cube 'speckles --match' wrote, which is turned into the model's orientation",
                       o->speckles, a, o->science, fb ? "was turned " : "is in the camera's own orientation", fb ? b : "",
                       "");
    return rc;
}

/* Mean circularity |<psi^2>|/<|psi|^2> inside 4 lambda/D (eq:zeroSqMean), NaN without PIXSCALE. */
static double core_circularity(const swfs_halo *h, double pix)
{
    const size_t nx = h->circ->nx, ny = h->circ->ny;
    double sum = 0.0;
    size_t n = 0;
    for (size_t j = 0; j < ny && isfinite(pix); j++)
        for (size_t i = 0; i < nx; i++) {
            double dx = ((double)i - (double)(nx / 2)) * pix, dy = ((double)j - (double)(ny / 2)) * pix;
            double c = h->circ->data[j * nx + i];
            if (dx * dx + dy * dy <= 16.0 && isfinite(c)) { sum += c; n++; }
        }
    return n ? sum / (double)n : NAN;
}

/* This member's frames [first, first + count) of the cubes into acc. */
static int accumulate(const swfs_estimate_run_options *o, swfs_fits_in *fs, swfs_fits_in *fp, swfs_accum *acc,
                      size_t first, size_t count)
{
    const size_t np = acc->nx * acc->ny;
    const size_t block = o->block < count ? o->block : (count ? count : 1);
    double *ibuf = block <= SIZE_MAX / sizeof(swfs_complex) / np ? malloc(block * np * sizeof *ibuf) : NULL;
    swfs_complex *pbuf = ibuf ? malloc(block * np * sizeof *pbuf) : NULL;
    int rc = pbuf ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "estimate: out of memory");
    for (size_t k = 0; !rc && k < count; k += block) {
        const size_t n = count - k < block ? count - k : block;
        if ((rc = swfs_fits_in_read_real(fs, first + k, n, ibuf)) || (rc = swfs_fits_in_read_cplx(fp, first + k, n, pbuf)))
            break;
        for (size_t j = 0; j < n && !rc; j++)
            if ((rc = swfs_accum_add(acc, ibuf + j * np, pbuf + j * np))) swfs_fail_context(rc, "%s", o->speckles);
        if (!rc) rc = swfs_progress_report(o->progress, o->progress_ctx, "frames", k + n, count);
    }
    free(ibuf);
    free(pbuf);
    return rc;
}

int swfs_estimate_run(const swfs_estimate_run_options *o, swfs_estimate_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->science || !o->speckles || !o->out) return swfs_fail(SWFS_ERR_ARG, "estimate: needs science, speckles, out");
    if (!o->block || o->block > 1u << 20)
        return swfs_fail(SWFS_ERR_ARG, "estimate: frames per read must be 1..%u, got %zu", 1u << 20, o->block);
    if (!(o->g_smooth_lod >= 0))
        return swfs_fail(SWFS_ERR_ARG, "estimate: g smoothing must be >= 0 lambda/D, got %g", o->g_smooth_lod);
    /* With a team every member reaches every agreement, whatever failed before it. */
    swfs_fits_in *fs = NULL, *fp = NULL;
    swfs_accum *acc = NULL;
    swfs_paths *paths = NULL;
    int rc = swfs_paths_create(&paths);
    swfs_paths_input(paths, "science cube", o->science);
    swfs_paths_input(paths, "speckle cube", o->speckles);
    if (!rc) rc = swfs_paths_output(paths, "output halo", o->out);
    swfs_paths_free(paths);
    if (rc) return rc;
    rc = swfs_fits_in_open(&fs, o->science, NULL);
    if (!rc) rc = swfs_fits_in_open(&fp, o->speckles, NULL);
    if (!rc) rc = check_cubes(o, swfs_fits_in_shape(fs), swfs_fits_in_shape(fp));
    if (!rc) rc = check_orientation(o, fs, fp);
    if (!rc) rc = swfs_noise_from_header(o->science, o->read_noise, o->gain, &r->noise);
    if (!rc) rc = swfs_fits_in_geom(fp, &r->geom);
    /* the scale factor's smoothing in pixels, checked before the frames are read */
    swfs_estimate_options eopt = {swfs_g_smooth_pixels(o->g_smooth_lod, r->geom.pixscale, &r->g_smooth_assumed)};
    if (!rc && !(eopt.g_smooth <= 60))
        rc = swfs_fail(SWFS_ERR_ARG, "estimate: g smoothing %g lambda/D is %g pixels at %s's %g lambda/D per pixel; "
                       "expected at most 60 pixels (%g lambda/D)", o->g_smooth_lod, eopt.g_smooth, o->speckles,
                       o->g_smooth_lod / eopt.g_smooth, 60 * o->g_smooth_lod / eopt.g_smooth);
    const swfs_fits_shape *ss = rc ? NULL : swfs_fits_in_shape(fs);
    if (!rc && !(acc = swfs_accum_create(ss->nx, ss->ny))) rc = swfs_fail(SWFS_ERR_NOMEM, "estimate: out of memory");
    if (!rc) {
        size_t first, count;
        swfs_team_share(&ss->nz, 1, 1, o->team ? o->team->rank : 0, o->team ? o->team->size : 1, &first, &count);
        rc = accumulate(o, fs, fp, acc, first, count);
    }
    rc = swfs_team_agree(o->team, rc);
    if (!rc) rc = swfs_team_merge_accum(o->team, acc, acc);
    if (!rc && swfs_team_writer(o->team)) {
        if ((rc = swfs_estimate(acc, &r->noise, &eopt, &r->halo))) swfs_fail_context(rc, "%s + %s", o->science, o->speckles);
        /* the speckles' tip-tilt treatment, and the AO residual's time mean that speckles
         * measured on the same frames, go with the halo */
        int tf = 0;
        if (!rc && (rc = swfs_fits_in_key_string_opt(fp, "TIPTILT", r->halo->tiptilt, sizeof r->halo->tiptilt, &tf)))
            swfs_fail_context(rc, "%s", o->speckles);
        if (!rc && swfs_fits_in_has_ext(fp, "RESMEAN")) rc = swfs_resmean_read_ext(fp, o->speckles, &r->halo->resmean);
        if (!rc && r->halo->resmean && r->geom.pupn > 0 && r->halo->resmean->nx != (size_t)r->geom.pupn)
            rc = swfs_fail(SWFS_ERR_SHAPE, "%s: RESMEAN is %zux%zu but PUPN = %ld", o->speckles, r->halo->resmean->nx,
                           r->halo->resmean->ny, r->geom.pupn);
        char nl[256];
        snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count", r->noise.read_noise,
                 r->noise.gain);
        const char **prov = rc ? NULL : swfs_prov_plus(o->prov, o->nprov, nl);
        if (!rc) rc = prov ? swfs_halo_write(r->halo, o->out, &r->geom, prov, o->nprov + 1)
                           : swfs_fail(SWFS_ERR_NOMEM, "estimate: out of memory");
        free(prov);
        if (!rc) r->circ_core = core_circularity(r->halo, r->geom.pixscale);
    }
    rc = swfs_team_agree(o->team, rc); /* every member ends with member 0's writing status */
    if (rc) {
        swfs_halo_free(r->halo);
        r->halo = NULL;
    }
    swfs_accum_free(acc);
    swfs_fits_in_close(fs);
    swfs_fits_in_close(fp);
    return rc;
}

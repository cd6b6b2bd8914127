/* Writing the Sec. 3 data set: science.fits, speckles.fits, truth.fits, pupil.fits. */
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/sim.h"
#include "specklewfs/status.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Provenance = the caller's lines, then "sim: key=value" for every parameter. */
static char **provenance_lines(const swfs_sim_result *r, const char *const *prov, size_t nprov, size_t *count)
{
    size_t len = swfs_sim_params_format(&r->params, NULL, 0);
    char *text = malloc(len + 1);
    if (!text) return NULL;
    swfs_sim_params_format(&r->params, text, len + 1);
    size_t nl = 0;
    for (const char *s = text; *s; s++) nl += *s == '\n';
    char **lines = calloc(nprov + nl + 1, sizeof *lines);
    if (!lines) {
        free(text);
        return NULL;
    }
    size_t k = 0;
    for (size_t i = 0; i < nprov; i++) lines[k++] = strdup(prov[i]);
    for (char *s = text, *e; (e = strchr(s, '\n')); s = e + 1) {
        *e = '\0';
        size_t m = strlen(s) + 8;
        lines[k] = malloc(m);
        if (lines[k]) snprintf(lines[k], m, "sim: %s", s);
        k++;
    }
    free(text);
    *count = k;
    for (size_t i = 0; i < k; i++)
        if (!lines[i]) {
            for (size_t j = 0; j < k; j++) free(lines[j]);
            free(lines);
            return NULL;
        }
    return lines;
}

static int start(swfs_fits_out **o, const char *dir, const char *name, const swfs_geom *g, char **lines, size_t nl)
{
    char path[4096];
    if ((size_t)snprintf(path, sizeof path, "%s/%s", dir, name) >= sizeof path)
        return swfs_fail(SWFS_ERR_ARG, "%s: output folder name too long", dir);
    int rc = swfs_fits_out_create(o, path);
    if (rc) return rc;
    rc = swfs_fits_out_set_stamp(*o, g, (const char *const *)lines, nl);
    if (rc) {
        swfs_fits_out_abort(*o);
        *o = NULL;
    }
    return rc;
}

static int finish(swfs_fits_out *o, int rc)
{
    if (rc) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

static int sim_write_files(const swfs_sim_result *r, const swfs_real *science, double read_noise, double gain,
                           const char *dir, const char *const *provenance, size_t nprov);

/* The four files as one group (atomic.h): a failure at the third leaves none of them. */
int swfs_sim_write(const swfs_sim_result *r, const swfs_real *science, double read_noise, double gain, const char *dir,
                   const char *const *provenance, size_t nprov)
{
    swfs_outputs_begin();
    int rc = sim_write_files(r, science, read_noise, gain, dir, provenance, nprov);
    const int erc = swfs_outputs_end(rc == SWFS_OK);
    return rc ? rc : erc;
}

static int sim_write_files(const swfs_sim_result *r, const swfs_real *science, double read_noise, double gain,
                           const char *dir, const char *const *provenance, size_t nprov)
{
    if (!r || !dir) return swfs_fail(SWFS_ERR_ARG, "simulation write: missing result or folder");
    if (!science) science = r->science;
    if (science->nx != r->science->nx || science->ny != r->science->ny || science->nz != r->science->nz)
        return swfs_fail(SWFS_ERR_SHAPE, "simulation write: science cube is %zux%zux%zu, expected %zux%zux%zu",
                         science->nx, science->ny, science->nz, r->science->nx, r->science->ny, r->science->nz);
    size_t nl = 0;
    char **lines = provenance_lines(r, provenance, nprov, &nl);
    if (!lines) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    swfs_fits_out *o = NULL;
    int rc;

    /* science.fits: counts, with the noise model the estimator must remove (Sec. 2.3). */
    if (!(rc = start(&o, dir, "science.fits", &r->geom, lines, nl))) {
        rc = swfs_fits_out_real(o, NULL, science, -32);
        if (!rc) rc = swfs_fits_out_key_double(o, "RDNOISE", read_noise, "[counts] Gaussian read/background noise sigma");
        if (!rc) rc = swfs_fits_out_key_double(o, "GAIN", gain, "[e-/count] photon noise: var = I/GAIN (0: none)");
        if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "counts", "science camera counts");
        if (!rc) rc = swfs_fits_out_key_double(o, "TOTCOUNT", r->params.total_counts, "mean counts per exposure, whole PSF");
        rc = finish(o, rc);
    }
    /* speckles.fits: the WFS-side complex speckle cube psi (no NCP), field units. */
    if (!rc && !(rc = start(&o, dir, "speckles.fits", &r->geom, lines, nl))) {
        rc = swfs_fits_out_cplx(o, NULL, r->speckles, -32);
        if (!rc)
            rc = swfs_fits_out_key_string(o, "BUNIT", "peak", "field / unaberrated peak amplitude, mean removed");
        rc = finish(o, rc);
    }
    /* truth.fits: NCP [m] and the true static halo [sqrt(counts)]. */
    if (!rc && !(rc = start(&o, dir, "truth.fits", &r->geom, lines, nl))) {
        rc = swfs_fits_out_real(o, "NCP", r->ncp, -64);
        if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "m", "injected NCP wavefront, piston removed");
        if (!rc) rc = swfs_fits_out_key_double(o, "NCPRMS", r->ncp_rms, "[m] rms over the pupil");
        if (!rc) rc = swfs_fits_out_key_double(o, "NCPPV", r->ncp_pv, "[m] peak-to-valley over the pupil");
        if (!rc) rc = swfs_fits_out_real(o, "PUPIL", r->pupil, -32);
        if (!rc) rc = swfs_fits_out_cplx(o, "HALO", r->halo_true, -64);
        if (!rc) rc = swfs_fits_out_key_string(o, "BUNIT", "sqrt(counts)", "true static halo, peak-phase referenced");
        if (!rc) rc = swfs_fits_out_key_double(o, "RESRMS", r->residual_rms, "[m] achieved AO residual rms");
        if (!rc) rc = swfs_fits_out_key_double(o, "KSIGMA", r->kernel_sigma, "[m] AO smoothing kernel sigma");
        if (!rc) rc = swfs_fits_out_key_double(o, "STREHL", r->strehl, "mean on-axis Strehl with NCP");
        rc = finish(o, rc);
    }
    /* pupil.fits: the mask. */
    if (!rc && !(rc = start(&o, dir, "pupil.fits", &r->geom, lines, nl))) {
        rc = swfs_fits_out_real(o, NULL, r->pupil, -32);
        rc = finish(o, rc);
    }
    for (size_t i = 0; i < nl; i++) free(lines[i]);
    free(lines);
    return rc;
}

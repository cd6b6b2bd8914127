/* Shared fixture of the reconstructor tests (test_recon_map.c, test_recon_vk.c): the
 * MMT-like geometry (217 hexapolar actuators on a 6.5 m pupil of 66 samples, 12 x 12
 * Shack-Hartmann, D = S T), synthetic slopes, and the pupil error of a reconstructor. */
#ifndef SWFS_RECON_FIXTURE_H
#define SWFS_RECON_FIXTURE_H

#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/interp.h"
#include "specklewfs/rng.h"
#include "specklewfs/sparse.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NPUP 66
#define PUPDX 0.1
#define TELD 6.5
#define NSUB 12

typedef struct setup {
    double *xy, *mask, *D, *L; /* L: optional prior factor (test_recon_vk), nact x nact */
    size_t nact, nslopes;
    swfs_sparse *T;
    swfs_shwfs *wfs;
} setup;

static void setup_init(setup *s)
{
    memset(s, 0, sizeof *s);
    s->mask = malloc(NPUP * NPUP * sizeof *s->mask);
    assert_ok(swfs_aperture_make(s->mask, NPUP, PUPDX, TELD, 0.1, 0, 0));
    assert_ok(swfs_actuators_hexapolar(TELD, 0.45, 0.2, &s->xy, &s->nact));
    size_t nout = 0;
    assert_ok(swfs_interp_ct_grid(s->xy, s->nact, NPUP, PUPDX, s->mask, &s->T, &nout));
    assert_ok(swfs_shwfs_create(&s->wfs, NSUB, TELD, s->mask, NPUP, PUPDX, 0.5));
    s->nslopes = s->wfs->nslopes;
    assert_ok(swfs_interaction_matrix(s->wfs, s->T, &s->D));
}

static void setup_free(setup *s)
{
    free(s->xy); free(s->mask); free(s->D); free(s->L);
    swfs_sparse_free(s->T);
    swfs_shwfs_free(s->wfs);
}

/* o = D z plus white noise of sigma [rad] on the valid slopes. */
static void slopes_of(const setup *s, swfs_rng *r, const double *z, double sigma, double *o)
{
    for (size_t i = 0; i < s->nslopes; i++) {
        double v = 0;
        for (size_t a = 0; a < s->nact; a++) v += s->D[i * s->nact + a] * z[a];
        o[i] = v + (s->wfs->valid[i % (s->nslopes / 2)] ? sigma * swfs_rng_normal(r) : 0);
    }
}

/* rms over the pupil of T (zr - z), piston removed (the slopes do not see it) [m]. */
static double pupil_err(const setup *s, const double *zr, const double *z, double *d, double *grid)
{
    for (size_t a = 0; a < s->nact; a++) d[a] = zr[a] - z[a];
    swfs_sparse_apply(s->T, d, grid);
    double m = 0, q = 0, n = 0;
    for (size_t i = 0; i < NPUP * NPUP; i++)
        if (s->mask[i] > 0) { m += grid[i]; q += grid[i] * grid[i]; n++; }
    return sqrt(q / n - (m / n) * (m / n));
}

/* rms pupil error of the reconstructor W over ntest frames (zt actuators, st slopes). */
static double test_err(const setup *s, const swfs_recon *W, const double *zt, const double *st, size_t ntest)
{
    double *zr = malloc(s->nact * sizeof *zr), *d = malloc(s->nact * sizeof *d), *g = malloc(NPUP * NPUP * sizeof *g);
    double e = 0;
    for (size_t t = 0; t < ntest; t++) {
        swfs_recon_apply(W, st + t * s->nslopes, zr);
        double x = pupil_err(s, zr, zt + t * s->nact, d, g);
        e += x * x;
    }
    free(zr); free(d); free(g);
    return sqrt(e / (double)ntest);
}

/* The error of reconstructing nothing (the signal) and of the best SVD cut tried. */
static double zero_err(const setup *s, const double *zt, const double *st, size_t ntest)
{
    swfs_recon zero = {.nact = s->nact, .nslopes = s->nslopes, .W = calloc(s->nact * s->nslopes, sizeof(double))};
    double e = test_err(s, &zero, zt, st, ntest);
    free(zero.W);
    return e;
}

static double best_svd_err(const setup *s, const double *zt, const double *st, size_t ntest)
{
    double best = INFINITY;
    const double rconds[] = {1e-2, 2e-2, 5e-2, 0.1, 0.2, 0.3};
    for (size_t i = 0; i < sizeof rconds / sizeof *rconds; i++) {
        swfs_recon *svd = NULL;
        assert_ok(swfs_recon_svd(s->D, s->nslopes, s->nact, rconds[i], 0, &svd));
        double e = test_err(s, svd, zt, st, ntest);
        print_message("SVD rcond %.2g: %zu modes, error %.3g nm\n", rconds[i], svd->nmodes, e * 1e9);
        if (e < best) best = e;
        swfs_recon_free(svd);
    }
    return best;
}

/* rms of the training slopes over the valid slopes [rad]. */
static double slopes_rms(const setup *s, const double *sl, size_t n)
{
    double q = 0;
    for (size_t i = 0; i < n * s->nslopes; i++) q += sl[i] * sl[i];
    return sqrt(q / (double)(n * 2 * s->wfs->nvalid));
}

#endif

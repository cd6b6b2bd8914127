/* DM offsets (dmfit.h, `specklewfs dmoffsets`): exact recovery of a surface the DM can
 * make, the Zernike modal filter, coverage (and the rim continued within one pitch, as
 * export_truth fits it) and bad-input errors. */
#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/dmfit.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>

#define NP 64
#define DX 0.1
#define DIAM 6.3

static swfs_geom geom(double obscur)
{
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6;
    g.teldiam = DIAM;
    g.obscur = obscur;
    g.pixscale = 0.25;
    g.pupdx = DX;
    g.pupn = NP;
    return g;
}

/* Mask-weighted rms, mean removed. */
static double rms(const double *v, const double *mask)
{
    double s = 0, s1 = 0, s2 = 0;
    for (size_t k = 0; k < NP * NP; k++) {
        s += mask[k];
        s1 += mask[k] * v[k];
        s2 += mask[k] * v[k] * v[k];
    }
    return sqrt(fmax(s2 / s - (s1 / s) * (s1 / s), 0));
}

static void known_surface(int influence)
{
    swfs_geom g = geom(0.1);
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, 0.6, DX, &xy, &nact));
    swfs_dmfit_options o;
    swfs_dmfit_options_default(&o);
    o.influence = influence;
    o.reg = 0.0; /* exact least squares */
    swfs_dmfit *f = NULL;
    assert_ok(swfs_dmfit_create(&f, xy, nact, &g, NULL, &o));
    assert_int_equal(swfs_dmfit_nact(f), nact);
    if (influence == SWFS_INFLUENCE_GAUSS) assert_close(swfs_dmfit_pitch(f), 0.6, 0.05);

    /* Commands -> surface -> fit -> the same surface and commands. */
    swfs_rng r;
    swfs_rng_seed(&r, 7);
    double *c = calloc(nact, sizeof *c), *c2 = calloc(nact, sizeof *c2);
    double *s = calloc(NP * NP, sizeof *s), *s2 = calloc(NP * NP, sizeof *s2), *d = calloc(NP * NP, sizeof *d);
    for (size_t a = 0; a < nact; a++) c[a] = 50e-9 * swfs_rng_normal(&r);
    swfs_dmfit_surface(f, c, s);
    swfs_dmfit_stats st;
    assert_ok(swfs_dmfit_apply(f, s, c2, s2, &st));
    const double *mask = swfs_dmfit_mask(f);
    for (size_t k = 0; k < NP * NP; k++) d[k] = s2[k] - s[k];
    const double srms = rms(s, mask);
    assert_true(srms > 10e-9);
    assert_true(rms(d, mask) < 1e-6 * srms);
    assert_true(st.unfit_rms < 1e-6 * srms);
    assert_close(st.fit_rms, st.target_rms, 1e-6 * srms);
    assert_close(st.filtered_rms, 0.0, 0.0);
    /* Commands: every actuator whose influence reaches well into the pupil comes back. */
    const swfs_sparse *A = swfs_dmfit_influence(f);
    double *colsum = calloc(nact, sizeof *colsum);
    for (size_t q = 0; q < A->nrows; q++)
        for (size_t e = A->row_ptr[q]; e < A->row_ptr[q + 1]; e++) colsum[A->col[e]] += A->val[e] * A->val[e];
    double maxcol = 0;
    for (size_t a = 0; a < nact; a++) maxcol = fmax(maxcol, colsum[a]);
    size_t checked = 0;
    for (size_t a = 0; a < nact; a++)
        if (colsum[a] > 0.2 * maxcol) {
            assert_close(c2[a], c[a], 1e-4 * 50e-9);
            checked++;
        }
    assert_true(checked > nact / 2);
    /* The two-step fit of three targets at once (the surface, twice it, a random one) gives
     * swfs_dmfit_apply's commands to rounding */
    double *b = calloc(3 * nact, sizeof *b), *cm = calloc(3 * nact, sizeof *cm), *c3 = calloc(nact, sizeof *c3);
    for (size_t k = 0; k < NP * NP; k++) d[k] = 40e-9 * swfs_rng_normal(&r);
    for (size_t k = 0; k < NP * NP; k++) s2[k] = 2 * s[k];
    const double *tg[3] = {s, s2, d};
    for (size_t t = 0; t < 3; t++) assert_ok(swfs_dmfit_rhs(f, tg[t], b + t * nact));
    swfs_dmfit_solve_many(f, b, 3, cm);
    for (size_t t = 0; t < 3; t++) {
        assert_ok(swfs_dmfit_apply(f, tg[t], c3, NULL, NULL));
        double m = 0;
        for (size_t a = 0; a < nact; a++) m = fmax(m, fabs(c3[a]));
        assert_true(m > 1e-9);
        for (size_t a = 0; a < nact; a++) assert_close(cm[t * nact + a], c3[a], 1e-9 * m);
    }
    /* the three at once (rhs_many, rows of 4 on the plan's samples): the same sums, bit for bit */
    const size_t npx = swfs_dmfit_npix(f), *px = swfs_dmfit_pix(f);
    double *R = calloc(npx * 4, sizeof *R), *bt = calloc(nact * 3, sizeof *bt);
    for (size_t k = 0; k < npx; k++)
        for (size_t t = 0; t < 3; t++) R[k * 4 + t] = tg[t][px[k]];
    assert_ok(swfs_dmfit_rhs_many(f, R, 4, 3, bt));
    for (size_t t = 0; t < 3; t++)
        for (size_t a = 0; a < nact; a++) assert_true(bt[a * 3 + t] == b[t * nact + a]);
    d[(NP / 2) * NP + NP / 2 + NP / 4] = NAN; /* a target not finite in the pupil is refused */
    assert_int_equal(swfs_dmfit_rhs(f, d, b), SWFS_ERR_VALUE);
    for (size_t k = 0; k < npx; k++) R[k * 4 + 2] = d[px[k]];
    assert_int_equal(swfs_dmfit_rhs_many(f, R, 4, 3, bt), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "target 2 of 3 is not finite"));
    free(R);
    free(bt);
    free(b);
    free(cm);
    free(c3);
    free(colsum);
    free(c);
    free(c2);
    free(s);
    free(s2);
    free(d);
    free(xy);
    swfs_dmfit_free(f);
}

static void test_known_surface_gauss(void **state)
{
    (void)state;
    known_surface(SWFS_INFLUENCE_GAUSS);
}

static void test_known_surface_cubic(void **state)
{
    (void)state;
    known_surface(SWFS_INFLUENCE_CUBIC);
}

/* Zernike (n, m) map on the grid. */
static void zernike_map(int j, double coef, double *out)
{
    int n, m;
    assert_ok(swfs_zernike_noll(j, &n, &m));
    const double c = 0.5 * (NP - 1);
    for (size_t q = 0; q < NP; q++)
        for (size_t p = 0; p < NP; p++) {
            const double x = ((double)p - c) * DX, y = ((double)q - c) * DX;
            out[q * NP + p] += coef * swfs_zernike(n, m, hypot(x, y) / (0.5 * DIAM), atan2(y, x));
        }
}

static void test_modes(void **state)
{
    (void)state;
    swfs_geom g = geom(0.0); /* full disk: the Zernikes are orthogonal */
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, 0.45, DX, &xy, &nact));
    double *lo = calloc(NP * NP, sizeof *lo), *hi = calloc(NP * NP, sizeof *hi), *t = calloc(NP * NP, sizeof *t);
    zernike_map(4, 40e-9, lo);   /* defocus */
    zernike_map(6, -25e-9, lo);  /* astigmatism */
    zernike_map(8, 30e-9, lo);   /* coma */
    zernike_map(37, 20e-9, hi);  /* spherical n = 10 */
    zernike_map(28, 15e-9, hi);  /* n = 6 */
    for (size_t k = 0; k < NP * NP; k++) t[k] = lo[k] + hi[k];
    swfs_dmfit_options o;
    swfs_dmfit_options_default(&o);
    o.modes = 15; /* through n = 4 */
    swfs_dmfit *f = NULL;
    assert_ok(swfs_dmfit_create(&f, xy, nact, &g, NULL, &o));
    const double *mask = swfs_dmfit_mask(f);
    double *c = calloc(nact, sizeof *c), *s = calloc(NP * NP, sizeof *s), *d = calloc(NP * NP, sizeof *d);
    swfs_dmfit_stats st;
    assert_ok(swfs_dmfit_apply(f, t, c, s, &st));
    const double rlo = rms(lo, mask), rhi = rms(hi, mask);
    assert_close(st.target_rms, sqrt(rlo * rlo + rhi * rhi), 0.01 * st.target_rms);
    assert_close(st.modal_rms, rlo, 0.01 * rlo);
    assert_close(st.filtered_rms, rhi, 0.01 * rhi);
    /* The DM reproduces the low orders to a few per cent, not the left-out high orders. */
    for (size_t k = 0; k < NP * NP; k++) d[k] = s[k] - lo[k];
    assert_true(rms(d, mask) < 0.03 * rlo);
    assert_true(st.fiterr_rms < 0.03 * rlo);
    assert_close(st.unfit_rms, rhi, 0.05 * rhi);
    /* Without the filter the fit follows the high orders too. */
    swfs_dmfit *f2 = NULL;
    o.modes = 0;
    assert_ok(swfs_dmfit_create(&f2, xy, nact, &g, NULL, &o));
    assert_ok(swfs_dmfit_apply(f2, t, c, s, &st));
    assert_true(st.unfit_rms < 0.25 * rhi);
    swfs_dmfit_free(f2);
    free(c);
    free(s);
    free(d);
    free(lo);
    free(hi);
    free(t);
    free(xy);
    swfs_dmfit_free(f);
}

static void test_not_covering(void **state)
{
    (void)state;
    swfs_geom g = geom(0.1);
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(4.0, 0.5, 0.0, &xy, &nact)); /* a 4 m DM for a 6.3 m pupil */
    swfs_dmfit *f = NULL;
    assert_int_equal(swfs_dmfit_create(&f, xy, nact, &g, NULL, NULL), SWFS_ERR_VALUE);
    assert_null(f);
    assert_non_null(strstr(swfs_last_error(), "do not cover the pupil"));
    /* with the rim continued (export_truth's fit) a DM that far short is still refused */
    swfs_dmfit_options o;
    swfs_dmfit_options_default(&o);
    o.rim = 1;
    assert_int_equal(swfs_dmfit_create(&f, xy, nact, &g, NULL, &o), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "by more than one actuator pitch"));
    free(xy);
    /* A DM whose hull misses the pupil's rim by less than its pitch (0.6 m; its outer ring at
     * r = 3 m, the pupil's rim at 3.15 m): refused by default; with the rim continued, a surface the DM makes is
     * fitted back exactly over the whole pupil, its rim included. */
    assert_ok(swfs_actuators_hexapolar(5.8, 0.6, 0.0, &xy, &nact));
    assert_int_equal(swfs_dmfit_create(&f, xy, nact, &g, NULL, NULL), SWFS_ERR_VALUE);
    o.influence = SWFS_INFLUENCE_CUBIC;
    o.reg = 0.0;
    assert_ok(swfs_dmfit_create(&f, xy, nact, &g, NULL, &o));
    double *mask = calloc(NP * NP, sizeof *mask), *c = calloc(nact, sizeof *c), *c2 = calloc(nact, sizeof *c2);
    double *s = calloc(NP * NP, sizeof *s), *s2 = calloc(NP * NP, sizeof *s2), *d = calloc(NP * NP, sizeof *d);
    assert_ok(swfs_aperture_make(mask, NP, DX, DIAM, 0.1, 0, 0.0));
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    for (size_t a = 0; a < nact; a++) c[a] = 50e-9 * swfs_rng_normal(&r);
    swfs_dmfit_surface(f, c, s);
    size_t rim = 0;
    for (size_t k = 0; k < NP * NP; k++) {
        const double x = ((double)(k % NP) - 0.5 * (NP - 1)) * DX, y = ((double)(k / NP) - 0.5 * (NP - 1)) * DX;
        rim += mask[k] > 0 && hypot(x, y) > 3.0;
    }
    swfs_dmfit_stats st;
    assert_ok(swfs_dmfit_apply(f, s, c2, s2, &st));
    for (size_t k = 0; k < NP * NP; k++) d[k] = s2[k] - s[k];
    print_message("rim continued: %zu pupil samples beyond r = 3 m; surface %.3g nm rms, fit residual %.3g nm\n", rim,
                  1e9 * rms(s, mask), 1e9 * rms(d, mask));
    assert_true(rim > 20 && rms(s, mask) > 10e-9 && rms(d, mask) < 1e-3 * rms(s, mask));
    free(mask); free(c); free(c2); free(s); free(s2); free(d);
    free(xy);
    swfs_dmfit_free(f);
}

/* ---- CLI -------------------------------------------------------------- */

/* A PUPIL.fits like `specklewfs pupil` writes (WFE with geometry, PUPIL); with_wfe = 0
 * leaves the WFE extension out. */
static void write_pupil_product(const char *path, const double *wfe, int with_wfe)
{
    swfs_geom g = geom(0.1);
    swfs_real *w = swfs_real_alloc(NP, NP, 1), *m = swfs_real_alloc(NP, NP, 1);
    assert_ok(swfs_aperture_make(m->data, NP, DX, DIAM, 0.1, 0, 0.0));
    for (size_t k = 0; k < NP * NP; k++) w->data[k] = m->data[k] > 0 ? wfe[k] : 0.0;
    swfs_fits_out *o = NULL;
    const char *prov[] = {"test_dmoffsets"};
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_set_stamp(o, &g, prov, 1));
    if (with_wfe) assert_ok(swfs_fits_out_real(o, "WFE", w, -64));
    assert_ok(swfs_fits_out_real(o, "PUPIL", m, -32));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(w);
    swfs_real_free(m);
}

static void test_cli(void **state)
{
    (void)state;
    char pup[1024], nowfe[1024], act[1024], small[1024], off[1024], args[4096], out[8192];
    snprintf(pup, sizeof pup, "%s", test_path("dmo_pupil.fits"));
    snprintf(nowfe, sizeof nowfe, "%s", test_path("dmo_nowfe.fits"));
    snprintf(act, sizeof act, "%s", test_path("dmo_act.fits"));
    snprintf(small, sizeof small, "%s", test_path("dmo_small_act.fits"));
    snprintf(off, sizeof off, "%s", test_path("dmo_offsets.fits"));
    double *wfe = calloc(NP * NP, sizeof *wfe);
    zernike_map(5, 120e-9, wfe);  /* astigmatism */
    zernike_map(9, -60e-9, wfe);  /* trefoil */
    write_pupil_product(pup, wfe, 1);
    write_pupil_product(nowfe, wfe, 0);
    double *xy = NULL;
    size_t nact = 0, nsmall = 0;
    assert_ok(swfs_actuators_hexapolar(5.0, 0.45, 0.0, &xy, &nsmall)); /* a 5 m DM */
    assert_ok(swfs_actuators_write(xy, nsmall, small));
    free(xy);
    assert_ok(swfs_actuators_hexapolar(DIAM, 0.45, DX, &xy, &nact));
    assert_ok(swfs_actuators_write(xy, nact, act));
    free(xy);

    /* Good run: OFFSETS of the right length, SURFACE = -WFE/2 inside the pupil. */
    snprintf(args, sizeof args, "dmoffsets %s -o %s --actuators %s", pup, off, act);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "unfittable"));
    swfs_real *o = NULL, *s = NULL, *m = NULL;
    swfs_geom g;
    assert_ok(swfs_fits_read_real(off, "OFFSETS", &o, &g));
    assert_int_equal(o->nx, nact);
    assert_close(g.pupdx, DX, 1e-12);
    assert_ok(swfs_fits_read_real(off, "SURFACE", &s, NULL));
    assert_ok(swfs_fits_read_real(off, "PUPIL", &m, NULL));
    double *d = calloc(NP * NP, sizeof *d);
    for (size_t k = 0; k < NP * NP; k++) d[k] = m->data[k] > 0 ? s->data[k] + 0.5 * wfe[k] : 0.0;
    double wrms = rms(wfe, m->data);
    assert_true(rms(d, m->data) < 0.02 * 0.5 * wrms);
    swfs_fits_in *fi = NULL;
    double unfit = NAN;
    assert_ok(swfs_fits_in_open(&fi, off, "OFFSETS"));
    assert_ok(swfs_fits_in_key_double(fi, "UNFITRMS", &unfit));
    swfs_fits_in_close(fi);
    assert_true(unfit < 0.02 * 0.5 * wrms);
    swfs_real_free(o);
    swfs_real_free(s);
    swfs_real_free(m);
    free(d);

    /* --modes 3 keeps only piston and tip/tilt: nothing of astigmatism + trefoil is fitted. */
    snprintf(args, sizeof args, "dmoffsets %s -o %s --hexapolar 0.45 --modes 3 --influence cubic", pup, off);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 0);
    assert_ok(swfs_fits_in_open(&fi, off, "OFFSETS"));
    double fitrms = NAN;
    assert_ok(swfs_fits_in_key_double(fi, "FITRMS", &fitrms));
    swfs_fits_in_close(fi);
    assert_true(fitrms < 0.05 * 0.5 * wrms);

    /* Bad inputs: clear one-line errors naming the file. */
    snprintf(args, sizeof args, "dmoffsets %s -o %s --actuators %s", nowfe, off, act);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 1);
    assert_non_null(strstr(out, "no WFE extension"));
    assert_non_null(strstr(out, "dmo_nowfe.fits"));
    snprintf(args, sizeof args, "dmoffsets %s -o %s --actuators %s", pup, off, small);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 1);
    assert_non_null(strstr(out, "do not cover the pupil"));
    assert_non_null(strstr(out, "dmo_small_act.fits"));
    snprintf(args, sizeof args, "dmoffsets %s -o %s", pup, off);
    assert_int_equal(test_run_cli(NULL, args, out, sizeof out), 2);
    assert_non_null(strstr(out, "--actuators"));
    free(wfe);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_known_surface_gauss),
        cmocka_unit_test(test_known_surface_cubic),
        cmocka_unit_test(test_modes),
        cmocka_unit_test(test_not_covering),
        cmocka_unit_test(test_cli),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

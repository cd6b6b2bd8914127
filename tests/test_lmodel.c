/* The generic linear speckle model (lmodel.h, swfs_pipeline_create_linear): the DM-grid
 * registration, the cubic resampling (exact for quadratics), and the speckles of a linear
 * model equal to the Shack-Hartmann pipeline's when the model is that pipeline written
 * linearly -- the actuators' interpolation as the basis and the reconstructor as the
 * control matrix (the two-stage engine form), or the reconstructed wavefront per slope as
 * a dense basis with the slopes as coefficients (the folded form) -- in every tip-tilt
 * mode; a control matrix with output points of its own (OUTXY) takes their interpolation as
 * its basis. Wrong units and bad shapes are refused with the values named. */
#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/lmodel.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/pupil.h"
#include "specklewfs/rng.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"
#include "../src/run/run_internal.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define NPUP 48
#define TELD 6.5
#define NSUB 8
#define NF 24

static swfs_geom geom(void)
{
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = 3.8e-6;
    g.teldiam = TELD;
    g.obscur = 0.1;
    g.pixscale = 0.25;
    g.pupdx = TELD / (NPUP - 2);
    g.pupn = NPUP;
    return g;
}

static void test_registration_round_trip(void **state)
{
    (void)state;
    const swfs_dm_registration r = {0.21, 0.13, -0.07, 0.4, 1};
    double worst = 0;
    for (double u = -1; u <= 50; u += 3.7)
        for (double v = -2; v <= 40; v += 4.1) {
            double x, y, u2, v2;
            swfs_dm_to_pupil(&r, 50, 41, u, v, &x, &y);
            swfs_pupil_to_dm(&r, 50, 41, x, y, &u2, &v2);
            worst = fmax(worst, fmax(fabs(u2 - u), fabs(v2 - v)));
        }
    assert_true(worst < 1e-12);
    /* The grid's centre is the offset; one step along the grid's x is the pitch, rotated and mirrored. */
    double x, y;
    swfs_dm_to_pupil(&r, 51, 41, 25, 20, &x, &y);
    assert_true(fabs(x - 0.13) < 1e-15 && fabs(y + 0.07) < 1e-15);
    swfs_dm_to_pupil(&r, 51, 41, 26, 20, &x, &y);
    assert_true(fabs(x - 0.13 + 0.21 * cos(0.4)) < 1e-15 && fabs(y + 0.07 + 0.21 * sin(0.4)) < 1e-15);
}

/* A quadratic of the pupil position sampled on a rotated, mirrored, offset DM grid comes back
 * exactly on the pupil samples inside the grid; samples beyond the grid are counted. */
static void test_grid_resampling_exact_for_quadratics(void **state)
{
    (void)state;
    const swfs_geom g = geom();
    double *mask = malloc(NPUP * NPUP * sizeof *mask);
    assert_ok(swfs_aperture_make(mask, NPUP, g.pupdx, g.teldiam, g.obscur, 0, 0));
    const size_t gx = 30, gy = 28, nk = 2;
    const swfs_dm_registration r = {0.29, 0.05, -0.11, 0.3, 1};
    double *cube = malloc(gx * gy * nk * sizeof *cube);
    for (size_t j = 0; j < gy; j++)
        for (size_t i = 0; i < gx; i++) {
            double x, y;
            swfs_dm_to_pupil(&r, gx, gy, (double)i, (double)j, &x, &y);
            cube[j * gx + i] = 1e-7 * (0.3 + x - 0.5 * y + 0.2 * x * x - 0.1 * x * y + 0.05 * y * y);
            cube[gx * gy + j * gx + i] = 0; /* a function that is zero: no nonzeros at all */
        }
    swfs_sparse *B = NULL;
    size_t nout = 0;
    assert_ok(swfs_basis_from_grid(&B, cube, gx, gy, nk, &r, mask, NPUP, g.pupdx, &nout));
    assert_int_equal(nout, 0);
    double c[2] = {1, 1}, *z = malloc(NPUP * NPUP * sizeof *z), worst = 0;
    swfs_sparse_apply(B, c, z);
    size_t nin = 0, nz1 = 0;
    for (size_t k = 0; k < B->nnz; k++) nz1 += B->col[k] == 1;
    for (size_t q = 0; q < NPUP; q++)
        for (size_t i = 0; i < NPUP; i++) {
            const size_t k = q * NPUP + i;
            if (!(mask[k] > 0)) { assert_true(z[k] == 0); continue; }
            const double x = ((double)i - 0.5 * (NPUP - 1)) * g.pupdx, y = ((double)q - 0.5 * (NPUP - 1)) * g.pupdx;
            double u, v;
            swfs_pupil_to_dm(&r, gx, gy, x, y, &u, &v);
            if (u < 1 || v < 1 || u > (double)gx - 2 || v > (double)gy - 2) continue; /* stencil clamped at the edge */
            nin++;
            worst = fmax(worst, fabs(z[k] - 1e-7 * (0.3 + x - 0.5 * y + 0.2 * x * x - 0.1 * x * y + 0.05 * y * y)));
        }
    printf("lmodel: quadratic through a rotated, mirrored DM grid: worst error %.2g m at %zu samples\n", worst, nin);
    assert_true(nin > 1000);
    assert_true(worst < 1e-19);
    assert_int_equal(nz1, 0);
    swfs_sparse_free(B);
    /* The same grid at half the pitch covers less than the pupil: the samples beyond it are counted. */
    const swfs_dm_registration small = {0.1, 0, 0, 0, 0};
    assert_ok(swfs_basis_from_grid(&B, cube, gx, gy, nk, &small, mask, NPUP, g.pupdx, &nout));
    assert_true(nout > 100);
    swfs_sparse_free(B);
    cube[5] = NAN;
    assert_int_equal(swfs_basis_from_grid(&B, cube, gx, gy, nk, &r, mask, NPUP, g.pupdx, &nout), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "x 5, y 0, function 0"));
    free(cube); free(z); free(mask);
}

/* Slopes of a random smooth residual (a few frames), and the SH pipeline with a given SVD reconstructor. */
typedef struct fixture {
    swfs_geom g;
    double *xy, *slopes, *mask;
    size_t nact, nslopes, nwfs;
    swfs_recon *rec;
} fixture;

static void fixture_make(fixture *f)
{
    f->g = geom();
    f->mask = malloc(NPUP * NPUP * sizeof *f->mask);
    assert_ok(swfs_aperture_make(f->mask, NPUP, f->g.pupdx, f->g.teldiam, f->g.obscur, 0, 0));
    assert_ok(swfs_actuators_hexapolar(TELD, 0.9, 0.2, &f->xy, &f->nact));
    f->nslopes = 2 * NSUB * NSUB;
    f->nwfs = 40;
    f->slopes = malloc(f->nwfs * f->nslopes * sizeof *f->slopes);
    /* the SVD reconstructor of the model's own D, taken as a given matrix */
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_SVD;
    swfs_pipeline *p = NULL;
    assert_ok(swfs_pipeline_create(&p, &f->g, NF, NF, f->xy, f->nact, f->mask, f->nslopes, NULL, NULL, 0, &o));
    const swfs_recon *r = swfs_pipeline_recon(p);
    /* slopes of smooth random actuator patterns (low orders with random weights, a little
     * actuator-scale texture) plus white noise: something a MAP reconstructor can learn */
    double *D = NULL, *za = malloc(f->nact * sizeof *za);
    assert_ok(swfs_interaction_matrix(swfs_pipeline_model(p)->wfs, swfs_pipeline_model(p)->T, &D));
    swfs_rng rng;
    swfs_rng_seed2(&rng, 7, 0);
    for (size_t t = 0; t < f->nwfs; t++) {
        double c[6];
        for (int k = 0; k < 6; k++) c[k] = 1e-7 * swfs_rng_normal(&rng);
        for (size_t a = 0; a < f->nact; a++) {
            const double x = f->xy[2 * a] / (TELD / 2), y = f->xy[2 * a + 1] / (TELD / 2);
            za[a] = c[0] * x + c[1] * y + c[2] * (2 * (x * x + y * y) - 1) + c[3] * (x * x - y * y) + c[4] * x * y +
                    c[5] * x * (x * x + y * y) + 2e-8 * swfs_rng_normal(&rng);
        }
        for (size_t s = 0; s < f->nslopes; s++) {
            double v = 0;
            for (size_t a = 0; a < f->nact; a++) v += D[s * f->nact + a] * za[a];
            f->slopes[t * f->nslopes + s] = v + (v != 0 ? 2e-9 * swfs_rng_normal(&rng) : 0);
        }
    }
    free(D);
    free(za);
    f->rec = calloc(1, sizeof *f->rec);
    f->rec->nact = r->nact;
    f->rec->nslopes = r->nslopes;
    f->rec->W = malloc(r->nact * r->nslopes * sizeof *f->rec->W);
    memcpy(f->rec->W, r->W, r->nact * r->nslopes * sizeof *f->rec->W);
    swfs_pipeline_free(p);
}

static void fixture_free(fixture *f)
{
    free(f->xy); free(f->slopes); free(f->mask);
    swfs_recon_free(f->rec);
}

/* Exposures of 3.5 WFS frames from a fractional start: the fields of pipeline a and b. */
static double field_difference(swfs_pipeline *a, swfs_pipeline *b, const fixture *f, double *peak)
{
    swfs_exposure sched[10];
    const size_t need = swfs_engine_schedule(3.5, 0.3, 10, sched);
    assert_true(need <= f->nwfs);
    swfs_complex *ha = malloc(10 * NF * NF * sizeof *ha), *hb = malloc(10 * NF * NF * sizeof *hb);
    assert_ok(swfs_pipeline_process(a, f->slopes, f->nwfs, sched, 10, ha));
    assert_ok(swfs_pipeline_process(b, f->slopes, f->nwfs, sched, 10, hb));
    double d = 0;
    *peak = 0;
    for (size_t k = 0; k < 10 * NF * NF; k++) {
        d = fmax(d, cabs(ha[k] - hb[k]));
        *peak = fmax(*peak, cabs(ha[k]));
    }
    free(ha); free(hb);
    return d;
}

static void test_linear_equals_shack_hartmann(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    const int modes[3] = {SWFS_TT_EXPOSURE, SWFS_TT_FRAME, SWFS_TT_KEEP};
    for (int m = 0; m < 3; m++) {
        swfs_pipeline_options o;
        swfs_pipeline_options_default(&o);
        o.recon = SWFS_RECON_GIVEN;
        o.tiptilt = modes[m];
        o.band = 0.5 * NSUB; /* the Shack-Hartmann default, given to the linear models too */
        swfs_pipeline *sh = NULL, *lin = NULL, *fold = NULL;
        assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, f.rec, NULL, 0, &o));
        /* SWFS_TT_FRAME projects the mean slopes out of W: take the matrix the SH pipeline uses */
        const swfs_recon *used = swfs_pipeline_recon(sh);
        const swfs_sparse *T = swfs_pipeline_model(sh)->T;
        /* (1) the interpolation as the basis, W as the control matrix: the two-stage form */
        swfs_linear_input in = {f.nslopes, T, used->W, NULL, 1.0, NULL, 0, 0};
        assert_ok(swfs_pipeline_create_linear(&lin, &f.g, NF, NF, f.mask, &in, f.slopes, f.nwfs, &o));
        swfs_pipeline_info li;
        swfs_pipeline_get_info(lin, &li);
        assert_int_equal(li.composed, 0);
        assert_int_equal(li.nbasis, f.nact);
        /* (2) T W e_s per slope as a dense basis, the slopes as coefficients: the folded form */
        const size_t ng = NPUP * NPUP, ns = f.nslopes;
        double *cube = calloc(ng * ns, sizeof *cube), *e = calloc(f.nact, sizeof *e), *z = malloc(ng * sizeof *z);
        for (size_t s = 0; s < ns; s++) {
            for (size_t a = 0; a < f.nact; a++) e[a] = used->W[a * ns + s];
            swfs_sparse_apply(T, e, z);
            memcpy(cube + s * ng, z, ng * sizeof *z);
        }
        swfs_sparse *B = NULL;
        assert_ok(swfs_basis_from_pupil(&B, cube, NPUP, ns, f.mask));
        swfs_linear_input in2 = {ns, B, NULL, NULL, 1.0, NULL, 0, 0};
        assert_ok(swfs_pipeline_create_linear(&fold, &f.g, NF, NF, f.mask, &in2, f.slopes, f.nwfs, &o));
        swfs_pipeline_get_info(fold, &li);
        assert_int_equal(li.composed, 1);
        assert_true(li.resid_rms > 1e-9 && li.resid_rms < 1e-5);
        /* SWFS_TT_FRAME removes each frame's tilt: the Shack-Hartmann pipeline the mean slopes
         * (the G-tilt, projected out of W), the linear model the Z-tilt of its wavefront (it
         * has no slopes); there the two linear forms are compared with each other. */
        double peak, d1 = field_difference(modes[m] == SWFS_TT_FRAME ? fold : sh, lin, &f, &peak);
        double d2 = field_difference(sh, fold, &f, &peak);
        printf("lmodel: tip-tilt mode %d: linear two-stage %.2g, folded %.2g of the peak; residual %.1f nm rms\n",
               modes[m], d1 / peak, d2 / peak, li.resid_rms * 1e9);
        /* single-precision engine: ~1e-6 of the peak */
        assert_true(d1 / peak < 2e-5);
        if (modes[m] != SWFS_TT_FRAME) assert_true(d2 / peak < 2e-5);
        swfs_sparse_free(B);
        free(cube); free(e); free(z);
        swfs_pipeline_free(sh); swfs_pipeline_free(lin); swfs_pipeline_free(fold);
    }
    fixture_free(&f);
}

/* A space-time control matrix (swfs_linear_input.nlags): lag blocks [W, 0] on the telemetry
 * stacked at lags 0 and 2 give the per-frame W's fields and mean reconstruction; [0, W] the
 * per-frame W's on the telemetry two frames on; the mean of a constant telemetry through
 * [W/2, W/2] is W's (swfs_pipeline_wavefront_of_mean at every lag); a width that is not a
 * multiple of the lags, or an interaction matrix with lags, refused. */
static void test_space_time_control(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_GIVEN;
    swfs_pipeline *sh = NULL;
    assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, f.rec, NULL, 0, &o));
    const swfs_recon *used = swfs_pipeline_recon(sh);
    const swfs_sparse *T = swfs_pipeline_model(sh)->T;
    const size_t ns = f.nslopes, na = f.nact, nw = f.nwfs;
    const long lags[2] = {0, 2};
    double *st = malloc(nw * 2 * ns * sizeof *st), *c0 = calloc(na * 2 * ns, sizeof *c0),
           *c1 = calloc(na * 2 * ns, sizeof *c1), *ch = calloc(na * 2 * ns, sizeof *ch);
    swfs_slopes_stack(f.slopes, nw, ns, lags, 2, 0, nw, st);
    for (size_t a = 0; a < na; a++)
        for (size_t i = 0; i < ns; i++) {
            c0[a * 2 * ns + i] = used->W[a * ns + i];
            c1[a * 2 * ns + ns + i] = used->W[a * ns + i];
            ch[a * 2 * ns + i] = ch[a * 2 * ns + ns + i] = 0.5 * used->W[a * ns + i];
        }
    swfs_pipeline *lin = NULL, *p0 = NULL, *p1 = NULL, *ph = NULL;
    swfs_linear_input in = {ns, T, used->W, NULL, 1.0, NULL, 0, 0};
    swfs_linear_input i0 = {2 * ns, T, c0, NULL, 1.0, NULL, 0, 2}, i1 = i0, ih = i0;
    i1.control = c1;
    ih.control = ch;
    assert_ok(swfs_pipeline_create_linear(&lin, &f.g, NF, NF, f.mask, &in, f.slopes, nw, &o));
    assert_ok(swfs_pipeline_create_linear(&p0, &f.g, NF, NF, f.mask, &i0, st, nw, &o));
    assert_ok(swfs_pipeline_create_linear(&p1, &f.g, NF, NF, f.mask, &i1, st, nw, &o));
    assert_ok(swfs_pipeline_create_linear(&ph, &f.g, NF, NF, f.mask, &ih, st, nw, &o));
    swfs_pipeline_info li;
    swfs_pipeline_get_info(p0, &li);
    assert_int_equal(li.nlags, 2);
    assert_int_equal(li.nslopes, 2 * ns);
    swfs_exposure sched[8];
    const size_t need = swfs_engine_schedule(3.5, 0.3, 8, sched);
    assert_true(need + 2 <= nw);
    const size_t nf2 = NF * NF, n = NPUP * NPUP;
    swfs_complex *ha = malloc(8 * nf2 * sizeof *ha), *hb = malloc(8 * nf2 * sizeof *hb);
    double d0 = 0, d1 = 0, peak = 0;
    assert_ok(swfs_pipeline_process(lin, f.slopes, need, sched, 8, ha));
    assert_ok(swfs_pipeline_process(p0, st, need, sched, 8, hb));
    for (size_t k = 0; k < 8 * nf2; k++) {
        d0 = fmax(d0, cabs(ha[k] - hb[k]));
        peak = fmax(peak, cabs(ha[k]));
    }
    double *ma = malloc(n * sizeof *ma), *mb = malloc(n * sizeof *mb), dm = 0, pm = 0;
    assert_ok(swfs_pipeline_mean_reconstruction(lin, ma));
    assert_ok(swfs_pipeline_mean_reconstruction(p0, mb));
    for (size_t i = 0; i < n; i++) {
        dm = fmax(dm, fabs(ma[i] - mb[i]));
        pm = fmax(pm, fabs(ma[i]));
    }
    /* [0, W]: the per-frame map two frames on */
    swfs_pipeline_mean_reset(lin);
    assert_ok(swfs_pipeline_process(lin, f.slopes + 2 * ns, need, sched, 8, ha));
    assert_ok(swfs_pipeline_process(p1, st, need, sched, 8, hb));
    for (size_t k = 0; k < 8 * nf2; k++) d1 = fmax(d1, cabs(ha[k] - hb[k]));
    /* the mean at every lag: [W/2, W/2] of a constant telemetry is W's */
    double dc = 0, pc = 0;
    assert_ok(swfs_pipeline_wavefront_of_mean(lin, f.slopes + 5 * ns, ns, ma));
    assert_ok(swfs_pipeline_wavefront_of_mean(ph, f.slopes + 5 * ns, ns, mb));
    for (size_t i = 0; i < n; i++) {
        dc = fmax(dc, fabs(ma[i] - mb[i]));
        pc = fmax(pc, fabs(ma[i]));
    }
    printf("lmodel: space-time control [W, 0] %.2g, [0, W] %.2g of the fields' peak; mean %.2g, of a constant %.2g\n",
           d0 / peak, d1 / peak, dm / pm, dc / pc);
    assert_true(peak > 0 && pm > 0 && pc > 0);
    assert_true(d0 / peak < 2e-5 && d1 / peak < 2e-5); /* the single-precision engine */
    assert_true(dm / pm < 1e-5 && dc / pc < 1e-5);
    /* refused: a width not a multiple of the lags; an interaction matrix with lags */
    swfs_pipeline *bad = NULL;
    swfs_linear_input odd = i0;
    odd.nmeas = 2 * ns + 1;
    assert_int_equal(swfs_pipeline_create_linear(&bad, &f.g, NF, NF, f.mask, &odd, NULL, 0, &o), SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "a multiple of 2 telemetry values"));
    assert_null(bad);
    swfs_clear_error();
    free(ha); free(hb); free(ma); free(mb); free(st); free(c0); free(c1); free(ch);
    swfs_pipeline_free(lin); swfs_pipeline_free(p0); swfs_pipeline_free(p1); swfs_pipeline_free(ph);
    swfs_pipeline_free(sh);
    fixture_free(&f);
}

/* The reconstruction's time mean (swfs_pipeline_mean_wavefront): over the exposures
 * processed, each its frames' weighted mean, it is T W s_bar with s_bar the mean of the
 * exposures' weighted mean slopes, piston, tip and tilt removed -- the same from the
 * Shack-Hartmann pipeline (tilt kept, or each exposure's tilt as its mean slopes) and from
 * the linear model written as that pipeline; none before an exposure, none after a reset. */
static void test_mean_wavefront(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    swfs_exposure sched[10];
    const size_t need = swfs_engine_schedule(3.5, 0.3, 10, sched);
    const size_t ns = f.nslopes, ng = NPUP * NPUP;
    double *sbar = calloc(ns, sizeof *sbar), *e = calloc(f.nact, sizeof *e), *want = malloc(ng * sizeof *want);
    double *got = malloc(ng * sizeof *got);
    for (size_t i = 0; i < 10; i++) {
        double wsum = 0;
        for (size_t k = 0; k < sched[i].count; k++)
            wsum += k == 0 ? sched[i].w_first : (k + 1 == sched[i].count ? sched[i].w_last : 1.0);
        for (size_t k = 0; k < sched[i].count; k++) {
            const double w = (k == 0 ? sched[i].w_first : (k + 1 == sched[i].count ? sched[i].w_last : 1.0)) / wsum;
            for (size_t s = 0; s < ns; s++) sbar[s] += w * f.slopes[(sched[i].first + k) * ns + s] / 10.0;
        }
    }
    assert_true(need <= f.nwfs);
    for (size_t a = 0; a < f.nact; a++)
        for (size_t s = 0; s < ns; s++) e[a] += f.rec->W[a * ns + s] * sbar[s];
    const int modes[2] = {SWFS_TT_KEEP, SWFS_TT_EXPOSURE};
    for (int m = 0; m < 2; m++) {
        swfs_pipeline_options o;
        swfs_pipeline_options_default(&o);
        o.recon = SWFS_RECON_GIVEN;
        o.tiptilt = modes[m];
        swfs_pipeline *sh = NULL, *lin = NULL;
        assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, ns, f.rec, NULL, 0, &o));
        const swfs_sparse *T = swfs_pipeline_model(sh)->T;
        swfs_linear_input in = {ns, T, f.rec->W, NULL, 1.0, NULL, 0, 0};
        assert_ok(swfs_pipeline_create_linear(&lin, &f.g, NF, NF, f.mask, &in, f.slopes, f.nwfs, &o));
        size_t nexp = 99;
        assert_int_equal(swfs_pipeline_mean_wavefront(sh, got, &nexp, NULL), SWFS_ERR_VALUE);
        assert_int_equal(nexp, 0);
        double peak;
        field_difference(sh, lin, &f, &peak);
        swfs_sparse_apply(T, e, want);
        const double rms = swfs_wfe_remove_ptt(want, f.mask, NPUP);
        swfs_pipeline *both[2] = {sh, lin};
        for (int b = 0; b < 2; b++) {
            assert_ok(swfs_pipeline_mean_wavefront(both[b], got, &nexp, NULL));
            assert_int_equal(nexp, 10);
            double d = 0;
            for (size_t k = 0; k < ng; k++) {
                if (f.mask[k] > 0) d = fmax(d, fabs(got[k] - want[k]));
                else assert_true(got[k] == 0.0);
            }
            printf("lmodel: time mean, tip-tilt mode %d, %s: %.1f nm rms, off by %.2g of it\n", modes[m],
                   b ? "linear" : "Shack-Hartmann", rms * 1e9, d / rms);
            assert_true(rms > 1e-9);
            assert_true(d / rms < 1e-4); /* single-precision engine */
        }
        swfs_pipeline_mean_reset(sh);
        assert_int_equal(swfs_pipeline_mean_wavefront(sh, got, &nexp, NULL), SWFS_ERR_VALUE);
        swfs_pipeline_free(sh);
        swfs_pipeline_free(lin);
    }
    free(sbar); free(e); free(want); free(got);
    fixture_free(&f);
}

/* The AO system's valid-subaperture map (pipeline options valid/valid_nsub): with the map the
 * illumination rule would make, slopes of the used subapertures only (2 nvalid values) give
 * the full layout's fields, whatever the reconstructor (given in the same narrow layout, or
 * learned from narrow training frames) and tip-tilt mode; the reconstructor comes back in
 * the narrow layout; a map may use a partly lit subaperture the rule drops, not a dark one. */
static void narrow(const double *full, size_t rows, size_t nfull, const unsigned char *valid, size_t nsa, double *out,
                   size_t nv)
{
    for (size_t r = 0; r < rows; r++)
        for (size_t a = 0, j = 0; a < nsa; a++)
            if (valid[a]) {
                out[r * 2 * nv + j] = full[r * nfull + a];
                out[r * 2 * nv + nv + j++] = full[r * nfull + nsa + a];
            }
}

static void test_valid_map(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    const size_t nsa = NSUB * NSUB;
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_GIVEN;
    swfs_pipeline *sh = NULL, *nv_p = NULL;
    assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, f.rec, NULL, 0, &o));
    unsigned char valid[NSUB * NSUB];
    memcpy(valid, swfs_pipeline_model(sh)->wfs->valid, nsa);
    const size_t nv = swfs_pipeline_model(sh)->wfs->nvalid, nn = 2 * nv;
    assert_true(nv > 20 && nv < nsa);
    swfs_pipeline_free(sh);
    double *ns = malloc(f.nwfs * nn * sizeof *ns);
    narrow(f.slopes, f.nwfs, f.nslopes, valid, nsa, ns, nv);
    swfs_recon rn = *f.rec;
    rn.nslopes = nn;
    rn.W = malloc(f.nact * nn * sizeof *rn.W);
    narrow(f.rec->W, f.nact, f.nslopes, valid, nsa, rn.W, nv);
    fixture fn = f;
    fn.slopes = ns;
    fn.nslopes = nn;
    const int modes[3] = {SWFS_TT_EXPOSURE, SWFS_TT_FRAME, SWFS_TT_KEEP};
    for (int m = 0; m < 4; m++) {
        swfs_pipeline_options_default(&o);
        o.recon = m < 3 ? SWFS_RECON_GIVEN : SWFS_RECON_VK;
        o.tiptilt = modes[m % 3];
        assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, m < 3 ? f.rec : NULL,
                                       m < 3 ? NULL : f.slopes, m < 3 ? 0 : f.nwfs, &o));
        o.valid = valid;
        o.valid_nsub = NSUB;
        /* m = 1: the full-layout reconstructor given with the valid-only slopes (a map `learn` made
         * on full-layout simulated slopes), the same as its used columns */
        assert_ok(swfs_pipeline_create(&nv_p, &f.g, NF, NF, f.xy, f.nact, f.mask, nn, m < 3 ? (m == 1 ? f.rec : &rn) : NULL,
                                       m < 3 ? NULL : ns, m < 3 ? 0 : f.nwfs, &o));
        swfs_pipeline_info info;
        swfs_pipeline_get_info(nv_p, &info);
        assert_int_equal(info.nsub, NSUB);
        assert_int_equal(info.nvalid, nv);
        assert_int_equal(info.nslopes, nn);
        /* the reconstructor in the telemetry's layout: the full one's used columns */
        const swfs_recon *rf = swfs_pipeline_recon(sh), *rv = swfs_pipeline_recon(nv_p);
        assert_int_equal(rv->nslopes, nn);
        double *w = malloc(f.nact * nn * sizeof *w), dw = 0, mw = 0;
        narrow(rf->W, f.nact, f.nslopes, valid, nsa, w, nv);
        for (size_t k = 0; k < f.nact * nn; k++) {
            dw = fmax(dw, fabs(w[k] - rv->W[k]));
            mw = fmax(mw, fabs(w[k]));
        }
        free(w);
        /* the fields: each pipeline on its own layout of the same frames */
        swfs_exposure sched[10];
        assert_true(swfs_engine_schedule(3.5, 0.3, 10, sched) <= f.nwfs);
        swfs_complex *ha = malloc(10 * NF * NF * sizeof *ha), *hb = malloc(10 * NF * NF * sizeof *hb);
        assert_ok(swfs_pipeline_process(sh, f.slopes, f.nwfs, sched, 10, ha));
        assert_ok(swfs_pipeline_process(nv_p, fn.slopes, f.nwfs, sched, 10, hb));
        double d = 0, peak = 0;
        for (size_t k = 0; k < 10 * NF * NF; k++) {
            d = fmax(d, cabs(ha[k] - hb[k]));
            peak = fmax(peak, cabs(ha[k]));
        }
        printf("lmodel: valid-only slopes (%zu of %zu), %s, tip-tilt %d: reconstructor %.2g, fields %.2g of the peak\n",
               nn, f.nslopes, m < 3 ? "given" : "vk", modes[m % 3], dw / mw, d / peak);
        assert_true(dw <= 1e-12 * mw);
        assert_true(d <= 1e-6 * peak);
        free(ha); free(hb);
        swfs_pipeline_free(sh); swfs_pipeline_free(nv_p);
    }
    /* a partly lit subaperture the 50 % rule drops is used when the map says so; a dark one is refused */
    swfs_shwfs *w0 = NULL, *w1 = NULL;
    assert_ok(swfs_shwfs_create(&w0, NSUB, TELD, f.mask, NPUP, f.g.pupdx, 0.0));
    size_t extra = nsa;
    for (size_t a = 0; a < nsa; a++)
        if (w0->valid[a] && !valid[a]) { extra = a; break; }
    assert_true(extra < nsa);
    unsigned char more[NSUB * NSUB];
    memcpy(more, valid, nsa);
    more[extra] = 1;
    assert_ok(swfs_shwfs_create_valid(&w1, NSUB, TELD, f.mask, NPUP, f.g.pupdx, more));
    assert_int_equal(w1->nvalid, nv + 1);
    assert_true(w1->S->row_ptr[extra + 1] > w1->S->row_ptr[extra]);
    assert_true(w1->S->row_ptr[nsa + extra + 1] > w1->S->row_ptr[nsa + extra]);
    for (size_t a = 0; a < nsa; a++)
        if (!more[a]) assert_true(w1->S->row_ptr[a + 1] == w1->S->row_ptr[a]);
    swfs_shwfs_free(w1);
    swfs_shwfs_free(w0);
    more[0] = 1; /* the corner (0, 0): outside the pupil */
    assert_int_equal(swfs_shwfs_create_valid(&w1, NSUB, TELD, f.mask, NPUP, f.g.pupdx, more), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "subaperture (0, 0)"));
    /* a width that is neither layout */
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_SVD;
    o.valid = valid;
    o.valid_nsub = NSUB;
    assert_int_equal(swfs_pipeline_create(&nv_p, &f.g, NF, NF, f.xy, f.nact, f.mask, nn + 2, NULL, NULL, 0, &o),
                     SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "or 128 (all, unused ones 0)"));
    free(ns);
    free(rn.W);
    fixture_free(&f);
}

static void test_linear_refusals(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    swfs_pipeline *sh = NULL, *p = NULL;
    o.recon = SWFS_RECON_GIVEN;
    assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, f.rec, NULL, 0, &o));
    const swfs_sparse *T = swfs_pipeline_model(sh)->T;
    /* um of DM surface taken as metres: a wavefront of kilometres */
    swfs_linear_input in = {f.nslopes, T, f.rec->W, NULL, 2e6, NULL, 0, 0};
    assert_int_equal(swfs_pipeline_create_linear(&p, &f.g, NF, NF, f.mask, &in, f.slopes, f.nwfs, &o), SWFS_ERR_VALUE);
    printf("lmodel: %s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "scale (2e+06)"));
    /* the coefficients of a basis of another size */
    swfs_linear_input bad = {f.nslopes + 1, T, NULL, NULL, 1.0, NULL, 0, 0};
    assert_int_equal(swfs_pipeline_create_linear(&p, &f.g, NF, NF, f.mask, &bad, NULL, 0, &o), SWFS_ERR_SHAPE);
    assert_non_null(strstr(swfs_last_error(), "129 telemetry values per frame taken as the coefficients of"));
    assert_null(p);
    swfs_pipeline_free(sh);
    fixture_free(&f);
}

/* An interaction matrix instead of a control matrix: the MAP reconstructor of it, learned
 * from the telemetry, gives the fields of the SH pipeline's own MAP reconstructor. */
static void test_interaction_matrix(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_MAP;
    /* tip-tilt kept: in the exposure mode the Shack-Hartmann pipeline also takes the frames'
     * tilt from their mean slopes (pipeline.c), which a generic linear model does not have */
    o.tiptilt = SWFS_TT_KEEP;
    o.band = 0.5 * NSUB; /* the Shack-Hartmann default, given to the linear model too */
    swfs_pipeline *sh = NULL, *lin = NULL;
    assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, f.nslopes, NULL, f.slopes, f.nwfs, &o));
    const swfs_speckle_model *m = swfs_pipeline_model(sh);
    double *D = NULL;
    assert_ok(swfs_interaction_matrix(m->wfs, m->T, &D));
    swfs_linear_input in = {f.nslopes, m->T, NULL, D, 1.0, NULL, 0, 0};
    assert_ok(swfs_pipeline_create_linear(&lin, &f.g, NF, NF, f.mask, &in, f.slopes, f.nwfs, &o));
    swfs_pipeline_info a, b;
    swfs_pipeline_get_info(sh, &a);
    swfs_pipeline_get_info(lin, &b);
    assert_int_equal(a.recon_modes, b.recon_modes);
    double peak, d = field_difference(sh, lin, &f, &peak);
    printf("lmodel: interaction matrix, MAP: %zu modes, fields differ by %.2g of the peak\n", b.recon_modes, d / peak);
    assert_true(d / peak < 2e-5);
    free(D);
    swfs_pipeline_free(sh); swfs_pipeline_free(lin);
    fixture_free(&f);
}

/* A basis on a DM grid in factored form (the grid's interpolation, the cube's values at the
 * grid points) is the resampled basis, and its pipeline gives the resampled basis' fields. */
static void test_factored_grid_basis(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    const size_t gx = 21, gy = 19, nk = 12, gn = gx * gy;
    const swfs_dm_registration r = {0.4, 0.02, -0.05, -0.2, 1};
    double *cube = malloc(gn * nk * sizeof *cube), *shapes = malloc(gn * nk * sizeof *shapes);
    swfs_rng rng;
    swfs_rng_seed2(&rng, 3, 0);
    for (size_t k = 0; k < gn * nk; k++) cube[k] = swfs_rng_normal(&rng);
    for (size_t q = 0; q < gn; q++)
        for (size_t k = 0; k < nk; k++) shapes[q * nk + k] = cube[k * gn + q];
    swfs_sparse *B = NULL, *T = NULL;
    size_t n1 = 0, n2 = 0;
    assert_ok(swfs_basis_from_grid(&B, cube, gx, gy, nk, &r, f.mask, NPUP, f.g.pupdx, &n1));
    assert_ok(swfs_grid_interp(&T, gx, gy, &r, f.mask, NPUP, f.g.pupdx, &n2));
    assert_int_equal(n1, n2);
    size_t maxrow = 0;
    for (size_t q = 0; q < T->nrows; q++) maxrow = T->row_ptr[q + 1] - T->row_ptr[q] > maxrow ? T->row_ptr[q + 1] - T->row_ptr[q] : maxrow;
    assert_true(maxrow <= 16);
    double *e = calloc(nk, sizeof *e), *z1 = malloc(NPUP * NPUP * sizeof *z1), *z2 = malloc(NPUP * NPUP * sizeof *z2);
    double *gv = malloc(gn * sizeof *gv), worst = 0;
    for (size_t k = 0; k < nk; k++) {
        e[k] = 1;
        swfs_sparse_apply(B, e, z1);
        e[k] = 0;
        for (size_t q = 0; q < gn; q++) gv[q] = shapes[q * nk + k];
        swfs_sparse_apply(T, gv, z2);
        for (size_t p = 0; p < NPUP * NPUP; p++) worst = fmax(worst, fabs(z1[p] - z2[p]));
    }
    assert_true(worst < 1e-12);
    /* the pipelines: random coefficients of the 12 functions as the telemetry */
    double *v = malloc(f.nwfs * nk * sizeof *v);
    for (size_t k = 0; k < f.nwfs * nk; k++) v[k] = 3e-8 * swfs_rng_normal(&rng);
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    swfs_pipeline *dense = NULL, *fact = NULL;
    swfs_linear_input a = {nk, B, NULL, NULL, 1.0, NULL, 0, 0}, b = {nk, T, NULL, NULL, 1.0, shapes, nk, 0};
    assert_ok(swfs_pipeline_create_linear(&dense, &f.g, NF, NF, f.mask, &a, v, f.nwfs, &o));
    assert_ok(swfs_pipeline_create_linear(&fact, &f.g, NF, NF, f.mask, &b, v, f.nwfs, &o));
    swfs_pipeline_info ia, ib;
    swfs_pipeline_get_info(dense, &ia);
    swfs_pipeline_get_info(fact, &ib);
    assert_int_equal(ib.nbasis, nk);
    assert_true(fabs(ia.resid_rms - ib.resid_rms) < 1e-9 * ia.resid_rms);
    swfs_exposure sched[10];
    assert_true(swfs_engine_schedule(3.5, 0.3, 10, sched) <= f.nwfs);
    swfs_complex *ha = malloc(10 * NF * NF * sizeof *ha), *hb = malloc(10 * NF * NF * sizeof *hb);
    assert_ok(swfs_pipeline_process(dense, v, f.nwfs, sched, 10, ha));
    assert_ok(swfs_pipeline_process(fact, v, f.nwfs, sched, 10, hb));
    double d = 0, peak = 0;
    for (size_t k = 0; k < 10 * NF * NF; k++) { d = fmax(d, cabs(ha[k] - hb[k])); peak = fmax(peak, cabs(ha[k])); }
    printf("lmodel: factored DM-grid basis: operator %.2g, fields %.2g of the peak (residual %.1f nm)\n", worst, d / peak,
           ib.resid_rms * 1e9);
    assert_true(d / peak < 2e-5);
    free(ha); free(hb); free(v); free(e); free(z1); free(z2); free(gv); free(cube); free(shapes);
    swfs_sparse_free(B);
    swfs_sparse_free(T);
    swfs_pipeline_free(dense);
    swfs_pipeline_free(fact);
    fixture_free(&f);
}

/* A control matrix with output points of its own (extension OUTXY: speckles' loops' map on a
 * grid finer than the DM, run_loops_map.c) gives the linear model their interpolation as its
 * basis in place of the one --basis names: the same fields as the basis file of those
 * functions with the plain matrix, and the same wavefront of given coefficients; the plain
 * matrix on that other basis is refused (its functions' count). */
static void write_cube(const char *path, double *data, size_t nx, size_t ny, size_t nz)
{
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, path));
    assert_ok(swfs_fits_out_real(o, NULL, &(swfs_real){nx, ny, nz, data}, -64));
    assert_ok(swfs_fits_out_commit(o));
}

static void test_control_points_basis(void **state)
{
    (void)state;
    fixture f;
    fixture_make(&f);
    const size_t ns = f.nslopes, ng = NPUP * NPUP;
    swfs_pipeline_options o;
    swfs_pipeline_options_default(&o);
    o.recon = SWFS_RECON_GIVEN;
    swfs_pipeline *sh = NULL, *pa = NULL, *pb = NULL;
    assert_ok(swfs_pipeline_create(&sh, &f.g, NF, NF, f.xy, f.nact, f.mask, ns, f.rec, NULL, 0, &o));
    const swfs_sparse *T = swfs_pipeline_model(sh)->T;
    double *cube = malloc(ng * f.nact * sizeof *cube), *eye = calloc(f.nact, sizeof *eye), *other = malloc(2 * ng * sizeof *other);
    for (size_t a = 0; a < f.nact; a++) {
        eye[a] = 1.0;
        swfs_sparse_apply(T, eye, cube + a * ng);
        eye[a] = 0.0;
    }
    for (size_t k = 0; k < 2 * ng; k++) other[k] = 1.0;
    char pbasis[4096], pother[4096], pc[4096], pcx[4096];
    snprintf(pbasis, sizeof pbasis, "%s", test_path("lmodel_pts_basis.fits"));
    snprintf(pother, sizeof pother, "%s", test_path("lmodel_pts_other.fits"));
    snprintf(pc, sizeof pc, "%s", test_path("lmodel_pts_c.fits"));
    snprintf(pcx, sizeof pcx, "%s", test_path("lmodel_pts_cxy.fits"));
    write_cube(pbasis, cube, NPUP, NPUP, f.nact);
    write_cube(pother, other, NPUP, NPUP, 2);
    assert_ok(swfs_recon_write(f.rec, pc));
    f.rec->oxy = f.xy; /* (borrowed for the write) */
    assert_ok(swfs_recon_write(f.rec, pcx));
    f.rec->oxy = NULL;
    swfs_linear_files a, b;
    swfs_linear_files_default(&a);
    swfs_linear_files_default(&b);
    a.basis = pbasis;
    a.control = pc;
    b.basis = pother;
    b.control = pcx;
    assert_ok(swfs_linear_pipeline(&pa, &a, &f.g, NF, NF, f.mask, ns, NULL, 0, &o));
    assert_ok(swfs_linear_pipeline(&pb, &b, &f.g, NF, NF, f.mask, ns, NULL, 0, &o));
    double peak;
    const double d = field_difference(pa, pb, &f, &peak);
    printf("lmodel: a control matrix's own points (OUTXY) as the basis: fields %.2g of the peak apart\n", d / peak);
    assert_true(peak > 0 && d < 1e-6 * peak);
    /* the wavefront of given coefficients through each */
    double *c = malloc(f.nact * sizeof *c), *wa = malloc(ng * sizeof *wa), *wb = malloc(ng * sizeof *wb);
    for (size_t k = 0; k < f.nact; k++) c[k] = 1e-8 * sin(0.37 * (double)k);
    assert_ok(swfs_linear_wavefront_(&a, &f.g, f.mask, c, f.nact, wa));
    assert_ok(swfs_linear_wavefront_(&b, &f.g, f.mask, c, f.nact, wb));
    double dw = 0, pw = 0;
    for (size_t k = 0; k < ng; k++) {
        dw = fmax(dw, fabs(wa[k] - wb[k]));
        pw = fmax(pw, fabs(wa[k]));
    }
    assert_true(pw > 0 && dw <= 1e-12 * pw);
    swfs_pipeline *px = NULL;
    b.control = pc;
    assert_int_equal(swfs_linear_pipeline(&px, &b, &f.g, NF, NF, f.mask, ns, NULL, 0, &o), SWFS_ERR_SHAPE);
    assert_null(px);
    swfs_pipeline_free(sh);
    swfs_pipeline_free(pa);
    swfs_pipeline_free(pb);
    free(cube); free(eye); free(other); free(c); free(wa); free(wb);
    fixture_free(&f);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_registration_round_trip),
        cmocka_unit_test(test_grid_resampling_exact_for_quadratics),
        cmocka_unit_test(test_linear_equals_shack_hartmann),
        cmocka_unit_test(test_space_time_control),
        cmocka_unit_test(test_mean_wavefront),
        cmocka_unit_test(test_linear_refusals),
        cmocka_unit_test(test_valid_map),
        cmocka_unit_test(test_interaction_matrix),
        cmocka_unit_test(test_factored_grid_basis),
        cmocka_unit_test(test_control_points_basis),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

/* Speckle-cube helpers (src/sensing/speckles.c): the registration-matched tip-tilt
 * (speckles.h, SWFS_TT_EXPOSURE). The extended reconstructor turns a frame's extra
 * columns into an exact tilt on the pupil grid while its first block reconstructs no
 * Z-tilt; swfs_speckles_expand copies every exposure's frames with their tip-tilt minus
 * the exposure's weighted mean. */
#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/engine.h"
#include "specklewfs/rng.h"
#include "specklewfs/sparse.h"
#include "specklewfs/speckles.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#define NPUP 66
#define PUPDX 0.1
#define TELD 6.5
#define NSUB 12

/* Least-squares plane p + cx x + cy y of a grid phase over the illuminated samples. */
static void fit_tilt(const double *z, const double *mask, double *cx, double *cy)
{
    double G[3][3] = {{0}}, r[3] = {0, 0, 0};
    for (size_t q = 0; q < NPUP; q++)
        for (size_t i = 0; i < NPUP; i++) {
            size_t k = q * NPUP + i;
            if (!(mask[k] > 0)) continue;
            double v[3] = {1, ((double)i - 0.5 * (NPUP - 1)) * PUPDX, ((double)q - 0.5 * (NPUP - 1)) * PUPDX};
            for (int u = 0; u < 3; u++) {
                r[u] += v[u] * z[k];
                for (int w = 0; w < 3; w++) G[u][w] += v[u] * v[w];
            }
        }
    /* Cramer's rule for the x and y coefficients. */
    double det = G[0][0] * (G[1][1] * G[2][2] - G[1][2] * G[2][1]) - G[0][1] * (G[1][0] * G[2][2] - G[1][2] * G[2][0]) +
                 G[0][2] * (G[1][0] * G[2][1] - G[1][1] * G[2][0]);
    *cx = (G[0][0] * (r[1] * G[2][2] - G[1][2] * r[2]) - r[0] * (G[1][0] * G[2][2] - G[1][2] * G[2][0]) +
           G[0][2] * (G[1][0] * r[2] - r[1] * G[2][0])) / det;
    *cy = (G[0][0] * (G[1][1] * r[2] - r[1] * G[2][1]) - G[0][1] * (G[1][0] * r[2] - r[1] * G[2][0]) +
           r[0] * (G[1][0] * G[2][1] - G[1][1] * G[2][0])) / det;
}

static void apply_ext(const double *W_ext, size_t nact, size_t ne, const double *s, const swfs_sparse *T, double *a, double *z)
{
    for (size_t k = 0; k < nact; k++) {
        double v = 0;
        for (size_t i = 0; i < ne; i++) v += W_ext[k * ne + i] * s[i];
        a[k] = v;
    }
    swfs_sparse_apply(T, a, z);
}

/* [W - C R | C]: the extra columns give z = tx x + ty y exactly on the illuminated grid;
 * the first block reconstructs no Z-tilt; R s is the Z-tilt of T W s. And the case that
 * broke the 0.5 lambda/D vibration time series: a frame with coma (its Z-tilt differs from
 * its mean slope, the G-tilt) alone in its exposure must come out with no tilt at all,
 * as a registered frame has it. With the mean slopes removed instead, its Z - G stayed. */
static void test_tilt_columns_exact(void **state)
{
    (void)state;
    double *mask = malloc(NPUP * NPUP * sizeof *mask), *xy = NULL, *W_ext = NULL, *R = NULL;
    size_t nact = 0;
    assert_ok(swfs_aperture_make(mask, NPUP, PUPDX, TELD, 0.1, 0, 0));
    assert_ok(swfs_actuators_hexapolar(TELD, 0.45, PUPDX, &xy, &nact));
    swfs_speckle_model *m = NULL;
    assert_ok(swfs_speckle_model_create(&m, xy, nact, mask, NPUP, PUPDX, TELD, NSUB, NULL, 1e-2, 0, 0));
    assert_int_equal(m->n_outside, 0);
    assert_ok(swfs_speckles_recon_tilt(m, xy, &W_ext, &R));
    const size_t ns = m->nslopes, ne = ns + 2;
    const double tx = 3e-7, ty = -2e-7;
    double *s = calloc(ne, sizeof *s), *a = calloc(nact, sizeof *a), *z = calloc(NPUP * NPUP, sizeof *z);
    double *zc = calloc(NPUP * NPUP, sizeof *zc);
    /* Extra columns alone: the exact plane. */
    s[ns] = tx;
    s[ns + 1] = ty;
    apply_ext(W_ext, nact, ne, s, m->T, a, z);
    double emax = 0, zmax = 0;
    for (size_t q = 0; q < NPUP; q++)
        for (size_t i = 0; i < NPUP; i++) {
            size_t k = q * NPUP + i;
            if (!(mask[k] > 0)) continue;
            double x = ((double)i - 0.5 * (NPUP - 1)) * PUPDX, y = ((double)q - 0.5 * (NPUP - 1)) * PUPDX;
            double t = tx * x + ty * y;
            emax = fmax(emax, fabs(z[k] - t));
            zmax = fmax(zmax, fabs(t));
            /* coma along x plus a tilt: Z-tilt and mean gradient differ */
            double r2 = (x * x + y * y) / (0.25 * TELD * TELD);
            zc[k] = 2e-7 * (3 * r2 - 2) * x / (0.5 * TELD) + 1e-7 * y / (0.5 * TELD);
        }
    assert_true(zmax > 5e-7);
    assert_true(emax < 1e-9 * zmax);
    /* A frame with coma: R s is the Z-tilt of T W s; the tilt-free block has none. */
    swfs_shwfs_measure(m->wfs, zc, s);
    double gx = 0, nv = 0; /* the mean x gradient G */
    for (size_t i = 0; i < ns / 2; i++)
        if (m->wfs->valid[i]) { gx += s[i]; nv++; }
    gx /= nv;
    swfs_recon_apply(m->recon, s, a);
    swfs_sparse_apply(m->T, a, z);
    double zx, zy;
    fit_tilt(z, mask, &zx, &zy);
    double rx = 0, ry = 0;
    for (size_t i = 0; i < ns; i++) { rx += R[i] * s[i]; ry += R[ns + i] * s[i]; }
    assert_close(rx, zx, 1e-9 * fabs(zx) + 1e-15);
    assert_close(ry, zy, 1e-9 * fabs(zy) + 1e-15);
    assert_true(fabs(zx - gx) > 0.05 * fabs(zx)); /* the test needs Z != G */
    /* One frame alone in its exposure: extra values t - tbar = 0. */
    s[ns] = s[ns + 1] = 0;
    apply_ext(W_ext, nact, ne, s, m->T, a, z);
    double cx, cy;
    fit_tilt(z, mask, &cx, &cy);
    assert_true(fabs(cx) < 1e-9 * fabs(zx));
    assert_true(fabs(cy) < 1e-9 * fabs(zx));
    free(s); free(a); free(z); free(zc); free(W_ext); free(R); free(xy); free(mask);
    swfs_speckle_model_free(m);
}

/* Every exposure gets its own copy of its frames; the extra columns are the frame's tilt
 * R s minus the exposure's weighted mean. */
static void test_expand(void **state)
{
    (void)state;
    enum { NS = 2 * 4 * 4, NW = 40, NE = 10 };
    double R[2 * NS];
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    for (size_t i = 0; i < 2 * NS; i++) R[i] = swfs_rng_normal(&r);
    double *sl = malloc(NW * NS * sizeof *sl);
    for (size_t k = 0; k < NW * NS; k++) sl[k] = swfs_rng_normal(&r);
    swfs_exposure sched[NE], sx[NE];
    size_t need = swfs_engine_schedule(2.5, 0.3, NE, sched);
    assert_true(need > 0 && need <= NW);
    size_t nx = swfs_speckles_expand_frames(sched, NE);
    assert_true(nx > need); /* shared frames are copied into both exposures */
    double *out = malloc(nx * (NS + 2) * sizeof *out);
    assert_ok(swfs_speckles_expand(sl, NS, need, R, sched, NE, out, sx));
    size_t k = 0;
    for (size_t j = 0; j < NE; j++) {
        assert_int_equal(sx[j].first, k);
        assert_int_equal(sx[j].count, sched[j].count);
        assert_close(sx[j].w_first, sched[j].w_first, 0);
        assert_close(sx[j].w_last, sched[j].w_last, 0);
        double s0x = 0, s0y = 0;
        for (size_t q = 0; q < sched[j].count; q++) {
            const double *o = out + (k + q) * (NS + 2), *in = sl + (sched[j].first + q) * NS;
            assert_memory_equal(o, in, NS * sizeof *o);
            double mx = 0, my = 0;
            for (size_t i = 0; i < NS; i++) { mx += R[i] * in[i]; my += R[NS + i] * in[i]; }
            double w = q == 0 ? sched[j].w_first : (q + 1 == sched[j].count ? sched[j].w_last : 1.0);
            /* o[NS] = mx - mean: the weighted sum of the extra columns vanishes. */
            s0x += w * o[NS];
            s0y += w * o[NS + 1];
            if (q > 0) {
                const double *p = out + (k + q - 1) * (NS + 2), *pin = sl + (sched[j].first + q - 1) * NS;
                double px = 0, py = 0;
                for (size_t i = 0; i < NS; i++) { px += R[i] * pin[i]; py += R[NS + i] * pin[i]; }
                assert_close(o[NS] - p[NS], mx - px, 1e-12);
                assert_close(o[NS + 1] - p[NS + 1], my - py, 1e-12);
            }
        }
        assert_close(s0x, 0, 1e-12);
        assert_close(s0y, 0, 1e-12);
        k += sched[j].count;
    }
    assert_int_equal(k, nx);
    /* An exposure beyond the slopes is an error. */
    assert_int_equal(swfs_speckles_expand(sl, NS, need - 1, R, sched, NE, out, sx), SWFS_ERR_VALUE);
    free(sl); free(out);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_tilt_columns_exact),
        cmocka_unit_test(test_expand),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

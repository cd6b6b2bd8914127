/* Speckle-cube helpers (src/sensing/speckles.c): the registration-matched tip-tilt
 * (speckles.h, SWFS_TT_EXPOSURE). The extended reconstructor turns a frame's extra
 * columns into an exact tilt on the pupil grid while the projected W ignores the mean
 * slopes; swfs_speckles_expand copies every exposure's frames with their tip-tilt minus
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

/* [W | x_a | y_a] applied to [s, tx, ty] with s a pure tilt (the same slope in every valid
 * subaperture) plus the tilt itself in the extra columns: the projected W sees nothing,
 * the tilt columns give z = tx x + ty y exactly on the illuminated grid. */
static void test_tilt_columns_exact(void **state)
{
    (void)state;
    double *mask = malloc(NPUP * NPUP * sizeof *mask), *xy = NULL, *W_ext = NULL;
    size_t nact = 0;
    assert_ok(swfs_aperture_make(mask, NPUP, PUPDX, TELD, 0.1, 0, 0));
    assert_ok(swfs_actuators_hexapolar(TELD, 0.45, PUPDX, &xy, &nact));
    swfs_speckle_model *m = NULL;
    assert_ok(swfs_speckle_model_create(&m, xy, nact, mask, NPUP, PUPDX, TELD, NSUB, NULL, 1e-2, 0, 1));
    assert_int_equal(m->n_outside, 0);
    assert_ok(swfs_speckles_recon_tilt(m->recon, xy, &W_ext));
    const size_t ns = m->nslopes, ne = ns + 2, nh = ns / 2;
    const double tx = 3e-7, ty = -2e-7;
    double *s = calloc(ne, sizeof *s), *a = calloc(nact, sizeof *a), *z = calloc(NPUP * NPUP, sizeof *z);
    for (size_t i = 0; i < nh; i++)
        if (m->wfs->valid[i]) { s[i] = tx; s[nh + i] = ty; }
    s[ns] = tx;
    s[ns + 1] = ty;
    for (size_t k = 0; k < nact; k++) {
        double v = 0;
        for (size_t i = 0; i < ne; i++) v += W_ext[k * ne + i] * s[i];
        a[k] = v;
    }
    swfs_sparse_apply(m->T, a, z);
    double emax = 0, zmax = 0;
    for (size_t q = 0; q < NPUP; q++)
        for (size_t i = 0; i < NPUP; i++) {
            size_t k = q * NPUP + i;
            if (!(mask[k] > 0)) continue;
            double x = ((double)i - 0.5 * (NPUP - 1)) * PUPDX, y = ((double)q - 0.5 * (NPUP - 1)) * PUPDX;
            double t = tx * x + ty * y;
            emax = fmax(emax, fabs(z[k] - t));
            zmax = fmax(zmax, fabs(t));
        }
    assert_true(zmax > 5e-7);
    assert_true(emax < 1e-9 * zmax);
    free(s); free(a); free(z); free(W_ext); free(xy); free(mask);
    swfs_speckle_model_free(m);
}

/* Every exposure gets its own copy of its frames; the extra columns are the frame's mean
 * x / y slope over the valid subapertures minus the exposure's weighted mean. */
static void test_expand(void **state)
{
    (void)state;
    enum { NS = 2 * 4 * 4, NW = 40, NE = 10 };
    unsigned char valid[NS / 2];
    for (size_t i = 0; i < NS / 2; i++) valid[i] = (i % 5) != 0;
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    double *sl = malloc(NW * NS * sizeof *sl);
    for (size_t k = 0; k < NW * NS; k++) sl[k] = swfs_rng_normal(&r);
    swfs_exposure sched[NE], sx[NE];
    size_t need = swfs_engine_schedule(2.5, 0.3, NE, sched);
    assert_true(need > 0 && need <= NW);
    size_t nx = swfs_speckles_expand_frames(sched, NE);
    assert_true(nx > need); /* shared frames are copied into both exposures */
    double *out = malloc(nx * (NS + 2) * sizeof *out);
    assert_ok(swfs_speckles_expand(sl, NS, need, valid, sched, NE, out, sx));
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
            double mx = 0, my = 0, n = 0;
            for (size_t i = 0; i < NS / 2; i++)
                if (valid[i]) { mx += in[i]; my += in[NS / 2 + i]; n++; }
            mx /= n; my /= n;
            double w = q == 0 ? sched[j].w_first : (q + 1 == sched[j].count ? sched[j].w_last : 1.0);
            /* o[NS] = mx - mean: the weighted sum of the extra columns vanishes. */
            s0x += w * o[NS];
            s0y += w * o[NS + 1];
            if (q > 0) {
                const double *p = out + (k + q - 1) * (NS + 2), *pin = sl + (sched[j].first + q - 1) * NS;
                double px = 0, py = 0;
                for (size_t i = 0; i < NS / 2; i++)
                    if (valid[i]) { px += pin[i]; py += pin[NS / 2 + i]; }
                assert_close(o[NS] - p[NS], mx - px / n, 1e-12);
                assert_close(o[NS + 1] - p[NS + 1], my - py / n, 1e-12);
            }
        }
        assert_close(s0x, 0, 1e-12);
        assert_close(s0y, 0, 1e-12);
        k += sched[j].count;
    }
    assert_int_equal(k, nx);
    /* An exposure beyond the slopes is an error. */
    assert_int_equal(swfs_speckles_expand(sl, NS, need - 1, valid, sched, NE, out, sx), SWFS_ERR_VALUE);
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

/* WFS model: Clough-Tocher interpolation exactness, Shack-Hartmann slopes, SVD
 * reconstructor recovering known low-order modes, tip-tilt projection, FITS files, the white
 * slope noise from the slopes, the DM modes of one system and of another. */
#include "testutil.h"

#include "specklewfs/interp.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

static double poly2(double x, double y, int which)
{
    switch (which) {
    case 0: return 0.3 - 1.2 * x + 0.7 * y;                                     /* plane */
    case 1: return 0.1 + 0.4 * x - 0.2 * y + 0.9 * x * x - 0.5 * x * y + 0.3 * y * y; /* quadratic */
    default: return 2.0 * (x * x + y * y) - 1.0;                                 /* focus */
    }
}

static void check_exact(const double *pts, size_t n, double span)
{
    swfs_rng rng;
    swfs_rng_seed(&rng, 7);
    enum { NQ = 400 };
    double qx[NQ], qy[NQ];
    for (size_t q = 0; q < NQ; q++) {
        /* Inside the disc of radius 0.8 span: inside the hull of both layouts below. */
        double r = 0.8 * span * sqrt(swfs_rng_uniform(&rng)), t = 2 * M_PI * swfs_rng_uniform(&rng);
        qx[q] = r * cos(t); qy[q] = r * sin(t);
    }
    swfs_sparse *T = NULL;
    size_t outside = 99;
    assert_ok(swfs_interp_ct_points(pts, n, qx, qy, NQ, &T, &outside));
    assert_int_equal(outside, 0);
    double *f = malloc(n * sizeof *f), out[NQ];
    for (int which = 0; which < 3; which++) {
        for (size_t i = 0; i < n; i++) f[i] = poly2(pts[2 * i], pts[2 * i + 1], which);
        swfs_sparse_apply(T, f, out);
        double maxerr = 0;
        for (size_t q = 0; q < NQ; q++) maxerr = fmax(maxerr, fabs(out[q] - poly2(qx[q], qy[q], which)));
        assert_true(maxerr < 1e-9);
    }
    /* A cubic is not reproduced exactly, but closely (the element is C1 cubic). */
    for (size_t i = 0; i < n; i++) f[i] = pow(pts[2 * i], 3);
    swfs_sparse_apply(T, f, out);
    double maxerr = 0;
    for (size_t q = 0; q < NQ; q++) maxerr = fmax(maxerr, fabs(out[q] - pow(qx[q], 3)));
    assert_true(maxerr > 1e-12 && maxerr < 0.05 * span * span * span);
    free(f);
    swfs_sparse_free(T);
}

static void test_interp_exact_quadratics(void **state)
{
    (void)state;
    /* Scattered random points in a disc plus a ring to make the hull round. */
    enum { NR = 150, NB = 24 };
    double pts[2 * (NR + NB)];
    swfs_rng rng;
    swfs_rng_seed(&rng, 3);
    for (size_t i = 0; i < NR; i++) {
        double r = sqrt(swfs_rng_uniform(&rng)), t = 2 * M_PI * swfs_rng_uniform(&rng);
        pts[2 * i] = r * cos(t); pts[2 * i + 1] = r * sin(t);
    }
    for (size_t i = 0; i < NB; i++) {
        pts[2 * (NR + i)] = 1.05 * cos(2 * M_PI * (double)i / NB);
        pts[2 * (NR + i) + 1] = 1.05 * sin(2 * M_PI * (double)i / NB);
    }
    check_exact(pts, NR + NB, 1.0);
    /* The hexapolar actuator layout (co-circular rings: a degenerate Delaunay case). */
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(6.5, 0.45, 0.05, &xy, &nact));
    assert_true(nact > 150 && nact < 400);
    check_exact(xy, nact, 3.25);
    free(xy);
    /* Square grids clipped to a circle (co-circular squares; vertices whose Delaunay
     * neighbours lie on two lines): exact for quadratics too. Pitch D/20 with a margin of a
     * full pitch once failed with "neighbours do not determine a quadratic". */
    const double pitches[3] = {6.5 / 20, 6.5 / 16, 0.36}, margins[3] = {6.5 / 20, 0.5 * 6.5 / 16, 0.1};
    for (int k = 0; k < 3; k++) {
        assert_ok(swfs_actuators_square(6.5, pitches[k], margins[k], &xy, &nact));
        assert_true(nact > 100);
        check_exact(xy, nact, 3.25 - pitches[k]);
        free(xy);
    }
}

static void test_interp_outside_and_bad(void **state)
{
    (void)state;
    double pts[] = {0, 0, 1, 0, 0, 1, 1, 1, 0.5, 0.5, 0.2, 0.7};
    double qx[] = {0.5, 2.0}, qy[] = {0.5, 2.0};
    swfs_sparse *T = NULL;
    size_t outside = 0;
    assert_ok(swfs_interp_ct_points(pts, 6, qx, qy, 2, &T, &outside));
    assert_int_equal(outside, 1);
    assert_int_equal(T->row_ptr[2] - T->row_ptr[1], 0);
    swfs_sparse_free(T);
    double line[] = {0, 0, 1, 1, 2, 2, 3, 3};
    assert_int_not_equal(swfs_interp_ct_points(line, 4, qx, qy, 2, &T, NULL), 0);
    assert_null(T);
    assert_int_not_equal(swfs_interp_ct_points(pts, 2, qx, qy, 2, &T, NULL), 0);
}

/* Gaussian influence functions: at an actuator's own sample the row holds 1 for it, the
 * coupling c for its four neighbours one pitch away, c^2 for the four diagonal ones, nothing
 * from the next ring (c^4 under the 1e-3 cut at c = 0.15); the pitch is the actuators' own;
 * samples outside the mask get empty rows; bad couplings are refused. */
static void test_influence_gauss(void **state)
{
    (void)state;
    enum { NA = 7, NPUP = 33 };
    const double d = 0.2, dx = 0.05, c = 0.15;
    double pts[2 * NA * NA], mask[NPUP * NPUP];
    for (int j = 0; j < NA; j++)
        for (int i = 0; i < NA; i++) {
            pts[2 * (j * NA + i)] = (i - NA / 2) * d;
            pts[2 * (j * NA + i) + 1] = (j - NA / 2) * d;
        }
    for (int k = 0; k < NPUP * NPUP; k++) mask[k] = k % NPUP == 0 ? 0 : 1; /* the first column dark */
    swfs_sparse *T = NULL;
    assert_ok(swfs_influence_gauss_grid(pts, NA * NA, NPUP, dx, mask, c, &T));
    assert_int_equal(T->nrows, NPUP * NPUP);
    assert_int_equal(T->ncols, NA * NA);
    const size_t centre = (NPUP / 2) * NPUP + NPUP / 2, act = (NA / 2) * NA + NA / 2; /* both at (0, 0) */
    assert_int_equal(T->row_ptr[centre + 1] - T->row_ptr[centre], 9);
    double w1 = 0, wn = 0, wd = 0;
    for (size_t q = T->row_ptr[centre]; q < T->row_ptr[centre + 1]; q++) {
        const long di = labs((long)(T->col[q] % NA) - NA / 2), dj = labs((long)(T->col[q] / NA) - NA / 2);
        if (T->col[q] == act) w1 = T->val[q];
        else if (di + dj == 1) wn += T->val[q];
        else if (di == 1 && dj == 1) wd += T->val[q];
        else fail_msg("actuator %zu beyond the diagonal neighbours in the centre's row", T->col[q]);
    }
    assert_true(fabs(w1 - 1) < 1e-12);
    assert_true(fabs(wn - 4 * c) < 1e-12);
    assert_true(fabs(wd - 4 * c * c) < 1e-12);
    for (size_t r = 0; r < NPUP; r++) /* the dark column's rows */
        assert_int_equal(T->row_ptr[r * NPUP + 1] - T->row_ptr[r * NPUP], 0);
    swfs_sparse_free(T);
    T = NULL;
    const double bad[] = {0, 1, -0.1, NAN};
    for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
        assert_int_not_equal(swfs_influence_gauss_grid(pts, NA * NA, NPUP, dx, mask, bad[k], &T), 0);
        assert_null(T);
    }
    assert_int_not_equal(swfs_influence_gauss_grid(pts, 1, NPUP, dx, mask, c, &T), 0);
}

/* Circular pupil with a central obstruction on the DESIGN.md grid. */
/* Piston-removed rms of a - b over the mask. */
static double rms_diff(const double *a, const double *b, const double *mask, size_t n)
{
    double s = 0, s2 = 0, c = 0;
    for (size_t i = 0; i < n; i++)
        if (mask[i] > 0) { double d = a[i] - (b ? b[i] : 0); s += d; s2 += d * d; c++; }
    return sqrt(s2 / c - (s / c) * (s / c));
}

static void test_shwfs_and_reconstructor(void **state)
{
    (void)state;
    const double D = 6.5;
    const size_t npup = 66, nsub = 12;
    const double dx = D / 64.0;
    double *mask = test_annulus(npup, dx, D, 0.1);
    swfs_shwfs *w = NULL;
    assert_ok(swfs_shwfs_create(&w, nsub, D, mask, npup, dx, 0.5));
    assert_int_equal(w->nslopes, 288);
    assert_true(w->nvalid > 90 && w->nvalid < 144);

    /* Slopes of a pure tilt z = a x are a in every valid x slope, 0 in y. */
    size_t ng = npup * npup;
    double *z = malloc(ng * sizeof *z), *z2 = malloc(ng * sizeof *z2), s[288];
    for (size_t q = 0; q < npup; q++)
        for (size_t p = 0; p < npup; p++) z[q * npup + p] = 2e-7 * ((double)p - 0.5 * (double)(npup - 1)) * dx;
    swfs_shwfs_measure(w, z, s);
    for (size_t i = 0; i < 144; i++) {
        assert_close(s[i], w->valid[i] ? 2e-7 : 0.0, 1e-18);
        assert_close(s[144 + i], 0.0, 1e-18);
    }

    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(D, 0.45, dx, &xy, &nact));
    swfs_sparse *T = NULL;
    size_t outside = 1;
    assert_ok(swfs_interp_ct_grid(xy, nact, npup, dx, mask, &T, &outside));
    assert_int_equal(outside, 0);
    double *Dm = NULL;
    assert_ok(swfs_interaction_matrix(w, T, &Dm));
    swfs_recon *r = NULL;
    assert_ok(swfs_recon_svd(Dm, w->nslopes, nact, 1e-3, 0, &r));
    assert_true(r->nmodes > 100);
    assert_true(r->sv[0] >= r->sv[r->nmodes - 1]);

    /* Low-order modes (focus, astigmatism, coma, trefoil) sampled on the grid: their
     * slopes reconstruct to the same wavefront through W and T. */
    double *act = malloc(nact * sizeof *act);
    for (int mode = 0; mode < 4; mode++) {
        for (size_t q = 0; q < npup; q++)
            for (size_t p = 0; p < npup; p++) {
                double x = ((double)p - 0.5 * (double)(npup - 1)) * dx / (0.5 * D);
                double y = ((double)q - 0.5 * (double)(npup - 1)) * dx / (0.5 * D);
                double rr = x * x + y * y, v;
                if (mode == 0) v = 2 * rr - 1;
                else if (mode == 1) v = x * x - y * y;
                else if (mode == 2) v = (3 * rr - 2) * x;
                else v = x * x * x - 3 * x * y * y;
                z[q * npup + p] = 1e-7 * v;
            }
        swfs_shwfs_measure(w, z, s);
        swfs_recon_apply(r, s, act);
        swfs_sparse_apply(T, act, z2);
        double err = rms_diff(z2, z, mask, ng), ref = rms_diff(z, NULL, mask, ng);
        assert_true(err < 0.05 * ref);
    }

    /* Tip-tilt projection: a tilt reconstructs to (almost) nothing, focus survives. */
    swfs_recon *rt = NULL;
    assert_ok(swfs_recon_svd(Dm, w->nslopes, nact, 1e-3, 0, &rt));
    assert_ok(swfs_recon_project_tiptilt(rt, w->valid));
    for (size_t q = 0; q < npup; q++)
        for (size_t p = 0; p < npup; p++)
            z[q * npup + p] = 1e-7 * (((double)p - 0.5 * (double)(npup - 1)) - 0.5 * ((double)q - 0.5 * (double)(npup - 1))) * dx;
    swfs_shwfs_measure(w, z, s);
    double s2[288];
    memcpy(s2, s, sizeof s);
    swfs_slopes_remove_tiptilt(s2, 288, w->valid);
    for (size_t i = 0; i < 288; i++) assert_close(s2[i], 0.0, 1e-20);
    swfs_recon_apply(rt, s, act);
    swfs_sparse_apply(T, act, z2);
    assert_true(rms_diff(z2, NULL, mask, ng) < 1e-3 * rms_diff(z, NULL, mask, ng));

    /* The surface on the pupil's samples only (swfs_sparse_apply_rows): the same values to the
     * bit there, every other entry left as it was. */
    size_t *rows = malloc(ng * sizeof *rows), nrows = 0;
    double *z3 = malloc(ng * sizeof *z3);
    assert_non_null(rows);
    assert_non_null(z3);
    for (size_t g = 0; g < ng; g++) {
        if (mask[g] > 0) rows[nrows++] = g;
        z3[g] = -7.0;
    }
    swfs_sparse_apply_rows(T, act, rows, nrows, z3);
    for (size_t g = 0, k = 0; g < ng; g++) {
        if (k < nrows && rows[k] == g) {
            assert_memory_equal(&z3[g], &z2[g], sizeof z3[g]);
            k++;
        } else {
            assert_true(z3[g] == -7.0);
        }
    }
    assert_true(nrows > 0 && nrows < ng);
    free(rows);
    free(z3);

    /* Mode-count cut. */
    swfs_recon *r56 = NULL;
    assert_ok(swfs_recon_svd(Dm, w->nslopes, nact, 0.0, 56, &r56));
    assert_int_equal(r56->nmodes, 56);

    /* FITS round trip, and a wrong-shape actuator file. */
    assert_ok(swfs_recon_write(r, test_path("recon.fits")));
    swfs_recon *rr = NULL;
    assert_ok(swfs_recon_read(test_path("recon.fits"), &rr));
    assert_int_equal(rr->nact, nact);
    assert_int_equal(rr->nslopes, 288);
    assert_memory_equal(rr->W, r->W, nact * 288 * sizeof(double));
    assert_ok(swfs_actuators_write(xy, nact, test_path("act.fits")));
    double *xy2 = NULL;
    size_t n2 = 0;
    assert_ok(swfs_actuators_read(test_path("act.fits"), &xy2, &n2));
    assert_int_equal(n2, nact);
    assert_memory_equal(xy2, xy, 2 * nact * sizeof(double));
    free(xy2);
    xy2 = NULL;
    assert_int_not_equal(swfs_actuators_read(test_path("recon.fits"), &xy2, &n2), 0);
    assert_non_null(strstr(swfs_last_error(), "2 x nact"));

    free(xy2); swfs_recon_free(rr); swfs_recon_free(r56); swfs_recon_free(rt); swfs_recon_free(r);
    free(Dm); free(act); free(z); free(z2); free(xy); free(mask);
    swfs_sparse_free(T);
    swfs_shwfs_free(w);
}

/* The white slope noise from the slopes alone (swfs_slopes_white_noise): a pattern of many
 * spatial frequencies, up to twice the subapertures' cutoff (so that the slopes carry the
 * aliased part that has curl), moving 0.1 subaperture per frame, measured by the
 * Shack-Hartmann with white noise of known rms added: the estimate comes out within 10 % of it,
 * from a noise well below the pattern's slopes to one above them, and close to 0 without. */
static void test_white_noise(void **state)
{
    (void)state;
    const double D = 6.5, dx = D / 64.0, d = D / 12.0;
    const size_t npup = 66, nsub = 12, nf = 200, ns = 2 * nsub * nsub, NC = 24;
    double *mask = test_annulus(npup, dx, D, 0.1);
    swfs_shwfs *w = NULL;
    assert_ok(swfs_shwfs_create(&w, nsub, D, mask, npup, dx, 0.5));
    double kx[NC], ky[NC], amp[NC], ph[NC];
    swfs_rng rng;
    swfs_rng_seed(&rng, 11);
    for (size_t m = 0; m < NC; m++) {
        const double k = (0.2 + 1.8 * swfs_rng_uniform(&rng)) * M_PI / d, t = 2 * M_PI * swfs_rng_uniform(&rng);
        kx[m] = k * cos(t);
        ky[m] = k * sin(t);
        amp[m] = 3e-8 * pow(k * d / M_PI, -11.0 / 6.0);
        ph[m] = 2 * M_PI * swfs_rng_uniform(&rng);
    }
    double *z = malloc(npup * npup * sizeof *z), *clean = malloc(nf * ns * sizeof *clean), *s = malloc(nf * ns * sizeof *s);
    assert_non_null(z); assert_non_null(clean); assert_non_null(s);
    double sig2 = 0;
    for (size_t t = 0; t < nf; t++) {
        const double shift = 0.1 * d * (double)t;
        for (size_t q = 0; q < npup; q++)
            for (size_t p = 0; p < npup; p++) {
                const double x = (double)p * dx - shift, y = (double)q * dx;
                double v = 0;
                for (size_t m = 0; m < NC; m++) v += amp[m] * cos(kx[m] * x + ky[m] * y + ph[m]);
                z[q * npup + p] = v;
            }
        swfs_shwfs_measure(w, z, clean + t * ns);
        for (size_t i = 0; i < ns; i++) sig2 += clean[t * ns + i] * clean[t * ns + i];
    }
    const double srms = sqrt(sig2 / (double)(nf * 2 * w->nvalid)); /* the pattern's slopes, rms */
    double var = -1;
    size_t nc = 0;
    assert_ok(swfs_slopes_white_noise(clean, nf, ns, nsub, NULL, &var, &nc, NULL));
    assert_true(nc > 60 && nc < 121);
    print_message("white noise: pattern slopes %.3g rad rms; without noise %.3g\n", srms, sqrt(var));
    assert_true(sqrt(var) < 0.02 * srms);
    /* the curl's whole power (swfs_slopes_curl_noise): the aliased part of the pattern, which
     * the white estimate leaves out, and the same white estimate */
    double white0 = -1, total0 = -1;
    assert_ok(swfs_slopes_curl_noise(clean, nf, ns, nsub, NULL, &white0, &total0));
    print_message("curl power without noise: %.3g rad rms per slope (white %.3g)\n", sqrt(total0), sqrt(white0));
    assert_true(white0 == var);
    assert_true(sqrt(total0) > 0.1 * srms && total0 < srms * srms);
    const double sig[3] = {0.05, 0.3, 2.0};
    for (int c = 0; c < 3; c++) {
        for (size_t i = 0; i < nf * ns; i++)
            s[i] = clean[i] + (w->valid[i % (ns / 2)] ? sig[c] * srms * swfs_rng_normal(&rng) : 0.0);
        assert_ok(swfs_slopes_white_noise(s, nf, ns, nsub, NULL, &var, NULL, NULL));
        double var2 = -1;
        assert_ok(swfs_slopes_white_noise(s, nf, ns, nsub, w->valid, &var2, NULL, NULL));
        print_message("white noise: %.3g rad rms added, %.3g estimated\n", sig[c] * srms, sqrt(var));
        assert_close(sqrt(var), sig[c] * srms, 0.1 * sig[c] * srms);
        assert_close(var2, var, 1e-12 * var);
        /* the curl's power: the pattern's plus the noise's (independent of it) */
        double white = -1, total = -1;
        assert_ok(swfs_slopes_curl_noise(s, nf, ns, nsub, NULL, &white, &total));
        const double want = total0 + sig[c] * srms * sig[c] * srms;
        print_message("curl power: %.3g rad rms per slope, pattern's and noise's %.3g\n", sqrt(total), sqrt(want));
        assert_true(white == var);
        assert_close(total, want, 0.1 * want);
        /* the used subapertures' slopes only (x then y), with the map: the same */
        const size_t nv = w->nvalid, n2 = ns / 2;
        double *cs = malloc(nf * 2 * nv * sizeof *cs), var3 = -1;
        assert_non_null(cs);
        for (size_t t = 0; t < nf; t++)
            for (size_t k = 0, u = 0; k < n2; k++)
                if (w->valid[k]) {
                    cs[t * 2 * nv + u] = s[t * ns + k];
                    cs[t * 2 * nv + nv + u++] = s[t * ns + n2 + k];
                }
        assert_ok(swfs_slopes_white_noise(cs, nf, 2 * nv, nsub, w->valid, &var3, NULL, NULL));
        assert_close(var3, var2, 1e-12 * var2);
        assert_int_equal(swfs_slopes_white_noise(cs, nf, 2 * nv, nsub, NULL, &var3, NULL, NULL), SWFS_ERR_SHAPE);
        free(cs);
    }
    /* refused: too few frames, fewer than 2 x 2 subapertures, a NaN, no cell of four used ones */
    assert_int_equal(swfs_slopes_white_noise(s, 15, ns, nsub, NULL, &var, NULL, NULL), SWFS_ERR_ARG);
    assert_int_equal(swfs_slopes_white_noise(s, nf, ns, 1, NULL, &var, NULL, NULL), SWFS_ERR_ARG);
    unsigned char none[144] = {0};
    assert_int_equal(swfs_slopes_white_noise(s, nf, ns, nsub, none, &var, NULL, NULL), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "no 2 x 2 cell"));
    s[7 * ns + 20] = NAN;
    assert_int_equal(swfs_slopes_white_noise(s, nf, ns, nsub, NULL, &var, NULL, NULL), SWFS_ERR_VALUE);
    assert_non_null(strstr(swfs_last_error(), "slope 20 of WFS frame 7 is not finite"));
    free(z); free(clean); free(s); free(mask);
    swfs_shwfs_free(w);
}

/* The DM's modes of one system, of another (its pupil one column darker), then of the first
 * again: swfs_dm_modes keeps the last system's result for the next call on the same inputs,
 * and must give each system its own modes, M-orthonormal. */
static void dm_system(size_t dark, double *mask, swfs_sparse **T)
{
    enum { NA = 9, NPUP = 41 };
    const double d = 0.1, dx = 0.025;
    double pts[2 * NA * NA];
    for (int j = 0; j < NA; j++)
        for (int i = 0; i < NA; i++) {
            pts[2 * (j * NA + i)] = (i - NA / 2) * d;
            pts[2 * (j * NA + i) + 1] = (j - NA / 2) * d;
        }
    for (size_t k = 0; k < NPUP * NPUP; k++) {
        const double x = ((double)(k % NPUP) - NPUP / 2) * dx, y = ((double)(k / NPUP) - NPUP / 2) * dx;
        mask[k] = hypot(x, y) <= 0.4 && k % NPUP >= dark ? 1 : 0;
    }
    assert_ok(swfs_interp_ct_grid(pts, NA * NA, NPUP, dx, mask, T, NULL));
}

static void test_dm_modes_per_system(void **state)
{
    (void)state;
    enum { NPUP = 41, NA2 = 81 };
    static double ma[NPUP * NPUP], mb[NPUP * NPUP];
    swfs_sparse *Ta = NULL, *Tb = NULL;
    dm_system(0, ma, &Ta);
    dm_system(12, mb, &Tb);
    double *a1 = NULL, *b1 = NULL, *a2 = NULL, *b2 = NULL;
    assert_ok(swfs_dm_modes(Ta, ma, NPUP, &a1));
    assert_ok(swfs_dm_modes(Tb, mb, NPUP, &b1));
    assert_ok(swfs_dm_modes(Ta, ma, NPUP, &a2));
    assert_ok(swfs_dm_modes(Tb, mb, NPUP, &b2));
    assert_memory_equal(a1, a2, NA2 * NA2 * sizeof *a1);
    assert_memory_equal(b1, b2, NA2 * NA2 * sizeof *b1);
    assert_true(a1 != a2 && b1 != b2); /* each call its own copy, the caller's to free */
    /* M-orthonormal: each mode's surface T v has unit mean square sum over the pupil */
    double *const m[2] = {a1, b1}, *const mk[2] = {ma, mb};
    const swfs_sparse *const T[2] = {Ta, Tb};
    for (int s = 0; s < 2; s++)
        for (size_t k = 0; k < 12; k++) {
            double ss = 0;
            for (size_t g = 0; g < NPUP * NPUP; g++) {
                if (!(mk[s][g] > 0)) continue;
                double z = 0;
                for (size_t q = T[s]->row_ptr[g]; q < T[s]->row_ptr[g + 1]; q++) z += T[s]->val[q] * m[s][T[s]->col[q] * NA2 + k];
                ss += z * z;
            }
            assert_true(fabs(ss - 1) < 1e-6);
        }
    /* the darker pupil's modes are its own: its focus-like modes differ from the first system's */
    double diff = 0;
    for (size_t k = 0; k < NA2 * NA2; k++) diff = fmax(diff, fabs(fabs(a1[k]) - fabs(b1[k])));
    assert_true(diff > 1e-3);
    free(a1); free(b1); free(a2); free(b2);
    swfs_sparse_free(Ta);
    swfs_sparse_free(Tb);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_interp_exact_quadratics),
        cmocka_unit_test(test_interp_outside_and_bad),
        cmocka_unit_test(test_influence_gauss),
        cmocka_unit_test(test_shwfs_and_reconstructor),
        cmocka_unit_test(test_white_noise),
        cmocka_unit_test(test_dm_modes_per_system),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

/* Optics primitives: MFT against FFT on a matching grid, Parseval, the inverse, the
 * Airy pattern of a circular pupil, aperture areas, Zernike polynomials. */
#include "testutil.h"

#include "specklewfs/aperture.h"
#include "specklewfs/array.h"
#include "specklewfs/mft.h"
#include "specklewfs/rng.h"

#include <cblas.h>
#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <stdlib.h>

static double complex *random_field(size_t n, uint64_t seed)
{
    double complex *a = swfs_malloc(n * sizeof *a);
    swfs_rng r;
    swfs_rng_seed(&r, seed);
    for (size_t k = 0; k < n; k++) a[k] = swfs_rng_cnormal_value(&r);
    return a;
}

/* MFT with alpha = 1/N and an N x N window is the centred DFT:
 *   MFT(i, j) = sum_p x_p exp(-2 pi i (i - N/2)(p - c)/N), c = (np - 1)/2
 *             = exp(+2 pi i k c / N) FFT(x)(k),   k = i - N/2 (per axis). */
static void check_mft_fft(size_t np, size_t nn, int precision, double tol)
{
    double complex *x = random_field(np * np, 7 + np);
    double complex *buf = fftw_malloc(nn * nn * sizeof *buf);
    for (size_t k = 0; k < nn * nn; k++) buf[k] = 0;
    for (size_t q = 0; q < np; q++)
        for (size_t p = 0; p < np; p++) buf[q * nn + p] = x[q * np + p];
    fftw_plan plan = fftw_plan_dft_2d((int)nn, (int)nn, (fftw_complex *)buf, (fftw_complex *)buf, FFTW_FORWARD,
                                      FFTW_ESTIMATE);
    fftw_execute(plan);
    swfs_mft *m = swfs_mft_create(np, nn, nn, 1.0 / (double)nn, precision);
    assert_non_null(m);
    double complex *f = swfs_malloc(nn * nn * sizeof *f);
    assert_ok(swfs_mft_forward(m, x, f));
    const double c = 0.5 * (double)(np - 1);
    double maxerr = 0, maxval = 0;
    for (size_t j = 0; j < nn; j++)
        for (size_t i = 0; i < nn; i++) {
            const long kx = (long)i - (long)(nn / 2), ky = (long)j - (long)(nn / 2);
            const size_t bx = (size_t)((kx + (long)nn) % (long)nn), by = (size_t)((ky + (long)nn) % (long)nn);
            const double complex ref = buf[by * nn + bx] * cexp(2.0 * M_PI * I * (double)(kx + ky) * c / (double)nn);
            maxerr = fmax(maxerr, cabs(f[j * nn + i] - ref));
            maxval = fmax(maxval, cabs(ref));
        }
    assert_true(maxval > 0);
    if (!(maxerr / maxval < tol)) fail_msg("np=%zu N=%zu prec=%d: MFT-FFT rel err %.3g >= %.3g", np, nn, precision, maxerr / maxval, tol);
    /* Parseval for the full window: sum |F|^2 = N^2 sum |x|^2. */
    double ef = 0, ex = 0;
    for (size_t k = 0; k < nn * nn; k++) ef += creal(f[k] * conj(f[k]));
    for (size_t k = 0; k < np * np; k++) ex += creal(x[k] * conj(x[k]));
    assert_close(ef / ((double)nn * (double)nn * ex), 1.0, precision == SWFS_MFT_SINGLE ? 1e-5 : 1e-12);
    /* The inverse is the adjoint: alpha^2 inverse(forward(x)) = x for a full window. */
    double complex *back = swfs_malloc(np * np * sizeof *back);
    assert_ok(swfs_mft_inverse(m, f, back));
    double berr = 0;
    for (size_t k = 0; k < np * np; k++) berr = fmax(berr, cabs(back[k] / ((double)nn * (double)nn) - x[k]));
    assert_true(berr < (precision == SWFS_MFT_SINGLE ? 1e-4 : 1e-11));
    swfs_free(back);
    swfs_free(f);
    swfs_mft_free(m);
    fftw_destroy_plan(plan);
    fftw_free(buf);
    swfs_free(x);
}

static void test_mft_equals_fft(void **state)
{
    (void)state;
    check_mft_fft(33, 96, SWFS_MFT_DOUBLE, 1e-12); /* odd pupil: integer centre */
    check_mft_fft(32, 64, SWFS_MFT_DOUBLE, 1e-12); /* even pupil: half-sample centre */
    check_mft_fft(33, 96, SWFS_MFT_SINGLE, 3e-6);  /* the per-frame precision */
    check_mft_fft(40, 50, SWFS_MFT_SINGLE, 3e-6);  /* N barely above the pupil */
}

/* Single-precision fast path against the double plan at the paper's sampling. */
static void test_mft_single_accuracy(void **state)
{
    (void)state;
    const size_t np = 163, nf = 60;
    const double alpha = 0.25 * 0.04 / 6.5;
    double complex *x = random_field(np * np, 3);
    float complex *xf = swfs_malloc(np * np * sizeof *xf);
    for (size_t k = 0; k < np * np; k++) xf[k] = (float complex)x[k];
    swfs_mft *md = swfs_mft_create(np, nf, nf, alpha, SWFS_MFT_DOUBLE);
    swfs_mft *ms = swfs_mft_create(np, nf, nf, alpha, SWFS_MFT_SINGLE);
    double complex *fd = swfs_malloc(nf * nf * sizeof *fd);
    float complex *fs = swfs_malloc(nf * nf * sizeof *fs);
    assert_ok(swfs_mft_forward(md, x, fd));
    assert_ok(swfs_mft_forward_f(ms, xf, fs));
    double e2 = 0, n2 = 0;
    for (size_t k = 0; k < nf * nf; k++) {
        e2 += pow(cabs(fd[k] - (double complex)fs[k]), 2);
        n2 += pow(cabs(fd[k]), 2);
    }
    assert_true(sqrt(e2 / n2) < 2e-6);
    /* Wrong-precision call is an error, not a crash. */
    assert_int_not_equal(swfs_mft_forward_f(md, xf, fs), 0);
    swfs_free(fs);
    swfs_free(fd);
    swfs_mft_free(ms);
    swfs_mft_free(md);
    swfs_free(xf);
    swfs_free(x);
}

/* Unobstructed circular pupil: peak on pixel (W/2, H/2) with value (sum P)^2, first dark
 * ring at 1.220 lambda/D, first bright ring at 1.635 lambda/D with 1.75 % of the peak. */
static void test_airy_pattern(void **state)
{
    (void)state;
    const size_t np = 128;
    const double dx = 0.05, diam = (double)np * dx;
    double *mask = swfs_malloc(np * np * sizeof *mask);
    assert_ok(swfs_aperture_make(mask, np, dx, diam, 0.0, 0, 0.0));
    double complex *pup = swfs_malloc(np * np * sizeof *pup);
    double s = 0;
    for (size_t k = 0; k < np * np; k++) {
        pup[k] = mask[k];
        s += mask[k];
    }
    /* 2-D window at 0.25 lambda/D: the brightest pixel is the centre one, = S^2. */
    const size_t nw = 21;
    swfs_mft *m2 = swfs_mft_create(np, nw, nw, 0.25 * dx / diam, SWFS_MFT_DOUBLE);
    double complex *f2 = swfs_malloc(nw * nw * sizeof *f2);
    assert_ok(swfs_mft_forward(m2, pup, f2));
    size_t kmax = 0;
    for (size_t k = 0; k < nw * nw; k++)
        if (cabs(f2[k]) > cabs(f2[kmax])) kmax = k;
    assert_int_equal(kmax, (nw / 2) * nw + nw / 2);
    assert_close(cabs(f2[kmax]), s, 1e-9 * s);
    assert_close(carg(f2[kmax]), 0.0, 1e-12);
    /* Radial cut along +x, fine sampling. */
    const double ps = 0.005;
    const size_t nx = 800; /* 0 .. 2 lambda/D from the centre pixel nx/2 */
    swfs_mft *m1 = swfs_mft_create(np, nx, 1, ps * dx / diam, SWFS_MFT_DOUBLE);
    double complex *f1 = swfs_malloc(nx * sizeof *f1);
    assert_ok(swfs_mft_forward(m1, pup, f1));
    double best_min = INFINITY, best_max = -INFINITY, th_min = 0, th_max = 0;
    for (size_t i = nx / 2; i < nx; i++) {
        const double th = (double)(i - nx / 2) * ps, v = pow(cabs(f1[i]) / s, 2);
        if (th > 1.0 && th < 1.4 && v < best_min) { best_min = v; th_min = th; }
        if (th > 1.4 && th < 1.9 && v > best_max) { best_max = v; th_max = th; }
    }
    assert_close(th_min, 1.2197, 0.02);
    assert_close(th_max, 1.6347, 0.02);
    assert_true(best_min < 1e-4);
    assert_close(best_max, 0.0175, 0.0175 * 0.08);
    swfs_free(f1);
    swfs_free(f2);
    swfs_mft_free(m1);
    swfs_mft_free(m2);
    swfs_free(pup);
    swfs_free(mask);
}

static void test_aperture_area(void **state)
{
    (void)state;
    const size_t n = 500;
    const double diam = 6.5, dx = diam / 480.0, eps = 0.1;
    double *mask = swfs_malloc(n * n * sizeof *mask);
    assert_ok(swfs_aperture_make(mask, n, dx, diam, eps, 0, 0.0));
    double a = 0;
    for (size_t k = 0; k < n * n; k++) a += mask[k];
    a *= dx * dx;
    const double ideal = M_PI / 4 * diam * diam * (1 - eps * eps);
    assert_close(a / ideal, 1.0, 0.005);
    /* Centre sample blocked by the obstruction; a rim sample inside, a corner outside. */
    assert_true(mask[(n / 2) * n + n / 2] == 0.0);
    assert_true(mask[0] == 0.0);
    /* Four spiders of width w remove ~ 4 w (R - r_in). */
    /* width 8 dx: exactly 8 sample rows (at half-integer offsets) per vane */
    assert_ok(swfs_aperture_make(mask, n, dx, diam, eps, 4, 8 * dx));
    double as = 0;
    for (size_t k = 0; k < n * n; k++) as += mask[k];
    as *= dx * dx;
    const double removed = 4 * 8 * dx * (diam / 2) * (1 - eps);
    assert_close((a - as) / removed, 1.0, 0.03);
    /* Spider 0 lies along +x: the sample at (x = 0.8 R, y = 0) is blocked, (x = -0.8 R, y = 0) too
     * for 4 spiders (spider 2 along -x), but (0.8R cos 45, 0.8R sin 45) is open. */
    const size_t c = n / 2;
    assert_true(mask[c * n + c + 190] == 0.0 || mask[(c - 1) * n + c + 190] == 0.0);
    const size_t d = (size_t)(0.8 * diam / 2 / dx * M_SQRT1_2);
    assert_true(mask[(c + d) * n + c + d] == 1.0);
    /* Bad inputs. */
    assert_int_not_equal(swfs_aperture_make(mask, n, dx, diam, 1.2, 0, 0), 0);
    assert_int_not_equal(swfs_aperture_make(mask, n, -1, diam, 0, 0, 0), 0);
    swfs_free(mask);
}

static void test_zernike(void **state)
{
    (void)state;
    /* Paper Sec. 3: trefoil Z_3^3(rho, theta) = rho^3 cos 3 theta. */
    for (double rho = 0; rho <= 1.0; rho += 0.25)
        for (double th = -3; th < 3; th += 0.7) assert_close(swfs_zernike(3, 3, rho, th), pow(rho, 3) * cos(3 * th), 1e-14);
    assert_close(swfs_zernike(4, 0, 0.5, 1.0), 6 * 0.0625 - 6 * 0.25 + 1, 1e-14);
    assert_close(swfs_zernike(3, -1, 0.5, 0.3), (3 * 0.125 - 2 * 0.5) * sin(0.3), 1e-14);
    assert_close(swfs_zernike(2, 0, 1.0, 0.0), 1.0, 1e-14);
    assert_true(isnan(swfs_zernike(3, 2, 0.5, 0.0)));
    /* the recurrence against the explicit sum where that holds (n <= 20: within 3e-11 of the
     * exact rational values, measured), and beyond it the
     * radial polynomials' R(1) = 1 and their orthogonality, int_0^1 R_n R_n' rho drho =
     * delta / (2 (n + 1)), at orders where the sum had lost every digit */
    for (int n = 0; n <= 20; n++)
        for (int m = -n; m <= n; m += 2)
            for (double rho = 0; rho <= 1.0; rho += 0.125) {
                const int am = abs(m);
                double r = 0, f[41];
                f[0] = 1;
                for (int i = 1; i <= 40; i++) f[i] = f[i - 1] * i;
                for (int s2 = 0; s2 <= (n - am) / 2; s2++)
                    r += (s2 % 2 ? -1 : 1) * f[n - s2] / (f[s2] * f[(n + am) / 2 - s2] * f[(n - am) / 2 - s2]) *
                         pow(rho, n - 2 * s2);
                const double z = m > 0 ? r * cos(m * 0.4) : m < 0 ? r * sin(am * 0.4) : r;
                assert_close(swfs_zernike(n, m, rho, 0.4), z, 1e-10); /* (the sum's own rounding: 3e-11) */
            }
    for (int n = 0; n <= 200; n += 5) assert_close(swfs_zernike(n, n % 2, 1.0, 0.0), 1.0, 1e-10);
    const int orders[3][2] = {{60, 60}, {60, 62}, {101, 103}};
    for (int k = 0; k < 3; k++) {
        const int na = orders[k][0], nb = orders[k][1], m = na % 2, steps = 20000;
        double sum = 0;
        for (int i = 0; i < steps; i++) {
            const double rho = (i + 0.5) / steps;
            sum += swfs_zernike(na, m, rho, 0.0) * swfs_zernike(nb, m, rho, 0.0) * rho / steps;
        }
        assert_close(sum, na == nb ? 1.0 / (2 * (na + 1)) : 0.0, 1e-5); /* (the midpoint rule at n ~ 100) */
    }
    /* Orthogonality over the unit disc (midpoint quadrature). */
    const int nn = 400;
    double s12 = 0, s11 = 0;
    for (int j = 0; j < nn; j++)
        for (int i = 0; i < nn; i++) {
            const double x = -1 + (i + 0.5) * 2.0 / nn, y = -1 + (j + 0.5) * 2.0 / nn, r = hypot(x, y);
            if (r > 1) continue;
            const double a = swfs_zernike(2, 0, r, atan2(y, x)), b = swfs_zernike(4, 0, r, atan2(y, x));
            s12 += a * b;
            s11 += a * a;
        }
    assert_true(fabs(s12) < 1e-3 * s11);
    /* Noll indices. */
    const int expect[][3] = {{1, 0, 0}, {2, 1, 1}, {3, 1, -1}, {4, 2, 0}, {5, 2, -2}, {6, 2, 2},
                             {7, 3, -1}, {8, 3, 1}, {9, 3, -3}, {10, 3, 3}, {11, 4, 0}, {22, 6, 0}};
    for (size_t k = 0; k < sizeof expect / sizeof expect[0]; k++) {
        int n, m;
        assert_ok(swfs_zernike_noll(expect[k][0], &n, &m));
        assert_int_equal(n, expect[k][1]);
        assert_int_equal(m, expect[k][2]);
    }
    int n, m;
    assert_int_not_equal(swfs_zernike_noll(0, &n, &m), 0);
}

int main(void)
{
    openblas_set_num_threads(1);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_mft_equals_fft), cmocka_unit_test(test_mft_single_accuracy),
        cmocka_unit_test(test_airy_pattern),   cmocka_unit_test(test_aperture_area),
        cmocka_unit_test(test_zernike),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

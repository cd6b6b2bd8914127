/* Accuracy of the vectorized sin/cos and exp(i phi) kernels (src/optics/kernels_fastmath.c,
 * the one file compiled with -ffast-math) against double-precision libm. */
#include "testutil.h"

#include "specklewfs/kernels.h"
#include "specklewfs/rng.h"

#include <complex.h>
#include <math.h>
#include <stdlib.h>

#define N 10007 /* odd: exercises the scalar remainder of the vector loops */

static void test_sincos_f(void **state)
{
    (void)state;
    swfs_rng r;
    swfs_rng_seed(&r, 11);
    float *x = malloc(N * sizeof *x), *s = malloc(N * sizeof *s), *c = malloc(N * sizeof *c);
    assert_non_null(x);
    assert_non_null(s);
    assert_non_null(c);
    /* Phases of a few tens of radians: AO residuals plus unwrapped static terms. */
    for (size_t k = 0; k < N; k++) x[k] = (float)(60.0 * (swfs_rng_uniform(&r) - 0.5));
    swfs_sincos_f(x, s, c, N);
    double emax = 0.0;
    for (size_t k = 0; k < N; k++) {
        const double xd = (double)x[k];
        emax = fmax(emax, fabs((double)s[k] - sin(xd)));
        emax = fmax(emax, fabs((double)c[k] - cos(xd)));
    }
    print_message("sincos_f max abs error %.3g\n", emax);
    assert_true(emax < 3e-7);
    free(x); free(s); free(c);
}

static void test_sincos_d(void **state)
{
    (void)state;
    swfs_rng r;
    swfs_rng_seed(&r, 12);
    double *x = malloc(N * sizeof *x), *s = malloc(N * sizeof *s), *c = malloc(N * sizeof *c);
    assert_non_null(x);
    assert_non_null(s);
    assert_non_null(c);
    for (size_t k = 0; k < N; k++) x[k] = 60.0 * (swfs_rng_uniform(&r) - 0.5);
    swfs_sincos_d(x, s, c, N);
    double emax = 0.0;
    for (size_t k = 0; k < N; k++) {
        emax = fmax(emax, fabs(s[k] - sin(x[k])));
        emax = fmax(emax, fabs(c[k] - cos(x[k])));
    }
    print_message("sincos_d max abs error %.3g\n", emax);
    assert_true(emax < 1e-14);
    free(x); free(s); free(c);
}

static void test_expi(void **state)
{
    (void)state;
    swfs_rng r;
    swfs_rng_seed(&r, 13);
    float *phi = malloc(N * sizeof *phi), *amp = malloc(N * sizeof *amp);
    float complex *out = malloc(N * sizeof *out), *out1 = malloc(N * sizeof *out1);
    double *phid = malloc(N * sizeof *phid), *ampd = malloc(N * sizeof *ampd);
    double complex *outd = malloc(N * sizeof *outd);
    assert_true(phi && amp && out && out1 && phid && ampd && outd);
    for (size_t k = 0; k < N; k++) {
        phid[k] = 20.0 * (swfs_rng_uniform(&r) - 0.5);
        ampd[k] = swfs_rng_uniform(&r);
        phi[k] = (float)phid[k];
        amp[k] = (float)ampd[k];
        phid[k] = (double)phi[k]; /* compare the same input */
        ampd[k] = (double)amp[k];
    }
    swfs_expi_f(phi, amp, out, N);
    swfs_expi_f(phi, NULL, out1, N);
    swfs_expi_d(phid, ampd, outd, N);
    double ef = 0.0, e1 = 0.0, ed = 0.0;
    for (size_t k = 0; k < N; k++) {
        const double complex ref = ampd[k] * cexp(I * phid[k]);
        ef = fmax(ef, cabs((double complex)out[k] - ref));
        e1 = fmax(e1, cabs((double complex)out1[k] - cexp(I * phid[k])));
        ed = fmax(ed, cabs(outd[k] - ref));
    }
    print_message("expi max abs error: float %.3g, float unit %.3g, double %.3g\n", ef, e1, ed);
    assert_true(ef < 4e-7);
    assert_true(e1 < 4e-7);
    assert_true(ed < 1e-14);
    /* Unit modulus without an amplitude. */
    for (size_t k = 0; k < N; k += 97) assert_close(cabs((double complex)out1[k]), 1.0, 3e-7);
    free(phi); free(amp); free(out); free(out1); free(phid); free(ampd); free(outd);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_sincos_f),
        cmocka_unit_test(test_sincos_d),
        cmocka_unit_test(test_expi),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

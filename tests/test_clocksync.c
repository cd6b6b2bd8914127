/* The camera clock against the WFS clock (clocksync.h) on synthetic time-stamped data: a
 * smooth random tip-tilt sampled by a 1 kHz WFS, a camera whose clock runs fast by 2e-4 and
 * late by 3.1 ms, a transposed and y-mirrored track; offset, drift and pairing recovered; the
 * clock file round trip; no overlap refused. */
#include "testutil.h"

#include "specklewfs/clocksync.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum { NW = 30000, NCUBE = 5, NF = 200 };
static const int64_t E = 1700000000LL * 1000000000LL;
static const double RATE = 1000, EXPT = 5.3e-3, DRIFT = 2e-4, OFFSET = 3.1e-3;

typedef struct data {
    uint64_t wcnt[NW], ccnt[NCUBE * NF];
    int64_t wst[NW], cst[NCUBE * NF];
    double mx[NW], my[NW], C[2][NW + 1], tx[NCUBE * NF], ty[NCUBE * NF];
} data;

/* Box mean of series a over [u0, u1) (frame units, frame k covers [k, k + 1)). */
static double box(const double *C, const double *m, double u0, double u1)
{
    const double f0 = floor(u0), f1 = floor(u1);
    const double c0 = C[(size_t)f0] + (u0 - f0) * m[(size_t)f0], c1 = C[(size_t)f1] + (u1 - f1) * m[(size_t)f1];
    return (c1 - c0) / (u1 - u0);
}

static data *make(void)
{
    data *d = calloc(1, sizeof *d);
    swfs_rng r;
    swfs_rng_seed2(&r, 7, 1);
    double ph[2][12], fr[12];
    for (int k = 0; k < 12; k++) {
        fr[k] = 0.5 + 40.0 * swfs_rng_uniform(&r);
        ph[0][k] = 2 * M_PI * swfs_rng_uniform(&r);
        ph[1][k] = 2 * M_PI * swfs_rng_uniform(&r);
    }
    for (size_t k = 0; k < NW; k++) {
        const double t = ((double)k + 0.5) / RATE;
        double a = 0, b = 0;
        for (int q = 0; q < 12; q++) {
            a += sin(2 * M_PI * fr[q] * t + ph[0][q]) / (1 + fr[q] / 5);
            b += sin(2 * M_PI * fr[q] * t + ph[1][q]) / (1 + fr[q] / 5);
        }
        d->mx[k] = 1e-6 * a;
        d->my[k] = 1e-6 * b;
        d->wcnt[k] = k + 1;
        d->wst[k] = E + llround(1e9 * ((double)(k + 1) / RATE + 2e-6 * swfs_rng_normal(&r)));
    }
    for (int a = 0; a < 2; a++)
        for (size_t k = 0; k < NW; k++) d->C[a][k + 1] = d->C[a][k] + (a ? d->my : d->mx)[k];
    for (size_t c = 0; c < NCUBE; c++)
        for (size_t j = 0; j < NF; j++) {
            const size_t e = c * NF + j;
            const double tw = 1.0 + (double)c * 5.5 + (double)(j + 1) * EXPT; /* the exposure's end, WFS clock */
            const double u1 = tw * RATE, u0 = u1 - EXPT * RATE;
            /* the camera is transposed and mirrored in y: x follows the y slopes, y the x slopes negated */
            d->tx[e] = 3e6 * box(d->C[1], d->my, u0, u1) + 0.02 * swfs_rng_normal(&r);
            d->ty[e] = -3e6 * box(d->C[0], d->mx, u0, u1) + 0.02 * swfs_rng_normal(&r);
            d->ccnt[e] = 1 + c * 1000 + j;
            d->cst[e] = E + llround(1e9 * ((tw - OFFSET) / (1 + DRIFT) + 2e-6 * swfs_rng_normal(&r)));
        }
    return d;
}

static void test_recover(void **state)
{
    (void)state;
    data *d = make();
    swfs_clock_data cd = {NW, d->wcnt, d->wst, d->mx, d->my, NCUBE * NF, d->ccnt, d->cst, d->tx, d->ty, EXPT};
    swfs_clock_params p;
    swfs_clock_params_default(&p);
    swfs_clock c;
    assert_ok(swfs_clock_estimate(&cd, &p, &c));
    printf("test_clocksync: offset %.4f ms (true %.4f at the epoch) +- %.2g, drift %.4g (true %.4g) +- %.2g, corr %.3f %.3f, "
           "resid %.3g px, %zu segments\n", 1e3 * c.offset, 1e3 * (OFFSET + DRIFT), 1e3 * c.offset_err, c.drift, DRIFT,
           c.drift_err, c.fit.corr_x, c.fit.corr_y, c.resid, c.nsegments);
    /* the epoch: the whole second before the first camera stamp (1.002 s after E); the
     * offset there is OFFSET + DRIFT x 1 s */
    assert_true(c.epoch == E + 1000000000LL);
    assert_close(c.drift, DRIFT, 3e-6);
    assert_close(c.offset, OFFSET + DRIFT * 1.0, 2e-5);
    assert_int_equal(c.fit.swap, 1);
    assert_int_equal(c.fit.sign_x, 1);
    assert_int_equal(c.fit.sign_y, -1);
    assert_int_equal(c.nsegments, NCUBE);
    assert_true(c.fit.corr_x > 0.99 && c.fit.corr_y < -0.99);
    assert_close(c.wfs_period, 1e-3, 1e-8);
    /* a camera stamp on the WFS clock */
    const int64_t tw = swfs_clock_to_wfs(&c, d->cst[0]);
    assert_true(llabs(tw - (E + llround(1e9 * (1.0 + EXPT)))) < 30000);
    /* the clock file */
    const char *path = test_path("clock.txt");
    assert_ok(swfs_clock_write(path, &c, "test"));
    swfs_clock r;
    assert_ok(swfs_clock_read(path, &r));
    assert_true(r.epoch == c.epoch);
    assert_close(r.offset, c.offset, 1e-12);
    assert_close(r.drift, c.drift, 1e-15);
    assert_int_equal(r.fit.swap, 1);
    assert_int_equal(r.fit.sign_y, -1);
    /* a camera 100 s after the WFS data */
    for (size_t j = 0; j < NCUBE * NF; j++) d->cst[j] += 100000000000LL;
    assert_int_not_equal(swfs_clock_estimate(&cd, &p, &c), 0);
    assert_non_null(strstr(swfs_last_error(), "do not overlap in time"));
    free(d);
}

int main(void)
{
    const struct CMUnitTest tests[] = {cmocka_unit_test(test_recover)};
    return cmocka_run_group_tests(tests, NULL, NULL);
}

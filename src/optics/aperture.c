/* Pupil masks and Zernike polynomials: see include/specklewfs/aperture.h. */
#include "specklewfs/aperture.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>

int swfs_aperture_make(double *mask, size_t n, double dx, double diam, double obscur, int nspiders,
                       double spider_width)
{
    if (!mask || !n || !(dx > 0) || !(diam > 0))
        return swfs_fail(SWFS_ERR_ARG, "aperture: need n > 0, dx > 0 and a diameter > 0 (got n=%zu dx=%g D=%g)", n, dx,
                         diam);
    if (!(obscur >= 0 && obscur < 1))
        return swfs_fail(SWFS_ERR_ARG, "aperture: central obstruction %g must be a fraction of the diameter in [0, 1)",
                         obscur);
    if (nspiders < 0 || nspiders > 64 || (nspiders > 0 && !(spider_width >= 0)))
        return swfs_fail(SWFS_ERR_ARG, "aperture: spiders must be 0..64 with a width >= 0 (got %d, %g m)", nspiders,
                         spider_width);
    const double c = 0.5 * (double)(n - 1), rout = 0.5 * diam, rin = obscur * rout, hw = 0.5 * spider_width;
    for (size_t q = 0; q < n; q++) {
        const double y = ((double)q - c) * dx;
        for (size_t p = 0; p < n; p++) {
            const double x = ((double)p - c) * dx, r = hypot(x, y);
            double v = (r <= rout && r >= rin) ? 1.0 : 0.0;
            for (int k = 0; k < nspiders && v > 0; k++) {
                const double a = 2.0 * M_PI * k / nspiders, ca = cos(a), sa = sin(a);
                if (x * ca + y * sa >= 0 && fabs(-x * sa + y * ca) <= hw) v = 0.0;
            }
            mask[q * n + p] = v;
        }
    }
    return SWFS_OK;
}

/* The radial polynomial R_n^|m|(rho) = (-1)^k rho^|m| P_k^(|m|,0)(1 - 2 rho^2), k = (n - |m|)/2,
 * through the Jacobi polynomials' three-term recurrence: stable to any order, where the explicit
 * sum of factorials with alternating signs lost every digit beyond n of about 30 (R_50^0(1) came
 * out 48.6 instead of 1). */
static double radial(int n, int am, double rho)
{
    const int k = (n - am) / 2;
    const double a = am, x = 1.0 - 2.0 * rho * rho;
    double p0 = 1.0, p1 = (a + 1.0) + (a + 2.0) * (x - 1.0) / 2.0;
    if (k == 0) p1 = p0;
    for (int j = 2; j <= k; j++) {
        const double c = 2.0 * j + a;
        const double p2 = ((c - 1.0) * (c * (c - 2.0) * x + a * a) * p1 - 2.0 * (j + a - 1.0) * (j - 1.0) * c * p0) /
                          (2.0 * j * (j + a) * (c - 2.0));
        p0 = p1;
        p1 = p2;
    }
    return (k % 2 ? -p1 : p1) * pow(rho, am);
}

double swfs_zernike(int n, int m, double rho, double theta)
{
    if (n < 0 || m < -n || m > n || (n - m) % 2) return NAN;
    const int am = m < 0 ? -m : m;
    const double r = radial(n, am, rho);
    if (m > 0) return r * cos(m * theta);
    if (m < 0) return r * sin(am * theta);
    return r;
}

int swfs_zernike_noll(int j, int *n, int *m)
{
    if (j < 1) return swfs_fail(SWFS_ERR_ARG, "Zernike: Noll index %d must be >= 1", j);
    int nn = 0;
    while (j > (nn + 1) * (nn + 2) / 2) nn++;
    const int k = j - nn * (nn + 1) / 2 - 1; /* position within radial order nn */
    const int am = nn % 2 ? 2 * (k / 2) + 1 : 2 * ((k + 1) / 2);
    *n = nn;
    *m = am == 0 ? 0 : (j % 2 ? -am : am);
    return SWFS_OK;
}

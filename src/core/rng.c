#define _DEFAULT_SOURCE /* lgamma_r: lgamma() writes the global signgam, a race between the simulators' threads */
#include "specklewfs/rng.h"

#include <math.h>

static inline uint64_t rotl(uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }

static uint64_t splitmix64(uint64_t *x)
{
    uint64_t z = (*x += 0x9e3779b97f4a7c15ULL);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
    return z ^ (z >> 31);
}

void swfs_rng_seed(swfs_rng *r, uint64_t seed)
{
    uint64_t x = seed;
    for (int i = 0; i < 4; i++) r->s[i] = splitmix64(&x);
    r->has_spare = 0;
    r->spare = 0.0;
}

void swfs_rng_seed2(swfs_rng *r, uint64_t seed, uint64_t index)
{
    uint64_t x = seed;
    uint64_t a = splitmix64(&x);
    x = index ^ 0x6a09e667f3bcc909ULL;
    uint64_t b = splitmix64(&x);
    swfs_rng_seed(r, a ^ rotl(b, 17));
}

uint64_t swfs_rng_u64(swfs_rng *r)
{
    uint64_t *s = r->s;
    const uint64_t result = rotl(s[1] * 5, 7) * 9;
    const uint64_t t = s[1] << 17;
    s[2] ^= s[0];
    s[3] ^= s[1];
    s[1] ^= s[2];
    s[0] ^= s[3];
    s[2] ^= t;
    s[3] = rotl(s[3], 45);
    return result;
}

double swfs_rng_uniform(swfs_rng *r) { return (double)(swfs_rng_u64(r) >> 11) * 0x1.0p-53; }

double swfs_rng_normal(swfs_rng *r)
{
    if (r->has_spare) {
        r->has_spare = 0;
        return r->spare;
    }
    double u, v, s;
    do {
        u = 2.0 * swfs_rng_uniform(r) - 1.0;
        v = 2.0 * swfs_rng_uniform(r) - 1.0;
        s = u * u + v * v;
    } while (s >= 1.0 || s == 0.0);
    double f = sqrt(-2.0 * log(s) / s);
    r->spare = v * f;
    r->has_spare = 1;
    return u * f;
}

void swfs_rng_cnormal(swfs_rng *r, swfs_complex *z)
{
    double a = swfs_rng_normal(r), b = swfs_rng_normal(r);
    *z = (a + I * b) * M_SQRT1_2;
}

/* PTRS: Hormann (1993), "The transformed rejection method for generating Poisson
 * random variables", valid for mean >= 10. */
static double poisson_ptrs(swfs_rng *r, double mu)
{
    const double slam = sqrt(mu), loglam = log(mu);
    const double b = 0.931 + 2.53 * slam;
    const double a = -0.059 + 0.02483 * b;
    const double invalpha = 1.1239 + 1.1328 / (b - 3.4);
    const double vr = 0.9277 - 3.6224 / (b - 2.0);
    int sign;
    for (;;) {
        double U = swfs_rng_uniform(r) - 0.5;
        double V = swfs_rng_uniform(r);
        double us = 0.5 - fabs(U);
        double k = floor((2.0 * a / us + b) * U + mu + 0.43);
        if (us >= 0.07 && V <= vr) return k;
        if (k < 0.0 || (us < 0.013 && V > us)) continue;
        if (log(V) + log(invalpha) - log(a / (us * us) + b) <= -mu + k * loglam - lgamma_r(k + 1.0, &sign))
            return k;
    }
}

double swfs_rng_poisson(swfs_rng *r, double mean)
{
    if (!(mean > 0.0)) return 0.0;
    if (mean >= 10.0) return poisson_ptrs(r, mean);
    /* Inversion by sequential search for small means. */
    double p = exp(-mean), F = p, u = swfs_rng_uniform(r);
    double k = 0.0;
    while (u > F && k < 1000.0) {
        k += 1.0;
        p *= mean / k;
        F += p;
    }
    return k;
}

/* Seeded pseudo-random numbers: xoshiro256** (uniform), polar Box-Muller (normal),
 * inversion / PTRS transformed rejection (Poisson). Every simulation and test is
 * reproducible from its seed; independent streams come from swfs_rng_seed2(seed, index). */
#ifndef SWFS_RNG_H
#define SWFS_RNG_H

#include "specklewfs/defs.h"

#include <stdint.h>

SWFS_BEGIN_DECLS

typedef struct swfs_rng {
    uint64_t s[4];
    int has_spare;
    double spare;
} swfs_rng;

void swfs_rng_seed(swfs_rng *r, uint64_t seed);
/* A stream for (seed, index), e.g. one per frame, independent of evaluation order. */
void swfs_rng_seed2(swfs_rng *r, uint64_t seed, uint64_t index);
uint64_t swfs_rng_u64(swfs_rng *r);
double swfs_rng_uniform(swfs_rng *r);            /* [0, 1) */
double swfs_rng_normal(swfs_rng *r);             /* N(0, 1) */
void swfs_rng_cnormal(swfs_rng *r, swfs_complex *z);    /* circular complex Gaussian, E|z|^2 = 1 */
double swfs_rng_poisson(swfs_rng *r, double mean);

#ifndef __cplusplus
/* C convenience (inline, not an exported symbol): swfs_rng_cnormal as a value. */
static inline swfs_complex swfs_rng_cnormal_value(swfs_rng *r)
{
    swfs_complex z;
    swfs_rng_cnormal(r, &z);
    return z;
}
#endif

SWFS_END_DECLS

#endif

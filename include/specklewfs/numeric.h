/* Small numeric helpers every stage shares: sorting, medians, FFT frequency indices. */
#ifndef SWFS_NUMERIC_H
#define SWFS_NUMERIC_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

/* Sort v[0..n) ascending (NaN-free input; qsort with a total order on doubles). */
void swfs_sort_doubles(double *v, size_t n);
/* Median of v[0..n) (the mean of the two middle values for even n; NaN for n = 0); sorts v. */
double swfs_median_inplace(double *v, size_t n);
/* Signed frequency index of FFT bin k of n: 0, 1, ..., ceil(n/2) - 1, then -floor(n/2),
 * ..., -1 (numpy's fftfreq order; correct for odd n as well). */
static inline long swfs_fft_freq_index(size_t k, size_t n)
{
    return k < (n + 1) / 2 ? (long)k : (long)k - (long)n;
}

SWFS_END_DECLS

#endif

/* Small numeric helpers every stage shares: sorting, medians, FFT frequency indices, time
 * stamps as text. */
#ifndef SWFS_NUMERIC_H
#define SWFS_NUMERIC_H

#include "specklewfs/defs.h"

#include <stddef.h>
#include <stdint.h>

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

/* Seconds as text ("1700000000.123456789") <-> int64 nanoseconds, exactly: the integer and
 * the fractional digits are parsed separately (a double of ~1.7e9 s resolves only ~0.2 us);
 * at most 9 decimals are kept (the tenth rounds); an exponent form goes through a double.
 * The parser returns 0, or non-zero for anything else (no message: the caller names the
 * file and line); negative times are refused. */
int swfs_time_parse_ns(const char *s, int64_t *ns);
void swfs_time_format_ns(int64_t ns, char *buf, size_t cap);

SWFS_END_DECLS

#endif

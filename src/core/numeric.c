/* Sorting and medians: see include/specklewfs/numeric.h. */
#include "specklewfs/numeric.h"

#include <math.h>
#include <stdlib.h>

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

void swfs_sort_doubles(double *v, size_t n) { qsort(v, n, sizeof *v, cmp_double); }

double swfs_median_inplace(double *v, size_t n)
{
    if (!n) return NAN;
    swfs_sort_doubles(v, n);
    return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

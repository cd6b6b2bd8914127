/* Sorting, medians and time stamps as text: see include/specklewfs/numeric.h. */
#include "specklewfs/numeric.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

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

#define NS_PER_S 1000000000LL

int swfs_time_parse_ns(const char *s, int64_t *ns)
{
    const char *p = s;
    if (!isdigit((unsigned char)*p) && !(*p == '.' && isdigit((unsigned char)p[1]))) return 1;
    if (strpbrk(s, "eE")) { /* an exponent form: through a double */
        char *end = NULL;
        errno = 0;
        const double v = strtod(s, &end);
        if (errno || *end || !(v >= 0) || v > 9.2e9) return 1;
        *ns = (int64_t)llround(v * 1e9);
        return 0;
    }
    int64_t sec = 0, frac = 0;
    int nd = 0;
    for (; isdigit((unsigned char)*p); p++) {
        if (sec > 9200000000LL) return 1;
        sec = 10 * sec + (*p - '0');
    }
    if (*p == '.') {
        p++;
        int round_up = 0;
        for (; isdigit((unsigned char)*p); p++, nd++) {
            if (nd < 9) frac = 10 * frac + (*p - '0');
            else if (nd == 9) round_up = *p >= '5';
        }
        for (int k = nd; k < 9; k++) frac *= 10;
        frac += round_up;
    }
    if (*p) return 1;
    *ns = sec * NS_PER_S + frac;
    return 0;
}

void swfs_time_format_ns(int64_t ns, char *buf, size_t cap)
{
    const int64_t s = ns / NS_PER_S, f = ns % NS_PER_S;
    snprintf(buf, cap, "%lld.%09lld", (long long)s, (long long)f);
}

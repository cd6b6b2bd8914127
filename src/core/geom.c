/* Geometry of the focal and pupil grids: see include/specklewfs/geom.h. */
#include "specklewfs/geom.h"
#include "specklewfs/status.h"

#include <ctype.h>
#include <math.h>
#include <stdio.h>
#include <stddef.h>

void swfs_geom_init(swfs_geom *g)
{
    g->wavelen = g->teldiam = g->obscur = g->pixscale = g->pupdx = NAN;
    g->pupn = 0;
}

int swfs_geom_overlay(swfs_geom *a, const swfs_geom *given)
{
    int changed = 0;
    double *const da[5] = {&a->wavelen, &a->teldiam, &a->obscur, &a->pixscale, &a->pupdx};
    const double dg[5] = {given->wavelen, given->teldiam, given->obscur, given->pixscale, given->pupdx};
    for (int k = 0; k < 5; k++)
        if (isfinite(dg[k])) {
            changed += isfinite(*da[k]) && *da[k] != dg[k];
            *da[k] = dg[k];
        }
    if (given->pupn > 0) {
        changed += a->pupn > 0 && a->pupn != given->pupn;
        a->pupn = given->pupn;
    }
    return changed;
}

int swfs_geom_missing(const swfs_geom *g, char *buf, size_t cap)
{
    const char *names[6] = {"WAVELEN", "TELDIAM", "OBSCUR", "PIXSCALE", "PUPDX", "PUPN"};
    const int miss[6] = {!isfinite(g->wavelen), !isfinite(g->teldiam), !isfinite(g->obscur), !isfinite(g->pixscale),
                         !isfinite(g->pupdx), g->pupn <= 0};
    int n = 0;
    size_t len = 0;
    if (cap) buf[0] = 0;
    for (int k = 0; k < 6; k++)
        if (miss[k]) {
            int w = snprintf(buf + len, cap > len ? cap - len : 0, "%s%s", n ? " " : "", names[k]);
            if (w > 0) len += (size_t)w;
            n++;
        }
    return n;
}

int swfs_geom_require(const swfs_geom *g, const char *what)
{
    const char *missing = NULL;
    if (!isfinite(g->wavelen)) missing = "WAVELEN";
    else if (!isfinite(g->teldiam)) missing = "TELDIAM";
    else if (!isfinite(g->obscur)) missing = "OBSCUR";
    else if (!isfinite(g->pixscale)) missing = "PIXSCALE";
    else if (!isfinite(g->pupdx)) missing = "PUPDX";
    else if (g->pupn <= 0) missing = "PUPN";
    if (missing) {
        char opt[16];
        size_t k = 0;
        for (; missing[k] && k + 1 < sizeof opt; k++) opt[k] = (char)tolower((unsigned char)missing[k]);
        opt[k] = 0;
        return swfs_fail(SWFS_ERR_FORMAT, "%s: missing geometry keyword %s (expected WAVELEN, TELDIAM, OBSCUR, "
                         "PIXSCALE, PUPDX, PUPN; give it with --%s or --geom FILE to reduce, speckles or stream)",
                         what, missing, opt);
    }
    return swfs_geom_check(g, what);
}

/* The physical ranges: wide enough for any telescope, laboratory bench and camera
 * (docs/reliability.md), narrow enough that a value in the wrong unit or a corrupt header
 * (WAVELEN = 1E300, PIXSCALE = 1E-300) is refused instead of giving inf or 0 nm. */
int swfs_geom_check(const swfs_geom *g, const char *what)
{
    const struct { const char *key; double v, lo, hi; const char *unit; } k[] = {
        {"WAVELEN", g->wavelen, 1e-8, 1e-3, "m (10 nm .. 1 mm)"},
        {"TELDIAM", g->teldiam, 1e-3, 1e3, "m"},
        {"PIXSCALE", g->pixscale, 1e-3, 100, "lambda/D per pixel"},
        {"PUPDX", g->pupdx, 1e-6, 100, "m per pupil sample"},
    };
    for (size_t i = 0; i < sizeof k / sizeof k[0]; i++)
        if (!isnan(k[i].v) && !(k[i].v >= k[i].lo && k[i].v <= k[i].hi))
            return swfs_fail(SWFS_ERR_VALUE, "%s: %s = %g is outside its physical range %g .. %g %s", what, k[i].key,
                             k[i].v, k[i].lo, k[i].hi, k[i].unit);
    if (!isnan(g->obscur) && !(g->obscur >= 0 && g->obscur < 1))
        return swfs_fail(SWFS_ERR_VALUE, "%s: OBSCUR = %g is outside its range 0 .. <1 (central obstruction as a "
                         "fraction of the diameter)", what, g->obscur);
    if (g->pupn != 0 && !(g->pupn >= 2 && g->pupn <= 8192))
        return swfs_fail(SWFS_ERR_VALUE, "%s: PUPN = %ld is outside its range 2 .. 8192 pupil samples across", what,
                         g->pupn);
    if (!isnan(g->pupdx) && !isnan(g->teldiam) && g->pupdx > 0.5 * g->teldiam)
        return swfs_fail(SWFS_ERR_VALUE, "%s: PUPDX = %g m is more than half of TELDIAM = %g m: fewer than two pupil "
                         "samples across the telescope", what, g->pupdx, g->teldiam);
    if (!isnan(g->pupdx) && !isnan(g->teldiam) && g->pupn > 0 &&
        (double)g->pupn * g->pupdx < g->teldiam * (1 - 1e-6))
        return swfs_fail(SWFS_ERR_VALUE, "%s: PUPN x PUPDX = %ld x %g m = %g m does not hold TELDIAM = %g m: the pupil "
                         "grid must cover the telescope", what, g->pupn, g->pupdx, (double)g->pupn * g->pupdx,
                         g->teldiam);
    return SWFS_OK;
}

static int same_value(double a, double b)
{
    if (isnan(a) || isnan(b)) return 1; /* not recorded by one of them */
    return fabs(a - b) <= 1e-9 * fmax(fabs(a), fabs(b));
}

int swfs_geom_check_same(const swfs_geom *a, const char *what_a, const swfs_geom *b, const char *what_b)
{
    const struct { const char *key; double va, vb; } k[] = {
        {"WAVELEN", a->wavelen, b->wavelen}, {"TELDIAM", a->teldiam, b->teldiam},
        {"OBSCUR", a->obscur, b->obscur},    {"PIXSCALE", a->pixscale, b->pixscale},
        {"PUPDX", a->pupdx, b->pupdx},
        {"PUPN", a->pupn ? (double)a->pupn : NAN, b->pupn ? (double)b->pupn : NAN},
    };
    for (size_t i = 0; i < sizeof k / sizeof k[0]; i++)
        if (!same_value(k[i].va, k[i].vb))
            return swfs_fail(SWFS_ERR_VALUE, "%s has %s = %.10g but %s has %.10g: not the same observing setup",
                             what_b, k[i].key, k[i].vb, what_a, k[i].va);
    return SWFS_OK;
}

/* Keywords recorded by b but not by a are taken from b. */
void swfs_geom_union(swfs_geom *a, const swfs_geom *b)
{
    if (isnan(a->wavelen)) a->wavelen = b->wavelen;
    if (isnan(a->teldiam)) a->teldiam = b->teldiam;
    if (isnan(a->obscur)) a->obscur = b->obscur;
    if (isnan(a->pixscale)) a->pixscale = b->pixscale;
    if (isnan(a->pupdx)) a->pupdx = b->pupdx;
    if (!a->pupn) a->pupn = b->pupn;
}

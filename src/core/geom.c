/* Geometry of the focal and pupil grids: see include/specklewfs/geom.h. */
#include "specklewfs/geom.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stddef.h>

void swfs_geom_init(swfs_geom *g)
{
    g->wavelen = g->teldiam = g->obscur = g->pixscale = g->pupdx = NAN;
    g->pupn = 0;
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
    if (missing)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: missing geometry keyword %s (expected WAVELEN, TELDIAM, "
                         "OBSCUR, PIXSCALE, PUPDX, PUPN)", what, missing);
    if (!(g->wavelen > 0 && g->teldiam > 0 && g->obscur >= 0 && g->obscur < 1 && g->pixscale > 0 && g->pupdx > 0))
        return swfs_fail(SWFS_ERR_VALUE, "%s: geometry out of range (WAVELEN=%g TELDIAM=%g OBSCUR=%g "
                         "PIXSCALE=%g PUPDX=%g)", what, g->wavelen, g->teldiam, g->obscur, g->pixscale, g->pupdx);
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

/* Geometry of the focal and pupil grids (docs/conventions.md's geometry keywords): the one domain
 * type every stage shares. Focal pixel (i, j) sits at ((i - floor(W/2)), (j - floor(H/2)))
 * PIXSCALE lambda/D; pupil sample (p, q) at (p - (PUPN - 1)/2, q - (PUPN - 1)/2) PUPDX. */
#ifndef SWFS_GEOM_H
#define SWFS_GEOM_H

#include <stddef.h>

#include "specklewfs/defs.h"

SWFS_BEGIN_DECLS

/* Missing values are NaN (pupn: 0). */
typedef struct swfs_geom {
    double wavelen;  /* WAVELEN [m] */
    double teldiam;  /* TELDIAM [m] */
    double obscur;   /* OBSCUR: central obstruction, fraction of the diameter */
    double pixscale; /* PIXSCALE [lambda/D per focal pixel] */
    double pupdx;    /* PUPDX [m per pupil sample] */
    long pupn;       /* PUPN: pupil samples across */
} swfs_geom;

void swfs_geom_init(swfs_geom *g); /* all missing */
/* SWFS_ERR_FORMAT naming `what` and the first missing keyword; SWFS_ERR_VALUE when a value
 * is out of its physical range. */
int swfs_geom_require(const swfs_geom *g, const char *what);
/* The keywords present (missing ones are not checked) against their physical ranges, each
 * message naming `what`, the keyword, its value and the range:
 *   WAVELEN 1e-8 .. 1e-3 m (10 nm .. 1 mm), TELDIAM 1e-3 .. 1e3 m, OBSCUR 0 .. <1,
 *   PIXSCALE 1e-3 .. 100 lambda/D per pixel, PUPDX 1e-6 .. 100 m, PUPN 2 .. 8192,
 * and, when present together, PUPDX <= TELDIAM/2 (two samples across the pupil) and
 * PUPN PUPDX >= TELDIAM (the pupil grid holds the pupil). SWFS_ERR_VALUE. */
int swfs_geom_check(const swfs_geom *g, const char *what);
/* SWFS_ERR_VALUE naming both sources and the keyword when two geometries disagree on a
 * keyword that both record (relative tolerance 1e-9): merging halos of different
 * wavelengths or samplings would be meaningless. */
int swfs_geom_check_same(const swfs_geom *a, const char *what_a, const swfs_geom *b, const char *what_b);
/* Keywords recorded by b but not by a are taken from b. */
void swfs_geom_union(swfs_geom *a, const swfs_geom *b);
/* Keywords recorded by `given` replace a's (the user's word over a file's header); returns
 * how many of them differed from a value a already had. */
int swfs_geom_overlay(swfs_geom *a, const swfs_geom *given);
/* The missing keywords as "WAVELEN PUPDX ..." into buf ("" when none); returns their count. */
int swfs_geom_missing(const swfs_geom *g, char *buf, size_t cap);

SWFS_END_DECLS

#endif

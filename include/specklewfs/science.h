/* The reduced science cube (`specklewfs reduce` writes it, `sync` and `speckles` read it):
 * registered frames (x, y, frame) in counts, the geometry keywords of the raw cubes, the
 * noise model (NOISEVAR, RDNOISE, NOISERAW, NOISEFAC, GAIN, GAINRAW), NCUBES and CUBEnnnn
 * (the raw camera file of each cube, in order), NBADPIX, REGISTER, and the extension
 * TRACK: 4 x nframes (peak x, peak y [pixels, before the shift], cube index, frame within
 * the cube), which `sync` cross-correlates with the WFS tip-tilt. This file is the one
 * owner of that layout. */
#ifndef SWFS_SCIENCE_H
#define SWFS_SCIENCE_H

#include <stddef.h>

#include "specklewfs/fits.h"

SWFS_BEGIN_DECLS

/* What reduce records besides the frames. */
typedef struct swfs_science_meta {
    double noise_var;   /* raw background noise variance [counts^2] (NaN: unknown) */
    double noise_fac;   /* variance factor of the registration's interpolation */
    double gain_raw;    /* [e-/count] from the raw cube (NaN: unknown) */
    size_t ncubes;
    const char *const *cubes; /* raw camera file names (base names are recorded) */
    size_t nbad;
    int registered;
} swfs_science_meta;

/* Keywords and the TRACK extension (track: 4 x nframes) on an output whose frames are
 * written; the caller commits. */
int swfs_science_write_meta(swfs_fits_out *o, const swfs_science_meta *m, const double *track, size_t nframes);

/* TRACK, NCUBES and the CUBEnnnn names of a reduced science cube, checked: every frame's
 * cube index in range and each cube's frames contiguous. */
typedef struct swfs_science_track {
    size_t nframes, ncubes;
    double *x, *y;     /* nframes peak positions [pixels] */
    size_t *first, *n; /* ncubes: first frame and frame count of each cube */
    char **camera;     /* ncubes raw camera file names */
} swfs_science_track;

int swfs_science_track_read(const char *path, swfs_science_track **out);
void swfs_science_track_free(swfs_science_track *t);

SWFS_END_DECLS

#endif

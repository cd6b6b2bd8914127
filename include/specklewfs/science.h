/* The reduced science cube (`specklewfs reduce` writes it, `sync` and `speckles` read it):
 * registered frames (x, y, frame) in counts, the geometry keywords of the raw cubes, the
 * noise model (NOISEVAR, RDNOISE, NOISERAW, NOISEFAC, GAIN, GAINRAW), NCUBES and CUBEnnnn
 * (the raw camera file of each cube, in order), NBADPIX, REGISTER, and the extension
 * TRACK: 4 x nframes (peak x, peak y [pixels, before the shift], cube index, frame within
 * the cube), which `sync` cross-correlates with the WFS tip-tilt; when the raw cubes were
 * milk logs (a timestamp table beside each, milklog.h) also the extension STAMPS: 3 x
 * nframes float64 (cnt0, whole seconds, nanoseconds: the stamp of the END of the frame's
 * exposure, exact as two numbers) with EXPTIME [s] where the raw header had it. This file
 * is the one owner of that layout. */
#ifndef SWFS_SCIENCE_H
#define SWFS_SCIENCE_H

#include <stddef.h>
#include <stdint.h>

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
    const uint64_t *cnt;  /* nframes camera counters (cnt0) and stamps [ns]: STAMPS (NULL: none) */
    const int64_t *stamp;
    double exptime;       /* [s] the raw headers' EXPTIME, the least over the cubes (0: none) */
    double exptime_res;   /* [s] the resolution it was written to (swfs_fits_in_key_double_res_opt) */
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
    double exptime;    /* [s] EXPTIME (0: none) */
    double exptime_res; /* [s] its resolution: the raw header's (EXPTRES) or its own text's, the coarser */
} swfs_science_track;

int swfs_science_track_read(const char *path, swfs_science_track **out);
void swfs_science_track_free(swfs_science_track *t);

/* The STAMPS extension: *n = the cube's frames, counters and stamps [ns] (caller frees
 * both), *exptime the EXPTIME recorded (0: none). SWFS_ERR_FORMAT naming the file when the
 * cube has no STAMPS (its raw cubes had no timestamp table) or a malformed one. */
int swfs_science_stamps_read(const char *path, uint64_t **cnt, int64_t **stamp, size_t *n, double *exptime);

SWFS_END_DECLS

#endif

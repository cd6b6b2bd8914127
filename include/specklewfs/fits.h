/* FITS input and output through CFITSIO, with the conventions of docs/conventions.md:
 *  - cubes: NAXIS1 = x (fastest), NAXIS2 = y, NAXIS3 = frame;
 *  - complex data (FITS standard §8.5): BITPIX -32/-64, NAXIS1 = 2 with CTYPE1 = 'COMPLEX'
 *    (real, imaginary), then x, y[, frame] -- the memory layout of C99 complex arrays;
 *  - geometry keywords WAVELEN, TELDIAM, OBSCUR, PIXSCALE, PUPDX, PUPN carried through;
 *  - every product records SWFSVER and the parameters that made it (HISTORY cards);
 *  - outputs are written to a unique part file and renamed on commit (atomic.h), so a
 *    failed run never leaves a file that looks complete; every HDU carries DATASUM and
 *    CHECKSUM, and readers refuse an HDU whose checksums do not match;
 *  - file names are taken literally (no CFITSIO extended syntax: "o[1].fits" is a name);
 *  - inputs may be gzip-compressed files or tile-compressed images (fpack), which CFITSIO
 *    reads transparently;
 *  - header values are parsed from their text by specklewfs (a logical, string or
 *    overlong value where a number is expected is an error naming file and keyword), and
 *    the geometry keywords are checked against their physical ranges (swfs_geom_check).
 * Real input of any BITPIX is scaled by BZERO/BSCALE into doubles (CFITSIO does it). */
#ifndef SWFS_FITS_H
#define SWFS_FITS_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/geom.h"

SWFS_BEGIN_DECLS


/* ---- reading ---------------------------------------------------------- */

typedef struct swfs_fits_in swfs_fits_in;

typedef struct swfs_fits_shape {
    size_t nx, ny, nz; /* nz = 1 for a 2-D image */
    int is_complex;    /* NAXIS1 = 2 with CTYPE1 = 'COMPLEX' */
    int bitpix;
} swfs_fits_shape;

/* Open `path` at the image HDU named `extname` (NULL: the first HDU holding an image). */
int swfs_fits_in_open(swfs_fits_in **out, const char *path, const char *extname);
void swfs_fits_in_close(swfs_fits_in *f);
/* Move to another image HDU of the same file by EXTNAME. */
int swfs_fits_in_move(swfs_fits_in *f, const char *extname);
int swfs_fits_in_has_ext(swfs_fits_in *f, const char *extname);
const swfs_fits_shape *swfs_fits_in_shape(const swfs_fits_in *f);
const char *swfs_fits_in_path(const swfs_fits_in *f);

/* Read frames [first, first + n) into buf (nx*ny*n values). Real reads of a complex
 * HDU, or complex reads of a real one, are SWFS_ERR_FORMAT. */
int swfs_fits_in_read_real(swfs_fits_in *f, size_t first, size_t n, double *buf);
int swfs_fits_in_read_cplx(swfs_fits_in *f, size_t first, size_t n, swfs_complex *buf);
/* Rows [first, first + n) of a real 2-D image (nx values each) into buf: one frame per row
 * of a log of vectors (milklog.h). SWFS_ERR_FORMAT for a cube or a complex image. */
int swfs_fits_in_read_rows(swfs_fits_in *f, size_t first, size_t n, double *buf);
/* Whole HDU into a new array. */
int swfs_fits_in_read_real_all(swfs_fits_in *f, swfs_real **out);
int swfs_fits_in_read_cplx_all(swfs_fits_in *f, swfs_cplx **out);

/* Keywords of the current HDU, falling back to the primary header. */
int swfs_fits_in_key_double(swfs_fits_in *f, const char *key, double *val);      /* missing: error */
int swfs_fits_in_key_double_opt(swfs_fits_in *f, const char *key, double *val, int *found);
/* The same, and *res the resolution the number was written to: half a unit in the last digit
 * of its text ("0.0082" -> 5e-5, "8.189E-3" -> 5e-7, "12" -> 0.5); a value rounded when it
 * was written lies within *res of the quantity (0 when the keyword is missing). */
int swfs_fits_in_key_double_res_opt(swfs_fits_in *f, const char *key, double *val, double *res, int *found);
int swfs_fits_in_key_string_opt(swfs_fits_in *f, const char *key, char *val, size_t cap, int *found);
/* An integer keyword in lo..hi (SWFS_ERR_VALUE naming file, keyword and range otherwise). */
int swfs_fits_in_key_long_opt(swfs_fits_in *f, const char *key, long lo, long hi, long *val, int *found);
/* The geometry keywords present, each checked against its physical range (swfs_geom_check). */
int swfs_fits_in_geom(swfs_fits_in *f, swfs_geom *g);
/* Geometry given in a file: a FITS file's first header with the keywords, or a text file of
 * "KEY = VALUE" lines (WAVELEN, TELDIAM, OBSCUR, PIXSCALE, PUPDX, PUPN in any case; '#'
 * comments). Keys it does not hold stay missing; a file with none of them, an unknown key or
 * a value out of its physical range is an error naming the file (and line). */
int swfs_geom_read_file(const char *path, swfs_geom *g);
/* SWFS_ERR_FORMAT unless the current HDU holds floating-point data (BITPIX -32 or -64): for
 * product layouts that fix it (an integer BITPIX there is a corrupt or foreign file).
 * `what` names the product in the message ("a HALO.fits product"). */
int swfs_fits_in_require_float(swfs_fits_in *f, const char *what);

/* Convenience: read one HDU of a file. */
int swfs_fits_read_real(const char *path, const char *extname, swfs_real **out, swfs_geom *g);
int swfs_fits_read_cplx(const char *path, const char *extname, swfs_cplx **out, swfs_geom *g);

/* ---- writing ---------------------------------------------------------- */

typedef struct swfs_fits_out swfs_fits_out;

/* Create the part file of `path` (atomic.h); nothing appears at `path` until
 * swfs_fits_out_commit(). The output checks of outpaths.h apply to `path`. */
int swfs_fits_out_create(swfs_fits_out **out, const char *path);
/* The same, started as a copy of every HDU of the file `from` (opened as swfs_fits_in_open
 * opens it), the primary HDU current: keys written next go there, and commit writes the checksums anew. */
int swfs_fits_out_copy(swfs_fits_out **out, const char *from, const char *path);
/* Write DATASUM/CHECKSUM on every HDU, close, fsync, rename to the final path (or keep it
 * for the group's commit, atomic.h), free. On failure the partial file is removed. */
int swfs_fits_out_commit(swfs_fits_out *o);
/* Close, remove the partial file, free. Safe on NULL. */
void swfs_fits_out_abort(swfs_fits_out *o);

/* Append an image HDU. extname NULL: the data go into the primary HDU (single-cube
 * files such as science.fits); otherwise an empty primary is written first if needed.
 * bitpix: -32 or -64 (and 16/32 for real data). At -32 a finite value that single precision
 * cannot hold (it would round to infinity, read back as NaN) is refused (SWFS_ERR_VALUE, the
 * file, HDU, value and its index named) before it is written; NaN and infinite values are
 * written as they are. The *_frames calls check the same. */
int swfs_fits_out_real(swfs_fits_out *o, const char *extname, const swfs_real *a, int bitpix);
int swfs_fits_out_cplx(swfs_fits_out *o, const char *extname, const swfs_cplx *a, int bitpix);
/* Start a cube HDU to be filled frame by frame with swfs_fits_out_*_frames. */
int swfs_fits_out_begin(swfs_fits_out *o, const char *extname, size_t nx, size_t ny, size_t nz,
                        int is_complex, int bitpix);
int swfs_fits_out_real_frames(swfs_fits_out *o, size_t first, size_t n, const double *buf);
int swfs_fits_out_cplx_frames(swfs_fits_out *o, size_t first, size_t n, const swfs_complex *buf);

/* Keywords on the current HDU. */
int swfs_fits_out_key_double(swfs_fits_out *o, const char *key, double v, const char *comment);
int swfs_fits_out_key_long(swfs_fits_out *o, const char *key, long v, const char *comment);
int swfs_fits_out_key_string(swfs_fits_out *o, const char *key, const char *v, const char *comment);
int swfs_fits_out_history(swfs_fits_out *o, const char *text);
/* Geometry keywords that are present in g. */
int swfs_fits_out_geom(swfs_fits_out *o, const swfs_geom *g);
/* SWFSVER, DATE, and one HISTORY card per provenance line (e.g. the command line and
 * parameters). Written on the current HDU. */
int swfs_fits_out_provenance(swfs_fits_out *o, const char *const *lines, size_t nlines);
/* Provenance lines set once and stamped on every HDU written afterwards. */
int swfs_fits_out_set_stamp(swfs_fits_out *o, const swfs_geom *g, const char *const *lines, size_t nlines);

SWFS_END_DECLS

#endif

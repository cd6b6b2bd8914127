/* milk / cacao telemetry logs (../shared/FORMATS.md): one stream's log is a folder or a
 * list of FITS files `SNAME_hh:mm:ss.sssssssss.fits` (or `.fits.fz`, tile-compressed; any
 * FITS file with a timestamp table works too), each with a `.txt` of the same name:
 * '#' comment lines, then one line per frame of 7 whitespace-separated columns (index in
 * file, main index, time since the first frame, absolute logging time, absolute
 * acquisition time, cnt0, cnt1) or of 2 columns (cnt0, stamp). Times are seconds of the
 * Unix epoch (or TAI: one clock per machine).
 *
 * The stamp of a frame is the acquisition time (column 5, the END of its exposure), or the
 * logging time (column 4) where column 5 is 0. Stamps are kept as int64 nanoseconds
 * parsed from the text (a double of ~1.7e9 s resolves only ~0.2 us). A frame is a vector
 * of nvals values: an N x M image per frame in a cube N x M x T (a 1-D vector is an N x 1
 * image), or one row of a plain N x T image. Files are ordered by their first stamp;
 * stamps must not go back (within a file or from one file to the next); a jump of more
 * than one in cnt0 is a dropped frame (counted). The FITS files are read through the
 * project's FITS layer (fits.h: CFITSIO, compressed inputs included), one file open at a
 * time. */
#ifndef SWFS_MILKLOG_H
#define SWFS_MILKLOG_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/defs.h"

SWFS_BEGIN_DECLS

/* "1700000000.123456789" (seconds, at most 9 decimals are kept exactly; more are rounded,
 * an exponent form goes through a double) -> nanoseconds. SWFS_ERR_FORMAT otherwise (no
 * message set: the caller names file and line). */
int swfs_milk_parse_time(const char *s, int64_t *ns);
/* ns -> "SSSSSSSSSS.NNNNNNNNN" (exactly: the inverse of swfs_milk_parse_time). */
void swfs_milk_format_time(int64_t ns, char *buf, size_t cap);

/* A timestamp table: rows frames of cnt0 and stamp [ns]. SWFS_ERR_FORMAT naming the file and
 * line for a line that is neither 7 nor 2 numbers or differs from the first line's column
 * count; SWFS_ERR_VALUE naming file, line and both values for a stamp before the previous
 * line's. The caller frees *cnt and *stamp. */
int swfs_milk_txt_read(const char *path, uint64_t **cnt, int64_t **stamp, size_t *rows);
/* The table beside a FITS file: X.fits, X.fits.fz, X.fits.gz -> X.txt (SWFS_ERR_ARG if the
 * name does not end in .fits[.fz|.gz] or the result does not fit). */
int swfs_milk_txt_path(const char *fits, char *txt, size_t cap);
/* Write a 7-column table (the milk logger's layout): frame k has main index index0 + k,
 * logging time logt[k] (NULL: the acquisition time) and acquisition time acq[k]; cnt1 = 0.
 * Atomic (atomic.h). */
int swfs_milk_txt_write(const char *path, const uint64_t *cnt, const int64_t *acq, const int64_t *logt, size_t n,
                        size_t index0);
/* The log file name of a stream whose first frame has stamp ns: "SNAME_hh:mm:ss.sssssssss"
 * (UTC time of day; add ".fits" / ".txt"). */
void swfs_milk_file_stem(const char *sname, int64_t ns, char *buf, size_t cap);

typedef struct swfs_milklog swfs_milklog;

typedef struct swfs_milklog_info {
    size_t nframes;     /* frames over all files */
    size_t nvals;       /* values per frame */
    size_t nx, ny;      /* frame shape (a vector: nvals x 1) */
    size_t nfiles;
    uint64_t dropped;   /* cnt0 jumps > 1, summed over the log (file boundaries included) */
    uint64_t restarts;  /* cnt0 going back (a restarted writer) */
    double exptime;     /* [s] EXPTIME of the first file's header (0: none) */
    const char *source; /* the folder or the first file (for messages) */
} swfs_milklog_info;

/* One stream's log: npaths = 1 folder (its *.fits, *.fits.fz and *.fits.gz with a .txt
 * beside) or npaths files. Errors name the file: no FITS file in a folder, a missing .txt,
 * frames in the FITS file differing from the rows of its .txt (both files and both counts),
 * frame sizes differing between files, stamps going back. */
int swfs_milklog_open(swfs_milklog **out, const char *const *paths, size_t npaths);
void swfs_milklog_free(swfs_milklog *l);
const swfs_milklog_info *swfs_milklog_get_info(const swfs_milklog *l);
const uint64_t *swfs_milklog_counters(const swfs_milklog *l); /* nframes cnt0 */
const int64_t *swfs_milklog_stamps(const swfs_milklog *l);    /* nframes stamps [ns] */
/* The FITS file that holds frame k (for messages). */
const char *swfs_milklog_file_of(const swfs_milklog *l, size_t k);
/* Frames [first, first + n) into out (n x nvals, may cross files). Opens the file that
 * holds them when it is not the one open: no allocation while reading within a file. */
int swfs_milklog_read(swfs_milklog *l, size_t first, size_t n, double *out);

SWFS_END_DECLS

#endif

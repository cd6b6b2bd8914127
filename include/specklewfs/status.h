/* Status codes and the last error message.
 *
 * Every library call that can fail returns an int status (SWFS_OK = 0) and, on failure,
 * leaves a human-readable message that says what and where, e.g.
 *   "speckles.fits: cube is 60x60x980 but science.fits is 60x60x960".
 * The library never prints and never exits; cli/ chooses messages and exit codes.
 * The message is thread-local, so workers can fail independently. */
#ifndef SWFS_STATUS_H
#define SWFS_STATUS_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

enum swfs_status {
    SWFS_OK = 0,
    SWFS_ERR_ARG,      /* a caller passed an invalid argument or option */
    SWFS_ERR_NOMEM,    /* allocation failed */
    SWFS_ERR_IO,       /* file could not be opened, read or written */
    SWFS_ERR_FORMAT,   /* file is not what it must be (not FITS, missing keyword, wrong type) */
    SWFS_ERR_SHAPE,    /* array shapes do not match */
    SWFS_ERR_VALUE,    /* a value is out of range, NaN/Inf where not allowed */
    SWFS_ERR_NUMERIC,  /* a computation has no valid result (e.g. nothing valid to estimate) */
    SWFS_ERR_INTERNAL,
    SWFS_ERR_STOPPED   /* the caller's progress callback asked the run to stop (swfs_progress_fn) */
};

/* Set the thread's error message (printf-style) and return code, so that
 *   return swfs_fail(SWFS_ERR_SHAPE, "%s: ...", path);
 * is the whole error path. */
int swfs_fail(int code, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

/* Prefix the current message with more context ("reading science.fits: <old message>"). */
int swfs_fail_context(int code, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

const char *swfs_last_error(void);
void swfs_clear_error(void);

/* A value for a message, into buf: "is 3.2e+31", or "is not finite (NaN or infinite)" (CFITSIO
 * reads a stored infinity back as NaN, so a value read from a file cannot tell which). */
const char *swfs_value_words(double v, char *buf, size_t cap);
const char *swfs_status_name(int code);

/* Progress of a long run: `done` of `total` units of the named stage. The library calls
 * it (when given one) and never prints; the application decides what to show. It returns 0
 * to go on; any other value stops the run at that point: the call returns SWFS_ERR_STOPPED
 * ("<stage>: stopped by the caller at <done> of <total>") and, like any failure, leaves none
 * of its output files (atomic.h). The callback is how an application offers Ctrl-C, a
 * deadline or a cancel button; it is called on the caller's thread only. */
typedef int (*swfs_progress_fn)(void *ctx, const char *stage, size_t done, size_t total);

/* Call `progress` (if not NULL) and turn a request to stop into SWFS_ERR_STOPPED with its
 * message; SWFS_OK otherwise. Every progress report of the library goes through it. */
int swfs_progress_report(swfs_progress_fn progress, void *ctx, const char *stage, size_t done, size_t total);

SWFS_END_DECLS

#endif

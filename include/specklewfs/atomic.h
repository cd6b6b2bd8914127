/* The one way products reach their final names: every output (FITS or text) is written to
 * a part file NAME.part.<pid>.<random> beside it, flushed to disk (fsync) and renamed onto
 * NAME. A failed write removes the part and leaves a previous NAME as it was; two runs
 * writing the same NAME never share a part file; a reader never sees half a file under
 * NAME.
 *
 * Products of one run that belong together (the four files of `simulate`, the halo and
 * the checkpoint of `merge`, ...) are grouped: between swfs_outputs_begin() and
 * swfs_outputs_end(), a commit on this thread finishes and syncs its part but does not
 * rename it; swfs_outputs_end(1) renames them all, swfs_outputs_end(0) removes them, so a
 * run that fails half way leaves none of them under a final name. */
#ifndef SWFS_ATOMIC_H
#define SWFS_ATOMIC_H

#include <stdio.h>

#include "specklewfs/defs.h"

SWFS_BEGIN_DECLS

typedef struct swfs_atomic swfs_atomic;

/* Start the output `path`. stdio = 1: the part is created (exclusively) and opened as a
 * stdio stream for swfs_atomic_stream(); stdio = 0: only its unique name is chosen, for
 * a writer that creates the file itself (CFITSIO). SWFS_ERR_IO naming the folder and the
 * system's reason when it cannot be created. */
int swfs_atomic_begin(swfs_atomic **out, const char *path, int stdio);
const char *swfs_atomic_part(const swfs_atomic *a);
const char *swfs_atomic_path(const swfs_atomic *a);
FILE *swfs_atomic_stream(swfs_atomic *a);
/* Flush and fsync the part, then rename it onto the final name (inside a group: keep it
 * for swfs_outputs_end). On failure the part is removed and the message names the file
 * and the system's reason. Frees a. */
int swfs_atomic_commit(swfs_atomic *a);
/* Remove the part, free a. Safe on NULL. */
void swfs_atomic_abort(swfs_atomic *a);

/* Groups (thread-local, nestable: only the outermost end acts). */
void swfs_outputs_begin(void);
/* commit = 1: rename every part of the group into place (if one rename fails, the group's
 * other files are removed and the error returned); commit = 0: remove the parts. */
int swfs_outputs_end(int commit);

/* Remove every part file not yet renamed into place (any thread's, groups' too). Only
 * async-signal-safe calls: for a handler that then ends the process on SIGINT/SIGTERM, so
 * that a run killed at once leaves no NAME.part.* behind. */
void swfs_atomic_remove_parts(void);

SWFS_END_DECLS

#endif

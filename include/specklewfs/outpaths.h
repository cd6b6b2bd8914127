/* A command's files checked before any work: every output against every input and every
 * other output (the same file by device and inode, also for outputs that do not exist yet:
 * by their folder's device and inode and their name), special files refused (a FIFO or
 * device as input would block or never end; as output it would be replaced by a regular
 * file, as would a symbolic link), output folders checked for existence and write
 * permission with the system's reason, and names that would be read as compressed files
 * (.gz, .fz, ...) refused as outputs.
 *
 * Usage (inherited status, like CFITSIO): create, add every input and output with a role
 * that names it in messages ("science cube", "output halo", ...), read the status:
 *     swfs_paths *p; swfs_paths_create(&p);
 *     swfs_paths_input(p, "science cube", sci);
 *     swfs_paths_output(p, "output", out);
 *     int rc = swfs_paths_status(p); swfs_paths_free(p);
 * Each call checks at once and returns the status; after a failure the later calls do
 * nothing and return it again. */
#ifndef SWFS_OUTPATHS_H
#define SWFS_OUTPATHS_H

#include "specklewfs/defs.h"

#include <stdio.h>

SWFS_BEGIN_DECLS

typedef struct swfs_paths swfs_paths;

int swfs_paths_create(swfs_paths **out);
void swfs_paths_free(swfs_paths *p);
/* An input file. A missing file is left to its reader (which names it); a folder, FIFO,
 * device or socket is refused. NULL path: nothing to check. */
int swfs_paths_input(swfs_paths *p, const char *role, const char *path);
/* An input that may be a folder (its files are added separately) or a file. */
int swfs_paths_input_or_dir(swfs_paths *p, const char *role, const char *path);
/* An output file. NULL path: nothing to check. */
int swfs_paths_output(swfs_paths *p, const char *role, const char *path);
int swfs_paths_status(const swfs_paths *p);

/* The check every reader makes itself (also when a command's list missed the file): a
 * regular file, or a missing one (SWFS_OK: the reader's open reports it). `what` names
 * the kind of file in the message. */
int swfs_input_check(const char *path, const char *what);

/* One line of a text input (the text readers' fgets): reads it into buf (cap bytes) and
 * returns 1; returns 0 at the end of the file, or when the line does not fit in buf, then
 * with *rc = SWFS_ERR_FORMAT naming path and lineno: a reader refuses the file rather
 * than read the rest of the line as a line of its own (a long comment's tail as a setting). */
int swfs_text_line(FILE *f, char *buf, int cap, const char *path, long lineno, int *rc);

/* An output folder and its parents made where missing (mkdir -p); SWFS_ERR_IO naming the
 * folder and the system's reason when it cannot be made or is not a folder. */
int swfs_make_dirs(const char *path);

/* The folders a run makes (thread-local, between the two calls): swfs_made_dirs_end(0),
 * for a run that failed or was stopped, removes those of them left empty (its part files
 * and products gone: atomic.h), the last made first; swfs_made_dirs_end(1) keeps them.
 * swfs_make_dirs records what it makes while recording is on. */
void swfs_made_dirs_begin(void);
void swfs_made_dirs_end(int keep);

SWFS_END_DECLS

#endif

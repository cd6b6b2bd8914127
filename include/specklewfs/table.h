/* Text products: numeric tables (TSV) and atomic text files.
 *
 * A table file is one header line "# name1<TAB>name2..." followed by rows of as many
 * tab-separated numbers ("nan" where a value is undefined); further lines starting with
 * '#' are comments. The closed loop's loop.tsv and the demo's recovery.tsv are such
 * tables. */
#ifndef SWFS_TABLE_H
#define SWFS_TABLE_H

#include "specklewfs/defs.h"
#include "specklewfs/recovery.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_table {
    size_t ncols, nrows;
    char **names; /* ncols column names */
    double *v;    /* nrows x ncols, row-major: v[r * ncols + c] */
} swfs_table;

/* Read a table file; SWFS_ERR_FORMAT naming the file and line when a row is not ncols
 * numbers or the header is missing. */
int swfs_table_read(const char *path, swfs_table **out);
void swfs_table_free(swfs_table *t);
/* Index of the column named `name`, or -1. */
long swfs_table_col(const swfs_table *t, const char *name);

/* Write len bytes to path through the atomic writer (atomic.h: a part file, fsync, rename;
 * inside an output group, renamed with the group): a failure leaves no file under the final
 * name (and the previous one, if any, untouched). */
int swfs_text_write(const char *path, const char *data, size_t len);

/* The demo's recovery table (one row per noise level, the columns `specklewfs demo`
 * prints: sigma, valid_pct, g_undef_pct, the NCP error of each estimator in nm, median_SNR,
 * time_s); seconds may be NULL (no time column). */
int swfs_recovery_table_write(const char *path, const swfs_recovery *r, const double *seconds, size_t n);

SWFS_END_DECLS

#endif

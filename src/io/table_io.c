/* Text products: TSV tables and atomic text files (include/specklewfs/table.h). */
#include "specklewfs/table.h"
#include "specklewfs/atomic.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <math.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Bounds that no table of ours comes near: a corrupt file is refused, not allocated. */
#define MAX_COLS 256
#define MAX_ROWS 1000000

int swfs_text_write(const char *path, const char *data, size_t len)
{
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    if (len && fwrite(data, 1, len, swfs_atomic_stream(a)) != len) {
        const int err = errno;
        swfs_atomic_abort(a);
        return swfs_fail(SWFS_ERR_IO, "%s: writing the output failed: %s (nothing written under that name)", path,
                         strerror(err));
    }
    return swfs_atomic_commit(a); /* inside an output group: renamed with the group (atomic.h) */
}

void swfs_table_free(swfs_table *t)
{
    if (!t) return;
    for (size_t c = 0; c < t->ncols && t->names; c++) free(t->names[c]);
    free(t->names);
    free(t->v);
    free(t);
}

long swfs_table_col(const swfs_table *t, const char *name)
{
    for (size_t c = 0; c < t->ncols; c++)
        if (!strcmp(t->names[c], name)) return (long)c;
    return -1;
}

/* The header "# a<TAB>b..." into t->names. */
static int parse_header(swfs_table *t, char *line, const char *path)
{
    line[strcspn(line, "\r\n")] = '\0';
    if (line[0] != '#') return swfs_fail(SWFS_ERR_FORMAT, "%s: line 1 is not a '# name<TAB>name...' header", path);
    char *s = line + 1;
    while (*s == ' ') s++;
    size_t n = 1;
    for (const char *q = s; *q; q++) n += *q == '\t';
    if (!*s || n > MAX_COLS)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: header has %zu columns, expected 1 to %d", path, *s ? n : 0,
                         MAX_COLS);
    t->names = calloc(n, sizeof *t->names);
    if (!t->names) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    for (size_t c = 0; c < n; c++) {
        size_t len = strcspn(s, "\t");
        t->names[c] = malloc(len + 1);
        if (!t->names[c]) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
        memcpy(t->names[c], s, len);
        t->names[c][len] = '\0';
        t->ncols = c + 1;
        s += len + (s[len] == '\t');
    }
    return SWFS_OK;
}

/* One data row into row[ncols]. */
static int parse_row(const swfs_table *t, char *line, double *row, const char *path, size_t lineno)
{
    char *s = line;
    for (size_t c = 0; c < t->ncols; c++) {
        char *end;
        errno = 0;
        row[c] = strtod(s, &end);
        if (end == s || (*end && *end != '\t' && *end != '\n' && *end != '\r'))
            return swfs_fail(SWFS_ERR_FORMAT, "%s: line %zu, column %zu (%s): expected a number", path, lineno, c + 1,
                             t->names[c]);
        s = end;
        if (c + 1 < t->ncols) {
            if (*s != '\t')
                return swfs_fail(SWFS_ERR_FORMAT, "%s: line %zu has %zu values, expected %zu (the header's columns)",
                                 path, lineno, c + 1, t->ncols);
            s++;
        }
    }
    s += strspn(s, "\r\n");
    if (*s)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: line %zu has more than %zu values (the header's columns)", path,
                         lineno, t->ncols);
    return SWFS_OK;
}

int swfs_table_read(const char *path, swfs_table **out)
{
    *out = NULL;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open: %s", path, strerror(errno));
    swfs_table *t = calloc(1, sizeof *t);
    char *line = NULL;
    size_t cap = 0, rows_cap = 0, lineno = 0;
    int rc = t ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    while (!rc && getline(&line, &cap, f) >= 0) {
        lineno++;
        if (!t->names) {
            rc = parse_header(t, line, path);
            continue;
        }
        if (line[0] == '#' || line[strspn(line, " \t\r\n")] == '\0') continue;
        if (t->nrows == rows_cap) {
            size_t nc = rows_cap ? 2 * rows_cap : 16;
            double *v = nc <= MAX_ROWS ? realloc(t->v, nc * t->ncols * sizeof *v) : NULL;
            if (!v) {
                rc = swfs_fail(SWFS_ERR_FORMAT, "%s: more than %d rows or out of memory", path, MAX_ROWS);
                break;
            }
            t->v = v;
            rows_cap = nc;
        }
        if (!(rc = parse_row(t, line, t->v + t->nrows * t->ncols, path, lineno))) t->nrows++;
    }
    if (!rc && ferror(f)) rc = swfs_fail(SWFS_ERR_IO, "%s: read error", path);
    if (!rc && !t->names) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: empty file, expected a '# name...' header", path);
    free(line);
    fclose(f);
    if (rc) {
        swfs_table_free(t);
        return rc;
    }
    *out = t;
    return SWFS_OK;
}

/* ---- the demo's recovery table --------------------------------------------- */

/* One column per line: a new estimator is one more line here (and in the demo's printout). */
static const struct {
    const char *name;
    size_t off;
    double scale;
} recovery_cols[] = {
    {"sigma", offsetof(swfs_recovery, sigma), 1.0},
    {"valid_pct", offsetof(swfs_recovery, valid_fraction), 100.0},
    {"g_undef_pct", offsetof(swfs_recovery, bad_radicand), 100.0},
    {"paper_nm", offsetof(swfs_recovery, err_paper), 1e9},
    {"HALO_nm", offsetof(swfs_recovery, err_halo), 1e9},
    {"HALO_LF_nm", offsetof(swfs_recovery, err_lf), 1e9},
    {"HALO_LF+SNR_nm", offsetof(swfs_recovery, err_lf_snr), 1e9},
    {"joint_fit_nm", offsetof(swfs_recovery, err_fit), 1e9},
    {"median_SNR", offsetof(swfs_recovery, median_snr), 1.0},
};

int swfs_recovery_table_write(const char *path, const swfs_recovery *r, const double *seconds, size_t n)
{
    const size_t ncol = sizeof recovery_cols / sizeof recovery_cols[0];
    size_t cap = 256 + n * (ncol + 1) * 32 + ncol * 32;
    char *buf = malloc(cap);
    if (!buf) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    size_t len = 0;
    for (size_t c = 0; c < ncol; c++)
        len += (size_t)snprintf(buf + len, cap - len, "%s%s", c ? "\t" : "# ", recovery_cols[c].name);
    len += (size_t)snprintf(buf + len, cap - len, "%s\n", seconds ? "\ttime_s" : "");
    for (size_t k = 0; k < n; k++) {
        for (size_t c = 0; c < ncol; c++) {
            double v = *(const double *)((const char *)&r[k] + recovery_cols[c].off) * recovery_cols[c].scale;
            len += (size_t)snprintf(buf + len, cap - len, c ? "\t%.9g" : "%.9g", v);
        }
        if (seconds) len += (size_t)snprintf(buf + len, cap - len, "\t%.3f", seconds[k]);
        len += (size_t)snprintf(buf + len, cap - len, "\n");
    }
    int rc = swfs_text_write(path, buf, len);
    free(buf);
    return rc;
}

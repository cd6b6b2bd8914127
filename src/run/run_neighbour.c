/* The telemetry file before or after another one in a logger's series of files: shared by
 * sync (which follows a cube across files) and speckles (which stacks a space-time map's lags
 * across them). */
#include "specklewfs/source.h"
#include "run_internal.h"

#include <dirent.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

/* The name with its last run of digits (in the base name) moved by dir, keeping its width:
 * slopes_009.fits -> slopes_010.fits; 0 when there is none or it would go below zero. */
static int numbered_neighbour(const char *name, int dir, char *out, size_t cap)
{
    const char *base = strrchr(name, '/');
    base = base ? base + 1 : name;
    const char *end = NULL;
    for (const char *q = base; *q; q++)
        if (*q >= '0' && *q <= '9' && !(q[1] >= '0' && q[1] <= '9')) end = q + 1;
    if (!end) return 0;
    const char *beg = end;
    while (beg > base && beg[-1] >= '0' && beg[-1] <= '9') beg--;
    if (end - beg > 18) return 0;
    long long v = strtoll(beg, NULL, 10) + dir;
    if (v < 0) return 0;
    int len = snprintf(out, cap, "%.*s%0*lld%s", (int)(beg - name), name, (int)(end - beg), v, end);
    return len > 0 && (size_t)len < cap;
}

/* Two file names that differ in digits only (the same length, the same other characters):
 * the files of one logger, numbered or time-stamped (slopes_20261126T010000.fits). */
static int same_pattern(const char *a, const char *b)
{
    if (strlen(a) != strlen(b)) return 0;
    for (; *a; a++, b++) {
        const int da = *a >= '0' && *a <= '9', db = *b >= '0' && *b <= '9';
        if (da != db || (!da && *a != *b)) return 0;
    }
    return 1;
}

static int cmp_names(const void *a, const void *b) { return strcmp(*(char *const *)a, *(char *const *)b); }

/* name's neighbour (dir -1 or +1) among the files of its folder that share its pattern, in the
 * order of their names (for fixed-width numbers and time stamps, the order they were written):
 * the file after slopes_20261126T010000.fits may be slopes_20261126T010640.fits. 1 with buf
 * set (name's folder part + the neighbour's name), 0 if none. */
static int listed_neighbour(const char *logdir, const char *name, int dir, char *buf, size_t cap)
{
    char path[8192], folder[8192];
    if (swfs_telemetry_path(logdir, name, path, sizeof path)) return 0;
    const char *base = strrchr(path, '/');
    const size_t fl = base ? (size_t)(base - path) : 0;
    snprintf(folder, sizeof folder, "%.*s", (int)(fl ? fl : 1), fl ? path : ".");
    base = base ? base + 1 : path;
    DIR *d = opendir(folder);
    if (!d) return 0;
    char **names = NULL;
    size_t n = 0, capn = 0;
    int ok = 1;
    for (struct dirent *e; ok && (e = readdir(d));) {
        if (!same_pattern(e->d_name, base)) continue;
        if (n == capn) {
            char **t = realloc(names, (capn ? 2 * capn : 16) * sizeof *t);
            if (!t) { ok = 0; break; }
            names = t;
            capn = capn ? 2 * capn : 16;
        }
        if (!(names[n] = strdup(e->d_name))) { ok = 0; break; }
        n++;
    }
    closedir(d);
    int found = 0;
    if (ok && n) {
        qsort(names, n, sizeof *names, cmp_names);
        for (size_t k = 0; k < n; k++) {
            if (strcmp(names[k], base)) continue;
            const size_t j = dir > 0 ? k + 1 : k - 1; /* k = 0, dir < 0: wraps to SIZE_MAX */
            if (j < n) {
                const char *slash = strrchr(name, '/');
                const int len = snprintf(buf, cap, "%.*s%s", slash ? (int)(slash - name + 1) : 0, name, names[j]);
                found = len > 0 && (size_t)len < cap;
            }
            break;
        }
    }
    for (size_t k = 0; k < n; k++) free(names[k]);
    free(names);
    return found;
}

/* The n names at order, order + stride, ... (a field of an array of structs) */
static const char *nth(const char *order, size_t stride, size_t k) { return order + k * stride; }

/* name's neighbour in the order the names first appear in that list (repeats skipped). */
static int ordered_neighbour(const char *order, size_t stride, size_t n, const char *name, int step, char *buf,
                             size_t cap)
{
    const char *prev = NULL, *hit = NULL;
    int found = 0;
    for (size_t k = 0; k < n && !hit; k++) {
        const char *f = nth(order, stride, k);
        int seen = 0;
        for (size_t q = 0; q < k && !seen; q++) seen = !strcmp(nth(order, stride, q), f);
        if (seen) continue;
        if (found) hit = step > 0 ? f : prev;
        else if (!strcmp(f, name)) found = 1;
        else prev = f;
    }
    if (!hit && found && step < 0) hit = prev;
    return hit && snprintf(buf, cap, "%s", hit) < (int)cap;
}

int swfs_telemetry_neighbour_(const char *dir, const char *name, int step, const char *order, size_t stride, size_t n,
                              char *buf, size_t cap)
{
    char path[8192];
    if (numbered_neighbour(name, step, buf, cap) && !swfs_telemetry_path(dir, buf, path, sizeof path) &&
        access(path, R_OK) == 0)
        return 1;
    if (listed_neighbour(dir, name, step, buf, cap)) return 1;
    return order && ordered_neighbour(order, stride, n, name, step, buf, cap);
}

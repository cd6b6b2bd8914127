/* milk / cacao telemetry logs: see include/specklewfs/milklog.h. */
#include "specklewfs/milklog.h"
#include "specklewfs/atomic.h"
#include "specklewfs/fits.h"
#include "specklewfs/numeric.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <ctype.h>
#include <dirent.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#define NS_PER_S 1000000000LL

int swfs_milk_parse_time(const char *s, int64_t *ns) { return swfs_time_parse_ns(s, ns) ? SWFS_ERR_FORMAT : SWFS_OK; }

void swfs_milk_format_time(int64_t ns, char *buf, size_t cap) { swfs_time_format_ns(ns, buf, cap); }

void swfs_milk_file_stem(const char *sname, int64_t ns, char *buf, size_t cap)
{
    const time_t s = (time_t)(ns / NS_PER_S);
    struct tm tm;
    gmtime_r(&s, &tm);
    snprintf(buf, cap, "%s_%02d:%02d:%02d.%09lld", sname, tm.tm_hour, tm.tm_min, tm.tm_sec,
             (long long)(ns % NS_PER_S));
}

int swfs_milk_txt_path(const char *fits, char *txt, size_t cap)
{
    static const char *ext[] = {".fits.fz", ".fits.gz", ".fits"};
    const size_t n = strlen(fits);
    for (size_t k = 0; k < sizeof ext / sizeof ext[0]; k++) {
        const size_t e = strlen(ext[k]);
        if (n > e && !strcmp(fits + n - e, ext[k])) {
            const int w = snprintf(txt, cap, "%.*s.txt", (int)(n - e), fits);
            if (w < 0 || (size_t)w >= cap) return swfs_fail(SWFS_ERR_ARG, "%s: path too long", fits);
            return SWFS_OK;
        }
    }
    return swfs_fail(SWFS_ERR_ARG, "%s: a milk log file name ends in .fits, .fits.fz or .fits.gz", fits);
}

/* One data line: its columns -> (cnt0, stamp). ncol: the first line's count (0: not yet). */
static int parse_line(const char *path, long lineno, char *s, int *ncol, uint64_t *cnt, int64_t *stamp)
{
    char *tok[8];
    int n = 0;
    for (char *t = strtok(s, " \t\r\n"); t; t = strtok(NULL, " \t\r\n")) {
        if (n == 8) break;
        tok[n++] = t;
    }
    if ((n != 7 && n != 2) || (*ncol && n != *ncol))
        return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: %d columns; expected %s", path, lineno, n,
                         *ncol ? (*ncol == 7 ? "7 as the lines before" : "2 as the lines before")
                               : "7 (index, main index, dt, logging time, acquisition time, cnt0, cnt1) or 2 (cnt0, "
                                 "stamp)");
    *ncol = n;
    const char *c = n == 7 ? tok[5] : tok[0];
    char *end = NULL;
    errno = 0;
    const unsigned long long v = strtoull(c, &end, 10);
    if (errno || *end || c[0] == '-')
        return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: cnt0 '%s' is not a counter (a non-negative integer)", path, lineno, c);
    *cnt = (uint64_t)v;
    int64_t acq = 0, logt = 0;
    const char *ts = n == 7 ? tok[4] : tok[1];
    if (swfs_milk_parse_time(ts, &acq))
        return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: time stamp '%s' is not a non-negative number of seconds", path, lineno,
                         ts);
    if (n == 7 && acq == 0) { /* some writers leave the acquisition time at 0: the logging time */
        if (swfs_milk_parse_time(tok[3], &logt))
            return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: logging time '%s' is not a non-negative number of seconds", path,
                             lineno, tok[3]);
        acq = logt;
    }
    *stamp = acq;
    return SWFS_OK;
}

int swfs_milk_txt_read(const char *path, uint64_t **cnt, int64_t **stamp, size_t *rows)
{
    *cnt = NULL;
    *stamp = NULL;
    *rows = 0;
    if (swfs_input_check(path, "timestamp table")) return SWFS_ERR_IO;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the timestamp table: %s", path, strerror(errno));
    size_t cap = 0, n = 0;
    uint64_t *c = NULL;
    int64_t *t = NULL;
    char line[4096];
    long lineno = 0, prev_line = 0;
    int ncol = 0, rc = SWFS_OK;
    while (!rc && fgets(line, sizeof line, f)) {
        lineno++;
        char *s = line;
        while (*s == ' ' || *s == '\t') s++;
        if (*s == '#' || *s == '\n' || *s == '\r' || !*s) continue;
        if (n == cap) {
            cap = cap ? 2 * cap : 1024;
            uint64_t *nc = realloc(c, cap * sizeof *nc);
            if (nc) c = nc;
            int64_t *nt = nc ? realloc(t, cap * sizeof *nt) : NULL;
            if (nt) t = nt;
            if (!nc || !nt) { rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory at line %ld", path, lineno); break; }
        }
        if ((rc = parse_line(path, lineno, s, &ncol, &c[n], &t[n]))) break;
        if (n && t[n] < t[n - 1]) {
            char a[40], b[40];
            swfs_milk_format_time(t[n], a, sizeof a);
            swfs_milk_format_time(t[n - 1], b, sizeof b);
            rc = swfs_fail(SWFS_ERR_VALUE, "%s:%ld: time stamp %s s goes back from %s s (line %ld); stamps must not "
                           "decrease", path, lineno, a, b, prev_line);
            break;
        }
        prev_line = lineno;
        n++;
    }
    fclose(f);
    if (!rc && !n) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the timestamp table has no frame lines", path);
    if (rc) {
        free(c);
        free(t);
        return rc;
    }
    *cnt = c;
    *stamp = t;
    *rows = n;
    return SWFS_OK;
}

int swfs_milk_txt_write(const char *path, const uint64_t *cnt, const int64_t *acq, const int64_t *logt, size_t n,
                        size_t index0)
{
    swfs_atomic *a = NULL;
    int rc = swfs_atomic_begin(&a, path, 1);
    if (rc) return rc;
    FILE *f = swfs_atomic_stream(a);
    fprintf(f, "# milk stream log (specklewfs)\n# localcnt  cnt  dt[s]  logtime[s]  acqtime[s]  cnt0  cnt1\n");
    for (size_t k = 0; k < n; k++) {
        char ta[40], tl[40];
        swfs_milk_format_time(acq[k], ta, sizeof ta);
        swfs_milk_format_time(logt ? logt[k] : acq[k], tl, sizeof tl);
        const double dt = 1e-9 * (double)((logt ? logt[k] : acq[k]) - (logt ? logt[0] : acq[0]));
        fprintf(f, "%zu %zu %.9f %s %s %llu 0\n", k, index0 + k, dt, tl, ta, (unsigned long long)cnt[k]);
    }
    return swfs_atomic_commit(a);
}

/* ---- a stream's log ---------------------------------------------------------------- */

typedef struct mfile {
    char *fits;
    size_t first, n;    /* frames [first, first + n) of the log */
    int rows;           /* 1: one frame per row of a 2-D image */
    int64_t t0;         /* first stamp (sorting) */
    uint64_t *cnt;
    int64_t *stamp;
} mfile;

struct swfs_milklog {
    swfs_milklog_info info;
    char *source;
    mfile *f;
    uint64_t *cnt;
    int64_t *stamp;
    swfs_fits_in *open;
    size_t open_idx;
};

void swfs_milklog_free(swfs_milklog *l)
{
    if (!l) return;
    for (size_t k = 0; l->f && k < l->info.nfiles; k++) {
        free(l->f[k].fits);
        free(l->f[k].cnt);
        free(l->f[k].stamp);
    }
    free(l->f);
    free(l->cnt);
    free(l->stamp);
    free(l->source);
    swfs_fits_in_close(l->open);
    free(l);
}

static int is_log_name(const char *name)
{
    static const char *ext[] = {".fits", ".fits.fz", ".fits.gz"};
    const size_t n = strlen(name);
    if (name[0] == '.') return 0;
    for (size_t k = 0; k < 3; k++) {
        const size_t e = strlen(ext[k]);
        if (n > e && !strcmp(name + n - e, ext[k])) return 1;
    }
    return 0;
}

static int cmp_str(const void *a, const void *b) { return strcmp(*(char *const *)a, *(char *const *)b); }

/* The FITS files of a folder (sorted by name; the caller sorts them by stamp later). */
static int list_dir(const char *dir, char ***names, size_t *n)
{
    DIR *d = opendir(dir);
    if (!d) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the log folder: %s", dir, strerror(errno));
    size_t cap = 0, cnt = 0;
    char **v = NULL;
    int rc = SWFS_OK;
    for (struct dirent *e; !rc && (e = readdir(d));) {
        if (!is_log_name(e->d_name)) continue;
        if (cnt == cap) {
            cap = cap ? 2 * cap : 16;
            char **nv = realloc(v, cap * sizeof *nv);
            if (!nv) { rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", dir); break; }
            v = nv;
        }
        const size_t len = strlen(dir) + strlen(e->d_name) + 2;
        if (!(v[cnt] = malloc(len))) { rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", dir); break; }
        snprintf(v[cnt++], len, "%s/%s", dir, e->d_name);
    }
    closedir(d);
    if (!rc && !cnt) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no log file (*.fits, *.fits.fz, *.fits.gz) in the folder", dir);
    if (rc) {
        for (size_t k = 0; k < cnt; k++) free(v[k]);
        free(v);
        return rc;
    }
    qsort(v, cnt, sizeof *v, cmp_str);
    *names = v;
    *n = cnt;
    return SWFS_OK;
}

/* One file: its table, its shape (frames = the table's rows), EXPTIME of the first. */
static int load_file(swfs_milklog *l, mfile *m, size_t idx)
{
    char txt[8192];
    int rc = swfs_milk_txt_path(m->fits, txt, sizeof txt);
    size_t rows = 0;
    if (!rc) {
        struct stat sb;
        if (stat(txt, &sb) != 0)
            return swfs_fail(SWFS_ERR_IO, "%s: no timestamp table %s beside it (%s)", m->fits, txt, strerror(errno));
        rc = swfs_milk_txt_read(txt, &m->cnt, &m->stamp, &rows);
    }
    swfs_fits_in *f = NULL;
    if (!rc) rc = swfs_fits_in_open(&f, m->fits, NULL);
    if (rc) {
        swfs_fits_in_close(f);
        return rc;
    }
    const swfs_fits_shape *s = swfs_fits_in_shape(f);
    size_t frames, nvals, nx = s->nx, ny = s->ny;
    if (s->is_complex) rc = swfs_fail(SWFS_ERR_FORMAT, "%s: a complex image; a log holds real frames", m->fits);
    if (s->nz > 1 || (s->nz == 1 && rows == 1 && s->ny > 1)) { /* a cube, or one 2-D frame */
        frames = s->nz;
        nvals = s->nx * s->ny;
    } else { /* N x T: one vector per row */
        frames = s->ny;
        nvals = s->nx;
        ny = 1;
        m->rows = 1;
    }
    if (!rc && frames != rows)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s holds %zu frames (%zux%zux%zu) but its timestamp table %s lists %zu",
                       m->fits, frames, s->nx, s->ny, s->nz, txt, rows);
    if (!rc && idx == 0) {
        l->info.nvals = nvals;
        l->info.nx = nx;
        l->info.ny = ny;
        int found = 0;
        double e = 0;
        rc = swfs_fits_in_key_double_opt(f, "EXPTIME", &e, &found);
        if (!rc && found && !(e > 0 && e < 1e4))
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: EXPTIME = %g s; expected a positive exposure time", m->fits, e);
        l->info.exptime = found ? e : 0;
    } else if (!rc && nvals != l->info.nvals)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: frames of %zu values but %s has %zu (one stream's files share a frame size)",
                       m->fits, nvals, l->f[0].fits, l->info.nvals);
    swfs_fits_in_close(f);
    m->n = frames;
    m->t0 = m->stamp[0];
    return rc;
}

static int cmp_file(const void *a, const void *b)
{
    const mfile *x = a, *y = b;
    return x->t0 < y->t0 ? -1 : x->t0 > y->t0;
}

/* Files in stamp order -> one table; stamps checked across files, drops counted. */
static int join(swfs_milklog *l)
{
    const size_t nf = l->info.nfiles;
    qsort(l->f, nf, sizeof *l->f, cmp_file);
    size_t n = 0;
    for (size_t k = 0; k < nf; k++) {
        l->f[k].first = n;
        n += l->f[k].n;
    }
    l->cnt = malloc(n * sizeof *l->cnt);
    l->stamp = malloc(n * sizeof *l->stamp);
    if (!l->cnt || !l->stamp) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for %zu frames", l->source, n);
    for (size_t k = 0; k < nf; k++) {
        const mfile *m = &l->f[k];
        if (k && m->stamp[0] < l->stamp[m->first - 1]) {
            char a[40], b[40];
            swfs_milk_format_time(m->stamp[0], a, sizeof a);
            swfs_milk_format_time(l->stamp[m->first - 1], b, sizeof b);
            return swfs_fail(SWFS_ERR_VALUE, "%s: first time stamp %s s is before the last one of %s (%s s): the files "
                             "of one stream overlap in time", m->fits, a, l->f[k - 1].fits, b);
        }
        memcpy(l->cnt + m->first, m->cnt, m->n * sizeof *l->cnt);
        memcpy(l->stamp + m->first, m->stamp, m->n * sizeof *l->stamp);
    }
    for (size_t k = 0; k < nf; k++) { /* the log's table is the one copy kept */
        free(l->f[k].cnt);
        free(l->f[k].stamp);
        l->f[k].cnt = NULL;
        l->f[k].stamp = NULL;
    }
    for (size_t i = 1; i < n; i++) {
        if (l->cnt[i] > l->cnt[i - 1]) l->info.dropped += l->cnt[i] - l->cnt[i - 1] - 1;
        else l->info.restarts++;
    }
    l->info.nframes = n;
    return SWFS_OK;
}

int swfs_milklog_open(swfs_milklog **out, const char *const *paths, size_t npaths)
{
    *out = NULL;
    if (!npaths) return swfs_fail(SWFS_ERR_ARG, "milk log: no folder or file given");
    swfs_milklog *l = calloc(1, sizeof *l);
    if (!l) return swfs_fail(SWFS_ERR_NOMEM, "milk log: out of memory");
    char **names = NULL;
    size_t nn = 0;
    struct stat sb;
    int rc = SWFS_OK;
    l->source = strdup(paths[0]);
    l->info.source = l->source;
    if (npaths == 1 && stat(paths[0], &sb) == 0 && S_ISDIR(sb.st_mode)) rc = list_dir(paths[0], &names, &nn);
    else if (!(names = calloc(npaths, sizeof *names))) rc = swfs_fail(SWFS_ERR_NOMEM, "milk log: out of memory");
    else
        for (nn = 0; nn < npaths && !rc; nn++)
            if (!(names[nn] = strdup(paths[nn]))) rc = swfs_fail(SWFS_ERR_NOMEM, "milk log: out of memory");
    if (!rc && !(l->f = calloc(nn, sizeof *l->f))) rc = swfs_fail(SWFS_ERR_NOMEM, "milk log: out of memory");
    for (size_t k = 0; !rc && k < nn; k++) {
        l->f[k].fits = names[k];
        names[k] = NULL;
        l->info.nfiles = k + 1;
        rc = load_file(l, &l->f[k], k);
    }
    for (size_t k = 0; names && k < nn; k++) free(names[k]);
    free(names);
    if (!rc) rc = join(l);
    if (rc) {
        swfs_milklog_free(l);
        return rc;
    }
    l->open_idx = SIZE_MAX;
    *out = l;
    return SWFS_OK;
}

const swfs_milklog_info *swfs_milklog_get_info(const swfs_milklog *l) { return &l->info; }
const uint64_t *swfs_milklog_counters(const swfs_milklog *l) { return l->cnt; }
const int64_t *swfs_milklog_stamps(const swfs_milklog *l) { return l->stamp; }

static size_t file_index(const swfs_milklog *l, size_t k)
{
    size_t lo = 0, hi = l->info.nfiles;
    while (hi - lo > 1) {
        const size_t mid = (lo + hi) / 2;
        if (l->f[mid].first <= k) lo = mid;
        else hi = mid;
    }
    return lo;
}

const char *swfs_milklog_file_of(const swfs_milklog *l, size_t k)
{
    return k < l->info.nframes ? l->f[file_index(l, k)].fits : l->source;
}

int swfs_milklog_read(swfs_milklog *l, size_t first, size_t n, double *out)
{
    if (first > l->info.nframes || n > l->info.nframes - first)
        return swfs_fail(SWFS_ERR_ARG, "%s: frames %zu..%zu requested but the log holds %zu", l->source, first,
                         first + n - 1, l->info.nframes);
    while (n) {
        const size_t fi = file_index(l, first);
        const mfile *m = &l->f[fi];
        if (fi != l->open_idx) {
            swfs_fits_in_close(l->open);
            l->open = NULL;
            l->open_idx = SIZE_MAX;
            int rc = swfs_fits_in_open(&l->open, m->fits, NULL);
            if (rc) return rc;
            l->open_idx = fi;
        }
        const size_t j = first - m->first, k = m->n - j < n ? m->n - j : n;
        int rc = m->rows ? swfs_fits_in_read_rows(l->open, j, k, out) : swfs_fits_in_read_real(l->open, j, k, out);
        if (rc) return rc;
        out += k * l->info.nvals;
        first += k;
        n -= k;
    }
    return SWFS_OK;
}

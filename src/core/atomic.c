/* Part file + fsync + rename for every product: see include/specklewfs/atomic.h. */
#define _GNU_SOURCE
#include "specklewfs/atomic.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/random.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

struct swfs_atomic {
    char *path, *part;
    FILE *fp;
    int listed; /* its part is in the list swfs_atomic_remove_parts removes */
};

/* ---- the part files not yet renamed, for a signal handler (swfs_atomic_remove_parts) --- */

#define PART_SLOTS 256
static struct {
    atomic_int used;
    char path[4200];
} parts[PART_SLOTS];
static pthread_mutex_t parts_lock = PTHREAD_MUTEX_INITIALIZER;

/* 1 when listed (a path too long, or more than PART_SLOTS parts at once, is not: such a part
 * is only left behind by a process a signal ends) */
static int part_list(const char *part)
{
    if (strlen(part) >= sizeof parts[0].path) return 0;
    int listed = 0;
    pthread_mutex_lock(&parts_lock);
    for (int i = 0; i < PART_SLOTS && !listed; i++)
        if (!atomic_load(&parts[i].used)) {
            strcpy(parts[i].path, part);
            atomic_store(&parts[i].used, 1); /* the path complete before a handler can see it */
            listed = 1;
        }
    pthread_mutex_unlock(&parts_lock);
    return listed;
}

static void part_unlist(const char *part)
{
    pthread_mutex_lock(&parts_lock);
    for (int i = 0; i < PART_SLOTS; i++)
        if (atomic_load(&parts[i].used) && !strcmp(parts[i].path, part)) {
            atomic_store(&parts[i].used, 0);
            break;
        }
    pthread_mutex_unlock(&parts_lock);
}

void swfs_atomic_remove_parts(void)
{
    for (int i = 0; i < PART_SLOTS; i++)
        if (atomic_load(&parts[i].used)) (void)unlink(parts[i].path); /* async-signal-safe */
}

/* 48 random bits for the part name: two runs (or two threads) never pick the same one. */
static unsigned long long part_tag(void)
{
    static _Thread_local unsigned long long counter;
    unsigned long long r = 0;
    if (getrandom(&r, sizeof r, GRND_NONBLOCK) != (ssize_t)sizeof r) {
        struct timespec ts;
        clock_gettime(CLOCK_REALTIME, &ts);
        r = (unsigned long long)ts.tv_nsec * 0x9E3779B97F4A7C15ULL ^ (unsigned long long)(uintptr_t)&counter;
    }
    r ^= ++counter * 0xD1B54A32D192ED03ULL;
    return r & 0xFFFFFFFFFFFFULL;
}

static void dir_of(const char *path, char *dir, size_t cap)
{
    const char *s = strrchr(path, '/');
    if (!s) snprintf(dir, cap, ".");
    else if (s == path) snprintf(dir, cap, "/");
    else snprintf(dir, cap, "%.*s", (int)(s - path), path);
}

/* The rename is durable once the folder's entry is on disk too; a failure here is not an
 * error of the product (the data are synced), so it is ignored. */
static void sync_dir(const char *path)
{
    char dir[4096];
    dir_of(path, dir, sizeof dir);
    int fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd >= 0) {
        (void)fsync(fd);
        close(fd);
    }
}

static void free_atomic(swfs_atomic *a)
{
    if (a->listed) part_unlist(a->part);
    free(a->path);
    free(a->part);
    free(a);
}

int swfs_atomic_begin(swfs_atomic **out, const char *path, int stdio)
{
    *out = NULL;
    if (!path || !*path) return swfs_fail(SWFS_ERR_ARG, "an output needs a file name");
    const char *base = strrchr(path, '/');
    base = base ? base + 1 : path;
    if (!*base) return swfs_fail(SWFS_ERR_ARG, "%s: output name is a folder name, expected a file name", path);
    swfs_atomic *a = calloc(1, sizeof *a);
    size_t cap = strlen(path) + 48;
    if (a) a->path = strdup(path);
    if (a) a->part = malloc(cap);
    if (!a || !a->path || !a->part) {
        if (a) free_atomic(a);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    if (strlen(base) + 30 > 255) {
        free_atomic(a);
        return swfs_fail(SWFS_ERR_ARG, "%s: file name too long (the part file adds 30 characters to it; at most 225)",
                         path);
    }
    snprintf(a->part, cap, "%s.part.%ld.%012llx", path, (long)getpid(), part_tag());
    a->listed = part_list(a->part);
    if (stdio) {
        int fd = open(a->part, O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
        if (fd < 0 || !(a->fp = fdopen(fd, "w"))) {
            int e = errno;
            char dir[4096];
            dir_of(path, dir, sizeof dir);
            if (fd >= 0) {
                close(fd);
                unlink(a->part);
            }
            free_atomic(a);
            return swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (folder %s: %s)", path, dir, strerror(e));
        }
    }
    *out = a;
    return SWFS_OK;
}

const char *swfs_atomic_part(const swfs_atomic *a) { return a->part; }
const char *swfs_atomic_path(const swfs_atomic *a) { return a->path; }
FILE *swfs_atomic_stream(swfs_atomic *a) { return a->fp; }

void swfs_atomic_abort(swfs_atomic *a)
{
    if (!a) return;
    if (a->fp) fclose(a->fp);
    unlink(a->part);
    free_atomic(a);
}

/* ---- groups ------------------------------------------------------------------ */

static _Thread_local struct {
    int depth;
    size_t n, cap;
    char **part, **path;
} group;

static int group_add(swfs_atomic *a)
{
    for (size_t i = 0; i < group.n; i++)
        if (!strcmp(group.path[i], a->path)) { /* rewritten within the group: the newer part wins */
            unlink(group.part[i]);
            part_unlist(group.part[i]);
            free(group.part[i]);
            free(a->path);
            group.part[i] = a->part;
            free(a);
            return SWFS_OK;
        }
    if (group.n == group.cap) {
        size_t cap = group.cap ? 2 * group.cap : 8;
        char **np = realloc(group.part, cap * sizeof *np);
        if (np) group.part = np;
        char **nq = np ? realloc(group.path, cap * sizeof *nq) : NULL;
        if (nq) group.path = nq;
        if (!np || !nq) {
            int rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", a->path);
            swfs_atomic_abort(a);
            return rc;
        }
        group.cap = cap;
    }
    group.part[group.n] = a->part;
    group.path[group.n++] = a->path;
    free(a);
    return SWFS_OK;
}

int swfs_atomic_commit(swfs_atomic *a)
{
    int e = 0;
    if (a->fp) {
        /* stdio buffers: a full disk shows up at fflush, or only at fsync/close on some filesystems. */
        if (fflush(a->fp) != 0 || ferror(a->fp)) e = errno ? errno : EIO;
        if (!e && fsync(fileno(a->fp)) != 0) e = errno;
        if (fclose(a->fp) != 0 && !e) e = errno ? errno : EIO;
        a->fp = NULL;
    } else {
        int fd = open(a->part, O_RDONLY | O_CLOEXEC);
        if (fd < 0 || fsync(fd) != 0) e = errno;
        if (fd >= 0) close(fd);
    }
    if (e) {
        int rc = swfs_fail(SWFS_ERR_IO, "%s: writing the output failed: %s (nothing written under that name)", a->path,
                           strerror(e));
        swfs_atomic_abort(a);
        return rc;
    }
    if (group.depth > 0) return group_add(a);
    if (rename(a->part, a->path) != 0) {
        int rc = swfs_fail(SWFS_ERR_IO, "%s: cannot rename the finished part file into place: %s", a->path,
                           strerror(errno));
        swfs_atomic_abort(a);
        return rc;
    }
    sync_dir(a->path);
    free_atomic(a);
    return SWFS_OK;
}

void swfs_outputs_begin(void) { group.depth++; }

int swfs_outputs_end(int commit)
{
    if (group.depth <= 0) return swfs_fail(SWFS_ERR_INTERNAL, "swfs_outputs_end without swfs_outputs_begin");
    if (--group.depth > 0) return SWFS_OK;
    int rc = SWFS_OK;
    size_t done = 0;
    for (; commit && done < group.n; done++)
        if (rename(group.part[done], group.path[done]) != 0) {
            rc = swfs_fail(SWFS_ERR_IO, "%s: cannot rename the finished part file into place: %s (the run's other "
                           "outputs were removed too)", group.path[done], strerror(errno));
            break;
        }
    /* On failure the products already renamed are removed: the run's files come as a set. */
    for (size_t i = 0; i < group.n; i++) {
        if (rc && i < done) unlink(group.path[i]);
        else if (!commit || rc) unlink(group.part[i]);
        else sync_dir(group.path[i]);
        part_unlist(group.part[i]);
        free(group.part[i]);
        free(group.path[i]);
    }
    free(group.part);
    free(group.path);
    group.part = group.path = NULL;
    group.n = group.cap = 0;
    return rc;
}

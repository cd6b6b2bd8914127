/* A command's inputs and outputs checked before any work: see include/specklewfs/outpaths.h. */
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

typedef struct entry {
    char *path, *role;
    int output, exists;
    dev_t dev, ddev; /* the file's device and inode (exists), its folder's */
    ino_t ino, dino;
    const char *base;
} entry;

struct swfs_paths {
    entry *e;
    size_t n, cap;
    int status;
};

int swfs_paths_create(swfs_paths **out)
{
    *out = calloc(1, sizeof **out);
    return *out ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "out of memory");
}

void swfs_paths_free(swfs_paths *p)
{
    if (!p) return;
    for (size_t i = 0; i < p->n; i++) {
        free(p->e[i].path);
        free(p->e[i].role);
    }
    free(p->e);
    free(p);
}

int swfs_paths_status(const swfs_paths *p) { return p ? p->status : SWFS_ERR_NOMEM; }

static const char *kind(mode_t m)
{
    if (S_ISFIFO(m)) return "a FIFO";
    if (S_ISCHR(m)) return "a character device";
    if (S_ISBLK(m)) return "a block device";
    if (S_ISSOCK(m)) return "a socket";
    if (S_ISDIR(m)) return "a folder";
    if (S_ISLNK(m)) return "a symbolic link";
    return "not a regular file";
}

int swfs_input_check(const char *path, const char *what)
{
    struct stat sb;
    if (!path || stat(path, &sb) != 0) return SWFS_OK;
    if (S_ISREG(sb.st_mode)) return SWFS_OK;
    if (S_ISDIR(sb.st_mode)) return swfs_fail(SWFS_ERR_IO, "%s: is a folder, expected a %s file", path, what);
    return swfs_fail(SWFS_ERR_IO, "%s: is %s, not a regular file: the %s must be a file (reading it could block "
                     "forever or never end)", path, kind(sb.st_mode), what);
}

static int add(swfs_paths *p, const entry *e)
{
    if (p->n == p->cap) {
        size_t cap = p->cap ? 2 * p->cap : 16;
        entry *ne = realloc(p->e, cap * sizeof *ne);
        if (!ne) return p->status = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        p->e = ne;
        p->cap = cap;
    }
    entry *d = &p->e[p->n];
    *d = *e;
    d->path = strdup(e->path);
    d->role = strdup(e->role);
    if (!d->path || !d->role) {
        free(d->path);
        free(d->role);
        return p->status = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    const char *s = strrchr(d->path, '/');
    d->base = s ? s + 1 : d->path;
    p->n++;
    return SWFS_OK;
}

static int same_file(const entry *a, const entry *b)
{
    if (a->exists && b->exists && a->dev == b->dev && a->ino == b->ino) return 1;
    /* Outputs that do not exist yet: the same name in the same folder. */
    return a->output && b->output && a->ddev == b->ddev && a->dino == b->dino && !strcmp(a->base, b->base);
}

/* The new entry e against all earlier ones. */
static int clash(swfs_paths *p, const entry *e)
{
    for (size_t i = 0; i < p->n; i++) {
        const entry *o = &p->e[i];
        if (!o->output && !e->output) continue;
        if (!same_file(o, e)) continue;
        const entry *out = e->output ? e : o, *other = e->output ? o : e;
        if (!other->output)
            return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s) is the same file as the input %s (%s): refusing to "
                                         "overwrite an input; write the output elsewhere", out->path, out->role,
                                         other->path, other->role);
        return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s) and %s (%s) are the same file: every output needs its own "
                                     "name", other->path, other->role, out->path, out->role);
    }
    return SWFS_OK;
}

static int input(swfs_paths *p, const char *role, const char *path, int dir_ok)
{
    if (!p) return SWFS_ERR_NOMEM;
    if (p->status || !path) return p->status;
    struct stat sb;
    if (stat(path, &sb) != 0) return SWFS_OK; /* the reader names a missing file */
    if (S_ISDIR(sb.st_mode) && !dir_ok)
        return p->status = swfs_fail(SWFS_ERR_IO, "%s: is a folder, expected a file (the %s)", path, role);
    if (!S_ISDIR(sb.st_mode) && !S_ISREG(sb.st_mode))
        return p->status = swfs_fail(SWFS_ERR_IO, "%s: is %s, not a regular file: the %s must be a file (reading it "
                                     "could block forever or never end)", path, kind(sb.st_mode), role);
    entry e = {.path = (char *)path, .role = (char *)role, .exists = 1, .dev = sb.st_dev, .ino = sb.st_ino};
    if (clash(p, &e)) return p->status;
    return add(p, &e);
}

int swfs_paths_input(swfs_paths *p, const char *role, const char *path) { return input(p, role, path, 0); }
int swfs_paths_input_or_dir(swfs_paths *p, const char *role, const char *path) { return input(p, role, path, 1); }

/* Output names that CFITSIO and other tools take for compressed files: specklewfs writes
 * plain files, so such a name would lie about its content. */
static const char *compressed_suffix(const char *path)
{
    static const char *sfx[] = {".gz", ".Z", ".z", ".bz2", ".zip", ".fz", ".xz", ".zst"};
    size_t n = strlen(path);
    for (size_t i = 0; i < sizeof sfx / sizeof sfx[0]; i++) {
        size_t k = strlen(sfx[i]);
        if (n > k && !strcmp(path + n - k, sfx[i])) return sfx[i];
    }
    return NULL;
}

int swfs_paths_output(swfs_paths *p, const char *role, const char *path)
{
    if (!p) return SWFS_ERR_NOMEM;
    if (p->status || !path) return p->status;
    const char *base = strrchr(path, '/');
    base = base ? base + 1 : path;
    if (!*base || !strcmp(base, ".") || !strcmp(base, ".."))
        return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s): is a folder name, expected a file name", path, role);
    const char *sfx = compressed_suffix(path);
    if (sfx)
        return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s): a name ending in %s is read as a compressed file, but "
                                     "specklewfs writes uncompressed files: drop %s (and compress the file afterwards "
                                     "if you want)", path, role, sfx, sfx);
    entry e = {.path = (char *)path, .role = (char *)role, .output = 1, .base = base};
    struct stat sb;
    if (lstat(path, &sb) == 0) {
        if (S_ISLNK(sb.st_mode))
            return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s): is a symbolic link; writing would replace the link "
                                         "by a file: give the name of the file it points to", path, role);
        if (!S_ISREG(sb.st_mode))
            return p->status = swfs_fail(SWFS_ERR_ARG, "%s (%s): is %s; outputs are new regular files renamed into "
                                         "place, which would replace it: give a file name", path, role,
                                         kind(sb.st_mode));
        e.exists = 1;
        e.dev = sb.st_dev;
        e.ino = sb.st_ino;
    } else if (errno != ENOENT && errno != ENOTDIR) {
        return p->status = swfs_fail(SWFS_ERR_IO, "%s (%s): cannot create output file: %s", path, role,
                                     strerror(errno));
    }
    char dir[4096];
    size_t dl = (size_t)(base - path);
    if (dl >= sizeof dir) return p->status = swfs_fail(SWFS_ERR_ARG, "%s: folder name too long", path);
    if (dl == 0) snprintf(dir, sizeof dir, ".");
    else if (dl == 1) snprintf(dir, sizeof dir, "/");
    else snprintf(dir, sizeof dir, "%.*s", (int)(dl - 1), path);
    struct stat db;
    if (stat(dir, &db) != 0)
        return p->status = swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (folder %s: %s)", path, dir,
                                     strerror(errno));
    if (!S_ISDIR(db.st_mode))
        return p->status = swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (folder %s: %s)", path, dir,
                                     strerror(ENOTDIR));
    if (access(dir, W_OK | X_OK) != 0)
        return p->status = swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (folder %s: %s)", path, dir,
                                     strerror(errno));
    e.ddev = db.st_dev;
    e.dino = db.st_ino;
    if (clash(p, &e)) return p->status;
    return add(p, &e);
}

int swfs_text_line(FILE *f, char *buf, int cap, const char *path, long lineno, int *rc)
{
    buf[cap - 1] = 1; /* fgets writes its terminator there only when it filled buf */
    if (!fgets(buf, cap, f)) return 0;
    if (buf[cap - 1] == 0 && buf[cap - 2] != '\n') {
        const int ch = getc(f);
        if (ch != EOF && ch != '\n') {
            *rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: line longer than %d characters", path, lineno, cap - 2);
            return 0;
        }
    }
    return 1;
}

/* The folders made since swfs_made_dirs_begin (outpaths.h). */
static _Thread_local struct {
    int on;
    size_t n, cap;
    char **path;
} made;

static void made_add(const char *path)
{
    if (!made.on) return;
    if (made.n == made.cap) {
        const size_t cap = made.cap ? 2 * made.cap : 16;
        char **p = realloc(made.path, cap * sizeof *p);
        if (!p) return; /* a folder not recorded only stays */
        made.path = p;
        made.cap = cap;
    }
    if ((made.path[made.n] = strdup(path))) made.n++;
}

void swfs_made_dirs_begin(void)
{
    swfs_made_dirs_end(1);
    made.on = 1;
}

void swfs_made_dirs_end(int keep)
{
    for (size_t i = made.n; i-- > 0;) {
        if (!keep) (void)rmdir(made.path[i]); /* only an empty one goes */
        free(made.path[i]);
    }
    free(made.path);
    made.path = NULL;
    made.n = made.cap = 0;
    made.on = 0;
}

int swfs_make_dirs(const char *path)
{
    char tmp[4096];
    if (!path || !*path) return swfs_fail(SWFS_ERR_ARG, "an output folder needs a name");
    if (strlen(path) >= sizeof tmp) return swfs_fail(SWFS_ERR_ARG, "output folder name too long: %.200s...", path);
    strcpy(tmp, path);
    for (char *p = tmp + 1; *p; p++) {
        if (*p != '/') continue;
        *p = '\0';
        if (mkdir(tmp, 0777) == 0) made_add(tmp);
        else if (errno != EEXIST)
            return swfs_fail(SWFS_ERR_IO, "cannot create output folder %s (making %s): %s", path, tmp, strerror(errno));
        *p = '/';
    }
    if (mkdir(tmp, 0777) == 0) made_add(tmp);
    else if (errno != EEXIST)
        return swfs_fail(SWFS_ERR_IO, "cannot create output folder %s: %s", path, strerror(errno));
    struct stat sb;
    if (stat(tmp, &sb) != 0) return swfs_fail(SWFS_ERR_IO, "cannot create output folder %s: %s", path, strerror(errno));
    if (!S_ISDIR(sb.st_mode)) return swfs_fail(SWFS_ERR_IO, "cannot create output folder %s: a file of that name exists", path);
    return SWFS_OK;
}

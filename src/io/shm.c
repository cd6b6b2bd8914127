/* ImageStreamIO 2.00 shared-memory streams: see include/specklewfs/shm.h. Written from the
 * layout description (../shared/FORMATS.md), not from any milk source. */
#include "specklewfs/shm.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <sched.h>
#include <semaphore.h>
#include <signal.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

/* The 384-byte IMAGE_METADATA of x86-64, field offsets as documented; bytes we do not
 * use are padding here and written as zeros. */
typedef struct isio_meta {
    char version[32];                /* 0 */
    char name[80];                   /* 32 */
    uint8_t naxis;                   /* 112 */
    uint8_t pad0[3];
    uint32_t size[3];                /* 116 */
    uint64_t nelement;               /* 128 */
    uint8_t datatype;                /* 136 */
    uint8_t pad1[7];
    uint64_t imagetype;              /* 144 */
    struct timespec creationtime;    /* 152 */
    struct timespec lastaccesstime;  /* 168 */
    struct timespec atime;           /* 184 */
    struct timespec writetime;       /* 200 */
    uint8_t pad2[8];                 /* 216 */
    uint8_t shared;                  /* 224 */
    uint8_t pad3[7];
    uint64_t inode;                  /* 232 */
    int8_t location;                 /* 240 */
    uint8_t pad4[17];
    uint16_t sem;                    /* 258 */
    uint16_t nbproctrace;            /* 260 */
    uint8_t pad5[2];
    uint64_t cnt0;                   /* 264 */
    uint64_t cnt1;                   /* 272 */
    uint64_t cnt2;                   /* 280 */
    uint8_t write;                   /* 288 */
    uint8_t pad6;
    uint16_t nbkw;                   /* 290 */
    uint32_t cbsize;                 /* 292 */
    uint64_t cbindex;                /* 296 */
    uint64_t cbcycle;                /* 304 */
    uint64_t imdatamemsize;          /* 312 */
    uint8_t cudamemhandle[64];       /* 320 */
} isio_meta;

_Static_assert(sizeof(struct timespec) == 16, "ImageStreamIO 2.00 layout assumes a 16-byte timespec (x86-64)");
_Static_assert(sizeof(sem_t) == 32, "ImageStreamIO 2.00 layout assumes a 32-byte sem_t (glibc x86-64)");
_Static_assert(sizeof(pid_t) == 4, "ImageStreamIO 2.00 layout assumes a 4-byte pid_t");
_Static_assert(offsetof(isio_meta, naxis) == 112 && offsetof(isio_meta, size) == 116 &&
                   offsetof(isio_meta, nelement) == 128 && offsetof(isio_meta, datatype) == 136 &&
                   offsetof(isio_meta, imagetype) == 144 && offsetof(isio_meta, creationtime) == 152 &&
                   offsetof(isio_meta, atime) == 184 && offsetof(isio_meta, writetime) == 200 &&
                   offsetof(isio_meta, shared) == 224 && offsetof(isio_meta, inode) == 232 &&
                   offsetof(isio_meta, location) == 240 && offsetof(isio_meta, sem) == 258 &&
                   offsetof(isio_meta, nbproctrace) == 260 && offsetof(isio_meta, cnt0) == 264 &&
                   offsetof(isio_meta, cnt1) == 272 && offsetof(isio_meta, write) == 288 &&
                   offsetof(isio_meta, nbkw) == 290 && offsetof(isio_meta, cbsize) == 292 &&
                   offsetof(isio_meta, cbindex) == 296 && offsetof(isio_meta, imdatamemsize) == 312 &&
                   offsetof(isio_meta, cudamemhandle) == 320,
               "IMAGE_METADATA field offsets");
_Static_assert(sizeof(isio_meta) == SWFS_SHM_METADATA_BYTES, "IMAGE_METADATA is 384 bytes");

enum { KW_BYTES = 128, PROCTRACE_BYTES = 64, CB_ENTRY_BYTES = 48, SEM_CAP = 100000 };

/* Byte offsets of the blocks after the metadata. */
typedef struct layout {
    size_t data, kw, sems, semlog, readpid, writepid, semctrl, semstatus, proctrace, atimes, wtimes, cnts, cb, total;
} layout;

struct swfs_shm {
    char path[4096];
    int fd, writer;
    unsigned char *map;
    size_t mapsize;
    isio_meta *m;
    unsigned char *data;
    sem_t *sems, *semlog;
    pid_t *readpid, *writepid;
    struct timespec *atimes, *wtimes;
    uint64_t *cnts;
    swfs_shm_shape shape;
    size_t elsize, fvals, fbytes, nslices; /* values / bytes per frame, frames in the data */
    int claimed;                   /* semaphore index, -1 if none */
    uint64_t last;                 /* counter of the last frame read */
    uint64_t inode;
    unsigned char *raw;            /* one frame of raw bytes (reader) */
};

static size_t up8(size_t n) { return (n + 7) & ~(size_t)7; }

static size_t type_size(int t)
{
    switch (t) {
    case SWFS_SHM_U16: case SWFS_SHM_I16: return 2;
    case SWFS_SHM_F32: return 4;
    case SWFS_SHM_F64: return 8;
    default: return 0;
    }
}

const char *swfs_shm_type_name(int t)
{
    static const char *names[] = {"undefined", "uint8", "int8", "uint16", "int16", "uint32", "int32", "uint64",
                                  "int64", "float32", "float64", "complex float32", "complex float64", "float16"};
    if (t >= 0 && t < (int)(sizeof names / sizeof names[0])) return names[t];
    return "unknown";
}

int64_t swfs_shm_now_ns(void)
{
    struct timespec ts;
#ifdef CLOCK_TAI
    if (clock_gettime(CLOCK_TAI, &ts) == 0) return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
#endif
    clock_gettime(CLOCK_REALTIME, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static int64_t ts_ns(struct timespec t) { return (int64_t)t.tv_sec * 1000000000 + (int64_t)t.tv_nsec; }
static struct timespec ns_ts(int64_t ns)
{
    struct timespec t;
    t.tv_sec = (time_t)(ns / 1000000000);
    t.tv_nsec = (long)(ns % 1000000000);
    if (t.tv_nsec < 0) {
        t.tv_nsec += 1000000000;
        t.tv_sec -= 1;
    }
    return t;
}

static int is_dir(const char *p)
{
    struct stat sb;
    return p && p[0] && stat(p, &sb) == 0 && S_ISDIR(sb.st_mode);
}

void swfs_shm_dir(const char *dir, char *out, size_t cap)
{
    const char *env = getenv("MILK_SHM_DIR");
    const char *pick = dir && dir[0] ? dir
                       : env && env[0] ? env
                       : is_dir("/milk/shm") ? "/milk/shm"
                       : is_dir("/dev/shm") ? "/dev/shm"
                                            : "/tmp";
    snprintf(out, cap, "%s", pick);
}

int swfs_shm_path(const char *dir, const char *name, char *out, size_t cap)
{
    if (!name || !name[0] || strchr(name, '/') || strlen(name) > 79)
        return swfs_fail(SWFS_ERR_ARG, "stream name '%s': expected 1..79 characters without '/'", name ? name : "");
    char d[4096];
    swfs_shm_dir(dir, d, sizeof d);
    int n = snprintf(out, cap, "%s/%s.im.shm", d, name);
    if (n < 0 || (size_t)n >= cap) return swfs_fail(SWFS_ERR_ARG, "stream path %s/%s.im.shm is too long", d, name);
    return SWFS_OK;
}

/* The 2.00 layout of a stream with these counts. */
static layout make_layout(size_t databytes, size_t nbkw, size_t nsem, size_t nproc, int temporal, size_t nz,
                          size_t cbsize)
{
    layout l;
    size_t o = SWFS_SHM_METADATA_BYTES;
    l.data = o;       o += up8(databytes);
    l.kw = o;         o += up8(nbkw * KW_BYTES);
    l.sems = o;       o += up8(nsem * sizeof(sem_t));
    l.semlog = o;     o += up8(sizeof(sem_t));
    l.readpid = o;    o += up8(nsem * sizeof(pid_t));
    l.writepid = o;   o += up8(nsem * sizeof(pid_t));
    l.semctrl = o;    o += up8(nsem * sizeof(uint32_t));
    l.semstatus = o;  o += up8(nsem * sizeof(uint32_t));
    l.proctrace = o;  o += up8(nproc * PROCTRACE_BYTES);
    l.atimes = l.wtimes = l.cnts = 0;
    if (temporal) {
        l.atimes = o; o += up8(nz * sizeof(struct timespec));
        l.wtimes = o; o += up8(nz * sizeof(struct timespec));
        l.cnts = o;   o += up8(nz * sizeof(uint64_t));
    }
    l.cb = o;         o += up8(cbsize * CB_ENTRY_BYTES);
    l.total = o;
    return l;
}

static void bind(swfs_shm *s, const layout *l)
{
    s->m = (isio_meta *)s->map;
    s->data = s->map + l->data;
    s->sems = (sem_t *)(void *)(s->map + l->sems);
    s->semlog = (sem_t *)(void *)(s->map + l->semlog);
    s->readpid = (pid_t *)(void *)(s->map + l->readpid);
    s->writepid = (pid_t *)(void *)(s->map + l->writepid);
    s->atimes = l->atimes ? (struct timespec *)(void *)(s->map + l->atimes) : NULL;
    s->wtimes = l->wtimes ? (struct timespec *)(void *)(s->map + l->wtimes) : NULL;
    s->cnts = l->cnts ? (uint64_t *)(void *)(s->map + l->cnts) : NULL;
}

static void set_sizes(swfs_shm *s)
{
    const swfs_shm_shape *sh = &s->shape;
    s->elsize = type_size(sh->datatype);
    s->fvals = sh->nx * sh->ny * (sh->temporal ? 1 : sh->nz);
    s->fbytes = s->fvals * s->elsize;
    s->nslices = sh->temporal ? sh->nz : 1;
}

void swfs_shm_close(swfs_shm *s, int unlink_file)
{
    if (!s) return;
    if (!s->writer) swfs_shm_release(s);
    if (s->map && s->writer && s->m) {
        for (int i = 0; i < s->shape.nsem; i++) __atomic_store_n(&s->writepid[i], 0, __ATOMIC_RELAXED);
    }
    if (unlink_file && s->path[0]) {
        /* Only remove the file if it is still ours (not a newer stream of the same name). */
        struct stat sb;
        if (stat(s->path, &sb) == 0 && (uint64_t)sb.st_ino == s->inode) unlink(s->path);
    }
    if (s->map) munmap(s->map, s->mapsize);
    if (s->fd >= 0) close(s->fd);
    free(s->raw);
    free(s);
}

int swfs_shm_create(swfs_shm **out, const char *dir, const char *name, const swfs_shm_shape *shape)
{
    *out = NULL;
    swfs_shm_shape sh = *shape;
    if (sh.nsem == 0) sh.nsem = SWFS_SHM_MAX_SEM;
    if (sh.nz == 0) sh.nz = 1;
    if (sh.ny == 0) sh.ny = 1;
    if (!type_size(sh.datatype))
        return swfs_fail(SWFS_ERR_ARG, "stream %s: datatype %d (%s) cannot be written; expected uint16, int16, float32 "
                         "or float64", name, sh.datatype, swfs_shm_type_name(sh.datatype));
    if (!sh.nx || sh.nx > UINT32_MAX || sh.ny > UINT32_MAX || sh.nz > UINT32_MAX || sh.nsem < 1 ||
        sh.nsem > SWFS_SHM_MAX_SEM || (sh.temporal && sh.nz < 2))
        return swfs_fail(SWFS_ERR_ARG, "stream %s: size %zux%zux%zu with %d semaphores%s is not valid", name, sh.nx,
                         sh.ny, sh.nz, sh.nsem, sh.temporal ? " (a temporal buffer needs nz >= 2)" : "");
    swfs_shm *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "stream %s: out of memory", name);
    s->fd = -1;
    s->writer = 1;
    s->claimed = -1;
    s->shape = sh;
    set_sizes(s);
    int rc = swfs_shm_path(dir, name, s->path, sizeof s->path);
    if (rc) {
        free(s);
        return rc;
    }
    const size_t nel = sh.nx * sh.ny * sh.nz;
    const layout l = make_layout(nel * s->elsize, 0, (size_t)sh.nsem, 0, sh.temporal, sh.nz, 0);
    char tmp[4200];
    snprintf(tmp, sizeof tmp, "%s.%ld.part", s->path, (long)getpid());
    s->fd = open(tmp, O_RDWR | O_CREAT | O_TRUNC, 0666);
    if (s->fd < 0) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot create the stream: %s", tmp, strerror(errno));
        swfs_shm_close(s, 0);
        return rc;
    }
    if (ftruncate(s->fd, (off_t)l.total) != 0) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot size the stream to %zu bytes: %s", tmp, l.total, strerror(errno));
        unlink(tmp);
        swfs_shm_close(s, 0);
        return rc;
    }
    s->mapsize = l.total;
    void *p = mmap(NULL, l.total, PROT_READ | PROT_WRITE, MAP_SHARED, s->fd, 0);
    if (p == MAP_FAILED) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot map %zu bytes: %s", tmp, l.total, strerror(errno));
        unlink(tmp);
        swfs_shm_close(s, 0);
        return rc;
    }
    s->map = p;
    memset(s->map, 0, l.total);
    bind(s, &l);
    struct stat sb;
    fstat(s->fd, &sb);
    s->inode = (uint64_t)sb.st_ino;
    isio_meta *m = s->m;
    snprintf(m->version, sizeof m->version, "2.00");
    snprintf(m->name, sizeof m->name, "%s", name);
    m->naxis = (uint8_t)(sh.nz > 1 ? 3 : (sh.ny > 1 ? 2 : 1));
    m->size[0] = (uint32_t)sh.nx;
    m->size[1] = (uint32_t)(m->naxis >= 2 ? sh.ny : 0);
    m->size[2] = (uint32_t)(m->naxis >= 3 ? sh.nz : 0);
    if (m->naxis == 1) m->size[1] = 1; /* x only; readers take the missing axes as 1 */
    if (m->naxis <= 2) m->size[2] = 1;
    m->nelement = nel;
    m->datatype = (uint8_t)sh.datatype;
    m->imagetype = sh.temporal ? (SWFS_SHM_CIRCULAR | SWFS_SHM_ZTEMPORAL) : 0;
    m->creationtime = ns_ts(swfs_shm_now_ns());
    m->lastaccesstime = m->creationtime;
    m->shared = 1;
    m->inode = s->inode;
    m->location = -1;
    m->sem = (uint16_t)sh.nsem;
    m->imdatamemsize = nel * s->elsize;
    for (int i = 0; i < sh.nsem; i++) {
        if (sem_init(&s->sems[i], 1, 0) != 0) {
            rc = swfs_fail(SWFS_ERR_IO, "%s: cannot initialize semaphore %d: %s", tmp, i, strerror(errno));
            unlink(tmp);
            swfs_shm_close(s, 0);
            return rc;
        }
        s->writepid[i] = getpid();
    }
    sem_init(s->semlog, 1, 0);
    if (rename(tmp, s->path) != 0) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot publish the stream (rename from %s): %s", s->path, tmp, strerror(errno));
        unlink(tmp);
        swfs_shm_close(s, 0);
        return rc;
    }
    *out = s;
    return SWFS_OK;
}

static void to_raw(const swfs_shm *s, const double *in, unsigned char *dst)
{
    const size_t n = s->fvals;
    switch (s->shape.datatype) {
    case SWFS_SHM_F64: memcpy(dst, in, n * sizeof(double)); break;
    case SWFS_SHM_F32:
        for (size_t k = 0; k < n; k++) {
            const float v = (float)in[k];
            memcpy(dst + 4 * k, &v, 4);
        }
        break;
    case SWFS_SHM_U16:
        for (size_t k = 0; k < n; k++) {
            const double x = isfinite(in[k]) ? floor(in[k] + 0.5) : 0.0;
            const uint16_t v = (uint16_t)(x < 0 ? 0 : (x > 65535 ? 65535 : x));
            memcpy(dst + 2 * k, &v, 2);
        }
        break;
    default: /* SWFS_SHM_I16 */
        for (size_t k = 0; k < n; k++) {
            const double x = isfinite(in[k]) ? floor(in[k] + 0.5) : 0.0;
            const int16_t v = (int16_t)(x < -32768 ? -32768 : (x > 32767 ? 32767 : x));
            memcpy(dst + 2 * k, &v, 2);
        }
        break;
    }
}

static void from_raw(const swfs_shm *s, const unsigned char *src, double *out)
{
    const size_t n = s->fvals;
    switch (s->shape.datatype) {
    case SWFS_SHM_F64: memcpy(out, src, n * sizeof(double)); break;
    case SWFS_SHM_F32:
        for (size_t k = 0; k < n; k++) {
            float v;
            memcpy(&v, src + 4 * k, 4);
            out[k] = v;
        }
        break;
    case SWFS_SHM_U16:
        for (size_t k = 0; k < n; k++) {
            uint16_t v;
            memcpy(&v, src + 2 * k, 2);
            out[k] = v;
        }
        break;
    default:
        for (size_t k = 0; k < n; k++) {
            int16_t v;
            memcpy(&v, src + 2 * k, 2);
            out[k] = v;
        }
        break;
    }
}

static void post_all(swfs_shm *s)
{
    for (int i = 0; i < s->shape.nsem; i++) {
        int v = 0;
        if (sem_getvalue(&s->sems[i], &v) == 0 && v < SEM_CAP) sem_post(&s->sems[i]);
    }
    int v = 0;
    if (sem_getvalue(s->semlog, &v) == 0 && v < SEM_CAP) sem_post(s->semlog);
}

int swfs_shm_write(swfs_shm *s, const double *frame, int64_t atime_ns)
{
    isio_meta *m = s->m;
    const uint64_t c = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
    size_t slice = 0;
    if (s->shape.temporal) slice = c == 0 ? 0 : (size_t)((__atomic_load_n(&m->cnt1, __ATOMIC_RELAXED) + 1) % s->nslices);
    __atomic_store_n(&m->write, 1, __ATOMIC_SEQ_CST);
    to_raw(s, frame, s->data + slice * s->fbytes);
    const int64_t wt = swfs_shm_now_ns();
    const struct timespec wts = ns_ts(wt), ats = ns_ts(atime_ns ? atime_ns : wt);
    m->writetime = wts;
    m->atime = ats;
    if (s->shape.temporal) {
        s->atimes[slice] = ats;
        s->wtimes[slice] = wts;
        __atomic_store_n(&s->cnts[slice], c + 1, __ATOMIC_RELEASE);
        __atomic_store_n(&m->cnt1, (uint64_t)slice, __ATOMIC_RELEASE);
    }
    __atomic_store_n(&m->cnt0, c + 1, __ATOMIC_RELEASE);
    __atomic_store_n(&m->write, 0, __ATOMIC_RELEASE);
    post_all(s);
    return SWFS_OK;
}

void swfs_shm_skip(swfs_shm *s)
{
    __atomic_add_fetch(&s->m->cnt0, 1, __ATOMIC_RELEASE);
}

int swfs_shm_open(swfs_shm **out, const char *dir, const char *name)
{
    *out = NULL;
    swfs_shm *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "stream %s: out of memory", name);
    s->fd = -1;
    s->claimed = -1;
    int rc = swfs_shm_path(dir, name, s->path, sizeof s->path);
    if (rc) {
        free(s);
        return rc;
    }
    const char *path = s->path;
    s->fd = open(path, O_RDWR);
    if (s->fd < 0) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot open the stream: %s", path, strerror(errno));
        swfs_shm_close(s, 0);
        return rc;
    }
    struct stat sb;
    if (fstat(s->fd, &sb) != 0 || sb.st_size < SWFS_SHM_METADATA_BYTES) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: %lld bytes, too small for an ImageStreamIO stream (metadata alone is %d)",
                       path, (long long)sb.st_size, SWFS_SHM_METADATA_BYTES);
        swfs_shm_close(s, 0);
        return rc;
    }
    s->inode = (uint64_t)sb.st_ino;
    s->mapsize = (size_t)sb.st_size;
    void *p = mmap(NULL, s->mapsize, PROT_READ | PROT_WRITE, MAP_SHARED, s->fd, 0);
    if (p == MAP_FAILED) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot map %zu bytes: %s", path, s->mapsize, strerror(errno));
        swfs_shm_close(s, 0);
        return rc;
    }
    s->map = p;
    isio_meta *m = (isio_meta *)s->map;
    s->m = m;
    char ver[33];
    memcpy(ver, m->version, 32);
    ver[32] = '\0';
    if (strcmp(ver, "2.00") != 0) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: ImageStreamIO version '%s'; only '2.00' is supported (1.x streams use "
                       "named semaphores and another layout)", path, ver);
        swfs_shm_close(s, 0);
        return rc;
    }
    const int naxis = m->naxis;
    if (naxis < 1 || naxis > 3) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: naxis = %d; expected 1, 2 or 3", path, naxis);
        swfs_shm_close(s, 0);
        return rc;
    }
    swfs_shm_shape *sh = &s->shape;
    sh->datatype = m->datatype;
    sh->nx = m->size[0];
    sh->ny = naxis >= 2 ? m->size[1] : 1;
    sh->nz = naxis >= 3 ? m->size[2] : 1;
    const uint64_t itype = m->imagetype & SWFS_SHM_TYPEMASK;
    sh->temporal = naxis == 3 && itype == (SWFS_SHM_CIRCULAR | SWFS_SHM_ZTEMPORAL);
    sh->nsem = m->sem;
    if (!type_size(sh->datatype)) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: datatype %d (%s) is not supported; expected uint16 (3), int16 (4), "
                       "float32 (9) or float64 (10)", path, sh->datatype, swfs_shm_type_name(sh->datatype));
        swfs_shm_close(s, 0);
        return rc;
    }
    if (!sh->nx || !sh->ny || !sh->nz || m->nelement != (uint64_t)sh->nx * sh->ny * sh->nz) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: size %zux%zux%zu but nelement = %llu", path, sh->nx, sh->ny, sh->nz,
                       (unsigned long long)m->nelement);
        swfs_shm_close(s, 0);
        return rc;
    }
    if (m->location != -1) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: the stream lives on GPU %d (location); only CPU streams (-1) can be read",
                       path, (int)m->location);
        swfs_shm_close(s, 0);
        return rc;
    }
    if (m->cbsize != 0) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: CBsize = %u: streams with an attached circular-buffer area are not "
                       "supported", path, m->cbsize);
        swfs_shm_close(s, 0);
        return rc;
    }
    if (sh->nsem < 1 || sh->nsem > 64) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: %d semaphores; need at least one to wait on", path, sh->nsem);
        swfs_shm_close(s, 0);
        return rc;
    }
    set_sizes(s);
    const layout l = make_layout((size_t)m->nelement * s->elsize, m->nbkw, (size_t)sh->nsem, m->nbproctrace,
                                 sh->temporal, sh->nz, 0);
    if (l.total != s->mapsize) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: %zu bytes, but the 2.00 layout of a %zux%zux%zu %s stream with %u keywords, "
                       "%d semaphores and %u process traces%s is %zu bytes: another build or version of ImageStreamIO",
                       path, s->mapsize, sh->nx, sh->ny, sh->nz, swfs_shm_type_name(sh->datatype), m->nbkw, sh->nsem,
                       m->nbproctrace, sh->temporal ? " (temporal circular buffer)" : "", l.total);
        swfs_shm_close(s, 0);
        return rc;
    }
    bind(s, &l);
    s->raw = malloc(s->fbytes);
    if (!s->raw) {
        swfs_shm_close(s, 0);
        return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    s->last = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
    *out = s;
    return SWFS_OK;
}

static int pid_alive(pid_t p)
{
    return p > 0 && (kill(p, 0) == 0 || errno != ESRCH);
}

int swfs_shm_claim(swfs_shm *s)
{
    if (s->claimed >= 0) return SWFS_OK;
    const pid_t me = getpid();
    int idx = -1;
    for (int i = 0; i < s->shape.nsem && idx < 0; i++)
        if (__atomic_load_n(&s->readpid[i], __ATOMIC_ACQUIRE) == me) idx = i;
    for (int i = 0; i < s->shape.nsem && idx < 0; i++) {
        pid_t cur = __atomic_load_n(&s->readpid[i], __ATOMIC_ACQUIRE);
        if (cur != 0 && pid_alive(cur)) continue;
        if (__atomic_compare_exchange_n(&s->readpid[i], &cur, me, 0, __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE)) idx = i;
    }
    if (idx < 0)
        return swfs_fail(SWFS_ERR_VALUE, "%s: all %d semaphores are claimed by live readers", s->path, s->shape.nsem);
    s->claimed = idx;
    while (sem_trywait(&s->sems[idx]) == 0) {
    }
    return SWFS_OK;
}

int swfs_shm_reader_count(const swfs_shm *s)
{
    int n = 0;
    for (int i = 0; i < s->shape.nsem; i++) n += pid_alive(__atomic_load_n(&s->readpid[i], __ATOMIC_ACQUIRE));
    return n;
}

void swfs_shm_release(swfs_shm *s)
{
    if (!s || s->claimed < 0 || !s->map) return;
    pid_t me = getpid();
    __atomic_compare_exchange_n(&s->readpid[s->claimed], &me, 0, 0, __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE);
    s->claimed = -1;
}

int swfs_shm_wait(swfs_shm *s, double timeout, int *posted)
{
    *posted = 0;
    if (s->claimed < 0) {
        int rc = swfs_shm_claim(s);
        if (rc) return rc;
    }
    sem_t *sem = &s->sems[s->claimed];
    struct timespec dl;
    clock_gettime(CLOCK_REALTIME, &dl);
    const double t = timeout > 0 ? timeout : 0;
    const long long ns = (long long)(t * 1e9);
    dl.tv_sec += (time_t)(ns / 1000000000);
    dl.tv_nsec += (long)(ns % 1000000000);
    if (dl.tv_nsec >= 1000000000) {
        dl.tv_nsec -= 1000000000;
        dl.tv_sec += 1;
    }
    for (;;) {
        if (sem_timedwait(sem, &dl) == 0) break;
        if (errno == EINTR) continue;
        if (errno == ETIMEDOUT) return SWFS_OK;
        return swfs_fail(SWFS_ERR_IO, "%s: waiting on semaphore %d: %s", s->path, s->claimed, strerror(errno));
    }
    *posted = 1;
    while (sem_trywait(sem) == 0) {
    }
    return SWFS_OK;
}

static void frame_times(const struct timespec *at, const struct timespec *wt, swfs_shm_frame *f)
{
    f->wtime_ns = ts_ns(*wt);
    f->atime_ns = ts_ns(*at);
    f->stamped = 0;
    if (!f->atime_ns) f->atime_ns = f->wtime_ns;
    if (!f->atime_ns) {
        f->atime_ns = swfs_shm_now_ns();
        f->stamped = 1;
    }
}

/* The newest frame of a stream read whole (no per-slice counters): copy, then check that
 * no write overlapped the copy (the counter and the write flag unchanged). */
static int read_whole(swfs_shm *s, double *buf, swfs_shm_frame *meta, uint64_t *cnt)
{
    isio_meta *m = s->m;
    for (int attempt = 0; attempt < 1000; attempt++) {
        const uint64_t c1 = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
        if (__atomic_load_n(&m->write, __ATOMIC_ACQUIRE)) {
            sched_yield();
            continue;
        }
        const size_t slice = s->shape.temporal ? (size_t)(__atomic_load_n(&m->cnt1, __ATOMIC_ACQUIRE) % s->nslices) : 0;
        memcpy(s->raw, s->data + slice * s->fbytes, s->fbytes);
        struct timespec at = m->atime, wt = m->writetime;
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        const uint64_t c2 = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
        if (c1 != c2 || __atomic_load_n(&m->write, __ATOMIC_ACQUIRE)) continue;
        from_raw(s, s->raw, buf);
        frame_times(&at, &wt, meta);
        meta->cnt = c1;
        *cnt = c1;
        return SWFS_OK;
    }
    return swfs_fail(SWFS_ERR_IO, "%s: no consistent copy of the frame in 1000 attempts (the writer never pauses?)",
                     s->path);
}

int swfs_shm_read_latest(swfs_shm *s, double *frame, swfs_shm_frame *meta, size_t *n)
{
    *n = 0;
    if (!__atomic_load_n(&s->m->cnt0, __ATOMIC_ACQUIRE)) return SWFS_OK;
    uint64_t c = 0;
    int rc = read_whole(s, frame, meta, &c);
    if (!rc) *n = 1;
    return rc;
}

int swfs_shm_read(swfs_shm *s, double *buf, swfs_shm_frame *meta, size_t cap, size_t *n, uint64_t *lost)
{
    *n = 0;
    if (lost) *lost = 0;
    isio_meta *m = s->m;
    const uint64_t c = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
    if (c == s->last || !cap) return SWFS_OK;
    if (c < s->last)
        return swfs_fail(SWFS_ERR_VALUE, "%s: frame counter went back from %llu to %llu (writer restarted in place)",
                         s->path, (unsigned long long)s->last, (unsigned long long)c);
    if (!s->shape.temporal) {
        uint64_t got = 0;
        int rc = read_whole(s, buf, meta, &got);
        if (rc) return rc;
        if (got < s->last) return SWFS_OK; /* cannot happen with a sane writer */
        if (lost) *lost = got - s->last - 1;
        s->last = got;
        *n = 1;
        return SWFS_OK;
    }
    /* Rolling buffer: every counter after the last read that is still in a slice. */
    uint64_t k = s->last + 1, nlost = 0;
    const uint64_t depth = s->nslices;
    if (c - s->last > depth) {
        nlost += c - s->last - depth;
        k = c - depth + 1;
    }
    for (; k <= c && *n < cap; k++) {
        const size_t newest = (size_t)(__atomic_load_n(&m->cnt1, __ATOMIC_ACQUIRE) % depth);
        size_t sl = (size_t)((newest + depth - (c - k) % depth) % depth);
        int found = __atomic_load_n(&s->cnts[sl], __ATOMIC_ACQUIRE) == k;
        for (size_t j = 0; j < depth && !found; j++)
            if (__atomic_load_n(&s->cnts[j], __ATOMIC_ACQUIRE) == k) {
                sl = j;
                found = 1;
            }
        if (!found) {
            nlost++;
            continue;
        }
        const uint64_t c1 = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
        const int w1 = __atomic_load_n(&m->write, __ATOMIC_ACQUIRE);
        memcpy(s->raw, s->data + sl * s->fbytes, s->fbytes);
        struct timespec at = s->atimes[sl], wt = s->wtimes[sl];
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        /* Intact if the slice still holds k and no write can have touched it: the writer
         * overwrites the slice of counter k only at counter k + depth or later, and a
         * write that started or ended during the copy shows in the flag or the counter. */
        const uint64_t c2 = __atomic_load_n(&m->cnt0, __ATOMIC_ACQUIRE);
        const int w2 = __atomic_load_n(&m->write, __ATOMIC_ACQUIRE);
        const int safe = c2 + 1 < k + depth || (!w1 && !w2 && c1 == c2);
        if (__atomic_load_n(&s->cnts[sl], __ATOMIC_ACQUIRE) != k || !safe) {
            nlost++;
            continue;
        }
        from_raw(s, s->raw, buf + *n * s->fvals);
        swfs_shm_frame *f = &meta[*n];
        frame_times(&at, &wt, f);
        f->cnt = k;
        (*n)++;
    }
    s->last = k - 1;
    if (lost) *lost = nlost;
    return SWFS_OK;
}

int swfs_shm_check(const swfs_shm *s, int *state)
{
    struct stat sb;
    *state = 0;
    if (stat(s->path, &sb) != 0) {
        if (errno == ENOENT) {
            *state = 2;
            return SWFS_OK;
        }
        return swfs_fail(SWFS_ERR_IO, "%s: %s", s->path, strerror(errno));
    }
    if ((uint64_t)sb.st_ino != s->inode) *state = 1;
    return SWFS_OK;
}

void swfs_shm_skip_to_now(swfs_shm *s) { s->last = __atomic_load_n(&s->m->cnt0, __ATOMIC_ACQUIRE); }
void swfs_shm_set_last(swfs_shm *s, uint64_t last) { s->last = last; }

const swfs_shm_shape *swfs_shm_get_shape(const swfs_shm *s) { return &s->shape; }
const char *swfs_shm_get_path(const swfs_shm *s) { return s->path; }
size_t swfs_shm_frame_values(const swfs_shm *s) { return s->fvals; }
uint64_t swfs_shm_counter(const swfs_shm *s) { return __atomic_load_n(&s->m->cnt0, __ATOMIC_ACQUIRE); }
uint64_t swfs_shm_inode(const swfs_shm *s) { return s->inode; }

/* Shared-memory streams as a source of stream batches: see include/specklewfs/shm.h. */
#include "specklewfs/parallel.h"
#include "specklewfs/shm.h"
#include "specklewfs/status.h"

#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

enum { LAG_BINS = 2200 };                  /* log bins of 1 % from 1 us */
static const double lag_lo = 1e-6, lag_step = 1.01;

/* A frame in a reader's ring. */
typedef struct entry {
    uint64_t cnt;
    int64_t stamp;
    int expect;                 /* 1: the stream was (re)opened before this frame */
    int restarted;
    uint64_t from;              /* its counter when opened */
} entry;

typedef struct reader {
    struct swfs_shm_source *src;
    const char *name;
    int camera;                 /* 0: WFS stream `index` */
    size_t index;
    size_t nvals;               /* frame values (fixed at the first open) */
    swfs_shm *shm;
    int ever_open, expect_pending, restarted_pending;
    uint64_t expect_from;
    /* single-producer single-consumer ring */
    size_t cap;
    entry *meta;
    double *data;
    size_t head, tail;          /* atomics: consumer owns head, producer tail */
    uint64_t overruns;
    /* reader scratch */
    double *buf;
    swfs_shm_frame *fm;
    size_t bufcap;
    pthread_t th;
    int started;
} reader;

struct swfs_shm_source {
    swfs_shm_source_options o;
    size_t nr;                  /* readers: nwfs WFS + 1 camera (last) */
    reader r[SWFS_FRAMESYNC_MAX_WFS + 1];
    swfs_framesync *fs;
    pthread_mutex_t mu;
    pthread_cond_t cv;
    int quit;                   /* atomic */
    int failed;                 /* under mu */
    double last_in;             /* under mu: monotonic seconds of the last frame a reader took (-1: none) */
    int fail_code;
    char err[4800];
    uint64_t reopens;           /* atomic */
    double last_frame, first_frame; /* monotonic seconds (consumer) */
    int ended, have_prev;
    size_t prev_n;
    int64_t *prev_stamps;
    size_t batch_cap;
    double *scratch;            /* one frame of the largest stream (consumer) */
    uint64_t lag_hist[LAG_BINS];
    size_t lag_n;
    double lag_max;
};

void swfs_shm_source_options_default(swfs_shm_source_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_framesync_options_default(&o->sync);
    o->poll = 0.02;
    o->timeout = 10.0;
}

static void set_error(struct swfs_shm_source *s, int code, const char *msg)
{
    pthread_mutex_lock(&s->mu);
    if (!s->failed) {
        s->failed = 1;
        s->fail_code = code ? code : SWFS_ERR_IO;
        snprintf(s->err, sizeof s->err, "%s", msg);
    }
    pthread_cond_broadcast(&s->cv);
    pthread_mutex_unlock(&s->mu);
}

static int quitting(const struct swfs_shm_source *s) { return __atomic_load_n(&s->quit, __ATOMIC_ACQUIRE); }

static void sleep_s(double t)
{
    struct timespec ts = {(time_t)t, (long)((t - floor(t)) * 1e9)};
    nanosleep(&ts, NULL);
}

/* Open the reader's stream and check its frame size; SWFS_ERR_IO while it does not exist.
 * claim: take one of its semaphores now (a reopen in the reader's thread). The first open
 * claims later, when the readers start (swfs_shm_source_create): a writer waiting for a
 * reader (`replay --wait-reader`) must not start before the data start, or the frames it
 * publishes in between would be skipped without a count. */
static int reader_open(reader *rd, int claim)
{
    swfs_shm *m = NULL;
    int rc = swfs_shm_open(&m, rd->src->o.dir, rd->name);
    if (rc) return rc;
    const size_t nv = swfs_shm_frame_values(m);
    const swfs_shm_shape *sh = swfs_shm_get_shape(m);
    if (rd->ever_open && nv != rd->nvals) {
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the restarted stream has %zu values per frame; it had %zu",
                       swfs_shm_get_path(m), nv, rd->nvals);
        swfs_shm_close(m, 0);
        return rc;
    }
    const size_t depth = sh->temporal ? sh->nz : 1;
    if (!rd->ever_open) {
        rd->nvals = nv;
        rd->bufcap = depth;
        rd->buf = malloc(depth * nv * sizeof *rd->buf);
        rd->fm = malloc(depth * sizeof *rd->fm);
        if (!rd->buf || !rd->fm) {
            swfs_shm_close(m, 0);
            return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", rd->name);
        }
    } else if (depth > rd->bufcap) {
        double *b = realloc(rd->buf, depth * nv * sizeof *b);
        swfs_shm_frame *f = b ? realloc(rd->fm, depth * sizeof *f) : NULL;
        if (b) rd->buf = b;
        if (!b || !f) {
            swfs_shm_close(m, 0);
            return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", rd->name);
        }
        rd->fm = f;
        rd->bufcap = depth;
    }
    if (claim && (rc = swfs_shm_claim(m))) {
        swfs_shm_close(m, 0);
        return rc;
    }
    rd->shm = m;
    return SWFS_OK;
}

static void push(reader *rd, const swfs_shm_frame *f, const double *v)
{
    const size_t head = __atomic_load_n(&rd->head, __ATOMIC_ACQUIRE), tail = rd->tail;
    if (tail - head >= rd->cap) {
        rd->overruns++; /* the frame is lost; its counter gap shows in framesync too */
        return;
    }
    const size_t k = tail % rd->cap;
    rd->meta[k].cnt = f->cnt;
    rd->meta[k].stamp = f->atime_ns;
    rd->meta[k].expect = rd->expect_pending;
    rd->meta[k].restarted = rd->restarted_pending;
    rd->meta[k].from = rd->expect_from;
    rd->expect_pending = rd->restarted_pending = 0;
    memcpy(rd->data + k * rd->nvals, v, rd->nvals * sizeof *v);
    __atomic_store_n(&rd->tail, tail + 1, __ATOMIC_RELEASE);
}

static void *reader_main(void *arg)
{
    reader *rd = arg;
    struct swfs_shm_source *s = rd->src;
    char msg[4800];
    double gone_since = -1, last_check = swfs_wall_seconds();
    while (!quitting(s)) {
        if (!rd->shm) {
            int rc = reader_open(rd, 1);
            if (rc == SWFS_OK) {
                /* A restarted writer counts from 0: read what its stream still holds. */
                swfs_shm_set_last(rd->shm, 0);
                rd->expect_pending = rd->restarted_pending = 1;
                rd->expect_from = 0;
                __atomic_add_fetch(&s->reopens, 1, __ATOMIC_RELAXED);
                rd->ever_open = 1;
                gone_since = -1;
                continue;
            }
            if (rc != SWFS_ERR_IO) { /* exists but is not acceptable: no point in waiting */
                set_error(s, rc, swfs_last_error());
                break;
            }
            const double now = swfs_wall_seconds();
            if (gone_since < 0) gone_since = now;
            if (now - gone_since > s->o.timeout) {
                /* No frame from any stream for `idle` seconds: the data had ended, as the
                 * consumer sees when it keeps up (idle before the timeout); one far behind
                 * must not get an error for it (nothing is missing) */
                pthread_mutex_lock(&s->mu);
                const double last_in = s->last_in;
                pthread_mutex_unlock(&s->mu);
                if (s->o.idle > 0 && last_in >= 0 && now - last_in > s->o.idle) break;
                char path[4200];
                swfs_shm_path(s->o.dir, rd->name, path, sizeof path);
                snprintf(msg, sizeof msg, "%s stream '%s' (%s) %s for %.3g s", rd->camera ? "camera" : "WFS", rd->name,
                         path, rd->ever_open ? "disappeared and did not come back" : "did not appear",
                         s->o.timeout);
                set_error(s, SWFS_ERR_IO, msg);
                break;
            }
            sleep_s(s->o.poll);
            continue;
        }
        int posted = 0;
        int rc = swfs_shm_wait(rd->shm, s->o.poll, &posted);
        size_t n = 0;
        if (!rc) rc = swfs_shm_read(rd->shm, rd->buf, rd->fm, rd->bufcap, &n, NULL);
        if (rc == SWFS_ERR_VALUE) { /* the counter went back: a writer restarted in place */
            swfs_shm_close(rd->shm, 0);
            rd->shm = NULL;
            continue;
        }
        if (rc) {
            set_error(s, rc, swfs_last_error());
            break;
        }
        for (size_t k = 0; k < n; k++) push(rd, &rd->fm[k], rd->buf + k * rd->nvals);
        if (n) {
            pthread_mutex_lock(&s->mu);
            s->last_in = swfs_wall_seconds();
            pthread_cond_signal(&s->cv);
            pthread_mutex_unlock(&s->mu);
        }
        const double now = swfs_wall_seconds();
        if (!posted || now - last_check >= s->o.poll) {
            last_check = now;
            int state = 0;
            if (swfs_shm_check(rd->shm, &state) == SWFS_OK && state != 0) {
                /* Read what the old stream still holds, then switch. */
                if (swfs_shm_read(rd->shm, rd->buf, rd->fm, rd->bufcap, &n, NULL) == SWFS_OK)
                    for (size_t k = 0; k < n; k++) push(rd, &rd->fm[k], rd->buf + k * rd->nvals);
                swfs_shm_close(rd->shm, 0);
                rd->shm = NULL;
                if (state == 2) gone_since = now;
            }
        }
    }
    pthread_mutex_lock(&s->mu);
    pthread_cond_broadcast(&s->cv);
    pthread_mutex_unlock(&s->mu);
    return NULL;
}

void swfs_shm_source_close(swfs_shm_source *s)
{
    if (!s) return;
    __atomic_store_n(&s->quit, 1, __ATOMIC_RELEASE);
    for (size_t i = 0; i < s->nr; i++)
        if (s->r[i].started) pthread_join(s->r[i].th, NULL);
    for (size_t i = 0; i < s->nr; i++) {
        reader *rd = &s->r[i];
        swfs_shm_close(rd->shm, 0);
        free(rd->meta);
        free(rd->data);
        free(rd->buf);
        free(rd->fm);
    }
    swfs_framesync_free(s->fs);
    free(s->prev_stamps);
    free(s->scratch);
    pthread_mutex_destroy(&s->mu);
    pthread_cond_destroy(&s->cv);
    free(s);
}

int swfs_shm_source_open(swfs_shm_source **out, const swfs_shm_source_options *o)
{
    *out = NULL;
    if (!o->wfs || o->nwfs < 1 || o->nwfs > SWFS_FRAMESYNC_MAX_WFS || !o->camera)
        return swfs_fail(SWFS_ERR_ARG, "shm source: needs 1..%d WFS streams and a camera stream", SWFS_FRAMESYNC_MAX_WFS);
    if (!(o->poll > 0) || !(o->timeout >= 0) || !(o->idle >= 0))
        return swfs_fail(SWFS_ERR_ARG, "shm source: poll %g, timeout %g, idle %g (expected > 0, >= 0, >= 0)", o->poll,
                         o->timeout, o->idle);
    swfs_shm_source *s = calloc(1, sizeof *s);
    if (!s) return swfs_fail(SWFS_ERR_NOMEM, "shm source: out of memory");
    s->o = *o;
    pthread_mutex_init(&s->mu, NULL);
    pthread_cond_init(&s->cv, NULL);
    s->last_in = -1;
    s->nr = o->nwfs + 1;
    for (size_t i = 0; i < s->nr; i++) {
        reader *rd = &s->r[i];
        rd->src = s;
        rd->camera = i == o->nwfs;
        rd->index = rd->camera ? 0 : i;
        rd->name = rd->camera ? o->camera : o->wfs[i];
    }
    /* Open every stream (waiting for the missing ones), then check the sizes. */
    int rc = SWFS_OK;
    const double t0 = swfs_wall_seconds();
    for (size_t i = 0; i < s->nr && !rc; i++) {
        for (;;) {
            rc = reader_open(&s->r[i], 0);
            if (rc != SWFS_ERR_IO || swfs_wall_seconds() - t0 > o->timeout) break;
            if (o->stop && *o->stop) break;
            sleep_s(o->poll);
        }
        if (rc == SWFS_ERR_IO)
            swfs_fail_context(rc, "%s stream '%s' (waited %.3g s)", s->r[i].camera ? "camera" : "WFS", s->r[i].name,
                              o->timeout);
        s->r[i].ever_open = !rc;
    }
    size_t nsl = 0, nvals[SWFS_FRAMESYNC_MAX_WFS];
    for (size_t i = 0; i < o->nwfs && !rc; i++) nsl += nvals[i] = s->r[i].nvals;
    const reader *cam = &s->r[o->nwfs];
    if (!rc && o->nslopes && nsl != o->nslopes) {
        char names[1024] = "";
        for (size_t i = 0; i < o->nwfs; i++) {
            const size_t l = strlen(names);
            snprintf(names + l, sizeof names - l, "%s%s (%zu)", i ? " + " : "", swfs_shm_get_path(s->r[i].shm),
                     s->r[i].nvals);
        }
        rc = swfs_fail(SWFS_ERR_SHAPE, "WFS stream%s %s: %zu values per frame but the reconstructor expects %zu slopes",
                       o->nwfs > 1 ? "s" : "", names, nsl, o->nslopes);
    }
    if (!rc && o->nfx && o->nfy && cam->nvals != o->nfx * o->nfy) {
        const swfs_shm_shape *sh = swfs_shm_get_shape(cam->shm);
        rc = swfs_fail(SWFS_ERR_SHAPE, "camera stream %s: frames of %zux%zu%s (%zu values) but the geometry needs %zux%zu",
                       swfs_shm_get_path(cam->shm), sh->nx, sh->ny, sh->temporal ? " (rolling buffer)" : "", cam->nvals,
                       o->nfx, o->nfy);
    }
    if (!rc) rc = swfs_framesync_create(&s->fs, o->nwfs, nvals, cam->nvals, &o->sync);
    size_t maxv = 0;
    for (size_t i = 0; i < s->nr && !rc; i++) {
        reader *rd = &s->r[i];
        const size_t fb = rd->nvals * sizeof(double);
        rd->cap = o->ring ? o->ring : ((size_t)64 << 20) / fb;
        if (rd->cap < 256) rd->cap = 256;
        if (rd->cap > 16384) rd->cap = 16384;
        rd->meta = malloc(rd->cap * sizeof *rd->meta);
        rd->data = malloc(rd->cap * fb);
        if (!rd->meta || !rd->data) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for %zu frames", rd->name, rd->cap);
        if (rd->nvals > maxv) maxv = rd->nvals;
    }
    s->batch_cap = o->sync.batch;
    s->prev_stamps = rc ? NULL : malloc(s->batch_cap * sizeof *s->prev_stamps);
    s->scratch = rc ? NULL : malloc(maxv * sizeof *s->scratch);
    if (!rc && (!s->prev_stamps || !s->scratch)) rc = swfs_fail(SWFS_ERR_NOMEM, "shm source: out of memory");
    for (size_t i = 0; i < s->nr && !rc; i++) rc = swfs_shm_claim(s->r[i].shm);
    for (size_t i = 0; i < s->nr && !rc; i++) {
        /* The data start now: frames after the counter at this moment count. */
        const uint64_t c0 = swfs_shm_counter(s->r[i].shm);
        swfs_shm_set_last(s->r[i].shm, c0);
        s->r[i].expect_pending = 1;
        s->r[i].expect_from = c0;
        if (pthread_create(&s->r[i].th, NULL, reader_main, &s->r[i]) != 0)
            rc = swfs_fail(SWFS_ERR_INTERNAL, "shm source: cannot start the reader of %s", s->r[i].name);
        else s->r[i].started = 1;
    }
    if (rc) {
        swfs_shm_source_close(s);
        return rc;
    }
    s->first_frame = -1;
    *out = s;
    return SWFS_OK;
}

/* Move every frame the readers have buffered into the framesync. */
static int drain(swfs_shm_source *s, double now)
{
    int rc = SWFS_OK;
    for (size_t i = 0; i < s->nr && !rc; i++) {
        reader *rd = &s->r[i];
        size_t head = rd->head;
        const size_t tail = __atomic_load_n(&rd->tail, __ATOMIC_ACQUIRE);
        for (; head < tail && !rc; head++) {
            const size_t k = head % rd->cap;
            const entry *e = &rd->meta[k];
            if (e->expect) swfs_framesync_expect(s->fs, rd->camera, rd->index, e->from, e->restarted);
            const double *v = rd->data + k * rd->nvals;
            rc = rd->camera ? swfs_framesync_add_camera(s->fs, e->cnt, e->stamp, v, now)
                            : swfs_framesync_add_wfs(s->fs, rd->index, e->cnt, e->stamp, v, now);
            s->last_frame = now;
            if (s->first_frame < 0) s->first_frame = now;
        }
        __atomic_store_n(&rd->head, head, __ATOMIC_RELEASE);
    }
    return rc;
}

static void record_lags(swfs_shm_source *s)
{
    if (!s->have_prev) return;
    const int64_t now = swfs_shm_now_ns();
    for (size_t j = 0; j < s->prev_n; j++) {
        const double lag = 1e-9 * (double)(now - s->prev_stamps[j]);
        if (lag > s->lag_max) s->lag_max = lag;
        long bin = lag <= lag_lo ? 0 : (long)(log(lag / lag_lo) / log(lag_step));
        if (bin >= LAG_BINS) bin = LAG_BINS - 1;
        s->lag_hist[bin]++;
        s->lag_n++;
    }
    s->have_prev = 0;
}

int swfs_shm_source_next(void *ctx, swfs_batch *b)
{
    swfs_shm_source *s = ctx;
    memset(b, 0, sizeof *b);
    record_lags(s);
    if (s->ended) return SWFS_OK;
    for (;;) {
        const double now = swfs_wall_seconds();
        int rc = drain(s, now);
        if (rc) return rc;
        pthread_mutex_lock(&s->mu);
        const int failed = s->failed;
        pthread_mutex_unlock(&s->mu);
        if (failed) return swfs_fail(s->fail_code, "%s", s->err);
        const int stop = (s->o.stop && *s->o.stop) ||
                         (s->o.idle > 0 && s->first_frame >= 0 && now - s->last_frame > s->o.idle);
        if ((rc = swfs_framesync_next(s->fs, now, stop, b))) return rc;
        if (b->nexp) {
            memcpy(s->prev_stamps, swfs_framesync_batch_stamps(s->fs), b->nexp * sizeof *s->prev_stamps);
            s->prev_n = b->nexp;
            s->have_prev = 1;
            return SWFS_OK;
        }
        if (stop) {
            s->ended = 1;
            return SWFS_OK;
        }
        /* Wait for a reader to signal new frames (or the poll period). */
        struct timespec dl;
        clock_gettime(CLOCK_REALTIME, &dl);
        const long ns = (long)(s->o.poll * 1e9);
        dl.tv_sec += ns / 1000000000;
        dl.tv_nsec += ns % 1000000000;
        if (dl.tv_nsec >= 1000000000) {
            dl.tv_nsec -= 1000000000;
            dl.tv_sec++;
        }
        pthread_mutex_lock(&s->mu);
        int pending = s->failed;
        for (size_t i = 0; i < s->nr && !pending; i++)
            pending = __atomic_load_n(&s->r[i].tail, __ATOMIC_ACQUIRE) != s->r[i].head;
        if (!pending) pthread_cond_timedwait(&s->cv, &s->mu, &dl);
        pthread_mutex_unlock(&s->mu);
    }
}

void swfs_shm_source_settle(swfs_shm_source *s, double seconds)
{
    swfs_framesync_settle(s->fs, swfs_shm_now_ns() + (int64_t)(seconds * 1e9));
}

void swfs_shm_source_fail(swfs_shm_source *s, int code) { set_error(s, code, swfs_last_error()); }

static double lag_quantile(const swfs_shm_source *s, double q)
{
    if (!s->lag_n) return NAN;
    const double target = q * (double)s->lag_n;
    double acc = 0;
    for (int k = 0; k < LAG_BINS; k++) {
        acc += (double)s->lag_hist[k];
        if (acc >= target) return fmin(lag_lo * pow(lag_step, (double)k + 0.5), s->lag_max);
    }
    return s->lag_max;
}

void swfs_shm_source_get_stats(const swfs_shm_source *s, swfs_shm_source_stats *st)
{
    memset(st, 0, sizeof *st);
    swfs_framesync_get_stats(s->fs, &st->sync);
    for (size_t i = 0; i < s->nr; i++) st->ring_overruns += s->r[i].overruns;
    st->reopens = __atomic_load_n(&s->reopens, __ATOMIC_RELAXED);
    st->lag_count = s->lag_n;
    st->lag_median = lag_quantile(s, 0.5);
    st->lag_p99 = lag_quantile(s, 0.99);
    st->lag_max = s->lag_n ? s->lag_max : NAN;
    st->seconds = s->first_frame >= 0 ? s->last_frame - s->first_frame : 0.0;
}

size_t swfs_shm_source_wfs_values(const swfs_shm_source *s, size_t i) { return i < s->nr - 1 ? s->r[i].nvals : 0; }
size_t swfs_shm_source_camera_values(const swfs_shm_source *s) { return s->r[s->nr - 1].nvals; }

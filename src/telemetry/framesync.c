/* Timestamped frames -> stream batches: see include/specklewfs/framesync.h. */
#include "specklewfs/framesync.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum { NSEG = 4 }; /* WFS segments remembered (camera frames may still need a closed one) */

/* Linear clock of one stream within a segment: t = mt + beta (n - n0 - mn), least squares
 * with exponential forgetting (Welford's centered update with decayed weights, so large
 * counters and times keep their precision). */
typedef struct fclock {
    int npts;
    double w, mn, mt, snn, snt, n0;
    double prior;       /* period [s] of the previous segment (0: unknown) */
    double lam;
    uint64_t last;      /* last counter seen */
    int have_last, restart;
} fclock;

/* Points of a segment before its own slope replaces the previous segment's period: a
 * slope from a few jittered stamps is worse than a period fitted over a whole segment
 * (the offset is fitted either way). A slope more than 10 % off the prior is a changed
 * frame rate and is used at once. */
enum { FREE_SLOPE = 32 };

static double clock_beta(const fclock *c)
{
    const double free = c->npts >= 2 && c->snn > 0 ? c->snt / c->snn : 0.0;
    if (!(c->prior > 0)) return free;
    if (c->npts < 3) return c->prior;
    if (c->npts >= FREE_SLOPE || fabs(free - c->prior) > 0.1 * c->prior) return free;
    return c->prior;
}

static double clock_at(const fclock *c, double n)
{
    return c->mt + clock_beta(c) * (n - c->n0 - c->mn);
}

/* Add (cnt, t); returns 1 when it starts a new segment (first point, counter back, a
 * restart signalled, or a stamp off the model by more than half a period). */
static int clock_add(fclock *c, uint64_t cnt, double t)
{
    int fresh = c->npts == 0 || c->restart || !c->have_last || cnt <= c->last;
    if (!fresh && (c->npts >= 2 || !(c->prior > 0))) {
        const double b = clock_beta(c);
        if (b > 0 && fabs(t - clock_at(c, (double)cnt)) > 0.5 * b) fresh = 1;
    }
    if (fresh) {
        if (c->npts >= 2) c->prior = clock_beta(c);
        c->npts = 0;
        c->w = c->mn = c->mt = c->snn = c->snt = 0.0;
        c->n0 = (double)cnt;
    }
    const double x = (double)cnt - c->n0, lam = c->npts ? c->lam : 0.0;
    const double wn = lam * c->w + 1.0, dx = x - c->mn, dt = t - c->mt, f = lam * c->w / wn;
    c->snn = lam * c->snn + f * dx * dx;
    c->snt = lam * c->snt + f * dx * dt;
    c->mn += dx / wn;
    c->mt += dt / wn;
    c->w = wn;
    c->npts++;
    return fresh;
}

/* Frame counting: returns the frames lost before this one. */
static uint64_t count_lost(fclock *c, uint64_t cnt, uint64_t *restarts)
{
    uint64_t lost = 0;
    if (c->restart) {
        lost = cnt > c->last ? cnt - c->last - 1 : 0;
        (*restarts)++;
    } else if (c->have_last && cnt > c->last) {
        lost = cnt - c->last - 1;
    } else if (c->have_last) {
        (*restarts)++; /* the counter went back without a signal: a new writer */
        lost = cnt > 1 ? cnt - 1 : 0;
    }
    return lost;
}

/* A WFS segment: g(t) = ga + (t - ta) / beta maps a time to the global frame index g
 * (frame g covers [g - 1, g)); g = counter + off within the segment. */
typedef struct wseg {
    int id, live;
    int64_t off;
    int64_t g_first, g_last;
    double ga, ta, beta, t_first, t_last;
} wseg;

/* The master WFS clock's time -> frame map right after one of its frames (segment id, ga, ta, beta). */
typedef struct wmap {
    int id;
    double ga, ta, beta;
} wmap;

typedef struct camslot {
    uint64_t cnt;
    int seg;
    double t_end, arrival;
    int64_t stamp;
    double *data;
    fclock ck;          /* the camera clock right after this frame (its fit of frames up to it) */
} camslot;

struct swfs_framesync {
    swfs_framesync_options o;
    size_t nw, nvals[SWFS_FRAMESYNC_MAX_WFS], voff[SWFS_FRAMESYNC_MAX_WFS], ns, nf2;
    uint32_t fullmask;
    int64_t epoch;
    int have_epoch;
    /* WFS */
    fclock wc[SWFS_FRAMESYNC_MAX_WFS];
    wseg seg[NSEG];
    int nseg_total, cur;            /* segments opened; index of the current one in seg[] */
    int64_t last_g[SWFS_FRAMESYNC_MAX_WFS];
    size_t hist;
    int64_t *tag;
    /* per WFS slot: the master's time -> frame map right after that frame (segment id, ga, ta,
     * beta), so a batch is refined with the fit of the frames up to its last one, whatever
     * arrived since: the same numbers offline and live */
    wmap *snap;
    uint32_t *mask;
    unsigned char *bad;
    double *vals;                   /* hist x ns */
    /* camera */
    fclock cc;                      /* the current segment's clock */
    int camseg;
    size_t qcap, qhead, qlen;
    camslot *q;
    double *qdata;
    int64_t settle;
    int have_settle;
    /* the batch being filled */
    size_t bn, slcap, nwfs;
    int64_t g0, gend;
    int bseg_w, bseg_c;
    uint64_t blast;
    double boldest;
    int emitted;
    double *slopes, *science;
    swfs_exposure *sched;
    int64_t *stamps;
    uint64_t *bcnt;                 /* camera counters of the batch's frames */
    fclock bck;                     /* the camera clock right after the batch's last frame */
    swfs_framesync_stats st;
    /* a space-time reconstructor's lags: the batch's rows stacked at them (header, "Lags") */
    size_t nl;
    long lags[SWFS_RECON_MAXLAGS], lmax;
    double *stk;
    size_t stkcap;                  /* rows stk holds */
    int pending;                    /* the batch is closed, waiting for its lag frames */
};

void swfs_framesync_options_default(swfs_framesync_options *o)
{
    memset(o, 0, sizeof *o);
    o->batch = 16;
    o->max_wait = 0.5;
    o->clock_memory = 4096;
}

void swfs_framesync_free(swfs_framesync *f)
{
    if (!f) return;
    free(f->tag);
    free(f->snap);
    free(f->mask);
    free(f->bad);
    free(f->vals);
    free(f->q);
    free(f->qdata);
    free(f->slopes);
    free(f->science);
    free(f->sched);
    free(f->stamps);
    free(f->bcnt);
    free(f->stk);
    free(f);
}

int swfs_framesync_create(swfs_framesync **out, size_t nwfs, const size_t *nvals, size_t nf2,
                          const swfs_framesync_options *o)
{
    *out = NULL;
    swfs_framesync_options def;
    if (!o) {
        swfs_framesync_options_default(&def);
        o = &def;
    }
    if (nwfs < 1 || nwfs > SWFS_FRAMESYNC_MAX_WFS)
        return swfs_fail(SWFS_ERR_ARG, "framesync: %zu WFS streams; expected 1..%d", nwfs, SWFS_FRAMESYNC_MAX_WFS);
    if (!nf2 || !o->batch || !(o->max_wait >= 0) || !(o->exptime >= 0) || !(o->clock_memory >= 1))
        return swfs_fail(SWFS_ERR_ARG, "framesync: frame size %zu, batch %zu, max_wait %g, exptime %g, clock memory %g "
                         "(expected > 0, > 0, >= 0, >= 0, >= 1)", nf2, o->batch, o->max_wait, o->exptime,
                         o->clock_memory);
    if (o->nlags > 1) {
        const int lrc = o->lags && o->nlags <= SWFS_RECON_MAXLAGS ? swfs_lags_check(o->lags, o->nlags, "framesync: lags")
                                                                  : swfs_fail(SWFS_ERR_ARG, "framesync: %zu lags (at most "
                                                                              "%d)", o->nlags, SWFS_RECON_MAXLAGS);
        if (lrc) return lrc;
    }
    swfs_framesync *f = calloc(1, sizeof *f);
    if (!f) return swfs_fail(SWFS_ERR_NOMEM, "framesync: out of memory");
    f->o = *o;
    f->o.lags = NULL;
    if (o->nlags > 1) {
        f->nl = o->nlags;
        for (size_t k = 0; k < f->nl; k++) {
            f->lags[k] = o->lags[k];
            if (labs(o->lags[k]) > f->lmax) f->lmax = labs(o->lags[k]);
        }
    }
    f->nw = nwfs;
    for (size_t i = 0; i < nwfs; i++) {
        if (!nvals[i]) {
            free(f);
            return swfs_fail(SWFS_ERR_ARG, "framesync: WFS stream %zu has no values", i);
        }
        f->nvals[i] = nvals[i];
        f->voff[i] = f->ns;
        f->ns += nvals[i];
        f->wc[i].lam = 1.0 - 1.0 / o->clock_memory;
        f->last_g[i] = 0;
    }
    f->fullmask = (uint32_t)((1u << nwfs) - 1u);
    f->nf2 = nf2;
    f->cc.lam = 1.0 - 1.0 / o->clock_memory;
    const size_t cap = (size_t)256 << 20;
    f->hist = o->wfs_history ? o->wfs_history : 8192;
    if (!o->wfs_history && f->hist * f->ns * sizeof(double) > cap / 2) f->hist = cap / 2 / (f->ns * sizeof(double));
    if (f->hist < 64) f->hist = 64;
    f->qcap = o->camera_queue ? o->camera_queue : 4 * o->batch + 64;
    if (!o->camera_queue && f->qcap * nf2 * sizeof(double) > cap) f->qcap = cap / (nf2 * sizeof(double));
    if (f->qcap < o->batch + 1) f->qcap = o->batch + 1;
    f->tag = calloc(f->hist, sizeof *f->tag);
    f->snap = calloc(f->hist, sizeof *f->snap);
    f->mask = calloc(f->hist, sizeof *f->mask);
    f->bad = calloc(f->hist, 1);
    f->vals = malloc(f->hist * f->ns * sizeof *f->vals);
    f->q = calloc(f->qcap, sizeof *f->q);
    f->qdata = malloc(f->qcap * nf2 * sizeof *f->qdata);
    f->science = malloc(o->batch * nf2 * sizeof *f->science);
    f->sched = malloc(o->batch * sizeof *f->sched);
    f->stamps = malloc(o->batch * sizeof *f->stamps);
    f->bcnt = malloc(o->batch * sizeof *f->bcnt);
    if (!f->tag || !f->snap || !f->mask || !f->bad || !f->vals || !f->q || !f->qdata || !f->science || !f->sched ||
        !f->stamps || !f->bcnt) {
        swfs_framesync_free(f);
        return swfs_fail(SWFS_ERR_NOMEM, "framesync: out of memory for %zu WFS frames of %zu values and %zu camera "
                         "frames of %zu pixels", f->hist, f->ns, f->qcap, nf2);
    }
    for (size_t k = 0; k < f->qcap; k++) f->q[k].data = f->qdata + k * nf2;
    f->cur = -1;
    f->camseg = 0;
    *out = f;
    return SWFS_OK;
}

static double rel(swfs_framesync *f, int64_t ns)
{
    if (!f->have_epoch) {
        f->epoch = ns;
        f->have_epoch = 1;
    }
    return 1e-9 * (double)(ns - f->epoch);
}

/* The time -> frame map of a segment from the master clock. */
static void seg_update(wseg *s, const fclock *c)
{
    const double b = clock_beta(c);
    s->beta = b;
    s->ta = c->mt;
    s->ga = c->n0 + c->mn + (double)s->off;
}

static double seg_g(const wseg *s, double t) { return s->ga + (t - s->ta) / s->beta; }

static int64_t slot_of(const swfs_framesync *f, int64_t g) { return (int64_t)((uint64_t)g % f->hist); }

static void check_finite(swfs_framesync *f, size_t k, const double *v, size_t n)
{
    for (size_t i = 0; i < n; i++)
        if (!isfinite(v[i])) {
            if (!f->bad[k]) f->st.wfs_bad++;
            f->bad[k] = 1;
            return;
        }
}

int swfs_framesync_add_wfs(swfs_framesync *f, size_t i, uint64_t cnt, int64_t stamp_ns, const double *vals, double now)
{
    (void)now;
    if (i >= f->nw) return swfs_fail(SWFS_ERR_ARG, "framesync: WFS stream %zu of %zu", i, f->nw);
    f->st.wfs_received++;
    const double t = rel(f, stamp_ns);
    fclock *c = &f->wc[i];
    f->st.wfs_dropped += count_lost(c, cnt, &f->st.wfs_restarts);
    const int fresh = clock_add(c, cnt, t);
    c->restart = 0;
    c->last = cnt;
    c->have_last = 1;
    int64_t g;
    if (i == 0) {
        if (fresh || f->cur < 0) {
            /* Close the current segment (its map stays as it is) and open the next, its
             * frame indices two past the last one so nothing is contiguous across. */
            const int64_t g_next = f->cur >= 0 ? f->seg[f->cur].g_last + 2 : 1;
            f->cur = f->nseg_total % NSEG;
            wseg *s = &f->seg[f->cur];
            memset(s, 0, sizeof *s);
            s->id = f->nseg_total++;
            s->off = g_next - (int64_t)cnt;
            s->g_first = g_next;
            s->t_first = t;
            f->st.wfs_segments++;
        }
        wseg *s = &f->seg[f->cur];
        g = (int64_t)cnt + s->off;
        s->g_last = g;
        s->t_last = t;
        seg_update(s, c);
    } else {
        /* Another WFS stream: the master frame nearest in time (its own clock smooths its
         * stamp). Needs the master's clock. */
        if (f->cur < 0 || !(f->seg[f->cur].beta > 0)) {
            f->st.wfs_late++;
            return SWFS_OK;
        }
        g = llround(seg_g(&f->seg[f->cur], clock_at(c, (double)cnt)));
        if (g < f->seg[f->cur].g_first) {
            f->st.wfs_late++;
            return SWFS_OK;
        }
    }
    if (g <= f->last_g[0] - (int64_t)f->hist) {
        f->st.wfs_late++;
        return SWFS_OK;
    }
    const int64_t k = slot_of(f, g);
    if (f->tag[k] != g) {
        if (f->tag[k] > g) {
            f->st.wfs_late++;
            return SWFS_OK;
        }
        f->tag[k] = g;
        f->mask[k] = 0;
        f->bad[k] = 0;
    }
    if (i == 0) {
        const wseg *s = &f->seg[f->cur];
        f->snap[k] = (wmap){s->id, s->ga, s->ta, s->beta};
    }
    memcpy(f->vals + (size_t)k * f->ns + f->voff[i], vals, f->nvals[i] * sizeof *vals);
    check_finite(f, (size_t)k, vals, f->nvals[i]);
    f->mask[k] |= 1u << i;
    if (g > f->last_g[i]) f->last_g[i] = g;
    return SWFS_OK;
}

int swfs_framesync_add_camera(swfs_framesync *f, uint64_t cnt, int64_t stamp_ns, const double *frame, double now)
{
    f->st.camera_received++;
    const double t = rel(f, stamp_ns);
    fclock *c = &f->cc;
    f->st.camera_dropped += count_lost(c, cnt, &f->st.camera_restarts);
    if (clock_add(c, cnt, t)) {
        f->camseg++;
        f->st.camera_segments++;
    }
    c->restart = 0;
    c->last = cnt;
    c->have_last = 1;
    if (f->qlen == f->qcap) {
        f->qhead = (f->qhead + 1) % f->qcap;
        f->qlen--;
        f->st.overrun++;
    }
    camslot *q = &f->q[(f->qhead + f->qlen) % f->qcap];
    f->qlen++;
    q->cnt = cnt;
    q->seg = f->camseg;
    q->t_end = clock_at(c, (double)cnt);
    q->ck = *c;
    q->stamp = stamp_ns;
    q->arrival = now;
    memcpy(q->data, frame, f->nf2 * sizeof *frame);
    return SWFS_OK;
}

void swfs_framesync_expect(swfs_framesync *f, int camera, size_t i, uint64_t last, int restarted)
{
    fclock *c = camera ? &f->cc : i < f->nw ? &f->wc[i] : NULL;
    if (!c) return;
    c->last = last;
    c->have_last = 1;
    c->restart = restarted;
}

void swfs_framesync_settle(swfs_framesync *f, int64_t stamp_ns)
{
    f->settle = stamp_ns;
    f->have_settle = 1;
}

/* The segment that holds the exposure [t0, t1]: 0 found (*s), 1 not decidable yet (the
 * current segment has not reached t1), 2 none (before the WFS data or across a gap). */
static int locate(const swfs_framesync *f, double t0, double t1, const wseg **s)
{
    if (f->cur < 0) return 1;
    for (int back = 0; back < NSEG && back < f->nseg_total; back++) {
        const wseg *w = &f->seg[(f->cur - back + NSEG) % NSEG];
        if (!(w->beta > 0)) continue;
        if (t0 < w->t_first - w->beta) continue; /* before this segment's first frame */
        *s = w;
        if (back == 0) return 0;
        return t1 <= w->t_last + 0.5 * w->beta ? 0 : 2;
    }
    return f->cur >= 0 && t0 >= f->seg[f->cur].t_first ? 1 : 2;
}

static int frame_ok(const swfs_framesync *f, int64_t g)
{
    const int64_t k = slot_of(f, g);
    return f->tag[k] == g && f->mask[k] == f->fullmask && !f->bad[k];
}

static int grow_slopes(swfs_framesync *f, size_t nrows)
{
    if (nrows <= f->slcap) return SWFS_OK;
    size_t cap = f->slcap ? f->slcap : 64;
    while (cap < nrows) cap *= 2;
    double *t = realloc(f->slopes, cap * f->ns * sizeof *t);
    if (!t) return swfs_fail(SWFS_ERR_NOMEM, "framesync: out of memory for a batch of %zu WFS frames", nrows);
    f->slopes = t;
    f->slcap = cap;
    return SWFS_OK;
}

/* The weights of an exposure [x0, x1) in frame units over frames ga..gb. */
static void weights(swfs_exposure *e, double x0, double x1, int64_t ga, int64_t gb)
{
    e->w_first = fmin((double)ga, x1) - x0;
    e->w_last = e->count == 1 ? e->w_first : x1 - (double)(gb - 1);
}

/* Frames are appended as soon as their WFS frames are in; by the time the batch closes the
 * clocks have seen more stamps. Re-evaluate the exposures with the fits of the frames up to
 * the batch's last ones: the camera clock right after its last camera frame and the WFS
 * map right after its last WFS frame -- not with whatever arrived since, so the batch's
 * numbers depend on the data alone, not on how the streams' frames interleaved (`live`
 * and `stream --wfs-log` agree). The frames an exposure uses stay the same; a refinement
 * that would change them is not applied. */
static void refine(swfs_framesync *f)
{
    const int64_t slot = slot_of(f, f->gend);
    const wmap *m = &f->snap[slot];
    if (f->tag[slot] != f->gend || m->id != f->bseg_w) return;
    const wseg map = {.ga = m->ga, .ta = m->ta, .beta = m->beta};
    const wseg *s = &map;
    const fclock *cc = &f->bck;
    const double cam_period = f->o.exptime > 0 ? f->o.exptime : clock_beta(cc);
    if (!(cam_period > 0) || !(s->beta > 0)) return;
    for (size_t j = 0; j < f->bn; j++) {
        swfs_exposure *e = &f->sched[j];
        const double t1 = clock_at(cc, (double)f->bcnt[j]), t0 = t1 - cam_period;
        const double x0 = seg_g(s, t0), x1 = seg_g(s, t1);
        const int64_t ga = (int64_t)floor(x0) + 1, gb0 = (int64_t)ceil(x1), gb = gb0 < ga ? ga : gb0;
        if (ga - f->g0 != (int64_t)e->first || gb - ga + 1 != (int64_t)e->count) continue;
        weights(e, x0, x1, ga, gb);
    }
}

/* The batch's segment, or NULL when it has left the ring. */
static const wseg *batch_seg(const swfs_framesync *f)
{
    for (int k = 0; k < NSEG; k++)
        if (f->seg[k].id == f->bseg_w && f->seg[k].beta > 0) return &f->seg[k];
    return NULL;
}

/* Lags: whether the frames of the batch's last row plus the largest lag are in from every
 * WFS stream, or its segment has ended (flush: the data have). */
static int lags_ready(const swfs_framesync *f, int flush)
{
    if (flush || f->cur < 0 || f->seg[f->cur].id != f->bseg_w) return 1;
    for (size_t i = 0; i < f->nw; i++)
        if (f->last_g[i] < f->gend + f->lmax) return 0;
    return 1;
}

/* Lags: the batch's rows stacked (header, "Lags"). */
static int stack_rows(swfs_framesync *f)
{
    const size_t ns = f->ns, w = ns * f->nl;
    if (f->nwfs > f->stkcap) {
        double *t = realloc(f->stk, f->nwfs * w * sizeof *t);
        if (!t) return swfs_fail(SWFS_ERR_NOMEM, "framesync: out of memory for %zu WFS frames of %zu lags", f->nwfs, f->nl);
        f->stk = t;
        f->stkcap = f->nwfs;
    }
    const wseg *s = batch_seg(f);
    int64_t lo = s ? s->g_first : f->g0, hi = s ? s->g_last : f->gend;
    for (size_t i = 1; i < f->nw; i++)
        if (f->last_g[i] < hi) hi = f->last_g[i];
    if (hi < f->gend) hi = f->gend;
    if (lo < f->last_g[0] - (int64_t)f->hist + 1) lo = f->last_g[0] - (int64_t)f->hist + 1;
    for (size_t r = 0; r < f->nwfs; r++) {
        const int64_t g = f->g0 + (int64_t)r;
        const double *own = f->slopes + r * ns;
        for (size_t k = 0; k < f->nl; k++) {
            int64_t t = g + f->lags[k];
            t = t < lo ? lo : t > hi ? hi : t;
            const double *src = frame_ok(f, t) ? f->vals + (size_t)slot_of(f, t) * ns : own;
            memcpy(f->stk + r * w + k * ns, src, ns * sizeof *src);
        }
    }
    return SWFS_OK;
}

static void emit(swfs_framesync *f, swfs_batch *b)
{
    refine(f);
    b->slopes = f->nl ? f->stk : f->slopes;
    b->nwfs = f->nwfs;
    b->sched = f->sched;
    b->science = f->science;
    b->nexp = f->bn;
    b->cube = (size_t)f->st.batches;
    f->st.batches++;
    f->st.used += f->bn;
    f->emitted = 1;
}

static void pop(swfs_framesync *f)
{
    f->qhead = (f->qhead + 1) % f->qcap;
    f->qlen--;
}

/* The batch out now, or (lags) once its lag frames are in: pending until then. */
static int close_batch(swfs_framesync *f, int flush, swfs_batch *b)
{
    if (f->nl && !lags_ready(f, flush)) {
        f->pending = 1;
        return SWFS_OK;
    }
    f->pending = 0;
    const int rc = f->nl ? stack_rows(f) : SWFS_OK;
    if (!rc) emit(f, b);
    return rc;
}

int swfs_framesync_next(swfs_framesync *f, double now, int flush, swfs_batch *b)
{
    memset(b, 0, sizeof *b);
    if (f->emitted) {
        f->emitted = 0;
        f->bn = 0;
        f->nwfs = 0;
    }
    if (f->pending) return close_batch(f, flush, b);
    const double cam_period = f->o.exptime > 0 ? f->o.exptime : clock_beta(&f->cc);
    while (f->qlen) {
        camslot *q = &f->q[f->qhead];
        if (!(cam_period > 0)) {
            if (!flush) break;
            f->st.no_wfs++;
            pop(f);
            continue;
        }
        const double t1 = q->t_end, t0 = t1 - cam_period;
        if (f->have_settle && t0 < 1e-9 * (double)(f->settle - f->epoch)) {
            f->st.unsettled++;
            pop(f);
            continue;
        }
        const wseg *s = NULL;
        int r = locate(f, t0, t1, &s);
        if (r == 1 && !flush) break;
        if (r) {
            f->st.no_wfs++;
            pop(f);
            continue;
        }
        const double x0 = seg_g(s, t0), x1 = seg_g(s, t1);
        const int64_t ga = (int64_t)floor(x0) + 1;
        int64_t gb = (int64_t)ceil(x1);
        if (gb < ga) gb = ga;
        int decided = gb <= s->g_last;
        for (size_t i = 1; i < f->nw && decided; i++) decided = f->last_g[i] >= gb;
        if (!decided && s == &f->seg[f->cur] && !flush) break;
        int ok = decided && ga >= s->g_first && ga > f->last_g[0] - (int64_t)f->hist;
        for (int64_t g = ga; g <= gb && ok; g++) ok = frame_ok(f, g);
        if (!ok) {
            f->st.incomplete++;
            pop(f);
            continue;
        }
        /* A complete exposure: close the batch first if it does not continue it. */
        if (f->bn && (q->seg != f->bseg_c || q->cnt != f->blast + 1 || s->id != f->bseg_w || ga < f->g0))
            return close_batch(f, flush, b);
        if (!f->bn) {
            f->g0 = ga;
            f->gend = ga - 1;
            f->bseg_w = s->id;
            f->bseg_c = q->seg;
            f->boldest = q->arrival;
        }
        const size_t nrows = (size_t)(gb - f->g0 + 1);
        int rc = grow_slopes(f, nrows);
        if (rc) return rc;
        for (int64_t g = f->gend + 1; g <= gb; g++) {
            double *row = f->slopes + (size_t)(g - f->g0) * f->ns;
            if (frame_ok(f, g)) memcpy(row, f->vals + (size_t)slot_of(f, g) * f->ns, f->ns * sizeof *row);
            else memset(row, 0, f->ns * sizeof *row); /* between exposures: used by none */
        }
        if (gb > f->gend) f->gend = gb;
        f->nwfs = (size_t)(f->gend - f->g0 + 1);
        swfs_exposure *e = &f->sched[f->bn];
        e->first = (size_t)(ga - f->g0);
        e->count = (size_t)(gb - ga + 1);
        weights(e, x0, x1, ga, gb);
        memcpy(f->science + f->bn * f->nf2, q->data, f->nf2 * sizeof *f->science);
        f->stamps[f->bn] = q->stamp;
        f->bcnt[f->bn] = q->cnt;
        f->blast = q->cnt;
        f->bck = q->ck;
        f->bn++;
        pop(f);
        if (f->bn == f->o.batch) return close_batch(f, flush, b);
    }
    if (f->bn && (flush || now - f->boldest >= f->o.max_wait)) return close_batch(f, flush, b);
    return SWFS_OK;
}

const int64_t *swfs_framesync_batch_stamps(const swfs_framesync *f) { return f->stamps; }

void swfs_framesync_get_stats(const swfs_framesync *f, swfs_framesync_stats *s)
{
    *s = f->st;
    s->wfs_period = f->cur >= 0 && f->seg[f->cur].beta > 0 ? f->seg[f->cur].beta : 0.0;
    const double cp = clock_beta(&f->cc);
    s->camera_period = cp > 0 ? cp : 0.0;
}

size_t swfs_framesync_nslopes(const swfs_framesync *f) { return f->ns; }

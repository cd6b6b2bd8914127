/* The fast per-frame engine: see include/specklewfs/engine.h and docs/streaming.md.
 *
 * Data layout of one worker's pass over up to NG WFS frames, in blocks of BLK:
 *   sblk  NG x nslopes        slopes (float, tip-tilt removed)
 *   zt    nact x NG           phases at the actuators, (2 pi/lambda) W s, one GEMM for all
 *                             NG frames (a GEMM with few columns would re-read W, 32 MB for
 *                             the ExAO case, for every handful of frames)
 *   y     BLK x TILE          phases of one block on TILE illuminated pupil samples: each
 *                             CSR nonzero of the interpolation is one BLK-wide FMA
 *   s, c  BLK x TILE          sin, cos (kernels.h)
 *   fre, fim  per exposure    sum over the exposure's frames of w cos, w sin (npin each)
 * then per exposure: grid = amp (fre + i fim) scattered onto the pupil grid, one float MFT,
 * core-phase referencing (eq:downsampledHalo), double output. */
#include "specklewfs/engine.h"
#include "specklewfs/array.h"
#include "specklewfs/kernels.h"
#include "specklewfs/mft.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum {
    BLK = 16,           /* WFS frames per interpolation pass: one AVX-512 float vector */
    NG = 256,           /* WFS frames per reconstruction GEMM (OpenBLAS sgemm reaches its rate here) */
    LDZ = NG + BLK,     /* row stride of zt: a power-of-two stride (1 KB) would map the rows
                           the interpolation reads onto a few cache sets */
    TILE = 512,         /* pupil samples per pass: y, s, c stay in L2 (3 x 32 KB) */
    CHUNK_EXP = 16,     /* exposures open at once in a worker (field buffers) */
    CHUNK_FRAMES = 256, /* WFS frames spanned by a chunk (unless one exposure is longer) */
    CHUNK_MIN_FRAMES = 32, /* a batch is cut into CHUNKS_MIN chunks, but none spans fewer
                              WFS frames than this unless one exposure is shorter: below it
                              the GEMM re-reads W for too few frames */
    CHUNKS_MIN = 4,
    MAX_THREADS = SWFS_ENGINE_MAX_THREADS
};

/* 16 floats, one frame per lane (GCC/Clang vector extension: the auto-vectorizer does not
 * find this loop on its own). */
typedef float v16f __attribute__((vector_size(BLK * sizeof(float))));

typedef struct seg {
    size_t b0, b1;  /* frames [b0, b1) of the block */
    float w[BLK];   /* weight of frame b (index in the block) */
    float *re, *im; /* field sums of the target exposure (npin) */
} seg;

typedef struct worker {
    float *zt, *zb, *y, *s, *c; /* zb: nact x BLK, the block's columns of zt packed */
    float *sblk;             /* NG x nslopes (batch path) */
    float *fre, *fim;        /* CHUNK_EXP slots x npin */
    float complex *grid;     /* npup^2, zero outside the illuminated samples */
    float complex *focal;    /* nfx * nfy */
    swfs_mft *mft;
    seg segs[2 * BLK + 1];
    int status;
    char err[512];
} worker;

/* A batch job: exposures come from a schedule or are implicit single frames. */
typedef struct job {
    const double *slopes;
    size_t nwfs;
    const swfs_exposure *sched; /* NULL: exposure j = WFS frame j, weight 1 */
    size_t nexp;
    double complex *out;
    size_t next;                /* next exposure to hand out (under mu) */
    size_t chunk1;              /* single-frame exposures per chunk */
    size_t span_max;            /* schedule: WFS frames a chunk may span (chunk_end) */
} job;

struct swfs_engine {
    size_t nslopes, nact, npup, nfx, nfy, npin;
    double alpha, wavelen;
    int remove_tiptilt, nthreads;
    /* Plans, built once. */
    float *wf;          /* nact x nslopes: (2 pi / lambda) W */
    size_t *rp;         /* npin + 1: CSR of the interpolation restricted to illuminated rows */
    uint32_t *col;      /* column (actuator) a, stored as its offset a * BLK in zb */
    float *val;
    size_t *pidx;       /* npin: grid index of illuminated sample r */
    float *amp;         /* npin: pupil transmission */
    worker *wk;
    /* Stream state (add_wfs / end_exposure). */
    float *pend;        /* NG x nslopes */
    float pend_w[NG];
    size_t npend;
    float *run_re, *run_im;
    /* Thread pool: nthreads - 1 helpers; the caller is worker 0. */
    pthread_t *th;
    size_t nth_started, nth_started_ok;
    pthread_mutex_t mu;
    pthread_cond_t cv_start, cv_done;
    unsigned long gen;
    size_t ndone;
    int stop;
    job *cur;
};

/* ---- per-frame kernels ------------------------------------------------- */

/* Slopes of one frame to float, tip-tilt removed; SWFS_ERR_VALUE on a non-finite value. */
static int convert_slopes(const swfs_engine *e, const double *s, float *out, size_t frame)
{
    const size_t n = e->nslopes, h = n / 2;
    double mx = 0.0, my = 0.0;
    for (size_t k = 0; k < n; k++)
        if (!isfinite(s[k]))
            return swfs_fail(SWFS_ERR_VALUE, "slope %zu of WFS frame %zu is not finite", k, frame);
    if (e->remove_tiptilt) {
        for (size_t k = 0; k < h; k++) { mx += s[k]; my += s[h + k]; }
        mx /= (double)h;
        my /= (double)h;
    }
    for (size_t k = 0; k < h; k++) {
        out[k] = (float)(s[k] - mx);
        out[h + k] = (float)(s[h + k] - my);
    }
    if (n % 2) out[n - 1] = (float)s[n - 1]; /* odd count only without tip-tilt removal */
    return SWFS_OK;
}

/* zt (nact x NG, row stride LDZ) = wf (nact x nslopes) * sblk^T: ng <= NG frames in one GEMM. */
static void reconstruct(const swfs_engine *e, worker *w, const float *sblk, size_t ng)
{
    cblas_sgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)e->nact, (int)ng, (int)e->nslopes, 1.0f, e->wf,
                (int)e->nslopes, sblk, (int)e->nslopes, 0.0f, w->zt, LDZ);
}

/* The pupil-field sums of the nb frames in columns [bo, bo + nb) of zt into the segments'
 * targets (segment frame indices are relative to bo). */
static void project_block(const swfs_engine *e, worker *w, size_t bo, size_t nb, const seg *segs, size_t nseg)
{
    unsigned used = 0; /* frames of the block some segment needs */
    for (size_t k = 0; k < nseg; k++)
        for (size_t b = segs[k].b0; b < segs[k].b1; b++)
            if (segs[k].w[b] != 0.0f) used |= 1u << b;

    /* Pack the block's 16 columns contiguously (64 B per actuator): the interpolation's
     * gathers then stay within a few pages instead of one page per few actuators. */
    for (size_t a = 0; a < e->nact; a++) memcpy(w->zb + a * BLK, w->zt + a * LDZ + bo, BLK * sizeof(float));
    for (size_t r0 = 0; r0 < e->npin; r0 += TILE) {
        const size_t len = e->npin - r0 < TILE ? e->npin - r0 : TILE;
        float *restrict y = w->y;
        const float *restrict zt = w->zb;
        /* Interpolation, 16 frames per nonzero (lanes beyond nb are never read): one vector
         * multiply-add of a whole zt row segment per nonzero, then the lanes are stored
         * frame-major so that everything downstream runs over contiguous samples. */
        for (size_t rr = 0; rr < len; rr++) {
            const size_t r = r0 + rr;
            /* Four independent sums: one chain would wait on the add latency. */
            v16f a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0}, z0, z1, z2, z3;
            size_t k = e->rp[r];
            const size_t kend = e->rp[r + 1];
            for (; k + 4 <= kend; k += 4) {
                memcpy(&z0, zt + e->col[k], sizeof z0);
                memcpy(&z1, zt + e->col[k + 1], sizeof z1);
                memcpy(&z2, zt + e->col[k + 2], sizeof z2);
                memcpy(&z3, zt + e->col[k + 3], sizeof z3);
                a0 += e->val[k] * z0;
                a1 += e->val[k + 1] * z1;
                a2 += e->val[k + 2] * z2;
                a3 += e->val[k + 3] * z3;
            }
            for (; k < kend; k++) {
                memcpy(&z0, zt + e->col[k], sizeof z0);
                a0 += e->val[k] * z0;
            }
            const v16f acc = (a0 + a1) + (a2 + a3);
            for (int b = 0; b < BLK; b++) y[(size_t)b * TILE + rr] = acc[b];
        }
        for (size_t b = 0; b < nb; b++)
            if (used & (1u << b)) swfs_sincos_f(y + b * TILE, w->s + b * TILE, w->c + b * TILE, len);
        /* Weighted sums into the exposures (amplitude applied once per exposure). */
        for (size_t k = 0; k < nseg; k++) {
            float *restrict re = segs[k].re + r0, *restrict im = segs[k].im + r0;
            for (size_t b = segs[k].b0; b < segs[k].b1; b++) {
                const float wb = segs[k].w[b];
                if (wb == 0.0f) continue;
                const float *restrict cb = w->c + b * TILE, *restrict sb = w->s + b * TILE;
                for (size_t rr = 0; rr < len; rr++) {
                    re[rr] += wb * cb[rr];
                    im[rr] += wb * sb[rr];
                }
            }
        }
    }
}

/* MFT of one exposure's field and core-phase referencing (eq:downsampledHalo). */
static void finish_exposure(const swfs_engine *e, worker *w, const float *re, const float *im,
                            double complex *out)
{
    float *g = (float *)w->grid;
    for (size_t r = 0; r < e->npin; r++) {
        g[2 * e->pidx[r]] = e->amp[r] * re[r];
        g[2 * e->pidx[r] + 1] = e->amp[r] * im[r];
    }
    swfs_mft_forward_f(w->mft, w->grid, w->focal);
    const size_t nf = e->nfx * e->nfy;
    const double complex core = w->focal[(e->nfy / 2) * e->nfx + e->nfx / 2];
    const double mag = cabs(core);
    const double complex ref = mag > 0.0 ? conj(core) / mag : 1.0;
    for (size_t k = 0; k < nf; k++) out[k] = (double complex)w->focal[k] * ref;
}

/* ---- batches ------------------------------------------------------------- */

static void get_exposure(const job *j, size_t i, swfs_exposure *x)
{
    if (j->sched) {
        *x = j->sched[i];
        if (x->count == 1) x->w_last = x->w_first;
    } else {
        x->first = i;
        x->count = 1;
        x->w_first = x->w_last = 1.0;
    }
}

/* Exposures [e0, e1) handed to one worker. The split depends on the schedule only. With a
 * schedule: at most CHUNK_EXP exposures (one field slot each) spanning at most CHUNK_FRAMES
 * WFS frames (more only for a single long exposure). Single-frame exposures: CHUNK_FRAMES of
 * them at most, fewer for small batches (chunk1: at least 8 chunks per batch when possible,
 * so that a worker slowed by other load does not hold up the batch); those of one BLK
 * block occupy distinct slots and all finish with the block. A schedule's chunks span at
 * most span_max frames: the batch's span over CHUNKS_MIN, within [CHUNK_MIN_FRAMES,
 * CHUNK_FRAMES], so that a small batch (a live stream's few camera frames) still gives
 * every worker a chunk instead of one worker all of it. Fixed by the schedule alone. */
static size_t chunk_end(const job *j, size_t e0)
{
    if (!j->sched) return j->nexp - e0 < j->chunk1 ? j->nexp : e0 + j->chunk1;
    swfs_exposure x;
    get_exposure(j, e0, &x);
    size_t lo = x.first, hi = x.first + x.count, e1 = e0 + 1;
    while (e1 < j->nexp && e1 - e0 < CHUNK_EXP) {
        get_exposure(j, e1, &x);
        const size_t nlo = x.first < lo ? x.first : lo;
        const size_t nhi = x.first + x.count > hi ? x.first + x.count : hi;
        if (nhi - nlo > j->span_max) break;
        lo = nlo;
        hi = nhi;
        e1++;
    }
    return e1;
}

static int run_chunk(const swfs_engine *e, worker *w, const job *j, size_t e0, size_t e1)
{
    swfs_exposure x;
    size_t lo = SIZE_MAX, hi = 0;
    for (size_t i = e0; i < e1; i++) {
        get_exposure(j, i, &x);
        if (x.first < lo) lo = x.first;
        if (x.first + x.count > hi) hi = x.first + x.count;
    }
    memset(w->fre, 0, CHUNK_EXP * e->npin * sizeof(float));
    memset(w->fim, 0, CHUNK_EXP * e->npin * sizeof(float));
    for (size_t g0 = lo; g0 < hi; g0 += NG) {
        const size_t ng = hi - g0 < NG ? hi - g0 : NG;
        for (size_t b = 0; b < ng; b++) {
            int rc = convert_slopes(e, j->slopes + (g0 + b) * e->nslopes, w->sblk + b * e->nslopes, g0 + b);
            if (rc) return rc;
        }
        reconstruct(e, w, w->sblk, ng);
        for (size_t bo = 0; bo < ng; bo += BLK) {
            const size_t b0 = g0 + bo, nb = ng - bo < BLK ? ng - bo : BLK;
            size_t nseg = 0;
            for (size_t i = e0; i < e1; i++) {
                get_exposure(j, i, &x);
                const size_t last = x.first + x.count - 1;
                const size_t f0 = x.first > b0 ? x.first : b0;
                const size_t f1 = last + 1 < b0 + nb ? last + 1 : b0 + nb;
                if (f0 >= f1) continue;
                seg *sg = &w->segs[nseg++];
                sg->b0 = f0 - b0;
                sg->b1 = f1 - b0;
                for (size_t f = f0; f < f1; f++)
                    sg->w[f - b0] = (float)(f == x.first ? x.w_first : f == last ? x.w_last : 1.0);
                sg->re = w->fre + (i - e0) % CHUNK_EXP * e->npin;
                sg->im = w->fim + (i - e0) % CHUNK_EXP * e->npin;
            }
            if (nseg) project_block(e, w, bo, nb, w->segs, nseg);
            /* Exposures that end in this block: propagate, then free their slot. */
            for (size_t i = e0; i < e1; i++) {
                get_exposure(j, i, &x);
                const size_t last = x.first + x.count - 1;
                if (last < b0 || last >= b0 + nb) continue;
                float *re = w->fre + (i - e0) % CHUNK_EXP * e->npin, *im = w->fim + (i - e0) % CHUNK_EXP * e->npin;
                finish_exposure(e, w, re, im, j->out + i * e->nfx * e->nfy);
                memset(re, 0, e->npin * sizeof(float));
                memset(im, 0, e->npin * sizeof(float));
            }
        }
    }
    return SWFS_OK;
}

/* Take chunks until the job is done; the first error stops this worker. */
static void run_job(swfs_engine *e, int tid)
{
    worker *w = &e->wk[tid];
    job *j = e->cur;
    for (;;) {
        pthread_mutex_lock(&e->mu);
        const size_t e0 = j->next;
        const size_t e1 = e0 < j->nexp ? chunk_end(j, e0) : e0;
        j->next = e1;
        pthread_mutex_unlock(&e->mu);
        if (e0 >= j->nexp) break;
        int rc = run_chunk(e, w, j, e0, e1);
        if (rc) {
            w->status = rc;
            snprintf(w->err, sizeof w->err, "%s", swfs_last_error());
            pthread_mutex_lock(&e->mu);
            j->next = j->nexp; /* stop the others early */
            pthread_mutex_unlock(&e->mu);
            break;
        }
    }
}

static void *pool_main(void *arg)
{
    swfs_engine *e = arg;
    pthread_mutex_lock(&e->mu);
    const int tid = (int)++e->nth_started; /* helpers are workers 1..nthreads-1 */
    unsigned long seen = 0; /* gen only grows after creation: a late starter still runs its first job */
    for (;;) {
        while (e->gen == seen && !e->stop) pthread_cond_wait(&e->cv_start, &e->mu);
        if (e->stop) break;
        seen = e->gen;
        pthread_mutex_unlock(&e->mu);
        run_job(e, tid);
        pthread_mutex_lock(&e->mu);
        e->ndone++;
        pthread_cond_signal(&e->cv_done);
    }
    pthread_mutex_unlock(&e->mu);
    return NULL;
}

static int run_batch(swfs_engine *e, job *j)
{
    for (int t = 0; t < e->nthreads; t++) e->wk[t].status = SWFS_OK;
    e->cur = j;
    if (e->nthreads > 1) {
        pthread_mutex_lock(&e->mu);
        e->ndone = 0;
        e->gen++;
        pthread_cond_broadcast(&e->cv_start);
        pthread_mutex_unlock(&e->mu);
    }
    run_job(e, 0);
    if (e->nthreads > 1) {
        pthread_mutex_lock(&e->mu);
        while (e->ndone < (size_t)(e->nthreads - 1)) pthread_cond_wait(&e->cv_done, &e->mu);
        pthread_mutex_unlock(&e->mu);
    }
    e->cur = NULL;
    for (int t = 0; t < e->nthreads; t++)
        if (e->wk[t].status) return swfs_fail(e->wk[t].status, "%s", e->wk[t].err);
    return SWFS_OK;
}

int swfs_engine_process(swfs_engine *e, const double *slopes, size_t nwfs, const swfs_exposure *sched,
                        size_t nexp, double complex *halo_out)
{
    if (!e || (nexp && (!slopes || !sched || !halo_out)))
        return swfs_fail(SWFS_ERR_ARG, "engine: missing slopes, schedule or output buffer");
    for (size_t i = 0; i < nexp; i++) {
        const swfs_exposure *x = &sched[i];
        if (x->count == 0 || x->first >= nwfs || x->count > nwfs - x->first) /* (no sum that could wrap) */
            return swfs_fail(SWFS_ERR_ARG,
                             "engine: camera frame %zu integrates %zu WFS frames from frame %zu but the block holds %zu",
                             i, x->count, x->first, nwfs);
        if (!isfinite(x->w_first) || !isfinite(x->w_last))
            return swfs_fail(SWFS_ERR_VALUE, "engine: camera frame %zu has a non-finite weight", i);
    }
    if (!nexp) return SWFS_OK;
    size_t lo = SIZE_MAX, hi = 0;
    for (size_t i = 0; i < nexp; i++) {
        if (sched[i].first < lo) lo = sched[i].first;
        if (sched[i].first + sched[i].count > hi) hi = sched[i].first + sched[i].count;
    }
    size_t span_max = (hi - lo + CHUNKS_MIN - 1) / CHUNKS_MIN;
    span_max = span_max < CHUNK_MIN_FRAMES ? CHUNK_MIN_FRAMES : span_max > CHUNK_FRAMES ? CHUNK_FRAMES : span_max;
    job j = {slopes, nwfs, sched, nexp, halo_out, 0, 0, span_max};
    return run_batch(e, &j);
}

int swfs_engine_process_wfs(swfs_engine *e, const double *slopes, size_t nwfs, double complex *halo_out)
{
    if (!e || (nwfs && (!slopes || !halo_out)))
        return swfs_fail(SWFS_ERR_ARG, "engine: missing slopes or output buffer");
    if (!nwfs) return SWFS_OK;
    /* Chunk size from the batch size only: results must not depend on the thread count. */
    size_t c1 = (nwfs / 8 + BLK - 1) / BLK * BLK;
    c1 = c1 < BLK ? BLK : c1 > CHUNK_FRAMES ? CHUNK_FRAMES : c1;
    job j = {slopes, nwfs, NULL, nwfs, halo_out, 0, c1, CHUNK_FRAMES};
    return run_batch(e, &j);
}

size_t swfs_engine_schedule(double ratio, double offset, size_t nexp, swfs_exposure *sched)
{
    if (!(ratio >= SWFS_ENGINE_MIN_RATIO) || !isfinite(ratio) || !(offset >= 0.0) || !isfinite(offset)) return 0;
    size_t need = 0;
    for (size_t j = 0; j < nexp && ratio < 1.0; j++) {
        /* An exposure shorter than a WFS frame: the field interpolated linearly in time
         * between the two WFS frames whose centres (k + 1/2) bracket the exposure's centre,
         * with a total weight equal to the exposure's length, as for longer exposures. */
        const double s = offset + ((double)j + 0.5) * ratio - 0.5;
        const double k0 = s < 0.0 ? 0.0 : floor(s), a = s < 0.0 ? 0.0 : s - k0;
        swfs_exposure *x = &sched[j];
        x->first = (size_t)k0;
        x->count = 2;
        x->w_first = (1.0 - a) * ratio;
        x->w_last = a * ratio;
        if (x->first + 2 > need) need = x->first + 2;
    }
    for (size_t j = 0; j < nexp && ratio >= 1.0; j++) {
        const double t0 = offset + (double)j * ratio, t1 = t0 + ratio;
        const size_t first = (size_t)floor(t0);
        size_t last = (size_t)ceil(t1) - 1;
        if (last < first) last = first;
        swfs_exposure *x = &sched[j];
        x->first = first;
        x->count = last - first + 1;
        x->w_first = fmin((double)first + 1.0, t1) - t0;
        x->w_last = x->count == 1 ? x->w_first : t1 - (double)last;
        if (last + 1 > need) need = last + 1;
    }
    return need;
}

/* ---- stream -------------------------------------------------------------- */

static void flush_pending(swfs_engine *e)
{
    if (!e->npend) return;
    worker *w = &e->wk[0];
    reconstruct(e, w, e->pend, e->npend);
    for (size_t bo = 0; bo < e->npend; bo += BLK) {
        const size_t nb = e->npend - bo < BLK ? e->npend - bo : BLK;
        seg *sg = &w->segs[0];
        sg->b0 = 0;
        sg->b1 = nb;
        memcpy(sg->w, e->pend_w + bo, nb * sizeof(float));
        sg->re = e->run_re;
        sg->im = e->run_im;
        project_block(e, w, bo, nb, sg, 1);
    }
    e->npend = 0;
}

int swfs_engine_add_wfs(swfs_engine *e, const double *slopes, double weight)
{
    if (!isfinite(weight)) return swfs_fail(SWFS_ERR_VALUE, "engine: non-finite WFS frame weight");
    int rc = convert_slopes(e, slopes, e->pend + e->npend * e->nslopes, e->npend);
    if (rc) return rc;
    e->pend_w[e->npend++] = (float)weight;
    if (e->npend == NG) flush_pending(e);
    return SWFS_OK;
}

int swfs_engine_end_exposure(swfs_engine *e, double complex *halo_out)
{
    flush_pending(e);
    finish_exposure(e, &e->wk[0], e->run_re, e->run_im, halo_out);
    swfs_engine_reset(e);
    return SWFS_OK;
}

void swfs_engine_reset(swfs_engine *e)
{
    e->npend = 0;
    memset(e->run_re, 0, e->npin * sizeof(float));
    memset(e->run_im, 0, e->npin * sizeof(float));
}

/* ---- plans --------------------------------------------------------------- */

int swfs_engine_nthreads(const swfs_engine *e) { return e->nthreads; }
size_t swfs_engine_npin(const swfs_engine *e) { return e->npin; }

int swfs_engine_wavefront(const swfs_engine *e, const double *v, double *out)
{
    double *z = malloc(e->nact * sizeof *z);
    if (!z) return swfs_fail(SWFS_ERR_NOMEM, "engine: out of memory");
    for (size_t k = 0; k < e->nslopes; k++)
        if (!isfinite(v[k])) {
            free(z);
            return swfs_fail(SWFS_ERR_VALUE, "engine: telemetry value %zu is not finite", k);
        }
    for (size_t a = 0; a < e->nact; a++) {
        const float *w = e->wf + a * e->nslopes;
        double s = 0.0;
        for (size_t k = 0; k < e->nslopes; k++) s += (double)w[k] * v[k];
        z[a] = s;
    }
    const double m_per_rad = e->wavelen / (2.0 * M_PI);
    memset(out, 0, e->npup * e->npup * sizeof *out);
    for (size_t r = 0; r < e->npin; r++) {
        double y = 0.0;
        for (size_t k = e->rp[r]; k < e->rp[r + 1]; k++) y += (double)e->val[k] * z[e->col[k] / BLK];
        out[e->pidx[r]] = m_per_rad * y;
    }
    free(z);
    return SWFS_OK;
}

static int worker_init(const swfs_engine *e, worker *w)
{
    const size_t np2 = e->npup * e->npup;
    w->zt = swfs_calloc(e->nact * LDZ, sizeof(float));
    w->zb = swfs_calloc(e->nact * BLK, sizeof(float));
    w->y = swfs_calloc(BLK * TILE, sizeof(float));
    w->s = swfs_calloc(BLK * TILE, sizeof(float));
    w->c = swfs_calloc(BLK * TILE, sizeof(float));
    w->sblk = swfs_calloc(NG * e->nslopes, sizeof(float));
    w->fre = swfs_calloc(CHUNK_EXP * e->npin, sizeof(float));
    w->fim = swfs_calloc(CHUNK_EXP * e->npin, sizeof(float));
    w->grid = swfs_calloc(np2, sizeof(float complex));
    w->focal = swfs_calloc(e->nfx * e->nfy, sizeof(float complex));
    if (!w->zt || !w->zb || !w->y || !w->s || !w->c || !w->sblk || !w->fre || !w->fim || !w->grid || !w->focal)
        return swfs_fail(SWFS_ERR_NOMEM, "engine: out of memory for worker buffers");
    w->mft = swfs_mft_create(e->npup, e->nfx, e->nfy, e->alpha, SWFS_MFT_SINGLE);
    return w->mft ? SWFS_OK : SWFS_ERR_NOMEM;
}

static void worker_free(worker *w)
{
    swfs_free(w->zt); swfs_free(w->zb); swfs_free(w->y); swfs_free(w->s); swfs_free(w->c); swfs_free(w->sblk);
    swfs_free(w->fre); swfs_free(w->fim); swfs_free(w->grid); swfs_free(w->focal);
    swfs_mft_free(w->mft);
}

static int check_config(const swfs_engine_config *c)
{
    if (!c) return swfs_fail(SWFS_ERR_ARG, "engine: no configuration");
    if (!c->nslopes || !c->nact || !c->npup || !c->nfx || !c->nfy)
        return swfs_fail(SWFS_ERR_ARG, "engine: zero size (nslopes %zu, nact %zu, npup %zu, window %zux%zu)",
                         c->nslopes, c->nact, c->npup, c->nfx, c->nfy);
    if (!(c->alpha > 0.0) || !isfinite(c->alpha))
        return swfs_fail(SWFS_ERR_ARG, "engine: sampling alpha = %g must be positive", c->alpha);
    if (!(c->wavelen > 0.0) || !isfinite(c->wavelen))
        return swfs_fail(SWFS_ERR_ARG, "engine: wavelength %g m must be positive", c->wavelen);
    if (!c->recon || !c->interp || !c->pupil)
        return swfs_fail(SWFS_ERR_ARG, "engine: reconstructor, interpolation and pupil are required");
    if (c->interp->nrows != c->npup * c->npup || c->interp->ncols != c->nact)
        return swfs_fail(SWFS_ERR_SHAPE, "engine: interpolation matrix is %zux%zu, expected %zux%zu (pupil grid x actuators)",
                         c->interp->nrows, c->interp->ncols, c->npup * c->npup, c->nact);
    if (c->remove_tiptilt && c->nslopes % 2)
        return swfs_fail(SWFS_ERR_ARG, "engine: tip-tilt removal needs x then y slopes, got an odd count %zu",
                         c->nslopes);
    if (c->nact > UINT32_MAX / BLK || c->npup > 46340 || c->nslopes > (size_t)INT32_MAX)
        return swfs_fail(SWFS_ERR_ARG, "engine: sizes too large");
    if (c->nthreads < 0 || c->nthreads > MAX_THREADS)
        return swfs_fail(SWFS_ERR_ARG, "engine: %d threads (1..%d)", c->nthreads, MAX_THREADS);
    return SWFS_OK;
}

swfs_engine *swfs_engine_create(const swfs_engine_config *c)
{
    if (check_config(c)) return NULL;
    swfs_engine *e = calloc(1, sizeof *e);
    if (!e) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    pthread_mutex_init(&e->mu, NULL);
    pthread_cond_init(&e->cv_start, NULL);
    pthread_cond_init(&e->cv_done, NULL);
    e->nslopes = c->nslopes; e->nact = c->nact; e->npup = c->npup; e->nfx = c->nfx; e->nfy = c->nfy;
    e->alpha = c->alpha; e->wavelen = c->wavelen;
    e->remove_tiptilt = c->remove_tiptilt;
    e->nthreads = c->nthreads < 1 ? 1 : c->nthreads;

    /* Reconstructor with 2 pi / lambda folded in: phases [rad] at the actuators. */
    const double k = 2.0 * M_PI / c->wavelen;
    e->wf = swfs_malloc(c->nact * c->nslopes * sizeof(float));
    if (!e->wf) goto nomem;
    for (size_t i = 0; i < c->nact * c->nslopes; i++) {
        if (!isfinite(c->recon[i])) {
            swfs_fail(SWFS_ERR_VALUE, "engine: reconstructor element %zu is not finite", i);
            goto fail;
        }
        e->wf[i] = (float)(k * c->recon[i]);
    }

    /* Interpolation restricted to the illuminated samples. */
    const size_t np2 = c->npup * c->npup;
    size_t npin = 0, nnz = 0;
    for (size_t p = 0; p < np2; p++)
        if (c->pupil[p] > 0.0) {
            npin++;
            nnz += c->interp->row_ptr[p + 1] - c->interp->row_ptr[p];
        }
    if (!npin) {
        swfs_fail(SWFS_ERR_VALUE, "engine: the pupil has no illuminated sample");
        goto fail;
    }
    e->npin = npin;
    e->rp = swfs_malloc((npin + 1) * sizeof *e->rp);
    e->col = swfs_malloc((nnz ? nnz : 1) * sizeof *e->col);
    e->val = swfs_malloc((nnz ? nnz : 1) * sizeof *e->val);
    e->pidx = swfs_malloc(npin * sizeof *e->pidx);
    e->amp = swfs_malloc(npin * sizeof *e->amp);
    if (!e->rp || !e->col || !e->val || !e->pidx || !e->amp) goto nomem;
    size_t r = 0, q = 0;
    e->rp[0] = 0;
    for (size_t p = 0; p < np2; p++) {
        if (!(c->pupil[p] > 0.0)) continue;
        for (size_t t = c->interp->row_ptr[p]; t < c->interp->row_ptr[p + 1]; t++) {
            e->col[q] = (uint32_t)(c->interp->col[t] * BLK); /* offset of the actuator's row in zb */
            e->val[q] = (float)c->interp->val[t];
            q++;
        }
        e->pidx[r] = p;
        e->amp[r] = (float)c->pupil[p];
        e->rp[++r] = q;
    }

    e->pend = swfs_calloc(NG * c->nslopes, sizeof(float));
    e->run_re = swfs_calloc(npin, sizeof(float));
    e->run_im = swfs_calloc(npin, sizeof(float));
    e->wk = calloc((size_t)e->nthreads, sizeof *e->wk);
    if (!e->pend || !e->run_re || !e->run_im || !e->wk) goto nomem;
    for (int t = 0; t < e->nthreads; t++)
        if (worker_init(e, &e->wk[t])) goto fail;

    if (e->nthreads > 1) {
        e->th = calloc((size_t)e->nthreads - 1, sizeof *e->th);
        if (!e->th) goto nomem;
        for (int t = 0; t < e->nthreads - 1; t++) {
            if (pthread_create(&e->th[t], NULL, pool_main, e)) {
                swfs_fail(SWFS_ERR_INTERNAL, "engine: cannot start worker thread %d", t + 1);
                goto fail;
            }
            e->nth_started_ok = (size_t)t + 1;
        }
    }
    return e;
nomem:
    swfs_fail(SWFS_ERR_NOMEM, "engine: out of memory");
fail:
    swfs_engine_free(e);
    return NULL;
}

void swfs_engine_free(swfs_engine *e)
{
    if (!e) return;
    if (e->th) {
        pthread_mutex_lock(&e->mu);
        e->stop = 1;
        pthread_cond_broadcast(&e->cv_start);
        pthread_mutex_unlock(&e->mu);
        for (size_t t = 0; t < e->nth_started_ok; t++) pthread_join(e->th[t], NULL);
        free(e->th);
    }
    if (e->wk)
        for (int t = 0; t < e->nthreads; t++) worker_free(&e->wk[t]);
    free(e->wk);
    swfs_free(e->wf); swfs_free(e->rp); swfs_free(e->col); swfs_free(e->val);
    swfs_free(e->pidx); swfs_free(e->amp);
    swfs_free(e->pend); swfs_free(e->run_re); swfs_free(e->run_im);
    pthread_mutex_destroy(&e->mu);
    pthread_cond_destroy(&e->cv_start);
    pthread_cond_destroy(&e->cv_done);
    free(e);
}

/* A reconstructor learned from simulated closed loops: the least-squares map from a frame's
 * slopes to the true residual wavefront on the actuators (wfs.h swfs_recon_learner;
 * docs/telemetry.md, "A reconstructor learned from simulated closed loops"). */
#include "specklewfs/wfs.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <lapacke.h>
#include <limits.h>
#include <stdint.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Frames per block of the H update; blocks summed in single precision before they go into
 * the double sums (add_cross). */
#define LEARN_BLOCK 256
#define LEARN_FLUSH 16
#define MIN2(a, b) ((a) < (b) ? (a) : (b))

struct swfs_recon_learner {
    size_t nslopes, nact, nframes;
    int remove_mean; /* 1: z's mean over its values is piston (actuator values) and comes out */
    /* The sums hold only the inputs that ever carried signal (unilluminated subapertures'
     * slopes are exactly 0 in every frame: their rows of G and H would be 0): of the base
     * slopes (a frame's, ns0 = nslopes / nl), the nu0 in used0, at each of the nl lags; input
     * (k, used0[u]) at k nu0 + u of the sums ("compressed"). Set by the first add, grown when
     * a later one shows signal in another slope. */
    size_t ns0, nl, nu0, nc; /* nc = nu0 nl */
    size_t *used0;
    double *G;    /* nc x nc: sum of s s^T (upper triangle, row-major) */
    double *H;    /* nc x nact: sum of s z^T, z with its mean removed when remove_mean */
    double zz;    /* sum of |z|^2, mean removed */
    double *zza;  /* nact: each output's share of zz */
    float *Sf;    /* LEARN_BLOCK x nc: a block of inputs in single precision */
    float *Zf;    /* LEARN_BLOCK x nact: its truth, mean removed */
    float *Hf;    /* nc x nact: one add call's S^T Zc, summed in single precision */
    double *W0;   /* nact x nslopes or NULL: the prior map the solves shrink toward (set_prior) */
};

int swfs_recon_learner_new(size_t nslopes, size_t nact, int remove_mean, swfs_recon_learner **out)
{
    *out = NULL;
    if (!nslopes || !nact) return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: %zu slopes, %zu actuators", nslopes, nact);
    swfs_recon_learner *l = calloc(1, sizeof *l);
    if (l) {
        l->nslopes = nslopes;
        l->nact = nact;
        l->remove_mean = remove_mean != 0;
        l->Zf = malloc(LEARN_BLOCK * nact * sizeof *l->Zf);
        l->zza = calloc(nact, sizeof *l->zza);
    }
    if (!l || !l->Zf || !l->zza) {
        swfs_recon_learner_free(l);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu slopes x %zu actuators", nslopes,
                         nact);
    }
    *out = l;
    return SWFS_OK;
}

void swfs_recon_learner_free(swfs_recon_learner *l)
{
    if (!l) return;
    free(l->used0);
    free(l->G);
    free(l->H);
    free(l->Sf);
    free(l->Zf);
    free(l->Hf);
    free(l->zza);
    free(l->W0);
    free(l);
}

int swfs_recon_learner_set_prior(swfs_recon_learner *l, const swfs_recon *w0)
{
    if (!w0) {
        free(l->W0);
        l->W0 = NULL;
        return SWFS_OK;
    }
    if (w0->nact != l->nact || w0->nslopes != l->nslopes)
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: a prior map of %zu outputs x %zu inputs for sums of %zu x "
                         "%zu", w0->nact, w0->nslopes, l->nact, l->nslopes);
    const size_t na = l->nact, ns = l->nslopes;
    double *W = malloc(na * ns * sizeof *W);
    if (!W) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for the prior map");
    for (size_t k = 0; k < na * ns; k++)
        if (!isfinite(w0->W[k])) {
            char val[48];
            free(W);
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: the prior map's element (%zu, %zu) %s; expected "
                             "finite", k / ns, k % ns, swfs_value_words(w0->W[k], val, sizeof val));
        }
    memcpy(W, w0->W, na * ns * sizeof *W);
    /* the truth's piston is out of every frame (remove_mean): out of the prior's outputs too */
    for (size_t c = 0; l->remove_mean && c < ns; c++) {
        double m = 0;
        for (size_t a = 0; a < na; a++) m += W[a * ns + c];
        m /= (double)na;
        for (size_t a = 0; a < na; a++) W[a * ns + c] -= m;
    }
    free(l->W0);
    l->W0 = W;
    return SWFS_OK;
}

size_t swfs_recon_learner_frames(const swfs_recon_learner *l) { return l->nframes; }

/* Compressed input i's index in the full layout (slopes_stack's: lag-major). */
static size_t full_of(const swfs_recon_learner *l, size_t i) { return i / l->nu0 * l->ns0 + l->used0[i % l->nu0]; }

/* The sums' layout for a file of n frames of ns0 slopes at nl lags: the first call sets the
 * base shape, every call adds the slopes with signal in its file (moving the sums' entries to
 * their places among the new ones, which are 0 over the frames already added). */
static int grow(swfs_recon_learner *l, unsigned char *sig, size_t nu0, size_t ns0, size_t nl);

static int layout(swfs_recon_learner *l, const double *s, size_t n, size_t ns0, size_t nl)
{
    if (l->ns0 && (l->ns0 != ns0 || l->nl != nl))
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: %zu slopes x %zu lags after %zu x %zu", ns0, nl, l->ns0,
                         l->nl);
    unsigned char *sig = calloc(ns0, 1);
    if (!sig) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    for (size_t u = 0; u < l->nu0; u++) sig[l->used0[u]] = 1;
    size_t nu0 = l->nu0;
    for (size_t t = 0; t < n; t++) {
        const double *f = s + t * ns0;
        for (size_t c = 0; c < ns0; c++)
            if (!sig[c] && f[c] != 0) {
                sig[c] = 1;
                nu0++;
            }
    }
    return grow(l, sig, nu0, ns0, nl);
}

/* The sums grown to the nu0 base slopes marked in sig (ns0 long, a superset of l's; freed
 * here), the old entries moved to their places. */
static int grow(swfs_recon_learner *l, unsigned char *sig, size_t nu0, size_t ns0, size_t nl)
{
    if (l->ns0 && nu0 == l->nu0) {
        free(sig);
        return SWFS_OK;
    }
    const size_t nc = nu0 * nl, na = l->nact;
    size_t *used0 = malloc((nu0 ? nu0 : 1) * sizeof *used0), *to = malloc((l->nc ? l->nc : 1) * sizeof *to);
    double *G = calloc(nc * nc + 1, sizeof *G), *H = calloc(nc * na + 1, sizeof *H);
    float *Sf = malloc((LEARN_BLOCK * nc + 1) * sizeof *Sf), *Hf = malloc((nc * na + 1) * sizeof *Hf);
    if (!used0 || !to || !G || !H || !Sf || !Hf) {
        free(sig); free(used0); free(to); free(G); free(H); free(Sf); free(Hf);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu inputs x %zu outputs", nc, na);
    }
    for (size_t c = 0, u = 0; c < ns0; c++)
        if (sig[c]) used0[u++] = c;
    /* the old inputs' new places: the union is sorted, so the order (and the upper triangle) holds */
    for (size_t k = 0, o = 0; k < l->nl; k++)
        for (size_t u = 0, v = 0; u < l->nu0; u++, o++) {
            while (used0[v] != l->used0[u]) v++;
            to[o] = k * nu0 + v;
        }
    for (size_t i = 0; i < l->nc; i++) {
        for (size_t j = i; j < l->nc; j++) G[to[i] * nc + to[j]] = l->G[i * l->nc + j];
        memcpy(H + to[i] * na, l->H + i * na, na * sizeof *H);
    }
    free(sig); free(to);
    free(l->used0); free(l->G); free(l->H); free(l->Sf); free(l->Hf);
    l->used0 = used0;
    l->G = G;
    l->H = H;
    l->Sf = Sf;
    l->Hf = Hf;
    l->ns0 = ns0;
    l->nl = nl;
    l->nu0 = nu0;
    l->nc = nc;
    return SWFS_OK;
}

/* The file's used slopes (n x nu0), in *out (malloc'd). */
static int compress(const swfs_recon_learner *l, const double *s, size_t n, double **out)
{
    double *c = malloc((n * l->nu0 + 1) * sizeof *c);
    if (!c) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu frames", n);
    for (size_t t = 0; t < n; t++)
        for (size_t u = 0; u < l->nu0; u++) c[t * l->nu0 + u] = s[t * l->ns0 + l->used0[u]];
    *out = c;
    return SWFS_OK;
}

static int check_finite(const double *slopes, size_t ns, const double *truth, size_t na, size_t nframes)
{
    for (size_t k = 0; k < nframes * ns; k++)
        if (!isfinite(slopes[k]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: slope %zu of frame %zu is not finite", k % ns, k / ns);
    for (size_t k = 0; k < nframes * na; k++)
        if (!isfinite(truth[k]))
            return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: actuator %zu of frame %zu of the truth is not finite",
                             k % na, k / na);
    return SWFS_OK;
}

/* H += S^T Zc for block blk of at most LEARN_BLOCK frames (S: nb x nc, the used inputs), with
 * Zc = Z - m 1^T (m the frames' means: piston, which nothing sees; modal coefficients carry
 * none and are taken as they are), by one SGEMM into Hf, which goes into H after every
 * LEARN_FLUSH blocks and after an add call's last (last); and zz (in double). Single
 * precision: the cross product only scales the map linearly (no inverse amplifies its
 * rounding, as (G + lam)^-1 would G's, which stays double), and its relative rounding over at
 * most 4096 frames, about sqrt(4096) 2^-24 = 4e-6, is far below the statistical error of a
 * map of 10 frames per input (about 1 / sqrt(10)). SGEMM takes half DGEMM's time: the cross
 * product is the largest product of a map of many outputs (teach's grid; docs/telemetry.md). */
static void add_cross(swfs_recon_learner *l, const double *S, const double *Z, size_t nb, size_t blk, int last)
{
    const size_t ns = l->nc, na = l->nact;
    for (size_t f = 0; f < nb; f++) {
        const double *z = Z + f * na;
        float *zf = l->Zf + f * na;
        double m = 0;
        if (l->remove_mean) {
            for (size_t a = 0; a < na; a++) m += z[a];
            m /= (double)na;
        }
        for (size_t a = 0; a < na; a++) {
            const double c = z[a] - m;
            l->zz += c * c;
            l->zza[a] += c * c;
            zf[a] = (float)c;
        }
    }
    if (!ns) return; /* no slope with signal yet: the truth's power only */
    for (size_t k = 0; k < nb * ns; k++) l->Sf[k] = (float)S[k];
    cblas_sgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)ns, (int)na, (int)nb, 1.0f, l->Sf, (int)ns, l->Zf, (int)na,
                blk % LEARN_FLUSH ? 1.0f : 0.0f, l->Hf, (int)na);
    if (last || blk % LEARN_FLUSH == LEARN_FLUSH - 1)
        for (size_t i = 0; i < ns * na; i++) l->H[i] += (double)l->Hf[i];
}

int swfs_recon_learner_add(swfs_recon_learner *l, const double *slopes, const double *truth, size_t nframes)
{
    const size_t na = l->nact;
    int rc = check_finite(slopes, l->nslopes, truth, na, nframes);
    if (!rc) rc = layout(l, slopes, nframes, l->nslopes, 1);
    double *S = NULL;
    if (!rc) rc = compress(l, slopes, nframes, &S);
    if (rc) return rc;
    /* G += S^T S (one rank-k update); H block by block. */
    const size_t ns = l->nc;
    if (ns) cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)ns, (int)nframes, 1.0, S, (int)ns, 1.0, l->G, (int)ns);
    for (size_t f0 = 0; f0 < nframes; f0 += LEARN_BLOCK) {
        const size_t nb = nframes - f0 < LEARN_BLOCK ? nframes - f0 : LEARN_BLOCK;
        add_cross(l, S + f0 * ns, truth + f0 * na, nb, f0 / LEARN_BLOCK, f0 + nb == nframes);
    }
    free(S);
    l->nframes += nframes;
    return SWFS_OK;
}

/* C += alpha S[a..a+m)^T S[a+d..a+d+m) (ns0 x ns0, row-major), S: frames x ns0. */
static void lag_product(const double *S, size_t ns0, size_t a, size_t d, size_t m, double alpha, double *C)
{
    if (!m) return;
    cblas_dgemm(CblasRowMajor, CblasTrans, CblasNoTrans, (int)ns0, (int)ns0, (int)m, alpha, S + a * ns0, (int)ns0,
                S + (a + d) * ns0, (int)ns0, 1.0, C, (int)ns0);
}

int swfs_recon_learner_add_lagged(swfs_recon_learner *l, const double *sfull, size_t nsfull, const double *truth,
                                  size_t n, const long *lags, size_t nl)
{
    const size_t na = l->nact;
    if (!nl || nl > SWFS_RECON_MAXLAGS || nsfull * nl != l->nslopes)
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: %zu slopes x %zu lags, but the learner takes %zu inputs",
                         nsfull, nl, l->nslopes);
    int rc = check_finite(sfull, nsfull, truth, na, n);
    if (rc || !n) return rc;
    /* the file's used slopes: every product below over them only */
    double *s = NULL;
    if ((rc = layout(l, sfull, n, nsfull, nl)) || (rc = compress(l, sfull, n, &s))) return rc;
    const size_t ns0 = l->nu0, ns = l->nc;
    long lmin = 0, lmax = 0;
    for (size_t k = 0; k < nl; k++) {
        lmin = lags[k] < lmin ? lags[k] : lmin;
        lmax = lags[k] > lmax ? lags[k] : lmax;
    }
    /* The frames t whose every lag falls inside the file: [ta, tb]; the others are clamped. */
    const long ta = -lmin, tb = (long)n - 1 - lmax;
    const size_t nedge = ta <= tb ? n - (size_t)(tb - ta + 1) : n;
    const size_t rows = nedge > LEARN_BLOCK ? nedge : LEARN_BLOCK;
    double *X = malloc((rows * ns + 1) * sizeof *X), *Q = malloc((ns0 * ns0 + 1) * sizeof *Q),
           *T = malloc((ns0 * ns0 + 1) * sizeof *T);
    if (!X || !Q || !T) {
        free(s); free(X); free(Q); free(T);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu lags of %zu slopes", nl, ns0);
    }
    /* H and zz from the stacked input, a block at a time. */
    for (size_t f0 = 0; f0 < n; f0 += LEARN_BLOCK) {
        const size_t nb = n - f0 < LEARN_BLOCK ? n - f0 : LEARN_BLOCK;
        swfs_slopes_stack(s, n, ns0, lags, nl, f0, nb, X);
        add_cross(l, X, truth + f0 * na, nb, f0 / LEARN_BLOCK, f0 + nb == n);
    }
    /* G: block (i, j) of the inner frames is sum_t s(t + L_i) s(t + L_j)^T, a product of the
     * file with itself d = |L_j - L_i| frames apart, over a range that depends on i only by a
     * shift. One GEMM per distinct d over a reference range (the pairs' smallest leading
     * lag), and for each pair the frames its own range adds and leaves out at the ends: about
     * (distinct d) / (nl (nl + 1) / 2) of the stacked DSYRK's work. */
    if (ta <= tb && ns0) {
        const size_t m = (size_t)(tb - ta + 1);
        int done[SWFS_RECON_MAXLAGS * SWFS_RECON_MAXLAGS] = {0};
        for (size_t i = 0; i < nl; i++)
            for (size_t j = i; j < nl; j++) {
                if (done[i * nl + j]) continue;
                const long ad = labs(lags[j] - lags[i]);
                /* the pairs at this distance; a pair's range starts at its smaller lag (the
                 * leading one), the reference at the smallest of those */
                long lref = LONG_MAX;
                for (size_t i2 = 0; i2 < nl; i2++)
                    for (size_t j2 = i2; j2 < nl; j2++)
                        if (labs(lags[j2] - lags[i2]) == ad && MIN2(lags[i2], lags[j2]) < lref)
                            lref = MIN2(lags[i2], lags[j2]);
                memset(Q, 0, ns0 * ns0 * sizeof *Q);
                lag_product(s, ns0, (size_t)(ta + lref), (size_t)ad, m, 1.0, Q);
                for (size_t i2 = 0; i2 < nl; i2++)
                    for (size_t j2 = i2; j2 < nl; j2++) {
                        if (labs(lags[j2] - lags[i2]) != ad) continue;
                        done[i2 * nl + j2] = 1;
                        const size_t sh = (size_t)(MIN2(lags[i2], lags[j2]) - lref);
                        memcpy(T, Q, ns0 * ns0 * sizeof *T);
                        /* the range [ta + lead, tb + lead] = the reference's less its first
                         * sh frames, plus sh frames beyond its end */
                        lag_product(s, ns0, (size_t)(ta + lref), (size_t)ad, sh, -1.0, T);
                        lag_product(s, ns0, (size_t)(tb + lref + 1), (size_t)ad, sh, 1.0, T);
                        /* T[r][c] = sum s(u)_r s(u + ad)_c, u = t + lead: rows at the leading
                         * lag's slopes; G's block (i2, j2) has rows at lag i2's (transposed
                         * when lag j2 leads). */
                        const int flip = lags[j2] < lags[i2];
                        for (size_t r = 0; r < ns0; r++) {
                            double *g = l->G + (i2 * ns0 + r) * ns + j2 * ns0;
                            for (size_t c = i2 == j2 ? r : 0; c < ns0; c++) g[c] += flip ? T[c * ns0 + r] : T[r * ns0 + c];
                        }
                    }
            }
    }
    /* The clamped frames, stacked, by one rank-k update. */
    size_t k = 0;
    for (size_t t = 0; t < n; t++) {
        if (ta <= tb && (long)t >= ta && (long)t <= tb) continue;
        swfs_slopes_stack(s, n, ns0, lags, nl, t, 1, X + k * ns);
        k++;
    }
    if (k && ns)
        cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)ns, (int)k, 1.0, X, (int)ns, 1.0, l->G, (int)ns);
    l->nframes += n;
    free(s);
    free(X);
    free(Q);
    free(T);
    return SWFS_OK;
}

void swfs_recon_learner_reset(swfs_recon_learner *l)
{
    if (l->G) memset(l->G, 0, l->nc * l->nc * sizeof *l->G);
    if (l->H) memset(l->H, 0, l->nc * l->nact * sizeof *l->H);
    l->zz = 0;
    memset(l->zza, 0, l->nact * sizeof *l->zza);
    l->nframes = 0;
}

static int positions(const swfs_recon_learner *l, const swfs_recon_learner *m, size_t **out);

int swfs_recon_learner_merge(swfs_recon_learner *dst, const swfs_recon_learner *src)
{
    if (dst->nslopes != src->nslopes || dst->nact != src->nact || dst->remove_mean != src->remove_mean)
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: sums of %zu inputs x %zu outputs merged into %zu x %zu",
                         src->nslopes, src->nact, dst->nslopes, dst->nact);
    for (size_t a = 0; a < dst->nact; a++) dst->zza[a] += src->zza[a];
    if (!src->ns0) { /* no frames with any slope yet: the truth's power alone */
        dst->zz += src->zz;
        dst->nframes += src->nframes;
        return SWFS_OK;
    }
    if (dst->ns0 && (dst->ns0 != src->ns0 || dst->nl != src->nl))
        return swfs_fail(SWFS_ERR_SHAPE, "reconstructor learning: %zu slopes x %zu lags merged into %zu x %zu", src->ns0,
                         src->nl, dst->ns0, dst->nl);
    unsigned char *sig = calloc(src->ns0, 1);
    if (!sig) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    size_t nu0 = 0;
    for (size_t u = 0; u < dst->nu0; u++) sig[dst->used0[u]] = 1;
    for (size_t u = 0; u < src->nu0; u++) sig[src->used0[u]] = 1;
    for (size_t c = 0; c < src->ns0; c++) nu0 += sig[c];
    int rc = grow(dst, sig, nu0, src->ns0, src->nl);
    size_t *mp = NULL;
    if (!rc) rc = positions(dst, src, &mp);
    if (rc) return rc;
    /* the union is sorted, so i <= j maps to p <= q: upper triangle onto upper triangle */
    const size_t nc = dst->nc, na = dst->nact;
    for (size_t i = 0; i < nc; i++) {
        const size_t p = mp[i];
        if (p == SIZE_MAX) continue;
        for (size_t j = i; j < nc; j++)
            if (mp[j] != SIZE_MAX) dst->G[i * nc + j] += src->G[p * src->nc + mp[j]];
        for (size_t a = 0; a < na; a++) dst->H[i * na + a] += src->H[p * na + a];
    }
    dst->zz += src->zz;
    dst->nframes += src->nframes;
    free(mp);
    return SWFS_OK;
}

/* Where each of l's inputs sits among m's (SIZE_MAX: not there, so 0 in m's sums), for the
 * sums of l less m; NULL when m is NULL. m must be a part of l's frames: an input with signal
 * in m has it in l. */
static int positions(const swfs_recon_learner *l, const swfs_recon_learner *m, size_t **out)
{
    *out = NULL;
    if (!m) return SWFS_OK;
    if (m->ns0 && (m->ns0 != l->ns0 || m->nl != l->nl))
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: a held-out part of %zu slopes x %zu lags, sums of %zu x %zu",
                         m->ns0, m->nl, l->ns0, l->nl);
    size_t *pos = malloc((l->nc + 1) * sizeof *pos);
    if (!pos) return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    size_t v = 0;
    for (size_t u = 0; u < l->nu0; u++) {
        const int in = v < m->nu0 && m->used0[v] == l->used0[u];
        for (size_t k = 0; k < l->nl; k++) pos[k * l->nu0 + u] = in ? k * m->nu0 + v : SIZE_MAX;
        v += in ? 1u : 0u;
    }
    if (v != m->nu0) {
        free(pos);
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: the held-out part has signal in slopes the whole has not");
    }
    *out = pos;
    return SWFS_OK;
}

/* G's element (a, b) of the sums l less m (m NULL: none; mp: positions); upper triangle. */
static double gsum(const swfs_recon_learner *l, const swfs_recon_learner *m, const size_t *mp, size_t a, size_t b)
{
    const size_t i = a < b ? a : b, j = a < b ? b : a;
    double g = l->G[i * l->nc + j];
    if (m && mp[i] != SIZE_MAX && mp[j] != SIZE_MAX) {
        const size_t p = mp[i] < mp[j] ? mp[i] : mp[j], q = mp[i] < mp[j] ? mp[j] : mp[i];
        g -= m->G[p * m->nc + q];
    }
    return g;
}

/* The normal equations of the sums l less m solved over the inputs with signal in them:
 * A = (G + lam I)^-1 H (nu x na) in *A, those inputs (l's compressed indices) in idx (l->nc
 * long), nu of them. */
static int solve_sums(const swfs_recon_learner *l, const swfs_recon_learner *m, const size_t *mp, double ridge,
                      size_t block, size_t *idx, size_t *nu_out, double **A_out, double *lam_out)
{
    *A_out = NULL;
    const size_t ns = l->nc, na = l->nact, nf = l->nframes - (m ? m->nframes : 0);
    if (!(ridge > 0) || !isfinite(ridge))
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: the ridge must be a finite fraction > 0, got %g", ridge);
    /* The slopes seen: those with any signal over the frames (unilluminated ones are 0). */
    size_t nu = 0;
    double tr = 0;
    for (size_t i = 0; i < ns; i++) {
        if (block != SIZE_MAX && i / l->nu0 != block) continue; /* one lag block's inputs alone */
        const double d = gsum(l, m, mp, i, i);
        if (d > 1e-12 * l->G[i * ns + i] && d > 0) {
            idx[nu++] = i;
            tr += d;
        }
    }
    if (nu == 0 || nf < 2 * nu)
        return swfs_fail(SWFS_ERR_VALUE, "reconstructor learning: %zu frames for %zu slopes with signal; a map needs at "
                         "least twice as many frames as slopes (more simulated frames, or more data sets)", nf, nu);
    double *M = malloc(nu * nu * sizeof *M), *B = malloc(nu * na * sizeof *B);
    if (!M || !B) {
        free(M); free(B);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory for %zu slopes", nu);
    }
    const double lam = ridge * tr / (double)nu;
    for (size_t i = 0; i < nu; i++) {
        for (size_t j = 0; j < nu; j++) M[i * nu + j] = gsum(l, m, mp, idx[i], idx[j]);
        M[i * nu + i] += lam;
        const size_t p = m ? mp[idx[i]] : SIZE_MAX;
        for (size_t a = 0; a < na; a++)
            B[i * na + a] = l->H[idx[i] * na + a] - (p != SIZE_MAX ? m->H[p * na + a] : 0.0);
        if (l->W0) /* (G + lam I) A = H + lam A0: the ridge toward the prior map */
            for (size_t a = 0; a < na; a++) B[i * na + a] += lam * l->W0[a * l->nslopes + full_of(l, idx[i])];
    }
    lapack_int info = LAPACKE_dposv(LAPACK_ROW_MAJOR, 'U', (lapack_int)nu, (lapack_int)na, M, (lapack_int)nu, B,
                                    (lapack_int)na);
    free(M);
    if (info != 0) {
        free(B);
        return swfs_fail(SWFS_ERR_NUMERIC, "reconstructor learning: the normal equations are not positive definite "
                         "(LAPACK dposv info %d) with a ridge of %g", (int)info, ridge);
    }
    *nu_out = nu;
    *A_out = B;
    *lam_out = lam;
    return SWFS_OK;
}

/* The map of all inputs (block SIZE_MAX) or of lag block `block` alone, in the full layout of
 * those inputs (a block's map takes one frame's slopes). */
static int solve_block(const swfs_recon_learner *l, const swfs_recon_learner *m, size_t block, double ridge,
                       swfs_recon **out, swfs_recon_learn_info *info)
{
    *out = NULL;
    size_t *mp = NULL;
    int prc = positions(l, m, &mp);
    if (prc) return prc;
    const size_t ns = block == SIZE_MAX ? l->nslopes : l->ns0, na = l->nact;
    size_t *idx = malloc((l->nc + 1) * sizeof *idx), nu = 0;
    swfs_recon *r = calloc(1, sizeof *r);
    if (r) r->W = calloc(na * ns, sizeof *r->W);
    if (!idx || !r || !r->W) {
        free(idx);
        free(mp);
        swfs_recon_free(r);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    }
    double *A = NULL, lam = 0;
    int rc = solve_sums(l, m, mp, ridge, block, idx, &nu, &A, &lam);
    free(mp);
    if (rc) {
        free(idx);
        swfs_recon_free(r);
        return rc;
    }
    /* W = A^T on the seen slopes, in the full layout; the others the prior's, where one is set. */
    for (size_t c = 0; l->W0 && c < ns; c++) {
        const size_t c0 = block == SIZE_MAX ? c : block * l->ns0 + c;
        for (size_t a = 0; a < na; a++) r->W[a * ns + c] = l->W0[a * l->nslopes + c0];
    }
    for (size_t i = 0; i < nu; i++) {
        const size_t c = block == SIZE_MAX ? full_of(l, idx[i]) : l->used0[idx[i] % l->nu0];
        for (size_t a = 0; a < na; a++) r->W[a * ns + c] = A[i * na + a];
    }
    r->nact = na;
    r->nslopes = ns;
    r->nmodes = 0;
    if (info && !m) {
        /* The training misfit: sum |z - W s|^2 = zz - 2 tr(A^T H) + tr(A^T G A), and
         * (G + lam) A = H + lam A0 makes tr(A^T G A) = tr(A^T H) - lam (|A|^2 - A.A0). */
        double cross = 0, aa = 0;
        for (size_t i = 0; i < nu; i++)
            for (size_t a = 0; a < na; a++) {
                cross += A[i * na + a] * l->H[idx[i] * na + a];
                aa += A[i * na + a] * (A[i * na + a] - (l->W0 ? l->W0[a * l->nslopes + full_of(l, idx[i])] : 0.0));
            }
        info->nframes = l->nframes;
        info->nslopes_seen = nu;
        info->truth_rms = sqrt(l->zz / (double)(l->nframes * na));
        info->misfit_rms = sqrt(fmax(0.0, l->zz - cross - lam * aa) / (double)(l->nframes * na));
    }
    free(idx);
    free(A);
    *out = r;
    return SWFS_OK;
}

int swfs_recon_learner_solve(const swfs_recon_learner *l, double ridge, swfs_recon **out, swfs_recon_learn_info *info)
{
    return solve_block(l, NULL, SIZE_MAX, ridge, out, info);
}

int swfs_recon_learner_solve_without(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                                     swfs_recon **out)
{
    *out = NULL;
    if (part->nslopes != all->nslopes || part->nact != all->nact || part->nframes >= all->nframes)
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: a part of %zu frames (%zu inputs, %zu outputs) left "
                         "out of sums over %zu frames (%zu, %zu)", part->nframes, part->nslopes, part->nact,
                         all->nframes, all->nslopes, all->nact);
    return solve_block(all, part, SIZE_MAX, ridge, out, NULL);
}

int swfs_recon_learner_solve_lag(const swfs_recon_learner *l, size_t k, double ridge, swfs_recon **out,
                                 swfs_recon_learn_info *info)
{
    *out = NULL;
    if (!l->nc || k >= l->nl)
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: lag block %zu of %zu (no frames added?)", k, l->nl);
    return solve_block(l, NULL, k, ridge, out, info);
}

int swfs_recon_learner_heldout(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                               double *misfit2, double *truth2)
{
    return swfs_recon_learner_heldout_on(all, part, ridge, NULL, misfit2, truth2, NULL);
}

/* On the sums s (with ms: s's positions in all's inputs): the misfit of the map A (nu inputs
 * idx of all's, na outputs) over the outputs keep (NULL: all), as swfs_recon_learner_heldout_on
 * defines them; Gp and C: nu x nu and nu x na of scratch. */
static void misfit_on(const swfs_recon_learner *s, const size_t *ms, const size_t *idx, size_t nu, const double *A,
                      const unsigned char *keep, double *Gp, double *C, double *misfit2, double *truth2, double *scaled2)
{
    const size_t na = s->nact;
    /* On s's frames: sum |z - A^T s|^2 = zz - 2 tr(A^T H) + tr(A^T G A), its sums. */
    for (size_t i = 0; i < nu; i++)
        for (size_t j = 0; j < nu; j++) {
            const size_t p = ms[idx[i]], q = ms[idx[j]];
            Gp[i * nu + j] = p == SIZE_MAX || q == SIZE_MAX ? 0.0 : s->G[MIN2(p, q) * s->nc + (p < q ? q : p)];
        }
    cblas_dsymm(CblasRowMajor, CblasLeft, CblasUpper, (int)nu, (int)na, 1.0, Gp, (int)nu, A, (int)na, 0.0, C, (int)na);
    double cross = 0, quad = 0, zz = 0;
    size_t nk = 0;
    for (size_t a = 0; a < na; a++)
        if (!keep || keep[a]) {
            zz += s->zza[a];
            nk++;
        }
    for (size_t i = 0; i < nu; i++) {
        const size_t p = ms[idx[i]];
        for (size_t a = 0; a < na; a++) {
            if (keep && !keep[a]) continue;
            cross += p == SIZE_MAX ? 0.0 : A[i * na + a] * s->H[p * na + a];
            quad += A[i * na + a] * C[i * na + a];
        }
    }
    const double n = (double)(s->nframes * (nk ? nk : 1));
    *misfit2 = fmax(0.0, zz - 2 * cross + quad) / n;
    if (truth2) *truth2 = zz / n;
    /* scaled by the best single factor k = cross / quad: zz - cross^2 / quad */
    if (scaled2) *scaled2 = quad > 0 ? fmax(0.0, zz - cross * cross / quad) / n : zz / n;
}

int swfs_recon_learner_heldout_on(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                                  const unsigned char *keep, double *misfit2, double *truth2, double *scaled2)
{
    return swfs_recon_learner_heldout_split(all, part, NULL, 0, ridge, keep, misfit2, truth2, scaled2, NULL);
}

int swfs_recon_learner_heldout_split(const swfs_recon_learner *all, const swfs_recon_learner *part,
                                     const swfs_recon_learner *const *subs, size_t nsubs, double ridge,
                                     const unsigned char *keep, double *misfit2, double *truth2, double *scaled2,
                                     double *sub_misfit2)
{
    *misfit2 = *truth2 = NAN;
    if (scaled2) *scaled2 = NAN;
    for (size_t k = 0; k < nsubs && sub_misfit2; k++) sub_misfit2[k] = NAN;
    const size_t ns = all->nslopes, na = all->nact;
    if (part->nslopes != ns || part->nact != na || part->nframes == 0 || part->nframes >= all->nframes)
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: a held-out part of %zu frames (%zu slopes, %zu "
                         "actuators) of sums over %zu frames (%zu, %zu)", part->nframes, part->nslopes, part->nact,
                         all->nframes, ns, na);
    if (nsubs && !sub_misfit2) return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: sub-parts without their misfits' place");
    size_t held = 0;
    for (size_t k = 0; k < nsubs; k++) {
        const swfs_recon_learner *s = subs[k];
        if (!s || s->nslopes != ns || s->nact != na || s->nframes == 0)
            return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: sub-part %zu of a held-out part: %zu frames of %zu "
                             "slopes x %zu outputs, the part's %zu x %zu", k, s ? s->nframes : 0, s ? s->nslopes : 0,
                             s ? s->nact : 0, ns, na);
        held += s->nframes;
    }
    if (held > part->nframes)
        return swfs_fail(SWFS_ERR_ARG, "reconstructor learning: sub-parts of %zu frames in all of a held-out part of %zu",
                         held, part->nframes);
    size_t *mp = NULL;
    int rc = positions(all, part, &mp);
    if (rc) return rc;
    size_t *idx = malloc((all->nc + 1) * sizeof *idx), nu = 0;
    if (!idx) {
        free(mp);
        return swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    }
    double *A = NULL, lam = 0;
    rc = solve_sums(all, part, mp, ridge, SIZE_MAX, idx, &nu, &A, &lam);
    double *Gp = NULL, *C = NULL;
    if (!rc) {
        Gp = malloc(nu * nu * sizeof *Gp);
        C = malloc(nu * na * sizeof *C);
        if (!Gp || !C) rc = swfs_fail(SWFS_ERR_NOMEM, "reconstructor learning: out of memory");
    }
    if (!rc) misfit_on(part, mp, idx, nu, A, keep, Gp, C, misfit2, truth2, scaled2);
    for (size_t k = 0; !rc && k < nsubs; k++) {
        size_t *ms = NULL;
        if (!(rc = positions(all, subs[k], &ms))) misfit_on(subs[k], ms, idx, nu, A, keep, Gp, C, sub_misfit2 + k, NULL, NULL);
        free(ms);
    }
    free(mp);
    free(idx);
    free(A);
    free(Gp);
    free(C);
    return rc;
}

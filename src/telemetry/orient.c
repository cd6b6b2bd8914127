/* The camera's orientation relative to the model's focal plane (sync.h): the pairing `sync`
 * finds by correlating the star's track with the mean slopes says which camera axis follows
 * which slope axis and with which sign. The speckles are computed in the model's frame
 * (docs/conventions.md's sign and sampling); the science frames are brought into that frame, so the
 * halo, the pupil field and the DM offsets are all in the frame of the WFS and the DM.
 *
 * Model pixel (cx + u, cy + v), (cx, cy) = (nx/2, ny/2) the star, shows what the camera has
 * at (cx + a, cy + b): a = sx u, b = sy v (straight), a = sx v, b = sy u (swapped, a
 * transposed camera: square frames only). Pixels the camera did not see are NaN, which the
 * estimator skips. */
#include "specklewfs/status.h"
#include "specklewfs/sync.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int swfs_orient_is_identity(const swfs_sync_result *p)
{
    return !p->swap && p->sign_x >= 0 && p->sign_y >= 0;
}

int swfs_orient_check(const swfs_sync_result *p, size_t nx, size_t ny, const char *what)
{
    if ((p->sign_x != 1 && p->sign_x != -1) || (p->sign_y != 1 && p->sign_y != -1) || (p->swap != 0 && p->swap != 1))
        return swfs_fail(SWFS_ERR_VALUE, "%s: camera pairing swap %d, signs %d %d: expected swap 0 or 1 and signs +-1",
                         what, p->swap, p->sign_x, p->sign_y);
    if (p->swap && nx != ny)
        return swfs_fail(SWFS_ERR_SHAPE,
                         "%s: the camera is transposed relative to the model (its x follows the y slopes) but its "
                         "frames are %zux%zu; re-orienting them needs square frames (crop the science cube square)",
                         what, nx, ny);
    return SWFS_OK;
}

void swfs_orient_describe(const swfs_sync_result *p, char *buf, size_t cap)
{
    snprintf(buf, cap, "SWAP=%d SX=%+d SY=%+d", p->swap, p->sign_x, p->sign_y);
}

/* The camera pixel model pixel (i, j) takes in pairing p, -1 where the camera did not see it
 * (and for a swapped pairing of frames that are not square). */
static long orient_source(const swfs_sync_result *p, size_t nx, size_t ny, size_t i, size_t j)
{
    const long cx = (long)(nx / 2), cy = (long)(ny / 2);
    const long u = (long)i - cx, v = (long)j - cy;
    const long a = cx + p->sign_x * (p->swap ? v : u), b = cy + p->sign_y * (p->swap ? u : v);
    if ((p->swap && nx != ny) || a < 0 || b < 0 || a >= (long)nx || b >= (long)ny) return -1;
    return b * (long)nx + a;
}

void swfs_orient_frame(const swfs_sync_result *p, size_t nx, size_t ny, size_t comps, const double *cam, double *model)
{
    for (size_t j = 0; j < ny; j++)
        for (size_t i = 0; i < nx; i++) {
            const long q = orient_source(p, nx, ny, i, j);
            double *o = model + (j * nx + i) * comps;
            for (size_t c = 0; c < comps; c++) o[c] = q < 0 ? NAN : cam[(size_t)q * comps + c];
        }
}

/* ---- the orientation from the speckles (sync.h swfs_orient_acc) ---- */

struct swfs_orient_acc {
    size_t nx, ny, np, nframes;
    long *src;         /* 8 x np: the camera pixel of model pixel p in pairing k, -1 outside */
    double *sa, *saa, *sab, *sb, *sbb, *n; /* 8 x np each: camera, its square, the product; |psi|^2 and its square; count */
};

void swfs_orient_pairing(int k, swfs_sync_result *p)
{
    p->swap = k / 4;
    p->sign_x = k & 2 ? -1 : 1;
    p->sign_y = k & 1 ? -1 : 1;
}

static int pairing_index(const swfs_sync_result *p)
{
    return 4 * (p->swap ? 1 : 0) + (p->sign_x < 0 ? 2 : 0) + (p->sign_y < 0 ? 1 : 0);
}

int swfs_orient_acc_new(size_t nx, size_t ny, swfs_orient_acc **out)
{
    *out = NULL;
    if (!nx || !ny) return swfs_fail(SWFS_ERR_ARG, "orientation check: frames of %zux%zu", nx, ny);
    swfs_orient_acc *a = calloc(1, sizeof *a);
    const size_t np = nx * ny;
    if (a) {
        a->nx = nx; a->ny = ny; a->np = np;
        a->src = malloc(8 * np * sizeof *a->src);
        a->sa = calloc(8 * np, sizeof *a->sa); a->saa = calloc(8 * np, sizeof *a->saa);
        a->sab = calloc(8 * np, sizeof *a->sab); a->sb = calloc(8 * np, sizeof *a->sb);
        a->sbb = calloc(8 * np, sizeof *a->sbb); a->n = calloc(8 * np, sizeof *a->n);
    }
    if (!a || !a->src || !a->sa || !a->saa || !a->sab || !a->sb || !a->sbb || !a->n) {
        swfs_orient_acc_free(a);
        return swfs_fail(SWFS_ERR_NOMEM, "orientation check: out of memory for %zux%zu frames", nx, ny);
    }
    for (int k = 0; k < 8; k++) {
        swfs_sync_result p;
        swfs_orient_pairing(k, &p);
        for (size_t j = 0; j < ny; j++)
            for (size_t i = 0; i < nx; i++) a->src[(size_t)k * np + j * nx + i] = orient_source(&p, nx, ny, i, j);
    }
    *out = a;
    return SWFS_OK;
}

void swfs_orient_acc_free(swfs_orient_acc *a)
{
    if (!a) return;
    free(a->src); free(a->sa); free(a->saa); free(a->sab); free(a->sb); free(a->sbb); free(a->n);
    free(a);
}

void swfs_orient_acc_add(swfs_orient_acc *a, const double *cam, const double *psi2)
{
    const size_t np = a->np;
    for (size_t k = 0; k < 8; k++) {
        const long *src = a->src + k * np;
        double *sa = a->sa + k * np, *saa = a->saa + k * np, *sab = a->sab + k * np, *sb = a->sb + k * np,
               *sbb = a->sbb + k * np, *n = a->n + k * np;
        for (size_t p = 0; p < np; p++) {
            if (src[p] < 0) continue;
            const double c = cam[src[p]], b = psi2[p];
            if (!isfinite(c) || !isfinite(b)) continue;
            sa[p] += c; saa[p] += c * c; sab[p] += c * b; sb[p] += b; sbb[p] += b * b; n[p] += 1;
        }
    }
    a->nframes++;
}

/* The correlation over the frames at pixel p of pairing k; NaN where either does not vary. */
static double pixel_corr(const swfs_orient_acc *a, size_t k, size_t p)
{
    const size_t q = k * a->np + p;
    const double n = a->n[q];
    if (n < 3) return NAN;
    const double va = a->saa[q] - a->sa[q] * a->sa[q] / n, vb = a->sbb[q] - a->sb[q] * a->sb[q] / n;
    const double cab = a->sab[q] - a->sa[q] * a->sb[q] / n;
    /* a variance at the sums' rounding is none */
    if (!(va > 1e-12 * a->saa[q]) || !(vb > 1e-12 * a->sbb[q])) return NAN;
    return cab / sqrt(va * vb);
}

void swfs_orient_acc_pixel_corrs(const swfs_orient_acc *a, int k, double *c)
{
    for (size_t p = 0; p < a->np; p++) c[p] = k >= 0 && k < 8 ? pixel_corr(a, (size_t)k, p) : NAN;
}

/* The 8 pairings' correlations at pixel p; 0 unless every pairing the frames allow has one
 * (the swapped ones on frames that are not square: none, NaN). */
static int pixel_corrs(const swfs_orient_acc *a, size_t p, double c[8])
{
    for (size_t k = 0; k < 8; k++) {
        c[k] = pixel_corr(a, k, p);
        if (!isfinite(c[k]) && !(k >= 4 && a->nx != a->ny)) return 0;
    }
    return 1;
}

int swfs_orient_acc_result(const swfs_orient_acc *a, const swfs_sync_result *ref, double pix_per_speckle,
                           swfs_orient_check_result *r)
{
    memset(r, 0, sizeof *r);
    r->nframes = a->nframes;
    r->ref = pairing_index(ref);
    r->best = r->ref;
    r->diff = r->diff_se = NAN;
    for (int k = 0; k < 8; k++) r->corr[k] = NAN;
    if (a->nframes < 3)
        return swfs_fail(SWFS_ERR_VALUE, "orientation check: %zu frames; the correlations need at least 3", a->nframes);
    if (!(pix_per_speckle >= 1)) pix_per_speckle = 1;
    /* the pixels every seen pairing has a correlation at: the means compare like with like */
    size_t npix = 0;
    double sum[8] = {0};
    for (size_t p = 0; p < a->np; p++) {
        double c[8];
        if (!pixel_corrs(a, p, c)) continue;
        for (size_t k = 0; k < 8; k++) sum[k] += c[k];
        npix++;
    }
    r->npix = npix;
    if (!npix) return swfs_fail(SWFS_ERR_VALUE, "orientation check: no pixel where the camera and the speckles both vary in every pairing");
    for (int k = 0; k < 8; k++)
        if (k < 4 || a->nx == a->ny) r->corr[k] = sum[k] / (double)npix;
    for (int k = 0; k < 8; k++)
        if (r->corr[k] > r->corr[r->best]) r->best = k;
    /* the best's per-pixel excess over ref's, its mean and spread (over the same pixels) */
    double *cr = malloc(2 * a->np * sizeof *cr);
    if (!cr) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t p = 0; p < a->np; p++) {
        double c[8];
        const int ok = pixel_corrs(a, p, c);
        cr[p] = ok ? c[r->ref] : NAN;
        cr[a->np + p] = ok ? c[r->best] : NAN;
    }
    swfs_orient_corr_diff(cr, cr + a->np, a->np, pix_per_speckle, &r->diff, &r->diff_se);
    free(cr);
    return SWFS_OK;
}

size_t swfs_orient_corr_diff(const double *a, const double *b, size_t np, double pix_per_speckle, double *mean,
                             double *se)
{
    double sd = 0, sd2 = 0;
    size_t n = 0;
    for (size_t p = 0; p < np; p++) {
        if (!isfinite(a[p]) || !isfinite(b[p])) continue;
        const double d = b[p] - a[p];
        sd += d;
        sd2 += d * d;
        n++;
    }
    const double m = n ? sd / (double)n : NAN;
    const double var = n > 1 ? fmax(0.0, sd2 / (double)n - m * m) * (double)n / (double)(n - 1) : NAN;
    *mean = m;
    *se = sqrt(var / fmax(1.0, (double)n / (pix_per_speckle >= 1 ? pix_per_speckle : 1.0)));
    return n;
}

void swfs_orient_check_describe(const swfs_orient_check_result *c, char *buf, size_t cap)
{
    char tb[64], bb[64];
    swfs_sync_result pt, pb;
    swfs_orient_pairing(c->ref, &pt);
    swfs_orient_pairing(c->best, &pb);
    swfs_orient_describe(&pt, tb, sizeof tb);
    swfs_orient_describe(&pb, bb, sizeof bb);
    if (c->best == c->ref)
        snprintf(buf, cap, "the timing table's pairing (%s) follows them best, mean correlation of intensity and "
                 "|psi|^2 %.3f over %zu pixels", tb, c->corr[c->ref], c->npix);
    else
        snprintf(buf, cap, "%s %.3f, the timing table's pairing (%s) %.3f (mean correlation of intensity and |psi|^2 "
                 "over %zu pixels; %.1f standard errors apart)", bb, c->corr[c->best], tb, c->corr[c->ref], c->npix,
                 c->diff / c->diff_se);
}

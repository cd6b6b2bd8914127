/* The von Karman prior of the speckle reconstructor fitted to the telemetry by maximum
 * likelihood (wfs.h, swfs_vk_fit_slopes; docs/telemetry.md "The reconstructor's prior from
 * the data").
 *
 * Model of one frame's valid slopes with each axis' mean removed (P: that projector; the
 * mean is tip-tilt, which carries vibration rather than turbulence):
 *   P s ~ N(0, Sigma),  Sigma = P (c A + sigma^2 I) P,  A = D C_vk(L0) D^T,
 * c the prior's scale [m^2], sigma^2 the effective slope noise (white noise plus the
 * aliasing of what the DM cannot make). With B = P A P - (I - P) = U diag(l) U^T (the two
 * directions P removes get l = -1 and drop out) and s_i = u_i^T S u_i (S the slopes' sample
 * covariance), the log-likelihood per frame is
 *   -1/2 sum_i [ s_i / (c l_i + sigma^2) + ln(c l_i + sigma^2) ]   over l_i > -1/2.
 * For a ratio r = c / sigma^2 the best sigma^2 is mean_i s_i / (r l_i + 1) in closed form,
 * so the likelihood is profiled over log r (a scan, then golden section), and over log L0
 * (a scan of octaves of the actuator extent, then golden section). One eigendecomposition
 * per L0; the frames enter only through S. */
#include "specklewfs/numeric.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <cblas.h>
#include <lapacke.h>

#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef struct vkctx {
    size_t mv, n;        /* valid slopes, actuators */
    const double *xy;
    double *PD;          /* mv x n: valid rows of D, each axis' mean over the valid rows removed */
    double *S;           /* mv x mv sample covariance of the projected slopes (upper) */
    double *ex, *ey;     /* unit vectors of the two removed directions */
    double *C, *T, *B, *SU, *l, *s;
    size_t k;            /* eigenvalues kept */
} vkctx;

/* Profile log-likelihood per frame at ratio r (c = r sigma^2); *sig2 the best sigma^2. */
static double profile(const vkctx *v, double r, double *sig2)
{
    double q = 0.0, lg = 0.0;
    for (size_t i = 0; i < v->k; i++) {
        const double d = r * v->l[i] + 1.0;
        q += v->s[i] / d;
        lg += log(d);
    }
    const double s2 = q / (double)v->k;
    *sig2 = s2;
    return -0.5 * ((double)v->k + (double)v->k * log(s2) + lg);
}

/* The best log r for the current spectrum: a scan over 16 decades around the scale where
 * signal and noise are comparable, then golden section. */
static double best_ratio(const vkctx *v, double *r_out, double *sig2)
{
    double lmax = 0.0, stot = 0.0;
    for (size_t i = 0; i < v->k; i++) { lmax = fmax(lmax, v->l[i]); stot += v->s[i]; }
    if (!(lmax > 0.0) || !(stot > 0.0)) { *r_out = 0.0; return profile(v, 0.0, sig2); }
    const double c0 = log(1.0 / lmax);
    double best = -INFINITY, bu = c0;
    for (int j = -40; j <= 120; j++) {
        const double u = c0 + 0.25 * j, f = profile(v, exp(u), sig2);
        if (f > best) { best = f; bu = u; }
    }
    double a = bu - 0.25, b = bu + 0.25;
    const double g = 0.5 * (sqrt(5.0) - 1.0);
    double x1 = b - g * (b - a), x2 = a + g * (b - a);
    double f1 = profile(v, exp(x1), sig2), f2 = profile(v, exp(x2), sig2);
    for (int it = 0; it < 40; it++) {
        if (f1 > f2) { b = x2; x2 = x1; f2 = f1; x1 = b - g * (b - a); f1 = profile(v, exp(x1), sig2); }
        else { a = x1; x1 = x2; f1 = f2; x2 = a + g * (b - a); f2 = profile(v, exp(x2), sig2); }
    }
    *r_out = exp(0.5 * (a + b));
    return profile(v, *r_out, sig2);
}

/* Log-likelihood per frame at outer scale L0, maximized over c and sigma^2. */
static int at_l0(vkctx *v, double L0, double *ll, double *c, double *sig2)
{
    const size_t mv = v->mv, n = v->n;
    int rc = swfs_vk_covariance(v->xy, n, L0, v->C);
    if (rc) return rc;
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)mv, (int)n, (int)n, 1.0, v->PD, (int)n, v->C, (int)n,
                0.0, v->T, (int)n);
    cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasTrans, (int)mv, (int)mv, (int)n, 1.0, v->T, (int)n, v->PD, (int)n,
                0.0, v->B, (int)mv);
    for (size_t i = 0; i < mv; i++)
        for (size_t j = 0; j < mv; j++) v->B[i * mv + j] -= v->ex[i] * v->ex[j] + v->ey[i] * v->ey[j];
    double *w = malloc(mv * sizeof *w);
    if (!w) return swfs_fail(SWFS_ERR_NOMEM, "vk prior fit: out of memory");
    if (LAPACKE_dsyevd(LAPACK_ROW_MAJOR, 'V', 'U', (lapack_int)mv, v->B, (lapack_int)mv, w) != 0) {
        free(w);
        return swfs_fail(SWFS_ERR_NUMERIC, "vk prior fit: eigendecomposition failed at L0 = %g m", L0);
    }
    cblas_dsymm(CblasRowMajor, CblasLeft, CblasUpper, (int)mv, (int)mv, 1.0, v->S, (int)mv, v->B, (int)mv, 0.0, v->SU,
                (int)mv);
    v->k = 0;
    for (size_t i = 0; i < mv; i++) {
        if (w[i] < -0.5) continue; /* the two directions P removes */
        double si = 0.0;
        for (size_t q = 0; q < mv; q++) si += v->B[q * mv + i] * v->SU[q * mv + i];
        v->l[v->k] = w[i] > 0.0 ? w[i] : 0.0;
        v->s[v->k] = si > 0.0 ? si : 0.0;
        v->k++;
    }
    free(w);
    double r;
    *ll = best_ratio(v, &r, sig2);
    *c = r * *sig2;
    return SWFS_OK;
}

/* Valid rows, the projected D and the slopes' sample covariance. */
static int setup(vkctx *v, const double *D, size_t m, size_t n, const double *slopes, size_t nframes)
{
    const size_t nsa = m / 2;
    size_t *row = malloc(m * sizeof *row), nv[2] = {0, 0};
    if (!row) return swfs_fail(SWFS_ERR_NOMEM, "vk prior fit: out of memory");
    size_t mv = 0;
    for (size_t i = 0; i < m; i++) {
        int nz = 0;
        for (size_t j = 0; j < n && !nz; j++) nz = D[i * n + j] != 0.0;
        if (nz) { row[mv++] = i; nv[i / nsa]++; }
    }
    if (nv[0] < 2 || nv[1] < 2) { free(row); return swfs_fail(SWFS_ERR_ARG, "vk prior fit: fewer than 2 valid x or y slopes"); }
    v->mv = mv;
    v->n = n;
    v->PD = malloc(mv * n * sizeof *v->PD);
    v->S = calloc(mv * mv, sizeof *v->S);
    v->ex = calloc(mv, sizeof *v->ex);
    v->ey = calloc(mv, sizeof *v->ey);
    v->C = malloc(n * n * sizeof *v->C);
    v->T = malloc(mv * n * sizeof *v->T);
    v->B = malloc(mv * mv * sizeof *v->B);
    v->SU = malloc(mv * mv * sizeof *v->SU);
    v->l = malloc(mv * sizeof *v->l);
    v->s = malloc(mv * sizeof *v->s);
    const size_t blk = 256;
    double *Y = malloc(blk * mv * sizeof *Y);
    int rc = SWFS_OK;
    if (!v->PD || !v->S || !v->ex || !v->ey || !v->C || !v->T || !v->B || !v->SU || !v->l || !v->s || !Y) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "vk prior fit: out of memory for %zu slopes x %zu actuators", mv, n);
        goto done;
    }
    for (size_t q = 0; q < mv; q++) {
        if (row[q] < nsa) v->ex[q] = 1.0 / sqrt((double)nv[0]);
        else v->ey[q] = 1.0 / sqrt((double)nv[1]);
    }
    /* PD = P D on the valid rows */
    for (size_t q = 0; q < mv; q++) memcpy(v->PD + q * n, D + row[q] * n, n * sizeof *D);
    for (size_t j = 0; j < n; j++) {
        double mx = 0.0, my = 0.0;
        for (size_t q = 0; q < mv; q++) *(row[q] < nsa ? &mx : &my) += v->PD[q * n + j];
        mx /= (double)nv[0];
        my /= (double)nv[1];
        for (size_t q = 0; q < mv; q++) v->PD[q * n + j] -= row[q] < nsa ? mx : my;
    }
    /* S = (1/N) sum_t (P s_t)(P s_t)^T, blocks of frames through DSYRK */
    for (size_t t0 = 0; t0 < nframes; t0 += blk) {
        const size_t nb = nframes - t0 < blk ? nframes - t0 : blk;
        for (size_t b = 0; b < nb; b++) {
            const double *s = slopes + (t0 + b) * m;
            double mx = 0.0, my = 0.0;
            for (size_t q = 0; q < mv; q++) *(row[q] < nsa ? &mx : &my) += s[row[q]];
            mx /= (double)nv[0];
            my /= (double)nv[1];
            for (size_t q = 0; q < mv; q++) Y[b * mv + q] = s[row[q]] - (row[q] < nsa ? mx : my);
        }
        cblas_dsyrk(CblasRowMajor, CblasUpper, CblasTrans, (int)mv, (int)nb, 1.0 / (double)nframes, Y, (int)mv, 1.0,
                    v->S, (int)mv);
    }
done:
    free(Y);
    free(row);
    return rc;
}

static void vk_free(vkctx *v)
{
    free(v->PD); free(v->S); free(v->ex); free(v->ey); free(v->C); free(v->T); free(v->B); free(v->SU);
    free(v->l); free(v->s);
}

int swfs_vk_fit_slopes(const double *D, size_t nslopes, size_t nact, const double *xy, const double *slopes,
                       size_t nframes, swfs_vk_fit *out)
{
    memset(out, 0, sizeof *out);
    if (nslopes == 0 || nact == 0 || nslopes % 2)
        return swfs_fail(SWFS_ERR_ARG, "vk prior fit: %zu slopes x %zu actuators", nslopes, nact);
    if (nframes < 8) return swfs_fail(SWFS_ERR_ARG, "vk prior fit: %zu frames, expected at least 8", nframes);
    /* The scale of the layout: the largest actuator separation (about D). */
    double ext = 0.0;
    for (size_t a = 0; a < nact; a++)
        for (size_t b = a + 1; b < nact; b++)
            ext = fmax(ext, hypot(xy[2 * a] - xy[2 * b], xy[2 * a + 1] - xy[2 * b + 1]));
    if (!(ext > 0.0)) return swfs_fail(SWFS_ERR_ARG, "vk prior fit: the actuators all sit at one point");
    vkctx v;
    memset(&v, 0, sizeof v);
    v.xy = xy;
    int rc = setup(&v, D, nslopes, nact, slopes, nframes);
    /* Octaves of the extent from 1/8 to 32, then golden section on log L0 around the best. */
    enum { NG = 9 };
    double ll[NG], cc[NG], ss[NG];
    size_t kb = 0;
    for (size_t k = 0; k < NG && !rc; k++) {
        rc = at_l0(&v, ext * ldexp(1.0, (int)k - 3), &ll[k], &cc[k], &ss[k]);
        if (!rc && ll[k] > ll[kb]) kb = k;
    }
    if (!rc) {
        double a = log(ext) + ((double)kb - 4.0) * M_LN2, b = log(ext) + ((double)kb - 2.0) * M_LN2;
        if (kb == 0) a = log(ext) - 3.0 * M_LN2;
        if (kb == NG - 1) b = log(ext) + 5.0 * M_LN2;
        double bestl = ll[kb], bestL0 = ext * ldexp(1.0, (int)kb - 3), bestc = cc[kb], bests = ss[kb];
        const double g = 0.5 * (sqrt(5.0) - 1.0);
        double x[2] = {b - g * (b - a), a + g * (b - a)}, f[2], c1, s1;
        for (int e = 0; e < 2 && !rc; e++) {
            rc = at_l0(&v, exp(x[e]), &f[e], &c1, &s1);
            if (!rc && f[e] > bestl) { bestl = f[e]; bestL0 = exp(x[e]); bestc = c1; bests = s1; }
        }
        for (int it = 0; it < 5 && !rc; it++) {
            int e;
            if (f[0] > f[1]) { b = x[1]; x[1] = x[0]; f[1] = f[0]; x[0] = b - g * (b - a); e = 0; }
            else { a = x[0]; x[0] = x[1]; f[0] = f[1]; x[1] = a + g * (b - a); e = 1; }
            rc = at_l0(&v, exp(x[e]), &f[e], &c1, &s1);
            if (!rc && f[e] > bestl) { bestl = f[e]; bestL0 = exp(x[e]); bestc = c1; bests = s1; }
        }
        out->L0 = bestL0;
        out->scale = bestc;
        out->noise_var = bests;
        out->loglik = bestl;
        out->nvalid = v.mv;
    }
    vk_free(&v);
    return rc;
}

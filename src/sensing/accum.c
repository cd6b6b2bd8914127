/* Welford / Chan co-moment accumulators: see include/specklewfs/accum.h. */
#include "specklewfs/accum.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

swfs_accum *swfs_accum_create(size_t nx, size_t ny)
{
    if (!nx || !ny || nx > 65536 || ny > 65536) { /* (nx ny times 15 fields must not wrap) */
        swfs_fail(SWFS_ERR_ARG, "accumulator of size %zux%zu: expected 1 to 65536 pixels a side", nx, ny);
        return NULL;
    }
    swfs_accum *a = calloc(1, sizeof *a);
    if (!a) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    a->nx = nx;
    a->ny = ny;
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) {
        a->f[k] = swfs_calloc(nx * ny, sizeof(double));
        if (!a->f[k]) { swfs_accum_free(a); return NULL; }
    }
    if (!(a->reg = swfs_regress_create(nx, ny))) { swfs_accum_free(a); return NULL; }
    return a;
}

void swfs_accum_free(swfs_accum *a)
{
    if (!a) return;
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) swfs_free(a->f[k]);
    swfs_regress_free(a->reg);
    free(a);
}

void swfs_accum_reset(swfs_accum *a)
{
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) memset(a->f[k], 0, a->nx * a->ny * sizeof(double));
    a->frames = a->skipped = 0;
    swfs_regress_reset(a->reg);
}

int swfs_accum_add(swfs_accum *a, const double *Iv, const double complex *psi)
{
    const size_t np = a->nx * a->ny;
    double *restrict n = a->f[SWFS_ACC_N];
    double *restrict mI = a->f[SWFS_ACC_MI], *restrict mX = a->f[SWFS_ACC_MX];
    double *restrict mY = a->f[SWFS_ACC_MY], *restrict mA = a->f[SWFS_ACC_MA];
    double *restrict cII = a->f[SWFS_ACC_CII], *restrict cIX = a->f[SWFS_ACC_CIX];
    double *restrict cIY = a->f[SWFS_ACC_CIY], *restrict cIA = a->f[SWFS_ACC_CIA];
    double *restrict cXX = a->f[SWFS_ACC_CXX], *restrict cXY = a->f[SWFS_ACC_CXY];
    double *restrict cXA = a->f[SWFS_ACC_CXA], *restrict cYY = a->f[SWFS_ACC_CYY];
    double *restrict cYA = a->f[SWFS_ACC_CYA], *restrict cAA = a->f[SWFS_ACC_CAA];
    const double *ps = (const double *)psi;
    uint64_t skipped = 0;

    for (size_t p = 0; p < np; p++) {
        const double x = ps[2 * p], y = ps[2 * p + 1];
        if (!isfinite(x) || !isfinite(y))
            return swfs_fail(SWFS_ERR_VALUE, "speckle value at pixel (%zu, %zu) of frame %llu is not finite",
                             p % a->nx, p / a->nx, (unsigned long long)a->frames);
    }
    for (size_t p = 0; p < np; p++) {
        const double Ip = Iv[p];
        if (!isfinite(Ip)) { skipped++; continue; }
        const double x = ps[2 * p], y = ps[2 * p + 1], A = x * x + y * y;
        const double nn = n[p] + 1.0, r = 1.0 / nn;
        /* d = v - old mean; e = v - new mean; C += d e^T (symmetric by construction). */
        const double dI = Ip - mI[p], dX = x - mX[p], dY = y - mY[p], dA = A - mA[p];
        mI[p] += dI * r; mX[p] += dX * r; mY[p] += dY * r; mA[p] += dA * r;
        const double eI = Ip - mI[p], eX = x - mX[p], eY = y - mY[p], eA = A - mA[p];
        n[p] = nn;
        cII[p] += dI * eI; cIX[p] += dI * eX; cIY[p] += dI * eY; cIA[p] += dI * eA;
        cXX[p] += dX * eX; cXY[p] += dX * eY; cXA[p] += dX * eA;
        cYY[p] += dY * eY; cYA[p] += dY * eA; cAA[p] += dA * eA;
    }
    a->frames++;
    a->skipped += skipped;
    /* The regression statistics of the same frame (psi already checked finite). */
    return swfs_regress_add(a->reg, Iv, ps, NULL);
}

int swfs_accum_merge(swfs_accum *dst, const swfs_accum *src)
{
    if (dst->nx != src->nx || dst->ny != src->ny)
        return swfs_fail(SWFS_ERR_SHAPE, "cannot merge accumulators of %zux%zu and %zux%zu pixels", dst->nx,
                         dst->ny, src->nx, src->ny);
    static const int mean_of[4] = {SWFS_ACC_MI, SWFS_ACC_MX, SWFS_ACC_MY, SWFS_ACC_MA};
    static const int cov[10][3] = {
        {SWFS_ACC_CII, 0, 0}, {SWFS_ACC_CIX, 0, 1}, {SWFS_ACC_CIY, 0, 2}, {SWFS_ACC_CIA, 0, 3},
        {SWFS_ACC_CXX, 1, 1}, {SWFS_ACC_CXY, 1, 2}, {SWFS_ACC_CXA, 1, 3},
        {SWFS_ACC_CYY, 2, 2}, {SWFS_ACC_CYA, 2, 3}, {SWFS_ACC_CAA, 3, 3},
    };
    const size_t np = dst->nx * dst->ny;
    for (size_t p = 0; p < np; p++) {
        const double na = dst->f[SWFS_ACC_N][p], nb = src->f[SWFS_ACC_N][p];
        if (nb == 0.0) continue;
        const double n = na + nb;
        double d[4];
        for (int k = 0; k < 4; k++) d[k] = src->f[mean_of[k]][p] - dst->f[mean_of[k]][p];
        const double w = na * nb / n;
        for (int k = 0; k < 10; k++)
            dst->f[cov[k][0]][p] += src->f[cov[k][0]][p] + d[cov[k][1]] * d[cov[k][2]] * w;
        for (int k = 0; k < 4; k++) dst->f[mean_of[k]][p] += d[k] * (nb / n);
        dst->f[SWFS_ACC_N][p] = n;
    }
    dst->frames += src->frames;
    dst->skipped += src->skipped;
    return swfs_regress_merge(dst->reg, src->reg);
}

int swfs_accum_has_regress(const swfs_accum *a)
{
    return a && a->reg && a->reg->frames == a->frames;
}

size_t swfs_accum_state_len(size_t nx, size_t ny)
{
    return (size_t)(SWFS_ACC_NFIELDS + SWFS_REGRESS_NSTATE) * nx * ny + 4;
}

void swfs_accum_export(const swfs_accum *a, double *state)
{
    const size_t np = a->nx * a->ny;
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) memcpy(state + (size_t)k * np, a->f[k], np * sizeof *state);
    double *tail = state + (size_t)SWFS_ACC_NFIELDS * np;
    swfs_regress_export(a->reg, tail);
    tail += (size_t)SWFS_REGRESS_NSTATE * np;
    tail[0] = (double)a->frames;
    tail[1] = (double)a->skipped;
    tail[2] = (double)a->reg->frames;
    tail[3] = (double)a->reg->skipped;
}

/* A count carried as a double: whole, >= 0, exact. */
static int state_count(double v, const char *what, uint64_t *out)
{
    if (!(v >= 0) || v != floor(v) || v > 9007199254740992.0)
        return swfs_fail(SWFS_ERR_VALUE, "accumulator state: %s = %g is not a count", what, v);
    *out = (uint64_t)v;
    return SWFS_OK;
}

int swfs_accum_import(swfs_accum *a, const double *state)
{
    const size_t np = a->nx * a->ny;
    const double *tail = state + (size_t)(SWFS_ACC_NFIELDS + SWFS_REGRESS_NSTATE) * np;
    uint64_t fr = 0, sk = 0, rfr = 0, rsk = 0;
    int rc = state_count(tail[0], "frames", &fr);
    if (!rc) rc = state_count(tail[1], "skipped", &sk);
    if (!rc) rc = state_count(tail[2], "regression frames", &rfr);
    if (!rc) rc = state_count(tail[3], "regression skipped", &rsk);
    if (rc) return rc;
    static const int diag[4] = {SWFS_ACC_CII, SWFS_ACC_CXX, SWFS_ACC_CYY, SWFS_ACC_CAA};
    for (size_t p = 0; p < np; p++) {
        const double n = state[p];
        if (!(n >= 0) || n != floor(n) || n > (double)fr)
            return swfs_fail(SWFS_ERR_VALUE, "accumulator state: pixel (%zu, %zu) has count %g with %llu frames",
                             p % a->nx, p / a->nx, n, (unsigned long long)fr);
        for (int k = 1; k < SWFS_ACC_NFIELDS; k++)
            if (!isfinite(state[(size_t)k * np + p]))
                return swfs_fail(SWFS_ERR_VALUE, "accumulator state: plane %d of pixel (%zu, %zu) is not finite", k,
                                 p % a->nx, p / a->nx);
        for (int k = 0; k < 4; k++)
            if (state[(size_t)diag[k] * np + p] < 0)
                return swfs_fail(SWFS_ERR_VALUE, "accumulator state: negative variance in plane %d at pixel (%zu, %zu)",
                                 diag[k], p % a->nx, p / a->nx);
    }
    if ((rc = swfs_regress_import(a->reg, state + (size_t)SWFS_ACC_NFIELDS * np))) return rc;
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) memcpy(a->f[k], state + (size_t)k * np, np * sizeof *state);
    a->frames = fr;
    a->skipped = sk;
    a->reg->frames = rfr;
    a->reg->skipped = rsk;
    return SWFS_OK;
}

/* A non-owning accumulator over a flat state (the layout of swfs_accum_export). */
static void state_view(double *state, size_t nx, size_t ny, swfs_accum *a, swfs_regress *r)
{
    const size_t np = nx * ny;
    memset(a, 0, sizeof *a);
    memset(r, 0, sizeof *r);
    a->nx = r->nx = nx;
    a->ny = r->ny = ny;
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) a->f[k] = state + (size_t)k * np;
    r->state = state + (size_t)SWFS_ACC_NFIELDS * np;
    const double *tail = r->state + (size_t)SWFS_REGRESS_NSTATE * np;
    a->frames = (uint64_t)tail[0];
    a->skipped = (uint64_t)tail[1];
    r->frames = (uint64_t)tail[2];
    r->skipped = (uint64_t)tail[3];
    a->reg = r;
}

int swfs_accum_merge_state(double *dst_state, const double *src_state, size_t nx, size_t ny)
{
    swfs_accum da, sa;
    swfs_regress dr, sr;
    state_view(dst_state, nx, ny, &da, &dr);
    state_view((double *)src_state, nx, ny, &sa, &sr);
    int rc = swfs_accum_merge(&da, &sa);
    if (rc) return rc;
    double *tail = dst_state + (size_t)(SWFS_ACC_NFIELDS + SWFS_REGRESS_NSTATE) * nx * ny;
    tail[0] = (double)da.frames;
    tail[1] = (double)da.skipped;
    tail[2] = (double)dr.frames;
    tail[3] = (double)dr.skipped;
    return SWFS_OK;
}

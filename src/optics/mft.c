/* Matrix Fourier transform by two GEMMs: see include/specklewfs/mft.h. */
#include "specklewfs/mft.h"
#include "specklewfs/array.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <math.h>
#include <stdlib.h>

struct swfs_mft {
    size_t np, nfx, nfy;
    int single;
    /* Row-major matrices: ax is nfx x np, ay is nfy x np (forward, exp(-...)). */
    double complex *ax, *ay, *work;      /* double plans; work: np x nfx */
    float complex *axf, *ayf, *workf;    /* single plans */
    float complex *inf, *outf;           /* single plans: conversion buffers */
};

static void fill_matrix(double complex *a, size_t nf, size_t np, double alpha)
{
    const double cf = (double)(nf / 2), cp = 0.5 * (double)(np - 1);
    for (size_t i = 0; i < nf; i++)
        for (size_t p = 0; p < np; p++) {
            double ph = -2.0 * M_PI * alpha * ((double)i - cf) * ((double)p - cp);
            a[i * np + p] = cos(ph) + I * sin(ph);
        }
}

swfs_mft *swfs_mft_create(size_t npup, size_t nfx, size_t nfy, double alpha, int precision)
{
    if (!npup || !nfx || !nfy || !(alpha > 0)) {
        swfs_fail(SWFS_ERR_ARG, "MFT: invalid sizes %zu -> %zux%zu or sampling alpha=%g", npup, nfx, nfy, alpha);
        return NULL;
    }
    swfs_mft *m = calloc(1, sizeof *m);
    if (!m) { swfs_fail(SWFS_ERR_NOMEM, "out of memory"); return NULL; }
    m->np = npup; m->nfx = nfx; m->nfy = nfy;
    m->single = precision == SWFS_MFT_SINGLE;
    m->ax = swfs_malloc(nfx * npup * sizeof(double complex));
    m->ay = swfs_malloc(nfy * npup * sizeof(double complex));
    m->work = swfs_malloc(npup * (nfx > nfy ? nfx : nfy) * sizeof(double complex));
    if (!m->ax || !m->ay || !m->work) { swfs_mft_free(m); return NULL; }
    fill_matrix(m->ax, nfx, npup, alpha);
    fill_matrix(m->ay, nfy, npup, alpha);
    if (m->single) {
        m->axf = swfs_malloc(nfx * npup * sizeof(float complex));
        m->ayf = swfs_malloc(nfy * npup * sizeof(float complex));
        m->workf = swfs_malloc(npup * (nfx > nfy ? nfx : nfy) * sizeof(float complex));
        m->inf = swfs_malloc(npup * npup * sizeof(float complex));
        m->outf = swfs_malloc(nfx * nfy * sizeof(float complex));
        if (!m->axf || !m->ayf || !m->workf || !m->inf || !m->outf) { swfs_mft_free(m); return NULL; }
        for (size_t k = 0; k < nfx * npup; k++) m->axf[k] = (float complex)m->ax[k];
        for (size_t k = 0; k < nfy * npup; k++) m->ayf[k] = (float complex)m->ay[k];
    }
    return m;
}

void swfs_mft_free(swfs_mft *m)
{
    if (!m) return;
    swfs_free(m->ax); swfs_free(m->ay); swfs_free(m->work);
    swfs_free(m->axf); swfs_free(m->ayf); swfs_free(m->workf);
    swfs_free(m->inf); swfs_free(m->outf);
    free(m);
}

size_t swfs_mft_npup(const swfs_mft *m) { return m->np; }
size_t swfs_mft_nfx(const swfs_mft *m) { return m->nfx; }
size_t swfs_mft_nfy(const swfs_mft *m) { return m->nfy; }

int swfs_mft_forward_f(swfs_mft *m, const float complex *pupil, float complex *focal)
{
    if (!m->single) return swfs_fail(SWFS_ERR_ARG, "MFT: single-precision call on a double plan");
    const int np = (int)m->np, nfx = (int)m->nfx, nfy = (int)m->nfy;
    const float complex one = 1.0f, zero = 0.0f;
    /* work (np x nfx) = pupil (np x np, row q, column p) * ax^T (np x nfx) */
    cblas_cgemm(CblasRowMajor, CblasNoTrans, CblasTrans, np, nfx, np, &one, pupil, np, m->axf, np, &zero,
                m->workf, nfx);
    /* focal (nfy x nfx) = ay (nfy x np) * work (np x nfx) */
    cblas_cgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, nfy, nfx, np, &one, m->ayf, np, m->workf, nfx,
                &zero, focal, nfx);
    return SWFS_OK;
}

int swfs_mft_forward(swfs_mft *m, const double complex *pupil, double complex *focal)
{
    if (m->single) {
        for (size_t k = 0; k < m->np * m->np; k++) m->inf[k] = (float complex)pupil[k];
        swfs_mft_forward_f(m, m->inf, m->outf);
        for (size_t k = 0; k < m->nfx * m->nfy; k++) focal[k] = m->outf[k];
        return SWFS_OK;
    }
    const int np = (int)m->np, nfx = (int)m->nfx, nfy = (int)m->nfy;
    const double complex one = 1.0, zero = 0.0;
    cblas_zgemm(CblasRowMajor, CblasNoTrans, CblasTrans, np, nfx, np, &one, pupil, np, m->ax, np, &zero,
                m->work, nfx);
    cblas_zgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, nfy, nfx, np, &one, m->ay, np, m->work, nfx, &zero,
                focal, nfx);
    return SWFS_OK;
}

int swfs_mft_inverse(swfs_mft *m, const double complex *focal, double complex *pupil)
{
    /* With A = exp(-) matrices: pupil = conj( ay^T * conj(focal) * ax ). Always in double:
     * the inverse runs once per product, not per frame. */
    const int np = (int)m->np, nfx = (int)m->nfx, nfy = (int)m->nfy;
    const double complex one = 1.0, zero = 0.0;
    double complex *cf = swfs_malloc((size_t)nfx * (size_t)nfy * sizeof *cf);
    if (!cf) return SWFS_ERR_NOMEM;
    for (int k = 0; k < nfx * nfy; k++) cf[k] = conj(focal[k]);
    /* work (nfy x np) = conj(focal) (nfy x nfx) * ax (nfx x np) */
    cblas_zgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, nfy, np, nfx, &one, cf, nfx, m->ax, np, &zero,
                m->work, np);
    /* pupil (np x np) = ay^T (np x nfy) * work (nfy x np) */
    cblas_zgemm(CblasRowMajor, CblasTrans, CblasNoTrans, np, np, nfy, &one, m->ay, np, m->work, np, &zero,
                pupil, np);
    for (int k = 0; k < np * np; k++) pupil[k] = conj(pupil[k]);
    swfs_free(cf);
    return SWFS_OK;
}

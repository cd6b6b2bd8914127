/* The paper's Sec. 3 simulation: see include/specklewfs/sim.h and docs/simulation.md.
 *
 * Flow: NCP map and pupil -> AO model solves the kernel width (Parseval, no FFT) -> for
 * each pair of screens: draw a von Karman spectrum, multiply by the residual filter
 * 1 - G exp(-2 pi i f.s), one complex FFT gives two residual screens -> workers cut the
 * pupil sub-grids and, per frame, form P e^{i phi} and P e^{i (phi + ncp)}, two
 * single-precision MFTs, the peak-phase reference, science counts and the referenced
 * no-NCP field -> serial reductions (speckle mean, true halo) in frame order, so the
 * result does not depend on the number of threads. */
#include "sim_internal.h"
#include "specklewfs/aperture.h"
#include "specklewfs/fits.h"
#include "specklewfs/kernels.h"
#include "specklewfs/mft.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <cblas.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

int swfs_sim_pupil(const swfs_sim_params *p, double *mask)
{
    const size_t np = (size_t)p->pupn;
    if (!p->pupil_mask[0]) return swfs_aperture_make(mask, np, p->pupdx, p->teldiam, p->obscur, p->nspiders, p->spider_width);
    swfs_real *m = NULL;
    int rc = swfs_pupil_mask_read(p->pupil_mask, np, &m);
    if (rc) return swfs_fail_context(rc, "pupil mask");
    /* The Shack-Hartmann's subapertures, the DM and the focal scale (lambda/D) all span teldiam:
     * light beyond it would fall outside every subaperture. */
    const double c = 0.5 * (double)(np - 1), rmax = 0.5 * p->teldiam + 0.5 * p->pupdx;
    for (size_t q = 0; !rc && q < np * np; q++) {
        const double r = hypot((double)(q % np) - c, (double)(q / np) - c) * p->pupdx;
        if (m->data[q] > 0 && r > rmax)
            rc = swfs_fail(SWFS_ERR_VALUE, "%s: pupil mask transmits %g at sample (%zu, %zu), %g m from the centre; the "
                           "telescope (teldiam = %g m) reaches %g m", p->pupil_mask, m->data[q], q % np, q / np, r,
                           p->teldiam, 0.5 * p->teldiam);
    }
    if (!rc) memcpy(mask, m->data, np * np * sizeof *mask);
    swfs_real_free(m);
    return rc;
}

int swfs_sim_ncp_map(const swfs_sim_params *p, const double *mask, double *ncp, double *rms, double *pv)
{
    const size_t np = (size_t)p->pupn;
    const double c = 0.5 * (double)(np - 1), dx = p->pupdx, rad = 0.5 * p->teldiam;
    swfs_real *map = NULL;
    if (p->ncp_map[0]) {
        int rc = swfs_fits_read_real(p->ncp_map, NULL, &map, NULL);
        if (rc) return swfs_fail_context(rc, "NCP map");
        if (map->nx != np || map->ny != np || map->nz != 1) {
            swfs_fail(SWFS_ERR_SHAPE, "%s: NCP map is %zux%zux%zu but the pupil grid is %zux%zu", p->ncp_map, map->nx,
                      map->ny, map->nz, np, np);
            swfs_real_free(map);
            return SWFS_ERR_SHAPE;
        }
    }
    double s = 0.0, s1 = 0.0;
    for (size_t q = 0; q < np; q++) {
        const double y = ((double)q - c) * dx;
        for (size_t pp = 0; pp < np; pp++) {
            const double x = ((double)pp - c) * dx, rho = hypot(x, y) / rad, th = atan2(y, x);
            /* Sec. 3: dz = Z_3^3(2r/D, theta) lambda/16 + a Gaussian dip of depth lambda/8. */
            double v = p->ncp_trefoil * rho * rho * rho * cos(3.0 * th);
            if (p->ncp_gauss_depth != 0) {
                const double dxg = x - p->ncp_gauss_x, dyg = y - p->ncp_gauss_y;
                v -= p->ncp_gauss_depth * exp(-(dxg * dxg + dyg * dyg) / (p->ncp_gauss_radius * p->ncp_gauss_radius));
            }
            for (size_t k = 0; k < p->ncp_nzernike; k++)
                v += p->ncp_zernike[3 * k + 2] *
                     swfs_zernike((int)p->ncp_zernike[3 * k], (int)p->ncp_zernike[3 * k + 1], rho, th);
            if (map) v += map->data[q * np + pp];
            ncp[q * np + pp] = v;
            s += mask[q * np + pp];
            s1 += mask[q * np + pp] * v;
        }
    }
    swfs_real_free(map);
    if (!(s > 0)) return swfs_fail(SWFS_ERR_VALUE, "NCP map: the pupil mask is empty");
    const double mean = s1 / s;
    double s2 = 0.0, lo = INFINITY, hi = -INFINITY;
    for (size_t k = 0; k < np * np; k++) {
        if (mask[k] > 0) {
            ncp[k] -= mean;
            if (!isfinite(ncp[k])) return swfs_fail(SWFS_ERR_VALUE, "NCP map: non-finite value at pupil sample %zu", k);
            s2 += mask[k] * ncp[k] * ncp[k];
            if (ncp[k] < lo) lo = ncp[k];
            if (ncp[k] > hi) hi = ncp[k];
        } else {
            ncp[k] = 0.0;
        }
    }
    if (rms) *rms = sqrt(s2 / s);
    if (pv) *pv = hi - lo;
    return SWFS_OK;
}

/* ---- the per-frame work ------------------------------------------------ */

struct shared {
    const swfs_sim_params *p;
    size_t n, np, nf, nper, step, off0;
    const double *screens[2];  /* residual screens of this batch */
    size_t nscr, first_screen; /* screens in this batch, index of the first */
    const float *mask;         /* np*np */
    const float complex *ncp_phasor;
    double kphase;             /* 2 pi / lambda */
    double counts_scale, inv_s;
    size_t center;             /* index of pixel (nfx/2, nfy/2) */
    swfs_sim_result *r;
    float complex *halo_frames; /* nframes * nf: E_ncp e^{-i p_t} */
    double *frame_var, *frame_strehl, *frame_strehl_ao, *frame_total;
    struct worker *workers;
};

struct worker {
    swfs_mft *mft;
    float *phi;
    float complex *fnn, *fncp, *enn, *encp;
};

static void do_frame(const struct shared *sh, struct worker *w, size_t task)
{
    const size_t np = sh->np, n = sh->n, nf = sh->nf, per2 = sh->nper * sh->nper;
    const size_t si = task / per2, j = task % per2, row = j / sh->nper, col = j % sh->nper;
    const size_t t = (sh->first_screen + si) * per2 + j;
    const double *scr = sh->screens[si] + (sh->off0 + row * sh->step) * n + sh->off0 + col * sh->step;
    double s = 0.0, s1 = 0.0, s2 = 0.0;
    for (size_t q = 0; q < np; q++) {
        const double *zr = scr + q * n;
        for (size_t pp = 0; pp < np; pp++) {
            const size_t k = q * np + pp;
            const double m = sh->mask[k], z = zr[pp];
            s += m;
            s1 += m * z;
            s2 += m * z * z;
            w->phi[k] = (float)(sh->kphase * z);
        }
    }
    /* P e^{i phi} (vectorized kernel), and with the NCP phasor for the science camera. */
    swfs_expi_f(w->phi, sh->mask, w->fnn, np * np);
    for (size_t k = 0; k < np * np; k++) w->fncp[k] = w->fnn[k] * sh->ncp_phasor[k];
    const double mean = s1 / s;
    sh->frame_var[t] = s2 / s - mean * mean;
    swfs_mft_forward_f(w->mft, w->fnn, w->enn);
    swfs_mft_forward_f(w->mft, w->fncp, w->encp);
    /* Sec. 3: reference each frame to the phase of its (no-NCP) halo peak. */
    size_t kmax = 0;
    float best = -1.0f;
    for (size_t k = 0; k < nf; k++) {
        const float a = crealf(w->enn[k]) * crealf(w->enn[k]) + cimagf(w->enn[k]) * cimagf(w->enn[k]);
        if (a > best) {
            best = a;
            kmax = k;
        }
    }
    const double pt = atan2(cimagf(w->enn[kmax]), crealf(w->enn[kmax]));
    sh->r->ref_phase[t] = pt;
    const double complex rot = cos(pt) - I * sin(pt);
    const float complex rotf = (float complex)rot;
    double *sci = swfs_real_frame(sh->r->science, t);
    double complex *spk = swfs_cplx_frame(sh->r->speckles, t);
    float complex *hf = sh->halo_frames + t * nf;
    double total = 0.0;
    for (size_t k = 0; k < nf; k++) {
        const double complex e = w->encp[k];
        const double v = sh->counts_scale * (creal(e) * creal(e) + cimag(e) * cimag(e));
        sci[k] = v;
        total += v;
        spk[k] = (double complex)w->enn[k] * rot * sh->inv_s;
        hf[k] = w->encp[k] * rotf;
    }
    sh->frame_total[t] = total;
    const double complex ec = w->encp[sh->center], ea = w->enn[sh->center];
    const double is2 = sh->inv_s * sh->inv_s;
    sh->frame_strehl[t] = (creal(ec) * creal(ec) + cimag(ec) * cimag(ec)) * is2;
    sh->frame_strehl_ao[t] = (creal(ea) * creal(ea) + cimag(ea) * cimag(ea)) * is2;
}

static void frames_fn(void *ctx, size_t b, size_t e, int worker)
{
    const struct shared *sh = ctx;
    for (size_t task = b; task < e; task++) do_frame(sh, &sh->workers[worker], task);
}

static void workers_free(struct worker *w, int nw)
{
    if (!w) return;
    for (int i = 0; i < nw; i++) {
        swfs_mft_free(w[i].mft);
        swfs_free(w[i].phi);
        swfs_free(w[i].fnn);
        swfs_free(w[i].fncp);
        swfs_free(w[i].enn);
        swfs_free(w[i].encp);
    }
    free(w);
}

void swfs_sim_result_free(swfs_sim_result *r)
{
    if (!r) return;
    swfs_real_free(r->science);
    swfs_cplx_free(r->speckles);
    swfs_cplx_free(r->speckle_mean);
    swfs_real_free(r->ncp);
    swfs_cplx_free(r->halo_true);
    swfs_real_free(r->pupil);
    free(r->ref_phase);
    free(r);
}

/* Multiply the drawn spectrum and waves by H(f) = 1 - G(f) exp(-2 pi i f.s). G and the
 * shift factorize in x and y, so H costs one complex product per frequency. */
struct filter_ctx {
    double complex *spec;
    const double complex *hx, *hy;
    size_t n;
};

static void filter_rows(void *ctx, size_t b, size_t e, int worker)
{
    const struct filter_ctx *f = ctx;
    (void)worker;
    for (size_t ky = b; ky < e; ky++) {
        double complex *row = f->spec + ky * f->n;
        const double complex y = f->hy[ky];
        for (size_t kx = 0; kx < f->n; kx++) row[kx] *= 1.0 - f->hx[kx] * y;
    }
}

static int apply_residual_filter(swfs_screen_gen *gen, const swfs_sim_params *p, double sigma, int nthreads)
{
    const size_t n = p->screen.n;
    const double df = 1.0 / ((double)n * p->screen.dx), k = -2.0 * M_PI * M_PI * sigma * sigma;
    double sx, sy;
    swfs_sim_lag_vector(p, &sx, &sy);
    double complex *hx = malloc(2 * n * sizeof *hx);
    if (!hx) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    double complex *hy = hx + n;
    for (size_t i = 0; i < n; i++) {
        const double f = (double)swfs_fft_freq_index(i, n) * df;
        hx[i] = exp(k * f * f) * cexp(-2.0 * M_PI * I * f * sx);
        hy[i] = exp(k * f * f) * cexp(-2.0 * M_PI * I * f * sy);
    }
    struct filter_ctx fc = {swfs_screen_gen_spectrum(gen), hx, hy, n};
    swfs_parallel_for(nthreads, n, 32, filter_rows, &fc);
    free(hx);
    size_t nw = 0;
    swfs_screen_wave *wv = swfs_screen_gen_waves(gen, &nw);
    for (size_t i = 0; i < nw; i++) {
        const double f2 = wv[i].fx * wv[i].fx + wv[i].fy * wv[i].fy;
        wv[i].coef *= 1.0 - exp(k * f2) * cexp(-2.0 * M_PI * I * (wv[i].fx * sx + wv[i].fy * sy));
    }
    return SWFS_OK;
}

int swfs_sim_paper_run(const swfs_sim_params *p, swfs_progress_fn progress, void *ctx, swfs_sim_result **out)
{
    return swfs_sim_paper_run_ncp(p, NULL, progress, ctx, out);
}

/* ncp (pupn x pupn [m], may be NULL) replaces the NCP terms of p: the closed-loop
 * simulation (closed_loop.h) injects the residual after its DM corrections this way. */
static int ncp_override(const double *in, const double *mask, size_t n, double *ncp, double *rms, double *pv)
{
    double s = 0.0, s1 = 0.0;
    for (size_t k = 0; k < n; k++) {
        if (mask[k] > 0 && !isfinite(in[k]))
            return swfs_fail(SWFS_ERR_VALUE, "NCP map: non-finite value at pupil sample %zu", k);
        s += mask[k];
        s1 += mask[k] > 0 ? mask[k] * in[k] : 0.0;
    }
    if (!(s > 0)) return swfs_fail(SWFS_ERR_VALUE, "NCP map: the pupil mask is empty");
    const double mean = s1 / s;
    double s2 = 0.0, lo = INFINITY, hi = -INFINITY;
    for (size_t k = 0; k < n; k++) {
        ncp[k] = mask[k] > 0 ? in[k] - mean : 0.0;
        if (mask[k] > 0) {
            s2 += mask[k] * ncp[k] * ncp[k];
            if (ncp[k] < lo) lo = ncp[k];
            if (ncp[k] > hi) hi = ncp[k];
        }
    }
    *rms = sqrt(s2 / s);
    *pv = hi - lo;
    return SWFS_OK;
}

/* The result with its geometry and every array allocated (NULL when out of memory). */
static swfs_sim_result *result_alloc(const swfs_sim_params *p, size_t nframes, size_t nper)
{
    const size_t np = (size_t)p->pupn, nfx = (size_t)p->nfx, nfy = (size_t)p->nfy;
    swfs_sim_result *r = calloc(1, sizeof *r);
    if (!r) return NULL;
    r->params = *p;
    r->nframes = nframes;
    r->per_screen = nper;
    swfs_geom_init(&r->geom);
    r->geom.wavelen = p->wavelen;
    r->geom.teldiam = p->teldiam;
    r->geom.obscur = p->obscur;
    r->geom.pixscale = p->pixscale;
    r->geom.pupdx = p->pupdx;
    r->geom.pupn = p->pupn;
    r->science = swfs_real_alloc(nfx, nfy, nframes);
    r->speckles = swfs_cplx_alloc(nfx, nfy, nframes);
    r->ncp = swfs_real_alloc(np, np, 1);
    r->halo_true = swfs_cplx_alloc(nfx, nfy, 1);
    r->speckle_mean = swfs_cplx_alloc(nfx, nfy, 1);
    r->pupil = swfs_real_alloc(np, np, 1);
    r->ref_phase = calloc(nframes, sizeof *r->ref_phase);
    if (!r->science || !r->speckles || !r->ncp || !r->halo_true || !r->speckle_mean || !r->pupil || !r->ref_phase) {
        swfs_sim_result_free(r);
        return NULL;
    }
    return r;
}

/* The pupil and the NCP (ncp, else p's map) into r, their single-precision forms for the
 * workers, and the field and counts scales. */
static int pupil_and_ncp(const swfs_sim_params *p, const double *ncp, swfs_sim_result *r, float *maskf,
                         float complex *ncpph, double *ssum_out)
{
    const size_t np = (size_t)p->pupn;
    int rc = swfs_sim_pupil(p, r->pupil->data);
    if (rc) return rc;
    if (ncp) {
        if ((rc = ncp_override(ncp, r->pupil->data, np * np, r->ncp->data, &r->ncp_rms, &r->ncp_pv))) return rc;
    } else if ((rc = swfs_sim_ncp_map(p, r->pupil->data, r->ncp->data, &r->ncp_rms, &r->ncp_pv))) {
        return rc;
    }
    double ssum = 0.0, ssum2 = 0.0;
    const double kphase = 2.0 * M_PI / p->wavelen;
    for (size_t k = 0; k < np * np; k++) {
        const double m = r->pupil->data[k];
        ssum += m;
        ssum2 += m * m;
        maskf[k] = (float)m;
        ncpph[k] = (float complex)cexp(I * kphase * r->ncp->data[k]);
    }
    const double alpha = p->pixscale * p->pupdx / p->teldiam;
    r->field_scale = ssum;
    /* C: the whole focal plane (1/alpha x 1/alpha equivalent pixels) holds total_counts. */
    r->counts_scale = p->total_counts * alpha * alpha / ssum2;
    *ssum_out = ssum;
    return SWFS_OK;
}

/* nw workers with their MFT and buffers (NULL with the message set when out of memory). */
static struct worker *workers_create(int nw, size_t np, size_t nfx, size_t nfy, double alpha)
{
    const size_t nf = nfx * nfy;
    struct worker *wk = calloc((size_t)nw, sizeof *wk);
    if (!wk) {
        swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        return NULL;
    }
    for (int i = 0; i < nw; i++) {
        wk[i].mft = swfs_mft_create(np, nfx, nfy, alpha, SWFS_MFT_SINGLE);
        wk[i].phi = swfs_malloc(np * np * sizeof(float));
        wk[i].fnn = swfs_malloc(np * np * sizeof(float complex));
        wk[i].fncp = swfs_malloc(np * np * sizeof(float complex));
        wk[i].enn = swfs_malloc(nf * sizeof(float complex));
        wk[i].encp = swfs_malloc(nf * sizeof(float complex));
        if (!wk[i].mft || !wk[i].phi || !wk[i].fnn || !wk[i].fncp || !wk[i].enn || !wk[i].encp) {
            workers_free(wk, nw);
            swfs_fail(SWFS_ERR_NOMEM, "simulation: out of memory for worker buffers");
            return NULL;
        }
    }
    return wk;
}

/* Serial reductions in frame order: the speckle mean removed (eq:computedSpeckleField),
 * the true static halo, and the summary numbers. */
static void reduce_frames(const struct shared *sh, size_t nframes, swfs_sim_result *r)
{
    const size_t nf = sh->nf;
    double complex *mean = r->speckle_mean->data;
    for (size_t k = 0; k < nf; k++) mean[k] = 0.0;
    for (size_t t = 0; t < nframes; t++) {
        const double complex *s = swfs_cplx_frame(r->speckles, t);
        for (size_t k = 0; k < nf; k++) mean[k] += s[k];
    }
    for (size_t k = 0; k < nf; k++) mean[k] /= (double)nframes;
    for (size_t t = 0; t < nframes; t++) {
        double complex *s = swfs_cplx_frame(r->speckles, t);
        for (size_t k = 0; k < nf; k++) s[k] -= mean[k];
    }
    double complex *halo = r->halo_true->data;
    for (size_t k = 0; k < nf; k++) halo[k] = 0.0;
    for (size_t t = 0; t < nframes; t++) {
        const float complex *h = sh->halo_frames + t * nf;
        for (size_t k = 0; k < nf; k++) halo[k] += (double complex)h[k];
    }
    const double hs = sqrt(r->counts_scale) / (double)nframes;
    for (size_t k = 0; k < nf; k++) halo[k] *= hs;
    double var = 0.0, st = 0.0, sta = 0.0, tot = 0.0;
    for (size_t t = 0; t < nframes; t++) {
        var += sh->frame_var[t];
        st += sh->frame_strehl[t];
        sta += sh->frame_strehl_ao[t];
        tot += sh->frame_total[t];
    }
    r->residual_rms = sqrt(var / (double)nframes);
    r->strehl = st / (double)nframes;
    r->strehl_ao = sta / (double)nframes;
    r->window_fraction = tot / (double)nframes / sh->p->total_counts;
}

int swfs_sim_paper_run_ncp(const swfs_sim_params *p, const double *ncp, swfs_progress_fn progress, void *ctx,
                           swfs_sim_result **out)
{
    const double t0 = swfs_wall_seconds();
    *out = NULL;
    int rc = swfs_sim_params_check(p);
    if (rc) return rc;
    const size_t n = p->screen.n, np = (size_t)p->pupn, nfx = (size_t)p->nfx, nfy = (size_t)p->nfy, nf = nfx * nfy;
    const size_t step = (size_t)lround(p->spacing * p->teldiam / p->screen.dx);
    const size_t fit = (n - np) / step + 1, nper = p->per_screen ? (size_t)p->per_screen : fit;
    const size_t off0 = (n - (np + (nper - 1) * step)) / 2;
    const size_t per2 = nper * nper, nframes = per2 * (size_t)p->nscreens;

    struct shared sh;
    memset(&sh, 0, sizeof sh);
    struct worker *wk = NULL;
    int nw = 0;
    swfs_screen_gen *gen = NULL;
    swfs_ao_model *model = NULL;
    swfs_sim_result *r = result_alloc(p, nframes, nper);
    sh.halo_frames = swfs_malloc(nframes * nf * sizeof *sh.halo_frames);
    double *frame_buf = calloc(4 * nframes, sizeof *frame_buf);
    float *maskf = swfs_malloc(np * np * sizeof *maskf);
    float complex *ncpph = swfs_malloc(np * np * sizeof *ncpph);
    double *scr1 = swfs_malloc(n * n * sizeof *scr1), *scr2 = swfs_malloc(n * n * sizeof *scr2);
    if (!r || !sh.halo_frames || !frame_buf || !maskf || !ncpph || !scr1 || !scr2) {
        rc = swfs_fail(SWFS_ERR_NOMEM, "simulation: out of memory for %zu frames of %zux%zu", nframes, nfx, nfy);
        goto done;
    }
    double ssum;
    if ((rc = pupil_and_ncp(p, ncp, r, maskf, ncpph, &ssum))) goto done;
    const double alpha = p->pixscale * p->pupdx / p->teldiam;

    /* Screens and the AO model. */
    gen = swfs_screen_gen_create(&p->screen);
    if (!gen) {
        rc = SWFS_ERR_NOMEM;
        goto done;
    }
    swfs_screen_gen_set_threads(gen, p->threads);
    model = swfs_ao_model_create_with(p, gen);
    if (!model) {
        rc = SWFS_ERR_VALUE;
        goto done;
    }
    if ((rc = swfs_ao_model_solve(model, p->target_rms, &r->kernel_sigma))) goto done;
    r->expected_rms = swfs_ao_model_rms(model, r->kernel_sigma);
    r->lag_floor_rms = swfs_ao_model_rms(model, 0.0);

    nw = swfs_parallel_threads(p->threads, 0);
    if (!(wk = workers_create(nw, np, nfx, nfy, alpha))) {
        rc = SWFS_ERR_NOMEM;
        goto done;
    }
    sh.p = p;
    sh.n = n;
    sh.np = np;
    sh.nf = nf;
    sh.nper = nper;
    sh.step = step;
    sh.off0 = off0;
    sh.mask = maskf;
    sh.ncp_phasor = ncpph;
    sh.kphase = 2.0 * M_PI / p->wavelen;
    sh.counts_scale = r->counts_scale;
    sh.inv_s = 1.0 / ssum;
    sh.center = (nfy / 2) * nfx + nfx / 2;
    sh.r = r;
    sh.frame_var = frame_buf;
    sh.frame_strehl = frame_buf + nframes;
    sh.frame_strehl_ao = frame_buf + 2 * nframes;
    sh.frame_total = frame_buf + 3 * nframes;
    sh.workers = wk;

    swfs_rng rng;
    const size_t nbatch = ((size_t)p->nscreens + 1) / 2;
    for (size_t b = 0; b < nbatch; b++) {
        /* One stream per screen pair: the result depends on the seed only. */
        swfs_rng_seed2(&rng, p->seed, b);
        const int two = 2 * b + 1 < (size_t)p->nscreens;
        if ((rc = swfs_screen_gen_draw(gen, &rng))) goto done;
        if ((rc = apply_residual_filter(gen, p, r->kernel_sigma, nw))) goto done;
        if ((rc = swfs_screen_gen_finish(gen, scr1, two ? scr2 : NULL))) goto done;
        if ((rc = swfs_progress_report(progress, ctx, "screens", 2 * b + 1 + (size_t)two, (size_t)p->nscreens))) goto done;
        sh.screens[0] = scr1;
        sh.screens[1] = scr2;
        sh.nscr = two ? 2 : 1;
        sh.first_screen = 2 * b;
        swfs_parallel_for(nw, sh.nscr * per2, 1, frames_fn, &sh);
        if ((rc = swfs_progress_report(progress, ctx, "frames", (2 * b + sh.nscr) * per2, nframes))) goto done;
    }
    reduce_frames(&sh, nframes, r);
    r->seconds = swfs_wall_seconds() - t0;

done:
    workers_free(wk, nw);
    swfs_ao_model_free(model);
    swfs_screen_gen_free(gen);
    swfs_free(scr1);
    swfs_free(scr2);
    swfs_free(maskf);
    swfs_free(ncpph);
    swfs_free(sh.halo_frames);
    free(frame_buf);
    if (rc) {
        swfs_sim_result_free(r);
        return rc;
    }
    *out = r;
    return SWFS_OK;
}

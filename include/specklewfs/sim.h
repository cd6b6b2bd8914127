/* The paper's Sec. 3 simulation (Codona & Kenworthy 2013): an ensemble of post-AO
 * residual wavefronts cut from von Karman screens, a static NCP aberration, science
 * images |MFT(P e^{i(phi + ncp)})|^2 in counts, and the complex speckle cube the WFS
 * would give (computed WITHOUT the NCP, referenced to the halo peak phase, mean removed).
 * Design notes: docs/simulation.md.
 *
 * AO residual model (Sec. 3): residual z_res = z - shift_s(G_sigma * z), G_sigma a unit
 * Gaussian kernel exp(-r^2 / (2 sigma^2)) / (2 pi sigma^2), s = lag_shift * dx in direction
 * lag_angle (v_wind tau_lag). Applied on the spectrum: Z(f) [1 - exp(-2 pi^2 sigma^2 f^2)
 * exp(-2 pi i f.s)]. sigma is solved so that the EXPECTED piston-removed rms over the
 * pupil equals target_rms (Parseval on the von Karman spectrum weighted by 1 - |W(f)|^2,
 * W the normalized pupil transform), no FFT per iteration.
 *
 * Definitions the estimator relies on (E = MFT(field) with mft.h, alpha = PIXSCALE *
 * PUPDX / TELDIAM, S = sum P):
 *   science_t   = C |E(P e^{2 pi i (z_t + ncp)/lambda})|^2, C = total_counts alpha^2 / sum P^2
 *                 (so the WHOLE focal plane would hold total_counts; the window less);
 *   p_t         = arg E(P e^{2 pi i z_t / lambda}) at its peak pixel (max |E|);
 *   speckles_t  = E(P e^{2 pi i z_t/lambda}) e^{-i p_t} / S  minus its mean over t
 *                 (field units: the unaberrated PSF peak amplitude is 1);
 *   halo_true   = sqrt(C) mean_t E(P e^{2 pi i (z_t + ncp)/lambda}) e^{-i p_t}  [sqrt(counts)];
 *   ncp         = injected NCP wavefront [m], piston removed over the pupil, 0 outside.
 * Frame t = screen * per_screen^2 + row * per_screen + column. */
#ifndef SWFS_SIM_H
#define SWFS_SIM_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/array.h"
#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/screen.h"
#include "specklewfs/status.h"

SWFS_BEGIN_DECLS

#define SWFS_SIM_MAX_ZERNIKE 64 /* NCP Zernike terms */

typedef struct swfs_sim_params {
    /* turbulence */
    swfs_screen_params screen; /* n (2048), dx (0.04 m: also the pupil pitch), r0 (0.15 m at
                                  500 nm), L0 (30 m), subharmonics (1) */
    int nscreens;              /* 5 */
    /* telescope and sampling */
    double teldiam;            /* [m] 6.5 */
    long pupn;                 /* pupil samples across, 163 */
    double pupdx;              /* [m] 0.04, must equal screen.dx */
    double obscur;             /* 0.1 (fraction of the diameter) */
    int nspiders;              /* 0 */
    double spider_width;       /* [m] 0 */
    double wavelen;            /* [m] 3.8e-6 */
    double spacing;            /* sub-grid spacing / teldiam, 0.85 */
    long per_screen;           /* sub-grids per screen side; 0: as many as fit (14) */
    /* AO residual */
    double target_rms;         /* [m] expected piston-removed pupil rms, 250e-9 */
    double lag_shift;          /* [samples] v_wind tau_lag / dx, 1 (may be fractional) */
    double lag_angle;          /* [deg] direction of the shift from +x, 0 */
    /* focal plane and camera */
    long nfx, nfy;             /* 60 x 60 */
    double pixscale;           /* [lambda/D per pixel] 0.25 */
    double total_counts;       /* mean counts per exposure over the whole PSF, 157000 */
    double read_noise;         /* [counts] Gaussian background sigma, 0 */
    double gain;               /* [e-/count] 1; <= 0: no photon (Poisson) noise */
    /* NCP aberration [m of wavefront] */
    double ncp_trefoil;        /* Z_3^3(2r/D) coefficient, lambda/16 = 237.5e-9 */
    double ncp_gauss_depth;    /* Gaussian indentation depth, lambda/8 = 475e-9 (dip: negative) */
    double ncp_gauss_radius;   /* [m] 1/e radius, 1 */
    double ncp_gauss_x, ncp_gauss_y; /* [m] centre (-1, 2) */
    double ncp_zernike[3 * SWFS_SIM_MAX_ZERNIKE]; /* triples n, m, coefficient [m] (aperture.h
                                                     convention, rho = 2r/D) */
    size_t ncp_nzernike;       /* number of triples */
    char ncp_map[1024];        /* FITS map [m], pupn x pupn, added; "" = none */
    char pupil_mask[1024];     /* FITS transmission (0..1), pupn x pupn, in place of the
                                  annulus of teldiam, obscur and the spiders; "" = none */
    /* run */
    uint64_t seed;             /* 1 */
    int threads;               /* worker threads; 0 = number of online CPUs */
} swfs_sim_params;

void swfs_sim_params_default(swfs_sim_params *p);
/* Read every key this module knows (see config/paper-sec3.conf) from c over the current
 * values of p. Unknown keys are left unused for swfs_config_check_unused(). */
int swfs_sim_params_from_config(swfs_config *c, swfs_sim_params *p);
/* Consistency checks (sizes, ranges, pupdx = screen.dx, sub-grids fit the screen). */
int swfs_sim_params_check(const swfs_sim_params *p);
/* "key=value" lines describing p (for provenance). Writes at most cap bytes, lines
 * separated by '\n'; returns the length needed (like snprintf). */
size_t swfs_sim_params_format(const swfs_sim_params *p, char *buf, size_t cap);

typedef struct swfs_sim_result {
    swfs_sim_params params;   /* the parameters that made it */
    swfs_geom geom;
    size_t nframes, per_screen;
    swfs_real *science;       /* noise-free expected counts, nfx x nfy x nframes */
    swfs_cplx *speckles;      /* psi, nfx x nfy x nframes (see the definitions above) */
    swfs_cplx *speckle_mean;  /* the mean removed from the speckles (no-NCP static halo in
                                 speckle units), nfx x nfy */
    swfs_real *ncp;           /* injected NCP wavefront [m], pupn x pupn */
    swfs_cplx *halo_true;     /* true static halo [sqrt(counts)], nfx x nfy */
    swfs_real *pupil;         /* mask, pupn x pupn */
    double *ref_phase;        /* p_t [rad], nframes */
    double counts_scale;      /* C */
    double field_scale;       /* S = sum P: speckles = E e^{-i p_t} / S - mean */
    double residual_rms;      /* [m] achieved: sqrt(mean_t piston-removed pupil variance) */
    double expected_rms;      /* [m] the model's expectation for kernel_sigma */
    double lag_floor_rms;     /* [m] expected rms with no smoothing (pure lag error) */
    double kernel_sigma;      /* [m] Gaussian kernel sigma */
    double strehl;            /* mean on-axis Strehl of the science frames (with NCP) */
    double strehl_ao;         /* same without the NCP */
    double window_fraction;   /* mean science total over the window / total_counts */
    double ncp_rms, ncp_pv;   /* [m] over the pupil */
    double seconds;           /* wall time of swfs_sim_paper_run */
} swfs_sim_result;


/* Run the whole simulation. progress may be NULL; it is called from the calling thread
 * only, with stages "screens" and "frames". */
int swfs_sim_paper_run(const swfs_sim_params *p, swfs_progress_fn progress, void *ctx, swfs_sim_result **out);
/* The same with the NCP given as a map ncp [m] on the pupil grid (pupn x pupn) instead of
 * the NCP terms of p (piston is removed over the pupil, values outside it are ignored);
 * ncp = NULL is swfs_sim_paper_run. Used by the closed-loop simulation (closed_loop.h). */
int swfs_sim_paper_run_ncp(const swfs_sim_params *p, const double *ncp, swfs_progress_fn progress, void *ctx,
                           swfs_sim_result **out);
void swfs_sim_result_free(swfs_sim_result *r);

/* Building blocks (exposed for tests and other simulators). */
/* The NCP map of p on the pupil grid [m] (piston removed over mask, 0 outside); rms and pv
 * may be NULL. */
int swfs_sim_ncp_map(const swfs_sim_params *p, const double *mask, double *ncp, double *rms, double *pv);
/* The telescope pupil of p on its grid (pupn x pupn transmissions, row-major): the file
 * pupil_mask when given (its shape, values 0..1 and light within teldiam checked, the file
 * named in every refusal), else the annulus of teldiam and obscur with the spiders. */
int swfs_sim_pupil(const swfs_sim_params *p, double *mask);
/* The AO residual model of p (screen spectrum, lag, pupil diameter and obscuration):
 * expected piston-removed pupil rms [m] of the residual for a kernel sigma [m] (sigma = 0:
 * a perfect but late correction, the lag-error floor), and the sigma giving a target. */
typedef struct swfs_ao_model swfs_ao_model;
swfs_ao_model *swfs_ao_model_create(const swfs_sim_params *p);
double swfs_ao_model_rms(const swfs_ao_model *m, double sigma);
int swfs_ao_model_solve(const swfs_ao_model *m, double target_rms, double *sigma);
void swfs_ao_model_free(swfs_ao_model *m);

/* Camera noise: per frame k, an RNG stream swfs_rng_seed2(seed, k); photons =
 * Poisson(clean * gain) (skipped when gain <= 0), counts = photons / gain + read_noise N(0,1).
 * Reproducible and independent of threading. noisy may be clean (in place); shapes must
 * match. */
int swfs_sim_camera(const swfs_real *clean, double read_noise, double gain, uint64_t seed, swfs_real *noisy);

/* Write DIR/science.fits (science cube, primary HDU, RDNOISE, GAIN), DIR/speckles.fits
 * (complex cube, primary HDU), DIR/truth.fits (NCP [m], HALO complex), DIR/pupil.fits
 * (mask). Geometry keywords on every HDU, provenance lines plus the parameters as HISTORY.
 * science may be r->science (noise-free) or a noisy copy; DIR must exist. */
int swfs_sim_write(const swfs_sim_result *r, const swfs_real *science, double read_noise, double gain, const char *dir,
                   const char *const *provenance, size_t nprov);

SWFS_END_DECLS

#endif

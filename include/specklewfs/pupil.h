/* Pupil field and NCP wavefront from the static halo (paper Sec. 4.6):
 *   field(x) = alpha^2 sum_theta w(theta) Psi(theta) exp(+2 pi i theta.x / lambda)
 * (the inverse MFT of eq:Pupil-field-with-NCP1 on the PUPN x PUPN grid, alpha =
 * PIXSCALE*PUPDX/TELDIAM; the constant 1/((2 pi)^2 S^{1/2}) is left out: it changes
 * the amplitude scale, not the wavefront), then
 *   WFE(x) = lambda/(2 pi) arg{ field(x) + bias <field>_pupil }        (eq:NCP-WFE-estimate,
 *                                                                     eq:LFBiased-WFE-estimate)
 * inside the pupil with piston removed; SURFACE = WFE/2 (reflective DM).
 *
 * Weighting (beyond the paper): the paper lets every focal pixel in at full weight, so
 * noisy outer pixels add noise to the wavefront. With SWFS_WEIGHT_SNR each pixel is
 * multiplied by the Wiener factor SNR^2/(SNR^2 + k^2), SNR = |<psi' I>| / stderr (the
 * STAB and STAB_ERR extensions), k = 2 by default.
 *
 * Two methods. SWFS_PUPIL_MOMENTS is the above: the per-pixel moment estimate (HALO or HALO_LF)
 * transformed. SWFS_PUPIL_FIT (beyond the paper, docs/estimator.md) fits the pupil field, a
 * smooth g map and the unexplained speckle fraction to all focal pixels at once from the
 * regression statistics the halo carries (h->reg, HALO.fits REGSTATE; jointfit.h); the WFE is
 * then the fitted phase, with no phase wrapping and no focal window edge. SWFS_PUPIL_AUTO
 * (default) is the fit when the halo has regression statistics and the moments otherwise.
 */
#ifndef SWFS_PUPIL_H
#define SWFS_PUPIL_H

#include "specklewfs/array.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/jointfit.h"

SWFS_BEGIN_DECLS

enum { SWFS_WEIGHT_NONE = 0, SWFS_WEIGHT_SNR = 1 };
enum { SWFS_SOURCE_HALO_LF = 0, SWFS_SOURCE_HALO = 1 };
enum { SWFS_PUPIL_AUTO = 0, SWFS_PUPIL_FIT = 1, SWFS_PUPIL_MOMENTS = 2 };

typedef struct swfs_pupil_options {
    int weight;      /* SWFS_WEIGHT_NONE or SWFS_WEIGHT_SNR */
    double wiener_k; /* k of the Wiener factor (default 2) */
    double bias;     /* constant field added, as a fraction of the mean pupil field (0 = none) */
    int source;      /* SWFS_SOURCE_HALO_LF (eq:PSI-LowFreq, default) or SWFS_SOURCE_HALO */
    int method;      /* SWFS_PUPIL_AUTO (default), SWFS_PUPIL_FIT or SWFS_PUPIL_MOMENTS; weight,
                        wiener_k, bias and source apply to the moments only */
    swfs_jointfit_options fit; /* the joint fit's options (swfs_jointfit_options_default) */
    int keep_resmean; /* 0 (default): where the halo carries the AO residual's time mean that the
                         telemetry measured (swfs_halo.resmean), take it out of WFE and FIELD,
                         band-limited to the window (swfs_pupil_remove_resmean): WFE is then the
                         NCP alone. 1: keep it (WFE = the whole static aberration the camera saw) */
} swfs_pupil_options;

void swfs_pupil_options_default(swfs_pupil_options *o);

typedef struct swfs_pupil_result {
    swfs_cplx *field;     /* complex pupil field */
    swfs_real *wfe;       /* [m], 0 outside the pupil */
    swfs_real *surface;   /* [m] = WFE/2 */
    swfs_real *amplitude; /* |field| */
    swfs_real *mask;      /* pupil used */
    double wfe_rms, wfe_pv; /* inside the pupil, piston removed [m] */
    double strehl;          /* Marechal, exp(-(2 pi rms / lambda)^2) */
    swfs_pupil_options opt;
    int method;             /* SWFS_PUPIL_FIT or SWFS_PUPIL_MOMENTS: what was used */
    swfs_jointfit_result *fit; /* the joint fit (owned), NULL for the moments */
    double explained, explained_median; /* the joint fit's self-check of the speckles (swfs_regress_sol):
                                           NaN for the moments */
    swfs_real *explained_map; /* per focal pixel 1 - SSE / SST (NaN where not solved), NULL for the moments */
    swfs_real *resmean;   /* [m] the AO residual's time mean taken out of WFE (band-limited, piston,
                             tip and tilt removed); NULL when none was (no RESMEAN, or keep_resmean) */
    double resmean_rms;   /* [m] its rms in the pupil; 0 when none */
} swfs_pupil_result;

/* The self-check by ring: out[k] = the median of the finite values of map (a focal-plane
 * window, pixel (i, j) at (i - nx/2, j - ny/2) PIXSCALE lambda/D) over the ring
 * [k, k + 1) lambda/D, NaN where the ring has none, for k < nrings. Where the computed
 * speckles lack what the WFS aliases, the rings inside the control radius that the aliases
 * land on explain less than their neighbours (docs/telemetry.md). */
void swfs_pupil_explained_rings(const swfs_real *map, double pixscale, double *out, size_t nrings);
/* The rings out to the window's edge: ceil(nx PIXSCALE / 2). */
size_t swfs_pupil_explained_nrings(const swfs_real *map, double pixscale);

/* The self-check as a choice among candidate halos of the same science frames made from
 * different computed speckles (another reconstructor, such as a learned one, or another
 * tip-tilt treatment), each with its regression statistics (REGSTATE): per candidate the
 * fraction of the science intensity's variance about its mean that the regression on its
 * speckles explains, 1 - sum SSE / sum SST over the focal pixels solved in every candidate
 * (explained[i]; so all are scored on one set of pixels), and the index of the largest
 * (*best). *ncommon: those pixels. The science must be the same: the candidates' sum of SST
 * over those pixels must agree to 1e-6 (SWFS_ERR_VALUE naming the two otherwise), as must the
 * window; a halo without regression statistics is SWFS_ERR_VALUE. names: for messages (may be
 * NULL). docs/telemetry.md, "The self-check as the choice". */
int swfs_halo_choose(const swfs_halo *const *h, const char *const *names, size_t n, double *explained, size_t *best,
                     size_t *ncommon);

/* A pupil mask read from a file: transmissions in 0 .. 1, not all 0 (SWFS_ERR_VALUE
 * naming `what`, the sample and the value otherwise). */
int swfs_pupil_mask_check(const swfs_real *mask, const char *what);
/* A pupil mask file (its PUPIL extension when it has one, e.g. a simulation's truth.fits, else
 * its first image): n x n transmissions checked by swfs_pupil_mask_check, the file named in
 * every refusal. *out is the caller's. */
int swfs_pupil_mask_read(const char *path, size_t n, swfs_real **out);

/* mask: PUPN x PUPN transmission, or NULL to build the annulus from TELDIAM/OBSCUR. */
int swfs_pupil_estimate(const swfs_halo *h, const swfs_geom *g, const swfs_real *mask,
                        const swfs_pupil_options *opt, swfs_pupil_result **out);
void swfs_pupil_result_free(swfs_pupil_result *r);
/* PUPIL.fits: FIELD (complex), WFE, SURFACE, AMPLITUDE, PUPIL; keys WFERMS, WFEPV, STREHL, METHOD
 * ('FIT' or 'MOMENTS'); after a fit also HALO_FIT (complex Psi of the fit over the focal
 * window, in the frame of psi - <psi>), GAIN_FIT (g) and EXPLAINED (the self-check per pixel), keys FITKAPPA, FITCHI2, FITNPIX,
 * FITNPAR, FITLPHI, FITLAMP, FITITER. */
int swfs_pupil_write(const swfs_pupil_result *r, const char *path, const swfs_geom *g, const char *const *prov,
                     size_t nprov);

/* Compare an estimated wavefront with the truth inside the mask: the difference with
 * piston, tip and tilt removed (least squares), rms [m]. Also the truth's rms with
 * piston removed and with piston + tip/tilt removed. Any output may be NULL. */
int swfs_wfe_compare(const double *est, const double *truth, const double *mask, size_t n, double *err_rms,
                     double *truth_rms_piston, double *truth_rms_ptt);
/* Remove piston, tip and tilt (least squares over the mask) from w in place; returns rms. */
double swfs_wfe_remove_ptt(double *w, const double *mask, size_t n);

/* The AO residual's time mean (speckles measure it from the telemetry over the frames they
 * make: pipeline.h swfs_pipeline_mean_wavefront) is a static aberration of the science frames
 * like the NCP, and the static halo holds it. Only what the nfx x nfy focal window sees of it
 * is in the estimate, so it is band-limited to the window first: the spatial frequencies up to
 * floor(nfx/2) PIXSCALE (x) and floor(nfy/2) PIXSCALE (y) cycles per D, by FFT, as a
 * normalized convolution (the low-passed masked map over the low-passed mask) so the rim keeps
 * its level; piston, tip and tilt removed. out: n x n, 0 outside the mask; rms (may be NULL):
 * its rms in the mask [m]. */
int swfs_resmean_bandlimit(const double *map, const double *mask, size_t n, const swfs_geom *g, size_t nfx,
                           size_t nfy, double *out, double *rms);
/* That band-limited map subtracted from r->wfe and its phase from r->field, inside r->mask;
 * r->resmean and r->resmean_rms set (the caller recomputes the WFE statistics). */
int swfs_pupil_remove_resmean(swfs_pupil_result *r, const swfs_real *resmean, const swfs_geom *g, size_t nfx,
                              size_t nfy);
/* swfs_wfe_compare of r->wfe with the mean that swfs_pupil_remove_resmean took out put back
 * (what keep_resmean gives from the same fit; r->wfe itself where none was taken out):
 * err_rms [m], against truth (n x n, n = r->wfe's side). */
int swfs_pupil_compare_kept(const swfs_pupil_result *r, const double *truth, double *err_rms);

SWFS_END_DECLS

#endif

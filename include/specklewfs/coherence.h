/* Speckle coherence diagnostics (paper Sec. 3.3 "Effects of optical bandwidth and exposure
 * time" and Sec. 4.4): from a complex speckle cube at the WFS frame rate, per pixel,
 *
 *   Gamma(tau) = < psi(t) psi*(t + tau) >                        (eq:MutualCoh)
 *
 * after removing the per-pixel time mean of psi (eq:zeroMean), normalized by Gamma(0),
 * and the maps derived from it:
 *   MEAN_SP   Phi_sp = Gamma(0)
 *   TAU0      first lag where |Gamma(tau)/Gamma(0)| drops below e^{-1/2} [s]
 *             (linear interpolation between WFS frames; +Inf if it never does within the
 *             lags computed)
 *   PHRATE    signed rate of arg{Gamma(tau)/Gamma(0)} [rad/s], a least-squares line through
 *             the origin over lags 1..nfit frames (phase unwrapped frame to frame). For a
 *             frozen pattern translated by the wind v with our sign convention (docs/conventions.md:
 *             Psi = sum P exp(-i k theta.x)) the speckle phase turns by -k theta.v per second
 *             and PHRATE = +k theta.v (see docs/coherence.md; eq:MCF-spinningPhase writes
 *             2k, our derivation and test give k).
 *   TROT      (pi/2) / |PHRATE| [s]: time for the systematic phase to turn by pi/2
 *             (the paper's Fig. "Halo-tau0"(b), extrapolated from the first few frames)
 *   SNR_FACT  eq:MCF-SNReffect at a camera exposure T, normalized so that a perfectly
 *             coherent speckle gives 1:
 *               S(T) = (2/T) int_0^T (1 - tau/T) Re{Gamma(tau)/Gamma(0)} dtau
 *             evaluated by the trapezoid rule on the WFS frame lags (linear interpolation of
 *             Gamma for a fractional last interval). For T = M WFS frames this is exactly
 *             <|box average of M frames of psi|^2> / <|psi|^2>, i.e. what a camera exposure
 *             of M WFS frames does to <psi I> (eq:IntegratedStabTerm1).
 *   MCF       Gamma(tau)/Gamma(0) at the output lags (complex; lags along the last axis)
 *
 * Pixels whose Gamma(0) is zero (below min_power_rel times the largest Gamma(0)) or whose
 * time series holds a non-finite value are NaN in every map and counted, not an error.
 *
 * Computation: per pixel, the autocorrelation at every integer lag 0..max_lag, either by
 * FFT along time (zero-padded so nothing wraps; FFTW plans made once, applied to blocks of
 * pixels) or by direct sums, whichever the operation count says is cheaper (opt.method). */
#ifndef SWFS_COHERENCE_H
#define SWFS_COHERENCE_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/fits.h"

SWFS_BEGIN_DECLS

enum { SWFS_COH_AUTO = 0, SWFS_COH_FFT = 1, SWFS_COH_DIRECT = 2 };

/* The paper's lags (Fig. "Speckles-MCF-4panel1"): 0, 1, ..., 20, 25, 30, ..., 100 frames. */
#define SWFS_COH_DEFAULT_NLAGS 37
/* Fills lags[0..SWFS_COH_DEFAULT_NLAGS-1]. */
void swfs_coh_default_lags(long *lags);

typedef struct swfs_coh_options {
    const long *lags;     /* output lags [WFS frames], strictly increasing, lags[0] = 0;
                             NULL: the paper's. Lags beyond nframes - 1 are dropped. */
    size_t nlags;
    long max_lag;         /* dense lags kept (0: the largest output lag or the exposure,
                             whichever is larger); capped at nframes - 1 */
    int nfit;             /* phase-rate fit over lags 1..nfit frames (default 4, the paper's) */
    double exposure;      /* [s] camera exposure for SNR_FACT; 0: no SNR_FACT map */
    double min_power_rel; /* Gamma(0) <= this * max Gamma(0) counts as no power (1e-20) */
    int method;           /* SWFS_COH_AUTO / _FFT / _DIRECT */
} swfs_coh_options;

void swfs_coh_options_default(swfs_coh_options *o);

typedef struct swfs_coherence {
    size_t nx, ny, nframes;
    double framedt;      /* [s] between WFS frames */
    size_t nlags;        /* output lags */
    long *lag_frames;    /* [nlags] */
    swfs_real *lags;     /* nlags x 1: lags [s] */
    swfs_real *mean_sp;  /* Phi_sp = Gamma(0) */
    swfs_real *tau0;     /* [s] */
    swfs_real *trot;     /* [s]; +Inf: no rotation, or one slower than FLT_MAX s */
    swfs_real *phrate;   /* [rad/s] */
    swfs_real *snr_fact; /* NULL unless exposure > 0 */
    swfs_cplx *mcf;      /* nx x ny x nlags, Gamma(tau)/Gamma(0) */
    double exposure;     /* [s] of snr_fact (0: none) */
    /* Dense normalized MCF, every lag 0..max_lag: gamma[p * (max_lag + 1) + k]. */
    long max_lag;
    swfs_complex *dense;
    int nfit;            /* lags actually used for PHRATE */
    int method;          /* SWFS_COH_FFT or SWFS_COH_DIRECT, as used */
    size_t n_valid, n_nopower, n_nonfinite, n_tau0_beyond;
} swfs_coherence;

/* cube: nx x ny x nframes (frames at the WFS rate, >= 2), framedt > 0 [s]. opt may be NULL. */
int swfs_coherence_compute(const swfs_cplx *cube, double framedt, const swfs_coh_options *opt,
                           swfs_coherence **out);
void swfs_coherence_free(swfs_coherence *c);

/* SNR factor map at another exposure (<= max_lag frames) into out (nx x ny x 1). */
int swfs_coherence_snr_map(const swfs_coherence *c, double exposure, swfs_real *out);
/* S(T) for one normalized MCF gamma[0..nlag-1] at integer frame lags; NaN if T needs more
 * lags than given or gamma[0] is not finite. */
double swfs_coh_snr_factor(const swfs_complex *gamma, size_t nlag, double framedt, double exposure);

/* Apparent frozen-flow wind from PHRATE: weighted (by Phi_sp) least squares of
 * PHRATE(theta) = k theta.v over valid pixels off the star; needs PIXSCALE and TELDIAM.
 * v[0], v[1] along x (NAXIS1) and y [m/s]. The direction of fastest phase rotation is v. */
int swfs_coherence_fit_wind(const swfs_coherence *c, const swfs_geom *g, double v[2]);

/* Median of the finite values of a map (NaN if none); +Inf values count as large. */
double swfs_coh_median(const swfs_real *map);

/* COH.fits: empty primary HDU with summary keywords (FRAMEDT, NFRAMES, NLAGS, MAXLAG, NFIT,
 * EXPOSURE, NVALID, NNOPOWER, NNONFIN, NTAU0INF, COHMETH), geometry and provenance, then
 * MEAN_SP, TAU0 [s], TROT [s], PHRATE [rad/s], SNR_FACT (if computed, keyword EXPOSURE),
 * MCF (complex nx x ny x nlags) and LAGS (nlags x 1 image, [s]). Atomic (.part + rename).
 * g may be NULL. */
int swfs_coherence_write(const swfs_coherence *c, const char *path, const swfs_geom *g,
                         const char *const *prov, size_t nprov);

/* Read a WFS-rate complex speckle cube with FRAMEDT [s] (required: a clear error names the
 * file and keyword), the geometry keywords (missing ones NaN) and the science camera
 * exposure if the header gives it: CAMEXP [s], else FRATIO (WFS frames per camera frame)
 * times FRAMEDT; *exposure = 0 if neither. exposure may be NULL. */
int swfs_coherence_read_input(const char *path, swfs_cplx **cube, double *framedt, swfs_geom *g,
                              double *exposure);

/* eq:ExpLimit-Wind: the longest exposure before the wind's systematic phase rotation
 * reaches pi/2 at the exposure ends, T < D / (2 |theta/(lambda/D) . v|), for a radius
 * theta_lod [lambda/D] along the wind: D/(2 theta_lod wind) [s]. +Inf if theta or wind is 0. */
double swfs_exposure_limit_wind(double theta_lod, double diam, double wind);
/* Sec. 3.3 bandwidth limit: theta < (lambda/dlambda) lambda/D, returned in lambda/D. */
double swfs_bandwidth_radius(double frac_bw);

SWFS_END_DECLS

#endif

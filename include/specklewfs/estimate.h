/* The random-reference estimator (paper Sec. 2.2-2.4): per-pixel statistics of
 * synchronized science intensities I and computed speckle fields psi give the static
 * complex halo Psi, the scale factor g, the visibility and the SNR.
 *
 * Noise model: the per-frame noise variance in counts^2 is
 *   sigma_noise^2 = read_noise^2 + Phi_I / gain        (gain in e-/count; 0 = no photon term)
 * and is removed from sigma_I^2 before eq:scale-factor, as Sec. 2.3 requires.
 *
 * The scale factor. The paper's g (eq:scale-factor) is a per-pixel fourth root of a
 * difference of noisy variances: at low SNR the radicand is often <= 0 and, where it is
 * positive, biased high (only upward fluctuations survive; at the paper's sigma = 100 the
 * median valid g is twice the true one, which empties HALO_LF's amplitude). Beyond the
 * paper, g is regularized (g_smooth > 0, the default): the radicand is debiased
 * (|<psi' I>|^2 minus its noise power), then averaged over a Gaussian neighbourhood with
 * inverse-variance weights from a noise model that uses only well-measured quantities
 * (Phi_I, Phi_sp, sigma_sp^2, the camera noise), iterated three times; g = (that
 * average)^(1/4). The neighbourhood's size follows the information, pixel by pixel: on a
 * ladder of scales g_smooth 2^k (k in Z, from half a pixel to beyond the map) the largest
 * scale whose estimate stays inside the confidence intervals (SWFS_G_ICI_GAMMA standard
 * errors) of all smaller scales is kept (intersection of confidence intervals). Real
 * variation of g that the data resolve is kept; noise is averaged down.
 * GAIN holds the g used; GAIN_PIX the paper's per-pixel g.
 * g_smooth = 0 gives the paper's estimator exactly.
 *
 * Invalid pixels. VALID = 1 where the paper's per-pixel radicand and Phi_sp, sigma_sp^2 are
 * positive. Where the chosen average of the radicand is not positive, g is the map-wide
 * mean's; where that is not positive either, g falls back to the median of the valid
 * per-pixel g in the smallest square neighbourhood holding at least
 * SWFS_G_FALLBACK_MIN valid pixels (the whole map at most), so HALO and HALO_LF stay finite
 * and one bad pixel does not poison the pupil transform. Pixels with no usable frames or
 * no speckle power have HALO = HALO_LF = 0 and SNR = 0. */
#ifndef SWFS_ESTIMATE_H
#define SWFS_ESTIMATE_H

#include <stddef.h>

#include "specklewfs/accum.h"
#include "specklewfs/array.h"
#include "specklewfs/fits.h"

SWFS_BEGIN_DECLS

#define SWFS_G_FALLBACK_MIN 9
/* Half-width of the confidence intervals of the scale choice, in standard errors (a two-sided
 * 95 % interval). Measured over seeds, frame counts and noise levels in docs/estimator.md. */
#define SWFS_G_ICI_GAMMA 2.0

typedef struct swfs_noise {
    double read_noise; /* [counts] per frame, >= 0 */
    double gain;       /* [e-/count]; 0 disables the photon-noise term */
} swfs_noise;

typedef struct swfs_halo {
    size_t nx, ny;
    swfs_cplx *halo;     /* Psi, eq:TheAnswer */
    swfs_cplx *halo_lf;  /* eq:PSI-LowFreq */
    swfs_cplx *stab;     /* <psi' I>, eq:stabilized / eq:betterStabilized */
    swfs_real *gain;     /* g used for HALO, HALO_LF (regularized eq:scale-factor, see above) */
    swfs_real *gain_pix; /* the paper's per-pixel g (eq:scale-factor), NaN where undefined */
    swfs_real *visib;    /* eq:visibility */
    swfs_real *snr;      /* eq:SNR with Phi_noise = sigma_noise */
    swfs_real *mean_i;   /* Phi_I */
    swfs_real *var_i;    /* sigma_I^2 with the noise variance removed */
    swfs_real *mean_sp;  /* Phi_sp */
    swfs_real *var_sp;   /* sigma_sp^2 */
    swfs_real *stab_err; /* standard error of <psi' I> (complex Gaussian moments) */
    swfs_real *circ;     /* |<psi'^2>| / <|psi'|^2>, eq:zeroSqMean */
    swfs_real *valid;    /* 1 where g is defined */
    swfs_real *nframes;  /* frames used per pixel */
    /* Summary. */
    size_t npix, n_valid, n_bad_radicand, n_no_speckle, n_no_frames;
    double valid_fraction;
    double median_snr;   /* over valid pixels */
    double radicand_min; /* most negative radicand seen (diagnostic) */
    unsigned long long frames, skipped;
    swfs_noise noise;
    double g_smooth;     /* [pixels] regularization used (0 = the paper's per-pixel g) */
    size_t n_g_fallback; /* pixels whose g came from the local-median fallback */
    size_t n_var_below_noise; /* pixels whose intensity variance is significantly (3 sigma)
                                 below the noise model alone: the model is too large there */
    swfs_regress *reg;   /* regression statistics of the same frames (regress.h), what the joint
                            fit of pupil.h needs; NULL when the accumulator had none (owned) */
    swfs_real *resmean;  /* PUPN x PUPN [m]: the AO residual's time mean over the same frames as the
                            telemetry measures it (SPECKLES.fits RESMEAN, pipeline.h), which `pupil`
                            subtracts; NULL when the speckles came without it (owned) */
    char tiptilt[16];    /* the speckles' tip-tilt treatment ("exposure", "frame", "keep": SPECKLES.fits
                            and HALO.fits TIPTILT, `speckles --tiptilt`); "" when not known */
} swfs_halo;

#define SWFS_G_SMOOTH_DEFAULT 8.0 /* pixels: 2 lambda/D at the paper's 0.25 lambda/D sampling */

typedef struct swfs_estimate_options {
    double g_smooth; /* [pixels] Gaussian sigma of the g regularization; 0 = per-pixel (paper) */
} swfs_estimate_options;

/* opt may be NULL (defaults). */
int swfs_estimate(const swfs_accum *acc, const swfs_noise *noise, const swfs_estimate_options *opt, swfs_halo **out);
void swfs_halo_free(swfs_halo *h);

/* HALO.fits: an empty primary HDU with the summary keywords (NFRAMES, SKIPPED, NVALID,
 * VALIDFR, NBADRAD, NNOSP, MEDSNR, RDNOISE, GAIN), the geometry and provenance, then the
 * image extensions HALO, HALO_LF, STAB (complex), GAIN, VISIB, SNR, MEAN_I, VAR_I, MEAN_SP,
 * VAR_SP, STAB_ERR, CIRC, VALID, NFRAMES, GAIN_PIX (real), when h->reg is set REGSTATE (the
 * regression statistics, checkpoint.h's layout) and when h->resmean is set RESMEAN (PUPN x
 * PUPN [m]). Written atomically (.part + rename). */
int swfs_halo_write(const swfs_halo *h, const char *path, const swfs_geom *g, const char *const *prov,
                    size_t nprov);
/* Read back every extension present (HALO and HALO_LF are required). */
int swfs_halo_read(const char *path, swfs_halo **out, swfs_geom *g);
/* The extension RESMEAN of an open file (SPECKLES.fits, HALO.fits): one square map of finite
 * values [m]; errors name path. */
int swfs_resmean_read_ext(swfs_fits_in *f, const char *path, swfs_real **out);

/* Classic phase-shifting interferometry (Sec. 2.1), the baseline the random-reference
 * method generalizes: n interferograms I_k = |Psi + psi e^{i eta_k}|^2 of one pixel with
 * phase steps eta_k satisfying eq:zeroMeanUnitPhasors and eq:doublePhaseScrambledUnit.
 * Returns the stabilized product <I e^{i eta}> = Psi psi^* (eq:stabilizedInterferograms),
 * the subject phase given the reference phase (eq:subjectPhase), and the two intensity
 * solutions of eq:subjectIntensity (|Psi|^2 is one of them: the ambiguity is physical). */
typedef struct swfs_psi_result {
    swfs_complex stab;
    double subject_phase;
    double intensity_hi, intensity_lo;
} swfs_psi_result;

int swfs_phase_shift(const double *intensity, const double *eta, size_t n, double ref_phase,
                     swfs_psi_result *out);
/* Per-pixel version over images: intensities is n frames of npix. */
int swfs_phase_shift_map(const double *intensities, const double *eta, size_t n, size_t npix,
                         const double *ref_phase, swfs_complex *stab, double *subject_phase,
                         double *intensity_hi, double *intensity_lo);

SWFS_END_DECLS

#endif

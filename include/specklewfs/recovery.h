/* One noise level of the paper's Sec. 3 experiment, end to end: camera noise on the
 * simulated science cube -> streaming accumulators -> estimator -> pupil step ->
 * comparison with the injected NCP. Used by `specklewfs demo` and the end-to-end tests. */
#ifndef SWFS_RECOVERY_H
#define SWFS_RECOVERY_H

#include "specklewfs/sim.h"

SWFS_BEGIN_DECLS

typedef struct swfs_recovery {
    double sigma;          /* [counts] background noise of this level */
    double valid_fraction; /* pixels where g is defined */
    double bad_radicand;   /* fraction of pixels whose radicand of eq:scale-factor is <= 0 */
    double median_snr;     /* eq:SNR, valid pixels */
    /* recovered NCP error [m rms in the pupil, piston + tip/tilt removed]: */
    double err_paper;      /* the paper's formulae: per-pixel g, eq:PSI-LowFreq, full weight */
    double err_halo;       /* eq:TheAnswer with the regularized g, full weight */
    double err_lf;         /* eq:PSI-LowFreq with the regularized g, full weight */
    double err_lf_snr;     /* eq:PSI-LowFreq, regularized g, SNR (Wiener) weight: the moments'
                              default (the default before the joint fit) */
    double wfe_rms, wfe_pv, strehl; /* of the default estimate (the joint fit) */
    double err_fit;        /* the joint pupil-domain fit (pupil.h SWFS_PUPIL_FIT): the default */
    double fit_kappa;      /* its unexplained speckle power fraction */
} swfs_recovery;

/* dir: if not NULL, write science/speckles/truth/pupil.fits, halo.fits and wavefront.fits
 * (the joint fit's) there (the folder must exist). */
int swfs_recovery_run(const swfs_sim_result *sim, double sigma, uint64_t seed, const char *dir,
                      const char *const *prov, size_t nprov, swfs_recovery *out);

SWFS_END_DECLS

#endif

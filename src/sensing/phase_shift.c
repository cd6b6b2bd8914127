/* Classic phase-shifting interferometry, paper Sec. 2.1. */
#include "specklewfs/estimate.h"
#include "specklewfs/status.h"

#include <math.h>

int swfs_phase_shift(const double *intensity, const double *eta, size_t n, double ref_phase, swfs_psi_result *out)
{
    if (n < 3) return swfs_fail(SWFS_ERR_ARG, "phase shifting needs at least 3 phase steps, got %zu", n);
    double complex m1 = 0.0, m2 = 0.0;
    double mean_i = 0.0;
    for (size_t k = 0; k < n; k++) {
        if (!isfinite(intensity[k]) || !isfinite(eta[k]))
            return swfs_fail(SWFS_ERR_VALUE, "phase step %zu: intensity %g or phase %g is not finite", k,
                             intensity[k], eta[k]);
        m1 += cexp(I * eta[k]);
        m2 += cexp(2.0 * I * eta[k]);
        mean_i += intensity[k];
    }
    m1 /= (double)n;
    m2 /= (double)n;
    /* The steps must satisfy eq:zeroMeanUnitPhasors and eq:doublePhaseScrambledUnit,
     * otherwise <I e^{i eta}> is biased by the mean intensity and the conjugate term. */
    if (cabs(m1) > 1e-9 || cabs(m2) > 1e-9)
        return swfs_fail(SWFS_ERR_VALUE, "phase steps violate eq:zeroMeanUnitPhasors / eq:doublePhaseScrambledUnit: "
                         "|<e^{i eta}>| = %.3g, |<e^{2i eta}>| = %.3g (need 0, e.g. equally spaced steps, n >= 3)",
                         cabs(m1), cabs(m2));
    mean_i /= (double)n;
    double complex stab = 0.0;
    for (size_t k = 0; k < n; k++) stab += intensity[k] * cexp(I * eta[k]);
    stab /= (double)n; /* eq:stabilizedInterferograms: = Psi psi^* */
    out->stab = stab;
    out->subject_phase = carg(stab) + ref_phase; /* eq:subjectPhase */
    /* eq:subjectIntensity: two solutions, subject and reference are interchangeable. */
    double disc = mean_i * mean_i - 4.0 * (creal(stab) * creal(stab) + cimag(stab) * cimag(stab));
    if (disc < 0.0) disc = 0.0; /* noise can push it below zero at equal beam intensities */
    out->intensity_hi = 0.5 * mean_i + 0.5 * sqrt(disc);
    out->intensity_lo = 0.5 * mean_i - 0.5 * sqrt(disc);
    return SWFS_OK;
}

int swfs_phase_shift_map(const double *intensities, const double *eta, size_t n, size_t npix,
                         const double *ref_phase, double complex *stab, double *subject_phase,
                         double *intensity_hi, double *intensity_lo)
{
    double buf[64];
    if (n > sizeof buf / sizeof buf[0]) return swfs_fail(SWFS_ERR_ARG, "at most 64 phase steps, got %zu", n);
    for (size_t p = 0; p < npix; p++) {
        for (size_t k = 0; k < n; k++) buf[k] = intensities[k * npix + p];
        swfs_psi_result r;
        int rc = swfs_phase_shift(buf, eta, n, ref_phase ? ref_phase[p] : 0.0, &r);
        if (rc) return swfs_fail_context(rc, "pixel %zu", p);
        if (stab) stab[p] = r.stab;
        if (subject_phase) subject_phase[p] = r.subject_phase;
        if (intensity_hi) intensity_hi[p] = r.intensity_hi;
        if (intensity_lo) intensity_lo[p] = r.intensity_lo;
    }
    return SWFS_OK;
}

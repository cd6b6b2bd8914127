/* Von Karman turbulence phase screens by FFT, with optional subharmonics.
 *
 * A screen is a wavefront DISPLACEMENT map [m] (achromatic), n x n samples at pitch dx,
 * x fastest. Its statistics are those of the von Karman phase power spectrum at the
 * reference wavelength SWFS_SCREEN_LAMBDA_REF = 500 nm (where r0 is given):
 *
 *   Phi(f) = c_K r0^{-5/3} (f^2 + 1/L0^2)^{-11/6}   [rad^2 m^2],
 *   c_K = Gamma(11/6)^2 / (2 pi^{11/3}) [24/5 Gamma(6/5)]^{5/6} = 0.022896...
 *
 * which for r << L0 gives the Kolmogorov structure function 6.88 (r/r0)^{5/3}.
 *
 * Method: complex circular Gaussian coefficients c_k (E|c|^2 = 1) times
 * sqrt(2 Phi(f_k)) df on the FFT grid (df = 1/(n dx), f = 0 excluded), one inverse
 * (FFTW_BACKWARD) complex FFT; the real and imaginary parts are two independent screens.
 * Subharmonics (Lane et al. 1992; Johansson & Gavel 1994): 3 levels of the 8 neighbours
 * of f = 0 on grids of df/3, df/9, df/27, added as plane waves, restore the power below
 * df that a periodic FFT screen lacks (needed when the screen is not much larger than L0).
 *
 * Two interfaces: the one-shot swfs_screen_vonkarman(), and a plan-once generator whose
 * spectrum can be filtered between drawing and transforming (the AO residual model in
 * src/sim/ multiplies it by 1 - G(f) exp(-2 pi i f.s)). */
#ifndef SWFS_SCREEN_H
#define SWFS_SCREEN_H

#include <stddef.h>

#include "specklewfs/numeric.h"
#include "specklewfs/rng.h"

SWFS_BEGIN_DECLS

#define SWFS_SCREEN_LAMBDA_REF 500e-9 /* [m] wavelength at which r0 is given */
#define SWFS_SCREEN_NSUB 24           /* subharmonic plane waves: 3 levels x 8 */

typedef struct swfs_screen_params {
    size_t n;         /* samples across (square screen) */
    double dx;        /* [m] sample pitch */
    double r0;        /* [m] Fried length at 500 nm */
    double L0;        /* [m] outer scale; <= 0 or inf: Kolmogorov (then subharmonics matter) */
    int subharmonics; /* 0: FFT grid only; 1: add 3 levels of subharmonics */
} swfs_screen_params;

/* One-shot: out1 (and out2 unless NULL) receive independent displacement screens [m],
 * n*n each. Draws from rng. Plans and frees its own FFT. */
int swfs_screen_vonkarman(const swfs_screen_params *p, swfs_rng *rng, double *out1, double *out2);

/* Von Karman phase power spectrum [rad^2 m^2 at 500 nm] at spatial frequency f [1/m]. */
double swfs_vonkarman_psd(double f, double r0, double L0);

/* Theoretical phase structure function D(r) [rad^2 at 500 nm] for the von Karman
 * spectrum above (numerical Hankel integral, relative accuracy ~1e-5):
 *   D(r) = 4 pi int_0^inf f Phi(f) [1 - J0(2 pi f r)] df.
 * L0 <= 0 or inf gives Kolmogorov, 6.8839 (r/r0)^{5/3}. */
double swfs_vonkarman_structure(double r, double r0, double L0);

/* ---- plan-once generator ------------------------------------------------ */

typedef struct swfs_screen_gen swfs_screen_gen;

/* A subharmonic plane wave: screen += Re/Im of coef * exp(2 pi i (fx x + fy y)), x, y
 * measured from sample (0, 0). coef is in the same units as the spectrum. */
typedef struct swfs_screen_wave {
    double fx, fy;       /* [1/m] */
    swfs_complex coef; /* [m] */
} swfs_screen_wave;

swfs_screen_gen *swfs_screen_gen_create(const swfs_screen_params *p);
void swfs_screen_gen_free(swfs_screen_gen *g);
const swfs_screen_params *swfs_screen_gen_params(const swfs_screen_gen *g);
/* Worker threads for draw/finish/execute (default: online CPUs; <= 0: online CPUs).
 * Results do not depend on it: each row draws from its own stream seeded from rng. */
void swfs_screen_gen_set_threads(swfs_screen_gen *g, int threads);
/* Per-bin amplitude sqrt(2 Phi(f_k)) df lambda_ref / (2 pi) [m], n*n in FFTW order
 * (0 at f = 0): the drawn spectrum is this times a unit circular Gaussian. */
const double *swfs_screen_gen_amplitude(const swfs_screen_gen *g);

/* Draw a new random spectrum (and subharmonic waves) from rng. Nothing is transformed. */
int swfs_screen_gen_draw(swfs_screen_gen *g, swfs_rng *rng);
/* The drawn spectrum, n*n complex in FFTW order: element (kx, ky) at [ky*n + kx] holds the
 * coefficient [m] of frequency (kx', ky') / (n dx) with k' = k for k < n/2, k - n otherwise.
 * A caller may multiply it by a filter before swfs_screen_gen_finish(). */
swfs_complex *swfs_screen_gen_spectrum(swfs_screen_gen *g);
/* The subharmonic waves (count SWFS_SCREEN_NSUB when enabled, else 0), also filterable. */
swfs_screen_wave *swfs_screen_gen_waves(swfs_screen_gen *g, size_t *count);
/* Inverse FFT of the (filtered) spectrum plus the waves: out1 = real part, out2 =
 * imaginary part (independent screens); out2 may be NULL. The spectrum is destroyed. */
int swfs_screen_gen_finish(swfs_screen_gen *g, double *out1, double *out2);
/* Raw in-place inverse FFT (FFTW_BACKWARD, unnormalized) of the spectrum buffer, for
 * callers that need a transform of their own data on the same grid (e.g. an aperture
 * transfer function). */
void swfs_screen_gen_execute(swfs_screen_gen *g);

SWFS_END_DECLS

#endif

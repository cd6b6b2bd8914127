/* The AO telemetry model: actuator geometry, a Shack-Hartmann wavefront sensor on the
 * pupil grid, the interaction matrix and the regularized SVD reconstructor
 * (paper Sec. 4.1 and 4.4).
 *
 * Units (docs/telemetry.md):
 *  - slopes are wavefront tilt angles [rad] = mean dz/dx over a subaperture, z the
 *    wavefront displacement [m]. The slopes vector holds all nsub*nsub x slopes (subaperture
 *    (a, b) at index b*nsub + a, a along x) then all y slopes: 2 nsub^2 values (288 for
 *    12 x 12). Unilluminated subapertures report 0, as the MMT's quad-cells do;
 *  - the reconstructor W is nact x nslopes, row-major, [m per rad]: z_act = W s;
 *  - actuator positions are (x, y) pairs [m] in the pupil frame of docs/conventions.md.
 *
 * The DM surface (and the reconstruction's wavefront) is the Clough-Tocher interpolation
 * of the actuator values (interp.h), T z_act on the pupil grid, so the interaction matrix
 * is D = S T with S the Shack-Hartmann operator: the reconstructor is consistent with the
 * interpolation that turns its output into a wavefront. */
#ifndef SWFS_WFS_H
#define SWFS_WFS_H

#include <stddef.h>

#include "specklewfs/sparse.h"

SWFS_BEGIN_DECLS

/* ---- actuator geometry ------------------------------------------------ */

/* Hexapolar layout: a centre actuator and rings at radius k*pitch holding 6k actuators,
 * out to the first ring whose polygon covers the pupil radius diam/2 + margin (so the
 * Delaunay hull covers every illuminated pupil sample). *xy: 2*nact doubles (free()).
 * At most SWFS_HEXAPOLAR_MAX_RINGS rings (SWFS_ERR_ARG naming the count otherwise). */
#define SWFS_HEXAPOLAR_MAX_RINGS 200
int swfs_actuators_hexapolar(double diam, double pitch, double margin, double **xy, size_t *nact);
/* A square grid of pitch [m] centred on the pupil, clipped to the circle of radius diam/2 +
 * margin: the layout of most deformable mirrors. */
int swfs_actuators_square(double diam, double pitch, double margin, double **xy, size_t *nact);

/* ---- Shack-Hartmann --------------------------------------------------- */

typedef struct swfs_shwfs {
    size_t nsub;           /* subapertures across the diameter */
    size_t nslopes;        /* 2 nsub^2 */
    size_t npup;           /* pupil grid */
    double pupdx, diam;
    swfs_sparse *S;        /* nslopes x npup^2: slopes = S z */
    unsigned char *valid;  /* nsub^2: 1 for an illuminated subaperture */
    size_t nvalid;
} swfs_shwfs;

/* Subaperture (a, b) covers x in [-D/2 + a d, -D/2 + (a+1) d), d = diam/nsub (same in y).
 * Its x slope is the mean of (z[p+1,q] - z[p,q]) / pupdx over the grid pairs whose two
 * samples are illuminated (mask > 0.5) and whose midpoint lies in the subaperture (y
 * likewise). A subaperture is valid when it holds at least min_illum (0..1) of the pairs
 * a fully illuminated one holds. */
int swfs_shwfs_create(swfs_shwfs **out, size_t nsub, double diam, const double *mask, size_t npup, double pupdx,
                      double min_illum);
/* The same with the subapertures the AO system uses given (valid: nsub^2 flags, subaperture
 * (a, b) at b nsub + a; NULL = the min_illum 0.5 rule): a used subaperture needs at least one
 * pair of illuminated samples (SWFS_ERR_VALUE naming it otherwise), an unused one reports 0. */
int swfs_shwfs_create_valid(swfs_shwfs **out, size_t nsub, double diam, const double *mask, size_t npup,
                            double pupdx, const unsigned char *valid);
void swfs_shwfs_free(swfs_shwfs *w);
/* slopes (nslopes) [rad] of the displacement map z (npup^2) [m]. */
void swfs_shwfs_measure(const swfs_shwfs *w, const double *z, double *slopes);

/* D = S T (nslopes x nact, row-major) [rad per m] for the interpolation T (npup^2 x nact). */
int swfs_interaction_matrix(const swfs_shwfs *w, const swfs_sparse *T, double **D);

/* ---- DM modes ----------------------------------------------------------- */

/* "Lowest-energy mechanical modes" of the DM (Sec. 4.1): actuator vectors v solving
 * B v = lambda M v, B the bending energy sum |laplacian(T v)|^2 and M the mean square
 * sum |T v|^2 over the pupil grid (mask > 0), in increasing energy: piston, tip, tilt
 * (lambda = 0), then focus and astigmatism, and so on. modes: nact x nact, column k =
 * mode k (row-major, modes[a * nact + k]), M-orthonormal. Actuators that do not reach
 * the pupil end up in the last modes. */
int swfs_dm_modes(const swfs_sparse *T, const double *mask, size_t npup, double **modes);

/* ---- slopes' layouts ------------------------------------------------------ */

/* The used subapertures' slopes (valid: nsub^2 flags, subaperture (a, b) at b nsub + a): their
 * indices in the full layout, x slopes in index order then y slopes, into *cols (malloc'd,
 * 2 nvalid of them: the used-only layout's column k is full column (*cols)[k]). */
int swfs_slopes_used_cols(const unsigned char *valid, size_t nsub, size_t **cols, size_t *ncols);

/* rows x nc (row-major, the used-only layout's columns cols[0..nc)) -> rows x nfull, the other
 * columns 0 (malloc'd; NULL when out of memory or too large). */
double *swfs_slopes_expand_cols(const double *a, size_t rows, size_t nc, const size_t *cols, size_t nfull);

/* ---- tip-tilt --------------------------------------------------------- */

/* Subtract the mean x and the mean y slope over the valid subapertures (valid may be
 * NULL: all), leaving invalid entries 0 (Sec. 4.4: "we estimated and removed the mean x
 * and y slopes"). */
void swfs_slopes_remove_tiptilt(double *s, size_t nslopes, const unsigned char *valid);

/* ---- reconstructor ---------------------------------------------------- */

/* A space-time reconstructor: frame t's wavefront from the slopes of frames t + lags[k]
 * (docs/telemetry.md, "A space-time learned map"). At most this many lags. */
#define SWFS_RECON_MAXLAGS 16

typedef struct swfs_recon {
    size_t nact, nslopes;
    double *W;      /* nact x nslopes, row-major [m/rad]; a space-time one's nslopes is the
                       per-frame slopes times nlags, frame t + lags[k]'s in columns
                       [k ns, (k + 1) ns) (swfs_slopes_stack's layout) */
    size_t nmodes;  /* modes kept */
    double *sv;     /* all singular values of D, descending (min(nact, nslopes)); NULL if loaded */
    size_t nsv;
    double noise_var; /* swfs_recon_map: the slope noise variance used [rad^2]; 0 otherwise */
    double dof;       /* swfs_recon_map: sum of the modal Wiener factors (effective modes) */
    double l0;          /* swfs_recon_vk: the outer scale used [m] (fitted when asked for 0) */
    double prior_scale; /* swfs_recon_vk: the prior's scale c [m^2] */
    size_t nlags;       /* 0: one frame's slopes (every reconstructor but a space-time one);
                           else the lags [WFS frames] of the stacked input, one of them 0 */
    long lags[SWFS_RECON_MAXLAGS];
    double *oxy;        /* NULL: the outputs are the DM's actuators (the positions speckles is given);
                           else the map's own output points (nact x 2: x, y [m], pupil frame), e.g.
                           teach's grid finer than the DM's (docs/telemetry.md): speckles interpolates
                           the wavefront from them. File: extension OUTXY (NAXIS1 = 2, NAXIS2 = nact) */
} swfs_recon;

/* The lags of a space-time reconstructor: "0,-25,25" -> lags (at most SWFS_RECON_MAXLAGS,
 * distinct, one of them 0, each within +-100000 WFS frames). `what` names the source in the
 * message. */
int swfs_lags_parse(const char *text, long *lags, size_t *nlags, const char *what);
/* The same checks on lags already parsed (a file's keywords). */
int swfs_lags_check(const long *lags, size_t nlags, const char *what);
/* The largest |lag| [WFS frames]: how far the stacked input reaches (0 for none). */
long swfs_lags_max_abs(const long *lags, size_t nlags);
/* out (count x nslopes nlags, row-major) = the slopes of frames first + t + lags[k] of
 * s (nframes x nslopes) for t < count, each frame index clamped into [0, nframes): the
 * space-time reconstructor's input. The frames beyond a data set's ends repeat its edge. */
void swfs_slopes_stack(const double *s, size_t nframes, size_t nslopes, const long *lags, size_t nlags, size_t first,
                       size_t count, double *out);
/* The slopes' temporal correlation at each lag: r[k] = <s(t) . s(t + |lags[k]|)> / <|s(t)|^2>
 * over the slopes with any signal (x in the first half of a frame, y in the second), each
 * frame's mean x and y slopes and each slope's time mean taken out (1 at lag 0; NaN for a lag
 * beyond the series). It is what a space-time map learned on simulated loops assumes of the
 * observation: a layer the loops lack, or another speed, changes it (docs/telemetry.md). */
int swfs_slopes_lag_correlation(const double *s, size_t nframes, size_t nslopes, const long *lags, size_t nlags,
                                double *r);

/* Truncated pseudo-inverse of D (nslopes x nact) by LAPACKE SVD: keep mode i when
 * sv[i] > rcond * sv[0] and i < max_modes (0 = no count limit). This is the "better
 * reconstructor" of Sec. 4.4, or the AO loop's conservative modal filter with few modes. */
int swfs_recon_svd(const double *D, size_t nslopes, size_t nact, double rcond, size_t max_modes,
                   swfs_recon **out);
/* MAP (Wiener) reconstructor with the prior learned from the telemetry itself: with
 * D = U S V^T and white slope noise of variance sigma^2 on the valid slopes, the slopes'
 * projection on mode i, y_i = u_i^T s, has mean square P_i = s_i^2 a_i + sigma^2 (a_i the
 * prior variance of v_i^T z). a_i = (P_i - sigma^2)_+ / s_i^2 from the frames, capped at
 * the largest a_i of the well-sensed modes (s_i >= 0.1 s_0), gives the MAP reconstructor
 * of the Gaussian prior C_z = V diag(a) V^T,
 *   W = (D^T D / sigma^2 + C_z^-1)^-1 D^T / sigma^2 = V diag(g_i) U^T,
 *   g_i = s_i a_i / (s_i^2 a_i + sigma^2)  (= (1 - sigma^2 / P_i) / s_i below the cap),
 * a smooth roll-off instead of a hard singular-value cut. slopes: nframes x nslopes
 * (row-major, consecutive WFS frames); noise_var > 0 fixes sigma^2 [rad^2], noise_var
 * <= 0 estimates it (swfs_slopes_noise_var). D's rows of unilluminated subapertures must
 * be 0 (swfs_interaction_matrix), as the slopes there. r->noise_var, r->dof report the
 * sigma^2 used and sum g_i s_i (effective modes). */
int swfs_recon_map(const double *D, size_t nslopes, size_t nact, const double *slopes, size_t nframes,
                   double noise_var, swfs_recon **out);
/* Normalized von Karman phase covariance of the nact actuators at xy (2 x nact [m]):
 * C[a][b] = f(2 pi r_ab / L0) / f(0), f(x) = x^(5/6) K_5/6(x), r_ab the actuator
 * separation, L0 > 0 the outer scale [m] (C[a][a] = 1). C: nact x nact, row-major. */
int swfs_vk_covariance(const double *xy, size_t nact, double L0, double *C);
/* MAP reconstructor with a spatial prior: C_z = c C_vk (swfs_vk_covariance of the actuator
 * positions xy with outer scale L0 [m]) and white slope noise sigma^2 on the valid slopes,
 *   W = C_z D^T (D C_z D^T + sigma^2 I)^-1   (one Cholesky solve, LAPACKE dposv).
 * The scale c is learned from the telemetry: with the mean x/y slope over the valid
 * slopes (rows of D not all 0) removed frame by frame (tip-tilt: vibration, not
 * turbulence), the slopes' mean square per frame equals c tr(P D C_vk D^T P) + (nvs - 2)
 * sigma^2 (nvs valid slopes). slopes: nframes x nslopes (nframes >= 8); noise_var > 0 fixes
 * sigma^2 [rad^2], <= 0 estimates it (swfs_slopes_noise_var: noise + aliasing).
 * L0 <= 0: L0, and with noise_var <= 0 also c and sigma^2, by maximum likelihood from the
 * slopes (swfs_vk_fit_slopes) instead.
 * r->noise_var: the sigma^2 used; r->dof = tr(W D) (effective modes); r->nmodes = nact;
 * r->l0, r->prior_scale: the L0 and c used. */
int swfs_recon_vk(const double *D, size_t nslopes, size_t nact, const double *xy, double L0, const double *slopes,
                  size_t nframes, double noise_var, swfs_recon **out);
/* The von Karman prior of swfs_recon_vk fitted to the telemetry by maximum likelihood: the
 * valid slopes of every frame, each axis' mean removed, modelled as N(0, P (c D C_vk(L0) D^T
 * + sigma^2 I) P); L0 over octaves of the actuator extent (1/8 to 32) refined by golden
 * section, c and sigma^2 profiled exactly (src/wfs/vkfit.c). slopes: nframes >= 8 frames of
 * nslopes; xy: 2 x nact actuator positions [m]. */
typedef struct swfs_vk_fit {
    double L0;        /* [m] effective outer scale of the AO residual */
    double scale;     /* c [m^2]: the prior's variance per actuator */
    double noise_var; /* sigma^2 [rad^2]: white noise plus aliasing per slope */
    double loglik;    /* per frame, at the optimum */
    size_t nvalid;    /* valid slopes used */
} swfs_vk_fit;
int swfs_vk_fit_slopes(const double *D, size_t nslopes, size_t nact, const double *xy, const double *slopes,
                       size_t nframes, swfs_vk_fit *out);
/* Effective slope noise variance per slope [rad^2] of slopes (nframes x nslopes, nframes
 * >= 8): the mean square of the slopes outside the column space of D over the valid slopes
 * (rows of D not all 0), per degree of freedom -- white noise plus whatever the DM cannot
 * make (aliasing), both noise to a reconstructor. If D spans every valid slope: for every
 * mode, the temporal structure function d(tau) of y_i extrapolated to tau = 0 from
 * tau = 1, 2, (2 d(1) - d(2)) / 2, the median over the modes. */
int swfs_slopes_noise_var(const double *D, size_t nslopes, size_t nact, const double *slopes, size_t nframes,
                          double *noise_var);
/* The white measurement noise of a Shack-Hartmann's slopes, from the slopes alone: the
 * circulation of the slopes over every 2 x 2 cell of used subapertures (which a wavefront
 * hardly makes and the loop never feeds back), its temporal structure function over lags of
 * 1, 2 and 3 WFS frames extrapolated to 0 by a quadratic in the lag squared
 * (src/wfs/slope_noise.c): noise is new every frame, the turbulence's share changes smoothly.
 * slopes: nframes >= 16 consecutive frames of nslopes, the full layout (2 nsub^2: x then y,
 * row-major nsub x nsub) or, with valid given, the valid subapertures' only (2 nvalid, in
 * the map's order), as swfs_wind_from_slopes takes them; another width is SWFS_ERR_SHAPE.
 * valid: nsub^2 flags of the used subapertures, or NULL (those whose slopes vary). *var: the variance per slope [rad^2] (0
 * where the extrapolation leaves none); *ncells (or NULL): the cells it was measured over;
 * *slope_var (or NULL): the slopes' own variance per used slope [rad^2], each slope's time
 * mean and each frame's mean x and y slope (tip-tilt) removed, what *var is a share of.
 * Not finite slopes, or no cell of four used subapertures, are refused. */
int swfs_slopes_white_noise(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                            const unsigned char *valid, double *var, size_t *ncells, double *slope_var);
/* The same cells' curl, both ways: *white as swfs_slopes_white_noise's *var, and *total its
 * whole variance over the frames (each cell's time mean removed) over 8 [rad^2 per slope]:
 * white noise and the part of the residual the subapertures average unevenly (aliasing)
 * together, the power a gradient model cannot make. On a Shack-Hartmann's own slopes it is
 * what the vk and MAP maps' noise estimate finds outside the model's span (swfs_recon_map;
 * docs/telemetry.md: 1.73e-7 against 1.85e-7 rad on cli_modal's data), and unlike that it
 * survives a projection onto a modal control matrix's rows (modal-slopes: 1.70e-7). */
int swfs_slopes_curl_noise(const double *slopes, size_t nframes, size_t nslopes, size_t nsub,
                           const unsigned char *valid, double *white, double *total);
/* Modal reconstructor: W = V_K pinv(D V_K) over modes first..first+K-1 of the nact x nact
 * basis `modes` (swfs_dm_modes; first = 1 skips piston): the AO loop's modal filter.
 * swfs_recon_modal_factors gives its two factors instead: *VK (nact x K, row-major) and *P
 * (K x nslopes, its nmodes and singular values), W = VK P; applying them costs K (nact +
 * nslopes) per frame against W's nact nslopes. */
int swfs_recon_modal_factors(const double *D, size_t nslopes, size_t nact, const double *modes, size_t first, size_t K,
                             double **VK, swfs_recon **P);
/* W = VK P as a reconstructor (P's nmodes and singular values; nact rows). */
int swfs_recon_modal_compose(const double *VK, const swfs_recon *P, size_t nact, swfs_recon **out);
int swfs_recon_modal(const double *D, size_t nslopes, size_t nact, const double *modes, size_t first, size_t K,
                     swfs_recon **out);
void swfs_recon_free(swfs_recon *r);

/* A reconstructor learned from simulated closed loops of the system's geometry: the
 * least-squares map from one frame's slopes to the true residual wavefront on the actuators
 * (simulate mode=timeseries export_truth=1: slopes_NNN.fits and truewf_NNN.fits), piston
 * removed (remove_mean), over all the frames added,
 *   W = Z^T S (S^T S + lam I)^-1,  lam = ridge x the mean diagonal of S^T S,
 * over the slopes with any signal (the others get 0). It is the per-frame conditional mean of
 * the residual under the simulated loops' statistics: the closed loop's own residual spectrum
 * and what the slopes' aliases do in it, which the von Karman prior of swfs_recon_vk does not
 * know (docs/telemetry.md: trained on other systems of the same geometry it beat vk on 22 of
 * the matrix's 24 runs, and lost by 0.1-0.2 nm on the other two). The ridge only conditions
 * the solve (1e-6 and 1e-4 gave the same NCP errors to 0.3 nm). Accumulate with add (frames
 * x nslopes and frames x nact, row-major), then solve; add and add_lagged allocate their
 * scratch once per call (a file's frames: its used slopes, add_lagged's stacked block). The
 * cross product S^T Z is summed in single precision over at most 4096 frames (SGEMM: half DGEMM's time; a relative rounding of about 4e-6, which scales
 * the map linearly) and in double beyond; S^T S stays double, since its inverse with so
 * small a ridge would amplify single precision's rounding. The misfits the sums give (the
 * training misfit, the held-out check) are the truth's power less a cross term: good to
 * about 1e-5 of the truth's power. The sums hold only the slopes that carried signal in some
 * frame added (unilluminated subapertures' slopes are exactly 0, and so are their rows of
 * S^T S and S^T Z): every product runs over those, about 0.6 of the full layout's work for
 * S^T S (a 24 x 24 Shack-Hartmann uses 444 of its 576 subapertures); a slope that comes alive
 * in a later file grows the sums (its entries over the earlier frames 0). */
typedef struct swfs_recon_learner swfs_recon_learner;
typedef struct swfs_recon_learn_info {
    size_t nframes;      /* frames learned from */
    size_t nslopes_seen; /* slopes with signal (the map's columns) */
    double truth_rms;    /* [m] rms of the truth per actuator, piston removed (remove_mean) */
    double misfit_rms;   /* [m] rms of truth - W s over the training frames */
} swfs_recon_learn_info;
#define SWFS_RECON_LEARN_RIDGE 1e-6
/* remove_mean: 1 when the truth holds actuator values (their mean is piston, which no WFS
 * sees: taken out of every frame), 0 when it holds modal coefficients (no piston among them:
 * learned as they are; the map is then a control matrix for speckles --basis --control). */
int swfs_recon_learner_new(size_t nslopes, size_t nact, int remove_mean, swfs_recon_learner **out);
void swfs_recon_learner_free(swfs_recon_learner *l);
int swfs_recon_learner_add(swfs_recon_learner *l, const double *slopes, const double *truth, size_t nframes);
/* The same sums for a space-time learner (nslopes = ns0 x nl) from one file's slopes s
 * (n x ns0) and truth, as if s were stacked at the lags (swfs_slopes_stack, clamped at the
 * file's ends) and given to add, at a fraction of the work: the inner frames' products of
 * the file with itself at each distinct lag difference, shared by the lag pairs at that
 * difference, and the clamped frames stacked. It allocates its scratch (the file's used
 * slopes, a block of them stacked, two products of them with themselves) once per call. */
int swfs_recon_learner_add_lagged(swfs_recon_learner *l, const double *s, size_t ns0, const double *truth, size_t n,
                                  const long *lags, size_t nl);
size_t swfs_recon_learner_frames(const swfs_recon_learner *l);
int swfs_recon_learner_solve(const swfs_recon_learner *l, double ridge, swfs_recon **out, swfs_recon_learn_info *info);
/* The map of lag block k alone (the lags' order of add_lagged; one frame's slopes in, nact
 * out), from the same sums: with the block of lag 0 the per-frame map of the same frames, as a
 * learner given the frames unstacked would solve it (lag 0 is never clamped: the block's
 * sums are that learner's, to the single-precision rounding of S^T Z's summation order), and
 * its ridge on that block's own mean diagonal. info: that map's training misfit. */
/* The map of all's sums less part's (part: the sums of some of all's frames, e.g. one data
 * set's): what the other frames alone learn, without reading them again (leave-one-out). */
int swfs_recon_learner_solve_without(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                                     swfs_recon **out);
int swfs_recon_learner_solve_lag(const swfs_recon_learner *l, size_t k, double ridge, swfs_recon **out,
                                 swfs_recon_learn_info *info);
/* The held-out check: the map learned from the sums of `all` less those of `part` (the frames
 * of one data set, added to a learner of their own), and its mean square misfit per actuator
 * and frame on part's frames, with the mean square of part's truth (piston removed). Leave
 * one data set out in turn to see whether the simulated conditions cover each other. */
int swfs_recon_learner_heldout(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                               double *misfit2, double *truth2);
/* The same over the outputs a with keep[a] (NULL: all), and scaled2 (or NULL): the misfit of
 * the map's output scaled by the one factor that fits part's truth best over them, |z|^2 -
 * (z.Ws)^2 / |Ws|^2 per output and frame: 1 - rho^2 of the truth's power, rho the correlation
 * of map and truth, which a scale fitted downstream (the estimator's g) leaves; never above
 * truth2. */
int swfs_recon_learner_heldout_on(const swfs_recon_learner *all, const swfs_recon_learner *part, double ridge,
                                  const unsigned char *keep, double *misfit2, double *truth2, double *scaled2);
/* The same check with the part's frames in sub-parts as well (subs: nsubs learners, each the
 * sums of some of part's frames, together at most part's): sub_misfit2[k] the map's mean square
 * misfit on subs[k] alone, over the same outputs. The map is solved once; a part dealt into
 * data sets tells the held-out misfit of each (teach's learning curve pairs them). */
int swfs_recon_learner_heldout_split(const swfs_recon_learner *all, const swfs_recon_learner *part,
                                     const swfs_recon_learner *const *subs, size_t nsubs, double ridge,
                                     const unsigned char *keep, double *misfit2, double *truth2, double *scaled2,
                                     double *sub_misfit2);
void swfs_recon_learner_reset(swfs_recon_learner *l); /* no frames, the shapes kept (and the prior) */
/* A prior map w0 (nact x nslopes, the learner's shapes; NULL: none) that every later solve
 * shrinks toward: W = argmin sum |z - W s|^2 + lam |W - W0|^2, (G + lam I) A = H + lam A0,
 * lam = ridge x the mean diagonal of S^T S as before; the inputs without signal keep the
 * prior's columns. With remove_mean, each input's mean over the outputs (piston) comes out of
 * the copy kept. The ridge then says how far the frames may move the map from the prior: a
 * small one (the default 1e-6) leaves the least-squares map, a large one the prior. For a map
 * made some other way (the MAP of an interaction matrix) corrected by loops too few for a map
 * of their own. The held-out checks of the learner's sums use it too; a held-out part's own
 * learner needs none. */
int swfs_recon_learner_set_prior(swfs_recon_learner *l, const swfs_recon *w0);
/* dst += src: the sums of both sets of frames, as if src's had been added to dst (the inputs
 * with signal the union of both; the same inputs, lags and outputs). For learning curves: a
 * map from some parts' frames checked on the others' (swfs_recon_learner_heldout). */
int swfs_recon_learner_merge(swfs_recon_learner *dst, const swfs_recon_learner *src);

/* W <- W (I - M) with M the mean-slope (tip-tilt) projector over the valid subapertures:
 * the reconstructor then ignores tip-tilt exactly, so no separate removal step is needed. */
int swfs_recon_project_tiptilt(swfs_recon *r, const unsigned char *valid);
/* W <- W (I - M) + C G: the mean slopes G (per axis over the valid subapertures) projected
 * out, then put back as the plane they measure through the actuators xy (2 x nact [m]): the
 * reconstructed tilt is the mean slope plus the Z-tilt of the rest, and nothing else depends
 * on the mean slopes. Idempotent. */
int swfs_recon_tilt_as_mean_slopes(swfs_recon *r, const unsigned char *valid, const double *xy);
/* z = W s. */
void swfs_recon_apply(const swfs_recon *r, const double *slopes, double *z);
/* FITS: NAXIS1 = nslopes, NAXIS2 = nact, BUNIT m/rad. A space-time reconstructor is a cube:
 * NAXIS1 = the per-frame slopes, NAXIS2 = nact, NAXIS3 = nlags, plane k the map of the
 * slopes of frame t + LAGk (keywords NLAGS, LAG1 .. LAGn). */
int swfs_recon_write(const swfs_recon *r, const char *path);
/* The same image (and NLAGS, LAGk) as the current HDU of a file being written (fits.h), for a
 * writer that adds keywords of its own. */
struct swfs_fits_out;
int swfs_recon_write_hdu(struct swfs_fits_out *f, const swfs_recon *r);
/* Extension OUTXY: n points (NAXIS1 = 2: x, y; NAXIS2 = n [m], float64), BUNIT and `what`
 * as its comment; written after the previous HDU's keywords. The layout swfs_outxy_read reads
 * (a map's output points, the points truewf_NNN.fits were fitted on). */
int swfs_outxy_write(struct swfs_fits_out *f, const double *xy, size_t n, const char *what);
/* A map's own output points (r->oxy) as extension OUTXY (NAXIS1 = 2, NAXIS2 = nact [m]),
 * written after the primary HDU's keywords; nothing when r->oxy is NULL. */
int swfs_recon_write_outxy(struct swfs_fits_out *f, const swfs_recon *r);
/* The map and, when the file has extension OUTXY, its output points (r->oxy; checked to be
 * nact finite (x, y) pairs). */
int swfs_recon_read(const char *path, swfs_recon **out);
/* The lags of a cube of nz planes, one per lag, from its primary header (NLAGS = nz, LAG1 ..
 * LAGnz, swfs_lags_check'd) into lags (nz long): a space-time map's, or a control matrix's. */
int swfs_lags_read(const char *path, size_t nz, long *lags);
/* Extension OUTXY of `path` (NAXIS1 = 2, NAXIS2 = n finite (x, y) [m]) into *xy (malloc'd),
 * or *xy = NULL when the file has none: a map's output points, or those truewf_NNN.fits were
 * fitted on (simulate's truth_actuators). */
int swfs_outxy_read(const char *path, size_t n, double **xy);
/* Actuators: NAXIS1 = 2 (x, y), NAXIS2 = nact [m]. */
int swfs_actuators_write(const double *xy, size_t nact, const char *path);
int swfs_actuators_read(const char *path, double **xy, size_t *nact);
/* The AO system's valid-subaperture map: a square nsub x nsub image, nonzero = used
 * (subaperture (a, b) = pixel (x, y)); *map: nsub^2 flags (free()), *nvalid the used count. */
int swfs_valid_map_read(const char *path, unsigned char **map, size_t *nsub, size_t *nvalid);

SWFS_END_DECLS

#endif

/* Synchronizing WFS telemetry and science-camera cubes (paper Sec. 4.2).
 *
 * Time is counted in WFS frames: WFS frame k of a telemetry file covers [k, k+1). Camera
 * exposure j of a cube covers [s + j r, s + (j+1) r), r = <t_sci/t_wfs> (not an integer),
 * s = logged - lag: the handshake log gives the WFS frame `logged` current when the cube
 * started, late by an unknown lag. The star's track (peak x, y per exposure, from reduce)
 * follows the residual tip-tilt, i.e. the mean x/y slopes averaged over each exposure;
 * maximizing the correlation between the two over (r, lag), for all four pairings of
 * camera axis and slope axis (signs from the correlation), gives r and the lag.
 *
 * File formats (docs/telemetry.md): the handshake log and the timing table are small
 * text files; see swfs_handshake_read and swfs_timing_write. */
#ifndef SWFS_SYNC_H
#define SWFS_SYNC_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

/* ---- handshake log -------------------------------------------------------- */

#define SWFS_SYNC_NAME 512

typedef struct swfs_handshake {
    char camera[SWFS_SYNC_NAME]; /* camera cube file (base name) */
    char slopes[SWFS_SYNC_NAME]; /* telemetry file being written when it started */
    long frame;                  /* logged WFS frame in that file (0-based) */
} swfs_handshake;

/* Text, one cube per line: "CAMERA_FILE SLOPES_FILE WFS_FRAME"; '#' starts a comment. */
int swfs_handshake_read(const char *path, swfs_handshake **out, size_t *n);
int swfs_handshake_write(const char *path, const swfs_handshake *h, size_t n);

/* ---- estimation ------------------------------------------------------------ */

typedef struct swfs_sync_cube {
    size_t nframes;         /* exposures in the cube */
    const double *tx, *ty;  /* star position per exposure [pixels] */
    const double *mx, *my;  /* mean x / y slope of every WFS frame of its telemetry file */
    size_t nwfs;            /* frames in that file */
    double logged;          /* handshake frame */
} swfs_sync_cube;

typedef struct swfs_sync_params {
    double ratio_min, ratio_max; /* search range of <t_sci/t_wfs> (defaults 2, 12; swfs_sync_run
                                    takes ratio_max = 0 as "from the handshake log") */
    double lag_min, lag_max;     /* search range of the lag [WFS frames] (-20, 20) */
    double ratio_step, lag_step; /* coarse grid (0.01, 0.5); refined 20x around the peak */
} swfs_sync_params;

void swfs_sync_params_default(swfs_sync_params *p);
/* The search ranges and steps: valid, and a coarse grid of at most SWFS_SYNC_MAX_GRID
 * (ratio, lag) points (SWFS_ERR_ARG naming the count otherwise). */
#define SWFS_SYNC_MAX_GRID 1000000
/* The ratio search's end when nothing bounds it (swfs_sync_run: no two cubes in one file). */
#define SWFS_SYNC_RATIO_MAX_FALLBACK 12.0
/* swfs_sync_run's least ratio from the camera's EXPTIME starts this many coarse ratio steps
 * below EXPTIME x WFSRATE: room for the fit's scatter about a ratio at that bound (a camera
 * without dead time has it there). The refit over joined files searches the same +-5 steps
 * about the first fit; the matrix's fits lie within 0.002 of the true ratio, data made
 * without specklewfs within 0.04 (docs/telemetry.md). */
#define SWFS_SYNC_EXPTIME_STEPS 5
int swfs_sync_params_check(const swfs_sync_params *p);
/* The coarse grid's ratio and lag counts, as the search visits them. */
void swfs_sync_grid_size(const swfs_sync_params *p, double *nratios, double *nlags);

typedef struct swfs_sync_result {
    double ratio, ratio_err; /* <t_sci/t_wfs> and its 1-sigma uncertainty (scatter of the
                                per-cube estimates / sqrt(n); the coarse grid's ratio_step if
                                fewer than 3 cubes have half their exposures in their file) */
    double lag;              /* [WFS frames] start = logged - lag */
    int swap;                /* 0: camera x <- slope x, y <- y; 1: x <- y, y <- x */
    int sign_x, sign_y;      /* +1 / -1 for the camera x and y axes */
    double corr_x, corr_y;   /* correlations of the chosen pairing */
    double corr4[4];         /* |corr| of (tx, mx), (tx, my), (ty, mx), (ty, my) at the optimum */
    size_t ncubes_used;
    double neff;             /* effective number of independent exposures (Bartlett, lag-1
                                autocorrelations of the two series), mean of the two axes */
    size_t nexp;             /* the exposures the correlations are over (neff / nexp: their
                                autocorrelations' toll, which the continuation check applies too) */
    double z, z_need;        /* the pairing's correlations together in sigma ((z_x + z_y)/sqrt 2 of
                                their Fisher z over neff), and what the search needs: the
                                Bonferroni bound at 1 % over 2 pairings x the coarse grid's
                                points. z < z_need: the fit may be any peak of the search */
    double lag_min, lag_max; /* the lag window searched last: p's, or moved (its width kept) to be
                                centred on a peak that lay at its edge */
    int lag_moves;           /* how many times it moved (each a search of the whole window) */
} swfs_sync_result;

/* For each candidate (ratio, lag), exposures that would leave their telemetry file are
 * left out of the correlation; ncubes_used counts the cubes with at least half of their
 * exposures inside at the optimum (those give the per-cube ratio scatter). */
int swfs_sync_estimate(const swfs_sync_cube *cubes, size_t ncubes, const swfs_sync_params *p, swfs_sync_result *r);

/* Whether part of a camera cube continues in an adjacent telemetry file with no WFS frame
 * lost or repeated between the two files. part: the cube's exposures that lie wholly in the
 * adjacent file, with logged = their start there if the files were contiguous + fit->lag (so
 * that the fit's lag puts them where contiguity says). The lag is searched for this part
 * alone over p's lag range at the fit's ratio and pairing; the part continues when its best
 * lag is the fit's to within half a WFS frame (files hold whole frames: a lost or repeated
 * frame moves it by one or more) and both correlations of the fit's pairing are positive and
 * together significant at 5 sigma over the part's effective number of exposures ((z_x + z_y) /
 * sqrt 2 of their Fisher z over nexp x fit->neff / fit->nexp, the fit's share of independent
 * exposures; all of them when the fit has no neff: a short part cannot pass). */
typedef struct swfs_sync_continuation {
    int continues;
    double offset;          /* best lag - fit->lag [WFS frames] */
    double corr_x, corr_y;  /* the fit's pairing's correlations (signs applied) at the best lag */
    size_t nexp;            /* exposures of the part inside the file at the best lag */
    int significant;        /* both correlations positive and together 5 sigma, whatever the offset */
    double corr_x0, corr_y0; /* the same where the fit's lag places the part (offset 0) */
    int off_significant;    /* the best lag's correlations above those at offset 0 by 5 sigma together
                               ((dz_x + dz_y) / 2 over the part's effective exposures, dz the rise in
                               Fisher z; each dz of variance 2 / (ne - 3), the two placements taken
                               as independent samples, which is the cautious side): the camera
                               tells the part's lag from the fit's, not just prefers it */
} swfs_sync_continuation;

int swfs_sync_continuation_check(const swfs_sync_cube *part, const swfs_sync_result *fit, const swfs_sync_params *p,
                                 swfs_sync_continuation *out);

/* Whether telemetry file B starts with the frame that follows file A's last, from the
 * telemetry alone (any kind of vector: slopes, modal coefficients). An AO loop's telemetry
 * changes from frame to frame less than over two frames; q, the squared norm of the step from
 * A's last frame to B's first, is set against the steps inside the last SWFS_SYNC_EDGE_FRAMES
 * frames of A and the first of B: contiguous (+1) when q is below every two-frame step there
 * and not above every one-frame step; not contiguous (-1) when q is above every one-frame step
 * and not below every two-frame step, or zero (a repeated frame) where the steps are not;
 * otherwise a second stage, for telemetry where the WFS noise dominates one frame's change:
 * the means of m frames either side, q_m the squared norm of their difference, set against
 * the same statistic inside the edges, contiguous and over one lost frame; m (1, 2, 3, 4, 6,
 * 8, 12 or 16, with 16 disjoint windows a side at least: up to 8 with 128-frame edges) the one
 * whose contiguous steps lie furthest below the lost frame's, each kind
 * taken for a scaled chi-square of its mean and variance (Wilson-Hilferty). Contiguous (+1)
 * when a lost frame's step is that small with probability below 0.5 % and a contiguous one
 * that large with 0.5 % or more; the second stage never says not contiguous (a step's tail
 * under contiguity is heavier than the chi-square's where the signal moves: it called such
 * cuts not contiguous 1-3 % of the time). Otherwise the telemetry cannot tell (0: noise-
 * dominated, or too few frames). Measured over 11 simulated systems, their series cut at every
 * fifth frame (docs/telemetry.md): contiguous files called not contiguous at most 0.6 % of the
 * time, one lost frame called contiguous at most 0.7 % by the first stage. The second stage,
 * only where the two kinds part at all (the contiguous steps' mean below a lost frame's 0.5 %
 * point), called 8 of 4 656 lost-frame cuts contiguous (0.17 %; 3 of 336 on the worst series)
 * over three simulated loops and three made without specklewfs, and on a noise-dominated one
 * of those 99.5 % of the contiguous cuts contiguous where the first stage alone called 20 %.
 * tail: A's last ntail frames, head: B's first nhead frames, nvals values each. */
#define SWFS_SYNC_EDGE_FRAMES 128
typedef struct swfs_sync_boundary {
    int verdict;           /* +1 contiguous, -1 not, 0 the telemetry cannot tell */
    double q;              /* squared norm of the step across the boundary */
    double q1_max, q2_min; /* the largest one-frame step, the smallest two-frame step beside it */
    size_t n1, n2;         /* the steps of each kind */
    /* the second stage, where the first cannot tell (window 0 and NAN otherwise): */
    size_t window;         /* m [frames] */
    double q_window;       /* q_m */
    double p_lost;         /* P(a step over one lost frame <= q_m) */
    double p_contiguous;   /* P(a contiguous step >= q_m) */
} swfs_sync_boundary;

int swfs_sync_boundary_check(const double *tail, size_t ntail, const double *head, size_t nhead, size_t nvals,
                             swfs_sync_boundary *out);

/* Whether the telemetry across a boundary the check above calls not contiguous is what `lost`
 * WFS frames missing between A and B make (lost < 0: -lost frames repeated), the count the
 * camera's lag gives (sync_run). Repeated: B's first -lost frames are A's last, value for value
 * (and the telemetry moves). Lost: the step q across the boundary is a step over lost + 1
 * frames, so it must lie among the steps over lost + 1 frames inside the edges (qk_min ..
 * qk_max), and the data must tell such steps from a long gap at all: every one of them below
 * every step over the longest lags each edge holds (its second half, qfar_min; separable).
 * Without that (the residual decorrelates in fewer frames than lost + 1, or the steps are
 * noise) a whole missing file could not be told from a few lost frames: a tip-tilt dominated
 * by a periodic vibration matches the camera at the gap less whole periods (a test of 150
 * frames lost at 527 Hz with 20 Hz vibration: the camera counted 4 frames repeated). */
typedef struct swfs_sync_gap {
    long lost;
    int consistent;        /* the telemetry agrees with the count */
    int separable;         /* (lost > 0) steps over lost + 1 frames all below the long-lag steps */
    double q;              /* squared norm of the step across */
    double qk_min, qk_max; /* the steps over lost + 1 frames beside the boundary */
    double qfar_min;       /* the smallest step over the long lags */
} swfs_sync_gap;

int swfs_sync_boundary_gap(const double *tail, size_t ntail, const double *head, size_t nhead, size_t nvals,
                           long lost, swfs_sync_gap *out);

/* Predicted exposure means of a per-WFS-frame series m (n frames) for exposures
 * [start + j ratio, start + (j+1) ratio), j < nexp: out[j] = (1/ratio) * integral of the
 * piecewise-constant m. Returns SWFS_ERR_VALUE if an exposure leaves [0, n). */
int swfs_sync_box_means(const double *m, size_t n, double start, double ratio, size_t nexp, double *out);

/* Mean x and y slopes per frame over the valid subapertures (valid NULL: the
 * subapertures with a nonzero x or y slope in that frame): slopes is nwfs frames of
 * nslopes, x slopes first. */
/* The tip-tilt of any telemetry through tilt rows R (2 x nvals: x then y, e.g. the Z-tilt
 * of a linear model's wavefront, swfs_pipeline_tilt_rows): mx[k] = R[0] . v_k, my[k] = R[1] . v_k
 * for the nwfs frames v of nvals values. */
void swfs_tilt_rows_apply(const double *R, const double *v, size_t nvals, size_t nwfs, double *mx, double *my);
void swfs_slopes_mean_xy(const double *slopes, size_t nslopes, size_t nwfs, const unsigned char *valid, double *mx,
                         double *my);

/* ---- timing table -------------------------------------------------------------- */

/* A row's status: its exposures usable (ok), or left out: straddling a boundary of telemetry
 * files that do not continue each other (straddles), or in a cube whose telemetry file the
 * handshake log names but cannot be read (missing: absent, truncated, not telemetry of the
 * others' kind). */
enum { SWFS_CUBE_OK = 0, SWFS_CUBE_STRADDLES = 1, SWFS_CUBE_MISSING = 2 };

typedef struct swfs_timing_cube {
    char camera[SWFS_SYNC_NAME];
    char slopes[SWFS_SYNC_NAME];
    size_t first;     /* first frame of the cube in the reduced science file */
    size_t nframes;
    double start;     /* exposure start [WFS frames of the slopes file] = logged - lag */
    int status;       /* SWFS_CUBE_OK, or discarded */
    int joined;       /* 1: the part of a cube that continues in the file before or after the one
                         the handshake log names (sync's check; a comment of the table says so) */
    double join_offset, join_corr_x, join_corr_y; /* that check's figures (swfs_sync_continuation) */
    int join_verdict;  /* the telemetry's own verdict on the boundary crossed (swfs_sync_boundary) */
    long join_lost;    /* WFS frames lost across it (< 0: repeated), counted by the camera where the
                          telemetry says the files do not continue each other; 0: contiguous */
    size_t join_window; /* the verdict's window where the check's second stage gave it (the means of
                           join_window frames either side); 0: the one-frame steps */
    int join_frame0;    /* 1: the two files' FRAME0 placed the part (join_lost their count), the
                           telemetry not contradicting them (sync_run). Appended in 0.9.0 */
} swfs_timing_cube;

/* The boundary a joined row crossed, as sync and its timing table word it: the telemetry's
 * verdict "continuous", "continuous (the means of 3 frames either side)" or "undecided", or
 * "not continuous: 2 WFS frames lost there (the camera's count)"; with "; the files' FRAME0
 * say contiguous" (or "agree") where the files' counters placed it, and their count for frames
 * lost ("2 WFS frames lost there by the files' FRAME0; the telemetry undecided"). */
void swfs_timing_join_verdict(const swfs_timing_cube *c, char *buf, size_t cap);

typedef struct swfs_timing {
    double ratio, ratio_err, lag;
    swfs_sync_result fit;
    size_t ncubes;
    swfs_timing_cube *cubes;
} swfs_timing;

/* ---- the camera's orientation (src/telemetry/orient.c) ------------------------------
 *
 * The pairing sync found says how the camera's axes follow the slopes' axes: straight or
 * swapped (a transposed camera), each with a sign (a flipped axis). The speckles are
 * computed in the model's focal frame (docs/conventions.md), so the science frames are brought into
 * that frame: model pixel (cx + u, cy + v), (cx, cy) = (nx/2, ny/2), takes the camera's
 * (cx + a, cy + b) with a = sx u, b = sy v, or a = sx v, b = sy u when swapped; NaN where
 * the camera did not see. The frames keep their size. */
int swfs_orient_is_identity(const swfs_sync_result *p);
/* SWFS_ERR_VALUE for a pairing that is not one of the 8; SWFS_ERR_SHAPE for a transposed
 * camera with frames that are not square (what: the file, for the message). */
int swfs_orient_check(const swfs_sync_result *p, size_t nx, size_t ny, const char *what);
/* "SWAP=s SX=+-1 SY=+-1", the CAMORIEN keyword of re-oriented products. */
void swfs_orient_describe(const swfs_sync_result *p, char *buf, size_t cap);
/* cam (camera frame, nx x ny values of comps doubles each: 1 real, 2 complex) into model. */
void swfs_orient_frame(const swfs_sync_result *p, size_t nx, size_t ny, size_t comps, const double *cam, double *model);

/* The camera's orientation told by the speckles themselves, a check of sync's pairing (which
 * the star's track alone can get wrong: a vibration along a diagonal moves both slope axes
 * alike, and the swapped pairing with both signs flipped then follows the track nearly as
 * well). The science intensity fluctuates with the speckles' |psi|^2 (the g^2 |psi|^2 term of
 * |Psi + g psi|^2) in the orientation the camera really has and hardly in any other (the
 * 180 degree turn keeps some: |psi|^2 is nearly point-symmetric for small phases). Per model
 * pixel, the correlation over the frames of the camera's intensity (each of the 8 pairings'
 * pixel, swfs_orient_frame's mapping) with |psi|^2; over the pixels where both vary, the mean
 * correlation of each pairing, and of the best against `ref` (the timing table's) the mean
 * per-pixel difference and its standard error (the differences' spread over the pixels, the
 * pixels counted in speckles: npix / pix_per_speckle independent). The accumulator takes the
 * frames one at a time: 8 x 3 + 3 sums per pixel, no frame kept. */
typedef struct swfs_orient_acc swfs_orient_acc;
int swfs_orient_acc_new(size_t nx, size_t ny, swfs_orient_acc **out);
void swfs_orient_acc_free(swfs_orient_acc *a);
/* cam: the camera's frame as read (nx x ny); psi2: |psi|^2 of the frame in the model's frame.
 * Pixels not finite in either are left out of that frame's sums for that pairing. */
void swfs_orient_acc_add(swfs_orient_acc *a, const double *cam, const double *psi2);
typedef struct swfs_orient_check_result {
    double corr[8];    /* pairing k: swap = k / 4, sign_x = k & 2 ? -1 : 1, sign_y = k & 1 ? -1 : 1;
                          NaN for a swapped one on frames that are not square */
    int best, ref;     /* the pairing of the largest mean correlation; the timing table's */
    double diff, diff_se; /* mean per-pixel correlation, best less ref, and its standard error */
    size_t npix, nframes; /* the pixels that took part; the frames added */
} swfs_orient_check_result;
/* ref: the timing table's pairing; pix_per_speckle: pixels per speckle ((lambda/D / pixel
 * scale)^2), >= 1. SWFS_ERR_VALUE when fewer than 3 frames or no pixel varies. */
int swfs_orient_acc_result(const swfs_orient_acc *a, const swfs_sync_result *ref, double pix_per_speckle,
                           swfs_orient_check_result *r);
/* Pairing k's correlation at each of the nx x ny model pixels into c (NaN where either does
 * not vary, or the pairing gives the pixel no camera pixel): what swfs_orient_acc_result
 * averages, for comparing two speckle cubes of the same frames pixel by pixel (speckles'
 * choice of the DM's functions). Added in 0.11.0. */
void swfs_orient_acc_pixel_corrs(const swfs_orient_acc *a, int k, double *c);
/* Over the np pixels where both are finite, the mean of b - a (two such per-pixel
 * correlations) and its standard error, the pixels counted in speckles (n / pix_per_speckle
 * independent, at least 1): what swfs_orient_acc_result reports of the best pairing against
 * the table's. Returns n (mean NaN where 0). Added in 0.11.0. */
size_t swfs_orient_corr_diff(const double *a, const double *b, size_t np, double pix_per_speckle, double *mean,
                             double *se);
/* The pairing k's swap and signs into p (its other fields untouched). */
void swfs_orient_pairing(int k, swfs_sync_result *p);
/* One line of what the check found: "the timing table's pairing (SWAP=0 SX=+1 SY=+1) follows
 * them best, mean correlation of intensity and |psi|^2 0.228 over 2321 pixels", or the best
 * pairing's and the table's correlations and how many standard errors apart. */
void swfs_orient_check_describe(const swfs_orient_check_result *c, char *buf, size_t cap);

/* Text:  "ratio R ERR" / "lag L" / "pairing SWAP SX SY CX CY" lines, then one
 * "cube INDEX CAMERA FIRST NFRAMES SLOPES START STATUS" line per cube (STATUS ok, straddles
 * or missing); '#' comments. */
int swfs_timing_write(const char *path, const swfs_timing *t);
int swfs_timing_read(const char *path, swfs_timing **out);
void swfs_timing_free(swfs_timing *t);

SWFS_END_DECLS

#endif

/* The report: PNG figures of a run's products and one index.html with the key numbers,
 * so a halo or a wavefront map can be judged by looking at it (the paper's figures).
 *
 * A run folder: reads whatever exists in RUN_DIR -- science.fits, speckles.fits,
 * truth.fits, pupil.fits, halo.fits, wavefront.fits, coherence.fits (formats in
 * docs/conventions.md) -- and writes into the report folder:
 *   halo.png       log10 |Psi| (normalized to the reference pixel in the first Airy ring),
 *                  arg Psi, visibility (fig:Sim-PSI-Vis)
 *   focal.png      scale factor g with circles at 1..6 lambda/D (fig:Gain-map), mean
 *                  science image, science variance on a 4-decade log scale
 *                  (fig:Sim-PSF-Sigma2), mean speckle power (fig:Sim-SpeckleHaloMeanPower)
 *   pixel.png      one first-ring pixel's intensity against the speckle phase, with a
 *                  least-squares sinusoid, the model and arg Psi (fig:MMT-example-data)
 *   pupil.png      pupil amplitude and WFE [nm] with the pupil outline; for simulations
 *                  the true NCP and the error map (fig:Sim-NCP, fig:Sim-PField)
 *   coherence.png  tau0, phase-rotation time, SNR factor maps and Gamma(tau)/Gamma(0)
 *                  of one pixel with the e^{-1/2} circle (fig:Halo-tau0,
 *                  fig:Speckles-MCF-4panel1)
 *   index.html     the figures with the key numbers, and a note for each one skipped
 * Figures whose products are missing are skipped with a note; a product that exists
 * but cannot be read is an error, and so is a folder with none of the products.
 *
 * A demo folder (what `specklewfs demo -o DIR` writes: recovery.tsv, sigma<level>/,
 * loop/): one page with the recovery table as the demo wrote it (whatever its columns),
 * a section per noise level with its key numbers and figures (in sigma<level>/ of the
 * report folder), and the closed loop's table and loop.png (residual NCP and Strehl
 * against the iteration) when loop/loop.tsv exists.
 *
 * Colour ranges come from robust percentiles of the finite, displayed pixels (see
 * docs/report.md): "auto" maps use [P_lo, P_hi] and switch to log10 when both are
 * positive and P_hi/P_lo > 100 (then at most log_decades decades below log10 P_hi);
 * the science variance always spans exactly log_decades decades below log10 P_hi;
 * signed maps (WFE, NCP, error) use +-P_hi(|v|); phases use [-pi, pi], visibility [0, 1].
 *
 * Not thread-safe (PLplot, see plot.h). */
#ifndef SWFS_REPORT_H
#define SWFS_REPORT_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

#define SWFS_REPORT_MAX_FIGURES 96
#define SWFS_REPORT_MAX_RANGES 64
#define SWFS_REPORT_MAX_NOTES 64
#define SWFS_REPORT_MAX_LEVELS 16

typedef struct swfs_report_options {
    double pct_lo, pct_hi; /* robust percentiles for colour ranges [%]: 1, 99.5 */
    double log_decades;    /* decades shown on log scales: 4 */
    long pixel_i, pixel_j; /* pixel for pixel.png and the MCF plot; -1: chosen from the data */
    const char *title;     /* page title; NULL: "specklewfs report: <run dir>" */
} swfs_report_options;

void swfs_report_options_default(swfs_report_options *o);

/* One colour range as drawn: in displayed units (nm, ms, counts, ...), and for log
 * scales the log10 of them. */
typedef struct swfs_report_range {
    char name[24]; /* halo_amp, halo_phase, visib, gain, mean_i, var_i, mean_sp, amplitude,
                      wfe, ncp, err, tau0, trot, snr_fact */
    double lo, hi;
    int log;
} swfs_report_range;

typedef struct swfs_report_figure {
    char file[64]; /* relative to the report folder ("sigma100/halo.png" on a demo page) */
    int width, height;
} swfs_report_figure;

/* One noise level of a demo page: its key numbers (NaN where its products lack them). */
typedef struct swfs_report_level {
    double sigma; /* [counts], from the folder name sigma<level> */
    double valid_fraction, median_snr, wfe_rms, strehl, ncp_rms, err_rms; /* as in the summary */
    size_t nfigures;
} swfs_report_level;

typedef struct swfs_report_summary {
    size_t nfigures;
    swfs_report_figure figures[SWFS_REPORT_MAX_FIGURES];
    size_t nranges;
    swfs_report_range ranges[SWFS_REPORT_MAX_RANGES];
    size_t nnotes; /* figures skipped and why */
    char notes[SWFS_REPORT_MAX_NOTES][200];
    /* Key numbers; NaN when the products do not give them. */
    double frames;         /* frames in the estimate (halo NFRAMES, else science cube depth) */
    double valid_fraction; /* VALIDFR */
    double median_snr;     /* MEDSNR */
    double wfe_rms, wfe_pv; /* [m], inside the pupil */
    double strehl;          /* STREHL key, else Marechal exp(-(2 pi rms / lambda)^2) */
    double ncp_rms;         /* true NCP rms [m], piston removed (simulations) */
    double err_rms;         /* rms of WFE - NCP [m], piston and tip/tilt removed: swfs_wfe_compare,
                               the demo's recovery error (simulations) */
    double tau0_median;     /* [s] */
    long pixel_i, pixel_j;  /* pixel of pixel.png; -1 if not drawn */
    double pixel_halo_phase, pixel_fit_phase; /* arg Psi and the fitted sinusoid's phase [rad] */
    char html[4096];        /* path of index.html */
    /* A demo folder (the run's key numbers above stay NaN): */
    int demo;               /* 1: the page of a demo folder */
    size_t nlevels;         /* noise levels drawn */
    swfs_report_level levels[SWFS_REPORT_MAX_LEVELS];
    size_t recovery_rows;   /* rows of the recovery table shown (0: no recovery.tsv) */
    size_t loop_rows;       /* rows of the closed-loop table shown (0: no loop/loop.tsv) */
} swfs_report_summary;

/* Draw the figures and write index.html (via .part + rename) into out_dir (NULL:
 * RUN_DIR/report; created if needed) for a run folder or a demo folder. opt may be NULL
 * (defaults); summary may be NULL. A folder with nothing to report is SWFS_ERR_IO with a
 * message naming it and what was looked for (no page is written). */
int swfs_report_run(const char *run_dir, const char *out_dir, const swfs_report_options *opt,
                    swfs_report_summary *summary);

/* modes.png at `png`: ncurves (1 to 6) mode-variance profiles (timeseries.h
 * swfs_ts_mode_variance; var[c] of n[c] modes) on log-log axes, each knee[c] (0: none)
 * dashed, label[c] in the legend (`teach`: the observation and its calibration loops).
 * Needs swfs_plot_available(). */
int swfs_fig_modes(const char *png, const double *const *var, const size_t *n, const size_t *knee,
                   const char *const *label, size_t ncurves);

/* The range named `name` in a summary, or NULL. */
const swfs_report_range *swfs_report_find_range(const swfs_report_summary *s, const char *name);

/* pct-th percentile (linear interpolation between order statistics) of the finite
 * values v[k] with mask[k] != 0 (mask may be NULL); NaN if there are none. */
double swfs_report_percentile(const double *v, size_t n, const unsigned char *mask, double pct);

SWFS_END_DECLS

#endif

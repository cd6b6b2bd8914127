/* The camera clock against the WFS clock from time-stamped frames (milk logs, milklog.h),
 * refined by the tip-tilt cross-correlation of paper Sec. 4.2 (sync.h does it for the
 * handshake path; this is its time-stamped counterpart).
 *
 * Every frame's stamp marks the END of its exposure (FORMATS.md). The two clocks differ by
 * an offset and a rate:  t_wfs = epoch + (t_cam - epoch) (1 + drift) + offset, epoch a
 * whole second at or before the first camera stamp. The WFS clock is fitted to the WFS
 * stamps per segment (t = a + P cnt0; a new segment at a gap or a counter that goes back),
 * so WFS frame cnt covers [a + P (cnt - 1), a + P cnt). Camera frame j then covers
 * [T_j - E, T_j] mapped onto that time line (E the exposure time, or the camera's frame
 * period), and its exposure-mean x / y slopes are box means of the per-frame mean slopes
 * with fractional weights at the ends (as swfs_sync_box_means). The star's track (TRACK of
 * the reduced cube) follows them: (offset, drift) maximize the pooled correlation of the
 * four axis pairings (per camera segment, i.e. cube, the means removed), on a grid refined
 * twice 10x. Dropped WFS frames take the previous frame's mean slope for this purpose only.
 *
 * The uncertainty: at the fitted drift every camera segment's own best offset is found;
 * their scatter gives the offset error (scatter / sqrt(n)) and the drift error (scatter /
 * sqrt(sum (tau_s - mean tau)^2), tau_s the segments' mid times); NaN with fewer than 3
 * segments. */
#ifndef SWFS_CLOCKSYNC_H
#define SWFS_CLOCKSYNC_H

#include <stddef.h>
#include <stdint.h>

#include "specklewfs/sync.h"

SWFS_BEGIN_DECLS

typedef struct swfs_clock {
    int64_t epoch;          /* [ns] Unix time */
    double offset;          /* [s] */
    double drift;
    double offset_err, drift_err;
    swfs_sync_result fit;   /* the pairing (swap, sign_x, sign_y, corr_x, corr_y, corr4) */
    double resid;           /* [pixels] rms of the track about its fit by the exposure-mean slopes */
    double exptime;         /* [s] camera clock, used for the exposures */
    double wfs_period, cam_period;  /* [s] fitted frame periods */
    double wfs_jitter, cam_jitter;  /* [s] rms of the stamps about the clock fits */
    size_t nused, ncam;     /* camera frames in the correlation / given */
    size_t nsegments;       /* camera segments (cubes) used */
} swfs_clock;

typedef struct swfs_clock_params {
    double offset_min, offset_max; /* [s] search range of the offset (-0.01, 0.01) */
    double drift_max;              /* |drift| searched (5e-4) */
} swfs_clock_params;

void swfs_clock_params_default(swfs_clock_params *p);

/* The data, as arrays: WFS frames (counter, stamp [ns], mean x / y slope) and camera frames
 * (counter, stamp [ns], star position x / y [pixels]); exptime [s] (0: the camera period). */
typedef struct swfs_clock_data {
    size_t nwfs;
    const uint64_t *wcnt;
    const int64_t *wst;
    const double *mx, *my;
    size_t ncam;
    const uint64_t *ccnt;
    const int64_t *cst;
    const double *tx, *ty;
    double exptime;
} swfs_clock_data;

/* SWFS_ERR_VALUE when no camera exposure lies inside the WFS data for any (offset, drift)
 * of the search range (the message gives both time spans). */
int swfs_clock_estimate(const swfs_clock_data *d, const swfs_clock_params *p, swfs_clock *c);

/* A camera stamp [ns] on the WFS clock [ns]. */
int64_t swfs_clock_to_wfs(const swfs_clock *c, int64_t cam_ns);

/* Text: "epoch S.NNNNNNNNN", "offset O ERR", "drift D ERR", "exptime E", "pairing SWAP SX SY
 * CX CY", "resid R", "periods PW PC", "jitter JW JC", "frames USED TOTAL SEGMENTS" lines;
 * '#' comments (the writer adds `note`). The reader needs epoch, offset and drift. */
int swfs_clock_write(const char *path, const swfs_clock *c, const char *note);
int swfs_clock_read(const char *path, swfs_clock *c);

SWFS_END_DECLS

#endif

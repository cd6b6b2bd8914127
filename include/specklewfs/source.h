/* Sources of batches for the stream (stream.h) from files: the timing table of
 * `specklewfs sync`, the telemetry files it names (FITS, nslopes x WFS frames) and the
 * reduced science cube. Also the telemetry helpers the file-driven runs share. */
#ifndef SWFS_SOURCE_H
#define SWFS_SOURCE_H

#include <stddef.h>

#include "specklewfs/array.h"
#include "specklewfs/stream.h"
#include "specklewfs/sync.h"

SWFS_BEGIN_DECLS

typedef struct swfs_file_source swfs_file_source;

/* timing: the timing table (read and kept); science: the reduced science cube (real);
 * slopes: a folder holding the telemetry files the table names (relative names are
 * joined to it, absolute ones used as they are) or one telemetry file used for every
 * cube; NULL = the timing table's folder. nslopes: values per WFS frame; batch: camera
 * frames per batch (>= 1). tiptilt/expansion is the pipeline's business: a batch carries
 * the raw slopes. */
int swfs_file_source_open(swfs_file_source **out, const char *timing, const char *science, const char *slopes,
                          size_t nslopes, size_t batch);
void swfs_file_source_close(swfs_file_source *s);
/* The swfs_source_fn of stream.h (ctx = the swfs_file_source). */
int swfs_file_source_next(void *ctx, swfs_batch *b);
const swfs_timing *swfs_file_source_timing(const swfs_file_source *s);
/* Serve only the usable camera frames [first, first + count) of the data set (counted over
 * the usable cubes in table order): one member's share of a distributed run (team.h). Call
 * before the first batch. Batches stop at the range's end, and they are the whole data
 * set's batches when `first` lies a multiple of the batch size from its cube's start. */
int swfs_file_source_set_range(swfs_file_source *s, size_t first, size_t count);
/* Open every telemetry file the source's frames (its range, or the whole data set) need and
 * check it (present, not truncated, nslopes x WFS frames covering the frames' exposures)
 * without reading the data: a share's bad file is found before any work. */
int swfs_file_source_check(const swfs_file_source *s);
/* Where the last batch's slopes came from: the telemetry file in memory (nslopes x WFS frames,
 * valid until the next batch), its path, the timing table's name for it and the folder
 * that name was joined to (NULL when one file serves every cube), and the batch's first WFS
 * frame in it (b->slopes = tel->data + base nslopes). A space-time reconstructor's caller
 * stacks the lags from it (pipeline.h swfs_pipeline_process). SWFS_ERR_ARG before the first
 * batch. */
typedef struct swfs_file_source_pos {
    const swfs_real *tel;
    const char *path, *dir, *name;
    size_t base;
} swfs_file_source_pos;
int swfs_file_source_last(const swfs_file_source *s, swfs_file_source_pos *pos);
/* WFSRATE [Hz] of the last telemetry file read that had one (0 if none had). */
double swfs_file_source_wfs_rate(const swfs_file_source *s);

/* The telemetry file the source reads for a cube whose timing-table entry names `name`
 * (timing, slopes: as for swfs_file_source_open). */
int swfs_file_source_telemetry_path(const char *timing, const char *slopes, const char *name, char *path, size_t cap);

/* The path of telemetry file `name` of a timing table in folder dir (absolute names are
 * used as they are). SWFS_ERR_ARG if it does not fit in cap. */
int swfs_telemetry_path(const char *dir, const char *name, char *path, size_t cap);
/* The folder part of a path ("." when there is none). */
void swfs_path_dir(const char *path, char *dir, size_t cap);
/* A telemetry file: a 2-D image of nslopes x WFS frames (nslopes = 0: any width), and its
 * WFSRATE [Hz] in *rate (0 when absent or not a rate; rate may be NULL). */
int swfs_telemetry_read(const char *path, size_t nslopes, swfs_real **out, double *rate);
/* A telemetry file's NSUB keyword, when it has one, against the model's nsub
 * (SWFS_ERR_VALUE naming the file and both values). */
int swfs_telemetry_check_nsub(const char *path, size_t nsub);
/* The sensor a telemetry file's WFSTYPE names: SWFS_WFS_SH ("SH...", "...HARTMANN...", any
 * case), SWFS_WFS_PYRAMID ("...PYR..."), SWFS_WFS_OTHER (another name) or SWFS_WFS_UNNAMED (no
 * keyword); type (cap bytes, may be NULL): the keyword's text as written. */
enum { SWFS_WFS_UNNAMED = 0, SWFS_WFS_SH, SWFS_WFS_PYRAMID, SWFS_WFS_OTHER };
int swfs_telemetry_sensor(const char *path, int *kind, char *type, size_t cap);
/* Telemetry a Shack-Hartmann model may take: a file whose WFSTYPE names another sensor (a
 * pyramid's signals, `simulate wfs=pyramid`: WFSTYPE = 'PYRAMID') is SWFS_ERR_FORMAT, naming
 * it, `what` (the model refusing it) and the linear model that does describe it (--basis with
 * --imat or --control); no WFSTYPE, or one naming a Shack-Hartmann ("SH...", "...HARTMANN...",
 * any case), passes. */
int swfs_telemetry_check_sh(const char *path, const char *what);
/* The same checks without reading the data: *nframes (may be NULL) receives the WFS frames. */
int swfs_telemetry_check(const char *path, size_t nslopes, size_t *nframes);
/* Telemetry values: finite and at most SWFS_TELEMETRY_MAX in magnitude in any unit (FLT_MAX
 * and similar fill values are refused rather than averaged into the synchronization or the
 * reconstruction). SWFS_ERR_VALUE naming the file, slope and frame; a NaN and an infinity
 * alike are "not finite (NaN or infinite)" (CFITSIO reads a stored infinity as NaN). */
#define SWFS_TELEMETRY_MAX 1e30
int swfs_telemetry_check_values(const char *path, const swfs_real *s);
/* Every telemetry file the usable cubes of t use, in the order they first appear,
 * concatenated: *out = *nframes frames of nslopes (caller frees). */
int swfs_telemetry_load_training(const char *dir, const swfs_timing *t, size_t nslopes, double **out,
                                 size_t *nframes);

SWFS_END_DECLS

#endif

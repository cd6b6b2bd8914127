/* Accumulator checkpoints: the per-pixel state of accum.h saved to a FITS file, so a night
 * can be processed in chunks, on several machines, or resumed after a stop, and the parts
 * merged exactly (Chan et al.'s pairwise update, swfs_accum_merge).
 *
 * File layout (docs/conventions.md conventions): an empty primary HDU with SWFSVER/DATE/HISTORY
 * provenance and the geometry keywords, then the image extension EXTNAME = 'ACCUM': a real
 * cube (BITPIX -64) nx x ny x 15 whose plane k is field k of accum.h (count, the 4 means
 * of (I, x, y, |psi|^2), the 10 co-moments), with the keywords
 *   ACCVER  = 1                  layout version
 *   ACCFLDS = 'N MI MX MY MA CII CIX CIY CIA CXX CXY CXA CYY CYA CAA'
 *   FRAMES  frames offered;  SKIPPED  pixel-frames skipped (non-finite science)
 * and the geometry; then (version 2) the extension EXTNAME = 'REGSTATE': the regression
 * statistics of regress.h, a real cube nx x ny x SWFS_REGRESS_NSTATE (plane order of its enum)
 * with REGVER = 1, FRAMES, SKIPPED. Version 1 checkpoints (no REGSTATE) still load: their
 * accumulator has empty regression statistics (swfs_accum_has_regress says 0 when it holds
 * frames), and the joint fit is then unavailable for anything merged with them.
 * Written atomically (.part + rename), so a checkpoint that exists is
 * complete. Doubles are stored exactly: load(save(a)) == a bit for bit. */
#ifndef SWFS_CHECKPOINT_H
#define SWFS_CHECKPOINT_H

#include <stddef.h>

#include "specklewfs/accum.h"
#include "specklewfs/fits.h"

SWFS_BEGIN_DECLS

#define SWFS_CHECKPOINT_VERSION 2

/* g (may be NULL): geometry to record; prov: provenance lines (HISTORY). */
int swfs_accum_save(const swfs_accum *a, const char *path, const swfs_geom *g, const char *const *prov,
                    size_t nprov);
/* The same, with the AO residual's time mean over the accumulated frames (resmean: PUPN x PUPN
 * [m], HALO.fits RESMEAN; NULL: none) as the extension RESMEAN, nexp (key RESMNEXP) the
 * exposures it averages, so that merged checkpoints keep it (swfs_resmean_merge_files). */
int swfs_accum_save_resmean(const swfs_accum *a, const swfs_real *resmean, size_t nexp, const char *path,
                            const swfs_geom *g, const char *const *prov, size_t nprov);
/* The exposure-weighted mean of the checkpoints' RESMEAN (a linear reconstruction's mean over
 * the union of their frames): *out (NULL when any checkpoint lacks one, for a mean over part
 * of the frames is not the union's: *nmissing says how many), *nexp the exposures. */
int swfs_resmean_merge_files(const char *const *paths, size_t n, swfs_real **out, size_t *nexp, size_t *nmissing);
/* A new accumulator from a checkpoint; g (may be NULL) receives its geometry. */
int swfs_accum_load(const char *path, swfs_accum **out, swfs_geom *g);

/* Load and merge n checkpoints (same frame size and geometry) into *out; g (may be NULL)
 * receives the merged geometry (the union of the keywords recorded). */
int swfs_accum_merge_files(const char *const *paths, size_t n, swfs_accum **out, swfs_geom *g);

/* The REGSTATE extension alone (also carried by HALO.fits): write it as the next HDU of o;
 * read it from f (which must hold it) into a new nx x ny regression accumulator. */
int swfs_regress_write_ext(swfs_fits_out *o, const swfs_regress *r);
int swfs_regress_read_ext(swfs_fits_in *f, const char *path, size_t nx, size_t ny, swfs_regress **out);

SWFS_END_DECLS

#endif

/* The pipeline object's insides, shared by pipeline.c (the Shack-Hartmann model) and
 * pipeline_linear.c (the generic linear model). Not installed. */
#ifndef SWFS_PIPELINE_INTERNAL_H
#define SWFS_PIPELINE_INTERNAL_H

#include "specklewfs/pipeline.h"

struct swfs_pipeline {
    swfs_pipeline_options opt;
    swfs_pipeline_info info;
    swfs_speckle_model *model; /* the Shack-Hartmann model (NULL for a linear one) */
    swfs_recon *lin_map;       /* a linear model's reconstructor of its interaction matrix, unscaled */
    double *W_ext, *Rtilt; /* SWFS_TT_EXPOSURE: [W - C R | C] and the tilt rows R (speckles.h) */
    double *mask;
    swfs_engine *engine;
    /* SWFS_TT_EXPOSURE work space: every exposure's own copy of its frames + 2 tilt values */
    double *xslopes;
    size_t xcap;  /* frames xslopes holds */
    swfs_exposure *xsched;
    size_t xscap; /* exposures xsched holds */
    /* The time mean of the reconstruction (swfs_pipeline_mean_wavefront): the sum over the
     * exposures processed of each exposure's weighted mean engine input (mcols values), and
     * their count. */
    double *macc;
    size_t mcols, mexp;
    double *moff; /* npup^2 or NULL: added to that mean (swfs_pipeline_set_mean_offset) */
    size_t *band_idx; /* the focal pixels beyond info.band (info.band_out of them), zeroed */
};
/* info.band and band_idx from opt.band and the subapertures across (0 for a linear model). */
int swfs_pipeline_band_(swfs_pipeline *p, const swfs_geom *g, size_t nsub);

int swfs_pipeline_begin_(swfs_pipeline **out, const swfs_geom *g, size_t nfx, size_t nfy, const double *mask,
                         const swfs_pipeline_options *opt, const swfs_recon *recon, const double *training,
                         size_t ntrain, int sh);
int swfs_pipeline_engine_(swfs_pipeline *p, const swfs_geom *g, size_t nrows, size_t ncols, const double *W,
                          const swfs_sparse *T);

#endif

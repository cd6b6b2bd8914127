/* Private to src/sim/: shared helpers of the Sec. 3 simulator. */
#ifndef SWFS_SIM_INTERNAL_H
#define SWFS_SIM_INTERNAL_H

#include "specklewfs/screen.h"
#include "specklewfs/sim.h"
#include "specklewfs/timeseries.h"
#include "specklewfs/wfs.h"

/* AO residual model on the grid of gen (uses its amplitude table). */
swfs_ao_model *swfs_ao_model_create_with(const swfs_sim_params *p, swfs_screen_gen *gen);
/* Lag vector [m] of p. */
void swfs_sim_lag_vector(const swfs_sim_params *p, double *sx, double *sy);
/* A file name setting into dst[cap] (kept when the key is absent; refused when too long). */
int swfs_sim_config_path(swfs_config *c, const char *key, char *dst, size_t cap);

/* The time series' given files (timeseries.h: actuators, ao_recon, valid), each NULL / 0
 * when not given. */
int swfs_ts_read_given(const swfs_ts_params *p, double D, double **xy, size_t *nact, swfs_recon **rao,
                       unsigned char **vmap);
/* The loop's given reconstructor r (read from path) for the simulated Shack-Hartmann sh and nact
 * actuators: one of the used subapertures' slopes only put into sh's full layout (in place),
 * any other shape refused, its numerical rank (singular values above 1e-9 of the largest) in
 * r->nmodes, a zero one refused. */
int swfs_ts_check_given_recon(const char *path, swfs_recon *r, const swfs_shwfs *sh, size_t nact);
/* The loop's DM and WFS on the pupil mask: the actuators *xy (*nact of them) as given, or,
 * when *xy is NULL, built from act_pitch / act_square into it (the caller frees it either
 * way); their interpolation T and the Shack-Hartmann (vmap: its used subapertures, or NULL). */
int swfs_ts_loop_model(const swfs_ts_params *p, const double *mask, const unsigned char *vmap, double **xy,
                       size_t *nact, swfs_sparse **T, swfs_shwfs **sh);

#endif

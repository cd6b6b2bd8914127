/* Private to src/sim/: shared helpers of the Sec. 3 simulator. */
#ifndef SWFS_SIM_INTERNAL_H
#define SWFS_SIM_INTERNAL_H

#include "specklewfs/screen.h"
#include "specklewfs/sim.h"

/* AO residual model on the grid of gen (uses its amplitude table). */
swfs_ao_model *swfs_ao_model_create_with(const swfs_sim_params *p, swfs_screen_gen *gen);
/* Lag vector [m] of p. */
void swfs_sim_lag_vector(const swfs_sim_params *p, double *sx, double *sy);
/* A file name setting into dst[cap] (kept when the key is absent; refused when too long). */
int swfs_sim_config_path(swfs_config *c, const char *key, char *dst, size_t cap);

#endif

/* Science-camera noise for simulated images: Poisson photon noise and Gaussian
 * read/background noise, one RNG stream per frame (see swfs_sim_camera in sim.h). */
#include "sim_internal.h"
#include "specklewfs/parallel.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"

#include <math.h>

struct cam_job {
    const swfs_real *clean;
    swfs_real *noisy;
    double read_noise, gain;
    uint64_t seed;
};

static void cam_frames(void *ctx, size_t b, size_t e, int worker)
{
    const struct cam_job *j = ctx;
    const size_t npix = j->clean->nx * j->clean->ny;
    (void)worker;
    for (size_t t = b; t < e; t++) {
        swfs_rng rng;
        swfs_rng_seed2(&rng, j->seed, t);
        const double *in = swfs_real_frame(j->clean, t);
        double *out = swfs_real_frame(j->noisy, t);
        for (size_t k = 0; k < npix; k++) {
            double v = in[k];
            if (j->gain > 0) v = swfs_rng_poisson(&rng, v > 0 ? v * j->gain : 0.0) / j->gain;
            if (j->read_noise > 0) v += j->read_noise * swfs_rng_normal(&rng);
            out[k] = v;
        }
    }
}

int swfs_sim_camera(const swfs_real *clean, double read_noise, double gain, uint64_t seed, swfs_real *noisy)
{
    if (!clean || !noisy) return swfs_fail(SWFS_ERR_ARG, "camera: missing image cube");
    if (clean->nx != noisy->nx || clean->ny != noisy->ny || clean->nz != noisy->nz)
        return swfs_fail(SWFS_ERR_SHAPE, "camera: input is %zux%zux%zu but output is %zux%zux%zu", clean->nx, clean->ny,
                         clean->nz, noisy->nx, noisy->ny, noisy->nz);
    if (!(read_noise >= 0) || !isfinite(read_noise))
        return swfs_fail(SWFS_ERR_VALUE, "camera: read noise %g counts must be >= 0", read_noise);
    if (!isfinite(gain)) return swfs_fail(SWFS_ERR_VALUE, "camera: gain %g e-/count must be finite", gain);
    struct cam_job job = {clean, noisy, read_noise, gain, seed};
    swfs_parallel_for(swfs_parallel_threads(0, 0), clean->nz, 1, cam_frames, &job);
    return SWFS_OK;
}

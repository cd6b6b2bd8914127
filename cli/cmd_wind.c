/* specklewfs wind SLOPES.fits... --teldiam D: the frozen-flow layers' winds, the dominant one tracked. */
#include "cli.h"

#include "specklewfs/run.h"
#include "specklewfs/status.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>

static const char *usage_text =
    "usage: specklewfs wind SLOPES.fits... --teldiam D [--valid MAP.fits] [--nsub N] [--wfs-hz HZ]\n"
    "\n"
    "The winds of the frozen-flow layers from the Shack-Hartmann slopes alone (closed\n"
    "loop is fine: the residual of a linear loop moves with the layer). For lags of 1, 2, 4, ...\n"
    "WFS frames the slopes of every pair of subapertures are correlated and summed by the pair's\n"
    "displacement on the grid (the slope grids' lagged cross-correlation, by FFT), and the peak\n"
    "of that map is tracked from the first lag it lies a subaperture out until the layer\n"
    "decorrelates or leaves the map; the velocity is the least-squares fit over the lags\n"
    "tracked (include/specklewfs/wind.h). Use it to set the wind of the simulations `learn` is\n"
    "taught on (docs/telemetry.md).\n"
    "\n"
    "  SLOPES.fits...  consecutive telemetry files of one series (slopes x WFS frames: all\n"
    "                  subapertures' x slopes then y, or with --valid the valid ones' only)\n"
    "  --teldiam D     [m] the pupil the subapertures span: pitch = D / nsub\n"
    "  --valid MAP     the AO system's valid-subaperture map (nsub x nsub, nonzero = used;\n"
    "                  default: the subapertures whose slopes are not all 0)\n"
    "  --nsub N        subapertures across (default: the files' NSUB, or the map's size)\n"
    "  --wfs-hz HZ     WFS frame rate (default: the files' WFSRATE)\n"
    "Prints every lag's peak displacement and correlation, then the speed [m/s] and the\n"
    "direction [deg, counter-clockwise from the grid's +x, toward which the layer moves: the\n"
    "time-series simulator's layer_dir]. Exit 0 also when no lag resolves a displacement (a\n"
    "layer too slow for the series, or no frozen flow): it says so.\n"
    "Then further layers: the maps over the whole grid at lags of 1, 2, 3, 4, 6, 8, ... frames\n"
    "are summed along every candidate velocity's track over three lags or more (the tracked\n"
    "layer's left out); a track that stands more than twice the expected noise maximum out of\n"
    "the candidates' scatter is a layer (\"layer N: ... m/s toward ... deg\"), and the search\n"
    "repeats without it. A tracked layer whose own track stands below that, where a further\n"
    "one stands above it, is left out of the layers.\n";

int swfs_cmd_wind(int argc, char **argv)
{
    const char *cmd = "wind";
    swfs_wind_run_options o = {0};
    o.nsub = LONG_MIN; /* not given: the files' (0 to the library) */
    o.rate = NAN;
    const char **files = calloc((size_t)argc, sizeof *files);
    size_t nf = 0;
    if (!files) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); return CLI_FAIL; }
    const cli_opt opts[] = {
        {"--teldiam", CLI_DOUBLE, &o.teldiam, NULL, 0},
        {"--valid", CLI_STRING, &o.valid, "a file name", 0},
        {"--nsub", CLI_LONG, &o.nsub, NULL, 0},
        {"--wfs-hz", CLI_DOUBLE, &o.rate, NULL, 0},
    };
    const cli_args args = {cmd, usage_text, opts, CLI_NOPTS(opts), NULL, 0, NULL, NULL, files, &nf};
    int rc = cli_parse_args(&args, argc, argv);
    if (rc) { free(files); return rc < 0 ? CLI_OK : rc; }
    if (!nf) rc = cli_usage_error(cmd, "needs at least one telemetry file");
    else if (o.teldiam == 0) rc = cli_usage_error(cmd, "needs --teldiam D > 0 [m]");
    /* (the geometry's range of TELDIAM: beyond it the pitch's products overflow) */
    else if (!(o.teldiam >= 1e-3 && o.teldiam <= 1e3)) rc = cli_usage_error(cmd, "--teldiam must be 1e-3 to 1e3 m, got %g", o.teldiam);
    else if (o.nsub != LONG_MIN && !(o.nsub > 0 && o.nsub <= 100000)) rc = cli_usage_error(cmd, "--nsub must be 1 to 100000, got %ld", o.nsub);
    else if (!isnan(o.rate) && !(o.rate > 0 && o.rate <= 1e7)) rc = cli_usage_error(cmd, "--wfs-hz must be > 0 and at most 1e7, got %g", o.rate);
    if (o.nsub == LONG_MIN) o.nsub = 0;
    if (isnan(o.rate)) o.rate = 0.0;
    if (rc) { free(files); return rc; }
    o.files = files;
    o.nfiles = nf;
    swfs_wind_run_result r;
    if (swfs_wind_run(&o, &r)) { free(files); return cli_error(cmd); }
    const swfs_wind_estimate *e = &r.est;
    printf("wind: %zu WFS frames at %g Hz, %zu x %zu subapertures of %.4g m (%zu used), map +-%zu subapertures\n",
           r.nframes, r.rate, r.nsub, r.nsub, r.pitch, e->nvalid, e->radius);
    printf("  lag [frames]  peak shift x, y [subapertures]  correlation\n");
    for (size_t k = 0; k < e->nlags; k++) {
        const swfs_wind_lag *L = &e->lag[k];
        printf("  %12zu  %+13.2f %+7.2f          %.3f%s\n", L->lag, L->dx, L->dy, L->corr,
               L->used ? "  <- tracked" : L->inside ? "" : "  (at the map's edge)");
    }
    if (e->found) {
        printf("wind: %.2f m/s toward %.1f deg (vx %+.2f, vy %+.2f m/s), from %zu lags\n", e->speed, e->direction,
               e->vx, e->vy, e->nused);
        printf("layers: the maps (+-%zu subapertures) stacked along each candidate track over %zu lags; a layer stands "
               "%.1f robust sd or more out\n", r.nsub - 1, e->nstack, e->threshold);
        for (size_t k = 0; k < e->nlayers; k++) {
            const swfs_wind_layer *L = &e->layer[k];
            printf("layer %zu: %.2f m/s toward %.1f deg, correlation %.3f along %zu lags, %.1f sd%s\n", k + 1, L->speed,
                   L->direction, L->corr, L->nlags, L->signif, k || e->tracked_dropped ? "" : " (the tracked layer)");
        }
        if (e->tracked_dropped)
            printf("layers: the tracked layer's own track stands %.1f sd out, below the threshold where a further one "
                   "stands above it: left out (its peaks were another layer's)\n", e->tracked_signif);
        if (isfinite(e->next_signif))
            printf("layers: %zu found; the best other track stands %.1f sd out\n", e->nlayers, e->next_signif);
        else
            printf("layers: %zu found\n", e->nlayers);
    } else
        printf("wind: no displacement of a subaperture or more tracked over two lags (a layer too slow for %zu "
               "frames, or no frozen flow)\n", r.nframes);
    free(files);
    return CLI_OK;
}

/* specklewfs: focal-plane wavefront sensing with residual AO speckles
 * (Codona & Kenworthy 2013). Dispatches to the subcommands in cli/cmd_*.c. */
#include "cli.h"

#include "specklewfs/outpaths.h"
#include "specklewfs/parallel.h"
#include "specklewfs/version.h"

#include <stdio.h>
#include <string.h>

struct command {
    const char *name;
    int (*run)(int argc, char **argv);
    const char *summary;
    int stoppable; /* a long run that asks at its progress reports whether to stop (cli_stop_catch) */
};

static const struct command commands[] = {
    {"simulate", swfs_cmd_simulate, "simulate the paper's Sec. 3 data set (science, speckles, truth, pupil)", 1},
    {"estimate", swfs_cmd_estimate, "static complex halo, scale factor, visibility, SNR from science + speckle cubes", 1},
    {"pupil", swfs_cmd_pupil, "pupil field and NCP wavefront from a halo product", 0},
    {"demo", swfs_cmd_demo, "the paper's simulation end to end at four noise levels, with a table", 1},
    {"report", swfs_cmd_report, "PNG figures and index.html of a run's products (halo, g, pupil WFE, coherence)", 0},
    {"reduce", swfs_cmd_reduce, "camera frames: dark, flat, bad pixels, registration, noise variance (Sec. 4.3)", 1},
    {"stream", swfs_cmd_stream, "real-time path: slopes + camera frames in time order -> HALO.fits updated as they arrive", 1},
    {"merge", swfs_cmd_merge, "combine accumulator checkpoints of disjoint frame sets exactly (optionally -> HALO.fits)", 0},
    {"sync", swfs_cmd_sync, "WFS/camera frame-rate ratio and handshake lag by tip-tilt cross-correlation (Sec. 4.2)", 0},
    {"speckles", swfs_cmd_speckles, "speckle cube from WFS slopes matching the science frames (Sec. 4.4)", 1},
    {"learn", swfs_cmd_learn, "a reconstructor learned from simulated closed loops (for speckles --recon)", 1},
    {"wind", swfs_cmd_wind, "the frozen-flow layers' winds from the slopes", 0},
    {"modal-slopes", swfs_cmd_modal_slopes, "a modal system's coefficients back to its Shack-Hartmann's slopes (CM+ c)", 0},
    {"teach", swfs_cmd_teach, "a learned map for one observation from simulated loops of your system at its winds", 1},
    {"dmoffsets", swfs_cmd_dmoffsets, "deformable-mirror offsets (metres per actuator) that cancel a PUPIL.fits WFE", 0},
    {"correct", swfs_cmd_correct, "closed-loop NCP correction in simulation: measure, fit DM offsets, apply, repeat", 1},
    {"coherence", swfs_cmd_coherence, "speckle MCF, coherence time, phase-rotation time, SNR loss vs exposure (Sec. 3.3, 4.4)", 0},
    {"live", swfs_cmd_live, "beside a running AO system: WFS + camera shared-memory streams -> HALO/PUPIL (+ DM offsets)", 0},
    {"replay", swfs_cmd_replay, "publish telemetry + camera frames into shared-memory streams at the WFS rate (for live)", 0},
    {"liveloop", swfs_cmd_liveloop, "closed NCP loop in simulation through streams: simulate -> replay -> live -> DM stream", 0},
};

static void usage(FILE *out)
{
    fprintf(out, "specklewfs %s -- focal-plane wavefront sensing with residual AO speckles\n\n", SWFS_VERSION);
    fprintf(out, "usage: specklewfs <command> [options]   (specklewfs <command> --help for details)\n\ncommands:\n");
    for (size_t i = 0; i < sizeof commands / sizeof commands[0]; i++)
        fprintf(out, "  %-10s %s\n", commands[i].name, commands[i].summary);
}

int main(int argc, char **argv)
{
    /* OpenBLAS's generic kernels on a CPU newer than it knows: run again with the CPU's own
     * (parallel.h; a no-op when OpenBLAS knew the CPU or OPENBLAS_CORETYPE is set) */
    swfs_blas_reexec(argv);
    /* The library runs its own workers over frames; BLAS inside them stays single-threaded
     * (parallel.h). */
    swfs_blas_set_threads(1);
    if (argc < 2) {
        usage(stderr);
        return CLI_USAGE;
    }
    if (!strcmp(argv[1], "--help") || !strcmp(argv[1], "-h") || !strcmp(argv[1], "help")) {
        usage(stdout);
        return CLI_OK;
    }
    if (!strcmp(argv[1], "--version")) {
        printf("specklewfs %s\n", SWFS_VERSION);
        swfs_blas_kernel_info k;
        swfs_blas_kernel(&k);
        if (k.fallback[0])
            printf("BLAS: OpenBLAS %s kernels (OPENBLAS_CORETYPE=%s, set by specklewfs: OpenBLAS chose %s for this CPU)\n",
                   k.core, k.core, k.fallback);
        else if (k.better[0])
            printf("BLAS: OpenBLAS %s kernels; this CPU runs %s's (set OPENBLAS_CORETYPE=%s)\n", k.core, k.better,
                   k.better);
        else
            printf("BLAS: OpenBLAS %s kernels\n", k.core);
        return CLI_OK;
    }
    for (size_t i = 0; i < sizeof commands / sizeof commands[0]; i++)
        if (!strcmp(argv[1], commands[i].name)) {
            if (commands[i].stoppable) cli_stop_catch();
            else cli_end_catch();
            swfs_made_dirs_begin(); /* a run that fails or is stopped leaves no empty folder it made */
            const int rc = commands[i].run(argc - 1, argv + 1);
            swfs_made_dirs_end(rc == CLI_OK);
            cli_team_end();
            if (commands[i].stoppable && !rc && cli_stop_requested())
                fprintf(stderr, "specklewfs %s: the signal came after the run's last step: it finished, its products "
                        "are complete\n", argv[1]);
            return rc;
        }
    fprintf(stderr, "specklewfs: unknown command '%s'\n", argv[1]);
    usage(stderr);
    return CLI_USAGE;
}

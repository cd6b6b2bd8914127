/* The command line's side of a distributed run (docs/cluster.md): launched by mpirun,
 * srun or another MPI launcher, `specklewfs stream|estimate|speckles|simulate|correct`
 * joins the team of its processes (team.h, team_mpi.h); otherwise it runs alone. MPI is
 * started only when a launcher started the process, so the ordinary command never loads
 * it, and only by the commands that run as a team. */
#include "cli.h"

#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <stdio.h>
#include <stdlib.h>

#ifdef SWFS_HAVE_MPI
#include <mpi.h>

#include "specklewfs/team_mpi.h"

static swfs_team *team;
static int mpi_started;
#endif

/* The number of processes an MPI launcher says it started (0: none did). Open MPI's
 * mpirun, PMIx (srun --mpi=pmix, prterun) and PMI-1/2 (MPICH's hydra, srun --mpi=pmi2). */
static long launched_size(void)
{
    const char *vars[] = {"OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE"};
    for (size_t k = 0; k < sizeof vars / sizeof vars[0]; k++) {
        const char *v = getenv(vars[k]);
        if (v && *v) return atol(v) > 0 ? atol(v) : 1;
    }
    return getenv("PMIX_RANK") || getenv("PMI_RANK") ? 1 : 0;
}

int cli_team_join(const char *cmd, const swfs_team **out)
{
    *out = NULL;
    const long n = launched_size();
#ifdef SWFS_HAVE_MPI
    if (!n || team) {
        *out = team;
        return CLI_OK;
    }
    int provided = 0;
    if (MPI_Init_thread(NULL, NULL, MPI_THREAD_FUNNELED, &provided) != MPI_SUCCESS) {
        fprintf(stderr, "specklewfs %s: MPI_Init failed\n", cmd);
        return CLI_FAIL;
    }
    mpi_started = 1;
    if (swfs_mpi_team_create(MPI_COMM_WORLD, &team)) return cli_error(cmd);
    if (n > 1 && team->size == 1) {
        /* N copies that do not see each other would each write the whole products. */
        fprintf(stderr, "specklewfs %s: the launcher started %ld processes but MPI sees only this one; with Slurm use "
                "srun --mpi=pmix (or pmi2)\n", cmd, n);
        return CLI_FAIL;
    }
    *out = team;
    return CLI_OK;
#else
    if (n > 1) {
        fprintf(stderr, "specklewfs %s: started as one of %ld processes, but this specklewfs was built without MPI "
                "(install libopenmpi-dev and rebuild; CMake option SWFS_MPI): every process would write the same "
                "products\n", cmd, n);
        return CLI_FAIL;
    }
    return CLI_OK;
#endif
}

int cli_writer(void)
{
#ifdef SWFS_HAVE_MPI
    return !team || team->rank == 0;
#else
    return 1;
#endif
}

void cli_team_end(void)
{
#ifdef SWFS_HAVE_MPI
    swfs_mpi_team_free(team);
    team = NULL;
    if (mpi_started) MPI_Finalize();
    mpi_started = 0;
#endif
}

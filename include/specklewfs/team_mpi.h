/* A team (team.h) over an MPI communicator: `mpirun -n N specklewfs ...` and any MPI
 * application that runs specklewfs on shares of one data set (docs/cluster.md). Built
 * only with the CMake option SWFS_MPI (libspecklewfs_mpi; the core library links no MPI).
 *
 *   MPI_Init_thread(&argc, &argv, MPI_THREAD_FUNNELED, &provided);
 *   swfs_team *t;  swfs_mpi_team_create(MPI_COMM_WORLD, &t);
 *   opts.team = t;  swfs_stream_run_files(&opts, &res);      // every rank, same options
 *   swfs_mpi_team_free(t);  MPI_Finalize();
 *
 * The accumulators are reduced with MPI_Reduce and a user-defined, non-commutative
 * operation (swfs_accum_merge_state on whole states), so the merge order is the ranks'
 * order. Only the calling thread uses MPI (MPI_THREAD_FUNNELED is enough). */
#ifndef SWFS_TEAM_MPI_H
#define SWFS_TEAM_MPI_H

#include <mpi.h>

#include "specklewfs/team.h"

SWFS_BEGIN_DECLS

/* A team of the members of comm (duplicated: the team's messages never mix with the
 * caller's). Free with swfs_mpi_team_free before MPI_Finalize. */
int swfs_mpi_team_create(MPI_Comm comm, swfs_team **out);
void swfs_mpi_team_free(swfs_team *t);

/* Bytes and seconds of the last accumulator reduction on this rank (for benchmarks). */
void swfs_mpi_team_last_reduce(const swfs_team *t, double *bytes, double *seconds);

SWFS_END_DECLS

#endif

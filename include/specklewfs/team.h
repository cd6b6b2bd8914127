/* A team: several processes running one command together on shares of one data set
 * (`mpirun -n N specklewfs stream ...`; docs/cluster.md).
 *
 * The library links no message-passing library. A team is a table of collective
 * operations; src/mpi implements it over an MPI communicator (team_mpi.h), and a run given
 * a team (run.h: the `team` member of the run options) processes only its share of the
 * data set and meets the other members through these calls. Every member must make the
 * same sequence of calls; the runs are written so that they do, also when a member fails
 * (it passes its status to `agree` at the next meeting point instead of returning).
 * A NULL team, or a team of one, is the ordinary single-process run.
 *
 * Member 0 holds the data set's first frames and writes every product; no other member
 * writes a product, so a failure anywhere leaves no product behind. */
#ifndef SWFS_TEAM_H
#define SWFS_TEAM_H

#include <stddef.h>

#include "specklewfs/accum.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/defs.h"

SWFS_BEGIN_DECLS

typedef struct swfs_team {
    int rank, size;  /* this member, number of members */
    void *ctx;       /* the implementation's own state */
    /* Every member passes its status; all return the status of the lowest-ranked member
     * that failed (SWFS_OK when none did), with that member's message, prefixed
     * "rank r of n: ", as their last error (status.h). A message that already has the
     * prefix (a failure agreed on before, passed on) keeps it as it is. */
    int (*agree)(void *ctx, int status);
    /* `bytes` of buf from member `root` to every member. */
    int (*bcast)(void *ctx, void *buf, size_t bytes, int root);
    /* Flat accumulator states (accum.h: swfs_accum_export, nx x ny pixels) of all members
     * merged exactly (swfs_accum_merge_state), in rank order, into member 0's `state`; the
     * other members' `state` is left unspecified. */
    int (*merge_accum)(void *ctx, double *state, size_t nx, size_t ny);
    /* v[0..n) summed over the members; every member receives the sums. */
    int (*sum)(void *ctx, double *v, size_t n);
    /* Member 0 receives every member's `bytes` (counts[r] from member r) one after another
     * in rank order into `all`; member 0's own part must already be in place at the start
     * of `all` (it passes mine == all). Other members pass all = NULL, counts = NULL. */
    int (*gather)(void *ctx, const void *mine, size_t bytes, void *all, const size_t *counts);
} swfs_team;

/* 1 when t is a team of more than one member (a distributed run). */
int swfs_team_active(const swfs_team *t);
/* 1 on the member that writes the products (member 0, or a process alone). */
int swfs_team_writer(const swfs_team *t);

/* This member's share of a data set of nseg segments (cubes) of len[s] items (frames),
 * in order: items [*first, *first + *count) of their concatenation. Shares are
 * contiguous, in rank order, and balanced by items, not segments: a member may take part
 * of a segment. A cut inside a segment falls on a multiple of `grain` items from the
 * segment's start (0 or 1: anywhere), so that a member's batches are those of the
 * single-process run. Member 0's share is never empty when there are items. Alone
 * (size <= 1): the whole data set. */
void swfs_team_share(const size_t *len, size_t nseg, size_t grain, int rank, int size, size_t *first,
                     size_t *count);

/* t->agree(status), or status itself without a team. */
int swfs_team_agree(const swfs_team *t, int status);
/* Member 0's `bytes` at v to every member of an active team; nothing alone (SWFS_OK). */
int swfs_team_bcast0(const swfs_team *t, void *v, size_t bytes);
/* The union of every member's accumulator `mine` into member 0's `out` (an accumulator of
 * the same size, may be `mine`; other members' out is not touched and may be NULL).
 * Without a team, out becomes a copy of mine. Transports swfs_accum_state_len(nx, ny)
 * doubles per member. */
int swfs_team_merge_accum(const swfs_team *t, const swfs_accum *mine, swfs_accum *out);
/* Every member's pipeline time mean (pipeline.h swfs_pipeline_mean_state) summed over the
 * team, sums and exposure count, into every member's p; nothing without a team. */
int swfs_team_sum_pipeline_mean(const swfs_team *t, swfs_pipeline *p);

SWFS_END_DECLS

#endif

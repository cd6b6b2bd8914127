/* A team over MPI: see include/specklewfs/team_mpi.h. */
#include "specklewfs/team_mpi.h"
#include "specklewfs/status.h"

#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct mpi_team {
    swfs_team t;
    MPI_Comm comm;
    MPI_Op merge;
    double last_bytes, last_seconds;
} mpi_team;

/* What the merge operation needs to know about the states it combines: their size and
 * the first failure, attached to the reduction's datatype (the operation's only context). */
typedef struct op_info {
    size_t nx, ny;
    double *scratch; /* one state */
    int status;
} op_info;

static int op_keyval = MPI_KEYVAL_INVALID;

/* MPI's contract for a reduction operation: inout = in (o) inout, with `in` the partial
 * result of the lower ranks. Declared non-commutative, so MPI keeps the ranks' order. The
 * lower ranks' state is the one merged into (in a scratch copy: `in` is MPI's), so the
 * union keeps what the single-process run keeps from its first frames -- the provisional
 * centres of the regression statistics (regress.h) are the data set's first frame's --
 * and the products match it to rounding, whatever the tree MPI reduces along. */
static void merge_op(void *in, void *inout, int *len, MPI_Datatype *dt)
{
    op_info *info = NULL;
    int flag = 0;
    MPI_Type_get_attr(*dt, op_keyval, &info, &flag);
    if (!flag || !info) return;
    const size_t n = swfs_accum_state_len(info->nx, info->ny);
    for (int i = 0; i < *len; i++) {
        double *dst = (double *)inout + (size_t)i * n;
        memcpy(info->scratch, (const double *)in + (size_t)i * n, n * sizeof(double));
        int rc = swfs_accum_merge_state(info->scratch, dst, info->nx, info->ny);
        if (rc && !info->status) info->status = rc;
        memcpy(dst, info->scratch, n * sizeof(double));
    }
}

static int mpi_fail(int err, const char *what)
{
    char msg[MPI_MAX_ERROR_STRING];
    int len = 0;
    MPI_Error_string(err, msg, &len);
    return swfs_fail(SWFS_ERR_IO, "MPI: %s failed: %s", what, msg);
}

static int agree(void *ctx, int status)
{
    mpi_team *m = ctx;
    int mine = status ? m->t.rank : m->t.size, lowest = m->t.size;
    int err = MPI_Allreduce(&mine, &lowest, 1, MPI_INT, MPI_MIN, m->comm);
    if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Allreduce (status)");
    if (lowest == m->t.size) return SWFS_OK;
    struct {
        int code;
        char msg[2048];
    } buf;
    memset(&buf, 0, sizeof buf);
    if (m->t.rank == lowest) {
        buf.code = status;
        snprintf(buf.msg, sizeof buf.msg, "%s", swfs_last_error());
    }
    if ((err = MPI_Bcast(&buf, (int)sizeof buf, MPI_BYTE, lowest, m->comm)) != MPI_SUCCESS)
        return mpi_fail(err, "MPI_Bcast (status)");
    buf.msg[sizeof buf.msg - 1] = '\0';
    /* A failure agreed on before keeps the rank it names. */
    int r = -1, n = -1, pos = 0;
    if (sscanf(buf.msg, "rank %d of %d: %n", &r, &n, &pos) == 2 && pos > 0 && n == m->t.size)
        return swfs_fail(buf.code, "%s", buf.msg);
    return swfs_fail(buf.code, "rank %d of %d: %s", lowest, m->t.size, buf.msg);
}

/* Messages of at most 1 GiB: MPI counts are ints. */
enum { CHUNK = 1 << 30 };

static int bcast(void *ctx, void *buf, size_t bytes, int root)
{
    mpi_team *m = ctx;
    for (size_t off = 0; off < bytes; off += CHUNK) {
        const size_t n = bytes - off < CHUNK ? bytes - off : CHUNK;
        int err = MPI_Bcast((char *)buf + off, (int)n, MPI_BYTE, root, m->comm);
        if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Bcast");
    }
    return SWFS_OK;
}

static int sum(void *ctx, double *v, size_t n)
{
    mpi_team *m = ctx;
    if (n > INT_MAX) return swfs_fail(SWFS_ERR_ARG, "MPI: %zu values to sum at once", n);
    int err = MPI_Allreduce(MPI_IN_PLACE, v, (int)n, MPI_DOUBLE, MPI_SUM, m->comm);
    return err == MPI_SUCCESS ? SWFS_OK : mpi_fail(err, "MPI_Allreduce (sum)");
}

static int gather(void *ctx, const void *mine, size_t bytes, void *all, const size_t *counts)
{
    mpi_team *m = ctx;
    const int tag = 7;
    if (m->t.rank) {
        for (size_t off = 0; off < bytes; off += CHUNK) {
            const size_t n = bytes - off < CHUNK ? bytes - off : CHUNK;
            int err = MPI_Send((const char *)mine + off, (int)n, MPI_BYTE, 0, tag, m->comm);
            if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Send");
        }
        return SWFS_OK;
    }
    size_t at = counts[0];
    for (int r = 1; r < m->t.size; r++) {
        for (size_t off = 0; off < counts[r]; off += CHUNK) {
            const size_t n = counts[r] - off < CHUNK ? counts[r] - off : CHUNK;
            int err = MPI_Recv((char *)all + at + off, (int)n, MPI_BYTE, r, tag, m->comm, MPI_STATUS_IGNORE);
            if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Recv");
        }
        at += counts[r];
    }
    return SWFS_OK;
}

static int merge_accum(void *ctx, double *state, size_t nx, size_t ny)
{
    mpi_team *m = ctx;
    const size_t n = swfs_accum_state_len(nx, ny);
    if (n > INT_MAX) return swfs_fail(SWFS_ERR_ARG, "MPI: an accumulator state of %zu doubles is too large", n);
    /* One element of the reduction is one whole state, so that MPI never splits a state
     * between two calls of the operation. */
    MPI_Datatype dt;
    int err = MPI_Type_contiguous((int)n, MPI_DOUBLE, &dt);
    if (err == MPI_SUCCESS) err = MPI_Type_commit(&dt);
    if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Type_contiguous");
    op_info info = {nx, ny, malloc(n * sizeof(double)), SWFS_OK};
    int rc = agree(m, info.scratch ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "MPI: out of memory for a %zu-double "
                                                                           "accumulator state", n));
    if (rc) {
        MPI_Type_free(&dt);
        free(info.scratch);
        return rc;
    }
    err = MPI_Type_set_attr(dt, op_keyval, &info);
    const double t0 = MPI_Wtime();
    if (err == MPI_SUCCESS)
        err = MPI_Reduce(m->t.rank ? state : MPI_IN_PLACE, m->t.rank ? NULL : state, 1, dt, m->merge, 0, m->comm);
    m->last_seconds = MPI_Wtime() - t0;
    m->last_bytes = (double)n * sizeof(double);
    MPI_Type_free(&dt);
    free(info.scratch);
    if (err != MPI_SUCCESS) return mpi_fail(err, "MPI_Reduce (accumulators)");
    return info.status ? swfs_fail_context(info.status, "merging accumulator states") : SWFS_OK;
}

int swfs_mpi_team_create(MPI_Comm comm, swfs_team **out)
{
    *out = NULL;
    int inited = 0;
    MPI_Initialized(&inited);
    if (!inited) return swfs_fail(SWFS_ERR_ARG, "MPI team: MPI is not initialized");
    mpi_team *m = calloc(1, sizeof *m);
    if (!m) return swfs_fail(SWFS_ERR_NOMEM, "MPI team: out of memory");
    int err = MPI_Comm_dup(comm, &m->comm);
    if (err != MPI_SUCCESS) {
        free(m);
        return mpi_fail(err, "MPI_Comm_dup");
    }
    MPI_Comm_rank(m->comm, &m->t.rank);
    MPI_Comm_size(m->comm, &m->t.size);
    if (op_keyval == MPI_KEYVAL_INVALID)
        err = MPI_Type_create_keyval(MPI_TYPE_NULL_COPY_FN, MPI_TYPE_NULL_DELETE_FN, &op_keyval, NULL);
    if (err == MPI_SUCCESS) err = MPI_Op_create(merge_op, 0, &m->merge);
    if (err != MPI_SUCCESS) {
        MPI_Comm_free(&m->comm);
        free(m);
        return mpi_fail(err, "creating the merge operation");
    }
    m->t.ctx = m;
    m->t.agree = agree;
    m->t.bcast = bcast;
    m->t.merge_accum = merge_accum;
    m->t.sum = sum;
    m->t.gather = gather;
    *out = &m->t;
    return SWFS_OK;
}

void swfs_mpi_team_free(swfs_team *t)
{
    if (!t) return;
    mpi_team *m = t->ctx;
    MPI_Op_free(&m->merge);
    MPI_Comm_free(&m->comm);
    free(m);
}

void swfs_mpi_team_last_reduce(const swfs_team *t, double *bytes, double *seconds)
{
    const mpi_team *m = t->ctx;
    *bytes = m->last_bytes;
    *seconds = m->last_seconds;
}

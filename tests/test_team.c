/* Shares of a data set for a team (team.h), without MPI: contiguous, covering every frame
 * once, balanced by frames within one batch, cut only at batch boundaries inside a cube,
 * member 0 never empty; and a team of threads running `estimate` whose product equals the
 * single-process one (the collective contract of team.h, as src/mpi implements it). */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"

#include <complex.h>
#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Every property of one split. */
static void check_split(const size_t *len, size_t nseg, size_t grain, int size)
{
    size_t total = 0, maxlen = 0;
    for (size_t s = 0; s < nseg; s++) {
        total += len[s];
        if (len[s] > maxlen) maxlen = len[s];
    }
    size_t next = 0;
    for (int r = 0; r < size; r++) {
        size_t f, n;
        swfs_team_share(len, nseg, grain, r, size, &f, &n);
        assert_int_equal(f, next);
        next = f + n;
        if (r == 0 && total) assert_true(n > 0);
        /* a cut inside a segment lies on a multiple of grain from its start */
        size_t b = 0;
        for (size_t s = 0; s < nseg && r > 0; s++) {
            if (f > b && f < b + len[s]) assert_int_equal((f - b) % (grain ? grain : 1), 0);
            b += len[s];
        }
        /* balance: a share differs from total/size by less than two batches (one at each
         * end), or by less than a segment when cuts fall between segments only */
        const double ideal = (double)total / size, slack = 2.0 * (double)(grain > maxlen ? maxlen : (grain ? grain : 1));
        if (!(r == 0 && (double)n > ideal)) assert_true(fabs((double)n - ideal) <= slack + 1.0);
    }
    assert_int_equal(next, total);
}

static void test_shares(void **state)
{
    (void)state;
    const size_t a[] = {37, 50, 0, 23, 41};
    for (int size = 1; size <= 7; size++)
        for (size_t grain = 0; grain <= 64; grain += grain < 4 ? 1 : 15) check_split(a, 5, grain, size);
    /* one cube (estimate), many members: frames split to the frame */
    const size_t one[] = {1000};
    for (int size = 1; size <= 16; size++) check_split(one, 1, 1, size);
    size_t f, n;
    swfs_team_share(one, 1, 1, 3, 4, &f, &n);
    assert_int_equal(f, 750);
    assert_int_equal(n, 250);
    /* more members than batches: the later ones get nothing, member 0 the first batch */
    const size_t small[] = {0, 10};
    swfs_team_share(small, 2, 8, 0, 6, &f, &n);
    assert_int_equal(f, 0);
    assert_true(n >= 8);
    for (int size = 1; size <= 12; size++) check_split(small, 2, 8, size);
    /* an empty data set */
    const size_t none[] = {0, 0};
    swfs_team_share(none, 2, 8, 1, 3, &f, &n);
    assert_int_equal(n, 0);
    /* a night: 2^40 frames over 1024 members, no overflow */
    const size_t night[] = {(size_t)1 << 40};
    swfs_team_share(night, 1, 128, 1023, 1024, &f, &n);
    assert_int_equal(f + n, (size_t)1 << 40);
    assert_true(n >= ((size_t)1 << 30) - 128 && n <= ((size_t)1 << 30) + 128);
}

/* ---- a team of threads --------------------------------------------------------- */

#define NT 3
typedef struct shared {
    pthread_barrier_t bar;
    int status[NT];
    char msg[NT][512];
    void *slot[NT];
    size_t bytes[NT];
    double sums[NT][8];
} shared;

typedef struct member {
    swfs_team t;
    shared *sh;
} member;

static int th_agree(void *ctx, int status)
{
    member *m = ctx;
    shared *sh = m->sh;
    sh->status[m->t.rank] = status;
    snprintf(sh->msg[m->t.rank], sizeof sh->msg[0], "%s", status ? swfs_last_error() : "");
    pthread_barrier_wait(&sh->bar);
    int rc = SWFS_OK, who = -1;
    for (int r = 0; r < NT && who < 0; r++)
        if (sh->status[r]) who = r;
    char msg[600];
    if (who >= 0) snprintf(msg, sizeof msg, "%s", sh->msg[who]);
    pthread_barrier_wait(&sh->bar);
    int a, b, pos = 0;
    if (who >= 0 && sscanf(msg, "rank %d of %d: %n", &a, &b, &pos) == 2 && pos > 0) /* agreed before */
        rc = swfs_fail(sh->status[who], "%s", msg);
    else if (who >= 0) rc = swfs_fail(sh->status[who], "rank %d of %d: %s", who, NT, msg);
    return rc;
}

static int th_bcast(void *ctx, void *buf, size_t bytes, int root)
{
    member *m = ctx;
    if (m->t.rank == root) m->sh->slot[root] = buf;
    pthread_barrier_wait(&m->sh->bar);
    if (m->t.rank != root) memcpy(buf, m->sh->slot[root], bytes);
    pthread_barrier_wait(&m->sh->bar);
    return SWFS_OK;
}

/* rank order: ((s0 + s1) + s2), as MPI's non-commutative reduction promises */
static int th_merge(void *ctx, double *state, size_t nx, size_t ny)
{
    member *m = ctx;
    m->sh->slot[m->t.rank] = state;
    pthread_barrier_wait(&m->sh->bar);
    int rc = SWFS_OK;
    if (m->t.rank == 0)
        for (int r = 1; r < NT && !rc; r++) rc = swfs_accum_merge_state(state, m->sh->slot[r], nx, ny);
    pthread_barrier_wait(&m->sh->bar);
    return rc;
}

static int th_sum(void *ctx, double *v, size_t n)
{
    member *m = ctx;
    memcpy(m->sh->sums[m->t.rank], v, n * sizeof *v);
    pthread_barrier_wait(&m->sh->bar);
    for (size_t k = 0; k < n; k++) {
        v[k] = 0;
        for (int r = 0; r < NT; r++) v[k] += m->sh->sums[r][k];
    }
    pthread_barrier_wait(&m->sh->bar);
    return SWFS_OK;
}

static int th_gather(void *ctx, const void *mine, size_t bytes, void *all, const size_t *counts)
{
    member *m = ctx;
    m->sh->slot[m->t.rank] = (void *)mine;
    m->sh->bytes[m->t.rank] = bytes;
    pthread_barrier_wait(&m->sh->bar);
    size_t at = 0;
    for (int r = 1; r < NT && m->t.rank == 0; r++) {
        at += counts[r - 1];
        memcpy((char *)all + at, m->sh->slot[r], counts[r]);
    }
    pthread_barrier_wait(&m->sh->bar);
    return SWFS_OK;
}

typedef struct job {
    member m;
    swfs_estimate_run_options o;
    int rc;
    char err[512];
} job;

static void *run_member(void *arg)
{
    job *j = arg;
    swfs_estimate_run_result r;
    j->rc = swfs_estimate_run(&j->o, &r);
    if (j->rc) snprintf(j->err, sizeof j->err, "%s", swfs_last_error());
    swfs_halo_free(r.halo);
    return NULL;
}

static int run_team(const char *science, const char *speckles, const char *out, job *jobs)
{
    shared sh;
    memset(&sh, 0, sizeof sh);
    pthread_barrier_init(&sh.bar, NULL, NT);
    pthread_t th[NT];
    for (int r = 0; r < NT; r++) {
        job *j = &jobs[r];
        memset(j, 0, sizeof *j);
        j->m.sh = &sh;
        j->m.t = (swfs_team){r, NT, &j->m, th_agree, th_bcast, th_merge, th_sum, th_gather};
        swfs_estimate_run_options_default(&j->o);
        j->o.science = science;
        j->o.speckles = speckles;
        j->o.out = out;
        j->o.block = 5;
        j->o.team = &j->m.t;
        pthread_create(&th[r], NULL, run_member, j);
    }
    for (int r = 0; r < NT; r++) pthread_join(th[r], NULL);
    pthread_barrier_destroy(&sh.bar);
    return jobs[0].rc;
}

static void write_cubes(const char *sci, const char *sp, size_t nframes)
{
    const size_t n = 12;
    swfs_real *cube = swfs_real_alloc(n, n, nframes);
    swfs_cplx *psi = swfs_cplx_alloc(n, n, nframes);
    assert_true(cube && psi);
    swfs_rng r;
    swfs_rng_seed(&r, 5);
    for (size_t f = 0; f < nframes; f++)
        for (size_t p = 0; p < n * n; p++) {
            const double complex ps = swfs_rng_normal(&r) + I * swfs_rng_normal(&r), Psi = 3.0 * cexp(0.3 * I * (double)p);
            psi->data[f * n * n + p] = ps;
            const double complex t = Psi + 2.0 * ps;
            cube->data[f * n * n + p] = creal(t * conj(t)) + 0.5 * swfs_rng_normal(&r);
        }
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, sci));
    assert_ok(swfs_fits_out_real(o, NULL, cube, -64));
    assert_ok(swfs_fits_out_commit(o));
    assert_ok(swfs_fits_out_create(&o, sp));
    assert_ok(swfs_fits_out_cplx(o, NULL, psi, -64));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(cube);
    swfs_cplx_free(psi);
}

static void test_thread_team_estimate(void **state)
{
    (void)state;
    char sci[1024], sp[1024], h1[1024], h3[1024];
    snprintf(sci, sizeof sci, "%s", test_path("team_sci.fits"));
    snprintf(sp, sizeof sp, "%s", test_path("team_sp.fits"));
    snprintf(h1, sizeof h1, "%s", test_path("team_h1.fits"));
    snprintf(h3, sizeof h3, "%s", test_path("team_h3.fits"));
    write_cubes(sci, sp, 101);
    remove(h3);
    swfs_estimate_run_options o;
    swfs_estimate_run_options_default(&o);
    o.science = sci;
    o.speckles = sp;
    o.out = h1;
    swfs_estimate_run_result r1;
    assert_ok(swfs_estimate_run(&o, &r1));
    job jobs[NT];
    if (run_team(sci, sp, h3, jobs)) fail_msg("%s", jobs[0].err);
    for (int r = 1; r < NT; r++) assert_int_equal(jobs[r].rc, 0);
    swfs_halo *h = NULL;
    assert_ok(swfs_halo_read(h3, &h, NULL));
    assert_int_equal(h->frames, 101);
    const size_t np = h->halo->nx * h->halo->ny;
    double hmax = 0;
    for (size_t p = 0; p < np; p++) hmax = fmax(hmax, cabs(r1.halo->halo->data[p]));
    for (size_t p = 0; p < np; p++) {
        assert_true(cabs(h->halo->data[p] - r1.halo->halo->data[p]) <= 1e-12 * hmax);
        assert_true(fabs(h->mean_i->data[p] - r1.halo->mean_i->data[p]) <= 1e-12 * fabs(r1.halo->mean_i->data[p]));
    }
    swfs_halo_free(h);
    swfs_halo_free(r1.halo);

    /* A failure on one member (here: all, a missing file) stops every member, with the
     * lowest failing member's message, and no product. */
    char missing[1024], bad[1024];
    snprintf(missing, sizeof missing, "%s", test_path("team_missing.fits"));
    snprintf(bad, sizeof bad, "%s", test_path("team_bad.fits"));
    remove(bad);
    assert_int_not_equal(run_team(missing, sp, bad, jobs), 0);
    for (int r = 0; r < NT; r++) {
        assert_int_not_equal(jobs[r].rc, 0);
        assert_non_null(strstr(jobs[r].err, "rank 0 of 3"));
        assert_non_null(strstr(jobs[r].err, "team_missing.fits"));
    }
    assert_false(test_file_exists(bad));
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_shares),
        cmocka_unit_test(test_thread_team_estimate),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

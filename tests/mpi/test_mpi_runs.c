/* Distributed runs (docs/cluster.md): `mpirun -n 2|3 specklewfs stream|speckles|estimate`
 * on a small synthetic data set whose cubes split unevenly across the ranks give the
 * products of the single-process run to 1e-12 relative; bad input on one rank (a truncated
 * telemetry file only the last ranks read) stops every rank with the file's name and no
 * product; periodic updates are refused. Registered only when MPI is built. */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/aperture.h"
#include "specklewfs/array.h"
#include "specklewfs/interp.h"
#include "specklewfs/sparse.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/team.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>

#define NPUP 24
#define NF 14

/* The teams tried: 2 and 3 processes (3: uneven shares), in every build. */
#define NP_FIRST 2
#define NSUB 4
#define NSL (2 * NSUB * NSUB)
#define RATIO 3.37
#define DIAM 6.5
#define LAMBDA 3.8e-6
#define PIXSCALE 0.5
#define NCUBES 5

/* Cube 2 straddles two telemetry files: the runs skip it. The others split unevenly. */
static const size_t cube_frames[NCUBES] = {37, 50, 10, 23, 41};
static const double cube_start[NCUBES] = {10.25, 140.0, 300.0, 5.5, 100.75};
static const char *cube_slopes[NCUBES] = {"slopes_a.fits", "slopes_a.fits", "slopes_a.fits", "slopes_b.fits",
                                          "slopes_b.fits"};
static const size_t nwfs_a = 330, nwfs_b = 260;

static char dir[1024];

static const char *in_dir(const char *name)
{
    static char buf[8][1200];
    static int k = 0;
    char *b = buf[k++ % 8];
    snprintf(b, sizeof buf[0], "%s/%s", dir, name);
    return b;
}

/* `[mpirun -n N] specklewfs ARGS` in dir; output in out; the exit status. */
static int run(int nproc, const char *args, char *out, size_t cap)
{
    char cmd[8192];
    if (nproc)
        snprintf(cmd, sizeof cmd, "cd '%s' && %s --oversubscribe -n %d %s %s 2>&1", dir, SWFS_MPIEXEC, nproc,
                 SWFS_CLI_BIN, args);
    else
        snprintf(cmd, sizeof cmd, "cd '%s' && %s %s 2>&1", dir, SWFS_CLI_BIN, args);
    FILE *p = popen(cmd, "r");
    size_t len = 0;
    out[0] = '\0';
    if (!p) return -1;
    while (len + 1 < cap && fgets(out + len, (int)(cap - len), p)) len = strlen(out);
    int st = pclose(p);
    return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

static void run_ok(int nproc, const char *args)
{
    static char out[65536];
    int rc = run(nproc, args, out, sizeof out);
    if (rc) print_message("%s\n", out);
    assert_int_equal(rc, 0);
}

static swfs_geom geom(void)
{
    swfs_geom g;
    swfs_geom_init(&g);
    g.wavelen = LAMBDA;
    g.teldiam = DIAM;
    g.obscur = 0.1;
    g.pixscale = PIXSCALE;
    g.pupdx = DIAM / (NPUP - 1.0);
    g.pupn = NPUP;
    return g;
}

/* Slopes of random actuator displacements (D z, so that a reconstructor learned from them
 * finds something), a tip-tilt drift and a little noise. */
static void write_slopes(const char *name, size_t nwfs, const double *D, size_t nact, swfs_rng *r)
{
    swfs_real *sl = swfs_real_alloc(NSL, nwfs, 1);
    double *z = malloc(nact * sizeof *z);
    assert_true(sl && z);
    for (size_t k = 0; k < nwfs; k++) {
        for (size_t a = 0; a < nact; a++) z[a] = 1e-7 * swfs_rng_normal(r);
        for (size_t i = 0; i < NSL; i++) {
            double v = 0;
            for (size_t a = 0; a < nact; a++) v += D[i * nact + a] * z[a];
            sl->data[k * NSL + i] = v + 1e-6 * (0.05 * swfs_rng_normal(r) + (i < NSL / 2 ? 0.3 : -0.2) * sin(0.05 * (double)k));
        }
    }
    free(z);
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, in_dir(name)));
    assert_ok(swfs_fits_out_real(o, NULL, sl, -64));
    assert_ok(swfs_fits_out_key_double(o, "WFSRATE", 527.0, "[Hz]"));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(sl);
}

static size_t science_frames(void)
{
    size_t n = 0;
    for (int k = 0; k < NCUBES; k++) n += cube_frames[k];
    return n;
}

static void write_science(const swfs_real *sci)
{
    swfs_geom g = geom();
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, in_dir("sci.fits")));
    assert_ok(swfs_fits_out_set_stamp(o, &g, NULL, 0));
    assert_ok(swfs_fits_out_real(o, NULL, sci, -64));
    assert_ok(swfs_fits_out_key_double(o, "RDNOISE", 2.0, "[counts]"));
    assert_ok(swfs_fits_out_commit(o));
}

/* The data set: telemetry, timing table, actuators, a reconstructor, and a science cube
 * I = |Psi + 0.8 psi|^2 + noise with psi the single-process speckles of the usable cubes. */
static void make_data(void)
{
    swfs_rng r;
    swfs_rng_seed(&r, 77);
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, 1.2, 0.6, &xy, &nact));
    assert_ok(swfs_actuators_write(xy, nact, in_dir("act.fits")));
    double mask[NPUP * NPUP], *D = NULL;
    const double pupdx = DIAM / (NPUP - 1.0);
    swfs_sparse *T = NULL;
    swfs_shwfs *wfs = NULL;
    size_t nout = 0;
    assert_ok(swfs_aperture_make(mask, NPUP, pupdx, DIAM, 0.1, 0, 0.0));
    assert_ok(swfs_interp_ct_grid(xy, nact, NPUP, pupdx, mask, &T, &nout));
    assert_ok(swfs_shwfs_create(&wfs, NSUB, DIAM, mask, NPUP, pupdx, 0.5));
    assert_ok(swfs_interaction_matrix(wfs, T, &D));
    /* A reconstructor of the model's D (speckles checks a given matrix against it). */
    swfs_recon *rec = NULL;
    assert_ok(swfs_recon_svd(D, NSL, nact, 5e-2, 0, &rec));
    assert_ok(swfs_recon_write(rec, in_dir("recon.fits")));
    /* the same map as a space-time one of lags 0, -2 and 3 (a third of it at each other lag) */
    swfs_recon st = {.nact = rec->nact, .nslopes = 3 * NSL, .W = calloc(3 * NSL * rec->nact, sizeof(double)), .nlags = 3,
                     .lags = {0, -2, 3}};
    assert_non_null(st.W);
    for (size_t a = 0; a < rec->nact; a++)
        for (size_t i = 0; i < 3 * (size_t)NSL; i++) st.W[a * 3 * NSL + i] = (i < NSL ? 1.0 : 0.3) * rec->W[a * NSL + i % NSL];
    assert_ok(swfs_recon_write(&st, in_dir("recon_st.fits")));
    free(st.W);
    swfs_recon_free(rec);
    write_slopes("slopes_a.fits", nwfs_a, D, nact, &r);
    write_slopes("slopes_b.fits", nwfs_b, D, nact, &r);
    free(D);
    free(xy);
    swfs_sparse_free(T);
    swfs_shwfs_free(wfs);

    swfs_timing t;
    memset(&t, 0, sizeof t);
    swfs_timing_cube c[NCUBES];
    memset(c, 0, sizeof c);
    t.ratio = RATIO;
    t.ncubes = NCUBES;
    t.cubes = c;
    t.fit.sign_x = t.fit.sign_y = 1;
    size_t first = 0;
    for (int k = 0; k < NCUBES; k++) {
        snprintf(c[k].camera, sizeof c[k].camera, "raw_%d.fits", k);
        snprintf(c[k].slopes, sizeof c[k].slopes, "%s", cube_slopes[k]);
        c[k].first = first;
        c[k].nframes = cube_frames[k];
        c[k].start = cube_start[k];
        c[k].status = k == 2 ? SWFS_CUBE_STRADDLES : SWFS_CUBE_OK;
        first += cube_frames[k];
    }
    assert_ok(swfs_timing_write(in_dir("timing.txt"), &t));

    /* A placeholder science cube (geometry and window), the speckles, then the real cube. */
    const size_t nsci = science_frames();
    swfs_real *sci = swfs_real_alloc(NF, NF, nsci);
    assert_non_null(sci);
    memset(sci->data, 0, NF * NF * nsci * sizeof(double));
    write_science(sci);
    run_ok(0, "speckles timing.txt --science sci.fits --actuators act.fits --recon recon.fits -o psi0.fits");
    swfs_cplx *psi = NULL;
    assert_ok(swfs_fits_read_cplx(in_dir("psi0.fits"), NULL, &psi, NULL));
    for (size_t k = 0, u = 0; k < NCUBES; k++)
        for (size_t j = 0; j < cube_frames[k]; j++) {
            double *frame = swfs_real_frame(sci, c[k].first + j);
            const swfs_complex *ps = k == 2 ? NULL : swfs_cplx_frame(psi, u++);
            for (size_t p = 0; p < NF * NF; p++) {
                const double complex Psi = 30.0 * cexp(I * 0.4 * (double)p) / (1.0 + 0.05 * (double)p);
                const double complex tot = Psi + (ps ? 0.8 * 40.0 * ps[p] : 0.0);
                frame[p] = creal(tot * conj(tot)) + 2.0 * swfs_rng_normal(&r);
            }
        }
    write_science(sci);
    swfs_real_free(sci);
    swfs_cplx_free(psi);
}

/* |a - b| <= rel max(|a|, floor_frac x the largest |a| of the plane) for every element (n
 * values; plane: values per image plane); NaN only where both are NaN. Returns the largest
 * relative gap. floor_frac = 1: relative to each plane's scale, the products' measure
 * (every estimate divides differences of moments: a pixel where they nearly cancel, e.g.
 * the radicand of eq:scale-factor, amplifies rounding -- measured up to 7e-13 of the
 * pixel's own value in HALO_LF); 1e-3: nearly elementwise, for the accumulator states. */
static double floor_frac = 1.0;
static double compare_planes(const double *a, const double *b, size_t n, size_t plane, double rel, const char *what)
{
    double worst = 0;
    for (size_t k0 = 0; k0 < n; k0 += plane) {
        double amax = 0;
        for (size_t k = k0; k < k0 + plane && k < n; k++)
            if (isfinite(a[k]) && fabs(a[k]) > amax) amax = fabs(a[k]);
        for (size_t k = k0; k < k0 + plane && k < n; k++) {
        if (isnan(a[k]) || isnan(b[k])) {
            if (!(isnan(a[k]) && isnan(b[k]))) fail_msg("%s: element %zu is %g vs %g", what, k, a[k], b[k]);
            continue;
        }
            const double scale = fmax(fabs(a[k]), floor_frac * amax);
            const double d = scale > 0 ? fabs(a[k] - b[k]) / scale : fabs(a[k] - b[k]);
            if (d > worst) worst = d;
            if (d > rel)
                fail_msg("%s: element %zu is %.17g vs %.17g (relative %.3g > %.3g)", what, k, a[k], b[k], d, rel);
        }
    }
    return worst;
}



/* Every image extension of two FITS products, real or complex, to rel. */
static void compare_products(const char *p1, const char *p2, const char *const *ext, size_t next, double rel)
{
    double worst = 0;
    for (size_t e = 0; e < next; e++) {
        char what[1200];
        snprintf(what, sizeof what, "%s vs %s [%s]", p1, p2, ext[e] ? ext[e] : "primary");
        swfs_fits_in *f = NULL;
        assert_ok(swfs_fits_in_open(&f, in_dir(p1), ext[e]));
        const int cplx = swfs_fits_in_shape(f)->is_complex;
        swfs_fits_in_close(f);
        if (cplx) {
            swfs_cplx *a = NULL, *b = NULL;
            assert_ok(swfs_fits_read_cplx(in_dir(p1), ext[e], &a, NULL));
            assert_ok(swfs_fits_read_cplx(in_dir(p2), ext[e], &b, NULL));
            assert_int_equal(a->nx * a->ny * a->nz, b->nx * b->ny * b->nz);
            double w = compare_planes((const double *)a->data, (const double *)b->data, 2 * a->nx * a->ny * a->nz,
                                      2 * a->nx * a->ny, rel, what);
            worst = fmax(worst, w);
            swfs_cplx_free(a);
            swfs_cplx_free(b);
        } else {
            swfs_real *a = NULL, *b = NULL;
            assert_ok(swfs_fits_read_real(in_dir(p1), ext[e], &a, NULL));
            assert_ok(swfs_fits_read_real(in_dir(p2), ext[e], &b, NULL));
            assert_int_equal(a->nx * a->ny * a->nz, b->nx * b->ny * b->nz);
            const double w = compare_planes(a->data, b->data, a->nx * a->ny * a->nz, a->nx * a->ny, rel, what);
            worst = fmax(worst, w);
            swfs_real_free(a);
            swfs_real_free(b);
        }
    }
    print_message("%s vs %s: largest relative difference %.3g over %zu extensions\n", p1, p2, worst, next);
}

static const char *halo_ext[] = {"HALO", "HALO_LF", "STAB", "GAIN", "GAIN_PIX", "VISIB", "SNR", "MEAN_I", "VAR_I",
                                 "MEAN_SP", "VAR_SP", "STAB_ERR", "CIRC", "VALID", "NFRAMES", "REGSTATE",
                                 "RESMEAN"};

static int setup(void **state)
{
    (void)state;
    snprintf(dir, sizeof dir, "%s", test_path("mpi_runs"));
    char mk[2200];
    snprintf(mk, sizeof mk, "rm -rf '%s' && mkdir -p '%s'", dir, dir);
    assert_int_equal(system(mk), 0);
    make_data();
    return 0;
}

/* The shares of the stream test split cubes: the split is by frames, not by cubes. */
static void test_shares_cut_cubes(void **state)
{
    (void)state;
    const size_t len[NCUBES] = {37, 50, 0, 23, 41};
    for (int size = 2; size <= 3; size++) {
        size_t inside = 0, total = 0, f, n, next = 0;
        for (int r = 0; r < size; r++) {
            swfs_team_share(len, NCUBES, 8, r, size, &f, &n);
            assert_int_equal(f, next);
            next = f + n;
            total += n;
            /* a cut at f > 0 that is no cube boundary */
            if (r > 0 && f != 37 && f != 87 && f != 110) inside++;
            print_message("%d ranks: rank %d takes frames %zu..%zu\n", size, r, f, f + n - 1);
        }
        assert_int_equal(total, 151);
        assert_true(inside > 0);
    }
}

static void test_stream_equal(void **state)
{
    (void)state;
    /* The pupil product through the moments: on this small synthetic window (14 x 14 pixels,
     * 7 spline intervals) the joint fit is ill-conditioned and amplifies the 1e-15 differences
     * of the merged halos; the halos themselves (REGSTATE included) are compared below. */
    const char *common = "stream --timing timing.txt --science sci.fits --recon recon.fits --actuators act.fits "
                         "--threads 1 --batch 8 --pupil-method moments";
    char args[2048];
    snprintf(args, sizeof args, "%s -o halo1.fits --checkpoint ck1.fits --static-out st1.fits --pupil-out pu1.fits", common);
    run_ok(0, args);
    for (int np = NP_FIRST; np <= 3; np++) {
        char h[64], ck[64], st[64], pu[64];
        snprintf(h, sizeof h, "halo%d.fits", np);
        snprintf(ck, sizeof ck, "ck%d.fits", np);
        snprintf(st, sizeof st, "st%d.fits", np);
        snprintf(pu, sizeof pu, "pu%d.fits", np);
        snprintf(args, sizeof args, "%s -o %s --checkpoint %s --static-out %s --pupil-out %s", common, h, ck, st, pu);
        run_ok(np, args);
        compare_products("halo1.fits", h, halo_ext, sizeof halo_ext / sizeof halo_ext[0], 1e-12);
        const char *st_ext[] = {NULL};
        compare_products("st1.fits", st, st_ext, 1, 0.0); /* member 0's first batch, sent as is */
        const char *pu_ext[] = {"FIELD", "WFE"};
        compare_products("pu1.fits", pu, pu_ext, 2, 1e-12);
        swfs_accum *a = NULL, *b = NULL;
        assert_ok(swfs_accum_load(in_dir("ck1.fits"), &a, NULL));
        assert_ok(swfs_accum_load(in_dir(ck), &b, NULL));
        assert_int_equal(a->frames, 151);
        assert_int_equal(b->frames, a->frames);
        assert_int_equal(b->reg->frames, a->reg->frames);
        const size_t n = swfs_accum_state_len(NF, NF);
        double *sa = malloc(n * sizeof *sa), *sb = malloc(n * sizeof *sb);
        assert_true(sa && sb);
        swfs_accum_export(a, sa);
        swfs_accum_export(b, sb);
        floor_frac = 1e-3;
        compare_planes(sa, sb, n - 4, NF * NF, 1e-12, ck);
        floor_frac = 1.0;
        for (size_t k = n - 4; k < n; k++) assert_true(sa[k] == sb[k]); /* the counts */
        free(sa);
        free(sb);
        swfs_accum_free(a);
        swfs_accum_free(b);
    }
    /* a space-time map: each member stacks its batches' lags from the files, across the
     * telemetry files' boundary, as the single process does */
    const char *st = "stream --timing timing.txt --science sci.fits --recon recon_st.fits --actuators act.fits "
                     "--threads 1 --batch 8 --pupil-method moments";
    snprintf(args, sizeof args, "%s -o halo_st1.fits", st);
    run_ok(0, args);
    snprintf(args, sizeof args, "%s -o halo_st2.fits", st);
    run_ok(2, args);
    compare_products("halo_st1.fits", "halo_st2.fits", halo_ext, sizeof halo_ext / sizeof halo_ext[0], 1e-12);
}

/* --max-frames: the first N frames of the data set, whatever the number of ranks. */
static void test_stream_max_frames(void **state)
{
    (void)state;
    const char *common = "stream --timing timing.txt --science sci.fits --recon recon.fits --actuators act.fits "
                         "--threads 1 --batch 8 --max-frames 100";
    char args[2048];
    snprintf(args, sizeof args, "%s -o mf1.fits", common);
    run_ok(0, args);
    snprintf(args, sizeof args, "%s -o mf3.fits", common);
    run_ok(3, args);
    compare_products("mf1.fits", "mf3.fits", halo_ext, sizeof halo_ext / sizeof halo_ext[0], 1e-12);
    swfs_halo *h = NULL;
    assert_ok(swfs_halo_read(in_dir("mf3.fits"), &h, NULL));
    assert_int_equal(h->frames, 100);
    swfs_halo_free(h);
}

static void test_speckles_and_estimate_equal(void **state)
{
    (void)state;
    /* The default reconstructor: a map taught for the observation (speckles --recon teach).
     * These random slopes show no frozen-flow layer, so member 0 teaches from loops at the
     * speed of their time correlation (run_speckles_teach.c: member 0 teaches, the others take
     * its map). */
    const char *common = "speckles timing.txt --science sci.fits --actuators act.fits --batch 8";
    char args[2048];
    static char out[65536];
    snprintf(args, sizeof args, "%s -o sp1.fits --match sci.fits scim1.fits", common);
    assert_int_equal(run(0, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "the space-time map of loops at the slopes' speed"));
    /* and a second map of a Gaussian DM's loops, the better one kept by the frames: a team
     * compares as one process does (member 0 teaches and decides), so the products below are
     * the same whichever it keeps */
    assert_non_null(strstr(out, "speckles: the loops' DM by the science frames: "));
    run_ok(0, "estimate scim1.fits sp1.fits -o est1.fits");
    const char *prim[] = {NULL};
    for (int np = NP_FIRST; np <= 3; np++) {
        char sp[64], sm[64], est[64];
        snprintf(sp, sizeof sp, "sp%d.fits", np);
        snprintf(sm, sizeof sm, "scim%d.fits", np);
        snprintf(est, sizeof est, "est%d.fits", np);
        /* two members teach anew (the same maps to the bit as one process's, below); three
         * reuse the single process's (member 0 finds them, the others take them) */
        snprintf(args, sizeof args, "%s -o %s --match sci.fits %s%s", common, sp, sm,
                 np == 3 ? " --teach-work sp1.teach" : "");
        assert_int_equal(run(np, args, out, sizeof out), 0);
        assert_non_null(strstr(out, "speckles: the loops' DM by the science frames: "));
        if (np == 3) assert_non_null(strstr(out, "speckles: reused sp1.teach/"));
        const char *sp_ext[] = {NULL, "RESMEAN"}; /* RESMEAN: the members' sums added (pipeline.h) */
        compare_products("sp1.fits", sp, sp_ext, 2, 1e-12);
        compare_products("scim1.fits", sm, prim, 1, 0.0);
        /* estimate over MPI on the single-process speckles: only the reduction differs */
        snprintf(args, sizeof args, "estimate scim1.fits sp1.fits -o %s --frames-per-read 7", est);
        run_ok(np, args);
        compare_products("est1.fits", est, halo_ext, sizeof halo_ext / sizeof halo_ext[0], 1e-12);
    }
    /* Where member 0 cannot teach (telemetry without WFSRATE: no rate for the loops) every
     * rank falls back to the von Karman MAP learned from the telemetry, as one process does:
     * member 0 decides, the others follow, and every rank builds the same map. */
    char cmd[4096];
    snprintf(cmd, sizeof cmd, "cd '%s' && mkdir -p norate && cp timing.txt sci.fits act.fits norate/", dir);
    assert_int_equal(system(cmd), 0);
    const char *names[] = {"slopes_a.fits", "slopes_b.fits"};
    for (int k = 0; k < 2; k++) {
        swfs_real *sl = NULL;
        swfs_fits_out *o = NULL;
        char to[64];
        snprintf(to, sizeof to, "norate/%s", names[k]);
        assert_ok(swfs_fits_read_real(in_dir(names[k]), NULL, &sl, NULL));
        assert_ok(swfs_fits_out_create(&o, in_dir(to)));
        assert_ok(swfs_fits_out_real(o, NULL, sl, -64));
        assert_ok(swfs_fits_out_commit(o));
        swfs_real_free(sl);
    }
    const char *nr = "speckles norate/timing.txt --science norate/sci.fits --actuators norate/act.fits --batch 8";
    snprintf(args, sizeof args, "%s -o norate/sp0.fits", nr);
    assert_int_equal(run(0, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "no map could be taught"));
    assert_non_null(strstr(out, "WFSRATE"));
    snprintf(args, sizeof args, "%s -o norate/sp2.fits", nr);
    assert_int_equal(run(2, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "no map could be taught"));
    compare_products("norate/sp0.fits", "norate/sp2.fits", (const char *[]){NULL, "RESMEAN"}, 2, 1e-12);
    /* at the WFS rate, cut inside cubes too */
    run_ok(0, "speckles timing.txt --science sci.fits --actuators act.fits --recon recon.fits --wfs-rate --batch 16 "
           "-o w1.fits");
    run_ok(3, "speckles timing.txt --science sci.fits --actuators act.fits --recon recon.fits --wfs-rate --batch 16 "
           "-o w3.fits");
    compare_products("w1.fits", "w3.fits", prim, 1, 1e-12);
}

/* A truncated telemetry file that only the later ranks read stops every rank, names the
 * file, and leaves no product (not even a .part). */
static void test_truncated_on_one_rank(void **state)
{
    (void)state;
    char cmd[4096], out[65536];
    snprintf(cmd, sizeof cmd, "cd '%s' && mkdir -p bad && cp timing.txt sci.fits recon.fits act.fits slopes_a.fits bad/ "
             "&& head -c 20000 slopes_b.fits > bad/slopes_b.fits", dir);
    assert_int_equal(system(cmd), 0);
    for (int np = NP_FIRST; np <= 3; np++) {
        int rc = run(np, "stream --timing bad/timing.txt --science bad/sci.fits --recon bad/recon.fits "
                     "--actuators bad/act.fits --threads 1 --batch 8 -o bad/halo.fits --checkpoint bad/ck.fits",
                     out, sizeof out);
        print_message("%s", out);
        assert_int_not_equal(rc, 0);
        assert_non_null(strstr(out, "slopes_b.fits"));
        assert_non_null(strstr(out, "truncated"));
        assert_non_null(strstr(out, "rank"));
        assert_false(test_file_exists(in_dir("bad/halo.fits")));
        assert_false(test_file_exists(in_dir("bad/halo.fits.part")));
        assert_false(test_file_exists(in_dir("bad/ck.fits")));
        rc = run(np, "speckles bad/timing.txt --science bad/sci.fits --actuators bad/act.fits --recon bad/recon.fits "
                 "-o bad/sp.fits --write-recon bad/w.fits --match bad/sci.fits bad/scim.fits", out, sizeof out);
        print_message("%s", out);
        assert_int_not_equal(rc, 0);
        assert_non_null(strstr(out, "slopes_b.fits"));
        assert_false(test_file_exists(in_dir("bad/sp.fits")));
        assert_false(test_file_exists(in_dir("bad/w.fits")));
        assert_false(test_file_exists(in_dir("bad/scim.fits")));
    }
}

static void test_periodic_updates_refused(void **state)
{
    (void)state;
    char out[65536];
    int rc = run(2, "stream --timing timing.txt --science sci.fits --recon recon.fits --actuators act.fits "
                 "--threads 1 -o ev.fits --every 16", out, sizeof out);
    print_message("%s", out);
    assert_int_not_equal(rc, 0);
    assert_non_null(strstr(out, "periodic updates"));
    assert_false(test_file_exists(in_dir("ev.fits")));
}

/* A sweep's table without its comment lines and last (timing) column. */
static void table_body(const char *name, char *buf, size_t cap)
{
    FILE *f = fopen(in_dir(name), "r");
    assert_non_null(f);
    char line[4096];
    size_t len = 0;
    buf[0] = '\0';
    while (fgets(line, sizeof line, f)) {
        if (line[0] == '#') continue;
        char *tab = strrchr(line, '\t');
        assert_non_null(tab);
        *tab = '\0';
        len += (size_t)snprintf(buf + len, cap - len, "%s\n", line);
        assert_true(len < cap);
    }
    fclose(f);
}

/* simulate / correct sweeps shared out over 2 and 3 ranks: the single-process table. */
static void test_sweeps_equal(void **state)
{
    (void)state;
    const char *small = "screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24 ncp_gauss_x=-0.4 ncp_gauss_y=0.8 "
                        "ncp_gauss_radius=0.4 threads=1";
    FILE *f = fopen(in_dir("sets.txt"), "w");
    assert_non_null(f);
    fputs("read_noise=0 seed=1\nread_noise=30 seed=1\nread_noise=100 seed=2\nr0=0.12 seed=3\n", f);
    fclose(f);
    f = fopen(in_dir("loop.txt"), "w");
    assert_non_null(f);
    fputs("loop_iterations=1 loop_gain=0.5\nloop_iterations=1 seed=2\nloop_iterations=0\n", f);
    fclose(f);
    static char t1[16384], tn[16384];
    char args[2048];
    for (int kind = 0; kind < 2; kind++) {
        const char *cmd = kind ? "correct" : "simulate", *sets = kind ? "loop.txt" : "sets.txt";
        snprintf(args, sizeof args, "%s %s --sweep %s -o %s1", cmd, small, sets, cmd);
        run_ok(0, args);
        snprintf(args, sizeof args, "%s1/sweep.tsv", cmd);
        table_body(args, t1, sizeof t1);
        for (int np = NP_FIRST; np <= 3; np++) {
            snprintf(args, sizeof args, "%s %s --sweep %s -o %s%d", cmd, small, sets, cmd, np);
            run_ok(np, args);
            snprintf(args, sizeof args, "%s%d/sweep.tsv", cmd, np);
            table_body(args, tn, sizeof tn);
            if (strcmp(t1, tn)) print_message("1 process:\n%s%d processes:\n%s", t1, np, tn);
            assert_string_equal(t1, tn);
        }
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_shares_cut_cubes),
        cmocka_unit_test(test_stream_equal),
        cmocka_unit_test(test_stream_max_frames),
        cmocka_unit_test(test_speckles_and_estimate_equal),
        cmocka_unit_test(test_truncated_on_one_rank),
        cmocka_unit_test(test_periodic_updates_refused),
        cmocka_unit_test(test_sweeps_equal),
    };
    return cmocka_run_group_tests(tests, setup, NULL);
}

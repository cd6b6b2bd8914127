/* `specklewfs stream` and `specklewfs merge` end to end on a small synthetic data set:
 * the streamed accumulators equal a direct computation with the library (engine ->
 * accumulators), the result does not depend on --threads, two runs over disjoint cubes
 * merged equal one run over both, and bad inputs give a clear error. */
#include "testutil.h"

#include "specklewfs/accum.h"
#include "specklewfs/aperture.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/engine.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/speckles.h"
#include "specklewfs/rng.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>

#define NPUP 24
#define NF 14
#define NSUB 4
#define NSL (2 * NSUB * NSUB)
#define NCAM 30   /* camera frames per cube */
#define NWFS 400  /* WFS frames in the telemetry file */
#define RATIO 3.37
#define DIAM 6.5
#define LAMBDA 3.8e-6
#define PIXSCALE 0.5

static char dir[1024];

static const char *in_dir(const char *name)
{
    static char buf[8][1200];
    static int k = 0;
    char *b = buf[k++ % 8];
    snprintf(b, sizeof buf[0], "%s/%s", dir, name);
    return b;
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

static void write_timing(const char *path, int use0, int use1)
{
    swfs_timing t;
    memset(&t, 0, sizeof t);
    swfs_timing_cube c[2];
    memset(c, 0, sizeof c);
    t.ratio = RATIO;
    t.ncubes = 2;
    t.cubes = c;
    t.fit.sign_x = t.fit.sign_y = 1;
    const double start[2] = {10.25, 150.5};
    for (int k = 0; k < 2; k++) {
        snprintf(c[k].camera, sizeof c[k].camera, "raw_%d.fits", k);
        snprintf(c[k].slopes, sizeof c[k].slopes, "slopes.fits");
        c[k].first = (size_t)k * NCAM;
        c[k].nframes = NCAM;
        c[k].start = start[k];
        c[k].status = (k ? use1 : use0) ? SWFS_CUBE_OK : SWFS_CUBE_STRADDLES;
    }
    assert_ok(swfs_timing_write(path, &t));
}

/* The data set, and the expected accumulators computed with the library directly from
 * the files as written (so that float storage does not matter). */
static swfs_accum *make_data(void)
{
    swfs_rng r;
    swfs_rng_seed(&r, 2024);
    swfs_geom g = geom();
    /* Actuators, a reconstructor of the model's own D (the truncated SVD: `speckles` checks a
     * given matrix against D), slopes giving phases of ~1 rad, with a tip-tilt to be removed. */
    double *xy = NULL;
    size_t nact = 0;
    assert_ok(swfs_actuators_hexapolar(DIAM, 1.2, 0.6, &xy, &nact));
    {
        double m0[NPUP * NPUP];
        assert_ok(swfs_aperture_make(m0, NPUP, g.pupdx, DIAM, g.obscur, 0, 0.0));
        swfs_speckle_model *m = NULL;
        assert_ok(swfs_speckle_model_create(&m, xy, nact, m0, NPUP, g.pupdx, DIAM, NSUB, NULL, 5e-2, 0, 0));
        assert_ok(swfs_recon_write(m->recon, in_dir("recon.fits")));
        swfs_speckle_model_free(m);
    }
    assert_ok(swfs_actuators_write(xy, nact, in_dir("act.fits")));
    free(xy);
    swfs_real *sl = swfs_real_alloc(NSL, NWFS, 1);
    assert_non_null(sl);
    const double s1 = 0.3 * LAMBDA / (2 * M_PI) / (DIAM / NSUB); /* ~0.3 rad of phase per subaperture */
    for (size_t k = 0; k < NWFS; k++)
        for (size_t i = 0; i < NSL; i++) sl->data[k * NSL + i] = s1 * (swfs_rng_normal(&r) + (i < NSL / 2 ? 0.5 : -0.2));
    swfs_fits_out *o = NULL;
    assert_ok(swfs_fits_out_create(&o, in_dir("slopes.fits")));
    assert_ok(swfs_fits_out_real(o, NULL, sl, -64));
    assert_ok(swfs_fits_out_key_double(o, "WFSRATE", 527.0, "[Hz]"));
    assert_ok(swfs_fits_out_commit(o));
    swfs_real_free(sl);
    write_timing(in_dir("timing.txt"), 1, 1);
    write_timing(in_dir("timing0.txt"), 1, 0);
    write_timing(in_dir("timing1.txt"), 0, 1);

    /* Read everything back and run the engine as the command should. */
    swfs_recon *rb = NULL;
    double *xyb = NULL;
    size_t nb = 0;
    swfs_real *slb = NULL;
    assert_ok(swfs_recon_read(in_dir("recon.fits"), &rb));
    assert_ok(swfs_actuators_read(in_dir("act.fits"), &xyb, &nb));
    assert_ok(swfs_fits_read_real(in_dir("slopes.fits"), NULL, &slb, NULL));
    double mask[NPUP * NPUP];
    assert_ok(swfs_aperture_make(mask, NPUP, g.pupdx, DIAM, g.obscur, 0, 0.0));
    /* The model of 'specklewfs speckles': tip-tilt projected out of the reconstructor. */
    swfs_speckle_model *model = NULL;
    assert_ok(swfs_speckle_model_create(&model, xyb, nb, mask, NPUP, g.pupdx, DIAM, NSUB, rb, 0.0, 0, 1));
    swfs_engine_config c = {NSL, nb, NPUP, NF, NF, PIXSCALE * g.pupdx / DIAM, LAMBDA, model->recon->W, model->T, mask,
                            0, 1};
    swfs_engine *e = swfs_engine_create(&c);
    assert_non_null(e);
    swfs_timing *t = NULL;
    assert_ok(swfs_timing_read(in_dir("timing.txt"), &t));

    /* Science: I = |Psi + 0.8 psi|^2 + noise, psi the engine's fields. */
    swfs_real *sci = swfs_real_alloc(NF, NF, 2 * NCAM);
    double complex *h = malloc(NCAM * NF * NF * sizeof *h);
    swfs_exposure sched[NCAM];
    swfs_accum *acc = swfs_accum_create(NF, NF);
    assert_true(sci && h && acc);
    for (int k = 0; k < 2; k++) {
        const double t0 = t->cubes[k].start;
        const size_t base = (size_t)floor(t0);
        swfs_engine_schedule(t->ratio, t0 - (double)base, NCAM, sched);
        assert_ok(swfs_engine_process(e, slb->data + base * NSL, NWFS - base, sched, NCAM, h));
        for (size_t j = 0; j < NCAM; j++) {
            double *frame = swfs_real_frame(sci, (size_t)k * NCAM + j);
            for (size_t p = 0; p < NF * NF; p++) {
                const double complex Psi = 30.0 * cexp(I * 0.4 * (double)p) / (1.0 + 0.05 * (double)p);
                const double complex tot = Psi + 0.8 * h[j * NF * NF + p];
                frame[p] = creal(tot * conj(tot)) + 2.0 * swfs_rng_normal(&r);
            }
            assert_ok(swfs_accum_add(acc, frame, h + j * NF * NF));
        }
    }
    assert_ok(swfs_fits_out_create(&o, in_dir("sci.fits")));
    assert_ok(swfs_fits_out_set_stamp(o, &g, NULL, 0));
    assert_ok(swfs_fits_out_real(o, NULL, sci, -64));
    assert_ok(swfs_fits_out_key_double(o, "RDNOISE", 2.0, "[counts]"));
    assert_ok(swfs_fits_out_commit(o));
    free(h);
    swfs_real_free(sci);
    swfs_engine_free(e);
    swfs_speckle_model_free(model);
    swfs_recon_free(rb);
    free(xyb);
    swfs_real_free(slb);
    swfs_timing_free(t);
    return acc;
}

/* Every accumulator field of b within rel of a, relative to the field's largest magnitude:
 * the float engine's rounding depends on how frames are grouped into GEMMs (the stream's
 * batches are not the whole cube), and a per-pixel relative test would measure that
 * rounding against co-moments that cancel to near zero at some pixels. */
static void assert_accum_close(const swfs_accum *a, const swfs_accum *b, double rel)
{
    assert_int_equal(a->nx, b->nx);
    assert_int_equal(a->frames, b->frames);
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) {
        double peak = 0.0;
        for (size_t p = 0; p < a->nx * a->ny; p++) peak = fmax(peak, fabs(a->f[k][p]));
        for (size_t p = 0; p < a->nx * a->ny; p++) assert_close(b->f[k][p], a->f[k][p], rel * peak);
    }
}

/* Both halos carry an AO residual mean (RESMEAN), a's within rel of b's largest value. */
static void assert_resmean_close(const swfs_halo *a, const swfs_halo *b, double rel, const char *what)
{
    assert_non_null(a->resmean);
    assert_non_null(b->resmean);
    assert_int_equal(a->resmean->nx, b->resmean->nx);
    assert_int_equal(a->resmean->ny, b->resmean->ny);
    double d = 0, mx = 0;
    for (size_t q = 0; q < b->resmean->nx * b->resmean->ny; q++) {
        d = fmax(d, fabs(a->resmean->data[q] - b->resmean->data[q]));
        mx = fmax(mx, fabs(b->resmean->data[q]));
    }
    print_message("%s: max |RESMEAN difference| %.3g of %.3g m\n", what, d, mx);
    assert_true(mx > 0 && d <= rel * mx);
}

static void test_stream_and_merge(void **state)
{
    (void)state;
    snprintf(dir, sizeof dir, "%s", test_path("cli_stream"));
    char mk[1200];
    snprintf(mk, sizeof mk, "mkdir -p %s", dir);
    assert_int_equal(system(mk), 0);
    swfs_accum *expect = make_data();
    char out[16384];
    /* --tiptilt frame: the reconstructor projected, exactly what make_data computed. */
    const char *common = "--timing timing.txt --science sci.fits --slopes . --recon recon.fits --actuators act.fits "
                         "--static none --tiptilt frame --band none";
    char args[2048];

    /* One pass, 2 threads, updates every 16 frames, checkpoint. */
    snprintf(args, sizeof args, "stream %s -o halo.fits --checkpoint ck.fits --every 16 --batch 8 --threads 2", common);
    int rc = test_run_cli(dir, args, out, sizeof out);
    print_message("%s", out);
    assert_int_equal(rc, 0);
    assert_non_null(strstr(out, "valid"));
    assert_non_null(strstr(out, "x real time"));
    swfs_accum *got = NULL;
    assert_ok(swfs_accum_load(in_dir("ck.fits"), &got, NULL));
    /* Batches of 8 camera frames instead of the 30 computed directly: single-precision
     * rounding in the GEMMs may differ with the blocking, nothing else. */
    assert_accum_close(expect, got, 1e-6); /* measured 1.2e-7 at most */
    swfs_halo *h = NULL;
    assert_ok(swfs_halo_read(in_dir("halo.fits"), &h, NULL));
    assert_int_equal(h->nx, NF);
    swfs_halo_free(h);

    /* The batch path gives the same halo: 'specklewfs speckles' then 'estimate' (its static
     * halo is the data-set mean, a constant: the estimate does not change, eq:zeroMean),
     * both with their default tip-tilt model (the exposure mean removed). */
    assert_int_equal(test_run_cli(dir, "speckles timing.txt --science sci.fits --actuators act.fits --recon recon.fits -o sp.fits",
                         out, sizeof out), 0);
    assert_int_equal(test_run_cli(dir, "estimate sci.fits sp.fits -o halo_sp.fits", out, sizeof out), 0);
    assert_int_equal(test_run_cli(dir, "stream --timing timing.txt --science sci.fits --recon recon.fits --actuators act.fits "
                         "--static none -o halo_x.fits", out, sizeof out), 0);
    swfs_halo *hs = NULL, *hb = NULL;
    assert_ok(swfs_halo_read(in_dir("halo_x.fits"), &hs, NULL));
    assert_ok(swfs_halo_read(in_dir("halo_sp.fits"), &hb, NULL));
    double dmax = 0, hmax = 0;
    for (size_t p = 0; p < NF * NF; p++) {
        dmax = fmax(dmax, cabs(hs->halo->data[p] - hb->halo->data[p]));
        hmax = fmax(hmax, cabs(hb->halo->data[p]));
    }
    print_message("stream vs speckles + estimate: max |HALO difference| %.3g of max %.3g\n", dmax, hmax);
    assert_true(dmax <= 1e-6 * hmax);
    /* and the same AO residual's time mean over the same exposures (pipeline.h) */
    assert_resmean_close(hs, hb, 1e-9, "stream vs speckles + estimate");
    swfs_halo_free(hs);
    swfs_halo_free(hb);

    /* One thread: the same accumulators, bit for bit. */
    snprintf(args, sizeof args, "stream %s -o halo1.fits --checkpoint ck1.fits --batch 8 --threads 1", common);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    swfs_accum *got1 = NULL;
    assert_ok(swfs_accum_load(in_dir("ck1.fits"), &got1, NULL));
    for (int k = 0; k < SWFS_ACC_NFIELDS; k++) assert_memory_equal(got->f[k], got1->f[k], NF * NF * sizeof(double));

    /* The two cubes separately (a night in chunks), merged. */
    const char *part = "--science sci.fits --slopes slopes.fits --recon recon.fits --actuators act.fits --static none "
                       "--tiptilt frame --band none";
    snprintf(args, sizeof args, "stream --timing timing0.txt %s -o h0.fits --checkpoint p0.fits", part);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    snprintf(args, sizeof args, "stream --timing timing1.txt %s -o h1.fits --checkpoint p1.fits", part);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    rc = test_run_cli(dir, "merge p1.fits p0.fits -o merged.fits --halo merged_halo.fits --read-noise 2", out, sizeof out);
    print_message("%s", out);
    assert_int_equal(rc, 0);
    swfs_accum *m = NULL;
    assert_ok(swfs_accum_load(in_dir("merged.fits"), &m, NULL));
    assert_accum_close(expect, m, 1e-9); /* same blocking as the direct computation */
    /* The checkpoints carry the AO residual's mean, and the merge weighs them by their
     * exposures: the merged halo's is the one-pass run's (halo.fits, the same frames). */
    {
        swfs_halo *hm = NULL, *h1 = NULL;
        assert_ok(swfs_halo_read(in_dir("merged_halo.fits"), &hm, NULL));
        assert_ok(swfs_halo_read(in_dir("halo.fits"), &h1, NULL));
        assert_resmean_close(hm, h1, 1e-12, "merged checkpoints vs one pass");
        swfs_halo_free(hm);
        swfs_halo_free(h1);
        /* a checkpoint without it (an older one) leaves the merge without it, and says so */
        swfs_accum *plain = NULL;
        assert_ok(swfs_accum_load(in_dir("p0.fits"), &plain, NULL));
        assert_ok(swfs_accum_save(plain, in_dir("p0_plain.fits"), NULL, NULL, 0));
        swfs_accum_free(plain);
        rc = test_run_cli(dir, "merge p1.fits p0_plain.fits -o merged2.fits --halo merged2_halo.fits --g-smooth 0", out,
                          sizeof out);
        assert_int_equal(rc, 0);
        assert_non_null(strstr(out, "1 of 2 checkpoints carry no AO residual mean"));
        assert_ok(swfs_halo_read(in_dir("merged2_halo.fits"), &hm, NULL));
        assert_null(hm->resmean);
        swfs_halo_free(hm);
    }

    /* The same with the automatic static halo, shared through --static-out. */
    const char *pa = "--science sci.fits --slopes slopes.fits --recon recon.fits --actuators act.fits --tiptilt frame "
                     "--band none";
    snprintf(args, sizeof args, "stream --timing timing0.txt %s -o s0.fits --checkpoint q0.fits --static-out st.fits", pa);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    assert_non_null(strstr(out, "S^1/2"));
    snprintf(args, sizeof args, "stream --timing timing1.txt %s -o s1.fits --checkpoint q1.fits --static st.fits", pa);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    snprintf(args, sizeof args, "stream --timing timing.txt %s -o s.fits --checkpoint q.fits --static st.fits", pa);
    assert_int_equal(test_run_cli(dir, args, out, sizeof out), 0);
    assert_int_equal(test_run_cli(dir, "merge q0.fits q1.fits -o qm.fits", out, sizeof out), 0);
    swfs_accum *qa = NULL, *qm = NULL;
    assert_ok(swfs_accum_load(in_dir("q.fits"), &qa, NULL));
    assert_ok(swfs_accum_load(in_dir("qm.fits"), &qm, NULL));
    assert_accum_close(qa, qm, 1e-9);
    /* A constant offset of psi changes no covariance with I (eq:zeroMean): the stabilized
     * products <psi' I> equal those without subtraction. */
    for (size_t p = 0; p < NF * NF; p++) {
        assert_close(qa->f[SWFS_ACC_CIX][p], expect->f[SWFS_ACC_CIX][p], 1e-4 * fmax(1.0, fabs(expect->f[SWFS_ACC_CIX][p])));
        assert_close(qa->f[SWFS_ACC_CIY][p], expect->f[SWFS_ACC_CIY][p], 1e-4 * fmax(1.0, fabs(expect->f[SWFS_ACC_CIY][p])));
    }
    swfs_accum_free(qa);
    swfs_accum_free(qm);

    /* Errors: a missing telemetry file; a cube reaching past its telemetry; bad options. */
    rc = test_run_cli(dir, "stream --timing timing.txt --science sci.fits --slopes nowhere.fits --recon recon.fits "
             "--actuators act.fits -o x.fits", out, sizeof out);
    assert_int_not_equal(rc, 0);
    assert_non_null(strstr(out, "nowhere.fits"));
    FILE *f = fopen(in_dir("timing_bad.txt"), "w");
    assert_non_null(f);
    fprintf(f, "ratio %.6f 0\nlag 0\ncube 0 raw_0.fits 0 30 slopes.fits 390.0 ok\n", RATIO);
    fclose(f);
    snprintf(args, sizeof args, "stream --timing timing_bad.txt %s -o x.fits", part);
    rc = test_run_cli(dir, args, out, sizeof out);
    assert_int_not_equal(rc, 0);
    assert_non_null(strstr(out, "slopes.fits holds 400"));
    assert_int_equal(test_run_cli(dir, "stream --timing timing.txt -o x.fits", out, sizeof out), 2);
    assert_int_not_equal(test_run_cli(dir, "merge ck.fits sci.fits -o y.fits", out, sizeof out), 0);
    assert_non_null(strstr(out, "sci.fits"));

    swfs_accum_free(expect);
    swfs_accum_free(got);
    swfs_accum_free(got1);
    swfs_accum_free(m);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_stream_and_merge),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

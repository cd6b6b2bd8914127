/* The slopes -> speckles step on systems it was not tuned on (docs/telemetry.md, "Over many
 * systems"). For each system of a matrix -- Shack-Hartmann 12 x 12, 16 x 16 and 24 x 24,
 * frame ratios 4-10, one and two wind layers at 5-25 m/s, vibration 0-0.5 lambda/D, read
 * noise 0-20 counts, WFS rates 500-1000 Hz -- and two seeds, the time-series simulation
 * is run through the documented path with default options (reduce -> sync -> speckles ->
 * estimate -> pupil) and, on the same reduced frames, with the simulator's ideal speckles
 * (the true residual wavefront); the table gives both NCP errors and their ratio.
 *
 *   ./build/bench/bench_telemetry [--quick] [--seeds N | --seed S] [--keep DIR] [--only K]
 *                                 [--tiptilt exposure|frame] [--kind slopes|modal|modal-cm|modal-rm|pyramid|pyramid-imat|pyramid-learn|pyramid-miss|pyramid-choose]
 *                                 [--vk-l0 M] [--recon teach|vk|map|svd] [--truth] [--print-keys]
 *                                 [--band B|wfs] [--set key=value ...]
 *
 * --set key=value (up to 8): simulator keys added to every observation after the system's own
 * (slope_noise, r0, ao_gain, ...: what the matrix holds fixed and teach is not told);
 * docs/telemetry.md, "The loops' slope noise from the slopes".
 * --print-keys (with --only K, --seed S): prints system K's simulator keys, one per line, and
 * exits (bench/spacetime.sh simulates training loops of the system with them).
 * --recon: the speckle reconstructor on every system (default teach, the library's: a map taught
 * for each observation from its own files, in DIR/speckles.teach; vk the default before it).
 * --truth: the simulation also writes the true residual on the actuators and the modal export
 * (export_truth=1 export_modal=1), for bench/recon_oracle.py on a --keep DIR.
 * --seeds N: seeds 1 .. N (default 2); --seed S: seed S alone; --only K: system K (0-based) alone.
 *
 * --band B: the speckles' band [lambda/D] on every system; --band wfs: each system's subaperture
 * band nsub / 2 (what the Shack-Hartmann kind takes by default; for --kind modal, the band a user
 * would give a modal system whose WFS is that Shack-Hartmann: docs/telemetry.md).
 *
 * --vk-l0 M: the von Karman reconstructor's outer scale (default: the library's, 10 m) on every
 * system, to measure the constant over the whole matrix (docs/telemetry.md).
 *
 * --kind modal: each system's telemetry exported as cacao's modal coefficients on a DM grid
 * that is offset, turned and mirrored (simulate export_modal=1), timed by sync and turned into
 * speckles through the linear model: the non-Shack-Hartmann input kind over the same matrix.
 * --kind modal-cm: the same modal coefficients with their control matrix (the export's
 * cm_modes.fits), turned back into valid-only slopes by modal-slopes (into DIR/ms, which names
 * the matrix: MODALCM), then sync and the Shack-Hartmann default with the export's valid map:
 * what a modal system whose WFS is a Shack-Hartmann of known control matrix gets.
 * --kind modal-rm: the same with the modal response matrix instead of the control matrix (the
 * export's rm_modes.fits, modal-slopes --imat): what such a system gets when it has the
 * calibration's response matrix but not the control matrix its loop made from it.
 * --kind pyramid: each system sensed by a modulated pyramid instead (simulate wfs=pyramid, 3
 * lambda/D, the sensing wavelength 0.85, 1.25 or 1.65 um by the system's place in the matrix,
 * the simulator's 1000 photons per subaperture and frame), its signals through the linear
 * model with the run's influence functions and interaction matrix (--basis influence.fits
 * --imat imat_ao.fits: the MAP reconstructor from the telemetry), sync included.
 * --kind pyramid-learn: the same observations through a per-frame map learned (learn, its
 * default miss of the residual's time mean included) from 4 loops of the same system at other
 * seeds, as --control: what a pyramid system's user gets from simulations of it.
 * --kind pyramid-miss: --kind pyramid's --imat path with the same 4 loops as --mean-loop: the
 * miss of the residual's time mean by the observation's own reconstruction, from the loops.
 * --kind pyramid-choose: pyramid-miss's loops given to speckles --loops-map choose (the map
 * learned from them against the interaction matrix's, the self-check choosing): what a pyramid
 * system's user with simulations of it gets; both NCP errors and both scores under the row.
 * --kind pyramid is speckles' default for a pyramid's telemetry: with --mean-loop teach, the
 * loops speckles simulates itself of the system the observation's files describe (no key of
 * the bench's own given to them); --kind pyramid-imat: --mean-loop none (the --imat path alone).
 *
 * --quick: 3 cubes of 60 frames instead of 6 of 100 (a smoke run). Nothing here is tuned:
 * every system runs with the same options; only the simulated system changes. */
#include "specklewfs/fits.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pupil.h"
#include "specklewfs/run.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

typedef struct system_def {
    const char *name;
    int nsub;
    double wfs_rate, ratio;
    int nlayers;
    double speed[2], dir[2];
    double vib, vib_freq, read_noise;
} system_def;

/* The matrix: every parameter of the range is visited, each value in several
 * combinations. */
static const system_def systems[] = {
    {"sh12-mmt", 12, 527, 6.48, 2, {10, 15}, {0, 110}, 0.5, 20, 19},
    {"sh12-slow", 12, 500, 4.0, 1, {5, 0}, {30, 0}, 0.0, 20, 0},
    {"sh12-fast", 12, 1000, 10.0, 2, {20, 25}, {250, 340}, 0.3, 35, 10},
    {"sh12-mid", 12, 800, 7.3, 1, {18, 0}, {135, 0}, 0.2, 12, 15},
    {"sh16-issue", 16, 1000, 9.7, 1, {14, 0}, {200, 0}, 0.4, 12, 15},
    {"sh16-calm", 16, 600, 5.0, 2, {8, 12}, {45, 300}, 0.2, 25, 5},
    {"sh16-windy", 16, 1000, 8.0, 1, {25, 0}, {90, 0}, 0.5, 18, 20},
    {"sh16-shear", 16, 700, 4.2, 2, {5, 22}, {10, 190}, 0.0, 20, 10},
    {"sh24-base", 24, 1000, 6.0, 1, {10, 0}, {60, 0}, 0.1, 15, 10},
    {"sh24-noisy", 24, 800, 4.5, 2, {15, 20}, {170, 260}, 0.3, 22, 20},
    {"sh24-still", 24, 500, 9.0, 1, {5, 0}, {315, 0}, 0.0, 20, 0},
    {"sh24-jet", 24, 1000, 7.7, 2, {12, 25}, {20, 220}, 0.5, 30, 5},
};
#define NSYS (sizeof systems / sizeof systems[0])

static char dir[1024];
/* --set key=value (repeatable): simulator keys added to every observation after the
 * system's own (the loop's r0, slope noise, gain, ... that teach does not get told) */
static const char *extra_keys[8];
static int nextra;
static int tiptilt = SWFS_TT_EXPOSURE; /* --tiptilt: the speckles' tip-tilt treatment (speckles.h) */
static double band = 0.0;            /* --band B: the speckles' band [lambda/D] (0: the default) */
static int band_wfs;                  /* --band wfs: each system's subaperture band nsub / 2 */
static double vk_l0 = -1.0;           /* --vk-l0: the reconstructor's outer scale [m] (< 0: the default) */
static int recon = SWFS_RECON_TEACH;  /* --recon teach|vk|map|svd: the speckle reconstructor */
/* --kind modal: the same telemetry as cacao's modal coefficients on a registered DM grid
 * (simulate export_modal=1), through sync and speckles with the linear model (--basis) */
static int modal;
static int modal_cm; /* --kind modal-cm: the modal coefficients back to slopes by modal-slopes */
static int modal_rm; /* --kind modal-rm: the same through the modal response matrix (--imat) */
static int pyramid;  /* --kind pyramid: a modulated pyramid senses; its signals through --basis --imat */
static int pyr_learn; /* --kind pyramid-learn: the same through a map learned from loops of the system (--control) */
static int pyr_miss;  /* --kind pyramid-miss: --imat, with the mean's miss from loops of the system (--mean-loop) */
static int pyr_choose; /* --kind pyramid-choose: pyramid-miss's loops, speckles --loops-map choose on them */
static int pyr_imat;  /* --kind pyramid-imat: --imat alone, --mean-loop none (the default's loops left out) */
static swfs_dm_registration modal_reg;
static int truth; /* --truth: also simulate export_truth=1 export_modal=1 (for --keep) */

static const char *pth(const char *name)
{
    static char buf[32][sizeof dir + 256]; /* the folder and a file name of its names (the longest 191) */
    static int k;
    k = (k + 1) % 32;
    snprintf(buf[k], sizeof buf[k], "%s/%s", dir, name);
    return buf[k];
}

static int die(const char *what)
{
    fprintf(stderr, "bench_telemetry: %s: %s\n", what, swfs_last_error());
    return 1;
}

/* The simulator's keys of system s and seed (at most 24): what simulate() runs and what
 * --print-keys prints for `specklewfs simulate mode=timeseries`. */
static int system_keys(const system_def *s, unsigned seed, int quick, char kv[24][96])
{
    int n = 0;
    /* One pupil grid for every system: 100 samples of 6.5 cm (>= 4 per subaperture at 24 x 24). */
    snprintf(kv[n++], 96, "pupn=100");
    snprintf(kv[n++], 96, "pupdx=0.065");
    snprintf(kv[n++], 96, "screen_n=1024");
    snprintf(kv[n++], 96, "nsub=%d", s->nsub);
    /* The DM as the MMT's relative to its WFS: a hexapolar pitch 0.83 subapertures, a modal
     * filter keeping 39 % of nsub^2 modes (56 of 144). */
    snprintf(kv[n++], 96, "act_pitch=%.4f", 0.83 * 6.5 / s->nsub);
    snprintf(kv[n++], 96, "ao_modes=%d", (int)lround(0.39 * s->nsub * s->nsub));
    snprintf(kv[n++], 96, "wfs_rate=%g", s->wfs_rate);
    snprintf(kv[n++], 96, "frame_ratio=%g", s->ratio);
    snprintf(kv[n++], 96, "nlayers=%d", s->nlayers);
    if (s->nlayers == 1) {
        snprintf(kv[n++], 96, "layer_frac=1");
        snprintf(kv[n++], 96, "layer_speed=%g", s->speed[0]);
        snprintf(kv[n++], 96, "layer_dir=%g", s->dir[0]);
    } else {
        snprintf(kv[n++], 96, "layer_frac=0.6,0.4");
        snprintf(kv[n++], 96, "layer_speed=%g,%g", s->speed[0], s->speed[1]);
        snprintf(kv[n++], 96, "layer_dir=%g,%g", s->dir[0], s->dir[1]);
    }
    snprintf(kv[n++], 96, "vib_amp=%g", s->vib);
    snprintf(kv[n++], 96, "vib_freq=%g", s->vib_freq);
    snprintf(kv[n++], 96, "read_noise=%g", s->read_noise);
    snprintf(kv[n++], 96, "ncubes=%d", quick ? 3 : 6);
    snprintf(kv[n++], 96, "cube_frames=%d", quick ? 60 : 100);
    /* camera cubes start at a random fraction of a WFS frame (the seed decides), telemetry
       in files of 4000 frames so that some cubes straddle two */
    snprintf(kv[n++], 96, "start_offset=%.3f", 300.0 + 0.137 * seed + 0.5 * (seed % 2));
    snprintf(kv[n++], 96, "wfs_file_frames=4000");
    snprintf(kv[n++], 96, "seed=%u", seed);
    if (truth) snprintf(kv[n++], 96, "export_truth=1");
    if (pyramid) {
        static const double lw[3] = {0.85e-6, 1.25e-6, 1.65e-6};
        snprintf(kv[n++], 96, "wfs=pyramid");
        snprintf(kv[n++], 96, "wfs_wavelen=%g", lw[(size_t)(s - systems) % 3]);
    }
    return n;
}

/* The run of system s into into (NULL: the bench's folder; a training loop for --kind
 * pyramid-learn: export_truth=1 and no export). */
static int simulate_into(const system_def *s, unsigned seed, int quick, swfs_ts_summary *sum, const char *into)
{
    swfs_config *c = swfs_config_new();
    char kv[24][96];
    const int n = system_keys(s, seed, quick, kv);
    int rc = 0;
    for (int i = 0; i < n && !rc; i++) rc = swfs_config_set(c, kv[i]);
    for (int i = 0; i < nextra && !rc; i++) rc = swfs_config_set(c, extra_keys[i]);
    if (!rc && into) rc = swfs_config_set(c, "export_truth=1");
    swfs_ts_params tp;
    swfs_ts_params_default(&tp);
    if (!rc) rc = swfs_ts_params_from_config(c, &tp);
    if (!rc) rc = swfs_ts_params_check(&tp);
    swfs_config_free(c);
    const char *prov[] = {"bench_telemetry"};
    if (!rc) rc = swfs_ts_run(&tp, into ? into : dir, prov, 1, NULL, NULL, sum);
    size_t nmodes;
    if (!rc && !into && (modal || truth)) rc = swfs_ts_export_modal(&tp, dir, prov, 1, &modal_reg, &nmodes);
    return rc;
}

static int simulate(const system_def *s, unsigned seed, int quick, swfs_ts_summary *sum)
{
    return simulate_into(s, seed, quick, sum, NULL);
}

/* --kind pyramid-learn: PYR_LEARN_LOOPS loops of the same system (seeds 1000 s + k: other
 * turbulence and noise, as a user simulates their described system), their per-frame map
 * learned with its miss of the residual's time mean (learn's default) into DIR/W.fits. */
#define PYR_LEARN_LOOPS 4
static int pyramid_learn(const system_def *s, unsigned seed, int quick)
{
    char tdir[PYR_LEARN_LOOPS][sizeof dir + 32];
    const char *dirs[PYR_LEARN_LOOPS];
    int rc = 0;
    for (int k = 0; k < PYR_LEARN_LOOPS && !rc; k++) {
        snprintf(tdir[k], sizeof tdir[k], "%s/train_%d", dir, k);
        dirs[k] = tdir[k];
        mkdir(tdir[k], 0755);
        swfs_ts_summary ts;
        rc = simulate_into(s, 1000 * seed + (unsigned)k, quick, &ts, tdir[k]);
    }
    if (rc || pyr_miss) return rc; /* --kind pyramid-miss, -choose: the loops themselves, no map */
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = dirs;
    lo.ndirs = PYR_LEARN_LOOPS;
    lo.out = pth("W.fits");
    lo.no_heldout = 1;
    lo.mean_miss = 1;
    swfs_learn_run_result lr;
    if (!rc) rc = swfs_learn_run(&lo, &lr);
    if (!rc)
        printf("  (learned from %d loops: misfit %.1f of %.1f nm; the mean's miss %.1f nm per loop, held out %.2f: %s)\n",
               PYR_LEARN_LOOPS, 1e9 * lr.info.misfit_rms, 1e9 * lr.info.truth_rms, 1e9 * lr.meanmiss_set_rms,
               lr.meanmiss_heldout, lr.meanmiss_kept ? "kept" : "not kept");
    return rc;
}

/* The NCP error of the default pupil step on a halo file (err[0]), and with the AO
 * residual's time mean kept in the wavefront (what --keep-resmean gives from the same fit:
 * WFE + the mean taken out, err[1]); resm: the rms of the band-limited mean taken out. */
static int ncp_error(const char *halo_path, const swfs_real *ncp, double err[2], double *resm)
{
    swfs_halo *h = NULL;
    swfs_geom g;
    int rc = swfs_halo_read(halo_path, &h, &g);
    swfs_pupil_options po;
    swfs_pupil_options_default(&po);
    swfs_pupil_result *pr = NULL;
    if (!rc) rc = swfs_pupil_estimate(h, &g, NULL, &po, &pr);
    if (!rc) rc = swfs_wfe_compare(pr->wfe->data, ncp->data, pr->mask->data, ncp->nx, &err[0], NULL, NULL);
    if (!rc) rc = swfs_pupil_compare_kept(pr, ncp->data, &err[1]);
    if (!rc) *resm = pr->resmean_rms;
    swfs_pupil_result_free(pr);
    swfs_halo_free(h);
    return rc;
}

static int estimate(const char *sci, const char *sp, const char *out)
{
    swfs_estimate_run_options eo;
    swfs_estimate_run_options_default(&eo);
    eo.science = sci;
    eo.speckles = sp;
    eo.out = out;
    swfs_estimate_run_result er;
    int rc = swfs_estimate_run(&eo, &er);
    if (!rc) swfs_halo_free(er.halo);
    return rc;
}

typedef struct row {
    double slopes, ideal, ratio_true, ratio, lag_true, lag, res_nm, tt, secs;
    double slopes_keep, ideal_keep, resm_slopes, resm_ideal; /* --keep-resmean; the means taken out */
    size_t nvalid, nact, nexp;
} row;

/* A handshake log (handshake_modal.log, handshake_ms.log) naming prefix_NNN.fits for the
 * slopes_NNN.fits of the same WFS frames. */
static int modal_handshake(const char *prefix, const char *name)
{
    FILE *in = fopen(pth("handshake.log"), "r"), *out = in ? fopen(pth(name), "w") : NULL;
    if (!in || !out) {
        if (in) fclose(in);
        return 1;
    }
    char line[1024];
    while (fgets(line, sizeof line, in)) {
        char *m = strstr(line, "slopes_");
        if (m) {
            fwrite(line, 1, (size_t)(m - line), out);
            fprintf(out, "%s%s", prefix, m + 7);
        } else {
            fputs(line, out);
        }
    }
    fclose(in);
    return fclose(out) != 0;
}

/* --kind modal-cm: every modal_NNN.fits the export wrote, through modal-slopes with the
 * export's control matrix into DIR/ms (emptied first), and handshake_ms.log naming them. */
static int modal_cm_slopes(void)
{
    char *files[256];
    size_t n = 0;
    char name[32];
    for (; n < 256; n++) {
        snprintf(name, sizeof name, "modal_%03zu.fits", n);
        if (access(pth(name), R_OK)) break;
        files[n] = strdup(pth(name));
    }
    if (!n) return swfs_fail(SWFS_ERR_IO, "no modal_000.fits in %s", dir);
    mkdir(pth("ms"), 0755);
    for (size_t k = 0; k < n; k++) {
        snprintf(name, sizeof name, "ms/modal_%03zu.fits", k);
        unlink(pth(name));
    }
    unlink(pth("ms/cm_modes.fits"));
    unlink(pth("ms/pinv_rm_modes.fits"));
    swfs_modal_slopes_options mo = {(const char *const *)files, n, NULL, pth("ms"), NULL};
    if (modal_rm) mo.imat = pth("rm_modes.fits");
    else mo.cm = pth("cm_modes.fits");
    swfs_modal_slopes_result mr;
    int rc = swfs_modal_slopes_run(&mo, &mr);
    for (size_t k = 0; k < n; k++) free(files[k]);
    if (!rc) {
        printf("  (modal-slopes: %zu coefficients -> %zu slopes, rank %zu, %zu files)\n", mr.ncoef, mr.nslopes, mr.rank, n);
        rc = modal_handshake("ms/modal_", "handshake_ms.log") ? swfs_fail(SWFS_ERR_IO, "handshake_ms.log") : SWFS_OK;
    }
    return rc;
}

static void pyramid_files(swfs_linear_files *lf)
{
    swfs_linear_files_default(lf);
    lf->basis = pth("influence.fits");
    lf->imat = pth("imat_ao.fits");
}

static void modal_files(swfs_linear_files *lf)
{
    swfs_linear_files_default(lf);
    lf->basis = pth("dm_modes.fits");
    lf->reg = modal_reg;
    lf->scale = 2e-6; /* um of DM surface on unit-rms modes */
}

static int run_system(const system_def *s, unsigned seed, int quick, row *r)
{
    const double t0 = swfs_wall_seconds();
    swfs_ts_summary sum;
    if (simulate(s, seed, quick, &sum)) return die("simulate");
    r->res_nm = sum.residual_rms_nott * 1e9;
    r->tt = sum.tt_rms;
    r->nvalid = sum.nvalid;
    r->nact = sum.nact;
    const int ncubes = quick ? 3 : 6;
    const char *raw[6];
    char names[6][32];
    for (int k = 0; k < ncubes; k++) {
        snprintf(names[k], sizeof names[k], "raw_%03d.fits", k);
        raw[k] = strdup(pth(names[k]));
    }
    swfs_reduce_run_options ro;
    swfs_reduce_run_options_default(&ro);
    ro.raw = raw;
    ro.nraw = (size_t)ncubes;
    ro.dark = pth("dark.fits");
    ro.flat = pth("flat.fits");
    ro.out = pth("science.fits");
    swfs_reduce_run_result rr;
    int rc = swfs_reduce_run(&ro, &rr);
    for (int k = 0; k < ncubes; k++) free((void *)raw[k]);
    if (rc) return die("reduce");

    swfs_sync_run_options so;
    swfs_sync_run_options_default(&so);
    so.science = pth("science.fits");
    so.handshake = pth("handshake.log");
    if (pyramid) {
        pyramid_files(&so.lin);
    } else if (modal_cm) {
        if (modal_cm_slopes()) return die("modal-slopes");
        so.handshake = pth("handshake_ms.log");
    } else if (modal) {
        if (modal_handshake("modal_", "handshake_modal.log")) return die("handshake_modal.log");
        so.handshake = pth("handshake_modal.log");
        modal_files(&so.lin);
    }
    so.out = pth("timing.txt");
    swfs_sync_run_result sr;
    if (swfs_sync_run(&so, &sr)) return die("sync");
    r->ratio = sr.t.ratio;
    r->lag = sr.t.lag;
    free(sr.t.cubes);
    r->ratio_true = s->ratio;
    r->lag_true = 3; /* the simulator's handshake_lag default */

    swfs_speckles_run_options sp;
    swfs_speckles_run_options_default(&sp);
    sp.timing = pth("timing.txt");
    sp.science = pth("science.fits");
    sp.actuators = pth("actuators.fits");
    if (pyramid) {
        sp.actuators = NULL;
        pyramid_files(&sp.lin);
        if (pyr_learn || pyr_miss) {
            if (pyramid_learn(s, seed, quick)) return die("learn (pyramid loops)");
        }
        if (pyr_learn) {
            sp.lin.imat = NULL;
            sp.lin.control = pth("W.fits");
        }
        static char loopdir[PYR_LEARN_LOOPS][sizeof dir + 32];
        static const char *loops[PYR_LEARN_LOOPS];
        for (int k = 0; pyr_miss && k < PYR_LEARN_LOOPS; k++) {
            snprintf(loopdir[k], sizeof loopdir[k], "%s/train_%d", dir, k);
            loops[k] = loopdir[k];
        }
        if (pyr_imat || pyr_learn) sp.mean_teach = 0; /* learn's map carries its own miss (MEANMISS) */
        if (pyr_miss) {
            sp.mean_loops = loops;
            sp.nmean_loops = PYR_LEARN_LOOPS;
        }
        if (pyr_choose) sp.loops_map = 1; /* speckles --loops-map choose on the same loops */
    } else if (modal_cm) {
        sp.valid = pth("valid.fits");
    } else if (modal) {
        sp.actuators = NULL;
        modal_files(&sp.lin);
    }
    sp.out = pth("speckles.fits");
    const char *min[] = {pth("science.fits")}, *mout[] = {pth("science_m.fits")};
    sp.match_in = min;
    sp.match_out = mout;
    sp.nmatch = 1;
    sp.pipe.tiptilt = tiptilt;
    if (vk_l0 >= 0.0) sp.pipe.vk_l0 = vk_l0;
    if (band > 0.0) sp.pipe.band = band;
    if (band_wfs) sp.pipe.band = 0.5 * s->nsub;
    sp.pipe.recon = recon;
    swfs_speckles_run_result spr;
    if (swfs_speckles_run(&sp, &spr)) return die("speckles");
    r->nexp = spr.nout;
    if (spr.dm_choice_done) /* speckles' choice of the loops' DM by the science frames */
        fprintf(stderr, "  %s s%d: the loops' DM: %s kept, correlation per pixel %+.4f +- %.4f\n", s->name, seed,
                spr.dm_gauss_chosen ? "the Gaussian functions' map" : "the interpolated surface's map", spr.dm_corr_diff,
                spr.dm_corr_se);
    const swfs_mean_teach_result *mt = &spr.mean_teach;
    if (mt->done)
        fprintf(stderr, "  %s s%d: the mean's loops: %zu of %zu frames, r0 %.4g m (%zu pairs for its fit; their power %.3f "
                "of the telemetry's), %.0f s; held out %.2f\n", s->name, seed, mt->nloops, mt->loop_frames, mt->r0,
                mt->r0_pairs, mt->power_ratio, mt->seconds, spr.meanmiss_heldout);

    if (estimate(pth("science_m.fits"), pth("speckles.fits"), pth("halo.fits"))) return die("estimate (slopes)");
    if (estimate(pth("science.fits"), pth("speckles_ideal.fits"), pth("halo_ideal.fits"))) return die("estimate (ideal)");

    swfs_real *ncp = NULL;
    swfs_geom g;
    if (swfs_fits_read_real(pth("truth.fits"), "NCP", &ncp, &g)) return die("truth.fits");
    /* speckles' loops' map (the pyramid default): both halos it scored, and what they give */
    const swfs_loops_map_result *lm = &spr.loops_map;
    if (lm->fallback[0]) fprintf(stderr, "  %s s%d: --loops-map: not tried: %s\n", s->name, seed, lm->fallback);
    if (lm->tried) {
        char h[2][4300];
        double ea[2], eb[2], ra, rb;
        snprintf(h[0], sizeof h[0], "%.4200s/halo_imat.fits", lm->work);
        snprintf(h[1], sizeof h[1], "%.4200s/halo_loops.fits", lm->work);
        if (ncp_error(h[0], ncp, ea, &ra) || ncp_error(h[1], ncp, eb, &rb)) return die("pupil (the loops' map's halos)");
        printf("  (--loops-map: explained %.2f %% (--imat) / %.2f %% (the loops' map; DM carried within %.3f; its miss "
               "held out %.2f%s): %s; NCP %.1f / %.1f nm, kept %.1f / %.1f)\n", 100 * lm->explained[0],
               100 * lm->explained[1], lm->carry_resid, lm->meanmiss_heldout, lm->mean_from_imat ? ", the --imat mean" : "",
               lm->weight == 1 ? "--imat" : lm->weight == 0 ? "the loops' map" : "a mix", 1e9 * ea[0], 1e9 * eb[0],
               1e9 * ea[1], 1e9 * eb[1]);
        printf("  (--loops-map: the two mixed at %.2f / %.2f / %.2f of --imat's map: explained %.2f / %.2f / %.2f %%; "
               "written w = %.2f)\n", lm->mix_weight[0], lm->mix_weight[1], lm->mix_weight[2], 100 * lm->explained_mix[0],
               100 * lm->explained_mix[1], 100 * lm->explained_mix[2], lm->weight);
    }
    double e1[2], e2[2];
    rc = ncp_error(pth("halo.fits"), ncp, e1, &r->resm_slopes);
    if (!rc) rc = ncp_error(pth("halo_ideal.fits"), ncp, e2, &r->resm_ideal);
    r->slopes = e1[0];
    r->slopes_keep = e1[1];
    r->ideal = e2[0];
    r->ideal_keep = e2[1];
    swfs_real_free(ncp);
    if (rc) return die("pupil");
    r->secs = swfs_wall_seconds() - t0;
    return 0;
}

int main(int argc, char **argv)
{
    swfs_blas_reexec(argv); /* the CPU's own BLAS kernels (parallel.h) */
    int quick = 0, seeds = 2, only = -1, seed1 = 1, print_keys = 0;
    const char *keep = NULL;
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--quick")) quick = 1;
        else if (!strcmp(argv[i], "--seeds") && i + 1 < argc) seeds = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--seed") && i + 1 < argc) seed1 = seeds = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--keep") && i + 1 < argc) keep = argv[++i];
        else if (!strcmp(argv[i], "--only") && i + 1 < argc) only = atoi(argv[++i]);
        else if (!strcmp(argv[i], "--truth")) truth = 1;
        else if (!strcmp(argv[i], "--tiptilt") && i + 1 < argc && !strcmp(argv[i + 1], "frame")) tiptilt = SWFS_TT_FRAME, i++;
        else if (!strcmp(argv[i], "--tiptilt") && i + 1 < argc && !strcmp(argv[i + 1], "exposure")) i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "modal")) modal = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "modal-cm")) modal = modal_cm = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "modal-rm"))
            modal = modal_cm = modal_rm = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "pyramid")) pyramid = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "pyramid-learn"))
            pyramid = pyr_learn = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "pyramid-miss"))
            pyramid = pyr_miss = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "pyramid-choose"))
            pyramid = pyr_miss = pyr_choose = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "pyramid-imat"))
            pyramid = pyr_imat = 1, i++;
        else if (!strcmp(argv[i], "--kind") && i + 1 < argc && !strcmp(argv[i + 1], "slopes")) i++;
        else if (!strcmp(argv[i], "--vk-l0") && i + 1 < argc) vk_l0 = atof(argv[++i]);
        else if (!strcmp(argv[i], "--band") && i + 1 < argc && !strcmp(argv[i + 1], "wfs")) band_wfs = 1, i++;
        else if (!strcmp(argv[i], "--band") && i + 1 < argc) band = atof(argv[++i]);
        else if (!strcmp(argv[i], "--recon") && i + 1 < argc && !strcmp(argv[i + 1], "map")) recon = SWFS_RECON_MAP, i++;
        else if (!strcmp(argv[i], "--recon") && i + 1 < argc && !strcmp(argv[i + 1], "svd")) recon = SWFS_RECON_SVD, i++;
        else if (!strcmp(argv[i], "--recon") && i + 1 < argc && !strcmp(argv[i + 1], "vk")) recon = SWFS_RECON_VK, i++;
        else if (!strcmp(argv[i], "--recon") && i + 1 < argc && !strcmp(argv[i + 1], "teach")) i++;
        else if (!strcmp(argv[i], "--print-keys")) print_keys = 1;
        else if (!strcmp(argv[i], "--set") && i + 1 < argc && nextra < 8 && strchr(argv[i + 1], '='))
            extra_keys[nextra++] = argv[++i];
        else {
            fprintf(stderr, "usage: bench_telemetry [--quick] [--seeds N | --seed S] [--keep DIR] [--only K] "
                    "[--tiptilt exposure|frame] [--kind slopes|modal|modal-cm|modal-rm|pyramid|pyramid-imat|pyramid-learn|pyramid-miss|pyramid-choose] [--vk-l0 M] [--recon teach|vk|map|svd] [--truth] "
                    "[--band B|wfs] [--print-keys] [--set key=value ...]\n");
            return 2;
        }
    }
    if (print_keys) { /* --only K --seed S: the keys, one per line, for specklewfs simulate */
        if (only < 0 || (size_t)only >= NSYS) {
            fprintf(stderr, "bench_telemetry: --print-keys needs --only K (0..%zu)\n", (size_t)NSYS - 1);
            return 2;
        }
        char kv[24][96];
        const int n = system_keys(&systems[only], (unsigned)seed1, quick, kv);
        for (int i = 0; i < n; i++) printf("%s\n", kv[i]);
        for (int i = 0; i < nextra; i++) printf("%s\n", extra_keys[i]);
        return 0;
    }
    swfs_blas_set_threads(1);
    if (keep) {
        snprintf(dir, sizeof dir, "%s", keep);
        mkdir(dir, 0755);
    } else {
        snprintf(dir, sizeof dir, "/tmp/bench_telemetry.%ld", (long)getpid());
        if (mkdir(dir, 0755)) { perror(dir); return 1; }
    }
    printf("NCP error [nm rms, piston+tip/tilt removed], default options everywhere (%s)%s\n",
           quick ? "3 cubes x 60 frames" : "6 cubes x 100 frames", tiptilt == SWFS_TT_FRAME ? ", --tiptilt frame" :
           pyr_learn ? ", a modulated pyramid's signals (--basis influence.fits --control W.fits, learned from 4 loops)" :
           pyr_choose ? ", a modulated pyramid's signals (--imat, --mean-loop x 4, --loops-map choose)" :
           pyr_miss ? ", a modulated pyramid's signals (--basis influence.fits --imat imat_ao.fits, --mean-loop x 4)" :
           pyr_imat ? ", a modulated pyramid's signals (--basis influence.fits --imat imat_ao.fits, --mean-loop none)" :
           pyramid ? ", a modulated pyramid's signals (--basis influence.fits --imat imat_ao.fits; the default's --mean-loop teach)" :
           modal_rm ? ", modal telemetry with its response matrix (modal-slopes --imat, --valid)" :
           modal_cm ? ", modal telemetry with its control matrix (modal-slopes, --valid)" :
           modal ? ", modal telemetry (--basis)" : "");
    if (recon != SWFS_RECON_TEACH)
        printf("speckle reconstructor: %s\n", recon == SWFS_RECON_MAP ? "map" : recon == SWFS_RECON_SVD ? "svd" : "vk");
    if (band > 0.0) printf("speckles within %g lambda/D on every system\n", band);
    if (band_wfs) printf("speckles within each system's subaperture band, nsub / 2\n");
    if (vk_l0 >= 0.0) printf("von Karman outer scale of the reconstructor: %g m%s\n", vk_l0, vk_l0 == 0 ? " (fitted)" : "");
    printf("slopes / ideal: the default path (the AO residual's time mean that the speckles carry taken out of the\n"
           "wavefront: reconstructed from the slopes, the simulation's true one with the ideal speckles); keep: with\n"
           "pupil --keep-resmean; mean: the rms of the band-limited mean taken out [nm]\n");
    printf("%-11s %4s %4s %5s %6s %4s %4s %5s | %7s %7s %6s | %6s %6s %6s | %5s %5s | %6s %6s %5s | %5s\n", "system",
           "seed", "nsub", "rate", "ratio", "vib", "rn", "res", "slopes", "ideal", "x", "keep:s", "keep:i", "x", "mean",
           "true", "ratio", "lag", "nexp", "s");
    double worst = 0.0, sum_ratio = 0.0, worst_k = 0.0, sum_k = 0.0, sum_s = 0.0, sum_sk = 0.0;
    int nrun = 0, nfail = 0, within = 0, within_k = 0;
    for (size_t k = 0; k < NSYS; k++) {
        if (only >= 0 && (size_t)only != k) continue;
        for (int sd = seed1; sd <= seeds; sd++) {
            const system_def *s = &systems[k];
            row r;
            memset(&r, 0, sizeof r);
            if (run_system(s, (unsigned)sd, quick, &r)) {
                printf("%-11s %4d  failed\n", s->name, sd);
                nfail++;
                continue;
            }
            const double x = r.slopes / r.ideal, xk = r.slopes_keep / r.ideal_keep;
            worst = fmax(worst, x);
            sum_ratio += x;
            worst_k = fmax(worst_k, xk);
            sum_k += xk;
            sum_s += r.slopes;
            sum_sk += r.slopes_keep;
            nrun++;
            within += x <= 1.3;
            within_k += xk <= 1.3;
            printf("%-11s %4d %4d %5.0f %6.2f %4.1f %4.0f %5.0f | %7.1f %7.1f %6.2f | %6.1f %6.1f %6.2f | %5.1f %5.1f | "
                   "%6.3f %6.2f %5zu | %5.1f\n",
                   s->name, sd, s->nsub, s->wfs_rate, s->ratio, s->vib, s->read_noise, r.res_nm, r.slopes * 1e9,
                   r.ideal * 1e9, x, r.slopes_keep * 1e9, r.ideal_keep * 1e9, xk, r.resm_slopes * 1e9, r.resm_ideal * 1e9,
                   r.ratio, r.lag, r.nexp, r.secs);
            fflush(stdout);
        }
    }
    printf("runs %d (failed %d): slopes / ideal mean %.2f, worst %.2f; within 1.3x: %d of %d; sum of the slopes "
           "path's NCP errors %.1f nm\n", nrun, nfail, nrun ? sum_ratio / nrun : NAN, worst, within, nrun, sum_s * 1e9);
    printf("with --keep-resmean:        mean %.2f, worst %.2f; within 1.3x: %d of %d; sum %.1f nm\n",
           nrun ? sum_k / nrun : NAN, worst_k, within_k, nrun, sum_sk * 1e9);
    return nfail ? 1 : 0;
}

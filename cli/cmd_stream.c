/* specklewfs stream: WFS slopes + camera frames in time order -> HALO.fits updated as
 * the data arrive (the real-time path of issue 6; design in docs/streaming.md).
 *
 * The data come from a "source" that hands over one batch at a time: B camera frames,
 * the block of WFS slopes they integrate and the exposure schedule within that block.
 * The file source below reads a timing table (specklewfs sync), the telemetry files it
 * names and a reduced science cube; a shared-memory source (milk/ImageStreamIO-like) would
 * implement the same next_batch() from the stream counters. Everything downstream --
 * engine, static-halo subtraction, accumulators, periodic estimates -- sees only batches. */
#include "cli.h"

#include "specklewfs/accum.h"
#include "specklewfs/aperture.h"
#include "specklewfs/checkpoint.h"
#include "specklewfs/engine.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/pupil.h"
#include "specklewfs/speckles.h"
#include "specklewfs/status.h"
#include "specklewfs/sync.h"
#include "specklewfs/wfs.h"

#include <complex.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

static const char *usage_text =
    "usage: specklewfs stream --timing TIMING.txt --science SCIENCE.fits [--slopes DIR|FILE]\n"
    "                         --recon RECON.fits --actuators ACT.fits -o HALO.fits\n"
    "                         [--pupil-out PUPIL.fits] [--every K] [--every-seconds T]\n"
    "                         [--threads N] [--checkpoint FILE] [--static auto|none|HALO0.fits]\n"
    "                         [--static-out FILE] [--pupil MASK.fits] [--tiptilt exposure|frame|keep]\n"
    "                         [--batch B]\n"
    "                         [--max-frames N]\n"
    "                         [--read-noise SIGMA] [--gain G] [--g-smooth L]\n"
    "\n"
    "The whole real-time path in one pass (Codona & Kenworthy 2013, Sec. 4): WFS slopes ->\n"
    "reconstructed wavefront -> pupil field summed over each camera exposure -> focal field\n"
    "(one MFT per camera frame), core-phase referenced (eq:downsampledHalo), minus a static\n"
    "halo (eq:computedSpeckleField) -> per-pixel accumulators against the camera frames.\n"
    "HALO.fits is rewritten (atomically) every K camera frames and/or T seconds and at the\n"
    "end; progress, valid fraction and median SNR go to stderr. Memory does not grow with\n"
    "the number of frames (one telemetry file and one batch are held at a time).\n"
    "\n"
    "  --timing TIMING.txt   ratio and per-cube exposure starts from 'specklewfs sync'; cubes\n"
    "                        marked 'straddles' are skipped\n"
    "  --science FILE        reduced science cube ('specklewfs reduce'): frames, geometry\n"
    "                        keywords, RDNOISE / GAIN\n"
    "  --slopes DIR|FILE     folder holding the telemetry files the timing table names, or\n"
    "                        one telemetry file used for every cube (default: the timing\n"
    "                        table's folder; absolute names in the table are used as they are)\n"
    "  --recon, --actuators  reconstructor (nact x nslopes [m/rad]) and actuator positions\n"
    "  -o HALO.fits          the estimate (extensions as 'specklewfs estimate')\n"
    "  --pupil-out FILE      also the pupil field / NCP map at every update ('specklewfs pupil')\n"
    "  --every K             update after every K camera frames (default: only at the end)\n"
    "  --every-seconds T     update when T seconds have passed since the last one\n"
    "  --threads N           engine workers (default 2)\n"
    "  --checkpoint FILE     save the accumulators at every update ('specklewfs merge')\n"
    "  --static auto         (default) the paper's choice: S^1/2 Psi_0, the unaberrated halo\n"
    "                        scaled by the mean core amplitude of the first batch, fixed\n"
    "                        from then on; none: no subtraction; or a complex image file\n"
    "                        (e.g. the HALO extension of an earlier run). A constant offset\n"
    "                        does not bias the estimate: the accumulators remove the\n"
    "                        data-set mean of psi exactly (eq:zeroMean) -- but runs whose\n"
    "                        checkpoints will be merged must share it: save it from the\n"
    "                        first with --static-out and give it to the others\n"
    "  --static-out FILE     write the static halo used (complex image)\n"
    "  --pupil MASK.fits     pupil transmission (PUPN x PUPN; default: annulus from TELDIAM,\n"
    "                        OBSCUR)\n"
    "  --tiptilt MODE        as in 'specklewfs speckles': exposure (default) removes from every\n"
    "                        WFS frame the weighted mean x/y slope of its exposure and keeps\n"
    "                        the motion within it, as registered science frames have it;\n"
    "                        frame removes every frame's own mean slopes (the paper's Sec.\n"
    "                        4.4); keep removes nothing (pair with reduce --no-register)\n"
    "  --keep-tiptilt        same as --tiptilt keep\n"
    "  --batch B             camera frames per batch (default 128)\n"
    "  --max-frames N        stop after N camera frames\n"
    "  --read-noise, --gain  noise model for the estimate (default: science header)\n"
    "  --g-smooth L          scale-factor regularization [lambda/D] as in 'specklewfs estimate'\n"
    "                        (default 2; 0 = the paper's per-pixel g)\n";

/* ---- the file source ------------------------------------------------------ */

typedef struct batch {
    const double *slopes; /* nwfs frames of nslopes */
    size_t nwfs;
    swfs_exposure *sched; /* nexp, indices into slopes */
    double *science;      /* nexp frames */
    size_t nexp;
} batch;

typedef struct file_source {
    swfs_timing *timing;
    const double *rtilt;   /* expansion (SWFS_TT_EXPOSURE): tilt rows R (speckles.h), else NULL */
    double *xslopes;            /* expanded frames: [s_k, t_k - exposure mean] */
    swfs_exposure *xsched;
    int expand;
    swfs_fits_in *sci;
    const char *slopes_arg;
    int slopes_is_dir;
    size_t nslopes, nf2, bmax;
    size_t cube, j;        /* next camera frame: cube index, frame within the cube */
    char loaded[1100];     /* telemetry file currently in memory */
    swfs_real *tel;
    double wfs_rate;       /* [Hz] from the telemetry header (WFSRATE), 0 if unknown */
    swfs_exposure *sched;
    double *science;
} file_source;

static int is_dir(const char *p)
{
    struct stat sb;
    return stat(p, &sb) == 0 && S_ISDIR(sb.st_mode);
}

/* The next batch, or nexp = 0 at the end. */
static int next_batch(file_source *s, batch *b)
{
    b->nexp = 0;
    const swfs_timing *t = s->timing;
    while (s->cube < t->ncubes &&
           (t->cubes[s->cube].status != SWFS_CUBE_OK || s->j >= t->cubes[s->cube].nframes)) {
        s->cube++;
        s->j = 0;
    }
    if (s->cube >= t->ncubes) return SWFS_OK;
    const swfs_timing_cube *c = &t->cubes[s->cube];
    char path[1100];
    if (!s->slopes_is_dir) snprintf(path, sizeof path, "%s", s->slopes_arg);
    else if (c->slopes[0] == '/') snprintf(path, sizeof path, "%s", c->slopes);
    else snprintf(path, sizeof path, "%s/%s", s->slopes_arg, c->slopes);
    if (strcmp(path, s->loaded)) {
        swfs_real_free(s->tel);
        s->tel = NULL;
        s->loaded[0] = '\0';
        swfs_fits_in *f = NULL;
        int found = 0;
        double rate = NAN;
        int rc = swfs_fits_in_open(&f, path, NULL);
        if (!rc) rc = swfs_fits_in_key_double_opt(f, "WFSRATE", &rate, &found);
        if (!rc) rc = swfs_fits_in_read_real_all(f, &s->tel);
        swfs_fits_in_close(f);
        if (rc) return rc;
        if (found && rate > 0) s->wfs_rate = rate;
        if (s->tel->nx != s->nslopes || s->tel->nz != 1)
            return swfs_fail(SWFS_ERR_SHAPE, "%s: telemetry is %zux%zux%zu; expected %zu slopes x WFS frames", path,
                             s->tel->nx, s->tel->ny, s->tel->nz, s->nslopes);
        snprintf(s->loaded, sizeof s->loaded, "%s", path);
    }
    const size_t nwfs_file = s->tel->ny;
    size_t n = c->nframes - s->j < s->bmax ? c->nframes - s->j : s->bmax;
    const double t0 = c->start + (double)s->j * t->ratio;
    if (!(t0 >= 0))
        return swfs_fail(SWFS_ERR_VALUE, "cube %zu (%s) starts at WFS frame %g, before the start of %s", s->cube,
                         c->camera, t0, path);
    const size_t base = (size_t)floor(t0);
    const size_t need = swfs_engine_schedule(t->ratio, t0 - (double)base, n, s->sched);
    if (!need || base + need > nwfs_file)
        return swfs_fail(SWFS_ERR_VALUE, "cube %zu (%s) frames %zu..%zu need WFS frames up to %zu but %s holds %zu",
                         s->cube, c->camera, s->j, s->j + n - 1, base + need, path, nwfs_file);
    int rc = swfs_fits_in_read_real(s->sci, c->first + s->j, n, s->science);
    if (rc) return rc;
    b->slopes = s->tel->data + base * s->nslopes;
    b->nwfs = nwfs_file - base;
    b->sched = s->sched;
    if (s->expand) {
        /* Tip-tilt relative to each exposure's mean, as two extra slopes (speckles.h). */
        rc = swfs_speckles_expand(b->slopes, s->nslopes, need, s->rtilt, s->sched, n, s->xslopes, s->xsched);
        if (rc) return swfs_fail_context(rc, "%s, cube %zu", path, s->cube);
        b->slopes = s->xslopes;
        b->nwfs = swfs_speckles_expand_frames(s->sched, n);
        b->sched = s->xsched;
    }
    b->science = s->science;
    b->nexp = n;
    s->j += n;
    return SWFS_OK;
}

/* ---- the command ------------------------------------------------------------ */

typedef struct opts {
    const char *timing, *science, *slopes, *recon, *act, *out, *pupil_out, *checkpoint, *stat, *mask, *stat_out;
    long every, threads, batch, max_frames;
    double every_s, read_noise, gain, g_smooth;
    int tt_mode; /* SWFS_TT_EXPOSURE (default), SWFS_TT_FRAME, SWFS_TT_KEEP (speckles.h) */
} opts;

static int parse(int argc, char **argv, opts *o)
{
    const char *cmd = "stream";
    memset(o, 0, sizeof *o);
    o->threads = 2;
    o->batch = 128;
    o->stat = "auto";
    o->tt_mode = SWFS_TT_EXPOSURE;
    o->read_noise = o->gain = NAN;
    o->g_smooth = 2.0;
    for (int i = 1; i < argc; i++) {
        const char *a = argv[i];
        const char **str = NULL;
        long *lv = NULL;
        double *dv = NULL;
        if (!strcmp(a, "-h") || !strcmp(a, "--help")) { fputs(usage_text, stdout); return -1; }
        else if (!strcmp(a, "--timing")) str = &o->timing;
        else if (!strcmp(a, "--science")) str = &o->science;
        else if (!strcmp(a, "--slopes")) str = &o->slopes;
        else if (!strcmp(a, "--recon")) str = &o->recon;
        else if (!strcmp(a, "--actuators")) str = &o->act;
        else if (!strcmp(a, "-o")) str = &o->out;
        else if (!strcmp(a, "--pupil-out")) str = &o->pupil_out;
        else if (!strcmp(a, "--checkpoint")) str = &o->checkpoint;
        else if (!strcmp(a, "--static")) str = &o->stat;
        else if (!strcmp(a, "--pupil")) str = &o->mask;
        else if (!strcmp(a, "--static-out")) str = &o->stat_out;
        else if (!strcmp(a, "--every")) lv = &o->every;
        else if (!strcmp(a, "--threads")) lv = &o->threads;
        else if (!strcmp(a, "--batch")) lv = &o->batch;
        else if (!strcmp(a, "--max-frames")) lv = &o->max_frames;
        else if (!strcmp(a, "--every-seconds")) dv = &o->every_s;
        else if (!strcmp(a, "--read-noise")) dv = &o->read_noise;
        else if (!strcmp(a, "--gain")) dv = &o->gain;
        else if (!strcmp(a, "--g-smooth")) dv = &o->g_smooth;
        else if (!strcmp(a, "--keep-tiptilt")) { o->tt_mode = SWFS_TT_KEEP; continue; }
        else if (!strcmp(a, "--tiptilt")) {
            const char *v = i + 1 < argc ? argv[++i] : "";
            if (!strcmp(v, "exposure")) o->tt_mode = SWFS_TT_EXPOSURE;
            else if (!strcmp(v, "frame")) o->tt_mode = SWFS_TT_FRAME;
            else if (!strcmp(v, "keep")) o->tt_mode = SWFS_TT_KEEP;
            else return cli_usage_error(cmd, "--tiptilt needs exposure, frame or keep");
            continue;
        }
        else return cli_usage_error(cmd, "unknown argument '%s'", a);
        const char *v = i + 1 < argc ? argv[++i] : NULL;
        if (str) {
            if (!v) return cli_usage_error(cmd, "%s needs a value", a);
            *str = v;
        } else if (lv) {
            if (cli_parse_long(cmd, a, v, lv)) return CLI_USAGE;
        } else if (cli_parse_double(cmd, a, v, dv)) {
            return CLI_USAGE;
        }
    }
    if (!o->timing || !o->science || !o->recon || !o->act || !o->out)
        return cli_usage_error(cmd, "needs --timing, --science, --recon, --actuators and -o");
    if (o->every < 0) return cli_usage_error(cmd, "--every must be >= 0, got %ld", o->every);
    if (o->every_s < 0) return cli_usage_error(cmd, "--every-seconds must be >= 0, got %g", o->every_s);
    if (o->threads < 1 || o->threads > 64) return cli_usage_error(cmd, "--threads must be 1..64, got %ld", o->threads);
    if (o->batch < 1 || o->batch > 100000) return cli_usage_error(cmd, "--batch must be 1..100000, got %ld", o->batch);
    if (o->max_frames < 0) return cli_usage_error(cmd, "--max-frames must be >= 0");
    if (!isnan(o->read_noise) && o->read_noise < 0) return cli_usage_error(cmd, "--read-noise must be >= 0");
    if (!isnan(o->gain) && o->gain < 0) return cli_usage_error(cmd, "--gain must be >= 0");
    if (!(o->g_smooth >= 0)) return cli_usage_error(cmd, "--g-smooth must be >= 0, got %g", o->g_smooth);
    return 0;
}

/* Pupil mask: a file (its PUPIL extension if it has one) or the annulus of the geometry. */
static int load_mask(const char *path, const swfs_geom *g, swfs_real **out)
{
    if (path) {
        swfs_fits_in *f = NULL;
        int rc = swfs_fits_in_open(&f, path, NULL);
        if (!rc && swfs_fits_in_has_ext(f, "PUPIL")) rc = swfs_fits_in_move(f, "PUPIL");
        if (!rc) rc = swfs_fits_in_read_real_all(f, out);
        swfs_fits_in_close(f);
        if (rc) return rc;
        if ((*out)->nx != (size_t)g->pupn || (*out)->ny != (size_t)g->pupn || (*out)->nz != 1)
            return swfs_fail(SWFS_ERR_SHAPE, "%s: pupil mask is %zux%zux%zu but PUPN = %ld", path, (*out)->nx,
                             (*out)->ny, (*out)->nz, g->pupn);
        return SWFS_OK;
    }
    *out = swfs_real_alloc((size_t)g->pupn, (size_t)g->pupn, 1);
    if (!*out) return SWFS_ERR_NOMEM;
    return swfs_aperture_make((*out)->data, (size_t)g->pupn, g->pupdx, g->teldiam, isnan(g->obscur) ? 0.0 : g->obscur,
                              0, 0.0);
}

static int write_static(const char *path, const double complex *stat, size_t nfx, size_t nfy, const swfs_geom *g,
                        const char *const *prov, size_t nprov)
{
    swfs_cplx a = {nfx, nfy, 1, (double complex *)stat};
    swfs_fits_out *o = NULL;
    int rc = swfs_fits_out_create(&o, path);
    if (rc) return rc;
    if ((rc = swfs_fits_out_set_stamp(o, g, prov, nprov)) || (rc = swfs_fits_out_cplx(o, NULL, &a, -64)) ||
        (rc = swfs_fits_out_history(o, "static halo subtracted from the speckle fields (eq:computedSpeckleField)"))) {
        swfs_fits_out_abort(o);
        return rc;
    }
    return swfs_fits_out_commit(o);
}

typedef struct update_ctx {
    const opts *o;
    const swfs_geom *g;
    const swfs_real *mask;
    swfs_noise noise;
    swfs_estimate_options eopt;
    const char *const *prov;
    size_t nprov;
} update_ctx;

/* Estimate from the accumulators, write the products, one line on stderr. */
static int update(const update_ctx *u, const swfs_accum *acc, size_t cam, double wfs, double elapsed, int final)
{
    swfs_halo *h = NULL;
    swfs_pupil_result *pr = NULL;
    int rc = swfs_estimate(acc, &u->noise, &u->eopt, &h);
    if (rc) {
        if (final) return rc;
        fprintf(stderr, "stream: %zu camera frames: no estimate yet (%s)\n", cam, swfs_last_error());
        return SWFS_OK;
    }
    rc = swfs_halo_write(h, u->o->out, u->g, u->prov, u->nprov);
    if (!rc && u->o->pupil_out) {
        swfs_pupil_options po;
        swfs_pupil_options_default(&po);
        rc = swfs_pupil_estimate(h, u->g, u->mask, &po, &pr);
        if (!rc) rc = swfs_pupil_write(pr, u->o->pupil_out, u->g, u->prov, u->nprov);
    }
    if (!rc && u->o->checkpoint) rc = swfs_accum_save(acc, u->o->checkpoint, u->g, u->prov, u->nprov);
    if (!rc) {
        fprintf(stderr, "stream: %zu camera frames (%.0f WFS frames, %.0f/s): valid %.1f %%, median SNR %.3g", cam, wfs,
                elapsed > 0 ? wfs / elapsed : 0.0, 100.0 * h->valid_fraction, h->median_snr);
        if (pr) fprintf(stderr, ", pupil WFE rms %.1f nm", 1e9 * pr->wfe_rms);
        fputc('\n', stderr);
    }
    swfs_pupil_result_free(pr);
    swfs_halo_free(h);
    return rc;
}

int swfs_cmd_stream(int argc, char **argv)
{
    const char *cmd = "stream";
    opts o;
    int prc = parse(argc, argv, &o);
    if (prc < 0) return CLI_OK;
    if (prc) return prc;

    int rc = CLI_FAIL;
    const double t_start = cli_now();
    file_source src;
    memset(&src, 0, sizeof src);
    swfs_recon *rec = NULL;
    double *act = NULL;
    size_t nact = 0;
    swfs_real *mask = NULL;
    swfs_cplx *stat_c = NULL;
    swfs_speckle_model *model = NULL;
    double *W_ext = NULL, *Rtilt = NULL;
    swfs_engine *e = NULL;
    swfs_accum *acc = NULL;
    double complex *out = NULL, *stat = NULL, *psi = NULL;
    swfs_geom g;

    if (swfs_timing_read(o.timing, &src.timing)) { cli_error(cmd); goto done; }
    if (!(src.timing->ratio >= 1.0)) {
        fprintf(stderr, "specklewfs %s: %s: frame-rate ratio %g; expected >= 1 WFS frame per camera frame\n", cmd,
                o.timing, src.timing->ratio);
        goto done;
    }
    if (swfs_fits_in_open(&src.sci, o.science, NULL) || swfs_fits_in_geom(src.sci, &g)) { cli_error(cmd); goto done; }
    const swfs_fits_shape *ss = swfs_fits_in_shape(src.sci);
    if (ss->is_complex) {
        fprintf(stderr, "specklewfs %s: %s: science cube is complex; expected real intensities\n", cmd, o.science);
        goto done;
    }
    if (swfs_geom_require(&g, o.science) || g.pupn < 2) {
        if (g.pupn < 2) swfs_fail(SWFS_ERR_FORMAT, "%s: PUPN missing", o.science);
        cli_error(cmd);
        goto done;
    }
    for (size_t c = 0; c < src.timing->ncubes; c++)
        if (src.timing->cubes[c].status == SWFS_CUBE_OK &&
            src.timing->cubes[c].first + src.timing->cubes[c].nframes > ss->nz) {
            fprintf(stderr, "specklewfs %s: %s: cube %zu needs frames %zu..%zu but %s holds %zu\n", cmd, o.timing, c,
                    src.timing->cubes[c].first, src.timing->cubes[c].first + src.timing->cubes[c].nframes - 1,
                    o.science, ss->nz);
            goto done;
        }
    /* Noise model: flags win over the science header. */
    swfs_noise noise = {0.0, 0.0};
    {
        double v;
        int found;
        if (!swfs_fits_in_key_double_opt(src.sci, "RDNOISE", &v, &found) && found) noise.read_noise = v;
        if (!swfs_fits_in_key_double_opt(src.sci, "GAIN", &v, &found) && found) noise.gain = v;
        if (!isnan(o.read_noise)) noise.read_noise = o.read_noise;
        if (!isnan(o.gain)) noise.gain = o.gain;
    }

    if (swfs_recon_read(o.recon, &rec) || swfs_actuators_read(o.act, &act, &nact)) { cli_error(cmd); goto done; }
    if (rec->nact != nact) {
        fprintf(stderr, "specklewfs %s: %s has %zu actuators but the reconstructor %s has %zu rows\n", cmd, o.act, nact,
                o.recon, rec->nact);
        goto done;
    }
    if (load_mask(o.mask, &g, &mask)) { cli_error(cmd); goto done; }
    /* The same model as 'specklewfs speckles' (speckles.h): Clough-Tocher interpolation from
     * the actuators; tip-tilt: --tiptilt frame projects the reconstructor onto the complement
     * of the mean x/y slopes over the valid subapertures (Sec. 4.4), exposure takes the
     * reconstructed Z-tilt out (swfs_speckles_recon_tilt). */
    const size_t nsub = (size_t)llround(sqrt((double)rec->nslopes / 2.0));
    if (2 * nsub * nsub != rec->nslopes) {
        fprintf(stderr, "specklewfs %s: %s: %zu slopes is not 2 nsub^2 (x then y slopes of a square Shack-Hartmann)\n",
                cmd, o.recon, rec->nslopes);
        goto done;
    }
    if (swfs_speckle_model_create(&model, act, nact, mask->data, (size_t)g.pupn, g.pupdx, g.teldiam, nsub, rec, 0.0, 0,
                                  o.tt_mode == SWFS_TT_FRAME)) {
        cli_error(cmd);
        goto done;
    }
    const int xt = o.tt_mode == SWFS_TT_EXPOSURE;
    if (xt && swfs_speckles_recon_tilt(model, act, &W_ext, &Rtilt)) { cli_error(cmd); goto done; }
    if (model->n_outside)
        fprintf(stderr, "specklewfs %s: warning: %zu illuminated pupil samples lie outside the actuators' hull (phase 0 "
                "there)\n", cmd, model->n_outside);

    const size_t nfx = ss->nx, nfy = ss->ny, nf2 = nfx * nfy;
    swfs_engine_config ec = {rec->nslopes + (xt ? 2 : 0), nact, (size_t)g.pupn, nfx, nfy,
                             g.pixscale * g.pupdx / g.teldiam, g.wavelen, xt ? W_ext : model->recon->W, model->T,
                             mask->data, 0, (int)o.threads};
    if (!(e = swfs_engine_create(&ec))) { cli_error(cmd); goto done; }

    /* Telemetry files: --slopes, else the timing table's folder. */
    char tdir[1024];
    snprintf(tdir, sizeof tdir, "%s", o.timing);
    char *slash = strrchr(tdir, '/');
    if (slash) *slash = '\0';
    else snprintf(tdir, sizeof tdir, ".");
    src.slopes_arg = o.slopes ? o.slopes : tdir;
    src.slopes_is_dir = is_dir(src.slopes_arg);
    src.nslopes = rec->nslopes;
    src.nf2 = nf2;
    src.bmax = (size_t)o.batch;
    src.sched = malloc(src.bmax * sizeof *src.sched);
    if (xt) {
        /* Each exposure gets its own copy of its frames: at most ceil(ratio) + 1 each. */
        const size_t per = (size_t)ceil(src.timing->ratio) + 1;
        src.expand = 1;
        src.rtilt = Rtilt;
        src.xsched = malloc(src.bmax * sizeof *src.xsched);
        src.xslopes = malloc(src.bmax * per * (rec->nslopes + 2) * sizeof *src.xslopes);
        if (!src.xsched || !src.xslopes) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
    }
    src.science = malloc(src.bmax * nf2 * sizeof *src.science);
    out = malloc(src.bmax * nf2 * sizeof *out);
    stat = calloc(nf2, sizeof *stat);
    psi = malloc(nf2 * sizeof *psi);
    acc = swfs_accum_create(nfx, nfy);
    if (!src.sched || !src.science || !out || !stat || !psi || !acc) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }

    /* Static halo (eq:computedSpeckleField). auto: S^1/2 Psi_0 with Psi_0 the referenced halo
     * of flat slopes (the unaberrated pupil) and S^1/2 from the first batch's mean core. */
    int stat_auto = !strcmp(o.stat, "auto"), stat_pending = 0;
    if (stat_auto) {
        double *zero = calloc(rec->nslopes + 2, sizeof *zero);
        if (!zero) { fprintf(stderr, "specklewfs %s: out of memory\n", cmd); goto done; }
        int erc = swfs_engine_add_wfs(e, zero, 1.0);
        if (!erc) erc = swfs_engine_end_exposure(e, stat);
        free(zero);
        if (erc) { cli_error(cmd); goto done; }
        stat_pending = 1;
    } else if (strcmp(o.stat, "none")) {
        if (swfs_fits_read_cplx(o.stat, NULL, &stat_c, NULL)) { cli_error(cmd); goto done; }
        if (stat_c->nx != nfx || stat_c->ny != nfy) {
            fprintf(stderr, "specklewfs %s: %s: static halo is %zux%zu but the science frames are %zux%zu\n", cmd,
                    o.stat, stat_c->nx, stat_c->ny, nfx, nfy);
            goto done;
        }
        memcpy(stat, stat_c->data, nf2 * sizeof *stat);
    }

    char cl[2048], nl[256];
    cli_command_line(argc, argv, cl, sizeof cl);
    snprintf(nl, sizeof nl, "noise model: read noise %.6g counts, gain %.6g e-/count; ratio %.6g WFS frames per camera "
             "frame", noise.read_noise, noise.gain, src.timing->ratio);
    const char *prov[] = {cl, nl};
    update_ctx u = {&o, &g, mask, noise, {o.g_smooth / g.pixscale}, prov, 2};
    if (!stat_auto && o.stat_out && write_static(o.stat_out, stat, nfx, nfy, &g, prov, 2)) { cli_error(cmd); goto done; }

    size_t cam = 0, since = 0;
    double wfs = 0.0, t_last = cli_now();
    const double t0 = cli_now();
    batch b;
    for (;;) {
        if (next_batch(&src, &b)) { cli_error(cmd); goto done; }
        if (!b.nexp) break;
        if (o.max_frames && cam + b.nexp > (size_t)o.max_frames) b.nexp = (size_t)o.max_frames - cam;
        if (swfs_engine_process(e, b.slopes, b.nwfs, b.sched, b.nexp, out)) {
            swfs_fail_context(SWFS_ERR_VALUE, "cube %zu (%s)", src.cube, src.timing->cubes[src.cube].camera);
            cli_error(cmd);
            goto done;
        }
        if (stat_pending) {
            /* S^1/2 Psi_0: the referenced cores are real; scale Psi_0 to their mean. */
            const size_t core = (nfy / 2) * nfx + nfx / 2;
            double m = 0.0;
            for (size_t j = 0; j < b.nexp; j++) m += creal(out[j * nf2 + core]);
            m /= (double)b.nexp * creal(stat[core]);
            for (size_t k = 0; k < nf2; k++) stat[k] *= m;
            stat_pending = 0;
            fprintf(stderr, "stream: static halo S^1/2 Psi_0 with S^1/2 = %.4g (per unit exposure weight %.4g)\n", m,
                    m / src.timing->ratio);
            if (o.stat_out && write_static(o.stat_out, stat, nfx, nfy, &g, prov, 2)) { cli_error(cmd); goto done; }
        }
        for (size_t j = 0; j < b.nexp; j++) {
            for (size_t k = 0; k < nf2; k++) psi[k] = out[j * nf2 + k] - stat[k];
            if (swfs_accum_add(acc, b.science + j * nf2, psi)) { cli_error(cmd); goto done; }
            wfs += b.sched[j].count == 1 ? b.sched[j].w_first
                                         : b.sched[j].w_first + b.sched[j].w_last + (double)(b.sched[j].count - 2);
        }
        cam += b.nexp;
        since += b.nexp;
        const double now = cli_now();
        if ((o.every && since >= (size_t)o.every) || (o.every_s > 0 && now - t_last >= o.every_s)) {
            if (update(&u, acc, cam, wfs, now - t0, 0)) { cli_error(cmd); goto done; }
            since = 0;
            t_last = cli_now();
        }
        if (o.max_frames && cam >= (size_t)o.max_frames) break;
    }
    if (!cam) {
        fprintf(stderr, "specklewfs %s: %s: no usable cube (all straddle their telemetry files?)\n", cmd, o.timing);
        goto done;
    }
    if (update(&u, acc, cam, wfs, cli_now() - t0, 1)) { cli_error(cmd); goto done; }
    const double rate = wfs / (cli_now() - t0);
    printf("stream: %s: %zu camera frames, %.0f WFS frames in %.2f s; processing %.0f WFS frames/s on %ld threads", o.out,
           cam, wfs, cli_now() - t_start, rate, o.threads);
    if (src.wfs_rate > 0) printf(" = %.1f x real time (WFSRATE %.0f Hz)", rate / src.wfs_rate, src.wfs_rate);
    printf("\n");
    rc = CLI_OK;
done:
    swfs_engine_free(e);
    swfs_accum_free(acc);
    swfs_speckle_model_free(model);
    swfs_recon_free(rec);
    free(act);
    swfs_real_free(mask);
    swfs_cplx_free(stat_c);
    free(out);
    free(stat);
    free(psi);
    free(src.sched);
    free(src.xsched);
    free(src.xslopes);
    free(W_ext);
    free(Rtilt);
    free(src.science);
    swfs_real_free(src.tel);
    swfs_fits_in_close(src.sci);
    swfs_timing_free(src.timing);
    return rc;
}

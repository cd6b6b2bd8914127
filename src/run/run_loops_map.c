/* speckles' second map for a linear model with loops of the system (run.h loops_map;
 * docs/telemetry.md, "The loops' own map, chosen by the self-check"): the map learn makes from
 * the loops' telemetry to their true residual, carried from the loops' DM onto the
 * observation's basis by least squares over the pupil, applied to the observation as a
 * control matrix with its own miss of the residual's mean (each loop's by the map of the
 * others, checked on the wavefront it makes in the pupil), or the interaction matrix's
 * corrected mean where only that one's miss is shared;
 * the two maps also mixed at quarters (w C_imat + (1 - w) C_loops, their means alike); of
 * the five, the speckles that explain most of the science frames are written (the self-check
 * of `pupil A.fits B.fits ...`, swfs_halo_choose_files). */
#include "specklewfs/run.h"
#include "specklewfs/atomic.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/parallel.h"
#include "specklewfs/pipeline.h"
#include "specklewfs/source.h"
#include "specklewfs/wfs.h"
#include "run_internal.h"

#include <cblas.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* A map on the basis started as a --control file (NAXIS1 = telemetry values, NAXIS2 = basis
 * functions) with its kind (RECON); the caller adds its keys and commits (aborted on failure) */
static int map_out(swfs_fits_out **f, const char *path, const swfs_recon *c, const char *kind, const char *comment)
{
    int rc = swfs_fits_out_create(f, path);
    if (!rc) rc = swfs_recon_write_hdu(*f, c);
    if (!rc) rc = swfs_fits_out_key_string(*f, "BUNIT", "", "basis coefficient per telemetry value");
    if (!rc) rc = swfs_fits_out_key_string(*f, "RECON", kind, comment);
    return rc;
}

int swfs_loops_map_lags_(const char *loop0, long *lags, size_t *nl, double *speed)
{
    *nl = 0;
    *speed = 0;
    char path[4400];
    snprintf(path, sizeof path, "%.4300s/slopes_000.fits", loop0);
    swfs_real *s = NULL;
    int rc = swfs_telemetry_read(path, 0, &s, NULL);
    if (rc) return rc;
    const size_t nsub = (size_t)llround(sqrt(0.5 * (double)s->nx));
    swfs_wind_estimate e;
    memset(&e, 0, sizeof e);
    if (2 * nsub * nsub == s->nx) rc = swfs_spacetime_stats_(s->data, s->ny, s->nx, nsub, NULL, NULL, 0, &e, NULL);
    swfs_real_free(s);
    if (rc) return swfs_fail_context(rc, "the loops' wind (%s)", path);
    for (size_t j = 0; e.found && j < e.nlayers; j++) *speed = fmax(*speed, e.layer[j].speed);
    swfs_spacetime_lags_(*speed > 0 ? 0.5 / *speed : 0.0, lags);
    *nl = SWFS_SPACETIME_NLAGS;
    return SWFS_OK;
}

/* W_loops (nact_l x nsig: the loops' truth on their DM's functions per telemetry value) onto
 * the observation's basis: C = P W_loops, P the least-squares coefficients of each of the
 * loops' influence functions (loops[0]/influence.fits, on the same pupil grid) on the basis;
 * written as a control matrix file (NAXIS1 = telemetry values, NAXIS2 = basis functions), with
 * learn's MEANMISS carried the same way (P times it) where learn kept one. */
static int carry_map(const swfs_speckles_run_options *o, const char *loop0, const char *learned, const char *out,
                     const swfs_geom *g, const double *mask, double *carry_resid)
{
    char ip[4400];
    snprintf(ip, sizeof ip, "%.4300s/influence.fits", loop0);
    swfs_recon *wl = NULL, c;
    swfs_real *inf = NULL;
    double *P = NULL;
    size_t nk = 0;
    memset(&c, 0, sizeof c);
    swfs_real *mm = NULL;
    double *cmm = NULL;
    int rc = swfs_recon_read(learned, &wl);
    /* a map on points of its own (the loops' truth on their output grid, OUTXY) stays there:
     * its basis is their interpolation (run_linear.c), finer than the observation's */
    const int own = !rc && wl->oxy;
    if (!rc && !own) rc = swfs_fits_read_real(ip, NULL, &inf, NULL);
    /* the loops' miss of the mean, per output (learn's MEANMISS, where kept) */
    swfs_fits_in *fi = NULL;
    int has = 0;
    if (!rc && !(rc = swfs_fits_in_open(&fi, learned, NULL))) has = swfs_fits_in_has_ext(fi, "MEANMISS");
    swfs_fits_in_close(fi);
    if (!rc && has) rc = swfs_fits_read_real(learned, "MEANMISS", &mm, NULL);
    if (!rc && mm && mm->nx * mm->ny * mm->nz != wl->nact)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: MEANMISS holds %zu values for %zu outputs", learned,
                       mm->nx * mm->ny * mm->nz, wl->nact);
    const size_t np = (size_t)g->pupn;
    if (!rc && !own && (inf->nx != np || inf->ny != np || inf->nz != wl->nact))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the loops' influence functions are %zu x %zu x %zu; expected PUPN = %zu "
                       "squared by the %zu outputs of their learned map", ip, inf->nx, inf->ny, inf->nz, np, wl->nact);
    const size_t na = rc ? 0 : wl->nact, ns = rc ? 0 : wl->nslopes;
    if (!rc && !own) rc = swfs_linear_fit_(&o->lin, g, mask, inf->data, na, &P, &nk, carry_resid);
    if (!rc && own) { /* kept as it is: P would be the identity */
        *carry_resid = 0;
        nk = na;
    }
    if (!rc) { /* (a space-time map's lag blocks carried alike: P acts on its outputs) */
        c.nact = nk;
        c.nslopes = ns;
        c.nlags = wl->nlags;
        memcpy(c.lags, wl->lags, sizeof c.lags);
        c.oxy = own ? wl->oxy : NULL;
        if (!(c.W = malloc(nk * ns * sizeof *c.W))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    if (!rc) {
        if (own) memcpy(c.W, wl->W, nk * ns * sizeof *c.W);
        else
            cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nk, (int)ns, (int)na, 1.0, P, (int)na, wl->W,
                        (int)ns, 0.0, c.W, (int)ns);
        if (mm && !(cmm = malloc(nk * sizeof *cmm))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        if (cmm && own) memcpy(cmm, mm->data, nk * sizeof *cmm);
        else if (cmm) cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)nk, (int)na, 1.0, P, (int)na, mm->data, 1, 0.0, cmm, 1);
    }
    if (!rc) {
        swfs_fits_out *f = NULL;
        rc = map_out(&f, out, &c, "LOOPS", own ? "learned from the loops, on their output points (OUTXY)"
                                                : "learned from the loops, carried onto the basis");
        if (!rc) rc = swfs_fits_out_key_double(f, "LOOPFIT", *carry_resid, own ? "0: on the loops' own output points, "
                                               "not carried" : "the loops' DM on the basis: rms residual");
        if (!rc) rc = swfs_fits_out_history(f, own ? "specklewfs: the map learned from the loops of the system (speckles' "
                                            "loops_map), NAXIS1 = telemetry values, NAXIS2 = its output points (OUTXY)"
                                            : "specklewfs: the map learned from the loops of the system (speckles' "
                                            "loops_map), NAXIS1 = telemetry values, NAXIS2 = basis functions");
        if (!rc) rc = swfs_recon_write_outxy(f, &c);
        if (!rc && cmm) { /* the loops' miss of the mean on the basis: speckles adds it to RESMEAN */
            swfs_real m = {nk, 1, 1, cmm};
            rc = swfs_fits_out_real(f, "MEANMISS", &m, -64);
            if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "", "the map's miss of the residual's time mean, "
                                                   "per basis function (the loops', held out)");
        }
        if (rc) swfs_fits_out_abort(f);
        else rc = swfs_fits_out_commit(f);
    }
    free(c.W);
    free(cmm);
    swfs_real_free(mm);
    free(P);
    swfs_real_free(inf);
    swfs_recon_free(wl);
    return rc;
}

static int estimate_into(const char *sci, const char *sp, const char *out, const swfs_speckles_run_options *o)
{
    swfs_estimate_run_options eo;
    swfs_estimate_run_options_default(&eo);
    eo.science = sci;
    eo.speckles = sp;
    eo.out = out;
    eo.prov = o->prov;
    eo.nprov = o->nprov;
    swfs_estimate_run_result er;
    const int rc = swfs_estimate_run(&eo, &er);
    if (!rc) swfs_halo_free(er.halo);
    return rc;
}

/* Replace dst by a copy of src (atomic.h: the whole file or the old one). */
static int replace_with(const char *src, const char *dst, const char *why)
{
    swfs_fits_out *f = NULL;
    int rc = swfs_fits_out_copy(&f, src, dst);
    if (!rc) rc = swfs_fits_out_history(f, why);
    if (rc) {
        swfs_fits_out_abort(f);
        return rc;
    }
    return swfs_fits_out_commit(f);
}

/* The maps' mixes (docs/telemetry.md, "The two maps mixed"): two reconstructions of the same
 * frames whose errors are partly their own average to a smaller error, and the self-check
 * scores the mix as it scores the ends. The mean is linear in the map, so the mix's RESMEAN is
 * the same mix of the two sets' (each with the miss it carries). */
typedef struct mixer {
    const swfs_recon *imat;    /* the interaction matrix's map (swfs_pipeline_linear_map) */
    double *imat_own;          /* that map on the loops' map's own points where it has them
                                  (loops->oxy: Q W, Q the least-squares coefficients of the
                                  basis's functions on the points' interpolation), NULL else */
    swfs_recon *loops;         /* the loops' map (loops_map.fits): on the basis, or on its own
                                  points (OUTXY) */
    swfs_real *mean0, *mean1;  /* RESMEAN of the two sets (NULL: either has none) */
    double *off0, *off1;       /* each set's RESMEAN less its map's reconstruction of the
                                  telemetry's mean, on the pupil grid (piston, tip and tilt out of
                                  both): the miss each was given, which a map file carries as its
                                  MEANMISS image so that stream and live add what speckles did
                                  (NULL: no means, or the engine's mean not the maps' input) */
    double *off0_own;          /* off0 for the mixes where they hold imat_own (NULL else) */
} mixer;

/* A speckles file's RESMEAN (swfs_resmean_read_ext), NULL where it has none */
static int read_resmean(const char *path, swfs_real **out)
{
    *out = NULL;
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc && swfs_fits_in_has_ext(f, "RESMEAN")) rc = swfs_resmean_read_ext(f, path, out);
    swfs_fits_in_close(f);
    return rc;
}

/* The telemetry's mean over the exposures as the per-frame maps take it (*v, malloc'd, the
 * interaction matrix's map's width): the observation's pipeline p's engine input, the
 * telemetry itself (with the exposure-relative tilt's two columns after it, whose mean is 0:
 * swfs_pipeline_wavefront_of_mean); *v NULL where p has none of that width */
static int telemetry_mean(swfs_pipeline *p, double **v)
{
    *v = NULL;
    double *sum = NULL;
    size_t nc = 0, nexp = 0;
    swfs_pipeline_mean_state(p, &sum, &nc, &nexp);
    const swfs_recon *im = swfs_pipeline_linear_map(p);
    const size_t ns = im ? im->nslopes : 0;
    if (!ns || !sum || !nexp || (nc != ns && nc != ns + 2)) return SWFS_OK;
    if (!(*v = malloc(ns * sizeof **v))) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t k = 0; k < ns; k++) (*v)[k] = sum[k] / (double)nexp;
    return SWFS_OK;
}

/* The per-frame map c's reconstruction of the telemetry's mean v (c->nslopes values), plus
 * extra coefficients (NULL: none), on the pupil grid, piston, tip and tilt removed, into out */
static int mean_through(const swfs_linear_files *lf, const swfs_geom *g, const double *mask,
                        const swfs_recon *c, const double *v, const double *extra, double *out)
{
    double *coef = malloc(c->nact * sizeof *coef);
    if (!coef) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (extra) memcpy(coef, extra, c->nact * sizeof *coef);
    cblas_dgemv(CblasRowMajor, CblasNoTrans, (int)c->nact, (int)c->nslopes, 1.0, c->W, (int)c->nslopes, v, 1,
                extra ? 1.0 : 0.0, coef, 1);
    int rc = swfs_linear_wavefront_(lf, g, mask, coef, c->nact, out);
    if (!rc) swfs_wfe_remove_ptt(out, mask, (size_t)g->pupn);
    free(coef);
    return rc;
}

/* The two sets' misses (mixer.off0, off1), each set's RESMEAN less its map's reconstruction of
 * the mean: the interaction matrix's map through the telemetry's mean (telemetry_mean of the
 * observation's pipeline p); the loops' map's from its run's own, rec1 (mean_rec_out: a
 * space-time map's input is the telemetry at its lags, whose means over the exposures are not
 * the telemetry's) */
static int mixer_offsets(mixer *m, const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask,
                         swfs_pipeline *p, const char *rec1, const char *map)
{
    const size_t n = (size_t)g->pupn;
    if (!m->mean0 || m->mean0->nx != n || m->mean0->ny != n) return SWFS_OK;
    double *v = NULL;
    int rc = telemetry_mean(p, &v);
    if (rc || !v) return rc;
    if (!(m->off0 = calloc(n * n, sizeof *m->off0))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = mean_through(&o->lin, g, mask, m->imat, v, NULL, m->off0);
    for (size_t i = 0; !rc && i < n * n; i++) m->off0[i] = mask[i] > 0 ? m->mean0->data[i] - m->off0[i] : 0.0;
    /* the same where the mixes hold the interaction matrix's map on the loops' output points
     * (Q W, whose wavefront is the basis's to the fit's residual, which this miss then holds) */
    if (!rc && m->imat_own) {
        swfs_recon ci = *m->imat;
        ci.W = m->imat_own;
        ci.nact = m->loops->nact;
        swfs_linear_files lf = o->lin;
        lf.control = map;
        lf.imat = NULL;
        if (!(m->off0_own = calloc(n * n, sizeof *m->off0_own))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        if (!rc) rc = mean_through(&lf, g, mask, &ci, v, NULL, m->off0_own);
        for (size_t i = 0; !rc && i < n * n; i++)
            m->off0_own[i] = mask[i] > 0 ? m->mean0->data[i] - m->off0_own[i] : 0.0;
    }
    free(v);
    swfs_real *rec = NULL;
    if (!rc) rc = swfs_fits_read_real(rec1, "RESMEAN", &rec, NULL);
    if (!rc && (rec->nx != n || rec->ny != n || rec->nz != 1))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: RESMEAN is %zu x %zu x %zu; expected %zu x %zu", rec1, rec->nx, rec->ny,
                       rec->nz, n, n);
    if (!rc && !(m->off1 = calloc(n * n, sizeof *m->off1))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t i = 0; !rc && i < n * n; i++) m->off1[i] = mask[i] > 0 ? m->mean1->data[i] - rec->data[i] : 0.0;
    swfs_real_free(rec);
    if (rc) { /* both or neither */
        free(m->off0);
        free(m->off0_own);
        free(m->off1);
        m->off0 = m->off0_own = m->off1 = NULL;
    }
    return rc;
}

/* The interaction matrix's map imat (on o's basis) on the points of the map file `map`
 * (nk of them): *W = Q imat->W, Q the least-squares coefficients of the basis's functions on
 * the points' interpolation over the pupil (swfs_linear_fit_) */
static int imat_on_points(const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask,
                          const swfs_recon *imat, const char *map, size_t nk, double **W)
{
    *W = NULL;
    swfs_linear_files ub = o->lin, pb = o->lin;
    ub.control = ub.imat = NULL;
    pb.control = map;
    pb.imat = NULL;
    double *F = NULL, *Q = NULL;
    size_t nb = 0, nq = 0;
    int rc = swfs_linear_functions_(&ub, g, mask, &F, &nb);
    if (!rc && nb != imat->nact)
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu basis functions, the interaction matrix's map %zu outputs", o->lin.basis,
                       nb, imat->nact);
    if (!rc) rc = swfs_linear_fit_(&pb, g, mask, F, nb, &Q, &nq, NULL);
    if (!rc && nq != nk) rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu output points, its basis %zu", map, nk, nq);
    if (!rc && !(*W = malloc(nk * imat->nslopes * sizeof **W))) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc)
        cblas_dgemm(CblasRowMajor, CblasNoTrans, CblasNoTrans, (int)nk, (int)imat->nslopes, (int)nb, 1.0, Q, (int)nb,
                    imat->W, (int)imat->nslopes, 0.0, *W, (int)imat->nslopes);
    free(F);
    free(Q);
    return rc ? swfs_fail_context(rc, "the interaction matrix's map on the loops' output points") : SWFS_OK;
}

static int mixer_open(mixer *m, const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask,
                      const swfs_recon *imat, const char *map, const char *sp0, const char *sp1)
{
    memset(m, 0, sizeof *m);
    m->imat = imat;
    if (!imat) return swfs_fail(SWFS_ERR_ARG, "no interaction matrix's map to mix with the loops'");
    int rc = swfs_recon_read(map, &m->loops);
    const size_t nl = !rc && m->loops->nlags > 1 ? m->loops->nlags : 1;
    if (!rc && m->loops->oxy) rc = imat_on_points(o, g, mask, imat, map, m->loops->nact, &m->imat_own);
    if (!rc && ((!m->imat_own && m->loops->nact != imat->nact) || m->loops->nslopes != nl * imat->nslopes || imat->nlags))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: the loops' map is %zu x %zu (%zu lags); the interaction matrix's %zu x %zu", map,
                       m->loops->nact, m->loops->nslopes, nl, imat->nact, imat->nslopes);
    swfs_real *a = NULL, *b = NULL;
    if (!rc) rc = read_resmean(sp0, &a);
    if (!rc) rc = read_resmean(sp1, &b);
    if (!rc && a && b) { /* either without one: no mixed mean */
        m->mean0 = a;
        m->mean1 = b;
        a = b = NULL;
    }
    swfs_real_free(a);
    swfs_real_free(b);
    if (!rc && m->mean0 && (m->mean1->nx != m->mean0->nx || m->mean1->ny != m->mean0->ny || m->mean1->nz != m->mean0->nz))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s and %s: RESMEAN of two shapes", sp0, sp1);
    return rc;
}

static void mixer_close(mixer *m)
{
    free(m->imat_own);
    swfs_recon_free(m->loops);
    swfs_real_free(m->mean0);
    swfs_real_free(m->mean1);
    free(m->off0);
    free(m->off0_own);
    free(m->off1);
}

/* w off0 + (1 - w) off1 as the MEANMISS image of the map file f (the pupil grid, RESMEAN's) */
static int mixer_miss_out(swfs_fits_out *f, const mixer *m, double w)
{
    const size_t n = m->mean0->nx;
    swfs_real a = {n, n, 1, malloc(n * n * sizeof(double))};
    if (!a.data) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    /* (a mix holds the interaction matrix's map on the loops' points where they have their own;
     * w = 1 is that map itself, on the basis) */
    const double *o0 = w < 1 && m->off0_own ? m->off0_own : m->off0;
    for (size_t i = 0; i < n * n; i++) a.data[i] = w * o0[i] + (1 - w) * m->off1[i];
    int rc = swfs_fits_out_real(f, "MEANMISS", &a, -64);
    if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "m", "the miss of the residual's time mean speckles added with "
                                           "this map (its RESMEAN less the map's reconstruction), on the pupil grid");
    free(a.data);
    return rc;
}

/* C_w to map (a --control file, RECON = 'MIX'; the loops' map's lags, the interaction matrix's
 * map in its lag-0 block) and the mixed RESMEAN to mean (NULL where the sets have none) */
static int mixer_write(const mixer *m, double w, const char *map, const char *mean)
{
    swfs_recon c = *m->loops; /* (its output points, OUTXY, kept) */
    c.sv = NULL;
    const size_t ns = m->imat->nslopes, nc = c.nslopes;
    const double *wi = m->imat_own ? m->imat_own : m->imat->W;
    size_t k0 = 0;
    while (c.nlags > 1 && k0 + 1 < c.nlags && c.lags[k0] != 0) k0++;
    if (!(c.W = malloc(c.nact * nc * sizeof *c.W))) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t i = 0; i < c.nact * nc; i++) c.W[i] = (1 - w) * m->loops->W[i];
    for (size_t a = 0; a < c.nact; a++)
        for (size_t i = 0; i < ns; i++) c.W[a * nc + k0 * ns + i] += w * wi[a * ns + i];
    swfs_fits_out *f = NULL;
    int rc = map_out(&f, map, &c, "MIX", "the interaction matrix's map and the loops' mixed");
    if (!rc) rc = swfs_fits_out_key_double(f, "LOOPMIXW", w, "weight of the interaction matrix's map (1 - w: loops')");
    if (!rc) rc = swfs_fits_out_history(f, "specklewfs: speckles' loops_map, w MAP + (1 - w) LOOPS, NAXIS1 = telemetry "
                                        "values, NAXIS2 = basis functions (or the loops' output points, OUTXY)");
    if (!rc) rc = swfs_recon_write_outxy(f, &c);
    if (!rc && m->off0) rc = mixer_miss_out(f, m, w);
    if (rc) swfs_fits_out_abort(f);
    else rc = swfs_fits_out_commit(f);
    free(c.W);
    if (rc || !mean) return rc;
    swfs_real a = *m->mean0;
    const size_t na = a.nx * a.ny * a.nz;
    if (!(a.data = malloc(na * sizeof *a.data))) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t i = 0; i < na; i++) a.data[i] = w * m->mean0->data[i] + (1 - w) * m->mean1->data[i];
    f = NULL;
    rc = swfs_fits_out_create(&f, mean);
    if (!rc) rc = swfs_fits_out_real(f, "RESMEAN", &a, -64);
    if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "m", "the two sets' RESMEAN mixed as their maps");
    if (rc) swfs_fits_out_abort(f);
    else rc = swfs_fits_out_commit(f);
    free(a.data);
    return rc;
}

/* The mixes' speckles and halos (step 5 of loops_map): nmix of them made, with mx open */
static int mix_candidates(const swfs_speckles_run_options *o, const swfs_speckles_run_options *s2, const mixer *mx,
                          swfs_loops_map_result *r, const char *sci, const char *mmean, char (*mmap)[4400],
                          char (*msp)[4400], char (*mh)[4400], size_t *nmix)
{
    int rc = SWFS_OK;
    for (size_t k = 0; !rc && k < SWFS_LOOPS_MAP_NMIX; k++) {
        const double w = 1.0 - (double)(k + 1) / (SWFS_LOOPS_MAP_NMIX + 1); /* 0.75, 0.5, 0.25 */
        const int pc = (int)lround(100 * w);
        snprintf(mmap[k], 4400, "%.4300s/mix_%02d.fits", r->work, pc);
        snprintf(msp[k], 4400, "%.4300s/speckles_mix_%02d.fits", r->work, pc);
        snprintf(mh[k], 4400, "%.4300s/halo_mix_%02d.fits", r->work, pc);
        rc = mixer_write(mx, w, mmap[k], mx->mean0 ? mmean : NULL);
        swfs_speckles_run_options s3 = *s2;
        s3.lin.control = mmap[k];
        s3.out = msp[k];
        s3.nmatch = 0; /* the frames: s2's match, sci */
        s3.match_in = s3.match_out = NULL;
        s3.resmean_from = mx->mean0 ? mmean : NULL;
        s3.mean_rec_out = NULL;
        swfs_speckles_run_result r3;
        if (!rc) rc = swfs_speckles_run(&s3, &r3);
        if (!rc) rc = estimate_into(sci, msp[k], mh[k], o);
        if (!rc) {
            r->mix_weight[k] = w;
            *nmix = k + 1;
        }
    }
    return rc;
}

/* --write-recon's map for the written set (dst, or src copied onto it), with the miss of the
 * mean that set was given as its MEANMISS image where the file has no MEANMISS of its own
 * (the loops' map's, per basis function) */
static int recon_with_miss(const char *src, const char *dst, const mixer *mx, double w)
{
    swfs_fits_out *f = NULL;
    int rc = swfs_fits_out_copy(&f, src, dst);
    if (!rc) rc = swfs_fits_out_history(f, "specklewfs speckles: the map of the speckles the self-check chose");
    if (!rc && mx->off0 && !swfs_map_has_meanmiss_(src)) rc = mixer_miss_out(f, mx, w);
    if (rc) {
        swfs_fits_out_abort(f);
        return rc;
    }
    return swfs_fits_out_commit(f);
}

/* A space-time map's mean where the loops do not share its miss of it (its inputs the lags'
 * times a frame's: each loop's mean is fitted more in-sample) but share the per-frame map's
 * (learned, its MEANMISS kept): the observation's mean telemetry (p's engine input over the
 * exposures) through the per-frame map carried onto the basis, plus its miss,
 * piston, tip and tilt out, into the file mean (extension RESMEAN, what resmean_from takes);
 * mean[0] = 0 where they do not */
static int perframe_mean(const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask, swfs_pipeline *p,
                         const char *learned, swfs_loops_map_result *r, char *mean, size_t len)
{
    mean[0] = 0;
    char map[4400];
    snprintf(map, sizeof map, "%.4300s/loops_map_pf.fits", r->work);
    double resid = 0;
    int rc = carry_map(o, o->mean_loops[0], learned, map, g, mask, &resid);
    swfs_recon *c = NULL;
    swfs_real *mm = NULL;
    const size_t n = (size_t)g->pupn;
    double *v = NULL, *z = calloc(n * n, sizeof *z);
    if (!rc && !z) rc = swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    if (!rc) rc = telemetry_mean(p, &v);
    if (!rc && !v) rc = swfs_fail(SWFS_ERR_VALUE, "the observation's mean telemetry is not the per-frame map's input");
    if (!rc) rc = swfs_recon_read(map, &c);
    if (!rc) rc = swfs_fits_read_real(map, "MEANMISS", &mm, NULL);
    if (!rc && (c->nslopes != swfs_pipeline_linear_map(p)->nslopes || mm->nx * mm->ny * mm->nz != c->nact))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %zu x %zu with %zu MEANMISS values; expected %zu values per frame", map,
                       c->nact, c->nslopes, mm->nx * mm->ny * mm->nz, swfs_pipeline_linear_map(p)->nslopes);
    /* its coefficients of the mean, its miss added on the same basis (its own points' where
     * it has them: the map's file as the control names them) */
    swfs_linear_files lf = o->lin;
    lf.control = map;
    lf.imat = NULL;
    if (!rc) rc = mean_through(&lf, g, mask, c, v, mm->data, z);
    swfs_fits_out *f = NULL;
    if (!rc) {
        snprintf(mean, len, "%.4300s/mean_pf.fits", r->work);
        rc = swfs_fits_out_create(&f, mean);
    }
    if (!rc) rc = swfs_fits_out_real(f, "RESMEAN", &(swfs_real){n, n, 1, z}, -64);
    if (!rc) rc = swfs_fits_out_key_string(f, "BUNIT", "m", "the per-frame loops' map's mean with its shared miss");
    if (f && rc) swfs_fits_out_abort(f);
    else if (f) rc = swfs_fits_out_commit(f);
    if (rc) mean[0] = 0;
    free(v);
    free(z);
    swfs_real_free(mm);
    swfs_recon_free(c);
    return rc;
}

/* The mean's miss's metric (learn's meanmiss_metric) on the functions of the loops' truth: the
 * interpolation of its own points where it has them (truewf's OUTXY: the loops' output grid),
 * else their DM's influence functions (influence.fits) */
static int loops_metric(const char *loop0, const swfs_geom *g, const double *mask, double **M, size_t *n)
{
    *M = NULL;
    *n = 0;
    char tp[4400];
    snprintf(tp, sizeof tp, "%.4300s/truewf_000.fits", loop0);
    swfs_fits_in *f = NULL;
    int rc = swfs_fits_in_open(&f, tp, NULL);
    const size_t nt = rc ? 0 : swfs_fits_in_shape(f)->nx;
    swfs_fits_in_close(f);
    double *xy = NULL, *F = NULL;
    if (!rc) rc = swfs_outxy_read(tp, nt, &xy);
    if (!rc && !xy) {
        char ip[4400];
        snprintf(ip, sizeof ip, "%.4300s/influence.fits", loop0);
        return swfs_meanmiss_metric(ip, (size_t)g->pupn, mask, NULL, M, n);
    }
    if (!rc) rc = swfs_points_functions_(xy, nt, g, mask, &F);
    if (!rc) rc = swfs_meanmiss_metric_data_(F, nt, (size_t)g->pupn, mask, tp, M);
    if (!rc) *n = nt;
    free(F);
    free(xy);
    return rc;
}

static int loops_map(const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask, double imat_heldout,
                     swfs_pipeline *p, swfs_loops_map_result *r)
{
    int made = 0;
    int rc = swfs_speckles_work_folder_(o, r->work, sizeof r->work, &made);
    char learned[4400], learned_pf[4400], sp[4400], sci[4400], h0[4400], h1[4400], rec1[4400];
    snprintf(learned, sizeof learned, "%.4300s/loops_learned.fits", r->work);
    snprintf(learned_pf, sizeof learned_pf, "%.4300s/loops_learned_pf.fits", r->work);
    snprintf(r->map, sizeof r->map, "%.4100s/loops_map.fits", r->work);
    snprintf(sp, sizeof sp, "%.4300s/speckles_loops.fits", r->work);
    snprintf(sci, sizeof sci, "%.4300s/science_loops.fits", r->work);
    snprintf(h0, sizeof h0, "%.4300s/halo_imat.fits", r->work);
    snprintf(h1, sizeof h1, "%.4300s/halo_loops.fits", r->work);
    snprintf(rec1, sizeof rec1, "%.4300s/rec_loops.fits", r->work);
    /* 1. learn: the loops' telemetry to their true residual on their DM (truewf_NNN.fits), a
     * space-time map at teach's lags (docs/telemetry.md, "A space-time loops' map": frames at
     * half a subaperture's wind motion tell what one frame's signals under-read) */
    if (!rc) rc = swfs_loops_map_lags_(o->mean_loops[0], r->lags, &r->nlags, &r->lag_speed);
    swfs_learn_run_options lo;
    swfs_learn_run_options_default(&lo);
    lo.dirs = o->mean_loops;
    lo.ndirs = o->nmean_loops;
    lo.out = learned_pf;
    lo.no_heldout = 1;
    /* the map's miss of the mean, each loop's by the map of the others (held out: the map of all
     * fits its loops' means in-sample), written where the loops share it */
    lo.mean_miss = 1;
    lo.mean_miss_heldout = 1;
    /* ... checked on the wavefront the misses make in the pupil, piston, tip and tilt out: over
     * the DM's functions alone its actuators beyond the pupil, whose truth is the fit's
     * extrapolation (hundreds of nm, another pattern in each loop), outweigh the rest and hide a
     * miss the loops share inside it (docs/telemetry.md, "The mean's miss over the pupil") */
    double *metric = NULL;
    if (!rc) rc = loops_metric(o->mean_loops[0], g, mask, &metric, &lo.meanmiss_metric_n);
    lo.meanmiss_metric = metric;
    lo.prov = o->prov;
    lo.nprov = o->nprov;
    lo.progress = o->progress;
    lo.progress_ctx = o->progress_ctx;
    swfs_learn_run_result lr;
    /* enough frames for a map of its own: a least-squares map of p inputs learned from n
     * independent frames misses new frames by (1 + p / n) times its floor in misfit^2, so n >= p /
     * SWFS_LEARN_CURVE_EXCESS (teach's floor on its loops, run.h); fewer, and the map's excess
     * (and its miss of the mean, learned in-sample) is the loops' noise, not the sensor's. The
     * per-frame map first; the space-time one, its lags' times the inputs, where the frames are
     * enough for it (else the per-frame map is the loops') */
    const int st = !rc && r->nlags > 1;
    if (!rc) rc = swfs_learn_run(&lo, &lr);
    if (!rc) {
        r->meanmiss_heldout = lr.meanmiss_heldout;
        r->nframes = lr.info.nframes;
        r->inputs = lr.info.nslopes_seen;
        r->misfit_rms = lr.info.misfit_rms;
        r->truth_rms = lr.info.truth_rms;
    }
    const double need_st = (double)r->nlags * (double)r->inputs / SWFS_LEARN_CURVE_EXCESS;
    if (!rc && st && (double)r->nframes < need_st) {
        r->st_frames = (size_t)ceil(need_st);
        r->nlags = 0;
    }
    const char *map_from = r->nlags ? learned : learned_pf;
    if (!rc && r->nlags) {
        const double pf_heldout = r->meanmiss_heldout;
        lo.out = learned;
        lo.lags = r->lags;
        lo.nlags = r->nlags;
        rc = swfs_learn_run(&lo, &lr);
        if (!rc) {
            r->pf_meanmiss_heldout = pf_heldout;
            r->meanmiss_heldout = lr.meanmiss_heldout;
            r->inputs = lr.info.nslopes_seen;
            r->misfit_rms = lr.info.misfit_rms;
        }
    }
    free(metric);
    lo.meanmiss_metric = NULL;
    const double need = (double)r->inputs / SWFS_LEARN_CURVE_EXCESS;
    if (!rc && (double)r->nframes < need)
        rc = swfs_fail(SWFS_ERR_VALUE, "the loops hold %zu frames for a map of %zu inputs, fewer than the %.0f a "
                       "least-squares map needs to come within %.0f %% of its floor (more loops: --mean-teach-loops)",
                       r->nframes, r->inputs, need, 100 * SWFS_LEARN_CURVE_EXCESS);
    /* 2. onto the observation's basis */
    if (!rc) rc = carry_map(o, o->mean_loops[0], map_from, r->map, g, mask, &r->carry_resid);
    /* the space-time map's mean where its miss is not shared: the per-frame map's where that is */
    char pfmean[4400] = "";
    if (!rc && r->nlags && !(r->meanmiss_heldout < 1) && r->pf_meanmiss_heldout < 1)
        rc = perframe_mean(o, g, mask, p, learned_pf, r, pfmean, sizeof pfmean);
    /* 3. the observation through it, with its miss of the mean (MEANMISS) and a copy of the
     * science frames it covers */
    swfs_speckles_run_options s2 = *o;
    s2.lin.imat = NULL;
    s2.lin.control = r->map;
    s2.out = sp;
    const char *min[1] = {o->science}, *mout[1] = {sci};
    s2.match_in = min;
    s2.match_out = mout;
    s2.nmatch = 1;
    s2.write_recon = NULL;
    s2.mean_teach = 0;
    s2.mean_loops = NULL; /* the map's own miss instead (MEANMISS: held out) */
    s2.nmean_loops = 0;
    /* the residual's mean: where the loops share the interaction matrix's miss (held out < 1)
     * but not this map's, the interaction matrix's corrected mean is the one the loops vouch
     * for; else the map's own, with its miss where shared */
    r->mean_from_perframe = !rc && pfmean[0];
    r->mean_from_imat = !rc && !r->mean_from_perframe && !(r->meanmiss_heldout < 1) && imat_heldout < 1;
    if (r->mean_from_perframe) s2.resmean_from = pfmean;
    else if (r->mean_from_imat) s2.resmean_from = o->out;
    s2.loops_map = 0;
    s2.mean_rec_out = rec1;
    s2.teach_work = NULL;
    s2.teach_again = 0;
    s2.nteach_keys = 0;
    s2.teach_keys = NULL;
    swfs_speckles_run_options d;
    swfs_speckles_run_options_default(&d);
    s2.teach_seed = d.teach_seed;
    swfs_speckles_run_result r2;
    if (!rc) rc = swfs_speckles_run(&s2, &r2);
    if (!rc) r->meanmiss_rms = r2.meanmiss_rms;
    /* 4. both estimated on the same frames */
    if (!rc) rc = estimate_into(sci, o->out, h0, o);
    if (!rc) rc = estimate_into(sci, sp, h1, o);
    /* 5. the two maps mixed at quarters, each through the observation as in 3 (its mean the
     * same mix of the two sets'), estimated alike; where they cannot be, the two ends alone */
    enum { NC = 2 + SWFS_LOOPS_MAP_NMIX };
    char mmap[SWFS_LOOPS_MAP_NMIX][4400], msp[SWFS_LOOPS_MAP_NMIX][4400], mh[SWFS_LOOPS_MAP_NMIX][4400], mmean[4400];
    memset(mmap, 0, sizeof mmap);
    memset(msp, 0, sizeof msp);
    memset(mh, 0, sizeof mh);
    snprintf(mmean, sizeof mmean, "%.4300s/mix_resmean.fits", r->work);
    size_t nmix = 0;
    mixer mx;
    memset(&mx, 0, sizeof mx);
    if (!rc) {
        int mrc = mixer_open(&mx, o, g, mask, swfs_pipeline_linear_map(p), r->map, o->out, s2.out);
        if (!mrc) mrc = mixer_offsets(&mx, o, g, mask, p, rec1, r->map);
        if (!mrc) mrc = mix_candidates(o, &s2, &mx, r, sci, mmean, mmap, msp, mh, &nmix);
        if (mrc == SWFS_ERR_STOPPED) rc = mrc; /* the caller asked the run to stop */
        else if (mrc) { /* the note says why; the two ends are scored as before (their misses, where
                         * made, still go with --write-recon's map) */
            snprintf(r->mix_note, sizeof r->mix_note, "%s", swfs_last_error());
            swfs_clear_error();
            nmix = 0;
        }
    }
    /* 6. the self-check's choice among the five */
    const char *halos[NC] = {h0, h1, mh[0], mh[1], mh[2]}, *sps[NC] = {o->out, sp, msp[0], msp[1], msp[2]},
               *maps[NC] = {o->write_recon, r->map, mmap[0], mmap[1], mmap[2]}; /* o->write_recon: o's own map */
    double ex[NC];
    size_t best = 0;
    if (!rc) rc = swfs_halo_choose_files(halos, 2 + nmix, ex, &best, &r->ncommon, NULL, NULL);
    if (!rc) {
        r->tried = 1;
        r->explained[0] = ex[0];
        r->explained[1] = ex[1];
        for (size_t k = 0; k < nmix; k++) r->explained_mix[k] = ex[2 + k];
        r->weight = best == 0 ? 1.0 : best == 1 ? 0.0 : r->mix_weight[best - 2];
    }
    if (!rc && best == 0 && o->write_recon && mx.off0) /* the interaction matrix's map, with its miss */
        rc = recon_with_miss(maps[0], o->write_recon, &mx, r->weight);
    if (!rc && best > 0) {
        char why[300];
        if (best == 1)
            snprintf(why, sizeof why, "specklewfs speckles: the loops' map's speckles (loops_map.fits), chosen by the "
                     "self-check: %.4g %% of the frames' variance explained, the interaction matrix's %.4g %%",
                     100 * ex[1], 100 * ex[0]);
        else
            snprintf(why, sizeof why, "specklewfs speckles: the speckles of %.2f the interaction matrix's map + %.2f the "
                     "loops' (mix_%02d.fits), chosen by the self-check: %.4g %% of the frames' variance explained, the "
                     "interaction matrix's %.4g %%, the loops' map's %.4g %%", r->weight, 1 - r->weight,
                     (int)lround(100 * r->weight), 100 * ex[best], 100 * ex[0], 100 * ex[1]);
        swfs_outputs_begin(); /* the speckles and --write-recon's map replaced together, or neither */
        rc = replace_with(sps[best], o->out, why);
        if (!rc && o->write_recon) rc = recon_with_miss(maps[best], o->write_recon, &mx, r->weight);
        const int erc = swfs_outputs_end(rc == SWFS_OK);
        if (!rc) rc = erc;
        if (!rc) r->chosen = 1;
    }
    mixer_close(&mx);
    /* the scored speckles, frames and mixed mean: the halos and maps stay */
    (void)remove(sp);
    (void)remove(sci);
    (void)remove(mmean);
    (void)remove(rec1);
    for (size_t k = 0; k < SWFS_LOOPS_MAP_NMIX; k++)
        if (msp[k][0]) (void)remove(msp[k]);
    return rc;
}

int swfs_loops_map_wanted_(const swfs_speckles_run_options *o, int pyramid_loops)
{
    return o->lin.basis && o->lin.imat &&
           (o->loops_map == 1 || (o->loops_map == SWFS_LOOPS_MAP_AUTO && pyramid_loops));
}

int swfs_speckles_loops_map_(const swfs_speckles_run_options *o, const swfs_geom *g, const double *mask,
                             double imat_heldout, swfs_pipeline *p, swfs_loops_map_result *r)
{
    const double t0 = swfs_wall_seconds();
    memset(r, 0, sizeof *r);
    r->explained[0] = r->explained[1] = r->carry_resid = r->meanmiss_heldout = r->pf_meanmiss_heldout = NAN;
    for (size_t k = 0; k < SWFS_LOOPS_MAP_NMIX; k++) r->mix_weight[k] = r->explained_mix[k] = NAN;
    r->weight = 1.0;
    const int rc = loops_map(o, g, mask, imat_heldout, p, r);
    r->seconds = swfs_wall_seconds() - t0;
    if (rc == SWFS_ERR_STOPPED) return rc; /* the caller asked the whole run to stop: no fallback */
    if (rc) { /* the interaction matrix's speckles stay, and the run says why */
        snprintf(r->fallback, sizeof r->fallback, "%s", swfs_last_error());
        swfs_clear_error();
        r->tried = r->chosen = 0;
        r->weight = 1.0;
    }
    return SWFS_OK;
}

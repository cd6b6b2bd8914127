/* sync: reduced science + handshake log -> the timing table (Sec. 4.2). See include/specklewfs/run.h. */
#include "specklewfs/engine.h"
#include "specklewfs/run.h"
#include "run_internal.h"
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <dirent.h>
#include <unistd.h>

void swfs_sync_run_options_default(swfs_sync_run_options *o)
{
    memset(o, 0, sizeof *o);
    swfs_sync_params_default(&o->params);
    swfs_linear_files_default(&o->lin);
    o->params.lag_min = -3;
    o->params.lag_max = 12;
    o->params.ratio_min = 0; /* from EXPTIME x WFSRATE, else SWFS_ENGINE_MIN_RATIO (resolve_ratio_range) */
    o->params.ratio_max = 0; /* from the handshake log (ratio_bound) */
}

/* The mean x/y slopes of one telemetry file, loaded once however many cubes use it. */
typedef struct slopes_file {
    char name[SWFS_SYNC_NAME];
    size_t nwfs;
    double *mx, *my;
    int has_frame0;   /* the file's FRAME0 (the WFS frame counter of its first row) */
    long frame0;
} slopes_file;

#define NO_FILE ((size_t)-1) /* work.cube_file of a cube whose telemetry file cannot be read */

typedef struct work {
    const swfs_sync_run_options *o;
    double *R;                /* the linear model's tilt rows (o->lin.basis), built at the first file */
    swfs_science_track *tr;
    swfs_handshake *hs;
    size_t nhs, nfiles, files_cap, nwfs_slopes;
    slopes_file *files;       /* grows: the log's files and the neighbours the cubes reach */
    swfs_sync_cube *cubes;
    size_t *cube_file;
    long *cube_hs;
    char logdir[4096];
    swfs_sync_params params;  /* o->params with the ratio range resolved (ratio_bound) */
    double wfs_rate;          /* [Hz] WFSRATE of the first telemetry file that has it (0: none) */
    struct boundary_memo { size_t a, b; swfs_sync_boundary bd; } *memo; /* checked boundaries, file a -> b */
    size_t nmemo, memo_cap;
} work;

static int load_file(work *w, const char *name, size_t *fi)
{
    for (*fi = 0; *fi < w->nfiles; (*fi)++)
        if (!strcmp(w->files[*fi].name, name)) return SWFS_OK;
    if (w->nfiles == w->files_cap) {
        const size_t cap = w->files_cap ? 2 * w->files_cap : 8;
        slopes_file *f = realloc(w->files, cap * sizeof *f);
        if (!f) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", name);
        memset(f + w->files_cap, 0, (cap - w->files_cap) * sizeof *f);
        w->files = f;
        w->files_cap = cap;
    }
    char path[8192];
    int rc = swfs_telemetry_path(w->logdir, name, path, sizeof path);
    swfs_real *s = NULL;
    if (!rc && access(path, F_OK) != 0)
        rc = swfs_fail(SWFS_ERR_IO, "%s: no such telemetry file (%s)", path, strerror(errno));
    double rate = 0; /* WFSRATE (0: none), for the least ratio from the camera's EXPTIME */
    if (!rc) rc = swfs_telemetry_read(path, 0, &s, &rate);
    if (rc) return rc;
    if (!(w->wfs_rate > 0)) w->wfs_rate = rate;
    const int lin = w->o->lin.basis != NULL;
    /* the width (a 3-D file swfs_telemetry_read has refused) */
    if ((!lin && s->nx % 2) || (w->nwfs_slopes && s->nx != w->nwfs_slopes))
        rc = swfs_fail(SWFS_ERR_SHAPE, "%s: %s must be a 2-D image %s x N_WFS, got %zux%zux%zu", path,
                       lin ? "telemetry" : "slopes", lin ? (w->nwfs_slopes ? "NVALUES (the same in every file)" : "NVALUES")
                       : (w->nwfs_slopes ? "NSLOPES (even, the same in every file)" : "NSLOPES (even)"), s->nx, s->ny, s->nz);
    slopes_file *f = &w->files[*fi];
    if (!rc && (!(f->mx = malloc(s->ny * sizeof(double))) || !(f->my = malloc(s->ny * sizeof(double))))) {
        free(f->mx);
        f->mx = NULL;
        rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    }
    if (!rc) { /* FRAME0, where the writer gave it: the files' own account of their frames */
        swfs_fits_in *h = NULL;
        long f0 = 0;
        f->has_frame0 = 0;
        rc = swfs_fits_in_open(&h, path, NULL);
        if (!rc) rc = swfs_fits_in_key_long_opt(h, "FRAME0", 0, (long)1 << 50, &f0, &f->has_frame0);
        swfs_fits_in_close(h);
        f->frame0 = f0;
    }
    if (!rc) {
        w->nwfs_slopes = s->nx;
        snprintf(f->name, sizeof f->name, "%s", name);
        f->nwfs = s->ny;
        if (lin && !w->R) rc = swfs_linear_tilt_rows(&w->o->lin, w->o->science, s->nx, &w->R);
        if (lin && !rc) swfs_tilt_rows_apply(w->R, s->data, s->nx, s->ny, f->mx, f->my);
        else if (!lin) swfs_slopes_mean_xy(s->data, s->nx, s->ny, NULL, f->mx, f->my);
        w->nfiles++;
    }
    swfs_real_free(s);
    return rc;
}

/* Cube ci: its handshake entry, its telemetry file's mean slopes, its timing-table row. A
 * telemetry file that cannot be read (missing, truncated, NaN values, another shape) leaves
 * the cube out (NO_FILE; r->nmissing, the first reason in r->missing_reason): one bad file
 * of a night does not stop the rest. */
static int setup_cube(const swfs_sync_run_options *o, work *w, size_t ci, swfs_timing_cube *tc, swfs_sync_run_result *r)
{
    const char *cam = w->tr->camera[ci];
    size_t h = w->nhs, fi;
    for (size_t k = 0; k < w->nhs; k++)
        if (!strcmp(w->hs[k].camera, cam)) { h = k; break; }
    if (h == w->nhs) return swfs_fail(SWFS_ERR_VALUE, "%s: the handshake log does not cover cube %zu (%s)", o->handshake, ci, cam);
    const size_t first = w->tr->first[ci], n = w->tr->n[ci];
    w->cube_hs[ci] = w->hs[h].frame;
    snprintf(tc->camera, sizeof tc->camera, "%s", cam);
    snprintf(tc->slopes, sizeof tc->slopes, "%s", w->hs[h].slopes);
    tc->first = first;
    tc->nframes = n;
    int rc = load_file(w, w->hs[h].slopes, &fi);
    if (rc == SWFS_ERR_NOMEM) return rc;
    if (rc) { /* a file missing, truncated or not telemetry of this kind: the cube is left out */
        w->cube_file[ci] = NO_FILE;
        if (!r->nmissing++) snprintf(r->missing_reason, sizeof r->missing_reason, "%s", swfs_last_error());
        r->nexp_missing += n;
        return SWFS_OK;
    }
    w->cube_file[ci] = fi;
    w->cubes[ci] = (swfs_sync_cube){n, w->tr->x + first, w->tr->y + first, w->files[fi].mx, w->files[fi].my,
                                    w->files[fi].nwfs, (double)w->hs[h].frame};
    return SWFS_OK;
}

/* The timing table may live elsewhere: it records the telemetry file's absolute path. */
static int table_path(const work *w, const char *name, char *out, size_t cap)
{
    char rel[8192], *abs = NULL;
    int rc = swfs_telemetry_path(w->logdir, name, rel, sizeof rel);
    if (rc) return rc;
    abs = realpath(rel, NULL);
    int len = snprintf(out, cap, "%s", abs ? abs : rel);
    free(abs);
    if (len < 0 || (size_t)len >= cap) return swfs_fail(SWFS_ERR_ARG, "%s: telemetry path too long", rel);
    return SWFS_OK;
}

/* Exposures [*j0, *j1) of n that lie wholly in a file of nwfs WFS frames when the cube starts
 * at s there: s + j ratio >= 0 and s + (j + 1) ratio <= nwfs. */
static void inside(double s, double ratio, size_t n, size_t nwfs, size_t *j0, size_t *j1)
{
    double lo = fmax(ceil(-s / ratio), 0), hi = fmin(floor(((double)nwfs - s) / ratio), (double)n);
    *j0 = lo > (double)n ? n : (size_t)lo;
    *j1 = hi > lo ? (size_t)hi : *j0;
}

/* The telemetry file just before (dir -1) or after (+1) name: the numbered neighbour in the
 * same folder when it exists (slopes_004.fits -> slopes_005.fits), else the neighbour among
 * the folder's files named like it (time-stamped names; swfs_telemetry_neighbour_), else the next or
 * previous one in the order the handshake log first names them; NULL if none. sync's check
 * on the data (split_cube) decides whether it really continues name. */
static const char *adjacent_file(const work *w, const char *name, int dir, char *buf, size_t cap)
{
    return swfs_telemetry_neighbour_(w->logdir, name, dir, w->nhs ? w->hs[0].slopes : NULL, sizeof *w->hs, w->nhs, buf,
                                     cap) ? buf : NULL;
}

/* One row of the table: exposures [j0, j1) of the cube, starting at s in the file name. */
static int add_row(const work *w, const swfs_timing_cube *c, size_t j0, size_t j1, const char *name, double s,
                   int status, swfs_timing *t)
{
    if (j1 <= j0) return SWFS_OK;
    swfs_timing_cube *row = &t->cubes[t->ncubes++];
    *row = *c;
    row->first = c->first + j0;
    row->nframes = j1 - j0;
    row->start = s;
    row->status = status;
    return table_path(w, name, row->slopes, sizeof row->slopes);
}

/* The first (tail 0) or last (tail 1) SWFS_SYNC_EDGE_FRAMES frames of telemetry file fi, read
 * again from its file: the edges are kept for no longer than one boundary check, as a night's
 * files would not fit in memory. */
static int read_edge(const work *w, size_t fi, int tail, double **buf, size_t *n)
{
    char path[8192];
    swfs_fits_in *f = NULL;
    const size_t nwfs = w->files[fi].nwfs, k = nwfs < SWFS_SYNC_EDGE_FRAMES ? nwfs : SWFS_SYNC_EDGE_FRAMES;
    *buf = NULL;
    *n = k;
    int rc = swfs_telemetry_path(w->logdir, w->files[fi].name, path, sizeof path);
    if (!rc) rc = swfs_fits_in_open(&f, path, NULL);
    if (!rc && !(*buf = malloc(k * w->nwfs_slopes * sizeof **buf))) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    if (!rc) rc = swfs_fits_in_read_rows(f, tail ? nwfs - k : 0, k, *buf);
    swfs_fits_in_close(f);
    if (rc) {
        free(*buf);
        *buf = NULL;
    }
    return rc;
}

/* The telemetry's own verdict on file a running on into file b (swfs_sync_boundary_check),
 * checked once per pair. */
static int boundary(work *w, size_t a, size_t b, swfs_sync_boundary *out)
{
    for (size_t k = 0; k < w->nmemo; k++)
        if (w->memo[k].a == a && w->memo[k].b == b) {
            *out = w->memo[k].bd;
            return SWFS_OK;
        }
    if (w->nmemo == w->memo_cap) {
        const size_t cap = w->memo_cap ? 2 * w->memo_cap : 8;
        struct boundary_memo *m = realloc(w->memo, cap * sizeof *m);
        if (!m) return swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory");
        w->memo = m;
        w->memo_cap = cap;
    }
    double *ta = NULL, *hb = NULL;
    size_t na = 0, nb = 0;
    int rc = read_edge(w, a, 1, &ta, &na);
    if (!rc) rc = read_edge(w, b, 0, &hb, &nb);
    if (!rc) rc = swfs_sync_boundary_check(ta, na, hb, nb, w->nwfs_slopes, out);
    free(ta);
    free(hb);
    if (!rc) w->memo[w->nmemo++] = (struct boundary_memo){a, b, *out};
    return rc;
}

/* Whether `lost` WFS frames missing between files a and b (< 0: repeated) is what the telemetry
 * across the boundary shows (swfs_sync_boundary_gap), read again from the files. */
static int gap_agrees(const work *w, size_t a, size_t b, long lost, int *agrees)
{
    double *ta = NULL, *hb = NULL;
    size_t na = 0, nb = 0;
    swfs_sync_gap g;
    *agrees = 0;
    int rc = read_edge(w, a, 1, &ta, &na);
    if (!rc) rc = read_edge(w, b, 0, &hb, &nb);
    if (!rc) rc = swfs_sync_boundary_gap(ta, na, hb, nb, w->nwfs_slopes, lost, &g);
    if (!rc) *agrees = g.consistent;
    free(ta);
    free(hb);
    return rc;
}

/* One cube's telemetry files at a fit's timing: segment k holds the exposures [j0, j1) that lie
 * wholly in file fi, where the cube starts at s (WFS frames of fi); the segments are in time
 * order and contiguous file to file, own the cube's own file (its handshake entry). cc: the
 * check on the data that made a neighbour's segment part of the chain. */
typedef struct chain_seg {
    size_t fi, j0, j1;
    double s;
    swfs_sync_continuation cc;
    int verdict; /* the telemetry's verdict on the boundary into this segment's file */
    size_t window; /* its second stage's window (swfs_sync_boundary), 0: none */
    long lost;   /* WFS frames lost across that boundary (< 0: repeated), the camera's count where
                    the telemetry says the files do not continue each other, or the files' FRAME0;
                    0: contiguous */
    int frame0;  /* the files' FRAME0 placed the segment (the telemetry did not contradict them) */
} chain_seg;

typedef struct chain {
    chain_seg *seg;
    size_t nseg, own, cap;
} chain;

static int chain_push(chain *ch, const chain_seg *sg, int front)
{
    if (ch->nseg == ch->cap) {
        const size_t cap = ch->cap ? 2 * ch->cap : 4;
        chain_seg *t = realloc(ch->seg, cap * sizeof *t);
        if (!t) return swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory");
        ch->seg = t;
        ch->cap = cap;
    }
    if (front) {
        memmove(ch->seg + 1, ch->seg, ch->nseg * sizeof *ch->seg);
        ch->seg[0] = *sg;
        ch->own++;
    } else {
        ch->seg[ch->nseg] = *sg;
    }
    ch->nseg++;
    return SWFS_OK;
}

/* The part of cube c in file fi where it starts at sb there (WFS frames of fi): its exposures
 * [j0, j1) inside fi beyond those already placed (dir < 0: before lo, dir > 0: from hi on) and
 * the camera's check of them (swfs_sync_continuation_check). 0 when no exposure lies there. */
static int place_part(work *w, const swfs_sync_cube *c, size_t fi, double sb, int dir, size_t lo, size_t hi,
                      const swfs_sync_result *fit, chain_seg *sg, int *rc)
{
    const double R = fit->ratio;
    size_t j0, j1;
    inside(sb, R, c->nframes, w->files[fi].nwfs, &j0, &j1);
    if (dir < 0 && j1 > lo) j1 = lo;
    if (dir > 0 && j0 < hi) j0 = hi;
    if (j1 <= j0) return 0;
    const double st = sb + (double)j0 * R;
    const swfs_sync_cube part = {j1 - j0, c->tx + j0, c->ty + j0, w->files[fi].mx, w->files[fi].my,
                                 w->files[fi].nwfs, st + fit->lag};
    *sg = (chain_seg){fi, j0, j1, sb, {0}, 0, 0, 0, 0};
    *rc = swfs_sync_continuation_check(&part, fit, &w->params, &sg->cc);
    return 1;
}

/* Whether the camera lets a part join that something else (the telemetry, the files' FRAME0)
 * places: it does not where its best lag is significant and tol or more from the fit's; where
 * the telemetry itself says contiguous only where that lag is also told from the placement
 * (off_significant) and a frame or more off (build_chain). */
static int camera_allows(const swfs_sync_continuation *cc, double tol, int telemetry_contiguous)
{
    const double off = fabs(cc->offset);
    return telemetry_contiguous ? !(cc->significant && cc->off_significant && !(off < fmax(1.0, tol)))
                                : !(cc->significant && !(off < tol));
}

/* Cube ci's chain at fit: its own file's exposures, then file by file outwards (adjacent_file)
 * the neighbours' while the files continue each other. Two checks decide, one on the camera
 * and one on the telemetry alone:
 * - swfs_sync_continuation_check: the part's camera tip-tilt is significant against the file
 *   and its best lag is within tol(j) of the fit's, tol(j) = 0.5 + slack |j - j_own| WFS
 *   frames (j a part's middle exposure, j_own the own file's): slack = 0 is the check's own
 *   rule (files hold whole frames: a lost or repeated frame moves the lag by one or more);
 *   slack > 0 widens it by the drift an uncertain ratio makes over the exposures in between.
 * - swfs_sync_boundary_check on the telemetry across the boundary. Where it says contiguous,
 *   the part joins unless the camera contradicts it: a significant best lag max(1, tol) frames
 *   or more from the fit's, whose correlations stand 5 sigma above those where the fit's lag
 *   puts the part (off_significant: on centre-of-gravity slopes the tilt's correlation is a
 *   flat ridge along lag, and a contiguous part's best lag lay 1.15 frames off at correlations
 *   0.90 / 0.22 against 0.93 / 0.18 in place; docs/telemetry.md). A part of 25 exposures
 *   measures its lag to a few tenths of a frame only (contiguous files were refused at -0.66
 *   and -0.74: docs/telemetry.md, t16-f250), and one of 5 exposures is not significant at all.
 *   Where the telemetry says not contiguous, the
 *   part is refused, unless frames were lost or repeated there by a count the camera and the
 *   telemetry both show (below): then it is placed that many frames off. Where the telemetry
 *   cannot tell, the camera's rule alone decides.
 * Where both files carry FRAME0 (the writer's WFS frame counter of its first row) they say
 * where the part lies: B's first frame FRAME0_B - FRAME0_A - nwfs_A frames after A's last
 * (0: contiguous). Unless the telemetry contradicts them (not contiguous where they say
 * contiguous, contiguous where they count frames lost: a file cut or a header copied), the
 * part is placed there and joins unless the camera contradicts it: by the contiguous
 * verdict's rule where the telemetry says contiguous too, else a significant best lag tol or
 * more from the fit's. Where either contradicts them the data decide as above. The 8 x 8 and
 * 10 x 10 foreign loops of 40 modes lost a cube's 49 exposures where neither the telemetry
 * (undecided) nor the camera (not significant over 49 exposures) could tell
 * (docs/telemetry.md). */
static int build_chain(work *w, size_t ci, const swfs_sync_result *fit, double slack, chain *ch)
{
    const swfs_sync_cube *c = &w->cubes[ci];
    const size_t fa = w->cube_file[ci], n = c->nframes;
    const double R = fit->ratio, s = (double)w->cube_hs[ci] - fit->lag;
    size_t a0, a1;
    ch->nseg = ch->own = 0;
    if (fa == NO_FILE) return SWFS_OK; /* no telemetry: no segment */
    inside(s, R, n, w->files[fa].nwfs, &a0, &a1);
    if (a1 <= a0) { /* no whole exposure in its own file: the parts before and after meet at its edge */
        const double e = s >= 0 ? floor(((double)w->files[fa].nwfs - s) / R) : ceil(-s / R);
        a0 = a1 = e <= 0 ? 0 : e >= (double)n ? n : (size_t)e;
    }
    const chain_seg own = {fa, a0, a1, s, {0}, 0, 0, 0, 0};
    int rc = chain_push(ch, &own, 0);
    const double jown = 0.5 * (double)(a0 + a1);
    for (int dir = -1; !rc && dir <= 1; dir += 2) {
        size_t cur = fa, lo = a0, hi = a1;
        double scur = s;
        while (!rc && (dir < 0 ? lo > 0 : hi < n)) {
            char nbuf[SWFS_SYNC_NAME];
            const char *name = adjacent_file(w, w->files[cur].name, dir, nbuf, sizeof nbuf);
            size_t fi;
            rc = name ? load_file(w, name, &fi) : SWFS_OK;
            if (rc == SWFS_ERR_NOMEM) break;
            if (rc || !name) { rc = SWFS_OK; break; } /* a neighbour that is not telemetry of this kind continues nothing */
            int seen = 0;
            for (size_t k = 0; k < ch->nseg && !seen; k++) seen = ch->seg[k].fi == fi;
            if (seen) break;
            const double sb = dir < 0 ? scur + (double)w->files[fi].nwfs : scur - (double)w->files[cur].nwfs;
            const size_t ea = dir < 0 ? fi : cur, eb = dir < 0 ? cur : fi;
            const int hdr = w->files[ea].has_frame0 && w->files[eb].has_frame0;
            const long hdr_lost = hdr ? w->files[eb].frame0 - w->files[ea].frame0 - (long)w->files[ea].nwfs : 0;
            swfs_sync_boundary bd;
            if ((rc = boundary(w, ea, eb, &bd))) break;
            const int by_hdr = hdr && (hdr_lost == 0 ? bd.verdict >= 0 : bd.verdict <= 0);
            chain_seg sg;
            int ok = 0, placed = 0;
            if (by_hdr) { /* the part where the two counters put it, unless the camera contradicts */
                const double sh = scur + (double)(w->files[cur].frame0 - w->files[fi].frame0);
                if (!place_part(w, c, fi, sh, dir, lo, hi, fit, &sg, &rc) || rc) break;
                ok = camera_allows(&sg.cc, 0.5 + slack * fabs(0.5 * (double)(sg.j0 + sg.j1) - jown), bd.verdict > 0);
                sg.frame0 = ok;
                sg.lost = ok ? hdr_lost : 0;
                /* counters that say contiguous placed it where the data would: the rules below
                 * (the telemetry's verdict then >= 0) ask no less of the same check */
                placed = hdr_lost == 0;
            }
            if (!ok && !placed && !place_part(w, c, fi, sb, dir, lo, hi, fit, &sg, &rc)) break;
            if (rc) break;
            const double tol = 0.5 + slack * fabs(0.5 * (double)(sg.j0 + sg.j1) - jown);
            const double off = fabs(sg.cc.offset);
            if (!ok)
                ok = bd.verdict > 0 ? camera_allows(&sg.cc, tol, 1) : bd.verdict == 0 && sg.cc.significant && off < tol;
            if (!ok && bd.verdict < 0 && sg.cc.significant) {
                /* Not contiguous: the camera counts the frames lost (or repeated) between the
                 * files, a whole number k != 0 of WFS frames within tol of its lag offset, the
                 * nearest first (k > 0: the part lies k frames later than contiguity puts it,
                 * for dir < 0 earlier), and the telemetry across the boundary must show that
                 * count too (gap_agrees: the camera alone mistakes a missing file for a few
                 * frames where the tip-tilt is periodic). The part is placed again there and
                 * joins when the camera then finds it in place. Where the telemetry cannot
                 * tell (verdict 0) nothing is counted: a part of 25 exposures puts a contiguous
                 * boundary 0.6-0.7 frames off, and the telemetry that leaves 0 and 1 lost
                 * undecided cannot refuse the 1. */
                const double o = sg.cc.offset, k0 = nearbyint(o);
                const chain_seg first = sg;
                for (int t = 0; !ok && !rc && t <= 2 * (int)ceil(tol); t++) {
                    /* candidates k0, k0 +- 1, ... in order of distance from o */
                    const double k = k0 + ((t + 1) / 2) * (((t % 2) == 1) == (o >= k0) ? 1.0 : -1.0);
                    const long lost = (long)(dir > 0 ? k : -k);
                    int agrees = 0;
                    if (k == 0 || !(fabs(o - k) < tol) || (double)w->files[ea].nwfs + (double)lost < 1) continue;
                    if ((rc = gap_agrees(w, ea, eb, lost, &agrees)) || !agrees) continue;
                    if (place_part(w, c, fi, sb - k, dir, lo, hi, fit, &sg, &rc) && !rc &&
                        (ok = sg.cc.significant && fabs(sg.cc.offset) < tol))
                        sg.lost = lost;
                    else
                        sg = first;
                }
                if (rc) break;
            }
            sg.verdict = bd.verdict;
            sg.window = bd.window;
            if (!ok) break;
            if ((rc = chain_push(ch, &sg, dir < 0))) break;
            cur = fi;
            scur = sg.s;
            if (dir < 0) lo = sg.j0;
            else hi = sg.j1;
        }
    }
    return rc;
}

static int chains_equal(const chain *a, const chain *b, size_t nc)
{
    for (size_t ci = 0; ci < nc; ci++) {
        if (a[ci].nseg != b[ci].nseg || a[ci].own != b[ci].own) return 0;
        for (size_t k = 0; k < a[ci].nseg; k++)
            if (a[ci].seg[k].fi != b[ci].seg[k].fi || a[ci].seg[k].lost != b[ci].seg[k].lost) return 0;
    }
    return 1;
}

/* Frames lost (< 0: repeated) between segment k - 1 and segment k of a chain (k >= 1): each
 * segment holds the count of its boundary toward the own file's. */
static long seg_lost(const chain *ch, size_t k) { return k <= ch->own ? ch->seg[k - 1].lost : ch->seg[k].lost; }

static size_t chains_joined(const chain *ch, size_t nc)
{
    size_t m = 0;
    for (size_t ci = 0; ci < nc; ci++) m += ch[ci].nseg ? ch[ci].nseg - 1 : 0;
    return m;
}

/* The fit again, each cube's chain of files joined end to end into one series (the files are
 * contiguous there: build_chain), over the ratios within 5 coarse steps and the lags within 2
 * WFS frames of fit0: a cube now lies in one series, so its whole length pins the ratio where
 * its own file held a part of it. The detection's figures (the bound z_need of the full
 * search, its lag window) stay fit0's. */
static int refit_joined(work *w, const chain *ch, size_t nc, const swfs_sync_result *fit0, swfs_sync_result *out)
{
    swfs_sync_cube *jc = calloc(nc, sizeof *jc);
    double **buf = calloc(nc, sizeof *buf);
    size_t nj = 0; /* the cubes with telemetry */
    int rc = jc && buf ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory");
    for (size_t ci = 0; !rc && ci < nc; ci++) {
        if (!ch[ci].nseg) continue;
        /* File k starts at pos(k) of the series: the files before it and the frames lost
         * between them (seg_lost; repeated frames overlap, lost ones are filled by a straight
         * line from the last frame before to the first after). */
        size_t ntot = 0, before = 0;
        for (size_t k = 0; k < ch[ci].nseg; k++) {
            ntot = (size_t)((long)ntot + (k ? seg_lost(&ch[ci], k) : 0));
            if (k == ch[ci].own) before = ntot;
            ntot += w->files[ch[ci].seg[k].fi].nwfs;
        }
        double *b = buf[nj] = malloc(2 * ntot * sizeof **buf);
        if (!b) { rc = swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory"); break; }
        size_t o = 0;
        for (size_t k = 0; k < ch[ci].nseg; k++) {
            const slopes_file *f = &w->files[ch[ci].seg[k].fi];
            const long gap = k ? seg_lost(&ch[ci], k) : 0;
            for (long g = 1; g <= gap; g++, o++) {
                const double t = (double)g / (double)(gap + 1);
                b[o] = (1 - t) * b[o - 1] + t * f->mx[0];
                b[ntot + o] = (1 - t) * b[ntot + o - 1] + t * f->my[0];
            }
            if (gap < 0) o -= (size_t)(-gap);
            memcpy(b + o, f->mx, f->nwfs * sizeof *b);
            memcpy(b + ntot + o, f->my, f->nwfs * sizeof *b);
            o += f->nwfs;
        }
        jc[nj] = w->cubes[ci];
        jc[nj].mx = b;
        jc[nj].my = b + ntot;
        jc[nj].nwfs = ntot;
        jc[nj].logged = (double)before + (double)w->cube_hs[ci];
        nj++;
    }
    if (!rc) {
        swfs_sync_params p = w->params;
        p.ratio_min = fmax(fit0->ratio - 5 * p.ratio_step, 0.5 * fit0->ratio);
        p.ratio_max = fit0->ratio + 5 * p.ratio_step;
        p.lag_min = fit0->lag - 2;
        p.lag_max = fit0->lag + 2;
        rc = swfs_sync_estimate(jc, nj, &p, out);
    }
    if (!rc) {
        out->z_need = fit0->z_need;
        out->lag_min = fit0->lag_min;
        out->lag_max = fit0->lag_max;
        out->lag_moves = fit0->lag_moves;
    }
    for (size_t ci = 0; buf && ci < nc; ci++) free(buf[ci]);
    free(buf);
    free(jc);
    return rc;
}

/* The fit that decides the table. fit0 is the fit over the cubes' own files. A file shorter
 * than a cube leaves each cube a short part there, and fit0's ratio is then only as good as
 * those parts: its error, carried over the exposures to the next file, moved the lags of
 * contiguous files by 0.54-0.67 WFS frames (docs/telemetry.md, t16-files600), and the
 * half-frame rule refused them. So the chains are first built with the tolerance widened by
 * 3 sigma of fit0's ratio drift, the fit is made again over the chains joined end to end
 * (refit_joined), and the chains are built again at the refit by the strict rule; until they
 * agree with the ones refitted (at most 3 rounds). Only the strict chains make rows. */
static int settle_chains(work *w, size_t nc, swfs_sync_result *fit, chain *fin, swfs_sync_run_result *r)
{
    const swfs_sync_result fit0 = *fit;
    chain *used = calloc(nc, sizeof *used);
    int rc = used ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "sync: out of memory");
    for (size_t ci = 0; !rc && ci < nc; ci++) rc = build_chain(w, ci, &fit0, 3 * fit0.ratio_err, &used[ci]);
    int settled = 0;
    for (int round = 0; !rc && round < 3 && chains_joined(used, nc); round++) {
        if ((rc = refit_joined(w, used, nc, &fit0, fit))) break;
        r->refits++;
        for (size_t ci = 0; !rc && ci < nc; ci++) rc = build_chain(w, ci, fit, 0, &fin[ci]);
        if (rc || (settled = chains_equal(fin, used, nc))) break;
        for (size_t ci = 0; ci < nc; ci++) { /* the strict chains are refitted next round */
            const chain tmp = used[ci];
            used[ci] = fin[ci];
            fin[ci] = tmp;
        }
    }
    if (!rc && !settled) {
        if (!chains_joined(used, nc)) { /* no file continues another: the own files' fit */
            *fit = fit0;
            r->refits = 0;
        }
        for (size_t ci = 0; !rc && ci < nc; ci++) rc = build_chain(w, ci, fit, 0, &fin[ci]);
    }
    for (size_t ci = 0; used && ci < nc; ci++) free(used[ci].seg);
    free(used);
    return rc;
}

/* Cube ci's rows from its chain, in exposure order: each segment a usable row of its file
 * (joined to the cube when it is a neighbour's), the exposures between segments (they straddle
 * a boundary) rows of the own file marked straddles. */
static int chain_rows(const work *w, const swfs_timing_cube *c, const chain *ch, double R, swfs_timing *t,
                      swfs_sync_run_result *r)
{
    r->nexp += c->nframes;
    if (!ch->nseg) /* its telemetry file cannot be read (setup_cube): one row, left out */
        return add_row(w, c, 0, c->nframes, c->slopes, c->start, SWFS_CUBE_MISSING, t);
    const chain_seg *own = &ch->seg[ch->own];
    const char *oname = w->files[own->fi].name;
    int rc = SWFS_OK;
    size_t j = 0;
    for (size_t k = 0; k <= ch->nseg && !rc; k++) {
        const size_t j0 = k < ch->nseg ? ch->seg[k].j0 : c->nframes;
        if (j0 > j) rc = add_row(w, c, j, j0, oname, own->s + (double)j * R, SWFS_CUBE_STRADDLES, t);
        if (k == ch->nseg || rc) break;
        const chain_seg *sg = &ch->seg[k];
        if (sg->j1 > sg->j0) {
            r->nexp_ok += sg->j1 - sg->j0;
            r->nok++;
            rc = add_row(w, c, sg->j0, sg->j1, w->files[sg->fi].name, sg->s + (double)sg->j0 * R, SWFS_CUBE_OK, t);
            if (!rc && k != ch->own) {
                swfs_timing_cube *row = &t->cubes[t->ncubes - 1];
                row->joined = 1;
                row->join_offset = sg->cc.offset;
                row->join_corr_x = sg->cc.corr_x;
                row->join_corr_y = sg->cc.corr_y;
                row->join_verdict = sg->verdict;
                row->join_window = sg->window;
                row->join_lost = sg->lost;
                row->join_frame0 = sg->frame0;
                r->ncontinued++;
            }
        }
        j = sg->j1 > j ? sg->j1 : j;
    }
    return rc;
}

/* The ratio's upper bound from the handshake log: a camera cube of N frames that starts at
 * WFS frame h of a file, followed by the next cube at h' of the same file, lasts at most
 * (h' - h + 1) / N WFS frames per camera frame (the lag is common to both, the logged frames
 * are whole). The smallest over such pairs, or 0 when no two cubes share a file. */
static double ratio_bound(const work *w, const swfs_timing *t)
{
    double b = 0;
    for (size_t ci = 0; ci + 1 < t->ncubes; ci++) {
        if (w->cube_file[ci] == NO_FILE || w->cube_file[ci] != w->cube_file[ci + 1] || w->cube_hs[ci + 1] <= w->cube_hs[ci] ||
            !t->cubes[ci].nframes)
            continue;
        const double q = (double)(w->cube_hs[ci + 1] - w->cube_hs[ci] + 1) / (double)t->cubes[ci].nframes;
        if (b == 0 || q < b) b = q;
    }
    return b;
}

/* ratio_max <= 0: the search's ratios end at ratio_bound (SWFS_SYNC_RATIO_MAX_FALLBACK when the
 * log gives none) and are cut to the largest grid params_check allows; a ratio_min above the
 * bound is refused. */
static int resolve_ratio_range(work *w, const swfs_timing *t, swfs_sync_run_result *r)
{
    swfs_sync_params *p = &w->params;
    r->ratio_bound = ratio_bound(w, t);
    r->ratio_auto = !(p->ratio_max > 0);
    if (r->ratio_auto) p->ratio_max = r->ratio_bound > 0 ? r->ratio_bound : SWFS_SYNC_RATIO_MAX_FALLBACK;
    /* ratio_min <= 0: from the camera's exposure, which lasts at most its frame period, so
     * ratio >= EXPTIME x WFSRATE (EXPTIME less the resolution its header was written to; a
     * camera with dead time has a larger ratio), less SWFS_SYNC_EXPTIME_STEPS coarse steps
     * for the fit's own scatter about a ratio at the bound; SWFS_ENGINE_MIN_RATIO without
     * both keywords, or where that bound is above ratio_max */
    if (p->ratio_min <= 0) {
        p->ratio_min = SWFS_ENGINE_MIN_RATIO;
        if (w->tr->exptime > 0 && w->wfs_rate > 0) {
            r->exptime_ratio = (w->tr->exptime - w->tr->exptime_res) * w->wfs_rate;
            const double lo = r->exptime_ratio - SWFS_SYNC_EXPTIME_STEPS * p->ratio_step;
            if (lo > p->ratio_min && lo < p->ratio_max) {
                p->ratio_min = lo;
                r->exptime_used = 1;
            }
        }
    }
    if (!r->ratio_auto) return SWFS_OK;
    if (p->ratio_max < p->ratio_min)
        return swfs_fail(SWFS_ERR_ARG, "%s: the handshake log bounds the ratio at %g WFS frames per camera frame (a "
                         "camera cube ends before the next cube of its telemetry file starts), below the search's "
                         "least ratio %g: give --ratio-max, or check the log", w->o->handshake, p->ratio_max,
                         p->ratio_min);
    double nr, nl;
    swfs_sync_grid_size(p, &nr, &nl);
    const double nr_max = floor((double)SWFS_SYNC_MAX_GRID / nl);
    if (p->ratio_max > p->ratio_min + (nr_max - 1) * p->ratio_step) p->ratio_max = p->ratio_min + (nr_max - 1) * p->ratio_step;
    return SWFS_OK;
}

int swfs_sync_run(const swfs_sync_run_options *o, swfs_sync_run_result *r)
{
    memset(r, 0, sizeof *r);
    if (!o->science || !o->handshake || !o->out) return swfs_fail(SWFS_ERR_ARG, "sync: needs science, handshake, out");
    work w;
    memset(&w, 0, sizeof w);
    w.o = o;
    swfs_timing *t = &r->t;
    swfs_paths *paths = NULL;
    /* The ranges checked now; a ratio_max from the log (<= 0) is resolved once the cubes are read. */
    w.params = o->params;
    swfs_sync_params chk = o->params;
    if (chk.ratio_min <= 0) chk.ratio_min = SWFS_ENGINE_MIN_RATIO; /* resolved from EXPTIME once read */
    if (chk.ratio_max <= 0) chk.ratio_max = fmax(chk.ratio_min, SWFS_SYNC_RATIO_MAX_FALLBACK);
    int rc = swfs_sync_params_check(&chk);
    if (rc) return rc;
    rc = swfs_paths_create(&paths);
    swfs_paths_input(paths, "science cube", o->science);
    swfs_linear_paths(paths, &o->lin);
    swfs_paths_input(paths, "handshake log", o->handshake);
    if (!rc) rc = swfs_paths_output(paths, "output timing table", o->out);
    if (!rc) rc = swfs_science_track_read(o->science, &w.tr);
    if (!rc) rc = swfs_handshake_read(o->handshake, &w.hs, &w.nhs);
    /* The telemetry files the log names are inputs too. */
    for (size_t k = 0; !rc && k < w.nhs; k++) {
        char dir[4096], path[8192];
        swfs_path_dir(o->handshake, dir, sizeof dir);
        if (!(rc = swfs_telemetry_path(dir, w.hs[k].slopes, path, sizeof path)))
            rc = swfs_paths_input(paths, "telemetry file named by the handshake log", path);
    }
    swfs_paths_free(paths);
    if (!rc) {
        const size_t nc = w.tr->ncubes;
        swfs_path_dir(o->handshake, w.logdir, sizeof w.logdir);
        t->ncubes = nc;
        t->cubes = calloc(nc, sizeof *t->cubes);
        w.cubes = calloc(nc, sizeof *w.cubes);
        w.cube_file = calloc(nc, sizeof *w.cube_file);
        w.cube_hs = calloc(nc, sizeof *w.cube_hs);
        if (!t->cubes || !w.cubes || !w.cube_file || !w.cube_hs) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
    }
    for (size_t ci = 0; !rc && ci < t->ncubes; ci++) rc = setup_cube(o, &w, ci, &t->cubes[ci], r);
    if (!rc && r->nmissing == t->ncubes)
        rc = swfs_fail(SWFS_ERR_IO, "%s: no telemetry file of the %zu cube%s can be read; the first: %s", o->handshake,
                       t->ncubes, t->ncubes == 1 ? "" : "s", r->missing_reason);
    swfs_sync_cube *have = NULL; /* the cubes with telemetry, for the fit */
    size_t nhave = 0;
    if (!rc && !(have = malloc(t->ncubes * sizeof *have))) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
    for (size_t ci = 0; !rc && ci < t->ncubes; ci++)
        if (w.cube_file[ci] != NO_FILE) have[nhave++] = w.cubes[ci];
    if (!rc) {
        /* A best ratio at the least one EXPTIME gave: the header does not describe the frames
         * (an exposure time longer than their period); the search again from the engine's least */
        for (int pass = 0; !rc && pass < 2; pass++) {
            rc = resolve_ratio_range(&w, t, r);
            r->ratio_min = w.params.ratio_min;
            r->ratio_max = w.params.ratio_max;
            if (!rc) rc = swfs_sync_estimate(have, nhave, &w.params, &t->fit);
            if (rc || !r->exptime_used || !(t->fit.ratio < w.params.ratio_min + w.params.ratio_step)) break;
            w.params = o->params;
            w.params.ratio_min = SWFS_ENGINE_MIN_RATIO;
            r->exptime_used = 0;
            r->exptime_widened = 1;
        }
        /* The continuations search the window the fit ended in. */
        if (!rc) {
            w.params.lag_min = t->fit.lag_min;
            w.params.lag_max = t->fit.lag_max;
        }
    }
    if (!rc && !(t->fit.z >= t->fit.z_need)) {
        const swfs_sync_result *f = &t->fit;
        rc = swfs_fail(SWFS_ERR_VALUE, "%s: the camera's tip-tilt matches the telemetry's nowhere in the search: the "
                       "best ratio %.4f WFS frames per camera frame, lag %.2f, has correlations %.3f and %.3f over %.0f "
                       "independent exposures, %.1f sigma together, where a search of ratios %g to %g and lags %g to %g "
                       "needs %.1f. Check that the cubes and the handshake log %s belong together, or narrow the "
                       "search to the known ratio (--ratio-min/--ratio-max: the WFS rate over the camera's frame "
                       "rate) and lag (--lag-min/--lag-max)", o->science, f->ratio, f->lag, f->corr_x, f->corr_y,
                       f->neff, f->z, w.params.ratio_min, w.params.ratio_max, w.params.lag_min, w.params.lag_max,
                       f->z_need, o->handshake);
    }
    free(have);
    chain *ch = NULL;
    const size_t nc = t->ncubes;
    if (!rc) {
        r->ratio_first = t->fit.ratio;
        r->lag_first = t->fit.lag;
        if (!(ch = calloc(nc, sizeof *ch))) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
        if (!rc) rc = settle_chains(&w, nc, &t->fit, ch, r);
    }
    if (!rc) {
        t->ratio = t->fit.ratio;
        t->ratio_err = t->fit.ratio_err;
        t->lag = t->fit.lag;
        for (size_t ci = 0; ci < nc; ci++) /* the log's start of a cube left out, for its row */
            if (w.cube_file[ci] == NO_FILE) t->cubes[ci].start = (double)w.cube_hs[ci] - t->lag;
        /* A cube of s segments makes at most 2 s + 1 rows (chain_rows). */
        size_t nrows = 0;
        for (size_t ci = 0; ci < nc; ci++) nrows += 2 * ch[ci].nseg + 1;
        swfs_timing_cube *cubes = t->cubes;
        t->cubes = calloc(nrows, sizeof *t->cubes);
        t->ncubes = 0;
        if (!t->cubes) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", o->science);
        for (size_t ci = 0; !rc && ci < nc; ci++) rc = chain_rows(&w, &cubes[ci], &ch[ci], t->ratio, t, r);
        free(cubes);
        if (!rc) rc = swfs_timing_write(o->out, t);
    }
    for (size_t ci = 0; ch && ci < nc; ci++) free(ch[ci].seg);
    free(ch);
    if (!rc && !r->nok) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no exposure lies inside a telemetry file", o->science);
    swfs_science_track_free(w.tr);
    free(w.hs);
    for (size_t k = 0; w.files && k < w.nfiles; k++) { free(w.files[k].mx); free(w.files[k].my); }
    free(w.files); free(w.cubes); free(w.cube_file); free(w.cube_hs); free(w.R); free(w.memo);
    return rc;
}

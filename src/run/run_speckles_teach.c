/* speckles' default reconstructor: a map taught for the observation from its own files
 * (run.h SWFS_RECON_TEACH; docs/telemetry.md, "The default path: a map taught for each
 * observation"). */
#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/team.h"
#include "specklewfs/version.h"
#include "run_internal.h"

#include <dirent.h>
#include <errno.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* The telemetry files the timing table names, each once, in the table's order (the series'
 * order: sync writes the rows in camera time). */
int swfs_speckles_table_files_(const swfs_timing *t, const char *tdir, char **names, size_t *n)
{
    *n = 0;
    for (size_t c = 0; c < t->ncubes; c++) {
        char path[8192];
        int rc = swfs_telemetry_path(tdir, t->cubes[c].slopes, path, sizeof path);
        if (rc) return rc;
        if (*n && !strcmp(names[*n - 1], path)) continue;
        if (!(names[*n] = strdup(path))) return swfs_fail(SWFS_ERR_NOMEM, "speckles: out of memory");
        ++*n;
    }
    return SWFS_OK;
}

/* The work folder: o->teach_work, or beside out (swfs_teach_work_default); created (*made = 1
 * when this call made it). */
int swfs_speckles_work_folder_(const swfs_speckles_run_options *o, char *work, size_t cap, int *made)
{
    *made = 0;
    int rc = o->teach_work ? (snprintf(work, cap, "%s", o->teach_work) >= (int)cap
                                  ? swfs_fail(SWFS_ERR_ARG, "speckles: the teach folder's name %s is too long", o->teach_work)
                                  : SWFS_OK)
                           : swfs_teach_work_default(o->out, work, cap);
    if (!rc && !mkdir(work, 0777)) *made = 1;
    else if (!rc && errno != EEXIST)
        rc = swfs_fail(SWFS_ERR_IO, "speckles: cannot create the teach folder %s: %s", work, strerror(errno));
    return rc;
}

/* The loops' folders teach made in work (loop_NN, mixed_NN, modes_NN, zonal_NN, prior_NN,
 * speed_NN: the simulator's files, no subfolders), removed once the map is taught; what cannot
 * be removed is left as it is (the map is taught: it only costs space). */
static void drop_loops(const char *work, const struct swfs_teach_run_result *tr, size_t nloops)
{
    static const char *const kinds[] = {"loop", "mixed", "modes", "zonal", "prior", "speed"};
    for (int t = 0; t < 6; t++) {
        const size_t n = t == 5 ? tr->nspeed : t == 3 ? (tr->ncal ? SWFS_TEACH_NZONAL : 0)
                         : t == 2 ? tr->ncal : (t == 0 || t == 4) && tr->st_loops > nloops ? tr->st_loops : nloops;
        for (size_t k = 0; k < n; k++) {
            char d[4300], f[4600];
            snprintf(d, sizeof d, "%s/%s_%02zu", work, kinds[t], k);
            DIR *dir = opendir(d);
            if (!dir) continue;
            for (struct dirent *e; (e = readdir(dir));) {
                if (!strcmp(e->d_name, ".") || !strcmp(e->d_name, "..")) continue;
                snprintf(f, sizeof f, "%s/%s", d, e->d_name);
                (void)remove(f);
            }
            closedir(dir);
            (void)rmdir(d);
        }
    }
}

/* The fingerprint of what a taught map depends on (TEACHFPR): FNV-1a (64 bits) over the
 * library's version and teach's rule (SWFS_TEACH_RULE), the description teach is given (c's
 * keys and values, in order), the loops and the seed, and the contents of the telemetry files
 * and of the system's files (actuators, pupil, valid map). Each text item is hashed with its
 * NUL and each file after a label and with its length, so that no item runs into the next. */
static uint64_t fnv(uint64_t h, const void *p, size_t n)
{
    const unsigned char *b = p;
    for (size_t i = 0; i < n; i++) h = (h ^ b[i]) * 0x100000001b3ULL;
    return h;
}

uint64_t swfs_fnv_text_(uint64_t h, const char *s)
{
    return fnv(h, s, strlen(s) + 1); /* with its NUL: the end of the item */
}

int swfs_fnv_file_(uint64_t *h, const char *label, const char *path)
{
    FILE *f = fopen(path, "rb");
    if (!f) return swfs_fail(SWFS_ERR_IO, "speckles: cannot read %s (%s) for teach's fingerprint: %s", path, label,
                             strerror(errno));
    unsigned char *buf = malloc(1u << 20);
    if (!buf) {
        fclose(f);
        return swfs_fail(SWFS_ERR_NOMEM, "speckles: out of memory");
    }
    uint64_t x = swfs_fnv_text_(*h, label), len = 0;
    for (size_t k; (k = fread(buf, 1, 1u << 20, f)) > 0;) {
        x = fnv(x, buf, k);
        len += k;
    }
    const int bad = ferror(f);
    free(buf);
    fclose(f);
    if (bad) return swfs_fail(SWFS_ERR_IO, "speckles: error reading %s (%s) for teach's fingerprint", path, label);
    *h = fnv(x, &len, sizeof len);
    return SWFS_OK;
}

static int fingerprint(const swfs_speckles_run_options *o, const swfs_config *c, char *const *names, size_t n,
                       char out[17])
{
    uint64_t h = 0xcbf29ce484222325ULL;
    h = swfs_fnv_text_(swfs_fnv_text_(h, "specklewfs " SWFS_VERSION), SWFS_TEACH_RULE);
    for (size_t k = 0; k < swfs_config_count(c); k++)
        h = swfs_fnv_text_(swfs_fnv_text_(h, swfs_config_key(c, k)), swfs_config_value(c, k));
    char v[64];
    snprintf(v, sizeof v, "loops %zu to %zu seed %" PRIu64, o->teach_loops, o->teach_max_loops, o->teach_seed);
    h = swfs_fnv_text_(h, v);
    int rc = SWFS_OK;
    for (size_t k = 0; !rc && k < n; k++) rc = swfs_fnv_file_(&h, "telemetry", names[k]);
    if (!rc) rc = swfs_fnv_file_(&h, "actuators", o->actuators);
    if (!rc && o->mask) rc = swfs_fnv_file_(&h, "pupil", o->mask);
    if (!rc && o->valid) rc = swfs_fnv_file_(&h, "valid", o->valid);
    if (!rc) snprintf(out, 17, "%016" PRIx64, h);
    return rc;
}

/* map taught for these inputs (its TEACHFPR is fpr): 1, with its choice and loops in tr; 0
 * when there is no such file, or it cannot be read, or it was taught for other inputs. */
static int taught_for(const char *map, const char *fpr, struct swfs_teach_run_result *tr)
{
    swfs_fits_in *f = NULL;
    if (swfs_fits_in_open(&f, map, NULL)) {
        swfs_clear_error();
        return 0;
    }
    char v[80] = "", sel[80] = "";
    int found = 0, fsel = 0, floops = 0;
    long loops = 0;
    int rc = swfs_fits_in_key_string_opt(f, "TEACHFPR", v, sizeof v, &found);
    if (!rc && found && !strcmp(v, fpr)) {
        rc = swfs_fits_in_key_string_opt(f, "TEACHSEL", sel, sizeof sel, &fsel);
        if (!rc) rc = swfs_fits_in_key_long_opt(f, "TEACHLOO", 0, 1L << 20, &loops, &floops);
    }
    swfs_fits_in_close(f);
    if (rc) swfs_clear_error();
    int chosen = -1;
    for (int k = 0; k < (int)(sizeof swfs_teach_chosen_names_ / sizeof *swfs_teach_chosen_names_) && fsel; k++)
        if (!strcmp(sel, swfs_teach_chosen_names_[k])) chosen = k;
    if (rc || !found || strcmp(v, fpr) || chosen < 0 || !floops) return 0;
    memset(tr, 0, sizeof *tr);
    tr->chosen = chosen;
    tr->nloops = (size_t)loops;
    return 1;
}

/* Teach as `teach --science --actuators [--pupil] [--valid]` does, into map; or reuse the map
 * there when it was taught for the same inputs (*reused = 1). fpr: their fingerprint. With
 * dm_gauss > 0 the loops' DM has Gaussian influence functions of that coupling (one more
 * `dm_coupling` key, after the user's), taught in the work folder's SWFS_TEACH_DM_DIR. */
static int teach(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir, const swfs_geom *g,
                 double dm_gauss, char *map, size_t cap, struct swfs_teach_run_result *tr, char fpr[17], int *reused)
{
    *reused = 0;
    fpr[0] = 0;
    char work[4200];
    int made = 0;
    char **names = calloc(t->ncubes ? t->ncubes : 1, sizeof *names);
    size_t n = 0;
    swfs_config *c = swfs_config_new();
    int rc = names && c ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "speckles: out of memory");
    if (!rc) rc = swfs_speckles_table_files_(t, tdir, names, &n);
    if (!rc && !n) rc = swfs_fail(SWFS_ERR_VALUE, "%s: names no telemetry file", o->timing);
    if (!rc) rc = swfs_speckles_work_folder_(o, work, sizeof work, &made);
    if (!rc && dm_gauss > 0) {
        const size_t len = strlen(work);
        if (snprintf(work + len, sizeof work - len, "/%s", SWFS_TEACH_DM_DIR) >= (int)(sizeof work - len))
            rc = swfs_fail(SWFS_ERR_ARG, "speckles: the teach folder's name %s is too long", work);
        made = 0;
        if (!rc && !mkdir(work, 0777)) made = 1;
        else if (!rc && errno != EEXIST)
            rc = swfs_fail(SWFS_ERR_IO, "speckles: cannot create the teach folder %s: %s", work, strerror(errno));
    }
    if (!rc && snprintf(map, cap, "%s/taught.fits", work) >= (int)cap)
        rc = swfs_fail(SWFS_ERR_ARG, "speckles: the teach folder's name %s is too long", work);
    /* the rate the run uses where the telemetry has none (--wfs-hz) */
    if (!rc && o->wfs_hz > 0) {
        char v[64];
        snprintf(v, sizeof v, "%.17g", o->wfs_hz);
        rc = swfs_config_set_kv(c, "wfs_rate", v);
    }
    if (!rc) rc = swfs_config_set_kv(c, "mode", "timeseries");
    /* what the user says of the system (--teach-set, checked with the options): first, so that
     * the files' description adds only the keys not given, as `teach key=value` */
    for (size_t k = 0; !rc && k < o->nteach_keys; k++) rc = swfs_config_set(c, o->teach_keys[k]);
    if (!rc && dm_gauss > 0) {
        char v[64];
        snprintf(v, sizeof v, "%.17g", dm_gauss);
        rc = swfs_config_set_kv(c, "dm_coupling", v);
    }
    const int filter_given = !rc && swfs_ts_config_gives_filter(c), noise_given = !rc && swfs_config_has(c, "slope_noise");
    if (!rc) rc = swfs_teach_describe_geom_(c, g, o->actuators, o->mask, o->valid, names[0]);
    if (!rc) rc = fingerprint(o, c, names, n, fpr);
    if (!rc && !o->teach_again && !o->teach_keep_loops && taught_for(map, fpr, tr)) {
        *reused = 1;
        goto done;
    }
    swfs_teach_run_options to;
    swfs_teach_run_options_default(&to);
    if (!rc) rc = swfs_ts_params_from_config(c, &to.sim);
    if (!rc) rc = swfs_ts_params_check(&to.sim);
    if (!rc) {
        to.files = (const char *const *)names;
        to.nfiles = n;
        to.out = map;
        to.work = work;
        to.nloops = o->teach_loops;
        to.max_loops = o->teach_max_loops;
        to.seed = o->teach_seed;
        to.modes_from_slopes = !filter_given;
        to.noise_from_slopes = !noise_given;
        to.coupling_from_recon = !swfs_config_has(c, "dm_coupling");
        to.prov = o->prov;
        to.nprov = o->nprov;
        to.progress = o->progress;
        to.progress_ctx = o->progress_ctx;
        to.fingerprint = fpr;
        rc = swfs_teach_run(&to, tr);
    }
    if (!rc && !o->teach_keep_loops) drop_loops(work, tr, to.nloops);
    if (rc && made) (void)rmdir(work); /* refused before any loop: the folder this run made, empty */
done:
    swfs_config_free(c);
    for (size_t k = 0; names && k < n; k++) free(names[k]);
    free(names);
    return rc;
}

/* One map taught (teach above, dm_gauss as there) for a run alone or a team: member 0 teaches,
 * the others wait for its map (teach is the same to the bit wherever it runs, but one folder
 * holds it). *taught, or fallback saying why not; a request to stop is not a map that cannot
 * be taught: the run ends, with no fallback. */
static int team_teach(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir, const swfs_geom *g,
                      double dm_gauss, char *map, size_t cap, struct swfs_teach_run_result *tr, char fpr[17],
                      int *reused, int *taught, char *fallback, size_t fcap)
{
    int rc = SWFS_OK, trc = SWFS_OK;
    *taught = *reused = 0;
    fallback[0] = map[0] = fpr[0] = 0;
    if (swfs_team_writer(o->team)) {
        trc = teach(o, t, tdir, g, dm_gauss, map, cap, tr, fpr, reused);
        *taught = !trc;
        if (trc) snprintf(fallback, fcap, "%s", swfs_last_error());
    } else {
        memset(tr, 0, sizeof *tr);
    }
    const int stopped = trc == SWFS_ERR_STOPPED ? trc : SWFS_OK;
    if (!swfs_team_active(o->team) && stopped) return stopped;
    if (swfs_team_active(o->team)) {
        rc = swfs_team_agree(o->team, stopped);
        if (!rc) rc = swfs_team_bcast0(o->team, taught, sizeof *taught);
        if (!rc) rc = swfs_team_bcast0(o->team, map, cap);
        if (!rc && !*taught && !swfs_team_writer(o->team))
            snprintf(fallback, fcap, "member 0 could not teach (its output says why)");
    }
    if (!*taught) map[0] = 0;
    return rc;
}

int swfs_speckles_teach_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                         const swfs_geom *g, swfs_speckles_run_result *r)
{
    swfs_teach_run_result own, *tr = o->teach ? o->teach : &own;
    return team_teach(o, t, tdir, g, 0.0, r->teach_map, sizeof r->teach_map, tr, r->teach_fingerprint,
                      &r->teach_reused, &r->taught, r->teach_fallback, sizeof r->teach_fallback);
}

int swfs_speckles_dm_choice_wanted_(const swfs_speckles_run_options *o, const swfs_speckles_run_result *r)
{
    if (!r->taught || o->lin.basis || o->pipe.wfs_rate) return 0;
    swfs_config *c = swfs_config_new();
    int told = !c;
    for (size_t k = 0; !told && k < o->nteach_keys; k++) told = swfs_config_set(c, o->teach_keys[k]) != SWFS_OK;
    if (!told) told = swfs_config_has(c, "dm_coupling") || swfs_config_has(c, "ao_recon");
    swfs_config_free(c);
    swfs_clear_error(); /* (the keys were checked with the options) */
    return !told;
}

int swfs_speckles_teach_dm_(const swfs_speckles_run_options *o, const swfs_timing *t, const char *tdir,
                            const swfs_geom *g, char *map, size_t cap, struct swfs_teach_run_result *tr,
                            char fpr[17], int *reused, int *taught, char *fallback, size_t fcap)
{
    return team_teach(o, t, tdir, g, SWFS_TEACH_DM_GAUSS, map, cap, tr, fpr, reused, taught, fallback, fcap);
}

/* Fuzzing the FITS readers (docs/fuzzing.md). One input = one file's bytes, handed to every
 * reader of the library that takes a FITS file: the generic reader (open, shape, frames,
 * keywords, geometry, extensions), and the product readers (HALO.fits, checkpoints, the
 * reduced science cube's TRACK, actuators, reconstructors, telemetry, the coherence input,
 * the noise model). Each must return a status (any status) without crashing, hanging,
 * leaking or touching memory it does not own.
 *
 * Built two ways from this file:
 *  - with SWFS_LIBFUZZER (cmake -DSWFS_FUZZ=ON, clang): the libFuzzer target fuzz_fits;
 *  - without: fuzz_corpus DIR..., the regression test that feeds every file of the kept
 *    corpus (tests/fuzz-corpus) to the same readers, run by ctest in every build. */
#include "specklewfs/checkpoint.h"
#include "specklewfs/coherence.h"
#include "specklewfs/estimate.h"
#include "specklewfs/fits.h"
#include "specklewfs/run.h"
#include "specklewfs/science.h"
#include "specklewfs/source.h"
#include "specklewfs/status.h"
#include "specklewfs/wfs.h"

#include <fitsio.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
#include "fuzz_tmp.h"

/* Images the harness lets the readers load: tile-compressed headers may claim any size,
 * and allocating terabytes is the system's "out of memory", not a bug of the reader. */
#define MAX_VALUES (1u << 20)

static int small_enough(const char *path)
{
    /* CFITSIO itself must not see a header the library has not checked (some crash it):
     * only a file the library opens is scanned here. */
    swfs_fits_in *chk = NULL;
    if (swfs_fits_in_open(&chk, path, NULL)) return 1; /* the readers refuse it the same way */
    swfs_fits_in_close(chk);
    fitsfile *fp = NULL;
    int st = 0, n = 0, ok = 1;
    fits_open_diskfile(&fp, path, READONLY, &st);
    if (st) { fits_clear_errmsg(); return 1; } /* the readers report it */
    fits_get_num_hdus(fp, &n, &st);
    for (int i = 1; i <= n && i <= 64 && !st && ok; i++) {
        int type = 0, cmp = 0, bitpix = 0, naxis = 0;
        long ax[9] = {0};
        fits_movabs_hdu(fp, i, &type, &st);
        if (st || type != IMAGE_HDU || !fits_is_compressed_image(fp, &st) || st) continue;
        fits_get_img_param(fp, 9, &bitpix, &naxis, ax, &st);
        double v = 1;
        for (int k = 0; k < naxis && k < 9; k++) v *= (double)ax[k];
        ok = !st && v <= MAX_VALUES;
        (void)cmp;
    }
    st = 0;
    fits_close_file(fp, &st);
    fits_clear_errmsg();
    return ok;
}

static void generic(const char *path)
{
    swfs_fits_in *f = NULL;
    if (swfs_fits_in_open(&f, path, NULL)) return;
    static const char *exts[] = {"HALO", "HALO_LF", "GAIN", "ACCUM", "TRACK", "WFE", "PUPIL", "MCF"};
    for (size_t e = 0; e <= sizeof exts / sizeof exts[0]; e++) {
        if (e > 0 && (!swfs_fits_in_has_ext(f, exts[e - 1]) || swfs_fits_in_move(f, exts[e - 1]))) continue;
        const swfs_fits_shape *s = swfs_fits_in_shape(f);
        double v, n = (double)s->nx * (double)s->ny * (double)s->nz;
        long l;
        char str[80];
        int found;
        swfs_geom g;
        (void)swfs_fits_in_geom(f, &g);
        (void)swfs_fits_in_key_double_opt(f, "WAVELEN", &v, &found);
        (void)swfs_fits_in_key_long_opt(f, "PUPN", 1, 8192, &l, &found);
        (void)swfs_fits_in_key_string_opt(f, "EXTNAME", str, sizeof str, &found);
        (void)swfs_fits_in_require_float(f, "a product");
        if (n > MAX_VALUES) continue;
        if (s->is_complex) {
            swfs_cplx *c = NULL;
            if (!swfs_fits_in_read_cplx_all(f, &c)) swfs_cplx_free(c);
        } else {
            swfs_real *r = NULL;
            if (!swfs_fits_in_read_real_all(f, &r)) swfs_real_free(r);
        }
    }
    swfs_fits_in_close(f);
}

static void products(const char *path)
{
    swfs_geom g;
    swfs_halo *h = NULL;
    if (!swfs_halo_read(path, &h, &g)) swfs_halo_free(h);
    swfs_accum *a = NULL;
    if (!swfs_accum_load(path, &a, &g)) swfs_accum_free(a);
    swfs_science_track *t = NULL;
    if (!swfs_science_track_read(path, &t)) swfs_science_track_free(t);
    double *xy = NULL;
    size_t nact = 0;
    if (!swfs_actuators_read(path, &xy, &nact)) free(xy);
    swfs_recon *rc = NULL;
    if (!swfs_recon_read(path, &rc)) swfs_recon_free(rc);
    swfs_real *tel = NULL;
    double rate = 0;
    if (!swfs_telemetry_read(path, 0, &tel, &rate)) swfs_real_free(tel);
    swfs_cplx *cube = NULL;
    double dt = 0, exp = 0;
    if (!swfs_coherence_read_input(path, &cube, &dt, &g, &exp)) swfs_cplx_free(cube);
    swfs_noise nz;
    (void)swfs_noise_from_header(path, NAN, NAN, &nz);
    (void)swfs_geom_read_file(path, &g); /* FITS header or KEY = VALUE text (--geom) */
}

/* The readers on one file's bytes. */
static int fuzz_one(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write_tmp(data, size, "swfs-fuzz", "fits");
    if (!path) return 0;
    if (small_enough(path)) {
        generic(path);
        products(path);
    }
    swfs_clear_error();
    return 0;
}

#ifdef SWFS_LIBFUZZER
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) { return fuzz_one(data, size); }
#else
#define FUZZ_REPLAY_NAME "fuzz_corpus"
#define FUZZ_REPLAY_WHAT "the FITS readers"
#include "fuzz_replay.h"
#endif

/* CFITSIO wrappers: see include/specklewfs/fits.h for the conventions. */
#include "specklewfs/fits.h"
#include "specklewfs/status.h"
#include "specklewfs/version.h"

#include <fitsio.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* Turn a CFITSIO status into our status with a message naming the file and action. */
static int fits_fail(int code, int fstatus, const char *path, const char *action)
{
    char text[FLEN_STATUS] = "";
    char detail[FLEN_ERRMSG] = "";
    fits_get_errstatus(fstatus, text);
    /* The first message on CFITSIO's stack is usually the most specific. */
    (void)fits_read_errmsg(detail);
    fits_clear_errmsg();
    if (fstatus == END_OF_FILE || fstatus == 107 /* tried to move past end of file */)
        return swfs_fail(code, "%s: %s: file is truncated (%s)", path, action, text);
    return swfs_fail(code, "%s: %s: %s%s%s", path, action, text, detail[0] ? " -- " : "", detail);
}

/* ---- reading ---------------------------------------------------------- */

struct swfs_fits_in {
    fitsfile *fp;
    char *path;
    swfs_fits_shape shape;
};

static int load_shape(swfs_fits_in *f)
{
    int st = 0, bitpix = 0, naxis = 0;
    long naxes[4] = {1, 1, 1, 1};
    fits_get_img_param(f->fp, 4, &bitpix, &naxis, naxes, &st);
    if (st) return fits_fail(SWFS_ERR_FORMAT, st, f->path, "reading image size");
    char ctype1[FLEN_VALUE] = "";
    int cst = 0;
    fits_read_key(f->fp, TSTRING, "CTYPE1", ctype1, NULL, &cst);
    int is_complex = naxis >= 3 && naxes[0] == 2 && cst == 0 && strcmp(ctype1, "COMPLEX") == 0;
    memset(&f->shape, 0, sizeof f->shape);
    f->shape.bitpix = bitpix;
    f->shape.is_complex = is_complex;
    if (is_complex) {
        if (naxis > 4) return swfs_fail(SWFS_ERR_FORMAT, "%s: complex image has %d axes (at most 4)", f->path, naxis);
        f->shape.nx = (size_t)naxes[1];
        f->shape.ny = (size_t)naxes[2];
        f->shape.nz = naxis == 4 ? (size_t)naxes[3] : 1;
    } else {
        if (naxis < 2 || naxis > 3)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: image has %d axes (expected a 2-D image or 3-D cube)", f->path, naxis);
        f->shape.nx = (size_t)naxes[0];
        f->shape.ny = (size_t)naxes[1];
        f->shape.nz = naxis == 3 ? (size_t)naxes[2] : 1;
    }
    if (!f->shape.nx || !f->shape.ny || !f->shape.nz)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: image has an empty axis", f->path);
    /* Catch truncated files when they are opened, not frames later. */
    LONGLONG head = 0, dstart = 0, dend = 0;
    struct stat sb;
    int ast = 0;
    fits_get_hduaddrll(f->fp, &head, &dstart, &dend, &ast);
    if (!ast && stat(f->path, &sb) == 0 && S_ISREG(sb.st_mode)) {
        LONGLONG need = dstart + (LONGLONG)(f->shape.nx * f->shape.ny * f->shape.nz * (is_complex ? 2 : 1)) *
                                     (LONGLONG)(abs(bitpix) / 8);
        if ((LONGLONG)sb.st_size < need)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: the %zux%zux%zu%s image needs %lld bytes but "
                             "the file has %lld", f->path, f->shape.nx, f->shape.ny, f->shape.nz,
                             is_complex ? " complex" : "", (long long)need, (long long)sb.st_size);
    }
    return SWFS_OK;
}

/* A file cut short behind the HDU being read (a halo file missing its last extensions): the
 * last HDU CFITSIO can read must hold all its (padded) data, and no partial extension header may
 * follow it. Only a cut exactly at an HDU boundary goes unnoticed (that is a valid file). */
static int check_complete(fitsfile *fp, const char *path)
{
    struct stat sb;
    if (stat(path, &sb) != 0 || !S_ISREG(sb.st_mode)) return SWFS_OK;
    int st = 0, last = 0;
    for (int i = 1;; i++) {
        int type = 0;
        fits_movabs_hdu(fp, i, &type, &st);
        if (st == END_OF_FILE) { st = 0; fits_clear_errmsg(); break; }
        if (st) return fits_fail(SWFS_ERR_FORMAT, st, path, "file is truncated or corrupt: reading HDU header");
        last = i;
    }
    if (last < 1) return SWFS_OK;
    fits_movabs_hdu(fp, last, NULL, &st);
    LONGLONG head = 0, dstart = 0, dend = 0;
    fits_get_hduaddrll(fp, &head, &dstart, &dend, &st);
    if (st) { fits_clear_errmsg(); return SWFS_OK; } /* CFITSIO reports anything stranger when it is read */
    /* CFITSIO reads whole 2880-byte blocks: the data's padding must be there too. */
    LONGLONG need = dend;
    if ((LONGLONG)sb.st_size < need)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: HDU %d needs %lld bytes but the file has %lld", path, last,
                         (long long)need, (long long)sb.st_size);
    if ((LONGLONG)sb.st_size > dend) {
        char tag[8] = "";
        FILE *fh = fopen(path, "rb");
        if (fh && fseeko(fh, (off_t)dend, SEEK_SET) == 0 && fread(tag, 1, 8, fh) == 8 && !memcmp(tag, "XTENSION", 8)) {
            fclose(fh);
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: extension %d after byte %lld is incomplete (%lld bytes "
                             "of it in the file)", path, last, (long long)dend, (long long)((LONGLONG)sb.st_size - dend));
        }
        if (fh) fclose(fh);
    }
    return SWFS_OK;
}

int swfs_fits_in_open(swfs_fits_in **out, const char *path, const char *extname)
{
    *out = NULL;
    swfs_fits_in *f = calloc(1, sizeof *f);
    if (!f) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    f->path = strdup(path);
    int st = 0, rc;
    fits_open_file(&f->fp, path, READONLY, &st);
    if (st) {
        rc = fits_fail(SWFS_ERR_IO, st, path, "cannot open as FITS");
        f->fp = NULL;
        swfs_fits_in_close(f);
        return rc;
    }
    if ((rc = check_complete(f->fp, path))) { swfs_fits_in_close(f); return rc; }
    if (extname) {
        rc = swfs_fits_in_move(f, extname);
        if (rc) { swfs_fits_in_close(f); return rc; }
    } else {
        int nhdu = 0, found = 0;
        fits_get_num_hdus(f->fp, &nhdu, &st);
        for (int i = 1; i <= nhdu && !st && !found; i++) {
            int type = 0, naxis = 0;
            fits_movabs_hdu(f->fp, i, &type, &st);
            if (!st && type == IMAGE_HDU) {
                fits_get_img_dim(f->fp, &naxis, &st);
                found = !st && naxis > 0;
            }
        }
        if (st) { rc = fits_fail(SWFS_ERR_FORMAT, st, path, "scanning HDUs"); swfs_fits_in_close(f); return rc; }
        if (!found) { swfs_fits_in_close(f); return swfs_fail(SWFS_ERR_FORMAT, "%s: no image data in any HDU", path); }
        if ((rc = load_shape(f))) { swfs_fits_in_close(f); return rc; }
    }
    *out = f;
    return SWFS_OK;
}

void swfs_fits_in_close(swfs_fits_in *f)
{
    if (!f) return;
    int st = 0;
    if (f->fp) fits_close_file(f->fp, &st);
    free(f->path);
    free(f);
}

int swfs_fits_in_has_ext(swfs_fits_in *f, const char *extname)
{
    int st = 0, cur = 0;
    fits_get_hdu_num(f->fp, &cur);
    fits_movnam_hdu(f->fp, IMAGE_HDU, (char *)extname, 0, &st);
    int ok = st == 0;
    st = 0;
    fits_movabs_hdu(f->fp, cur, NULL, &st);
    fits_clear_errmsg();
    return ok;
}

int swfs_fits_in_move(swfs_fits_in *f, const char *extname)
{
    int st = 0;
    fits_movnam_hdu(f->fp, IMAGE_HDU, (char *)extname, 0, &st);
    if (st) {
        fits_clear_errmsg();
        return swfs_fail(SWFS_ERR_FORMAT, "%s: no image extension EXTNAME='%s'", f->path, extname);
    }
    return load_shape(f);
}

const swfs_fits_shape *swfs_fits_in_shape(const swfs_fits_in *f) { return &f->shape; }
const char *swfs_fits_in_path(const swfs_fits_in *f) { return f->path; }

static int read_frames(swfs_fits_in *f, size_t first, size_t n, double *buf, int want_complex)
{
    const swfs_fits_shape *s = &f->shape;
    if (s->is_complex != want_complex)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: expected a %s image (%s), found a %s one", f->path,
                         want_complex ? "complex" : "real",
                         want_complex ? "NAXIS1 = 2, CTYPE1 = 'COMPLEX'" : "NAXIS1 = x",
                         s->is_complex ? "complex" : "real");
    if (first + n > s->nz)
        return swfs_fail(SWFS_ERR_ARG, "%s: frames %zu..%zu requested but the cube has %zu", f->path, first,
                         first + n - 1, s->nz);
    size_t per = s->nx * s->ny * (want_complex ? 2 : 1);
    double nul = NAN;
    int anynul = 0, st = 0;
    fits_read_img(f->fp, TDOUBLE, (LONGLONG)(first * per + 1), (LONGLONG)(n * per), &nul, buf, &anynul, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, f->path, "reading image data");
    return SWFS_OK;
}

int swfs_fits_in_read_real(swfs_fits_in *f, size_t first, size_t n, double *buf)
{
    return read_frames(f, first, n, buf, 0);
}

int swfs_fits_in_read_cplx(swfs_fits_in *f, size_t first, size_t n, double complex *buf)
{
    return read_frames(f, first, n, (double *)buf, 1);
}

int swfs_fits_in_read_real_all(swfs_fits_in *f, swfs_real **out)
{
    *out = NULL;
    if (f->shape.is_complex) return read_frames(f, 0, 0, NULL, 0);
    swfs_real *a = swfs_real_alloc(f->shape.nx, f->shape.ny, f->shape.nz);
    if (!a) return SWFS_ERR_NOMEM;
    int rc = swfs_fits_in_read_real(f, 0, a->nz, a->data);
    if (rc) { swfs_real_free(a); return rc; }
    *out = a;
    return SWFS_OK;
}

int swfs_fits_in_read_cplx_all(swfs_fits_in *f, swfs_cplx **out)
{
    *out = NULL;
    if (!f->shape.is_complex) return read_frames(f, 0, 0, NULL, 1);
    swfs_cplx *a = swfs_cplx_alloc(f->shape.nx, f->shape.ny, f->shape.nz);
    if (!a) return SWFS_ERR_NOMEM;
    int rc = swfs_fits_in_read_cplx(f, 0, a->nz, a->data);
    if (rc) { swfs_cplx_free(a); return rc; }
    *out = a;
    return SWFS_OK;
}

/* Read a keyword from the current HDU, else from the primary header. */
static int read_key(swfs_fits_in *f, int type, const char *key, void *val, int *found)
{
    int st = 0, cur = 0;
    *found = 0;
    fits_read_key(f->fp, type, key, val, NULL, &st);
    if (st == 0) { *found = 1; return SWFS_OK; }
    if (st != KEY_NO_EXIST) {
        char what[120];
        snprintf(what, sizeof what, "reading keyword %s", key);
        return fits_fail(SWFS_ERR_FORMAT, st, f->path, what);
    }
    st = 0;
    fits_clear_errmsg();
    fits_get_hdu_num(f->fp, &cur);
    if (cur == 1) return SWFS_OK;
    fits_movabs_hdu(f->fp, 1, NULL, &st);
    fits_read_key(f->fp, type, key, val, NULL, &st);
    int rst = st;
    st = 0;
    fits_movabs_hdu(f->fp, cur, NULL, &st);
    fits_clear_errmsg();
    if (rst == 0) *found = 1;
    else if (rst != KEY_NO_EXIST) {
        char what[120];
        snprintf(what, sizeof what, "reading keyword %s", key);
        return fits_fail(SWFS_ERR_FORMAT, rst, f->path, what);
    }
    return SWFS_OK;
}

int swfs_fits_in_key_double_opt(swfs_fits_in *f, const char *key, double *val, int *found)
{
    return read_key(f, TDOUBLE, key, val, found);
}

int swfs_fits_in_key_double(swfs_fits_in *f, const char *key, double *val)
{
    int found = 0, rc = read_key(f, TDOUBLE, key, val, &found);
    if (rc) return rc;
    if (!found) return swfs_fail(SWFS_ERR_FORMAT, "%s: missing keyword %s", f->path, key);
    return SWFS_OK;
}

int swfs_fits_in_key_string_opt(swfs_fits_in *f, const char *key, char *val, size_t cap, int *found)
{
    char buf[FLEN_VALUE] = "";
    int rc = read_key(f, TSTRING, key, buf, found);
    if (rc) return rc;
    if (*found) snprintf(val, cap, "%s", buf);
    return SWFS_OK;
}

int swfs_fits_in_geom(swfs_fits_in *f, swfs_geom *g)
{
    swfs_geom_init(g);
    struct { const char *key; double *dst; } keys[] = {
        {"WAVELEN", &g->wavelen}, {"TELDIAM", &g->teldiam}, {"OBSCUR", &g->obscur},
        {"PIXSCALE", &g->pixscale}, {"PUPDX", &g->pupdx},
    };
    int found, rc;
    for (size_t i = 0; i < sizeof keys / sizeof keys[0]; i++) {
        double v;
        if ((rc = read_key(f, TDOUBLE, keys[i].key, &v, &found))) return rc;
        if (found) *keys[i].dst = v;
    }
    long n;
    if ((rc = read_key(f, TLONG, "PUPN", &n, &found))) return rc;
    if (found) g->pupn = n;
    return SWFS_OK;
}

int swfs_fits_read_real(const char *path, const char *extname, swfs_real **out, swfs_geom *g)
{
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, path, extname);
    if (rc) return rc;
    rc = swfs_fits_in_read_real_all(f, out);
    if (!rc && g) rc = swfs_fits_in_geom(f, g);
    swfs_fits_in_close(f);
    return rc;
}

int swfs_fits_read_cplx(const char *path, const char *extname, swfs_cplx **out, swfs_geom *g)
{
    swfs_fits_in *f;
    int rc = swfs_fits_in_open(&f, path, extname);
    if (rc) return rc;
    rc = swfs_fits_in_read_cplx_all(f, out);
    if (!rc && g) rc = swfs_fits_in_geom(f, g);
    swfs_fits_in_close(f);
    return rc;
}

/* ---- writing ---------------------------------------------------------- */

struct swfs_fits_out {
    fitsfile *fp;
    char *path, *part;
    int nhdu;
    int cur_complex;
    size_t cur_nx, cur_ny, cur_nz;
    int have_stamp;
    swfs_geom stamp_geom;
    char **stamp;
    size_t nstamp;
};

int swfs_fits_out_create(swfs_fits_out **out, const char *path)
{
    *out = NULL;
    swfs_fits_out *o = calloc(1, sizeof *o);
    if (!o) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    size_t len = strlen(path);
    o->path = strdup(path);
    o->part = malloc(len + 8);
    char *bang = malloc(len + 9);
    if (!o->path || !o->part || !bang) {
        free(bang);
        swfs_fits_out_abort(o);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    snprintf(o->part, len + 8, "%s.part", path);
    snprintf(bang, len + 9, "!%s", o->part);
    int st = 0;
    fits_create_file(&o->fp, bang, &st);
    free(bang);
    if (st) {
        fits_clear_errmsg();
        o->fp = NULL;
        int rc = swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (is the folder there and writable?)", path);
        swfs_fits_out_abort(o);
        return rc;
    }
    *out = o;
    return SWFS_OK;
}

static void free_out(swfs_fits_out *o)
{
    for (size_t i = 0; i < o->nstamp; i++) free(o->stamp[i]);
    free(o->stamp);
    free(o->path);
    free(o->part);
    free(o);
}

void swfs_fits_out_abort(swfs_fits_out *o)
{
    if (!o) return;
    int st = 0;
    if (o->fp) fits_close_file(o->fp, &st);
    if (o->part) remove(o->part);
    free_out(o);
}

int swfs_fits_out_commit(swfs_fits_out *o)
{
    int st = 0;
    if (o->nhdu == 0) fits_create_img(o->fp, 8, 0, NULL, &st);
    fits_close_file(o->fp, &st);
    o->fp = NULL;
    if (st) {
        int rc = fits_fail(SWFS_ERR_IO, st, o->path, "finishing output file");
        swfs_fits_out_abort(o);
        return rc;
    }
    if (rename(o->part, o->path) != 0) {
        int rc = swfs_fail(SWFS_ERR_IO, "%s: cannot rename %s into place", o->path, o->part);
        swfs_fits_out_abort(o);
        return rc;
    }
    free_out(o);
    return SWFS_OK;
}

static int stamp_current(swfs_fits_out *o)
{
    if (!o->have_stamp) return SWFS_OK;
    int rc = swfs_fits_out_geom(o, &o->stamp_geom);
    if (!rc) rc = swfs_fits_out_provenance(o, (const char *const *)o->stamp, o->nstamp);
    return rc;
}

int swfs_fits_out_set_stamp(swfs_fits_out *o, const swfs_geom *g, const char *const *lines, size_t nlines)
{
    o->have_stamp = 1;
    if (g) o->stamp_geom = *g;
    else swfs_geom_init(&o->stamp_geom);
    o->stamp = calloc(nlines ? nlines : 1, sizeof *o->stamp);
    if (!o->stamp) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    for (size_t i = 0; i < nlines; i++) {
        o->stamp[i] = strdup(lines[i]);
        if (!o->stamp[i]) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        o->nstamp = i + 1;
    }
    return SWFS_OK;
}

int swfs_fits_out_begin(swfs_fits_out *o, const char *extname, size_t nx, size_t ny, size_t nz,
                        int is_complex, int bitpix)
{
    int st = 0;
    if (is_complex && bitpix != -32 && bitpix != -64)
        return swfs_fail(SWFS_ERR_ARG, "%s: complex data need BITPIX -32 or -64, not %d", o->path, bitpix);
    if (extname && o->nhdu == 0) {
        fits_create_img(o->fp, 8, 0, NULL, &st);
        o->nhdu = 1;
        if (!st && o->have_stamp) {
            int rc = stamp_current(o);
            if (rc) return rc;
        }
    }
    long naxes[4];
    int naxis = 0;
    if (is_complex) naxes[naxis++] = 2;
    naxes[naxis++] = (long)nx;
    naxes[naxis++] = (long)ny;
    if (nz > 1) naxes[naxis++] = (long)nz;
    fits_create_img(o->fp, bitpix, naxis, naxes, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "creating image HDU");
    o->nhdu++;
    if (is_complex) fits_write_key(o->fp, TSTRING, "CTYPE1", "COMPLEX", "axis 1 is (real, imaginary)", &st);
    if (extname) fits_write_key(o->fp, TSTRING, "EXTNAME", (char *)extname, NULL, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing header");
    o->cur_complex = is_complex;
    o->cur_nx = nx; o->cur_ny = ny; o->cur_nz = nz;
    return stamp_current(o);
}

static int write_frames(swfs_fits_out *o, size_t first, size_t n, const double *buf, int is_complex)
{
    if (is_complex != o->cur_complex)
        return swfs_fail(SWFS_ERR_ARG, "%s: writing %s frames into a %s HDU", o->path,
                         is_complex ? "complex" : "real", o->cur_complex ? "complex" : "real");
    if (first + n > o->cur_nz)
        return swfs_fail(SWFS_ERR_ARG, "%s: frame %zu beyond cube depth %zu", o->path, first + n, o->cur_nz);
    size_t per = o->cur_nx * o->cur_ny * (is_complex ? 2 : 1);
    int st = 0;
    fits_write_img(o->fp, TDOUBLE, (LONGLONG)(first * per + 1), (LONGLONG)(n * per), (double *)buf, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing image data");
    return SWFS_OK;
}

int swfs_fits_out_real_frames(swfs_fits_out *o, size_t first, size_t n, const double *buf)
{
    return write_frames(o, first, n, buf, 0);
}

int swfs_fits_out_cplx_frames(swfs_fits_out *o, size_t first, size_t n, const double complex *buf)
{
    return write_frames(o, first, n, (const double *)buf, 1);
}

int swfs_fits_out_real(swfs_fits_out *o, const char *extname, const swfs_real *a, int bitpix)
{
    int rc = swfs_fits_out_begin(o, extname, a->nx, a->ny, a->nz, 0, bitpix);
    return rc ? rc : write_frames(o, 0, a->nz, a->data, 0);
}

int swfs_fits_out_cplx(swfs_fits_out *o, const char *extname, const swfs_cplx *a, int bitpix)
{
    int rc = swfs_fits_out_begin(o, extname, a->nx, a->ny, a->nz, 1, bitpix);
    return rc ? rc : write_frames(o, 0, a->nz, (const double *)a->data, 1);
}

static int ensure_hdu(swfs_fits_out *o)
{
    if (o->nhdu) return SWFS_OK;
    int st = 0;
    fits_create_img(o->fp, 8, 0, NULL, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "creating primary HDU");
    o->nhdu = 1;
    return SWFS_OK;
}

int swfs_fits_out_key_double(swfs_fits_out *o, const char *key, double v, const char *comment)
{
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    if (isfinite(v)) fits_update_key(o->fp, TDOUBLE, key, &v, comment, &st);
    else fits_update_key_null(o->fp, key, comment, &st); /* FITS has no NaN header values */
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing keyword");
    return SWFS_OK;
}

int swfs_fits_out_key_long(swfs_fits_out *o, const char *key, long v, const char *comment)
{
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    fits_update_key(o->fp, TLONG, key, &v, comment, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing keyword");
    return SWFS_OK;
}

int swfs_fits_out_key_string(swfs_fits_out *o, const char *key, const char *v, const char *comment)
{
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    fits_update_key_longstr(o->fp, key, v, comment, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing keyword");
    return SWFS_OK;
}

int swfs_fits_out_history(swfs_fits_out *o, const char *text)
{
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    fits_write_history(o->fp, text, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing HISTORY");
    return SWFS_OK;
}

int swfs_fits_out_geom(swfs_fits_out *o, const swfs_geom *g)
{
    int rc = SWFS_OK;
    if (!rc && isfinite(g->wavelen)) rc = swfs_fits_out_key_double(o, "WAVELEN", g->wavelen, "[m] wavelength");
    if (!rc && isfinite(g->teldiam)) rc = swfs_fits_out_key_double(o, "TELDIAM", g->teldiam, "[m] telescope diameter");
    if (!rc && isfinite(g->obscur)) rc = swfs_fits_out_key_double(o, "OBSCUR", g->obscur, "central obstruction / diameter");
    if (!rc && isfinite(g->pixscale)) rc = swfs_fits_out_key_double(o, "PIXSCALE", g->pixscale, "[lambda/D] per focal pixel");
    if (!rc && isfinite(g->pupdx)) rc = swfs_fits_out_key_double(o, "PUPDX", g->pupdx, "[m] per pupil sample");
    if (!rc && g->pupn > 0) rc = swfs_fits_out_key_long(o, "PUPN", g->pupn, "pupil samples across");
    return rc;
}

int swfs_fits_out_provenance(swfs_fits_out *o, const char *const *lines, size_t nlines)
{
    int st = 0, rc = swfs_fits_out_key_string(o, "SWFSVER", SWFS_VERSION, "specklewfs version");
    if (rc) return rc;
    fits_write_date(o->fp, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing DATE");
    for (size_t i = 0; i < nlines && !rc; i++) rc = swfs_fits_out_history(o, lines[i]);
    return rc;
}

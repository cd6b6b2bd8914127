/* CFITSIO wrappers: see include/specklewfs/fits.h for the conventions. */
#include "specklewfs/fits.h"
#include "specklewfs/atomic.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"
#include "specklewfs/version.h"

#include <errno.h>
#include <float.h>
#include <fitsio.h>
#include <fitsio2.h> /* ffgbyt: raw header bytes (check_raw_header) */
#include <limits.h>
#include <zlib.h>
#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

/* CFITSIO stamps DATE and the CHECKSUM card's comment with the time from gmtime(), whose
 * result is one static buffer: files written by several threads at once (teach's loops)
 * take this lock around those calls. */
static pthread_mutex_t cfitsio_clock = PTHREAD_MUTEX_INITIALIZER;

/* Turn a CFITSIO status into our status with a message naming the file and action. */
static int fits_fail(int code, int fstatus, const char *path, const char *action)
{
    const int sys = errno;
    char text[FLEN_STATUS] = "";
    char detail[FLEN_ERRMSG] = "";
    fits_get_errstatus(fstatus, text);
    /* The first message on CFITSIO's stack is usually the most specific. */
    (void)fits_read_errmsg(detail);
    fits_clear_errmsg();
    if (fstatus == END_OF_FILE || fstatus == 107 /* tried to move past end of file */)
        return swfs_fail(code, "%s: %s: file is truncated (%s)", path, action, text);
    /* A write that failed in the system (a full disk, a quota): say why. */
    if ((fstatus == WRITE_ERROR || fstatus == FILE_NOT_CREATED) && sys)
        return swfs_fail(code, "%s: %s: %s (%s)", path, action, text, strerror(sys));
    return swfs_fail(code, "%s: %s: %s%s%s", path, action, text, detail[0] ? " -- " : "", detail);
}

/* ---- reading ---------------------------------------------------------- */

struct swfs_fits_in {
    fitsfile *fp;
    char *path;
    swfs_fits_shape shape;
    long long fsize;           /* bytes of the FITS file (after CFITSIO's decompression of a gzip'd one) */
    unsigned long long checked; /* HDUs 1..64 whose checksums were verified (bit k-1 for HDU k) */
};

/* A gzip'd file's trailer states its uncompressed size (mod 2^32), and CFITSIO allocates
 * that much before decompressing: a corrupt trailer (or a decompression bomb) must not
 * make a 60-kB file allocate gigabytes. Real FITS files compress by far less than 1000:1. */
static int check_gzip_size(const char *path)
{
    unsigned char m[2] = {0}, t[4] = {0};
    FILE *fh = fopen(path, "rb");
    if (!fh) return SWFS_OK;
    int gz = fread(m, 1, 2, fh) == 2 && m[0] == 0x1f && m[1] == 0x8b;
    long long csize = 0;
    if (gz && fseeko(fh, -4, SEEK_END) == 0 && fread(t, 1, 4, fh) == 4) csize = (long long)ftello(fh);
    fclose(fh);
    if (!gz || !csize) return SWFS_OK;
    const long long isize = (long long)t[0] | (long long)t[1] << 8 | (long long)t[2] << 16 | (long long)t[3] << 24;
    /* Fewer bytes than compressed: CFITSIO takes that for a 4-GB wrap and allocates 4 GB more. */
    if (isize + isize / 1000 + 64 < csize) /* deflate expands incompressible data by < 0.1 % */
        return swfs_fail(SWFS_ERR_FORMAT, "%s: gzip'd file of %lld bytes claims only %lld bytes uncompressed: corrupt "
                         "(or over 4 GB uncompressed: gunzip it first)", path, csize, isize);
    if (isize > 1000 * csize + (1LL << 20))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: gzip'd file of %lld bytes claims %lld bytes uncompressed (more than 1000:1): "
                         "corrupt, or gunzip it first", path, csize, isize);
    /* And the stream itself must end where it should (CFITSIO loops on a cut-short one). */
    gzFile gf = gzopen(path, "rb");
    if (!gf) return SWFS_OK;
    static _Thread_local char buf[65536];
    long long total = 0;
    int n;
    while ((n = gzread(gf, buf, sizeof buf)) > 0 && total <= 1000 * csize + (1LL << 20)) total += n;
    int err = 0;
    gzerror(gf, &err);
    gzclose(gf);
    if (n < 0 || err < 0 || total > 1000 * csize + (1LL << 20) || (total & 0xffffffffLL) != isize)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: gzip'd file is corrupt or cut short (%lld bytes inflated, the trailer says "
                         "%lld)", path, total, isize);
    return SWFS_OK;
}

/* A header keyword's raw value string (never converted by CFITSIO: a value of 70 digits
 * must not reach its fixed-size integer conversion). *found = 0 when the HDU lacks it. */
static int raw_key(fitsfile *fp, const char *path, const char *key, char *val, int *found)
{
    char comment[FLEN_COMMENT];
    int st = 0;
    *found = 0;
    val[0] = 0;
    fits_read_keyword(fp, (char *)key, val, comment, &st);
    if (st == KEY_NO_EXIST) {
        fits_clear_errmsg();
        return SWFS_OK;
    }
    if (st) {
        char what[120];
        snprintf(what, sizeof what, "reading keyword %s", key);
        return fits_fail(SWFS_ERR_FORMAT, st, path, what);
    }
    *found = 1;
    return SWFS_OK;
}

/* A FITS number ("1.5", "-3", "1.0D-6") from a raw value string; anything else -- a
 * logical, a string, a complex value, no value, overflow -- is an error naming the key. */
static int parse_number(const char *path, const char *key, const char *raw, double *out)
{
    char buf[FLEN_VALUE];
    size_t n = 0;
    while (*raw == ' ') raw++;
    for (; raw[n] && n + 1 < sizeof buf; n++) buf[n] = raw[n] == 'D' || raw[n] == 'd' ? 'E' : raw[n];
    while (n && buf[n - 1] == ' ') n--;
    buf[n] = 0;
    if (!n) return swfs_fail(SWFS_ERR_FORMAT, "%s: keyword %s has no value, expected a number", path, key);
    if (!strcmp(buf, "T") || !strcmp(buf, "F"))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %s is a logical (true/false), expected a number", path, key, buf);
    if (buf[0] == '\'')
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %.40s is a string, expected a number", path, key, buf);
    if (buf[0] == '(')
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %.40s is a complex value, expected a real number", path, key, buf);
    char *end;
    errno = 0;
    double v = strtod(buf, &end);
    if (end == buf || *end)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %.40s is not a number", path, key, buf);
    if (!isfinite(v) || (errno == ERANGE && fabs(v) > 1))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %.40s is not a finite number", path, key, buf);
    *out = v;
    return SWFS_OK;
}

/* An integer header value: a number with no fraction (its own text checked for the size). */
static int structural(fitsfile *fp, const char *path, const char *key, long long lo, long long hi, long long dflt,
                      long long *out)
{
    char raw[FLEN_VALUE];
    int found = 0, rc = raw_key(fp, path, key, raw, &found);
    double v = (double)dflt;
    if (!rc && found) rc = parse_number(path, key, raw, &v);
    if (rc) return rc;
    if (v != floor(v) || v < (double)lo || v > (double)hi)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: %s = %.17g, expected an integer %lld..%lld", path, key, v, lo, hi);
    *out = (long long)v;
    return SWFS_OK;
}

/* Bytes of the current HDU's data, from its own keywords with overflow checks (CFITSIO's
 * sums of NAXISn wrap silently). *bytes = -1 when they do not fit in 63 bits. */
static int hdu_data_bytes(fitsfile *fp, const char *path, int hdu, long long *bytes)
{
    long long bitpix = 0, naxis = 0, pcount = 0, gcount = 1;
    int rc = structural(fp, path, "BITPIX", -64, 64, 8, &bitpix);
    if (!rc) rc = structural(fp, path, "NAXIS", 0, 999, 0, &naxis);
    if (!rc && hdu > 1) rc = structural(fp, path, "PCOUNT", 0, LLONG_MAX / 2, 0, &pcount);
    if (!rc && hdu > 1) rc = structural(fp, path, "GCOUNT", 0, LLONG_MAX / 2, 1, &gcount);
    if (rc) return rc;
    unsigned long long n = naxis ? 1 : 0, b = 0;
    int ovf = 0;
    for (long long i = 1; i <= naxis && !rc; i++) {
        char key[32];
        long long v = 0;
        snprintf(key, sizeof key, "NAXIS%lld", i);
        rc = structural(fp, path, key, 0, LLONG_MAX, 0, &v);
        if (!rc && !(i == 1 && v == 0 && naxis > 1 && hdu == 1)) /* random groups: NAXIS1 = 0 */
            ovf |= __builtin_mul_overflow(n, (unsigned long long)v, &n);
    }
    if (rc) return rc;
    ovf |= __builtin_add_overflow(n, (unsigned long long)pcount, &n);
    ovf |= __builtin_mul_overflow(n, (unsigned long long)gcount, &n);
    ovf |= __builtin_mul_overflow(n, (unsigned long long)(llabs(bitpix) / 8), &b);
    *bytes = ovf || b > (unsigned long long)LLONG_MAX / 2 ? -1 : (long long)b;
    return SWFS_OK;
}

/* Checksums of HDU k (DATASUM, CHECKSUM: written on every product) when it has them. */
static int verify_hdu(swfs_fits_in *f, int k)
{
    if (k >= 1 && k <= 64 && (f->checked >> (k - 1) & 1)) return SWFS_OK;
    char raw[FLEN_VALUE];
    int have_d = 0, have_c = 0, rc = raw_key(f->fp, f->path, "DATASUM", raw, &have_d);
    if (!rc) rc = raw_key(f->fp, f->path, "CHECKSUM", raw, &have_c);
    if (rc) return rc;
    if (have_d || have_c) {
        int dst = 0, hst = 0, st = 0;
        fits_verify_chksum(f->fp, &dst, &hst, &st);
        if (st) return fits_fail(SWFS_ERR_FORMAT, st, f->path, "verifying checksums");
        char ext[FLEN_VALUE] = "";
        int est = 0;
        fits_read_key(f->fp, TSTRING, "EXTNAME", ext, NULL, &est);
        fits_clear_errmsg();
        if (dst < 0)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d%s%s%s: the data do not match their DATASUM: the file is corrupt "
                             "(changed after it was written); refusing it", f->path, k, ext[0] ? " (" : "", ext,
                             ext[0] ? ")" : "");
        if (hst < 0)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d%s%s%s: the header does not match its CHECKSUM: the file is "
                             "corrupt, or was edited without updating CHECKSUM (delete the CHECKSUM card after a "
                             "deliberate edit); refusing it", f->path, k, ext[0] ? " (" : "", ext, ext[0] ? ")" : "");
    }
    if (k >= 1 && k <= 64) f->checked |= 1ULL << (k - 1);
    return SWFS_OK;
}

/* Inflate GZIP data (gzip or zlib wrapper) without keeping it: SWFS_OK when the stream
 * ends properly within cap bytes. */
static int inflate_capped(const unsigned char *in, size_t n, double cap, double *total)
{
    unsigned char out[65536];
    z_stream z;
    memset(&z, 0, sizeof z);
    if (inflateInit2(&z, 15 + 32) != Z_OK) return -1;
    z.next_in = (unsigned char *)in;
    z.avail_in = (uInt)n;
    int zr;
    *total = 0;
    do {
        z.next_out = out;
        z.avail_out = sizeof out;
        zr = inflate(&z, Z_NO_FLUSH);
        *total += (double)(sizeof out - z.avail_out);
    } while (zr == Z_OK && *total <= cap);
    inflateEnd(&z);
    return zr == Z_STREAM_END && *total <= cap ? 0 : -1;
}

static int check_gzip_tile(swfs_fits_in *f, int col, LONGLONG row, double cap)
{
    LONGLONG len = 0, off = 0;
    int st = 0, anynul = 0;
    fits_read_descriptll(f->fp, col, row, &len, &off, &st);
    if (st || len <= 0) { fits_clear_errmsg(); return SWFS_OK; }
    unsigned char *buf = malloc((size_t)len);
    if (!buf) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory for a compressed tile", f->path);
    fits_read_col(f->fp, TBYTE, col, row, 1, len, NULL, buf, &anynul, &st);
    double total = 0;
    int bad = st ? 0 : inflate_capped(buf, (size_t)len, cap, &total);
    free(buf);
    if (st) return fits_fail(SWFS_ERR_FORMAT, st, f->path, "reading a compressed tile");
    if (bad)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image: the GZIP data of tile %lld are %s (file corrupt)", f->path,
                         (long long)row, total > cap ? "larger than the tile" : "corrupt or cut short");
    return SWFS_OK;
}

/* An Hcompress tile's stream states its own dimensions, and CFITSIO decodes that many
 * pixels into the tile's buffer: they must be the tile's. */
static int check_hcompress_tile(swfs_fits_in *f, int col, LONGLONG row, long long npix)
{
    LONGLONG len = 0, off = 0;
    int st = 0, anynul = 0;
    unsigned char h[14];
    fits_read_descriptll(f->fp, col, row, &len, &off, &st);
    if (!st && len >= 14) fits_read_col(f->fp, TBYTE, col, row, 1, 14, NULL, h, &anynul, &st);
    fits_clear_errmsg();
    if (st || len < 14 || h[0] != 0xDD || h[1] != 0x99)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image: the Hcompress data of tile %lld are corrupt", f->path,
                         (long long)row);
    const long long nx = (long long)h[2] << 24 | h[3] << 16 | h[4] << 8 | h[5],
                    ny = (long long)h[6] << 24 | h[7] << 16 | h[8] << 8 | h[9];
    if (nx <= 0 || ny <= 0 || nx * ny != npix)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image: Hcompress tile %lld claims %lld x %lld pixels but the "
                         "tile has %lld (file corrupt)", f->path, (long long)row, nx, ny, npix);
    return SWFS_OK;
}

/* A tile-compressed image (fpack): tiles no larger than the image and one table row per
 * tile, so that CFITSIO never allocates a tile buffer larger than the image itself. */
static int check_tiles(swfs_fits_in *f)
{
    long long zn = 0, rows = 0, axes[6] = {0}, tiles[6] = {0};
    int rc = structural(f->fp, f->path, "ZNAXIS", 1, 6, 0, &zn); /* CFITSIO compresses up to 6 axes */
    if (!rc) rc = structural(f->fp, f->path, "NAXIS2", 0, LLONG_MAX, 0, &rows);
    double ntiles = 1, tilepix = 1;
    for (long long i = 1; i <= zn && !rc; i++) {
        char key[32], tkey[32];
        long long ax = 0, tile = 0;
        snprintf(key, sizeof key, "ZNAXIS%lld", i);
        snprintf(tkey, sizeof tkey, "ZTILE%lld", i);
        rc = structural(f->fp, f->path, key, 1, LLONG_MAX, 1, &ax);
        if (!rc) rc = structural(f->fp, f->path, tkey, 1, LLONG_MAX, i == 1 ? ax : 1, &tile);
        if (!rc && tile > ax)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image: %s = %lld is larger than %s = %lld", f->path, tkey,
                             tile, key, ax);
        ntiles *= ceil((double)ax / (double)tile);
        tilepix *= (double)tile;
        axes[i - 1] = ax;
        tiles[i - 1] = tile;
    }
    if (!rc && ntiles != (double)rows)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image of %.0f tiles has %lld table rows (one per tile)", f->path,
                         ntiles, rows);
    /* Each tile's compressed bytes (variable-length array descriptors) must lie inside the
     * heap: CFITSIO allocates what a descriptor claims before reading it. */
    long long heap = 0;
    int ncol = 0, st = 0;
    if (!rc) rc = structural(f->fp, f->path, "PCOUNT", 0, LLONG_MAX, 0, &heap);
    if (!rc) fits_get_num_cols(f->fp, &ncol, &st);
    for (int c = 1; c <= ncol && !rc && !st; c++) {
        int type = 0;
        LONGLONG rep = 0, width = 0;
        fits_get_coltypell(f->fp, c, &type, &rep, &width, &st);
        if (st || type >= 0) continue; /* fixed-size column */
        for (LONGLONG row = 1; row <= rows && !st; row++) {
            LONGLONG len = 0, off = 0;
            fits_read_descriptll(f->fp, c, row, &len, &off, &st);
            if (!st && (len < 0 || off < 0 || off > heap || (width > 0 && len > (heap - off) / width)))
                rc = swfs_fail(SWFS_ERR_FORMAT, "%s: compressed image: tile %lld claims %lld elements at heap offset %lld, "
                               "outside the %lld-byte heap (file corrupt)", f->path, (long long)row, (long long)len,
                               (long long)off, heap);
        }
    }
    if (!rc && st) rc = fits_fail(SWFS_ERR_FORMAT, st, f->path, "reading the compressed image's tile table");
    /* GZIP tiles are inflated once here with a cap of the tile's size: CFITSIO grows its
     * buffer without bound on a corrupt or cut-short stream (minutes of reallocation). */
    char cmptype[FLEN_VALUE] = "";
    st = 0;
    fits_read_key(f->fp, TSTRING, "ZCMPTYPE", cmptype, NULL, &st);
    st = 0;
    fits_clear_errmsg();
    for (int c = 1; c <= ncol && !rc; c++) {
        char tkey[32], name[FLEN_VALUE] = "";
        snprintf(tkey, sizeof tkey, "TTYPE%d", c);
        fits_read_key(f->fp, TSTRING, tkey, name, NULL, &st);
        st = 0;
        fits_clear_errmsg();
        const int hcomp = !strcmp(name, "COMPRESSED_DATA") && !strncmp(cmptype, "HCOMPRESS", 9);
        if (hcomp) {
            for (LONGLONG row = 1; row <= rows && !rc; row++) {
                /* The pixels of this tile (edge tiles are smaller), first axis fastest. */
                long long t = (long long)row - 1, npix = 1;
                for (long long i = 0; i < zn; i++) {
                    const long long nt = (axes[i] + tiles[i] - 1) / tiles[i], ti = t % nt;
                    t /= nt;
                    npix *= axes[i] - ti * tiles[i] < tiles[i] ? axes[i] - ti * tiles[i] : tiles[i];
                }
                rc = check_hcompress_tile(f, c, row, npix);
            }
            continue;
        }
        if (strcmp(name, "GZIP_COMPRESSED_DATA") && (strcmp(name, "COMPRESSED_DATA") || strncmp(cmptype, "GZIP", 4)))
            continue;
        for (LONGLONG row = 1; row <= rows && !rc; row++)
            rc = check_gzip_tile(f, c, row, 8 * tilepix + 1024);
    }
    return rc;
}

static int load_shape(swfs_fits_in *f)
{
    int st = 0, bitpix = 0, naxis = 0, hdu = 0;
    long naxes[4] = {1, 1, 1, 1};
    fits_get_hdu_num(f->fp, &hdu);
    int rc = verify_hdu(f, hdu);
    if (rc) return rc;
    const int cmp = fits_is_compressed_image(f->fp, &st) && !st;
    st = 0;
    if (cmp && (rc = check_tiles(f))) return rc;
    fits_get_img_param(f->fp, 4, &bitpix, &naxis, naxes, &st);
    if (st) return fits_fail(SWFS_ERR_FORMAT, st, f->path, "reading image size");
    char ctype1[FLEN_VALUE] = "";
    int cst = 0;
    fits_read_key(f->fp, TSTRING, "CTYPE1", ctype1, NULL, &cst);
    fits_clear_errmsg();
    int is_complex = naxis >= 3 && naxes[0] == 2 && cst == 0 && strcmp(ctype1, "COMPLEX") == 0;
    memset(&f->shape, 0, sizeof f->shape);
    f->shape.bitpix = bitpix;
    f->shape.is_complex = is_complex;
    if (is_complex) {
        if (naxis > 4) return swfs_fail(SWFS_ERR_FORMAT, "%s: complex image has %d axes (at most 4)", f->path, naxis);
        if (bitpix != -32 && bitpix != -64)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: complex image has BITPIX = %d; complex data are stored as floating "
                             "point (BITPIX -32 or -64)", f->path, bitpix);
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
    /* Values in memory (doubles) must be countable without overflow. */
    size_t nval = 0;
    if (__builtin_mul_overflow(f->shape.nx, f->shape.ny, &nval) || __builtin_mul_overflow(nval, f->shape.nz, &nval) ||
        __builtin_mul_overflow(nval, (size_t)(is_complex ? 16 : 8), &nval))
        return swfs_fail(SWFS_ERR_FORMAT, "%s: image %zux%zux%zu%s is too large to address", f->path, f->shape.nx,
                         f->shape.ny, f->shape.nz, is_complex ? " complex" : "");
    /* Catch truncated files when they are opened, not frames later (plain files only:
     * tile-compressed images hold fewer bytes than their pixels, and check_complete has
     * checked that their tables are whole). */
    st = 0;
    if (!cmp) {
        LONGLONG head = 0, dstart = 0, dend = 0;
        fits_get_hduaddrll(f->fp, &head, &dstart, &dend, &st);
        long long need = 0;
        if (!st && !__builtin_mul_overflow((long long)(nval / 8), (long long)(abs(bitpix) / 8), &need) &&
            !__builtin_add_overflow(need, (long long)dstart, &need) && f->fsize < need)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: the %zux%zux%zu%s image needs %lld bytes but "
                             "the file has %lld", f->path, f->shape.nx, f->shape.ny, f->shape.nz,
                             is_complex ? " complex" : "", need, f->fsize);
    }
    fits_clear_errmsg();
    return SWFS_OK;
}

/* ---- raw header checks --------------------------------------------------
 * CFITSIO parses an extension's structural keywords as soon as it moves onto the HDU, and
 * some malformed values crash it there (a division by ZTILEn = 0 in the tile-compression
 * set-up, a strcpy overflow on a 70-character unquoted TTYPEn). So each extension header
 * is read as raw bytes and checked before CFITSIO is allowed to move to it. */

enum { KEY_STRING = 1, KEY_INT = 2 };

/* What a structural keyword must be: a quoted string, an integer (>= lo), or 0 (not one). */
static int key_kind(const char *key, long long *lo)
{
    static const char *const strs[] = {"XTENSION", "EXTNAME", "ZCMPTYPE", "ZQUANTIZ", "ZTENSION", "ZIMAGE"};
    static const char *const strp[] = {"TTYPE", "TFORM", "TUNIT", "TDIM", "TDISP", "ZNAME", "CTYPE"};
    static const struct { const char *key; long long lo; } ints[] = {
        {"BITPIX", -64}, {"NAXIS", 0}, {"PCOUNT", 0}, {"GCOUNT", 0}, {"TFIELDS", 0}, {"THEAP", 0}, {"ZBITPIX", -64},
        {"ZNAXIS", 0}, {"ZPCOUNT", 0}, {"ZGCOUNT", 0}};
    static const struct { const char *prefix; long long lo; } intp[] = {
        {"NAXIS", 0}, {"ZNAXIS", 0}, {"ZTILE", 1}, {"TBCOL", 1}};
    for (size_t i = 0; i < sizeof strs / sizeof strs[0]; i++)
        if (!strcmp(key, strs[i])) return strcmp(key, "ZIMAGE") ? KEY_STRING : 0;
    for (size_t i = 0; i < sizeof ints / sizeof ints[0]; i++)
        if (!strcmp(key, ints[i].key)) { *lo = ints[i].lo; return KEY_INT; }
    for (size_t i = 0; i < sizeof strp / sizeof strp[0]; i++) {
        size_t n = strlen(strp[i]);
        if (!strncmp(key, strp[i], n) && key[n] >= '1' && key[n] <= '9') return KEY_STRING;
    }
    for (size_t i = 0; i < sizeof intp / sizeof intp[0]; i++) {
        size_t n = strlen(intp[i].prefix);
        if (!strncmp(key, intp[i].prefix, n) && key[n] >= '1' && key[n] <= '9') { *lo = intp[i].lo; return KEY_INT; }
    }
    return 0;
}

/* One header (starting at byte pos of the file as CFITSIO sees it, uncompressed) checked
 * card by card up to END. */
static int check_raw_header(swfs_fits_in *f, long long pos, int hdu)
{
    enum { MAXKEYS = 512, MAXZ = 10 };
    char keys[MAXKEYS][9], zname[MAXZ][72] = {{0}};
    double zval[MAXZ];
    size_t nkeys = 0;
    for (int k = 0; k < MAXZ; k++) zval[k] = NAN;
    char blk[2880];
    for (long long b = 0; b < 10000; b++) {
        int st = 0;
        ffmbyt(f->fp, pos + 2880 * b, REPORT_EOF, &st);
        ffgbyt(f->fp, 2880, blk, &st);
        if (st) {
            fits_clear_errmsg();
            return b ? swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: the header of HDU %d has no END card", f->path,
                                 hdu)
                     : SWFS_OK; /* no further HDU: CFITSIO reports the end of the file */
        }
        for (int c = 0; c < 36; c++) {
            const char *card = blk + 80 * c;
            char key[9], val[73];
            memcpy(key, card, 8);
            key[8] = 0;
            for (int k = 7; k >= 0 && key[k] == ' '; k--) key[k] = 0;
            if (!strcmp(key, "END")) {
                /* Rice BLOCKSIZE and BYTEPIX divide and size buffers inside CFITSIO. */
                for (int k = 0; k < MAXZ; k++)
                    if ((!strcmp(zname[k], "BLOCKSIZE") && !(zval[k] >= 1 && zval[k] <= 1e6)) ||
                        (!strcmp(zname[k], "BYTEPIX") && zval[k] != 1 && zval[k] != 2 && zval[k] != 4 && zval[k] != 8))
                        return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: compression parameter %s = %g is invalid (file "
                                         "corrupt)", f->path, hdu, zname[k], zval[k]);
                return SWFS_OK;
            }
            if (card[8] != '=' || card[9] != ' ') continue; /* commentary card */
            long long lo = 0;
            const int kind = key_kind(key, &lo);
            /* The value: a quoted string (with '' inside), or the text before a comment. */
            const char *v = card + 10;
            int n = 70;
            while (n && *v == ' ') { v++; n--; }
            int quoted = n && *v == '\'', closed = 0, len = 0;
            if (quoted) {
                for (int k = 1; k < n; k++)
                    if (v[k] == '\'') {
                        if (k + 1 < n && v[k + 1] == '\'') { k++; continue; }
                        closed = 1;
                        break;
                    }
            } else {
                while (len < n && v[len] != '/') len++;
                while (len && v[len - 1] == ' ') len--;
                memcpy(val, v, (size_t)len);
                val[len] = 0;
            }
            if (quoted && !closed)
                return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: keyword %s has an unterminated string value (file corrupt)",
                                 f->path, hdu, key);
            if (!quoted && len > 40 && strspn(val, "0123456789+-.EeDd") != (size_t)len)
                return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: keyword %s has a %d-character value that is neither a "
                                 "string nor a number (file corrupt)", f->path, hdu, key, len);
            if (!strncmp(key, "ZNAME", 5) && key[5] >= '1' && key[5] <= '9' && !key[6] && quoted) {
                int k = key[5] - '1', m = 0;
                for (const char *q = v + 1; *q != '\'' && *q != ' ' && m < 71; q++) zname[k][m++] = *q;
                zname[k][m] = 0;
            }
            if (!strncmp(key, "ZVAL", 4) && key[4] >= '1' && key[4] <= '9' && !key[5]) {
                char *end;
                zval[key[4] - '1'] = quoted ? NAN : strtod(val, &end);
                if (!quoted && (end == val || *end)) zval[key[4] - '1'] = NAN;
            }
            if (!kind) continue;
            for (size_t k = 0; k < nkeys; k++)
                if (!strcmp(keys[k], key))
                    return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: structural keyword %s appears twice (file corrupt)",
                                     f->path, hdu, key);
            if (nkeys < MAXKEYS) snprintf(keys[nkeys++], sizeof keys[0], "%s", key);
            if (kind == KEY_STRING && !quoted)
                return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: %s = %s, expected a quoted string (file corrupt)", f->path,
                                 hdu, key, val);
            if (kind == KEY_INT) {
                char *end;
                errno = 0;
                long long x = quoted ? 0 : strtoll(val, &end, 10);
                if (quoted || !len || *end || errno || x < lo)
                    return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: %s = %.40s, expected an integer >= %lld (file corrupt)",
                                     f->path, hdu, key, quoted ? "(a string)" : val, lo);
            }
        }
    }
    return swfs_fail(SWFS_ERR_FORMAT, "%s: HDU %d: no END card in 10000 header blocks (file corrupt)", f->path, hdu);
}

/* The whole file walked header by header before anything is read: every HDU's data (as
 * its own NAXISn say, summed with overflow checks) must lie inside the file, headers must
 * follow each other forward, and no partial extension may follow the last one. Only a
 * cut exactly at an HDU boundary goes unnoticed (that is a valid file). */
static int check_complete(swfs_fits_in *f)
{
    const char *path = f->path;
    const long long size = f->fsize;
    int st = 0, last = 0;
    long long prev_head = -1, dend_last = 0;
    for (int i = 1;; i++) {
        int type = 0;
        if ((long long)(i - 1) * 2880 >= size) break; /* every HDU takes at least one block */
        if (i > 1 && dend_last < size) {
            int rc = check_raw_header(f, dend_last, i);
            if (rc) return rc;
        }
        fits_movabs_hdu(f->fp, i, &type, &st);
        if (st == END_OF_FILE) { st = 0; fits_clear_errmsg(); break; }
        if (st) return fits_fail(SWFS_ERR_FORMAT, st, path, "file is truncated or corrupt: reading HDU header");
        LONGLONG head = 0, dstart = 0, dend = 0;
        fits_get_hduaddrll(f->fp, &head, &dstart, &dend, &st);
        if (st) return fits_fail(SWFS_ERR_FORMAT, st, path, "file is corrupt: locating HDU");
        long long bytes = 0;
        int rc = hdu_data_bytes(f->fp, path, i, &bytes);
        if (rc) return swfs_fail_context(rc, "HDU %d", i);
        if ((long long)head <= prev_head || dstart < head)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is corrupt: HDU %d's header does not follow HDU %d's data", path,
                             i, i - 1);
        if (bytes < 0 || bytes > size - (long long)dstart)
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated or corrupt: HDU %d's keywords (NAXISn, BITPIX, "
                             "PCOUNT, GCOUNT) describe %s bytes of data but the file has %lld bytes after its header",
                             path, i, bytes < 0 ? "more than 2^62" : "more", size - (long long)dstart);
        prev_head = (long long)head;
        dend_last = (long long)dend;
        last = i;
    }
    if (last < 1) return swfs_fail(SWFS_ERR_FORMAT, "%s: no FITS header in the file", path);
    /* CFITSIO reads whole 2880-byte blocks: the last data's padding must be there too. */
    if (size < dend_last)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: HDU %d needs %lld bytes but the file has %lld", path, last,
                         dend_last, size);
    if (size > dend_last) {
        char tag[8] = "";
        int tst = 0;
        ffmbyt(f->fp, dend_last, REPORT_EOF, &tst);
        if (!tst && size - dend_last >= 8) ffgbyt(f->fp, 8, tag, &tst);
        fits_clear_errmsg();
        if (!tst && !memcmp(tag, "XTENSION", 8))
            return swfs_fail(SWFS_ERR_FORMAT, "%s: file is truncated: extension %d after byte %lld is incomplete (%lld bytes "
                             "of it in the file)", path, last + 1, dend_last, size - dend_last);
    }
    return SWFS_OK;
}

int swfs_fits_in_open(swfs_fits_in **out, const char *path, const char *extname)
{
    *out = NULL;
    int rc = swfs_input_check(path, "FITS");
    if (rc) return rc;
    swfs_fits_in *f = calloc(1, sizeof *f);
    if (!f || !(f->path = strdup(path))) {
        free(f);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    if ((rc = check_gzip_size(path))) {
        swfs_fits_in_close(f);
        return rc;
    }
    int st = 0;
    /* The name is taken literally: no extended file-name syntax ("x.fits[1]"). */
    fits_open_diskfile(&f->fp, path, READONLY, &st);
    if (st) {
        rc = fits_fail(SWFS_ERR_IO, st, path, "cannot open as FITS");
        f->fp = NULL;
        swfs_fits_in_close(f);
        return rc;
    }
    /* Sizes as CFITSIO sees the file: a gzip'd file is checked after its decompression. */
    f->fsize = (long long)f->fp->Fptr->logfilesize;
    if ((rc = check_complete(f))) { swfs_fits_in_close(f); return rc; }
    fits_movabs_hdu(f->fp, 1, NULL, &st);
    if (!st && (rc = verify_hdu(f, 1))) { swfs_fits_in_close(f); return rc; }
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
    fits_clear_errmsg();
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

int swfs_fits_in_require_float(swfs_fits_in *f, const char *what)
{
    if (f->shape.bitpix == -32 || f->shape.bitpix == -64) return SWFS_OK;
    char ext[FLEN_VALUE] = "";
    int st = 0;
    fits_read_key(f->fp, TSTRING, "EXTNAME", ext, NULL, &st);
    fits_clear_errmsg();
    return swfs_fail(SWFS_ERR_FORMAT, "%s: %s%s has BITPIX = %d, but %s stores floating-point data (BITPIX -32 or -64)",
                     f->path, ext[0] ? "extension " : "the image", ext, f->shape.bitpix, what);
}

static int read_frames(swfs_fits_in *f, size_t first, size_t n, double *buf, int want_complex)
{
    const swfs_fits_shape *s = &f->shape;
    if (s->is_complex != want_complex)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: expected a %s image (%s), found a %s one", f->path,
                         want_complex ? "complex" : "real",
                         want_complex ? "NAXIS1 = 2, CTYPE1 = 'COMPLEX'" : "NAXIS1 = x",
                         s->is_complex ? "complex" : "real");
    if (first > s->nz || n > s->nz - first)
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

int swfs_fits_in_read_rows(swfs_fits_in *f, size_t first, size_t n, double *buf)
{
    const swfs_fits_shape *s = &f->shape;
    if (s->is_complex || s->nz != 1)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: rows of a real 2-D image requested from a %s %zux%zux%zu image", f->path,
                         s->is_complex ? "complex" : "real", s->nx, s->ny, s->nz);
    if (first > s->ny || n > s->ny - first)
        return swfs_fail(SWFS_ERR_ARG, "%s: rows %zu..%zu requested but the image has %zu", f->path, first, first + n - 1,
                         s->ny);
    double nul = NAN;
    int anynul = 0, st = 0;
    fits_read_img(f->fp, TDOUBLE, (LONGLONG)(first * s->nx + 1), (LONGLONG)(n * s->nx), &nul, buf, &anynul, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, f->path, "reading image rows");
    return SWFS_OK;
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
    if (!a) return swfs_fail_context(SWFS_ERR_NOMEM, "%s: the %zux%zux%zu image", f->path, f->shape.nx, f->shape.ny,
                                     f->shape.nz);
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
    if (!a) return swfs_fail_context(SWFS_ERR_NOMEM, "%s: the %zux%zux%zu complex image", f->path, f->shape.nx,
                                     f->shape.ny, f->shape.nz);
    int rc = swfs_fits_in_read_cplx(f, 0, a->nz, a->data);
    if (rc) { swfs_cplx_free(a); return rc; }
    *out = a;
    return SWFS_OK;
}

/* A keyword's raw value from the current HDU, else from the primary header. */
static int find_key(swfs_fits_in *f, const char *key, char *raw, int *found)
{
    int st = 0, cur = 0;
    int rc = raw_key(f->fp, f->path, key, raw, found);
    if (rc || *found) return rc;
    fits_get_hdu_num(f->fp, &cur);
    if (cur == 1) return SWFS_OK;
    fits_movabs_hdu(f->fp, 1, NULL, &st);
    rc = st ? fits_fail(SWFS_ERR_FORMAT, st, f->path, "reading the primary header") : raw_key(f->fp, f->path, key, raw, found);
    st = 0;
    fits_movabs_hdu(f->fp, cur, NULL, &st);
    fits_clear_errmsg();
    return rc;
}


/* Half a unit in the last digit a number's text shows: "0.0082" 5e-5, "8.189E-3" 5e-7, "12" 0.5,
 * "1.0D-6" 5e-8 (the text parse_number accepted). */
static double written_resolution(const char *raw)
{
    while (*raw == ' ') raw++;
    int decimals = 0, seen_point = 0;
    const char *c = raw;
    for (; *c && *c != 'E' && *c != 'e' && *c != 'D' && *c != 'd' && *c != ' '; c++) {
        if (*c == '.') seen_point = 1;
        else if (seen_point && *c >= '0' && *c <= '9') decimals++;
    }
    const long ex = (*c == 'E' || *c == 'e' || *c == 'D' || *c == 'd') ? strtol(c + 1, NULL, 10) : 0;
    return 0.5 * pow(10.0, (double)(ex - decimals));
}

int swfs_fits_in_key_double_res_opt(swfs_fits_in *f, const char *key, double *val, double *res, int *found)
{
    char raw[FLEN_VALUE];
    int rc = find_key(f, key, raw, found);
    if (!rc && *found) rc = parse_number(f->path, key, raw, val);
    *res = !rc && *found ? written_resolution(raw) : 0.0;
    return rc;
}

int swfs_fits_in_key_double_opt(swfs_fits_in *f, const char *key, double *val, int *found)
{
    double res;
    return swfs_fits_in_key_double_res_opt(f, key, val, &res, found);
}

int swfs_fits_in_key_double(swfs_fits_in *f, const char *key, double *val)
{
    int found = 0, rc = swfs_fits_in_key_double_opt(f, key, val, &found);
    if (rc) return rc;
    if (!found) return swfs_fail(SWFS_ERR_FORMAT, "%s: missing keyword %s", f->path, key);
    return SWFS_OK;
}

int swfs_fits_in_key_long_opt(swfs_fits_in *f, const char *key, long lo, long hi, long *val, int *found)
{
    double v = 0;
    int rc = swfs_fits_in_key_double_opt(f, key, &v, found);
    if (rc || !*found) return rc;
    if (v != floor(v) || v < (double)lo || v > (double)hi)
        return swfs_fail(SWFS_ERR_VALUE, "%s: %s = %.17g, expected an integer %ld..%ld", f->path, key, v, lo, hi);
    *val = (long)v;
    return SWFS_OK;
}

int swfs_fits_in_key_string_opt(swfs_fits_in *f, const char *key, char *val, size_t cap, int *found)
{
    char raw[FLEN_VALUE], buf[FLEN_VALUE] = "";
    int rc = find_key(f, key, raw, found);
    if (rc || !*found) return rc;
    /* A quoted FITS string: '' is a quote, trailing blanks are not significant. */
    const char *s = raw;
    while (*s == ' ') s++;
    if (*s != '\'') {
        snprintf(buf, sizeof buf, "%s", s);
    } else {
        size_t n = 0;
        for (s++; *s && n + 1 < sizeof buf; s++) {
            if (*s == '\'') {
                if (s[1] != '\'') break;
                s++;
            }
            buf[n++] = *s;
        }
        while (n && buf[n - 1] == ' ') n--;
        buf[n] = 0;
    }
    snprintf(val, cap, "%s", buf);
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
        if ((rc = swfs_fits_in_key_double_opt(f, keys[i].key, &v, &found))) return rc;
        if (found) *keys[i].dst = v;
    }
    double n = 0;
    if ((rc = swfs_fits_in_key_double_opt(f, "PUPN", &n, &found))) return rc;
    if (found) {
        if (n != floor(n) || !(n >= 1 && n <= 2147483647.0))
            return swfs_fail(SWFS_ERR_VALUE, "%s: PUPN = %.17g, expected a whole number 2 .. 8192 of pupil samples across", f->path, n);
        g->pupn = (long)n;
    }
    return swfs_geom_check(g, f->path);
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
    char *path;
    swfs_atomic *part;
    int nhdu;
    int cur_complex;
    int cur_bitpix;   /* the current HDU's BITPIX */
    char cur_ext[72]; /* its EXTNAME ("" for the primary) */
    size_t cur_nx, cur_ny, cur_nz;
    int have_stamp;
    swfs_geom stamp_geom;
    char **stamp;
    size_t nstamp;
};

static void free_out(swfs_fits_out *o)
{
    for (size_t i = 0; i < o->nstamp; i++) free(o->stamp[i]);
    free(o->stamp);
    free(o->path);
    free(o);
}

int swfs_fits_out_create(swfs_fits_out **out, const char *path)
{
    *out = NULL;
    /* The output checks of outpaths.h for this one file (the commands check all their
     * files together before any work; this catches writers called on their own). */
    swfs_paths *chk = NULL;
    int rc = swfs_paths_create(&chk);
    if (!rc) rc = swfs_paths_output(chk, "output", path);
    swfs_paths_free(chk);
    if (rc) return rc;
    swfs_fits_out *o = calloc(1, sizeof *o);
    if (!o || !(o->path = strdup(path))) {
        free(o);
        return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    }
    if ((rc = swfs_atomic_begin(&o->part, path, 0))) {
        free_out(o);
        return rc;
    }
    /* fits_create_diskfile takes the name literally: "o[1].fits" is a file of that name,
     * not an extension request, and the part is created only if it does not exist. */
    int st = 0;
    fits_create_diskfile(&o->fp, (char *)swfs_atomic_part(o->part), &st);
    if (st) {
        int e = errno;
        fits_clear_errmsg();
        o->fp = NULL;
        char dir[4096];
        const char *sl = strrchr(path, '/');
        if (!sl) snprintf(dir, sizeof dir, ".");
        else snprintf(dir, sizeof dir, "%.*s", sl == path ? 1 : (int)(sl - path), path);
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot create output file (folder %s: %s)", path, dir,
                       e ? strerror(e) : "CFITSIO could not create the file");
        swfs_fits_out_abort(o);
        return rc;
    }
    *out = o;
    return SWFS_OK;
}

int swfs_fits_out_copy(swfs_fits_out **out, const char *from, const char *path)
{
    swfs_fits_in *in = NULL;
    int rc = swfs_fits_in_open(&in, from, NULL); /* checks it and its checksums */
    swfs_fits_out *o = NULL;
    if (!rc) rc = swfs_fits_out_create(&o, path);
    int st = 0, nhdu = 0;
    if (!rc) {
        fits_copy_file(in->fp, o->fp, 1, 1, 1, &st);
        fits_get_num_hdus(o->fp, &nhdu, &st);
        fits_movabs_hdu(o->fp, 1, NULL, &st);
        if (st) rc = fits_fail(SWFS_ERR_IO, st, path, "copying the HDUs of another file");
    }
    swfs_fits_in_close(in);
    if (rc) { swfs_fits_out_abort(o); return rc; }
    o->nhdu = nhdu;
    *out = o;
    return SWFS_OK;
}

void swfs_fits_out_abort(swfs_fits_out *o)
{
    if (!o) return;
    int st = 0;
    if (o->fp) fits_close_file(o->fp, &st);
    fits_clear_errmsg();
    swfs_atomic_abort(o->part);
    free_out(o);
}

int swfs_fits_out_commit(swfs_fits_out *o)
{
    int st = 0;
    if (o->nhdu == 0) fits_create_img(o->fp, 8, 0, NULL, &st);
    /* DATASUM and CHECKSUM on every HDU, last, when the headers are complete: readers
     * refuse an HDU whose data or header changed since. */
    int nhdu = 0;
    fits_get_num_hdus(o->fp, &nhdu, &st);
    pthread_mutex_lock(&cfitsio_clock);
    for (int k = 1; k <= nhdu && !st; k++) {
        fits_movabs_hdu(o->fp, k, NULL, &st);
        fits_write_chksum(o->fp, &st);
    }
    pthread_mutex_unlock(&cfitsio_clock);
    if (st) {
        int rc = fits_fail(SWFS_ERR_IO, st, o->path, "finishing output file");
        swfs_fits_out_abort(o);
        return rc;
    }
    fits_close_file(o->fp, &st);
    o->fp = NULL;
    if (st) {
        int rc = fits_fail(SWFS_ERR_IO, st, o->path, "finishing output file (is the disk full?)");
        swfs_fits_out_abort(o);
        return rc;
    }
    int rc = swfs_atomic_commit(o->part);
    o->part = NULL;
    free_out(o);
    return rc;
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
    o->cur_bitpix = bitpix;
    snprintf(o->cur_ext, sizeof o->cur_ext, "%s", extname ? extname : "");
    o->cur_nx = nx; o->cur_ny = ny; o->cur_nz = nz;
    return stamp_current(o);
}

/* The smallest double that rounds to infinity as a float: FLT_MAX + half its last unit. */
#define FLT_OVERFLOWS 0x1.ffffffp+127

static int write_frames(swfs_fits_out *o, size_t first, size_t n, const double *buf, int is_complex)
{
    if (is_complex != o->cur_complex)
        return swfs_fail(SWFS_ERR_ARG, "%s: writing %s frames into a %s HDU", o->path,
                         is_complex ? "complex" : "real", o->cur_complex ? "complex" : "real");
    if (first + n > o->cur_nz)
        return swfs_fail(SWFS_ERR_ARG, "%s: frame %zu beyond cube depth %zu", o->path, first + n, o->cur_nz);
    size_t per = o->cur_nx * o->cur_ny * (is_complex ? 2 : 1);
    /* Single precision: a finite value that rounds to infinity (beyond FLT_MAX by half its
     * last unit or more) would be stored as infinite, read back as NaN, in silence; refused
     * before any of these frames is written. NaN and infinite values are written as they are
     * (a product's "no value" and "beyond the range" marks). */
    if (o->cur_bitpix == -32)
        for (size_t i = 0; i < n * per; i++)
            if (isfinite(buf[i]) && fabs(buf[i]) >= FLT_OVERFLOWS) {
                const size_t q = first * per + i, v = is_complex ? q / 2 : q, np = o->cur_nx * o->cur_ny;
                return swfs_fail(SWFS_ERR_VALUE, "%s: %s%s: %svalue %zu (x %zu, y %zu, frame %zu) is %.9g, beyond "
                                 "single precision's largest %.9g (BITPIX -32 would store it as infinite, read back as "
                                 "NaN); BITPIX -64 holds it", o->path, o->cur_ext[0] ? "extension " : "the image",
                                 o->cur_ext, !is_complex ? "" : q % 2 ? "the imaginary part of " : "the real part of ",
                                 v, v % o->cur_nx, v / o->cur_nx % o->cur_ny, v / np, buf[i], (double)FLT_MAX);
            }
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

/* A keyword the caller may write: not one that describes the HDU's layout or scaling (BZERO
 * 100 would shift every value read back, NAXIS2 50 read the padding as data), which the
 * writer sets itself, and FITS's own syntax (up to 8 of A-Z, 0-9, '-', '_'). */
static int user_key(swfs_fits_out *o, const char *key)
{
    static const char *const layout[] = {"SIMPLE", "BITPIX", "NAXIS", "EXTEND", "XTENSION", "PCOUNT", "GCOUNT",
                                         "BZERO", "BSCALE", "BLANK", "END", "EXTNAME", "CHECKSUM", "DATASUM",
                                         "TFIELDS", "THEAP", "ZIMAGE", "ZBITPIX", "ZNAXIS", "ZCMPTYPE"};
    size_t n = key ? strlen(key) : 0;
    int ok = n >= 1 && n <= 8;
    for (size_t i = 0; ok && i < n; i++)
        ok = (key[i] >= 'A' && key[i] <= 'Z') || (key[i] >= '0' && key[i] <= '9') || key[i] == '-' || key[i] == '_';
    if (!ok)
        return swfs_fail(SWFS_ERR_ARG, "%s: keyword '%.20s': expected 1 to 8 of A-Z, 0-9, '-', '_'", o->path,
                         key ? key : "");
    for (size_t k = 0; k < sizeof layout / sizeof layout[0]; k++) {
        const size_t m = strlen(layout[k]);
        const int numbered = !strcmp(layout[k], "NAXIS") || !strcmp(layout[k], "ZNAXIS");
        if (!strncmp(key, layout[k], m) && (key[m] == 0 || (numbered && strspn(key + m, "0123456789") == n - m)))
            return swfs_fail(SWFS_ERR_ARG, "%s: keyword %s describes the data's layout or scaling, which the writer "
                             "sets itself", o->path, key);
    }
    return SWFS_OK;
}

int swfs_fits_out_key_double(swfs_fits_out *o, const char *key, double v, const char *comment)
{
    if (user_key(o, key)) return SWFS_ERR_ARG;
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    if (isfinite(v)) fits_update_key(o->fp, TDOUBLE, key, &v, comment, &st);
    else fits_update_key_null(o->fp, key, comment, &st); /* FITS has no NaN header values */
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing keyword");
    return SWFS_OK;
}

int swfs_fits_out_key_long(swfs_fits_out *o, const char *key, long v, const char *comment)
{
    if (user_key(o, key)) return SWFS_ERR_ARG;
    int st = 0, rc = ensure_hdu(o);
    if (rc) return rc;
    fits_update_key(o->fp, TLONG, key, &v, comment, &st);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing keyword");
    return SWFS_OK;
}

int swfs_fits_out_key_string(swfs_fits_out *o, const char *key, const char *v, const char *comment)
{
    if (user_key(o, key)) return SWFS_ERR_ARG;
    for (const unsigned char *c = (const unsigned char *)v; c && *c; c++) /* (a newline would cut the card) */
        if (*c < 32 || *c == 127)
            return swfs_fail(SWFS_ERR_ARG, "%s: keyword %s: its value holds a control character (code %d), which a "
                             "FITS header cannot", o->path, key, *c);
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
    pthread_mutex_lock(&cfitsio_clock);
    fits_write_date(o->fp, &st);
    pthread_mutex_unlock(&cfitsio_clock);
    if (st) return fits_fail(SWFS_ERR_IO, st, o->path, "writing DATE");
    for (size_t i = 0; i < nlines && !rc; i++) rc = swfs_fits_out_history(o, lines[i]);
    return rc;
}

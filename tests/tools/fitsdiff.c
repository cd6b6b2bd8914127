/* fitsdiff A B: exit 0 when the two FITS files hold the same data, HDU by HDU (the same number
 * of HDUs; each image of the same shape with every value equal, compared as doubles, NaN equal
 * to NaN; each table of the same shape with the same bytes in its rows), whatever their
 * headers say otherwise (dates, file names). Exit 1 with the first difference on stderr, 2 on
 * a usage or read error. For the tests that check that two runs made the same product.
 * fitsdiff --rms A B: prints rms(A - B) / rms(A) over the first HDUs' images (of one shape). */
#include <fitsio.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int same(double a, double b) { return a == b || (isnan(a) && isnan(b)); }

/* --rms: rms(A - B) / rms(A) of the first HDUs' images, on stdout */
static int rms_ratio(const char *a, const char *b)
{
    fitsfile *f[2] = {NULL, NULL};
    int st = 0, naxis[2] = {0, 0};
    long n[2][9] = {{0}};
    double *v[2] = {NULL, NULL};
    long total = 1;
    for (int i = 0; i < 2 && !st; i++) {
        fits_open_image(&f[i], i ? b : a, READONLY, &st);
        fits_get_img_param(f[i], 9, &(int){0}, &naxis[i], n[i], &st);
    }
    if (!st && (naxis[0] != naxis[1] || memcmp(n[0], n[1], sizeof n[0]))) {
        fprintf(stderr, "fitsdiff: %s and %s: images of another shape\n", a, b);
        st = -1;
    }
    for (int k = 0; !st && k < naxis[0]; k++) total *= n[0][k];
    for (int i = 0; i < 2 && !st; i++) {
        if (!(v[i] = malloc((size_t)total * sizeof(double)))) st = MEMORY_ALLOCATION;
        else fits_read_img(f[i], TDOUBLE, 1, total, NULL, v[i], &(int){0}, &st);
    }
    double d2 = 0, a2 = 0;
    for (long j = 0; !st && j < total; j++) {
        d2 += (v[0][j] - v[1][j]) * (v[0][j] - v[1][j]);
        a2 += v[0][j] * v[0][j];
    }
    if (!st) printf("%.6g\n", a2 > 0 ? sqrt(d2 / a2) : 0.0);
    else if (st > 0) fits_report_error(stderr, st);
    for (int i = 0; i < 2; i++) {
        free(v[i]);
        int s2 = 0;
        if (f[i]) fits_close_file(f[i], &s2);
    }
    return st ? 2 : 0;
}

int main(int argc, char **argv)
{
    if (argc == 4 && !strcmp(argv[1], "--rms")) return rms_ratio(argv[2], argv[3]);
    if (argc != 3) {
        fprintf(stderr, "usage: fitsdiff A B | fitsdiff --rms A B\n");
        return 2;
    }
    fitsfile *f[2] = {NULL, NULL};
    int st = 0, nh[2] = {0, 0}, diff = 0;
    for (int i = 0; i < 2; i++) {
        fits_open_diskfile(&f[i], argv[1 + i], READONLY, &st);
        fits_get_num_hdus(f[i], &nh[i], &st);
    }
    if (!st && nh[0] != nh[1]) {
        fprintf(stderr, "fitsdiff: %s has %d HDUs, %s %d\n", argv[1], nh[0], argv[2], nh[1]);
        diff = 1;
    }
    for (int k = 1; k <= nh[0] && !st && !diff; k++) {
        int type[2] = {0, 0}, naxis[2] = {0, 0};
        long n[2][9] = {{0}};
        for (int i = 0; i < 2; i++) {
            fits_movabs_hdu(f[i], k, &type[i], &st);
            if (type[i] == IMAGE_HDU) fits_get_img_param(f[i], 9, &(int){0}, &naxis[i], n[i], &st);
            else {
                naxis[i] = 2; /* a table: NAXIS1 bytes per row, NAXIS2 rows */
                fits_get_num_rows(f[i], &n[i][1], &st);
                fits_read_key_lng(f[i], "NAXIS1", &n[i][0], NULL, &st);
            }
        }
        if (st) break;
        if (type[0] != type[1] || naxis[0] != naxis[1] || memcmp(n[0], n[1], sizeof n[0])) {
            fprintf(stderr, "fitsdiff: HDU %d: another kind or shape\n", k);
            diff = 1;
            break;
        }
        long total = 1;
        for (int a = 0; a < naxis[0]; a++) total *= n[0][a];
        if (naxis[0] == 0 || total == 0) continue;
        if (type[0] == IMAGE_HDU) {
            double *v[2] = {malloc((size_t)total * sizeof(double)), malloc((size_t)total * sizeof(double))};
            for (int i = 0; i < 2 && v[0] && v[1]; i++)
                fits_read_img(f[i], TDOUBLE, 1, total, NULL, v[i], &(int){0}, &st);
            if (!v[0] || !v[1]) { fprintf(stderr, "fitsdiff: out of memory\n"); st = MEMORY_ALLOCATION; }
            for (long j = 0; !st && j < total; j++)
                if (!same(v[0][j], v[1][j])) {
                    fprintf(stderr, "fitsdiff: HDU %d, value %ld of %ld: %.17g against %.17g\n", k, j, total, v[0][j], v[1][j]);
                    diff = 1;
                    break;
                }
            free(v[0]);
            free(v[1]);
        } else {
            unsigned char *r[2] = {malloc((size_t)total), malloc((size_t)total)};
            for (int i = 0; i < 2 && r[0] && r[1]; i++) fits_read_tblbytes(f[i], 1, 1, total, r[i], &st);
            if (!r[0] || !r[1]) { fprintf(stderr, "fitsdiff: out of memory\n"); st = MEMORY_ALLOCATION; }
            if (!st && memcmp(r[0], r[1], (size_t)total)) {
                fprintf(stderr, "fitsdiff: HDU %d: the table's rows differ\n", k);
                diff = 1;
            }
            free(r[0]);
            free(r[1]);
        }
    }
    if (st) {
        char msg[FLEN_ERRMSG];
        fits_get_errstatus(st, msg);
        fprintf(stderr, "fitsdiff: %s / %s: %s\n", argv[1], argv[2], msg);
    }
    int cst = 0;
    for (int i = 0; i < 2; i++)
        if (f[i]) fits_close_file(f[i], &cst);
    return st ? 2 : diff;
}

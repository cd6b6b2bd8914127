/* fitscopy IN OUT [lossless]: copy a FITS file through CFITSIO, with CFITSIO's extended syntax on the
 * output name, for the tests of compressed inputs:
 *   fitscopy halo.fits 'halo.fits.fz[compress R]'       Rice tile compression of every image
 *   fitscopy halo.fits 'halo.fits.fz[compress H]'       Hcompress
 *   fitscopy halo.fits 'halo.fits.fz[compress G]' lossless  floating-point data unquantized
 *   fitscopy halo.fits halo.fits.gz                      the whole file gzip-compressed
 * (what fpack and gzip make). Exit 0 on success, 1 with CFITSIO's message otherwise. */
#include <fitsio.h>
#include <stdio.h>
#include <string.h>

int main(int argc, char **argv)
{
    if (argc != 3 && !(argc == 4 && !strcmp(argv[3], "lossless"))) {
        fprintf(stderr, "usage: fitscopy IN OUT [lossless]\n");
        return 2;
    }
    fitsfile *in = NULL, *out = NULL;
    int st = 0, nhdu = 0;
    char name[4096];
    snprintf(name, sizeof name, "!%s", argv[2]); /* "!": replace an existing file */
    const int tiles = strstr(argv[2], "[compress") != NULL;
    fits_open_diskfile(&in, argv[1], READONLY, &st);
    fits_create_file(&out, name, &st);
    int ctype = 0;
    fits_get_compression_type(out, &ctype, &st);
    fits_get_num_hdus(in, &nhdu, &st);
    for (int k = 1; k <= nhdu && !st; k++) {
        int type = 0, naxis = 0;
        fits_movabs_hdu(in, k, &type, &st);
        if (type == IMAGE_HDU) fits_get_img_dim(in, &naxis, &st);
        if (tiles && type == IMAGE_HDU && naxis > 0) {
            if (k == 1) fits_create_img(out, 8, 0, NULL, &st); /* compressed images are extensions */
            /* The request is reset after each compressed HDU: set it again for every one.
             * Quantize level 0: floating-point values stored losslessly. */
            fits_set_compression_type(out, ctype, &st);
            if (argc == 4) fits_set_quantize_level(out, 0.0, &st);
            fits_img_compress(in, out, &st);
        } else {
            fits_copy_hdu(in, out, 0, &st);
        }
    }
    fits_close_file(out, &st);
    fits_close_file(in, &st);
    if (st) {
        fits_report_error(stderr, st);
        return 1;
    }
    return 0;
}

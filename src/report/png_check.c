/* Is a PNG file complete? The chunk structure is walked from the signature to an IEND
 * chunk that ends the file (see include/specklewfs/plot.h). A PNG cut short by a full
 * disk or a killed writer fails here, so it is never renamed into place. */
#include "specklewfs/plot.h"
#include "specklewfs/status.h"

#include <errno.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/stat.h>

static uint32_t be32(const unsigned char *b)
{
    return (uint32_t)b[0] << 24 | (uint32_t)b[1] << 16 | (uint32_t)b[2] << 8 | (uint32_t)b[3];
}

int swfs_plot_png_check(const char *path)
{
    static const unsigned char sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
    static const unsigned char iend_crc[4] = {0xae, 0x42, 0x60, 0x82};
    FILE *f = fopen(path, "rb");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open: %s", path, strerror(errno));
    struct stat sb;
    unsigned char b[8];
    int rc = SWFS_OK;
    if (fstat(fileno(f), &sb) != 0) {
        rc = swfs_fail(SWFS_ERR_IO, "%s: cannot stat: %s", path, strerror(errno));
    } else if (fread(b, 1, 8, f) != 8 || memcmp(b, sig, 8)) {
        rc = swfs_fail(SWFS_ERR_FORMAT, "%s: not a PNG file (%lld bytes, no PNG signature)", path,
                       (long long)sb.st_size);
    }
    const long long size = (long long)sb.st_size;
    long long pos = 8;
    for (size_t k = 0; !rc; k++) {
        if (pos + 12 > size) {
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: PNG is truncated: %lld bytes end before chunk %zu and no IEND chunk",
                           path, size, k + 1);
            break;
        }
        if (fseek(f, (long)pos, SEEK_SET) != 0 || fread(b, 1, 8, f) != 8) {
            rc = swfs_fail(SWFS_ERR_IO, "%s: read error at byte %lld", path, pos);
            break;
        }
        const uint32_t len = be32(b);
        char type[5];
        memcpy(type, b + 4, 4);
        type[4] = '\0';
        if (k == 0 && strcmp(type, "IHDR")) {
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: PNG does not start with an IHDR chunk", path);
            break;
        }
        if (len > 0x7fffffffu || pos + 12 + (long long)len > size) {
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: PNG is truncated: chunk %zu (%s, %lu bytes at byte %lld) runs past "
                           "the end of the file (%lld bytes)", path, k + 1, type, (unsigned long)len, pos, size);
            break;
        }
        pos += 12 + (long long)len;
        if (strcmp(type, "IEND")) continue;
        unsigned char crc[4];
        if (len != 0 || fseek(f, (long)(pos - 4), SEEK_SET) != 0 || fread(crc, 1, 4, f) != 4 || memcmp(crc, iend_crc, 4))
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: PNG has a damaged IEND chunk", path);
        else if (pos != size)
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s: PNG has %lld bytes after its IEND chunk", path, size - pos);
        break;
    }
    fclose(f);
    return rc;
}

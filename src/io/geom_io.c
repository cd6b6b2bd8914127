/* Geometry given in a file (fits.h, swfs_geom_read_file): for camera cubes and telemetry that
 * do not carry the geometry keywords (no camera writes PUPDX or PUPN: they are pupil-grid
 * choices), one place to state them for reduce, speckles and stream. */
#include "specklewfs/fits.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <ctype.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

/* "KEY = VALUE" or "KEY VALUE" lines, '#' comments, the six keywords in any case. */
static int read_text(const char *path, FILE *f, swfs_geom *g)
{
    char line[1024];
    long lineno = 0, seen[6] = {0}; /* the line of each keyword given (a second is refused) */
    static const char *const keys[6] = {"WAVELEN", "TELDIAM", "OBSCUR", "PIXSCALE", "PUPDX", "PUPN"};
    int rc = SWFS_OK;
    while (swfs_text_line(f, line, sizeof line, path, ++lineno, &rc)) {
        char *h = strchr(line, '#');
        if (h) *h = 0;
        char key[64], *p = line;
        while (isspace((unsigned char)*p)) p++;
        if (!*p) continue;
        size_t k = 0;
        while (*p && !isspace((unsigned char)*p) && *p != '=' && k + 1 < sizeof key) key[k++] = *p++;
        key[k] = 0;
        while (isspace((unsigned char)*p) || *p == '=') p++;
        char *end = NULL;
        const double v = strtod(p, &end);
        if (end == p) return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: '%s' has no number", path, lineno, key);
        while (isspace((unsigned char)*end)) end++;
        if (*end) return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: '%s' is followed by '%s'", path, lineno, key, end);
        /* (NaN is the reader's "not given": a value of nan would vanish in silence) */
        if (!isfinite(v) || strpbrk(p, "xX"))
            return swfs_fail(SWFS_ERR_VALUE, "%s:%ld: %s = %.*s: expected a finite decimal number", path, lineno, key,
                             (int)(strcspn(p, " \t\r\n") < 40 ? strcspn(p, " \t\r\n") : 40), p);
        for (int q = 0; q < 6; q++)
            if (!strcasecmp(key, keys[q])) {
                if (seen[q])
                    return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: %s given again (line %ld gave it): one value each", path,
                                     lineno, keys[q], seen[q]);
                seen[q] = lineno;
            }
        if (!strcasecmp(key, "WAVELEN")) g->wavelen = v;
        else if (!strcasecmp(key, "TELDIAM")) g->teldiam = v;
        else if (!strcasecmp(key, "OBSCUR")) g->obscur = v;
        else if (!strcasecmp(key, "PIXSCALE")) g->pixscale = v;
        else if (!strcasecmp(key, "PUPDX")) g->pupdx = v;
        else if (!strcasecmp(key, "PUPN")) {
            if (!(v >= 1 && v <= 1e6) || v != floor(v))
                return swfs_fail(SWFS_ERR_VALUE, "%s:%ld: PUPN = %g; expected a whole number of pupil samples", path,
                                 lineno, v);
            g->pupn = (long)v;
        } else
            return swfs_fail(SWFS_ERR_FORMAT, "%s:%ld: unknown key '%s' (expected WAVELEN, TELDIAM, OBSCUR, PIXSCALE, "
                             "PUPDX, PUPN)", path, lineno, key);
    }
    return rc;
}

int swfs_geom_read_file(const char *path, swfs_geom *g)
{
    swfs_geom_init(g);
    FILE *f = fopen(path, "rb");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the geometry file", path);
    char head[9] = {0};
    const size_t n = fread(head, 1, 8, f);
    int rc;
    if (n == 8 && !memcmp(head, "SIMPLE  ", 8)) {
        fclose(f);
        swfs_fits_in *fi = NULL;
        rc = swfs_fits_in_open(&fi, path, NULL);
        if (!rc) rc = swfs_fits_in_geom(fi, g);
        swfs_fits_in_close(fi);
        if (rc) return rc;
    } else {
        rewind(f);
        rc = read_text(path, f, g);
        fclose(f);
        if (rc) return rc;
    }
    char miss[96];
    if (swfs_geom_missing(g, miss, sizeof miss) == 6)
        return swfs_fail(SWFS_ERR_FORMAT, "%s: no geometry keyword (expected some of WAVELEN, TELDIAM, OBSCUR, PIXSCALE, "
                         "PUPDX, PUPN)", path);
    return swfs_geom_check(g, path);
}

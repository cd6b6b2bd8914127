/* The readers a harness fuzzes take paths: every input is written to one temporary file per
 * process (under TMPDIR, /tmp by default), removed at exit. Included by fuzz_fits.c and
 * fuzz_text.c. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>

static char tmp_path[256];

static void remove_file(void) { unlink(tmp_path); }

/* data written to the process's temporary file NAME-PID.SUFFIX; its path, or NULL. */
static const char *fuzz_write_tmp(const uint8_t *data, size_t size, const char *name, const char *suffix)
{
    if (!tmp_path[0]) {
        const char *tmp = getenv("TMPDIR");
        snprintf(tmp_path, sizeof tmp_path, "%s/%s-%ld.%s", tmp && *tmp ? tmp : "/tmp", name, (long)getpid(), suffix);
        atexit(remove_file);
    }
    FILE *fh = fopen(tmp_path, "wb");
    if (!fh) return NULL;
    if (size) fwrite(data, 1, size, fh);
    fclose(fh);
    return tmp_path;
}

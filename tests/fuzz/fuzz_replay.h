/* The corpus replay of a fuzzing harness built without libFuzzer (fuzz_fits.c, fuzz_text.c):
 * FUZZ_REPLAY_NAME FILE_OR_DIR... feeds every file to the harness's fuzz_one, the regression
 * test of the kept corpus. Included once, at the end of the harness, which defines
 * fuzz_one(data, size), FUZZ_REPLAY_NAME (the program) and FUZZ_REPLAY_WHAT (its readers). */
#include <dirent.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>

static int run_file(const char *path)
{
    FILE *fh = fopen(path, "rb");
    if (!fh) return 1;
    uint8_t *buf = NULL;
    size_t n = 0, cap = 0, k;
    do {
        if (n == cap) {
            cap = cap ? 2 * cap : 65536;
            uint8_t *nb = realloc(buf, cap);
            if (!nb) { free(buf); fclose(fh); return 1; }
            buf = nb;
        }
        k = fread(buf + n, 1, cap - n, fh);
        n += k;
    } while (k > 0);
    fclose(fh);
    fuzz_one(buf, n);
    free(buf);
    return 0;
}

int main(int argc, char **argv)
{
    size_t nfiles = 0;
    for (int i = 1; i < argc; i++) {
        DIR *d = opendir(argv[i]);
        if (!d) {
            if (run_file(argv[i])) { fprintf(stderr, FUZZ_REPLAY_NAME ": cannot read %s\n", argv[i]); return 1; }
            nfiles++;
            continue;
        }
        struct dirent *e;
        while ((e = readdir(d))) {
            if (e->d_name[0] == '.') continue;
            char p[4096];
            snprintf(p, sizeof p, "%s/%s", argv[i], e->d_name);
            if (run_file(p)) { fprintf(stderr, FUZZ_REPLAY_NAME ": cannot read %s\n", p); closedir(d); return 1; }
            nfiles++;
        }
        closedir(d);
    }
    printf(FUZZ_REPLAY_NAME ": %zu files through " FUZZ_REPLAY_WHAT ", no crash\n", nfiles);
    return nfiles ? 0 : 1;
}

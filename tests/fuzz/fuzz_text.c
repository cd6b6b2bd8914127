/* Fuzzing the TEXT readers (docs/fuzzing.md). One input = one file's bytes, handed to every
 * reader of the library that takes a text file: the timing table (swfs_timing_read, with the
 * pairing check its users make), the handshake log (swfs_handshake_read), the key = value
 * configuration (swfs_config_load, then every value read as a number, an integer, a list
 * and a string, and the whole input as one --set assignment), the geometry file of --geom
 * (swfs_geom_read_file), the numeric tables (swfs_table_read) and the sweep's sets file
 * (swfs_sweep_read, each set applied to a configuration). Each must return a status (any
 * status) without crashing, hanging, leaking or touching memory it does not own.
 *
 * Built two ways from this file, like fuzz_fits.c:
 *  - with SWFS_LIBFUZZER (cmake -DSWFS_FUZZ=ON, clang): the libFuzzer target fuzz_text;
 *  - without: fuzz_text_corpus DIR..., the regression test that feeds every file of the kept
 *    corpus (tests/fuzz-corpus-text) to the same readers, run by ctest in every build. */
#include "specklewfs/config.h"
#include "specklewfs/fits.h"
#include "specklewfs/geom.h"
#include "specklewfs/status.h"
#include "specklewfs/sweep.h"
#include "specklewfs/sync.h"
#include "specklewfs/table.h"

#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "fuzz_tmp.h"
#include <unistd.h>

static void timing(const char *path)
{
    swfs_timing *t = NULL;
    if (swfs_timing_read(path, &t)) return;
    (void)swfs_orient_check(&t->fit, 64, 64, path);
    (void)swfs_orient_check(&t->fit, 64, 32, path);
    char buf[80];
    swfs_orient_describe(&t->fit, buf, sizeof buf);
    swfs_timing_free(t);
}

static void handshake(const char *path)
{
    swfs_handshake *h = NULL;
    size_t n = 0;
    if (!swfs_handshake_read(path, &h, &n)) free(h);
}

static void values(swfs_config *c)
{
    for (size_t i = 0; i < swfs_config_count(c); i++) {
        const char *key = swfs_config_key(c, i), *s = NULL;
        double v, list[16];
        size_t n = sizeof list / sizeof list[0];
        long l;
        (void)swfs_config_double(c, key, 0, &v);
        (void)swfs_config_long(c, key, 0, &l);
        (void)swfs_config_doubles(c, key, list, &n);
        (void)swfs_config_string(c, key, "", &s);
    }
    (void)swfs_config_check_unused(c);
}

static void config(const char *path, const uint8_t *data, size_t size)
{
    swfs_config *c = swfs_config_new();
    if (!c) return;
    if (!swfs_config_load(c, path)) values(c);
    swfs_config_free(c);
    /* The input as one command-line assignment (--set / key=value arguments). */
    char *s = malloc(size + 1);
    if (!s) return;
    if (size) memcpy(s, data, size);
    s[size] = 0;
    if ((c = swfs_config_new())) {
        if (!swfs_config_set(c, s)) values(c);
        swfs_config_free(c);
    }
    free(s);
}

static void geometry(const char *path)
{
    swfs_geom g;
    (void)swfs_geom_read_file(path, &g);
}

static void table(const char *path)
{
    swfs_table *t = NULL;
    if (swfs_table_read(path, &t)) return;
    (void)swfs_table_col(t, "sigma");
    swfs_table_free(t);
}

static void sweep(const char *path)
{
    swfs_sweep *s = NULL;
    if (swfs_sweep_read(path, &s)) return;
    for (size_t i = 0; i < s->nsets; i++) {
        swfs_config *c = swfs_config_new();
        if (!c) break;
        if (!swfs_sweep_apply(s, i, c)) values(c);
        swfs_config_free(c);
    }
    swfs_sweep_free(s);
}

/* The readers on one file's bytes. */
static int fuzz_one(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write_tmp(data, size, "swfs-fuzz-text", "txt");
    if (!path) return 0;
    timing(path);
    handshake(path);
    config(path, data, size);
    geometry(path);
    table(path);
    sweep(path);
    swfs_clear_error();
    return 0;
}

#ifdef SWFS_LIBFUZZER
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);
int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) { return fuzz_one(data, size); }
#else
#define FUZZ_REPLAY_NAME "fuzz_text_corpus"
#define FUZZ_REPLAY_WHAT "the text readers"
#include "fuzz_replay.h"
#endif

/* ImageStreamIO 2.00 streams: the byte layout (sizes and offsets computed by hand from
 * FORMATS.md), frames round trip through every datatype, counters and lost frames,
 * the rolling buffer, semaphores between threads, a restarted writer, and streams of
 * another version, size or type refused with a clear message. */
#include "testutil.h"

#include "specklewfs/parallel.h"
#include "specklewfs/shm.h"
#include "specklewfs/status.h"

#include <math.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static char dir[1024];

static void setup_dir(void)
{
    snprintf(dir, sizeof dir, "%s", test_path("shm"));
    mkdir(dir, 0777);
}

static long file_size(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0 ? (long)sb.st_size : -1;
}

static void read_bytes(const char *path, size_t off, void *out, size_t n)
{
    FILE *f = fopen(path, "rb");
    assert_non_null(f);
    assert_int_equal(fseek(f, (long)off, SEEK_SET), 0);
    assert_int_equal(fread(out, 1, n, f), n);
    fclose(f);
}

static void write_bytes(const char *path, size_t off, const void *in, size_t n)
{
    FILE *f = fopen(path, "r+b");
    assert_non_null(f);
    assert_int_equal(fseek(f, (long)off, SEEK_SET), 0);
    assert_int_equal(fwrite(in, 1, n, f), n);
    fclose(f);
}

static void test_layout(void **state)
{
    (void)state;
    setup_dir();
    swfs_shm *w = NULL;
    /* 288 float32 values, 10 semaphores: 384 + 1152 (data) + 320 (sems) + 32 (semlog)
     * + 4 x 40 (read PIDs, write PIDs, semctrl, semstatus: 10 x 4 rounded up to 8) = 2048. */
    swfs_shm_shape sh = {SWFS_SHM_F32, 288, 1, 1, 0, 10};
    assert_ok(swfs_shm_create(&w, dir, "t_vec", &sh));
    char path[4200];
    assert_ok(swfs_shm_path(dir, "t_vec", path, sizeof path));
    assert_int_equal(file_size(path), 2048);
    char ver[32];
    read_bytes(path, 0, ver, 32);
    assert_string_equal(ver, "2.00");
    char name[80];
    read_bytes(path, 32, name, 80);
    assert_string_equal(name, "t_vec");
    uint8_t naxis, dtype;
    uint32_t size[3];
    uint16_t nsem;
    int8_t loc;
    read_bytes(path, 112, &naxis, 1);
    read_bytes(path, 116, size, 12);
    read_bytes(path, 136, &dtype, 1);
    read_bytes(path, 258, &nsem, 2);
    read_bytes(path, 240, &loc, 1);
    assert_int_equal(naxis, 1);
    assert_int_equal(size[0], 288);
    assert_int_equal(dtype, 9);
    assert_int_equal(nsem, 10);
    assert_int_equal(loc, -1);
    double v[288];
    for (int k = 0; k < 288; k++) v[k] = 0.25 * k - 3;
    assert_ok(swfs_shm_write(w, v, (int64_t)1234567890123456789));
    assert_ok(swfs_shm_write(w, v, 0));
    uint64_t cnt0;
    read_bytes(path, 264, &cnt0, 8);
    assert_int_equal(cnt0, 2);
    int64_t at[2];
    read_bytes(path, 184, at, 16); /* atime of the second frame = its write time */
    float f5;
    read_bytes(path, 384 + 5 * 4, &f5, 4);
    assert_close(f5, 0.25 * 5 - 3, 0);
    swfs_shm_close(w, 1);
    assert_int_equal(file_size(path), -1);

    /* Temporal rolling buffer of 5 slices of 4 x 3 uint16: data 120, sems 320 + 32,
     * 4 x 40, atimes 80, writetimes 80, counters 40: 384 + 832 = 1216; imagetype 0x20001. */
    swfs_shm_shape cb = {SWFS_SHM_U16, 4, 3, 5, 1, 10};
    assert_ok(swfs_shm_create(&w, dir, "t_cb", &cb));
    assert_ok(swfs_shm_path(dir, "t_cb", path, sizeof path));
    assert_int_equal(file_size(path), 1216);
    uint64_t itype;
    read_bytes(path, 144, &itype, 8);
    assert_int_equal(itype, 0x20001);
    read_bytes(path, 112, &naxis, 1);
    assert_int_equal(naxis, 3);
    swfs_shm_close(w, 1);
}

static void test_roundtrip(void **state)
{
    (void)state;
    setup_dir();
    const int types[4] = {SWFS_SHM_U16, SWFS_SHM_I16, SWFS_SHM_F32, SWFS_SHM_F64};
    const double in[6] = {-3.6, 0.4, 2.5, 70000.0, 1e-3, 12345.678901234};
    for (int t = 0; t < 4; t++) {
        swfs_shm *w = NULL, *r = NULL;
        swfs_shm_shape sh = {types[t], 3, 2, 1, 0, 2};
        assert_ok(swfs_shm_create(&w, dir, "t_rt", &sh));
        assert_ok(swfs_shm_open(&r, dir, "t_rt"));
        assert_int_equal(swfs_shm_frame_values(r), 6);
        assert_int_equal(swfs_shm_get_shape(r)->datatype, types[t]);
        double out[6];
        swfs_shm_frame m;
        size_t n = 9;
        uint64_t lost = 9;
        assert_ok(swfs_shm_read(r, out, &m, 1, &n, &lost));
        assert_int_equal(n, 0);
        const int64_t at = (int64_t)1700000000 * 1000000000 + 123;
        assert_ok(swfs_shm_write(w, in, at));
        assert_ok(swfs_shm_read(r, out, &m, 1, &n, &lost));
        assert_int_equal(n, 1);
        assert_int_equal(lost, 0);
        assert_int_equal(m.cnt, 1);
        assert_true(m.atime_ns == at);
        assert_true(m.wtime_ns > at);
        const double exp_u16[6] = {0, 0, 3, 65535, 0, 12346}, exp_i16[6] = {-4, 0, 3, 32767, 0, 12346};
        for (int k = 0; k < 6; k++) {
            const double e = types[t] == SWFS_SHM_U16 ? exp_u16[k]
                             : types[t] == SWFS_SHM_I16 ? exp_i16[k]
                             : types[t] == SWFS_SHM_F32 ? (double)(float)in[k]
                                                        : in[k];
            assert_close(out[k], e, 0);
        }
        /* A skipped counter is a lost frame; a 2-D stream keeps only the newest. */
        swfs_shm_skip(w);
        assert_ok(swfs_shm_write(w, in, 0));
        assert_ok(swfs_shm_write(w, in, 0));
        assert_ok(swfs_shm_read(r, out, &m, 1, &n, &lost));
        assert_int_equal(n, 1);
        assert_int_equal(m.cnt, 4);
        assert_int_equal(lost, 2);
        assert_true(m.atime_ns == m.wtime_ns); /* atime 0: the write time */
        swfs_shm_close(r, 0);
        swfs_shm_close(w, 1);
    }
}

static void test_rolling(void **state)
{
    (void)state;
    setup_dir();
    swfs_shm *w = NULL, *r = NULL;
    swfs_shm_shape sh = {SWFS_SHM_F32, 2, 1, 8, 1, 1};
    assert_ok(swfs_shm_create(&w, dir, "t_roll", &sh));
    assert_ok(swfs_shm_open(&r, dir, "t_roll"));
    assert_int_equal(swfs_shm_frame_values(r), 2);
    assert_true(swfs_shm_get_shape(r)->temporal);
    double v[2], out[16 * 2];
    swfs_shm_frame m[16];
    size_t n;
    uint64_t lost;
    /* Three frames, one skipped in between: all read in order with their own times. */
    for (int k = 1; k <= 4; k++) {
        v[0] = k;
        v[1] = -k;
        if (k == 3) swfs_shm_skip(w);
        else assert_ok(swfs_shm_write(w, v, (int64_t)k * 1000));
    }
    assert_ok(swfs_shm_read(r, out, m, 16, &n, &lost));
    assert_int_equal(n, 3);
    assert_int_equal(lost, 1);
    assert_int_equal(m[0].cnt, 1);
    assert_int_equal(m[2].cnt, 4);
    assert_close(out[2 * 2], 4, 0);
    assert_true(m[1].atime_ns == 2000 && m[2].atime_ns == 4000);
    /* Twenty frames written while not reading: the last 8 slices are there (the oldest
     * one only if no write is under way, which is the case here). */
    for (int k = 5; k <= 24; k++) {
        v[0] = k;
        assert_ok(swfs_shm_write(w, v, (int64_t)k * 1000));
    }
    assert_ok(swfs_shm_read(r, out, m, 16, &n, &lost));
    assert_int_equal(n, 8);
    assert_int_equal(lost, 12);
    assert_int_equal(m[0].cnt, 17);
    assert_close(out[7 * 2], 24, 0);
    /* A reader with little room continues where it stopped. */
    for (int k = 25; k <= 28; k++) assert_ok(swfs_shm_write(w, v, 0));
    assert_ok(swfs_shm_read(r, out, m, 3, &n, &lost));
    assert_int_equal(n, 3);
    assert_ok(swfs_shm_read(r, out, m, 3, &n, &lost));
    assert_int_equal(n, 1);
    assert_int_equal(m[0].cnt, 28);
    swfs_shm_close(r, 0);
    swfs_shm_close(w, 1);
}

typedef struct wctx {
    swfs_shm *w;
    int nframes;
    double delay;
} wctx;

static void *writer_thread(void *arg)
{
    wctx *c = arg;
    double v[4] = {1, 2, 3, 4};
    for (int k = 0; k < c->nframes; k++) {
        struct timespec ts = {0, (long)(c->delay * 1e9)};
        nanosleep(&ts, NULL);
        v[0] = k;
        swfs_shm_write(c->w, v, 0);
    }
    return NULL;
}

static void test_semaphores(void **state)
{
    (void)state;
    setup_dir();
    swfs_shm *w = NULL, *r = NULL, *r2 = NULL;
    swfs_shm_shape sh = {SWFS_SHM_F64, 4, 1, 1, 0, 3};
    assert_ok(swfs_shm_create(&w, dir, "t_sem", &sh));
    assert_ok(swfs_shm_open(&r, dir, "t_sem"));
    assert_ok(swfs_shm_claim(r));
    /* The same process claiming again gets the same semaphore back. */
    assert_ok(swfs_shm_open(&r2, dir, "t_sem"));
    assert_ok(swfs_shm_claim(r2));
    pid_t pid[3];
    char path[4200];
    assert_ok(swfs_shm_path(dir, "t_sem", path, sizeof path));
    /* PIDs after data (32), no keywords, 3 sems (96), semlog (32): 384 + 32 + 96 + 32. */
    read_bytes(path, 384 + 32 + 96 + 32, pid, sizeof pid);
    assert_int_equal(pid[0], getpid());
    assert_int_equal(pid[1], 0);
    swfs_shm_close(r2, 0);
    /* Posts made before the claim were flushed: nothing pending now. */
    int posted = 1;
    const double t0 = swfs_wall_seconds();
    assert_ok(swfs_shm_wait(r, 0.05, &posted));
    assert_int_equal(posted, 0);
    assert_true(swfs_wall_seconds() - t0 >= 0.04);
    /* A writer in another thread: every wait returns with the frame. */
    wctx c = {w, 5, 0.01};
    pthread_t th;
    assert_int_equal(pthread_create(&th, NULL, writer_thread, &c), 0);
    int got = 0;
    double out[4];
    swfs_shm_frame m;
    size_t n;
    uint64_t lost, lost_total = 0;
    for (int k = 0; k < 100 && got < 5; k++) {
        assert_ok(swfs_shm_wait(r, 1.0, &posted));
        if (!posted) continue;
        assert_ok(swfs_shm_read(r, out, &m, 1, &n, &lost));
        got += (int)n;
        lost_total += lost;
    }
    pthread_join(th, NULL);
    assert_int_equal((uint64_t)got + lost_total, 5);
    assert_int_equal(m.cnt, 5);
    swfs_shm_close(r, 0);
    read_bytes(path, 384 + 32 + 96 + 32, pid, sizeof pid);
    assert_int_equal(pid[0], 0); /* released */
    swfs_shm_close(w, 1);
}

static void test_restart_and_refusals(void **state)
{
    (void)state;
    setup_dir();
    swfs_shm *w = NULL, *r = NULL, *w2 = NULL;
    swfs_shm_shape sh = {SWFS_SHM_F32, 16, 16, 1, 0, 10};
    assert_ok(swfs_shm_create(&w, dir, "t_rs", &sh));
    assert_ok(swfs_shm_open(&r, dir, "t_rs"));
    int st = -1;
    assert_ok(swfs_shm_check(r, &st));
    assert_int_equal(st, 0);
    assert_ok(swfs_shm_create(&w2, dir, "t_rs", &sh)); /* the writer restarts: a new file */
    assert_ok(swfs_shm_check(r, &st));
    assert_int_equal(st, 1);
    swfs_shm_close(w, 1); /* the old writer's close must not remove the new stream */
    assert_ok(swfs_shm_check(r, &st));
    assert_int_equal(st, 1);
    swfs_shm_close(w2, 1);
    assert_ok(swfs_shm_check(r, &st));
    assert_int_equal(st, 2);
    swfs_shm_close(r, 0);

    /* Another version, another size, another datatype, a GPU stream: refused by name. */
    char path[4200];
    assert_ok(swfs_shm_create(&w, dir, "t_bad", &sh));
    assert_ok(swfs_shm_path(dir, "t_bad", path, sizeof path));
    swfs_shm_close(w, 0);
    write_bytes(path, 0, "1.00", 4);
    assert_int_not_equal(swfs_shm_open(&r, dir, "t_bad"), 0);
    assert_null(r);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "version '1.00'"));
    assert_non_null(strstr(swfs_last_error(), "t_bad.im.shm"));
    write_bytes(path, 0, "2.00", 4);
    const uint8_t cplx = 11;
    write_bytes(path, 136, &cplx, 1);
    assert_int_not_equal(swfs_shm_open(&r, dir, "t_bad"), 0);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "complex float32"));
    const uint8_t f32 = 9;
    write_bytes(path, 136, &f32, 1);
    const int8_t gpu = 0;
    write_bytes(path, 240, &gpu, 1);
    assert_int_not_equal(swfs_shm_open(&r, dir, "t_bad"), 0);
    assert_non_null(strstr(swfs_last_error(), "GPU"));
    const int8_t cpu = -1;
    write_bytes(path, 240, &cpu, 1);
    assert_ok(swfs_shm_open(&r, dir, "t_bad"));
    swfs_shm_close(r, 0);
    assert_int_equal(truncate(path, file_size(path) + 64), 0); /* another build of the struct */
    assert_int_not_equal(swfs_shm_open(&r, dir, "t_bad"), 0);
    print_message("%s\n", swfs_last_error());
    assert_non_null(strstr(swfs_last_error(), "another build or version"));
    assert_int_equal(unlink(path), 0);
    assert_int_not_equal(swfs_shm_open(&r, dir, "t_bad"), 0);
    assert_non_null(strstr(swfs_last_error(), "t_bad.im.shm"));
    /* Names. */
    assert_int_not_equal(swfs_shm_path(dir, "a/b", path, sizeof path), 0);
    assert_int_not_equal(swfs_shm_path(dir, "", path, sizeof path), 0);
    swfs_shm_shape bad = {SWFS_SHM_F32, 0, 1, 1, 0, 1};
    assert_int_not_equal(swfs_shm_create(&w, dir, "t_x", &bad), 0);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_layout),    cmocka_unit_test(test_roundtrip),
        cmocka_unit_test(test_rolling),   cmocka_unit_test(test_semaphores),
        cmocka_unit_test(test_restart_and_refusals),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}

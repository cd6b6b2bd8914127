/* Shared helpers for the cmocka tests. */
#ifndef SWFS_TESTUTIL_H
#define SWFS_TESTUTIL_H

#include <stdarg.h>
#include <stddef.h>
#include <setjmp.h>
#include <stdint.h>
#include <cmocka.h>

/* A path inside the test scratch folder (created on demand): tmp/<name>. */
const char *test_path(const char *name);
/* Fail the test with the library's message unless rc == 0. */
#define assert_ok(rc) test_assert_ok((rc), #rc, __FILE__, __LINE__)
void test_assert_ok(int rc, const char *expr, const char *file, int line);
/* |a - b| <= tol, with a readable message. */
#define assert_close(a, b, tol) test_assert_close((a), (b), (tol), #a, __FILE__, __LINE__)
void test_assert_close(double a, double b, double tol, const char *expr, const char *file, int line);
int test_file_exists(const char *path);
/* An annular pupil on the n x n grid of spacing dx [m]: 1 where obs diam / 2 <= r <= diam / 2
 * (r from the grid's centre), else 0 (malloc'd; the caller frees). */
double *test_annulus(size_t n, double dx, double diam, double obs);
/* The command line's OpenBLAS kernels made this process's (OPENBLAS_CORETYPE, unless set):
 * on a CPU OpenBLAS does not know, the command would switch to better kernels than the ones
 * this process loaded, and a test comparing the two would measure the kernels' rounding
 * (scripts/test.sh sets the variable for both; a plain ctest does not). */
void test_cli_same_kernels(void);
/* Run `specklewfs ARGS` (in folder dir unless NULL) with this process's kernels
 * (test_cli_same_kernels), capture stdout + stderr into out; return the exit status (-1 if
 * it did not exit normally). */
int test_run_cli(const char *dir, const char *args, char *out, size_t cap);

#endif

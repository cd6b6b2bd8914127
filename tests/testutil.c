#include "testutil.h"

#include "specklewfs/parallel.h"
#include "specklewfs/status.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>

const char *test_path(const char *name)
{
    static char buf[8][1024];
    static int k = 0;
    mkdir(SWFS_TEST_TMPDIR, 0777);
    char *b = buf[k++ % 8];
    snprintf(b, sizeof buf[0], "%s/%s", SWFS_TEST_TMPDIR, name);
    return b;
}

void test_assert_ok(int rc, const char *expr, const char *file, int line)
{
    if (rc != 0) {
        print_error("%s:%d: %s returned %d: %s\n", file, line, expr, rc, swfs_last_error());
        _fail(file, line);
    }
}

void test_assert_close(double a, double b, double tol, const char *expr, const char *file, int line)
{
    if (!(fabs(a - b) <= tol)) {
        print_error("%s:%d: %s = %.10g, expected %.10g within %.3g\n", file, line, expr, a, b, tol);
        _fail(file, line);
    }
}

int test_file_exists(const char *path)
{
    struct stat sb;
    return stat(path, &sb) == 0;
}

void test_cli_same_kernels(void)
{
    if (getenv("OPENBLAS_CORETYPE")) return;
    swfs_blas_kernel_info k;
    swfs_blas_kernel(&k);
    if (strcmp(k.core, "unknown")) (void)setenv("OPENBLAS_CORETYPE", k.core, 0);
}

int test_run_cli(const char *dir, const char *args, char *out, size_t cap)
{
    char cmd[8192];
    test_cli_same_kernels();
    if (dir) snprintf(cmd, sizeof cmd, "cd '%s' && %s %s 2>&1", dir, SWFS_CLI_BIN, args);
    else snprintf(cmd, sizeof cmd, "%s %s 2>&1", SWFS_CLI_BIN, args);
    FILE *p = popen(cmd, "r");
    size_t len = 0;
    out[0] = '\0';
    if (!p) return -1;
    while (len + 1 < cap && fgets(out + len, (int)(cap - len), p)) len = strlen(out);
    int st = pclose(p);
    return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

double *test_annulus(size_t n, double dx, double diam, double obs)
{
    double *m = malloc(n * n * sizeof *m);
    for (size_t q = 0; m && q < n; q++)
        for (size_t p = 0; p < n; p++) {
            double x = ((double)p - 0.5 * (double)(n - 1)) * dx, y = ((double)q - 0.5 * (double)(n - 1)) * dx;
            double r = sqrt(x * x + y * y);
            m[q * n + p] = (r <= 0.5 * diam && r >= 0.5 * obs * diam) ? 1.0 : 0.0;
        }
    return m;
}


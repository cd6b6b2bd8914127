/* The command line's plumbing: error messages, the command line as provenance, progress,
 * output folders and paths (cli.h). */
#include "cli.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/config.h"
#include "specklewfs/status.h"
#include "specklewfs/timeseries.h"

#include <errno.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

int cli_error(const char *cmd)
{
    /* Library messages of a module named like the command ("report: ...") would read
     * "specklewfs report: report: ..."; say the command once. */
    const char *msg = swfs_last_error();
    size_t n = strlen(cmd);
    if (!strncmp(msg, cmd, n) && msg[n] == ':' && msg[n + 1] == ' ') msg += n + 2;
    const int sig = cli_stop_signal();
    if (sig) { /* the shell's convention for a run ended by a signal: 128 + its number */
        fprintf(stderr, "specklewfs %s: %s (%s)\n", cmd, msg, sig == SIGINT ? "SIGINT" : "SIGTERM");
        return 128 + sig;
    }
    fprintf(stderr, "specklewfs %s: %s\n", cmd, msg);
    return CLI_FAIL;
}

int cli_usage_error(const char *cmd, const char *fmt, ...)
{
    va_list ap;
    fprintf(stderr, "specklewfs %s: ", cmd);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fprintf(stderr, " (see 'specklewfs %s --help')\n", cmd);
    return CLI_USAGE;
}

int cli_check(const char *cmd, int rc)
{
    return rc ? cli_usage_error(cmd, "%s", swfs_last_error()) : 0;
}

void cli_command_line(int argc, char **argv, char *buf, size_t cap)
{
    size_t len = 0;
    buf[0] = '\0';
    len += (size_t)snprintf(buf, cap, "specklewfs");
    for (int i = 0; i < argc && len < cap; i++) len += (size_t)snprintf(buf + len, cap - len, " %s", argv[i]);
}

double cli_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

void cli_progress(const char *label, size_t k, size_t n)
{
    static int tty = -1;
    static char last[128];
    static size_t last_k, last_n;
    if (tty < 0) tty = isatty(fileno(stderr));
    /* a stage may report the same count again (a long step checking whether to stop) */
    if (k == last_k && n == last_n && !strncmp(label, last, sizeof last - 1)) return;
    snprintf(last, sizeof last, "%s", label);
    last_k = k;
    last_n = n;
    if (tty) {
        fprintf(stderr, "\r%s %zu/%zu", label, k, n);
        if (k == n) fputc('\n', stderr);
    } else if (k == n || (n >= 10 && k % (n / 10 ? n / 10 : 1) == 0)) {
        fprintf(stderr, "%s %zu/%zu\n", label, k, n);
    }
    fflush(stderr);
}

int cli_stage_progress(void *ctx, const char *stage, size_t done, size_t total)
{
    char label[128];
    if (ctx) snprintf(label, sizeof label, "%s %s", (const char *)ctx, stage);
    else snprintf(label, sizeof label, "%s", stage);
    cli_progress(label, done, total);
    return cli_stop_requested();
}

int cli_make_dir(const char *cmd, const char *path)
{
    return swfs_make_dirs(path) ? cli_error(cmd) : 0;
}

int cli_paths_check(const char *cmd, swfs_paths *p)
{
    int rc = swfs_paths_status(p);
    swfs_paths_free(p);
    return rc ? cli_error(cmd) : CLI_OK;
}

void cli_paths_outputs_in(swfs_paths *p, const char *dir, const char *const *names, size_t n)
{
    char path[8192];
    for (size_t k = 0; k < n; k++) {
        snprintf(path, sizeof path, "%s/%s", dir, names[k]);
        swfs_paths_output(p, "output", path);
    }
}

void cli_dir_of(const char *path, char *dir, size_t cap)
{
    const char *s = strrchr(path, '/');
    if (!s) { snprintf(dir, cap, "."); return; }
    size_t n = (size_t)(s - path);
    if (n >= cap) n = cap - 1;
    memcpy(dir, path, n);
    dir[n] = 0;
    if (n == 0) snprintf(dir, cap, "/");
}

const char *const *cli_provenance(int argc, char **argv, size_t *n)
{
    static char line[2048];
    static const char *lines[1] = {line};
    cli_command_line(argc, argv, line, sizeof line);
    *n = 1;
    return lines;
}

int cli_ts_params(const char *cmd, const char *cfgfile, struct swfs_config *over, struct swfs_ts_params *p,
                  int *filter_given, int *noise_given, int (*describe)(struct swfs_config *, void *), void *ctx)
{
    swfs_config *file = NULL;
    int rc = 0;
    if (cfgfile) { /* the file first, then the key=value overrides */
        if (!(file = swfs_config_new()) || swfs_config_load(file, cfgfile)) rc = cli_error(cmd);
        for (size_t k = 0; !rc && k < swfs_config_count(over); k++)
            if (swfs_config_set_kv(file, swfs_config_key(over, k), swfs_config_value(over, k))) rc = cli_error(cmd);
    }
    swfs_config *use = file ? file : over;
    if (!rc && filter_given) *filter_given = swfs_ts_config_gives_filter(use);
    if (!rc && noise_given) *noise_given = swfs_config_has(use, "slope_noise");
    if (!rc && describe && describe(use, ctx)) rc = cli_error(cmd); /* adds only the keys not given */
    if (!rc && (swfs_ts_params_from_config(use, p) || swfs_config_check_unused(use) || swfs_ts_params_check(p)))
        rc = cli_error(cmd);
    swfs_config_free(file);
    return rc;
}

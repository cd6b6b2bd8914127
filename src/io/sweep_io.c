/* The sweep's files: the sets it reads and the table it writes. See include/specklewfs/sweep.h. */
#include "specklewfs/sweep.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

void swfs_sweep_free(swfs_sweep *s)
{
    if (!s) return;
    for (size_t i = 0; i < s->nsets; i++) free(s->sets[i]);
    free(s->sets);
    free(s->line);
    free(s->path);
    free(s);
}

/* One line's assignments, normalized to "k=v k=v" (NULL for a line without any). */
static int parse_line(const char *path, size_t lineno, char *text, char **out)
{
    *out = NULL;
    char *hash = strchr(text, '#');
    if (hash) *hash = '\0';
    size_t cap = strlen(text) + 1, len = 0;
    char *set = NULL;
    for (char *tok = strtok(text, " \t\r\n"); tok; tok = strtok(NULL, " \t\r\n")) {
        const char *eq = strchr(tok, '=');
        if (!eq || eq == tok || !eq[1]) {
            free(set);
            return swfs_fail(SWFS_ERR_FORMAT, "%s:%zu: '%s' is not key=value (a set is key=value assignments "
                             "separated by spaces)", path, lineno, tok);
        }
        if (!set && !(set = malloc(cap))) return swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
        len += (size_t)snprintf(set + len, cap - len, "%s%s", len ? " " : "", tok);
    }
    *out = set;
    return SWFS_OK;
}

int swfs_sweep_read(const char *path, swfs_sweep **out)
{
    *out = NULL;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open the sets file: %s", path, strerror(errno));
    swfs_sweep *s = calloc(1, sizeof *s);
    int rc = s && (s->path = strdup(path)) ? SWFS_OK : swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    char line[8192];
    size_t lineno = 0, cap = 0;
    while (!rc && fgets(line, sizeof line, f)) {
        lineno++;
        if (!strchr(line, '\n') && !feof(f)) {
            rc = swfs_fail(SWFS_ERR_FORMAT, "%s:%zu: line longer than %zu characters", path, lineno, sizeof line - 2);
            break;
        }
        char *set = NULL;
        if ((rc = parse_line(path, lineno, line, &set)) || !set) continue;
        if (s->nsets == cap) {
            cap = cap ? 2 * cap : 16;
            char **ns = realloc(s->sets, cap * sizeof *ns);
            size_t *nl = ns ? realloc(s->line, cap * sizeof *nl) : NULL;
            if (ns) s->sets = ns;
            if (nl) s->line = nl;
            if (!ns || !nl) {
                free(set);
                rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
                break;
            }
        }
        s->sets[s->nsets] = set;
        s->line[s->nsets++] = lineno;
    }
    if (!rc && ferror(f)) rc = swfs_fail(SWFS_ERR_IO, "%s: read error", path);
    fclose(f);
    if (!rc && !s->nsets) rc = swfs_fail(SWFS_ERR_VALUE, "%s: no parameter set (one line of key=value per set)", path);
    if (rc) {
        swfs_sweep_free(s);
        return rc;
    }
    *out = s;
    return SWFS_OK;
}

int swfs_sweep_apply(const swfs_sweep *s, size_t i, swfs_config *cfg)
{
    if (i >= s->nsets) return swfs_fail(SWFS_ERR_ARG, "%s: set %zu of %zu", s->path, i, s->nsets);
    char *copy = strdup(s->sets[i]);
    if (!copy) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    int rc = SWFS_OK;
    for (char *tok = strtok(copy, " "); tok && !rc; tok = strtok(NULL, " "))
        if ((rc = swfs_config_set(cfg, tok))) swfs_fail_context(rc, "%s:%zu", s->path, s->line[i]);
    free(copy);
    return rc;
}

int swfs_sweep_write(const char *path, const swfs_sweep *s, const char *const *cols, size_t ncols,
                     const double *rows, const char *const *prov, size_t nprov)
{
    const size_t n = strlen(path);
    char *part = malloc(n + 6);
    if (!part) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    snprintf(part, n + 6, "%s.part", path);
    FILE *f = fopen(part, "w");
    if (!f) {
        int e = errno;
        free(part);
        return swfs_fail(SWFS_ERR_IO, "%s: cannot write: %s", path, strerror(e));
    }
    for (size_t k = 0; k < nprov; k++) fprintf(f, "# %s\n", prov[k]);
    fprintf(f, "# sets from %s\nset\tparams", s->path);
    for (size_t c = 0; c < ncols; c++) fprintf(f, "\t%s", cols[c]);
    fputc('\n', f);
    for (size_t i = 0; i < s->nsets; i++) {
        fprintf(f, "%zu\t%s", i, s->sets[i]);
        for (size_t c = 0; c < ncols; c++) fprintf(f, "\t%.10g", rows[i * ncols + c]);
        fputc('\n', f);
    }
    int rc = ferror(f) ? SWFS_ERR_IO : SWFS_OK;
    if (fclose(f) != 0) rc = SWFS_ERR_IO;
    if (!rc && rename(part, path) != 0) rc = SWFS_ERR_IO;
    if (rc) {
        remove(part);
        swfs_fail(rc, "%s: write failed: %s", path, strerror(errno));
    }
    free(part);
    return rc;
}

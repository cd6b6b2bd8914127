#include "specklewfs/config.h"
#include "specklewfs/outpaths.h"
#include "specklewfs/status.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

struct entry {
    char *key, *value;
    int used;
};

struct swfs_config {
    struct entry *e;
    size_t n, cap;
};

swfs_config *swfs_config_new(void)
{
    swfs_config *c = calloc(1, sizeof *c);
    if (!c) swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    return c;
}

void swfs_config_free(swfs_config *c)
{
    if (!c) return;
    for (size_t i = 0; i < c->n; i++) {
        free(c->e[i].key);
        free(c->e[i].value);
    }
    free(c->e);
    free(c);
}

static char *trim(char *s)
{
    while (isspace((unsigned char)*s)) s++;
    char *end = s + strlen(s);
    while (end > s && isspace((unsigned char)end[-1])) *--end = '\0';
    return s;
}

static struct entry *find(const swfs_config *c, const char *key)
{
    for (size_t i = c->n; i-- > 0;)
        if (strcmp(c->e[i].key, key) == 0) return &c->e[i];
    return NULL;
}

int swfs_config_set_kv(swfs_config *c, const char *key, const char *value)
{
    if (!*key) return swfs_fail(SWFS_ERR_ARG, "empty key in setting '%s=%s'", key, value);
    struct entry *e = find(c, key);
    if (e) {
        char *v = strdup(value);
        if (!v) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        free(e->value);
        e->value = v;
        return SWFS_OK;
    }
    if (c->n == c->cap) {
        size_t cap = c->cap ? 2 * c->cap : 16;
        struct entry *ne = realloc(c->e, cap * sizeof *ne);
        if (!ne) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
        c->e = ne;
        c->cap = cap;
    }
    c->e[c->n].key = strdup(key);
    c->e[c->n].value = strdup(value);
    c->e[c->n].used = 0;
    if (!c->e[c->n].key || !c->e[c->n].value) return swfs_fail(SWFS_ERR_NOMEM, "out of memory");
    c->n++;
    return SWFS_OK;
}

static int set_line(swfs_config *c, const char *line, const char *where)
{
    char buf[1024];
    if (strlen(line) >= sizeof buf) return swfs_fail(SWFS_ERR_ARG, "%s: line too long", where);
    strcpy(buf, line);
    char *hash = strchr(buf, '#');
    if (hash) *hash = '\0';
    char *s = trim(buf);
    if (!*s) return SWFS_OK;
    char *eq = strchr(s, '=');
    if (!eq) return swfs_fail(SWFS_ERR_ARG, "%s: expected key=value, got '%s'", where, s);
    *eq = '\0';
    return swfs_config_set_kv(c, trim(s), trim(eq + 1));
}

int swfs_config_set(swfs_config *c, const char *assignment)
{
    return set_line(c, assignment, "setting");
}

int swfs_config_load(swfs_config *c, const char *path)
{
    if (swfs_input_check(path, "config")) return SWFS_ERR_IO;
    FILE *f = fopen(path, "r");
    if (!f) return swfs_fail(SWFS_ERR_IO, "%s: cannot open config file: %s", path, strerror(errno));
    char line[1024], where[600];
    long lineno = 0;
    int st = SWFS_OK;
    while (swfs_text_line(f, line, sizeof line, path, ++lineno, &st)) {
        snprintf(where, sizeof where, "%s:%ld", path, lineno);
        if ((st = set_line(c, line, where)) != SWFS_OK) break;
    }
    fclose(f);
    return st;
}

int swfs_config_has(const swfs_config *c, const char *key) { return find(c, key) != NULL; }

int swfs_config_double(swfs_config *c, const char *key, double def, double *out)
{
    struct entry *e = find(c, key);
    *out = def;
    if (!e) return SWFS_OK;
    e->used = 1;
    char *end;
    errno = 0;
    double v = strtod(e->value, &end);
    if (end == e->value || *trim(end) != '\0' || errno == ERANGE || isnan(v))
        return swfs_fail(SWFS_ERR_VALUE, "setting %s=%s: expected a number", key, e->value);
    *out = v;
    return SWFS_OK;
}

int swfs_config_long(swfs_config *c, const char *key, long def, long *out)
{
    struct entry *e = find(c, key);
    *out = def;
    if (!e) return SWFS_OK;
    e->used = 1;
    char *end;
    errno = 0;
    long v = strtol(e->value, &end, 10);
    if (end == e->value || *trim(end) != '\0' || errno == ERANGE)
        return swfs_fail(SWFS_ERR_VALUE, "setting %s=%s: expected an integer", key, e->value);
    *out = v;
    return SWFS_OK;
}

int swfs_config_string(swfs_config *c, const char *key, const char *def, const char **out)
{
    struct entry *e = find(c, key);
    *out = def;
    if (!e) return SWFS_OK;
    e->used = 1;
    *out = e->value;
    return SWFS_OK;
}

int swfs_config_doubles(swfs_config *c, const char *key, double *out, size_t *n)
{
    struct entry *e = find(c, key);
    size_t cap = *n, k = 0;
    *n = 0;
    if (!e) return SWFS_OK;
    e->used = 1;
    const char *s = e->value;
    while (*s) {
        while (*s == ',' || isspace((unsigned char)*s)) s++;
        if (!*s) break;
        char *end;
        double v = strtod(s, &end);
        if (end == s || isnan(v)) return swfs_fail(SWFS_ERR_VALUE, "setting %s=%s: expected numbers", key, e->value);
        if (k == cap) return swfs_fail(SWFS_ERR_VALUE, "setting %s: more than %zu values", key, cap);
        out[k++] = v;
        s = end;
    }
    *n = k;
    return SWFS_OK;
}

int swfs_config_check_unused(const swfs_config *c)
{
    for (size_t i = 0; i < c->n; i++)
        if (!c->e[i].used)
            return swfs_fail(SWFS_ERR_ARG, "unknown setting '%s' (value '%s')", c->e[i].key, c->e[i].value);
    return SWFS_OK;
}

size_t swfs_config_count(const swfs_config *c) { return c->n; }
const char *swfs_config_key(const swfs_config *c, size_t i) { return c->e[i].key; }
const char *swfs_config_value(const swfs_config *c, size_t i) { return c->e[i].value; }

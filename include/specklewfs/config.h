/* key = value configuration: a file (one pair per line, '#' comments) plus command-line
 * overrides ("key=value"). Later settings win. Lookups record which keys were used so a
 * caller can reject unknown keys (typos) with swfs_config_check_unused(). */
#ifndef SWFS_CONFIG_H
#define SWFS_CONFIG_H

#include "specklewfs/defs.h"

#include <stddef.h>

SWFS_BEGIN_DECLS

typedef struct swfs_config swfs_config;

swfs_config *swfs_config_new(void);
void swfs_config_free(swfs_config *c);
int swfs_config_load(swfs_config *c, const char *path);
/* "key=value" (spaces around '=' allowed). */
int swfs_config_set(swfs_config *c, const char *assignment);
int swfs_config_set_kv(swfs_config *c, const char *key, const char *value);
int swfs_config_has(const swfs_config *c, const char *key);

/* Each returns SWFS_OK with *out = def if the key is absent; SWFS_ERR_VALUE with a
 * message naming the key if the value does not parse. */
int swfs_config_double(swfs_config *c, const char *key, double def, double *out);
int swfs_config_long(swfs_config *c, const char *key, long def, long *out);
int swfs_config_string(swfs_config *c, const char *key, const char *def, const char **out);
/* Comma/space separated list of doubles; *n is in: capacity, out: count. */
int swfs_config_doubles(swfs_config *c, const char *key, double *out, size_t *n);

/* SWFS_ERR_ARG naming the first key that no lookup asked for. */
int swfs_config_check_unused(const swfs_config *c);

size_t swfs_config_count(const swfs_config *c);
const char *swfs_config_key(const swfs_config *c, size_t i);
const char *swfs_config_value(const swfs_config *c, size_t i);

SWFS_END_DECLS

#endif

/* Private to src/run/. */
#ifndef SWFS_RUN_INTERNAL_H
#define SWFS_RUN_INTERNAL_H

#include <stddef.h>

/* The caller's provenance lines followed by `extra` (a new array the caller frees; the
 * strings are not copied). NULL when out of memory. */
const char **swfs_prov_plus(const char *const *prov, size_t nprov, const char *extra);

#endif

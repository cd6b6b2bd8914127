/* Provenance lines of the runs: see src/run/run_internal.h. */
#include "run_internal.h"

#include <stdlib.h>

const char **swfs_prov_plus(const char *const *prov, size_t nprov, const char *extra)
{
    const char **p = malloc((nprov + 1) * sizeof *p);
    if (!p) return NULL;
    for (size_t i = 0; i < nprov; i++) p[i] = prov[i];
    p[nprov] = extra;
    return p;
}

/* The FFTW planner lock: see src/core/planner.h. */
#include "planner.h"

#include <pthread.h>

static pthread_mutex_t planner_mu = PTHREAD_MUTEX_INITIALIZER;

void swfs_planner_lock(void) { pthread_mutex_lock(&planner_mu); }
void swfs_planner_unlock(void) { pthread_mutex_unlock(&planner_mu); }

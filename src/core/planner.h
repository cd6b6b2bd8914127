/* Private to the library: FFTW's planner (plan creation and destruction) is not
 * thread-safe, while executing a plan is. Every fftw_plan_* and fftw_destroy_plan call in
 * the library runs under this one lock, so independent objects (engines, screen
 * generators, coherence workers) may be created and freed from any thread. */
#ifndef SWFS_PLANNER_H
#define SWFS_PLANNER_H

void swfs_planner_lock(void);
void swfs_planner_unlock(void);

#endif

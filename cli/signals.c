/* SIGINT and SIGTERM on the command line (cli.h): a stoppable command's run stops at its next
 * progress report (status.h swfs_progress_fn); any other command, and a second signal, end
 * the process at once with its part files removed (atomic.h swfs_atomic_remove_parts). */
#include "cli.h"
#include "specklewfs/atomic.h"

#include <signal.h>
#include <string.h>
#include <unistd.h>

/* The signal (SIGINT, SIGTERM) that asked a run with progress to stop, or 0. */
static volatile sig_atomic_t stop_signal;

/* End the process by the signal, its part files removed first (atomic.h). */
static void end_by_signal(int sig)
{
    swfs_atomic_remove_parts();
    signal(sig, SIG_DFL);
    raise(sig);
}

static void on_stop_signal(int sig)
{
    if (stop_signal) { /* a second signal, of either kind: end at once */
        end_by_signal(sig);
        return;
    }
    static const char msg[] = "\nspecklewfs: stopping at the run's next step (a second signal ends it at once)\n";
    stop_signal = sig;
    const ssize_t w = write(STDERR_FILENO, msg, sizeof msg - 1);
    (void)w;
}

/* SIGINT and SIGTERM, where nothing else handles them, ask the run to stop at its next
 * progress report (the library then removes its partial outputs); a second signal of either
 * kind ends the process at once, its part files removed first. */
static void catch_signals(void (*handler)(int))
{
    const int sigs[2] = {SIGINT, SIGTERM};
    for (int k = 0; k < 2; k++) {
        struct sigaction old, sa;
        if (sigaction(sigs[k], NULL, &old) || old.sa_handler != SIG_DFL) continue; /* ignored, or live's own */
        memset(&sa, 0, sizeof sa);
        sa.sa_handler = handler;
        sigemptyset(&sa.sa_mask);
        sigaction(sigs[k], &sa, NULL);
    }
}

void cli_stop_catch(void)
{
    catch_signals(on_stop_signal);
}

void cli_end_catch(void)
{
    catch_signals(end_by_signal);
}

int cli_stop_requested(void)
{
    return stop_signal != 0;
}

int cli_stop_signal(void)
{
    return stop_signal;
}

int cli_stop_check(void *ctx, const char *stage, size_t done, size_t total)
{
    (void)ctx, (void)stage, (void)done, (void)total;
    return cli_stop_requested();
}


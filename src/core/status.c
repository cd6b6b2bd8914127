#include "specklewfs/status.h"

#include <stdarg.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

static _Thread_local char swfs_msg[1024];

int swfs_fail(int code, const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(swfs_msg, sizeof swfs_msg, fmt, ap);
    va_end(ap);
    return code;
}

int swfs_fail_context(int code, const char *fmt, ...)
{
    char old[sizeof swfs_msg];
    memcpy(old, swfs_msg, sizeof old);
    va_list ap;
    va_start(ap, fmt);
    int len = vsnprintf(swfs_msg, sizeof swfs_msg, fmt, ap);
    va_end(ap);
    if (len >= 0 && (size_t)len + 2 < sizeof swfs_msg) {
        size_t used = (size_t)len;
        swfs_msg[used++] = ':';
        swfs_msg[used++] = ' ';
        size_t room = sizeof swfs_msg - used - 1;
        size_t olen = strlen(old);
        if (olen > room) olen = room;
        memcpy(swfs_msg + used, old, olen);
        swfs_msg[used + olen] = '\0';
    }
    return code;
}

const char *swfs_last_error(void) { return swfs_msg[0] ? swfs_msg : "no error"; }

void swfs_clear_error(void) { swfs_msg[0] = '\0'; }

const char *swfs_status_name(int code)
{
    switch (code) {
    case SWFS_OK: return "ok";
    case SWFS_ERR_ARG: return "invalid argument";
    case SWFS_ERR_NOMEM: return "out of memory";
    case SWFS_ERR_IO: return "I/O error";
    case SWFS_ERR_FORMAT: return "format error";
    case SWFS_ERR_SHAPE: return "shape mismatch";
    case SWFS_ERR_VALUE: return "invalid value";
    case SWFS_ERR_NUMERIC: return "numerical failure";
    case SWFS_ERR_STOPPED: return "stopped by the caller";
    default: return "internal error";
    }
}

int swfs_progress_report(swfs_progress_fn progress, void *ctx, const char *stage, size_t done, size_t total)
{
    if (!progress || !progress(ctx, stage, done, total)) return SWFS_OK;
    return swfs_fail(SWFS_ERR_STOPPED, "%s: stopped by the caller at %zu of %zu", stage ? stage : "run", done, total);
}

const char *swfs_value_words(double v, char *buf, size_t cap)
{
    if (isfinite(v)) snprintf(buf, cap, "is %g", v);
    else snprintf(buf, cap, "is not finite (NaN or infinite)");
    return buf;
}

/* The HTML of a report: a growing string, the key-number and TSV tables, the notes, and
 * the page written through io's atomic text writer. */
#define _POSIX_C_SOURCE 200809L /* gmtime_r */
#include "report_internal.h"

#include "specklewfs/status.h"
#include "specklewfs/table.h"
#include "specklewfs/version.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

void rep_printf(rep_strbuf *b, const char *fmt, ...)
{
    if (b->oom) return;
    for (;;) {
        size_t room = b->cap - b->len;
        va_list ap;
        va_start(ap, fmt);
        int n = vsnprintf(b->s ? b->s + b->len : NULL, b->s ? room : 0, fmt, ap);
        va_end(ap);
        if (n < 0) {
            b->oom = 1;
            return;
        }
        if (b->s && (size_t)n < room) {
            b->len += (size_t)n;
            return;
        }
        size_t cap = b->cap ? b->cap : 4096;
        while (cap - b->len <= (size_t)n) cap *= 2;
        char *s = realloc(b->s, cap);
        if (!s) {
            b->oom = 1;
            return;
        }
        b->s = s;
        b->cap = cap;
    }
}

void rep_text(rep_strbuf *b, const char *t)
{
    for (; *t; t++) {
        switch (*t) {
        case '&': rep_printf(b, "&amp;"); break;
        case '<': rep_printf(b, "&lt;"); break;
        case '>': rep_printf(b, "&gt;"); break;
        case '"': rep_printf(b, "&quot;"); break;
        default: rep_printf(b, "%c", *t);
        }
    }
}

static void row(rep_strbuf *b, const char *key, const char *val, const char *prefix, const char *id)
{
    rep_printf(b, "<tr><th>%s</th><td id=\"%s%s\">%s</td></tr>\n", key, prefix, id, val);
}

void rep_key_numbers(rep_strbuf *b, const swfs_report_summary *s, const char *id_prefix)
{
    const char *px = id_prefix;
    char v[256];
    rep_printf(b, "<table id=\"%skey-numbers\">\n", px);
    if (isfinite(s->frames)) snprintf(v, sizeof v, "%.0f", s->frames);
    else snprintf(v, sizeof v, "n/a");
    row(b, "frames", v, px, "frames");
    if (isfinite(s->valid_fraction)) snprintf(v, sizeof v, "%.1f %%", 100.0 * s->valid_fraction);
    else snprintf(v, sizeof v, "n/a");
    row(b, "valid fraction (g defined)", v, px, "valid-fraction");
    if (isfinite(s->median_snr)) snprintf(v, sizeof v, "%.2f", s->median_snr);
    else snprintf(v, sizeof v, "n/a");
    row(b, "median SNR (valid pixels)", v, px, "median-snr");
    if (isfinite(s->wfe_rms)) snprintf(v, sizeof v, "%.1f nm rms / %.1f nm PV", 1e9 * s->wfe_rms, 1e9 * s->wfe_pv);
    else snprintf(v, sizeof v, "n/a");
    row(b, "estimated WFE", v, px, "wfe");
    if (isfinite(s->strehl)) snprintf(v, sizeof v, "%.3f", s->strehl);
    else snprintf(v, sizeof v, "n/a");
    row(b, "Strehl estimate (Maréchal)", v, px, "strehl");
    if (isfinite(s->err_rms)) {
        snprintf(v, sizeof v, "%.1f nm rms (true NCP %.1f nm rms, residual %.0f %%)", 1e9 * s->err_rms,
                 1e9 * s->ncp_rms, s->ncp_rms > 0 ? 100.0 * s->err_rms / s->ncp_rms : NAN);
        row(b, "recovery error WFE − true NCP (piston, tip/tilt removed)", v, px, "recovered-error");
    }
    if (isfinite(s->tau0_median)) {
        snprintf(v, sizeof v, "%.1f ms", 1e3 * s->tau0_median);
        row(b, "median speckle coherence time τ₀", v, px, "tau0");
    }
    if (s->pixel_i >= 0) {
        snprintf(v, sizeof v, "pixel (%ld, %ld): fitted %.2f rad, arg Ψ %.2f rad", s->pixel_i, s->pixel_j,
                 s->pixel_fit_phase, s->pixel_halo_phase);
        row(b, "halo phase check", v, px, "pixel-phase");
    }
    rep_printf(b, "</table>\n");
}

void rep_notes(rep_strbuf *b, const swfs_report_summary *s)
{
    if (!s->nnotes) return;
    rep_printf(b, "<h2>Notes</h2>\n<ul class=\"notes\">\n");
    for (size_t k = 0; k < s->nnotes; k++) {
        rep_printf(b, "<li>");
        rep_text(b, s->notes[k]);
        rep_printf(b, "</li>\n");
    }
    rep_printf(b, "</ul>\n");
}

/* A column name as a heading: a unit suffix becomes a bracket. */
static void heading(rep_strbuf *b, const char *name)
{
    static const struct { const char *suffix, *unit; } units[] = {{"_nm", "nm"}, {"_pct", "%"}, {"_s", "s"}};
    size_t n = strlen(name);
    for (size_t k = 0; k < sizeof units / sizeof units[0]; k++) {
        size_t m = strlen(units[k].suffix);
        if (n > m && !strcmp(name + n - m, units[k].suffix)) {
            char base[256];
            snprintf(base, sizeof base, "%.*s", (int)(n - m), name);
            rep_text(b, base);
            rep_printf(b, " [%s]", units[k].unit);
            return;
        }
    }
    rep_text(b, name);
}

void rep_table(rep_strbuf *b, const swfs_table *t, const char *id)
{
    rep_printf(b, "<div class=\"wide\"><table id=\"%s\">\n<tr>", id);
    for (size_t c = 0; c < t->ncols; c++) {
        rep_printf(b, "<th>");
        heading(b, t->names[c]);
        rep_printf(b, "</th>");
    }
    rep_printf(b, "</tr>\n");
    for (size_t r = 0; r < t->nrows; r++) {
        rep_printf(b, "<tr>");
        for (size_t c = 0; c < t->ncols; c++) {
            double v = t->v[r * t->ncols + c];
            if (isfinite(v)) rep_printf(b, "<td>%.4g</td>", v);
            else rep_printf(b, "<td>–</td>");
        }
        rep_printf(b, "</tr>\n");
    }
    rep_printf(b, "</table></div>\n");
}

static void page_head(rep_strbuf *b, const char *title)
{
    rep_printf(b, "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>");
    rep_text(b, title);
    rep_printf(b,
               "</title>\n<style>\n"
               "body{font-family:sans-serif;max-width:1200px;margin:1em auto;padding:0 1em;color:#222}\n"
               "table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #ccc;padding:.3em .8em;"
               "text-align:left}th{background:#f4f4f4}\n"
               "div.wide{overflow-x:auto}div.wide td{text-align:right}\n"
               "img{max-width:100%%;height:auto;border:1px solid #ddd}figcaption{color:#444;margin:.4em 0 1.5em}\n"
               ".notes li{color:#7a4b00}\n</style>\n"
               "<script>\n"
               "window.addEventListener('load', function () {\n"
               "  var imgs = document.images, ok = 0;\n"
               "  for (var i = 0; i < imgs.length; i++) if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++;\n"
               "  document.body.setAttribute('data-images-ok', String(ok));\n"
               "  document.body.setAttribute('data-images-total', String(imgs.length));\n"
               "});\n</script>\n</head>\n<body>\n<h1>");
    rep_text(b, title);
    rep_printf(b, "</h1>\n<p>Focal-plane wavefront sensing with residual AO speckles (Codona &amp; Kenworthy 2013). "
                  "specklewfs %s.</p>\n", SWFS_VERSION);
}

int rep_write_page(const char *out_dir, const char *title, const char *run_dir, const rep_strbuf *body,
                   swfs_report_summary *s)
{
    char path[REP_PATHMAX];
    int rc = rep_join(path, out_dir, "index.html");
    if (rc) return rc;
    rep_strbuf b = {0};
    page_head(&b, title);
    if (body->len) rep_printf(&b, "%s", body->s);
    time_t now = time(NULL);
    char date[64];
    struct tm tm;
    strftime(date, sizeof date, "%Y-%m-%d %H:%M:%S UTC", gmtime_r(&now, &tm));
    rep_printf(&b, "<hr><p><small>Products read from <code>");
    rep_text(&b, run_dir);
    rep_printf(&b, "</code> on %s by specklewfs %s.</small></p>\n</body>\n</html>\n", date, SWFS_VERSION);
    if (b.oom || body->oom) rc = swfs_fail(SWFS_ERR_NOMEM, "%s: out of memory", path);
    if (!rc) rc = swfs_text_write(path, b.s, b.len);
    free(b.s);
    if (!rc) snprintf(s->html, sizeof s->html, "%s", path);
    return rc;
}

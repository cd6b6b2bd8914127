#!/usr/bin/env bash
# specklewfs report: help, bad input answered with a clear error, a folder with nothing to
# report refused (figures of a run folder are covered by tests/test_report.c, which builds a
# synthetic run and loads the page in headless Chromium).
set -euo pipefail
bin=$1
tmp=$2
rm -rf "$tmp"
mkdir -p "$tmp/run"

help=$("$bin" report --help)
grep -q "REPORT_DIR" <<< "$help"

if "$bin" report "$tmp/missing" 2>"$tmp/err"; then echo "FAIL: missing run folder accepted"; exit 1; fi
grep -q "missing" "$tmp/err" || { echo "FAIL: error does not name the folder"; cat "$tmp/err"; exit 1; }

set +e
"$bin" report "$tmp/run" --bogus 2>"$tmp/err"
rc=$?
set -e
[ "$rc" -eq 2 ] || { echo "FAIL: unknown option exit $rc, expected 2"; exit 1; }

# A folder with nothing to report: exit 1, a message naming it and what was looked for, no page.
set +e
"$bin" report "$tmp/run" -o "$tmp/out/page" >"$tmp/out.txt" 2>"$tmp/err"
rc=$?
set -e
[ "$rc" -eq 1 ] || { echo "FAIL: empty run folder exit $rc, expected 1"; exit 1; }
grep -q "run: nothing to report" "$tmp/err" || { echo "FAIL: message"; cat "$tmp/err"; exit 1; }
grep -q "halo.fits" "$tmp/err" || { echo "FAIL: message does not say what was looked for"; cat "$tmp/err"; exit 1; }
test ! -e "$tmp/out/page/index.html"
test ! -e "$tmp/out/page/index.html.part"
echo "cli_report: ok"

# ---- a demo folder: one page for the whole demo
SMALL="screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24"
"$bin" demo -o "$tmp/demo" $SMALL --levels 0,100 --loop-iterations 1 >"$tmp/demo.txt" 2>"$tmp/demo.err" \
    || { echo "FAIL: demo"; cat "$tmp/demo.err"; exit 1; }
page="$tmp/demo/report/index.html"
test -s "$page" || { echo "FAIL: demo wrote no page"; exit 1; }
grep -q "figures: $page" "$tmp/demo.txt" || { echo "FAIL: demo does not name its page"; exit 1; }
# The table is the demo's: as many rows and columns as recovery.tsv, one section per level.
[ "$(grep -vc '^#' "$tmp/demo/recovery.tsv")" -eq 2 ] || { echo "FAIL: recovery.tsv rows"; exit 1; }
ncol=$(head -1 "$tmp/demo/recovery.tsv" | awk -F'\t' '{print NF}')
table=$(sed -n '/<table id="recovery">/,/<\/table>/p' "$page")
[ "$(grep -c '<tr><td>' <<<"$table")" -eq 2 ] || { echo "FAIL: recovery table rows"; exit 1; }
[ "$(grep -o '<th>' <<<"$table" | wc -l)" -eq "$ncol" ] || { echo "FAIL: recovery table columns"; exit 1; }
grep -q '<th>HALO_LF+SNR \[nm\]</th>' <<<"$table" || { echo "FAIL: estimator column heading"; exit 1; }
grep -q '<th>joint_fit \[nm\]</th>' <<<"$table" || { echo "FAIL: joint fit column heading"; exit 1; }
for s in 0 100; do
    grep -q "<section id=\"sigma$s\">" "$page" || { echo "FAIL: no section for sigma $s"; exit 1; }
    for f in halo focal pixel pupil; do
        grep -q "src=\"sigma$s/$f.png\"" "$page" || { echo "FAIL: sigma$s/$f.png not on the page"; exit 1; }
        test -s "$tmp/demo/report/sigma$s/$f.png" || { echo "FAIL: sigma$s/$f.png missing"; exit 1; }
    done
    # Each level's recovery error on the page is the demo table's joint fit column (wavefront.fits).
    want=$(awk -v s="$s" '$1 == s && $5 == "|" && $9 == "|" {print $10}' "$tmp/demo.txt")
    [ -n "$want" ] || { echo "FAIL: no demo row for sigma $s"; exit 1; }
    grep -q "<td id=\"sigma$s-recovered-error\">$want nm rms" "$page" \
        || { echo "FAIL: sigma $s recovery error on the page is not the table's $want nm"; exit 1; }
done
grep -q '<table id="loop-table">' "$page" || { echo "FAIL: no closed-loop table"; exit 1; }
grep -q 'src="loop.png"' "$page" && test -s "$tmp/demo/report/loop.png" || { echo "FAIL: no loop.png"; exit 1; }

# `report DEMO_DIR` draws the same page again; the figure count is every image on it.
"$bin" report "$tmp/demo" -o "$tmp/demo/page2" >"$tmp/out.txt" 2>"$tmp/err" || { cat "$tmp/err"; exit 1; }
nfig=$(sed -n 's/^report: \([0-9]*\) figures.*/\1/p' "$tmp/out.txt")
[ "$nfig" = 9 ] || { echo "FAIL: report of the demo folder drew '$nfig' figures, expected 9"; cat "$tmp/out.txt"; exit 1; }
[ "$(grep -c '<img ' "$tmp/demo/page2/index.html")" -eq 9 ] || { echo "FAIL: images on the page"; exit 1; }
if command -v chromium >/dev/null 2>&1; then
    dom=$(chromium --headless --no-sandbox --disable-gpu --disable-background-networking --no-first-run \
        --disable-dev-shm-usage --user-data-dir="$tmp/chromium" --virtual-time-budget=5000 \
        --dump-dom "file://$tmp/demo/page2/index.html" 2>/dev/null)
    grep -q 'data-images-ok="9"' <<<"$dom" && grep -q 'data-images-total="9"' <<<"$dom" \
        || { echo "FAIL: chromium did not load every image of the demo page"; grep -o '<body[^>]*>' <<<"$dom"; exit 1; }
else
    echo "cli_report: chromium is not on PATH: browser check of the demo page skipped"
fi
echo "cli_report: demo page ok"

# ---- the report's output checked before any work (outpaths.h), nothing left behind
touch "$tmp/afile"
if "$bin" report "$tmp/demo" -o "$tmp/afile" >"$tmp/out.txt" 2>"$tmp/err"; then echo "FAIL: report onto a file"; exit 1; fi
grep -q "is not a folder" "$tmp/err" || { echo "FAIL: report onto a file: message"; cat "$tmp/err"; exit 1; }
mkfifo "$tmp/afifo"
if "$bin" report "$tmp/demo" -o "$tmp/afifo" >"$tmp/out.txt" 2>"$tmp/err"; then echo "FAIL: report onto a FIFO"; exit 1; fi
mkdir -p "$tmp/linked" && ln -sf "$tmp/demo/recovery.tsv" "$tmp/linked/index.html"
if "$bin" report "$tmp/demo" -o "$tmp/linked" >"$tmp/out.txt" 2>"$tmp/err"; then echo "FAIL: report page onto a link"; exit 1; fi
grep -q "symbolic link" "$tmp/err" || { echo "FAIL: report page onto a link: message"; cat "$tmp/err"; exit 1; }
[ -z "$(ls "$tmp/linked" | grep -v '^index.html$')" ] || { echo "FAIL: a refused report left files"; ls "$tmp/linked"; exit 1; }
[ "$(ls "$tmp/demo/page2" | grep -c '\.part')" -eq 0 ] || { echo "FAIL: part files left in the report folder"; exit 1; }
echo "cli_report: output checks ok"

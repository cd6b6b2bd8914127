#!/usr/bin/env bash
# specklewfs report: help, bad input answered with a clear error, and a page for a run
# folder with no products (figures are covered by tests/test_report.c, which builds a
# synthetic run and loads the page in headless Chromium).
set -euo pipefail
bin=$1
tmp=$2
rm -rf "$tmp"
mkdir -p "$tmp/run"

"$bin" report --help | grep -q "REPORT_DIR"

if "$bin" report "$tmp/missing" 2>"$tmp/err"; then echo "FAIL: missing run folder accepted"; exit 1; fi
grep -q "missing" "$tmp/err" || { echo "FAIL: error does not name the folder"; cat "$tmp/err"; exit 1; }

set +e
"$bin" report "$tmp/run" --bogus 2>"$tmp/err"
rc=$?
set -e
[ "$rc" -eq 2 ] || { echo "FAIL: unknown option exit $rc, expected 2"; exit 1; }

"$bin" report "$tmp/run" -o "$tmp/out/page" >"$tmp/out.txt" 2>"$tmp/err"
test -s "$tmp/out/page/index.html"
grep -q "halo.fits not found" "$tmp/out/page/index.html"
grep -q "index.html" "$tmp/out.txt"
test ! -e "$tmp/out/page/index.html.part"
echo "cli_report: ok"

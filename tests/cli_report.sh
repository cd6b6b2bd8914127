#!/usr/bin/env bash
# specklewfs report: help, bad input answered with a clear error, a folder with nothing to
# report refused (figures of a run folder are covered by tests/test_report.c, which builds a
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

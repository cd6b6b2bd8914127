#!/bin/bash
# specklewfs simulate|correct --sweep: one row per parameter set in DIR/sweep.tsv, the same
# numbers as the set run on its own, and clear errors for bad sets (one process; the
# distributed sweep is in tests/mpi/).
set -u
BIN=$1
DIR=$2
rm -rf "$DIR"
mkdir -p "$DIR"
fail() { echo "FAIL: $*"; exit 1; }
SMALL="screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24 ncp_gauss_x=-0.4 ncp_gauss_y=0.8 ncp_gauss_radius=0.4 threads=1"

cat > "$DIR/sets.txt" <<'SETS'
# read noise at two seeds
read_noise=0 seed=1
read_noise=100 seed=1   # same turbulence, more noise

read_noise=100 seed=2
SETS
"$BIN" simulate $SMALL --sweep "$DIR/sets.txt" -o "$DIR/sim" > "$DIR/sim.txt" 2>&1 || { cat "$DIR/sim.txt"; fail "simulate --sweep"; }
T="$DIR/sim/sweep.tsv"
[ -f "$T" ] || fail "no sweep.tsv"
[ "$(grep -v '^#' "$T" | wc -l)" -eq 4 ] || { cat "$T"; fail "expected a header and 3 rows"; }
col() { awk -F'\t' -v c="$1" -v r="$2" 'BEGIN{n=-1} /^#/ {next} { n++; if (n == 0) { for (i = 1; i <= NF; i++) if ($i == c) k = i; next } if (n - 1 == r) print $k }' "$3"; }
# same seed: the same turbulence (AO residual), less valid pixels and a larger error with noise
[ "$(col residual_nm 0 "$T")" = "$(col residual_nm 1 "$T")" ] || fail "sets 0 and 1 share seed=1 but not the AO residual"
[ "$(col residual_nm 0 "$T")" != "$(col residual_nm 2 "$T")" ] || fail "seed=2 gave the same AO residual"
awk -v a="$(col valid 0 "$T")" -v b="$(col valid 1 "$T")" 'BEGIN { exit !(a > b) }' || fail "read noise did not lower the valid fraction"
[ "$(col params 1 "$T")" = "read_noise=100 seed=1" ] || fail "params column: '$(col params 1 "$T")'"
# a row equals the set run on its own (simulate writes the data; its error is the default estimate's)
"$BIN" simulate $SMALL read_noise=100 seed=2 --sweep /dev/stdin -o "$DIR/one" <<< "" > /dev/null 2>&1 && fail "empty sets file accepted"
printf 'read_noise=100 seed=2\n' > "$DIR/one.txt"
"$BIN" simulate $SMALL --sweep "$DIR/one.txt" -o "$DIR/one" > /dev/null 2>&1 || fail "one-set sweep"
[ "$(col err_nm 0 "$DIR/one/sweep.tsv")" = "$(col err_nm 2 "$T")" ] || fail "set 2 alone gives another error"

# correct: the loop settings per set
printf 'loop_iterations=1 loop_gain=0.5\nloop_iterations=1 loop_gain=1 seed=2\n' > "$DIR/loop.txt"
"$BIN" correct $SMALL --sweep "$DIR/loop.txt" -o "$DIR/loop" > "$DIR/loop.out" 2>&1 || { cat "$DIR/loop.out"; fail "correct --sweep"; }
L="$DIR/loop/sweep.tsv"
[ "$(grep -v '^#' "$L" | wc -l)" -eq 3 ] || { cat "$L"; fail "expected a header and 2 rows"; }
awk -v a="$(col resid0_nm 0 "$L")" -v b="$(col resid_nm 0 "$L")" 'BEGIN { exit !(b < a) }' || fail "the loop did not lower the residual"

# bad sets: the file and line named, nothing written
printf 'seed=1\nread_noise=10 r00=0.2\n' > "$DIR/bad.txt"
"$BIN" simulate $SMALL --sweep "$DIR/bad.txt" -o "$DIR/bad" > "$DIR/err.txt" 2>&1 && fail "unknown key accepted"
grep -q "bad.txt:2" "$DIR/err.txt" && grep -q "r00" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "message lacks file:line and key"; }
[ -f "$DIR/bad/sweep.tsv" ] && fail "a table was written for bad sets"
printf 'seed=1\nread_noise 10\n' > "$DIR/bad2.txt"
"$BIN" simulate $SMALL --sweep "$DIR/bad2.txt" -o "$DIR/bad" > "$DIR/err.txt" 2>&1 && fail "malformed set accepted"
grep -q "bad2.txt:2: 'read_noise' is not key=value" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "malformed-set message"; }
printf 'loop_gain=0.5\n' > "$DIR/bad3.txt"
"$BIN" simulate $SMALL --sweep "$DIR/bad3.txt" -o "$DIR/bad" > "$DIR/err.txt" 2>&1 && fail "loop key accepted by simulate"
grep -q "loop_gain" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "loop key message"; }
echo "cli_sweep: ok"

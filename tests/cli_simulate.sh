#!/bin/bash
# specklewfs simulate end to end at reduced size: files, shapes, keywords, errors.
set -u
BIN=$1
DIR=$2
SRC=$(cd "$(dirname "$0")/.." && pwd)
rm -rf "$DIR"
mkdir -p "$DIR"
fail() { echo "FAIL: $*"; exit 1; }

# FITS header card value: card KEY FILE -> value (first occurrence, primary or extension)
card() { head -c 200000 "$2" | fold -w 80 | grep -a -m1 "^$1 *=" | sed -e 's/^[^=]*= *//' -e 's/ *\/.*//' -e "s/'//g" -e 's/ *$//'; }

SMALL="screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24 ncp_gauss_x=-0.4 ncp_gauss_y=0.8 ncp_gauss_radius=0.4"

# 1. the shipped config with small-size overrides
"$BIN" simulate "$SRC/config/paper-sec3.conf" $SMALL read_noise=10 -o "$DIR/run" --seed 3 --quiet > "$DIR/out.txt" 2> "$DIR/err.txt" \
    || { cat "$DIR/err.txt"; fail "simulate exited non-zero"; }
cat "$DIR/out.txt"
for f in science speckles truth pupil; do
    [ -s "$DIR/run/$f.fits" ] || fail "$f.fits missing"
    [ -e "$DIR/run/$f.fits.part" ] && fail "$f.fits.part left behind"
done
grep -q "32 frames" "$DIR/out.txt" || fail "summary does not report 32 frames (2 screens x 4 x 4)"
grep -q "AO residual" "$DIR/out.txt" || fail "summary lacks the AO residual"
S="$DIR/run/science.fits"
[ "$(card NAXIS "$S")" = 3 ] || fail "science NAXIS $(card NAXIS "$S")"
[ "$(card NAXIS1 "$S")" = 32 ] || fail "science NAXIS1 $(card NAXIS1 "$S")"
[ "$(card NAXIS2 "$S")" = 24 ] || fail "science NAXIS2 $(card NAXIS2 "$S")"
[ "$(card NAXIS3 "$S")" = 32 ] || fail "science NAXIS3 $(card NAXIS3 "$S")"
[ "$(card RDNOISE "$S")" = 10 ] || [ "$(card RDNOISE "$S")" = 10. ] || [ "$(card RDNOISE "$S")" = 1.0E+01 ] \
    || fail "science RDNOISE $(card RDNOISE "$S")"
[ -n "$(card GAIN "$S")" ] || fail "science GAIN missing"
for k in WAVELEN TELDIAM OBSCUR PIXSCALE PUPDX PUPN; do
    [ -n "$(card $k "$S")" ] || fail "science.fits lacks $k"
    [ -n "$(card $k "$DIR/run/speckles.fits")" ] || fail "speckles.fits lacks $k"
done
[ "$(card PUPN "$S")" = 64 ] || fail "PUPN $(card PUPN "$S")"
P="$DIR/run/speckles.fits"
[ "$(card NAXIS "$P")" = 4 ] || fail "speckles NAXIS $(card NAXIS "$P")"
[ "$(card NAXIS1 "$P")" = 2 ] || fail "speckles NAXIS1 $(card NAXIS1 "$P")"
[ "$(card CTYPE1 "$P")" = COMPLEX ] || fail "speckles CTYPE1 $(card CTYPE1 "$P")"
[ "$(card NAXIS4 "$P")" = 32 ] || fail "speckles NAXIS4 $(card NAXIS4 "$P")"
grep -aq "EXTNAME = 'NCP" "$DIR/run/truth.fits" || fail "truth.fits lacks NCP"
grep -aq "EXTNAME = 'HALO" "$DIR/run/truth.fits" || fail "truth.fits lacks HALO"
head -c 200000 "$S" | fold -w 80 | grep -aq "HISTORY.*sim: target_rms" || fail "science.fits lacks parameter HISTORY"

# 2. same seed -> identical science cube; the seed changes it
"$BIN" simulate $SMALL read_noise=10 -o "$DIR/run2" --seed 3 --quiet > /dev/null 2>&1 || fail "second run"
cmp -s <(tail -c +20000 "$DIR/run/science.fits") <(tail -c +20000 "$DIR/run2/science.fits") || fail "same seed, different science data"
"$BIN" simulate $SMALL read_noise=10 -o "$DIR/run3" --seed 4 --quiet > /dev/null 2>&1 || fail "third run"
cmp -s <(tail -c +20000 "$DIR/run/science.fits") <(tail -c +20000 "$DIR/run3/science.fits") && fail "seed has no effect"

# 3. errors: unknown key (named), bad value (named), missing -o, missing config file
"$BIN" simulate $SMALL tel_diam=6.5 -o "$DIR/bad" 2> "$DIR/err.txt" && fail "unknown key accepted"
grep -q "tel_diam" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "unknown key not named"; }
[ -e "$DIR/bad/science.fits" ] && fail "output written despite a bad key"
"$BIN" simulate $SMALL pupn=many -o "$DIR/bad" 2> "$DIR/err.txt" && fail "bad value accepted"
grep -q "pupn" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "bad value not named"; }
"$BIN" simulate $SMALL target_rms=1e-9 -o "$DIR/bad" 2> "$DIR/err.txt" && fail "impossible target accepted"
grep -q "lag" "$DIR/err.txt" || { cat "$DIR/err.txt"; fail "lag-floor message missing"; }
"$BIN" simulate $SMALL 2> "$DIR/err.txt" && fail "missing -o accepted"
grep -q -- "-o" "$DIR/err.txt" || fail "missing -o not explained"
"$BIN" simulate "$DIR/no-such.conf" -o "$DIR/bad" 2> "$DIR/err.txt" && fail "missing config accepted"
grep -q "no-such.conf" "$DIR/err.txt" || fail "missing config not named"
"$BIN" simulate --help | grep -q "science.fits" || fail "--help"
echo "cli_simulate: ok"

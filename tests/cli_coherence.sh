#!/usr/bin/env bash
# specklewfs coherence end to end on a hand-made FITS cube with known answers, plus the
# analytic limits and the error paths. Usage: cli_coherence.sh <specklewfs> <scratch dir>
set -euo pipefail
BIN=$1
DIR=$2
mkdir -p "$DIR"
cd "$DIR"
rm -f in.fits nodt.fits coh.fits ./*.part

fail() { echo "FAIL: $*" >&2; exit 1; }

# A complex float32 cube (NAXIS1 = 2 'COMPLEX', 2 x 2 pixels, 8 frames), written byte by byte:
#   (0,0) and (1,1): psi = i^t      -> Gamma(tau)/Gamma(0) = i^-tau, PHRATE = -(pi/2)/FRAMEDT
#   (0,1):           psi = (-i)^t   -> PHRATE = +(pi/2)/FRAMEDT
#   (1,0):           0              -> no speckle power: NaN, counted
# so TROT = FRAMEDT exactly, |Gamma| = 1 (tau0 beyond every lag) and the SNR factor of a
# 2-frame exposure is (1/2)(1 + Re i^-1) = 0.5.
write_fits() { # $1 = file, $2 = 1 to include FRAMEDT
  {
    n=0
    card() { printf '%-80s' "$1"; n=$((n + 1)); }
    kv() { card "$(printf '%-8s= %20s' "$1" "$2")"; }
    kv SIMPLE T; kv BITPIX -32; kv NAXIS 4; kv NAXIS1 2; kv NAXIS2 2; kv NAXIS3 2; kv NAXIS4 8
    card "CTYPE1  = 'COMPLEX '"
    [ "$2" = 1 ] && kv FRAMEDT 0.001
    kv TELDIAM 6.5; kv PIXSCALE 0.25; kv WAVELEN 3.8E-06
    card END
    while [ $((n % 36)) -ne 0 ]; do card ""; done
    one='\x3f\x80\x00\x00'; neg='\xbf\x80\x00\x00'; zero='\x00\x00\x00\x00'
    p=("$one$zero" "$zero$one" "$neg$zero" "$zero$neg") # i^t for t mod 4 = 0..3
    for t in 0 1 2 3 4 5 6 7; do
      a=${p[$((t % 4))]}; b=${p[$(((4 - t % 4) % 4))]}
      printf "$a$zero$zero$b$a" # (0,0) (1,0) | (0,1) (1,1)   [y = 0 row, then y = 1]
    done
    for ((k = 0; k < 2880 - 256; k++)); do printf '\x00'; done
  } > "$1"
}
write_fits in.fits 1
write_fits nodt.fits 0
[ "$(stat -c %s in.fits)" -eq 5760 ] || fail "hand-made FITS has the wrong size"

help=$("$BIN" coherence --help)
grep -q "eq:MutualCoh" <<< "$help" || fail "--help"

# The paper's number: 6 lambda/D, D = 6.5 m, 10 m/s -> about 54 ms (18.5 frames/s).
out=$("$BIN" coherence --wind 10 --diam 6.5 --bandwidth 0.2)
grep -q "54.2 ms at 6 lambda/D" <<< "$out" || fail "wind exposure limit: $out"
grep -q "18.5 frames/s" <<< "$out" || fail "frame rate: $out"
grep -q "5.00 lambda/D" <<< "$out" || fail "bandwidth radius: $out"

out=$("$BIN" coherence in.fits -o coh.fits --exposure 0.002 --pixel 0,0 --wind 10)
echo "$out"
[ -f coh.fits ] && [ ! -f coh.fits.part ] || fail "COH.fits not written"
grep -q "3 with speckle power; NaN: 1 without speckle power, 0 non-finite" <<< "$out" || fail "NaN count"
grep -q "median TROT            1.00 ms" <<< "$out" || fail "TROT"
grep -q "median SNR factor      0.5000 at exposure 2 ms" <<< "$out" || fail "SNR factor"
grep -q "3 pixels beyond" <<< "$out" || fail "tau0 beyond the lags"
grep -q "54.2 ms" <<< "$out" || fail "wind limit from TELDIAM"
echo "$out" | grep -Eq "^ +1 +1.0000 +0.000000 +-1.000000 +1.000000 +-90.000" || fail "--pixel table lag 1"
echo "$out" | grep -Eq "^ +7 " || fail "--pixel table stops at lag 7"
grep -q "PHRATE -1571 rad/s" <<< "$out" || fail "signed phase rate"
# --exposure none: no SNR_FACT, said so
out=$("$BIN" coherence in.fits -o cohn.fits --exposure none)
grep -q "SNR factor             none (--exposure none)" <<< "$out" && ! grep -aq "EXTNAME = 'SNR_FACT" cohn.fits \
    || fail "--exposure none: $out"

# Error paths: one line naming the file or value, non-zero exit.
set +e
err=$("$BIN" coherence nodt.fits -o x.fits 2>&1); rc=$?
[ $rc -ne 0 ] && grep -q "nodt.fits: missing keyword FRAMEDT" <<< "$err" || fail "missing FRAMEDT: $err"
err=$("$BIN" coherence missing.fits -o x.fits 2>&1); rc=$?
[ $rc -ne 0 ] && grep -q "missing.fits" <<< "$err" || fail "missing file: $err"
err=$("$BIN" coherence in.fits -o x.fits --pixel 2,0 2>&1); rc=$?
[ $rc -eq 2 ] && grep -q "outside the 2x2 image" <<< "$err" || fail "--pixel out of range: $err"
err=$("$BIN" coherence in.fits -o x.fits --pixel 1 2>&1); rc=$?
[ $rc -eq 2 ] || fail "--pixel without Y: $err"
err=$("$BIN" coherence in.fits -o x.fits --exposure 0.02 2>&1); rc=$?
[ $rc -ne 0 ] && grep -q "8 frames" <<< "$err" || fail "exposure longer than the cube: $err"
err=$("$BIN" coherence in.fits 2>&1); rc=$?
[ $rc -eq 2 ] || fail "missing -o"
err=$("$BIN" coherence --wind 10 2>&1); rc=$?
[ $rc -eq 2 ] && grep -q "diam" <<< "$err" || fail "limits without --diam: $err"
set -e
[ ! -f x.fits ] && [ ! -f x.fits.part ] || fail "a failed run left an output file"
echo "cli_coherence: OK"

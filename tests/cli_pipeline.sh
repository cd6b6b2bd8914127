#!/bin/bash
# The documented command-line pipeline on a reduced-size Sec. 3 data set:
# simulate -> estimate -> pupil --truth, and the recovered NCP error it reports.
set -u
BIN=$1
DIR=$2
rm -rf "$DIR"
mkdir -p "$DIR"
fail() { echo "FAIL: $*"; exit 1; }

"$BIN" simulate screen_n=1024 nscreens=3 read_noise=10 -o "$DIR/run" --seed 5 --quiet > "$DIR/sim.txt" 2>&1 \
    || { cat "$DIR/sim.txt"; fail "simulate"; }
"$BIN" estimate "$DIR/run/science.fits" "$DIR/run/speckles.fits" -o "$DIR/run/halo.fits" > "$DIR/est.txt" 2>&1 \
    || { cat "$DIR/est.txt"; fail "estimate"; }
cat "$DIR/est.txt"
grep -q "read noise 10 counts, gain 1 e-/count" "$DIR/est.txt" || fail "estimate did not take the noise model from the science header"
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/run/wavefront.fits" --truth "$DIR/run/truth.fits" > "$DIR/pupil.txt" 2>&1 \
    || { cat "$DIR/pupil.txt"; fail "pupil"; }
cat "$DIR/pupil.txt"
err=$(sed -n 's/.*error \([0-9.]*\) nm rms.*/\1/p' "$DIR/pupil.txt")
inj=$(sed -n 's/.*injected \([0-9.]*\) nm rms.*/\1/p' "$DIR/pupil.txt")
[ -n "$err" ] && [ -n "$inj" ] || fail "pupil --truth printed no comparison"
# 147 frames instead of the paper's 980: the error must still be a small fraction of the NCP.
awk -v e="$err" -v i="$inj" 'BEGIN { exit !(e < 0.3 * i && i > 100) }' || fail "NCP error $err nm for $inj nm injected"
[ -e "$DIR/run/wavefront.fits.part" ] && fail "partial file left behind"
grep -q "method            joint fit" "$DIR/pupil.txt" || fail "the default pupil step is not the joint fit"

# The moments, one option away, and the same implied by a moments-only option; the joint fit
# must beat them on the same halo.
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/run/wf_m.fits" --method moments --truth "$DIR/run/truth.fits" > "$DIR/pm.txt" 2>&1 \
    || { cat "$DIR/pm.txt"; fail "pupil --method moments"; }
grep -q "method            moments: source HALO_LF, weight snr" "$DIR/pm.txt" || fail "--method moments: $(cat "$DIR/pm.txt")"
errm=$(sed -n 's/.*error \([0-9.]*\) nm rms.*/\1/p' "$DIR/pm.txt")
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/run/wf_h.fits" --source halo > "$DIR/ph.txt" 2>&1 || fail "pupil --source halo"
grep -q "moments: source HALO," "$DIR/ph.txt" || fail "--source did not imply the moments"
awk -v e="$err" -v m="$errm" 'BEGIN { exit !(e < m) }' || fail "joint fit $err nm not better than the moments $errm nm"
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/x.fits" --method fit --weight none > "$DIR/bad.txt" 2>&1; [ $? -eq 2 ] \
    || fail "--method fit with --weight: exit code"
grep -q "apply to --method moments" "$DIR/bad.txt" || fail "no message for --method fit --weight"

# Bad input: a halo without geometry, a truth of the wrong size, a missing file.
"$BIN" pupil "$DIR/run/science.fits" -o "$DIR/x.fits" > "$DIR/bad.txt" 2>&1 && fail "pupil accepted a science cube"
grep -q "HALO" "$DIR/bad.txt" || fail "no message naming the missing HALO extension: $(cat "$DIR/bad.txt")"
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/x.fits" --truth "$DIR/run/halo.fits" > "$DIR/bad.txt" 2>&1 && fail "pupil accepted a truth without NCP"
grep -q "NCP" "$DIR/bad.txt" || fail "no message naming NCP"
[ -e "$DIR/x.fits" ] && fail "output written although the run failed"
"$BIN" pupil "$DIR/nope.fits" -o "$DIR/x.fits" > "$DIR/bad.txt" 2>&1; [ $? -eq 1 ] || fail "missing file: exit code"
"$BIN" pupil "$DIR/run/halo.fits" -o "$DIR/x.fits" --weight maybe > "$DIR/bad.txt" 2>&1; [ $? -eq 2 ] || fail "bad --weight: exit code"
echo "cli_pipeline: NCP error $err nm (joint fit), $errm nm (moments) for $inj nm injected"
echo "1 passed, 0 failed"

#!/bin/bash
# The reliability classes across the commands (docs/reliability.md): an output naming an
# input or another output, special files (FIFO, device, symbolic link) as inputs and
# outputs, extreme and mistyped keyword values, all-NaN and overflowing data, compressed
# inputs (fpack tile compression, gzip), literal output names, bounded search grids and
# layouts, wrong-file blame, and that a refused run changes no file.
# usage: bash cli_reliability.sh <specklewfs> <scratch dir>
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
B=$(cd "$(dirname "$1")" && pwd)/$(basename "$1")
FITSCOPY=$(dirname "$B")/tests/fitscopy
D=$2
rm -rf "$D"
mkdir -p "$D"
cd "$D" || exit 1
PY=/usr/bin/python3
hdr() { "$PY" "$HERE/tools/fitshdr.py" "$@"; }
pass=0
nfail=0
bad() { echo "FAIL $1: $2"; sed 's/^/    /' err.txt 2> /dev/null | head -3; nfail=$((nfail + 1)); }

# expect NAME RC PHRASE -- ARGS...: exit code RC within 60 s (a hang fails), PHRASE on stderr.
expect() {
    local name=$1 want=$2 phrase=$3
    shift 4
    timeout 60 "$B" "$@" > out.txt 2> err.txt
    local rc=$?
    if [ "$rc" = 124 ]; then bad "$name" "no answer within 60 s"
    elif [ "$rc" != "$want" ]; then bad "$name" "exit code $rc, expected $want"
    elif [ -n "$phrase" ] && ! grep -qF -- "$phrase" err.txt; then bad "$name" "message lacks '$phrase'"
    else pass=$((pass + 1)); fi
}
# same NAME FILE -- ARGS...: the run must refuse (exit 1, "same file") and leave FILE as it was.
same() {
    local name=$1 file=$2
    shift 3
    local before
    before=$(md5sum < "$file")
    expect "$name" 1 "same file" -- "$@"
    [ "$(md5sum < "$file")" = "$before" ] || bad "$name" "$file was changed"
    ls ./*.part.* */*.part.* > /dev/null 2>&1 && bad "$name" "part file left behind"
}
setup_fail() { echo "FAIL setup: $*"; exit 1; }

# ---- inputs (small: a few seconds)
SMALL="screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24"
"$B" simulate $SMALL read_noise=10 -o run --seed 3 --quiet > /dev/null 2>&1 || setup_fail "simulate"
"$B" estimate run/science.fits run/speckles.fits -o run/halo.fits > /dev/null 2>&1 || setup_fail "estimate"
"$B" pupil run/halo.fits -o run/wf.fits > wf.txt 2>&1 || setup_fail "pupil"
TS="pupn=66 pupdx=0.1 screen_n=256 wfs_file_frames=1000"
"$B" simulate mode=timeseries $TS ncubes=2 cube_frames=20 cube_gap=10 seed=1 --quiet -o ts > /dev/null 2>&1 \
    || setup_fail "simulate mode=timeseries"
"$B" reduce ts/raw_000.fits ts/raw_001.fits --dark ts/dark.fits --flat ts/flat.fits -o sci.fits > /dev/null 2>&1 \
    || setup_fail "reduce"
"$B" sync sci.fits ts/handshake.log -o timing.txt --ratio-min 5 --ratio-max 8 > /dev/null 2>&1 || setup_fail "sync"
"$B" speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o spw.fits --wfs-rate --recon vk > /dev/null 2>&1 \
    || setup_fail "speckles"
STREAM="--timing timing.txt --science sci.fits --slopes ts --recon ts/recon_ao.fits --actuators ts/actuators.fits"
"$B" stream $STREAM -o sh.fits --checkpoint ck1.fits --max-frames 20 > /dev/null 2>&1 || setup_fail "stream"
cp ck1.fits ck2.fits
"$B" dmoffsets run/wf.fits -o off.fits --hexapolar 0.35 > /dev/null 2>&1 || setup_fail "dmoffsets"
echo "seed = 3" > conf.txt
R=ts/raw_000.fits
H=ts/handshake.log
SLOPES=ts/slopes_000.fits

# ---- an output naming an input, or two outputs one file: refused before any work
mkdir -p run2 && echo "seed = 3" > run2/science.fits
same simulate-config run2/science.fits -- simulate run2/science.fits $SMALL -o run2 --quiet
mkdir -p tso && echo "seed = 1" > tso/raw_001.fits
same ts-config tso/raw_001.fits -- simulate mode=timeseries tso/raw_001.fits $TS ncubes=2 cube_frames=20 -o tso --quiet
mkdir -p cor && echo "seed = 1" > cor/loop.tsv
same correct-config cor/loop.tsv -- correct cor/loop.tsv $SMALL -o cor --iterations 1
mkdir -p dem/sigma0 && echo "seed = 1" > dem/sigma0/halo.fits
same demo-config dem/sigma0/halo.fits -- demo dem/sigma0/halo.fits $SMALL -o dem --levels 0 --no-report
same estimate-science run/science.fits -- estimate run/science.fits run/speckles.fits -o run/science.fits
same estimate-speckles run/speckles.fits -- estimate run/science.fits run/speckles.fits -o ./run/speckles.fits
same pupil-halo run/halo.fits -- pupil run/halo.fits -o run/halo.fits
same pupil-mask run/pupil.fits -- pupil run/halo.fits --pupil run/pupil.fits -o run/pupil.fits
same pupil-truth run/truth.fits -- pupil run/halo.fits --truth run/truth.fits -o run/truth.fits
same reduce-raw ts/raw_001.fits -- reduce $R ts/raw_001.fits -o ts/raw_001.fits
same reduce-dark ts/dark.fits -- reduce $R --dark ts/dark.fits -o ts/dark.fits
same reduce-flat ts/flat.fits -- reduce $R --flat ts/flat.fits -o ts/flat.fits
same sync-science sci.fits -- sync sci.fits $H -o sci.fits
same sync-log $H -- sync sci.fits $H -o $H
same sync-telemetry $SLOPES -- sync sci.fits $H -o $SLOPES
same speckles-timing timing.txt -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o timing.txt
same speckles-science sci.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o sci.fits
same speckles-act ts/actuators.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits \
    -o ts/actuators.fits
same speckles-tel $SLOPES -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o $SLOPES
same speckles-recon ts/recon_ao.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits \
    --recon ts/recon_ao.fits -o ts/recon_ao.fits
same speckles-write-recon sci.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o x.fits \
    --write-recon x.fits
same speckles-match sci.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o x.fits \
    --match sci.fits sci.fits
same speckles-match-out sci.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o x.fits \
    --match sci.fits x.fits
for f in timing.txt sci.fits ts/recon_ao.fits ts/actuators.fits $SLOPES; do
    same "stream-o-$(basename $f)" $f -- stream $STREAM -o $f
    same "stream-ckpt-$(basename $f)" $f -- stream $STREAM -o x.fits --checkpoint $f
done
same stream-o-ckpt sci.fits -- stream $STREAM -o x.fits --checkpoint x.fits
same stream-pupil-ckpt sci.fits -- stream $STREAM -o x.fits --pupil-out y.fits --checkpoint ./y.fits
same stream-static sh.fits -- stream $STREAM -o x.fits --static sh.fits --static-out sh.fits
same merge-o ck1.fits -- merge ck1.fits ck2.fits -o ck1.fits
same merge-halo ck2.fits -- merge ck1.fits ck2.fits -o x.fits --halo ck2.fits
same merge-o-halo ck1.fits -- merge ck1.fits ck2.fits -o x.fits --halo x.fits
same coherence-o spw.fits -- coherence spw.fits -o spw.fits
same dmoffsets-o run/wf.fits -- dmoffsets run/wf.fits -o run/wf.fits --hexapolar 0.35
same dmoffsets-act ts/actuators.fits -- dmoffsets run/wf.fits -o ts/actuators.fits --actuators ts/actuators.fits
ln -f run/halo.fits hardlink.fits
same pupil-hardlink run/halo.fits -- pupil run/halo.fits -o hardlink.fits

# ---- special files: a FIFO as any input is refused at once; FIFO, device, link outputs too
mkfifo fifo.fits
expect fifo-estimate 1 "is a FIFO" -- estimate fifo.fits run/speckles.fits -o x.fits
expect fifo-pupil 1 "is a FIFO" -- pupil fifo.fits -o x.fits
expect fifo-pupil-mask 1 "is a FIFO" -- pupil run/halo.fits --pupil fifo.fits -o x.fits
expect fifo-reduce 1 "is a FIFO" -- reduce fifo.fits -o x.fits
expect fifo-reduce-dark 1 "is a FIFO" -- reduce $R --dark fifo.fits -o x.fits
expect fifo-sync 1 "is a FIFO" -- sync sci.fits fifo.fits -o x.txt
expect fifo-speckles 1 "is a FIFO" -- speckles fifo.fits --science sci.fits --actuators ts/actuators.fits -o x.fits
expect fifo-speckles-act 1 "is a FIFO" -- speckles timing.txt --science sci.fits --actuators fifo.fits -o x.fits
expect fifo-stream 1 "is a FIFO" -- stream --timing timing.txt --science fifo.fits --recon ts/recon_ao.fits \
    --actuators ts/actuators.fits -o x.fits
expect fifo-stream-slopes 1 "is a FIFO" -- stream $STREAM --slopes fifo.fits -o x.fits
expect fifo-merge 1 "is a FIFO" -- merge fifo.fits ck1.fits -o x.fits
expect fifo-coherence 1 "is a FIFO" -- coherence fifo.fits -o x.fits
expect fifo-dmoffsets 1 "is a FIFO" -- dmoffsets fifo.fits -o x.fits --hexapolar 0.35
expect fifo-simulate 1 "is a FIFO" -- simulate fifo.fits -o fo --quiet
expect fifo-correct 1 "is a FIFO" -- correct $SMALL -o fo --actuators fifo.fits
expect fifo-report 1 "fifo.fits" -- report fifo.fits
ln -s run/halo.fits link.fits
expect out-fifo 1 "is a FIFO" -- pupil run/halo.fits -o fifo.fits
expect out-link 1 "is a symbolic link" -- pupil run/halo.fits -o link.fits
expect out-device 1 "is a character device" -- pupil run/halo.fits -o /dev/null
expect out-folder 1 "is a folder" -- pupil run/halo.fits -o run
[ -p fifo.fits ] && [ -L link.fits ] && [ -c /dev/null ] && pass=$((pass + 1)) || bad special "a special file was replaced"
expect out-nodir 1 "folder nodir: No such file or directory" -- stream $STREAM -o nodir/h.fits
expect out-notdir 1 "(folder conf.txt: Not a directory)" -- pupil run/halo.fits -o conf.txt/x.fits

# ---- output names are taken literally; names that read as compressed are refused
expect out-gz 1 "a name ending in .gz is read as a compressed file" -- pupil run/halo.fits -o x.fits.gz
expect out-fz 1 "ending in .fz" -- estimate run/science.fits run/speckles.fits -o x.fits.fz
"$B" pupil run/halo.fits -o 'o[1].fits' > /dev/null 2> err.txt && [ -f 'o[1].fits' ] && [ ! -e o ] \
    && "$B" dmoffsets 'o[1].fits' -o 'p[2].fits' --hexapolar 0.35 > /dev/null 2>&1 && [ -f 'p[2].fits' ] \
    && pass=$((pass + 1)) || bad literal-names "o[1].fits was not written and read under that name"

# ---- extreme keyword values (header cards edited byte for byte)
LONG=$(printf '9%.0s' $(seq 1 69))
for v in $LONG 2147483648 4294967296 3037000500 0 -5 1.5 T "'64'"; do
    hdr run/halo.fits k.fits --hdu 2 "PUPN=$v"
    expect "pupn-$v" 1 "k.fits: PUPN = " -- pupil k.fits -o x.fits
done
hdr run/speckles.fits kp.fits PUPN=$LONG
expect pupn-long-estimate 1 "kp.fits: PUPN = 1.0000000000000001e+69" -- estimate run/science.fits kp.fits -o x.fits
hdr run/speckles.fits kp.fits PUPN=2147483648
expect pupn-big-estimate 1 "kp.fits: PUPN = 2147483648" -- estimate run/science.fits kp.fits -o x.fits
hdr run/science.fits ks.fits RDNOISE=$LONG
expect rdnoise-long-estimate 1 "ks.fits: read noise RDNOISE = 1e+69 counts is outside" -- \
    estimate ks.fits run/speckles.fits -o x.fits
hdr sci.fits kq.fits PUPN=3037000500
expect pupn-speckles 1 "kq.fits: PUPN = 3037000500" -- speckles timing.txt --science kq.fits \
    --actuators ts/actuators.fits -o x.fits
for kv in "WAVELEN=1E300:WAVELEN = 1e+300 is outside" "WAVELEN=T:WAVELEN = T is a logical" \
    "WAVELEN=-1:WAVELEN = -1 is outside" "PIXSCALE=1E-300:PIXSCALE = 1e-300" "PIXSCALE=0:PIXSCALE = 0 is outside" \
    "PIXSCALE=1E300:PIXSCALE = 1e+300" "TELDIAM=1E9:TELDIAM = 1e+09" "OBSCUR=1.5:OBSCUR = 1.5" \
    "PUPDX=1E9:PUPDX = 1e+09" "WAVELEN=1E999:WAVELEN = 1E999 is not a finite number" \
    "WAVELEN=(1,2):WAVELEN = (1,2) is a complex value"; do
    hdr run/halo.fits k.fits --hdu 2 "${kv%%:*}"
    expect "pupil-${kv%%:*}" 1 "k.fits: ${kv#*:}" -- pupil k.fits -o x.fits
done
hdr run/wf.fits kw.fits --hdu 3 TELDIAM=1E9 PUPDX=1E9
expect dm-teldiam 1 "kw.fits: TELDIAM = 1e+09" -- dmoffsets kw.fits -o x.fits --hexapolar 0.35
hdr sci.fits kg.fits GAIN=1E-300
expect stream-gain 1 "kg.fits: GAIN = 1e-300 e-/count is outside" -- stream --timing timing.txt --science kg.fits \
    --slopes ts --recon ts/recon_ao.fits --actuators ts/actuators.fits -o x.fits
hdr run/science.fits kr.fits RDNOISE=-4
expect estimate-rdnoise 1 "kr.fits: read noise RDNOISE = -4" -- estimate kr.fits run/speckles.fits -o x.fits
hdr sci.fits kn.fits NCUBES=2147483648
expect sync-ncubes 1 "kn.fits: no NCUBES keyword between 1 and the 40 frames" -- sync kn.fits $H -o x.txt
hdr run/halo.fits kh.fits --hdu 3 NAXIS1=9223372036854775807
expect naxis-pupil 1 "kh.fits: file is truncated or corrupt: HDU 3" -- pupil kh.fits -o x.fits
hdr ck1.fits kc.fits --hdu 2 NAXIS2=9223372036854775807
expect naxis-merge 1 "kc.fits: file is truncated or corrupt: HDU 2" -- merge kc.fits ck2.fits -o x.fits
# A floating-point BITPIX flipped to an integer one: the product layout fixes it.
hdr run/halo.fits kb.fits --hdu 5 BITPIX=64
expect bitpix-halo 1 "kb.fits: extension GAIN has BITPIX = 64, but a HALO.fits product stores floating-point" -- \
    pupil kb.fits -o x.fits
hdr run/halo.fits kb.fits --hdu 2 BITPIX=64
expect bitpix-complex 1 "kb.fits: complex image has BITPIX = 64" -- pupil kb.fits -o x.fits
hdr ck1.fits kb.fits --hdu 2 BITPIX=64
expect bitpix-ckpt 1 "kb.fits: extension ACCUM has BITPIX = 64, but an accumulator checkpoint stores" -- \
    merge kb.fits ck2.fits -o x.fits

# ---- checksums: a product changed after it was written is refused, naming the file
cp run/halo.fits kd.fits
printf '\x3f' | dd of=kd.fits bs=1 seek=20000 conv=notrunc status=none
expect datasum 1 "kd.fits: HDU 2 (HALO): the data do not match their DATASUM" -- pupil kd.fits -o x.fits

# ---- all-NaN and overflowing data
hdr run/halo.fits kf.fits --hdu 3 --fill nan 1
expect nan-halo-lf 1 "no focal-plane pixel has a finite, non-zero HALO_LF" -- pupil kf.fits -o x.fits --method moments
hdr run/halo.fits kf.fits --hdu 12 --fill nan 1
expect nan-stab-err 1 "with a positive SNR weight" -- pupil kf.fits -o x.fits --method moments
hdr run/wf.fits kf.fits --hdu 3 --fill 1.8e308 0.3
expect huge-wfe 1 "kf.fits: WFE [m] at pupil sample" -- dmoffsets kf.fits -o x.fits --hexapolar 0.35
mkdir -p tsb && cp ts/* tsb/ && hdr ts/slopes_000.fits tsb/slopes_000.fits --fill 3.4e38 0.3
expect huge-slopes 1 "tsb/slopes_000.fits: slope 0 of WFS frame 0 is 3.4e+38" -- sync sci.fits tsb/handshake.log -o x.txt
hdr ts/slopes_000.fits tsb/slopes_000.fits --fill nan 1
expect nan-slopes 1 "tsb/slopes_000.fits: slope 0 of WFS frame 0 is not finite (NaN or infinite)" -- stream --timing timing.txt \
    --science sci.fits --slopes tsb/slopes_000.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits -o x.fits
# an infinity alone in the file: CFITSIO reads it as NaN, so the message names both (it said
# "is nan" of an infinity); the file, frame and slope named, no output
rm -f x.txt x.fits
hdr ts/slopes_000.fits tsb/slopes_000.fits --fill inf 0 581
expect inf-slopes 1 "tsb/slopes_000.fits: slope 5 of WFS frame 2 is not finite (NaN or infinite); telemetry values must be finite" \
    -- sync sci.fits tsb/handshake.log -o x.txt
hdr ts/slopes_000.fits tsb/slopes_000.fits --fill -inf 0 290
expect minus-inf-slopes 1 "tsb/slopes_000.fits: slope 2 of WFS frame 1 is not finite (NaN or infinite)" -- stream \
    --timing timing.txt --science sci.fits --slopes tsb/slopes_000.fits --recon ts/recon_ao.fits \
    --actuators ts/actuators.fits -o x.fits
if [ -e x.txt ] || [ -e x.fits ]; then bad inf-slopes "an output was left"; fi
hdr ts/actuators.fits ka.fits --fill nan 0.5
expect nan-actuators 1 "ka.fits: actuator 0 has x = nan" -- dmoffsets run/wf.fits -o x.fits --actuators ka.fits
hdr sh.fits kz.fits --hdu 2 --fill nan 1
expect nan-static 1 "kz.fits: static halo value at pixel (0, 0) is not finite" -- stream $STREAM -o x.fits \
    --static kz.fits

# ---- bounded loops and grids, limits checked before work
expect hexapolar 1 "at most 200" -- dmoffsets run/wf.fits -o x.fits --hexapolar 1e-9
expect sync-ratio-step 1 "the search grid has" -- sync sci.fits $H -o x.txt --ratio-step 1e-12
expect sync-lag-step 1 "the search grid has" -- sync sci.fits $H -o x.txt --lag-step 1e-12
expect threads 2 "--threads must be 1..64" -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits \
    -o x.fits --threads 100000

# ---- the file at fault is the one named
hdr run/pupil.fits km.fits --fill 0 1
expect empty-mask 1 "km.fits: the pupil mask is empty" -- pupil run/halo.fits --pupil km.fits -o x.fits
expect recon-is-actuators 1 "ts/actuators.fits: the reconstructor takes 2 slopes per WFS frame" -- stream \
    --timing timing.txt --science sci.fits --slopes ts --recon ts/actuators.fits --actuators ts/actuators.fits -o x.fits

# ---- compressed inputs: tile-compressed (fpack's Rice, Hcompress, GZIP tiles) and gzip'd files
"$FITSCOPY" run/halo.fits 'hz.fits[compress G]' lossless && "$FITSCOPY" run/halo.fits hz.fits.gz \
    && "$FITSCOPY" run/halo.fits 'hr.fits[compress R]' || setup_fail "fitscopy"
want=$(grep WFE wf.txt)
for f in hz.fits hz.fits.gz; do
    "$B" pupil $f -o x.fits > o.txt 2> err.txt && [ "$(grep WFE o.txt)" = "$want" ] && pass=$((pass + 1)) \
        || bad "compressed-$f" "pupil gives '$(grep WFE o.txt)', expected '$want'"
done
# Rice quantizes floating-point images: the regression statistics (REGSTATE) are then no
# longer a state any data set can have, and the halo file is refused, naming the cause.
expect compressed-rice 1 "hr.fits: REGSTATE (a damaged file, or lossy compression" -- pupil hr.fits -o x.fits
for c in R H; do
    "$FITSCOPY" ts/raw_000.fits "r0$c.fits[compress $c]" && "$FITSCOPY" ts/raw_001.fits "r1$c.fits[compress $c]"
    expect "reduce-$c" 0 "reduce: 40 frames from 2 cubes" -- reduce r0$c.fits r1$c.fits --dark ts/dark.fits \
        --flat ts/flat.fits -o x.fits
done
"$FITSCOPY" sci.fits 'sciz.fits[compress G]' lossless || setup_fail fitscopy
expect sync-compressed 0 "" -- sync sciz.fits ts/handshake.log -o x.txt --ratio-min 5 --ratio-max 8
cmp -s <(grep -v '^#' x.txt | sed 's/ [^ ]*slopes_000.fits//') <(grep -v '^#' timing.txt | sed 's/ [^ ]*slopes_000.fits//') \
    && pass=$((pass + 1)) || bad sync-compressed "timing table differs from the uncompressed input's"

# ---- two runs writing one output at once: both finish, the file is whole, no part left
for k in 1 2 3 4 5; do
    "$B" pupil run/halo.fits -o race.fits > /dev/null 2>&1 &
    "$B" pupil run/halo.fits -o race.fits > /dev/null 2>&1 &
    wait
done
"$B" dmoffsets race.fits -o x.fits --hexapolar 0.35 > /dev/null 2> err.txt && ! ls race.fits.part* > /dev/null 2>&1 \
    && pass=$((pass + 1)) || bad concurrent "race.fits incomplete or part left"

# ---- a stream that fails mid-run removes the updates it had put in place
hdr ts/slopes_000.fits tsb/bad.fits --fill nan 1
sed "s|^\(cube 1 .*\) [^ ]*slopes_000.fits|\1 $PWD/tsb/bad.fits|" timing.txt > timing_bad.txt
expect stream-midrun 1 "removed the products it had written" -- stream --timing timing_bad.txt --science sci.fits \
    --recon ts/recon_ao.fits --actuators ts/actuators.fits -o mid.fits --checkpoint midck.fits --every 5
[ ! -e mid.fits ] && [ ! -e midck.fits ] && grep -q "tsb/bad.fits" err.txt && pass=$((pass + 1)) \
    || bad stream-midrun "products left or the bad telemetry file not named"

# ---- Ctrl-C (SIGINT) and SIGTERM stop a run at its next progress report: the stage named,
# exit code 128 + the signal, no product and no part file, and the output folders the run
# made (here stop_SIG and stop_SIG/run) gone with them. A
# background job (and a suite started in the background) has SIGINT ignored, which a shell
# cannot undo: the command starts with the terminal's default through Python's exec.
for sig in INT TERM; do
    "$PY" -c 'import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])' \
        "$B" simulate mode=timeseries $TS ncubes=40 cube_frames=100 -o stop_$sig/run > out.txt 2> err.txt &
    pid=$!
    for _ in $(seq 600); do grep -q "screens 2/2" err.txt && break; sleep 0.1; done
    kill -$sig $pid
    wait $pid
    rc=$?
    want=$((128 + $(kill -l $sig)))
    if [ "$rc" != "$want" ]; then bad stop-$sig "exit code $rc, expected $want"
    elif ! grep -qF "WFS frames: stopped by the caller at " err.txt || ! grep -qF "(SIG$sig)" err.txt; then
        bad stop-$sig "message lacks the stage or the signal"
    elif [ -e stop_$sig ]; then bad stop-$sig "left $(find stop_$sig | head -3)"
    else pass=$((pass + 1)); fi
done

# ---- a full disk (a small tmpfs, where the system allows mounting one): no product in place
mkdir -p full
if mount -t tmpfs -o size=300k tmpfs full 2> /dev/null; then
    expect full-simulate 1 "No space left on device" -- simulate $SMALL -o full/sim --quiet
    [ -z "$(ls full/sim)" ] && pass=$((pass + 1)) || bad full-simulate "left $(ls full/sim)"
    expect full-ts 1 "No space left on device" -- simulate mode=timeseries $TS ncubes=2 cube_frames=20 -o full/ts --quiet
    [ -z "$(ls full/ts)" ] && pass=$((pass + 1)) || bad full-ts "left $(ls full/ts)"
    rm -rf full/*
    echo old > full/t.txt
    cat /dev/zero > full/fill 2> /dev/null
    expect full-sync 1 "No space left on device" -- sync sci.fits $H -o full/t.txt --ratio-min 5 --ratio-max 8
    [ "$(cat full/t.txt)" = old ] && [ "$(ls full)" = "fill
t.txt" ] && pass=$((pass + 1)) || bad full-sync "t.txt changed or part left: $(ls full)"
    umount full
fi

ls ./*.part.* ./*/*.part.* > /dev/null 2>&1 && bad parts "part files left: $(ls ./*.part.* ./*/*.part.* 2> /dev/null)"
echo "$pass passed, $nfail failed"
[ "$nfail" = 0 ]

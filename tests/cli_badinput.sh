#!/bin/bash
# Bad input across the commands: missing, non-FITS and truncated files, the wrong cube type,
# missing keywords, NaN/Inf values, unwritable outputs, unknown options and out-of-range
# numbers. Each case checks the exit code (1 failure, 2 usage), a key phrase of the
# one-line message (file and value named) and that no output or .part is left behind.
# usage: bash cli_badinput.sh <specklewfs> <scratch dir>
set -u
FITSHDR=$(cd "$(dirname "$0")" && pwd)/tools/fitshdr.py
B=$(cd "$(dirname "$1")" && pwd)/$(basename "$1")
D=$2
rm -rf "$D"
mkdir -p "$D"
cd "$D" || exit 1
pass=0
nfail=0

# chk NAME RC PHRASE OUTPUT -- ARGS...: run, expect exit code RC, PHRASE (grep -F) on stderr,
# neither OUTPUT nor OUTPUT.part left.
chk() {
    local name=$1 want=$2 phrase=$3 out=$4
    shift 5
    rm -rf "$out" "$out.part"
    "$B" "$@" > out.txt 2> err.txt
    local rc=$? why=""
    [ "$rc" = "$want" ] || why="exit code $rc, expected $want"
    grep -qF -- "$phrase" err.txt || why="$why; message lacks '$phrase'"
    [ "$(grep -c . err.txt)" -ge 1 ] || why="$why; no message"
    [ -e "$out" ] && why="$why; $out left behind"
    [ -e "$out.part" ] && why="$why; $out.part left behind"
    ls "$out".part.* > /dev/null 2>&1 && why="$why; a part file of $out left behind"
    if [ -n "$why" ]; then
        echo "FAIL $name: $why"
        sed 's/^/    /' err.txt | head -3
        nfail=$((nfail + 1))
    else
        pass=$((pass + 1))
    fi
}
# poke FILE OFFSET BYTES: overwrite bytes at OFFSET into the primary HDU's data.
datastart() {
    local n
    n=$(head -c 288000 "$1" | fold -w 80 | grep -an -m1 '^END *$' | cut -d: -f1)
    echo $(((n * 80 + 2879) / 2880 * 2880))
}
poke() { printf "$3" | dd of="$1" bs=1 seek=$(($(datastart "$1") + $2)) conv=notrunc status=none; }
NAN='\x7f\xc0\x00\x00'
setup_fail() { echo "FAIL setup: $*"; echo "$pass passed, $((nfail + 1)) failed"; exit 1; }

# ---- inputs (all small: about 3 s in all)
SMALL="screen_n=256 teldiam=2.5 pupn=64 nscreens=2 nfx=32 nfy=24"
"$B" simulate $SMALL read_noise=10 -o run --seed 3 --quiet > /dev/null 2>&1 || setup_fail "simulate"
"$B" estimate run/science.fits run/speckles.fits -o run/halo.fits > /dev/null 2>&1 || setup_fail "estimate"
"$B" pupil run/halo.fits -o run/wavefront.fits > /dev/null 2>&1 || setup_fail "pupil"
TS="pupn=66 pupdx=0.1 screen_n=256 wfs_file_frames=1000"
"$B" simulate mode=timeseries $TS ncubes=2 cube_frames=20 cube_gap=10 seed=1 milk=1 --quiet -o ts > /dev/null 2>&1 \
    || setup_fail "simulate mode=timeseries"
"$B" reduce ts/raw_000.fits ts/raw_001.fits --dark ts/dark.fits --flat ts/flat.fits -o sci.fits > /dev/null 2>&1 \
    || setup_fail "reduce"
"$B" sync sci.fits ts/handshake.log -o timing.txt --ratio-min 5 --ratio-max 8 > /dev/null 2>&1 || setup_fail "sync"
"$B" speckles timing.txt --science sci.fits --actuators ts/actuators.fits -o spw.fits --wfs-rate --recon vk > /dev/null 2>&1 \
    || setup_fail "speckles --wfs-rate"
"$B" stream --timing timing.txt --science sci.fits --slopes ts --recon ts/recon_ao.fits --actuators ts/actuators.fits \
    -o sh.fits --checkpoint ck1.fits --max-frames 20 > /dev/null 2>&1 || setup_fail "stream --checkpoint"
cp ck1.fits ck2.fits
echo "not a fits file" > notfits.fits
UW=notfits.fits/x.fits # unwritable even as root: a folder inside a regular file
cp ts/raw_000.fits traw.fits && truncate -s 100000 traw.fits
cp run/halo.fits thalo.fits && truncate -s 100000 thalo.fits # cut inside an extension behind HALO
cp spw.fits tspw.fits && truncate -s 50000 tspw.fits
cp ck1.fits tck.fits && truncate -s 30000 tck.fits
cp run/wavefront.fits twf.fits && truncate -s 100000 twf.fits
# Files edited behind CFITSIO's back lose their (now wrong) CHECKSUM/DATASUM cards.
NOSUM() { /usr/bin/python3 "$FITSHDR" "$1" "$1" --nosum; }
perl -0777 -pe 's/FRAMEDT =/FRAMEDX =/' spw.fits > nodt.fits && NOSUM nodt.fits
perl -0777 -pe 's/FRAMEDT =  /FRAMEDT = -/' spw.fits > negdt.fits && NOSUM negdt.fits
perl -0777 -pe 's/PIXSCALE=                 0.25/PIXSCALE=                 0.50/g' ck1.fits > ckg.fits && NOSUM ckg.fits
cp ts/dark.fits nandark.fits
for i in $(seq 0 4 800); do poke nandark.fits "$i" "$NAN"; done
NOSUM nandark.fits
R=ts/raw_000.fits

# ---- simulate (paper and time-series modes)
chk sim-unwritable 1 "notfits.fits/x" $UW/science.fits -- simulate $SMALL -o $UW --quiet
chk sim-negative 1 "nscreens=-1" o/science.fits -- simulate $SMALL nscreens=-1 -o o --quiet
chk sim-nan 1 "read_noise=nan" o/science.fits -- simulate $SMALL read_noise=nan -o o --quiet
chk sim-inf 1 "gain=inf" o/science.fits -- simulate $SMALL gain=inf -o o --quiet
chk sim-unknown-key 1 "tel_diam" o/science.fits -- simulate $SMALL tel_diam=3 -o o --quiet
chk sim-unknown-opt 2 "--bogus" o/science.fits -- simulate $SMALL --bogus -o o
chk sim-bad-mode 2 "mode=foo: expected paper or timeseries" o/science.fits -- simulate mode=foo -o o
chk sim-config-not-text 1 "notfits.fits:1: expected key=value" o/science.fits -- simulate notfits.fits -o o
chk sim-bad-seed 1 "seed=abc" o/science.fits -- simulate $SMALL --seed abc -o o
chk ts-zero-frames 1 "cube_frames=0" o/raw_000.fits -- simulate mode=timeseries $TS cube_frames=0 -o o --quiet
chk ts-inf 1 "vib_amp=inf: must be finite" o/raw_000.fits -- simulate mode=timeseries $TS vib_amp=inf -o o --quiet
chk ts-neg-ratio 1 "frame_ratio=-6" o/raw_000.fits -- simulate mode=timeseries $TS frame_ratio=-6 -o o --quiet
chk ts-unknown-key 1 "'foo'" o/raw_000.fits -- simulate mode=timeseries $TS foo=1 -o o --quiet
chk ts-unwritable 1 "notfits.fits/x" $UW/raw_000.fits -- simulate mode=timeseries $TS -o $UW --quiet
chk ts-pupil-onto-itself 1 "refusing to overwrite an input" ts/raw_009.fits -- simulate mode=timeseries $TS pupil_mask=ts/pupil.fits -o ts --quiet
chk sim-pupil-onto-itself 1 "refusing to overwrite an input" run/raw_009.fits -- simulate $SMALL pupil_mask=run/pupil.fits -o run --quiet
chk sim-ncp-missing 1 "NCP map: nope.fits" o/science.fits -- simulate $SMALL ncp_map=nope.fits -o o --quiet
chk ts-ncp-missing 1 "NCP map: nope.fits" o/raw_000.fits -- simulate mode=timeseries $TS ncp_map=nope.fits -o o --quiet
chk ts-ncp-onto-itself 1 "refusing to overwrite an input" ts/raw_009.fits -- simulate mode=timeseries $TS ncp_map=ts/truth.fits -o ts --quiet

# ---- reduce
chk reduce-missing 1 "nofile.fits: cannot open" o.fits -- reduce nofile.fits -o o.fits
chk reduce-nonfits 1 "notfits.fits: cannot open as FITS" o.fits -- reduce notfits.fits -o o.fits
chk reduce-truncated 1 "traw.fits: file is truncated" o.fits -- reduce traw.fits -o o.fits
chk reduce-complex 1 "run/speckles.fits: camera cube is complex; expected real" o.fits -- reduce run/speckles.fits -o o.fits
chk reduce-shapes 1 "frames are 32x24 but $R has 54x54" o.fits -- reduce $R run/science.fits -o o.fits
chk reduce-dark-shape 1 "run/pupil.fits: calibration frame is 64x64x1 but the camera frames are 54x54" o.fits -- \
    reduce $R --dark run/pupil.fits -o o.fits
chk reduce-unwritable 1 "notfits.fits/x.fits: cannot create" $UW -- reduce $R -o $UW
chk reduce-unknown 2 "--frobnicate" o.fits -- reduce $R -o o.fits --frobnicate
chk reduce-neg-sigma 2 "--gauss-sigma expects a positive number, got -1" o.fits -- reduce $R -o o.fits --gauss-sigma -1
chk reduce-nan-sigma 2 "got 'nan'" o.fits -- reduce $R -o o.fits --gauss-sigma nan
chk reduce-neg-hot 2 "--hot-sigma expects a positive number" o.fits -- reduce $R -o o.fits --hot-sigma -3
chk reduce-bg-radius 1 "background radius 1e+06 pixels leaves no good pixel" o.fits -- \
    reduce $R -o o.fits --bg-radius 1e6 --noise-region
# NaN dark pixels are bad pixels: the run succeeds with a finite noise estimate.
"$B" reduce $R --dark nandark.fits -o nd.fits > out.txt 2> err.txt
if [ $? = 0 ] && grep -q "bad pixels, background noise [0-9]" err.txt && ! grep -qi "nan" err.txt; then
    pass=$((pass + 1))
else
    echo "FAIL reduce-nan-dark: $(tail -1 err.txt)"
    nfail=$((nfail + 1))
fi

# ---- sync
H=ts/handshake.log
chk sync-missing 1 "nofile.fits: cannot open" o.txt -- sync nofile.fits $H -o o.txt
chk sync-truncated 1 "file is truncated" o.txt -- sync tspw.fits $H -o o.txt
chk sync-not-reduced 1 "run/science.fits: no NCUBES keyword" o.txt -- sync run/science.fits $H -o o.txt
chk sync-log-missing 1 "nolog.log: cannot open the handshake log" o.txt -- sync sci.fits nolog.log -o o.txt
chk sync-log-garbage 1 "notfits.fits:1: expected" o.txt -- sync sci.fits notfits.fits -o o.txt
chk sync-unwritable 1 "notfits.fits/x.fits: cannot create output file (folder notfits.fits: Not a directory)" $UW -- sync sci.fits $H -o $UW
chk sync-ratio-range 1 "ratio [8, 5]" o.txt -- sync sci.fits $H -o o.txt --ratio-min 8 --ratio-max 5
chk sync-ratio-min-zero 2 "--ratio-min must be > 0, got 0" o.txt -- sync sci.fits $H -o o.txt --ratio-min 0
chk sync-no-match 1 "matches the telemetry's nowhere in the search" o.txt -- sync sci.fits $H -o o.txt --ratio-min 2 --ratio-max 4
chk sync-min-above-bound 1 "bounds the ratio at" o.txt -- sync sci.fits $H -o o.txt --ratio-min 8
chk sync-nan 2 "got 'nan'" o.txt -- sync sci.fits $H -o o.txt --lag-step nan
chk sync-unknown 2 "--bogus" o.txt -- sync sci.fits $H -o o.txt --bogus

# ---- speckles, stream: a slopes file's NSUB against the Shack-Hartmann the slopes make
mkdir -p nsub && /usr/bin/python3 "$FITSHDR" ts/slopes_000.fits nsub/slopes_000.fits NSUB=16
sed "s#[^ ]*/ts/slopes_000.fits#$PWD/nsub/slopes_000.fits#" timing.txt > nsub/timing.txt
chk speckles-keep-registered 1 "sci.fits: REGISTER = 1 (frames re-centred on their peak), but --tiptilt keep" o.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits --tiptilt keep -o o.fits
rm -rf o.teach
chk speckles-nsub 1 "nsub/slopes_000.fits: NSUB = 16 subapertures across, but the slopes' width (and the valid map, if given) make a 12 x 12" o.fits -- speckles nsub/timing.txt --science sci.fits --actuators ts/actuators.fits -o o.fits
# refused before teach (the default reconstructor) simulated any loop
if grep -q "simulating the loops" err.txt || [ -e o.teach ]; then
    echo "FAIL speckles-nsub: teach ran before the NSUB check"
    nfail=$((nfail + 1))
fi
# a timing table whose rows time the same science frames twice (cube 1 edited to start at 0)
sed 's/^\(cube 1 [^ ]*\) [0-9]* /\1 0 /' timing.txt > t_overlap.txt
chk speckles-timing-overlap 1 "t_overlap.txt: cubes 0 (raw_000.fits) and 1 (raw_001.fits) both time science frames 0-19" o.fits -- speckles t_overlap.txt --science sci.fits --actuators ts/actuators.fits --recon vk -o o.fits
chk stream-timing-overlap 1 "t_overlap.txt: cubes 0 (raw_000.fits) and 1 (raw_001.fits) both time science frames 0-19" o.fits -- stream --timing t_overlap.txt --science sci.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits -o o.fits
# teach's map named as its own telemetry or science cube: refused before any loop, the input
# as it was, no work folder left
cp ts/slopes_000.fits tslopes.fits
cp sci.fits tsci.fits
for out in tslopes.fits tsci.fits; do
    rm -rf "${out%.fits}.teach"
    "$B" teach tslopes.fits --science tsci.fits --actuators ts/actuators.fits -o $out --loops 2 > out.txt 2> err.txt
    rc=$?
    if [ "$rc" = 1 ] && grep -qF "$out (the taught map (-o)) is the same file as the input $out" err.txt \
        && cmp -s tslopes.fits ts/slopes_000.fits && cmp -s tsci.fits sci.fits && [ ! -e "${out%.fits}.teach" ] \
        && ! grep -q "simulating" out.txt err.txt; then
        pass=$((pass + 1))
    else
        echo "FAIL teach-out-is-input ($out): exit code $rc, the message, the input or its work folder"
        sed 's/^/    /' err.txt | head -3
        nfail=$((nfail + 1))
    fi
done
chk speckles-threads 2 "--threads must be >= 1, got 0" o.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits --recon vk --threads 0 -o o.fits
chk stream-every 2 "--every must be >= 0, got -1" o.fits -- stream --timing timing.txt --science sci.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits --every -1 -o o.fits
chk speckles-pupn 2 "--pupn must be 2 to 8192 pupil samples, got 0" o.fits -- speckles timing.txt --science sci.fits --actuators ts/actuators.fits --recon vk --pupn 0 -o o.fits
chk stream-static-cube 1 "spw.fits: static halo is 54x54x260 but the science frames are 54x54: expected one complex image" o.fits -- stream --timing timing.txt --science sci.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits --static spw.fits -o o.fits
chk stream-keep-registered 1 "sci.fits: REGISTER = 1 (frames re-centred on their peak), but --tiptilt keep" o.fits -- stream --timing timing.txt --science sci.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits --keep-tiptilt -o o.fits
chk stream-nsub 1 "nsub/slopes_000.fits: NSUB = 16" o.fits -- stream --timing nsub/timing.txt --science sci.fits --recon ts/recon_ao.fits --actuators ts/actuators.fits -o o.fits

# ---- replay of milk logs (nothing is published: the checks come before the streams)
chk replay-milk-nostamps 1 "sci.fits: no STAMPS extension" o.fits -- replay --wfs-log ts/milk/wfs --science sci.fits --shm-dir .
chk replay-milk-timing 2 "--wfs-log publishes a milk log with its own stamps: no --timing" o.fits -- replay --wfs-log ts/milk/wfs --timing timing.txt --science sci.fits
chk replay-milk-jitter 2 "no --drop-wfs, --drop-camera, --jitter" o.fits -- replay --wfs-log ts/milk/wfs --science sci.fits --jitter 1e-6
chk replay-milk-nolog 1 "nolog: a milk log file name ends in .fits" o.fits -- replay --wfs-log nolog --science sci.fits --shm-dir .
[ -e swfs_wfs.im.shm ] && echo "FAIL replay-milk: a stream was left" && nfail=$((nfail + 1))

# ---- coherence
chk coh-missing 1 "nofile.fits: cannot open" o.fits -- coherence nofile.fits -o o.fits
chk coh-nonfits 1 "notfits.fits: cannot open as FITS" o.fits -- coherence notfits.fits -o o.fits
chk coh-truncated 1 "tspw.fits: file is truncated" o.fits -- coherence tspw.fits -o o.fits
chk coh-real 1 "run/science.fits: missing keyword FRAMEDT" o.fits -- coherence run/science.fits -o o.fits
chk coh-no-framedt 1 "nodt.fits: missing keyword FRAMEDT" o.fits -- coherence nodt.fits -o o.fits
chk coh-neg-framedt 1 "negdt.fits: FRAMEDT = -" o.fits -- coherence negdt.fits -o o.fits
/usr/bin/python3 "$FITSHDR" spw.fits negfr.fits FRATIO=-3
chk coh-neg-fratio 1 "negfr.fits: FRATIO = -3, expected WFS frames per camera frame, a positive number" o.fits -- coherence negfr.fits -o o.fits
/usr/bin/python3 "$FITSHDR" spw.fits hugedt.fits FRAMEDT=1e300
chk coh-huge-framedt 1 "hugedt.fits: FRAMEDT = 1e+300, expected a positive number of seconds (at most 60)" o.fits -- coherence hugedt.fits -o o.fits
chk coh-unwritable 1 "notfits.fits/x.fits: cannot create" $UW -- coherence spw.fits -o $UW
chk coh-zero-exposure 2 "--exposure must be positive seconds, got 0" o.fits -- coherence spw.fits -o o.fits --exposure 0
chk coh-pixel 2 "--pixel 100,3 is outside the 54x54 image" o.fits -- coherence spw.fits -o o.fits --pixel 100,3
chk coh-nfit 2 "--nfit must be 1..1000" o.fits -- coherence spw.fits -o o.fits --nfit 0
/usr/bin/python3 "$FITSHDR" spw.fits spwz.fits --fill 0 1
chk coh-no-power 1 "no pixel of the 54 x 54 speckle cube has speckle power to measure (0 with a non-finite value in some frame, 2916 without power)" o.fits -- coherence spwz.fits -o o.fits
chk coh-unknown 2 "--bogus" o.fits -- coherence spw.fits -o o.fits --bogus

# ---- learn (ts/ is a time series without the true residual)
chk learn-no-truth 1 "ts/truewf_000.fits beside it" o.fits -- learn ts -o o.fits
chk learn-not-sim 1 "run: no slopes_000.fits" o.fits -- learn run -o o.fits
chk learn-ridge 2 "--ridge must be a fraction > 0 and at most 1e30 (of the normal equations' mean diagonal: beyond, the map is the prior, or 0), got 0" o.fits -- learn ts -o o.fits --ridge 0
chk learn-no-dir 2 "needs at least one simulated data set" o.fits -- learn -o o.fits
# two small loops with the true residual: learn writes the map and its held-out check; a truth
# file cut short stops it with the file named and no map left
for k in 1 2; do
    "$B" simulate mode=timeseries $TS ncubes=2 cube_frames=40 cube_gap=40 seed=$k layer_speed=$((10 * k)),$((15 * k)) \
        export_truth=1 --quiet -o lt$k > /dev/null 2>&1 || setup_fail "simulate export_truth=1"
done
if "$B" learn lt1 lt2 -o lw.fits > out.txt 2> err.txt && [ -s lw.fits ] && grep -q "learn: held out, all 2:" out.txt \
    && grep -q "^  lt2 " out.txt; then
    pass=$((pass + 1))
else
    echo "FAIL learn-ok: exit code, lw.fits or the held-out lines"; sed 's/^/    /' out.txt err.txt | head -8
    nfail=$((nfail + 1))
fi
# a space-time map (--lags): written as a cube with its lags; no AO loop's reconstructor
if "$B" learn lt1 lt2 -o lw3.fits --lags 0,-3,3 --no-heldout > out.txt 2> err.txt && [ -s lw3.fits ] \
    && grep -q "288 slopes x 3 lags (0,-3,3)" out.txt; then
    pass=$((pass + 1))
else
    echo "FAIL learn-lags-ok: exit code, lw3.fits or the lags line"; sed 's/^/    /' out.txt err.txt | head -8
    nfail=$((nfail + 1))
fi
chk learn-lags-no-zero 1 "--lags: no lag 0" o.fits -- learn lt1 -o o.fits --lags 3,6
chk learn-lags-text 1 "\"0,a\" is not a list of whole WFS frames" o.fits -- learn lt1 -o o.fits --lags 0,a
chk learn-lags-modal 1 "a modal control matrix (--modal) acts on one frame" o.fits -- learn lt1 -o o.fits --lags 0,2 --modal
chk sim-spacetime-aorecon 1 "lw3.fits: a space-time reconstructor (3 lags) is no AO loop's" lt3/slopes_000.fits -- simulate mode=timeseries \
    $TS ncubes=2 cube_frames=40 cube_gap=40 ao_recon=lw3.fits -o lt3 --quiet
# learn's map named as one of its data sets' files: refused, the file as it was; a data set whose
# numbers skip one (000 and 002) is refused, naming the missing file, not read up to the gap
rm -rf lr lg && cp -r lt1 lr && cp -r lt1 lg
"$B" learn lr -o lr/truewf_000.fits > out.txt 2> err.txt
rc=$?
if [ "$rc" = 1 ] && grep -qF "lr/truewf_000.fits (output reconstructor) is the same file as the input lr/truewf_000.fits" err.txt \
    && cmp -s lr/truewf_000.fits lt1/truewf_000.fits; then
    pass=$((pass + 1))
else
    echo "FAIL learn-out-is-input: exit code $rc, the message or the truth file"; sed 's/^/    /' err.txt | head -3
    nfail=$((nfail + 1))
fi
mv lg/slopes_000.fits lg/slopes_002.fits && cp lt1/slopes_000.fits lg/ && cp lg/truewf_000.fits lg/truewf_002.fits
chk learn-gap 1 "lg: 2 slopes files numbered up to 002, but no slopes_001.fits" o.fits -- learn lg -o o.fits
rm -rf lz && cp -r lt1 lz && /usr/bin/python3 "$FITSHDR" lt1/truewf_000.fits lz/truewf_000.fits --fill 0 1
chk learn-zero-truth 1 "lz/truewf_000.fits: every value is 0: a data set holds a loop's true residual" o.fits -- learn lt1 lz -o o.fits
chk learn-metric-count 1 "the mean's miss's metric is 1 x 1; the truth has 217 outputs (lt1/truewf_000.fits" o.fits -- learn lt1 -o o.fits --mean-miss-over ts/pupil.fits,ts/pupil.fits
chk learn-ridge-huge 2 "--ridge must be a fraction > 0 and at most 1e30" o.fits -- learn lt1 -o o.fits --ridge 1e308
truncate -s 100000 lt2/truewf_000.fits
chk learn-truncated 1 "lt2/truewf_000.fits: file is truncated" o.fits -- learn lt1 lt2 -o o.fits

# ---- wind
chk wind-no-teldiam 2 "needs --teldiam D > 0" o.fits -- wind ts/slopes_000.fits
chk wind-missing 1 "nofile.fits" o.fits -- wind nofile.fits --teldiam 6.5
chk wind-other-width 1 "expected 288 slopes x WFS frames as in ts/slopes_000.fits" o.fits -- wind ts/slopes_000.fits ts/actuators.fits --teldiam 6.5
chk wind-bad-valid 1 "sh.fits" o.fits -- wind ts/slopes_000.fits --teldiam 6.5 --valid sh.fits
chk wind-huge-teldiam 2 "--teldiam must be 1e-3 to 1e3 m, got 1e+308" o.fits -- wind ts/slopes_000.fits --teldiam 1e308
chk wind-nsub-zero 2 "--nsub must be 1 to 100000, got 0" o.fits -- wind ts/slopes_000.fits --teldiam 6.5 --nsub 0
# a series' file given twice, or a copy whose FRAME0 repeats the frames before it: not frames
# that follow each other (their time correlations would count each frame twice)
chk wind-same-file 1 "ts/slopes_000.fits and ts/slopes_000.fits are the same file" o.fits -- wind ts/slopes_000.fits ts/slopes_000.fits --teldiam 6.5
cp ts/slopes_000.fits again.fits
/usr/bin/python3 "$FITSHDR" ts/slopes_000.fits const.fits --fill 1e-6 1
chk wind-constant 1 "const.fits: wind: the slopes of 0 of the 144 subapertures with signal vary in time" o.fits -- wind const.fits --teldiam 6.5
chk wind-repeated-frames 1 "again.fits: FRAME0 = 0, but ts/slopes_000.fits ends at WFS frame 582" o.fits -- wind ts/slopes_000.fits again.fits --teldiam 6.5

# ---- pupil: halos of other frames to choose among
chk pupil-choose-other 1 "window where run/halo.fits has" o.fits -- pupil run/halo.fits sh.fits -o o.fits
chk pupil-wiener-k 2 "--wiener-k must be > 0 and at most 1e6" o.fits -- pupil run/halo.fits -o o.fits --method moments --wiener-k 1e300
chk pupil-g-radial 2 "--g-radial must be >= 0" o.fits -- pupil run/halo.fits -o o.fits --g-radial -1
chk pupil-g-radial-moments 2 "--g-radial applies to --method fit, not moments" o.fits -- pupil run/halo.fits -o o.fits --method moments --g-radial 2
chk pupil-g-radial-bias 2 "--g-radial applies to the fit, not to --bias" o.fits -- pupil run/halo.fits -o o.fits --bias 0.5 --g-radial 2
chk teach-valid-size 1 "the valid map ts/pupil.fits is 66 x 66 (3268 used), but ts/slopes_000.fits has 288 slopes per WFS frame" o.fits -- teach ts/slopes_000.fits --science sci.fits --actuators ts/actuators.fits --valid ts/pupil.fits -o o.fits --loops 2
chk pupil-choose-missing 1 "nofile.fits" o.fits -- pupil run/halo.fits nofile.fits -o o.fits
# the same frames' halo whose HALO header says another sampling: not one of these frames' halos
/usr/bin/python3 "$FITSHDR" run/halo.fits hps.fits --hdu 2 PIXSCALE=0.5 && NOSUM hps.fits
chk pupil-choose-pixscale 1 "hps.fits has PIXSCALE = 0.5 but run/halo.fits has" o.fits -- pupil run/halo.fits hps.fits -o o.fits

# ---- merge
chk merge-missing 1 "nofile.fits: cannot open" o.fits -- merge nofile.fits ck1.fits -o o.fits
chk merge-truncated 1 "tck.fits: file is truncated" o.fits -- merge tck.fits ck1.fits -o o.fits
chk merge-not-checkpoint 1 "run/halo.fits: no image extension EXTNAME='ACCUM'" o.fits -- merge run/halo.fits ck1.fits -o o.fits
chk merge-geometry 1 "PIXSCALE = 0.25 but ckg.fits has 0.5" o.fits -- merge ckg.fits ck2.fits -o o.fits
chk merge-unwritable 1 "notfits.fits/x.fits: cannot create" $UW -- merge ck1.fits ck2.fits -o $UW
chk merge-halo-unwritable 1 "notfits.fits/x.fits: cannot create" o.fits -- merge ck1.fits ck2.fits -o o.fits --halo $UW
chk merge-same 1 "ck1.fits (-o) is the same file as the input ck1.fits" ck1.fits.x -- merge ck1.fits ck2.fits -o ck1.fits
chk merge-neg-rn 2 "--read-noise must be >= 0, got -1" o.fits -- merge ck1.fits ck2.fits -o o.fits --read-noise -1

# ---- report (a failed run may leave its empty output folder, never an index.html)
chk report-missing 1 "nodir: not a folder" rep/index.html -- report nodir -o rep
mkdir -p badrun trrun swrun
cp notfits.fits badrun/halo.fits
cp thalo.fits trrun/halo.fits
cp run/science.fits swrun/speckles.fits
chk report-nonfits 1 "badrun/halo.fits: cannot open as FITS" badrun/report/index.html -- report badrun
chk report-truncated 1 "trrun/halo.fits: file is truncated" trrun/report/index.html -- report trrun
chk report-real-speckles 1 "swrun/speckles.fits: expected a complex cube" swrun/report/index.html -- report swrun
chk report-unwritable 1 "notfits.fits/x.fits" $UW -- report run -o $UW
chk report-pixel 1 "pixel (500, 3) is outside the 32x24" rep/index.html -- report run -o rep --pixel 500 3
chk report-percentiles 2 "--percentiles needs 0 <= LO < HI <= 100" rep/index.html -- report run -o rep --percentiles 99 1

# ---- dmoffsets
chk dm-missing 1 "nofile.fits: cannot open" o.fits -- dmoffsets nofile.fits -o o.fits --hexapolar 0.35
chk dm-truncated 1 "twf.fits: file is truncated" o.fits -- dmoffsets twf.fits -o o.fits --hexapolar 0.35
chk dm-no-wfe 1 "run/science.fits: no WFE extension" o.fits -- dmoffsets run/science.fits -o o.fits --hexapolar 0.35
chk dm-actuators 1 "run/science.fits: actuator positions must be a 2 x nact image" o.fits -- \
    dmoffsets run/wavefront.fits -o o.fits --actuators run/science.fits
chk dm-unwritable 1 "notfits.fits/x.fits: cannot create" $UW -- dmoffsets run/wavefront.fits -o $UW --hexapolar 0.35
chk dm-pitch 2 "--hexapolar needs a pitch > 0" o.fits -- dmoffsets run/wavefront.fits -o o.fits --hexapolar 0
chk dm-reg 2 "--reg expects a finite decimal number, got 'nan'" o.fits -- dmoffsets run/wavefront.fits -o o.fits --hexapolar 0.35 --reg nan

# ---- option values: the next option taken for a file name, C's hexadecimal numbers
chk opt-value-is-option 2 "-o needs a file name, got the option '--gain' (a file of that name: write ./--gain)" ./--gain -- estimate run/science.fits run/speckles.fits -o --gain 2
/usr/bin/python3 "$FITSHDR" run/science.fits allnan.fits --fill nan 1
chk est-all-nan 1 "allnan.fits + run/speckles.fits: no pixel has 2 frames with finite values" o.fits -- estimate allnan.fits run/speckles.fits -o o.fits
chk est-gain-option 1 "the gain given (--gain) 1e-05 e-/count is outside 1e-4 .. 1e6" o.fits -- estimate run/science.fits run/speckles.fits -o o.fits --gain 1e-5
chk est-g-smooth 1 "g smoothing 60 lambda/D is 240 pixels at run/speckles.fits's 0.25 lambda/D per pixel; expected at most 60 pixels (15 lambda/D)" o.fits -- estimate run/science.fits run/speckles.fits -o o.fits --g-smooth 60
# and refused before a frame is read
grep -q "frames" out.txt err.txt && echo "FAIL est-g-smooth: frames read before the check" && nfail=$((nfail + 1))
chk opt-hex-number 2 "--read-noise expects a finite decimal number, got '0x10'" o.fits -- estimate run/science.fits run/speckles.fits -o o.fits --read-noise 0x10

# ---- correct, demo (argument and configuration errors; they simulate everything else)
chk correct-unknown-key 1 "tel_diam" o -- correct $SMALL tel_diam=3 -o o --iterations 1
chk correct-gain 2 "--gain" o -- correct $SMALL -o o --gain nan
chk correct-iterations 2 "--iterations" o -- correct $SMALL -o o --iterations -1
chk correct-actuators 1 "noact.fits: cannot open" o -- correct $SMALL -o o --actuators noact.fits
chk demo-levels 2 "--levels" o -- demo -o o --levels 1,abc
chk demo-unknown-key 1 "tel_diam" o -- demo -o o tel_diam=3
chk demo-unwritable 1 "notfits.fits/x" $UW -- demo -o $UW $SMALL --loop-iterations 0 --no-report

echo "$pass passed, $nfail failed"
[ "$nfail" = 0 ]

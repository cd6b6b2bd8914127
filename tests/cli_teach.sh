# Speckles' default, --recon teach (docs/telemetry.md): the teach run inside speckles on the
# observation's own files gives the map `teach` gives on them, and the same NCP error; stream
# takes that space-time map and its per-frame map; a later run on the same inputs reuses the map
# (its fingerprint TEACHFPR), and where its second map (the DM's choice) cannot be taught goes on
# with the first; with the DM told (--teach-set, one map taught), --teach-again and an edited
# telemetry file teach anew (the same speckles, compared value by value with
# tests/tools/fitsdiff); teach on the used subapertures' slopes (cacao's layout) with --valid, in
# a work folder holding stale loop files, clears them and gives the map of speckles' teach on the
# full layout. On lib_learn.sh's observation (the 12 x 12 of cli_learn.sh, which runs the recipe,
# learn and teach's other checks, teach_files among them). Then a zonal loop whose slopes show no
# layer to `wind`: taught at the speed of their time correlation, better than the von Karman map.
# usage: bash cli_teach.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_learn.sh"
learn_setup "$@"
FITSDIFF=$(dirname "$B")/tests/fitsdiff
[ -x "$FITSDIFF" ] || fail "no $FITSDIFF (tests/tools/fitsdiff.c)"
# speckles' default (--recon teach) is teach run inside speckles on the same files (the
# timing table's telemetry, --science, --actuators, --pupil), here with 4 loops
# (--teach-loops 4 --teach-max-loops 4), the map in spk_dt.teach/ beside its output (the
# loops' folders removed, the maps and the modes' profile kept); the `teach` command on the
# same system gives the same map (below, on the valid-only slopes)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 --teach-max-loops 4 \
    --match science.fits sci_dt.fits -o spk_dt.fits 2> speckles_dt.log || { cat speckles_dt.log; fail "speckles (default)"; }
grep -q "^speckles: chose the space-time map (neither check warned) -> spk_dt.teach/taught.fits" speckles_dt.log \
    && grep -q "given space-time reconstructor spk_dt.teach/taught.fits: 288 slopes x 5 lags" speckles_dt.log \
    && grep -q "ao_modes = 5[3-9]$" speckles_dt.log && [ -s spk_dt.teach/spacetime.fits ] \
    && [ -s spk_dt.teach/modes.tsv ] && ! ls -d spk_dt.teach/loop_* spk_dt.teach/modes_* spk_dt.teach/zonal_* > /dev/null 2>&1 \
    || { cat speckles_dt.log; fail "speckles (default): the taught map in spk_dt.teach, its loops removed"; }
# told neither the DM's functions nor a control matrix, speckles teaches a second map of a DM
# of Gaussian functions (spk_dt.teach/dm-gauss/) and keeps the one whose speckles follow the
# frames better: the observation's own DM, simulate's interpolated surface
grep -q "^speckles: the loops' DM by the science frames: the interpolated surface's map kept (mean correlation of intensity and |psi|^2: Gaussian influence functions of coupling 0.15 0\.[0-9]*, the interpolated surface 0\.[0-9]*; per pixel -0\.[0-9]* +- 0\.[0-9]* over [0-9]* pixels; the Gaussian's kept beyond 2 standard errors); the other map spk_dt.teach/dm-gauss/taught.fits" \
    speckles_dt.log && [ -s spk_dt.teach/dm-gauss/taught.fits ] && ! ls -d spk_dt.teach/dm-gauss/loop_* > /dev/null 2>&1 \
    || { cat speckles_dt.log; fail "speckles (default): the interpolated surface's map kept over a Gaussian DM's"; }
"$B" estimate sci_dt.fits spk_dt.fits -o halo_dt.fits > /dev/null 2>&1 || fail "estimate (default)"
"$B" pupil halo_dt.fits -o pupil_dt.fits --truth obs/truth.fits > pupil_dt.log || fail "pupil (default)"
edt=$(ncp_error pupil_dt.log)
echo "cli_teach: speckles' default (teach inside speckles): $edt nm"
[ -n "$edt" ] || fail "speckles' default: no NCP error"
# stream takes that space-time map too (each batch's slopes stacked at its lags): the same NCP
# error through stream's own estimate, in batches of 7 camera frames
"$B" stream --timing timing.txt --science science.fits --recon spk_dt.teach/taught.fits --actuators actuators.fits \
    --pupil pupil.fits --batch 7 -o halo_stst.fits > stream_st.log 2>&1 || { cat stream_st.log; fail "stream with the taught map"; }
grep -q "^stream: space-time reconstructor of 5 lags (0,-6,6,-12,12 WFS frames)" stream_st.log \
    || { cat stream_st.log; fail "stream: the space-time map's lags expected"; }
"$B" pupil halo_stst.fits -o pupil_stst.fits --truth obs/truth.fits > pupil_stst.log || fail "pupil (stream)"
est=$(ncp_error pupil_stst.log)
echo "cli_teach: stream with speckles' taught map: $est nm"
[ "$est" = "$edt" ] || fail "stream with the taught map $est nm against speckles' $edt nm"
# beside it the per-frame map of the same loops (the lag-0 block of the same sums), for live:
# one frame's slopes in, within 15 % of the space-time map through the whole path (measured
# 23.2 nm against 20.7; 24.2 against 22.3 before the loops' speeds were spread, 2026-12-03,
# which took the space-time map further below it)
[ -s spk_dt.teach/perframe.fits ] && ! head -c 8640 spk_dt.teach/perframe.fits | grep -aq "NLAGS" \
    || fail "speckles' teach folder: a per-frame map perframe.fits expected"
"$B" stream --timing timing.txt --science science.fits --recon spk_dt.teach/perframe.fits --actuators actuators.fits \
    --pupil pupil.fits -o halo_stpf.fits > stream_pf.log 2>&1 || { cat stream_pf.log; fail "stream with perframe.fits"; }
"$B" pupil halo_stpf.fits -o pupil_stpf.fits --truth obs/truth.fits > pupil_stpf.log || fail "pupil (perframe.fits)"
epf=$(ncp_error pupil_stpf.log)
echo "cli_teach: stream with the taught per-frame map: $epf nm (space-time $edt nm)"
awk -v a="$epf" -v b="$edt" 'BEGIN { exit !(a > 0 && a < 1.15 * b) }' || fail "the per-frame map $epf nm against $edt nm"
# again REF TAG [options]: speckles as spk_REF.fits was made (the options given), into another
# output, in the same teach folder; its speckles must be spk_REF.fits's, value for value (so the
# same NCP error)
again() {
    local ref=$1 tag=$2
    shift 2
    "$B" speckles "$@" --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 --teach-max-loops 4 \
        --teach-work spk_dt.teach --match science.fits "sci_$tag.fits" -o "spk_$tag.fits" 2> "speckles_$tag.log" \
        || { cat "speckles_$tag.log" >&2; fail "speckles ($tag)"; }
    "$FITSDIFF" "spk_$ref.fits" "spk_$tag.fits" || fail "speckles ($tag): other speckles than spk_$ref.fits"
}
# a later run on the same inputs reuses that map at once (its TEACHFPR: the telemetry's and
# the system files' contents, the description and teach's options are this run's), to the
# same speckles
fpr_of() { head -c 20000 "$1" | grep -ao "TEACHFPR= '[0-9a-f]*'" | cut -d"'" -f2; }
fpr=$(fpr_of spk_dt.teach/taught.fits)
[ "${#fpr}" = 16 ] || fail "speckles' taught map carries no TEACHFPR"
again dt dt2 timing.txt
grep -q "^speckles: reused spk_dt.teach/taught.fits, taught by an earlier run for the same telemetry, system files and teach options (TEACHFPR = '$fpr'; 4 loops): the space-time map" \
    speckles_dt2.log && ! grep -q "simulating the loops" speckles_dt2.log \
    || { cat speckles_dt2.log; fail "speckles on the same inputs: the taught map should be reused"; }
echo "cli_teach: speckles' default again on the same inputs: reused the map, the same speckles"
# the second map cannot be taught (here its folder, spk_dt.teach/dm-gauss, is a file): the run
# goes on with the first map, says why, and its speckles are the default's (the surface's map,
# which the choice kept above)
mv spk_dt.teach/dm-gauss spk_dt.teach/dm-gauss.kept && echo x > spk_dt.teach/dm-gauss || fail "the dm-gauss file"
again dt dt5 timing.txt
grep -q "^speckles: the loops' DM: the interpolated surface's map kept; no Gaussian DM's to compare (the second map could not be taught: teach: spk_dt.teach/dm-gauss/taught.fits: cannot create output file (folder spk_dt.teach/dm-gauss: Not a directory))" \
    speckles_dt5.log || { cat speckles_dt5.log; fail "the second map not taught: the first's speckles, said why"; }
rm spk_dt.teach/dm-gauss && mv spk_dt.teach/dm-gauss.kept spk_dt.teach/dm-gauss || fail "dm-gauss back"
echo "cli_teach: the second map not taught (its folder a file): the first map's speckles, the reason said"
# --teach-set: what the files do not say of the system, in simulate's keys (here the DM's
# Gaussian influence functions, which the observation's own DM does not have): part of the
# fingerprint (taught anew, not reused), said in the summary, and reaching the loops (other
# speckles than the default's); an unknown key, a value out of range and one without '=' are
# refused before anything is read, naming it, and nothing is written
dm=(--teach-set dm_coupling=0.15)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 \
    --teach-max-loops 4 --teach-work spk_dt.teach "${dm[@]}" --match science.fits sci_dm.fits \
    -o spk_dm.fits 2> speckles_dm.log || { cat speckles_dm.log; fail "speckles --teach-set dm_coupling=0.15"; }
grep -q "^speckles: the loops' system as its files describe it, with dm_coupling=0.15 (--teach-set)" speckles_dm.log \
    && grep -q "^speckles: chose the .* -> spk_dt.teach/taught.fits" speckles_dm.log && ! grep -q "reused" speckles_dm.log \
    && ! grep -q "the loops' DM" speckles_dm.log \
    || { cat speckles_dm.log; fail "--teach-set: taught anew with the key, said so, no second map (the DM told)"; }
"$FITSDIFF" spk_dt.fits spk_dm.fits 2> /dev/null && fail "--teach-set dm_coupling=0.15: the default's speckles (the key did not reach the loops)"
dmfpr=$(fpr_of spk_dt.teach/taught.fits)
[ "${#dmfpr}" = 16 ] && [ "$dmfpr" != "$fpr" ] || fail "--teach-set: TEACHFPR '$dmfpr', the default's '$fpr'"
# on that run's inputs (one map taught, the DM told: the again-checks at the cost of one teach,
# not the default's two), --teach-again teaches anew (the same map: teach is deterministic); a
# telemetry file that differs by one header card (CHECKSUM renamed, which the reader then does
# not verify; the slopes the same) is another input, and teach runs again, to the same speckles
again dm dm3 timing.txt "${dm[@]}" --teach-again
grep -q "^speckles: chose the .* -> spk_dt.teach/taught.fits" speckles_dm3.log \
    && ! grep -q "reused" speckles_dm3.log || { cat speckles_dm3.log; fail "--teach-again: teach expected"; }
[ "$(fpr_of spk_dt.teach/taught.fits)" = "$dmfpr" ] || fail "--teach-again: another TEACHFPR for the same inputs"
mkdir -p edited
LC_ALL=C sed 's/CHECKSUM=/CHECKSUX=/' obs/slopes_000.fits > edited/slopes_000.fits
cmp -s obs/slopes_000.fits edited/slopes_000.fits && fail "the edited telemetry file is the same"
sed "s|[^ ]*/slopes_000.fits|$PWD/edited/slopes_000.fits|" timing.txt > edited/timing.txt
grep -q "edited/slopes_000.fits" edited/timing.txt || fail "the timing table names no slopes_000.fits"
again dm dm4 edited/timing.txt "${dm[@]}"
grep -q "^speckles: chose the .* -> spk_dt.teach/taught.fits" speckles_dm4.log \
    && ! grep -q "reused" speckles_dm4.log || { cat speckles_dm4.log; fail "another telemetry file: teach expected"; }
[ "$(fpr_of spk_dt.teach/taught.fits)" != "$dmfpr" ] || fail "another telemetry file, the same TEACHFPR"
echo "cli_teach: --teach-again and an edited telemetry header: taught anew; the same speckles"
for bad in "bogus_key=1:unknown setting 'bogus_key'" "dm_coupling=1:dm_coupling=1: must be in \[0, 1)" \
           "dm_coupling:takes key=value"; do
    "$B" speckles timing.txt --science science.fits --actuators actuators.fits --teach-set "${bad%%:*}" -o spk_bad.fits \
        2> speckles_bad.log && fail "--teach-set ${bad%%:*} accepted"
    grep -q -- "--teach-set.*${bad#*:}" speckles_bad.log || { cat speckles_bad.log; fail "--teach-set ${bad%%:*}: the message"; }
    [ ! -e spk_bad.fits ] || fail "--teach-set ${bad%%:*} refused, but spk_bad.fits written"
done
echo "cli_teach: --teach-set dm_coupling=0.15: taught anew, other speckles; bad keys refused by name"
# the system's own control matrix given to the loops (ao_recon) and no dm_coupling: the DM's
# functions from that matrix (ts_coupling.c); this observation's DM is the interpolated surface,
# which its matrix says (the Gaussian functions' best misfit larger), and the map says so
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 \
    --teach-max-loops 4 --teach-work spk_cm.teach --teach-set ao_recon=obs/recon_ao.fits -o spk_cm.fits \
    2> speckles_cm.log || { cat speckles_cm.log; fail "speckles --teach-set ao_recon=obs/recon_ao.fits"; }
! grep -q "the loops' DM" speckles_cm.log && [ ! -e spk_cm.teach/dm-gauss ] \
    || { cat speckles_cm.log; fail "ao_recon given: no second map (the DM's functions from the matrix)"; }
line=$(grep "^speckles: the DM's functions from the loops' control matrix (ao_recon, rank [0-9]*): the interpolated surface" \
    speckles_cm.log) || { cat speckles_cm.log; fail "ao_recon: the DM's functions from the control matrix expected"; }
echo "$line" | awk '{ for (i = 1; i <= NF; i++) if ($i == "%,") g = $(i - 1); s = $(NF - 1) }
    END { if (!(s + 0 < 1 && g + 0 > 5 * (s + 0))) exit 1 }' \
    || fail "ao_recon: the surface's misfit under 1 % and the Gaussian functions' 5 times it expected: $line"
head -c 20000 spk_cm.teach/taught.fits | grep -aq "TEACHCPL=  *0\.0* " \
    || fail "ao_recon: the map's TEACHCPL (the loops' coupling) 0 expected"
echo "cli_teach: ao_recon given: ${line#speckles: }"
# the observation's telemetry as the used subapertures' slopes only (cacao's layout), with the
# system's valid map (from the files, as above, with --valid): the same layers, filter and
# loops as speckles' teach above, so the same map (the same calibration loops' profile misfits,
# training misfit and white slope noise printed); speckles --valid applies it to that telemetry
# (the timing table's rows renamed to those files) to the same NCP error. It runs one loop at a
# time (threads=1), speckles' teach as many at once as there are cores (the calibration loops
# too): a loop is the same whatever runs beside it. Its work folder holds a loop folder with a
# slopes / truewf pair beyond this loop's own (as a longer earlier loop would leave it; learn
# reads every pair; speckles' default teaches into the same OUT.teach every run): teach clears
# it first, or the map would learn from other frames.
mkdir -p taught_v/loop_00
cp obs/slopes_000.fits taught_v/loop_00/slopes_001.fits
cp obs/slopes_000.fits taught_v/loop_00/truewf_001.fits
"$B" teach obs/slopes_valid_000.fits --science science.fits --actuators actuators.fits --pupil pupil.fits \
    --valid valid.fits -o taught_v.fits --work taught_v --loops 4 --max-loops 4 threads=1 > teach_v.log 2>&1 \
    || { cat teach_v.log; fail "teach on valid-only slopes"; }
[ ! -e taught_v/loop_00/slopes_001.fits ] && [ ! -e taught_v/loop_00/truewf_001.fits ] \
    || fail "teach left a stale slopes / truewf pair in a loop folder it used again"
grep -q "ao_modes = 5[3-9]$" teach_v.log || { cat teach_v.log; fail "teach (valid-only): the modal filter expected"; }
grep -q "chose the space-time map" teach_v.log || { cat teach_v.log; fail "teach (valid-only): the space-time map expected"; }
for what in "calibration loops (ao_modes -> knee): .*" "misses the loops' residual by .* nm" "white noise .*"; do
    a=$(grep -o "$what" teach_v.log)
    b=$(grep -o "$what" speckles_dt.log)
    [ -n "$a" ] && [ "$a" = "$b" ] || fail "teach (valid-only) against speckles' teach: '$a' against '$b'"
done
sed 's/slopes_0/slopes_valid_0/' timing.txt > obs/timing_v.txt
etv=$(ncp_with taught_v.fits tv obs/timing_v.txt --valid valid.fits --pupil pupil.fits)
grep -q "224 slopes x 5 lags" speckles_tv.log || { cat speckles_tv.log; fail "speckles did not narrow the taught map"; }
echo "cli_teach: teach on the used subapertures' slopes: $etv nm (speckles' default on the full layout $edt nm)"
[ "$etv" = "$edt" ] || fail "teach on the used subapertures' slopes $etv nm against speckles' default $edt nm"
# slopes in which `wind` tracks no layer: a zonal loop (ao_rcond 0.05) of one 15 m/s layer on the
# same system, seed 6, whose slopes are mostly its sensor's noise amplified. speckles' default still
# teaches: the speed from the slopes' time correlation (measured 14.0 m/s), loops near it in any
# direction, their space-time map at lags of 1 and 2 frames (TEACHSEL 'spacetime_prior', the loops'
# folders removed; the per-frame map beside it). The NCP error below the von Karman map's (measured
# 34.9 nm against 71.2 on 2026-12-07, 32.3 against 52.3 when first written: the joint fit's radial g
# terms, added between, cost both here, docs/estimator.md "Where the radial terms cost most"; the
# ideal speckles' 26.1 then, 29.0 now; before the lags, the per-frame map, 35.8; bound 0.85 times
# vk's). Its first 12 loops only (--teach-max-loops 12): the 40 its learning curve asked for gave
# the same 32.3 nm when first written, at three times the cost. The DM told, the observation's own
# (--teach-set dm_coupling=0, the interpolated surface: the map the default's choice by the science
# frames keeps here, to the same speckles: fitsdiff, by hand), so one map is taught, not two (the
# choice is the first run's subject).
mkdir -p nowind && cd nowind || fail "cd nowind"
"$B" simulate ../my.conf nlayers=1 layer_frac=1 layer_speed=15 layer_dir=30 seed=6 ao_rcond=0.05 -o obs --quiet > /dev/null 2>&1 \
    || fail "simulate the zonal loop without a layer to track"
"$B" reduce obs/raw_000.fits obs/raw_001.fits obs/raw_002.fits --dark obs/dark.fits --flat obs/flat.fits \
    -o science.fits 2> reduce.log || fail "reduce (no layer)"
"$B" sync science.fits obs/handshake.log -o timing.txt --ratio-min 5 --ratio-max 8 > sync.log || fail "sync (no layer)"
cp obs/actuators.fits actuators.fits
e_nw=$(ncp_with teach nw timing.txt --pupil obs/pupil.fits --teach-max-loops 12 --teach-set dm_coupling=0)
grep -q "none tracked: the slopes' time correlation" speckles_nw.log \
    && grep -q "^speckles: 12 loops simulated.*; lags 0,-1,1,-2,2 WFS frames; the space-time map misses" speckles_nw.log \
    && grep -q "chose the space-time map of loops at the slopes' speed" speckles_nw.log \
    && head -c 14400 spk_nw.teach/taught.fits | grep -aq "TEACHSEL= 'spacetime_prior'" \
    && [ -s spk_nw.teach/perframe.fits ] \
    && ! ls -d spk_nw.teach/prior_* spk_nw.teach/speed_* > /dev/null 2>&1 \
    || { cat speckles_nw.log; fail "speckles (no layer): the map taught at the slopes' speed, its loops removed"; }
psp=$(head -c 14400 spk_nw.teach/taught.fits | grep -ao "TEACHPSP= *[0-9.E+-]*" | sed 's/TEACHPSP= *//')
awk -v v="$psp" 'BEGIN { exit !(v >= 11.25 && v <= 18.75) }' || fail "teach (no layer): speed $psp m/s, the layer's 15 within 25 %"
e_vk=$(ncp_with vk nwvk timing.txt --pupil obs/pupil.fits)
echo "cli_teach: no layer tracked: the slopes' speed $psp m/s; NCP $e_nw nm (von Karman map $e_vk nm)"
awk -v a="$e_nw" -v b="$e_vk" 'BEGIN { exit !(a <= 0.85 * b) }' || fail "no layer: taught $e_nw nm, vk $e_vk nm"
cd .. || fail "cd .."
echo "cli_teach: ok"

# docs/telemetry.md's recipe for a reconstructor learned from simulated closed loops, run as
# written there (the training loops on the observation's actuators.fits, valid.fits and
# pupil.fits, their first layer at the wind `specklewfs wind` finds in the observation's
# slopes: 14.64 m/s toward 0 deg for its 15 m/s layer) on a small system (my.conf: the
# 12 x 12 Shack-Hartmann of 217 actuators on a 66-sample pupil, 3 cubes of 60 camera frames):
# six simulated loops -> learn -> speckles --recon on an observation of its own seed (15/22
# m/s), then estimate and pupil --truth. The learned map must come out no worse than the
# default reconstructor on that observation (measured 23.3 nm against 23.3: on so small a data
# set the two are alike through the whole path; the gain is in docs/telemetry.md's matrix),
# and learn must print the held-out check for every folder (measured 0.65-0.67, training
# 0.55). The same map given to the linear model as a control matrix over the influence
# functions gives the same NCP error within 10 % (measured 23.4 nm). A space-time map of the
# same loops (learn --lags) goes through speckles, which prints its two checks against the
# observation (the winds, the slopes' correlation at the lags).
# usage: bash cli_learn.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
cd "$D" || fail "cd $D"
cp "$(dirname "$0")/../config/small-loop.conf" my.conf || fail "config/small-loop.conf"
# the observation: two layers at 15 / 22 m/s, its own seed
"$B" simulate my.conf layer_speed=15,22 vib_amp=0.3 seed=9 export_modal=1 -o obs --quiet > /dev/null 2>&1 || fail "simulate obs"
"$B" reduce obs/raw_000.fits obs/raw_001.fits obs/raw_002.fits --dark obs/dark.fits --flat obs/flat.fits \
    -o science.fits 2> reduce.log || fail "reduce"
"$B" sync science.fits obs/handshake.log -o timing.txt --ratio-min 5 --ratio-max 8 > sync.log || fail "sync"
cp obs/actuators.fits actuators.fits
cp obs/valid.fits valid.fits
cp obs/pupil.fits pupil.fits
cp obs/slopes_0*.fits .  # the observation's telemetry, as the recipe's `wind` reads it
# the recipe, with `specklewfs` the binary under test
recipe=$(sed -n '/<!-- learn-recipe:start -->/,/<!-- learn-recipe:end -->/p' \
    "$(dirname "$0")/../docs/telemetry.md" | sed '1,2d;$d' | sed '$d')
[ -n "$recipe" ] || fail "no learn recipe in docs/telemetry.md"
specklewfs() { "$B" "$@"; }
eval "$recipe" > recipe.log 2>&1 || { cat recipe.log; fail "the recipe failed"; }
[ -s learned.fits ] && [ -s speckles.fits ] && [ -s science_m.fits ] || fail "the recipe left no map or speckles"
[ "$(ls -d train/*/ | wc -l)" = 6 ] || fail "the recipe should simulate six loops"
grep -q "learn: held out, all 6:" recipe.log || { cat recipe.log; fail "learn printed no held-out check"; }
[ "$(grep -c '^  train/' recipe.log)" = 6 ] || { cat recipe.log; fail "learn should list the six folders"; }
"$B" estimate science_m.fits speckles.fits -o halo_l.fits > /dev/null 2>&1 || fail "estimate (learned)"
"$B" pupil halo_l.fits -o pupil_l.fits --truth obs/truth.fits > pupil_l.log || fail "pupil (learned)"
# the same map as the linear model's control matrix over the actuators' influence functions
# (how a system outside the simulator uses it): the same wavefronts through another
# representation
"$B" speckles timing.txt --science science.fits --basis obs/influence.fits --control learned.fits \
    --match science.fits sci_c.fits -o spk_c.fits 2> speckles_c.log || { cat speckles_c.log; fail "speckles --control"; }
"$B" estimate sci_c.fits spk_c.fits -o halo_c.fits > /dev/null 2>&1 || fail "estimate (control)"
"$B" pupil halo_c.fits -o pupil_c.fits --truth obs/truth.fits > pupil_c.log || fail "pupil (control)"
# the von Karman map on the same observation (--recon vk, the default before --recon teach;
# "default" in the messages below)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --recon vk --match science.fits sci_d.fits \
    -o spk_d.fits 2> speckles_d.log || fail "speckles (vk)"
"$B" estimate sci_d.fits spk_d.fits -o halo_d.fits > /dev/null 2>&1 || fail "estimate (default)"
"$B" pupil halo_d.fits -o pupil_d.fits --truth obs/truth.fits > pupil_d.log || fail "pupil (default)"
# the self-check chooses among the three halos of the same frames: it prints the table and
# uses one of them, no worse than the best by more than 5 %
"$B" pupil halo_d.fits halo_l.fits halo_c.fits -o pupil_ch.fits --truth obs/truth.fits > pupil_ch.log \
    || { cat pupil_ch.log; fail "pupil with three halos"; }
[ "$(grep -c '<- used' pupil_ch.log)" = 1 ] && grep -q "chosen by the self-check among 3 halos" pupil_ch.log \
    || { cat pupil_ch.log; fail "pupil printed no choice"; }
eh=$(ncp_error pupil_ch.log)
el=$(ncp_error pupil_l.log)
ed=$(ncp_error pupil_d.log)
ec=$(ncp_error pupil_c.log)
echo "cli_learn: NCP error with the learned map $el nm (as a control matrix $ec nm), with the von Karman map (vk) $ed nm"
sed -n '/held out in turn/,$p' recipe.log | head -8
awk -v l="$el" -v d="$ed" 'BEGIN { exit !(l > 0 && d > 0 && l < 1.05 * d && d < 40) }' \
    || fail "learned $el nm against the default $ed nm"
echo "cli_learn: the self-check chose $(awk '/<- used/ { print $1 }' pupil_ch.log): $eh nm"
awk -v h="$eh" -v a="$el" -v b="$ed" -v c="$ec" \
    'BEGIN { m = a; if (b < m) m = b; if (c < m) m = c; exit !(h > 0 && h <= 1.05 * m) }' \
    || fail "the halo chosen by the self-check: $eh nm, the three $el $ed $ec nm"
awk -v l="$el" -v c="$ec" 'BEGIN { exit !(c > 0 && c < 1.1 * l && l < 1.1 * c) }' \
    || fail "the learned map as a control matrix $ec nm against $el nm as a reconstructor"
# a space-time map of the same loops (their second layers drawn from a spread, not the
# observation's): learn records the loops' layers and slopes' correlation, and speckles prints
# both checks against the observation's telemetry, whose two layers (15 and 22 m/s) `wind`
# finds
"$B" learn train/* -o lagged.fits --lags 0,-4,4 --no-heldout > learn_lags.log 2>&1 || { cat learn_lags.log; fail "learn --lags"; }
grep -q "x 3 lags (0,-4,4)" learn_lags.log || { cat learn_lags.log; fail "learn --lags printed no lags"; }
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --recon lagged.fits \
    -o spk_st.fits 2> speckles_st.log || { cat speckles_st.log; fail "speckles with a space-time map"; }
grep -q "given space-time reconstructor lagged.fits: 288 slopes x 3 lags" speckles_st.log \
    && grep -q "space-time map: the slopes' correlation, this telemetry's against the training loops'" speckles_st.log \
    && grep -q "space-time map: this telemetry's slopes show 2 frozen-flow layers" speckles_st.log \
    || { cat speckles_st.log; fail "speckles printed no check of the space-time map"; }
grep "space-time map" speckles_st.log | cut -c1-160
# teach: the same rule in one command (wind -> loops at the layers found -> the space-time map
# and its checks -> the choice; the loops in taught.teach, the default work folder). Its two layers must be the observation's (15 and 22 m/s), its
# map the space-time one (neither check warns on loops of the same system), and through the
# whole path no worse than the default reconstructor by more than 10 %.
"$B" teach obs/slopes_0*.fits --system my.conf vib_amp=0.3 -o taught.fits --loops 4 --max-loops 4 > teach.log 2>&1 \
    || { cat teach.log; fail "teach"; }
grep -q "2 frozen-flow layers" teach.log && grep -q "chose the space-time map (neither check warned)" teach.log \
    || { cat teach.log; fail "teach: two layers and the space-time map expected"; }
awk '/^teach:   layer [12]: / { v[++n] = $4 } END { exit !(n == 2 && ((v[1] > 13.5 && v[1] < 16.5 && v[2] > 19.8 && v[2] < 24.2) ||
    (v[2] > 13.5 && v[2] < 16.5 && v[1] > 19.8 && v[1] < 24.2))) }' teach.log || { cat teach.log; fail "teach: the layers"; }
# the observation's file holds ~1780 frames: four loops that long would give the map (5 lags x
# 224 slopes = 1120 inputs) 6.4 frames per input; teach lengthens them to 10 (4 x 2800 frames)
grep -q "^teach: 4 loops simulated of 2800 WFS frames (lengthened from 17[0-9][0-9]: the map's 1120 inputs need 10 frames each)" \
    teach.log || { grep "loops simulated" teach.log; fail "teach: loops of 10 frames per map input expected"; }
# --max-loops 4: no more loops to add, so no learning curve measured (six solves of the map's
# normal equations saved; python/tests/test_realdata.py lets teach measure it and add loops)
grep -q "^teach: the space-time map's learning curve: not measured (at most 4 loops: no more to add)" \
    teach.log || { grep "learning curve" teach.log; fail "teach: the learning curve's line expected"; }
head -c 8640 taught.fits | grep -aq "NLAGS   =                    5" || fail "teach: taught.fits is no 5-lag cube"
head -c 8640 taught.fits | grep -aq "TEACHSEL= 'spacetime'" || fail "teach: the map's header should say it was chosen as such"
[ "$(ls -d taught.teach/loop_*/ | wc -l)" = 4 ] && [ -s taught.teach/spacetime.fits ] \
    || fail "teach: the loops or the map tried (in the default work folder taught.teach)"
# my.conf gives no ao_modes: the loops' modal filter from the slopes, the observation's loop
# controlling the simulator's 56 modes (within 3), its calibration loops kept in modes_NN/
awk '/modal filter from the slopes/ { for (i = 1; i <= NF; i++) if ($i == "ao_modes" && $(i + 1) == "=") k = $(i + 2) + 0 }
    END { exit !(k >= 53 && k <= 59) }' teach.log || { cat teach.log; fail "teach: the modal filter from the slopes (56)"; }
head -c 11520 taught.fits | grep -aq "TEACHMSR= 'slopes" && [ -d taught.teach/modes_00 ] \
    || fail "teach: TEACHMSR = 'slopes' and a calibration loop expected"
# the profiles it read the filter from: modes.tsv (a row per mode after piston, the observation
# and the calibration loop) and modes.png
head -1 taught.teach/modes.tsv | grep -q "^# mode	observation	loop_5[3-9]$" \
    && [ "$(grep -vc '^#' taught.teach/modes.tsv)" -gt 150 ] && [ -s taught.teach/modes.png ] \
    || { head -3 taught.teach/modes.tsv; fail "teach: modes.tsv / modes.png"; }
# ncp_with MAP TAG TIMING [speckles options]: the whole path with a taught map (speckles --recon
# MAP, estimate, pupil --truth; files *_TAG), the NCP error [nm] on stdout
ncp_with() {
    local map=$1 tag=$2 timing=$3
    shift 3
    "$B" speckles "$timing" --science science.fits --actuators actuators.fits --recon "$map" "$@" --match science.fits \
        "sci_$tag.fits" -o "spk_$tag.fits" 2> "speckles_$tag.log" || { cat "speckles_$tag.log" >&2; fail "speckles ($map)"; }
    "$B" estimate "sci_$tag.fits" "spk_$tag.fits" -o "halo_$tag.fits" > /dev/null 2>&1 || fail "estimate ($map)"
    "$B" pupil "halo_$tag.fits" -o "pupil_$tag.fits" --truth obs/truth.fits > "pupil_$tag.log" || fail "pupil ($map)"
    ncp_error "pupil_$tag.log"
}
et=$(ncp_with taught.fits t timing.txt)
echo "cli_learn: teach: NCP error $et nm with the taught map, $ed nm with vk"
awk -v t="$et" -v d="$ed" 'BEGIN { exit !(t > 0 && t < 1.1 * d) }' || fail "taught $et nm against the default $ed nm"
# no description at all: the system from the observation's own files (the science cube's
# geometry, the DM, the pupil), the rest the simulator's defaults; the same layers and filter,
# and through the whole path within 1 nm of the described teach
"$B" teach obs/slopes_0*.fits --science science.fits --actuators actuators.fits --pupil pupil.fits -o taught_f.fits \
    --work taught_f --loops 4 --max-loops 4 > teach_f.log 2>&1 || { cat teach_f.log; fail "teach from the observation's files"; }
grep -q "2 frozen-flow layers" teach_f.log && grep -q "ao_modes = 5[3-9]$" teach_f.log \
    || { cat teach_f.log; fail "teach from files: two layers and the modal filter expected"; }
# the loops' slope noise is the observation's white slope noise, measured from its slopes (the
# simulator's 3e-8 rad rms; measured 3.0e-8), a small share of the slopes' variance (under
# 5 %), in the map's header too
awk '/the slopes. white noise/ { for (i = 1; i <= NF; i++) { if ($i == "noise") v = $(i + 1) + 0;
    if ($i == "%" && $(i + 1) == "of") p = $(i - 1) + 0 } }
    END { exit !(v > 2.7e-8 && v < 3.3e-8 && p > 0 && p < 5) }' teach_f.log && grep -q "the loops' slope_noise [0-9.e-]* rad, the same$" teach_f.log \
    || { grep "white noise" teach_f.log; fail "teach: the white slope noise (3e-8) expected"; }
head -c 14400 taught_f.fits | grep -aq "TEACHNOI=" || fail "teach: TEACHNOI expected in the map's header"
etf=$(ncp_with taught_f.fits tf timing.txt)
# a second teach in the same work folder (as speckles' default does on every run), one loop
# folder holding a slopes / truewf pair beyond this loop's own (as a longer earlier loop would
# leave it; learn reads every pair): teach clears it first, so the map learns from the same
# frames, its training misfit printed the same
cp taught_f/loop_00/slopes_000.fits taught_f/loop_00/slopes_001.fits
cp taught_f/loop_00/truewf_000.fits taught_f/loop_00/truewf_001.fits
"$B" teach obs/slopes_0*.fits --science science.fits --actuators actuators.fits --pupil pupil.fits -o taught_f2.fits \
    --work taught_f --loops 4 --max-loops 4 > teach_f2.log 2>&1 || { cat teach_f2.log; fail "teach again in the same work folder"; }
[ ! -e taught_f/loop_00/slopes_001.fits ] && [ ! -e taught_f/loop_00/truewf_001.fits ] \
    || fail "teach left a stale slopes / truewf pair in a loop folder it used again"
m1=$(grep -o "misses the loops' residual by .* nm" teach_f.log)
m2=$(grep -o "misses the loops' residual by .* nm" teach_f2.log)
[ -n "$m1" ] && [ "$m1" = "$m2" ] || fail "teach in a used work folder: '$m2' against '$m1'"
echo "cli_learn: teach from the observation's files: $etf nm (described: $et nm; vk $ed nm)"
awk -v a="$etf" -v b="$et" 'BEGIN { exit !(a > 0 && a - b < 1 && b - a < 1) }' || fail "teach from files $etf nm against $et nm"
# speckles' default (--recon teach) is that teach run inside speckles on the same files (the
# timing table's telemetry, --science, --actuators, --pupil): with the same loops
# (--teach-loops 4 --teach-max-loops 4) the same map, in spk_dt.teach/ beside its output (the loops' folders
# removed, the maps and the modes' profile kept), and the same NCP error
# as the map of the command above given with --recon and the same --pupil
etfp=$(ncp_with taught_f.fits tfp timing.txt --pupil pupil.fits)
"$B" speckles timing.txt --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 --teach-max-loops 4 \
    --match science.fits sci_dt.fits -o spk_dt.fits 2> speckles_dt.log || { cat speckles_dt.log; fail "speckles (default)"; }
grep -q "^speckles: chose the space-time map (neither check warned) -> spk_dt.teach/taught.fits" speckles_dt.log \
    && grep -q "given space-time reconstructor spk_dt.teach/taught.fits: 288 slopes x 5 lags" speckles_dt.log \
    && grep -q "ao_modes = 5[3-9]$" speckles_dt.log && [ -s spk_dt.teach/spacetime.fits ] \
    && [ -s spk_dt.teach/modes.tsv ] && ! ls -d spk_dt.teach/loop_* spk_dt.teach/modes_* > /dev/null 2>&1 \
    || { cat speckles_dt.log; fail "speckles (default): the taught map in spk_dt.teach, its loops removed"; }
"$B" estimate sci_dt.fits spk_dt.fits -o halo_dt.fits > /dev/null 2>&1 || fail "estimate (default)"
"$B" pupil halo_dt.fits -o pupil_dt.fits --truth obs/truth.fits > pupil_dt.log || fail "pupil (default)"
edt=$(ncp_error pupil_dt.log)
echo "cli_learn: speckles' default (teach inside speckles): $edt nm; teach's map given: $etfp nm"
[ -n "$edt" ] && [ "$edt" = "$etfp" ] || fail "speckles' default $edt nm against teach's map $etfp nm"
# stream takes that space-time map too (each batch's slopes stacked at its lags): the same NCP
# error through stream's own estimate, in batches of 7 camera frames
"$B" stream --timing timing.txt --science science.fits --recon spk_dt.teach/taught.fits --actuators actuators.fits \
    --pupil pupil.fits --batch 7 -o halo_stst.fits > stream_st.log 2>&1 || { cat stream_st.log; fail "stream with the taught map"; }
grep -q "^stream: space-time reconstructor of 5 lags (0,-6,6,-12,12 WFS frames)" stream_st.log \
    || { cat stream_st.log; fail "stream: the space-time map's lags expected"; }
"$B" pupil halo_stst.fits -o pupil_stst.fits --truth obs/truth.fits > pupil_stst.log || fail "pupil (stream)"
est=$(ncp_error pupil_stst.log)
echo "cli_learn: stream with speckles' taught map: $est nm"
[ "$est" = "$edt" ] || fail "stream with the taught map $est nm against speckles' $edt nm"
# beside it the per-frame map of the same loops (the lag-0 block of the same sums), for live:
# one frame's slopes in, within 10 % of the space-time map through the whole path
[ -s spk_dt.teach/perframe.fits ] && ! head -c 8640 spk_dt.teach/perframe.fits | grep -aq "NLAGS" \
    || fail "speckles' teach folder: a per-frame map perframe.fits expected"
"$B" stream --timing timing.txt --science science.fits --recon spk_dt.teach/perframe.fits --actuators actuators.fits \
    --pupil pupil.fits -o halo_stpf.fits > stream_pf.log 2>&1 || { cat stream_pf.log; fail "stream with perframe.fits"; }
"$B" pupil halo_stpf.fits -o pupil_stpf.fits --truth obs/truth.fits > pupil_stpf.log || fail "pupil (perframe.fits)"
epf=$(ncp_error pupil_stpf.log)
echo "cli_learn: stream with the taught per-frame map: $epf nm (space-time $edt nm)"
awk -v a="$epf" -v b="$edt" 'BEGIN { exit !(a > 0 && a < 1.1 * b) }' || fail "the per-frame map $epf nm against $edt nm"
# dt_again TAG [options]: speckles' default as above, into another output, in the same teach
# folder (the NCP error on stdout)
dt_again() {
    local tag=$1
    shift
    "$B" speckles "$@" --science science.fits --actuators actuators.fits --pupil pupil.fits --teach-loops 4 --teach-max-loops 4 \
        --teach-work spk_dt.teach --match science.fits "sci_$tag.fits" -o "spk_$tag.fits" 2> "speckles_$tag.log" \
        || { cat "speckles_$tag.log" >&2; fail "speckles ($tag)"; }
    "$B" estimate "sci_$tag.fits" "spk_$tag.fits" -o "halo_$tag.fits" > /dev/null 2>&1 || fail "estimate ($tag)"
    "$B" pupil "halo_$tag.fits" -o "pupil_$tag.fits" --truth obs/truth.fits > "pupil_$tag.log" || fail "pupil ($tag)"
    ncp_error "pupil_$tag.log"
}
# a later run on the same inputs reuses that map at once (its TEACHFPR: the telemetry's and
# the system files' contents, the description and teach's options are this run's), to the
# same NCP error; --teach-again teaches anew (the same map: teach is deterministic); a
# telemetry file that differs by one header card (CHECKSUM renamed, which the reader then
# does not verify; the slopes the same) is another input, and teach runs again
fpr_of() { head -c 20000 "$1" | grep -ao "TEACHFPR= '[0-9a-f]*'" | cut -d"'" -f2; }
fpr=$(fpr_of spk_dt.teach/taught.fits)
[ "${#fpr}" = 16 ] || fail "speckles' taught map carries no TEACHFPR"
e2=$(dt_again dt2 timing.txt)
grep -q "^speckles: reused spk_dt.teach/taught.fits, taught by an earlier run for the same telemetry, system files and teach options (TEACHFPR = '$fpr'; 4 loops): the space-time map" \
    speckles_dt2.log && ! grep -q "simulating the loops" speckles_dt2.log \
    || { cat speckles_dt2.log; fail "speckles on the same inputs: the taught map should be reused"; }
[ "$e2" = "$edt" ] || fail "the reused map: $e2 nm against $edt nm"
e3=$(dt_again dt3 timing.txt --teach-again)
grep -q "^speckles: chose the space-time map (neither check warned) -> spk_dt.teach/taught.fits" speckles_dt3.log \
    && ! grep -q "reused" speckles_dt3.log || { cat speckles_dt3.log; fail "--teach-again: teach expected"; }
[ "$e3" = "$edt" ] || fail "--teach-again: $e3 nm against $edt nm"
mkdir -p edited
LC_ALL=C sed 's/CHECKSUM=/CHECKSUX=/' obs/slopes_000.fits > edited/slopes_000.fits
cmp -s obs/slopes_000.fits edited/slopes_000.fits && fail "the edited telemetry file is the same"
sed "s|[^ ]*/slopes_000.fits|$PWD/edited/slopes_000.fits|" timing.txt > edited/timing.txt
grep -q "edited/slopes_000.fits" edited/timing.txt || fail "the timing table names no slopes_000.fits"
e4=$(dt_again dt4 edited/timing.txt)
grep -q "^speckles: chose the space-time map (neither check warned) -> spk_dt.teach/taught.fits" speckles_dt4.log \
    && ! grep -q "reused" speckles_dt4.log || { cat speckles_dt4.log; fail "another telemetry file: teach expected"; }
[ "$(fpr_of spk_dt.teach/taught.fits)" != "$fpr" ] \
    || fail "another telemetry file, the same TEACHFPR"
[ "$e4" = "$edt" ] || fail "the edited header changed the NCP error: $e4 nm against $edt nm"
echo "cli_learn: speckles' default again on the same inputs: reused the map ($e2 nm); --teach-again $e3 nm; edited telemetry header: taught anew, $e4 nm"
# the system from files needs both files; without any system teach says what it needs
"$B" teach obs/slopes_000.fits --science science.fits -o bad.fits > bad.log 2>&1 && fail "teach without --actuators"
grep -q "needs both --science and --actuators" bad.log || { cat bad.log; fail "teach: --science alone"; }
"$B" teach obs/slopes_000.fits -o bad.fits > bad.log 2>&1 && fail "teach without a system"
grep -q "needs the system: --science SCI.fits --actuators ACT.fits" bad.log || { cat bad.log; fail "teach: no system"; }
[ -e bad.fits ] && fail "teach left a map after a usage error"
# the observation's telemetry as the used subapertures' slopes only (cacao's layout), with the
# system's valid map (from the files, as above, with --valid): the same layers, filter and
# loops, so the same map; speckles --valid applies it to that telemetry (the timing table's
# rows renamed to those files) to the same NCP error
"$B" teach obs/slopes_valid_000.fits --science science.fits --actuators actuators.fits --pupil pupil.fits \
    --valid valid.fits -o taught_v.fits --work taught_v --loops 4 --max-loops 4 > teach_v.log 2>&1 \
    || { cat teach_v.log; fail "teach on valid-only slopes"; }
grep -q "ao_modes = 5[3-9]$" teach_v.log || { cat teach_v.log; fail "teach (valid-only): the modal filter expected"; }
grep -q "chose the space-time map" teach_v.log || { cat teach_v.log; fail "teach (valid-only): the space-time map expected"; }
[ "$(grep "white noise" teach_v.log)" = "$(grep "white noise" teach_f.log)" ] \
    || { grep "white noise" teach_v.log teach_f.log; fail "teach (valid-only): another white slope noise than the full layout's"; }
sed 's/slopes_0/slopes_valid_0/' timing.txt > obs/timing_v.txt
etv=$(ncp_with taught_v.fits tv obs/timing_v.txt --valid valid.fits)
grep -q "224 slopes x 5 lags" speckles_tv.log || { cat speckles_tv.log; fail "speckles did not narrow the taught map"; }
echo "cli_learn: teach on the used subapertures' slopes: $etv nm (the full layout's $etf nm)"
awk -v a="$etv" -v b="$etf" 'BEGIN { exit !(a > 0 && a - b < 0.2 && b - a < 0.2) }' || fail "valid-only teach $etv nm against $etf nm"
# the loops described with ten times the slope noise: the correlation check warns, and with one
# layer found teach falls back to the per-frame map of the layer and random seconds. The
# observation's loop controls 36 modes, which teach finds from its slopes (within 15 %).
"$B" simulate my.conf nlayers=1 layer_frac=1 layer_speed=15 layer_dir=30 seed=5 ao_modes=36 -o obs1 --quiet > /dev/null 2>&1 \
    || fail "simulate the one-layer observation"
"$B" teach obs1/slopes_0*.fits --system my.conf slope_noise=3e-7 -o taught1.fits --work taught1 --loops 2 > teach1.log 2>&1 \
    || { cat teach1.log; fail "teach (one layer)"; }
grep -q "warning: .* frames apart this telemetry's slopes correlate" teach1.log \
    && grep -q "chose the per-frame map of the measured layer and random second layers" teach1.log \
    || { cat teach1.log; fail "teach: the correlation check should warn and the per-frame map be chosen"; }
head -c 8640 taught1.fits | grep -aq "NLAGS" && fail "teach: the per-frame map should hold no lags"
grep -q "the loops' slope_noise 3e-07 rad, as given$" teach1.log || { grep "white noise" teach1.log; fail "teach: slope_noise as given"; }
[ "$(ls -d taught1/mixed_*/ | wc -l)" = 2 ] || fail "teach: two loops of a random second layer expected"
awk '/modal filter from the slopes/ { for (i = 1; i <= NF; i++) if ($i == "ao_modes" && $(i + 1) == "=") k = $(i + 2) + 0 }
    END { exit !(k >= 31 && k <= 41) }' teach1.log || { cat teach1.log; fail "teach: the modal filter from the slopes (36)"; }
# given ao_modes: used as given, no calibration loop
"$B" teach obs1/slopes_0*.fits --system my.conf ao_modes=36 -o taught2.fits --work taught2 --loops 2 > teach2.log 2>&1 \
    || { cat teach2.log; fail "teach (ao_modes given)"; }
grep -q "modal filter: ao_modes = 36, as given" teach2.log && [ ! -d taught2/modes_00 ] \
    && head -c 11520 taught2.fits | grep -aq "TEACHMSR= 'given" || { cat teach2.log; fail "teach: ao_modes as given"; }
head -c 8640 taught1.fits | grep -aq "TEACHSEL= 'perframe_mixed'" && head -c 8640 taught1.fits | grep -aq "TEACHWRN=  *2 " \
    || fail "teach: the map's header should say the per-frame map of random seconds, the correlation check warning"
# a system of another geometry than the telemetry's: refused, naming the file; no map left
"$B" teach obs1/slopes_000.fits --system my.conf nsub=16 -o bad.fits --work badw --loops 2 > bad.log 2>&1 \
    && fail "teach accepted a 16 x 16 system for 12 x 12 telemetry"
grep -q "obs1/slopes_000.fits: 288 slopes per WFS frame; the system's 16 x 16" bad.log || { cat bad.log; fail "teach: the message"; }
[ -e bad.fits ] && fail "teach left a map after failing"
[ -e badw ] && fail "teach left the work folder it made (empty) after refusing its input"
echo "cli_learn: ok"

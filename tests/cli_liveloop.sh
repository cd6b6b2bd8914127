# The NCP loop closed in simulation through shared-memory streams (specklewfs liveloop):
# simulate mode=timeseries -> reduce -> sync -> replay -> live -> DM stream -> simulate ...
# on the small time series of cli_telemetry.sh. Asserts that live used every camera frame
# and that the residual NCP (piston, tip, tilt removed) falls: 90.7 -> 59 -> 42 nm measured
# (seeds 1 and 2; with the 36-mode filter, gain 0.5).
# usage: bash cli_liveloop.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"

"$B" liveloop -o "$D/loop" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=60 cube_gap=150 layer_speed=30,40 \
    vib_amp=0.6 jitter_amp=0.15 seed=1 --iterations 2 --speed 4 --modes 36 > "$D/loop.log" 2> "$D/loop.err" \
    || { cat "$D/loop.err"; fail "liveloop"; }
cat "$D/loop.log"
r0=$(awk '$1 == "0" {print $2}' "$D/loop.log")
r2=$(awk '$1 == "2" {print $2}' "$D/loop.log")
[ -n "$r0" ] && [ -n "$r2" ] || fail "no residual table"
awk -v a="$r0" -v b="$r2" 'BEGIN { exit !(a > 80 && a < 100 && b < 0.6 * a) }' \
    || fail "residual $r0 -> $r2 nm: expected ~91 nm falling below 60 % of it"
[ "$(awk '($1 == "0" || $1 == "1") && $5 == 180' "$D/loop.log" | wc -l)" -eq 2 ] || fail "live did not use all 180 frames"
for k in 00 01; do
    [ -f "$D/loop/iter_$k/halo.fits" ] && [ -f "$D/loop/iter_$k/pupil.fits" ] || fail "iteration $k products"
done
[ -f "$D/loop/dm_01.fits" ] || fail "the simulator's DM map of iteration 1"
ls "$D/loop/shm" | grep -q . && fail "streams left in $D/loop/shm"
"$B" liveloop -o "$D/x" --iterations 0 > /dev/null 2>&1
[ $? -eq 2 ] || fail "--iterations 0 should be a usage error"
echo "cli_liveloop: ok"

# A science camera faster than the WFS (0.8 WFS frames per camera frame, as a 2.5 kHz camera
# on a 2 kHz WFS): simulate frame_ratio=0.8, then reduce -> sync -> speckles -> estimate ->
# pupil with default options. sync must find the ratio and the lag, speckles must take the
# sub-frame exposures (each the field interpolated in time between the two WFS frames that
# bracket it), and the NCP must come out close to the simulator's ideal speckles (measured
# 19.7 nm against 17.2 nm ideal with the AO residual's time mean kept, lib_cli.sh
# resmean_bounds; speckles refused any ratio below 1 before).
# usage: bash cli_fastcam.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
SPK_RECON=(--recon vk) # the von Karman map: this test is not about the reconstructor
"$B" simulate mode=timeseries --quiet -o "$D/sim" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=400 \
    cube_gap=150 layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 frame_ratio=0.8 seed=1 > "$D/sim.log" || fail "simulate"
d="$D"
reduce_sync "$d" --ratio-min 0.5 --ratio-max 8
ratio=$(awk '$1 == "ratio" {print $2}' "$D/timing.txt")
lag=$(awk '$1 == "lag" {print $2}' "$D/timing.txt")
echo "sync: ratio $ratio (true 0.8), lag $lag (true 2.6: 3 frames less the start's fraction 0.4)"
awk -v r="$ratio" -v l="$lag" 'BEGIN { d = r - 0.8; e = l - 2.6; if (d < 0) d = -d; if (e < 0) e = -e; exit !(d < 0.002 && e < 0.2) }' \
    || fail "sync: ratio $ratio, lag $lag"
e=$(speckles_pupil "$d")
grep -q "1200 frames from 3 of 3 timing-table rows" "$d/speckles.log" || { cat "$d/speckles.log"; fail "speckles frame count"; }
ei=$(ideal_pupil "$d")
set -- $(keep_errors "$d")
echo "NCP error: $e nm from the slopes, $ei nm from the ideal speckles; with the residual mean kept $1 and $2 nm"
awk -v a="$e" 'BEGIN { exit !(a < 30) }' || fail "NCP error $e nm"
resmean_bounds fastcam "$e" "$ei" "$1" "$2" 1.3
echo "cli_fastcam: ok"

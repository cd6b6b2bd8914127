# Any actuator layout: a DM whose actuators sit on a square grid clipped to a circle (the
# most common DM), at a pitch that gives fewer actuators than valid slopes and at one that
# gives more (the MMT's own situation), through the default path (reduce -> sync ->
# speckles -> estimate -> pupil). The Clough-Tocher gradients of a square grid used to fail
# ("neighbours do not determine a quadratic"), and with more actuators than valid slopes the
# default reconstructor stopped ("the slope noise estimate is 0"). Bounds (lib_cli.sh
# resmean_bounds): the speckles from the slopes within 1.3x the ideal speckles' NCP error with
# the AO residual's time mean kept in both (measured 30.2 against 29.1 nm at 0.45 m pitch,
# 137 actuators; 23.4 against 23.4 nm at 0.36 m, 277 actuators, before the mean was taken
# out), and the default (the mean taken out) no worse than keeping it.
# usage: bash cli_actuators.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
SPK_RECON=(--recon vk) # the von Karman map: this test is not about the reconstructor
run() { # run <name> <pitch>: prints the actuator count last
    local d="$D/$1"
    "$B" simulate mode=timeseries --quiet -o "$d/sim" pupn=66 pupdx=0.1 screen_n=1024 ncubes=3 cube_frames=60 \
        cube_gap=150 layer_speed=30,40 vib_amp=0.6 jitter_amp=0.15 seed=1 act_square=1 act_pitch="$2" \
        > "$D/$1.sim.log" 2>&1 || { cat "$D/$1.sim.log"; fail "$1: simulate"; }
    reduce_sync "$d" --ratio-min 5 --ratio-max 8
    local e ei nact
    e=$(speckles_pupil "$d")
    ei=$(ideal_pupil "$d")
    nact=$(sed -n 's/.*(\([0-9]*\) reconstructor modes.*/\1/p' "$d/speckles.log")
    set -- "$1" $(keep_errors "$d")
    echo "$1: $nact actuators, NCP error $e nm (ideal speckles $ei nm); residual mean kept $2 nm (ideal $3 nm)" >&2
    awk -v a="$e" 'BEGIN { exit !(a < 35) }' || fail "$1: NCP error $e nm"
    resmean_bounds "$1" "$e" "$ei" "$2" "$3" 1.3
    echo "$nact"
}
n1=$(run sparse 0.45 | tail -1)
n2=$(run dense 0.36 | tail -1)
# 12 x 12 subapertures: at most 2 x 144 = 288 slopes, fewer valid (the obscuration and the rim).
[ "$n1" -lt 200 ] && [ "$n2" -gt 250 ] || fail "actuator counts $n1 and $n2: expected < 200 and > 250"
echo "cli_actuators: ok"

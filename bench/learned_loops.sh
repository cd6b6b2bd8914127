#!/bin/bash
# How a learned reconstructor carries over to a loop other than the one simulated for it
# (docs/telemetry.md, "A reconstructor learned from simulated closed loops"). The 16 x 16
# system of bench/systems_cli.sh's v16 rows (1 kHz, 9.7 WFS frames per exposure, read noise
# 15): `learn` on six simulated loops of docs/telemetry.md's recipe (two layers at 5/8, 12/18,
# 25/30 m/s, vibration 0.3, two seeds each, the simulator's default loop: gain 0.4, delay 2),
# then each observation (one layer at 14 m/s, vibration 0.4, as v16-base) through the default
# path, the path with `speckles --recon learned.fits`, and the ideal speckles, with the loop's
# gain and delay, the slope noise or the wind changed in the observation only. Last, the 60-mode
# loop with a map taught on loops given its own reconstructor (simulate ao_recon=), and a
# telescope pupil unlike the simulated annulus (obscuration 0.3, four vanes of 0.3 m) with the
# map taught on the annulus and on loops given that pupil (simulate pupil_mask=). Every step
# is given the observation's pupil.fits (on the annulus rows the mask it would build itself).
# Prints one line per observation: NCP error [nm] default / learned / ideal and the ratios.
# usage: bash bench/learned_loops.sh <specklewfs> <scratch dir>     (about 17 minutes)
set -u
B=$1
D=$2
mkdir -p "$D"
. "$(dirname "$0")/../tests/lib_cli.sh"  # ncp_error
BASE="pupn=100 pupdx=0.06501 screen_n=2048 nsub=16 act_pitch=0.3372 ao_modes=100 wfs_rate=1000 frame_ratio=9.7
      vib_freq=15 read_noise=15 ncubes=4 cube_frames=100 start_offset=300.41 wfs_file_frames=3000"
# train NAME [simulate keys]: the recipe's six loops in $D/NAME (kept when present) with the
# keys added, and the map learned on them, $D/learned-NAME.fits
train() {
    local name=$1 wind seed t
    shift
    for wind in 5,8 12,18 25,30; do
        for seed in 11 12; do
            t="$D/$name/wind${wind/,/-}-seed$seed"
            [ -f "$t/truewf_000.fits" ] && continue
            # shellcheck disable=SC2086
            "$B" simulate mode=timeseries $BASE nlayers=2 layer_frac=0.6,0.4 layer_speed=$wind layer_dir=30,160 \
                vib_amp=0.3 seed=$seed export_truth=1 "$@" --quiet -o "$t" > "$D/train.log" 2>&1 \
                || { echo "simulate $t failed: $(tail -1 "$D/train.log")"; exit 1; }
        done
    done
    "$B" learn "$D/$name"/* -o "$D/learned-$name.fits" > "$D/learn-$name.log" || { cat "$D/learn-$name.log"; exit 1; }
}
train train
LEARNED=$D/learned-train.fits
grep "held out, all" "$D/learn-train.log"
printf "%-14s | %7s %7s %7s | %6s %6s\n" observation default learned ideal "x def" "x lrn"
obs() { # name [simulate keys]
    local name=$1 d="$D/$1"
    shift
    rm -rf "$d"
    mkdir -p "$d"
    # shellcheck disable=SC2086
    "$B" simulate mode=timeseries $BASE nlayers=1 layer_frac=1 layer_speed=14 layer_dir=200 vib_amp=0.4 seed=1 "$@" \
        --quiet -o "$d/sim" > "$d/sim.log" 2>&1 || { echo "$name: simulate failed"; return; }
    "$B" reduce "$d"/sim/raw_[0-9]*.fits --dark "$d/sim/dark.fits" --flat "$d/sim/flat.fits" -o "$d/science.fits" \
        2> "$d/reduce.log" || { echo "$name: reduce failed"; return; }
    "$B" sync "$d/science.fits" "$d/sim/handshake.log" -o "$d/timing.txt" > "$d/sync.log" 2>&1 \
        || { echo "$name: sync failed"; return; }
    local r
    for r in default learned; do
        local extra=()
        [ "$r" = learned ] && extra=(--recon "$LEARNED")
        "$B" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/sim/actuators.fits" "${extra[@]}" \
            --pupil "$d/sim/pupil.fits" \
            -o "$d/spk_$r.fits" --match "$d/science.fits" "$d/sci_$r.fits" 2> "$d/speckles_$r.log" \
            || { echo "$name: speckles ($r) failed"; return; }
        "$B" estimate "$d/sci_$r.fits" "$d/spk_$r.fits" -o "$d/halo_$r.fits" > /dev/null 2>&1 \
            || { echo "$name: estimate ($r) failed"; return; }
    done
    "$B" estimate "$d/science.fits" "$d/sim/speckles_ideal.fits" -o "$d/halo_ideal.fits" > /dev/null 2>&1 \
        || { echo "$name: estimate (ideal) failed"; return; }
    for r in default learned ideal; do
        "$B" pupil "$d/halo_$r.fits" -o "$d/pupil_$r.fits" --truth "$d/sim/truth.fits" --pupil "$d/sim/pupil.fits" \
            > "$d/pupil_$r.log" 2>&1 \
            || { echo "$name: pupil ($r) failed"; return; }
    done
    awk -v n="$name" -v a="$(ncp_error "$d/pupil_default.log")" -v b="$(ncp_error "$d/pupil_learned.log")" \
        -v c="$(ncp_error "$d/pupil_ideal.log")" \
        'BEGIN { printf "%-14s | %7.1f %7.1f %7.1f | %6.2f %6.2f\n", n, a, b, c, a / c, b / c }'
}
obs v16-base
obs gain0.2 ao_gain=0.2
obs g0.6d1 ao_gain=0.6 ao_delay=1
obs g0.3d3 ao_gain=0.3 ao_delay=3
obs slope3x slope_noise=1e-7
obs modes60 ao_modes=60
obs wind40 layer_speed=40
obs seed2 seed=2
# The 60-mode loop again, with the map taught on loops that run the observed system's own
# reconstructor (simulate ao_recon=...: what a user gives from the AO system's control matrix).
train train60 ao_recon="$D/modes60/sim/recon_ao.fits"
LEARNED=$D/learned-train60.fits obs modes60-own ao_modes=60
# A pupil unlike the annulus the maps above were taught on, then a map taught on loops given it.
VANES="obscur=0.3 nspiders=4 spider_width=0.3"
# shellcheck disable=SC2086
LEARNED=$D/learned-train.fits obs vanes $VANES
train trainvanes pupil_mask="$D/vanes/sim/pupil.fits"
# shellcheck disable=SC2086
LEARNED=$D/learned-trainvanes.fits obs vanes-own $VANES

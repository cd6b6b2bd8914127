#!/usr/bin/env bash
# The space-time learned map (`specklewfs learn --lags`) from the data alone, over bench_telemetry's
# matrix (docs/telemetry.md, "A space-time learned map"), and the choice its checks make. For
# each observation K:S (system K, seed S):
#   1. bench_telemetry --only K --seed S --truth --keep: the observation, with the von Karman
#      map's path (--recon vk) and the ideal speckles' NCP errors;
#   2. `specklewfs wind` on its slopes: the tracked layer's speed v and direction, and the
#      further layers its stacking finds ("layer N:");
#   3. twelve simulated loops of the system (its keys from bench_telemetry --print-keys: the
#      DM, loop, vibration and read noise a user describes; other seeds) with the layers at
#      the winds found, export_truth=1: one layer alone, or the first two with the first's
#      share of the turbulence spread over 0.3-0.7 across the loops (`wind` does not measure
#      the shares);
#   4. `learn` per frame and with lags 0, +-L1, +-2 L1, where the fastest layer found moves
#      half a subaperture in L1 frames (L1 = round(d rate / (2 v)), d = 6.5 m / nsub, v that
#      layer's speed: derived from the measured winds, not chosen per system);
#   5. speckles --recon, estimate, pupil --truth with each map; speckles' two checks of the
#      space-time map against the observation (run.h): the winds' distance at the largest lag
#      [subapertures] and whether the slopes' correlation at a lag lies beyond three spreads of
#      the loops' ("warn");
#   6. the choice: the space-time map when speckles warns of neither; otherwise the per-frame
#      map: of the same loops where `wind` found two layers, or where it found one, of twelve
#      loops of the measured layer (a share of 0.5-0.8) and a second layer drawn at random
#      (8-30 m/s, any direction, from the loop's seed; docs/telemetry.md, "The training winds
#      from the data"). The same rule for every system.
# Prints one row per observation. Data sets are kept in WORK and reused when present. About
# 5 minutes per single-layer observation, 10 per two-layer one, on 2 cores.
#
# usage: bash bench/spacetime.sh BUILD_DIR WORK_DIR [K:S ...]   (default: every system, seed 1)
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
bench_args "$@"

# path NAME OBSDIR MAP: speckles with the map, estimate, pupil --truth; prints the NCP error.
path() {
    local d=$2
    "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/actuators.fits" --recon "$3" \
        -o "$d/spk_$1.fits" --match "$d/science.fits" "$d/sci_$1.fits" 2> "$d/speckles_$1.log"
    "$X" estimate "$d/sci_$1.fits" "$d/spk_$1.fits" -o "$d/halo_$1.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_$1.fits" -o "$d/pupil_$1.fits" --truth "$d/truth.fits" > "$d/pupil_$1.log"
    ncp_error "$d/pupil_$1.log"
}

printf "%-11s %4s %4s | %6s %6s | %-16s %-16s %-16s | %7s %7s | %5s %4s | %7s %-11s | %5s %5s %5s\n" system seed nsub \
    vk ideal "wind [m/s, deg]" "layer 2" lags learned space-t wind corr chosen "" "x vk" "x st" "x ch"
for ks in $OBS; do
    obs_setup "$BT" "$W" "$ks"
    keys=$("$BT" --only "$k" --seed "$s" --print-keys | grep -v -e '^layer_speed=' -e '^layer_dir=' -e '^seed=' -e '^nlayers=' \
        -e '^layer_frac=')
    rate=$(echo "$keys" | awk -F= '$1 == "wfs_rate" { print $2 }')
    "$X" wind "$d"/slopes_0*.fits --teldiam 6.5 > "$d/wind.log"
    w=$(awk '/^wind: .* m\/s toward / { print $2 "," $5 }' "$d/wind.log")
    [ -n "$w" ] || { echo "$name $s: wind found no layer" >&2; continue; }
    w2=$(awk '/^layer 2: / { print $3 "," $6 }' "$d/wind.log")
    v=${w%,*}
    # the lags from the fastest layer found (for one layer, that one): its pattern moves half a
    # subaperture in L1 frames
    vmax=$(awk '/^layer [0-9]+: / { if ($3 > m) m = $3 } END { print m }' "$d/wind.log")
    lags=$(awk -v n="$nsub" -v r="$rate" -v v="$vmax" \
        'BEGIN { l1 = int(6.5 / n * r / (2 * v) + 0.5); if (l1 < 1) l1 = 1; printf "0,-%d,%d,-%d,%d", l1, l1, 2 * l1, 2 * l1 }')
    train=()
    for t in $(seq 101 112); do
        if [ -z "$w2" ]; then
            td="$d/train-$t"
            train+=("$td")
            [ -f "$td/truewf_000.fits" ] && continue
            # shellcheck disable=SC2086
            "$X" simulate mode=timeseries $keys nlayers=1 layer_frac=1 layer_speed="$v" layer_dir="${w#*,}" seed="$t" \
                export_truth=1 -o "$td" --quiet > /dev/null
        else
            td="$d/train2-$t"
            train+=("$td")
            [ -f "$td/truewf_000.fits" ] && continue
            f1=$(awk -v t="$t" 'BEGIN { printf "%.3f", 0.3 + 0.4 * (t - 101) / 11 }')
            # shellcheck disable=SC2086
            "$X" simulate mode=timeseries $keys nlayers=2 layer_frac="$f1,$(awk -v f="$f1" 'BEGIN { print 1 - f }')" \
                layer_speed="$v,${w2%,*}" layer_dir="${w#*,},${w2#*,}" seed="$t" export_truth=1 -o "$td" --quiet > /dev/null
        fi
    done
    tag=${w2:+2}
    "$X" learn "${train[@]}" -o "$d/learned$tag.fits" --no-heldout > "$d/learn$tag.log" 2>&1
    "$X" learn "${train[@]}" -o "$d/spacetime$tag.fits" --lags "$lags" --no-heldout > "$d/learn_st$tag.log" 2>&1
    lrn=$(path "learned$tag" "$d" "$d/learned$tag.fits")
    st=$(path "spacetime$tag" "$d" "$d/spacetime$tag.fits")
    # speckles' checks of the map against the observation: the winds' distance at the largest
    # lag [subapertures], and whether the slopes' correlation at a lag is beyond 3 spreads
    mis=$(awk '/subapertures apart at the largest lag/ { print $(NF - 6) }' "$d/speckles_spacetime$tag.log")
    cw=$(grep -q "correlate at" "$d/speckles_spacetime$tag.log" && echo warn || echo ok)
    ch=$st
    which=space-time$tag
    if grep -q "warning:" "$d/speckles_spacetime$tag.log" && [ -n "$w2" ]; then
        ch=$lrn
        which=per-frame2
    elif grep -q "warning:" "$d/speckles_spacetime$tag.log"; then
        mixed=()
        for t in $(seq 201 212); do
            td="$d/mixed-$t"
            mixed+=("$td")
            [ -f "$td/truewf_000.fits" ] && continue
            second=$(awk -v t="$t" 'BEGIN { srand(t); printf "%.2f %.1f %.0f", 0.5 + 0.3 * rand(), 8 + 22 * rand(), 360 * rand() }')
            read -r f2 v2 d2 <<< "$second"
            # shellcheck disable=SC2086
            "$X" simulate mode=timeseries $keys nlayers=2 layer_frac="$f2,$(awk -v f="$f2" 'BEGIN { print 1 - f }')" \
                layer_speed="$v,$v2" layer_dir="${w#*,},$d2" seed="$t" export_truth=1 -o "$td" --quiet > /dev/null
        done
        "$X" learn "${mixed[@]}" -o "$d/mixed.fits" --no-heldout > "$d/learn_mixed.log" 2>&1
        ch=$(path mixed "$d" "$d/mixed.fits")
        which=per-frame*
    fi
    awk -v n="$name" -v s="$s" -v g="$nsub" -v d="$def" -v i="$ideal" -v w="$w" -v w2="${w2:--}" -v l="$lags" -v a="$lrn" \
        -v t="$st" -v m="$mis" -v c="$cw" -v h="$ch" -v wh="$which" \
        'BEGIN { printf "%-11s %4s %4s | %6s %6s | %-16s %-16s %-16s | %7s %7s | %5s %4s | %7s %-11s | %5.2f %5.2f %5.2f\n",
        n, s, g, d, i, w, w2, l, a, t, m, c, h, wh, d / i, t / i, h / i }'
done
echo "chosen: space-time[2] = the lags' map of the loops of the layer[s] found (no warning); per-frame2 = the per-frame map"
echo "of the two layers' loops; per-frame* = the per-frame map of the measured layer and a random second"

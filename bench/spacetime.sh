#!/usr/bin/env bash
# The space-time learned map (`specklewfs learn --lags`) from the data alone, on single-layer
# systems of bench_telemetry's matrix (docs/telemetry.md, "A space-time learned map"). For
# each observation K:S (system K, seed S):
#   1. bench_telemetry --only K --seed S --truth --keep: the observation, with the default
#      path's and the ideal speckles' NCP errors;
#   2. `specklewfs wind` on its slopes: the layer's speed v and direction;
#   3. twelve simulated loops of the system (its keys from bench_telemetry --print-keys, other
#      seeds) with the layer at that wind, export_truth=1;
#   4. `learn` per frame and with lags 0, +-L1, +-L2, where the screen moves half a
#      subaperture in L1 frames and one in L2 (L1 = round(d rate / (2 v)), d = 6.5 m / nsub:
#      derived from the measured wind, not chosen per system);
#   5. speckles --recon, estimate, pupil --truth with each map.
# Prints one row per observation, with speckles' two checks of the space-time map against
# the observation (run.h): the winds' distance at the largest lag [subapertures] and whether
# the slopes' correlation at a lag lies beyond three spreads of the loops' ("warn"). Data sets are kept in WORK and reused when present. About
# 25 minutes on 2 cores for the default five observations.
#
# usage: bash bench/spacetime.sh BUILD_DIR WORK_DIR [K:S ...]   (default 1:1 3:1 4:1 6:1 10:2)
set -euo pipefail
B=$1
W=$2
shift 2
OBS=${*:-1:1 3:1 4:1 6:1 10:2}
BT="$B/bench/bench_telemetry"
X="$B/specklewfs"
mkdir -p "$W"
err() { awk '/versus truth/ { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$1"; }

# path NAME OBSDIR MAP: speckles with the map, estimate, pupil --truth; prints the NCP error.
path() {
    local d=$2
    "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/actuators.fits" --recon "$3" \
        -o "$d/spk_$1.fits" --match "$d/science.fits" "$d/sci_$1.fits" 2> "$d/speckles_$1.log"
    "$X" estimate "$d/sci_$1.fits" "$d/spk_$1.fits" -o "$d/halo_$1.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_$1.fits" -o "$d/pupil_$1.fits" --truth "$d/truth.fits" > "$d/pupil_$1.log"
    err "$d/pupil_$1.log"
}

printf "%-11s %4s %4s | %6s %6s | %-16s %-16s | %8s %8s | %6s %6s %6s | %5s %4s\n" system seed nsub default ideal \
    "wind [m/s, deg]" lags "learned" "space-t." "x def" "x lrn" "x st" "wind" corr
for ks in $OBS; do
    k=${ks%:*}
    s=${ks#*:}
    d="$W/k${k}s$s"
    if [ ! -f "$d/run.log" ]; then
        "$BT" --only "$k" --seed "$s" --truth --keep "$d" > "$d.log" 2>&1 || { echo "bench_telemetry --only $k --seed $s failed: $d.log" >&2; exit 1; }
        mv "$d.log" "$d/run.log"
    fi
    row=$(grep -E "^[a-z0-9-]+ +$s +[0-9]+ " "$d/run.log" | head -1)
    name=$(echo "$row" | awk '{ print $1 }')
    nsub=$(echo "$row" | awk '{ print $3 }')
    def=$(echo "$row" | awk -F'|' '{ split($2, a, " "); print a[1] }')
    ideal=$(echo "$row" | awk -F'|' '{ split($2, a, " "); print a[2] }')
    keys=$("$BT" --only "$k" --seed "$s" --print-keys | grep -v -e '^layer_speed=' -e '^layer_dir=' -e '^seed=' -e '^nlayers=' \
        -e '^layer_frac=')
    rate=$(echo "$keys" | awk -F= '$1 == "wfs_rate" { print $2 }')
    w=$("$X" wind "$d"/slopes_0*.fits --teldiam 6.5 | awk '/ m\/s toward / { print $2 "," $5 }')
    [ -n "$w" ] || { echo "$name $s: wind found no layer" >&2; continue; }
    v=${w%,*}
    lags=$(awk -v n="$nsub" -v r="$rate" -v v="$v" \
        'BEGIN { l1 = int(6.5 / n * r / (2 * v) + 0.5); if (l1 < 1) l1 = 1; printf "0,-%d,%d,-%d,%d", l1, l1, 2 * l1, 2 * l1 }')
    train=()
    for t in $(seq 101 112); do
        td="$d/train-$t"
        train+=("$td")
        [ -f "$td/truewf_000.fits" ] && continue
        # shellcheck disable=SC2086
        "$X" simulate mode=timeseries $keys nlayers=1 layer_frac=1 layer_speed="$v" layer_dir="${w#*,}" seed="$t" \
            export_truth=1 -o "$td" --quiet > /dev/null
    done
    "$X" learn "${train[@]}" -o "$d/learned.fits" --no-heldout > "$d/learn.log" 2>&1
    "$X" learn "${train[@]}" -o "$d/spacetime.fits" --lags "$lags" --no-heldout > "$d/learn_st.log" 2>&1
    lrn=$(path learned "$d" "$d/learned.fits")
    st=$(path spacetime "$d" "$d/spacetime.fits")
    # speckles' checks of the map against the observation: the winds' distance at the largest
    # lag [subapertures], and whether the slopes' correlation at a lag is beyond 3 spreads
    mis=$(awk '/subapertures apart at the largest lag/ { print $(NF - 6) }' "$d/speckles_spacetime.log")
    cw=$(grep -q "correlate at" "$d/speckles_spacetime.log" && echo warn || echo ok)
    awk -v n="$name" -v s="$s" -v g="$nsub" -v d="$def" -v i="$ideal" -v w="$w" -v l="$lags" -v a="$lrn" -v t="$st" \
        -v m="$mis" -v c="$cw" 'BEGIN { printf "%-11s %4s %4s | %6s %6s | %-16s %-16s | %8s %8s | %6.2f %6.2f %6.2f | %5s %4s\n",
        n, s, g, d, i, w, l, a, t, d / i, a / i, t / i, m, c }' 
done

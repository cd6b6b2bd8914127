#!/bin/bash
# The wind from the slopes (`specklewfs wind`) over bench_telemetry's matrix of systems
# (docs/telemetry.md, "The wind from the slopes"): each system's telemetry kept by
# bench_telemetry --keep, its dominant layer's wind estimated from the slopes alone, against
# the layers the simulation had (bench_telemetry --print-keys).
# Prints one row per system: the true layers, the estimate, the lags tracked, and the speed and
# direction errors against the nearest layer in direction; then the further layers the
# stacking found ("layer N:"), each with its standing [robust sd] and the same errors, and the
# best track not taken against the threshold.
# usage: bash bench/wind_matrix.sh BUILD_DIR WORK_DIR [SEED (default 1)]     (about 5 minutes)
set -euo pipefail
B=$1
W=$2
SEED=${3:-1}
mkdir -p "$W"
BT="$B/bench/bench_telemetry"
nsys=12
printf "%-11s %4s | %-22s | %-26s | %-18s | %6s %6s | %s\n" system seed "layers [m/s toward deg]" estimate "lags" "speed" \
    "dir" "further layers: speed toward dir (sd) speed, dir error; best other / threshold [sd]"
for k in $(seq 0 $((nsys - 1))); do
    d="$W/k${k}s$SEED"
    if [ ! -f "$d/slopes_000.fits" ]; then
        "$BT" --only "$k" --seed "$SEED" --keep "$d" > "$d.log" 2>&1 \
            || { echo "bench_telemetry --only $k failed: $d.log" >&2; exit 1; }
    fi
    # the system's name from its table row, its layers from the keys it was simulated with
    name=$(grep -E "^[a-z0-9-]+ +$SEED +[0-9]+ " "$d.log" | head -1 | awk '{ print $1 }')
    layers=$("$BT" --only "$k" --seed "$SEED" --print-keys | awk -F= '
        $1 == "layer_speed" { ns = split($2, sp, ",") } $1 == "layer_dir" { split($2, di, ",") }
        END { for (i = 1; i <= ns; i++) printf "%s%s,%s", (i > 1 ? " " : ""), sp[i], di[i] }')
    "$B/specklewfs" wind "$d"/slopes_0*.fits --teldiam 6.5 > "$d/wind.log"
    est=$(awk '/^wind: .* m\/s toward / { print $2, $5 }' "$d/wind.log")
    lags=$(awk '/<- tracked/ { printf "%s%s", s, $1; s = "," }' "$d/wind.log")
    if [ -z "$est" ]; then
        printf "%-11s %4s | %-22s | %-26s | %-18s |\n" "$name" "$SEED" "$layers" "not found" ""
        continue
    fi
    # the layer nearest in direction, and the errors against it
    echo "$est $layers" | awk -v n="$name" -v s="$SEED" -v lags="$lags" -v layers="$layers" '{
        v = $1; a = $2; best = 1e9
        for (i = 3; i <= NF; i++) {
            split($i, p, ","); d = a - p[2]; d = d - 360 * int(d / 360); if (d > 180) d -= 360; if (d < -180) d += 360
            if (d < 0) d = -d
            if (d < best) { best = d; sv = p[1] }
        }
        printf "%-11s %4s | %-22s | %6.2f m/s toward %6.1f | %-18s | %+5.0f%% %5.1f | ", n, s, layers, v, a, lags,
               100 * (v / sv - 1), best
    }'
    # the further layers against the true layer nearest in direction
    awk -v layers="$layers" '
        /^layer [0-9]+: / && $2 != "1:" {
            v = $3; a = $6; sd = $(NF - 1); best = 1e9; nl = split(layers, L, " ")
            for (i = 1; i <= nl; i++) {
                split(L[i], p, ","); d = a - p[2]; d = d - 360 * int(d / 360); if (d > 180) d -= 360; if (d < -180) d += 360
                if (d < 0) d = -d
                if (d < best) { best = d; sv = p[1] }
            }
            printf "%.2f toward %.1f (%s) %+.0f%% %.1f; ", v, a, sd, 100 * (v / sv - 1), best
        }
        /^layers: the maps / { thr = $(NF - 5) }
        /^layers: [0-9]+ found/ { other = ($0 ~ /best other/) ? $(NF - 2) : "-" }
        END { printf "best other %s / %s\n", other, thr }' "$d/wind.log"
done

#!/usr/bin/env bash
# The matrix of bench_telemetry with a reconstructor learned from simulated closed loops
# (`specklewfs learn`), leave one system out: for each system and test seed, the map is
# learned on the OTHER systems of the same Shack-Hartmann geometry (their seeds 11 and 12),
# then the path runs with `speckles --recon W.fits` on the test seed's data.
# Prints, per run, the von Karman map's NCP error (--recon vk, the default before 2026-11-28), the learned one's, and the
# ideal speckles', and their ratios (docs/telemetry.md, "A reconstructor learned from
# simulated closed loops"). About 23 minutes on 2 cores; data sets are kept in WORK and
# reused when present.
#
# usage: bash bench/learned_matrix.sh BUILD_DIR WORK_DIR [TEST_SEEDS (default "1 2")]
set -euo pipefail
B=$1
W=$2
SEEDS=${3:-1 2}
BT="$B/bench/bench_telemetry"
X="$B/specklewfs"
mkdir -p "$W"
nsys=12

. "$(dirname "$0")/lib_bench.sh"
# sim K S: bench_telemetry's system K, seed S, kept with the true residual.
sim() { keep_obs "$BT" "$W/k$1s$2" "$1" "$2"; }
# row K S: the table row of system K, seed S.
row() { obs_row "$W/k$1s$2" "$2"; }
nsub_of() { row "$1" "$2" | awk '{ print $3 }'; }

for k in $(seq 0 $((nsys - 1))); do
    for s in 11 12 $SEEDS; do sim "$k" "$s"; done
done

printf "%-11s %4s %4s | %7s %7s %7s | %6s %6s\n" system seed nsub vk learned ideal "x vk" "x lrn"
rm -f "$W/table.txt"
for k in $(seq 0 $((nsys - 1))); do
    g=$(nsub_of "$k" 11)
    train=()
    for j in $(seq 0 $((nsys - 1))); do
        [ "$j" = "$k" ] && continue
        [ "$(nsub_of "$j" 11)" = "$g" ] && train+=("$W/k${j}s11" "$W/k${j}s12")
    done
    "$X" learn "${train[@]}" -o "$W/learned_k$k.fits" > "$W/learn_k$k.log"
    for s in $SEEDS; do
        d="$W/k${k}s$s"
        "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/actuators.fits" \
            --recon "$W/learned_k$k.fits" -o "$d/spk_learned.fits" --match "$d/science.fits" "$d/sci_learned.fits" \
            2> "$d/speckles_learned.log"
        "$X" estimate "$d/sci_learned.fits" "$d/spk_learned.fits" -o "$d/halo_learned.fits" > /dev/null 2>&1
        "$X" pupil "$d/halo_learned.fits" -o "$d/pupil_learned.fits" --truth "$d/truth.fits" > "$d/pupil_learned.log"
        r=$(row "$k" "$s")
        name=$(echo "$r" | awk '{ print $1 }')
        def=$(echo "$r" | awk -F'|' '{ split($2, a, " "); print a[1] }')
        ideal=$(echo "$r" | awk -F'|' '{ split($2, a, " "); print a[2] }')
        lrn=$(ncp_error "$d/pupil_learned.log")
        echo "$name $s $g $def $lrn $ideal" >> "$W/table.txt"
        awk -v n="$name" -v s="$s" -v g="$g" -v d="$def" -v l="$lrn" -v i="$ideal" \
            'BEGIN { printf "%-11s %4s %4s | %7.1f %7.1f %7.1f | %6.2f %6.2f\n", n, s, g, d, l, i, d / i, l / i }'
    done
done
awk '{ sd += $4; sl += $5; n++; if ($4 <= 1.3 * $6) id++; if ($5 <= 1.3 * $6) il++; xd += $4 / $6; xl += $5 / $6 }
     END { printf "runs %d: sum of NCP errors, vk %.1f nm, learned %.1f nm; mean ratio to the ideal speckles %.2f / %.2f; within 1.3x: vk %d, learned %d\n", n, sd, sl, xd / n, xl / n, id, il }' "$W/table.txt"

#!/usr/bin/env bash
# The default path on sixteen short observations made without specklewfs, of other geometries,
# loops, noise, wavelengths, pupils, WFS rates, frame ratios, winds, camera sampling, loop delays
# and turbulence (docs/telemetry.md, "Six more observations", "A pupil under spiders", "Other
# rates, frame ratios, winds and pixels", "Odd subapertures across, strong turbulence, a longer
# delay, coarse pixels"): each through bench/foreign.sh --quick, then one table of the NCP
# errors (default path, ideal speckles, their ratio) and teach's loops. About 1-6 minutes per
# observation on 2 cores (the 20 x 20's loops the longest); an observation already in WORK_DIR
# is not simulated again. Needs Debian's python3-numpy and python3-astropy.
#
# usage: bash bench/foreign_sweep.sh BUILD_DIR WORK_DIR
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
[ $# -eq 2 ] || { sed -n '2,9p' "$0"; exit 2; }
B=$1
W=$2
mkdir -p "$W"
runs=(
    "n10m40|--nsub 10 --modes 40 --seed 3"
    "ph80|--photons 80 --seed 5"
    "d1k|--delay 1 --substeps 3 --lam-sci 2.2e-6 --seed 6"
    "m100|--vib 0 --modes 100 --seed 7"
    "n20|--nsub 20 --seed 4"
    "q60|--modes 60 --seed 1"
    "sp4|--obscur 0.3 --spiders 4 --seed 8"
    "r4w22|--rate 500 --ratio 4.2 --wind 22@120 --seed 21"
    "r10w5|--rate 1500 --ratio 10.3 --wind 5@300,12@45 --cam-rn 20 --seed 22"
    "v5|--vib 0.5 --vib-freq 40 --rate 1200 --ratio 6 --wind 25@180 --seed 24"
    "px35|--pixscale 0.35 --r0 0.1 --nsub 16 --modes 120 --seed 23"
    "n13|--nsub 13 --seed 31"
    "n11m50|--nsub 11 --modes 50 --seed 32"
    "r008|--r0 0.08 --seed 36"
    "d3|--delay 3 --seed 35"
    "px80|--pixscale 0.8 --seed 37"
)
rows=()
for r in "${runs[@]}"; do
    name=${r%%|*}
    opts=${r#*|}
    echo "== $name: foreign.sh --quick $opts"
    # shellcheck disable=SC2086
    bash "$(dirname "$0")/foreign.sh" "$B" "$W/$name" --quick $opts > "$W/$name.out" 2>&1 \
        || { echo "$name failed:"; tail -20 "$W/$name.out"; exit 1; }
    grep -E "^NCP error" "$W/$name.out"
    e=$(ncp_error "$W/$name/pupil.log")
    i=$(ncp_error "$W/$name/pupil_i.log")
    loops=$(grep -oE "[0-9]+ loops (simulated|in all)" "$W/$name/speckles.log" | tail -1 | awk '{ print $1 }')
    rows+=("$(printf '%-7s %-72s %8s %8s %6s %6s' "$name" "$opts" "$e" "$i" \
        "$(awk -v e="$e" -v i="$i" 'BEGIN { printf "%.2f", e / i }')" "${loops:-?}")")
done
echo
printf '%-7s %-72s %8s %8s %6s %6s\n' run "foreign_loop.py options (--quick)" "default" "ideal" "x" loops
for row in "${rows[@]}"; do echo "$row"; done

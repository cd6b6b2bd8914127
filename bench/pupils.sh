#!/usr/bin/env bash
# Pupils and DMs the matrix (bench_telemetry) does not have (docs/telemetry.md, "Fewer slopes
# than DM modes"): the test system (config/small-loop.conf: 12 x 12 on a 66-sample pupil, 3
# cubes of 60 camera frames) with a valid map that leaves out the pupil's edge ring,
# central obstructions of 0.25 and 0.3, four spiders, a square DM grid, and a square grid with
# a 0.3 obstruction. For each: the ideal speckles' NCP error, the path with the von Karman map
# (reduce -> sync -> speckles --recon vk -> estimate -> pupil --truth, the default until
# 2026-11-28; --valid with the ring map) and that of `teach` from the observation's own files
# (--science, --actuators, --pupil, and --valid for the ring: speckles' default teaches the same
# map from the same files) given to speckles --recon, with their ratios to the ideal,
# the modal filter teach read from the slopes and its choice. About 3 minutes in all on 2
# cores; the observations are kept in WORK_DIR and reused.
#
# usage: bash bench/pupils.sh BUILD_DIR WORK_DIR   (PYTHON=...: a python3 with numpy, for the ring map)
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
[ $# -eq 2 ] || { sed -n '2,13p' "$0"; exit 2; }
X="$1/specklewfs"
LIB="$(cd "$1" && pwd)/libspecklewfs.so"
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
W=$2
mkdir -p "$W"
VARIANTS=(
    "ring:3:nlayers=1 layer_frac=1 layer_speed=12"
    "obscur30:3:nlayers=1 layer_frac=1 layer_speed=12 obscur=0.3"
    "obscur30-2l:4:obscur=0.3"
    "obscur25-fast:4:layer_speed=25,8 obscur=0.25"
    "spiders:3:nlayers=1 layer_frac=1 layer_speed=12 nspiders=4 spider_width=0.15"
    "square:3:nlayers=1 layer_frac=1 layer_speed=12 act_square=1"
    "square-obscur30:3:nlayers=1 layer_frac=1 layer_speed=12 act_square=1 obscur=0.3"
)

# ring_map SLOPES OUT: the subapertures full-layout slopes use, less those with an unused
# neighbour (the pupil's edge ring), as a valid map (bench/mode_knee.py's ring_map)
ring_map() {
    PYTHONPATH="$ROOT/python:$ROOT/bench" SPECKLEWFS_LIB="$LIB" "${PYTHON:-python3}" -c \
        'import sys, numpy as np, specklewfs as sw, mode_knee; mode_knee.ring_map(np.array(sw.read_fits(sys.argv[1])[0]), sys.argv[2])' \
        "$1" "$2"
}

# path DIR TAG [speckles options]: the whole path from DIR's science.fits and timing.txt, the
# NCP error [nm] on stdout
path() {
    local d=$1 tag=$2
    shift 2
    "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/obs/actuators.fits" "$@" \
        --match "$d/science.fits" "$d/sci_$tag.fits" -o "$d/spk_$tag.fits" 2> "$d/speckles_$tag.log" \
        || { echo "speckles failed: $d/speckles_$tag.log" >&2; echo nan; return; }
    "$X" estimate "$d/sci_$tag.fits" "$d/spk_$tag.fits" -o "$d/halo_$tag.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_$tag.fits" -o "$d/pupil_$tag.fits" --truth "$d/obs/truth.fits" > "$d/pupil_$tag.log"
    ncp_error "$d/pupil_$tag.log"
}

printf "%-16s %4s | %6s | %6s %5s | %6s %5s | %7s %-10s %4s\n" variant seed ideal vk "x" teach "x" ao_modes chosen "[s]"
sums=
for v in "${VARIANTS[@]}"; do
    IFS=: read -r name seed keys <<< "$v"
    d="$W/$name"
    mkdir -p "$d"
    cp "$ROOT/config/small-loop.conf" "$d/my.conf"
    valid=()
    if [ "$name" = ring ]; then
        [ -f "$d/plain/slopes_000.fits" ] || "$X" simulate "$d/my.conf" $keys seed="$seed" -o "$d/plain" --quiet > /dev/null
        ring_map "$d/plain/slopes_000.fits" "$d/ring.fits"
        keys="$keys valid=$d/ring.fits"
        valid=(--valid "$d/ring.fits")
    fi
    if [ ! -f "$d/timing.txt" ]; then
        # shellcheck disable=SC2086
        "$X" simulate "$d/my.conf" $keys seed="$seed" -o "$d/obs" --quiet > /dev/null
        "$X" reduce "$d"/obs/raw_00[0-2].fits --dark "$d/obs/dark.fits" --flat "$d/obs/flat.fits" -o "$d/science.fits" \
            2> /dev/null
        "$X" sync "$d/science.fits" "$d/obs/handshake.log" -o "$d/timing.txt" --ratio-min 5 --ratio-max 8 > /dev/null
    fi
    "$X" estimate "$d/science.fits" "$d/obs/speckles_ideal.fits" -o "$d/halo_ideal.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_ideal.fits" -o "$d/pupil_ideal.fits" --truth "$d/obs/truth.fits" > "$d/pupil_ideal.log"
    ideal=$(ncp_error "$d/pupil_ideal.log")
    def=$(path "$d" default --recon vk "${valid[@]}")
    "$X" teach "$d"/obs/slopes_0*.fits --science "$d/science.fits" --actuators "$d/obs/actuators.fits" \
        --pupil "$d/obs/pupil.fits" "${valid[@]}" -o "$d/taught.fits" --work "$d/teach" > "$d/teach.log" 2>&1 \
        || { echo "$name: teach failed ($d/teach.log)" >&2; continue; }
    t=$(path "$d" taught --recon "$d/taught.fits" "${valid[@]}")
    rm -rf "$d"/teach/loop_* "$d"/teach/mixed_* "$d"/teach/modes_* "$d"/teach/zonal_*
    k=$(awk '/modal filter from the slopes/ { for (i = 1; i <= NF; i++) if ($i == "ao_modes" && $(i + 1) == "=") print $(i + 2) }' "$d/teach.log")
    ch=$(awk '/^teach: chose the / { print $4 }' "$d/teach.log")
    sec=$(awk '/^teach: chose the / { for (i = 1; i <= NF; i++) if ($i == "s;") print substr($(i - 1), 2) }' "$d/teach.log")
    printf "%-16s %4s | %6s | %6s %5.2f | %6s %5.2f | %7s %-10s %4s\n" "$name" "$seed" "$ideal" "$def" \
        "$(echo "$def $ideal" | awk '{ print $1 / $2 }')" "$t" "$(echo "$t $ideal" | awk '{ print $1 / $2 }')" "$k" "$ch" "$sec"
    sums="$sums $def $ideal $t"
done
echo "${sums:-}" | awk '{ for (i = 1; i + 2 <= NF; i += 3) { n++; rd = $i / $(i + 1); rt = $(i + 2) / $(i + 1);
    kd += rd <= 1.3; kt += rt <= 1.3; if (rt > wt) wt = rt; if (rd > wd) wd = rd } }
    END { if (n) printf "%d variants: within 1.3x of the ideal speckles: vk %d (worst %.2f), teach %d (worst %.2f)\n", n, kd, wd, kt, wt }'

#!/usr/bin/env bash
# `specklewfs teach` over bench_telemetry's matrix (docs/telemetry.md, "teach: the rule in one
# command"): for each observation K:S (system K, seed S), kept with its truth
# (bench_telemetry --only K --seed S --truth --keep), the system's description
# (bench_telemetry --print-keys without its layers and seed: the DM, loop, vibration, noise
# and camera timing a user describes) given to teach with the observation's slopes; the map
# it chooses through speckles --recon, estimate and pupil --truth. Prints one row per
# observation: the default path's and the ideal speckles' NCP errors (from the kept run), the
# layers teach found, its lags and choice, the NCP error with its map and the ratios. Data
# sets are kept in WORK and reused when present; the loops teach simulates into WORK/kKsS/teach
# are removed after the row (the maps it tried stay). About 1-2 minutes per 12 x 12 observation, 3-6 per 24 x 24, on
# 2 cores.
#
# usage: bash bench/teach.sh BUILD_DIR WORK_DIR [K:S ...]   (default: every system, seed 1)
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
bench_args "$@"

printf "%-11s %4s %4s | %6s %6s | %-36s | %-16s %-10s | %6s %6s | %5s %5s\n" system seed nsub default ideal \
    "layers found [m/s toward deg]" lags chosen teach "[s]" "x def" "x tch"
sums=
for ks in $OBS; do
    obs_setup "$BT" "$W" "$ks"
    "$BT" --only "$k" --seed "$s" --print-keys | grep -v -e '^layer_' -e '^seed=' -e '^nlayers=' > "$d/system.conf"
    "$X" teach "$d"/slopes_0*.fits --system "$d/system.conf" -o "$d/taught.fits" --work "$d/teach" > "$d/teach.log" 2> "$d/teach.err" \
        || { echo "$name $s: teach failed ($d/teach.err)" >&2; continue; }
    "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/actuators.fits" --recon "$d/taught.fits" \
        -o "$d/spk_taught.fits" --match "$d/science.fits" "$d/sci_taught.fits" 2> "$d/speckles_taught.log"
    "$X" estimate "$d/sci_taught.fits" "$d/spk_taught.fits" -o "$d/halo_taught.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_taught.fits" -o "$d/pupil_taught.fits" --truth "$d/truth.fits" > "$d/pupil_taught.log"
    t=$(ncp_error "$d/pupil_taught.log")
    rm -rf "$d"/teach/loop_* "$d"/teach/mixed_*
    layers=$(awk '/^teach:   layer [0-9]+: / { printf "%s%s toward %s", n++ ? "; " : "", $4, $7 }' "$d/teach.log")
    lags=$(awk '/ loops simulated; lags / { for (i = 1; i <= NF; i++) if ($i == "lags") print $(i + 1) }' "$d/teach.log")
    ch=$(awk '/^teach: chose the / { print $4 }' "$d/teach.log")
    sec=$(awk '/^teach: chose the / { for (i = 1; i <= NF; i++) if ($i == "s;") print substr($(i - 1), 2) }' "$d/teach.log")
    printf "%-11s %4s %4s | %6s %6s | %-36s | %-16s %-10s | %6s %6s | %5.2f %5.2f\n" "$name" "$s" "$nsub" "$def" "$ideal" \
        "$layers" "$lags" "$ch" "$t" "$sec" "$(echo "$def $ideal" | awk '{ print $1 / $2 }')" \
        "$(echo "$t $ideal" | awk '{ print $1 / $2 }')"
    sums="$sums $def $ideal $t"
done
echo "chosen: space-time = the lags' map (neither check warned); per-frame = a per-frame map (teach.log says which loops)"
# the target's terms: runs within 1.3x of the ideal speckles, the mean and worst ratio
echo "${sums:-}" | awk '{ for (i = 1; i + 2 <= NF; i += 3) { n++; rd = $i / $(i + 1); rt = $(i + 2) / $(i + 1);
    kd += rd <= 1.3; kt += rt <= 1.3; md += rd; mt += rt; if (rt > wt) wt = rt; if (rd > wd) wd = rd } }
    END { if (n) printf "%d runs; within 1.3x of the ideal speckles: teach %d (mean %.2f, worst %.2f), the default path %d " \
        "(mean %.2f, worst %.2f)\n", n, kt, mt / n, wt, kd, md / n, wd }' 

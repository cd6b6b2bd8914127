#!/usr/bin/env bash
# `specklewfs teach` over bench_telemetry's matrix (docs/telemetry.md, "teach: the rule in one
# command"): for each observation K:S (system K, seed S), kept with its truth
# (bench_telemetry --only K --seed S --truth --keep), the system's description
# (bench_telemetry --print-keys without its layers and seed: the DM, loop, vibration, noise
# and camera timing a user describes) given to teach with the observation's slopes; the map
# it chooses through speckles --recon, estimate and pupil --truth. Prints one row per
# observation: the von Karman map's path (--recon vk, the default before 2026-11-28) and the ideal speckles' NCP errors (from the kept run), the
# layers teach found, its lags and choice, the NCP error with its map and the ratios. Data
# sets are kept in WORK and reused when present; the loops teach simulates into WORK/kKsS/teach
# are removed after the row (the maps it tried stay). About 1-2 minutes per 12 x 12 observation, 3-6 per 24 x 24, on
# 2 cores.
#
# With --modes-from-slopes (after WORK_DIR) the description has no ao_modes: teach takes the
# loops' modal filter from the slopes (docs/telemetry.md); its files are then named *_auto.
# With --from-files there is no description: teach takes the system from the observation's
# files (--science science.fits --actuators actuators.fits, as speckles has them), the rest
# the simulator's defaults; its files are named *_ff.
#
# usage: bash bench/teach.sh BUILD_DIR WORK_DIR [--modes-from-slopes | --from-files] [K:S ...]
#        (default: every system, seed 1)
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
auto=
if [ "${3:-}" = --modes-from-slopes ]; then auto=_auto; set -- "$1" "$2" "${@:4}"; fi
if [ "${3:-}" = --from-files ]; then auto=_ff; set -- "$1" "$2" "${@:4}"; fi
bench_args "$@"

printf "%-11s %4s %4s | %6s %6s | %-36s | %-16s %-10s | %6s %6s | %5s %5s\n" system seed nsub vk ideal \
    "layers found [m/s toward deg]" lags chosen teach "[s]" "x vk" "x tch"
sums=
for ks in $OBS; do
    obs_setup "$BT" "$W" "$ks"
    "$BT" --only "$k" --seed "$s" --print-keys | grep -v -e '^layer_' -e '^seed=' -e '^nlayers=' \
        ${auto:+-e '^ao_modes='} > "$d/system$auto.conf"
    tl="$d/teach$auto.log"
    sys=(--system "$d/system$auto.conf")
    [ "$auto" = _ff ] && sys=(--science "$d/science.fits" --actuators "$d/actuators.fits")
    "$X" teach "$d"/slopes_0*.fits "${sys[@]}" -o "$d/taught$auto.fits" --work "$d/teach$auto" \
        > "$tl" 2> "$d/teach$auto.err" || { echo "$name $s: teach failed ($d/teach$auto.err)" >&2; continue; }
    "$X" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/actuators.fits" --recon "$d/taught$auto.fits" \
        -o "$d/spk_taught$auto.fits" --match "$d/science.fits" "$d/sci_taught$auto.fits" 2> "$d/speckles_taught$auto.log"
    "$X" estimate "$d/sci_taught$auto.fits" "$d/spk_taught$auto.fits" -o "$d/halo_taught$auto.fits" > /dev/null 2>&1
    "$X" pupil "$d/halo_taught$auto.fits" -o "$d/pupil_taught$auto.fits" --truth "$d/truth.fits" > "$d/pupil_taught$auto.log"
    t=$(ncp_error "$d/pupil_taught$auto.log")
    rm -rf "$d"/teach$auto/loop_* "$d"/teach$auto/mixed_* "$d"/teach$auto/modes_* "$d"/teach$auto/zonal_*
    layers=$(awk '/^teach:   layer [0-9]+: / { printf "%s%s toward %s", n++ ? "; " : "", $4, $7 }' "$tl")
    lags=$(awk '/ loops simulated; lags / { for (i = 1; i <= NF; i++) if ($i == "lags") print $(i + 1) }' "$tl")
    ch=$(awk '/^teach: chose the / { print $4 }' "$tl")
    sec=$(awk '/^teach: chose the / { for (i = 1; i <= NF; i++) if ($i == "s;") print substr($(i - 1), 2) }' "$tl")
    [ -n "$auto" ] && awk '/modal filter from the slopes/ { sub(/^teach: /, ""); print "    " $0 }' "$tl"
    printf "%-11s %4s %4s | %6s %6s | %-36s | %-16s %-10s | %6s %6s | %5.2f %5.2f\n" "$name" "$s" "$nsub" "$def" "$ideal" \
        "$layers" "$lags" "$ch" "$t" "$sec" "$(echo "$def $ideal" | awk '{ print $1 / $2 }')" \
        "$(echo "$t $ideal" | awk '{ print $1 / $2 }')"
    sums="$sums $def $ideal $t"
done
echo "chosen: space-time = the lags' map (neither check warned); per-frame = a per-frame map (teach.log says which loops)"
# the target's terms: runs within 1.3x of the ideal speckles, the mean and worst ratio
echo "${sums:-}" | awk '{ for (i = 1; i + 2 <= NF; i += 3) { n++; rd = $i / $(i + 1); rt = $(i + 2) / $(i + 1);
    kd += rd <= 1.3; kt += rt <= 1.3; md += rd; mt += rt; if (rt > wt) wt = rt; if (rd > wd) wd = rd } }
    END { if (n) printf "%d runs; within 1.3x of the ideal speckles: teach %d (mean %.2f, worst %.2f), vk %d " \
        "(mean %.2f, worst %.2f)\n", n, kt, mt / n, wt, kd, md / n, wd }' 

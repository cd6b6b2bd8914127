#!/bin/bash
# Systems outside bench_telemetry's matrix through the command line with default options:
# simulate mode=timeseries -> reduce -> sync -> speckles -> estimate -> pupil, and estimate +
# pupil from the simulator's ideal speckles on the same reduced frames (docs/telemetry.md,
# "Systems outside the matrix"). Prints one line per system: sync's ratio and lag (true lag
# 2.59), the NCP errors [nm] from the slopes and the ideal speckles, and both with the AO
# residual's time mean kept (pupil --keep-resmean). After the first seven, four are one 16 x 16
# system with other timing: the handshake logged 20 WFS frames late (true lag 19.59), 12 cubes
# of 30 frames, telemetry files of 600 frames (shorter than a cube), one cube of 300 frames;
# then four systems in telemetry files of 600-1500 frames (x*). The last nine are the same system as it is (v16-base) and with one thing changed each: the loop's gain
# and delay, the WFS's slope noise, a 20 % optical bandwidth, the camera's background, hot and
# dead pixels, a square actuator grid; then a zonal controller (ao_rcond) and a DM of Gaussian
# influence functions (dm_coupling), which teach is not told. Last, a 22 x 22 system of three
# layers at 1.5 kHz, a geometry nothing else here has.
# usage: bash bench/systems_cli.sh <specklewfs> <scratch dir> [NAME-REGEX]
#   NAME-REGEX   only the systems whose names match it (grep -E), e.g. 'v16-(zonal|dmgauss)'
set -u
B=$1
D=$2
ONLY=${3:-}
mkdir -p "$D"
. "$(dirname "$0")/../tests/lib_cli.sh"  # ncp_error, ncp_error_kept
stop() { echo "$1: $2 failed: $(tail -1 "$3")"; }
run() { # name nsub rate ratio nlayers speeds dirs fracs vib rn seed pupn [more simulate keys]
    local n=$1 nsub=$2 rate=$3 ratio=$4 nl=$5 sp=$6 dr=$7 fr=$8 vib=$9 rn=${10} seed=${11} pupn=${12}
    shift 12
    if [ -n "$ONLY" ] && ! grep -Eq -- "$ONLY" <<< "$n"; then return; fi
    local d=$D/$n pitch modes pupdx t0
    rm -rf "$d"
    mkdir -p "$d"
    pupdx=$(awk -v p="$pupn" 'BEGIN { printf "%.5f", 6.5 / p + 0.000005 }')
    pitch=$(awk -v s="$nsub" 'BEGIN { printf "%.4f", 0.83 * 6.5 / s }')
    modes=$(awk -v s="$nsub" 'BEGIN { printf "%d", 0.39 * s * s + 0.5 }')
    t0=$(date +%s)
    "$B" simulate mode=timeseries --quiet -o "$d/sim" pupn="$pupn" pupdx="$pupdx" screen_n=2048 nsub="$nsub" \
        act_pitch="$pitch" ao_modes="$modes" wfs_rate="$rate" frame_ratio="$ratio" nlayers="$nl" layer_frac="$fr" \
        layer_speed="$sp" layer_dir="$dr" vib_amp="$vib" vib_freq=15 read_noise="$rn" ncubes=4 cube_frames=100 \
        start_offset=300.41 wfs_file_frames=3000 seed="$seed" "$@" > "$d/sim.log" 2>&1 || { stop "$n" simulate "$d/sim.log"; return; }
    "$B" reduce "$d"/sim/raw_[0-9]*.fits --dark "$d/sim/dark.fits" --flat "$d/sim/flat.fits" -o "$d/science.fits" \
        2> "$d/reduce.log" || { stop "$n" reduce "$d/reduce.log"; return; }
    "$B" sync "$d/science.fits" "$d/sim/handshake.log" -o "$d/timing.txt" > "$d/sync.log" 2>&1 \
        || { stop "$n" sync "$d/sync.log"; return; }
    "$B" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/sim/actuators.fits" \
        -o "$d/speckles.fits" --match "$d/science.fits" "$d/sci_m.fits" 2> "$d/speckles.log" \
        || { stop "$n" speckles "$d/speckles.log"; return; }
    "$B" estimate "$d/sci_m.fits" "$d/speckles.fits" -o "$d/halo.fits" > "$d/estimate.log" 2>&1 \
        || { stop "$n" estimate "$d/estimate.log"; return; }
    "$B" estimate "$d/science.fits" "$d/sim/speckles_ideal.fits" -o "$d/halo_i.fits" > "$d/estimate_i.log" 2>&1 \
        || { stop "$n" "estimate (ideal)" "$d/estimate_i.log"; return; }
    local h
    for h in halo halo_i; do  # one fit each: pupil --truth prints the error with the mean kept too
        "$B" pupil "$d/$h.fits" -o "$d/p_$h.fits" --truth "$d/sim/truth.fits" > "$d/p_$h.log" 2>&1 \
            || { stop "$n" pupil "$d/p_$h.log"; return; }
    done
    echo "$n: sync ratio $(awk '/^ratio/ { print $2 }' "$d/timing.txt") lag $(awk '/^lag/ { print $2 }' "$d/timing.txt");" \
        "NCP error: slopes $(ncp_error "$d/p_halo.log") ideal $(ncp_error "$d/p_halo_i.log"); mean kept: slopes" \
        "$(ncp_error_kept "$d/p_halo.log") ideal $(ncp_error_kept "$d/p_halo_i.log"); $(( $(date +%s) - t0 )) s"
}
#   name          nsub rate ratio layers speeds   dirs        fractions    vib  rn seed pupn
run sh8-noisy      8  400   3    1      10       45          1            0.2  30 1    100
run sh20-fast     20 1200  12    1      40       120         1            0.3   8 1    100
run sh12-short    12  600   2.5  1      12       200         1            0.0   0 1    100
run sh32-2lay     32 1000   5    2      15,30    0,90        0.6,0.4      0.1   5 1    128
run sh16-3lay     16  800   6    3      8,16,30  10,100,250  0.5,0.3,0.2  0.3  12 2    100
run sh10-2khz     10 2000  20    1      20       300         1            0.4  10 3    100
run sh14-mid      14  900   7    2      6,18     170,20      0.7,0.3      0.0  25 4    100
# timing variants of one 16 x 16 system (true lag 2.59 but for hslag20: 19.59)
run t16-hslag20   16 1000   9.7  1      14       200         1            0.4  15 1    100 ncubes=4 handshake_lag=20
run t16-short     16 1000   9.7  1      14       200         1            0.4  15 1    100 ncubes=12 cube_frames=30 cube_gap=50
run t16-files600  16 1000   9.7  1      14       200         1            0.4  15 1    100 ncubes=3 wfs_file_frames=600
run t16-onecube   16 1000   9.7  1      14       200         1            0.4  15 1    100 ncubes=1 cube_frames=300 wfs_file_frames=8000
# systems of the matrix's kind in telemetry files too short for teach's loops as they are
# described (docs/telemetry.md, "Loops long enough for the map")
run x12-f600      12  527   6.48 2      10,15    0,110       0.6,0.4      0.5  19 1    100 wfs_file_frames=600
run x16-f800      16  700   4.2  2      5,22     10,190      0.6,0.4      0.0  10 2    100 wfs_file_frames=800
run x20-f1500     20 1200   8    1      18       75          1            0.3  12 3    100 wfs_file_frames=1500
run x24-f1000     24 1000   6    1      10       60          1            0.1  15 1    100 wfs_file_frames=1000
# loop, sensor, camera and DM variants of that system (4 cubes x 100 frames, files of 3000)
run v16-base      16 1000   9.7  1      14       200         1            0.4  15 1    100
run v16-gain0.2   16 1000   9.7  1      14       200         1            0.4  15 1    100 ao_gain=0.2
run v16-g0.6d1    16 1000   9.7  1      14       200         1            0.4  15 1    100 ao_gain=0.6 ao_delay=1
run v16-g0.3d3    16 1000   9.7  1      14       200         1            0.4  15 1    100 ao_gain=0.3 ao_delay=3
run v16-slope3x   16 1000   9.7  1      14       200         1            0.4  15 1    100 slope_noise=1e-7
run v16-band20    16 1000   9.7  1      14       200         1            0.4  15 1    100 bandwidth=0.2
run v16-bg500     16 1000   9.7  1      14       200         1            0.4  15 1    100 background=500
run v16-hotdead   16 1000   9.7  1      14       200         1            0.4  15 1    100 nhot=50 ndead=20
run v16-actsq     16 1000   9.7  1      14       200         1            0.4  15 1    100 act_square=1
# a zonal controller (every mode but the sensor's weakest controlled) and a DM of Gaussian
# influence functions (coupling 0.2 at the next actuator): neither said to teach
run v16-zonal     16 1000   9.7  1      14       200         1            0.4  15 1    100 ao_rcond=0.05
run v16-dmgauss   16 1000   9.7  1      14       200         1            0.4  15 1    100 dm_coupling=0.2
# a geometry of its own: 22 x 22 at 1.5 kHz, 8.5 WFS frames per exposure, three layers
run sh22-3lay     22 1500   8.5  3      25,12,6  300,40,160  0.4,0.4,0.2  0.25 12 5    100

# The slopes path on two systems of other geometries than the shipped 12 x 12, with default
# options everywhere (reduce -> sync -> speckles -> estimate -> pupil; speckles' default: a
# map taught for the observation), as bench_telemetry's matrix runs them (docs/telemetry.md,
# "Over many systems"), on short data sets (3 cubes x 60 frames; bench_telemetry --quick,
# seed 1):
#   sh16-issue: 16 x 16 Shack-Hartmann at 1 kHz, 9.7 WFS frames per camera frame, 14 m/s wind
#               at 200 deg, 0.4 lambda/D 12 Hz vibration, read noise 15 counts
#               (measured: NCP error 14.7 nm from the slopes, 14.7 nm from the ideal speckles;
#               with --recon vk 20.0 nm);
#   sh24-base:  24 x 24 at 1 kHz, 6 frames per camera frame, 10 m/s at 60 deg, 0.1 lambda/D,
#               read noise 10 (measured: 25.5 nm, 24.8 nm ideal; vk 30.6 nm; 28.9 nm before
#               teach's loops held 10 frames per input of its map).
# Asserts sync's ratio within 0.005 of the truth and its lag within 0.2 WFS frames (the
# cubes start at a fraction 0.637 of a WFS frame: true lag 3 - 0.637), and the NCP error
# from the slopes within 1.3x the ideal speckles' (the issue's target), below 2.5x the
# full-size table's ideal-speckle error on that system, within 1.6x the ideal speckles' with
# the AO residual's time mean kept in both, and no worse with the mean taken out than kept
# (lib_cli.sh resmean_bounds).
# Under the sanitizers (SWFS_TEST_SANITIZED, tests/CMakeLists.txt) teach's loops would take
# minutes, so there the von Karman map (--recon vk) runs with the same bounds but the 1.3x
# (measured 20.0 nm on sh16-issue), and in place of sh24-base's seed 1 (the same code as
# sh16-issue's, 80-90 s under the sanitizers) its seed 2 (start fraction 0.274), a known
# failure of the joint fit on so few frames with vk (docs/telemetry.md): it must either
# meet the same bounds or say that the fit took no step or ran away (pupil's warnings), never
# pass a flat start or a runaway off as an estimate.
# (With the taught map it met them: 28.8 nm, ideal 26.5.) cli_learn.sh runs the taught
# default under the sanitizers.
# Sourced by cli_systems_sh16.sh and cli_systems_sh24.sh, one system each (two ctest tests,
# so the two run side by side): after `. lib_systems.sh`, `systems_setup "$@"` then
# run_system with the system's arguments.
. "$(dirname "$0")/lib_cli.sh"
systems_setup() { # systems_setup <specklewfs> <scratch dir>
    cli_setup "$@"
    taught=1
    # teach's first 12 loops only: the loops its learning curve would add (up to 48) take
    # minutes on sh24-base; bench/systems_cli.sh and bench_telemetry measure the default's
    SPK_RECON=(--teach-max-loops 12)
    if [ -n "${SWFS_TEST_SANITIZED:-}" ]; then
        taught=
        SPK_RECON=(--recon vk)
    fi
}

run_system() { # run_system NAME NSUB RATIO SPEED DIR VIB VIBFREQ RDNOISE MAXNM SEED START
    local n=$1-s${10} nsub=$2 ratio=$3 d="$D/$1-s${10}" lagt
    lagt=$(awk -v s="${11}" 'BEGIN { printf "%.3f", 3 - (s - int(s)) }')
    mkdir -p "$d"
    local pitch modes
    pitch=$(awk -v s="$nsub" 'BEGIN { printf "%.4f", 0.83 * 6.5 / s }')
    modes=$(awk -v s="$nsub" 'BEGIN { printf "%d", 0.39 * s * s + 0.5 }')
    "$B" simulate mode=timeseries --quiet -o "$d/sim" pupn=100 pupdx=0.065 screen_n=1024 nsub="$nsub" \
        act_pitch="$pitch" ao_modes="$modes" wfs_rate=1000 frame_ratio="$ratio" nlayers=1 layer_frac=1 \
        layer_speed="$4" layer_dir="$5" vib_amp="$6" vib_freq="$7" read_noise="$8" ncubes=3 cube_frames=60 \
        start_offset="${11}" wfs_file_frames=4000 seed="${10}" > "$d/sim.log" 2>&1 || { cat "$d/sim.log"; fail "$n: simulate"; }
    reduce_sync "$d"
    local r l
    r=$(awk '/^ratio/ { print $2 }' "$d/timing.txt")
    l=$(awk '/^lag/ { print $2 }' "$d/timing.txt")
    awk -v r="$r" -v t="$ratio" -v l="$l" -v lt="$lagt" 'BEGIN { dr = r - t; dl = l - lt; exit !(dr < 0.005 && dr > -0.005 && dl < 0.2 && dl > -0.2) }' \
        || fail "$n: sync ratio $r (true $ratio), lag $l (true $lagt)"
    local e i
    e=$(speckles_pupil "$d")
    i=$(ideal_pupil "$d")
    local k
    k=$(keep_errors "$d")
    echo "cli_systems: $n: sync ratio $r lag $l; NCP error $e nm from the slopes, $i nm from the ideal speckles;" \
        "residual mean kept: $k" >&2
    if [ -n "$taught" ]; then
        grep -q "^speckles: chose the space-time map" "$d/speckles.log" || { cat "$d/speckles.log"; fail "$n: no taught map"; }
        awk -v e="$e" -v i="$i" 'BEGIN { exit !(e > 0 && e <= 1.3 * i) }' || fail "$n: NCP error $e nm, ideal $i nm: 1.3x"
    fi
    if awk -v e="$e" -v m="$9" 'BEGIN { exit !(e > 0 && e <= m) }' && (resmean_bounds "$n" "$e" "$i" $k 1.6); then
        return
    fi
    # outside the bounds: only a fit that says it took no step, or that it ran away (a WFE of
    # more than half the wavelength: with OpenBLAS's generic Prescott kernels the same data's
    # fit took steps, to 4165 nm), is accepted
    "$B" pupil "$d/halo.fits" -o "$d/pupil2.fits" > /dev/null 2> "$d/pupil2.err" || fail "$n: pupil"
    { grep -q "warning: the joint fit took no step" "$d/pupil2.err" && grep -q "FITITER = 0" "$d/pupil2.err"; } \
        || grep -q "is more than half the wavelength .*the fit ran away from its start and this is not an estimate" \
            "$d/pupil2.err" || fail "$n: NCP error $e nm (ideal $i nm, bound 1.6x and $9 nm) and no warning"
    echo "cli_systems: $n: outside the bounds, and pupil says why: $(cat "$d/pupil2.err")" >&2
}

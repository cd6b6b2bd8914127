# Helpers shared by the bench/*.sh scripts (sourced, not run), beside the tests' own
# (tests/lib_cli.sh: ncp_error, the NCP error that `pupil --truth` printed).
. "$(dirname "${BASH_SOURCE[0]}")/../tests/lib_cli.sh"

# keep_obs BENCH_TELEMETRY DIR K S: bench_telemetry's system K, seed S, kept in DIR with the
# true residual (--truth --keep) and its table in DIR/run.log; reused when present. Its
# slopes path runs the von Karman map (--recon vk, speckles' default until 2026-11-28): the
# scripts compare their maps with it.
keep_obs() {
    local d=$2
    [ -f "$d/truewf_000.fits" ] && [ -f "$d/run.log" ] && return 0
    "$1" --only "$3" --seed "$4" --truth --keep "$d" --recon vk > "$d.log" 2>&1 \
        || { echo "bench_telemetry --only $3 --seed $4 failed: $d.log" >&2; exit 1; }
    mv "$d.log" "$d/run.log"
}
# obs_row DIR S: the table row of the observation kept in DIR, seed S
# (name seed nsub ... | slopes ideal x | ...).
obs_row() { grep -E "^[a-z0-9-]+ +$2 +[0-9]+ " "$1/run.log" | head -1; }
# obs_setup BENCH_TELEMETRY WORK K:S: the observation K:S kept in WORK/kKsS (keep_obs) and its
# row's fields: sets k, s, d (the folder), name, nsub, def (the NCP error [nm] of the path
# with the von Karman map, the default before teach) and ideal (the ideal speckles').
obs_setup() {
    k=${3%:*}
    s=${3#*:}
    d="$2/k${k}s$s"
    keep_obs "$1" "$d" "$k" "$s"
    local row
    row=$(obs_row "$d" "$s")
    name=$(echo "$row" | awk '{ print $1 }')
    nsub=$(echo "$row" | awk '{ print $3 }')
    def=$(echo "$row" | awk -F'|' '{ split($2, a, " "); print a[1] }')
    ideal=$(echo "$row" | awk -F'|' '{ split($2, a, " "); print a[2] }')
}
# bench_args BUILD_DIR WORK_DIR [K:S ...]: a matrix script's arguments: sets B, W (created), OBS
# (the observations K:S given; default every system, seed 1), BT (bench_telemetry) and X
# (specklewfs).
bench_args() {
    B=$1
    W=$2
    shift 2
    OBS=${*:-0:1 1:1 2:1 3:1 4:1 5:1 6:1 7:1 8:1 9:1 10:1 11:1}
    BT="$B/bench/bench_telemetry"
    X="$B/specklewfs"
    mkdir -p "$W"
}

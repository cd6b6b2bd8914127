# Helpers shared by the bench/*.sh scripts (sourced, not run), beside the tests' own
# (tests/lib_cli.sh: ncp_error, the NCP error that `pupil --truth` printed).
. "$(dirname "${BASH_SOURCE[0]}")/../tests/lib_cli.sh"

# keep_obs BENCH_TELEMETRY DIR K S: bench_telemetry's system K, seed S, kept in DIR with the
# true residual (--truth --keep) and its table in DIR/run.log; reused when present.
keep_obs() {
    local d=$2
    [ -f "$d/truewf_000.fits" ] && [ -f "$d/run.log" ] && return 0
    "$1" --only "$3" --seed "$4" --truth --keep "$d" > "$d.log" 2>&1 \
        || { echo "bench_telemetry --only $3 --seed $4 failed: $d.log" >&2; exit 1; }
    mv "$d.log" "$d/run.log"
}
# obs_row DIR S: the table row of the observation kept in DIR, seed S
# (name seed nsub ... | slopes ideal x | ...).
obs_row() { grep -E "^[a-z0-9-]+ +$2 +[0-9]+ " "$1/run.log" | head -1; }

# Helpers shared by the tests/cli_*.sh scripts that drive the time-series simulation through
# the real-data path (sourced, not run: its name keeps it out of the cli_*.sh test list).
#   . "$(dirname "$0")/lib_cli.sh"   then   cli_setup "$@"   (sets B and D)
cli_setup() { # cli_setup <specklewfs> <scratch dir>
    set -u
    B=$1
    D=$2
    rm -rf "$D"
    mkdir -p "$D"
}
fail() { echo "FAIL: $*" >&2; exit 1; }
expect_error() { # expect_error <pattern> <command...>: fails, and says <pattern>
    local pat=$1; shift
    if "$@" > "$D/err.out" 2> "$D/err.log"; then fail "expected an error from: $*"; fi
    grep -q "$pat" "$D/err.log" || { cat "$D/err.log"; fail "error message lacks '$pat'"; }
}
ncp_error() { # ncp_error <pupil log>: the NCP error [nm] 'pupil --truth' printed
    awk '/versus truth/ { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$1"
}
reduce_sync() { # reduce_sync <run dir> <sync args...>: raw_000..002 -> science.fits, timing.txt
    local d=$1; shift
    "$B" reduce "$d"/sim/raw_000.fits "$d"/sim/raw_001.fits "$d"/sim/raw_002.fits --dark "$d/sim/dark.fits" \
        --flat "$d/sim/flat.fits" -o "$d/science.fits" 2> "$d/reduce.log" || fail "$d: reduce"
    "$B" sync "$d/science.fits" "$d/sim/handshake.log" -o "$d/timing.txt" "$@" > "$d/sync.log" \
        || { cat "$d/sync.log"; fail "$d: sync"; }
}
# ncp_error_kept <pupil log>: the NCP error [nm] with the AO residual's time mean left in the
# wavefront, which 'pupil --truth' prints beside ncp_error's when it took a mean (RESMEAN) out,
# from the same fit ('pupil --keep-resmean' gives it; cli_modal.sh checks the two agree); where
# none was taken out, ncp_error's. keep_errors <run dir> prints it for speckles_pupil's and
# ideal_pupil's runs, slopes then ideal.
ncp_error_kept() {
    local k
    k=$(awk '/^  mean kept / { for (i = 1; i <= NF; i++) if ($i == "error") print $(i + 1) }' "$1")
    if [ -n "$k" ]; then echo "$k"; else ncp_error "$1"; fi
}
keep_errors() { echo "$(ncp_error_kept "$1/pupil.log") $(ncp_error_kept "$1/pupil_i.log")"; }
# SPK_RECON: speckles' reconstructor options (an array; empty: the default, a map taught for the
# observation); the tests that are not about the reconstructor set (--recon vk).
SPK_RECON=()
speckles_pupil() { # speckles_pupil <run dir>: speckles --match, estimate, pupil --truth; prints the NCP error
    local d=$1
    "$B" speckles "$d/timing.txt" --science "$d/science.fits" --actuators "$d/sim/actuators.fits" "${SPK_RECON[@]}" \
        -o "$d/speckles.fits" --match "$d/science.fits" "$d/sci_m.fits" 2> "$d/speckles.log" \
        || { cat "$d/speckles.log"; fail "$d: speckles"; }
    "$B" estimate "$d/sci_m.fits" "$d/speckles.fits" -o "$d/halo.fits" > "$d/estimate.log" 2>&1 || fail "$d: estimate"
    "$B" pupil "$d/halo.fits" -o "$d/pupil.fits" --truth "$d/sim/truth.fits" > "$d/pupil.log" || fail "$d: pupil"
    ncp_error "$d/pupil.log"
}
ideal_pupil() { # ideal_pupil <run dir>: the same from the simulator's ideal speckles
    local d=$1
    "$B" estimate "$d/science.fits" "$d/sim/speckles_ideal.fits" -o "$d/halo_i.fits" > "$d/estimate_i.log" 2>&1 \
        || fail "$d: estimate (ideal)"
    "$B" pupil "$d/halo_i.fits" -o "$d/pupil_i.fits" --truth "$d/sim/truth.fits" > "$d/pupil_i.log" || fail "$d: pupil"
    ncp_error "$d/pupil_i.log"
}
# resmean_bounds <name> <slopes> <ideal> <slopes kept> <ideal kept> <factor>: the speckles from
# the slopes within factor x the ideal speckles' (both with the residual's mean kept: the
# speckles step itself), and the mean the telemetry measured, taken out, no worse than
# keeping it (5 % for the estimate's own scatter)
resmean_bounds() {
    awk -v e="$2" -v i="$3" -v ek="$4" -v ik="$5" -v f="$6" \
        'BEGIN { exit !(e > 0 && i > 0 && ek > 0 && ik > 0 && ek <= f * ik && e <= 1.05 * ek) }' \
        || fail "$1: NCP error $2 nm (ideal $3), residual mean kept $4 nm (ideal $5): bounds ${6}x and 1.05x"
}

#!/usr/bin/env bash
# The default path on an observation made without specklewfs (bench/foreign_loop.py: numpy and
# astropy; a physical-optics Shack-Hartmann, a Fried-geometry DM of Gaussian influence
# functions, a zonal or modal loop, a 16-bit camera; docs/telemetry.md, "Data made without
# specklewfs"): reduce -> sync -> speckles (the default, with the observation's --valid map
# and --pupil mask) -> estimate -> pupil --truth, and the same frames with the ideal speckles;
# then how much of the ideal speckles' variance the computed ones hold, ring by ring. About 3
# minutes with --quick on 2 cores (the simulation 30 s), 6 without. Needs Debian's
# python3-numpy and python3-astropy.
#
# usage: bash bench/foreign.sh BUILD_DIR WORK_DIR [foreign_loop.py options: --seed S --photons P --quick ...]
set -euo pipefail
. "$(dirname "$0")/lib_bench.sh"
[ $# -ge 2 ] || { sed -n '2,11p' "$0"; exit 2; }
X="$1/specklewfs"
W=$2
shift 2
PY=${PYTHON:-/usr/bin/python3}
SIM="$(cd "$(dirname "$0")" && pwd)/foreign_loop.py"
D="$W/data"
mkdir -p "$W"
[ -f "$D/foreign.json" ] || "$PY" "$SIM" "$D" "$@" 2> "$W/sim.log" | tail -1
step() { # name log command...
    local n=$1 log=$2
    shift 2
    "$@" > "$log" 2>&1 || { echo "$n failed:"; tail -20 "$log"; exit 1; }
}
step reduce "$W/reduce.log" "$X" reduce "$D"/raw_[0-9]*.fits --dark "$D/dark.fits" --flat "$D/flat.fits" -o "$W/science.fits"
step sync "$W/sync.log" "$X" sync "$W/science.fits" "$D/handshake.log" -o "$W/timing.txt"
t0=$(date +%s)
step speckles "$W/speckles.log" "$X" speckles "$W/timing.txt" --science "$W/science.fits" --actuators "$D/actuators.fits" \
    --valid "$D/valid.fits" --pupil "$D/pupil.fits" -o "$W/speckles.fits" --match "$W/science.fits" "$W/sci_m.fits"
t1=$(date +%s)
step estimate "$W/estimate.log" "$X" estimate "$W/sci_m.fits" "$W/speckles.fits" -o "$W/halo.fits"
step "estimate (ideal)" "$W/estimate_i.log" "$X" estimate "$W/science.fits" "$D/speckles_ideal.fits" -o "$W/halo_i.fits"
step pupil "$W/pupil.log" "$X" pupil "$W/halo.fits" -o "$W/p_halo.fits" --pupil "$D/pupil.fits" --truth "$D/truth.fits"
step "pupil (ideal)" "$W/pupil_i.log" "$X" pupil "$W/halo_i.fits" -o "$W/p_halo_i.fits" --pupil "$D/pupil.fits" --truth "$D/truth.fits"
"$PY" - "$D/foreign.json" "$W/timing.txt" <<'EOF'
import json, sys
info = json.load(open(sys.argv[1]))
lag = [l.split()[1] for l in open(sys.argv[2]) if l.startswith('lag ')][0]
print(f"system: {info['nsub']} x {info['nsub']} ({info['nvalid']} valid), {info['nact']} actuators, {info['modes']} modes, "
      f"{info['rate']:.0f} Hz, ratio {info['ratio']}, {info['photons']:.0f} photons; residual "
      f"{info['res_rms_ptt'] * 1e9:.1f} nm without tip-tilt; sync lag {lag} (true {', '.join(f'{v:.2f}' for v in info['true_lags'])})")
EOF
e=$(ncp_error "$W/pupil.log")
i=$(ncp_error "$W/pupil_i.log")
echo "NCP error: default path $e nm, ideal speckles $i nm ($(awk -v e="$e" -v i="$i" 'BEGIN { printf "%.2f", e / i }') x); speckles $((t1 - t0)) s"
grep "self-check" "$W/pupil.log" "$W/pupil_i.log" | sed "s#$W/##"
"$PY" "$SIM" "$D" --rho "$W"

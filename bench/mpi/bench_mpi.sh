#!/usr/bin/env bash
# Strong scaling of a distributed `specklewfs stream` on this machine, and the reduction
# costs behind the model of docs/cluster.md.
#
# 1. An MMT/Clio-like time series (config/mmt-clio.conf, NCUBES x CUBE_FRAMES camera
#    frames; made once, kept in SCRATCH), reduced, synchronized, with the reconstructor
#    `speckles --write-recon` builds.
# 2. stream on it: 1 process x 1 thread, 1 x 2 threads, mpirun -n 2 x 1 thread (and -n 1),
#    wall time from the command's own summary, and the products compared with the
#    single-process ones (largest relative difference of HALO).
# 3. bench_mpi under mpirun -n 1 and -n 2: state bytes, merge and reduction times.
#
# usage: bench/mpi/bench_mpi.sh BUILD_DIR [SCRATCH (/tmp/swfs-bench-mpi)] [NCUBES (16)] [CUBE_FRAMES (500)]
set -euo pipefail
BUILD=$(cd "$1" && pwd)
D=${2:-/tmp/swfs-bench-mpi}
NCUBES=${3:-16}
CUBE_FRAMES=${4:-500}
SRC=$(cd "$(dirname "$0")/../.." && pwd)
B=$BUILD/specklewfs
MPIRUN="mpirun --oversubscribe"
[ "$(id -u)" -eq 0 ] && MPIRUN="$MPIRUN --allow-run-as-root"
export OPENBLAS_NUM_THREADS=1
mkdir -p "$D"

DATA="$D/n${NCUBES}x${CUBE_FRAMES}"
if [ ! -f "$DATA/recon.fits" ]; then
    echo "bench_mpi: simulating $NCUBES cubes x $CUBE_FRAMES camera frames (once) in $DATA"
    rm -rf "$DATA"
    t0=$(date +%s.%N)
    "$B" simulate "$SRC/config/mmt-clio.conf" --quiet -o "$DATA/sim" ncubes="$NCUBES" cube_frames="$CUBE_FRAMES" \
        wfs_file_frames=20000 seed=3 > "$DATA.sim.log"
    "$B" reduce "$DATA"/sim/raw_*.fits --dark "$DATA/sim/dark.fits" --flat "$DATA/sim/flat.fits" \
        -o "$DATA/science.fits" 2> "$DATA.reduce.log"
    "$B" sync "$DATA/science.fits" "$DATA/sim/handshake.log" -o "$DATA/timing.txt" --ratio-min 5 --ratio-max 8 \
        > "$DATA.sync.log"
    "$B" speckles "$DATA/timing.txt" --science "$DATA/science.fits" --actuators "$DATA/sim/actuators.fits" \
        -o "$DATA/speckles.fits" --write-recon "$DATA/recon.fits" --threads 2 2> "$DATA.speckles.log"
    t1=$(date +%s.%N)
    awk -v a="$t0" -v b="$t1" 'BEGIN { printf "bench_mpi: data set made in %.0f s\n", b - a }'
fi
usable=$(awk '$1 == "cube" && $8 == "ok" { n += $5 } END { print n }' "$DATA/timing.txt")
echo "bench_mpi: $usable usable camera frames in $(awk '$1 == "cube" && $8 == "ok"' "$DATA/timing.txt" | wc -l) cubes;" \
     "machine load $(cut -d' ' -f1-3 /proc/loadavg) on $(nproc) cores"

ARGS=(stream --timing "$DATA/timing.txt" --science "$DATA/science.fits" --recon "$DATA/recon.fits"
      --actuators "$DATA/sim/actuators.fits")
# runs LABEL PREFIX THREADS: best of 3 wall times from the command's summary line
runs() {
    local label=$1 prefix=$2 th=$3 best=""
    for k in 1 2 3; do
        line=$($prefix "$B" "${ARGS[@]}" --threads "$th" -o "$D/halo_$label.fits" 2> "$D/$label.log" | grep "^stream:")
        s=$(echo "$line" | sed -n 's/.* WFS frames in \([0-9.]*\) s.*/\1/p')
        best=$(awk -v a="$best" -v b="$s" 'BEGIN { print (a == "" || b < a) ? b : a }')
    done
    wfs=$(echo "$line" | sed -n 's/.*camera frames, \([0-9]*\) WFS frames.*/\1/p')
    printf "%-22s %8.2f s %10.0f WFS frames/s\n" "$label" "$best" "$(awk -v w="$wfs" -v s="$best" 'BEGIN { print w / s }')"
    echo "$best" > "$D/$label.best"
}
echo "bench_mpi: stream, best of 3 (wall time of the whole command)"
runs "1proc_1thread" "" 1
runs "1proc_2threads" "" 2
runs "mpirun_n1_1thread" "$MPIRUN -n 1" 1
runs "mpirun_n2_1thread" "$MPIRUN -n 2" 1
awk -v a="$(cat "$D/1proc_1thread.best")" -v b="$(cat "$D/mpirun_n2_1thread.best")" -v c="$(cat "$D/1proc_2threads.best")" \
    'BEGIN { printf "speedup 2 ranks / 1 process: %.2f (2 threads in one process: %.2f)\n", a / b, a / c }'
echo "bench_mpi: reduction costs"
$MPIRUN -n 1 "$BUILD/bench/bench_mpi" 20
$MPIRUN -n 2 "$BUILD/bench/bench_mpi" 20

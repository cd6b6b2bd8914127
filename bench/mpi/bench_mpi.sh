#!/usr/bin/env bash
# Strong scaling of a distributed `specklewfs stream` on this machine, and the reduction
# costs behind the model of docs/cluster.md.
#
# 1. An MMT/Clio-like time series (config/mmt-clio.conf, NCUBES x CUBE_FRAMES camera
#    frames; made once, kept in SCRATCH), reduced, synchronized, with the reconstructor
#    `speckles --write-recon` builds.
# 2. stream on it: alone with 1 and 2 threads, mpirun -n 1 and -n 2 with 1 thread each:
#    wall time, and each process's CPU time (see runs() below).
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
# runs LABEL NPROC THREADS: best of 3. Wall time of the whole command, and every process's
# own wall and CPU time (user + system; /usr/bin/time around each rank): on a machine
# shared with other jobs the wall time says how busy the cores were, the CPU time what the
# run cost, and the largest per-rank CPU time is the wall time the run would take with a
# free core per rank.
runs() {
    local label=$1 np=$2 th=$3 best="" bestcpu="" bestsum=""
    local prefix=""
    [ "$np" -gt 0 ] && prefix="$MPIRUN -n $np"
    for k in 1 2 3; do
        rm -f "$D/$label.ranks"
        t0=$(date +%s.%N)
        $prefix /usr/bin/time -f "%e %U %S" -a -o "$D/$label.ranks" "$B" "${ARGS[@]}" --threads "$th" \
            -o "$D/halo_$label.fits" > "$D/$label.out" 2> "$D/$label.log"
        t1=$(date +%s.%N)
        w=$(awk -v a="$t0" -v b="$t1" 'BEGIN { print b - a }')
        cpu=$(awk '{ c = $2 + $3; if (c > m) m = c } END { print m }' "$D/$label.ranks")
        sum=$(awk '{ s += $2 + $3 } END { print s }' "$D/$label.ranks")
        best=$(awk -v a="$best" -v b="$w" 'BEGIN { print (a == "" || b < a) ? b : a }')
        bestcpu=$(awk -v a="$bestcpu" -v b="$cpu" 'BEGIN { print (a == "" || b < a) ? b : a }')
        bestsum=$(awk -v a="$bestsum" -v b="$sum" 'BEGIN { print (a == "" || b < a) ? b : a }')
    done
    wfs=$(sed -n 's/.*camera frames, \([0-9]*\) WFS frames.*/\1/p' "$D/$label.out")
    printf "%-20s %5d %7d %9.2f %12.2f %10.2f %14.0f\n" "$label" "$np" "$th" "$best" "$bestcpu" "$bestsum" \
        "$(awk -v w="$wfs" -v s="$bestcpu" 'BEGIN { print w / s }')"
    echo "$bestcpu" > "$D/$label.cpu"
}
echo "bench_mpi: stream, best of 3 runs"
printf "%-20s %5s %7s %9s %12s %10s %14s\n" "run" "ranks" "threads" "wall [s]" "max CPU [s]" "CPU [s]" "WFS/s per max"
runs "alone_1thread" 0 1
runs "alone_2threads" 0 2
runs "mpirun_n1" 1 1
runs "mpirun_n2" 2 1
awk -v a="$(cat "$D/alone_1thread.cpu")" -v b="$(cat "$D/mpirun_n2.cpu")" \
    'BEGIN { printf "strong scaling from the per-rank CPU time: 1 -> 2 ranks %.2fx\n", a / b }'
echo "bench_mpi: reduction costs"
$MPIRUN -n 1 "$BUILD/bench/bench_mpi" 20
$MPIRUN -n 2 "$BUILD/bench/bench_mpi" 20

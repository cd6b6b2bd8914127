#!/usr/bin/env bash
# All tests: a Release build with -Werror and the tests that need its speed (ctest label
# "release": the two systems with teach's loops, the pyramid's loops as its curve asks, the Python
# package's), then every test of
# the suite under AddressSanitizer + UndefinedBehaviorSanitizer (Python's aside: a sanitized
# library cannot be loaded into Debian's python3). Used by the README's test command and by
# CI. The Release pass builds only what its tests run (the command, the library and the
# tests' fitsdiff, with -Werror); the sanitizer pass builds every target (tests, benchmarks, fuzz corpus runners),
# also with -Werror. The whole suite in the Release build: `cmake --build build -j2 && cd build
# && ctest -j2`.
set -euo pipefail
cd "$(dirname "$0")/.."
jobs=$(nproc)
cmake -S . -B build -DCMAKE_BUILD_TYPE=Release -DSWFS_WERROR=ON >/dev/null
cmake --build build -j"$jobs" --target specklewfs-cli specklewfs fitsdiff
. scripts/blas-env.sh
blas_env ./build/specklewfs
(cd build && ctest --output-on-failure -j"$jobs" -L release)
cmake -S . -B build-asan -DCMAKE_BUILD_TYPE=RelWithDebInfo -DSWFS_WERROR=ON -DSWFS_SANITIZE=ON -DSWFS_NATIVE=OFF >/dev/null
cmake --build build-asan -j"$jobs"
# one test more than cores: the sanitizer pass's tests are mostly single-threaded, with serial
# phases (process start-up, file I/O) that leave a core idle (2 cores, back to back: 374 s at
# -j2, 345 s at -j3, 344 s at -j4; a fresh clone's run at -j3 379 s, on a machine whose build
# steps took a fifth longer than the run before it at -j2, 375 s)
(cd build-asan && ASAN_OPTIONS=detect_leaks=1 UBSAN_OPTIONS=print_stacktrace=1 ctest --output-on-failure -j"$((jobs + 1))")

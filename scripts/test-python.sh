#!/usr/bin/env bash
# The Python package's tests (pytest, Debian's python3 with python3-numpy and
# python3-pytest) against the Release build's shared library and command line.
# The sanitizer build's libspecklewfs.so cannot be loaded by a plain Python: use build/.
#   scripts/test-python.sh [BUILD_DIR] [pytest args...]
set -euo pipefail
cd "$(dirname "$0")/.."
build=${1:-build}; shift || true
if [ ! -f "$build/CMakeCache.txt" ]; then
  cmake -S . -B "$build" -DCMAKE_BUILD_TYPE=Release -DSWFS_WERROR=ON >/dev/null
fi
cmake --build "$build" -j"$(nproc)" --target specklewfs specklewfs-cli
. scripts/blas-env.sh
blas_env "$build/specklewfs"
SPECKLEWFS_LIB="$PWD/$build/libspecklewfs.so" SPECKLEWFS_CLI="$PWD/$build/specklewfs" PYTHONDONTWRITEBYTECODE=1 \
  exec /usr/bin/python3 -m pytest -q -p no:cacheprovider python/tests "$@"

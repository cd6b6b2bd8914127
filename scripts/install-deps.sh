#!/usr/bin/env bash
# Install the Debian packages specklewfs builds and tests with (root or sudo).
set -euo pipefail
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends \
  build-essential cmake pkg-config \
  libcfitsio-dev zlib1g-dev libfftw3-dev libopenblas-dev liblapacke-dev libcmocka-dev libqhull-dev \
  libplplot-dev plplot-driver-cairo libpng-dev fonts-dejavu-core \
  python3 python3-numpy python3-pytest openmpi-bin libopenmpi-dev "$@" >/dev/null
# Optional, for the fuzzer of the FITS readers (docs/fuzzing.md): pass clang-14 libclang-rt-14-dev.

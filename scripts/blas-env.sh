# Sourced by scripts/test.sh, test-python.sh and tsan.sh: OpenBLAS's own kernels for this CPU
# when OpenBLAS does not know its model (parallel.h, swfs_blas_kernel; README "BLAS kernels").
# The command line switches itself; the unit tests and Python's load the library without that
# switch and would run the kernels OpenBLAS chose (GEMMs 2-3x slower on a Xeon of model 207).
# blas_env <built specklewfs>: exports OPENBLAS_CORETYPE as that command set it, unless set.
blas_env() {
    [ -z "${OPENBLAS_CORETYPE:-}" ] || return 0
    local core
    core=$("$1" --version | sed -n 's/.*(OPENBLAS_CORETYPE=\([A-Za-z0-9]*\), set by specklewfs.*/\1/p')
    if [ -n "$core" ]; then
        export OPENBLAS_CORETYPE=$core
        echo "$(basename "$0"): OPENBLAS_CORETYPE=$core (OpenBLAS does not know this CPU)" >&2
    fi
}

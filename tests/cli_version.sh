# `specklewfs --version` and OpenBLAS's kernels (parallel.h, swfs_blas_kernel): on a CPU with
# AVX2 and FMA the command line never runs OpenBLAS's pre-AVX2 kernels. Told to use them
# (OPENBLAS_CORETYPE=Prescott, as OpenBLAS falls back for a CPU it does not know) it runs
# them, as the user asked, and says which kernels the CPU runs; left to itself it runs modern
# ones (OpenBLAS's choice, or its own switch when OpenBLAS fell back), and says which.
# usage: bash cli_version.sh <specklewfs> <scratch dir>
. "$(dirname "$0")/lib_cli.sh"
cli_setup "$@"
"$B" --version > "$D/v.txt" || fail "--version"
grep -q "^specklewfs [0-9]" "$D/v.txt" && grep -q "^BLAS: OpenBLAS [A-Za-z0-9]* kernels" "$D/v.txt" \
    || { cat "$D/v.txt"; fail "--version: the version and the BLAS kernels expected"; }
OPENBLAS_CORETYPE=Prescott "$B" --version > "$D/p.txt" || fail "--version (Prescott)"
cat "$D/v.txt"
if grep -qw avx2 /proc/cpuinfo && grep -qw fma /proc/cpuinfo; then
    grep -Eq "^BLAS: OpenBLAS Prescott kernels; this CPU runs (Haswell|SkylakeX)'s \(set OPENBLAS_CORETYPE=(Haswell|SkylakeX)\)$" \
        "$D/p.txt" || { cat "$D/p.txt"; fail "Prescott kernels asked for: the CPU's own expected in the message"; }
    env -u OPENBLAS_CORETYPE "$B" --version | grep -Eq "^BLAS: OpenBLAS (Haswell|Zen|SkylakeX|Cooperlake|SapphireRapids) kernels" \
        || fail "AVX2 CPU: the command line ran pre-AVX2 kernels"
else
    grep -q "^BLAS: OpenBLAS Prescott kernels$" "$D/p.txt" || { cat "$D/p.txt"; fail "no AVX2: no other kernels to name"; }
fi
echo "cli_version: ok"

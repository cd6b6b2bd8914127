"""pytest fixtures shared by the specklewfs tests.

Run against the Release build's library (the sanitizer build's cannot be loaded by a
plain Python): SPECKLEWFS_LIB=build/libspecklewfs.so /usr/bin/python3 -m pytest python/tests
(scripts/test-python.sh). The CLI tests use $SPECKLEWFS_CLI, else the specklewfs binary next
to the library."""
import os
import sys

import pytest

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.normpath(os.path.join(HERE, "..", ".."))
sys.path.insert(0, os.path.join(ROOT, "python"))

import specklewfs as sw  # noqa: E402

# The command line the tests run takes this process's OpenBLAS kernels: on a CPU OpenBLAS does
# not know, it would switch itself to better ones than this process loaded, and a test comparing
# the two would measure the kernels' rounding (scripts/test-python.sh sets the variable for
# both; a plain ctest does not).
if not os.environ.get("OPENBLAS_CORETYPE") and sw.blas_kernel()["core"] != "unknown":
    os.environ["OPENBLAS_CORETYPE"] = sw.blas_kernel()["core"]


@pytest.fixture(scope="session")
def cli():
    exe = os.environ.get("SPECKLEWFS_CLI") or os.path.join(os.path.dirname(os.path.realpath(sw.LIBRARY_PATH)),
                                                          "specklewfs")
    if not os.access(exe, os.X_OK):
        pytest.skip(f"no specklewfs command line at {exe} (set SPECKLEWFS_CLI)")
    return exe


@pytest.fixture(scope="session")
def small_sim():
    """A small Sec. 3 simulation (fast): 2 screens of 512^2, 64^2 pupil, 32^2 window."""
    return sw.simulate(screen_n=512, nscreens=2, pupn=64, teldiam=2.5, nfx=32, nfy=32, threads=2, seed=3)


@pytest.fixture(scope="session")
def paper_sim():
    """The paper's default simulation (seed 1), as `specklewfs demo` runs it."""
    return sw.simulate(threads=2)

"""Generic FITS I/O, BLAS threads, the library locator."""
import os
import subprocess
import sys

import numpy as np
import pytest

import specklewfs as sw

from conftest import ROOT


def test_write_read_real_and_complex(tmp_path):
    rng = np.random.default_rng(0)
    cube = rng.normal(size=(3, 4, 5))
    z = rng.normal(size=(4, 5)) + 1j * rng.normal(size=(4, 5))
    geom = sw.Geom(wavelen=3.8e-6, teldiam=6.5, obscur=0.1, pixscale=0.25, pupdx=0.04, pupn=163)
    p = str(tmp_path / "x.fits")
    sw.write_fits(p, {"CUBE": cube, "Z": z}, geom=geom, provenance=["made by a test"],
                  keys={"FRAMEDT": 0.002, "NAME": "abc", "COUNT": 7})
    c, g = sw.read_fits(p, "CUBE")
    assert c.dtype == np.float64 and c.shape == (3, 4, 5) and np.array_equal(c, cube) and g == geom
    zz, _ = sw.read_fits(p, "Z")
    assert zz.dtype == np.complex128 and np.array_equal(zz, z)
    assert sw.fits_info(p, "Z") == {"nx": 5, "ny": 4, "nz": 1, "is_complex": True, "bitpix": -64}
    assert sw.read_keys(p, ["FRAMEDT", "NAME", "COUNT", "NOPE"], ext="Z") == \
        {"FRAMEDT": 0.002, "NAME": "abc", "COUNT": 7.0, "NOPE": None}
    # A single array goes to the primary HDU; -32 rounds to single precision.
    p1 = str(tmp_path / "one.fits")
    sw.write_fits(p1, cube, bitpix=-32)
    c1, g1 = sw.read_fits(p1)
    np.testing.assert_array_equal(c1, cube.astype(np.float32).astype(np.float64))
    assert np.isnan(g1.wavelen) and g1.pupn == 0
    assert sw.read_fits(p1, squeeze=False)[0].shape == (3, 4, 5)


def test_fits_errors(tmp_path):
    missing = str(tmp_path / "missing.fits")
    with pytest.raises(sw.Error) as e:
        sw.read_fits(missing)
    assert missing in e.value.message and e.value.status_name == "SWFS_ERR_IO"
    p = str(tmp_path / "x.fits")
    sw.write_fits(p, {"A": np.zeros((2, 2))})
    with pytest.raises(sw.Error, match="NOPE"):
        sw.read_fits(p, "NOPE")
    with pytest.raises(ValueError, match=r"B: expected 2 or 3 dimensions, got shape \(4,\)"):
        sw.write_fits(str(tmp_path / "y.fits"), {"B": np.zeros(4)})
    assert not os.path.exists(str(tmp_path / "y.fits")) and not os.path.exists(str(tmp_path / "y.fits.part"))
    # keys that would rewrite the data's layout or scaling (BZERO 100 read back every value
    # shifted, NAXIS2 50 the padding as data), that FITS cannot spell, or whose value would cut
    # the card: refused, no file left
    for keys, what in (({"BZERO": 100}, "BZERO describes the data's layout"),
                       ({"NAXIS2": 50}, "NAXIS2 describes the data's layout"),
                       ({"bad key": 1}, "expected 1 to 8 of A-Z"),
                       ({"NOTE": "a\nb"}, "control character")):
        with pytest.raises(sw.Error, match=what):
            sw.write_fits(str(tmp_path / "k.fits"), np.arange(4.0).reshape(2, 2), keys=keys)
        assert not os.path.exists(str(tmp_path / "k.fits"))


def test_single_precision_overflow_is_refused(tmp_path):
    """write_fits(bitpix=-32) of a finite value single precision cannot hold: refused, naming
    the file, the HDU, the value, its index and BITPIX -64; nothing written (an earlier file
    of the name kept). It stored inf in silence, which read back as NaN. NaN and infinities
    are written as before (read back as NaN, as CFITSIO reads them)."""
    p = str(tmp_path / "x.fits")
    sw.write_fits(p, np.zeros((2, 3, 4)), bitpix=-32)
    before = open(p, "rb").read()
    a = np.zeros((2, 3, 4))
    a[1, 2, 3] = 1e300
    with pytest.raises(sw.Error) as e:
        sw.write_fits(p, a, bitpix=-32)
    assert e.value.status_name == "SWFS_ERR_VALUE"
    assert p + ": the image: value 23 (x 3, y 2, frame 1) is 1e+300, beyond single precision's largest " \
        "3.40282347e+38 (BITPIX -32 would store it as infinite, read back as NaN); BITPIX -64 holds it" in e.value.message
    assert open(p, "rb").read() == before and os.listdir(tmp_path) == ["x.fits"]
    with pytest.raises(sw.Error, match=r"new.fits: extension Z: the real part of value 1 \(x 1, y 0, frame 0\) "
                                       r"is -1e\+39, beyond single precision"):
        sw.write_fits(str(tmp_path / "new.fits"), {"A": np.ones((2, 2)), "Z": np.array([[0, -1e39 + 1j]])}, bitpix=-32)
    assert os.listdir(tmp_path) == ["x.fits"]
    sw.write_fits(p, a)  # BITPIX -64 holds it
    assert sw.read_fits(p)[0][1, 2, 3] == 1e300
    b = np.array([[np.nan, np.inf], [-np.inf, -np.finfo(np.float32).max]])
    sw.write_fits(p, b, bitpix=-32)
    back = sw.read_fits(p)[0]
    assert np.isnan(back[0]).all() and np.isnan(back[1, 0]) and back[1, 1] == b[1, 1]


def test_blas_threads():
    # The package sets 1 at import (as the command line does) unless told otherwise.
    assert sw.blas_threads() == 1
    sw.set_blas_threads(2)
    try:
        assert sw.blas_threads() == 2
    finally:
        sw.set_blas_threads(1)


def _cpu_flags():
    try:
        with open("/proc/cpuinfo") as f:
            return next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return []


def test_blas_kernel():
    # OpenBLAS told to run its pre-AVX2 kernels (as it falls back for a CPU it does not know):
    # on a CPU with AVX2 and FMA the package names the CPU's own and warns once at import, and
    # with those named no warning; on another CPU there is nothing better to name.
    k = sw.blas_kernel()
    assert k["core"] and set(k) == {"core", "better", "fallback"}
    flags = _cpu_flags()
    modern = "avx2" in flags and "fma" in flags
    code = "import specklewfs as s; print(s.blas_kernel()['core'], s.blas_kernel()['better'] or '-')"
    env = dict(os.environ, SPECKLEWFS_LIB=sw.LIBRARY_PATH, OPENBLAS_CORETYPE="Prescott")
    r = subprocess.run([sys.executable, "-W", "always", "-c", code], env=env, capture_output=True, text=True,
                       cwd=os.path.join(ROOT, "python"), check=True)
    core, better = r.stdout.split()
    assert core == "Prescott"
    if not modern:
        assert better == "-" and "RuntimeWarning" not in r.stderr
        return
    assert better in ("Haswell", "SkylakeX")
    assert better == ("SkylakeX" if "avx512f" in flags and "avx512vl" in flags else "Haswell")
    # the warning is not given when OPENBLAS_CORETYPE is set (here: the user asked for Prescott)
    assert "RuntimeWarning" not in r.stderr
    env = dict(env, OPENBLAS_CORETYPE=better)
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=os.path.join(ROOT, "python"), check=True)
    assert r.stdout.split() == [better, "-"]
    # left to itself: a warning naming OPENBLAS_CORETYPE exactly when OpenBLAS fell back
    env = {k: v for k, v in env.items() if k != "OPENBLAS_CORETYPE"}
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       cwd=os.path.join(ROOT, "python"), check=True)
    core, better = r.stdout.split()
    assert (f"set OPENBLAS_CORETYPE={better} before starting Python" in r.stderr) == (better != "-")


def test_library_is_found_from_the_environment_and_errors_are_clear():
    env = dict(os.environ, SPECKLEWFS_LIB="/nonexistent/libspecklewfs.so")
    r = subprocess.run([sys.executable, "-c", "import specklewfs"], env=env, capture_output=True, text=True,
                       cwd=os.path.join(ROOT, "python"))
    assert r.returncode != 0 and "SPECKLEWFS_LIB: /nonexistent/libspecklewfs.so (no such file)" in r.stderr
    env = dict(os.environ, SPECKLEWFS_LIB=sw.LIBRARY_PATH, SPECKLEWFS_BLAS_THREADS="keep", OPENBLAS_NUM_THREADS="2")
    r = subprocess.run([sys.executable, "-c", "import specklewfs as s; print(s.blas_threads(), s.LIBRARY_PATH)"],
                       env=env, capture_output=True, text=True, cwd=os.path.join(ROOT, "python"), check=True)
    assert r.stdout.split() == ["2", sw.LIBRARY_PATH]

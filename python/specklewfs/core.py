"""Geometry, pupil masks, wavefront comparison, BLAS threads."""
import ctypes
import math
from dataclasses import dataclass, fields

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, dptr, count, swfs_blas_kernel_info


@dataclass
class Geom:
    """The geometry keywords of docs/conventions.md (SI units). Missing values are NaN (pupn: 0)."""
    wavelen: float = math.nan   # WAVELEN [m]
    teldiam: float = math.nan   # TELDIAM [m]
    obscur: float = math.nan    # OBSCUR, fraction of the diameter
    pixscale: float = math.nan  # PIXSCALE [lambda/D per focal pixel]
    pupdx: float = math.nan     # PUPDX [m per pupil sample]
    pupn: int = 0               # PUPN, pupil samples across

    def to_c(self):
        return _lib.swfs_geom(float(self.wavelen), float(self.teldiam), float(self.obscur), float(self.pixscale),
                              float(self.pupdx), count(self.pupn, "Geom.pupn", 0, 1 << 31))

    @classmethod
    def from_c(cls, g):
        return cls(g.wavelen, g.teldiam, g.obscur, g.pixscale, g.pupdx, int(g.pupn))

    def require(self, what="geometry"):
        """Raise specklewfs.Error naming the first missing keyword."""
        g = self.to_c()
        check(lib.swfs_geom_require(ctypes.byref(g), what.encode()), "swfs_geom_require")
        return self

    @property
    def alpha(self):
        """PIXSCALE * PUPDX / TELDIAM: the MFT sampling factor (mft.h)."""
        return self.pixscale * self.pupdx / self.teldiam

    def as_dict(self):
        return {f.name: getattr(self, f.name) for f in fields(self)}


def geom_arg(geom):
    """A swfs_geom for an optional Geom / dict / None argument."""
    if geom is None:
        g = _lib.swfs_geom()
        lib.swfs_geom_init(ctypes.byref(g))
        return g
    if isinstance(geom, dict):
        unknown = sorted(set(geom) - {f.name for f in fields(Geom)})
        if unknown:
            raise ValueError(f"geom: unknown keys {unknown}; a geometry has {[f.name for f in fields(Geom)]}")
        geom = Geom(**geom)
    if not isinstance(geom, Geom):
        raise TypeError(f"geom: expected a specklewfs.Geom, a dict of its fields or None, got {type(geom).__name__}")
    return geom.to_c()


def set_blas_threads(n):
    """OpenBLAS's thread count (process-wide: numpy may share the same OpenBLAS). The
    library's own workers run best with 1, which the command line sets; the Python
    package leaves it alone unless you call this."""
    lib.swfs_blas_set_threads(int(n))


def blas_threads():
    return int(lib.swfs_blas_threads())


def blas_kernel():
    """OpenBLAS's kernels in this process (parallel.h, swfs_blas_kernel): a dict with 'core'
    (the kernels in use, e.g. 'SkylakeX'), 'better' (the kernels this CPU runs when OpenBLAS
    fell back to older ones than AVX2 on a CPU with AVX2 and FMA, else '') and 'fallback'
    (the core OpenBLAS chose by itself when the command line switched it, else ''). A
    'better' means OpenBLAS did not know this CPU: set OPENBLAS_CORETYPE to it before
    starting Python (the GEMMs of teach, learn and pupil run 2-3 times as fast)."""
    k = swfs_blas_kernel_info()
    lib.swfs_blas_kernel(ctypes.byref(k))
    return {"core": k.core.decode(), "better": k.better.decode(), "fallback": k.fallback.decode()}


def aperture(n, dx, diam, obscur=0.0, nspiders=0, spider_width=0.0):
    """Binary annular pupil (n, n) on the grid of docs/conventions.md (aperture.h)."""
    m = np.zeros((int(n), int(n)))
    check(lib.swfs_aperture_make(dptr(m), int(n), float(dx), float(diam), float(obscur), int(nspiders),
                                 float(spider_width)), "swfs_aperture_make")
    return m


def zernike(n, m, rho, theta):
    """Peak-normalized Zernike Z_n^m (aperture.h convention), elementwise."""
    # (whole numbers for the C side's ints; the radial polynomial takes (n - |m|)/2 recurrence
    # steps per point)
    n = count(n, "zernike: n", 0, 1000)
    m = count(m, "zernike: m", -n, n)
    f = np.vectorize(lambda r, t: lib.swfs_zernike(n, m, float(r), float(t)), otypes=[float])
    return f(rho, theta)


def wfe_compare(est, truth, mask):
    """(err_rms, truth_rms_piston, truth_rms_ptt) [m]: the rms of est - truth inside the
    mask with piston, tip and tilt removed, and the truth's rms (piston / piston+tip/tilt
    removed). All three arrays are n x n."""
    truth = as_array(truth, "truth", np.float64, ndim=2)
    n = truth.shape[0]
    truth = as_array(truth, "truth", np.float64, shape=(n, n))
    est = as_array(est, "est", np.float64, shape=(n, n))
    mask = as_array(mask, "mask", np.float64, shape=(n, n))
    e, tp, tptt = ctypes.c_double(), ctypes.c_double(), ctypes.c_double()
    check(lib.swfs_wfe_compare(dptr(est), dptr(truth), dptr(mask), n, ctypes.byref(e), ctypes.byref(tp),
                               ctypes.byref(tptt)), "swfs_wfe_compare")
    return e.value, tp.value, tptt.value


def wfe_remove_ptt(w, mask):
    """A copy of w (n x n) with piston, tip and tilt removed over the mask, and its rms."""
    w = np.array(w, dtype=np.float64, order="C", copy=True)
    if w.ndim != 2 or w.shape[0] != w.shape[1]:
        raise ValueError(f"w: expected a square (n, n) map, got shape {w.shape}")
    mask = as_array(mask, "mask", np.float64, shape=w.shape)
    rms = lib.swfs_wfe_remove_ptt(dptr(w), dptr(mask), w.shape[0])
    return w, rms

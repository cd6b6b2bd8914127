"""Speckle coherence diagnostics (coherence.h): mutual coherence function, tau0, phase
rotation, SNR loss of a camera exposure."""
import ctypes

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, enc
from .core import Geom, geom_arg

P = ctypes.POINTER
_METHODS = {"auto": 0, "fft": 1, "direct": 2}
DEFAULT_NLAGS = 37


def default_lags():
    """The paper's lags [WFS frames]: 0..20, 25, 30, ..., 100."""
    a = (ctypes.c_long * DEFAULT_NLAGS)()
    lib.swfs_coh_default_lags(a)
    return np.array(a[:], dtype=np.int64)


class Coherence:
    """Maps (ny, nx) views: mean_sp, tau0 [s], trot [s], phrate [rad/s], snr_fact (None
    unless an exposure was given); mcf (nlags, ny, nx) complex Gamma(tau)/Gamma(0); lags
    [s] and lag_frames; dense (ny, nx, max_lag + 1) normalized MCF at every lag; counts
    n_valid, n_nopower, n_nonfinite, n_tau0_beyond; framedt, exposure, nfit, method."""

    def __init__(self, ptr):
        self._p = ptr
        self._owner = _lib.Owner(ptr, lib.swfs_coherence_free)
        c = ptr.contents
        o = self._owner
        self.nx, self.ny, self.nframes, self.framedt, self.nlags = c.nx, c.ny, c.nframes, c.framedt, c.nlags
        self.lag_frames = _lib.view(ctypes.cast(c.lag_frames, ctypes.c_void_p).value, (c.nlags,), np.int64
                                    if ctypes.sizeof(ctypes.c_long) == 8 else np.int32, o)
        self.lags = _lib.real_view(c.lags, o).reshape(-1)
        for n in ("mean_sp", "tau0", "trot", "phrate", "snr_fact"):
            setattr(self, n, _lib.real_view(getattr(c, n), o))
        self.mcf = _lib.cplx_view(c.mcf, o, squeeze=False)
        self.max_lag = c.max_lag
        self.dense = _lib.view(c.dense, (c.ny, c.nx, c.max_lag + 1), np.complex128, o)
        self.exposure, self.nfit = c.exposure, c.nfit
        self.method = {1: "fft", 2: "direct"}.get(c.method, "auto")
        for n in ("n_valid", "n_nopower", "n_nonfinite", "n_tau0_beyond"):
            setattr(self, n, getattr(c, n))

    def snr_map(self, exposure):
        """SNR factor map (ny, nx) at another exposure [s] (<= max_lag frames)."""
        out = np.empty((self.ny, self.nx))
        s = _lib.real_struct(out)
        check(lib.swfs_coherence_snr_map(self._p, float(exposure), ctypes.byref(s)), "swfs_coherence_snr_map")
        return out

    def fit_wind(self, geom):
        """Apparent frozen-flow wind (vx, vy) [m/s] from PHRATE (needs PIXSCALE, TELDIAM)."""
        g = geom_arg(geom)
        v = (ctypes.c_double * 2)()
        check(lib.swfs_coherence_fit_wind(self._p, ctypes.byref(g), v), "swfs_coherence_fit_wind")
        return v[0], v[1]

    def write(self, path, geom=None, provenance=()):
        g = geom_arg(geom)
        prov, n = _lib.strings(provenance)
        check(lib.swfs_coherence_write(self._p, enc(path), ctypes.byref(g), prov, n), "swfs_coherence_write")


def coherence(cube, framedt, lags=None, max_lag=0, nfit=4, exposure=0.0, min_power_rel=1e-20, method="auto"):
    """Coherence maps of a complex speckle cube (nframes, ny, nx) at the WFS rate
    (framedt [s] between frames). lags: output lags [frames] (None: the paper's)."""
    cube = as_array(cube, "cube", np.complex128, ndim=3)
    o = _lib.swfs_coh_options()
    lib.swfs_coh_options_default(ctypes.byref(o))
    lag_arr = None
    if lags is not None:
        lag_arr = (ctypes.c_long * len(lags))(*[_lib.count(x, "coherence: lags", -(1 << 31), 1 << 31) for x in lags])
        o.lags, o.nlags = ctypes.cast(lag_arr, P(ctypes.c_long)), len(lags)
    o.max_lag, o.nfit = _lib.count(max_lag, "coherence: max_lag"), _lib.count(nfit, "coherence: nfit", 0, (1 << 31) - 1)
    o.exposure, o.min_power_rel = float(exposure), float(min_power_rel)
    o.method = _lib.choice(_METHODS, method, "coherence: method")
    s = _lib.cplx_struct(cube)
    out = P(_lib.swfs_coherence)()
    check(lib.swfs_coherence_compute(ctypes.byref(s), float(framedt), ctypes.byref(o), ctypes.byref(out)),
          "swfs_coherence_compute")
    del lag_arr
    return Coherence(out)


def read_coherence_input(path):
    """(cube (nframes, ny, nx) complex, framedt [s], geom, exposure [s] or 0) of a
    WFS-rate speckle cube with FRAMEDT."""
    cube = P(_lib.swfs_cplx)()
    dt, exp = ctypes.c_double(), ctypes.c_double()
    g = _lib.swfs_geom()
    check(lib.swfs_coherence_read_input(enc(path), ctypes.byref(cube), ctypes.byref(dt), ctypes.byref(g),
                                        ctypes.byref(exp)), "swfs_coherence_read_input")
    return _lib.take_cplx(cube, squeeze=False), dt.value, Geom.from_c(g), exp.value


def snr_factor(gamma, framedt, exposure):
    """S(T) of one normalized MCF gamma at integer frame lags (eq:MCF-SNReffect)."""
    gamma = as_array(gamma, "gamma", np.complex128, ndim=1)
    return lib.swfs_coh_snr_factor(gamma.ctypes.data, gamma.shape[0], float(framedt), float(exposure))


def exposure_limit_wind(theta_lod, diam, wind):
    """eq:ExpLimit-Wind: D / (2 theta wind) [s]."""
    return lib.swfs_exposure_limit_wind(float(theta_lod), float(diam), float(wind))


def bandwidth_radius(frac_bw):
    """Sec. 3.3 bandwidth limit radius [lambda/D]."""
    return lib.swfs_bandwidth_radius(float(frac_bw))

"""The random-reference estimator: streaming accumulators (accum.h), the estimate
(estimate.h), halo products and accumulator checkpoints (checkpoint.h)."""
import ctypes
import math

import numpy as np

from . import _lib
from ._lib import lib, check, check_ptr, as_array, dptr, enc
from .core import Geom, geom_arg

P = ctypes.POINTER

#: Default Gaussian sigma [pixels] of the g regularization (estimate.h).
G_SMOOTH_DEFAULT = 8.0

#: The accumulator fields, in the order of accum.h and the checkpoint planes.
ACC_FIELDS = tuple(_lib.ACC_FIELDS)


class Accumulator:
    """Per-pixel streaming, mergeable accumulators for nx x ny frames (accum.h).

    add() takes one frame (science (ny, nx) float, psi (ny, nx) complex) or a cube of
    frames ((n, ny, nx) each). Non-finite science values skip that pixel-frame; speckles
    must be finite. Memory is 15 doubles per pixel whatever the number of frames."""

    def __init__(self, nx, ny, _ptr=None):
        if _ptr is None:
            nx, ny = _lib.count(nx, "Accumulator: nx"), _lib.count(ny, "Accumulator: ny")  # (the library's range)
            _ptr = check_ptr(lib.swfs_accum_create(nx, ny), "swfs_accum_create")
        self._owner = _lib.Owner(_ptr, lib.swfs_accum_free)
        self._p = _ptr
        self.geom = None  # set by load() / merge_files()

    @property
    def nx(self):
        return self._p.contents.nx

    @property
    def ny(self):
        return self._p.contents.ny

    @property
    def frames(self):
        """Frames offered."""
        return int(self._p.contents.frames)

    @property
    def skipped(self):
        """Pixel-frames skipped for non-finite science values."""
        return int(self._p.contents.skipped)

    def field(self, name):
        """A (ny, nx) view of one accumulator field ('N', 'MI', ..., 'CAA'; accum.h)."""
        k = ACC_FIELDS.index(name)
        a = self._p.contents
        return _lib.view(ctypes.cast(a.f[k], ctypes.c_void_p).value, (a.ny, a.nx), np.float64, self._owner)

    def state(self):
        """All fields as a (15, ny, nx) copy (the checkpoint's cube)."""
        return np.stack([self.field(n) for n in ACC_FIELDS])

    def export(self):
        """The whole state (moments and regression statistics) as one flat float64 array
        (swfs_accum_export): for transport between processes; merge with merge_states()."""
        out = np.empty(lib.swfs_accum_state_len(self.nx, self.ny), np.float64)
        lib.swfs_accum_export(self._p, out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)))
        return out

    @classmethod
    def from_export(cls, state, nx, ny):
        """A new accumulator from export()'s array (checked: counts, variances)."""
        a = cls(nx, ny)
        st = as_array(state, "state", np.float64, shape=(lib.swfs_accum_state_len(int(nx), int(ny)),))
        check(lib.swfs_accum_import(a._p, st.ctypes.data_as(ctypes.POINTER(ctypes.c_double))), "swfs_accum_import")
        return a

    @property
    def has_regress(self):
        """True when the regression statistics (for the joint fit) cover every frame."""
        return bool(lib.swfs_accum_has_regress(self._p))

    def reset(self):
        lib.swfs_accum_reset(self._p)

    def add(self, science, psi):
        """Add one frame or a cube of synchronized frames; returns self."""
        nx, ny = self.nx, self.ny
        sci = np.asarray(science)
        frame = sci.ndim == 2
        shape = (ny, nx) if frame else (None, ny, nx)
        sci = as_array(sci, "science", np.float64, shape=shape)
        psi = as_array(psi, "psi", np.complex128, shape=sci.shape)
        n = 1 if frame else sci.shape[0]
        # the speckles checked whole first: the library refuses a frame with a non-finite one,
        # and the frames before it would already be in (a retry would count them twice)
        bad = ~np.isfinite(psi)
        if bad.any():
            k, y, x = np.argwhere(bad.reshape(n, ny, nx))[0]
            raise _lib.Error(_lib.STATUS_NAMES.index("SWFS_ERR_VALUE"), f"psi: the speckle value at pixel ({x}, {y}) "
                             f"of frame {k} is not finite; no frame of the {n} added", "swfs_accum_add")
        np_ = nx * ny
        sbase, pbase = sci.ctypes.data, psi.ctypes.data
        dp = ctypes.POINTER(ctypes.c_double)
        add = lib.swfs_accum_add
        for k in range(n):
            rc = add(self._p, ctypes.cast(sbase + 8 * np_ * k, dp), pbase + 16 * np_ * k)
            if rc:
                check(rc, "swfs_accum_add")
        return self

    def merge(self, other):
        """self += other (disjoint frame sets): exactly the accumulator of the union."""
        if not isinstance(other, Accumulator):
            raise TypeError(f"other: expected an Accumulator, got {type(other).__name__}")
        check(lib.swfs_accum_merge(self._p, other._p), "swfs_accum_merge")
        return self

    def estimate(self, read_noise=0.0, gain=0.0, g_smooth=G_SMOOTH_DEFAULT):
        """The halo estimate (estimate.h). read_noise [counts] per frame, gain [e-/count]
        (0: no photon-noise term), g_smooth [pixels] (0: the paper's per-pixel g; the
        command line's --g-smooth L [lambda/D] is L / PIXSCALE pixels)."""
        noise = _lib.swfs_noise(float(read_noise), float(gain))
        opt = _lib.swfs_estimate_options(float(g_smooth))
        out = P(_lib.swfs_halo)()
        check(lib.swfs_estimate(self._p, ctypes.byref(noise), ctypes.byref(opt), ctypes.byref(out)),
              "swfs_estimate")
        return Halo._take(out)

    def save(self, path, geom=None, provenance=()):
        """Checkpoint (checkpoint.h): load(save(a)) == a bit for bit."""
        g = geom_arg(geom if geom is not None else self.geom)
        prov, n = _lib.strings(provenance)
        check(lib.swfs_accum_save(self._p, enc(path), ctypes.byref(g), prov, n), "swfs_accum_save")

    @classmethod
    def load(cls, path):
        out = P(_lib.swfs_accum)()
        g = _lib.swfs_geom()
        check(lib.swfs_accum_load(enc(path), ctypes.byref(out), ctypes.byref(g)), "swfs_accum_load")
        a = cls(0, 0, _ptr=out)
        a.geom = Geom.from_c(g)
        return a

    @classmethod
    def merge_files(cls, paths):
        """Load and merge checkpoints (same frame size and geometry)."""
        paths = [enc(p) for p in paths]
        arr = (ctypes.c_char_p * max(1, len(paths)))(*paths)
        out = P(_lib.swfs_accum)()
        g = _lib.swfs_geom()
        check(lib.swfs_accum_merge_files(arr, len(paths), ctypes.byref(out), ctypes.byref(g)),
              "swfs_accum_merge_files")
        a = cls(0, 0, _ptr=out)
        a.geom = Geom.from_c(g)
        return a


#: EXTNAME of each map of a halo product and the attribute holding it.
HALO_EXTS = {"HALO": "halo", "HALO_LF": "halo_lf", "STAB": "stab", "GAIN": "gain", "GAIN_PIX": "gain_pix",
             "VISIB": "visib", "SNR": "snr", "MEAN_I": "mean_i", "VAR_I": "var_i", "MEAN_SP": "mean_sp",
             "VAR_SP": "var_sp", "STAB_ERR": "stab_err", "CIRC": "circ", "VALID": "valid", "NFRAMES": "nframes"}
_HALO_SUMMARY = ["npix", "n_valid", "n_bad_radicand", "n_no_speckle", "n_no_frames", "valid_fraction", "median_snr",
                 "radicand_min", "frames", "skipped", "g_smooth", "n_g_fallback", "n_var_below_noise"]


class Halo:
    """A halo estimate (estimate.h). Every map is a (ny, nx) numpy array or None when
    absent: halo (Psi, eq:TheAnswer), halo_lf (eq:PSI-LowFreq), stab (<psi' I>), gain (g
    used), gain_pix (the paper's per-pixel g), visib, snr, mean_i, var_i, mean_sp, var_sp,
    stab_err, circ, valid, nframes; resmean ((pupn, pupn) [m]: the AO residual's time mean
    that the speckles carried, HALO.fits RESMEAN); tiptilt (the speckles' tip-tilt treatment,
    HALO.fits TIPTILT, or None). Maps of a computed or read halo are views of the
    library's memory (no copies). Summary: npix, n_valid, valid_fraction, median_snr,
    frames, skipped, read_noise, gain_e (e-/count), g_smooth, ... and geom (read())."""

    def __init__(self):
        raise TypeError("a Halo comes from Accumulator.estimate(), Halo.read() or Halo.from_arrays()")

    @classmethod
    def _take(cls, ptr):
        return cls._wrap(ptr, _lib.Owner(ptr, lib.swfs_halo_free))

    @classmethod
    def _wrap(cls, ptr, owner, keep=None):
        self = object.__new__(cls)
        self._p = ptr
        self._owner = owner
        self._keep = keep
        h = ptr.contents
        self.nx, self.ny = h.nx, h.ny
        for name in _lib.HALO_CPLX:
            setattr(self, name, _lib.cplx_view(getattr(h, name), owner))
        for name in _lib.HALO_REAL:
            setattr(self, name, _lib.real_view(getattr(h, name), owner))
        for name in _HALO_SUMMARY:
            setattr(self, name, getattr(h, name))
        self.read_noise = h.noise.read_noise
        self.gain_e = h.noise.gain
        self.resmean = _lib.real_view(h.resmean, owner) if h.resmean else None
        self.tiptilt = h.tiptilt.decode() or None  # the speckles' --tiptilt (HALO.fits TIPTILT), None: not known
        self.geom = None
        return self

    @property
    def maps(self):
        """{EXTNAME: array} of the maps present."""
        return {e: getattr(self, a) for e, a in HALO_EXTS.items() if getattr(self, a) is not None}

    @classmethod
    def read(cls, path):
        """Read a HALO.fits product (HALO and HALO_LF required); .geom holds its geometry."""
        out = P(_lib.swfs_halo)()
        g = _lib.swfs_geom()
        check(lib.swfs_halo_read(enc(path), ctypes.byref(out), ctypes.byref(g)), "swfs_halo_read")
        h = cls._take(out)
        h.geom = Geom.from_c(g)
        return h

    @classmethod
    def from_arrays(cls, halo, halo_lf=None, geom=None, **maps):
        """A halo from numpy maps computed elsewhere, e.g. for pupil_estimate(): halo and
        halo_lf complex (ny, nx) (halo_lf defaults to halo), stab complex, any real map of
        HALO_EXTS by attribute name (stab and stab_err are needed for the SNR weight), and
        resmean: the AO residual's time mean [m] on the (pupn, pupn) pupil grid, which
        pupil_estimate() takes out of the wavefront.
        The arrays are used in place (no copies when already float64/complex128)."""
        resmean = maps.pop("resmean", None)
        halo = as_array(halo, "halo", np.complex128, ndim=2)
        ny, nx = halo.shape
        halo_lf = halo if halo_lf is None else as_array(halo_lf, "halo_lf", np.complex128, shape=(ny, nx))
        h = _lib.swfs_halo()
        h.nx, h.ny, h.npix = nx, ny, nx * ny
        keep = {"halo": halo, "halo_lf": halo_lf}
        structs = []
        for name, arr in [("halo", halo), ("halo_lf", halo_lf)] + [(k, v) for k, v in maps.items()]:
            if name not in _lib.HALO_CPLX and name not in _lib.HALO_REAL:
                raise TypeError(f"unknown halo map '{name}' (expected one of {', '.join(HALO_EXTS.values())})")
            if arr is None:
                continue
            if name in _lib.HALO_CPLX:
                arr = as_array(arr, name, np.complex128, shape=(ny, nx))
                s = _lib.cplx_struct(arr)
            else:
                arr = as_array(arr, name, np.float64, shape=(ny, nx))
                s = _lib.real_struct(arr)
            keep[name] = arr
            structs.append(s)
            setattr(h, name, ctypes.pointer(s))
        if resmean is not None:
            resmean = as_array(resmean, "resmean", np.float64, ndim=2)
            if resmean.shape[0] != resmean.shape[1]:
                raise ValueError(f"resmean: expected a square (pupn, pupn) map, got shape {resmean.shape}")
            s = _lib.real_struct(resmean)
            keep["resmean"] = resmean
            structs.append(s)
            h.resmean = ctypes.pointer(s)
        h.median_snr = math.nan
        ptr = ctypes.pointer(h)
        self = cls._wrap(ptr, None, keep=(keep, structs, h))
        # The views of _wrap alias the caller's arrays; expose those arrays themselves.
        for name, arr in keep.items():
            setattr(self, name, arr)
        self.geom = None if geom is None else (geom if isinstance(geom, Geom) else Geom(**geom))
        return self

    def write(self, path, geom=None, provenance=()):
        """HALO.fits (estimate.h layout), atomically. geom defaults to self.geom."""
        if self.stab is None:
            raise ValueError("write: a halo product needs the STAB map (stab=)")
        g = geom_arg(geom if geom is not None else self.geom)
        prov, n = _lib.strings(provenance)
        check(lib.swfs_halo_write(self._p, enc(path), ctypes.byref(g), prov, n), "swfs_halo_write")


def phase_shift_map(intensities, eta, ref_phase):
    """Classic phase-shifting interferometry (Sec. 2.1) per pixel: intensities (n, ny, nx)
    at phase steps eta (n,), reference phase map (ny, nx). Returns (stab, subject_phase,
    intensity_hi, intensity_lo), each (ny, nx)."""
    I = as_array(intensities, "intensities", np.float64, ndim=3)
    n, ny, nx = I.shape
    eta = as_array(eta, "eta", np.float64, shape=(n,))
    ref = as_array(ref_phase, "ref_phase", np.float64, shape=(ny, nx))
    stab = np.empty((ny, nx), np.complex128)
    ph, hi, lo = (np.empty((ny, nx)) for _ in range(3))
    check(lib.swfs_phase_shift_map(dptr(I), dptr(eta), n, nx * ny, dptr(ref), stab.ctypes.data, dptr(ph), dptr(hi),
                                   dptr(lo)), "swfs_phase_shift_map")
    return stab, ph, hi, lo

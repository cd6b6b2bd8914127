"""From WFS telemetry to speckle fields: actuators, Shack-Hartmann model, reconstructors
(wfs.h), Clough-Tocher interpolation (interp.h), the speckle model (speckles.h), the
per-frame engine (engine.h) and the matrix Fourier transform (mft.h).

Slopes are (nframes, nslopes) float64 arrays (x slopes then y slopes, wfs.h units [rad]);
actuator positions (nact, 2) [m]; reconstructors (nact, nslopes) [m/rad]; pupil maps
(npup, npup); focal fields (nfy, nfx) complex."""
import ctypes
import os

import numpy as np

from . import _lib
from ._lib import lib, check, check_ptr, as_array, dptr, enc, count, EXPOSURE_DTYPE

P = ctypes.POINTER
_u8 = P(ctypes.c_ubyte)


# ---- sparse matrices -----------------------------------------------------------------

class Sparse:
    """A CSR matrix (sparse.h) as numpy arrays row_ptr, col (uintp) and val (float64)."""

    def __init__(self, row_ptr, col, val, shape, _owner=None):
        self.shape = (int(shape[0]), int(shape[1]))
        self.row_ptr = as_array(row_ptr, "row_ptr", np.uintp, shape=(self.shape[0] + 1,))
        nnz = int(self.row_ptr[-1])
        self.col = as_array(col, "col", np.uintp, shape=(nnz,))
        self.val = as_array(val, "val", np.float64, shape=(nnz,))
        if nnz and int(self.col.max()) >= self.shape[1]:
            raise ValueError(f"col: column index {int(self.col.max())} >= ncols {self.shape[1]}")
        self._owner = _owner
        self._s = _lib.swfs_sparse(self.shape[0], self.shape[1], nnz, self.row_ptr.ctypes.data_as(P(ctypes.c_size_t)),
                                   self.col.ctypes.data_as(P(ctypes.c_size_t)), dptr(self.val))

    @classmethod
    def from_dense(cls, a):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 2:
            raise ValueError(f"a: expected a 2-D matrix, got shape {a.shape}")
        rows, cols = np.nonzero(a)
        row_ptr = np.zeros(a.shape[0] + 1, np.uintp)
        np.cumsum(np.bincount(rows, minlength=a.shape[0]), out=row_ptr[1:])
        return cls(row_ptr, cols.astype(np.uintp), a[rows, cols], a.shape)

    @classmethod
    def _take(cls, p, owner=None):
        """Wrap a library swfs_sparse* (freed with it unless owned by another object)."""
        if owner is None:
            owner = _lib.Owner(p, lib.swfs_sparse_free)
        s = p.contents
        addr = lambda x: ctypes.cast(x, ctypes.c_void_p).value
        rp = _lib.view(addr(s.row_ptr), (s.nrows + 1,), np.uintp, owner)
        col = _lib.view(addr(s.col), (s.nnz,), np.uintp, owner)
        val = _lib.view(addr(s.val), (s.nnz,), np.float64, owner)
        return cls(rp, col, val, (s.nrows, s.ncols), _owner=owner)

    @property
    def nnz(self):
        return int(self.row_ptr[-1])

    def to_dense(self):
        out = np.zeros(self.shape)
        rows = np.repeat(np.arange(self.shape[0]), np.diff(self.row_ptr.astype(np.int64)))
        out[rows, self.col.astype(np.int64)] = self.val
        return out

    def __matmul__(self, x):
        return self.to_dense() @ x


def interp_ct_grid(xy, npup, pupdx, mask=None):
    """Clough-Tocher interpolation (interp.h) from the actuators xy (nact, 2) [m] to the
    npup x npup pupil grid: (T as Sparse (npup^2 x nact), n_outside)."""
    xy = as_array(xy, "xy", np.float64, shape=(None, 2))
    npup = count(npup, "interp_ct_grid: npup", 2, 8192)
    if mask is not None:
        mask = as_array(mask, "mask", np.float64, shape=(npup, npup))
    out = P(_lib.swfs_sparse)()
    nout = ctypes.c_size_t()
    check(lib.swfs_interp_ct_grid(dptr(xy), xy.shape[0], int(npup), float(pupdx), dptr(mask), ctypes.byref(out),
                                  ctypes.byref(nout)), "swfs_interp_ct_grid")
    return Sparse._take(out), nout.value


# ---- actuators and the Shack-Hartmann model ------------------------------------------

def actuators_hexapolar(diam, pitch, margin=0.0):
    """Hexapolar actuator layout (wfs.h): (nact, 2) positions [m]."""
    xy = P(ctypes.c_double)()
    n = ctypes.c_size_t()
    check(lib.swfs_actuators_hexapolar(float(diam), float(pitch), float(margin), ctypes.byref(xy), ctypes.byref(n)),
          "swfs_actuators_hexapolar")
    return _lib.take_buffer(ctypes.cast(xy, ctypes.c_void_p).value, (n.value, 2), np.float64)


def actuators_square(diam, pitch, margin=0.0):
    """Square-grid actuator layout centred on the pupil, clipped to the circle of radius
    diam/2 + margin (wfs.h): (nact, 2) positions [m]."""
    xy = P(ctypes.c_double)()
    n = ctypes.c_size_t()
    check(lib.swfs_actuators_square(float(diam), float(pitch), float(margin), ctypes.byref(xy), ctypes.byref(n)),
          "swfs_actuators_square")
    return _lib.take_buffer(ctypes.cast(xy, ctypes.c_void_p).value, (n.value, 2), np.float64)


def actuators_write(xy, path):
    xy = as_array(xy, "xy", np.float64, shape=(None, 2))
    check(lib.swfs_actuators_write(dptr(xy), xy.shape[0], enc(path)), "swfs_actuators_write")


def actuators_read(path):
    xy = P(ctypes.c_double)()
    n = ctypes.c_size_t()
    check(lib.swfs_actuators_read(enc(path), ctypes.byref(xy), ctypes.byref(n)), "swfs_actuators_read")
    return _lib.take_buffer(ctypes.cast(xy, ctypes.c_void_p).value, (n.value, 2), np.float64)


class ShackHartmann:
    """Shack-Hartmann model on the pupil grid (wfs.h): nsub x nsub subapertures across
    diam; S (Sparse nslopes x npup^2), valid (nsub, nsub) bool."""

    def __init__(self, nsub, diam, mask, pupdx, min_illum=0.5, _ptr=None, _owner=None):
        if _ptr is None:
            mask = as_array(mask, "mask", np.float64, ndim=2)
            if mask.shape[0] != mask.shape[1]:
                raise ValueError(f"mask: expected a square (npup, npup) map, got shape {mask.shape}")
            _ptr = P(_lib.swfs_shwfs)()
            check(lib.swfs_shwfs_create(ctypes.byref(_ptr), int(nsub), float(diam), dptr(mask), mask.shape[0],
                                        float(pupdx), float(min_illum)), "swfs_shwfs_create")
            _owner = _lib.Owner(_ptr, lib.swfs_shwfs_free)
        self._p, self._owner = _ptr, _owner
        w = _ptr.contents
        self.nsub, self.nslopes, self.npup, self.pupdx, self.diam, self.nvalid = (w.nsub, w.nslopes, w.npup, w.pupdx,
                                                                                  w.diam, w.nvalid)
        self.S = Sparse._take(w.S, owner=_owner)
        self.valid = _lib.view(ctypes.cast(w.valid, ctypes.c_void_p).value, (w.nsub, w.nsub), np.uint8,
                               _owner).astype(bool)

    def measure(self, z):
        """Slopes (nslopes,) [rad] of the displacement map z (npup, npup) [m]; z may also be
        a stack (n, npup, npup) -> (n, nslopes)."""
        z = np.asarray(z)
        single = z.ndim == 2
        z = as_array(z, "z", np.float64, shape=(self.npup, self.npup) if single else (None, self.npup, self.npup))
        zz = z.reshape(-1, self.npup * self.npup)
        out = np.empty((zz.shape[0], self.nslopes))
        for k in range(zz.shape[0]):
            lib.swfs_shwfs_measure(self._p, dptr(zz[k]), dptr(out[k]))
        return out[0] if single else out

    def interaction_matrix(self, T):
        """D = S T (nslopes, nact) [rad per m] for the interpolation T (Sparse)."""
        D = P(ctypes.c_double)()
        check(lib.swfs_interaction_matrix(self._p, ctypes.byref(T._s), ctypes.byref(D)), "swfs_interaction_matrix")
        return _lib.take_buffer(ctypes.cast(D, ctypes.c_void_p).value, (self.nslopes, T.shape[1]), np.float64)


def dm_modes(T, mask):
    """Lowest-energy DM modes (wfs.h): (nact, nact), column k = mode k."""
    mask = as_array(mask, "mask", np.float64, ndim=2)
    if mask.shape[0] != mask.shape[1] or mask.size != T.shape[0]:
        raise ValueError(f"dm_modes: mask: expected the square pupil grid of T's {T.shape[0]} rows, got shape {mask.shape}")
    out = P(ctypes.c_double)()
    check(lib.swfs_dm_modes(ctypes.byref(T._s), dptr(mask), mask.shape[0], ctypes.byref(out)), "swfs_dm_modes")
    return _lib.take_buffer(ctypes.cast(out, ctypes.c_void_p).value, (T.shape[1], T.shape[1]), np.float64)


def slopes_remove_tiptilt(slopes, valid=None):
    """A copy of slopes ((nslopes,) or (n, nslopes)) with the mean x and y slopes over the
    valid subapertures removed (wfs.h)."""
    s = np.array(slopes, dtype=np.float64, order="C", copy=True)
    ss = s.reshape(-1, s.shape[-1])
    v = None
    if valid is not None:
        v = as_array(np.asarray(valid).astype(np.uint8), "valid", np.uint8, ndim=(1, 2))
        if v.size != ss.shape[1] // 2:  # (the library reads one flag per subaperture)
            raise ValueError(f"slopes_remove_tiptilt: valid has {v.size} flags, expected one per subaperture, "
                             f"{ss.shape[1] // 2}")
    for k in range(ss.shape[0]):
        lib.swfs_slopes_remove_tiptilt(dptr(ss[k]), ss.shape[1], v.ctypes.data_as(_u8) if v is not None else None)
    return s


def slopes_noise_var(D, slopes):
    """Effective slope noise variance per slope [rad^2] (wfs.h)."""
    D = as_array(D, "D", np.float64, ndim=2)
    s = as_array(slopes, "slopes", np.float64, shape=(None, D.shape[0]))
    v = ctypes.c_double()
    check(lib.swfs_slopes_noise_var(dptr(D), D.shape[0], D.shape[1], dptr(s), s.shape[0], ctypes.byref(v)),
          "swfs_slopes_noise_var")
    return v.value


def _valid_flags(valid, nsub, name):
    """A valid-subaperture map as nsub^2 uint8 flags (None stays None)."""
    if valid is None:
        return None
    v = np.ascontiguousarray(np.asarray(valid, dtype=bool).reshape(-1), dtype=np.uint8)
    if v.size != nsub * nsub:
        raise ValueError("%s: valid has %d flags, expected nsub^2 = %d" % (name, v.size, nsub * nsub))
    return v


def slopes_white_noise(slopes, nsub, valid=None):
    """The white measurement noise of Shack-Hartmann slopes from the slopes alone (wfs.h
    swfs_slopes_white_noise: their curl over 2 x 2 cells of used subapertures, its temporal
    structure function extrapolated to lag 0): slopes (nframes >= 16, 2 nsub^2), valid (nsub^2
    flags, or None: the subapertures whose slopes vary). Returns (variance per slope [rad^2],
    cells used)."""
    nsub = count(nsub, "slopes_white_noise: nsub", 1, 100000)
    s = as_array(slopes, "slopes", np.float64, shape=(None, 2 * nsub * nsub))
    v = _valid_flags(valid, nsub, "slopes_white_noise")
    var, nc = ctypes.c_double(), ctypes.c_size_t()
    check(lib.swfs_slopes_white_noise(dptr(s), s.shape[0], s.shape[1], nsub, v.ctypes.data_as(_u8) if v is not None else None,
                                      ctypes.byref(var), ctypes.byref(nc), None), "swfs_slopes_white_noise")
    return var.value, nc.value


def slopes_curl_noise(slopes, nsub, valid=None):
    """The same cells' curl both ways (wfs.h swfs_slopes_curl_noise): returns (white, total)
    [rad^2 per slope], white as slopes_white_noise's variance, total the curl's whole variance
    over 8: white noise and the aliasing a gradient model cannot make, the effective noise of
    the vk and MAP maps (speckles takes it on slopes modal-slopes made). slopes: (nframes >= 16,
    2 nsub^2) or, with valid, the used subapertures' only (nframes, 2 nvalid)."""
    nsub = count(nsub, "slopes_curl_noise: nsub", 1, 100000)
    s = as_array(slopes, "slopes", np.float64, shape=(None, None))
    v = _valid_flags(valid, nsub, "slopes_curl_noise")
    white, total = ctypes.c_double(), ctypes.c_double()
    check(lib.swfs_slopes_curl_noise(dptr(s), s.shape[0], s.shape[1], nsub, v.ctypes.data_as(_u8) if v is not None else None,
                                     ctypes.byref(white), ctypes.byref(total)), "swfs_slopes_curl_noise")
    return white.value, total.value


def wind_from_slopes(slopes, nsub, pitch, rate, valid=None):
    """The frozen-flow layers' winds from the slopes, the dominant one tracked (wind.h): slopes (nframes,
    2 nsub^2) or, with valid (nsub, nsub), the valid subapertures' only; pitch [m] the
    subaperture size, rate [Hz]. A dict: found, vx, vy, speed [m/s], direction [deg, toward
    which the pattern moves, counter-clockwise from +x], lags: one dict per lag examined
    (lag, dx, dy [subapertures], corr, inside, used), and layers: every layer found, the
    tracked one first, then those the stacking of the maps found (wind.h), each a dict of vx,
    vy, speed, direction, corr (the mean correlation along its track), signif (robust standard
    deviations above the candidates' median) and nlags; threshold: the significance a layer
    needs; next_signif: the best track not taken (NaN when none was scored); tracked_signif: the
    tracked layer's own standing, and tracked_dropped: True where it stood below the threshold
    while a further layer stood above it (then layers holds the further ones only)."""
    nsub = count(nsub, "wind_from_slopes: nsub", 1, 100000)
    s = as_array(slopes, "slopes", np.float64, ndim=2)
    v = None if valid is None else as_array(valid, "valid", np.uint8, shape=(nsub, nsub))
    e = _lib.swfs_wind_estimate()
    check(lib.swfs_wind_from_slopes(dptr(s), s.shape[0], s.shape[1], int(nsub),
                                    None if v is None else v.ctypes.data_as(P(ctypes.c_ubyte)), float(pitch),
                                    float(rate), ctypes.byref(e)), "swfs_wind_from_slopes")
    lags = [dict(lag=L.lag, dx=L.dx, dy=L.dy, corr=L.corr, inside=bool(L.inside), used=bool(L.used))
            for L in e.lag[:e.nlags]]
    layers = [dict(vx=L.vx, vy=L.vy, speed=L.speed, direction=L.direction, corr=L.corr, signif=L.signif,
                   nlags=L.nlags) for L in e.layer[:e.nlayers]]
    return dict(found=bool(e.found), vx=e.vx, vy=e.vy, speed=e.speed, direction=e.direction, nused=e.nused,
                nvalid=e.nvalid, radius=e.radius, lags=lags, layers=layers, threshold=e.threshold,
                next_signif=e.next_signif, nstack=e.nstack, tracked_signif=e.tracked_signif,
                tracked_dropped=bool(e.tracked_dropped))


def vk_covariance(xy, L0):
    """Normalized von Karman covariance of the actuators (nact, nact)."""
    xy = as_array(xy, "xy", np.float64, shape=(None, 2))
    C = np.empty((xy.shape[0], xy.shape[0]))
    check(lib.swfs_vk_covariance(dptr(xy), xy.shape[0], float(L0), dptr(C)), "swfs_vk_covariance")
    return C


# ---- reconstructors ------------------------------------------------------------------

def _lags_c(lags, what):
    """Lags [WFS frames] as the library's array, checked as it checks them (one of them 0,
    distinct, at most RECON_MAXLAGS; wfs.h swfs_lags_check)."""
    lv = [_lib.count(v, f"{what}: lag", -(1 << 31), 1 << 31) for v in lags]
    arr = (ctypes.c_long * max(len(lv), 1))(*lv)
    check(lib.swfs_lags_check(arr, len(lv), enc(what)), what)
    return arr, len(lv)


def stack_lags(values, lags, first=0, count=None):
    """A space-time map's input (wfs.h swfs_slopes_stack): row t = the values of frames
    first + t + lags[k] of values (nframes, nv), k = 0..len(lags)-1, side by side
    ((count, len(lags) nv)); frames beyond the series' ends repeat its edge frame. count:
    None = every frame from first on. Stack one contiguous series at a time: its ends are
    the only frames clamped."""
    v = as_array(values, "values", np.float64, ndim=(2,))
    arr, nl = _lags_c(lags, "stack_lags")
    first = _lib.count(first, "stack_lags: first")
    n = v.shape[0] - first if count is None else _lib.count(count, "stack_lags: count")
    if n < 0 or first + n > v.shape[0]:
        raise ValueError(f"stack_lags: frames {first}..{first + n} of a series of {v.shape[0]}")
    out = np.empty((n, nl * v.shape[1]), np.float64)
    lib.swfs_slopes_stack(dptr(v), v.shape[0], v.shape[1], arr, nl, first, n, dptr(out))
    return out


def read_control(path):
    """A linear model's control matrix from its file (`--control`): (control, lags), control
    (nk, nmeas) with lags None, or a space-time one's cube (nlags, nk, nv) with its lags
    (NLAGS, LAG1..LAGn, as `learn --lags` writes them) for Pipeline.linear(control=,
    lags=)."""
    from .fits import read_fits
    c = np.ascontiguousarray(read_fits(path, squeeze=False)[0], dtype=np.float64)
    if c.shape[0] == 1:
        return np.ascontiguousarray(c[0]), None
    arr = (ctypes.c_long * c.shape[0])()
    check(lib.swfs_lags_read(enc(os.fspath(path)), c.shape[0], arr), "swfs_lags_read")
    return c, tuple(arr)


class Recon:
    """A reconstructor (wfs.h): W (nact, nslopes) [m/rad], nmodes, sv (singular values of
    D or None), noise_var, dof, lags (a space-time map's, () for one frame's slopes: W then
    takes stack_lags(slopes, lags)). Build with Recon.svd / map / vk / modal, or from_matrix."""

    def __init__(self, ptr, owner):
        # the address itself, not the struct field it may have been read from (a field's pointer
        # follows the field: a model's set_map would move this Recon onto its new map)
        ptr = ctypes.cast(ctypes.cast(ptr, ctypes.c_void_p).value, P(_lib.swfs_recon))
        self._p, self._owner = ptr, owner
        r = ptr.contents
        self.nact, self.nslopes = r.nact, r.nslopes
        self.W = _lib.view(ctypes.cast(r.W, ctypes.c_void_p).value, (r.nact, r.nslopes), np.float64, owner)
        self.sv = (_lib.view(ctypes.cast(r.sv, ctypes.c_void_p).value, (r.nsv,), np.float64, owner)
                   if r.sv else None)

    nmodes = property(lambda self: self._p.contents.nmodes)
    lags = property(lambda self: tuple(self._p.contents.lags[:self._p.contents.nlags])
                    if self._p.contents.nlags > 1 else ())
    noise_var = property(lambda self: self._p.contents.noise_var)
    dof = property(lambda self: self._p.contents.dof)

    @classmethod
    def _take(cls, p):
        return cls(p, _lib.Owner(p, lib.swfs_recon_free))

    @classmethod
    def from_matrix(cls, W, lags=None):
        """A reconstructor over a numpy matrix (nact, nslopes) (used in place). lags: a
        space-time map's (nslopes = len(lags) x the slopes per frame, lag k's block in
        columns [k ns, (k + 1) ns), stack_lags' layout), or None."""
        W = as_array(W, "W", np.float64, ndim=2)
        r = _lib.swfs_recon(W.shape[0], W.shape[1], dptr(W), W.shape[0], None, 0, 0.0, 0.0)
        if lags is not None and len(lags) > 1:
            arr, nl = _lags_c(lags, "Recon.from_matrix")
            if W.shape[1] % nl:
                raise ValueError(f"Recon.from_matrix: W has {W.shape[1]} columns, not a multiple of its {nl} lags")
            r.nlags = nl
            r.lags[:nl] = arr[:nl]
        self = cls(ctypes.pointer(r), None)
        self._keep = (W, r)
        self.W = W
        return self

    @staticmethod
    def _D(D):
        return as_array(D, "D", np.float64, ndim=2)

    @classmethod
    def svd(cls, D, rcond=1e-3, max_modes=0):
        """Truncated SVD pseudo-inverse of D (nslopes, nact)."""
        D = cls._D(D)
        out = P(_lib.swfs_recon)()
        check(lib.swfs_recon_svd(dptr(D), D.shape[0], D.shape[1], float(rcond), int(max_modes), ctypes.byref(out)),
              "swfs_recon_svd")
        return cls._take(out)

    @classmethod
    def map(cls, D, slopes, noise_var=0.0):
        """MAP (Wiener) reconstructor with the modal prior learned from slopes (n, nslopes);
        noise_var <= 0 estimates the slope noise."""
        D = cls._D(D)
        s = as_array(slopes, "slopes", np.float64, shape=(None, D.shape[0]))
        out = P(_lib.swfs_recon)()
        check(lib.swfs_recon_map(dptr(D), D.shape[0], D.shape[1], dptr(s), s.shape[0], float(noise_var),
                                 ctypes.byref(out)), "swfs_recon_map")
        return cls._take(out)

    @classmethod
    def vk(cls, D, xy, L0, slopes, noise_var=0.0):
        """MAP reconstructor with a von Karman spatial prior over the actuators xy."""
        D = cls._D(D)
        xy = as_array(xy, "xy", np.float64, shape=(D.shape[1], 2))
        s = as_array(slopes, "slopes", np.float64, shape=(None, D.shape[0]))
        out = P(_lib.swfs_recon)()
        check(lib.swfs_recon_vk(dptr(D), D.shape[0], D.shape[1], dptr(xy), float(L0), dptr(s), s.shape[0],
                                float(noise_var), ctypes.byref(out)), "swfs_recon_vk")
        return cls._take(out)

    @classmethod
    def modal(cls, D, modes, first, K):
        """W = V_K pinv(D V_K) over modes first..first+K-1 of `modes` (nact, nact)."""
        D = cls._D(D)
        modes = as_array(modes, "modes", np.float64, shape=(D.shape[1], D.shape[1]))
        out = P(_lib.swfs_recon)()
        check(lib.swfs_recon_modal(dptr(D), D.shape[0], D.shape[1], dptr(modes), int(first), int(K),
                                   ctypes.byref(out)), "swfs_recon_modal")
        return cls._take(out)

    @classmethod
    def read(cls, path):
        out = P(_lib.swfs_recon)()
        check(lib.swfs_recon_read(enc(path), ctypes.byref(out)), "swfs_recon_read")
        return cls._take(out)

    def write(self, path):
        check(lib.swfs_recon_write(self._p, enc(path)), "swfs_recon_write")

    def project_tiptilt(self, valid=None):
        """W <- W (I - M), M the mean-slope projector over the valid subapertures (in place)."""
        v = None if valid is None else np.ascontiguousarray(np.asarray(valid).astype(np.uint8).reshape(-1))
        if v is not None and v.size != self.nslopes // 2:  # (the library reads one flag per subaperture)
            raise ValueError(f"project_tiptilt: valid has {v.size} flags, expected one per subaperture, "
                             f"{self.nslopes // 2}")
        if not self.W.flags.writeable:
            raise ValueError("project_tiptilt: W is read-only, and the projection changes it in place; give "
                             "Recon.from_matrix a writable copy")
        check(lib.swfs_recon_project_tiptilt(self._p, v.ctypes.data_as(_u8) if v is not None else None),
              "swfs_recon_project_tiptilt")
        return self

    def apply(self, slopes):
        """z = W s for (nslopes,) or (n, nslopes) slopes."""
        s = np.asarray(slopes)
        single = s.ndim == 1
        s = as_array(s, "slopes", np.float64, shape=(self.nslopes,) if single else (None, self.nslopes))
        ss = s.reshape(-1, self.nslopes)
        z = np.empty((ss.shape[0], self.nact))
        for k in range(ss.shape[0]):
            lib.swfs_recon_apply(self._p, dptr(ss[k]), dptr(z[k]))
        return z[0] if single else z


# ---- the speckle model -----------------------------------------------------------------

class SpeckleModel:
    """Everything the engine needs on the pupil grid (speckles.h): interpolation T from
    the actuators xy (nact, 2), the Shack-Hartmann model (nsub across), and the
    reconstructor (recon given, or the truncated SVD of D = S T with rcond / max_modes).
    Attributes: mask, T (Sparse), wfs (ShackHartmann), recon (Recon), n_outside."""

    def __init__(self, xy, mask, pupdx, teldiam, nsub, recon=None, rcond=1e-3, max_modes=0, remove_tiptilt=True):
        xy = as_array(xy, "xy", np.float64, shape=(None, 2))
        mask = as_array(mask, "mask", np.float64, ndim=2)
        if mask.shape[0] != mask.shape[1]:
            raise ValueError(f"mask: expected a square (npup, npup) map, got shape {mask.shape}")
        rin = None
        if recon is not None:
            rin = recon if isinstance(recon, Recon) else Recon.from_matrix(recon)
        out = P(_lib.swfs_speckle_model)()
        check(lib.swfs_speckle_model_create(ctypes.byref(out), dptr(xy), xy.shape[0], dptr(mask), mask.shape[0],
                                            float(pupdx), float(teldiam), int(nsub), rin._p if rin else None,
                                            float(rcond), int(max_modes), int(bool(remove_tiptilt))),
              "swfs_speckle_model_create")
        self._p = out
        self._owner = _lib.Owner(out, lib.swfs_speckle_model_free)
        self.xy = xy
        self._refresh()

    def _refresh(self):
        m = self._p.contents
        self.npup, self.nact, self.nslopes, self.pupdx, self.n_outside = m.npup, m.nact, m.nslopes, m.pupdx, m.n_outside
        self.mask = _lib.view(ctypes.cast(m.mask, ctypes.c_void_p).value, (m.npup, m.npup), np.float64, self._owner)
        self.T = Sparse._take(m.T, owner=self._owner)
        self.wfs = ShackHartmann(0, 0, None, 0, _ptr=m.wfs, _owner=self._owner)
        self.recon = Recon(m.recon, self._owner)

    def interaction_matrix(self):
        return self.wfs.interaction_matrix(self.T)

    def _replace_recon(self, call, function):
        """call() replaces the model's reconstructor: the one it had is handed to an owner that
        lives as long as the model's, so that the Recon taken before (its W, sv, and what was
        built on it) stays valid; put back if the call fails."""
        m = self._p.contents
        old = ctypes.cast(m.recon, ctypes.c_void_p).value
        m.recon = None
        try:
            check(call(), function)
        except BaseException:
            m.recon = ctypes.cast(old, type(m.recon))
            raise
        if old:
            self._owner.keep.append(_lib.Owner(ctypes.cast(old, P(_lib.swfs_recon)), lib.swfs_recon_free))
        self._refresh()
        return self

    def set_map(self, slopes, noise_var=0.0, remove_tiptilt=True):
        """Replace the reconstructor by the MAP reconstructor learned from slopes."""
        s = as_array(slopes, "slopes", np.float64, shape=(None, self.nslopes))
        return self._replace_recon(lambda: lib.swfs_speckle_model_set_map(self._p, dptr(s), s.shape[0], float(noise_var),
                                                                          int(bool(remove_tiptilt))),
                                   "swfs_speckle_model_set_map")

    def set_vk(self, slopes, L0=30.0, noise_var=0.0, remove_tiptilt=True):
        """Replace the reconstructor by the von Karman MAP reconstructor (the default of
        `specklewfs speckles`)."""
        s = as_array(slopes, "slopes", np.float64, shape=(None, self.nslopes))
        return self._replace_recon(lambda: lib.swfs_speckle_model_set_vk(self._p, dptr(self.xy), float(L0), dptr(s),
                                                                         s.shape[0], float(noise_var),
                                                                         int(bool(remove_tiptilt))),
                                   "swfs_speckle_model_set_vk")

    def recon_tilt(self):
        """(W_ext (nact, nslopes + 2), R (2, nslopes)) of speckles.h for the exposure
        tip-tilt model (the model's reconstructor must not be tip-tilt projected)."""
        W = P(ctypes.c_double)()
        R = P(ctypes.c_double)()
        check(lib.swfs_speckles_recon_tilt(self._p, dptr(self.xy), ctypes.byref(W), ctypes.byref(R)),
              "swfs_speckles_recon_tilt")
        addr = lambda x: ctypes.cast(x, ctypes.c_void_p).value
        return (_lib.take_buffer(addr(W), (self.nact, self.nslopes + 2), np.float64),
                _lib.take_buffer(addr(R), (2, self.nslopes), np.float64))

    def engine(self, nfx, nfy, alpha, wavelen, nthreads=1, recon=None, remove_tiptilt=False):
        """An Engine over this model (recon: a matrix replacing the model's, e.g. W_ext)."""
        W = self.recon.W if recon is None else recon
        return Engine(W, self.T, self.mask, nfx, nfy, alpha, wavelen, remove_tiptilt=remove_tiptilt,
                      nthreads=nthreads)


# ---- schedules -------------------------------------------------------------------------

def schedule(ratio, offset, nexp):
    """The common camera schedule (engine.h): (sched, nwfs_needed). sched is a structured
    array (fields first, count, w_first, w_last) with the C layout of swfs_exposure."""
    s = np.zeros(int(nexp), EXPOSURE_DTYPE)
    need = lib.swfs_engine_schedule(float(ratio), float(offset), int(nexp), s.ctypes.data)
    if need == 0:
        raise ValueError(f"schedule: invalid arguments ratio={ratio} offset={offset} nexp={nexp} (need ratio >= 0.1, "
                         "offset >= 0, nexp >= 1)")
    return s, int(need)


def make_schedule(first, count, w_first=1.0, w_last=1.0):
    """A schedule from arrays (broadcast)."""
    first, count, w_first, w_last = np.broadcast_arrays(first, count, w_first, w_last)
    for name, v in (("first", first), ("count", count)):  # whole frame numbers, not wrapped or truncated
        v = np.asarray(v)
        if v.size and (v.dtype.kind not in "iuf" or not np.all(np.isfinite(v)) or np.any(v < 0) or np.any(v != np.floor(v))):
            raise ValueError(f"make_schedule: {name} must be whole numbers of WFS frames >= 0, got {v.ravel()[:6]}")
    s = np.zeros(first.shape, EXPOSURE_DTYPE)
    s["first"], s["count"], s["w_first"], s["w_last"] = first, count, w_first, w_last
    return s


def _sched(s):
    s = np.asarray(s)
    if s.dtype != EXPOSURE_DTYPE:
        raise ValueError(f"schedule: expected a structured array of dtype {EXPOSURE_DTYPE} (schedule() or "
                         f"make_schedule()), got {s.dtype}")
    return np.ascontiguousarray(s)


def speckles_expand(slopes, R, sched):
    """Per-exposure copies of the WFS frames with the exposure tip-tilt (speckles.h):
    (expanded slopes (m, nslopes + 2), expanded schedule)."""
    s = as_array(slopes, "slopes", np.float64, ndim=2)
    nwfs, nslopes = s.shape
    R = as_array(R, "R", np.float64, shape=(2, nslopes))
    sched = _sched(sched)
    m = lib.swfs_speckles_expand_frames(sched.ctypes.data, sched.shape[0])
    out = np.empty((m, nslopes + 2))
    so = np.zeros(sched.shape[0], EXPOSURE_DTYPE)
    check(lib.swfs_speckles_expand(dptr(s), nslopes, nwfs, dptr(R), sched.ctypes.data, sched.shape[0], dptr(out),
                                   so.ctypes.data), "swfs_speckles_expand")
    return out, so


def speckles_subtract_static(cube, first=None, n=None, mode="ensemble"):
    """eq:computedSpeckleField in place on a complex cube (nframes, nfy, nfx): subtract the
    ensemble mean ('ensemble', or 'cube': the mean of each camera cube [first[c],
    first[c] + n[c]))."""
    cube = as_array(cube, "cube", np.complex128, ndim=3, writable=True)
    if first is None:
        first, n = [0], [cube.shape[0]]
    first = np.ascontiguousarray(first, dtype=np.uintp)
    n = as_array(n, "n", np.uintp, shape=first.shape)
    c = _lib.cplx_struct(cube)
    sp = P(ctypes.c_size_t)
    check(lib.swfs_speckles_subtract_static(ctypes.byref(c), first.ctypes.data_as(sp), n.ctypes.data_as(sp),
                                            first.shape[0], {"ensemble": 0, "cube": 1}[mode]),
          "swfs_speckles_subtract_static")
    return cube


# ---- the engine ------------------------------------------------------------------------

class Engine:
    """The per-frame engine (engine.h): slopes -> W -> T -> exp(i phi) -> MFT, core-phase
    referenced. recon: (nact, nslopes) matrix; interp: Sparse (npup^2 x nact) or a dense
    matrix; pupil: (npup, npup) transmission; alpha = PIXSCALE * PUPDX / TELDIAM."""

    def __init__(self, recon, interp, pupil, nfx, nfy, alpha, wavelen, remove_tiptilt=False, nthreads=1):
        W = as_array(recon.W if isinstance(recon, Recon) else recon, "recon", np.float64, ndim=2)
        T = interp if isinstance(interp, Sparse) else Sparse.from_dense(interp)
        pupil = as_array(pupil, "pupil", np.float64, ndim=2)
        nact, nslopes = W.shape
        c = _lib.swfs_engine_config(nslopes, nact, pupil.shape[0], int(nfx), int(nfy), float(alpha), float(wavelen),
                                    dptr(W), ctypes.pointer(T._s), dptr(pupil), int(bool(remove_tiptilt)),
                                    int(nthreads))
        if pupil.shape[0] != pupil.shape[1]:
            raise ValueError(f"pupil: expected a square (npup, npup) map, got shape {pupil.shape}")
        e = check_ptr(lib.swfs_engine_create(ctypes.byref(c)), "swfs_engine_create")
        self._e = e
        self._owner = _lib.Owner(e, lib.swfs_engine_free)
        self.nslopes, self.nact, self.npup, self.nfx, self.nfy = nslopes, nact, pupil.shape[0], int(nfx), int(nfy)

    @property
    def nthreads(self):
        return lib.swfs_engine_nthreads(self._e)

    @property
    def npin(self):
        """Illuminated pupil samples."""
        return lib.swfs_engine_npin(self._e)

    def _slopes(self, slopes):
        return as_array(slopes, "slopes", np.float64, shape=(None, self.nslopes))

    def add_wfs(self, slopes, weight=1.0):
        """Add one WFS frame (nslopes,) to the current exposure."""
        s = as_array(slopes, "slopes", np.float64, shape=(self.nslopes,))
        check(lib.swfs_engine_add_wfs(self._e, dptr(s), float(weight)), "swfs_engine_add_wfs")

    def end_exposure(self, out=None):
        """The exposure's core-referenced focal field (nfy, nfx); starts a new exposure."""
        if out is None:
            out = np.empty((self.nfy, self.nfx), np.complex128)
        out = as_array(out, "out", np.complex128, shape=(self.nfy, self.nfx), writable=True)
        check(lib.swfs_engine_end_exposure(self._e, out.ctypes.data), "swfs_engine_end_exposure")
        return out

    def reset(self):
        lib.swfs_engine_reset(self._e)

    def process(self, slopes, sched, out=None):
        """Camera frames (nexp, nfy, nfx) from slopes (nwfs, nslopes) and a schedule."""
        s = self._slopes(slopes)
        sched = _sched(sched)
        nexp = sched.shape[0]
        if nexp and int((sched["first"] + sched["count"]).max()) > s.shape[0]:
            raise ValueError(f"sched: exposures need {int((sched['first'] + sched['count']).max())} WFS frames, "
                             f"slopes has {s.shape[0]}")
        if out is None:
            out = np.empty((nexp, self.nfy, self.nfx), np.complex128)
        out = as_array(out, "out", np.complex128, shape=(nexp, self.nfy, self.nfx), writable=True)
        check(lib.swfs_engine_process(self._e, dptr(s), s.shape[0], sched.ctypes.data, nexp, out.ctypes.data),
              "swfs_engine_process")
        return out

    def process_wfs(self, slopes, out=None):
        """One core-referenced focal field per WFS frame: (nwfs, nfy, nfx)."""
        s = self._slopes(slopes)
        if out is None:
            out = np.empty((s.shape[0], self.nfy, self.nfx), np.complex128)
        out = as_array(out, "out", np.complex128, shape=(s.shape[0], self.nfy, self.nfx), writable=True)
        check(lib.swfs_engine_process_wfs(self._e, dptr(s), s.shape[0], out.ctypes.data), "swfs_engine_process_wfs")
        return out


# ---- MFT -----------------------------------------------------------------------------

class MFT:
    """Matrix Fourier transform (mft.h) between an npup x npup pupil grid and an nfy x nfx
    focal window with the conventions of docs/conventions.md (double precision)."""

    def __init__(self, npup, nfx, nfy, alpha, single=False):
        self._m = check_ptr(lib.swfs_mft_create(int(npup), int(nfx), int(nfy), float(alpha), int(bool(single))),
                            "swfs_mft_create")
        self._owner = _lib.Owner(self._m, lib.swfs_mft_free)
        self.npup, self.nfx, self.nfy = int(npup), int(nfx), int(nfy)

    def forward(self, pupil):
        p = as_array(pupil, "pupil", np.complex128, shape=(self.npup, self.npup))
        out = np.empty((self.nfy, self.nfx), np.complex128)
        check(lib.swfs_mft_forward(self._m, p.ctypes.data, out.ctypes.data), "swfs_mft_forward")
        return out

    def inverse(self, focal):
        f = as_array(focal, "focal", np.complex128, shape=(self.nfy, self.nfx))
        out = np.empty((self.npup, self.npup), np.complex128)
        check(lib.swfs_mft_inverse(self._m, f.ctypes.data, out.ctypes.data), "swfs_mft_inverse")
        return out

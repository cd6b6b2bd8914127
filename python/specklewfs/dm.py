"""The NCP correction on the deformable mirror (dmfit.h): a surface fitted onto the
actuators' influence functions, and `specklewfs dmoffsets` on a pupil product."""
import ctypes

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, dptr, enc
from .core import Geom
from .realdata import _opt

_INFLUENCE = {"gauss": 0, "cubic": 1}


def _fit_options(influence, coupling, pitch, modes, reg):
    o = _lib.swfs_dmfit_options()
    lib.swfs_dmfit_options_default(ctypes.byref(o))
    if influence not in _INFLUENCE:
        raise ValueError(f"influence: expected 'gauss' or 'cubic', got {influence!r}")
    o.influence = _lib.choice(_INFLUENCE, influence, "influence")
    if coupling is not None:
        o.coupling = float(coupling)
    if pitch is not None:
        o.pitch = float(pitch)
    if reg is not None:
        o.reg = float(reg)
    o.modes = int(modes)
    return o


class DMFit:
    """A least-squares fit of pupil surfaces onto a DM's actuators (dmfit.h), planned once.

    xy: (nact, 2) actuator positions [m] in the pupil frame; geom: PUPN, PUPDX, TELDIAM
    (and OBSCUR without a mask); mask: (pupn, pupn) or None; influence 'gauss' (coupling at
    one pitch, default 0.2; pitch None: the actuators' median nearest-neighbour distance) or
    'cubic' (the AO reconstruction's Clough-Tocher model); modes K > 0: fit only the
    target's projection on Noll Zernikes 1..K; reg: Tikhonov damping (default 1e-3).
    A pupil sample outside the actuators' hull is refused (a DM cannot correct there)."""

    def __init__(self, xy, geom, mask=None, influence="gauss", coupling=None, pitch=None, modes=0, reg=None):
        geom = geom if isinstance(geom, Geom) else Geom(**geom)
        xy = as_array(xy, "xy", np.float64, shape=(None, 2))
        if mask is not None:
            mask = as_array(mask, "mask", np.float64, shape=(geom.pupn, geom.pupn))
        o = _fit_options(influence, coupling, pitch, modes, reg)
        g = geom.to_c()
        f = ctypes.c_void_p()
        check(lib.swfs_dmfit_create(ctypes.byref(f), dptr(xy), xy.shape[0], ctypes.byref(g), dptr(mask),
                                    ctypes.byref(o)), "swfs_dmfit_create")
        self._f = f
        self._owner = _lib.Owner(f, lib.swfs_dmfit_free)
        self.geom, self.nact, self.npup = geom, int(lib.swfs_dmfit_nact(f)), int(lib.swfs_dmfit_npup(f))
        self.active, self.pitch = int(lib.swfs_dmfit_active(f)), float(lib.swfs_dmfit_pitch(f))

    def fit(self, target):
        """(cmd (nact,) [m], fitted surface (pupn, pupn) [m], stats dict) for a target
        surface (pupn, pupn) [m]; stats [m rms]: target_rms, modal_rms, filtered_rms, fit_rms,
        fiterr_rms, unfit_rms, cmd_rms, cmd_min, cmd_max. The NCP correction of a pupil
        product's WFE is the surface -WFE/2 (a reflective DM)."""
        t = as_array(target, "target", np.float64, shape=(self.npup, self.npup))
        cmd = np.empty(self.nact)
        fitted = np.empty((self.npup, self.npup))
        st = _lib.swfs_dmfit_stats()
        check(lib.swfs_dmfit_apply(self._f, dptr(t), dptr(cmd), dptr(fitted), ctypes.byref(st)), "swfs_dmfit_apply")
        return cmd, fitted, {n: getattr(st, n) for n in _lib.DMFIT_STATS_FIELDS}

    def surface(self, cmd):
        """The DM surface (pupn, pupn) [m] that commands cmd (nact,) [m] make (0 outside the pupil)."""
        c = as_array(cmd, "cmd", np.float64, shape=(self.nact,))
        out = np.empty((self.npup, self.npup))
        lib.swfs_dmfit_surface(self._f, dptr(c), dptr(out))
        return out


def dm_offsets(pupil, out, actuators=None, hexapolar=None, influence="gauss", coupling=None, pitch=None, modes=0,
               reg=None, provenance=()):
    """OFFSETS.fits (`specklewfs dmoffsets`): the DM offsets that cancel the NCP wavefront
    of a pupil product (pupil_files' output; its WFE, PUPIL and geometry): the surface
    -WFE/2 fitted onto the actuators (a positions file, or hexapolar = a ring pitch [m]),
    to ADD to the DM's current shape. Returns nact, active (those reaching the pupil),
    pitch [m] and stats (DMFit.fit's) as the command prints them."""
    if (actuators is None) == (hexapolar is None):
        raise ValueError("dm_offsets: give actuators (a positions file) or hexapolar (a ring pitch [m]), one of them")
    o = _lib.swfs_dmoffsets_run_options()
    lib.swfs_dmoffsets_run_options_default(ctypes.byref(o))
    o.pupil, o.out, o.actuators = enc(pupil), enc(out), _opt(actuators)
    o.hexapolar = 0.0 if hexapolar is None else float(hexapolar)
    o.fit = _fit_options(influence, coupling, pitch, modes, reg)
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = _lib.swfs_dmoffsets_run_result()
    check(lib.swfs_dmoffsets_run(ctypes.byref(o), ctypes.byref(r)), "swfs_dmoffsets_run")
    return dict(nact=r.nact, active=r.active, pitch=r.pitch,
                stats={n: getattr(r.stats, n) for n in _lib.DMFIT_STATS_FIELDS})


"""Pupil field and NCP wavefront from the static halo (pupil.h)."""
import ctypes
import os

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, enc
from .core import Geom, geom_arg
from .estimate import Halo

_WEIGHTS = {"none": 0, "snr": 1}
_SOURCES = {"lf": 0, "halo_lf": 0, "halo": 1}
_METHODS = {"auto": 0, "fit": 1, "moments": 2}


class PupilResult:
    """field (complex pupil field), wfe [m] (0 outside the pupil, piston removed),
    surface [m] (WFE/2), amplitude, mask: (pupn, pupn) views of the library's arrays;
    wfe_rms, wfe_pv [m], strehl (Marechal); method ('fit' or 'moments', what was used);
    weight, wiener_k, bias, source: the moments' options; geom. After a fit also halo_fit
    (complex focal-plane Psi of the fit), gain_fit (g map), kappa (unexplained speckle
    power fraction), fit_iterations, fit_noise_scale (the data's weight by the evidence),
    fit_nparams (the fit's unknowns), fit_warm_start, fit_log_evidence, fit_log_evidence_alt
    (the evidence rule run from the start and after a warm start: which fixed point was kept,
    its log evidence and the other's; jointfit.h),
    explained, explained_median (the self-check of the speckles: the science variance they
    explain, summed and median pixel), explained_map (per pixel; NaN where not solved) and
    explained_rings(). resmean: the AO residual's time mean [m] taken out of wfe (the halo's
    RESMEAN band-limited to the window, pupil.h), None when none was; resmean_rms [m]."""

    def __init__(self, ptr, geom):
        self._p = ptr
        self._owner = _lib.Owner(ptr, lib.swfs_pupil_result_free)
        r = ptr.contents
        self.field = _lib.cplx_view(r.field, self._owner)
        for n in ("wfe", "surface", "amplitude", "mask"):
            setattr(self, n, _lib.real_view(getattr(r, n), self._owner))
        self.wfe_rms, self.wfe_pv, self.strehl = r.wfe_rms, r.wfe_pv, r.strehl
        self.weight = {v: k for k, v in _WEIGHTS.items()}[r.opt.weight]
        self.wiener_k, self.bias = r.opt.wiener_k, r.opt.bias
        self.source = "halo" if r.opt.source == 1 else "lf"
        self.method = "fit" if r.method == 1 else "moments"
        self.halo_fit = self.gain_fit = self.kappa = self.fit_iterations = self.fit_noise_scale = None
        self.fit_nparams = self.fit_warm_start = self.fit_log_evidence = self.fit_log_evidence_alt = None
        self.explained, self.explained_median = r.explained, r.explained_median
        self.explained_map = _lib.real_view(r.explained_map, self._owner) if r.explained_map else None
        self.resmean = _lib.real_view(r.resmean, self._owner) if r.resmean else None
        self.resmean_rms = r.resmean_rms
        if r.method == 1 and r.fit:
            f = r.fit.contents
            self.halo_fit = _lib.cplx_view(f.halo, self._owner)
            self.gain_fit = _lib.real_view(f.gain, self._owner)
            self.kappa, self.fit_iterations, self.fit_noise_scale = f.kappa, f.iterations, f.noise_scale
            self.fit_nparams = f.nparams
            self.fit_warm_start = bool(f.warm_start)
            self.fit_log_evidence, self.fit_log_evidence_alt = f.log_evidence, f.log_evidence_alt
        self.geom = geom

    def explained_rings(self, nrings=None):
        """The self-check by ring of 1 lambda/D (pupil.h, swfs_pupil_explained_rings): array of
        the median explained fraction over [k, k + 1) lambda/D, NaN where a ring has no pixel;
        nrings defaults to the rings out to the window's edge. None after the moments."""
        if self.explained_map is None or self.geom is None:
            return None
        m, ps = self._p.contents.explained_map, float(self.geom.pixscale)
        n = int(nrings) if nrings is not None else min(32, lib.swfs_pupil_explained_nrings(m, ps))
        out = np.empty(n)
        lib.swfs_pupil_explained_rings(m, ps, out.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), n)
        return out

    def write(self, path, geom=None, provenance=()):
        """PUPIL.fits: FIELD, WFE, SURFACE, AMPLITUDE, PUPIL; keys WFERMS, WFEPV, STREHL."""
        g = geom_arg(geom if geom is not None else self.geom)
        prov, n = _lib.strings(provenance)
        check(lib.swfs_pupil_write(self._p, enc(path), ctypes.byref(g), prov, n), "swfs_pupil_write")


def pupil_estimate(halo, geom=None, mask=None, weight="snr", wiener_k=2.0, bias=0.0, source="lf", method="auto",
                   keep_resmean=False, g_radial=None):
    """Pupil field and NCP wavefront from a Halo (pupil.h; the defaults are those of
    `specklewfs pupil`). geom: a Geom (default halo.geom; needs WAVELEN, TELDIAM, OBSCUR,
    PIXSCALE, PUPDX, PUPN); mask: (pupn, pupn) transmission or None for the annulus;
    method 'auto' (the joint fit when the halo carries regression statistics, else the
    moments), 'fit' or 'moments'; for the moments: weight 'snr' (Wiener SNR^2/(SNR^2+k^2))
    or 'none', source 'lf' (HALO_LF) or 'halo'. When the halo carries the AO residual's time
    mean (HALO.fits RESMEAN, from `speckles` or a stream), it is taken out of the wavefront
    unless keep_resmean (`pupil --keep-resmean`). g_radial: the fit's radial log g terms'
    spacing [lambda/D] (`pupil --g-radial`; None: the library's default, 3; 0: none)."""
    if not isinstance(halo, Halo):
        raise TypeError(f"halo: expected a specklewfs.Halo, got {type(halo).__name__}")
    geom = geom if geom is not None else halo.geom
    if geom is None:
        raise ValueError("geom: the halo has no geometry; pass geom=Geom(...)")
    if isinstance(geom, dict):
        geom = Geom(**geom)
    g = geom.to_c()
    o = _options(weight, wiener_k, bias, source, method, keep_resmean, g_radial=g_radial)
    ms = ms_s = None
    if mask is not None:
        mask = as_array(mask, "mask", np.float64, ndim=2)
        ms_s = _lib.real_struct(mask)
        ms = ctypes.byref(ms_s)
    out = ctypes.POINTER(_lib.swfs_pupil_result)()
    check(lib.swfs_pupil_estimate(halo._p, ctypes.byref(g), ms, ctypes.byref(o), ctypes.byref(out)),
          "swfs_pupil_estimate")
    return PupilResult(out, geom)


def _options(weight, wiener_k, bias, source, method, keep_resmean, o=None, g_radial=None):
    """pupil.h's swfs_pupil_options from the keyword arguments (o: fill this one)."""
    if o is None:
        o = _lib.swfs_pupil_options()
        lib.swfs_pupil_options_default(ctypes.byref(o))
    o.weight = _lib.choice(_WEIGHTS, weight, "pupil: weight")
    o.source = _lib.choice(_SOURCES, source, "pupil: source")
    o.method = _lib.choice(_METHODS, method, "pupil: method")
    o.wiener_k, o.bias = float(wiener_k), float(bias)
    o.keep_resmean = 1 if keep_resmean else 0
    if g_radial is not None:
        if method == "moments":
            raise ValueError("pupil: g_radial applies to the fit, not to method='moments'")
        g_radial = float(g_radial)
        if not g_radial >= 0:
            raise ValueError(f"pupil: g_radial must be >= 0 (lambda/D; 0: no radial terms), got {g_radial}")
        o.fit.g_radial = g_radial
    return o


def pupil_files(halos, out, mask=None, truth=None, weight="snr", wiener_k=2.0, bias=0.0, source="lf",
                method="auto", keep_resmean=False, provenance=(), g_radial=None):
    """`specklewfs pupil` on files (run.h swfs_pupil_run): HALO.fits (a path, or several
    halos of the same frames, of which the self-check chooses one) -> PUPIL.fits `out`.
    mask: a pupil mask file (its PUPIL extension when it has one) or None for the annulus;
    truth: a simulation's truth file whose NCP the wavefront is compared with; the other
    options as pupil_estimate's. Returns a dict: pupil (the PupilResult written), halo (the
    path of the halo used), chosen (its index), explained (each halo's self-check score, with
    more than one) and ncommon, err, truth_rms, truth_rms_ptt [m] (swfs_wfe_compare's; NaN
    without truth), err_kept [m] (with truth: the error with the AO residual's time mean
    left in, what keep_resmean=True gives from the same fit; err where none was taken out),
    ran_away (the WFE above half the wavelength: the fit ran away from its start,
    no estimate; the command line warns). Nothing is written on failure."""
    halos = _lib.path_list(halos)
    halos = [os.fsdecode(h) for h in halos]  # (str, bytes or a path object)
    o = _lib.swfs_pupil_run_options()
    lib.swfs_pupil_run_options_default(ctypes.byref(o))
    _options(weight, wiener_k, bias, source, method, keep_resmean, o.pupil, g_radial=g_radial)
    names, o.nhalo = _lib.strings(halos)
    o.halos, o.out = names, enc(out)
    o.mask = enc(mask) if mask is not None else None
    o.truth = enc(truth) if truth is not None else None
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = _lib.swfs_pupil_run_result()
    check(lib.swfs_pupil_run(ctypes.byref(o), ctypes.byref(r)), "swfs_pupil_run")
    try:
        res = {"halo": halos[r.chosen], "chosen": int(r.chosen), "ncommon": int(r.ncommon),
               "explained": [r.explained[k] for k in range(len(halos))] if r.explained else None,
               "err": r.err, "truth_rms": r.truth_rms, "truth_rms_ptt": r.truth_rms_ptt,
               "err_kept": r.err_kept, "ran_away": bool(r.ran_away)}
        res["pupil"] = PupilResult(r.pupil, Geom.from_c(r.geom))
        r.pupil = None  # the PupilResult owns it now
    finally:
        lib.swfs_pupil_run_result_free(ctypes.byref(r))
    return res


def choose_halo(halos, names=None):
    """The self-check as a choice (`specklewfs pupil A.fits B.fits ...`, pupil.h
    swfs_halo_choose): halos of the same science frames from different computed speckles
    (another reconstructor, a learned one, another tip-tilt treatment), each with regression
    statistics. Returns (best, explained, ncommon): the index of the halo whose speckles
    explain the largest fraction of the science intensity's variance, those fractions, and
    the number of focal pixels (solved in every halo) they were taken over."""
    halos = list(halos)
    for k, h in enumerate(halos):
        if not isinstance(h, Halo):
            raise TypeError(f"halos[{k}]: expected a specklewfs.Halo, got {type(h).__name__}")
    n = len(halos)
    if n == 0:
        raise ValueError("choose_halo: no halo")
    arr = (ctypes.POINTER(_lib.swfs_halo) * n)(*[h._p for h in halos])
    nm = None
    if names is not None:
        names = [enc(str(x)) for x in names]
        if len(names) != n:
            raise ValueError(f"names: {len(names)} for {n} halos")
        nm = (ctypes.c_char_p * n)(*names)
    ex = np.full(n, np.nan)
    best, ncommon = ctypes.c_size_t(), ctypes.c_size_t()
    check(lib.swfs_halo_choose(arr, nm, n, ex.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), ctypes.byref(best),
                               ctypes.byref(ncommon)), "swfs_halo_choose")
    return best.value, ex, ncommon.value

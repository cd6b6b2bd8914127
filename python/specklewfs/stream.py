"""The speckle pipeline (pipeline.h: WFS telemetry arrays -> speckle fields matching the
science frames) and the stream (stream.h: batches of slopes and camera frames ->
accumulators -> the static-halo estimate, updated as the data arrive), with a Python
source callback."""
import ctypes
import os
import time

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, dptr, EXPOSURE_DTYPE
from .core import Geom
from .estimate import Accumulator, Halo, G_SMOOTH_DEFAULT
from .telemetry import Recon, SpeckleModel, _sched, _lags_c

P = ctypes.POINTER
_RECON = {"vk": 0, "map": 1, "svd": 2, "given": 3}
_TT = {"exposure": 0, "frame": 1, "keep": 2}


def _band(band):
    """pipeline.h options.band from 'auto', 'none' or a radius > 0 [lambda/D]."""
    if isinstance(band, str):
        if band not in ("auto", "none"):
            raise ValueError(f"band: expected 'auto', 'none' or a radius > 0 [lambda/D], got {band!r}")
        return 0.0 if band == "auto" else -1.0
    b = float(band)
    if not (b > 0 and np.isfinite(b)):
        raise ValueError(f"band: expected 'auto', 'none' or a radius > 0 [lambda/D], got {band!r}")
    return b


def _linear_options(recon, rcond, tiptilt, threads, wfs_rate, band):
    """pipeline.h options of a linear model's pipeline (recon: its interaction matrix's inverse)."""
    if recon not in ("map", "svd"):
        raise ValueError(f"recon: expected 'map' or 'svd' (an interaction matrix's inverse), got {recon!r}")
    return _file_options(recon, rcond, tiptilt, threads, wfs_rate, band)


def _file_options(recon, rcond, tiptilt, threads, wfs_rate, band):
    """pipeline.h options of a pipeline built from files (Pipeline.from_files, from_map)."""
    o = _lib.swfs_pipeline_options()
    lib.swfs_pipeline_options_default(ctypes.byref(o))
    o.recon, o.rcond = _lib.choice(_RECON, recon, "recon"), float(rcond)
    o.tiptilt, o.threads, o.wfs_rate = _lib.choice(_TT, tiptilt, "tiptilt"), int(threads), int(bool(wfs_rate))
    o.band = _band(band)
    return o


class Pipeline:
    """The speckle pipeline (pipeline.h).

    geom: a Geom with every keyword; nfx, nfy: the focal window; xy: (nact, 2) actuator
    positions [m]; nslopes: 2 nsub^2; mask: (pupn, pupn) or None (annulus); recon: 'vk'
    (default), 'map', 'svd' or a (nact, nslopes) matrix / Recon (used as given; a space-time
    one, Recon.read of `learn --lags`' map or Recon.from_matrix(W, lags), takes each frame as
    stack_lags(slopes, recon.lags)'s row: the pipeline's lags and nslopes say so); training:
    (ntrain, nslopes) WFS frames for 'vk' / 'map'; rcond, max_modes: for 'svd';
    slope_noise [rad] (0: estimated); vk_l0 [m]; tiptilt: 'exposure' (default), 'frame'
    or 'keep' (speckles.h); threads: engine workers; wfs_rate: one field per WFS frame
    (process_wfs; needs tiptilt 'frame' or 'keep'); valid: None or the AO system's
    (nsub, nsub) valid-subaperture map (nonzero = used, [b, a] = subaperture (a, b)): the
    subapertures used whatever their illumination, and nslopes may then be 2 nvalid (the
    used subapertures' x slopes in index order, then their y slopes); band: 'auto' (the
    speckles within the subapertures' sampling band nsub/2 lambda/D, 0 beyond; for a linear
    model everywhere), 'none' (everywhere) or a radius [lambda/D] (pipeline.h).
    mean_wavefront() is the reconstruction's time mean over the exposures processed (the AO
    residual's, as the telemetry measures it) [m] on the pupil grid."""

    def __init__(self, geom, nfx, nfy, xy, nslopes, mask=None, recon="vk", training=None, rcond=5e-2, max_modes=0,
                 slope_noise=0.0, vk_l0=10.0, tiptilt="exposure", threads=1, wfs_rate=False, valid=None, band="auto"):
        geom = geom if isinstance(geom, Geom) else Geom(**geom)
        g = geom.to_c()
        xy = as_array(xy, "xy", np.float64, shape=(None, 2))
        if mask is not None:
            mask = as_array(mask, "mask", np.float64, shape=(geom.pupn, geom.pupn))
        o = _lib.swfs_pipeline_options()
        lib.swfs_pipeline_options_default(ctypes.byref(o))
        rin = None
        if isinstance(recon, str):
            if recon not in _RECON or recon == "given":
                raise ValueError(f"recon: expected 'vk', 'map', 'svd' or a matrix, got {recon!r}")
            o.recon = _lib.choice(_RECON, recon, "recon")
        else:
            rin = recon if isinstance(recon, Recon) else Recon.from_matrix(
                as_array(recon, "recon", np.float64, shape=(xy.shape[0], nslopes)))
            o.recon = _RECON["given"]
        o.rcond, o.max_modes, o.slope_noise, o.vk_l0 = float(rcond), int(max_modes), float(slope_noise), float(vk_l0)
        o.tiptilt, o.threads, o.wfs_rate = _lib.choice(_TT, tiptilt, "tiptilt"), int(threads), int(bool(wfs_rate))
        o.band = _band(band)
        vmap = None
        if valid is not None:
            v = np.asarray(valid)
            if v.ndim != 2 or v.shape[0] != v.shape[1] or v.shape[0] == 0:
                raise ValueError(f"valid: expected a square (nsub, nsub) map, got shape {v.shape}")
            vmap = np.ascontiguousarray(v != 0, dtype=np.uint8)
            o.valid, o.valid_nsub = vmap.ctypes.data, vmap.shape[0]
        tr, ntr = None, 0
        if training is not None:
            tr = as_array(training, "training", np.float64, shape=(None, nslopes))
            ntr = tr.shape[0]
        p = ctypes.c_void_p()
        check(lib.swfs_pipeline_create(ctypes.byref(p), ctypes.byref(g), int(nfx), int(nfy), dptr(xy), xy.shape[0],
                                       dptr(mask), int(nslopes), rin._p if rin is not None else None, dptr(tr), ntr,
                                       ctypes.byref(o)), "swfs_pipeline_create")
        self._p = p
        self._owner = _lib.Owner(p, lib.swfs_pipeline_free)
        self.geom, self.nfx, self.nfy = geom, int(nfx), int(nfy)
        self.tiptilt, self.wfs_rate = tiptilt, bool(wfs_rate)
        self._frame_width(int(nslopes), rin.lags if rin is not None else ())

    def _frame_width(self, nvalues, lags):
        """nvalues: the telemetry's values per WFS frame; lags: a space-time map's (() for
        one frame's): each frame given to process is then stack_lags' row of them, nslopes
        = len(lags) x nvalues values (the pipeline's info.nslopes)."""
        self.lags, self.nvalues = tuple(lags), nvalues
        self.nslopes = int(self.info["nslopes"])

    def _frames(self, slopes, name="slopes"):
        s = np.asarray(slopes)
        if self.lags and s.ndim == 2 and s.shape[1] == self.nvalues:
            raise ValueError(f"{name}: {s.shape[1]} values per frame, one frame's; this pipeline's map is space-time "
                             f"(lags {list(self.lags)}): give each frame with its lagged frames, "
                             f"stack_lags({name}, pipeline.lags) over the contiguous series "
                             f"({self.nslopes} values per frame)")
        return as_array(s, name, np.float64, shape=(None, self.nslopes))

    @classmethod
    def linear(cls, geom, nfx, nfy, basis, control=None, imat=None, scale=1.0, registration=None, mask=None,
               training=None, recon="map", rcond=5e-2, tiptilt="exposure", threads=1, wfs_rate=False, band="auto",
               lags=None):
        """The pipeline over the generic linear model (lmodel.h, docs/telemetry.md): per WFS
        frame the wavefront is scale * B (A v).

        basis: (nk, pupn, pupn) on the pupil grid, or (nk, gy, gx) on the DM's own grid with
        registration = dict(pitch=[m per grid step], offset=(x0, y0) [m], rot=[deg],
        flip=bool); control: (nk, nmeas) or None (the telemetry values are the coefficients),
        or a space-time control matrix with lags = its lags [WFS frames] (one of them 0): a
        cube (nlags, nk, nv), one plane per lag as `learn --lags` writes it (read_control), or
        (nk, nlags nv) with lag k's block in columns [k nv, (k + 1) nv); each frame's
        coefficients are then sum_k C_k v(t + lags[k]), and process takes each frame as
        stack_lags(values, lags)'s row; imat: (nmeas, nk) instead (not with lags), inverted
        by the MAP reconstructor learned from training (ntrain, nmeas) ('map') or the
        truncated SVD ('svd', rcond); scale: metres of
        wavefront per unit of basis x coefficient (cacao: 2e-6); band: as for Pipeline
        ('auto' = everywhere here: a linear model has no subapertures to derive a band from)."""
        geom = geom if isinstance(geom, Geom) else Geom(**geom)
        g = geom.to_c()
        b = as_array(basis, "basis", np.float64, ndim=(3,))
        nk = b.shape[0]
        if mask is not None:
            mask = as_array(mask, "mask", np.float64, shape=(geom.pupn, geom.pupn))
        else:
            from .core import aperture  # the annulus the library would build
            mask = aperture(geom.pupn, geom.pupdx, geom.teldiam, geom.obscur)
        B = P(_lib.swfs_sparse)()
        shapes = None
        if registration is not None:
            r = _lib.swfs_dm_registration(float(registration["pitch"]), float(registration.get("offset", (0, 0))[0]),
                                          float(registration.get("offset", (0, 0))[1]),
                                          float(np.radians(registration.get("rot", 0.0))),
                                          int(bool(registration.get("flip", False))))
            nout = ctypes.c_size_t()
            # the factored form: the grid's interpolation and the modes' values at the grid points
            check(lib.swfs_grid_interp(ctypes.byref(B), b.shape[2], b.shape[1], ctypes.byref(r), dptr(mask),
                                       geom.pupn, geom.pupdx, ctypes.byref(nout)), "swfs_grid_interp")
            shapes = np.ascontiguousarray(b.reshape(nk, -1).T)
            if nout.value:
                lib.swfs_sparse_free(B)
                raise ValueError(f"registration: {nout.value} illuminated pupil samples lie more than one grid step "
                                 f"beyond the {b.shape[2]} x {b.shape[1]} DM grid")
        else:
            b = as_array(b, "basis", np.float64, shape=(nk, geom.pupn, geom.pupn))
            check(lib.swfs_basis_from_pupil(ctypes.byref(B), dptr(b), geom.pupn, nk, dptr(mask)),
                  "swfs_basis_from_pupil")
        try:
            ctl = im = None
            if control is not None and imat is not None:
                raise ValueError("control and imat: give one of them")
            lag_arr, nl = (None, 0) if lags is None else _lags_c(lags, "Pipeline.linear: lags")
            if control is not None:
                ctl = as_array(control, "control", np.float64, ndim=(2, 3))
                if ctl.ndim == 3:
                    if nl != ctl.shape[0]:
                        raise ValueError(f"control: a cube of {ctl.shape[0]} lags' planes needs lags= with as many "
                                         f"lags, got {'none' if lags is None else list(lags)}")
                    ctl = as_array(ctl, "control", np.float64, shape=(nl, nk, None))
                    ctl = np.ascontiguousarray(ctl.transpose(1, 0, 2).reshape(nk, -1))
                ctl = as_array(ctl, "control", np.float64, shape=(nk, None))
                if nl > 1 and ctl.shape[1] % nl:
                    raise ValueError(f"control: {ctl.shape[1]} columns, not {nl} lags' blocks of equal width")
                nmeas = ctl.shape[1]
            elif nl > 1:
                raise ValueError("lags: a space-time model needs its control matrix (control=); imat and the "
                                 "coefficients themselves are one frame's")
            elif imat is not None:
                im = as_array(imat, "imat", np.float64, shape=(None, nk))
                nmeas = im.shape[0]
            else:
                nmeas = nk
            o = _linear_options(recon, rcond, tiptilt, threads, wfs_rate, band)
            tr, ntr = None, 0
            if training is not None:
                tr = as_array(training, "training", np.float64, shape=(None, nmeas))
                ntr = tr.shape[0]
            lin = _lib.swfs_linear_input(nmeas, B, dptr(ctl), dptr(im), float(scale), dptr(shapes),
                                         nk if shapes is not None else 0, nl if nl > 1 else 0)
            p = ctypes.c_void_p()
            check(lib.swfs_pipeline_create_linear(ctypes.byref(p), ctypes.byref(g), int(nfx), int(nfy), dptr(mask),
                                                  ctypes.byref(lin), dptr(tr), ntr, ctypes.byref(o)),
                  "swfs_pipeline_create_linear")
        finally:
            lib.swfs_sparse_free(B)
        self = cls.__new__(cls)
        self._p = p
        self._owner = _lib.Owner(p, lib.swfs_pipeline_free)
        self.geom, self.nfx, self.nfy = geom, int(nfx), int(nfy)
        self.tiptilt, self.wfs_rate = tiptilt, bool(wfs_rate)
        self._frame_width(nmeas // nl if nl > 1 else nmeas, tuple(lag_arr[:nl]) if nl > 1 else ())
        return self

    @classmethod
    def from_files(cls, geom, nfx, nfy, linear, nmeas=0, training=None, mask=None, recon="map", rcond=5e-2,
                   tiptilt="exposure", threads=1, wfs_rate=False, band="auto"):
        """The linear model's pipeline from its files, as `stream --basis` and `live --basis`
        build it (run.h swfs_linear_pipeline): linear = dict(basis=, control= or imat=, scale=,
        dm_pitch=, dm_offset=, dm_rot=, dm_flip=) as speckles() takes it; a space-time control
        cube's lags (NLAGS, LAGk) become the pipeline's lags, and a map's MEANMISS (learn's, or
        the image speckles' write_recon= writes) its mean offset (meanmiss_rms [m]: its rms,
        0 without). nmeas: telemetry values per frame (0: as the control matrix takes)."""
        from .realdata import _linear
        geom = geom if isinstance(geom, Geom) else Geom(**geom)
        g = geom.to_c()
        lf = _lib.swfs_linear_files()
        _linear(lf, linear)
        if mask is not None:
            mask = as_array(mask, "mask", np.float64, shape=(geom.pupn, geom.pupn))
        o = _linear_options(recon, rcond, tiptilt, threads, wfs_rate, band)
        tr, ntr = None, 0
        if training is not None:
            tr = as_array(training, "training", np.float64, ndim=(2,))
            ntr = tr.shape[0]
        p = ctypes.c_void_p()
        check(lib.swfs_linear_pipeline(ctypes.byref(p), ctypes.byref(lf), ctypes.byref(g), int(nfx), int(nfy),
                                       dptr(mask), int(nmeas), dptr(tr), ntr, ctypes.byref(o)), "swfs_linear_pipeline")
        lags = (ctypes.c_long * _lib.RECON_MAXLAGS)()
        nl = ctypes.c_size_t()
        check(lib.swfs_linear_control_lags(ctypes.byref(lf), lags, ctypes.byref(nl)), "swfs_linear_control_lags")
        nls = nl.value if nl.value > 1 else 0
        return cls._built(p, geom, g, nfx, nfy, tiptilt, wfs_rate, tuple(lags[:nls]), lf.control, lf)

    @classmethod
    def _built(cls, p, geom, g, nfx, nfy, tiptilt, wfs_rate, lags, mapfile, lf):
        """A Pipeline over the pipeline p a run.h builder made from files: its frame width from
        its lags, the map file's MEANMISS (swfs_map_meanmiss_attach; lf the linear model's
        files, None for the Shack-Hartmann model's) as its mean offset."""
        self = cls.__new__(cls)
        self._p = p
        self._owner = _lib.Owner(p, lib.swfs_pipeline_free)
        self.geom, self.nfx, self.nfy = geom, int(nfx), int(nfy)
        self.tiptilt, self.wfs_rate = tiptilt, bool(wfs_rate)
        width = int(self.info["nslopes"])
        self._frame_width(width // len(lags) if lags else width, lags)
        rms = ctypes.c_double()
        check(lib.swfs_map_meanmiss_attach(p, mapfile, ctypes.byref(lf) if lf is not None else None, ctypes.byref(g),
                                           ctypes.byref(rms)), "swfs_map_meanmiss_attach")
        self.meanmiss_rms = rms.value
        return self

    @classmethod
    def from_map(cls, geom, nfx, nfy, recon, actuators, valid=None, telemetry=None, mask=None, tiptilt="exposure",
                 threads=1, wfs_rate=False, band="auto"):
        """The Shack-Hartmann model's pipeline with a map from its file, as `stream --recon
        W.fits --actuators A.fits [--valid V.fits]` and `live` build it (run.h
        swfs_sh_pipeline): recon a map file (learn's, teach's, speckles' write_recon=, any
        Recon.write; a space-time one's lags become the pipeline's lags: give each frame as
        stack_lags' row), actuators a file (actuators.fits) or (nact, 2) positions [m], valid
        None or the AO system's valid-subaperture map file (the map may then take the used
        subapertures' slopes only), telemetry None or a telemetry file checked against the
        model (a Shack-Hartmann's layout and NSUB, the file named where it is not), mask, tiptilt,
        threads, wfs_rate, band as Pipeline's. The map's MEANMISS (learn's miss of the
        residual's mean, per output) becomes the mean offset (meanmiss_rms [m]: its rms in the
        pupil, piston, tip and tilt out; 0 without)."""
        from .telemetry import actuators_read
        geom = geom if isinstance(geom, Geom) else Geom(**geom)
        g = geom.to_c()
        path = os.fspath(recon)
        rec = Recon.read(path)
        if isinstance(actuators, (str, os.PathLike)):
            xy, what = actuators_read(os.fspath(actuators)), os.fspath(actuators)
        else:
            xy, what = as_array(actuators, "actuators", np.float64, shape=(None, 2)), "the actuators given"
        if mask is not None:
            mask = as_array(mask, "mask", np.float64, shape=(geom.pupn, geom.pupn))
        o = _file_options("given", 0.0, tiptilt, threads, wfs_rate, band)
        per = rec.nslopes // (len(rec.lags) or 1)
        p = ctypes.c_void_p()
        def opt(v):
            return _lib.enc(os.fspath(v)) if v is not None else None
        check(lib.swfs_sh_pipeline(ctypes.byref(p), _lib.enc(f"{path} with {what}"), opt(valid), opt(telemetry),
                                   ctypes.byref(g), int(nfx), int(nfy), dptr(xy), xy.shape[0], dptr(mask), per, rec._p,
                                   None, 0, ctypes.byref(o)), "swfs_sh_pipeline")
        return cls._built(p, geom, g, nfx, nfy, tiptilt, wfs_rate, rec.lags, _lib.enc(path), None)

    @property
    def info(self):
        """dict: nact, nslopes, npup, nfx, nfy, recon_modes, recon_dof, noise_var,
        noise_given, ntrain, n_outside, vk_l0 (the outer scale used by the vk reconstructor);
        for a linear model nbasis, basis_nnz, composed (basis and control folded into one
        matrix) and resid_rms (the training frames' wavefront, tip-tilt removed [m]); band (the
        radius speckles are computed within [lambda/D], 0: everywhere) and band_out (focal
        pixels beyond it)."""
        i = _lib.swfs_pipeline_info()
        lib.swfs_pipeline_get_info(self._p, ctypes.byref(i))
        return {k: getattr(i, k) for k, _t in _lib.PIPELINE_INFO_FIELDS}

    @property
    def recon(self):
        """The reconstructor in use (a view owned by the pipeline); None for a linear model."""
        r = lib.swfs_pipeline_recon(self._p)
        return Recon(r, self._owner) if r else None

    @property
    def mask(self):
        """The Shack-Hartmann model's pupil mask (a view); None for a linear model."""
        m = lib.swfs_pipeline_model(self._p)
        if not m:
            return None
        m = m.contents
        return _lib.view(ctypes.cast(m.mask, ctypes.c_void_p).value, (m.npup, m.npup), np.float64, self._owner)

    def process(self, slopes, sched, out=None):
        """(nexp, nfy, nfx) core-referenced focal fields (before the static halo is
        subtracted) of the exposures sched over slopes (nwfs, nslopes): each WFS frame's
        values, or with lags (a space-time map) stack_lags(values, lags)'s rows."""
        s = self._frames(slopes)
        sched = _sched(sched)
        if out is None:
            out = np.empty((sched.shape[0], self.nfy, self.nfx), np.complex128)
        out = as_array(out, "out", np.complex128, shape=(sched.shape[0], self.nfy, self.nfx), writable=True)
        check(lib.swfs_pipeline_process(self._p, dptr(s), s.shape[0], sched.ctypes.data, sched.shape[0],
                                        out.ctypes.data), "swfs_pipeline_process")
        return out

    def process_wfs(self, slopes, out=None):
        s = self._frames(slopes)
        if out is None:
            out = np.empty((s.shape[0], self.nfy, self.nfx), np.complex128)
        out = as_array(out, "out", np.complex128, shape=(s.shape[0], self.nfy, self.nfx), writable=True)
        check(lib.swfs_pipeline_process_wfs(self._p, dptr(s), s.shape[0], out.ctypes.data),
              "swfs_pipeline_process_wfs")
        return out

    def mean_wavefront(self):
        """(wavefront, nexp): the reconstruction's time mean over the exposures processed so far
        [m] on the (pupn, pupn) grid, piston, tip and tilt removed (pipeline.h
        swfs_pipeline_mean_wavefront: the AO residual's time mean as the telemetry measures it)."""
        n = self.geom.pupn
        out = np.empty((n, n), np.float64)
        nexp = ctypes.c_size_t()
        check(lib.swfs_pipeline_mean_wavefront(self._p, dptr(out), ctypes.byref(nexp), None), "swfs_pipeline_mean_wavefront")
        return out, nexp.value

    def mean_offset(self, offset):
        """A miss of the AO residual's time mean, added to mean_wavefront() from then on before
        piston, tip and tilt come out (pipeline.h swfs_pipeline_set_mean_offset): offset (pupn,
        pupn) [m] on the pupil grid, e.g. the MEANMISS image of the map speckles wrote
        (write_recon=) where it chose among the loops' maps, read_fits(path, 'MEANMISS')[0];
        None: none. What `stream --control` and `live` add from such a map."""
        if offset is None:
            check(lib.swfs_pipeline_set_mean_offset(self._p, None), "swfs_pipeline_set_mean_offset")
            return
        n = self.geom.pupn
        off = as_array(offset, "offset", np.float64, shape=(n, n))
        check(lib.swfs_pipeline_set_mean_offset(self._p, dptr(off)), "swfs_pipeline_set_mean_offset")

    def mean_reset(self):
        """Start the time mean anew."""
        lib.swfs_pipeline_mean_reset(self._p)

    def mean_loops(self, dirs):
        """The miss of the AO residual's time mean by this pipeline's reconstruction, from
        simulated closed loops of the same system (`--mean-loop DIR...`; run.h
        swfs_pipeline_mean_loops): dirs, at least 2 folders of `simulate_timeseries` (the
        telemetry of this pipeline's kind, truth.fits' RESMEAN), e.g. the mean_NN that
        `speckles(..., mean_loops='teach')` left in its teach folder. Where the others' mean
        predicts each loop's miss (held out below 1) their mean is added to mean_wavefront()
        from then on. Returns dict(heldout=ratio, rms=[m] of what was added, 0 if nothing)."""
        names = [os.fspath(d) for d in dirs]
        arr, n = _lib.strings(names)
        held, rms = ctypes.c_double(), ctypes.c_double()
        check(lib.swfs_pipeline_mean_loops(self._p, arr, n, ctypes.byref(held), ctypes.byref(rms)),
              "swfs_pipeline_mean_loops")
        return {"heldout": held.value, "rms": rms.value}

    def flat_halo(self):
        """Psi_0: the referenced focal field of flat slopes (nfy, nfx)."""
        out = np.empty((self.nfy, self.nfx), np.complex128)
        check(lib.swfs_pipeline_flat_halo(self._p, out.ctypes.data), "swfs_pipeline_flat_halo")
        return out


class Stream:
    """The stream (stream.h) over a Pipeline (kept alive by the stream).

    static: 'auto' (default: the unaberrated halo scaled by the first batch's core
    amplitude, the paper's choice), 'none', or an (nfy, nfx) complex array; read_noise
    [counts], gain [e-/count], g_smooth [pixels]: the estimator's options; every: update
    after this many camera frames (0: only at the end); every_seconds; max_frames (0: all).

    Feed it with push(slopes, sched, science) per batch, or run(source) with an iterable
    of batches (tuples (slopes, sched, science) or dicts with those keys and an optional
    'cube' label); each batch: science (nexp, nfy, nfx) camera frames, slopes (nwfs,
    nslopes) the WFS frames they integrate, sched (nexp,) exposure schedule into slopes."""

    def __init__(self, pipeline, static="auto", read_noise=0.0, gain=0.0, g_smooth=G_SMOOTH_DEFAULT, every=0,
                 every_seconds=0.0, max_frames=0):
        if not isinstance(pipeline, Pipeline):
            raise TypeError(f"pipeline: expected a specklewfs.Pipeline, got {type(pipeline).__name__}")
        o = _lib.swfs_stream_options()
        lib.swfs_stream_options_default(ctypes.byref(o))
        self._static_in = None
        if isinstance(static, str):
            modes = {"auto": 0, "none": 1}
            if static not in modes:
                raise ValueError(f"static: expected 'auto', 'none' or an array, got {static!r}")
            o.static_mode = modes[static]
        else:
            self._static_in = as_array(static, "static", np.complex128, shape=(pipeline.nfy, pipeline.nfx))
            o.static_mode, o.static_halo = 2, self._static_in.ctypes.data
        o.noise = _lib.swfs_noise(float(read_noise), float(gain))
        o.est = _lib.swfs_estimate_options(float(g_smooth))
        o.every, o.every_seconds, o.max_frames = int(every), float(every_seconds), int(max_frames)
        s = ctypes.c_void_p()
        check(lib.swfs_stream_create(ctypes.byref(s), pipeline._p, ctypes.byref(o)), "swfs_stream_create")
        self._s = s
        self.pipeline = pipeline  # borrowed by the C stream: keep it alive (and free it after)
        self._owner = _lib.Owner(s, lib.swfs_stream_free)
        self._pending = None

    def _batch(self, item):
        if isinstance(item, dict):
            slopes, sched, science, cube = item["slopes"], item["sched"], item["science"], item.get("cube", 0)
        else:
            slopes, sched, science = item[:3]
            cube = item[3] if len(item) > 3 else 0
        p = self.pipeline
        s = p._frames(slopes)
        sc = _sched(sched)
        sci = as_array(science, "science", np.float64, shape=(sc.shape[0], p.nfy, p.nfx))
        if sc.shape[0] and int((sc["first"] + sc["count"]).max()) > s.shape[0]:
            raise ValueError(f"sched: exposures need {int((sc['first'] + sc['count']).max())} WFS frames, slopes has "
                             f"{s.shape[0]}")
        b = _lib.swfs_batch(dptr(s), s.shape[0], sc.ctypes.data, dptr(sci), sc.shape[0], int(cube))
        return b, (s, sc, sci)

    def push(self, slopes, sched, science, cube=0):
        """Process one batch."""
        b, keep = self._batch((slopes, sched, science, cube))
        check(lib.swfs_stream_push(self._s, ctypes.byref(b)), "swfs_stream_push")
        return self

    def run(self, source, on_update=None):
        """Pull batches from `source` (an iterable) until it ends or max_frames, calling
        on_update(stream, final) at every update and once at the end. An exception raised
        by the source or the callback stops the run and is re-raised here."""
        it = iter(source)
        state = {"keep": None, "exc": None}

        def next_batch(ctx, bp):
            try:
                end = object()
                item = next(it, end)
                if item is end:
                    bp.contents.nexp = 0
                    state["keep"] = None
                    return 0
                if item is None:  # (not the end: the batches after it would be dropped in silence)
                    raise ValueError("Stream.run: the source gave None as a batch; expected (slopes, schedule, "
                                     "science) batches, and the end of the iteration to stop")
                b, keep = self._batch(item)
                state["keep"] = keep  # valid until the next call, as stream.h asks
                ctypes.memmove(bp, ctypes.byref(b), ctypes.sizeof(b))
                return 0
            except BaseException as e:  # noqa: BLE001 -- re-raised after the C call returns
                state["exc"] = e
                return _lib.SWFS_ERR_INTERNAL

        def update(ctx, s, final):
            try:
                if on_update is not None:
                    on_update(self, bool(final))
                return 0
            except BaseException as e:  # noqa: BLE001
                state["exc"] = e
                return 8

        src_cb, upd_cb = _lib.SOURCE_FN(next_batch), _lib.UPDATE_FN(update)
        rc = lib.swfs_stream_run(self._s, src_cb, None, upd_cb, None)
        if state["exc"] is not None:
            raise state["exc"]
        check(rc, "swfs_stream_run")
        return self

    def estimate(self):
        """The halo estimate from what has been accumulated."""
        out = P(_lib.swfs_halo)()
        check(lib.swfs_stream_estimate(self._s, ctypes.byref(out)), "swfs_stream_estimate")
        return Halo._take(out)

    def accumulator(self):
        """A copy of the stream's accumulators (an Accumulator)."""
        src = lib.swfs_stream_accum(self._s)
        a = Accumulator(src.contents.nx, src.contents.ny)
        check(lib.swfs_accum_merge(a._p, src), "swfs_accum_merge")
        return a

    @property
    def static_halo(self):
        """The static halo in use (nfy, nfx), or None before the first batch ('auto')."""
        p = lib.swfs_stream_static(self._s)
        if not p:
            return None
        return _lib.view(p, (self.pipeline.nfy, self.pipeline.nfx), np.complex128, self._owner)

    camera_frames = property(lambda self: int(lib.swfs_stream_camera_frames(self._s)))
    wfs_frames = property(lambda self: lib.swfs_stream_wfs_frames(self._s))
    seconds = property(lambda self: lib.swfs_stream_seconds(self._s))
    static_scale = property(lambda self: lib.swfs_stream_static_scale(self._s))


class FrameSync:
    """Timestamped frames -> stream batches (framesync.h): the live counterpart of the
    timing table, for frames that come from a source of one's own (a telemetry server, a
    camera SDK) rather than shared memory (`live`).

    nvals: values per frame of each WFS stream (an int for one; several are concatenated
    in this order into each frame's slope vector); shape: the camera frames' (nfy, nfx);
    batch: camera frames per batch; max_wait [s]: the longest a ready camera frame waits
    for its batch to fill; exptime [s]: the camera's exposure (0: its frame period);
    clock_memory [frames]; wfs_history, camera_queue: 0 for the library's defaults; lags:
    a space-time map's (pipeline.lags), each batch row then the frame's values stacked at
    them, the batch waiting for the frames its largest lag needs (framesync.h "Lags").

    Stamps are integers [ns] of the writers' clock marking the END of each frame, counters
    the writers' frame counters (a jump counts dropped frames, one going back a restart).
    Add frames in the order they arrive; take the batches with next() or batches(), each a
    dict (slopes (nwfs, nslopes), sched, science (nexp, nfy, nfx), cube, stamps [ns]; copies,
    valid after the next call) as Stream.run takes its source's batches, or
    Stream.push(b["slopes"], b["sched"], b["science"]). now [s]: the monotonic time for
    max_wait (default time.monotonic())."""

    def __init__(self, nvals, shape, batch=16, max_wait=0.5, exptime=0.0, clock_memory=4096.0, wfs_history=0,
                 camera_queue=0, lags=None):
        nv = [int(nvals)] if np.ndim(nvals) == 0 else [int(v) for v in nvals]
        if not nv or min(nv) < 1:
            raise ValueError(f"nvals: expected values per frame of each WFS stream (>= 1), got {nvals!r}")
        ny, nx = (int(v) for v in shape)
        if ny < 1 or nx < 1:
            raise ValueError(f"shape: expected the camera frames' (nfy, nfx), got {shape!r}")
        o = _lib.swfs_framesync_options()
        lib.swfs_framesync_options_default(ctypes.byref(o))
        o.batch, o.max_wait, o.exptime, o.clock_memory = int(batch), float(max_wait), float(exptime), float(clock_memory)
        o.wfs_history, o.camera_queue = int(wfs_history), int(camera_queue)
        self.lags = ()
        if lags is not None and len(lags) > 1:
            self._lag_arr, n = _lags_c(lags, "FrameSync: lags")
            o.lags, o.nlags = self._lag_arr, n
            self.lags = tuple(self._lag_arr[:n])
        nva = (ctypes.c_size_t * len(nv))(*nv)
        f = ctypes.c_void_p()
        check(lib.swfs_framesync_create(ctypes.byref(f), len(nv), nva, ny * nx, ctypes.byref(o)), "swfs_framesync_create")
        self._f = f
        self._owner = _lib.Owner(f, lib.swfs_framesync_free)
        self.nvals, self.shape = tuple(nv), (ny, nx)
        self.nvalues = int(lib.swfs_framesync_nslopes(f))
        self.nslopes = self.nvalues * max(len(self.lags), 1)

    @staticmethod
    def _now(now):
        return time.monotonic() if now is None else float(now)

    def add_wfs(self, values, counter, stamp_ns, stream=0, now=None):
        """One frame of WFS stream `stream`: its nvals[stream] values (copied)."""
        i = int(stream)
        if not 0 <= i < len(self.nvals):
            raise ValueError(f"stream: expected 0..{len(self.nvals) - 1}, got {stream}")
        v = as_array(values, "values", np.float64, shape=(self.nvals[i],))
        check(lib.swfs_framesync_add_wfs(self._f, i, int(counter), int(stamp_ns), dptr(v), self._now(now)),
              "swfs_framesync_add_wfs")

    def add_camera(self, frame, counter, stamp_ns, now=None):
        """One camera frame (nfy, nfx) (copied)."""
        fr = as_array(frame, "frame", np.float64, shape=self.shape)
        check(lib.swfs_framesync_add_camera(self._f, int(counter), int(stamp_ns), dptr(fr), self._now(now)),
              "swfs_framesync_add_camera")

    def expect(self, last, camera=False, stream=0, restarted=False):
        """The counter of WFS stream `stream` (or of the camera) stood at `last` when it was
        opened: frames after it that never arrive count as dropped; restarted: the writer
        started counting again (a new segment)."""
        lib.swfs_framesync_expect(self._f, int(bool(camera)), int(stream), int(last), int(bool(restarted)))

    def settle(self, stamp_ns):
        """Skip camera exposures that begin before stamp_ns (e.g. until a DM change settled)."""
        lib.swfs_framesync_settle(self._f, int(stamp_ns))

    def next(self, flush=False, now=None):
        """The next batch if one is ready, else None; flush: close the batch being filled
        and skip frames that cannot be completed (the end of the data)."""
        b = _lib.swfs_batch()
        check(lib.swfs_framesync_next(self._f, self._now(now), int(bool(flush)), ctypes.byref(b)),
              "swfs_framesync_next")
        if not b.nexp:
            return None
        addr = lambda p: ctypes.cast(p, ctypes.c_void_p).value
        sl = _lib.view(addr(b.slopes), (b.nwfs, self.nslopes), np.float64, None).copy()
        sc = _lib.view(b.sched, (b.nexp,), EXPOSURE_DTYPE, None).copy()
        sci = _lib.view(addr(b.science), (b.nexp,) + self.shape, np.float64, None).copy()
        st = _lib.view(addr(lib.swfs_framesync_batch_stamps(self._f)), (b.nexp,), np.int64, None).copy()
        return dict(slopes=sl, sched=sc, science=sci, cube=int(b.cube), stamps=st)

    def batches(self, flush=False, now=None):
        """Every batch ready now (with flush: and the rest), as next() gives them."""
        while True:
            b = self.next(flush, now)
            if b is None:
                return
            yield b

    @property
    def stats(self):
        """dict: the counts of framesync.h swfs_framesync_stats (frames received, dropped,
        restarts, segments, used, skipped by cause, batches) and wfs_period, camera_period [s]."""
        st = _lib.swfs_framesync_stats()
        lib.swfs_framesync_get_stats(self._f, ctypes.byref(st))
        return {n: getattr(st, n) for n, _t in st._fields_}

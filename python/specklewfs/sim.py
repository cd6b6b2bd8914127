"""The simulators: the paper's Sec. 3 ensemble (sim.h), one noise level end to end
(recovery.h) and the AO time series of the real-data path (timeseries.h)."""
import ctypes
import os
import signal
import threading

import numpy as np

from . import _lib
from ._lib import lib, check, check_ptr, as_array, dptr, enc
from .core import Geom, geom_arg

P = ctypes.POINTER


def _cfg_value(v):
    """A config value as text: numbers, strings, or sequences written comma-separated."""
    if isinstance(v, (list, tuple, np.ndarray)):
        return ", ".join(repr(float(x)) if not isinstance(x, str) else x for x in np.ravel(v).tolist())
    return repr(v) if isinstance(v, float) else str(v)


def _config(config, params):
    """A swfs_config from a config file and key=value overrides (_cfg_value)."""
    c = check_ptr(lib.swfs_config_new(), "swfs_config_new")
    owner = _lib.Owner(c, lib.swfs_config_free)
    if config is not None:
        check(lib.swfs_config_load(c, enc(config)), "swfs_config_load")
    for k, v in params.items():
        check(lib.swfs_config_set_kv(c, str(k).encode(), _cfg_value(v).encode()), "swfs_config_set_kv")
    return c, owner


class _Progress:
    """A run's progress callback (status.h swfs_progress_fn), used as `with _Progress(p) as
    prog: rc = lib.f(..., prog.fn, ...)` then `prog.check(rc, "f")`. It calls the caller's
    progress(stage, done, total), if given; an exception raised there asks the run to stop,
    the library removes what it had begun to write, and check() raises that exception rather
    than the library's SWFS_ERR_STOPPED. Ctrl-C stops the run the same way: for the call's
    length (on the main thread, where SIGINT has Python's default handler) SIGINT only marks
    the run interrupted, the library's next report asks it to stop, and check() raises
    KeyboardInterrupt -- also after a run that ended before its next report."""

    def __init__(self, progress):
        if progress is not None and not callable(progress):
            raise TypeError(f"progress: expected a callable(stage, done, total) or None, got {progress!r}")
        self.error, self.interrupted, self._old = None, False, None

        def cb(_ctx, stage, done, total):
            if self.interrupted:
                return 1
            try:
                if progress is not None:
                    progress(stage.decode(errors="replace") if stage else "", int(done), int(total))
            except BaseException as e:  # noqa: B036 -- the caller's own KeyboardInterrupt too
                self.error = e
                return 1
            return 1 if self.interrupted else 0
        self.fn = _lib.PROGRESS_FN(cb)

    def _on_sigint(self, _signum, _frame):
        self.interrupted = True

    def __enter__(self):
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._old = signal.signal(signal.SIGINT, self._on_sigint)
        return self

    def __exit__(self, *exc):
        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
            self._old = None
        return False

    def check(self, rc, function):
        e, self.error = self.error, None
        if rc == _lib.SWFS_ERR_STOPPED and e is not None:
            raise e
        if self.interrupted:
            raise KeyboardInterrupt
        check(rc, function)


def _run(function, o, result, geom=None, provenance=(), progress=None):
    """run.h's `function` on options o (their geometry, provenance and progress filled in
    here); its result struct, raising Error on failure (or the progress callback's own
    exception: _Progress)."""
    if geom is not None:
        o.geom = geom_arg(geom)
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = result()
    with _Progress(progress) as prog:
        o.progress = prog.fn
        rc = getattr(lib, function)(ctypes.byref(o), ctypes.byref(r))
    prog.check(rc, function)
    return r


def _struct_dict(s):
    out = {}
    for name, _t in s._fields_:
        v = getattr(s, name)
        if isinstance(v, _lib.Struct):
            out[name] = _struct_dict(v)
        elif isinstance(v, bytes):
            out[name] = v.decode()
        elif isinstance(v, ctypes.Array):
            out[name] = list(v)
        else:
            out[name] = v
    return out


def sim_params(config=None, **params):
    """The Sec. 3 simulation parameters (config file keys, config/paper-sec3.conf) as the
    library reads and checks them, as a dict."""
    p = _params(config, params)
    return _struct_dict(p)


def _checked_params(kind, config, params, describe=None):
    """swfs_<kind>_params from the defaults, the config and the keyword overrides, read and
    checked by the library (kind: "sim" or "ts"); describe(c), if given, adds keys first."""
    c, owner = _config(config, params)
    if describe is not None:
        describe(c)
    p = getattr(_lib, "swfs_%s_params" % kind)()
    getattr(lib, "swfs_%s_params_default" % kind)(ctypes.byref(p))
    for name, args in (("swfs_%s_params_from_config" % kind, (c, ctypes.byref(p))),
                       ("swfs_config_check_unused", (c,)),
                       ("swfs_%s_params_check" % kind, (ctypes.byref(p),))):
        check(getattr(lib, name)(*args), name)
    del owner
    return p


def _params(config, params):
    return _checked_params("sim", config, params)


class SimResult:
    """The Sec. 3 data set (sim.h). Arrays (views of the library's memory):
    science (nframes, nfy, nfx) noise-free counts, speckles (nframes, nfy, nfx) complex
    psi, speckle_mean, halo_true (nfy, nfx) complex, ncp [m] and pupil (pupn, pupn),
    ref_phase (nframes,). Scalars: nframes, per_screen, counts_scale, field_scale,
    residual_rms, expected_rms, lag_floor_rms, kernel_sigma, strehl, strehl_ao,
    window_fraction, ncp_rms, ncp_pv, seconds; geom; params (dict)."""

    def __init__(self, ptr):
        self._p = ptr
        self._owner = _lib.Owner(ptr, lib.swfs_sim_result_free)
        r = ptr.contents
        self.geom = Geom.from_c(r.geom)
        self.params = _struct_dict(r.params)
        self.nframes, self.per_screen = r.nframes, r.per_screen
        self.science = _lib.real_view(r.science, self._owner, squeeze=False)
        self.speckles = _lib.cplx_view(r.speckles, self._owner, squeeze=False)
        self.speckle_mean = _lib.cplx_view(r.speckle_mean, self._owner)
        self.halo_true = _lib.cplx_view(r.halo_true, self._owner)
        self.ncp = _lib.real_view(r.ncp, self._owner)
        self.pupil = _lib.real_view(r.pupil, self._owner)
        self.ref_phase = _lib.view(ctypes.cast(r.ref_phase, ctypes.c_void_p).value, (r.nframes,), np.float64,
                                   self._owner)
        for n in _lib.SIM_RESULT_SCALARS:
            setattr(self, n, getattr(r, n))

    def camera(self, read_noise=None, gain=None, seed=None):
        """A noisy copy of the science cube (sim.h swfs_sim_camera): per frame k an RNG
        stream (seed, k), Poisson(clean * gain) / gain (gain <= 0: none) + read_noise
        N(0, 1). Defaults: the parameters' read_noise and gain, and the seed that
        `specklewfs simulate` uses (seed ^ 0x5eed0fca3e7a)."""
        p = self._p.contents.params
        read_noise = p.read_noise if read_noise is None else read_noise
        gain = p.gain if gain is None else gain
        seed = (p.seed ^ 0x5eed0fca3e7a) if seed is None else seed
        noisy = np.empty_like(self.science)
        src, dst = _lib.real_struct(self.science), _lib.real_struct(noisy)
        check(lib.swfs_sim_camera(ctypes.byref(src), float(read_noise), float(gain), int(seed) & (2**64 - 1),
                                  ctypes.byref(dst)), "swfs_sim_camera")
        return noisy

    def write(self, directory, science=None, read_noise=None, gain=None, provenance=()):
        """DIR/science.fits, speckles.fits, truth.fits, pupil.fits, as `specklewfs simulate`
        writes them. science: the cube to write (default: the noise-free one)."""
        p = self._p.contents.params
        read_noise = p.read_noise if read_noise is None else read_noise
        gain = p.gain if gain is None else gain
        sci = self.science if science is None else as_array(science, "science", np.float64,
                                                            shape=self.science.shape)
        s = _lib.real_struct(sci)
        prov, n = _lib.strings(provenance)
        check(lib.swfs_sim_write(self._p, ctypes.byref(s), float(read_noise), float(gain), enc(directory), prov, n),
              "swfs_sim_write")

    def recovery(self, sigma, seed=None, directory=None, provenance=()):
        """One noise level end to end (recovery.h, a row of `specklewfs demo`): dict with
        sigma, valid_fraction, bad_radicand, median_snr, err_paper, err_halo, err_lf,
        err_lf_snr (the default path), wfe_rms, wfe_pv, strehl ([m] for errors). seed
        defaults to the demo's, seed * 1000003 + sigma."""
        p = self._p.contents.params
        if seed is None:
            seed = (p.seed * 1000003 + int(sigma)) & (2**64 - 1)
        out = _lib.swfs_recovery()
        prov, n = _lib.strings(provenance)
        check(lib.swfs_recovery_run(self._p, float(sigma), int(seed), enc(directory) if directory else None, prov, n,
                                    ctypes.byref(out)), "swfs_recovery_run")
        return {k: getattr(out, k) for k in _lib.RECOVERY_FIELDS}


def simulate(config=None, progress=None, ncp=None, **params):
    """Run the paper's Sec. 3 simulation (sim.h). config: a config file (e.g.
    config/paper-sec3.conf); params: key=value overrides with the config keys (screen_n,
    nscreens, pupn, nfx, seed, threads, ...; unknown keys raise). progress: callable(stage,
    done, total). ncp: an NCP map [m] (pupn, pupn) replacing the parameters' NCP terms.
    Returns a SimResult."""
    p = _params(config, params)
    out = P(_lib.swfs_sim_result)()
    if ncp is not None:
        ncp = as_array(ncp, "ncp", np.float64, shape=(p.pupn, p.pupn))
    with _Progress(progress) as prog:
        if ncp is None:
            rc, name = lib.swfs_sim_paper_run(ctypes.byref(p), prog.fn, None, ctypes.byref(out)), "swfs_sim_paper_run"
        else:
            rc = lib.swfs_sim_paper_run_ncp(ctypes.byref(p), dptr(ncp), prog.fn, None, ctypes.byref(out))
            name = "swfs_sim_paper_run_ncp"
    prog.check(rc, name)
    return SimResult(out)


def demo(directory="demo-out", config=None, levels=(0, 10, 100, 1000), report=True, loop_iterations=None,
         loop_gain=None, loop_sigma=None, progress=None, provenance=(), **params):
    """`specklewfs demo` (run.h swfs_demo_run): the paper's Sec. 3 simulation (config and
    params as simulate()'s), each camera noise level in `levels` [counts] recovered into
    DIR/sigma<level>/ and DIR/recovery.tsv, then the closed loop (loop_iterations, default 5,
    0 for none; loop_gain 0.8; loop_sigma 100 counts) into DIR/loop/, then the figures
    (DIR/report/index.html) unless report is False. All products are renamed into place
    together: a failure leaves none. progress: callable(stage, done, total).
    Returns a dict: sim (the SimResult), recovery (one dict per level as
    SimResult.recovery's, with its seconds), loop (one dict per row of the loop table:
    resid_rms, resid_rms_ptt, strehl, ..., est_err, fit_rms, unfit_rms, seconds; [] without
    the loop), ncp_rms_ptt [m], sim_seconds, seconds, html ("" without the report)."""
    o = _lib.swfs_demo_run_options()
    lib.swfs_demo_run_options_default(ctypes.byref(o))
    o.sim = _params(config, params)
    lv = np.ascontiguousarray(np.atleast_1d(np.asarray(levels, dtype=np.float64)))
    if lv.ndim != 1 or lv.size == 0:
        raise ValueError("levels: expected a list of camera noise levels [counts], got %r" % (levels,))
    o.levels, o.nlevels = dptr(lv), lv.size
    o.outdir = enc(directory)
    o.report = 1 if report else 0
    if config is not None:
        o.config = enc(config)
    if loop_iterations is not None:
        o.loop.iterations = int(loop_iterations)
    if loop_gain is not None:
        o.loop.gain = float(loop_gain)
    if loop_sigma is not None:
        o.loop.sigma = float(loop_sigma)
    r = _run("swfs_demo_run", o, _lib.swfs_demo_run_result, None, provenance, progress)
    try:
        rec = []
        for k in range(r.nlevels):
            d = {n: getattr(r.levels[k], n) for n in _lib.RECOVERY_FIELDS}
            d["seconds"] = r.level_seconds[k]
            rec.append(d)
        loop = []
        if r.loop:
            lr = r.loop.contents
            for k in range(lr.nrows):
                it = lr.rows[k]
                d = {n: getattr(it, n) for n in _lib.LOOP_ITER_FIELDS}
                d["fit_rms"], d["unfit_rms"] = it.fit.fit_rms, it.fit.unfit_rms
                d["seconds"] = it.seconds
                loop.append(d)
        res = {"recovery": rec, "loop": loop, "ncp_rms_ptt": r.ncp_rms_ptt, "sim_seconds": r.sim_seconds,
               "seconds": r.seconds, "html": r.html.decode()}
        res["sim"] = SimResult(r.sim)
        r.sim = None  # the SimResult owns it now
    finally:
        lib.swfs_demo_run_result_free(ctypes.byref(r))
    return res


def report(run_dir, out_dir=None, title=None, pixel=None, percentiles=None, log_decades=None):
    """`specklewfs report`: the figures of a run folder (its science, speckles, halo and
    pupil products) or of a demo folder, as PNGs and an index.html in out_dir (None:
    RUN_DIR/report). title: the page's; pixel (i, j): the pixel of pixel.png (None: chosen
    from the data); percentiles (lo, hi) [%] of the colour ranges (1, 99.5); log_decades (4).
    Returns html (the page), figures [(file, width, height)], ranges {name: (lo, hi, log)} in
    displayed units, notes (figures skipped and why), the run's key numbers (frames,
    valid_fraction, median_snr, wfe_rms, wfe_pv, strehl, ncp_rms, err_rms [m], tau0_median
    [s]; NaN where the products lack them), pixel, and for a demo folder demo=True with
    levels (one dict per noise level), recovery_rows, loop_rows. A folder with nothing to
    report raises Error naming what was looked for, and writes no page."""
    o = _lib.swfs_report_options()
    lib.swfs_report_options_default(ctypes.byref(o))
    if title is not None:
        o.title = enc(str(title))
    if pixel is not None:
        o.pixel_i, o.pixel_j = int(pixel[0]), int(pixel[1])
    if percentiles is not None:
        o.pct_lo, o.pct_hi = float(percentiles[0]), float(percentiles[1])
    if log_decades is not None:
        o.log_decades = float(log_decades)
    s = _lib.swfs_report_summary()
    check(lib.swfs_report_run(enc(run_dir), None if out_dir is None else enc(out_dir), ctypes.byref(o),
                              ctypes.byref(s)), "swfs_report_run")
    d = {n: getattr(s, n) for n in _lib.REPORT_KEY_FIELDS}
    d.update(html=s.html.decode(), demo=bool(s.demo), pixel=(s.pixel_i, s.pixel_j),
             figures=[(f.file.decode(), f.width, f.height) for f in s.figures[:s.nfigures]],
             ranges={r.name.decode(): (r.lo, r.hi, bool(r.log)) for r in s.ranges[:s.nranges]},
             notes=[n.value.decode() for n in s.notes[:s.nnotes]], recovery_rows=s.recovery_rows,
             loop_rows=s.loop_rows,
             levels=[{n: getattr(v, n) for n in _lib.REPORT_LEVEL_FIELDS + ["nfigures"]} for v in s.levels[:s.nlevels]])
    return d


def ncp_map(config=None, mask=None, **params):
    """The NCP map [m] the parameters describe, on the pupil grid, and its rms and pv."""
    from .core import aperture
    p = _params(config, params)
    if mask is None:
        mask = aperture(p.pupn, p.pupdx, p.teldiam, p.obscur, p.nspiders, p.spider_width)
    mask = as_array(mask, "mask", np.float64, shape=(p.pupn, p.pupn))
    out = np.zeros((p.pupn, p.pupn))
    rms, pv = ctypes.c_double(), ctypes.c_double()
    check(lib.swfs_sim_ncp_map(ctypes.byref(p), dptr(mask), dptr(out), ctypes.byref(rms), ctypes.byref(pv)),
          "swfs_sim_ncp_map")
    return out, rms.value, pv.value


def mode_variance(slopes, config=None, **params):
    """The loop's controlled modes as its residual slopes show them (timeseries.h
    swfs_ts_mode_variance, swfs_mode_knee): slopes (nframes, 2 nsub^2) in the full layout,
    or its used subapertures' only (the valid map valid=, else the simulator's), of the system
    described by config and params (`simulate mode=timeseries` keys: its pupil,
    DM and Shack-Hartmann). Returns (var, knee): the slopes' variance along each DM mode after
    piston, less what the lower modes explain [rad^2] (NaN for a mode the lower ones' patterns
    explain, e.g. beyond the rank of a valid map's interaction matrix), and the knee of that
    profile (the loop's modal filter, as `teach` reads it)."""
    params = dict(params)
    params.setdefault("mode", "timeseries")
    p = _checked_params("ts", config, params)
    s = as_array(slopes, "slopes", np.float64, ndim=2)
    out = ctypes.POINTER(ctypes.c_double)()
    n = ctypes.c_size_t()
    check(lib.swfs_ts_mode_variance(ctypes.byref(p), dptr(s), s.shape[0], s.shape[1], ctypes.byref(out), ctypes.byref(n)),
          "swfs_ts_mode_variance")
    var = _lib.take_buffer(ctypes.cast(out, ctypes.c_void_p).value, (n.value,), np.float64)
    return var, int(lib.swfs_mode_knee(dptr(var), var.shape[0]))


def mode_timecorr(slopes, lags, config=None, **params):
    """The slopes' time correlation along the upper half of the system's DM modes (timeseries.h
    swfs_ts_mode_timecorr; what `teach` matches its speed calibration loops to where `wind`
    tracks no layer): slopes as mode_variance() takes them, lags (each 1 to nframes - 1).
    Returns rho, one per lag: the coefficients' lag products over their lag-0 ones, summed
    over those modes, per frame pair."""
    params = dict(params)
    params.setdefault("mode", "timeseries")
    p = _checked_params("ts", config, params)
    s = as_array(slopes, "slopes", np.float64, ndim=2)
    lv = np.ascontiguousarray(np.asarray(lags, dtype=np.int64).ravel())
    rho = np.empty(lv.size)
    check(lib.swfs_ts_mode_timecorr(ctypes.byref(p), dptr(s), s.shape[0], s.shape[1],
                                    lv.ctypes.data_as(ctypes.POINTER(ctypes.c_long)), lv.size, dptr(rho)),
          "swfs_ts_mode_timecorr")
    return rho


def simulate_timeseries(directory, config=None, progress=None, provenance=(), **params):
    """The AO time series of the real-data path (timeseries.h), written to directory
    (created if needed): telemetry, raw camera cubes, calibrations, truth. params: the
    shared and time-series config keys (config/mmt-clio.conf). Returns the summary dict."""
    p = _checked_params("ts", config, params)
    os.makedirs(directory, exist_ok=True)
    s = _lib.swfs_ts_summary()
    prov, n = _lib.strings(provenance)
    with _Progress(progress) as prog:
        rc = lib.swfs_ts_run(ctypes.byref(p), enc(directory), prov, n, prog.fn, None, ctypes.byref(s))
    prog.check(rc, "swfs_ts_run")
    return {k: getattr(s, k) for k, _t in _lib.TS_SUMMARY_FIELDS}

"""Live at the telescope from Python (live.h, docs/live.md): `live`, the NCP estimate beside
a running AO system through ImageStreamIO shared-memory streams; `replay`, which feeds such
streams from recorded files (a timing table, its telemetry and the reduced science cube, or
a WFS milk log) at the WFS rate or faster; and `live_loop`, the NCP loop closed in
simulation through the streams. Each runs as its command does and returns what it prints,
as a dict; errors raise specklewfs.Error with the library's message.

The library releases Python while it runs (ctypes), so a replay in a thread and live in
another, or live in a thread beside one's own loop, run side by side:

    stop = specklewfs.StopFlag()
    t = threading.Thread(target=specklewfs.live, args=(["wfs"], "cam", "sci.fits", "HALO.fits"),
                         kwargs=dict(recon="recon.fits", actuators="act.fits", stop=stop))
    t.start(); ...; stop.set(); t.join()
"""
import ctypes
import math
import os
import select
import signal
import threading

from . import _lib
from ._lib import lib, check, enc, c_ptr, P
from .dm import _fit_options
from .pupil import _SOURCES
from .realdata import _opt
from .sim import _checked_params, _Progress, _struct_dict
from .streamfiles import _mean_loops, _stream_run_model, _stream_result

# on_update(ctx, stream, halo, pupil_result, final) of run.h
_UPDATE = ctypes.CFUNCTYPE(None, c_ptr, c_ptr, P(_lib.swfs_halo), P(_lib.swfs_pupil_result), ctypes.c_int)


def _run_stoppable(call, stop, raised):
    """call() (a library run that polls `stop`) with Ctrl-C as its stop, on this thread (so
    on_update runs where the caller is). Python runs its own SIGINT handler only between its
    bytecodes, never while the library waits on the streams; its C-level handler, though,
    writes the signal's number to the wakeup fd (signal.set_wakeup_fd), which a watcher thread
    reads: it sets the flag, the run ends cleanly at its next batch (the products of the frames
    so far written, as the command line's SIGINT does), and a KeyboardInterrupt is put in
    `raised` for the caller to raise after the run. For the call's length SIGINT's Python
    handler only records it too (a KeyboardInterrupt raised inside on_update would be lost in
    ctypes). Only on the main thread where SIGINT has Python's default handler; elsewhere
    call() runs as it is. Returns call()'s status."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        return call()

    def interrupted(*_):
        if not raised:
            raised.append(KeyboardInterrupt())
        stop.set()
    r, w = os.pipe()
    os.set_blocking(w, False)
    old_fd = signal.set_wakeup_fd(w)
    old_handler = signal.signal(signal.SIGINT, interrupted)
    done = threading.Event()

    def watch():
        while not done.is_set():
            if select.select([r], [], [], 0.1)[0] and signal.SIGINT in os.read(r, 512):
                interrupted()
    t = threading.Thread(target=watch, name="specklewfs-sigint", daemon=True)
    t.start()
    try:
        return call()
    finally:
        signal.signal(signal.SIGINT, old_handler)
        signal.set_wakeup_fd(old_fd)
        done.set()
        t.join()
        os.close(r)
        os.close(w)


class StopFlag:
    """A flag `live` polls (its streams' `stop`): set() ends the run cleanly at the next
    batch, with the products of the data so far written, as Ctrl-C ends the command."""

    def __init__(self):
        self._flag = ctypes.c_int(0)

    def set(self):
        self._flag.value = 1

    def clear(self):
        self._flag.value = 0

    def is_set(self):
        return bool(self._flag.value)


def _source(name):
    """The pupil product's source (pupil.h SWFS_SOURCE_*): 'lf' (or 'halo_lf': HALO_LF) or 'halo'."""
    if name not in _SOURCES:
        raise ValueError(f"pupil_source: expected 'lf' (HALO_LF) or 'halo', got {name!r}")
    return _SOURCES[name]


def _names(v, what):
    names = [v] if isinstance(v, (str, bytes, os.PathLike)) else list(v)
    if not names or len(names) > 8:
        raise ValueError(f"live: {what}: expected 1 to 8 stream names, got {len(names)}")
    return names


def live(wfs, camera, geom, out, recon=None, actuators=None, linear=None, shm_dir=None, batch=None,
         max_wait=None, exptime=None, timeout=None, idle_exit=None, poll=None, tiptilt="exposure", threads=2,
         read_noise=None, gain=None, g_smooth_lod=2.0, static="auto", static_out=None, every=0,
         every_seconds=0.0, max_frames=0, pupil_out=None, pupil_source="lf", checkpoint=None, pupil=None,
         valid=None, band="auto", mean_loops=None, dm_out=None, dm_file=None, dm_gain=0.5, dm_max_step=0.0,
         dm_max_rms=0.0, dm_scale=1.0, dm_settle=0.1, dm_keep=False, dm_final=False, dm_tiptilt=False,
         dm_fit=None, stop=None, on_update=None, provenance=()):
    """HALO.fits `out` from the WFS stream(s) `wfs` (a name, or up to 8 whose values are
    concatenated in that order) and the camera stream `camera` in shm_dir (None: the
    library's rule, $MILK_SHM_DIR or /milk/shm, else /dev/shm), as `specklewfs live`: the
    frames' time stamps map WFS frames onto camera exposures, batches of `batch` camera
    frames (None: 16) go through the stream run, the products are written every `every`
    camera frames / `every_seconds` and at the end. geom: a FITS file with the geometry
    keys, the camera frame size and the noise model (RDNOISE, GAIN), e.g. a reduced science
    cube. The model: recon with actuators (the Shack-Hartmann model), or linear= (a dict
    as speckles() takes). The run ends at the stop flag (StopFlag), after idle_exit seconds
    without a frame, at max_frames, or when a stream's writer goes for longer than timeout
    [s] (10). max_wait [s]: how long an exposure waits for its WFS frames; exptime [s]: the
    camera's exposure (None: its frame period); poll [s] (0.02). pupil_out: the pupil
    product at each update, from pupil_source 'lf' (HALO_LF) or 'halo'. mean_loops:
    folders of simulated loops (their shared miss of the residual mean added) or 'none'.
    DM offsets (dm_out: a stream name; dm_file: OFFSETS.fits too): -WFE/2 fitted onto the
    actuators (dm_fit: a dict of influence 'gauss'/'cubic', coupling, pitch, modes, reg)
    times dm_gain, each step at most dm_max_step [m], the total at most dm_max_rms [m],
    in stream units per metre dm_scale; exposures starting within dm_settle [s] of a write
    skipped. on_update(d): called at each update with camera_frames, wfs_frames, final,
    and valid_fraction, median_snr and wfe_rms [m] (None where not made); an exception in
    it ends the run with that exception. Returns what stream_files returns (camera_frames,
    wfs_frames, seconds (the processing), wfs_rate, ratio, noise, info (the pipeline's),
    st_lags, meanmiss_rms, meanmiss_heldout, ...) and sync (framesync's counts: received, dropped, restarts, used,
    skipped exposures, batches, the streams' periods), ring_overruns, reopens, lag_count,
    lag_median, lag_p99, lag_max [s], data_seconds, dm_updates, dm_step_rms, dm_total_rms
    [m] and dm_fixed."""
    o = _lib.swfs_live_options()
    lib.swfs_live_options_default(ctypes.byref(o))
    if (recon is None) == (linear is None) or (recon is not None and actuators is None):
        raise ValueError("live: give recon with actuators (the Shack-Hartmann model), or linear")
    names = _names(wfs, "wfs")
    warr = (ctypes.c_char_p * len(names))(*[enc(n) for n in names])
    o.src.wfs, o.src.nwfs, o.src.camera, o.src.dir = ctypes.cast(warr, P(ctypes.c_char_p)), len(names), \
        enc(camera), _opt(shm_dir)
    for key, v in (("batch", batch), ("max_wait", max_wait), ("exptime", exptime)):
        if v is not None:
            setattr(o.src.sync, key, int(v) if key == "batch" else float(v))
    for key, v in (("timeout", timeout), ("idle", idle_exit), ("poll", poll)):
        if v is not None:
            setattr(o.src, key, float(v))
    if stop is not None and not isinstance(stop, StopFlag):
        raise ValueError("live: stop takes a specklewfs.StopFlag")
    stop = stop or StopFlag()  # one of our own: an exception in on_update sets it
    o.src.stop = ctypes.addressof(stop._flag)
    r_ = o.run
    r_.science, r_.out = enc(geom), enc(out)
    _stream_run_model(r_, recon, actuators, linear, tiptilt, threads, read_noise, gain, g_smooth_lod, static, static_out,
                      pupil_out, checkpoint, every, every_seconds, max_frames, pupil, valid, band)
    r_.pupil_source = _source(pupil_source)
    _mean_loops(r_, mean_loops, ("none",), "live: mean_loops takes a list of folders or 'none' (teach needs recorded "
                "files: stream_files)")
    o.dm_out, o.dm_file = _opt(dm_out), _opt(dm_file)
    o.dm_gain, o.dm_max_step, o.dm_max_rms = float(dm_gain), float(dm_max_step), float(dm_max_rms)
    o.dm_scale, o.dm_settle = float(dm_scale), float(dm_settle)
    o.dm_keep, o.dm_final, o.dm_tiptilt = int(bool(dm_keep)), int(bool(dm_final)), int(bool(dm_tiptilt))
    fit = dict(influence="gauss", coupling=None, pitch=None, modes=0, reg=None)
    for key in dm_fit or {}:
        if key not in fit:
            raise ValueError(f"dm_fit: unknown key {key!r} (influence, coupling, pitch, modes, reg)")
    fit.update(dm_fit or {})
    o.dmfit = _fit_options(**fit)
    raised = []
    if on_update is not None:
        def hook(ctx, s, h, pr, final):
            if raised:
                return
            try:
                d = dict(camera_frames=lib.swfs_stream_camera_frames(s), wfs_frames=lib.swfs_stream_wfs_frames(s),
                         final=bool(final), valid_fraction=None, median_snr=None, wfe_rms=None)
                if h:
                    d.update(valid_fraction=h.contents.valid_fraction, median_snr=h.contents.median_snr)
                if pr:
                    d["wfe_rms"] = pr.contents.wfe_rms
                on_update(d)
            except BaseException as e:  # ends the run at its next batch
                raised.append(e)
                stop.set()
        cb = _UPDATE(hook)
        r_.on_update = ctypes.cast(cb, c_ptr).value
    prov, r_.nprov = _lib.strings(provenance)
    r_.prov = prov
    res = _lib.swfs_live_result()
    rc = _run_stoppable(lambda: lib.swfs_live_run(ctypes.byref(o), ctypes.byref(res)), stop, raised)
    if raised:
        raise raised[0]
    check(rc, "swfs_live_run")
    d = _stream_result(res.run, "live")
    d["sync"] = _struct_dict(res.src.sync)
    d.update({k: getattr(res.src, k) for k in ("ring_overruns", "reopens", "lag_count", "lag_median", "lag_p99",
                                                "lag_max")})
    d["data_seconds"] = res.src.seconds
    d.update({k: getattr(res, k) for k in ("dm_updates", "dm_step_rms", "dm_total_rms", "dm_fixed")})
    return d


_TYPES = {None: 0, "float32": 9, "float64": 10, "int16": 4, "uint16": 3}  # shm.h SWFS_SHM_*


def replay(science, timing=None, slopes=None, wfs_log=None, shm_dir=None, wfs_name="swfs_wfs",
           camera_name="swfs_camera", wfs_rate=0.0, speed=1.0, drop_wfs=0.0, drop_camera=0.0, jitter=0.0, seed=1,
           depth=0, wfs_type=None, camera_type=None, wait_reader=0.0, restart_after=0, drop_log=None,
           remove=False, progress=None):
    """Publishes recorded data into shared-memory streams as `specklewfs replay`: the
    telemetry a timing table (`sync`'s) pairs with the reduced science cube `science`
    (slopes: the telemetry's folder or one file; None: the table's folder), at wfs_rate
    [Hz] (0: the telemetry's WFSRATE) times speed, with time stamps from the table; or a
    WFS milk log (wfs_log) with its own stamps and lost frames, the camera frames at the
    cube's STAMPS. drop_wfs / drop_camera: the probability of losing each frame; jitter
    [s] rms on the stamps and publication times; seed; depth: slices of a rolling buffer
    (0: 2-D streams); wfs_type / camera_type: 'float32', 'float64', 'int16', 'uint16'
    (None: as the files); wait_reader [s]: wait that long for a reader on every stream
    before publishing; restart_after: re-create the streams after that many WFS frames;
    drop_log: a text file of the frames lost; remove: remove the streams at the end.
    progress(stage, done, total): every 1024 frames published; an exception there, or
    Ctrl-C on the main thread, stops the replay and comes out of the call. Returns wfs_frames, camera_frames, wfs_dropped, camera_dropped, restarts, wfs_rate,
    ratio, seconds and late_max [s]."""
    o = _lib.swfs_replay_options()
    lib.swfs_replay_options_default(ctypes.byref(o))
    if (timing is None) == (wfs_log is None):
        raise ValueError("replay: give timing (a timing table) or wfs_log (a WFS milk log), one of them")
    o.timing, o.science, o.slopes, o.wfs_log = _opt(timing), enc(science), _opt(slopes), _opt(wfs_log)
    o.dir, o.wfs_name, o.camera_name = _opt(shm_dir), enc(wfs_name), enc(camera_name)
    o.wfs_rate, o.speed, o.drop_wfs, o.drop_camera = float(wfs_rate), float(speed), float(drop_wfs), \
        float(drop_camera)
    o.jitter, o.seed, o.depth = float(jitter), int(seed), int(depth)
    o.wfs_type = _lib.choice(_TYPES, wfs_type, "replay: wfs_type")
    o.camera_type = _lib.choice(_TYPES, camera_type, "replay: camera_type")
    o.wait_reader, o.restart_after, o.drop_log, o.remove = float(wait_reader), int(restart_after), \
        _opt(drop_log), int(bool(remove))
    r = _lib.swfs_replay_result()
    with _Progress(progress) as prog:
        o.progress = prog.fn
        rc = lib.swfs_replay_run(ctypes.byref(o), ctypes.byref(r))
    prog.check(rc, "swfs_replay_run")
    return _struct_dict(r)


def live_loop(directory, iterations=3, speed=2.0, batch=16, modes=0, influence="cubic", coupling=None, gain=0.5,
              max_step=0.0, max_rms=0.0, pupil_source="halo", tiptilt=False, config=None, stop=None, progress=None,
              provenance=(), **params):
    """The NCP loop closed in simulation through shared-memory streams (`specklewfs
    liveloop`), into directory (created if needed): iteration k simulates the AO time
    series (params: the time-series config keys, as simulate_timeseries takes them; seed
    + k) with the NCP plus twice the DM offsets read from the DM stream, reduces and syncs
    it, replays it into streams at `speed` times real time, and live (batches of `batch`
    camera frames) writes its correction (the pupil from pupil_source 'halo' or 'lf'
    fitted onto the actuators with `influence` 'cubic'/'gauss', `coupling`, `modes` Zernike
    modes (0: all), times gain, each step at most max_step [m], the total at most max_rms
    [m], tip-tilt corrected with tiptilt) onto the DM stream. stop: a StopFlag; progress(stage,
    done, total). Returns states (one per iteration and one after the last: residual_rms
    [m] of the NCP plus twice the DM, piston, tip and tilt removed; estimate_err [m], live's
    WFE against it, None after the last; dm_rms [m]; frames_used; lag_median, lag_p99 [s])
    and seconds."""
    o = _lib.swfs_live_loop_options()
    lib.swfs_live_loop_options_default(ctypes.byref(o))
    o.sim = _checked_params("ts", config, params)
    os.makedirs(directory, exist_ok=True)
    o.dir, o.iterations, o.speed, o.batch = enc(directory), int(iterations), float(speed), int(batch)
    o.dmfit = _fit_options(influence, coupling, None, modes, None)
    o.gain, o.max_step, o.max_rms = float(gain), float(max_step), float(max_rms)
    o.pupil_source, o.tiptilt = _source(pupil_source), int(bool(tiptilt))
    if stop is not None and not isinstance(stop, StopFlag):
        raise ValueError("live_loop: stop takes a specklewfs.StopFlag")
    o.stop = ctypes.addressof(stop._flag) if stop is not None else None
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = _lib.swfs_live_loop_result()
    with _Progress(progress) as prog:
        o.progress = prog.fn
        rc = lib.swfs_live_loop_run(ctypes.byref(o), ctypes.byref(r))
    prog.check(rc, "swfs_live_loop_run")
    states = []
    for k in range(r.nstates):
        st = _struct_dict(r.s[k])
        if not math.isfinite(st["estimate_err"]):
            st.update(estimate_err=None, frames_used=None, lag_median=None, lag_p99=None)
        states.append(st)
    return dict(states=states, seconds=r.seconds)

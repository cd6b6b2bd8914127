"""The streaming path on files, as the command line runs it (run.h): `stream` over a timing
table or over milk/cacao logs (time stamps instead of a handshake log), and `sync --wfs-log`,
the clock file that puts the camera's stamps on the WFS clock. Each writes the same products
as its command and returns what it prints, as a dict; errors raise specklewfs.Error with the
library's message and leave no output looking complete."""
import ctypes
import math
import os

from . import _lib
from ._lib import lib, check, enc
from .core import geom_arg
from .realdata import _linear, _mean_teach_dict, _opt, _paths
from .sim import _Progress, _struct_dict
from .stream import _TT, _band

_STATIC = {"auto": 0, "none": 1}


def _stream_run_model(o, recon, actuators, linear, tiptilt, threads, read_noise, gain, g_smooth_lod, static,
                      static_out, pupil_out, checkpoint, every, every_seconds, max_frames, pupil, valid, band):
    """swfs_stream_run_options o's model, noise, static halo, products and updates, as
    stream_files and live take them"""
    o.recon, o.actuators = _opt(recon), _opt(actuators)
    _linear(o.lin, linear)
    o.tiptilt, o.threads = _lib.choice(_TT, tiptilt, "stream_files: tiptilt"), int(threads)
    o.read_noise = math.nan if read_noise is None else float(read_noise)
    o.gain = math.nan if gain is None else float(gain)
    o.g_smooth_lod = float(g_smooth_lod)
    if isinstance(static, str) and static in _STATIC:
        o.stream.static_mode = _lib.choice(_STATIC, static, "stream_files: static")
    else:
        o.stream.static_mode, o.static_file = 2, enc(static)
    o.static_out, o.pupil_out, o.checkpoint = _opt(static_out), _opt(pupil_out), _opt(checkpoint)
    o.stream.every, o.stream.every_seconds, o.stream.max_frames = int(every), float(every_seconds), int(max_frames)
    o.mask, o.valid, o.band = _opt(pupil), _opt(valid), _band(band)


def _mean_loops(o, mean_loops, words, refusal):
    """swfs_stream_run_options o's mean loops: a list of folders, or one of words ('teach':
    simulate them, 'none': neither); any other single name refused with `refusal`"""
    if isinstance(mean_loops, str) and mean_loops in words:
        o.mean_teach, mean_loops = int(mean_loops == "teach"), None
    elif isinstance(mean_loops, (str, bytes, os.PathLike)):
        raise ValueError(refusal)
    o.mean_loops, o.nmean_loops = _lib.strings([os.fspath(m) for m in (mean_loops or ())])


def sync_wfs_log(science, wfs_log, out, exptime=0.0, offset=None, drift_max=None, linear=None, provenance=()):
    """The clock file (`specklewfs sync --wfs-log`): the camera's clock against the WFS's,
    t_wfs = epoch + (t_cam - epoch)(1 + drift) + offset, fitted by the pooled correlation
    of the reduced science cube's TRACK (its frames' STAMPS: `reduce` of the camera's milk
    logs) with the exposure-mean slopes of wfs_log (a milk log folder or its files;
    Shack-Hartmann slopes, x then y, or with linear= the linear model's telemetry).
    exptime [s]: 0 takes STAMPS' EXPTIME, else the camera's frame period; offset: (min,
    max) [s] searched (default -0.01, 0.01); drift_max (5e-4). Returns epoch [ns], offset,
    drift and their errors, the pairing (swap, sign_x, sign_y, corr_x, corr_y), resid
    [pixels], exptime, the fitted periods and stamp jitters [s], the frames used, and the
    counter jumps of both logs (wfs_dropped, cam_dropped)."""
    o = _lib.swfs_clock_run_options()
    lib.swfs_clock_run_options_default(ctypes.byref(o))
    logs = _lib.path_list(wfs_log)
    arr, n = _paths(logs)
    o.science, o.wfs, o.nwfs, o.out = enc(science), arr, n, enc(out)
    o.exptime = float(exptime)
    if offset is not None:
        o.params.offset_min, o.params.offset_max = float(offset[0]), float(offset[1])
    if drift_max is not None:
        o.params.drift_max = float(drift_max)
    _linear(o.lin, linear)
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = _lib.swfs_clock_run_result()
    check(lib.swfs_clock_run(ctypes.byref(o), ctypes.byref(r)), "swfs_clock_run")
    c = r.clock
    d = {k: getattr(c, k) for k in ("epoch", "offset", "drift", "offset_err", "drift_err", "resid", "exptime",
                                     "wfs_period", "cam_period", "wfs_jitter", "cam_jitter", "nused", "ncam",
                                     "nsegments")}
    d.update({k: getattr(c.fit, k) for k in ("swap", "sign_x", "sign_y", "corr_x", "corr_y")})
    d.update(wfs_dropped=r.wfs_dropped, cam_dropped=r.cam_dropped, wfs_frames=r.wfs_frames, wfs_files=r.wfs_files)
    return d


def stream_files(science, out, timing=None, wfs_log=None, clock=None, exptime=0.0, recon=None, actuators=None,
                 linear=None, slopes=None, batch=128, tiptilt="exposure", threads=2, read_noise=None, gain=None,
                 g_smooth_lod=2.0, static="auto", static_out=None, every=0, every_seconds=0.0, max_frames=0,
                 pupil_out=None, checkpoint=None, pupil=None, valid=None, band="auto", mean_loops=None,
                 mean_teach_loops=None, mean_teach_max_loops=None, teach_work=None, teach_again=False, geom=None,
                 provenance=(), progress=None):
    """HALO.fits `out` updated as the data stream through (`specklewfs stream`): the science
    cube's frames with the telemetry that timing (`sync`'s table) pairs them with, or with
    wfs_log (milk logs: one folder or file, or several whose values are concatenated in the
    order given) by the frames' time stamps, the science cube's STAMPS put on the WFS clock
    by `clock` (sync_wfs_log's file; None: the camera on the WFS clock) with exptime [s]
    (0: STAMPS' EXPTIME, else the frame period). The model: recon (a reconstructor file,
    e.g. speckles(..., write_recon=) or teach's map; a space-time one stacks the frames at
    its lags) with actuators, or linear= (a dict as speckles() takes). batch: camera frames
    per batch; tiptilt 'exposure', 'frame' or 'keep'; read_noise [counts], gain [e-/count]
    (None: the science header's); static: 'auto', 'none' or a complex image file;
    static_out: write the static halo used; every (camera frames) / every_seconds: update the
    products that often (0: at the end); max_frames (0: all); pupil_out: also the pupil field
    at each update; checkpoint: the accumulators at each update; pupil: the pupil mask file;
    valid: the subaperture map; band: 'auto', 'none' or a radius [lambda/D]; mean_loops:
    folders of simulated loops (their shared miss of the residual mean added), 'teach'
    (simulated by the run, for a timing table) or 'none'. Returns camera_frames, wfs_frames,
    seconds, wfs_rate, static_scale, ratio, noise (read_noise, gain), info (the pipeline's),
    stamped and, for milk logs, stamps (framesync's counts in `sync`, the logs' counter jumps
    wfs_dropped_log / camera_dropped_log, exptime), st_lags (a space-time map's) and its file
    edges (st_edges_joined, _clamped, _unreadable, _why), meanmiss_rms, meanmiss_heldout and
    mean_teach (as speckles()). progress(stage, done, total): after every batch, the camera
    frames taken so far (total 0 for milk logs); an exception there, or Ctrl-C, stops the run,
    removes the updates it had written and comes out of the call."""
    o = _lib.swfs_stream_run_options()
    lib.swfs_stream_run_options_default(ctypes.byref(o))
    logs = _lib.path_list(wfs_log)
    if (timing is None) == (not logs):
        raise ValueError("stream_files: give timing (a timing table) or wfs_log (milk logs), one of them")
    if clock is not None and not logs:
        raise ValueError("stream_files: clock goes with wfs_log")
    if (recon is None) == (linear is None) or (recon is not None and actuators is None):
        raise ValueError("stream_files: give recon with actuators (the Shack-Hartmann model), or linear")
    o.timing, o.science, o.out = _opt(timing), enc(science), enc(out)
    larr, nl = _paths(logs)
    o.wfs_logs, o.nwfs_logs = (larr, nl) if logs else (None, 0)
    o.clock, o.exptime = _opt(clock), float(exptime)
    o.slopes, o.batch = _opt(slopes), int(batch)
    _stream_run_model(o, recon, actuators, linear, tiptilt, threads, read_noise, gain, g_smooth_lod, static, static_out,
                      pupil_out, checkpoint, every, every_seconds, max_frames, pupil, valid, band)
    _mean_loops(o, mean_loops, ("teach", "none"), "stream_files: mean_loops takes a list of folders, 'teach' or 'none'")
    if mean_teach_loops is not None:
        o.mean_teach_loops = int(mean_teach_loops)
    if mean_teach_max_loops is not None:
        o.mean_teach_max_loops = int(mean_teach_max_loops)
    o.teach_work, o.teach_again = _opt(teach_work), int(bool(teach_again))
    if geom is not None:
        o.geom = geom_arg(geom)
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    r = _lib.swfs_stream_run_result()
    with _Progress(progress) as prog:
        o.progress = prog.fn
        rc = lib.swfs_stream_run_files(ctypes.byref(o), ctypes.byref(r))
    prog.check(rc, "swfs_stream_run_files")
    return _stream_result(r, "stream_files")


def _stream_result(r, what):
    """swfs_stream_run_result r as the dict stream_files and live return"""
    d = {k: getattr(r, k) for k in ("camera_frames", "wfs_frames", "seconds", "wfs_rate", "static_scale", "ratio",
                                     "st_edges_joined", "st_edges_clamped", "st_edges_unreadable", "meanmiss_rms",
                                     "meanmiss_heldout")}
    d["noise"] = dict(read_noise=r.noise.read_noise, gain=r.noise.gain)
    d["info"] = _struct_dict(r.info)
    d["stamped"] = bool(r.stamped)
    d["stamps"] = None if not r.stamped else dict(_struct_dict(r.stamps.sync), wfs_dropped_log=r.stamps.wfs_dropped_log,
                                                  camera_dropped_log=r.stamps.camera_dropped_log,
                                                  exptime=r.stamps.exptime)
    d["st_lags"] = tuple(r.st_lags[k] for k in range(r.info.nlags))
    d["st_edges_why"] = r.st_edges_why.decode(errors="replace")
    d["mean_teach"] = _mean_teach_dict(r.mean_teach, what)
    return d

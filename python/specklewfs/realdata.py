"""The real-data path on files, as the command line runs it (run.h): reduce -> sync ->
speckles -> estimate, then pupil_estimate(Halo.read(...)). Each step writes the same
products as its command (docs/telemetry.md) and returns what the command prints, as a dict
(estimate_files: the Halo). Errors raise specklewfs.Error with the library's message; a step
that fails leaves no output file."""
import ctypes
import math
import os
import warnings

import numpy as np

from . import _lib
from ._lib import lib, check, as_array, dptr, enc
from .estimate import Halo
from .sim import _cfg_value, _run, _struct_dict
from .stream import _RECON, _TT, _band


def _paths(paths):
    """(char **, n) of file names; the array keeps them alive."""
    names = [enc(p) for p in paths]
    return (ctypes.c_char_p * max(1, len(names)))(*names), len(names)


def _opt(path):
    return enc(path) if path is not None else None


_LINEAR_KEYS = {"basis", "control", "imat", "scale", "dm_pitch", "dm_offset", "dm_rot", "dm_flip"}


def _linear(lf, linear):
    """The linear model (`--basis` and its options; run.h swfs_linear_files) from a dict:
    basis (required), control or imat, scale (`--coef-scale`, 1), and the DM grid's
    registration dm_pitch [m], dm_offset (x, y) [m], dm_rot [deg], dm_flip (bool)."""
    if linear is None:
        return
    unknown = set(linear) - _LINEAR_KEYS
    if unknown or "basis" not in linear:
        raise ValueError(f"linear: expected basis and any of {sorted(_LINEAR_KEYS - {'basis'})}, got {sorted(linear)}")
    lib.swfs_linear_files_default(ctypes.byref(lf))
    lf.basis, lf.control, lf.imat = _opt(linear["basis"]), _opt(linear.get("control")), _opt(linear.get("imat"))
    lf.scale = float(linear.get("scale", 1.0))
    if linear.get("dm_pitch"):
        lf.reg.pitch = float(linear["dm_pitch"])
        lf.reg.x0, lf.reg.y0 = (float(v) for v in linear.get("dm_offset", (0.0, 0.0)))
        lf.reg.rot = math.radians(float(linear.get("dm_rot", 0.0)))
        lf.reg.flip_x = int(bool(linear.get("dm_flip", False)))


def reduce(raw, out, dark=None, flat=None, badpix=None, geom=None, noise_region=False, progress=None,
           provenance=()):
    """Raw camera cubes (a path or a list, concatenated in that order) -> the reduced science
    cube `out` (`specklewfs reduce`): dark, flat, bad pixels, registration, the noise
    variance, TRACK. geom: a Geom/dict whose keywords fill or replace the raw header's.
    Returns nframes, nbad, noise_var (written; 0 when the measured noise_var_measured came
    out below 0), noise_fac, missing (geometry keywords still absent), stamped, dropped,
    exptime."""
    raw = _lib.path_list(raw)
    o = _lib.swfs_reduce_run_options()
    lib.swfs_reduce_run_options_default(ctypes.byref(o))
    arr, n = _paths(raw)
    o.raw, o.nraw = arr, n
    o.dark, o.flat, o.badpix, o.out = _opt(dark), _opt(flat), _opt(badpix), enc(out)
    o.noise_region = 1 if noise_region else 0
    return _struct_dict(_run("swfs_reduce_run", o, _lib.swfs_reduce_run_result, geom, provenance, progress))


def sync(science, handshake, out, ratio=None, lag=None, ratio_step=None, lag_step=None, linear=None):
    """The timing table (`specklewfs sync`): the reduced science cube's TRACK against the
    telemetry files the handshake log names. ratio: (min, max) WFS frames per camera frame,
    None: from the camera's EXPTIME x the telemetry's WFSRATE (an exposure lasts at most its
    frame period; less EXPTIME's resolution and 5 coarse steps), or 0.1 without them, to the
    handshake log's bound (a cube ends before the next cube of its file starts); lag: (min, max) WFS frames, None: -3 .. 12. A fit that is not significant over
    its search raises Error and writes nothing; a best lag at the window's edge moves the
    window (lag_min, lag_max: the last one; lag_moves). Returns ratio, ratio_err, lag, the pairing
    (swap, sign_x, sign_y, corr_x, corr_y), z and z_need [sigma], neff, the exposures (nexp,
    nexp_ok), rows usable (nok), ncontinued and the ratios searched (ratio_min, ratio_max,
    ratio_bound, ratio_auto; exptime_ratio, exptime_used, and exptime_widened: the best ratio
    lay at EXPTIME's bound and the search was made again from 0.1); refits: times the fit was made again over cubes joined across
    contiguous telemetry files (ratio_first, lag_first: the fit over each cube's own file);
    nmissing, nexp_missing: cubes (their exposures) left out because the telemetry file the
    log names cannot be read (missing, truncated, another shape), missing_reason the first
    such file's message. No readable telemetry file at all raises Error. linear: the telemetry
    is the linear model's (a dict as speckles() takes): the tip-tilt correlated with the star's
    track is then the Z-tilt of its wavefront."""
    o = _lib.swfs_sync_run_options()
    lib.swfs_sync_run_options_default(ctypes.byref(o))
    o.science, o.handshake, o.out = enc(science), enc(handshake), enc(out)
    _linear(o.lin, linear)
    if ratio is not None:
        if not float(ratio[0]) > 0:
            raise ValueError(f"ratio: the least ratio must be > 0, got {ratio[0]} (None: from the camera's EXPTIME)")
        o.params.ratio_min, o.params.ratio_max = float(ratio[0]), float(ratio[1])
    if lag is not None:
        o.params.lag_min, o.params.lag_max = float(lag[0]), float(lag[1])
    if ratio_step is not None:
        o.params.ratio_step = float(ratio_step)
    if lag_step is not None:
        o.params.lag_step = float(lag_step)
    r = _lib.swfs_sync_run_result()
    try:
        check(lib.swfs_sync_run(ctypes.byref(o), ctypes.byref(r)), "swfs_sync_run")
        f = r.t.fit
        d = {k: getattr(f, k) for k in ("ratio", "ratio_err", "lag", "swap", "sign_x", "sign_y", "corr_x", "corr_y",
                                        "neff", "z", "z_need", "lag_min", "lag_max", "lag_moves")}
        d.update({k: getattr(r, k) for k, _t in _lib.SYNC_RUN_FIELDS})
        d["ratio_auto"] = bool(d["ratio_auto"])
        d["exptime_used"], d["exptime_widened"] = bool(d["exptime_used"]), bool(d["exptime_widened"])
        d["missing_reason"] = d["missing_reason"].decode(errors="replace")
        return d
    finally:
        lib.swfs_free(r.t.cubes)


def meanmiss_metric(funcs, pupil):
    """learn's meanmiss_metric from files, as `learn --mean-miss-over FUNCS,PUPIL` makes it
    (run.h swfs_meanmiss_metric): funcs a FITS cube of the truth's outputs' functions on the
    pupil grid (a DM's influence.fits, one plane per output), pupil the pupil mask's file;
    returns M (nout, nout), the mask-weighted mean over the pupil of f_a f_b, each function
    with piston, tip and tilt removed: m^T M m is the mean square of the wavefront a miss m
    makes there."""
    M = ctypes.POINTER(ctypes.c_double)()
    n = ctypes.c_size_t()
    check(lib.swfs_meanmiss_metric(enc(os.fspath(funcs)), 0, None, enc(os.fspath(pupil)), ctypes.byref(M),
                                   ctypes.byref(n)), "swfs_meanmiss_metric")
    return _lib.take_buffer(ctypes.cast(M, ctypes.c_void_p).value, (n.value, n.value), np.float64)


def learn(dirs, out, ridge=None, heldout=True, modal=False, provenance=(), lags=None, perframe_out=None, curve=False,
          curve_radius=None, threads=0, mean_miss=True, prior=None, mean_miss_heldout=False, meanmiss_metric=None):
    """A reconstructor learned from simulated closed loops (`specklewfs learn`): the
    least-squares map from a frame's slopes to the true residual on the actuators over the
    folders `dirs` (simulate_timeseries(..., export_truth=1): slopes_NNN.fits beside
    truewf_NNN.fits, one geometry), written to `out` for speckles(..., recon=out); with
    modal=True the truth files hold coefficients on a basis without piston (any AO system)
    and `out` is a control matrix for the linear model (Pipeline.linear(control=...),
    `speckles --basis B --control out`). Returns
    nframes, nfiles, nslopes, nslopes_seen, nact, truth_rms and misfit_rms [m], and with more
    than one folder (heldout=True) the leave-one-folder-out check: nheldout,
    heldout_misfit_rms, heldout_truth_rms [m], heldout_ratio (each folder's misfit / truth,
    NaN where not checked; >= 1: a condition the others do not cover), heldout_worst and
    heldout_worst_set (the worst folder's ratio and index), heldout_outputs (the outputs it was
    measured on: all, or those curve_radius keeps) and heldout_scaled_rms (the misfit with each
    check's map scaled by the one factor that fits best: what the estimator's g leaves). lags (WFS frames, one of them 0,
    e.g. (0, -25, 25)): a space-time map from the slopes of frames t + lag, written as a cube
    of one map per lag that speckles(..., recon=out) applies the same way (`learn --lags`);
    it pays only when the folders hold the observation's own wind and profile. With lags it
    also returns nwind, wind_v (the training loops' mean wind [subapertures per WFS frame])
    and wind_spread, and wind_layers: the loops' frozen-flow layers grouped over the folders
    (dicts of v, nsets, spread); speckles() then returns st_mismatch, the largest distance of
    an observed layer from the nearest taught one at the largest lag [subapertures]
    (st_found, st_train_v, st_obs_v that pair; st_obs_nlayers, st_train_nlayers), and the
    slopes' correlation at the lags: corr / corr_spread here (the loops'), st_corr_train,
    st_corr_spread, st_corr_obs and st_corr_excess (> 0: beyond three spreads) there, and
    st_warn_wind, st_warn_corr: whether each check warns (swfs_spacetime_warns).
    perframe_out (with lags): also the per-frame map of the same frames, the lag-0 block of the
    same sums solved alone, for runs that take one frame's slopes (live); its fit is returned
    as perframe (nframes, nslopes_seen, truth_rms, misfit_rms). curve=True (at least 4
    folders): the map's learning curve (`learn --curve`), returned as curve: n (the training
    frames of its two points, about N/2 and 3N/4), misfit_rms (the held-out misfit there [m]),
    a and b (misfit^2 = a + b / n), excess (b / (a N): the map of all N frames over one of
    unlimited frames) and frames (the frames for an excess of 0.1; 0: the misfit does not
    fall; None: no bound), nframes, outputs (those it was measured on); None where it could not
    be measured. curve_radius=(r0, r1) [m]: both checks, the curve and the held-out one, over
    the outputs at those radii only, the pupil's annulus (their positions: the truth's points,
    OUTXY, else the first folder's actuators.fits; not with modal). threads: with curve, the folders' sums and the curve's checks that many at
    once (0: the CPUs; the same map at any count). mean_miss (with more than one folder, as
    `learn` without --no-mean-miss): the map's miss of the residual's time mean per folder,
    checked held out (meanmiss_heldout < 1: the others' mean predicts each one's, the sensor's
    own miss) and then written as out's extension MEANMISS, which speckles() adds to RESMEAN
    (its meanmiss_rms); returned as meanmiss (heldout, rms, set_rms, kept), None when not
    checked. prior (a map file of the same slopes and outputs, e.g. what speckles(...,
    write_recon=) wrote for the linear model's MAP; `learn --prior`): the map shrinks toward
    it, as far from it as the ridge lets the frames move it (give a ridge of weight, e.g. 0.1;
    not with lags). mean_miss_heldout=True (`learn --mean-miss-heldout`): each folder's miss
    taken with the map of the other folders, not the map of all (which fits few folders' means
    in-sample). meanmiss_metric: None, or an (nact, nact) symmetric positive semi-definite
    matrix M: the check weighs a miss m as m^T M m instead of its sum of squares over the
    outputs (speckles' loops map gives the mean square over the pupil of the wavefront the
    outputs make, piston, tip and tilt removed, which meanmiss_metric(funcs, pupil) and `learn
    --mean-miss-over FUNCS,PUPIL` make from files; set_rms is then sqrt(m^T M m) over the
    folders)."""
    dirs = _lib.path_list(dirs)
    o = _lib.swfs_learn_run_options()
    lib.swfs_learn_run_options_default(ctypes.byref(o))
    arr, n = _paths(dirs)
    o.dirs, o.ndirs, o.out = arr, n, enc(out)
    if ridge is not None:
        o.ridge = float(ridge)
    o.no_heldout = 0 if heldout else 1
    o.modal = 1 if modal else 0
    ratio = np.full(n, np.nan)
    o.heldout_ratio = dptr(ratio)
    prov, o.nprov = _lib.strings(provenance)
    o.prov = prov
    if lags is not None:
        lagv = (ctypes.c_long * max(len(lags), 1))(*[int(v) for v in lags])
        o.lags, o.nlags = ctypes.cast(lagv, ctypes.POINTER(ctypes.c_long)), len(lags)
    if perframe_out is not None:
        o.perframe_out = enc(perframe_out)
    o.curve = int(bool(curve))
    o.threads = int(threads)
    o.mean_miss = int(bool(mean_miss))
    o.mean_miss_heldout = int(bool(mean_miss_heldout))
    if prior is not None:
        o.prior = enc(prior)
    metric = None
    if meanmiss_metric is not None:
        metric = as_array(meanmiss_metric, "meanmiss_metric", np.float64, ndim=(2,))
        if metric.shape[0] != metric.shape[1]:
            raise ValueError(f"meanmiss_metric: expected a square (nact, nact) matrix, got shape {metric.shape}")
        o.meanmiss_metric, o.meanmiss_metric_n = dptr(metric), metric.shape[0]
    if curve_radius is not None:
        o.curve_radius[0], o.curve_radius[1] = float(curve_radius[0]), float(curve_radius[1])
    r = _lib.swfs_learn_run_result()
    check(lib.swfs_learn_run(ctypes.byref(o), ctypes.byref(r)), "swfs_learn_run")
    d = _struct_dict(r.info)
    d.update(nfiles=r.nfiles, nslopes=r.nslopes, nact=r.nact, nheldout=r.nheldout,
             heldout_misfit_rms=r.heldout_misfit_rms, heldout_truth_rms=r.heldout_truth_rms,
             heldout_worst=r.heldout_worst, heldout_worst_set=r.heldout_worst_set, heldout_ratio=ratio,
             heldout_outputs=r.heldout_outputs, heldout_scaled_rms=r.heldout_scaled_rms,
             nwind=r.nwind, wind_v=(r.wind_vx, r.wind_vy), wind_spread=r.wind_spread,
             wind_layers=[dict(v=(r.wlayer_vx[k], r.wlayer_vy[k]), nsets=r.wlayer_n[k], spread=r.wlayer_spread[k])
                          for k in range(r.nwlayers)])
    if lags is not None:
        d.update(corr=np.array(r.corr[:len(lags)]), corr_spread=np.array(r.corr_spread[:len(lags)]))
    if perframe_out is not None and lags is not None and len(lags) > 1:
        d.update(perframe=_struct_dict(r.perframe_info))
    if curve:
        d.update(curve=_curve_dict(r))
    d.update(meanmiss=None if math.isnan(r.meanmiss_heldout) else
             dict(heldout=r.meanmiss_heldout, rms=r.meanmiss_rms, set_rms=r.meanmiss_set_rms, kept=bool(r.meanmiss_kept)))
    return d


def _curve_dict(r):
    """A learn result's learning curve (run.h swfs_learn_run_result.curve_*), None if not measured."""
    if not r.curve_n[0]:
        return None
    return dict(n=(r.curve_n[0], r.curve_n[1]), misfit_rms=(math.sqrt(r.curve_m2[0]), math.sqrt(r.curve_m2[1])),
                a=r.curve_a, b=r.curve_b, excess=r.curve_excess, fall_se=r.curve_fall_se,
                frames=None if r.curve_frames == ctypes.c_size_t(-1).value else r.curve_frames,
                nframes=r.info.nframes, outputs=r.curve_outputs)


def _edges(tail, head):
    t = np.ascontiguousarray(tail, dtype=np.float64)
    h = np.ascontiguousarray(head, dtype=np.float64)
    if t.ndim != 2 or h.ndim != 2 or t.shape[1] != h.shape[1] or not t.shape[0] or not h.shape[0]:
        raise ValueError(f"tail {t.shape} and head {h.shape}: expected (nframes, nvals) arrays with the same nvals")
    return t, h


def boundary_gap(tail, head, lost):
    """Whether the telemetry across a boundary shows `lost` WFS frames missing between `tail`
    and `head` (lost < 0: -lost frames repeated), the count `sync` takes from the camera where
    boundary_check says not contiguous (sync.h swfs_sync_boundary_gap). Repeated: head starts
    with tail's last -lost frames. Lost: the step across lies among the steps over lost + 1
    frames beside it, and those are all below every step over the longest lags of each side
    (separable: the data tell a few lost frames from a long gap). Returns lost, consistent,
    separable, q, qk_min, qk_max, qfar_min."""
    t, h = _edges(tail, head)
    if int(lost) == 0:
        raise ValueError("lost: a number of frames lost (> 0) or repeated (< 0), not 0")
    g = _lib.swfs_sync_gap()
    check(lib.swfs_sync_boundary_gap(dptr(t), t.shape[0], dptr(h), h.shape[0], t.shape[1], int(lost),
                                     ctypes.byref(g)), "swfs_sync_boundary_gap")
    d = _struct_dict(g)
    d["consistent"], d["separable"] = bool(d["consistent"]), bool(d["separable"])
    return d


def boundary_check(tail, head):
    """Whether the telemetry in `head` (nhead, nvals) starts with the frame that follows the
    last of `tail` (ntail, nvals): `sync`'s own check of two telemetry files (sync.h
    swfs_sync_boundary_check; use the last and first SYNC_EDGE_FRAMES = 128 frames of two
    files). The step across the boundary against the one- and two-frame steps beside it; where
    that cannot tell, the step between means of `window` frames either side against the same
    inside the edges, contiguous and over a lost frame. Returns verdict (+1 contiguous, -1 not,
    0 the telemetry cannot tell), q, q1_max, q2_min, n1, n2, and of the second stage window
    (0 where it did not run), q_window, p_lost, p_contiguous."""
    t, h = _edges(tail, head)
    b = _lib.swfs_sync_boundary()
    check(lib.swfs_sync_boundary_check(dptr(t), t.shape[0], dptr(h), h.shape[0], t.shape[1], ctypes.byref(b)),
          "swfs_sync_boundary_check")
    return _struct_dict(b)


def _st_checks(r):
    """A space-time map's checks against the observation (run.h st_*) as a dict; st_warn_wind
    and st_warn_corr: whether each warns (swfs_spacetime_warns)."""
    nl = r.info.nlags
    w = lib.swfs_spacetime_warns(ctypes.byref(r))
    return dict(st_found=bool(r.st_found), st_train_v=(r.st_train_vx, r.st_train_vy), st_obs_v=(r.st_obs_vx, r.st_obs_vy),
                st_mismatch=r.st_mismatch, st_obs_nlayers=r.st_obs_nlayers, st_train_nlayers=r.st_train_nlayers,
                st_corr_train=np.array(r.st_corr_train[:nl]),
                st_corr_spread=np.array(r.st_corr_spread[:nl]), st_corr_obs=np.array(r.st_corr_obs[:nl]),
                st_corr_excess=r.st_corr_excess, st_edges_joined=r.st_edges_joined,
                st_edges_clamped=r.st_edges_clamped, st_edges_unreadable=r.st_edges_unreadable,
                st_edges_why=r.st_edges_why.decode(errors="replace"), st_warn_wind=bool(w & _lib.SPACETIME_WARN_WIND),
                st_warn_corr=bool(w & _lib.SPACETIME_WARN_CORR))


def modal_slopes(files, cm=None, outdir=None, imat=None):
    """A modal system's coefficient files back to its Shack-Hartmann's slopes
    (`specklewfs modal-slopes`): s' = CM+ c through the pseudo-inverse of the modal control
    matrix `cm` (NAXIS1 the slopes, NAXIS2 the coefficients), or, given `imat` instead, the
    modal response matrix RM (NAXIS1 the coefficients, NAXIS2 the slopes), s' = RM c with RM's
    pseudo-inverse taken as the control matrix (written as pinv_NAME); each file under its own
    name in the existing folder `outdir` (not the inputs') with the control matrix that their
    MODALCM key names, all or none; the slopes then take the
    Shack-Hartmann path (speckles with actuators, valid and pupil; its teach projects its loops'
    slopes the same way). Returns ncoef, nslopes, rank, nframes, cond and resid (the share of
    the coefficients CM cannot have made)."""
    files = _lib.path_list(files)
    if outdir is None:
        raise ValueError("modal_slopes: needs outdir, an existing folder")
    if (cm is None) == (imat is None):
        raise ValueError("modal_slopes: give cm (the modal control matrix) or imat (the modal response matrix), one of them")
    arr, n = _paths(files)
    o = _lib.swfs_modal_slopes_options(arr, n, enc(cm) if cm is not None else None, enc(outdir),
                                       enc(imat) if imat is not None else None)
    r = _lib.swfs_modal_slopes_result()
    check(lib.swfs_modal_slopes_run(ctypes.byref(o), ctypes.byref(r)), "modal_slopes")
    return _struct_dict(r)


def teach(files, out, work=None, config=None, loops=None, seed=None, progress=None, provenance=(), science=None,
          actuators=None, pupil=None, valid=None, max_loops=None, **params):
    """A learned map for one observation from simulated closed loops of your system at the
    winds its slopes show (`specklewfs teach`, run.h swfs_teach_run): files, the observation's
    consecutive telemetry files (2 nsub^2 slopes per WFS frame); config and params, the system
    in `simulate mode=timeseries` keys (its nsub, wfs_rate and teldiam the observation's; the
    layers and seeds are set per loop); work, a folder (created if needed) for the loops and
    the maps tried (default: out's name without .fits, plus .teach); out, the chosen map for
    speckles(..., recon=out). Returns the layers found
    (wind: as wind_from_slopes' layers), lags, nloops, loop_frames (each loop's WFS frames:
    loop_frames_described, lengthened where the loops hold fewer than 10 frames per input of
    the map, map_inputs), the space-time map's training misfit
    and truth [m], its checks on the observation (the st_* of speckles()), and chosen:
    "spacetime" (neither check warned), "perframe" (the same loops' per-frame map) or
    "perframe_mixed" (loops of the measured layer and random second layers) or "spacetime_prior"
    (no frozen-flow layer tracked: the slopes' time correlation, tcorr at tcorr_lags, matched
    by calibration loops of one layer, speed_calibration = [(speed, misfit), ...], gives
    prior_speed [m/s]; loops of two layers within a factor sqrt 2 of it in any direction;
    lags [0, -1, 1, -2, 2], no checks; "perframe_prior" in maps taught before 2026-12-03). With
    science and actuators (and pupil, valid) the system comes from the observation's own files, the ones
    speckles() takes (run.h swfs_teach_describe: their geometry, DM, pupil and valid map;
    nsub, wfs_rate and the loops' length from the first telemetry file); config and params
    may still set any key, and win. Without ao_modes
    (and ao_recon) in config or params the loops' modal filter comes from the slopes
    (modes_from_slopes: the knee of their DM-mode variances, knee_obs, matched by calibration
    loops, calibration = [(ao_modes, knee), ...]); ao_modes says what the loops used. Without
    slope_noise the loops' slope noise is the observation's white slope noise (noise_rms [rad],
    measured either way over noise_cells cells, as telemetry.slopes_white_noise measures it;
    noise_share its share of the slopes' variance); slope_noise says what the loops used. The map
    writes the wavefront on out_points points of its own (a hexapolar grid of out_pitch [m],
    half the DM's dm_pitch, at least two pupil samples; extension OUTXY of out), which
    speckles() interpolates in place of the DM's actuators. The space-time map's learning curve
    (learn(..., curve=True)) over the first loops is curve_first; where it asks for more frames
    than they hold, more loops are simulated, up to max_loops (default 4 loops, at most 64;
    loops: never more),
    st_loops of them in all, and curve is the curve over them all. A first curve that does not
    fall cannot tell, nor end the loops (one that falls and asks for at most twice the first
    loops: teach rule 2026-12-08): the loops are doubled once, curve_doubled is the curve over
    them, and it asks for more as any curve does (None where there was no doubling). The loops a curve asks
    for are the last unless their own curve falls (beyond twice its parts' scatter) faster than
    any a + b / n allows: then asked_loops is their count, curve_asked their curve, and more
    loops follow to max_loops (asked_loops 0, curve_asked None otherwise). The curve is measured
    only where more loops may follow (max_loops, the budget in effect, above loops)."""
    from .sim import _checked_params
    files = _lib.path_list(files)
    params = dict(params)
    params.setdefault("mode", "timeseries")
    o = _lib.swfs_teach_run_options()
    lib.swfs_teach_run_options_default(ctypes.byref(o))
    if (science is None) != (actuators is None):
        raise ValueError("teach: the system from the observation's files needs both science and actuators")
    if (pupil is not None or valid is not None) and science is None:
        raise ValueError("teach: pupil and valid describe the system with science and actuators "
                         "(otherwise give pupil_mask= and valid= as params)")
    filter_given, noise_given, coupling_given = [], [], []

    def describe(c):  # on the config of config and params, as the command does (cli_ts_params)
        filter_given.append(bool(lib.swfs_ts_config_gives_filter(c)))
        noise_given.append(lib.swfs_config_has(c, b"slope_noise"))
        coupling_given.append(lib.swfs_config_has(c, b"dm_coupling"))
        if science is not None:
            check(lib.swfs_teach_describe(c, enc(science), enc(actuators), enc(pupil) if pupil is not None else None,
                                          enc(valid) if valid is not None else None, enc(files[0])),
                  "swfs_teach_describe")
    o.sim = _checked_params("ts", config, params, describe)
    o.modes_from_slopes = int(not filter_given[0])
    o.noise_from_slopes = int(not noise_given[0])
    o.coupling_from_recon = int(not coupling_given[0])
    arr, n = _paths(files)
    if work is None:  # beside out (run.h swfs_teach_work_default)
        buf = ctypes.create_string_buffer(4200)
        check(lib.swfs_teach_work_default(enc(out), buf, len(buf)), "swfs_teach_work_default")
        work = buf.value.decode()
    os.makedirs(work, exist_ok=True)
    o.files, o.nfiles, o.out, o.work = arr, n, enc(out), enc(work)
    if loops is not None:  # None: the library's defaults (swfs_teach_run_options_default)
        o.nloops = int(loops)
    if seed is not None:
        o.seed = int(seed)
    if max_loops is not None:
        o.max_loops = int(max_loops)
    r = _run("swfs_teach_run", o, _lib.swfs_teach_run_result, None, provenance, progress)
    return _teach_dict(r, bool(o.modes_from_slopes))


def _teach_dict(r, modes_from_slopes):
    e = r.wind.est
    layers = [dict(vx=L.vx, vy=L.vy, speed=L.speed, direction=L.direction, corr=L.corr, signif=L.signif,
                   nlags=L.nlags) for L in e.layer[:e.nlayers]]
    d = dict(layers=layers, nlayers_given=r.nlayers, nframes=r.wind.nframes, nsub=r.wind.nsub, pitch=r.wind.pitch,
             rate=r.wind.rate, lags=list(r.lags[:r.nlags]), nloops=r.nloops, map_inputs=r.map_inputs,
             loop_frames=r.loop_frames, loop_frames_described=r.loop_frames_described, st_misfit_rms=r.st_misfit_rms,
             st_truth_rms=r.st_truth_rms, chosen=_lib.TEACH_CHOSEN[r.chosen], seconds=r.seconds,
             ao_modes=r.ao_modes, modes_from_slopes=modes_from_slopes, knee_obs=r.knee_obs,
             calibration=[(r.cal_modes[k], r.cal_knee[k]) for k in range(r.ncal)], zonal=bool(r.zonal),
             misfit_modal=r.misfit_modal, misfit_zonal=list(r.zonal_misfit),
             zonal_rcond=(ctypes.c_double * 6).in_dll(lib, "swfs_teach_zonal_rcond")[r.zonal_best],
             out_points=r.out_points, out_pitch=r.out_pitch, dm_pitch=r.dm_pitch, noise_rms=r.noise_rms,
             noise_cells=r.noise_cells, noise_share=r.noise_share, slope_noise=r.slope_noise,
             st_loops=r.st_loops, max_loops=r.max_loops, curve_first=_curve_dict(r.curve_first),
             curve=_curve_dict(r.curve), curve_doubled=_curve_dict(r.curve_doubled), asked_loops=r.asked_loops,
             curve_asked=_curve_dict(r.curve_asked),
             coupling=dict(coupling=r.coupling.coupling, misfit=r.coupling.misfit,
                           misfit_interp=r.coupling.misfit_interp, rank=r.coupling.rank,
                           gaussian=bool(r.coupling.gaussian)) if r.coupling_done else None)
    # no layer tracked: the speed from the slopes' time correlation
    if d["chosen"] in ("spacetime_prior", "perframe_prior"):
        d.update(tcorr_lags=list(r.tcorr_lags[:r.ntcorr]), tcorr=list(r.tcorr[:r.ntcorr]),
                 speed_calibration=[(r.speed_cal[k], r.speed_misfit[k]) for k in range(r.nspeed)],
                 prior_speed=r.prior_speed)
    d.update(_st_checks(r.check))
    return d


def _mean_teach_dict(m, what):
    """The loops a run simulated for the residual mean's miss (run.h swfs_mean_teach_result)
    as a dict, None where it simulated none; a RuntimeWarning where the default could not."""
    if m.fallback:
        warnings.warn(f"{what}: a pyramid's telemetry, but no loops of the system for the residual mean's miss: "
                      f"{m.fallback.decode()}", RuntimeWarning, stacklevel=3)
    return None if not m.done else dict(
        reused=bool(m.reused), automatic=bool(m.automatic), nloops=m.nloops, loop_frames=m.loop_frames, pyramid=bool(m.pyramid),
        noise_rms=m.noise_rms, photons=m.photons, slope_noise=m.slope_noise, knee=m.knee,
        layers=[(m.speed[k], m.direction[k]) for k in range(m.nlayers)], act_pitch=m.act_pitch,
        r0=m.r0, r0_pairs=m.r0_pairs, power=m.power, power_ratio=m.power_ratio, nloops_first=m.nloops_first,
        curve_excess=m.curve_excess, curve_frames=m.curve_frames, seconds=m.seconds, work=m.work.decode())


def speckles(timing, science, actuators, out, match=(), recon="teach", band="auto", valid=None, write_recon=None,
             geom=None, progress=None, provenance=(), pupil=None, teach_work=None, teach_loops=None, teach_seed=None,
             teach_keep_loops=False, tiptilt=None, wfs_rate=False, wfs_hz=None, teach_again=False,
             teach_max_loops=None, linear=None, teach_keys=None, mean_loops=None, mean_teach_loops=None,
             loops_map="auto", mean_teach_max_loops=None, pairing="speckles"):
    """The speckle cube (`specklewfs speckles`) from the timing table, the reduced science
    cube (geometry, focal window) and the actuator positions. match: (in, out) pairs of
    science cubes reduced to the frames the speckle cube has (`--match`). recon: 'teach'
    (default: a map taught for this observation from its own files, as teach(..., science=,
    actuators=) makes it, in teach_work (default: out's name without .fits, plus .teach) as
    taught.fits, its loops' folders removed unless teach_keep_loops; a taught.fits there that
    was taught for the same telemetry, system files and teach options (its TEACHFPR) is reused
    at once unless teach_again, and then teach_reused is True and teach holds only chosen and
    nloops; where teach cannot, a RuntimeWarning says why and 'vk' is used), 'vk',
    'map', 'svd' or a reconstructor file; band: 'auto' (the subapertures' nsub/2 lambda/D),
    'none' or a radius; valid: the AO system's subaperture map; pupil: the pupil mask. Returns
    nout, ncubes, nok, ratio, lag, wfs_hz, resmean_rms and wavelen [m], curl_noise [rad] (vk / map on
    slopes modal-slopes made: the slope noise from their curl, else 0), meanmiss_rms [m] (a
    learned map's MEANMISS added to the residual's mean, else 0), modal_regularized and
    modal_lsq (slopes modal_slopes(..., imat=) made from coefficients its check flagged: also a
    RuntimeWarning), the pipeline's info
    (dict), and with 'teach' taught (bool), teach_map and teach (what teach() returns) or
    teach_fallback (why not); where teach_keys say neither dm_coupling nor ao_recon, a second
    map is taught with a DM of Gaussian functions, kept where its speckles follow the science
    frames better by more than 2 standard errors: dm_choice (gauss, coupling, corr of each, diff, diff_se, npix,
    other_map; None where not compared) and dm_fallback (why not). A RuntimeWarning when resmean_rms exceeds the wavelength (run.h
    swfs_speckles_resmean_warns: no closed loop's). orient: the camera's orientation told by the
    speckles (corr by pairing (swap, sign_x, sign_y), best, table, diff, diff_se, npix, warns,
    adopted; a RuntimeWarning where another pairing beats the timing table's by 5 standard
    errors). pairing: 'speckles' (the default: such a pairing is the one the speckle cube and the
    match copies take, adopted True; the timing table is not changed) or 'table' (the table's
    kept, `--pairing table`). tiptilt: None (the default: 'exposure',
    or at the WFS rate 'frame'), 'exposure', 'frame' or 'keep'. wfs_rate: one speckle field
    per WFS frame instead of per exposure (`--wfs-rate`, for coherence(); FRAMEDT = 1/rate;
    wfs_hz [Hz] where the telemetry has no WFSRATE); it takes no match and no 'exposure'.
    linear: any AO system's telemetry through the generic linear model instead of the
    Shack-Hartmann's (`--basis`; actuators then None): a dict of basis (the cube of basis
    functions), control (telemetry -> coefficients) or imat (the interaction matrix, inverted by
    the MAP reconstructor from the telemetry), scale (`--coef-scale`) and for a basis on the
    DM's grid dm_pitch [m], dm_offset (x, y) [m], dm_rot [deg], dm_flip; e.g. a pyramid's
    signals with simulate wfs=pyramid's influence.fits and imat_ao.fits. No map is taught for
    a linear model (recon applies to the Shack-Hartmann's); write_recon then writes its map to
    the coefficients (imat's reconstructor, MAP or SVD), which control= takes back (where
    loops_map chose among the loops' maps, the written set's map, carrying the miss of the
    residual's mean that set was given as a MEANMISS image: stream and live add it, and no
    default loops are simulated for a control= map that carries one). teach_keys: what the files do not
    say of the system teach's loops simulate, a dict in `simulate mode=timeseries` keys (e.g.
    dict(dm_coupling=0.15) for a DM of Gaussian influence functions; `--teach-set`), as
    teach(**params): they win over the files' description and are part of the fingerprint.
    mean_loops: folders of simulated loops of the same system (`simulate_timeseries`, at least
    2; `--mean-loop`): this run's own reconstruction's miss of the residual's time mean in
    them, checked held out (meanmiss_heldout < 1: shared by the loops) and then added to RESMEAN
    (meanmiss_rms). mean_loops='teach' (`--mean-loop teach`, with linear): speckles simulates
    mean_teach_loops (4) such loops itself, of the system the files describe (the sensor from the
    telemetry's header, its noise, layers and modal filter from the telemetry, the DM's pitch
    from the basis; teach_keys for the rest), in teach_work and reused while that description
    is the same (teach_again: anew); returned as mean_teach (a dict: what was read, the loops'
    folder; automatic when the default chose them, fallback why it could not), None otherwise.
    The default (mean_loops=None) does so for a pyramid's telemetry (WFSTYPE) through linear,
    and where the files do not describe the loops goes on without them, warning why;
    mean_loops='none': never. loops_map ('auto', 'choose' or 'none'; `--loops-map`): with
    linear's interaction matrix (imat) and mean loops, also the map learned from the loops
    (their truth on a grid of half their DM's pitch, the map on those points: carry_resid 0; loops
    whose truth is on their DM: carried onto the basis) and the self-check's choice among the
    two speckle sets and those of the two maps mixed at quarters (w the interaction matrix's
    map + (1 - w) the loops', w = 0.75, 0.5, 0.25) on the science frames; 'auto' where speckles
    simulated the loops of a pyramid (mean_loops='teach', its default for one), 'choose' with any
    mean loops. Returned as loops_map (a dict: chosen, explained (the interaction matrix's, the
    loops' map's), mix_weight, explained_mix (the mixes'), weight (the written set's w: 1 the
    interaction matrix's, 0 the loops'), map, work, meanmiss_heldout, mean_from_imat,
    carry_resid, nframes, inputs; lags: the space-time map's (teach's rule: 0, -L, L, -2L, 2L,
    the loops' fastest layer moving half a subaperture in L frames, lag_speed [subapertures per
    frame], 0 none), () where the loops held fewer frames than it needs (st_frames) and the
    per-frame map was learned; pf_meanmiss_heldout, mean_from_perframe: where the space-time
    map's miss of the mean is not shared, the per-frame map's of the same loops and whether its
    mean went with the speckles) when tried, else None and loops_map_fallback says why (too
    few frames in the loops for a map of their own, ...). Where speckles simulates the loops for
    that map, it simulates more of them where the map's learning curve over the first ones asks
    for more frames (teach's rule), up to mean_teach_max_loops (None: 4 mean_teach_loops, at
    most 16); mean_teach then says nloops, nloops_first, curve_excess and curve_frames."""
    if (linear is None) == (actuators is None):
        raise ValueError("speckles: give the actuators (the Shack-Hartmann model) or linear (the linear model), not both")
    o = _lib.swfs_speckles_run_options()
    lib.swfs_speckles_run_options_default(ctypes.byref(o))
    o.timing, o.science, o.actuators, o.out = enc(timing), enc(science), _opt(actuators), enc(out)
    _linear(o.lin, linear)
    tr = _lib.swfs_teach_run_result()
    # The teach options go to the library whatever recon is: its check (run.h
    # swfs_speckles_run_options_check) refuses them with another reconstructor.
    o.teach_work = _opt(teach_work)
    if teach_loops is not None:  # None: the library's default (swfs_speckles_run_options_default)
        o.teach_loops = int(teach_loops)
    if teach_seed is not None:
        o.teach_seed = int(teach_seed)
    if teach_max_loops is not None:  # None: 4 teach_loops (at most 64) where the learning curve asks
        o.teach_max_loops = int(teach_max_loops)
    o.teach_keep_loops = int(bool(teach_keep_loops))
    o.teach_again = int(bool(teach_again))
    tkeys = [f"{k}={_cfg_value(v)}" for k, v in (teach_keys or {}).items()]
    o.teach_keys, o.nteach_keys = _lib.strings(tkeys)  # kept alive by o until the run returns
    if isinstance(mean_loops, str) and mean_loops in ("teach", "none"):
        o.mean_teach, mean_loops = int(mean_loops == "teach"), None
    elif isinstance(mean_loops, (str, bytes, os.PathLike)):
        raise ValueError("speckles: mean_loops takes a list of folders, 'teach' or 'none'")
    if mean_teach_loops is not None:  # None: the library's default (4)
        o.mean_teach_loops = int(mean_teach_loops)
    if mean_teach_max_loops is not None:  # None: 4 mean_teach_loops (at most 16) where the curve asks
        o.mean_teach_max_loops = int(mean_teach_max_loops)
    mloops = [os.fspath(m) for m in (mean_loops or ())]
    o.mean_loops, o.nmean_loops = _lib.strings(mloops)
    if loops_map not in ("auto", "choose", "none"):
        raise ValueError(f"speckles: loops_map takes 'auto', 'choose' or 'none', got {loops_map!r}")
    o.loops_map = {"auto": -1, "choose": 1, "none": 0}[loops_map]
    if pairing not in ("speckles", "table"):
        raise ValueError(f"speckles: pairing takes 'speckles' or 'table', got {pairing!r}")
    o.pairing_table = int(pairing == "table")
    if recon == "teach":
        o.pipe.recon = _lib.RECON_TEACH
        o.teach = ctypes.cast(ctypes.byref(tr), ctypes.c_void_p)
    elif recon in _RECON and recon != "given":
        o.pipe.recon = _lib.choice(_RECON, recon, "speckles: recon")
    else:
        o.pipe.recon, o.recon = _RECON["given"], enc(recon)
    o.mask = _opt(pupil)
    o.pipe.band = _band(band)
    if tiptilt is not None:
        o.pipe.tiptilt = _lib.choice(_TT, tiptilt, "speckles: tiptilt")
        if wfs_rate and tiptilt == "exposure":
            raise ValueError("wfs_rate removes the tip-tilt per WFS frame (or tiptilt='keep'); 'exposure' does not apply")
    if wfs_rate and match:
        raise ValueError("match pairs camera frames; it does not apply with wfs_rate")
    if wfs_hz is not None and not wfs_rate:
        raise ValueError("wfs_hz goes with wfs_rate")
    o.pipe.wfs_rate = int(bool(wfs_rate))
    if wfs_hz is not None:
        o.wfs_hz = float(wfs_hz)
    o.valid, o.write_recon = _opt(valid), _opt(write_recon)
    match = list(match or ())
    mi, n = _paths([a for a, _b in match])
    mo, _n = _paths([b for _a, b in match])
    o.match_in, o.match_out, o.nmatch = mi, mo, n
    r = _run("swfs_speckles_run", o, _lib.swfs_speckles_run_result, geom, provenance, progress)
    d = {k: getattr(r, k) for k, _t in _lib.SPECKLES_RUN_FIELDS}
    d["resmean_rms"], d["wavelen"] = r.resmean_rms, r.wavelen
    d["curl_noise"] = r.curl_noise
    d["meanmiss_rms"], d["meanmiss_heldout"] = r.meanmiss_rms, r.meanmiss_heldout
    d["mean_teach"] = _mean_teach_dict(r.mean_teach, "speckles")
    lm = r.loops_map
    d["loops_map_fallback"] = lm.fallback.decode()
    d["loops_map"] = None if not lm.tried else dict(
        chosen=bool(lm.chosen), explained=(lm.explained[0], lm.explained[1]), ncommon=lm.ncommon, nframes=lm.nframes,
        inputs=lm.inputs, misfit_rms=lm.misfit_rms, truth_rms=lm.truth_rms, carry_resid=lm.carry_resid,
        meanmiss_heldout=lm.meanmiss_heldout, meanmiss_rms=lm.meanmiss_rms, mean_from_imat=bool(lm.mean_from_imat),
        seconds=lm.seconds, work=lm.work.decode(), map=lm.map.decode(), mix_weight=tuple(lm.mix_weight),
        explained_mix=tuple(lm.explained_mix), weight=lm.weight, mix_note=lm.mix_note.decode(),
        lags=tuple(lm.lags[k] for k in range(lm.nlags)), lag_speed=lm.lag_speed, st_frames=lm.st_frames,
        pf_meanmiss_heldout=lm.pf_meanmiss_heldout, mean_from_perframe=bool(lm.mean_from_perframe))
    d["modal_regularized"], d["modal_lsq"] = bool(r.modal_regularized), r.modal_lsq
    if r.modal_regularized:
        warnings.warn("speckles: these slopes came through modal_slopes(..., imat=) from coefficients whose white "
                      f"noise is not a least-squares control matrix's (MODALLSQ {r.modal_lsq:.3g}): no map fits them; "
                      "give modal_slopes the system's control matrix (cm=), or use the linear model", RuntimeWarning,
                      stacklevel=2)
    if lib.swfs_speckles_resmean_warns(ctypes.byref(r)):
        warnings.warn(f"speckles: the AO residual's time mean is {r.resmean_rms * 1e9:.0f} nm rms, more than the "
                      f"wavelength ({r.wavelen * 1e9:.0f} nm), which no closed loop's is: the reconstructor amplifies "
                      "slope patterns the model's D does not make", RuntimeWarning, stacklevel=2)
    d["info"] = _struct_dict(r.info)
    d.update(_st_checks(r))
    if r.orient_done:  # the camera's orientation told by the speckles (sync.h swfs_orient_acc_result)
        o_ = r.orient
        pair = []
        for k in range(8):
            p_ = _lib.swfs_sync_result()
            lib.swfs_orient_pairing(k, ctypes.byref(p_))
            pair.append((p_.swap, p_.sign_x, p_.sign_y))
        d["orient"] = dict(corr={pair[k]: o_.corr[k] for k in range(8)}, best=pair[o_.best], table=pair[o_.ref],
                           diff=o_.diff, diff_se=o_.diff_se, npix=o_.npix,
                           warns=bool(lib.swfs_speckles_orient_warns(ctypes.byref(r))),
                           adopted=bool(r.orient_adopted))
        if d["orient"]["warns"]:
            line, why = ctypes.create_string_buffer(1024), ctypes.create_string_buffer(1024)
            lib.swfs_orient_check_describe(ctypes.byref(o_), line, 1024)
            lib.swfs_speckles_orient_warning(ctypes.byref(r), why, 1024)
            warnings.warn(f"speckles: {why.value.decode()}; {line.value.decode()}", RuntimeWarning, stacklevel=2)
    if recon == "teach" and linear is None:
        d["taught"] = bool(r.taught)
        if r.taught:
            d["teach_map"] = r.teach_map.decode()
            d["teach_reused"] = bool(r.teach_reused)
            d["teach_fingerprint"] = r.teach_fingerprint.decode()
            d["teach"] = ({"chosen": _lib.TEACH_CHOSEN[tr.chosen], "nloops": tr.nloops}
                          if r.teach_reused else _teach_dict(tr, True))
            # the loops' DM chosen by the science frames (run.h dm_choice_done)
            d["dm_choice"] = None if not r.dm_choice_done else dict(
                gauss=bool(r.dm_gauss_chosen), coupling=r.dm_gauss_coupling,
                corr=dict(surface=r.dm_corr[0], gauss=r.dm_corr[1]), diff=r.dm_corr_diff, diff_se=r.dm_corr_se,
                npix=r.dm_npix, other_map=r.dm_other_map.decode())
            d["dm_fallback"] = r.dm_fallback.decode()
        else:
            d["teach_fallback"] = r.teach_fallback.decode()
            warnings.warn(f"speckles: no map could be taught for this observation ({d['teach_fallback']}); the von "
                          "Karman map (recon='vk') instead", RuntimeWarning, stacklevel=2)
    return d


def estimate_files(science, speckles, out, read_noise=None, gain=None, g_smooth_lod=None, progress=None,
                   provenance=()):
    """HALO.fits (`specklewfs estimate`) from a science cube and the speckle cube made for
    it, frame for frame. read_noise [counts], gain [e-/count]: None takes RDNOISE and GAIN
    from the science header; g_smooth_lod [lambda/D] None: the library's 2. Returns the Halo
    (with the AO residual's time mean when the speckle cube has one)."""
    o = _lib.swfs_estimate_run_options()
    lib.swfs_estimate_run_options_default(ctypes.byref(o))
    o.science, o.speckles, o.out = enc(science), enc(speckles), enc(out)
    o.read_noise = math.nan if read_noise is None else float(read_noise)
    o.gain = math.nan if gain is None else float(gain)
    if g_smooth_lod is not None:
        o.g_smooth_lod = float(g_smooth_lod)
    r = _run("swfs_estimate_run", o, _lib.swfs_estimate_run_result, None, provenance, progress)
    lib.swfs_halo_free(r.halo)
    return Halo.read(out)

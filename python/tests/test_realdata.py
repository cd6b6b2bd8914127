"""The real-data path on files from Python (realdata.py): reduce -> sync -> speckles ->
estimate_files -> pupil_estimate on a small AO time series, its products equal to the command
line's on the same inputs, and its errors raised with nothing written."""
import math
import os
import subprocess

import warnings

import numpy as np
import pytest

import specklewfs as sw

from conftest import ROOT


class Enough(Exception):
    """Raised by the tests' progress callbacks to stop a run."""


def _at_second_poll():
    """A progress callback that stops teach at the second report of its loops: the first
    loops' count shown again from within the caller's loop (every 256 WFS frames)."""
    calls = []

    def poll(stage, done, total):
        calls.append(stage)
        if calls.count("simulating the loops") == 2:
            raise Enough(f"{done} of {total}")
    return poll


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("realdata")
    keys = dict(screen_n=512, ncubes=3, cube_frames=40, cube_gap=60, start_offset=50.4, wfs_file_frames=1000)
    sw.simulate_timeseries(str(d / "sim"), config=os.path.join(ROOT, "config", "mmt-clio.conf"), **keys)
    return d


def test_path_on_files_equals_the_cli(series, cli):
    d, s = series, series / "sim"
    raws = [str(s / f"raw_{k:03d}.fits") for k in range(3)]
    r = sw.reduce(raws, str(d / "sci.fits"), dark=str(s / "dark.fits"), flat=str(s / "flat.fits"))
    # mmt-clio.conf's camera: 19 counts of read noise, as the raw frames carry it.
    assert r["nframes"] == 120 and r["missing"] == "" and 18 < r["noise_var_measured"] ** 0.5 < 20.5
    t = sw.sync(str(d / "sci.fits"), str(s / "handshake.log"), str(d / "timing.txt"))
    assert t["ratio_auto"] and t["ratio_bound"] > t["ratio"]
    # the raw cubes' EXPTIME (6.48 WFS frames at 527 Hz) starts the search 5 coarse steps below it
    assert t["exptime_used"] and not t["exptime_widened"] and t["exptime_ratio"] == pytest.approx(6.48, abs=1e-9)
    assert t["ratio_min"] == pytest.approx(6.43, abs=1e-9)
    assert abs(t["ratio"] - 6.4811) < 0.01 and t["z"] > t["z_need"] and t["nexp_ok"] >= 118
    # The fit over each cube's own file, and the refit (if a cube crosses into a contiguous file).
    assert 0 <= t["refits"] <= 3 and abs(t["ratio_first"] - t["ratio"]) < 0.05 and abs(t["lag_first"] - t["lag"]) < 2
    assert t["refits"] > 0 or (t["ratio_first"], t["lag_first"]) == (t["ratio"], t["lag"])
    assert t["refits"] == 0 or t["ncontinued"] > 0
    assert t["nmissing"] == 0 and t["nexp_missing"] == 0 and t["missing_reason"] == ""
    # (teach_max_loops=12: the first 12 loops only, for the suite's time; the learning curve's
    # own choice of more is measured by the benchmarks)
    sp = sw.speckles(str(d / "timing.txt"), str(d / "sci.fits"), str(s / "actuators.fits"), str(d / "sp.fits"),
                     match=[(str(d / "sci.fits"), str(d / "sci_m.fits"))], teach_max_loops=12)
    assert sp["nout"] == t["nexp_ok"] and sp["resmean_rms"] > 0
    # the camera's orientation told by the speckles: the table's pairing (as the model), well
    # above the transposed ones, and no warning
    o = sp["orient"]
    assert o["table"] == o["best"] == (0, 1, 1) and not o["warns"] and o["npix"] > 100
    assert o["corr"][(0, 1, 1)] > 0.05 and all(o["corr"][(1, sx, sy)] < 0.5 * o["corr"][(0, 1, 1)]
                                               for sx in (1, -1) for sy in (1, -1))
    assert not o["adopted"]
    # a table whose pairing mirrors the camera in x (beside the right one: the same telemetry
    # names): the speckles' check finds the camera as the model and the matched copy takes it,
    # the right table's frame for frame; with pairing='table' the table's is kept, and warned of
    wrong = d / "timing_mirrored.txt"
    wrong.write_text("".join("pairing 0 -1 1" + line[line.index(" 0 1 1 ") + 6:] if line.startswith("pairing")
                             else line for line in (d / "timing.txt").read_text().splitlines(True)))
    assert "pairing 0 -1 1 " in wrong.read_text()
    with pytest.warns(RuntimeWarning, match="take the speckles' pairing"):
        sw_ = sw.speckles(str(wrong), str(d / "sci.fits"), str(s / "actuators.fits"), str(d / "sp_w.fits"),
                          match=[(str(d / "sci.fits"), str(d / "sci_w.fits"))], recon="vk")
    assert sw_["orient"]["adopted"] and sw_["orient"]["best"] == (0, 1, 1) and sw_["orient"]["table"] == (0, -1, 1)
    assert sw_["orient"]["diff"] > 5 * sw_["orient"]["diff_se"]
    np.testing.assert_array_equal(sw.read_fits(str(d / "sci_w.fits"))[0], sw.read_fits(str(d / "sci_m.fits"))[0])
    assert sw.read_keys(str(d / "sci_w.fits"), ["CAMORIEN"])["CAMORIEN"] is None
    with pytest.warns(RuntimeWarning, match="which was kept"):
        sk = sw.speckles(str(wrong), str(d / "sci.fits"), str(s / "actuators.fits"), str(d / "sp_k.fits"),
                         match=[(str(d / "sci.fits"), str(d / "sci_k.fits"))], recon="vk", pairing="table")
    assert not sk["orient"]["adopted"] and sk["orient"]["warns"]
    assert sw.read_keys(str(d / "sci_k.fits"), ["CAMORIEN"])["CAMORIEN"] == "SWAP=0 SX=-1 SY=+1"
    # the taught map writes on its own grid (half the DM's pitch): the speckles within its band
    assert sp["info"]["out_pitch"] == pytest.approx(sp["teach"]["out_pitch"], rel=1e-12)
    assert sp["info"]["band"] == pytest.approx(6.5 / (2 * sp["info"]["out_pitch"]), rel=1e-9) and sp["info"]["band"] > 6
    # the default reconstructor: a map taught for this observation from its own files, in
    # sp.teach/ beside the output (the loops' layers those the slopes show)
    # and a second one whose loops' DM has Gaussian functions (the files do not say the DM's):
    # the one whose speckles follow the science frames better is kept, the series' own DM's
    # (simulate's interpolated surface)
    dm = sp["dm_choice"]
    assert dm is not None and sp["dm_fallback"] == "" and dm["coupling"] == 0.15 and dm["npix"] > 100
    print(f"the loops' DM: surface {dm['corr']['surface']:.4f}, Gaussian {dm['corr']['gauss']:.4f}, per pixel "
          f"{dm['diff']:+.4f} +- {dm['diff_se']:.4f}")
    assert not dm["gauss"] and dm["diff"] < 0 and dm["corr"]["surface"] > dm["corr"]["gauss"]
    assert o["corr"][(0, 1, 1)] == dm["corr"]["surface"]  # the kept speckles' check is the one reported
    assert dm["other_map"] == str(d / "sp.teach" / "dm-gauss" / "taught.fits") and os.path.exists(dm["other_map"])
    assert sp["taught"] and sp["teach_map"] == str(d / "sp.teach" / "taught.fits") and os.path.exists(sp["teach_map"])
    assert sp["teach"]["nloops"] >= 12 and sp["teach"]["modes_from_slopes"] and sp["teach"]["layers"]
    # at most 12 loops: no more to add, so no learning curve measured (test_teach measures it)
    assert sp["teach"]["st_loops"] == sp["teach"]["max_loops"] == 12 and sp["teach"]["curve"] is None
    assert sp["info"]["nlags"] == (5 if sp["teach"]["chosen"] == "spacetime" else 0)
    assert not sp["teach_reused"] and len(sp["teach_fingerprint"]) == 16
    h = sw.estimate_files(str(d / "sci_m.fits"), str(d / "sp.fits"), str(d / "halo.fits"))
    assert h.resmean is not None and h.frames == sp["nout"]
    assert h.tiptilt == "exposure" and sw.Halo.read(str(d / "halo.fits")).tiptilt == "exposure"
    truth = sw.read_fits(str(s / "truth.fits"), "NCP")[0]
    p = sw.pupil_estimate(h, sw.read_geom(str(d / "halo.fits")))
    err = sw.wfe_compare(p.wfe, truth, p.mask)[0]
    print(f"NCP error {err * 1e9:.1f} nm over {sp['nout']} exposures")
    assert err < 40e-9
    # The command line on the same inputs: the same products.
    c = d / "cli"
    c.mkdir()
    run = lambda *a: subprocess.run([cli, *a], check=True, capture_output=True)  # noqa: E731
    run("reduce", *raws, "--dark", str(s / "dark.fits"), "--flat", str(s / "flat.fits"), "-o", str(c / "sci.fits"))
    run("sync", str(c / "sci.fits"), str(s / "handshake.log"), "-o", str(c / "timing.txt"))
    # the command line's speckles in Python's teach folder: the same telemetry, system files and
    # teach options (its own copies of the reduced cubes), so the map taught above is reused
    spc = run("speckles", str(c / "timing.txt"), "--science", str(c / "sci.fits"), "--actuators",
              str(s / "actuators.fits"), "-o", str(c / "sp.fits"), "--match", str(c / "sci.fits"), str(c / "sci_m.fits"),
              "--teach-work", str(d / "sp.teach"), "--teach-max-loops", "12").stderr.decode()
    assert f"speckles: reused {d / 'sp.teach' / 'taught.fits'}, taught by an earlier run" in spc, spc
    assert f"TEACHFPR = '{sp['teach_fingerprint']}'" in spc, spc
    run("estimate", str(c / "sci_m.fits"), str(c / "sp.fits"), "-o", str(c / "halo.fits"))
    out = run("pupil", str(c / "halo.fits"), "-o", str(c / "pupil.fits"), "--truth", str(s / "truth.fits")).stdout
    # the pupil step on files from Python (run.h swfs_pupil_run, as the command line runs it)
    pf = sw.pupil_files(str(d / "halo.fits"), str(d / "pupil.fits"), truth=str(s / "truth.fits"))
    assert pf["halo"] == str(d / "halo.fits") and pf["explained"] is None and pf["err"] == err
    assert f"error {pf['err'] * 1e9:.1f} nm rms".encode() in out
    # the error with the AO residual's time mean left in (the halo's RESMEAN), from the same fit
    assert pf["err_kept"] > 0 and f"error {pf['err_kept'] * 1e9:.1f} nm rms with the AO residual mean".encode() in out
    np.testing.assert_array_equal(pf["pupil"].wfe, p.wfe)
    for f, ext in [("sci.fits", None), ("sci_m.fits", None), ("sp.fits", None), ("sp.fits", "RESMEAN"),
                   ("halo.fits", "HALO"), ("halo.fits", "GAIN"), ("pupil.fits", "WFE"), ("pupil.fits", "FIELD")]:
        np.testing.assert_array_equal(sw.read_fits(str(d / f), ext)[0], sw.read_fits(str(c / f), ext)[0],
                                      err_msg=f"{f} {ext}")
    # a mask of another grid: refused by name, nothing written
    with pytest.raises(sw.Error, match="dark.fits: pupil mask is"):
        sw.pupil_files(str(d / "halo.fits"), str(d / "p2.fits"), mask=str(s / "dark.fits"))
    assert not os.path.exists(d / "p2.fits")


def test_wfs_rate_speckles_equal_the_cli(series, cli, tmp_path):
    """speckles(wfs_rate=True) is `speckles --wfs-rate`: one field per WFS frame, the tip-tilt
    removed per frame by default (the run's rule, run.h), FRAMEDT = 1/WFSRATE; the same cube
    to the bit. The exposure mean asked for by name, or match, is refused."""
    s = series / "sim"
    raws = [str(s / f"raw_{k:03d}.fits") for k in range(3)]
    sw.reduce(raws, str(tmp_path / "sci.fits"), dark=str(s / "dark.fits"), flat=str(s / "flat.fits"))
    sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(tmp_path / "timing.txt"))
    args = (str(tmp_path / "timing.txt"), str(tmp_path / "sci.fits"), str(s / "actuators.fits"))
    r = sw.speckles(*args, str(tmp_path / "wr.fits"), recon="vk", wfs_rate=True)
    subprocess.run([cli, "speckles", args[0], "--science", args[1], "--actuators", args[2], "--recon", "vk",
                    "--wfs-rate", "-o", str(tmp_path / "wr_cli.fits")], check=True, capture_output=True)
    a, b = sw.read_fits(str(tmp_path / "wr.fits"))[0], sw.read_fits(str(tmp_path / "wr_cli.fits"))[0]
    assert a.shape[0] == r["nout"] and r["nout"] > 6 * 118
    np.testing.assert_array_equal(a, b)
    k = sw.read_keys(str(tmp_path / "wr.fits"), ["TIPTILT", "FRAMEDT"])
    assert k["TIPTILT"].strip() == "frame" and abs(float(k["FRAMEDT"]) * r["wfs_hz"] - 1) < 1e-12
    with pytest.raises(ValueError, match="'exposure' does not apply"):
        sw.speckles(*args, str(tmp_path / "x.fits"), recon="vk", wfs_rate=True, tiptilt="exposure")
    with pytest.raises(ValueError, match="does not apply with wfs_rate"):
        sw.speckles(*args, str(tmp_path / "x.fits"), recon="vk", wfs_rate=True,
                    match=[(args[1], str(tmp_path / "m.fits"))])
    assert not os.path.exists(tmp_path / "x.fits")


def test_errors_leave_nothing(series, tmp_path):
    s = series / "sim"
    with pytest.raises(sw.Error, match="nofile.fits"):
        sw.reduce(str(tmp_path / "nofile.fits"), str(tmp_path / "sci.fits"))
    assert not os.path.exists(tmp_path / "sci.fits")
    sw.reduce([str(s / "raw_000.fits"), str(s / "raw_001.fits"), str(s / "raw_002.fits")], str(tmp_path / "sci.fits"),
              dark=str(s / "dark.fits"), flat=str(s / "flat.fits"))
    # A ratio range without the true ratio (6.48): refused, no table.
    with pytest.raises(sw.Error, match="nowhere in the search"):
        sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(tmp_path / "t.txt"), ratio=(2, 4))
    assert not os.path.exists(tmp_path / "t.txt")
    with pytest.raises(ValueError, match="least ratio must be > 0"):
        sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(tmp_path / "t.txt"), ratio=(0, 8))
    # A log naming a telemetry file that is gone: its cube left out (rows marked missing);
    # every file gone: refused, no table.
    lines = (s / "handshake.log").read_text().splitlines()
    cubes = [k for k, ln in enumerate(lines) if ln and not ln.startswith("#")]
    gone = list(lines)
    f = gone[cubes[-1]].split()
    gone[cubes[-1]] = " ".join([f[0], "gone.fits", f[2]])
    (s / "handshake_gone.log").write_text("\n".join(gone) + "\n")
    t = sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake_gone.log"), str(tmp_path / "t.txt"))
    assert t["nmissing"] == 1 and t["nexp_missing"] == 40 and "gone.fits: no such telemetry file" in t["missing_reason"]
    assert t["nexp_ok"] <= 80 and " missing\n" in (tmp_path / "t.txt").read_text()
    for k in cubes:
        f = gone[k].split()
        gone[k] = " ".join([f[0], "gone.fits", f[2]])
    (s / "handshake_gone.log").write_text("\n".join(gone) + "\n")
    os.remove(tmp_path / "t.txt")
    with pytest.raises(sw.Error, match="no telemetry file of the 3 cubes can be read"):
        sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake_gone.log"), str(tmp_path / "t.txt"))
    assert not os.path.exists(tmp_path / "t.txt")
    sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(tmp_path / "t.txt"))
    with pytest.raises(sw.Error, match="noact.fits: cannot open"):
        sw.speckles(str(tmp_path / "t.txt"), str(tmp_path / "sci.fits"), str(tmp_path / "noact.fits"),
                    str(tmp_path / "sp.fits"))
    assert not os.path.exists(tmp_path / "sp.fits")
    # Options out of range get the command line's message from the library's check (run.h
    # swfs_speckles_run_options_check), before any file is opened.
    for kw, msg in [({"teach_loops": 1}, "--teach-loops must be 2..64, got 1"),
                    ({"recon": "vk", "teach_seed": 7}, "--teach-work, --teach-seed, --teach-again and --teach-set go with"),
                    ({"recon": "vk", "teach_again": True}, "--teach-again and --teach-set go with --recon teach"),
                    ({"recon": "vk", "teach_keys": {"dm_coupling": 0.15}}, "--teach-set go with --recon teach"),
                    ({"teach_keys": {"bogus_key": 1}}, "--teach-set: unknown setting 'bogus_key'"),
                    ({"teach_keys": {"dm_coupling": 1.5}}, r"dm_coupling=1.5: must be in \[0, 1\)"),
                    ({"wfs_hz": 1000.0, "wfs_rate": True, "match": [("a.fits", "b.fits")]}, "does not apply")]:
        with pytest.raises((sw.Error, ValueError), match=msg) as e:
            sw.speckles(str(tmp_path / "t.txt"), str(tmp_path / "sci.fits"), str(s / "actuators.fits"),
                        str(tmp_path / "sp.fits"), **kw)
        if "teach" in msg:
            assert e.value.status_name == "SWFS_ERR_ARG"
    assert not os.path.exists(tmp_path / "sp.fits")


def test_boundary_check_on_telemetry(series):
    """sync's own check of a file boundary, from Python: the simulated loop's slopes cut into
    two files (contiguous), with a frame lost, with one repeated; and its errors."""
    slopes = sw.read_fits(str(series / "sim" / "slopes_000.fits"))[0]
    k, cut = sw.realdata._lib.SYNC_EDGE_FRAMES, 500
    tail = slopes[cut - k:cut]
    b = sw.boundary_check(tail, slopes[cut:cut + k])
    assert b["verdict"] == 1 and b["q"] < b["q2_min"] and b["n1"] == 2 * (k - 1) and b["n2"] == 2 * (k - 2)
    assert b["window"] == 0 and np.isnan(b["p_lost"])  # decided by the one-frame steps: no second stage
    # Where one-frame steps cannot tell (white noise of ten times the step added), the second
    # stage's means of a few frames either side; it never says "not contiguous".
    noisy = slopes + 10 * np.sqrt(np.mean(np.diff(slopes, axis=0) ** 2)) * np.random.default_rng(1).standard_normal(slopes.shape)
    b = sw.boundary_check(noisy[cut - k:cut], noisy[cut:cut + k])
    assert b["verdict"] in (0, 1) and (b["window"] == 0 or 0 <= b["p_lost"] <= 1)
    assert sw.boundary_check(tail, slopes[cut + 1:cut + 1 + k])["verdict"] == -1
    assert sw.boundary_check(tail, slopes[cut - 1:cut - 1 + k])["verdict"] == -1
    with pytest.raises(ValueError, match="same nvals"):
        sw.boundary_check(tail, slopes[cut:cut + k, :10])
    # The count of frames lost or repeated that sync takes from the camera, against the telemetry.
    g = sw.boundary_gap(tail, slopes[cut + 1:cut + 1 + k], 1)
    assert g["separable"] and g["consistent"] and g["qk_min"] <= g["q"] <= g["qk_max"] < g["qfar_min"]
    assert sw.boundary_gap(tail, slopes[cut - 1:cut - 1 + k], -1)["consistent"]
    assert not sw.boundary_gap(tail, slopes[cut + 1:cut + 1 + k], -1)["consistent"]
    assert not sw.boundary_gap(tail, slopes[cut + 300:cut + 300 + k], 1)["consistent"]  # a long gap
    with pytest.raises(ValueError, match="not 0"):
        sw.boundary_gap(tail, slopes[cut:cut + k], 0)


def test_learn_reconstructor(series, tmp_path):
    """`specklewfs learn` from Python: a reconstructor learned from two simulated closed loops
    of the series' geometry (export_truth), used by speckles(recon=...); its errors."""
    keys = dict(screen_n=512, ncubes=2, cube_frames=40, cube_gap=60, export_truth=1)
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    dirs = []
    for k, (speed, seed) in enumerate([("10,15", 31), ("35,45", 32)]):
        d = tmp_path / f"train{k}"
        sw.simulate_timeseries(str(d), config=conf, layer_speed=speed, seed=seed, **keys)
        dirs.append(str(d))
    r = sw.learn(dirs, str(tmp_path / "W.fits"))
    assert r["nfiles"] == 2 and r["nact"] == 217 and r["nslopes"] == 288 and r["nslopes_seen"] == 224
    assert r["nframes"] > 2 * r["nslopes_seen"] and 0 < r["misfit_rms"] < r["truth_rms"]
    # each loop held out in turn: the other's map misses it by more than the training misfit
    assert r["nheldout"] == 2 and r["heldout_ratio"].shape == (2,) and np.all(np.isfinite(r["heldout_ratio"]))
    assert r["heldout_misfit_rms"] > r["misfit_rms"] and r["heldout_worst"] == r["heldout_ratio"].max()
    assert r["heldout_ratio"].min() > r["misfit_rms"] / r["truth_rms"]
    assert r["heldout_outputs"] == 217 and r["heldout_scaled_rms"] <= r["heldout_misfit_rms"]
    # the held-out check over the pupil's annulus (the actuators' positions from actuators.fits):
    # fewer outputs, the same map; the annulus's truth is not the all-actuator one
    ra = sw.learn(dirs, str(tmp_path / "Wa.fits"), curve_radius=(0.325, 3.25), mean_miss=False)
    assert 0 < ra["heldout_outputs"] < 217 and ra["heldout_truth_rms"] != r["heldout_truth_rms"]
    assert np.array_equal(sw.read_fits(str(tmp_path / "Wa.fits"))[0], sw.read_fits(str(tmp_path / "W.fits"))[0])
    assert sw.fits.read_keys(str(tmp_path / "Wa.fits"), ["LRNHOUT"])["LRNHOUT"] == ra["heldout_outputs"]
    # the truth taken as modal coefficients (piston kept), no held-out check: a control matrix
    rm = sw.learn(dirs, str(tmp_path / "Wm.fits"), modal=True, heldout=False, mean_miss=False)
    assert rm["nheldout"] == 0 and np.isnan(rm["heldout_misfit_rms"]) and np.all(np.isnan(rm["heldout_ratio"]))
    assert rm["meanmiss"] is None  # not asked for
    assert rm["truth_rms"] >= r["truth_rms"] and rm["nframes"] == r["nframes"]
    assert sw.fits.read_keys(str(tmp_path / "Wm.fits"), ["LRNMODAL"])["LRNMODAL"] == 1
    W = sw.read_fits(str(tmp_path / "W.fits"))[0]
    assert W.shape == (217, 288) and (np.abs(W).sum(0) == 0).sum() == 288 - 224
    # a prior map (learn --prior): the learned map itself, with a ridge that leaves the frames nothing
    # to move, comes back; a misfit no better than the least squares' own
    rp = sw.learn(dirs, str(tmp_path / "Wp.fits"), prior=str(tmp_path / "W.fits"), ridge=1e9, heldout=False,
                  mean_miss=False)
    Wp = sw.read_fits(str(tmp_path / "Wp.fits"))[0]
    assert np.abs(Wp - W).max() < 1e-6 * np.abs(W).max() and rp["misfit_rms"] >= r["misfit_rms"] * (1 - 1e-6)
    assert sw.fits.read_keys(str(tmp_path / "Wp.fits"), ["LRNPRIOR"])["LRNPRIOR"] == "W.fits"
    d, s = series, series / "sim"
    t = tmp_path / "timing.txt"
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(3)], str(tmp_path / "sci.fits"), dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(t))
    sp = sw.speckles(str(t), str(tmp_path / "sci.fits"), str(s / "actuators.fits"), str(tmp_path / "sp.fits"),
                     recon=str(tmp_path / "W.fits"))
    assert sp["nout"] >= 118
    # the map's miss of the residual's time mean: checked over the two loops (each against the
    # other's), written as MEANMISS only where the other's predicts it
    mm = r["meanmiss"]
    assert mm is not None and np.isfinite(mm["heldout"]) and mm["set_rms"] > 0
    try:
        sw.read_fits(str(tmp_path / "W.fits"), "MEANMISS")
        has = True
    except sw.Error:
        has = False
    assert has == mm["kept"] == (mm["heldout"] < 1) and (sp["meanmiss_rms"] > 0) == has
    # a map carrying one (a focus of 30 nm peak on the actuators): speckles adds it, through the
    # model's interpolation, to the residual's mean (RESMEAN), and says how much
    xy = sw.read_fits(str(s / "actuators.fits"))[0]  # (nact, 2): x, y per actuator
    rr = np.hypot(xy[:, 0], xy[:, 1]) / np.hypot(xy[:, 0], xy[:, 1]).max()
    c = 30e-9 * (2 * rr ** 2 - 1)
    sw.write_fits(str(tmp_path / "Wmm.fits"), {"W": W, "MEANMISS": (c - c.mean())[None, :]})
    spm = sw.speckles(str(t), str(tmp_path / "sci.fits"), str(s / "actuators.fits"), str(tmp_path / "spm.fits"),
                      recon=str(tmp_path / "Wmm.fits"))
    base = sw.read_fits(str(tmp_path / ("sp.fits" if not has else "spm.fits")), "RESMEAN")[0]
    diff = sw.read_fits(str(tmp_path / "spm.fits"), "RESMEAN")[0] - sw.read_fits(str(tmp_path / "sp.fits"), "RESMEAN")[0]
    inside = base != 0
    if not has:
        assert 5e-9 < spm["meanmiss_rms"] < 30e-9
        assert np.sqrt(np.mean(diff[inside] ** 2)) == pytest.approx(spm["meanmiss_rms"], rel=1e-3)
        n = diff.shape[0]
        yy, xx = (np.mgrid[:n, :n] - (n - 1) / 2)
        focus = (xx ** 2 + yy ** 2)[inside]
        assert np.corrcoef(diff[inside], focus)[0, 1] > 0.99
    # a space-time map: the slopes of frames t, t - 3 and t + 3; a cube of one map per lag that
    # fits its training frames better than the per-frame map, and that speckles applies
    rl = sw.learn(dirs, str(tmp_path / "Wl.fits"), lags=(0, -3, 3), heldout=False, perframe_out=str(tmp_path / "W1.fits"))
    assert rl["nslopes"] == 288 and rl["nslopes_seen"] == 3 * 224 and rl["misfit_rms"] < 0.99 * r["misfit_rms"]
    # with it, from the lag-0 block of the same sums, the per-frame map of the same frames: learn's
    W1 = sw.read_fits(str(tmp_path / "W1.fits"))[0]
    assert W1.shape == W.shape and np.abs(W1 - W).max() <= 1e-5 * np.abs(W).max()
    assert rl["perframe"]["misfit_rms"] == pytest.approx(r["misfit_rms"], rel=1e-6)
    assert rl["perframe"]["nslopes_seen"] == 224 and rl["perframe"]["nframes"] == r["nframes"]
    Wl = sw.read_fits(str(tmp_path / "Wl.fits"))[0]
    keys = sw.fits.read_keys(str(tmp_path / "Wl.fits"), ["NLAGS", "LAG1", "LAG2", "LAG3"])
    assert Wl.shape == (3, 217, 288) and [keys[k] for k in ("NLAGS", "LAG1", "LAG2", "LAG3")] == [3, 0, -3, 3]
    spl = sw.speckles(str(t), str(tmp_path / "sci.fits"), str(s / "actuators.fits"), str(tmp_path / "spl.fits"),
                      recon=str(tmp_path / "Wl.fits"))
    assert spl["nout"] == sp["nout"] and spl["info"]["nlags"] == 3 and spl["info"]["nslopes"] == 3 * 288
    # the training loops' wind (two winds: 10 and 35 m/s) in subapertures per frame, for the check in speckles
    assert rl["nwind"] == 2 and rl["wind_spread"] > 0 and np.hypot(*rl["wind_v"]) > 0
    keys = sw.fits.read_keys(str(tmp_path / "Wl.fits"), ["LRNVX", "LRNVY"])
    assert np.allclose((keys["LRNVX"], keys["LRNVY"]), rl["wind_v"])
    # its layers grouped over the two folders (10 and 35 m/s: two groups, a folder each), in the
    # map's keys; speckles matches the data's layers against them
    lay = rl["wind_layers"]
    assert len(lay) >= 2 and sum(L["nsets"] for L in lay) >= 2
    keys = sw.fits.read_keys(str(tmp_path / "Wl.fits"), ["LRNNLAY", "LRNL1X", "LRNL1Y", "LRNL1N"])
    assert keys["LRNNLAY"] == len(lay) and np.allclose((keys["LRNL1X"], keys["LRNL1Y"]), lay[0]["v"])
    assert keys["LRNL1N"] == lay[0]["nsets"]
    if spl["st_found"]:
        assert spl["st_train_nlayers"] == len(lay) and spl["st_obs_nlayers"] >= 1
        assert any(np.allclose(spl["st_train_v"], L["v"]) for L in lay)
    else:
        assert np.isnan(spl["st_mismatch"])
    # and the slopes' correlation at each lag (1 at lag 0), the loops' mean against the data's
    assert rl["corr"].shape == (3,) and rl["corr"][0] == pytest.approx(1.0) and np.all(rl["corr"][1:] < 1)
    assert np.allclose(spl["st_corr_train"], rl["corr"]) and spl["st_corr_obs"][0] == pytest.approx(1.0)
    with pytest.raises(sw.Error, match="no lag 0"):
        sw.learn(dirs, str(tmp_path / "W3.fits"), lags=(2, 4))
    assert not os.path.exists(tmp_path / "W3.fits")
    with pytest.raises(sw.Error, match="truewf_000.fits beside it"):
        sw.learn(str(s), str(tmp_path / "W2.fits"))
    assert not os.path.exists(tmp_path / "W2.fits")


def test_mean_miss_checked_on_a_metric(tmp_path):
    """learn(meanmiss_metric=M): the check of the folders' misses of the mean weighs a miss m as
    m^T M m. Six folders whose truth is a linear map of their slopes plus a time mean: on the
    first 20 outputs the same pattern in every folder (the sensor's own miss), on the last 10
    a large one of its own in each (a DM's actuators beyond the pupil, whose truth is the fit's
    extrapolation). Over all outputs the others' mean does not predict a folder's miss (held
    out >= 1: no MEANMISS); over the first 20 (M their projector) it does, to the folders'
    noise, and MEANMISS is the mean miss; a metric of another size is refused naming both."""
    rng = np.random.default_rng(5)
    ns, na, nf = 16, 30, 400
    W = rng.normal(size=(ns, na))
    shared = np.zeros(na)
    shared[:20] = rng.normal(size=20)
    shared -= shared.mean()
    dirs = []
    for d in range(6):
        s = rng.normal(size=(nf, ns))
        own = np.zeros(na)
        own[20:] = 30 * rng.normal(size=10)
        t = s @ W + shared + own + 0.05 * rng.normal(size=(nf, na))
        p = tmp_path / f"set_{d}"
        p.mkdir()
        sw.write_fits(str(p / "slopes_000.fits"), {"S": s})
        sw.write_fits(str(p / "truewf_000.fits"), {"T": t})
        dirs.append(str(p))
    r0 = sw.learn(dirs, str(tmp_path / "W0.fits"), heldout=False)
    assert r0["meanmiss"]["heldout"] >= 1 and not r0["meanmiss"]["kept"]
    M = np.zeros((na, na))
    M[:20, :20] = np.eye(20) - 1.0 / 20  # the first 20 outputs, their mean out
    r1 = sw.learn(dirs, str(tmp_path / "W1.fits"), heldout=False, meanmiss_metric=M)
    mm = r1["meanmiss"]
    assert mm["heldout"] < 0.1 and mm["kept"]
    got = sw.read_fits(str(tmp_path / "W1.fits"), "MEANMISS")[0].ravel()
    sh = shared[:20] - shared[:20].mean()
    g = got[:20] - got[:20].mean()
    assert np.sqrt(np.mean((g - sh) ** 2)) < 0.05 * np.sqrt(np.mean(sh ** 2))
    # set_rms in the metric's units: each folder's own miss is its pattern on the first 20
    assert mm["set_rms"] == pytest.approx(np.sqrt(sh @ sh), rel=0.1)
    with pytest.raises(sw.Error, match=r"metric is 29 x 29; the truth has 30 outputs"):
        sw.learn(dirs, str(tmp_path / "W2.fits"), heldout=False, meanmiss_metric=np.eye(29))
    assert not (tmp_path / "W2.fits").exists()
    with pytest.raises(ValueError, match="square"):
        sw.learn(dirs, str(tmp_path / "W3.fits"), meanmiss_metric=np.eye(30)[:5])
    # the pupil's metric from files (learn --mean-miss-over FUNCS,PUPIL): each function's piston,
    # tip and tilt out over the mask, the mask-weighted mean of their products
    n = 16
    funcs = rng.normal(size=(na, n, n))
    yy, xx = np.indices((n, n)) - (n - 1) / 2
    pupil = (np.hypot(xx, yy) < 7).astype(float) * (0.5 + 0.5 * (xx > 0))  # transmissions 0.5 and 1
    sw.write_fits(str(tmp_path / "funcs.fits"), funcs)
    sw.write_fits(str(tmp_path / "pupil.fits"), pupil)
    Mf = sw.meanmiss_metric(tmp_path / "funcs.fits", tmp_path / "pupil.fits")
    m = pupil > 0
    B = np.stack([np.ones(m.sum()), xx[m], yy[m]], 1)
    w = pupil[m]
    F = funcs[:, m].T
    F = F - B @ np.linalg.solve(B.T @ (w[:, None] * B), B.T @ (w[:, None] * F))
    want = F.T @ (w[:, None] * F) / w.sum()
    assert Mf.shape == (na, na) and np.abs(Mf - want).max() < 1e-12 * np.abs(want).max()
    funcs[3, 8, 5] = np.nan
    sw.write_fits(str(tmp_path / "fnan.fits"), funcs)
    with pytest.raises(sw.Error, match=r"fnan.fits: output 3's function at sample \(5, 8\) inside the pupil is not finite \(NaN or infinite\)"):
        sw.meanmiss_metric(tmp_path / "fnan.fits", tmp_path / "pupil.fits")
    sw.write_fits(str(tmp_path / "p8.fits"), pupil[:8, :8])
    with pytest.raises(sw.Error, match="p8.fits: pupil mask is 8x8x1 but the pupil grid is pupn x pupn = 16x16"):
        sw.meanmiss_metric(tmp_path / "funcs.fits", tmp_path / "p8.fits")


def test_teach(series, tmp_path):
    """`specklewfs teach` from Python: the series' layers, loops of its own system at them, the
    space-time map and its checks, and the choice; the chosen map goes through speckles."""
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    keys = dict(screen_n=512, ncubes=3, cube_frames=40, cube_gap=60, start_offset=50.4, wfs_file_frames=1000)
    s = series / "sim"
    files = sorted(str(p) for p in s.glob("slopes_0*.fits"))
    out = tmp_path / "T.fits"
    r = sw.teach(files, str(out), str(tmp_path / "work"), config=conf, loops=4, max_loops=6, **keys)
    assert 1 <= len(r["layers"]) <= 4 and r["nlayers_given"] == min(len(r["layers"]), 3) and r["nsub"] == 12
    vmax = max(L["speed"] for L in r["layers"][:r["nlayers_given"]])
    l1 = max(1, round(r["pitch"] * r["rate"] / (2 * vmax)))
    assert r["lags"] == [0, -l1, l1, -2 * l1, 2 * l1]
    assert r["chosen"] in ("spacetime", "perframe", "perframe_mixed") and 0 < r["st_misfit_rms"] < r["st_truth_rms"]
    warned = r["st_warn_wind"] or r["st_warn_corr"]
    assert warned == (r["chosen"] != "spacetime")
    # the space-time map's learning curve over the first 4 loops, on the grid's points in the
    # pupil; where it asks for more frames than they hold, more loops (here at most 6: the
    # suite's time), as many as it asks for, and the curve again over them all
    cf, per = r["curve_first"], r["curve_first"]["nframes"] / 4
    assert 0 < cf["outputs"] < r["out_points"] and cf["n"][0] < cf["n"][1] < cf["nframes"] and r["max_loops"] == 6
    assert all(m > 0 for m in cf["misfit_rms"])
    assert cf["b"] <= 0 or cf["a"] <= 0 or cf["excess"] == pytest.approx(cf["b"] / (cf["a"] * cf["nframes"]))
    # a curve that does not fall, or falls within twice the standard error its four parts'
    # own falls give, cannot tell: twice the loops (here the budget's 6), and the curve over
    # them (curve_doubled) is the last one measured
    assert math.isfinite(cf["fall_se"]) and cf["fall_se"] > 0
    fall = cf["misfit_rms"][0] ** 2 - cf["misfit_rms"][1] ** 2
    # a first curve that falls does not end teach either, nor ask for fewer than twice the
    # first loops (teach rule 2026-12-08): where it asks for at most 8 loops, or none, the loops
    # are doubled too (to the budget's 6)
    asks = math.inf if cf["frames"] is None else math.ceil(cf["frames"] / per) if cf["frames"] > cf["nframes"] else 4
    if not (cf["b"] > 0 and fall > 2 * cf["fall_se"]) or asks <= 8:
        assert r["st_loops"] == 6 and r["curve"]["nframes"] == pytest.approx(6 * per)
        assert r["curve_doubled"] == r["curve"]
        lcd = r["curve"]["excess"]  # the header's -1: a curve without a bound (an infinite excess)
        assert sw.fits.read_keys(str(out), ["TEACHLCD"])["TEACHLCD"] == pytest.approx(-1.0 if math.isinf(lcd) else lcd)
    else:  # it asks for more than 8: as many as it asks for, to the budget
        want = 6 if cf["frames"] is None else min(6, math.ceil(cf["frames"] / per))
        assert r["curve_doubled"] is None
        # the loops asked for are the last unless their own curve falls without a bound: then
        # the budget's 6
        if r["asked_loops"]:
            ca = r["curve_asked"]
            assert r["asked_loops"] == want < 6 and ca["nframes"] == pytest.approx(want * per)
            assert ca["b"] > 0 and ca["a"] <= 0 and ca["frames"] is None
            assert r["st_loops"] == 6 and r["curve"]["nframes"] == pytest.approx(6 * per)
            assert sw.fits.read_keys(str(out), ["TEACHASK"])["TEACHASK"] == want
        else:
            assert r["st_loops"] == want > 4 and r["curve"]["nframes"] == pytest.approx(want * per)
            assert r["curve_asked"] is None
    assert r["asked_loops"] == 0 or r["curve_asked"] is not None
    print(f"teach: learning curve over 4 loops: excess {cf['excess']:.3f}, {cf['frames']} frames asked; fall "
          f"{fall:.3g} m^2, {fall / cf['fall_se']:.2f} standard errors; {r['st_loops']} loops")
    assert sw.fits.read_keys(str(out), ["TEACHSTL"])["TEACHSTL"] == r["st_loops"]
    assert r["nloops"] == r["st_loops"] + (4 if r["chosen"] == "perframe_mixed" else 0)
    assert r["st_corr_obs"].shape == (5,) and r["st_corr_obs"][0] == pytest.approx(1.0)
    nl = sw.fits.read_keys(str(tmp_path / "work" / "spacetime.fits"), ["NLAGS"])["NLAGS"]
    assert nl == 5 and os.path.exists(out)
    hk = sw.fits.read_keys(str(out), ["TEACHSEL", "TEACHLOO", "TEACHWRN", "TEACHMOD", "TEACHMSR"])
    assert hk["TEACHSEL"] == r["chosen"] and hk["TEACHLOO"] == r["nloops"]
    # mmt-clio.conf gives ao_modes = 56: used as given, no calibration loop
    assert r["ao_modes"] == 56 and not r["modes_from_slopes"] and r["calibration"] == []
    assert hk["TEACHMOD"] == 56 and hk["TEACHMSR"] == "given"
    assert hk["TEACHWRN"] == int(r["st_warn_wind"]) + 2 * int(r["st_warn_corr"])
    # mmt-clio.conf gives slope_noise = 3e-8: used as given; the series' own, measured from its
    # slopes, is that (its simulation's) within 10 %
    assert r["slope_noise"] == 3e-8 and abs(r["noise_rms"] / 3e-8 - 1) < 0.1 and r["noise_cells"] > 60
    assert sw.fits.read_keys(str(out), ["TEACHSNO"])["TEACHSNO"] == pytest.approx(3e-8, rel=1e-12)
    # the map's output points: a grid of half the DM's pitch (its nearest-neighbour median
    # within 5 % of the layout's), written to the work folder and carried by the map (OUTXY)
    assert r["dm_pitch"] > 0 and abs(r["out_pitch"] / (0.5 * r["dm_pitch"]) - 1) < 0.05
    grid, _ = sw.read_fits(str(tmp_path / "work" / "outgrid.fits"))
    oxy, _ = sw.read_fits(str(out), ext="OUTXY")
    assert grid.shape == (r["out_points"], 2) and np.array_equal(oxy, grid) and r["out_points"] > 3 * 217
    assert sw.fits.read_keys(str(out), ["TEACHNOP"])["TEACHNOP"] == r["out_points"]
    t = tmp_path / "timing.txt"
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(3)], str(tmp_path / "sci.fits"), dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(t))
    sp = sw.speckles(str(t), str(tmp_path / "sci.fits"), str(s / "actuators.fits"), str(tmp_path / "sp.fits"),
                     recon=str(out))
    assert sp["nout"] >= 118 and sp["info"]["nlags"] == (5 if r["chosen"] == "spacetime" else 0)
    # speckles builds its model on the map's points and computes them within their band
    assert sp["info"]["nact"] == r["out_points"] and sp["info"]["out_pitch"] == pytest.approx(r["out_pitch"], rel=1e-12)
    assert sp["info"]["band"] == pytest.approx(6.5 / (2 * r["out_pitch"]), rel=1e-9)
    # a system of another geometry than the telemetry's is refused, naming the file; no map left
    with pytest.raises(sw.Error, match="slopes_000.fits: 288 slopes per WFS frame; the system's 16 x 16"):
        sw.teach(files, str(tmp_path / "bad.fits"), str(tmp_path / "badw"), config=conf, loops=2, nsub=16, **keys)
    assert not os.path.exists(tmp_path / "bad.fits")

    # a progress callback that raises once a loop is done stops teach there, its loops on both
    # workers: the exception comes out of the call; no map, no part file, fewer loops than asked
    def after_one(stage, done, total):
        if stage == "simulating the loops" and done >= 1:
            raise Enough(f"{done} of {total}")
    with pytest.raises(Enough, match="of 4"):
        sw.teach(files, str(tmp_path / "stopped.fits"), str(tmp_path / "sw"), config=conf, loops=4, progress=after_one,
                 **keys)
    assert not os.path.exists(tmp_path / "stopped.fits") and not list((tmp_path / "sw").rglob("*.part.*"))
    made = list((tmp_path / "sw").glob("loop_*"))
    assert 1 <= len(made) < 4 and all((d / "slopes_000.fits").exists() for d in made)
    # stopped within its first loops in a new work folder: the stopped loops' folders are gone,
    # not left empty
    with pytest.raises(Enough, match="0 of 4"):
        sw.teach(files, str(tmp_path / "stopped.fits"), str(tmp_path / "sw2"), config=conf, loops=4,
                 progress=_at_second_poll(), **keys)
    assert not list((tmp_path / "sw2").glob("loop_*"))
    # the same stop in the first run's work folder: its loops stay whole (a loop's earlier slopes
    # and truth go only once the new loop's files are in place)
    work = tmp_path / "work"
    loops = sorted(work.glob("loop_*"))
    assert len(loops) >= 4 and all((d / "slopes_000.fits").exists() for d in loops)
    with pytest.raises(Enough, match="0 of 4"):
        sw.teach(files, str(tmp_path / "again.fits"), str(work), config=conf, loops=4, progress=_at_second_poll(),
                 **keys)
    for d in loops:
        names = {f.name for f in d.iterdir()}
        assert {"slopes_000.fits", "truewf_000.fits", "truth.fits"} <= names, (d.name, sorted(names))


def test_mode_variance(series):
    """The loop's modal filter as its slopes show it (timeseries.h swfs_ts_mode_variance,
    swfs_mode_knee): the series' loop controls mmt-clio.conf's 56 modes; its profile's knee
    is there (within 15 %), the variances are finite, and another width is refused by name;
    and the slopes' time correlation along the upper modes (swfs_ts_mode_timecorr)."""
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    keys = dict(screen_n=512, ncubes=3, cube_frames=40, cube_gap=60, start_offset=50.4, wfs_file_frames=1000)
    s, _ = sw.read_fits(str(series / "sim" / "slopes_000.fits"))
    var, knee = sw.mode_variance(s, config=conf, **keys)
    assert var.ndim == 1 and var.shape[0] > 150 and np.all(np.isfinite(var)) and np.all(var >= 0)
    assert abs(knee - 56) <= 0.15 * 56
    with pytest.raises(sw.Error, match="2 nsub\\^2 = 288"):
        sw.mode_variance(s[:, :200], config=conf, **keys)
    # The used subapertures' slopes alone give the same profile: the full layout's unused
    # subapertures are 0, and the basis rows they meet are the ones dropped.
    used = np.flatnonzero(np.any(s != 0, axis=0))
    assert 0 < used.size < s.shape[1]
    var_v, knee_v = sw.mode_variance(np.ascontiguousarray(s[:, used]), config=conf, **keys)
    assert knee_v == knee and np.allclose(var_v, var, rtol=1e-9, atol=0)
    # the time correlation along the upper modes (teach's speed where no layer is tracked):
    # within [-1, 1], falling with the lag at first; the same from the used subapertures'
    # slopes; the frames in random order lose it (|rho| < 0.05); a lag beyond the frames refused
    rho = sw.mode_timecorr(s, [1, 2, 4, 8], config=conf, **keys)
    assert np.all(np.abs(rho) <= 1) and rho[0] > rho[1] > rho[2] and rho[0] > 0.5
    assert np.allclose(sw.mode_timecorr(np.ascontiguousarray(s[:, used]), [1, 2, 4, 8], config=conf, **keys), rho,
                       rtol=1e-9, atol=1e-12)
    shuffled = s[np.random.default_rng(5).permutation(s.shape[0])]
    assert np.all(np.abs(sw.mode_timecorr(shuffled, [1, 2, 4, 8], config=conf, **keys)) < 0.05)
    with pytest.raises(sw.Error, match="lag"):
        sw.mode_timecorr(s, [s.shape[0]], config=conf, **keys)
    print(f"mode time correlation at 1, 2, 4, 8 frames: {np.round(rho, 3)}")


def test_teach_coupling_from_cm(series, tmp_path):
    """teach given the series' own loop control matrix (ao_recon) and no dm_coupling: the DM's
    functions from that matrix (timeseries.h swfs_ts_coupling_from_recon); the series' DM is
    the interpolated surface, which the matrix says, and the map's TEACHCPL is 0. With
    dm_coupling given, nothing is taken from the matrix."""
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    keys = dict(screen_n=512, ncubes=3, cube_frames=40, cube_gap=60, start_offset=50.4, wfs_file_frames=1000)
    s = series / "sim"
    files = sorted(str(p) for p in s.glob("slopes_0*.fits"))
    out = tmp_path / "C.fits"
    r = sw.teach(files, str(out), str(tmp_path / "work"), config=conf, loops=2, max_loops=2,
                 ao_recon=str(s / "recon_ao.fits"), **keys)
    c = r["coupling"]
    assert c is not None and not c["gaussian"] and c["misfit_interp"] < 1e-3 and c["misfit"] > 5 * c["misfit_interp"]
    assert 0.02 <= c["coupling"] <= 0.8 and c["rank"] > 0
    assert sw.fits.read_keys(str(out), ["TEACHCPL"])["TEACHCPL"] == 0
    r = sw.teach(files, str(tmp_path / "D.fits"), str(tmp_path / "work2"), config=conf, loops=2, max_loops=2,
                 ao_recon=str(s / "recon_ao.fits"), dm_coupling=0.2, **keys)
    assert r["coupling"] is None


def test_teach_from_files(series, tmp_path):
    """teach with no description: the system from the observation's own files (the science
    cube's geometry, the DM's positions; nsub, rate and length from the telemetry), the modal
    filter from the slopes (the series' loop controls 56 modes)."""
    s = series / "sim"
    files = sorted(str(p) for p in s.glob("slopes_0*.fits"))
    sci = str(tmp_path / "sci.fits")
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(3)], sci, dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    out = tmp_path / "F.fits"
    r = sw.teach(files, str(out), str(tmp_path / "work"), loops=3, science=sci, actuators=str(s / "actuators.fits"))
    # three loops: too few parts for a learning curve (4), so no more loops whatever the budget
    assert r["curve_first"] is None and r["curve"] is None and r["st_loops"] == 3
    assert r["modes_from_slopes"] and abs(r["ao_modes"] - 56) <= 0.15 * 56 and r["knee_obs"] > 0
    assert 1 <= len(r["calibration"]) <= 4 and r["calibration"][0][0] == r["knee_obs"]
    # the modal loop's profile is the closer: the zonal loops' (one per cut) further off
    assert not r["zonal"] and len(r["misfit_zonal"]) == 6 and r["misfit_modal"] < min(r["misfit_zonal"])
    assert r["nsub"] == 12 and r["chosen"] in ("spacetime", "perframe", "perframe_mixed")
    # three loops as long as the series' file would hold fewer than 10 frames per input of
    # the map (5 lags x the 224 slopes used): lengthened to hold them
    assert r["map_inputs"] == 5 * 224 and r["loop_frames_described"] < 10 * r["map_inputs"] / 3
    assert r["loop_frames"] >= 10 * r["map_inputs"] / 3 > r["loop_frames"] - 3
    hk = sw.fits.read_keys(str(out), ["TEACHMOD", "TEACHMSR"])
    assert hk["TEACHMOD"] == r["ao_modes"] and hk["TEACHMSR"] == "slopes"
    # no slope_noise given: the loops' is the series' white slope noise, measured from its first
    # file's slopes (telemetry.slopes_white_noise), the simulation's 3e-8 within 10 %
    s0, _ = sw.read_fits(files[0])
    var, nc = sw.slopes_white_noise(s0, 12)
    assert r["slope_noise"] == r["noise_rms"] and r["noise_rms"] == pytest.approx(np.sqrt(var), rel=1e-12)
    assert nc == r["noise_cells"] and abs(r["noise_rms"] / 3e-8 - 1) < 0.1
    # the curl's whole power: the same white part, and above it the aliasing (the slopes'
    # effective noise), below the slopes' own variance
    white, total = sw.slopes_curl_noise(s0, 12)
    assert white == var and var < total < r["noise_rms"] ** 2 / r["noise_share"]
    # its share of the slopes' variance (tip-tilt removed): about 1 % on the matrix's noise
    assert 0.001 < r["noise_share"] < 0.05
    assert sw.fits.read_keys(str(out), ["TEACHNOI"])["TEACHNOI"] == pytest.approx(r["noise_rms"], rel=1e-12)
    with pytest.raises(sw.Error, match="not finite"):
        bad = np.array(s0[:100]); bad[5, 3] = np.nan
        sw.slopes_white_noise(bad, 12)
    assert os.path.exists(tmp_path / "work" / "modes.tsv")
    with pytest.raises(ValueError, match="needs both science and actuators"):
        sw.teach(files, str(tmp_path / "G.fits"), str(tmp_path / "w2"), science=sci)


def test_speckles_warns_of_a_mean_residual_no_loop_has(series, tmp_path):
    """A given reconstructor that amplifies a slope pattern the model's D does not make keeps
    its gain on D (the gain check passes) but makes the reconstructed residual's time mean
    larger than the wavelength, which no closed loop's is: speckles() says so (RuntimeWarning,
    resmean_rms > wavelen); the default reconstructor's mean on the same data stays far below."""
    s = series / "sim"
    sci, timing = str(tmp_path / "sci.fits"), str(tmp_path / "timing.txt")
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(3)], sci, dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    sw.sync(sci, str(s / "handshake.log"), timing)
    act = str(s / "actuators.fits")
    w0 = str(tmp_path / "vk.fits")
    sp = sw.speckles(timing, sci, act, str(tmp_path / "sp0.fits"), write_recon=w0, recon="vk")
    assert 0 < sp["resmean_rms"] < 0.1 * sp["wavelen"]
    W = np.array(sw.read_fits(w0)[0])
    xy = np.array(sw.read_fits(act)[0])
    _, g = sw.read_fits(sci)
    mask = sw.aperture(g.pupn, g.pupdx, g.teldiam, g.obscur)
    D = sw.SpeckleModel(xy, mask, g.pupdx, g.teldiam, 12).interaction_matrix()
    assert D.shape == (W.shape[1], W.shape[0])
    # a slope pattern of the used subapertures orthogonal to everything D makes
    rows = np.flatnonzero(np.linalg.norm(D, axis=1) > 0)
    U, S, _ = np.linalg.svd(D[rows], full_matrices=True)
    assert np.sum(S > 1e-10 * S[0]) < rows.size
    v = np.zeros(D.shape[0])
    v[rows] = U[:, -1]
    assert np.abs(v @ D).max() < 1e-10 * np.abs(D).max()
    slopes = np.concatenate([np.array(sw.read_fits(str(f))[0]) for f in sorted(s.glob("slopes_0*.fits"))])
    c = abs(v @ slopes.mean(axis=0))
    u = np.random.default_rng(3).standard_normal(W.shape[0])
    Wb = W + (1e-3 / c) * np.outer(u, v)  # about 1 mm of mean residual on the actuators
    wb = str(tmp_path / "amplifies.fits")
    sw.write_fits(wb, Wb)
    with pytest.warns(RuntimeWarning, match="more than the wavelength"):
        bad = sw.speckles(timing, sci, act, str(tmp_path / "sp1.fits"), recon=wb)
    assert bad["resmean_rms"] > bad["wavelen"] > 0
    assert 0.5 <= bad["info"]["recon_gain"] <= 2
    print(f"default mean {sp['resmean_rms'] * 1e9:.1f} nm, amplifying map {bad['resmean_rms'] * 1e9:.0f} nm, "
          f"wavelength {bad['wavelen'] * 1e9:.0f} nm, gain {bad['info']['recon_gain']:.3f}")


def _series_copy(series, tmp_path, name, change):
    """The CI series' reduced cubes and timing, its slopes rewritten by change(data, rate) ->
    (data, keys) into tmp_path/name: (timing, science, actuators)."""
    s = series / "sim"
    sci, timing = str(tmp_path / "sci.fits"), str(tmp_path / "timing.txt")
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(3)], sci, dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    sw.sync(sci, str(s / "handshake.log"), timing)
    sh = tmp_path / name
    sh.mkdir()
    for f in sorted(s.glob("slopes_0*.fits")):
        data = np.array(sw.read_fits(str(f))[0])
        rate = sw.fits.read_keys(str(f), ["WFSRATE"])["WFSRATE"]
        data, keys = change(data, rate)
        sw.write_fits(str(sh / f.name), data, keys=keys)
    text = open(timing).read()
    assert str(s) in text
    with open(tmp_path / f"timing_{name}.txt", "w") as t:
        t.write(text.replace(str(s), str(sh)))
    return str(tmp_path / f"timing_{name}.txt"), sci, str(s / "actuators.fits")


def test_speckles_teaches_from_the_prior_without_a_frozen_flow_layer(series, tmp_path):
    """Slopes whose frames are shuffled in time show no frozen-flow layer: speckles' default
    teaches its map from loops at the speed the slopes' time correlation gives and takes their
    space-time map at lags of 1 and 2 frames (chosen "spacetime_prior", no layer given), without
    a warning; the map's
    header says so. Shuffled frames decorrelate at once, so the speed is the calibration
    loops' fastest (64 m/s, where the grid stops), well above any frozen-flow series'."""
    rng = np.random.default_rng(3)
    timing, sci, act = _series_copy(series, tmp_path, "shuffled",
                                    lambda d, rate: (d[rng.permutation(d.shape[0])], {"WFSRATE": rate}))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        # 4 loops and no more: for the lags' five times the inputs the learning curve asks for
        # 16 (21 s against 13 here); the DM told, the series' own interpolated surface, so one
        # map is taught, not the DM choice's two (test_speckles_keeps_the_gaussian_dm_map's subject)
        sp = sw.speckles(timing, sci, act, str(tmp_path / "sp.fits"), teach_loops=4, teach_max_loops=4,
                         teach_keys={"dm_coupling": 0})
    assert sp["taught"] and sp["teach"]["chosen"] == "spacetime_prior" and sp["teach"]["nloops"] >= 4
    assert list(sp["teach"]["lags"]) == [0, -1, 1, -2, 2]
    keys = sw.fits.read_keys(sp["teach_map"], ["TEACHSEL", "TEACHLAY", "TEACHLOO", "TEACHPSP"])
    assert keys["TEACHSEL"] == "spacetime_prior" and keys["TEACHLAY"] == 0 and keys["TEACHLOO"] == sp["teach"]["nloops"]
    assert keys["TEACHPSP"] > 32


def test_speckles_falls_back_where_no_map_can_be_taught(series, tmp_path):
    """Slopes whose files carry no WFS frame rate (no WFSRATE) give teach no rate for its loops,
    so speckles' default (a map taught for the observation) cannot teach one: speckles() says
    why (RuntimeWarning, taught False, teach_fallback) and uses the von Karman map: the same
    speckles as recon='vk'."""
    timing, sci, act = _series_copy(series, tmp_path, "norate", lambda d, rate: (d, None))
    with pytest.warns(RuntimeWarning, match="no map could be taught for this observation .*WFSRATE"):
        sp = sw.speckles(timing, sci, act, str(tmp_path / "sp.fits"))
    assert not sp["taught"] and "WFSRATE" in sp["teach_fallback"] and "teach" not in sp
    vk = sw.speckles(timing, sci, act, str(tmp_path / "sp_vk.fits"), recon="vk")
    assert vk["nout"] == sp["nout"] and "taught" not in vk
    np.testing.assert_array_equal(sw.read_fits(str(tmp_path / "sp.fits"))[0], sw.read_fits(str(tmp_path / "sp_vk.fits"))[0])


def test_a_stop_while_teaching_is_no_fallback(series, tmp_path):
    """A progress callback that stops speckles while its default teaches the map ends the run:
    no fallback to the von Karman map, no speckle cube (a map that cannot be taught falls back,
    test_speckles_falls_back_where_no_map_can_be_taught; a request to stop is not one)."""
    timing, sci, act = _series_copy(series, tmp_path, "stop", lambda d, rate: (d, {"WFSRATE": rate}))

    def at_loops(stage, done, total):
        if stage.startswith("simulating"):
            raise Enough(stage)
    with pytest.raises(Enough, match="simulating"):
        sw.speckles(timing, sci, act, str(tmp_path / "sp.fits"), teach_loops=2, teach_max_loops=2, progress=at_loops)
    assert not os.path.exists(tmp_path / "sp.fits")


def test_milk_logs_stream_equals_the_cli(tmp_path, cli):
    """milk/cacao logs from Python: reduce of the camera's logs (STAMPS), sync_wfs_log (the
    clock file: drift and offset near the simulated ones, the drops counted) and stream_files
    over the WFS logs give the command line's clock and halo; the time-stamped path's NCP
    error within 10 % of the handshake path's through stream_files with the timing table."""
    d, s = tmp_path, tmp_path / "sim"
    sw.simulate_timeseries(str(s), pupn=66, pupdx=0.1, screen_n=1024, ncubes=4, cube_frames=50, cube_gap=1500,
                           layer_speed=[30, 40], vib_amp=0.6, jitter_amp=0.15, seed=1, milk=1, milk_file_frames=2000)
    truth = dict(line.split()[:2] for line in open(s / "milk" / "truth.txt") if line.strip() and line[0] != "#")
    raws = sorted(str(p) for p in s.glob("raw_*.fits"))
    cams = sorted(str(p) for p in (s / "milk" / "cam").glob("*.fits"))
    cal = dict(dark=str(s / "dark.fits"), flat=str(s / "flat.fits"))
    sw.reduce(raws, str(d / "sci.fits"), **cal)
    sw.sync(str(d / "sci.fits"), str(s / "handshake.log"), str(d / "timing.txt"), ratio=(5, 8))
    sw.speckles(str(d / "timing.txt"), str(d / "sci.fits"), str(s / "actuators.fits"), str(d / "sp.fits"), recon="vk",
                write_recon=str(d / "recon.fits"))
    rm = sw.reduce(cams, str(d / "sci_milk.fits"), **cal)
    assert rm["stamped"] and rm["dropped"] == int(truth["cam_dropped"])
    wfs = str(s / "milk" / "wfs")
    c = sw.sync_wfs_log(str(d / "sci_milk.fits"), wfs, str(d / "clock.txt"))
    assert c["epoch"] == round(float(truth["epoch"]) * 1e9)
    assert abs(c["drift"] - float(truth["drift"])) <= 2e-5 and abs(c["offset"] - float(truth["offset"])) <= 3e-4
    assert c["wfs_dropped"] == int(truth["wfs_dropped"]) and c["nsegments"] == 4
    model = dict(recon=str(d / "recon.fits"), actuators=str(s / "actuators.fits"))
    m = sw.stream_files(str(d / "sci_milk.fits"), str(d / "halo_milk.fits"), wfs_log=wfs, clock=str(d / "clock.txt"),
                        **model)
    assert m["stamped"] and m["stamps"]["camera_dropped_log"] == int(truth["cam_dropped"])
    assert m["stamps"]["wfs_dropped_log"] == int(truth["wfs_dropped"]) and m["camera_frames"] > 150
    seen = []
    n = sw.stream_files(str(d / "sci.fits"), str(d / "halo_native.fits"), timing=str(d / "timing.txt"),
                        progress=lambda *a: seen.append(a), **model)
    assert not n["stamped"] and n["stamps"] is None and n["camera_frames"] > 150
    # progress: the camera frames after every batch (at most 128, within a cube), of the
    # timing table's usable frames
    assert seen[-1] == ("camera frames", n["camera_frames"], n["camera_frames"]) and 0 < seen[0][1] < seen[1][1]
    # a progress callback that raises at the second batch stops the run; the update written
    # after the first (every=1) is removed with it, and the exception comes out
    def two(stage, done, total):
        if done > seen[0][1]:
            assert os.path.exists(d / "halo_stop.fits")  # the first batch's update, in place
            raise Enough(f"{stage} {done} of {total}")
    with pytest.raises(Enough, match=f"camera frames {seen[1][1]} of {n['camera_frames']}"):
        sw.stream_files(str(d / "sci.fits"), str(d / "halo_stop.fits"), timing=str(d / "timing.txt"), every=1,
                        progress=two, **model)
    assert not os.path.exists(d / "halo_stop.fits")
    # the same stop in a run over an earlier run's products (the halo, its pupil and checkpoint):
    # those are put back as they were, byte for byte, not removed with the run's own updates
    prod = {k: d / f"prev_{k}.fits" for k in ("halo", "pupil", "ck")}
    sw.stream_files(str(d / "sci.fits"), str(prod["halo"]), timing=str(d / "timing.txt"), pupil_out=str(prod["pupil"]),
                    checkpoint=str(prod["ck"]), **model)
    before = {k: p.read_bytes() for k, p in prod.items()}

    def two_over(stage, done, total):
        if done > seen[0][1]:
            assert prod["halo"].read_bytes() != before["halo"]  # the first batch's update, in place
            raise Enough(f"{stage} {done} of {total}")
    with pytest.raises(Enough):
        sw.stream_files(str(d / "sci.fits"), str(prod["halo"]), timing=str(d / "timing.txt"), every=1,
                        pupil_out=str(prod["pupil"]), checkpoint=str(prod["ck"]), progress=two_over, **model)
    assert {k: p.read_bytes() for k, p in prod.items()} == before and not list(d.glob("prev_*.prev.*"))
    # stopped before its first update (the kept links are the same files: they went too), and
    # over a link name an earlier run killed outright left (the next free name is taken)
    (d / f"prev_halo.fits.prev.{os.getpid()}.0").write_text("left by a run killed outright")

    def at_first(stage, done, total):
        raise Enough(stage)
    with pytest.raises(Enough):
        sw.stream_files(str(d / "sci.fits"), str(prod["halo"]), timing=str(d / "timing.txt"), every=1,
                        pupil_out=str(prod["pupil"]), checkpoint=str(prod["ck"]), progress=at_first, **model)
    assert {k: p.read_bytes() for k, p in prod.items()} == before
    assert [p.name for p in d.glob("prev_*.prev.*")] == [f"prev_halo.fits.prev.{os.getpid()}.0"]
    # replay's progress, every 1024 frames published (WFS and camera): an exception there stops it
    (d / "shm").mkdir()

    def at_once(stage, done, total):
        raise Enough(f"{stage} {done} of {total}")
    with pytest.raises(Enough, match="frames 1024 of "):
        sw.replay(str(d / "sci.fits"), timing=str(d / "timing.txt"), shm_dir=str(d / "shm"), speed=50, remove=True,
                  progress=at_once)
    # the command line on the same files: the same clock and the same halo
    run = lambda *a: subprocess.run([cli, *a], check=True, capture_output=True)  # noqa: E731
    run("sync", "--wfs-log", wfs, str(d / "sci_milk.fits"), "-o", str(d / "clock_cli.txt"))
    keep = lambda p: [x for x in open(p) if x.split()[:1] in (["epoch"], ["offset"], ["drift"], ["pairing"])]  # noqa
    assert keep(d / "clock.txt") == keep(d / "clock_cli.txt") and len(keep(d / "clock.txt")) == 4
    run("stream", "--wfs-log", wfs, "--clock", str(d / "clock.txt"), "--science", str(d / "sci_milk.fits"),
        "--recon", model["recon"], "--actuators", model["actuators"], "-o", str(d / "halo_cli.fits"))
    for ext in ("HALO", "GAIN", "MEAN_SP"):
        np.testing.assert_array_equal(sw.read_fits(str(d / "halo_milk.fits"), ext)[0],
                                      sw.read_fits(str(d / "halo_cli.fits"), ext)[0], err_msg=ext)
    ncp = sw.read_fits(str(s / "truth.fits"), "NCP")[0]
    err = {}
    for k in ("milk", "native"):
        h = sw.Halo.read(str(d / f"halo_{k}.fits"))
        p = sw.pupil_estimate(h, sw.read_geom(str(d / f"halo_{k}.fits")))
        err[k] = sw.wfe_compare(p.wfe, ncp, p.mask)[0]
    print(f"NCP error: milk logs {err['milk'] * 1e9:.1f} nm, timing table {err['native'] * 1e9:.1f} nm")
    assert 0 < err["native"] < 35e-9 and err["milk"] <= 1.1 * err["native"]
    # bad input: one of the two inputs, a clock without logs, a log that is not there
    with pytest.raises(ValueError, match="one of them"):
        sw.stream_files(str(d / "sci.fits"), str(d / "x.fits"), timing=str(d / "timing.txt"), wfs_log=wfs, **model)
    with pytest.raises(ValueError, match="clock goes with wfs_log"):
        sw.stream_files(str(d / "sci.fits"), str(d / "x.fits"), timing=str(d / "timing.txt"), clock="c.txt", **model)
    with pytest.raises(sw.Error, match="nowhere"):
        sw.stream_files(str(d / "sci_milk.fits"), str(d / "x.fits"), wfs_log=str(d / "nowhere"), **model)
    assert not os.path.exists(d / "x.fits")


def test_speckles_keeps_the_gaussian_dm_map(tmp_path):
    """The series of test_path_on_files_equals_the_cli made with a DM of Gaussian functions
    (dm_coupling=0.15, which the files do not say): speckles' second map, its loops' DM
    Gaussian, follows the science frames better and is kept (write_recon writes it), and its NCP
    error is below that of the map not kept (the interpolated surface's, given as recon=)."""
    keys = dict(screen_n=512, ncubes=3, cube_frames=40, cube_gap=60, start_offset=50.4, wfs_file_frames=1000,
                dm_coupling=0.15)
    s = tmp_path / "sim"
    sw.simulate_timeseries(str(s), config=os.path.join(ROOT, "config", "mmt-clio.conf"), **keys)
    raws = [str(s / f"raw_{k:03d}.fits") for k in range(3)]
    sw.reduce(raws, str(tmp_path / "sci.fits"), dark=str(s / "dark.fits"), flat=str(s / "flat.fits"))
    sw.sync(str(tmp_path / "sci.fits"), str(s / "handshake.log"), str(tmp_path / "timing.txt"))
    truth = sw.read_fits(str(s / "truth.fits"), "NCP")[0]
    args = (str(tmp_path / "timing.txt"), str(tmp_path / "sci.fits"), str(s / "actuators.fits"))
    sp = sw.speckles(*args, str(tmp_path / "sp_choice.fits"), teach_max_loops=12,
                     match=[(str(tmp_path / "sci.fits"), str(tmp_path / "sci_choice.fits"))],
                     write_recon=str(tmp_path / "recon_choice.fits"))
    dm = sp["dm_choice"]
    print(f"the loops' DM: surface {dm['corr']['surface']:.4f}, Gaussian {dm['corr']['gauss']:.4f}, per "
          f"pixel {dm['diff']:+.4f} +- {dm['diff_se']:.4f}")
    assert dm["gauss"] and dm["diff"] > 2 * dm["diff_se"] and dm["corr"]["gauss"] > dm["corr"]["surface"]
    assert sp["teach_map"] == str(tmp_path / "sp_choice.teach" / "dm-gauss" / "taught.fits")
    assert dm["other_map"] == str(tmp_path / "sp_choice.teach" / "taught.fits")
    assert sp["orient"]["corr"][(0, 1, 1)] == dm["corr"]["gauss"]
    # --write-recon writes the map kept, as the pipeline holds it (its form differs from the
    # taught file's by about 1 % of the largest value either way): far from the other one
    w = sw.read_fits(str(tmp_path / "recon_choice.fits"))[0]
    kept, other = sw.read_fits(sp["teach_map"])[0], sw.read_fits(dm["other_map"])[0]
    assert np.abs(w - kept).max() < 0.1 * np.abs(w - other).max()
    sw.speckles(*args, str(tmp_path / "sp_surface.fits"), recon=dm["other_map"],
                match=[(str(tmp_path / "sci.fits"), str(tmp_path / "sci_surface.fits"))])
    errs = {}
    for tag in ("choice", "surface"):
        h = sw.estimate_files(str(tmp_path / f"sci_{tag}.fits"), str(tmp_path / f"sp_{tag}.fits"),
                              str(tmp_path / f"halo_{tag}.fits"))
        p = sw.pupil_estimate(h, sw.read_geom(str(tmp_path / f"halo_{tag}.fits")))
        errs[tag] = sw.wfe_compare(p.wfe, truth, p.mask)[0]
    print(f"NCP error: the choice {errs['choice'] * 1e9:.1f} nm, the surface's map {errs['surface'] * 1e9:.1f} nm")
    assert errs["choice"] < errs["surface"]

"""The simulators, the paper's numbers through Python, and the same data set through the
command line and through Python giving identical products."""
import os
import re
import signal
import subprocess
import threading

import numpy as np
import pytest

import specklewfs as sw

from conftest import ROOT

SMALL = dict(screen_n=512, nscreens=2, pupn=64, teldiam=2.5, nfx=32, nfy=32, seed=3, threads=2)


def test_paper_default_path_through_python(paper_sim):
    """simulate -> camera -> Accumulator -> estimate -> pupil -> compare, piece by piece
    in Python: the demo's 15.6 nm NCP error at sigma = 0, seed 1."""
    s = paper_sim
    assert s.science.shape == (980, 60, 60) and s.speckles.shape == (980, 60, 60) and s.nframes == 980
    assert s.geom == sw.Geom(wavelen=3.8e-6, teldiam=6.5, obscur=0.1, pixscale=0.25, pupdx=0.04, pupn=163)
    assert round(s.ncp_rms * 1e9, 1) == 105.5 and round(s.residual_rms * 1e9, 1) == 249.8
    assert s.params["seed"] == 1 and s.params["nfx"] == 60 and s.params["screen"]["n"] == 2048
    gain = s.params["gain"]
    noisy = s.camera(read_noise=0.0, gain=gain, seed=1 * 1000003 + 0)  # the demo's camera stream
    h = sw.Accumulator(60, 60).add(noisy, s.speckles).estimate(read_noise=0.0, gain=gain)
    assert round(100 * h.valid_fraction, 1) == 98.2
    p = sw.pupil_estimate(h, s.geom, mask=s.pupil, method="moments")
    assert p.method == "moments" and p.halo_fit is None
    err, truth_p, truth_ptt = sw.wfe_compare(p.wfe, s.ncp, s.pupil)
    assert round(err * 1e9, 1) == 15.6
    assert round(truth_ptt * 1e9, 1) == 91.2
    # The default: the joint fit of the regression statistics the accumulator also kept.
    pf = sw.pupil_estimate(h, s.geom, mask=s.pupil)
    assert pf.method == "fit" and 0 <= pf.kappa < 0.1 and pf.halo_fit.shape == (60, 60)
    assert sw.wfe_compare(pf.wfe, s.ncp, s.pupil)[0] < 9e-9
    # The fit's radial log g terms (6 on this window at 3 lambda/D); g_radial=0 the Legendre
    # terms alone: the same NCP error within 0.2 nm on this case (docs/estimator.md)
    pf0 = sw.pupil_estimate(h, s.geom, mask=s.pupil, g_radial=0)
    assert pf.fit_nparams - pf0.fit_nparams == 6
    assert abs(sw.wfe_compare(pf0.wfe, s.ncp, s.pupil)[0] - sw.wfe_compare(pf.wfe, s.ncp, s.pupil)[0]) < 0.2e-9
    with pytest.raises(ValueError, match="g_radial applies to the fit"):
        sw.pupil_estimate(h, s.geom, mask=s.pupil, method="moments", g_radial=3)
    with pytest.raises(ValueError, match="g_radial must be >= 0"):
        sw.pupil_estimate(h, s.geom, mask=s.pupil, g_radial=-1)
    # The self-check per pixel: its median is the median pixel's; by ring it is the median
    # of each ring [k, k + 1) lambda/D (the exact speckles of the simulation explain most).
    m = pf.explained_map
    assert m.shape == (60, 60) and abs(np.nanmedian(m) - pf.explained_median) < 1e-12
    rings = pf.explained_rings()
    assert len(rings) == 8  # 60 pixels of 0.25 lambda/D: 7.5 lambda/D to the edge
    y, x = np.mgrid[0:60, 0:60]
    r = np.hypot(x - 30, y - 30) * 0.25
    for k in range(8):
        ring = m[(r >= k) & (r < k + 1)]
        assert abs(rings[k] - np.nanmedian(ring)) < 1e-12
    assert np.nanmin(rings[1:]) > 0.5
    assert p.explained_map is None and p.explained_rings() is None  # the moments have no self-check
    # The paper's formulae (per-pixel g, HALO_LF, full weight): 15.7.
    hp = sw.Accumulator(60, 60).add(noisy, s.speckles).estimate(read_noise=0.0, gain=gain, g_smooth=0)
    pp = sw.pupil_estimate(hp, s.geom, mask=s.pupil, weight="none", method="moments")
    assert round(sw.wfe_compare(pp.wfe, s.ncp, s.pupil)[0] * 1e9, 1) == 15.7


def test_demo_table_equals_python_recovery(paper_sim, cli, tmp_path):
    """`specklewfs demo` prints the same table as SimResult.recovery at every level."""
    out = subprocess.run([cli, "demo", "-o", str(tmp_path / "demo"), "--no-report", "--loop-iterations", "0"],
                         check=True, capture_output=True, text=True).stdout
    rows = re.findall(r"^\s+(\d+)\s+([\d.]+)%\s+([\d.]+)%\s+([\d.]+) \|\s+([\d.]+)\s+([\d.]+)\s+([\d.]+) \|"
                      r"\s+([\d.]+)\s+(\S+)", out, re.M)
    assert [r[0] for r in rows] == ["0", "10", "100", "1000"], out
    for r in rows:
        res = paper_sim.recovery(float(r[0]))
        got = ("%g" % res["sigma"], "%.1f" % (100 * res["valid_fraction"]), "%.1f" % (100 * res["bad_radicand"]),
               "%.1f" % (res["err_paper"] * 1e9), "%.1f" % (res["err_halo"] * 1e9), "%.1f" % (res["err_lf"] * 1e9),
               "%.1f" % (res["err_lf_snr"] * 1e9), "%.1f" % (res["err_fit"] * 1e9), "%.3g" % res["median_snr"])
        assert got == tuple(r), (got, r)
    assert rows[0][6] == "15.6" and float(rows[0][7]) < 9.0


def test_demo_through_python_equals_the_cli(small_sim, cli, tmp_path):
    """demo() is `specklewfs demo` (run.h swfs_demo_run): the same products to the bit, its
    rows SimResult.recovery's, the loop's rows those of loop.tsv; a bad level, or an output
    of the loop that could not be written, is refused before the simulation, with no
    product written."""
    kv = ["%s=%s" % (k, v) for k, v in SMALL.items()]
    subprocess.run([cli, "demo", "-o", str(tmp_path / "cli"), "--levels", "0,100", "--loop-iterations", "1",
                    "--no-report"] + kv, check=True, capture_output=True)
    seen = []
    r = sw.demo(tmp_path / "py", levels=(0, 100), loop_iterations=1, report=False,
                progress=lambda stage, done, total: seen.append((stage, done, total)), **SMALL)
    assert [x["sigma"] for x in r["recovery"]] == [0, 100] and r["html"] == ""
    for row in r["recovery"]:
        want = small_sim.recovery(row["sigma"])
        assert {k: row[k] for k in want} == want
    for f in ("sigma0/halo.fits", "sigma100/wavefront.fits", "sigma100/science.fits", "loop/loop.fits"):
        a, b = sw.read_fits(str(tmp_path / "cli" / f))[0], sw.read_fits(str(tmp_path / "py" / f))[0]
        if f.startswith("loop"):  # its last column is the wall time of each row
            a, b = a[:, :-1], b[:, :-1]
        assert np.array_equal(a, b, equal_nan=True), f
    assert np.array_equal(r["sim"].science, small_sim.science)
    tsv = np.loadtxt(tmp_path / "py" / "loop" / "loop.tsv")
    assert len(r["loop"]) == 2 == tsv.shape[0]
    assert np.allclose([x["resid_rms"] * 1e9 for x in r["loop"]], tsv[:, 1], rtol=1e-5)
    assert ("simulate", 0, 1) in seen and ("noise levels", 2, 2) in seen and ("closed loop", 2, 2) in seen
    assert r["ncp_rms_ptt"] > 0 and r["seconds"] >= r["sim_seconds"] > 0
    with pytest.raises(sw.Error, match="noise level 2 is -1 counts"):
        sw.demo(tmp_path / "bad", levels=(0, -1), **SMALL)
    assert not os.path.exists(tmp_path / "bad")
    # The loop's table cannot be written (a folder in its place): no level's products either.
    os.makedirs(tmp_path / "fail" / "loop" / "loop.tsv")
    with pytest.raises(sw.Error, match="loop.tsv .output.: is a folder"):
        sw.demo(tmp_path / "fail", levels=(0,), loop_iterations=1, report=False, **SMALL)
    assert not os.path.exists(tmp_path / "fail" / "sigma0" / "halo.fits")
    assert not os.path.exists(tmp_path / "fail" / "recovery.tsv")
    # Stopped at the closed loop, after the levels' table was written: none of the run's
    # products, that table included (text products join the run's output group)
    class Enough(Exception):
        pass

    def at_loop(stage, done, total):
        if stage == "closed loop":
            raise Enough(stage)
    with pytest.raises(Enough):
        sw.demo(tmp_path / "stop", levels=(0,), loop_iterations=1, report=False, progress=at_loop, **SMALL)
    assert not os.path.exists(tmp_path / "stop" / "recovery.tsv")
    assert not os.path.exists(tmp_path / "stop" / "sigma0" / "halo.fits")


def test_small_simulation(small_sim, tmp_path):
    s = small_sim
    assert s.science.shape == (s.nframes, 32, 32) and s.pupil.shape == (64, 64) and s.halo_true.shape == (32, 32)
    assert s.ref_phase.shape == (s.nframes,)
    # The speckles have their mean removed (sim.h).
    assert np.abs(s.speckles.mean(0)).max() < 1e-12 * np.abs(s.speckles).max()
    # Camera noise is reproducible from its seed and follows the model.
    a, b = s.camera(10.0, 0.0, seed=5), s.camera(10.0, 0.0, seed=5)
    assert np.array_equal(a, b)
    assert np.std(a - s.science) == pytest.approx(10.0, rel=0.01)
    assert not np.array_equal(a, s.camera(10.0, 0.0, seed=6))
    # The NCP the parameters describe is the one injected.
    ncp, rms, pv = sw.ncp_map(mask=s.pupil, **SMALL)
    np.testing.assert_array_equal(ncp, s.ncp)
    assert rms == pytest.approx(s.ncp_rms, rel=1e-12)
    # A given NCP map replaces the parameters' terms.
    s2 = sw.simulate(ncp=np.zeros((64, 64)), **dict(SMALL, nscreens=1, screen_n=256))
    assert np.all(s2.ncp == 0)
    # write(): the files of `specklewfs simulate`.
    s.write(str(tmp_path), science=a, read_noise=10.0, gain=0.0)
    sci, g = sw.read_fits(str(tmp_path / "science.fits"))
    np.testing.assert_array_equal(sci, a.astype(np.float32))
    assert g == s.geom
    assert sw.read_keys(str(tmp_path / "science.fits"), ["RDNOISE"])["RDNOISE"] == 10.0
    t, _ = sw.read_fits(str(tmp_path / "truth.fits"), "NCP")
    np.testing.assert_array_equal(t, s.ncp)


def test_simulation_parameters_errors():
    with pytest.raises(sw.Error, match="bogus_key") as e:
        sw.simulate(bogus_key=1)
    assert e.value.function == "swfs_config_check_unused"
    with pytest.raises(sw.Error, match="nfx"):
        sw.sim_params(nfx="many")
    p = sw.sim_params(config=os.path.join(ROOT, "config", "paper-sec3.conf"), nfx=40, ncp_zernike=[2, 0, 20e-9])
    assert p["nfx"] == 40 and p["ncp_nzernike"] == 1 and p["ncp_zernike"][:3] == [2.0, 0.0, 20e-9]


def test_zonal_loop_parameter(tmp_path):
    """ao_rcond (a zonal loop) read by the library into the ctypes mirror at its place: the
    fields after it keep their defaults; out of range refused before anything is written."""
    from specklewfs.sim import _checked_params
    p = _checked_params("ts", None, dict(mode="timeseries", ao_rcond=0.05))
    assert p.ao_rcond == 0.05 and p.ao_modes == 56 and p.slope_noise == pytest.approx(3e-8) and p.pyr_mod == 3
    with pytest.raises(sw.Error, match=r"ao_rcond=1.5: must be in \[0, 1\)"):
        sw.simulate_timeseries(str(tmp_path / "z"), ao_rcond=1.5)
    assert not (tmp_path / "z").exists() or not os.listdir(tmp_path / "z")


def test_loop_reconstructor_of_the_used_subapertures(tmp_path):
    """ao_recon= may hold only the used subapertures' slopes (2 nvalid columns: their x slopes,
    then their y slopes), as most AO systems keep their control matrix: the loop runs it as the
    same matrix in the full layout (the same slopes to the bit). A width that is neither is
    refused, naming both."""
    ts = dict(pupn=66, pupdx=0.1, screen_n=256, ncubes=2, cube_frames=40, cube_gap=30, seed=4)
    sw.simulate_timeseries(str(tmp_path / "a"), **ts)
    W, _ = sw.read_fits(str(tmp_path / "a" / "recon_ao.fits"))[:2]
    W = np.array(W)
    s = np.array(sw.read_fits(str(tmp_path / "a" / "slopes_000.fits"))[0])
    n2 = s.shape[1] // 2
    used = np.flatnonzero(np.abs(s[:, :n2]).sum(0) + np.abs(s[:, n2:]).sum(0) > 0)
    assert 0 < used.size < n2
    sw.write_fits(str(tmp_path / "full.fits"), W)
    sw.write_fits(str(tmp_path / "used.fits"), np.hstack([W[:, used], W[:, n2 + used]]))
    for name in ("full", "used"):
        sw.simulate_timeseries(str(tmp_path / name), ao_recon=str(tmp_path / f"{name}.fits"), **ts)
    a = np.array(sw.read_fits(str(tmp_path / "full" / "slopes_000.fits"))[0])
    b = np.array(sw.read_fits(str(tmp_path / "used" / "slopes_000.fits"))[0])
    assert a.shape == s.shape and np.array_equal(a, b) and np.abs(a).max() > 0
    sw.write_fits(str(tmp_path / "odd.fits"), W[:, :-2])
    with pytest.raises(sw.Error, match=rf"odd.fits: the loop's reconstructor is {2 * n2 - 2} slopes x \d+ actuators, "
                                       rf"but the simulated Shack-Hartmann gives {2 * n2} slopes \({used.size} used "
                                       rf"subapertures: {2 * used.size} with the used ones' only\)"):
        sw.simulate_timeseries(str(tmp_path / "odd"), ao_recon=str(tmp_path / "odd.fits"), **ts)


TS_LONG = dict(pupn=66, pupdx=0.1, screen_n=256, wfs_file_frames=1000, ncubes=40, cube_frames=100)


def test_progress_stops_a_run(tmp_path):
    """An exception raised in a progress callback stops the library's run at that report: the
    exception itself comes out of the call (not the library's SWFS_ERR_STOPPED), and nothing is
    left in the output folder. Ctrl-C works the same way, with or without a callback of one's own:
    Python raises KeyboardInterrupt inside the library's next report."""
    class Enough(Exception):
        pass

    seen = []

    def enough(stage, done, total):
        seen.append((stage, done, total))
        if stage == "WFS frames":
            raise Enough(f"at {done} of {total}")
    with pytest.raises(Enough, match=r"at \d+ of \d+"):
        sw.simulate_timeseries(str(tmp_path / "a"), progress=enough, **TS_LONG)
    assert seen[0] == ("screens", 1, 2) and seen[-1][0] == "WFS frames" and os.listdir(tmp_path / "a") == []

    def ctrl_c(stage, done, total):
        if stage == "WFS frames":
            os.kill(os.getpid(), signal.SIGINT)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            sw.simulate_timeseries(str(tmp_path / "b"), progress=ctrl_c, **TS_LONG)
        assert os.listdir(tmp_path / "b") == []
        # no callback given: the signal, sent while the library runs, stops it at its next report
        timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
        timer.start()
        try:
            with pytest.raises(KeyboardInterrupt):
                sw.simulate_timeseries(str(tmp_path / "c"), **TS_LONG)
        finally:
            timer.cancel()
        assert os.listdir(tmp_path / "c") == []
    finally:
        signal.signal(signal.SIGINT, old)
    # the run goes on where the callback returns normally; a callback that is not callable is refused
    with pytest.raises(TypeError, match="progress: expected a callable"):
        sw.simulate_timeseries(str(tmp_path / "d"), progress=5, **TS_LONG)


def test_dm_coupling_parameter(tmp_path):
    """dm_coupling (Gaussian influence functions) read into the mirror at its place, the fields
    after it at their defaults; out of range refused before anything is written."""
    from specklewfs.sim import _checked_params
    p = _checked_params("ts", None, dict(mode="timeseries", dm_coupling=0.15))
    assert p.dm_coupling == 0.15 and p.act_square == 0 and p.export_modal == 0 and p.milk_file_frames == 400
    assert _checked_params("ts", None, dict(mode="timeseries")).dm_coupling == 0
    with pytest.raises(sw.Error, match=r"dm_coupling=1: must be in \[0, 1\)"):
        sw.simulate_timeseries(str(tmp_path / "g"), dm_coupling=1)
    assert not (tmp_path / "g").exists() or not os.listdir(tmp_path / "g")


def test_progress_callback():
    seen = []
    sw.simulate(progress=lambda stage, done, total: seen.append((stage, done, total)),
                **dict(SMALL, nscreens=1, screen_n=256))
    stages = {s for s, _, _ in seen}
    assert {"screens", "frames"} <= stages
    assert all(0 <= d <= t for _, d, t in seen)


def test_cli_and_python_give_identical_products(cli, tmp_path):
    """simulate with the CLI; estimate and pupil with the CLI and with Python on the same
    science/speckles FITS: identical arrays."""
    d = tmp_path / "sim"
    args = [f"{k}={v}" for k, v in SMALL.items()]
    subprocess.run([cli, "simulate", *args, "read_noise=5", "-o", str(d), "--quiet"], check=True,
                   capture_output=True)
    sci_f, sp_f = str(d / "science.fits"), str(d / "speckles.fits")
    halo_cli, pupil_cli = str(tmp_path / "halo_cli.fits"), str(tmp_path / "pupil_cli.fits")
    subprocess.run([cli, "estimate", sci_f, sp_f, "-o", halo_cli], check=True, capture_output=True)
    subprocess.run([cli, "pupil", halo_cli, "-o", pupil_cli], check=True, capture_output=True)

    sci, _ = sw.read_fits(sci_f)
    psi, geom = sw.read_fits(sp_f)
    noise = sw.read_keys(sci_f, ["RDNOISE", "GAIN"])
    assert noise == {"RDNOISE": 5.0, "GAIN": 1.0}
    acc = sw.Accumulator(geom_nx := sci.shape[2], sci.shape[1]).add(sci, psi)
    assert geom_nx == 32
    # The CLI's --g-smooth is 2 lambda/D by default: 2 / PIXSCALE pixels.
    h = acc.estimate(read_noise=noise["RDNOISE"], gain=noise["GAIN"], g_smooth=2.0 / geom.pixscale)
    assert h.n_valid > 0.5 * h.npix
    for ext, arr in h.maps.items():
        ref, g = sw.read_fits(halo_cli, ext)
        np.testing.assert_array_equal(arr, ref, err_msg=ext)
    assert g == geom
    keys = sw.read_keys(halo_cli, ["NVALID", "MEDSNR", "GSMOOTH"])
    # Header keywords are printed with ~15 significant digits.
    assert keys["NVALID"] == h.n_valid and keys["MEDSNR"] == pytest.approx(h.median_snr, rel=1e-13)
    assert keys["GSMOOTH"] == h.g_smooth

    p = sw.pupil_estimate(h, geom)  # the CLI's defaults: SNR weight, HALO_LF, annulus from the geometry
    for ext, arr in [("FIELD", p.field), ("WFE", p.wfe), ("SURFACE", p.surface), ("AMPLITUDE", p.amplitude),
                     ("PUPIL", p.mask)]:
        ref, _ = sw.read_fits(pupil_cli, ext)
        np.testing.assert_array_equal(arr, ref, err_msg=ext)
    assert sw.read_keys(pupil_cli, ["WFERMS"], ext="WFE")["WFERMS"] == pytest.approx(p.wfe_rms, rel=1e-13)

    # Python's products read by the CLI: the CLI's pupil of Python's halo.fits is the same.
    halo_py, pupil_py = str(tmp_path / "halo_py.fits"), str(tmp_path / "pupil_py.fits")
    h.write(halo_py, geom, provenance=["python"])
    subprocess.run([cli, "pupil", halo_py, "-o", pupil_py], check=True, capture_output=True)
    for ext in ("FIELD", "WFE"):
        np.testing.assert_array_equal(sw.read_fits(pupil_py, ext)[0], sw.read_fits(pupil_cli, ext)[0])
    p.write(str(tmp_path / "p.fits"))
    np.testing.assert_array_equal(sw.read_fits(str(tmp_path / "p.fits"), "WFE")[0], p.wfe)

    # And the simulation itself: Python's run with the same parameters and the camera seed
    # `simulate` uses writes the same files' contents (science and speckles are -32 files).
    s = sw.simulate(read_noise=5, **SMALL)
    np.testing.assert_array_equal(s.camera().astype(np.float32), sci)
    np.testing.assert_array_equal(s.speckles.astype(np.complex64), psi)
    np.testing.assert_array_equal(s.ncp, sw.read_fits(str(d / "truth.fits"), "NCP")[0])

    # Checkpoints: the CLI's merge of Python's checkpoints equals Python's merge.
    a, b = str(tmp_path / "a.ckpt.fits"), str(tmp_path / "b.ckpt.fits")
    n = sci.shape[0] // 2
    sw.Accumulator(32, 32).add(sci[:n], psi[:n]).save(a, geom)
    sw.Accumulator(32, 32).add(sci[n:], psi[n:]).save(b, geom)
    merged, mhalo = str(tmp_path / "m.ckpt.fits"), str(tmp_path / "m.halo.fits")
    subprocess.run([cli, "merge", a, b, "-o", merged, "--halo", mhalo, "--read-noise", "5", "--gain", "1"],
                   check=True, capture_output=True)
    m = sw.Accumulator.load(merged)
    np.testing.assert_array_equal(m.state(), sw.merge_files([a, b]).state())
    hm = sw.merge_files([a, b]).estimate(read_noise=5, gain=1, g_smooth=2.0 / geom.pixscale)
    for ext in ("HALO", "HALO_LF", "GAIN", "SNR"):
        np.testing.assert_array_equal(hm.maps[ext], sw.read_fits(mhalo, ext)[0], err_msg=ext)
    # ... and equals the single pass to rounding.
    np.testing.assert_allclose(hm.halo, h.halo, rtol=1e-9, atol=1e-12 * np.abs(h.halo).max())


def test_timeseries_simulation_equals_the_cli(cli, tmp_path):
    """The AO time series (timeseries.h) from Python and from `specklewfs simulate
    mode=timeseries` with the same keys: the same telemetry and camera cubes."""
    keys = dict(screen_n=512, ncubes=2, cube_frames=30, cube_gap=20, start_offset=50.4)
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    s = sw.simulate_timeseries(str(tmp_path / "py"), config=conf, **keys)
    assert s["nact"] == 217 and s["ao_modes"] == 56 and s["nwfs"] > 2 * 30 * 6
    assert 0.5 < s["strehl"] < 1 and s["ncp_rms"] == pytest.approx(105.5e-9, rel=0.01)
    subprocess.run([cli, "simulate", conf, *[f"{k}={v}" for k, v in keys.items()], "-o", str(tmp_path / "cli"),
                    "--quiet"], check=True, capture_output=True)
    for f, ext in [("slopes_000.fits", None), ("raw_001.fits", None), ("speckles_ideal.fits", None),
                   ("truth.fits", "NCP"), ("actuators.fits", None)]:
        a = sw.read_fits(str(tmp_path / "py" / f), ext)[0]
        b = sw.read_fits(str(tmp_path / "cli" / f), ext)[0]
        np.testing.assert_array_equal(a, b, err_msg=f)
    sp, g = sw.read_fits(str(tmp_path / "py" / "speckles_ideal.fits"), squeeze=False)
    assert sp.shape == (60, 54, 54) and sp.dtype == np.complex128 and g.pixscale == 0.25


def test_timeseries_truth_export(tmp_path):
    """export_truth=1: truewf_NNN.fits beside each slopes file, the same WFS frames: the true
    residual least-squares fitted on the actuators and (extension DM) the loop's commands, which
    follow the loop's own integrator on the recorded slopes frame by frame."""
    keys = dict(screen_n=512, ncubes=2, cube_frames=30, cube_gap=20, start_offset=50.4, wfs_file_frames=300)
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    d = tmp_path / "t"
    s = sw.simulate_timeseries(str(d), config=conf, export_truth=1, **keys)
    files = sorted(p.name for p in d.glob("truewf_*.fits"))
    assert files == sorted(p.name.replace("slopes_", "truewf_") for p in d.glob("slopes_*.fits")) and len(files) >= 2
    z = np.concatenate([sw.read_fits(str(d / f))[0] for f in files])
    dm = np.concatenate([sw.read_fits(str(d / f), "DM")[0] for f in files])
    sl = np.concatenate([sw.read_fits(str(d / f.replace("truewf_", "slopes_")))[0] for f in files])
    assert z.shape == dm.shape == (s["nwfs"], s["nact"]) and sl.shape[0] == s["nwfs"]
    assert sw.read_keys(str(d / files[1]), ["FRAME0"])["FRAME0"] == 300
    # the commands: DM[k+1] = DM[k] + gain W_ao s[k + 1 - delay] (mmt-clio.conf: gain 0.4, delay 2)
    w = sw.read_fits(str(d / "recon_ao.fits"))[0]
    step = 0.4 * sl[:-2] @ w.T
    np.testing.assert_allclose(dm[2:] - dm[1:-1], step, rtol=0, atol=1e-6 * np.abs(dm).max())
    assert np.abs(step).max() > 1e-3 * np.abs(dm).max()
    # the true residual on the pupil (T z), tip-tilt removed, is the summary's RESRMSNT less what
    # the actuators cannot hold; the commands' open-loop wavefront is far larger
    mask, g = sw.read_fits(str(d / "truth.fits"), "PUPIL")
    t, _ = sw.interp_ct_grid(sw.actuators_read(str(d / "actuators.fits")), g.pupn, g.pupdx, mask)
    inside = mask.ravel() > 0
    tp = t.to_dense()[inside]
    n = (np.arange(g.pupn) - (g.pupn - 1) / 2) * g.pupdx
    x, y = np.meshgrid(n, n)
    a = np.stack([np.ones(inside.sum()), x.ravel()[inside], y.ravel()[inside]], 1)

    def rms_nott(v):
        p = v @ tp.T
        return np.sqrt(np.mean((p - (p @ np.linalg.pinv(a).T) @ a.T) ** 2))

    r = rms_nott(z) / s["residual_rms_nott"]
    assert 0.6 < r <= 1.01, r
    assert rms_nott(dm) > 3 * rms_nott(z)


def test_timeseries_dm_from_a_file(tmp_path):
    """actuators = FILE: the simulated loop runs on a DM the simulator cannot build itself (the
    hexapolar rings moved by up to 4 cm at random, an AO system's own layout), its
    actuators.fits is that file's positions, and the loop closes as on the built DM."""
    keys = dict(screen_n=512, ncubes=1, cube_frames=30, cube_gap=20, start_offset=50.4)
    conf = os.path.join(ROOT, "config", "mmt-clio.conf")
    s0 = sw.simulate_timeseries(str(tmp_path / "built"), config=conf, **keys)
    xy = sw.actuators_read(str(tmp_path / "built" / "actuators.fits"))
    rng = np.random.default_rng(5)
    moved = xy + rng.uniform(-0.04, 0.04, xy.shape) * (np.hypot(xy[:, 0], xy[:, 1]) < 3.0)[:, None]
    sw.write_fits(str(tmp_path / "mine.fits"), moved)
    s = sw.simulate_timeseries(str(tmp_path / "given"), config=conf, actuators=str(tmp_path / "mine.fits"), **keys)
    assert s["nact"] == len(moved) == s0["nact"]
    np.testing.assert_array_equal(sw.actuators_read(str(tmp_path / "given" / "actuators.fits")), moved)
    assert abs(s["residual_rms_nott"] / s0["residual_rms_nott"] - 1) < 0.1
    sl0 = sw.read_fits(str(tmp_path / "built" / "slopes_000.fits"))[0]
    sl = sw.read_fits(str(tmp_path / "given" / "slopes_000.fits"))[0]
    assert sl.shape == sl0.shape and not np.array_equal(sl, sl0)
    with pytest.raises(sw.Error, match="nofile.fits"):
        sw.simulate_timeseries(str(tmp_path / "bad"), config=conf, actuators=str(tmp_path / "nofile.fits"), **keys)


def test_pupil_mask_from_a_file(tmp_path):
    """pupil_mask = FILE: the simulators take a telescope pupil from a file. The spidered
    annulus the keys describe, given back as a file, makes the same frames to the bit; a
    hexagonal pupil (which no key describes) is the one the frames saw, and the file's
    problems are refused naming it."""
    keys = dict(SMALL, nscreens=1, screen_n=256)
    s0 = sw.simulate(**dict(keys, nspiders=3, spider_width=0.1))
    sw.write_fits(str(tmp_path / "spiders.fits"), s0.pupil)
    s1 = sw.simulate(pupil_mask=str(tmp_path / "spiders.fits"), **keys)
    np.testing.assert_array_equal(s1.pupil, s0.pupil)
    np.testing.assert_array_equal(s1.science, s0.science)
    assert sw.sim_params(pupil_mask=str(tmp_path / "spiders.fits"))["pupil_mask"] == str(tmp_path / "spiders.fits")
    # A hexagon of flat-to-flat 2.2 m inside the 2.5 m telescope.
    n, dx = keys["pupn"], sw.sim_params(**keys)["pupdx"]
    c = (np.arange(n) - (n - 1) / 2) * dx
    x, y = np.meshgrid(c, c)
    hexa = np.ones((n, n))
    for a in np.deg2rad([0, 60, 120]):
        hexa *= np.abs(x * np.cos(a) + y * np.sin(a)) <= 1.1
    sw.write_fits(str(tmp_path / "hex.fits"), hexa)
    s2 = sw.simulate(pupil_mask=str(tmp_path / "hex.fits"), **keys)
    np.testing.assert_array_equal(s2.pupil, hexa)
    assert np.all(s2.ncp[hexa == 0] == 0) and np.any(s2.ncp[hexa > 0] != 0)
    # The fields are normalized by the pupil's own sum (sim.h field_scale).
    assert s2.field_scale == pytest.approx(hexa.sum(), rel=1e-12)
    with pytest.raises(sw.Error, match="wide.fits.*reaches 1.25 m"):
        sw.write_fits(str(tmp_path / "wide.fits"), np.ones((n, n)))
        sw.simulate(pupil_mask=str(tmp_path / "wide.fits"), **keys)
    with pytest.raises(sw.Error, match="small.fits: pupil mask is 32x32x1"):
        sw.write_fits(str(tmp_path / "small.fits"), np.ones((32, 32)))
        sw.simulate(pupil_mask=str(tmp_path / "small.fits"), **keys)


def test_modal_slopes(tmp_path, cli):
    """modal_slopes (`specklewfs modal-slopes`): the export's modal coefficients through the
    pseudo-inverse of its modal control matrix are its valid-only slopes projected onto CM's row
    space (within 15 % of them in rms), each file under its own name with MODALCM naming the
    control matrix's copy beside them; a control matrix of another shape raises, nothing
    written. Through the modal response matrix instead (imat=): exact for coefficients made by
    its least-squares control matrix."""
    d = tmp_path / "sim"
    subprocess.run([cli, "simulate", "mode=timeseries", "--quiet", "-o", str(d), "screen_n=512", "ncubes=2",
                    "cube_frames=30", "cube_gap=20", "start_offset=50.4", "wfs_file_frames=300", "export_modal=1",
                    os.path.join(ROOT, "config", "mmt-clio.conf")], check=True, capture_output=True)
    modal = sorted(str(p) for p in d.glob("modal_*.fits"))
    out = tmp_path / "slopes"
    out.mkdir()
    r = sw.modal_slopes(modal, str(d / "cm_modes.fits"), str(out))
    assert r["rank"] == r["ncoef"] < r["nslopes"] and r["resid"] < 1e-6 and len(modal) >= 2
    for f in modal:
        name = os.path.basename(f)
        s = sw.read_fits(str(out / name))[0]
        v = sw.read_fits(str(d / name.replace("modal_", "slopes_valid_")))[0]
        assert s.shape == v.shape and np.sqrt(np.mean((s - v) ** 2) / np.mean(v ** 2)) < 0.15
        k = sw.read_keys(str(out / name), ["MODALCM", "FRAME0", "BUNIT"])
        assert k["MODALCM"] == "cm_modes.fits" and k["BUNIT"] == "rad"
        assert k["FRAME0"] == sw.read_keys(f, ["FRAME0"])["FRAME0"]
    # the control matrix copied beside the slopes, under the name their MODALCM gives
    np.testing.assert_array_equal(sw.read_fits(str(out / "cm_modes.fits"))[0], sw.read_fits(str(d / "cm_modes.fits"))[0])
    # the projection keeps the slopes' curl power (what speckles' vk then takes as their noise,
    # the power outside the modes being gone): within 10 % of the valid slopes' own
    vm = sw.read_fits(str(d / "valid.fits"))[0]
    nsub = vm.shape[0]
    name = os.path.basename(modal[0])
    tp = sw.slopes_curl_noise(sw.read_fits(str(out / name))[0], nsub, vm)[1]
    tv = sw.slopes_curl_noise(sw.read_fits(str(d / name.replace("modal_", "slopes_valid_")))[0], nsub, vm)[1]
    assert tv > 0 and abs(tp / tv - 1) < 0.1
    bad = tmp_path / "bad"
    bad.mkdir()
    with pytest.raises(sw.Error, match="coefficients per WFS frame; .*control.fits maps"):
        sw.modal_slopes(modal, str(d / "control.fits"), str(bad))
    assert not list(bad.iterdir())
    # the modal response matrix (rm_modes.fits: each mode's valid slopes per um): the export's
    # (von Karman MAP) control matrix inverts it on the well-sensed modes, shrunk as a MAP
    # shrinks them (its units and sign: the first 30 modes' gains 0.75-1.01, measured 0.77-0.98,
    # the first 10's mean within 10 % of 1, measured 0.94); coefficients made through its least-squares control matrix come back
    # through --imat as the slopes projected onto its modes (as through --cm with that matrix,
    # whose pinv_ copy MODALCM names)
    rm = sw.read_fits(str(d / "rm_modes.fits"))[0]
    cmv = sw.read_fits(str(d / "cm_modes.fits"))[0]
    assert rm.shape == (cmv.shape[1], cmv.shape[0])
    gains = np.diag(cmv @ rm)
    assert np.all((gains[:30] > 0.75) & (gains[:30] < 1.01)) and abs(gains[:10].mean() - 1) < 0.1
    cls = np.linalg.pinv(rm)
    lsq = tmp_path / "lsq"
    lsq.mkdir()
    made = []
    for f in modal:
        v = sw.read_fits(str(d / os.path.basename(f).replace("modal_", "slopes_valid_")))[0]
        made.append(str(lsq / os.path.basename(f)))
        sw.write_fits(made[-1], v @ cls.T, keys={"FRAME0": int(sw.read_keys(f, ["FRAME0"])["FRAME0"])})
    viaim = tmp_path / "viaim"
    viaim.mkdir()
    r = sw.modal_slopes(made, outdir=str(viaim), imat=str(d / "rm_modes.fits"))
    assert r["rank"] == r["ncoef"] == rm.shape[1] and r["resid"] < 1e-6
    # their white noise is what a least-squares CM gives every mode (measured 1.01); the
    # export's own coefficients, a MAP's, are flagged (measured 0.011)
    assert 0.8 < r["lsq_ratio"] < 1.25 and not r["lsq_warns"]
    own = tmp_path / "own"
    own.mkdir()
    r = sw.modal_slopes(modal, outdir=str(own), imat=str(d / "rm_modes.fits"))
    assert r["lsq_ratio"] < 0.5 and r["lsq_warns"]
    np.testing.assert_allclose(sw.read_fits(str(viaim / "pinv_rm_modes.fits"))[0], cls, rtol=0, atol=1e-6 * np.abs(cls).max())
    P = rm @ cls
    for f in made:
        name = os.path.basename(f)
        s = sw.read_fits(str(viaim / name))[0]
        v = sw.read_fits(str(d / name.replace("modal_", "slopes_valid_")))[0]
        assert sw.read_keys(str(viaim / name), ["MODALCM"])["MODALCM"] == "pinv_rm_modes.fits"
        assert np.sqrt(np.mean((s - v @ P.T) ** 2) / np.mean(v ** 2)) < 1e-5
    with pytest.raises(ValueError, match="one of them"):
        sw.modal_slopes(modal, str(d / "cm_modes.fits"), str(bad), imat=str(d / "rm_modes.fits"))


def test_pyramid_timeseries(tmp_path):
    """simulate_timeseries(wfs='pyramid'): a modulated pyramid senses; its signals are the
    telemetry (the Shack-Hartmann's layout, WFSTYPE 'PYRAMID'), the run writes its linear
    model (influence.fits, imat_ao.fits); sync and speckles take them through the linear model
    (linear=dict(basis=, imat=)), and the Shack-Hartmann model refuses them naming why."""
    d = tmp_path / "sim"
    r = sw.simulate_timeseries(str(d), pupn=66, pupdx=0.1, screen_n=512, ncubes=2, cube_frames=30, cube_gap=20,
                               start_offset=50.4, wfs="pyramid", wfs_wavelen=1.6e-6, pyr_mod=2)
    k = sw.read_keys(str(d / "slopes_000.fits"), ["WFSTYPE", "PYRMOD", "PYRNMOD", "WFSLAM", "NSUB"])
    assert k["WFSTYPE"] == "PYRAMID" and k["PYRMOD"] == 2 and k["PYRNMOD"] == 28 and k["WFSLAM"] == 1.6e-6
    s = sw.read_fits(str(d / "slopes_000.fits"))[0]
    D = sw.read_fits(str(d / "imat_ao.fits"))[0]
    F = sw.read_fits(str(d / "influence.fits"))[0]
    assert s.shape[1] == 2 * k["NSUB"] ** 2 and D.shape == (s.shape[1], r["nact"]) and F.shape[0] == r["nact"]
    # unused subapertures report 0; the used ones respond to the actuators
    used = np.abs(D).sum(axis=1) > 0
    assert used.sum() == 2 * r["nvalid"] and np.all(s[:, ~used] == 0)
    sci, timing = str(tmp_path / "sci.fits"), str(tmp_path / "timing.txt")
    sw.reduce([str(d / f"raw_{c:03d}.fits") for c in range(2)], sci, dark=str(d / "dark.fits"), flat=str(d / "flat.fits"))
    lin = dict(basis=str(d / "influence.fits"), imat=str(d / "imat_ao.fits"))
    t = sw.sync(sci, str(d / "handshake.log"), timing, linear=lin)
    assert abs(t["ratio"] - 6.48) < 0.02
    sp = sw.speckles(timing, sci, None, str(tmp_path / "sp.fits"), linear=lin, mean_loops="none")
    assert sp["nout"] == 60 and sp["info"]["nbasis"] == r["nact"] and "taught" not in sp
    # a control matrix carrying a miss of the residual's mean (learn's MEANMISS, here a tilt-free
    # pattern of 20 nm on the actuators: astigmatism): speckles adds it through the basis
    xy = sw.read_fits(str(d / "actuators.fits"))[0]
    c = 20e-9 * (xy[:, 0] ** 2 - xy[:, 1] ** 2) / np.max(xy[:, 0] ** 2 + xy[:, 1] ** 2)
    C = sw.read_fits(str(d / "recon_ao.fits"))[0]
    sw.write_fits(str(tmp_path / "Cmm.fits"), {"C": C, "MEANMISS": c[None, :]})
    a0 = sw.speckles(timing, sci, None, str(tmp_path / "a0.fits"), linear=dict(basis=lin["basis"], control=str(d / "recon_ao.fits")),
                     mean_loops="none")
    a1 = sw.speckles(timing, sci, None, str(tmp_path / "a1.fits"), linear=dict(basis=lin["basis"], control=str(tmp_path / "Cmm.fits")),
                     mean_loops="none")
    assert a0["meanmiss_rms"] == 0 and 2e-9 < a1["meanmiss_rms"] < 20e-9
    diff = sw.read_fits(str(tmp_path / "a1.fits"), "RESMEAN")[0] - sw.read_fits(str(tmp_path / "a0.fits"), "RESMEAN")[0]
    F2 = np.tensordot(c, F, axes=(0, 0))  # the pattern through the influence functions
    inside = diff != 0
    assert np.sqrt(np.mean(diff[inside] ** 2)) == pytest.approx(a1["meanmiss_rms"], rel=1e-3)
    assert np.corrcoef(diff[inside], F2[inside])[0, 1] > 0.99
    # the miss as an image on the pupil grid (what speckles' choice among the loops' maps gives
    # --write-recon's map): added as it stands, the same as through the basis, and the default's
    # loops for a pyramid's telemetry not simulated for a map that carries its own miss
    sw.write_fits(str(tmp_path / "Cpg.fits"), {"C": C, "MEANMISS": F2})
    a2 = sw.speckles(timing, sci, None, str(tmp_path / "a2.fits"), linear=dict(basis=lin["basis"], control=str(tmp_path / "Cpg.fits")))
    assert a2["mean_teach"] is None and a2["meanmiss_rms"] == pytest.approx(a1["meanmiss_rms"], rel=1e-9)
    d2 = sw.read_fits(str(tmp_path / "a2.fits"), "RESMEAN")[0] - sw.read_fits(str(tmp_path / "a0.fits"), "RESMEAN")[0]
    assert np.max(np.abs(d2 - diff)) < 1e-9 * np.max(np.abs(diff))
    sw.write_fits(str(tmp_path / "Cbad.fits"), {"C": C, "MEANMISS": F2[:10, :10]})
    with pytest.raises(sw.Error, match=r"Cbad.fits: MEANMISS is a 10 x 10 x 1 image; expected the pupil grid"):
        sw.speckles(timing, sci, None, str(tmp_path / "a3.fits"), linear=dict(basis=lin["basis"], control=str(tmp_path / "Cbad.fits")))
    assert not os.path.exists(tmp_path / "a3.fits")
    # the miss of the observation's own reconstruction from simulated loops (mean_loops): here
    # the run itself twice, so the loops agree (held out 0) and the miss added is its own: the
    # mean taken out comes nearer the true one (truth.fits RESMEAN, over the camera's frames:
    # measured 6.7 nm off against 27.7 without, the loop's telemetry averaged from its first
    # exposure's start as its truth is; 11.0 over all its frames, the loop's closing included)
    m1 = sw.speckles(timing, sci, None, str(tmp_path / "m1.fits"), linear=lin, mean_loops=[str(d), str(d)])
    assert m1["meanmiss_heldout"] == pytest.approx(0, abs=1e-12) and m1["meanmiss_rms"] > 0 and np.isnan(sp["meanmiss_heldout"])
    true = sw.read_fits(str(d / "truth.fits"), "RESMEAN")[0]
    inside = true != 0
    def off(path):  # rms of the mean taken out against the true one (piston, tip, tilt are the pupil step's)
        x = sw.read_fits(path, "RESMEAN")[0][inside] - true[inside]
        A = np.c_[np.ones(x.size), np.nonzero(inside)[1], np.nonzero(inside)[0]]
        return np.sqrt(np.mean((x - A @ np.linalg.lstsq(A, x, rcond=None)[0]) ** 2))
    assert off(str(tmp_path / "m1.fits")) < 0.5 * off(str(tmp_path / "sp.fits"))
    with pytest.raises(sw.Error, match="needs at least 2 simulated loops"):
        sw.speckles(timing, sci, None, str(tmp_path / "m2.fits"), linear=lin, mean_loops=[str(d)])
    assert not os.path.exists(tmp_path / "m2.fits")
    # the same on a Pipeline of one's own (a stream's: `stream --mean-loop`): the loops' shared
    # miss becomes its mean offset; one loop is refused
    g = sw.read_geom(sci)
    sci_shape = sw.fits_info(sci)
    pl = sw.Pipeline.linear(g, sci_shape["nx"], sci_shape["ny"], F, imat=D, training=s)
    # the interaction matrix's rank: every basis function sensed; a matrix whose columns all
    # repeat the first senses one combination, the sum of all functions, which is nearly piston:
    # refused for its wavefront, naming the rank (it said "-nan nm rms", the root of a rounding)
    assert pl.info["imat_rank"] == np.linalg.matrix_rank(D) == F.shape[0]
    with pytest.raises(sw.Error, match=r"wavefront is [0-9.e-]+ nm rms .* senses only 1 combinations of its 217 basis"):
        sw.Pipeline.linear(g, sci_shape["nx"], sci_shape["ny"], F, imat=np.repeat(D[:, :1], F.shape[0], 1), training=s)
    ml = pl.mean_loops([str(d), str(d)])
    assert ml["heldout"] == pytest.approx(0, abs=1e-12) and ml["rms"] > 0
    with pytest.raises(sw.Error, match="at least 2 folders"):
        pl.mean_loops([str(d)])
    # the default for a pyramid's telemetry (mean_loops='teach' by name): loops speckles simulates
    # itself (two, for the time) of the system the files describe: the pyramid's keys from the
    # header, its photons from the signals' white noise (the simulator's 1000), the DM's pitch
    # from the basis's centroids (0.45 m, hexapolar), the filter's knee through the pyramid's own
    # interaction matrix (56 modes), the layers from `wind`; a second run with the same
    # description reuses them, to the same result
    tw = str(tmp_path / "tw")
    t1 = sw.speckles(timing, sci, None, str(tmp_path / "t1.fits"), linear=lin, mean_teach_loops=2, teach_work=tw)
    mt = t1["mean_teach"]
    assert mt["pyramid"] and mt["automatic"] and not mt["reused"] and mt["nloops"] == 2 and mt["loop_frames"] >= 1000
    assert 700 < mt["photons"] < 1400 and mt["act_pitch"] == pytest.approx(0.45, rel=0.02)
    assert abs(mt["knee"] - 56) <= 3 and len(mt["layers"]) >= 1 and np.isfinite(t1["meanmiss_heldout"])
    # two loops: no learning curve (it takes 4), so no more loops
    assert mt["nloops_first"] == 2 and np.isnan(mt["curve_excess"]) and mt["curve_frames"] == 0
    assert sp["mean_teach"] is None and os.path.isfile(os.path.join(tw, "mean_loops.conf"))
    # their r0 fitted to the signals' residual power: the simulator's 0.15 here, so the first
    # pair's power is the telemetry's and the fit stops there
    assert mt["r0_pairs"] == 1 and mt["r0"] == 0.15 and 0.8 < mt["power_ratio"] < 1.25 and mt["power"] > 0
    t2 = sw.speckles(timing, sci, None, str(tmp_path / "t2.fits"), linear=lin, mean_loops="teach", mean_teach_loops=2,
                     teach_work=tw)
    assert t2["mean_teach"]["reused"] and not t2["mean_teach"]["automatic"]
    assert t2["meanmiss_heldout"] == t1["meanmiss_heldout"]
    assert t2["meanmiss_rms"] == t1["meanmiss_rms"]
    assert t2["mean_teach"]["r0"] == 0.15 and t2["mean_teach"]["r0_pairs"] == 0  # mean_loops.conf's
    # the loops' own map (loops_map='auto'): two loops hold fewer than 10 frames per input, so it
    # is not tried and says why; asked for with three folders (the second loop twice, for the
    # time) it is learned, carried onto the basis, scored and the better set written
    assert t1["loops_map"] is None and "fewer than the" in t1["loops_map_fallback"]
    lm3 = [os.path.join(tw, "mean_00"), os.path.join(tw, "mean_01"), os.path.join(tw, "mean_01")]
    t5 = sw.speckles(timing, sci, None, str(tmp_path / "t5.fits"), linear=lin, mean_loops=lm3, loops_map="choose",
                     teach_work=str(tmp_path / "tw5"))
    L = t5["loops_map"]
    assert L is not None and L["inputs"] == 2 * r["nvalid"] and L["nframes"] >= 10 * L["inputs"]
    # (a space-time map, teach's five lags, would need ten times its inputs in frames: these three
    # loops hold fewer, so the per-frame map of them, and the run says how many it needed)
    assert L["lags"] == () and L["st_frames"] > L["nframes"] and L["st_frames"] >= 10 * 5 * L["inputs"]
    # the written set is the one of the five (the two ends, the three mixes) that explains most
    scores = [L["explained"][0], L["explained"][1]] + list(L["explained_mix"])
    weights = [1.0, 0.0] + list(L["mix_weight"])
    assert weights[2:] == [0.75, 0.5, 0.25] and all(0 < e < 1 for e in scores)
    assert L["weight"] == weights[scores.index(max(scores))] and L["chosen"] == (L["weight"] != 1.0)
    assert L["mix_note"] == ""
    # (the loops' truth is on teach's grid of half their DM's pitch, tw/outgrid.fits, so their map
    # stays on those points, not carried onto the basis: its file carries them as OUTXY)
    assert L["carry_resid"] == 0
    # each mix w C_imat + (1 - w) C_loops: the interaction matrix's map from the 0.25 mix and the
    # loops' map gives the 0.75 and the 0.5 ones
    Cl = sw.read_fits(L["map"])[0].copy()
    Cm = {pc: sw.read_fits(os.path.join(L["work"], f"mix_{pc:02d}.fits"))[0].copy() for pc in (75, 50, 25)}
    Ci = 4 * Cm[25] - 3 * Cl
    assert np.abs(Ci - Cl).max() > 1e-3 * np.abs(Cl).max()
    for pc in (75, 50):
        assert np.allclose(Cm[pc], pc / 100 * Ci + (1 - pc / 100) * Cl, rtol=0, atol=1e-9 * np.abs(Ci).max())
    C5 = sw.read_fits(L["map"])[0]
    og = sw.read_fits(os.path.join(tw, "outgrid.fits"))[0]
    assert C5.shape == (og.shape[0], s.shape[1]) and og.shape[0] > 2 * r["nact"]
    assert np.array_equal(sw.read_fits(L["map"], "OUTXY")[0], og) and os.path.isfile(os.path.join(L["work"], "halo_loops.fits"))
    with pytest.raises(ValueError, match="loops_map takes"):
        sw.speckles(timing, sci, None, str(tmp_path / "t6.fits"), linear=lin, loops_map="yes")
    # a system observed at another r0 (0.09 m): the fit finds it from the signals in more pairs
    # (measured 0.0974 m in 3 pairs, the kept pair's power 0.99 of the telemetry's: the loops'
    # residual matches the observation's, their other keys the files' description); given, r0 is
    # taken as it is
    d9 = tmp_path / "sim9"
    sw.simulate_timeseries(str(d9), pupn=66, pupdx=0.1, screen_n=512, ncubes=2, cube_frames=30, cube_gap=20,
                           start_offset=50.4, wfs="pyramid", wfs_wavelen=1.6e-6, pyr_mod=2, r0=0.09)
    sci9, timing9 = str(tmp_path / "sci9.fits"), str(tmp_path / "timing9.txt")
    sw.reduce([str(d9 / f"raw_{c:03d}.fits") for c in range(2)], sci9, dark=str(d9 / "dark.fits"), flat=str(d9 / "flat.fits"))
    lin9 = dict(basis=str(d9 / "influence.fits"), imat=str(d9 / "imat_ao.fits"))
    sw.sync(sci9, str(d9 / "handshake.log"), timing9, linear=lin9)
    m9 = sw.speckles(timing9, sci9, None, str(tmp_path / "t9.fits"), linear=lin9, mean_teach_loops=2,
                     teach_work=str(tmp_path / "tw9"))["mean_teach"]
    assert m9["r0_pairs"] >= 2 and m9["r0"] == pytest.approx(0.09, rel=0.1) and 0.8 < m9["power_ratio"] < 1.25
    g9 = sw.speckles(timing9, sci9, None, str(tmp_path / "g9.fits"), linear=lin9, mean_teach_loops=2,
                     teach_work=str(tmp_path / "tw9g"), teach_keys=dict(r0=0.12))["mean_teach"]
    assert g9["r0_pairs"] == 0 and g9["r0"] == 0.12 and np.isnan(g9["power_ratio"])
    # where the loops cannot be made (here their folder: under a file), the default goes on
    # without them, saying why
    (tmp_path / "afile").write_text("x")
    with pytest.warns(RuntimeWarning, match="no loops of the system .*cannot create the teach folder"):
        t4 = sw.speckles(timing, sci, None, str(tmp_path / "t4.fits"), linear=lin, teach_work=str(tmp_path / "afile" / "tw"))
    assert t4["mean_teach"] is None and np.isnan(t4["meanmiss_heldout"]) and os.path.isfile(tmp_path / "t4.fits")
    with pytest.raises(sw.Error, match="--mean-loop teach goes with the linear model"):
        sw.speckles(timing, sci, str(d / "actuators.fits"), str(tmp_path / "t3.fits"), mean_loops="teach")
    with pytest.raises(sw.Error, match="--mean-teach-loops must be 2"):
        sw.speckles(timing, sci, None, str(tmp_path / "t3.fits"), linear=lin, mean_loops="teach", mean_teach_loops=1)
    with pytest.raises(sw.Error, match=r"--mean-teach-max-loops must be --mean-teach-loops \(2\)..16, got 1"):
        sw.speckles(timing, sci, None, str(tmp_path / "t3.fits"), linear=lin, mean_teach_loops=2, mean_teach_max_loops=1)
    assert not os.path.exists(tmp_path / "t3.fits")
    with pytest.raises(sw.Error, match="WFSTYPE = 'PYRAMID': not a Shack-Hartmann's slopes"):
        sw.speckles(timing, sci, str(d / "actuators.fits"), str(tmp_path / "sp2.fits"), recon="vk")
    assert not os.path.exists(tmp_path / "sp2.fits")
    with pytest.raises(ValueError, match="not both"):
        sw.speckles(timing, sci, str(d / "actuators.fits"), str(tmp_path / "sp3.fits"), linear=lin)


def test_report(tmp_path, cli):
    """report(): the figures of a demo folder and of one of its run folders from Python, as
    the command line draws them (the same files); key numbers from the products; a folder
    with nothing to report raises naming what was looked for, and writes no page."""
    import subprocess
    d = tmp_path / "demo"
    sw.demo(str(d), levels=(0, 100), loop_iterations=1, report=False, screen_n=256, teldiam=2.5, pupn=64, nscreens=2,
            nfx=32, nfy=24)
    r = sw.report(str(d))
    assert r["demo"] and len(r["levels"]) == 2 and r["recovery_rows"] == 2 and r["loop_rows"] >= 1
    assert [lv["sigma"] for lv in r["levels"]] == [0, 100] and all(lv["nfigures"] > 0 for lv in r["levels"])
    assert r["html"] == str(d / "report" / "index.html") and os.path.getsize(r["html"]) > 1000
    assert r["figures"] and all(os.path.getsize(d / "report" / f) > 0 for f, _w, _h in r["figures"])
    run = sw.report(str(d / "sigma100"), str(tmp_path / "page"), title="sigma 100")
    assert not run["demo"] and run["figures"] and "sigma 100" in open(run["html"]).read()
    assert 0 < run["wfe_rms"] < 1e-6 and 0 < run["err_rms"] < run["ncp_rms"] and 0 < run["valid_fraction"] <= 1
    assert "halo_amp" in run["ranges"] and run["pixel"][0] >= 0
    subprocess.run([cli, "report", str(d / "sigma100"), "-o", str(tmp_path / "page_cli")], check=True, capture_output=True)
    assert sorted(os.listdir(tmp_path / "page")) == sorted(os.listdir(tmp_path / "page_cli"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(sw.Error, match="nothing to report.*halo.fits"):
        sw.report(str(tmp_path / "empty"), str(tmp_path / "none"))
    assert not (tmp_path / "none" / "index.html").exists()

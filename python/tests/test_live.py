"""Live from Python (live.py): replay publishes a small AO series into shared-memory streams
in one thread while live reads them in another; with regular stamps, no drops and the same
batch size live hands the stream the batches stream_files makes from the same files, so its
products equal stream_files'; the updates reach on_update; StopFlag ends a run cleanly;
errors raise with the library's message and leave no output."""
import os
import signal
import threading

import numpy as np
import pytest

import specklewfs as sw


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    d = tmp_path_factory.mktemp("live")
    s = d / "sim"
    sw.simulate_timeseries(str(s), pupn=66, pupdx=0.1, screen_n=512, ncubes=2, cube_frames=40, cube_gap=30,
                           start_offset=50.4, layer_speed=[30, 40], seed=2)
    sw.reduce([str(s / f"raw_{k:03d}.fits") for k in range(2)], str(d / "sci.fits"), dark=str(s / "dark.fits"),
              flat=str(s / "flat.fits"))
    sw.sync(str(d / "sci.fits"), str(s / "handshake.log"), str(d / "timing.txt"), ratio=(5, 8))
    sw.speckles(str(d / "timing.txt"), str(d / "sci.fits"), str(s / "actuators.fits"), str(d / "sp.fits"), recon="vk",
                write_recon=str(d / "recon.fits"))
    return d


def _model(d):
    return dict(recon=str(d / "recon.fits"), actuators=str(d / "sim" / "actuators.fits"))


def _replay_thread(d, shm, names, out, speed=1.0):
    """replay of the series into streams `names` (WFS, camera) in a thread at 1 kHz times
    speed; its result or exception in out"""
    def run():
        try:
            out["r"] = sw.replay(str(d / "sci.fits"), timing=str(d / "timing.txt"), shm_dir=str(shm),
                                 wfs_name=names[0], camera_name=names[1], wfs_rate=1000, speed=speed, depth=64,
                                 wait_reader=30,
                                 remove=True)
        except BaseException as e:  # noqa: BLE001 (raised again in the test's thread)
            out["e"] = e
    t = threading.Thread(target=run)
    t.start()
    return t


def test_live_on_replay_equals_stream_files(series, tmp_path):
    d = series
    shm = tmp_path / "shm"
    shm.mkdir()
    ref = sw.stream_files(str(d / "sci.fits"), str(tmp_path / "files.fits"), timing=str(d / "timing.txt"), batch=8,
                          every=16, **_model(d))
    rep, updates = {}, []
    t = _replay_thread(d, shm, ("w1", "c1"), rep)
    r = sw.live("w1", "c1", str(d / "sci.fits"), str(tmp_path / "live.fits"), shm_dir=str(shm), batch=8, max_wait=60,
                idle_exit=0.5, every=16, pupil_out=str(tmp_path / "pupil.fits"), pupil_source="halo",
                on_update=updates.append, **_model(d))
    t.join()
    assert "e" not in rep, rep.get("e")
    p = rep["r"]
    ncam = ref["camera_frames"]
    assert p["camera_frames"] == ncam and p["camera_dropped"] == 0 and p["wfs_dropped"] == 0
    assert p["wfs_rate"] == pytest.approx(1000) and p["ratio"] == pytest.approx(ref["ratio"], rel=1e-3)
    # every camera frame used, in batches of 8, with the WFS frames stream_files paired
    assert r["camera_frames"] == ncam and r["sync"]["used"] == ncam and r["sync"]["batches"] == -(-ncam // 8)
    assert r["sync"]["wfs_dropped"] == 0 and r["sync"]["incomplete"] == 0 and r["sync"]["no_wfs"] == 0
    assert r["wfs_frames"] == pytest.approx(ref["wfs_frames"], rel=1e-9)
    assert r["lag_count"] > 0 and 0 <= r["lag_median"] <= r["lag_max"] and r["data_seconds"] > 0
    for ext in ("HALO", "GAIN", "MEAN_SP", "RESMEAN"):
        a = sw.read_fits(str(tmp_path / "live.fits"), ext)[0]
        b = sw.read_fits(str(tmp_path / "files.fits"), ext)[0]
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.nanmax(np.abs(b)), equal_nan=True, err_msg=ext)
    # the updates: every 16 camera frames and the final one, with the pupil product's WFE
    assert len(updates) >= ncam // 16 and updates[-1]["final"] and updates[-1]["camera_frames"] == ncam
    assert all(not u["final"] for u in updates[:-1])
    assert [u["camera_frames"] for u in updates] == sorted(u["camera_frames"] for u in updates)
    last = updates[-1]
    assert 0 < last["valid_fraction"] <= 1 and last["median_snr"] > 0 and 0 < last["wfe_rms"] < 1e-6
    assert os.path.isfile(tmp_path / "pupil.fits")
    # the streams were removed at the end (remove=True)
    assert not any(f.name.startswith(("w1", "c1")) for f in shm.iterdir())


def test_stop_flag_and_update_errors(series, tmp_path):
    d = series
    shm = tmp_path / "shm"
    shm.mkdir()
    # StopFlag set after the second update: the streams' readers stop, the frames received
    # so far are used and the products written (the replay at a quarter of real time: 0.7 s
    # of data take 2.8 s, the two updates of 8 frames each about 0.4 s)
    stop, seen = sw.StopFlag(), []

    def on_update(u):
        seen.append(u)
        assert threading.current_thread() is threading.main_thread()  # the caller's thread
        if len(seen) == 2:
            stop.set()
    rep = {}
    t = _replay_thread(d, shm, ("w2", "c2"), rep, speed=0.25)
    r = sw.live("w2", "c2", str(d / "sci.fits"), str(tmp_path / "stopped.fits"), shm_dir=str(shm), batch=8,
                max_wait=60, idle_exit=0.5, every=8, stop=stop, on_update=on_update, **_model(d))
    t.join()
    assert stop.is_set() and "e" not in rep
    print(f"live stopped after {r['camera_frames']} of {rep['r']['camera_frames']} camera frames")
    assert 16 <= r["camera_frames"] < rep["r"]["camera_frames"] and seen[-1]["final"]
    assert sw.read_fits(str(tmp_path / "stopped.fits"), "HALO")[0].shape[-1] > 0
    # an exception in on_update ends the run and is raised to the caller
    def boom(u):
        raise KeyError("from on_update")
    rep = {}
    t = _replay_thread(d, shm, ("w3", "c3"), rep)
    with pytest.raises(KeyError, match="from on_update"):
        sw.live("w3", "c3", str(d / "sci.fits"), str(tmp_path / "boom.fits"), shm_dir=str(shm), batch=8,
                max_wait=60, idle_exit=0.5, every=8, on_update=boom, **_model(d))
    t.join()
    assert "e" not in rep
    # Ctrl-C (SIGINT while the library waits on the streams, no callback of one's own) ends the
    # run as the StopFlag does -- the frames so far used, the products written -- and then
    # raises KeyboardInterrupt; SIGINT's handler is Python's again afterwards
    rep = {}
    t = _replay_thread(d, shm, ("w4", "c4"), rep, speed=0.25)
    timer = threading.Timer(1.5, os.kill, (os.getpid(), signal.SIGINT))
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            sw.live("w4", "c4", str(d / "sci.fits"), str(tmp_path / "ctrlc.fits"), shm_dir=str(shm), batch=8,
                    max_wait=60, idle_exit=0.5, every=8, **_model(d))
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, old)
    t.join()
    assert "e" not in rep
    used = sw.fits.read_keys(str(tmp_path / "ctrlc.fits"), ["NFRAMES"])["NFRAMES"]
    print(f"live stopped by SIGINT after {used} of {rep['r']['camera_frames']} camera frames")
    assert 8 <= used < rep["r"]["camera_frames"]


def test_live_and_replay_errors(series, tmp_path):
    d = series
    shm = tmp_path / "shm"
    shm.mkdir()
    out = tmp_path / "x.fits"
    # no such stream within the timeout: the stream's name in the message, nothing written
    with pytest.raises(sw.Error, match="nowhere"):
        sw.live("nowhere", "cam", str(d / "sci.fits"), str(out), shm_dir=str(shm), timeout=0.3, **_model(d))
    assert not out.exists()
    with pytest.raises(sw.Error, match="missing.fits"):
        sw.live("w", "c", str(tmp_path / "missing.fits"), str(out), shm_dir=str(shm), timeout=0.3, **_model(d))
    assert not out.exists()
    with pytest.raises(ValueError, match="recon with actuators"):
        sw.live("w", "c", str(d / "sci.fits"), str(out), recon=str(d / "recon.fits"))
    with pytest.raises(ValueError, match="StopFlag"):
        sw.live("w", "c", str(d / "sci.fits"), str(out), stop=threading.Event(), **_model(d))
    with pytest.raises(sw.Error, match="dm-gain|dm_gain"):
        sw.live("w", "c", str(d / "sci.fits"), str(out), shm_dir=str(shm), dm_out="dm", dm_gain=-1,
                pupil_out=str(tmp_path / "p.fits"), **_model(d))
    with pytest.raises(ValueError, match="timing .* or wfs_log"):
        sw.replay(str(d / "sci.fits"), shm_dir=str(shm))
    with pytest.raises(ValueError, match="wfs_type"):
        sw.replay(str(d / "sci.fits"), timing=str(d / "timing.txt"), shm_dir=str(shm), wfs_type="int8")
    with pytest.raises(sw.Error, match="nothere.txt"):
        sw.replay(str(d / "sci.fits"), timing=str(tmp_path / "nothere.txt"), shm_dir=str(shm))
    assert not any(shm.iterdir())


def test_live_loop_equals_the_cli(tmp_path, cli):
    """live_loop: the NCP loop closed through the streams (cli_liveloop.sh's series, one
    correction): the residual falls (measured 90.7 -> 46.8 nm), live uses every camera frame,
    and the command line on the same settings prints the same table."""
    import subprocess
    keys = dict(pupn=66, pupdx=0.1, screen_n=1024, ncubes=3, cube_frames=60, cube_gap=150, layer_speed=[30, 40],
                vib_amp=0.6, jitter_amp=0.15, seed=1)
    stages = []
    r = sw.live_loop(str(tmp_path / "loop"), iterations=1, speed=4, modes=36,
                     progress=lambda stage, done, total: stages.append(stage), **keys)
    s = r["states"]
    print(f"live_loop: residual {s[0]['residual_rms'] * 1e9:.1f} -> {s[1]['residual_rms'] * 1e9:.1f} nm")
    assert len(s) == 2 and r["seconds"] > 0 and stages
    assert 80e-9 < s[0]["residual_rms"] < 100e-9 and s[1]["residual_rms"] < 0.75 * s[0]["residual_rms"]
    assert s[0]["frames_used"] == 180 and s[1]["estimate_err"] is None and s[1]["frames_used"] is None
    assert 0 < s[0]["estimate_err"] < s[0]["residual_rms"] and s[0]["dm_rms"] == 0 < s[1]["dm_rms"]
    assert os.path.isfile(tmp_path / "loop" / "iter_00" / "halo.fits")
    assert not any((tmp_path / "loop" / "shm").iterdir())
    args = [f"{k}={','.join(map(str, v)) if isinstance(v, list) else v}" for k, v in keys.items()]
    out = subprocess.run([cli, "liveloop", "-o", str(tmp_path / "cli"), *args, "--iterations", "1", "--speed", "4",
                          "--modes", "36"], check=True, capture_output=True, text=True).stdout
    rows = {int(x.split()[0]): x.split()[1:] for x in out.splitlines() if x.split()[:1] in (["0"], ["1"])}
    for k in range(2):
        assert float(rows[k][0]) == pytest.approx(s[k]["residual_rms"] * 1e9, abs=0.051), k
        assert float(rows[k][2]) == pytest.approx(s[k]["dm_rms"] * 1e9, abs=0.051), k
    with pytest.raises(sw.Error, match="iterations"):
        sw.live_loop(str(tmp_path / "bad"), iterations=0, **keys)
    with pytest.raises(ValueError, match="influence"):
        sw.live_loop(str(tmp_path / "bad"), influence="spline", **keys)

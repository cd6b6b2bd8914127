"""The speckle pipeline and the stream with a Python source: streaming numpy batches gives
the one-pass estimate."""
import numpy as np
import pytest

import specklewfs as sw

GEOM = sw.Geom(wavelen=1.6e-6, teldiam=2.0, obscur=0.1, pixscale=0.5, pupdx=0.05, pupn=40)
NF = 24
NSUB = 8
NSLOPES = 2 * NSUB * NSUB


@pytest.fixture(scope="module")
def data():
    """Random slopes, a camera schedule (3.5 WFS frames per exposure, straddling frames),
    the pipeline's fields, and science frames |Psi + g psi|^2 with a known static halo."""
    rng = np.random.default_rng(11)
    xy = sw.actuators_hexapolar(GEOM.teldiam, 0.4, 0.2)
    pipe = sw.Pipeline(GEOM, NF, NF, xy, NSLOPES, recon="svd", band="none")  # fields everywhere
    sched, nwfs = sw.schedule(3.5, 0.3, 120)
    slopes = rng.normal(size=(nwfs, NSLOPES)) * 2e-7
    fields = pipe.process(slopes, sched)
    static = pipe.flat_halo() * np.abs(fields[:, NF // 2, NF // 2]).mean() / np.abs(pipe.flat_halo()[NF // 2, NF // 2])
    psi = fields - static
    Psi = (rng.normal(size=(NF, NF)) + 1j * rng.normal(size=(NF, NF))) * np.abs(psi).std()
    g = 0.8
    science = np.abs(Psi + g * psi) ** 2
    return dict(xy=xy, pipe=pipe, sched=sched, slopes=slopes, fields=fields, static=static, psi=psi, Psi=Psi, g=g,
                science=science)


def batches(d, size):
    """The data set as a source would hand it over: per batch the WFS frames its
    exposures cover and the schedule as indices into them."""
    sched, n = d["sched"], len(d["sched"])
    for j in range(0, n, size):
        sc = sched[j:j + size].copy()
        lo = int(sc["first"].min())
        hi = int((sc["first"] + sc["count"]).max())
        sc["first"] -= lo
        yield d["slopes"][lo:hi], sc, d["science"][j:j + size]


def sh_as_linear(d, wfs_rate=False):
    """The Shack-Hartmann pipeline (SVD reconstructor, tip-tilt kept, no band) and its pieces
    as a linear model: T (pupn^2, nact) its interpolation, W its reconstructor, the basis
    (nact, pupn, pupn) T's columns on the pupil grid."""
    sh = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep", band="none", wfs_rate=wfs_rate)
    from specklewfs._lib import lib
    from specklewfs.telemetry import Sparse
    T = Sparse._take(lib.swfs_pipeline_model(sh._p).contents.T, owner=sh._owner).to_dense()
    return sh, T, np.array(sh.recon.W), T.T.reshape(-1, GEOM.pupn, GEOM.pupn)


def test_pipeline_matches_engine_pieces(data):
    """With tip-tilt kept, the pipeline is the engine over the model's reconstructor,
    interpolation and mask."""
    d = data
    p = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep", band="none")
    info = p.info
    assert info["band"] == 0 and info["band_out"] == 0
    assert info["nact"] == len(d["xy"]) and info["nslopes"] == NSLOPES and info["npup"] == 40
    assert 0 < info["recon_modes"] <= info["nact"]
    T, nout = sw.interp_ct_grid(d["xy"], 40, GEOM.pupdx, p.mask)
    assert nout == info["n_outside"] == 0
    e = sw.Engine(p.recon.W, T, p.mask, NF, NF, GEOM.alpha, GEOM.wavelen)
    a = p.process(d["slopes"], d["sched"])
    b = e.process(d["slopes"], d["sched"])
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * np.abs(b).max())
    # The default band: the same fields within nsub/2 lambda/D, 0 beyond.
    pb = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep")
    nsub = int(round(np.sqrt(NSLOPES / 2)))
    assert pb.info["band"] == nsub / 2
    yy, xx = np.indices((NF, NF))
    out = np.hypot(xx - NF // 2, yy - NF // 2) * GEOM.pixscale > nsub / 2
    assert pb.info["band_out"] == out.sum() > 0
    c = pb.process(d["slopes"], d["sched"])
    assert np.all(c[:, out] == 0)
    np.testing.assert_allclose(c[:, ~out], b[:, ~out], rtol=0, atol=1e-6 * np.abs(b).max())
    with pytest.raises(ValueError):
        sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", band=-1)
    # The time mean of what the pipeline reconstructed: T W s_bar over the exposures processed.
    m, nexp = p.mean_wavefront()
    assert nexp == len(d["sched"]) and m.shape == (40, 40)
    sched = d["sched"]
    sbar = np.zeros(NSLOPES)
    for x in sched:
        w = np.ones(x["count"])
        w[0] = x["w_first"]
        if x["count"] > 1:
            w[-1] = x["w_last"]
        sbar += (w[:, None] * d["slopes"][x["first"]:x["first"] + x["count"]]).sum(0) / w.sum() / len(sched)
    ref, rms = sw.wfe_remove_ptt((T.to_dense() @ (p.recon.W @ sbar)).reshape(40, 40), p.mask)
    inside = p.mask > 0
    assert rms > 0 and np.abs(m[inside] - ref[inside]).max() < 1e-4 * rms  # single-precision engine
    # A miss of the mean (a map's MEANMISS image) is added before piston, tip and tilt come out.
    yy, xx = (np.indices((40, 40)) - 19.5) / 20
    off = 30e-9 * (xx ** 2 - yy ** 2 + 0.5 * xx + 0.2)  # astigmatism, with a tilt and a piston
    p.mean_offset(off)
    m2, _ = p.mean_wavefront()
    want, _ = sw.wfe_remove_ptt(np.where(inside, off, 0.0), p.mask)
    assert np.abs((m2 - m)[inside] - want[inside]).max() < 1e-12 * np.abs(want).max()
    bad = off.copy()
    k = np.flatnonzero(inside)[100]  # inside the pupil: refused, the offset set before stays
    bad.flat[k] = np.nan
    with pytest.raises(sw.Error, match=rf"mean offset sample {k} \(x {k % 40}, y {k // 40}\) is not finite"):
        p.mean_offset(bad)
    bad.flat[k] = off.flat[k]
    bad[~inside] = np.nan  # outside it: not used
    p.mean_offset(bad)
    np.testing.assert_array_equal(p.mean_wavefront()[0], m2)
    np.testing.assert_array_equal(p.mean_wavefront()[0], m2)
    p.mean_offset(None)
    np.testing.assert_array_equal(p.mean_wavefront()[0], m)
    with pytest.raises(ValueError):
        p.mean_offset(off[:10])
    p.mean_reset()
    with pytest.raises(sw.Error):
        p.mean_wavefront()
    # The flat-slopes field is the unaberrated PSF, real and positive at the core.
    f = p.flat_halo()
    assert abs(f[NF // 2, NF // 2].imag) < 1e-9 * abs(f[NF // 2, NF // 2]) and f[NF // 2, NF // 2].real > 0
    assert np.abs(f).argmax() == (NF // 2) * NF + NF // 2
    # WFS-rate fields need tiptilt 'frame' or 'keep'; the library says so.
    with pytest.raises(sw.Error, match="SWFS_TT_FRAME or SWFS_TT_KEEP"):
        sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", wfs_rate=True)
    pw = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep", wfs_rate=True, band="none")
    w = pw.process_wfs(d["slopes"][:5])
    np.testing.assert_allclose(w, e.process_wfs(d["slopes"][:5]), atol=1e-6 * np.abs(w).max())


def test_pipeline_reconstructor_choices(data):
    d = data
    rng = np.random.default_rng(1)
    # Training slopes: random actuator wavefronts seen through D = S T, plus noise.
    model = sw.SpeckleModel(d["xy"], sw.aperture(40, GEOM.pupdx, GEOM.teldiam, GEOM.obscur), GEOM.pupdx,
                            GEOM.teldiam, NSUB)
    D = model.interaction_matrix()
    training = (D @ rng.normal(size=(len(d["xy"]), 200)) * 5e-8).T + 1e-9 * rng.normal(size=(200, NSLOPES))
    training[:, ~np.concatenate([model.wfs.valid.ravel()] * 2)] = 0  # unilluminated subapertures report 0
    vk = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, training=training)  # the default: von Karman MAP
    assert vk.info["ntrain"] == 200 and vk.info["noise_var"] > 0 and not vk.info["noise_given"]
    mp = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="map", training=training, slope_noise=1e-8)
    assert mp.info["noise_given"] and mp.info["noise_var"] == pytest.approx(1e-16)
    W = np.zeros((len(d["xy"]), NSLOPES))
    given = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=W, tiptilt="keep")
    out = given.process(d["slopes"][:8], sw.make_schedule(np.arange(4) * 2, 2))
    np.testing.assert_allclose(out, np.broadcast_to(given.flat_halo() * 2, out.shape), rtol=1e-6,
                               atol=1e-6 * np.abs(out).max())  # W = 0: two flat frames per exposure
    with pytest.raises(sw.Error, match="training") as e:
        sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES)  # vk without training slopes
    with pytest.raises(ValueError, match=r"recon: expected shape \(\d+, 128\), got \(3, 3\)"):
        sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=np.zeros((3, 3)))


@pytest.mark.parametrize("size", [1, 7, 120])
def test_streaming_numpy_batches_equals_one_pass(data, size):
    d = data
    one = sw.Accumulator(NF, NF).add(d["science"], d["psi"]).estimate(read_noise=0.5)
    s = sw.Stream(d["pipe"], static=d["static"], read_noise=0.5)
    updates = []
    s.run(batches(d, size), on_update=lambda st, final: updates.append((st.camera_frames, final)))
    assert s.camera_frames == 120 and updates[-1] == (120, True)
    assert s.wfs_frames == pytest.approx(120 * 3.5)
    np.testing.assert_array_equal(s.static_halo, d["static"])
    h = s.estimate()
    # One batch of everything is exactly the one-pass estimate over the pipeline's fields.
    # Smaller batches re-slice the WFS frames the single-precision engine reconstructs
    # together: the same to its precision (engine.h: ~1e-6 of the peak of psi). The maps
    # divide by g, the fourth root of a difference of variances, which amplifies that
    # (measured up to 2.4e-5 of HALO's peak for batches of 1 on this machine class).
    tol = 0 if size == 120 else 1e-4
    for name in ("HALO", "HALO_LF", "STAB", "GAIN", "MEAN_I", "MEAN_SP", "VAR_SP", "SNR"):
        ref = one.maps[name]
        np.testing.assert_allclose(h.maps[name], ref, rtol=0, atol=tol * np.abs(ref).max(), err_msg=name)
    assert h.frames == one.frames == 120
    # ... and it is the known halo: g and Psi recovered.
    assert np.median(np.abs(h.gain / d["g"] - 1)) < 0.05
    # (120 frames of non-Gaussian speckles: a rough check; an unrelated map would be ~1.4)
    assert np.median(np.abs(h.halo - d["Psi"])) < 0.3 * np.abs(d["Psi"]).mean()


def test_stream_push_updates_auto_static_and_errors(data):
    d = data
    a = sw.Stream(d["pipe"], static=d["static"], every=30)
    calls = []
    a.run(batches(d, 10), on_update=lambda st, final: calls.append((st.camera_frames, final)))
    assert [c for c in calls if not c[1]] and calls[-1] == (120, True)
    assert all(n % 10 == 0 for n, _ in calls)
    b = sw.Stream(d["pipe"], static=d["static"])
    for sl, sc, sci in batches(d, 10):
        b.push(sl, sc, sci)
    np.testing.assert_array_equal(b.accumulator().state(), a.accumulator().state())
    # 'auto': the unaberrated halo scaled to the first batch's core amplitude.
    c = sw.Stream(d["pipe"])
    assert c.static_halo is None
    c.run(batches(d, 40))
    np.testing.assert_allclose(c.static_halo, d["pipe"].flat_halo() * c.static_scale, rtol=1e-12)
    # max_frames stops early.
    m = sw.Stream(d["pipe"], static="none", max_frames=50).run(batches(d, 20))
    assert m.camera_frames == 50
    # A Python exception in the source stops the run and comes back as itself.

    def bad():
        yield next(batches(d, 5))
        raise KeyError("source broke")
    with pytest.raises(KeyError, match="source broke"):
        sw.Stream(d["pipe"]).run(bad())
    with pytest.raises(ValueError, match=r"science: expected shape \(5, 24, 24\), got \(5, 24, 23\)"):
        sl, sc, sci = next(batches(d, 5))
        sw.Stream(d["pipe"]).push(sl, sc, sci[:, :, :23])
    with pytest.raises(sw.Error, match="no") as e:
        sw.Stream(d["pipe"]).run([])
    assert e.value.status_name == "SWFS_ERR_NUMERIC"
    # a None among the batches is refused, not taken for the end (the batches after it were lost)
    bs = list(batches(d, 40))
    with pytest.raises(ValueError, match="the source gave None as a batch"):
        sw.Stream(d["pipe"], static=d["static"]).run([bs[0], None, bs[1]])


def test_linear_pipeline_equals_shack_hartmann(data):
    """The generic linear model (Pipeline.linear) with the Shack-Hartmann pipeline's own
    interpolation as the basis and its reconstructor as the control matrix gives the
    Shack-Hartmann pipeline's fields; the dense basis of the reconstructed wavefront per
    slope, with the slopes as coefficients, too; a units error is refused naming the size."""
    d = data
    sh, T, W, basis = sh_as_linear(d)
    lin = sw.Pipeline.linear(GEOM, NF, NF, basis, control=W, mask=sh.mask, tiptilt="keep")
    dense = sw.Pipeline.linear(GEOM, NF, NF, (T @ W).T.reshape(-1, GEOM.pupn, GEOM.pupn), mask=sh.mask,
                               tiptilt="keep", training=d["slopes"])
    ref = sh.process(d["slopes"], d["sched"])
    peak = np.abs(ref).max()
    for p, composed in ((lin, 0), (dense, 1)):
        assert p.info["composed"] == composed and p.recon is None and p.mask is None
        out = p.process(d["slopes"], d["sched"])
        assert np.abs(out - ref).max() < 2e-5 * peak
    assert dense.info["resid_rms"] > 0
    with pytest.raises(sw.Error, match=r"waves at .*scale \(1e\+06\)"):
        sw.Pipeline.linear(GEOM, NF, NF, basis, control=W * 1e6, mask=sh.mask, scale=1e6, training=d["slopes"])


def test_space_time_pipelines(data, tmp_path):
    """A space-time map in Python: the linear model's control cube (one plane per lag, as
    `learn --lags` writes it, read back by read_control) and a Shack-Hartmann Recon with lags
    take each frame as stack_lags' row. [W, 0] at lags (0, 2) gives W's fields, [0, W] W's two
    frames on (the series' last frame repeated past its end); one frame's slopes given to a
    space-time pipeline are refused, naming stack_lags; bad lags are refused."""
    d = data
    sh, _, W, basis = sh_as_linear(d, wfs_rate=True)
    s = d["slopes"]
    n = s.shape[0]
    lags = (0, 2)
    st = sw.stack_lags(s, lags)
    assert st.shape == (n, 2 * NSLOPES)
    np.testing.assert_array_equal(st[:, NSLOPES:][: n - 2], s[2:])
    np.testing.assert_array_equal(st[n - 2:, NSLOPES:], s[[n - 1, n - 1]])
    np.testing.assert_array_equal(sw.stack_lags(s, (0, -1), first=5, count=3)[:, NSLOPES:], s[4:7])
    ref = sw.Pipeline.linear(GEOM, NF, NF, basis, control=W, mask=sh.mask, tiptilt="keep", wfs_rate=True).process_wfs(s)
    peak = np.abs(ref).max()
    zero = np.zeros_like(W)
    path = str(tmp_path / "control.fits")
    sw.write_fits(path, np.stack([zero, W]), keys={"NLAGS": 2, "LAG1": 0, "LAG2": 2})
    cube, lg = sw.read_control(path)
    assert lg == lags and cube.shape == (2, W.shape[0], NSLOPES)
    for ctl, lg, shift in ((np.stack([W, zero]), lags, 0), (np.hstack([W, zero]), lags, 0), (cube, lg, 2)):
        p = sw.Pipeline.linear(GEOM, NF, NF, basis, control=ctl, mask=sh.mask, tiptilt="keep", lags=lg, wfs_rate=True)
        assert p.lags == lags and p.nvalues == NSLOPES and p.nslopes == 2 * NSLOPES
        assert p.info["nlags"] == 2
        out = p.process_wfs(st)
        np.testing.assert_allclose(out[: n - shift], ref[shift:], rtol=0, atol=2e-5 * peak)
        if shift:
            np.testing.assert_allclose(out[n - shift:], ref[[n - 1] * shift], rtol=0, atol=2e-5 * peak)
        with pytest.raises(ValueError, match=r"stack_lags\(slopes, pipeline.lags\)"):
            p.process_wfs(s)
    r = sw.Recon.from_matrix(np.hstack([zero, W]), lags=(0, 3))
    assert r.lags == (0, 3)
    shp = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=r, tiptilt="keep", band="none", wfs_rate=True)
    assert shp.lags == (0, 3) and shp.nslopes == 2 * NSLOPES and shp.info["nlags"] == 2
    out = shp.process_wfs(sw.stack_lags(s, (0, 3)))
    ref_sh = sh.process_wfs(s)
    np.testing.assert_allclose(out[: n - 3], ref_sh[3:], rtol=0, atol=2e-5 * np.abs(ref_sh).max())
    # per exposure, and in a stream: [W, 0] gives W's exposures; one frame's slopes refused
    exp = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=sw.Recon.from_matrix(np.hstack([W, zero]), lags=(0, 3)),
                      tiptilt="keep", band="none")
    ref_exp = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep", band="none").process(
        s, d["sched"])
    np.testing.assert_allclose(exp.process(sw.stack_lags(s, (0, 3)), d["sched"]), ref_exp, rtol=0,
                               atol=2e-5 * np.abs(ref_exp).max())
    sl, sc, sci = next(batches(d, 5))
    with pytest.raises(ValueError, match="stack_lags"):
        sw.Stream(exp).push(sl, sc, sci)
    sw.Stream(exp).push(sw.stack_lags(sl, (0, 3)), sc, sci)
    with pytest.raises(ValueError, match="needs lags="):
        sw.Pipeline.linear(GEOM, NF, NF, basis, control=np.stack([W, zero]), mask=sh.mask)
    with pytest.raises(sw.Error, match="no lag 0"):
        sw.Pipeline.linear(GEOM, NF, NF, basis, control=np.stack([W, zero]), mask=sh.mask, lags=(1, 2))
    with pytest.raises(ValueError, match="control matrix"):
        sw.Pipeline.linear(GEOM, NF, NF, basis, imat=W.T, mask=sh.mask, lags=lags)
    with pytest.raises(ValueError, match="not a multiple"):
        sw.Recon.from_matrix(np.hstack([zero, W[:, 1:]]), lags=(0, 3))


def test_pipeline_valid_map_takes_used_slopes_only(data):
    """With the AO system's valid-subaperture map the pipeline takes the used subapertures'
    slopes only (x then y, 2 nvalid values): the same fields as the full layout, the
    reconstructor in the narrow layout; a width of neither layout is refused."""
    d = data
    full = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep")
    nsub = int(round(np.sqrt(NSLOPES / 2)))
    assert full.info["nsub"] == nsub and full.info["nvalid"] > 0
    sl = np.asarray(d["slopes"])
    W = np.array(full.recon.W)
    from specklewfs._lib import lib
    from specklewfs.telemetry import ShackHartmann
    used = ShackHartmann(0, 0, None, 0, _ptr=lib.swfs_pipeline_model(full._p).contents.wfs,
                         _owner=full._owner).valid.ravel()  # the illumination rule's subapertures
    assert used.sum() == full.info["nvalid"] < nsub * nsub
    cols = np.concatenate([np.flatnonzero(used), nsub * nsub + np.flatnonzero(used)])
    narrow = sw.Pipeline(GEOM, NF, NF, d["xy"], len(cols), recon=W[:, cols], tiptilt="keep",
                         valid=used.reshape(nsub, nsub))
    assert narrow.info["nvalid"] == used.sum() and narrow.info["nslopes"] == len(cols)
    assert np.array_equal(np.array(narrow.recon.W), W[:, cols])
    ref = full.process(sl, d["sched"])
    out = narrow.process(np.ascontiguousarray(sl[:, cols]), d["sched"])
    assert np.abs(out - ref).max() < 1e-6 * np.abs(ref).max()
    with pytest.raises(sw.Error, match="valid-subaperture map"):
        sw.Pipeline(GEOM, NF, NF, d["xy"], len(cols) + 2, recon="svd", valid=used.reshape(nsub, nsub))
    with pytest.raises(ValueError, match="square"):
        sw.Pipeline(GEOM, NF, NF, d["xy"], len(cols), recon="svd", valid=np.ones((3, 4)))


def feed_framesync(fs, slopes, sched, science, period=1e-3, t0=10**12, drop_camera=()):
    """The data set as timestamped frames in time order (WFS frame k ends at (k + 1) periods,
    exposure j at its schedule's end, 0.3 + 3.5 (j + 1) frames; counters from 1), the
    batches collected as they come and, at the end, flushed."""
    ends = sched["first"] + sched["count"] - 1 + sched["w_last"]  # in WFS periods
    out, cam = [], 0
    for k in range(slopes.shape[0]):
        fs.add_wfs(slopes[k], k + 1, t0 + round((k + 1) * period * 1e9), now=0)
        while cam < len(sched) and ends[cam] <= k + 1 + 1e-9:
            if cam not in drop_camera:
                fs.add_camera(science[cam], cam + 1, t0 + round(ends[cam] * period * 1e9), now=0)
            cam += 1
        out += list(fs.batches(now=0))
    return out + list(fs.batches(flush=True, now=0))


def test_framesync_batches(data):
    """Timestamped frames through FrameSync (framesync.h) in Python: regular stamps give the
    schedule's exposures and, streamed, the estimate of the whole data set pushed at once
    (to the engine's precision); with a space-time pipeline's lags each row is its frame's
    values stacked at them (the series' ends clamped), and the space-time stream [W, 0]
    gives W's estimate; a dropped camera frame is counted and skipped."""
    d = data
    nexp = len(d["sched"])
    fs = sw.FrameSync(NSLOPES, (NF, NF), batch=16, max_wait=1e9)
    out = feed_framesync(fs, d["slopes"], d["sched"], d["science"])
    st = fs.stats
    assert st["used"] == nexp and st["camera_received"] == nexp and st["batches"] == len(out) == 8
    assert st["wfs_period"] == pytest.approx(1e-3, rel=1e-9) and st["camera_period"] == pytest.approx(3.5e-3, rel=1e-9)
    np.testing.assert_array_equal(np.concatenate([b["science"] for b in out]), d["science"])
    assert np.all(np.diff(np.concatenate([b["stamps"] for b in out])) > 0)
    for b in out:  # each exposure's frames are the schedule's, relative to its batch's rows
        j = np.flatnonzero((d["science"] == b["science"][0]).all(axis=(1, 2)))[0]
        ref = d["sched"][j:j + len(b["sched"])]
        lo = int(ref["first"].min())
        np.testing.assert_array_equal(b["sched"]["first"] + lo, ref["first"])
        np.testing.assert_array_equal(b["sched"]["count"], ref["count"])
        np.testing.assert_allclose(b["sched"]["w_first"], ref["w_first"], atol=1e-9)
        np.testing.assert_allclose(b["sched"]["w_last"], ref["w_last"], atol=1e-9)
        np.testing.assert_array_equal(b["slopes"][: int((b["sched"]["first"] + b["sched"]["count"]).max())],
                                      d["slopes"][lo: lo + int((b["sched"]["first"] + b["sched"]["count"]).max())])
    one = sw.Stream(d["pipe"], static=d["static"]).push(d["slopes"], d["sched"], d["science"]).estimate()
    live = sw.Stream(d["pipe"], static=d["static"]).run(out).estimate()
    for name in ("HALO", "GAIN", "MEAN_SP"):
        ref = one.maps[name]
        np.testing.assert_allclose(live.maps[name], ref, rtol=0, atol=1e-4 * np.abs(ref).max(), err_msg=name)
    # a space-time pipeline: rows stacked at its lags, clamped at the series' ends
    W = np.array(d["pipe"].recon.W)
    stp = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=sw.Recon.from_matrix(np.hstack([W, 0 * W, 0 * W]),
                                                                                   lags=(0, -2, 3)), band="none")
    code = np.arange(d["slopes"].shape[0], dtype=float)[:, None] * np.ones(NSLOPES)  # each value its frame
    fsl = sw.FrameSync(NSLOPES, (NF, NF), batch=16, max_wait=1e9, lags=stp.lags)
    assert fsl.lags == (0, -2, 3) and fsl.nslopes == stp.nslopes == 3 * NSLOPES
    n = code.shape[0]
    for b in feed_framesync(fsl, code, d["sched"], d["science"]):
        t = b["slopes"][:, 0]
        np.testing.assert_array_equal(b["slopes"][:, NSLOPES], np.clip(t - 2, 0, n - 1))
        np.testing.assert_array_equal(b["slopes"][:, 2 * NSLOPES], np.clip(t + 3, 0, n - 1))
    fsl = sw.FrameSync(NSLOPES, (NF, NF), batch=16, max_wait=1e9, lags=stp.lags)
    st_est = sw.Stream(stp, static=d["static"]).run(feed_framesync(fsl, d["slopes"], d["sched"],
                                                                   d["science"])).estimate()
    ref = one.maps["HALO"]
    np.testing.assert_allclose(st_est.maps["HALO"], ref, rtol=0, atol=1e-4 * np.abs(ref).max())
    # a camera frame that never arrives: counted from the counters, its batch split there
    fsd = sw.FrameSync(NSLOPES, (NF, NF), batch=16, max_wait=1e9)
    outd = feed_framesync(fsd, d["slopes"], d["sched"], d["science"], drop_camera=(40,))
    assert fsd.stats["camera_dropped"] == 1 and fsd.stats["used"] == nexp - 1
    assert sum(len(b["sched"]) for b in outd) == nexp - 1
    with pytest.raises(ValueError, match=r"values: expected shape \(128\), got \(5,\)"):
        fsd.add_wfs(np.zeros(5), 999, 10**13)
    with pytest.raises(ValueError, match="nvals"):
        sw.FrameSync(0, (NF, NF))


def test_linear_pipeline_from_files(data, tmp_path):
    """Pipeline.from_files builds the linear model's pipeline from its files as stream and
    live do: a space-time control cube's lags from its keys (the same fields as
    Pipeline.linear with the arrays), a map's MEANMISS image as the mean offset (the same mean
    wavefront as mean_offset given it), and a basis of another grid refused naming the file."""
    d = data
    sh, _, W, basis = sh_as_linear(d)
    sw.write_fits(str(tmp_path / "basis.fits"), basis, geom=GEOM)
    cube = np.stack([W, 0.5 * W, -0.25 * W])
    sw.write_fits(str(tmp_path / "st.fits"), cube, keys={"NLAGS": 3, "LAG1": 0, "LAG2": -2, "LAG3": 4})
    lin = dict(basis=str(tmp_path / "basis.fits"), control=str(tmp_path / "st.fits"))
    p = sw.Pipeline.from_files(GEOM, NF, NF, lin, mask=sh.mask, tiptilt="keep", wfs_rate=True)
    assert p.lags == (0, -2, 4) and p.nvalues == NSLOPES and p.nslopes == 3 * NSLOPES and p.meanmiss_rms == 0
    q = sw.Pipeline.linear(GEOM, NF, NF, basis, control=cube, lags=(0, -2, 4), mask=sh.mask, tiptilt="keep",
                           wfs_rate=True)
    st = sw.stack_lags(d["slopes"], p.lags)
    a, b = p.process_wfs(st), q.process_wfs(st)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * np.abs(b).max())
    # a per-frame map with its miss of the mean as an image on the pupil grid
    y, x = np.indices((GEOM.pupn, GEOM.pupn)) - GEOM.pupn / 2
    miss = 30e-9 * (x ** 2 - y ** 2) / (GEOM.pupn / 2) ** 2 * (sh.mask > 0)
    sw.write_fits(str(tmp_path / "mm.fits"), {"C": W, "MEANMISS": miss})
    pm = sw.Pipeline.from_files(GEOM, NF, NF, dict(basis=lin["basis"], control=str(tmp_path / "mm.fits")),
                                mask=sh.mask)
    qm = sw.Pipeline.linear(GEOM, NF, NF, basis, control=W, mask=sh.mask)
    qm.mean_offset(miss)
    assert pm.lags == () and 5e-9 < pm.meanmiss_rms < 30e-9
    for pl in (pm, qm):
        pl.process(d["slopes"], d["sched"])
    np.testing.assert_allclose(pm.mean_wavefront()[0], qm.mean_wavefront()[0], rtol=0, atol=1e-6 * np.abs(miss).max())
    small = sw.Geom(wavelen=GEOM.wavelen, teldiam=GEOM.teldiam, obscur=GEOM.obscur, pixscale=GEOM.pixscale,
                    pupdx=GEOM.pupdx * 2, pupn=GEOM.pupn // 2)
    with pytest.raises(sw.Error, match="basis.fits"):
        sw.Pipeline.from_files(small, NF, NF, lin)


def test_sh_pipeline_from_map_file(data, tmp_path):
    """Pipeline.from_map builds the Shack-Hartmann model's pipeline from a map file as stream
    and live do (swfs_sh_pipeline): the fields of Pipeline given the same matrix; a space-time
    map's lags from its keys; the map's MEANMISS (per actuator) as the mean offset; a valid map
    of another size and a pyramid's telemetry refused, naming the file."""
    d = data
    sh = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon="svd", tiptilt="keep", band="none")
    W = np.array(sh.recon.W)
    sw.Recon.from_matrix(W).write(str(tmp_path / "W.fits"))
    sw.actuators_write(d["xy"], str(tmp_path / "act.fits"))
    p = sw.Pipeline.from_map(GEOM, NF, NF, tmp_path / "W.fits", tmp_path / "act.fits", tiptilt="keep", band="none")
    assert p.lags == () and p.nslopes == NSLOPES and p.meanmiss_rms == 0
    a, b = p.process(d["slopes"], d["sched"]), sh.process(d["slopes"], d["sched"])
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max())
    # a space-time map (learn --lags' layout: one block per lag, NLAGS / LAGk)
    Wst = np.hstack([W, 0.5 * W, -0.25 * W])
    sw.Recon.from_matrix(Wst, lags=(0, -2, 4)).write(str(tmp_path / "Wst.fits"))
    pst = sw.Pipeline.from_map(GEOM, NF, NF, str(tmp_path / "Wst.fits"), d["xy"], tiptilt="keep", band="none",
                               wfs_rate=True)
    qst = sw.Pipeline(GEOM, NF, NF, d["xy"], NSLOPES, recon=sw.Recon.from_matrix(Wst, lags=(0, -2, 4)),
                      tiptilt="keep", band="none", wfs_rate=True)
    assert pst.lags == (0, -2, 4) and pst.nvalues == NSLOPES and pst.nslopes == 3 * NSLOPES
    st = sw.stack_lags(d["slopes"], pst.lags)
    a, b = pst.process_wfs(st), qst.process_wfs(st)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9 * np.abs(b).max())
    # the map's miss of the residual's mean: a focus of 20 nm peak on the actuators
    r = np.hypot(d["xy"][:, 0], d["xy"][:, 1]) / np.hypot(d["xy"][:, 0], d["xy"][:, 1]).max()
    c = 20e-9 * (2 * r ** 2 - 1)
    sw.write_fits(str(tmp_path / "Wmm.fits"), {"W": W, "MEANMISS": (c - c.mean())[None, :]})
    pm = sw.Pipeline.from_map(GEOM, NF, NF, str(tmp_path / "Wmm.fits"), str(tmp_path / "act.fits"), tiptilt="keep",
                              band="none")
    assert 2e-9 < pm.meanmiss_rms < 20e-9
    for pl in (p, pm):
        pl.mean_reset()
        pl.process(d["slopes"], d["sched"])
    diff = pm.mean_wavefront()[0] - p.mean_wavefront()[0]
    inside = sh.mask > 0
    assert np.sqrt(np.mean(diff[inside] ** 2)) == pytest.approx(pm.meanmiss_rms, rel=1e-3)
    yy, xx = np.indices(diff.shape) - (GEOM.pupn - 1) / 2
    assert np.corrcoef(diff[inside], (xx ** 2 + yy ** 2)[inside])[0, 1] > 0.99
    # refused, naming the file: a valid map of another size, a pyramid's telemetry
    sw.write_fits(str(tmp_path / "valid5.fits"), np.ones((5, 5)))
    with pytest.raises(sw.Error, match="valid5.fits"):
        sw.Pipeline.from_map(GEOM, NF, NF, str(tmp_path / "W.fits"), d["xy"], valid=str(tmp_path / "valid5.fits"))
    sw.write_fits(str(tmp_path / "pyr.fits"), d["slopes"][:10], keys={"WFSTYPE": "PYRAMID", "NSUB": NSUB})
    with pytest.raises(sw.Error, match=r"pyr.fits: WFSTYPE = 'PYRAMID'"):
        sw.Pipeline.from_map(GEOM, NF, NF, str(tmp_path / "W.fits"), d["xy"], telemetry=str(tmp_path / "pyr.fits"))

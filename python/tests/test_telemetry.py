"""WFS model, reconstructors, interpolation, the speckle model, the engine, the MFT."""
import os
import re

import numpy as np
import pytest

import specklewfs as sw

NPUP, DX, DIAM = 40, 0.05, 2.0
WAVELEN, PIXSCALE, NF = 1.6e-6, 0.5, 24
ALPHA = PIXSCALE * DX / DIAM


def coords(n=NPUP, dx=DX):
    c = (np.arange(n) - (n - 1) / 2) * dx
    return np.meshgrid(c, c)


def mft(field, nfx=NF, nfy=NF, alpha=ALPHA):
    n = field.shape[0]
    u = np.arange(n) - (n - 1) / 2
    Ex = np.exp(-2j * np.pi * alpha * np.outer(np.arange(nfx) - nfx // 2, u))
    Ey = np.exp(-2j * np.pi * alpha * np.outer(np.arange(nfy) - nfy // 2, u))
    return Ey @ field @ Ex.T


@pytest.fixture(scope="module")
def model():
    xy = sw.actuators_hexapolar(DIAM, 0.4, 0.2)
    mask = sw.aperture(NPUP, DX, DIAM, 0.1)
    return sw.SpeckleModel(xy, mask, DX, DIAM, 8, rcond=1e-3)


def test_mft_matches_the_convention():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(NPUP, NPUP)) + 1j * rng.normal(size=(NPUP, NPUP))
    m = sw.MFT(NPUP, NF, NF + 2, ALPHA)
    np.testing.assert_allclose(m.forward(f), mft(f, NF, NF + 2), rtol=1e-10, atol=1e-10)
    g = rng.normal(size=(NF + 2, NF)) + 1j * rng.normal(size=(NF + 2, NF))
    # The inverse is the adjoint: <F f, g> = <f, F^H g>.
    assert np.vdot(g, m.forward(f)) == pytest.approx(np.vdot(m.inverse(g), f), rel=1e-10)


def test_engine_against_numpy():
    """One 'actuator' whose influence is the x coordinate: a slope s tilts the wavefront
    by s x. The engine's field is the MFT of P exp(2 pi i s x / lambda), core-referenced."""
    X, Y = coords()
    P = sw.aperture(NPUP, DX, DIAM, 0.1)
    T = sw.Sparse.from_dense(X.reshape(-1, 1) * (P.reshape(-1, 1) > 0))
    e = sw.Engine(np.array([[1.0]]), T, P, NF, NF, ALPHA, WAVELEN)
    assert e.npin == int(P.sum()) and e.nthreads == 1
    s = np.array([[0.0], [0.3 * WAVELEN / DIAM], [-1.1 * WAVELEN / DIAM]])
    out = e.process_wfs(s)
    for k in range(3):
        h = mft(P * np.exp(2j * np.pi * s[k, 0] * X / WAVELEN))
        c = h[NF // 2, NF // 2]
        ref = h * np.exp(-1j * np.angle(c))
        np.testing.assert_allclose(out[k], ref, rtol=0, atol=2e-6 * np.abs(ref).max())
    # A wavefront tilt z = s x puts the star at theta = s (docs/conventions.md's sign): -1.1 lambda/D
    # is 2.2 pixels of 0.5 lambda/D toward -x, +0.3 lambda/D 0.6 pixels toward +x.
    assert np.unravel_index(np.abs(out[2]).argmax(), out[2].shape) == (NF // 2, NF // 2 - 2)
    assert np.unravel_index(np.abs(out[1]).argmax(), out[1].shape) == (NF // 2, NF // 2 + 1)
    # Exposures: process == add_wfs/end_exposure, weights included.
    sched = sw.make_schedule([0, 1], [2, 2], [0.5, 1.0], [1.0, 0.25])
    a = e.process(s, sched)
    e.add_wfs(s[0], 0.5)
    e.add_wfs(s[1], 1.0)
    b0 = e.end_exposure()
    e.add_wfs(s[1], 1.0)
    e.add_wfs(s[2], 0.25)
    b1 = e.end_exposure()
    np.testing.assert_allclose(a, np.stack([b0, b1]), rtol=0, atol=1e-6 * np.abs(b0).max())
    f0 = P * np.exp(2j * np.pi * s[0, 0] * X / WAVELEN)
    f1 = P * np.exp(2j * np.pi * s[1, 0] * X / WAVELEN)
    h = mft(0.5 * f0 + f1)
    np.testing.assert_allclose(a[0], h * np.exp(-1j * np.angle(h[NF // 2, NF // 2])), atol=2e-6 * np.abs(h).max())
    with pytest.raises(ValueError, match=r"sched: exposures need 5 WFS frames, slopes has 3"):
        e.process(s, sw.make_schedule([3], [2]))
    with pytest.raises(sw.Error, match="interpolation matrix is 1600x1, expected 1600x2"):
        sw.Engine(np.ones((2, 1)), T, P, NF, NF, ALPHA, WAVELEN)
    with pytest.raises(sw.Error, match="not finite"):
        e.process_wfs(np.array([[np.nan]]))


def test_schedule():
    s, need = sw.schedule(6.48, 0.4, 3)
    assert need == 20  # ceil(0.4 + 3 * 6.48)
    assert list(s["first"]) == [0, 6, 13] and list(s["count"]) == [7, 8, 7]
    np.testing.assert_allclose(s["w_first"], [0.6, 0.12, 0.64], atol=1e-12)
    np.testing.assert_allclose(s["w_last"], [0.88, 0.36, 0.84], atol=1e-12)
    # Every exposure integrates 6.48 WFS frames.
    w = s["w_first"] + s["w_last"] + (s["count"] - 2)
    np.testing.assert_allclose(w, 6.48, atol=1e-12)
    # A camera faster than the WFS: each exposure interpolates the two WFS frames whose
    # centres bracket its own (centres 0.8, 1.6, 2.4 -> frames 0-1, 1-2, 1-2), weights summing to 0.8.
    s, need = sw.schedule(0.8, 0.4, 3)
    assert need == 3 and list(s["first"]) == [0, 1, 1] and list(s["count"]) == [2, 2, 2]
    np.testing.assert_allclose(s["w_first"], [0.56, 0.72, 0.08], atol=1e-12)
    np.testing.assert_allclose(s["w_last"], [0.24, 0.08, 0.72], atol=1e-12)
    with pytest.raises(ValueError, match="invalid arguments"):
        sw.schedule(0.05, 0, 3)


def test_interpolation_and_dm_modes(model):
    X, Y = coords()
    xy = model.xy
    T, nout = sw.interp_ct_grid(xy, NPUP, DX, model.mask)
    assert nout == 0 and T.shape == (NPUP * NPUP, len(xy))
    # Clough-Tocher reproduces planes exactly inside the hull.
    plane = 0.3 + 2.0 * xy[:, 0] - 1.5 * xy[:, 1]
    z = (T @ plane).reshape(NPUP, NPUP)
    inside = model.mask > 0
    np.testing.assert_allclose(z[inside], (0.3 + 2.0 * X - 1.5 * Y)[inside], atol=1e-10)
    np.testing.assert_allclose(model.T.to_dense(), T.to_dense(), atol=0)
    modes = sw.dm_modes(T, model.mask)
    # Modes 0-2 (zero bending energy) span piston, tip and tilt over the pupil; mode 3 not.
    A = np.stack([np.ones(inside.sum()), X[inside], Y[inside]], 1)
    for k in range(4):
        m = (T @ modes[:, k]).reshape(NPUP, NPUP)[inside]
        res = m - A @ np.linalg.lstsq(A, m, rcond=None)[0]
        assert (np.std(res) < 1e-3 * np.std(m) + 1e-3 * abs(m.mean())) == (k < 3), k


def test_shack_hartmann_and_reconstructors(model):
    wfs = model.wfs
    assert wfs.nsub == 8 and wfs.nslopes == 128 and wfs.valid.shape == (8, 8) and 0 < wfs.nvalid <= 64
    X, Y = coords()
    # The slopes of a tilt z = a x + b y are (a, b) in every valid subaperture.
    s = wfs.measure((1e-6 * X - 2e-6 * Y) * model.mask)
    v = wfs.valid.ravel()
    np.testing.assert_allclose(s[:64][v], 1e-6, rtol=1e-9)
    np.testing.assert_allclose(s[64:][v], -2e-6, rtol=1e-9)
    assert np.all(s[:64][~v] == 0)
    np.testing.assert_allclose(sw.slopes_remove_tiptilt(s, wfs.valid)[np.concatenate([v, v])], 0, atol=1e-18)
    D = model.interaction_matrix()
    assert D.shape == (128, len(model.xy))
    # The truncated SVD is numpy's pseudo-inverse with the same cut.
    r = sw.Recon.svd(D, rcond=1e-3)
    U, sv, Vt = np.linalg.svd(D, full_matrices=False)
    keep = sv > 1e-3 * sv[0]
    np.testing.assert_allclose(r.sv, sv, rtol=1e-10)
    assert r.nmodes == keep.sum()
    Wnp = (Vt[keep].T / sv[keep]) @ U[:, keep].T
    np.testing.assert_allclose(r.W, Wnp, atol=1e-9 * np.abs(Wnp).max())
    r5 = sw.Recon.svd(D, rcond=0, max_modes=5)
    assert r5.nmodes == 5
    # A wavefront the DM can make comes back from its slopes (up to piston and tilt).
    rng = np.random.default_rng(3)
    zact = rng.normal(size=len(model.xy)) * 1e-7
    zt = (model.T @ zact).reshape(NPUP, NPUP)
    zr = (model.T @ r.apply(wfs.measure(zt))).reshape(NPUP, NPUP)
    err, truth_p, truth_ptt = sw.wfe_compare(zr, zt, model.mask)
    assert err < 0.2 * truth_ptt, (err, truth_ptt)
    # MAP reconstructors from telemetry, with the noise fixed tiny: W D -> the identity on
    # the modes the data excite (all of them here).
    slopes = (D @ rng.normal(size=(len(model.xy), 400)) * 1e-7).T
    rm = sw.Recon.map(D, slopes, noise_var=1e-30)
    P_ = Vt[keep].T @ Vt[keep]  # projector on the sensed modes
    np.testing.assert_allclose(rm.W @ D @ P_, P_, atol=1e-3)
    assert rm.noise_var == 1e-30 and 0 < rm.dof <= len(model.xy)
    rv = sw.Recon.vk(D, model.xy, 10.0, slopes, noise_var=1e-24)
    assert rv.W.shape == (len(model.xy), 128) and np.isfinite(rv.W).all()
    assert rv.dof == pytest.approx(np.trace(rv.W @ D), rel=1e-6)
    C = sw.vk_covariance(model.xy, 10.0)
    np.testing.assert_allclose(np.diag(C), 1)
    np.testing.assert_allclose(C, C.T)
    d = np.hypot(*(model.xy[:, None] - model.xy[None]).transpose(2, 0, 1))
    assert np.all(np.diff(C[0][np.argsort(d[0])]) <= 1e-12)  # decreasing with distance
    noisy = slopes + 1e-9 * rng.normal(size=slopes.shape) * np.concatenate([v, v])
    assert sw.slopes_noise_var(D, noisy) == pytest.approx(1e-18, rel=0.3)


def test_recon_and_actuator_files(model, tmp_path):
    r = sw.Recon.svd(model.interaction_matrix(), rcond=1e-2)
    p = str(tmp_path / "recon.fits")
    r.write(p)
    np.testing.assert_array_equal(sw.Recon.read(p).W, r.W)
    a = str(tmp_path / "act.fits")
    sw.actuators_write(model.xy, a)
    np.testing.assert_array_equal(sw.actuators_read(a), model.xy)
    with pytest.raises(sw.Error) as e:
        sw.Recon.read(str(tmp_path / "none.fits"))
    assert "none.fits" in e.value.message
    # Tip-tilt projection: the projected reconstructor ignores mean slopes.
    rp = sw.Recon.svd(model.interaction_matrix(), rcond=1e-2).project_tiptilt(model.wfs.valid)
    v = np.concatenate([model.wfs.valid.ravel()] * 2).astype(float)
    tilt = np.concatenate([model.wfs.valid.ravel() * 1e-6, model.wfs.valid.ravel() * 0.0])
    np.testing.assert_allclose(rp.apply(tilt), 0, atol=1e-12)
    assert v.sum() > 0


def test_speckle_model_and_tilt(model):
    assert model.n_outside == 0 and model.nslopes == 128 and model.recon.W.shape == (len(model.xy), 128)
    m2 = sw.SpeckleModel(model.xy, model.mask, DX, DIAM, 8, remove_tiptilt=False)
    W_ext, R = m2.recon_tilt()
    assert W_ext.shape == (len(model.xy), 130) and R.shape == (2, 128)
    # The extended reconstructor makes no tilt from slopes; the two extra inputs are tilts.
    e = m2.engine(NF, NF, ALPHA, WAVELEN, recon=W_ext)
    sched = sw.make_schedule([0, 2], [2, 2])
    s = np.zeros((4, 128))
    xs, so = sw.speckles_expand(s, R, sched)
    assert xs.shape == (4, 130) and list(so["first"]) == [0, 2]
    out = e.process(xs, so)
    assert out.shape == (2, NF, NF)
    cube = out.copy()
    sw.speckles_subtract_static(cube)
    np.testing.assert_allclose(cube.mean(0), 0, atol=1e-12 * np.abs(out).max())
    with pytest.raises(ValueError, match="writable C-contiguous complex128"):
        sw.speckles_subtract_static(out.astype(np.complex64))


def test_square_actuators_and_geometry_file(tmp_path):
    # A square grid clipped to a circle: every actuator within diam/2 + margin, a whole grid.
    xy = sw.actuators_square(6.5, 0.45, 0.1)
    r = np.hypot(xy[:, 0], xy[:, 1])
    assert len(xy) > 150 and r.max() <= 3.35 + 1e-12
    np.testing.assert_allclose(np.round(xy / 0.45) * 0.45, xy, atol=1e-12)
    # Its Clough-Tocher interpolation reproduces planes (the neighbourhoods of a square grid
    # once left the gradient fit undetermined).
    T, nout = sw.interp_ct_grid(xy, NPUP, DX, None)
    X, Y = coords()
    plane = 0.2 + 1.5 * xy[:, 0] - 0.7 * xy[:, 1]
    z = (T @ plane).reshape(NPUP, NPUP)
    inside = np.hypot(X, Y) < 3.0
    np.testing.assert_allclose(z[inside], (0.2 + 1.5 * X - 0.7 * Y)[inside], atol=1e-9)
    # The --geom file: KEY = VALUE lines; what it lacks stays missing.
    f = tmp_path / "geom.txt"
    f.write_text("# a camera's geometry\nWAVELEN = 3.8e-6\npixscale 0.25\nPUPN = 163\n")
    g = sw.read_geom_file(str(f))
    assert g.wavelen == 3.8e-6 and g.pixscale == 0.25 and g.pupn == 163 and np.isnan(g.pupdx)
    f.write_text("WAVELEN = 3.8\n")
    with pytest.raises(sw.Error, match="WAVELEN"):
        sw.read_geom_file(str(f))


def test_wind_from_slopes(cli, tmp_path):
    """The dominant layer's wind from a closed loop's slopes, in Python and through
    `specklewfs wind`: the same numbers, the layer's speed within 10 % and its direction
    within 5 deg, and no second layer; with two layers both found within 10 % and 5 deg;
    bad input refused."""
    import subprocess
    out = str(tmp_path / "ts")
    sw.simulate_timeseries(out, pupn=66, pupdx=0.1, screen_n=1024, ncubes=2, cube_frames=100, cube_gap=100,
                           nlayers=1, layer_frac=1, layer_speed=15, layer_dir=120, seed=6)
    s, _ = sw.read_fits(os.path.join(out, "slopes_000.fits"))
    e = sw.wind_from_slopes(s, 12, 6.5 / 12, 527)
    assert e["found"] and e["nused"] >= 2 and sum(L["used"] for L in e["lags"]) == e["nused"]
    assert abs(e["speed"] / 15 - 1) < 0.1 and abs(e["direction"] - 120) < 5
    assert e["vx"] < 0 < e["vy"]
    r = subprocess.run([cli, "wind", os.path.join(out, "slopes_000.fits"), "--teldiam", "6.5"], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    m = re.search(r"wind: ([0-9.]+) m/s toward ([0-9.]+) deg", r.stdout)
    assert m and float(m.group(1)) == round(e["speed"], 2) and float(m.group(2)) == round(e["direction"], 1)
    # one layer: the stacking finds no other
    assert len(e["layers"]) == 1 and e["layers"][0]["speed"] == e["speed"]
    assert e["next_signif"] < e["threshold"] < e["layers"][0]["signif"]
    assert re.search(r"^layers: 1 found", r.stdout, re.M)
    # two layers of equal share: the second found by the stacking, in Python and printed
    out2 = str(tmp_path / "ts2")
    sw.simulate_timeseries(out2, pupn=66, pupdx=0.1, screen_n=1024, ncubes=2, cube_frames=100, cube_gap=100,
                           nlayers=2, layer_frac="0.5,0.5", layer_speed="15,7", layer_dir="120,330", seed=6)
    s2, _ = sw.read_fits(os.path.join(out2, "slopes_000.fits"))
    e2 = sw.wind_from_slopes(s2, 12, 6.5 / 12, 527)
    assert len(e2["layers"]) == 2, e2["layers"]
    found = sorted((L["speed"], L["direction"]) for L in e2["layers"])
    assert abs(found[0][0] / 7 - 1) < 0.1 and abs(found[0][1] - 330) < 5
    assert abs(found[1][0] / 15 - 1) < 0.1 and abs(found[1][1] - 120) < 5
    r = subprocess.run([cli, "wind", os.path.join(out2, "slopes_000.fits"), "--teldiam", "6.5"], capture_output=True,
                       text=True)
    m = re.search(r"^layer 2: ([0-9.]+) m/s toward ([0-9.]+) deg", r.stdout, re.M)
    assert m and float(m.group(1)) == round(e2["layers"][1]["speed"], 2), r.stdout
    with pytest.raises(sw.Error, match="30 WFS frames"):
        sw.wind_from_slopes(s[:30], 12, 6.5 / 12, 527)
    r = subprocess.run([cli, "wind", os.path.join(out, "slopes_000.fits")], capture_output=True, text=True)
    assert r.returncode != 0 and "--teldiam" in r.stderr

"""Accumulators, the estimator, halo products and checkpoints."""
import os

import numpy as np
import pytest

import specklewfs as sw


def synth(nframes, nx=12, ny=10, g=0.7, seed=0, noise=0.0):
    """I = |Psi + g psi|^2 (+ Gaussian noise) with random complex Gaussian psi (Phi_sp
    varying over the map) and a known static halo Psi."""
    rng = np.random.default_rng(seed)
    Psi = (rng.normal(size=(ny, nx)) + 1j * rng.normal(size=(ny, nx))) * 0.7
    sp = 0.5 + rng.random((ny, nx))  # speckle rms per pixel
    psi = (rng.normal(size=(nframes, ny, nx)) + 1j * rng.normal(size=(nframes, ny, nx))) * sp / np.sqrt(2)
    I = np.abs(Psi + g * psi) ** 2
    if noise:
        I += noise * rng.normal(size=I.shape)
    return Psi, psi, I


def test_recovers_known_halo_and_gain():
    g = 0.7
    Psi, psi, I = synth(20000, g=g)
    acc = sw.Accumulator(12, 10).add(I, psi)
    assert acc.frames == 20000 and acc.skipped == 0
    # The paper's per-pixel g (eq:scale-factor): a fourth root of a difference of noisy
    # variances, so a pixel may fall out; the median is still right.
    h = acc.estimate(g_smooth=0)
    assert h.n_valid >= 118 and h.npix == 120
    assert np.nanmedian(np.abs(h.gain_pix / g - 1)) < 0.01
    rel = np.abs(h.halo - Psi) / np.abs(Psi)
    assert np.median(rel) < 0.04
    # The regularized g (the default) on a constant g: g to 0.5 %, Psi to the sampling
    # noise of <psi' I> (~1/sqrt(N) of the speckle power).
    hr = acc.estimate()
    assert hr.g_smooth == sw.G_SMOOTH_DEFAULT
    assert np.max(np.abs(hr.gain / g - 1)) < 0.005
    rel = np.abs(hr.halo - Psi) / np.abs(Psi)
    assert np.median(rel) < 0.025 and np.percentile(rel, 90) < 0.05
    # eq:PSI-LowFreq: |HALO_LF|^2 = Phi_I - g^2 Phi_sp, with the phase of <psi' I>.
    assert np.median(np.abs(np.abs(hr.halo_lf) / np.abs(Psi) - 1)) < 0.01
    assert np.median(np.abs(np.angle(hr.halo_lf / Psi))) < 0.03
    # Phi_sp and the visibility-free quantities: Phi_sp = E|psi|^2 = sp^2 (synth's rms).
    np.testing.assert_allclose(hr.mean_sp, np.mean(np.abs(psi) ** 2, 0), rtol=1e-3)


def test_moments_are_the_sample_moments():
    Psi, psi, I = synth(500, seed=1)
    I[7, 3, 4] = np.nan  # skipped pixel-frame
    h = sw.Accumulator(12, 10).add(I, psi).estimate(read_noise=0.1, gain=50.0)
    assert h.skipped == 1 and h.frames == 500 and h.nframes[3, 4] == 499 and h.nframes[0, 0] == 500
    ok = np.isfinite(I)
    n = ok.sum(0)
    Ii = np.where(ok, I, 0)
    mi = Ii.sum(0) / n
    m_psi = (psi * ok).sum(0) / n
    d = np.where(ok, psi - m_psi, 0)
    stab = (d * np.where(ok, I - mi, 0)).sum(0) / n
    phi_sp = (np.abs(d) ** 2).sum(0) / n
    var_i = (np.where(ok, I - mi, 0) ** 2).sum(0) / (n - 1) - (0.1 ** 2 + mi / 50.0)
    circ = np.abs((d ** 2).sum(0) / n) / phi_sp
    np.testing.assert_allclose(h.mean_i, mi, rtol=1e-12)
    np.testing.assert_allclose(h.stab, stab, rtol=1e-10)
    np.testing.assert_allclose(h.mean_sp, phi_sp, rtol=1e-12)
    np.testing.assert_allclose(h.var_i, var_i, rtol=1e-10)
    np.testing.assert_allclose(h.circ, circ, rtol=1e-9)
    np.testing.assert_allclose(h.halo, stab / (h.gain * phi_sp), rtol=1e-12)
    # eq:visibility and eq:SNR with sigma_noise^2 = read_noise^2 + Phi_I / gain.
    np.testing.assert_allclose(h.visib, 2 * np.abs(stab) / (mi * np.sqrt(phi_sp)), rtol=1e-10)
    np.testing.assert_allclose(h.snr, 2 * np.abs(stab) / np.sqrt((0.01 + mi / 50) * phi_sp), rtol=1e-10)
    assert h.read_noise == 0.1 and h.gain_e == 50.0


def test_merge_of_two_halves_equals_single_pass():
    _, psi, I = synth(3001, seed=2)
    one = sw.Accumulator(12, 10).add(I, psi)
    a = sw.Accumulator(12, 10).add(I[:1400], psi[:1400])
    b = sw.Accumulator(12, 10)
    for k in range(1400, 3001):  # frame by frame, too
        b.add(I[k], psi[k])
    a.merge(b)
    assert a.frames == one.frames == 3001
    np.testing.assert_allclose(a.state(), one.state(), rtol=1e-11, atol=1e-9)
    ha, h1 = a.estimate(), one.estimate()
    for name, m in h1.maps.items():
        np.testing.assert_allclose(ha.maps[name], m, rtol=1e-9, atol=1e-12, err_msg=name)


def test_export_import_carries_the_regression_statistics():
    """The flat state (moments + regression statistics) round-trips exactly, and an
    impossible state is refused with the library's message."""
    _, psi, I = synth(500, seed=4)
    a = sw.Accumulator(12, 10).add(I, psi)
    assert a.has_regress
    st = a.export()
    assert st.shape == ((15 + 21) * 120 + 4,) and st[-4] == 500
    b = sw.Accumulator.from_export(st, 12, 10)
    assert b.frames == 500 and b.has_regress
    np.testing.assert_array_equal(b.export(), st)
    bad = st.copy()
    bad[0] = -1  # a negative count
    with pytest.raises(sw.Error, match="count"):
        sw.Accumulator.from_export(bad, 12, 10)
    with pytest.raises(ValueError, match="state"):
        sw.Accumulator.from_export(st[:-1], 12, 10)


def test_checkpoints_roundtrip_and_merge_files(tmp_path):
    _, psi, I = synth(900, seed=3)
    geom = sw.Geom(wavelen=3.8e-6, teldiam=6.5, obscur=0.1, pixscale=0.25, pupdx=0.04, pupn=163)
    a = sw.Accumulator(12, 10).add(I[:400], psi[:400])
    b = sw.Accumulator(12, 10).add(I[400:], psi[400:])
    pa, pb = str(tmp_path / "a.fits"), str(tmp_path / "b.fits")
    a.save(pa, geom=geom, provenance=["part a"])
    b.save(pb, geom=geom)
    la = sw.Accumulator.load(pa)
    assert np.array_equal(la.state(), a.state()) and la.frames == 400  # bit for bit
    assert la.geom == geom
    m = sw.merge_files([pa, pb])
    assert m.geom == geom and m.frames == 900
    a.merge(b)
    assert np.array_equal(m.state(), a.state())
    np.testing.assert_allclose(m.state(), sw.Accumulator(12, 10).add(I, psi).state(), rtol=1e-11, atol=1e-9)


def test_halo_write_read_roundtrip(tmp_path):
    _, psi, I = synth(300, seed=4)
    h = sw.Accumulator(12, 10).add(I, psi).estimate(read_noise=1.0)
    geom = sw.Geom(wavelen=1e-6, teldiam=2.0, obscur=0.0, pixscale=0.5, pupdx=0.05, pupn=40)
    p = str(tmp_path / "halo.fits")
    h.write(p, geom=geom, provenance=["test"])
    r = sw.Halo.read(p)
    assert r.geom == geom and r.frames == 300
    assert set(r.maps) == set(h.maps)
    for name, m in h.maps.items():
        np.testing.assert_array_equal(r.maps[name], m, err_msg=name)
    # The extensions through the generic FITS reader: same arrays, complex HALO.
    d, g = sw.read_fits(p, "HALO")
    assert d.dtype == np.complex128 and np.array_equal(d, h.halo) and g == geom


def test_bad_shapes_raise_valueerror_naming_the_argument():
    acc = sw.Accumulator(12, 10)
    with pytest.raises(ValueError, match=r"psi: expected shape \(5, 10, 12\), got \(5, 12, 10\)"):
        acc.add(np.zeros((5, 10, 12)), np.zeros((5, 12, 10), complex))
    with pytest.raises(ValueError, match=r"science: expected shape \(\?, 10, 12\), got \(3, 10, 11\)"):
        acc.add(np.zeros((3, 10, 11)), np.zeros((3, 10, 11), complex))
    with pytest.raises(ValueError, match="science: expected real values"):
        acc.add(np.zeros((10, 12), complex), np.zeros((10, 12), complex))
    assert acc.frames == 0


def test_library_errors_carry_message_and_status(tmp_path):
    # Shapes the library checks itself: its message comes through.
    with pytest.raises(sw.Error) as e:
        sw.Accumulator(12, 10).merge(sw.Accumulator(10, 12))
    assert e.value.status_name == "SWFS_ERR_SHAPE" and e.value.description == "shape mismatch" and "10x12" in e.value.message and "12x10" in e.value.message
    assert e.value.function == "swfs_accum_merge"
    missing = str(tmp_path / "no-such-halo.fits")
    with pytest.raises(sw.Error) as e:
        sw.Halo.read(missing)
    assert missing in e.value.message and e.value.status_name == "SWFS_ERR_IO"
    assert missing in str(e.value)
    # An estimate with nothing valid is SWFS_ERR_NUMERIC with the library's explanation.
    with pytest.raises(sw.Error, match="no pixel has a defined scale factor") as e:
        sw.Accumulator(4, 4).add(np.ones((3, 4, 4)), np.zeros((3, 4, 4), complex)).estimate()
    with pytest.raises(sw.Error, match="accumulator of size 0x3"):
        sw.Accumulator(0, 3)


def test_speckles_must_be_finite():
    _, psi, I = synth(4, seed=5)
    psi[2, 1, 1] = np.inf
    with pytest.raises(sw.Error) as e:
        sw.Accumulator(12, 10).add(I, psi)
    assert e.value.function == "swfs_accum_add"


def test_halo_from_arrays_and_views():
    _, psi, I = synth(200, seed=6)
    h = sw.Accumulator(12, 10).add(I, psi).estimate()
    halo = h.halo
    del h  # the views keep the library's halo alive
    assert np.isfinite(halo).all() and halo.shape == (10, 12)
    x = np.ones((10, 12), complex)
    hh = sw.Halo.from_arrays(x, stab=x, stab_err=np.ones((10, 12)))
    assert hh.halo is x and hh.halo_lf is x and hh.gain is None
    with pytest.raises(ValueError, match=r"stab: expected shape \(10, 12\), got \(12, 10\)"):
        sw.Halo.from_arrays(x, stab=np.ones((12, 10), complex))
    with pytest.raises(TypeError, match="unknown halo map 'bogus'"):
        sw.Halo.from_arrays(x, bogus=x)


def test_phase_shift_map():
    # Four phase steps (Sec. 2.1): <I e^{i eta}> = Psi psi^*, subject phase recovered.
    rng = np.random.default_rng(7)
    Psi = rng.normal(size=(3, 4)) + 1j * rng.normal(size=(3, 4))
    ref_phase = rng.uniform(-np.pi, np.pi, (3, 4))
    psi = 0.8 * np.exp(1j * ref_phase)
    eta = np.array([0, np.pi / 2, np.pi, 3 * np.pi / 2])
    I = np.abs(Psi[None] + psi[None] * np.exp(1j * eta)[:, None, None]) ** 2
    stab, phase, hi, lo = sw.phase_shift_map(I, eta, ref_phase)
    np.testing.assert_allclose(stab, Psi * np.conj(psi), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.exp(1j * phase), np.exp(1j * np.angle(Psi)), atol=1e-12)
    truth = np.abs(Psi) ** 2
    assert np.all(np.isclose(hi, truth, rtol=1e-10) | np.isclose(lo, truth, rtol=1e-10))


def test_choose_halo_by_the_self_check():
    """choose_halo (`pupil A.fits B.fits`): halos of the same frames from the exact speckles
    and from speckles with an error; the exact ones explain the most and are chosen; halos of
    other frames are refused."""
    Psi, psi, I = synth(3000, seed=4, noise=0.05)
    rng = np.random.default_rng(5)
    noisy = psi + 0.3 * (rng.normal(size=psi.shape) + 1j * rng.normal(size=psi.shape))
    ha = sw.Accumulator(12, 10).add(I, psi).estimate()
    hb = sw.Accumulator(12, 10).add(I, noisy).estimate()
    best, ex, n = sw.choose_halo([hb, ha], names=["noisy", "exact"])
    assert best == 1 and n == 120 and ex[1] > ex[0] > 0 and ex[1] > 0.9
    _, _, I2 = synth(3000, seed=6, noise=0.05)
    hc = sw.Accumulator(12, 10).add(I2, psi).estimate()
    with pytest.raises(sw.Error, match="other and exact: the science intensity's variance differs"):
        sw.choose_halo([ha, hc], names=["exact", "other"])

"""The remaining bindings: reset, geometry reads, modal reconstructor, model reconstructor
swaps, the wind fit."""
import os

import numpy as np
import pytest

import specklewfs as sw


def test_accumulator_reset_and_fields():
    rng = np.random.default_rng(0)
    a = sw.Accumulator(3, 2).add(rng.normal(size=(4, 2, 3)), rng.normal(size=(4, 2, 3)) + 0j)
    np.testing.assert_array_equal(a.field("N"), 4)
    a.reset()
    assert a.frames == 0 and np.all(a.state() == 0)
    with pytest.raises(ValueError):
        a.field("NOPE")


def test_read_geom(tmp_path):
    g = sw.Geom(wavelen=1e-6, teldiam=2, obscur=0.1, pixscale=0.5, pupdx=0.05, pupn=40)
    p = str(tmp_path / "g.fits")
    sw.write_fits(p, np.zeros((2, 2)), geom=g)
    assert sw.read_geom(p) == g and g.require() is g
    with pytest.raises(sw.Error, match="PIXSCALE"):
        sw.Geom(wavelen=1e-6, teldiam=2, obscur=0.1, pupdx=0.05, pupn=40).require("test geometry")


def test_modal_reconstructor_and_model_swaps():
    xy = sw.actuators_hexapolar(2.0, 0.4, 0.2)
    mask = sw.aperture(40, 0.05, 2.0, 0.1)
    m = sw.SpeckleModel(xy, mask, 0.05, 2.0, 8)
    wfs = sw.ShackHartmann(8, 2.0, mask, 0.05)
    np.testing.assert_array_equal(wfs.valid, m.wfs.valid)
    np.testing.assert_array_equal(wfs.S.to_dense(), m.wfs.S.to_dense())
    D = m.interaction_matrix()
    modes = sw.dm_modes(m.T, mask)
    r = sw.Recon.modal(D, modes, 1, 20)
    # W = V_K pinv(D V_K): W D is the identity on the K modes kept.
    V = modes[:, 1:21]
    np.testing.assert_allclose(r.W @ D @ V, V, atol=1e-6 * np.abs(V).max())
    rng = np.random.default_rng(2)
    slopes = (D @ rng.normal(size=(len(xy), 300)) * 5e-8).T
    W0 = m.recon.W.copy()
    m.set_map(slopes, noise_var=1e-20)
    assert not np.allclose(m.recon.W, W0) and m.recon.noise_var == 1e-20
    m.set_vk(slopes, L0=10.0, noise_var=1e-20)
    assert m.recon.W.shape == W0.shape and m.recon.noise_var == 1e-20


def test_fit_wind():
    """Speckles whose phase turns at k theta.v (a frozen flow v): fit_wind finds v."""
    geom = sw.Geom(wavelen=3.8e-6, teldiam=6.5, obscur=0.1, pixscale=0.25, pupdx=0.04, pupn=163)
    v = np.array([30.0, -20.0])
    dt, n, nf = 0.01, 3000, 12
    i = np.arange(nf) - nf // 2
    tx, ty = np.meshgrid(i * geom.pixscale * geom.wavelen / geom.teldiam, i * geom.pixscale * geom.wavelen /
                         geom.teldiam)
    rate = 2 * np.pi / geom.wavelen * (tx * v[0] + ty * v[1])  # PHRATE = +k theta.v (coherence.h)
    rng = np.random.default_rng(4)
    a = 0.97 * np.exp(-1j * rate * dt)  # Gamma(tau) ~ a^tau: arg turns by +rate per second
    psi = np.empty((n, nf, nf), complex)
    psi[0] = rng.normal(size=(nf, nf))
    for t in range(1, n):
        psi[t] = a * psi[t - 1] + np.sqrt(1 - 0.97 ** 2) * (rng.normal(size=(nf, nf)) + 1j * rng.normal(size=(nf, nf)))
    c = sw.coherence(psi, dt, lags=[0, 1, 2, 3, 4, 5])
    np.testing.assert_allclose(np.median((c.phrate / np.where(rate == 0, np.nan, rate))[rate != 0]), 1, rtol=0.05)
    vx, vy = c.fit_wind(geom)
    np.testing.assert_allclose([vx, vy], v, rtol=0.05)


def test_bad_sizes_and_replaced_reconstructors():
    """Sizes and counts the C side takes as size_t are refused when negative or fractional (they
    wrapped to 2^64 - n: a crash, or a read before the slopes), a path with a NUL is refused (the C
    side would open the name up to it), high Zernike orders are right (R(1) = 1: the alternating sum
    gave 48.6 at n = 50), and a Recon taken from a model stays what it was after set_map replaces
    the model's (its W was freed memory)."""
    rng = np.random.default_rng(2)
    with pytest.raises(ValueError, match="first must be whole numbers of WFS frames >= 0"):
        sw.make_schedule([0, -2 ** 20], [4, 2 ** 20 + 3])
    with pytest.raises(ValueError, match="count must be whole numbers"):
        sw.make_schedule([0], [2.5])
    for f in (lambda: sw.slopes_white_noise(rng.normal(size=(40, 128)), -8),
              lambda: sw.wind_from_slopes(rng.normal(size=(40, 128)), -8, 0.25, 1000),
              lambda: sw.interp_ct_grid(sw.actuators_hexapolar(2.0, 0.4, 0.2), -40, 0.05)):
        with pytest.raises(ValueError, match="expected a whole number from"):
            f()
    with pytest.raises(ValueError, match="NUL"):
        sw.write_fits("nul\0x.fits", np.ones((2, 2)))
    # fractional sizes and lags were truncated (pupn 40.7 -> 40, lag 1.7 -> 1)
    with pytest.raises(ValueError, match=r"Geom.pupn: expected a whole number from 0 to \d+, got 40.7"):
        sw.Geom(wavelen=1e-6, teldiam=2, obscur=0.1, pixscale=0.5, pupdx=0.05, pupn=40.7).to_c()
    with pytest.raises(ValueError, match="stack_lags: lag: expected a whole number"):
        sw.stack_lags(rng.normal(size=(10, 4)), [0, 1.7])
    with pytest.raises(ValueError, match="stack_lags: first: expected a whole number"):
        sw.stack_lags(rng.normal(size=(10, 4)), [0, 1], first=-1)
    with pytest.raises(ValueError, match="coherence: lags: expected a whole number"):
        sw.coherence(rng.normal(size=(8, 4, 4)) + 0j, 1e-3, lags=[0, 2.5])
    # a geometry that is not one (it leaked as AttributeError / TypeError from inside)
    with pytest.raises(TypeError, match="geom: expected a specklewfs.Geom, a dict of its fields or None, got tuple"):
        sw.reduce(["raw.fits"], "sci.fits", geom=(1e-6, 2.0))
    with pytest.raises(ValueError, match=r"geom: unknown keys \['wavelength'\]"):
        sw.reduce(["raw.fits"], "sci.fits", geom=dict(wavelength=1e-6))
    # an option spelled wrong names itself and its spellings (it leaked as KeyError/TypeError)
    with pytest.raises(ValueError, match="coherence: method: expected one of 'auto', 'fft', 'direct', got 'fast'"):
        sw.coherence(rng.normal(size=(8, 4, 4)) + 0j, 1e-3, method="fast")
    with pytest.raises(ValueError, match=r"tiptilt: expected one of 'exposure', 'frame', 'keep', got \['frame'\]"):
        sw.speckles("timing.txt", "science.fits", "actuators.fits", "out.fits", tiptilt=["frame"])
    assert [sw.zernike(n, n % 2, 1.0, 0.0) for n in (50, 51, 200)] == pytest.approx([1, 1, 1], abs=1e-9)
    xy = sw.actuators_hexapolar(2.0, 0.4, 0.2)
    m = sw.SpeckleModel(xy, sw.aperture(40, 0.05, 2.0, 0.1), 0.05, 2.0, 8)
    r = m.recon
    W, s = r.W, rng.normal(size=(3, m.nslopes))
    W0, a0 = W.copy(), r.apply(s)
    m.set_map(rng.normal(size=(300, m.nslopes)) * 1e-7)
    junk = [rng.normal(size=10000) for _ in range(50)]  # reuse of freed memory, if it were freed
    assert np.array_equal(W, W0) and np.array_equal(r.apply(s), a0) and not np.array_equal(m.recon.W, W0)
    del junk
    with pytest.raises(sw.Error, match="not finite"):
        m.set_map(np.full((300, m.nslopes), np.nan))
    assert np.all(np.isfinite(m.recon.W))  # the model keeps the map it had
    # validity flags and masks of another length than the library reads (it read past their end)
    with pytest.raises(ValueError, match="project_tiptilt: valid has 3 flags, expected one per subaperture, 64"):
        sw.Recon.from_matrix(rng.normal(size=(10, 128))).project_tiptilt(valid=np.ones(3))
    with pytest.raises(ValueError, match="slopes_remove_tiptilt: valid has 2 flags, expected one per subaperture, 64"):
        sw.slopes_remove_tiptilt(rng.normal(size=(1, 128)), valid=np.ones(2))
    with pytest.raises(ValueError, match=r"dm_modes: mask: expected the square pupil grid of T's 1600 rows, got shape \(40, 41\)"):
        sw.dm_modes(m.T, np.zeros((40, 41)))
    W = rng.normal(size=(10, 128))
    W.flags.writeable = False
    with pytest.raises(ValueError, match="W is read-only"):
        sw.Recon.from_matrix(W).project_tiptilt()


def test_accumulator_and_simulation_writes_are_whole(small_sim, tmp_path):
    """An Accumulator of a size whose pixel count would wrap is refused (2^33 x 2^33 was taken
    as an empty one); a cube with a non-finite speckle value adds no frame at all (the frames
    before it went in, and a retry counted them twice); SimResult.write writes its four files or
    none (science.fits and speckles.fits stayed when truth.fits could not be written)."""
    with pytest.raises(sw.Error, match="accumulator of size 8589934592x8589934592: expected 1 to 65536 pixels a side"):
        sw.Accumulator(2 ** 33, 2 ** 33)
    with pytest.raises(ValueError, match="Accumulator: nx: expected a whole number from 0"):
        sw.Accumulator(-1, 5)
    rng = np.random.default_rng(3)
    a = sw.Accumulator(3, 2)
    psi = rng.normal(size=(20, 2, 3)) + 1j * rng.normal(size=(20, 2, 3))
    psi[13, 1, 2] = np.nan
    with pytest.raises(sw.Error, match=r"pixel \(2, 1\) of frame 13 is not finite; no frame of the 20 added"):
        a.add(rng.normal(size=(20, 2, 3)), psi)
    assert a.frames == 0
    d = tmp_path / "sim"
    d.mkdir()
    (d / "truth.fits").mkdir()  # the third file cannot be written
    with pytest.raises(sw.Error):
        small_sim.write(str(d))
    assert sorted(p.name for p in d.iterdir()) == ["truth.fits"]
    # a folder given as bytes is that folder (it became one named "b'...'")
    b = tmp_path / "bytes"
    b.mkdir()
    small_sim.write(os.fsencode(str(b)))
    assert sorted(p.name for p in b.iterdir()) == ["pupil.fits", "science.fits", "speckles.fits", "truth.fits"]

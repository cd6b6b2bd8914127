"""Coherence maps of a speckle process with a known mutual coherence function."""
import numpy as np
import pytest

import specklewfs as sw

DT = 0.002  # [s] between WFS frames
RHO, OMEGA = 0.9, 0.1  # per-frame decorrelation and phase rotation [rad/frame]


@pytest.fixture(scope="module")
def cube():
    """AR(1) speckles psi_{t+1} = rho e^{i omega} psi_t + sqrt(1 - rho^2) n_t:
    Gamma(tau)/Gamma(0) = <psi_t psi*_{t+tau}> / <|psi|^2> = rho^tau e^{-i omega tau}."""
    rng = np.random.default_rng(5)
    n, ny, nx = 6000, 6, 7
    noise = (rng.normal(size=(n, ny, nx)) + 1j * rng.normal(size=(n, ny, nx))) / np.sqrt(2)
    psi = np.empty((n, ny, nx), complex)
    psi[0] = noise[0]
    a, b = RHO * np.exp(1j * OMEGA), np.sqrt(1 - RHO ** 2)
    for t in range(1, n):
        psi[t] = a * psi[t - 1] + b * noise[t]
    return psi * 3.0


def test_coherence_maps(cube, tmp_path):
    c = sw.coherence(cube, DT, exposure=4 * DT)
    assert c.mean_sp.shape == (6, 7) and c.n_valid == 42 and c.nframes == 6000
    np.testing.assert_array_equal(c.lag_frames, sw.default_lags())
    np.testing.assert_allclose(c.lags, sw.default_lags() * DT)
    assert c.mcf.shape == (37, 6, 7)
    np.testing.assert_allclose(np.median(c.mean_sp), 9.0, rtol=0.05)
    tau0 = -1 / (2 * np.log(RHO)) * DT  # |gamma| = e^{-1/2}
    np.testing.assert_allclose(np.median(c.tau0), tau0, rtol=0.05)
    np.testing.assert_allclose(np.median(c.phrate), -OMEGA / DT, rtol=0.05)  # d arg Gamma / d tau
    np.testing.assert_allclose(np.median(c.trot), (np.pi / 2) / (OMEGA / DT), rtol=0.05)
    g5 = c.mcf[5]
    np.testing.assert_allclose(np.median(np.abs(g5)), RHO ** 5, rtol=0.05)
    # SNR factor of a 4-frame exposure: (1/M)[1 + 2 sum_{0<k<M} (1 - k/M) Re gamma_k].
    M = 4
    expect = (1 + 2 * sum((1 - k / M) * RHO ** k * np.cos(OMEGA * k) for k in range(1, M))) / M
    np.testing.assert_allclose(np.median(c.snr_fact), expect, rtol=0.03)
    np.testing.assert_allclose(c.snr_map(4 * DT), c.snr_fact, rtol=1e-12)
    # The same from the dense MCF of one pixel through snr_factor().
    assert sw.snr_factor(c.dense[2, 3], DT, 4 * DT) == pytest.approx(c.snr_fact[2, 3], rel=1e-12)
    # ... which is the box-average power loss of the actual data.
    box = cube[: (6000 // M) * M].reshape(-1, M, 6, 7).mean(1)
    box -= box.mean(0)
    measured = np.mean(np.abs(box) ** 2, 0) / np.mean(np.abs(cube - cube.mean(0)) ** 2, 0)
    np.testing.assert_allclose(np.median(measured), expect, rtol=0.05)
    # FFT and direct sums agree.
    d = sw.coherence(cube[:500], DT, method="direct", lags=[0, 1, 2, 5])
    f = sw.coherence(cube[:500], DT, method="fft", lags=[0, 1, 2, 5])
    assert d.method == "direct" and f.method == "fft"
    np.testing.assert_allclose(d.mcf, f.mcf, atol=1e-10)
    # Product written and read back.
    geom = sw.Geom(wavelen=3.8e-6, teldiam=6.5, obscur=0.1, pixscale=0.25, pupdx=0.04, pupn=163)
    p = str(tmp_path / "coh.fits")
    c.write(p, geom)
    # (COH.fits stores single precision)
    np.testing.assert_array_equal(sw.read_fits(p, "TAU0")[0], c.tau0.astype(np.float32))
    np.testing.assert_array_equal(sw.read_fits(p, "MCF")[0], c.mcf.astype(np.complex64))
    # An input cube with FRAMEDT is read back as such.
    q = str(tmp_path / "sp.fits")
    sw.write_fits(q, cube[:50], geom=geom, keys={"FRAMEDT": DT})
    cc, dt, g, exposure = sw.read_coherence_input(q)
    assert dt == DT and g == geom and exposure == 0 and np.array_equal(cc, cube[:50])
    sw.write_fits(q, cube[:50])
    with pytest.raises(sw.Error, match="FRAMEDT"):
        sw.read_coherence_input(q)


def test_coherence_helpers():
    # eq:ExpLimit-Wind: D / (2 theta wind); the bandwidth radius lambda/dlambda.
    assert sw.exposure_limit_wind(2.0, 6.5, 10.0) == pytest.approx(6.5 / 40)
    assert sw.exposure_limit_wind(0.0, 6.5, 10.0) == np.inf
    assert sw.bandwidth_radius(0.2) == pytest.approx(5.0)
    assert sw.snr_factor(np.ones(10), DT, 5 * DT) == pytest.approx(1.0)
    assert np.isnan(sw.snr_factor(np.ones(3), DT, 5 * DT))
    with pytest.raises(sw.Error, match="framedt|frame"):
        sw.coherence(np.zeros((1, 2, 2), complex), DT)

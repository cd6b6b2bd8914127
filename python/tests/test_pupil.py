"""The pupil step, wavefront comparison, apertures."""
import numpy as np
import pytest

import specklewfs as sw

GEOM = sw.Geom(wavelen=1e-6, teldiam=1.0, obscur=0.0, pixscale=0.5, pupdx=1.0 / 32, pupn=32)


def grid(n, dx):
    c = (np.arange(n) - (n - 1) / 2) * dx
    return np.meshgrid(c, c)  # X varies along axis 1 (x fastest)


def mft_forward(field, geom, nfx, nfy):
    """docs/conventions.md's focal field, written out with numpy: sum_x P(x) exp(-2 pi i theta.x / lambda)."""
    n = field.shape[0]
    u = np.arange(n) - (n - 1) / 2
    a = geom.alpha
    Ex = np.exp(-2j * np.pi * a * np.outer(np.arange(nfx) - nfx // 2, u))  # (nfx, n)
    Ey = np.exp(-2j * np.pi * a * np.outer(np.arange(nfy) - nfy // 2, u))
    return Ey @ field @ Ex.T


def known_wavefront():
    X, Y = grid(GEOM.pupn, GEOM.pupdx)
    R = np.hypot(X, Y) / (GEOM.teldiam / 2)
    mask = sw.aperture(GEOM.pupn, GEOM.pupdx, GEOM.teldiam, GEOM.obscur)
    th = np.arctan2(Y, X)
    # Trefoil + astigmatism, ~40 nm rms: well inside +-lambda/2.
    w = 60e-9 * sw.zernike(3, 3, R, th) + 40e-9 * sw.zernike(2, 2, R, th)
    return w * mask, mask


def test_pupil_of_a_known_field():
    w, mask = known_wavefront()
    field = mask * np.exp(2j * np.pi * w / GEOM.wavelen)
    # 64 pixels of 0.5 lambda/D = the full field of the 32-sample pupil (1/alpha = 64): the
    # inverse transform is then exact, and so must be the wavefront.
    Psi = mft_forward(field, GEOM, 64, 64)
    h = sw.Halo.from_arrays(Psi, geom=GEOM)
    r = sw.pupil_estimate(h, weight="none")
    assert r.wfe.shape == (32, 32) and r.field.dtype == np.complex128
    assert np.array_equal(r.mask, mask)
    err, truth_p, truth_ptt = sw.wfe_compare(r.wfe, w, mask)
    assert truth_p > 20e-9
    assert err < 1e-9 * truth_p, (err, truth_p)
    # A window of 20 x 20 lambda/D low-passes the field: a few per cent error, no more.
    r40 = sw.pupil_estimate(sw.Halo.from_arrays(mft_forward(field, GEOM, 40, 40), geom=GEOM), weight="none")
    err40 = sw.wfe_compare(r40.wfe, w, mask)[0]
    assert 1e-3 * truth_p < err40 < 0.1 * truth_p, (err40, truth_p)
    np.testing.assert_allclose(r.surface, r.wfe / 2)
    np.testing.assert_allclose(r.amplitude, np.abs(r.field))
    inside = mask > 0
    assert abs(r.wfe[inside].mean()) < 1e-12 and np.all(r.wfe[~inside] == 0)  # piston removed, 0 outside
    assert r.wfe_rms == pytest.approx(np.sqrt(np.mean(r.wfe[inside] ** 2)), rel=1e-9)
    assert r.strehl == pytest.approx(np.exp(-(2 * np.pi * r.wfe_rms / GEOM.wavelen) ** 2), rel=1e-9)
    # The source option: 'halo' reads HALO, which here is the same map.
    r2 = sw.pupil_estimate(h, source="halo", weight="none")
    np.testing.assert_array_equal(r2.wfe, r.wfe)
    # The amplitude is flat inside the pupil to a few per cent (the field up to a scale).
    amp = r.amplitude[inside]
    assert np.std(amp) / np.mean(amp) < 0.1


def test_residual_mean_is_taken_out(tmp_path):
    """A halo that carries the AO residual's time mean (resmean): pupil_estimate takes it out
    of the wavefront unless keep_resmean, and HALO.fits keeps it."""
    w, mask = known_wavefront()
    X, Y = grid(GEOM.pupn, GEOM.pupdx)
    m = 30e-9 * np.cos(2 * np.pi * 2 * X / GEOM.teldiam + 0.4) * mask  # 2 cycles per D: seen by the window
    field = mask * np.exp(2j * np.pi * (w + m) / GEOM.wavelen)
    Psi = mft_forward(field, GEOM, 64, 64)
    h = sw.Halo.from_arrays(Psi, geom=GEOM, resmean=m)
    assert h.resmean is not None and h.resmean.shape == (32, 32)
    r = sw.pupil_estimate(h, weight="none")
    k = sw.pupil_estimate(h, weight="none", keep_resmean=True)
    assert r.resmean is not None and k.resmean is None and k.resmean_rms == 0
    e_out = sw.wfe_compare(r.wfe, w, mask)[0]
    e_keep = sw.wfe_compare(k.wfe, w, mask)[0]
    e_tot = sw.wfe_compare(k.wfe, w + m, mask)[0]
    rm = sw.wfe_compare(m, np.zeros_like(m), mask)[0]
    assert r.resmean_rms == pytest.approx(rm, rel=0.1)
    assert e_keep == pytest.approx(rm, rel=0.1), (e_keep, rm)
    assert e_out < 0.1 * e_keep and e_tot < 1e-3 * e_keep, (e_out, e_tot, e_keep)
    np.testing.assert_allclose(r.wfe, k.wfe - r.resmean, rtol=0, atol=1e-15)  # the same fit, the mean taken out
    # HALO.fits round trip (the halo needs STAB to be written)
    h2 = sw.Halo.from_arrays(Psi, stab=Psi, stab_err=np.ones(Psi.shape), geom=GEOM, resmean=m)
    h2.write(tmp_path / "h.fits")
    back = sw.Halo.read(tmp_path / "h.fits")
    np.testing.assert_array_equal(back.resmean, m)
    with pytest.raises(ValueError):
        sw.Halo.from_arrays(Psi, geom=GEOM, resmean=np.zeros((32, 30)))


def test_pupil_weight_and_errors(tmp_path):
    w, mask = known_wavefront()
    Psi = mft_forward(mask * np.exp(2j * np.pi * w / GEOM.wavelen), GEOM, 64, 64)
    no_stab = sw.Halo.from_arrays(Psi, geom=GEOM)
    with pytest.raises(sw.Error, match="SNR weighting needs the STAB and STAB_ERR") as e:
        sw.pupil_estimate(no_stab)  # default weight='snr'
    assert e.value.status_name == "SWFS_ERR_FORMAT"
    with pytest.raises(sw.Error, match="pupil mask is 10x10 but the geometry says PUPN = 32") as e:
        sw.pupil_estimate(no_stab, mask=np.ones((10, 10)), weight="none")
    assert e.value.status_name == "SWFS_ERR_SHAPE"
    with pytest.raises(sw.Error, match="PIXSCALE"):
        sw.pupil_estimate(no_stab, geom=sw.Geom(wavelen=1e-6, teldiam=1, obscur=0, pupdx=0.03, pupn=32),
                          weight="none")
    with pytest.raises(ValueError, match="pupil: weight: expected one of 'none', 'snr', got 'bogus'"):
        sw.pupil_estimate(no_stab, weight="bogus")
    # SNR weight with a uniform, huge SNR is the unweighted estimate.
    stab = Psi.copy()
    h = sw.Halo.from_arrays(Psi, stab=stab, stab_err=np.full(Psi.shape, 1e-9 * np.abs(Psi).max()), geom=GEOM)
    a = sw.pupil_estimate(h, weight="snr")
    b = sw.pupil_estimate(h, weight="none")
    np.testing.assert_allclose(a.wfe, b.wfe, atol=1e-15)
    # An SNR of 1 everywhere: every pixel weighted by 1/(1 + 4): same wavefront (the phase
    # does not change under a uniform scale), smaller field.
    h1 = sw.Halo.from_arrays(Psi, stab=stab, stab_err=np.abs(stab), geom=GEOM)
    c = sw.pupil_estimate(h1, weight="snr")
    np.testing.assert_allclose(c.field, b.field / 5, rtol=1e-12, atol=1e-12 * np.abs(b.field).max())
    assert c.weight == "snr" and c.wiener_k == 2.0 and c.source == "lf"
    # Written product through the generic reader.
    p = str(tmp_path / "pupil.fits")
    a.write(p, provenance=["test"])
    for ext, arr in [("FIELD", a.field), ("WFE", a.wfe), ("SURFACE", a.surface), ("AMPLITUDE", a.amplitude),
                     ("PUPIL", a.mask)]:
        d, g = sw.read_fits(p, ext)
        np.testing.assert_array_equal(d, arr, err_msg=ext)
        assert g == GEOM
    keys = sw.read_keys(p, ["WFERMS", "STREHL"], ext="WFE")
    assert keys["WFERMS"] == pytest.approx(a.wfe_rms, rel=1e-12)


def test_bias_option_changes_the_wavefront():
    w, mask = known_wavefront()
    Psi = mft_forward(mask * np.exp(2j * np.pi * w / GEOM.wavelen), GEOM, 64, 64)
    h = sw.Halo.from_arrays(Psi, geom=GEOM)
    a = sw.pupil_estimate(h, weight="none")
    b = sw.pupil_estimate(h, weight="none", bias=1.0)
    assert b.bias == 1.0
    # eq:LFBiased-WFE-estimate: adding the mean field shrinks the phase excursions.
    assert b.wfe_rms < 0.8 * a.wfe_rms


def test_wfe_compare_and_remove_ptt():
    w, mask = known_wavefront()
    X, Y = grid(GEOM.pupn, GEOM.pupdx)
    ptt = (3e-9 + 20e-9 * X - 7e-9 * Y) * mask
    err, tp, tptt = sw.wfe_compare(w + ptt, w, mask)
    assert err < 1e-15
    inside = mask > 0
    assert tp == pytest.approx(np.std(w[inside]), rel=1e-9)
    extra = 5e-9 * sw.zernike(4, 0, np.hypot(X, Y) / 0.5, 0 * X) * mask
    err2, _, _ = sw.wfe_compare(w + ptt + extra, w, mask)
    e2, rms = sw.wfe_remove_ptt(extra, mask)
    assert err2 == pytest.approx(rms, rel=1e-9) and rms > 1e-9
    t, rms_t = sw.wfe_remove_ptt(ptt, mask)
    assert rms_t < 1e-20
    with pytest.raises(ValueError, match=r"est: expected shape \(32, 32\), got \(31, 32\)"):
        sw.wfe_compare(w[:31], w, mask)


def test_aperture():
    m = sw.aperture(200, 0.01, 2.0, 0.2)
    assert set(np.unique(m)) == {0.0, 1.0}
    assert m.sum() * 0.01 ** 2 == pytest.approx(np.pi * (1 - 0.2 ** 2), rel=0.01)
    assert m[100, 100] == 0 and m[100, 150] == 1
    sp = sw.aperture(200, 0.01, 2.0, 0.0, nspiders=4, spider_width=0.05)
    assert sp.sum() < m.sum() + np.pi * 0.04 / 0.01 ** 2 * 0.99 and sp[100, 150] == 0  # vane along +x


def test_dm_offsets(tmp_path, cli):
    """The NCP correction on the DM from Python: dm_offsets on a pupil product writes the
    command line's OFFSETS.fits (the same offsets and surface), DMFit on the arrays gives the
    same commands, a smooth aberration is fitted to a few % of its rms (-WFE/2 of surface,
    whose DM surface puts back what the commands say), and bad input is refused naming it."""
    import subprocess
    g = sw.Geom(wavelen=1.6e-6, teldiam=6.5, obscur=0.1, pixscale=0.5, pupdx=0.1, pupn=66)
    mask = sw.aperture(g.pupn, g.pupdx, g.teldiam, g.obscur)
    y, x = (np.indices((g.pupn, g.pupn)) - (g.pupn - 1) / 2) * g.pupdx / (g.teldiam / 2)
    wfe = 40e-9 * (x ** 2 - y ** 2) + 25e-9 * x * (x ** 2 + y ** 2) * mask  # astigmatism and coma [m]
    wfe *= mask
    sw.write_fits(str(tmp_path / "p.fits"), {"WFE": wfe, "PUPIL": mask}, geom=g)
    r = sw.dm_offsets(str(tmp_path / "p.fits"), str(tmp_path / "off.fits"), hexapolar=0.35)
    assert r["nact"] == 331 and 0 < r["active"] <= r["nact"] and r["pitch"] > 0.3
    st = r["stats"]
    inside = mask > 0
    assert st["target_rms"] == pytest.approx(np.std(wfe[inside]) / 2, rel=0.02)
    assert st["unfit_rms"] < 0.05 * st["target_rms"] and st["fit_rms"] == pytest.approx(st["target_rms"], rel=0.05)
    subprocess.run([cli, "dmoffsets", str(tmp_path / "p.fits"), "-o", str(tmp_path / "off_cli.fits"), "--hexapolar",
                    "0.35"], check=True, capture_output=True)
    for ext in ("OFFSETS", "SURFACE", "UNFIT", "ACTUATORS"):
        np.testing.assert_array_equal(sw.read_fits(str(tmp_path / "off.fits"), ext)[0],
                                      sw.read_fits(str(tmp_path / "off_cli.fits"), ext)[0], err_msg=ext)
    xy = sw.actuators_hexapolar(g.teldiam, 0.35, g.pupdx)
    f = sw.DMFit(xy, g, mask)
    cmd, fitted, st2 = f.fit(-wfe / 2)
    assert f.nact == 331 and f.active == r["active"] and f.pitch == pytest.approx(r["pitch"])
    off = sw.read_fits(str(tmp_path / "off.fits"), "OFFSETS")[0].ravel()
    np.testing.assert_allclose(cmd, off, rtol=0, atol=1e-6 * np.abs(off).max())
    np.testing.assert_allclose(f.surface(cmd), fitted, rtol=0, atol=1e-12 * np.abs(fitted).max())
    assert st2["unfit_rms"] == pytest.approx(st["unfit_rms"], rel=1e-6)
    # bad input: both layouts, a NaN inside the pupil (nothing written), a product without WFE
    with pytest.raises(ValueError, match="one of them"):
        sw.dm_offsets(str(tmp_path / "p.fits"), str(tmp_path / "x.fits"), hexapolar=0.35, actuators="a.fits")
    bad = wfe.copy()
    bad[33, 50] = np.nan  # row 33, column 50: inside the pupil
    sw.write_fits(str(tmp_path / "bad.fits"), {"WFE": bad, "PUPIL": mask}, geom=g)
    with pytest.raises(sw.Error, match=r"bad.fits: WFE \[m\] at pupil sample \(50, 33\) is not finite \(NaN or infinite\)"):
        sw.dm_offsets(str(tmp_path / "bad.fits"), str(tmp_path / "x.fits"), hexapolar=0.35)
    sw.write_fits(str(tmp_path / "nowfe.fits"), {"PUPIL": mask}, geom=g)
    with pytest.raises(sw.Error, match="nowfe.fits: no WFE extension"):
        sw.dm_offsets(str(tmp_path / "nowfe.fits"), str(tmp_path / "x.fits"), hexapolar=0.35)
    assert not (tmp_path / "x.fits").exists()

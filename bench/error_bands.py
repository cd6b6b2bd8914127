#!/usr/bin/env python3
"""Where in spatial frequency the slopes path's NCP error exceeds the ideal speckles', on one
data set kept by bench_telemetry (docs/telemetry.md, "Where the last misses are").

    ./build/bench/bench_telemetry --only K --seed S --keep DIR
    PYTHONPATH=python SPECKLEWFS_LIB=build/libspecklewfs.so python3 bench/error_bands.py DIR

For the default path (halo.fits from the slopes' speckles) and the ideal one
(halo_ideal.fits), `pupil`'s defaults give the wavefront; its error against the simulation's
NCP (truth.fits), piston, tip and tilt removed over the pupil, is split into rings of spatial
frequency [cycles per D] by an FFT of the error map zero-padded twice (the pupil's rim
leaks a little power between neighbouring rings). Printed per ring, in nm rms (the rings'
squares add up to the whole): the two errors, their difference map, and the AO residual's
time mean as the simulation has it against as the slopes reconstruct it (speckles.fits
RESMEAN against truth.fits RESMEAN). The last lines split at the speckles' band (SPKBAND,
the Shack-Hartmann's nsub/2): the part of the error within what the wavefront sensor
samples, and the part beyond it, which no telemetry carries.
"""
import sys

import numpy as np

import specklewfs as sw


def main(d):
    ncp = sw.read_fits(f"{d}/truth.fits", "NCP")[0]
    band = float(sw.read_keys(f"{d}/speckles.fits", ["SPKBAND"])["SPKBAND"])
    wfe, errs = {}, {}
    for tag, f in (("slopes", "halo.fits"), ("ideal", "halo_ideal.fits")):
        p = sw.pupil_estimate(sw.Halo.read(f"{d}/{f}"))
        wfe[tag], mask = p.wfe, p.mask > 0
        errs[tag] = sw.wfe_compare(p.wfe, ncp, p.mask)[0]
    n = ncp.shape[0]
    y, x = np.mgrid[:n, :n]
    a = np.stack([np.ones(mask.sum()), x[mask], y[mask]], 1)

    def ptt(m):  # piston, tip and tilt out over the pupil, zero outside
        v = m[mask]
        o = np.zeros_like(m)
        o[mask] = v - a @ np.linalg.lstsq(a, v, rcond=None)[0]
        return o

    tm = sw.read_fits(f"{d}/truth.fits", "RESMEAN")[0]
    rm = sw.read_fits(f"{d}/speckles.fits", "RESMEAN")[0]
    maps = {"slopes": ptt(wfe["slopes"] - ncp), "ideal": ptt(wfe["ideal"] - ncp)}
    maps["slopes-ideal"] = maps["slopes"] - maps["ideal"]
    maps["mean"] = ptt(tm)
    maps["mean rec-true"] = ptt(rm - tm)
    p2 = 2 * n
    g = sw.read_geom(f"{d}/speckles.fits")
    f = np.fft.fftfreq(p2, d=g.pupdx) * g.teldiam  # cycles per D
    fr = np.hypot(*np.meshgrid(f, f))
    pw = {}
    for k, m in maps.items():
        s = np.abs(np.fft.fft2(m, (p2, p2))) ** 2
        pw[k] = (s / s.sum(), np.mean(m[mask] ** 2))

    def rms(k, sel):
        frac, ms = pw[k]
        return 1e9 * np.sqrt(ms * frac[sel].sum())

    print(f"{d}: NCP error slopes {errs['slopes'] * 1e9:.1f} nm, ideal {errs['ideal'] * 1e9:.1f} nm "
          f"(x {errs['slopes'] / errs['ideal']:.2f}); the speckles' band {band:g} cycles per D")
    print("ring [c/D]  " + " ".join(f"{k:>13}" for k in maps))
    edges = sorted({0, 2, 4, band, band + 1, band + 2, band + 4, 2 * band, fr.max() + 1})
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (fr >= lo) & (fr < hi)
        print(f"{lo:4.1f}-{hi:<6.1f} " + " ".join(f"{rms(k, sel):13.1f}" for k in maps))
    for name, sel in (("within band", fr < band), ("beyond band", fr >= band)):
        s, i = rms("slopes", sel), rms("ideal", sel)
        print(f"{name}: slopes {s:.1f} nm, ideal {i:.1f} nm, x {s / i:.2f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])

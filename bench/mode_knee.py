#!/usr/bin/env python3
"""The loop's modal filter as its residual slopes show it, over systems (docs/telemetry.md,
"What the description must get right"): for each variant of one small closed loop (the
modes it controls, wind, layers, slope noise, loop gain and delay, vibration, r0, a square
DM grid, 16 x 16 subapertures, a valid map without the pupil's edge ring) a simulated time
series, and the knee of its slopes'
variances along the DM modes (swfs_ts_mode_variance, swfs_mode_knee) against the modes the
loop controlled. About 3 minutes on 2 cores; the series are kept in DIR and reused.

    PYTHONPATH=python SPECKLEWFS_LIB=build/libspecklewfs.so python3 bench/mode_knee.py DIR
"""
import os
import sys

import numpy as np

import specklewfs as sw

BASE = dict(mode="timeseries", pupn=66, pupdx=0.1, screen_n=1024, ncubes=2, cube_frames=60, cube_gap=150,
            wfs_file_frames=4000, nlayers=1, layer_frac=1, layer_speed=15, layer_dir=30, ao_modes=56, seed=3)
CASES = [dict(ao_modes=k) for k in (20, 36, 56, 80, 120)] + [
    dict(layer_speed=5), dict(layer_speed=30),
    dict(nlayers=2, layer_frac="0.6,0.4", layer_speed="8,25", layer_dir="30,200"),
    dict(slope_noise=3e-7), dict(slope_noise=1e-6), dict(ao_gain=0.15), dict(ao_gain=0.7), dict(ao_delay=4),
    dict(vib_amp=0.5), dict(r0=0.08), dict(act_square=1), dict(nsub=16, ao_modes=100), dict(nsub=16, ao_modes=150),
    dict(valid="ring"), dict(nsub=16, ao_modes=100, valid="ring")]


def ring_map(slopes, path):
    """The subapertures full-layout slopes use, less those with an unused neighbour (the
    pupil's edge ring), as a valid map file."""
    n = int(round((slopes.shape[1] / 2) ** 0.5))
    used = np.any(slopes != 0, axis=0)[: n * n].reshape(n, n)
    pad = np.pad(used, 1)
    inner = used & pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
    sw.write_fits(path, inner.astype(np.float64))
    return int(used.sum()), int(inner.sum())


def main(work):
    os.makedirs(work, exist_ok=True)
    print(f"{'variant':58s} {'frames':>6s} {'modes':>5s} {'knee':>5s}")
    exact = 0
    for i, c in enumerate(CASES):
        kw = dict(BASE, **c)
        d = os.path.join(work, f"v{i:02d}")
        if c.get("valid") == "ring":  # from the same geometry's series without a valid map
            j = next(j for j, o in enumerate(CASES) if "valid" not in o and o.get("nsub") == c.get("nsub"))
            s0, _ = sw.read_fits(os.path.join(work, f"v{j:02d}", "slopes_000.fits"))
            os.makedirs(d, exist_ok=True)
            kw["valid"] = os.path.abspath(os.path.join(d, "ring.fits"))
            nu, ni = ring_map(np.array(s0), kw["valid"])
            c = dict(c, valid=f"{ni} of {nu} subapertures")
        if not os.path.exists(os.path.join(d, "slopes_000.fits")):
            os.makedirs(d, exist_ok=True)
            sw.simulate_timeseries(d, **kw)
        s, _ = sw.read_fits(os.path.join(d, "slopes_000.fits"))
        var, knee = sw.mode_variance(np.array(s), **{k: v for k, v in kw.items() if k != "seed"})
        exact += knee == kw["ao_modes"]
        desc = ", ".join(f"{k}={v}" for k, v in c.items())
        print(f"{desc:58s} {s.shape[0]:6d} {kw['ao_modes']:5d} {knee:5d}", flush=True)
    print(f"{len(CASES)} variants; the knee is the modes controlled on {exact}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    main(sys.argv[1])

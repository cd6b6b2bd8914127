#!/usr/bin/env python3
"""Which DM influence functions does a Shack-Hartmann system's control matrix say it has?

The control matrix C (actuators x valid-only slopes, as bench/foreign_loop.py writes
control.fits) is a pseudo-inverse of the interaction matrix the system measured through its
own DM; its pseudo-inverse at its rank gives that interaction matrix back within C's row and
column spaces. This compares it with the mean-gradient interaction matrix of candidate
influence functions on the observation's pupil and subapertures, both within those spaces,
after the best single scale (a centre of gravity reads less than the mean gradient): Gaussian
functions exp(ln(c) r^2 / pitch^2) of coupling c, and the Clough-Tocher surface through the
commands that specklewfs' simulated loops use by default (docs/telemetry.md, "A DM of Gaussian
influence functions"). Prints the relative misfit of each.

usage: cm_coupling.py DATADIR   (pupil.fits with PUPN, PUPDX, TELDIAM; valid.fits;
                                 actuators.fits [m]; control.fits)
numpy, astropy and scipy (Debian python3-numpy, python3-astropy, python3-scipy).
"""
import math
import sys

import numpy as np
from astropy.io import fits
from scipy.interpolate import CloughTocher2DInterpolator


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    d = sys.argv[1]
    pup = fits.getdata(f'{d}/pupil.fits').astype(float)
    h = fits.getheader(f'{d}/pupil.fits')
    n, dx, diam = int(h['PUPN']), float(h['PUPDX']), float(h['TELDIAM'])
    valid = fits.getdata(f'{d}/valid.fits').astype(bool)
    nsub = valid.shape[0]
    npx = int(round(diam / nsub / dx))  # pupil samples per subaperture
    o = (n - nsub * npx) // 2
    act = fits.getdata(f'{d}/actuators.fits').astype(float)
    cm = fits.getdata(f'{d}/control.fits').astype(float)
    x1 = (np.arange(n) - (n - 1) / 2) * dx
    xs, ys = np.meshgrid(x1, x1)
    subs = [(a, b) for b in range(nsub) for a in range(nsub) if valid[b, a]]
    pitch = diam / nsub

    def gradient(opd):
        """Valid-only mean-gradient slopes (all x, then all y) of one OPD map."""
        gx, gy = [], []
        for a, b in subs:
            cut = (slice(o + b * npx, o + (b + 1) * npx), slice(o + a * npx, o + (a + 1) * npx))
            w, m = opd[cut], pup[cut] > 0
            mx, my = m[:, 1:] & m[:, :-1], m[1:, :] & m[:-1, :]
            gx.append(np.diff(w, axis=1)[mx].mean() / dx)
            gy.append(np.diff(w, axis=0)[my].mean() / dx)
        return np.array(gx + gy)

    u, s, vt = np.linalg.svd(cm, full_matrices=False)
    r = int((s > 1e-9 * s[0]).sum())
    im_sys = (vt[:r].T / s[:r]) @ u[:, :r].T  # slopes x actuators
    p_slopes, p_act = vt[:r].T @ vt[:r], u[:, :r] @ u[:, :r].T

    def misfit(im):
        im = p_slopes @ im @ p_act
        k = (im_sys * im).sum() / (im * im).sum()
        return np.linalg.norm(im_sys - k * im) / np.linalg.norm(im_sys), k

    print(f'{d}: control matrix {cm.shape[0]} x {cm.shape[1]}, rank {r}; misfit of each model (scale)')
    for c in (0.05, 0.1, 0.15, 0.2, 0.3, 0.4):
        im = np.stack([gradient(np.exp(math.log(c) * ((xs - x) ** 2 + (ys - y) ** 2) / pitch ** 2))
                       for x, y in act], 1)
        e, k = misfit(im)
        print(f'  Gaussian, coupling {c:<5} {e:.3f} (x{k:.2f})')
    im = []
    for j in range(len(act)):
        v = np.zeros(len(act))
        v[j] = 1.0
        im.append(gradient(np.nan_to_num(CloughTocher2DInterpolator(act, v, fill_value=0.0)(xs, ys))))
    e, k = misfit(np.stack(im, 1))
    print(f'  Clough-Tocher surface   {e:.3f} (x{k:.2f})')


if __name__ == '__main__':
    main()

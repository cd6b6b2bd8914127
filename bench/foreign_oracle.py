#!/usr/bin/env python3
"""How much of a foreign observation's true AO residual can any linear map of its slopes
recover? The question behind docs/telemetry.md's "What limits the controlled region".

usage: foreign_oracle.py TRAINDIR TESTDIR [--taught TAUGHT.fits] [--frames N]
                         [--speckles OUTDIR --science SCIENCE.fits [--specklewfs BIN]]

TRAINDIR and TESTDIR are made by bench/foreign_loop.py with the same system options and
different seeds: TRAINDIR with --train N (a long loop, no camera), TESTDIR with --dump (the
observation itself). Prints, by ring of 1 lambda/D of the pupil-plane field's transform, the
rho^2 of each reconstruction on the true residual of TESTDIR's frames (piston, tip and tilt
out; medians over each ring's pixels), and the fraction of the residual's variance it
explains (R^2):

- linear maps learned by least squares on TRAINDIR's true residual from its slopes at the
  lags 0; -1..1; -2..2; -4, -2, 0, 2, 4 (an oracle no telemetry has);
- the same from noise-free mean-gradient slopes of the residual (on the dump's grid), and of
  the residual's part within the sensor's band (nsub/2 cycles per D): what aliasing costs;
- with --taught, the map `speckles` used (teach's taught.fits: NLAGS, LAGk, OUTXY), applied
  to TESTDIR's slopes and carried to the grid by Clough-Tocher interpolation (scipy).

With --speckles, the same end to end: TESTDIR's residual as maps learned on TRAINDIR's truth
reconstruct it (lags 0, and nine lags 0, +-8, ..., +-32; each from the slopes alone and with
the DM commands applied during the frame as inputs too: commands.npy, or for older dumps the
loop's integrator rebuilt from the slopes through TESTDIR's control.fits), and the truth
itself on the same grid, made into speckle cubes as foreign_loop.py makes its ideal ones
(each exposure's mean tip-tilt out, the field's phase referenced to the core; one sample per
WFS frame, the grid of 2 x 2 samples repeated), with the ideal speckles' RESMEAN; then, given
--science (the run's reduced frames, e.g. WORK/science.fits of bench/foreign.sh), `estimate`
and `pupil --truth` on each and a table of the NCP errors: what the best linear map of the
slopes, with or without the commands, leaves to the estimate.
numpy and astropy (Debian python3-numpy, python3-astropy; python3-scipy for --taught).
"""
import argparse
import json
import os

import numpy as np


def load(d, n2, m2, P3, limit=None):
    R = np.load(os.path.join(d, 'residual.npy'), mmap_mode='r')
    S = np.load(os.path.join(d, 'slopes_all.npy'))
    settle = json.load(open(os.path.join(d, 'dump.json')))['settle']
    end = len(R) if limit is None else min(len(R), settle + limit)
    Y = np.asarray(R[settle:end])[:, m2].astype(float)
    return S[settle:end], Y - Y @ P3.T


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('train')
    ap.add_argument('test')
    ap.add_argument('--taught', help="teach's map (speckles.teach/taught.fits of TESTDIR's run)")
    ap.add_argument('--frames', type=int, default=20000, help='training frames for the mean-gradient rows')
    ap.add_argument('--speckles', metavar='OUTDIR', help='also the end-to-end oracle: speckle cubes into OUTDIR')
    ap.add_argument('--science', help="the observation's reduced frames (with --speckles: estimate and pupil)")
    ap.add_argument('--specklewfs', default='specklewfs', help='the specklewfs binary (default: on the PATH)')
    a = ap.parse_args()
    g = json.load(open(os.path.join(a.test, 'dump.json')))
    D, N, nsub, npx = g['D'], g['N'], g['nsub'], g['npx']
    n2, dx2 = N // 2, 2 * g['dx']
    mask = np.load(os.path.join(a.test, 'mask.npy'))
    m2 = mask.reshape(n2, 2, n2, 2).mean(axis=(1, 3)) > 0.5
    yy, xx = np.indices((n2, n2)) - (n2 - 1) / 2
    A3 = np.stack([np.ones(m2.sum()), xx[m2], yy[m2]], 1)
    P3 = A3 @ np.linalg.pinv(A3)
    S1, Y1 = load(a.train, n2, m2, P3)
    S2, Y2 = load(a.test, n2, m2, P3)
    M = 4 * n2  # transform size: lambda/D per pixel D / (M dx2)
    lod = D / (M * dx2)
    fy, fx = np.indices((M, M)) - M // 2
    rr = np.hypot(fx, fy) * lod
    nring = int(nsub)

    def focal(Yv):
        buf = np.zeros((len(Yv), M, M))
        tmp = np.zeros((len(Yv), n2, n2))
        tmp[:, m2] = Yv
        buf[:, :n2, :n2] = tmp
        return np.fft.fftshift(np.fft.fft2(buf), axes=(1, 2))

    def report(label, Yt, Yp):
        r2 = 1 - ((Yt - Yp) ** 2).sum() / ((Yt - Yt.mean(0)) ** 2).sum()
        Ft, Fp = focal(Yt[::2]), focal(Yp[::2])
        Ft -= Ft.mean(0)
        Fp -= Fp.mean(0)
        c = (Ft * Fp.conj()).mean(0)
        rho2 = abs(c) ** 2 / np.maximum((abs(Ft) ** 2).mean(0) * (abs(Fp) ** 2).mean(0), 1e-300)
        rings = ' '.join(f'{k}-{k + 1} {np.median(rho2[(rr >= k) & (rr < k + 1)]):.2f}' for k in range(nring))
        print(f'{label:44s} R2 {r2:6.3f}  rho2 by ring [lambda/D]: {rings}', flush=True)

    def learn(X1, T1, X2):
        Xm, Tm = X1.mean(0), T1.mean(0)
        Xc = X1 - Xm
        G = Xc.T @ Xc
        W = np.linalg.solve(G + 1e-6 * np.trace(G) / len(G) * np.eye(len(G)), Xc.T @ (T1 - Tm))
        return (X2 - Xm) @ W + Tm

    def lagged(S, lags):
        L = max(abs(l) for l in lags)
        idx = np.arange(L, len(S) - L)
        return np.concatenate([S[idx + l] for l in lags], 1), idx

    print(f'{len(S1)} training frames ({a.train}), {len(S2)} test frames ({a.test})')
    for lags in ([0], [-1, 0, 1], [-2, -1, 0, 1, 2], [-4, -2, 0, 2, 4]):
        X1, i1 = lagged(S1, lags)
        X2, i2 = lagged(S2, lags)
        report(f'map learned on the true residual, lags {lags[0]}..{lags[-1]}', Y2[i2], learn(X1, Y1[i1], X2))

    # mean-gradient slopes on the dump's grid (npx / 2 samples per subaperture)
    p, o = npx // 2, (N - nsub * npx) // 4
    ab = [(v % nsub, v // nsub) for v in g['valid']]

    def geo(Yv):
        R = np.zeros((len(Yv), n2, n2))
        R[:, m2] = Yv
        cut = [R[:, o + b * p:o + (b + 1) * p, o + a_ * p:o + (a_ + 1) * p] for a_, b in ab]
        return np.concatenate([np.array([np.diff(c, axis=2).mean(axis=(1, 2)) for c in cut]).T,
                               np.array([np.diff(c, axis=1).mean(axis=(1, 2)) for c in cut]).T], 1) / dx2

    def inband(Yv):
        R = np.zeros((len(Yv), n2, n2))
        R[:, m2] = Yv
        f = np.fft.fftfreq(2 * n2, dx2) * D
        keep = np.hypot(f[None, :], f[:, None]) <= nsub / 2
        return np.fft.ifft2(np.fft.fft2(R, s=(2 * n2, 2 * n2)) * keep).real[:, :n2, :n2][:, m2]

    n1 = min(a.frames, len(Y1))
    report('mean-gradient slopes of the residual', Y2, learn(geo(Y1[:n1]), Y1[:n1], geo(Y2)))
    report(f'the same of its part within {nsub / 2:g} cycles per D', Y2,
           learn(geo(inband(Y1[:n1])), Y1[:n1], geo(inband(Y2))))

    if a.taught:
        from astropy.io import fits
        from scipy.interpolate import CloughTocher2DInterpolator
        with fits.open(a.taught) as h:
            W, hd, oxy = h[0].data.astype(float), h[0].header, h['OUTXY'].data.astype(float)
        lags = [int(hd[f'LAG{k + 1}']) for k in range(int(hd['NLAGS']))] if 'NLAGS' in hd else [0]
        W = W.reshape(len(lags), -1, W.shape[-1])
        S = np.load(os.path.join(a.test, 'slopes_all.npy'))
        nv = len(ab)
        full = np.zeros((len(S), 2 * nsub * nsub))
        full[:, g['valid']] = S[:, :nv]
        full[:, [nsub * nsub + v for v in g['valid']]] = S[:, nv:]
        out = np.zeros((len(S), W.shape[1]))
        for k, l in enumerate(lags):
            out += full[np.clip(np.arange(len(S)) + l, 0, len(S) - 1)] @ W[k].T
        out = out[g['settle']:g['settle'] + len(Y2)]
        c1 = (np.arange(n2) - (n2 - 1) / 2) * dx2
        gx, gy = np.meshgrid(c1, c1)
        Yt = np.nan_to_num(CloughTocher2DInterpolator(oxy, out.T)(np.stack([gx[m2], gy[m2]], 1))).T
        report("teach's map", Y2, Yt - Yt @ P3.T)

    if a.speckles:
        end_to_end(a, g, mask, m2, learn)


def end_to_end(a, g, mask, m2, learn):
    import math
    import subprocess
    from astropy.io import fits
    D, N, dx, nsub, settle = g['D'], g['N'], g['dx'], g['nsub'], g['settle']
    n2 = N // 2
    info = json.load(open(os.path.join(a.test, 'foreign.json')))
    ideal_path = os.path.join(a.test, 'speckles_ideal.fits')
    with fits.open(ideal_path) as h:
        hdr, resmean = h[0].header, h['RESMEAN'].copy()
    lam, pixscale, W = hdr['WAVELEN'], hdr['PIXSCALE'], hdr['NAXIS2']
    xs1 = (np.arange(N) - (N - 1) / 2) * dx
    xs, ys = np.meshgrid(xs1, xs1)
    Ex = np.exp(-2j * math.pi * np.outer((np.arange(W) - W // 2) * pixscale / D, xs1))
    mm = mask > 0
    A3 = np.stack([np.ones(mm.sum()), xs[mm], ys[mm]], 1)
    A3p = np.linalg.pinv(A3)
    # the camera's schedule: each cube's start from the handshake's logged frame and its true lag
    split = fits.getdata(os.path.join(a.test, 'slopes_000.fits')).shape[0]
    t0s = []
    for c, line in enumerate(x for x in open(os.path.join(a.test, 'handshake.log')) if not x.startswith('#')):
        _, sf, off = line.split()
        t0s.append(int(off) + (0 if sf.endswith('000.fits') else split) - info['true_lags'][c])
    ncubes, cube_frames, ratio = info['cubes'], info['cube_frames'], info['ratio']

    def commands(d):
        f = os.path.join(d, 'commands.npy')
        if os.path.exists(f):
            return np.load(f).astype(float)
        CM = fits.getdata(os.path.join(a.test, 'control.fits')).astype(float)
        S = np.load(os.path.join(d, 'slopes_all.npy'))
        c = np.cumsum(g.get('gain', 0.4) * S @ CM.T, 0)
        C = np.zeros_like(c)
        dl = g.get('delay', 2)
        C[dl:] = c[:-dl]
        return C

    def residual(d, rows):  # the residual with its tip-tilt (piston out)
        R = np.load(os.path.join(d, 'residual.npy'), mmap_mode='r')
        Y = np.asarray(R[rows])[:, m2].astype(float)
        return Y - Y.mean(1, keepdims=True)

    def lagged(S, lags):
        idx = np.clip(np.arange(len(S))[:, None] + np.array(lags)[None, :], 0, len(S) - 1)
        return S[idx].reshape(len(S), -1)

    def cube(Y):
        out = np.zeros((ncubes * cube_frames, W, W), complex)
        acc = {}
        for k in range(len(Y)):
            hit = []
            for c, t0 in enumerate(t0s):
                e0 = int(math.floor((k - t0) / ratio))
                for e in (e0, e0 + 1):
                    if 0 <= e < cube_frames:
                        lo, hi = max(k, t0 + e * ratio), min(k + 1, t0 + (e + 1) * ratio)
                        if hi > lo:
                            hit.append((c, e, hi - lo, hi >= t0 + (e + 1) * ratio - 1e-12))
            if not hit:
                continue
            r = np.zeros((n2, n2))
            r[m2] = Y[k]
            res = np.kron(r, np.ones((2, 2)))
            cp = A3p @ res[mm]
            rf = np.zeros((N, N))
            rf[mm] = res[mm] - A3 @ cp
            for c, e, w, done in hit:
                acc.setdefault((c, e), []).append((w, rf, cp[1], cp[2]))
                if done:
                    lst = acc.pop((c, e))
                    sw = sum(x[0] for x in lst)
                    mtx, mty = sum(x[0] * x[2] for x in lst) / sw, sum(x[0] * x[3] for x in lst) / sw
                    f = np.zeros((N, N), complex)
                    for wi, rfi, tx, ty in lst:
                        f += wi * mask * np.exp(2j * math.pi * (rfi + (tx - mtx) * xs + (ty - mty) * ys) / lam)
                    h = Ex @ f @ Ex.T
                    core = h[W // 2, W // 2]
                    out[c * cube_frames + e] = h * np.conj(core) / abs(core)
        return out

    os.makedirs(a.speckles, exist_ok=True)
    S1, S2 = np.load(os.path.join(a.train, 'slopes_all.npy')), np.load(os.path.join(a.test, 'slopes_all.npy'))
    C1, C2 = commands(a.train), commands(a.test)
    tr = slice(settle, len(S1))
    Y1 = residual(a.train, tr)
    Y2 = residual(a.test, slice(0, len(S2)))
    sets = [('truth', 'the true residual on the same grid', Y2)]
    for lags, ln in (([0], 'lag 0'), ([0, -8, 8, -16, 16, -24, 24, -32, 32], 'nine lags to +-32')):
        X1, X2 = lagged(S1, lags)[tr], lagged(S2, lags)
        for dm in (0, 1):
            if dm:
                X1, X2 = np.concatenate([X1, C1[tr]], 1), np.concatenate([X2, C2], 1)
            Yp = learn(X1, Y1, X2)
            e = Y2[settle:] - Y2[settle:].mean(0)
            r2 = 1 - ((Y2[settle:] - Yp[settle:]) ** 2).sum() / (e ** 2).sum()
            name = ('l0' if lags == [0] else 'l9') + ('dm' if dm else '')
            sets.append((name, f'map of the slopes, {ln}' + (', DM commands' if dm else '') + f' (R2 {r2:.3f})', Yp))
    rows = []
    for name, label, Y in sets:
        sp = cube(Y)
        path = os.path.join(a.speckles, f'sp_{name}.fits')
        fits.HDUList([fits.PrimaryHDU(np.stack([sp.real, sp.imag], -1).astype(np.float32), hdr), resmean]).writeto(
            path, overwrite=True)
        rows.append((name, label, path))
    rows.append(('ideal', "foreign_loop.py's ideal speckles", ideal_path))
    if not a.science:
        print(f'speckle cubes in {a.speckles}; give --science for the NCP errors')
        return
    print(f'NCP error [nm] on the frames of {a.science}:')
    for name, label, path in rows:
        halo, pup = (os.path.join(a.speckles, f'{k}_{name}.fits') for k in ('halo', 'pupil'))
        subprocess.run([a.specklewfs, 'estimate', a.science, path, '-o', halo], check=True, capture_output=True)
        out = subprocess.run([a.specklewfs, 'pupil', halo, '-o', pup, '--truth', os.path.join(a.test, 'truth.fits')],
                             check=True, capture_output=True, text=True).stdout
        err = [x for x in out.splitlines() if 'versus truth' in x][0].split('error')[1].split('nm')[0].strip()
        print(f'  {label:64s} {err:>6s}', flush=True)


if __name__ == '__main__':
    main()

#!/usr/bin/env python3
"""A closed-loop AO observation made without specklewfs: numpy for the physics, astropy for
the files, written from the documented file formats alone (docs/conventions.md, the
telemetry table of docs/telemetry.md), so that the default path is measured on data whose
every model differs from the simulator it was developed with:

- the pupil: an annulus of 8.2 m (obstruction 0.14, --obscur), with --spiders legs of
  --spider-width (none by default);
- turbulence: von Karman OPD screens by FFT (--r0), frozen flow by bilinear interpolation
  between samples, two layers (--wind: one or two, their speeds and directions);
- the Shack-Hartmann: physical optics (each subaperture's field Fourier-transformed at twice
  Nyquist, photon and read noise, centre of gravity over its window), the WFS integrating
  two sub-steps of each frame, valid-only slopes (with a valid map);
- the DM: a Fried-geometry square grid (actuators at the subapertures' corners) of Gaussian
  influence functions, coupling 0.15; the interaction matrix measured through the physical
  sensor (push-pull); a least-squares control matrix truncated in its singular values (zonal)
  or of the K first Karhunen-Loeve modes (--modes K); integrator of gain 0.4, two frames of delay
  (--delay); a telescope vibration in tip-tilt (--vib, --vib-freq);
- the camera: the image of every sub-step through a matrix Fourier transform (--pixscale,
  +-16 lambda/D), integrated over exposures of --ratio WFS frames (at --rate) that start at
  arbitrary fractions of a WFS frame, photon and read noise (--cam-rn), a
  flat field, a bias frame, 16-bit counts (astropy's BZERO); slopes in two files;
- the reference: ideal speckles from the true residual (each exposure's mean tip-tilt
  removed, as `reduce` registers the frames), with its time mean as RESMEAN, and the NCP.

usage: foreign_loop.py OUTDIR [--seed S] [--nsub N] [--modes K] [--lam-sci M] [--photons P] [--vib A]
                       [--rate HZ] [--ratio R] [--wind V@DEG[,V@DEG]] [--r0 M] [--vib-freq HZ]
                       [--cam-rn E] [--pixscale P]
                       [--obscur F] [--spiders N] [--spider-width M] [--spider-angle DEG]
                       [--substeps N] [--delay N] [--quick] [--geometric] [--loop-geometric]
                       [--dump] [--train N]
       foreign_loop.py OUTDIR --rho WORKDIR   (how much of the ideal speckles' variance the
                                              speckles WORKDIR/speckles.fits hold, by ring)
Writes OUTDIR/raw_NNN.fits, dark.fits, flat.fits, slopes_000.fits, slopes_001.fits,
valid.fits, actuators.fits, control.fits (the loop's control matrix), handshake.log, speckles_ideal.fits, truth.fits, pupil.fits and
foreign.json (the parameters and the true timing).
--dump also writes the true residual of every WFS frame (residual.npy: the mean of its
sub-steps on a grid of 2 x 2 samples, float32), the slopes (slopes_all.npy), the DM commands
applied during each frame (commands.npy), the pupil (mask.npy) and the geometry (dump.json),
for bench/foreign_oracle.py; --train N: only that,
N WFS frames of the loop and no camera (a learning set for the oracle).
"""
import argparse
import json
import math
import os
import sys

import numpy as np
from astropy.io import fits


def vk_screen(n, dx, r0, l0, rng):
    """A periodic von Karman OPD screen [m], r0 at 0.5 um."""
    f = np.fft.fftfreq(n, dx)
    f2 = f[None, :] ** 2 + f[:, None] ** 2 + 1.0 / l0 ** 2
    psd = 0.023 * r0 ** (-5.0 / 3.0) * f2 ** (-11.0 / 6.0)  # phase [rad^2 m^2] at 0.5 um
    psd[0, 0] = 0.0
    df = 1.0 / (n * dx)
    c = (rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))) * np.sqrt(psd) * df
    return np.fft.ifft2(c).real * n * n * 0.5e-6 / (2 * math.pi)


def window(screen, ox, oy, n):
    """n x n samples of a periodic screen from (ox, oy) [samples], bilinear."""
    m = screen.shape[0]
    ix, iy = int(math.floor(ox)), int(math.floor(oy))
    fx, fy = ox - ix, oy - iy
    sub = screen[np.ix_((np.arange(n + 1) + iy) % m, (np.arange(n + 1) + ix) % m)]
    return ((1 - fy) * ((1 - fx) * sub[:-1, :-1] + fx * sub[:-1, 1:]) +
            fy * ((1 - fx) * sub[1:, :-1] + fx * sub[1:, 1:]))


class ShackHartmann:
    """Physical-optics Shack-Hartmann: npx pupil samples per subaperture, FFT padded x2."""

    def __init__(self, mask, nsub, npx, lam, dx, photons, read_noise, rng):
        n = mask.shape[0]
        self.o = (n - nsub * npx) // 2
        self.nsub, self.npx, self.lam, self.dx = nsub, npx, lam, dx
        illum = np.zeros((nsub, nsub))
        for b in range(nsub):
            for a in range(nsub):
                illum[b, a] = self.cut(mask, a, b).mean()
        self.valid = illum >= 0.5
        self.ab = [(a, b) for b in range(nsub) for a in range(nsub) if self.valid[b, a]]
        self.amp = np.array([self.cut(mask, a, b) for a, b in self.ab])
        self.photons = photons * self.amp.mean(axis=(1, 2)) / max(self.amp.mean(axis=(1, 2)))
        self.read_noise, self.rng = read_noise, rng
        k = np.arange(2 * npx) - npx
        self.kx, self.ky = np.meshgrid(k, k)
        self.pix = lam / (2 * npx * dx)  # rad per detector pixel
        self.ref = 0.0
        self.ref = self.slopes(np.zeros(mask.shape), False)  # reference slopes: a flat wavefront's

    def cut(self, a2, a, b):
        o, p = self.o, self.npx
        return a2[..., o + b * p:o + (b + 1) * p, o + a * p:o + (a + 1) * p]

    def images(self, opd):
        """Noise-free spot images of one OPD map [m], summed over the first axis if 3-D."""
        opds = opd if opd.ndim == 3 else opd[None]
        tot = 0
        for o in opds:
            f = self.amp * np.exp(2j * math.pi * np.array([self.cut(o, a, b) for a, b in self.ab]) / self.lam)
            pad = np.zeros((len(self.ab), 2 * self.npx, 2 * self.npx), complex)
            pad[:, :self.npx, :self.npx] = f
            im = np.abs(np.fft.fftshift(np.fft.fft2(pad), axes=(1, 2))) ** 2
            tot = tot + im
        return tot

    def mean_gradient(self, opd):
        """The geometric slopes of one OPD map [rad]: the mean difference of illuminated neighbours."""
        gx, gy = [], []
        for a, b in self.ab:
            o, m = self.cut(opd, a, b), self.amp[len(gx)] > 0
            mx, my = m[:, 1:] & m[:, :-1], m[1:, :] & m[:-1, :]
            gx.append(np.diff(o, axis=1)[mx].mean() / self.dx)
            gy.append(np.diff(o, axis=0)[my].mean() / self.dx)
        return np.array(gx + gy)

    def slopes(self, opd, noise=True):
        """Valid-only slopes [rad]: all x, then all y."""
        im = self.images(opd)
        im = im * (self.photons / im.sum(axis=(1, 2)))[:, None, None]
        if noise:
            im = self.rng.poisson(im).astype(float) + self.read_noise * self.rng.standard_normal(im.shape)
        s = im.sum(axis=(1, 2))
        cx = (im * self.kx).sum(axis=(1, 2)) / s
        cy = (im * self.ky).sum(axis=(1, 2)) / s
        return np.concatenate([cx, cy]) * self.pix - self.ref


def ptt_remove(w, mask, xs, ys):
    m = mask > 0
    A = np.stack([np.ones(m.sum()), xs[m], ys[m]], 1)
    c = np.linalg.lstsq(A, w[m], rcond=None)[0]
    out = np.zeros_like(w)
    out[m] = w[m] - A @ c
    return out


def rho_by_ring(data, work):
    """Pixel by pixel over the matched frames, rho^2 = |<psi psi_c*>|^2 / (<|psi|^2> <|psi_c|^2>) of
    the ideal speckles psi on the computed ones psi_c (both less their means) and the scale
    beta = <psi psi_c*> / <|psi_c|^2>; medians by rings of 1 lambda/D."""
    def cplx(path):
        a = fits.getdata(path).astype(float)
        return a[..., 0] + 1j * a[..., 1]
    ps, pi = cplx(os.path.join(work, 'speckles.fits')), cplx(os.path.join(data, 'speckles_ideal.fits'))
    sci = fits.getdata(os.path.join(work, 'science.fits')).astype(float)
    scm = fits.getdata(os.path.join(work, 'sci_m.fits')).astype(float)
    pi = pi[[int(np.argmin(np.nansum((sci - f) ** 2, axis=(1, 2)))) for f in scm]]
    a, b = ps - ps.mean(0), pi - pi.mean(0)
    c = (b * a.conj()).mean(0)
    va, vb = (abs(a) ** 2).mean(0), (abs(b) ** 2).mean(0)
    ok = va > 0
    rho2 = np.where(ok, abs(c) ** 2 / np.where(ok, va * vb, 1), np.nan)
    beta = np.where(ok, abs(c) / np.where(ok, va, 1), np.nan)
    w = ps.shape[1]
    y, x = np.indices((w, w)) - w // 2
    r = np.hypot(x, y) * float(fits.getheader(os.path.join(work, 'science.fits'))['PIXSCALE'])
    rows = []
    for r0 in range(int(r.max())):
        m = (r >= r0) & (r < r0 + 1) & ok
        if m.any():
            rows.append((r0, float(np.median(rho2[m])), float(np.median(beta[m]))))
    print('rho2 by ring [lambda/D]: ' + ' '.join(f'{r0}-{r0 + 1} {v:.2f}' for r0, v, _ in rows))
    print('|beta| by ring:          ' + ' '.join(f'{r0}-{r0 + 1} {v:.2f}' for r0, _, v in rows))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('out')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--nsub', type=int, default=14)
    ap.add_argument('--quick', action='store_true', help='fewer and shorter cubes (a test-sized observation)')
    ap.add_argument('--geometric', action='store_true',
                    help='also the mean-gradient slopes of the same residuals (geo_slopes_NNN.fits, handshake_geo.log)')
    ap.add_argument('--modes', type=int, default=0,
                    help='a modal loop controlling the K first Karhunen-Loeve modes (default: zonal, a truncated inverse)')
    ap.add_argument('--loop-geometric', action='store_true',
                    help='the loop senses with mean-gradient slopes (plus the CoG noise level) instead of the CoG')
    ap.add_argument('--substeps', type=int, default=2, help='time steps per WFS frame (the WFS and camera integrate them)')
    ap.add_argument('--delay', type=int, default=2, help="the loop's delay [WFS frames]: slopes of frame k act from frame k + delay")
    ap.add_argument('--vib', type=float, default=0.3, help="the telescope's tip-tilt vibration at 17 Hz [lambda_sci / D]")
    ap.add_argument('--lam-sci', type=float, default=1.65e-6, help='the science wavelength [m]')
    ap.add_argument('--photons', type=float, default=600.0, help='photons per subaperture and WFS frame')
    ap.add_argument('--obscur', type=float, default=0.14, help="the central obstruction [fraction of the diameter]")
    ap.add_argument('--spiders', type=int, default=0, help='legs of the secondary\'s support, evenly spaced')
    ap.add_argument('--spider-width', type=float, default=0.15, help="a leg's width [m]")
    ap.add_argument('--spider-angle', type=float, default=45.0, help="the first leg's direction [deg from +x]")
    ap.add_argument('--rate', type=float, default=900.0, help='the WFS frame rate [Hz]')
    ap.add_argument('--ratio', type=float, default=7.37, help='WFS frames per camera exposure')
    ap.add_argument('--wind', default='9@30,17@250', metavar='V@DEG[,V@DEG]',
                    help="the layers' speeds [m/s] and the directions the pupil's window moves [deg]; "
                         'one layer takes all the turbulence, two share it 0.6 / 0.4')
    ap.add_argument('--r0', type=float, default=0.14, help="Fried's parameter at 0.5 um [m]")
    ap.add_argument('--vib-freq', type=float, default=17.0, help="the vibration's frequency [Hz]")
    ap.add_argument('--cam-rn', type=float, default=10.0, help="the camera's read noise [e-]")
    ap.add_argument('--pixscale', type=float, default=0.5, help="the camera's pixel [lambda_sci / D]")
    ap.add_argument('--dump', action='store_true', help='also keep the true residual and the slopes per WFS frame')
    ap.add_argument('--train', type=int, default=0, metavar='N',
                    help='only the dump of N WFS frames, no camera (implies --dump)')
    ap.add_argument('--rho', metavar='WORKDIR', help='compare WORKDIR/speckles.fits with the ideal speckles and stop')
    args = ap.parse_args()
    if args.rho:
        return rho_by_ring(args.out, args.rho)
    rng = np.random.default_rng(args.seed)
    os.makedirs(args.out, exist_ok=True)
    args.dump = args.dump or args.train > 0

    # --- the system (none of these values is one of specklewfs' configurations)
    D, obscur, nsub, npx = 8.2, args.obscur, args.nsub, 8
    N = nsub * npx + 8  # pupil grid, a margin of half a subaperture each side
    dx = D / (nsub * npx)
    rate = args.rate
    lam_wfs, lam_sci = 0.7e-6, args.lam_sci
    r0, l0 = args.r0, 25.0
    # share, m/s, direction [deg] of the pupil's window over the screen: the turbulence moves
    # across the pupil the other way (toward direction + 180 deg, what `specklewfs wind` reports)
    winds = [tuple(float(v) for v in w.split('@')) for w in args.wind.split(',')]
    if not 1 <= len(winds) <= 2 or any(len(w) != 2 for w in winds):
        ap.error(f'--wind {args.wind}: expected one or two V@DEG')
    layers = [(sh_, v, a) for sh_, (v, a) in zip((1.0,) if len(winds) == 1 else (0.6, 0.4), winds)]
    vib_amp, vib_freq = args.vib, args.vib_freq  # lambda_sci / D, Hz
    gain, delay, coupling, rcond = 0.4, args.delay, 0.15, 0.03
    photons, wfs_rn = args.photons, 0.5
    pixscale = args.pixscale
    W = 2 * int(round(16.0 / pixscale))  # +-16 lambda/D
    flux, cam_gain, cam_rn, bias = 2.0e5, 10.0, args.cam_rn, 500.0
    ratio = args.ratio  # WFS frames per camera frame
    ncubes, cube_frames, gap = (3, 80, 150) if args.quick else (4, 150, 200)
    settle, substeps, true_lag = 300, args.substeps, 2.4
    ncp_rms = 80e-9

    xs1 = (np.arange(N) - (N - 1) / 2) * dx
    xs, ys = np.meshgrid(xs1, xs1)
    r = np.hypot(xs, ys)
    mask = ((r <= D / 2) & (r >= obscur * D / 2)).astype(float)
    for k in range(args.spiders):  # legs from the centre out, each a strip of the given width
        t = math.radians(args.spider_angle) + 2 * math.pi * k / args.spiders
        along, across = xs * math.cos(t) + ys * math.sin(t), -xs * math.sin(t) + ys * math.cos(t)
        mask[(along > 0) & (np.abs(across) < args.spider_width / 2)] = 0.0

    # NCP: a power law between 1 and 10 cycles per D, 80 nm rms without piston, tip, tilt
    fq = np.fft.fftfreq(4 * N, dx) * D
    fr = np.hypot(fq[None, :], fq[:, None])
    amp = np.where((fr >= 1) & (fr <= 10), np.maximum(fr, 1) ** -1.3, 0)
    ncp = np.fft.ifft2(amp * (rng.standard_normal(fr.shape) + 1j * rng.standard_normal(fr.shape))).real[:N, :N]
    ncp = ptt_remove(ncp, mask, xs, ys)
    ncp *= ncp_rms / math.sqrt((ncp[mask > 0] ** 2).mean())

    sh = ShackHartmann(mask, nsub, npx, lam_wfs, dx, photons, wfs_rn, rng)
    nvalid = len(sh.ab)

    # DM: Fried geometry, actuators at the subapertures' corners within D/2 + 0.75 pitch
    pitch = D / nsub
    g1 = -D / 2 + pitch * np.arange(nsub + 1)
    ax, ay = np.meshgrid(g1, g1)
    keep = np.hypot(ax, ay) <= D / 2 + 0.75 * pitch
    act = np.stack([ax[keep], ay[keep]], 1)
    nact = len(act)
    IF = np.exp(math.log(coupling) * ((xs[None] - act[:, 0, None, None]) ** 2 +
                                       (ys[None] - act[:, 1, None, None]) ** 2) / pitch ** 2)
    IFm = IF.reshape(nact, -1)

    # push-pull interaction matrix through the sensor the loop runs, truncated pseudo-inverse
    poke = 20e-9
    IM = np.zeros((2 * nvalid, nact))
    sense = (lambda o: sh.mean_gradient(o)) if args.loop_geometric else (lambda o: sh.slopes(o, False))
    for j in range(nact):
        IM[:, j] = (sense(poke * IF[j]) - sense(-poke * IF[j])) / (2 * poke)
    # the CoG's white noise per slope, for the mean-gradient sensor (--loop-geometric)
    geo_noise = float(np.std([sh.slopes(np.zeros((N, N))) for _ in range(50)], axis=0).mean()) if args.loop_geometric else 0.0
    if args.modes:
        # a modal loop: the turbulence's Karhunen-Loeve modes on the actuators (the Kolmogorov
        # structure function's covariance, piston out), the K of most variance controlled
        rij = np.hypot(act[:, 0, None] - act[None, :, 0], act[:, 1, None] - act[None, :, 1])
        C = -0.5 * 6.88 * (rij / r0) ** (5.0 / 3.0)
        J = np.eye(nact) - 1.0 / nact
        ev, V = np.linalg.eigh(J @ C @ J)
        M = V[:, np.argsort(ev)[::-1][:args.modes]]
        U, S, Vt = np.linalg.svd(IM @ M, full_matrices=False)
        CM = M @ (Vt.T / S) @ U.T
        nmodes = args.modes
    else:
        U, S, Vt = np.linalg.svd(IM, full_matrices=False)
        keep_s = S > rcond * S[0]
        CM = (Vt[keep_s].T / S[keep_s]) @ U[:, keep_s].T
        nmodes = int(keep_s.sum())

    # turbulence
    nscr = 2048
    screens = [math.sqrt(s) * vk_screen(nscr, dx, r0, l0, rng) for s, _, _ in layers]
    vel = [(v * math.cos(math.radians(a)) / dx, v * math.sin(math.radians(a)) / dx) for _, v, a in layers]
    start = [(rng.uniform(0, nscr), rng.uniform(0, nscr)) for _ in layers]
    vib_phase = rng.uniform(0, 2 * math.pi)
    vib_dir = rng.uniform(0, math.pi)

    # camera schedule: cube c starts at WFS time t0_c (fractional), frame e covers [t, t + ratio)
    t0s, t = [], float(settle) + rng.uniform(0, 1)
    for c in range(ncubes):
        t0s.append(t)
        t += cube_frames * ratio + gap + rng.uniform(0, 1)
    nwfs = int(math.ceil(t)) + 10
    if args.train:
        nwfs, t0s = args.train, []

    Ex = np.exp(-2j * math.pi * np.outer((np.arange(W) - W // 2) * pixscale / D, xs1))
    cam_flux = flux / mask.sum() ** 2  # a perfect image's peak: `flux` photons
    flat = 1 + 0.03 * rng.standard_normal((W, W))
    dark = bias + 5 * rng.standard_normal((W, W)) + np.linspace(0, 20, W)[None, :]

    clean = [np.zeros((cube_frames, W, W)) for _ in range(ncubes)]
    ideal = [np.zeros((cube_frames, W, W), complex) for _ in range(ncubes)]
    ex_res = {}  # (cube, frame) -> list of (weight, tip-tilt-free residual, tip, tilt)
    resmean, resw = np.zeros((N, N)), 0.0
    slopes_all = np.zeros((nwfs, 2 * nvalid))
    geo_all = np.zeros((nwfs, 2 * nvalid)) if args.geometric else None
    queue = [np.zeros(nact) for _ in range(delay)]
    cmd = np.zeros(nact)
    mm = mask > 0
    A3 = np.stack([np.ones(mm.sum()), xs[mm], ys[mm]], 1)
    A3p = np.linalg.pinv(A3)
    res2 = []
    dump = np.zeros((nwfs, N // 2, N // 2), np.float32) if args.dump else None
    cmd_all = np.zeros((nwfs, nact), np.float32) if args.dump else None
    for k in range(nwfs):
        dm = (queue[0] @ IFm).reshape(N, N)
        subs = []
        for q in range(substeps):
            tt = (k + (q + 0.5) / substeps) / rate
            turb = sum(window(s, x0 + vx * tt, y0 + vy * tt, N) for s, (x0, y0), (vx, vy) in zip(screens, start, vel))
            vib = vib_amp * lam_sci / D * math.sin(2 * math.pi * vib_freq * tt + vib_phase)
            turb = turb + vib * (math.cos(vib_dir) * xs + math.sin(vib_dir) * ys)
            subs.append(turb - dm)
        if args.loop_geometric:  # the mean-gradient sensor with the CoG's photon noise level
            s = sum(sh.mean_gradient(x) for x in subs) / len(subs) + geo_noise * rng.standard_normal(2 * nvalid)
        else:
            s = sh.slopes(np.array(subs))
        slopes_all[k] = s
        if args.geometric:
            geo_all[k] = sum(sh.mean_gradient(x) for x in subs) / len(subs)
        if args.dump:
            dump[k] = (sum(subs) / len(subs)).reshape(N // 2, 2, N // 2, 2).mean(axis=(1, 3))
            cmd_all[k] = queue[0]  # the commands applied during frame k
        cmd = cmd + gain * (CM @ s)
        queue = queue[1:] + [cmd.copy()]
        for q, res in enumerate(subs):
            ts = k + q / substeps  # this sub-step covers [ts, ts + 1/substeps) in WFS frames
            c_ptt = A3p @ res[mm]
            if k >= settle:
                res2.append(((res[mm] - A3 @ c_ptt) ** 2).mean())
            im = rf = None
            for c, t0 in enumerate(t0s):
                e0 = int(math.floor((ts - t0) / ratio))
                for e in (e0, e0 + 1):
                    if e < 0 or e >= cube_frames:
                        continue
                    lo, hi = max(ts, t0 + e * ratio), min(ts + 1 / substeps, t0 + (e + 1) * ratio)
                    w = (hi - lo) * substeps
                    if w <= 0:
                        continue
                    if im is None:
                        field = mask * np.exp(2j * math.pi * (res + ncp) / lam_sci)
                        im = np.abs(Ex @ field @ Ex.T) ** 2
                        rf = np.zeros((N, N))
                        rf[mm] = res[mm] - A3 @ c_ptt
                    clean[c][e] += w * im
                    ex_res.setdefault((c, e), []).append((w, rf, c_ptt[1], c_ptt[2]))
                    if hi >= t0 + (e + 1) * ratio - 1e-12:
                        # exposure complete: the ideal speckles, its mean tip-tilt removed
                        lst = ex_res.pop((c, e))
                        sw = sum(x[0] for x in lst)
                        mtx = sum(x[0] * x[2] for x in lst) / sw
                        mty = sum(x[0] * x[3] for x in lst) / sw
                        acc = np.zeros((N, N), complex)
                        for wi, rfi, tx, ty in lst:
                            ph = rfi + (tx - mtx) * xs + (ty - mty) * ys
                            # weights in WFS frames, as the speckles of `speckles` sum them
                            acc += wi / substeps * mask * np.exp(2j * math.pi * ph / lam_sci)
                            resmean += wi * rfi
                            resw += wi
                        h = Ex @ acc @ Ex.T
                        core = h[W // 2, W // 2]
                        ideal[c][e] = h * np.conj(core) / abs(core)
        if k % 500 == 0:
            print(f'  WFS frame {k} of {nwfs}', file=sys.stderr)
    if args.dump:
        np.save(os.path.join(args.out, 'residual.npy'), dump)
        np.save(os.path.join(args.out, 'slopes_all.npy'), slopes_all)
        np.save(os.path.join(args.out, 'commands.npy'), cmd_all)
        np.save(os.path.join(args.out, 'mask.npy'), mask)
        with open(os.path.join(args.out, 'dump.json'), 'w') as f:
            json.dump(dict(D=D, N=N, dx=dx, nsub=nsub, npx=npx, settle=settle, seed=args.seed, modes=args.modes,
                           gain=gain, delay=delay, lam_sci=lam_sci, pixscale=pixscale, W=W,
                           valid=[int(b * nsub + a) for a, b in sh.ab]), f)
        if args.train:
            print(f'foreign loop: {nwfs} WFS frames of residual and slopes -> {args.out}')
            return
    resmean = ptt_remove(resmean / resw, mask, xs, ys)

    # --- files, as an outside user's tools would write them
    geo = dict(WAVELEN=lam_sci, TELDIAM=D, OBSCUR=obscur, PIXSCALE=pixscale, PUPDX=dx, PUPN=N)

    def hdr(extra=None):
        h = fits.Header()
        for key, v in geo.items():
            h[key] = v
        for key, v in (extra or {}).items():
            h[key] = v
        return h

    for c in range(ncubes):
        ph = rng.poisson(np.maximum(clean[c] * cam_flux, 0)).astype(float)
        e = ph * flat + cam_rn * rng.standard_normal(ph.shape)
        counts = np.clip(np.round(e / cam_gain + dark), 0, 65535).astype(np.uint16)
        fits.PrimaryHDU(counts, hdr({'GAIN': (cam_gain, 'e-/ADU'), 'EXPTIME': ratio / rate})).writeto(
            os.path.join(args.out, f'raw_{c:03d}.fits'), overwrite=True)
    fits.PrimaryHDU(dark.astype(np.float32), hdr()).writeto(os.path.join(args.out, 'dark.fits'), overwrite=True)
    fits.PrimaryHDU(flat.astype(np.float32), hdr()).writeto(os.path.join(args.out, 'flat.fits'), overwrite=True)
    fits.PrimaryHDU(mask.astype(np.float32), hdr()).writeto(os.path.join(args.out, 'pupil.fits'), overwrite=True)
    split = nwfs // 2
    for i, (a, b) in enumerate(((0, split), (split, nwfs))):
        fits.PrimaryHDU(slopes_all[a:b].astype(np.float32),
                        fits.Header([('BUNIT', 'rad'), ('WFSRATE', rate), ('NSUB', nsub), ('FRAME0', a)])).writeto(
            os.path.join(args.out, f'slopes_{i:03d}.fits'), overwrite=True)
    if args.geometric:
        for i, (a, b) in enumerate(((0, split), (split, nwfs))):
            fits.PrimaryHDU(geo_all[a:b].astype(np.float32),
                            fits.Header([('BUNIT', 'rad'), ('WFSRATE', rate), ('NSUB', nsub), ('FRAME0', a)])).writeto(
                os.path.join(args.out, f'geo_slopes_{i:03d}.fits'), overwrite=True)
    fits.PrimaryHDU(sh.valid.astype(np.uint8)).writeto(os.path.join(args.out, 'valid.fits'), overwrite=True)
    fits.PrimaryHDU(act, fits.Header([('BUNIT', 'm')])).writeto(os.path.join(args.out, 'actuators.fits'), overwrite=True)
    # the loop's own control matrix (DM commands per valid-only slope), as an AO system keeps it
    fits.PrimaryHDU(CM).writeto(os.path.join(args.out, 'control.fits'), overwrite=True)
    with open(os.path.join(args.out, 'handshake.log'), 'w') as f:
        f.write('# camera cube, slopes file, WFS frame logged at the cube start\n')
        for c, t0 in enumerate(t0s):
            logged = int(math.floor(t0 + true_lag))
            fi = 0 if logged < split else 1
            f.write(f'raw_{c:03d}.fits slopes_{fi:03d}.fits {logged - (0 if fi == 0 else split)}\n')
    if args.geometric:
        with open(os.path.join(args.out, 'handshake.log')) as f, open(os.path.join(args.out, 'handshake_geo.log'), 'w') as g:
            g.write(f.read().replace(' slopes_', ' geo_slopes_'))
    cube = np.concatenate(ideal)
    sp = np.stack([cube.real, cube.imag], -1).astype(np.float32)
    rm_rms = math.sqrt((resmean[mask > 0] ** 2).mean())
    h = hdr({'CTYPE1': 'COMPLEX'})
    fits.HDUList([fits.PrimaryHDU(sp, h),
                  fits.ImageHDU(resmean, fits.Header([('RESMRMS', rm_rms)]), name='RESMEAN')]).writeto(
        os.path.join(args.out, 'speckles_ideal.fits'), overwrite=True)
    fits.HDUList([fits.PrimaryHDU(header=hdr()), fits.ImageHDU(ncp, hdr(), name='NCP')]).writeto(
        os.path.join(args.out, 'truth.fits'), overwrite=True)
    res_rms = math.sqrt(np.mean(res2))
    lags = []
    for t0 in t0s:
        lags.append(math.floor(t0 + true_lag) - t0)
    info = dict(true_lags=lags, photons=photons, seed=args.seed, nsub=nsub, nvalid=nvalid, nact=nact, modes=nmodes, rate=rate,
                ratio=ratio, lag=true_lag, layers=layers, r0=r0, vib=[vib_amp, vib_freq], ncp_rms=ncp_rms,
                res_rms_ptt=res_rms, resmean_rms=rm_rms, wfs_frames=nwfs, cubes=ncubes, cube_frames=cube_frames,
                obscur=obscur, spiders=args.spiders, spider_width=args.spider_width)
    with open(os.path.join(args.out, 'foreign.json'), 'w') as f:
        json.dump(info, f, indent=1)
    print(f'foreign loop: {nsub} x {nsub} SH ({nvalid} valid), {nact} actuators, {nmodes} modes, '
          f'{nwfs} WFS frames; residual {res_rms * 1e9:.1f} nm rms without tip-tilt, its time mean '
          f'{rm_rms * 1e9:.1f} nm; NCP {ncp_rms * 1e9:.0f} nm -> {args.out}')


if __name__ == '__main__':
    main()

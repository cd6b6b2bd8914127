#!/usr/bin/env python3
"""How far a better per-frame reconstructor could go, measured on one simulated data set
(docs/telemetry.md, "The true residual as telemetry").

    ./build/bench/bench_telemetry --only K --seed S --truth --keep DIR
    PYTHONPATH=python SPECKLEWFS_LIB=build/libspecklewfs.so \\
        python3 bench/recon_oracle.py DIR [--specklewfs build/specklewfs] [--ridge R] [--in-sample] [--train DIR...]

On the kept data set (the simulation with export_truth=1 and export_modal=1, reduced and
timed by bench_telemetry), each row below goes through the same speckles -> estimate ->
pupil --truth as the default path, with the wavefront of every WFS frame given on the
actuators as the telemetry of their influence functions (speckles --basis influence.fits,
the Shack-Hartmann's band nsub/2):

  vk       the von Karman reconstructor's wavefront (W of speckles --recon vk --write-recon times the
           slopes): the path of `--recon vk`;
  truth    the true residual on the actuators (truewf_NNN.fits): what the representation,
           the engine and the estimator keep of the ideal speckles;
  learned  the least-squares linear map slopes -> true residual on the actuators, with a
           ridge of R times the mean diagonal, trained on one half of the frames and
           applied to the other (2-fold): the best per-frame linear reconstructor the
           data set itself could teach;
  --in-sample  trains and applies on the same frames, and adds the control row
           "reversed": the same fit on the slopes time-reversed, which carry no
           information about the frame (an in-sample fit that beats it is memorizing).
  --train DIR...  adds the rows "sim" and "sim+dm": the same least-squares map learned on
           other simulations kept by bench_telemetry --truth (other seeds, other systems of
           the same Shack-Hartmann and actuator geometry), from the slopes alone and from
           the slopes with the DM commands the loop applied (truewf_NNN.fits extension DM),
           applied to this data set's frames: what a reconstructor learned from simulated
           closed loops of this geometry would give.
  --lags L,L...  with --train: the "sim" map's input is the slopes of frames t + L for
           every L given (0 is frame t itself; clamped at each data set's ends), stacked:
           a space-time map from a few neighbouring frames' slopes, learned on the
           simulations (frozen flow moves the screen by L v / rate between them).
  --rows R,R...  only these rows (e.g. vk,sim).
  --write-sim-recon W.fits  writes the "sim" map as a reconstructor file (nslopes x nact,
           m per rad; 0 for the slopes no subaperture sees) for `speckles --recon W.fits`.

Prints the NCP error [nm] of each row: the default (the residual's mean taken out) and with
pupil --keep-resmean."""
import argparse
import glob
import os
import re
import subprocess
import sys

import numpy as np
import specklewfs.fits as F

ap = argparse.ArgumentParser()
ap.add_argument("dir")
ap.add_argument("--specklewfs", default=os.path.join(os.path.dirname(__file__), "..", "build", "specklewfs"))
ap.add_argument("--ridge", type=float, default=1e-6)
ap.add_argument("--in-sample", action="store_true")
ap.add_argument("--train", nargs="+", default=[])
ap.add_argument("--write-sim-recon")
ap.add_argument("--rows", default="")
ap.add_argument("--lags", default="0")
a = ap.parse_args()
D, EXE = a.dir, a.specklewfs


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode:
        sys.exit(f"recon_oracle: {' '.join(cmd)} failed:\n{r.stdout}{r.stderr}")
    return r.stdout


def series(pattern, ext=None, d=None):
    d = d or D
    files = sorted(glob.glob(os.path.join(d, pattern)))
    if not files:
        sys.exit(f"recon_oracle: {d}: no {pattern} (run bench_telemetry with --truth --keep {d})")
    return np.concatenate([np.array(F.read_fits(f, ext)[0]) for f in files]), files


S, sfiles = series("slopes_0*.fits")
Z, _ = series("truewf_0*.fits")
Z = Z - Z.mean(1, keepdims=True)  # piston: nothing sees it
nfr = S.shape[0]
ffr = F.read_fits(sfiles[0])[0].shape[0]
keys = F.read_keys(sfiles[0], ["NSUB", "WFSRATE"])
band, rate = int(keys["NSUB"]) / 2, keys["WFSRATE"]
used = np.where(np.abs(S).sum(0) > 0)[0]
X = S[:, used]
print(f"{D}: {nfr} WFS frames, {len(used)} slopes, {Z.shape[1]} actuators, band {band:g} lambda/D")


def ncp(prefix, Zhat):
    """The NCP errors of the wavefronts Zhat (frames x actuators) through the linear model."""
    for f in range(len(sfiles)):
        F.write_fits(os.path.join(D, f"{prefix}_{f:03d}.fits"), Zhat[f * ffr:(f + 1) * ffr],
                     keys={"FRAME0": f * ffr, "WFSRATE": rate})
    t = open(os.path.join(D, "timing.txt")).read().replace("/slopes_", f"/{prefix}_")
    open(os.path.join(D, f"timing_{prefix}.txt"), "w").write(t)
    run([EXE, "speckles", f"{D}/timing_{prefix}.txt", "--science", f"{D}/science.fits", "--basis",
         f"{D}/influence.fits", "--coef-scale", "1", "--band", f"{band:g}", "--match", f"{D}/science.fits",
         f"{D}/sci_{prefix}.fits", "-o", f"{D}/spk_{prefix}.fits"])
    run([EXE, "estimate", f"{D}/sci_{prefix}.fits", f"{D}/spk_{prefix}.fits", "-o", f"{D}/halo_{prefix}.fits"])
    # one fit: pupil --truth prints the error with the AO residual's mean kept too (where it
    # took one out; else the same error)
    o = run([EXE, "pupil", f"{D}/halo_{prefix}.fits", "-o", f"{D}/pupil_{prefix}.fits", "--truth", f"{D}/truth.fits"])
    err = float(re.search(r"versus truth.*error ([0-9.]+) nm", o).group(1))
    kept = re.search(r"mean kept +error ([0-9.]+) nm", o)
    return [err, float(kept.group(1)) if kept else err]


LAGS = [int(v) for v in a.lags.split(",")]


def stack(X):
    """The slopes of frames t + L for every L of --lags side by side (one data set's frames)."""
    t = np.arange(X.shape[0])
    return np.hstack([X[np.clip(t + L, 0, X.shape[0] - 1)] for L in LAGS])


def fit(Xt, Yt):
    G = Xt.T @ Xt
    G[np.diag_indices_from(G)] += a.ridge * np.trace(G) / len(G)
    return np.linalg.solve(G, Xt.T @ Yt)


def learned(X):
    if a.in_sample:
        return X @ fit(X, Z)
    out = np.zeros_like(Z)
    half = np.arange(nfr) < nfr // 2
    for tr in (half, ~half):
        out[~tr] = X[~tr] @ fit(X[tr], Z[tr])
    return out


run([EXE, "speckles", f"{D}/timing.txt", "--science", f"{D}/science.fits", "--actuators", f"{D}/actuators.fits",
     "--recon", "vk", "--write-recon", f"{D}/recon_vk.fits", "-o", f"{D}/spk_vk_native.fits"])
W = np.array(F.read_fits(f"{D}/recon_vk.fits")[0])
want = set(a.rows.split(",")) if a.rows else None
rows = [("vk", S @ W.T), ("truth", Z)]
if want is None or "learned" in want:
    rows.append(("learned", learned(X)))
if a.in_sample:
    rows.append(("reversed", learned(X[::-1].copy())))
if a.train:
    DMc = series("truewf_0*.fits", "DM")[0]
    St, Zt, Mt = [], [], []
    for d in a.train:
        St.append(stack(series("slopes_0*.fits", d=d)[0][:, used]))
        z = series("truewf_0*.fits", d=d)[0]
        Zt.append(z - z.mean(1, keepdims=True))
        m = series("truewf_0*.fits", "DM", d=d)[0]
        Mt.append(m - m.mean(1, keepdims=True))
    St, Zt, Mt = np.concatenate(St), np.concatenate(Zt), np.concatenate(Mt)
    if St.shape[1] != len(LAGS) * X.shape[1] or Zt.shape[1] != Z.shape[1]:
        sys.exit(f"recon_oracle: --train data have {St.shape[1]} slopes and {Zt.shape[1]} actuators, this set "
                 f"{X.shape[1]} and {Z.shape[1]}: train on the same geometry")
    print(f"trained on {St.shape[0]} simulated WFS frames from {len(a.train)} data sets, lags {LAGS}")
    A = fit(St, Zt)
    rows.append(("sim", stack(X) @ A))
    if a.write_sim_recon and LAGS != [0]:
        sys.exit("recon_oracle: --write-sim-recon writes a per-frame map; it cannot hold --lags")
    if a.write_sim_recon:
        Wsim = np.zeros((Z.shape[1], S.shape[1]))
        Wsim[:, used] = A.T
        F.write_fits(a.write_sim_recon, Wsim)
        print(f"wrote {a.write_sim_recon}: the sim map as a reconstructor ({Wsim.shape[1]} slopes x {Wsim.shape[0]} "
              f"actuators)")
    Mc = DMc - DMc.mean(1, keepdims=True)
    rows.append(("sim+dm", np.hstack([stack(X), Mc]) @ fit(np.hstack([St, Mt]), Zt)))
print(f"{'wavefront':10s} {'NCP [nm]':>9s} {'kept':>6s} {'per frame [nm]':>15s}")
for name, Zhat in rows:
    if want is not None and name not in want:
        continue
    e = ncp(f"or_{name.replace('+', '_')}", Zhat)
    print(f"{name:10s} {e[0]:9.1f} {e[1]:6.1f} {1e9 * np.sqrt(((Zhat - Z) ** 2).mean()):15.1f}", flush=True)

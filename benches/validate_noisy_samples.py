"""False attributions of the gap diagnosis on noisy single samples of a sensor turned by hand.

A table of 300 rows, each one sample (or a short mean) taken while the sensor is turned
slowly by hand: a random walk of attitudes with steps of 3-25 deg, white noise of ``sigma``
(relative to g) on each row, raw counts of a lower-triangular K (about 16400 counts per g),
no effect. Diagnosed as ``accelcal diagnose FILE --means --g 1`` does (no per-row variance:
unit weights, F tests). Any attributed effect, or a structure verdict other than "none", is
a false alarm (alpha 5 %).

Before the effect columns took the output on the calibration's ellipsoid, every such session
was attributed to settling (the measured mean's own noise sat in the step column and in the
residual alike). Run: ``python benches/validate_noisy_samples.py [--n 100]``.
"""

from __future__ import annotations

import argparse
import collections
import time
import warnings

import numpy as np
from accelcal import DwellSet
from accelcal.gap import diagnose

K = np.array([[16500.0, 0.0, 0.0], [-200.0, 16300.0, 0.0], [-50.0, -40.0, 16480.0]])
B = np.array([-100.0, 30.0, -300.0])


def session(sigma: float, seed: int, n: int = 300) -> np.ndarray:
    """Raw means of ``n`` rows along a random walk of attitudes, noise ``sigma`` (in g)."""
    rng = np.random.default_rng(seed)
    u = np.zeros((n, 3))
    v = rng.normal(size=3)
    v /= np.linalg.norm(v)
    for i in range(n):
        w = rng.normal(size=3)
        w -= (w @ v) * v
        w /= np.linalg.norm(w)
        th = np.radians(rng.uniform(3.0, 25.0))
        v = np.cos(th) * v + np.sin(th) * w
        v /= np.linalg.norm(v)
        u[i] = v
    a = u + rng.normal(scale=sigma, size=u.shape)
    return np.asarray((K @ a.T).T + B)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100, help="sessions per noise level")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    t0 = time.perf_counter()
    print("| noise per row | sessions | effect attributed | structure not 'none' |")
    print("|---|---|---|---|")
    for sigma in (0.044, 0.01):
        best: collections.Counter[str] = collections.Counter()
        verdict: collections.Counter[str] = collections.Counter()
        for seed in range(args.n):
            r = diagnose(DwellSet(session(sigma, 1000 + seed)), g=1.0)
            best[r.best] += 1
            verdict[r.structure.verdict] += 1
        fa = args.n - best["none"]
        fs = args.n - verdict["none"]
        detail = ", ".join(f"{k} {v}" for k, v in sorted(best.items()) if k != "none")
        sdetail = ", ".join(f"{k} {v}" for k, v in sorted(verdict.items()) if k != "none")
        print(f"| {sigma:g} g | {args.n} | {100 * fa / args.n:.1f} % ({detail or 'none'}) | "
              f"{100 * fs / args.n:.1f} % ({sdetail or 'none'}) |")
    print(f"\nRun time: {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()

"""Timing of accelcal.diagnose on 30 dwells with the structure tests (target <= 5 ms), against a
NumPy/SciPy baseline run in the same process.

The session carries half-dwell means, so every structure test runs (persistence, attitude
harmonics, time and temperature trends, pose history, per-dwell offset). The baseline is the
same baseline fit + leave-one-dwell-out held-out gap in pure NumPy/SciPy
(scipy.optimize.least_squares per fold, no effect selection, no structure tests) - a lower bound
on what a Python implementation of the full diagnosis would cost.

    .venv/bin/python -m pytest benches/bench_gap.py -o addopts="" --benchmark-only -s
"""

from __future__ import annotations

import time

import accelcal
import numpy as np
import pytest
from accelcal.sim.gap import gap_session


def _session():  # type: ignore[no-untyped-def]
    s = gap_session(("drift",), rng=1, n_dwells=30, amplitudes=[20.0])
    d = s.dwells
    gen = np.random.default_rng(1)
    noise = gen.normal(size=(len(d), 2, 3)) * np.sqrt(d.var / d.count[:, None])[:, None, :]
    half = d.mean[:, None, :] + noise - noise.mean(axis=1, keepdims=True)
    s.dwells = accelcal.DwellSet(d.mean, d.var, d.count, d.t, d.temperature, fs=d.fs,
                                 half_mean=half)
    return s


def _numpy_loo(mean: np.ndarray, sig: np.ndarray, g: float, p0: np.ndarray) -> float:
    from scipy.optimize import least_squares

    def res(p, rows):  # type: ignore[no-untyped-def]
        K = np.array([[p[0], 0, 0], [p[6], p[1], 0], [p[7], p[8], p[2]]])
        a = np.linalg.solve(K, (mean[rows] - p[3:6]).T).T
        return (np.linalg.norm(a, axis=1) - g) / sig[rows]

    n = len(mean)
    z = []
    for j in range(n):
        rows = np.array([k for k in range(n) if k != j])
        f = least_squares(res, p0, args=(rows,), method="lm")
        z.append(res(f.x, np.array([j]))[0])
    return float(np.sqrt(np.mean(np.square(z))))


def test_diagnose_30_dwells(benchmark):  # type: ignore[no-untyped-def]
    s = _session()
    r = benchmark(lambda: accelcal.diagnose(s.dwells, g=s.g))
    assert r.best == "drift" and r.structure.persistence_testable
    assert all(t.status == "testable" for t in r.structure.tests
               if t.name in ("attitude", "time", "temperature", "pose_history", "persistence"))
    med = benchmark.stats.stats.median
    d = s.dwells
    sig = np.sqrt(np.mean(d.var / d.count[:, None], axis=1))
    t0 = time.perf_counter()
    _numpy_loo(d.mean, sig, s.g, r.params)
    base = time.perf_counter() - t0
    print(f"\ndiagnose(30 dwells, LOO + in-fold selection + structure tests): {1e3 * med:.2f} ms "
          f"(target <= 5 ms); NumPy/SciPy baseline LOO only: {1e3 * base:.1f} ms; ratio "
          f"{base / med:.0f}x")


if __name__ == "__main__":  # plain timing without pytest-benchmark
    s = _session()
    for _ in range(5):
        accelcal.diagnose(s.dwells, g=s.g)
    ts = []
    for _ in range(50):
        t0 = time.perf_counter()
        accelcal.diagnose(s.dwells, g=s.g)
        ts.append(time.perf_counter() - t0)
    print(f"diagnose on 30 dwells: median {1e3 * np.median(ts):.2f} ms, min {1e3 * min(ts):.2f} ms")
    pytest.main([__file__, "-q", "--benchmark-only", "-s", "-p", "no:cacheprovider"])

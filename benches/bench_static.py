"""pytest-benchmark: the static field fit against scipy.optimize.least_squares, in one process.

Workload: the norm-observation paper's simulation, n = 20 dwells, sigma = 1e-3 per axis.
``fit_static`` (the default call: exact quadric start, maximum-likelihood LM, covariance,
observability check) with the noise estimated and with ``sigma=`` given, on the whole sphere
(a determined design) and within +-30 deg (the weak-design case; the WeakDesignWarning is
filtered, as a Monte Carlo loop would). Baseline: ``least_squares(method="lm")`` on the same
maximum-likelihood residual (NumPy, 2-point Jacobian) from the same quadric start.
``fit_static_batch``: 20 000 sessions of n = 20 on all cores, fits per second.
The ratios, the load average (idle or under load) and the CPU count are printed at the end.
Run with ``make bench``.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal._reference import static_ml_residuals_reference
from accelcal.sim.static import static_dwell_means
from scipy.optimize import least_squares

_MEDIANS: dict[str, float] = {}
B = 20_000


@pytest.fixture(scope="module")
def sphere() -> Any:
    return static_dwell_means(20, max_tilt_deg=None, rng=1)


@pytest.fixture(scope="module")
def tilt30() -> Any:
    return static_dwell_means(20, rng=1)


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    yield
    m = {k: v * 1e6 for k, v in _MEDIANS.items()}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"\n[bench_static] load average {load} on {os.cpu_count()} CPUs")
    for k in ("sphere", "sphere_sigma", "weak", "weak_sigma"):
        if k in m:
            print(f"[bench_static] fit_static {k}: median {m[k]:.1f} us")
    if {"sphere", "scipy"} <= m.keys():
        print(f"[bench_static] scipy least_squares(lm), same ML cost: {m['scipy']:.0f} us "
              f"({m['scipy'] / m['sphere']:.0f}x fit_static)")
    if "batch" in _MEDIANS:
        print(f"[bench_static] fit_static_batch {B / _MEDIANS['batch']:.0f} fits/s at n = 20")


def _quiet(fn: Any, *a: Any, **k: Any) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        return fn(*a, **k)


def test_fit_static(benchmark: Any, sphere: Any) -> None:
    f = benchmark(ac.fit_static, sphere.means, sphere.g_measured)
    _MEDIANS["sphere"] = benchmark.stats.stats.median
    assert f.converged and not f.weak


def test_fit_static_sigma(benchmark: Any, sphere: Any) -> None:
    f = benchmark(ac.fit_static, sphere.means, sphere.g_measured, sigma=1e-3)
    _MEDIANS["sphere_sigma"] = benchmark.stats.stats.median
    assert f.converged and f.noise_known


def test_fit_static_tilt30_weak(benchmark: Any, tilt30: Any) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        f = benchmark(ac.fit_static, tilt30.means, tilt30.g_measured)
    _MEDIANS["weak"] = benchmark.stats.stats.median
    assert f.weak


def test_fit_static_tilt30_weak_sigma(benchmark: Any, tilt30: Any) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        f = benchmark(ac.fit_static, tilt30.means, tilt30.g_measured, sigma=1e-3)
    _MEDIANS["weak_sigma"] = benchmark.stats.stats.median
    assert f.weak


def test_scipy_least_squares_lm(benchmark: Any, sphere: Any) -> None:
    ref = ac.fit_static(sphere.means, sphere.g_measured)
    args = (sphere.means, sphere.g_measured, None, "lower")
    x = benchmark(lambda: least_squares(static_ml_residuals_reference, ref.start, args=args,
                                        method="lm", xtol=1e-12, ftol=1e-12).x)
    _MEDIANS["scipy"] = benchmark.stats.stats.median
    assert np.all(np.abs(x - ref.vector) < 1e-3 * ref.std)


def test_fit_static_batch(benchmark: Any) -> None:
    rng = np.random.default_rng(2)
    means = np.stack([static_dwell_means(20, rng=rng).means for _ in range(200)])
    means = np.ascontiguousarray(np.tile(means, (B // 200, 1, 1)))
    b = benchmark.pedantic(
        ac.fit_static_batch, args=(means, 9.80665), kwargs={"sigma": 1e-3}, rounds=5
    )
    _MEDIANS["batch"] = benchmark.stats.stats.median
    assert b.ok.mean() > 0.99

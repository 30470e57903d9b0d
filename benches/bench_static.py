"""pytest-benchmark: static field fit (seed 000) against scipy.optimize.least_squares.

Workload: SPEC 1 simulation, n = 20 dwells, sigma = 1e-3 per axis, attitudes on the whole
sphere (a determined design: the default call returns without a warning).
``accelcal``: ``fit_static(means, g)`` (default: exact quadric start, LM on ``|a| - g``,
covariance, observability check). ``fit_static (+-30 deg)``: the seed's tilt range, where the
default call also builds and emits a WeakDesignWarning (silenced by a filter; still formatted).
Baseline: ``scipy.optimize.least_squares(method="lm")`` on the same residual ``|K^-1 (am - b)| - g``
(NumPy vectorised, 2-point Jacobian), started from the same quadric solution, in the same
process. ``fit_static_batch``: 20 000 sessions of n = 20, fits per second on all cores.
The ratios are printed at the end of the module. Run with ``make bench``.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal.sim.static import static_dwell_means
from scipy.optimize import least_squares

_MEDIANS: dict[str, float] = {}
B = 20_000


@pytest.fixture(scope="module")
def session() -> Any:
    return static_dwell_means(20, max_tilt_deg=None, rng=1)


def _residual(means: np.ndarray, g: float):  # type: ignore[no-untyped-def]
    def res(p: np.ndarray) -> np.ndarray:
        K = np.array([[p[0], 0.0, 0.0], [p[6], p[1], 0.0], [p[7], p[8], p[2]]])
        a = np.linalg.solve(K, (means - p[3:6]).T).T
        return np.linalg.norm(a, axis=1) - g  # type: ignore[no-any-return]

    return res


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    yield
    if {"accelcal", "scipy"} <= _MEDIANS.keys():
        r = _MEDIANS["scipy"] / _MEDIANS["accelcal"]
        print(
            f"\n[bench_static] fit_static median {_MEDIANS['accelcal'] * 1e6:.1f} us, "
            f"scipy least_squares(lm) {_MEDIANS['scipy'] * 1e6:.0f} us: {r:.0f}x"
        )
    if "weak" in _MEDIANS:
        w = _MEDIANS["weak"] * 1e6
        print(f"[bench_static] fit_static at +-30 deg (warning path) {w:.1f} us")
    if "batch" in _MEDIANS:
        print(
            f"[bench_static] fit_static_batch {B / _MEDIANS['batch']:.0f} fits/s at n = 20 on "
            f"{os.cpu_count()} cores"
        )


def test_fit_static(benchmark: Any, session: Any) -> None:
    f = benchmark(ac.fit_static, session.means, session.g_measured)
    _MEDIANS["accelcal"] = benchmark.stats.stats.median
    assert f.converged and not f.weak


def test_fit_static_tilt30_weak(benchmark: Any) -> None:
    s = static_dwell_means(20, rng=1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        f = benchmark(ac.fit_static, s.means, s.g_measured)
    _MEDIANS["weak"] = benchmark.stats.stats.median
    assert f.weak


def test_scipy_least_squares_lm(benchmark: Any, session: Any) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        ref = ac.fit_static(session.means, session.g_measured)
    res = _residual(session.means, session.g_measured)
    x = benchmark(lambda: least_squares(res, ref.start, method="lm", xtol=1e-12, ftol=1e-12).x)
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

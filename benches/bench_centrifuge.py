"""pytest-benchmark: a 60-row centrifuge nls fit against scipy.optimize.least_squares.

Workload: the seed-004 sign-corrected table (60 rows, scale + bias + K2, 9 parameters).
Baseline: scipy.optimize.least_squares (trf, analytic-free 2-point Jacobian, default
tolerances tightened to 1e-12) on the same residual ``(|f|^2 - A^2 - 1) / (2 sqrt(A^2 + 1))``
with the same exact per-axis inversion, started from the same linear start values the Rust
core uses (so both solve the same problem from the same point). The ratio is printed at the
end of the module. Run with ``make bench``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from accelcal import _core
from accelcal.centrifuge import fit_centrifuge, read_centrifuge_table
from scipy.optimize import least_squares

TABLE = Path(__file__).resolve().parents[2] / "shared" / "data" / "seed004"
TABLE = TABLE / "table1_sign_corrected.csv"
G = 9.8
_MEDIANS: dict[str, float] = {}


@pytest.fixture(scope="module")
def problem() -> tuple[np.ndarray, np.ndarray]:
    t = read_centrifuge_table(TABLE)
    return np.ascontiguousarray(t.outputs), np.ascontiguousarray(t.omega)


def _linear_start(out: np.ndarray, omega: np.ndarray) -> np.ndarray:
    t = (omega**2 / G) ** 2 + 1
    a = np.c_[out**2, out, np.ones(len(out))]
    c = np.linalg.lstsq(a, t, rcond=None)[0]
    s = 1 / np.sqrt(c[:3])
    return np.r_[s, -c[3:6] / (2 * c[:3]), np.zeros(3)]


def scipy_fit(out: np.ndarray, omega: np.ndarray) -> np.ndarray:
    t = (omega**2 / G) ** 2 + 1
    st = np.sqrt(t)

    def res(p: np.ndarray) -> np.ndarray:
        s, b, d = p[:3], p[3:6], p[6:9] * 1e-4
        h = (out - b) / s
        f = 2 * h / (1 + np.sqrt(1 + 4 * d * h))
        return ((f**2).sum(1) - t) / (2 * st)

    x = least_squares(res, _linear_start(out, omega), xtol=1e-12, ftol=1e-12, gtol=1e-12).x
    return np.r_[x[:6], x[6:9] * 1e-4]


@pytest.fixture(scope="module", autouse=True)
def report() -> Iterator[None]:
    yield
    if {"accelcal", "scipy"} <= _MEDIANS.keys():
        a, s = _MEDIANS["accelcal"], _MEDIANS["scipy"]
        print(
            f"\ncentrifuge nls, 60 rows: accelcal.fit_centrifuge {a * 1e6:.1f} us "
            f"(raw core call {_MEDIANS.get('raw', float('nan')) * 1e6:.1f} us), "
            f"scipy least_squares {s * 1e6:.0f} us, ratio {s / a:.0f}x"
        )


def _run(benchmark: Any, name: str, fn: Any) -> Any:
    r = benchmark(fn)
    _MEDIANS[name] = benchmark.stats.stats.median
    return r


def test_accelcal_fit(benchmark: Any, problem: tuple[np.ndarray, np.ndarray]) -> None:
    out, om = problem
    f = _run(benchmark, "accelcal", lambda: fit_centrifuge(out, om, 1.0, g=G))
    assert abs(f.scale[0] - 1.29) < 1e-6


def test_raw_core(benchmark: Any, problem: tuple[np.ndarray, np.ndarray]) -> None:
    out, om = problem
    d = _run(benchmark, "raw",
             lambda: _core.centrifuge_fit_raw(out, om, 1.0, G, check_units=False))
    assert abs(d.params[0] - 1.29) < 1e-6


def test_scipy_least_squares(benchmark: Any, problem: tuple[np.ndarray, np.ndarray]) -> None:
    out, om = problem
    p = _run(benchmark, "scipy", lambda: scipy_fit(out, om))
    assert abs(p[0] - 1.29) < 1e-6

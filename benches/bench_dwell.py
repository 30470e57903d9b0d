"""pytest-benchmark: accelcal.dwell_stats against NumPy in the same process.

Workload: 20 dwells x 20 s x 5 kHz x 3 axes, float64 (48 MB) and int16 (12 MB). Baseline:
np.add.reduceat of the values and of their squares; ceiling: np.sum over the whole array.
Run with ``make bench`` (or ``pytest benches/bench_dwell.py --benchmark-only -p no:randomly``);
the GB/s table is printed at the end of the module.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import accelcal
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from dwell_bandwidth import numpy_reduceat, table, workload  # noqa: E402

DTYPES = ["float64", "int16"]
IMPLS: dict[str, Callable[[np.ndarray, np.ndarray], Any]] = {
    "accelcal": lambda x, b: accelcal.dwell_stats(x, b),
    "reduceat": numpy_reduceat,
    "npsum": lambda x, b: np.sum(x),
}
_MEDIANS: dict[tuple[str, str], float] = {}
_BYTES: dict[str, int] = {}


@pytest.fixture(scope="module")
def data() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {d: workload(np.dtype(d)) for d in DTYPES}


@pytest.fixture(scope="module", autouse=True)
def report(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    if len(_MEDIANS) < len(DTYPES) * len(IMPLS):
        return
    rows = []
    for d in DTYPES:
        nb = _BYTES[d]
        t = {k: _MEDIANS[(d, k)] for k in IMPLS}
        rows.append(
            {
                "dtype": d,
                "mb": nb / 1e6,
                "accelcal": nb / t["accelcal"] / 1e9,
                "reduceat": nb / t["reduceat"] / 1e9,
                "npsum": nb / t["npsum"] / 1e9,
                "t_acc_ms": 1e3 * t["accelcal"],
                "t_red_ms": 1e3 * t["reduceat"],
                "t_sum_ms": 1e3 * t["npsum"],
            }
        )
    ceiling = rows[0]["npsum"]
    for r in rows:
        r["ratio"] = r["accelcal"] / r["reduceat"]
        r["of_ceiling"] = r["accelcal"] / ceiling
        r["of_own_sum"] = r["accelcal"] / r["npsum"]
    text = "\nDwell statistics bandwidth (median times, GB/s of input bytes)\n" + table(rows)
    capman = request.config.pluginmanager.getplugin("capturemanager")
    if capman is not None:
        with capman.global_and_fixture_disabled():
            print(text)
    else:
        print(text)


@pytest.mark.parametrize("impl", list(IMPLS))
@pytest.mark.parametrize("dtype", DTYPES)
def test_dwell_bandwidth(benchmark: Any, data: Any, dtype: str, impl: str) -> None:
    x, b = data[dtype]
    fn = IMPLS[impl]
    benchmark.group = f"dwell {dtype}"
    benchmark(fn, x, b)
    _MEDIANS[(dtype, impl)] = benchmark.stats.stats.median
    _BYTES[dtype] = x.nbytes

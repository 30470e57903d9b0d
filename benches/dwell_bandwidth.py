"""Bandwidth of accelcal.dwell_stats against NumPy, in one process (plain script).

Workload (a 5 kHz field session): 20 dwells x 20 s x 5 kHz x 3 axes = 2 000 000 rows, as float64
(48 MB) and as int16 raw counts (12 MB). For each dtype the table gives, as GB/s of input bytes
(median of ``--repeats`` runs timed with time.perf_counter):

* ``accelcal``  - accelcal.dwell_stats(samples, bounds): count, mean, variance, half-dwell
  means, Allan inflation and LSB per dwell (one pass);
* ``reduceat``  - the NumPy baseline: np.add.reduceat of the values and of their squares
  (int16 first converted to float64, as the squares overflow int16);
* ``np.sum``    - np.sum over the whole array: NumPy's streaming read bandwidth of those bytes,
  taken as the machine's ceiling.

Run: ``.venv/bin/python benches/dwell_bandwidth.py [--repeats 15]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import accelcal
import numpy as np

DWELLS = 20
ROWS_PER_DWELL = 20 * 5000


def workload(dtype: Any, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) samples and (20, 2) bounds covering them."""
    rng = np.random.default_rng(seed)
    n = DWELLS * ROWS_PER_DWELL
    if np.dtype(dtype) == np.int16:
        x = (-32000 + rng.integers(-10, 11, size=(n, 3))).astype(np.int16)
    else:
        x = (9.80665 + 1e-3 * rng.standard_normal((n, 3))).astype(dtype)
    starts = np.arange(DWELLS) * ROWS_PER_DWELL
    bounds = np.column_stack([starts, starts + ROWS_PER_DWELL])
    return x, bounds


def median_time(fn: Callable[[], Any], repeats: int) -> float:
    fn()  # warm up (page faults, thread pool)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def numpy_reduceat(x: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-dwell sums of values and squares (NumPy baseline)."""
    xf = x if x.dtype == np.float64 else x.astype(np.float64)
    idx = bounds[:, 0]
    return np.add.reduceat(xf, idx, axis=0), np.add.reduceat(xf * xf, idx, axis=0)


def measure(repeats: int) -> list[dict[str, Any]]:
    rows = []
    for dtype in (np.float64, np.int16):
        x, bounds = workload(dtype)
        nbytes = x.nbytes
        # Sanity: both give the same means.
        d = accelcal.dwell_stats(x, bounds)
        s1, _ = numpy_reduceat(x, bounds)
        np.testing.assert_allclose(d.mean, s1 / ROWS_PER_DWELL, rtol=1e-9)
        t_acc = median_time(lambda x=x, b=bounds: accelcal.dwell_stats(x, b), repeats)
        t_red = median_time(lambda x=x, b=bounds: numpy_reduceat(x, b), repeats)
        t_sum = median_time(lambda x=x: np.sum(x), repeats)
        rows.append(
            {
                "dtype": np.dtype(dtype).name,
                "mb": nbytes / 1e6,
                "accelcal": nbytes / t_acc / 1e9,
                "reduceat": nbytes / t_red / 1e9,
                "npsum": nbytes / t_sum / 1e9,
                "t_acc_ms": t_acc * 1e3,
                "t_red_ms": t_red * 1e3,
                "t_sum_ms": t_sum * 1e3,
            }
        )
    # The machine's memory-bandwidth ceiling: np.sum over the float64 array.
    ceiling = rows[0]["npsum"]
    for r in rows:
        r["ratio"] = r["accelcal"] / r["reduceat"]
        r["of_ceiling"] = r["accelcal"] / ceiling
        r["of_own_sum"] = r["accelcal"] / r["npsum"]
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    out = [
        "| dtype | MB | accelcal GB/s (ms) | reduceat GB/s (ms) | np.sum GB/s (ms) "
        "| x reduceat | of f64 np.sum ceiling | of same-array np.sum |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r['dtype']} | {r['mb']:.0f} | {r['accelcal']:.2f} ({r['t_acc_ms']:.1f}) "
            f"| {r['reduceat']:.2f} ({r['t_red_ms']:.1f}) | {r['npsum']:.2f} ({r['t_sum_ms']:.1f}) "
            f"| {r['ratio']:.1f}x | {100 * r['of_ceiling']:.0f} % | {100 * r['of_own_sum']:.0f} % |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    rows = measure(args.repeats)
    print(
        f"# {time.strftime('%Y-%m-%d')}  {platform.machine()} {platform.processor() or ''} "
        f"{os.cpu_count()} CPUs  numpy {np.__version__}  accelcal {accelcal.__version__}  "
        f"median of {args.repeats} repeats"
    )
    print(table(rows))


if __name__ == "__main__":
    main()

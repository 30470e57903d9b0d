"""pytest-benchmark: 2-omega demodulation (accelcal.demodulate) against NumPy in the same process.

Workload: a simulated start-up, 4 dwells x 250 s x 1 kHz of a1..a4 float64 plus the spin phase
(1e6 rows, 40 MB). Baseline: the same least squares in NumPy (np.sin/np.cos of the phase, the
5-column design and np.linalg.lstsq per dwell, `accelcal.gradiometer.demodulate_reference`);
ceiling: np.sum over the samples and the phase (one pass at memory bandwidth). Run with
``make bench`` or ``pytest benches/bench_gradiometer.py --benchmark-only``; the GB/s table is
printed at the end of the module.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import accelcal
import numpy as np
import pytest
from accelcal._reference import demodulate_reference
from accelcal.sim import gradiometer_session

_MEDIANS: dict[str, float] = {}


@pytest.fixture(scope="module")
def session() -> Any:
    return gradiometer_session(
        [0.0, 45.0, 90.0, 135.0], fs=1000.0, dwell_s=250.0, noise_mps2=3e-8,
        scale_mismatch=1e-4, tilt_mps2=(1e-4, 0.0), seed=1,
    )


def _numpy(s: Any) -> list[tuple[float, float]]:
    out = []
    for a, b in s.bounds:
        out.append(demodulate_reference(s.accel, s.phase, int(a), int(b), s.radius_m))
    return out


IMPLS: dict[str, Callable[[Any], Any]] = {
    "accelcal": lambda s: accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m),
    "numpy": _numpy,
    "npsum": lambda s: (np.sum(s.accel), np.sum(s.phase)),
}


@pytest.fixture(scope="module", autouse=True)
def report(request: pytest.FixtureRequest, session: Any) -> Iterator[None]:
    yield
    if len(_MEDIANS) < len(IMPLS):
        return
    nb = session.accel.nbytes + session.phase.nbytes
    gbs = {k: nb / v / 1e9 for k, v in _MEDIANS.items()}
    text = (
        f"\n2-omega demodulation, {nb / 1e6:.0f} MB (a1..a4 + phase, float64), median times\n"
        + "".join(f"  {k:<9} {1e3 * _MEDIANS[k]:9.2f} ms {gbs[k]:8.2f} GB/s\n" for k in IMPLS)
        + f"  accelcal / numpy = {gbs['accelcal'] / gbs['numpy']:.1f}x; "
        f"accelcal at {gbs['accelcal'] / gbs['npsum']:.0%} of the np.sum ceiling"
    )
    capman = request.config.pluginmanager.getplugin("capturemanager")
    if capman is not None:
        with capman.global_and_fixture_disabled():
            print(text)
    else:
        print(text)


@pytest.mark.parametrize("impl", list(IMPLS))
def test_demodulation_bandwidth(benchmark: Any, session: Any, impl: str) -> None:
    benchmark.group = "gradiometer demodulation"
    out = benchmark(IMPLS[impl], session)
    _MEDIANS[impl] = benchmark.stats.stats.median
    if impl == "accelcal":
        ref = _numpy(session)
        assert np.allclose(out.outputs, np.array(ref), atol=1e-6)

"""Every dwell entry point gives bit-identical results for every layout of its array arguments
(C/Fortran order, strides, slices, unaligned, float32/int16/int32/int64/uint16, big-endian, a
pandas DataFrame, ``__array__``) as for the C-ordered float64 call."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from accelcal import CalibrationError, DwellAccumulator, DwellSet, detect_dwells, dwell_stats
from layouts import LAYOUT_NAMES, layout_variants

FIELDS = (
    "mean", "var", "count", "start", "stop", "t", "temperature", "threshold", "noise_std",
    "half_mean", "inflation", "lsb",
)


def assert_same(a: DwellSet, b: DwellSet) -> None:
    for name in FIELDS:
        va, vb = getattr(a, name), getattr(b, name)
        assert (va is None) == (vb is None), name
        if va is not None:
            assert va.dtype == vb.dtype and va.shape == vb.shape, name
            assert np.array_equal(va, vb, equal_nan=va.dtype.kind == "f"), name
    assert a.dropped == b.dropped


def counts(seed: int = 5, fs: float = 100.0) -> np.ndarray:
    """Static poses and moves as whole, positive raw counts (exact in every dtype)."""
    rng = np.random.default_rng(seed)
    rows, prev = [], np.array([0.0, 0.0, 1.0])
    for _ in range(5):
        rows.append(prev + 0.004 * rng.standard_normal((int(fs * rng.uniform(3, 5)), 3)))
        nxt = rng.normal(size=3)
        nxt /= np.linalg.norm(nxt)
        f = np.linspace(0, 1, int(fs))[:, None]
        rows.append(prev + f * (nxt - prev) + 0.004 * rng.standard_normal((int(fs), 3)))
        prev = nxt
    return np.round(np.concatenate(rows) * 3000) + 5000


X = counts()
N = X.shape[0]
T = np.arange(N, dtype=np.float64)  # whole numbers: exact in every dtype
# T counts samples, so the rate is 1 sample per unit of T (fs = 1) and the detector settings
# are in samples (those of 1 s, 0.1 s and 0.02 s at 100 Hz): t must agree with fs.
SAMPLE_UNITS: dict[str, float] = {"window_s": 100.0, "min_dwell_s": 100.0, "trim_s": 10.0,
                                  "block_s": 2.0}
TEMP = np.round(np.linspace(10, 30, N))
BOUNDS = np.array([[20, 300], [500, 800], [1000, 1001 + 64], [1500, 1780]])
VARIANTS = dict(layout_variants(X))
CH_VARIANTS = dict(layout_variants(T))
TEMP_VARIANTS = dict(layout_variants(TEMP))


@pytest.fixture(scope="module")
def ref() -> dict[str, DwellSet]:
    return {
        "stats": dwell_stats(X, BOUNDS, t=T, temperature=TEMP, fs=1.0),
        "detect": detect_dwells(X, 1.0, **SAMPLE_UNITS, t=T, temperature=TEMP),
    }


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_dwell_stats_any_layout(layout: str, ref: dict[str, DwellSet]) -> None:
    got = dwell_stats(VARIANTS[layout], BOUNDS, t=CH_VARIANTS[layout],
                      temperature=TEMP_VARIANTS[layout], fs=1.0)
    assert_same(got, ref["stats"])


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_detect_dwells_any_layout(layout: str, ref: dict[str, DwellSet]) -> None:
    got = detect_dwells(VARIANTS[layout], 1.0, **SAMPLE_UNITS, t=CH_VARIANTS[layout],
                        temperature=TEMP_VARIANTS[layout])
    assert len(got) == 5
    assert_same(got, ref["detect"])


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
@pytest.mark.parametrize("mode", ["bounds", "detect"])
def test_accumulator_any_layout(layout: str, mode: str, ref: dict[str, DwellSet]) -> None:
    acc = DwellAccumulator(BOUNDS, fs=1.0) if mode == "bounds" else DwellAccumulator(
        fs=1.0, **SAMPLE_UNITS)
    x, t, temp = VARIANTS[layout], CH_VARIANTS[layout], TEMP_VARIANTS[layout]
    for a, b in [(0, 333), (333, 334), (334, 1200), (1200, N)]:
        # Chunks of the layout variant itself (a DataFrame is sliced as a DataFrame).
        sl = slice(a, b)
        chunk = x.iloc[sl] if hasattr(x, "iloc") else (
            np.asarray(x)[sl] if not isinstance(x, np.ndarray) else x[sl]
        )
        tc = t.iloc[sl] if hasattr(t, "iloc") else np.asarray(t)[sl]
        tpc = temp.iloc[sl] if hasattr(temp, "iloc") else np.asarray(temp)[sl]
        acc.push(chunk, t=tc, temperature=tpc)
    assert_same(acc.finish(), ref["stats" if mode == "bounds" else "detect"])


BOUND_LAYOUTS: list[tuple[str, Any]] = [
    ("list", BOUNDS.tolist()),
    ("int32", BOUNDS.astype(np.int32)),
    ("uint32", BOUNDS.astype(np.uint32)),
    ("F", np.asfortranarray(BOUNDS)),
    ("big_endian", BOUNDS.astype(">i8")),
    ("whole_floats", BOUNDS.astype(np.float64)),
    ("strided", np.repeat(BOUNDS, 2, axis=0)[::2]),
]


@pytest.mark.parametrize(("name", "bounds"), BOUND_LAYOUTS)
def test_bounds_any_layout(name: str, bounds: Any, ref: dict[str, DwellSet]) -> None:
    assert_same(dwell_stats(X, bounds, t=T, temperature=TEMP, fs=1.0), ref["stats"])


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_dwellset_any_layout(layout: str) -> None:
    mean = np.round(X[:8] - 5000)
    want = DwellSet(mean, np.abs(mean), np.arange(1, 9), T[:8], start=np.arange(8),
                    stop=np.arange(8) + 5)
    m = dict(layout_variants(mean))[layout]
    v = dict(layout_variants(np.abs(mean)))[layout]
    c = dict(layout_variants(np.arange(1.0, 9.0)))[layout]
    got = DwellSet(m, v, c, T[:8], start=np.arange(8), stop=np.arange(8) + 5)
    assert_same(got, want)


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (X + 0j, ["complex"]),
        (X.astype(object), ["dtype object"]),
        (X > 5000, ["boolean"]),
        (X.astype(str), ["dtype"]),
    ],
)
def test_refused_containers_name_the_argument(value: Any, words: list[str]) -> None:
    for call in (lambda: dwell_stats(value, BOUNDS), lambda: detect_dwells(value, 100.0)):
        with pytest.raises(CalibrationError) as e:
            call()
        assert "samples" in str(e.value)
        for w in words:
            assert w in str(e.value)

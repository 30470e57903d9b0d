"""Dwell statistics: parity with a slow NumPy reference, streaming = one-shot, detection on the
three real sessions, and every bad input."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Any

import accelcal
import numpy as np
import pytest
from accelcal import CalibrationError, DwellAccumulator, DwellSet, detect_dwells, dwell_stats
from accelcal.io import read_stream
from conftest import shared_data
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

XSENS = partial(shared_data, 'xsens-mti', 'xsens_acc.txt')
MPU = partial(shared_data, 'mpu6050-10poses', 'example_data_calibration.csv')
IMUCAL = partial(shared_data, 'imucal', 'example_ferraris_session.csv')
IMUCAL_LIST = partial(shared_data, 'imucal', 'example_ferraris_session_list.json')



HYP = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
DTYPES = [np.float64, np.float32, np.int16, np.int32]


@contextlib.contextmanager
def clear_error(*words: str) -> Iterator[None]:
    """Expect a CalibrationError whose message contains every word (never a PanicException)."""
    try:
        yield
    except CalibrationError as e:
        msg = str(e).lower()
        for w in words:
            assert w.lower() in msg, f"{w!r} not in {str(e)!r}"
    except BaseException as e:  # a pyo3 PanicException derives from BaseException
        assert type(e).__name__ != "PanicException", f"panic: {e}"
        raise AssertionError(f"expected CalibrationError, got {type(e).__name__}: {e}") from e
    else:
        raise AssertionError("expected CalibrationError, nothing was raised")


# ---- slow reference ---------------------------------------------------------------------------
def reference(x: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-pass float64 mean and variance (ddof=1) per dwell, one dwell at a time."""
    xf = np.asarray(x, dtype=np.float64)
    mean = np.array([np.mean(xf[a:b], axis=0) for a, b in bounds])
    var = np.array([np.var(xf[a:b], axis=0, ddof=1) for a, b in bounds])
    count = np.array([b - a for a, b in bounds])
    return mean, var, count


def make_samples(rng: np.random.Generator, n: int, dtype: Any, layout: str) -> np.ndarray:
    """Random samples of ``dtype`` in a C, Fortran, row-strided or column-strided layout."""
    if np.dtype(dtype).kind == "i":
        info = np.iinfo(dtype)
        centre = rng.integers(info.min // 2, info.max // 2, size=3)
        spread = rng.integers(0, 2000, size=3)
        base = centre + rng.integers(-1, 2, size=(n, 3)) * rng.integers(0, spread + 1, size=(n, 3))
        base = np.clip(base, info.min, info.max)
    else:
        offset = rng.normal(0, 1e4, size=3)
        scale = 10.0 ** rng.uniform(-4, 3, size=3)
        base = offset + scale * rng.standard_normal((n, 3))
    base = base.astype(dtype)
    if layout == "C":
        return np.ascontiguousarray(base)
    if layout == "F":
        return np.asfortranarray(base)
    if layout == "rows":  # every other row of a bigger array
        big = np.zeros((2 * n, 3), dtype=dtype)
        big[::2] = base
        return big[::2]
    big = np.zeros((n, 7), dtype=dtype)  # columns 1, 3, 5 of a wider array
    big[:, 1:6:2] = base
    return big[:, 1:6:2]


def random_bounds(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """k disjoint [start, stop) dwells of at least 2 samples (gaps allowed), shuffled."""
    cuts = np.sort(rng.choice(np.arange(1, n), size=min(2 * k, n - 1) // 2 * 2, replace=False))
    pairs = cuts.reshape(-1, 2)
    pairs = pairs[pairs[:, 1] - pairs[:, 0] >= 2]
    if pairs.shape[0] == 0:
        pairs = np.array([[0, n]])
    return pairs[rng.permutation(pairs.shape[0])]


# ---- parity -----------------------------------------------------------------------------------
@HYP
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(3, 3000),
    k=st.integers(1, 12),
    dtype=st.sampled_from(DTYPES),
    layout=st.sampled_from(["C", "F", "rows", "cols"]),
)
def test_dwell_stats_matches_numpy_reference(
    seed: int, n: int, k: int, dtype: Any, layout: str
) -> None:
    rng = np.random.default_rng(seed)
    x = make_samples(rng, n, dtype, layout)
    b = random_bounds(rng, n, k)
    got = dwell_stats(x, b)
    mean, var, count = reference(x, b)
    scale = np.abs(np.asarray(x, dtype=np.float64)).max() + 1.0
    np.testing.assert_array_equal(got.count, count)
    np.testing.assert_array_equal(got.start, b[:, 0])
    np.testing.assert_array_equal(got.stop, b[:, 1])
    np.testing.assert_allclose(got.mean, mean, rtol=1e-13, atol=1e-13 * scale)
    np.testing.assert_allclose(got.var, var, rtol=1e-10, atol=1e-24 * scale**2)


@pytest.mark.parametrize(
    ("dtype", "offset"),
    [(np.int32, 33000), (np.float64, 33000.0), (np.float32, 33000.0), (np.int16, -32000)],
)
def test_large_offset_variance_to_1e9(dtype: Any, offset: float) -> None:
    # Raw counts: a large offset with about 3 counts of noise; the variance must survive.
    rng = np.random.default_rng(33)
    n = 200_000
    noise = np.round(rng.normal(0.0, 3.0, size=(n, 3)))
    x = (offset + noise).astype(dtype)
    b = np.array([[0, 100_000], [100_000, 100_001 + 50_000], [160_000, n]])
    got = dwell_stats(x, b)
    mean, var, _ = reference(x, b)
    assert np.all(np.abs(got.var / var - 1.0) < 1e-9)
    assert np.all(np.abs(got.mean - mean) < 1e-12 * abs(offset))
    # The naive one-pass formula E[x^2] - E[x]^2 in float32 would fail this comparison:
    # make sure the test is sensitive to it by checking a known-bad estimate is rejected.
    xs = x[:100_000].astype(np.float32)
    naive = np.mean(xs * xs, axis=0, dtype=np.float32) - np.mean(xs, axis=0, dtype=np.float32) ** 2
    assert np.any(np.abs(naive / var[0] - 1.0) > 1e-9)


def test_t_and_temperature_channels() -> None:
    rng = np.random.default_rng(1)
    n = 5000
    x = rng.normal(size=(n, 3))
    t = 10.0 + np.arange(n) / 250.0 + rng.uniform(0, 1e-4, n)
    temp = 20.0 + rng.normal(0, 0.1, n)
    b = np.array([[100, 900], [1000, 4999], [0, 50]])
    d = dwell_stats(x, b, t=t, temperature=temp)
    np.testing.assert_allclose(d.t, [(t[a] + t[z - 1]) / 2 for a, z in b], rtol=1e-15)
    np.testing.assert_allclose(d.temperature, [temp[a:z].mean() for a, z in b], rtol=1e-13)
    # With only fs, the time is the mid sample time.
    d2 = dwell_stats(x, b, fs=250.0)
    np.testing.assert_allclose(d2.t, (b[:, 0] + b[:, 1] - 1) / 2 / 250.0, rtol=1e-15)
    np.testing.assert_allclose(d2.duration, (b[:, 1] - b[:, 0]) / 250.0)


# ---- streaming equals one-shot ----------------------------------------------------------------
def piecewise_static(seed: int, fs: float = 100.0, n_poses: int = 6) -> np.ndarray:
    """Static poses of 3-8 s joined by 1-2 s smooth moves, noise 0.01 (units of g)."""
    rng = np.random.default_rng(seed)
    rows = []
    prev = rng.normal(size=3)
    prev /= np.linalg.norm(prev)
    for i in range(n_poses):
        m = int(fs * rng.uniform(3, 8))
        rows.append(prev + 0.01 * rng.standard_normal((m, 3)))
        if i + 1 < n_poses:
            nxt = rng.normal(size=3)
            nxt /= np.linalg.norm(nxt)
            r = int(fs * rng.uniform(1, 2))
            f = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, r))[:, None]
            rows.append(prev + f * (nxt - prev) + 0.01 * rng.standard_normal((r, 3)))
            prev = nxt
    return np.concatenate(rows)


def push_in_chunks(acc: DwellAccumulator, cuts: list[int], x: np.ndarray, **ch: Any) -> None:
    edges = [0, *sorted(c for c in cuts if 0 < c < x.shape[0]), x.shape[0]]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        acc.push(x[a:b], **{k: v[a:b] for k, v in ch.items()})


def assert_same(a: DwellSet, b: DwellSet) -> None:
    for name in (
        "mean",
        "var",
        "count",
        "start",
        "stop",
        "t",
        "temperature",
        "threshold",
        "noise_std",
    ):
        va, vb = getattr(a, name), getattr(b, name)
        assert (va is None) == (vb is None), name
        if va is not None:
            assert np.array_equal(va, vb), name


@HYP
@given(
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from(DTYPES),
    cuts=st.lists(st.integers(0, 4000), max_size=30),
)
def test_streaming_bounds_equals_one_shot(seed: int, dtype: Any, cuts: list[int]) -> None:
    rng = np.random.default_rng(seed)
    n = 4000
    x = make_samples(rng, n, dtype, "C")
    b = random_bounds(rng, n, 8)
    t = np.cumsum(rng.uniform(0.001, 0.002, n))
    temp = rng.normal(25, 1, n)
    acc = DwellAccumulator(b, fs=500.0)
    push_in_chunks(acc, cuts, x, t=t, temperature=temp)
    assert acc.position == n
    assert_same(acc.finish(), dwell_stats(x, b, t=t, temperature=temp, fs=500.0))


@HYP
@given(
    seed=st.integers(0, 2**32 - 1),
    cuts=st.lists(st.integers(0, 5000), max_size=40),
    int_counts=st.booleans(),
)
def test_streaming_detection_equals_one_shot(seed: int, cuts: list[int], int_counts: bool) -> None:
    x = piecewise_static(seed % 1000)
    if int_counts:
        x = np.round(x * 4000 + 1000).astype(np.int16)
    n = x.shape[0]
    t = np.arange(n) / 100.0 + 5.0
    temp = np.linspace(20, 21, n)
    acc = DwellAccumulator(fs=100.0)
    push_in_chunks(acc, cuts, x, t=t, temperature=temp)
    one = detect_dwells(x, 100.0, t=t, temperature=temp)
    assert len(one) >= 1
    assert_same(acc.finish(), one)


def test_detection_finds_simulated_poses() -> None:
    x = piecewise_static(7, n_poses=8)
    d = detect_dwells(x, 100.0)
    assert len(d) == 8
    assert d.threshold is not None and np.all(np.isfinite(d.threshold)) and np.all(d.threshold > 0)
    np.testing.assert_allclose(d.noise_std, 0.01, rtol=0.25)


# ---- CSV round trip ---------------------------------------------------------------------------
def test_dwellset_csv_round_trip_exact(tmp_path: Path) -> None:
    x = piecewise_static(3)
    n = x.shape[0]
    rng = np.random.default_rng(3)
    d = detect_dwells(
        x, 100.0, t=np.arange(n) / 100.0 + 1 / 3, temperature=rng.normal(20, 1, n), units="g"
    )
    path = tmp_path / "dwells.csv"
    text = d.to_csv(path)
    for back in (DwellSet.from_csv(path), DwellSet.from_csv(text)):
        assert len(back) == len(d)
        assert_same(back, d)
        assert back.fs == d.fs and back.units == "g"
    # Constructed from arrays with only a mean.
    m = DwellSet([[1.0, 2.0, 3.0], [0.1, 0.2, 1 / 3]])
    back = DwellSet.from_csv(m.to_csv())
    assert np.array_equal(back.mean, m.mean) and back.var is None and len(back) == 2


# ---- real sessions ----------------------------------------------------------------------------
G_UNITS = {"xsens": 4070.0, "mpu": 16384.0, "imucal": 9.81}  # one g in the file's units


@pytest.fixture(scope="module")
def real() -> dict[str, tuple[np.ndarray, DwellSet]]:
    out = {}
    for name, path, fs in (
        ("xsens", XSENS(), None), ("mpu", MPU(), None), ("imucal", IMUCAL(), 102.4)
    ):
        s = read_stream(path, fs=fs)
        assert s.fs is not None
        out[name] = (s.samples, detect_dwells(s.samples, s.fs))
    return out


def test_xsens_finds_imu_tk_intervals(real: Any) -> None:
    _, d = real["xsens"]
    assert 38 <= len(d) <= 40  # imu_tk finds 38


def test_mpu6050_finds_about_ten_poses(real: Any) -> None:
    _, d = real["mpu"]
    assert 9 <= len(d) <= 11


def test_imucal_faces_found_and_rotations_avoided(real: Any) -> None:
    _, d = real["imucal"]
    sections = json.loads(IMUCAL_LIST().read_text())
    for name, sec in sections.items():
        a, b = sec["start"], sec["end"]
        overlap = np.clip(np.minimum(d.stop, b) - np.maximum(d.start, a), 0, None)
        if name.endswith("_rot"):
            assert np.all(overlap == 0), f"a dwell overlaps rotation {name}"
        else:
            # The face is (almost entirely) inside one detected dwell.
            assert overlap.max() >= 0.8 * (b - a), f"static face {name} not found"


@pytest.mark.parametrize("name", ["xsens", "mpu", "imucal"])
def test_no_dwell_spans_a_pose_change(real: Any, name: str) -> None:
    x, d = real[name]
    assert d.threshold is not None and d.noise_std is not None
    assert np.all(np.isfinite(d.threshold)) and np.all(d.threshold > 0)
    g = G_UNITS[name]
    for a, b in zip(d.start, d.stop, strict=True):
        seg = np.asarray(x[a:b], dtype=np.float64)
        h = seg.shape[0] // 2
        diff = np.abs(seg[:h].mean(axis=0) - seg[h:].mean(axis=0))
        sem = 2.0 * seg.std(axis=0, ddof=1) / np.sqrt(seg.shape[0])
        assert np.all(diff < 5.0 * sem + 0.015 * g), (name, a, b, diff)
        # The dwell is as quiet as the recording's noise floor.
        assert np.all(seg.std(axis=0, ddof=1) < 3.0 * d.noise_std), (name, a, b)
    # Consecutive dwells either hold the same pose or differ by far more than the noise.
    assert np.all(d.stop[:-1] <= d.start[1:])


# ---- bad input --------------------------------------------------------------------------------
GOOD = np.random.default_rng(0).normal(size=(2000, 3))
BAD_SAMPLES = {
    "nan": (np.where(np.arange(6000).reshape(2000, 3) == 301, np.nan, GOOD), ["nan"]),
    "inf": (np.where(np.arange(6000).reshape(2000, 3) == 302, np.inf, GOOD), ["inf"]),
    "n2": (GOOD[:, :2], ["shape"]),
    "1d": (GOOD[:, 0], ["shape"]),
    "3d": (GOOD.reshape(2000, 3, 1), ["shape"]),
    "empty": (np.empty((0, 3)), ["empty"]),
    "complex": (GOOD.astype(np.complex128), ["dtype"]),
    "bool": (GOOD > 0, ["dtype"]),
    "object": (GOOD.astype(object), ["dtype"]),
    "str": (GOOD.astype(str), ["dtype"]),
}


@pytest.mark.parametrize("case", sorted(BAD_SAMPLES))
def test_bad_samples_dwell_stats(case: str) -> None:
    x, words = BAD_SAMPLES[case]
    with clear_error(*words):
        dwell_stats(x, [[0, 1000]])


@pytest.mark.parametrize("case", sorted(BAD_SAMPLES))
def test_bad_samples_detect_and_stream(case: str) -> None:
    x, words = BAD_SAMPLES[case]
    with clear_error(*words):
        detect_dwells(x, 100.0)
    # Pushing an empty chunk is a no-op; finishing an empty stream says so.
    with clear_error(*(["no samples"] if case == "empty" else words)):
        acc = DwellAccumulator(fs=100.0)
        acc.push(x)
        acc.finish()


@pytest.mark.parametrize(
    ("bounds", "words"),
    [
        ([[0, 2001]], ["out of range"]),
        ([[-1, 10]], ["negative"]),
        ([[0, 100], [50, 150]], ["overlap"]),
        ([[100, 50]], ["reversed"]),
        ([[10, 10]], ["empty"]),
        ([[0.5, 10]], ["integer"]),
        ([["a", "b"]], ["integer"]),
        ([[0, 1, 2]], ["shape"]),
        (np.empty((0, 2)), ["empty"]),
        ([[0, np.nan]], ["integer"]),
    ],
)
def test_bad_bounds(bounds: Any, words: list[str]) -> None:
    with clear_error(*words):
        dwell_stats(GOOD, bounds)
    if words != ["out of range"]:
        with clear_error(*words):
            DwellAccumulator(bounds)


def test_stream_bounds_beyond_pushed_samples() -> None:
    acc = DwellAccumulator([[0, 100], [1900, 2500]])
    acc.push(GOOD)
    with clear_error("out of range", "2000"):
        acc.finish()


@pytest.mark.parametrize("fs", [0.0, -100.0, np.nan, np.inf, "fast"])
def test_bad_fs(fs: Any) -> None:
    with clear_error("fs"):
        detect_dwells(GOOD, fs)
    with clear_error("fs"):
        DwellAccumulator(fs=fs)
    with clear_error("fs"):
        dwell_stats(GOOD, [[0, 10]], fs=fs)


def test_bad_channels() -> None:
    with clear_error("t", "shape"):
        dwell_stats(GOOD, [[0, 10]], t=np.arange(1999.0))
    with clear_error("temperature", "shape"):
        detect_dwells(GOOD, 100.0, temperature=np.zeros(5))
    acc = DwellAccumulator([[0, 10]])
    with clear_error("t", "shape"):
        acc.push(GOOD, t=np.zeros(3))
    temp = np.zeros(2000)
    temp[5] = np.nan
    with clear_error("temperature", "nan"):
        dwell_stats(GOOD, [[0, 10]], temperature=temp)
    # A channel given with some chunks but not others.
    acc = DwellAccumulator([[0, 10]])
    acc.push(GOOD[:100], t=np.zeros(100))
    with clear_error("t", "every chunk"):
        acc.push(GOOD[100:])


def test_detector_bad_settings_and_short_stream() -> None:
    with clear_error("too short"):
        detect_dwells(GOOD[:50], 100.0)
    with clear_error("window_s"):
        detect_dwells(GOOD, 100.0, window_s=-1.0)
    with clear_error("noise_quantile"):
        detect_dwells(GOOD, 100.0, noise_quantile=1.5)
    with clear_error("noise_std"):
        detect_dwells(GOOD, 100.0, noise_std=(1.0, 0.0, 1.0))
    with clear_error("bounds", "fs"):
        DwellAccumulator()
    with clear_error("no samples"):
        DwellAccumulator(fs=100.0).finish()


def test_overflowing_values_are_an_error_not_garbage() -> None:
    x = np.full((100, 3), 1e300)
    x[::2] *= -1
    with clear_error("nan or inf"):
        dwell_stats(x, [[0, 100]])


@pytest.mark.parametrize("path", ["/nonexistent/file.txt", "/", "__bin__"])
def test_unreadable_file(path: str, tmp_path: Path) -> None:
    if path == "__bin__":
        p = tmp_path / "rec.csv"
        p.write_bytes(b"\x00\xff\xfe\x80" * 100)
        path = str(p)
    with clear_error(str(path)):
        accelcal.io.read_stream(path)
    with clear_error(str(path)):
        accelcal.io.stream_dwells(path, fs=100.0)

"""Property test over the public API: any array (random shape, dtype, memory layout and
content - NaN, inf, huge, constant, empty) or any value of a numeric option gives either a
correct result or a ``CalibrationError`` / ``DegenerateDataError`` whose message names the
argument. Never another exception type, never a NaN in a result without a status, never a
panic (pyo3's PanicException is a BaseException and would fail the test), never a hang
(the profile's cases each finish in well under a second).

The centrifuge and gradiometer fits have their own property tests in
``test_centrifuge_gradiometer_inputs.py``; the dwell kernels' streaming properties are in
``test_dwell.py``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from typing import Any

import accelcal as ac
import hypothesis.extra.numpy as hnp
import numpy as np
from accelcal import CalibrationError
from accelcal._triad import fibonacci_sphere
from hypothesis import given
from hypothesis import strategies as st

G = 9.80665
GOOD = G * fibonacci_sphere(24) @ np.diag([1.01, 0.99, 1.02]).T + [0.02, -0.03, 0.05]

DTYPES = [np.float64, np.float32, np.int16, np.int32, np.int64, np.uint8, np.bool_,
          np.complex128, np.dtype(">f8"), np.dtype("<M8[s]")]
SPECIAL = [np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0, 1e-300]


@st.composite
def any_array(draw: Any, max_dims: int = 3, max_side: int = 30) -> Any:
    """A random array in a random container and layout."""
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")  # casts of drawn specials to small dtypes may overflow
        return _any_array(draw, max_dims, max_side)


def _any_array(draw: Any, max_dims: int, max_side: int) -> Any:
    dtype = np.dtype(draw(st.sampled_from(DTYPES)))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=max_dims, min_side=0, max_side=max_side))
    kind = draw(st.sampled_from(["random", "special", "constant", "good_like"]))
    if kind == "good_like" and dtype.kind == "f":
        n = draw(st.integers(0, 40))
        a = np.resize(GOOD, (n, 3)).astype(dtype)
    elif dtype.kind == "M":
        a = np.zeros(shape, dtype=dtype)
    else:
        a = draw(hnp.arrays(dtype, shape, elements=hnp.from_dtype(
            dtype, allow_nan=True, allow_infinity=True) if dtype.kind in "fc" else None))
        if kind == "special" and a.size and dtype.kind == "f":
            flat = a.reshape(-1)
            idx = draw(st.lists(st.integers(0, flat.size - 1), max_size=5))
            for i in idx:
                flat[i] = draw(st.sampled_from(SPECIAL))
        if kind == "constant" and a.size:
            a = np.full(a.shape, a.reshape(-1)[0], dtype=a.dtype)
    layout = draw(st.sampled_from(["C", "F", "strided", "reversed", "list", "pandas"]))
    if layout == "F":
        return np.asfortranarray(a)
    if layout == "strided" and a.ndim >= 1:
        big = np.zeros((2 * a.shape[0], *a.shape[1:]), dtype=a.dtype)
        big[::2] = a
        return big[::2]
    if layout == "reversed" and a.ndim >= 1:
        return a[::-1]
    if layout == "list":
        return a.tolist()
    if layout == "pandas" and a.ndim == 2 and dtype.kind in "fiu":
        import pandas as pd

        return pd.DataFrame(a)
    return a


ANY_NUMBER = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**70), 2**70),
    st.sampled_from([None, "ten", "", True, [1.0, 2.0], complex(1, 1)]),
)


def _check(call: Callable[[], Any], words: list[str], result_ok: Callable[[Any], bool]) -> None:
    """Run ``call``: a result must pass ``result_ok``, an error must be ours and name one of
    ``words``."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # warnings are the point of other tests
            res = call()
    except CalibrationError as e:  # DegenerateDataError included
        msg = str(e).lower()
        assert any(w.lower() in msg for w in words), f"message names none of {words}: {e}"
        assert msg.strip(), "empty message"
        return
    assert result_ok(res), f"result without a status: {res!r}"


def _finite(*xs: Any) -> bool:
    return all(np.all(np.isfinite(np.asarray(x, dtype=np.float64))) for x in xs)


# ---- static calibration --------------------------------------------------------------------
@given(any_array())
def test_fit_static_any_data(x: Any) -> None:
    # chi2/dof (and the scaled std) are NaN only when dof == 0 (no redundancy: said so).
    _check(lambda: ac.fit_static(x, G), ["data", "dwell", "mean", "means"],
           lambda f: _finite(f.vector, f.residuals) and (f.chi2_dof >= 0 or f.dof == 0))


@given(ANY_NUMBER)
def test_fit_static_any_g(g: Any) -> None:
    _check(lambda: ac.fit_static(GOOD, g), ["g"], lambda f: _finite(f.vector))


@given(st.sampled_from(["max_iter", "weak_std", "degenerate_std"]), ANY_NUMBER)
def test_fit_static_any_option(name: str, v: Any) -> None:
    _check(lambda: ac.fit_static(GOOD, G, **{name: v}), [name], lambda f: _finite(f.vector))


@given(any_array())
def test_fit_static_any_sigma(s: Any) -> None:
    # A huge sigma makes the design undetermined: the error then names what the dwells cannot
    # determine.
    _check(lambda: ac.fit_static(GOOD, G, sigma=s), ["sigma", "dwells cannot determine"],
           lambda f: _finite(f.vector))


@given(st.one_of(any_array(), st.lists(any_array(max_dims=2), max_size=4)))
def test_fit_static_batch_any_means(x: Any) -> None:
    def ok(b: Any) -> bool:
        bad = ~np.all(np.isfinite(np.asarray(b.params, dtype=np.float64)), axis=-1)
        state = np.asarray(b.state)
        # Non-finite parameters only where the session's state says why.
        return bool(np.all(state[np.atleast_1d(bad)] != "ok"))

    _check(lambda: ac.fit_static_batch(x, G), ["means", "session", "dwell", "mask"], ok)


@given(any_array())
def test_triad_model_any_k(k: Any) -> None:
    _check(lambda: ac.TriadModel(k, [0.0, 0.0, 0.0]), ["K"],
           lambda m: _finite(m.apply(GOOD)))


@given(any_array())
def test_triad_model_apply_any_raw(x: Any) -> None:
    m = ac.TriadModel(np.eye(3), [0.0, 0.0, 0.0])

    def ok(a: Any) -> bool:
        a = np.asarray(a)
        raw = np.asarray(x, dtype=np.float64) if not hasattr(x, "to_numpy") else x.to_numpy()
        # A calibrated sample is non-finite only where its raw row has a non-finite value
        # (K^-1 mixes the axes of one row, never rows): dropouts pass through as dropouts.
        bad_in = ~np.all(np.isfinite(raw.reshape(-1, 3)), axis=1)
        bad_out = ~np.all(np.isfinite(a.reshape(-1, 3)), axis=1)
        return a.shape[-1] == 3 and bool(np.all(~bad_out | bad_in))

    _check(lambda: m.apply(x), ["raw"], ok)


@given(any_array())
def test_predict_accuracy_any_attitudes(x: Any) -> None:
    _check(lambda: ac.predict_accuracy(x, 1e-3), ["attitude"],
           lambda p: p.singular or _finite(p.std))


@given(ANY_NUMBER, ANY_NUMBER)
def test_plan_poses_any_options(n: Any, tilt: Any) -> None:
    if isinstance(n, int) and not isinstance(n, bool) and n > 60:
        n = 60  # D-optimal exchange cost grows with n; the range check is what is tested
    _check(lambda: ac.plan_poses(n, tilt, restarts=1), ["n", "max_tilt"],
           lambda p: p.prediction.singular or _finite(p.std))


@given(ANY_NUMBER, ANY_NUMBER)
def test_local_gravity_any_position(lat: Any, h: Any) -> None:
    _check(lambda: ac.local_gravity(lat, h), ["lat", "height"],
           lambda g: math.isfinite(g) and 9.6 < g < 9.9)  # 9.65 at 50 km


# ---- dwells --------------------------------------------------------------------------------
@given(any_array(), ANY_NUMBER)
def test_detect_dwells_any_samples(x: Any, fs: Any) -> None:
    _check(lambda: ac.detect_dwells(x, fs if fs is not None else 100.0),
           ["samples", "fs", "window", "dwell", "min_dwell"],
           lambda d: _finite(d.mean, d.var) and np.all(d.count >= 2))


@given(any_array(max_dims=2), any_array(max_dims=2))
def test_dwell_stats_any_bounds(x: Any, b: Any) -> None:
    _check(lambda: ac.dwell_stats(x, b), ["samples", "bounds", "dwell"],
           lambda d: _finite(d.mean))


@given(any_array(), any_array())
def test_dwellset_any_arrays(m: Any, v: Any) -> None:
    _check(lambda: ac.DwellSet(m, v), ["mean", "var", "dwell"],
           lambda d: _finite(d.mean, d.var))


@given(any_array())
def test_accumulator_any_chunk(x: Any) -> None:
    acc = ac.DwellAccumulator(fs=100.0)

    def run() -> Any:
        acc.push(x)
        return acc.position

    _check(run, ["chunk", "samples"], lambda p: isinstance(p, int) and p >= 0)
    assert acc.position >= 0  # still usable after any error


# ---- gap diagnosis -------------------------------------------------------------------------
@given(any_array())
def test_diagnose_any_data(x: Any) -> None:
    def ok(r: Any) -> bool:
        return math.isfinite(r.chi2) or bool(r.statements)

    _check(lambda: ac.diagnose(x, g=G, fs=100.0, loo=False),
           ["data", "dwell", "mean", "samples", "fs"], ok)


@given(st.sampled_from(["alpha", "max_effects", "n_draws", "g"]), ANY_NUMBER)
def test_diagnose_any_option(name: str, v: Any) -> None:
    d = ac.DwellSet(GOOD, np.full_like(GOOD, 1e-6), np.ones(len(GOOD)))
    kw: dict[str, Any] = {"g": G, "loo": False}
    kw[name] = v
    _check(lambda: ac.diagnose(d, **kw), [name], lambda r: math.isfinite(r.chi2))


@given(any_array(max_dims=2, max_side=70))
def test_diagnose_centrifuge_any_outputs(x: Any) -> None:
    from accelcal.centrifuge import paper_design

    des = paper_design()
    _check(lambda: ac.diagnose_centrifuge(x, des.omega, des.radius, spin_axis=des.spin_axis,
                                          sigma=1e-5, loo=False),
           ["outputs", "omega", "row", "spin_axis"], lambda r: r.best is not None)


@given(any_array(max_dims=1), any_array(max_dims=2))
def test_diagnose_gradiometer_any_arrays(az: Any, y: Any) -> None:
    _check(lambda: ac.diagnose_gradiometer(az, y, sigma=1.0, loo=False),
           ["azimuth", "outputs"], lambda r: r.best is not None)


@given(any_array(), ANY_NUMBER)
def test_allan_deviation_any_series(x: Any, fs: Any) -> None:
    _check(lambda: ac.allan_deviation(x, fs), ["x", "fs", "sample"],
           lambda r: _finite(r[0]) and np.all(np.asarray(r[0]) > 0))


# ---- design --------------------------------------------------------------------------------
@given(ANY_NUMBER)
def test_plan_azimuths_any_m(m: Any) -> None:
    if isinstance(m, int) and not isinstance(m, bool) and m > 10_000:
        m = 10_000
    _check(lambda: ac.plan_azimuths(m), ["m", "azimuth", "dwell"],
           lambda a: _finite(a) and np.all((np.asarray(a) >= 0) & (np.asarray(a) < 180)))


@given(any_array(max_dims=1, max_side=5))
def test_centrifuge_sensitivity_any_magnitudes(m: Any) -> None:
    _check(lambda: ac.centrifuge_sensitivity(None, None, "radius", m), ["magnitude"],
           lambda s: _finite(s.shifts))

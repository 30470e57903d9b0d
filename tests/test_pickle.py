"""Every result type pickles and round-trips with every public field equal, a
DwellAccumulator checkpointed mid-stream resumes in another process with identical results, and
the results come back from a real two-process Dask cluster equal to the local ones."""

from __future__ import annotations

import copy
import dataclasses
import datetime
import multiprocessing
import pickle
import sys
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal.sim import centrifuge_session, field_session, gap_session, static_dwell_means

G = 9.80665


# ---- equality of every public field -------------------------------------------------------------
#: Zero-argument methods whose answers are part of a result's public state.
_METHODS = ("to_dict", "summary", "observability", "table", "finish")


def _state(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in dir(obj):
        if name.startswith("_"):
            continue
        try:
            v = getattr(obj, name)
        except Exception as e:  # a property that refuses (e.g. a unit alias): same refusal
            v = ("raises", type(e).__name__, str(e))
        if callable(v) and not isinstance(v, type):
            if name in _METHODS:
                out[f"{name}()"] = v()
            continue
        out[name] = v
    return out


def _same(a: Any, b: Any, where: str = "") -> None:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape and a.dtype == b.dtype, where
        if a.dtype.kind in "fc":
            np.testing.assert_array_equal(a, b, err_msg=where)  # NaN == NaN here
        elif a.dtype.kind == "O":
            for i, (x, y) in enumerate(zip(a.ravel(), b.ravel(), strict=True)):
                _same(x, y, f"{where}[{i}]")
        else:
            assert np.array_equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, float):
        assert isinstance(b, float) and (a == b or (np.isnan(a) and np.isnan(b))), where
    elif a is None or isinstance(a, (str, int, bool, np.generic, type, datetime.date)):
        assert type(a) is type(b) and (a == b or (a != a and b != b)), where
    else:  # a nested result object (NormStats, a DwellSet ...): compare its public state
        assert type(a) is type(b), where
        if dataclasses.is_dataclass(a):
            for f in dataclasses.fields(a):
                _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
        else:
            _same(_state(a), _state(b), where)


def assert_same_result(a: Any, b: Any) -> None:
    assert type(a) is type(b)
    sa, sb = _state(a), _state(b)
    assert sa, f"{type(a).__name__} has no public state to compare"
    _same(sa, sb, type(a).__name__)


def test_the_comparison_can_fail() -> None:
    s = static_dwell_means(20, max_tilt_deg=None, rng=1)
    d1 = s.dwellset()
    d2 = s.dwellset()
    d2.mean[3, 1] += 1e-15
    with pytest.raises(AssertionError):
        assert_same_result(d1, d2)
    m = ac.TriadModel(np.eye(3), [0.0, 0.0, 0.0], sensor_id="a", date="2026-01-01")
    with pytest.raises(AssertionError):
        assert_same_result(m, ac.TriadModel(np.eye(3), [0.0, 0.0, 0.0], sensor_id="b",
                                            date="2026-01-01"))


# ---- one builder per result type (module level: they run on Dask workers too) ----------------
def make_static_fit(seed: int) -> Any:
    s = static_dwell_means(20, max_tilt_deg=None, rng=seed)
    return ac.fit_static(s.dwellset(), s.g_measured)


def make_triad_model(seed: int) -> Any:
    return make_static_fit(seed).to_model(sensor_id=f"S{seed}", date="2026-05-01T08:00:00+00:00",
                                          temperature=21.5, metadata={"line": 3})


def make_dwell_set(seed: int) -> Any:
    s = field_session(fs=200.0, n_dwells=12, dwell_s=4.0, move_s=1.5, rng=seed)
    return ac.detect_dwells(s.samples, s.fs, t=s.t, temperature=20 + 0.01 * s.t)


def _stream(seed: int) -> Any:
    return field_session(fs=200.0, n_dwells=12, dwell_s=4.0, move_s=1.5, rng=seed)


def make_dwell_accumulator(seed: int) -> Any:
    s = _stream(seed)
    acc = ac.DwellAccumulator(fs=s.fs)
    acc.push(s.samples[: len(s.samples) // 2], t=s.t[: len(s.t) // 2])
    return acc


def make_centrifuge_fit(seed: int) -> Any:
    c = centrifuge_session(noise_g=1e-5, rng=seed)
    return ac.fit_centrifuge(c.outputs, c.omega, c.radius, g=c.g)


def make_startup_bias(seed: int) -> Any:
    rng = np.random.default_rng(seed)
    az = np.array([0.0, 45.0, 90.0, 135.0, 0.0, 45.0])
    t = np.arange(az.size) * 60.0
    th = np.radians(az)
    c, s = np.cos(2 * th), np.sin(2 * th)
    b, gam = rng.normal(0, 10, 2), rng.normal(0, 30, 2)
    y = np.column_stack([b[0] + c * gam[0] + s * gam[1], b[1] - s * gam[0] + c * gam[1]])
    y += np.outer(t, [1e-3, -2e-3]) + rng.normal(0, 0.5, y.shape)
    return ac.startup_bias(az, y, t=t, drift=True)


def make_gap_report(seed: int) -> Any:
    s = gap_session(("drift",), rng=seed, n_dwells=24, amplitudes=[20.0])
    return ac.diagnose(s.dwells, g=s.g)


BUILDERS: dict[str, Callable[[int], Any]] = {
    "StaticFit": make_static_fit,
    "TriadModel": make_triad_model,
    "DwellSet": make_dwell_set,
    "DwellAccumulator": make_dwell_accumulator,
    "CentrifugeFit": make_centrifuge_fit,
    "StartupBias": make_startup_bias,
    "GapReport": make_gap_report,
}


@pytest.mark.parametrize("name", list(BUILDERS))
@pytest.mark.parametrize("protocol", [2, pickle.HIGHEST_PROTOCOL])
def test_round_trip_keeps_every_public_field(name: str, protocol: int) -> None:
    obj = BUILDERS[name](3)
    assert type(obj).__name__ == name
    back = pickle.loads(pickle.dumps(obj, protocol=protocol))
    assert_same_result(obj, back)


# ---- checkpoint and resume of a stream ----------------------------------------------------------
def _resume(blob: bytes, samples: Any, t: Any) -> Any:
    acc = pickle.loads(blob)
    for i in range(0, len(samples), 997):
        acc.push(samples[i : i + 997], t=t[i : i + 997])
    return acc.finish()


@pytest.mark.parametrize("mode", ["detect", "bounds"])
def test_accumulator_checkpoint_resumes_in_another_process(mode: str) -> None:
    s = _stream(5)
    cut = int(s.bounds[5, 0] + 37)  # inside the sixth dwell
    acc = (ac.DwellAccumulator(fs=s.fs) if mode == "detect"
           else ac.DwellAccumulator(s.bounds, fs=s.fs))
    acc.push(s.samples[:cut], t=s.t[:cut])
    blob = pickle.dumps(acc)
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(1, mp_context=ctx) as ex:
        resumed = ex.submit(_resume, blob, s.samples[cut:], s.t[cut:]).result()
    whole = (ac.detect_dwells(s.samples, s.fs, t=s.t) if mode == "detect"
             else ac.dwell_stats(s.samples, s.bounds, fs=s.fs, t=s.t))
    assert len(whole) == 12
    assert_same_result(resumed, whole)
    # and the original, continued here, agrees with the copy continued elsewhere
    acc.push(s.samples[cut:], t=s.t[cut:])
    assert_same_result(acc.finish(), resumed)


# ---- a real Dask cluster ------------------------------------------------------------------------
@pytest.fixture(scope="module")
def by_value() -> None:
    import cloudpickle

    # The builders live in this test module, which the workers cannot import.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.mark.parametrize("name", list(BUILDERS))
def test_results_from_dask_workers_equal_local_ones(name: str, dask_client: Any,
                                                    by_value: None) -> None:
    import os

    seeds = [11, 12, 13, 14]
    futs = dask_client.map(BUILDERS[name], seeds, pure=False)
    remote = dask_client.gather(futs)
    for seed, r in zip(seeds, remote, strict=True):
        assert_same_result(r, BUILDERS[name](seed))
    pids = dask_client.run(os.getpid)
    assert len(set(pids.values())) == 2 and os.getpid() not in pids.values()


def test_static_fits_of_several_sessions_on_dask_workers(dask_client: Any) -> None:
    # Sessions made here, fitted on the workers (DwellSet out, StaticFit back).
    sessions = [static_dwell_means(24, max_tilt_deg=None, rng=i) for i in range(8)]
    futs = dask_client.map(ac.fit_static, [s.dwellset() for s in sessions],
                           [s.g_measured for s in sessions], pure=False)
    remote = dask_client.gather(futs)
    for s, r in zip(sessions, remote, strict=True):
        local = ac.fit_static(s.dwellset(), s.g_measured)
        assert_same_result(r, local)
        z = (r.vector - s.truth) / r.std
        assert np.abs(z).max() < 4.5


def test_result_reprs_say_what_they_hold():
    """CentrifugeFit and StartupBias printed as <object at 0x...>."""
    import warnings

    from accelcal.sim.centrifuge import centrifuge_session

    s = centrifuge_session(noise_g=1e-6, rng=1, g=9.8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        f = ac.fit_centrifuge(s.outputs, s.omega, s.radius, g=9.8)
    assert repr(f).startswith("CentrifugeFit(method='nls', rows=60, excluded=0")
    b = ac.startup_bias([0, 90, 180, 270], [[3, 3.5], [1, 2.5], [3, 3.5], [1, 2.5]], sigma=0.1)
    assert repr(b) == "StartupBias(dwells=4, bias_E=[2, 3], std_E=[0.05, 0.05], dof=4)", repr(b)


# ---- read-only arrays stay read-only in a copy ---------------------------------------------------
#: The arrays a TriadModel and a StaticFit hand out read-only (an edit in place would change
#: what apply does, or make the fit contradict itself: K against scale, to_model against vector).
_READ_ONLY = {
    "TriadModel": ("K", "bias", "covariance", "covariance_noise_model", "covariance_scaled"),
    "StaticFit": ("K", "covariance", "covariance_scaled", "covariance_realistic", "std",
                  "std_realistic"),
}

_COPIES: dict[str, Callable[[Any], Any]] = {
    **{f"pickle{p}": (lambda o, p=p: pickle.loads(pickle.dumps(o, protocol=p)))
       for p in range(pickle.HIGHEST_PROTOCOL + 1)},
    "copy": copy.copy,
    "deepcopy": copy.deepcopy,
}


@pytest.mark.parametrize("name", list(_READ_ONLY))
@pytest.mark.parametrize("how", list(_COPIES))
def test_copies_keep_the_arrays_read_only(name: str, how: str) -> None:
    obj = BUILDERS[name](3)
    for a in _READ_ONLY[name]:  # cached before the copy, as a service's fit would be
        assert not getattr(obj, a).flags.writeable, a
    back = _COPIES[how](obj)
    assert type(back) is type(obj)
    for a in _READ_ONLY[name]:
        arr = getattr(back, a)
        assert not arr.flags.writeable, f"{how}: {a} is writable"
        with pytest.raises(ValueError, match="read-only"):
            arr[0] += 1.0
        np.testing.assert_array_equal(arr, getattr(obj, a))
    assert_same_result(obj, back)


def test_an_edit_of_a_copy_cannot_change_what_it_applies() -> None:
    # The tester's case: a model through pickle, K edited in place, apply changed silently.
    m = make_triad_model(4)
    x = np.array([[0.1, -9.7, 0.3], [9.8, 0.2, -0.1]])
    back = pickle.loads(pickle.dumps(m))
    with pytest.raises(ValueError, match="read-only"):
        back.K[1, 0] += 0.5
    with pytest.raises(ValueError, match="read-only"):
        back.bias[0] += 1.0
    np.testing.assert_array_equal(back.apply(x), m.apply(x))
    assert back == m
    f = make_static_fit(4)
    f2 = copy.deepcopy(f)
    with pytest.raises(ValueError, match="read-only"):
        f2.K[0, 0] = 5.0
    np.testing.assert_array_equal(f2.to_model().K, f.K)


_CORE_RESULTS: dict[str, tuple[Callable[[], Any], tuple[str, ...]]] = {
    "Observability": (lambda: make_static_fit(5).observability(),
                      ("singular_values", "std_comparable", "weakest")),
    "BatchFit": (lambda: ac.fit_static_batch(
        np.stack([static_dwell_means(20, max_tilt_deg=None, rng=k).means for k in range(3)]),
        9.80665, sigma=1e-3),
        ("params", "std", "chi2_dof", "rms", "iterations", "n_dwells", "status", "weak")),
}


@pytest.mark.parametrize("name", list(_CORE_RESULTS))
@pytest.mark.parametrize("how", [h for h in _COPIES if h not in ("pickle0", "pickle1")])
def test_core_results_stay_read_only_through_copies(name: str, how: str) -> None:
    build, fields = _CORE_RESULTS[name]
    obj = build()
    back = _COPIES[how](obj)
    for a in fields:
        arr = getattr(back, a)
        assert not getattr(obj, a).flags.writeable and not arr.flags.writeable, f"{how}: {a}"
        np.testing.assert_array_equal(arr, getattr(obj, a))

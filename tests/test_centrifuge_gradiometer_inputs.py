"""Centrifuge and gradiometer entry points: every memory layout and dtype gives the answer of
the C-ordered float64 call; bad options and arrays give a CalibrationError naming them;
results pickle exactly; demodulation is thread-safe and independent of the thread count."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

import accelcal as ac
import numpy as np
import pandas as pd
import pytest
from accelcal import CalibrationError
from accelcal.sim import gradiometer_session
from accelcal.sim.centrifuge import centrifuge_session
from conftest import shared_data

# The layouts' made-up gradiometer outputs exceed the sigma they pass (chi2/dof 69 and 214):
# the misfit warning is right, and beside the point of these tests.
pytestmark = pytest.mark.filterwarnings("ignore::accelcal.StartupMisfitWarning")

# ---- layouts ---------------------------------------------------------------------------------


def _layouts(a: np.ndarray) -> dict[str, Any]:
    """The same logical values in every layout a user can hand over."""
    out: dict[str, Any] = {
        "fortran": np.asfortranarray(a),
        "big-endian": a.astype(a.dtype.newbyteorder(">")),
        "list": a.tolist(),
    }
    wide = np.zeros((a.shape[0] * 2,) + a.shape[1:], dtype=a.dtype)
    wide[::2] = a
    out["strided"] = wide[::2]
    pad = np.zeros(a.shape[:1] + (a.shape[1] + 2,) if a.ndim == 2 else (a.shape[0] + 3,),
                   dtype=a.dtype)
    if a.ndim == 2:
        pad[:, 1:-1] = a
        out["sliced"] = pad[:, 1:-1]
        out["dataframe"] = pd.DataFrame(a)
    else:
        pad[1:-2] = a
        out["sliced"] = pad[1:-2]
        out["series"] = pd.Series(a)
    return out


def _same(x: Any, y: Any) -> None:
    """Every public array / number of two results is identical (bit for bit)."""
    for name in dir(x):
        if name.startswith("_"):
            continue
        vx, vy = getattr(x, name), getattr(y, name)
        if callable(vx):
            continue
        if isinstance(vx, np.ndarray):
            np.testing.assert_array_equal(vx, vy, err_msg=name)
        elif isinstance(vx, float):
            assert vx == vy or (np.isnan(vx) and np.isnan(vy)), name
        elif isinstance(vx, (int, str, bool, list, tuple)) or vx is None:
            if isinstance(vx, list) and vx and isinstance(vx[0], np.ndarray):
                continue
            assert vx == vy, name


@pytest.fixture(scope="module")
def centrifuge_rows():
    s = centrifuge_session(noise_g=1e-6, rng=3)
    return s.outputs, s.omega, s.spin_axis


def _check(call: Callable[..., Any], base_args: list[Any], which: int) -> None:
    """``call`` with argument ``which`` in every layout equals the plain call."""
    ref = call(*base_args)
    for lay in _layouts(np.asarray(base_args[which])).values():
        args = list(base_args)
        args[which] = lay
        _same(call(*args), ref)


def test_fit_centrifuge_every_layout_identical(centrifuge_rows):
    out, om, _ = centrifuge_rows

    def call(o, w):
        return ac.fit_centrifuge(o, w, 1.0, g=9.8, sigma=1e-6)

    _check(call, [out, om], 0)
    _check(call, [out, om], 1)
    # DataFrame.to_numpy() is Fortran-ordered: the case that used to say "no subset consistent".
    df = pd.DataFrame(out, columns=["x", "y", "z"])
    _same(ac.fit_centrifuge(df.to_numpy(), om, 1.0, g=9.8, sigma=1e-6), call(out, om))


def test_fit_centrifuge_float32_and_integer_outputs(centrifuge_rows):
    out, om, _ = centrifuge_rows
    # Counts of 0.01 g, as a counting device would give them (scale 100 counts per g: the
    # unit check is turned off for it), and float32 outputs in g.
    for dt, per_g, check in ((np.float32, 1.0, True), (np.int16, 100.0, False),
                             (np.int32, 100.0, False)):
        o = np.round(out * per_g).astype(dt) if per_g != 1 else out.astype(dt)
        ref = ac.fit_centrifuge(o.astype(np.float64), om, 1.0, g=9.8, check_units=check)
        assert np.all(np.isfinite(ref.params))
        for lay in _layouts(o).values():
            _same(ac.fit_centrifuge(lay, om, 1.0, g=9.8, check_units=check), ref)


def test_table_and_helpers_every_layout_identical(centrifuge_rows):
    out, om, up = centrifuge_rows
    fit = ac.fit_centrifuge(out, om, 1.0, g=9.8)
    ref = fit.correct(out)
    for name, lay in _layouts(out).items():
        np.testing.assert_array_equal(fit.correct(lay), ref, err_msg=name)
    s_ref = ac.centrifuge_sensitivity(source="radius", magnitudes=np.array([1e-3, 2e-3]))
    for lay in _layouts(np.array([1e-3, 2e-3])).values():
        _same(ac.centrifuge_sensitivity(source="radius", magnitudes=lay), s_ref)


def test_calibrate_centrifuge_table_matches_arrays():
    t = ac.read_centrifuge_table(shared_data("seed004", "table1_sign_corrected.csv"))
    a = ac.calibrate_centrifuge_table(shared_data("seed004", "table1_sign_corrected.csv"), 1.0,
                                      g=9.8)
    b = ac.fit_centrifuge(np.asfortranarray(t.outputs), t.omega, 1.0, g=9.8,
                          labels=t.labels())
    _same(a, b)


GRAD_AZ = np.array([0.0, 45.0, 90.0, 135.0, 10.0])
GRAD_Y = np.array([[3.0, 1.0], [2.5, 4.0], [-1.0, 2.0], [0.5, -3.0], [2.9, 1.7]])
GRAD_T = np.array([0.0, 60.0, 120.0, 180.0, 240.0])


def test_startup_entry_points_every_layout_identical():
    _check(lambda a: ac.startup_bias(a, GRAD_Y), [GRAD_AZ], 0)
    _check(lambda y: ac.startup_bias(GRAD_AZ, y, sigma=0.3), [GRAD_Y], 0)
    _check(lambda t: ac.startup_bias(GRAD_AZ, GRAD_Y, t=t, drift=True), [GRAD_T], 0)
    _check(lambda a: ac.predict_startup_accuracy(a, sigma=0.5, sigma_theta=0.1, gradient=30.0),
           [GRAD_AZ], 0)
    _check(lambda t: ac.predict_startup_accuracy(GRAD_AZ, t, 0.5), [GRAD_T], 0)
    for dt in (np.float32, np.int16, np.int32):
        az = GRAD_AZ.astype(dt)
        ref = ac.startup_bias(az.astype(np.float64), GRAD_Y)
        for lay in _layouts(az).values():
            _same(ac.startup_bias(lay, GRAD_Y), ref)
    np.testing.assert_array_equal(ac.plan_azimuths(np.int16(4)), ac.plan_azimuths(4))


def test_startup_calibration_record_layouts():
    rng = np.random.default_rng(0)
    chans = rng.normal(size=(500, 2))
    ref = ac.StartupCalibration()
    ref.record(0.0, chans)
    for name, lay in _layouts(chans).items():
        c = ac.StartupCalibration()
        c.record(0.0, lay)
        np.testing.assert_array_equal(c.outputs, ref.outputs, err_msg=name)


@pytest.fixture(scope="module")
def grad_stream():
    return gradiometer_session([0.0, 90.0], radius_m=0.1, spin_hz=0.5, fs=400.0, dwell_s=20.0,
                               slew_s=2.0, noise_mps2=1e-8, seed=1)


def test_demodulate_every_layout_identical(grad_stream):
    s = grad_stream

    def call(a, ph):
        return ac.demodulate(a, ph, s.bounds, radius_m=s.radius_m, t=s.t)

    ref = call(s.accel, s.phase)
    for lay in _layouts(s.accel).values():
        _same(call(lay, s.phase), ref)
    for lay in _layouts(s.phase).values():
        _same(call(s.accel, lay), ref)
    # float32 / int16 / int32 samples: the same as their float64 values
    for dt, scale in ((np.float32, 1.0), (np.int16, 1e7), (np.int32, 1e9)):
        a = np.round(s.accel * scale).astype(dt) if scale != 1 else s.accel.astype(dt)
        # Scaled counts read as m/s^2 are 1e7-1e9 times too large: the unit check (which
        # would refuse them) is off, as this tests layouts and dtypes, not units.
        r = ac.demodulate(a.astype(np.float64), s.phase, s.bounds, radius_m=s.radius_m,
                          check_units=False)
        for lay in _layouts(a).values():
            _same(ac.demodulate(lay, s.phase, s.bounds, radius_m=s.radius_m,
                                check_units=False), r)


# ---- options and arrays ------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [None, "many", float("inf"), float("nan"), 0, -3, 2.5, True])
def test_centrifuge_numeric_options_name_the_argument(centrifuge_rows, bad):
    out, om, _ = centrifuge_rows
    with pytest.raises(CalibrationError, match=r"max_draws must be an integer in \[1, 1e\+07\]"):
        ac.fit_centrifuge(out, om, 1.0, max_draws=bad)
    if bad is not None and not isinstance(bad, (str, bool)) and bad > 0 and np.isfinite(bad):
        return  # a valid positive outlier_k / radius
    for kw, word in (("outlier_k", "outlier_k"), ("radius", "radius"), ("g", "g")):
        args: dict[str, Any] = {"radius": 1.0, kw: bad}
        with pytest.raises(CalibrationError, match=rf"^{word} must be a number in \(0, inf\)"):
            ac.fit_centrifuge(out, om, **args)


def test_gradiometer_numeric_options_name_the_argument():
    for bad in (None, "x", float("inf"), -1.0):
        with pytest.raises(CalibrationError, match="sigma_theta must be a number in"):
            ac.predict_startup_accuracy(GRAD_AZ, sigma=1.0, sigma_theta=bad, gradient=10.0)
        if bad is None:
            continue  # None: estimate sigma / no radius (valid)
        with pytest.raises(CalibrationError, match="sigma must be"):
            ac.startup_bias(GRAD_AZ, GRAD_Y, sigma=bad)
        with pytest.raises(CalibrationError, match="radius_m must be"):
            ac.StartupCalibration(radius_m=bad)
    for bad in (None, "x", float("inf"), 10**9, 2.5):
        with pytest.raises(CalibrationError, match=r"m must be an integer in \[1, 100000\]"):
            ac.plan_azimuths(bad)
    with pytest.raises(CalibrationError, match="t_ref must be a number"):
        ac.startup_bias(GRAD_AZ, GRAD_Y, t=GRAD_T, drift=True, t_ref="noon")


@pytest.mark.parametrize("bad, word", [(np.array([True, False, True]), "boolean"),
                                       (np.array([0, 45, 90]) + 0j, "complex"),
                                       (np.array(["0", "45", "90"]), "text")])
def test_bad_azimuth_arrays_are_refused(bad, word):
    y = np.zeros((3, 2))
    with pytest.raises(CalibrationError, match=f"azimuth_deg must be real numbers.*{word}"):
        ac.startup_bias(bad, y)
    with pytest.raises(CalibrationError, match=f"azimuths must be real numbers.*{word}"):
        ac.predict_startup_accuracy(bad, sigma=1.0)


def test_bad_centrifuge_arrays_are_refused(centrifuge_rows):
    out, om, _ = centrifuge_rows
    with pytest.raises(CalibrationError, match="outputs must be real numbers.*complex"):
        ac.fit_centrifuge(out + 0j, om, 1.0)
    with pytest.raises(CalibrationError, match="omega must be real numbers.*boolean"):
        ac.fit_centrifuge(out, om > 10, 1.0)
    with pytest.raises(CalibrationError, match=r"sigma \(per-axis output noise, g\)"):
        ac.fit_centrifuge(out, om, 1.0, sigma=np.ones(7))
    with pytest.raises(CalibrationError, match="sigma"):
        ac.fit_centrifuge(out, om, 1.0, sigma=-1.0)


# ---- pickling ----------------------------------------------------------------------------------


def test_results_pickle_and_round_trip_exactly(centrifuge_rows, grad_stream):
    out, om, _ = centrifuge_rows
    t = ac.read_centrifuge_table(shared_data("seed004", "table1_as_printed.csv"))
    with pytest.warns(ac.CentrifugeOutlierWarning):
        screened = ac.calibrate_centrifuge_table(
            shared_data("seed004", "table1_as_printed.csv"), 1.0, g=9.8)
    with pytest.warns(ac.CentrifugeModelWarning, match="the model leaves a misfit"):
        unscreened = ac.fit_centrifuge(t.outputs, t.omega, 1.0, g=9.8, method="taylor-paper",
                                       robust=False)  # 23 lost signs kept: a misfit
    results = [
        ac.fit_centrifuge(out, om, 1.0, g=9.8, sigma=1e-6),
        screened,
        unscreened,
        ac.startup_bias(GRAD_AZ, GRAD_Y),
        ac.startup_bias([0.0, 90.0], GRAD_Y[:2]),  # NaN covariance: no redundancy
        ac.startup_bias(GRAD_AZ, GRAD_Y, t=GRAD_T, drift=True, sigma=0.2),
        ac.predict_startup_accuracy(GRAD_AZ, sigma=0.5),
        ac.demodulate(grad_stream.accel, grad_stream.phase, grad_stream.bounds,
                      radius_m=grad_stream.radius_m, t=grad_stream.t),
    ]
    for r in results:
        for proto in (2, pickle.HIGHEST_PROTOCOL):
            back = pickle.loads(pickle.dumps(r, protocol=proto))
            assert type(back) is type(r)
            _same(back, r)
            if hasattr(r, "summary"):
                assert back.summary() == r.summary()
    # Arrays of a result are read-only, like the frozen result itself.
    with pytest.raises(ValueError, match="read-only"):
        results[0].params[0] = 2.0
    with pytest.raises(AttributeError):
        results[0].params = np.zeros(9)


# ---- threads -----------------------------------------------------------------------------------


def test_demodulate_from_several_threads_gives_identical_results(grad_stream):
    s = grad_stream
    big = np.tile(s.accel, (20, 1))
    ph = np.tile(s.phase, 20)
    bounds = [[0, big.shape[0] // 2], [big.shape[0] // 2, big.shape[0]]]
    ref = ac.demodulate(big, ph, bounds, radius_m=s.radius_m)
    results: list[Any] = [None] * 6

    def work(i: int) -> None:
        results[i] = ac.demodulate(big, ph, bounds, radius_m=s.radius_m)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(6)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=120)
    for r in results:
        _same(r, ref)


_RAYON_SCRIPT = """
import numpy as np, accelcal as ac
from accelcal.sim import gradiometer_session
s = gradiometer_session([0.0, 90.0], radius_m=0.1, spin_hz=0.5, fs=400.0, dwell_s=20.0,
                        slew_s=2.0, noise_mps2=1e-8, seed=1)
big = np.tile(s.accel, (40, 1)); ph = np.tile(s.phase, 40)
d = ac.demodulate(big, ph, [[0, big.shape[0]]], radius_m=s.radius_m)
print(repr(d.inline_E.tobytes().hex()), repr(d.cross_E.tobytes().hex()),
      repr(d.std_inline_E.tobytes().hex()), repr(d.nuisance.tobytes().hex()))
"""


def test_demodulate_bit_identical_with_one_and_two_rayon_threads():
    outs = []
    for n in ("1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=n)
        r = subprocess.run([sys.executable, "-c", _RAYON_SCRIPT], env=env, capture_output=True,
                           text=True, timeout=300, check=True)
        outs.append(r.stdout)
    assert outs[0] == outs[1] and outs[0].strip()


def test_startup_calibration_refuses_bad_values_by_name():
    c = ac.StartupCalibration()
    for bad in (None, "north", float("nan")):
        with pytest.raises(CalibrationError, match="azimuth_deg must be a number"):
            c.record_mean(bad, 1.0, 2.0)
    with pytest.raises(CalibrationError, match="inline_E must be a number"):
        c.record_mean(0.0, None, 2.0)
    with pytest.raises(CalibrationError, match="std must be a number in \\(0, inf\\) E"):
        c.record_mean(0.0, 1.0, 2.0, std=-1)
    with pytest.raises(CalibrationError, match="sigma must be a number, an array, 'stream'"):
        ac.StartupCalibration(sigma="noise")
    assert len(c) == 0


# ---- property-based: any array gives a result or a clear error ---------------------------------

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

_VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, 1.0, -1.0, 1e300, -1e300, 1e-300, 6.283185307179586]),
)


@st.composite
def _arrays(draw: Any, ncols: int | None) -> np.ndarray:
    rows = draw(st.integers(0, 30))
    shape = (rows,) if ncols is None else (rows, draw(st.sampled_from([ncols, ncols, 2, 4])))
    dtype = draw(st.sampled_from([np.float64, np.float32, np.int16, np.int32, ">f8", bool,
                                  np.complex128]))
    if np.dtype(dtype).kind in "iub":
        a = draw(hnp.arrays(dtype, shape))
    else:
        with np.errstate(over="ignore"):  # 1e300 as float32 is inf: also a case to try
            a = draw(hnp.arrays(np.float64, shape, elements=_VALUES)).astype(dtype)
    if draw(st.booleans()) and a.ndim == 2:
        a = np.asfortranarray(a)
    return a


def _clear(call: Callable[[], Any], names: tuple[str, ...]) -> None:
    """A result without NaN where none was asked for, or a CalibrationError naming an input."""
    try:
        r = call()
    except CalibrationError as e:
        msg = str(e)
        assert any(n in msg for n in names) or "row" in msg or "speed" in msg or "design" in msg \
            or "dwell" in msg or "azimuth" in msg or "rotation" in msg or "parameter" in msg \
            or "units" in msg or "scale" in msg or "converge" in msg or "consistent" in msg, msg
        return
    assert r is not None


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(out=_arrays(3), om=_arrays(None))
def test_fit_centrifuge_any_array(out, om):
    def call():
        with __import__("warnings").catch_warnings():
            __import__("warnings").simplefilter("ignore", ac.CentrifugeOutlierWarning)
            f = ac.fit_centrifuge(out, om, 1.0, g=9.8, max_draws=200)
        assert np.all(np.isfinite(f.params)) and np.all(np.isfinite(f.std))
        return f

    _clear(call, ("outputs", "omega"))


@settings(max_examples=150, deadline=None)
@given(az=_arrays(None), y=_arrays(2))
def test_startup_bias_any_array(az, y):
    def call():
        r = ac.startup_bias(az, y, sigma=1.0)
        assert np.all(np.isfinite(r.params)) and np.all(np.isfinite(r.covariance))
        return r

    _clear(call, ("azimuth_deg", "outputs", "sigma"))
    _clear(lambda: ac.predict_startup_accuracy(az, sigma=1.0), ("azimuths", "sigma"))


@settings(max_examples=100, deadline=None)
@given(acc=_arrays(4), ph=_arrays(None))
def test_demodulate_any_array(acc, ph):
    def call():
        d = ac.demodulate(acc, ph, radius_m=0.1)
        assert np.all(np.isfinite(d.inline_E)) and np.all(np.isfinite(d.cross_E))
        return d

    _clear(call, ("accel", "phase", "samples"))

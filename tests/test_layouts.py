"""Every public entry point gives, for every memory layout, dtype and container of its array
arguments, exactly the result of the C-ordered float64 call.

The dwell kernels are covered in ``test_layouts_dwell.py`` and the centrifuge/gradiometer entry
points in ``test_centrifuge_gradiometer_inputs.py``; this file covers the static fit, the
batch fit, calibration files, pose design and the gap diagnosis. The data are whole numbers
within int16 range (raw counts of a simulated triad), so every dtype variant holds exactly the
same values (``tests/layouts.py``).
"""

from __future__ import annotations

import warnings
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal._triad import fibonacci_sphere
from layouts import LAYOUT_NAMES, layout_variants

G = 9.80665
# A triad in counts: ~410 counts per m/s^2, small non-orthogonality, biases of a few hundred.
TRUTH = np.array([410.0, 402.0, 415.0, 120.0, -240.0, 310.0, 3.0, -2.0, 4.0])


def _means(n: int = 24, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    K = np.array([[TRUTH[0], 0, 0], [TRUTH[6], TRUTH[1], 0], [TRUTH[7], TRUTH[8], TRUTH[2]]])
    a = G * fibonacci_sphere(n)
    m = a @ K.T + TRUTH[3:6] + rng.normal(0, 0.6, (n, 3))
    return np.round(m)  # whole counts: every dtype holds the same values


MEANS = _means()
VARIANTS = dict(layout_variants(MEANS))


def _quiet(fn: Any, *a: Any, **k: Any) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ac.WeakDesignWarning)
        return fn(*a, **k)


@pytest.fixture(scope="module")
def ref_fit() -> ac.StaticFit:
    return _quiet(ac.fit_static, MEANS, G)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_fit_static_any_layout(layout: str, ref_fit: ac.StaticFit) -> None:
    fit = _quiet(ac.fit_static, VARIANTS[layout], G)
    assert np.array_equal(fit.vector, ref_fit.vector)
    assert np.array_equal(fit.covariance, ref_fit.covariance, equal_nan=True)
    assert np.array_equal(fit.residuals, ref_fit.residuals)
    # The truth is recovered (the fit is right, not only repeatable).
    assert np.all(np.abs(fit.vector - TRUTH) < 6 * fit.std)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_fit_static_sigma_any_layout(layout: str) -> None:
    sig = np.full_like(MEANS, 1.0)
    ref = _quiet(ac.fit_static, MEANS, G, sigma=sig)
    fit = _quiet(ac.fit_static, MEANS, G, sigma=dict(layout_variants(sig))[layout])
    assert np.array_equal(fit.vector, ref.vector)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_fit_static_batch_any_layout(layout: str) -> None:
    other = _means(20, seed=7)
    ref = _quiet(ac.fit_static_batch, [MEANS, other], G)
    got = _quiet(ac.fit_static_batch, [VARIANTS[layout], dict(layout_variants(other))[layout]], G)
    assert np.array_equal(got.params, ref.params, equal_nan=True)
    assert np.array_equal(got.std, ref.std, equal_nan=True)
    # One session of the batch is the single fit.
    single = _quiet(ac.fit_static, MEANS, G)
    np.testing.assert_allclose(got.params[0], single.vector, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("layout", ["C", "F", "rows_strided", "big_endian_f8", "pandas"])
def test_fit_static_batch_padded_array_any_layout(layout: str) -> None:
    stack = np.stack([MEANS, _means(24, seed=9)])
    ref = _quiet(ac.fit_static_batch, stack, G)
    if layout == "C":
        arr: Any = stack
    elif layout == "F":
        arr = np.asfortranarray(stack)
    elif layout == "rows_strided":
        big = np.zeros((4, 24, 3))
        big[::2] = stack
        arr = big[::2]
    elif layout == "big_endian_f8":
        arr = stack.astype(">f8")
    else:
        arr = [dict(layout_variants(s))["pandas"] for s in stack]
    got = _quiet(ac.fit_static_batch, arr, G)
    assert np.array_equal(got.params, ref.params, equal_nan=True)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_triad_model_apply_any_layout(layout: str, ref_fit: ac.StaticFit) -> None:
    model = ref_fit.to_model()
    ref = model.apply(MEANS)
    got = model.apply(VARIANTS[layout])
    assert got.dtype == np.float64 and got.shape == (len(MEANS), 3)
    assert np.array_equal(got, ref)
    # Calibrated dwell means have norm g (to the fit's residual level).
    assert np.all(np.abs(np.linalg.norm(ref, axis=1) - G) < 5e-3)


@pytest.mark.parametrize("layout", ["C", "F", "float32", "int32", "big_endian_f8", "pandas"])
def test_triad_model_from_any_k_layout(layout: str, ref_fit: ac.StaticFit) -> None:
    K = np.round(ref_fit.K)
    b = np.round(ref_fit.bias)
    ref = ac.TriadModel(K, b).apply(MEANS)
    got = ac.TriadModel(dict(layout_variants(K))[layout], dict(layout_variants(b))[layout])
    assert np.array_equal(got.apply(MEANS), ref)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_predict_accuracy_any_layout(layout: str) -> None:
    tilts = np.array([[a, b] for a in (-30, -10, 10, 30) for b in (-25, 0, 25)], float)
    ref = ac.predict_accuracy(tilts, 1e-3)
    got = ac.predict_accuracy(dict(layout_variants(tilts))[layout], 1e-3)
    assert np.array_equal(got.std, ref.std)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_allan_deviation_any_layout(layout: str) -> None:
    x = np.round(np.random.default_rng(1).normal(0, 50, (600, 3)))
    tau0, ad0 = ac.allan_deviation(x, 100.0)
    tau, ad = ac.allan_deviation(dict(layout_variants(x))[layout], 100.0)
    assert np.array_equal(tau, tau0) and np.array_equal(ad, ad0)
    # White noise: ADEV at one sample is the sample std (to sampling error).
    assert np.all(np.abs(ad0[0] / 50.0 - 1) < 0.15)


@pytest.fixture(scope="module")
def ref_diag() -> Any:
    return ac.diagnose(ac.DwellSet(MEANS, np.full_like(MEANS, 1.0), np.ones(len(MEANS))), g=G,
                       loo=False)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_diagnose_any_layout(layout: str, ref_diag: Any) -> None:
    var = np.full_like(MEANS, 1.0)
    d = ac.DwellSet(VARIANTS[layout], dict(layout_variants(var))[layout], np.ones(len(MEANS)))
    rep = ac.diagnose(d, g=G, loo=False)
    assert rep.chi2 == ref_diag.chi2 and rep.best == ref_diag.best
    assert np.array_equal(rep.params, ref_diag.params)
    # Null session (white noise as reported): no effect is attributed.
    assert ref_diag.best == "none"


@pytest.mark.parametrize("layout", ["C", "F", "rows_strided", "float32", "int16",
                                    "big_endian_f8", "pandas", "array_protocol"])
def test_diagnose_centrifuge_any_layout(layout: str) -> None:
    from accelcal.sim import centrifuge_session

    s = centrifuge_session(noise_g=2e-6, rng=4)
    out = np.round(s.outputs * 500)  # whole numbers: outputs in units of 2e-3 g
    out_g = out / 500
    ref = ac.diagnose_centrifuge(out_g, s.omega, s.radius, g=s.g, spin_axis=s.spin_axis,
                                 sigma=6e-4, loo=False)
    v = dict(layout_variants(out))[layout]
    got = ac.diagnose_centrifuge(np.asarray(v, dtype=np.float64) / 500, s.omega, s.radius,
                                 g=s.g, spin_axis=s.spin_axis, sigma=6e-4, loo=False)
    om = dict(layout_variants(np.round(s.omega * 1000)))[layout]
    got2 = ac.diagnose_centrifuge(out_g, np.asarray(om, dtype=np.float64) / 1000, s.radius,
                                  g=s.g, spin_axis=s.spin_axis, sigma=6e-4, loo=False)
    assert got.chi2 == ref.chi2 and got.best == ref.best
    assert np.isfinite(got2.chi2)


@pytest.mark.parametrize("layout", LAYOUT_NAMES)
def test_diagnose_gradiometer_any_layout(layout: str) -> None:
    az = np.array([0.0, 45, 90, 135, 135, 90, 45, 0, 0, 90, 45, 135])
    rng = np.random.default_rng(2)
    th = np.radians(2 * az)
    y = np.column_stack([30 + 20 * np.cos(th) + 10 * np.sin(th),
                         -12 - 20 * np.sin(th) + 10 * np.cos(th)])
    y = np.round(y + rng.normal(0, 1, y.shape))
    t = np.arange(12) * 80.0
    ref = ac.diagnose_gradiometer(az, y, t=t, sigma=1.0, loo=False)
    got = ac.diagnose_gradiometer(dict(layout_variants(az))[layout],
                                  dict(layout_variants(y))[layout], t=t, sigma=1.0, loo=False)
    assert got.chi2 == ref.chi2 and got.best == ref.best

"""Parity: every Rust kernel against its slow NumPy/SciPy reference in ``accelcal._reference``
(or a NumPy one-liner), on the same inputs, in memory layouts the kernels read without a copy.

| Rust kernel (via the public API)      | reference                                         |
|---------------------------------------|---------------------------------------------------|
| per-dwell statistics (`dwell_stats`)  | `dwell_reference` (mean, var, half means, Allan)  |
| output resolution (`DwellSet.lsb`)    | `lsb_reference`                                   |
| output faults (`DwellSet.faults`)     | `output_faults_reference` (peak-to-peak of samples)|
| static ML fit (`fit_static`)          | `static_fit_reference` (SciPy LM, numerical Jac.) |
| static ML residuals (`StaticFit`)     | `static_ml_residuals_reference`                   |
| batch static fit (`fit_static_batch`) | `static_fit_reference`, session by session        |
| Fisher rows (`predict_accuracy`)      | finite differences of the reference residuals     |
| centrifuge fit (`fit_centrifuge`)     | `centrifuge_fit_reference` (SciPy)                |
| demodulation (`demodulate`)           | `demodulate_reference`                            |
| applying a calibration (`TriadModel`) | `apply_triad_reference` (NumPy solve)             |
| text reader (`io.read_stream`)        | `numpy.loadtxt`                                   |

Property-based versions over random shapes, dtypes and layouts live beside each module's
tests (test_dwell.py, test_layouts.py, test_properties.py); this file is the one place that
pairs each kernel with its reference.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import accelcal as ac
import numpy as np
import pytest
from accelcal import _reference as ref
from accelcal.sim import centrifuge_session, gradiometer_session, static_dwell_means

LAYOUTS = ("C", "F", "strided")


def _layout(x: np.ndarray, layout: str) -> np.ndarray:
    if layout == "F":
        return np.asfortranarray(x)
    if layout == "strided":
        big = np.zeros((x.shape[0] * 2, x.shape[1] + 2), dtype=x.dtype)
        big[::2, 1:-1] = x
        return big[::2, 1:-1]
    return np.ascontiguousarray(x)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16, np.int32])
def test_dwell_statistics(layout: str, dtype: Any) -> None:
    rng = np.random.default_rng(5)
    n = 6000
    x = rng.normal(0, 40, (n, 3)) + np.array([100.0, -2000.0, 16000.0])
    x = np.cumsum(rng.normal(0, 0.5, (n, 3)), axis=0) + x  # some 1/f-like wander
    x = x.astype(dtype) if np.dtype(dtype).kind == "f" else np.round(x).astype(dtype)
    bounds = np.array([[0, 700], [900, 2900], [3000, 3050], [3100, 6000]])
    got = ac.dwell_stats(_layout(x, layout), bounds)
    for k, (a, b) in enumerate(bounds):
        want = ref.dwell_reference(x, int(a), int(b))
        np.testing.assert_allclose(got.mean[k], want["mean"], rtol=1e-13)
        np.testing.assert_allclose(got.var[k], want["var"], rtol=1e-9)
        np.testing.assert_allclose(got.half_mean[k], want["half_mean"], rtol=1e-13)
        np.testing.assert_allclose(got.inflation[k], want["inflation"], rtol=1e-9)
    lsb = ref.lsb_reference(x)
    if lsb is None:
        assert got.lsb is None
    else:
        np.testing.assert_allclose(got.lsb, lsb, rtol=1e-12)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16, np.int32])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_output_faults(layout: str, dtype: Any, seed: int) -> None:
    rng = np.random.default_rng(seed)
    k, m = 16, 300
    lvl = rng.uniform(-3000, 3000, (k, 3))
    x = np.repeat(lvl, m, axis=0) + rng.normal(0, 4, (k * m, 3))
    x = x.astype(dtype) if np.dtype(dtype).kind == "f" else np.round(x).astype(dtype)
    # Clip some dwells at the axis extremes, freeze one, make one axis stuck, and one short
    # constant dwell.
    bounds = np.array([[i * m + 20, (i + 1) * m - 20] for i in range(k)])
    clip, part = rng.choice(k, 2, replace=False), rng.choice(k, 2, replace=False)
    for i, i2 in zip(clip, part, strict=True):
        # Dwell i saturates on axis a; dwell i2 sits 0.3 noise std inside that rail, its
        # samples beyond the rail clipped (partly saturated), unless i2 is i itself.
        a = rng.integers(3)
        rail = x[:, a].max() if rng.random() < 0.5 else x[:, a].min()
        x[bounds[i, 0]:bounds[i, 1], a] = rail
        if i2 != i:
            near = rail - np.sign(rail - x[:, a].mean()) * 1.2 + rng.normal(0, 4, m - 40)
            x[bounds[i2, 0]:bounds[i2, 1], a] = np.clip(near, x[:, a].min(), x[:, a].max())
    i = rng.integers(k)
    x[bounds[i, 0]:bounds[i, 1]] = x[bounds[i, 0]]
    i = rng.integers(k)
    x[bounds[i, 0]:bounds[i, 1], 2] = x[bounds[i, 0], 2]
    bounds[-1, 1] = bounds[-1, 0] + 25
    x[bounds[-1, 0]:bounds[-1, 1], 0] = x[bounds[-1, 0], 0]
    got = ac.dwell_stats(_layout(x, layout), bounds)
    want = ref.output_faults_reference(x, bounds, got.lsb)
    assert len(want) >= 3 and any(w[2].startswith("partly") for w in want)
    assert [(f.dwell, f.axis, f.kind) for f in got.faults()] == want


@pytest.mark.parametrize("model", ["lower", "upper", "diag"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_static_fit_and_residuals(model: str, seed: int) -> None:
    s = static_dwell_means(16, sigma=2e-3, max_tilt_deg=None, rng=seed, model=model)
    var = np.full((16, 3), 4e-6)
    fit = ac.fit_static(s.means, s.g_measured, model=model, sigma=np.sqrt(var))
    p = 6 if model == "diag" else 9
    x, cost = ref.static_fit_reference(s.means, s.g_measured, var, model,
                                       starts=(np.r_[np.ones(3), np.zeros(p - 3)],))
    # SciPy's numerical Jacobian limits its optimum to ~1e-8; compare in units of the std.
    assert np.all(np.abs(fit.vector - x) < 1e-4 * fit.std)
    e = ref.static_ml_residuals_reference(fit.vector, s.means, s.g_measured, var, model)
    np.testing.assert_allclose(fit.residuals / fit.sigma_residual, e, rtol=1e-9, atol=1e-9)
    assert fit.cost == pytest.approx(cost, rel=1e-7)


def test_batch_fit_matches_the_reference_session_by_session() -> None:
    sessions = [static_dwell_means(20, sigma=1e-3, max_tilt_deg=None, rng=s) for s in range(4)]
    means = np.stack([s.means for s in sessions])
    g = [s.g_measured for s in sessions]
    batch = ac.fit_static_batch(_layout(means.reshape(4, -1), "F").reshape(4, 20, 3), g,
                                sigma=1e-3)
    for i, s in enumerate(sessions):
        x, _ = ref.static_fit_reference(s.means, s.g_measured, np.full((20, 3), 1e-6))
        assert np.all(np.abs(batch.params[i] - x) < 1e-4 * batch.std[i])


def test_fisher_rows_against_finite_differences() -> None:
    from accelcal._triad import attitudes_to_force, k_matrix

    rng = np.random.default_rng(11)
    att = np.column_stack([rng.uniform(-180, 180, 12), rng.uniform(-70, 70, 12)])
    truth = np.array([1.01, 0.99, 1.002, 0.03, -0.02, 0.05, 1e-3, -2e-3, 5e-4])
    means = attitudes_to_force(att, 9.80665) @ k_matrix(truth).T + truth[3:6]
    var = np.full((12, 3), 1e-6)
    jac = np.empty((12, 9))
    for j in range(9):
        h = np.zeros(9)
        h[j] = 1e-7
        jac[:, j] = (ref.static_ml_residuals_reference(truth + h, means, 9.80665, var)
                     - ref.static_ml_residuals_reference(truth - h, means, 9.80665, var)) / 2e-7
    p = ac.predict_accuracy(att, 1e-3, truth=truth)
    np.testing.assert_allclose(p.std, np.sqrt(np.diag(np.linalg.inv(jac.T @ jac))), rtol=1e-5)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_centrifuge_fit(layout: str) -> None:
    s = centrifuge_session(noise_g=1e-6, rng=4)
    fit = ac.fit_centrifuge(_layout(s.outputs, layout), s.omega, s.radius, g=s.g, robust=False)
    want, res = ref.centrifuge_fit_reference(s.outputs, s.omega, s.radius, s.g, fit.params)
    np.testing.assert_allclose(fit.params, want, rtol=1e-6, atol=1e-10)
    x0 = np.r_[fit.params[:6], fit.params[6:9] * 1e4]
    np.testing.assert_allclose(np.sum(fit.residuals**2), np.sum(res(x0) ** 2), rtol=1e-6)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_demodulation(layout: str) -> None:
    s = gradiometer_session([0.0, 90.0, 200.0], fs=120.0, dwell_s=8.0, spin_hz=0.5,
                            noise_mps2=1e-7, scale_mismatch=2e-3, seed=3)
    d = ac.demodulate(_layout(s.accel, layout), s.phase, s.bounds, radius_m=s.radius_m)
    for k in range(3):
        inline, cross = ref.demodulate_reference(s.accel, s.phase, d.start[k], d.stop[k],
                                                 s.radius_m)
        assert d.inline_E[k] == pytest.approx(inline, abs=1e-9)
        assert d.cross_E[k] == pytest.approx(cross, abs=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int16])
def test_apply_calibration(layout: str, dtype: Any) -> None:
    rng = np.random.default_rng(2)
    k = np.array([[1.02, 0.0, 0.0], [3e-3, 0.98, 0.0], [-2e-3, 1e-3, 1.01]])
    b = np.array([0.1, -0.2, 0.05])
    raw = (rng.normal(0, 3000, (500, 3))).astype(dtype)
    got = ac.TriadModel(k, b).apply(_layout(raw, layout))
    np.testing.assert_allclose(got, ref.apply_triad_reference(raw, k, b), rtol=1e-12,
                               atol=1e-9)


@pytest.mark.parametrize("delim", [",", "\t", " "])
def test_text_reader(tmp_path: Path, delim: str) -> None:
    rng = np.random.default_rng(8)
    data = np.column_stack([np.arange(2000) / 100.0, rng.normal(0, 5, (2000, 3))])
    path = tmp_path / "rec.txt"
    lines = [delim.join(repr(float(v)) for v in row) for row in data]
    path.write_text(f"t{delim}ax{delim}ay{delim}az\n" + "\n".join(lines) + "\n")
    st = ac.io.read_stream(path)
    want = np.loadtxt(path, skiprows=1, delimiter=None if delim == " " else delim)
    np.testing.assert_array_equal(st.samples, want[:, 1:])
    assert st.t is not None
    np.testing.assert_array_equal(st.t, want[:, 0] - want[0, 0])
    assert st.fs == pytest.approx(100.0)

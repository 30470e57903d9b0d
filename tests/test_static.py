"""Static field calibration (seed 000): truth round trips, SciPy reference, observability,
bad input, TriadModel, local gravity, batch, pose planning, real data."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import accelcal as ac
import numpy as np
import pytest
from accelcal import CalibrationError, DegenerateDataError, WeakDesignWarning
from accelcal._triad import k_matrix as _k_matrix
from accelcal.sim.static import (
    G0,
    SEED000_TRUTH,
    attitudes_to_force,
    sphere_attitudes,
    static_dwell_means,
    uniform_attitudes,
)
from conftest import shared_data
from scipy.optimize import least_squares

UPPER_TRUTH = np.array([1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, -0.02, 0.03])


def fit_quiet(*a, **k):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", WeakDesignWarning)
        return ac.fit_static(*a, **k)


def scipy_fit(means, g, model, x0, sigma_r=None):
    """Independent reference: SciPy LM on (|K^-1 (am - b)| - g) / sigma_r."""

    def res(p):
        K = _k_matrix(p, model)
        a = np.linalg.solve(K, (means - p[3:6]).T).T
        r = np.linalg.norm(a, axis=1) - g
        return r if sigma_r is None else r / sigma_r

    return least_squares(res, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x


# ---- truth round trips ---------------------------------------------------------------------
@pytest.mark.parametrize("method", ["lm", "gauss-newton", "quadric"])
def test_noise_free_recovery_is_exact(method):
    s = static_dwell_means(20, sigma=0.0, sigma_g=0.0, max_tilt_deg=60, rng=1)
    f = fit_quiet(s.means, G0, method=method)
    np.testing.assert_allclose(f.vector, SEED000_TRUTH, atol=1e-9)
    assert f.rms < 1e-10


def test_paper_back_substitution_is_biased_on_noise_free_data():
    s = static_dwell_means(20, sigma=0.0, sigma_g=0.0, max_tilt_deg=60, rng=2)
    f = fit_quiet(s.means, G0, method="linear-paper")
    err = np.abs(f.vector - SEED000_TRUTH).max()
    assert 1e-5 < err < 1e-2  # SPEC 1: dropping M^2 terms biases it by ~1e-4


@pytest.mark.parametrize("model,truth", [("upper", UPPER_TRUTH), ("diag", UPPER_TRUTH[:6])])
def test_other_models_round_trip(model, truth):
    s = static_dwell_means(12, truth=truth, sigma=0.0, sigma_g=0.0, max_tilt_deg=None, rng=3,
                           model=model)
    f = ac.fit_static(s.means, G0, model=model)
    np.testing.assert_allclose(f.vector, truth, atol=1e-9)
    assert f.vector.size == truth.size


def test_raw_counts_are_well_conditioned():
    truth = np.array([414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0])
    s = static_dwell_means(38, truth=truth, g=9.81744, sigma=1.0, max_tilt_deg=None, rng=4)
    f = ac.fit_static(s.means, 9.81744, sigma=1.0)
    err = (f.vector - truth) / f.std
    assert np.all(np.abs(err) < 5)
    assert f.std[0] < 0.1 and f.rms < 0.01


def test_lm_equals_independent_scipy_fit():
    s = static_dwell_means(20, rng=5)
    f = fit_quiet(s.dwellset(), s.g_measured)
    sr = f.sigma_residual
    ref = scipy_fit(s.means, s.g_measured, "lower", f.start, sr)
    assert np.all(np.abs(f.vector - ref) < 1e-4 * f.std)
    # Unit weights (noise estimated) too, and for the upper model.
    f2 = fit_quiet(s.means, s.g_measured, model="upper")
    ref2 = scipy_fit(s.means, s.g_measured, "upper", f2.start)
    assert np.all(np.abs(f2.vector - ref2) < 1e-4 * f2.std)
    assert f2.noise_model.startswith("estimated")


def test_estimated_noise_scales_covariance():
    s = static_dwell_means(30, sigma=2e-3, max_tilt_deg=None, rng=6)
    f = ac.fit_static(s.means, s.g_measured)
    np.testing.assert_allclose(f.covariance, f.covariance_unscaled * f.chi2_dof)
    assert 0.3e-3 < np.sqrt(f.chi2_dof) < 4e-3
    f2 = ac.fit_static(s.means, s.g_measured, sigma=2e-3)
    assert f2.noise_known and 0.2 < f2.chi2_dof < 3
    np.testing.assert_allclose(np.diag(f2.correlation), 1.0)


# ---- observability -----------------------------------------------------------------------
def test_tilt_limited_design_warns_with_predicted_std():
    s = static_dwell_means(20, rng=7)
    with pytest.warns(WeakDesignWarning, match="bz"):
        f = ac.fit_static(s.dwellset(), s.g_measured)
    assert f.weak and 0.05 < f.std[5] < 1.0  # bz: SPEC's CRLB ~0.29 m/s^2 at +-30 deg


def test_full_sphere_is_not_weak_and_accurate():
    s = static_dwell_means(20, max_tilt_deg=None, rng=8)
    f = ac.fit_static(s.dwellset(), s.g_measured)  # no warning (filterwarnings=error)
    assert not f.weak and np.mean((f.vector - SEED000_TRUTH) ** 2) < 1e-6


@pytest.mark.parametrize("sigma", [0.0, 1e-4, 1e-3])
def test_papers_two_plane_procedure_is_reported_singular(sigma):
    sweep = np.linspace(-30, 30, 10)
    tilts = np.r_[np.c_[np.zeros(10), sweep], np.c_[sweep, np.zeros(10)]]
    s = static_dwell_means(tilts, sigma=sigma, rng=9)
    with pytest.raises(DegenerateDataError, match="cannot determine") as e:
        ac.fit_static(s.means, s.g_measured)
    assert "m1" in str(e.value) or "m2" in str(e.value)
    # With observability="warn" the (meaningless) numbers come back with a warning.
    if sigma > 0:
        with pytest.warns(WeakDesignWarning, match="cannot determine"):
            ac.fit_static(s.means, s.g_measured, observability="warn")


def test_too_few_dwells_names_the_count():
    s = static_dwell_means(7, max_tilt_deg=None, rng=10)
    with pytest.raises(DegenerateDataError, match="need at least 9"):
        ac.fit_static(s.means, G0)
    f = ac.fit_static(s.means, s.g_measured, model="diag", sigma=1e-4)
    assert f.vector.size == 6 and not f.weak


# ---- bad input ---------------------------------------------------------------------------
def test_bad_input_gives_clear_errors():
    s = static_dwell_means(20, max_tilt_deg=None, rng=11)
    m = s.means.copy()
    m[4, 1] = np.nan
    with pytest.raises(CalibrationError, match="dwell 4"):
        ac.fit_static(m, G0)
    for g in (0.0, -9.8, np.nan):
        with pytest.raises(CalibrationError, match="positive"):
            ac.fit_static(s.means, g)
    with pytest.raises(CalibrationError, match="plausible"):
        ac.fit_static(s.means, 5.0)
    with pytest.raises(CalibrationError, match="model"):
        ac.fit_static(s.means, G0, model="full")
    with pytest.raises(CalibrationError, match="method"):
        ac.fit_static(s.means, G0, method="newton")
    with pytest.raises(CalibrationError, match="start"):
        ac.fit_static(s.means, G0, start=[1, 1, 1])
    with pytest.raises(CalibrationError, match="shape"):
        ac.fit_static(s.means[:, :2], G0)
    with pytest.raises(CalibrationError, match="sigma"):
        ac.fit_static(s.means, G0, sigma=-1.0)


def test_not_an_ellipsoid():
    rng = np.random.default_rng(12)
    x, y = rng.uniform(-3, 3, (2, 20))
    hyper = np.c_[x, y, np.sqrt(x * x - y * y + 30)]  # a hyperboloid sheet
    with pytest.raises(DegenerateDataError, match="ellipsoid|cannot determine"):
        ac.fit_static(hyper, G0)


def test_gauss_newton_from_far_start_fails_clearly_lm_does_not():
    s = static_dwell_means(20, sigma=1e-2, rng=13)
    with pytest.raises(CalibrationError):  # diverges, or the design is undetermined at 1e-2
        fit_quiet(s.means, s.g_measured, method="gauss-newton", start=[2.0] * 9)
    s = static_dwell_means(20, sigma=1e-3, rng=13)
    e0 = [1, 1, 1, 0, 0, 0, 0, 0, 0]
    f = fit_quiet(s.means, s.g_measured, method="lm", start=e0)
    ref = fit_quiet(s.means, s.g_measured)
    assert f.converged and np.all(np.abs(f.vector - ref.vector) < 1e-3 * ref.std)
    # From e0 = [2]*9 the norm cost slides towards K -> infinity (every dwell mapped to one
    # vector, cost -> 0; SciPy's LM does the same): a clear error, not a confident answer.
    s0 = static_dwell_means(20, sigma=1e-3, rng=1)
    with pytest.raises(CalibrationError, match="ran away"):
        fit_quiet(s0.means, s0.g_measured, method="lm", start=[2.0] * 9)


# ---- TriadModel, local gravity, batch ------------------------------------------------------
def test_triad_model_apply_save_load(tmp_path):
    s = static_dwell_means(20, max_tilt_deg=None, rng=14)
    f = ac.fit_static(s.means, s.g_measured, sigma=1e-3)
    tm = f.to_model(sensor_id="unit-7", temperature=21.5)
    a = tm.apply(s.means)
    np.testing.assert_allclose(np.linalg.norm(a, axis=1) - s.g_measured, f.residuals, atol=1e-12)
    np.testing.assert_allclose(a, f.calibrated_means(), atol=1e-12)
    # Streaming: chunks give the same as the whole; integer dtypes are read in place.
    np.testing.assert_allclose(np.vstack([tm.apply(s.means[:7]), tm.apply(s.means[7:])]), a)
    raw = np.array([[100, -200, 3000]], dtype=np.int16)
    ref = np.linalg.solve(tm.K, raw[0].astype(float) - tm.bias)
    np.testing.assert_allclose(tm.apply(raw)[0], ref, rtol=1e-13)
    np.testing.assert_allclose(tm.apply(raw[:, ::1].astype(np.float32))[0], ref, rtol=1e-6)
    path = tmp_path / "m.json"
    tm.save(path)
    back = ac.TriadModel.load(path)
    np.testing.assert_array_equal(back.K, tm.K)
    np.testing.assert_array_equal(back.covariance, tm.covariance)
    assert back.sensor_id == "unit-7" and back.g == s.g_measured and back.temperature == 21.5
    d = json.loads(path.read_text())
    assert d["format"] == "accelcal.TriadModel" and d["version"] == 1
    d["version"] = 99
    path.write_text(json.dumps(d))
    with pytest.raises(CalibrationError, match="version"):
        ac.TriadModel.load(path)
    with pytest.raises(CalibrationError, match="singular"):
        ac.TriadModel(np.zeros((3, 3)), [0, 0, 0])


def test_local_gravity_wgs84():
    assert ac.local_gravity(0.0) == pytest.approx(9.7803253359, abs=1e-9)
    assert ac.local_gravity(90.0) == pytest.approx(9.8321849378, abs=1e-9)
    assert ac.local_gravity(-90.0) == pytest.approx(9.8321849378, abs=1e-9)
    grad = ac.local_gravity(45.0, 100.0) - ac.local_gravity(45.0, 0.0)
    assert grad / 100 == pytest.approx(-3.086e-6, rel=3e-3)
    with pytest.raises(CalibrationError):
        ac.local_gravity(95.0)


def test_batch_matches_single_fits():
    ss = [static_dwell_means(20, max_tilt_deg=45, rng=100 + i) for i in range(6)]
    means = np.stack([s.means for s in ss])
    b = ac.fit_static_batch(means, G0, sigma=1e-3)
    assert b.ok.all()
    for i, s in enumerate(ss):
        f = fit_quiet(s.means, G0, sigma=1e-3)
        np.testing.assert_allclose(b.params[i], f.vector, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(b.std[i], f.std, rtol=1e-6)
    bad = means.copy()
    bad[2, 0, 0] = np.nan
    bad[3] = bad[3, :1]  # all dwells identical
    st = ac.fit_static_batch(bad, G0).status
    assert st[2] == 3 and st[3] == 1 and st[0] == 0


def test_reported_std_is_calibrated():
    """Empirical std over simulated sessions matches the reported std and the CRLB."""
    n_ses = 300
    rng = np.random.default_rng(15)
    att = uniform_attitudes(20, 45, rng)
    truth = SEED000_TRUTH
    force = attitudes_to_force(att, G0)
    K = _k_matrix(truth, "lower")
    means = force @ K.T + truth[3:6] + rng.normal(0, 1e-3, (n_ses, 20, 3))
    b = ac.fit_static_batch(means, G0, sigma=1e-3)
    assert b.ok.all()
    emp = b.params.std(axis=0, ddof=1)
    rep = np.median(b.std, axis=0)
    crlb = ac.predict_accuracy(att, 1e-3, truth=truth).std
    np.testing.assert_allclose(emp, rep, rtol=0.15)
    np.testing.assert_allclose(rep, crlb, rtol=0.05)
    bias = np.abs(b.params.mean(axis=0) - truth) / (emp / np.sqrt(n_ses))
    assert np.all(bias < 4.5)


# ---- real data -----------------------------------------------------------------------------
def test_xsens_real_session():
    raw = np.loadtxt(shared_data("xsens-mti", "xsens_acc.txt"))[:, 1:4]
    ds = ac.detect_dwells(raw, fs=100)
    assert 30 <= len(ds) <= 45
    f = ac.fit_static(ds, 9.81744)
    assert 5e-4 < f.rms < 2e-3  # independent fit on imu_tk's intervals: 0.00098
    assert f.chi2_dof > 3  # more than white noise explains (a real sim-to-real gap)
    # Compare with imu_tk through the product: raw = K a + b with K = (T_imu K_imu)^-1.
    t_imu = np.array([[1, -0.0033593, -0.0089064], [0, 1, -0.0213341], [0, 0, 1]])
    k_imu = np.diag(1 / np.array([414.459, 412.010, 414.649]))
    b_imu = np.array([33124.2, 33275.2, 32364.4])
    a_imu = (t_imu @ k_imu @ (ds.mean - b_imu).T).T
    rms_imu = np.sqrt(np.mean((np.linalg.norm(a_imu, axis=1) - 9.81744) ** 2))
    assert f.rms <= rms_imu * 1.05
    np.testing.assert_allclose(np.abs(np.linalg.det(f.K)), 1 / abs(np.linalg.det(t_imu @ k_imu)),
                               rtol=2e-3)
    np.testing.assert_allclose(f.bias, b_imu, atol=3.0)
    up = ac.fit_static(ds, 9.81744, model="upper")
    assert up.rms == pytest.approx(f.rms, rel=1e-6)  # same ellipsoid, other triangle


def test_mpu6050_few_poses_reported_weak():
    raw = np.loadtxt(shared_data("mpu6050-10poses", "example_data_calibration.csv"), delimiter=",",
                     skiprows=5)[:, :3]
    ds = ac.detect_dwells(raw.astype(np.int32), fs=100)
    assert len(ds) <= 12
    with pytest.warns(WeakDesignWarning, match="diag"):
        f9 = ac.fit_static(ds, 9.80665)
    assert f9.weak
    f6 = ac.fit_static(ds, 9.80665, model="diag")
    assert not f6.weak and np.all(np.abs(f6.scale / 16384 * 9.80665 - 1) < 0.05)


def test_imucal_six_faces_needs_diag():
    x = np.loadtxt(shared_data("imucal", "example_ferraris_session.csv"), delimiter=",", skiprows=1)
    sec = json.loads(shared_data("imucal", "example_ferraris_session_list.json").read_text())
    b = [[v["start"], v["end"]] for k, v in sec.items() if not k.endswith("rot")]
    ds = ac.dwell_stats(x[:, 4:7], b, fs=102.4)
    with pytest.raises(DegenerateDataError, match="diag"):
        ac.fit_static(ds, 9.81)
    f = ac.fit_static(ds, 9.81, model="diag")
    assert np.all(np.abs(f.scale - 1) < 0.05) and f.rms < 1e-6


def test_saved_model_carries_the_realistic_covariance_and_input_units(tmp_path: Path) -> None:
    # Means with a scatter 4x the noise the DwellSet claims: chi2/dof ~ 16.
    rng = np.random.default_rng(12)
    truth = np.array([1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03])
    sess = static_dwell_means(sphere_attitudes(30, rng=rng), truth=truth, sigma=4e-4,
                              sigma_g=0.0, rng=rng)
    d = ac.DwellSet(sess.means, var=np.full((30, 3), 1e-6), count=np.full(30, 100), units="V")
    fit = ac.fit_static(d, sess.g_measured)
    assert 8 < fit.chi2_dof < 30
    path = tmp_path / "cal.json"
    fit.to_model(sensor_id="unit-7").save(path)
    m = ac.TriadModel.load(path)
    np.testing.assert_allclose(m.covariance, fit.covariance_scaled, rtol=1e-12)
    raw = json.loads(path.read_text())
    assert raw["units"]["input"] == "V"
    assert raw["metadata"]["covariance"] == "scaled by chi2/dof"
    assert abs(raw["metadata"]["chi2_dof"] - fit.chi2_dof) < 1e-9

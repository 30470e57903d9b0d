"""Gradiometer per-startup bias: estimator, design, demodulation, simulator, workflow."""

from __future__ import annotations

import json
import pickle
import warnings

import accelcal
import numpy as np
import pytest
from accelcal import CalibrationError, DegenerateDataError
from accelcal._reference import demodulate_reference
from accelcal.gradiometer import StartupMisfitWarning
from accelcal.sim import gradiometer_session


def model(az_deg, bias, gamma, t=None, drift=None, t_ref=0.0):
    """Measurement model y_k = b + R(2 theta_k) gamma (+ drift (t - t_ref))."""
    th = np.radians(np.asarray(az_deg, dtype=float))
    c, s = np.cos(2 * th), np.sin(2 * th)
    y = np.column_stack(
        [bias[0] + c * gamma[0] + s * gamma[1], bias[1] - s * gamma[0] + c * gamma[1]]
    )
    if drift is not None:
        y += np.outer(np.asarray(t) - t_ref, drift)
    return y


def closed_form(az_deg):
    u = np.exp(-2j * np.radians(np.asarray(az_deg, dtype=float)))
    m = u.size
    return m / (m**2 - abs(u.sum()) ** 2)


BAL = [0.0, 45.0, 90.0, 135.0]
UNBAL = [0.0, 30.0, 100.0, 150.0, 10.0]


# ---- estimator --------------------------------------------------------------------------
@pytest.mark.parametrize("az", [BAL, [0.0, 90.0], [0.0, 60.0, 120.0], UNBAL, [0.0, 20.0, 50.0]])
def test_noise_free_recovery(az):
    b, g = np.array([12.5, -7.25]), np.array([43.0, -18.0])
    r = accelcal.startup_bias(az, model(az, b, g))
    assert np.allclose(r.bias, b, atol=1e-9, rtol=0)
    assert np.allclose(r.gradient, g, atol=1e-9, rtol=0)
    assert r.drift is None and r.covariance.shape == (4, 4)
    assert np.allclose(r.residuals, 0.0, atol=1e-9)


@pytest.mark.parametrize("az", [BAL, [0.0, 90.0], UNBAL, [0.0, 20.0, 50.0], [10.0, 40.0]])
def test_bias_variance_closed_form(az):
    sigma = 0.7
    y = model(az, [1.0, 2.0], [3.0, 4.0]) + 0.01
    r = accelcal.startup_bias(az, y, sigma=sigma)
    v = closed_form(az) * sigma**2
    for j in range(4):
        assert r.covariance[j, j] == pytest.approx(v, rel=1e-10)
    p = accelcal.predict_startup_accuracy(az, sigma=sigma)
    assert p.closed_form_variance == pytest.approx(v, rel=1e-12)
    assert np.allclose(p.covariance, r.covariance, rtol=1e-10, atol=1e-14)
    if abs(np.exp(2j * np.radians(az)).sum()) < 1e-9:
        # Balanced: the bias is the plain mean.
        assert np.allclose(r.bias, y.mean(axis=0), atol=1e-12)


@pytest.mark.parametrize(
    "az, t, drift, words",
    [
        ([0.0, 180.0], None, False, "modulo 180"),
        ([30.0, 210.0, 30.0], None, False, "modulo 180"),
        ([45.0], None, False, "two azimuths"),
        ([0.0, 90.0], [0.0, 10.0], True, "at least 3"),
        ([0.0, 90.0, 0.0], [5.0, 5.0, 5.0], True, "same time"),
    ],
)
def test_singular_designs_say_why(az, t, drift, words):
    y = np.zeros((len(az), 2))
    with pytest.raises(DegenerateDataError, match=words):
        accelcal.startup_bias(az, y, t=t, drift=drift)


def test_bad_input_is_refused():
    with pytest.raises(CalibrationError, match="shape"):
        accelcal.startup_bias([0, 90], np.zeros((3, 2)))
    with pytest.raises(CalibrationError, match="NaN"):
        accelcal.startup_bias([0, 90], [[0, np.nan], [1, 2]])
    with pytest.raises(CalibrationError, match="needs the dwell times"):
        accelcal.startup_bias([0, 90, 0], np.zeros((3, 2)), drift=True)
    with pytest.raises(CalibrationError, match="sigma"):
        accelcal.startup_bias([0, 90], np.zeros((2, 2)), sigma=-1.0)
    # An azimuth of 1e17 deg (a double's step there: 16 deg) was taken: a biased answer.
    az = np.array([0.0, 45.0, 90.0, 135.0, 1e17])
    with pytest.raises(CalibrationError, match=r"\[4\] = 1e\+17 deg cannot be an azimuth"):
        accelcal.startup_bias(az, np.ones((5, 2)))
    # Unwrapped angles of many turns are fine (+-1e9 deg).
    turns = np.array([0.0, 45.0, 90.0, 135.0]) + 360.0 * 2_000_000
    y = np.c_[np.cos(np.radians(2 * turns)), np.sin(np.radians(2 * turns))]
    np.testing.assert_allclose(accelcal.startup_bias(turns, y).bias,
                               accelcal.startup_bias(turns % 360, y).bias, atol=1e-9)


def test_no_redundancy_without_sigma_gives_nan_covariance():
    r = accelcal.startup_bias([0, 90], model([0, 90], [1, 2], [3, 4]))
    assert r.dof == 0 and r.sigma is None and np.all(np.isnan(r.covariance))
    assert np.allclose(r.bias, [1, 2], atol=1e-12)


def test_abba_with_drift():
    az = [0.0, 90.0, 90.0, 0.0]
    t = np.array([30.0, 110.0, 190.0, 270.0])
    b, g, d = np.array([5.0, -3.0]), np.array([40.0, 25.0]), np.array([0.02, -0.015])
    y = model(az, b, g, t, d, t_ref=150.0)
    r = accelcal.startup_bias(az, y, t=t, drift=True, sigma=1.0)
    assert r.t_ref == pytest.approx(150.0)
    assert np.allclose(r.bias, b, atol=1e-9)
    assert np.allclose(r.gradient, g, atol=1e-9)
    assert np.allclose(r.drift, d, atol=1e-12)
    # Time-symmetric return-to-start: drift uncorrelated with bias and gradient.
    assert np.allclose(r.covariance[:4, 4:], 0.0, atol=1e-14)
    # ABBA is immune to a linear drift even without the drift model (it shows in the
    # residuals only); the non-symmetric ABAB order is not.
    r0 = accelcal.startup_bias(az, y)
    assert np.allclose(r0.params, np.r_[b, g], atol=1e-9)
    assert np.abs(r0.residuals).max() > 1.0
    abab = [0.0, 90.0, 0.0, 90.0]
    r1 = accelcal.startup_bias(abab, model(abab, b, g, t, d, t_ref=150.0))
    assert np.abs(r1.params - np.r_[b, g]).max() > 0.5


def test_unbalanced_drift_recovery():
    az = [0.0, 70.0, 130.0, 20.0, 95.0]
    t = np.array([0.0, 50.0, 100.0, 160.0, 200.0])
    b, g, d = np.array([-2.0, 9.0]), np.array([15.0, -33.0]), np.array([-0.01, 0.03])
    r = accelcal.startup_bias(az, model(az, b, g, t, d, t_ref=0.0), t=t, drift=True, t_ref=0.0)
    assert np.allclose(r.params, np.r_[b, g, d], atol=1e-9)


# Thousands of draws: p < 1e-3 happens; the misfit check is tested below.
@pytest.mark.filterwarnings("ignore::accelcal.gradiometer.StartupMisfitWarning")
def test_monte_carlo_matches_covariance():
    rng = np.random.default_rng(3)
    for az, t in [(UNBAL, None), ([0.0, 90.0, 90.0, 0.0], np.array([0.0, 60.0, 120.0, 180.0]))]:
        sigma = 0.8
        truth = model(az, [3.0, -1.0], [20.0, 10.0], t, None if t is None else [0.01, 0.0])
        est = []
        for _ in range(3000):
            y = truth + rng.normal(0.0, sigma, truth.shape)
            est.append(accelcal.startup_bias(az, y, t=t, drift=t is not None, sigma=sigma).params)
        emp = np.cov(np.array(est).T)
        pred = accelcal.predict_startup_accuracy(az, t, sigma).covariance
        assert np.allclose(np.diag(emp), np.diag(pred), rtol=0.15)


def test_residual_sigma_estimate():
    rng = np.random.default_rng(5)
    az = np.tile(BAL, 10)
    y = model(az, [1, 1], [5, 5]) + rng.normal(0, 0.5, (az.size, 2))
    r = accelcal.startup_bias(az, y)
    assert r.sigma_estimated and r.dof == 2 * az.size - 4
    assert r.sigma[0] == pytest.approx(0.5, rel=0.15)
    assert r.std[0] == pytest.approx(0.5 / np.sqrt(az.size), rel=0.15)


# ---- azimuth errors and planning ----------------------------------------------------------
def test_common_azimuth_offset_leaves_bias_unchanged():
    b, g = np.array([4.0, -6.0]), np.array([50.0, 20.0])
    y = model(np.array(UNBAL) + 3.0, b, g)
    r = accelcal.startup_bias(UNBAL, y)
    assert np.allclose(r.bias, b, atol=1e-9)
    assert np.linalg.norm(r.gradient) == pytest.approx(np.linalg.norm(g), rel=1e-12)


# ---- demodulation and simulator -------------------------------------------------------------
@pytest.mark.parametrize("frame", ["platform", "nav"])
def test_demodulation_recovers_gradient_and_rate_terms(frame):
    wx, wy = 1.2e-4, -7e-5  # rate terms of several E
    s = gradiometer_session(
        [0.0, 30.0, 90.0, 145.0],
        gradient_E=(35.0, -20.0),
        bias_E=(0.0, 0.0),
        rates_rad_s=(wx, wy),
        rates_frame=frame,
        scale_mismatch=[1e-3, -2e-3, 0.5e-3, 0.5e-3],
        tilt_mps2=(2e-3, -1e-3),
        fs=200.0,
        dwell_s=12.0,
        spin_hz=0.7,
        phase0_rad=0.4,
    )
    d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m, t=s.t)
    tr = s.truth
    # Residual rates add -(Wx^2 - Wy^2)/2 to I and -Wx Wy to C (platform-frame rates).
    pw = tr.platform_rates_rad_s
    formula = np.column_stack([-(pw[:, 0] ** 2 - pw[:, 1] ** 2) / 2, -pw[:, 0] * pw[:, 1]]) / 1e-9
    assert np.abs(formula).max() > 3.0
    want = tr.sensor_gradient_E + formula
    assert np.allclose(d.outputs, want, atol=1e-6, rtol=0)
    # The sensor-frame gradient is R(2 theta) gamma.
    assert np.allclose(tr.sensor_gradient_E, model(tr.azimuth_true_deg, [0, 0], tr.gradient_E))
    if frame == "platform":
        assert np.allclose(formula, formula[0])
    # Whole revolutions were used.
    span = (d.stop - d.start) * s.omega_rad_s / s.fs / (2 * np.pi)
    assert np.all(np.abs(span - d.revolutions) < s.omega_rad_s / s.fs)


def test_demodulation_parity_with_numpy_and_layouts():
    s = gradiometer_session(
        [0.0, 60.0, 120.0], fs=150.0, dwell_s=9.0, spin_hz=0.45, noise_mps2=2e-7,
        scale_mismatch=1e-3, tilt_mps2=(1e-3, 0.0), seed=7,
    )
    d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m)
    for k in range(3):
        i_ref, c_ref = demodulate_reference(s.accel, s.phase, d.start[k], d.stop[k], s.radius_m)
        assert d.inline_E[k] == pytest.approx(i_ref, abs=1e-9)
        assert d.cross_E[k] == pytest.approx(c_ref, abs=1e-9)
    wrapped = np.mod(s.phase, 2 * np.pi) - np.pi / 3
    dw = accelcal.demodulate(s.accel, wrapped + np.pi / 3, s.bounds, radius_m=s.radius_m)
    assert np.allclose(dw.outputs, d.outputs, atol=1e-8)
    assert np.array_equal(dw.stop, d.stop)
    fortran = np.asfortranarray(s.accel)
    df = accelcal.demodulate(fortran, s.phase, s.bounds, radius_m=s.radius_m)
    assert np.allclose(df.outputs, d.outputs, atol=1e-9)
    d32 = accelcal.demodulate(s.accel.astype(np.float32), s.phase, s.bounds, radius_m=s.radius_m)
    assert np.allclose(d32.outputs, d.outputs, atol=0.5)  # float32 rounding of 1e-7 m/s^2 noise


def test_demodulation_errors():
    s = gradiometer_session([0.0], fs=100.0, dwell_s=5.0)
    with pytest.raises(DegenerateDataError, match="revolution"):
        accelcal.demodulate(s.accel, s.phase, [[0, 100]], radius_m=0.1)
    with pytest.raises(CalibrationError, match=r"\(N, 4\)"):
        accelcal.demodulate(s.accel[:, :3], s.phase, radius_m=0.1)
    with pytest.raises(CalibrationError, match="phase"):
        accelcal.demodulate(s.accel, s.phase[:-1], radius_m=0.1)
    with pytest.raises(CalibrationError, match="radius"):
        accelcal.demodulate(s.accel, s.phase, radius_m=0.0)
    bad = s.accel.copy()
    bad[10, 2] = np.nan
    with pytest.raises(CalibrationError, match="NaN"):
        accelcal.demodulate(bad, s.phase, radius_m=0.1)


def test_end_to_end_abba_with_drift():
    s = gradiometer_session(
        [0.0, 90.0, 90.0, 0.0],
        gradient_E=(45.0, 18.0),
        bias_E=(9.0, -4.0),
        drift_E_per_s=(0.02, -0.01),
        rates_rad_s=(7e-5, 2e-5),
        scale_mismatch=1e-3,
        tilt_mps2=(1e-3, -2e-3),
        fs=200.0,
        dwell_s=20.0,
    )
    d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m, t=s.t)
    r = accelcal.startup_bias(s.azimuth_deg, d.outputs, t=d.t, drift=True)
    tr = s.truth
    assert np.allclose(r.bias, tr.bias_at(r.t_ref), atol=5e-3)
    assert np.allclose(r.gradient, tr.effective_gradient_E, atol=5e-3)
    assert np.allclose(r.drift, tr.drift_E_per_s, atol=1e-4)


def test_raw_monte_carlo_matches_predicted_std():
    rng = np.random.default_rng(21)
    az = [0.0, 45.0, 90.0, 135.0]
    est, dstd = [], []
    for _ in range(120):
        s = gradiometer_session(
            az, fs=100.0, dwell_s=10.0, spin_hz=0.5, noise_mps2=1e-7, slew_s=2.0, seed=rng,
        )
        d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m)
        est.append(accelcal.startup_bias(az, d.outputs, sigma=d.std.mean()).params)
        dstd.append(d.std.mean())
    sig = float(np.mean(dstd))
    pred = accelcal.predict_startup_accuracy(az, sigma=sig).std
    emp = np.std(np.array(est), axis=0, ddof=1)
    assert np.allclose(emp, pred, rtol=0.15)
    # Demodulation white-noise std: sqrt(2 * 4 sigma_a^2 / N) / (4 R).
    assert sig == pytest.approx(np.sqrt(8 * 1e-14 / 1000) / 0.4 / 1e-9, rel=0.05)


# ---- workflow and table ---------------------------------------------------------------------
def test_startup_calibration_workflow_streams_and_raw():
    rng = np.random.default_rng(2)
    az = accelcal.plan_azimuths(4, drift=True)
    b, g, dr = np.array([3.0, -2.0]), np.array([30.0, 12.0]), np.array([0.01, 0.0])
    cal = accelcal.StartupCalibration(drift=True)
    means, times = [], []
    for k, a in enumerate(az):
        t = 100.0 * k + np.arange(2000) * 0.01
        y = model(np.full(t.size, a), b, g, t, dr) + rng.normal(0, 1.0, (t.size, 2))
        cal.record(a, y, t=t)
        means.append(y.mean(axis=0))
        times.append(0.5 * (t[0] + t[-1]))
    r = cal.solve()
    ref = accelcal.startup_bias(az, np.array(means), t=np.array(times), drift=True)
    assert np.allclose(r.params, ref.params, atol=1e-9)
    assert np.allclose(r.bias, b + dr * r.t_ref, atol=0.2)
    rot = accelcal.StartupCalibration.frame_rotation(90.0)
    assert np.allclose(rot, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)

    s = gradiometer_session(az, fs=200.0, dwell_s=10.0, bias_E=(5.0, 1.0), noise_mps2=1e-7)
    cal2 = accelcal.StartupCalibration(radius_m=s.radius_m, sigma="stream")
    for k, (a0, a1) in enumerate(s.bounds):
        cal2.record_raw(s.azimuth_deg[k], s.accel[a0:a1], s.phase[a0:a1], t=s.t[a0:a1])
    r2 = cal2.solve()
    assert not r2.sigma_estimated
    assert np.all(np.abs(r2.bias - s.truth.bias_E) < 5 * r2.bias_std)
    # the summary says where sigma came from, and a pickle keeps it
    assert r2.sigma_source == "from the streams"
    assert "E (from the streams)" in r2.summary() and "(given)" not in r2.summary()
    assert pickle.loads(pickle.dumps(r2)).sigma_source == "from the streams"
    assert "E (given)" in accelcal.startup_bias(az, np.array(means), t=np.array(times),
                                                drift=True, sigma=1.0).summary()
    assert "(estimated from residuals)" in r.summary()

    bad = accelcal.StartupCalibration(drift=True)
    bad.record_mean(0.0, 1.0, 2.0)
    with pytest.raises(CalibrationError, match="time"):
        bad.solve()


def test_calibrate_gradiometer_table(tmp_path):
    az = [0.0, 90.0, 90.0, 0.0]
    t = np.array([0.0, 100.0, 200.0, 300.0])
    y = model(az, [2.0, 1.0], [10.0, -5.0], t, [0.01, 0.02], t_ref=150.0)
    p = tmp_path / "g.csv"
    rows = "\n".join(
        f"{a},{float(i)!r},{float(c)!r},{tt}" for a, (i, c), tt in zip(az, y, t, strict=True)
    )
    p.write_text("# start-up\nazimuth_deg,inline_E,cross_E,t_s\n" + rows + "\n")
    r = accelcal.calibrate_gradiometer_table(p)
    assert r.drift is not None
    assert np.allclose(r.bias, [2.0, 1.0], atol=1e-9)
    p2 = tmp_path / "bad.csv"
    p2.write_text("bearing,inline_E,cross_E\n0,1,2\n")
    with pytest.raises(CalibrationError, match="missing column.*azimuth_deg"):
        accelcal.calibrate_gradiometer_table(p2)
    # Other names and units: radians, mE, minutes, semicolons, any column order.
    p3 = tmp_path / "other.csv"
    rows = "\n".join(f"{tt / 60};{float(1e3 * c)!r};{float(np.radians(a))!r};{float(1e3 * i)!r}"
                     for a, (i, c), tt in zip(az, y, t, strict=True))
    p3.write_text("time [min];cross [mE];heading [rad];inline [mE]\n" + rows + "\n")
    r3 = accelcal.calibrate_gradiometer_table(p3)
    np.testing.assert_allclose(r3.bias, r.bias, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r3.drift, r.drift, rtol=1e-9, atol=1e-12)
    p4 = tmp_path / "unit.csv"
    p4.write_text("azimuth [grad],inline_E,cross_E\n0,1,2\n")
    with pytest.raises(CalibrationError, match="'azimuth \\[grad\\]'.*deg, rad"):
        accelcal.calibrate_gradiometer_table(p4)
    with pytest.raises(CalibrationError, match="cannot read"):
        accelcal.calibrate_gradiometer_table(tmp_path / "missing.csv")


def test_demo_section_runs():
    from accelcal.demo.gradiometer import demo_section

    text = demo_section(0)
    assert "bias_I" in text and "truth" in text


def test_summary_warns_when_sigma_rests_on_few_degrees_of_freedom() -> None:
    az = [0.0, 45.0, 90.0, 135.0, 0.0]
    rng = np.random.default_rng(3)
    y = np.column_stack([rng.normal(size=5), rng.normal(size=5)])
    sb = accelcal.startup_bias(az, y)
    assert sb.sigma_estimated and sb.dof == 6
    assert "uncertain by about +-29 %" in sb.summary()
    with pytest.warns(StartupMisfitWarning):  # this draw: chi2 25.4 on 6 dof (p = 3e-4)
        given = accelcal.startup_bias(az, y, sigma=1.0)
    assert "uncertain by" not in given.summary()


# Thousands of draws: p < 1e-3 happens; the misfit check is tested below.
@pytest.mark.filterwarnings("ignore::accelcal.gradiometer.StartupMisfitWarning")
def test_azimuth_error_prediction():
    rng = np.random.default_rng(11)
    az, g, st = np.array(BAL), np.array([60.0, -30.0]), 0.5
    est = []
    for _ in range(4000):
        y = model(az + rng.normal(0, st, az.size), [0, 0], g)
        est.append(accelcal.startup_bias(az, y, sigma=1.0).bias)
    emp = np.var(np.array(est), axis=0)
    p = accelcal.predict_startup_accuracy(az, sigma=1e-12, sigma_theta=st, gradient=g)
    assert np.allclose(emp, np.diag(p.azimuth_covariance)[:2], rtol=0.15)
    # Magnitude only: sigma_bias ~ sqrt(2) sigma_theta |gamma| / sqrt(m).
    pm = accelcal.predict_startup_accuracy(
        az, sigma=1e-12, sigma_theta=st, gradient=np.linalg.norm(g)
    )
    want = np.sqrt(2) * np.radians(st) * np.linalg.norm(g) / np.sqrt(az.size)
    assert pm.bias_std == pytest.approx([want, want], rel=1e-6)
    with pytest.raises(CalibrationError, match="gradient"):
        accelcal.predict_startup_accuracy(az, sigma_theta=0.1)


def test_cli_gradiometer_plot_and_option_words(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from accelcal.cli import main
    from accelcal.plots import gradiometer_figure
    from click.testing import CliRunner

    az = [0.0, 45.0, 90.0, 135.0, 0.0]
    t = [0.0, 60.0, 120.0, 180.0, 240.0]
    y = model(az, [3.0, -2.0], [10.0, 5.0], t, [0.01, -0.02], t_ref=120.0)
    y += np.array([[0.1, -0.05], [0.0, 0.08], [-0.07, 0.0], [0.02, 0.03], [-0.04, -0.06]])
    tab = tmp_path / "startup.csv"
    tab.write_text("azimuth_deg,inline_E,cross_E,t_s\n" + "\n".join(
        f"{a},{u},{v},{s}" for a, (u, v), s in zip(az, y, t, strict=True)) + "\n")
    png = tmp_path / "g.png"
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", str(tab), "--plot", str(png)])
    assert r.exit_code == 0, r.output
    assert png.stat().st_size > 10_000
    # The summary's caution names the CLI option, not the Python keyword.
    assert "sigma=" not in r.output and "--sigma" in r.output
    sb = accelcal.startup_bias(az, y, t=t, drift=True)
    fig = gradiometer_figure(sb)
    a0, a1 = fig.axes
    assert a0.get_ylabel() == "inline I  [E]" and a1.get_xlabel() == "platform azimuth  [deg]"
    # The drawn averages, drift removed, lie on the fitted curve up to the residuals.
    pts = a0.lines[0].get_ydata() if a0.lines[0].get_marker() == "o" else None
    curve = [ln for ln in a0.lines if ln.get_label().startswith("fit")][0]
    grid, cv = curve.get_xdata(), curve.get_ydata()
    assert pts is None or np.allclose(
        np.asarray(pts) - np.interp(np.mod(az, 180), grid, cv), sb.residuals[:, 0], atol=1e-3)
    plt.close(fig)
    # Errors name CLI options.
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", str(tab), "--sigma", "-1"])
    assert r.exit_code == 2 and "--sigma must" in r.output, r.output


def test_no_residual_dof_says_why_the_std_are_nan() -> None:
    from accelcal.gradiometer import startup_bias

    r = startup_bias([0.0, 60.0], [[52.2, -32.0], [-29.1, -29.2]])
    assert r.dof == 0 and not np.all(np.isfinite(r.std))
    assert "std n/a: 2 azimuths leave no residual degree of freedom" in r.summary()


# ---- units of the azimuths and the misfit against a given sigma ------------------------------
def _session(az, seed, noise_mps2=1e-9):
    """Channel averages (E) and their noise std (E) of a simulated start-up at ``az`` deg."""
    ses = gradiometer_session(az, fs=100.0, dwell_s=10.0, slew_s=2.0, noise_mps2=noise_mps2,
                              seed=seed)
    d = accelcal.demodulate(ses.accel, ses.phase, ses.bounds, radius_m=ses.radius_m)
    return ses, d.outputs, d.std.mean(axis=1)


RAD_DESIGNS = [BAL, [0.0, 90.0, 180.0, 270.0], [0.0, 120.0, 240.0], [0.0, 60.0, 120.0],
               [0.0, 90.0, 90.0, 0.0], [0.0, 90.0], [3.0, 33.0, 97.0, 151.0]]


@pytest.mark.parametrize("az", RAD_DESIGNS)
@pytest.mark.parametrize("given", [True, False])
def test_azimuths_in_radians_are_refused(az, given):
    ses, y, sd = _session(az, 5)
    with pytest.raises(CalibrationError, match=r"the azimuths look like radians.*np\.degrees"):
        accelcal.startup_bias(np.radians(az), y, sigma=sd if given else None)
    # The workflow goes through the same check.
    cal = accelcal.StartupCalibration(sigma=sd if given else None)
    for a, (i, c) in zip(np.radians(az), y, strict=True):
        cal.record_mean(a, i, c)
    with pytest.raises(CalibrationError, match="look like radians"):
        cal.solve()
    # The same data in degrees: no refusal, no misfit warning (warnings are errors here),
    # the bias within 4 std (from the given sigma: [0, 90] has no residual to estimate it).
    r = accelcal.startup_bias(az, y, sigma=sd if given else None)
    std = accelcal.startup_bias(az, y, sigma=sd).bias_std
    assert np.all(np.abs(r.bias - ses.truth.bias_E) < 4 * std)


def test_radians_refusal_figures_and_opt_out():
    # The explorer's case: 0, 45, 90, 135 deg passed as radians with sigma = 0.05 E.
    rng = np.random.default_rng(0)
    y = model(BAL, [12.0, -7.0], [40.0, -25.0]) + rng.normal(0, 0.05, (4, 2))
    with pytest.raises(CalibrationError) as e:
        accelcal.startup_bias(np.radians(BAL), y, sigma=0.05)
    msg = str(e.value)
    assert "read as radians (0, 45, 90, 135 deg) they fit the data within the given noise" in msg
    assert "where read as degrees they do not" in msg and "check_units=False" in msg
    r = accelcal.startup_bias(BAL, y, sigma=0.05)
    assert np.all(np.abs(r.bias - [12.0, -7.0]) < 4 * r.bias_std) and r.chi2_p > 1e-3
    # Without sigma: residuals compared.
    with pytest.raises(CalibrationError, match="residuals .* times smaller"):
        accelcal.startup_bias(np.radians(BAL), y)
    # check_units=False fits them as degrees, and the misfit is reported.
    with pytest.warns(StartupMisfitWarning, match="exceed the noise model.*wrong azimuths") as w:
        bad = accelcal.startup_bias(np.radians(BAL), y, sigma=0.05, check_units=False)
    assert len(w) == 1 and abs(bad.bias[0] - 12.0) > 100
    assert "note: residuals exceed the noise model" in bad.summary()
    # Radians with a sigma ten times too small: neither reading is within the noise, so the
    # fits do not refuse, but the spread does (2.58 deg as degrees, 148 deg as radians).
    az = [3.0, 33.0, 97.0, 151.0]
    y = model(az, [12.0, -7.0], [40.0, -25.0]) + rng.normal(0, 1.0, (4, 2))
    with pytest.raises(CalibrationError, match=r"look like radians.*span only 2\.58 deg"):
        accelcal.startup_bias(np.radians(az), y, sigma=0.1)
    # Radians rounded to 0.1 (round as degrees, so not refused by the spread): the misfit
    # warning says how much better the radians reading fits.
    rad = np.array([0.1, 0.6, 1.7, 2.6])
    y = model(np.degrees(rad), [12.0, -7.0], [40.0, -25.0]) + rng.normal(0, 1.0, (4, 2))
    with pytest.warns(StartupMisfitWarning, match=r"read as radians \(5\.72958, 34\.3775, "
                      r"97\.4028, 148\.969 deg\) the azimuths leave chi2/dof .* instead of "
                      r".*np\.degrees"):
        accelcal.startup_bias(rad, y, sigma=0.1)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("given", [True, False])
def test_small_degree_design_is_not_refused(seed, given):
    # 0, 1, 2, 3 deg: legal (if poorly conditioned) and all within 2 pi; the data say degrees.
    az = [0.0, 1.0, 2.0, 3.0]
    ses, y, sd = _session(az, seed)
    r = accelcal.startup_bias(az, y, sigma=sd if given else None)
    assert np.isfinite(r.condition) and np.all(np.isfinite(r.bias_std))
    assert np.all(np.abs(r.bias - ses.truth.bias_E) < 4 * r.bias_std)
    # Also a gradient-free session (nothing to tell the readings apart by): not refused.
    y0 = model(az, [12.0, -7.0], [0.0, 0.0]) + np.random.default_rng(seed).normal(0, 0.05, (4, 2))
    accelcal.startup_bias(az, y0, sigma=0.05 if given else None)


@pytest.mark.parametrize("seed", range(5))
def test_misfit_against_a_given_sigma(seed):
    az = [0.0, 45.0, 90.0, 135.0, 0.0, 90.0]
    ses, y, sd = _session(az, seed)
    # The right sigma: no warning (warnings are errors here), no note.
    ok = accelcal.startup_bias(az, y, sigma=sd)
    assert ok.chi2_p > 1e-3 and ok.misfit_text() is None
    assert "exceed" not in ok.summary()
    assert ok.to_dict()["chi2"] == pytest.approx(ok.chi2)
    # Ten times too small: a warning naming the factor and the suspects, and a summary line.
    with pytest.warns(StartupMisfitWarning) as w:
        bad = accelcal.startup_bias(az, y, sigma=sd / 10)
    msg = str(w[0].message)
    assert "residuals exceed the noise model" in msg
    assert f"they are {np.sqrt(bad.chi2 / bad.dof):.3g} times the given noise std" in msg
    assert "wrong azimuths (units, sign or zero), a wrong sigma, or a platform error" in msg
    assert np.sqrt(bad.chi2 / bad.dof) == pytest.approx(10 * np.sqrt(ok.chi2 / ok.dof))
    assert bad.chi2_p < 1e-3
    assert "  note: residuals exceed the noise model" in bad.summary()
    # Estimated sigma: nothing to test against.
    est = accelcal.startup_bias(az, y)
    assert np.isnan(est.chi2) and np.isnan(est.chi2_p) and "exceed" not in est.summary()


def test_cli_gradiometer_radians_and_misfit(tmp_path):
    from accelcal.cli import main
    from click.testing import CliRunner

    rng = np.random.default_rng(0)
    y = model(BAL, [12.0, -7.0], [40.0, -25.0]) + rng.normal(0, 0.05, (4, 2))

    def table(name, header, az):
        p = tmp_path / name
        p.write_text(f"{header},inline_E,cross_E\n" + "\n".join(
            f"{a!r},{u!r},{v!r}" for a, (u, v) in zip(az, y.tolist(), strict=True)) + "\n")
        return str(p)

    rad = table("rad.csv", "azimuth_deg", np.radians(BAL).tolist())
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", rad, "--sigma", "0.05"])
    assert r.exit_code == 2, r.output
    assert "the azimuths look like radians" in r.output and "'azimuth [rad]'" in r.output
    assert "--no-unit-check" in r.output and "np.degrees" not in r.output
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", rad])
    assert r.exit_code == 2 and "look like radians" in r.output, r.output
    # Labelled as radians, the same numbers are converted and fit.
    lab = table("lab.csv", "azimuth [rad]", np.radians(BAL).tolist())
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", lab, "--sigma", "0.05"])
    assert r.exit_code == 0 and "bias_I" in r.output and "exceed" not in r.output, r.output
    # Forced as degrees: fit, with the misfit in the summary (once: the warning is the note).
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", rad, "--sigma", "0.05",
                                  "--no-unit-check"])
    assert r.exit_code == 0, r.output
    assert r.output.count("residuals exceed the noise model") == 1
    assert "724 times the given noise std" in r.output
    # A sigma ten times too small: the note, once, naming the option.
    deg = table("deg.csv", "azimuth_deg", BAL)
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", deg, "--sigma", "0.005"])
    assert r.exit_code == 0, r.output
    assert r.output.count("residuals exceed the noise model") == 1
    assert "a wrong --sigma" in r.output
    r = CliRunner().invoke(main, ["calibrate", "gradiometer", deg, "--sigma", "0.005", "--json"])
    import json

    out = json.loads(r.output)
    assert out["chi2_p"] < 1e-3 and "exceed the noise model" in out["warnings"][0]


def test_phase_in_degrees_is_refused_and_radians_recover_the_truth() -> None:
    """The explorer's case: the phase passed in degrees gave inline ~[0.1 0.2 -0.2 1.4] E
    (truth [52 -13 -28 37]) without a word. A wrapped phase whose wraps make 360 and whose
    values exceed 2 pi, or a phase stepping more than pi per sample, is refused."""
    s = gradiometer_session([0, 45, 90, 135], noise_mps2=1e-8, fs=400.0, dwell_s=20.0, seed=1)
    truth = s.truth.channels_E
    wrapped = np.mod(s.phase, 2 * np.pi)
    for ph in (s.phase, wrapped, wrapped - np.pi):  # radians, continuous or wrapped
        d = accelcal.demodulate(s.accel, ph, s.bounds, radius_m=s.radius_m)
        assert np.all(np.abs(d.outputs - truth) < 4 * d.std), (d.outputs, truth)
    for deg in (np.degrees(wrapped), np.degrees(wrapped) - 180.0,
                np.degrees(np.mod(-s.phase, 2 * np.pi))):  # [0, 360), [-180, 180), reversed
        with pytest.raises(CalibrationError, match=r"looks like degrees, not radians.*"
                           r"wraps around.*np\.radians\(phase\).*check_units=False"):
            accelcal.demodulate(s.accel, deg, s.bounds, radius_m=s.radius_m)
    # The opt-out demodulates as told: the wrong answer the check prevents.
    bad = accelcal.demodulate(s.accel, np.degrees(wrapped), s.bounds, radius_m=s.radius_m,
                              check_units=False)
    assert np.all(np.abs(bad.inline_E - truth[:, 0]) > 10.0)
    cal = accelcal.StartupCalibration(radius_m=s.radius_m)
    a0, a1 = s.bounds[0]
    with pytest.raises(CalibrationError, match="degrees"):
        cal.record_raw(0.0, s.accel[a0:a1], np.degrees(wrapped[a0:a1]))
    assert len(cal) == 0


def test_coarse_phase_in_degrees_is_refused() -> None:
    # 40 samples a turn: 9 deg per sample, more than half a turn per sample read as radians.
    s = gradiometer_session([0, 45, 90, 135], fs=20.0, spin_hz=0.5, dwell_s=40.0,
                            slew_s=4.0, seed=3)
    d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m)
    np.testing.assert_allclose(d.outputs, s.truth.channels_E, atol=1e-6)
    with pytest.raises(CalibrationError, match=r"advances 9 per sample.*40 samples per turn"):
        accelcal.demodulate(s.accel, np.degrees(s.phase), s.bounds, radius_m=s.radius_m)


def test_sigma_of_the_wrong_shape_is_named_as_given() -> None:
    # It used to say "got (8,)" for the (4, 2) array given (flattened before the message).
    rng = np.random.default_rng(2)
    y = model(BAL, [12.0, -7.0], [40.0, -25.0]) + rng.normal(0, 0.05, (4, 2))
    with pytest.raises(CalibrationError, match=r"shape \(4,\).*got shape \(4, 2\)"):
        accelcal.startup_bias(BAL, y, sigma=np.full((4, 2), 0.05))
    # A column of one std per azimuth is still read as such, and recovers the truth.
    col = accelcal.startup_bias(BAL, y, sigma=np.full((4, 1), 0.05))
    np.testing.assert_array_equal(col.std, accelcal.startup_bias(BAL, y, sigma=0.05).std)
    assert np.all(np.abs(col.bias - [12.0, -7.0]) < 4 * col.bias_std)


# ---- input plausibility: dead / stuck / clipped channels, unit slips, correlated streams ------
def _raw_abba(seed):
    plan = np.asarray(accelcal.plan_azimuths(4, drift=True))
    ses = gradiometer_session(plan, drift_E_per_s=(0.01, -0.005), noise_mps2=1e-9, fs=200,
                              seed=seed)
    return plan, ses


def _solve_raw(plan, ses, accel, **kw):
    cal = accelcal.StartupCalibration(drift=True, sigma="stream", radius_m=ses.radius_m)
    for k, az in enumerate(plan):
        a, b = ses.bounds[k]
        cal.record_raw(az, accel[a:b], ses.phase[a:b], t=ses.t[a:b], **kw)
    r = cal.solve()
    return r, r.bias - ses.truth.bias_at(r.t_ref)


@pytest.mark.parametrize("fault", ["dead", "stuck", "clipped"])
def test_dead_stuck_or_clipped_channel_is_refused(fault):
    # The tester's case: silently 3.4 / 1.9 E (dead, stuck a2) or 0.9 E (a1 clipped at its
    # 80th percentile) off the truth, against a quoted std of 0.03 E.
    plan, ses = _raw_abba(0)
    r, err = _solve_raw(plan, ses, ses.accel)
    assert np.all(np.abs(err) < 4 * r.bias_std)  # the clean session is right
    a = ses.accel.copy()
    if fault == "dead":
        a[:, 1] = 0.0
        words = r"a2 of dwell 0 \(samples 0\.\.12000\) is all zero: a dead channel"
    elif fault == "stuck":
        a[:, 1] = a[0, 1]
        words = r"a2 of dwell 0 \(samples 0\.\.12000\) is constant at .*: a stuck channel"
    else:
        lim = np.percentile(np.abs(a[:, 0]), 80)
        a[:, 0] = np.clip(a[:, 0], -lim, lim)
        words = r"a1 of dwell 0 \(samples 0\.\.12000\): \d+ of 12000 samples .* its largest"
    with pytest.raises(CalibrationError, match=words):
        _solve_raw(plan, ses, a)
    with pytest.raises(CalibrationError, match=words):
        accelcal.demodulate(a, ses.phase, ses.bounds, radius_m=ses.radius_m)
    # check_channels=False demodulates as given: the bias is then far off the truth.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StartupMisfitWarning)
        bad, err = _solve_raw(plan, ses, a, check_channels=False)
    assert np.max(np.abs(err)) > 0.5 and np.max(np.abs(err) / bad.bias_std) > 10


def test_quantised_peak_is_not_a_rail():
    # Integer counts of a coarsely resolved sinusoid: the top level holds a few % of the
    # samples but no more than ~2.5 times its neighbour; not clipped.
    ses = gradiometer_session([0.0, 90.0], fs=200.0, dwell_s=20.0, noise_mps2=2e-10, seed=3)
    a = np.round(ses.accel / 1e-9)  # ~+-10 counts: the peaks are coarse
    d = accelcal.demodulate(a * 1e-9, ses.phase, ses.bounds, radius_m=ses.radius_m)
    assert np.allclose(d.inline_E, ses.truth.channels_E[:, 0], atol=1.0)
    # All four channels below the resolution (all zero) are not a dead channel either.
    accelcal.demodulate(np.zeros_like(a), ses.phase, ses.bounds, radius_m=ses.radius_m,
                        check_units=False)


@pytest.mark.parametrize("sigma", [None, 0.05])
def test_measured_radians_abba_drift_are_refused(sigma):
    # 0.7/90.9/90.2/0.3 deg passed as radians with ABBA + drift: accepted in 169 of 200
    # sessions before (bias 951 E against a truth of 13.5 E).
    az = np.array([0.7, 90.9, 90.2, 0.3])
    t = np.array([30.0, 110.0, 190.0, 270.0])
    y = model(az, [12.0, -7.0], [40.0, -25.0], t=t, drift=[0.01, -0.005]) + \
        np.random.default_rng(0).normal(0, 0.05, (4, 2))
    with pytest.raises(CalibrationError, match=r"look like radians.*span only 1\.58 deg.*"
                       r"read as radians \(0\.7, 90\.9, 90\.2, 0\.3 deg\) 90\.6 deg.*np\.degrees"):
        accelcal.startup_bias(np.radians(az), y, t=t, drift=True, sigma=sigma)
    r = accelcal.startup_bias(az, y, t=t, drift=True, sigma=sigma)
    truth = np.array([12.0, -7.0]) + np.array([0.01, -0.005]) * r.t_ref
    assert np.all(np.abs(r.bias - truth) < 4 * r.bias_std)
    # check_units=False fits them as degrees: the escape hatch.
    accelcal.startup_bias(np.radians(az), y, t=t, drift=True, sigma=None, check_units=False)
    # Tiny designs typed in degrees (whole multiples of 0.1 deg) are not refused.
    for tiny in ([0.0, 1.0, 2.0, 3.0], [0.3, 1.2, 2.7, 3.1]):
        accelcal.startup_bias(tiny, model(tiny, [12.0, -7.0], [40.0, -25.0]) + 0.01 *
                              np.random.default_rng(1).normal(size=(4, 2)))


def test_outputs_in_impossible_units_are_refused(tmp_path):
    y = model(BAL, [12.0, -7.0], [40.0, -25.0]) + np.random.default_rng(7).normal(0, 0.05, (4, 2))
    assert np.allclose(accelcal.startup_bias(BAL, y).bias, [12.0, -7.0], atol=0.1)
    for scale in (1e-9, 4 * 0.1 * 1e-9):  # s^-2, or m/s^2 at R = 0.1 m, given as E
        with pytest.raises(CalibrationError, match=r"look like s\^-2.*below 0\.001 E"):
            accelcal.startup_bias(BAL, y * scale, sigma=0.05)
        r = accelcal.startup_bias(BAL, y * scale, check_units=False)
        assert np.allclose(r.bias, np.array([12.0, -7.0]) * scale, atol=0.1 * scale)
    with pytest.raises(CalibrationError, match=r"far too large for E.*raw counts"):
        accelcal.startup_bias(BAL, y * 1e9)
    accelcal.startup_bias(BAL, np.zeros((4, 2)))  # all zero: not a unit slip
    # Integer counts (1 LSB = 1e-9 m/s^2) through demodulate: 5.2e10 E before.
    ses = gradiometer_session([0.0, 90.0, 90.0, 0.0], noise_mps2=1e-9, fs=200, seed=1)
    counts = np.round(ses.accel / 1e-9).astype(np.int32)
    with pytest.raises(CalibrationError,
                       match=r"far too large for E: largest \|value\| 5\.2\d?e\+10.*raw counts"):
        accelcal.demodulate(counts, ses.phase, ses.bounds, radius_m=ses.radius_m)
    d = accelcal.demodulate(counts, ses.phase, ses.bounds, radius_m=ses.radius_m,
                            check_units=False)
    assert np.allclose(d.inline_E * 1e-9, ses.truth.channels_E[:, 0], atol=1.0)
    # A radius in mm given as m: channels 1000 times too small.
    with pytest.raises(CalibrationError, match=r"radius_m 100 m .* pass radius_m=0\.1"):
        accelcal.demodulate(ses.accel, ses.phase, ses.bounds, radius_m=100.0)
    # The command line refuses (exit 2) in its own words.
    from accelcal.cli import main
    from click.testing import CliRunner

    tab = tmp_path / "sinv.csv"
    rows = "\n".join(f"{a:g},{yi:.6g},{yc:.6g}" for a, (yi, yc) in zip(BAL, y * 1e-9, strict=True))
    tab.write_text("azimuth_deg,inline_E,cross_E\n" + rows + "\n")
    res = CliRunner().invoke(main, ["calibrate", "gradiometer", str(tab)])
    assert res.exit_code == 2
    assert "look like s^-2" in res.output and "'inline [1/s^2]'" in res.output
    assert "--no-unit-check" in res.output and "check_units" not in res.output
    res = CliRunner().invoke(main, ["calibrate", "gradiometer", str(tab), "--no-unit-check"])
    assert res.exit_code == 0


def test_record_stream_sigma_allows_for_correlated_noise():
    # 1 s low-pass of white noise at 10 Hz: the white-noise standard error was 4.7 times too
    # small (rms z 4.8, coverage 33 %). Known truth: bias (12, -7).
    from scipy.signal import lfilter

    fs, n, tau = 10.0, 600, 1.0
    a = np.exp(-1 / (fs * tau))
    z = []
    for s in range(120):
        rng = np.random.default_rng(s)
        cal = accelcal.StartupCalibration(sigma="stream")
        for k, az in enumerate(BAL):
            mu = model([az], [12.0, -7.0], [40.0, -25.0])[0]
            e = lfilter([1 - a], [1, -a], rng.normal(0, 3.0, (n, 2)), axis=0)
            cal.record(az, mu + e, t=k * 80 + np.arange(n) / fs)
        r = cal.solve()
        z.append((r.bias - [12.0, -7.0]) / r.bias_std)
    rms = np.sqrt(np.mean(np.square(z)))
    assert 0.8 < rms < 1.3, rms
    # White noise: the factor stays about 1 (the plain standard error).
    rng = np.random.default_rng(0)
    c = rng.normal(0, 3.0, (600, 2))
    cal = accelcal.StartupCalibration(sigma="stream")
    for az in BAL:
        cal.record(az, model([az], [12.0, -7.0], [40.0, -25.0])[0] + c)
    assert cal.solve().sigma[0] == pytest.approx(3.0 / np.sqrt(600), rel=0.1)


# ---- azimuth errors in the stated accuracy (sigma_theta) -------------------------------------
def _coverage_sessions(n, sigma_theta, seed=20261128):
    """``n`` simulated 0/45/90/135 start-ups with a strong gradient and independent azimuth
    errors of ``sigma_theta`` deg, demodulated; per session the bias error and its stated std
    without and with the azimuth term, and whether each fit warned of a misfit."""
    rng = np.random.default_rng(seed)
    out = {"err": [], "std0": [], "std1": [], "warn0": 0, "warn1": 0}
    for _ in range(n):
        s = gradiometer_session(
            BAL, gradient_E=(150.0, -100.0), bias_E=(12.0, -7.0), fs=50.0, dwell_s=20.0,
            slew_s=2.0, noise_mps2=2e-10, azimuth_error_deg=sigma_theta, seed=rng,
        )
        d = accelcal.demodulate(s.accel, s.phase, s.bounds, radius_m=s.radius_m)
        sd = float(d.std.mean())
        with warnings.catch_warnings(record=True) as w0:
            warnings.simplefilter("always")
            r0 = accelcal.startup_bias(BAL, d.outputs, sigma=sd)
        with warnings.catch_warnings(record=True) as w1:
            warnings.simplefilter("always")
            r1 = accelcal.startup_bias(BAL, d.outputs, sigma=sd, sigma_theta=sigma_theta)
        out["warn0"] += any(issubclass(x.category, StartupMisfitWarning) for x in w0)
        out["warn1"] += any(issubclass(x.category, StartupMisfitWarning) for x in w1)
        out["err"].append(r1.bias - s.truth.effective_bias_E)
        out["std0"].append(r0.bias_std)
        out["std1"].append(r1.bias_std)
    return {k: np.array(v) if isinstance(v, list) else v for k, v in out.items()}


def test_sigma_theta_gives_the_stated_coverage_on_simulated_startups():
    """0.1 deg of independent azimuth error on a 180 E gradient (noise 0.05 E per average):
    the azimuth term dominates the bias error. With it the 1-sigma interval covers the truth
    in about 68 % of sessions; without it far less."""
    n = 300
    r = _coverage_sessions(n, 0.1)
    # Same estimate either way: only the stated std differs.
    cov1 = np.mean(np.abs(r["err"]) <= r["std1"], axis=0)
    cov0 = np.mean(np.abs(r["err"]) <= r["std0"], axis=0)
    p = 0.6827
    band = 4.0 * np.sqrt(p * (1 - p) / n)  # binomial, 4 sigma: about 0.58 .. 0.79
    assert np.all(np.abs(cov1 - p) < band), cov1
    assert np.all(cov0 < 0.35), cov0
    # The stated std agrees with the spread of the errors, the noise-only one does not.
    emp = np.std(r["err"], axis=0, ddof=1)
    assert np.allclose(np.mean(r["std1"], axis=0), emp, rtol=0.15), (r["std1"].mean(0), emp)
    assert np.all(np.mean(r["std0"], axis=0) < 0.3 * emp)
    # The misfit test allows for the azimuth errors: rare with the term, nearly always without.
    assert r["warn1"] <= 0.02 * n and r["warn0"] >= 0.8 * n, (r["warn1"], r["warn0"])


def test_sigma_theta_zero_changes_nothing():
    rng = np.random.default_rng(4)
    az, t = [0.0, 90.0, 90.0, 0.0, 45.0], np.array([0.0, 80.0, 160.0, 240.0, 320.0])
    y = model(az, [3.0, -1.0], [150.0, -60.0]) + rng.normal(0, 0.05, (5, 2))
    for kw in ({}, {"sigma": 0.05}, {"sigma": np.full(5, 0.05)}, {"t": t, "drift": True},
               {"t": t, "drift": True, "sigma": 0.05}):
        ref = accelcal.startup_bias(az, y, **kw)
        for zero in (0.0, 0, np.float32(0.0), -0.0):
            r = accelcal.startup_bias(az, y, sigma_theta=zero, **kw)
            assert r.sigma_theta == 0.0 and not np.any(r.azimuth_covariance)
            for f in ("params", "covariance", "std", "residuals", "unit_covariance", "sigma"):
                assert np.array_equal(getattr(r, f), getattr(ref, f)), f
            assert r.chi2_scale == 1.0 and r.chi2_dof == r.dof
            assert r.summary() == ref.summary()
            assert np.array_equal(r.chi2_p, ref.chi2_p, equal_nan=True)
        # Exactly the noise-only covariance, as before the term existed.
        if "sigma" in kw:
            assert np.array_equal(ref.covariance, ref.unit_covariance)
        else:
            s2 = float(np.sum(ref.residuals**2)) / ref.dof
            np.testing.assert_allclose(ref.covariance, ref.unit_covariance * s2, rtol=1e-13)
            np.testing.assert_allclose(ref.sigma, np.sqrt(s2), rtol=1e-13)
        if "sigma" in kw:
            assert ref.chi2_p == pytest.approx(
                float(accelcal._core.chi2_sf(ref.chi2, float(ref.dof))), rel=1e-15)
    assert "azimuth errors" not in ref.summary()


@pytest.mark.parametrize("bad, words", [
    (-0.1, r"sigma_theta must be a number in \[0, inf\) deg"),
    (float("nan"), r"sigma_theta must be a number in \[0, inf\) deg"),
    (float("inf"), r"sigma_theta must be a number in \[0, inf\) deg"),
    ("0.1", r"sigma_theta must be a number"),
    (True, r"sigma_theta must be a number"),
    (None, r"sigma_theta must be a number"),
    ([0.1, 0.2], r"sigma_theta must be a number"),
    (6.0, r"sigma_theta is the std of independent azimuth errors in deg; 6 deg .*above 5 deg "
          r"refused.*arcmin, arcsec or mrad given as deg"),
    (360.0, r"360 deg is not a platform's azimuth repeatability"),
])
def test_bad_sigma_theta_is_refused(bad, words):
    y = model(BAL, [1.0, 2.0], [30.0, 10.0])
    with pytest.raises(CalibrationError, match=words):
        accelcal.startup_bias(BAL, y, sigma=0.1, sigma_theta=bad)
    with pytest.raises(CalibrationError, match=words):
        accelcal.StartupCalibration(sigma_theta=bad)
    assert accelcal.startup_bias(BAL, y, sigma=0.1, sigma_theta=5.0).sigma_theta == 5.0


@pytest.mark.parametrize("az, t", [
    (BAL, None),
    (UNBAL, None),
    ([0.0, 90.0, 90.0, 0.0], [30.0, 110.0, 190.0, 270.0]),
    ([0.0, 60.0, 120.0], None),
])
def test_startup_bias_agrees_with_predict_startup_accuracy(az, t):
    """For the same design and gradient the std startup_bias states and the one
    predict_startup_accuracy predicts agree: exactly for noise-free data, to first order when
    the gradient is fitted from noisy data."""
    g, st, sd = np.array([150.0, -100.0]), 0.1, 0.05
    drift = t is not None
    y = model(az, [12.0, -7.0], g, t, [0.001, 0.0] if drift else None, t_ref=0.0)
    pred = accelcal.predict_startup_accuracy(az, t, sd, st, gradient=g, drift=drift)
    r = accelcal.startup_bias(az, y, t=t, drift=drift, sigma=sd, sigma_theta=st)
    np.testing.assert_allclose(r.covariance, pred.total_covariance, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(r.azimuth_covariance, pred.azimuth_covariance, rtol=1e-9,
                               atol=1e-15)
    np.testing.assert_allclose(r.std, pred.std, rtol=1e-9)
    assert r.sigma_theta == st
    # Noisy data and azimuth errors: the fitted gradient is off by a fraction of a percent.
    rng = np.random.default_rng(8)
    for _ in range(20):
        azn = np.asarray(az) + rng.normal(0.0, st, len(az))
        yn = model(azn, [12.0, -7.0], g, t, [0.001, 0.0] if drift else None, t_ref=0.0)
        yn = yn + rng.normal(0.0, sd, yn.shape)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", StartupMisfitWarning)
            rn = accelcal.startup_bias(az, yn, t=t, drift=drift, sigma=sd, sigma_theta=st)
        np.testing.assert_allclose(rn.bias_std, pred.bias_std, rtol=0.02)
    # For a balanced set the magnitude-only prediction gives the same bias std:
    # sqrt(2) sigma_theta |gamma| / sqrt(m) for the azimuth part.
    if az is BAL:
        pm = accelcal.predict_startup_accuracy(az, sigma=sd, sigma_theta=st,
                                               gradient=float(np.linalg.norm(g)))
        np.testing.assert_allclose(r.bias_std, pm.bias_std, rtol=1e-9)
        want = np.sqrt(2) * np.radians(st) * np.linalg.norm(g) / np.sqrt(len(az))
        np.testing.assert_allclose(np.sqrt(np.diag(r.azimuth_covariance))[:2], want, rtol=1e-9)


def test_sigma_theta_with_the_noise_estimated_is_not_counted_twice():
    """Without sigma the noise comes from the residuals, which also carry part of the azimuth
    errors; that expected share is taken out, so the noise estimate stays the noise and the
    stated bias std matches the spread."""
    rng = np.random.default_rng(12)
    az = np.tile(BAL, 3)
    st = 0.1
    # (gradient, noise): azimuth share comparable to the noise; azimuth errors dominating.
    for g, sd in ((np.array([60.0, -40.0]), 0.3), (np.array([150.0, -100.0]), 0.05)):
        s2_plain, s2_with, err, std = [], [], [], []
        for _ in range(400):
            y = model(az + rng.normal(0, st, az.size), [12.0, -7.0], g)
            y = y + rng.normal(0, sd, y.shape)
            r0 = accelcal.startup_bias(az, y)
            r1 = accelcal.startup_bias(az, y, sigma_theta=st)
            assert np.array_equal(r0.params, r1.params) and r1.sigma_estimated
            s2_plain.append(r0.sigma[0] ** 2)
            s2_with.append(r1.sigma[0] ** 2)
            err.append(r1.bias - [12.0, -7.0])
            std.append(r1.bias_std)
        if sd > 0.1:
            # Rarely floored here: the noise estimate is unbiased with the share taken out.
            assert np.mean(s2_with) == pytest.approx(sd**2, rel=0.08)
            assert np.mean(s2_plain) > 1.15 * sd**2
        else:
            # The residuals are mostly azimuth error: without the share taken out the noise
            # would be counted again on top of the azimuth term.
            assert np.mean(s2_plain) > 10 * sd**2
            assert np.mean(s2_with) < 0.25 * np.mean(s2_plain)
        emp = np.std(np.array(err), axis=0, ddof=1)
        assert np.allclose(np.sqrt(np.mean(np.array(std) ** 2, axis=0)), emp, rtol=0.15)


def test_sigma_theta_in_the_summary_workflow_pickle_and_cli(tmp_path):
    from accelcal.cli import main
    from click.testing import CliRunner

    az = [0.0, 45.0, 90.0, 135.0, 0.0]
    y = model(az, [3.0, -2.0], [150.0, -100.0])
    y += np.array([[0.1, -0.05], [0.0, 0.08], [-0.07, 0.0], [0.02, 0.03], [-0.04, -0.06]])
    r = accelcal.startup_bias(az, y, sigma=0.05, sigma_theta=0.1)
    az_sd = np.sqrt(np.diag(r.azimuth_covariance))[:2]
    assert (f"azimuth errors: 0.1 deg (independent), at the fitted gradient {az_sd[0]:.3g}, "
            f"{az_sd[1]:.3g} E of the bias std") in r.summary()
    d = r.to_dict()
    assert d["sigma_theta_deg"] == 0.1 and np.allclose(d["azimuth_covariance"],
                                                       r.azimuth_covariance)
    back = pickle.loads(pickle.dumps(r))
    assert type(back) is type(r) and back.sigma_theta == 0.1
    for f in ("covariance", "azimuth_covariance", "std"):
        assert np.array_equal(getattr(back, f), getattr(r, f))
    assert (back.chi2_scale, back.chi2_dof) == (r.chi2_scale, r.chi2_dof)
    # The workflow passes it on.
    cal = accelcal.StartupCalibration(sigma=0.05, sigma_theta=0.1)
    for a, (i, c) in zip(az, y, strict=True):
        cal.record_mean(a, i, c)
    np.testing.assert_array_equal(cal.solve().covariance, r.covariance)
    # A misfit beyond what noise and azimuth errors allow names both.
    with pytest.warns(StartupMisfitWarning, match="a wrong sigma or sigma_theta"):
        accelcal.startup_bias(az, y, sigma=0.005, sigma_theta=0.001)
    # The command line: --sigma-theta in deg.
    tab = tmp_path / "startup.csv"
    tab.write_text("azimuth_deg,inline_E,cross_E\n" + "\n".join(
        f"{a},{float(u)!r},{float(v)!r}" for a, (u, v) in zip(az, y, strict=True)) + "\n")
    run = CliRunner().invoke
    out = run(main, ["calibrate", "gradiometer", str(tab), "--sigma", "0.05",
                     "--sigma-theta", "0.1", "--json"])
    assert out.exit_code == 0, out.output
    js = json.loads(out.output)
    np.testing.assert_allclose(js["std"], r.std, rtol=1e-12)
    assert js["sigma_theta_deg"] == 0.1 and js["warnings"] == []
    out = run(main, ["calibrate", "gradiometer", str(tab), "--sigma", "0.05",
                     "--sigma-theta", "0.1"])
    assert out.exit_code == 0 and "azimuth errors: 0.1 deg" in out.output, out.output
    plain = run(main, ["calibrate", "gradiometer", str(tab), "--sigma", "0.05", "--json"])
    assert json.loads(plain.output)["std"][0] < 0.5 * js["std"][0]
    for bad, words in (("6", "--sigma-theta is the std of independent azimuth errors in deg"),
                       ("-1", "--sigma-theta must be a number in [0, inf) deg")):
        out = run(main, ["calibrate", "gradiometer", str(tab), "--sigma-theta", bad])
        assert out.exit_code == 2 and words in out.output, out.output
        assert "sigma_theta" not in out.output

"""Experiment design: Cramer-Rao predictions and pose plans (static), azimuth sequences and
their predicted accuracy (gradiometer), error-source sensitivity (centrifuge)."""

from __future__ import annotations

import accelcal
import accelcal as ac
import accelcal.sim
import numpy as np
import pytest
from accelcal import CalibrationError, DegenerateDataError
from accelcal.design import centrifuge_sensitivity
from accelcal.sim.centrifuge import paper_design
from accelcal.sim.static import (
    SEED000_TRUTH,
    sphere_attitudes,
    uniform_attitudes,
)


# ---- pose planning -----------------------------------------------------------------------
def test_predict_accuracy_matches_spec_orders():
    rng = np.random.default_rng(16)
    bz = [
        ac.predict_accuracy(uniform_attitudes(20, 30, rng), 1e-3, truth=SEED000_TRUTH).std[5]
        for _ in range(30)
    ]
    assert 0.1 < np.median(bz) < 0.6  # SPEC 1: CRLB std of bz = 0.29 at +-30 deg
    sph = ac.predict_accuracy(sphere_attitudes(20, rng), 1e-3, truth=SEED000_TRUTH).std[5]
    assert sph < 3e-3 and sph < np.median(bz) / 50
    sweep = np.linspace(-30, 30, 10)
    two_plane = np.r_[np.c_[np.zeros(10), sweep], np.c_[sweep, np.zeros(10)]]
    p = ac.predict_accuracy(two_plane, 1e-3)
    assert p.singular and ("m1" in p.combination or "m2" in p.combination)


def test_plan_poses_beats_random_designs():
    plan = ac.plan_poses(20, 30, sigma=1e-3, rng=0)
    assert plan.tilts_deg is not None and plan.tilts_deg.shape == (20, 2)
    assert np.all(np.abs(plan.tilts_deg) <= 30 + 1e-9)
    rng = np.random.default_rng(17)
    rand = [ac.predict_accuracy(uniform_attitudes(20, 30, rng), 1e-3).std for _ in range(30)]
    assert plan.std[5] < np.min([r[5] for r in rand])
    assert np.prod(plan.std) < np.min([np.prod(r) for r in rand])
    sphere = ac.plan_poses(20, None, sigma=1e-3)
    assert sphere.std.max() < plan.std.max() / 20


def test_prediction_matches_a_numpy_fisher_information():
    """The Rust Jacobian rows against finite differences of the reference ML residuals."""
    from accelcal._reference import static_ml_residuals_reference
    from accelcal._triad import attitudes_to_force, k_matrix

    att = uniform_attitudes(20, 45, np.random.default_rng(3))
    force = attitudes_to_force(att, 9.80665)
    truth = SEED000_TRUTH
    means = force @ k_matrix(truth).T + truth[3:6]
    var = np.full((20, 3), 1e-6)
    J = np.empty((20, 9))
    for j in range(9):
        h = np.zeros(9)
        h[j] = 1e-7
        J[:, j] = (static_ml_residuals_reference(truth + h, means, 9.80665, var)
                   - static_ml_residuals_reference(truth - h, means, 9.80665, var)) / 2e-7
    cov = np.linalg.inv(J.T @ J)
    p = ac.predict_accuracy(att, 1e-3, truth=truth)
    np.testing.assert_allclose(p.covariance, cov, rtol=1e-4, atol=1e-6 * np.abs(cov).max())
    np.testing.assert_allclose(p.std, np.sqrt(np.diag(cov)), rtol=1e-5)


@pytest.mark.parametrize("kwargs,words", [
    ({"sigma_g": -1e-5}, "sigma_g must be a non-negative, finite"),
    ({"sigma_g": float("nan")}, "sigma_g must be a non-negative, finite"),
    ({"sigma_g": 0.5}, r"sigma_g = 0\.5 is more than 1 % of g .*\(m/s\^2"),
    ({"attitudes": np.zeros((0, 2))}, "attitudes"),
    ({"g": float("nan")}, "g must be"),
    ({"g": "9.8"}, "g must be"),
    ({"g": -1.0}, "g must be"),
    ({"sigma": 0.0}, "sigma must be"),
    ({"sigma": None}, "sigma must be"),
    ({"sigma": float("inf")}, "sigma must be"),
    ({"model": "full"}, "model"),
    ({"attitudes": [[0.0, float("nan")]] * 12}, "NaN"),
])
def test_predict_accuracy_bad_input_names_the_argument(kwargs, words):
    args = {"attitudes": uniform_attitudes(20, 30, 1), "sigma": 1e-3}
    args.update(kwargs)
    with pytest.raises(CalibrationError, match=words):
        ac.predict_accuracy(args.pop("attitudes"), args.pop("sigma"), **args)


def test_predict_accuracy_adds_the_reference_gravity_term():
    """sigma_g adds sigma_g^2 j j^T (j = -p / g for K's entries, 0 for the biases) to the
    bound, which the fit then reports for the same design; the singularity report is the
    poses' alone."""
    att = sphere_attitudes(24, np.random.default_rng(3))
    g, sg = 9.80665, 3e-5
    p0 = ac.predict_accuracy(att, 1e-5, truth=SEED000_TRUTH)
    p = ac.predict_accuracy(att, 1e-5, truth=SEED000_TRUTH, sigma_g=sg)
    j = -SEED000_TRUTH / g
    j[3:6] = 0.0
    np.testing.assert_allclose(p.covariance, p0.covariance + sg**2 * np.outer(j, j),
                               rtol=1e-12, atol=1e-30)
    assert np.all(p.std[:3] > 2 * p0.std[:3])
    np.testing.assert_array_equal(p.std[3:6], p0.std[3:6])
    assert (p.singular, p.condition, p.combination) == (p0.singular, p0.condition,
                                                        p0.combination)
    assert p.sigma_g == sg and ac.predict_accuracy(att, 1e-5).sigma_g is None
    import pickle
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(p)).std, p.std)
    s = accelcal.sim.static_dwell_means(att, sigma=1e-5, sigma_g=0.0, rng=4)
    f = ac.fit_static(s.means, g, sigma=1e-5, sigma_g=sg)
    np.testing.assert_allclose(f.std, p.std, rtol=0.05)
    # Too few poses: still infinite (the term does not make a singular design determined).
    assert np.all(np.isinf(ac.predict_accuracy(att[:5], 1e-5, sigma_g=sg).std))


@pytest.mark.parametrize("kwargs,words", [
    ({"n": None}, "n must be"),
    ({"n": "20"}, "n must be"),
    ({"n": float("inf")}, "n must be"),
    ({"n": 2.5}, "n must be"),
    ({"n": -3}, "n must be"),
    ({"max_tilt_deg": 0.0}, "max_tilt_deg must be"),
    ({"max_tilt_deg": 120.0}, "max_tilt_deg must be"),
    ({"max_tilt_deg": float("nan")}, "max_tilt_deg must be"),
    ({"max_tilt_deg": "30"}, "max_tilt_deg must be"),
    ({"sigma": -1.0}, "sigma must be"),
    ({"restarts": 0}, "restarts must be"),
    ({"grid_step_deg": 0.0}, "grid_step_deg must be"),
])
def test_plan_poses_bad_options_name_argument_value_and_range(kwargs, words):
    args = {"n": 12, "max_tilt_deg": 30.0}
    args.update(kwargs)
    with pytest.raises(CalibrationError, match=words) as e:
        ac.plan_poses(args.pop("n"), args.pop("max_tilt_deg"), **args)
    assert "[" in str(e.value) or "(" in str(e.value)  # the valid range
    with pytest.raises(DegenerateDataError, match="n = 5"):
        ac.plan_poses(5, 30)


def test_poses_are_named_as_a_person_places_them():
    from accelcal.design import pose_name

    assert pose_name([0, 0, 1]) == "bottom down, level"
    assert pose_name([0, 0, -1]) == "top down, level"
    assert pose_name([0, 1, 0]) == "right side down, level"
    assert pose_name([-1, 0, 0]) == "nose down, level"
    s30 = np.sin(np.radians(30))
    c30 = np.cos(np.radians(30))
    assert pose_name([s30, 0, c30]) == "bottom down, nose up 30 deg"
    assert pose_name([s30, -c30, 0]) == "left side down, nose up 30 deg"
    plan = ac.plan_poses(12, 30, rng=1)
    lines = plan.checklist().splitlines()
    assert len(lines) == 13 and lines[1].startswith("[ ]  1. bottom down")
    assert "platform tilt x" in lines[1]
    # The named tilt is the platform's: nose up when ty < 0 (the force has -g sin ty on x).
    for (tx, ty), nm in zip(plan.tilts_deg, plan.pose_names(), strict=True):
        if abs(tx) < 0.5 and ty < -1:
            assert f"nose up {abs(ty):.0f} deg" in nm
    sphere = ac.plan_poses(12, None, rng=1)
    assert "platform" not in sphere.checklist()


def test_balanced_set_variances():
    for az, v in [([0, 90], 0.5), ([0, 60, 120], 1 / 3), ([0, 45, 90, 135], 0.25)]:
        p = accelcal.predict_startup_accuracy(az, sigma=1.0)
        assert p.bias_std ** 2 == pytest.approx([v, v], rel=1e-12)


@pytest.mark.parametrize("m", [2, 3, 4, 5, 8])
def test_plan_balanced(m):
    az = accelcal.plan_azimuths(m)
    assert abs(np.exp(2j * np.radians(az)).sum()) < 1e-12
    p = accelcal.predict_startup_accuracy(az, sigma=1.0)
    assert p.bias_std ** 2 == pytest.approx([1 / m, 1 / m], rel=1e-10)


@pytest.mark.parametrize("m", [3, 4, 5, 6, 7, 9])
def test_plan_with_drift(m):
    az = accelcal.plan_azimuths(m, drift=True)
    assert az.size == m and np.allclose(az, az[::-1])  # time-symmetric, returns to start
    t = np.arange(m) * 100.0
    p = accelcal.predict_startup_accuracy(az, t, 1.0)
    assert np.allclose(p.covariance[:4, 4:], 0.0, atol=1e-12)
    want = 3 / 8 if m == 3 else 1 / m
    assert p.bias_std ** 2 == pytest.approx([want, want], rel=1e-9)


def test_plan_refuses_impossible():
    with pytest.raises(DegenerateDataError):
        accelcal.plan_azimuths(1)
    with pytest.raises(DegenerateDataError):
        accelcal.plan_azimuths(2, drift=True)


# The centrifuge paper's simulation truth: scale and K2 (g/g^2) per axis.
S = np.array([1.29, 1.21, 1.26])
D = np.array([0.57e-4, 0.31e-4, 0.45e-4])


def test_sensitivity_along_axis_lever_arm_is_not_negligible():
    # SPEC 2: 2 cm along the x accelerometer's own axis -> |dbx| ~ 0.285 g, |dDx| ~ 4.2e-4.
    sens = centrifuge_sensitivity(paper_design(), None, "lever_along_x", [0.02, -0.02])
    dbx = sens.shifts[:, 3]
    ddx = sens.shifts[:, 6]
    assert np.all((np.abs(dbx) > 0.28) & (np.abs(dbx) < 0.295))
    assert np.all((np.abs(ddx) > 4.0e-4) & (np.abs(ddx) < 4.3e-4))
    assert abs(ddx[0]) > 7 * D[0]
    # Across-axis offsets are small (the paper's Table 3 regime); along y exactly zero here.
    across = centrifuge_sensitivity(None, None, "lever_x_y", [0.02])
    assert np.all(np.abs(across.shifts) < 1e-9)
    # nls sees the same error (different split between bias and K2)
    nls = centrifuge_sensitivity(None, None, "lever_along_x", [0.02], method="nls")
    assert abs(nls.shifts[0, 3]) > 0.1


def test_sensitivity_misalignment_and_radius():
    mags = np.array([2e-4, 4e-4, 6e-4, 8e-4, 1e-3])
    sens = centrifuge_sensitivity(None, None, "misalignment", mags)
    # first-order: shifts grow linearly and stay small (< 1e-3 relative on S)
    ratio = sens.shifts[-1, :3] / sens.shifts[0, :3]
    np.testing.assert_allclose(ratio, 5.0, rtol=0.05)
    assert np.all(np.abs(sens.shifts[:, :3]) < 1e-3 * S)
    rad = centrifuge_sensitivity(None, None, "radius", [1e-3])
    # dA/A = dR/R: scale factors absorb it (dS/S = 1e-3), biases do not move
    np.testing.assert_allclose(rad.shifts[0, :3] / S, 1e-3, rtol=0.01)
    assert np.all(np.abs(rad.shifts[0, 3:6]) < 1e-6)
    with pytest.raises(CalibrationError, match="unknown error source"):
        centrifuge_sensitivity(None, None, "wind", [1.0])


def test_plan_poses_says_when_its_best_cannot_determine_the_model():
    """Tilts within +-1 or 2 deg: the plan came back with sz at a predicted std of 5e3 and
    347 relative, no word (and fit_static on such data returned a far-off calibration with a
    warning only). Now a WeakDesignWarning says the plan cannot determine the model."""
    import warnings

    from accelcal import WeakDesignWarning

    for mt in (1.0, 2.0):
        with pytest.warns(WeakDesignWarning, match="cannot determine model 'lower'.*sz"):
            ac.plan_poses(20, mt)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ac.plan_poses(20, 30.0)


def test_plan_poses_grid_reaches_the_limit_and_large_plans_are_not_cut_short():
    """A grid step that did not divide 2 max_tilt dropped the +max edge (step 16 at +-30:
    tilts only up to +18, bz std 0.158 against 0.056); 200 exchanges from a random draw of
    hundreds of poses stopped below the n = 20 plan repeated (n = 500: log det 0.51 lower)."""
    p16 = ac.plan_poses(20, 30.0, grid_step_deg=16.0)
    p30 = ac.plan_poses(20, 30.0, grid_step_deg=30.0)
    assert p16.tilts_deg is not None and np.abs(p16.tilts_deg).max() == 30.0
    assert p16.logdet >= p30.logdet - 1e-9
    assert p16.prediction.std[5] < 0.07
    base = ac.plan_poses(20, 30.0)
    big = ac.plan_poses(300, 30.0)
    assert big.logdet >= base.logdet + 9 * np.log(300 / 20) - 1e-6

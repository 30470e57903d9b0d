"""Sim-to-real gap diagnosis: checked against the withheld-effect generator's truth."""

from __future__ import annotations

import json
import math
from typing import Any

import accelcal
import numpy as np
import pytest
from accelcal import CalibrationError, DegenerateDataError, DwellSet, diagnose
from accelcal.gap import allan_deviation, noise_inflation
from accelcal.sim import gap_session


def test_null_sessions_rarely_alarm() -> None:
    # 100 quick null sessions at alpha = 0.05: binomial(100, 0.05) exceeds 12 with p < 0.001.
    alarms = 0
    chi2 = []
    for seed in range(100):
        s = gap_session((), rng=seed, n_dwells=24)
        r = diagnose(s.dwells, g=s.g, loo=False)
        alarms += r.best != "none"
        chi2.append(r.chi2_per_dof)
    assert alarms <= 12
    # The noise model is right: chi2/dof averages 1 (std of the mean ~ 0.036).
    assert abs(float(np.mean(chi2)) - 1.0) < 0.15


@pytest.mark.parametrize("effect", ["drift", "temperature_scale", "k2", "settling"])
def test_strong_effect_is_attributed_and_gap_closes(effect: str) -> None:
    s = gap_session((effect,), rng=8, amplitudes=[30.0])
    assert s.lam > 100
    r = diagnose(s.dwells, g=s.g)
    assert r.best == effect
    # The structure line says it reads what the selected effects leave.
    assert f"\nStructure (of what remains after {', '.join(r.selected)}): " in r.summary()
    assert r.held_out_gap > 3.0
    assert 0.7 < r.held_out_gap_after < 1.3
    assert r.shrink < 0.4
    est = next(e for e in r.effects if e["effect"] == effect)
    truth = s.effects[effect]
    # Estimates within 5 standard deviations of the hidden truth, per axis.
    assert np.all(np.abs(est["estimate"] - truth) < 5 * est["std"] + 0.05 * np.abs(truth))
    assert r.rms_after_mps2 < r.rms_before_mps2


def test_report_text_dict_and_plot() -> None:
    s = gap_session(("drift",), rng=3, amplitudes=[20.0])
    r = diagnose(s.dwells, g=s.g)
    txt = r.summary()
    assert "best = drift" in txt and "Blind spot: wrong_g" in txt
    d = r.to_dict()
    json.dumps(d, default=float)
    assert d["best"] == "drift" and len(d["dwells"]["e"]) == 24
    import matplotlib

    matplotlib.use("Agg")
    fig = r.plot()
    assert len(fig.axes) == 4  # time, temperature, pose angle, noise
    assert "after + drift" in fig.axes[0].get_legend_handles_labels()[1]


def test_blind_spots_without_temperature_and_on_faces() -> None:
    s = gap_session(("temperature_scale",), rng=2, amplitudes=[20.0], temperature=False)
    r = diagnose(s.dwells, g=s.g, loo=False)
    names = {b["effect"]: b["reason"] for b in r.blind_spots}
    assert "not testable" in names["temperature_bias"]
    assert "not testable" in names["temperature_scale"]
    assert all(e["status"] != "testable" for e in r.effects if e["effect"].startswith("temp"))
    # Hand-placed faces: K3 is absorbed by the scale factors.
    s = gap_session(("k3",), rng=2, amplitudes=[20.0], poses="faces", n_dwells=30)
    r = diagnose(s.dwells, g=s.g, loo=False)
    assert "k3" in {b["effect"] for b in r.blind_spots}
    assert r.best != "k3"


def test_constant_temperature_is_not_testable() -> None:
    s = gap_session((), rng=4)
    d = s.dwells
    d2 = DwellSet(d.mean, d.var, d.count, d.t, np.full(len(d), 21.0))
    r = diagnose(d2, g=s.g, loo=False)
    reasons = " ".join(b["reason"] for b in r.blind_spots)
    assert "temperature constant" in reasons


def test_bad_inputs() -> None:
    s = gap_session((), rng=5)
    with pytest.raises(DegenerateDataError, match="at least 10 dwells"):
        diagnose(s.dwells[:8], g=s.g)
    with pytest.raises(CalibrationError, match="unknown effect"):
        diagnose(s.dwells, g=s.g, effects=["magic"])
    with pytest.raises(CalibrationError, match=r"g must be a number in \(0, inf\)"):
        diagnose(s.dwells, g=-1.0)
    # Few dwells: a gap figure but no effect test.
    r = diagnose(s.dwells[:11], g=s.g)
    assert any("too few dwells" in x for x in r.statements)
    assert r.best == "none"
    # No variance: sigma-free F tests only, stated.
    d = s.dwells
    r = diagnose(DwellSet(d.mean, t=d.t, temperature=d.temperature), g=s.g, loo=False)
    assert math.isnan(r.p_value) and "not testable" in r.noise_model


@pytest.mark.parametrize("preset, most", [("conservative", 6), ("targeted", 9)])
def test_mis_scaled_noise_flags_gap_not_an_effect(preset: str, most: int) -> None:
    # Noise twice what the DwellSet reports, no effect: the gap is visible; an effect is
    # (wrongly) attributed in a minority of sessions, more often with the targeted preset
    # (the trade-off documented in docs/gap-validation.md).
    alarms = 0
    for seed in range(30):
        s = gap_session((), rng=100 + seed, noise_scale=2.0)
        r = diagnose(s.dwells, g=s.g, loo=False, preset=preset)
        alarms += r.best != "none"
        assert r.chi2_per_dof > 1.5 or seed % 10  # the gap itself is visible
    assert alarms <= most


def test_allan_deviation_refuses_a_sample_rate_that_gives_infinite_tau() -> None:
    with pytest.raises(CalibrationError, match="fs must be"):
        allan_deviation(np.arange(6.0), 5e-324)


def test_allan_deviation_of_white_noise_and_random_walk() -> None:
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40000, 2))
    tau, ad = allan_deviation(x, 100.0)
    # White noise: ADEV = sigma / sqrt(m) (within sampling error).
    m = tau * 100
    assert np.allclose(ad[:6, 0] * np.sqrt(m[:6]), 1.0, rtol=0.1)
    # Independent NumPy reference (non-overlapping clusters, m = 16).
    c = x[: 40000 // 16 * 16, 0].reshape(-1, 16).mean(axis=1)
    ref = math.sqrt(0.5 * np.mean(np.diff(c) ** 2))
    assert abs(ad[4, 0] - ref) / ref < 0.1
    # Correlated (random-walk + white) samples inflate the dwell-mean noise.
    walk = np.cumsum(rng.normal(scale=0.05, size=(6000, 3)), axis=0) + rng.normal(size=(6000, 3))
    d = DwellSet(np.zeros((2, 3)), start=np.array([0, 3000]), stop=np.array([3000, 6000]))
    f = noise_inflation(walk, d, 100.0)
    assert np.all(f > 2.0)
    f0 = noise_inflation(rng.normal(size=(6000, 3)), d, 100.0)
    assert np.all(f0 < 1.5)


def test_public_names() -> None:
    assert accelcal.diagnose is diagnose
    assert "GapReport" in accelcal.__all__


# ----------------------------------------------------------------------------------------------
# Held-out gate and the centrifuge / gradiometer dictionaries.


def test_held_out_gate_rejects_selection_that_does_not_predict() -> None:
    # Bias random walk (outside the dictionary) with a white-noise model: whatever is selected
    # in-sample must lower the held-out gap, else it is "not_confirmed" and best = none.
    for seed in range(40):
        s = gap_session(("bias_random_walk",), rng=2_000_000 + seed, amplitudes=[20.0])
        r = diagnose(s.dwells, g=s.g, gate="strict")
        gs = r.raw["g_steps"]
        if r.best != "none":
            assert r.held_out_gap_after < r.held_out_gap
        nc = r.raw["not_confirmed"]
        if nc is not None:
            # Not confirmed: G^2 fell by less than the 3 parameters' held-out cost 3/n.
            assert nc[3] ** 2 >= nc[2] ** 2 * (1 - 3 / 24) - 1e-12
            row = next(e for e in r.effects if e["effect"] == nc[0])
            assert row["status"] == "not_confirmed"
            assert any("does not reduce the held-out gap" in x for x in r.statements)
            k = len(r.selected)
            assert len(gs) == k + 1 or gs[k + 1] ** 2 >= gs[k] ** 2 * (1 - 3 / 24) - 1e-12
    with pytest.raises(CalibrationError, match="gate"):
        diagnose(s.dwells, g=s.g, gate="maybe")


def test_chi2_attribution_is_more_powerful_than_f() -> None:
    # A weak drift (lambda ~ 20): the chi2 score test (trusted noise model) detects it more
    # often than the sigma-free F test, without false alarms on the null sessions.
    hit = {"auto": 0, "f": 0}
    for seed in range(30):
        s = gap_session(("drift",), rng=3_100_000 + seed, amplitudes=[1.8])
        for mode in hit:
            hit[mode] += diagnose(s.dwells, g=s.g, test=mode, loo=False).best == "drift"
    assert hit["auto"] >= hit["f"] + 4


def _cf(**kw: object) -> object:
    from accelcal.sim import centrifuge_session

    return centrifuge_session(noise_g=2e-6, rng=1, **kw)  # type: ignore[arg-type]


def test_centrifuge_lever_arm_is_found_with_its_size() -> None:
    lev = np.diag([4e-5, -3e-5, 2e-5])  # m
    s = _cf(lever_arm=lev)
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     spin_axis=s.spin_axis, sigma=np.full((60, 3), 2e-6))
    assert r.best == "lever_along" and r.system == "centrifuge"
    est = next(e for e in r.effects if e["effect"] == "lever_along")
    assert np.all(np.abs(est["estimate"] - 1e3 * np.diag(lev)) < 5 * est["std"] + 1e-3)
    assert r.held_out_gap > 2 and r.held_out_gap_after < 1.4
    blind = {b["effect"] for b in r.blind_spots}
    # Mostly absorbed by the scale factors (the aliasing is stated), but its 1 g part is seen.
    assert "common_scale_vs_radius" in blind and "radius_error" not in blind
    assert next(e for e in r.effects if e["effect"] == "radius_error")["status"] == "testable"
    # Null session: no attribution; without spin_axis the lever arms are not testable.
    s = _cf()
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     sigma=np.full((60, 3), 2e-6))
    assert r.best == "none"
    reasons = {b["effect"]: b["reason"] for b in r.blind_spots}
    assert "no spin_axis" in reasons["lever_along"]


def test_centrifuge_misalignment_and_rate_offset() -> None:
    m = np.zeros((3, 3))
    m[1, 0], m[2, 0], m[2, 1] = 2e-5, -1e-5, 1.5e-5
    s = _cf(misalignment=m)
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     spin_axis=s.spin_axis, sigma=np.full((60, 3), 2e-6))
    assert r.best == "misalignment"
    est = next(e for e in r.effects if e["effect"] == "misalignment")
    assert np.all(np.abs(est["estimate"] - 1e3 * np.array([2e-5, -1e-5, 1.5e-5]))
                  < 5 * est["std"] + 2e-3)
    s = _cf(latitude_deg=39.0)  # Earth rate adds 45.9 urad/s to the spin rate
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     spin_axis=s.spin_axis, sigma=np.full((60, 3), 2e-6))
    assert r.best == "rate_offset"
    est = next(e for e in r.effects if e["effect"] == "rate_offset")
    earth = 7.2921150e-5 * np.sin(np.radians(39.0)) * 1e6
    assert abs(est["estimate"][0] - earth) < 5 * est["std"][0]


def _grad(seed: int, **kw: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, object]:
    from accelcal.design import plan_azimuths
    from accelcal.sim import gradiometer_session

    az = plan_azimuths(12, drift=True)
    s = gradiometer_session(az, fs=10.0, dwell_s=60.0, slew_s=20.0, seed=seed, **kw)  # type: ignore[arg-type]
    y = s.truth.channels_E + np.random.default_rng(seed).normal(0, 0.5, (12, 2))
    return az, y, s.truth.dwell_t_mid, s.truth


def test_gradiometer_drift_azimuth_and_channel_scale() -> None:
    az, y, t, tr = _grad(1)
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    assert r.best == "none" and r.system == "gradiometer" and r.units == "E"
    # Drift 2e-3 E/s = 7.2 E/h (aliased with a slow warm-up: reported as ambiguous).
    az, y, t, tr = _grad(2, drift_E_per_s=(2e-3, -1.5e-3))
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5, effects=["drift", "azimuth_error",
                                                                      "channel_scale"])
    assert r.best == "drift"
    est = next(e for e in r.effects if e["effect"] == "drift")
    truth = 3600 * np.array([2e-3, -1.5e-3]) * tr.gain
    assert np.all(np.abs(est["estimate"] - truth) < 5 * est["std"])
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    assert r.best == "drift" or {"drift", r.best} <= set(sum((a["effects"] for a in r.ambiguous),
                                                             []))
    # Azimuth errors of 1 deg on a 47 E gradient.
    az, y, t, tr = _grad(3, azimuth_error_deg=1.0)
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    assert r.best == "azimuth_error"
    # Channel gain mismatch 2 %, cross-talk 1 %.
    az, y, t, tr = _grad(4)
    y2 = (y - 0.0) @ np.array([[1.02, 0.01], [0.01, 0.98]]).T
    r = accelcal.diagnose_gradiometer(az, y2, t=t, sigma=0.5)
    assert r.best == "channel_scale"
    est = next(e for e in r.effects if e["effect"] == "channel_scale")
    assert np.all(np.abs(est["estimate"] - [2.0, 1.0]) < 5 * est["std"] + 0.05)
    # No times: drift and warm-up not testable (listed as such).
    r = accelcal.diagnose_gradiometer(az, y, sigma=0.5, loo=False)
    assert {"drift", "warmup"} <= {b["effect"] for b in r.blind_spots}
    with pytest.raises(DegenerateDataError, match="0/180"):
        accelcal.diagnose_gradiometer([0.0, 180.0, 0.0], np.zeros((3, 2)), sigma=0.5)
    # sigma per channel, as demodulate gives it (inline, cross): equal columns are the scalar;
    # a noisier cross channel weighs less.
    both = accelcal.diagnose_gradiometer(az, y2, t=t, sigma=np.full((len(az), 2), 0.5))
    r = accelcal.diagnose_gradiometer(az, y2, t=t, sigma=0.5)
    assert both.chi2 == r.chi2 and both.best == r.best
    noisy = accelcal.diagnose_gradiometer(az, y2, t=t, sigma=np.c_[np.full(len(az), 0.5),
                                                                   np.full(len(az), 2.0)])
    assert noisy.chi2 < 0.9 * r.chi2
    with pytest.raises(CalibrationError, match=r"sigma must be scalar, \(\d+,\) or \(\d+, 2\)"):
        accelcal.diagnose_gradiometer(az, y2, t=t, sigma=np.full((len(az), 3), 0.5))


def test_screening_estimate_has_the_sign_of_the_truth() -> None:
    # Not selected (max_effects=0): the linearised screening estimate is reported.
    s = gap_session(("drift",), rng=5, amplitudes=[30.0])
    r = diagnose(s.dwells, g=s.g, max_effects=0, loo=False)
    est = next(e for e in r.effects if e["effect"] == "drift")
    assert r.best == "none"
    assert np.all(np.abs(est["estimate"] - s.effects["drift"]) < 5 * est["std"] + 50.0)


# ----------------------------------------------------------------------------------------------
# Min-p (Westfall-Young) family-wise correction.


def test_min_p_is_between_raw_and_bonferroni_and_reproducible() -> None:
    for seed, amp in ((11, 2.5), (12, 3.0), (13, 20.0)):
        s = gap_session(("drift",), rng=4_000_000 + seed, amplitudes=[amp])
        r = diagnose(s.dwells, g=s.g, loo=False)
        r2 = diagnose(s.dwells, g=s.g, loo=False)
        assert r.raw["step_p_adj"] == r2.raw["step_p_adj"]  # fixed seed: deterministic
        assert r.raw["stop_p_adj"] == r2.raw["stop_p_adj"] or math.isnan(r.raw["stop_p_adj"])
        for p, pa, m in zip(r.raw["step_p"], r.raw["step_p_adj"], r.raw["step_m"], strict=True):
            assert p <= pa + 1e-15 and pa <= min(1.0, m * p) + 1e-15
            assert pa < 0.05
        # Bonferroni never declares more than min-p on the same data.
        rb = diagnose(s.dwells, g=s.g, loo=False, correction="bonferroni")
        assert len(rb.selected) <= len(r.selected)
    with pytest.raises(CalibrationError, match="correction"):
        diagnose(s.dwells, g=s.g, correction="holm")


def test_min_p_null_calibration() -> None:
    # On null sessions the first-stage adjusted p-value is (close to) uniform: about 20 % of
    # sessions below 0.2 (Bonferroni's M p would give far fewer), and alarms near alpha.
    below = 0
    alarms = {"minp": 0, "bonferroni": 0}
    for seed in range(100):
        s = gap_session((), rng=5_000_000 + seed, n_dwells=24)
        for corr in alarms:
            r = diagnose(s.dwells, g=s.g, loo=False, correction=corr)
            alarms[corr] += r.best != "none"
            if corr == "minp":
                pa = r.raw["step_p_adj"][0] if r.selected else r.raw["stop_p_adj"]
                below += pa < 0.2
    # binomial(100, 0.2): 8..33 holds with p > 0.999.
    assert 8 <= below <= 33
    assert alarms["minp"] <= 12
    assert alarms["bonferroni"] <= alarms["minp"]


# ----------------------------------------------------------------------------------------------
# Review fixes: units, labels, blind-spot text, small leave-one-out, raw-path t/temperature.


def test_report_units_and_labels_of_the_systems() -> None:
    s = _cf(lever_arm=np.diag([4e-5, -3e-5, 2e-5]))
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     spin_axis=s.spin_axis, sigma=np.full((60, 3), 2e-6))
    assert r.units == "g" and r.rms_before > r.rms_after > 0
    with pytest.raises(AttributeError, match="static sessions only"):
        _ = r.rms_before_mps2
    txt = r.summary()
    assert "by speed" in txt and "by time third" not in txt and "row(s)" in txt
    reason = next(b["reason"] for b in r.blind_spots if b["effect"] == "common_scale_vs_radius")
    assert "all 3 speeds" in reason and "single speed" not in reason
    assert "resid" in r.dwells and "resid_mps2" not in r.dwells
    az, y, t, _ = _grad(1)
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    txt = r.summary()
    assert "by channel" in txt and "by pose axis" not in txt and "residual" in txt
    assert r.units == "E" and math.isfinite(r.rms_before)
    # Static: unit-neutral names and the m/s^2 aliases agree.
    s2 = gap_session(("drift",), rng=3, amplitudes=[20.0])
    r = diagnose(s2.dwells, g=s2.g)
    assert r.rms_before_mps2 == r.rms_before and r.units == "m/s^2"
    assert np.array_equal(r.dwells["resid"], r.dwells["resid_mps2"])
    assert "rms_before" in r.to_dict()


def test_gradiometer_abba_too_small_for_held_out_gate() -> None:
    az = np.array([0.0, 45.0, 45.0, 0.0])
    t = np.array([30.0, 110.0, 190.0, 270.0])
    c, s = np.cos(np.radians(2 * az)), np.sin(np.radians(2 * az))
    y = np.column_stack([5 + 30 * c - 10 * s, 2 - 30 * s - 10 * c])
    y += np.outer((t - t.mean()) / 3600, [200.0, -150.0])
    y += np.random.default_rng(1).normal(0, 0.5, y.shape)
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5, effects=["drift", "azimuth_error"])
    assert r.best == "drift"
    assert not any(e["status"] == "not_confirmed" for e in r.effects)
    assert any("too small to judge" in x for x in r.statements)


def test_raw_stream_with_per_sample_time_and_temperature() -> None:
    from accelcal.sim import field_session

    s = field_session(fs=200.0, n_dwells=24, dwell_s=6.0, move_s=2.0, max_tilt_deg=80.0,
                      sigma=1e-3, rng=3)
    temp = 20 + 8 * np.sin(np.pi * (s.t - s.t[0]) / (s.t[-1] - s.t[0]))  # heat, then cool
    x = s.samples + 0.004 * (temp - temp.mean())[:, None] * np.array([1.0, -0.7, 0.5])
    r = diagnose(x, fs=s.fs, g=s.g, t=s.t, temperature=temp)
    assert r.best == "temperature_bias"
    est = next(e for e in r.effects if e["effect"] == "temperature_bias")["estimate"]
    # 0.004 (m/s^2)/K per axis = 1e6 * 0.004 / c_i ug/K with c_i = s_i g (truth scales).
    truth = 1e6 * 0.004 * np.array([1.0, -0.7, 0.5]) / (s.truth[:3] * s.g)
    assert np.all(np.abs(est - truth) < 0.1 * np.abs(truth) + 30.0)
    r = diagnose(x, fs=s.fs, g=s.g, t=s.t)
    assert r.best != "temperature_bias"
    assert "temperature_bias" in {b["effect"] for b in r.blind_spots}
    with pytest.raises(CalibrationError, match="one value per sample|temperature"):
        diagnose(x, fs=s.fs, g=s.g, temperature=temp[:-5])
    with pytest.raises(CalibrationError, match="DwellSet"):
        diagnose(accelcal.detect_dwells(x, s.fs), g=s.g, temperature=temp)


# ----------------------------------------------------------------------------------------------
# Round 2: one engine, typed report, fixed calibrations, structure, clear errors.


def _half_means(samples: np.ndarray, d: DwellSet) -> np.ndarray:
    """Independent NumPy reference: first- and second-half sample means of each dwell."""
    out = np.empty((len(d), 2, 3))
    for k, (a, b) in enumerate(zip(d.start, d.stop, strict=True)):
        mid = (int(a) + int(b)) // 2
        out[k, 0] = samples[int(a):mid].mean(axis=0)
        out[k, 1] = samples[mid:int(b)].mean(axis=0)
    return out


def test_report_pickles_and_round_trips() -> None:
    import pickle

    from accelcal.gap import GapReport

    s = gap_session(("drift",), rng=3, amplitudes=[20.0])
    r = diagnose(s.dwells, g=s.g)
    r2 = pickle.loads(pickle.dumps(r))
    assert r2.summary() == r.summary()
    assert np.array_equal(r2.dwells["e"], r.dwells["e"])
    r3 = GapReport.from_dict(json.loads(json.dumps(r.to_dict())))
    assert r3.summary() == r.summary()
    assert repr(r3.structure) == repr(r.structure)  # NaN-aware
    assert np.allclose(r3.params_after, r.params_after)
    # Equal by value (it raised "truth value of an array is ambiguous"); from_dict leaves the
    # caller's dict as it was (its estimates became arrays, and json.dumps of it then failed).
    import copy

    assert r == copy.deepcopy(r) and r == r2 and r != diagnose(s.dwells, g=s.g, alpha=0.01)
    d = r.to_dict()
    before = json.dumps(d, sort_keys=True)
    GapReport.from_dict(d)
    assert json.dumps(d, sort_keys=True) == before


def test_ml_baseline_matches_a_scipy_reference() -> None:
    # The baseline is maximum likelihood: sigma_k^2 = w^T Sigma_k w, w = K^-T a / |a|,
    # re-evaluated at every parameter vector. Independent reference: scipy least_squares on
    # the same cost from the same start.
    from scipy.optimize import least_squares

    s = gap_session((), rng=21, n_dwells=20, sigma=3e-3)
    d = s.dwells
    var = np.tile([1e-6, 9e-6, 2.5e-7], (len(d), 1)) * (1 + np.arange(len(d)))[:, None] / 10
    r = diagnose(d, g=s.g, noise=np.sqrt(var), effects=[], loo=False)

    def cost(p: np.ndarray) -> np.ndarray:
        K = np.array([[p[0], 0, 0], [p[6], p[1], 0], [p[7], p[8], p[2]]])
        T = np.linalg.inv(K)
        a = (T @ (d.mean - p[3:6]).T).T
        na = np.linalg.norm(a, axis=1)
        w = (T.T @ (a / na[:, None]).T).T
        sig = np.sqrt(np.sum(w**2 * var, axis=1))
        return (na - s.g) / sig

    ref = least_squares(cost, r.params + 1e-4, method="lm", xtol=1e-14, ftol=1e-14)
    assert np.allclose(ref.x, r.params, rtol=0, atol=1e-8 * np.abs(r.params).max() + 1e-9)
    assert abs(2 * ref.cost - r.chi2) < 1e-6 * r.chi2


def test_existing_calibration_is_checked_not_refitted(tmp_path: Any) -> None:
    from accelcal import TriadModel, fit_static

    s = gap_session((), rng=31, n_dwells=16)
    d = s.dwells
    truth = s.nuisance
    K = np.array([[truth[0], 0, 0], [truth[6], truth[1], 0], [truth[7], truth[8], truth[2]]])
    good = diagnose(d, g=s.g, fit=TriadModel(K, truth[3:6]))
    assert good.dof == 16 and "held fixed" in " ".join(good.statements)
    assert good.p_value > 1e-3
    # The bias moved since that calibration: a clear gap (chi2 from 16 dwells, no refit).
    bad = diagnose(d, g=s.g, fit=TriadModel(K, truth[3:6] + [0, 0, 2e-3]))
    assert bad.p_value < 1e-6 and bad.chi2 > 10 * good.chi2
    # A StaticFit is a start: the calibration is refitted (9 parameters).
    f = fit_static(d, g=s.g)
    r = diagnose(d, g=s.g, fit=f)
    assert r.dof == 16 - 9
    with pytest.raises(CalibrationError, match="StaticFit .* TriadModel"):
        diagnose(d, g=s.g, fit="cal.json")
    # The CLI does the same with --calibration.
    from accelcal.cli import main
    from accelcal.sim import field_session
    from click.testing import CliRunner

    fs_ = field_session(fs=100.0, n_dwells=14, dwell_s=4.0, move_s=2.0, max_tilt_deg=80.0,
                        sigma=1e-3, rng=4)
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack([fs_.t, fs_.samples]), delimiter=",",
               header="t,ax,ay,az", comments="")
    t0 = fs_.truth
    Kt = np.array([[t0[0], 0, 0], [t0[6], t0[1], 0], [t0[7], t0[8], t0[2]]])
    cal = tmp_path / "cal.json"
    TriadModel(Kt, t0[3:6]).save(cal)
    out = CliRunner().invoke(main, ["diagnose", str(path), "--g", f"{fs_.g}", "--calibration",
                                    str(cal), "--json"])
    assert out.exit_code == 0, out.output
    rep = json.loads(out.output)
    assert rep["dof"] == rep["n"] and "held fixed" in " ".join(rep["statements"])


def test_a_calibration_checked_against_its_own_dwells_is_told_so(tmp_path: Any) -> None:
    """Checking a calibration against the dwells it was fitted to double-counts its
    uncertainty (chi2/dof far below 1 on the shared MPU-6050): the model records a hash of
    each dwell mean, and the check says how many of the session's dwells are its own, in
    Python, through a saved file, and in the CLI (also when other detector settings give
    other dwells of the same recording)."""
    from accelcal import TriadModel, fit_static

    s = gap_session((), rng=32, n_dwells=20)
    own = "ones the calibration was fitted to"
    model = fit_static(s.dwells, g=s.g).to_model()
    path = tmp_path / "cal.json"
    model.save(path)
    loaded = TriadModel.load(path)
    assert loaded.own_dwells(s.dwells.mean) == 20
    same = diagnose(s.dwells, g=s.g, fit=loaded)
    assert any(x.startswith(f"20 of the 20 dwells are {own}") for x in same.statements)
    # The saved file keeps the session: its uncertainty is a bootstrap of it.
    assert np.array(loaded.metadata["fit_session"]["means"]).shape == (20, 3)
    assert any("its session refitted 1500 times" in x for x in same.statements)
    assert same.chi2_per_dof < 0.7  # the double count it warns of
    other = gap_session((), rng=33, n_dwells=20)
    assert loaded.own_dwells(other.dwells.mean) == 0
    assert not any(own in x for x in diagnose(other.dwells, g=s.g, fit=loaded).statements)
    # A hand-made model records nothing: never claimed.
    assert TriadModel(model.K, model.bias).own_dwells(s.dwells.mean) == 0
    # The CLI: calibrate -o, then diagnose --calibration on the same file.
    from accelcal.cli import main
    from accelcal.sim import field_session
    from click.testing import CliRunner

    fs_ = field_session(fs=100.0, n_dwells=16, dwell_s=4.0, move_s=2.0, max_tilt_deg=80.0,
                        sigma=1e-3, rng=6)
    rec = tmp_path / "rec.csv"
    np.savetxt(rec, np.column_stack([fs_.t, fs_.samples]), delimiter=",",
               header="t,ax,ay,az", comments="")
    cal = tmp_path / "own.json"
    r = CliRunner().invoke(main, ["calibrate", "static", str(rec), "--g", f"{fs_.g}", "-o",
                                  str(cal)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(main, ["diagnose", str(rec), "--g", f"{fs_.g}", "--calibration",
                                  str(cal)])
    assert r.exit_code == 0 and f"16 of the 16 dwells are {own}" in r.output, r.output
    r = CliRunner().invoke(main, ["diagnose", str(rec), "--g", f"{fs_.g}", "--calibration",
                                  str(cal), "--window", "0.7"])
    assert r.exit_code == 0 and "made from this same recording" in r.output, r.output
    assert own not in r.output


def test_centrifuge_and_gradiometer_run_the_same_engine() -> None:
    s = _cf(lever_arm=np.diag([4e-5, -3e-5, 2e-5]))
    r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g,
                                     spin_axis=s.spin_axis, sigma=np.full((60, 3), 2e-6))
    # Min-p family-wise adjusted p-value, between the raw p and the Bonferroni bound.
    p, pa, m = r.raw["step_p"][0], r.raw["step_p_adj"][0], r.raw["step_m"][0]
    assert p <= pa <= min(1.0, m * p) + 1e-15
    assert r.structure.verdict in {"none", "per_dwell"}
    statuses = {e["status"] for e in r.effects}
    # no_time: the drift, without row times t.
    assert statuses <= {"selected", "testable", "blind", "too_few_dwells", "no_spin_axis",
                        "not_confirmed", "no_time"}
    az, y, t, _ = _grad(2, drift_E_per_s=(2e-3, -1.5e-3))
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    assert r.raw["step_p_adj"] and r.raw["step_p_adj"][0] <= min(1.0, r.raw["step_m"][0]
                                                                  * r.raw["step_p"][0])
    assert math.isfinite(r.structure.per_dwell_rms)


@pytest.mark.parametrize("name, bad", [
    ("max_effects", None), ("max_effects", "3"), ("max_effects", math.inf),
    ("max_effects", 2.5), ("n_draws", -1), ("n_draws", "many"), ("alpha", 0.0),
    ("alpha", None), ("trust_level", math.nan), ("gate_margin", math.inf), ("alpha", True),
])
def test_bad_option_values_name_the_argument(name: str, bad: Any) -> None:
    s = gap_session((), rng=5)
    with pytest.raises(CalibrationError, match=rf"{name} must be .* in [\[(].*got"):
        diagnose(s.dwells, g=s.g, **{name: bad})
    if name in ("max_effects", "alpha"):
        az, y, t, _ = _grad(1)
        with pytest.raises(CalibrationError, match=name):
            accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5, **{name: bad})
        c = _cf()
        with pytest.raises(CalibrationError, match=name):
            accelcal.diagnose_centrifuge(c.outputs, c.omega, c.radius, **{name: bad})


def test_bad_arrays_are_clear_errors() -> None:
    az, y, t, _ = _grad(1)
    with pytest.raises(CalibrationError, match="azimuth_deg must be real numbers; got a boolean"):
        accelcal.diagnose_gradiometer(az > 90, y, t=t, sigma=0.5)
    with pytest.raises(CalibrationError, match="outputs contains NaN"):
        accelcal.diagnose_gradiometer(az, np.where(y > 40, np.nan, y), t=t, sigma=0.5)
    with pytest.raises(CalibrationError, match="complex"):
        accelcal.diagnose_gradiometer(az, y.astype(complex), sigma=0.5)
    with pytest.raises(CalibrationError, match="preset"):
        diagnose(gap_session((), rng=1).dwells, g=9.8, preset="bold")
    # A stream in which the sensor never rests: the diagnosis says so.
    tt = np.arange(3000) / 100.0
    moving = np.column_stack([9.81 * np.sin(2 * tt), 9.81 * np.cos(2 * tt), 0.1 * np.sin(7 * tt)])
    with pytest.raises(CalibrationError, match="no static dwells detected"):
        diagnose(moving, g=9.81, fs=100.0)


def test_no_nan_without_a_status() -> None:
    # Few dwells: every NaN figure comes with the statement or status that explains it.
    s = gap_session((), rng=8, n_dwells=11)
    r = diagnose(s.dwells, g=s.g)
    for e in r.effects:
        if not math.isfinite(e["p_value"]):
            assert e["status"] != "testable" and e["effect"] in {b["effect"]
                                                                 for b in r.blind_spots}
    if not math.isfinite(r.held_out_gap):
        assert any("held-out" in x for x in r.statements)
    for t in r.structure.tests:
        if t.status == "testable":
            assert math.isfinite(t.p_value), t
        else:
            assert not math.isfinite(t.p_value)


def test_raw_stream_gives_half_dwell_means_and_persistence() -> None:
    from accelcal.sim import field_session

    s = field_session(fs=200.0, n_dwells=30, dwell_s=6.0, move_s=2.0, max_tilt_deg=80.0,
                      sigma=1e-3, rng=9)
    d = accelcal.dwell_stats(s.samples, np.column_stack([accelcal.detect_dwells(
        s.samples, s.fs).start, accelcal.detect_dwells(s.samples, s.fs).stop]))
    assert d.half_mean is not None
    assert np.allclose(d.half_mean, _half_means(s.samples, d), atol=1e-12)
    r = diagnose(s.samples, g=s.g, fs=s.fs)
    st = r.structure
    assert st.persistence_testable and math.isfinite(st.persistence)
    assert st.noise_empirical is not None and 0.6 < st.noise_empirical.ratio_model < 1.6
    assert st.verdict == "none", r.summary()
    assert "Structure: none" in r.summary()
    # No temperature: said as not given (perhaps a column not recognised), not as absent.
    assert ("temperature_bias: not testable: no temperature given (none recorded, or its "
            "column not recognised") in r.summary()


@pytest.mark.parametrize("kind", ["per_dwell", "correlated_noise", "attitude", "hysteresis",
                                  "quantization", "time", "temperature"])
def test_structure_verdicts_of_simulated_classes(kind: str) -> None:
    # 12 sessions per class at lambda 100-300: the verdict named by the simulator's class in
    # at least 10 (the measured rate at lambda >= 30 is in docs/gap-validation.md).
    from accelcal.sim.gap import STRUCTURE_CLASSES, structure_session

    ok = 0
    for i in range(12):
        s = structure_session(kind, rng=70_000 + i, lam_range=(100.0, 300.0))
        r = diagnose(s.dwells, g=s.g, loo=False)
        ok += r.structure.verdict == STRUCTURE_CLASSES[kind]
    assert ok >= 10, (kind, ok)


def test_half_dwell_differences_alone_make_the_noise_model_verdict() -> None:
    # A null session whose half-dwell means scatter 3x more than the reported white noise
    # predicts while the dwell means agree with it (the halves' errors cancel in the mean):
    # without half means the verdict is "none"; with them, "noise_model", and the sentence
    # gives the half-difference evidence, not the persistent share labelled as an F.
    from accelcal.sim.gap import structure_session

    s = structure_session("per_dwell", rng=7_900_003, lam=1e-9)
    d = s.dwells
    base = diagnose(DwellSet(d.mean, d.var, d.count, d.t, d.temperature, fs=d.fs), g=s.g,
                    loo=False)
    assert base.structure.verdict == "none", base.summary()
    gen = np.random.default_rng(5)
    dev = 3.0 * gen.normal(size=d.mean.shape) * np.sqrt(d.var / d.count[:, None])
    half = np.stack([d.mean + dev, d.mean - dev], axis=1)
    r = diagnose(DwellSet(d.mean, d.var, d.count, d.t, d.temperature, fs=d.fs, half_mean=half),
                 g=s.g, loo=False)
    st = r.structure
    assert st.verdict == "noise_model", r.summary()
    assert st.noise_empirical is not None and st.noise_empirical.ratio_model > 2.0
    assert st.p_value == st.noise_empirical.p_model < 1e-6
    text = st.summary()
    assert "half-dwell differences give a dwell-mean noise" in text
    assert "under the noise model" in text and "persistence F =" in text


def test_gap_figure_sphere_map_flags_and_allan_panel(tmp_path: Any) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from accelcal.plots import save_figure
    from accelcal.sim import field_session

    # No temperature: the middle panel is the residual on a sphere map (Mollweide), with the
    # Bonferroni limit on its colour bar; the raw stream gives the Allan panel its curves.
    s = field_session(fs=200.0, n_dwells=24, dwell_s=6.0, move_s=2.0, max_tilt_deg=80.0,
                      sigma=1e-3, rng=11)
    x = s.samples.copy()
    d = accelcal.detect_dwells(x, s.fs)
    k = 5  # one dwell knocked by 0.02 m/s^2 along its axis: flagged
    x[d.start[k]:d.stop[k]] += 0.02 * x[d.start[k]:d.stop[k]] / 9.8
    r = diagnose(x, g=s.g, fs=s.fs)
    assert k in r.where["flagged"]
    fig = r.plot()
    names = [a.name for a in fig.axes]
    assert "mollweide" in names
    sphere = fig.axes[names.index("mollweide")]
    # Every dwell plotted once; each flagged dwell ringed once more.
    offsets = [c.get_offsets().shape[0] for c in sphere.collections]
    assert offsets == [r.n, len(r.where["flagged"])]
    allan = [a for a in fig.axes if a.get_xscale() == "log"]
    assert len(allan) == 1
    labels = allan[0].get_legend_handles_labels()[1]
    assert "noise model used" in labels and "half-dwell differences" in labels
    assert any(lab.startswith("ADEV") for lab in labels)
    save_figure(fig, str(tmp_path / "gap.png"))
    assert (tmp_path / "gap.png").stat().st_size > 10_000
    # Centrifuge: residuals by row with the limit.
    c = _cf()
    fig = accelcal.diagnose_centrifuge(c.outputs, c.omega, c.radius, g=c.g,
                                       sigma=np.full((60, 3), 2e-6)).plot()
    assert len(fig.axes) == 1


def test_random_offset_model_keeps_false_alarms_on_per_dwell_offsets() -> None:
    # Sessions whose only gap is persistent random per-dwell offsets (what the
    # variance-component model describes), chi2 300 above the noise model: with the offset
    # variance estimated under every model compared, no dictionary effect is attributed
    # (alpha = 0.05 family-wise; at most 1 of 12 allowed), and the option reaches the engine.
    from accelcal.sim.gap import structure_session

    assert accelcal._core.GapSettings(random_offset=True).random_offset is True
    assert accelcal._core.GapSettings().random_offset is False
    alarms = 0
    for seed in range(12):
        s = structure_session("per_dwell", rng=500 + seed, n_dwells=40, lam=300.0)
        r = accelcal.diagnose(s.dwells, g=s.g, random_offset=True, loo=False)
        assert r.chi2_per_dof > 3.0
        alarms += r.best != "none"
    assert alarms <= 1, alarms


def test_a_marginal_gap_without_structure_is_not_called_unexplained() -> None:
    # Null sessions with half-dwell means: the residual chi2 is sometimes significant at alpha
    # on its own but not at alpha / 2, where the structure analysis tests it beside the
    # half-dwell check. The statement must then agree with the structure verdict "none".
    from accelcal.sim.gap import structure_session

    marginal = 0
    for seed in range(100):
        s = structure_session("per_dwell", rng=seed, lam=1e-9, n_dwells=30)
        r = diagnose(s.dwells, g=s.g, loo=False)
        if r.selected or not r.p_value < 0.05:
            continue
        unexplained = any("no dictionary effect explains it" in x for x in r.statements)
        called_marginal = any("marginal gap with no structure" in x for x in r.statements)
        if r.structure.verdict == "none":
            marginal += 1
            assert 0.025 <= r.p_value and called_marginal and not unexplained, r.statements
        else:
            assert unexplained and not called_marginal, r.statements
    assert marginal >= 1


def test_bic_weights_use_the_known_noise_when_it_is_trusted() -> None:
    # 16 dwells and 9 parameters: a 3-parameter effect leaves 4 degrees of freedom, where the
    # sigma-free BIC n ln(RSS/n) would reward almost any fit. With the noise model trusted
    # (a remainder of at least 3 degrees of freedom consistent with it) each weight against
    # "none" is exp((score - d ln n) / 2) (BIC = chi2 + k ln n), so it agrees with the chi2
    # test: no candidate that the test rejects gets most of the weight.
    checked = 0
    for seed in range(30):
        s = gap_session((), rng=seed, n_dwells=16)
        r = diagnose(s.dwells, g=s.g, loo=False)
        if not r.p_value > 0.02:  # the baseline must be consistent with the noise model
            continue
        w_none = r.raw["weight_none"]
        for e in r.effects:
            if e["status"] != "testable" or e["test"] != "chi2":
                continue
            want = math.exp((e["score"] - e["d"] * math.log(16)) / 2)
            assert e["bic_weight"] / w_none == pytest.approx(want, rel=1e-9)
            if e["p_value"] > 0.05:
                assert e["bic_weight"] < 0.5, (seed, e)
            checked += 1
    assert checked >= 50


def test_fixed_pose_order_cannot_test_pose_history_and_says_so() -> None:
    """Six faces in the same order seven times over, a warm-up offset on the first dwell:
    the first dwell has no previous pose and is left out of the pose-history test, which is
    then blind (every other dwell's previous pose follows from its own), and the summary
    says to shuffle the order instead of reporting hysteresis."""
    from accelcal.sim.static import static_dwell_means

    faces = np.array([[0, 0, 1], [0, 0, -1], [0, 1, 0], [0, -1, 0], [1, 0, 0], [-1, 0, 0]],
                     dtype=float)
    tilt = np.array([[0.03, -0.02, 0.0], [0.01, 0.02, 0.0], [-0.02, 0.0, 0.03],
                     [0.02, 0.0, -0.01], [0.0, 0.03, 0.02], [0.0, -0.01, -0.03]])
    rng = np.random.default_rng(4)
    u = np.tile(faces + tilt, (7, 1)) + 0.001 * rng.standard_normal((42, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    s = static_dwell_means(u, sigma=1e-4, sigma_g=0.0, rng=5)
    m = s.means.copy()
    m[0] += 2e-3 * u[0]  # warm-up: the first dwell alone
    d = DwellSet(m, var=np.full((42, 3), 1e-8 * 400), count=np.full(42, 400),
                 t=60.0 * np.arange(42))
    r = diagnose(d, g=s.g_measured, effects=[])
    ph = r.structure.test("pose_history")
    assert ph.status == "blind"
    assert r.structure.verdict != "pose_history"
    assert "pose_history (each pose follows the same pose every time: shuffle the pose " \
           "order to test it)" in r.summary()


def test_a_session_in_units_of_g_is_reported_in_g() -> None:
    """The same session in m/s^2 and in g (means / 9.80665, g = 1): the same statistics, and
    every magnitude in the units of g (mg, not mm/s^2), as the fit and its calibration file
    give them."""
    s = gap_session(("drift",), rng=3, amplitudes=[20.0], sigma=1e-3)
    d, c = s.dwells, 1.0 / 9.80665
    in_g = DwellSet(d.mean * c, d.var * c * c, d.count, t=d.t, temperature=d.temperature,
                    half_mean=None if d.half_mean is None else d.half_mean * c)
    a, b = diagnose(d, g=9.80665), diagnose(in_g, g=1.0)
    assert (a.units, b.units) == ("m/s^2", "g")
    assert b.chi2 == pytest.approx(a.chi2, rel=1e-6) and b.best == a.best
    assert b.rms_after == pytest.approx(a.rms_after * c, rel=1e-6)
    if math.isfinite(a.structure.per_dwell_rms):
        assert b.structure.per_dwell_rms == pytest.approx(a.structure.per_dwell_rms * c,
                                                          rel=1e-6)
    text = b.summary()
    assert "m/s^2" not in text and "mm/s" not in text
    assert accelcal.fit_static(in_g, 1.0).to_model().units == "g"
    assert accelcal.fit_static(d, 9.80665).to_model().units == "m/s^2"


def test_a_session_that_cannot_determine_the_calibration_is_refused_as_the_fit_does() -> None:
    """Six faces only (a tumble test): the 9-parameter calibration the diagnosis fits is not
    determined, so the diagnosis refuses, naming the combination and the two ways on; with
    a bias + scale calibration of the same session held fixed it runs."""
    from accelcal.sim.static import static_dwell_means

    faces = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
                     dtype=float)
    truth = [1.01, 0.99, 1.02, 0.05, -0.03, 0.08, 0.0, 0.0, 0.0]
    s = static_dwell_means(np.repeat(faces, 3, axis=0), truth, 9.80665, sigma=1e-3,
                           sigma_g=0.0, rng=4)
    d = DwellSet(s.means, np.full((18, 3), 1e-6) * 100, np.full(18, 100))
    with pytest.raises(DegenerateDataError) as exc:
        diagnose(d, g=9.80665)
    msg = str(exc.value)
    assert "determine m1" in msg and "The gap diagnosis fits that 9-parameter" in msg
    assert msg.count("add poses") == 1
    assert 'calibrate with model "diag"' in msg and "fit=" in msg
    with pytest.raises(DegenerateDataError):
        accelcal.fit_static(d, 9.80665)  # the fit refuses it too
    cal = accelcal.fit_static(d, 9.80665, model="diag").to_model()
    rep = diagnose(d, g=9.80665, fit=cal)
    assert rep.best == "none" and rep.chi2_per_dof < 3


def test_a_checked_calibration_brings_its_own_uncertainty() -> None:
    """A calibration from a weak session (12 dwells within +-30 deg) checked against a new
    session over the whole sphere: taken as exact, its weakly determined terms look like a gap
    in every seed; with its uncertainty propagated to each dwell's norm, far fewer false
    alarms, fewest when the model carries its session (a parametric bootstrap: the weak
    design's sampling distribution is far from the Gaussian of its covariance), and the
    report says how much it added and how it was drawn."""
    from accelcal.sim.static import static_dwell_means

    truth = [1.01, 0.99, 1.02, 0.05, -0.03, 0.08, 0.004, -0.003, 0.002]
    var = np.full((12, 3), 1e-6) * 100

    def dwells(m: np.ndarray) -> DwellSet:
        return DwellSet(m, np.full(m.shape, 1e-4), np.full(len(m), 100))

    alarms_with = alarms_without = alarms_cov = 0
    for seed in range(12):
        s1 = static_dwell_means(12, truth, 9.80665, sigma=1e-3, sigma_g=0.0, max_tilt_deg=30,
                                rng=seed)
        with pytest.warns(accelcal.WeakDesignWarning):
            m = accelcal.fit_static(DwellSet(s1.means, var, np.full(12, 100)),
                                    9.80665).to_model()
        s2 = static_dwell_means(24, truth, 9.80665, sigma=1e-3, sigma_g=0.0,
                                max_tilt_deg=None, rng=1000 + seed)
        rep = diagnose(dwells(s2.means), g=9.80665, fit=m, loo=False)
        exact = diagnose(dwells(s2.means), g=9.80665,
                         fit=accelcal.TriadModel(m.K, m.bias, model=m.model), loo=False)
        # The same calibration without its session (a model written before it was kept,
        # or made by hand): its covariance draws.
        md = {x: y for x, y in m.metadata.items() if x != "fit_session"}
        cov = diagnose(dwells(s2.means), g=9.80665, loo=False, fit=accelcal.TriadModel(
            m.K, m.bias, model=m.model, g=m.g, metadata=md, realistic=m.realistic,
            covariance_noise_model=m.covariance_noise_model,
            covariance_scaled=m.covariance_scaled))
        alarms_with += rep.p_value < 0.05
        alarms_without += exact.p_value < 0.05
        alarms_cov += cov.p_value < 0.05
        assert rep.chi2 < exact.chi2
        assert any("the calibration's own uncertainty (its session refitted 1500 times" in x
                   for x in rep.statements)
        assert any("the calibration's own uncertainty (its parameters drawn 1500 times" in x
                   for x in cov.statements)
        assert any("taken as exact" in x for x in exact.statements)
    # Measured on 100 seeds (benches/validate_calibration_check.py): 100 %, 22 %, 6 %.
    assert alarms_without >= 11 and alarms_with <= 2 and alarms_cov <= 5, (
        alarms_with, alarms_cov, alarms_without)
    # A calibration the poses determine (40 dwells over the sphere): about alpha.
    alarms = 0
    for seed in range(12):
        s1 = static_dwell_means(40, truth, 9.80665, sigma=1e-3, sigma_g=0.0,
                                max_tilt_deg=None, rng=50 + seed)
        m = accelcal.fit_static(dwells(s1.means), 9.80665).to_model()
        s2 = static_dwell_means(24, truth, 9.80665, sigma=1e-3, sigma_g=0.0,
                                max_tilt_deg=None, rng=2000 + seed)
        alarms += diagnose(dwells(s2.means), g=9.80665, fit=m, loo=False).p_value < 0.05
    assert alarms <= 2


def test_the_allan_inflation_is_read_at_each_dwells_length() -> None:
    """Dwells of one length share the median inflation; dwells of different lengths get a
    power law in the length (flicker noise: inflation ~ L^0.5), so a short dwell does not take
    the drift of a long one (a 14 s and a 75 s dwell, as a real two-pose recording had)."""
    from accelcal.gap import _pool_inflation

    rng = np.random.default_rng(3)
    same = np.exp(0.2 * rng.standard_normal((20, 3))) * [1.0, 2.0, 3.0]
    np.testing.assert_allclose(_pool_inflation(same, np.full(20, 1000)),
                               np.tile(np.maximum(np.median(same, axis=0), 1), (20, 1)))
    length = np.exp(rng.uniform(np.log(300), np.log(30000), 40))
    truth = 2.0 * (length / 1000.0) ** 0.5
    noisy = truth[:, None] * np.exp(0.15 * rng.standard_normal((40, 3)))
    pooled = _pool_inflation(noisy, length)
    assert np.all(np.abs(np.log(np.maximum(pooled, 1) / np.maximum(truth, 1)[:, None])) < 0.3)
    two = _pool_inflation(np.array([[1.3, 1.0, 1.3], [30.7, 1.0, 30.7]]), [1400, 7500])
    assert two[0, 0] < 5 < two[1, 0]  # not 16 for both, as the median gave
    np.testing.assert_allclose(_pool_inflation(same), np.tile(np.maximum(
        np.median(same, axis=0), 1), (20, 1)))  # without lengths: the median, as before


def test_two_dwells_checking_a_fixed_calibration_are_too_few_not_blind() -> None:
    """Two dwells against a held-fixed calibration: the effects have no direction left to
    test, which is too few dwells (said so, with the count), not a pattern the calibration
    absorbs (no parameter is fitted)."""
    from accelcal.sim.field import FIELD_TRUTH
    from accelcal.sim.static import static_dwell_means

    s = static_dwell_means(2, FIELD_TRUTH, 9.80665, sigma=1e-3, sigma_g=0.0, rng=3)
    model = accelcal.TriadModel.from_vector(FIELD_TRUTH)
    rep = diagnose(DwellSet(s.means, np.full((2, 3), 1e-4), np.full(2, 100)), g=9.80665,
                   fit=model)
    drift = next(e for e in rep.effects if e["effect"] == "drift")
    assert drift["status"] in ("too_few_dwells", "no_time")
    text = rep.summary()
    assert "absorbed by the calibration parameters" not in text
    assert "too few dwells (2)" in text or "no dwell times" in text


def test_a_calibration_checked_at_one_attitude_attributes_no_effect() -> None:
    """A fixed calibration checked on dwells that are all one pose (a long rest cut into
    pieces, as a user did with tomisuarez2's initialisation-time recording): a gap there is a
    constant offset, which every effect's column fitted alike (best = k3 at -4e7 ug/g^3), and
    the previous pose is the same pose (pose_history F = 239). Now no effect is attributed,
    attitude and pose history are not testable, and the report says why."""
    from accelcal import fit_static
    from accelcal.sim.static import static_dwell_means

    s1 = static_dwell_means(30, rng=1, max_tilt_deg=None)
    m = fit_static(DwellSet(s1.means, np.full((30, 3), 1e-4), np.full(30, 100)),
                   9.80665).to_model()
    rng = np.random.default_rng(0)
    one = s1.means[3] + 1e-3 * rng.standard_normal((10, 3)) + [0.0, 0.0, 0.01]
    r = diagnose(DwellSet(one, np.full((10, 3), 1e-4), np.full(10, 100)), g=9.80665, fit=m)
    assert r.p_value < 1e-10  # the offset is a gap
    assert r.best == "none" and not [e for e in r.effects if e["status"] == "selected"]
    # The engine decides: every effect is not testable there, and the report says why.
    assert r.effects and all(e["status"] == "one_attitude" for e in r.effects)
    assert sum("every dwell at one attitude" in b["reason"] for b in r.blind_spots) == len(
        r.effects)
    assert [t.status for t in r.structure.tests if t.name in ("attitude", "pose_history")] == [
        "one_attitude", "one_attitude"]
    assert any(x.startswith("the 10 dwells are one pose: at one attitude a gap is a constant "
                            "offset") for x in r.statements)
    assert "not testable (every dwell at one attitude): attitude, pose_history" in r.summary()
    assert r.structure.verdict != "pose_history"
    # Two attitudes: the effects are tested again.
    two = np.vstack([one, s1.means[7] + 1e-3 * rng.standard_normal((10, 3))])
    r2 = diagnose(DwellSet(two, np.full((20, 3), 1e-4), np.full(20, 100)), g=9.80665, fit=m)
    assert not any("are one pose" in x for x in r2.statements)
    assert any(e["status"] in ("testable", "selected") for e in r2.effects)


def test_a_calibration_checked_without_a_noise_model_is_tested_against_a_refit() -> None:
    """A real ICM-20948 table of pose means (no per-pose noise) checked against its sibling
    session's calibration read "chi2/dof = 1.00, G = 1.00 (1 = adequate)": with the noise
    unknown, both are scaled to the checked calibration's own residuals, so they are 1
    whatever the calibration. A refit of the session against the calibration's parameters
    (a Wald test over both covariances) is the test that can fail."""
    from accelcal import TriadModel
    from accelcal.sim.static import static_dwell_means
    from accelcal.static import fit_quietly

    truth = np.array([1.02, 0.98, 1.01, 0.01, -0.02, 0.015, 0.002, -0.001, 0.003])
    n_bad = 0
    for seed in range(40):  # two sessions of the same sensor: it holds (5 % false alarms)
        a = static_dwell_means(200, truth=truth, g=1.0, max_tilt_deg=None, sigma=3e-3,
                               rng=1000 + seed)
        cal = fit_quietly(a.means, 1.0).to_model()
        b = static_dwell_means(150, truth=truth, g=1.0, max_tilt_deg=None, sigma=3e-3,
                               rng=seed)
        r = diagnose(DwellSet(b.means), g=1.0, fit=cal, loo=False)
        c = r.calibration_check
        assert c is not None and c["test"] == "F" and (c["dof"], c["dof2"]) == (9, 141)
        n_bad += c["p_value"] < 0.05
        if c["p_value"] > 0.05:
            held = r.summary()
    assert n_bad <= 5  # 2 expected; 5 or more happens once in 20 runs of 40
    assert "p = n/a: 1 by construction" in held and "it holds on this session" in held
    # bz moved by 3 mg (the real session's 3.6 mg): named first, and the check fails.
    moved = truth.copy()
    moved[5] += 4e-3
    b = static_dwell_means(150, truth=moved, g=1.0, max_tilt_deg=None, sigma=3e-3, rng=40)
    r = diagnose(DwellSet(b.means), g=1.0, fit=cal, loo=False)
    c = r.calibration_check
    assert c["p_value"] < 1e-6 and c["moved"][0]["name"] == "bz"
    assert c["moved"][0]["delta"] == pytest.approx(4e-3, abs=1.2e-3)
    assert "it does NOT hold on this session" in r.summary()
    # With the noise known the statistic is chi2 on 9 parameters; a calibration without a
    # covariance is taken as exact.
    r = diagnose(DwellSet(mean=b.means, var=np.full_like(b.means, 9e-6), count=np.ones(150)), g=1.0,
                 fit=TriadModel(cal.K, cal.bias, units="g", g=1.0), loo=False)
    assert r.calibration_check["test"] == "chi2" and r.calibration_check["p_value"] < 1e-6
    # Too few dwells to refit: no check (the chi2 of the fixed calibration stands alone).
    assert diagnose(DwellSet(b.means[:8]), g=1.0, fit=cal, loo=False).calibration_check is None


def test_a_table_of_means_of_rounded_outputs_is_said_to_carry_their_rounding() -> None:
    """A real MPU-6050 table (107 means of 25 readings printed to 0.01 g, noise about 1 mg):
    61 % of the means are whole multiples of 0.01, so the rounding was not dithered away, and
    the structure verdict read 'attitude' (the rounding error is a function of the output).
    The report now says so; with noise of a few steps (dithered) it does not."""
    from accelcal.gap import table_grid
    from accelcal.sim.static import static_dwell_means

    truth = [1.01, 0.99, 1.0, 0.05, -0.03, 0.02, 0.0, 0.0, 0.0]
    s = static_dwell_means(150, truth=truth, g=1.0, max_tilt_deg=None, sigma=0.0, rng=5)
    rng = np.random.default_rng(6)
    for noise, said in ((1e-3, True), (2e-2, False)):
        samples = s.means[:, None, :] + rng.normal(0, noise, (150, 25, 3))
        means = np.round(samples, 2).mean(axis=1)
        grid = table_grid(means)
        assert grid is not None and (grid[0] == 0.01) == said, grid
        r = diagnose(DwellSet(means), g=1.0, loo=False)
        note = [x for x in r.statements if "whole multiples of 0.01" in x]
        assert bool(note) == said, r.statements
    assert note == [] and "may be that rounding" in "\n".join(
        diagnose(DwellSet(np.round(s.means, 2)), g=1.0, loo=False).statements)
    assert table_grid(np.random.default_rng(1).normal(0, 0.5, 300)) is None
    assert table_grid(np.round(np.random.default_rng(1).normal(0, 0.5, 300) * 16384)) == (1, 1)


def test_an_effect_that_predicts_held_out_rows_worse_is_said_to() -> None:
    """A real ICM-20948 table (1113 pose means, no noise given) whose first row after each move
    is noisier: 'best = settling (p 1.6e-62)' while the report's own held-out RMS rose from
    5.29 to 5.77 mg. Settling's column is non-zero on those few rows only, so the held-out gap
    G, which divides each error by its prediction's spread, fell as those predictions grew
    uncertain. Requiring the held-out error not to grow cut the real-noise top-1 of K2 and K3
    (docs/gap-validation.md) from 76-92 % to 23-36 %, whose few off-axis poses are such rows
    too; so the decision stands and the report says what it rests on."""
    truth = [1.02, 0.98, 1.01, 0.01, -0.02, 0.015, 0.001, -0.002, 0.001]
    rng = np.random.default_rng(7)
    u = rng.normal(size=(140, 3))
    u = np.repeat(u / np.linalg.norm(u, axis=1)[:, None], 8, axis=0)  # 8 rows per pose
    s = accelcal.sim.static.static_dwell_means(u, truth=truth, g=1.0, sigma=3.5e-3, rng=7)
    m = s.means.copy()
    m[::8] += rng.normal(0, 9e-3, (140, 3))  # the first row after each move: noisier
    r = diagnose(DwellSet(m), g=1.0)
    assert r.best == "settling" and r.rms_after > r.rms_before
    assert r.held_out_gap_after < r.held_out_gap
    assert any(x.startswith("with settling the held-out rows are predicted worse, not better")
               for x in r.statements), r.statements
    # A real effect predicts the held-out rows better: no such statement.
    g = gap_session(("k2",), rng=3, n_dwells=30, amplitudes=[40.0])
    ok = diagnose(g.dwells, g=g.g)
    assert ok.best == "k2" and ok.rms_after < ok.rms_before
    assert not any("predicted worse" in x for x in ok.statements)


def test_noise_that_differs_between_axes_is_said_and_row_order_is_not_time() -> None:
    """A real ADXL345 table on a two-axis bench (1295 pose means, no noise given, no times):
    its z axis is the noisiest (1.8 mg against 0.9 and 1.1), the report printed mean e^2 by
    pose axis 0.72 / 0.81 / 1.37 and then 'Structure: none'; and it called its row order a time
    order while drift was refused for want of times."""
    rng = np.random.default_rng(11)
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    truth = [1.0, 1.0, 1.0, 0.01, -0.02, 0.01, 0.0, 0.0, 0.0]
    s = accelcal.sim.static.static_dwell_means(u, truth=truth, g=1.0, sigma=0.0, rng=1)
    noisy = s.means + rng.normal(0, 1.0, s.means.shape) * [0.9e-3, 1.1e-3, 1.8e-3]
    r = diagnose(DwellSet(noisy), g=1.0, loo=False)
    note = [x for x in r.statements if x.startswith("the residuals' spread depends on the axis")]
    assert note and "give each axis's noise" in note[0], r.statements
    text = r.summary()
    assert "by row-order third" in text and "serial correlation (row order: no dwell times)" \
        in text
    # The same noise on every axis: nothing said.
    even = s.means + rng.normal(0, 1.2e-3, s.means.shape)
    assert not any("spread depends" in x
                   for x in diagnose(DwellSet(even), g=1.0, loo=False).statements)


def test_repeats_are_not_counted_on_a_densely_sampled_sphere() -> None:
    """Poses 3 deg apart on a bench are different poses: the fit no longer says that a
    quarter of the residuals 'show only how well a pose repeats'. Six faces placed twice
    still get the line."""
    from accelcal.static import fit_quietly

    i = np.arange(1200) + 0.5  # a Fibonacci sphere: nearest neighbours about 6 deg apart
    phi = np.arccos(1 - 2 * i / 1200)
    th = np.pi * (1 + 5**0.5) * i
    u = np.column_stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)])
    u = np.vstack([u, u[::4] + 0.02])  # and some dwells 1 deg off others
    u /= np.linalg.norm(u, axis=1)[:, None]
    dense = accelcal.sim.static.static_dwell_means(u, g=1.0, sigma=1e-4, rng=2)
    f = fit_quietly(dense.means, 1.0)
    assert f.distinct_poses < len(u) and "distinct poses" not in f.summary()
    faces = np.repeat(np.vstack([np.eye(3), -np.eye(3)]), 2, axis=0)
    faces = faces + 0.003 * np.random.default_rng(3).normal(size=faces.shape)
    six = accelcal.sim.static.static_dwell_means(
        faces / np.linalg.norm(faces, axis=1)[:, None], g=1.0, sigma=1e-4, rng=4)
    assert "the 12 dwells are at 6 distinct poses" in fit_quietly(six.means, 1.0,
                                                                 model="diag").summary()


def test_the_axis_spread_test_is_scipy_levene_about_the_medians() -> None:
    from accelcal.gap import _brown_forsythe
    from scipy.stats import levene

    rng = np.random.default_rng(4)
    for _ in range(20):
        g = [rng.normal(0, s, n) for s, n in ((1, 20), (rng.uniform(0.5, 2), 15), (1, 9))]
        assert _brown_forsythe(g) == pytest.approx(levene(*g, center="median").pvalue,
                                                   rel=1e-9, abs=1e-300)
        assert _brown_forsythe(g[:2]) == pytest.approx(
            levene(*g[:2], center="median").pvalue, rel=1e-9, abs=1e-300)


def test_the_diagnosis_runs_without_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    """SciPy is not a run-time dependency: the wheel's demo failed on the axis-spread test's
    F tail (scipy.special) in a clean venv. Every p-value of a diagnosis is the engine's."""
    import sys

    from accelcal.sim.static import static_dwell_means

    for name in [m for m in sys.modules if m == "scipy" or m.startswith("scipy.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "scipy", None)  # import scipy -> ImportError
    truth = [1.02, 0.98, 1.01, 0.01, -0.02, 0.015, 0.002, -0.001, 0.003]
    a = static_dwell_means(60, truth=truth, g=1.0, max_tilt_deg=None, sigma=1e-3, rng=1)
    cal = accelcal.fit_static(DwellSet(a.means, np.full(a.means.shape, 1e-4),
                                       np.full(60, 100)), 1.0).to_model()
    b = static_dwell_means(60, truth=truth, g=1.0, max_tilt_deg=None, sigma=1e-3, rng=2)
    for d in (DwellSet(b.means), DwellSet(b.means, np.full(b.means.shape, 1e-4),
                                          np.full(60, 100))):
        r = diagnose(d, g=1.0, fit=cal, loo=False)
        assert r.calibration_check is not None and math.isfinite(r.calibration_check["p_value"])
        assert diagnose(d, g=1.0).summary()


def test_a_fixed_calibration_checked_with_another_g_is_refused_or_named() -> None:
    """An exploratory test: `diagnose(d, g=1, fit=model)` against a calibration made in m/s^2
    gave "best = k3" at chi2/dof 5e10, and g 100 ppm off gave k3 without a word about g. Now
    a g in other units is refused (naming both), and a common offset of the calibrated norms
    is named with the g difference (not taken out: that made a real settling effect come with
    a spurious K3); the right g gives neither."""
    import warnings

    from accelcal.sim import field_session

    s1 = field_session(fs=200.0, n_dwells=24, dwell_s=8.0, move_s=3.0, max_tilt_deg=80, rng=2)
    s2 = field_session(fs=200.0, n_dwells=24, dwell_s=8.0, move_s=3.0, max_tilt_deg=80, rng=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        d1 = accelcal.detect_dwells(s1.samples, s1.fs, t=s1.t)
        model = accelcal.fit_static(d1, s1.g).to_model()
    d2 = accelcal.detect_dwells(s2.samples, s2.fs, t=s2.t)
    with pytest.raises(accelcal.CalibrationError,
                       match=r"g = 1, but the calibration was made with g = 9.80665 \(m/s\^2\)"):
        accelcal.diagnose(d2, g=1.0, fit=model)
    same = accelcal.diagnose(d2, g=s2.g, fit=model)
    assert not any("common offset" in x for x in same.statements)
    off = accelcal.diagnose(d2, g=s2.g * (1 + 1e-4), fit=model)
    text = [x for x in off.statements if "common offset" in x]
    assert len(text) == 1 and "-98.2 ppm of g off" in text[0] and "+100 ppm" in text[0], text
    assert "so check g before believing either of them" in text[0]
    assert "common offset" in off.summary()
    # Held fixed, a wrong g shows in the gap; the check then says the scales moved, and the
    # effects are tested against the refit (which absorbs g): no K3 is blamed for it.
    assert same.calibration_check["p_value"] >= 0.05
    assert "wrong_g" not in [b["effect"] for b in same.blind_spots]
    assert off.calibration_check["attribution"] == "refit" and off.best == "none"
    assert {m["name"] for m in off.calibration_check["moved"]} == {"sx", "sy", "sz"}
    assert not any("a significant gap remains" in x for x in off.statements)
    assert "wrong_g" in [b["effect"] for b in accelcal.diagnose(d2, g=s2.g).blind_spots]


def test_a_moved_calibration_is_not_blamed_on_an_attitude_effect() -> None:
    """A calibration whose bias moved by 10 std (or scale by 20 std) since it was made,
    checked against a clean session: "best = k2" (k3 for the scale) in 8 of 8 sessions, K2
    at -742+-63 ug/g^2 where the truth is 0, beside a check that named bx. Now, when the
    check says the calibration does not hold, the effects are tested against the session
    refitted: none for a moved calibration, and a real K2 or settling effect is still found;
    the gap figures stay the fixed calibration's."""
    found: dict[str, list[str]] = {"bx": [], "sy": [], "k2": [], "settling": []}
    for seed in range(4):
        s = gap_session((), n_dwells=30, rng=seed)
        for name, i, step in (("bx", 3, 10 * s.sigma), ("sy", 1, 20 * s.sigma / s.g)):
            v = s.nuisance.copy()
            v[i] += step
            r = diagnose(s.dwells, g=s.g, fit=accelcal.TriadModel.from_vector(v))
            assert r.calibration_check["attribution"] == "refit"
            assert r.calibration_check["moved"][0]["name"] == name
            assert r.chi2_per_dof > 20 and r.p_value < 1e-9  # the fixed calibration's gap
            found[name].append(r.best)
        for eff in ("k2", "settling"):
            e = gap_session([eff], n_dwells=30, rng=seed, amplitudes=[8.0])
            found[eff].append(diagnose(e.dwells, g=e.g,
                                       fit=accelcal.TriadModel.from_vector(e.nuisance)).best)
    assert found == {"bx": ["none"] * 4, "sy": ["none"] * 4, "k2": ["k2"] * 4,
                     "settling": ["settling"] * 4}, found
    moved = s.nuisance + np.r_[0, 0, 0, 10 * s.sigma, 0, 0, 0, 0, 0]
    text = diagnose(s.dwells, g=s.g, fit=accelcal.TriadModel.from_vector(moved)).summary()
    assert "the effects below are tested against the refit" in text
    assert "a moved bias looks like K2" in text


_TRUTH_24 = np.array([1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03])


def _checked_pair(seed: int, bz_moved_std: float = 0.0) -> Any:
    """A calibration from 24 dwells over the sphere (noise 1e-3 m/s^2 per dwell mean, its
    covariance and session kept) and the report of 24 other dwells checked against it; the
    second session's bz moved by ``bz_moved_std`` of the calibration's own std."""
    from accelcal.sim.static import static_dwell_means

    g = 9.81
    a = static_dwell_means(24, truth=_TRUTH_24, g=g, sigma=1e-3, sigma_g=0, max_tilt_deg=None,
                           rng=1000 + seed)
    cal = accelcal.fit_static(a.dwellset(), g, observability="ignore").to_model()
    tb = _TRUTH_24.copy()
    tb[5] += bz_moved_std * cal.std[5]
    b = static_dwell_means(24, truth=tb, g=g, sigma=1e-3, sigma_g=0, max_tilt_deg=None,
                           rng=9000 + seed)
    return diagnose(b.dwellset(), g=g, fit=cal)


def test_a_calibration_that_holds_names_no_effect_beyond_the_family_level() -> None:
    """A calibration that holds (same truth, no effect) checked on a new session: an effect
    was named in 41 of 200 sessions (K2, K3, settling) at a family-wise 5 %, because the
    effects were tested against each dwell's share of the calibration's error only, and that
    error, shared by the dwells and smooth in attitude, passes for them. Tested against the
    full covariance (generalised least squares): 5 of 200 (mc_check.py). 60 sessions here
    (2 named); Binomial(60, 0.05) exceeds 7 with probability 0.01 (a 20 % rate: 0.93)."""
    named = [r.best for r in (_checked_pair(s) for s in range(60)) if r.best != "none"]
    assert len(named) <= 7, named


def test_a_bias_moved_by_ten_of_its_std_is_not_named_k2() -> None:
    """The calibration of the test above, its bz moved by 10 of its own std (4 mm/s^2): the
    check rejects it in every session, and K2 (with K3) against it was named in 64 of 100
    sessions, because the effects were tested against each dwell's share of the
    calibration's error and the fixed calibration's BIC left out the log-determinant of that
    shared error (its chi2 was lowered by the larger variance, its likelihood not widened).
    Now 14 of 100 (mc_check.py); 30 sessions here (5 named, 25 refitted)."""
    reps = [_checked_pair(s, 10.0) for s in range(30)]
    assert all(r.calibration_check["p_value"] < 0.05 for r in reps)
    named = [r.best for r in reps if r.best != "none"]
    assert len(named) <= 8, named
    assert sum(r.calibration_check["attribution"] == "refit" for r in reps) >= 22



def _known_noise(means: np.ndarray, sig: float, **kw: Any) -> DwellSet:
    """Dwell means of 1000 samples each whose mean's noise is ``sig`` per axis."""
    k = len(means)
    return DwellSet(means, np.full((k, 3), sig**2 * 1000), np.full(k, 1000), **kw)


def _sphere_calibration() -> tuple[np.ndarray, float, Any]:
    """(truth, sigma, calibration) of a sensor calibrated on 40 dwells over the sphere, its
    noise known: a calibration that holds, to check on other sessions of it."""
    from accelcal.sim.static import static_dwell_means

    tr = np.array([1.02, 0.98, 1.01, 0.01, -0.02, 0.015, 0.002, -0.001, 0.003])
    sig = 1e-3
    first = static_dwell_means(40, truth=tr, g=1.0, max_tilt_deg=None, sigma=sig, rng=1)
    return tr, sig, accelcal.fit_static(_known_noise(first.means, sig), 1.0).to_model()


def test_a_real_effect_on_a_small_session_is_not_lost_to_a_refit() -> None:
    """A calibration that holds, checked on 12 dwells with a real K2 (1e4 ug/g^2 on x): K2
    pulls the refit away, the check rejects the calibration, and the refit of 12 dwells had
    no room left for K2: named in 1 of 12 sessions (12 of 12 before the refit attribution).
    Now the explanation with the lower BIC attributes: K2 against the calibration, with a
    note that on these poses K2 and a moved calibration look alike; a moved bias with no
    effect is still not called K2 on 30 dwells (the test above)."""
    from accelcal.sim.static import static_dwell_means

    tr, sig, cal = _sphere_calibration()
    named = 0
    for seed in range(6):
        ses = static_dwell_means(12, truth=tr, g=1.0, max_tilt_deg=60, sigma=sig,
                                 rng=1000 + seed)
        m = ses.means + 0.01 * ((ses.force * tr[:3]) ** 2) * [1, 0, 0]
        d = _known_noise(m, sig, t=np.arange(12) * 60.0)
        r = diagnose(d, g=1.0, fit=cal)
        named += r.best == "k2"
        if r.calibration_check["attribution"] == "fixed":
            c = r.calibration_check
            assert c["bic_fixed"] <= c["bic_refit"]
            assert "tested against the calibration, which with them explains" in r.summary()
    assert named == 6
    note = next(x for x in r.statements if "BIC" in x)
    assert "k2 may also be the calibration having moved" in note, note


def test_dwell_times_from_a_reset_clock_are_not_used() -> None:
    """Six files joined, each with its clock from 0: every dwell time about 2.28 s, and
    diagnose called drift "testable" (0.000774+-0.00059 ug/h) and sorted the dwells by those
    times. Now detected dwells whose times step back in the sample order have no times: drift
    is not testable, the dwells keep their sample order, and the report says why; the
    caller's DwellSet is not changed. A table of means without sample indices is still put in
    time order."""
    s = gap_session(("drift",), n_dwells=24, rng=5, amplitudes=[20.0])
    d = s.dwells
    k = len(d)
    start = np.arange(k) * 1000
    t = np.asarray(d.t, dtype=np.float64).copy()
    t[k // 2:] -= t[k // 2] - 1.0  # the clock restarted half way
    joined = DwellSet(d.mean, d.var, d.count, t, d.temperature, start=start, stop=start + 900)
    r = diagnose(joined, g=s.g)
    assert np.array_equal(joined.t, t)
    assert next(e for e in r.effects if e["effect"] == "drift")["status"] == "no_time"
    assert any("step back 1 time(s) from one dwell to the next" in x for x in r.statements)
    drift = next(b for b in r.blind_spots if b["effect"] == "drift")
    assert "the dwell times were dropped, since they step back" in drift["reason"], drift
    np.testing.assert_array_equal(r.dwells["index"], np.arange(k))
    one_clock = diagnose(DwellSet(d.mean, d.var, d.count, d.t, d.temperature, start=start,
                                  stop=start + 900), g=s.g)
    assert one_clock.best == "drift"
    table = diagnose(DwellSet(d.mean, d.var, d.count, t, d.temperature), g=s.g)
    assert not any("step back" in x for x in table.statements)
    np.testing.assert_array_equal(table.dwells["index"], np.argsort(t, kind="stable"))


def test_a_centrifuge_radius_error_is_named_not_called_blind() -> None:
    """A 0.2 mm radius error on a 1 m arm at 1e-6 g noise: chi2/dof 600, radius_error
    "blind" (its direction outside the scale factors has sine 0.004, under the 0.05 absorbed
    limit) and rate_offset named instead (-30+-3.9 urad/s), in 20 of 20 sessions. Now the
    centrifuge counts a direction absorbed below a sine of 1e-3: the radius error is named with
    its size, a relative rate error (the same column) too, and the null and Earth-rate
    sessions keep their verdicts."""
    from accelcal.sim import centrifuge_session

    for seed in range(3):
        s = centrifuge_session(noise_g=1e-6, radius_error=2e-4, rng=seed)
        r = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, g=s.g, sigma=1e-6)
        assert r.best == "radius_error", (seed, r.best)
        e = next(x for x in r.effects if x["effect"] == "radius_error")
        assert abs(e["estimate"][0] - 0.2) < 4 * e["std"][0] + 1e-3, e  # mm
        fixed = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius + 2e-4, g=s.g,
                                             sigma=1e-6)
        assert fixed.best == "none" and fixed.chi2_per_dof < 2
        rel = centrifuge_session(noise_g=1e-6, rate_error=1e-4, rng=seed)
        assert accelcal.diagnose_centrifuge(rel.outputs, rel.omega, rel.radius, g=rel.g,
                                            sigma=1e-6).best == "radius_error"
        earth = centrifuge_session(noise_g=1e-6, latitude_deg=45.0, rng=seed)
        assert accelcal.diagnose_centrifuge(earth.outputs, earth.omega, earth.radius,
                                            g=earth.g, sigma=1e-6).best == "rate_offset"
        null = centrifuge_session(noise_g=1e-6, rng=seed)
        assert accelcal.diagnose_centrifuge(null.outputs, null.omega, null.radius, g=null.g,
                                            sigma=1e-6).best == "none"


def test_a_start_given_as_values_is_checked_by_what_is_wrong() -> None:
    """fit=[nan]*9 said "... the 9 values ...; got list" (the NaN was the problem), and the
    6 values of a scale-and-bias start were refused. Now a NaN is named, and 6 values start
    a fit as 9 with no misalignment do."""
    s = gap_session((), n_dwells=30, rng=1)
    with pytest.raises(accelcal.CalibrationError, match=r"fit holds NaN or inf"):
        diagnose(s.dwells, g=s.g, fit=[np.nan] * 9)
    with pytest.raises(accelcal.CalibrationError, match=r"or the 6 .* of a start; got 3 values"):
        diagnose(s.dwells, g=s.g, fit=[1, 2, 3])
    with pytest.raises(accelcal.CalibrationError, match=r"scale factors .* must be positive"):
        diagnose(s.dwells, g=s.g, fit=[-s.nuisance[0], *s.nuisance[1:]])
    six = diagnose(s.dwells, g=s.g, fit=s.nuisance[:6].tolist())
    nine = diagnose(s.dwells, g=s.g, fit=[*s.nuisance[:6], 0, 0, 0])
    assert six.chi2 == nine.chi2 and six.best == nine.best == "none"


def test_a_calibration_that_holds_is_not_rejected_on_a_weak_session() -> None:
    """A calibration from 40 dwells over the sphere checked on sessions of 10 dwells within
    +-30 deg, nothing moved: "it does NOT hold" in 13 of 30 sessions, since the weak refit's
    linearised covariance is far narrower than its spread. Now the weak refit's spread is
    bootstrapped as the calibration's is (benches/validate_calibration_check.py)."""
    import warnings

    from accelcal.sim.static import static_dwell_means

    tr, sig, cal = _sphere_calibration()
    rejected = 0
    for seed in range(30):
        s = static_dwell_means(10, truth=tr, g=1.0, max_tilt_deg=30, sigma=sig, rng=1000 + seed)
        d = _known_noise(s.means, sig)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", accelcal.WeakDesignWarning)
            c = diagnose(d, g=1.0, fit=cal, loo=False).calibration_check
        rejected += c is not None and c["p_value"] < 0.05
    assert rejected <= 5, rejected  # 13 of 30 with the linearised covariance


def test_centrifuge_sigma_means_what_fit_centrifuge_takes() -> None:
    """A scalar sigma was the norm residual's std in diagnose_centrifuge but the per-axis
    output noise in fit_centrifuge: the same value gave chi2/dof 2.57 (p = 6e-9, "a gap")
    on a clean session of scale 0.5. Now a scalar or (k,) is the output noise as in the fit
    (identical to the (k, 3) array), and sigma_norm= keeps the other meaning."""
    from accelcal.sim import centrifuge_session

    s = centrifuge_session(noise_g=1e-6, rng=1, g=9.8, scale=[0.5, 0.5, 0.5])
    kw: dict[str, Any] = {"g": 9.8, "spin_axis": s.spin_axis, "loo": False}
    scalar = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, sigma=1e-6, **kw)
    full = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius,
                                        sigma=np.full(s.outputs.shape, 1e-6), **kw)
    rows = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius,
                                        sigma=np.full(len(s.omega), 1e-6), **kw)
    assert scalar.chi2 == full.chi2 == rows.chi2 and scalar.p_value > 0.05
    norm = accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, sigma_norm=1e-6, **kw)
    assert norm.chi2 == pytest.approx(4 * scalar.chi2, rel=0.05)  # the norm's noise is 2e-6
    with pytest.raises(CalibrationError, match="not both"):
        accelcal.diagnose_centrifuge(s.outputs, s.omega, s.radius, sigma=1e-6, sigma_norm=1e-6,
                                     **kw)


def test_an_effect_named_beside_untestable_ones_is_reported_ambiguous_with_them():
    # 12 dwells: a hidden temperature bias (3 directions) cannot be tested beside the 9
    # calibration parameters, while K2 or K3 (2 identifiable directions) can, and may take the
    # gap. Before: 'best = k2' with no word that the truth was never tested.
    wrong = 0
    for seed in range(40):
        s = gap_session(("temperature_bias",), rng=seed, amplitudes=[40.0], n_dwells=12)
        r = diagnose(s.dwells, g=s.g)
        status = {e["effect"]: e["status"] for e in r.effects}
        assert status["temperature_bias"] in ("too_few_dwells", "selected", "testable")
        if r.best not in ("none", "temperature_bias"):
            wrong += 1
            amb = [a for a in r.ambiguous if "temperature_bias" in a["effects"]]
            assert amb and amb[0]["effects"][0] == r.best, seed
            assert "more dwells" in amb[0]["experiment"]
            assert "not testable beside it" in r.summary()
    assert wrong >= 1  # the case occurs in these sessions


def test_a_noise_model_far_too_pessimistic_is_said():
    # The dwells' noise given 4x too large in std: chi2/dof about 1/16.
    s = gap_session((), rng=7, n_dwells=30)
    d = s.dwells[:]
    d.var = d.var * 16.0
    r = diagnose(d, g=s.g, noise_model="white")
    assert r.chi2_per_dof < 0.2
    assert any("too pessimistic" in st for st in r.statements)
    ok = diagnose(s.dwells, g=s.g, noise_model="white")
    assert not any("too pessimistic" in st for st in ok.statements)


@pytest.mark.parametrize("n_dwells", [13, 14])
def test_a_small_session_with_understated_noise_names_no_effect_it_cannot_check(n_dwells):
    # Null sessions whose noise is 2x the stated: after a 3-parameter candidate 1 or 2
    # degrees of freedom remain, too few to check the noise model, so the automatic test is
    # the sigma-free F test there (before: the chi2 test trusted the understated noise and an
    # effect was named in most such sessions).
    named = sum(
        diagnose(gap_session((), rng=s, n_dwells=n_dwells, noise_scale=2.0).dwells,
                 g=9.80665).best != "none"
        for s in range(60))
    assert named <= 12


def test_excess_remaining_only_beyond_chance() -> None:
    """A table of means with the noise unknown has a held-out gap G of 1 by construction: the
    share of its 'excess' an effect leaves is a ratio of noise and is not reported (a hand-
    turned BNO055 table printed 'excess remaining -58.45' from G 1.00026 -> 0.985); a real
    excess still gets its share."""
    from accelcal.gap import _chance_excess

    assert _chance_excess(50) == pytest.approx(0.2)
    s = gap_session(("drift",), rng=8, amplitudes=[30.0])
    rep = diagnose(DwellSet(np.asarray(s.dwells.mean)), g=s.g)  # means only: noise unknown
    assert abs(rep.held_out_gap - 1.0) < _chance_excess(rep.n)
    assert math.isnan(rep.excess_remaining)
    assert "excess remaining n/a: no held-out excess beyond chance" in rep.summary()
    strong = diagnose(s.dwells, g=s.g)
    assert strong.held_out_gap > 1.0 + _chance_excess(strong.n)
    assert -0.05 < strong.excess_remaining < 0.5


def test_a_report_records_the_settings_that_made_it() -> None:
    """to_dict() and summary() did not say which preset (nor alpha, test, correction,
    n_draws ...) made a report, though the preset changes the verdict."""
    s = gap_session(("k2",), rng=5, amplitudes=[4.0], noise_scale=1.5)
    a = diagnose(s.dwells, g=s.g)
    b = diagnose(s.dwells, g=s.g, preset="conservative", alpha=0.01, n_draws=500,
                 correction="bonferroni", test="chi2")
    assert a.settings == {"preset": "targeted", "alpha": 0.05, "test": "auto",
                          "correction": "minp", "n_draws": 4000, "trust_level": 0.02,
                          "gate": "auto", "gate_margin": 1.0, "max_effects": 3, "loo": True,
                          "random_offset": False}
    assert b.settings == {**a.settings, "preset": "conservative", "alpha": 0.01,
                          "test": "chi2", "correction": "bonferroni", "n_draws": 500,
                          "trust_level": 0.1, "gate_margin": 0.0}
    assert b.summary().splitlines()[-1] == (
        "Settings: preset conservative, alpha 0.01, test chi2, correction bonferroni, "
        "n_draws 500, trust_level 0.1, gate auto, gate_margin 0, max_effects 3, loo")
    d = json.loads(json.dumps(b.to_dict()))
    assert d["settings"] == b.settings
    back = accelcal.GapReport.from_dict(d)
    assert back == b and back.settings == b.settings
    # A report rebuilt from a dict written before settings were recorded: none, no line.
    old = {k: v for k, v in a.to_dict().items() if k != "settings"}
    rebuilt = accelcal.GapReport.from_dict(old)
    assert rebuilt.settings == {} and not rebuilt.summary().splitlines()[-1].startswith("Sett")


# ----------------------------------------------------------------------------------------------
# Ambiguity of significant runners-up, centrifuge drift and unseen components, the figures of
# the summary's lines.


@pytest.mark.parametrize(("effect", "seed", "amp"), [("settling", 68, (2.0, 20.0)),
                                                     ("temperature_scale", 65, (1.0, 8.0)),
                                                     ("temperature_bias", 32, (1.0, 8.0))])
def test_a_significant_runner_up_close_in_bic_is_reported_ambiguous(
        effect: str, seed: int, amp: tuple[float, float]) -> None:
    """Weak effects named as another (settling as K3 at p 1e-6) while the injected effect was
    significant on its own with a BIC close to the best's: the report says the two are not
    told apart, whatever the cosine between their columns."""
    s = gap_session(effect, rng=seed, amp_range=amp)
    r = diagnose(s.dwells, g=s.g)
    assert r.best != effect  # the case: another effect has the smallest p
    amb = [a for a in r.ambiguous if effect in a["effects"]]
    assert amb and amb[0]["effects"][0] == r.best, r.ambiguous
    assert amb[0]["rule"] == "both_significant" and amb[0]["cosine"] < 0.9
    assert amb[0]["pair_weight"][effect] < 0.9933
    p_other = next(e["p_value"] for e in r.effects if e["effect"] == effect)
    assert amb[0]["significant"][effect] == p_other < 0.05 / 6
    line = next(x for x in r.summary().splitlines() if x.startswith("Ambiguous:"))
    assert f"{r.best} / {effect}" in line and "significant on their own" in line
    # A strong effect leaves no significant runner-up close to it.
    s = gap_session(("drift",), rng=8, amplitudes=[30.0])
    r = diagnose(s.dwells, g=s.g)
    assert r.best == "drift" and not r.ambiguous


def _spin_y0_session(lever: np.ndarray, rng: int, drift: np.ndarray | None = None,
                     ) -> tuple[np.ndarray, Any]:
    """The tester's own centrifuge physics on the paper design (its spin axis has no y
    component): accelerometer i at body offset lever[i] (m), outputs b + S f + K2 f^2, noise
    1e-6 g, plus an optional bias drift[i] (output units) over the run."""
    from accelcal.centrifuge import paper_design

    des = paper_design(radius=1.0)
    g = 9.8
    w, c1, c3 = des.omega, des.radial, des.spin_axis
    out = np.empty((len(w), 3))
    for i, (s_, b_, k2) in enumerate(zip((1.29, 1.21, 1.26), (0.213, 0.256, 0.516),
                                         (0.57e-4, 0.31e-4, 0.45e-4), strict=True)):
        perp = lever[i][None, :] - (c3 @ lever[i])[:, None] * c3
        f = (w**2 * des.radius / g)[:, None] * c1 - (w**2 / g)[:, None] * perp + c3
        out[:, i] = b_ + s_ * f[:, i] + k2 * f[:, i] ** 2
    out += np.random.default_rng(rng).normal(scale=1e-6, size=out.shape)
    if drift is not None:
        out += np.outer(np.linspace(-0.5, 0.5, len(w)), drift)
    return out, des


def test_centrifuge_drift_is_tested_with_row_times_and_a_blind_spot_without() -> None:
    """A bias drift over the run was blamed on a lever arm at p 3e-7 (no time input): with the
    row times it is named; without them the report says time effects are not tested."""
    amp = 2e-5 * np.array([1.0, -0.6, 0.8])  # output units over the 1 h run
    out, des = _spin_y0_session(np.zeros((3, 3)), 3, drift=amp)
    t = np.linspace(0.0, 3600.0, len(des.omega))
    kw: dict[str, Any] = {"g": 9.8, "spin_axis": des.spin_axis, "sigma": 1e-6}
    r = accelcal.diagnose_centrifuge(out, des.omega, des.radius, t=t, **kw)
    assert r.best == "drift"
    est = next(e for e in r.effects if e["effect"] == "drift")
    truth = 1e6 * amp / np.array([1.29, 1.21, 1.26])  # ug/h
    assert np.all(np.abs(est["estimate"] - truth) < 5 * est["std"] + 0.1 * np.abs(truth))
    r0 = accelcal.diagnose_centrifuge(out, des.omega, des.radius, **kw)
    assert r0.best != "drift"
    reason = {b["effect"]: b["reason"] for b in r0.blind_spots}["drift"]
    assert "no row times" in reason and "no time effect" in reason
    assert "Blind spot: drift: not testable: no row times" in r0.summary()
    # A null session with times: no drift named.
    out, des = _spin_y0_session(np.zeros((3, 3)), 4)
    assert accelcal.diagnose_centrifuge(out, des.omega, des.radius, t=t, **kw).best == "none"
    with pytest.raises(CalibrationError, match="t must have 60 values"):
        accelcal.diagnose_centrifuge(out, des.omega, des.radius, t=t[:5], **kw)


def test_centrifuge_components_the_design_cannot_see_are_not_determined() -> None:
    """With no y component of the spin axis the across-axis lever arms x:y, y:x, y:z and z:y
    have zero columns: not "0 +- 9e-15 mm" but not determined, and said so."""
    lever = np.zeros((3, 3))
    lever[0, 2] = -0.003  # accelerometer x 3 mm along body z: seen
    out, des = _spin_y0_session(lever, 1)
    r = accelcal.diagnose_centrifuge(out, des.omega, des.radius, g=9.8,
                                     spin_axis=des.spin_axis, sigma=1e-6)
    assert r.best == "lever_across"
    e = next(x for x in r.effects if x["effect"] == "lever_across")
    unseen = [0, 2, 3, 5]
    assert np.all(np.isnan(e["estimate"][unseen])) and np.all(np.isnan(e["std"][unseen]))
    assert abs(e["estimate"][1] + 3.0) < 5 * e["std"][1] + 1e-3
    blind = {b["effect"] for b in r.blind_spots}
    assert "lever_across (x:y, y:x, y:z, z:y)" in blind
    line = next(x for x in r.summary().splitlines() if x.strip().startswith("lever_across"))
    assert line.count("n/a") == 4 and not any(f"e-{k}" in line for k in (13, 14, 15, 16))
    # Not selected: the screening estimate says the same.
    out, des = _spin_y0_session(np.zeros((3, 3)), 2)
    r = accelcal.diagnose_centrifuge(out, des.omega, des.radius, g=9.8,
                                     spin_axis=des.spin_axis, sigma=1e-6)
    e = next(x for x in r.effects if x["effect"] == "lever_across")
    assert e["status"] == "testable" and np.all(np.isnan(e["estimate"][unseen]))
    assert "lever_across (x:y, y:x, y:z, z:y)" in {b["effect"] for b in r.blind_spots}


def test_azimuth_errors_shrink_line_uses_the_in_sample_chi2() -> None:
    """Per-dwell azimuth errors cannot be predicted for a held-out dwell: the held-out gap
    barely moves although they explain the data; the line says so and its excess remaining
    is the in-sample chi2's."""
    az, y, t, _ = _grad(3, azimuth_error_deg=1.0)
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5)
    assert r.best == "azimuth_error"
    assert r.remaining["p"] > 1e-3 and r.held_out_gap_after > 0.5 * r.held_out_gap
    gi = (math.sqrt(r.chi2 / r.dof), math.sqrt(r.remaining["chi2"] / r.remaining["dof"]))
    assert r.excess_remaining == pytest.approx((gi[1] - 1) / (gi[0] - 1))
    held = (r.held_out_gap_after - 1) / (r.held_out_gap - 1)  # what the line said before
    assert r.excess_remaining < 0.4 < 0.8 < held
    line = next(x for x in r.summary().splitlines() if x.startswith("How far it shrinks"))
    assert "cannot credit azimuth_error" in line and "in-sample" in line
    # Other effects keep the held-out figure.
    az, y, t, _ = _grad(2, drift_E_per_s=(2e-3, -1.5e-3))
    r = accelcal.diagnose_gradiometer(az, y, t=t, sigma=0.5, effects=["drift"])
    assert r.excess_remaining == pytest.approx(
        (r.held_out_gap_after - 1) / (r.held_out_gap - 1))


def test_the_p_of_an_effect_selected_later_is_its_step_p() -> None:
    s = gap_session(("drift", "temperature_bias"), rng=1, amplitudes=[10.0, 6.0])
    r = diagnose(s.dwells, g=s.g, loo=False)
    assert r.selected[:2] == ["drift", "temperature_bias"]
    e = next(x for x in r.effects if x["effect"] == "temperature_bias")
    assert e["p_value"] > 0.1 and e["p_step"] == r.raw["step_p"][1] < 1e-10
    line = next(x for x in r.summary().splitlines() if x.strip().startswith("temperature_bias"))
    assert "selected at step 2" in line and f"{e['p_step']:9.2g}" in line
    assert "its test at that step" in r.summary()


def test_cli_plot_has_the_allan_curve(tmp_path: Any) -> None:
    """The CLI's streaming pass keeps no samples: the noise panel's Allan curve is read
    again for --plot, as the Python path computes it."""
    pytest.importorskip("matplotlib")
    from accelcal.cli import main
    from accelcal.sim import field_session
    from click.testing import CliRunner

    fs_ = field_session(fs=100.0, n_dwells=14, dwell_s=4.0, move_s=2.0, max_tilt_deg=80.0,
                        sigma=1e-3, rng=4)
    rec = tmp_path / "rec.csv"
    np.savetxt(rec, np.column_stack([fs_.t, fs_.samples]), delimiter=",",
               header="t,ax,ay,az", comments="")
    out = CliRunner().invoke(main, ["diagnose", str(rec), "--g", f"{fs_.g}", "--plot",
                                    str(tmp_path / "gap.png"), "--json"])
    assert out.exit_code == 0, out.output
    nc = json.loads(out.output)["noise_curves"]
    assert len(nc["tau"]) > 3 and np.asarray(nc["adev"]).shape == (len(nc["tau"]), 3)
    # White noise of 1e-3 at 100 Hz: the Allan deviation at the shortest tau is about it.
    assert 0.5e-3 < np.asarray(nc["adev"])[0].mean() < 2e-3
    assert "std_allan" in nc and (tmp_path / "gap.png").stat().st_size > 0


def test_a_moved_calibration_shrink_line_separates_the_refit_from_the_effect() -> None:
    """Against a moved calibration the starting G is mostly the calibration's: the line goes
    from the calibration as given through the refit alone to the refit with its effects."""
    from accelcal import TriadModel

    s = gap_session(("k2",), rng=31, n_dwells=24, amplitudes=[20.0])
    t = s.nuisance
    K = np.array([[t[0], 0, 0], [t[6], t[1], 0], [t[7], t[8], t[2]]])
    r = diagnose(s.dwells, g=s.g,
                 fit=TriadModel(K * (1 + np.diag([8e-4, 0, 0])), t[3:6] + [0, 0, 6e-3]))
    cc = r.calibration_check
    assert cc is not None and cc["attribution"] == "refit" and r.best == "k2"
    assert r.held_out_gap_after < cc["g_refit"] < 0.5 * r.held_out_gap
    line = next(x for x in r.summary().splitlines() if x.startswith("How far it shrinks"))
    assert (f"{r.held_out_gap:.2f} (the calibration as given) -> {cc['g_refit']:.2f} "
            "(refitted, no effect") in line and "refitted with k2" in line

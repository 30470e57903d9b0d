"""Sim-to-real gap diagnosis: checked against the withheld-effect generator's truth."""

from __future__ import annotations

import json
import math

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
    assert len(fig.axes) == 3


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
    with pytest.raises(CalibrationError, match="positive gravity"):
        diagnose(s.dwells, g=-1.0)
    # Few dwells: a gap figure but no effect test.
    r = diagnose(s.dwells[:11], g=s.g)
    assert any("too few dwells" in x for x in r.statements)
    assert r.best == "none"
    # No variance: sigma-free F tests only, stated.
    d = s.dwells
    r = diagnose(DwellSet(d.mean, t=d.t, temperature=d.temperature), g=s.g, loo=False)
    assert math.isnan(r.p_value) and "not testable" in r.noise_model


def test_mis_scaled_noise_flags_gap_not_an_effect() -> None:
    alarms = 0
    for seed in range(30):
        s = gap_session((), rng=100 + seed, noise_scale=2.0)
        r = diagnose(s.dwells, g=s.g, loo=False)
        alarms += r.best != "none"
        assert r.chi2_per_dof > 1.5 or seed % 10  # the gap itself is visible
    assert alarms <= 6


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

"""Field-session simulator and the dwell pipeline against its truth."""

from __future__ import annotations

import accelcal as ac
import numpy as np
import pytest
from accelcal.sim import field_session, gravity_from_tilts, triad_matrix


def test_noise_free_dwell_means_equal_the_model() -> None:
    s = field_session(fs=200.0, n_dwells=6, dwell_s=3.0, move_s=1.0, sigma=0.0, rng=1)
    d = ac.dwell_stats(s.samples, s.bounds, fs=s.fs)
    a = gravity_from_tilts(np.radians(s.tilts_deg[:, 0]), np.radians(s.tilts_deg[:, 1]), s.g)
    expect = a @ triad_matrix(s.truth).T + s.truth[3:6]
    np.testing.assert_allclose(d.mean, expect, rtol=0, atol=1e-12)
    # Calibrating with the truth gives |a| = g exactly.
    cal = np.linalg.solve(triad_matrix(s.truth), (d.mean - s.truth[3:6]).T).T
    np.testing.assert_allclose(np.linalg.norm(cal, axis=1), s.g, rtol=1e-14)


def test_detected_dwells_lie_inside_true_static_intervals() -> None:
    s = field_session(fs=1000.0, n_dwells=8, dwell_s=5.0, move_s=2.0, rng=3)
    d = ac.detect_dwells(s.samples, s.fs)
    assert len(d) == 8
    assert d.start is not None and d.stop is not None
    for a, b in zip(d.start, d.stop, strict=True):
        assert np.any((s.bounds[:, 0] <= a) & (b <= s.bounds[:, 1])), (a, b)
    # Noise estimated from the data is the simulated one.
    assert d.noise_std is not None
    np.testing.assert_allclose(d.noise_std, s.sigma, rtol=0.05)


def test_bad_simulator_settings() -> None:
    with pytest.raises(ac.CalibrationError, match="fs"):
        field_session(fs=0.0)
    with pytest.raises(ac.CalibrationError, match="truth"):
        field_session(fs=100.0, n_dwells=2, dwell_s=1.0, truth=[1.0, 2.0])

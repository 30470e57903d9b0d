"""Shared test helpers.

``shared_data(*parts)`` is the one way tests reach the reference recordings, which live in
``../shared/data`` beside the checkout (CI lays it out that way): it returns the path, or skips
the calling test with a clear reason when the folder is absent (a bare source checkout).
``dask_client`` is a real two-worker Dask cluster (separate processes) for the session.
``clipped_session`` simulates a recording whose output saturates at the sensor's range,
``vibrating_session`` one in which a pump vibrates the sensor for part of the session, and
``write_csv`` writes a recording as ``t,ax,ay,az`` text.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from accelcal.sim.field import field_session
from hypothesis import HealthCheck, settings

# Hypothesis profiles: "default" is fast and derandomised (CI gives the same cases every run);
# HYPOTHESIS_PROFILE=slow draws many more cases on demand. Tests that set no max_examples of
# their own follow the profile.
settings.register_profile(
    "default", max_examples=60, derandomize=True, deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile(
    "slow", max_examples=2000, deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
SHARED_DATA = SHARED / "data"


def shared_data(*parts: str) -> Path:
    """Path of ``../shared/data/<parts>``; skips the calling test when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(
            f"reference data {p} is not present: the real recordings live in ../shared/data "
            "beside the repository (as in CI)"
        )
    return p


def shared_root() -> Path:
    """``../shared`` itself (the docs tests lay out a scratch copy around it)."""
    if not SHARED_DATA.exists():
        pytest.skip(f"{SHARED} is not present beside the repository")
    return SHARED


@pytest.fixture(scope="session")
def dask_client() -> Iterator[Any]:
    """A real two-process Dask cluster (LocalCluster, processes=True), shared by the session."""
    import distributed

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster:
        with distributed.Client(cluster) as client:
            yield client


COUNTS_PER_MPS2 = 16384 / 9.80665  # an int16 +-2 g sensor


def clipped_session(rail_g: float = 0.95, seed: int = 3) -> tuple[Any, np.ndarray, dict[int, str]]:
    """A simulated field session in int16 counts whose outputs are clipped at +-rail_g g, and
    the truth: the dwells whose noise-free value lies beyond the rail on some axis (by more
    than 6 sample deviations; the seed is chosen so that no dwell lies within 6 of it)."""
    s = field_session(fs=200, n_dwells=24, dwell_s=30, move_s=4, max_tilt_deg=80, sigma=3e-3,
                      rng=seed)
    rail = rail_g * 16384
    sd = 3e-3 * COUNTS_PER_MPS2
    x = np.clip(np.round(s.samples * COUNTS_PER_MPS2), -rail, rail).astype(np.int16)
    truth = {}
    for k, (a, b) in enumerate(s.bounds):
        clean = s.samples[a:b].mean(axis=0) * COUNTS_PER_MPS2
        assert not np.any(np.abs(np.abs(clean) - rail) < 6 * sd), (k, clean)
        if np.any(np.abs(clean) > rail):
            truth[k] = "saturated_high" if clean[np.argmax(np.abs(clean))] > 0 else "saturated_low"
    return s, x, truth


def vibrating_session(n_dwells: int = 16, dwell_s: float = 20.0, move_s: float = 4.0,
                      after: float = 0.5, axes: Any = (1.0, 0.5, 0.3)) -> tuple[Any, np.ndarray]:
    """A 500 Hz field session (noise 1e-3 m/s^2) and its samples with a 30 Hz vibration of
    5e-3 m/s^2 (times ``axes``) from the fraction ``after`` of the session on."""
    s = field_session(fs=500.0, n_dwells=n_dwells, dwell_s=dwell_s, move_s=move_s,
                      max_tilt_deg=80, sigma=1e-3, rng=5)
    t = s.t
    vib = 5e-3 * np.sin(2 * np.pi * 30 * t)[:, None] * np.asarray(axes, dtype=np.float64)
    return s, s.samples + (t > after * t[-1])[:, None] * vib


def write_csv(path: Path, t: np.ndarray, x: np.ndarray, fmt: Any = "%.7f") -> Path:
    """``t,ax,ay,az`` text with a header line."""
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", header="t,ax,ay,az", comments="",
               fmt=fmt)
    return path

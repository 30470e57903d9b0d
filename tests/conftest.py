"""Shared test helpers.

``shared_data(*parts)`` is the one way tests reach the reference recordings, which live in
``../shared/data`` beside the checkout (CI lays it out that way): it returns the path, or skips
the calling test with a clear reason when the folder is absent (a bare source checkout).
``dask_client`` is a real two-worker Dask cluster (separate processes) for the session.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
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

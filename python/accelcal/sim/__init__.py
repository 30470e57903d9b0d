"""Simulators for all three systems, with known truth (every method is tested against them).

- :func:`field_session`: a static field calibration session as a raw high-rate stream.
- :func:`static_dwell_means`: dwell means of a static session (the norm-observation paper's
  simulation settings).
- :func:`centrifuge_session`: centrifuge runs with K2 terms and unmodelled error sources.
- :func:`gradiometer_session`: a rotating-accelerometer gradiometer start-up.
- :func:`gap_session`: static sessions with hidden effects, for checking the gap diagnosis.
"""

from __future__ import annotations

from numpy.typing import ArrayLike, NDArray

from .._triad import gravity_from_tilts, k_matrix
from .centrifuge import centrifuge_session
from .field import FIELD_TRUTH, SEED000_TRUTH, FieldSession, field_session
from .gap import gap_session
from .gradiometer import gradiometer_session
from .static import static_dwell_means

__all__ = [
    "centrifuge_session",
    "gap_session",
    "gradiometer_session",
    "static_dwell_means",
    "FIELD_TRUTH",
    "SEED000_TRUTH",
    "FieldSession",
    "field_session",
    "gravity_from_tilts",
    "triad_matrix",
]


def triad_matrix(vector: ArrayLike) -> NDArray:  # type: ignore[type-arg]
    """``K`` (3, 3), lower triangular, from ``[sx, sy, sz, bx, by, bz, m1, m2, m3]``."""
    return k_matrix(vector, "lower")

"""Simulators for all three systems, with known truth.

- :func:`field_session`: static field calibration (seed 000), raw high-rate stream.
- ``static_dwell_means``: the seed-000 paper's dwell-mean simulation.
- ``centrifuge_session``: centrifuge runs with K2 terms (seed 004).
- ``gradiometer_session``: rotating-accelerometer gradiometer start-up (seed 003).
"""

from .sim_centrifuge import centrifuge_session
from .sim_field import SEED000_TRUTH, FieldSession, field_session, gravity_from_tilts, triad_matrix
from .sim_gap import gap_session
from .sim_gradiometer import gradiometer_session

__all__ = [
    "centrifuge_session",
    "gap_session",
    "gradiometer_session",
    "SEED000_TRUTH",
    "FieldSession",
    "field_session",
    "gravity_from_tilts",
    "triad_matrix",
]

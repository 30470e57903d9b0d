"""accelcal: calibrate accelerometers from the norm of what they measure.

Static field calibration (|a| = g), centrifuge calibration with K2 terms, gradiometer
per-startup bias, per-dwell statistics of high-rate streams, and sim-to-real gap diagnosis.
The numerics are Rust (``accelcal._core``); this package is the API.
"""

from __future__ import annotations

from ._core import CalibrationError, DegenerateDataError
from .dwell import DetectorSettings, DwellAccumulator, DwellSet, detect_dwells, dwell_stats

__version__ = "0.1.0"

__all__ = [
    "CalibrationError",
    "DegenerateDataError",
    "DetectorSettings",
    "DwellAccumulator",
    "DwellSet",
    "detect_dwells",
    "dwell_stats",
]

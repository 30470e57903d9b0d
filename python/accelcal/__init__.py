"""accelcal: calibrate accelerometers from the norm of what they measure.

Static field calibration (|a| = g), centrifuge calibration with K2 terms, gradiometer
per-startup bias, per-dwell statistics of high-rate streams, and sim-to-real gap diagnosis.
The numerics are Rust (``accelcal._core``); this package is the API.
"""

from __future__ import annotations

from . import io as io  # accelcal.io.read_stream, iter_stream, stream_dwells
from ._core import CalibrationError, DegenerateDataError
from .centrifuge import (
    CentrifugeFit,
    CentrifugeModelWarning,
    CentrifugeOutlierWarning,
    calibrate_centrifuge_table,
    fit_centrifuge,
    read_centrifuge_table,
)
from .design import (
    CentrifugeSensitivity,
    PosePlan,
    Prediction,
    StartupPrediction,
    centrifuge_sensitivity,
    plan_azimuths,
    plan_poses,
    predict_accuracy,
    predict_startup_accuracy,
)
from .dwell import (
    DetectorSettings,
    DwellAccumulator,
    DwellSet,
    TimeStepWarning,
    detect_dwells,
    dwell_stats,
)
from .fleet import FleetReport, calibrate_many, fleet_report
from .gap import (
    GapReport,
    allan_deviation,
    diagnose,
    diagnose_centrifuge,
    diagnose_gradiometer,
)
from .gradiometer import (
    Demodulated,
    StartupBias,
    StartupCalibration,
    StartupMisfitWarning,
    calibrate_gradiometer_table,
    demodulate,
    startup_bias,
)
from .io import read_stream
from .static import (
    BatchFit,
    OffNormWarning,
    StaticFit,
    TriadModel,
    WeakDesignWarning,
    fit_static,
    fit_static_batch,
    local_gravity,
)

__version__ = "0.1.0"

__all__ = [
    "CentrifugeFit",
    "CentrifugeModelWarning",
    "CentrifugeOutlierWarning",
    "CentrifugeSensitivity",
    "calibrate_centrifuge_table",
    "centrifuge_sensitivity",
    "fit_centrifuge",
    "read_centrifuge_table",
    "CalibrationError",
    "DegenerateDataError",
    "Demodulated",
    "StartupBias",
    "StartupCalibration",
    "StartupMisfitWarning",
    "TimeStepWarning",
    "StartupPrediction",
    "calibrate_gradiometer_table",
    "demodulate",
    "plan_azimuths",
    "predict_startup_accuracy",
    "startup_bias",
    "DetectorSettings",
    "DwellAccumulator",
    "DwellSet",
    "GapReport",
    "allan_deviation",
    "diagnose",
    "diagnose_centrifuge",
    "diagnose_gradiometer",
    "detect_dwells",
    "dwell_stats",
    "read_stream",
    "FleetReport",
    "calibrate_many",
    "fleet_report",
    "BatchFit",
    "PosePlan",
    "Prediction",
    "StaticFit",
    "TriadModel",
    "OffNormWarning",
    "WeakDesignWarning",
    "fit_static",
    "fit_static_batch",
    "local_gravity",
    "plan_poses",
    "predict_accuracy",
]

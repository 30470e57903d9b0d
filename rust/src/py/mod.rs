//! The only place that imports pyo3: module definition, conversions and error mapping.

mod centrifuge;
mod convert;
mod dwell;
mod gap;
mod gradiometer;
mod static_fit;
mod text;

use crate::error::CoreError;
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::PyErr;

pyo3::create_exception!(
    accelcal,
    CalibrationError,
    PyValueError,
    "Input that cannot be calibrated: wrong shape, NaN, bad units, non-convergence."
);
pyo3::create_exception!(
    accelcal,
    DegenerateDataError,
    CalibrationError,
    "The data cannot determine what was asked: singular pose set, too few dwells."
);

impl From<CoreError> for PyErr {
    fn from(e: CoreError) -> PyErr {
        match e {
            CoreError::Degenerate(m) => DegenerateDataError::new_err(m),
            CoreError::InvalidInput(m) | CoreError::NotConverged(m) => CalibrationError::new_err(m),
            CoreError::OutOfMemory(m) => PyMemoryError::new_err(m),
        }
    }
}

#[pyo3::pymodule]
mod _core {
    #[pymodule_export]
    use super::centrifuge::{
        centrifuge_correct_raw, centrifuge_fit_raw, centrifuge_unit_check_raw, PyCentrifugeFit,
    };
    #[pymodule_export]
    use super::dwell::{
        detect_dwells_raw, dwell_output_faults, dwell_stats_raw, dwell_step_log, DwellTableRaw,
        PyOutputFault, PyStepLog, RawDwellAccumulator,
    };
    #[pymodule_export]
    use super::gap::{
        chi2_sf, f_sf, gap_diagnose_centrifuge, gap_diagnose_gradiometer, gap_diagnose_static,
        gap_dictionary, gap_distinct_poses, GapCandidate, GapGroup, GapHeldOut, GapLocation,
        GapNoiseEmpirical, GapRaw, GapSettings, GapStructure, GapStructureTest,
    };
    #[pymodule_export]
    use super::gradiometer::{
        demodulate_raw, startup_bias_raw, startup_predict_raw, PyDemodulated, PyStartupBias,
        PyStartupPrediction,
    };
    #[pymodule_export]
    use super::static_fit::{
        apply_triad_raw, gravity_problem, static_design_rows, static_fit_batch,
        static_model_violation, PyBatchFit, PyObservability, PyPrediction, PyStaticFit,
    };
    #[pymodule_export]
    use super::text::{format_rows, parse_iso8601, text_parse_head, text_read_all, TextBlocks};
    #[pymodule_export]
    use super::{CalibrationError, DegenerateDataError};
    /// The fewest samples the dwell detector's window may hold.
    #[pymodule_export]
    const MIN_WINDOW_SAMPLES: f64 = crate::dwell::MIN_WINDOW_SAMPLES;
    /// The fewest samples a dwell needs for its variance to count in the output-fault checks.
    #[pymodule_export]
    const FAULT_MIN_SAMPLES: u64 = crate::dwell::FAULT_MIN_SAMPLES;
    /// Unit gravity directions closer than this (about 3 deg) are one pose.
    #[pymodule_export]
    const SAME_POSE: f64 = crate::static_fit::start::SAME_POSE;
}

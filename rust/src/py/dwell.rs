//! Bindings of the dwell-statistics core.
//!
//! Locking rule (no deadlock with the GIL): the accumulator's mutex is only ever taken with the
//! interpreter detached (`py.detach`), so a thread holding the mutex never waits for the GIL
//! and a thread waiting for the mutex never holds it.

use numpy::{PyArray1, PyArray2, PyArray3, PyReadonlyArray1, PyReadonlyArray2, ToPyArray};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyTuple};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Mutex, PoisonError};

use super::convert::{bounds_from, frozen2, opt_slice, rows3, with_view, SampleArray};
use super::CalibrationError;
use crate::dwell::{
    output_faults, step_log, DetectorSettings, DwellAccumulator, DwellTable, OutputFault, StepLog,
};

/// Run `f`, turning a panic (a bug) into a CalibrationError instead of letting it cross the
/// boundary.
pub(super) fn guarded<R>(what: &str, f: impl FnOnce() -> crate::Result<R>) -> PyResult<R> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r.map_err(PyErr::from),
        Err(p) => {
            let msg = p
                .downcast_ref::<String>()
                .map(String::as_str)
                .or_else(|| p.downcast_ref::<&str>().copied())
                .unwrap_or("unknown panic");
            Err(CalibrationError::new_err(format!(
                "internal error in {what} ({msg}); please report it"
            )))
        }
    }
}

/// A finished dwell table (see `accelcal.DwellSet` for the meaning of each field).
#[pyclass(name = "DwellTableRaw", module = "accelcal._core", frozen, get_all)]
pub struct DwellTableRaw {
    /// (k,) int64 first sample of each dwell.
    start: Py<PyArray1<i64>>,
    /// (k,) int64 one past the last sample.
    stop: Py<PyArray1<i64>>,
    /// (k,) int64 samples per dwell.
    count: Py<PyArray1<i64>>,
    /// (k, 3) mean per dwell and axis.
    mean: Py<PyArray2<f64>>,
    /// (k, 3) sample variance (ddof = 1).
    var: Py<PyArray2<f64>>,
    /// (k, 2, 3) mean of the first and of the second half of each dwell.
    half_mean: Py<PyArray3<f64>>,
    /// (k, 3) Allan noise inflation of each dwell mean (NaN where not estimable).
    inflation: Py<PyArray2<f64>>,
    /// (3,) output resolution per axis, or None when the values are not quantised.
    lsb: Option<Py<PyArray1<f64>>>,
    /// Rows with NaN or inf left out of every dwell (detection).
    dropped: u64,
    /// (k,) mid time per dwell, when a time channel was given.
    t: Option<Py<PyArray1<f64>>>,
    /// (k,) mean temperature per dwell, when given.
    temperature: Option<Py<PyArray1<f64>>>,
    /// (3,) noise variance the detector used.
    noise_var: Option<Py<PyArray1<f64>>>,
    /// (3,) the detector's variance threshold.
    threshold: Option<Py<PyArray1<f64>>>,
    /// (m, 2) int64 bounds of the stretches that look still but vibrate above the threshold.
    vibrating_bounds: Py<PyArray2<i64>>,
    /// (m, 3) their sample std per axis.
    vibrating_std: Py<PyArray2<f64>>,
    /// Shorter detector settings that find more steady dwells (brief rests), when few were
    /// found: ``(window_s, min_dwell_s, trim_s, dwells)``, or None.
    shorter: Option<(f64, f64, f64, usize)>,
}

impl DwellTableRaw {
    fn new(py: Python<'_>, t: &DwellTable) -> Self {
        let k = t.stats.len();
        let v1 = |v: &[f64]| v.to_pyarray(py).unbind();
        let o3 = |v: Option<[f64; 3]>| v.map(|v| v1(&v));
        let i1 = |f: &dyn Fn(usize) -> i64| -> Py<PyArray1<i64>> {
            let v: Vec<i64> = (0..k).map(f).collect();
            v.to_pyarray(py).unbind()
        };
        let f2 = |f: &dyn Fn(usize, usize) -> f64| -> Py<PyArray2<f64>> {
            ndarray::Array2::from_shape_fn((k, 3), |(i, a)| f(i, a))
                .to_pyarray(py)
                .unbind()
        };
        let s = &t.stats;
        DwellTableRaw {
            start: i1(&|i| t.bounds[i][0] as i64),
            stop: i1(&|i| t.bounds[i][1] as i64),
            count: i1(&|i| s[i].moments.n as i64),
            mean: f2(&|i, a| s[i].moments.mean[a]),
            var: f2(&|i, a| s[i].moments.var()[a]),
            half_mean: ndarray::Array3::from_shape_fn((k, 2, 3), |(i, h, a)| s[i].half_mean[h][a])
                .to_pyarray(py)
                .unbind(),
            inflation: f2(&|i, a| s[i].inflation[a]),
            lsb: o3(t.lsb),
            dropped: t.dropped,
            t: t.t_mid.as_deref().map(v1),
            temperature: t.aux_mean.as_deref().map(v1),
            noise_var: o3(t.noise_var),
            threshold: o3(t.threshold),
            vibrating_bounds: ndarray::Array2::from_shape_fn((t.vibrating.len(), 2), |(i, j)| {
                t.vibrating[i].bounds[j] as i64
            })
            .to_pyarray(py)
            .unbind(),
            vibrating_std: ndarray::Array2::from_shape_fn((t.vibrating.len(), 3), |(i, j)| {
                t.vibrating[i].std[j]
            })
            .to_pyarray(py)
            .unbind(),
            shorter: t
                .shorter
                .map(|w| (w.window_s, w.min_dwell_s, w.trim_s, w.dwells)),
        }
    }
}

impl From<DwellTable> for DwellTableRaw {
    fn from(t: DwellTable) -> Self {
        Python::attach(|py| DwellTableRaw::new(py, &t))
    }
}

/// Per-dwell statistics over explicit bounds.
#[pyfunction]
#[pyo3(signature = (samples, bounds, t=None, temperature=None))]
pub fn dwell_stats_raw<'py>(
    py: Python<'py>,
    samples: &Bound<'py, PyAny>,
    bounds: PyReadonlyArray2<'py, i64>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    temperature: Option<PyReadonlyArray1<'py, f64>>,
) -> PyResult<DwellTableRaw> {
    let arr = SampleArray::extract(samples)?;
    let b = bounds_from(&bounds)?;
    let ts = opt_slice(&t, "t")?;
    let temp = opt_slice(&temperature, "temperature")?;
    let table = with_view!(&arr, v => py.detach(|| guarded("dwell_stats", || {
        crate::dwell::dwell_table(&v, &b, ts, temp)
    })))?;
    Ok(DwellTableRaw::new(py, &table))
}

#[allow(clippy::too_many_arguments)]
fn settings_from(
    fs: f64,
    window_s: f64,
    k: f64,
    min_dwell_s: f64,
    trim_s: f64,
    noise_quantile: f64,
    block_s: f64,
    noise_var: Option<[f64; 3]>,
) -> DetectorSettings {
    DetectorSettings {
        fs,
        window_s,
        k,
        min_dwell_s,
        trim_s,
        noise_quantile,
        block_s,
        noise_var,
    }
}

/// Automatic static-interval detection plus per-dwell statistics.
#[pyfunction]
#[pyo3(signature = (samples, fs, window_s, k, min_dwell_s, trim_s, noise_quantile, block_s, noise_var=None, t=None, temperature=None))]
#[allow(clippy::too_many_arguments)]
pub fn detect_dwells_raw<'py>(
    py: Python<'py>,
    samples: &Bound<'py, PyAny>,
    fs: f64,
    window_s: f64,
    k: f64,
    min_dwell_s: f64,
    trim_s: f64,
    noise_quantile: f64,
    block_s: f64,
    noise_var: Option<[f64; 3]>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    temperature: Option<PyReadonlyArray1<'py, f64>>,
) -> PyResult<DwellTableRaw> {
    let arr = SampleArray::extract(samples)?;
    let s = settings_from(
        fs,
        window_s,
        k,
        min_dwell_s,
        trim_s,
        noise_quantile,
        block_s,
        noise_var,
    );
    let ts = opt_slice(&t, "t")?;
    let temp = opt_slice(&temperature, "temperature")?;
    let table = with_view!(&arr, v => py.detach(|| guarded("detect_dwells", || {
        crate::dwell::detect_table(&v, s, ts, temp)
    })))?;
    Ok(DwellTableRaw::new(py, &table))
}

/// Streaming accumulator (bounds or detector mode); safe to share between threads.
#[pyclass(name = "RawDwellAccumulator", module = "accelcal._core", frozen)]
pub struct RawDwellAccumulator {
    inner: Mutex<DwellAccumulator>,
}

impl RawDwellAccumulator {
    /// Run `f` on the state. Call only with the interpreter detached (see the module doc). A
    /// poisoned mutex (a panic inside `f`, caught by `guarded`) is recovered, not fatal.
    fn locked<R>(&self, f: impl FnOnce(&mut DwellAccumulator) -> R) -> R {
        let mut g = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        f(&mut g)
    }
}

#[pymethods]
impl RawDwellAccumulator {
    #[new]
    #[pyo3(signature = (bounds=None, fs=None, window_s=1.0, k=6.0, min_dwell_s=1.0, trim_s=0.1, noise_quantile=0.2, block_s=0.02, noise_var=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        bounds: Option<PyReadonlyArray2<'_, i64>>,
        fs: Option<f64>,
        window_s: f64,
        k: f64,
        min_dwell_s: f64,
        trim_s: f64,
        noise_quantile: f64,
        block_s: f64,
        noise_var: Option<[f64; 3]>,
    ) -> PyResult<Self> {
        let inner = match (bounds, fs) {
            (Some(b), _) => DwellAccumulator::with_bounds(bounds_from(&b)?)?,
            (None, Some(fs)) => DwellAccumulator::with_detector(settings_from(
                fs,
                window_s,
                k,
                min_dwell_s,
                trim_s,
                noise_quantile,
                block_s,
                noise_var,
            ))?,
            (None, None) => {
                return Err(CalibrationError::new_err(
                    "give either bounds (k, 2) or fs (Hz) for automatic detection",
                ))
            }
        };
        Ok(RawDwellAccumulator {
            inner: Mutex::new(inner),
        })
    }

    /// Push a chunk `(m, 3)` with optional `t` and `temperature` (m,) channels. On error
    /// nothing of the chunk is kept and the accumulator stays usable.
    #[pyo3(signature = (chunk, t=None, temperature=None))]
    fn push<'py>(
        &self,
        py: Python<'py>,
        chunk: &Bound<'py, PyAny>,
        t: Option<PyReadonlyArray1<'py, f64>>,
        temperature: Option<PyReadonlyArray1<'py, f64>>,
    ) -> PyResult<()> {
        let arr = SampleArray::extract(chunk)?;
        let ts = opt_slice(&t, "t")?;
        let temp = opt_slice(&temperature, "temperature")?;
        with_view!(&arr, v => py.detach(|| guarded("DwellAccumulator.push", || {
            self.locked(|acc| acc.push(&v, ts, temp))
        })))
    }

    /// Samples pushed so far.
    #[getter]
    fn position(&self, py: Python<'_>) -> usize {
        py.detach(|| self.locked(|acc| acc.position()))
    }

    /// The dwell table of everything pushed so far (the accumulator stays usable).
    fn finish(&self, py: Python<'_>) -> PyResult<DwellTableRaw> {
        let t = py.detach(|| {
            guarded("DwellAccumulator.finish", || {
                self.locked(|acc| acc.finish())
            })
        })?;
        Ok(DwellTableRaw::new(py, &t))
    }

    /// The state as versioned bytes (see `from_state`).
    fn to_state<'py>(&self, py: Python<'py>) -> Bound<'py, PyBytes> {
        let b = py.detach(|| self.locked(|acc| acc.to_state()));
        PyBytes::new(py, &b)
    }

    /// Rebuild an accumulator from `to_state` bytes (checked; corrupted bytes are an error).
    #[staticmethod]
    fn from_state(py: Python<'_>, state: &[u8]) -> PyResult<Self> {
        let inner = py.detach(|| {
            guarded("DwellAccumulator.from_state", || {
                DwellAccumulator::from_state(state)
            })
        })?;
        Ok(RawDwellAccumulator {
            inner: Mutex::new(inner),
        })
    }

    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyTuple>> {
        let py = slf.py();
        let ctor = py.get_type::<Self>().getattr("from_state")?;
        let state = slf.get().to_state(py);
        PyTuple::new(py, [ctor, PyTuple::new(py, [state])?.into_any()])
    }
}

/// One dwell whose output did not follow the sensor (`accelcal.DwellSet.faults`).
#[pyclass(name = "OutputFault", module = "accelcal._core", frozen, get_all)]
pub struct PyOutputFault {
    /// Index of the dwell.
    dwell: usize,
    /// The constant axis (0, 1, 2), or None when every axis is constant (frozen).
    axis: Option<usize>,
    /// "saturated_high", "saturated_low", "partly_saturated_high", "partly_saturated_low",
    /// "stuck" or "frozen".
    kind: &'static str,
    /// The dwell mean on that axis, input units (the constant value; x for a frozen dwell).
    value: f64,
    /// The value at which the axis saturates (NaN for stuck and frozen dwells).
    rail: f64,
    /// The axis's typical dwell variance, squared input units.
    typical_var: f64,
}

impl From<&OutputFault> for PyOutputFault {
    fn from(f: &OutputFault) -> Self {
        PyOutputFault {
            dwell: f.dwell,
            axis: f.axis,
            kind: f.kind.name(),
            value: f.value,
            rail: f.rail,
            typical_var: f.typical_var,
        }
    }
}

/// Dwells with a saturated, stuck or frozen output (exactly constant axes), and those within
/// reach of a rail that a saturated dwell has shown.
#[pyfunction]
#[pyo3(signature = (mean, var, count, lsb=None))]
pub fn dwell_output_faults(
    mean: PyReadonlyArray2<'_, f64>,
    var: PyReadonlyArray2<'_, f64>,
    count: PyReadonlyArray1<'_, i64>,
    lsb: Option<[f64; 3]>,
) -> PyResult<Vec<PyOutputFault>> {
    let m = rows3(&mean, "mean")?;
    let v = rows3(&var, "var")?;
    let n: Vec<u64> = count
        .as_array()
        .iter()
        .map(|&c| u64::try_from(c).unwrap_or(0))
        .collect();
    let f = guarded("DwellSet.faults", || output_faults(&m, &v, &n, lsb))?;
    Ok(f.iter().map(PyOutputFault::from).collect())
}

/// A recording that holds only the rests (a block of samples per pose, nothing recorded
/// while the sensor was turned): its runs between jumps.
#[pyclass(name = "StepLog", module = "accelcal._core", frozen, get_all)]
pub struct PyStepLog {
    /// `[start, stop)` sample bounds of each run, (k, 2) int64.
    runs: Py<PyArray2<i64>>,
    /// Jumps found.
    jumps: usize,
    /// The run length shared by at least half of the runs, or None.
    period: Option<usize>,
    /// Share of the samples in recorded motion.
    motion_fraction: f64,
}

impl PyStepLog {
    fn new(py: Python<'_>, log: &StepLog) -> PyStepLog {
        let flat: Vec<i64> = log
            .runs
            .iter()
            .flat_map(|r| r.iter().map(|&v| i64::try_from(v).unwrap_or(i64::MAX)))
            .collect();
        PyStepLog {
            runs: frozen2(py, flat, log.runs.len(), 2),
            jumps: log.jumps,
            period: log.period,
            motion_fraction: log.motion_fraction,
        }
    }
}

/// The stream read as a log of rests, or None when it does not read as one (its moves are
/// recorded, or it has too few jumps).
#[pyfunction]
pub fn dwell_step_log<'py>(
    py: Python<'py>,
    samples: &Bound<'py, PyAny>,
) -> PyResult<Option<PyStepLog>> {
    let arr = SampleArray::extract(samples)?;
    let log = with_view!(&arr, v => py.detach(|| guarded("step_log", || Ok(step_log(&v)))))?;
    Ok(log.map(|l| PyStepLog::new(py, &l)))
}

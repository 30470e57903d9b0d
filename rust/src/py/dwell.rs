//! Bindings of the dwell-statistics core.

use numpy::{IntoPyArray, PyArray2, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Mutex;

use super::convert::{bounds_from, opt_slice, with_view, SampleArray};
use super::CalibrationError;
use crate::dwell::{DetectorSettings, DwellAccumulator, DwellTable};

fn table_to_dict<'py>(py: Python<'py>, t: DwellTable) -> PyResult<Bound<'py, PyDict>> {
    let k = t.bounds.len();
    let mut mean = Vec::with_capacity(3 * k);
    let mut var = Vec::with_capacity(3 * k);
    let mut count = Vec::with_capacity(k);
    for m in &t.moments {
        mean.extend_from_slice(&m.mean);
        var.extend_from_slice(&m.var());
        count.push(m.n as i64);
    }
    let to2 = |v: Vec<f64>| -> PyResult<Bound<'py, PyArray2<f64>>> {
        let a = ndarray::Array2::from_shape_vec((k, 3), v)
            .map_err(|e| CalibrationError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py))
    };
    let d = PyDict::new(py);
    d.set_item("mean", to2(mean)?)?;
    d.set_item("var", to2(var)?)?;
    d.set_item("count", count.into_pyarray(py))?;
    for (key, end) in [("start", 0), ("stop", 1)] {
        let v: Vec<i64> = t.bounds.iter().map(|b| b[end] as i64).collect();
        d.set_item(key, v.into_pyarray(py))?;
    }
    d.set_item("t", t.t_mid.map(|v| v.into_pyarray(py)))?;
    d.set_item("temperature", t.aux_mean.map(|v| v.into_pyarray(py)))?;
    for (key, v) in [("noise_var", t.noise_var), ("threshold", t.threshold)] {
        d.set_item(key, v.map(|v| v.to_vec().into_pyarray(py)))?;
    }
    Ok(d)
}

/// Per-dwell statistics over explicit bounds; returns a dict of arrays.
#[pyfunction]
#[pyo3(signature = (samples, bounds, t=None, temperature=None))]
pub fn dwell_stats_raw<'py>(
    py: Python<'py>,
    samples: &Bound<'py, PyAny>,
    bounds: PyReadonlyArray2<'py, i64>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    temperature: Option<PyReadonlyArray1<'py, f64>>,
) -> PyResult<Bound<'py, PyDict>> {
    let arr = SampleArray::extract(samples)?;
    let b = bounds_from(&bounds)?;
    let ts = opt_slice(&t, "t")?;
    let temp = opt_slice(&temperature, "temperature")?;
    let table = with_view!(&arr, v => {
        py.detach(|| -> crate::Result<DwellTable> {
            // One-shot: parallel over dwells, then the (cheap) time/temperature channels.
            let moments = crate::dwell::dwell_moments(&v, &b)?;
            let t_mid = match ts {
                Some(x) => {
                    if x.len() != v.nrows() {
                        return crate::error::invalid(format!(
                            "t has {} values but samples have {} rows", x.len(), v.nrows()));
                    }
                    Some(b.iter().map(|&[a, z]| 0.5 * (x[a] + x[z - 1])).collect())
                }
                None => None,
            };
            let aux_mean = match temp {
                Some(x) => {
                    if x.len() != v.nrows() {
                        return crate::error::invalid(format!(
                            "temperature has {} values but samples have {} rows", x.len(), v.nrows()));
                    }
                    Some(crate::dwell::aux_mean(x, &b)?)
                }
                None => None,
            };
            Ok(DwellTable { bounds: b.clone(), moments, t_mid, aux_mean, noise_var: None, threshold: None })
        })
    })?;
    table_to_dict(py, table)
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

/// Automatic static-interval detection plus per-dwell statistics; returns a dict of arrays.
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
) -> PyResult<Bound<'py, PyDict>> {
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
    let table = with_view!(&arr, v => {
        py.detach(|| -> crate::Result<DwellTable> {
            crate::dwell::check_samples(&v)?;
            let mut acc = DwellAccumulator::with_detector(s)?;
            acc.push(&v, ts, temp)?;
            acc.finish()
        })
    })?;
    table_to_dict(py, table)
}

/// Streaming accumulator (bounds or detector mode).
#[pyclass(name = "RawDwellAccumulator", module = "accelcal._core")]
pub struct RawDwellAccumulator {
    inner: Mutex<DwellAccumulator>,
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

    /// Push a chunk `(m, 3)` with optional `t` and `temperature` (m,) channels.
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
        let mut g = self
            .inner
            .lock()
            .map_err(|_| CalibrationError::new_err("accumulator poisoned by an earlier error"))?;
        let acc: &mut DwellAccumulator = &mut g;
        with_view!(&arr, v => py.detach(|| acc.push(&v, ts, temp)))?;
        Ok(())
    }

    /// Samples pushed so far.
    #[getter]
    fn position(&self) -> PyResult<usize> {
        let g = self
            .inner
            .lock()
            .map_err(|_| CalibrationError::new_err("accumulator poisoned by an earlier error"))?;
        Ok(g.position())
    }

    /// The dwell table of everything pushed so far (the accumulator stays usable).
    fn finish<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let g = self
            .inner
            .lock()
            .map_err(|_| CalibrationError::new_err("accumulator poisoned by an earlier error"))?;
        let acc: &DwellAccumulator = &g;
        let t = py.detach(|| acc.finish())?;
        table_to_dict(py, t)
    }
}

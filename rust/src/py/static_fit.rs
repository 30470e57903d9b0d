//! Bindings of the static-field calibration core.

use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3,
    PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::convert::{rows3, with_view, SampleArray};
use super::CalibrationError;
use crate::static_fit::{
    apply_model, fit_batch, fit_static, FitSettings, Method, Model, Noise, StaticFit,
};

fn mat_to_py<'py>(py: Python<'py>, m: &nalgebra::DMatrix<f64>) -> Bound<'py, PyArray2<f64>> {
    let (r, c) = (m.nrows(), m.ncols());
    let v: Vec<f64> = (0..r)
        .flat_map(|i| (0..c).map(move |j| m[(i, j)]))
        .collect();
    ndarray::Array2::from_shape_vec((r, c), v)
        .expect("shape matches length")
        .into_pyarray(py)
}

#[allow(clippy::too_many_arguments)]
fn settings(
    model: &str,
    method: &str,
    start: Option<Vec<f64>>,
    max_iter: usize,
    raise_degenerate: bool,
    degenerate_std: f64,
    weak_std: f64,
) -> PyResult<FitSettings> {
    let mut s = FitSettings::new(Model::parse(model)?, Method::parse(method)?);
    s.start = start;
    s.max_iter = max_iter;
    s.raise_degenerate = raise_degenerate;
    s.degenerate_std = degenerate_std;
    s.weak_std = weak_std;
    Ok(s)
}

/// Result of one static fit (the Python `StaticFit` wraps it).
#[pyclass(name = "StaticFitRaw", module = "accelcal._core", frozen)]
pub struct StaticFitRaw {
    inner: StaticFit,
    settings: FitSettings,
}

#[pymethods]
impl StaticFitRaw {
    #[getter]
    fn model(&self) -> &'static str {
        self.inner.model.name()
    }
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.params.clone().into_pyarray(py)
    }
    #[getter]
    fn start<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.start.clone().into_pyarray(py)
    }
    #[getter]
    fn covariance<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        mat_to_py(py, &self.inner.covariance)
    }
    #[getter]
    fn residuals<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.residuals.clone().into_pyarray(py)
    }
    #[getter]
    fn sigma_r<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.sigma_r.clone().into_pyarray(py)
    }
    #[getter]
    fn cost(&self) -> f64 {
        self.inner.cost
    }
    #[getter]
    fn dof(&self) -> usize {
        self.inner.dof
    }
    #[getter]
    fn chi2_dof(&self) -> f64 {
        self.inner.chi2_dof
    }
    #[getter]
    fn iterations(&self) -> usize {
        self.inner.iterations
    }
    #[getter]
    fn converged(&self) -> bool {
        self.inner.converged
    }
    #[getter]
    fn noise_known(&self) -> bool {
        self.inner.noise_known
    }
    #[getter]
    fn note(&self) -> String {
        self.inner.note.clone()
    }
    #[getter]
    fn weak(&self) -> bool {
        self.inner.summary.weak
    }
    #[getter]
    fn degenerate(&self) -> bool {
        self.inner.summary.degenerate
    }
    #[getter]
    fn std_comparable<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.inner.summary.std_comparable.clone().into_pyarray(py)
    }
    #[getter]
    fn weakest_std(&self) -> f64 {
        self.inner.summary.weakest_std
    }
    /// Text naming the weakly determined parameters (predicted std above `weak_std`).
    fn weak_text(&self, weak_std: f64) -> String {
        self.inner.weak_text(weak_std)
    }
    /// Observability report as a dict (singular values, condition, predicted std in
    /// comparable units, weakest combination), from the SVD of the whitened Jacobian.
    fn observability<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let o = self.inner.observability(&self.settings)?;
        let d = PyDict::new(py);
        d.set_item(
            "singular_values",
            o.singular_values.clone().into_pyarray(py),
        )?;
        d.set_item("condition", o.condition)?;
        d.set_item("std_comparable", o.std_comparable.clone().into_pyarray(py))?;
        d.set_item("weakest", o.weakest.clone().into_pyarray(py))?;
        d.set_item("weakest_std", o.weakest_std)?;
        d.set_item("degenerate", o.degenerate)?;
        d.set_item("weak", o.weak)?;
        d.set_item("combination", o.combination.clone())?;
        Ok(d)
    }
}

/// Fit the static norm model to `(k, 3)` dwell means; `var` is the `(k, 3)` variance of
/// each mean (None: estimated from the residuals).
#[pyfunction]
#[pyo3(signature = (means, g, model="lower", method="lm", var=None, start=None, max_iter=200, raise_degenerate=true, degenerate_std=0.1, weak_std=1e-3))]
#[allow(clippy::too_many_arguments)]
pub fn static_fit_raw(
    means: PyReadonlyArray2<'_, f64>,
    g: f64,
    model: &str,
    method: &str,
    var: Option<PyReadonlyArray2<'_, f64>>,
    start: Option<Vec<f64>>,
    max_iter: usize,
    raise_degenerate: bool,
    degenerate_std: f64,
    weak_std: f64,
) -> PyResult<StaticFitRaw> {
    let m = rows3(&means, "means")?;
    let noise = match var {
        Some(v) => Noise::Known(rows3(&v, "var")?),
        None => Noise::Estimated,
    };
    let s = settings(
        model,
        method,
        start,
        max_iter,
        raise_degenerate,
        degenerate_std,
        weak_std,
    )?;
    let inner = fit_static(&m, g, &noise, &s)?;
    Ok(StaticFitRaw { inner, settings: s })
}

/// Fit `(B, n, 3)` sessions in parallel; returns a dict of arrays (params, std, rms,
/// iterations, status: 0 ok, 1 degenerate, 2 not converged, 3 invalid).
#[pyfunction]
#[pyo3(signature = (means, g, model="lower", method="lm", sigma=None, start=None, max_iter=200, degenerate_std=0.1))]
#[allow(clippy::too_many_arguments)]
pub fn static_fit_batch_raw<'py>(
    py: Python<'py>,
    means: PyReadonlyArray3<'py, f64>,
    g: PyReadonlyArray1<'py, f64>,
    model: &str,
    method: &str,
    sigma: Option<f64>,
    start: Option<Vec<f64>>,
    max_iter: usize,
    degenerate_std: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let sh = means.shape().to_vec();
    if sh[2] != 3 {
        return Err(CalibrationError::new_err(format!(
            "means must have shape (B, n, 3); got {sh:?}"
        )));
    }
    let (b, n) = (sh[0], sh[1]);
    let s = settings(model, method, start, max_iter, true, degenerate_std, 1e-3)?;
    // `as_array().iter()` walks in logical (C) order whatever the memory layout.
    let data: Vec<f64> = match (means.is_c_contiguous(), means.as_slice()) {
        (true, Ok(x)) => x.to_vec(),
        _ => means.as_array().iter().copied().collect(),
    };
    let gv = g.as_array().to_vec();
    let rows = py.detach(|| fit_batch(&data, b, n, &gv, sigma, &s))?;
    let np = s.model.n_params();
    let mut params = Vec::with_capacity(b * np);
    let mut std = Vec::with_capacity(b * np);
    let mut rms = Vec::with_capacity(b);
    let mut its = Vec::with_capacity(b);
    let mut status = Vec::with_capacity(b);
    for r in rows {
        params.extend_from_slice(&r.params);
        std.extend_from_slice(&r.std);
        rms.push(r.rms);
        its.push(r.iterations as i64);
        status.push(r.status);
    }
    let to2 = |v: Vec<f64>| -> PyResult<Bound<'py, PyArray2<f64>>> {
        ndarray::Array2::from_shape_vec((b, np), v)
            .map(|a| a.into_pyarray(py))
            .map_err(|e| CalibrationError::new_err(e.to_string()))
    };
    let d = PyDict::new(py);
    d.set_item("params", to2(params)?)?;
    d.set_item("std", to2(std)?)?;
    d.set_item("rms", rms.into_pyarray(py))?;
    d.set_item("iterations", its.into_pyarray(py))?;
    d.set_item("status", status.into_pyarray(py))?;
    Ok(d)
}

/// Calibrated specific force `K^-1 (am - b)` of an `(N, 3)` array (float64, float32, int16,
/// int32, any strides).
#[pyfunction]
pub fn apply_triad_raw<'py>(
    py: Python<'py>,
    samples: &Bound<'py, PyAny>,
    k: [[f64; 3]; 3],
    b: [f64; 3],
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let arr = SampleArray::extract(samples)?;
    let (out, n) = with_view!(&arr, v => {
        let n = v.nrows();
        (py.detach(|| apply_model(&v, &k, &b))?, n)
    });
    ndarray::Array2::from_shape_vec((n, 3), out)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| CalibrationError::new_err(e.to_string()))
}

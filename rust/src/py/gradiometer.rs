//! Bindings of the gradiometer core: start-up bias least squares, predictions, demodulation.

use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::convert::{bounds_from, with_view, SampleArray};
use super::CalibrationError;
use crate::gradiometer::{self as g, GradientPrior};

fn slice1<'a>(a: &'a PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| {
        CalibrationError::new_err(format!("{what} must be a contiguous 1-D float64 array"))
    })
}

fn square<'py>(py: Python<'py>, v: Vec<f64>, p: usize) -> PyResult<Bound<'py, PyAny>> {
    let a = ndarray::Array2::from_shape_vec((p, p), v)
        .map_err(|e| CalibrationError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py).into_any())
}

/// Start-up least squares; returns a dict (params, unit_cov, residuals, rss, dof, condition).
#[pyfunction]
#[pyo3(signature = (theta_rad, outputs, dwell_std, t=None, t_ref=0.0))]
pub fn startup_bias_raw<'py>(
    py: Python<'py>,
    theta_rad: PyReadonlyArray1<'py, f64>,
    outputs: PyReadonlyArray2<'py, f64>,
    dwell_std: PyReadonlyArray1<'py, f64>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    t_ref: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let th = slice1(&theta_rad, "theta_rad")?;
    let sd = slice1(&dwell_std, "dwell_std")?;
    if outputs.shape()[1] != 2 {
        return Err(CalibrationError::new_err(format!(
            "outputs must have shape (m, 2) (inline, cross); got {:?}",
            outputs.shape()
        )));
    }
    let y: Vec<[f64; 2]> = outputs
        .as_array()
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1]])
        .collect();
    let ts = match &t {
        Some(a) => Some(slice1(a, "t")?),
        None => None,
    };
    let fit = g::fit_startup_bias(th, &y, ts, t_ref, sd)?;
    let p = fit.params.len();
    let m = y.len();
    let d = PyDict::new(py);
    d.set_item("params", fit.params.into_pyarray(py))?;
    d.set_item("unit_cov", square(py, fit.unit_cov, p)?)?;
    let res = ndarray::Array2::from_shape_fn((m, 2), |(k, c)| fit.residuals[k][c]);
    d.set_item("residuals", res.into_pyarray(py))?;
    d.set_item("rss", fit.rss)?;
    d.set_item("dof", fit.dof)?;
    d.set_item("condition", fit.condition)?;
    Ok(d)
}

/// Predicted unit covariance of a design, the covariance from azimuth errors and the SPEC
/// closed form; returns a dict (unit_cov, theta_cov, condition, closed_form).
#[pyfunction]
#[pyo3(signature = (theta_rad, dwell_std, t=None, t_ref=0.0, gradient=None, gradient_magnitude=0.0, sigma_theta_rad=0.0))]
#[allow(clippy::too_many_arguments)]
pub fn startup_predict_raw<'py>(
    py: Python<'py>,
    theta_rad: PyReadonlyArray1<'py, f64>,
    dwell_std: PyReadonlyArray1<'py, f64>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    t_ref: f64,
    gradient: Option<[f64; 2]>,
    gradient_magnitude: f64,
    sigma_theta_rad: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let th = slice1(&theta_rad, "theta_rad")?;
    let sd = slice1(&dwell_std, "dwell_std")?;
    let ts = match &t {
        Some(a) => Some(slice1(a, "t")?),
        None => None,
    };
    let (cov, p, cond) = g::startup_unit_cov(th, ts, t_ref, sd)?;
    let prior = match gradient {
        Some(v) => GradientPrior::Vector(v),
        None => GradientPrior::Magnitude(gradient_magnitude),
    };
    let tcov = g::azimuth_error_covariance(th, ts, t_ref, sd, prior, sigma_theta_rad)?;
    let d = PyDict::new(py);
    d.set_item("unit_cov", square(py, cov, p)?)?;
    d.set_item("theta_cov", square(py, tcov, p)?)?;
    d.set_item("condition", cond)?;
    d.set_item("closed_form", g::balanced_variance(th))?;
    Ok(d)
}

/// 2-omega demodulation of `(N, 4)` streams per dwell; returns a dict of per-dwell arrays.
#[pyfunction]
#[pyo3(signature = (accel, phase, bounds, radius_m))]
pub fn demodulate_raw<'py>(
    py: Python<'py>,
    accel: &Bound<'py, PyAny>,
    phase: PyReadonlyArray1<'py, f64>,
    bounds: PyReadonlyArray2<'py, i64>,
    radius_m: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let arr = SampleArray::extract(accel)?;
    let b = bounds_from(&bounds)?;
    let ph = slice1(&phase, "phase")?;
    let out = with_view!(&arr, v => py.detach(|| g::demodulate(&v, ph, &b, radius_m)))?;
    let col = |f: &dyn Fn(&g::DemodDwell) -> f64| -> Vec<f64> { out.iter().map(f).collect() };
    let d = PyDict::new(py);
    d.set_item("inline_e", col(&|o| o.inline_e).into_pyarray(py))?;
    d.set_item("cross_e", col(&|o| o.cross_e).into_pyarray(py))?;
    d.set_item("std_inline_e", col(&|o| o.std_e[0]).into_pyarray(py))?;
    d.set_item("std_cross_e", col(&|o| o.std_e[1]).into_pyarray(py))?;
    d.set_item("resid_rms", col(&|o| o.resid_rms).into_pyarray(py))?;
    let nuis = ndarray::Array2::from_shape_fn((out.len(), 3), |(k, c)| out[k].nuisance[c]);
    d.set_item("nuisance", nuis.into_pyarray(py))?;
    d.set_item(
        "start",
        out.iter()
            .map(|o| o.start as i64)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    d.set_item(
        "stop",
        out.iter()
            .map(|o| o.stop as i64)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    d.set_item(
        "revolutions",
        out.iter()
            .map(|o| o.revolutions as i64)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    Ok(d)
}

//! Bindings of the centrifuge calibration core.

use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use super::convert::rows3;
use super::CalibrationError;
use crate::centrifuge::{fit, CentrifugeData, FitOptions, LeverArm, Method, ModelOptions};

/// Centrifuge calibration (see `accelcal.fit_centrifuge`); returns a dict of arrays.
#[pyfunction]
#[pyo3(signature = (outputs, omega, radius, g, method="nls", k3=false, misalignment=false, lever_arm=None, spin_axis=None, sigma=None, robust=true, outlier_k=5.0, sigma_floor=1e-9, max_draws=20000, seed=0))]
#[allow(clippy::too_many_arguments)]
pub fn centrifuge_fit_raw<'py>(
    py: Python<'py>,
    outputs: PyReadonlyArray2<'py, f64>,
    omega: PyReadonlyArray1<'py, f64>,
    radius: f64,
    g: f64,
    method: &str,
    k3: bool,
    misalignment: bool,
    lever_arm: Option<&str>,
    spin_axis: Option<PyReadonlyArray2<'py, f64>>,
    sigma: Option<PyReadonlyArray1<'py, f64>>,
    robust: bool,
    outlier_k: f64,
    sigma_floor: f64,
    max_draws: usize,
    seed: u64,
) -> PyResult<Bound<'py, PyDict>> {
    let method = match method {
        "nls" => Method::Nls,
        "taylor-paper" => Method::TaylorPaper,
        m => {
            return Err(CalibrationError::new_err(format!(
                "unknown method {m:?}; use 'nls' or 'taylor-paper'"
            )))
        }
    };
    let lever = match lever_arm {
        None => LeverArm::None,
        Some("along") => LeverArm::Along,
        Some("full") => LeverArm::Full,
        Some(m) => {
            return Err(CalibrationError::new_err(format!(
                "unknown lever_arm {m:?}; use None, 'along' or 'full'"
            )))
        }
    };
    let out = rows3(&outputs, "outputs")?;
    let om = omega.as_array().to_vec();
    let sa = match &spin_axis {
        Some(a) => Some(rows3(a, "spin_axis")?),
        None => None,
    };
    let sg = sigma.as_ref().map(|s| s.as_array().to_vec());
    let opt = FitOptions {
        model: ModelOptions {
            k3,
            misalignment,
            lever,
        },
        method,
        robust,
        outlier_k,
        sigma_floor,
        max_draws,
        seed,
    };
    let res = {
        let data = CentrifugeData {
            outputs: &out,
            omega: &om,
            radius,
            g,
            sigma: sg.as_deref(),
            spin_axis: sa.as_deref(),
        };
        // The robust screen can take milliseconds: release the interpreter.
        py.detach(|| fit(&data, &opt))?
    };
    let p = res.params.len();
    // Everything the Python layer needs, in final form (it only takes views).
    let std: Vec<f64> = (0..p)
        .map(|j| res.covariance[j * p + j].max(0.0).sqrt())
        .collect();
    // Keys named after the `CentrifugeFit` fields they fill (the Python layer copies the dict
    // into the instance and adds views), plus `extra`.
    let d = PyDict::new(py);
    d.set_item("params", res.params.into_pyarray(py))?;
    d.set_item("std", std.into_pyarray(py))?;
    d.set_item("names", res.names)?;
    let cov = ndarray::Array2::from_shape_vec((p, p), res.covariance)
        .map_err(|e| CalibrationError::new_err(e.to_string()))?;
    d.set_item("covariance", cov.into_pyarray(py))?;
    d.set_item("residuals", res.residuals.into_pyarray(py))?;
    d.set_item(
        "outliers",
        res.outliers
            .iter()
            .map(|&k| k as i64)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    d.set_item("residual_rms", res.residual_rms)?;
    let obs = PyDict::new(py);
    obs.set_item("singular_values", res.singular_values.into_pyarray(py))?;
    obs.set_item("condition_number", res.condition)?;
    obs.set_item("unobservable", PyList::empty(py))?;
    d.set_item("observability", obs)?;
    d.set_item("iterations", res.iterations)?;
    d.set_item("converged", res.converged)?;
    d.set_item("draws", res.draws)?;
    d.set_item(
        "taylor_coefficients",
        res.taylor_coefficients.map(|c| c.into_pyarray(py)),
    )?;
    let extra = PyDict::new(py);
    extra.set_item("screen_sigma", res.screen_sigma)?;
    d.set_item("extra", extra)?;
    Ok(d)
}

//! Bindings of the gradiometer core: start-up bias least squares, predictions, demodulation.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use super::convert::{
    bounds_from, cow1, frozen1, frozen2, frozen_copy1, frozen_copy2, vec1, with_view, SampleArray,
};
use super::CalibrationError;
use crate::gradiometer::{self as g, GradientPrior};

fn names(p: usize) -> Vec<String> {
    g::PARAM_NAMES[..p].iter().map(|s| s.to_string()).collect()
}

fn radians(deg: &[f64]) -> Vec<f64> {
    deg.iter().map(|d| d.to_radians()).collect()
}

/// `(m, 2)` channel averages as pairs (logical order, any layout).
fn pairs(a: &PyReadonlyArray2<'_, f64>, what: &str) -> PyResult<Vec<[f64; 2]>> {
    if a.shape()[1] != 2 {
        return Err(CalibrationError::new_err(format!(
            "{what} must have shape (m, 2) (inline, cross); got {:?}",
            a.shape()
        )));
    }
    Ok(a.as_array()
        .rows()
        .into_iter()
        .map(|r| [r[0], r[1]])
        .collect())
}

/// Start-up bias, gradient (and drift) with covariance; the Python `accelcal.StartupBias`
/// subclasses it. Every array is read-only.
#[pyclass(
    name = "StartupBiasCore",
    module = "accelcal._core",
    frozen,
    get_all,
    subclass
)]
pub struct PyStartupBias {
    /// Per-startup bias of the inline and cross channels, E (at `t_ref` with drift).
    bias: Py<PyArray1<f64>>,
    /// Navigation-frame gradient `(I, C)`, E.
    gradient: Py<PyArray1<f64>>,
    /// Linear bias drift, E/s (drift model only).
    drift: Option<Py<PyArray1<f64>>>,
    /// `(p, p)` in the order of `names`.
    covariance: Py<PyArray2<f64>>,
    std: Py<PyArray1<f64>>,
    /// `(m, 2)`, E.
    residuals: Py<PyArray2<f64>>,
    unit_covariance: Py<PyArray2<f64>>,
    sigma: Option<Py<PyArray1<f64>>>,
    sigma_estimated: bool,
    dof: usize,
    condition: f64,
    azimuth_deg: Py<PyArray1<f64>>,
    t: Option<Py<PyArray1<f64>>>,
    t_ref: Option<f64>,
    names: Vec<String>,
    /// Std of the independent azimuth errors allowed for, deg.
    sigma_theta: f64,
    /// `(p, p)`: the part of `covariance` from the azimuth errors.
    azimuth_covariance: Py<PyArray2<f64>>,
    chi2_scale: f64,
    chi2_dof: f64,
}

/// A start-up estimate and the design it came from.
pub struct StartupInput {
    pub azimuth_deg: Vec<f64>,
    pub t: Option<Vec<f64>>,
    pub t_ref: Option<f64>,
}

impl From<(g::StartupBias, StartupInput)> for PyStartupBias {
    fn from((f, d): (g::StartupBias, StartupInput)) -> Self {
        Python::attach(|py| {
            let p = f.params.len();
            let m = f.residuals.len();
            PyStartupBias {
                bias: frozen1(py, f.params[..2].to_vec()),
                gradient: frozen1(py, f.params[2..4].to_vec()),
                drift: (p == 6).then(|| frozen1(py, f.params[4..6].to_vec())),
                covariance: frozen2(py, f.covariance, p, p),
                std: frozen1(py, f.std),
                residuals: frozen2(py, f.residuals.into_iter().flatten().collect(), m, 2),
                unit_covariance: frozen2(py, f.unit_cov, p, p),
                sigma: f.sigma.map(|s| frozen1(py, s)),
                sigma_estimated: f.sigma_estimated,
                dof: f.dof,
                condition: f.condition,
                azimuth_deg: frozen1(py, d.azimuth_deg),
                t: d.t.map(|t| frozen1(py, t)),
                t_ref: d.t_ref,
                names: names(p),
                sigma_theta: f.sigma_theta.to_degrees(),
                azimuth_covariance: frozen2(py, f.azimuth_covariance, p, p),
                chi2_scale: f.chi2_scale,
                chi2_dof: f.chi2_dof,
            }
        })
    }
}

#[pymethods]
impl PyStartupBias {
    /// Rebuild from the fields in declaration order (what pickling uses).
    #[new]
    #[pyo3(signature = (bias, gradient, drift, covariance, std, residuals, unit_covariance, sigma, sigma_estimated, dof, condition, azimuth_deg, t, t_ref, names, sigma_theta=0.0, azimuth_covariance=None, chi2_scale=1.0, chi2_dof=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        bias: PyReadonlyArray1<'_, f64>,
        gradient: PyReadonlyArray1<'_, f64>,
        drift: Option<PyReadonlyArray1<'_, f64>>,
        covariance: PyReadonlyArray2<'_, f64>,
        std: PyReadonlyArray1<'_, f64>,
        residuals: PyReadonlyArray2<'_, f64>,
        unit_covariance: PyReadonlyArray2<'_, f64>,
        sigma: Option<PyReadonlyArray1<'_, f64>>,
        sigma_estimated: bool,
        dof: usize,
        condition: f64,
        azimuth_deg: PyReadonlyArray1<'_, f64>,
        t: Option<PyReadonlyArray1<'_, f64>>,
        t_ref: Option<f64>,
        names: Vec<String>,
        sigma_theta: f64,
        azimuth_covariance: Option<PyReadonlyArray2<'_, f64>>,
        chi2_scale: f64,
        chi2_dof: Option<f64>,
    ) -> PyResult<Self> {
        let p = names.len();
        if bias.len() != 2
            || gradient.len() != 2
            || covariance.shape() != [p, p]
            || std.len() != p
            || azimuth_covariance
                .as_ref()
                .is_some_and(|a| a.shape() != [p, p])
        {
            return Err(CalibrationError::new_err(
                "StartupBias fields have inconsistent shapes",
            ));
        }
        Ok(PyStartupBias {
            bias: frozen_copy1(&bias),
            gradient: frozen_copy1(&gradient),
            drift: drift.as_ref().map(frozen_copy1),
            covariance: frozen_copy2(&covariance),
            std: frozen_copy1(&std),
            residuals: frozen_copy2(&residuals),
            unit_covariance: frozen_copy2(&unit_covariance),
            sigma: sigma.as_ref().map(frozen_copy1),
            sigma_estimated,
            dof,
            condition,
            azimuth_deg: frozen_copy1(&azimuth_deg),
            t: t.as_ref().map(frozen_copy1),
            t_ref,
            names,
            sigma_theta,
            azimuth_covariance: match &azimuth_covariance {
                Some(a) => frozen_copy2(a),
                None => frozen2(py, vec![0.0; p * p], p, p),
            },
            chi2_scale,
            chi2_dof: chi2_dof.unwrap_or(dof as f64),
        })
    }

    /// Pickle support: the class (a Python subclass included) and the fields.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyTuple>> {
        let py = slf.py();
        let s = slf.get();
        let args = (
            s.bias.clone_ref(py),
            s.gradient.clone_ref(py),
            s.drift.as_ref().map(|a| a.clone_ref(py)),
            s.covariance.clone_ref(py),
            s.std.clone_ref(py),
            s.residuals.clone_ref(py),
            s.unit_covariance.clone_ref(py),
            s.sigma.as_ref().map(|a| a.clone_ref(py)),
            s.sigma_estimated,
            s.dof,
            s.condition,
            s.azimuth_deg.clone_ref(py),
        );
        let rest = (
            s.t.as_ref().map(|a| a.clone_ref(py)),
            s.t_ref,
            s.names.clone(),
            s.sigma_theta,
            s.azimuth_covariance.clone_ref(py),
            s.chi2_scale,
            s.chi2_dof,
        );
        let all = args
            .into_pyobject(py)?
            .add(rest.into_pyobject(py)?)?
            .cast_into::<PyTuple>()?;
        PyTuple::new(py, [slf.get_type().into_any(), all.into_any()])
    }
}

/// Start-up least squares from azimuths in degrees; `sigma` the noise std of each average
/// (E), or `None` to estimate it from the residuals; `sigma_theta_deg` the std of independent
/// azimuth errors (deg) whose first-order effect is added to the covariance.
#[pyfunction]
#[pyo3(signature = (azimuth_deg, outputs, sigma=None, t=None, t_ref=None, sigma_theta_deg=0.0))]
pub fn startup_bias_raw(
    azimuth_deg: PyReadonlyArray1<'_, f64>,
    outputs: PyReadonlyArray2<'_, f64>,
    sigma: Option<PyReadonlyArray1<'_, f64>>,
    t: Option<PyReadonlyArray1<'_, f64>>,
    t_ref: Option<f64>,
    sigma_theta_deg: f64,
) -> PyResult<PyStartupBias> {
    let az = vec1(&azimuth_deg);
    let y = pairs(&outputs, "outputs")?;
    let sd = sigma.as_ref().map(vec1);
    let ts = t.as_ref().map(vec1);
    let tr = match (&ts, t_ref) {
        (Some(_), Some(r)) => Some(r),
        (Some(t), None) => Some(t.iter().sum::<f64>() / t.len().max(1) as f64),
        (None, _) => None,
    };
    let fit = g::startup_bias(
        &radians(&az),
        &y,
        ts.as_deref(),
        tr.unwrap_or(0.0),
        sd.as_deref(),
        sigma_theta_deg.to_radians(),
    )?;
    let input = StartupInput {
        azimuth_deg: az,
        t: ts,
        t_ref: tr,
    };
    Ok((fit, input).into())
}

/// Predicted accuracy of a start-up sequence; the Python `accelcal.StartupPrediction`
/// subclasses it. Every array is read-only.
#[pyclass(
    name = "StartupPredictionCore",
    module = "accelcal._core",
    frozen,
    get_all,
    subclass
)]
pub struct PyStartupPrediction {
    covariance: Py<PyArray2<f64>>,
    azimuth_covariance: Py<PyArray2<f64>>,
    total_covariance: Py<PyArray2<f64>>,
    std: Py<PyArray1<f64>>,
    closed_form_variance: f64,
    condition: f64,
    names: Vec<String>,
}

impl From<g::StartupPrediction> for PyStartupPrediction {
    fn from(f: g::StartupPrediction) -> Self {
        Python::attach(|py| {
            let p = f.std.len();
            PyStartupPrediction {
                covariance: frozen2(py, f.covariance, p, p),
                azimuth_covariance: frozen2(py, f.azimuth_covariance, p, p),
                total_covariance: frozen2(py, f.total_covariance, p, p),
                std: frozen1(py, f.std),
                closed_form_variance: f.closed_form_variance,
                condition: f.condition,
                names: names(p),
            }
        })
    }
}

#[pymethods]
impl PyStartupPrediction {
    /// Rebuild from the fields in declaration order (what pickling uses).
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        covariance: PyReadonlyArray2<'_, f64>,
        azimuth_covariance: PyReadonlyArray2<'_, f64>,
        total_covariance: PyReadonlyArray2<'_, f64>,
        std: PyReadonlyArray1<'_, f64>,
        closed_form_variance: f64,
        condition: f64,
        names: Vec<String>,
    ) -> Self {
        PyStartupPrediction {
            covariance: frozen_copy2(&covariance),
            azimuth_covariance: frozen_copy2(&azimuth_covariance),
            total_covariance: frozen_copy2(&total_covariance),
            std: frozen_copy1(&std),
            closed_form_variance,
            condition,
            names,
        }
    }

    /// Pickle support: the class (a Python subclass included) and the fields.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyTuple>> {
        let py = slf.py();
        let s = slf.get();
        let args = (
            s.covariance.clone_ref(py),
            s.azimuth_covariance.clone_ref(py),
            s.total_covariance.clone_ref(py),
            s.std.clone_ref(py),
            s.closed_form_variance,
            s.condition,
            s.names.clone(),
        )
            .into_pyobject(py)?;
        PyTuple::new(py, [slf.get_type().into_any(), args.into_any()])
    }
}

/// Predicted covariances of a design from azimuths in degrees (`t` switches the drift model
/// on, referenced to `t_ref`, default the mean time); `gradient` the navigation-frame
/// `(I, C)` in E, else `gradient_magnitude`; `sigma_theta_deg` the azimuth error std.
#[pyfunction]
#[pyo3(signature = (azimuth_deg, dwell_std, t=None, t_ref=None, gradient=None, gradient_magnitude=0.0, sigma_theta_deg=0.0))]
pub fn startup_predict_raw(
    azimuth_deg: PyReadonlyArray1<'_, f64>,
    dwell_std: PyReadonlyArray1<'_, f64>,
    t: Option<PyReadonlyArray1<'_, f64>>,
    t_ref: Option<f64>,
    gradient: Option<[f64; 2]>,
    gradient_magnitude: f64,
    sigma_theta_deg: f64,
) -> PyResult<PyStartupPrediction> {
    let th = radians(&vec1(&azimuth_deg));
    let sd = vec1(&dwell_std);
    let ts = t.as_ref().map(vec1);
    let tr = match (&ts, t_ref) {
        (Some(_), Some(r)) => r,
        (Some(t), None) => t.iter().sum::<f64>() / t.len().max(1) as f64,
        (None, _) => 0.0,
    };
    let prior = match gradient {
        Some(v) => GradientPrior::Vector(v),
        None => GradientPrior::Magnitude(gradient_magnitude),
    };
    let pr = g::predict_startup(
        &th,
        ts.as_deref(),
        tr,
        &sd,
        prior,
        sigma_theta_deg.to_radians(),
    )?;
    Ok(pr.into())
}

/// Per-dwell inline and cross channels from raw streams; the Python `accelcal.Demodulated`
/// subclasses it. Every array is read-only.
#[pyclass(
    name = "DemodulatedCore",
    module = "accelcal._core",
    frozen,
    get_all,
    subclass
)]
pub struct PyDemodulated {
    /// Inline channel per dwell, E.
    #[pyo3(name = "inline_E")]
    inline_e: Py<PyArray1<f64>>,
    /// Cross channel per dwell, E.
    #[pyo3(name = "cross_E")]
    cross_e: Py<PyArray1<f64>>,
    #[pyo3(name = "std_inline_E")]
    std_inline_e: Py<PyArray1<f64>>,
    #[pyo3(name = "std_cross_E")]
    std_cross_e: Py<PyArray1<f64>>,
    start: Py<PyArray1<i64>>,
    stop: Py<PyArray1<i64>>,
    revolutions: Py<PyArray1<i64>>,
    resid_rms: Py<PyArray1<f64>>,
    nuisance: Py<PyArray2<f64>>,
    t: Option<Py<PyArray1<f64>>>,
}

impl From<(Vec<g::DemodDwell>, Option<Vec<f64>>)> for PyDemodulated {
    fn from((out, t): (Vec<g::DemodDwell>, Option<Vec<f64>>)) -> Self {
        Python::attach(|py| {
            let col = |f: &dyn Fn(&g::DemodDwell) -> f64| -> Py<PyArray1<f64>> {
                frozen1(py, out.iter().map(f).collect())
            };
            let icol = |f: &dyn Fn(&g::DemodDwell) -> i64| -> Py<PyArray1<i64>> {
                frozen1(py, out.iter().map(f).collect())
            };
            PyDemodulated {
                inline_e: col(&|o| o.inline_e),
                cross_e: col(&|o| o.cross_e),
                std_inline_e: col(&|o| o.std_e[0]),
                std_cross_e: col(&|o| o.std_e[1]),
                start: icol(&|o| o.start as i64),
                stop: icol(&|o| o.stop as i64),
                revolutions: icol(&|o| o.revolutions as i64),
                resid_rms: col(&|o| o.resid_rms),
                nuisance: frozen2(
                    py,
                    out.iter().flat_map(|o| o.nuisance).collect(),
                    out.len(),
                    3,
                ),
                t: t.map(|t| frozen1(py, t)),
            }
        })
    }
}

#[pymethods]
impl PyDemodulated {
    /// Rebuild from the fields in declaration order (what pickling uses).
    #[new]
    #[pyo3(signature = (inline_E, cross_E, std_inline_E, std_cross_E, start, stop, revolutions, resid_rms, nuisance, t))]
    #[allow(clippy::too_many_arguments, non_snake_case)]
    fn new(
        inline_E: PyReadonlyArray1<'_, f64>,
        cross_E: PyReadonlyArray1<'_, f64>,
        std_inline_E: PyReadonlyArray1<'_, f64>,
        std_cross_E: PyReadonlyArray1<'_, f64>,
        start: PyReadonlyArray1<'_, i64>,
        stop: PyReadonlyArray1<'_, i64>,
        revolutions: PyReadonlyArray1<'_, i64>,
        resid_rms: PyReadonlyArray1<'_, f64>,
        nuisance: PyReadonlyArray2<'_, f64>,
        t: Option<PyReadonlyArray1<'_, f64>>,
    ) -> Self {
        PyDemodulated {
            inline_e: frozen_copy1(&inline_E),
            cross_e: frozen_copy1(&cross_E),
            std_inline_e: frozen_copy1(&std_inline_E),
            std_cross_e: frozen_copy1(&std_cross_E),
            start: frozen_copy1(&start),
            stop: frozen_copy1(&stop),
            revolutions: frozen_copy1(&revolutions),
            resid_rms: frozen_copy1(&resid_rms),
            nuisance: frozen_copy2(&nuisance),
            t: t.as_ref().map(frozen_copy1),
        }
    }

    /// Pickle support: the class (a Python subclass included) and the fields.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyTuple>> {
        let py = slf.py();
        let s = slf.get();
        let args = (
            s.inline_e.clone_ref(py),
            s.cross_e.clone_ref(py),
            s.std_inline_e.clone_ref(py),
            s.std_cross_e.clone_ref(py),
            s.start.clone_ref(py),
            s.stop.clone_ref(py),
            s.revolutions.clone_ref(py),
            s.resid_rms.clone_ref(py),
            s.nuisance.clone_ref(py),
            s.t.as_ref().map(|a| a.clone_ref(py)),
        )
            .into_pyobject(py)?;
        PyTuple::new(py, [slf.get_type().into_any(), args.into_any()])
    }
}

/// 2-omega demodulation of `(N, 4)` streams per dwell (`t` the sample times, s, gives each
/// dwell's mid time).
#[pyfunction]
#[pyo3(signature = (accel, phase, bounds, radius_m, t=None))]
pub fn demodulate_raw(
    py: Python<'_>,
    accel: &Bound<'_, PyAny>,
    phase: PyReadonlyArray1<'_, f64>,
    bounds: PyReadonlyArray2<'_, i64>,
    radius_m: f64,
    t: Option<PyReadonlyArray1<'_, f64>>,
) -> PyResult<PyDemodulated> {
    let arr = SampleArray::extract(accel)?;
    let b = bounds_from(&bounds)?;
    let ph = cow1(&phase);
    let out = with_view!(&arr, v => py.detach(|| g::demodulate(&v, &ph, &b, radius_m)))?;
    let tm = match &t {
        Some(t) => {
            let tv = vec1(t);
            if tv.len() != ph.len() {
                return Err(CalibrationError::new_err(format!(
                    "t must have shape ({},) to match accel; got ({},)",
                    ph.len(),
                    tv.len()
                )));
            }
            Some(g::mid_times(&tv, &out)?)
        }
        None => None,
    };
    Ok((out, tm).into())
}

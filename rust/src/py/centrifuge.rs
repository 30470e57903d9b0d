//! Bindings of the centrifuge calibration core.

use numpy::{PyArray1, PyArray2, PyReadonlyArray1, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyTuple;

use super::convert::{frozen1, frozen2, frozen_copy1, frozen_copy2, rows3, vec1};
use super::CalibrationError;
use crate::centrifuge::{
    check_units, correct, fit, CentrifugeData, CentrifugeFit as CoreFit, FitOptions, LeverArm,
    Method, ModelOptions,
};

fn parse_method(method: &str) -> PyResult<Method> {
    match method {
        "nls" => Ok(Method::Nls),
        "taylor-paper" => Ok(Method::TaylorPaper),
        m => Err(CalibrationError::new_err(format!(
            "unknown method {m:?}; use 'nls' or 'taylor-paper'"
        ))),
    }
}

fn parse_model(k3: bool, misalignment: bool, lever_arm: Option<&str>) -> PyResult<ModelOptions> {
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
    Ok(ModelOptions {
        k3,
        misalignment,
        lever,
    })
}

/// The settings a fit ran with (kept with the result).
#[derive(Debug, Clone)]
pub struct Settings {
    pub method: String,
    pub radius: f64,
    pub g: f64,
    pub model: ModelOptions,
    pub noise_known: bool,
    pub labels: Vec<String>,
}

/// Result of one centrifuge fit; the Python `accelcal.CentrifugeFit` subclasses it (adds
/// views and text). Every array is read-only.
#[pyclass(
    name = "CentrifugeFitCore",
    module = "accelcal._core",
    frozen,
    get_all,
    subclass
)]
pub struct PyCentrifugeFit {
    /// Parameters in the order of `names` (S, b g, K2 g/g^2 [, K3] [, angles rad] [, lever m]).
    params: Py<PyArray1<f64>>,
    names: Vec<String>,
    /// `(p, p)`, scaled by the residual variance unless the noise was given.
    covariance: Py<PyArray2<f64>>,
    std: Py<PyArray1<f64>>,
    /// Norm residual of every row, g (outliers included; inf where not invertible).
    residuals: Py<PyArray1<f64>>,
    outliers: Py<PyArray1<i64>>,
    residual_rms: f64,
    screen_sigma: f64,
    studentized: Py<PyArray1<f64>>,
    threshold: f64,
    residual_std: Py<PyArray1<f64>>,
    draws: usize,
    singular_values: Py<PyArray1<f64>>,
    condition_number: f64,
    iterations: usize,
    converged: bool,
    taylor_coefficients: Option<Py<PyArray1<f64>>>,
    method: String,
    radius: f64,
    g: f64,
    fit_k3: bool,
    fit_misalignment: bool,
    lever_model: Option<String>,
    noise_known: bool,
    labels: Vec<String>,
}

impl From<(CoreFit, Settings)> for PyCentrifugeFit {
    fn from((f, s): (CoreFit, Settings)) -> Self {
        Python::attach(|py| {
            let p = f.params.len();
            let std = (0..p)
                .map(|j| f.covariance[j * p + j].max(0.0).sqrt())
                .collect();
            PyCentrifugeFit {
                params: frozen1(py, f.params),
                names: f.names,
                covariance: frozen2(py, f.covariance, p, p),
                std: frozen1(py, std),
                residuals: frozen1(py, f.residuals),
                outliers: frozen1(py, f.outliers.iter().map(|&k| k as i64).collect()),
                residual_rms: f.residual_rms,
                screen_sigma: f.screen_sigma,
                studentized: frozen1(py, f.studentized),
                threshold: f.threshold,
                residual_std: frozen1(py, f.residual_std),
                draws: f.draws,
                singular_values: frozen1(py, f.singular_values),
                condition_number: f.condition,
                iterations: f.iterations,
                converged: f.converged,
                taylor_coefficients: f.taylor_coefficients.map(|c| frozen1(py, c)),
                method: s.method,
                radius: s.radius,
                g: s.g,
                fit_k3: s.model.k3,
                fit_misalignment: s.model.misalignment,
                lever_model: match s.model.lever {
                    LeverArm::None => None,
                    LeverArm::Along => Some("along".into()),
                    LeverArm::Full => Some("full".into()),
                },
                noise_known: s.noise_known,
                labels: s.labels,
            }
        })
    }
}

impl PyCentrifugeFit {
    /// The same result, sharing every (read-only) array.
    fn share(&self, py: Python<'_>) -> Self {
        PyCentrifugeFit {
            params: self.params.clone_ref(py),
            names: self.names.clone(),
            covariance: self.covariance.clone_ref(py),
            std: self.std.clone_ref(py),
            residuals: self.residuals.clone_ref(py),
            outliers: self.outliers.clone_ref(py),
            residual_rms: self.residual_rms,
            screen_sigma: self.screen_sigma,
            studentized: self.studentized.clone_ref(py),
            threshold: self.threshold,
            residual_std: self.residual_std.clone_ref(py),
            draws: self.draws,
            singular_values: self.singular_values.clone_ref(py),
            condition_number: self.condition_number,
            iterations: self.iterations,
            converged: self.converged,
            taylor_coefficients: self.taylor_coefficients.as_ref().map(|a| a.clone_ref(py)),
            method: self.method.clone(),
            radius: self.radius,
            g: self.g,
            fit_k3: self.fit_k3,
            fit_misalignment: self.fit_misalignment,
            lever_model: self.lever_model.clone(),
            noise_known: self.noise_known,
            labels: self.labels.clone(),
        }
    }
}

#[pymethods]
impl PyCentrifugeFit {
    /// `CentrifugeFitCore(fit)`: the same result (arrays shared, not copied), for a Python
    /// subclass to wrap the core's result; `CentrifugeFitCore(*fields)`: rebuilt from its fields
    /// in declaration order (what pickling uses).
    #[new]
    #[pyo3(signature = (*args))]
    fn new(args: &Bound<'_, PyTuple>) -> PyResult<Self> {
        let py = args.py();
        if args.len() == 1 {
            let a = args.get_item(0)?;
            let f = a.cast::<PyCentrifugeFit>().map_err(|_| {
                CalibrationError::new_err("CentrifugeFit(fit) takes a centrifuge fit result")
            })?;
            return Ok(f.get().share(py));
        }
        if args.len() != 25 {
            return Err(CalibrationError::new_err(format!(
                "CentrifugeFit takes a fit result or its 25 fields; got {} arguments",
                args.len()
            )));
        }
        macro_rules! arg {
            ($i:expr) => {
                args.get_item($i)?.extract()?
            };
        }
        let params: PyReadonlyArray1<'_, f64> = arg!(0);
        let names: Vec<String> = arg!(1);
        let covariance: PyReadonlyArray2<'_, f64> = arg!(2);
        let std: PyReadonlyArray1<'_, f64> = arg!(3);
        let residuals: PyReadonlyArray1<'_, f64> = arg!(4);
        let outliers: PyReadonlyArray1<'_, i64> = arg!(5);
        let studentized: PyReadonlyArray1<'_, f64> = arg!(8);
        let residual_std: PyReadonlyArray1<'_, f64> = arg!(10);
        let singular_values: PyReadonlyArray1<'_, f64> = arg!(12);
        let taylor: Option<PyReadonlyArray1<'_, f64>> = arg!(16);
        let p = params.len();
        let k = residuals.len();
        if names.len() != p
            || covariance.shape() != [p, p]
            || std.len() != p
            || studentized.len() != k
            || residual_std.len() != k
        {
            return Err(CalibrationError::new_err(
                "CentrifugeFit fields have inconsistent shapes",
            ));
        }
        Ok(PyCentrifugeFit {
            params: frozen_copy1(&params),
            names,
            covariance: frozen_copy2(&covariance),
            std: frozen_copy1(&std),
            residuals: frozen_copy1(&residuals),
            outliers: frozen_copy1(&outliers),
            residual_rms: arg!(6),
            screen_sigma: arg!(7),
            studentized: frozen_copy1(&studentized),
            threshold: arg!(9),
            residual_std: frozen_copy1(&residual_std),
            draws: arg!(11),
            singular_values: frozen_copy1(&singular_values),
            condition_number: arg!(13),
            iterations: arg!(14),
            converged: arg!(15),
            taylor_coefficients: taylor.as_ref().map(frozen_copy1),
            method: arg!(17),
            radius: arg!(18),
            g: arg!(19),
            fit_k3: arg!(20),
            fit_misalignment: arg!(21),
            lever_model: arg!(22),
            noise_known: arg!(23),
            labels: arg!(24),
        })
    }

    /// Pickle support: the class (a Python subclass included) and the fields.
    fn __reduce__<'py>(slf: &Bound<'py, Self>) -> PyResult<Bound<'py, PyTuple>> {
        let py = slf.py();
        let s = slf.get();
        let args = (
            s.params.clone_ref(py),
            s.names.clone(),
            s.covariance.clone_ref(py),
            s.std.clone_ref(py),
            s.residuals.clone_ref(py),
            s.outliers.clone_ref(py),
            s.residual_rms,
            s.screen_sigma,
            s.studentized.clone_ref(py),
            s.threshold,
            s.residual_std.clone_ref(py),
            s.draws,
        );
        let args2 = (
            s.singular_values.clone_ref(py),
            s.condition_number,
            s.iterations,
            s.converged,
            s.taylor_coefficients.as_ref().map(|c| c.clone_ref(py)),
            s.method.clone(),
            s.radius,
            s.g,
        );
        let args3 = (
            s.fit_k3,
            s.fit_misalignment,
            s.lever_model.clone(),
            s.noise_known,
            s.labels.clone(),
        );
        let all = args
            .into_pyobject(py)?
            .add(args2.into_pyobject(py)?)?
            .add(args3.into_pyobject(py)?)?
            .cast_into::<PyTuple>()?;
        PyTuple::new(py, [slf.get_type().into_any(), all.into_any()])
    }
}

/// Centrifuge calibration (see `accelcal.fit_centrifuge`). `sigma`: per-axis output noise
/// `(k, 3)` in g.
#[pyfunction]
#[pyo3(signature = (outputs, omega, radius, g, method="nls", k3=false, misalignment=false, lever_arm=None, spin_axis=None, sigma=None, robust=true, outlier_k=5.0, sigma_floor=1e-9, max_draws=20000, seed=0, check_units=true, labels=None))]
#[allow(clippy::too_many_arguments)]
pub fn centrifuge_fit_raw(
    py: Python<'_>,
    outputs: PyReadonlyArray2<'_, f64>,
    omega: PyReadonlyArray1<'_, f64>,
    radius: f64,
    g: f64,
    method: &str,
    k3: bool,
    misalignment: bool,
    lever_arm: Option<&str>,
    spin_axis: Option<PyReadonlyArray2<'_, f64>>,
    sigma: Option<PyReadonlyArray2<'_, f64>>,
    robust: bool,
    outlier_k: f64,
    sigma_floor: f64,
    max_draws: usize,
    seed: u64,
    check_units: bool,
    labels: Option<Vec<String>>,
) -> PyResult<PyCentrifugeFit> {
    let model = parse_model(k3, misalignment, lever_arm)?;
    let out = rows3(&outputs, "outputs")?;
    let om = vec1(&omega);
    let sa = spin_axis
        .as_ref()
        .map(|a| rows3(a, "spin_axis"))
        .transpose()?;
    let sg = sigma.as_ref().map(|a| rows3(a, "sigma")).transpose()?;
    let opt = FitOptions {
        model,
        method: parse_method(method)?,
        robust,
        outlier_k,
        sigma_floor,
        check_units,
        max_draws,
        seed,
    };
    let labels = labels.unwrap_or_default();
    if !labels.is_empty() && labels.len() != out.len() {
        return Err(CalibrationError::new_err(format!(
            "labels has {} names for {} rows",
            labels.len(),
            out.len()
        )));
    }
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
    let settings = Settings {
        method: method.to_string(),
        radius,
        g,
        model,
        noise_known: sg.is_some(),
        labels,
    };
    Ok((res, settings).into())
}

/// A unit mistake found by [`centrifuge_unit_check_raw`]: (input, unit it looks like, unit it
/// should be in, conversion, scale factor after it, rms g of the fit after it).
type Finding = (String, String, String, String, f64, f64);

/// The unit check of the centrifuge fit: `None` when the units look right, else the scale
/// factor the outputs need as given and the conversions that explain it, best first.
#[pyfunction]
#[pyo3(signature = (outputs, omega, radius, g, robust=true, max_draws=20000, seed=0))]
#[allow(clippy::too_many_arguments)]
pub fn centrifuge_unit_check_raw(
    py: Python<'_>,
    outputs: PyReadonlyArray2<'_, f64>,
    omega: PyReadonlyArray1<'_, f64>,
    radius: f64,
    g: f64,
    robust: bool,
    max_draws: usize,
    seed: u64,
) -> PyResult<Option<(f64, Vec<Finding>)>> {
    let out = rows3(&outputs, "outputs")?;
    let om = vec1(&omega);
    let data = CentrifugeData {
        outputs: &out,
        omega: &om,
        radius,
        g,
        sigma: None,
        spin_axis: None,
    };
    crate::centrifuge::validate(&data, &ModelOptions::default())?;
    crate::centrifuge::check_gravity(g)?;
    let opt = FitOptions {
        robust,
        max_draws,
        seed,
        ..FitOptions::default()
    };
    let found = py.detach(|| check_units(&data, &opt));
    Ok(found.map(|u| {
        let f = u
            .findings
            .into_iter()
            .map(|f| {
                (
                    f.what.to_string(),
                    f.unit.to_string(),
                    f.want.to_string(),
                    f.fix.to_string(),
                    f.scale,
                    f.rms,
                )
            })
            .collect();
        (u.scale, f)
    }))
}

/// Specific force `(k, 3)` in g from outputs in g by exact inversion of fitted parameters.
#[pyfunction]
#[pyo3(signature = (params, outputs, k3=false, misalignment=false, lever_arm=None))]
pub fn centrifuge_correct_raw<'py>(
    py: Python<'py>,
    params: PyReadonlyArray1<'py, f64>,
    outputs: PyReadonlyArray2<'py, f64>,
    k3: bool,
    misalignment: bool,
    lever_arm: Option<&str>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    use numpy::IntoPyArray;
    let model = parse_model(k3, misalignment, lever_arm)?;
    let out = rows3(&outputs, "outputs")?;
    let f = correct(&model, &vec1(&params), &out)?;
    let k = f.len();
    let flat: Vec<f64> = f.into_iter().flatten().collect();
    let arr = ndarray::Array2::from_shape_vec((k, 3), flat)
        .map_err(|e| CalibrationError::new_err(e.to_string()))?;
    Ok(arr.into_pyarray(py))
}

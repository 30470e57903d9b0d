//! Bindings of the static-field calibration core: typed, frozen result classes.
//!
//! A result class's constructor is its computation (`StaticFit(means, g, ...)` fits,
//! `Prediction(force, sigma, ...)` predicts), so that the Python classes subclass them, and
//! they pickle as their inputs (`__getnewargs_ex__`): unpickling recomputes, which is
//! deterministic and bit-identical.

use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2,
    PyReadonlyArray3, PyUntypedArrayMethods,
};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyList, PyString, PyTuple};

use super::convert::{frozen1, frozen2, frozen_copy1, frozen_copy2, rows3, with_view, SampleArray};
use super::CalibrationError;
use crate::static_fit::{
    apply_inverse, apply_inverse_into, check_sigma_g, design_rows, fit_batch_sigma_g, fit_static,
    gravity_cov_entry, gravity_sensitivity, predict, BatchRow, FitSettings, Method, Model, Noise,
    Observability as CoreObservability, PARAM_NAMES,
};

// ------------------------------------------------------------------------------------------
// Argument checks: the name, the value received and the valid range in every message.

/// An optional argument that tells "not given" (the default) from an explicit `None`, so that
/// `max_iter=None` is refused with a clear message instead of meaning the default.
pub struct Given<'py>(Option<Bound<'py, PyAny>>);

impl<'a, 'py> FromPyObject<'a, 'py> for Given<'py> {
    type Error = PyErr;
    fn extract(obj: pyo3::Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        Ok(Given(Some(obj.to_owned())))
    }
}

const NOT_GIVEN: Given<'static> = Given(None);

fn describe(obj: &Bound<'_, PyAny>) -> String {
    obj.repr()
        .map(|r| r.to_string())
        .unwrap_or_else(|_| "?".into())
}

/// A float argument within `ok`, or a `CalibrationError` naming it and its range.
fn arg_f64(
    obj: &Bound<'_, PyAny>,
    name: &str,
    range: &str,
    ok: impl Fn(f64) -> bool,
) -> PyResult<f64> {
    arg_f64_with(obj, name, || range.to_string(), ok)
}

/// [`arg_f64`] with the range worded only for the error message.
fn arg_f64_with(
    obj: &Bound<'_, PyAny>,
    name: &str,
    range: impl FnOnce() -> String,
    ok: impl Fn(f64) -> bool,
) -> PyResult<f64> {
    let v = if let Ok(f) = obj.cast_exact::<pyo3::types::PyFloat>() {
        Some(f.value())
    } else if obj.is_instance_of::<pyo3::types::PyBool>() {
        None
    } else {
        obj.extract::<f64>().ok()
    };
    match v {
        Some(x) if ok(x) => Ok(x),
        _ => Err(CalibrationError::new_err(format!(
            "{name} must be {}; got {}",
            range(),
            describe(obj)
        ))),
    }
}

/// An integer argument in `[lo, hi]` (integral floats accepted), or a `CalibrationError`.
fn arg_int(obj: &Bound<'_, PyAny>, name: &str, lo: i64, hi: i64) -> PyResult<usize> {
    let v = if obj.is_instance_of::<pyo3::types::PyBool>() {
        None
    } else if let Ok(i) = obj.extract::<i64>() {
        Some(i)
    } else {
        obj.extract::<f64>()
            .ok()
            .filter(|x| x.is_finite() && x.fract() == 0.0 && x.abs() < 9e15)
            .map(|x| x as i64)
    };
    match v {
        Some(i) if (lo..=hi).contains(&i) => Ok(i as usize),
        _ => Err(CalibrationError::new_err(format!(
            "{name} must be an integer in [{lo}, {hi}]; got {}",
            describe(obj)
        ))),
    }
}

fn positive(obj: &Bound<'_, PyAny>, name: &str, what: &str) -> PyResult<f64> {
    arg_f64_with(
        obj,
        name,
        || format!("a positive, finite {what}"),
        |x| x > 0.0 && x.is_finite(),
    )
}

/// The optional std `sigma_g` of the reference gravity `g` (units of g): `None` when absent
/// or None, else non-negative, finite and at most 1 % of `g`.
fn sigma_g_arg(obj: Option<&Bound<'_, PyAny>>, g: f64) -> PyResult<Option<f64>> {
    match obj {
        Some(o) if !o.is_none() => {
            let x = arg_f64(
                o,
                "sigma_g",
                "a non-negative, finite std of the reference gravity (in the units of g)",
                |x| x >= 0.0 && x.is_finite(),
            )?;
            Ok(Some(check_sigma_g(x, g)?))
        }
        _ => Ok(None),
    }
}

fn check_g(obj: &Bound<'_, PyAny>, check: bool) -> PyResult<f64> {
    let g = positive(obj, "g", "reference gravity (e.g. 9.81 m/s^2)")?;
    if check {
        if let Some(why) = gravity_problem(g) {
            return Err(CalibrationError::new_err(why));
        }
    }
    Ok(g)
}

/// Why ``g`` cannot be a local gravity in m/s^2, in units of g or in cm/s^2, with what to do
/// (None when it can).
#[pyfunction]
pub fn gravity_problem(g: f64) -> Option<String> {
    crate::static_fit::implausible_g(g).map(|why| {
        format!(
            "{why}. Give g in the units the calibrated output should have, or turn this check \
             off (check_g=False) for a deliberate other value"
        )
    })
}

/// The entries of the symmetric covariance `m` row by row. It is stored by columns, but every
/// covariance the fit makes is symmetric to the bit (the lower triangle is mirrored, and the
/// unit conversion multiplies both triangles alike), so its storage is also its row-major
/// order: one copy instead of a walk over row views.
fn row_major_symmetric(m: &nalgebra::DMatrix<f64>) -> Vec<f64> {
    debug_assert!(
        m.is_square()
            && (0..m.nrows()).all(|i| (0..i).all(|j| {
                m[(i, j)].to_bits() == m[(j, i)].to_bits()
                    || (m[(i, j)].is_nan() && m[(j, i)].is_nan())
            }))
    );
    m.as_slice().to_vec()
}

/// `(k, 3)` float64 array argument (any strides).
fn means_arg<'py>(obj: &Bound<'py, PyAny>, name: &str) -> PyResult<PyReadonlyArray2<'py, f64>> {
    obj.extract::<PyReadonlyArray2<'py, f64>>().map_err(|_| {
        // An array says its dtype and shape (as Python prints them); anything else its type.
        let got = match (obj.getattr("dtype"), obj.getattr("shape")) {
            (Ok(d), Ok(s)) => format!(
                "{} array of shape {}",
                d.str().map(|x| x.to_string()).unwrap_or_default(),
                s.repr().map(|x| x.to_string()).unwrap_or_default()
            ),
            _ => obj
                .get_type()
                .name()
                .map(|n| n.to_string())
                .unwrap_or_default(),
        };
        CalibrationError::new_err(format!("{name} must be a (k, 3) float64 array; got {got}"))
    })
}

/// Refuse a dwell-mean variance `var` (one value for every dwell and axis) below what double
/// precision resolves in the means (the whitened problem would overflow): `sqrt(var)` must be
/// at least 1e-12 of the largest mean (NaN in the means: no test; the NaN is reported later).
fn resolvable(py: Python<'_>, var: f64, means: &[[f64; 3]]) -> PyResult<()> {
    let mag = means.iter().flatten().fold(0.0f64, |m, x| {
        if m.is_nan() || x.is_nan() {
            f64::NAN
        } else {
            m.max(x.abs())
        }
    });
    let floor = (1e-12 * mag) * (1e-12 * mag);
    if !(mag > 0.0 && var < floor) {
        return Ok(());
    }
    // The numbers as Python formats them (`format(x, ".3g")`), as for every message of the
    // Python layer.
    let g3 = |x: f64| -> PyResult<String> {
        pyo3::types::PyString::new(py, "{:.3g}")
            .call_method1("format", (x,))?
            .extract::<String>()
    };
    Err(CalibrationError::new_err(format!(
        "sigma = {} is below the double-precision resolution of dwell means of size {} (sigma \
         must be >= {}, 1e-12 of the largest mean): give the std of each dwell mean in the \
         means' units",
        g3(var.sqrt())?,
        g3(mag)?,
        g3(1e-12 * mag)?
    )))
}

fn settings_from(
    model: &str,
    method: &str,
    start: Option<Vec<f64>>,
    max_iter: &Given<'_>,
    raise_degenerate: bool,
    degenerate_std: &Given<'_>,
    weak_std: &Given<'_>,
) -> PyResult<FitSettings> {
    let mut s = FitSettings::new(Model::parse(model)?, Method::parse(method)?);
    s.start = start;
    s.raise_degenerate = raise_degenerate;
    if let Some(o) = &max_iter.0 {
        s.max_iter = arg_int(o, "max_iter", 1, 100_000)?;
    }
    if let Some(o) = &degenerate_std.0 {
        s.degenerate_std = positive(o, "degenerate_std", "relative std (default 3)")?;
    }
    if let Some(o) = &weak_std.0 {
        s.weak_std = positive(o, "weak_std", "relative std (default 1e-3)")?;
    }
    Ok(s)
}

/// A read-only copy of `v`.
fn arr1(py: Python<'_>, v: &[f64]) -> Py<PyArray1<f64>> {
    frozen1(py, v.to_vec())
}

/// A read-only `(rows, cols)` array of `f(i, j)`.
fn arr2(
    py: Python<'_>,
    rows: usize,
    cols: usize,
    f: impl Fn(usize, usize) -> f64,
) -> Py<PyArray2<f64>> {
    frozen2(
        py,
        (0..rows * cols).map(|k| f(k / cols, k % cols)).collect(),
        rows,
        cols,
    )
}

fn flat(v: &[[f64; 3]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

// ------------------------------------------------------------------------------------------
// Observability

/// What the dwells can determine: the SVD of the whitened Jacobian in comparable units
/// (scale factors and misalignments relative, biases in units of g).
#[pyclass(name = "Observability", module = "accelcal._core", frozen, get_all)]
pub struct PyObservability {
    /// Singular values, descending.
    singular_values: Py<PyArray1<f64>>,
    /// `s_max / s_min`.
    condition: f64,
    /// Predicted std of each parameter (comparable units).
    std_comparable: Py<PyArray1<f64>>,
    /// Least determined combination (unit vector, comparable units).
    weakest: Py<PyArray1<f64>>,
    /// Predicted std of that combination (comparable units).
    weakest_std: f64,
    /// Exactly or numerically undetermined.
    degenerate: bool,
    /// Some parameter is weakly determined.
    weak: bool,
    /// The weakest combination in parameter names.
    combination: String,
}

impl PyObservability {
    fn from_core(py: Python<'_>, o: &CoreObservability) -> Self {
        PyObservability {
            singular_values: arr1(py, &o.singular_values),
            condition: o.condition,
            std_comparable: arr1(py, &o.std_comparable),
            weakest: arr1(py, &o.weakest),
            weakest_std: o.weakest_std,
            degenerate: o.degenerate,
            weak: o.weak,
            combination: o.combination.clone(),
        }
    }
}

#[pymethods]
impl PyObservability {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        singular_values: PyReadonlyArray1<'_, f64>,
        condition: f64,
        std_comparable: PyReadonlyArray1<'_, f64>,
        weakest: PyReadonlyArray1<'_, f64>,
        weakest_std: f64,
        degenerate: bool,
        weak: bool,
        combination: String,
    ) -> Self {
        // Read-only, as made (an unpickled or copied result came back writable).
        PyObservability {
            singular_values: frozen_copy1(&singular_values),
            condition,
            std_comparable: frozen_copy1(&std_comparable),
            weakest: frozen_copy1(&weakest),
            weakest_std,
            degenerate,
            weak,
            combination,
        }
    }

    fn __getnewargs__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        PyTuple::new(
            py,
            [
                self.singular_values.clone_ref(py).into_any(),
                self.condition.into_pyobject(py)?.into_any().unbind(),
                self.std_comparable.clone_ref(py).into_any(),
                self.weakest.clone_ref(py).into_any(),
                self.weakest_std.into_pyobject(py)?.into_any().unbind(),
                pyo3::types::PyBool::new(py, self.degenerate)
                    .to_owned()
                    .into_any()
                    .unbind(),
                pyo3::types::PyBool::new(py, self.weak)
                    .to_owned()
                    .into_any()
                    .unbind(),
                self.combination
                    .clone()
                    .into_pyobject(py)?
                    .into_any()
                    .unbind(),
            ],
        )
    }

    fn __repr__(&self) -> String {
        format!(
            "Observability(condition={:.3e}, weakest_std={:.3e}, combination={:?}, degenerate={})",
            self.condition, self.weakest_std, self.combination, self.degenerate
        )
    }
}

// ------------------------------------------------------------------------------------------
// StaticFit

/// One static fit (the Python `accelcal.StaticFit` subclasses it). Constructing it fits
/// `means` (k, 3) to the reference gravity `g`; every field is in the caller's units.
///
/// The array fields are kept as Rust values and become read-only NumPy arrays on first
/// access (then the same array on every access): a fit whose arrays are never read costs
/// no array allocation.
#[pyclass(name = "StaticFit", module = "accelcal._core", frozen, subclass)]
pub struct PyStaticFit {
    /// Sensor model: "lower", "diag" or "upper".
    #[pyo3(get)]
    model: &'static str,
    /// Estimation method.
    #[pyo3(get)]
    method: &'static str,
    /// Reference gravity (units of the calibrated output).
    #[pyo3(get)]
    g: f64,
    /// Dwell means (k, 3), output units (a copy of the input).
    means_v: Vec<[f64; 3]>,
    means: PyOnceLock<Py<PyArray2<f64>>>,
    /// Variance of each dwell mean per axis, output units squared: one value for every dwell
    /// and axis, or (k, 3); None when the noise is estimated.
    #[pyo3(get)]
    var: Option<Py<PyAny>>,
    /// Number of parameters (9, or 6 for "diag").
    np: usize,
    /// Parameters `[sx, sy, sz, bx, by, bz, m1, m2, m3]` (p = 6 for "diag").
    vector_v: [f64; 9],
    vector: PyOnceLock<Py<PyArray1<f64>>>,
    /// Start of GN/LM (or the linear method's own solution).
    start_v: [f64; 9],
    start: PyOnceLock<Py<PyArray1<f64>>>,
    /// Where the start came from: "quadric", "linear-paper", "user" or "fallback".
    #[pyo3(get)]
    start_source: &'static str,
    /// Why the linear solution failed (when the start is the fallback).
    #[pyo3(get)]
    start_error: Option<String>,
    /// The start given by the caller, if any.
    #[pyo3(get)]
    user_start: Option<Vec<f64>>,
    /// `(J^T W J)^-1` (p, p) row-major.
    covariance_v: Vec<f64>,
    covariance_unscaled: PyOnceLock<Py<PyArray2<f64>>>,
    /// `|a_k| - g` per dwell (units of g).
    residuals_v: Vec<f64>,
    residuals: PyOnceLock<Py<PyArray1<f64>>>,
    /// Predicted std of each residual (units of g).
    sigma_residual_v: Vec<f64>,
    sigma_residual: PyOnceLock<Py<PyArray1<f64>>>,
    /// Minimised cost `sum e_k^2`.
    #[pyo3(get)]
    cost: f64,
    /// Degrees of freedom `k - p`.
    #[pyo3(get)]
    dof: usize,
    /// chi2/dof of a known noise model, or the estimated per-axis variance of a dwell mean
    /// (output units squared) when the noise is estimated. NaN when `dof == 0`.
    #[pyo3(get)]
    chi2_dof: f64,
    /// GN/LM iterations.
    #[pyo3(get)]
    iterations: usize,
    /// The minimum was reached (within 1e-3 parameter std).
    #[pyo3(get)]
    converged: bool,
    /// Squared distance, in parameter std, to the minimum of the local quadratic model.
    #[pyo3(get)]
    decrement: f64,
    /// The noise model was known (not estimated from the residuals).
    #[pyo3(get)]
    noise_known: bool,
    /// Some parameter is weakly determined (predicted std above `weak_std`).
    #[pyo3(get)]
    weak: bool,
    /// The dwells cannot determine some combination (predicted std above `degenerate_std`).
    #[pyo3(get)]
    degenerate: bool,
    /// Predicted std of each parameter in comparable units.
    predicted_std_v: [f64; 9],
    predicted_std_relative: PyOnceLock<Py<PyArray1<f64>>>,
    /// Predicted std of the least determined combination (comparable units).
    #[pyo3(get)]
    weakest_std: f64,
    /// Iteration limit used.
    #[pyo3(get)]
    max_iter: usize,
    /// A degenerate design raised (True) or was returned with `degenerate` set (False).
    #[pyo3(get)]
    raise_degenerate: bool,
    /// Threshold of `degenerate` (comparable units).
    #[pyo3(get)]
    degenerate_std: f64,
    /// Threshold of `weak` (comparable units).
    #[pyo3(get)]
    weak_std: f64,
    /// `g` was checked for plausibility.
    #[pyo3(get)]
    check_g: bool,
    /// How the dwell weights were obtained (text from the caller).
    #[pyo3(get)]
    noise_model: Py<PyString>,
    /// Units of the raw output (text from the caller).
    #[pyo3(get)]
    input_units: Py<PyString>,
    /// Nominal model for the "before" norm statistics (any object; None).
    #[pyo3(get)]
    nominal: Option<Py<PyAny>>,
    /// Std of the reference gravity (units of g), or None: its covariance
    /// (`covariance_gravity`) is part of every reported covariance but `covariance_unscaled`.
    #[pyo3(get)]
    sigma_g: Option<f64>,
    covariance_gravity: PyOnceLock<Py<PyArray2<f64>>>,
}

/// The noise argument: one variance for every dwell and axis, a `(k, 3)` array, or none.
enum VarArg {
    Estimated,
    Uniform(f64),
    PerDwell(Vec<[f64; 3]>),
}

impl VarArg {
    fn from_py(var: Option<&Bound<'_, PyAny>>) -> PyResult<VarArg> {
        let Some(v) = var.filter(|v| !v.is_none()) else {
            return Ok(VarArg::Estimated);
        };
        if let Ok(x) = v.cast_exact::<pyo3::types::PyFloat>() {
            // The common case (one variance from a scalar sigma): no failed array extraction.
            let x = x.value();
            if x >= 0.0 && x.is_finite() {
                return Ok(VarArg::Uniform(x));
            }
        }
        if let Ok(a) = v.extract::<PyReadonlyArray2<'_, f64>>() {
            return Ok(VarArg::PerDwell(rows3(&a, "var")?));
        }
        Ok(VarArg::Uniform(arg_f64(
            v,
            "var",
            "a non-negative, finite variance of a dwell mean or a (k, 3) float64 array",
            |x| x >= 0.0 && x.is_finite(),
        )?))
    }

    fn noise(&self) -> Noise<'_> {
        match self {
            VarArg::Estimated => Noise::Estimated,
            VarArg::Uniform(v) => Noise::Uniform([*v; 3]),
            VarArg::PerDwell(v) => Noise::Known(v),
        }
    }
}

#[pymethods]
impl PyStaticFit {
    #[new]
    #[pyo3(signature = (means, g, model="lower", method="lm", var=None, start=None, max_iter=NOT_GIVEN, raise_degenerate=true, degenerate_std=NOT_GIVEN, weak_std=NOT_GIVEN, check_g=true, noise_model=None, input_units=None, nominal=None, sigma_g=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        means: &Bound<'_, PyAny>,
        g: &Bound<'_, PyAny>,
        model: &str,
        method: &str,
        var: Option<&Bound<'_, PyAny>>,
        start: Option<Vec<f64>>,
        max_iter: Given<'_>,
        raise_degenerate: bool,
        degenerate_std: Given<'_>,
        weak_std: Given<'_>,
        check_g: bool,
        noise_model: Option<Bound<'_, PyString>>,
        input_units: Option<Bound<'_, PyString>>,
        nominal: Option<Py<PyAny>>,
        sigma_g: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let gv = self::check_g(g, check_g)?;
        let sigma_g = sigma_g_arg(sigma_g, gv)?;
        let ma = means_arg(means, "dwell means")?;
        let m = rows3(&ma, "dwell means")?;
        drop(ma);
        let va = VarArg::from_py(var)?;
        if let VarArg::Uniform(v) = va {
            resolvable(py, v, &m)?;
        }
        let s = settings_from(
            model,
            method,
            start.clone(),
            &max_iter,
            raise_degenerate,
            &degenerate_std,
            &weak_std,
        )?;
        let f = fit_static(&m, gv, &va.noise(), &s)?;
        let np = f.params.len();
        let k = m.len();
        let mut vector_v = [0.0; 9];
        vector_v[..np].copy_from_slice(&f.params);
        let mut start_v = [0.0; 9];
        start_v[..np].copy_from_slice(&f.start);
        let mut predicted_std_v = [0.0; 9];
        predicted_std_v[..np].copy_from_slice(f.summary.std());
        Ok(PyStaticFit {
            model: f.model.name(),
            method: method_name(f.method),
            g: gv,
            means_v: m,
            means: PyOnceLock::new(),
            var: match va {
                VarArg::Estimated => None,
                VarArg::Uniform(x) => Some(x.into_pyobject(py)?.into_any().unbind()),
                VarArg::PerDwell(v) => Some(frozen2(py, flat(&v), k, 3).into_any()),
            },
            np,
            vector_v,
            vector: PyOnceLock::new(),
            start_v,
            start: PyOnceLock::new(),
            start_source: f.start_source.name(),
            start_error: f.start_error,
            user_start: start,
            covariance_v: row_major_symmetric(&f.covariance),
            covariance_unscaled: PyOnceLock::new(),
            residuals_v: f.residuals,
            residuals: PyOnceLock::new(),
            sigma_residual_v: f.sigma_r,
            sigma_residual: PyOnceLock::new(),
            cost: f.cost,
            dof: f.dof,
            chi2_dof: f.chi2_dof,
            iterations: f.iterations,
            converged: f.converged,
            decrement: f.decrement,
            noise_known: f.noise_known,
            weak: f.summary.weak,
            degenerate: f.summary.degenerate,
            predicted_std_v,
            predicted_std_relative: PyOnceLock::new(),
            weakest_std: f.summary.weakest_std,
            max_iter: s.max_iter,
            raise_degenerate,
            degenerate_std: s.degenerate_std,
            weak_std: s.weak_std,
            check_g,
            // The caller's str objects themselves (no copy).
            noise_model: noise_model
                .unwrap_or_else(|| pyo3::intern!(py, "").clone())
                .unbind(),
            input_units: input_units
                .unwrap_or_else(|| pyo3::intern!(py, "").clone())
                .unbind(),
            nominal,
            sigma_g,
            covariance_gravity: PyOnceLock::new(),
        })
    }

    /// Dwell means (k, 3), output units (a copy of the input).
    #[getter]
    fn means<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        self.means
            .get_or_init(py, || {
                frozen2(py, flat(&self.means_v), self.means_v.len(), 3)
            })
            .bind(py)
            .clone()
    }

    /// Parameters `[sx, sy, sz, bx, by, bz, m1, m2, m3]` (p = 6 for "diag").
    #[getter]
    fn vector<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.vector
            .get_or_init(py, || arr1(py, &self.vector_v[..self.np]))
            .bind(py)
            .clone()
    }

    /// Start of GN/LM (or the linear method's own solution).
    #[getter]
    fn start<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.start
            .get_or_init(py, || arr1(py, &self.start_v[..self.np]))
            .bind(py)
            .clone()
    }

    /// `(J^T W J)^-1` (p, p) with the noise model's weights; per unit output variance when
    /// the noise is estimated. NaN when singular.
    #[getter]
    fn covariance_unscaled<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        self.covariance_unscaled
            .get_or_init(py, || {
                frozen2(py, self.covariance_v.clone(), self.np, self.np)
            })
            .bind(py)
            .clone()
    }

    /// `sigma_g^2 (dp/dg) (dp/dg)^T` (p, p): the covariance the uncertainty `sigma_g` of the
    /// reference gravity adds (zero without `sigma_g`). With `g` scaled by `1 + e` the fit's
    /// `K` scales by `1 / (1 + e)` and the bias stays, so `dp/dg = -p / g` for every entry of
    /// `K` and 0 for the biases.
    #[getter]
    fn covariance_gravity<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        self.covariance_gravity
            .get_or_init(py, || {
                let np = self.np;
                let sg = self.sigma_g.unwrap_or(0.0);
                let jv = gravity_sensitivity(&self.vector_v[..np], self.g);
                let v = (0..np * np)
                    .map(|k| gravity_cov_entry(&jv, k / np, k % np, sg))
                    .collect();
                frozen2(py, v, np, np)
            })
            .bind(py)
            .clone()
    }

    /// Upper-tail probability of the residual chi2 under the noise model: `P(X >= chi2_dof *
    /// dof)`, `X ~ chi2(dof)`. NaN when the noise is estimated or `dof == 0`.
    #[getter]
    fn chi2_p(&self) -> f64 {
        if !self.noise_known || self.dof == 0 || !self.chi2_dof.is_finite() {
            return f64::NAN;
        }
        let k = self.dof as f64;
        crate::gap::special::chi2_sf(self.chi2_dof * k, k)
    }

    /// `|a_k| - g` per dwell (units of g).
    #[getter]
    fn residuals<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.residuals
            .get_or_init(py, || arr1(py, &self.residuals_v))
            .bind(py)
            .clone()
    }

    /// Predicted std of each residual (units of g): from the noise model, or from the noise
    /// level estimated from the residuals.
    #[getter]
    fn sigma_residual<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.sigma_residual
            .get_or_init(py, || arr1(py, &self.sigma_residual_v))
            .bind(py)
            .clone()
    }

    /// Predicted std of each parameter in comparable units (scale and misalignment relative,
    /// biases in g).
    #[getter]
    fn predicted_std_relative<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        self.predicted_std_relative
            .get_or_init(py, || arr1(py, &self.predicted_std_v[..self.np]))
            .bind(py)
            .clone()
    }

    /// What the caller must act on, in one read: bit 0 the fit neither converged nor found
    /// the design degenerate (an error), bit 1 it is weak or degenerate (a warning), bit 2 a
    /// norm residual beyond 5 % of g (a dwell that may not be at rest: the caller screens);
    /// 0 for a fit to return as it is.
    #[getter]
    fn _attention(&self) -> u8 {
        let far = self
            .residuals_v
            .iter()
            .any(|r| r.is_nan() || r.abs() > crate::static_fit::OFF_NORM_FRACTION * self.g);
        u8::from(!self.converged && !self.degenerate)
            | (u8::from(self.weak || self.degenerate) << 1)
            | (u8::from(far) << 2)
    }

    /// Full observability report: SVD of the whitened Jacobian in comparable units.
    fn observability(&self, py: Python<'_>) -> PyResult<PyObservability> {
        let (m, v, s) = self.inputs(py)?;
        let noise = v.noise();
        let f = fit_static(&m, self.g, &noise, &s)?;
        let o = f.observability(&noise, self.g, &s)?;
        Ok(PyObservability::from_core(py, &o))
    }

    /// The constructor's arguments (pickling recomputes the fit: deterministic).
    fn __getnewargs_ex__<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyTuple>, Bound<'py, PyDict>)> {
        let args = PyTuple::new(
            py,
            [
                self.means(py).into_any().unbind(),
                self.g.into_pyobject(py)?.into_any().unbind(),
            ],
        )?;
        let kw = PyDict::new(py);
        kw.set_item("model", self.model)?;
        kw.set_item("method", self.method)?;
        kw.set_item("var", self.var.as_ref().map(|v| v.clone_ref(py)))?;
        kw.set_item("start", self.user_start.clone())?;
        kw.set_item("max_iter", self.max_iter)?;
        kw.set_item("raise_degenerate", self.raise_degenerate)?;
        kw.set_item("degenerate_std", self.degenerate_std)?;
        kw.set_item("weak_std", self.weak_std)?;
        kw.set_item("check_g", self.check_g)?;
        kw.set_item("noise_model", self.noise_model.clone_ref(py))?;
        kw.set_item("input_units", self.input_units.clone_ref(py))?;
        kw.set_item("nominal", self.nominal.as_ref().map(|n| n.clone_ref(py)))?;
        kw.set_item("sigma_g", self.sigma_g)?;
        Ok((args, kw))
    }
}

impl PyStaticFit {
    fn inputs(&self, py: Python<'_>) -> PyResult<(Vec<[f64; 3]>, VarArg, FitSettings)> {
        let m = self.means_v.clone();
        let v = VarArg::from_py(self.var.as_ref().map(|v| v.bind(py)))?;
        let mut s = FitSettings::new(Model::parse(self.model)?, Method::parse(self.method)?);
        s.start = self.user_start.clone();
        s.max_iter = self.max_iter;
        s.raise_degenerate = false;
        s.degenerate_std = self.degenerate_std;
        s.weak_std = self.weak_std;
        Ok((m, v, s))
    }
}

fn method_name(m: Method) -> &'static str {
    match m {
        Method::LinearPaper => "linear-paper",
        Method::Quadric => "quadric",
        Method::GaussNewton => "gauss-newton",
        Method::Lm => "lm",
    }
}

// ------------------------------------------------------------------------------------------
// Batch

/// Result of a batch of static fits, one row per session.
#[pyclass(name = "BatchFit", module = "accelcal._core", frozen, get_all)]
pub struct PyBatchFit {
    /// Sensor model.
    model: &'static str,
    /// Parameters (B, p); NaN where the fit failed.
    params: Py<PyArray2<f64>>,
    /// Std of each parameter (B, p): noise model when known, scaled by chi2/dof when the
    /// noise is estimated.
    std: Py<PyArray2<f64>>,
    /// chi2/dof, or the estimated per-axis variance of a dwell mean when the noise is
    /// estimated (B,).
    chi2_dof: Py<PyArray1<f64>>,
    /// RMS of `|a| - g` (B,), units of g.
    rms: Py<PyArray1<f64>>,
    /// GN/LM iterations (B,).
    iterations: Py<PyArray1<i64>>,
    /// Dwells per session (B,).
    n_dwells: Py<PyArray1<i64>>,
    /// 0 ok (weak included), 1 degenerate, 2 not converged / ran away, 3 invalid input (B,).
    status: Py<PyArray1<u8>>,
    /// Some parameter weakly determined (B,).
    weak: Py<PyArray1<bool>>,
    /// What went wrong per session ("" for ok and weak), e.g. "session 17: dwell 3 has a
    /// NaN mean".
    messages: Py<PyList>,
}

#[pymethods]
impl PyBatchFit {
    #[new]
    #[allow(clippy::too_many_arguments)]
    fn new(
        model: &str,
        params: PyReadonlyArray2<'_, f64>,
        std: PyReadonlyArray2<'_, f64>,
        chi2_dof: PyReadonlyArray1<'_, f64>,
        rms: PyReadonlyArray1<'_, f64>,
        iterations: PyReadonlyArray1<'_, i64>,
        n_dwells: PyReadonlyArray1<'_, i64>,
        status: PyReadonlyArray1<'_, u8>,
        weak: PyReadonlyArray1<'_, bool>,
        messages: Py<PyList>,
    ) -> PyResult<Self> {
        // Read-only, as made (an unpickled or copied result came back writable).
        Ok(PyBatchFit {
            model: Model::parse(model)?.name(),
            params: frozen_copy2(&params),
            std: frozen_copy2(&std),
            chi2_dof: frozen_copy1(&chi2_dof),
            rms: frozen_copy1(&rms),
            iterations: frozen_copy1(&iterations),
            n_dwells: frozen_copy1(&n_dwells),
            status: frozen_copy1(&status),
            weak: frozen_copy1(&weak),
            messages,
        })
    }

    /// Sessions fitted (status 0, weak included) (B,).
    #[getter]
    fn ok<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<bool>> {
        let st = self.status.bind(py).readonly();
        st.as_array()
            .iter()
            .map(|s| *s == 0)
            .collect::<Vec<_>>()
            .into_pyarray(py)
    }

    /// Outcome per session: "ok", "weak", "degenerate" or "error".
    #[getter]
    fn state(&self, py: Python<'_>) -> Vec<&'static str> {
        let st = self.status.bind(py).readonly();
        let wk = self.weak.bind(py).readonly();
        st.as_array()
            .iter()
            .zip(wk.as_array().iter())
            .map(|(s, w)| match (s, w) {
                (0, false) => "ok",
                (0, true) => "weak",
                (1, _) => "degenerate",
                _ => "error",
            })
            .collect()
    }

    /// Parameter names of the columns of `params` and `std`.
    #[getter]
    fn names(&self) -> Vec<&'static str> {
        let np = Model::parse(self.model).map(|m| m.n_params()).unwrap_or(9);
        PARAM_NAMES[..np].to_vec()
    }

    fn __len__(&self, py: Python<'_>) -> usize {
        self.status.bind(py).len()
    }

    fn __getnewargs__<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        PyTuple::new(
            py,
            [
                self.model.into_pyobject(py)?.into_any().unbind(),
                self.params.clone_ref(py).into_any(),
                self.std.clone_ref(py).into_any(),
                self.chi2_dof.clone_ref(py).into_any(),
                self.rms.clone_ref(py).into_any(),
                self.iterations.clone_ref(py).into_any(),
                self.n_dwells.clone_ref(py).into_any(),
                self.status.clone_ref(py).into_any(),
                self.weak.clone_ref(py).into_any(),
                self.messages.clone_ref(py).into_any(),
            ],
        )
    }

    fn __repr__(&self, py: Python<'_>) -> String {
        let st = self.status.bind(py).readonly();
        let ok = st.as_array().iter().filter(|s| **s == 0).count();
        format!(
            "BatchFit(model={:?}, sessions={}, fitted={ok})",
            self.model,
            st.len()
        )
    }
}

/// The sessions of a batch as slices of one buffer: the `(B, n, 3)` array itself when it is
/// C-contiguous and unmasked (zero copy), else gathered once.
enum Gathered<'a> {
    Borrowed(&'a [[f64; 3]], usize),
    Owned(Vec<[f64; 3]>, Vec<usize>),
}

impl Gathered<'_> {
    fn sessions(&self) -> Vec<&[[f64; 3]]> {
        match self {
            Gathered::Borrowed(all, n) => {
                if *n == 0 {
                    Vec::new()
                } else {
                    all.chunks(*n).collect()
                }
            }
            Gathered::Owned(all, off) => off.windows(2).map(|w| &all[w[0]..w[1]]).collect(),
        }
    }
}

/// Fit many sessions in parallel: `means` is a `(B, n, 3)` float64 array (with an optional
/// `(B, n)` boolean `mask` of the dwells to use) or a list of `(n_i, 3)` float64 arrays.
#[pyfunction]
#[pyo3(signature = (means, g, *, model="lower", method="lm", sigma=None, start=None, max_iter=NOT_GIVEN, degenerate_std=NOT_GIVEN, weak_std=NOT_GIVEN, mask=None, sigma_g=None))]
#[allow(clippy::too_many_arguments)]
pub fn static_fit_batch<'py>(
    py: Python<'py>,
    means: &Bound<'py, PyAny>,
    g: &Bound<'py, PyAny>,
    model: &str,
    method: &str,
    sigma: Option<&Bound<'py, PyAny>>,
    start: Option<Vec<f64>>,
    max_iter: Given<'py>,
    degenerate_std: Given<'py>,
    weak_std: Given<'py>,
    mask: Option<PyReadonlyArray2<'py, bool>>,
    sigma_g: Option<&Bound<'py, PyAny>>,
) -> PyResult<PyBatchFit> {
    let s = settings_from(
        model,
        method,
        start,
        &max_iter,
        true,
        &degenerate_std,
        &weak_std,
    )?;
    let sig = match sigma {
        Some(o) if !o.is_none() => Some(positive(
            o,
            "sigma",
            "std of a dwell mean per axis (output units)",
        )?),
        _ => None,
    };
    // Sessions: a 3-D array (optionally masked) or a list of 2-D arrays.
    let arr3 = means.extract::<PyReadonlyArray3<'py, f64>>().ok();
    let gathered;
    let b;
    if let Some(a) = &arr3 {
        let sh = a.shape().to_vec();
        if sh[2] != 3 {
            return Err(CalibrationError::new_err(format!(
                "means must have shape (B, n, 3); got {sh:?}"
            )));
        }
        b = sh[0];
        let n = sh[1];
        match &mask {
            None => match (a.is_c_contiguous(), a.as_slice()) {
                (true, Ok(flat)) => {
                    let (rows, _) = flat.as_chunks::<3>();
                    gathered = Gathered::Borrowed(rows, n);
                }
                _ => {
                    let v = a.as_array();
                    let rows: Vec<[f64; 3]> = (0..b)
                        .flat_map(|i| (0..n).map(move |k| (i, k)))
                        .map(|(i, k)| [v[[i, k, 0]], v[[i, k, 1]], v[[i, k, 2]]])
                        .collect();
                    let off = (0..=b).map(|i| i * n).collect();
                    gathered = Gathered::Owned(rows, off);
                }
            },
            Some(mk) => {
                if mk.shape() != [b, n] {
                    return Err(CalibrationError::new_err(format!(
                        "mask must have shape ({b}, {n}) (True for the dwells to use); got {:?}",
                        mk.shape()
                    )));
                }
                let v = a.as_array();
                let m = mk.as_array();
                let mut rows = Vec::with_capacity(b * n);
                let mut off = Vec::with_capacity(b + 1);
                off.push(0);
                for i in 0..b {
                    for k in 0..n {
                        if m[[i, k]] {
                            rows.push([v[[i, k, 0]], v[[i, k, 1]], v[[i, k, 2]]]);
                        }
                    }
                    off.push(rows.len());
                }
                gathered = Gathered::Owned(rows, off);
            }
        }
    } else if let Ok(list) = means.cast::<PyList>() {
        if mask.is_some() {
            return Err(CalibrationError::new_err(
                "mask is for a padded (B, n, 3) array; a list of sessions needs none",
            ));
        }
        b = list.len();
        let mut rows = Vec::new();
        let mut off = Vec::with_capacity(b + 1);
        off.push(0);
        for (i, item) in list.iter().enumerate() {
            let a = means_arg(&item, &format!("session {i}"))?;
            rows.extend(rows3(&a, &format!("session {i}"))?);
            off.push(rows.len());
        }
        gathered = Gathered::Owned(rows, off);
    } else {
        return Err(CalibrationError::new_err(
            "means must be a (B, n, 3) float64 array or a list of (n_i, 3) float64 arrays",
        ));
    };
    let gv: Vec<f64> = if let Ok(x) = g.extract::<f64>() {
        vec![x]
    } else {
        g.extract::<Vec<f64>>().map_err(|_| {
            CalibrationError::new_err(format!(
                "g must be a number or one value per session ({b}); got {}",
                describe(g)
            ))
        })?
    };
    if let Some((i, x)) = gv
        .iter()
        .enumerate()
        .find(|(_, x)| !(**x > 0.0 && x.is_finite()))
    {
        return Err(CalibrationError::new_err(format!(
            "g must be positive and finite (reference gravity); g[{i}] = {x}"
        )));
    }
    // Checked against every session's g (by the core: the message names the value).
    let sg = sigma_g_arg(sigma_g, gv.iter().copied().fold(f64::INFINITY, f64::min))?;
    let sessions = gathered.sessions();
    let rows: Vec<BatchRow> = py.detach(|| fit_batch_sigma_g(&sessions, &gv, sig, sg, &s))?;
    let np = s.model.n_params();
    let nb = rows.len();
    let messages = PyList::new(
        py,
        rows.iter().map(|r| r.message.clone().unwrap_or_default()),
    )?;
    Ok(PyBatchFit {
        model: s.model.name(),
        params: arr2(py, nb, np, |i, j| rows[i].params[j]),
        std: arr2(py, nb, np, |i, j| rows[i].std[j]),
        chi2_dof: frozen1(py, rows.iter().map(|r| r.chi2_dof).collect()),
        rms: frozen1(py, rows.iter().map(|r| r.rms).collect()),
        iterations: frozen1(py, rows.iter().map(|r| r.iterations as i64).collect()),
        n_dwells: frozen1(py, rows.iter().map(|r| r.n_dwells as i64).collect()),
        status: frozen1(py, rows.iter().map(|r| r.status.code()).collect()),
        weak: frozen1(
            py,
            rows.iter()
                .map(|r| r.status == crate::static_fit::BatchStatus::Weak)
                .collect(),
        ),
        messages: messages.unbind(),
    })
}

// ------------------------------------------------------------------------------------------
// Pose design

/// Cramer-Rao bound of a pose design (the Python `accelcal.Prediction` subclasses it).
/// Constructing it computes the bound for true specific forces `force` (n, 3) (units of the
/// calibrated output, `|force| = g`) at the parameters `truth`, for dwell-mean noise `sigma`
/// per axis (output units).
#[pyclass(
    name = "Prediction",
    module = "accelcal._core",
    frozen,
    get_all,
    subclass
)]
pub struct PyPrediction {
    /// Sensor model.
    model: &'static str,
    /// Specific force at each pose (n, 3).
    force: Py<PyArray2<f64>>,
    /// Dwell-mean noise per axis (output units).
    sigma: f64,
    /// Reference gravity.
    g: f64,
    /// Std of the reference gravity (units of g), or None; its term is in `covariance`.
    sigma_g: Option<f64>,
    /// Parameters at which the bound is evaluated.
    truth: Py<PyArray1<f64>>,
    /// Std of each parameter (p,), output units (inf when singular).
    std: Py<PyArray1<f64>>,
    /// Covariance (p, p), output units (inf when singular).
    covariance: Py<PyArray2<f64>>,
    /// Some combination is undetermined (or fewer poses than parameters).
    singular: bool,
    /// `s_max / s_min` of the comparable Jacobian (inf when singular or too few poses).
    condition: f64,
    /// Least determined combination (comparable units; empty with too few poses).
    weakest: Py<PyArray1<f64>>,
    /// That combination in parameter names ("" with too few poses).
    combination: String,
}

#[pymethods]
impl PyPrediction {
    #[new]
    #[pyo3(signature = (force, sigma, model="lower", *, g=None, truth=None, sigma_g=None))]
    fn new(
        py: Python<'_>,
        force: &Bound<'_, PyAny>,
        sigma: &Bound<'_, PyAny>,
        model: &str,
        g: Option<&Bound<'_, PyAny>>,
        truth: Option<Vec<f64>>,
        sigma_g: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let md = Model::parse(model)?;
        let gv = match g {
            Some(o) if !o.is_none() => positive(o, "g", "reference gravity")?,
            _ => 9.80665,
        };
        let sg = positive(
            sigma,
            "sigma",
            "std of a dwell mean per axis (output units)",
        )?;
        let fa = means_arg(force, "force")?;
        let f = rows3(&fa, "force")?;
        let np = md.n_params();
        let t = match truth {
            Some(t) => t,
            None => [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0][..np].to_vec(),
        };
        let set = FitSettings::new(md, Method::Lm);
        let sigma_g = sigma_g_arg(sigma_g, gv)?;
        let p = predict(md, &t, &f, sg, gv, sigma_g.unwrap_or(0.0), &set)?;
        let (cond, weakest, comb) = match &p.observability {
            Some(o) => (o.condition, o.weakest.clone(), o.combination.clone()),
            None => (f64::INFINITY, Vec::new(), String::new()),
        };
        let n = f.len();
        Ok(PyPrediction {
            model: md.name(),
            force: arr2(py, n, 3, |i, j| f[i][j]),
            sigma: sg,
            g: gv,
            sigma_g,
            truth: arr1(py, &t),
            std: arr1(py, &p.std),
            covariance: arr2(py, np, np, |i, j| p.covariance[i * np + j]),
            singular: p.singular,
            condition: cond,
            weakest: arr1(py, &weakest),
            combination: comb,
        })
    }

    fn __getnewargs_ex__<'py>(
        &self,
        py: Python<'py>,
    ) -> PyResult<(Bound<'py, PyTuple>, Bound<'py, PyDict>)> {
        let args = PyTuple::new(
            py,
            [
                self.force.clone_ref(py).into_any(),
                self.sigma.into_pyobject(py)?.into_any().unbind(),
                self.model.into_pyobject(py)?.into_any().unbind(),
            ],
        )?;
        let kw = PyDict::new(py);
        kw.set_item("g", self.g)?;
        kw.set_item("truth", self.truth.bind(py).to_vec()?)?;
        kw.set_item("sigma_g", self.sigma_g)?;
        Ok((args, kw))
    }
}

/// Fisher-information rows (n, p) of poses with true specific forces `force` (n, 3) at the
/// parameters `truth`, for dwell-mean noise `sigma` per axis: the candidate matrix of
/// D-optimal pose planning.
#[pyfunction]
#[pyo3(signature = (force, truth, model, sigma))]
pub fn static_design_rows<'py>(
    py: Python<'py>,
    force: PyReadonlyArray2<'py, f64>,
    truth: Vec<f64>,
    model: &str,
    sigma: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyArray2<f64>>> {
    let md = Model::parse(model)?;
    let sg = positive(
        sigma,
        "sigma",
        "std of a dwell mean per axis (output units)",
    )?;
    let f = rows3(&force, "force")?;
    let rows = py.detach(|| design_rows(md, &truth, &f, sg))?;
    let np = md.n_params();
    ndarray::Array2::from_shape_vec((f.len(), np), rows)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| CalibrationError::new_err(e.to_string()))
}

/// Rows per block of [`apply_triad_raw`] between two checks of the interpreter's signals
/// (about 20 ms of work).
const APPLY_BLOCK_ROWS: usize = 1 << 20;

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
        let t = apply_inverse(&v, &k, &b)?;
        let mut out = vec![0.0; 3 * n];
        // Block by block, the interpreter's signals checked between blocks: Ctrl-C stops a
        // long apply within a block instead of at its end (12 s for 60 million rows).
        for (i, dst) in out.chunks_mut(3 * APPLY_BLOCK_ROWS).enumerate() {
            if i > 0 {
                py.check_signals()?;
            }
            let r0 = i * APPLY_BLOCK_ROWS;
            let part = v.slice(ndarray::s![r0..r0 + dst.len() / 3, ..]);
            py.detach(|| apply_inverse_into(&part, &t, &b, dst));
        }
        (out, n)
    });
    ndarray::Array2::from_shape_vec((n, 3), out)
        .map(|a| a.into_pyarray(py))
        .map_err(|e| CalibrationError::new_err(e.to_string()))
}

/// `K` entries outside the pattern of `model` that are not zero: `(row, column)` or None.
#[pyfunction]
pub fn static_model_violation(k: [[f64; 3]; 3], model: &str) -> PyResult<Option<(usize, usize)>> {
    Ok(Model::parse(model)?.violations(&k))
}

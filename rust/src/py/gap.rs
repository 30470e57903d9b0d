//! Bindings of the gap-diagnosis core: plain dicts of arrays, the Python layer builds GapReport.

use numpy::{IntoPyArray, PyReadonlyArray1, PyReadonlyArray2};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use super::convert::{opt_slice, rows3};
use super::CalibrationError;
use crate::gap::{self, Correction, Effect, GapInput, GapOptions, Gate, TestMode, N_BASE};

fn effects_from(names: &[String]) -> PyResult<Vec<Effect>> {
    let mut out = vec![];
    for n in names {
        let e = Effect::from_name(n)?;
        if !out.contains(&e) {
            out.push(e);
        }
    }
    Ok(out)
}

/// Static gap diagnosis on dwell means (raw units); returns a dict of arrays and lists.
#[pyfunction]
#[pyo3(signature = (mean, sigma_mean, t, temperature, g, effects, alpha=0.05, max_effects=3,
                    loo=true, start=None, sine_tol=0.05, ambiguity_cos=0.9, min_temp_range=0.05,
                    test="auto", trust_level=0.1, gate="auto", correction="minp",
                    n_draws=4000, gate_margin=0.0))]
#[allow(clippy::too_many_arguments)]
pub fn gap_diagnose_raw<'py>(
    py: Python<'py>,
    mean: PyReadonlyArray2<'py, f64>,
    sigma_mean: Option<PyReadonlyArray2<'py, f64>>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    temperature: Option<PyReadonlyArray1<'py, f64>>,
    g: f64,
    effects: Vec<String>,
    alpha: f64,
    max_effects: usize,
    loo: bool,
    start: Option<Vec<f64>>,
    sine_tol: f64,
    ambiguity_cos: f64,
    min_temp_range: f64,
    test: &str,
    trust_level: f64,
    gate: &str,
    correction: &str,
    n_draws: usize,
    gate_margin: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let inp = GapInput {
        mean: rows3(&mean, "mean")?,
        sigma_mean: sigma_mean
            .as_ref()
            .map(|s| rows3(s, "sigma_mean"))
            .transpose()?,
        t: opt_slice(&t, "t")?.map(|s| s.to_vec()),
        temperature: opt_slice(&temperature, "temperature")?.map(|s| s.to_vec()),
        g,
    };
    let start = match start {
        None => None,
        Some(v) => {
            let a: [f64; N_BASE] = v.try_into().map_err(|_| {
                CalibrationError::new_err("start must be [sx,sy,sz,bx,by,bz,m1,m2,m3]")
            })?;
            Some(a)
        }
    };
    let opt = GapOptions {
        alpha,
        effects: effects_from(&effects)?,
        max_effects,
        loo,
        sine_tol,
        ambiguity_cos,
        min_temp_range,
        start,
        test: TestMode::from_name(test)?,
        trust_level,
        gate: Gate::from_name(gate)?,
        correction: Correction::from_name(correction)?,
        n_draws,
        gate_margin,
    };
    let r = py.detach(|| gap::diagnose(&inp, &opt))?;
    let d = PyDict::new(py);
    d.set_item("n", r.n)?;
    d.set_item("base_params", r.base_params.into_pyarray(py))?;
    d.set_item("base_std", r.base_std.into_pyarray(py))?;
    d.set_item("sigma_r", r.sigma_r.into_pyarray(py))?;
    d.set_item("resid", r.resid.into_pyarray(py))?;
    d.set_item("e", r.e.into_pyarray(py))?;
    d.set_item("leverage", r.leverage.into_pyarray(py))?;
    d.set_item("chi2", r.chi2)?;
    d.set_item("dof", r.dof)?;
    d.set_item("p_chi2", r.p_chi2)?;
    d.set_item("noise_known", r.noise_known)?;
    let cl = PyList::empty(py);
    for c in &r.candidates {
        let cd = PyDict::new(py);
        cd.set_item("effect", c.effect.name())?;
        cd.set_item("unit", c.effect.unit())?;
        cd.set_item("status", c.status.name())?;
        cd.set_item("sines", c.sines.clone())?;
        cd.set_item("d", c.d)?;
        cd.set_item("score", c.score)?;
        cd.set_item("f", c.f)?;
        cd.set_item("p_f", c.p_f)?;
        cd.set_item("p_chi2", c.p_chi2)?;
        cd.set_item("p", c.p)?;
        cd.set_item("chi2_used", c.chi2_used)?;
        cd.set_item("bic", c.bic)?;
        cd.set_item("weight", c.weight)?;
        cd.set_item("estimate", c.estimate.to_vec())?;
        cd.set_item("std", c.std.to_vec())?;
        cl.append(cd)?;
    }
    d.set_item("candidates", cl)?;
    d.set_item("bic_none", r.bic_none)?;
    d.set_item("weight_none", r.weight_none)?;
    d.set_item(
        "selected",
        r.selected.iter().map(|e| e.name()).collect::<Vec<_>>(),
    )?;
    d.set_item("step_p", r.step_p)?;
    d.set_item("step_p_adj", r.step_p_adj)?;
    d.set_item("step_m", r.step_m)?;
    d.set_item("stop_p", r.stop_p)?;
    d.set_item("stop_p_adj", r.stop_p_adj)?;
    d.set_item("gate_skipped", r.gate_skipped)?;
    match r.not_confirmed {
        None => d.set_item("not_confirmed", py.None())?,
        Some((e, p, a, b)) => d.set_item("not_confirmed", (e.name(), p, a, b))?,
    }
    d.set_item("params_after", r.params_after.into_pyarray(py))?;
    d.set_item("std_after", r.std_after.into_pyarray(py))?;
    d.set_item("resid_after", r.resid_after.into_pyarray(py))?;
    d.set_item("e_after", r.e_after.into_pyarray(py))?;
    d.set_item("chi2_after", r.chi2_after)?;
    d.set_item("dof_after", r.dof_after)?;
    d.set_item("p_after", r.p_after)?;
    d.set_item(
        "ambiguous",
        r.ambiguous
            .iter()
            .map(|(a, b, c)| (a.name(), b.name(), *c))
            .collect::<Vec<_>>(),
    )?;
    match r.loo {
        None => d.set_item("loo", py.None())?,
        Some(l) => {
            let ld = PyDict::new(py);
            ld.set_item("g_before", l.g_before)?;
            ld.set_item("g_after", l.g_after)?;
            ld.set_item("rms_before", l.rms_before)?;
            ld.set_item("rms_after", l.rms_after)?;
            ld.set_item("z_before", l.z_before.into_pyarray(py))?;
            ld.set_item("z_after", l.z_after.into_pyarray(py))?;
            ld.set_item("g_steps", l.g_steps)?;
            let counts = PyDict::new(py);
            for (e, c) in Effect::ALL.iter().zip(l.fold_counts) {
                counts.set_item(e.name(), c)?;
            }
            ld.set_item("fold_counts", counts)?;
            ld.set_item("n_failed", l.n_failed)?;
            d.set_item("loo", ld)?;
        }
    }
    Ok(d)
}

/// Norm residuals (m/s^2) of raw dwell means under given parameters and effects.
#[pyfunction]
#[pyo3(signature = (mean, t, temperature, g, params, effects))]
pub fn gap_model_residuals_raw<'py>(
    py: Python<'py>,
    mean: PyReadonlyArray2<'py, f64>,
    t: Option<PyReadonlyArray1<'py, f64>>,
    temperature: Option<PyReadonlyArray1<'py, f64>>,
    g: f64,
    params: Vec<f64>,
    effects: Vec<String>,
) -> PyResult<Bound<'py, numpy::PyArray1<f64>>> {
    let m = rows3(&mean, "mean")?;
    let eff = effects_from(&effects)?;
    let r = gap::model_residuals(
        &m,
        opt_slice(&t, "t")?,
        opt_slice(&temperature, "temperature")?,
        g,
        &params,
        &eff,
    )?;
    Ok(r.into_pyarray(py))
}

/// Survival function of chi2 with `k` degrees of freedom (NaN for k <= 0).
#[pyfunction]
pub fn gap_chi2_sf(x: f64, k: f64) -> f64 {
    gap::chi2_sf(x, k)
}

/// Survival function of F(d1, d2) (NaN for non-positive degrees of freedom).
#[pyfunction]
pub fn gap_f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    gap::f_sf(f, d1, d2)
}

//! Bindings of the gap-diagnosis engine: one typed result (`GapRaw`, with nested classes) for
//! the static, centrifuge and gradiometer diagnoses; the Python layer builds `GapReport`.

use numpy::{PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;

use super::convert::{opt_slice, rows3};
use super::CalibrationError;
use crate::gap::centrifuge::{self as gcf, CentrifugeInput};
use crate::gap::engine::{CandidateReport, EngineResult, LooReport};
use crate::gap::gradiometer::{self as ggr, GradiometerInput};
use crate::gap::locate::{Group, Location};
use crate::gap::statics::{self, Calibration, DwellExtras, Effect, StaticInput};
use crate::gap::structure::{NoiseEmpirical, Structure, StructureTest};
use crate::gap::{Correction, GapOptions, GapResult, Gate, TestMode};

/// Engine settings (the defaults are `GapOptions::default()` in the core: the one place).
#[pyclass(name = "GapSettings", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapSettings {
    alpha: f64,
    max_effects: usize,
    loo: bool,
    sine_tol: f64,
    ambiguity_cos: f64,
    ambiguity_weight: f64,
    min_temp_range: f64,
    test: String,
    trust_level: f64,
    gate: String,
    gate_sd: f64,
    gate_margin: f64,
    correction: String,
    n_draws: usize,
    random_offset: bool,
}

#[pymethods]
impl GapSettings {
    /// Settings; every value not given is the engine's default.
    #[new]
    #[pyo3(signature = (*, alpha=None, max_effects=None, loo=None, sine_tol=None,
                        ambiguity_cos=None, ambiguity_weight=None, min_temp_range=None,
                        test=None, trust_level=None, gate=None, gate_sd=None, gate_margin=None,
                        correction=None, n_draws=None, random_offset=None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        alpha: Option<f64>,
        max_effects: Option<usize>,
        loo: Option<bool>,
        sine_tol: Option<f64>,
        ambiguity_cos: Option<f64>,
        ambiguity_weight: Option<f64>,
        min_temp_range: Option<f64>,
        test: Option<String>,
        trust_level: Option<f64>,
        gate: Option<String>,
        gate_sd: Option<f64>,
        gate_margin: Option<f64>,
        correction: Option<String>,
        n_draws: Option<usize>,
        random_offset: Option<bool>,
    ) -> PyResult<Self> {
        let d = GapSettings::from(&GapOptions::default());
        let s = GapSettings {
            alpha: alpha.unwrap_or(d.alpha),
            max_effects: max_effects.unwrap_or(d.max_effects),
            loo: loo.unwrap_or(d.loo),
            sine_tol: sine_tol.unwrap_or(d.sine_tol),
            ambiguity_cos: ambiguity_cos.unwrap_or(d.ambiguity_cos),
            ambiguity_weight: ambiguity_weight.unwrap_or(d.ambiguity_weight),
            min_temp_range: min_temp_range.unwrap_or(d.min_temp_range),
            test: test.unwrap_or(d.test),
            trust_level: trust_level.unwrap_or(d.trust_level),
            gate: gate.unwrap_or(d.gate),
            gate_sd: gate_sd.unwrap_or(d.gate_sd),
            gate_margin: gate_margin.unwrap_or(d.gate_margin),
            correction: correction.unwrap_or(d.correction),
            n_draws: n_draws.unwrap_or(d.n_draws),
            random_offset: random_offset.unwrap_or(d.random_offset),
        };
        s.options()?.validate()?;
        Ok(s)
    }

    fn __repr__(&self) -> String {
        format!(
            "GapSettings(alpha={}, max_effects={}, test={:?}, trust_level={}, gate={:?}, \
             gate_margin={}, correction={:?}, n_draws={}, random_offset={})",
            self.alpha,
            self.max_effects,
            self.test,
            self.trust_level,
            self.gate,
            self.gate_margin,
            self.correction,
            self.n_draws,
            if self.random_offset { "True" } else { "False" }
        )
    }
}

impl From<&GapOptions> for GapSettings {
    fn from(o: &GapOptions) -> Self {
        let test = match o.test {
            TestMode::F => "f",
            TestMode::Chi2 => "chi2",
            TestMode::Auto => "auto",
        };
        let gate = match o.gate {
            Gate::Off => "off",
            Gate::Strict => "strict",
            Gate::Auto => "auto",
        };
        let correction = match o.correction {
            Correction::MinP => "minp",
            Correction::Bonferroni => "bonferroni",
        };
        GapSettings {
            alpha: o.alpha,
            max_effects: o.max_effects,
            loo: o.loo,
            sine_tol: o.sine_tol,
            ambiguity_cos: o.ambiguity_cos,
            ambiguity_weight: o.ambiguity_weight,
            min_temp_range: o.min_temp_range,
            test: test.into(),
            trust_level: o.trust_level,
            gate: gate.into(),
            gate_sd: o.gate_sd,
            gate_margin: o.gate_margin,
            correction: correction.into(),
            n_draws: o.n_draws,
            random_offset: o.random_offset,
        }
    }
}

impl GapSettings {
    fn options(&self) -> PyResult<GapOptions> {
        Ok(GapOptions {
            alpha: self.alpha,
            max_effects: self.max_effects,
            loo: self.loo,
            sine_tol: self.sine_tol,
            ambiguity_cos: self.ambiguity_cos,
            ambiguity_weight: self.ambiguity_weight,
            min_temp_range: self.min_temp_range,
            test: TestMode::from_name(&self.test)?,
            trust_level: self.trust_level,
            gate: Gate::from_name(&self.gate)?,
            gate_sd: self.gate_sd,
            gate_margin: self.gate_margin,
            correction: Correction::from_name(&self.correction)?,
            n_draws: self.n_draws,
            random_offset: self.random_offset,
        })
    }
}

/// One candidate effect's screening and estimate.
#[pyclass(name = "GapCandidate", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapCandidate {
    name: String,
    unit: String,
    status: String,
    sines: Vec<f64>,
    d: usize,
    score: f64,
    f: f64,
    p_f: f64,
    p_chi2: f64,
    p: f64,
    chi2_used: bool,
    bic: f64,
    weight: f64,
    estimate: Vec<f64>,
    std: Vec<f64>,
}

/// Leave-one-group-out held-out gap.
#[pyclass(name = "GapHeldOut", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapHeldOut {
    g_before: f64,
    g_after: f64,
    rms_before: f64,
    rms_after: f64,
    z_before: Vec<f64>,
    z_after: Vec<f64>,
    g_steps: Vec<f64>,
    fold_counts: Vec<usize>,
    n_failed: usize,
}

impl From<&LooReport> for GapHeldOut {
    fn from(l: &LooReport) -> Self {
        GapHeldOut {
            g_before: l.g_before,
            g_after: l.g_after,
            rms_before: l.rms_before,
            rms_after: l.rms_after,
            z_before: l.z_before.clone(),
            z_after: l.z_after.clone(),
            g_steps: l.g_steps.clone(),
            fold_counts: l.fold_counts.clone(),
            n_failed: l.n_failed,
        }
    }
}

/// The gap of one group of rows.
#[pyclass(name = "GapGroup", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapGroup {
    key: f64,
    n: usize,
    mean_e2: f64,
    p: f64,
}

impl From<&Group> for GapGroup {
    fn from(g: &Group) -> Self {
        GapGroup {
            key: g.key,
            n: g.n,
            mean_e2: g.mean_e2,
            p: g.p,
        }
    }
}

/// Where the gap lies.
#[pyclass(name = "GapLocation", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapLocation {
    t_stud: Vec<f64>,
    threshold: f64,
    flagged: Vec<usize>,
    axes: Vec<GapGroup>,
    segments: Vec<GapGroup>,
    serial: Option<(f64, f64, f64)>,
    temperature: Option<(f64, f64, f64, f64)>,
}

impl From<&Location> for GapLocation {
    fn from(l: &Location) -> Self {
        GapLocation {
            t_stud: l.t_stud.clone(),
            threshold: l.threshold,
            flagged: l.flagged.clone(),
            axes: l.axes.iter().map(GapGroup::from).collect(),
            segments: l.segments.iter().map(GapGroup::from).collect(),
            serial: l.serial,
            temperature: l.temperature,
        }
    }
}

/// One structure test.
#[pyclass(name = "GapStructureTest", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapStructureTest {
    name: String,
    status: String,
    n_columns: usize,
    d: usize,
    dof2: f64,
    statistic: f64,
    p_value: f64,
    p_adjusted: f64,
    explained: f64,
}

impl From<&StructureTest> for GapStructureTest {
    fn from(t: &StructureTest) -> Self {
        GapStructureTest {
            name: t.name.into(),
            status: t.status.name().into(),
            n_columns: t.n_columns,
            d: t.d,
            dof2: t.dof2,
            statistic: t.statistic,
            p_value: t.p_value,
            p_adjusted: t.p_adjusted,
            explained: t.explained,
        }
    }
}

/// Empirical dwell-mean noise from half-dwell differences.
#[pyclass(name = "GapNoiseEmpirical", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapNoiseEmpirical {
    n: usize,
    rms: f64,
    rms_model: f64,
    rms_white: f64,
    rms_allan: f64,
    ratio_model: f64,
    ratio_white: f64,
    ratio_allan: f64,
    p_model: f64,
}

impl From<&NoiseEmpirical> for GapNoiseEmpirical {
    fn from(n: &NoiseEmpirical) -> Self {
        GapNoiseEmpirical {
            n: n.n,
            rms: n.rms,
            rms_model: n.rms_model,
            rms_white: n.rms_white,
            rms_allan: n.rms_allan,
            ratio_model: n.ratio_model,
            ratio_white: n.ratio_white,
            ratio_allan: n.ratio_allan,
            p_model: n.p_model,
        }
    }
}

/// What the remaining gap is made of.
#[pyclass(name = "GapStructure", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapStructure {
    verdict: String,
    statistic: f64,
    p_value: f64,
    persistence: f64,
    persistence_testable: bool,
    per_dwell_rms: f64,
    quantization_rms: f64,
    tests: Vec<GapStructureTest>,
    noise_empirical: Option<GapNoiseEmpirical>,
}

impl From<&Structure> for GapStructure {
    fn from(s: &Structure) -> Self {
        GapStructure {
            verdict: s.verdict.name().into(),
            statistic: s.statistic,
            p_value: s.p_value,
            persistence: s.persistence,
            persistence_testable: s.persistence_testable,
            per_dwell_rms: s.per_dwell_rms,
            quantization_rms: s.quantization_rms,
            tests: s.tests.iter().map(GapStructureTest::from).collect(),
            noise_empirical: s.noise_empirical.as_ref().map(GapNoiseEmpirical::from),
        }
    }
}

/// Everything one diagnosis measured (any system).
#[pyclass(name = "GapRaw", module = "accelcal._core", frozen, get_all)]
#[derive(Clone)]
pub struct GapRaw {
    system: String,
    n: usize,
    base_params: Vec<f64>,
    base_std: Vec<f64>,
    sigma: Vec<f64>,
    resid: Vec<f64>,
    e: Vec<f64>,
    leverage: Vec<f64>,
    chi2: f64,
    dof: usize,
    p_chi2: f64,
    noise_known: bool,
    noise_scale: f64,
    candidates: Vec<GapCandidate>,
    bic_none: f64,
    weight_none: f64,
    selected: Vec<String>,
    step_p: Vec<f64>,
    step_p_adj: Vec<f64>,
    step_m: Vec<usize>,
    not_confirmed: Option<(String, f64, f64, f64)>,
    stop_p: f64,
    stop_p_adj: f64,
    params_after: Vec<f64>,
    std_after: Vec<f64>,
    resid_after: Vec<f64>,
    e_after: Vec<f64>,
    sigma_after: Vec<f64>,
    chi2_after: f64,
    dof_after: usize,
    p_after: f64,
    ambiguous: Vec<(String, String, f64, f64)>,
    loo: Option<GapHeldOut>,
    gate_skipped: bool,
    location: GapLocation,
    structure: GapStructure,
    direction: Vec<[f64; 3]>,
    pose_angle_deg: Vec<f64>,
}

fn candidate(c: &CandidateReport, name: &str, unit: &str) -> GapCandidate {
    GapCandidate {
        name: name.into(),
        unit: unit.into(),
        status: c.status.name().into(),
        sines: c.screen.sines.clone(),
        d: c.screen.d,
        score: c.screen.score,
        f: c.screen.f,
        p_f: c.screen.p_f,
        p_chi2: c.screen.p_chi2,
        p: c.screen.p,
        chi2_used: c.screen.chi2_used,
        bic: c.bic,
        weight: c.weight,
        estimate: c.estimate.clone(),
        std: c.std.clone(),
    }
}

fn raw_from(r: &GapResult, names: &[(&str, &str)]) -> GapRaw {
    let e: &EngineResult = &r.engine;
    let nm = |c: usize| names[c].0.to_string();
    GapRaw {
        system: r.system.name().into(),
        n: e.n,
        base_params: e.base_params.clone(),
        base_std: e.base_std.clone(),
        sigma: e.sigma.clone(),
        resid: e.resid.clone(),
        e: e.e.clone(),
        leverage: e.leverage.clone(),
        chi2: e.chi2,
        dof: e.dof,
        p_chi2: e.p_chi2,
        noise_known: e.noise_known,
        noise_scale: e.noise_scale,
        candidates: e
            .candidates
            .iter()
            .map(|c| candidate(c, names[c.effect].0, names[c.effect].1))
            .collect(),
        bic_none: e.bic_none,
        weight_none: e.weight_none,
        selected: e.selected.iter().map(|&c| nm(c)).collect(),
        step_p: e.step_p.clone(),
        step_p_adj: e.step_p_adj.clone(),
        step_m: e.step_m.clone(),
        not_confirmed: e
            .not_confirmed
            .map(|n| (nm(n.effect), n.p, n.g_before, n.g_with)),
        stop_p: e.stop_p,
        stop_p_adj: e.stop_p_adj,
        params_after: e.params_after.clone(),
        std_after: e.std_after.clone(),
        resid_after: e.resid_after.clone(),
        e_after: e.e_after.clone(),
        sigma_after: e.sigma_after.clone(),
        chi2_after: e.chi2_after,
        dof_after: e.dof_after,
        p_after: e.p_after,
        ambiguous: e
            .ambiguous
            .iter()
            .map(|a| (nm(a.best), nm(a.other), a.cosine, a.pair_weight))
            .collect(),
        loo: e.loo.as_ref().map(GapHeldOut::from),
        gate_skipped: e.gate_skipped,
        location: GapLocation::from(&r.location),
        structure: GapStructure::from(&r.structure),
        direction: r.rows.direction.clone(),
        pose_angle_deg: r.rows.pose_angle_deg.clone(),
    }
}

/// Number of distinct poses among dwell means `mean` (k, 3): clusters of means closer than
/// `tol` (raw units) count once.
#[pyfunction]
pub fn gap_distinct_poses(mean: PyReadonlyArray2<'_, f64>, tol: f64) -> PyResult<usize> {
    Ok(statics::distinct_poses(&rows3(&mean, "mean")?, tol))
}

/// Upper tail of the chi-square distribution with `k` degrees of freedom at `x` (the
/// engine's own; Python calls it so that no test needs SciPy at run time).
#[pyfunction]
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    crate::gap::special::chi2_sf(x, k)
}

/// Upper tail of the F distribution with `d1`, `d2` degrees of freedom at `f`.
#[pyfunction]
pub fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    crate::gap::special::f_sf(f, d1, d2)
}

/// The effect dictionary of a system: `(name, unit, number of parameters)` (the
/// gradiometer's azimuth_error has one parameter per dwell: 0 here).
#[pyfunction]
pub fn gap_dictionary(system: &str) -> PyResult<Vec<(String, String, usize)>> {
    let out = match system {
        "static" => statics::DICTIONARY
            .iter()
            .map(|e| (e.name.into(), e.unit.into(), e.dim))
            .collect(),
        "centrifuge" => gcf::DICTIONARY
            .iter()
            .map(|e| (e.name.into(), e.unit.into(), e.dim))
            .collect(),
        "gradiometer" => ggr::NAMES
            .iter()
            .map(|(n, u)| {
                (
                    n.to_string(),
                    u.to_string(),
                    if *n == "azimuth_error" { 0 } else { 2 },
                )
            })
            .collect(),
        _ => {
            return Err(CalibrationError::new_err(format!(
                "system must be 'static', 'centrifuge' or 'gradiometer'; got {system:?}"
            )))
        }
    };
    Ok(out)
}

fn indices(names: &[String], dict: &[&str]) -> PyResult<Vec<usize>> {
    let mut out = vec![];
    for n in names {
        let i = dict.iter().position(|d| d == n).ok_or_else(|| {
            CalibrationError::new_err(format!("unknown effect {n:?}; known: {}", dict.join(", ")))
        })?;
        if !out.contains(&i) {
            out.push(i);
        }
    }
    Ok(out)
}

fn slice1<'a>(a: &'a PyReadonlyArray1<'_, f64>, what: &str) -> PyResult<&'a [f64]> {
    a.as_slice().map_err(|_| {
        CalibrationError::new_err(format!("{what} must be a contiguous 1-D float64 array"))
    })
}

fn opt_rows3(a: &Option<PyReadonlyArray2<'_, f64>>, what: &str) -> PyResult<Option<Vec<[f64; 3]>>> {
    a.as_ref().map(|a| rows3(a, what)).transpose()
}

fn halves(a: &Option<PyReadonlyArray3<'_, f64>>) -> PyResult<Option<Vec<[[f64; 3]; 2]>>> {
    let Some(a) = a else { return Ok(None) };
    let sh = a.shape();
    if sh[1] != 2 || sh[2] != 3 {
        return Err(CalibrationError::new_err(format!(
            "half_mean must have shape (k, 2, 3); got {sh:?}"
        )));
    }
    let v = a.as_array();
    Ok(Some(
        (0..sh[0])
            .map(|k| {
                [
                    [v[[k, 0, 0]], v[[k, 0, 1]], v[[k, 0, 2]]],
                    [v[[k, 1, 0]], v[[k, 1, 1]], v[[k, 1, 2]]],
                ]
            })
            .collect(),
    ))
}

/// Static gap diagnosis on raw dwell means (`var`: per-axis variance of each mean; None:
/// unknown). `calibration`: `(K, b, fixed)` to start from, or to hold fixed. `resid_corr`:
/// `(n, n)` correlation of the dwells' norm residuals (a fixed calibration's own error).
#[pyfunction]
#[pyo3(signature = (mean, var, t, temperature, g, effects, settings, calibration=None,
                    half_mean=None, white_var=None, allan_var=None, sample_var=None, lsb=None,
                    resid_corr=None))]
#[allow(clippy::too_many_arguments)]
pub fn gap_diagnose_static(
    py: Python<'_>,
    mean: PyReadonlyArray2<'_, f64>,
    var: Option<PyReadonlyArray2<'_, f64>>,
    t: Option<PyReadonlyArray1<'_, f64>>,
    temperature: Option<PyReadonlyArray1<'_, f64>>,
    g: f64,
    effects: Vec<String>,
    settings: &GapSettings,
    calibration: Option<([[f64; 3]; 3], [f64; 3], bool)>,
    half_mean: Option<PyReadonlyArray3<'_, f64>>,
    white_var: Option<PyReadonlyArray2<'_, f64>>,
    allan_var: Option<PyReadonlyArray2<'_, f64>>,
    sample_var: Option<PyReadonlyArray2<'_, f64>>,
    lsb: Option<[f64; 3]>,
    resid_corr: Option<PyReadonlyArray2<'_, f64>>,
) -> PyResult<GapRaw> {
    let inp = StaticInput {
        mean: rows3(&mean, "mean")?,
        var: opt_rows3(&var, "var")?,
        t: opt_slice(&t, "t")?.map(|s| s.to_vec()),
        temperature: opt_slice(&temperature, "temperature")?.map(|s| s.to_vec()),
        g,
        calibration: calibration.map(|(k, b, fixed)| Calibration { k, b, fixed }),
        extras: DwellExtras {
            half_mean: halves(&half_mean)?,
            white_var: opt_rows3(&white_var, "white_var")?,
            allan_var: opt_rows3(&allan_var, "allan_var")?,
            sample_var: opt_rows3(&sample_var, "sample_var")?,
            lsb,
            resid_corr: resid_corr
                .as_ref()
                .map(|c| c.as_array().iter().copied().collect()),
        },
    };
    let eff: Vec<Effect> = effects
        .iter()
        .map(|n| Effect::from_name(n))
        .collect::<crate::Result<_>>()?;
    let opt = settings.options()?;
    let r = py.detach(|| statics::diagnose(&inp, &eff, &opt))?;
    let names: Vec<(&str, &str)> = statics::DICTIONARY
        .iter()
        .map(|e| (e.name, e.unit))
        .collect();
    Ok(raw_from(&r, &names))
}

/// Centrifuge gap diagnosis (outputs in g, omega rad/s, radius m). `sigma_norm`: std of each
/// row's norm residual (g); `sigma_axis`: per-axis output std (g), propagated to the norm;
/// `t`: time of each row, s (for the drift).
#[pyfunction]
#[pyo3(signature = (outputs, omega, radius, g, effects, settings, spin_axis=None,
                    sigma_norm=None, sigma_axis=None, t=None))]
#[allow(clippy::too_many_arguments)]
pub fn gap_diagnose_centrifuge(
    py: Python<'_>,
    outputs: PyReadonlyArray2<'_, f64>,
    omega: PyReadonlyArray1<'_, f64>,
    radius: f64,
    g: f64,
    effects: Vec<String>,
    settings: &GapSettings,
    spin_axis: Option<PyReadonlyArray2<'_, f64>>,
    sigma_norm: Option<PyReadonlyArray1<'_, f64>>,
    sigma_axis: Option<PyReadonlyArray2<'_, f64>>,
    t: Option<PyReadonlyArray1<'_, f64>>,
) -> PyResult<GapRaw> {
    let noise = match (
        opt_slice(&sigma_norm, "sigma")?,
        opt_rows3(&sigma_axis, "sigma")?,
    ) {
        (Some(s), _) => gcf::Noise::Norm(s.to_vec()),
        (None, Some(s)) => gcf::Noise::PerAxis(s),
        (None, None) => gcf::Noise::Unknown,
    };
    let inp = CentrifugeInput {
        outputs: rows3(&outputs, "outputs")?,
        omega: slice1(&omega, "omega")?.to_vec(),
        radius,
        g,
        spin_axis: opt_rows3(&spin_axis, "spin_axis")?,
        noise,
        t: opt_slice(&t, "t")?.map(|s| s.to_vec()),
    };
    let dict: Vec<&str> = gcf::DICTIONARY.iter().map(|e| e.name).collect();
    let idx = indices(&effects, &dict)?;
    let opt = settings.options()?;
    let r = py.detach(|| gcf::diagnose(&inp, &idx, &opt))?;
    let names: Vec<(&str, &str)> = gcf::DICTIONARY.iter().map(|e| (e.name, e.unit)).collect();
    Ok(raw_from(&r, &names))
}

/// Gradiometer gap diagnosis (azimuths deg, outputs (m, 2) inline/cross in E, t s, sigma E).
#[pyfunction]
#[pyo3(signature = (azimuth_deg, outputs, effects, settings, t=None, sigma=None,
                    warmup_tau_s=600.0))]
#[allow(clippy::too_many_arguments)]
pub fn gap_diagnose_gradiometer(
    py: Python<'_>,
    azimuth_deg: PyReadonlyArray1<'_, f64>,
    outputs: PyReadonlyArray2<'_, f64>,
    effects: Vec<String>,
    settings: &GapSettings,
    t: Option<PyReadonlyArray1<'_, f64>>,
    sigma: Option<PyReadonlyArray1<'_, f64>>,
    warmup_tau_s: f64,
) -> PyResult<GapRaw> {
    if outputs.shape()[1] != 2 {
        return Err(CalibrationError::new_err(format!(
            "outputs must have shape (m, 2) (inline, cross, E); got {:?}",
            outputs.shape()
        )));
    }
    let y = outputs.as_array();
    let inp = GradiometerInput {
        azimuth_deg: slice1(&azimuth_deg, "azimuth_deg")?.to_vec(),
        outputs: y.rows().into_iter().map(|r| [r[0], r[1]]).collect(),
        t: opt_slice(&t, "t")?.map(|s| s.to_vec()),
        sigma: opt_slice(&sigma, "sigma")?.map(|s| s.to_vec()),
        warmup_tau_s,
    };
    let dict: Vec<&str> = ggr::NAMES.iter().map(|e| e.0).collect();
    let idx = indices(&effects, &dict)?;
    let opt = settings.options()?;
    let r = py.detach(|| ggr::diagnose(&inp, &idx, &opt))?;
    Ok(raw_from(&r, &ggr::NAMES))
}

//! Sim-to-real gap diagnosis of a static norm-observation session (GAP-DESIGN.md).
//!
//! Model (raw units, dwell means): `am_k = K a_k + b + sum_e term_e(k)`, with `K` lower
//! triangular `[[sx,0,0],[m1,sy,0],[m2,m3,sz]]` and `|a_k| = g`. The residual is
//! `r_k = |K^-1 (am_k - b - terms)| - g` (m/s^2), whitened by its propagated standard deviation
//! `sigma_r,k^2 = v^T Sigma_k v`, `v = K^-T a/|a|`.
//!
//! Effect dictionary (terms subtracted from the raw output; `c_i = s_i g` raw units per g,
//! `z = am - b`, `dT` temperature minus its mean, `th` hours from the mean time); every effect
//! has one parameter per axis, in the physical unit of [`Effect::unit`]:
//!
//! | effect | term on axis i |
//! |---|---|
//! | temperature bias | `1e-6 p_i c_i dT` (ug/K) |
//! | temperature scale | `1e-6 p_i z_i dT` (ppm/K) |
//! | drift | `1e-6 p_i c_i th` (ug/h) |
//! | K2 | `1e-6 p_i z_i^2 / c_i` (ug/g^2) |
//! | K3 | `1e-6 p_i z_i^3 / c_i^2` (ug/g^3) |
//! | settling | `1e-6 p_i (am_{k-1,i} - am_{k,i})` (ppm of the step) |
//!
//! [`diagnose`] fits the baseline (exact linear quadric start, then Levenberg-Marquardt),
//! screens every candidate by principal angles (identifiability) and a score test on the
//! projected columns ([`TestMode`]: chi2 when the noise model is known and the remainder after
//! the candidate is consistent with it, the sigma-free F form otherwise), selects
//! forward-stepwise with a family-wise correction over the candidates of each stage
//! ([`Correction`]: exact min-p by fixed-seed Monte Carlo, or Bonferroni) and a nonlinear
//! re-fit after each step, and measures the
//! leave-one-dwell-out held-out gap after 0, 1, ... effects with the selection redone inside
//! each fold. The held-out [`Gate`] then drops a selected effect that does not lower it.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lsq::{lstsq_qr, solve_nls, NlsOptions, Residuals};
use nalgebra::{DMatrix, DVector};

const MICRO: f64 = 1e-6;
/// Number of calibration parameters of the baseline model.
pub const N_BASE: usize = 9;

/// A candidate unmodelled effect of the static dictionary.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Effect {
    /// Bias proportional to the temperature change.
    TemperatureBias,
    /// Scale factor proportional to the temperature change.
    TemperatureScale,
    /// Bias linear in time.
    Drift,
    /// Quadratic nonlinearity per axis.
    K2,
    /// Cubic nonlinearity per axis.
    K3,
    /// Incomplete settling after a pose change: a fraction of the step persists.
    Settling,
}

impl Effect {
    /// Every static effect, in dictionary order.
    pub const ALL: [Effect; 6] = [
        Effect::TemperatureBias,
        Effect::TemperatureScale,
        Effect::Drift,
        Effect::K2,
        Effect::K3,
        Effect::Settling,
    ];

    /// Public name (`"temperature_bias"`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Effect::TemperatureBias => "temperature_bias",
            Effect::TemperatureScale => "temperature_scale",
            Effect::Drift => "drift",
            Effect::K2 => "k2",
            Effect::K3 => "k3",
            Effect::Settling => "settling",
        }
    }

    /// Parse a public name.
    pub fn from_name(s: &str) -> Result<Effect> {
        Effect::ALL
            .iter()
            .copied()
            .find(|e| e.name() == s)
            .ok_or_else(|| {
                CoreError::InvalidInput(format!(
                    "unknown effect {s:?}; known: temperature_bias, temperature_scale, drift, k2, \
                     k3, settling"
                ))
            })
    }

    /// Physical unit of the effect's parameters.
    pub fn unit(self) -> &'static str {
        match self {
            Effect::TemperatureBias => "ug/K",
            Effect::TemperatureScale => "ppm/K",
            Effect::Drift => "ug/h",
            Effect::K2 => "ug/g^2",
            Effect::K3 => "ug/g^3",
            Effect::Settling => "ppm of step",
        }
    }

    fn uses_temperature(self) -> bool {
        matches!(self, Effect::TemperatureBias | Effect::TemperatureScale)
    }
}

/// Whether a candidate could be tested on this session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    /// Tested (some direction outside the baseline's range).
    Testable,
    /// Every direction is absorbed by the calibration parameters: a blind spot of this session.
    Blind,
    /// Temperature effect, no temperature recorded.
    NoTemperature,
    /// Temperature effect, temperature (nearly) constant.
    ConstantTemperature,
    /// Drift, no dwell times.
    NoTime,
    /// Too few dwells left for a test.
    TooFewDwells,
    /// Already in the model (later stepwise stages).
    Selected,
}

impl Status {
    /// Public name.
    pub fn name(self) -> &'static str {
        match self {
            Status::Testable => "testable",
            Status::Blind => "blind",
            Status::NoTemperature => "no_temperature",
            Status::ConstantTemperature => "constant_temperature",
            Status::NoTime => "no_time",
            Status::TooFewDwells => "too_few_dwells",
            Status::Selected => "selected",
        }
    }
}

/// Input of [`diagnose`]: dwell means in raw units and their noise.
#[derive(Debug, Clone)]
pub struct GapInput {
    /// Raw dwell means, time order.
    pub mean: Vec<[f64; 3]>,
    /// Standard deviation of each dwell mean per axis (raw units); `None`: unknown, the
    /// diagnosis then scales unit weights by the baseline residual (no absolute gap test).
    pub sigma_mean: Option<Vec<[f64; 3]>>,
    /// Mid time of each dwell, s.
    pub t: Option<Vec<f64>>,
    /// Temperature of each dwell.
    pub temperature: Option<Vec<f64>>,
    /// Reference gravity, m/s^2.
    pub g: f64,
}

/// Settings of [`diagnose`].
#[derive(Debug, Clone)]
pub struct GapOptions {
    /// Family-wise false-alarm level of the attribution.
    pub alpha: f64,
    /// Candidates to consider.
    pub effects: Vec<Effect>,
    /// At most this many effects are added.
    pub max_effects: usize,
    /// Compute the leave-one-dwell-out held-out gap.
    pub loo: bool,
    /// Principal-angle sine below which a direction counts as absorbed.
    pub sine_tol: f64,
    /// Principal-angle cosine above which two candidates count as aliased.
    pub ambiguity_cos: f64,
    /// Temperature range below which the temperature counts as constant.
    pub min_temp_range: f64,
    /// Start values `[sx,sy,sz,bx,by,bz,m1,m2,m3]` instead of the linear quadric fit.
    pub start: Option<[f64; N_BASE]>,
    /// Which test attributes (see [`TestMode`]).
    pub test: TestMode,
    /// [`TestMode::Auto`]: the chi2 score test is used for a candidate only when the chi2 of
    /// what remains after it has an upper-tail p-value above this level (noise model trusted).
    pub trust_level: f64,
    /// Held-out gate (see [`Gate`]).
    pub gate: Gate,
    /// Family-wise correction over the candidates of a stepwise stage (see [`Correction`]).
    pub correction: Correction,
    /// [`Correction::MinP`]: at most this many null draws per decision (sequential: fewer
    /// when the decision is clear).
    pub n_draws: usize,
    /// [`Gate::Auto`]: an effect after which the remainder is consistent in-sample is also
    /// kept when the held-out `G^2` grows by at most `gate_margin * sqrt(2 / n)` (about
    /// `gate_margin` standard deviations of `G^2`).
    pub gate_margin: f64,
}

/// Family-wise correction of the attribution over the testable candidates of a stage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Correction {
    /// Declare the best candidate when `p < alpha / M` (M testable candidates).
    Bonferroni,
    /// Exact min-p (Westfall-Young, max-statistic): the adjusted p-value of the best
    /// candidate is the probability, under the null of the current model, that the smallest
    /// p-value over the candidates is at most the observed one. The null whitened residual is
    /// `(I - H) z`, `z ~ N(0, I)`; each candidate keeps the test (chi2 or sigma-free F) chosen
    /// on the data. Monte Carlo with fixed-seed draws (deterministic), computed only when the
    /// Bonferroni decision is not already clear (`alpha / M <= p < alpha`, always on the
    /// full data for the reported value). Never above the Bonferroni bound `M p`.
    MinP,
}

impl Correction {
    /// Parse `"minp"` or `"bonferroni"`.
    pub fn from_name(s: &str) -> Result<Correction> {
        match s {
            "minp" => Ok(Correction::MinP),
            "bonferroni" => Ok(Correction::Bonferroni),
            _ => invalid(format!(
                "correction must be 'minp' or 'bonferroni'; got {s:?}"
            )),
        }
    }
}

/// When a selected effect must also lower the held-out gap to count as an explanation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Gate {
    /// No held-out check.
    Off,
    /// Every selected effect must lower the held-out gap.
    Strict,
    /// As `Strict`, except that an effect after which the remainder is consistent with the
    /// (known) noise model is kept: remaining chi2 p >= alpha and held-out `G^2 <= 1 +
    /// 2 sqrt(2/n)`. The held-out gap is too noisy to confirm weak effects, and a model that
    /// fits to the noise level, in-sample and held out, needs no further explanation.
    Auto,
}

impl Gate {
    /// Parse `"auto"`, `"strict"` or `"off"`.
    pub fn from_name(s: &str) -> Result<Gate> {
        match s {
            "off" => Ok(Gate::Off),
            "strict" => Ok(Gate::Strict),
            "auto" => Ok(Gate::Auto),
            _ => invalid(format!("gate must be 'auto', 'strict' or 'off'; got {s:?}")),
        }
    }
}

/// Test statistic used to attribute (select) an effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TestMode {
    /// Sigma-free F test (robust to a mis-scaled noise model, less power with few dwells).
    F,
    /// chi2 score test (trusts the noise model).
    Chi2,
    /// chi2 when the noise model is known and the remainder after the candidate is consistent
    /// with it, F otherwise.
    Auto,
}

impl TestMode {
    /// Parse `"f"`, `"chi2"` or `"auto"`.
    pub fn from_name(s: &str) -> Result<TestMode> {
        match s {
            "f" => Ok(TestMode::F),
            "chi2" => Ok(TestMode::Chi2),
            "auto" => Ok(TestMode::Auto),
            _ => invalid(format!("test must be 'auto', 'chi2' or 'f'; got {s:?}")),
        }
    }
}

impl Default for GapOptions {
    fn default() -> Self {
        GapOptions {
            alpha: 0.05,
            effects: Effect::ALL.to_vec(),
            max_effects: 3,
            loo: true,
            sine_tol: 0.05,
            ambiguity_cos: 0.9,
            min_temp_range: 0.05,
            start: None,
            test: TestMode::Auto,
            trust_level: 0.1,
            gate: Gate::Auto,
            correction: Correction::MinP,
            n_draws: 4000,
            gate_margin: 0.0,
        }
    }
}

/// One candidate's screening result (first stepwise stage: single effect against the baseline).
#[derive(Debug, Clone)]
pub struct CandidateReport {
    /// The effect.
    pub effect: Effect,
    /// Testable, blind, or why not testable.
    pub status: Status,
    /// Sines of the principal angles between its columns and the baseline Jacobian.
    pub sines: Vec<f64>,
    /// Directions kept (sine above tolerance).
    pub d: usize,
    /// Score statistic (chi2 reduction of the whitened residual, linearised).
    pub score: f64,
    /// F statistic (sigma free).
    pub f: f64,
    /// p-value of the F test.
    pub p_f: f64,
    /// p-value of the chi2 score test (trusts the noise model).
    pub p_chi2: f64,
    /// p-value used for attribution (chi2 or F, see [`TestMode`]).
    pub p: f64,
    /// Whether the chi2 form was used for `p`.
    pub chi2_used: bool,
    /// BIC of baseline + this effect (sigma-free form).
    pub bic: f64,
    /// BIC weight among "none" and all testable candidates.
    pub weight: f64,
    /// Estimated parameters per axis, physical units (linearised; re-fitted if selected).
    pub estimate: [f64; 3],
    /// Their standard deviations.
    pub std: [f64; 3],
    /// Orthonormal basis of the kept projected directions (`n x d`), for aliasing.
    w: DMatrix<f64>,
}

/// Leave-one-dwell-out held-out gap.
#[derive(Debug, Clone)]
pub struct LooReport {
    /// Held-out gap of the baseline (1 for an adequate model).
    pub g_before: f64,
    /// Held-out gap with the selection redone inside each fold.
    pub g_after: f64,
    /// Held-out RMS of the norm residual, m/s^2, baseline.
    pub rms_before: f64,
    /// The same after.
    pub rms_after: f64,
    /// Standardised prediction error per dwell, baseline (NaN where the fold failed).
    pub z_before: Vec<f64>,
    /// The same after.
    pub z_after: Vec<f64>,
    /// Held-out gap with at most k effects selected in each fold, k = 0, 1, ... (the number
    /// selected on all dwells, before the gate).
    pub g_steps: Vec<f64>,
    /// How many folds selected each effect (order of [`Effect::ALL`]; a fold selects at most
    /// as many effects as the full data did).
    pub fold_counts: [usize; 6],
    /// Folds whose fit failed.
    pub n_failed: usize,
}

/// Everything [`diagnose`] measured.
#[derive(Debug, Clone)]
pub struct GapResult {
    /// Dwells.
    pub n: usize,
    /// Baseline parameters `[sx,sy,sz,bx,by,bz,m1,m2,m3]` (K in raw units per m/s^2).
    pub base_params: Vec<f64>,
    /// Their standard deviations (unit-variance whitening).
    pub base_std: Vec<f64>,
    /// Propagated noise of each residual, m/s^2.
    pub sigma_r: Vec<f64>,
    /// Baseline norm residuals, m/s^2.
    pub resid: Vec<f64>,
    /// Baseline whitened residuals.
    pub e: Vec<f64>,
    /// Baseline leverages.
    pub leverage: Vec<f64>,
    /// Baseline chi2, degrees of freedom and p-value (NaN when the noise is unknown).
    pub chi2: f64,
    /// Degrees of freedom of the baseline.
    pub dof: usize,
    /// p-value of the baseline chi2.
    pub p_chi2: f64,
    /// Whether the noise model came from the data (false: unit weights scaled to the fit).
    pub noise_known: bool,
    /// Candidate screening, dictionary order of the requested effects.
    pub candidates: Vec<CandidateReport>,
    /// BIC and weight of "no effect".
    pub bic_none: f64,
    /// BIC weight of "no effect".
    pub weight_none: f64,
    /// Selected effects in order.
    pub selected: Vec<Effect>,
    /// p-value at which each was selected (the candidate's own test).
    pub step_p: Vec<f64>,
    /// Family-wise adjusted p-value of each selection (min-p; the Bonferroni bound `M p`
    /// with [`Correction::Bonferroni`]).
    pub step_p_adj: Vec<f64>,
    /// Number of testable candidates (family size M) at each selection.
    pub step_m: Vec<usize>,
    /// Effect selected in-sample but rejected by the held-out gate: (effect, p, G before, G
    /// with it).
    pub not_confirmed: Option<(Effect, f64, f64, f64)>,
    /// p-value of the best remaining candidate when the selection stopped (NaN: none left).
    pub stop_p: f64,
    /// Its family-wise adjusted p-value (NaN: none left).
    pub stop_p_adj: f64,
    /// Parameters after (baseline then 3 per selected effect).
    pub params_after: Vec<f64>,
    /// Their standard deviations (scaled by the residual variance when it exceeds 1).
    pub std_after: Vec<f64>,
    /// Norm residuals after, m/s^2.
    pub resid_after: Vec<f64>,
    /// Whitened residuals after.
    pub e_after: Vec<f64>,
    /// chi2 after.
    pub chi2_after: f64,
    /// Degrees of freedom after.
    pub dof_after: usize,
    /// p-value of chi2 after.
    pub p_after: f64,
    /// Aliased pairs `(best, other, cosine)` with similar evidence.
    pub ambiguous: Vec<(Effect, Effect, f64)>,
    /// Held-out gap (when requested and possible).
    pub loo: Option<LooReport>,
    /// The held-out gate was skipped: a leave-one-out fold keeps fewer than 2 residual
    /// degrees of freedom after the selected model.
    pub gate_skipped: bool,
}

// ------------------------------------------------------------------------------------------
// Special functions (p-values without SciPy).

fn ln_gamma(x: f64) -> f64 {
    // Lanczos (g = 7, n = 9), |rel err| < 1e-13 for x > 0.
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma `Q(a, x)`.
fn gamma_q(a: f64, x: f64) -> f64 {
    if !(x > 0.0) {
        return 1.0;
    }
    if !x.is_finite() {
        return 0.0;
    }
    let lg = ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut del, mut ap) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            ap += 1.0;
            del *= x / ap;
            sum += del;
            if del.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        (1.0 - sum * (-x + a * x.ln() - lg).exp()).clamp(0.0, 1.0)
    } else {
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        ((-x + a * x.ln() - lg).exp() * h).clamp(0.0, 1.0)
    }
}

fn beta_cf(a: f64, b: f64, x: f64) -> f64 {
    let tiny = 1e-300;
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 - qab * x / qap;
    if d.abs() < tiny {
        d = tiny;
    }
    d = 1.0 / d;
    let mut h = d;
    for m in 1..1000 {
        let m = m as f64;
        let m2 = 2.0 * m;
        let aa = m * (b - m) * x / ((qam + m2) * (a + m2));
        d = 1.0 + aa * d;
        if d.abs() < tiny {
            d = tiny;
        }
        c = 1.0 + aa / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        h *= d * c;
        let aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2));
        d = 1.0 + aa * d;
        if d.abs() < tiny {
            d = tiny;
        }
        c = 1.0 + aa / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-15 {
            break;
        }
    }
    h
}

/// Regularised incomplete beta `I_x(a, b)`.
fn beta_inc(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_bt = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let bt = ln_bt.exp();
    if x < (a + 1.0) / (a + b + 2.0) {
        (bt * beta_cf(a, b, x) / a).clamp(0.0, 1.0)
    } else {
        (1.0 - bt * beta_cf(b, a, 1.0 - x) / b).clamp(0.0, 1.0)
    }
}

/// Survival function of chi2 with `k` degrees of freedom.
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    if !(k > 0.0) || x.is_nan() {
        return f64::NAN;
    }
    gamma_q(0.5 * k, 0.5 * x)
}

/// Survival function of F(d1, d2).
pub fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if !(d1 > 0.0 && d2 > 0.0) || f.is_nan() {
        return f64::NAN;
    }
    if f <= 0.0 {
        return 1.0;
    }
    beta_inc(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * f))
}

// ------------------------------------------------------------------------------------------
// Linear quadric start (SPEC 1, exact recovery steps 1-4).

/// Exact linear norm fit `[sx,sy,sz,bx,by,bz,m1,m2,m3]` of raw dwell means (no iteration).
pub fn quadric_start(mean: &[[f64; 3]], g: f64) -> Result<[f64; N_BASE]> {
    let n = mean.len();
    if n < N_BASE {
        return degenerate(format!(
            "{n} dwells cannot determine the 9 calibration parameters (need at least 9)"
        ));
    }
    let mut mu = [0.0; 3];
    for m in mean {
        for i in 0..3 {
            mu[i] += m[i] / n as f64;
        }
    }
    let mut s2 = 0.0;
    for m in mean {
        for i in 0..3 {
            s2 += (m[i] - mu[i]).powi(2) / n as f64;
        }
    }
    let sc = s2.sqrt();
    if !(sc > 0.0) || !sc.is_finite() {
        return degenerate("all dwell means are identical: the session has one pose");
    }
    let mut a = Vec::with_capacity(n * 9);
    let mut y = Vec::with_capacity(n);
    for m in mean {
        let (x0, x1, x2) = (
            (m[0] - mu[0]) / sc,
            (m[1] - mu[1]) / sc,
            (m[2] - mu[2]) / sc,
        );
        a.extend_from_slice(&[
            x0 * x0,
            x1 * x1,
            2.0 * x0 * x1,
            2.0 * x0 * x2,
            2.0 * x1 * x2,
            2.0 * x0,
            2.0 * x1,
            2.0 * x2,
            1.0,
        ]);
        y.push(x2 * x2);
    }
    let beta = lstsq_qr(&a, n, 9, &y)?;
    let qt = nalgebra::Matrix3::new(
        -beta[0], -beta[2], -beta[3], -beta[2], -beta[1], -beta[4], -beta[3], -beta[4], 1.0,
    );
    let qti = qt.try_inverse().ok_or_else(|| {
        CoreError::Degenerate("the quadric of the dwell means is singular".into())
    })?;
    let bb = qti * nalgebra::Vector3::new(beta[5], beta[6], beta[7]);
    let q33 = g * g / ((bb.transpose() * qt * bb)[(0, 0)] + beta[8]);
    let q = qt * q33;
    let chol = q.cholesky().ok_or_else(|| {
        CoreError::Degenerate(
            "the dwell means do not lie on an ellipsoid (quadric not positive definite): \
             poses too few or too clustered"
                .into(),
        )
    })?;
    let qi = chol.inverse();
    let k = qi.cholesky().ok_or_else(|| {
        CoreError::Degenerate("the fitted ellipsoid is not positive definite".into())
    })?;
    let k = k.l();
    let p = [
        k[(0, 0)] * sc,
        k[(1, 1)] * sc,
        k[(2, 2)] * sc,
        bb[0] * sc + mu[0],
        bb[1] * sc + mu[1],
        bb[2] * sc + mu[2],
        k[(1, 0)] * sc,
        k[(2, 0)] * sc,
        k[(2, 1)] * sc,
    ];
    if p.iter().any(|v| !v.is_finite()) {
        return degenerate("the linear norm fit produced non-finite parameters");
    }
    Ok(p)
}

// ------------------------------------------------------------------------------------------
// The augmented model.

struct Session {
    n: usize,
    am: Vec<[f64; 3]>,
    dt: Vec<f64>,
    th: Vec<f64>,
    step: Vec<[f64; 3]>,
    c: [f64; 3],
    sig: Vec<f64>,
    c_g: f64,
}

/// Term of `effect` on axis `i` per unit (1e-6) parameter, and its derivative in `z_i`.
#[inline]
fn h_term(s: &Session, e: Effect, k: usize, i: usize, z: f64) -> (f64, f64) {
    let c = s.c[i];
    match e {
        Effect::TemperatureBias => (c * s.dt[k], 0.0),
        Effect::TemperatureScale => (z * s.dt[k], s.dt[k]),
        Effect::Drift => (c * s.th[k], 0.0),
        Effect::K2 => (z * z / c, 2.0 * z / c),
        Effect::K3 => (z * z * z / (c * c), 3.0 * z * z / (c * c)),
        Effect::Settling => (s.step[k][i], 0.0),
    }
}

struct RowEval {
    r: f64,
    v: [f64; 3],
    a: [f64; 3],
    z: [f64; 3],
    dwdz: [f64; 3],
}

fn row_eval(s: &Session, p: &[f64], effects: &[Effect], k: usize) -> Option<RowEval> {
    let (sx, sy, sz, m1, m2, m3) = (p[0], p[1], p[2], p[6], p[7], p[8]);
    let z = [s.am[k][0] - p[3], s.am[k][1] - p[4], s.am[k][2] - p[5]];
    let mut w = z;
    let mut dwdz = [1.0; 3];
    for (j, &e) in effects.iter().enumerate() {
        for i in 0..3 {
            let pe = MICRO * p[N_BASE + 3 * j + i];
            let (h, hp) = h_term(s, e, k, i, z[i]);
            w[i] -= pe * h;
            dwdz[i] -= pe * hp;
        }
    }
    if sx == 0.0 || sy == 0.0 || sz == 0.0 {
        return None;
    }
    let a0 = w[0] / sx;
    let a1 = (w[1] - m1 * a0) / sy;
    let a2 = (w[2] - m2 * a0 - m3 * a1) / sz;
    let na = (a0 * a0 + a1 * a1 + a2 * a2).sqrt();
    if !(na > 0.0) || !na.is_finite() {
        return None;
    }
    let u = [a0 / na, a1 / na, a2 / na];
    // v = K^-T u (K^T upper triangular).
    let v2 = u[2] / sz;
    let v1 = (u[1] - m3 * v2) / sy;
    let v0 = (u[0] - m1 * v1 - m2 * v2) / sx;
    Some(RowEval {
        r: na - s.c_g,
        v: [v0, v1, v2],
        a: [a0, a1, a2],
        z,
        dwdz,
    })
}

struct Prob<'a> {
    s: &'a Session,
    rows: &'a [usize],
    effects: &'a [Effect],
}

fn fill_row(s: &Session, ev: &RowEval, effects: &[Effect], k: usize, out: &mut [f64]) {
    let (v, a) = (ev.v, ev.a);
    out[0] = -v[0] * a[0];
    out[1] = -v[1] * a[1];
    out[2] = -v[2] * a[2];
    out[3] = -v[0] * ev.dwdz[0];
    out[4] = -v[1] * ev.dwdz[1];
    out[5] = -v[2] * ev.dwdz[2];
    out[6] = -v[1] * a[0];
    out[7] = -v[2] * a[0];
    out[8] = -v[2] * a[1];
    for (j, &e) in effects.iter().enumerate() {
        for i in 0..3 {
            out[N_BASE + 3 * j + i] = -v[i] * MICRO * h_term(s, e, k, i, ev.z[i]).0;
        }
    }
}

impl Residuals for Prob<'_> {
    fn n_params(&self) -> usize {
        N_BASE + 3 * self.effects.len()
    }
    fn n_residuals(&self) -> usize {
        self.rows.len()
    }
    fn eval(&self, p: &[f64], r: &mut [f64], jac: &mut DMatrix<f64>) -> Result<()> {
        let np = self.n_params();
        let mut row = vec![0.0; np];
        for (ri, &k) in self.rows.iter().enumerate() {
            let ev = row_eval(self.s, p, self.effects, k).ok_or_else(|| {
                CoreError::NotConverged("model not evaluable (zero scale or norm)".into())
            })?;
            let w = 1.0 / self.s.sig[k];
            r[ri] = ev.r * w;
            fill_row(self.s, &ev, self.effects, k, &mut row);
            for (c, v) in row.iter().enumerate() {
                jac[(ri, c)] = v * w;
            }
        }
        Ok(())
    }
}

fn nls_opts(gauss_newton: bool) -> NlsOptions {
    NlsOptions {
        max_iter: if gauss_newton { 12 } else { 100 },
        ftol: if gauss_newton { 1e-10 } else { 1e-12 },
        xtol: 1e-10,
        gtol: 1e-10,
        gauss_newton,
    }
}

struct Fit {
    p: Vec<f64>,
    e: Vec<f64>,
    jac: DMatrix<f64>,
    rss: f64,
}

/// Gauss-Newton from a (warm) start, falling back to Levenberg-Marquardt when it fails or
/// ends above its start cost.
fn fit(s: &Session, rows: &[usize], effects: &[Effect], p0: &[f64]) -> Result<Fit> {
    let prob = Prob { s, rows, effects };
    let rep = match solve_nls(&prob, p0, &nls_opts(true)) {
        Ok(r) if r.converged && r.cost.is_finite() => r,
        _ => solve_nls(&prob, p0, &nls_opts(false))?,
    };
    Ok(Fit {
        rss: rep.cost,
        p: rep.params,
        e: rep.residuals,
        jac: rep.jacobian,
    })
}

/// Range basis, leverage and unit covariance of a Jacobian via SVD (rank-truncated).
struct Basis {
    q: DMatrix<f64>,
    cov: DMatrix<f64>,
    rank: usize,
}

fn basis(j: &DMatrix<f64>) -> Result<Basis> {
    let (m, n) = (j.nrows(), j.ncols());
    // Scale columns for a scale-free rank decision.
    let mut d = vec![0.0; n];
    for c in 0..n {
        d[c] = j.column(c).norm();
        if !(d[c] > 0.0) {
            d[c] = 1.0;
        }
    }
    let js = DMatrix::from_fn(m, n, |a, b| j[(a, b)] / d[b]);
    let svd = js.svd(true, true);
    let (u, vt) = match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => (u, vt),
        _ => return Err(CoreError::NotConverged("SVD of the Jacobian failed".into())),
    };
    let smax = svd.singular_values.max();
    let keep: Vec<usize> = (0..svd.singular_values.len())
        .filter(|&i| svd.singular_values[i] > 1e-9 * smax)
        .collect();
    let q = DMatrix::from_fn(m, keep.len(), |a, b| u[(a, keep[b])]);
    let mut cov = DMatrix::zeros(n, n);
    for &k in &keep {
        let w = 1.0 / svd.singular_values[k].powi(2);
        for a in 0..n {
            let va = vt[(k, a)] * w / d[a];
            for b in 0..n {
                cov[(a, b)] += va * vt[(k, b)] / d[b];
            }
        }
    }
    Ok(Basis {
        q,
        cov,
        rank: keep.len(),
    })
}

fn candidate_columns(s: &Session, rows: &[usize], evs: &[RowEval], e: Effect) -> DMatrix<f64> {
    let mut c = DMatrix::zeros(rows.len(), 3);
    for (ri, (&k, ev)) in rows.iter().zip(evs).enumerate() {
        for i in 0..3 {
            c[(ri, i)] = -ev.v[i] * MICRO * h_term(s, e, k, i, ev.z[i]).0 / s.sig[k];
        }
    }
    c
}

fn row_evals(s: &Session, rows: &[usize], p: &[f64], active: &[Effect]) -> Result<Vec<RowEval>> {
    rows.iter()
        .map(|&k| {
            row_eval(s, p, active, k)
                .ok_or_else(|| CoreError::NotConverged("model not evaluable".into()))
        })
        .collect()
}

struct Screened {
    status: Status,
    sines: Vec<f64>,
    d: usize,
    score: f64,
    f: f64,
    p_f: f64,
    p_chi2: f64,
    p: f64,
    chi2_used: bool,
    est: [f64; 3],
    std: [f64; 3],
    w: DMatrix<f64>,
}

/// Test mode and trust level after accounting for an unknown noise model.
#[derive(Clone, Copy)]
struct TestCfg {
    mode: TestMode,
    trust_level: f64,
    sine_tol: f64,
}

fn screen_one(
    c: &DMatrix<f64>,
    b: &Basis,
    e: &DVector<f64>,
    rss: f64,
    cfg: TestCfg,
    full: bool,
) -> Screened {
    let sine_tol = cfg.sine_tol;
    let n = c.nrows();
    let mut out = Screened {
        status: Status::Blind,
        sines: vec![],
        d: 0,
        score: 0.0,
        f: f64::NAN,
        p_f: f64::NAN,
        p_chi2: f64::NAN,
        p: f64::NAN,
        chi2_used: false,
        est: [f64::NAN; 3],
        std: [f64::NAN; 3],
        w: DMatrix::zeros(n, 0),
    };
    let norms: Vec<f64> = (0..3).map(|i| c.column(i).norm()).collect();
    let nmax = norms.iter().cloned().fold(0.0, f64::max);
    if !(nmax > 0.0) {
        return out;
    }
    let cn = DMatrix::from_fn(n, 3, |a, i| {
        if norms[i] > 1e-12 * nmax {
            c[(a, i)] / norms[i]
        } else {
            0.0
        }
    });
    // Orthonormal basis of range(C).
    let svd_c = cn.svd(true, false);
    let Some(uc) = svd_c.u else { return out };
    let kc: Vec<usize> = (0..svd_c.singular_values.len())
        .filter(|&i| svd_c.singular_values[i] > 1e-8)
        .collect();
    if kc.is_empty() {
        return out;
    }
    let ucn = DMatrix::from_fn(n, kc.len(), |a, b| uc[(a, kc[b])]);
    let p = &ucn - &b.q * (b.q.transpose() * &ucn);
    let svd_p = p.svd(true, false);
    let Some(up) = svd_p.u else { return out };
    let mut sines: Vec<f64> = svd_p.singular_values.iter().copied().collect();
    let kept: Vec<usize> = (0..sines.len()).filter(|&i| sines[i] > sine_tol).collect();
    sines.sort_by(|a, b| b.total_cmp(a));
    out.sines = sines;
    if kept.is_empty() {
        return out;
    }
    let d = kept.len();
    let w = DMatrix::from_fn(n, d, |a, bb| up[(a, kept[bb])]);
    let we = w.transpose() * e;
    let score = we.norm_squared();
    let dof2 = n as f64 - b.rank as f64 - d as f64;
    out.d = d;
    out.score = score;
    out.w = w;
    if dof2 < 1.0 {
        out.status = Status::TooFewDwells;
        return out;
    }
    out.status = Status::Testable;
    let rem = (rss - score).max(1e-300);
    out.f = (score / d as f64) / (rem / dof2);
    out.p_f = f_sf(out.f, d as f64, dof2);
    out.p_chi2 = chi2_sf(score, d as f64);
    out.chi2_used = match cfg.mode {
        TestMode::F => false,
        TestMode::Chi2 => true,
        TestMode::Auto => chi2_sf(rem, dof2) > cfg.trust_level,
    };
    out.p = if out.chi2_used { out.p_chi2 } else { out.p_f };
    if full {
        // Minimal-norm estimate on the projected columns, truncated like the test.
        let cp = c - &b.q * (b.q.transpose() * c);
        let svd = cp.svd(true, true);
        if let (Some(u2), Some(vt2)) = (svd.u, svd.v_t) {
            let s2 = rem / dof2;
            let mut est = [0.0; 3];
            let mut var = [0.0; 3];
            for k in 0..svd.singular_values.len() {
                let sk = svd.singular_values[k];
                if !(sk > sine_tol * nmax) {
                    continue;
                }
                // The residual falls along e + C x: x = -C^+ e.
                let coef = -u2.column(k).dot(e) / sk;
                for i in 0..3 {
                    est[i] += vt2[(k, i)] * coef;
                    var[i] += (vt2[(k, i)] / sk).powi(2) * s2;
                }
            }
            out.est = est;
            out.std = [var[0].sqrt(), var[1].sqrt(), var[2].sqrt()];
        }
    }
    out
}

struct Stepwise {
    effects: Vec<Effect>,
    step_p: Vec<f64>,
    step_p_adj: Vec<f64>,
    step_m: Vec<usize>,
    stop_p: f64,
    stop_p_adj: f64,
    /// Fits after 0, 1, ... selected effects (the last is the final model).
    history: Vec<Fit>,
    first: Vec<(Effect, Screened)>,
    basis0: Option<Basis>,
}

// ------------------------------------------------------------------------------------------
// Family-wise correction: exact min-p by Monte Carlo under the null of the current model.

/// One testable candidate of a stage, as the min-p correction needs it.
struct Member {
    /// Orthonormal projected directions (`n x d`), orthogonal to the current Jacobian.
    w: DMatrix<f64>,
    /// chi2 score test (else the sigma-free F test).
    chi2: bool,
    /// Denominator degrees of freedom of the F test.
    dof2: f64,
    /// Observed p-value.
    p: f64,
    /// Observed statistic (score for chi2, F for F).
    stat: f64,
}

const POOL_LEN: usize = 1 << 18;
const POOL_SEED: u64 = 0x9E37_79B9_7F4A_7C15;
static NULL_POOL: std::sync::OnceLock<Vec<f64>> = std::sync::OnceLock::new();

/// `len` standard normals from a fixed seed (xoshiro256++, Marsaglia polar method).
fn normals(seed: u64, len: usize) -> Vec<f64> {
    let mut sm = seed;
    let mut next_sm = || {
        sm = sm.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = sm;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut st = [next_sm(), next_sm(), next_sm(), next_sm()];
    let mut next = || {
        let r = st[0]
            .wrapping_add(st[3])
            .rotate_left(23)
            .wrapping_add(st[0]);
        let t = st[1] << 17;
        st[2] ^= st[0];
        st[3] ^= st[1];
        st[1] ^= st[2];
        st[0] ^= st[3];
        st[2] ^= t;
        st[3] = st[3].rotate_left(45);
        (r >> 11) as f64 * (1.0 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    let mut out = Vec::with_capacity(len + 1);
    while out.len() < len {
        let (u, v) = (next(), next());
        let s = u * u + v * v;
        if s >= 1.0 || s == 0.0 {
            continue;
        }
        let f = (-2.0 * s.ln() / s).sqrt();
        out.push(u * f);
        out.push(v * f);
    }
    out.truncate(len);
    out
}

/// Upper-tail quantile: the statistic at which the test's p-value equals `p`.
fn isf(p: f64, chi2: bool, d: f64, dof2: f64) -> f64 {
    let sf = |x: f64| {
        if chi2 {
            chi2_sf(x, d)
        } else {
            f_sf(x, d, dof2)
        }
    };
    let (mut lo, mut hi) = (0.0, 1.0);
    let mut it = 0;
    while sf(hi) > p && it < 1100 {
        lo = hi;
        hi *= 2.0;
        it += 1;
    }
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if sf(mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-9 * hi {
            break;
        }
    }
    hi
}

/// Min-p adjusted p-value of the best of `fam` (observed smallest p-value `p_obs`) under the
/// null whitened residual `(I - Q Q^T) z`, `z ~ N(0, I)`, `Q` the orthonormal range basis
/// of the current Jacobian. Sequential Monte Carlo (250 fixed-seed draws, then chunks of 500,
/// at most `n_draws`, stopped once the estimate is 3 standard errors from `alpha`); the estimate
/// `(k + 1) / (b + 1)` is capped by the Bonferroni bound `M p_obs`.
fn min_p(q: &DMatrix<f64>, fam: &[Member], p_obs: f64, alpha: f64, n_draws: usize) -> f64 {
    let m_fam = fam.len();
    if m_fam == 0 || !p_obs.is_finite() {
        return f64::NAN;
    }
    let bonf = (p_obs * m_fam as f64).min(1.0);
    if m_fam == 1 || !(p_obs > 0.0) || bonf < 1e-4 || n_draws == 0 {
        return if m_fam == 1 { p_obs } else { bonf };
    }
    let m = q.nrows();
    let r = q.ncols();
    // Stacked columns [Q | W_1 | ... | W_M], transposed.
    let ncol = r + fam.iter().map(|f| f.w.ncols()).sum::<usize>();
    let mut at = DMatrix::zeros(ncol, m);
    let mut off = vec![];
    let mut c0 = 0;
    for j in 0..r {
        at.row_mut(c0 + j).copy_from(&q.column(j).transpose());
    }
    c0 += r;
    for f in fam {
        off.push(c0);
        for j in 0..f.w.ncols() {
            at.row_mut(c0 + j).copy_from(&f.w.column(j).transpose());
        }
        c0 += f.w.ncols();
    }
    // Critical values at p_obs (one inversion per distinct test).
    let mut cache: Vec<(bool, usize, f64, f64)> = vec![];
    let crit: Vec<f64> = fam
        .iter()
        .map(|f| {
            let d = f.w.ncols();
            if f.p <= p_obs {
                return f.stat;
            }
            let key_dof2 = if f.chi2 { 0.0 } else { f.dof2 };
            if let Some(c) = cache
                .iter()
                .find(|c| c.0 == f.chi2 && c.1 == d && c.2 == key_dof2)
            {
                return c.3;
            }
            let c = isf(p_obs, f.chi2, d as f64, f.dof2);
            cache.push((f.chi2, d, key_dof2, c));
            c
        })
        .collect();
    let local;
    let pool: &[f64] = if m * n_draws <= POOL_LEN {
        NULL_POOL.get_or_init(|| normals(POOL_SEED, POOL_LEN))
    } else {
        local = normals(POOL_SEED ^ m as u64, m * n_draws);
        &local
    };
    let (mut hits, mut done) = (0usize, 0usize);
    while done < n_draws {
        let bc = (if done == 0 { 250 } else { 500 }).min(n_draws - done);
        let zs = nalgebra::DMatrixView::from_slice(&pool[done * m..(done + bc) * m], m, bc);
        let pm = &at * zs;
        for b in 0..bc {
            let col = pm.column(b);
            let zz: f64 = zs.column(b).norm_squared();
            let ssq: f64 = (0..r).map(|j| col[j] * col[j]).sum();
            let rss = zz - ssq;
            let hit = fam.iter().enumerate().any(|(i, f)| {
                let d = f.w.ncols();
                let sc: f64 = (off[i]..off[i] + d).map(|j| col[j] * col[j]).sum();
                if f.chi2 {
                    sc >= crit[i]
                } else {
                    let rem = rss - sc;
                    rem <= 0.0 || (sc / d as f64) >= crit[i] * rem / f.dof2
                }
            });
            hits += hit as usize;
        }
        done += bc;
        let ph = (hits + 1) as f64 / (done + 1) as f64;
        let se = (alpha * (1.0 - alpha) / done as f64).sqrt();
        if (ph - alpha).abs() > 3.0 * se {
            break;
        }
    }
    ((hits + 1) as f64 / (done + 1) as f64).min(bonf)
}

fn stepwise(
    s: &Session,
    rows: &[usize],
    base: Fit,
    cands: &[Effect],
    opt: &GapOptions,
    cfg: TestCfg,
    full: bool,
) -> Result<Stepwise> {
    let mut active: Vec<Effect> = vec![];
    let mut step_p = vec![];
    let mut step_p_adj = vec![];
    let mut step_m = vec![];
    let mut history: Vec<Fit> = vec![];
    let mut cur = base;
    let mut first = vec![];
    let mut basis0 = None;
    let mut m_test = 0usize;
    let mut stop_p = f64::NAN;
    let mut stop_p_adj = f64::NAN;
    let e_max = opt.max_effects.min(cands.len());
    for step in 0..=e_max {
        if !full && step == e_max {
            // Inside a fold nothing more can be selected: no need to screen.
            break;
        }
        let b = basis(&cur.jac)?;
        let ev = DVector::from_column_slice(&cur.e);
        let evs = row_evals(s, rows, &cur.p, &active)?;
        let mut best: Option<(Effect, f64)> = None;
        let mut fam: Vec<Member> = vec![];
        for &c in cands {
            if active.contains(&c) {
                continue;
            }
            let cols = candidate_columns(s, rows, &evs, c);
            let sc = screen_one(&cols, &b, &ev, cur.rss, cfg, full && step == 0);
            if sc.status == Status::Testable {
                if best.is_none_or(|(_, pb)| sc.p < pb || pb.is_nan()) {
                    best = Some((c, sc.p));
                }
                fam.push(Member {
                    w: sc.w.clone(),
                    chi2: sc.chi2_used,
                    dof2: (rows.len() - b.rank - sc.d) as f64,
                    p: sc.p,
                    stat: if sc.chi2_used { sc.score } else { sc.f },
                });
            }
            if step == 0 {
                if sc.status == Status::Testable {
                    m_test += 1;
                }
                first.push((c, sc));
            }
        }
        let m_step = fam.len();
        // Family-wise adjusted p-value of the best candidate and the decision.
        let (p_adj, declare) = match best {
            None => (f64::NAN, false),
            Some((_, pb)) => match opt.correction {
                Correction::Bonferroni => {
                    let m_b = (m_test.saturating_sub(step)).max(1) as f64;
                    ((pb * m_b).min(1.0), pb < opt.alpha / m_b)
                }
                Correction::MinP => {
                    let bonf = (pb * m_step.max(1) as f64).min(1.0);
                    if full {
                        let pa = min_p(&b.q, &fam, pb, opt.alpha, opt.n_draws);
                        (pa, pa < opt.alpha)
                    } else if !(pb < opt.alpha) {
                        (f64::NAN, false)
                    } else if bonf < opt.alpha {
                        (bonf, true)
                    } else {
                        let pa = min_p(&b.q, &fam, pb, opt.alpha, opt.n_draws);
                        (pa, pa < opt.alpha)
                    }
                }
            },
        };
        if step == 0 {
            basis0 = Some(b);
        }
        if step == e_max {
            stop_p = best.map_or(f64::NAN, |x| x.1);
            stop_p_adj = p_adj;
            break;
        }
        let Some((bc, pb)) = best else { break };
        if !declare {
            stop_p = pb;
            stop_p_adj = p_adj;
            break;
        }
        active.push(bc);
        step_p.push(pb);
        step_p_adj.push(p_adj);
        step_m.push(m_step);
        let mut p0 = cur.p.clone();
        p0.extend_from_slice(&[0.0; 3]);
        let next = fit(s, rows, &active, &p0)?;
        history.push(std::mem::replace(&mut cur, next));
    }
    history.push(cur);
    Ok(Stepwise {
        effects: active,
        step_p,
        step_p_adj,
        step_m,
        stop_p,
        stop_p_adj,
        history,
        first,
        basis0,
    })
}

fn predict(
    s: &Session,
    p: &[f64],
    effects: &[Effect],
    cov: &DMatrix<f64>,
    k: usize,
) -> (f64, f64, f64) {
    let Some(ev) = row_eval(s, p, effects, k) else {
        return (f64::NAN, f64::NAN, f64::NAN);
    };
    let np = p.len();
    let mut row = vec![0.0; np];
    fill_row(s, &ev, effects, k, &mut row);
    let w = 1.0 / s.sig[k];
    let jr = DVector::from_iterator(np, row.iter().map(|v| v * w));
    let q = (jr.transpose() * cov * &jr)[(0, 0)];
    (ev.r * w, q.max(0.0), ev.r)
}

/// Held-out (z, residual) after 0, 1, ... selected effects, and the effects, of one fold.
type FoldOut = (Vec<(f64, f64)>, Vec<Effect>);

/// Run the full static diagnosis.
pub fn diagnose(inp: &GapInput, opt: &GapOptions) -> Result<GapResult> {
    let n = inp.mean.len();
    if !(inp.g > 0.0) || !inp.g.is_finite() {
        return invalid(format!(
            "g must be a positive gravity value in m/s^2; got {}",
            inp.g
        ));
    }
    if !(opt.alpha > 0.0 && opt.alpha < 1.0) {
        return invalid(format!("alpha must be in (0, 1); got {}", opt.alpha));
    }
    if n < N_BASE + 1 {
        return degenerate(format!(
            "{n} dwells: the 9-parameter model needs at least 10 dwells to leave any redundancy \
             for a gap test"
        ));
    }
    if inp.mean.iter().flatten().any(|v| !v.is_finite()) {
        return invalid("dwell means contain NaN or inf");
    }
    if let Some(sm) = &inp.sigma_mean {
        if sm.len() != n {
            return invalid("sigma_mean must have one row per dwell");
        }
        if sm.iter().flatten().any(|v| !(*v > 0.0) || !v.is_finite()) {
            return invalid("dwell-mean noise must be positive and finite (var > 0, count >= 1)");
        }
    }
    for (nm, a) in [("t", &inp.t), ("temperature", &inp.temperature)] {
        if let Some(a) = a {
            if a.len() != n {
                return invalid(format!("{nm} must have one value per dwell"));
            }
            if a.iter().any(|v| !v.is_finite()) {
                return invalid(format!("{nm} contains NaN or inf"));
            }
        }
    }
    let start = match opt.start {
        Some(s) => s,
        None => quadric_start(&inp.mean, inp.g)?,
    };
    let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let (dt, temp_status) = match &inp.temperature {
        None => (vec![0.0; n], Some(Status::NoTemperature)),
        Some(tv) => {
            let lo = tv.iter().cloned().fold(f64::INFINITY, f64::min);
            let hi = tv.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            let m = mean_of(tv);
            let d: Vec<f64> = tv.iter().map(|v| v - m).collect();
            if hi - lo < opt.min_temp_range {
                (d, Some(Status::ConstantTemperature))
            } else {
                (d, None)
            }
        }
    };
    let (th, time_status) = match &inp.t {
        None => (vec![0.0; n], Some(Status::NoTime)),
        Some(tv) => {
            let m = mean_of(tv);
            (tv.iter().map(|v| (v - m) / 3600.0).collect(), None)
        }
    };
    let mut step = vec![[0.0; 3]; n];
    for k in 1..n {
        for i in 0..3 {
            step[k][i] = inp.mean[k - 1][i] - inp.mean[k][i];
        }
    }
    let mut s = Session {
        n,
        am: inp.mean.clone(),
        dt,
        th,
        step,
        c: [start[0] * inp.g, start[1] * inp.g, start[2] * inp.g],
        sig: vec![1.0; n],
        c_g: inp.g,
    };
    // Noise propagated at the start values.
    for k in 0..n {
        let ev = row_eval(&s, &start, &[], k).ok_or_else(|| {
            CoreError::Degenerate("the start calibration maps a dwell to zero".into())
        })?;
        s.sig[k] = match &inp.sigma_mean {
            Some(sm) => (0..3)
                .map(|i| (ev.v[i] * sm[k][i]).powi(2))
                .sum::<f64>()
                .sqrt(),
            None => 1.0,
        };
    }
    let rows: Vec<usize> = (0..n).collect();
    let mut base = fit(&s, &rows, &[], &start)?;
    let dof = n - N_BASE;
    let noise_known = inp.sigma_mean.is_some();
    if !noise_known {
        let sc = (base.rss / dof as f64).sqrt().max(1e-300);
        for v in s.sig.iter_mut() {
            *v = sc;
        }
        base = fit(&s, &rows, &[], &base.p)?;
    }
    let b0 = basis(&base.jac)?;
    let leverage: Vec<f64> = (0..n).map(|k| b0.q.row(k).norm_squared()).collect();
    let base_std: Vec<f64> = (0..N_BASE).map(|i| b0.cov[(i, i)].sqrt()).collect();
    let chi2 = base.rss;
    let p_chi2 = if noise_known {
        chi2_sf(chi2, dof as f64)
    } else {
        f64::NAN
    };
    let resid: Vec<f64> = (0..n).map(|k| base.e[k] * s.sig[k]).collect();
    let e0 = base.e.clone();
    let base_p = base.p.clone();

    // Candidates: availability first.
    let mut cands = vec![];
    let mut unavailable = vec![];
    for &c in &opt.effects {
        let st = if c.uses_temperature() {
            temp_status
        } else if c == Effect::Drift {
            time_status
        } else {
            None
        };
        match st {
            Some(st) => unavailable.push((c, st)),
            None => cands.push(c),
        }
    }
    let cfg = TestCfg {
        mode: if noise_known { opt.test } else { TestMode::F },
        trust_level: opt.trust_level,
        sine_tol: opt.sine_tol,
    };
    let sw = stepwise(&s, &rows, base, &cands, opt, cfg, true)?;

    // Candidate reports and BIC weights (sigma-free form).
    let nf = n as f64;
    let rank0 = sw.basis0.as_ref().map_or(N_BASE, |b| b.rank) as f64;
    let bic_of = |rss: f64, k: f64| nf * (rss.max(1e-300) / nf).ln() + k * nf.ln();
    let bic_none = bic_of(chi2, rank0);
    let mut reports = vec![];
    for &c in &opt.effects {
        if let Some(&(_, st)) = unavailable.iter().find(|(e, _)| *e == c) {
            reports.push(CandidateReport {
                effect: c,
                status: st,
                sines: vec![],
                d: 0,
                score: f64::NAN,
                f: f64::NAN,
                p_f: f64::NAN,
                p_chi2: f64::NAN,
                p: f64::NAN,
                chi2_used: false,
                bic: f64::NAN,
                weight: f64::NAN,
                estimate: [f64::NAN; 3],
                std: [f64::NAN; 3],
                w: DMatrix::zeros(n, 0),
            });
            continue;
        }
        if let Some((_, sc)) = sw.first.iter().find(|(e, _)| *e == c) {
            let bic = if sc.status == Status::Testable {
                bic_of(chi2 - sc.score, rank0 + sc.d as f64)
            } else {
                f64::NAN
            };
            reports.push(CandidateReport {
                effect: c,
                status: sc.status,
                sines: sc.sines.clone(),
                d: sc.d,
                score: sc.score,
                f: sc.f,
                p_f: sc.p_f,
                p_chi2: sc.p_chi2,
                p: sc.p,
                chi2_used: sc.chi2_used,
                bic,
                weight: f64::NAN,
                estimate: sc.est,
                std: sc.std,
                w: sc.w.clone(),
            });
        }
    }
    let bmin = reports
        .iter()
        .filter(|r| r.bic.is_finite())
        .map(|r| r.bic)
        .fold(bic_none, f64::min);
    let mut wsum = (-(bic_none - bmin) / 2.0).exp();
    for r in &reports {
        if r.bic.is_finite() {
            wsum += (-(r.bic - bmin) / 2.0).exp();
        }
    }
    let weight_none = (-(bic_none - bmin) / 2.0).exp() / wsum;
    for r in reports.iter_mut() {
        if r.bic.is_finite() {
            r.weight = (-(r.bic - bmin) / 2.0).exp() / wsum;
        }
    }

    // Leave-one-dwell-out held-out gap, selection redone in every fold; the held-out z of
    // each fold is kept after 0, 1, ... selected effects so that every in-sample step can be
    // checked against the held-out gap of "select at most k effects".
    let k_full = sw.effects.len();
    // Folds select at most k_full effects (only g_steps[0..=k_full] is used).
    let fold_opt = GapOptions {
        max_effects: k_full,
        ..opt.clone()
    };
    let loo_raw = if opt.loo && n > N_BASE + 1 {
        use rayon::prelude::*;
        let one_fold = |j: usize| -> Result<FoldOut> {
            let fr: Vec<usize> = (0..n).filter(|&k| k != j).collect();
            let bfit = fit(&s, &fr, &[], &base_p)?;
            let swf = stepwise(&s, &fr, bfit, &cands, &fold_opt, cfg, false)?;
            let mut zs = Vec::with_capacity(swf.history.len());
            for (k, h) in swf.history.iter().enumerate() {
                let bb = basis(&h.jac)?;
                let (z, q, r) = predict(&s, &h.p, &swf.effects[..k], &bb.cov, j);
                zs.push((z / (1.0 + q).sqrt(), r));
            }
            Ok((zs, swf.effects))
        };
        let folds: Vec<Result<FoldOut>> = (0..n).into_par_iter().map(one_fold).collect();
        // z[k][j], r[k][j] for k = 0..=k_full.
        let mut zk = vec![vec![f64::NAN; n]; k_full + 1];
        let mut rk = vec![vec![f64::NAN; n]; k_full + 1];
        let mut counts = [0usize; 6];
        let mut failed = 0usize;
        for (j, f) in folds.into_iter().enumerate() {
            match f {
                Ok((zs, effs)) if !zs.is_empty() && zs.iter().all(|x| x.0.is_finite()) => {
                    for k in 0..=k_full {
                        let (z, r) = zs[k.min(zs.len() - 1)];
                        zk[k][j] = z;
                        rk[k][j] = r;
                    }
                    for e in &effs {
                        if let Some(ix) = Effect::ALL.iter().position(|x| x == e) {
                            counts[ix] += 1;
                        }
                    }
                }
                _ => failed += 1,
            }
        }
        Some((zk, rk, counts, failed))
    } else {
        None
    };
    let rms = |v: &[f64]| {
        let ok: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
        if ok.is_empty() {
            f64::NAN
        } else {
            (ok.iter().map(|x| x * x).sum::<f64>() / ok.len() as f64).sqrt()
        }
    };
    let g_steps: Vec<f64> = loo_raw
        .as_ref()
        .map_or(vec![], |(zk, _, _, _)| zk.iter().map(|z| rms(z)).collect());

    // Held-out gate: an effect that does not lower the held-out gap is not an explanation.
    let mut k_acc = k_full;
    let mut not_confirmed = None;
    // A fold must keep at least 2 residual degrees of freedom after the selected model for
    // its held-out prediction to judge the effect; otherwise the gate is skipped.
    let gate_skipped = opt.gate != Gate::Off
        && k_full > 0
        && g_steps.len() == k_full + 1
        && (n - 1).saturating_sub(basis(&sw.history[k_full].jac)?.rank) < 2;
    if opt.gate != Gate::Off && g_steps.len() == k_full + 1 && !gate_skipped {
        for k in 1..=k_full {
            // Adequate: the remainder is consistent with the noise model both in-sample
            // (chi2 p >= alpha) and held out (G^2 within 2 standard deviations of 1).
            let adequate = opt.gate == Gate::Auto && noise_known && {
                let h = &sw.history[k];
                let rk = basis(&h.jac)?.rank;
                n > rk
                    && chi2_sf(h.rss, (n - rk) as f64) >= opt.alpha
                    && (g_steps[k].powi(2) <= 1.0 + 3.0 * (2.0 / n as f64).sqrt()
                        || g_steps[k].powi(2)
                            <= g_steps[k - 1].powi(2) + opt.gate_margin * (2.0 / n as f64).sqrt())
            };
            if !(g_steps[k] < g_steps[k - 1]) && !adequate {
                k_acc = k - 1;
                not_confirmed = Some((
                    sw.effects[k - 1],
                    sw.step_p[k - 1],
                    g_steps[k - 1],
                    g_steps[k],
                ));
                break;
            }
        }
    }
    let selected: Vec<Effect> = sw.effects[..k_acc].to_vec();
    let step_p: Vec<f64> = sw.step_p[..k_acc].to_vec();
    let step_p_adj: Vec<f64> = sw.step_p_adj[..k_acc].to_vec();
    let step_m: Vec<usize> = sw.step_m[..k_acc].to_vec();
    let loo = loo_raw.map(|(zk, rk, counts, failed)| LooReport {
        g_before: g_steps[0],
        g_after: g_steps[k_acc],
        rms_before: rms(&rk[0]),
        rms_after: rms(&rk[k_acc]),
        z_before: zk[0].clone(),
        z_after: zk[k_acc].clone(),
        g_steps: g_steps.clone(),
        fold_counts: counts,
        n_failed: failed,
    });

    // Final model: parameters, errors, residuals.
    let fin = &sw.history[k_acc];
    let bf = basis(&fin.jac)?;
    let dof_after = n.saturating_sub(bf.rank);
    let s2 = if dof_after > 0 {
        (fin.rss / dof_after as f64).max(1.0)
    } else {
        1.0
    };
    let std_after: Vec<f64> = (0..fin.p.len())
        .map(|i| (bf.cov[(i, i)] * s2).sqrt())
        .collect();
    for (j, &eff) in selected.iter().enumerate() {
        if let Some(r) = reports.iter_mut().find(|r| r.effect == eff) {
            for i in 0..3 {
                r.estimate[i] = fin.p[N_BASE + 3 * j + i];
                r.std[i] = std_after[N_BASE + 3 * j + i];
            }
        }
    }
    let resid_after: Vec<f64> = (0..n).map(|k| fin.e[k] * s.sig[k]).collect();
    let chi2_after = fin.rss;
    let p_after = if noise_known && dof_after > 0 {
        chi2_sf(chi2_after, dof_after as f64)
    } else {
        f64::NAN
    };

    // Ambiguity: the best candidate against others with similar evidence and aliased columns.
    let mut ambiguous = vec![];
    if let Some(&best) = selected.first() {
        if let Some(rb) = reports.iter().find(|r| r.effect == best) {
            for r in &reports {
                if r.effect == best || r.status != Status::Testable || rb.w.ncols() == 0 {
                    continue;
                }
                let cos = (rb.w.transpose() * &r.w)
                    .singular_values()
                    .iter()
                    .cloned()
                    .fold(0.0, f64::max);
                if cos > opt.ambiguity_cos && r.weight > 0.05 * rb.weight {
                    ambiguous.push((best, r.effect, cos));
                }
            }
        }
    }

    Ok(GapResult {
        n,
        base_params: base_p,
        base_std,
        sigma_r: s.sig.clone(),
        resid,
        e: e0,
        leverage,
        chi2,
        dof,
        p_chi2,
        noise_known,
        candidates: reports,
        bic_none,
        weight_none,
        selected,
        step_p,
        step_p_adj,
        step_m,
        not_confirmed,
        stop_p: sw.stop_p,
        stop_p_adj: sw.stop_p_adj,
        params_after: fin.p.clone(),
        std_after,
        resid_after,
        e_after: fin.e.clone(),
        chi2_after,
        dof_after,
        p_after,
        ambiguous,
        loo,
        gate_skipped,
    })
}

/// Norm residuals `|K^-1 (am - b - terms)| - g` (m/s^2) of dwell means under given parameters
/// and effects, with the same `c` scaling as [`diagnose`] (`c_i = s_i g` from `params`).
pub fn model_residuals(
    mean: &[[f64; 3]],
    t: Option<&[f64]>,
    temperature: Option<&[f64]>,
    g: f64,
    params: &[f64],
    effects: &[Effect],
) -> Result<Vec<f64>> {
    let n = mean.len();
    if params.len() != N_BASE + 3 * effects.len() {
        return invalid("params must hold 9 calibration values plus 3 per effect");
    }
    let mean_of = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let dt = temperature.map_or(vec![0.0; n], |tv| {
        let m = mean_of(tv);
        tv.iter().map(|v| v - m).collect()
    });
    let th = t.map_or(vec![0.0; n], |tv| {
        let m = mean_of(tv);
        tv.iter().map(|v| (v - m) / 3600.0).collect()
    });
    let mut step = vec![[0.0; 3]; n];
    for k in 1..n {
        for i in 0..3 {
            step[k][i] = mean[k - 1][i] - mean[k][i];
        }
    }
    let s = Session {
        n,
        am: mean.to_vec(),
        dt,
        th,
        step,
        c: [params[0] * g, params[1] * g, params[2] * g],
        sig: vec![1.0; n],
        c_g: g,
    };
    (0..s.n)
        .map(|k| {
            row_eval(&s, params, effects, k)
                .map(|e| e.r)
                .ok_or_else(|| CoreError::Degenerate("model not evaluable".into()))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    struct Rng(u64);
    impl Rng {
        fn uniform(&mut self) -> f64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 11) as f64 / (1u64 << 53) as f64
        }
        fn normal(&mut self) -> f64 {
            let (u, v) = (self.uniform().max(1e-300), self.uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        }
    }

    fn session(seed: u64, drift_ug_h: f64, sigma: f64) -> GapInput {
        let mut rng = Rng(seed);
        let g = 9.81;
        let n = 24;
        let k = [[1.02, 0.0, 0.0], [0.002, 0.98, 0.0], [-0.001, 0.003, 1.01]];
        let b = [0.05, -0.03, 0.02];
        let mut mean = vec![];
        let mut t = vec![];
        let mut temp = vec![];
        for i in 0..n {
            let (mut x, mut y, mut z) = (rng.normal(), rng.normal(), rng.normal());
            let r = (x * x + y * y + z * z).sqrt();
            x *= g / r;
            y *= g / r;
            z *= g / r;
            let ti = 90.0 * i as f64;
            let th = (ti - 90.0 * 11.5) / 3600.0;
            let mut m = [0.0; 3];
            let a = [x, y, z];
            for r in 0..3 {
                m[r] = (0..3).map(|c| k[r][c] * a[c]).sum::<f64>()
                    + b[r]
                    + drift_ug_h * 1e-6 * k[r][r] * g * th
                    + sigma * rng.normal();
            }
            mean.push(m);
            t.push(ti);
            temp.push(20.0 + 5.0 * (i as f64 / n as f64 * 3.1).sin());
        }
        GapInput {
            mean,
            sigma_mean: Some(vec![[sigma; 3]; n]),
            t: Some(t),
            temperature: Some(temp),
            g,
        }
    }

    #[test]
    fn p_values_match_tables() {
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-10);
        assert!((chi2_sf(18.307_038_053_275_146, 10.0) - 0.05).abs() < 1e-10);
        assert!((f_sf(3.708_264_819_046_843_5, 3.0, 10.0) - 0.05).abs() < 1e-9);
        assert!((f_sf(1.0, 5.0, 5.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn quadric_start_is_exact_on_noise_free_data() {
        let inp = session(7, 0.0, 0.0);
        let p = quadric_start(&inp.mean, inp.g).unwrap();
        let want = [1.02, 0.98, 1.01, 0.05, -0.03, 0.02, 0.002, -0.001, 0.003];
        for i in 0..9 {
            assert!(
                (p[i] - want[i]).abs() < 1e-9,
                "{i}: {} vs {}",
                p[i],
                want[i]
            );
        }
    }

    #[test]
    fn null_session_is_adequate_and_drift_is_found() {
        let inp = session(11, 0.0, 1e-4);
        let r = diagnose(&inp, &GapOptions::default()).unwrap();
        assert!(r.selected.is_empty(), "{:?}", r.selected);
        let loo = r.loo.unwrap();
        assert!(loo.g_before > 0.6 && loo.g_before < 1.5, "{}", loo.g_before);
        // 1 mg/h-scale drift, far above 1e-4 m/s^2 noise over 36 min.
        let inp = session(11, 2000.0, 1e-4);
        let r = diagnose(&inp, &GapOptions::default()).unwrap();
        assert_eq!(r.selected.first(), Some(&Effect::Drift));
        let loo = r.loo.unwrap();
        assert!(
            loo.g_before > 3.0 && loo.g_after < 1.5,
            "{} {}",
            loo.g_before,
            loo.g_after
        );
        let d = r
            .candidates
            .iter()
            .find(|c| c.effect == Effect::Drift)
            .unwrap();
        for i in 0..3 {
            assert!(
                (d.estimate[i] - 2000.0).abs() < 5.0 * d.std[i] + 50.0,
                "{:?}",
                d.estimate
            );
        }
    }

    #[test]
    fn min_p_matches_closed_forms() {
        // n = 40, Q = first 5 unit vectors; members are further unit vectors (orthogonal to Q).
        let n = 40;
        let q = DMatrix::from_fn(n, 5, |a, b| if a == b { 1.0 } else { 0.0 });
        let unit = |k: usize| DMatrix::from_fn(n, 1, |a, _| if a == k { 1.0 } else { 0.0 });
        let p_obs: f64 = 0.02;
        let crit = isf(p_obs, true, 1.0, 1.0);
        assert!((chi2_sf(crit, 1.0) - p_obs).abs() < 1e-9);
        let mk = |w: DMatrix<f64>, p: f64| Member {
            w,
            chi2: true,
            dof2: 30.0,
            p,
            stat: isf(p, true, 1.0, 1.0),
        };
        // Two identical members: min-p = the single-test p-value (no multiplicity).
        let same = [mk(unit(7), p_obs), mk(unit(7), 0.3)];
        let pa = min_p(&q, &same, p_obs, 0.05, 4000);
        assert!((pa - p_obs).abs() < 0.008, "{pa}");
        // Four independent members: 1 - (1 - p)^4 = 0.0776 (Bonferroni 0.08).
        let ind = [
            mk(unit(7), p_obs),
            mk(unit(8), 0.5),
            mk(unit(9), 0.5),
            mk(unit(10), 0.5),
        ];
        let pa = min_p(&q, &ind, p_obs, 0.05, 4000);
        let want = 1.0 - (1.0 - p_obs).powi(4);
        assert!((pa - want).abs() < 0.015, "{pa} vs {want}");
        assert!(pa <= 4.0 * p_obs + 1e-12);
        // Deterministic.
        assert_eq!(pa, min_p(&q, &ind, p_obs, 0.05, 4000));
    }

    #[test]
    fn bad_inputs_are_clear_errors() {
        let mut inp = session(3, 0.0, 1e-4);
        inp.mean.truncate(9);
        inp.sigma_mean = None;
        inp.t = None;
        inp.temperature = None;
        assert!(matches!(
            diagnose(&inp, &GapOptions::default()),
            Err(CoreError::Degenerate(_))
        ));
        let mut inp = session(3, 0.0, 1e-4);
        inp.temperature = None;
        let r = diagnose(&inp, &GapOptions::default()).unwrap();
        let tb = r
            .candidates
            .iter()
            .find(|c| c.effect == Effect::TemperatureBias)
            .unwrap();
        assert_eq!(tb.status, Status::NoTemperature);
    }
}

//! Static field calibration by norm observation.
//!
//! Sensor model: raw output `am = K a + b`, calibrated specific force `a = K^-1 (am - b)`.
//! At rest `|a| = g` whatever the attitude, so dwell means at several attitudes and a
//! reference `g` determine `K` and `b`. Parameter vector, always in the paper's order:
//! `[sx, sy, sz, bx, by, bz, m1, m2, m3]` (model [`Model::Diag`] keeps the first 6). `K` is in
//! output units per (m/s^2) (raw counts per m/s^2 for raw data), `b` in output units.
//!
//! - [`Model::Lower`] (the norm-observation paper's): `K = [[sx,0,0],[m1,sy,0],[m2,m3,sz]]`.
//! - [`Model::Upper`] (imu_tk's triangle): `K = [[sx,m1,m2],[0,sy,m3],[0,0,sz]]`.
//! - [`Model::Diag`]: `K = diag(sx, sy, sz)`.
//!
//! [`fit_static`] is a short orchestration of named stages, each in its own module and
//! unit-tested:
//!
//! 1. [`start::start_stage`]: the exact linear solution of the quadric regression (or the
//!    paper's biased back-substitution, or the caller's start; a bias + scale fallback when
//!    the linear solution fails, so that the design can still be diagnosed);
//! 2. the frame change ([`frame::Frame`]): fitting runs where `K ~ I` and `b ~ 0`;
//! 3. [`ml_stage`]: Levenberg-Marquardt (or Gauss-Newton) on the maximum-likelihood cost of
//!    [`cost`] (whitened norm residuals whose weights are re-evaluated inside the cost);
//! 4. [`runaway_guard`]: the norm cost can fall towards infinite scale factors when the
//!    dwells cover too little of the sphere; such fits are refused;
//! 5. [`observe::covariance_stage`]: covariance, observability summary and the convergence
//!    check (distance to the minimum of the local quadratic model, in parameter std).
//!
//! [`batch::fit_batch`] runs the same stages over many sessions without allocating per fit.

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod batch;
pub mod cost;
pub mod frame;
pub mod observe;
pub mod start;

pub use batch::{fit_batch, fit_batch_sigma_g, BatchRow, BatchStatus};
pub use cost::{eval_dwell, inv_k, jac_row, ml_row, DwellEval, DwellNoise, NormProblem};
pub use observe::{
    describe_combination, design_rows, obs_report, predict, ObsSummary, Observability, Prediction,
};
pub use start::{Start, StartSource};

use crate::dwell::Sample;
use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lsq::{inverse3, solve_normal_fixed, NlsOptions, NormalEquationsFixed};
use frame::Frame;
use nalgebra::{DMatrix, Matrix3, Vector3};
use ndarray::ArrayView2;
use observe::{comparable_jacobian, covariance_stage, degenerate_message, CovStage};
use rayon::prelude::*;

/// Names of the parameters in vector order.
pub const PARAM_NAMES: [&str; 9] = ["sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3"];

/// Default predicted std (comparable units) above which a combination counts as undetermined:
/// a combination known to no better than 300 % (of the scale, or of g for a bias) is not
/// determined. Below it a large predicted std is reported as a weak design, with the fit
/// (the +-30 deg field design at sigma 1e-2 has its ML minimum returned where one exists, with
/// a weakest std of 0.23-1.8). An exactly singular pose set fitted to noisy means (the
/// two-plane field procedure) gets 0.4 to several hundred along its null combination, so the
/// warning of a fit returned with a weakest std above 0.3 (Python's `StaticFit.warning_text`)
/// says the data cannot tell its design from one that does not see that combination at all.
pub const DEGENERATE_STD: f64 = 3.0;
/// Default predicted std (comparable units) above which a parameter counts as weakly determined.
pub const WEAK_STD: f64 = 1e-3;
/// Scale factors above this multiple of the data's spread scale (median distance of the
/// dwell means from their centroid, over g) count as a runaway fit.
pub const RUNAWAY: f64 = 100.0;
/// A dwell whose norm residual exceeds this fraction of g may not be at rest (the Python
/// status getter's bit 2, the batch's message).
pub const OFF_NORM_FRACTION: f64 = 0.05;

/// The shape of a calibration `p` (output units): how far apart its scale factors are (the
/// largest `|K_ii|` over the smallest: infinite when one is 0) and whether some bias lies
/// beyond one g of its axis's response (`|b_i| > |K_ii| g`).
pub fn triad_shape(p: &[f64; 9], g: f64) -> (f64, bool) {
    let s = [p[0].abs(), p[1].abs(), p[2].abs()];
    let (lo, hi) = (s[0].min(s[1]).min(s[2]), s[0].max(s[1]).max(s[2]));
    (hi / lo, (0..3).any(|i| p[3 + i].abs() > s[i] * g))
}
/// Relative singular value below which the design is exactly singular.
pub const SINGULAR_RTOL: f64 = 1e-9;
/// A fit has converged when the minimum of the local quadratic model of the cost is within
/// `sqrt(CONVERGED_DECREMENT)` parameter standard deviations (1e-3 std).
pub const CONVERGED_DECREMENT: f64 = 1e-6;

/// Earth's gravity, m/s^2: 9.780 at the equator and 9.832 at the poles at sea level, about
/// 9.75 at 10 km; a reference outside these bounds (in m/s^2, in units of the standard 9.80665,
/// or in cm/s^2) cannot be local gravity, and would bias every scale factor.
pub const G_BOUNDS: [f64; 2] = [9.74, 9.85];
/// The standard gravity, m/s^2 (the unit "g").
pub const G_STANDARD: f64 = 9.80665;

/// Why `g` cannot be a local gravity in m/s^2, in units of g or in cm/s^2 (None when it can).
pub fn implausible_g(g: f64) -> Option<String> {
    let [lo, hi] = G_BOUNDS;
    let within = |scale: f64| (lo * scale..=hi * scale).contains(&g);
    if within(1.0) || within(1.0 / G_STANDARD) || within(100.0) || within(1000.0 / G_STANDARD) {
        return None;
    }
    // Shortest round trip, in exponent form far from 1 (1e-300 was 300 digits long).
    let shown = if (1e-4..1e9).contains(&g.abs()) {
        format!("{g}")
    } else {
        format!("{g:e}")
    };
    Some(format!(
        "g = {shown} is not a plausible local gravity: Earth's is 9.78-9.83 m/s^2 at sea level \
         ({lo}-{hi} allowed: {:.4}-{:.4} in units of g, {}-{} cm/s^2, {:.1}-{:.1} mg)",
        lo / G_STANDARD,
        hi / G_STANDARD,
        lo * 100.0,
        hi * 100.0,
        1000.0 * lo / G_STANDARD,
        1000.0 * hi / G_STANDARD
    ))
}

/// Which triangle of `K` carries the misalignment terms.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    /// The paper's: `K` lower triangular (9 parameters).
    Lower,
    /// Bias and scale only (6 parameters).
    Diag,
    /// imu_tk's convention: `K` upper triangular (9 parameters).
    Upper,
}

impl Model {
    /// Parse `"lower" | "diag" | "upper"`.
    pub fn parse(s: &str) -> Result<Model> {
        match s {
            "lower" => Ok(Model::Lower),
            "diag" => Ok(Model::Diag),
            "upper" => Ok(Model::Upper),
            _ => invalid(format!(
                "unknown model {s:?}; use \"lower\" (9 parameters, the paper's triangle), \"diag\" (6: bias + scale) or \"upper\" (9, imu_tk's triangle)"
            )),
        }
    }

    /// Name as accepted by [`Model::parse`].
    pub fn name(self) -> &'static str {
        match self {
            Model::Lower => "lower",
            Model::Diag => "diag",
            Model::Upper => "upper",
        }
    }

    /// Number of parameters.
    pub fn n_params(self) -> usize {
        match self {
            Model::Diag => 6,
            _ => 9,
        }
    }

    /// The entries `(row, column)` of `K` that hold `m1, m2, m3` (none for [`Model::Diag`]).
    #[inline(always)]
    pub fn misalignment_entries(self) -> Option<[(usize, usize); 3]> {
        match self {
            Model::Lower => Some([(1, 0), (2, 0), (2, 1)]),
            Model::Upper => Some([(0, 1), (0, 2), (1, 2)]),
            Model::Diag => None,
        }
    }

    /// `K` from a parameter vector (the entries of [`Model::misalignment_entries`], written
    /// out: this runs once per evaluation of the cost).
    #[inline]
    pub fn k_matrix(self, p: &[f64]) -> Matrix3<f64> {
        let (sx, sy, sz) = (p[0], p[1], p[2]);
        match self {
            Model::Lower => Matrix3::new(sx, 0.0, 0.0, p[6], sy, 0.0, p[7], p[8], sz),
            Model::Upper => Matrix3::new(sx, p[6], p[7], 0.0, sy, p[8], 0.0, 0.0, sz),
            Model::Diag => Matrix3::new(sx, 0.0, 0.0, 0.0, sy, 0.0, 0.0, 0.0, sz),
        }
    }

    /// Parameter vector from `K` (the entries outside the model's pattern are ignored) and
    /// `b`; unused slots (6..9 for [`Model::Diag`]) are zero.
    pub fn params_from(self, k: &Matrix3<f64>, b: &Vector3<f64>) -> [f64; 9] {
        let mut p = [
            k[(0, 0)],
            k[(1, 1)],
            k[(2, 2)],
            b[0],
            b[1],
            b[2],
            0.0,
            0.0,
            0.0,
        ];
        for (slot, (i, j)) in self
            .misalignment_entries()
            .into_iter()
            .flatten()
            .enumerate()
        {
            p[6 + slot] = k[(i, j)];
        }
        p
    }

    /// `K` entries outside the model's pattern that are not zero (row, column), if any.
    pub fn violations(self, k: &[[f64; 3]; 3]) -> Option<(usize, usize)> {
        (0..3)
            .flat_map(|i| (0..3).map(move |j| (i, j)))
            .find(|&(i, j)| {
                let allowed = i == j
                    || match self {
                        Model::Lower => i > j,
                        Model::Upper => i < j,
                        Model::Diag => false,
                    };
                !allowed && k[i][j] != 0.0
            })
    }
}

/// Estimation method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// The paper's regression and small-M back-substitution (biased ~1e-4; for reproduction).
    LinearPaper,
    /// Exact recovery from the quadric regression (no small-M assumption).
    Quadric,
    /// Undamped Gauss-Newton on the whitened norm residual.
    GaussNewton,
    /// Levenberg-Marquardt on the whitened norm residual (maximum likelihood).
    Lm,
}

impl Method {
    /// Parse `"linear-paper" | "quadric" | "gauss-newton" | "lm"`.
    pub fn parse(s: &str) -> Result<Method> {
        match s {
            "linear-paper" => Ok(Method::LinearPaper),
            "quadric" => Ok(Method::Quadric),
            "gauss-newton" | "gn" => Ok(Method::GaussNewton),
            "lm" => Ok(Method::Lm),
            _ => invalid(format!(
                "unknown method {s:?}; use \"lm\", \"gauss-newton\", \"quadric\" or \"linear-paper\""
            )),
        }
    }
}

/// What is known about the noise of the dwell means (output units squared).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Noise<'a> {
    /// Nothing: isotropic output noise of unknown level, estimated from the residuals.
    Estimated,
    /// The same per-axis variance of every dwell mean.
    Uniform([f64; 3]),
    /// Per-axis variance of each dwell mean (`k` rows).
    Known(&'a [[f64; 3]]),
}

impl Noise<'_> {
    /// The noise level is known.
    pub fn known(&self) -> bool {
        !matches!(self, Noise::Estimated)
    }

    /// The noise in a frame of scale `s` (variances divided by `s^2`).
    fn in_frame(&self, s: f64) -> DwellNoise<'_> {
        let is2 = 1.0 / (s * s);
        match *self {
            Noise::Estimated => DwellNoise::Isotropic,
            Noise::Uniform(v) => DwellNoise::Uniform([v[0] * is2, v[1] * is2, v[2] * is2]),
            Noise::Known(var) => DwellNoise::PerDwell { var, scale: is2 },
        }
    }
}

/// Fit settings.
#[derive(Debug, Clone, PartialEq)]
pub struct FitSettings {
    /// Sensor model.
    pub model: Model,
    /// Estimation method.
    pub method: Method,
    /// Start for GN/LM in the parameter order (default: the quadric solution).
    pub start: Option<Vec<f64>>,
    /// Iteration limit of GN/LM.
    pub max_iter: usize,
    /// Return [`CoreError::Degenerate`] when the dwells cannot determine the parameters.
    pub raise_degenerate: bool,
    /// Predicted std (comparable units) above which a combination is undetermined.
    pub degenerate_std: f64,
    /// Predicted std (comparable units) above which a parameter is weakly determined.
    pub weak_std: f64,
}

impl FitSettings {
    /// Defaults for a model and method.
    pub fn new(model: Model, method: Method) -> Self {
        FitSettings {
            model,
            method,
            start: None,
            max_iter: 200,
            raise_degenerate: true,
            degenerate_std: DEGENERATE_STD,
            weak_std: WEAK_STD,
        }
    }

    /// Check the numeric settings (names, values and valid ranges in the message).
    pub fn validate(&self) -> Result<()> {
        if self.max_iter == 0 || self.max_iter > 100_000 {
            return invalid(format!(
                "max_iter must be an integer in [1, 100000]; got {}",
                self.max_iter
            ));
        }
        for (name, v) in [
            ("degenerate_std", self.degenerate_std),
            ("weak_std", self.weak_std),
        ] {
            if !(v > 0.0) || !v.is_finite() {
                return invalid(format!(
                    "{name} must be a positive, finite predicted std (relative units); got {v}"
                ));
            }
        }
        Ok(())
    }
}

/// Result of one static fit (parameters in the caller's units).
#[derive(Debug, Clone)]
pub struct StaticFit {
    /// Sensor model.
    pub model: Model,
    /// Estimation method.
    pub method: Method,
    /// Parameters `[sx, sy, sz, bx, by, bz, m1, m2, m3]` (first 6 for diag).
    pub params: Vec<f64>,
    /// Start used by GN/LM (or the method's own solution).
    pub start: Vec<f64>,
    /// Where the start came from.
    pub start_source: StartSource,
    /// Why the linear solution failed, when the start is the bias + scale fallback.
    pub start_error: Option<String>,
    /// `(J^T W J)^-1` (`p x p`, output units) with the noise model's weights. With the noise
    /// estimated this is the covariance per unit of output noise variance: multiply by
    /// `chi2_dof`. NaN when singular.
    pub covariance: DMatrix<f64>,
    /// `|a_k| - g` per dwell (units of g).
    pub residuals: Vec<f64>,
    /// Predicted std of each residual `sqrt(w_k^T Sigma_k w_k)` (units of g); with the noise
    /// estimated, `Sigma_k = chi2_dof I`.
    pub sigma_r: Vec<f64>,
    /// Minimised cost `sum e_k^2`: dimensionless for a known noise model, output units
    /// squared when the noise is estimated (`Sigma_k = I`).
    pub cost: f64,
    /// Degrees of freedom `k - p`.
    pub dof: usize,
    /// `cost / dof` (NaN when `dof == 0`): the chi-square per degree of freedom of a known
    /// noise model, or the estimated per-axis variance of a dwell mean (output units squared).
    pub chi2_dof: f64,
    /// Iterations of GN/LM (0 for the linear methods).
    pub iterations: usize,
    /// The minimum was reached: the minimum of the local quadratic model is within 1e-3
    /// parameter std (true for the linear methods, which do not iterate).
    pub converged: bool,
    /// Squared distance (in parameter std) to the minimum of the local quadratic model.
    pub decrement: f64,
    /// The noise model was known (true) or estimated from the residuals (false).
    pub noise_known: bool,
    /// Quick observability summary (Cholesky covariance and power iteration).
    pub summary: ObsSummary,
    /// Fitting frame and frame parameters (for [`StaticFit::observability`]).
    frame: (Frame, [f64; 9]),
    /// Frame points (for [`StaticFit::observability`]).
    pts: Vec<[f64; 3]>,
    /// Covariance scale used to judge observability (1, or chi2/dof floored at (1e-7 g)^2,
    /// frame units).
    pub obs_scale: f64,
}

impl StaticFit {
    /// Full observability report (SVD of the comparable whitened Jacobian at the fitted
    /// parameters) with the given thresholds. `noise` must be the fit's.
    pub fn observability(
        &self,
        noise: &Noise<'_>,
        g: f64,
        set: &FitSettings,
    ) -> Result<Observability> {
        let np = self.params.len();
        let prob = NormProblem {
            pts: &self.pts,
            g,
            noise: noise.in_frame(self.frame.0.s),
            model: self.model,
            kmax: f64::INFINITY,
        };
        let jc = comparable_jacobian(&prob, &self.frame.1, np)?;
        obs_report(&jc, self.obs_scale, set)
    }
}

// ------------------------------------------------------------------------------------------
// Stages

/// One or two axes that read the same in every dwell (all three: identical dwells, said
/// later): a dead or disconnected channel.
#[cold]
fn dead_channel(means: &[[f64; 3]]) -> Result<()> {
    let m0 = means[0];
    let flat: [bool; 3] = std::array::from_fn(|a| means.iter().all(|m| m[a] == m0[a]));
    match flat.iter().position(|&f| f) {
        Some(a) if !flat.iter().all(|&f| f) => degenerate(format!(
            "the {} output reads {} in every one of the {} dwells: a dead or disconnected \
             channel (a static calibration needs each axis to see gravity change between poses)",
            ["x", "y", "z"][a],
            m0[a],
            means.len()
        )),
        _ => Ok(()),
    }
}

/// Check the dwell means, `g` and the noise model.
pub fn validate(means: &[[f64; 3]], g: f64, noise: &Noise<'_>, model: Model) -> Result<()> {
    if !(g > 0.0) || !g.is_finite() {
        return invalid(format!(
            "g must be a positive, finite reference gravity (e.g. 9.81 m/s^2); got {g}"
        ));
    }
    for (k, m) in means.iter().enumerate() {
        if let Some(v) = m.iter().find(|v| !v.is_finite()) {
            let what = if v.is_nan() { "a NaN" } else { "an infinite" };
            return invalid(format!("dwell {k} has {what} mean"));
        }
    }
    // The second dwell differs from the first on every axis in any real session: only then
    // is the scan for a channel that never changes skipped.
    if means.len() > 1 && (0..3).any(|a| means[1][a] == means[0][a]) {
        dead_channel(means)?;
    }
    let p = model.n_params();
    if means.len() < p {
        return degenerate(format!(
            "{} cannot determine the {p} parameters of model {:?}: need at least {p} dwells \
             (more to estimate the noise){}",
            crate::error::count_of(means.len(), "dwell"),
            model.name(),
            if p > 6 && means.len() >= 6 {
                "; model \"diag\" (bias + scale) needs 6"
            } else {
                ""
            }
        ));
    }
    match noise {
        Noise::Known(v) => {
            if v.len() != means.len() {
                return invalid(format!(
                    "noise has {} rows for {} dwells",
                    v.len(),
                    means.len()
                ));
            }
            for (k, r) in v.iter().enumerate() {
                if r.iter().any(|x| !(x.is_finite() && *x >= 0.0)) {
                    return invalid(format!(
                        "dwell {k}: variance must be finite and non-negative"
                    ));
                }
            }
        }
        Noise::Uniform(r) => {
            if r.iter().any(|x| !(x.is_finite() && *x >= 0.0)) {
                return invalid("the dwell-mean variance must be finite and non-negative");
            }
        }
        Noise::Estimated => {}
    }
    Ok(())
}

/// Outcome of the ML stage (frame units).
#[derive(Debug, Clone, Copy)]
pub struct MlOutcome {
    /// Final parameters.
    pub params: [f64; 9],
    /// Cost `sum e_k^2` at `params`.
    pub cost: f64,
    /// `J^T J` of the whitened residuals at `params` (first `N x N`).
    pub jtj: [[f64; 9]; 9],
    /// `J^T e` at `params`.
    pub jtr: [f64; 9],
    /// Iterations taken.
    pub iterations: usize,
    /// The solver met one of its tolerances.
    pub solver_converged: bool,
}

/// The ML stage: Levenberg-Marquardt (or undamped Gauss-Newton) from `p0` on the
/// maximum-likelihood cost `prob`, when `iterate`; otherwise `p0` unchanged. Either way the
/// outcome carries the cost and normal equations at the final point.
pub fn ml_stage<const N: usize>(
    prob: &NormProblem<'_>,
    p0: &[f64; 9],
    set: &FitSettings,
    iterate: bool,
    gauss_newton: bool,
    lambda0: f64,
) -> Result<MlOutcome> {
    let mut p = [0.0f64; N];
    p.copy_from_slice(&p0[..N]);
    let (params, cost, jtj, jtr, iterations, solver_converged) = if iterate {
        // Stop when the next step could lower the cost by less than 1e-9 of it (the cost is
        // then within 1e-9 of the minimum) and by less than 2.5e-7 of cost / dof (a decrement
        // below 5e-7 in the realistic std: inside CONVERGED_DECREMENT).
        let dof = prob.pts.len().saturating_sub(N).max(1) as f64;
        let opt = NlsOptions {
            max_iter: set.max_iter,
            gauss_newton,
            ftol: (2.5e-7 / dof).min(1e-9),
            xtol: 1e-10,
            gtol: 1e-9,
        };
        let r = solve_normal_fixed::<N, _>(prob, &p, &opt, lambda0)?;
        (r.params, r.cost, r.jtj, r.jtr, r.iterations, r.converged)
    } else {
        let (mut h, mut gr) = ([[0.0f64; N]; N], [0.0f64; N]);
        let c = NormalEquationsFixed::<N>::normal(prob, &p, &mut h, &mut gr)?;
        (p, c, h, gr, 0, true)
    };
    let mut out = MlOutcome {
        params: *p0,
        cost,
        jtj: [[0.0; 9]; 9],
        jtr: [0.0; 9],
        iterations,
        solver_converged,
    };
    out.params[..N].copy_from_slice(&params);
    out.jtr[..N].copy_from_slice(&jtr);
    for (dst, src) in out.jtj.iter_mut().zip(&jtj) {
        dst[..N].copy_from_slice(src);
    }
    Ok(out)
}

/// A second ML run, from the isotropic start centred on zero output (scale = the median
/// norm of the dwell means / g), when some axis barely moves over the dwells
/// ([`start::unexcited_axes`]) and the fit `current` looks collapsed (a bias beyond one g
/// of its axis's response, or scale factors more than 3 times apart): dwells in a small cap
/// of attitudes also lie on small ellipsoids centred near the data, and the quadric's start
/// can fall into one (scale factors collapsed tenfold or more, a bias the size of the
/// outputs, chi2/dof 45-156 with the noise known, in 20 of 100 sessions tilted within +-5
/// deg) while the unit-scale calibration explains the data as well or better. `None` when
/// the fit does not look collapsed, the dwells move on every axis or the second run fails.
fn small_cap_restart<const N: usize>(
    prob: &NormProblem<'_>,
    means: &[[f64; 3]],
    g: f64,
    set: &FitSettings,
    f1: Frame,
    gauss_newton: bool,
    current: &MlOutcome,
) -> Option<MlOutcome> {
    let (spread, bias_beyond) = triad_shape(&f1.unframe(&current.params), g);
    if !(bias_beyond || spread > 3.0) {
        return None;
    }
    start::unexcited_axes(means)?;
    let s = Frame::origin(means, g).s;
    if !(s.is_finite() && s > 0.0) {
        return None;
    }
    let p = f1.to_frame(&[s, s, s, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    ml_stage::<N>(prob, &p, set, true, gauss_newton, 1e-3).ok()
}

/// chi2 of 9 degrees of freedom at 0.999: two minima closer in cost than this (in units of
/// the noise, or of the better one's cost per degree of freedom when that is larger or the
/// noise is estimated) are both inside the data's confidence region.
const TWO_MINIMA_CHI2: f64 = 27.88;

/// The local quadratic model of the cost at the fit puts a point this many noise units of
/// chi2 away (10 standard deviations): [`two_minima`] calls it far.
const TWO_MINIMA_FAR: f64 = 100.0;

/// Two calibrations far apart (scale factors more than 1 % apart, and the fit's own
/// covariance putting `b` more than 10 standard deviations from `a`: [`TWO_MINIMA_FAR`])
/// whose costs the data cannot tell apart ([`TWO_MINIMA_CHI2`]; `b` need not be a converged
/// minimum: any point that close in cost lies in the confidence region): the local
/// covariance of the fit describes neither, so the calibration is undetermined. Two
/// calibrations a few percent apart that the fit's std already span are not refused, nor a
/// rival whose scale factors are more than 2 times apart (no triad).
fn two_minima<const N: usize>(
    a: &MlOutcome,
    b: &MlOutcome,
    n: usize,
    f1: Frame,
    noise_known: bool,
) -> Result<()> {
    let dof = n.saturating_sub(N).max(1) as f64;
    let lo = a.cost.min(b.cost);
    let unit = if noise_known {
        (lo / dof).max(1.0)
    } else {
        lo / dof
    };
    let (pa, pb) = (f1.unframe(&a.params), f1.unframe(&b.params));
    // |scale|: a mirror image (one scale factor negated) gives the same norms.
    let apart =
        (0..3).any(|i| (pa[i].abs() - pb[i].abs()).abs() > 0.01 * pa[i].abs().max(pb[i].abs()));
    let close = (a.cost - b.cost).abs() <= TWO_MINIMA_CHI2 * unit;
    // a.cost + d^T (J^T J) d: the cost the fit's quadratic model predicts at b.
    let d: [f64; N] = std::array::from_fn(|i| b.params[i] - a.params[i]);
    let predicted: f64 = (0..N)
        .map(|i| (0..N).map(|j| d[i] * a.jtj[i][j] * d[j]).sum::<f64>())
        .sum();
    let far = predicted > TWO_MINIMA_FAR * unit;
    // The rival must be a triad: scale factors within a factor 2 of each other (offset
    // outputs over +-30 deg also fit an ellipsoid centred at zero output with scale factors
    // 3 times apart; the fit, a few std from the truth, stands).
    let triad = triad_shape(&pb, 1.0).0 <= 2.0;
    if !(unit > 0.0 && unit.is_finite() && apart && close && far && triad) {
        return Ok(());
    }
    let show = |p: &[f64; 9]| {
        format!(
            "scale factors {:.4}, {:.4}, {:.4} with bias {:.4}, {:.4}, {:.4}",
            p[0], p[1], p[2], p[3], p[4], p[5]
        )
    };
    degenerate(format!(
        "two calibrations explain the {n} dwells about equally ({} and {}; their chi2 differ by \
         {:.1} noise units, under {TWO_MINIMA_CHI2}): the dwells cover too small a cap of \
         attitudes to tell a calibration from one whose ellipsoid is centred near the data; \
         add poses with gravity along each axis up and down (tilts of 30 deg or more)",
        show(&pa),
        show(&pb),
        (a.cost - b.cost).abs() / unit
    ))
}

/// The runaway guard: scale factors (frame `f1` parameters `p`) beyond [`RUNAWAY`] times the
/// data's spread scale (`f0.s`) mean the cost fell towards `K -> infinity` (every dwell mapped
/// onto one vector) instead of reaching a finite minimum.
pub fn runaway_guard(p: &[f64; 9], f0: Frame, f1: Frame, n: usize) -> Result<()> {
    if p[..3].iter().any(|v| !(v.abs() * f1.s <= RUNAWAY * f0.s)) {
        return Err(CoreError::NotConverged(format!(
            "the fit ran away towards infinite scale factors (the norm cost falls when every \
             dwell is mapped onto one vector): the {n} dwells span too small a part of the \
             sphere for their noise to have a finite best fit near the start. Use the default \
             start (exact quadric solution), larger tilts or more poses, or model \"diag\""
        )));
    }
    Ok(())
}

/// What [`solve`] computed (frame units), before packaging.
#[derive(Debug, Clone)]
pub struct Solved {
    /// The start stage's outcome (output units).
    pub start: Start,
    /// Centroid frame (the data's spread).
    pub f0: Frame,
    /// Fitting frame.
    pub f1: Frame,
    /// The ML stage's outcome.
    pub ml: MlOutcome,
    /// The covariance stage's outcome.
    pub cov: CovStage,
    /// The fit has converged (the linear methods: always).
    pub converged: bool,
}

/// Run the stages on `means`: validate, start, frame change (points into `pts`), ML,
/// runaway guard, covariance. A failure after a failed linear solution reports that failure.
pub fn solve<const N: usize>(
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    set: &FitSettings,
    pts: &mut Vec<[f64; 3]>,
) -> Result<Solved> {
    validate(means, g, noise, set.model)?;
    solve_valid::<N>(means, g, noise, set, pts).map_err(|e| match e {
        // An iteration that failed because no pose turned an axis towards gravity: say so
        // (a failed linear solution says so itself; a degenerate design names its own cause).
        CoreError::NotConverged(_) => start::unexcited_axes(means).unwrap_or(e),
        CoreError::InvalidInput(ref m) if m == crate::lsq::START_NOT_EVALUABLE => {
            start::unexcited_axes(means).unwrap_or(e)
        }
        // One pose: said as such before any combination it leaves undetermined (that
        // message's advice, a smaller model, cannot help there).
        // Not for outputs with offsets of several g (raw counts of a mid-scale ADC): their
        // spans are small against the norm whatever the attitudes (+-30 deg read "one pose").
        CoreError::Degenerate(_) if !start::offset_outputs(means, g) => {
            start::one_pose(means).unwrap_or(e)
        }
        e => e,
    })
}

/// [`solve`] on validated input.
fn solve_valid<const N: usize>(
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    set: &FitSettings,
    pts: &mut Vec<[f64; 3]>,
) -> Result<Solved> {
    let model = set.model;
    let f0 = Frame::centroid(means, g)?;
    let start = start_stage_checked(means, g, set, f0)?;
    let f1 = Frame::from_params(model, &start.params, f0);
    f1.points_into(means, pts);
    let prob = NormProblem {
        pts,
        g,
        noise: noise.in_frame(f1.s),
        model,
        kmax: 10.0 * RUNAWAY * f0.s / f1.s,
    };
    let p0 = f1.to_frame(&start.params);
    let failed = start.error.is_some();
    let iterate = matches!(set.method, Method::GaussNewton | Method::Lm) || failed;
    let gauss_newton = set.method == Method::GaussNewton && !failed;
    // A user start may be far off (the paper's e0): damp; the linear start is already close
    // to the optimum: start nearly undamped.
    let lambda0 = if start.source == StartSource::User {
        1e-3
    } else {
        1e-8
    };
    let keep = |e: CoreError| start.error.clone().unwrap_or(e);
    if failed {
        undetermined_by_design::<N>(&prob, means, g, noise, set, f0, f1)?;
    }
    let mut ml = ml_stage::<N>(&prob, &p0, set, iterate, gauss_newton, lambda0).map_err(keep)?;
    // The second run, when the fit looks collapsed onto a small cap of attitudes.
    let mut other = None;
    if iterate && !failed && start.source != StartSource::User {
        let n = means.len();
        other = small_cap_restart::<N>(&prob, means, g, set, f1, gauss_newton, &ml)
            .filter(|o| runaway_guard(&o.params, f0, f1, n).is_ok());
        // Never the mirror image (a negative scale factor: the same norms).
        if let Some(o) = other
            .filter(|o| o.cost < ml.cost && f1.unframe(&o.params)[..3].iter().all(|v| *v > 0.0))
        {
            other = Some(ml);
            ml = o;
        }
    }
    if iterate {
        runaway_guard(&ml.params, f0, f1, means.len()).map_err(keep)?;
    }
    let cov = covariance_stage::<N>(&ml, means.len(), g, noise.known(), set);
    // A design that cannot determine some combination says so itself (check_solved).
    if let Some(o) = other.filter(|_| set.raise_degenerate && !cov.summary.degenerate) {
        two_minima::<N>(&ml, &o, means.len(), f1, noise.known())?;
    }
    if set.raise_degenerate && cov.summary.weak && !cov.summary.degenerate {
        let p = f1.unframe(&ml.params);
        start::too_few_poses(means, model, &p, max_std(&cov.summary)).map_err(keep)?;
    }
    let converged = !iterate
        || cov.decrement <= CONVERGED_DECREMENT
        || (cov.cov_c.is_none() && ml.solver_converged);
    Ok(Solved {
        start,
        f0,
        f1,
        ml,
        cov,
        converged,
    })
}

impl Solved {
    /// The fitting problem of this fit on its frame points `pts`.
    pub fn problem<'a>(
        &self,
        pts: &'a [[f64; 3]],
        g: f64,
        noise: &'a Noise<'a>,
        model: Model,
    ) -> NormProblem<'a> {
        NormProblem {
            pts,
            g,
            noise: noise.in_frame(self.f1.s),
            model,
            kmax: f64::INFINITY,
        }
    }
}

/// Largest predicted std of the parameters (comparable units).
fn max_std(s: &observe::ObsSummary) -> f64 {
    s.std().iter().cloned().fold(0.0, f64::max)
}

/// After a failed linear solution: when the bias + scale model ("diag") fits the dwells but
/// the full model's design is degenerate there (six faces only: the misalignments are not
/// seen), the design is the cause, and the error is the observability message rather than
/// the linear solution's ("not an ellipsoid").
#[cold]
fn undetermined_by_design<const N: usize>(
    prob: &NormProblem<'_>,
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    set: &FitSettings,
    f0: Frame,
    f1: Frame,
) -> Result<()> {
    if set.model == Model::Diag {
        return Ok(());
    }
    let Ok(diag) = start::quadric_fit(means, f0, g, Model::Diag, false) else {
        return Ok(());
    };
    let p = f1.to_frame(&f0.unframe(&diag));
    let Ok(at) = ml_stage::<N>(prob, &p, set, false, false, 0.0) else {
        return Ok(());
    };
    let cov = covariance_stage::<N>(&at, means.len(), g, noise.known(), set);
    let n = means.len();
    if !cov.summary.degenerate {
        if !cov.summary.weak {
            return Ok(());
        }
        // Weakly determined there: the linear solution's failure ("not an ellipsoid") comes
        // from parameters the poses barely see, which the message names.
        let weak: Vec<String> = (0..N)
            .filter(|&i| !(cov.summary.std_comparable[i] <= set.weak_std))
            .map(|i| {
                let unit = if (3..6).contains(&i) { " g" } else { "" };
                let name = PARAM_NAMES[i];
                format!(
                    "{name} (predicted std {:.1e}{unit})",
                    cov.summary.std_comparable[i]
                )
            })
            .collect();
        return degenerate(format!(
            "the {n} dwells barely determine {} of model \"{}\" (relative units), so its \
             linear solution fails (the fitted quadric is not an ellipsoid) while the bias + \
             scale model fits them; add poses between the axes (tilts of 35-55 deg in both \
             axes at once), or fit model \"diag\"",
            weak.join(", "),
            set.model.name()
        ));
    }
    let jc = comparable_jacobian(prob, &at.params, N)?;
    let o = observe::obs_report(&jc, cov.obs_scale, set)?;
    degenerate(degenerate_message(
        &o,
        set.model,
        n,
        &cov.summary,
        set.degenerate_std,
    ))
}

fn start_stage_checked(means: &[[f64; 3]], g: f64, set: &FitSettings, f0: Frame) -> Result<Start> {
    set.validate()?;
    start::start_stage(means, g, set, f0)
}

/// The checks after the stages: a degenerate design is an error when asked for (or when the
/// linear solution failed: then the design explains it), the linear solution's own failure
/// otherwise, and non-finite parameters. `jc` builds the comparable Jacobian for the message.
pub fn check_solved(
    s: &Solved,
    set: &FitSettings,
    n: usize,
    jc: impl FnOnce() -> Result<DMatrix<f64>>,
) -> Result<()> {
    let failed = s.start.error.is_some();
    if s.cov.summary.degenerate && (set.raise_degenerate || failed) {
        let o = obs_report(&jc()?, s.cov.obs_scale, set)?;
        return degenerate(degenerate_message(
            &o,
            set.model,
            n,
            &s.cov.summary,
            set.degenerate_std,
        ));
    }
    if let Some(e) = &s.start.error {
        // The design is determined, so the linear solution failed because of the data.
        return Err(e.clone());
    }
    if s.ml.params.iter().any(|v| !v.is_finite()) {
        return Err(CoreError::NotConverged(
            "the fit produced non-finite parameters".into(),
        ));
    }
    Ok(())
}

/// Covariance in output units (`p x p`) from the comparable frame covariance: bias rows and
/// columns times `g`, everything times `s^2` for a known noise model (with the noise
/// estimated the covariance is per unit output variance, so the frame scale cancels).
pub fn output_covariance(s: &Solved, np: usize, g: f64, noise_known: bool) -> DMatrix<f64> {
    let cs = if noise_known { s.f1.s * s.f1.s } else { 1.0 };
    match &s.cov.cov_c {
        Some(c) => DMatrix::from_fn(np, np, |i, j| output_cov_entry(c, i, j, g, cs)),
        None => DMatrix::from_element(np, np, f64::NAN),
    }
}

/// Entry `(i, j)` of the output covariance from the comparable frame covariance `c`: bias
/// rows and columns times `g`, everything times `scale`. The unit factors are multiplied
/// together first (commutative), so the result is symmetric to the bit, and a batch row's std
/// equals the single fit's.
pub fn output_cov_entry(c: &[[f64; 9]; 9], i: usize, j: usize, g: f64, scale: f64) -> f64 {
    let d = |i: usize| if (3..6).contains(&i) { g } else { 1.0 };
    c[i][j] * (d(i) * d(j) * scale)
}

/// Largest `sigma_g` accepted, relative to `g`: a reference gravity known no better than 1 %
/// is not a reference (and a larger value is most likely in other units than `g`).
pub const SIGMA_G_MAX_RELATIVE: f64 = 1e-2;

/// The unit `g` is most likely in, for messages: `"m/s^2"`, `"g"` or `"cm/s^2"`
/// (`"the units of g"` otherwise).
fn likely_unit(g: f64) -> &'static str {
    if (9.0..=10.5).contains(&g) {
        "m/s^2"
    } else if (0.9..=1.1).contains(&g) {
        "g"
    } else if (900.0..=1050.0).contains(&g) {
        "cm/s^2"
    } else {
        "the units of g"
    }
}

/// Check the std `sigma_g` of the reference gravity `g` (same unit as `g`): non-negative,
/// finite and at most [`SIGMA_G_MAX_RELATIVE`] of `g`.
pub fn check_sigma_g(sigma_g: f64, g: f64) -> Result<f64> {
    if !(sigma_g >= 0.0 && sigma_g.is_finite()) {
        return invalid(format!(
            "sigma_g must be a non-negative, finite std of the reference gravity (in the \
             units of g); got {sigma_g}"
        ));
    }
    if sigma_g > SIGMA_G_MAX_RELATIVE * g.abs() {
        return invalid(format!(
            "sigma_g = {sigma_g} is more than 1 % of g = {g}: give the std of the reference \
             gravity in the units of g ({}); typically 1e-5 m/s^2 from an absolute gravimeter, \
             1e-3 m/s^2 from a latitude formula",
            likely_unit(g)
        ));
    }
    Ok(sigma_g)
}

/// Sensitivity of the parameters to the reference gravity, `dp/dg` (first `np` entries; the
/// rest zero). Exact for the norm model: with `g` scaled by `1 + e` the fit's `K` scales by
/// `1 / (1 + e)` and `b` stays (every residual `|K^-1 (a - b)| - g` and its std scale alike),
/// so every entry of `K` (scale factors and misalignments: all models store entries of `K`)
/// has `dp/dg = -p / g` and the biases none.
pub fn gravity_sensitivity(params: &[f64], g: f64) -> [f64; 9] {
    let mut j = [0.0; 9];
    for (i, (v, p)) in j.iter_mut().zip(params).enumerate() {
        if !(3..6).contains(&i) {
            *v = -p / g;
        }
    }
    j
}

/// Entry `(i, j)` of the reference-gravity covariance `sigma_g^2 (dp/dg) (dp/dg)^T` (`jv`
/// from [`gravity_sensitivity`]); symmetric to the bit.
pub fn gravity_cov_entry(jv: &[f64; 9], i: usize, j: usize, sigma_g: f64) -> f64 {
    (jv[i] * jv[j]) * (sigma_g * sigma_g)
}

/// Fit the static model to `k` dwell means.
pub fn fit_static(
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    set: &FitSettings,
) -> Result<StaticFit> {
    match set.model.n_params() {
        6 => fit_static_n::<6>(means, g, noise, set),
        _ => fit_static_n::<9>(means, g, noise, set),
    }
}

fn fit_static_n<const N: usize>(
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    set: &FitSettings,
) -> Result<StaticFit> {
    let n = means.len();
    let mut pts = Vec::with_capacity(n);
    let s = solve::<N>(means, g, noise, set, &mut pts)?;
    let mut residuals = vec![0.0; n];
    let mut sigma_r = vec![0.0; n];
    let prob = s.problem(&pts, g, noise, set.model);
    let pass = prob.residuals_each(&s.ml.params, |k, r, sd| {
        residuals[k] = r;
        sigma_r[k] = sd;
    });
    if let Err(e) = pass {
        return Err(s.start.error.clone().unwrap_or(e));
    }
    check_solved(&s, set, n, || comparable_jacobian(&prob, &s.ml.params, N)).map_err(|e| {
        // One pose: said as such before any combination it leaves undetermined (the
        // combination's advice, a smaller model, cannot help there).
        match e {
            CoreError::Degenerate(_) => start::one_pose(means).unwrap_or(e),
            e => e,
        }
    })?;
    if !s.converged && !s.cov.summary.degenerate {
        // An iteration that wanders because no pose turned an axis towards gravity (and the
        // design check above did not already say what is undetermined): say so.
        if let Some(e) = start::unexcited_axes(means) {
            return Err(e);
        }
    }
    let known = noise.known();
    // With the noise estimated, costs are in frame units squared: report output units.
    let s2 = s.f1.s * s.f1.s;
    let (cost, chi2_dof) = if known {
        (s.cov.cost, s.cov.chi2_dof)
    } else {
        (s.cov.cost * s2, s.cov.chi2_dof * s2)
    };
    if !known {
        let sc = s.cov.chi2_dof.sqrt();
        for v in &mut sigma_r {
            *v *= sc;
        }
    }
    let params = s.f1.unframe(&s.ml.params)[..N].to_vec();
    Ok(StaticFit {
        model: set.model,
        method: set.method,
        params,
        start: s.start.params[..N].to_vec(),
        start_source: s.start.source,
        start_error: s.start.error.as_ref().map(|e| e.to_string()),
        covariance: output_covariance(&s, N, g, known),
        residuals,
        sigma_r,
        cost,
        dof: n - N,
        chi2_dof,
        iterations: s.ml.iterations,
        converged: s.converged,
        decrement: s.cov.decrement,
        noise_known: known,
        summary: s.cov.summary,
        frame: (s.f1, s.ml.params),
        pts,
        obs_scale: s.cov.obs_scale,
    })
}

// ------------------------------------------------------------------------------------------
// Applying a model

/// Rows per parallel task of [`apply_model`].
const APPLY_CHUNK: usize = 16384;

/// Calibrated specific force `K^-1 (am - b)` for every row of an `(N, 3)` array of any
/// [`Sample`] dtype and strides; returns row-major `N x 3` values.
pub fn apply_model<T: Sample>(
    samples: &ArrayView2<'_, T>,
    k: &[[f64; 3]; 3],
    b: &[f64; 3],
) -> Result<Vec<f64>> {
    let t = apply_inverse(samples, k, b)?;
    let mut out = vec![0.0; 3 * samples.nrows()];
    apply_inverse_into(samples, &t, b, &mut out);
    Ok(out)
}

/// `K^-1` after the checks of [`apply_model`] (shape, finite model, invertible `K`).
pub fn apply_inverse<T: Sample>(
    samples: &ArrayView2<'_, T>,
    k: &[[f64; 3]; 3],
    b: &[f64; 3],
) -> Result<Matrix3<f64>> {
    if samples.ncols() != 3 {
        return invalid(format!(
            "samples must have shape (N, 3); got {} columns",
            samples.ncols()
        ));
    }
    let km = Matrix3::from_fn(|i, j| k[i][j]);
    if km.iter().any(|v| !v.is_finite()) || b.iter().any(|v| !v.is_finite()) {
        return invalid("model matrix and bias must be finite");
    }
    inverse3(&km).ok_or_else(|| CoreError::InvalidInput("the model's K matrix is singular".into()))
}

/// [`apply_model`] of the rows of `samples` into `out` (row-major, `3 * rows` values) with
/// `t = K^-1` from [`apply_inverse`]: a caller can work through a long array block by block.
pub fn apply_inverse_into<T: Sample>(
    samples: &ArrayView2<'_, T>,
    t: &Matrix3<f64>,
    b: &[f64; 3],
    out: &mut [f64],
) {
    out.par_chunks_mut(3 * APPLY_CHUNK)
        .enumerate()
        .for_each(|(c, dst)| {
            let r0 = c * APPLY_CHUNK;
            for (i, o) in dst.chunks_exact_mut(3).enumerate() {
                let r = r0 + i;
                let d = [
                    samples[[r, 0]].to_f64() - b[0],
                    samples[[r, 1]].to_f64() - b[1],
                    samples[[r, 2]].to_f64() - b[2],
                ];
                for (a, trow) in o.iter_mut().zip(0..3) {
                    *a = t[(trow, 0)] * d[0] + t[(trow, 1)] * d[1] + t[(trow, 2)] * d[2];
                }
            }
        });
}

// ------------------------------------------------------------------------------------------

#[cfg(test)]
pub(crate) mod tests_common {
    use super::*;

    pub const TRUTH: [f64; 9] = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03];
    pub const G: f64 = 9.80665;

    /// Deterministic pseudo-random numbers in [-1, 1].
    pub fn lcg(seed: &mut u64) -> f64 {
        crate::test_rng::unit(seed) * 2.0 - 1.0
    }

    /// Gravity seen at tilts (tx, ty): `[-g sin ty, g sin tx cos ty, g cos tx cos ty]`.
    pub fn force(tx_deg: f64, ty_deg: f64) -> Vector3<f64> {
        let (tx, ty) = (tx_deg.to_radians(), ty_deg.to_radians());
        Vector3::new(
            -G * ty.sin(),
            G * tx.sin() * ty.cos(),
            G * tx.cos() * ty.cos(),
        )
    }

    /// Noise-free dwell means at `n` random tilts within +-`tilt_deg`.
    pub fn simulate(model: Model, p: &[f64], n: usize, tilt_deg: f64, seed: u64) -> Vec<[f64; 3]> {
        simulate_noisy(model, p, n, tilt_deg, 0.0, seed)
    }

    /// Dwell means with uniform noise of std `sigma` per axis.
    pub fn simulate_noisy(
        model: Model,
        p: &[f64],
        n: usize,
        tilt_deg: f64,
        sigma: f64,
        seed: u64,
    ) -> Vec<[f64; 3]> {
        let k = model.k_matrix(p);
        let mut s = seed;
        (0..n)
            .map(|_| {
                let a = force(lcg(&mut s) * tilt_deg, lcg(&mut s) * tilt_deg);
                let am = k * a + Vector3::new(p[3], p[4], p[5]);
                let u = 3f64.sqrt() * sigma;
                [
                    am[0] + u * lcg(&mut s),
                    am[1] + u * lcg(&mut s),
                    am[2] + u * lcg(&mut s),
                ]
            })
            .collect()
    }

    pub fn maxerr(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }
}

#[cfg(test)]
mod tests {
    use super::tests_common::*;
    use super::*;

    fn settings(method: Method) -> FitSettings {
        FitSettings::new(Model::Lower, method)
    }

    #[test]
    fn gravity_is_plausible_in_each_unit_within_earths_range_only() {
        for g in [9.78, 9.832, 9.75, 1.0, 0.9973, 1.0026, 978.0, 983.2] {
            assert_eq!(implausible_g(g), None, "{g}");
        }
        for g in [9.8895, 9.7, 9.9, 0.99, 1.005, 970.0, 990.0, 5.0, 32.17] {
            let why = implausible_g(g).expect("refused");
            assert!(why.starts_with(&format!("g = {g} is not")), "{why}");
        }
        for (g, shown) in [(1e-300, "1e-300"), (1e300, "1e300"), (2.5e12, "2.5e12")] {
            let why = implausible_g(g).expect("refused");
            assert!(why.starts_with(&format!("g = {shown} is not")), "{why}");
        }
    }

    #[test]
    fn a_dead_channel_is_named() {
        let mut m = simulate(Model::Lower, &TRUTH, 20, 60.0, 1);
        m.iter_mut().for_each(|r| r[1] = 0.0);
        let e = fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)).unwrap_err();
        assert!(
            matches!(&e, CoreError::Degenerate(t) if t.contains("the y output reads 0 in every \
                one of the 20 dwells: a dead or disconnected channel")),
            "{e:?}"
        );
    }

    #[test]
    fn quadric_and_lm_recover_truth_exactly() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 1);
        for method in [Method::Quadric, Method::Lm, Method::GaussNewton] {
            let f = fit_static(&m, G, &Noise::Estimated, &settings(method)).unwrap();
            assert!(
                maxerr(&f.params, &TRUTH) < 1e-9,
                "{method:?} {:?}",
                f.params
            );
            assert!(f.converged);
        }
    }

    #[test]
    fn gravity_sensitivity_matches_a_refit_with_g_perturbed() {
        // dp/dg = -p/g for every entry of K (misalignments included), 0 for the biases: a
        // refit with g (1 + 1e-6) agrees with the first-order prediction, for every model.
        for model in [Model::Lower, Model::Upper, Model::Diag] {
            let m = simulate_noisy(model, &TRUTH, 24, 90.0, 1e-4, 11);
            let set = FitSettings::new(model, Method::Lm);
            let noise = Noise::Uniform([1e-8; 3]);
            let f0 = fit_static(&m, G, &noise, &set).unwrap();
            let e = 1e-6;
            let f1 = fit_static(&m, G * (1.0 + e), &noise, &set).unwrap();
            let jv = gravity_sensitivity(&f0.params, G);
            let np = model.n_params();
            for (i, (want, (p1, p0))) in jv.iter().zip(f1.params.iter().zip(&f0.params)).enumerate()
            {
                let fd = (p1 - p0) / (G * e);
                let tol = 1e-4 * (p0.abs() / G).max(1e-3);
                assert!(
                    i < np && (fd - want).abs() < tol,
                    "{model:?} {i}: refit {fd:e}, predicted {want:e}"
                );
            }
        }
    }

    #[test]
    fn sigma_g_is_refused_unless_non_negative_finite_and_within_one_percent() {
        assert_eq!(check_sigma_g(0.0, G).unwrap(), 0.0);
        assert_eq!(check_sigma_g(1e-3, G).unwrap(), 1e-3);
        for bad in [-1e-5, f64::NAN, f64::INFINITY] {
            let e = check_sigma_g(bad, G).unwrap_err().to_string();
            assert!(e.contains("non-negative, finite"), "{e}");
        }
        let e = check_sigma_g(0.2, G).unwrap_err().to_string();
        assert!(
            e.contains("more than 1 % of g") && e.contains("m/s^2"),
            "{e}"
        );
        assert!(check_sigma_g(0.02, 1.0)
            .unwrap_err()
            .to_string()
            .contains("(g);"));
    }

    #[test]
    fn batch_and_prediction_add_the_reference_gravity_term() {
        let m = simulate_noisy(Model::Lower, &TRUTH, 24, 90.0, 1e-5, 12);
        let set = settings(Method::Lm);
        let sg = 1e-4;
        let a = fit_batch(&[&m], &[G], Some(1e-5), &set).unwrap();
        let b = fit_batch_sigma_g(&[&m], &[G], Some(1e-5), Some(sg), &set).unwrap();
        let jv = gravity_sensitivity(&a[0].params, G);
        for (i, (d, (s0, s1))) in jv.iter().zip(a[0].std.iter().zip(&b[0].std)).enumerate() {
            let want = (s0.powi(2) + (d * sg).powi(2)).sqrt();
            assert!((s1 - want).abs() < 1e-12 * want, "{i}");
        }
        assert_eq!(a[0].std[3], b[0].std[3]);
        assert!(fit_batch_sigma_g(&[&m], &[G], None, Some(1.0), &set).is_err());
        let force: Vec<[f64; 3]> = (0..24)
            .map(|k| {
                let a = force(
                    (k as f64 * 47.0) % 360.0 - 180.0,
                    (k as f64 * 29.0) % 180.0 - 90.0,
                );
                [a[0], a[1], a[2]]
            })
            .collect();
        let p0 = observe::predict(Model::Lower, &TRUTH, &force, 1e-5, G, 0.0, &set).unwrap();
        let p1 = observe::predict(Model::Lower, &TRUTH, &force, 1e-5, G, sg, &set).unwrap();
        let jv = gravity_sensitivity(&TRUTH, G);
        for (i, (d, (s0, s1))) in jv.iter().zip(p0.std.iter().zip(&p1.std)).enumerate() {
            let want = (s0.powi(2) + (d * sg).powi(2)).sqrt();
            assert!((s1 - want).abs() < 1e-12 * want, "{i}");
        }
        assert!(observe::predict(Model::Lower, &TRUTH, &force, 1e-5, G, -1.0, &set).is_err());
    }

    #[test]
    fn covariance_is_symmetric_to_the_bit() {
        // The Python glue hands the column-major storage over as row-major order.
        for (model, noise) in [
            (Model::Lower, Noise::Estimated),
            (Model::Lower, Noise::Uniform([1e-6; 3])),
            (Model::Upper, Noise::Uniform([2e-6, 1e-6, 3e-6])),
            (Model::Diag, Noise::Estimated),
        ] {
            let m = simulate_noisy(model, &TRUTH, 20, 40.0, 1e-3, 5);
            let f = fit_static(&m, G, &noise, &FitSettings::new(model, Method::Lm)).unwrap();
            let c = &f.covariance;
            for i in 0..c.nrows() {
                for j in 0..i {
                    assert_eq!(
                        c[(i, j)].to_bits(),
                        c[(j, i)].to_bits(),
                        "{model:?} {i} {j}"
                    );
                }
            }
        }
    }

    #[test]
    fn paper_method_is_biased_by_the_dropped_terms() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 2);
        let f = fit_static(&m, G, &Noise::Estimated, &settings(Method::LinearPaper)).unwrap();
        let e = maxerr(&f.params, &TRUTH);
        assert!(e > 1e-5 && e < 1e-2, "paper error {e}");
        assert_eq!(f.start_source, StartSource::Paper);
    }

    #[test]
    fn upper_and_diag_models_round_trip() {
        let up = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, -0.02, 0.03];
        let m = simulate(Model::Upper, &up, 15, 90.0, 3);
        let set = FitSettings::new(Model::Upper, Method::Lm);
        let f = fit_static(&m, G, &Noise::Estimated, &set).unwrap();
        assert!(maxerr(&f.params, &up) < 1e-9);
        let m = simulate(Model::Diag, &up[..6], 8, 90.0, 4);
        let set = FitSettings::new(Model::Diag, Method::Lm);
        let f = fit_static(&m, G, &Noise::Estimated, &set).unwrap();
        assert!(maxerr(&f.params, &up[..6]) < 1e-9);
        assert_eq!(f.covariance.ncols(), 6);
    }

    #[test]
    fn raw_counts_scale_is_handled() {
        let p = [
            414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0,
        ];
        let m = simulate(Model::Lower, &p, 30, 90.0, 5);
        let f = fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)).unwrap();
        for (a, b) in f.params.iter().zip(&p) {
            assert!((a - b).abs() < 1e-7 * b.abs().max(1.0), "{a} vs {b}");
        }
    }

    #[test]
    fn estimated_noise_is_reported_in_output_units() {
        // Raw counts, 1 count of noise per axis: chi2/dof estimates 1 count^2 whatever the
        // frame, and the scaled covariance equals the one with the noise given.
        let p = [
            414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0,
        ];
        let m = simulate_noisy(Model::Lower, &p, 400, 90.0, 1.0, 6);
        let f = fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)).unwrap();
        assert!((f.chi2_dof - 1.0).abs() < 0.2, "{}", f.chi2_dof);
        let k = fit_static(&m, G, &Noise::Uniform([1.0; 3]), &settings(Method::Lm)).unwrap();
        assert!(maxerr(&f.params, &k.params) < 1e-9 * 4e4);
        for i in 0..9 {
            let a = f.covariance[(i, i)] * f.chi2_dof;
            let b = k.covariance[(i, i)];
            assert!((a / b - f.chi2_dof).abs() < 1e-6 * f.chi2_dof, "{i}");
        }
        for (a, b) in f.sigma_r.iter().zip(&k.sigma_r) {
            assert!((a / b - f.chi2_dof.sqrt()).abs() < 1e-9);
        }
    }

    #[test]
    fn two_plane_procedure_is_exactly_singular() {
        // Hold tx = 10 deg and sweep ty, then hold ty = 10 deg and sweep tx.
        let k = Model::Lower.k_matrix(&TRUTH);
        let mut m = Vec::new();
        for i in 0..10 {
            let s = -30.0 + 6.0 * i as f64;
            for (tx, ty) in [(10.0, s), (s, 10.0)] {
                let am = k * force(tx, ty) + Vector3::new(TRUTH[3], TRUTH[4], TRUTH[5]);
                m.push([am[0], am[1], am[2]]);
            }
        }
        match fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)).unwrap_err() {
            CoreError::Degenerate(msg) => {
                assert!(msg.contains("m1") || msg.contains("m2"), "{msg}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn fewer_distinct_poses_than_parameters_are_refused() {
        // Six faces, each recorded twice with noise (a dwell split in halves, say): the
        // misalignments are set by the noise alone. Weak, not degenerate, by the predicted
        // std (above 0.1 relative); refused by the pose count. The bias + scale model fits
        // them. (Many repeats of few poses at high signal to noise, whose predicted std is
        // small, are not refused: tests/test_gap.py's fixed pose order.)
        let k = Model::Lower.k_matrix(&TRUTH);
        let mut s = 7u64;
        let mut m = Vec::new();
        for face in 0..6 {
            // Each face tilted by a few degrees, as a hand-placed box sits, and placed twice
            // (a tenth of a degree apart).
            let mut a = Vector3::new(0.1 * lcg(&mut s), 0.1 * lcg(&mut s), 0.1 * lcg(&mut s));
            a[face % 3] = if face < 3 { 1.0 } else { -1.0 };
            for _ in 0..2 {
                let b = a + Vector3::new(lcg(&mut s), lcg(&mut s), lcg(&mut s)) * 0.003;
                let am = k * (b * (G / b.norm())) + Vector3::new(TRUTH[3], TRUTH[4], TRUTH[5]);
                m.push([0, 1, 2].map(|i| am[i] + 5e-3 * lcg(&mut s)));
            }
        }
        match fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)) {
            Err(CoreError::Degenerate(msg)) => assert!(
                msg.starts_with("the 12 dwells are at only 6 distinct poses")
                    && msg.contains("or fit model \"diag\""),
                "{msg}"
            ),
            other => panic!("{other:?}"),
        }
        let diag = FitSettings::new(Model::Diag, Method::Lm);
        let f = fit_static(&m, G, &Noise::Estimated, &diag).unwrap();
        assert!((f.params[0] - TRUTH[0]).abs() < 1e-2, "{:?}", f.params);
        // Not refused when asked not to (observability "warn"): a weak fit.
        let warn = FitSettings {
            raise_degenerate: false,
            ..settings(Method::Lm)
        };
        let f = fit_static(&m, G, &Noise::Estimated, &warn).unwrap();
        assert!(f.summary.weak && !f.summary.degenerate, "{:?}", f.summary);
        // Poses counted up to the limit, on the calibrated directions; the same poses in any
        // order count the same. On the raw means, whose norms carry the biases, a tolerance
        // of 5 % of the norm would merge poses of a sensor with large offsets.
        let u: Vec<[f64; 3]> = start::directions(&m, Model::Lower, &TRUTH)
            .into_iter()
            .map(Option::unwrap)
            .collect();
        assert_eq!(start::distinct_poses_upto(&u, start::SAME_POSE, 4), 4);
        let mut r = u.clone();
        r.reverse();
        assert_eq!(start::distinct_poses(&r, start::SAME_POSE), 6);
        let far: Vec<[f64; 3]> = m
            .iter()
            .map(|x| [x[0] + 500.0, x[1] + 500.0, x[2]])
            .collect();
        let mut off = TRUTH;
        off[3] += 500.0;
        off[4] += 500.0;
        let uf: Vec<[f64; 3]> = start::directions(&far, Model::Lower, &off)
            .into_iter()
            .map(Option::unwrap)
            .collect();
        assert_eq!(start::distinct_poses(&uf, start::SAME_POSE), 6);
        assert!(start::distinct_poses(&far, 0.05 * 700.0) < 6);
    }

    #[test]
    fn dwells_in_a_small_cap_are_not_fitted_to_a_collapsed_ellipsoid() {
        // Tilts within +-5 deg, noise known: the quadric's start can fall into a small
        // ellipsoid centred near the data (sz 0.006, bz 12 for 1.2 and 0.3, chi2/dof 45-156)
        // that the restart from the unit scale shows to be a worse minimum, or no better
        // than a calibration far from it: degenerate every time, never a fit.
        let sigma = 1e-3;
        let var = [[sigma * sigma; 3]].repeat(20);
        for seed in 0..40u64 {
            let m = simulate_noisy(Model::Lower, &TRUTH, 20, 5.0, sigma, 100 + seed);
            let noise = Noise::Known(&var);
            match fit_static(&m, G, &noise, &settings(Method::Lm)) {
                Err(CoreError::Degenerate(_)) => {}
                other => panic!("seed {seed}: {other:?}"),
            }
        }
        // Offsets of several g (raw counts of a mid-scale ADC), every attitude: the restart
        // runs (biases beyond one g of the response, spans under 20 % of the norm) but finds
        // the same calibration or its mirror image, and the fit stands.
        let counts = [
            414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0,
        ];
        // Offsets of several g are told from a cap of one pose (the message of a degenerate
        // fit says "one pose" only for the latter), at +-30 deg as over the sphere.
        for tilt in [30.0, 180.0] {
            let m = simulate_noisy(Model::Lower, &counts, 20, tilt, 1.0, 5);
            assert!(start::offset_outputs(&m, G), "{tilt}");
        }
        for tilt in [5.0, 30.0, 180.0] {
            let m = simulate_noisy(Model::Lower, &TRUTH, 20, tilt, 1e-3, 5);
            assert!(!start::offset_outputs(&m, G), "{tilt}");
        }
        let m = simulate_noisy(Model::Lower, &counts, 38, 180.0, 1.0, 4);
        let f = fit_static(&m, G, &Noise::Uniform([1.0; 3]), &settings(Method::Lm)).unwrap();
        for (p, c) in f.params.iter().zip(counts) {
            assert!((p - c).abs() < 3.0, "{:?}", f.params);
        }
    }

    #[test]
    fn bad_input_is_reported() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 6);
        let set = settings(Method::Lm);
        assert!(matches!(
            fit_static(&m[..5], G, &Noise::Estimated, &set),
            Err(CoreError::Degenerate(_))
        ));
        assert!(matches!(
            fit_static(&m, -1.0, &Noise::Estimated, &set),
            Err(CoreError::InvalidInput(_))
        ));
        let mut bad = m.clone();
        bad[3][1] = f64::NAN;
        let e = fit_static(&bad, G, &Noise::Estimated, &set).unwrap_err();
        assert_eq!(e.to_string(), "dwell 3 has a NaN mean");
        let mut s = set.clone();
        s.max_iter = 0;
        assert!(fit_static(&m, G, &Noise::Estimated, &s)
            .unwrap_err()
            .to_string()
            .contains("max_iter"));
        // Points on a hyperboloid-like cloud: not an ellipsoid.
        let mut s = 9;
        let h: Vec<[f64; 3]> = (0..20)
            .map(|_| {
                let (x, y) = (3.0 * lcg(&mut s), 3.0 * lcg(&mut s));
                [x, y, (x * x - y * y + 5.0).sqrt()]
            })
            .collect();
        assert!(fit_static(&h, G, &Noise::Estimated, &set).is_err());
    }

    /// The ML stage reaches the minimum of the re-weighted cost: the gradient of the cost
    /// (with the weights' own derivative) vanishes there, while at the fixed-weight minimum
    /// (weights frozen at the start) it does not.
    #[test]
    fn ml_stage_minimises_the_likelihood_not_a_fixed_point() {
        let m = simulate_noisy(Model::Lower, &TRUTH, 20, 30.0, 1e-3, 11);
        let var = vec![[1e-6, 4e-6, 0.25e-6]; 20];
        let noise = Noise::Known(&var);
        let set = settings(Method::Lm);
        let f0 = Frame::centroid(&m, G).unwrap();
        let st = start::start_stage(&m, G, &set, f0).unwrap();
        let f1 = Frame::from_params(Model::Lower, &st.params, f0);
        let mut pts = Vec::new();
        f1.points_into(&m, &mut pts);
        let prob = NormProblem {
            pts: &pts,
            g: G,
            noise: noise.in_frame(f1.s),
            model: Model::Lower,
            kmax: f64::INFINITY,
        };
        let p0 = f1.to_frame(&st.params);
        let ml = ml_stage::<9>(&prob, &p0, &set, true, false, 1e-8).unwrap();
        assert!(ml.solver_converged && ml.iterations > 0);
        let c = covariance_stage::<9>(&ml, 20, G, true, &set);
        assert!(c.decrement < 1e-7, "{}", c.decrement);
        // Not iterating returns the start unchanged, with its (non-stationary) normal
        // equations: far from the minimum in parameter std.
        let same = ml_stage::<9>(&prob, &p0, &set, false, false, 1e-8).unwrap();
        assert_eq!(same.params, p0);
        let c0 = covariance_stage::<9>(&same, 20, G, true, &set);
        assert!(
            c0.decrement > 1e-4 && c0.cost > c.cost,
            "{} {}",
            c0.decrement,
            c0.cost
        );
        // The cost's gradient at the ML point vanishes: central differences of the cost.
        let h = 1e-7;
        for j in 0..9 {
            let (mut a, mut b) = (ml.params, ml.params);
            a[j] += h;
            b[j] -= h;
            let fd = (prob.cost_at(&a).unwrap() - prob.cost_at(&b).unwrap()) / (2.0 * h);
            let gj = 2.0 * ml.jtr[j];
            assert!(
                (fd - gj).abs() < 1e-5 * ml.jtj[j][j].sqrt(),
                "{j}: {fd} {gj}"
            );
        }
    }

    #[test]
    fn runaway_guard_refuses_infinite_scale_factors() {
        let f0 = Frame {
            c: [0.0; 3],
            s: 1.0,
        };
        let mut p = [1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        assert!(runaway_guard(&p, f0, f0, 20).is_ok());
        p[2] = 1e3;
        let e = runaway_guard(&p, f0, f0, 20).unwrap_err();
        assert!(matches!(e, CoreError::NotConverged(_)) && e.to_string().contains("ran away"));
        p[2] = f64::NAN;
        assert!(runaway_guard(&p, f0, f0, 20).is_err());
        // From the paper's e0 = [2]*9 the fixed-weight cost used to run away; the ML cost
        // either converges near the truth or is refused, never a confident wrong answer.
        let m = simulate_noisy(Model::Lower, &TRUTH, 20, 30.0, 1e-3, 1);
        let mut set = settings(Method::Lm);
        set.start = Some(vec![2.0; 9]);
        if let Ok(f) = fit_static(&m, G, &Noise::Uniform([1e-6; 3]), &set) {
            let r = fit_static(&m, G, &Noise::Uniform([1e-6; 3]), &settings(Method::Lm)).unwrap();
            assert!(f.converged && (f.cost - r.cost).abs() < 1e-6 * r.cost);
        }
    }

    #[test]
    fn check_solved_reports_degenerate_designs_and_failed_starts() {
        // Six faces: the 9-parameter quadric fails (too few distinct directions); the
        // fallback start diagnoses the design as degenerate.
        let k = Model::Lower.k_matrix(&TRUTH);
        let mut m = Vec::new();
        for a in [
            [G, 0.0, 0.0],
            [-G, 0.0, 0.0],
            [0.0, G, 0.0],
            [0.0, -G, 0.0],
            [0.0, 0.0, G],
            [0.0, 0.0, -G],
        ] {
            for _ in 0..2 {
                let am = k * Vector3::from(a) + Vector3::new(TRUTH[3], TRUTH[4], TRUTH[5]);
                m.push([am[0], am[1], am[2]]);
            }
        }
        let e = fit_static(&m, G, &Noise::Estimated, &settings(Method::Lm)).unwrap_err();
        assert!(matches!(e, CoreError::Degenerate(_)), "{e}");
        let set = FitSettings::new(Model::Diag, Method::Lm);
        let f = fit_static(&m, G, &Noise::Estimated, &set).unwrap();
        assert!(maxerr(&f.params, &[1.1, 0.95, 1.2, 0.3, -0.6, 0.3]) < 0.05);
    }

    #[test]
    fn batch_matches_single_fits() {
        let sessions: Vec<Vec<[f64; 3]>> = (0..4)
            .map(|s| simulate_noisy(Model::Lower, &TRUTH, 20 + s, 90.0, 1e-3, 10 + s as u64))
            .collect();
        let refs: Vec<&[[f64; 3]]> = sessions.iter().map(|s| s.as_slice()).collect();
        let set = settings(Method::Lm);
        let rows = fit_batch(&refs, &[G], Some(1e-3), &set).unwrap();
        for (r, s) in rows.iter().zip(&sessions) {
            let f = fit_static(s, G, &Noise::Uniform([1e-6; 3]), &set).unwrap();
            assert_eq!(r.status, BatchStatus::Ok);
            assert_eq!(&r.params[..9], f.params.as_slice());
            assert_eq!(r.n_dwells, s.len());
            for i in 0..9 {
                assert_eq!(r.std[i], f.covariance[(i, i)].sqrt());
            }
            assert_eq!(r.chi2_dof, f.chi2_dof);
        }
    }

    #[test]
    fn apply_inverts_the_model() {
        let p = TRUTH;
        let k = Model::Lower.k_matrix(&p);
        let a = Vector3::new(1.0, -2.0, 9.0);
        let am = k * a + Vector3::new(p[3], p[4], p[5]);
        let arr = ndarray::Array2::from_shape_vec((1, 3), vec![am[0], am[1], am[2]]).unwrap();
        let kk = [
            [k[(0, 0)], k[(0, 1)], k[(0, 2)]],
            [k[(1, 0)], k[(1, 1)], k[(1, 2)]],
            [k[(2, 0)], k[(2, 1)], k[(2, 2)]],
        ];
        let out = apply_model(&arr.view(), &kk, &[p[3], p[4], p[5]]).unwrap();
        assert!(maxerr(&out, &[1.0, -2.0, 9.0]) < 1e-12);
    }

    #[test]
    fn k_matrix_places_the_misalignments_where_the_model_says() {
        let p: Vec<f64> = (1..=9).map(f64::from).collect();
        for model in [Model::Lower, Model::Upper, Model::Diag] {
            let mut want = Matrix3::from_diagonal(&Vector3::new(1.0, 2.0, 3.0));
            for (slot, (i, j)) in model
                .misalignment_entries()
                .into_iter()
                .flatten()
                .enumerate()
            {
                want[(i, j)] = p[6 + slot];
            }
            assert_eq!(model.k_matrix(&p), want, "{}", model.name());
            assert_eq!(
                model.params_from(&want, &Vector3::new(4.0, 5.0, 6.0))[..model.n_params()],
                p[..model.n_params()]
            );
        }
    }

    #[test]
    fn model_pattern_violations_are_found() {
        let lower = [[1.0, 0.0, 0.0], [0.1, 1.0, 0.0], [0.2, 0.3, 1.0]];
        assert_eq!(Model::Lower.violations(&lower), None);
        assert_eq!(Model::Upper.violations(&lower), Some((1, 0)));
        assert_eq!(Model::Diag.violations(&lower), Some((1, 0)));
    }
}

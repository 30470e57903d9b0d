//! Static field calibration by norm observation (seed 000, SPEC section 1).
//!
//! Sensor model: raw output `am = K a + b`, calibrated specific force `a = K^-1 (am - b)`.
//! Parameter vector, always in the seed's order: `[sx, sy, sz, bx, by, bz, m1, m2, m3]`
//! (model [`Model::Diag`] keeps the first 6). `K` is in output units per (m/s^2) (raw counts
//! per m/s^2 for raw data), `b` in output units.
//!
//! - [`Model::Lower`] (seed 000): `K = [[sx,0,0],[m1,sy,0],[m2,m3,sz]]`.
//! - [`Model::Upper`] (imu_tk's triangle): `K = [[sx,m1,m2],[0,sy,m3],[0,0,sz]]`.
//! - [`Model::Diag`]: `K = diag(sx, sy, sz)`.
//!
//! Methods: the paper's linear regression with its small-M back-substitution
//! ([`Method::LinearPaper`]), the exact quadric recovery (SPEC 1 steps 1-4,
//! [`Method::Quadric`]), and Gauss-Newton / Levenberg-Marquardt on the whitened residual
//! `(|a_k| - g) / sigma_k` (maximum likelihood), started from the quadric solution.
//!
//! All fitting runs in a normalised frame `am' = (am - c) / s` chosen so that `K' ~ I` and
//! `b' ~ 0`, which keeps raw-count data (offsets ~33000, ~414 counts per m/s^2) as well
//! conditioned as data in m/s^2. Observability is judged from the SVD of the whitened
//! Jacobian in *comparable units*: scale factors and misalignments relative to the mean scale,
//! biases in units of g.

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use crate::dwell::Sample;
use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lsq::{
    covariance_normal_fixed, lstsq_rows, solve_normal, solve_normal_fixed, svd_report,
    top_eigen_fixed, NlsOptions, NormalEquations, NormalEquationsFixed, Residuals,
};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};
use ndarray::ArrayView2;
use rayon::prelude::*;

/// Names of the parameters in vector order.
pub const PARAM_NAMES: [&str; 9] = ["sx", "sy", "sz", "bx", "by", "bz", "m1", "m2", "m3"];

/// Default predicted std (comparable units) above which a combination counts as undetermined.
pub const DEGENERATE_STD: f64 = 0.1;
/// Default predicted std (comparable units) above which a parameter counts as weakly determined.
pub const WEAK_STD: f64 = 1e-3;
/// Scale factors above this multiple of the data's spread scale (median distance of the
/// dwell means from their centroid, over g) count as a runaway fit.
pub const RUNAWAY: f64 = 100.0;
/// Relative singular value below which the design is exactly singular.
pub const SINGULAR_RTOL: f64 = 1e-9;

/// Which triangle of `K` carries the misalignment terms.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    /// Seed 000: `K` lower triangular (9 parameters).
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
                "unknown model {s:?}; use \"lower\" (9 parameters, seed 000), \"diag\" (6: bias + scale) or \"upper\" (9, imu_tk's triangle)"
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

    /// `K` from a parameter vector.
    pub fn k_matrix(self, p: &[f64]) -> Matrix3<f64> {
        match self {
            Model::Lower => Matrix3::new(p[0], 0.0, 0.0, p[6], p[1], 0.0, p[7], p[8], p[2]),
            Model::Upper => Matrix3::new(p[0], p[6], p[7], 0.0, p[1], p[8], 0.0, 0.0, p[2]),
            Model::Diag => Matrix3::new(p[0], 0.0, 0.0, 0.0, p[1], 0.0, 0.0, 0.0, p[2]),
        }
    }

    /// Parameter vector from `K` (the entries outside the model's pattern are ignored) and `b`.
    pub fn params_from(self, k: &Matrix3<f64>, b: &Vector3<f64>) -> Vec<f64> {
        let mut p = vec![k[(0, 0)], k[(1, 1)], k[(2, 2)], b[0], b[1], b[2]];
        match self {
            Model::Lower => p.extend_from_slice(&[k[(1, 0)], k[(2, 0)], k[(2, 1)]]),
            Model::Upper => p.extend_from_slice(&[k[(0, 1)], k[(0, 2)], k[(1, 2)]]),
            Model::Diag => {}
        }
        p
    }
}

/// Estimation method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// The paper's regression and small-M back-substitution (biased ~1e-4; for reproduction).
    LinearPaper,
    /// Exact recovery from the quadric regression (SPEC 1 steps 1-4).
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

/// What is known about the noise of the dwell means.
#[derive(Debug, Clone, PartialEq)]
pub enum Noise {
    /// Nothing: unit weights, the noise level is estimated from the residuals.
    Estimated,
    /// Variance of each dwell mean per axis, output units squared (`k` rows).
    Known(Vec<[f64; 3]>),
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
}

/// What the dwells can determine.
#[derive(Debug, Clone, PartialEq)]
pub struct Observability {
    /// Singular values of the whitened Jacobian in comparable units, descending.
    pub singular_values: Vec<f64>,
    /// `s_max / s_min`.
    pub condition: f64,
    /// Predicted std of each parameter in comparable units (scale-relative; bias in g).
    pub std_comparable: Vec<f64>,
    /// Least determined parameter combination (unit vector, comparable units).
    pub weakest: Vec<f64>,
    /// Predicted std of [`Observability::weakest`] (comparable units).
    pub weakest_std: f64,
    /// The combination is exactly or numerically undetermined.
    pub degenerate: bool,
    /// Some parameter's predicted std exceeds the weak threshold.
    pub weak: bool,
    /// Human-readable description of the weakest combination.
    pub combination: String,
}

/// Result of one static fit (parameters in the caller's units).
#[derive(Debug, Clone)]
pub struct StaticFit {
    /// Sensor model.
    pub model: Model,
    /// Parameters `[sx, sy, sz, bx, by, bz, m1, m2, m3]` (first 6 for diag).
    pub params: Vec<f64>,
    /// Start used by GN/LM (or the method's own solution).
    pub start: Vec<f64>,
    /// `(J^T W J)^-1` with the weights of the noise model (unit weights when estimated:
    /// multiply by `chi2_dof`). NaN when singular.
    pub covariance: DMatrix<f64>,
    /// `|a_k| - g` per dwell, m/s^2 (units of g).
    pub residuals: Vec<f64>,
    /// Predicted std of each residual from the noise model (1 when estimated).
    pub sigma_r: Vec<f64>,
    /// Sum of squared whitened residuals.
    pub cost: f64,
    /// Degrees of freedom `k - p`.
    pub dof: usize,
    /// `cost / dof` (NaN when `dof == 0`).
    pub chi2_dof: f64,
    /// Iterations of GN/LM (0 for the linear methods).
    pub iterations: usize,
    /// The iterative solver met a tolerance (true for the linear methods).
    pub converged: bool,
    /// The noise model was known (true) or estimated from the residuals (false).
    pub noise_known: bool,
    /// Quick observability summary (QR covariance and power iteration).
    pub summary: ObsSummary,
    /// Whitened Jacobian in comparable units (for [`StaticFit::observability`]).
    pub jc: DMatrix<f64>,
    /// Covariance scale used to judge observability (1, or chi2/dof floored at (1e-7 g)^2).
    pub obs_scale: f64,
    /// Note on how the start was obtained (e.g. quadric fallback).
    pub note: String,
}

/// Predicted accuracy in comparable units (scale-relative; biases in g).
#[derive(Debug, Clone, PartialEq)]
pub struct ObsSummary {
    /// Predicted std of each parameter.
    pub std_comparable: Vec<f64>,
    /// Predicted std of the least determined combination (the bound `sqrt(trace C)` when
    /// that is already below the degenerate threshold; the SVD report has the exact value).
    pub weakest_std: f64,
    /// Exactly or numerically undetermined.
    pub degenerate: bool,
    /// Some parameter's predicted std exceeds the weak threshold.
    pub weak: bool,
}

impl StaticFit {
    /// Full observability report (SVD) with the given thresholds.
    pub fn observability(&self, set: &FitSettings) -> Result<Observability> {
        obs_report(&self.jc, self.obs_scale, set)
    }

    /// The weakly determined parameters as text: predicted std (output units, covariance
    /// scaled by chi2/dof when the noise is estimated) and relative std of every parameter
    /// above `weak_std`. Python's `.3g` / `.2g` formatting, so the Python layer can use it
    /// verbatim.
    pub fn weak_text(&self, weak_std: f64) -> String {
        let np = self.params.len();
        let rel = &self.summary.std_comparable;
        let sc = if self.noise_known { 1.0 } else { self.chi2_dof };
        let std: Vec<f64> = (0..np)
            .map(|i| {
                let v = self.covariance[(i, i)] * sc;
                if v >= 0.0 {
                    v.sqrt()
                } else {
                    f64::NAN
                }
            })
            .collect();
        if !std.iter().all(|v| v.is_finite()) {
            return "no redundancy (as many dwells as parameters): the noise and the uncertainty \
                    cannot be estimated"
                .into();
        }
        let parts: Vec<String> = (0..np)
            .filter(|&i| !(rel[i] <= weak_std))
            .map(|i| {
                let unit = if (3..6).contains(&i) { "g" } else { "of scale" };
                format!(
                    "{} +-{} ({} % {unit})",
                    PARAM_NAMES[i],
                    fmt_g(std[i], 3),
                    fmt_g(100.0 * rel[i], 2)
                )
            })
            .collect();
        let mut txt = format!("predicted std {} (1 sigma)", parts.join(", "));
        if self.model != Model::Diag && !rel[6..].iter().all(|r| *r <= weak_std) {
            txt.push_str("; model='diag' (bias + scale) needs fewer attitudes");
        }
        txt
    }
}

/// Python's `format(x, f".{prec}g")` (prec >= 1).
pub fn fmt_g(x: f64, prec: usize) -> String {
    if x.is_nan() {
        return "nan".into();
    }
    if x.is_infinite() {
        return if x > 0.0 { "inf".into() } else { "-inf".into() };
    }
    if x == 0.0 {
        return if x.is_sign_negative() {
            "-0".into()
        } else {
            "0".into()
        };
    }
    let p = prec.max(1);
    // Round once to p significant digits; lay the digits out in fixed or exponent form.
    let e = format!("{:.*e}", p - 1, x.abs());
    let (mant, exp) = e.split_once('e').unwrap_or((e.as_str(), "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    let digits: String = mant.chars().filter(|c| *c != '.').collect();
    let digits = digits.trim_end_matches('0');
    let digits = if digits.is_empty() { "0" } else { digits };
    let mut out = String::with_capacity(p + 8);
    if x < 0.0 {
        out.push('-');
    }
    if -4 <= exp && exp < p as i32 {
        if exp < 0 {
            out.push_str("0.");
            for _ in 0..(-exp - 1) {
                out.push('0');
            }
            out.push_str(digits);
        } else {
            let int_len = exp as usize + 1;
            if digits.len() <= int_len {
                out.push_str(digits);
                for _ in digits.len()..int_len {
                    out.push('0');
                }
            } else {
                out.push_str(&digits[..int_len]);
                out.push('.');
                out.push_str(&digits[int_len..]);
            }
        }
    } else {
        out.push_str(&digits[..1]);
        if digits.len() > 1 {
            out.push('.');
            out.push_str(&digits[1..]);
        }
        out.push('e');
        out.push(if exp < 0 { '-' } else { '+' });
        if exp.abs() < 10 {
            out.push('0');
        }
        out.push_str(&exp.abs().to_string());
    }
    out
}

// ------------------------------------------------------------------------------------------
// Normalised frame

#[derive(Debug, Clone, Copy)]
struct Frame {
    c: [f64; 3],
    s: f64,
}

impl Frame {
    fn to_frame(self, p: &[f64]) -> Vec<f64> {
        let mut q: Vec<f64> = p.iter().map(|v| v / self.s).collect();
        for i in 0..3 {
            q[3 + i] = (p[3 + i] - self.c[i]) / self.s;
        }
        q
    }
    fn unframe(self, q: &[f64]) -> Vec<f64> {
        let mut p: Vec<f64> = q.iter().map(|v| v * self.s).collect();
        for i in 0..3 {
            p[3 + i] = q[3 + i] * self.s + self.c[i];
        }
        p
    }
    fn points(self, means: &[[f64; 3]]) -> Vec<[f64; 3]> {
        means
            .iter()
            .map(|m| {
                [
                    (m[0] - self.c[0]) / self.s,
                    (m[1] - self.c[1]) / self.s,
                    (m[2] - self.c[2]) / self.s,
                ]
            })
            .collect()
    }
    /// Frame in which the model `p` has `K ~ I`, `b = 0`.
    fn from_params(model: Model, p: &[f64], fallback: Frame) -> Frame {
        let k = model.k_matrix(p);
        let d = (k[(0, 0)] * k[(1, 1)] * k[(2, 2)]).abs().cbrt();
        let c = [p[3], p[4], p[5]];
        if d.is_finite() && d > 0.0 && c.iter().all(|v| v.is_finite()) {
            Frame { c, s: d }
        } else {
            fallback
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n == 0 {
        return f64::NAN;
    }
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Centroid frame with a robust scale (median distance from the centroid over g).
fn centroid_frame(means: &[[f64; 3]], g: f64) -> Result<Frame> {
    let n = means.len() as f64;
    let mut c = [0.0; 3];
    for m in means {
        for i in 0..3 {
            c[i] += m[i] / n;
        }
    }
    let d = median(
        means
            .iter()
            .map(|m| ((m[0] - c[0]).powi(2) + (m[1] - c[1]).powi(2) + (m[2] - c[2]).powi(2)).sqrt())
            .collect(),
    );
    if !(d > 0.0) || !d.is_finite() {
        return degenerate(
            "the dwell means are (almost) all identical: the sensor was not turned between dwells",
        );
    }
    Ok(Frame { c, s: d / g })
}

// ------------------------------------------------------------------------------------------
// Linear methods

fn not_ellipsoid(detail: &str) -> CoreError {
    CoreError::Degenerate(format!(
        "the dwell means do not lie on an ellipsoid ({detail}): check that the data are static \
         dwell means of one sensor and that g is in the data's units"
    ))
}

/// Quadric regression `z^2 = x . beta` (9 columns, or 6 for the diagonal model).
fn quadric_beta(pts: &[[f64; 3]], diag: bool) -> Result<Vec<f64>> {
    let y: Vec<f64> = pts.iter().map(|p| p[2] * p[2]).collect();
    if diag {
        let rows: Vec<[f64; 6]> = pts
            .iter()
            .map(|&[x, yv, z]| [x * x, yv * yv, 2.0 * x, 2.0 * yv, 2.0 * z, 1.0])
            .collect();
        Ok(lstsq_rows(&rows, &y)?.to_vec())
    } else {
        let rows: Vec<[f64; 9]> = pts
            .iter()
            .map(|&[x, yv, z]| {
                [
                    x * x,
                    yv * yv,
                    2.0 * x * yv,
                    2.0 * x * z,
                    2.0 * yv * z,
                    2.0 * x,
                    2.0 * yv,
                    2.0 * z,
                    1.0,
                ]
            })
            .collect();
        Ok(lstsq_rows(&rows, &y)?.to_vec())
    }
}

/// Exact recovery (SPEC 1 steps 1-4) in the frame of `pts`; returns frame parameters.
fn quadric_fit(pts: &[[f64; 3]], g: f64, model: Model) -> Result<Vec<f64>> {
    let diag = model == Model::Diag;
    let beta = quadric_beta(pts, diag)?;
    let (qt, lin, c0) = if diag {
        (
            Matrix3::new(-beta[0], 0.0, 0.0, 0.0, -beta[1], 0.0, 0.0, 0.0, 1.0),
            Vector3::new(beta[2], beta[3], beta[4]),
            beta[5],
        )
    } else {
        (
            Matrix3::new(
                -beta[0], -beta[2], -beta[3], -beta[2], -beta[1], -beta[4], -beta[3], -beta[4], 1.0,
            ),
            Vector3::new(beta[5], beta[6], beta[7]),
            beta[8],
        )
    };
    if qt.cholesky().is_none() {
        return Err(not_ellipsoid("the fitted quadric is not positive definite"));
    }
    let qt_inv = qt
        .try_inverse()
        .ok_or_else(|| not_ellipsoid("the fitted quadric is singular"))?;
    let b = qt_inv * lin;
    let den = b.dot(&(qt * b)) + c0;
    if !(den > 0.0) || !den.is_finite() {
        return Err(not_ellipsoid("the fitted quadric has no real points"));
    }
    let q = qt * (g * g / den);
    let q_inv = q
        .try_inverse()
        .ok_or_else(|| not_ellipsoid("the fitted quadric is singular"))?;
    let k = match model {
        Model::Diag => Matrix3::from_diagonal(&Vector3::new(
            q_inv[(0, 0)].sqrt(),
            q_inv[(1, 1)].sqrt(),
            q_inv[(2, 2)].sqrt(),
        )),
        Model::Lower => q_inv
            .cholesky()
            .ok_or_else(|| not_ellipsoid("Q^-1 is not positive definite"))?
            .l(),
        Model::Upper => {
            // K K^T = Q^-1 with K upper: reverse the axes, take Cholesky, reverse back.
            let p = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
            let l = (p * q_inv * p)
                .cholesky()
                .ok_or_else(|| not_ellipsoid("Q^-1 is not positive definite"))?
                .l();
            p * l * p
        }
    };
    let out = model.params_from(&k, &b);
    if out.iter().any(|v| !v.is_finite()) {
        return Err(not_ellipsoid("non-finite recovery"));
    }
    Ok(out)
}

/// The paper's back-substitution (its eqs. 7-10, dropping terms of order M^2).
fn paper_fit(pts: &[[f64; 3]], g: f64, model: Model) -> Result<Vec<f64>> {
    if model == Model::Upper {
        return invalid(
            "method \"linear-paper\" is defined for model \"lower\" (and \"diag\") only",
        );
    }
    let diag = model == Model::Diag;
    let beta = quadric_beta(pts, diag)?;
    let (b1, b2) = (beta[0], beta[1]);
    if !(b1 < 0.0 && b2 < 0.0) {
        return Err(not_ellipsoid(
            "negative squared scale in the paper's back-substitution",
        ));
    }
    let (t11, t22, t33) = ((-b1).sqrt(), (-b2).sqrt(), 1.0);
    let (k21, k31, k32, lin, c0) = if diag {
        (0.0, 0.0, 0.0, [beta[2], beta[3], beta[4]], beta[5])
    } else {
        (
            beta[2] / (t11 * t22),
            beta[3] / (t11 * t33),
            beta[4] / (t22 * t33),
            [beta[5], beta[6], beta[7]],
            beta[8],
        )
    };
    let a = Matrix3::new(
        -t11,
        t11 * k21,
        t11 * k31,
        t22 * k21,
        -t22,
        t22 * k32,
        t33 * k31,
        t33 * k32,
        -t33,
    );
    let rhs = Vector3::new(-lin[0], -lin[1], -lin[2]);
    let bt = a
        .try_inverse()
        .map(|ai| ai * rhs)
        .ok_or_else(|| not_ellipsoid("singular back-substitution"))?;
    let ct = bt.norm_squared()
        - 2.0 * bt[0] * bt[1] * k21
        - 2.0 * bt[0] * bt[2] * k31
        - 2.0 * bt[1] * bt[2] * k32;
    let q = g * g / (ct + c0);
    if !(q > 0.0) || !q.is_finite() {
        return Err(not_ellipsoid(
            "the paper's back-substitution gives no real scale",
        ));
    }
    let r = q.sqrt();
    let (k11, k22, k33) = (r * t11, r * t22, r * t33);
    let (sx, sy, sz) = (1.0 / k11, 1.0 / k22, 1.0 / k33);
    let b = bt * r;
    let mut p = vec![sx, sy, sz, b[0] * sx, b[1] * sy, b[2] * sz];
    if !diag {
        p.extend_from_slice(&[k21 * sy, k31 * sz, k32 * sz]);
    }
    Ok(p)
}

// ------------------------------------------------------------------------------------------
// Norm residual

/// Whitened norm residuals `(|K^-1 (am - b)| - g) / sigma_k` and their Jacobian.
pub struct NormProblem<'a> {
    /// Dwell means (fit frame).
    pub pts: &'a [[f64; 3]],
    /// Reference gravity.
    pub g: f64,
    /// `1 / sigma_k` per dwell.
    pub inv_sigma: &'a [f64],
    /// Sensor model.
    pub model: Model,
    /// Largest admissible `|K_ii|` during the search (guards the runaway to infinite scale).
    pub kmax: f64,
}

impl NormProblem<'_> {
    fn in_range(&self, p: &[f64]) -> Result<()> {
        if p[..3].iter().all(|v| v.abs() <= self.kmax) {
            Ok(())
        } else {
            invalid("scale factors out of range")
        }
    }
}

#[inline]
fn inv_k(model: Model, p: &[f64]) -> Result<Matrix3<f64>> {
    let k = model.k_matrix(p);
    let d = k[(0, 0)] * k[(1, 1)] * k[(2, 2)];
    if !(d.abs() > 0.0) || !d.is_finite() {
        return invalid("singular scale-factor matrix");
    }
    k.try_inverse()
        .ok_or_else(|| CoreError::InvalidInput("singular scale-factor matrix".into()))
}

#[inline]
fn calibrated(t: &Matrix3<f64>, p: &[f64], am: &[f64; 3]) -> Vector3<f64> {
    t * Vector3::new(am[0] - p[3], am[1] - p[4], am[2] - p[5])
}

/// Jacobian row of `(|a| - g) * is`: `d|a|/dK_ij = -w_i a_j`, `d|a|/db_i = -w_i`.
#[inline(always)]
fn jac_row(model: Model, w: &Vector3<f64>, a: &Vector3<f64>, is: f64, row: &mut [f64; 9]) {
    let (w0, w1, w2) = (-w[0] * is, -w[1] * is, -w[2] * is);
    row[0] = w0 * a[0];
    row[1] = w1 * a[1];
    row[2] = w2 * a[2];
    row[3] = w0;
    row[4] = w1;
    row[5] = w2;
    match model {
        Model::Lower => {
            row[6] = w1 * a[0];
            row[7] = w2 * a[0];
            row[8] = w2 * a[1];
        }
        Model::Upper => {
            row[6] = w0 * a[1];
            row[7] = w0 * a[2];
            row[8] = w1 * a[2];
        }
        Model::Diag => {}
    }
}

impl Residuals for NormProblem<'_> {
    fn n_params(&self) -> usize {
        self.model.n_params()
    }
    fn n_residuals(&self) -> usize {
        self.pts.len()
    }
    fn eval(&self, p: &[f64], r: &mut [f64], jac: &mut DMatrix<f64>) -> Result<()> {
        let t = inv_k(self.model, p)?;
        let np = self.model.n_params();
        for (k, am) in self.pts.iter().enumerate() {
            let a = calibrated(&t, p, am);
            let na = a.norm();
            if !(na > 0.0) || !na.is_finite() {
                return invalid("a calibrated dwell has zero or non-finite norm");
            }
            let is = self.inv_sigma[k];
            let w = t.transpose() * a / na;
            r[k] = (na - self.g) * is;
            let mut row = [0.0f64; 9];
            jac_row(self.model, &w, &a, is, &mut row);
            for (j, v) in row.iter().enumerate().take(np) {
                jac[(k, j)] = *v;
            }
        }
        Ok(())
    }
}

impl NormProblem<'_> {
    /// Cost, `J^T r` and the upper triangle of `J^T J` for the first `np <= K` parameters at
    /// `p` (the rank-1 updates unroll when `np` is a compile-time constant).
    #[inline(always)]
    fn accumulate<const K: usize>(
        &self,
        p: &[f64],
        np: usize,
        h: &mut [[f64; K]; K],
        gr: &mut [f64; K],
    ) -> Result<f64> {
        self.in_range(p)?;
        let t = inv_k(self.model, p)?;
        let mut c = 0.0;
        let mut row = [0.0f64; 9];
        for (k, am) in self.pts.iter().enumerate() {
            let a = calibrated(&t, p, am);
            let na = a.norm();
            if !(na > 0.0) || !na.is_finite() {
                return invalid("a calibrated dwell has zero or non-finite norm");
            }
            let is = self.inv_sigma[k];
            let w = t.transpose() * a / na;
            let r = (na - self.g) * is;
            c += r * r;
            jac_row(self.model, &w, &a, is, &mut row);
            for i in 0..np {
                gr[i] += row[i] * r;
                for j in i..np {
                    h[i][j] += row[i] * row[j];
                }
            }
        }
        Ok(c)
    }
}

impl NormalEquations for NormProblem<'_> {
    fn n_params(&self) -> usize {
        self.model.n_params()
    }
    fn n_residuals(&self) -> usize {
        self.pts.len()
    }
    fn cost(&self, p: &[f64]) -> Result<f64> {
        self.in_range(p)?;
        let t = inv_k(self.model, p)?;
        let mut c = 0.0;
        for (k, am) in self.pts.iter().enumerate() {
            let r = (calibrated(&t, p, am).norm() - self.g) * self.inv_sigma[k];
            c += r * r;
        }
        if c.is_finite() {
            Ok(c)
        } else {
            invalid("non-finite cost")
        }
    }
    fn normal(&self, p: &[f64], jtj: &mut DMatrix<f64>, jtr: &mut DVector<f64>) -> Result<f64> {
        let np = self.model.n_params();
        let mut h = [[0.0f64; 9]; 9];
        let mut gr = [0.0f64; 9];
        let c = self.accumulate(p, np, &mut h, &mut gr)?;
        for i in 0..np {
            jtr[i] = gr[i];
            for j in i..np {
                jtj[(i, j)] = h[i][j];
                jtj[(j, i)] = h[i][j];
            }
        }
        Ok(c)
    }
}

impl<const N: usize> NormalEquationsFixed<N> for NormProblem<'_> {
    fn n_residuals(&self) -> usize {
        self.pts.len()
    }
    fn cost(&self, p: &[f64; N]) -> Result<f64> {
        NormalEquations::cost(self, p)
    }
    fn normal(&self, p: &[f64; N], jtj: &mut [[f64; N]; N], jtr: &mut [f64; N]) -> Result<f64> {
        let mut h = [[0.0f64; N]; N];
        let mut gr = [0.0f64; N];
        let c = self.accumulate(p, N, &mut h, &mut gr)?;
        *jtr = gr;
        for i in 0..N {
            for j in i..N {
                jtj[i][j] = h[i][j];
                jtj[j][i] = h[i][j];
            }
        }
        Ok(c)
    }
}

/// LM / GN on the norm problem: the fixed-size solver for 6 and 9 parameters.
fn solve_norm(
    prob: &NormProblem<'_>,
    p: &[f64],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<(Vec<f64>, usize, bool)> {
    fn run<const N: usize>(
        prob: &NormProblem<'_>,
        p: &[f64],
        opt: &NlsOptions,
        lambda0: f64,
    ) -> Result<(Vec<f64>, usize, bool)> {
        let mut p0 = [0.0f64; N];
        p0.copy_from_slice(p);
        let r = solve_normal_fixed::<N, _>(prob, &p0, opt, lambda0)?;
        Ok((r.params.to_vec(), r.iterations, r.converged))
    }
    match p.len() {
        6 => run::<6>(prob, p, opt, lambda0),
        9 => run::<9>(prob, p, opt, lambda0),
        _ => solve_normal(prob, p, opt, lambda0).map(|r| (r.params, r.iterations, r.converged)),
    }
}

/// Residual std per dwell: `sqrt(w^T Sigma_k w)`, `w = K^-T a / |a|` (fit frame variances).
fn residual_sigma(model: Model, p: &[f64], pts: &[[f64; 3]], var: &[[f64; 3]]) -> Result<Vec<f64>> {
    let t = inv_k(model, p)?;
    let mut out = Vec::with_capacity(pts.len());
    for (am, v) in pts.iter().zip(var) {
        let a = calibrated(&t, p, am);
        let na = a.norm();
        let w = t.transpose() * a / na;
        let s2 = w[0] * w[0] * v[0] + w[1] * w[1] * v[1] + w[2] * w[2] * v[2];
        if !(s2 > 0.0) || !s2.is_finite() {
            return invalid(
                "the noise model gives a zero or non-finite residual variance for a dwell \
                 (every dwell needs a positive variance)",
            );
        }
        out.push(s2.sqrt());
    }
    Ok(out)
}

// ------------------------------------------------------------------------------------------
// Observability

/// Describe a combination (comparable units) in parameter names.
pub fn describe_combination(v: &[f64]) -> String {
    let vmax = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    if !(vmax > 0.0) {
        return "(none)".into();
    }
    let imax = v.iter().position(|x| x.abs() == vmax).unwrap_or(0);
    let sign = v[imax].signum();
    let mut idx: Vec<usize> = (0..v.len()).filter(|&i| v[i].abs() >= 0.1 * vmax).collect();
    idx.sort_by(|&a, &b| v[b].abs().total_cmp(&v[a].abs()));
    let mut s = String::new();
    for (n, &i) in idx.iter().enumerate() {
        let c = sign * v[i] / vmax;
        let name = if (3..6).contains(&i) {
            format!("{}/g", PARAM_NAMES[i])
        } else {
            PARAM_NAMES[i].to_string()
        };
        let mag = c.abs();
        let coef = if (mag - 1.0).abs() < 5e-3 {
            String::new()
        } else {
            format!("{mag:.2} ")
        };
        if n == 0 {
            s.push_str(&format!("{}{coef}{name}", if c < 0.0 { "-" } else { "" }));
        } else {
            s.push_str(&format!(
                " {} {coef}{name}",
                if c < 0.0 { "-" } else { "+" }
            ));
        }
    }
    s
}

/// Final evaluation: whitened residuals `rw`, the whitened Jacobian in comparable units
/// `jc` (bias columns times g: biases in units of g) and its normal matrix, in one pass.
#[allow(clippy::needless_range_loop)]
fn final_eval<const N: usize>(
    prob: &NormProblem<'_>,
    p: &[f64],
    rw: &mut [f64],
    jc: &mut DMatrix<f64>,
) -> Result<[[f64; N]; N]> {
    let t = inv_k(prob.model, p)?;
    let mut h = [[0.0f64; N]; N];
    let mut row = [0.0f64; 9];
    for (k, am) in prob.pts.iter().enumerate() {
        let a = calibrated(&t, p, am);
        let na = a.norm();
        if !(na > 0.0) || !na.is_finite() {
            return invalid("a calibrated dwell has zero or non-finite norm");
        }
        let is = prob.inv_sigma[k];
        let w = t.transpose() * a / na;
        rw[k] = (na - prob.g) * is;
        jac_row(prob.model, &w, &a, is, &mut row);
        for v in &mut row[3..6] {
            *v *= prob.g;
        }
        for i in 0..N {
            jc[(k, i)] = row[i];
            for j in i..N {
                h[i][j] += row[i] * row[j];
            }
        }
    }
    for i in 0..N {
        for j in 0..i {
            h[i][j] = h[j][i];
        }
    }
    Ok(h)
}

/// Quick observability summary from the covariance of the comparable normal matrix `h`;
/// returns the summary and the unscaled comparable covariance.
fn obs_summary<const N: usize>(
    h: &[[f64; N]; N],
    scale: f64,
    set: &FitSettings,
) -> (ObsSummary, Option<DMatrix<f64>>) {
    let sc = if scale.is_finite() { scale } else { 0.0 };
    match covariance_normal_fixed(h, SINGULAR_RTOL) {
        Some(c) => {
            let std: Vec<f64> = (0..N).map(|i| (c[i][i] * sc).sqrt()).collect();
            // lambda_max(C) <= trace(C): only when the cheap bound is inconclusive, iterate.
            let tr: f64 = (0..N).map(|i| c[i][i]).sum();
            let lam = if (tr * sc).sqrt() <= set.degenerate_std {
                tr
            } else {
                top_eigen_fixed(&c, 500).0
            };
            let wstd = (lam * sc).sqrt();
            let sum = ObsSummary {
                weak: std.iter().any(|s| !(*s <= set.weak_std)),
                degenerate: !(wstd <= set.degenerate_std),
                std_comparable: std,
                weakest_std: wstd,
            };
            (sum, Some(DMatrix::from_fn(N, N, |i, j| c[i][j])))
        }
        None => (
            ObsSummary {
                std_comparable: vec![f64::INFINITY; N],
                weakest_std: f64::INFINITY,
                degenerate: true,
                weak: true,
            },
            None,
        ),
    }
}

/// Final residuals, cost and observability summary (dispatch on the parameter count).
fn finish(
    prob: &NormProblem<'_>,
    p: &[f64],
    noise_known: bool,
    set: &FitSettings,
    rw: &mut [f64],
    jc: &mut DMatrix<f64>,
) -> Result<(f64, f64, ObsSummary, Option<DMatrix<f64>>)> {
    fn run<const N: usize>(
        prob: &NormProblem<'_>,
        p: &[f64],
        noise_known: bool,
        set: &FitSettings,
        rw: &mut [f64],
        jc: &mut DMatrix<f64>,
    ) -> Result<(f64, f64, ObsSummary, Option<DMatrix<f64>>)> {
        let h = final_eval::<N>(prob, p, rw, jc)?;
        let cost: f64 = rw.iter().map(|v| v * v).sum();
        let n = rw.len();
        let chi2_dof = if n > N {
            cost / (n - N) as f64
        } else {
            f64::NAN
        };
        // With the noise estimated, a (near) perfect fit would predict zero uncertainty and
        // hide a singular design: floor the noise at 1e-7 g for the observability judgement.
        let scale = if noise_known {
            1.0
        } else {
            chi2_dof.max((1e-7 * prob.g).powi(2))
        };
        let (summary, cov) = obs_summary::<N>(&h, scale, set);
        Ok((cost, scale, summary, cov))
    }
    match p.len() {
        6 => run::<6>(prob, p, noise_known, set, rw, jc),
        _ => run::<9>(prob, p, noise_known, set, rw, jc),
    }
}

/// Full observability report (SVD of the comparable whitened Jacobian `jc`).
pub fn obs_report(jc: &DMatrix<f64>, scale: f64, set: &FitSettings) -> Result<Observability> {
    let np = jc.ncols();
    let svd = svd_report(jc)?;
    let smax = svd.s[0];
    let smin = svd.s[np - 1];
    let exact = !(smin > SINGULAR_RTOL * smax);
    let sc = if scale.is_finite() { scale } else { 0.0 };
    let weakest: Vec<f64> = (0..np).map(|i| svd.v[(i, np - 1)]).collect();
    let weakest_std = if exact {
        f64::INFINITY
    } else {
        sc.sqrt() / smin
    };
    let std_c: Vec<f64> = match svd.covariance().filter(|_| !exact) {
        Some(c) => (0..np).map(|i| (c[(i, i)] * sc).sqrt()).collect(),
        None => vec![f64::INFINITY; np],
    };
    Ok(Observability {
        condition: svd.condition(),
        singular_values: svd.s,
        combination: describe_combination(&weakest),
        weak: std_c.iter().any(|s| !(*s <= set.weak_std)),
        std_comparable: std_c,
        weakest,
        weakest_std,
        degenerate: exact || !(weakest_std <= set.degenerate_std),
    })
}

fn degenerate_message(obs: &Observability, model: Model, n: usize, sum: &ObsSummary) -> String {
    let how = if obs.weakest_std.is_infinite() || sum.weakest_std.is_infinite() {
        "exactly singular design".to_string()
    } else {
        format!(
            "predicted std {:.2e} in relative units (scale factors relative, biases in g), \
             condition number {:.2e}",
            obs.weakest_std, obs.condition
        )
    };
    let s = format!(
        "the {n} dwells cannot determine {} of model {:?} ({how}). Add poses with different \
         gravity directions (tilts in both axes at once, larger angles, ideally the whole \
         sphere), or fit model=\"diag\"",
        obs.combination,
        model.name()
    );
    s
}

// ------------------------------------------------------------------------------------------
// The fit

fn validate(means: &[[f64; 3]], g: f64, noise: &Noise, model: Model) -> Result<()> {
    if !(g > 0.0) || !g.is_finite() {
        return invalid(format!(
            "g must be a positive, finite reference gravity (e.g. 9.81 m/s^2); got {g}"
        ));
    }
    for (k, m) in means.iter().enumerate() {
        if m.iter().any(|v| !v.is_finite()) {
            return invalid(format!("dwell {k} has a NaN or infinite mean"));
        }
    }
    let p = model.n_params();
    if means.len() < p {
        return degenerate(format!(
            "{} dwells cannot determine the {p} parameters of model {:?}: need at least {p} \
             dwells (more to estimate the noise){}",
            means.len(),
            model.name(),
            if p > 6 && means.len() >= 6 {
                "; model \"diag\" (bias + scale) needs 6"
            } else {
                ""
            }
        ));
    }
    if let Noise::Known(v) = noise {
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
    Ok(())
}

/// Fit the static model to `k` dwell means.
pub fn fit_static(
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise,
    set: &FitSettings,
) -> Result<StaticFit> {
    let model = set.model;
    validate(means, g, noise, model)?;
    let np = model.n_params();
    let n = means.len();
    let f0 = centroid_frame(means, g)?;
    let mut note = String::new();
    let mut start_err: Option<CoreError> = None;

    // 1. Start / linear solution (raw units).
    let start: Vec<f64> = match (&set.start, set.method) {
        (Some(s), Method::GaussNewton | Method::Lm) => {
            if s.len() != np {
                return invalid(format!(
                    "start has {} values; model {:?} has {np} parameters",
                    s.len(),
                    model.name()
                ));
            }
            if s.iter().any(|v| !v.is_finite()) {
                return invalid("start values must be finite");
            }
            s.clone()
        }
        (Some(_), _) => {
            return invalid("start= is only used by method \"gauss-newton\" or \"lm\"");
        }
        (None, Method::LinearPaper) => {
            let fs = Frame {
                c: [0.0; 3],
                s: median(
                    means
                        .iter()
                        .map(|m| (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt())
                        .collect(),
                ) / g,
            };
            match paper_fit(&fs.points(means), g, model) {
                Ok(p) => fs.unframe(&p),
                Err(e @ CoreError::InvalidInput(_)) => return Err(e),
                Err(e) => {
                    start_err = Some(e);
                    fallback_start(means, g, model, f0)?
                }
            }
        }
        (None, _) => match quadric_fit(&f0.points(means), g, model) {
            Ok(p) => f0.unframe(&p),
            Err(e) => {
                start_err = Some(e);
                fallback_start(means, g, model, f0)?
            }
        },
    };
    if let Some(e) = &start_err {
        note = format!("linear solution failed ({e}); diagnosed from a bias+scale start");
    }

    // 2. Fit frame with K ~ I, b ~ 0.
    let f1 = Frame::from_params(model, &start, f0);
    let pts = f1.points(means);
    let var_f: Option<Vec<[f64; 3]>> = match noise {
        Noise::Known(v) => {
            let s2 = f1.s * f1.s;
            Some(
                v.iter()
                    .map(|r| [r[0] / s2, r[1] / s2, r[2] / s2])
                    .collect(),
            )
        }
        Noise::Estimated => None,
    };
    let mut p = f1.to_frame(&start);
    let sig = |p: &[f64]| -> Result<Vec<f64>> {
        match &var_f {
            Some(v) => residual_sigma(model, p, &pts, v),
            None => Ok(vec![1.0; n]),
        }
    };
    let mut sigma = match sig(&p) {
        Ok(s) => s,
        Err(e) if start_err.is_none() => return Err(e),
        Err(_) => vec![1.0; n],
    };

    // 3. Iterate (GN / LM; also the fallback diagnosis of a failed linear solution).
    let iterate = matches!(set.method, Method::GaussNewton | Method::Lm) || start_err.is_some();
    // A user start may be far off (the paper's e0): damp like solve_nls; the linear start is
    // already close to the optimum, so start nearly undamped.
    let lambda0 = if set.start.is_some() { 1e-3 } else { 1e-8 };
    let mut iterations = 0;
    let mut converged = true;
    // Runaway guard: the norm cost tends to zero as K -> infinity (every dwell mapped to one
    // vector of norm g). Scale factors are bounded at RUNAWAY x the data's spread scale.
    let kmax = RUNAWAY * 10.0 * f0.s / f1.s;
    if iterate {
        let opt = NlsOptions {
            max_iter: set.max_iter,
            gauss_newton: set.method == Method::GaussNewton && start_err.is_none(),
            ftol: 1e-10,
            xtol: 1e-10,
            gtol: 1e-9,
        };
        for pass in 0..3 {
            let inv: Vec<f64> = sigma.iter().map(|s| 1.0 / s).collect();
            let prob = NormProblem {
                pts: &pts,
                g,
                inv_sigma: &inv,
                model,
                kmax,
            };
            let (pr, its, conv) = match solve_norm(&prob, &p, &opt, lambda0) {
                Ok(r) => r,
                Err(e) => return Err(start_err.unwrap_or(e)),
            };
            iterations += its;
            converged = conv;
            p = pr;
            if var_f.is_none() || !converged || pass == 2 {
                break;
            }
            let s_new = sig(&p)?;
            let change = s_new
                .iter()
                .zip(&sigma)
                .map(|(a, b)| (a / b - 1.0).abs())
                .fold(0.0, f64::max);
            if change < 1e-2 {
                break;
            }
            sigma = s_new;
        }
    }

    if iterate && p[..3].iter().any(|v| v.abs() * f1.s > RUNAWAY * f0.s) {
        if let Some(e) = start_err {
            return Err(e);
        }
        return Err(CoreError::NotConverged(format!(
            "the fit ran away towards infinite scale factors (the norm cost tends to zero when \
             every dwell is mapped to one vector): the {n} dwells span too small a part of the \
             sphere for their noise to have a finite best fit near the start. Use the default \
             start (exact quadric solution), larger tilts or more poses, or model=\"diag\""
        )));
    }

    // 4. Residuals, covariance, observability at the final parameters.
    let inv: Vec<f64> = sigma.iter().map(|s| 1.0 / s).collect();
    let prob = NormProblem {
        pts: &pts,
        g,
        inv_sigma: &inv,
        model,
        kmax: f64::INFINITY,
    };
    let mut rw = vec![0.0; n];
    let mut jc = DMatrix::<f64>::zeros(n, np);
    let noise_known = var_f.is_some();
    let (cost, scale, summary, cov_c) = finish(&prob, &p, noise_known, set, &mut rw, &mut jc)?;
    let dof = n - np;
    let chi2_dof = if dof > 0 { cost / dof as f64 } else { f64::NAN };
    let residuals: Vec<f64> = rw.iter().zip(&sigma).map(|(r, s)| r * s).collect();
    let s2 = f1.s * f1.s;

    if summary.degenerate && (set.raise_degenerate || start_err.is_some()) {
        let o = obs_report(&jc, scale, set)?;
        return degenerate(degenerate_message(&o, model, n, &summary));
    }
    let mut cov_frame = match cov_c {
        Some(c) => c,
        None => DMatrix::from_element(np, np, f64::NAN),
    };
    for i in 0..np {
        for j in 0..np {
            let f = if (3..6).contains(&i) { g } else { 1.0 }
                * if (3..6).contains(&j) { g } else { 1.0 };
            cov_frame[(i, j)] *= f;
        }
    }
    if let Some(e) = start_err {
        // The design is determined, so the linear solution failed because of the data.
        return Err(e);
    }
    let params = f1.unframe(&p);
    if params.iter().any(|v| !v.is_finite()) {
        return Err(CoreError::NotConverged(
            "the fit produced non-finite parameters".into(),
        ));
    }
    Ok(StaticFit {
        model,
        params,
        start,
        covariance: cov_frame * s2,
        residuals,
        sigma_r: sigma,
        cost,
        dof,
        chi2_dof,
        iterations,
        converged,
        noise_known,
        summary,
        jc,
        obs_scale: scale,
        note,
    })
}

/// Bias + scale start used to diagnose designs where the 9-term quadric fails.
fn fallback_start(means: &[[f64; 3]], g: f64, model: Model, f0: Frame) -> Result<Vec<f64>> {
    let d = match quadric_fit(&f0.points(means), g, Model::Diag) {
        Ok(p) => f0.unframe(&p),
        Err(_) => {
            vec![f0.s, f0.s, f0.s, f0.c[0], f0.c[1], f0.c[2]]
        }
    };
    let mut p = d;
    p.resize(model.n_params(), 0.0);
    Ok(p)
}

// ------------------------------------------------------------------------------------------
// Batch

/// One row of a batch fit.
#[derive(Debug, Clone)]
pub struct BatchRow {
    /// Parameters (NaN when the fit failed).
    pub params: Vec<f64>,
    /// Std of each parameter (covariance scaled by chi2/dof when the noise is estimated).
    pub std: Vec<f64>,
    /// RMS of `|a| - g`.
    pub rms: f64,
    /// GN/LM iterations.
    pub iterations: usize,
    /// 0 ok, 1 degenerate data, 2 not converged / diverged, 3 invalid input.
    pub status: u8,
}

/// Fit `b` independent sessions of `n` dwells each (`means` row-major `b x n x 3`), in
/// parallel. `g` has 1 or `b` values; `sigma` (std of each dwell mean per axis, output
/// units) is shared by all sessions, `None` estimates it.
pub fn fit_batch(
    means: &[f64],
    b: usize,
    n: usize,
    g: &[f64],
    sigma: Option<f64>,
    set: &FitSettings,
) -> Result<Vec<BatchRow>> {
    if means.len() != b * n * 3 {
        return invalid(format!(
            "means has {} values for ({b}, {n}, 3)",
            means.len()
        ));
    }
    if g.len() != 1 && g.len() != b {
        return invalid(format!("g must have 1 or {b} values; got {}", g.len()));
    }
    if let Some(s) = sigma {
        if !(s > 0.0) || !s.is_finite() {
            return invalid(format!("sigma must be positive and finite; got {s}"));
        }
    }
    let np = set.model.n_params();
    let rows = (0..b)
        .into_par_iter()
        .map(|i| {
            let pts: Vec<[f64; 3]> = (0..n)
                .map(|k| {
                    let o = (i * n + k) * 3;
                    [means[o], means[o + 1], means[o + 2]]
                })
                .collect();
            let gi = if g.len() == 1 { g[0] } else { g[i] };
            let noise = match sigma {
                Some(s) => Noise::Known(vec![[s * s; 3]; n]),
                None => Noise::Estimated,
            };
            match fit_static(&pts, gi, &noise, set) {
                Ok(f) => {
                    let sc = if f.noise_known { 1.0 } else { f.chi2_dof };
                    let std = (0..np)
                        .map(|j| (f.covariance[(j, j)] * sc).sqrt())
                        .collect();
                    let rms = (f.residuals.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
                    BatchRow {
                        params: f.params,
                        std,
                        rms,
                        iterations: f.iterations,
                        status: if f.converged { 0 } else { 2 },
                    }
                }
                Err(e) => BatchRow {
                    params: vec![f64::NAN; np],
                    std: vec![f64::NAN; np],
                    rms: f64::NAN,
                    iterations: 0,
                    status: match e {
                        CoreError::Degenerate(_) => 1,
                        CoreError::NotConverged(_) => 2,
                        CoreError::InvalidInput(_) => 3,
                    },
                },
            }
        })
        .collect();
    Ok(rows)
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
    let t = km
        .try_inverse()
        .filter(|t| t.iter().all(|v| v.is_finite()))
        .ok_or_else(|| CoreError::InvalidInput("the model's K matrix is singular".into()))?;
    let n = samples.nrows();
    let mut out = vec![0.0; 3 * n];
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
    Ok(out)
}

// ------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    const TRUTH: [f64; 9] = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03];
    const G: f64 = 9.80665;

    /// Deterministic pseudo-random numbers in [-1, 1].
    fn lcg(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }

    fn simulate(model: Model, p: &[f64], n: usize, tilt_deg: f64, seed: u64) -> Vec<[f64; 3]> {
        let k = model.k_matrix(p);
        let mut s = seed;
        (0..n)
            .map(|_| {
                let tx = lcg(&mut s) * tilt_deg.to_radians();
                let ty = lcg(&mut s) * tilt_deg.to_radians();
                let a = Vector3::new(
                    -G * ty.sin(),
                    G * tx.sin() * ty.cos(),
                    G * tx.cos() * ty.cos(),
                );
                let am = k * a + Vector3::new(p[3], p[4], p[5]);
                [am[0], am[1], am[2]]
            })
            .collect()
    }

    fn maxerr(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn quadric_and_lm_recover_truth_exactly() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 1);
        for method in [Method::Quadric, Method::Lm, Method::GaussNewton] {
            let f = fit_static(
                &m,
                G,
                &Noise::Estimated,
                &FitSettings::new(Model::Lower, method),
            )
            .unwrap();
            assert!(
                maxerr(&f.params, &TRUTH) < 1e-9,
                "{method:?} {:?}",
                f.params
            );
        }
    }

    #[test]
    fn paper_method_is_biased_by_the_dropped_terms() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 2);
        let f = fit_static(
            &m,
            G,
            &Noise::Estimated,
            &FitSettings::new(Model::Lower, Method::LinearPaper),
        )
        .unwrap();
        let e = maxerr(&f.params, &TRUTH);
        assert!(e > 1e-5 && e < 1e-2, "paper error {e}");
    }

    #[test]
    fn upper_and_diag_models_round_trip() {
        let up = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, -0.02, 0.03];
        let m = simulate(Model::Upper, &up, 15, 90.0, 3);
        let f = fit_static(
            &m,
            G,
            &Noise::Estimated,
            &FitSettings::new(Model::Upper, Method::Lm),
        )
        .unwrap();
        assert!(maxerr(&f.params, &up) < 1e-9);
        let m = simulate(Model::Diag, &up[..6], 8, 90.0, 4);
        let f = fit_static(
            &m,
            G,
            &Noise::Estimated,
            &FitSettings::new(Model::Diag, Method::Lm),
        )
        .unwrap();
        assert!(maxerr(&f.params, &up[..6]) < 1e-9);
    }

    #[test]
    fn raw_counts_scale_is_handled() {
        let p = [
            414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0,
        ];
        let m = simulate(Model::Lower, &p, 30, 90.0, 5);
        let f = fit_static(
            &m,
            G,
            &Noise::Estimated,
            &FitSettings::new(Model::Lower, Method::Lm),
        )
        .unwrap();
        for (a, b) in f.params.iter().zip(&p) {
            assert!(
                (a - b).abs() < 1e-7 * b.abs().max(1.0),
                "{a} vs {b}: {:?} {}",
                f.params,
                f.note
            );
        }
    }

    #[test]
    fn two_plane_procedure_is_exactly_singular() {
        // Hold tx = 10 deg and sweep ty, then hold ty = 10 deg and sweep tx.
        let k = Model::Lower.k_matrix(&TRUTH);
        let mut m = Vec::new();
        for i in 0..10 {
            for (tx, ty) in [
                (10.0f64, -30.0 + 6.0 * i as f64),
                (-30.0 + 6.0 * i as f64, 10.0),
            ] {
                let (tx, ty) = (tx.to_radians(), ty.to_radians());
                let a = Vector3::new(
                    -G * ty.sin(),
                    G * tx.sin() * ty.cos(),
                    G * tx.cos() * ty.cos(),
                );
                let am = k * a + Vector3::new(TRUTH[3], TRUTH[4], TRUTH[5]);
                m.push([am[0], am[1], am[2]]);
            }
        }
        let e = fit_static(
            &m,
            G,
            &Noise::Estimated,
            &FitSettings::new(Model::Lower, Method::Lm),
        )
        .unwrap_err();
        match e {
            CoreError::Degenerate(msg) => {
                assert!(msg.contains("m1") || msg.contains("m2"), "{msg}")
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn bad_input_is_reported() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 6);
        let set = FitSettings::new(Model::Lower, Method::Lm);
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
        assert!(matches!(
            fit_static(&bad, G, &Noise::Estimated, &set),
            Err(CoreError::InvalidInput(_))
        ));
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

    #[test]
    fn batch_matches_single_fits() {
        let mut all = Vec::new();
        for s in 0..4 {
            for r in simulate(Model::Lower, &TRUTH, 20, 60.0, 10 + s) {
                all.extend_from_slice(&r);
            }
        }
        let set = FitSettings::new(Model::Lower, Method::Lm);
        let rows = fit_batch(&all, 4, 20, &[G], Some(1e-3), &set).unwrap();
        assert!(rows
            .iter()
            .all(|r| r.status == 0 && maxerr(&r.params, &TRUTH) < 1e-9));
    }

    #[test]
    fn fmt_g_matches_python() {
        // format(x, f".{p}g") in CPython, including exact ties (round half to even).
        for (x, p, want) in [
            (0.000123456, 3, "0.000123"),
            (1.5e-5, 2, "1.5e-05"),
            (123456.0, 3, "1.23e+05"),
            (99.95, 3, "100"),
            (0.0001, 2, "0.0001"),
            (1e20, 3, "1e+20"),
            (999.5, 3, "1e+03"),
            (0.125, 2, "0.12"),
            (2.5, 1, "2"),
            (0.0185, 2, "0.018"),
            (-0.00796, 3, "-0.00796"),
            (1.0, 3, "1"),
        ] {
            assert_eq!(fmt_g(x, p), want, "{x} .{p}g");
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
}

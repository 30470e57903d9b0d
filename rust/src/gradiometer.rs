//! Gravity gradiometer per-startup bias by platform azimuth rotation.
//!
//! Two parts, both pure:
//!
//! - The start-up estimator. At azimuth `theta_k` the two channel averages are
//!   `y_k = b + R(2 theta_k) gamma (+ bdot (t_k - t_ref)) + e_k` with
//!   `R(2t) = [[cos 2t, sin 2t], [-sin 2t, cos 2t]]`, `gamma = (I, C)` in the navigation frame.
//!   [`fit_startup_bias`] solves it by weighted linear least squares (exact for unbalanced
//!   angle sets), reports the unit covariance and names what a singular design cannot
//!   separate; [`startup_gain`], [`azimuth_error_covariance`] and [`balanced_variance`] give the
//!   predictions used for sequence design.
//! - The 2-omega demodulation of raw rotating-accelerometer streams. From `(N, 4)` samples
//!   `a1..a4` and the spin phase `phi` (rad) of accelerometer 1, [`demodulate`] forms
//!   `d = (a1 + a3) - (a2 + a4) = 4R [I sin 2phi - C cos 2phi] + ...` and fits, per dwell over
//!   whole revolutions, `d = c0 + c1 cos phi + s1 sin phi + c2 cos 2phi + s2 sin 2phi` by least
//!   squares, so `I = s2 / 4R` and `C = -c2 / 4R`. The 1-omega terms absorb what scale mismatch
//!   lets through of a tilt (horizontal specific force), the constant the accelerometer offsets.
//!
//! Parameter order everywhere: `[bias_I, bias_C, I, C, (drift_I, drift_C)]`.

use crate::dwell::Sample;
use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lsq::{cholesky_inverse_small, cholesky_small, lstsq_qr, svd_report};
use nalgebra::DMatrix;
use ndarray::ArrayView2;
use rayon::prelude::*;
use std::f64::consts::TAU;

/// One Eotvos in s^-2.
pub const EOTVOS: f64 = 1e-9;

/// Parameter names in covariance order.
pub const PARAM_NAMES: [&str; 6] = ["bias_I", "bias_C", "I", "C", "drift_I", "drift_C"];

/// Relative singular-value threshold below which a design direction is unobservable.
const RCOND: f64 = 1e-10;

// ------------------------------------------------------------------------------------------
// Start-up estimator
// ------------------------------------------------------------------------------------------

/// Result of the start-up least squares.
#[derive(Debug, Clone, PartialEq)]
pub struct StartupFit {
    /// `[bias_I, bias_C, I, C, (drift_I, drift_C)]`, channel units (E; drift E/s).
    pub params: Vec<f64>,
    /// `(A^T W A)^-1`, row-major `p x p`: the covariance when the dwell stds are the true ones.
    pub unit_cov: Vec<f64>,
    /// Residuals `y_k - model_k`, `(m, 2)`, channel units.
    pub residuals: Vec<[f64; 2]>,
    /// Weighted residual sum of squares `sum |r_k|^2 / s_k^2`.
    pub rss: f64,
    /// Degrees of freedom `2m - p`.
    pub dof: usize,
    /// Condition number of the column-scaled, weighted design.
    pub condition: f64,
}

/// Weighted, column-unscaled design rows `(2m, p)` row-major and the per-row weights `1/s_k`.
fn design(theta: &[f64], t: Option<&[f64]>, t_ref: f64) -> (Vec<f64>, usize) {
    let p = if t.is_some() { 6 } else { 4 };
    let m = theta.len();
    let mut a = vec![0.0; 2 * m * p];
    for (k, &th) in theta.iter().enumerate() {
        let (s, c) = (2.0 * th).sin_cos();
        let r1 = &mut a[(2 * k) * p..(2 * k + 1) * p];
        r1[0] = 1.0;
        r1[2] = c;
        r1[3] = s;
        if let Some(t) = t {
            r1[4] = t[k] - t_ref;
        }
        let r2 = &mut a[(2 * k + 1) * p..(2 * k + 2) * p];
        r2[1] = 1.0;
        r2[2] = -s;
        r2[3] = c;
        if let Some(t) = t {
            r2[5] = t[k] - t_ref;
        }
    }
    (a, p)
}

fn check_inputs(theta: &[f64], t: Option<&[f64]>, t_ref: f64, dwell_std: &[f64]) -> Result<()> {
    let m = theta.len();
    if m == 0 {
        return invalid("no azimuths given");
    }
    if let Some(k) = theta.iter().position(|v| !v.is_finite()) {
        return invalid(format!("azimuth {k} is NaN or inf"));
    }
    if dwell_std.len() != m {
        return invalid(format!(
            "dwell std has {} values for {m} azimuths",
            dwell_std.len()
        ));
    }
    if let Some(k) = dwell_std.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
        return invalid(format!(
            "noise std of dwell {k} must be positive and finite; got {}",
            dwell_std[k]
        ));
    }
    if let Some(t) = t {
        if t.len() != m {
            return invalid(format!("t has {} values for {m} azimuths", t.len()));
        }
        if let Some(k) = t.iter().position(|v| !v.is_finite()) {
            return invalid(format!("time of dwell {k} is NaN or inf"));
        }
        if !t_ref.is_finite() {
            return invalid("reference time t_ref must be finite");
        }
    }
    Ok(())
}

/// Explain why a design is singular, in user terms.
fn explain_singular(theta: &[f64], t: Option<&[f64]>, null: &[f64]) -> String {
    let m = theta.len();
    let p = null.len();
    let u0 = (2.0 * theta[0]).sin_cos();
    let same_2theta = theta.iter().all(|&th| {
        let u = (2.0 * th).sin_cos();
        (u.0 - u0.0).abs() < 1e-9 && (u.1 - u0.1).abs() < 1e-9
    });
    if same_2theta {
        let list: Vec<String> = theta
            .iter()
            .map(|v| format!("{:.6}", v.to_degrees()))
            .collect();
        return format!(
            "azimuths [{}] deg are all equal modulo 180 deg: a horizontal gradient looks the \
             same at theta and theta + 180 deg, so the per-startup bias cannot be separated from \
             the gradient. Add an azimuth 45..135 deg away (0/90 is the minimal set; 0/45/90/135 \
             is optimal for four dwells)",
            list.join(", ")
        );
    }
    if let Some(t) = t {
        if t.iter()
            .all(|&v| (v - t[0]).abs() <= 1e-12 * v.abs().max(1.0))
        {
            return "all dwells have the same time: a bias drift is not observable (give the \
                    dwell mid times, or fit without drift)"
                .to_string();
        }
        if m < 3 {
            return format!(
                "{m} dwells give {} equations for 6 unknowns (bias, gradient, drift): the drift \
                 model needs at least 3 dwells, e.g. the return-to-start sequence 0/90/0",
                2 * m
            );
        }
    }
    let vmax = null.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let names: Vec<&str> = (0..p)
        .filter(|&j| null[j].abs() > 0.1 * vmax)
        .map(|j| PARAM_NAMES[j])
        .collect();
    format!(
        "the azimuth/time design cannot separate {}: change the azimuth set or the dwell order",
        names.join(", ")
    )
}

/// Column-scaled weighted design, its SVD report and the scales, or a Degenerate error.
fn analyse(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
) -> Result<(Vec<f64>, usize, Vec<f64>, crate::lsq::SvdReport)> {
    check_inputs(theta, t, t_ref, dwell_std)?;
    let m = theta.len();
    let (mut a, p) = design(theta, t, t_ref);
    for k in 0..m {
        let w = 1.0 / dwell_std[k];
        for v in &mut a[2 * k * p..(2 * k + 2) * p] {
            *v *= w;
        }
    }
    if 2 * m < p {
        let null = vec![0.0; p];
        return degenerate(if t.is_some() {
            explain_singular(theta, t, &null)
        } else {
            format!(
                "one dwell gives 2 equations for 4 unknowns (bias and gradient): rotate the \
                 platform to at least two azimuths 90 deg apart (e.g. 0/90) [azimuth {:.6} deg]",
                theta[0].to_degrees()
            )
        });
    }
    let mut scale = vec![0.0; p];
    for r in 0..2 * m {
        for j in 0..p {
            scale[j] += a[r * p + j] * a[r * p + j];
        }
    }
    for s in scale.iter_mut() {
        *s = s.sqrt();
    }
    if let Some(j) = scale.iter().position(|s| s.is_nan() || *s <= 0.0) {
        // Only the drift columns can vanish (all t equal t_ref).
        let mut null = vec![0.0; p];
        null[j] = 1.0;
        return degenerate(explain_singular(theta, t, &null));
    }
    let js = DMatrix::<f64>::from_fn(2 * m, p, |r, j| a[r * p + j] / scale[j]);
    let rep = svd_report(&js)?;
    let nd = rep.null_directions(RCOND);
    if let Some(&i) = nd.first() {
        let null: Vec<f64> = (0..p).map(|j| rep.v[(j, i)]).collect();
        return degenerate(explain_singular(theta, t, &null));
    }
    Ok((a, p, scale, rep))
}

/// Unit covariance `(A^T W A)^-1` (row-major `p x p`) and condition number of a design.
pub fn startup_unit_cov(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
) -> Result<(Vec<f64>, usize, f64)> {
    let (_, p, scale, rep) = analyse(theta, t, t_ref, dwell_std)?;
    let cov = unscaled_cov(&rep, &scale, p)?;
    Ok((cov, p, rep.condition()))
}

fn unscaled_cov(rep: &crate::lsq::SvdReport, scale: &[f64], p: usize) -> Result<Vec<f64>> {
    let cs = rep
        .covariance()
        .ok_or_else(|| CoreError::Degenerate("singular start-up design".into()))?;
    let mut cov = vec![0.0; p * p];
    for i in 0..p {
        for j in 0..p {
            cov[i * p + j] = cs[(i, j)] / (scale[i] * scale[j]);
        }
    }
    Ok(cov)
}

/// Weighted least squares for bias, gradient (and drift).
///
/// `theta` azimuths (rad), `y` channel averages `(m, 2)`, `t` dwell times (s; `Some` turns the
/// drift model on, referenced to `t_ref`), `dwell_std` the noise std of each average (use all
/// ones for an unweighted fit; the covariance is then per unit variance).
pub fn fit_startup_bias(
    theta: &[f64],
    y: &[[f64; 2]],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
) -> Result<StartupFit> {
    let m = theta.len();
    if y.len() != m {
        return invalid(format!("outputs have {} rows for {m} azimuths", y.len()));
    }
    if let Some(k) = y
        .iter()
        .position(|r| !(r[0].is_finite() && r[1].is_finite()))
    {
        return invalid(format!("outputs of dwell {k} contain NaN or inf"));
    }
    let (a, p, scale, rep) = analyse(theta, t, t_ref, dwell_std)?;
    let mut b = vec![0.0; 2 * m];
    for k in 0..m {
        b[2 * k] = y[k][0] / dwell_std[k];
        b[2 * k + 1] = y[k][1] / dwell_std[k];
    }
    let params = lstsq_qr(&a, 2 * m, p, &b)?;
    let unit_cov = unscaled_cov(&rep, &scale, p)?;
    let condition = rep.condition();
    let (araw, _) = design(theta, t, t_ref);
    let mut residuals = Vec::with_capacity(m);
    let mut rss = 0.0;
    for k in 0..m {
        let mut r = [y[k][0], y[k][1]];
        for (c, rc) in r.iter_mut().enumerate() {
            let row = &araw[(2 * k + c) * p..(2 * k + c + 1) * p];
            *rc -= row.iter().zip(&params).map(|(x, q)| x * q).sum::<f64>();
        }
        rss += (r[0] * r[0] + r[1] * r[1]) / (dwell_std[k] * dwell_std[k]);
        residuals.push(r);
    }
    Ok(StartupFit {
        params,
        unit_cov,
        residuals,
        rss,
        dof: 2 * m - p,
        condition,
    })
}

/// The start-up estimate in channel units: [`fit_startup_bias`] with the covariance scaled to
/// the noise (given, or estimated from the residuals).
#[derive(Debug, Clone, PartialEq)]
pub struct StartupBias {
    /// `[bias_I, bias_C, I, C, (drift_I, drift_C)]` (E; drift E/s).
    pub params: Vec<f64>,
    /// Covariance (row-major `p x p`); NaN when the noise was not given and the design has no
    /// redundancy (`dof = 0`) to estimate it.
    pub covariance: Vec<f64>,
    /// Square roots of the covariance diagonal.
    pub std: Vec<f64>,
    /// Residuals `y_k - model_k`, `(m, 2)`.
    pub residuals: Vec<[f64; 2]>,
    /// `(A^T W A)^-1` (row-major `p x p`).
    pub unit_cov: Vec<f64>,
    /// Noise std of each average used for the covariance (given or estimated); `None` when
    /// it could not be estimated.
    pub sigma: Option<Vec<f64>>,
    /// True when `sigma` was estimated from the residuals.
    pub sigma_estimated: bool,
    /// Degrees of freedom `2m - p`.
    pub dof: usize,
    /// Condition number of the column-scaled, weighted design.
    pub condition: f64,
    /// Std of the independent azimuth errors allowed for, rad (0: none).
    pub sigma_theta: f64,
    /// Part of `covariance` caused by the azimuth errors (row-major `p x p`; first order, at
    /// the fitted gradient); all zero when `sigma_theta` is 0.
    pub azimuth_covariance: Vec<f64>,
    /// With `sigma` given, the whitened residual sum of squares is distributed about as
    /// `chi2_scale * chi2(chi2_dof)` (Satterthwaite) once the azimuth errors are allowed for;
    /// 1 and `dof` without them.
    pub chi2_scale: f64,
    /// See `chi2_scale`.
    pub chi2_dof: f64,
}

/// What independent azimuth errors do to a start-up fit, to first order at a gradient.
#[derive(Debug, Clone, PartialEq)]
pub struct AzimuthErrorTerms {
    /// Parameter covariance (row-major `p x p`), as [`azimuth_error_covariance`].
    pub covariance: Vec<f64>,
    /// `tr(P S)`: expected share of the weighted residual sum of squares, with `P = I - H` the
    /// weighted residual projector and `S` the weighted covariance of the output errors.
    pub trace_ps: f64,
    /// `tr(P S P S)`, for the variance of the weighted residual sum of squares.
    pub trace_psps: f64,
}

/// First-order effect of independent azimuth errors of std `sigma_theta` (rad) on a start-up
/// fit with weights `1 / dwell_std` when the navigation-frame gradient is `gradient`:
/// `dy_k = 2 dtheta_k R'(2 theta_k) gamma`, the parameter covariance and the traces that give
/// its share of the residuals.
pub fn azimuth_error_terms(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
    gradient: [f64; 2],
    sigma_theta: f64,
) -> Result<AzimuthErrorTerms> {
    let covariance = azimuth_error_covariance(
        theta,
        t,
        t_ref,
        dwell_std,
        GradientPrior::Vector(gradient),
        sigma_theta,
    )?;
    let (cov, p, _) = startup_unit_cov(theta, t, t_ref, dwell_std)?;
    let (a, _) = design(theta, t, t_ref);
    let m = theta.len();
    let [gi, gc] = gradient;
    // Whitened output error per unit dtheta / sigma_theta: v_k = sigma_theta w_k d_k; and
    // u_k = A_w,k^T v_k, so that Q_kl = v_k^T P_kl v_l = delta_kl |v_k|^2 - u_k^T C u_l.
    let mut vv = vec![0.0; m];
    let mut cu = vec![0.0; m * p];
    let mut u = vec![0.0; m * p];
    for k in 0..m {
        let w = 1.0 / dwell_std[k];
        let (s, c) = (2.0 * theta[k]).sin_cos();
        let v = [
            sigma_theta * w * 2.0 * (-s * gi + c * gc),
            sigma_theta * w * 2.0 * (-c * gi - s * gc),
        ];
        vv[k] = v[0] * v[0] + v[1] * v[1];
        for j in 0..p {
            u[k * p + j] = w * (a[(2 * k) * p + j] * v[0] + a[(2 * k + 1) * p + j] * v[1]);
        }
        for i in 0..p {
            cu[k * p + i] = (0..p).map(|j| cov[i * p + j] * u[k * p + j]).sum();
        }
    }
    let mut trace_ps = 0.0;
    let mut trace_psps = 0.0;
    for k in 0..m {
        for l in 0..m {
            let ucu: f64 = (0..p).map(|j| u[k * p + j] * cu[l * p + j]).sum();
            let q = if k == l { vv[k] - ucu } else { -ucu };
            if k == l {
                trace_ps += q;
            }
            trace_psps += q * q;
        }
    }
    Ok(AzimuthErrorTerms {
        covariance,
        trace_ps,
        trace_psps,
    })
}

/// [`fit_startup_bias`] with the noise std of each average `sigma` (E) when known; otherwise
/// unit weights and the noise estimated from the residuals (`rss / dof`).
///
/// `sigma_theta` (rad) is the std of independent azimuth errors: their first-order effect,
/// evaluated at the fitted gradient ([`azimuth_error_terms`]), is added to the covariance.
/// With the noise estimated from the residuals, the share the azimuth errors are expected to
/// leave in them (`tr(P S)`) is taken out first (floored at zero), so it is not counted twice.
/// `sigma_theta = 0` gives exactly the fit without the term.
pub fn startup_bias(
    theta: &[f64],
    y: &[[f64; 2]],
    t: Option<&[f64]>,
    t_ref: f64,
    sigma: Option<&[f64]>,
    sigma_theta: f64,
) -> Result<StartupBias> {
    if !(sigma_theta.is_finite() && sigma_theta >= 0.0) {
        return invalid(format!(
            "azimuth error std must be finite and >= 0 (rad); got {sigma_theta}"
        ));
    }
    let m = theta.len();
    let ones = vec![1.0; m];
    let weights = sigma.unwrap_or(&ones);
    let f = fit_startup_bias(theta, y, t, t_ref, weights)?;
    let p = f.params.len();
    let az = if sigma_theta > 0.0 {
        let g = [f.params[2], f.params[3]];
        Some(azimuth_error_terms(
            theta,
            t,
            t_ref,
            weights,
            g,
            sigma_theta,
        )?)
    } else {
        None
    };
    let (mut covariance, used, estimated) = match sigma {
        Some(s) => (f.unit_cov.clone(), Some(s.to_vec()), false),
        None if f.dof > 0 => {
            let rss = match &az {
                Some(a) => (f.rss - a.trace_ps).max(0.0),
                None => f.rss,
            };
            let s2 = rss / f.dof as f64;
            let cov = f.unit_cov.iter().map(|v| v * s2).collect();
            (cov, Some(vec![s2.sqrt(); m]), true)
        }
        None => (vec![f64::NAN; p * p], None, false),
    };
    let (mut chi2_scale, mut chi2_dof) = (1.0, f.dof as f64);
    if let Some(a) = &az {
        for (c, v) in covariance.iter_mut().zip(&a.covariance) {
            *c += v;
        }
        let dof = f.dof as f64;
        if sigma.is_some() && f.dof > 0 {
            // z^T P z with z ~ N(0, I + S): mean dof + tr(PS), variance
            // 2 (dof + 2 tr(PS) + tr(PSPS)); matched to a scaled chi2.
            let mean = dof + a.trace_ps;
            let var = 2.0 * (dof + 2.0 * a.trace_ps + a.trace_psps);
            chi2_scale = var / (2.0 * mean);
            chi2_dof = 2.0 * mean * mean / var;
        }
    }
    let std = (0..p).map(|j| covariance[j * p + j].sqrt()).collect();
    Ok(StartupBias {
        params: f.params,
        covariance,
        std,
        residuals: f.residuals,
        unit_cov: f.unit_cov,
        sigma: used,
        sigma_estimated: estimated,
        dof: f.dof,
        condition: f.condition,
        sigma_theta,
        azimuth_covariance: az.map_or_else(|| vec![0.0; p * p], |a| a.covariance),
        chi2_scale,
        chi2_dof,
    })
}

/// Predicted accuracy of a start-up sequence before it is run.
#[derive(Debug, Clone, PartialEq)]
pub struct StartupPrediction {
    /// From the noise alone (row-major `p x p`).
    pub covariance: Vec<f64>,
    /// From independent azimuth errors (first order).
    pub azimuth_covariance: Vec<f64>,
    /// Their sum.
    pub total_covariance: Vec<f64>,
    /// Square roots of the total covariance diagonal.
    pub std: Vec<f64>,
    /// Closed form `sigma^2 m / (m^2 - |U|^2)` with the mean noise std (no drift).
    pub closed_form_variance: f64,
    /// Condition number of the design.
    pub condition: f64,
}

/// Covariance of the start-up estimate for a planned sequence: noise `dwell_std` per average,
/// independent azimuth errors of std `sigma_theta` (rad) with what is known of the gradient.
pub fn predict_startup(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
    gradient: GradientPrior,
    sigma_theta: f64,
) -> Result<StartupPrediction> {
    let (covariance, p, condition) = startup_unit_cov(theta, t, t_ref, dwell_std)?;
    let azimuth_covariance =
        azimuth_error_covariance(theta, t, t_ref, dwell_std, gradient, sigma_theta)?;
    let total_covariance: Vec<f64> = covariance
        .iter()
        .zip(&azimuth_covariance)
        .map(|(a, b)| a + b)
        .collect();
    let std = (0..p).map(|j| total_covariance[j * p + j].sqrt()).collect();
    let mean_sd = dwell_std.iter().sum::<f64>() / dwell_std.len() as f64;
    Ok(StartupPrediction {
        covariance,
        azimuth_covariance,
        total_covariance,
        std,
        closed_form_variance: mean_sd * mean_sd * balanced_variance(theta),
        condition,
    })
}

/// Least-squares gain `L = (A^T W A)^-1 A^T W` (row-major `p x 2m`): parameter change per unit
/// change of each channel average (rows ordered dwell-major: `y_0I, y_0C, y_1I, ...`).
pub fn startup_gain(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
) -> Result<(Vec<f64>, usize)> {
    let (cov, p, _) = startup_unit_cov(theta, t, t_ref, dwell_std)?;
    let m = theta.len();
    let (a, _) = design(theta, t, t_ref);
    let mut l = vec![0.0; p * 2 * m];
    for i in 0..p {
        for r in 0..2 * m {
            let w = 1.0 / (dwell_std[r / 2] * dwell_std[r / 2]);
            let mut s = 0.0;
            for j in 0..p {
                s += cov[i * p + j] * a[r * p + j];
            }
            l[i * 2 * m + r] = s * w;
        }
    }
    Ok((l, p))
}

/// What is known about the gradient when predicting the effect of azimuth errors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GradientPrior {
    /// The navigation-frame gradient `(I, C)` (channel units): exact linearisation.
    Vector([f64; 2]),
    /// Only its magnitude `|gamma|`: the covariance averaged over the gradient's direction.
    Magnitude(f64),
}

/// Parameter covariance (row-major `p x p`, channel units squared) caused by independent
/// azimuth errors of std `sigma_theta` (rad): first order, `dy_k = 2 dtheta_k R'(2 theta_k) gamma`.
pub fn azimuth_error_covariance(
    theta: &[f64],
    t: Option<&[f64]>,
    t_ref: f64,
    dwell_std: &[f64],
    gradient: GradientPrior,
    sigma_theta: f64,
) -> Result<Vec<f64>> {
    if !(sigma_theta.is_finite() && sigma_theta >= 0.0) {
        return invalid("azimuth error std must be finite and >= 0");
    }
    let (l, p) = startup_gain(theta, t, t_ref, dwell_std)?;
    let m = theta.len();
    let n = 2 * m;
    let v2 = sigma_theta * sigma_theta;
    let mut cov = vec![0.0; p * p];
    for k in 0..m {
        // 2x2 covariance of dy_k.
        let blk: [[f64; 2]; 2] = match gradient {
            GradientPrior::Vector([gi, gc]) => {
                let (s, c) = (2.0 * theta[k]).sin_cos();
                // d/d(2t) of R(2t) gamma = [[-s, c], [-c, -s]] gamma, times 2 dtheta.
                let g = [2.0 * (-s * gi + c * gc), 2.0 * (-c * gi - s * gc)];
                [
                    [v2 * g[0] * g[0], v2 * g[0] * g[1]],
                    [v2 * g[1] * g[0], v2 * g[1] * g[1]],
                ]
            }
            GradientPrior::Magnitude(gm) => {
                if !(gm.is_finite() && gm >= 0.0) {
                    return invalid("gradient magnitude must be finite and >= 0");
                }
                let d = 2.0 * v2 * gm * gm;
                [[d, 0.0], [0.0, d]]
            }
        };
        for i in 0..p {
            for j in 0..p {
                let mut s = 0.0;
                for a in 0..2 {
                    for b in 0..2 {
                        s += l[i * n + 2 * k + a] * blk[a][b] * l[j * n + 2 * k + b];
                    }
                }
                cov[i * p + j] += s;
            }
        }
    }
    Ok(cov)
}

/// Closed form for equal weights, no drift: `Var(bias_j) = Var(gamma_j) =
/// m / (m^2 - |U|^2)` per unit variance, `U = sum exp(-2i theta_k)`. Infinite when singular.
pub fn balanced_variance(theta: &[f64]) -> f64 {
    let m = theta.len() as f64;
    let (mut ur, mut ui) = (0.0, 0.0);
    for &th in theta {
        ur += (2.0 * th).cos();
        ui -= (2.0 * th).sin();
    }
    let den = m * m - (ur * ur + ui * ui);
    if den > 1e-12 * m * m {
        m / den
    } else {
        f64::INFINITY
    }
}

// ------------------------------------------------------------------------------------------
// 2-omega demodulation
// ------------------------------------------------------------------------------------------

/// One demodulated dwell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DemodDwell {
    /// Inline channel `I`, E.
    pub inline_e: f64,
    /// Cross channel `C`, E.
    pub cross_e: f64,
    /// White-noise standard errors of `I` and `C` from the fit residuals, E.
    pub std_e: [f64; 2],
    /// RMS of the fit residuals of `d = (a1 + a3) - (a2 + a4)`, input units.
    pub resid_rms: f64,
    /// Constant and 1-omega terms of `d` `[c0, cos, sin]`, input units.
    pub nuisance: [f64; 3],
    /// First sample used.
    pub start: usize,
    /// One past the last sample used (whole revolutions from `start`).
    pub stop: usize,
    /// Whole revolutions covered.
    pub revolutions: u64,
}

// fdlibm Cody-Waite split of pi/2 and kernel polynomials on [-pi/4, pi/4].
const PIO2_1: f64 = 1.570_796_326_734_125_6e0;
const PIO2_2: f64 = 6.077_100_506_303_966e-11;
const PIO2_2T: f64 = 2.022_266_248_795_950_6e-21;
const S1: f64 = -1.666_666_666_666_663_2e-1;
const S2: f64 = 8.333_333_333_322_49e-3;
const S3: f64 = -1.984_126_982_985_795e-4;
const S4: f64 = 2.755_731_370_707_006_8e-6;
const S5: f64 = -2.505_076_025_340_686_3e-8;
const S6: f64 = 1.589_690_995_211_55e-10;
#[allow(clippy::excessive_precision)] // fdlibm's literal, kept verbatim
const C1: f64 = 4.166_666_666_666_660_2e-2;
const C2: f64 = -1.388_888_888_887_411e-3;
const C3: f64 = 2.480_158_728_947_673e-5;
const C4: f64 = -2.755_731_435_139_066_3e-7;
const C5: f64 = 2.087_572_321_298_175e-9;
const C6: f64 = -1.135_964_755_778_819_5e-11;
const ROUND_MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5 * 2^52

/// `(sin x, cos x)` by Cody-Waite reduction and the fdlibm kernels: branch free, within a
/// couple of ulp for `|x| < 1.6e6`, beyond that the absolute error grows like `|x| 1e-22`.
#[inline(always)]
pub fn sin_cos_fast(x: f64) -> (f64, f64) {
    // The low mantissa bits of `x 2/pi + 1.5 2^52` hold round(x 2/pi): the quadrant, branch free.
    let y = x * std::f64::consts::FRAC_2_PI + ROUND_MAGIC;
    let q = y.to_bits();
    let kf = y - ROUND_MAGIC;
    let r = ((x - kf * PIO2_1) - kf * PIO2_2) - kf * PIO2_2T;
    let z = r * r;
    let sr = r + r * z * (S1 + z * (S2 + z * (S3 + z * (S4 + z * (S5 + z * S6)))));
    let cr = 1.0 - 0.5 * z + z * z * (C1 + z * (C2 + z * (C3 + z * (C4 + z * (C5 + z * C6)))));
    // Quadrant q: (sin, cos) = (sr, cr), (cr, -sr), (-sr, -cr), (-cr, sr); integer bit
    // operations only, so the lane loops vectorise.
    let swap = 0u64.wrapping_sub(q & 1);
    let (srb, crb) = (sr.to_bits(), cr.to_bits());
    let sb = (srb & !swap) | (crb & swap);
    let cb = (crb & !swap) | (srb & swap);
    let s = f64::from_bits(sb ^ (((q >> 1) & 1) << 63));
    let c = f64::from_bits(cb ^ ((((q + 1) >> 1) & 1) << 63));
    (s, c)
}

/// Symmetric 5x5 normal matrix (upper triangle, 15 values), right-hand side, sum of squares.
#[derive(Debug, Clone, Copy)]
struct NormalAcc {
    xx: [f64; 15],
    xy: [f64; 5],
    yy: f64,
    n: u64,
}

impl NormalAcc {
    fn zero() -> Self {
        NormalAcc {
            xx: [0.0; 15],
            xy: [0.0; 5],
            yy: 0.0,
            n: 0,
        }
    }
    fn add(mut self, o: &NormalAcc) -> Self {
        for i in 0..15 {
            self.xx[i] += o.xx[i];
        }
        for i in 0..5 {
            self.xy[i] += o.xy[i];
        }
        self.yy += o.yy;
        self.n += o.n;
        self
    }
}

const LANES_D: usize = 8;

/// Lane-parallel accumulators of the 5x5 normal equations.
struct LaneAcc {
    xx: [[f64; LANES_D]; 15],
    xy: [[f64; LANES_D]; 5],
    yy: [f64; LANES_D],
}

impl LaneAcc {
    /// Add `LANES_D` samples: combination `d` and phase `ph` per lane (vectorisable over lanes).
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // explicit lane loops are what vectorises
    fn block(&mut self, d: &[f64; LANES_D], ph: &[f64; LANES_D]) {
        let mut f = [[0.0f64; LANES_D]; 5];
        for l in 0..LANES_D {
            let (s1, c1) = sin_cos_fast(ph[l]);
            f[0][l] = 1.0;
            f[1][l] = c1;
            f[2][l] = s1;
            f[3][l] = c1 * c1 - s1 * s1;
            f[4][l] = 2.0 * s1 * c1;
        }
        let mut idx = 0;
        for i in 0..5 {
            for j in i..5 {
                for l in 0..LANES_D {
                    self.xx[idx][l] += f[i][l] * f[j][l];
                }
                idx += 1;
            }
            for l in 0..LANES_D {
                self.xy[i][l] += f[i][l] * d[l];
            }
        }
        for l in 0..LANES_D {
            self.yy[l] += d[l] * d[l];
        }
    }
}

/// [`accumulate`] compiled for AVX2 when the CPU has it (4 lanes per instruction).
fn accumulate_dispatch<T: Sample>(
    x: &ArrayView2<'_, T>,
    phase: &[f64],
    a: usize,
    b: usize,
    d0: f64,
) -> NormalAcc {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the running CPU supports AVX-512F (checked just above).
            return unsafe { accumulate_avx512(x, phase, a, b, d0) };
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the running CPU supports AVX2 (checked just above).
            return unsafe { accumulate_avx2(x, phase, a, b, d0) };
        }
    }
    accumulate(x, phase, a, b, d0)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn accumulate_avx512<T: Sample>(
    x: &ArrayView2<'_, T>,
    phase: &[f64],
    a: usize,
    b: usize,
    d0: f64,
) -> NormalAcc {
    accumulate(x, phase, a, b, d0)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn accumulate_avx2<T: Sample>(
    x: &ArrayView2<'_, T>,
    phase: &[f64],
    a: usize,
    b: usize,
    d0: f64,
) -> NormalAcc {
    accumulate(x, phase, a, b, d0)
}

/// Accumulate the normal equations of rows `[a, b)` (d shifted by `d0`).
#[inline(always)]
fn accumulate<T: Sample>(
    x: &ArrayView2<'_, T>,
    phase: &[f64],
    a: usize,
    b: usize,
    d0: f64,
) -> NormalAcc {
    let mut acc = LaneAcc {
        xx: [[0.0; LANES_D]; 15],
        xy: [[0.0; LANES_D]; 5],
        yy: [0.0; LANES_D],
    };
    let comb = |r0: T, r1: T, r2: T, r3: T| -> f64 {
        (r0.to_f64() + r2.to_f64()) - (r1.to_f64() + r3.to_f64()) - d0
    };
    let sub = x.slice(ndarray::s![a..b, ..]);
    let ph = &phase[a..b];
    let mut d = [0.0f64; LANES_D];
    let mut p = [0.0f64; LANES_D];
    let mut fill = 0;
    let flush_tail =
        |acc: &mut LaneAcc, d: &mut [f64; LANES_D], p: &mut [f64; LANES_D], fill: usize| {
            // Pad the last partial block with zero-weight rows: d = 0 and a phase, then remove
            // their normal-matrix contribution by accumulating them separately.
            if fill == 0 {
                return;
            }
            let mut extra = LaneAcc {
                xx: [[0.0; LANES_D]; 15],
                xy: [[0.0; LANES_D]; 5],
                yy: [0.0; LANES_D],
            };
            for l in fill..LANES_D {
                d[l] = 0.0;
                p[l] = 0.0;
            }
            extra.block(d, p);
            for l in 0..fill {
                for i in 0..15 {
                    acc.xx[i][l] += extra.xx[i][l];
                }
                for i in 0..5 {
                    acc.xy[i][l] += extra.xy[i][l];
                }
                acc.yy[l] += extra.yy[l];
            }
        };
    if let Some(s) = sub.as_slice() {
        let mut rows = s.chunks_exact(4 * LANES_D);
        let mut phs = ph.chunks_exact(LANES_D);
        for (g, pp) in rows.by_ref().zip(phs.by_ref()) {
            for l in 0..LANES_D {
                d[l] = comb(g[4 * l], g[4 * l + 1], g[4 * l + 2], g[4 * l + 3]);
                p[l] = pp[l];
            }
            acc.block(&d, &p);
        }
        for (r, &q) in rows.remainder().chunks_exact(4).zip(phs.remainder()) {
            d[fill] = comb(r[0], r[1], r[2], r[3]);
            p[fill] = q;
            fill += 1;
        }
    } else {
        for (r, &q) in sub.rows().into_iter().zip(ph) {
            d[fill] = comb(r[0], r[1], r[2], r[3]);
            p[fill] = q;
            fill += 1;
            if fill == LANES_D {
                acc.block(&d, &p);
                fill = 0;
            }
        }
    }
    flush_tail(&mut acc, &mut d, &mut p, fill);
    let mut out = NormalAcc::zero();
    for i in 0..15 {
        out.xx[i] = acc.xx[i].iter().sum();
    }
    for i in 0..5 {
        out.xy[i] = acc.xy[i].iter().sum();
    }
    out.yy = acc.yy.iter().sum();
    out.n = (b - a) as u64;
    out
}

/// Wrap a phase difference into `(-pi, pi]`.
#[inline(always)]
fn wrap(d: f64) -> f64 {
    d - TAU * (d / TAU).round()
}

/// `[a, c)` covering whole revolutions from `a`, and their number. The phase may be wrapped or
/// continuous; the spin may run either way.
fn whole_revolutions(phase: &[f64], a: usize, b: usize, k: usize) -> Result<(usize, u64)> {
    let ph = &phase[a..b];
    if let Some(j) = ph.iter().position(|v| !v.is_finite()) {
        return invalid(format!("phase is NaN or inf at sample {}", a + j));
    }
    let total: f64 = ph.windows(2).map(|w| wrap(w[1] - w[0])).sum();
    let n = ph.len();
    if n < 2 {
        return degenerate(format!(
            "dwell {k} [{a}, {b}) has fewer than 2 samples: nothing to demodulate"
        ));
    }
    // Each sample stands for one step of phase: n samples cover about total * n / (n - 1).
    let step = total / (n - 1) as f64;
    let covered = (total + step).abs();
    let revs = (covered / TAU + 1e-9).floor();
    if revs < 1.0 {
        return degenerate(format!(
            "dwell {k} [{a}, {b}) covers only {:.3} revolutions of the disc: need at least one \
             whole revolution to demodulate at 2 omega",
            covered / TAU
        ));
    }
    // Walk back from the end until the samples [a, c) cover `revs` revolutions.
    let target = revs * TAU;
    let mut c = n;
    let mut cov = covered;
    while c > 1 && cov - target > 0.5 * step.abs() {
        cov -= wrap(ph[c - 1] - ph[c - 2]).abs();
        c -= 1;
    }
    Ok((a + c, revs as u64))
}

/// Samples per parallel work item.
const CHUNK: usize = 1 << 15;

/// Demodulate `(N, 4)` accelerometer samples `a1..a4` (any unit, e.g. m/s^2) with the spin
/// phase `phase` (rad, of accelerometer 1; wrapped or continuous) over `[start, stop)` dwell
/// bounds. Each dwell is cut to whole revolutions from its start. `radius_m` converts the
/// 2-omega amplitude to a gradient: `I = s2 / (4R)`, `C = -c2 / (4R)`, returned in E when the
/// samples are in m/s^2.
pub fn demodulate<T: Sample>(
    x: &ArrayView2<'_, T>,
    phase: &[f64],
    bounds: &[[usize; 2]],
    radius_m: f64,
) -> Result<Vec<DemodDwell>> {
    if x.ncols() != 4 {
        return invalid(format!(
            "accelerometer samples must have shape (N, 4) (a1..a4 per row); got {} columns",
            x.ncols()
        ));
    }
    if phase.len() != x.nrows() {
        return invalid(format!(
            "phase has {} values but the samples have {} rows",
            phase.len(),
            x.nrows()
        ));
    }
    if !(radius_m.is_finite() && radius_m > 0.0) {
        return invalid(format!(
            "disc radius must be positive and finite (m); got {radius_m}"
        ));
    }
    crate::dwell::check_bounds(bounds, x.nrows())?;
    let mut cuts = Vec::with_capacity(bounds.len());
    for (k, &[a, b]) in bounds.iter().enumerate() {
        let (c, revs) = whole_revolutions(phase, a, b, k)?;
        cuts.push((a, c, revs));
    }
    // Work items: (dwell, chunk start, chunk stop), parallel over all of them.
    let mut items = Vec::new();
    for (k, &(a, c, _)) in cuts.iter().enumerate() {
        let mut s = a;
        while s < c {
            let e = (s + CHUNK).min(c);
            items.push((k, s, e));
            s = e;
        }
    }
    let d0: Vec<f64> = cuts
        .iter()
        .map(|&(a, _, _)| {
            let r = x.row(a);
            (r[0].to_f64() + r[2].to_f64()) - (r[1].to_f64() + r[3].to_f64())
        })
        .collect();
    let parts: Vec<(usize, NormalAcc)> = items
        .par_iter()
        .map(|&(k, s, e)| (k, accumulate_dispatch(x, phase, s, e, d0[k])))
        .collect();
    let mut accs = vec![NormalAcc::zero(); cuts.len()];
    for (k, p) in &parts {
        accs[*k] = accs[*k].add(p);
    }
    let gain = 1.0 / (4.0 * radius_m * EOTVOS);
    let mut out = Vec::with_capacity(cuts.len());
    for (k, (&(a, c, revs), acc)) in cuts.iter().zip(&accs).enumerate() {
        let mut nm = [0.0f64; 25];
        let mut idx = 0;
        for i in 0..5 {
            for j in i..5 {
                nm[i * 5 + j] = acc.xx[idx];
                nm[j * 5 + i] = acc.xx[idx];
                idx += 1;
            }
        }
        let rhs = acc.xy;
        if !(rhs.iter().all(|v| v.is_finite()) && acc.yy.is_finite()) {
            return invalid(format!(
                "samples contain NaN or inf (or values too large to square) in dwell {k} [{a}, {c})"
            ));
        }
        // Inverse of the normal matrix by Cholesky (through `lsq`).
        let inv = (acc.n > 5 && cholesky_small(&mut nm, 5))
            .then(|| cholesky_inverse_small(&nm, 5))
            .filter(|m| m.iter().all(|v| v.is_finite()));
        let Some(inv) = inv else {
            return degenerate(format!(
                "dwell {k} [{a}, {c}): the phase does not sample the revolution densely \
                 enough to separate the 2-omega terms (need well over 4 samples per \
                 revolution, {} samples used)",
                acc.n
            ));
        };
        let beta: [f64; 5] =
            std::array::from_fn(|i| (0..5).map(|j| inv[i * 5 + j] * rhs[j]).sum::<f64>());
        let bdot: f64 = beta.iter().zip(&rhs).map(|(x, y)| x * y).sum();
        let rss = (acc.yy - bdot).max(0.0);
        let var = rss / (acc.n - 5) as f64;
        out.push(DemodDwell {
            inline_e: beta[4] * gain,
            cross_e: -beta[3] * gain,
            std_e: [
                (var * inv[4 * 5 + 4]).max(0.0).sqrt() * gain,
                (var * inv[3 * 5 + 3]).max(0.0).sqrt() * gain,
            ],
            resid_rms: (rss / acc.n as f64).sqrt(),
            nuisance: [beta[0] + d0[k], beta[1], beta[2]],
            start: a,
            stop: c,
            revolutions: revs,
        });
    }
    Ok(out)
}

/// Mid time of the samples each demodulated dwell used: `(t[start] + t[stop - 1]) / 2` (s).
pub fn mid_times(t: &[f64], dwells: &[DemodDwell]) -> Result<Vec<f64>> {
    dwells
        .iter()
        .enumerate()
        .map(|(k, d)| {
            let (a, b) = (t.get(d.start), t.get(d.stop.wrapping_sub(1)));
            match (a, b) {
                (Some(a), Some(b)) if a.is_finite() && b.is_finite() => Ok(0.5 * (a + b)),
                _ => invalid(format!(
                    "sample times of dwell {k} [{}, {}) are missing or not finite",
                    d.start, d.stop
                )),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;
    use std::f64::consts::PI;

    fn deg(v: &[f64]) -> Vec<f64> {
        v.iter().map(|d| d.to_radians()).collect()
    }

    fn synth(
        theta: &[f64],
        b: [f64; 2],
        g: [f64; 2],
        t: Option<(&[f64], [f64; 2])>,
    ) -> Vec<[f64; 2]> {
        theta
            .iter()
            .enumerate()
            .map(|(k, &th)| {
                let (s, c) = (2.0 * th).sin_cos();
                let mut y = [b[0] + c * g[0] + s * g[1], b[1] - s * g[0] + c * g[1]];
                if let Some((t, d)) = t {
                    y[0] += d[0] * t[k];
                    y[1] += d[1] * t[k];
                }
                y
            })
            .collect()
    }

    #[test]
    fn noise_free_recovery_unbalanced() {
        let th = deg(&[0.0, 30.0, 100.0]);
        let y = synth(&th, [3.0, -2.0], [40.0, 15.0], None);
        let f = fit_startup_bias(&th, &y, None, 0.0, &[1.0; 3]).unwrap();
        let want = [3.0, -2.0, 40.0, 15.0];
        for (a, b) in f.params.iter().zip(want) {
            assert!((a - b).abs() < 1e-10, "{a} vs {b}");
        }
        let v = balanced_variance(&th);
        assert!((f.unit_cov[0] - v).abs() < 1e-12 * v.max(1.0));
        assert!((f.unit_cov[2 * 4 + 2] - v).abs() < 1e-12 * v.max(1.0));
    }

    #[test]
    fn balanced_sets_closed_forms() {
        for (set, v) in [
            (vec![0.0, 90.0], 0.5),
            (vec![0.0, 60.0, 120.0], 1.0 / 3.0),
            (vec![0.0, 45.0, 90.0, 135.0], 0.25),
        ] {
            let (c, _, _) = startup_unit_cov(&deg(&set), None, 0.0, &vec![1.0; set.len()]).unwrap();
            assert!((c[0] - v).abs() < 1e-12 && (c[5] - v).abs() < 1e-12);
            assert!((balanced_variance(&deg(&set)) - v).abs() < 1e-12);
        }
    }

    #[test]
    fn singular_sets_are_explained() {
        let e = fit_startup_bias(&deg(&[0.0, 180.0]), &[[0.0; 2]; 2], None, 0.0, &[1.0; 2]);
        match e {
            Err(CoreError::Degenerate(m)) => assert!(m.contains("modulo 180"), "{m}"),
            other => panic!("{other:?}"),
        }
        let e = fit_startup_bias(&deg(&[0.0]), &[[0.0; 2]], None, 0.0, &[1.0]);
        assert!(matches!(e, Err(CoreError::Degenerate(_))));
        let t = [0.0, 1.0];
        let e = fit_startup_bias(&deg(&[0.0, 90.0]), &[[0.0; 2]; 2], Some(&t), 0.5, &[1.0; 2]);
        match e {
            Err(CoreError::Degenerate(m)) => assert!(m.contains("at least 3"), "{m}"),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn abba_with_drift() {
        let th = deg(&[0.0, 90.0, 90.0, 0.0]);
        let t = [0.0, 100.0, 200.0, 300.0];
        let tr = [-150.0, -50.0, 50.0, 150.0];
        let y = synth(&th, [1.0, 2.0], [30.0, -10.0], Some((&tr, [0.01, -0.02])));
        let f = fit_startup_bias(&th, &y, Some(&t), 150.0, &[1.0; 4]).unwrap();
        let want = [1.0, 2.0, 30.0, -10.0, 0.01, -0.02];
        for (a, b) in f.params.iter().zip(want) {
            assert!((a - b).abs() < 1e-10, "{a} vs {b}");
        }
        // Drift is decorrelated from bias and gradient.
        for j in 0..4 {
            assert!(f.unit_cov[j * 6 + 4].abs() < 1e-14);
        }
    }

    #[test]
    fn startup_bias_scales_the_covariance_to_the_noise() {
        let th = deg(&[0.0, 45.0, 90.0, 135.0, 10.0]);
        let mut y = synth(&th, [1.0, 2.0], [30.0, -10.0], None);
        y[1][0] += 0.3;
        y[3][1] -= 0.2;
        let f = fit_startup_bias(&th, &y, None, 0.0, &[1.0; 5]).unwrap();
        let est = startup_bias(&th, &y, None, 0.0, None, 0.0).unwrap();
        let s2 = f.rss / f.dof as f64;
        assert!(est.sigma_estimated && est.dof == 6);
        for (a, b) in est.covariance.iter().zip(&f.unit_cov) {
            assert!((a - b * s2).abs() <= 1e-15 * (b * s2).abs().max(1e-300));
        }
        assert!((est.std[0] - (f.unit_cov[0] * s2).sqrt()).abs() < 1e-15);
        let given = startup_bias(&th, &y, None, 0.0, Some(&[0.5; 5]), 0.0).unwrap();
        assert!(!given.sigma_estimated && given.sigma == Some(vec![0.5; 5]));
        // No redundancy and no noise given: the covariance cannot be known.
        let two = startup_bias(&th[..2], &y[..2], None, 0.0, None, 0.0).unwrap();
        assert!(two.dof == 0 && two.sigma.is_none() && two.covariance.iter().all(|v| v.is_nan()));
    }

    #[test]
    fn startup_bias_adds_azimuth_errors_at_the_fitted_gradient() {
        let th = deg(&[0.0, 30.0, 100.0, 150.0, 10.0]);
        let g = [120.0, -70.0];
        let y = synth(&th, [1.0, 2.0], g, None);
        let sd = [0.05, 0.05, 0.08, 0.05, 0.05];
        let st = 0.1f64.to_radians();
        let zero = startup_bias(&th, &y, None, 0.0, Some(&sd), 0.0).unwrap();
        assert!(zero.azimuth_covariance.iter().all(|v| *v == 0.0));
        assert!(zero.chi2_scale == 1.0 && zero.chi2_dof == zero.dof as f64);
        let with = startup_bias(&th, &y, None, 0.0, Some(&sd), st).unwrap();
        let pred = predict_startup(&th, None, 0.0, &sd, GradientPrior::Vector(g), st).unwrap();
        for (a, b) in with.covariance.iter().zip(&pred.total_covariance) {
            assert!((a - b).abs() <= 1e-9 * b.abs().max(1e-12), "{a} vs {b}");
        }
        assert!(with.std[0] > 3.0 * zero.std[0]);
        assert!(with.chi2_scale > 1.0 && with.chi2_dof > 0.0);
        for bad in [-1e-3, f64::NAN, f64::INFINITY] {
            assert!(startup_bias(&th, &y, None, 0.0, Some(&sd), bad).is_err());
        }
    }

    #[test]
    fn azimuth_error_traces_match_the_dense_projector() {
        let th = deg(&[0.0, 30.0, 100.0, 150.0, 10.0, 75.0]);
        let t = [0.0, 50.0, 100.0, 150.0, 200.0, 250.0];
        let sd = [0.5, 0.7, 0.5, 0.6, 0.5, 0.9];
        let g = [40.0, 25.0];
        let st = 0.3f64.to_radians();
        let a = azimuth_error_terms(&th, Some(&t), 125.0, &sd, g, st).unwrap();
        let (raw, p) = design(&th, Some(&t), 125.0);
        let m = th.len();
        let n = 2 * m;
        let aw = DMatrix::<f64>::from_fn(n, p, |r, j| raw[r * p + j] / sd[r / 2]);
        let c = (aw.transpose() * &aw).try_inverse().unwrap();
        let pm = DMatrix::<f64>::identity(n, n) - &aw * c * aw.transpose();
        let mut sm = DMatrix::<f64>::zeros(n, n);
        for k in 0..m {
            let (s, cc) = (2.0 * th[k]).sin_cos();
            let v = [
                st / sd[k] * 2.0 * (-s * g[0] + cc * g[1]),
                st / sd[k] * 2.0 * (-cc * g[0] - s * g[1]),
            ];
            for x in 0..2 {
                for z in 0..2 {
                    sm[(2 * k + x, 2 * k + z)] = v[x] * v[z];
                }
            }
        }
        let ps = &pm * &sm;
        let tr1 = ps.trace();
        let tr2 = (&ps * &ps).trace();
        assert!(
            (a.trace_ps - tr1).abs() < 1e-9 * tr1.abs(),
            "{} vs {tr1}",
            a.trace_ps
        );
        assert!(
            (a.trace_psps - tr2).abs() < 1e-9 * tr2.abs(),
            "{} vs {tr2}",
            a.trace_psps
        );
    }

    #[test]
    fn estimated_noise_leaves_out_the_azimuth_share() {
        let th = deg(&[0.0, 45.0, 90.0, 135.0, 22.5, 67.5, 112.5, 157.5]);
        let g = [200.0, 50.0];
        let st = 0.2f64.to_radians();
        // Outputs at azimuths off by +-sigma_theta alternately, no noise.
        let off: Vec<f64> = th
            .iter()
            .enumerate()
            .map(|(k, v)| v + if k % 2 == 0 { st } else { -st })
            .collect();
        let y = synth(&off, [3.0, -1.0], g, None);
        let plain = startup_bias(&th, &y, None, 0.0, None, 0.0).unwrap();
        let with = startup_bias(&th, &y, None, 0.0, None, st).unwrap();
        let s_plain = plain.sigma.unwrap()[0];
        let s_with = with.sigma.unwrap()[0];
        assert!(s_with < s_plain && s_with >= 0.0);
        assert!(with.std[0] > plain.std[0] * 0.5);
    }

    #[test]
    fn prediction_adds_azimuth_errors_and_gives_the_closed_form() {
        let th = deg(&[0.0, 45.0, 90.0, 135.0]);
        let p = predict_startup(
            &th,
            None,
            0.0,
            &[0.5; 4],
            GradientPrior::Magnitude(50.0),
            0.01,
        )
        .unwrap();
        assert!((p.closed_form_variance - 0.25 * 0.25).abs() < 1e-15);
        assert!((p.covariance[0] - 0.0625).abs() < 1e-12);
        let want = 0.0625 + 2.0 * 1e-4 * 2500.0 / 4.0;
        assert!(
            (p.total_covariance[0] - want).abs() < 1e-12 && (p.std[0] - want.sqrt()).abs() < 1e-12
        );
    }

    #[test]
    fn mid_times_of_demodulated_dwells() {
        let d = DemodDwell {
            inline_e: 0.0,
            cross_e: 0.0,
            std_e: [0.0; 2],
            resid_rms: 0.0,
            nuisance: [0.0; 3],
            start: 2,
            stop: 6,
            revolutions: 1,
        };
        let t = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        assert_eq!(mid_times(&t, &[d]).unwrap(), vec![3.5]);
        assert!(mid_times(&t[..4], &[d]).is_err());
    }

    #[test]
    fn fast_sincos_matches_libm() {
        let mut worst: f64 = 0.0;
        for i in 0..200_000 {
            let x = -5000.0 + i as f64 * 0.05000123;
            let (s, c) = sin_cos_fast(x);
            let (s0, c0) = x.sin_cos();
            worst = worst.max((s - s0).abs()).max((c - c0).abs());
        }
        assert!(worst < 1e-15, "{worst}");
    }

    #[test]
    fn demodulation_recovers_amplitudes() {
        let r = 0.1;
        let (gi, gc) = (25.0 * EOTVOS, -12.0 * EOTVOS);
        let fs = 200.0;
        let w = TAU * 0.7;
        let n = 20_000;
        let mut x = Array2::<f64>::zeros((n, 4));
        let mut ph = vec![0.0; n];
        for j in 0..n {
            let t = j as f64 / fs;
            ph[j] = (w * t + 0.3) % TAU; // wrapped phase
            for i in 0..4 {
                let p = w * t + 0.3 + i as f64 * PI / 2.0;
                x[(j, i)] = r * (gi * (2.0 * p).sin() - gc * (2.0 * p).cos())
                    + 1e-3 * (1.0 + 0.01 * i as f64) * (-(p.sin()))
                    + 0.01 * i as f64;
            }
        }
        let out = demodulate(&x.view(), &ph, &[[0, 9000], [9000, n]], r).unwrap();
        for o in &out {
            assert!((o.inline_e - 25.0).abs() < 1e-6, "{o:?}");
            assert!((o.cross_e + 12.0).abs() < 1e-6, "{o:?}");
            let covered = (o.stop - o.start) as f64 * w / fs;
            assert!((covered / TAU - o.revolutions as f64).abs() < w / fs);
        }
        let e = demodulate(&x.view(), &ph, &[[0, 100]], r);
        assert!(matches!(e, Err(CoreError::Degenerate(_))));
    }

    #[test]
    fn demodulation_reverse_spin_and_azimuth_error_formula() {
        let r = 0.05;
        let (fs, w, n) = (100.0, -TAU * 0.3, 7_000);
        let mut x = Array2::<f64>::zeros((n, 4));
        let ph: Vec<f64> = (0..n).map(|j| w * j as f64 / fs).collect();
        for j in 0..n {
            for i in 0..4 {
                let p = ph[j] + i as f64 * PI / 2.0;
                x[(j, i)] = r * EOTVOS * (7.0 * (2.0 * p).sin() - 3.0 * (2.0 * p).cos());
            }
        }
        let o = demodulate(&x.view(), &ph, &[[0, n]], r).unwrap()[0];
        assert!(
            (o.inline_e - 7.0).abs() < 1e-9 && (o.cross_e - 3.0).abs() < 1e-9,
            "{o:?}"
        );
        assert_eq!(o.revolutions, 21); // 70 s at 0.3 Hz
                                       // Balanced set, sigma_bias^2 = 2 sigma_theta^2 |gamma|^2 / m.
        let th = deg(&[0.0, 45.0, 90.0, 135.0]);
        let c = azimuth_error_covariance(
            &th,
            None,
            0.0,
            &[1.0; 4],
            GradientPrior::Magnitude(50.0),
            0.01,
        )
        .unwrap();
        let want = 2.0 * 1e-4 * 2500.0 / 4.0;
        assert!((c[0] - want).abs() < 1e-12 * want && (c[5] - want).abs() < 1e-12 * want);
    }
}

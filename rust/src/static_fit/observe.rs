//! The covariance stage and what a pose set can determine.
//!
//! Observability is judged in *comparable units*: scale factors and misalignments relative to
//! the mean scale, biases in units of g (in the fitting frame, where `K ~ I`, that is the
//! whitened Jacobian with its bias columns multiplied by `g`).

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::cost::{inv_k, jac_row, ml_row, DwellEval, NormProblem};
use super::{FitSettings, MlOutcome, Model, PARAM_NAMES, SINGULAR_RTOL};
use crate::error::{invalid, Result};
use crate::lsq::{covariance_normal_fixed, svd_report_qr, top_eigen_fixed};
use nalgebra::{DMatrix, Vector3};

/// Predicted accuracy in comparable units (scale-relative; biases in g).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ObsSummary {
    /// Number of parameters (entries used in `std_comparable`).
    pub n_params: usize,
    /// Predicted std of each parameter (first `n_params` entries).
    pub std_comparable: [f64; 9],
    /// Predicted std of the least determined combination (the bound `sqrt(trace C)` when
    /// that is already below the degenerate threshold; the SVD report has the exact value).
    pub weakest_std: f64,
    /// Exactly or numerically undetermined.
    pub degenerate: bool,
    /// Some parameter's predicted std exceeds the weak threshold.
    pub weak: bool,
}

impl ObsSummary {
    /// Predicted std of each parameter (comparable units).
    pub fn std(&self) -> &[f64] {
        &self.std_comparable[..self.n_params]
    }
}

/// What the dwells can determine (SVD of the comparable whitened Jacobian).
#[derive(Debug, Clone, PartialEq)]
pub struct Observability {
    /// Singular values, descending.
    pub singular_values: Vec<f64>,
    /// `s_max / s_min`.
    pub condition: f64,
    /// Predicted std of each parameter in comparable units.
    pub std_comparable: Vec<f64>,
    /// Least determined parameter combination (unit vector, comparable units).
    pub weakest: Vec<f64>,
    /// Predicted std of [`Observability::weakest`] (comparable units).
    pub weakest_std: f64,
    /// The combination is exactly or numerically undetermined.
    pub degenerate: bool,
    /// Some parameter's predicted std exceeds the weak threshold.
    pub weak: bool,
    /// The weakest combination in parameter names ([`describe_combination`]).
    pub combination: String,
}

/// Outcome of the covariance stage (frame units).
#[derive(Debug, Clone, Copy)]
pub struct CovStage {
    /// `sum e_k^2` at the final parameters.
    pub cost: f64,
    /// `cost / (k - p)` (NaN without redundancy).
    pub chi2_dof: f64,
    /// Covariance scale used to judge observability: 1 for a known noise model, else
    /// chi2/dof floored at `(1e-7 g)^2` (so that a perfect fit cannot hide a singular design).
    pub obs_scale: f64,
    /// Quick observability summary.
    pub summary: ObsSummary,
    /// `(J^T J)^-1` in comparable units (noise-model weights, unscaled); `None` when singular.
    pub cov_c: Option<[[f64; 9]; 9]>,
    /// `g^T (J^T J)^-1 g`, in units of the realistic parameter variance (the noise model's,
    /// times chi2/dof when that exceeds 1 or the noise is estimated): squared distance, in
    /// parameter std, from the current point to the minimum of the local quadratic model
    /// (infinite when singular).
    pub decrement: f64,
}

/// Describe a combination (comparable units) in parameter names, largest coefficient first,
/// e.g. `"m2 + 0.94 m1 - 0.23 bz/g"` (coefficients below a tenth of the largest omitted).
pub fn describe_combination(v: &[f64]) -> String {
    let vmax = v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    if !(vmax > 0.0) {
        return "(none)".into();
    }
    let imax = v.iter().position(|x| x.abs() == vmax).unwrap_or(0);
    let sign = v[imax].signum();
    let mut idx: Vec<usize> = (0..v.len().min(9))
        .filter(|&i| v[i].abs() >= 0.1 * vmax)
        .collect();
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

/// Quick observability summary from the comparable normal matrix `h` and the covariance
/// scale: Cholesky covariance, then the largest eigenvalue by power iteration only when the
/// bound `trace C` is inconclusive.
pub fn obs_summary<const N: usize>(
    h: &[[f64; N]; N],
    scale: f64,
    set: &FitSettings,
) -> (ObsSummary, Option<[[f64; N]; N]>) {
    let sc = if scale.is_finite() { scale } else { 0.0 };
    let mut std = [f64::INFINITY; 9];
    match covariance_normal_fixed(h, SINGULAR_RTOL) {
        Some(c) => {
            for (i, s) in std.iter_mut().enumerate().take(N) {
                *s = (c[i][i] * sc).sqrt();
            }
            // lambda_max(C) <= trace(C): only when the cheap bound is inconclusive, iterate.
            let tr: f64 = (0..N).map(|i| c[i][i]).sum();
            let lam = if (tr * sc).sqrt() <= set.degenerate_std {
                tr
            } else {
                top_eigen_fixed(&c, 500).0
            };
            let wstd = (lam * sc).sqrt();
            let sum = ObsSummary {
                n_params: N,
                weak: std[..N].iter().any(|s| !(*s <= set.weak_std)),
                degenerate: !(wstd <= set.degenerate_std),
                std_comparable: std,
                weakest_std: wstd,
            };
            (sum, Some(c))
        }
        None => (
            ObsSummary {
                n_params: N,
                std_comparable: std,
                weakest_std: f64::INFINITY,
                degenerate: true,
                weak: true,
            },
            None,
        ),
    }
}

/// The covariance stage: from the cost, `J^T J` and `J^T e` at the final frame parameters
/// (from the ML stage), chi2/dof, the comparable covariance, the observability summary and
/// the Newton decrement (the convergence check). `n` dwells, reference gravity `g`.
pub fn covariance_stage<const N: usize>(
    ml: &MlOutcome,
    n: usize,
    g: f64,
    noise_known: bool,
    set: &FitSettings,
) -> CovStage {
    let d = |i: usize| if (3..6).contains(&i) { g } else { 1.0 };
    let mut h = [[0.0f64; N]; N];
    let mut gr = [0.0f64; N];
    for (i, (hi, gi)) in h.iter_mut().zip(gr.iter_mut()).enumerate() {
        *gi = ml.jtr[i] * d(i);
        for (j, hij) in hi.iter_mut().enumerate() {
            *hij = ml.jtj[i][j] * d(i) * d(j);
        }
    }
    let cost = ml.cost;
    let chi2_dof = if n > N {
        cost / (n - N) as f64
    } else {
        f64::NAN
    };
    let obs_scale = if noise_known {
        1.0
    } else {
        chi2_dof.max((1e-7 * g).powi(2))
    };
    let (summary, cov) = obs_summary::<N>(&h, obs_scale, set);
    // The convergence check is in the realistic std: the noise model's, inflated by
    // chi2/dof when the residuals exceed it.
    let conv_scale = if noise_known {
        if chi2_dof > 1.0 {
            chi2_dof
        } else {
            1.0
        }
    } else {
        obs_scale
    };
    let (cov_c, decrement) = match cov {
        Some(c) => {
            let mut dec = 0.0;
            for i in 0..N {
                for j in 0..N {
                    dec += gr[i] * c[i][j] * gr[j];
                }
            }
            let mut out = [[0.0f64; 9]; 9];
            for i in 0..N {
                out[i][..N].copy_from_slice(&c[i]);
            }
            (Some(out), dec / conv_scale)
        }
        None => (None, f64::INFINITY),
    };
    CovStage {
        cost,
        chi2_dof,
        obs_scale,
        summary,
        cov_c,
        decrement,
    }
}

/// The comparable whitened Jacobian (`n x np`, bias columns times `g`) of every dwell at
/// the frame parameters `p`: what the observability report decomposes.
pub fn comparable_jacobian(
    prob: &NormProblem<'_>,
    p: &[f64; 9],
    np: usize,
) -> Result<DMatrix<f64>> {
    let mut jc = DMatrix::<f64>::zeros(prob.pts.len(), np);
    per_dwell(prob, p, |k, _, row| {
        for j in 0..np {
            jc[(k, j)] = row[j];
        }
    })?;
    Ok(jc)
}

/// Every dwell at the frame parameters `p`: `f(k, eval, row)` with the whitened Jacobian row
/// in comparable units (bias columns times `g`).
pub fn per_dwell(
    prob: &NormProblem<'_>,
    p: &[f64; 9],
    mut f: impl FnMut(usize, &DwellEval, &[f64; 9]),
) -> Result<()> {
    let mut row = [0.0f64; 9];
    let (g, model) = (prob.g, prob.model);
    prob.for_each(p, |k, t, d| {
        ml_row(model, t, d, &mut row);
        for v in &mut row[3..6] {
            *v *= g;
        }
        f(k, d, &row);
    })
}

/// Full observability report (SVD of the comparable whitened Jacobian `jc`, scaled by
/// `scale`).
pub fn obs_report(jc: &DMatrix<f64>, scale: f64, set: &FitSettings) -> Result<Observability> {
    let np = jc.ncols();
    let svd = svd_report_qr(jc)?;
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

/// The message of a degenerate fit, naming the undetermined combination.
pub fn degenerate_message(
    obs: &Observability,
    model: Model,
    n: usize,
    sum: &ObsSummary,
    degenerate_std: f64,
) -> String {
    let how = if obs.weakest_std.is_infinite() || sum.weakest_std.is_infinite() {
        "exactly singular design".to_string()
    } else {
        format!(
            "predicted std {:.2e} in relative units (scale factors relative, biases in g) \
             above degenerate_std = {degenerate_std}, condition number {:.2e}",
            obs.weakest_std, obs.condition
        )
    };
    let instead = if model == Model::Diag {
        ""
    } else {
        ", or fit model \"diag\""
    };
    format!(
        "the {n} dwells cannot determine {} of model {:?} ({how}). Add poses with different \
         gravity directions (tilts in both axes at once, larger angles, ideally the whole \
         sphere){instead}",
        obs.combination,
        model.name()
    )
}

// ------------------------------------------------------------------------------------------
// Pose design

/// Fisher-information rows of a pose design: for each true specific force `force[k]`
/// (units of g) the Jacobian row of the whitened residual at parameters `params` (the truth),
/// for dwell-mean noise `sigma` per axis (output units). Row-major `n x p`.
pub fn design_rows(
    model: Model,
    params: &[f64],
    force: &[[f64; 3]],
    sigma: f64,
) -> Result<Vec<f64>> {
    let np = model.n_params();
    if params.len() != np {
        return invalid(format!(
            "truth has {} values; model {:?} has {np} parameters",
            params.len(),
            model.name()
        ));
    }
    if params.iter().any(|v| !v.is_finite()) {
        return invalid("truth values must be finite");
    }
    if !(sigma > 0.0) || !sigma.is_finite() {
        return invalid(format!(
            "sigma must be a positive, finite std of a dwell mean (output units); got {sigma}"
        ));
    }
    let t = inv_k(model, params)?;
    let mut out = Vec::with_capacity(force.len() * np);
    let mut row = [0.0f64; 9];
    for (k, f) in force.iter().enumerate() {
        let a = Vector3::new(f[0], f[1], f[2]);
        let na = a.norm();
        if !(na > 0.0) || !na.is_finite() {
            return invalid(format!(
                "attitude {k} gives a zero or non-finite gravity direction"
            ));
        }
        let w = t.tr_mul(&a) / na;
        let is = 1.0 / (sigma * w.norm());
        jac_row(model, &w, &a, is, &mut row);
        out.extend_from_slice(&row[..np]);
    }
    Ok(out)
}

/// Cramer-Rao bound of a pose design in output units.
#[derive(Debug, Clone, PartialEq)]
pub struct Prediction {
    /// Std of each parameter (infinite when singular).
    pub std: Vec<f64>,
    /// Covariance, row-major `p x p` (infinite when singular).
    pub covariance: Vec<f64>,
    /// Some combination is undetermined.
    pub singular: bool,
    /// The SVD report in comparable units (`None` with fewer poses than parameters).
    pub observability: Option<Observability>,
}

/// Cramer-Rao bound of the design `force` (true specific forces, units of g) at `params`,
/// for dwell-mean noise `sigma` per axis and reference gravity `g` known to `sigma_g` (std,
/// units of `g`; 0 for exact): its covariance `sigma_g^2 (dp/dg) (dp/dg)^T` is added (the
/// observability report leaves it out: the poses cannot determine `g`).
pub fn predict(
    model: Model,
    params: &[f64],
    force: &[[f64; 3]],
    sigma: f64,
    g: f64,
    sigma_g: f64,
    set: &FitSettings,
) -> Result<Prediction> {
    if !(g > 0.0) || !g.is_finite() {
        return invalid(format!(
            "g must be a positive, finite reference gravity; got {g}"
        ));
    }
    super::check_sigma_g(sigma_g, g)?;
    if force.is_empty() {
        return invalid("attitudes: need at least one pose; got none");
    }
    let np = model.n_params();
    let rows = design_rows(model, params, force, sigma)?;
    let n = force.len();
    if n < np {
        return Ok(Prediction {
            std: vec![f64::INFINITY; np],
            covariance: vec![f64::INFINITY; np * np],
            singular: true,
            observability: None,
        });
    }
    let d = |j: usize| if (3..6).contains(&j) { g } else { 1.0 };
    let jc = DMatrix::from_fn(n, np, |i, j| rows[i * np + j] * d(j));
    let obs = obs_report(&jc, 1.0, set)?;
    let singular = !(obs.singular_values[np - 1] > SINGULAR_RTOL * obs.singular_values[0]);
    let mut covariance = if singular {
        vec![f64::INFINITY; np * np]
    } else {
        let svd = svd_report_qr(&jc)?;
        match svd.covariance() {
            Some(c) => (0..np * np)
                .map(|k| {
                    let (i, j) = (k / np, k % np);
                    c[(i, j)] * d(i) * d(j)
                })
                .collect(),
            None => vec![f64::INFINITY; np * np],
        }
    };
    if sigma_g > 0.0 && !singular {
        let jv = super::gravity_sensitivity(&params[..np], g);
        for (k, c) in covariance.iter_mut().enumerate() {
            *c += super::gravity_cov_entry(&jv, k / np, k % np, sigma_g);
        }
    }
    let std = (0..np).map(|i| covariance[i * np + i].sqrt()).collect();
    Ok(Prediction {
        std,
        covariance,
        singular,
        observability: Some(obs),
    })
}

#[cfg(test)]
mod tests {
    use super::super::tests_common::{simulate, G, TRUTH};
    use super::super::{fit_static, Method, Noise};
    use super::*;

    #[test]
    fn combination_is_named_largest_first() {
        let v = [0.23, 0.0, 0.0, 0.0, 0.0, -0.05, 0.94, -1.0, 0.01];
        assert_eq!(describe_combination(&v), "m2 - 0.94 m1 - 0.23 sx");
        assert_eq!(describe_combination(&[0.0; 9]), "(none)");
        assert_eq!(
            describe_combination(&[0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
            "bz/g"
        );
    }

    #[test]
    fn covariance_stage_matches_the_svd_report_and_flags_singular_designs() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 3);
        let set = FitSettings::new(Model::Lower, Method::Lm);
        let f = fit_static(&m, G, &Noise::Uniform([1e-6; 3]), &set).unwrap();
        let o = f
            .observability(&Noise::Uniform([1e-6; 3]), G, &set)
            .unwrap();
        for (a, b) in f.summary.std().iter().zip(&o.std_comparable) {
            assert!((a / b - 1.0).abs() < 1e-6, "{a} {b}");
        }
        // At the exact (noise-free) minimum the decrement is at rounding level.
        assert!(f.decrement < 1e-12, "{}", f.decrement);
        // The predicted design std equals the fit's at the truth (noise-free data).
        let force: Vec<[f64; 3]> = {
            let t = inv_k(Model::Lower, &TRUTH).unwrap();
            m.iter()
                .map(|am| {
                    let a = t * Vector3::new(am[0] - TRUTH[3], am[1] - TRUTH[4], am[2] - TRUTH[5]);
                    [a[0], a[1], a[2]]
                })
                .collect()
        };
        let p = predict(Model::Lower, &TRUTH, &force, 1e-3, G, 0.0, &set).unwrap();
        for i in 0..9 {
            let fs = f.covariance[(i, i)].sqrt();
            assert!((p.std[i] / fs - 1.0).abs() < 1e-6, "{i} {} {fs}", p.std[i]);
        }
        assert!(!p.singular);
        // Too few poses, no poses, bad g.
        assert!(
            predict(Model::Lower, &TRUTH, &force[..5], 1e-3, G, 0.0, &set)
                .unwrap()
                .singular
        );
        assert!(predict(Model::Lower, &TRUTH, &[], 1e-3, G, 0.0, &set).is_err());
        assert!(predict(Model::Lower, &TRUTH, &force, 1e-3, f64::NAN, 0.0, &set).is_err());
        assert!(predict(Model::Lower, &TRUTH, &force, -1.0, G, 0.0, &set).is_err());
    }
}

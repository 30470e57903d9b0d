//! Many independent sessions at once: the stages of [`super::fit_static`] on all cores, with
//! fixed-size types and one point buffer per worker thread (no allocation per fit, except
//! to word an error).

use super::observe::comparable_jacobian;
use super::{
    check_sigma_g, check_solved, gravity_sensitivity, output_cov_entry, solve, FitSettings, Model,
    Noise,
};
use crate::error::{invalid, CoreError, Result};
use rayon::prelude::*;

/// The outcome of one session of a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BatchStatus {
    /// Fitted, every parameter determined.
    Ok,
    /// Fitted, but some parameter is only weakly determined (the weak-design warning).
    Weak,
    /// The dwells cannot determine the parameters (or do not describe an ellipsoid).
    Degenerate,
    /// The fit did not converge or ran away.
    NotConverged,
    /// Bad input (NaN mean, bad noise, ...).
    Invalid,
}

impl BatchStatus {
    /// The short name: `"ok" | "weak" | "degenerate" | "error"`.
    pub fn name(self) -> &'static str {
        match self {
            BatchStatus::Ok => "ok",
            BatchStatus::Weak => "weak",
            BatchStatus::Degenerate => "degenerate",
            BatchStatus::NotConverged | BatchStatus::Invalid => "error",
        }
    }

    /// The numeric code: 0 ok (weak included), 1 degenerate, 2 not converged, 3 invalid.
    pub fn code(self) -> u8 {
        match self {
            BatchStatus::Ok | BatchStatus::Weak => 0,
            BatchStatus::Degenerate => 1,
            BatchStatus::NotConverged => 2,
            BatchStatus::Invalid => 3,
        }
    }
}

/// One session's result.
#[derive(Debug, Clone, PartialEq)]
pub struct BatchRow {
    /// Parameters (first `p`; NaN when the fit failed).
    pub params: [f64; 9],
    /// Std of each parameter: from the noise model when it is known, the covariance scaled
    /// by chi2/dof when the noise is estimated (NaN when the fit failed); with `sigma_g`
    /// given it includes the reference gravity's uncertainty.
    pub std: [f64; 9],
    /// chi2/dof of a known noise model, or the estimated per-axis variance of a dwell mean
    /// (output units squared); NaN without redundancy or when the fit failed.
    pub chi2_dof: f64,
    /// RMS of `|a_k| - g` (units of g).
    pub rms: f64,
    /// GN/LM iterations.
    pub iterations: usize,
    /// Dwells in the session.
    pub n_dwells: usize,
    /// The fit converged.
    pub converged: bool,
    /// Outcome.
    pub status: BatchStatus,
    /// What went wrong, or for a fitted session the dwell whose norm residual exceeds 5 %
    /// of g (it may not be at rest); `None` otherwise: starts with "session i: ".
    pub message: Option<String>,
}

impl BatchRow {
    fn failed(n: usize, i: usize, e: &CoreError) -> BatchRow {
        let status = match e {
            CoreError::Degenerate(_) => BatchStatus::Degenerate,
            CoreError::NotConverged(_) => BatchStatus::NotConverged,
            CoreError::InvalidInput(_) | CoreError::OutOfMemory(_) => BatchStatus::Invalid,
        };
        BatchRow {
            params: [f64::NAN; 9],
            std: [f64::NAN; 9],
            chi2_dof: f64::NAN,
            rms: f64::NAN,
            iterations: 0,
            n_dwells: n,
            converged: false,
            status,
            message: Some(format!("session {i}: {e}")),
        }
    }
}

fn fit_one<const N: usize>(
    i: usize,
    means: &[[f64; 3]],
    g: f64,
    noise: &Noise<'_>,
    sigma_g: f64,
    set: &FitSettings,
    pts: &mut Vec<[f64; 3]>,
) -> BatchRow {
    let n = means.len();
    let solved = solve::<N>(means, g, noise, set, pts).and_then(|s| {
        check_solved(&s, set, n, || {
            comparable_jacobian(&s.problem(pts, g, noise, set.model), &s.ml.params, N)
        })?;
        Ok(s)
    });
    let s = match solved {
        Ok(s) => s,
        Err(e) => return BatchRow::failed(n, i, &e),
    };
    if !s.converged {
        let e = super::start::unexcited_axes(means).unwrap_or_else(|| {
            CoreError::NotConverged(format!(
                "the fit did not converge in {} iterations",
                set.max_iter
            ))
        });
        return BatchRow::failed(n, i, &e);
    }
    // RMS of the norm residuals: one light pass (the frame leaves |a| unchanged).
    let mut ss = 0.0;
    let mut worst = (0usize, 0.0f64);
    let prob = s.problem(pts, g, noise, set.model);
    if prob
        .residuals_each(&s.ml.params, |k, r, _| {
            ss += r * r;
            if r.abs() > worst.1.abs() {
                worst = (k, r);
            }
        })
        .is_err()
    {
        ss = f64::NAN;
    }
    // As fit_static's OffNormWarning: a dwell far off g (a row written while moving, zeros).
    let off_norm = (worst.1.abs() > super::OFF_NORM_FRACTION * g).then(|| {
        format!(
            "session {i}: dwell {} (counted from 0) is {:.4} off g ({:.0} % of g): it may not \
             be at rest; leave it out and refit",
            worst.0,
            worst.1,
            100.0 * worst.1.abs() / g
        )
    });
    let known = noise.known();
    let s2 = s.f1.s * s.f1.s;
    let chi2_out = if known {
        s.cov.chi2_dof
    } else {
        s.cov.chi2_dof * s2
    };
    let scale = if known { s2 } else { chi2_out };
    let mut params = s.f1.unframe(&s.ml.params);
    let mut std = [f64::NAN; 9];
    if let Some(c) = &s.cov.cov_c {
        for (j, v) in std.iter_mut().enumerate().take(N) {
            *v = output_cov_entry(c, j, j, g, scale);
        }
        if sigma_g > 0.0 {
            let jv = gravity_sensitivity(&params[..N], g);
            for (v, d) in std.iter_mut().zip(jv) {
                *v += (d * sigma_g) * (d * sigma_g);
            }
        }
        for v in &mut std[..N] {
            *v = v.sqrt();
        }
    }
    for v in &mut params[N..] {
        *v = f64::NAN;
    }
    BatchRow {
        params,
        std,
        chi2_dof: chi2_out,
        rms: (ss / n as f64).sqrt(),
        iterations: s.ml.iterations,
        n_dwells: n,
        converged: true,
        status: if s.cov.summary.weak {
            BatchStatus::Weak
        } else {
            BatchStatus::Ok
        },
        message: off_norm,
    }
}

/// Fit independent sessions (each a slice of dwell means, any number of dwells) in
/// parallel. `g` has 1 or `sessions.len()` values; `sigma` (std of each dwell mean per axis,
/// output units) is shared by all sessions, `None` estimates it per session. Never fails
/// per session: see [`BatchRow::status`]. Results are identical whatever the thread count.
pub fn fit_batch(
    sessions: &[&[[f64; 3]]],
    g: &[f64],
    sigma: Option<f64>,
    set: &FitSettings,
) -> Result<Vec<BatchRow>> {
    fit_batch_sigma_g(sessions, g, sigma, None, set)
}

/// [`fit_batch`] with the reference gravity known to `sigma_g` (std, units of `g`; `None` or
/// 0 for exact): its uncertainty is added to every std, as in the single fit.
pub fn fit_batch_sigma_g(
    sessions: &[&[[f64; 3]]],
    g: &[f64],
    sigma: Option<f64>,
    sigma_g: Option<f64>,
    set: &FitSettings,
) -> Result<Vec<BatchRow>> {
    let b = sessions.len();
    if g.len() != 1 && g.len() != b {
        return invalid(format!("g must have 1 or {b} values; got {}", g.len()));
    }
    if let Some(s) = sigma {
        if !(s > 0.0 && s.is_finite()) {
            return invalid(format!(
                "sigma must be a positive, finite std of a dwell mean (output units); got {s}"
            ));
        }
    }
    let sg = match sigma_g {
        Some(x) => {
            for gi in g {
                check_sigma_g(x, *gi)?;
            }
            x
        }
        None => 0.0,
    };
    set.validate()?;
    let noise = match sigma {
        Some(s) => Noise::Uniform([s * s; 3]),
        None => Noise::Estimated,
    };
    let rows = sessions
        .par_iter()
        .enumerate()
        .map_init(
            || Vec::with_capacity(64),
            |pts, (i, means)| {
                let gi = if g.len() == 1 { g[0] } else { g[i] };
                match set.model {
                    Model::Diag => fit_one::<6>(i, means, gi, &noise, sg, set, pts),
                    _ => fit_one::<9>(i, means, gi, &noise, sg, set, pts),
                }
            },
        )
        .collect();
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::super::tests_common::{simulate_noisy, G, TRUTH};
    use super::super::Method;
    use super::*;

    #[test]
    fn ragged_sessions_get_a_status_each_naming_the_dwell() {
        let good = simulate_noisy(Model::Lower, &TRUTH, 20, 90.0, 1e-3, 1);
        let short = simulate_noisy(Model::Lower, &TRUTH, 12, 90.0, 1e-3, 2);
        let mut nan = good.clone();
        nan[3][2] = f64::NAN;
        let same = vec![good[0]; 15];
        let weak = simulate_noisy(Model::Lower, &TRUTH, 20, 25.0, 1e-3, 3);
        let sessions: Vec<&[[f64; 3]]> = vec![&good, &short, &nan, &same, &good[..4], &weak];
        let set = FitSettings::new(Model::Lower, Method::Lm);
        let rows = fit_batch(&sessions, &[G], Some(1e-3), &set).unwrap();
        assert_eq!(rows[0].status, BatchStatus::Ok);
        assert_eq!(rows[1].status.code(), 0);
        assert_eq!(rows[1].n_dwells, 12);
        assert_eq!(rows[2].status, BatchStatus::Invalid);
        assert_eq!(
            rows[2].message.as_deref(),
            Some("session 2: dwell 3 has a NaN mean")
        );
        assert!(rows[2].params.iter().all(|v| v.is_nan()));
        assert_eq!(rows[3].status, BatchStatus::Degenerate);
        assert_eq!(rows[4].status, BatchStatus::Degenerate);
        assert!(rows[4]
            .message
            .as_deref()
            .unwrap()
            .starts_with("session 4: 4 dwells"));
        assert_eq!(rows[5].status, BatchStatus::Weak);
        assert_eq!(rows[5].status.code(), 0);
        assert!(fit_batch(&sessions, &[G, G], None, &set).is_err());
        assert!(fit_batch(&sessions, &[G], Some(-1.0), &set).is_err());
    }

    #[test]
    fn batch_is_identical_on_one_and_two_threads() {
        let data: Vec<Vec<[f64; 3]>> = (0..64)
            .map(|s| simulate_noisy(Model::Lower, &TRUTH, 20, 45.0, 1e-3, 100 + s))
            .collect();
        let sessions: Vec<&[[f64; 3]]> = data.iter().map(|s| s.as_slice()).collect();
        let set = FitSettings::new(Model::Lower, Method::Lm);
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| fit_batch(&sessions, &[G], None, &set).unwrap())
        };
        let (a, b) = (run(1), run(2));
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.params.map(f64::to_bits), y.params.map(f64::to_bits));
            assert_eq!(x.std.map(f64::to_bits), y.std.map(f64::to_bits));
        }
    }
}

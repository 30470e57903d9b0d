//! What the remaining gap is made of: the structure tests on the residual after the
//! calibration fit (and any selected dictionary effect).
//!
//! - Smooth tests, each a set of columns `X` projected off the model's Jacobian and tested by
//!   the sigma-free F form (robust to a mis-scaled noise model), corrected for the family by
//!   the exact min-p method (for the best test; the others report the Bonferroni bound): "attitude" (real spherical harmonics of degree 3 and 4 of the
//!   gravity direction; degree <= 2 is absorbed by the 9 calibration parameters, whose
//!   Jacobian spans `u_i u_j` and `u_i`), "time" and "temperature" (per-axis bias and common
//!   scale, Legendre degree 1 and 2 of the normalised variable), "pose_history" (the previous
//!   dwell's gravity direction: hysteresis).
//! - Persistence: residuals of the first- and second-half dwell means with the calibration
//!   held fixed. Their correlation is near 1 for persistent per-dwell errors and near 0 when
//!   the excess is noise; the test compares the residual scatter per degree of freedom with the
//!   scatter of the half-dwell differences (`F(dof, n)` under noise that does not persist), and
//!   with a known noise model the persistent share of the excess is `(c - k^2) / (c - 1)`, `c`
//!   the residual chi2/dof and `k^2` the mean squared whitened half-dwell difference (the
//!   excess the half differences show is noise; the rest persists within the dwells). The
//!   verdict is "noise_model" or "per_dwell" by the likelihood of the residual and
//!   half-difference scatter under "the excess is noise", "it persists" and their mixture
//!   (see `excess_is_noise`). Noise with memory longer than a dwell (1/f below the dwell rate, a random
//!   walk across the session) is a per-dwell offset by this definition.
//! - Whether there is a gap at all: with a noise model and half-dwell means, two independent
//!   checks of the noise model, Bonferroni over the two (each at `alpha / 2`): the residual
//!   chi2 of the dwell means, and the whitened half-dwell differences (`chi2(n)`). Half-dwell
//!   differences that exceed the model while the means do not make the verdict
//!   "noise_model" (the noise model is too optimistic at the dwell's time scale). Without
//!   half-dwell means the residual chi2 alone, at `alpha`.
//! - Order of the decisions: the quantisation bias when there is a gap and it explains at
//!   least half of the excess (it is predicted from the LSB and the within-dwell noise, and
//!   is itself a function of attitude, time and temperature); a significant smooth test
//!   (family-wise at `alpha`, or at `alpha / 2` when the gap is noise that does not persist
//!   within a dwell: a smooth structure is constant within a dwell, so it must beat that
//!   explanation of the same excess); no gap ("none"); "noise_model" or "per_dwell" as above.
//! - Empirical dwell-mean noise from the half-dwell differences, `var((m1 - m2)/2)` propagated
//!   to the norm, against the noise model used, white noise and the Allan model.
//! - Quantisation: the bias a dwell mean carries when the within-dwell noise is below about one
//!   LSB (variance from the Fourier series of the quantiser error under Gaussian noise).
//! - Per-dwell random offset: `s_d` solving `sum r_k^2 / (sigma_k^2 + s_d^2) = dof` (moment
//!   estimate, Paule-Mandel form), in the residual's units.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use super::engine::{basis, member_of, screen, EngineResult, TestCfg};
use super::minp::min_p;
use super::special::{chi2_isf, chi2_sf, f_sf, pearson};
use super::{GapOptions, Status, TestMode};
use crate::error::Result;
use crate::lsq::RangeBasis;
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;

/// The verdict: what the remaining gap is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// No gap and no structure.
    None,
    /// The excess does not persist within a dwell: the noise model is too optimistic.
    NoiseModel,
    /// A smooth function of attitude beyond what the calibration absorbs.
    Attitude,
    /// A smooth function of time.
    Time,
    /// A smooth function of temperature.
    Temperature,
    /// It depends on the previous pose (hysteresis).
    PoseHistory,
    /// Dwell means carry a quantisation bias (within-dwell noise below about one LSB).
    Quantization,
    /// Persistent per-dwell offsets, smooth in nothing tested.
    PerDwell,
}

impl Verdict {
    /// Public name.
    pub fn name(self) -> &'static str {
        match self {
            Verdict::None => "none",
            Verdict::NoiseModel => "noise_model",
            Verdict::Attitude => "attitude",
            Verdict::Time => "time",
            Verdict::Temperature => "temperature",
            Verdict::PoseHistory => "pose_history",
            Verdict::Quantization => "quantization",
            Verdict::PerDwell => "per_dwell",
        }
    }

    fn of_smooth(name: &str) -> Verdict {
        match name {
            "attitude" => Verdict::Attitude,
            "time" => Verdict::Time,
            "temperature" => Verdict::Temperature,
            _ => Verdict::PoseHistory,
        }
    }
}

/// A smooth structure test as a system provides it: per-row columns (physical units, before
/// whitening) or why it cannot run.
#[derive(Debug, Clone)]
pub struct SmoothTest {
    /// "attitude", "time", "temperature" or "pose_history".
    pub name: &'static str,
    /// Columns (`n x c`), or `None` when unavailable.
    pub cols: Option<DMatrix<f64>>,
    /// Rows the test cannot judge (the first dwell has no previous pose): each gets an
    /// indicator column in the null model of this test alone, so its residual carries no
    /// weight in it.
    pub excluded: Vec<usize>,
    /// Why it is unavailable.
    pub status: Status,
}

impl SmoothTest {
    /// A test with its columns.
    pub fn ready(name: &'static str, cols: DMatrix<f64>) -> Self {
        SmoothTest {
            name,
            cols: Some(cols),
            excluded: vec![],
            status: Status::Testable,
        }
    }
    /// A test with its columns that leaves the rows `excluded` out.
    pub fn ready_without(name: &'static str, cols: DMatrix<f64>, excluded: Vec<usize>) -> Self {
        SmoothTest {
            excluded,
            ..SmoothTest::ready(name, cols)
        }
    }
    /// A test that cannot run on this session.
    pub fn unavailable(name: &'static str, status: Status) -> Self {
        SmoothTest {
            name,
            cols: None,
            excluded: vec![],
            status,
        }
    }
}

/// What the structure stage needs besides the engine's result (per residual row).
#[derive(Debug, Clone, Default)]
pub struct StructureInput {
    /// Smooth tests.
    pub smooth: Vec<SmoothTest>,
    /// Residuals (physical) of the first- and second-half means, calibration held fixed.
    pub halves: Option<(Vec<f64>, Vec<f64>)>,
    /// Predicted variance of each residual from the quantisation bias of the dwell mean.
    pub quant_var: Option<Vec<f64>>,
    /// Standard deviation of each residual under white noise (var / count).
    pub white_sigma: Option<Vec<f64>>,
    /// Standard deviation of each residual under the Allan model at the dwell length.
    pub allan_sigma: Option<Vec<f64>>,
    /// Unused by static sessions; reserved for systems whose rows come in groups.
    pub group_rows: Option<Vec<usize>>,
}

/// One structure test's outcome.
#[derive(Debug, Clone)]
pub struct StructureTest {
    /// "attitude", "time", "temperature", "pose_history", "persistence", "quantization",
    /// "per_dwell".
    pub name: &'static str,
    /// Testable, blind (absorbed), too few rows, or why unavailable.
    pub status: Status,
    /// Columns offered.
    pub n_columns: usize,
    /// Directions tested (outside the model's range).
    pub d: usize,
    /// Denominator degrees of freedom (F tests).
    pub dof2: f64,
    /// Test statistic (F for the smooth and persistence tests; see the module docs).
    pub statistic: f64,
    /// p-value.
    pub p_value: f64,
    /// Family-wise adjusted p-value (smooth tests; the p-value itself otherwise).
    pub p_adjusted: f64,
    /// Fraction of the residual (chi2) it explains.
    pub explained: f64,
}

impl StructureTest {
    fn new(name: &'static str, status: Status) -> Self {
        StructureTest {
            name,
            status,
            n_columns: 0,
            d: 0,
            dof2: f64::NAN,
            statistic: f64::NAN,
            p_value: f64::NAN,
            p_adjusted: f64::NAN,
            explained: f64::NAN,
        }
    }
}

/// Empirical dwell-mean noise from the half-dwell differences.
#[derive(Debug, Clone, Copy)]
pub struct NoiseEmpirical {
    /// Rows with both halves.
    pub n: usize,
    /// RMS of `(r1 - r2)/2`: the dwell-mean noise of the residual (physical units).
    pub rms: f64,
    /// RMS of the noise model used.
    pub rms_model: f64,
    /// RMS of the white-noise model (NaN when not given).
    pub rms_white: f64,
    /// RMS of the Allan model (NaN when not given).
    pub rms_allan: f64,
    /// Empirical over model noise (RMS of the whitened half differences).
    pub ratio_model: f64,
    /// Empirical over white noise.
    pub ratio_white: f64,
    /// Empirical over the Allan model.
    pub ratio_allan: f64,
    /// p-value of "the half differences are consistent with the model": chi2(n).
    pub p_model: f64,
}

/// The structure of the remaining gap.
#[derive(Debug, Clone)]
pub struct Structure {
    /// The verdict.
    pub verdict: Verdict,
    /// The statistic behind it: F of the deciding smooth test; the persistent share of the
    /// excess for "noise_model" and "per_dwell" (chi2/dof for "per_dwell" without half-dwell
    /// means); the share of the excess explained for "quantization"; chi2/dof for "none".
    pub statistic: f64,
    /// Its p-value.
    pub p_value: f64,
    /// Correlation of the half-dwell residuals (NaN: untestable).
    pub persistence: f64,
    /// Whether half-dwell means were given.
    pub persistence_testable: bool,
    /// Random per-dwell offset that makes chi2/dof = 1 (residual units; NaN without a noise
    /// model).
    pub per_dwell_rms: f64,
    /// RMS of the predicted quantisation bias of the residual (NaN without LSB and variance).
    pub quantization_rms: f64,
    /// Every test.
    pub tests: Vec<StructureTest>,
    /// Empirical dwell-mean noise (None without half means).
    pub noise_empirical: Option<NoiseEmpirical>,
}

// ------------------------------------------------------------------------------------------
// Columns.

/// Real spherical harmonics of degree 3 and 4 (16 columns, unnormalised) of unit vectors.
pub fn harmonics_34(u: &[[f64; 3]]) -> DMatrix<f64> {
    DMatrix::from_fn(u.len(), 16, |k, c| {
        let [x, y, z] = u[k];
        let (x2, y2, z2) = (x * x, y * y, z * z);
        match c {
            0 => y * (3.0 * x2 - y2),
            1 => x * y * z,
            2 => y * (5.0 * z2 - 1.0),
            3 => z * (5.0 * z2 - 3.0),
            4 => x * (5.0 * z2 - 1.0),
            5 => z * (x2 - y2),
            6 => x * (x2 - 3.0 * y2),
            7 => x * y * (x2 - y2),
            8 => y * z * (3.0 * x2 - y2),
            9 => x * y * (7.0 * z2 - 1.0),
            10 => y * z * (7.0 * z2 - 3.0),
            11 => 35.0 * z2 * z2 - 30.0 * z2 + 3.0,
            12 => x * z * (7.0 * z2 - 3.0),
            13 => (x2 - y2) * (7.0 * z2 - 1.0),
            14 => x * z * (x2 - 3.0 * y2),
            _ => x2 * (x2 - 3.0 * y2) - y2 * (3.0 * x2 - y2),
        }
    })
}

/// Smooth trend columns in a variable `x` (time or temperature): a per-axis bias
/// (`w_i P_j(s)`, `w = d r / d am`) and a common scale (`P_j(s)`), Legendre `P_1`, `P_2` of
/// `s` = `x` mapped to [-1, 1] (8 columns).
pub fn trend_columns(x: &[f64], w: &[[f64; 3]]) -> DMatrix<f64> {
    let lo = x.iter().cloned().fold(f64::INFINITY, f64::min);
    let hi = x.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let span = (hi - lo).max(1e-300);
    DMatrix::from_fn(x.len(), 8, |k, c| {
        let s = 2.0 * (x[k] - lo) / span - 1.0;
        let p = [s, 1.5 * s * s - 0.5];
        match c {
            0..=5 => w[k][c % 3] * p[c / 3],
            _ => p[c - 6],
        }
    })
}

/// Variance of the bias of a dwell mean from quantisation to steps of `lsb`, for Gaussian
/// noise whose quantised samples have variance `sample_var` (Sheppard-corrected to the
/// underlying variance): `sum_j lsb^2 / (2 pi^2 j^2) exp(-4 pi^2 j^2 s^2 / lsb^2)`, which is
/// `lsb^2 / 12` without noise and vanishes once the noise exceeds about one LSB.
pub fn quantization_bias_var(sample_var: f64, lsb: f64) -> f64 {
    if !(lsb > 0.0) || !sample_var.is_finite() {
        return 0.0;
    }
    let s2 = (sample_var - lsb * lsb / 12.0).max(0.0);
    if s2 == 0.0 {
        return lsb * lsb / 12.0;
    }
    let pi2 = std::f64::consts::PI * std::f64::consts::PI;
    let x = 4.0 * pi2 * s2 / (lsb * lsb);
    let mut sum = 0.0;
    for j in 1..=2000 {
        let jf = j as f64;
        let term = (-x * jf * jf).exp() / (jf * jf);
        sum += term;
        if term < 1e-17 * sum {
            break;
        }
    }
    lsb * lsb / (2.0 * pi2) * sum
}

// ------------------------------------------------------------------------------------------
// Stages.

/// Screen every smooth test against the final model and correct for the family by min-p.
fn smooth_stage(
    sin: &StructureInput,
    eng: &EngineResult,
    opt: &GapOptions,
) -> Result<Vec<StructureTest>> {
    let b = basis(&eng.jac_after)?;
    let qb = Arc::new(b.q.clone());
    let e = DVector::from_column_slice(&eng.e_after);
    let rss = eng.chi2_after;
    // The sigma-free F form: the alternative to a smooth structure is an unstructured excess
    // of unknown size (per-dwell offsets, correlated noise, quantisation), under which F is
    // exact. (A chi2 form, even when the half-dwell differences confirm the noise model,
    // mistakes per-dwell offsets for structure: the remainder after 16 columns is too short to
    // show that the noise model does not hold.)
    let cfg = TestCfg {
        mode: TestMode::F,
        trust_level: opt.trust_level,
        sine_tol: opt.sine_tol,
        estimate: false,
    };
    let mut out = vec![];
    let mut fam = vec![];
    for st in &sin.smooth {
        let Some(cols) = &st.cols else {
            out.push(StructureTest::new(st.name, st.status));
            continue;
        };
        let wc = DMatrix::from_fn(cols.nrows(), cols.ncols(), |k, c| {
            cols[(k, c)] / eng.sigma_after[k]
        });
        let own = without_rows(&eng.jac_after, &e, &st.excluded)?;
        let (b_t, e_t, rss_t, q_t) = match &own {
            Some((b2, e2)) => (b2, e2, e2.norm_squared(), Arc::new(b2.q.clone())),
            None => (&b, &e, rss, qb.clone()),
        };
        let sc = screen(&wc, b_t, e_t, rss_t, cfg);
        // Absorbed because the dwells leave too little room for the columns (not because the
        // pattern is one the calibration has): too few dwells.
        let crowded = sc.status == Status::Blind && wc.nrows() < b_t.rank + wc.ncols() + 1;
        let mut t = StructureTest::new(
            st.name,
            if crowded {
                Status::TooFewRows
            } else {
                sc.status
            },
        );
        t.n_columns = cols.ncols();
        t.d = sc.d;
        t.dof2 = sc.dof2;
        if sc.status == Status::Testable {
            t.statistic = if sc.chi2_used { sc.score } else { sc.f };
            t.p_value = sc.p;
            t.explained = sc.score / rss.max(1e-300);
            fam.push(member_of(&sc, &q_t));
        }
        out.push(t);
    }
    // The exact min-p value for the best test (the one a verdict can rest on); the others get
    // the Bonferroni bound M p, an upper bound of their min-p value.
    let m = fam.len() as f64;
    let best = out
        .iter()
        .filter(|t| t.status == Status::Testable)
        .map(|t| t.p_value)
        .fold(f64::INFINITY, f64::min);
    for t in out.iter_mut().filter(|t| t.status == Status::Testable) {
        t.p_adjusted = if t.p_value == best && t.p_value < opt.alpha {
            min_p(&fam, t.p_value, opt.alpha, opt.n_draws)
        } else {
            (m * t.p_value).min(1.0)
        };
    }
    Ok(out)
}

/// The null model of a test that leaves the rows `excluded` out: the range basis of the
/// whitened Jacobian `j` with an indicator column per excluded row, and the residual `e`
/// projected off those columns. `None` when no row is excluded.
fn without_rows(
    j: &DMatrix<f64>,
    e: &DVector<f64>,
    excluded: &[usize],
) -> Result<Option<(RangeBasis, DVector<f64>)>> {
    if excluded.is_empty() {
        return Ok(None);
    }
    let (n, p) = (j.nrows(), j.ncols());
    let mut aug = DMatrix::zeros(n, p + excluded.len());
    aug.view_mut((0, 0), (n, p)).copy_from(j);
    for (c, &k) in excluded.iter().enumerate() {
        if k < n {
            aug[(k, p + c)] = 1.0;
        }
    }
    let b = basis(&aug)?;
    let e2 = e - &b.q * (b.q.transpose() * e);
    Ok(Some((b, e2)))
}

/// Persistence test and the empirical noise from the half-dwell residuals.
fn persistence(
    sin: &StructureInput,
    eng: &EngineResult,
) -> (StructureTest, f64, Option<NoiseEmpirical>) {
    let mut t = StructureTest::new("persistence", Status::NoHalfMeans);
    let Some((r1, r2)) = &sin.halves else {
        return (t, f64::NAN, None);
    };
    t.status = Status::TooFewRows;
    let sig = &eng.sigma_after;
    let ok: Vec<usize> = (0..r1.len())
        .filter(|&k| r1[k].is_finite() && r2[k].is_finite() && sig[k] > 0.0)
        .collect();
    let n = ok.len();
    let d1: Vec<f64> = ok.iter().map(|&k| r1[k] / sig[k]).collect();
    let d2: Vec<f64> = ok.iter().map(|&k| r2[k] / sig[k]).collect();
    let corr = pearson(&d1, &d2).0;
    let half: Vec<f64> = ok.iter().map(|&k| 0.5 * (r1[k] - r2[k])).collect();
    let dw2: f64 = ok
        .iter()
        .zip(&half)
        .map(|(&k, h)| (h / sig[k]).powi(2))
        .sum();
    let ratio_of = |s: &Option<Vec<f64>>| {
        s.as_ref().map_or(f64::NAN, |s| {
            (ok.iter()
                .zip(&half)
                .map(|(&k, h)| (h / s[k]).powi(2))
                .sum::<f64>()
                / n as f64)
                .sqrt()
        })
    };
    let rms_of = |s: &Option<Vec<f64>>| {
        s.as_ref().map_or(f64::NAN, |s| {
            (ok.iter().map(|&k| s[k] * s[k]).sum::<f64>() / n as f64).sqrt()
        })
    };
    let ne = NoiseEmpirical {
        n,
        rms: super::engine::rms(&half),
        rms_model: rms_of(&Some(sig.clone())),
        rms_white: rms_of(&sin.white_sigma),
        rms_allan: rms_of(&sin.allan_sigma),
        ratio_model: (dw2 / n.max(1) as f64).sqrt(),
        ratio_white: ratio_of(&sin.white_sigma),
        ratio_allan: ratio_of(&sin.allan_sigma),
        p_model: if eng.noise_known {
            chi2_sf(dw2, n as f64)
        } else {
            f64::NAN
        },
    };
    let dof = eng.dof_after as f64;
    if n >= 3 && dof >= 1.0 && dw2 > 0.0 {
        t.status = Status::Testable;
        t.statistic = (eng.chi2_after / dof) / (dw2 / n as f64);
        t.p_value = f_sf(t.statistic, dof, n as f64);
        t.p_adjusted = t.p_value;
        t.dof2 = n as f64;
        // Persistent share of the excess: with a known noise model, the part of the excess
        // chi2/dof (c - 1) that the half-dwell differences (kappa^2 - 1) do not show.
        let (c, k2) = (eng.chi2_after / dof, dw2 / n as f64);
        t.explained = if eng.noise_known && c > 1.0 {
            ((c - k2) / (c - 1.0)).clamp(0.0, 1.0)
        } else {
            (1.0 - 1.0 / t.statistic).max(0.0)
        };
    }
    (t, corr, Some(ne))
}

/// Per-dwell random offset `s` with `sum r_k^2 / (sigma_k^2 + s^2) = dof` (0 when the
/// residuals do not exceed the noise model).
pub fn per_dwell_offset(r: &[f64], sigma: &[f64], dof: usize) -> f64 {
    let f = |s2: f64| -> f64 {
        r.iter()
            .zip(sigma)
            .map(|(r, s)| r * r / (s * s + s2))
            .sum::<f64>()
    };
    let dof = dof as f64;
    if !(dof > 0.0) || !(f(0.0) > dof) {
        return 0.0;
    }
    let (mut lo, mut hi) = (0.0, r.iter().map(|v| v * v).sum::<f64>().max(1e-300));
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if f(mid) > dof {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    (0.5 * (lo + hi)).sqrt()
}

/// The quantisation test: how much of the excess chi2 the predicted quantisation bias of the
/// dwell means explains, and the p-value of what remains with it in the noise model.
fn quantization(sin: &StructureInput, eng: &EngineResult) -> (StructureTest, f64) {
    let mut t = StructureTest::new("quantization", Status::NoLsb);
    let Some(q) = &sin.quant_var else {
        return (t, f64::NAN);
    };
    let qrms = (q.iter().sum::<f64>() / q.len().max(1) as f64).sqrt();
    if !eng.noise_known || eng.dof_after == 0 {
        t.status = if eng.noise_known {
            Status::TooFewRows
        } else {
            Status::NoNoiseModel
        };
        return (t, qrms);
    }
    let (r, s) = (&eng.resid_after, &eng.sigma_after);
    let chi2_q: f64 = (0..r.len())
        .map(|k| r[k] * r[k] / (s[k] * s[k] + q[k]))
        .sum();
    let dof = eng.dof_after as f64;
    t.status = Status::Testable;
    t.statistic = chi2_q / dof;
    t.p_value = chi2_sf(chi2_q, dof);
    t.p_adjusted = t.p_value;
    t.explained = if eng.chi2_after > dof {
        ((eng.chi2_after - chi2_q) / (eng.chi2_after - dof)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (t, qrms)
}

/// The per-dwell offset as a test: its share of the residual variance and the remaining gap.
fn per_dwell(eng: &EngineResult) -> (StructureTest, f64) {
    let st = if eng.noise_known {
        Status::TooFewRows
    } else {
        Status::NoNoiseModel
    };
    let mut t = StructureTest::new("per_dwell", st);
    if !eng.noise_known || eng.dof_after == 0 {
        return (t, f64::NAN);
    }
    let s = per_dwell_offset(&eng.resid_after, &eng.sigma_after, eng.dof_after);
    let ms2 = eng.sigma_after.iter().map(|v| v * v).sum::<f64>() / eng.n as f64;
    t.status = Status::Testable;
    t.statistic = eng.chi2_after / eng.dof_after as f64;
    t.p_value = eng.p_after;
    t.p_adjusted = eng.p_after;
    t.explained = s * s / (s * s + ms2);
    (t, s)
}

/// Whether the excess is mostly noise (the half-dwell differences show it) rather than
/// persistent offsets. Whitened by the noise model, the residuals `s` (`m` degrees of freedom,
/// mean square `c`) and the half-dwell differences `d` (`n` dwells, mean square `k^2`) are
/// independent normals with variances `v_s` and `v_d`, with log-likelihood
/// `-(m/2)(c/v_s + ln v_s) - (n/2)(k^2/v_d + ln v_d)`. Three models: "noise" (`v_s = v_d`,
/// fitted to both), "persistent" (`v_d = 1`, the model's noise) and their mixture (`v_d >= 1`
/// noise excess, `v_s >= v_d`, both fitted). When the mixture fits significantly better than
/// the better pure model (likelihood-ratio chi2(1) at level `alpha`), the larger component
/// decides (persistent share `(c - v_d) / (c - 1)` at least one half: persistent); otherwise the
/// better pure model. Without a noise model: never (the F test of persistence decides).
fn excess_is_noise(eng: &EngineResult, ne: &NoiseEmpirical, alpha: f64) -> bool {
    let k2 = ne.ratio_model * ne.ratio_model;
    let m = eng.dof_after as f64;
    let n = ne.n as f64;
    let c = eng.chi2_after / m.max(1.0);
    if !(eng.noise_known && c > 1.0 && m > 0.0 && n > 0.0 && k2 > 0.0) {
        return false;
    }
    let ll = |vs: f64, vd: f64| -0.5 * m * (c / vs + vs.ln()) - 0.5 * n * (k2 / vd + vd.ln());
    let vn = (m * c + n * k2) / (m + n);
    let (l_noise, l_pers) = (ll(vn, vn), ll(c, 1.0));
    let vd = k2.max(1.0);
    let l_mix = ll(c.max(vd), vd);
    if 2.0 * (l_mix - l_noise.max(l_pers)) > chi2_isf(alpha, 1.0) {
        (c - vd) / (c - 1.0) < 0.5
    } else {
        l_noise > l_pers
    }
}

/// The verdict from the tests (see the module docs for the order of the decisions).
fn decide(
    tests: &[StructureTest],
    eng: &EngineResult,
    halves: bool,
    noise_emp: Option<&NoiseEmpirical>,
    alpha: f64,
) -> (Verdict, f64, f64) {
    let find = |nm: &str| {
        tests
            .iter()
            .find(|t| t.name == nm && t.status == Status::Testable)
    };
    let best_smooth = tests
        .iter()
        .filter(|t| {
            matches!(t.name, "attitude" | "time" | "temperature" | "pose_history")
                && t.status == Status::Testable
        })
        .min_by(|a, b| a.p_adjusted.total_cmp(&b.p_adjusted));
    let pers = find("persistence");
    // With a noise model and half-dwell means, two independent checks of it: the residuals
    // (the dwell means) and the half-dwell differences, Bonferroni over the two.
    let half_p = noise_emp.map_or(f64::NAN, |ne| ne.p_model);
    let (means_gap, half_gap) = (eng.p_after < alpha / 2.0, half_p < alpha / 2.0);
    let gap = if eng.noise_known && half_p.is_finite() {
        means_gap || half_gap
    } else if eng.noise_known {
        eng.p_after < alpha
    } else {
        pers.is_some_and(|t| t.p_value < alpha)
    };
    // The predicted quantisation bias (from the LSB and the within-dwell noise, not from the
    // residual's pattern) comes first: it is itself a function of the true output, so of the
    // attitude, time and temperature, and a smooth test can pick up part of it.
    if let Some(q) = find("quantization").filter(|q| gap && q.explained >= 0.5) {
        return (Verdict::Quantization, q.explained, q.p_value);
    }
    // The excess is noise that does not persist within a dwell (the half-dwell differences
    // show it). A smooth structure is constant within a dwell, so it would persist: to be
    // named beside that explanation of the same excess it must pass at alpha / 2
    // (Bonferroni over the two explanations).
    let noise_excess = gap
        && halves
        && pers.is_some()
        && ((half_gap && !means_gap)
            || noise_emp.is_some_and(|ne| excess_is_noise(eng, ne, alpha)));
    let smooth_level = if noise_excess { alpha / 2.0 } else { alpha };
    if let Some(t) = best_smooth.filter(|t| t.p_adjusted < smooth_level) {
        return (Verdict::of_smooth(t.name), t.statistic, t.p_adjusted);
    }
    if !gap {
        return (
            Verdict::None,
            eng.chi2_after / eng.dof_after.max(1) as f64,
            eng.p_after,
        );
    }
    match (halves, pers) {
        (true, Some(p)) if half_gap && !means_gap => (Verdict::NoiseModel, p.explained, half_p),
        (true, Some(p)) if noise_excess => (Verdict::NoiseModel, p.explained, p.p_value),
        (true, Some(p)) => (Verdict::PerDwell, p.explained, p.p_value),
        _ => (
            Verdict::PerDwell,
            eng.chi2_after / eng.dof_after.max(1) as f64,
            eng.p_after,
        ),
    }
}

/// Run every structure test on the engine's final model.
pub fn run(sin: &StructureInput, eng: &EngineResult, opt: &GapOptions) -> Result<Structure> {
    let mut tests = smooth_stage(sin, eng, opt)?;
    let (pt, corr, ne) = persistence(sin, eng);
    let (qt, qrms) = quantization(sin, eng);
    let (dt, s) = per_dwell(eng);
    tests.extend([pt, qt, dt]);
    let (verdict, statistic, p_value) =
        decide(&tests, eng, sin.halves.is_some(), ne.as_ref(), opt.alpha);
    Ok(Structure {
        verdict,
        statistic,
        p_value,
        persistence: corr,
        persistence_testable: sin.halves.is_some(),
        per_dwell_rms: s,
        quantization_rms: qrms,
        tests,
        noise_empirical: ne,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A testable structure test with the given adjusted p-value and explained share.
    fn tested(name: &'static str, p: f64, explained: f64) -> StructureTest {
        let mut t = StructureTest::new(name, Status::Testable);
        (t.p_value, t.p_adjusted, t.explained, t.statistic) = (p, p, explained, 2.0);
        t
    }

    /// Half-dwell differences whose mean square (whitened) is `k2`, with p-value `p`.
    fn halves_noise(k2: f64, p: f64) -> NoiseEmpirical {
        NoiseEmpirical {
            n: 40,
            rms: 1.0,
            rms_model: 1.0,
            rms_white: f64::NAN,
            rms_allan: f64::NAN,
            ratio_model: k2.sqrt(),
            ratio_white: f64::NAN,
            ratio_allan: f64::NAN,
            p_model: p,
        }
    }

    #[test]
    fn decisions_put_quantisation_first_and_hold_smooth_tests_to_alpha_half_beside_noise() {
        let eng = |p_after: f64, c: f64| EngineResult {
            noise_known: true,
            p_after,
            chi2_after: 30.0 * c,
            dof_after: 30,
            ..Default::default()
        };
        let a = 0.05;
        // A gap in the means that a persistent offset explains (the half-dwell differences
        // agree with the model), and a smooth pattern at p = 0.03.
        let persistent = (eng(1e-6, 3.0), halves_noise(1.0, 0.5));
        // The same excess shown by the half-dwell differences too: noise, not persistent.
        let noise = (eng(1e-6, 3.0), halves_noise(3.0, 1e-6));
        let run = |(e, ne): &(EngineResult, NoiseEmpirical), tests: &[StructureTest]| {
            decide(tests, e, true, Some(ne), a).0
        };
        let pers = tested("persistence", 1e-3, 0.5);
        let smooth = |p| tested("time", p, 0.3);
        let quant = |x| tested("quantization", 0.2, x);
        // Quantisation explaining half the excess comes before any smooth test.
        let t = [smooth(1e-9), pers.clone(), quant(0.6)];
        assert_eq!(run(&persistent, &t), Verdict::Quantization);
        let t = [smooth(1e-9), pers.clone(), quant(0.4)];
        assert_eq!(run(&persistent, &t), Verdict::Time);
        // Beside a persistent excess the smooth tests keep alpha; beside noise, alpha / 2.
        let t = [smooth(0.03), pers.clone(), quant(0.0)];
        assert_eq!(run(&persistent, &t), Verdict::Time);
        assert_eq!(run(&noise, &t), Verdict::NoiseModel);
        let t = [smooth(0.02), pers.clone(), quant(0.0)];
        assert_eq!(run(&noise, &t), Verdict::Time);
        // Without a gap there is no quantisation verdict, and smooth tests keep alpha.
        let quiet = (eng(0.5, 1.0), halves_noise(1.0, 0.5));
        let t = [smooth(0.5), pers.clone(), quant(0.9)];
        assert_eq!(run(&quiet, &t), Verdict::None);
        let t = [smooth(0.03), pers, quant(0.9)];
        assert_eq!(run(&quiet, &t), Verdict::Time);
    }

    #[test]
    fn harmonics_are_orthogonal_on_a_dense_sphere() {
        // Fibonacci sphere: the 16 degree-3/4 harmonics are orthogonal to every polynomial of
        // degree <= 2 (what the calibration absorbs) and have full rank.
        let n = 2000;
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        let u: Vec<[f64; 3]> = (0..n)
            .map(|k| {
                let z = 1.0 - 2.0 * (k as f64 + 0.5) / n as f64;
                let r = (1.0 - z * z).sqrt();
                let th = golden * k as f64;
                [r * th.cos(), r * th.sin(), z]
            })
            .collect();
        let h = harmonics_34(&u);
        let low = DMatrix::from_fn(n, 10, |k, c| {
            let [x, y, z] = u[k];
            [1.0, x, y, z, x * x, y * y, z * z, x * y, x * z, y * z][c]
        });
        let g = low.transpose() * &h / n as f64;
        assert!(g.amax() < 2e-3, "{}", g.amax());
        let b = basis(&h).unwrap();
        assert_eq!(b.rank, 16);
    }

    #[test]
    fn quantization_bias_variance_limits() {
        let lsb = 2.0;
        assert!((quantization_bias_var(0.0, lsb) - lsb * lsb / 12.0).abs() < 1e-3);
        assert!(quantization_bias_var(4.0 * lsb * lsb, lsb) < 1e-12);
        // 0.3 LSB noise (observed variance includes the quantisation's lsb^2/12).
        let v = quantization_bias_var(0.09 * lsb * lsb + lsb * lsb / 12.0, lsb);
        let want = lsb * lsb / (2.0 * std::f64::consts::PI.powi(2))
            * (-4.0 * std::f64::consts::PI.powi(2) * 0.09).exp();
        assert!((v - want).abs() < 1e-3 * want, "{v} {want}");
    }

    #[test]
    fn per_dwell_offset_solves_the_moment_equation() {
        let r = [0.3, -0.5, 0.2, 0.6, -0.4, 0.1];
        let s = [0.1; 6];
        let sd = per_dwell_offset(&r, &s, 4);
        let lhs: f64 = r.iter().map(|v| v * v / (0.01 + sd * sd)).sum();
        assert!((lhs - 4.0).abs() < 1e-9, "{lhs}");
        assert_eq!(per_dwell_offset(&[0.01; 6], &s, 4), 0.0);
    }

    #[test]
    fn without_rows_adds_an_indicator_to_the_null_model() {
        // A line fitted to 8 rows; leaving row 0 out adds its indicator to the basis, and the
        // residual loses its row-0 component (and stays orthogonal to the line).
        let j = DMatrix::from_fn(8, 2, |k, c| if c == 0 { 1.0 } else { k as f64 });
        let e = DVector::from_fn(8, |k, _| [3.0, -1.0, 0.5, 0.2, -0.4, 0.1, 0.3, -0.2][k]);
        assert!(without_rows(&j, &e, &[]).unwrap().is_none());
        let (b, e2) = without_rows(&j, &e, &[0]).unwrap().unwrap();
        assert_eq!(b.rank, 3);
        assert!(e2[0].abs() < 1e-12, "{}", e2[0]);
        assert!((j.transpose() * &e2).norm() < 1e-12);
        // What is left is the residual of the same line fitted to rows 1..8 alone.
        let j7 = j.rows(1, 7).into_owned();
        let e7 = e.rows(1, 7).into_owned();
        let p = (j7.transpose() * &j7)
            .lu()
            .solve(&(j7.transpose() * &e7))
            .unwrap();
        let r7 = &e7 - &j7 * p;
        assert!((e2.rows(1, 7) - r7).norm() < 1e-12);
    }

    #[test]
    fn trend_columns_span_bias_and_scale_trends() {
        let x: Vec<f64> = (0..10).map(|k| k as f64).collect();
        let w = vec![[1.0, 0.5, -0.2]; 10];
        let c = trend_columns(&x, &w);
        assert_eq!(c.ncols(), 8);
        assert!((c[(0, 0)] + 1.0).abs() < 1e-12 && (c[(9, 6)] - 1.0).abs() < 1e-12);
        assert!((c[(9, 7)] - 1.0).abs() < 1e-12 && (c[(0, 4)] - 0.5).abs() < 1e-12);
    }
}

#[cfg(test)]
mod session_tests {

    use super::*;
    use crate::gap::statics::tests::Rng;
    use crate::gap::statics::{self, DwellExtras, Effect, StaticInput};

    /// A 40-dwell static session with half-dwell means: white noise `scale * sigma` per half
    /// (reported `sigma`), persistent per-dwell offsets `offset` (m/s^2, along gravity) and an
    /// attitude pattern of degree 3 (`att`, m/s^2).
    fn session(seed: u64, scale: f64, offset: f64, att: f64) -> StaticInput {
        let mut rng = Rng(seed);
        let (g, sigma, n) = (9.81, 1e-4, 40);
        let b = [0.05, -0.03, 0.02];
        let (mut mean, mut half, mut t) = (vec![], vec![], vec![]);
        for i in 0..n {
            let mut u = [rng.normal(), rng.normal(), rng.normal()];
            let r = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
            u.iter_mut().for_each(|v| *v /= r);
            let extra = offset * rng.normal() + att * u[0] * u[1] * u[2] * 10.0;
            let a: Vec<f64> = u.iter().map(|v| v * (g + extra)).collect();
            let h: Vec<[f64; 3]> = (0..2)
                .map(|_| {
                    let mut m = [0.0; 3];
                    for r in 0..3 {
                        m[r] = a[r] + b[r] + scale * sigma * 2f64.sqrt() * rng.normal();
                    }
                    m
                })
                .collect();
            mean.push([0, 1, 2].map(|r| 0.5 * (h[0][r] + h[1][r])));
            half.push([h[0], h[1]]);
            t.push(90.0 * i as f64);
        }
        StaticInput {
            mean,
            var: Some(vec![[sigma * sigma; 3]; n]),
            t: Some(t),
            temperature: None,
            g,
            calibration: None,
            extras: DwellExtras {
                half_mean: Some(half),
                ..DwellExtras::default()
            },
        }
    }

    fn verdict(inp: &StaticInput) -> Structure {
        statics::diagnose(inp, &Effect::ALL, &GapOptions::default())
            .unwrap()
            .structure
    }

    /// Six faces in a fixed order, `cycles` times over (each pose always follows the same
    /// pose), white noise sigma 1e-4 per axis, and an offset `first` (m/s^2, along gravity)
    /// on the first dwell alone (a warm-up).
    fn fixed_cycle(seed: u64, cycles: usize, first: f64) -> StaticInput {
        let mut rng = Rng(seed);
        let (g, sigma) = (9.81, 1e-4);
        let faces = [
            [0.0, 0.0, 1.0],
            [0.0, 0.0, -1.0],
            [0.0, 1.0, 0.0],
            [0.0, -1.0, 0.0],
            [1.0, 0.0, 0.0],
            [-1.0, 0.0, 0.0],
        ];
        let (mut mean, mut half) = (vec![], vec![]);
        for k in 0..6 * cycles {
            // Placed on a fixture: the same few degrees off the face each time, within 0.06 deg.
            let tilt = [
                [0.03, -0.02, 0.0],
                [0.01, 0.02, 0.0],
                [-0.02, 0.0, 0.03],
                [0.02, 0.0, -0.01],
                [0.0, 0.03, 0.02],
                [0.0, -0.01, -0.03],
            ][k % 6];
            let mut u = [0, 1, 2].map(|i| faces[k % 6][i] + tilt[i] + 0.001 * rng.normal());
            let r = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
            u.iter_mut().for_each(|v| *v /= r);
            let extra = if k == 0 { first } else { 0.0 };
            let h: Vec<[f64; 3]> = (0..2)
                .map(|_| [0, 1, 2].map(|i| u[i] * (g + extra) + sigma * 2f64.sqrt() * rng.normal()))
                .collect();
            mean.push([0, 1, 2].map(|i| 0.5 * (h[0][i] + h[1][i])));
            half.push([h[0], h[1]]);
        }
        let n = mean.len();
        StaticInput {
            mean,
            var: Some(vec![[sigma * sigma; 3]; n]),
            t: Some((0..n).map(|k| 60.0 * k as f64).collect()),
            temperature: None,
            g,
            calibration: None,
            extras: DwellExtras {
                half_mean: Some(half),
                ..DwellExtras::default()
            },
        }
    }

    #[test]
    fn the_first_dwell_alone_is_no_dependence_on_the_previous_pose() {
        // A warm-up offset on the first dwell of a fixed-order six-face session (20 sigma):
        // every other dwell's previous pose is a function of its own pose, so the first
        // dwell, which has none, would carry the whole pose-history test. It is left out of
        // that test, which is then blind (with it in: F = 144 on 1 direction, p = 2e-13,
        // verdict pose_history).
        // No dictionary effect (settling would take the offset up here): the structure stage
        // on the calibration's residual alone.
        let st = statics::diagnose(&fixed_cycle(7, 7, 2e-3), &[], &GapOptions::default())
            .unwrap()
            .structure;
        let ph = st.tests.iter().find(|t| t.name == "pose_history").unwrap();
        assert_eq!(ph.status, Status::Blind, "{ph:?}");
        assert_ne!(st.verdict, Verdict::PoseHistory, "{st:?}");
        // In a shuffled session a real dependence on the previous pose is still found.
        let mut h = session(6, 1.0, 0.0, 0.0);
        let dirs: Vec<[f64; 3]> = h.mean.iter().map(|m| m.map(|v| v / 9.81)).collect();
        for k in 1..h.mean.len() {
            let shift = 2e-3 * dirs[k - 1][0];
            for i in 0..3 {
                h.mean[k][i] += shift * dirs[k][i];
                for half in h.extras.half_mean.as_mut().unwrap()[k].iter_mut() {
                    half[i] += shift * dirs[k][i];
                }
            }
        }
        let st = verdict(&h);
        assert_eq!(st.verdict, Verdict::PoseHistory, "{st:?}");
    }

    #[test]
    fn verdicts_of_simulated_classes() {
        let none = verdict(&session(1, 1.0, 0.0, 0.0));
        assert_eq!(none.verdict, Verdict::None, "{none:?}");
        let pd = verdict(&session(2, 1.0, 5e-4, 0.0));
        assert_eq!(pd.verdict, Verdict::PerDwell, "{pd:?}");
        assert!(pd.persistence > 0.8, "{}", pd.persistence);
        assert!(
            (pd.per_dwell_rms / 5e-4 - 1.0).abs() < 0.5,
            "{}",
            pd.per_dwell_rms
        );
        let nm = verdict(&session(3, 3.0, 0.0, 0.0));
        assert_eq!(nm.verdict, Verdict::NoiseModel, "{nm:?}");
        let ne = nm.noise_empirical.unwrap();
        assert!(
            (ne.ratio_model / 3.0 - 1.0).abs() < 0.3,
            "{}",
            ne.ratio_model
        );
        assert!(nm.persistence.abs() < 0.5);
        let at = verdict(&session(4, 1.0, 0.0, 1e-3));
        assert_eq!(at.verdict, Verdict::Attitude, "{at:?}");
        let t = at.tests.iter().find(|t| t.name == "attitude").unwrap();
        assert!(t.explained > 0.5 && t.p_adjusted < 1e-3, "{t:?}");
        // Without half-dwell means persistence is untestable.
        let mut s = session(2, 1.0, 5e-4, 0.0);
        s.extras.half_mean = None;
        let pd = verdict(&s);
        assert!(!pd.persistence_testable && pd.persistence.is_nan());
        assert_eq!(pd.verdict, Verdict::PerDwell);
    }

    #[test]
    fn half_dwell_differences_alone_can_show_an_optimistic_noise_model() {
        // Dwell means consistent with the noise model, half-dwell means 3x noisier than it
        // predicts (the two halves' errors cancel in the mean): the means alone say "none",
        // the half-dwell differences say that the noise model is too optimistic.
        let mut s = session(7, 1.0, 0.0, 0.0);
        let without = {
            let mut t = s.clone();
            t.extras.half_mean = None;
            verdict(&t)
        };
        assert_eq!(without.verdict, Verdict::None, "{without:?}");
        let sigma = s.var.as_ref().unwrap()[0][0].sqrt();
        let mut rng = Rng(77);
        for (m, h) in s.mean.iter().zip(s.extras.half_mean.as_mut().unwrap()) {
            for r in 0..3 {
                let d = 3.0 * sigma * rng.normal();
                h[0][r] = m[r] + d;
                h[1][r] = m[r] - d;
            }
        }
        let st = verdict(&s);
        assert_eq!(st.verdict, Verdict::NoiseModel, "{st:?}");
        let ne = st.noise_empirical.unwrap();
        assert!(ne.p_model < 1e-6 && ne.ratio_model > 2.0, "{ne:?}");
    }

    #[test]
    fn attitude_is_not_testable_with_few_dwells() {
        let mut s = session(5, 1.0, 0.0, 0.0);
        s.mean.truncate(20);
        s.var.as_mut().unwrap().truncate(20);
        s.t.as_mut().unwrap().truncate(20);
        s.extras.half_mean.as_mut().unwrap().truncate(20);
        let st = verdict(&s);
        let t = st.tests.iter().find(|t| t.name == "attitude").unwrap();
        assert_eq!(t.status, Status::TooFewRows);
        assert_eq!(t.n_columns, 16);
    }

    #[test]
    fn quantization_explains_a_gap_it_predicts() {
        // Dwell means quantised to 1e-3 m/s^2 steps with almost no noise: the bias is up to
        // half a step per axis; the predicted quantisation variance explains the excess.
        let mut s = session(6, 0.1, 0.0, 0.0);
        let lsb = 1e-3;
        for m in s.mean.iter_mut() {
            m.iter_mut().for_each(|v| *v = (*v / lsb).round() * lsb);
        }
        s.extras.half_mean = None;
        s.extras.sample_var = Some(vec![[1e-10; 3]; 40]);
        s.extras.lsb = Some([lsb; 3]);
        s.var = Some(vec![[1e-10; 3]; 40]);
        let st = verdict(&s);
        assert_eq!(st.verdict, Verdict::Quantization, "{st:?}");
        assert!((st.quantization_rms / (lsb / 12f64.sqrt()) - 1.0).abs() < 0.3);
    }
}

//! Centrifuge norm-observation calibration with quadratic (K2) coefficients (Wang and Li 2021,
//! doi:10.19306/j.cnki.2095-8110.2021.06.019, with its printed equations corrected).
//!
//! Model per accelerometer triad, in g units:
//! `N = S Phi (h) + b`, `h_i = f_i + D_i f_i^2 [+ E_i f_i^3]`, `Phi = I + M` (small-angle,
//! lower triangular: the three rotation-like angles are invisible to a norm observation).
//! The constraint is `|f|^2 = A^2 + 1` with `A = omega^2 R / g`.
//!
//! - [`fit`] with [`Method::Nls`]: exact inversion of every row (`f_i` from `h_i` by the root
//!   continuous with `D -> 0`) and weighted least squares on the norm, via [`crate::lsq`].
//! - [`Method::TaylorPaper`]: the paper's 13-column regression of `A^2 + 1` on
//!   `[1, N, N^2, N^3, N^4]` with the corrected closed-form recovery (eqs. 19, 21, 22 corrected
//!   and made consistent with the series' `5 D^2 z^4` term: see [`taylor_recover`]).
//! - Robust screening: least median of squares over random minimal subsets (seeded, so
//!   deterministic), then iterated refit / reclassification at `k` robust sigmas.
//!
//! Sign convention: a norm observation cannot tell `S_i` from `-S_i` when `D_i = 0`; the fit
//! returns `S_i > 0` (start values are positive and the sign is folded at the end).

#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > 0.0)` deliberately rejects NaN too.

use crate::error::{degenerate, invalid, CoreError, Result};
use crate::gap::{chi2_sf, f_sf};
use crate::lsq::{
    cholesky_inverse_small, cholesky_small, cholesky_solve_small, lstsq_rows, lstsq_small,
    solve_nls, solve_normal_gn, svd_report_qr, symmetric_eigenvalues_small, NlsOptions,
    NormalEquations, Residuals,
};
use nalgebra::{DMatrix, DVector};
use std::cell::{OnceCell, RefCell};

/// Internal parameter scales (columns of the Jacobian are scaled by these).
/// Largest parameter count (S, b, K2, K3, misalignment, full lever arm).
const MAX_PARAMS: usize = 24;
const SCALE_D: f64 = 1e-4;
const SCALE_E: f64 = 1e-6;
const SCALE_M: f64 = 1e-3;
const SCALE_L: f64 = 1e-2;

/// Lever-arm terms of the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeverArm {
    /// No lever arm.
    None,
    /// One offset per accelerometer along its own sensing axis (m).
    Along,
    /// A full 3-vector offset per accelerometer (m), body frame.
    Full,
}

/// Which terms the model contains beyond scale, bias and K2.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ModelOptions {
    /// Cubic coefficient K3 per axis.
    pub k3: bool,
    /// Small-angle misalignment (m_yx, m_zx, m_zy).
    pub misalignment: bool,
    /// Lever-arm offsets (needs the spin-axis direction per row).
    pub lever: LeverArm,
}

impl Default for ModelOptions {
    fn default() -> Self {
        ModelOptions {
            k3: false,
            misalignment: false,
            lever: LeverArm::None,
        }
    }
}

impl ModelOptions {
    /// Number of parameters.
    pub fn n_params(&self) -> usize {
        9 + if self.k3 { 3 } else { 0 }
            + if self.misalignment { 3 } else { 0 }
            + match self.lever {
                LeverArm::None => 0,
                LeverArm::Along => 3,
                LeverArm::Full => 9,
            }
    }

    /// Parameter names in order.
    pub fn names(&self) -> Vec<String> {
        let mut v: Vec<String> = ["sx", "sy", "sz", "bx", "by", "bz", "k2x", "k2y", "k2z"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        if self.k3 {
            v.extend(["k3x", "k3y", "k3z"].iter().map(|s| s.to_string()));
        }
        if self.misalignment {
            v.extend(["m_yx", "m_zx", "m_zy"].iter().map(|s| s.to_string()));
        }
        match self.lever {
            LeverArm::None => {}
            LeverArm::Along => v.extend(
                ["lever_x", "lever_y", "lever_z"]
                    .iter()
                    .map(|s| s.to_string()),
            ),
            LeverArm::Full => {
                for a in ["x", "y", "z"] {
                    for c in ["x", "y", "z"] {
                        v.push(format!("lever_{a}_{c}"));
                    }
                }
            }
        }
        v
    }

    fn scales(&self) -> Vec<f64> {
        let mut s = vec![1.0, 1.0, 1.0, 1.0, 1.0, 1.0, SCALE_D, SCALE_D, SCALE_D];
        if self.k3 {
            s.extend([SCALE_E; 3]);
        }
        if self.misalignment {
            s.extend([SCALE_M; 3]);
        }
        match self.lever {
            LeverArm::None => {}
            LeverArm::Along => s.extend([SCALE_L; 3]),
            LeverArm::Full => s.extend([SCALE_L; 9]),
        }
        s
    }
}

/// Estimation method.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Method {
    /// Exact inversion + (weighted) nonlinear least squares on the norm.
    Nls,
    /// The paper's 13-coefficient regression with the corrected closed form.
    TaylorPaper,
}

/// One centrifuge session, already reduced to per-position means.
#[derive(Debug, Clone)]
pub struct CentrifugeData<'a> {
    /// Outputs `(k, 3)` in g.
    pub outputs: &'a [[f64; 3]],
    /// Spin rate per row (rad/s).
    pub omega: &'a [f64],
    /// Nominal radius (m).
    pub radius: f64,
    /// Gravity used to express A in g (m/s^2).
    pub g: f64,
    /// Optional noise standard deviation of each output, per row and axis (g): the weight of
    /// a row is the inverse of its norm residual's standard deviation, propagated from these
    /// at the current parameters.
    pub sigma: Option<&'a [[f64; 3]]>,
    /// Optional spin-axis (up) direction per row in the body frame (for lever arms).
    pub spin_axis: Option<&'a [[f64; 3]]>,
}

/// Settings of [`fit`].
#[derive(Debug, Clone, Copy)]
pub struct FitOptions {
    /// Model terms.
    pub model: ModelOptions,
    /// Estimation method.
    pub method: Method,
    /// Screen rows with a robust fit when the plain fit shows outliers.
    pub robust: bool,
    /// Outlier threshold: a row is excluded when its studentised residual is as unlikely as a
    /// `outlier_k`-sigma normal deviation (two-sided; see [`screen`]).
    pub outlier_k: f64,
    /// Smallest residual scale (g) used for the threshold (guards exact data).
    pub sigma_floor: f64,
    /// Refuse sessions whose units look wrong (see [`check_units`]).
    pub check_units: bool,
    /// Maximum number of random minimal subsets.
    pub max_draws: usize,
    /// Seed of the subset generator.
    pub seed: u64,
}

impl Default for FitOptions {
    fn default() -> Self {
        FitOptions {
            model: ModelOptions::default(),
            method: Method::Nls,
            robust: true,
            outlier_k: 5.0,
            sigma_floor: 1e-9,
            check_units: true,
            max_draws: 20_000,
            seed: 0,
        }
    }
}

/// Result of [`fit`].
#[derive(Debug, Clone)]
pub struct CentrifugeFit {
    /// Parameters in external units (see [`ModelOptions::names`]).
    pub params: Vec<f64>,
    /// Parameter names.
    pub names: Vec<String>,
    /// Covariance (`p x p`, row-major), scaled by the residual variance unless sigma was given.
    pub covariance: Vec<f64>,
    /// Residual of every row (norm error in g, before weighting), outliers included.
    pub residuals: Vec<f64>,
    /// Rows excluded as inconsistent with the model.
    pub outliers: Vec<usize>,
    /// RMS of the weighted residuals of the rows used.
    pub residual_rms: f64,
    /// Residual scale of the rows used, the screen's `s` (g; 1 when sigma was given: whitened).
    pub screen_sigma: f64,
    /// Studentised residual of every row, the screening statistic (see [`screen`]).
    pub studentized: Vec<f64>,
    /// Threshold on `|studentized|` above which a row is excluded.
    pub threshold: f64,
    /// Standard deviation of each row's norm residual (g): propagated from sigma when given,
    /// else the residual scale.
    pub residual_std: Vec<f64>,
    /// Minimal subsets drawn by the screen (0 when the fast path was enough).
    pub draws: usize,
    /// The screen ran but kept every row: its exclusion was judged a model error spread over
    /// the rows, not sparse outliers (see [`misfit_is_spread`]); the fit is the plain one and
    /// `studentized` / `threshold` are the plain fit's (rows beyond the threshold remain).
    pub screen_kept_all: bool,
    /// Singular values of the column-scaled Jacobian.
    pub singular_values: Vec<f64>,
    /// Condition number of the column-scaled Jacobian.
    pub condition: f64,
    /// Solver iterations (0 for the closed form).
    pub iterations: usize,
    /// Solver convergence flag.
    pub converged: bool,
    /// The 13 regression coefficients (TaylorPaper only).
    pub taylor_coefficients: Option<Vec<f64>>,
}

/// Invert one axis of the instrument model: the `f` with `f + d f^2 + e f^3 = h` continuous
/// with `d -> 0`, and `dh/df`; `None` outside the invertible range.
pub fn inv_axis(h: f64, d: f64, e: f64) -> Option<(f64, f64)> {
    let disc = 1.0 + 4.0 * d * h;
    if !(disc >= 0.0) {
        return None;
    }
    let mut f = 2.0 * h / (1.0 + disc.sqrt());
    let mut hp = 1.0 + 2.0 * d * f;
    if e != 0.0 {
        for _ in 0..30 {
            hp = 1.0 + 2.0 * d * f + 3.0 * e * f * f;
            if !(hp > 0.0) {
                return None;
            }
            let step = (f + d * f * f + e * f * f * f - h) / hp;
            f -= step;
            if step.abs() <= 1e-15 * (1.0 + f.abs()) {
                break;
            }
        }
        hp = 1.0 + 2.0 * d * f + 3.0 * e * f * f;
    }
    if !(hp > 0.0) || !f.is_finite() {
        return None;
    }
    Some((f, hp))
}

/// Instrument input `h = Phi^-1 S^-1 (n - b)` of one output row (small-angle misalignment
/// `m = (m_yx, m_zx, m_zy)`, `Phi` lower triangular): the model's first step, for diagnostics
/// that extend it (the gap diagnosis adds cross-coupling, rate and radius errors).
pub fn instrument_input(n: &[f64; 3], s: &[f64; 3], b: &[f64; 3], m: &[f64; 3]) -> [f64; 3] {
    let u = [
        (n[0] - b[0]) / s[0],
        (n[1] - b[1]) / s[1],
        (n[2] - b[2]) / s[2],
    ];
    [
        u[0],
        u[1] - m[0] * u[0],
        u[2] - m[1] * u[0] - m[2] * (u[1] - m[0] * u[0]),
    ]
}

fn target(data: &CentrifugeData<'_>, k: usize) -> f64 {
    let a = data.omega[k] * data.omega[k] * data.radius / data.g;
    a * a + 1.0
}

/// Per-row constants that do not depend on the parameters (computed once per fit).
#[derive(Debug, Clone, Copy)]
struct RowConst {
    /// Target `T = A^2 + 1`.
    t: f64,
    /// `1 / sqrt T`.
    inv_st: f64,
    /// `1 / (2 sqrt T)`.
    half_inv_st: f64,
    /// `omega^2 / g`.
    w2g: f64,
    /// Residual weight: 1 / (std of the norm residual) with sigma (see [`noise_weights`]), else 1.
    w: f64,
    /// Spin-axis direction in the body frame (zero when not given).
    c3: [f64; 3],
}

fn row_consts(data: &CentrifugeData<'_>) -> Vec<RowConst> {
    (0..data.outputs.len())
        .map(|k| {
            let t = target(data, k);
            let inv_st = 1.0 / t.sqrt();
            RowConst {
                t,
                inv_st,
                half_inv_st: 0.5 * inv_st,
                w2g: data.omega[k] * data.omega[k] / data.g,
                w: 1.0,
                c3: data.spin_axis.map(|sa| sa[k]).unwrap_or([0.0; 3]),
            }
        })
        .collect()
}

/// Parameter-dependent quantities shared by every row (external units).
struct ParamPre<'p> {
    p: &'p [f64],
    inv_s: [f64; 3],
    b: [f64; 3],
    d: [f64; 3],
    e: [f64; 3],
    m: [f64; 3],
    lever_at: usize,
}

/// `None` when a scale factor is zero (no row can be inverted).
fn param_pre<'p>(model: &ModelOptions, p: &'p [f64]) -> Option<ParamPre<'p>> {
    if p[0] == 0.0 || p[1] == 0.0 || p[2] == 0.0 {
        return None;
    }
    let mut idx = 9;
    let e = if model.k3 {
        idx += 3;
        [p[9], p[10], p[11]]
    } else {
        [0.0; 3]
    };
    let m = if model.misalignment {
        idx += 3;
        [p[idx - 3], p[idx - 2], p[idx - 1]]
    } else {
        [0.0; 3]
    };
    Some(ParamPre {
        p,
        inv_s: [1.0 / p[0], 1.0 / p[1], 1.0 / p[2]],
        b: [p[3], p[4], p[5]],
        d: [p[6], p[7], p[8]],
        e,
        m,
        lever_at: idx,
    })
}

/// One row of outputs inverted through the sensor model.
struct Inverted {
    /// `(N - b) / S`.
    u: [f64; 3],
    /// `h = Phi^-1 u`.
    h: [f64; 3],
    /// Specific force at each accelerometer (g): `f + D f^2 [+ E f^3] = h`.
    f: [f64; 3],
    /// `dh/df` per axis.
    hp: [f64; 3],
}

/// Invert one row of outputs; `None` outside the invertible range.
#[inline(always)]
fn invert_row(n: &[f64; 3], pp: &ParamPre<'_>) -> Option<Inverted> {
    let [m1, m2, m3] = pp.m;
    let u = [
        (n[0] - pp.b[0]) * pp.inv_s[0],
        (n[1] - pp.b[1]) * pp.inv_s[1],
        (n[2] - pp.b[2]) * pp.inv_s[2],
    ];
    // h = L u with L = Phi^-1 (lower triangular).
    let h = [
        u[0],
        u[1] - m1 * u[0],
        u[2] - m2 * u[0] - m3 * (u[1] - m1 * u[0]),
    ];
    let mut f = [0.0; 3];
    let mut hp = [0.0; 3];
    for i in 0..3 {
        let (fi, hpi) = inv_axis(h[i], pp.d[i], pp.e[i])?;
        f[i] = fi;
        hp[i] = hpi;
    }
    Some(Inverted { u, h, f, hp })
}

/// Specific force (k, 3) in g at the accelerometers from outputs in g, by exact inversion of
/// the fitted sensor model `p` (lever arms relate the accelerometers to the arm's centre and
/// are not applied). Errors name the first row outside the invertible range.
pub fn correct(model: &ModelOptions, p: &[f64], outputs: &[[f64; 3]]) -> Result<Vec<[f64; 3]>> {
    if p.len() != model.n_params() {
        return invalid(format!(
            "{} parameters given, the model has {}",
            p.len(),
            model.n_params()
        ));
    }
    let pp = param_pre(model, p)
        .ok_or_else(|| CoreError::InvalidInput("a scale factor is zero".into()))?;
    outputs
        .iter()
        .enumerate()
        .map(|(k, n)| {
            if !n.iter().all(|v| v.is_finite()) {
                return invalid(format!("outputs row {k} is not finite"));
            }
            invert_row(n, &pp).map(|x| x.f).ok_or_else(|| {
                CoreError::InvalidInput(format!(
                    "outputs row {k} lies outside the invertible range of the fitted K2/K3"
                ))
            })
        })
        .collect()
}

/// Norm residual `(|f|^2 - T) / (2 sqrt T)` (g, unweighted) of one row; with `grad`, also
/// `d r / d p` (external units, first `n_params` entries). `None`: outside the invertible
/// range.
#[inline(always)]
fn row_eval(
    n: &[f64; 3],
    rc: &RowConst,
    pp: &ParamPre<'_>,
    model: &ModelOptions,
    grad: Option<&mut [f64; MAX_PARAMS]>,
) -> Option<f64> {
    let [m1, m2, m3] = pp.m;
    let Inverted { u, h, f, hp } = invert_row(n, pp)?;
    let w2g = rc.w2g;
    let c3 = rc.c3;
    let la = pp.lever_at;
    let p = pp.p;
    // Lever-arm correction: f_center_i = f_i + w2g * [(I - c3 c3^T) r_i]_i.
    let mut fc = f;
    match model.lever {
        LeverArm::None => {}
        LeverArm::Along => {
            for i in 0..3 {
                fc[i] += w2g * p[la + i] * (1.0 - c3[i] * c3[i]);
            }
        }
        LeverArm::Full => {
            for i in 0..3 {
                let r = &p[la + 3 * i..la + 3 * i + 3];
                let cr = c3[0] * r[0] + c3[1] * r[1] + c3[2] * r[2];
                fc[i] += w2g * (r[i] - c3[i] * cr);
            }
        }
    }
    let norm2 = fc[0] * fc[0] + fc[1] * fc[1] + fc[2] * fc[2];
    let r = (norm2 - rc.t) * rc.half_inv_st;
    if !r.is_finite() {
        return None;
    }
    let Some(grad) = grad else {
        return Some(r);
    };
    // dr/dfc_i = fc_i / sqrt T ; dfc_i/dh_i = 1/hp_i ; dh_i/du_j = L[i][j].
    let gf = [fc[0] * rc.inv_st, fc[1] * rc.inv_st, fc[2] * rc.inv_st];
    let gh = [gf[0] / hp[0], gf[1] / hp[1], gf[2] / hp[2]];
    let dr_du = [
        gh[0] - m1 * gh[1] + (m1 * m3 - m2) * gh[2],
        gh[1] - m3 * gh[2],
        gh[2],
    ];
    for j in 0..3 {
        grad[j] = -dr_du[j] * u[j] * pp.inv_s[j];
        grad[3 + j] = -dr_du[j] * pp.inv_s[j];
        grad[6 + j] = -gh[j] * f[j] * f[j];
    }
    let mut idx = 9;
    if model.k3 {
        for j in 0..3 {
            grad[9 + j] = -gh[j] * f[j] * f[j] * f[j];
        }
        idx += 3;
    }
    if model.misalignment {
        let hx = h[0];
        let hy = h[1];
        grad[idx] = gh[1] * (-hx) + gh[2] * (m3 * hx);
        grad[idx + 1] = gh[2] * (-hx);
        grad[idx + 2] = gh[2] * (-hy);
        idx += 3;
    }
    match model.lever {
        LeverArm::None => {}
        LeverArm::Along => {
            for i in 0..3 {
                grad[idx + i] = gf[i] * w2g * (1.0 - c3[i] * c3[i]);
            }
        }
        LeverArm::Full => {
            for i in 0..3 {
                for c in 0..3 {
                    let delta = if c == i { 1.0 } else { 0.0 };
                    grad[idx + 3 * i + c] = gf[i] * w2g * (delta - c3[i] * c3[c]);
                }
            }
        }
    }
    Some(r)
}

/// The fitting problem on a set of rows (residuals and normal equations in internal, scaled
/// parameters `q = p / scale`).
struct Problem<'a> {
    outputs: &'a [[f64; 3]],
    rc: &'a [RowConst],
    rows: &'a [usize],
    model: ModelOptions,
    scales: [f64; MAX_PARAMS],
    np: usize,
    /// The most recent normal-equation evaluation (reused by the final covariance step).
    last: RefCell<LastNormal>,
    /// Row data in columns for the vectorised base-model kernel (built at the first
    /// normal-equation evaluation; `None` for other models).
    soa: OnceCell<Option<Soa>>,
}

/// Rows of a base-model (S, b, K2) problem as contiguous columns, so that the per-row
/// arithmetic (square roots and divisions included) vectorises across rows.
struct Soa {
    m: usize,
    /// `nx, ny, nz, T, 1/(2 sqrt T), 1/sqrt T, w`, each `m` long.
    cols: Vec<f64>,
    /// Per evaluation: 9 weighted, scaled Jacobian columns, weighted residuals, min `h'`,
    /// unweighted residuals.
    work: RefCell<Vec<f64>>,
}

impl Soa {
    fn new(outputs: &[[f64; 3]], rc: &[RowConst], rows: &[usize]) -> Self {
        let m = rows.len();
        let mut cols = vec![0.0; 7 * m];
        for (a, &k) in rows.iter().enumerate() {
            let c = &rc[k];
            let v = [
                outputs[k][0],
                outputs[k][1],
                outputs[k][2],
                c.t,
                c.half_inv_st,
                c.inv_st,
                c.w,
            ];
            for (j, x) in v.into_iter().enumerate() {
                cols[j * m + a] = x;
            }
        }
        Soa {
            m,
            cols,
            work: RefCell::new(vec![0.0; 12 * m]),
        }
    }
}

/// The per-row part of [`Problem::normal_base`]: every output is a separate `&mut` argument
/// (no aliasing, so the loop vectorises, square roots and divisions included).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn base_rows(
    inp: [&[f64]; 7],
    par: [[f64; 3]; 3],
    sc: &[f64; MAX_PARAMS],
    g0: &mut [f64],
    g1: &mut [f64],
    g2: &mut [f64],
    g3: &mut [f64],
    g4: &mut [f64],
    g5: &mut [f64],
    g6: &mut [f64],
    g7: &mut [f64],
    g8: &mut [f64],
    rr: &mut [f64],
    hpm: &mut [f64],
    r_raw: &mut [f64],
) {
    let [nx, ny, nz, t, hinv, inv_st, w] = inp;
    let [is, b, d] = par;
    let m = rr.len();
    let (nx, ny, nz, t, hinv, inv_st, w) = (
        &nx[..m],
        &ny[..m],
        &nz[..m],
        &t[..m],
        &hinv[..m],
        &inv_st[..m],
        &w[..m],
    );
    let (g0, g1, g2, g3, g4) = (
        &mut g0[..m],
        &mut g1[..m],
        &mut g2[..m],
        &mut g3[..m],
        &mut g4[..m],
    );
    let (g5, g6, g7, g8, hpm) = (
        &mut g5[..m],
        &mut g6[..m],
        &mut g7[..m],
        &mut g8[..m],
        &mut hpm[..m],
    );
    let r_raw = &mut r_raw[..m];
    for a in 0..m {
        let n = [nx[a], ny[a], nz[a]];
        let mut f = [0.0; 3];
        let mut u = [0.0; 3];
        let mut hp = [0.0; 3];
        for i in 0..3 {
            u[i] = (n[i] - b[i]) * is[i];
            let disc = 1.0 + 4.0 * d[i] * u[i];
            f[i] = 2.0 * u[i] / (1.0 + disc.sqrt());
            hp[i] = 1.0 + 2.0 * d[i] * f[i];
        }
        let norm2 = f[0] * f[0] + f[1] * f[1] + f[2] * f[2];
        let r = (norm2 - t[a]) * hinv[a];
        let gh = [
            f[0] * inv_st[a] / hp[0],
            f[1] * inv_st[a] / hp[1],
            f[2] * inv_st[a] / hp[2],
        ];
        let wa = w[a];
        r_raw[a] = r;
        rr[a] = wa * r;
        hpm[a] = hp[0].min(hp[1]).min(hp[2]);
        g0[a] = wa * (-gh[0] * u[0] * is[0]) * sc[0];
        g1[a] = wa * (-gh[1] * u[1] * is[1]) * sc[1];
        g2[a] = wa * (-gh[2] * u[2] * is[2]) * sc[2];
        g3[a] = wa * (-gh[0] * is[0]) * sc[3];
        g4[a] = wa * (-gh[1] * is[1]) * sc[4];
        g5[a] = wa * (-gh[2] * is[2]) * sc[5];
        g6[a] = wa * (-gh[0] * f[0] * f[0]) * sc[6];
        g7[a] = wa * (-gh[1] * f[1] * f[1]) * sc[7];
        g8[a] = wa * (-gh[2] * f[2] * f[2]) * sc[8];
    }
}

/// Dot product with four independent partial sums (vectorises; the summation order differs
/// from a sequential loop only by rounding).
#[inline(always)]
fn dot4(x: &[f64], y: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (xc, yc) = (x.chunks_exact(4), y.chunks_exact(4));
    let (xr, yr) = (xc.remainder(), yc.remainder());
    for (a, b) in xc.zip(yc) {
        for l in 0..4 {
            acc[l] += a[l] * b[l];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (a, b) in xr.iter().zip(yr) {
        s += a * b;
    }
    s
}

/// A normal-equation evaluation: external parameters, `J^T J` (row-major) and cost.
#[derive(Debug, Clone, Default)]
struct LastNormal {
    p: Vec<f64>,
    jtj: Vec<f64>,
    cost: f64,
    /// Unweighted residual of every row of the problem (base-model kernel only, else empty).
    r: Vec<f64>,
}

impl<'a> Problem<'a> {
    fn new(
        data: &'a CentrifugeData<'a>,
        rc: &'a [RowConst],
        rows: &'a [usize],
        model: ModelOptions,
    ) -> Self {
        let s = model.scales();
        let mut scales = [0.0; MAX_PARAMS];
        scales[..s.len()].copy_from_slice(&s);
        Problem {
            outputs: data.outputs,
            rc,
            rows,
            model,
            scales,
            np: s.len(),
            last: RefCell::new(LastNormal::default()),
            soa: OnceCell::new(),
        }
    }
    fn external(&self, q: &[f64]) -> [f64; MAX_PARAMS] {
        let mut p = [0.0; MAX_PARAMS];
        for j in 0..self.np {
            p[j] = q[j] * self.scales[j];
        }
        p
    }
    fn outside(&self, k: usize) -> CoreError {
        CoreError::Degenerate(format!("row {k} lies outside the invertible range"))
    }
    fn pre<'p>(&self, p: &'p [f64]) -> Result<ParamPre<'p>> {
        param_pre(&self.model, p)
            .ok_or_else(|| self.outside(self.rows.first().copied().unwrap_or(0)))
    }
}

impl Residuals for Problem<'_> {
    fn n_params(&self) -> usize {
        self.np
    }
    fn n_residuals(&self) -> usize {
        self.rows.len()
    }
    fn eval(&self, q: &[f64], r: &mut [f64], jac: &mut DMatrix<f64>) -> Result<()> {
        let p = self.external(q);
        let pp = self.pre(&p[..self.np])?;
        let mut grad = [0.0; MAX_PARAMS];
        for (a, &k) in self.rows.iter().enumerate() {
            let rc = &self.rc[k];
            let ev = row_eval(&self.outputs[k], rc, &pp, &self.model, Some(&mut grad))
                .ok_or_else(|| self.outside(k))?;
            r[a] = rc.w * ev;
            for j in 0..self.np {
                jac[(a, j)] = rc.w * grad[j] * self.scales[j];
            }
        }
        Ok(())
    }
}

impl NormalEquations for Problem<'_> {
    fn n_params(&self) -> usize {
        self.np
    }
    fn n_residuals(&self) -> usize {
        self.rows.len()
    }
    fn cost(&self, q: &[f64]) -> Result<f64> {
        let p = self.external(q);
        let pp = self.pre(&p[..self.np])?;
        let mut cost = 0.0;
        for &k in self.rows {
            let rc = &self.rc[k];
            let r = row_eval(&self.outputs[k], rc, &pp, &self.model, None)
                .ok_or_else(|| self.outside(k))?;
            cost += (rc.w * r) * (rc.w * r);
        }
        Ok(cost)
    }
    fn normal(&self, q: &[f64], jtj: &mut DMatrix<f64>, jtr: &mut DVector<f64>) -> Result<f64> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU supports AVX2 (checked just above).
                return unsafe { self.normal_avx2(q, jtj, jtr) };
            }
        }
        self.normal_dispatch(q, jtj, jtr)
    }
}

impl Problem<'_> {
    /// [`Self::normal_dispatch`] compiled for AVX2 (wider vectors for the rank-1 updates;
    /// no FMA, so the arithmetic and its rounding are those of the baseline build).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn normal_avx2(
        &self,
        q: &[f64],
        jtj: &mut DMatrix<f64>,
        jtr: &mut DVector<f64>,
    ) -> Result<f64> {
        self.normal_dispatch(q, jtj, jtr)
    }

    #[inline(always)]
    fn normal_dispatch(
        &self,
        q: &[f64],
        jtj: &mut DMatrix<f64>,
        jtr: &mut DVector<f64>,
    ) -> Result<f64> {
        let soa = self.soa.get_or_init(|| {
            (self.model == ModelOptions::default())
                .then(|| Soa::new(self.outputs, self.rc, self.rows))
        });
        if let Some(soa) = soa {
            if let Some(cost) = self.normal_base(soa, q, jtj, jtr) {
                return Ok(cost);
            }
            // Some row is outside the invertible range: the row-wise path names it.
        }
        // Fixed sizes for the common models (the compiler unrolls the rank-1 updates).
        match self.np {
            9 => self.normal_n::<9>(q, jtj, jtr),
            12 => self.normal_n::<12>(q, jtj, jtr),
            15 => self.normal_n::<15>(q, jtj, jtr),
            _ => self.normal_n::<MAX_PARAMS>(q, jtj, jtr),
        }
    }

    /// [`NormalEquations::normal`] for the base model (S, b, K2) on column data: the same
    /// formulas as [`row_eval`] evaluated for all rows in straight-line, vectorisable loops,
    /// then `J^T J` and `J^T r` as dot products. `None` when a row cannot be inverted or the
    /// cost is not finite (the caller then takes the row-wise path, which reports the row).
    #[inline(always)]
    fn normal_base(
        &self,
        soa: &Soa,
        q: &[f64],
        jtj: &mut DMatrix<f64>,
        jtr: &mut DVector<f64>,
    ) -> Option<f64> {
        let m = soa.m;
        let p = self.external(q);
        if p[0] == 0.0 || p[1] == 0.0 || p[2] == 0.0 {
            return None;
        }
        let is = [1.0 / p[0], 1.0 / p[1], 1.0 / p[2]];
        let (b, d) = ([p[3], p[4], p[5]], [p[6], p[7], p[8]]);
        let sc = &self.scales;
        let c = &soa.cols;
        let (nx, ny, nz) = (&c[..m], &c[m..2 * m], &c[2 * m..3 * m]);
        let (t, hinv) = (&c[3 * m..4 * m], &c[4 * m..5 * m]);
        let (inv_st, w) = (&c[5 * m..6 * m], &c[6 * m..7 * m]);
        let mut work = soa.work.borrow_mut();
        let mut cols: Vec<&mut [f64]> = work.chunks_exact_mut(m).collect();
        let [g0, g1, g2, g3, g4, g5, g6, g7, g8, rr, hpm, r_raw] = &mut cols[..] else {
            return None;
        };
        // Equal, known lengths: no bounds checks in the loop, so it vectorises.
        let (g0, g1, g2, g3, g4) = (
            &mut g0[..m],
            &mut g1[..m],
            &mut g2[..m],
            &mut g3[..m],
            &mut g4[..m],
        );
        let (g5, g6, g7, g8) = (&mut g5[..m], &mut g6[..m], &mut g7[..m], &mut g8[..m]);
        let (rr, hpm) = (&mut rr[..m], &mut hpm[..m]);
        let (nx, ny, nz, t, hinv, inv_st, w) = (
            &nx[..m],
            &ny[..m],
            &nz[..m],
            &t[..m],
            &hinv[..m],
            &inv_st[..m],
            &w[..m],
        );
        base_rows(
            [nx, ny, nz, t, hinv, inv_st, w],
            [is, b, d],
            sc,
            g0,
            g1,
            g2,
            g3,
            g4,
            g5,
            g6,
            g7,
            g8,
            rr,
            hpm,
            r_raw,
        );
        let cost = dot4(rr, rr);
        // NaN anywhere (a negative discriminant) makes the cost NaN.
        if !cost.is_finite() || !hpm.iter().all(|v| *v > 0.0) {
            return None;
        }
        let g = [&*g0, &*g1, &*g2, &*g3, &*g4, &*g5, &*g6, &*g7, &*g8];
        let rr = &*rr;
        let mut last = self.last.borrow_mut();
        last.p.clear();
        last.p.extend_from_slice(&p[..9]);
        last.jtj.resize(81, 0.0);
        for i in 0..9 {
            jtr[i] = dot4(g[i], rr);
            for j in i..9 {
                let v = dot4(g[i], g[j]);
                jtj[(i, j)] = v;
                jtj[(j, i)] = v;
                last.jtj[i * 9 + j] = v;
                last.jtj[j * 9 + i] = v;
            }
        }
        last.cost = cost;
        last.r.clear();
        last.r.extend_from_slice(r_raw);
        Some(cost)
    }

    /// [`NormalEquations::normal`] with the parameter count bounded by `N` (`np <= N`).
    #[inline(always)]
    fn normal_n<const N: usize>(
        &self,
        q: &[f64],
        jtj: &mut DMatrix<f64>,
        jtr: &mut DVector<f64>,
    ) -> Result<f64> {
        let np = self.np;
        debug_assert!(np <= N);
        let p = self.external(q);
        let pp = self.pre(&p[..np])?;
        let mut acc = [[0.0f64; N]; N];
        let mut g = [0.0f64; N];
        let mut grad = [0.0f64; MAX_PARAMS];
        let mut cost = 0.0;
        for &k in self.rows {
            let rc = &self.rc[k];
            let r = row_eval(&self.outputs[k], rc, &pp, &self.model, Some(&mut grad))
                .ok_or_else(|| self.outside(k))?;
            let rw = rc.w * r;
            cost += rw * rw;
            // Entries beyond np stay zero (grad and scales are zero there).
            let gs: [f64; N] = std::array::from_fn(|j| rc.w * grad[j] * self.scales[j]);
            for a in 0..N {
                let ga = gs[a];
                g[a] += ga * rw;
                for b in a..N {
                    acc[a][b] += ga * gs[b];
                }
            }
        }
        let mut last = self.last.borrow_mut();
        last.p.clear();
        last.p.extend_from_slice(&p[..np]);
        last.jtj.resize(np * np, 0.0);
        for a in 0..np {
            jtr[a] = g[a];
            for b in a..np {
                jtj[(a, b)] = acc[a][b];
                jtj[(b, a)] = acc[a][b];
                last.jtj[a * np + b] = acc[a][b];
                last.jtj[b * np + a] = acc[a][b];
            }
        }
        last.cost = cost;
        last.r.clear();
        Ok(cost)
    }
}

/// Norm residuals (g, unweighted) of every row at external parameters `p` (`inf` where a
/// row cannot be inverted).
fn residuals_pre(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    model: &ModelOptions,
    p: &[f64],
) -> Vec<f64> {
    match param_pre(model, p) {
        None => vec![f64::INFINITY; data.outputs.len()],
        Some(pp) => data
            .outputs
            .iter()
            .zip(rc)
            .map(|(n, c)| row_eval(n, c, &pp, model, None).unwrap_or(f64::INFINITY))
            .collect(),
    }
}

/// Norm residuals (g) of every row at external parameters (`inf` where not invertible).
pub fn residuals(data: &CentrifugeData<'_>, model: &ModelOptions, p: &[f64]) -> Result<Vec<f64>> {
    if p.len() != model.n_params() {
        return invalid(format!(
            "{} parameters given, the model has {}",
            p.len(),
            model.n_params()
        ));
    }
    Ok(residuals_pre(data, &row_consts(data), model, p))
}

/// Check the inputs; returns the number of distinct speeds.
pub fn validate(data: &CentrifugeData<'_>, model: &ModelOptions) -> Result<usize> {
    let k = data.outputs.len();
    if data.omega.len() != k {
        return invalid(format!(
            "omega has {} values but outputs have {k} rows",
            data.omega.len()
        ));
    }
    if !(data.radius > 0.0) || !data.radius.is_finite() {
        return invalid(format!(
            "radius must be positive and finite (m); got {}",
            data.radius
        ));
    }
    if !(data.g > 0.0) || !data.g.is_finite() {
        return invalid(format!(
            "g must be positive and finite (m/s^2); got {}",
            data.g
        ));
    }
    for (r, row) in data.outputs.iter().enumerate() {
        if row.iter().any(|v| !v.is_finite()) {
            return invalid(format!("outputs row {r} is not finite"));
        }
    }
    for (r, w) in data.omega.iter().enumerate() {
        if !w.is_finite() {
            return invalid(format!("omega[{r}] is not finite"));
        }
    }
    if let Some(s) = data.sigma {
        if s.len() != k {
            return invalid(format!(
                "sigma has {} rows but outputs have {k} rows",
                s.len()
            ));
        }
        if let Some(r) = s
            .iter()
            .position(|v| v.iter().any(|x| !(*x > 0.0) || !x.is_finite()))
        {
            return invalid(format!(
                "sigma (per-axis output noise, g) must be positive and finite; row {r} is {:?}",
                s[r]
            ));
        }
    }
    match (model.lever, data.spin_axis) {
        (LeverArm::None, _) => {}
        (_, None) => return invalid(
            "a lever-arm model needs the spin-axis direction in the body frame per row (spin_axis)",
        ),
        (_, Some(sa)) => {
            if sa.len() != k {
                return invalid(format!(
                    "spin_axis has {} rows but outputs have {k}",
                    sa.len()
                ));
            }
            for (r, c) in sa.iter().enumerate() {
                let n = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                if !((n - 1.0).abs() < 1e-3) {
                    return invalid(format!("spin_axis row {r} is not a unit vector (norm {n})"));
                }
            }
        }
    }
    if data.omega.iter().all(|w| *w == 0.0) {
        return degenerate(
            "no rotation: omega is 0 for every row, so the centrifuge never excites more than 1 g \
             (use the static fit for |a| = g data)",
        );
    }
    let mut speeds: Vec<f64> = data.omega.iter().map(|w| w.abs()).collect();
    speeds.sort_by(|a, b| a.total_cmp(b));
    speeds.dedup_by(|a, b| (*a - *b).abs() <= 1e-9 * b.abs().max(1e-300));
    // Two levels of specific force separate K2 from scale: two speeds, or one speed and rows
    // at rest (1 g).
    if speeds.len() < 2 {
        return degenerate(
            "only 1 distinct speed and no rows at rest: K2 cannot be separated from scale; \
             run at least two (better three) speeds, or add rows at rest",
        );
    }
    let p = model.n_params();
    if k < p + 1 {
        return degenerate(format!(
            "{k} rows cannot determine {p} parameters with a residual check (need at least {})",
            p + 1
        ));
    }
    if !model.misalignment {
        check_axis_levels(data, model)?;
    }
    Ok(speeds.len())
}

/// Distinct levels of `x` (sorted; a new level where the gap to the previous value exceeds
/// `tol`): the mean of each cluster.
fn levels(x: &mut [f64], tol: f64) -> Vec<f64> {
    x.sort_by(|a, b| a.total_cmp(b));
    let mut out: Vec<(f64, usize)> = Vec::new();
    let mut prev = f64::NEG_INFINITY;
    for &v in x.iter() {
        match out.last_mut() {
            Some((s, c)) if v - prev <= tol => {
                *s += v;
                *c += 1;
            }
            _ => out.push((v, 1)),
        }
        prev = v;
    }
    out.into_iter().map(|(s, c)| s / c as f64).collect()
}

/// Identifiability of each axis from the design, free of the noise: axis i's output is a
/// monotone function of its specific force `f_i`
/// (`N_i = b_i + S_i (f_i + K2_i f_i^2 [+ K3_i f_i^3])`), so the distinct levels of `N_i` over
/// the rows are the distinct levels of `f_i` the design gives it. The norm sees `f_i` only through its value at those levels, so bias, scale
/// and K2 (and K3) of the axis need at least as many levels as they are parameters: a flat
/// mount whose z axis only sees +1 and -1 g cannot tell `b_z` from `K2_z` (`f_z^2 = 1` on every
/// row), however the noise lifts the degeneracy of the fitted Jacobian. Levels closer than
/// 1e-3 of the axis's output range (plus six times its largest noise, when given) are one.
fn check_axis_levels(data: &CentrifugeData<'_>, model: &ModelOptions) -> Result<()> {
    let need = 3 + usize::from(model.k3);
    for i in 0..3 {
        let mut x: Vec<f64> = data.outputs.iter().map(|n| n[i]).collect();
        let (lo, hi) = x
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        let noise = data
            .sigma
            .map_or(0.0, |s| s.iter().map(|r| r[i]).fold(0.0, f64::max));
        let tol = 1e-3 * (hi - lo) + 6.0 * noise;
        let lv = levels(&mut x, tol);
        if lv.len() >= need {
            continue;
        }
        let axis = ["x", "y", "z"][i];
        let shown: Vec<String> = lv.iter().map(|v| format!("{v:.4}")).collect();
        let what = if lv.len() == 2 {
            format!(
                "with two levels of f_{axis}, b{axis}, s{axis} and k2{axis} (3 parameters) meet \
                 the norm at 2 points, so one combination of them is free (when f_{axis} is +-1 g, \
                 f_{axis}^2 = 1 on every row and k2{axis} acts exactly as bias)"
            )
        } else {
            format!("s{axis} and k2{axis} have nothing to scale")
        };
        let k3 = if model.k3 {
            format!(" (with k3{axis}: {need})")
        } else {
            String::new()
        };
        return degenerate(format!(
            "the design cannot determine the {axis} axis: its output takes only {} distinct \
             level(s) ({} g) over all rows; {what}. Bias, scale and K2 of an axis need at least \
             3 distinct levels of its specific force{k3}: add positions where the {axis} axis \
             sees other inputs (e.g. tilted so it shares the radial direction)",
            lv.len(),
            shown.join(", ")
        ));
    }
    Ok(())
}

/// Local gravity, m/s^2: anywhere on the Earth's surface (9.78 at the equator to 9.83 at the
/// poles, less with height), with a margin.
const GRAVITY_MPS2: (f64, f64) = (9.76, 9.84);

/// `g` is used as a local gravity in m/s^2 (`A = omega^2 R / g`). A value outside
/// [`GRAVITY_MPS2`] is refused, naming the unit it looks like (ft/s^2, cm/s^2, mm/s^2, in/s^2,
/// or g itself). A radius or rate off by a plain factor fits as a wrong, clean-looking model
/// (the constraint `|f|^2 = A^2 + 1` cannot absorb a factor on A), so a g in other units must
/// not reach the fit.
pub fn check_gravity(g: f64) -> Result<()> {
    if g >= GRAVITY_MPS2.0 && g <= GRAVITY_MPS2.1 {
        return Ok(());
    }
    const UNITS: [(&str, f64); 5] = [
        ("ft/s^2", 1.0 / 0.3048),
        ("cm/s^2 (Gal)", 100.0),
        ("mm/s^2", 1000.0),
        ("in/s^2", 1.0 / 0.0254),
        ("g (standard gravities)", 1.0 / 9.80665),
    ];
    let likely = UNITS.iter().find(|(_, f)| {
        let m = g / f;
        m >= GRAVITY_MPS2.0 && m <= GRAVITY_MPS2.1
    });
    let why = match likely {
        Some((unit, f)) => format!("it looks like {unit}: {g} {unit} is {:.5} m/s^2", g / f),
        None => "it is not a gravity on the Earth's surface in any common unit".into(),
    };
    invalid(format!(
        "g must be the local gravity in m/s^2 ({}..{}), as A = omega^2 R / g needs; got {g}: \
         {why}. Give g in m/s^2 (e.g. 9.80665), or pass check_units=False to fit as given",
        GRAVITY_MPS2.0, GRAVITY_MPS2.1
    ))
}

/// Start values (external units): axis-aligned ellipsoid regression without K2, solved by
/// column-scaled normal equations (a start value only; small and fast).
fn linear_start(
    data: &CentrifugeData<'_>,
    rows: &[usize],
    model: &ModelOptions,
) -> Result<Vec<f64>> {
    if rows.len() >= 20 {
        if let Some(p) = linear_start_n::<10>(data, rows, model) {
            return Ok(p);
        }
    }
    if let Some(p) = linear_start_n::<7>(data, rows, model) {
        return Ok(p);
    }
    degenerate(
        "the outputs cannot determine scale and bias: some axis takes too few distinct values \
         or the outputs do not describe an ellipsoid",
    )
}

/// `C` = 7: `[N^2, N, 1]`; `C` = 10: also `N^3` per axis, giving a K2 start `-C3 S^3 / 2`.
fn linear_start_n<const C: usize>(
    data: &CentrifugeData<'_>,
    rows: &[usize],
    model: &ModelOptions,
) -> Option<Vec<f64>> {
    let regs = |n: [f64; 3]| -> [f64; C] {
        let all = [
            n[0] * n[0],
            n[1] * n[1],
            n[2] * n[2],
            n[0],
            n[1],
            n[2],
            1.0,
            n[0] * n[0] * n[0],
            n[1] * n[1] * n[1],
            n[2] * n[2] * n[2],
        ];
        std::array::from_fn(|j| all[j])
    };
    let mut cs = [0.0f64; C];
    for &k in rows {
        let row = regs(data.outputs[k]);
        for j in 0..C {
            cs[j] += row[j] * row[j];
        }
    }
    for c in cs.iter_mut() {
        *c = c.sqrt();
        if !(*c > 0.0) || !c.is_finite() {
            return None;
        }
    }
    let ics: [f64; C] = std::array::from_fn(|j| 1.0 / cs[j]);
    // Column-scaled normal equations (row-major), solved by Cholesky through `lsq`.
    let mut ata = [[0.0f64; C]; C];
    let mut c = [0.0f64; C];
    for &k in rows {
        let raw = regs(data.outputs[k]);
        let row: [f64; C] = std::array::from_fn(|j| raw[j] * ics[j]);
        let t = target(data, k);
        for a in 0..C {
            c[a] += row[a] * t;
            for b in a..C {
                ata[a][b] += row[a] * row[b];
            }
        }
    }
    // Symmetric: the lower triangle is the mirror (same products, same order).
    for a in 1..C {
        let (upper, lower) = ata.split_at_mut(a);
        for (b, row) in upper.iter().enumerate() {
            lower[0][b] = row[a];
        }
    }
    let l = ata.as_flattened_mut();
    if !cholesky_small(l, C) {
        return None;
    }
    cholesky_solve_small(l, C, &mut c);
    let mut p = vec![0.0; model.n_params()];
    for i in 0..3 {
        let q = c[i] / cs[i];
        if !(q > 0.0) {
            return None;
        }
        p[i] = 1.0 / q.sqrt();
        p[3 + i] = -(c[3 + i] / cs[3 + i]) / (2.0 * q);
        if C == 10 {
            let d = -(c[7 + i] / cs[7 + i]) * p[i] * p[i] * p[i] / 2.0;
            // Keep only a plausible K2 start (|D f| well below 1 over the data).
            p[6 + i] = if d.is_finite() && d.abs() < 1e-2 {
                d
            } else {
                0.0
            };
        }
    }
    p.iter().all(|v| v.is_finite()).then_some(p)
}

fn nls_on_rows(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    rows: &[usize],
    model: &ModelOptions,
    start: &[f64],
    max_iter: usize,
) -> Result<(Vec<f64>, crate::lsq::NlsReport, LastNormal)> {
    let prob = Problem::new(data, rc, rows, *model);
    let q0: Vec<f64> = start.iter().zip(&prob.scales).map(|(a, s)| a / s).collect();
    // Tolerances a little looser than the lsq defaults: at the data's noise floor the default
    // ftol makes LM search dozens of dampings for a last 1e-15 cost reduction. A relative step
    // of 1e-11 in scaled parameters is far below any parameter's standard deviation.
    // Gauss-Newton first: from the linear start it converges quadratically and stops one step
    // after the noise floor, where LM would search many dampings for a last tiny decrease.
    // GN runs on normal equations accumulated row by row (no Jacobian storage, one pass per
    // iteration); LM on the stored Jacobian is the fallback whenever GN diverges or stalls.
    let opt = NlsOptions {
        max_iter,
        ftol: 1e-12,
        xtol: 1e-11,
        gtol: 1e-10,
        gauss_newton: true,
    };
    let rep = match solve_normal_gn(
        &prob,
        &q0,
        &NlsOptions {
            max_iter: 30,
            ..opt
        },
    ) {
        Ok(r) if r.converged => r,
        _ => solve_nls(
            &prob,
            &q0,
            &NlsOptions {
                gauss_newton: false,
                ..opt
            },
        )?,
    };
    let p = prob.external(&rep.params)[..prob.np].to_vec();
    Ok((p, rep, prob.last.into_inner()))
}

/// Closed-form recovery from the 13 Taylor coefficients, consistent with the series it
/// regresses on: returns `(S, b, D)` per axis.
///
/// With `z = (N - b) / S` and `N = S (f + D f^2) + b`, `f^2 = z^2 - 2 D z^3 + 5 D^2 z^4 +
/// O(z^5)`; expanding in `N` with `K = D b / S`:
/// `S^2 C2 = 1 + 6K + 30K^2`, `C3 = -2 D (1 + 10K) / S^3`, `C4 = 5 D^2 / S^4`,
/// `C1 = -2 b (1 + 3K + 10K^2) / S^2`. So `M = C4 C1 / (C3 C2) = 5K (1 + 3K + 10K^2) /
/// [(1 + 10K)(1 + 6K + 30K^2)]` (solved by Newton from `K = M / 5`, which stays the value when
/// no small root exists), then
/// `D = -C3 S^3 / [2 (1 + 10K)]` and `b = -C1 (1 + 6K + 30K^2) / [2 C2 (1 + 3K + 10K^2)]`.
/// The SPEC errata for eqs. 19-22 (`D = -C3 S^3 / [2 (1 + 2K)]`, `b = -C1 (1 + 6K + 6K^2) /
/// [2 C2 (1 + K)(1 + 2K)]`, `M (1 + 6K + 6K^2) = 5K (1 + K)`) take the `D^2 z^4` coefficient as
/// 1 in C1..C3 but 5 in C4; that inconsistency biases D by about `8K` relative (8e-5 on the
/// paper's x axis), on top of the truncation error of the dropped `z^5` term.
pub fn taylor_recover(c: &[f64]) -> Result<[[f64; 3]; 3]> {
    if c.len() != 13 {
        return invalid("13 Taylor coefficients expected");
    }
    let mut out = [[0.0; 3]; 3];
    let axis = ["x", "y", "z"];
    for i in 0..3 {
        let (c1, c2, c3, c4) = (c[1 + i], c[4 + i], c[7 + i], c[10 + i]);
        if c2 == 0.0 || c3 == 0.0 {
            return degenerate(format!(
                "taylor-paper: axis {}: zero quadratic or cubic coefficient, K2 not separable",
                axis[i]
            ));
        }
        let m = c4 / c3 * c1 / c2;
        if !m.is_finite() {
            return degenerate(format!(
                "taylor-paper: axis {}: no real K (M = {m:.3e})",
                axis[i]
            ));
        }
        // Without a small root the series does not hold for these rows (K = D b / S is not
        // small); the first-order K keeps the closed form defined (the robust screen's subset
        // fits), and the residuals of the exact model judge the result.
        let k = taylor_k(m).unwrap_or(m / 5.0);
        let q = 1.0 + 6.0 * k + 30.0 * k * k;
        if !(q / c2 > 0.0) {
            return degenerate(format!(
                "taylor-paper: axis {}: negative squared scale factor",
                axis[i]
            ));
        }
        let s = (q / c2).sqrt();
        // Eq. 21 corrected (sign of D) and made consistent with C41 = 5 D^2 S^-4.
        let d = -c3 * s * s * s / (2.0 * (1.0 + 10.0 * k));
        // Eq. 22 corrected (the printed one is inverted) and made consistent likewise.
        let b = -c1 * q / (2.0 * c2 * (1.0 + 3.0 * k + 10.0 * k * k));
        out[0][i] = s;
        out[1][i] = b;
        out[2][i] = d;
    }
    Ok(out)
}

/// The root `K ~ M / 5` of `5K (1 + 3K + 10K^2) = M (1 + 10K)(1 + 6K + 30K^2)`, i.e.
/// `(5 - 30M)(10K^3 + 3K^2) + (5 - 16M) K - M = 0`, by Newton; `None` when it does not
/// converge to a small root (|K| < 0.1: the series needs `|D f| << 1`, hence `|K| << 1`).
pub fn taylor_k(m: f64) -> Option<f64> {
    if !m.is_finite() {
        return None;
    }
    let a = 5.0 - 30.0 * m;
    let l = 5.0 - 16.0 * m;
    let mut k = m / 5.0;
    for _ in 0..50 {
        let g = a * (10.0 * k * k * k + 3.0 * k * k) + l * k - m;
        let dg = a * (30.0 * k * k + 6.0 * k) + l;
        if !(dg != 0.0) {
            return None;
        }
        let step = g / dg;
        k -= step;
        if !(k.abs() < 0.1) {
            return None;
        }
        if step == 0.0 || step.abs() <= 1e-13 * k.abs() {
            return Some(k);
        }
    }
    None
}

/// The paper's 13-column regression of `A^2 + 1` on `[1, N, N^2, N^3, N^4]` (unweighted OLS).
pub fn taylor_coefficients(data: &CentrifugeData<'_>, rows: &[usize]) -> Result<Vec<f64>> {
    let m = rows.len();
    let mut a = Vec::with_capacity(13 * m);
    let mut y = Vec::with_capacity(m);
    for &k in rows {
        let n = data.outputs[k];
        a.push(1.0);
        for pw in 1..=4 {
            for v in n {
                a.push(v.powi(pw));
            }
        }
        y.push(target(data, k));
    }
    lstsq_small(&a, m, 13, &y).map_err(|e| match e {
        CoreError::Degenerate(msg) => CoreError::Degenerate(format!(
            "taylor-paper regression: {msg}; every axis needs at least five distinct output levels"
        )),
        other => other,
    })
}

struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        // splitmix64
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

fn kth_smallest(v: &[f64], k: usize) -> f64 {
    let mut w: Vec<f64> = v.to_vec();
    let k = k.min(w.len() - 1);
    w.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    w[k]
}

/// Weighted robust residuals (`|r| / sigma`), inf for rows outside the invertible range.
fn weighted_abs(rc: &[RowConst], r: &[f64]) -> Vec<f64> {
    r.iter()
        .zip(rc)
        .map(|(v, c)| {
            if v.is_finite() {
                (v * c.w).abs()
            } else {
                f64::INFINITY
            }
        })
        .collect()
}

/// Least median of squares over random minimal subsets of the base (S, b, K2) model.
/// Returns (parameters of the base model, draws).
/// Exact fit of the base model (S, b, K2) to a minimal subset of 9 rows: linear start, then
/// Newton on the square system. `None` when the subset does not determine a solution.
fn subset_fit(data: &CentrifugeData<'_>, rc: &[RowConst], subset: &[usize]) -> Option<[f64; 9]> {
    let base = ModelOptions::default();
    let st = linear_start(data, subset, &base).ok()?;
    let mut p = [0.0f64; 9];
    p.copy_from_slice(&st[..9]);
    let sc = base.scales();
    for _ in 0..20 {
        let mut jm = [[0.0f64; 9]; 9];
        let mut r = [0.0f64; 9];
        let pp = param_pre(&base, &p)?;
        let mut grad = [0.0; MAX_PARAMS];
        for (a, &k) in subset.iter().enumerate() {
            r[a] = -row_eval(&data.outputs[k], &rc[k], &pp, &base, Some(&mut grad))?;
            for j in 0..9 {
                jm[a][j] = grad[j] * sc[j];
            }
        }
        // Newton step of the square system (QR with the rank test of `lsq`).
        let step = lstsq_rows::<9>(&jm, &r).ok()?;
        let mut big = 0.0f64;
        for j in 0..9 {
            let d = step[j] * sc[j];
            p[j] += d;
            big = big.max(step[j].abs());
        }
        if !p.iter().all(|v| v.is_finite()) || big > 1e6 {
            return None;
        }
        if big < 1e-12 {
            return Some(p);
        }
    }
    // Not converged: accept only if the subset residuals are negligible.
    let pp = param_pre(&base, &p)?;
    let ok = subset.iter().all(|&k| {
        row_eval(&data.outputs[k], &rc[k], &pp, &base, None).is_some_and(|r| r.abs() < 1e-9)
    });
    ok.then_some(p)
}

/// Least median of squares over random minimal subsets of the base (S, b, K2) model.
/// The number of draws assumes up to half the rows are bad (99.99 % confidence).
/// Returns (parameters of the base model, draws).
fn lmeds(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    opt: &FitOptions,
) -> Result<(Vec<f64>, usize)> {
    let p = ModelOptions::default().n_params();
    let w = 0.5f64.powi(p as i32);
    let needed = ((1e-4f64.ln() / (1.0 - w).ln()).ceil() as usize).min(opt.max_draws);
    lmeds_draws(data, rc, opt, needed).map(|(params, draws, _)| (params, draws))
}

/// The h-th smallest of the weighted absolute residuals `ab` ([`weighted_abs`];
/// `h = ceil((n + 9) / 2)`): the least-median criterion.
fn lmeds_criterion(ab: &[f64]) -> f64 {
    let n = ab.len();
    let h = (n + ModelOptions::default().n_params()).div_ceil(2);
    kth_smallest(ab, h.min(n) - 1)
}

/// A robust residual scale from an order statistic `x` of `m` absolute residuals of a fit of
/// `p` parameters (the median's, or the least-median criterion): `1.4826 x` with the
/// small-sample factor `1 + 5 / (m - p)`, at least `floor`.
fn robust_scale(x: f64, m: usize, p: usize, floor: f64) -> f64 {
    (1.4826 * (1.0 + 5.0 / (m - p) as f64) * x).max(floor)
}

/// [`lmeds`] with at most `needed` minimal subsets; also returns the best criterion.
fn lmeds_draws(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    opt: &FitOptions,
    needed: usize,
) -> Result<(Vec<f64>, usize, f64)> {
    let base = ModelOptions::default();
    let n = data.outputs.len();
    let p = base.n_params();
    let h = (n + p).div_ceil(2);
    let mut rng = Rng(opt.seed ^ 0xA5A5_5A5A_C3C3_3C3C);
    let mut best: Option<(f64, Vec<f64>)> = None;
    let mut draws = 0;
    let mut subset = Vec::with_capacity(p);
    let mut a = vec![0.0; n];
    let mut work = vec![0.0; n];
    while draws < needed {
        draws += 1;
        subset.clear();
        while subset.len() < p {
            let c = rng.below(n);
            if !subset.contains(&c) {
                subset.push(c);
            }
        }
        // At least two speeds in the subset, otherwise K2 is not separable.
        let w0 = data.omega[subset[0]].abs();
        if subset
            .iter()
            .all(|&k| (data.omega[k].abs() - w0).abs() <= 1e-9 * w0)
        {
            continue;
        }
        let Some(params) = subset_fit(data, rc, &subset) else {
            continue;
        };
        let Some(pp) = param_pre(&base, &params) else {
            continue;
        };
        for ((ak, n), c) in a.iter_mut().zip(data.outputs).zip(rc) {
            *ak = row_eval(n, c, &pp, &base, None)
                .map(|r| (r * c.w).abs())
                .unwrap_or(f64::INFINITY);
        }
        work.copy_from_slice(&a);
        work.select_nth_unstable_by(h - 1, |x, y| x.total_cmp(y));
        let crit = work[h - 1];
        if !crit.is_finite() {
            continue;
        }
        if best.as_ref().is_none_or(|(c, _)| crit < *c) {
            best = Some((crit, params.to_vec()));
        }
    }
    match best {
        Some((crit, params)) => Ok((params, draws, crit)),
        None => degenerate(
            "robust screening found no subset of rows consistent with the model \
             (need at least two speeds and more than half of the rows good)",
        ),
    }
}

// ------------------------------------------------------------------------------------------
// The fit, stage by stage. [`fit`] runs: input and option checks, the unit check, start values
// (with the noise weights at them), the plain fit on every row, screening, sign folding, and
// covariance / observability.

/// What one fit on a set of rows produced.
#[derive(Debug, Clone)]
struct Outcome {
    /// Parameters in external units.
    params: Vec<f64>,
    /// Solver iterations (0 for the closed form).
    iterations: usize,
    /// Solver convergence flag.
    converged: bool,
    /// The 13 regression coefficients (TaylorPaper only).
    taylor: Option<Vec<f64>>,
    /// The solver's last normal-equation evaluation (nls), reused by the covariance stage.
    last: Option<LastNormal>,
}

/// Stage (final fit) on `rows`: nls from `start` (the linear start when `None`) or the
/// paper's closed form.
fn final_fit(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    rows: &[usize],
    opt: &FitOptions,
    start: Option<&[f64]>,
) -> Result<Outcome> {
    match opt.method {
        Method::Nls => {
            let st = match start {
                Some(s) => {
                    let mut v = vec![0.0; opt.model.n_params()];
                    let m = s.len().min(v.len());
                    v[..m].copy_from_slice(&s[..m]);
                    v
                }
                None => linear_start(data, rows, &opt.model)?,
            };
            let (p, rep, last) = nls_on_rows(data, rc, rows, &opt.model, &st, 200)?;
            Ok(Outcome {
                params: p,
                iterations: rep.iterations,
                converged: rep.converged,
                taylor: None,
                last: Some(last),
            })
        }
        Method::TaylorPaper => {
            if opt.model != ModelOptions::default() {
                return invalid(
                    "method 'taylor-paper' supports only the scale + bias + K2 model; use 'nls'",
                );
            }
            let c = taylor_coefficients(data, rows)?;
            let sbd = taylor_recover(&c)?;
            Ok(Outcome {
                params: sbd.iter().flatten().copied().collect(),
                iterations: 0,
                converged: true,
                taylor: Some(c),
                last: None,
            })
        }
    }
}

/// Stage (noise weights): with per-axis output noise `sigma_kj` (g) the standard deviation of
/// row k's norm residual is, to first order, `|sigma_k * dr/dN_k|` (`dr/dN = -dr/db`); its
/// inverse is the row's weight. Rows the parameters cannot invert keep their weight. Without
/// `sigma` every weight stays 1.
fn noise_weights(data: &CentrifugeData<'_>, rc: &mut [RowConst], model: &ModelOptions, p: &[f64]) {
    let Some(sig) = data.sigma else {
        return;
    };
    let Some(pp) = param_pre(model, p) else {
        return;
    };
    let mut grad = [0.0; MAX_PARAMS];
    for (k, c) in rc.iter_mut().enumerate() {
        if row_eval(&data.outputs[k], c, &pp, model, Some(&mut grad)).is_none() {
            continue;
        }
        let s = sig[k];
        let v = (s[0] * grad[3]).powi(2) + (s[1] * grad[4]).powi(2) + (s[2] * grad[5]).powi(2);
        let sd = v.sqrt();
        if sd > 0.0 && sd.is_finite() {
            c.w = 1.0 / sd;
        }
    }
}

/// Standard deviation (g) of each row's norm residual from the per-axis output noise
/// `data.sigma`, propagated at the parameters `p` (first order, as the fit weighs the rows);
/// for callers that test residuals against the noise (e.g. the gap diagnosis). Errors when
/// `sigma` is missing or a row cannot be inverted at `p`.
pub fn residual_std(
    data: &CentrifugeData<'_>,
    model: &ModelOptions,
    p: &[f64],
) -> Result<Vec<f64>> {
    validate(data, model)?;
    if data.sigma.is_none() {
        return invalid("residual_std needs the per-axis output noise (sigma, g)");
    }
    if p.len() != model.n_params() {
        return invalid(format!(
            "{} parameters given, the model has {}",
            p.len(),
            model.n_params()
        ));
    }
    let mut rc = row_consts(data);
    for c in rc.iter_mut() {
        c.w = f64::NAN;
    }
    noise_weights(data, &mut rc, model, p);
    rc.iter()
        .enumerate()
        .map(|(k, c)| {
            if c.w.is_finite() {
                Ok(1.0 / c.w)
            } else {
                invalid(format!(
                    "row {k} lies outside the invertible range at these parameters"
                ))
            }
        })
        .collect()
}

/// Parameters at which the noise weights are first evaluated when no start exists: a unit
/// triad (only the direction of `dr/dN` matters much, and it is close to that of `N`).
fn nominal_params(model: &ModelOptions) -> Vec<f64> {
    let mut p = vec![0.0; model.n_params()];
    p[..3].fill(1.0);
    p
}

/// Stage (start): linear start on every row, and the noise weights there. `None` when the
/// rows do not describe an ellipsoid (gross outliers; the screen then starts on its own).
fn start_values(
    data: &CentrifugeData<'_>,
    rc: &mut [RowConst],
    rows: &[usize],
    model: &ModelOptions,
) -> Option<Vec<f64>> {
    let start = linear_start(data, rows, model).ok();
    let at = start.clone().unwrap_or_else(|| nominal_params(model));
    noise_weights(data, rc, model, &at);
    start
}

/// [`final_fit`] with the noise weights refreshed at the result and one refit from there when
/// the noise is given per axis (the weights depend on the parameters only through the slope of
/// the norm, so one refit makes them consistent with the estimate).
fn fit_rows(
    data: &CentrifugeData<'_>,
    rc: &mut [RowConst],
    rows: &[usize],
    opt: &FitOptions,
    start: Option<&[f64]>,
) -> Result<Outcome> {
    let out = final_fit(data, rc, rows, opt, start)?;
    if data.sigma.is_none() {
        return Ok(out);
    }
    noise_weights(data, rc, &opt.model, &out.params);
    if opt.method != Method::Nls {
        // The paper's regression is unweighted: the weights serve the covariance only.
        return Ok(out);
    }
    final_fit(data, rc, rows, opt, Some(&out.params))
}

/// The screening statistic of every row at parameters fitted on `rows`.
#[derive(Debug, Clone)]
struct Studentized {
    /// Externally studentised residual of each row used (`r_k / (s_(k) sqrt(1 - h_k))`, with
    /// `s_(k)` the residual scale without row k and `h_k` its leverage), prediction residual of
    /// the others (`r / (s sqrt(1 + h))`); `inf` where the row cannot be inverted, 0 where the
    /// row alone determines a parameter (`h = 1`, untestable).
    t: Vec<f64>,
    /// Residual scale `s` of the rows used: g without `sigma`, 1 (whitened) with it.
    scale: f64,
    /// Unweighted norm residual of every row (g; `inf` where not invertible).
    r: Vec<f64>,
    /// Leverage-corrected weighted residual `w r_k / sqrt(1 - h_k)` of each row used (each
    /// one's std is the noise's, whatever its leverage); NaN for the others and where the row
    /// is untestable. What [`masked`] measures against a robust scale.
    u: Vec<f64>,
    /// Residual degrees of freedom `m - p` of the rows used.
    dof: usize,
}

/// Stage (screening statistic): [`Studentized`] at `p` fitted on `rows`. The leverages come
/// from the Jacobian at `p` and the inverse of its column-normalised normal matrix (through
/// [`crate::lsq`]); a singular normal matrix gives zero leverages.
fn studentize(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    opt: &FitOptions,
    p: &[f64],
    rows: &[usize],
) -> Studentized {
    let model = &opt.model;
    let np = model.n_params();
    let n = data.outputs.len();
    let scales = model.scales();
    let mut r = vec![f64::INFINITY; n];
    let mut jr = vec![[0.0f64; MAX_PARAMS]; n];
    let mut ok = vec![false; n];
    if let Some(pp) = param_pre(model, p) {
        let mut grad = [0.0; MAX_PARAMS];
        for k in 0..n {
            if let Some(v) = row_eval(&data.outputs[k], &rc[k], &pp, model, Some(&mut grad)) {
                r[k] = v;
                ok[k] = true;
                for j in 0..np {
                    jr[k][j] = rc[k].w * grad[j] * scales[j];
                }
            }
        }
    }
    // Normal matrix of the rows used, column-normalised, and its inverse.
    let mut a = vec![0.0; np * np];
    let mut rss = 0.0;
    for &k in rows.iter().filter(|&&k| ok[k]) {
        let wr = rc[k].w * r[k];
        rss += wr * wr;
        for i in 0..np {
            for j in i..np {
                a[i * np + j] += jr[k][i] * jr[k][j];
            }
        }
    }
    let cn: Vec<f64> = (0..np).map(|j| a[j * np + j].sqrt()).collect();
    let mut an = vec![0.0; np * np];
    for i in 0..np {
        for j in i..np {
            let v = a[i * np + j] / (cn[i] * cn[j]);
            an[i * np + j] = v;
            an[j * np + i] = v;
        }
    }
    let c = (cn.iter().all(|v| *v > 0.0 && v.is_finite()) && cholesky_small(&mut an, np))
        .then(|| cholesky_inverse_small(&an, np));
    let mut icn = [0.0f64; MAX_PARAMS];
    for j in 0..np {
        icn[j] = 1.0 / cn[j];
    }
    let leverage = |k: usize| -> f64 {
        let Some(c) = &c else { return 0.0 };
        let mut x = [0.0f64; MAX_PARAMS];
        for j in 0..np {
            x[j] = jr[k][j] * icn[j];
        }
        let mut h = 0.0;
        for i in 0..np {
            let ci = &c[i * np..(i + 1) * np];
            let mut v = 0.0;
            for j in 0..np {
                v += ci[j] * x[j];
            }
            h += x[i] * v;
        }
        h
    };
    let m = rows.iter().filter(|&&k| ok[k]).count();
    let dof = m.saturating_sub(np);
    let known = data.sigma.is_some();
    let floor2 = opt.sigma_floor * opt.sigma_floor;
    let s2 = if known {
        1.0
    } else {
        (rss / dof.max(1) as f64).max(floor2)
    };
    let mut used = vec![false; n];
    for &k in rows {
        used[k] = true;
    }
    let mut u = vec![f64::NAN; n];
    let t = (0..n)
        .map(|k| {
            if !ok[k] {
                return f64::INFINITY;
            }
            let wr = rc[k].w * r[k];
            let h = leverage(k);
            if !used[k] {
                return wr / (s2 * (1.0 + h)).sqrt();
            }
            let q = 1.0 - h;
            if !(q > 1e-12) {
                return 0.0;
            }
            u[k] = wr / q.sqrt();
            let sk2 = if known {
                1.0
            } else if dof >= 2 {
                ((rss - wr * wr / q) / (dof - 1) as f64).max(floor2)
            } else {
                // No residual degree of freedom left without row k: untestable.
                return 0.0;
            };
            wr / (sk2 * q).sqrt()
        })
        .collect();
    Studentized {
        t,
        scale: s2.sqrt(),
        r,
        u,
        dof,
    }
}

/// The gate of [`masked`], in robust scales: one row beyond [`MASKING_GATE`], or
/// [`MASKING_TAIL_ROWS`] rows beyond [`MASKING_TAIL`] (many gross errors smear into each other
/// until none stands far out). On clean 60-row sessions it opens in 0.8 % of sessions
/// (20 000 simulated with a random Gaussian design and 9 parameters; 0.7 % for the first rule
/// alone) and in 1.6 % of 3000 sessions of the centrifuge paper's design
/// (`benches/validate_centrifuge_screen.py`), which then only cost a screen that keeps every
/// row.
const MASKING_GATE: f64 = 4.0;
/// See [`MASKING_GATE`].
const MASKING_TAIL: f64 = 3.0;
/// See [`MASKING_GATE`].
const MASKING_TAIL_ROWS: usize = 3;

/// Whether rows with gross errors may hide each other in the plain fit with the noise
/// estimated (masking): several of them inflate the residual scale that every studentised
/// residual is measured against (4 lost minus signs in 60 rows: the largest studentised
/// residual 3.5, under the threshold, with the residual RMS 80 000 times the noise). Against a
/// robust scale instead - the median of the leverage-corrected residuals `|u|`, with the
/// small-sample factor of the least-median start - such rows stand out. True when the gate of
/// [`MASKING_GATE`] opens (its single-row level capped at `threshold`): the screen then runs,
/// and decides (its classification is the studentised residual's, and its verdict,
/// [`misfit_is_spread`], keeps every row when the misfit is a model error).
fn masked(st: &Studentized, threshold: f64, p: usize, floor: f64) -> bool {
    let a: Vec<f64> =
        st.u.iter()
            .filter(|v| v.is_finite())
            .map(|v| v.abs())
            .collect();
    let m = a.len();
    if m < p + 3 {
        return false;
    }
    let s = robust_scale(kth_smallest(&a, (m - 1) / 2), m, p, floor);
    let gate = MASKING_GATE.min(threshold);
    a.iter().any(|&v| v > gate * s)
        || a.iter().filter(|&&v| v > MASKING_TAIL * s).count() >= MASKING_TAIL_ROWS
}

/// Minimal subsets drawn by [`probe_masked`]: with a quarter of the rows bad it misses every
/// clean subset with probability 4e-4 (`(1 - 0.75^9)^100`), in about half a millisecond.
const PROBE_DRAWS: usize = 100;

/// [`probe_masked`] finds the rows masked when its least-median criterion is below this
/// fraction of the plain fit's (gross errors: 1e-4 or less; clean rows and model errors
/// spread over the rows: near 1 or above, a minimal subset being a noisier fit).
const PROBE_RATIO: f64 = 0.2;

/// [`probe_masked`] runs when the plain fit's RMS norm residual exceeds this fraction of the
/// norm (RMS of `r / sqrt(A^2 + 1)`): gross errors that mask each other leave far more (10
/// lost signs in 60 rows: 3e-2); a precision triad's table leaves 1e-6 to 1e-5 and is not
/// probed (the probe costs about 2 ms, a hundred fits).
const PROBE_MIN_RELATIVE: f64 = 1e-4;

/// The second look for masking with the noise estimated, when [`masked`] sees nothing: so
/// many gross errors (10 lost signs in 60 rows) that the plain fit absorbs them and no row
/// stands out even against a robust scale. A short least-median search over [`PROBE_DRAWS`]
/// minimal subsets finds a fit whose median residual is far below the plain fit's
/// ([`PROBE_RATIO`]) only when a majority of the rows agree much better than the plain fit
/// says: then the full screen runs and decides. Only when the plain fit leaves more than
/// [`PROBE_MIN_RELATIVE`] of the norm.
fn probe_masked(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    opt: &FitOptions,
    r_plain: &[f64],
) -> bool {
    let (mut ss, mut m) = (0.0, 0usize);
    for (r, c) in r_plain.iter().zip(rc) {
        if r.is_finite() {
            ss += (r * c.inv_st) * (r * c.inv_st);
            m += 1;
        }
    }
    if m == 0 || !((ss / m as f64).sqrt() > PROBE_MIN_RELATIVE) {
        return false;
    }
    let plain = lmeds_criterion(&weighted_abs(rc, r_plain));
    if !(plain > opt.sigma_floor) {
        return false;
    }
    match lmeds_draws(data, rc, opt, PROBE_DRAWS.min(opt.max_draws)) {
        Ok((_, _, crit)) => crit < PROBE_RATIO * plain,
        Err(_) => false,
    }
}

/// Threshold on the studentised residual with the two-sided tail probability of `k` standard
/// normal deviations: `k` itself when the noise is known, else the Student t quantile with
/// `dof` degrees of freedom (so `outlier_k` means the same false-exclusion rate whatever the
/// number of rows).
fn t_threshold(k: f64, dof: usize, known: bool) -> f64 {
    if known || dof == 0 || dof > 100_000 {
        return k;
    }
    thread_local! {
        /// The last threshold computed: (k, dof, threshold). A fit asks for the same one again.
        static LAST: std::cell::Cell<(f64, usize, f64)> = const { std::cell::Cell::new((f64::NAN, 0, 0.0)) };
    }
    let (k0, d0, t0) = LAST.with(|c| c.get());
    if k0 == k && d0 == dof {
        return t0;
    }
    let t = student_quantile(chi2_sf(k * k, 1.0), dof as f64, k);
    LAST.with(|c| c.set((k, dof, t)));
    t
}

/// `t > 0` with two-sided Student tail `P(|T_nu| > t) = p`: secant steps on `ln P` from the
/// Cornish-Fisher expansion around the normal quantile `z`, then bisection if they stall.
fn student_quantile(p: f64, nu: f64, z: f64) -> f64 {
    let ln_tail = |t: f64| f_sf(t * t, 1.0, nu).ln() - p.ln();
    let (z3, z5, z7) = (z.powi(3), z.powi(5), z.powi(7));
    let cf = z
        + (z3 + z) / (4.0 * nu)
        + (5.0 * z5 + 16.0 * z3 + 3.0 * z) / (96.0 * nu * nu)
        + (3.0 * z7 + 19.0 * z5 + 17.0 * z3 - 15.0 * z) / (384.0 * nu.powi(3));
    let (mut a, mut b) = (cf.max(z), cf.max(z) * 1.001);
    let (mut fa, mut fb) = (ln_tail(a), ln_tail(b));
    for _ in 0..30 {
        if !(fa.is_finite() && fb.is_finite()) || fb == fa {
            break;
        }
        let c = b - fb * (b - a) / (fb - fa);
        if !(c > 0.0) || !c.is_finite() {
            break;
        }
        (a, fa) = (b, fb);
        b = c;
        fb = ln_tail(b);
        if (b - a).abs() <= 1e-12 * b {
            return b;
        }
    }
    // Bisection (the tail falls with t).
    let (mut lo, mut hi) = (z, 2.0 * z.max(1.0));
    while ln_tail(hi) > 0.0 && hi < 1e12 {
        lo = hi;
        hi *= 2.0;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if ln_tail(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    hi
}

/// Rows kept by the screen, the fit on them and the screening statistics.
#[derive(Debug, Clone)]
struct Screened {
    rows: Vec<usize>,
    out: Outcome,
    draws: usize,
    st: Studentized,
    threshold: f64,
    /// The screen ran and its exclusion was voided by [`misfit_is_spread`]: every row kept.
    kept_all: bool,
}

/// Most reclassification rounds of the screen (it stops earlier when the rows settle).
const SCREEN_ROUNDS: usize = 10;

/// Largest credible ratio of the excluded rows' residuals in the screened fit to their
/// residuals in the plain fit (root sum of squares over the excluded rows; see
/// [`misfit_is_spread`]).
const SCREEN_MAX_AMPLIFICATION: f64 = 30.0;

/// Fewest excluded rows (not lost signs) whose agreeing residuals make a systematic group
/// (rule 5 of [`misfit_is_spread`]).
const SCREEN_GROUP_MIN: usize = 4;

/// Fewest excluded rows (not lost signs), all at one speed, that make a systematic group
/// (rule 6 of [`misfit_is_spread`]).
const SCREEN_SPEED_GROUP_MIN: usize = 6;

/// Largest residual of a row with one output's sign flipped, relative to its residual as
/// given, for the flip to explain it (a lost sign takes a 0.1 g residual to the noise).
const SIGN_SLIP_RATIO: f64 = 0.05;

/// Whether each row meets the fit at `p` with one of its outputs' sign flipped (a lost minus
/// sign): its weighted residual then within `bound` and under [`SIGN_SLIP_RATIO`] of its
/// residual as given.
fn sign_slips(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    model: &ModelOptions,
    p: &[f64],
    rows: &[usize],
    bound: f64,
) -> Vec<bool> {
    let mut out = vec![false; data.outputs.len()];
    let Some(pp) = param_pre(model, p) else {
        return out;
    };
    for &k in rows {
        let r0 =
            row_eval(&data.outputs[k], &rc[k], &pp, model, None).map_or(f64::INFINITY, f64::abs);
        out[k] = (0..3).any(|i| {
            let mut n = data.outputs[k];
            n[i] = -n[i];
            row_eval(&n, &rc[k], &pp, model, None)
                .is_some_and(|r| (r * rc[k].w).abs() <= bound && r.abs() <= SIGN_SLIP_RATIO * r0)
        });
    }
    out
}

/// Stage (screen verdict): whether the screen's exclusion of `excluded` (of `n` rows) is a
/// misfit spread over the rows (a model error: radius, rate, lever arm, misalignment, K3)
/// rather than sparse gross errors, in which case every row is kept. The screen is for sparse
/// errors; it is overruled when
/// 1. it excludes more than half of the rows: beyond the breakdown point of its least-median
///    start, so whatever it keeps is not "the good majority";
/// 2. the excluded rows' residuals in the screened fit (`r_screened`, g) exceed
///    [`SCREEN_MAX_AMPLIFICATION`] times their residuals in the plain fit on every row
///    (`r_plain`, g; rows not invertible there are left out). For a linear model the deleted
///    residuals of a set O are `(I - H_OO)^-1` times its plain residuals, a ratio at most
///    `1 / (1 - lambda_max(H_OO))`: a ratio of 30 means the rows kept see less than 1/30 of
///    the information on some parameter combination that the excluded rows carry, so the
///    screened fit moved freely along it (absorbing a model error in the kept rows) and the
///    excluded rows' large residuals are made by the exclusion, not found by it. Gross errors
///    in simulated sessions (1 to 40 % of the rows, sign flips, offsets) give ratios of 1 to
///    11; a 1e-4 radius or rate error at 1e-6 g noise gives 700 to 9e4;
/// 3. it excludes more than a quarter of the rows, the noise is given, and the rows it keeps
///    still reject the noise model: their whitened chi-square `kept_chi2 = (chi2, dof)` is
///    beyond the screen's own tail probability `tail` (`2 Phi(-outlier_k)`). Such an exclusion
///    trimmed the worst rows of a misfit present in every row;
/// 4. more than a quarter of the rows are excluded and not explained as a lost sign (`slip[k]`:
///    row k meets the screened fit with one output's sign flipped, the transcription error of
///    the paper's printed table). A radius off by a factor 2 had 20 of 60 rows (whole position
///    groups) excluded and the other 40 fitted to the noise, with S twice the truth;
/// 5. at least [`SCREEN_GROUP_MIN`] rows not explained as lost signs are excluded and their
///    residuals in the screened fit agree in sign and within a factor 2 in size: one
///    systematic effect, not unrelated gross errors (a 10 % radius error excluded the 8 rows of
///    the lowest speed whose specific force is mostly gravity, residuals 0.0226 to 0.0229 g);
/// 6. at least [`SCREEN_SPEED_GROUP_MIN`] rows not explained as lost signs are excluded, all at
///    one speed (`omega`, rad/s, per row): an effect growing with the speed (a K3 of 8e-6 g/g^3
///    excluded 12 rows of the highest speed).
#[allow(clippy::too_many_arguments)]
fn misfit_is_spread(
    n: usize,
    excluded: &[usize],
    r_plain: &[f64],
    r_screened: &[f64],
    kept_chi2: Option<(f64, usize)>,
    tail: f64,
    slip: &[bool],
    omega: &[f64],
) -> bool {
    let q = excluded.len();
    if q == 0 {
        return false;
    }
    if 2 * q > n {
        return true;
    }
    let gross: Vec<f64> = excluded
        .iter()
        .filter(|&&k| !slip.get(k).copied().unwrap_or(false))
        .map(|&k| r_screened[k])
        .collect();
    if 4 * gross.len() > n {
        return true;
    }
    if gross.len() >= SCREEN_GROUP_MIN && gross.iter().all(|r| r.is_finite()) {
        let same_sign = gross.iter().all(|r| *r > 0.0) || gross.iter().all(|r| *r < 0.0);
        let (lo, hi) = gross.iter().fold((f64::INFINITY, 0.0f64), |(a, b), r| {
            (a.min(r.abs()), b.max(r.abs()))
        });
        if same_sign && hi <= 2.0 * lo {
            return true;
        }
    }
    let gross_rows: Vec<usize> = excluded
        .iter()
        .copied()
        .filter(|&k| !slip.get(k).copied().unwrap_or(false))
        .collect();
    if gross_rows.len() >= SCREEN_SPEED_GROUP_MIN {
        let w0 = omega.get(gross_rows[0]).map_or(f64::NAN, |w| w.abs());
        if gross_rows.iter().all(|&k| {
            omega
                .get(k)
                .is_some_and(|w| (w.abs() - w0).abs() <= 1e-9 * w0.max(1e-300))
        }) {
            return true;
        }
    }
    let (mut ss_screened, mut ss_plain) = (0.0, 0.0);
    for &k in excluded {
        let (a, b) = (r_screened[k], r_plain[k]);
        if a.is_finite() && b.is_finite() {
            ss_screened += a * a;
            ss_plain += b * b;
        }
    }
    if ss_screened > SCREEN_MAX_AMPLIFICATION * SCREEN_MAX_AMPLIFICATION * ss_plain {
        return true;
    }
    if 4 * q > n {
        if let Some((chi2, dof)) = kept_chi2 {
            if dof > 0 && chi2_sf(chi2, dof as f64) < tail {
                return true;
            }
        }
    }
    false
}

/// Stage (screening). A good row is excluded when its studentised residual exceeds the
/// threshold of [`t_threshold`], i.e. with the probability of a `outlier_k`-sigma normal event
/// (`2 Phi(-k)` per row). The plain fit on every row is kept when no row exceeds it (or the
/// screen is off); otherwise the least median of squares over random minimal subsets gives
/// an outlier-free start, and the rows are reclassified with the same statistic until they
/// settle. The plain fit is kept after all (`kept_all`) when [`misfit_is_spread`] judges the
/// exclusion a model error; fewer than `p + 2` rows left is an error saying so.
fn screen(
    data: &CentrifugeData<'_>,
    rc: &mut [RowConst],
    opt: &FitOptions,
    plain: Result<Outcome>,
) -> Result<Screened> {
    let n = data.outputs.len();
    let p = opt.model.n_params();
    let known = data.sigma.is_some();
    let all: Vec<usize> = (0..n).collect();
    // The plain fit with its row weights, for the verdict on the screen's exclusion.
    let mut plain_fit: Option<(Screened, Vec<RowConst>)> = None;
    match plain {
        Ok(out) => {
            let st = studentize(data, rc, opt, &out.params, &all);
            let threshold = t_threshold(opt.outlier_k, st.dof.saturating_sub(1), known);
            let sc = Screened {
                rows: all,
                out,
                draws: 0,
                st,
                threshold,
                kept_all: false,
            };
            let clean = sc.st.t.iter().all(|v| v.abs() <= threshold)
                && (known
                    || !opt.robust
                    || !(masked(&sc.st, threshold, p, opt.sigma_floor)
                        || probe_masked(data, rc, opt, &sc.st.r)));
            if !opt.robust || clean {
                return Ok(sc);
            }
            plain_fit = Some((sc, rc.to_vec()));
        }
        Err(e) if !opt.robust => return Err(e),
        // The plain fit can fail outright on gross outliers: go straight to the screen.
        Err(_) => {}
    }
    let (base_p, draws) = lmeds(data, rc, opt)?;
    // First classification from the least-median fit (a robust scale from the median).
    let rb = residuals_pre(data, rc, &ModelOptions::default(), &base_p);
    let ab = weighted_abs(rc, &rb);
    let sig_l = robust_scale(lmeds_criterion(&ab), n, 9, opt.sigma_floor);
    let mut rows: Vec<usize> = (0..n).filter(|&k| ab[k] <= opt.outlier_k * sig_l).collect();
    let mut start = base_p;
    let mut last: Option<Screened> = None;
    for _ in 0..SCREEN_ROUNDS {
        if rows.len() < p + 2 {
            return degenerate(format!(
                "the robust screen found only {} rows consistent with the model ({} parameters \
                 need at least {}): the model does not fit the rows as a whole, which is a \
                 model error (the radius or rate, a lever arm, misalignment, K3), not a few \
                 outliers, unless most rows are bad. Fit with the screen off (robust=False) to \
                 see the residuals over speed and position, and run diagnose_centrifuge to \
                 name the effect",
                rows.len(),
                p,
                p + 2
            ));
        }
        let st_opt = (opt.method == Method::Nls).then_some(&start[..]);
        let out = fit_rows(data, rc, &rows, opt, st_opt)?;
        let st = studentize(data, rc, opt, &out.params, &rows);
        let threshold = t_threshold(opt.outlier_k, st.dof.saturating_sub(1), known);
        let next: Vec<usize> = (0..n).filter(|&k| st.t[k].abs() <= threshold).collect();
        start.clone_from(&out.params);
        let settled = next == rows;
        last = Some(Screened {
            rows: std::mem::replace(&mut rows, next),
            out,
            draws,
            st,
            threshold,
            kept_all: false,
        });
        if settled {
            break;
        }
    }
    let sc =
        last.ok_or_else(|| CoreError::NotConverged("the robust screen ran no round".into()))?;
    let Some((mut whole, rc_plain)) = plain_fit else {
        return Ok(sc);
    };
    let mut used = vec![false; n];
    for &k in &sc.rows {
        used[k] = true;
    }
    let excluded: Vec<usize> = (0..n).filter(|&k| !used[k]).collect();
    let kept_chi2 = known.then(|| {
        let chi2 = sc
            .rows
            .iter()
            .map(|&k| rc[k].w * sc.st.r[k])
            .filter(|v| v.is_finite())
            .map(|v| v * v)
            .sum::<f64>();
        (chi2, sc.st.dof)
    });
    let tail = chi2_sf(opt.outlier_k * opt.outlier_k, 1.0);
    let slip = sign_slips(
        data,
        rc,
        &opt.model,
        &sc.out.params,
        &excluded,
        2.0 * sc.threshold * sc.st.scale,
    );
    if misfit_is_spread(
        n,
        &excluded,
        &whole.st.r,
        &sc.st.r,
        kept_chi2,
        tail,
        &slip,
        data.omega,
    ) {
        rc.copy_from_slice(&rc_plain);
        whole.draws = draws;
        whole.kept_all = true;
        return Ok(whole);
    }
    Ok(sc)
}

/// Stage (sign folding): `S > 0` (a norm observation cannot fix it when D = 0). Flipping `S_i`
/// flips `f_i`, so `D_i`, the misalignment terms touching axis i and its lever arm flip too.
/// Returns whether anything changed.
fn fold_sign(params: &mut [f64], model: &ModelOptions) -> bool {
    let at = if model.k3 { 12 } else { 9 };
    let mut folded = false;
    for i in 0..3 {
        if params[i] >= 0.0 {
            continue;
        }
        folded = true;
        params[i] = -params[i];
        params[6 + i] = -params[6 + i];
        if model.misalignment {
            // m_yx (x,y), m_zx (x,z), m_zy (y,z)
            let touches = [
                [true, true, false],
                [true, false, true],
                [false, true, true],
            ];
            for (j, t) in touches.iter().enumerate() {
                if t[i] {
                    params[at + j] = -params[at + j];
                }
            }
        }
        let lv = at + if model.misalignment { 3 } else { 0 };
        match model.lever {
            LeverArm::None => {}
            LeverArm::Along => params[lv + i] = -params[lv + i],
            LeverArm::Full => {
                for c in 0..3 {
                    params[lv + 3 * i + c] = -params[lv + 3 * i + c];
                }
            }
        }
    }
    folded
}

/// Covariance, singular values and condition number of a fit.
struct Uncertainty {
    covariance: Vec<f64>,
    singular_values: Vec<f64>,
    condition: f64,
    /// RMS of the weighted residuals of the rows used.
    rms: f64,
}

/// Stage (covariance and observability) at the final parameters on the rows used: from the
/// solver's last normal equations when they were evaluated exactly there, else afresh. Scaled
/// by the residual variance unless the noise was given.
fn uncertainty(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    rows: &[usize],
    opt: &FitOptions,
    params: &[f64],
    last: Option<&LastNormal>,
) -> Result<Uncertainty> {
    let p = params.len();
    let prob = Problem::new(data, rc, rows, opt.model);
    let scales = &prob.scales[..p];
    let q: Vec<f64> = params.iter().zip(scales).map(|(a, s)| a / s).collect();
    let (jtj, cost) = match last {
        Some(ln) if ln.p == params => (DMatrix::from_row_slice(p, p, &ln.jtj), ln.cost),
        _ => {
            let mut jtj = DMatrix::<f64>::zeros(p, p);
            let mut jtr = DVector::<f64>::zeros(p);
            let cost = prob.normal(&q, &mut jtj, &mut jtr)?;
            (jtj, cost)
        }
    };
    let rms = (cost / rows.len() as f64).sqrt();
    // Column norms of the Jacobian (its columns are normalised for conditioning / null
    // directions).
    let mut cn = vec![0.0; p];
    for j in 0..p {
        cn[j] = jtj[(j, j)].sqrt();
        if !(cn[j] > 0.0) {
            let names = opt.model.names();
            return degenerate(format!(
                "parameter {} has no effect on any row: the design cannot determine it",
                names[j]
            ));
        }
    }
    let (singular_values, condition, cov_n) = match observability_normal(&jtj, &cn) {
        Some(v) => v,
        None => observability_svd(&prob, &q, &opt.model)?,
    };
    let dof = rows.len().saturating_sub(p).max(1) as f64;
    let var = if data.sigma.is_some() {
        1.0
    } else {
        cost / dof
    };
    // (J^T J)^-1 = diag(1/cn) Cn diag(1/cn) with Cn the inverse of the normalised normal matrix.
    let mut covariance = vec![0.0; p * p];
    for a in 0..p {
        for b in 0..p {
            covariance[a * p + b] = cov_n[(a, b)] / (cn[a] * cn[b]) * scales[a] * scales[b] * var;
        }
    }
    Ok(Uncertainty {
        covariance,
        singular_values,
        condition,
        rms,
    })
}

/// Check the settings of [`fit`].
fn check_options(opt: &FitOptions) -> Result<()> {
    if !(opt.outlier_k > 0.0 && opt.outlier_k.is_finite()) {
        return invalid(format!(
            "outlier_k must be a positive, finite number of standard deviations; got {}",
            opt.outlier_k
        ));
    }
    if !(opt.sigma_floor >= 0.0 && opt.sigma_floor.is_finite()) {
        return invalid(format!(
            "sigma_floor must be finite and >= 0 (g); got {}",
            opt.sigma_floor
        ));
    }
    if opt.robust && opt.max_draws == 0 {
        return invalid("max_draws must be at least 1 when the robust screen is on");
    }
    Ok(())
}

// ------------------------------------------------------------------------------------------
// Units.

/// Scale factors (output g per input g) an accelerometer triad reporting in g can have.
pub const SCALE_PLAUSIBLE: (f64, f64) = (0.2, 5.0);
/// Scale factors close enough to 1 that a unit conversion bringing them there explains them.
const SCALE_EXPLAINED: (f64, f64) = (0.5, 2.0);

/// Scale factor the outputs need to meet `|f|^2 = A^2 + 1` at the fastest speed: the median
/// over its rows of `|N| / sqrt(A^2 + 1)`, with `A` multiplied by `a_factor` and the outputs
/// by `n_factor` (the bias is small next to `A` there).
fn implied_scale(data: &CentrifugeData<'_>, a_factor: f64, n_factor: f64) -> f64 {
    let wmax = data.omega.iter().fold(0.0f64, |m, w| m.max(w.abs()));
    let ratios: Vec<f64> = data
        .outputs
        .iter()
        .zip(data.omega)
        .filter(|(_, w)| (w.abs() - wmax).abs() <= 1e-9 * wmax)
        .map(|(n, w)| {
            let a = a_factor * w * w * data.radius / data.g;
            let nn = n_factor * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            nn / (a * a + 1.0).sqrt()
        })
        .collect();
    if ratios.is_empty() {
        return f64::NAN;
    }
    kth_smallest(&ratios, ratios.len() / 2)
}

/// A unit mistake the unit check can name.
struct UnitCandidate {
    /// Which input.
    what: &'static str,
    /// The unit it looks like.
    unit: &'static str,
    /// The unit it should be in.
    want: &'static str,
    /// Factor on `A` after conversion.
    a_factor: f64,
    /// Factor on the outputs after conversion (1 unless the outputs are meant).
    n_factor: f64,
    /// The conversion, in words.
    fix: &'static str,
}

fn unit_candidates(g: f64) -> [UnitCandidate; 6] {
    use std::f64::consts::PI;
    let c = |what, unit, want, a_factor, n_factor, fix| UnitCandidate {
        what,
        unit,
        want,
        a_factor,
        n_factor,
        fix,
    };
    [
        c(
            "omega",
            "rev/min (rpm)",
            "rad/s",
            (2.0 * PI / 60.0).powi(2),
            1.0,
            "omega * 2 pi / 60",
        ),
        c(
            "omega",
            "deg/s",
            "rad/s",
            (PI / 180.0).powi(2),
            1.0,
            "omega * pi / 180",
        ),
        c(
            "omega",
            "rev/s (Hz)",
            "rad/s",
            (2.0 * PI).powi(2),
            1.0,
            "omega * 2 pi",
        ),
        c("radius", "mm", "m", 1e-3, 1.0, "radius / 1000"),
        c("radius", "cm", "m", 1e-2, 1.0, "radius / 100"),
        c("outputs", "m/s^2", "g", 1.0, 1.0 / g, "outputs / g"),
    ]
}

/// A unit mistake that explains a session's implausible scale factors.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitFinding {
    /// Which input: `"omega"`, `"radius"` or `"outputs"`.
    pub what: &'static str,
    /// The unit it looks like.
    pub unit: &'static str,
    /// The unit it should be in.
    pub want: &'static str,
    /// The conversion, as an expression.
    pub fix: &'static str,
    /// Scale factor the constraint needs after the conversion (output g per input g).
    pub scale: f64,
    /// RMS of the weighted residuals of the fit after the conversion (`inf` if it fails).
    pub rms: f64,
}

/// What the unit check found: the scale factor the session needs as given, and the
/// conversions that explain it, best first.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitSuspect {
    /// Scale factor `|N| / sqrt(A^2 + 1)` at the fastest speed, as given.
    pub scale: f64,
    /// Conversions bringing it near 1, best fit first (may be empty).
    pub findings: Vec<UnitFinding>,
}

/// Stage (units): a session whose norm constraint `|f|^2 = A^2 + 1` can only be met with scale
/// factors no triad reporting in g has ([`SCALE_PLAUSIBLE`]) is suspect. Every conversion that
/// brings the implied scale factors near 1 (omega in rpm, deg/s or Hz; radius in mm or cm;
/// outputs in m/s^2) is fitted, and the findings are sorted by how well the converted session
/// meets the constraint. `None` when the units look right.
pub fn check_units(data: &CentrifugeData<'_>, opt: &FitOptions) -> Option<UnitSuspect> {
    let s0 = implied_scale(data, 1.0, 1.0);
    if !s0.is_finite() || (s0 >= SCALE_PLAUSIBLE.0 && s0 <= SCALE_PLAUSIBLE.1) {
        return None;
    }
    let given = FitOptions {
        check_units: false,
        ..*opt
    };
    let mut findings = Vec::new();
    for c in unit_candidates(data.g) {
        let s = implied_scale(data, c.a_factor, c.n_factor);
        if !(s >= SCALE_EXPLAINED.0 && s <= SCALE_EXPLAINED.1) {
            continue;
        }
        let (om, out, radius): (Vec<f64>, Vec<[f64; 3]>, f64) = match c.what {
            "omega" => (
                data.omega.iter().map(|w| w * c.a_factor.sqrt()).collect(),
                data.outputs.to_vec(),
                data.radius,
            ),
            "radius" => (
                data.omega.to_vec(),
                data.outputs.to_vec(),
                data.radius * c.a_factor,
            ),
            _ => (
                data.omega.to_vec(),
                data.outputs
                    .iter()
                    .map(|n| n.map(|v| v * c.n_factor))
                    .collect(),
                data.radius,
            ),
        };
        let d = CentrifugeData {
            outputs: &out,
            omega: &om,
            radius,
            sigma: None,
            ..*data
        };
        let rms = fit_staged(&d, &given)
            .map(|f| f.residual_rms)
            .unwrap_or(f64::INFINITY);
        findings.push(UnitFinding {
            what: c.what,
            unit: c.unit,
            want: c.want,
            fix: c.fix,
            scale: s,
            rms,
        });
    }
    findings.sort_by(|a, b| a.rms.total_cmp(&b.rms));
    Some(UnitSuspect {
        scale: s0,
        findings,
    })
}

/// Calibrate from one session (see the stages above).
pub fn fit(data: &CentrifugeData<'_>, opt: &FitOptions) -> Result<CentrifugeFit> {
    validate(data, &opt.model)?;
    check_options(opt)?;
    if opt.check_units {
        check_gravity(data.g)?;
        if let Some(u) = check_units(data, opt) {
            let likely = match u.findings.first() {
                Some(f) => format!(
                    "; {} looks like {} (want {}: {})",
                    f.what, f.unit, f.want, f.fix
                ),
                None => String::new(),
            };
            return invalid(format!(
                "implausible units: the outputs would need scale factors of {:.3e} (output g per \
                 input g; a triad reporting in g has {}..{}) to meet |f|^2 = A^2 + 1{likely}",
                u.scale, SCALE_PLAUSIBLE.0, SCALE_PLAUSIBLE.1
            ));
        }
    }
    fit_staged(data, opt)
}

/// [`fit`] after the checks: start, plain fit, screen, sign folding, covariance.
fn fit_staged(data: &CentrifugeData<'_>, opt: &FitOptions) -> Result<CentrifugeFit> {
    let n = data.outputs.len();
    let all: Vec<usize> = (0..n).collect();
    let mut rc = row_consts(data);
    let start = start_values(data, &mut rc, &all, &opt.model);
    let plain = match (&start, opt.method) {
        (None, Method::Nls) => degenerate(
            "the outputs cannot determine scale and bias: some axis takes too few distinct \
             values or the outputs do not describe an ellipsoid",
        ),
        _ => fit_rows(data, &mut rc, &all, opt, start.as_deref()),
    };
    let plain = if opt.method == Method::Nls {
        robust_restart(data, &mut rc, &all, opt, plain)
    } else {
        plain
    };
    let sc = screen(data, &mut rc, opt, plain)?;
    let mut params = sc.out.params.clone();
    if !params.iter().all(|v| v.is_finite()) {
        return Err(CoreError::NotConverged(
            "the centrifuge fit did not produce finite parameters".into(),
        ));
    }
    let folded = fold_sign(&mut params, &opt.model);
    let residuals = if folded {
        residuals_pre(data, &rc, &opt.model, &params)
    } else {
        sc.st.r.clone()
    };
    let last = sc.out.last.as_ref().filter(|_| !folded);
    let u = uncertainty(data, &rc, &sc.rows, opt, &params, last)?;
    let mut used = vec![false; n];
    for &k in &sc.rows {
        used[k] = true;
    }
    let residual_std = rc
        .iter()
        .map(|c| {
            if data.sigma.is_some() {
                1.0 / c.w
            } else {
                sc.st.scale
            }
        })
        .collect();
    Ok(CentrifugeFit {
        params,
        names: opt.model.names(),
        covariance: u.covariance,
        residuals,
        outliers: (0..n).filter(|&k| !used[k]).collect(),
        residual_rms: u.rms,
        screen_sigma: sc.st.scale,
        studentized: sc.st.t,
        threshold: sc.threshold,
        residual_std,
        draws: sc.draws,
        screen_kept_all: sc.kept_all,
        condition: u.condition,
        singular_values: u.singular_values,
        iterations: sc.out.iterations,
        converged: sc.out.converged,
        taylor_coefficients: sc.out.taylor,
    })
}

/// RMS of the norm residuals relative to the norm (`r / sqrt(A^2 + 1)`) over `rows` at `p`;
/// infinite when a row cannot be inverted.
fn relative_rms(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    model: &ModelOptions,
    p: &[f64],
    rows: &[usize],
) -> f64 {
    let r = residuals_pre(data, rc, model, p);
    let ss: f64 = rows.iter().map(|&k| (r[k] * rc[k].inv_st).powi(2)).sum();
    (ss / rows.len().max(1) as f64).sqrt()
}

/// Stage (plain fit, second start): the plain fit on `rows` from the linear start can stall in
/// a wrong minimum (a session with rows at rest and one speed, noise given: by 18 g, whitened
/// rms 2.6e5, sometimes "converged"). When it failed, did not converge or leaves more than
/// [`PROBE_MIN_RELATIVE`] of the norm, it is refitted from the screen's least-median start and
/// the fit with the smaller relative residual kept (with its noise weights in `rc`).
fn robust_restart(
    data: &CentrifugeData<'_>,
    rc: &mut [RowConst],
    rows: &[usize],
    opt: &FitOptions,
    plain: Result<Outcome>,
) -> Result<Outcome> {
    let model = &opt.model;
    let misfit = match &plain {
        Ok(o) if o.converged => relative_rms(data, rc, model, &o.params, rows),
        _ => f64::INFINITY,
    };
    if misfit <= PROBE_MIN_RELATIVE {
        return plain;
    }
    let Ok((base, _)) = lmeds(data, rc, opt) else {
        return plain;
    };
    let mut start = vec![0.0; model.n_params()];
    start[..base.len()].copy_from_slice(&base);
    let mut rc2 = rc.to_vec();
    noise_weights(data, &mut rc2, model, &start);
    let Ok(second) = fit_rows(data, &mut rc2, rows, opt, Some(&start)) else {
        return plain;
    };
    let m2 = relative_rms(data, &rc2, model, &second.params, rows);
    let better = match &plain {
        Ok(o) => {
            let m1 = relative_rms(data, rc, model, &o.params, rows);
            (second.converged && !o.converged) || (second.converged == o.converged && m2 < m1)
        }
        Err(_) => true,
    };
    if better {
        rc.copy_from_slice(&rc2);
        Ok(second)
    } else {
        plain
    }
}

/// Column-normalised condition above which [`observability_normal`] defers to the SVD of
/// the Jacobian (the normal matrix squares the condition number).
const NORMAL_MAX_COND: f64 = 1e4;

/// Singular values (descending), condition number and `Cn = (Jn^T Jn)^-1` of the
/// column-normalised Jacobian `Jn = J diag(1/cn)`, from the normal matrix `jtj = J^T J`:
/// eigenvalues of `Jn^T Jn` (no eigenvectors) and a Cholesky inverse. `None` when the
/// condition number exceeds [`NORMAL_MAX_COND`] (or the factorisation fails): then the
/// eigenvalues lose accuracy and a null direction must be named, so use [`observability_svd`].
fn observability_normal(jtj: &DMatrix<f64>, cn: &[f64]) -> Option<(Vec<f64>, f64, DMatrix<f64>)> {
    let p = cn.len();
    let mut an = vec![0.0; p * p];
    for a in 0..p {
        for b in 0..p {
            an[a * p + b] = jtj[(a, b)] / (cn[a] * cn[b]);
        }
    }
    let ev = symmetric_eigenvalues_small(&an, p)?;
    let s: Vec<f64> = ev.iter().rev().map(|l| l.max(0.0).sqrt()).collect();
    let (smax, smin) = (s[0], s[p - 1]);
    if !(smin > smax / NORMAL_MAX_COND) || !smax.is_finite() {
        return None;
    }
    if !cholesky_small(&mut an, p) {
        return None;
    }
    let c = cholesky_inverse_small(&an, p);
    if !c.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some((s, smax / smin, DMatrix::from_row_slice(p, p, &c)))
}

/// [`observability_normal`] by the SVD of the column-normalised Jacobian itself: accurate
/// for any conditioning; names the unobservable combinations of a singular design.
fn observability_svd(
    prob: &Problem<'_>,
    q: &[f64],
    model: &ModelOptions,
) -> Result<(Vec<f64>, f64, DMatrix<f64>)> {
    let p = prob.np;
    let m = prob.rows.len();
    let mut rr = vec![0.0; m];
    let mut jac = DMatrix::<f64>::zeros(m, p);
    prob.eval(q, &mut rr, &mut jac)?;
    let cn: Vec<f64> = (0..p).map(|j| jac.column(j).norm()).collect();
    let jn = DMatrix::<f64>::from_fn(m, p, |a, b| jac[(a, b)] / cn[b]);
    let svd_n = svd_report_qr(&jn)?;
    let null = svd_n.null_directions(1e-9);
    if !null.is_empty() {
        let names = model.names();
        let combos: Vec<String> = null
            .iter()
            .map(|&c| {
                let v = svd_n.v.column(c);
                let mut terms: Vec<(f64, usize)> = (0..p).map(|j| (v[j], j)).collect();
                terms.sort_by(|a, b| b.0.abs().total_cmp(&a.0.abs()));
                terms
                    .iter()
                    .filter(|(x, _)| x.abs() > 0.1)
                    .map(|(x, j)| format!("{x:+.2}*{}", names[*j]))
                    .collect::<Vec<_>>()
                    .join(" ")
            })
            .collect();
        return degenerate(format!(
            "the design cannot determine {} parameter combination(s): {}",
            combos.len(),
            combos.join("; ")
        ));
    }
    let cov_n = svd_n
        .covariance()
        .ok_or_else(|| CoreError::Degenerate("singular normal matrix".into()))?;
    let condition = svd_n.condition();
    Ok((svd_n.s, condition, cov_n))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::TAU;

    /// The paper's 20-position design: (radial-inward, up) unit vectors in the body frame.
    fn design() -> Vec<([f64; 3], [f64; 3])> {
        let mut v = Vec::new();
        for ai in 0..5 {
            let al = (45.0 * ai as f64).to_radians();
            for ti in 0..4 {
                let th = (180.0 - 60.0 * ti as f64).to_radians();
                let c1 = [al.cos() * th.cos(), -al.sin(), -al.cos() * th.sin()];
                let c3 = [th.sin(), 0.0, th.cos()];
                v.push((c1, c3));
            }
        }
        v
    }

    const S: [f64; 3] = [1.29, 1.21, 1.26];
    const B: [f64; 3] = [0.213, 0.256, 0.516];
    const D: [f64; 3] = [0.57e-4, 0.31e-4, 0.45e-4];

    pub(super) fn session() -> (Vec<[f64; 3]>, Vec<f64>, Vec<[f64; 3]>) {
        let mut out = Vec::new();
        let mut om = Vec::new();
        let mut up = Vec::new();
        for s in 1..=3 {
            let w = 2.0 * std::f64::consts::PI * s as f64;
            let a = w * w / 9.8;
            for (c1, c3) in design() {
                let mut n = [0.0; 3];
                for i in 0..3 {
                    let f = a * c1[i] + c3[i];
                    n[i] = S[i] * (f + D[i] * f * f) + B[i];
                }
                out.push(n);
                om.push(w);
                up.push(c3);
            }
        }
        (out, om, up)
    }

    fn data<'a>(o: &'a [[f64; 3]], w: &'a [f64]) -> CentrifugeData<'a> {
        CentrifugeData {
            outputs: o,
            omega: w,
            radius: 1.0,
            g: 9.8,
            sigma: None,
            spin_axis: None,
        }
    }

    #[test]
    fn inversion_is_continuous_at_zero_k2() {
        let (f, _) = inv_axis(3.0, 0.0, 0.0).unwrap();
        assert_eq!(f, 3.0);
        let (f, _) = inv_axis(3.0, 1e-12, 0.0).unwrap();
        assert!((f - 3.0).abs() < 1e-10);
        let (f, _) = inv_axis(40.0, 5e-5, 1e-7).unwrap();
        assert!((f + 5e-5 * f * f + 1e-7 * f * f * f - 40.0).abs() < 1e-12);
        assert!(inv_axis(-1e5, 1e-4, 0.0).is_none());
    }

    #[test]
    fn nls_recovers_truth_on_exact_data() {
        let (o, w, _) = session();
        let f = fit(&data(&o, &w), &FitOptions::default()).unwrap();
        for i in 0..3 {
            assert!((f.params[i] - S[i]).abs() < 1e-9 * S[i]);
            assert!((f.params[3 + i] - B[i]).abs() < 1e-9);
            assert!((f.params[6 + i] - D[i]).abs() < 1e-7 * D[i]);
        }
        assert!(f.outliers.is_empty());
    }

    #[test]
    fn taylor_closed_form_is_close() {
        let (o, w, _) = session();
        let opt = FitOptions {
            method: Method::TaylorPaper,
            ..FitOptions::default()
        };
        let f = fit(&data(&o, &w), &opt).unwrap();
        for i in 0..3 {
            assert!((f.params[i] - S[i]).abs() < 1e-5 * S[i]);
            assert!((f.params[6 + i] - D[i]).abs() < 0.02 * D[i]);
        }
    }

    /// Coefficients of the truncated series itself (`f^2 = z^2 - 2 D z^3 + 5 D^2 z^4`, `z = (N
    /// - b) / S`) are inverted exactly; on exact simulated data the K2 error is the truncation
    /// of the `z^5` term alone (3.5e-5, -1.4e-5, 1.8e-5 relative), under the 1.1e-4, 4.0e-5,
    /// 1.7e-4 of the SPEC's errata formulas (coefficient 1 on `D^2 z^4` in C1..C3).
    #[test]
    fn taylor_recovery_is_consistent_with_the_series() {
        let mut c = vec![0.0; 13];
        for i in 0..3 {
            let (s, b, d) = (S[i], B[i] * 40.0, D[i] * 30.0); // K = D b / S ~ 1e-2
            let k = d * b / s;
            c[1 + i] = -2.0 * b * (1.0 + 3.0 * k + 10.0 * k * k) / (s * s);
            c[4 + i] = (1.0 + 6.0 * k + 30.0 * k * k) / (s * s);
            c[7 + i] = -2.0 * d * (1.0 + 10.0 * k) / (s * s * s);
            c[10 + i] = 5.0 * d * d / (s * s * s * s);
        }
        let r = taylor_recover(&c).unwrap();
        for i in 0..3 {
            assert!((r[0][i] - S[i]).abs() < 1e-13 * S[i]);
            assert!((r[1][i] - B[i] * 40.0).abs() < 1e-12 * B[i] * 40.0);
            assert!((r[2][i] - D[i] * 30.0).abs() < 1e-12 * D[i] * 30.0);
        }
        assert_eq!(taylor_k(0.0), Some(0.0));
        assert_eq!(taylor_k(f64::NAN), None);
        let (o, w, _) = session();
        let opt = FitOptions {
            method: Method::TaylorPaper,
            ..FitOptions::default()
        };
        let f = fit(&data(&o, &w), &opt).unwrap();
        let c = f.taylor_coefficients.unwrap();
        let spec_error = [1.1e-4, 4.0e-5, 1.65e-4];
        for i in 0..3 {
            let rel = (f.params[6 + i] - D[i]) / D[i];
            assert!(rel.abs() < 4e-5, "axis {i}: K2 relative error {rel:.2e}");
            // The SPEC's errata formulas, for comparison.
            let (c1, c2, c3, c4) = (c[1 + i], c[4 + i], c[7 + i], c[10 + i]);
            let m = c4 / c3 * c1 / c2;
            let a = 6.0 * m - 5.0;
            let k = 2.0 * m / (-a + (a * a - 4.0 * a * m).sqrt());
            let s = ((1.0 + 6.0 * k + 6.0 * k * k) / c2).sqrt();
            let d = -c3 * s * s * s / (2.0 * (1.0 + 2.0 * k));
            let rel_spec = (d - D[i]) / D[i];
            assert!((rel_spec - spec_error[i]).abs() < 0.1 * spec_error[i]);
            assert!(rel.abs() < 0.4 * rel_spec.abs());
        }
    }

    #[test]
    fn screening_finds_sign_errors() {
        let (mut o, w, _) = session();
        for &k in &[0usize, 4, 25, 47] {
            o[k][2] = -o[k][2];
        }
        o[10][0] = -o[10][0];
        let f = fit(&data(&o, &w), &FitOptions::default()).unwrap();
        assert_eq!(f.outliers, vec![0, 4, 10, 25, 47]);
        assert!((f.params[6] - D[0]).abs() < 1e-6 * D[0]);
    }

    #[test]
    fn lever_arm_along_is_recovered() {
        let (_, w, up) = session();
        let dsn = design();
        let lever = [0.02, -0.01, 0.015];
        let mut o = Vec::new();
        for (k, &wk) in w.iter().enumerate() {
            let (c1, c3) = dsn[k % 20];
            let a = wk * wk / 9.8;
            let mut n = [0.0; 3];
            for i in 0..3 {
                let f = a * c1[i] + c3[i] - wk * wk / 9.8 * lever[i] * (1.0 - c3[i] * c3[i]);
                n[i] = S[i] * (f + D[i] * f * f) + B[i];
            }
            o.push(n);
        }
        let mut d = data(&o, &w);
        d.spin_axis = Some(&up);
        let opt = FitOptions {
            model: ModelOptions {
                lever: LeverArm::Along,
                ..ModelOptions::default()
            },
            ..FitOptions::default()
        };
        let f = fit(&d, &opt).unwrap();
        for (i, l) in lever.iter().enumerate() {
            assert!((f.params[9 + i] - l).abs() < 1e-8, "{:?}", f.params);
        }
    }

    #[test]
    fn fast_normal_equations_and_observability_match_the_jacobian_path() {
        let (mut o, w, _) = session();
        // A little noise so that the residuals are not zero.
        for (k, row) in o.iter_mut().enumerate() {
            row[k % 3] += 1e-6 * ((k * 7919 % 13) as f64 - 6.0);
        }
        let d = data(&o, &w);
        let rc = row_consts(&d);
        let rows: Vec<usize> = (0..o.len()).collect();
        let model = ModelOptions::default();
        let f = fit(&d, &FitOptions::default()).unwrap();
        let prob = Problem::new(&d, &rc, &rows, model);
        let q: Vec<f64> = f
            .params
            .iter()
            .zip(&prob.scales)
            .map(|(a, s)| a / s)
            .collect();
        // Vectorised base kernel vs the row-wise kernel vs J^T J of the stored Jacobian.
        let (mut a1, mut g1) = (DMatrix::zeros(9, 9), DVector::zeros(9));
        let c1 = prob.normal(&q, &mut a1, &mut g1).unwrap();
        let (mut a2, mut g2) = (DMatrix::zeros(9, 9), DVector::zeros(9));
        let c2 = prob.normal_n::<9>(&q, &mut a2, &mut g2).unwrap();
        let mut r = vec![0.0; rows.len()];
        let mut jac = DMatrix::zeros(rows.len(), 9);
        prob.eval(&q, &mut r, &mut jac).unwrap();
        let a3 = jac.transpose() * &jac;
        let c3: f64 = r.iter().map(|v| v * v).sum();
        assert!((c1 - c3).abs() <= 1e-10 * c3 && (c2 - c3).abs() <= 1e-10 * c3);
        assert!((&a1 - &a3).amax() <= 1e-12 * a3.amax());
        assert!((&a2 - &a3).amax() <= 1e-12 * a3.amax());
        // J^T r is ~0 at the optimum: compare on the scale of |J| |r|.
        let jr = (c3 * a3.amax()).sqrt();
        assert!((&g1 - &g2).amax() <= 1e-10 * jr);
        let g3 = jac.transpose() * DVector::from_column_slice(&r);
        assert!((&g1 - &g3).amax() <= 1e-10 * jr);
        // Eigenvalues of the normal matrix vs the SVD of the Jacobian.
        let cn: Vec<f64> = (0..9).map(|j| a1[(j, j)].sqrt()).collect();
        let (s1, k1, c1) = observability_normal(&a1, &cn).unwrap();
        let (s2, k2, c2) = observability_svd(&prob, &q, &model).unwrap();
        for (x, y) in s1.iter().zip(&s2) {
            assert!((x - y).abs() <= 1e-10 * s2[0]);
        }
        assert!((k1 - k2).abs() <= 1e-8 * k2);
        assert!((&c1 - &c2).amax() <= 1e-9 * c2.amax());
        assert_eq!(f.singular_values.len(), 9);
        // Residuals reused from the solver equal the row-wise evaluation.
        let r_pub = residuals(&d, &model, &f.params).unwrap();
        for (x, y) in f.residuals.iter().zip(&r_pub) {
            assert!((x - y).abs() <= 1e-15, "{x} {y}");
        }
        assert!((f.condition - k2).abs() <= 1e-8 * k2);
    }

    /// A session with small deterministic pseudo-noise on every output (g).
    fn noisy(level: f64) -> (Vec<[f64; 3]>, Vec<f64>) {
        let (mut o, w, _) = session();
        let mut rng = Rng(7);
        for row in o.iter_mut() {
            for v in row.iter_mut() {
                // Sum of uniforms: roughly normal, std `level`.
                let u: f64 = (0..12)
                    .map(|_| (rng.next() >> 11) as f64 / (1u64 << 53) as f64)
                    .sum();
                *v += level * (u - 6.0);
            }
        }
        (o, w)
    }

    #[test]
    fn stage_start_is_close_and_noise_weights_match_numeric_propagation() {
        let (o, w) = noisy(1e-6);
        let sig = vec![[1e-6, 2e-6, 3e-6]; o.len()];
        let mut d = data(&o, &w);
        d.sigma = Some(&sig);
        let model = ModelOptions::default();
        let all: Vec<usize> = (0..o.len()).collect();
        let mut rc = row_consts(&d);
        let st = start_values(&d, &mut rc, &all, &model).unwrap();
        for i in 0..3 {
            assert!((st[i] - S[i]).abs() < 1e-3 * S[i], "{st:?}");
        }
        // 1 / w = |sigma * dr/dN| by central differences on the outputs.
        let p: Vec<f64> = [S, B, D].concat();
        noise_weights(&d, &mut rc, &model, &p);
        let pp = param_pre(&model, &p).unwrap();
        for k in [0usize, 17, 45] {
            let mut v = 0.0;
            for j in 0..3 {
                let h = 1e-6;
                let (mut up, mut dn) = (o[k], o[k]);
                up[j] += h;
                dn[j] -= h;
                let ru = row_eval(&up, &rc[k], &pp, &model, None).unwrap();
                let rd = row_eval(&dn, &rc[k], &pp, &model, None).unwrap();
                v += (sig[k][j] * (ru - rd) / (2.0 * h)).powi(2);
            }
            assert!((1.0 / rc[k].w - v.sqrt()).abs() < 1e-6 * v.sqrt());
        }
    }

    #[test]
    fn residual_std_is_the_inverse_noise_weight() {
        let (o, w) = noisy(1e-6);
        let sig = vec![[2e-6; 3]; o.len()];
        let mut d = data(&o, &w);
        assert!(residual_std(&d, &ModelOptions::default(), &[S, B, D].concat()).is_err());
        d.sigma = Some(&sig);
        let p: Vec<f64> = [S, B, D].concat();
        let sd = residual_std(&d, &ModelOptions::default(), &p).unwrap();
        let mut rc = row_consts(&d);
        noise_weights(&d, &mut rc, &ModelOptions::default(), &p);
        for (s, c) in sd.iter().zip(&rc) {
            assert_eq!(*s, 1.0 / c.w);
            // |dr/dN| = |f / S| / sqrt(T) ~ 1/S for these scale factors.
            assert!(*s > 2e-6 / 1.3 * 0.9 && *s < 2e-6 / 1.2 * 1.1, "{s}");
        }
    }

    #[test]
    fn stage_threshold_is_the_student_quantile_of_the_normal_tail() {
        // scipy: t.isf(norm.sf(2), 10) and t.isf(norm.sf(5), 50).
        assert!((t_threshold(2.0, 10, false) - 2.28367820247793).abs() < 1e-9);
        assert!((t_threshold(5.0, 50, false) - 5.730061794672849).abs() < 1e-8);
        assert_eq!(t_threshold(5.0, 50, true), 5.0);
    }

    #[test]
    fn stage_studentize_matches_a_leave_one_out_refit() {
        let (mut o, w) = noisy(1e-5);
        o[7][2] += 3e-5; // make row 7 stand out a little
        let d = data(&o, &w);
        let opt = FitOptions::default();
        let all: Vec<usize> = (0..o.len()).collect();
        let mut rc = row_consts(&d);
        let out = fit_rows(&d, &mut rc, &all, &opt, None).unwrap();
        let st = studentize(&d, &rc, &opt, &out.params, &all);
        assert_eq!(st.dof, 51);
        // Without row 7: its prediction residual over its prediction std.
        let rest: Vec<usize> = all.iter().copied().filter(|&k| k != 7).collect();
        let o2 = fit_rows(&d, &mut rc, &rest, &opt, Some(&out.params)).unwrap();
        let st2 = studentize(&d, &rc, &opt, &o2.params, &rest);
        assert!(st.t[7].abs() > 0.1);
        assert!(
            (st.t[7] - st2.t[7]).abs() < 1e-3 * st.t[7].abs(),
            "{} {}",
            st.t[7],
            st2.t[7]
        );
    }

    #[test]
    fn stage_screen_sees_gross_errors_that_mask_each_other() {
        // Lost x signs in 4 to 8 rows, noise 1e-6 g estimated. In the plain fit they can
        // inflate the residual scale until no studentised residual crosses the threshold
        // (masking); the screen must find them all the same, in every selection tried.
        let (o0, w) = noisy(1e-6);
        let cand: Vec<usize> = (0..o0.len()).filter(|&k| o0[k][0].abs() > 0.5).collect();
        let opt = FitOptions::default();
        let all: Vec<usize> = (0..o0.len()).collect();
        let mut rng = Rng(11);
        let mut masking = 0;
        for trial in 0..28 {
            let q = 4 + trial % 7;
            let mut flipped: Vec<usize> = Vec::new();
            while flipped.len() < q {
                let k = cand[rng.below(cand.len())];
                if !flipped.contains(&k) {
                    flipped.push(k);
                }
            }
            flipped.sort_unstable();
            let mut o = o0.clone();
            for &k in &flipped {
                o[k][0] = -o[k][0];
            }
            let d = data(&o, &w);
            let mut rc = row_consts(&d);
            if let Ok(plain) = fit_rows(&d, &mut rc, &all, &opt, None) {
                let st = studentize(&d, &rc, &opt, &plain.params, &all);
                let thr = t_threshold(opt.outlier_k, st.dof - 1, false);
                if st.t.iter().all(|t| t.abs() <= thr) {
                    masking += 1;
                    assert!(
                        masked(&st, thr, 9, opt.sigma_floor) || probe_masked(&d, &rc, &opt, &st.r),
                        "trial {trial}"
                    );
                }
            }
            let f = fit(&d, &opt).unwrap();
            assert_eq!(f.outliers, flipped, "trial {trial}");
            assert!(
                (f.params[3] - B[0]).abs() < 1e-5,
                "trial {trial}: {}",
                f.params[3]
            );
        }
        assert!(
            masking >= 3,
            "only {masking} masking cases among the trials"
        );
        // Clean rows: nothing masked.
        let d0 = data(&o0, &w);
        let mut rc0 = row_consts(&d0);
        let p0 = fit_rows(&d0, &mut rc0, &all, &opt, None).unwrap();
        let st0 = studentize(&d0, &rc0, &opt, &p0.params, &all);
        let thr = t_threshold(opt.outlier_k, st0.dof - 1, false);
        assert!(!masked(&st0, thr, 9, opt.sigma_floor));
        assert!(!probe_masked(&d0, &rc0, &opt, &st0.r));
    }

    #[test]
    fn stage_screen_keeps_a_clean_session_whole() {
        let (o, w) = noisy(1e-5);
        let f = fit(&data(&o, &w), &FitOptions::default()).unwrap();
        assert!(f.outliers.is_empty() && f.draws == 0);
        assert!(f.studentized.iter().all(|t| t.abs() <= f.threshold));
        assert!((f.screen_sigma - 1e-5).abs() < 0.3e-5, "{}", f.screen_sigma);
    }

    #[test]
    fn stage_verdict_tells_a_spread_misfit_from_sparse_outliers() {
        let n = 60;
        let tail = chi2_sf(25.0, 1.0);
        let plain = vec![1e-5; n];
        // Sparse gross errors: the plain fit sees them (ratio ~1): the exclusion stands.
        let mut gross = vec![1e-6; n];
        for k in [3, 17, 40] {
            gross[k] = 1.2e-5;
        }
        let none = vec![false; n];
        let slips = vec![true; n];
        let w: Vec<f64> = (0..n).map(|k| 1.0 + k as f64).collect();
        assert!(!misfit_is_spread(
            n,
            &[3, 17, 40],
            &plain,
            &gross,
            None,
            tail,
            &none,
            &w
        ));
        // Residuals 600 times what the plain fit leaves on the same rows: made by the
        // exclusion (the kept rows barely see a parameter combination the excluded carry).
        let made: Vec<f64> = (0..n).map(|k| if k < 20 { 6e-3 } else { 1e-6 }).collect();
        let twenty: Vec<usize> = (0..20).collect();
        assert!(misfit_is_spread(
            n, &twenty, &plain, &made, None, tail, &slips, &w
        ));
        // ... even when a few of them are not amplified; rows the plain fit could not invert
        // do not count.
        let mut inf_plain = plain.clone();
        inf_plain[0] = f64::INFINITY;
        assert!(misfit_is_spread(
            n, &twenty, &inf_plain, &made, None, tail, &slips, &w
        ));
        assert!(!misfit_is_spread(
            n,
            &[0],
            &inf_plain,
            &made,
            None,
            tail,
            &none,
            &w
        ));
        // More than half the rows is never sparse.
        let most: Vec<usize> = (0..31).collect();
        assert!(misfit_is_spread(
            n, &most, &plain, &plain, None, tail, &slips, &w
        ));
        // More than a quarter with the rows kept still rejecting the noise model (chi2 104 on
        // 31 dof, p ~ 1e-9): a trimmed misfit. A quarter or less, or the kept rows consistent,
        // or the noise unknown: the exclusion stands.
        let sixteen: Vec<usize> = (0..16).collect();
        let fifteen: Vec<usize> = (0..15).collect();
        // (The rows are lost signs here, so rules 4 and 5 do not apply.)
        let spread = |q: &[usize], chi2: Option<(f64, usize)>| {
            misfit_is_spread(n, q, &plain, &plain, chi2, tail, &slips, &w)
        };
        assert!(spread(&sixteen, Some((104.0, 31))));
        assert!(!spread(&sixteen, Some((40.0, 31))));
        assert!(!spread(&fifteen, Some((104.0, 36))));
        assert!(!spread(&sixteen, None));
        assert!(!spread(&[], Some((1e9, 51))));
        // Rows that are not lost signs: more than a quarter of them is a model error whatever
        // the noise (a radius off by 2: 20 of 60 rows); a quarter or less stands unless they
        // agree in sign and size (one systematic effect).
        let varied: Vec<f64> = (0..n).map(|k| 1e-3 * (1.0 + k as f64)).collect();
        let by = |q: &[usize], r: &[f64]| misfit_is_spread(n, q, r, r, None, tail, &none, &w);
        assert!(by(&sixteen, &varied));
        assert!(!by(&fifteen, &varied));
        assert!(!by(&[3, 17, 40], &plain));
        let eight: Vec<usize> = (0..8).collect();
        assert!(by(&eight, &plain));
        let mut mixed = plain.clone();
        mixed[2] = -1e-5;
        assert!(!by(&eight, &mixed));
        // Six or more at one speed: an effect growing with the speed.
        let mut speed = w.clone();
        speed[..6].fill(3.0);
        let six: Vec<usize> = (0..6).collect();
        assert!(misfit_is_spread(
            n, &six, &mixed, &mixed, None, tail, &none, &speed
        ));
        assert!(!misfit_is_spread(
            n, &six, &mixed, &mixed, None, tail, &none, &w
        ));
        assert!(!misfit_is_spread(
            n, &six, &mixed, &mixed, None, tail, &slips, &speed
        ));
    }

    #[test]
    fn stage_level_check_names_an_axis_the_design_cannot_separate() {
        // Flat mount: z only ever sees +1 or -1 g, x and y the whole circle.
        let (s, b, d) = (S, B, D);
        let pi = std::f64::consts::PI;
        let mut out = vec![];
        let mut om = vec![];
        for &w in &[2.0 * pi, 4.0 * pi, 6.0 * pi] {
            let a: f64 = w * w / 9.8;
            for zs in [1.0, -1.0] {
                for j in 0..12 {
                    let t = (j as f64 * 30.0).to_radians();
                    let f = [a * t.cos(), zs * a * t.sin(), zs];
                    let mut n = [0.0; 3];
                    for i in 0..3 {
                        n[i] = s[i] * (f[i] + d[i] * f[i] * f[i]) + b[i];
                    }
                    out.push(n);
                    om.push(w);
                }
            }
        }
        match fit(&data(&out, &om), &FitOptions::default()) {
            Err(CoreError::Degenerate(m)) => {
                assert!(
                    m.contains("z axis")
                        && m.contains("k2z acts exactly as bias")
                        && m.contains("only 2 distinct"),
                    "{m}"
                )
            }
            other => panic!("{other:?}"),
        }
        // The paper's design is well posed.
        let (o, w, _) = session();
        assert!(check_axis_levels(&data(&o, &w), &ModelOptions::default()).is_ok());
    }

    #[test]
    fn stage_gravity_is_checked_in_mps2() {
        assert!(check_gravity(9.80665).is_ok() && check_gravity(9.78).is_ok());
        for (g, unit) in [
            (32.174, "ft/s^2"),
            (980.665, "cm/s^2"),
            (1.0, "g (standard"),
            (9806.65, "mm/s^2"),
        ] {
            match check_gravity(g) {
                Err(CoreError::InvalidInput(m)) => assert!(m.contains(unit), "{m}"),
                other => panic!("{g}: {other:?}"),
            }
        }
        assert!(check_gravity(5.0).is_err());
    }

    /// The paper's session on a true radius of `r_true` m (the fit is told 1 m), with
    /// roughly normal output noise of std `level` g.
    fn radius_error_session(r_true: f64, level: f64) -> (Vec<[f64; 3]>, Vec<f64>) {
        let mut rng = Rng(11);
        let mut o = Vec::new();
        let mut om = Vec::new();
        for s in 1..=3 {
            let w = 2.0 * std::f64::consts::PI * s as f64;
            let a = w * w * r_true / 9.8;
            for (c1, c3) in design() {
                let mut n = [0.0; 3];
                for i in 0..3 {
                    let f = a * c1[i] + c3[i];
                    let u: f64 = (0..12)
                        .map(|_| (rng.next() >> 11) as f64 / (1u64 << 53) as f64)
                        .sum();
                    n[i] = S[i] * (f + D[i] * f * f) + B[i] + level * (u - 6.0);
                }
                o.push(n);
                om.push(w);
            }
        }
        (o, om)
    }

    #[test]
    fn stage_screen_keeps_every_row_of_a_model_error() {
        // A 0.1 mm radius error with 1e-6 g noise given: every residual is ~1e-5 g (tens of
        // sigma) and smooth in the rate. The screen used to exclude 20 good rows, leaving a
        // fit that looked perfect with b_y 170 sigma off; now the plain fit is kept and flagged.
        let (o, w) = radius_error_session(1.0001, 1e-6);
        let sig = vec![[1e-6; 3]; o.len()];
        let mut d = data(&o, &w);
        d.sigma = Some(&sig);
        let f = fit(&d, &FitOptions::default()).unwrap();
        assert!(f.outliers.is_empty(), "{:?}", f.outliers);
        assert!(f.screen_kept_all && f.draws > 0);
        assert!(f.residual_rms > 5.0, "{}", f.residual_rms);
        assert!(f.studentized.iter().any(|t| t.abs() > f.threshold));
        let plain = fit(
            &d,
            &FitOptions {
                robust: false,
                ..FitOptions::default()
            },
        )
        .unwrap();
        assert_eq!(f.params, plain.params);
        assert!(!plain.screen_kept_all && plain.draws == 0);
        // b_y: within the model error of the plain fit (~5e-5 g), not 0.017 g off.
        assert!((f.params[4] - B[1]).abs() < 2e-4, "{}", f.params[4]);
        // Sparse gross errors on the same session are still excluded, and only they.
        let (mut o2, _) = radius_error_session(1.0, 1e-6);
        for &k in &[0usize, 4, 25, 47] {
            o2[k][2] = -o2[k][2];
        }
        let mut d2 = data(&o2, &w);
        d2.sigma = Some(&sig);
        let f2 = fit(&d2, &FitOptions::default()).unwrap();
        assert_eq!(f2.outliers, vec![0, 4, 25, 47]);
        assert!(!f2.screen_kept_all);
    }

    #[test]
    fn stage_fold_sign_keeps_the_residuals() {
        let (_, w, up) = session();
        let model = ModelOptions {
            k3: true,
            misalignment: true,
            lever: LeverArm::Along,
        };
        let mut p = vec![
            -1.29, 1.21, -1.26, 0.2, 0.3, 0.5, 5e-5, 3e-5, 4e-5, 1e-7, -2e-7, 3e-7, 1e-3, -2e-3,
            5e-4, 0.01, -0.02, 0.005,
        ];
        let (o, _, _) = session();
        let mut d = data(&o, &w);
        d.spin_axis = Some(&up);
        let r0 = residuals(&d, &model, &p).unwrap();
        assert!(fold_sign(&mut p, &model));
        assert!(p[0] > 0.0 && p[2] > 0.0);
        let r1 = residuals(&d, &model, &p).unwrap();
        for (a, b) in r0.iter().zip(&r1) {
            assert!((a - b).abs() <= 1e-12 * (1.0 + a.abs()), "{a} {b}");
        }
        assert!(!fold_sign(&mut p, &model));
    }

    #[test]
    fn stage_units_name_the_likely_mistake() {
        let (o, w, _) = session();
        assert!(check_units(&data(&o, &w), &FitOptions::default()).is_none());
        let rpm: Vec<f64> = w.iter().map(|v| v * 60.0 / TAU).collect();
        let u = check_units(&data(&o, &rpm), &FitOptions::default()).unwrap();
        assert!((u.scale - 0.0137).abs() < 2e-3, "{u:?}");
        assert_eq!(
            (u.findings[0].what, u.findings[0].unit),
            ("omega", "rev/min (rpm)")
        );
        assert!(u.findings[0].rms < 1e-9);
        let e = fit(&data(&o, &rpm), &FitOptions::default()).unwrap_err();
        assert!(matches!(e, CoreError::InvalidInput(m) if m.contains("rev/min")));
        let mut d = data(&o, &w);
        d.radius = 100.0;
        let u = check_units(&d, &FitOptions::default()).unwrap();
        assert_eq!((u.findings[0].what, u.findings[0].unit), ("radius", "cm"));
    }

    #[test]
    fn stage_uncertainty_is_the_inverse_normal_matrix() {
        // With the noise given, the covariance is (J^T W J)^-1 of the weighted Jacobian at the
        // fit, whichever path (the solver's last normal equations or afresh) computes it.
        let (o, w) = noisy(1e-6);
        let sig = vec![[1e-6; 3]; o.len()];
        let mut d = data(&o, &w);
        d.sigma = Some(&sig);
        let opt = FitOptions::default();
        let all: Vec<usize> = (0..o.len()).collect();
        let mut rc = row_consts(&d);
        let out = fit_rows(&d, &mut rc, &all, &opt, None).unwrap();
        let u1 = uncertainty(&d, &rc, &all, &opt, &out.params, out.last.as_ref()).unwrap();
        let u2 = uncertainty(&d, &rc, &all, &opt, &out.params, None).unwrap();
        let prob = Problem::new(&d, &rc, &all, opt.model);
        let q: Vec<f64> = out
            .params
            .iter()
            .zip(&prob.scales)
            .map(|(a, s)| a / s)
            .collect();
        let mut r = vec![0.0; all.len()];
        let mut jac = DMatrix::zeros(all.len(), 9);
        prob.eval(&q, &mut r, &mut jac).unwrap();
        let cq = (jac.transpose() * &jac).try_inverse().unwrap();
        for a in 0..9 {
            for b in 0..9 {
                let want = cq[(a, b)] * prob.scales[a] * prob.scales[b];
                let tol = 1e-6
                    * (want.abs()
                        + 1e-3
                            * (cq[(a, a)] * cq[(b, b)]).sqrt()
                            * prob.scales[a]
                            * prob.scales[b]);
                assert!((u1.covariance[a * 9 + b] - want).abs() <= tol, "{a} {b}");
                assert!((u2.covariance[a * 9 + b] - want).abs() <= tol, "{a} {b}");
            }
        }
        assert!((u1.rms - u2.rms).abs() < 1e-12 && u1.condition > 1.0);
    }

    #[test]
    fn correct_inverts_the_sensor_model() {
        let (o, w, _) = session();
        let p: Vec<f64> = [S, B, D].concat();
        let f = correct(&ModelOptions::default(), &p, &o).unwrap();
        let d = data(&o, &w);
        for (k, fk) in f.iter().enumerate() {
            let n2: f64 = fk.iter().map(|v| v * v).sum();
            assert!((n2 - target(&d, k)).abs() < 1e-9 * target(&d, k));
        }
        assert!(correct(&ModelOptions::default(), &p, &[[f64::NAN; 3]]).is_err());
    }

    #[test]
    fn bad_inputs_are_reported() {
        let (o, w, _) = session();
        let zero = vec![0.0; w.len()];
        assert!(matches!(
            fit(&data(&o, &zero), &FitOptions::default()),
            Err(CoreError::Degenerate(_))
        ));
        let one: Vec<f64> = vec![w[0]; w.len()];
        assert!(matches!(
            fit(&data(&o, &one), &FitOptions::default()),
            Err(CoreError::Degenerate(_))
        ));
        let mut d = data(&o, &w);
        d.radius = -1.0;
        assert!(matches!(
            fit(&d, &FitOptions::default()),
            Err(CoreError::InvalidInput(_))
        ));
        assert!(matches!(
            fit(&data(&o, &w[..10]), &FitOptions::default()),
            Err(CoreError::InvalidInput(_))
        ));
    }
}

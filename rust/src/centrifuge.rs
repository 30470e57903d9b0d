//! Centrifuge norm-observation calibration with quadratic (K2) coefficients (SPEC section 2).
//!
//! Model per accelerometer triad, in g units:
//! `N = S Phi (h) + b`, `h_i = f_i + D_i f_i^2 [+ E_i f_i^3]`, `Phi = I + M` (small-angle,
//! lower triangular: the three rotation-like angles are invisible to a norm observation).
//! The constraint is `|f|^2 = A^2 + 1` with `A = omega^2 R / g`.
//!
//! - [`fit`] with [`Method::Nls`]: exact inversion of every row (`f_i` from `h_i` by the root
//!   continuous with `D -> 0`) and weighted least squares on the norm, via [`crate::lsq`].
//! - [`Method::TaylorPaper`]: the paper's 13-column regression of `A^2 + 1` on
//!   `[1, N, N^2, N^3, N^4]` with the corrected closed-form recovery (SPEC 2 errata).
//! - Robust screening: least median of squares over random minimal subsets (seeded, so
//!   deterministic), then iterated refit / reclassification at `k` robust sigmas.
//!
//! Sign convention: a norm observation cannot tell `S_i` from `-S_i` when `D_i = 0`; the fit
//! returns `S_i > 0` (start values are positive and the sign is folded at the end).

#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > 0.0)` deliberately rejects NaN too.

use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lsq::{
    cholesky_inverse_small, cholesky_small, lstsq_small, solve_nls, solve_normal_gn, svd_report_qr,
    symmetric_eigenvalues_small, NlsOptions, NormalEquations, Residuals,
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
    /// Optional per-row standard deviation of the norm (g).
    pub sigma: Option<&'a [f64]>,
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
    /// Outlier threshold in robust standard deviations.
    pub outlier_k: f64,
    /// Smallest residual scale (g) used for the threshold (guards exact data).
    pub sigma_floor: f64,
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
    /// Robust residual scale used for screening (g); 0 when no screening ran.
    pub screen_sigma: f64,
    /// Minimal subsets drawn by the screen (0 when the fast path was enough).
    pub draws: usize,
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
    /// Residual weight `1 / sigma` (1 without sigma).
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
                w: data.sigma.map(|s| 1.0 / s[k]).unwrap_or(1.0),
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
                "sigma has {} values but outputs have {k} rows",
                s.len()
            ));
        }
        if s.iter().any(|v| !(*v > 0.0) || !v.is_finite()) {
            return invalid("sigma must be positive and finite (g)");
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
    let nonzero = speeds.iter().filter(|w| **w > 0.0).count();
    if nonzero < 2 {
        return degenerate(format!(
            "only {nonzero} distinct non-zero speed(s): K2 cannot be separated from scale; \
             run at least two (better three) speeds"
        ));
    }
    let p = model.n_params();
    if k < p + 1 {
        return degenerate(format!(
            "{k} rows cannot determine {p} parameters with a residual check (need at least {})",
            p + 1
        ));
    }
    Ok(speeds.len())
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
    use nalgebra::{SMatrix, SVector};
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
    let mut ata = SMatrix::<f64, C, C>::zeros();
    let mut aty = SVector::<f64, C>::zeros();
    for &k in rows {
        let raw = regs(data.outputs[k]);
        let row: [f64; C] = std::array::from_fn(|j| raw[j] * ics[j]);
        let t = target(data, k);
        for a in 0..C {
            aty[a] += row[a] * t;
            for b in a..C {
                ata[(a, b)] += row[a] * row[b];
            }
        }
    }
    // Symmetric: the lower triangle is the mirror (same products, same order).
    for a in 0..C {
        for b in 0..a {
            ata[(a, b)] = ata[(b, a)];
        }
    }
    let c = ata.cholesky()?.solve(&aty);
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

/// Corrected closed-form recovery from the 13 Taylor coefficients (SPEC 2): returns
/// `(S, b, D)` per axis.
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
        let a = 6.0 * m - 5.0;
        let disc = a * a - 4.0 * a * m;
        if !(disc >= 0.0) {
            return degenerate(format!(
                "taylor-paper: axis {}: no real K (discriminant {disc:.3e})",
                axis[i]
            ));
        }
        // Eq. 19 corrected: the root with K ~ M/5 (the printed one gives K ~ -1).
        let k = 2.0 * m / (-a + disc.sqrt());
        let q = 1.0 + 6.0 * k + 6.0 * k * k;
        if !(q / c2 > 0.0) {
            return degenerate(format!(
                "taylor-paper: axis {}: negative squared scale factor",
                axis[i]
            ));
        }
        let s = (q / c2).sqrt();
        // Eq. 21 corrected: D keeps the sign of -C3.
        let d = -c3 * s * s * s / (2.0 * (1.0 + 2.0 * k));
        // Eq. 22 corrected (the printed one is inverted).
        let b = -c1 * q / (2.0 * c2 * (1.0 + k) * (1.0 + 2.0 * k));
        out[0][i] = s;
        out[1][i] = b;
        out[2][i] = d;
    }
    Ok(out)
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
    use nalgebra::{SMatrix, SVector};
    let base = ModelOptions::default();
    let st = linear_start(data, subset, &base).ok()?;
    let mut p = [0.0f64; 9];
    p.copy_from_slice(&st[..9]);
    let sc = base.scales();
    for _ in 0..20 {
        let mut jm = SMatrix::<f64, 9, 9>::zeros();
        let mut r = SVector::<f64, 9>::zeros();
        let pp = param_pre(&base, &p)?;
        let mut grad = [0.0; MAX_PARAMS];
        for (a, &k) in subset.iter().enumerate() {
            r[a] = row_eval(&data.outputs[k], &rc[k], &pp, &base, Some(&mut grad))?;
            for j in 0..9 {
                jm[(a, j)] = grad[j] * sc[j];
            }
        }
        let step = jm.lu().solve(&(-r))?;
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
    let base = ModelOptions::default();
    let n = data.outputs.len();
    let p = base.n_params();
    let h = (n + p).div_ceil(2);
    let mut rng = Rng(opt.seed ^ 0xA5A5_5A5A_C3C3_3C3C);
    let mut best: Option<(f64, Vec<f64>)> = None;
    let w = 0.5f64.powi(p as i32);
    let needed = ((1e-4f64.ln() / (1.0 - w).ln()).ceil() as usize).min(opt.max_draws);
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
        Some((_, params)) => Ok((params, draws)),
        None => degenerate(
            "robust screening found no subset of rows consistent with the model \
             (need at least two speeds and more than half of the rows good)",
        ),
    }
}

/// (parameters, iterations, converged, Taylor coefficients, last normal equations (nls)).
type FitOutcome = (Vec<f64>, usize, bool, Option<Vec<f64>>, Option<LastNormal>);

fn final_fit(
    data: &CentrifugeData<'_>,
    rc: &[RowConst],
    rows: &[usize],
    opt: &FitOptions,
    start: Option<&[f64]>,
) -> Result<FitOutcome> {
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
            Ok((p, rep.iterations, rep.converged, None, Some(last)))
        }
        Method::TaylorPaper => {
            if opt.model != ModelOptions::default() {
                return invalid(
                    "method 'taylor-paper' supports only the scale + bias + K2 model; use 'nls'",
                );
            }
            let c = taylor_coefficients(data, rows)?;
            let sbd = taylor_recover(&c)?;
            let p: Vec<f64> = sbd.iter().flatten().copied().collect();
            Ok((p, 0, true, Some(c), None))
        }
    }
}

fn fold_sign(params: &mut [f64], model: &ModelOptions) {
    let at = if model.k3 { 12 } else { 9 };
    for i in 0..3 {
        if params[i] >= 0.0 {
            continue;
        }
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
}

fn robust_scale(a: &[f64], rows: &[usize], p: usize) -> f64 {
    let med = kth_smallest(
        &rows.iter().map(|&k| a[k]).collect::<Vec<_>>(),
        rows.len() / 2,
    );
    let mad = 1.4826 * (1.0 + 5.0 / (rows.len().saturating_sub(p).max(1)) as f64) * med;
    let rms = (rows.iter().map(|&k| a[k] * a[k]).sum::<f64>()
        / (rows.len().saturating_sub(p).max(1)) as f64)
        .sqrt();
    // RMS of the kept rows, but never below the median-based scale (guards a clean fit).
    rms.max(mad)
}

/// Calibrate from one session.
pub fn fit(data: &CentrifugeData<'_>, opt: &FitOptions) -> Result<CentrifugeFit> {
    validate(data, &opt.model)?;
    if !(opt.outlier_k > 0.0) {
        return invalid("outlier threshold k must be positive");
    }
    let n = data.outputs.len();
    let p = opt.model.n_params();
    let rc = row_consts(data);
    let all: Vec<usize> = (0..n).collect();
    let mut rows = all.clone();
    let mut draws = 0;
    let mut screen_sigma = 0.0;
    let (mut params, mut iterations, mut converged, mut taylor, mut last) =
        match final_fit(data, &rc, &rows, opt, None) {
            Ok(v) => v,
            Err(e) if opt.robust => {
                // The plain fit can fail outright on gross outliers: go straight to the screen.
                let _ = e;
                (vec![f64::NAN; p], 0, false, None, None)
            }
            Err(e) => return Err(e),
        };
    // Residuals of every row at `params` when already computed (the robust pre-check).
    let mut r_known: Option<Vec<f64>> = None;
    if opt.robust {
        let r0 = if let Some(ln) = last.as_ref().filter(|l| l.p == params && l.r.len() == n) {
            // The solver's last evaluation on all rows is at `params`: same residuals.
            ln.r.clone()
        } else if params.iter().all(|v| v.is_finite()) {
            residuals_pre(data, &rc, &opt.model, &params)
        } else {
            vec![f64::INFINITY; n]
        };
        let a0 = weighted_abs(&rc, &r0);
        let sig0 = robust_scale(&a0, &all, p).max(opt.sigma_floor);
        let med0 = kth_smallest(&a0, n / 2);
        let mad0 = (1.4826 * med0).max(opt.sigma_floor);
        let clean = a0.iter().all(|v| *v <= opt.outlier_k * mad0) && sig0.is_finite();
        if clean {
            r_known = Some(r0);
        } else {
            r_known = None;
            let (base_p, d) = lmeds(data, &rc, opt)?;
            draws = d;
            let mut start = base_p;
            let mut sig = f64::INFINITY;
            let rb = residuals_pre(data, &rc, &ModelOptions::default(), &start);
            let ab = weighted_abs(&rc, &rb);
            let h = (n + 9).div_ceil(2);
            let crit = kth_smallest(&ab, h - 1);
            let sig_l = (1.4826 * (1.0 + 5.0 / (n - 9) as f64) * crit).max(opt.sigma_floor);
            rows = (0..n).filter(|&k| ab[k] <= opt.outlier_k * sig_l).collect();
            for _ in 0..5 {
                if rows.len() < p + 1 {
                    return degenerate(format!(
                        "only {} rows are consistent with the model; {} parameters need more",
                        rows.len(),
                        p
                    ));
                }
                let st = if opt.method == Method::Nls {
                    Some(&start[..])
                } else {
                    None
                };
                let (pp, it, cv, tc, ln) = final_fit(data, &rc, &rows, opt, st)?;
                let r = residuals_pre(data, &rc, &opt.model, &pp);
                let a = weighted_abs(&rc, &r);
                sig = robust_scale(&a, &rows, p).max(opt.sigma_floor);
                let new_rows: Vec<usize> =
                    (0..n).filter(|&k| a[k] <= opt.outlier_k * sig).collect();
                params = pp;
                iterations = it;
                converged = cv;
                taylor = tc;
                last = ln;
                start = params.clone();
                if new_rows == rows {
                    break;
                }
                rows = new_rows;
                // Not refitted on these rows: the stored normal equations do not apply.
                last = None;
            }
            screen_sigma = sig;
        }
    }
    if !params.iter().all(|v| v.is_finite()) {
        return Err(CoreError::NotConverged(
            "the centrifuge fit did not produce finite parameters".into(),
        ));
    }
    // Sign convention: S > 0 (a norm observation cannot fix it when D = 0). Flipping S_i
    // flips f_i, so D_i, the misalignment terms touching axis i and its lever arm flip too.
    let before = params.clone();
    fold_sign(&mut params, &opt.model);
    let folded = params != before;
    let r_all = match r_known {
        Some(r) if !folded => r,
        _ => residuals_pre(data, &rc, &opt.model, &params),
    };
    // Observability and covariance at the final parameters on the rows used (the solver's
    // last evaluation is exactly there unless the sign was folded or LM took over).
    let prob = Problem::new(data, &rc, &rows, opt.model);
    let scales = &prob.scales[..p];
    let q: Vec<f64> = params.iter().zip(scales).map(|(a, s)| a / s).collect();
    let (jtj, cost) = match last {
        Some(ln) if !folded && ln.p == params => (DMatrix::from_row_slice(p, p, &ln.jtj), ln.cost),
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
    let mut cov = vec![0.0; p * p];
    for a in 0..p {
        for b in 0..p {
            cov[a * p + b] = cov_n[(a, b)] / (cn[a] * cn[b]) * scales[a] * scales[b] * var;
        }
    }
    let outliers: Vec<usize> = (0..n).filter(|k| !rows.contains(k)).collect();
    Ok(CentrifugeFit {
        params,
        names: opt.model.names(),
        covariance: cov,
        residuals: r_all,
        outliers,
        residual_rms: rms,
        screen_sigma,
        draws,
        condition,
        singular_values,
        iterations,
        converged,
        taylor_coefficients: taylor,
    })
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

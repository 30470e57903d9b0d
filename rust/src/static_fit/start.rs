//! The start stage: the linear solutions of the norm-observation paper, a user's start, or a
//! bias + scale fallback when the 9-term quadric fails.
//!
//! The paper's regression writes the constraint `|K^-1 (am - b)| = g` as the quadric
//! `am^T Q am - 2 (Q b)^T am + b^T Q b - g^2 = 0` (`Q = K^-T K^-1`) and, dividing by `-Q33`,
//! regresses `amz^2` on `[amx^2, amy^2, 2 amx amy, 2 amx amz, 2 amy amz, 2 amx, 2 amy, 2 amz,
//! 1]`. That regression is exact; the exact recovery of `K` and `b` from its coefficients is
//! [`quadric_fit`], the paper's own back-substitution (which drops terms of order `M^2`) is
//! [`paper_fit`].

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::frame::Frame;
use super::{FitSettings, Method, Model};
use crate::error::{invalid, CoreError, Result};
use crate::lanes::{F64x4, Portable, LANES};
use crate::lsq::{cholesky3, inverse3, lanes_by_rows, lstsq_fn, lstsq_normal_lanes, RowLanes};
use nalgebra::{Matrix3, Vector3};

/// Where the start of the iteration (or the linear answer) came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StartSource {
    /// Given by the caller.
    User,
    /// The exact recovery from the quadric regression.
    Quadric,
    /// The paper's small-M back-substitution.
    Paper,
    /// The linear solution failed; a bias + scale start, used to diagnose the design.
    Fallback,
}

impl StartSource {
    /// Name: `"user" | "quadric" | "linear-paper" | "fallback"`.
    pub fn name(self) -> &'static str {
        match self {
            StartSource::User => "user",
            StartSource::Quadric => "quadric",
            StartSource::Paper => "linear-paper",
            StartSource::Fallback => "fallback",
        }
    }
}

/// Outcome of the start stage (parameters in output units; unused slots are zero).
#[derive(Debug, Clone)]
pub struct Start {
    /// Start parameters.
    pub params: [f64; 9],
    /// Where they came from.
    pub source: StartSource,
    /// Why the linear solution failed ([`StartSource::Fallback`] only).
    pub error: Option<CoreError>,
}

fn not_ellipsoid(detail: &str) -> CoreError {
    CoreError::Degenerate(format!(
        "the dwell means do not lie on an ellipsoid ({detail}): check that the data are static \
         dwell means of one sensor (rows taken while it moved, or poses that cover little of \
         the sphere, give such a quadric; the data may be in any unit, g only sets the unit of \
         the calibrated output)"
    ))
}

/// Columns of the quadric regression, as the user reads them.
const QUADRIC_COLUMNS: [&str; 9] = ["x^2", "y^2", "xy", "xz", "yz", "x", "y", "z", "1"];
const QUADRIC_COLUMNS_DIAG: [&str; 6] = ["x^2", "y^2", "x", "y", "z", "1"];

/// A singular quadric regression in the terms of the dwell means (which output never varies).
fn quadric_design_error(e: CoreError, diag: bool) -> CoreError {
    let CoreError::Degenerate(m) = &e else {
        return e;
    };
    let names: &[&str] = if diag {
        &QUADRIC_COLUMNS_DIAG
    } else {
        &QUADRIC_COLUMNS
    };
    let col = m
        .strip_prefix("design column ")
        .and_then(|r| r.split(' ').next())
        .and_then(|j| j.parse::<usize>().ok())
        .and_then(|j| names.get(j));
    let what = match col {
        Some(c) => format!("its {c} column is zero or not finite"),
        None => m.clone(),
    };
    CoreError::Degenerate(format!(
        "the dwell means cannot determine an ellipsoid: the quadric regression is singular \
         ({what}); the outputs must vary on every axis between dwells (turn the sensor to \
         different attitudes) and be static dwell means of one sensor"
    ))
}

/// Quadric regression `z^2 = x . beta` on the points `f.point(means[k])` (9 columns, or 6
/// for the diagonal model; the last entries of the result are zero then). `exact`: by QR
/// (the linear method's answer); otherwise by the normal equations (a start value, with the
/// QR when the design is ill-conditioned).
pub fn quadric_beta(means: &[[f64; 3]], f: Frame, diag: bool, exact: bool) -> Result<[f64; 9]> {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::lanes::avx2_fma() {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            return unsafe { quadric_beta_avx2(means, f, diag, exact) };
        }
    }
    quadric_beta_body::<Portable>(means, f, diag, exact)
}

/// [`quadric_beta`] on 256-bit registers with fused multiply-adds (the QR's dot products and
/// updates, and the normal equations' sums in [`lstsq_normal_lanes`]).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn quadric_beta_avx2(
    means: &[[f64; 3]],
    f: Frame,
    diag: bool,
    exact: bool,
) -> Result<[f64; 9]> {
    quadric_beta_body::<crate::lanes::Avx2Fma>(means, f, diag, exact)
}

#[inline(always)]
fn quadric_beta_body<V: F64x4>(
    means: &[[f64; 3]],
    f: Frame,
    diag: bool,
    exact: bool,
) -> Result<[f64; 9]> {
    let rows = QuadricRows { means, f };
    let mut out = [0.0; 9];
    if diag {
        let b = regress::<V, 6>(&rows, exact).map_err(|e| quadric_design_error(e, true))?;
        out[..6].copy_from_slice(&b);
    } else {
        out = regress::<V, 9>(&rows, exact).map_err(|e| quadric_design_error(e, false))?;
    }
    Ok(out)
}

/// The regression on `rows`: by QR when `exact`, else by the normal equations in lanes.
#[inline(always)]
fn regress<V: F64x4, const C: usize>(rows: &QuadricRows<'_>, exact: bool) -> Result<[f64; C]>
where
    for<'a> QuadricRows<'a>: RowLanes<V, C>,
{
    if exact {
        lstsq_fn::<C>(rows.means.len(), |k| rows.row(k))
    } else {
        lstsq_normal_lanes::<V, C>(rows)
    }
}

/// The rows of the quadric regression on the points `f.point(means[k])`: `z^2` on
/// `[x^2, y^2, 2xy, 2xz, 2yz, 2x, 2y, 2z, 1]` (9 columns) or its [`DIAG_COLUMNS`] (6, the
/// diagonal model). Full blocks of lanes are built in registers.
struct QuadricRows<'a> {
    means: &'a [[f64; 3]],
    f: Frame,
}

impl QuadricRows<'_> {
    /// The points of rows `i0 .. i0 + LANES` in lanes (a full block).
    #[inline(always)]
    fn points<V: F64x4>(&self, i0: usize) -> [V; 3] {
        let m = V::transpose3_at(self.means, i0);
        let is = V::splat(1.0 / self.f.s);
        let c = self.f.c;
        [
            (m[0] - V::splat(c[0])) * is,
            (m[1] - V::splat(c[1])) * is,
            (m[2] - V::splat(c[2])) * is,
        ]
    }
}

impl<V: F64x4> RowLanes<V, 9> for QuadricRows<'_> {
    #[inline(always)]
    fn n_rows(&self) -> usize {
        self.means.len()
    }
    #[inline(always)]
    fn row(&self, k: usize) -> ([f64; 9], f64) {
        let [x, y, z] = self.f.point(&self.means[k]);
        (
            [
                x * x,
                y * y,
                2.0 * x * y,
                2.0 * x * z,
                2.0 * y * z,
                2.0 * x,
                2.0 * y,
                2.0 * z,
                1.0,
            ],
            z * z,
        )
    }
    #[inline(always)]
    fn lanes(&self, i0: usize) -> ([V; 9], V) {
        if self.means.len() - i0 < LANES {
            return lanes_by_rows(self, i0);
        }
        let [x, y, z] = self.points::<V>(i0);
        let two = V::splat(2.0);
        let (tx, ty, tz) = (two * x, two * y, two * z);
        (
            [
                x * x,
                y * y,
                tx * y,
                tx * z,
                ty * z,
                tx,
                ty,
                tz,
                V::splat(1.0),
            ],
            z * z,
        )
    }
}

/// The columns of the 9-column row that the diagonal model keeps: `x^2, y^2, 2x, 2y, 2z, 1`.
const DIAG_COLUMNS: [usize; 6] = [0, 1, 5, 6, 7, 8];

impl<V: F64x4> RowLanes<V, 6> for QuadricRows<'_> {
    #[inline(always)]
    fn n_rows(&self) -> usize {
        self.means.len()
    }
    #[inline(always)]
    fn row(&self, k: usize) -> ([f64; 6], f64) {
        let (r, y) = RowLanes::<V, 9>::row(self, k);
        (diag_columns(&r), y)
    }
    #[inline(always)]
    fn lanes(&self, i0: usize) -> ([V; 6], V) {
        let (r, y) = RowLanes::<V, 9>::lanes(self, i0);
        (diag_columns(&r), y)
    }
}

/// The [`DIAG_COLUMNS`] of a 9-column row.
#[inline(always)]
fn diag_columns<T: Copy>(r: &[T; 9]) -> [T; 6] {
    let mut out = [r[0]; 6];
    for (o, &c) in out.iter_mut().zip(&DIAG_COLUMNS) {
        *o = r[c];
    }
    out
}

/// Exact recovery of `K` and `b` from the quadric regression (no small-M assumption), in the
/// frame `f`; returns frame parameters.
///
/// 1. `Qt = [[-b1, -b3, -b4], [-b3, -b2, -b5], [-b4, -b5, 1]]` (`b_i = beta_i`);
/// 2. `b = Qt^-1 [beta6, beta7, beta8]`;
/// 3. `Q33 = g^2 / (b^T Qt b + beta9)`, `Q = Q33 Qt`;
/// 4. `K K^T = Q^-1` with `K` in the model's triangle (Cholesky).
pub fn quadric_fit(
    means: &[[f64; 3]],
    f: Frame,
    g: f64,
    model: Model,
    exact: bool,
) -> Result<[f64; 9]> {
    let diag = model == Model::Diag;
    let beta = quadric_beta(means, f, diag, exact)?;
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
    if cholesky3(&qt).is_none() {
        return Err(not_ellipsoid("the fitted quadric is not positive definite"));
    }
    let qt_inv = inverse3(&qt).ok_or_else(|| not_ellipsoid("the fitted quadric is singular"))?;
    let b = qt_inv * lin;
    let den = b.dot(&(qt * b)) + c0;
    if !(den > 0.0) || !den.is_finite() {
        return Err(not_ellipsoid("the fitted quadric has no real points"));
    }
    // Q^-1 = Qt^-1 den / g^2.
    let q_inv = qt_inv * (den / (g * g));
    let k = match model {
        Model::Diag => Matrix3::from_diagonal(&Vector3::new(
            q_inv[(0, 0)].sqrt(),
            q_inv[(1, 1)].sqrt(),
            q_inv[(2, 2)].sqrt(),
        )),
        Model::Lower => {
            cholesky3(&q_inv).ok_or_else(|| not_ellipsoid("Q^-1 is not positive definite"))?
        }
        Model::Upper => {
            // K K^T = Q^-1 with K upper: reverse the axes, take Cholesky, reverse back.
            let p = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
            let l = cholesky3(&(p * q_inv * p))
                .ok_or_else(|| not_ellipsoid("Q^-1 is not positive definite"))?;
            p * l * p
        }
    };
    let out = model.params_from(&k, &b);
    if out.iter().any(|v| !v.is_finite()) {
        return Err(not_ellipsoid("non-finite recovery"));
    }
    Ok(out)
}

/// The paper's back-substitution (its eqs. 7-10, dropping terms of order `M^2`), in the frame
/// `f` (which must be origin-centred: the paper's regression is about the raw origin).
pub fn paper_fit(means: &[[f64; 3]], f: Frame, g: f64, model: Model) -> Result<[f64; 9]> {
    if model == Model::Upper {
        return invalid(
            "method \"linear-paper\" is defined for model \"lower\" (and \"diag\") only",
        );
    }
    let diag = model == Model::Diag;
    let beta = quadric_beta(means, f, diag, true)?;
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
    let bt = inverse3(&a)
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
    let mut p = [sx, sy, sz, b[0] * sx, b[1] * sy, b[2] * sz, 0.0, 0.0, 0.0];
    if !diag {
        p[6..].copy_from_slice(&[k21 * sy, k31 * sz, k32 * sz]);
    }
    Ok(p)
}

/// Bias + scale start (output units) used to diagnose designs where the linear solution
/// fails: the diagonal quadric, else the centroid frame itself.
pub fn fallback_start(means: &[[f64; 3]], g: f64, f0: Frame) -> [f64; 9] {
    match quadric_fit(means, f0, g, Model::Diag, false) {
        Ok(p) => f0.unframe(&p),
        Err(_) => [f0.s, f0.s, f0.s, f0.c[0], f0.c[1], f0.c[2], 0.0, 0.0, 0.0],
    }
}

/// The start stage: the user's start (validated), or the method's linear solution (the
/// paper's for `LinearPaper`, the exact quadric otherwise), or, when that fails with
/// degenerate data, the bias + scale fallback with the failure recorded. `f0` is the
/// centroid frame of the data.
pub fn start_stage(means: &[[f64; 3]], g: f64, set: &FitSettings, f0: Frame) -> Result<Start> {
    let model = set.model;
    let np = model.n_params();
    if let Some(s) = &set.start {
        if !matches!(set.method, Method::GaussNewton | Method::Lm) {
            return invalid("start= is only used by method \"gauss-newton\" or \"lm\"");
        }
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
        let mut p = [0.0; 9];
        p[..np].copy_from_slice(s);
        return Ok(Start {
            params: p,
            source: StartSource::User,
            error: None,
        });
    }
    let (linear, source) = if set.method == Method::LinearPaper {
        let fs = Frame::origin(means, g);
        (
            paper_fit(means, fs, g, model).map(|p| fs.unframe(&p)),
            StartSource::Paper,
        )
    } else {
        // The quadric method's answer is the exact regression (QR); as the start of the
        // iteration the normal equations suffice.
        let exact = set.method == Method::Quadric;
        (
            quadric_fit(means, f0, g, model, exact).map(|p| f0.unframe(&p)),
            StartSource::Quadric,
        )
    };
    match linear {
        Ok(params) => Ok(Start {
            params,
            source,
            error: None,
        }),
        Err(e @ CoreError::InvalidInput(_)) => Err(e),
        Err(e) => Ok(Start {
            params: fallback_start(means, g, f0),
            source: StartSource::Fallback,
            error: Some(unexcited_axes(means).unwrap_or(e)),
        }),
    }
}

/// Unit gravity directions closer than this (about 3 deg) are one pose.
pub const SAME_POSE: f64 = 0.05;

/// Number of distinct poses among dwell means: clusters closer than `tol` (raw units),
/// counted up to `limit` (the count stops there).
pub fn distinct_poses_upto(mean: &[[f64; 3]], tol: f64, limit: usize) -> usize {
    let mut centres: Vec<[f64; 3]> = Vec::with_capacity(limit.min(mean.len()));
    for m in mean {
        if centres.len() >= limit {
            break;
        }
        let near = centres
            .iter()
            .any(|c| (0..3).map(|i| (c[i] - m[i]).powi(2)).sum::<f64>().sqrt() < tol);
        if !near {
            centres.push(*m);
        }
    }
    centres.len()
}

/// Number of distinct poses among dwell means: clusters closer than `tol` (raw units).
pub fn distinct_poses(mean: &[[f64; 3]], tol: f64) -> usize {
    distinct_poses_upto(mean, tol, usize::MAX)
}

/// A predicted relative std above this: the parameter is barely determined (set by the
/// noise, not by the poses).
pub const BARELY: f64 = 0.1;

/// Unit gravity direction of each dwell under the calibration `params` (output units):
/// `a/|a|` with `a = K^-1 (m - b)`; `None` for a dwell it cannot evaluate (every dwell when
/// `K` is singular).
pub fn directions(means: &[[f64; 3]], model: Model, params: &[f64; 9]) -> Vec<Option<[f64; 3]>> {
    let t = super::cost::inv_k(model, params).ok();
    let b = Vector3::new(params[3], params[4], params[5]);
    means
        .iter()
        .map(|m| {
            let a = t.as_ref()? * (Vector3::new(m[0], m[1], m[2]) - b);
            let n = a.norm();
            (n > 0.0 && n.is_finite()).then(|| [a[0] / n, a[1] / n, a[2] / n])
        })
        .collect()
}

/// A barely determined fit (largest predicted relative std `weakest` above [`BARELY`]) whose
/// dwells are at fewer distinct poses (calibrated gravity directions within [`SAME_POSE`],
/// about 3 deg, under the fit's `params`, output units) than the model has parameters: each
/// pose gives one norm equation, so some combination is set by the noise alone (six faces
/// recorded twice, say, fitted with misalignments). Repeats of few poses at high signal to
/// noise can still determine the model (a small `weakest`): not refused.
pub fn too_few_poses(
    means: &[[f64; 3]],
    model: Model,
    params: &[f64; 9],
    weakest: f64,
) -> Result<()> {
    if !(weakest > BARELY) {
        return Ok(());
    }
    let np = model.n_params();
    let Some(u) = directions(means, model, params)
        .into_iter()
        .collect::<Option<Vec<_>>>()
    else {
        return Ok(());
    };
    let k = distinct_poses_upto(&u, SAME_POSE, np);
    if k >= np {
        return Ok(());
    }
    let n = means.len();
    let instead = if np == 9 && k >= 6 {
        ", or fit model \"diag\" (bias + scale, 6 parameters)"
    } else {
        ""
    };
    Err(CoreError::Degenerate(format!(
        "the {n} dwells are at only {k} distinct poses (dwells within about 3 deg of each \
         other are one pose): model \"{}\" has {np} parameters and each pose gives one norm \
         equation, so some are set by the noise alone (predicted std up to {weakest:.1e} \
         relative); add poses with different gravity directions (tilts in both axes at \
         once){instead}",
        model.name()
    )))
}

/// An axis's dwell means spanning less than this fraction of their typical norm: no pose
/// turned that axis towards gravity.
const UNEXCITED_SPAN: f64 = 0.2;

/// Why a fit failed, when the cause is an axis that no pose turned towards gravity (its
/// dwell means span under [`UNEXCITED_SPAN`] of the norm): its scale and bias cannot be told
/// apart; or, when no axis moves, that the dwells are one pose. `None` when every axis moves,
/// or for identical dwells (said elsewhere, as such).
pub fn unexcited_axes(means: &[[f64; 3]]) -> Option<CoreError> {
    unexcited(means).map(|(e, _)| e)
}

/// [`unexcited_axes`] when no axis moves (the dwells are one pose), else `None`: a cause that
/// comes before any undetermined combination the fit names (no model, not even the diagonal
/// one, can be fitted to one pose).
pub fn one_pose(means: &[[f64; 3]]) -> Option<CoreError> {
    unexcited(means).and_then(|(e, all)| all.then_some(e))
}

/// Whether the outputs look offset by more than one g of their response on some axis, with
/// the three axes' responses alike (within a factor 1.5, as a triad's are): the bias + scale
/// quadric of the dwells says so. A fit collapsed onto a small cap (biases as large, but the
/// scale factors tens of times apart) does not count. False when the quadric fails.
pub fn offset_outputs(means: &[[f64; 3]], g: f64) -> bool {
    let Ok(f0) = Frame::centroid(means, g) else {
        return false;
    };
    let Ok(q) = quadric_fit(means, f0, g, Model::Diag, false) else {
        return false;
    };
    let (spread, bias_beyond) = super::triad_shape(&f0.unframe(&q), g);
    spread <= 1.5 && bias_beyond
}

/// [`unexcited_axes`] with whether every axis is flat.
fn unexcited(means: &[[f64; 3]]) -> Option<(CoreError, bool)> {
    if means.len() < 2 {
        return None;
    }
    let mut norms: Vec<f64> = means
        .iter()
        .map(|m| (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt())
        .collect();
    norms.sort_by(f64::total_cmp);
    let scale = norms[norms.len() / 2];
    if !(scale > 0.0) || !scale.is_finite() {
        return None;
    }
    // (axis, span) of the axes that barely move.
    let flat: Vec<(&str, f64)> = ["x", "y", "z"]
        .iter()
        .enumerate()
        .filter_map(|(a, name)| {
            let (lo, hi) = means
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), m| {
                    (lo.min(m[a]), hi.max(m[a]))
                });
            (hi - lo < UNEXCITED_SPAN * scale).then_some((*name, hi - lo))
        })
        .collect();
    let n = means.len();
    let pct = |span: f64| 100.0 * span / scale;
    match flat.len() {
        0 => None,
        3 if means.iter().all(|m| m == &means[0]) => None,
        3 => Some((
            CoreError::Degenerate(format!(
                "the {n} dwells are one pose: every output spans under {:.0} % of the norm \
             ({scale:.4e}) over them ({}); a calibration needs poses in different attitudes \
             (each axis up and down, or tilted by 30 deg or more)",
                100.0 * UNEXCITED_SPAN,
                flat.iter()
                    .map(|(a, s)| format!("{a} {:.1} %", pct(*s)))
                    .collect::<Vec<_>>()
                    .join(", ")
            )),
            true,
        )),
        _ => {
            let names: Vec<&str> = flat.iter().map(|(a, _)| *a).collect();
            let e = CoreError::Degenerate(format!(
                "{} over the {n} dwells: no pose turned the {} axis towards gravity, so its \
                 scale and bias cannot be told apart; add poses with {} (or tilted by 30 deg \
                 or more)",
                flat.iter()
                    .map(|(a, s)| format!(
                        "the {a} output spans only {s:.3e} ({:.1} % of the norm, {scale:.4e})",
                        pct(*s)
                    ))
                    .collect::<Vec<_>>()
                    .join(", "),
                names.join(" and "),
                names
                    .iter()
                    .map(|a| format!("{a} up and {a} down"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
            Some((e, false))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests_common::{simulate, G, TRUTH};
    use super::*;

    /// The portable build of the quadric regression's lanes gives the dispatched build's
    /// coefficients (AVX2 + FMA here), for 9 and 6 columns and a short last block.
    #[test]
    fn portable_quadric_lanes_match_the_dispatched_kernel() {
        for n in [20, 23] {
            let m = simulate(Model::Lower, &TRUTH, n, 60.0, 4);
            let f = Frame::centroid(&m, G).unwrap();
            for diag in [false, true] {
                let a = quadric_beta(&m, f, diag, false).unwrap();
                let b = quadric_beta_body::<Portable>(&m, f, diag, false).unwrap();
                for (x, y) in a.iter().zip(&b) {
                    assert!((x - y).abs() <= 1e-10 * x.abs().max(1e-3), "{x} {y}");
                }
            }
        }
    }

    #[test]
    fn quadric_start_is_exact_and_paper_start_is_biased() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 1);
        let f0 = Frame::centroid(&m, G).unwrap();
        let set = FitSettings::new(Model::Lower, Method::Lm);
        let s = start_stage(&m, G, &set, f0).unwrap();
        assert_eq!(s.source, StartSource::Quadric);
        for (a, b) in s.params.iter().zip(&TRUTH) {
            assert!((a - b).abs() < 1e-10);
        }
        let set = FitSettings::new(Model::Lower, Method::LinearPaper);
        let s = start_stage(&m, G, &set, f0).unwrap();
        assert_eq!(s.source, StartSource::Paper);
        let e = s
            .params
            .iter()
            .zip(&TRUTH)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(e > 1e-5 && e < 1e-2, "{e}");
    }

    #[test]
    fn user_start_is_validated_and_a_failed_quadric_falls_back() {
        let m = simulate(Model::Lower, &TRUTH, 20, 60.0, 2);
        let f0 = Frame::centroid(&m, G).unwrap();
        let mut set = FitSettings::new(Model::Lower, Method::Lm);
        set.start = Some(vec![1.0; 3]);
        assert!(matches!(
            start_stage(&m, G, &set, f0),
            Err(CoreError::InvalidInput(_))
        ));
        set.start = Some(vec![1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
        assert_eq!(
            start_stage(&m, G, &set, f0).unwrap().source,
            StartSource::User
        );
        set.method = Method::Quadric;
        assert!(start_stage(&m, G, &set, f0).is_err());
        // Points on a hyperboloid sheet: no ellipsoid, a bias + scale fallback.
        let h: Vec<[f64; 3]> = (0..20)
            .map(|i| {
                let (x, y) = ((i % 5) as f64 - 2.0, (i / 5) as f64 - 1.5);
                [x, y, (x * x - y * y + 30.0).sqrt()]
            })
            .collect();
        let f0 = Frame::centroid(&h, G).unwrap();
        let s = start_stage(&h, G, &FitSettings::new(Model::Lower, Method::Lm), f0).unwrap();
        assert_eq!(s.source, StartSource::Fallback);
        assert!(matches!(s.error, Some(CoreError::Degenerate(_))));
        assert!(s.params[6..].iter().all(|v| *v == 0.0));
    }

    /// A tumble that never turns x towards gravity (a table that rolls about x only): the
    /// failed linear solution is explained by the axis, not as "no ellipsoid".
    #[test]
    fn an_axis_no_pose_excites_is_named() {
        let m: Vec<[f64; 3]> = (0..12)
            .map(|i| {
                let r = i as f64 * std::f64::consts::PI / 6.0 + 0.1;
                let x = -0.03 + 1e-3 * (i % 3) as f64;
                [x, 1.02 * r.sin() + 0.05, 0.98 * r.cos() - 0.03]
            })
            .collect();
        let e = unexcited_axes(&m).unwrap().to_string();
        assert!(e.contains("the x output spans only 2.000e-3"), "{e}");
        assert!(
            e.contains("no pose turned the x axis towards gravity"),
            "{e}"
        );
        assert!(e.contains("add poses with x up and x down"), "{e}");
        let every: Vec<[f64; 3]> = simulate(Model::Lower, &TRUTH, 20, 60.0, 2);
        assert!(unexcited_axes(&every).is_none());
        // One pose, with noise: said as such; identical dwells are left to their own message.
        let one: Vec<[f64; 3]> = (0..8)
            .map(|i| [0.01 * (i % 2) as f64, -0.02, 9.8 + 0.01 * (i % 3) as f64])
            .collect();
        let e = unexcited_axes(&one).unwrap().to_string();
        assert!(
            e.starts_with("the 8 dwells are one pose: every output spans under 20 %"),
            "{e}"
        );
        assert!(unexcited_axes(&[[0.0, 0.0, 9.8]; 8]).is_none());
        // One pose fitted with the 9-parameter model: said as such, not as a combination
        // the model leaves undetermined with advice to fit the diagonal model (which fails on
        // one pose too).
        let one12: Vec<[f64; 3]> = (0..12)
            .map(|i| {
                let k = i as f64;
                [
                    0.01 * (k * 1.3).sin(),
                    -0.02 + 0.01 * (k * 0.7).cos(),
                    9.8 + 0.01 * (k * 2.1).sin(),
                ]
            })
            .collect();
        for model in [Model::Lower, Model::Diag] {
            let set = FitSettings::new(model, Method::Lm);
            let e = crate::static_fit::fit_static(
                &one12,
                9.8,
                &crate::static_fit::Noise::Estimated,
                &set,
            )
            .unwrap_err()
            .to_string();
            assert!(
                e.starts_with("the 12 dwells are one pose"),
                "{model:?}: {e}"
            );
        }
        // The fit says so too, whatever failed first (here the quadric start lies where the
        // model cannot be evaluated).
        let set = FitSettings::new(Model::Diag, Method::Lm);
        let e = crate::static_fit::fit_static(&m, 1.0, &crate::static_fit::Noise::Estimated, &set)
            .unwrap_err();
        assert!(matches!(e, CoreError::Degenerate(_)));
        assert!(e.to_string().contains("no pose turned the x axis"), "{e}");
    }
}

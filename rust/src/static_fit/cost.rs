//! The maximum-likelihood cost of a static fit: whitened norm residuals.
//!
//! Dwell `k` has mean `am_k` (output units) with per-axis noise variance `Sigma_k` (diagonal).
//! At parameters `p` the calibrated force is `a_k = T (am_k - b)` with `T = K^-1`, its norm
//! residual `r_k = |a_k| - g`, and to first order `d r_k = w_k^T d am_k` with
//! `w_k = T^T a_k / |a_k|` (`K^-T u_k`). The residual's variance is therefore
//! `sigma_k^2 = w_k^T Sigma_k w_k`, and the whitened residual is
//!
//! ```text
//! e_k(p) = (|K^-1 (am_k - b)| - g) / sigma_k(p)
//! ```
//!
//! Minimising `sum e_k^2` with `sigma_k` re-evaluated at every `p` is maximum likelihood for
//! noisy dwell means on an ellipsoid to first order in the noise (the gradient-weighted, or
//! Sampson, form of the orthogonal-distance fit). The Jacobian of `e_k` includes the
//! derivative of `sigma_k` (see [`ml_row`]). When the noise level is unknown, `Sigma_k = I`
//! (isotropic output noise of unknown level): the same cost, whose minimum per degree of
//! freedom estimates the per-axis noise variance of a dwell mean.
//!
//! These pieces are public so that other fits and diagnostics (for example the gap
//! diagnosis) use the same weighting: [`eval_dwell`] (residual, `w`, `sigma`), [`jac_row`]
//! (`d r / d p`) and [`ml_row`] (`d e / d p`).

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::Model;
use crate::error::{invalid, CoreError, Result};
use crate::lanes::{F64x4, Portable};
use crate::lsq::{inverse3, NormalEquations, NormalEquationsFixed};
use nalgebra::{DMatrix, DVector, Matrix3, Vector3};

/// Noise of the dwell means in the frame of the points being fitted.
#[derive(Debug, Clone, Copy)]
pub enum DwellNoise<'a> {
    /// `Sigma_k = I`: isotropic output noise of unknown level (estimated as chi2/dof).
    Isotropic,
    /// The same per-axis variance for every dwell.
    Uniform([f64; 3]),
    /// `Sigma_k = diag(var[k]) * scale` (per-axis variance of each dwell mean; `scale`
    /// converts output units squared into the fitting frame's).
    PerDwell {
        /// Per-axis variance of each dwell mean.
        var: &'a [[f64; 3]],
        /// Factor applied to every variance.
        scale: f64,
    },
}

impl DwellNoise<'_> {
    /// Per-axis variance of dwell `k`.
    #[inline(always)]
    pub fn var(&self, k: usize) -> [f64; 3] {
        match self {
            DwellNoise::Isotropic => [1.0; 3],
            DwellNoise::Uniform(v) => *v,
            DwellNoise::PerDwell { var, scale } => {
                let v = var[k];
                [v[0] * scale, v[1] * scale, v[2] * scale]
            }
        }
    }

    /// The noise level is known (not estimated from the residuals).
    pub fn known(&self) -> bool {
        !matches!(self, DwellNoise::Isotropic)
    }
}

/// One dwell evaluated at a parameter vector.
#[derive(Debug, Clone, Copy)]
pub struct DwellEval {
    /// Calibrated force `a = K^-1 (am - b)`.
    pub a: Vector3<f64>,
    /// `|a|`.
    pub norm: f64,
    /// Norm residual `|a| - g`.
    pub r: f64,
    /// `w = K^-T a / |a|`: the gradient of `|a|` with respect to the raw output `am`.
    pub w: Vector3<f64>,
    /// Per-axis variance of the dwell mean used (`Sigma_k` diagonal).
    pub var: [f64; 3],
    /// `sigma = sqrt(w^T Sigma w)`: std of the norm residual.
    pub sigma: f64,
    /// `1 / |a|`.
    pub inv_norm: f64,
    /// `1 / sigma`.
    pub inv_sigma: f64,
}

impl DwellEval {
    /// Whitened residual `r / sigma`.
    #[inline(always)]
    pub fn e(&self) -> f64 {
        self.r * self.inv_sigma
    }
}

/// `K^-1` of a parameter vector; an error when `K` is singular or not finite.
#[inline]
pub fn inv_k(model: Model, p: &[f64]) -> Result<Matrix3<f64>> {
    let k = model.k_matrix(p);
    let d = k[(0, 0)] * k[(1, 1)] * k[(2, 2)];
    if !(d.abs() > 0.0) || !d.is_finite() {
        return invalid("singular scale-factor matrix");
    }
    inverse3(&k).ok_or_else(|| CoreError::InvalidInput("singular scale-factor matrix".into()))
}

/// Evaluate dwell mean `am` (variance `var` per axis) at `p` with `t = K^-1`.
#[inline(always)]
pub fn eval_dwell(
    t: &Matrix3<f64>,
    p: &[f64],
    am: &[f64; 3],
    var: [f64; 3],
    g: f64,
) -> Result<DwellEval> {
    let a = t * Vector3::new(am[0] - p[3], am[1] - p[4], am[2] - p[5]);
    let norm = a.norm();
    if !(norm > 0.0) || !norm.is_finite() {
        return invalid("a calibrated dwell has zero or non-finite norm");
    }
    let inv_norm = 1.0 / norm;
    let w = t.tr_mul(&a) * inv_norm;
    let s2 = w[0] * w[0] * var[0] + w[1] * w[1] * var[1] + w[2] * w[2] * var[2];
    if !(s2 > 0.0) || !s2.is_finite() {
        return invalid(
            "the noise model gives a zero or non-finite residual variance for a dwell (every \
             dwell needs a positive variance)",
        );
    }
    let sigma = s2.sqrt();
    Ok(DwellEval {
        a,
        norm,
        r: norm - g,
        w,
        var,
        sigma,
        inv_norm,
        inv_sigma: 1.0 / sigma,
    })
}

/// Jacobian row of `(|a| - g) * is` with respect to the parameters at fixed weight `is`:
/// `d|a|/dK_ij = -w_i a_j`, `d|a|/db_i = -w_i`. At the true parameters (where `r = 0`) this
/// times `1 / sigma` is also the maximum-likelihood row [`ml_row`], so it is the row of the
/// Fisher information used for pose planning.
#[inline(always)]
pub fn jac_row(model: Model, w: &Vector3<f64>, a: &Vector3<f64>, is: f64, row: &mut [f64; 9]) {
    let (w0, w1, w2) = (-w[0] * is, -w[1] * is, -w[2] * is);
    row[0] = w0 * a[0];
    row[1] = w1 * a[1];
    row[2] = w2 * a[2];
    row[3] = w0;
    row[4] = w1;
    row[5] = w2;
    let w = [w0, w1, w2];
    for (slot, (i, j)) in model
        .misalignment_entries()
        .into_iter()
        .flatten()
        .enumerate()
    {
        row[6 + slot] = w[i] * a[j];
    }
}

/// Gradient of the whitened residual `e = r / sigma` with respect to the parameters,
/// including the derivative of `sigma` (`t = K^-1`, `d` from [`eval_dwell`] at the same `p`).
///
/// With `v = Sigma w`, `z = T v`, `u = a / |a|`, `y = (z - (z.u) u) / |a|` and `q = T^T y`:
/// `d sigma^2 / dK_ij = -2 (w_i z_j + q_i a_j)` and `d sigma^2 / db_i = -2 q_i`, so
/// `de/dK_ij = -w_i a_j / sigma + r (w_i z_j + q_i a_j) / sigma^3` and
/// `de/db_i = -w_i / sigma + r q_i / sigma^3`.
#[inline(always)]
pub fn ml_row(model: Model, t: &Matrix3<f64>, d: &DwellEval, row: &mut [f64; 9]) {
    let is = d.inv_sigma;
    let c = d.r * is * is * is;
    let (w, a) = (&d.w, &d.a);
    let v = Vector3::new(d.var[0] * w[0], d.var[1] * w[1], d.var[2] * w[2]);
    let z = t * v;
    let inv_n = d.inv_norm;
    let zu = z.dot(a) * inv_n * inv_n;
    let y = (z - a * zu) * inv_n;
    let q = t.tr_mul(&y);
    // de/dK_ij = -w_i a_j is + c (w_i z_j + q_i a_j) = w_i al_j + be_i a_j with
    // al = c z - is a, be = c q; de/db_i = -w_i is + be_i.
    let al = [
        c * z[0] - is * a[0],
        c * z[1] - is * a[1],
        c * z[2] - is * a[2],
    ];
    let be = [c * q[0], c * q[1], c * q[2]];
    let kij = |i: usize, j: usize| w[i] * al[j] + be[i] * a[j];
    row[0] = kij(0, 0);
    row[1] = kij(1, 1);
    row[2] = kij(2, 2);
    row[3] = be[0] - w[0] * is;
    row[4] = be[1] - w[1] * is;
    row[5] = be[2] - w[2] * is;
    for (slot, (i, j)) in model
        .misalignment_entries()
        .into_iter()
        .flatten()
        .enumerate()
    {
        row[6 + slot] = kij(i, j);
    }
}

/// The maximum-likelihood norm problem: residuals `e_k(p)` of the module documentation.
#[derive(Debug, Clone, Copy)]
pub struct NormProblem<'a> {
    /// Dwell means (in the fitting frame).
    pub pts: &'a [[f64; 3]],
    /// Reference gravity.
    pub g: f64,
    /// Noise of the dwell means (in the fitting frame).
    pub noise: DwellNoise<'a>,
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

    /// Evaluate every dwell at `p`, calling `f(k, t, eval)`.
    #[inline(always)]
    pub fn for_each(
        &self,
        p: &[f64],
        mut f: impl FnMut(usize, &Matrix3<f64>, &DwellEval),
    ) -> Result<()> {
        let t = inv_k(self.model, p)?;
        for (k, am) in self.pts.iter().enumerate() {
            let d = eval_dwell(&t, p, am, self.noise.var(k), self.g)?;
            f(k, &t, &d);
        }
        Ok(())
    }

    /// `sum e_k^2` at `p`.
    #[inline(always)]
    pub fn cost_at(&self, p: &[f64]) -> Result<f64> {
        self.in_range(p)?;
        let mut c = 0.0;
        self.for_each(p, |_, _, d| {
            let e = d.e();
            c += e * e;
        })?;
        if c.is_finite() {
            Ok(c)
        } else {
            invalid("non-finite cost")
        }
    }

    /// Cost, `J^T e` and the upper triangle of `J^T J` for the first `K` parameters at `p`
    /// (`K` = the model's parameter count), added to `h` and `gr`.
    ///
    /// The dwells are taken [`LANES`] at a time, every quantity of [`eval_dwell`] and
    /// [`ml_row`] computed for the lanes side by side in one vector (`crate::lanes`: AVX2
    /// with fused multiply-adds where the CPU has them); the sums are kept per lane and added
    /// across lanes at the end in a fixed order, so the result does not depend on threads or
    /// call order. A dwell that cannot be evaluated is reported as [`NormProblem::for_each`]
    /// reports it.
    #[inline(always)]
    pub fn accumulate<const K: usize>(
        &self,
        p: &[f64],
        h: &mut [[f64; K]; K],
        gr: &mut [f64; K],
    ) -> Result<f64> {
        #[cfg(target_arch = "x86_64")]
        {
            if crate::lanes::avx2_fma() {
                // SAFETY: the CPU supports AVX2 and FMA (checked just above).
                return unsafe { self.accumulate_avx2::<K>(p, h, gr) };
            }
        }
        self.accumulate_lanes::<Portable, K>(p, h, gr)
    }

    /// [`Self::accumulate_lanes`] on 256-bit registers with fused multiply-adds.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn accumulate_avx2<const K: usize>(
        &self,
        p: &[f64],
        h: &mut [[f64; K]; K],
        gr: &mut [f64; K],
    ) -> Result<f64> {
        self.accumulate_lanes::<crate::lanes::Avx2Fma, K>(p, h, gr)
    }

    #[inline(always)]
    fn accumulate_lanes<V: F64x4, const K: usize>(
        &self,
        p: &[f64],
        h: &mut [[f64; K]; K],
        gr: &mut [f64; K],
    ) -> Result<f64> {
        self.in_range(p)?;
        let t = inv_k(self.model, p)?;
        let ts = splat3::<V>(&t);
        let (g, zero) = (V::splat(self.g), V::splat(0.0));
        let bias = [V::splat(p[3]), V::splat(p[4]), V::splat(p[5])];
        let n = self.pts.len();
        // Per-lane partial sums of the cost, `J^T e` and the upper triangle of `J^T J`.
        let mut cl = zero;
        let mut gl = [zero; K];
        let mut hl = [[zero; K]; K];
        // Zero in every lane while every dwell evaluates (see `finite_check`).
        let mut check = zero;
        for k0 in (0..n).step_by(LANES) {
            let ev = self.block(&ts, &bias, g, k0);
            add_block(&ev, &mut cl, &mut gl, &mut hl);
            check = check + ev.check;
        }
        let bad = !check.fold().is_finite();
        for i in 0..K {
            gr[i] += gl[i].fold();
            for j in i..K {
                h[i][j] += hl[i][j].fold();
            }
        }
        let c = cl.fold();
        if bad {
            // Name the first dwell that cannot be evaluated, as the scalar pass does.
            self.for_each(p, |_, _, _| {})?;
        }
        Ok(c)
    }

    /// The block of [`LANES`] dwells from `k0`, evaluated at `p` (`ts = K^-1` in every lane,
    /// `g` the reference).
    #[inline(always)]
    fn block<V: F64x4>(&self, ts: &[[V; 3]; 3], bias: &[V; 3], g: V, k0: usize) -> LaneEval<V> {
        let (x, var, mask, _) = self.gather(bias, k0);
        eval_lanes(ts, x, var, g, mask, self.model)
    }

    /// Lanes of the block of dwells from `k0`: `am - b` (`bias` = `b` in every lane), the
    /// per-axis variance, the lane mask and the number of used lanes. A full block is
    /// transposed in registers; in the last, short block the unused lanes repeat the block's
    /// first dwell (finite whenever it is) and are masked out.
    #[inline(always)]
    fn gather<V: F64x4>(&self, bias: &[V; 3], k0: usize) -> ([V; 3], [V; 3], V, usize) {
        let used = (self.pts.len() - k0).min(LANES);
        if used == LANES {
            let x = V::transpose3_at(self.pts, k0);
            let x = [x[0] - bias[0], x[1] - bias[1], x[2] - bias[2]];
            let var = match self.noise {
                DwellNoise::Isotropic => [V::splat(1.0); 3],
                DwellNoise::Uniform(v) => [V::splat(v[0]), V::splat(v[1]), V::splat(v[2])],
                DwellNoise::PerDwell { var, scale } => {
                    let v = V::transpose3_at(var, k0);
                    let s = V::splat(scale);
                    [v[0] * s, v[1] * s, v[2] * s]
                }
            };
            return (x, var, V::splat(1.0), used);
        }
        let (mut x, mut var, mut mask) = ([[0.0; LANES]; 3], [[0.0; LANES]; 3], [0.0; LANES]);
        for l in 0..LANES {
            let k = if l < used { k0 + l } else { k0 };
            let (pt, v) = (&self.pts[k], self.noise.var(k));
            for i in 0..3 {
                x[i][l] = pt[i];
                var[i][l] = v[i];
            }
            mask[l] = if l < used { 1.0 } else { 0.0 };
        }
        let x = load3::<V>(&x);
        (
            [x[0] - bias[0], x[1] - bias[1], x[2] - bias[2]],
            load3(&var),
            V::from_array(mask),
            used,
        )
    }

    /// The norm residual `r_k = |a_k| - g` and its std `sigma_k` of every dwell at `p`, passed
    /// to `f(k, r_k, sigma_k)` in dwell order: the per-dwell pass of [`Self::for_each`] taken
    /// [`LANES`] dwells at a time (AVX2 with fused multiply-adds where the CPU has them). A
    /// dwell that cannot be evaluated is reported as [`Self::for_each`] reports it, after `f`
    /// has seen every dwell (the values passed for such a dwell are not finite).
    pub fn residuals_each(&self, p: &[f64], f: impl FnMut(usize, f64, f64)) -> Result<()> {
        #[cfg(target_arch = "x86_64")]
        {
            if crate::lanes::avx2_fma() {
                // SAFETY: the CPU supports AVX2 and FMA (checked just above).
                return unsafe { self.residuals_avx2(p, f) };
            }
        }
        self.residuals_lanes::<Portable>(p, f)
    }

    /// [`Self::residuals_lanes`] on 256-bit registers with fused multiply-adds.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn residuals_avx2(&self, p: &[f64], f: impl FnMut(usize, f64, f64)) -> Result<()> {
        self.residuals_lanes::<crate::lanes::Avx2Fma>(p, f)
    }

    #[inline(always)]
    fn residuals_lanes<V: F64x4>(
        &self,
        p: &[f64],
        mut f: impl FnMut(usize, f64, f64),
    ) -> Result<()> {
        let t = inv_k(self.model, p)?;
        let ts = splat3::<V>(&t);
        let g = V::splat(self.g);
        let bias = [V::splat(p[3]), V::splat(p[4]), V::splat(p[5])];
        let n = self.pts.len();
        let mut check = V::splat(0.0);
        for k0 in (0..n).step_by(LANES) {
            let (x, var, _, used) = self.gather(&bias, k0);
            let h = lane_norm(&ts, &x, &var);
            check = check + h.check;
            let (r, sd) = ((h.norm - g).to_array(), h.sd.to_array());
            for l in 0..used {
                f(k0 + l, r[l], sd[l]);
            }
        }
        if !check.fold().is_finite() {
            self.for_each(p, |_, _, _| {})?;
        }
        Ok(())
    }
}

/// Zero in the lanes where `|a|` and `sigma^2` (both >= 0 or NaN) are positive and finite,
/// NaN elsewhere: `x - x` is zero for a finite `x` and NaN for an infinite or NaN one, and a
/// zero `|a|` or `sigma^2` makes its reciprocal (`inv_n`, `inv_s`) infinite. No lane needs a
/// mask: an unused lane repeats a used one. Summed over blocks, the check stays finite while
/// every dwell evaluates, without a comparison per lane.
#[inline(always)]
#[allow(clippy::eq_op)] // x - x is the point: NaN for a non-finite x
fn finite_check<V: F64x4>(norm: V, inv_n: V, s2: V, inv_s: V) -> V {
    ((norm - norm) + (inv_n - inv_n)) + ((s2 - s2) + (inv_s - inv_s))
}

/// `T v` (or `T^T v` when `transpose`) in every lane.
#[inline(always)]
fn mat3_vec<V: F64x4>(t: &[[V; 3]; 3], v: &[V; 3], transpose: bool) -> [V; 3] {
    let mut out = [v[0]; 3];
    for (i, o) in out.iter_mut().enumerate() {
        let (c0, c1, c2) = if transpose {
            (t[0][i], t[1][i], t[2][i])
        } else {
            (t[i][0], t[i][1], t[i][2])
        };
        *o = c2.mul_add(v[2], c1.mul_add(v[1], c0 * v[0]));
    }
    out
}

/// Three rows of lanes as vectors.
#[inline(always)]
fn load3<V: F64x4>(x: &[[f64; LANES]; 3]) -> [V; 3] {
    [
        V::from_array(x[0]),
        V::from_array(x[1]),
        V::from_array(x[2]),
    ]
}

/// Every entry of `t` in every lane.
#[inline(always)]
fn splat3<V: F64x4>(t: &Matrix3<f64>) -> [[V; 3]; 3] {
    let mut out = [[V::splat(0.0); 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = V::splat(t[(i, j)]);
        }
    }
    out
}

/// `u . v` in every lane.
#[inline(always)]
fn dot3<V: F64x4>(u: &[V; 3], v: &[V; 3]) -> V {
    u[2].mul_add(v[2], u[1].mul_add(v[1], u[0] * v[0]))
}

/// Dwells evaluated side by side in [`NormProblem::accumulate`].
pub const LANES: usize = crate::lanes::LANES;

/// Add a block's cost, `J^T e` and upper triangle of `J^T J` to the per-lane sums.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // the triangle of a matrix, indexed as written
fn add_block<V: F64x4, const K: usize>(
    ev: &LaneEval<V>,
    cl: &mut V,
    gl: &mut [V; K],
    hl: &mut [[V; K]; K],
) {
    *cl = ev.e.mul_add(ev.e, *cl);
    for i in 0..K {
        gl[i] = ev.row[i].mul_add(ev.e, gl[i]);
        for j in i..K {
            hl[i][j] = ev.row[i].mul_add(ev.row[j], hl[i][j]);
        }
    }
}

/// [`LANES`] dwells evaluated: the whitened residual `e` and its gradient row (masked lanes
/// zero), with the check of [`finite_check`].
struct LaneEval<V> {
    e: V,
    check: V,
    row: [V; 9],
}

/// The part of [`eval_dwell`] that the residual pass and [`eval_lanes`] share, on every lane:
/// `a = T x`, `|a|`, `1 / |a|`, `T^T a` (`w |a|`), `Sigma T^T a`, the residual variance
/// `sigma^2 = w^T Sigma w`, `sigma`, `1 / sigma` and the [`finite_check`]. Each reciprocal
/// square root is a root and a reciprocal of the square taken side by side (not one after the
/// other): the chain of dependent operations is shorter.
#[inline(always)]
fn lane_norm<V: F64x4>(t: &[[V; 3]; 3], x: &[V; 3], var: &[V; 3]) -> LaneNorm<V> {
    let one = V::splat(1.0);
    let a = mat3_vec(t, x, false);
    let n2 = dot3(&a, &a);
    let (norm, inv_n2) = (n2.sqrt(), one / n2);
    let inv_n = norm * inv_n2;
    let ta = mat3_vec(t, &a, true);
    let vta = [var[0] * ta[0], var[1] * ta[1], var[2] * ta[2]];
    let s2 = dot3(&vta, &ta) * inv_n2;
    let (sd, inv_s2) = (s2.sqrt(), one / s2);
    let is = sd * inv_s2;
    LaneNorm {
        a,
        norm,
        inv_n,
        ta,
        vta,
        sd,
        is,
        check: finite_check(norm, inv_n, s2, is),
    }
}

/// What [`lane_norm`] computes.
struct LaneNorm<V> {
    a: [V; 3],
    norm: V,
    inv_n: V,
    ta: [V; 3],
    vta: [V; 3],
    sd: V,
    is: V,
    check: V,
}

/// [`eval_dwell`] and [`ml_row`] on every lane (`t = K^-1`, `x = am - b`, per-axis variance
/// `var`, lane mask `m`).
#[inline(always)]
fn eval_lanes<V: F64x4>(
    t: &[[V; 3]; 3],
    x: [V; 3],
    var: [V; 3],
    g: V,
    m: V,
    model: Model,
) -> LaneEval<V> {
    let LaneNorm {
        a,
        norm,
        inv_n,
        ta,
        vta,
        is,
        check,
        ..
    } = lane_norm(t, &x, &var);
    let r = norm - g;
    let w = [ta[0] * inv_n, ta[1] * inv_n, ta[2] * inv_n];
    let vw = [vta[0] * inv_n, vta[1] * inv_n, vta[2] * inv_n];
    let e = r * is * m;
    // ml_row: z = T Sigma w, y = (z - (z.u) u) / |a|, q = T^T y.
    let c = r * is * is * is;
    let z = mat3_vec(t, &vw, false);
    let zu = dot3(&z, &a) * inv_n * inv_n;
    let y = [
        (z[0] - a[0] * zu) * inv_n,
        (z[1] - a[1] * zu) * inv_n,
        (z[2] - a[2] * zu) * inv_n,
    ];
    let q = mat3_vec(t, &y, true);
    let al = [
        c * z[0] - is * a[0],
        c * z[1] - is * a[1],
        c * z[2] - is * a[2],
    ];
    let be = [c * q[0], c * q[1], c * q[2]];
    // de/dK_ij = w_i al_j + be_i a_j; de/db_i = be_i - w_i is.
    let kij = |i: usize, j: usize| -> V { w[i].mul_add(al[j], be[i] * a[j]) * m };
    let mut row = [V::splat(0.0); 9];
    row[0] = kij(0, 0);
    row[1] = kij(1, 1);
    row[2] = kij(2, 2);
    row[3] = (be[0] - w[0] * is) * m;
    row[4] = (be[1] - w[1] * is) * m;
    row[5] = (be[2] - w[2] * is) * m;
    for (slot, (i, j)) in model
        .misalignment_entries()
        .into_iter()
        .flatten()
        .enumerate()
    {
        row[6 + slot] = kij(i, j);
    }
    LaneEval { e, check, row }
}

impl NormalEquations for NormProblem<'_> {
    fn n_params(&self) -> usize {
        self.model.n_params()
    }
    fn n_residuals(&self) -> usize {
        self.pts.len()
    }
    fn cost(&self, p: &[f64]) -> Result<f64> {
        self.cost_at(p)
    }
    fn normal(&self, p: &[f64], jtj: &mut DMatrix<f64>, jtr: &mut DVector<f64>) -> Result<f64> {
        fn fill<const K: usize>(
            prob: &NormProblem<'_>,
            p: &[f64],
            jtj: &mut DMatrix<f64>,
            jtr: &mut DVector<f64>,
        ) -> Result<f64> {
            let mut h = [[0.0f64; K]; K];
            let mut gr = [0.0f64; K];
            let c = prob.accumulate::<K>(p, &mut h, &mut gr)?;
            for i in 0..K {
                jtr[i] = gr[i];
                for j in i..K {
                    jtj[(i, j)] = h[i][j];
                    jtj[(j, i)] = h[i][j];
                }
            }
            Ok(c)
        }
        match self.model.n_params() {
            6 => fill::<6>(self, p, jtj, jtr),
            _ => fill::<9>(self, p, jtj, jtr),
        }
    }
}

impl<const N: usize> NormalEquationsFixed<N> for NormProblem<'_> {
    fn n_residuals(&self) -> usize {
        self.pts.len()
    }
    #[inline(always)]
    fn cost(&self, p: &[f64; N]) -> Result<f64> {
        self.cost_at(p)
    }
    #[inline(always)]
    fn normal(&self, p: &[f64; N], jtj: &mut [[f64; N]; N], jtr: &mut [f64; N]) -> Result<f64> {
        let mut h = [[0.0f64; N]; N];
        let mut gr = [0.0f64; N];
        let c = self.accumulate::<N>(p, &mut h, &mut gr)?;
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The analytic row of `e = r / sigma` equals central differences of `e`, for every
    /// model and for isotropic and per-axis noise, away from the minimum (r != 0).
    #[test]
    fn ml_row_matches_finite_differences() {
        let am = [1.3, -0.4, 9.1];
        for model in [Model::Lower, Model::Upper, Model::Diag] {
            let p = [1.05, 0.97, 1.1, 0.02, -0.03, 0.05, 0.011, -0.02, 0.017];
            for var in [[1.0, 1.0, 1.0], [2e-6, 0.5e-6, 4e-6]] {
                let t = inv_k(model, &p).unwrap();
                let d = eval_dwell(&t, &p, &am, var, 9.5).unwrap();
                assert!(d.r.abs() > 0.1);
                let mut row = [0.0; 9];
                ml_row(model, &t, &d, &mut row);
                let e = |q: &[f64; 9]| {
                    let t = inv_k(model, q).unwrap();
                    eval_dwell(&t, q, &am, var, 9.5).unwrap().e()
                };
                for (j, rj) in row.iter().enumerate().take(model.n_params()) {
                    let h = 1e-6;
                    let (mut a, mut b) = (p, p);
                    a[j] += h;
                    b[j] -= h;
                    let fd = (e(&a) - e(&b)) / (2.0 * h);
                    assert!(
                        (fd - rj).abs() <= 1e-6 * fd.abs().max(1.0),
                        "{model:?} {j}: {fd} vs {rj}"
                    );
                }
                // jac_row is d r / dp times is: central differences of r.
                let mut jr = [0.0; 9];
                jac_row(model, &d.w, &d.a, 1.0, &mut jr);
                let r = |q: &[f64; 9]| {
                    let t = inv_k(model, q).unwrap();
                    eval_dwell(&t, q, &am, var, 9.5).unwrap().r
                };
                for (j, rj) in jr.iter().enumerate().take(model.n_params()) {
                    let h = 1e-6;
                    let (mut a, mut b) = (p, p);
                    a[j] += h;
                    b[j] -= h;
                    let fd = (r(&a) - r(&b)) / (2.0 * h);
                    assert!((fd - rj).abs() <= 1e-6 * fd.abs().max(1.0), "{j}");
                }
            }
        }
    }

    /// The portable build of the lane kernels (what a CPU without AVX2 and FMA runs) gives
    /// the normal equations and residuals of the dispatched build (AVX2 + FMA here), for
    /// every model, both noise kinds and dwell counts around the block size.
    #[test]
    fn portable_lanes_match_the_dispatched_kernels() {
        let p = [1.05, 0.97, 1.1, 0.02, -0.03, 0.05, 0.011, -0.02, 0.017];
        let mut seed = 3u64;
        let pts: Vec<[f64; 3]> = (0..23)
            .map(|_| [0; 3].map(|_| 9.0 * (crate::test_rng::unit(&mut seed) - 0.5)))
            .collect();
        let var: Vec<[f64; 3]> = (0..23)
            .map(|_| [0; 3].map(|_| 1e-6 * (0.5 + crate::test_rng::unit(&mut seed))))
            .collect();
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1e-300);
        for model in [Model::Lower, Model::Upper, Model::Diag] {
            for n in [9, 12, 23] {
                for noise in [
                    DwellNoise::Isotropic,
                    DwellNoise::PerDwell {
                        var: &var,
                        scale: 3.0,
                    },
                ] {
                    let prob = NormProblem {
                        pts: &pts[..n],
                        g: 9.8,
                        noise,
                        model,
                        kmax: f64::INFINITY,
                    };
                    let (mut h1, mut g1, mut h2, mut g2) =
                        ([[0.0; 9]; 9], [0.0; 9], [[0.0; 9]; 9], [0.0; 9]);
                    let c1 = prob.accumulate::<9>(&p, &mut h1, &mut g1).unwrap();
                    let c2 = prob
                        .accumulate_lanes::<Portable, 9>(&p, &mut h2, &mut g2)
                        .unwrap();
                    assert!(close(c1, c2), "{c1} {c2}");
                    // Entries are compared on the scale of their row and column (sums with
                    // cancellation are small next to their terms).
                    let np = model.n_params();
                    for i in 0..np {
                        let gi = (h1[i][i] * c1).sqrt();
                        assert!((g1[i] - g2[i]).abs() <= 1e-12 * gi, "{model:?} {n} g{i}");
                        for j in i..np {
                            let hij = (h1[i][i] * h1[j][j]).sqrt();
                            let d = (h1[i][j] - h2[i][j]).abs();
                            assert!(d <= 1e-12 * hij, "{model:?} {n} h{i}{j}: {d:e} of {hij:e}");
                        }
                    }
                    let (mut r1, mut r2) = (vec![], vec![]);
                    prob.residuals_each(&p, |_, r, sd| r1.push((r, sd)))
                        .unwrap();
                    prob.residuals_lanes::<Portable>(&p, |_, r, sd| r2.push((r, sd)))
                        .unwrap();
                    for (a, b) in r1.iter().zip(&r2) {
                        assert!((a.0 - b.0).abs() <= 1e-14 && close(a.1, b.1), "{a:?} {b:?}");
                    }
                }
            }
        }
    }

    /// The lane pass gives the residual and its std of the scalar pass (to the rounding of
    /// the fused multiply-adds) for every dwell count around the block size, and names the
    /// same bad dwell.
    #[test]
    fn residuals_each_matches_for_each() {
        let p = [1.05, 0.97, 1.1, 0.02, -0.03, 0.05, 0.011, -0.02, 0.017];
        let mut seed = 7u64;
        let pts: Vec<[f64; 3]> = (0..23)
            .map(|_| [0; 3].map(|_| 9.0 * (crate::test_rng::unit(&mut seed) - 0.5)))
            .collect();
        let var: Vec<[f64; 3]> = (0..23)
            .map(|_| [0; 3].map(|_| 1e-6 * (0.5 + crate::test_rng::unit(&mut seed))))
            .collect();
        for n in [1, 3, 4, 5, 8, 9, 23] {
            for noise in [
                DwellNoise::Isotropic,
                DwellNoise::PerDwell {
                    var: &var,
                    scale: 2.0,
                },
            ] {
                let prob = NormProblem {
                    pts: &pts[..n],
                    g: 9.8,
                    noise,
                    model: Model::Lower,
                    kmax: f64::INFINITY,
                };
                let mut want = vec![];
                prob.for_each(&p, |k, _, d| want.push((k, d.r, d.sigma)))
                    .unwrap();
                let mut got = vec![];
                prob.residuals_each(&p, |k, r, sd| got.push((k, r, sd)))
                    .unwrap();
                assert_eq!(got.len(), n);
                for (a, b) in got.iter().zip(&want) {
                    assert_eq!(a.0, b.0);
                    assert!(
                        (a.1 - b.1).abs() <= 1e-14 * b.1.abs().max(1.0),
                        "{a:?} {b:?}"
                    );
                    assert!((a.2 - b.2).abs() <= 1e-14 * b.2, "{a:?} {b:?}");
                }
            }
        }
        let mut bad = pts.clone();
        bad[6] = [p[3], p[4], p[5]];
        let prob = NormProblem {
            pts: &bad,
            g: 9.8,
            noise: DwellNoise::Isotropic,
            model: Model::Lower,
            kmax: f64::INFINITY,
        };
        let want = prob.for_each(&p, |_, _, _| {}).unwrap_err().to_string();
        let got = prob.residuals_each(&p, |_, _, _| {}).unwrap_err();
        assert_eq!(got.to_string(), want);
        let (mut h, mut gr) = ([[0.0; 9]; 9], [0.0; 9]);
        let got = prob.accumulate::<9>(&p, &mut h, &mut gr).unwrap_err();
        assert_eq!(got.to_string(), want);
        // A dwell with zero variance (sigma = 0): the same error from every pass, in any lane.
        for k in [0, 5, 22] {
            let mut v0 = var.clone();
            v0[k] = [0.0; 3];
            let prob = NormProblem {
                pts: &pts,
                g: 9.8,
                noise: DwellNoise::PerDwell {
                    var: &v0,
                    scale: 1.0,
                },
                model: Model::Lower,
                kmax: f64::INFINITY,
            };
            let want = prob.for_each(&p, |_, _, _| {}).unwrap_err().to_string();
            assert!(
                want.contains("zero or non-finite residual variance"),
                "{want}"
            );
            let got = prob.residuals_each(&p, |_, _, _| {}).unwrap_err();
            assert_eq!(got.to_string(), want);
            let got = prob.accumulate::<9>(&p, &mut h, &mut gr).unwrap_err();
            assert_eq!(got.to_string(), want);
        }
    }

    #[test]
    fn isotropic_sigma_is_the_length_of_w() {
        let p = [2.0, 2.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let t = inv_k(Model::Lower, &p).unwrap();
        let d = eval_dwell(&t, &p, &[0.0, 0.0, 20.0], [1.0; 3], 9.8).unwrap();
        assert!((d.sigma - 0.5).abs() < 1e-15 && (d.r - 0.2).abs() < 1e-12);
        assert!((d.e() - 0.4).abs() < 1e-12);
        assert!(eval_dwell(&t, &p, &[0.0, 0.0, 20.0], [0.0; 3], 9.8).is_err());
    }
}

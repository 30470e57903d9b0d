//! The diagnosis engine shared by every system: fit, screen, select, hold out, gate, report.
//!
//! A system implements [`GapModel`]; [`run`] chains the stages, each its own function with its
//! own unit test: [`fit`], [`basis`], [`screen`], [`gls_test`], [`family_decision`],
//! [`stepwise`], [`held_out`], [`gate`], [`candidate_reports`] (with BIC weights),
//! [`ambiguity`] and [`finish`].
//!
//! With a known noise model and [`GapOptions::random_offset`], the rows carry a random offset
//! of variance `s^2` on top of the noise model ([`super::gls`]): the fits, the tests that do
//! not trust the noise model (F), their min-p family and the held-out gate weigh every row by
//! `1 / (sigma_k^2 + s^2)`, with `s^2` re-estimated under every model compared (the current
//! one, each candidate added to it, each fold's). The global gap, the chi2 tests that trust the
//! noise model and the "after" chi2 stay in units of the noise model alone.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::gls::{factors, pm_offset, space, Space};
use super::minp::{min_p, Member};
use super::special::{chi2_sf, f_sf};
use super::{Correction, GapOptions, Gate, Status, TestMode};
use crate::error::{degenerate, CoreError, Result};
use crate::lsq::{
    householder_qr, range_basis, solve_nls, thin_svd, NlsOptions, RangeBasis, Residuals,
};
use nalgebra::{DMatrix, DVector};
use std::sync::Arc;

/// One effect of a system's dictionary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EffectInfo {
    /// Public name.
    pub name: &'static str,
    /// Physical unit of its parameters.
    pub unit: &'static str,
    /// Number of parameters.
    pub dim: usize,
}

/// A system's residual model. Parameters are `[base (n_base), then the parameters of each
/// active effect in the order given]`; residuals are whitened by the model's noise (the
/// engine divides them by a common scale when the noise level is unknown).
pub trait GapModel: Sync {
    /// Number of residual rows.
    fn n_rows(&self) -> usize;
    /// Number of calibration (baseline) parameters.
    fn n_base(&self) -> usize;
    /// The effect dictionary.
    fn dictionary(&self) -> &[EffectInfo];
    /// Why effect `c` cannot be tested on this session (`None`: it can).
    fn unavailable(&self, c: usize) -> Option<Status>;
    /// Held-out group of a row (rows of one group are left out together); by default each
    /// row is its own group.
    fn group(&self, row: usize) -> usize {
        row
    }
    /// Whether the noise level is known (otherwise it is estimated from the baseline fit).
    fn noise_known(&self) -> bool;
    /// Whitened residuals `e` and Jacobian `de/dp` of `rows` at `p` with `active` effects.
    fn eval(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        e: &mut [f64],
        jac: &mut DMatrix<f64>,
    ) -> Result<()>;
    /// Whitened Jacobian columns (`rows x dim`) of candidate `c` at zero effect, at `p`.
    fn columns(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        c: usize,
    ) -> Result<DMatrix<f64>>;
    /// [`Self::columns`] of each candidate in `cs`, in that order (a model whose candidates
    /// share their per-row work overrides this to do it once).
    fn columns_of(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        cs: &[usize],
    ) -> Vec<Result<DMatrix<f64>>> {
        cs.iter()
            .map(|&c| self.columns(rows, active, p, c))
            .collect()
    }
    /// Standard deviation of each row's residual (physical units) at `p`.
    fn sigma(&self, rows: &[usize], active: &[usize], p: &[f64]) -> Result<Vec<f64>>;
    /// Whether effect `c` can predict a held-out group (false for parameters that belong to
    /// one group, like a per-dwell azimuth error: the held-out gate does not judge those).
    fn predictable(&self, _c: usize) -> bool {
        true
    }
    /// Correlation (`n_rows x n_rows`, unit diagonal) of the rows' noise-whitened residuals
    /// beyond the model's own per-row noise, e.g. the shared error of a held-fixed
    /// calibration (`None`: independent rows). The engine then whitens the rows of every fit
    /// and test by the Cholesky factor of its submatrix on the rows used (generalised least
    /// squares), see [`whiten_rows`].
    fn row_correlation(&self) -> Option<&DMatrix<f64>> {
        None
    }
}

/// Generalised-least-squares whitening of row-whitened values `x` (`rows x m`) whose rows
/// have correlation `corr` (all model rows): `x <- L^-1 x`, `L` the Cholesky factor of
/// `corr[rows, rows]`. A single row is left as it is (unit diagonal).
pub fn whiten_rows(corr: &DMatrix<f64>, rows: &[usize], x: &mut DMatrix<f64>) -> Result<()> {
    if rows.len() < 2 || x.ncols() == 0 {
        return Ok(());
    }
    let sub = DMatrix::from_fn(rows.len(), rows.len(), |a, b| corr[(rows[a], rows[b])]);
    let l = sub.cholesky().ok_or_else(|| {
        CoreError::NotConverged("the rows' correlation is not positive definite".into())
    })?;
    l.l_dirty().solve_lower_triangular_mut(x);
    Ok(())
}

/// Number of parameters of the model with `active` effects.
pub fn n_params<M: GapModel>(m: &M, active: &[usize]) -> usize {
    m.n_base() + active.iter().map(|&c| m.dictionary()[c].dim).sum::<usize>()
}

/// The model, its noise scale, the test settings and the row weights of a fit.
pub struct Ctx<'a, M: GapModel> {
    /// The system model.
    pub m: &'a M,
    /// Residuals are divided by this (1 when the noise is known).
    pub scale: f64,
    /// Settings.
    pub opt: &'a GapOptions,
    /// Whether rows carry a random offset (variance-component model, see [`super::gls`]).
    pub gls: bool,
    /// Row factors of the variance-component whitening, per model row (empty: none).
    pub f: Vec<f64>,
    /// Correlation of the rows ([`GapModel::row_correlation`]; `None` with a random offset,
    /// whose row factors assume independent rows, and in [`Self::diagonal`]).
    pub corr: Option<&'a DMatrix<f64>>,
}

impl<'a, M: GapModel> Ctx<'a, M> {
    /// The context without row factors (rows whitened by the noise model alone).
    pub fn new(m: &'a M, scale: f64, opt: &'a GapOptions) -> Self {
        let gls = opt.random_offset && m.noise_known();
        Ctx {
            m,
            scale,
            opt,
            gls,
            f: vec![],
            corr: if gls { None } else { m.row_correlation() },
        }
    }

    /// The same context with the rows whitened one by one (no row correlation): the per-row
    /// figures of the report.
    pub fn diagonal(&self) -> Ctx<'a, M> {
        Ctx {
            m: self.m,
            scale: self.scale,
            opt: self.opt,
            gls: self.gls,
            f: self.f.clone(),
            corr: None,
        }
    }

    /// The same context with row factors `f` (one per model row).
    pub fn weighted(&self, f: Vec<f64>) -> Ctx<'a, M> {
        Ctx {
            m: self.m,
            scale: self.scale,
            opt: self.opt,
            gls: self.gls,
            f,
            corr: self.corr,
        }
    }

    /// The same context without row factors.
    pub fn unweighted(&self) -> Ctx<'a, M> {
        self.weighted(vec![])
    }

    fn eval(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        e: &mut [f64],
        jac: &mut DMatrix<f64>,
    ) -> Result<()> {
        self.m.eval(rows, active, p, e, jac)?;
        if self.scale != 1.0 {
            e.iter_mut().for_each(|v| *v /= self.scale);
            *jac /= self.scale;
        }
        if !self.f.is_empty() {
            for (ri, &k) in rows.iter().enumerate() {
                e[ri] *= self.f[k];
                jac.row_mut(ri).scale_mut(self.f[k]);
            }
        }
        if let Some(c) = self.corr {
            let mut ev = DMatrix::from_column_slice(e.len(), 1, e);
            whiten_rows(c, rows, &mut ev)?;
            e.copy_from_slice(ev.as_slice());
            whiten_rows(c, rows, jac)?;
        }
        if e.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::NotConverged(
                "the model is not evaluable at these parameters".into(),
            ));
        }
        Ok(())
    }

    /// The whitened columns of each candidate in `cs` in this context (the model's
    /// [`GapModel::columns_of`]; none, `rows x 0`, for a candidate that cannot be evaluated).
    fn columns_of(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        cs: &[usize],
    ) -> Vec<DMatrix<f64>> {
        let xs = self.m.columns_of(rows, active, p, cs);
        xs.into_iter()
            .map(|x| self.scaled_columns(rows, x))
            .collect()
    }

    /// A candidate's columns from the model in this context's whitening (scale and row
    /// factors); none (`rows x 0`) when they cannot be evaluated or are not finite.
    fn scaled_columns(&self, rows: &[usize], x: Result<DMatrix<f64>>) -> DMatrix<f64> {
        match x {
            Ok(mut x) => {
                x /= self.scale;
                if !self.f.is_empty() {
                    for (ri, &k) in rows.iter().enumerate() {
                        x.row_mut(ri).scale_mut(self.f[k]);
                    }
                }
                if let Some(c) = self.corr {
                    if whiten_rows(c, rows, &mut x).is_err() {
                        return DMatrix::zeros(rows.len(), 0);
                    }
                }
                if x.iter().all(|v| v.is_finite()) {
                    x
                } else {
                    DMatrix::zeros(rows.len(), 0)
                }
            }
            Err(_) => DMatrix::zeros(rows.len(), 0),
        }
    }

    /// Row factors of offset variance `s2` for every model row, at `p` with `active` effects.
    fn factors_at(&self, active: &[usize], p: &[f64], s2: f64) -> Result<Vec<f64>> {
        let all: Vec<usize> = (0..self.m.n_rows()).collect();
        let sig: Vec<f64> = self
            .m
            .sigma(&all, active, p)?
            .iter()
            .map(|s| s * self.scale)
            .collect();
        Ok(factors(&sig, s2))
    }
}

// ------------------------------------------------------------------------------------------
// Fit.

/// A fitted model on a set of rows.
#[derive(Debug, Clone)]
pub struct Fit {
    /// Parameters (base then active effects).
    pub p: Vec<f64>,
    /// Whitened residuals.
    pub e: Vec<f64>,
    /// Whitened Jacobian (all parameters; frozen ones have zero columns).
    pub jac: DMatrix<f64>,
    /// Sum of squared whitened residuals.
    pub rss: f64,
    /// Offset variance of the weights the fit used (0: the noise model alone).
    pub s2: f64,
}

/// The least-squares problem on the parameters whose Jacobian column is not zero at the
/// start (the others, e.g. a left-out dwell's own parameter, stay fixed). Every free
/// parameter is also anchored to its start by a pseudo-residual of weight [`ANCHOR`] times its
/// column norm: negligible where the data determine the parameter, it keeps directions the
/// data cannot see (a common azimuth offset against a rotation of the gradient) at the start
/// instead of letting the solver wander along them (the minimum-norm solution).
struct FreeProb<'a, M: GapModel> {
    ctx: &'a Ctx<'a, M>,
    rows: &'a [usize],
    active: &'a [usize],
    free: &'a [usize],
    p0: &'a [f64],
    anchor: Vec<f64>,
}

/// Relative weight of the anchor pseudo-residuals.
const ANCHOR: f64 = 1e-6;

impl<M: GapModel> FreeProb<'_, M> {
    fn full(&self, q: &[f64]) -> Vec<f64> {
        let mut p = self.p0.to_vec();
        for (k, &c) in self.free.iter().enumerate() {
            p[c] = q[k];
        }
        p
    }
}

impl<M: GapModel> Residuals for FreeProb<'_, M> {
    fn n_params(&self) -> usize {
        self.free.len()
    }
    fn n_residuals(&self) -> usize {
        self.rows.len() + self.free.len()
    }
    fn eval(&self, q: &[f64], r: &mut [f64], jac: &mut DMatrix<f64>) -> Result<()> {
        let p = self.full(q);
        let n = self.rows.len();
        let mut jf = DMatrix::zeros(n, p.len());
        self.ctx
            .eval(self.rows, self.active, &p, &mut r[..n], &mut jf)?;
        jac.fill(0.0);
        for (k, &c) in self.free.iter().enumerate() {
            jac.view_mut((0, k), (n, 1)).copy_from(&jf.column(c));
            r[n + k] = self.anchor[k] * (q[k] - self.p0[c]);
            jac[(n + k, k)] = self.anchor[k];
        }
        Ok(())
    }
}

fn nls_opts(gauss_newton: bool) -> NlsOptions {
    NlsOptions {
        max_iter: if gauss_newton { 12 } else { 100 },
        ftol: if gauss_newton { 1e-10 } else { 1e-12 },
        xtol: 1e-10,
        gtol: 1e-10,
        gauss_newton,
    }
}

/// Gauss-Newton from a (warm) start, falling back to Levenberg-Marquardt when it fails.
pub fn fit<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    active: &[usize],
    p0: &[f64],
) -> Result<Fit> {
    let np = p0.len();
    let mut e = vec![0.0; rows.len()];
    let mut jac = DMatrix::zeros(rows.len(), np);
    ctx.eval(rows, active, p0, &mut e, &mut jac)?;
    let free: Vec<usize> = (0..np).filter(|&c| jac.column(c).norm() > 0.0).collect();
    let p = if free.is_empty() {
        p0.to_vec()
    } else {
        let anchor = free
            .iter()
            .map(|&c| ANCHOR * jac.column(c).norm())
            .collect();
        let prob = FreeProb {
            ctx,
            rows,
            active,
            free: &free,
            p0,
            anchor,
        };
        let q0: Vec<f64> = free.iter().map(|&c| p0[c]).collect();
        let rep = match solve_nls(&prob, &q0, &nls_opts(true)) {
            Ok(r) if r.converged && r.cost.is_finite() => r,
            _ => solve_nls(&prob, &q0, &nls_opts(false))?,
        };
        prob.full(&rep.params)
    };
    ctx.eval(rows, active, &p, &mut e, &mut jac)?;
    let rss = e.iter().map(|v| v * v).sum();
    Ok(Fit {
        p,
        e,
        jac,
        rss,
        s2: 0.0,
    })
}

/// Range basis, unit covariance and rank of a whitened Jacobian.
pub fn basis(j: &DMatrix<f64>) -> Result<RangeBasis> {
    range_basis(j, 1e-9)
}

// ------------------------------------------------------------------------------------------
// Screening.

/// One candidate's (or structure test's) screening against the current model.
#[derive(Debug, Clone)]
pub struct Screened {
    /// Testable, blind, or too few rows.
    pub status: Status,
    /// Sines of the principal angles between its columns and the model's range, descending.
    pub sines: Vec<f64>,
    /// Directions kept (sine above tolerance).
    pub d: usize,
    /// Score statistic: chi2 reduction of the whitened residual along the kept directions.
    pub score: f64,
    /// F statistic (sigma free).
    pub f: f64,
    /// p-value of the F test.
    pub p_f: f64,
    /// p-value of the chi2 score test.
    pub p_chi2: f64,
    /// p-value used (chi2 or F).
    pub p: f64,
    /// Whether the chi2 form was used for `p`.
    pub chi2_used: bool,
    /// Linearised parameter estimate (minimal norm on the projected columns).
    pub est: Vec<f64>,
    /// Its standard deviations.
    pub std: Vec<f64>,
    /// Orthonormal basis of the kept projected directions (`n x d`).
    pub w: DMatrix<f64>,
    /// Denominator degrees of freedom of the F test.
    pub dof2: f64,
    /// Offset variance of the whitening the test ran in (0: the noise model alone).
    pub s2: f64,
}

/// Fewest degrees of freedom of the remainder after a candidate on which the automatic test
/// checks the noise model (and may then trust it: the chi2 test). On 1 or 2 the check has
/// next to no power: null sessions of 13 and 14 dwells whose noise was 2x the stated named
/// an effect in 58 and 63 of 100 (p < 1e-6 in up to 12), the chi2 test trusting the
/// understated noise; the sigma-free F test is exact whatever the noise's scale.
pub const TRUST_MIN_DOF: f64 = 3.0;

/// Test mode settings after accounting for an unknown noise model.
#[derive(Debug, Clone, Copy)]
pub struct TestCfg {
    /// Which test.
    pub mode: TestMode,
    /// See [`GapOptions::trust_level`].
    pub trust_level: f64,
    /// See [`GapOptions::sine_tol`].
    pub sine_tol: f64,
    /// Compute the linearised estimate of the candidate's parameters.
    pub estimate: bool,
}

impl TestCfg {
    /// The configuration of `opt`, forced to F when the noise level is unknown.
    pub fn of(opt: &GapOptions, noise_known: bool) -> Self {
        TestCfg {
            mode: if noise_known { opt.test } else { TestMode::F },
            trust_level: opt.trust_level,
            sine_tol: opt.sine_tol,
            estimate: false,
        }
    }

    /// The same with `estimate` set.
    pub fn with_estimate(self, estimate: bool) -> Self {
        TestCfg { estimate, ..self }
    }

    /// Whether the noise model is trusted for a residual sum of squares `rss` on `dof`
    /// degrees of freedom: the chi2 test (and the known-noise BIC) apply, else the sigma-free
    /// F test (and BIC). In the automatic mode, a remainder of fewer than [`TRUST_MIN_DOF`]
    /// degrees of freedom cannot check the noise model: F.
    pub fn trusts(&self, rss: f64, dof: f64) -> bool {
        match self.mode {
            TestMode::F => false,
            TestMode::Chi2 => true,
            TestMode::Auto => dof >= TRUST_MIN_DOF && chi2_sf(rss, dof) > self.trust_level,
        }
    }
}

fn empty_screen(n: usize, dim: usize) -> Screened {
    Screened {
        status: Status::Blind,
        sines: vec![],
        d: 0,
        score: 0.0,
        f: f64::NAN,
        p_f: f64::NAN,
        p_chi2: f64::NAN,
        p: f64::NAN,
        chi2_used: false,
        est: vec![f64::NAN; dim],
        std: vec![f64::NAN; dim],
        w: DMatrix::zeros(n, 0),
        dof2: f64::NAN,
        s2: 0.0,
    }
}

/// Orthonormal directions of `range(C)` outside `range(Q)` (principal-angle sine above
/// `sine_tol`), with all the sines.
fn projected_directions(
    c: &DMatrix<f64>,
    q: &DMatrix<f64>,
    sine_tol: f64,
) -> Option<(DMatrix<f64>, Vec<f64>)> {
    let n = c.nrows();
    let norms: Vec<f64> = (0..c.ncols()).map(|i| c.column(i).norm()).collect();
    let nmax = norms.iter().cloned().fold(0.0, f64::max);
    if !(nmax > 0.0) {
        return None;
    }
    let cn = DMatrix::from_fn(n, c.ncols(), |a, i| {
        if norms[i] > 1e-12 * nmax {
            c[(a, i)] / norms[i]
        } else {
            0.0
        }
    });
    // Orthonormal basis of range(C) by Householder QR (columns of unit norm, so the diagonal
    // of R measures what each column adds to the previous ones).
    if n < cn.ncols() || cn.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let (qm, r) = householder_qr(&cn);
    let kc: Vec<usize> = (0..r.nrows().min(r.ncols()))
        .filter(|&i| r[(i, i)].abs() > 1e-8)
        .collect();
    if kc.is_empty() {
        return None;
    }
    let ucn = DMatrix::from_fn(n, kc.len(), |a, b| qm[(a, kc[b])]);
    let p = &ucn - q * (q.transpose() * &ucn);
    let (up, sines, _) = thin_svd(&p).ok()?;
    let kept: Vec<usize> = (0..sines.len()).filter(|&i| sines[i] > sine_tol).collect();
    let w = DMatrix::from_fn(n, kept.len(), |a, b| up[(a, kept[b])]);
    Some((w, sines))
}

/// Relative column norm at or below which a parameter's column counts as zero: the design
/// does not see that parameter at all (finite-difference round-off is ~1e-11 of a seen
/// column's norm; the columns of one effect share its unit).
pub const ZERO_COLUMN: f64 = 1e-9;

/// Which columns of one effect's block `c` the design sees: norm above [`ZERO_COLUMN`] times
/// the block's largest (a centrifuge lever arm across to an axis the spin axis never has a
/// component on has an exactly zero column).
pub fn determined(c: &DMatrix<f64>) -> Vec<bool> {
    let norms: Vec<f64> = (0..c.ncols()).map(|i| c.column(i).norm()).collect();
    let nmax = norms.iter().cloned().fold(0.0, f64::max);
    norms
        .iter()
        .map(|&v| v > ZERO_COLUMN * nmax && v > 0.0)
        .collect()
}

/// Minimal-norm linearised estimate `x = -C_p^+ e` on the projected columns (directions with
/// singular value above `sine_tol` of the largest column norm) and its standard deviations
/// at residual variance `s2`.
fn projected_estimate(
    c: &DMatrix<f64>,
    q: &DMatrix<f64>,
    e: &DVector<f64>,
    s2: f64,
    sine_tol: f64,
) -> (Vec<f64>, Vec<f64>) {
    let k = c.ncols();
    // Each column scaled to unit norm, so that the kept directions are those of the
    // identifiability sines whatever the columns' sizes (K2's x^2, y^2, z^2 columns differ by
    // orders of magnitude on near-axis poses): scaled by the largest column alone, every
    // direction of the small ones was dropped and the estimate read "0 +- 0".
    let norms: Vec<f64> = (0..k).map(|i| c.column(i).norm()).collect();
    let seen = determined(c);
    let mut cn = c.clone();
    for (i, &nrm) in norms.iter().enumerate() {
        if seen[i] {
            cn.column_mut(i).scale_mut(1.0 / nrm);
        } else {
            cn.column_mut(i).fill(0.0);
        }
    }
    let cp = &cn - q * (q.transpose() * &cn);
    let mut est = vec![0.0; k];
    let mut var = vec![0.0; k];
    let mut kept = 0;
    if let Ok((u2, s, vt2)) = thin_svd(&cp) {
        for j in 0..s.len() {
            if !(s[j] > sine_tol) {
                continue;
            }
            kept += 1;
            let coef = -u2.column(j).dot(e) / s[j];
            for i in 0..k {
                est[i] += vt2[(j, i)] * coef;
                var[i] += (vt2[(j, i)] / s[j]).powi(2) * s2;
            }
        }
    }
    // Back to the columns' own scale; NaN where nothing could be estimated.
    let mut std = vec![f64::NAN; k];
    for i in 0..k {
        if kept == 0 || !seen[i] {
            est[i] = f64::NAN;
            continue;
        }
        est[i] /= norms[i];
        std[i] = var[i].sqrt() / norms[i];
    }
    (est, std)
}

/// Screen one candidate's whitened columns `c` against the current model (`b`, residual `e`,
/// `rss`): identifiability, score and F tests, and with `cfg.estimate` the linearised
/// estimate.
pub fn screen(
    c: &DMatrix<f64>,
    b: &RangeBasis,
    e: &DVector<f64>,
    rss: f64,
    cfg: TestCfg,
) -> Screened {
    let n = c.nrows();
    let mut out = empty_screen(n, c.ncols());
    let Some((w, sines)) = projected_directions(c, &b.q, cfg.sine_tol) else {
        return out;
    };
    out.sines = sines;
    let d = w.ncols();
    if d == 0 {
        return out;
    }
    let score = (w.transpose() * e).norm_squared();
    let dof2 = n as f64 - b.rank as f64 - d as f64;
    out.d = d;
    out.score = score;
    out.w = w;
    out.dof2 = dof2;
    if dof2 < 1.0 {
        out.status = Status::TooFewRows;
        return out;
    }
    out.status = Status::Testable;
    let rem = (rss - score).max(1e-300);
    out.f = (score / d as f64) / (rem / dof2);
    out.p_f = f_sf(out.f, d as f64, dof2);
    out.p_chi2 = chi2_sf(score, d as f64);
    out.chi2_used = cfg.trusts(rem, dof2);
    out.p = if out.chi2_used { out.p_chi2 } else { out.p_f };
    if cfg.estimate {
        (out.est, out.std) = projected_estimate(c, &b.q, e, rem / dof2, cfg.sine_tol);
    }
    out
}

/// The min-p family member of a testable screen run in the whitening whose range basis is `q`.
pub fn member_of(sc: &Screened, q: &Arc<DMatrix<f64>>) -> Member {
    Member {
        q: q.clone(),
        w: sc.w.clone(),
        chi2: sc.chi2_used,
        dof2: sc.dof2,
        p: sc.p,
        stat: if sc.chi2_used { sc.score } else { sc.f },
    }
}

// ------------------------------------------------------------------------------------------
// The variance-component whitening.

/// The model at one point in base units (rows whitened by the noise model alone).
#[derive(Debug, Clone)]
pub struct View {
    /// Whitened residual.
    pub e: DVector<f64>,
    /// Whitened Jacobian.
    pub j: DMatrix<f64>,
    /// Noise of each row, physical units.
    pub sig: Vec<f64>,
    /// Range basis of `j`.
    pub b: RangeBasis,
}

impl View {
    /// A view from its parts.
    pub fn new(e: DVector<f64>, j: DMatrix<f64>, sig: Vec<f64>) -> Result<View> {
        let b = basis(&j)?;
        Ok(View { e, j, sig, b })
    }

    /// The space of offset variance `s2` (0: the noise model's own whitening).
    pub fn space(&self, s2: f64) -> Space {
        space(&self.b.q, &self.e, &self.sig, s2)
    }

    /// Offset variance of the model, or of the model with the extra orthonormal directions
    /// `w` (orthogonal to the model's range), by the moment equation ([`pm_offset`]).
    pub fn offset(&self, w: Option<&DMatrix<f64>>, start: f64) -> f64 {
        let q = &self.b.q;
        let b = match w {
            Some(w) if w.ncols() > 0 => {
                let mut b = DMatrix::zeros(q.nrows(), q.ncols() + w.ncols());
                b.columns_mut(0, q.ncols()).copy_from(q);
                b.columns_mut(q.ncols(), w.ncols()).copy_from(w);
                b
            }
            _ => q.clone(),
        };
        let dof = self.e.len() as f64 - b.ncols() as f64;
        pm_offset(&b, self.e.as_slice(), &self.sig, dof, start)
    }
}

/// The model of `ctx` at `p` on `rows`, in base units.
pub fn view<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    active: &[usize],
    p: &[f64],
) -> Result<View> {
    let mut e = vec![0.0; rows.len()];
    let mut j = DMatrix::zeros(rows.len(), p.len());
    ctx.unweighted().eval(rows, active, p, &mut e, &mut j)?;
    let sig = ctx
        .m
        .sigma(rows, active, p)?
        .iter()
        .map(|s| s * ctx.scale)
        .collect();
    View::new(DVector::from_vec(e), j, sig)
}

/// A candidate's test in the whitening of its own model: the offset variance `s2` re-estimated
/// with the candidate's directions in the model (from the base screen `scb`, which must be
/// testable), the candidate's columns `xb` (base units) whitened by it, and the sigma-free F
/// test there (its denominator then estimates the unit variance of a model whose weights are
/// right). Returns the screen and the range basis of its whitening. An offset variance of 0
/// gives the base screen back.
pub fn gls_test(
    xb: &DMatrix<f64>,
    view: &View,
    scb: &Screened,
    qb: &Arc<DMatrix<f64>>,
    start: f64,
    cfg: TestCfg,
) -> (Screened, Arc<DMatrix<f64>>) {
    let s2 = view.offset(Some(&scb.w), start);
    if !(s2 > 0.0) {
        return (scb.clone(), qb.clone());
    }
    let sp = view.space(s2);
    let xf = DMatrix::from_fn(xb.nrows(), xb.ncols(), |k, c| xb[(k, c)] * sp.f[k]);
    let cfg_f = TestCfg {
        mode: TestMode::F,
        ..cfg
    };
    let mut sc = screen(&xf, &sp.basis, &sp.e, sp.rss, cfg_f);
    sc.s2 = s2;
    (sc, Arc::new(sp.basis.q))
}

/// Family-wise adjusted p-value of the best candidate of a stage and whether it is declared.
/// `m_bonf`: the Bonferroni family size. `exact`: always compute the min-p value (on the full
/// data, for the report); otherwise only when Bonferroni does not already decide.
pub fn family_decision(
    fam: &[Member],
    p_best: f64,
    m_bonf: usize,
    opt: &GapOptions,
    exact: bool,
) -> (f64, bool) {
    if !p_best.is_finite() || fam.is_empty() {
        return (f64::NAN, false);
    }
    match opt.correction {
        Correction::Bonferroni => {
            let m = m_bonf.max(1) as f64;
            ((p_best * m).min(1.0), p_best < opt.alpha / m)
        }
        Correction::MinP => {
            let bonf = (p_best * fam.len().max(1) as f64).min(1.0);
            if !exact && !(p_best < opt.alpha) {
                (f64::NAN, false)
            } else if !exact && bonf < opt.alpha {
                (bonf, true)
            } else {
                let pa = min_p(fam, p_best, opt.alpha, opt.n_draws);
                (pa, pa < opt.alpha)
            }
        }
    }
}

// ------------------------------------------------------------------------------------------
// Forward stepwise selection.

/// What one stepwise run selected, and its fits.
#[derive(Debug, Clone)]
pub struct Stepwise {
    /// Selected effects in order.
    pub effects: Vec<usize>,
    /// p-value at which each was selected.
    pub step_p: Vec<f64>,
    /// Family-wise adjusted p-value of each selection.
    pub step_p_adj: Vec<f64>,
    /// Family size at each selection.
    pub step_m: Vec<usize>,
    /// p-value of the best remaining candidate when the selection stopped (NaN: none).
    pub stop_p: f64,
    /// Its adjusted p-value.
    pub stop_p_adj: f64,
    /// Fits after 0, 1, ... selected effects.
    pub history: Vec<Fit>,
    /// Per fit of `history` that was screened: chi2 against the noise model alone (the
    /// calibration re-optimised with the noise model's weights, to first order), the rank of
    /// the Jacobian and the offset variance of the model.
    pub figures: Vec<StageFigures>,
    /// First-stage screening of every candidate (the test each ran).
    pub first: Vec<(usize, Screened)>,
    /// First-stage screening of every candidate in the whitening of the baseline (the common
    /// yardstick of the BIC weights and the ambiguity cosines).
    pub first_null: Vec<(usize, Screened)>,
}

/// Figures of one stage's model (see [`Stepwise::figures`]).
#[derive(Debug, Clone, Copy)]
pub struct StageFigures {
    /// chi2 against the noise model alone.
    pub chi2: f64,
    /// Rank of the Jacobian.
    pub rank: usize,
    /// Offset variance of the model (0 without the variance-component model).
    pub s2: f64,
    /// Residual sum of squares in the model's own offset whitening (= `chi2` when `s2` = 0).
    pub rss_null: f64,
}

/// One stepwise stage's screening: every candidate not yet active, the best (index, p) and
/// the min-p family of the testable ones.
pub struct Stage {
    /// Screen of every candidate not yet active (the test it ran).
    pub screens: Vec<(usize, Screened)>,
    /// The same in the model's own offset whitening (with `want_null`; else empty).
    pub nulls: Vec<(usize, Screened)>,
    /// The base-unit projected directions of every candidate (for its offset variance).
    pub base_w: Vec<(usize, DMatrix<f64>)>,
    /// The testable candidate with the smallest p-value.
    pub best: Option<(usize, f64)>,
    /// The family of testable candidates.
    pub fam: Vec<Member>,
    /// The model's figures.
    pub figures: StageFigures,
    /// The model at this stage, in base units (with the variance-component model only).
    pub view: Option<View>,
}

/// Screen every candidate not yet active against the current fit `cur`: the test in base
/// units (chi2 when the noise model is trusted, see [`screen`]), and, with the
/// variance-component model, an F test that does not trust it in the whitening of the
/// candidate's own model ([`gls_test`]). `want_null`: also screen every candidate in the
/// current model's own whitening.
fn screen_stage<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    cur: &Fit,
    active: &[usize],
    cands: &[usize],
    cfg: TestCfg,
    want_null: bool,
) -> Result<Stage> {
    // Without the variance-component model the fit's own rows are the base whitening.
    let view = if ctx.gls {
        Some(view(ctx, rows, active, &cur.p)?)
    } else {
        None
    };
    let sb = match &view {
        Some(v) => v.space(0.0),
        None => Space {
            s2: 0.0,
            f: vec![],
            basis: basis(&cur.jac)?,
            e: DVector::from_column_slice(&cur.e),
            rss: cur.rss,
        },
    };
    let qb = Arc::new(sb.basis.q.clone());
    let s2m = view.as_ref().map_or(0.0, |v| v.offset(None, cur.s2));
    let sm = view
        .as_ref()
        .filter(|_| want_null && s2m > 0.0)
        .map(|v| v.space(s2m));
    let figures = StageFigures {
        chi2: sb.rss,
        rank: sb.basis.rank,
        s2: s2m,
        rss_null: sm.as_ref().map_or(sb.rss, |x| x.rss),
    };
    let mut st = Stage {
        screens: vec![],
        nulls: vec![],
        base_w: vec![],
        best: None,
        fam: vec![],
        figures,
        view: view.clone(),
    };
    let todo: Vec<usize> = cands
        .iter()
        .copied()
        .filter(|c| !active.contains(c))
        .collect();
    let xbs = ctx.unweighted().columns_of(rows, active, &cur.p, &todo);
    for (&c, xb) in todo.iter().zip(&xbs) {
        let scb = screen(xb, &sb.basis, &sb.e, sb.rss, cfg);
        let (sc, q) = match &view {
            Some(v) if scb.status == Status::Testable && !scb.chi2_used => {
                gls_test(xb, v, &scb, &qb, s2m, cfg)
            }
            _ => (scb.clone(), qb.clone()),
        };
        if want_null {
            let nl = match &sm {
                Some(sm) => {
                    let xf = DMatrix::from_fn(xb.nrows(), xb.ncols(), |k, j| xb[(k, j)] * sm.f[k]);
                    screen(&xf, &sm.basis, &sm.e, sm.rss, cfg.with_estimate(false))
                }
                None => scb.clone(),
            };
            st.nulls.push((c, nl));
        }
        if sc.status == Status::Testable {
            if st.best.is_none_or(|(_, pb)| sc.p < pb || pb.is_nan()) {
                st.best = Some((c, sc.p));
            }
            st.fam.push(member_of(&sc, &q));
        }
        st.base_w.push((c, scb.w));
        st.screens.push((c, sc));
    }
    Ok(st)
}

/// Fit the model with `active` effects from `p0` with the offset variance `s2` in the weights
/// (factors at `at` with `at_active`).
fn fit_weighted<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    active: &[usize],
    p0: &[f64],
    s2: f64,
    (at_active, at): (&[usize], &[f64]),
) -> Result<Fit> {
    let mut f = if s2 > 0.0 {
        fit(
            &ctx.weighted(ctx.factors_at(at_active, at, s2)?),
            rows,
            active,
            p0,
        )?
    } else {
        fit(&ctx.unweighted(), rows, active, p0)?
    };
    f.s2 = s2;
    Ok(f)
}

/// Forward stepwise selection from the baseline fit `base`. `full`: the run on all rows
/// (exact min-p for the report, estimates); otherwise a held-out fold.
pub fn stepwise<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    base: Fit,
    cands: &[usize],
    max_effects: usize,
    cfg: TestCfg,
    full: bool,
) -> Result<Stepwise> {
    let mut sw = Stepwise {
        effects: vec![],
        step_p: vec![],
        step_p_adj: vec![],
        step_m: vec![],
        stop_p: f64::NAN,
        stop_p_adj: f64::NAN,
        history: vec![],
        figures: vec![],
        first: vec![],
        first_null: vec![],
    };
    let mut cur = base;
    let mut m_test = 0usize;
    let e_max = max_effects.min(cands.len());
    for step in 0..=e_max {
        if !full && step == e_max {
            break; // inside a fold nothing more can be selected: no need to screen
        }
        let cfg_s = cfg.with_estimate(full && step == 0);
        let st = screen_stage(
            ctx,
            rows,
            &cur,
            &sw.effects,
            cands,
            cfg_s,
            full && step == 0,
        )?;
        sw.figures.push(st.figures);
        // The offset variance of the best candidate's model, when its test ran in that
        // whitening.
        let best_s2 = st
            .best
            .and_then(|(bc, _)| st.screens.iter().find(|x| x.0 == bc))
            .map(|x| x.1.s2)
            .filter(|v| *v > 0.0);
        let fam = st.fam;
        if step == 0 {
            m_test = fam.len();
            sw.first = st.screens;
            sw.first_null = st.nulls;
        }
        let m_bonf = m_test.saturating_sub(step);
        let pb = st.best.map_or(f64::NAN, |x| x.1);
        let (p_adj, declare) = family_decision(&fam, pb, m_bonf, ctx.opt, full);
        let Some((bc, pb)) = st.best.filter(|_| declare && step < e_max) else {
            sw.stop_p = pb;
            sw.stop_p_adj = p_adj;
            break;
        };
        // The offset variance of the model with the selected effect: from its test when that
        // ran in its own whitening, otherwise re-estimated with its directions.
        let s2 = if !ctx.gls {
            0.0
        } else if let Some(v) = best_s2 {
            v
        } else {
            let w = st.base_w.iter().find(|x| x.0 == bc).map(|x| &x.1);
            st.view.as_ref().map_or(0.0, |v| v.offset(w, st.figures.s2))
        };
        sw.effects.push(bc);
        sw.step_p.push(pb);
        sw.step_p_adj.push(p_adj);
        sw.step_m.push(fam.len());
        let mut p0 = cur.p.clone();
        p0.extend(std::iter::repeat_n(0.0, ctx.m.dictionary()[bc].dim));
        let at_active = sw.effects[..sw.effects.len() - 1].to_vec();
        let next = fit_weighted(ctx, rows, &sw.effects, &p0, s2, (&at_active, &cur.p))?;
        sw.history.push(std::mem::replace(&mut cur, next));
    }
    sw.history.push(cur);
    Ok(sw)
}

// ------------------------------------------------------------------------------------------
// Held-out gap.

/// Leave-one-group-out held-out gap.
#[derive(Debug, Clone)]
pub struct LooReport {
    /// Held-out gap of the baseline (1 for an adequate model).
    pub g_before: f64,
    /// Held-out gap after the accepted selection (redone inside each fold).
    pub g_after: f64,
    /// Held-out RMS of the residual, physical units, baseline.
    pub rms_before: f64,
    /// The same after.
    pub rms_after: f64,
    /// Standardised prediction error per row, baseline (NaN where the fold failed).
    pub z_before: Vec<f64>,
    /// The same after.
    pub z_after: Vec<f64>,
    /// Held-out gap with at most k effects selected in each fold, k = 0, 1, ...
    pub g_steps: Vec<f64>,
    /// How many folds selected each effect (dictionary order).
    pub fold_counts: Vec<usize>,
    /// Folds whose fit failed.
    pub n_failed: usize,
}

/// Held-out z and physical residual of every row, after 0..=k_full effects.
#[derive(Debug, Clone)]
pub struct HeldOut {
    /// `z[k][row]`.
    pub z: Vec<Vec<f64>>,
    /// `r[k][row]` (physical units).
    pub r: Vec<Vec<f64>>,
    /// Folds that selected each effect.
    pub counts: Vec<usize>,
    /// Failed folds.
    pub failed: usize,
}

/// One fold: (left-out rows, [(z, r) per left-out row] per step, selected effects).
type FoldOut = (Vec<usize>, Vec<Vec<(f64, f64)>>, Vec<usize>);

fn one_fold<M: GapModel>(
    ctx: &Ctx<'_, M>,
    left: &[usize],
    inn: &[usize],
    base_p: &[f64],
    cands: &[usize],
    k_full: usize,
    cfg: TestCfg,
) -> Result<FoldOut> {
    let bfit = fit(ctx, inn, &[], base_p)?;
    let swf = stepwise(ctx, inn, bfit, cands, k_full, cfg, false)?;
    let mut steps = Vec::with_capacity(swf.history.len());
    for (k, h) in swf.history.iter().enumerate() {
        let act = &swf.effects[..k];
        let bb = basis(&h.jac)?;
        let mut e = vec![0.0; left.len()];
        let mut j = DMatrix::zeros(left.len(), h.p.len());
        ctx.eval(left, act, &h.p, &mut e, &mut j)?;
        let sig = ctx.m.sigma(left, act, &h.p)?;
        let mut out = Vec::with_capacity(left.len());
        for (a, &ek) in e.iter().enumerate() {
            let jr = j.row(a);
            let q = (jr * &bb.cov * jr.transpose())[(0, 0)].max(0.0);
            out.push((ek / (1.0 + q).sqrt(), ek * ctx.scale * sig[a]));
        }
        steps.push(out);
    }
    Ok((left.to_vec(), steps, swf.effects))
}

/// Leave one group out, redo the selection (at most `k_full` effects) inside every fold, and
/// predict the left-out rows after 0, 1, ... effects.
pub fn held_out<M: GapModel>(
    ctx: &Ctx<'_, M>,
    base_p: &[f64],
    cands: &[usize],
    k_full: usize,
    cfg: TestCfg,
) -> HeldOut {
    use rayon::prelude::*;
    let n = ctx.m.n_rows();
    let mut groups: Vec<usize> = (0..n).map(|r| ctx.m.group(r)).collect();
    groups.sort_unstable();
    groups.dedup();
    let folds: Vec<(Vec<usize>, Result<FoldOut>)> = groups
        .par_iter()
        .map(|&g| {
            let left: Vec<usize> = (0..n).filter(|&r| ctx.m.group(r) == g).collect();
            let inn: Vec<usize> = (0..n).filter(|&r| ctx.m.group(r) != g).collect();
            let res = one_fold(ctx, &left, &inn, base_p, cands, k_full, cfg);
            (left, res)
        })
        .collect();
    let mut ho = HeldOut {
        z: vec![vec![f64::NAN; n]; k_full + 1],
        r: vec![vec![f64::NAN; n]; k_full + 1],
        counts: vec![0; ctx.m.dictionary().len()],
        failed: 0,
    };
    for (_, f) in folds {
        match f {
            Ok((left, steps, effs)) if steps.iter().flatten().all(|x| x.0.is_finite()) => {
                for k in 0..=k_full {
                    let s = &steps[k.min(steps.len() - 1)];
                    for (a, &row) in left.iter().enumerate() {
                        ho.z[k][row] = s[a].0;
                        ho.r[k][row] = s[a].1;
                    }
                }
                effs.iter().for_each(|&c| ho.counts[c] += 1);
            }
            _ => ho.failed += 1,
        }
    }
    ho
}

/// Root mean square of the finite values (NaN when none).
pub fn rms(v: &[f64]) -> f64 {
    let ok: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if ok.is_empty() {
        f64::NAN
    } else {
        (ok.iter().map(|x| x * x).sum::<f64>() / ok.len() as f64).sqrt()
    }
}

// ------------------------------------------------------------------------------------------
// Gate.

/// An effect selected in-sample but rejected by the held-out gate.
#[derive(Debug, Clone, Copy)]
pub struct NotConfirmed {
    /// The effect (dictionary index).
    pub effect: usize,
    /// Its selection p-value.
    pub p: f64,
    /// Held-out gap before it.
    pub g_before: f64,
    /// Held-out gap with it.
    pub g_with: f64,
}

/// Outcome of the held-out gate.
#[derive(Debug, Clone, Copy)]
pub struct GateOutcome {
    /// Number of selected effects accepted.
    pub k_acc: usize,
    /// The first effect rejected, if any.
    pub not_confirmed: Option<NotConfirmed>,
    /// The gate was skipped: a fold keeps fewer than 2 residual degrees of freedom.
    pub skipped: bool,
}

/// Apply the held-out gate to the selection `sw` given the held-out gaps `g_steps` (`n`:
/// rows, `n_max_group`: the largest group, `noise_known`). `cost[k]`: the relative increase of
/// the held-out `G^2` that the k-th selected effect's parameters would cause if they were
/// useless (`d / n` for `d` parameters: leave-one-out charges every fitted parameter about
/// `1 / n`); the effect must lower `G^2` by more than that. `None`: the effect cannot predict a
/// held-out group (its parameters belong to one group) and is not judged held out.
pub fn gate(
    sw: &Stepwise,
    g_steps: &[f64],
    (n, n_max_group, noise_known): (usize, usize, bool),
    cost: &[Option<f64>],
    opt: &GapOptions,
) -> Result<GateOutcome> {
    let k_full = sw.effects.len();
    let mut out = GateOutcome {
        k_acc: k_full,
        not_confirmed: None,
        skipped: false,
    };
    if opt.gate == Gate::Off || k_full == 0 || g_steps.len() != k_full + 1 {
        return Ok(out);
    }
    let rank_full = basis(&sw.history[k_full].jac)?.rank;
    if (n - n_max_group).saturating_sub(rank_full) < 2 {
        out.skipped = true;
        return Ok(out);
    }
    let sd = (2.0 / n as f64).sqrt();
    for k in 1..=k_full {
        let adequate = opt.gate == Gate::Auto && noise_known && {
            let h = &sw.history[k];
            let rk = basis(&h.jac)?.rank;
            n > rk
                && chi2_sf(h.rss, (n - rk) as f64) >= opt.alpha
                && (g_steps[k].powi(2) <= 1.0 + opt.gate_sd * sd
                    || g_steps[k].powi(2) <= g_steps[k - 1].powi(2) + opt.gate_margin * sd)
        };
        let lowers = cost
            .get(k - 1)
            .copied()
            .flatten()
            .is_none_or(|c| g_steps[k].powi(2) < g_steps[k - 1].powi(2) * (1.0 - c));
        if !lowers && !adequate {
            out.k_acc = k - 1;
            out.not_confirmed = Some(NotConfirmed {
                effect: sw.effects[k - 1],
                p: sw.step_p[k - 1],
                g_before: g_steps[k - 1],
                g_with: g_steps[k],
            });
            break;
        }
    }
    Ok(out)
}

// ------------------------------------------------------------------------------------------
// Reports: candidates with BIC weights, ambiguity.

/// One candidate's report (first stepwise stage: single effect against the baseline).
#[derive(Debug, Clone)]
pub struct CandidateReport {
    /// Dictionary index.
    pub effect: usize,
    /// Testable, blind, or why not testable.
    pub status: Status,
    /// The screening.
    pub screen: Screened,
    /// BIC of baseline + this effect (see [`candidate_reports`]; NaN when not testable).
    pub bic: f64,
    /// BIC weight among "none" and the testable candidates.
    pub weight: f64,
    /// Estimated parameters (linearised; re-fitted when selected).
    pub estimate: Vec<f64>,
    /// Their standard deviations.
    pub std: Vec<f64>,
}

/// Candidate reports in dictionary order, BIC of "none" and its weight.
///
/// With `trusted` (the noise model is known and the baseline's residual is consistent with it,
/// the rule of the chi2 test) the BIC is `chi2 + k ln n`, the noise level known. Otherwise it
/// is the sigma-free `n ln(RSS / n) + k ln n`, which is robust to a mis-scaled noise model but
/// rewards a fit that leaves few residual degrees of freedom: with 14 rows and 12 parameters
/// it gave an effect whose chi2 test had p = 0.12 a weight of 1.00.
pub fn candidate_reports<M: GapModel>(
    m: &M,
    first: &[(usize, Screened)],
    unavailable: &[(usize, Status)],
    (chi2, rank0, n): (f64, usize, usize),
    trusted: bool,
) -> (Vec<CandidateReport>, f64, f64) {
    let nf = n as f64;
    let bic_of = |rss: f64, k: f64| {
        if trusted {
            rss + k * nf.ln()
        } else {
            nf * (rss.max(1e-300) / nf).ln() + k * nf.ln()
        }
    };
    let bic_none = bic_of(chi2, rank0 as f64);
    let mut reports = vec![];
    for c in 0..m.dictionary().len() {
        let dim = m.dictionary()[c].dim;
        let (status, screen) = if let Some(&(_, st)) = unavailable.iter().find(|u| u.0 == c) {
            (st, empty_screen(n, dim))
        } else if let Some((_, sc)) = first.iter().find(|f| f.0 == c) {
            (sc.status, sc.clone())
        } else {
            continue; // not requested
        };
        let bic = if status == Status::Testable {
            bic_of(chi2 - screen.score, (rank0 + screen.d) as f64)
        } else {
            f64::NAN
        };
        reports.push(CandidateReport {
            effect: c,
            status,
            estimate: screen.est.clone(),
            std: screen.std.clone(),
            screen,
            bic,
            weight: f64::NAN,
        });
    }
    let bmin = reports
        .iter()
        .filter(|r| r.bic.is_finite())
        .map(|r| r.bic)
        .fold(bic_none, f64::min);
    let wt = |b: f64| (-(b - bmin) / 2.0).exp();
    let wsum = wt(bic_none)
        + reports
            .iter()
            .filter(|r| r.bic.is_finite())
            .map(|r| wt(r.bic))
            .sum::<f64>();
    for r in reports.iter_mut().filter(|r| r.bic.is_finite()) {
        r.weight = wt(r.bic) / wsum;
    }
    (reports, bic_none, wt(bic_none) / wsum)
}

/// A pair the data do not tell apart: the best selected effect and another candidate.
#[derive(Debug, Clone, Copy)]
pub struct Ambiguity {
    /// The selected effect.
    pub best: usize,
    /// The other candidate.
    pub other: usize,
    /// Largest principal-angle cosine between their projected columns.
    pub cosine: f64,
    /// BIC weight of the best against the other alone, `1 / (1 + exp(-(BIC_o - BIC_b) / 2))`.
    pub pair_weight: f64,
}

/// BIC difference below which two candidates that are both significant on their own are not
/// told apart: 10 is the "very strong evidence" boundary of the Bayes-factor scale
/// (2 ln B > 10, Kass and Raftery 1995), a pairwise weight of 0.9933. Settling named K3 at
/// p = 1e-6 with a weight of 0.95 against it while settling's own p was 8.6e-7 (cosine 0.6
/// between their columns): both explain the gap, the data do not say which.
pub const DISTINCT_BIC: f64 = 10.0;

/// Candidates the data do not separate from the first selected effect `best`, by either rule:
///
/// - aliased: the largest principal-angle cosine of their projected columns above
///   `ambiguity_cos`, with similar evidence (a BIC weight at least `ambiguity_weight` times
///   the best's, or a p-value significant on its own, below `alpha / M`, M testable
///   candidates: Bonferroni at the first stage);
/// - both significant: whatever the cosine, the other's p-value significant on its own
///   (below `alpha / M`) and the best's BIC ahead of it by less than [`DISTINCT_BIC`].
pub fn ambiguity(reports: &[CandidateReport], best: usize, opt: &GapOptions) -> Vec<Ambiguity> {
    let Some(rb) = reports.iter().find(|r| r.effect == best) else {
        return vec![];
    };
    if rb.screen.w.ncols() == 0 {
        return vec![];
    }
    let m_test = reports
        .iter()
        .filter(|r| r.status == Status::Testable)
        .count()
        .max(1) as f64;
    let mut out = vec![];
    for r in reports {
        if r.effect == best || r.status != Status::Testable || r.screen.w.ncols() == 0 {
            continue;
        }
        let m = rb.screen.w.transpose() * &r.screen.w;
        let cos = thin_svd(&m).map_or(0.0, |(_, s, _)| s.first().copied().unwrap_or(0.0));
        let significant = r.screen.p < opt.alpha / m_test;
        let similar = r.weight > opt.ambiguity_weight * rb.weight || significant;
        let dbic = r.bic - rb.bic;
        let close = significant && dbic < DISTINCT_BIC;
        if (cos > opt.ambiguity_cos && similar) || close {
            out.push(Ambiguity {
                best,
                other: r.effect,
                cosine: cos,
                pair_weight: 1.0 / (1.0 + (-dbic / 2.0).exp()),
            });
        }
    }
    out
}

// ------------------------------------------------------------------------------------------
// The whole run.

/// Everything the engine measured.
#[derive(Debug, Clone)]
#[cfg_attr(test, derive(Default))]
pub struct EngineResult {
    /// Residual rows.
    pub n: usize,
    /// Baseline parameters.
    pub base_params: Vec<f64>,
    /// Their standard deviations (noise model; scaled when the noise is unknown).
    pub base_std: Vec<f64>,
    /// Standard deviation of each baseline residual, physical units.
    pub sigma: Vec<f64>,
    /// Baseline residuals, physical units.
    pub resid: Vec<f64>,
    /// Baseline whitened residuals.
    pub e: Vec<f64>,
    /// Baseline leverages.
    pub leverage: Vec<f64>,
    /// Baseline chi2.
    pub chi2: f64,
    /// Its degrees of freedom.
    pub dof: usize,
    /// Its p-value (NaN when the noise is unknown).
    pub p_chi2: f64,
    /// Whether the noise level was known.
    pub noise_known: bool,
    /// Common noise scale (1 when known; the baseline residual RMS per dof otherwise).
    pub noise_scale: f64,
    /// Candidate reports (dictionary order of the requested effects).
    pub candidates: Vec<CandidateReport>,
    /// BIC of "none".
    pub bic_none: f64,
    /// BIC weight of "none".
    pub weight_none: f64,
    /// Accepted selection in order.
    pub selected: Vec<usize>,
    /// p-value of each selection.
    pub step_p: Vec<f64>,
    /// Its family-wise adjusted p-value.
    pub step_p_adj: Vec<f64>,
    /// Family size at each selection.
    pub step_m: Vec<usize>,
    /// The first selected effect rejected by the held-out gate.
    pub not_confirmed: Option<NotConfirmed>,
    /// p-value of the best candidate left when the selection stopped.
    pub stop_p: f64,
    /// Its adjusted p-value.
    pub stop_p_adj: f64,
    /// Parameters after the selection (base then each selected effect's).
    pub params_after: Vec<f64>,
    /// Their standard deviations (scaled by the residual variance when it exceeds 1).
    pub std_after: Vec<f64>,
    /// Residuals after, physical units.
    pub resid_after: Vec<f64>,
    /// Whitened residuals after.
    pub e_after: Vec<f64>,
    /// Standard deviation of each residual after, physical units.
    pub sigma_after: Vec<f64>,
    /// Whitened Jacobian after.
    pub jac_after: DMatrix<f64>,
    /// chi2 after.
    pub chi2_after: f64,
    /// Its degrees of freedom.
    pub dof_after: usize,
    /// Its p-value.
    pub p_after: f64,
    /// Aliased candidates of the best.
    pub ambiguous: Vec<Ambiguity>,
    /// Held-out gap (when requested and possible).
    pub loo: Option<LooReport>,
    /// The held-out gate was skipped (folds too small).
    pub gate_skipped: bool,
}

/// Parameter errors, residual noise and degrees of freedom of the accepted model.
#[derive(Debug, Clone)]
pub struct Finished {
    /// Standard deviations of the parameters (scaled by the residual variance above 1).
    pub std: Vec<f64>,
    /// Standard deviation of each residual, physical units.
    pub sigma: Vec<f64>,
    /// Residual degrees of freedom.
    pub dof: usize,
}

/// Final parameter errors and residual noise of the accepted model.
pub fn finish<M: GapModel>(ctx: &Ctx<'_, M>, fin: &Fit, selected: &[usize]) -> Result<Finished> {
    let n = fin.e.len();
    let bf = basis(&fin.jac)?;
    let dof = n.saturating_sub(bf.rank);
    let s2 = if dof > 0 {
        (fin.rss / dof as f64).max(1.0)
    } else {
        1.0
    };
    let std: Vec<f64> = (0..fin.p.len())
        .map(|i| (bf.cov[(i, i)] * s2).sqrt())
        .collect();
    let rows: Vec<usize> = (0..n).collect();
    let sig: Vec<f64> = ctx
        .m
        .sigma(&rows, selected, &fin.p)?
        .iter()
        .map(|s| s * ctx.scale)
        .collect();
    Ok(Finished {
        std,
        sigma: sig,
        dof,
    })
}

fn availability<M: GapModel>(m: &M, effects: &[usize]) -> (Vec<usize>, Vec<(usize, Status)>) {
    let mut cands = vec![];
    let mut unavailable = vec![];
    for &c in effects {
        match m.unavailable(c) {
            Some(st) => unavailable.push((c, st)),
            None => cands.push(c),
        }
    }
    (cands, unavailable)
}

/// Baseline fit, its noise scale and range basis.
fn baseline<M: GapModel>(m: &M, start: &[f64], opt: &GapOptions) -> Result<(Fit, f64, RangeBasis)> {
    let n = m.n_rows();
    let rows: Vec<usize> = (0..n).collect();
    let ctx = Ctx::new(m, 1.0, opt);
    let base = fit(&ctx, &rows, &[], start)?;
    let b0 = basis(&base.jac)?;
    if n <= b0.rank {
        return degenerate(format!(
            "{n} residuals cannot test a {}-parameter calibration (no redundancy)",
            b0.rank
        ));
    }
    let scale = if m.noise_known() {
        1.0
    } else {
        (base.rss / (n - b0.rank) as f64).sqrt().max(1e-300)
    };
    let ctx = Ctx::new(m, scale, opt);
    let base = fit(&ctx, &rows, &[], &base.p)?;
    let b0 = basis(&base.jac)?;
    Ok((base, scale, b0))
}

/// Figures of the baseline fit kept for the report.
struct BaseFigures {
    params: Vec<f64>,
    std: Vec<f64>,
    e: Vec<f64>,
    sigma: Vec<f64>,
    leverage: Vec<f64>,
    chi2: f64,
    dof: usize,
    rank: usize,
}

fn base_figures<M: GapModel>(ctx: &Ctx<'_, M>, base: &Fit, b0: &RangeBasis) -> Result<BaseFigures> {
    let n = base.e.len();
    let rows: Vec<usize> = (0..n).collect();
    Ok(BaseFigures {
        params: base.p.clone(),
        std: (0..ctx.m.n_base()).map(|i| b0.cov[(i, i)].sqrt()).collect(),
        e: base.e.clone(),
        sigma: ctx
            .m
            .sigma(&rows, &[], &base.p)?
            .iter()
            .map(|s| s * ctx.scale)
            .collect(),
        leverage: (0..n).map(|k| b0.q.row(k).norm_squared()).collect(),
        chi2: base.rss,
        dof: n - b0.rank,
        rank: b0.rank,
    })
}

/// Number of held-out groups and the size of the largest.
pub fn group_sizes<M: GapModel>(m: &M) -> (usize, usize) {
    let mut g: Vec<usize> = (0..m.n_rows()).map(|r| m.group(r)).collect();
    g.sort_unstable();
    let mut sizes: Vec<usize> = vec![];
    for (i, &x) in g.iter().enumerate() {
        if i == 0 || g[i - 1] != x {
            sizes.push(0);
        }
        if let Some(s) = sizes.last_mut() {
            *s += 1;
        }
    }
    (sizes.len(), sizes.into_iter().max().unwrap_or(1))
}

/// The held-out gap of every step and the gate's decision on the selection `sw`.
fn held_out_and_gate<M: GapModel>(
    ctx: &Ctx<'_, M>,
    bf: &BaseFigures,
    cands: &[usize],
    sw: &Stepwise,
    cfg: TestCfg,
) -> Result<(Option<HeldOut>, Vec<f64>, GateOutcome)> {
    let n = ctx.m.n_rows();
    let (n_groups, n_max_group) = group_sizes(ctx.m);
    let ho = (ctx.opt.loo && n_groups > 2 && bf.dof > n_max_group)
        .then(|| held_out(ctx, &bf.params, cands, sw.effects.len(), cfg));
    let g_steps: Vec<f64> = ho
        .as_ref()
        .map_or(vec![], |h| h.z.iter().map(|z| rms(z)).collect());
    let cost: Vec<Option<f64>> = sw
        .effects
        .iter()
        .map(|&c| {
            ctx.m
                .predictable(c)
                .then(|| ctx.m.dictionary()[c].dim as f64 / n as f64)
        })
        .collect();
    let go = gate(
        sw,
        &g_steps,
        (n, n_max_group, ctx.m.noise_known()),
        &cost,
        ctx.opt,
    )?;
    Ok((ho, g_steps, go))
}

/// Run the whole diagnosis of model `m` from the baseline start `start`, on the requested
/// `effects` (dictionary indices).
pub fn run<M: GapModel>(
    m: &M,
    start: &[f64],
    effects: &[usize],
    opt: &GapOptions,
) -> Result<EngineResult> {
    opt.validate()?;
    let (base, scale, b0) = baseline(m, start, opt)?;
    let ctx = Ctx::new(m, scale, opt);
    let rows: Vec<usize> = (0..m.n_rows()).collect();
    let cfg = TestCfg::of(opt, m.noise_known());
    let (cands, unavailable) = availability(m, effects);
    // With correlated rows the fits and tests are generalised least squares; the per-row
    // figures of the report (residuals, leverage, localisation, structure) whiten each row
    // by its own noise, at the same parameters.
    let dctx = ctx.diagonal();
    let mut bf = if ctx.corr.is_some() {
        let bd = at(&dctx, &rows, &[], &base.p)?;
        let b0d = basis(&bd.jac)?;
        base_figures(&dctx, &bd, &b0d)?
    } else {
        base_figures(&ctx, &base, &b0)?
    };
    bf.chi2 = base.rss;
    let sw = stepwise(&ctx, &rows, base, &cands, opt.max_effects, cfg, true)?;
    let reports = candidate_reports(
        m,
        &sw.first,
        &unavailable,
        (bf.chi2, bf.rank, m.n_rows()),
        cfg.trusts(bf.chi2, bf.dof as f64),
    );
    let (ho, g_steps, go) = held_out_and_gate(&ctx, &bf, &cands, &sw, cfg)?;
    let selected = sw.effects[..go.k_acc].to_vec();
    let done = finish(&ctx, &sw.history[go.k_acc], &selected)?;
    let fin_rows = if ctx.corr.is_some() {
        at(&dctx, &rows, &selected, &sw.history[go.k_acc].p)?
    } else {
        sw.history[go.k_acc].clone()
    };
    let loo = ho.map(|h| LooReport {
        g_before: g_steps[0],
        g_after: g_steps[go.k_acc],
        rms_before: rms(&h.r[0]),
        rms_after: rms(&h.r[go.k_acc]),
        z_before: h.z[0].clone(),
        z_after: h.z[go.k_acc].clone(),
        g_steps: g_steps.clone(),
        fold_counts: h.counts,
        n_failed: h.failed,
    });
    Ok(assemble(&ctx, bf, reports, &sw, (go, &fin_rows), done, loo))
}

/// The model of `ctx` evaluated at `p` on `rows` (no fitting), as a [`Fit`].
fn at<M: GapModel>(ctx: &Ctx<'_, M>, rows: &[usize], active: &[usize], p: &[f64]) -> Result<Fit> {
    let mut e = vec![0.0; rows.len()];
    let mut jac = DMatrix::zeros(rows.len(), p.len());
    ctx.eval(rows, active, p, &mut e, &mut jac)?;
    let rss = e.iter().map(|v| v * v).sum();
    Ok(Fit {
        p: p.to_vec(),
        e,
        jac,
        rss,
        s2: 0.0,
    })
}

/// The engine's result from its parts (selected effects' estimates and their std from the
/// final fit; the figures after them from `fin_rows`, the final model with each row whitened
/// by its own noise).
fn assemble<M: GapModel>(
    ctx: &Ctx<'_, M>,
    bf: BaseFigures,
    (mut reports, bic_none, weight_none): (Vec<CandidateReport>, f64, f64),
    sw: &Stepwise,
    (go, fin_rows): (GateOutcome, &Fit),
    done: Finished,
    loo: Option<LooReport>,
) -> EngineResult {
    let (m, k) = (ctx.m, go.k_acc);
    let fin = &sw.history[k];
    let selected = sw.effects[..k].to_vec();
    let mut off = m.n_base();
    for &c in &selected {
        let dim = m.dictionary()[c].dim;
        if let Some(r) = reports.iter_mut().find(|r| r.effect == c) {
            // Components the design does not see: not determined (NaN), not "0 +- 1e-15".
            let seen = determined(&fin_rows.jac.columns(off, dim).into_owned());
            let or_nan = |v: &[f64]| -> Vec<f64> {
                v.iter()
                    .zip(&seen)
                    .map(|(&x, &s)| if s { x } else { f64::NAN })
                    .collect()
            };
            r.estimate = or_nan(&fin.p[off..off + dim]);
            r.std = or_nan(&done.std[off..off + dim]);
        }
        off += dim;
    }
    let ambiguous = selected
        .first()
        .map_or(vec![], |&b| ambiguity(&reports, b, ctx.opt));
    let known = m.noise_known();
    EngineResult {
        n: m.n_rows(),
        resid: bf.e.iter().zip(&bf.sigma).map(|(e, s)| e * s).collect(),
        p_chi2: if known {
            chi2_sf(bf.chi2, bf.dof as f64)
        } else {
            f64::NAN
        },
        base_params: bf.params,
        base_std: bf.std,
        sigma: bf.sigma,
        e: bf.e,
        leverage: bf.leverage,
        chi2: bf.chi2,
        dof: bf.dof,
        noise_known: known,
        noise_scale: ctx.scale,
        candidates: reports,
        bic_none,
        weight_none,
        step_p: sw.step_p[..k].to_vec(),
        step_p_adj: sw.step_p_adj[..k].to_vec(),
        step_m: sw.step_m[..k].to_vec(),
        selected,
        not_confirmed: go.not_confirmed,
        stop_p: sw.stop_p,
        stop_p_adj: sw.stop_p_adj,
        params_after: fin.p.clone(),
        std_after: done.std,
        resid_after: fin_rows
            .e
            .iter()
            .zip(&done.sigma)
            .map(|(e, s)| e * s)
            .collect(),
        e_after: fin_rows.e.clone(),
        sigma_after: done.sigma,
        jac_after: fin_rows.jac.clone(),
        chi2_after: fin_rows.rss,
        dof_after: done.dof,
        p_after: if known && done.dof > 0 {
            chi2_sf(fin_rows.rss, done.dof as f64)
        } else {
            f64::NAN
        },
        ambiguous,
        loo,
        gate_skipped: go.skipped,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gap::statics::tests::Rng;

    /// A linear toy system: `y_k = a + b x_k + sum_c theta_c f_c(x_k) + noise`, `x` on
    /// [-0.5, 0.5], known noise 0.1. Effects: quadratic, cubic, "alias" (= x, absorbed by the
    /// baseline: blind), step (a jump at the middle) and "quad2" (x^2 plus a little x^4:
    /// aliased with the quadratic).
    struct Toy {
        x: Vec<f64>,
        y: Vec<f64>,
        known: bool,
        pairs: bool,
        corr: Option<DMatrix<f64>>,
    }

    const DICT: [EffectInfo; 5] = [
        EffectInfo {
            name: "quad",
            unit: "u",
            dim: 1,
        },
        EffectInfo {
            name: "cubic",
            unit: "u",
            dim: 1,
        },
        EffectInfo {
            name: "alias",
            unit: "u",
            dim: 1,
        },
        EffectInfo {
            name: "step",
            unit: "u",
            dim: 1,
        },
        EffectInfo {
            name: "quad2",
            unit: "u",
            dim: 1,
        },
    ];
    const SIG: f64 = 0.1;

    fn f(c: usize, x: f64) -> f64 {
        match c {
            0 => x * x,
            1 => x * x * x,
            2 => x,
            3 => f64::from(u8::from(x > 0.0)),
            _ => x * x + 0.3 * x.powi(4),
        }
    }

    impl Toy {
        fn new(n: usize, effect: Option<(usize, f64)>, seed: u64) -> Self {
            let mut rng = Rng(seed);
            let x: Vec<f64> = (0..n).map(|k| k as f64 / (n - 1) as f64 - 0.5).collect();
            let y = x
                .iter()
                .map(|&xk| {
                    1.0 + 2.0 * xk + effect.map_or(0.0, |(c, a)| a * f(c, xk)) + SIG * rng.normal()
                })
                .collect();
            Toy {
                x,
                y,
                known: true,
                pairs: false,
                corr: None,
            }
        }
    }

    impl GapModel for Toy {
        fn n_rows(&self) -> usize {
            self.x.len()
        }
        fn n_base(&self) -> usize {
            2
        }
        fn dictionary(&self) -> &[EffectInfo] {
            &DICT
        }
        fn unavailable(&self, _c: usize) -> Option<Status> {
            None
        }
        fn group(&self, row: usize) -> usize {
            if self.pairs {
                row / 2
            } else {
                row
            }
        }
        fn noise_known(&self) -> bool {
            self.known
        }
        fn row_correlation(&self) -> Option<&DMatrix<f64>> {
            self.corr.as_ref()
        }
        fn eval(
            &self,
            rows: &[usize],
            active: &[usize],
            p: &[f64],
            e: &mut [f64],
            jac: &mut DMatrix<f64>,
        ) -> Result<()> {
            for (ri, &k) in rows.iter().enumerate() {
                let x = self.x[k];
                let mut m = p[0] + p[1] * x;
                jac[(ri, 0)] = -1.0 / SIG;
                jac[(ri, 1)] = -x / SIG;
                for (j, &c) in active.iter().enumerate() {
                    m += p[2 + j] * f(c, x);
                    jac[(ri, 2 + j)] = -f(c, x) / SIG;
                }
                e[ri] = (self.y[k] - m) / SIG;
            }
            Ok(())
        }
        fn columns(
            &self,
            rows: &[usize],
            _a: &[usize],
            _p: &[f64],
            c: usize,
        ) -> Result<DMatrix<f64>> {
            Ok(DMatrix::from_fn(rows.len(), 1, |ri, _| {
                -f(c, self.x[rows[ri]]) / SIG
            }))
        }
        fn sigma(&self, rows: &[usize], _a: &[usize], _p: &[f64]) -> Result<Vec<f64>> {
            Ok(vec![SIG; rows.len()])
        }
    }

    fn ctx(t: &Toy) -> Ctx<'_, Toy> {
        Ctx::new(t, 1.0, &OPT)
    }
    static OPT: std::sync::LazyLock<GapOptions> = std::sync::LazyLock::new(GapOptions::default);

    fn all(n: usize) -> Vec<usize> {
        (0..n).collect()
    }

    /// Ordinary least squares of `y` on columns (closed form by the normal equations).
    fn ols(cols: &[Vec<f64>], y: &[f64]) -> Vec<f64> {
        let p = cols.len();
        let a = DMatrix::from_fn(p, p, |i, j| {
            cols[i].iter().zip(&cols[j]).map(|(u, v)| u * v).sum()
        });
        let b = DVector::from_fn(p, |i, _| cols[i].iter().zip(y).map(|(u, v)| u * v).sum());
        a.lu().solve(&b).unwrap().as_slice().to_vec()
    }

    /// Residual sum of squares of the weighted least-squares fit of `y` on `cols`.
    fn wls_rss(cols: &[Vec<f64>], y: &[f64], w: &[f64]) -> f64 {
        let sc: Vec<Vec<f64>> = cols
            .iter()
            .map(|c| c.iter().zip(w).map(|(v, wk)| v * wk.sqrt()).collect())
            .collect();
        let ys: Vec<f64> = y.iter().zip(w).map(|(v, wk)| v * wk.sqrt()).collect();
        let b = ols(&sc, &ys);
        (0..y.len())
            .map(|k| (ys[k] - (0..sc.len()).map(|i| sc[i][k] * b[i]).sum::<f64>()).powi(2))
            .sum()
    }

    #[test]
    fn gls_test_is_the_weighted_f_test_at_its_own_offset_variance() {
        // A line plus a quadratic term, heteroscedastic noise and a per-row offset (sd 1.5).
        let n = 60;
        let mut rng = Rng(11);
        let sig: Vec<f64> = (0..n).map(|k| 0.5 + (k % 4) as f64 * 0.5).collect();
        let x: Vec<f64> = (0..n).map(|k| k as f64 / n as f64 - 0.5).collect();
        let session = |off: f64, noise: f64, rng: &mut Rng| -> Vec<f64> {
            (0..n)
                .map(|k| {
                    1.0 + 2.0 * x[k]
                        + 3.0 * x[k] * x[k]
                        + noise * sig[k] * rng.normal()
                        + off * rng.normal()
                })
                .collect()
        };
        let cfg = TestCfg::of(&OPT, true);
        let run = |y: &[f64]| {
            let e = DVector::from_fn(n, |k, _| y[k] / sig[k]);
            let j = DMatrix::from_fn(n, 2, |k, c| [1.0, x[k]][c] / sig[k]);
            let xb = DMatrix::from_fn(n, 1, |k, _| x[k] * x[k] / sig[k]);
            let v = View::new(e, j, sig.clone()).unwrap();
            let sb = v.space(0.0);
            let qb = Arc::new(sb.basis.q.clone());
            let scb = screen(&xb, &sb.basis, &sb.e, sb.rss, cfg);
            let (sc, q) = gls_test(&xb, &v, &scb, &qb, 0.0, cfg);
            (scb, sc, q, qb)
        };
        let y = session(1.5, 1.0, &mut rng);
        let (_, sc, q, qb) = run(&y);
        assert!(sc.s2 > 0.5 && sc.s2 < 6.0, "{}", sc.s2);
        assert!(!Arc::ptr_eq(&q, &qb) && !sc.chi2_used);
        // Independent reference: weighted least squares at weights 1 / (sigma^2 + s2), full
        // and restricted, by the normal equations; at the moment root the full fit's chi2 is
        // n - 3, and F is the usual nested-model F.
        let w: Vec<f64> = sig.iter().map(|s| 1.0 / (s * s + sc.s2)).collect();
        let (one, x2) = (vec![1.0; n], x.iter().map(|v| v * v).collect::<Vec<_>>());
        let rss1 = wls_rss(&[one.clone(), x.clone(), x2], &y, &w);
        let rss0 = wls_rss(&[one, x.clone()], &y, &w);
        assert!((rss1 - (n - 3) as f64).abs() < 1e-6, "{rss1}");
        let f_want = (rss0 - rss1) / (rss1 / (n - 3) as f64);
        assert!((sc.f / f_want - 1.0).abs() < 1e-6, "{} {f_want}", sc.f);
        assert_eq!(sc.dof2, (n - 3) as f64);
        // Without excess over the noise model the base screen comes back unchanged.
        let y = session(0.0, 0.3, &mut rng);
        let (scb, sc, q, qb) = run(&y);
        assert_eq!(sc.s2, 0.0);
        assert_eq!(sc.f, scb.f);
        assert!(Arc::ptr_eq(&q, &qb));
    }

    #[test]
    fn stepwise_with_random_offsets_selects_the_effect_in_its_own_whitening() {
        static RO: std::sync::LazyLock<GapOptions> = std::sync::LazyLock::new(|| GapOptions {
            random_offset: true,
            ..GapOptions::default()
        });
        let mut t = Toy::new(60, Some((3, 1.5)), 5);
        let mut rng = Rng(77);
        t.y.iter_mut().for_each(|y| *y += 3.0 * SIG * rng.normal());
        let c = Ctx::new(&t, 1.0, &RO);
        assert!(c.gls);
        let base = fit(&c, &all(60), &[], &[0.0, 0.0]).unwrap();
        let cfg = TestCfg::of(&RO, true);
        let sw = stepwise(&c, &all(60), base, &[0, 1, 2, 3], 3, cfg, true).unwrap();
        assert_eq!(sw.effects, vec![3]);
        // The offset variance of the model with the effect is near the true 9 SIG^2 (moment
        // estimate); the baseline's also carries the unexplained effect.
        let first = &sw.first.iter().find(|x| x.0 == 3).unwrap().1;
        let s2 = first.s2 / (SIG * SIG);
        assert!(s2 > 4.0 && s2 < 20.0, "{s2}");
        assert!(sw.figures[0].s2 > first.s2 && !first.chi2_used);
        assert!((sw.history[1].s2 - first.s2).abs() < 1e-12);
        assert!(
            (sw.history[1].p[2] - 1.5).abs() < 0.4,
            "{:?}",
            sw.history[1].p
        );
        // The same session without the variance-component model tests in the noise model's
        // whitening (no offset variance anywhere).
        let c0 = ctx(&t);
        let base = fit(&c0, &all(60), &[], &[0.0, 0.0]).unwrap();
        let sw0 = stepwise(&c0, &all(60), base, &[0, 1, 2, 3], 3, cfg, true).unwrap();
        assert!(sw0.first.iter().all(|x| x.1.s2 == 0.0));
        assert!(sw0.figures.iter().all(|f| f.s2 == 0.0));
    }

    #[test]
    fn fit_is_least_squares_and_anchors_unseen_directions() {
        let t = Toy::new(30, Some((0, 0.8)), 1);
        let c = ctx(&t);
        let f1 = fit(&c, &all(30), &[0], &[0.0, 0.0, 0.0]).unwrap();
        let want = ols(
            &[
                vec![1.0; 30],
                t.x.clone(),
                t.x.iter().map(|x| x * x).collect(),
            ],
            &t.y,
        );
        for i in 0..3 {
            assert!((f1.p[i] - want[i]).abs() < 1e-8, "{:?} {want:?}", f1.p);
        }
        // "alias" duplicates the slope: the data see only b + theta. From a start at the
        // least-squares slope, theta stays where it started (minimum-norm change).
        let lin = ols(&[vec![1.0; 30], t.x.clone()], &t.y);
        let f2 = fit(&c, &all(30), &[2], &[lin[0], lin[1], 0.0]).unwrap();
        assert!(f2.p[2].abs() < 1e-6, "{:?}", f2.p);
        assert!((f2.p[1] + f2.p[2] - lin[1]).abs() < 1e-8);
        // From zero the sum still fits.
        let f3 = fit(&c, &all(30), &[2], &[0.0, 0.0, 0.0]).unwrap();
        assert!((f3.p[1] + f3.p[2] - lin[1]).abs() < 1e-8);
    }

    #[test]
    fn basis_rank_and_pseudo_inverse() {
        let j = DMatrix::from_fn(10, 3, |i, c| {
            if c == 2 {
                2.0 * i as f64
            } else {
                [1.0, i as f64][c]
            }
        });
        let b = basis(&j).unwrap();
        assert_eq!(b.rank, 2);
        assert!((b.q.transpose() * &b.q - DMatrix::identity(2, 2)).norm() < 1e-12);
    }

    #[test]
    fn estimates_of_columns_of_very_different_sizes_are_kept() {
        // Two effect columns outside range(Q), one 1e4 times the other: scaled by the
        // largest alone, the small one's direction fell under the tolerance and the estimate
        // read 0 +- 0 for both parameters.
        let n = 12;
        let mut rng = Rng(7);
        let mut q = DMatrix::from_fn(n, 2, |_, _| rng.normal());
        q = q.qr().q().columns(0, 2).into_owned();
        let mut c = DMatrix::from_fn(n, 2, |_, _| rng.normal());
        c.column_mut(0).scale_mut(1e4);
        let theta = [3e-4, 2.5];
        let e =
            -(&c * DVector::from_column_slice(&theta)) + &q * DVector::from_vec(vec![1.0, -2.0]);
        let (est, std) = projected_estimate(&c, &q, &e, 1e-6, 0.05);
        for i in 0..2 {
            assert!(
                (est[i] - theta[i]).abs() < 1e-9 * theta[i].abs().max(1.0),
                "{est:?}"
            );
            assert!(std[i] > 0.0 && std[i].is_finite(), "{std:?}");
        }
        // Nothing outside range(Q): not estimated (NaN), not 0 +- 0.
        let inside = &q * DMatrix::from_fn(2, 2, |_, _| rng.normal());
        let (est, std) = projected_estimate(&inside, &q, &e, 1e-6, 0.05);
        assert!(
            est.iter().chain(&std).all(|v| v.is_nan()),
            "{est:?} {std:?}"
        );
    }

    #[test]
    fn screen_matches_the_closed_form_f_test_and_finds_blind_spots() {
        let t = Toy::new(30, Some((0, 0.5)), 2);
        let c = ctx(&t);
        let base = fit(&c, &all(30), &[], &[0.0, 0.0]).unwrap();
        let b = basis(&base.jac).unwrap();
        let e = DVector::from_column_slice(&base.e);
        let cfg = TestCfg::of(&OPT, true).with_estimate(true);
        let q = screen(
            &c.columns_of(&all(30), &[], &base.p, &[0])[0],
            &b,
            &e,
            base.rss,
            cfg,
        );
        assert_eq!(q.status, Status::Testable);
        // Closed form: F = (RSS0 - RSS1) / (RSS1 / (n - 3)).
        let r1: f64 = {
            let w = ols(
                &[
                    vec![1.0; 30],
                    t.x.clone(),
                    t.x.iter().map(|x| x * x).collect(),
                ],
                &t.y,
            );
            t.x.iter()
                .zip(&t.y)
                .map(|(x, y)| ((y - w[0] - w[1] * x - w[2] * x * x) / SIG).powi(2))
                .sum()
        };
        let f_want = (base.rss - r1) / (r1 / 27.0);
        assert!((q.f - f_want).abs() < 1e-8 * f_want, "{} {f_want}", q.f);
        assert!((q.p_f - f_sf(f_want, 1.0, 27.0)).abs() < 1e-12);
        assert!(
            (q.est[0] - 0.5).abs() < 4.0 * q.std[0],
            "{:?} {:?}",
            q.est,
            q.std
        );
        let a = screen(
            &c.columns_of(&all(30), &[], &base.p, &[2])[0],
            &b,
            &e,
            base.rss,
            cfg,
        );
        assert_eq!(a.status, Status::Blind);
        assert!(a.sines[0] < 1e-8);
    }

    #[test]
    fn the_noise_model_is_trusted_only_on_a_remainder_that_can_check_it() {
        let cfg = TestCfg {
            mode: TestMode::Auto,
            trust_level: 0.02,
            sine_tol: 0.05,
            estimate: false,
        };
        // A remainder at its expected chi2: trusted on 3 degrees of freedom, not on 1 or 2.
        assert!(cfg.trusts(3.0, 3.0));
        assert!(!cfg.trusts(2.0, 2.0) && !cfg.trusts(1.0, 1.0));
        // Beyond the trust level: not trusted however many.
        assert!(!cfg.trusts(60.0, 30.0));
        let chi2 = TestCfg {
            mode: TestMode::Chi2,
            ..cfg
        };
        assert!(chi2.trusts(1.0, 1.0));
    }

    #[test]
    fn whiten_rows_is_the_cholesky_solve_on_the_rows_used() {
        // AR(1) correlation 0.6 on 5 rows.
        let r = DMatrix::from_fn(5, 5, |a, b| 0.6f64.powi((a as i32 - b as i32).abs()));
        let x = DMatrix::from_column_slice(5, 1, &[0.3, -1.2, 0.8, 2.0, -0.5]);
        let quad = |rows: &[usize]| {
            let sub = DMatrix::from_fn(rows.len(), rows.len(), |a, b| r[(rows[a], rows[b])]);
            let xs = DMatrix::from_fn(rows.len(), 1, |a, _| x[(rows[a], 0)]);
            let q = xs.transpose() * sub.try_inverse().unwrap() * &xs;
            let mut w = xs.clone();
            whiten_rows(&r, rows, &mut w).unwrap();
            (w.norm_squared(), q[(0, 0)], w)
        };
        for rows in [vec![0, 1, 2, 3, 4], vec![0, 2, 4], vec![3, 1]] {
            let (a, b, _) = quad(&rows);
            assert!(
                (a - b).abs() < 1e-12 * b.abs().max(1.0),
                "{rows:?}: {a} {b}"
            );
        }
        // One row: left as it is; columns are whitened alike, the first row untouched.
        let (_, _, w) = quad(&[2]);
        assert_eq!(w[(0, 0)], x[(2, 0)]);
        let (_, _, w) = quad(&[0, 1, 2, 3, 4]);
        assert!((w[(0, 0)] - x[(0, 0)]).abs() < 1e-15);
        // Not positive definite: an error, not a panic.
        let bad = DMatrix::from_row_slice(2, 2, &[1.0, 2.0, 2.0, 1.0]);
        let mut y = DMatrix::from_column_slice(2, 1, &[1.0, 1.0]);
        assert!(whiten_rows(&bad, &[0, 1], &mut y).is_err());
    }

    #[test]
    fn correlated_rows_are_fitted_and_tested_by_generalised_least_squares() {
        // Every session carries a shared error along `a` (a quadratic in x, variance 10 noise
        // units along it): mistaken for the "quad" effect when the rows are taken as
        // independent, tested against it when the engine knows their correlation I + a a^T.
        let n = 30;
        let x: Vec<f64> = (0..n).map(|k| k as f64 / (n - 1) as f64 - 0.5).collect();
        let m = x.iter().map(|v| v * v).sum::<f64>() / n as f64;
        let raw: Vec<f64> = x.iter().map(|v| v * v - m).collect();
        let norm = raw.iter().map(|v| v * v).sum::<f64>().sqrt();
        let a: Vec<f64> = raw.iter().map(|v| v / norm * 10f64.sqrt()).collect();
        let corr = DMatrix::identity(n, n) + DMatrix::from_fn(n, n, |i, j| a[i] * a[j]);
        let opt = GapOptions {
            loo: false,
            ..GapOptions::default()
        };
        let (mut named_iid, mut named_gls) = (0, 0);
        let runs = 200;
        let mut shared = Rng(0x2545_F491_4F6C_DD1D);
        for seed in 0..runs {
            let mut t = Toy::new(n, None, 0x9E37_79B9_7F4A_7C15u64.wrapping_mul(seed + 1));
            let u = shared.normal();
            t.y.iter_mut()
                .zip(&a)
                .for_each(|(y, ak)| *y += SIG * u * ak);
            named_iid += usize::from(
                !run(&t, &[0.0, 0.0], &[0, 1, 3], &opt)
                    .unwrap()
                    .selected
                    .is_empty(),
            );
            t.corr = Some(corr.clone());
            let r = run(&t, &[0.0, 0.0], &[0, 1, 3], &opt).unwrap();
            named_gls += usize::from(!r.selected.is_empty());
            // The per-row figures stay each row's own: residual = y - baseline.
            let k = 7;
            let fit_k = r.base_params[0] + r.base_params[1] * t.x[k];
            assert!((r.resid[k] - (t.y[k] - fit_k)).abs() < 1e-9);
        }
        // 114 and 16 of 200 (12 of 200 for the toy without the shared error). Binomial(200,
        // 0.05): mean 10, 99.9 % at most 22.
        assert!(
            named_gls <= 22,
            "{named_gls} of {runs} named with the correlation"
        );
        assert!(named_iid >= 60, "{named_iid} of {runs} named without it");
        // A real effect beside the shared error (a step, not along `a`) is still found, and
        // its estimate is the generalised least-squares one.
        let mut t = Toy::new(n, Some((3, 1.0)), 42);
        t.corr = Some(corr.clone());
        let r = run(&t, &[0.0, 0.0], &[0, 1, 3], &opt).unwrap();
        assert_eq!(r.selected, vec![3]);
        let xm = DMatrix::from_fn(n, 3, |k, c| [1.0, t.x[k], f(3, t.x[k])][c]);
        let ci = corr.clone().try_inverse().unwrap();
        let y = DVector::from_column_slice(&t.y);
        let beta = (xm.transpose() * &ci * &xm).try_inverse().unwrap() * xm.transpose() * &ci * y;
        assert!(
            (r.params_after[2] - beta[2]).abs() < 1e-6,
            "{} {}",
            r.params_after[2],
            beta[2]
        );
    }

    #[test]
    fn family_decision_bonferroni_and_min_p() {
        let q = Arc::new(DMatrix::from_fn(40, 2, |a, b| f64::from(u8::from(a == b))));
        let mk = |k: usize, p: f64| Member {
            q: q.clone(),
            w: DMatrix::from_fn(40, 1, |a, _| f64::from(u8::from(a == k))),
            chi2: true,
            dof2: 30.0,
            p,
            stat: crate::gap::special::chi2_isf(p, 1.0),
        };
        let fam = [mk(5, 0.02), mk(6, 0.5), mk(7, 0.5)];
        let bon = GapOptions {
            correction: Correction::Bonferroni,
            ..GapOptions::default()
        };
        assert_eq!(family_decision(&fam, 0.02, 3, &bon, true), (0.06, false));
        let (pa, dec) = family_decision(&fam, 0.02, 3, &OPT, true);
        assert!(pa > 0.02 && pa <= 0.06 && !dec, "{pa}");
        // A clear case is declared without Monte Carlo inside folds.
        let (pa, dec) = family_decision(&fam, 1e-4, 3, &OPT, false);
        assert!((pa - 3e-4).abs() < 1e-15 && dec);
        assert!(family_decision(&fam, f64::NAN, 3, &OPT, true).0.is_nan());
    }

    #[test]
    fn stepwise_selects_the_hidden_effect_and_records_the_stop() {
        let t = Toy::new(40, Some((3, 0.6)), 3);
        let c = ctx(&t);
        let base = fit(&c, &all(40), &[], &[0.0, 0.0]).unwrap();
        let cfg = TestCfg::of(&OPT, true);
        let sw = stepwise(&c, &all(40), base, &[0, 1, 2, 3], 3, cfg, true).unwrap();
        assert_eq!(sw.effects, vec![3]);
        assert_eq!(sw.history.len(), 2);
        assert!(sw.step_p_adj[0] < 0.05 && sw.stop_p_adj >= 0.05, "{:?}", sw);
        assert_eq!(sw.first.len(), 4);
        assert!(
            (sw.history[1].p[2] - 0.6).abs() < 0.15,
            "{:?}",
            sw.history[1].p
        );
    }

    #[test]
    fn held_out_z_is_the_studentised_residual_for_a_linear_model() {
        let t = Toy::new(25, None, 4);
        let c = ctx(&t);
        let base = fit(&c, &all(25), &[], &[0.0, 0.0]).unwrap();
        let b = basis(&base.jac).unwrap();
        let cfg = TestCfg::of(&OPT, true);
        let ho = held_out(&c, &base.p, &[0, 1, 3], 0, cfg);
        assert_eq!(ho.failed, 0);
        for k in 0..25 {
            let h = b.q.row(k).norm_squared();
            let want = base.e[k] / (1.0 - h).sqrt();
            assert!(
                (ho.z[0][k] - want).abs() < 1e-6,
                "{k}: {} {want}",
                ho.z[0][k]
            );
        }
        let (ng, nmax) = group_sizes(&Toy {
            pairs: true,
            ..Toy::new(6, None, 1)
        });
        assert_eq!((ng, nmax), (3, 2));
    }

    #[test]
    fn gate_rejects_an_effect_that_does_not_predict() {
        let t = Toy::new(30, Some((0, 3.0)), 5);
        let c = ctx(&t);
        let base = fit(&c, &all(30), &[], &[0.0, 0.0]).unwrap();
        let sw = stepwise(&c, &all(30), base, &[0], 1, TestCfg::of(&OPT, true), true).unwrap();
        assert_eq!(sw.effects, vec![0]);
        let strict = GapOptions {
            gate: Gate::Strict,
            ..GapOptions::default()
        };
        let keep = gate(&sw, &[3.0, 1.0], (30, 1, true), &[Some(0.1)], &strict).unwrap();
        assert_eq!(keep.k_acc, 1);
        let drop = gate(&sw, &[1.5, 1.6], (30, 1, true), &[Some(0.1)], &strict).unwrap();
        assert_eq!(drop.k_acc, 0);
        assert_eq!(drop.not_confirmed.unwrap().effect, 0);
        // Auto keeps an effect after which the model is adequate, in-sample and held out.
        let auto = gate(&sw, &[1.05, 1.06], (30, 1, true), &[Some(0.1)], &OPT).unwrap();
        assert_eq!(auto.k_acc, 1);
        // Folds without 2 residual degrees of freedom: skipped.
        let skip = gate(&sw, &[3.0, 1.0], (30, 27, true), &[Some(0.1)], &strict).unwrap();
        assert!(skip.skipped);
        // A decrease smaller than the cost of the effect's parameters is not a confirmation;
        // an effect that cannot predict held out is not judged.
        let small = gate(&sw, &[2.0, 1.99], (30, 1, true), &[Some(0.1)], &strict).unwrap();
        assert_eq!(small.k_acc, 0);
        let per_group = gate(&sw, &[2.0, 2.5], (30, 1, true), &[None], &strict).unwrap();
        assert_eq!(per_group.k_acc, 1);
    }

    /// A testable candidate report with the unit direction `dir` (cosines between reports
    /// are their dot products), p-value `p` and BIC `bic`.
    fn report(effect: usize, dir: &[f64], p: f64, bic: f64) -> CandidateReport {
        let v = DVector::from_column_slice(dir).normalize();
        let mut screen = empty_screen(dir.len(), 1);
        screen.status = Status::Testable;
        screen.p = p;
        screen.w = DMatrix::from_column_slice(dir.len(), 1, v.as_slice());
        CandidateReport {
            effect,
            status: Status::Testable,
            screen,
            bic,
            weight: f64::NAN,
            estimate: vec![],
            std: vec![],
        }
    }

    #[test]
    fn zero_columns_are_not_determined_and_their_estimates_are_nan() {
        // Columns of very different sizes are seen; a zero or round-off column is not.
        let c = DMatrix::from_column_slice(
            4,
            3,
            &[
                1.0, 2.0, 0.5, -1.0, //
                1e-4, -2e-4, 3e-4, 1e-4, //
                1e-13, 0.0, -1e-13, 0.0,
            ],
        );
        assert_eq!(determined(&c), vec![true, true, false]);
        let q = DMatrix::from_column_slice(4, 1, &[0.5, 0.5, 0.5, 0.5]);
        let e = DVector::from_column_slice(&[0.3, -0.1, 0.2, 0.4]);
        let (est, std) = projected_estimate(&c, &q, &e, 1.0, 0.05);
        assert!(est[..2].iter().chain(&std[..2]).all(|v| v.is_finite()));
        assert!(est[2].is_nan() && std[2].is_nan(), "{est:?} +- {std:?}");
    }

    #[test]
    fn ambiguity_names_a_significant_runner_up_close_in_bic_whatever_the_cosine() {
        let opt = GapOptions::default();
        let (a, b, c) = ([1.0, 0.0, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]);
        // Best (0) and a significant runner-up 3 BIC units behind, cosine 0.6: ambiguous.
        let mut reps = vec![report(0, &a, 1e-7, 100.0), report(1, &b, 1e-6, 103.0)];
        reps[0].weight = 0.8;
        reps[1].weight = 0.18;
        let amb = ambiguity(&reps, 0, &opt);
        assert_eq!(amb.len(), 1, "{amb:?}");
        assert_eq!(amb[0].other, 1);
        assert!((amb[0].cosine - 0.6).abs() < 1e-12);
        assert!((amb[0].pair_weight - 1.0 / (1.0 + (-1.5f64).exp())).abs() < 1e-12);
        // Far behind in BIC (beyond DISTINCT_BIC): told apart.
        reps[1].bic = 100.0 + DISTINCT_BIC + 0.5;
        assert!(ambiguity(&reps, 0, &opt).is_empty());
        // Close in BIC but not significant on its own (p above alpha / M): told apart.
        reps[1].bic = 103.0;
        reps[1].screen.p = 0.2;
        reps[1].weight = 0.001;
        assert!(ambiguity(&reps, 0, &opt).is_empty());
        // Orthogonal, significant and close: still ambiguous (the data do not say which).
        let reps = vec![report(0, &a, 1e-7, 100.0), report(2, &c, 1e-6, 101.0)];
        assert_eq!(ambiguity(&reps, 0, &opt).len(), 1);
    }

    #[test]
    fn reports_weights_and_ambiguity() {
        let t = Toy::new(40, Some((0, 3.0)), 6);
        let r = run(&t, &[0.0, 0.0], &[0, 1, 2, 4], &OPT).unwrap();
        assert_eq!(r.selected.first(), Some(&0));
        let wsum: f64 = r.weight_none
            + r.candidates
                .iter()
                .filter(|c| c.weight.is_finite())
                .map(|c| c.weight)
                .sum::<f64>();
        assert!((wsum - 1.0).abs() < 1e-12);
        assert_eq!(
            r.candidates.iter().find(|c| c.effect == 2).unwrap().status,
            Status::Blind
        );
        // quad2 is aliased with quad and has similar evidence.
        assert!(
            r.ambiguous.iter().any(|a| a.other == 4 && a.cosine > 0.9),
            "{:?}",
            r.ambiguous
        );
        assert!(r
            .loo
            .as_ref()
            .is_some_and(|l| l.g_before > 1.5 && l.g_after < 1.3));
        let fin = finish(
            &ctx(&t),
            &fit(&ctx(&t), &all(40), &[0], &r.params_after).unwrap(),
            &[0],
        )
        .unwrap();
        assert_eq!(fin.dof, 37);
        assert!((fin.std[2] - r.std_after[2]).abs() < 1e-12);
    }
}

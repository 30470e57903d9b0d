//! The diagnosis engine shared by every system: fit, screen, select, hold out, gate, report.
//!
//! A system implements [`GapModel`]; [`run`] chains the stages, each its own function with its
//! own unit test: [`fit`], [`basis`], [`screen`], [`family_decision`], [`stepwise`],
//! [`held_out`], [`gate`], [`candidate_reports`] (with BIC weights), [`ambiguity`] and
//! [`finish`].

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::minp::{min_p, Member};
use super::special::{chi2_sf, f_sf};
use super::{Correction, GapOptions, Gate, Status, TestMode};
use crate::error::{degenerate, CoreError, Result};
use crate::lsq::{range_basis, solve_nls, thin_svd, NlsOptions, RangeBasis, Residuals};
use nalgebra::{DMatrix, DVector};

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
    /// Held-out group of a row (rows of one group are left out together).
    fn group(&self, row: usize) -> usize;
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
    /// Standard deviation of each row's residual (physical units) at `p`.
    fn sigma(&self, rows: &[usize], active: &[usize], p: &[f64]) -> Result<Vec<f64>>;
}

/// Number of parameters of the model with `active` effects.
pub fn n_params<M: GapModel>(m: &M, active: &[usize]) -> usize {
    m.n_base() + active.iter().map(|&c| m.dictionary()[c].dim).sum::<usize>()
}

/// The model, its noise scale and the test settings.
pub struct Ctx<'a, M: GapModel> {
    /// The system model.
    pub m: &'a M,
    /// Residuals are divided by this (1 when the noise is known).
    pub scale: f64,
    /// Settings.
    pub opt: &'a GapOptions,
}

impl<M: GapModel> Ctx<'_, M> {
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
        if e.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::NotConverged(
                "the model is not evaluable at these parameters".into(),
            ));
        }
        Ok(())
    }

    fn columns(&self, rows: &[usize], active: &[usize], p: &[f64], c: usize) -> DMatrix<f64> {
        match self.m.columns(rows, active, p, c) {
            Ok(mut x) => {
                x /= self.scale;
                if x.iter().all(|v| v.is_finite()) {
                    x
                } else {
                    DMatrix::zeros(rows.len(), 0)
                }
            }
            Err(_) => DMatrix::zeros(rows.len(), 0),
        }
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
    Ok(Fit { p, e, jac, rss })
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
}

/// Test mode settings after accounting for an unknown noise model.
#[derive(Debug, Clone, Copy)]
pub struct TestCfg {
    /// Which test.
    pub mode: TestMode,
    /// See [`GapOptions::trust_level`].
    pub trust_level: f64,
    /// See [`GapOptions::sine_tol`].
    pub sine_tol: f64,
}

impl TestCfg {
    /// The configuration of `opt`, forced to F when the noise level is unknown.
    pub fn of(opt: &GapOptions, noise_known: bool) -> Self {
        TestCfg {
            mode: if noise_known { opt.test } else { TestMode::F },
            trust_level: opt.trust_level,
            sine_tol: opt.sine_tol,
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
    let (uc, sc, _) = thin_svd(&cn).ok()?;
    let kc: Vec<usize> = (0..sc.len()).filter(|&i| sc[i] > 1e-8).collect();
    if kc.is_empty() {
        return None;
    }
    let ucn = DMatrix::from_fn(n, kc.len(), |a, b| uc[(a, kc[b])]);
    let p = &ucn - q * (q.transpose() * &ucn);
    let (up, sines, _) = thin_svd(&p).ok()?;
    let kept: Vec<usize> = (0..sines.len()).filter(|&i| sines[i] > sine_tol).collect();
    let w = DMatrix::from_fn(n, kept.len(), |a, b| up[(a, kept[b])]);
    Some((w, sines))
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
    let nmax = (0..k).map(|i| c.column(i).norm()).fold(0.0, f64::max);
    let cp = c - q * (q.transpose() * c);
    let mut est = vec![0.0; k];
    let mut var = vec![0.0; k];
    if let Ok((u2, s, vt2)) = thin_svd(&cp) {
        for j in 0..s.len() {
            if !(s[j] > sine_tol * nmax) {
                continue;
            }
            let coef = -u2.column(j).dot(e) / s[j];
            for i in 0..k {
                est[i] += vt2[(j, i)] * coef;
                var[i] += (vt2[(j, i)] / s[j]).powi(2) * s2;
            }
        }
    }
    (est, var.iter().map(|v| v.sqrt()).collect())
}

/// Screen one candidate's whitened columns `c` against the current model (`b`, residual `e`,
/// `rss`): identifiability, score and F tests, and with `estimate` the linearised estimate.
pub fn screen(
    c: &DMatrix<f64>,
    b: &RangeBasis,
    e: &DVector<f64>,
    rss: f64,
    cfg: TestCfg,
    estimate: bool,
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
    out.chi2_used = match cfg.mode {
        TestMode::F => false,
        TestMode::Chi2 => true,
        TestMode::Auto => chi2_sf(rem, dof2) > cfg.trust_level,
    };
    out.p = if out.chi2_used { out.p_chi2 } else { out.p_f };
    if estimate {
        (out.est, out.std) = projected_estimate(c, &b.q, e, rem / dof2, cfg.sine_tol);
    }
    out
}

/// The min-p family member of a testable screen.
pub fn member_of(sc: &Screened) -> Member {
    Member {
        w: sc.w.clone(),
        chi2: sc.chi2_used,
        dof2: sc.dof2,
        p: sc.p,
        stat: if sc.chi2_used { sc.score } else { sc.f },
    }
}

/// Family-wise adjusted p-value of the best candidate of a stage and whether it is declared.
/// `m_bonf`: the Bonferroni family size. `exact`: always compute the min-p value (on the full
/// data, for the report); otherwise only when Bonferroni does not already decide.
pub fn family_decision(
    q: &DMatrix<f64>,
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
                let pa = min_p(q, fam, p_best, opt.alpha, opt.n_draws);
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
    /// First-stage screening of every candidate.
    pub first: Vec<(usize, Screened)>,
}

/// Screen every candidate not yet active; returns the screens, the best (index, p) and the
/// min-p family.
fn screen_stage<M: GapModel>(
    ctx: &Ctx<'_, M>,
    rows: &[usize],
    cur: &Fit,
    b: &RangeBasis,
    active: &[usize],
    cands: &[usize],
    cfg: TestCfg,
    estimate: bool,
) -> (Vec<(usize, Screened)>, Option<(usize, f64)>, Vec<Member>) {
    let ev = DVector::from_column_slice(&cur.e);
    let mut screens = vec![];
    let mut best: Option<(usize, f64)> = None;
    let mut fam = vec![];
    for &c in cands.iter().filter(|c| !active.contains(c)) {
        let cols = ctx.columns(rows, active, &cur.p, c);
        let sc = screen(&cols, b, &ev, cur.rss, cfg, estimate);
        if sc.status == Status::Testable {
            if best.is_none_or(|(_, pb)| sc.p < pb || pb.is_nan()) {
                best = Some((c, sc.p));
            }
            fam.push(member_of(&sc));
        }
        screens.push((c, sc));
    }
    (screens, best, fam)
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
        first: vec![],
    };
    let mut cur = base;
    let mut m_test = 0usize;
    let e_max = max_effects.min(cands.len());
    for step in 0..=e_max {
        if !full && step == e_max {
            break; // inside a fold nothing more can be selected: no need to screen
        }
        let b = basis(&cur.jac)?;
        let (screens, best, fam) = screen_stage(
            ctx,
            rows,
            &cur,
            &b,
            &sw.effects,
            cands,
            cfg,
            full && step == 0,
        );
        if step == 0 {
            m_test = fam.len();
            sw.first = screens;
        }
        let m_bonf = m_test.saturating_sub(step);
        let pb = best.map_or(f64::NAN, |x| x.1);
        let (p_adj, declare) = family_decision(&b.q, &fam, pb, m_bonf, ctx.opt, full);
        let Some((bc, pb)) = best.filter(|_| declare && step < e_max) else {
            sw.stop_p = pb;
            sw.stop_p_adj = p_adj;
            break;
        };
        sw.effects.push(bc);
        sw.step_p.push(pb);
        sw.step_p_adj.push(p_adj);
        sw.step_m.push(fam.len());
        let mut p0 = cur.p.clone();
        p0.extend(std::iter::repeat_n(0.0, ctx.m.dictionary()[bc].dim));
        let next = fit(ctx, rows, &sw.effects, &p0)?;
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

/// Apply the held-out gate to the selection `sw` given the held-out gaps `g_steps`
/// (`n`: rows, `n_max_group`: the largest group, `noise_known`).
pub fn gate(
    sw: &Stepwise,
    g_steps: &[f64],
    n: usize,
    n_max_group: usize,
    noise_known: bool,
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
        if !(g_steps[k] < g_steps[k - 1]) && !adequate {
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
    /// BIC of baseline + this effect (sigma-free form; NaN when not testable).
    pub bic: f64,
    /// BIC weight among "none" and the testable candidates.
    pub weight: f64,
    /// Estimated parameters (linearised; re-fitted when selected).
    pub estimate: Vec<f64>,
    /// Their standard deviations.
    pub std: Vec<f64>,
}

/// Candidate reports in dictionary order, BIC of "none" and its weight.
pub fn candidate_reports<M: GapModel>(
    m: &M,
    first: &[(usize, Screened)],
    unavailable: &[(usize, Status)],
    chi2: f64,
    rank0: usize,
    n: usize,
) -> (Vec<CandidateReport>, f64, f64) {
    let nf = n as f64;
    let bic_of = |rss: f64, k: f64| nf * (rss.max(1e-300) / nf).ln() + k * nf.ln();
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

/// An aliased pair: the best selected effect and another with similar evidence.
#[derive(Debug, Clone, Copy)]
pub struct Ambiguity {
    /// The selected effect.
    pub best: usize,
    /// The aliased candidate.
    pub other: usize,
    /// Largest principal-angle cosine between their projected columns.
    pub cosine: f64,
}

/// Candidates aliased with the first selected effect (cosine above `ambiguity_cos`) whose BIC
/// weight is at least `ambiguity_weight` times the best's.
pub fn ambiguity(reports: &[CandidateReport], best: usize, opt: &GapOptions) -> Vec<Ambiguity> {
    let Some(rb) = reports.iter().find(|r| r.effect == best) else {
        return vec![];
    };
    if rb.screen.w.ncols() == 0 {
        return vec![];
    }
    let mut out = vec![];
    for r in reports {
        if r.effect == best || r.status != Status::Testable || r.screen.w.ncols() == 0 {
            continue;
        }
        let m = rb.screen.w.transpose() * &r.screen.w;
        let cos = thin_svd(&m).map_or(0.0, |(_, s, _)| s.first().copied().unwrap_or(0.0));
        if cos > opt.ambiguity_cos && r.weight > opt.ambiguity_weight * rb.weight {
            out.push(Ambiguity {
                best,
                other: r.effect,
                cosine: cos,
            });
        }
    }
    out
}

// ------------------------------------------------------------------------------------------
// The whole run.

/// Everything the engine measured.
#[derive(Debug, Clone)]
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

/// Final parameters, their errors and residuals of the accepted model.
pub fn finish<M: GapModel>(
    ctx: &Ctx<'_, M>,
    fin: &Fit,
    selected: &[usize],
) -> Result<(Vec<f64>, Vec<f64>, Vec<f64>, usize)> {
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
    Ok((std, sig, fin.e.clone(), dof))
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

/// Baseline fit, noise scale and the derived baseline figures.
fn baseline<M: GapModel>(m: &M, start: &[f64], opt: &GapOptions) -> Result<(Fit, f64, RangeBasis)> {
    let n = m.n_rows();
    let rows: Vec<usize> = (0..n).collect();
    let ctx = Ctx { m, scale: 1.0, opt };
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
    let ctx = Ctx { m, scale, opt };
    let base = fit(&ctx, &rows, &[], &base.p)?;
    let b0 = basis(&base.jac)?;
    Ok((base, scale, b0))
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
    let n = m.n_rows();
    let (base, scale, b0) = baseline(m, start, opt)?;
    let ctx = Ctx { m, scale, opt };
    let rows: Vec<usize> = (0..n).collect();
    let noise_known = m.noise_known();
    let cfg = TestCfg::of(opt, noise_known);
    let (cands, unavailable) = availability(m, effects);
    let base_p = base.p.clone();
    let (chi2, dof) = (base.rss, n - b0.rank);
    let e0 = base.e.clone();
    let sig0: Vec<f64> = m
        .sigma(&rows, &[], &base_p)?
        .iter()
        .map(|s| s * scale)
        .collect();
    let sw = stepwise(&ctx, &rows, base, &cands, opt.max_effects, cfg, true)?;
    let (mut reports, bic_none, weight_none) =
        candidate_reports(m, &sw.first, &unavailable, chi2, b0.rank, n);
    let k_full = sw.effects.len();
    let n_groups = {
        let mut g: Vec<usize> = rows.iter().map(|&r| m.group(r)).collect();
        g.sort_unstable();
        g.dedup();
        g.len()
    };
    let n_max_group = (0..n)
        .map(|g| rows.iter().filter(|&&r| m.group(r) == g).count())
        .max()
        .unwrap_or(1);
    let ho = (opt.loo && n_groups > 2 && dof > n_max_group)
        .then(|| held_out(&ctx, &base_p, &cands, k_full, cfg));
    let g_steps: Vec<f64> = ho
        .as_ref()
        .map_or(vec![], |h| h.z.iter().map(|z| rms(z)).collect());
    let go = gate(&sw, &g_steps, n, n_max_group, noise_known, opt)?;
    let k_acc = go.k_acc;
    let selected = sw.effects[..k_acc].to_vec();
    let fin = &sw.history[k_acc];
    let (std_after, sigma_after, e_after, dof_after) = finish(&ctx, fin, &selected)?;
    let mut off = m.n_base();
    for &c in &selected {
        let dim = m.dictionary()[c].dim;
        if let Some(r) = reports.iter_mut().find(|r| r.effect == c) {
            r.estimate = fin.p[off..off + dim].to_vec();
            r.std = std_after[off..off + dim].to_vec();
        }
        off += dim;
    }
    let ambiguous = selected
        .first()
        .map_or(vec![], |&b| ambiguity(&reports, b, opt));
    let loo = ho.map(|h| LooReport {
        g_before: g_steps[0],
        g_after: g_steps[k_acc],
        rms_before: rms(&h.r[0]),
        rms_after: rms(&h.r[k_acc]),
        z_before: h.z[0].clone(),
        z_after: h.z[k_acc].clone(),
        g_steps: g_steps.clone(),
        fold_counts: h.counts,
        n_failed: h.failed,
    });
    let leverage: Vec<f64> = (0..n).map(|k| b0.q.row(k).norm_squared()).collect();
    let s2b = if noise_known { 1.0 } else { 1.0 };
    Ok(EngineResult {
        n,
        base_std: (0..m.n_base())
            .map(|i| (b0.cov[(i, i)] * s2b).sqrt())
            .collect(),
        base_params: base_p,
        resid: e0.iter().zip(&sig0).map(|(e, s)| e * s).collect(),
        sigma: sig0,
        e: e0,
        leverage,
        chi2,
        dof,
        p_chi2: if noise_known {
            chi2_sf(chi2, dof as f64)
        } else {
            f64::NAN
        },
        noise_known,
        noise_scale: scale,
        candidates: {
            reports.sort_by_key(|r| r.effect);
            reports
        },
        bic_none,
        weight_none,
        step_p: sw.step_p[..k_acc].to_vec(),
        step_p_adj: sw.step_p_adj[..k_acc].to_vec(),
        step_m: sw.step_m[..k_acc].to_vec(),
        selected,
        not_confirmed: go.not_confirmed,
        stop_p: sw.stop_p,
        stop_p_adj: sw.stop_p_adj,
        params_after: fin.p.clone(),
        std_after,
        resid_after: e_after
            .iter()
            .zip(&sigma_after)
            .map(|(e, s)| e * s)
            .collect(),
        e_after,
        sigma_after,
        jac_after: fin.jac.clone(),
        chi2_after: fin.rss,
        dof_after,
        p_after: if noise_known && dof_after > 0 {
            chi2_sf(fin.rss, dof_after as f64)
        } else {
            f64::NAN
        },
        ambiguous,
        loo,
        gate_skipped: go.skipped,
    })
}

//! Least-squares numerics in one reviewable place.
//!
//! - [`lstsq_qr`]: tall linear least squares by Householder QR (faer), with column scaling.
//! - [`solve_nls`]: Levenberg-Marquardt (Marquardt scaling) or undamped Gauss-Newton on a
//!   [`Residuals`] problem with an analytic Jacobian; the small normal systems use nalgebra.
//! - [`svd_report`]: singular values and right singular vectors of a (whitened) Jacobian, for
//!   covariance, conditioning and naming unobservable parameter combinations.

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use crate::error::{degenerate, invalid, CoreError, Result};
use faer::linalg::solvers::SolveLstsq;
use nalgebra::{DMatrix, DVector};

/// Solve `min |A x - b|` for a tall `A` (row-major `m x n`, `m >= n`) by QR.
///
/// Columns are scaled to unit norm first so that the rank test is scale free. Returns
/// [`CoreError::Degenerate`] when a column is zero or `R` is numerically singular.
pub fn lstsq_qr(a: &[f64], m: usize, n: usize, b: &[f64]) -> Result<Vec<f64>> {
    if a.len() != m * n || b.len() != m {
        return invalid(format!(
            "lstsq_qr: design is {} values for {m} x {n}, rhs {}",
            a.len(),
            b.len()
        ));
    }
    if m < n {
        return degenerate(format!(
            "{m} equations cannot determine {n} unknowns (need at least {n})"
        ));
    }
    let mut scale = vec![0.0; n];
    for i in 0..m {
        for j in 0..n {
            scale[j] += a[i * n + j] * a[i * n + j];
        }
    }
    for (j, s) in scale.iter_mut().enumerate() {
        *s = s.sqrt();
        if !(*s > 0.0) || !s.is_finite() {
            return degenerate(format!("design column {j} is zero or not finite"));
        }
    }
    let mat = faer::Mat::<f64>::from_fn(m, n, |i, j| a[i * n + j] / scale[j]);
    let qr = mat.qr();
    let r = qr.thin_R();
    let mut dmax: f64 = 0.0;
    let mut dmin = f64::INFINITY;
    for j in 0..n {
        let d = r[(j, j)].abs();
        dmax = dmax.max(d);
        dmin = dmin.min(d);
    }
    if !(dmin > 1e-13 * dmax) {
        return degenerate(format!(
            "design matrix is numerically singular (R diagonal ratio {:.2e})",
            dmin / dmax
        ));
    }
    let rhs = faer::Mat::<f64>::from_fn(m, 1, |i, _| b[i]);
    let x = qr.solve_lstsq(&rhs);
    Ok((0..n).map(|j| x[(j, 0)] / scale[j]).collect())
}

/// A nonlinear least-squares problem: residuals `r(p)` (already whitened) and Jacobian.
pub trait Residuals {
    /// Number of parameters.
    fn n_params(&self) -> usize;
    /// Number of residuals.
    fn n_residuals(&self) -> usize;
    /// Fill `r` (length `n_residuals`) and `jac` (`n_residuals x n_params`) at `p`.
    fn eval(&self, p: &[f64], r: &mut [f64], jac: &mut DMatrix<f64>) -> Result<()>;
}

/// Solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NlsOptions {
    /// Maximum iterations.
    pub max_iter: usize,
    /// Relative reduction of the cost below which the fit has converged.
    pub ftol: f64,
    /// Relative step size below which the fit has converged.
    pub xtol: f64,
    /// Scaled gradient norm below which the fit has converged.
    pub gtol: f64,
    /// Undamped Gauss-Newton instead of Levenberg-Marquardt.
    pub gauss_newton: bool,
}

impl Default for NlsOptions {
    fn default() -> Self {
        NlsOptions {
            max_iter: 200,
            ftol: 1e-15,
            xtol: 1e-12,
            gtol: 1e-12,
            gauss_newton: false,
        }
    }
}

/// What the solver did.
#[derive(Debug, Clone)]
pub struct NlsReport {
    /// Final parameters.
    pub params: Vec<f64>,
    /// Final residuals.
    pub residuals: Vec<f64>,
    /// Jacobian at the final parameters.
    pub jacobian: DMatrix<f64>,
    /// Sum of squared residuals.
    pub cost: f64,
    /// Iterations taken.
    pub iterations: usize,
    /// True when a tolerance was met (false: iteration limit).
    pub converged: bool,
}

fn sumsq(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Minimise `sum r_i(p)^2` from `p0`.
///
/// Gauss-Newton takes full steps and fails with [`CoreError::NotConverged`] when it diverges
/// (non-finite parameters or cost), as the undamped method can; Levenberg-Marquardt never
/// accepts a step that increases the cost.
pub fn solve_nls<P: Residuals>(prob: &P, p0: &[f64], opt: &NlsOptions) -> Result<NlsReport> {
    let (n, m) = (prob.n_params(), prob.n_residuals());
    if p0.len() != n {
        return invalid(format!("start has {} values, the model {n}", p0.len()));
    }
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    if p0.iter().any(|v| !v.is_finite()) {
        return invalid("start values must be finite");
    }
    let mut p = p0.to_vec();
    let mut r = vec![0.0; m];
    let mut jac = DMatrix::<f64>::zeros(m, n);
    prob.eval(&p, &mut r, &mut jac)?;
    let mut cost = sumsq(&r);
    if !cost.is_finite() {
        return invalid("the model cannot be evaluated at the start values");
    }
    let mut lambda = 1e-3;
    let mut r_new = vec![0.0; m];
    let mut j_new = DMatrix::<f64>::zeros(m, n);
    let mut converged = false;
    let mut it = 0;
    while it < opt.max_iter {
        it += 1;
        let jtj = jac.transpose() * &jac;
        let g = jac.transpose() * DVector::from_column_slice(&r);
        let diag: Vec<f64> = (0..n).map(|i| jtj[(i, i)].max(1e-300)).collect();
        let gnorm = (0..n)
            .map(|i| g[i].abs() / diag[i].sqrt())
            .fold(0.0, f64::max);
        if gnorm <= opt.gtol * cost.sqrt().max(1e-300) || cost == 0.0 {
            converged = true;
            break;
        }
        let mut accepted = false;
        for _ in 0..60 {
            let mut a = jtj.clone();
            if !opt.gauss_newton {
                for i in 0..n {
                    a[(i, i)] += lambda * diag[i];
                }
            }
            let step = match a.clone().cholesky() {
                Some(c) => c.solve(&(-&g)),
                None => match a.lu().solve(&(-&g)) {
                    Some(s) => s,
                    None => {
                        if opt.gauss_newton {
                            return Err(CoreError::NotConverged(
                                "Gauss-Newton: singular normal equations".into(),
                            ));
                        }
                        lambda *= 10.0;
                        continue;
                    }
                },
            };
            let p_new: Vec<f64> = p.iter().zip(step.iter()).map(|(a, b)| a + b).collect();
            if p_new.iter().any(|v| !v.is_finite()) {
                if opt.gauss_newton {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (non-finite parameters)"
                    )));
                }
                lambda *= 10.0;
                continue;
            }
            let ok = prob.eval(&p_new, &mut r_new, &mut j_new).is_ok();
            let c_new = if ok { sumsq(&r_new) } else { f64::INFINITY };
            let pn: f64 = p.iter().map(|v| v * v).sum::<f64>().sqrt();
            let sn: f64 = step.iter().map(|v| v * v).sum::<f64>().sqrt();
            if opt.gauss_newton {
                if !c_new.is_finite() || c_new > 1e300 {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (cost {c_new:.3e})"
                    )));
                }
                let rel = (cost - c_new).abs() / cost.max(1e-300);
                std::mem::swap(&mut r, &mut r_new);
                std::mem::swap(&mut jac, &mut j_new);
                p = p_new;
                cost = c_new;
                accepted = true;
                if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
                    converged = true;
                }
                break;
            }
            if c_new <= cost {
                let rel = (cost - c_new) / cost.max(1e-300);
                std::mem::swap(&mut r, &mut r_new);
                std::mem::swap(&mut jac, &mut j_new);
                p = p_new;
                cost = c_new;
                lambda = (lambda / 3.0).max(1e-12);
                accepted = true;
                if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
                    converged = true;
                }
                break;
            }
            lambda *= 4.0;
            if lambda > 1e16 {
                break;
            }
        }
        if converged {
            break;
        }
        if !accepted {
            // No step decreases the cost at any damping: a (numerical) minimum.
            converged = true;
            break;
        }
    }
    if !converged && opt.gauss_newton {
        return Err(CoreError::NotConverged(format!(
            "Gauss-Newton did not converge in {} iterations",
            opt.max_iter
        )));
    }
    Ok(NlsReport {
        params: p,
        residuals: r,
        jacobian: jac,
        cost,
        iterations: it,
        converged,
    })
}

/// Singular value decomposition of a Jacobian for covariance and observability.
#[derive(Debug, Clone)]
pub struct SvdReport {
    /// Singular values, descending.
    pub s: Vec<f64>,
    /// Right singular vectors as columns (`n x n`), matching `s`.
    pub v: DMatrix<f64>,
}

impl SvdReport {
    /// Condition number `s_max / s_min` (inf when singular).
    pub fn condition(&self) -> f64 {
        let (a, b) = (self.s[0], *self.s.last().unwrap_or(&0.0));
        if b > 0.0 {
            a / b
        } else {
            f64::INFINITY
        }
    }

    /// Indices of singular values below `rtol * s_max` (numerically unobservable directions).
    pub fn null_directions(&self, rtol: f64) -> Vec<usize> {
        let smax = self.s.first().copied().unwrap_or(0.0);
        (0..self.s.len())
            .filter(|&i| !(self.s[i] > rtol * smax))
            .collect()
    }

    /// `(J^T J)^-1 = V diag(1/s^2) V^T`; `None` when a singular value is zero.
    pub fn covariance(&self) -> Option<DMatrix<f64>> {
        let n = self.s.len();
        if self.s.iter().any(|&s| !(s > 0.0)) {
            return None;
        }
        let mut c = DMatrix::<f64>::zeros(n, n);
        for k in 0..n {
            let w = 1.0 / (self.s[k] * self.s[k]);
            for i in 0..n {
                let vik = self.v[(i, k)] * w;
                for j in 0..n {
                    c[(i, j)] += vik * self.v[(j, k)];
                }
            }
        }
        Some(c)
    }
}

/// SVD of `J` (`m x n`, `m >= n`) with columns scaled to unit norm, then unscaled so that
/// the singular vectors refer to the original parameters: returns the SVD of `J` itself when
/// columns are already comparable; the column scaling only stabilises the decomposition.
pub fn svd_report(j: &DMatrix<f64>) -> Result<SvdReport> {
    let (m, n) = (j.nrows(), j.ncols());
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    let mat = faer::Mat::<f64>::from_fn(m, n, |a, b| j[(a, b)]);
    let svd = mat
        .thin_svd()
        .map_err(|_| CoreError::NotConverged("SVD of the Jacobian did not converge".into()))?;
    let s: Vec<f64> = (0..n).map(|i| svd.S()[i]).collect();
    let v = DMatrix::<f64>::from_fn(n, n, |a, b| svd.V()[(a, b)]);
    // faer returns singular values in non-increasing order; keep that contract explicit.
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    let s_sorted = idx.iter().map(|&i| s[i]).collect();
    let v_sorted = DMatrix::<f64>::from_fn(n, n, |a, b| v[(a, idx[b])]);
    Ok(SvdReport {
        s: s_sorted,
        v: v_sorted,
    })
}

// ------------------------------------------------------------------------------------------
// Small dense problems (a few parameters, tens of rows): faer's setup cost dominates there,
// so these use nalgebra's Householder QR and normal equations accumulated by the problem.

/// Rows above which [`lstsq_small`] hands over to [`lstsq_qr`] (faer).
pub const SMALL_ROWS: usize = 256;

/// [`lstsq_qr`] for small designs: same column scaling and rank test, nalgebra Householder
/// QR (no faer set-up cost). Falls back to [`lstsq_qr`] above [`SMALL_ROWS`] rows.
pub fn lstsq_small(a: &[f64], m: usize, n: usize, b: &[f64]) -> Result<Vec<f64>> {
    if m > SMALL_ROWS || a.len() != m * n || b.len() != m || m < n {
        return lstsq_qr(a, m, n, b);
    }
    let mut scale = vec![0.0; n];
    for i in 0..m {
        for j in 0..n {
            scale[j] += a[i * n + j] * a[i * n + j];
        }
    }
    for (j, s) in scale.iter_mut().enumerate() {
        *s = s.sqrt();
        if !(*s > 0.0) || !s.is_finite() {
            return degenerate(format!("design column {j} is zero or not finite"));
        }
    }
    let mat = DMatrix::<f64>::from_fn(m, n, |i, j| a[i * n + j] / scale[j]);
    let qr = mat.qr();
    let r = qr.r();
    let mut dmax: f64 = 0.0;
    let mut dmin = f64::INFINITY;
    for j in 0..n {
        let d = r[(j, j)].abs();
        dmax = dmax.max(d);
        dmin = dmin.min(d);
    }
    if !(dmin > 1e-13 * dmax) {
        return degenerate(format!(
            "design matrix is numerically singular (R diagonal ratio {:.2e})",
            dmin / dmax
        ));
    }
    let mut qtb = DVector::from_column_slice(b);
    qr.q_tr_mul(&mut qtb);
    let mut x = qtb.rows(0, n).into_owned();
    if !r.solve_upper_triangular_mut(&mut x) {
        return degenerate("design matrix is singular");
    }
    Ok((0..n).map(|j| x[j] / scale[j]).collect())
}

/// `(J^T J)^-1` of a small tall `J` by Cholesky of the column-scaled normal matrix (the
/// scaling makes the test scale free); `None` when a pivot falls below `rtol^2` (relative
/// singular value below about `rtol`) or the inverse is not finite.
pub fn covariance_small(j: &DMatrix<f64>, rtol: f64) -> Option<DMatrix<f64>> {
    let (m, n) = (j.nrows(), j.ncols());
    if m < n || n == 0 {
        return None;
    }
    // Normal matrix (column-major J: column dot products).
    let mut a = vec![0.0f64; n * n];
    let col = |k: usize| &j.as_slice()[k * m..(k + 1) * m];
    for p in 0..n {
        for q in p..n {
            let v: f64 = col(p).iter().zip(col(q)).map(|(x, y)| x * y).sum();
            a[p * n + q] = v;
            a[q * n + p] = v;
        }
    }
    let d: Vec<f64> = (0..n).map(|i| a[i * n + i].sqrt()).collect();
    if d.iter().any(|v| !(*v > 0.0) || !v.is_finite()) {
        return None;
    }
    for p in 0..n {
        for q in 0..n {
            a[p * n + q] /= d[p] * d[q];
        }
    }
    // In-place Cholesky (lower), then L^-1, then C = L^-T L^-1.
    for k in 0..n {
        let mut s = a[k * n + k];
        for t in 0..k {
            s -= a[k * n + t] * a[k * n + t];
        }
        if !(s > rtol * rtol) {
            return None;
        }
        let l = s.sqrt();
        a[k * n + k] = l;
        for i in (k + 1)..n {
            let mut v = a[i * n + k];
            for t in 0..k {
                v -= a[i * n + t] * a[k * n + t];
            }
            a[i * n + k] = v / l;
        }
    }
    let mut li = vec![0.0f64; n * n];
    for c in 0..n {
        li[c * n + c] = 1.0 / a[c * n + c];
        for i in (c + 1)..n {
            let mut v = 0.0;
            for t in c..i {
                v -= a[i * n + t] * li[t * n + c];
            }
            li[i * n + c] = v / a[i * n + i];
        }
    }
    let mut c = DMatrix::<f64>::zeros(n, n);
    for p in 0..n {
        for q in p..n {
            let mut v = 0.0;
            for t in q..n {
                v += li[t * n + p] * li[t * n + q];
            }
            v /= d[p] * d[q];
            c[(p, q)] = v;
            c[(q, p)] = v;
        }
    }
    if c.iter().all(|v| v.is_finite()) {
        Some(c)
    } else {
        None
    }
}

/// Largest eigenvalue and its eigenvector of a symmetric positive semi-definite matrix
/// (at most 16 x 16) by power iteration (relative tolerance 1e-9 on the eigenvalue), enough to
/// find the least determined combination of a covariance.
pub fn top_eigen(c: &DMatrix<f64>, iters: usize) -> (f64, Vec<f64>) {
    let n = c.nrows().min(16);
    let mut v = [0.0f64; 16];
    for (i, x) in v.iter_mut().enumerate().take(n) {
        *x = 1.0 + 0.1 * i as f64;
    }
    let mut lam = 0.0;
    for _ in 0..iters {
        let mut w = [0.0f64; 16];
        for i in 0..n {
            w[i] = (0..n).map(|j| c[(i, j)] * v[j]).sum();
        }
        let nv = v[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
        let nw = w[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(nw > 0.0) || !nw.is_finite() {
            return (nw, v[..n].to_vec());
        }
        let new_lam = nw / nv;
        for i in 0..n {
            v[i] = w[i] / nw;
        }
        let done = (new_lam - lam).abs() <= 1e-9 * new_lam;
        lam = new_lam;
        if done {
            break;
        }
    }
    (lam, v[..n].to_vec())
}

/// Solve `(A + damp diag(d)) x = -g` by an in-place Cholesky in `l` (flat `n x n`); false
/// when the damped matrix is not numerically positive definite.
fn chol_solve_damped(
    a: &DMatrix<f64>,
    d: &[f64],
    damp: f64,
    g: &DVector<f64>,
    l: &mut [f64],
    x: &mut [f64],
) -> bool {
    let n = d.len();
    for i in 0..n {
        for j in 0..=i {
            l[i * n + j] = a[(i, j)];
        }
        l[i * n + i] += damp * d[i];
    }
    for k in 0..n {
        let mut s = l[k * n + k];
        for t in 0..k {
            s -= l[k * n + t] * l[k * n + t];
        }
        if !(s > 1e-300) || !(s > 1e-15 * a[(k, k)].abs().max(1e-300) * 1e-3) {
            return false;
        }
        let lk = s.sqrt();
        l[k * n + k] = lk;
        for i in (k + 1)..n {
            let mut v = l[i * n + k];
            for t in 0..k {
                v -= l[i * n + t] * l[k * n + t];
            }
            l[i * n + k] = v / lk;
        }
    }
    // L y = -g, then L^T x = y.
    for i in 0..n {
        let mut v = -g[i];
        for t in 0..i {
            v -= l[i * n + t] * x[t];
        }
        x[i] = v / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = x[i];
        for t in (i + 1)..n {
            v -= l[t * n + i] * x[t];
        }
        x[i] = v / l[i * n + i];
    }
    x.iter().all(|v| v.is_finite())
}

/// A least-squares problem that supplies its normal equations directly: no Jacobian
/// storage and cost-only trial evaluations, for small parameter counts.
pub trait NormalEquations {
    /// Number of parameters.
    fn n_params(&self) -> usize;
    /// Number of residuals.
    fn n_residuals(&self) -> usize;
    /// Sum of squared residuals at `p`.
    fn cost(&self, p: &[f64]) -> Result<f64>;
    /// Fill `J^T J` and `J^T r` at `p`; return the cost.
    fn normal(&self, p: &[f64], jtj: &mut DMatrix<f64>, jtr: &mut DVector<f64>) -> Result<f64>;
}

/// Levenberg-Marquardt / Gauss-Newton on a [`NormalEquations`] problem: the algorithm of
/// [`solve_nls`] (Marquardt scaling, monotone LM, divergence errors for GN) with an initial
/// damping `lambda0` (small when the start is already good, e.g. an exact linear solution).
/// Returns the report without residuals/Jacobian (`jacobian` is empty).
pub fn solve_normal<P: NormalEquations>(
    prob: &P,
    p0: &[f64],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<NlsReport> {
    let (n, m) = (prob.n_params(), prob.n_residuals());
    if p0.len() != n {
        return invalid(format!("start has {} values, the model {n}", p0.len()));
    }
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    if p0.iter().any(|v| !v.is_finite()) {
        return invalid("start values must be finite");
    }
    let mut p = p0.to_vec();
    let mut jtj = DMatrix::<f64>::zeros(n, n);
    let mut g = DVector::<f64>::zeros(n);
    let mut cost = prob.normal(&p, &mut jtj, &mut g).map_err(|_| {
        CoreError::InvalidInput("the model cannot be evaluated at the start values".into())
    })?;
    if !cost.is_finite() {
        return invalid("the model cannot be evaluated at the start values");
    }
    let mut lambda = lambda0;
    let mut converged = false;
    let mut it = 0;
    let mut p_new = vec![0.0; n];
    // Flat work buffers: the damped matrix and its Cholesky factor, the step.
    let mut l = vec![0.0f64; n * n];
    let mut step = vec![0.0f64; n];
    let mut diag = vec![0.0f64; n];
    while it < opt.max_iter {
        it += 1;
        for i in 0..n {
            diag[i] = jtj[(i, i)].max(1e-300);
        }
        let gnorm = (0..n)
            .map(|i| g[i].abs() / diag[i].sqrt())
            .fold(0.0, f64::max);
        if gnorm <= opt.gtol * cost.sqrt().max(1e-300) || cost == 0.0 {
            converged = true;
            break;
        }
        let mut accepted = false;
        for _ in 0..60 {
            let damp = if opt.gauss_newton { 0.0 } else { lambda };
            let solved = chol_solve_damped(&jtj, &diag, damp, &g, &mut l, &mut step);
            if !solved {
                // Not positive definite (GN on a singular problem): general solver.
                let mut a = jtj.clone();
                for i in 0..n {
                    a[(i, i)] += damp * diag[i];
                }
                match a.lu().solve(&(-&g)) {
                    Some(s) => step.copy_from_slice(s.as_slice()),
                    None => {
                        if opt.gauss_newton {
                            return Err(CoreError::NotConverged(
                                "Gauss-Newton: singular normal equations".into(),
                            ));
                        }
                        lambda = lambda.max(1e-12) * 10.0;
                        continue;
                    }
                }
            }
            for i in 0..n {
                p_new[i] = p[i] + step[i];
            }
            if p_new.iter().any(|v| !v.is_finite()) {
                if opt.gauss_newton {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (non-finite parameters)"
                    )));
                }
                lambda = lambda.max(1e-12) * 10.0;
                continue;
            }
            let c_new = prob.cost(&p_new).unwrap_or(f64::INFINITY);
            let pn: f64 = p.iter().map(|v| v * v).sum::<f64>().sqrt();
            let sn: f64 = step.iter().map(|v| v * v).sum::<f64>().sqrt();
            // Predicted reduction of the local quadratic model: when even the full step can
            // only gain a negligible fraction of the cost, take it (if it does not hurt) and stop
            // without another normal-equation evaluation.
            let mut pred = 0.0;
            for i in 0..n {
                let mut hs = 0.0;
                for j in 0..n {
                    hs += jtj[(i, j)] * step[j];
                }
                pred -= g[i] * step[i] + 0.5 * step[i] * hs;
            }
            if c_new <= cost && pred <= opt.ftol * cost {
                std::mem::swap(&mut p, &mut p_new);
                cost = c_new;
                accepted = true;
                converged = true;
                break;
            }
            if opt.gauss_newton {
                if !c_new.is_finite() || c_new > 1e300 {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (cost {c_new:.3e})"
                    )));
                }
            } else if !(c_new <= cost) {
                if sn <= opt.xtol * (pn + opt.xtol) {
                    // Even a negligible step raises the cost: rounding-level minimum.
                    converged = true;
                    break;
                }
                lambda = lambda.max(1e-12) * 4.0;
                if lambda > 1e16 {
                    break;
                }
                continue;
            }
            let rel = (cost - c_new).abs() / cost.max(1e-300);
            std::mem::swap(&mut p, &mut p_new);
            cost = prob.normal(&p, &mut jtj, &mut g)?;
            lambda /= 3.0;
            accepted = true;
            if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
                converged = true;
            }
            break;
        }
        if converged || !accepted {
            converged = true;
            break;
        }
    }
    if !converged && opt.gauss_newton {
        return Err(CoreError::NotConverged(format!(
            "Gauss-Newton did not converge in {} iterations",
            opt.max_iter
        )));
    }
    Ok(NlsReport {
        params: p,
        residuals: Vec::new(),
        jacobian: DMatrix::zeros(0, n),
        cost,
        iterations: it,
        converged,
    })
}

/// Same contract as [`svd_report`] for small problems (a few to a few dozen parameters):
/// Householder QR of `J` (nalgebra), then the SVD of the small `n x n` factor `R`, whose
/// singular values and right singular vectors are those of `J`. Avoids the fixed overhead of
/// the large-matrix path, which dominates microsecond-scale fits.
pub fn svd_report_qr(j: &DMatrix<f64>) -> Result<SvdReport> {
    let (m, n) = (j.nrows(), j.ncols());
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    if j.iter().any(|v| !v.is_finite()) {
        return invalid("the Jacobian is not finite");
    }
    let r = j.clone().qr().r();
    let svd = r.svd(false, true);
    let vt = svd
        .v_t
        .ok_or_else(|| CoreError::NotConverged("SVD of the Jacobian did not converge".into()))?;
    let s: Vec<f64> = svd.singular_values.iter().copied().collect();
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    Ok(SvdReport {
        s: idx.iter().map(|&i| s[i]).collect(),
        v: DMatrix::<f64>::from_fn(n, n, |a, b| vt[(idx[b], a)]),
    })
}

/// Undamped Gauss-Newton on a [`NormalEquations`] problem, with the steps and convergence
/// tests of [`solve_nls`] with `gauss_newton: true` (`opt.gauss_newton` is ignored). GN accepts
/// every finite step, so each trial point is evaluated with [`NormalEquations::normal`]
/// directly: one pass over the data per iteration, no Jacobian storage. An error evaluating
/// the start is returned unchanged; divergence (non-finite parameters or cost, or a point
/// the model cannot evaluate), singular normal equations and the iteration limit give
/// [`CoreError::NotConverged`]. The report has no residuals/Jacobian (`jacobian` is empty).
pub fn solve_normal_gn<P: NormalEquations>(
    prob: &P,
    p0: &[f64],
    opt: &NlsOptions,
) -> Result<NlsReport> {
    let (n, m) = (prob.n_params(), prob.n_residuals());
    if p0.len() != n {
        return invalid(format!("start has {} values, the model {n}", p0.len()));
    }
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    if p0.iter().any(|v| !v.is_finite()) {
        return invalid("start values must be finite");
    }
    let mut p = p0.to_vec();
    let mut jtj = DMatrix::<f64>::zeros(n, n);
    let mut g = DVector::<f64>::zeros(n);
    let mut cost = prob.normal(&p, &mut jtj, &mut g)?;
    if !cost.is_finite() {
        return invalid("the model cannot be evaluated at the start values");
    }
    let mut jtj_new = DMatrix::<f64>::zeros(n, n);
    let mut g_new = DVector::<f64>::zeros(n);
    let mut p_new = vec![0.0; n];
    // Cholesky factor (lower triangle of the symmetric normal matrix) and step.
    let mut fac = vec![0.0; n * n];
    let mut step = vec![0.0; n];
    let mut converged = false;
    let mut it = 0;
    while it < opt.max_iter {
        it += 1;
        let gnorm = (0..n)
            .map(|i| g[i].abs() / jtj[(i, i)].max(1e-300).sqrt())
            .fold(0.0, f64::max);
        if gnorm <= opt.gtol * cost.sqrt().max(1e-300) || cost == 0.0 {
            converged = true;
            break;
        }
        fac.copy_from_slice(jtj.as_slice());
        for i in 0..n {
            step[i] = -g[i];
        }
        if !cholesky_small(&mut fac, n) {
            let s = jtj.clone().lu().solve(&(-&g)).ok_or_else(|| {
                CoreError::NotConverged("Gauss-Newton: singular normal equations".into())
            })?;
            step.copy_from_slice(s.as_slice());
        } else {
            cholesky_solve_small(&fac, n, &mut step);
        }
        for i in 0..n {
            p_new[i] = p[i] + step[i];
        }
        if p_new.iter().any(|v| !v.is_finite()) {
            return Err(CoreError::NotConverged(format!(
                "Gauss-Newton diverged at iteration {it} (non-finite parameters)"
            )));
        }
        let c_new = prob
            .normal(&p_new, &mut jtj_new, &mut g_new)
            .unwrap_or(f64::INFINITY);
        if !c_new.is_finite() || c_new > 1e300 {
            return Err(CoreError::NotConverged(format!(
                "Gauss-Newton diverged at iteration {it} (cost {c_new:.3e})"
            )));
        }
        let pn: f64 = p.iter().map(|v| v * v).sum::<f64>().sqrt();
        let sn: f64 = step.iter().map(|v| v * v).sum::<f64>().sqrt();
        let rel = (cost - c_new).abs() / cost.max(1e-300);
        std::mem::swap(&mut p, &mut p_new);
        std::mem::swap(&mut jtj, &mut jtj_new);
        std::mem::swap(&mut g, &mut g_new);
        cost = c_new;
        if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
            converged = true;
            break;
        }
    }
    if !converged {
        return Err(CoreError::NotConverged(format!(
            "Gauss-Newton did not converge in {} iterations",
            opt.max_iter
        )));
    }
    Ok(NlsReport {
        params: p,
        residuals: Vec::new(),
        jacobian: DMatrix::zeros(0, n),
        cost,
        iterations: it,
        converged,
    })
}

/// Cholesky factor `L` (lower, row-major `n x n`, upper part zeroed) of a symmetric positive
/// definite row-major matrix, in place, without allocation. `false` when a pivot is not
/// positive and finite (the matrix is not numerically positive definite).
pub fn cholesky_small(a: &mut [f64], n: usize) -> bool {
    for k in 0..n {
        let mut s = a[k * n + k];
        for t in 0..k {
            s -= a[k * n + t] * a[k * n + t];
        }
        if !(s > 0.0) || !s.is_finite() {
            return false;
        }
        let l = s.sqrt();
        a[k * n + k] = l;
        let inv = 1.0 / l;
        for i in (k + 1)..n {
            let mut v = a[i * n + k];
            for t in 0..k {
                v -= a[i * n + t] * a[k * n + t];
            }
            a[i * n + k] = v * inv;
        }
        for j in (k + 1)..n {
            a[k * n + j] = 0.0;
        }
    }
    true
}

/// Solve `L L^T x = b` in place (`l` from [`cholesky_small`]).
pub fn cholesky_solve_small(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        let mut v = b[i];
        for t in 0..i {
            v -= l[i * n + t] * b[t];
        }
        b[i] = v / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = b[i];
        for t in (i + 1)..n {
            v -= l[t * n + i] * b[t];
        }
        b[i] = v / l[i * n + i];
    }
}

/// `(L L^T)^-1` (row-major `n x n`, symmetric) from the factor of [`cholesky_small`].
pub fn cholesky_inverse_small(l: &[f64], n: usize) -> Vec<f64> {
    // L^-1 (lower), then C = L^-T L^-1.
    let mut li = vec![0.0f64; n * n];
    for c in 0..n {
        li[c * n + c] = 1.0 / l[c * n + c];
        for i in (c + 1)..n {
            let mut v = 0.0;
            for t in c..i {
                v -= l[i * n + t] * li[t * n + c];
            }
            li[i * n + c] = v / l[i * n + i];
        }
    }
    let mut c = vec![0.0f64; n * n];
    for p in 0..n {
        for q in p..n {
            let mut v = 0.0;
            for t in q..n {
                v += li[t * n + p] * li[t * n + q];
            }
            c[p * n + q] = v;
            c[q * n + p] = v;
        }
    }
    c
}

fn pythag(a: f64, b: f64) -> f64 {
    let (x, y) = (a.abs(), b.abs());
    if x > y {
        x * (1.0 + (y / x) * (y / x)).sqrt()
    } else if y == 0.0 {
        0.0
    } else {
        y * (1.0 + (x / y) * (x / y)).sqrt()
    }
}

/// Eigenvalues (ascending) of a small symmetric row-major `n x n` matrix (only its lower
/// triangle is read), without eigenvectors: Householder reduction to tridiagonal form and the
/// implicit QL iteration (the classic tred2 / tqli pair). Much cheaper than a general
/// decomposition for a handful of parameters. `None` if the iteration does not converge or
/// the input is not finite.
pub fn symmetric_eigenvalues_small(a: &[f64], n: usize) -> Option<Vec<f64>> {
    if n == 0 || a.len() != n * n || a.iter().any(|v| !v.is_finite()) {
        return None;
    }
    if n <= 12 {
        return sym_eig_fixed::<12>(a, n);
    }
    if n <= 24 {
        return sym_eig_fixed::<24>(a, n);
    }
    let mut z = a.to_vec();
    let mut d = vec![0.0f64; n];
    let mut e = vec![0.0f64; n];
    // Householder tridiagonalisation (eigenvalues only).
    for i in (1..n).rev() {
        let l = i - 1;
        let mut h = 0.0;
        if l > 0 {
            let scale: f64 = (0..i).map(|k| z[i * n + k].abs()).sum();
            if scale == 0.0 {
                e[i] = z[i * n + l];
            } else {
                for k in 0..i {
                    z[i * n + k] /= scale;
                    h += z[i * n + k] * z[i * n + k];
                }
                let f = z[i * n + l];
                let g = if f >= 0.0 { -h.sqrt() } else { h.sqrt() };
                e[i] = scale * g;
                h -= f * g;
                z[i * n + l] = f - g;
                let mut f = 0.0;
                for j in 0..i {
                    let mut g = 0.0;
                    for k in 0..=j {
                        g += z[j * n + k] * z[i * n + k];
                    }
                    for k in (j + 1)..i {
                        g += z[k * n + j] * z[i * n + k];
                    }
                    e[j] = g / h;
                    f += e[j] * z[i * n + j];
                }
                let hh = f / (h + h);
                for j in 0..i {
                    let f = z[i * n + j];
                    let g = e[j] - hh * f;
                    e[j] = g;
                    for k in 0..=j {
                        z[j * n + k] -= f * e[k] + g * z[i * n + k];
                    }
                }
            }
        } else {
            e[i] = z[i * n + l];
        }
    }
    for i in 0..n {
        d[i] = z[i * n + i];
    }
    // Implicit QL on the tridiagonal matrix (d diagonal, e[1..] sub-diagonal).
    for i in 1..n {
        e[i - 1] = e[i];
    }
    e[n - 1] = 0.0;
    for l in 0..n {
        let mut iter = 0;
        loop {
            let mut m = l;
            while m < n - 1 {
                let dd = d[m].abs() + d[m + 1].abs();
                if e[m].abs() <= f64::EPSILON * dd {
                    break;
                }
                m += 1;
            }
            if m == l {
                break;
            }
            iter += 1;
            if iter > 60 {
                return None;
            }
            let mut g = (d[l + 1] - d[l]) / (2.0 * e[l]);
            let mut r = pythag(g, 1.0);
            g = d[m] - d[l] + e[l] / (g + if g >= 0.0 { r.abs() } else { -r.abs() });
            let (mut s, mut c, mut p) = (1.0f64, 1.0f64, 0.0f64);
            let mut underflow = false;
            let mut i = m;
            while i > l {
                i -= 1;
                let f = s * e[i];
                let b = c * e[i];
                r = pythag(f, g);
                e[i + 1] = r;
                if r == 0.0 {
                    d[i + 1] -= p;
                    e[m] = 0.0;
                    underflow = true;
                    break;
                }
                s = f / r;
                c = g / r;
                g = d[i + 1] - p;
                r = (d[i] - g) * s + 2.0 * c * b;
                p = s * r;
                d[i + 1] = g + p;
                g = c * r - b;
            }
            if underflow {
                continue;
            }
            d[l] -= p;
            e[l] = g;
            e[m] = 0.0;
        }
    }
    d.sort_by(|a, b| a.total_cmp(b));
    d.iter().all(|v| v.is_finite()).then_some(d)
}

#[allow(clippy::needless_range_loop)] // index form mirrors the classic algorithm
fn sym_eig_fixed<const N: usize>(a: &[f64], n: usize) -> Option<Vec<f64>> {
    // Stack storage and n <= N known to the compiler: no allocation, fewer bounds checks.
    let n = n.min(N);
    let mut zz = [[0.0f64; N]; N];
    for i in 0..n {
        zz[i][..n].copy_from_slice(&a[i * n..(i + 1) * n]);
    }
    let mut d = [0.0f64; N];
    let mut e = [0.0f64; N];
    // Householder tridiagonalisation (eigenvalues only).
    for i in (1..n).rev() {
        let l = i - 1;
        let mut h = 0.0;
        if l > 0 {
            let scale: f64 = (0..i).map(|k| zz[i][k].abs()).sum();
            if scale == 0.0 {
                e[i] = zz[i][l];
            } else {
                for k in 0..i {
                    zz[i][k] /= scale;
                    h += zz[i][k] * zz[i][k];
                }
                let f = zz[i][l];
                let g = if f >= 0.0 { -h.sqrt() } else { h.sqrt() };
                e[i] = scale * g;
                h -= f * g;
                zz[i][l] = f - g;
                let mut f = 0.0;
                for j in 0..i {
                    let mut g = 0.0;
                    for k in 0..=j {
                        g += zz[j][k] * zz[i][k];
                    }
                    for k in (j + 1)..i {
                        g += zz[k][j] * zz[i][k];
                    }
                    e[j] = g / h;
                    f += e[j] * zz[i][j];
                }
                let hh = f / (h + h);
                for j in 0..i {
                    let f = zz[i][j];
                    let g = e[j] - hh * f;
                    e[j] = g;
                    for k in 0..=j {
                        zz[j][k] -= f * e[k] + g * zz[i][k];
                    }
                }
            }
        } else {
            e[i] = zz[i][l];
        }
    }
    for i in 0..n {
        d[i] = zz[i][i];
    }
    // Implicit QL on the tridiagonal matrix (d diagonal, e[1..] sub-diagonal).
    for i in 1..n {
        e[i - 1] = e[i];
    }
    e[n - 1] = 0.0;
    for l in 0..n {
        let mut iter = 0;
        loop {
            let mut m = l;
            while m < n - 1 {
                let dd = d[m].abs() + d[m + 1].abs();
                if e[m].abs() <= f64::EPSILON * dd {
                    break;
                }
                m += 1;
            }
            if m == l {
                break;
            }
            iter += 1;
            if iter > 60 {
                return None;
            }
            let mut g = (d[l + 1] - d[l]) / (2.0 * e[l]);
            let mut r = pythag(g, 1.0);
            g = d[m] - d[l] + e[l] / (g + if g >= 0.0 { r.abs() } else { -r.abs() });
            let (mut s, mut c, mut p) = (1.0f64, 1.0f64, 0.0f64);
            let mut underflow = false;
            let mut i = m;
            while i > l {
                i -= 1;
                let f = s * e[i];
                let b = c * e[i];
                r = pythag(f, g);
                e[i + 1] = r;
                if r == 0.0 {
                    d[i + 1] -= p;
                    e[m] = 0.0;
                    underflow = true;
                    break;
                }
                s = f / r;
                c = g / r;
                g = d[i + 1] - p;
                r = (d[i] - g) * s + 2.0 * c * b;
                p = s * r;
                d[i + 1] = g + p;
                g = c * r - b;
            }
            if underflow {
                continue;
            }
            d[l] -= p;
            e[l] = g;
            e[m] = 0.0;
        }
    }
    let mut d = d[..n].to_vec();
    d.sort_by(|a, b| a.total_cmp(b));
    d.iter().all(|v| v.is_finite()).then_some(d)
}

// ------------------------------------------------------------------------------------------
// Fixed-size small problems (parameter count known at compile time, e.g. the 6 or 9 of a
// static fit): the algorithms of `lstsq_small`, `solve_normal`, `covariance_small` and
// `top_eigen` on stack arrays with fully unrollable loops and no heap allocation.

/// Rows up to which [`lstsq_rows`] uses its own QR (more: [`lstsq_small`]).
pub const FIXED_ROWS: usize = 64;

/// [`lstsq_small`] for `C` columns given as rows: same column scaling, rank test and error
/// messages; a plain Householder QR for up to [`FIXED_ROWS`] rows (no matrix set-up cost).
pub fn lstsq_rows<const C: usize>(rows: &[[f64; C]], b: &[f64]) -> Result<[f64; C]> {
    let m = rows.len();
    if m > FIXED_ROWS || b.len() != m || m < C {
        let flat: Vec<f64> = rows.iter().flat_map(|r| r.iter().copied()).collect();
        let x = lstsq_small(&flat, m, C, b)?;
        let mut out = [0.0; C];
        out.copy_from_slice(&x);
        return Ok(out);
    }
    let mut scale = [0.0f64; C];
    for r in rows {
        for j in 0..C {
            scale[j] += r[j] * r[j];
        }
    }
    for (j, s) in scale.iter_mut().enumerate() {
        *s = s.sqrt();
        if !(*s > 0.0) || !s.is_finite() {
            return degenerate(format!("design column {j} is zero or not finite"));
        }
    }
    // Column-major copy (column stride m), scaled.
    let mut a = vec![0.0f64; C * m];
    for (j, col) in a.chunks_exact_mut(m).enumerate() {
        for (x, r) in col.iter_mut().zip(rows) {
            *x = r[j] / scale[j];
        }
    }
    let mut y = b.to_vec();
    let mut rdiag = [0.0f64; C];
    for j in 0..C {
        let (head, tail) = a.split_at_mut((j + 1) * m);
        let v = &mut head[j * m + j..(j + 1) * m];
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 0.0) {
            rdiag[j] = 0.0;
            continue;
        }
        let alpha = if v[0] > 0.0 { -norm } else { norm };
        v[0] -= alpha;
        let vv = v.iter().map(|x| x * x).sum::<f64>();
        if vv > 0.0 {
            let f = 2.0 / vv;
            for col in tail.chunks_exact_mut(m) {
                let c = &mut col[j..m];
                let s = f * v.iter().zip(c.iter()).map(|(a, b)| a * b).sum::<f64>();
                for (ci, vi) in c.iter_mut().zip(v.iter()) {
                    *ci -= s * vi;
                }
            }
            let c = &mut y[j..m];
            let s = f * v.iter().zip(c.iter()).map(|(a, b)| a * b).sum::<f64>();
            for (ci, vi) in c.iter_mut().zip(v.iter()) {
                *ci -= s * vi;
            }
        }
        rdiag[j] = alpha;
    }
    let mut dmax: f64 = 0.0;
    let mut dmin = f64::INFINITY;
    for d in rdiag {
        dmax = dmax.max(d.abs());
        dmin = dmin.min(d.abs());
    }
    if !(dmin > 1e-13 * dmax) {
        return degenerate(format!(
            "design matrix is numerically singular (R diagonal ratio {:.2e})",
            dmin / dmax
        ));
    }
    let mut x = [0.0f64; C];
    for j in (0..C).rev() {
        let mut v = y[j];
        for k in (j + 1)..C {
            v -= a[k * m + j] * x[k];
        }
        x[j] = v / rdiag[j];
    }
    if x.iter().any(|v| !v.is_finite()) {
        return degenerate("design matrix is singular");
    }
    for j in 0..C {
        x[j] /= scale[j];
    }
    Ok(x)
}

/// [`NormalEquations`] with `N` parameters fixed at compile time.
pub trait NormalEquationsFixed<const N: usize> {
    /// Number of residuals.
    fn n_residuals(&self) -> usize;
    /// Sum of squared residuals at `p`.
    fn cost(&self, p: &[f64; N]) -> Result<f64>;
    /// Fill `J^T J` (both triangles) and `J^T r` at `p`; return the cost.
    fn normal(&self, p: &[f64; N], jtj: &mut [[f64; N]; N], jtr: &mut [f64; N]) -> Result<f64>;
}

/// What [`solve_normal_fixed`] did.
#[derive(Debug, Clone, Copy)]
pub struct FixedReport<const N: usize> {
    /// Final parameters.
    pub params: [f64; N],
    /// Sum of squared residuals.
    pub cost: f64,
    /// Iterations taken.
    pub iterations: usize,
    /// True when a tolerance was met (false: iteration limit).
    pub converged: bool,
}

/// `chol_solve_damped` on stack arrays.
#[allow(clippy::needless_range_loop)] // index form of the reference algorithm
fn chol_solve_damped_fixed<const N: usize>(
    a: &[[f64; N]; N],
    d: &[f64; N],
    damp: f64,
    g: &[f64; N],
    x: &mut [f64; N],
) -> bool {
    let mut l = [[0.0f64; N]; N];
    for i in 0..N {
        l[i][..=i].copy_from_slice(&a[i][..=i]);
        l[i][i] += damp * d[i];
    }
    for k in 0..N {
        let mut s = l[k][k];
        for t in 0..k {
            s -= l[k][t] * l[k][t];
        }
        if !(s > 1e-300) || !(s > 1e-15 * a[k][k].abs().max(1e-300) * 1e-3) {
            return false;
        }
        let lk = s.sqrt();
        l[k][k] = lk;
        for i in (k + 1)..N {
            let mut v = l[i][k];
            for t in 0..k {
                v -= l[i][t] * l[k][t];
            }
            l[i][k] = v / lk;
        }
    }
    for i in 0..N {
        let mut v = -g[i];
        for t in 0..i {
            v -= l[i][t] * x[t];
        }
        x[i] = v / l[i][i];
    }
    for i in (0..N).rev() {
        let mut v = x[i];
        for t in (i + 1)..N {
            v -= l[t][i] * x[t];
        }
        x[i] = v / l[i][i];
    }
    x.iter().all(|v| v.is_finite())
}

/// [`solve_normal`] (same steps, damping schedule, convergence tests and errors) for a
/// [`NormalEquationsFixed`] problem, without heap allocation. One addition: a step that
/// raises the cost although its predicted gain is below `ftol * cost` ends the search at once
/// (a rounding-level minimum) instead of raising the damping until the step vanishes.
pub fn solve_normal_fixed<const N: usize, P: NormalEquationsFixed<N>>(
    prob: &P,
    p0: &[f64; N],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<FixedReport<N>> {
    let m = prob.n_residuals();
    if m < N {
        return degenerate(format!(
            "{m} observations cannot determine {N} parameters (need at least {N})"
        ));
    }
    if p0.iter().any(|v| !v.is_finite()) {
        return invalid("start values must be finite");
    }
    let mut p = *p0;
    let mut jtj = [[0.0f64; N]; N];
    let mut g = [0.0f64; N];
    let mut cost = prob.normal(&p, &mut jtj, &mut g).map_err(|_| {
        CoreError::InvalidInput("the model cannot be evaluated at the start values".into())
    })?;
    if !cost.is_finite() {
        return invalid("the model cannot be evaluated at the start values");
    }
    let mut lambda = lambda0;
    let mut converged = false;
    let mut it = 0;
    let mut p_new = [0.0f64; N];
    let mut step = [0.0f64; N];
    let mut diag = [0.0f64; N];
    while it < opt.max_iter {
        it += 1;
        for i in 0..N {
            diag[i] = jtj[i][i].max(1e-300);
        }
        let gnorm = (0..N)
            .map(|i| g[i].abs() / diag[i].sqrt())
            .fold(0.0, f64::max);
        if gnorm <= opt.gtol * cost.sqrt().max(1e-300) || cost == 0.0 {
            converged = true;
            break;
        }
        let mut accepted = false;
        for _ in 0..60 {
            let damp = if opt.gauss_newton { 0.0 } else { lambda };
            if !chol_solve_damped_fixed(&jtj, &diag, damp, &g, &mut step) {
                // Rare (not positive definite): the general solver of `solve_normal`.
                let mut a = DMatrix::<f64>::from_fn(N, N, |i, j| jtj[i][j]);
                for i in 0..N {
                    a[(i, i)] += damp * diag[i];
                }
                let rhs = DVector::<f64>::from_fn(N, |i, _| -g[i]);
                match a.lu().solve(&rhs) {
                    Some(s) => step.copy_from_slice(s.as_slice()),
                    None => {
                        if opt.gauss_newton {
                            return Err(CoreError::NotConverged(
                                "Gauss-Newton: singular normal equations".into(),
                            ));
                        }
                        lambda = lambda.max(1e-12) * 10.0;
                        continue;
                    }
                }
            }
            for i in 0..N {
                p_new[i] = p[i] + step[i];
            }
            if p_new.iter().any(|v| !v.is_finite()) {
                if opt.gauss_newton {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (non-finite parameters)"
                    )));
                }
                lambda = lambda.max(1e-12) * 10.0;
                continue;
            }
            let c_new = prob.cost(&p_new).unwrap_or(f64::INFINITY);
            let pn: f64 = p.iter().map(|v| v * v).sum::<f64>().sqrt();
            let sn: f64 = step.iter().map(|v| v * v).sum::<f64>().sqrt();
            let mut pred = 0.0;
            for i in 0..N {
                let mut hs = 0.0;
                for j in 0..N {
                    hs += jtj[i][j] * step[j];
                }
                pred -= g[i] * step[i] + 0.5 * step[i] * hs;
            }
            if c_new <= cost && pred <= opt.ftol * cost {
                std::mem::swap(&mut p, &mut p_new);
                cost = c_new;
                accepted = true;
                converged = true;
                break;
            }
            if opt.gauss_newton {
                if !c_new.is_finite() || c_new > 1e300 {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (cost {c_new:.3e})"
                    )));
                }
            } else if !(c_new <= cost) {
                // Even the full step can gain only a negligible fraction of the cost and it
                // raises it instead: a rounding-level minimum (no point in raising lambda).
                if sn <= opt.xtol * (pn + opt.xtol) || pred <= opt.ftol * cost {
                    converged = true;
                    break;
                }
                lambda = lambda.max(1e-12) * 4.0;
                if lambda > 1e16 {
                    break;
                }
                continue;
            }
            let rel = (cost - c_new).abs() / cost.max(1e-300);
            std::mem::swap(&mut p, &mut p_new);
            cost = prob.normal(&p, &mut jtj, &mut g)?;
            lambda /= 3.0;
            accepted = true;
            if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
                converged = true;
            }
            break;
        }
        if converged || !accepted {
            converged = true;
            break;
        }
    }
    if !converged && opt.gauss_newton {
        return Err(CoreError::NotConverged(format!(
            "Gauss-Newton did not converge in {} iterations",
            opt.max_iter
        )));
    }
    Ok(FixedReport {
        params: p,
        cost,
        iterations: it,
        converged,
    })
}

/// [`covariance_small`] from the normal matrix `J^T J` itself (fixed size, same column
/// scaling, pivot test and arithmetic): `None` when singular at `rtol` or not finite.
#[allow(clippy::needless_range_loop)] // index form of the reference algorithm
pub fn covariance_normal_fixed<const N: usize>(
    normal: &[[f64; N]; N],
    rtol: f64,
) -> Option<[[f64; N]; N]> {
    let mut a = *normal;
    let mut d = [0.0f64; N];
    for i in 0..N {
        d[i] = a[i][i].sqrt();
        if !(d[i] > 0.0) || !d[i].is_finite() {
            return None;
        }
    }
    for p in 0..N {
        for q in 0..N {
            a[p][q] /= d[p] * d[q];
        }
    }
    for k in 0..N {
        let mut s = a[k][k];
        for t in 0..k {
            s -= a[k][t] * a[k][t];
        }
        if !(s > rtol * rtol) {
            return None;
        }
        let l = s.sqrt();
        a[k][k] = l;
        for i in (k + 1)..N {
            let mut v = a[i][k];
            for t in 0..k {
                v -= a[i][t] * a[k][t];
            }
            a[i][k] = v / l;
        }
    }
    let mut li = [[0.0f64; N]; N];
    for c in 0..N {
        li[c][c] = 1.0 / a[c][c];
        for i in (c + 1)..N {
            let mut v = 0.0;
            for t in c..i {
                v -= a[i][t] * li[t][c];
            }
            li[i][c] = v / a[i][i];
        }
    }
    let mut c = [[0.0f64; N]; N];
    for p in 0..N {
        for q in p..N {
            let mut v = 0.0;
            for t in q..N {
                v += li[t][p] * li[t][q];
            }
            v /= d[p] * d[q];
            c[p][q] = v;
            c[q][p] = v;
        }
    }
    if c.iter().flatten().all(|v| v.is_finite()) {
        Some(c)
    } else {
        None
    }
}

/// [`top_eigen`] on a fixed-size matrix (same start, iteration and tolerance).
pub fn top_eigen_fixed<const N: usize>(c: &[[f64; N]; N], iters: usize) -> (f64, [f64; N]) {
    let mut v = [0.0f64; N];
    for (i, x) in v.iter_mut().enumerate() {
        *x = 1.0 + 0.1 * i as f64;
    }
    let mut lam = 0.0;
    for _ in 0..iters {
        let mut w = [0.0f64; N];
        for i in 0..N {
            w[i] = (0..N).map(|j| c[i][j] * v[j]).sum();
        }
        let nv = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let nw = w.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(nw > 0.0) || !nw.is_finite() {
            return (nw, v);
        }
        let new_lam = nw / nv;
        for i in 0..N {
            v[i] = w[i] / nw;
        }
        let done = (new_lam - lam).abs() <= 1e-9 * new_lam;
        lam = new_lam;
        if done {
            break;
        }
    }
    (lam, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_symmetric_eigenvalues_and_cholesky_match_nalgebra() {
        let mut seed = 0x1234_5678_u64;
        let mut rnd = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 11) as f64) / ((1u64 << 53) as f64) - 0.5
        };
        for n in [1usize, 2, 3, 9, 12, 24] {
            let b = DMatrix::<f64>::from_fn(n + 3, n, |_, _| rnd());
            let a = b.transpose() * &b;
            let flat: Vec<f64> = (0..n * n).map(|k| a[(k / n, k % n)]).collect();
            let mut want: Vec<f64> = a.symmetric_eigenvalues().iter().copied().collect();
            want.sort_by(|x, y| x.total_cmp(y));
            let got = symmetric_eigenvalues_small(&flat, n).unwrap();
            for (g, w) in got.iter().zip(&want) {
                assert!(
                    (g - w).abs() <= 1e-12 * want[n - 1],
                    "{n}: {got:?} {want:?}"
                );
            }
            let mut l = flat.clone();
            assert!(cholesky_small(&mut l, n));
            let inv = cholesky_inverse_small(&l, n);
            let want_inv = a.clone().cholesky().unwrap().inverse();
            let mut x: Vec<f64> = (0..n).map(|i| i as f64 + 1.0).collect();
            cholesky_solve_small(&l, n, &mut x);
            let xw = &want_inv * DVector::from_fn(n, |i, _| i as f64 + 1.0);
            for i in 0..n {
                assert!((x[i] - xw[i]).abs() <= 1e-9 * xw.amax());
                for j in 0..n {
                    assert!((inv[i * n + j] - want_inv[(i, j)]).abs() <= 1e-9 * want_inv.amax());
                }
            }
        }
        // Diagonal and repeated eigenvalues.
        let d = [2.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 5.0];
        assert_eq!(
            symmetric_eigenvalues_small(&d, 3).unwrap(),
            vec![2.0, 2.0, 5.0]
        );
        let mut s = [1.0, 2.0, 2.0, 4.0];
        assert!(!cholesky_small(&mut s, 2));
    }

    #[test]
    fn qr_solves_polynomial_fit_exactly() {
        let xs: Vec<f64> = (0..20).map(|i| i as f64 * 0.1).collect();
        let mut a = Vec::new();
        let mut b = Vec::new();
        for &x in &xs {
            a.extend_from_slice(&[1.0, x, x * x]);
            b.push(2.0 - 3.0 * x + 0.5 * x * x);
        }
        let c = lstsq_qr(&a, 20, 3, &b).unwrap();
        assert!((c[0] - 2.0).abs() < 1e-12 && (c[1] + 3.0).abs() < 1e-12);
        assert!((c[2] - 0.5).abs() < 1e-12);
    }

    #[test]
    fn qr_reports_singular_design() {
        let a = vec![1.0, 2.0, 2.0, 4.0, 3.0, 6.0];
        assert!(matches!(
            lstsq_qr(&a, 3, 2, &[1.0, 2.0, 3.0]),
            Err(CoreError::Degenerate(_))
        ));
    }

    struct Expo {
        t: Vec<f64>,
        y: Vec<f64>,
    }
    impl Residuals for Expo {
        fn n_params(&self) -> usize {
            2
        }
        fn n_residuals(&self) -> usize {
            self.t.len()
        }
        fn eval(&self, p: &[f64], r: &mut [f64], j: &mut DMatrix<f64>) -> Result<()> {
            for (i, (&t, &y)) in self.t.iter().zip(&self.y).enumerate() {
                let e = (-p[1] * t).exp();
                r[i] = p[0] * e - y;
                j[(i, 0)] = e;
                j[(i, 1)] = -p[0] * t * e;
            }
            Ok(())
        }
    }

    #[test]
    fn lm_fits_exponential_and_covariance_is_inverse_normal_matrix() {
        let t: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let y: Vec<f64> = t.iter().map(|t| 3.0 * (-0.7 * t).exp()).collect();
        let prob = Expo { t, y };
        let rep = solve_nls(&prob, &[1.0, 0.1], &NlsOptions::default()).unwrap();
        assert!(rep.converged);
        assert!((rep.params[0] - 3.0).abs() < 1e-9 && (rep.params[1] - 0.7).abs() < 1e-9);
        let svd = svd_report(&rep.jacobian).unwrap();
        let c = svd.covariance().unwrap();
        let jtj = rep.jacobian.transpose() * &rep.jacobian;
        let id = &jtj * &c;
        for i in 0..2 {
            for k in 0..2 {
                let want = if i == k { 1.0 } else { 0.0 };
                assert!((id[(i, k)] - want).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn small_solvers_agree_with_faer_and_solve_nls() {
        let xs: Vec<f64> = (0..25).map(|i| i as f64 * 0.1).collect();
        let mut a = Vec::new();
        let mut b = Vec::new();
        for &x in &xs {
            a.extend_from_slice(&[1.0, x, x * x, x.sin()]);
            b.push(2.0 - 3.0 * x + 0.5 * x * x + 0.1 * (7.0 * x).cos());
        }
        let q = lstsq_qr(&a, 25, 4, &b).unwrap();
        let s = lstsq_small(&a, 25, 4, &b).unwrap();
        for (u, v) in q.iter().zip(&s) {
            assert!((u - v).abs() < 1e-10, "{u} {v}");
        }
        let j = DMatrix::<f64>::from_fn(25, 4, |i, k| a[i * 4 + k]);
        let c = covariance_small(&j, 1e-12).unwrap();
        let id = j.transpose() * &j * &c;
        for i in 0..4 {
            for k in 0..4 {
                let want = if i == k { 1.0 } else { 0.0 };
                assert!((id[(i, k)] - want).abs() < 1e-8);
            }
        }
        let (lam, _) = top_eigen(&c, 1000);
        let e = c.clone().symmetric_eigen();
        let emax = e.eigenvalues.iter().fold(0.0f64, |m, v| m.max(*v));
        assert!((lam / emax - 1.0).abs() < 1e-6);
    }

    struct ExpoN(Expo);
    impl NormalEquations for ExpoN {
        fn n_params(&self) -> usize {
            2
        }
        fn n_residuals(&self) -> usize {
            self.0.t.len()
        }
        fn cost(&self, p: &[f64]) -> Result<f64> {
            let mut r = vec![0.0; self.0.t.len()];
            let mut j = DMatrix::zeros(self.0.t.len(), 2);
            self.0.eval(p, &mut r, &mut j)?;
            Ok(r.iter().map(|v| v * v).sum())
        }
        fn normal(&self, p: &[f64], jtj: &mut DMatrix<f64>, g: &mut DVector<f64>) -> Result<f64> {
            let mut r = vec![0.0; self.0.t.len()];
            let mut j = DMatrix::zeros(self.0.t.len(), 2);
            self.0.eval(p, &mut r, &mut j)?;
            jtj.copy_from(&(j.transpose() * &j));
            g.copy_from(&(j.transpose() * DVector::from_column_slice(&r)));
            Ok(r.iter().map(|v| v * v).sum())
        }
    }

    #[test]
    fn solve_normal_fits_exponential() {
        let t: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let y: Vec<f64> = t.iter().map(|t| 3.0 * (-0.7 * t).exp()).collect();
        let prob = ExpoN(Expo { t, y });
        let rep = solve_normal(&prob, &[1.0, 0.1], &NlsOptions::default(), 1e-3).unwrap();
        assert!(rep.converged);
        assert!((rep.params[0] - 3.0).abs() < 1e-8 && (rep.params[1] - 0.7).abs() < 1e-8);
    }
}

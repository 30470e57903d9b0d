//! Least-squares numerics in one reviewable place.
//!
//! - [`lstsq_qr`]: tall linear least squares by Householder QR (faer), with column scaling.
//! - [`solve_nls`]: Levenberg-Marquardt (Marquardt scaling) or undamped Gauss-Newton on a
//!   [`Residuals`] problem with an analytic Jacobian; the small normal systems use nalgebra.
//! - [`svd_report`]: singular values and right singular vectors of a (whitened) Jacobian, for
//!   covariance, conditioning and naming unobservable parameter combinations.

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
    let mut cost = prob
        .normal(&p, &mut jtj, &mut g)
        .map_err(|_| CoreError::InvalidInput("the model cannot be evaluated at the start values".into()))?;
    if !cost.is_finite() {
        return invalid("the model cannot be evaluated at the start values");
    }
    let mut lambda = lambda0;
    let mut converged = false;
    let mut it = 0;
    let mut p_new = vec![0.0; n];
    while it < opt.max_iter {
        it += 1;
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
            let rhs = -&g;
            let step = match a.clone().cholesky() {
                Some(c) => c.solve(&rhs),
                None => match a.lu().solve(&rhs) {
                    Some(s) => s,
                    None => {
                        if opt.gauss_newton {
                            return Err(CoreError::NotConverged(
                                "Gauss-Newton: singular normal equations".into(),
                            ));
                        }
                        lambda = lambda.max(1e-12) * 10.0;
                        continue;
                    }
                },
            };
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

#[cfg(test)]
mod tests {
    use super::*;

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
}

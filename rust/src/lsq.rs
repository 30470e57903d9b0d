//! Least-squares numerics in one reviewable place.
//!
//! - [`lstsq_qr`]: tall linear least squares by Householder QR (faer), with column scaling;
//!   [`lstsq_small`] and [`lstsq_rows`] for small designs.
//! - [`solve_nls`], [`solve_normal`], [`solve_normal_fixed`], [`solve_normal_gn`]:
//!   Levenberg-Marquardt (Marquardt scaling) or undamped Gauss-Newton. They are thin adapters
//!   over one iteration (`lm_core`) on a small linear-algebra workspace (`Dense`): stack
//!   arrays when the parameter count is known at compile time, heap buffers allocated once
//!   otherwise.
//! - [`svd_report`]: singular values and right singular vectors of a (whitened) Jacobian, for
//!   covariance, conditioning and naming unobservable parameter combinations.
//! - Small dense kernels (Cholesky solve/inverse, covariance, power iteration, eigenvalues),
//!   each written once for any storage (`Mat`).

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use std::ops::IndexMut;

use crate::error::{degenerate, invalid, CoreError, Result};
use crate::lanes::{F64x4, Portable, LANES};
use faer::linalg::solvers::SolveLstsq;
use nalgebra::{DMatrix, DVector, Matrix3};

/// Unit-norm scale of every column of a row-major `m x n` design; degenerate when a column
/// is zero or not finite.
fn column_scales(a: &[f64], m: usize, n: usize) -> Result<Vec<f64>> {
    let mut scale = vec![0.0; n];
    for i in 0..m {
        for j in 0..n {
            scale[j] += a[i * n + j] * a[i * n + j];
        }
    }
    finish_scales(&mut scale)?;
    Ok(scale)
}

/// Square roots of the column sums of squares in `scale`; degenerate when one is zero or not
/// finite.
fn finish_scales(scale: &mut [f64]) -> Result<()> {
    for (j, s) in scale.iter_mut().enumerate() {
        *s = s.sqrt();
        if !(*s > 0.0) || !s.is_finite() {
            return degenerate(format!("design column {j} is zero or not finite"));
        }
    }
    Ok(())
}

/// Rank test on the diagonal of `R` (of the column-scaled design).
fn check_r_diagonal(diag: impl Iterator<Item = f64>) -> Result<()> {
    let mut dmax: f64 = 0.0;
    let mut dmin = f64::INFINITY;
    for d in diag {
        dmax = dmax.max(d.abs());
        dmin = dmin.min(d.abs());
    }
    if !(dmin > 1e-13 * dmax) {
        return degenerate(format!(
            "design matrix is numerically singular (R diagonal ratio {:.2e})",
            dmin / dmax
        ));
    }
    Ok(())
}

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
    let scale = column_scales(a, m, n)?;
    let mat = faer::Mat::<f64>::from_fn(m, n, |i, j| a[i * n + j] / scale[j]);
    let qr = mat.qr();
    let r = qr.thin_R();
    check_r_diagonal((0..n).map(|j| r[(j, j)]))?;
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
/// accepts a step that increases the cost. Every trial point is evaluated with its Jacobian;
/// the normal equations are formed from the accepted one (`Flavor::Classic` rules).
pub fn solve_nls<P: Residuals>(prob: &P, p0: &[f64], opt: &NlsOptions) -> Result<NlsReport> {
    let (n, m) = (prob.n_params(), prob.n_residuals());
    check_start(n, m, p0)?;
    let mut ev = JacobianTrials {
        prob,
        r: DVector::zeros(m),
        jac: DMatrix::zeros(m, n),
        r_new: DVector::zeros(m),
        j_new: DMatrix::zeros(m, n),
        cost: f64::INFINITY,
    };
    let out = lm_core::<DMatrix<f64>, _>(
        &mut ev,
        DVector::from_column_slice(p0),
        opt,
        1e-3,
        Flavor::Classic,
    )?;
    Ok(NlsReport {
        params: out.params.as_slice().to_vec(),
        residuals: ev.r.as_slice().to_vec(),
        jacobian: ev.jac,
        cost: out.cost,
        iterations: out.iterations,
        converged: out.converged,
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

/// `m >= n` or the usual degenerate-data error.
fn need_rows(m: usize, n: usize) -> Result<()> {
    if m < n {
        return degenerate(format!(
            "{m} observations cannot determine {n} parameters (need at least {n})"
        ));
    }
    Ok(())
}

/// Singular values `s` and right singular vectors `v(row, k)` ordered by descending `s`.
fn sorted_svd(s: &[f64], v: impl Fn(usize, usize) -> f64) -> SvdReport {
    let n = s.len();
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| s[b].total_cmp(&s[a]));
    SvdReport {
        s: idx.iter().map(|&i| s[i]).collect(),
        v: DMatrix::<f64>::from_fn(n, n, |a, b| v(a, idx[b])),
    }
}

/// SVD of `J` (`m x n`, `m >= n`) with columns scaled to unit norm, then unscaled so that
/// the singular vectors refer to the original parameters: returns the SVD of `J` itself when
/// columns are already comparable; the column scaling only stabilises the decomposition.
pub fn svd_report(j: &DMatrix<f64>) -> Result<SvdReport> {
    let (m, n) = (j.nrows(), j.ncols());
    need_rows(m, n)?;
    let mat = faer::Mat::<f64>::from_fn(m, n, |a, b| j[(a, b)]);
    let svd = mat
        .thin_svd()
        .map_err(|_| CoreError::NotConverged("SVD of the Jacobian did not converge".into()))?;
    let s: Vec<f64> = (0..n).map(|i| svd.S()[i]).collect();
    // faer returns singular values in non-increasing order; keep that contract explicit.
    Ok(sorted_svd(&s, |a, b| svd.V()[(a, b)]))
}

/// Same contract as [`svd_report`] for small problems (a few to a few dozen parameters):
/// Householder QR of `J` (nalgebra), then the SVD of the small `n x n` factor `R`, whose
/// singular values and right singular vectors are those of `J`. Avoids the fixed overhead of
/// the large-matrix path, which dominates microsecond-scale fits.
pub fn svd_report_qr(j: &DMatrix<f64>) -> Result<SvdReport> {
    let (m, n) = (j.nrows(), j.ncols());
    need_rows(m, n)?;
    if j.iter().any(|v| !v.is_finite()) {
        return invalid("the Jacobian is not finite");
    }
    let r = j.clone().qr().r();
    let svd = r.svd(false, true);
    let vt = svd
        .v_t
        .ok_or_else(|| CoreError::NotConverged("SVD of the Jacobian did not converge".into()))?;
    let s: Vec<f64> = svd.singular_values.iter().copied().collect();
    Ok(sorted_svd(&s, |a, b| vt[(b, a)]))
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
    let scale = column_scales(a, m, n)?;
    let mat = DMatrix::<f64>::from_fn(m, n, |i, j| a[i * n + j] / scale[j]);
    let qr = mat.qr();
    let r = qr.r();
    check_r_diagonal((0..n).map(|j| r[(j, j)]))?;
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
    let mut a = DMatrix::<f64>::zeros(n, n);
    let col = |k: usize| &j.as_slice()[k * m..(k + 1) * m];
    for p in 0..n {
        for q in p..n {
            let v: f64 = col(p).iter().zip(col(q)).map(|(x, y)| x * y).sum();
            a[(p, q)] = v;
            a[(q, p)] = v;
        }
    }
    covariance_of_normal(a, rtol)
}

/// [`covariance_small`] from the normal matrix `J^T J` itself (fixed size, same column
/// scaling, pivot test and arithmetic): `None` when singular at `rtol` or not finite.
pub fn covariance_normal_fixed<const N: usize>(
    normal: &[[f64; N]; N],
    rtol: f64,
) -> Option<[[f64; N]; N]> {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::lanes::avx2_fma() {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            return unsafe { covariance_normal_fixed_avx2(normal, rtol) };
        }
    }
    covariance_of_normal(*normal, rtol)
}

/// [`covariance_normal_fixed`] compiled for AVX2: wider vectors for the row updates of the
/// Cholesky factor and the inverse, the same arithmetic (no contraction into fused
/// multiply-adds), so the same bits.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn covariance_normal_fixed_avx2<const N: usize>(
    normal: &[[f64; N]; N],
    rtol: f64,
) -> Option<[[f64; N]; N]> {
    covariance_of_normal(*normal, rtol)
}

/// Largest eigenvalue and its eigenvector of a symmetric positive semi-definite matrix
/// (at most 16 x 16) by power iteration (relative tolerance 1e-9 on the eigenvalue), enough to
/// find the least determined combination of a covariance.
pub fn top_eigen(c: &DMatrix<f64>, iters: usize) -> (f64, Vec<f64>) {
    let (lam, v, n) = power_iteration::<16, _>(c, iters);
    (lam, v[..n].to_vec())
}

/// [`top_eigen`] on a fixed-size matrix (same start, iteration and tolerance).
pub fn top_eigen_fixed<const N: usize>(c: &[[f64; N]; N], iters: usize) -> (f64, [f64; N]) {
    let (lam, v, _) = power_iteration::<N, _>(c, iters);
    (lam, v)
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
/// Trial points are evaluated by cost only; a step whose predicted gain is negligible ends
/// the fit without another normal-equation evaluation (`Flavor::Predicted` rules).
/// Returns the report without residuals/Jacobian (`jacobian` is empty).
pub fn solve_normal<P: NormalEquations>(
    prob: &P,
    p0: &[f64],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<NlsReport> {
    let n = prob.n_params();
    check_start(n, prob.n_residuals(), p0)?;
    let out = lm_core::<DMatrix<f64>, _>(
        &mut CostTrials(prob),
        DVector::from_column_slice(p0),
        opt,
        lambda0,
        Flavor::Predicted,
    )?;
    Ok(out.into_report(n))
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
    let n = prob.n_params();
    check_start(n, prob.n_residuals(), p0)?;
    let mut ev = NormalTrials {
        prob,
        jtj: DMatrix::zeros(n, n),
        g: DVector::zeros(n),
        cost: f64::INFINITY,
    };
    let opt = NlsOptions {
        gauss_newton: true,
        ..*opt
    };
    let out = lm_core::<DMatrix<f64>, _>(
        &mut ev,
        DVector::from_column_slice(p0),
        &opt,
        0.0,
        Flavor::Classic,
    )?;
    Ok(out.into_report(n))
}

/// Cholesky factor `L` (lower, row-major `n x n`, upper part zeroed) of a symmetric positive
/// definite row-major matrix, in place, without allocation. `false` when a pivot is not
/// positive and finite (the matrix is not numerically positive definite).
pub fn cholesky_small(a: &mut [f64], n: usize) -> bool {
    let pivot_ok = |_, s: f64| s > 0.0 && s.is_finite();
    if !cholesky_lower(&mut RowMajor { a: &mut *a, n }, pivot_ok) {
        return false;
    }
    for k in 0..n {
        for j in (k + 1)..n {
            a[k * n + j] = 0.0;
        }
    }
    true
}

/// Solve `L L^T x = b` in place (`l` from [`cholesky_small`]).
pub fn cholesky_solve_small(l: &[f64], n: usize, b: &mut [f64]) {
    cholesky_solve(&RowMajor { a: l, n }, b);
}

/// `(L L^T)^-1` (row-major `n x n`, symmetric) from the factor of [`cholesky_small`].
pub fn cholesky_inverse_small(l: &[f64], n: usize) -> Vec<f64> {
    let (mut li, mut c) = (RowMajor::zeros(n), RowMajor::zeros(n));
    cholesky_inverse(&RowMajor { a: l, n }, &mut li, &mut c, |_, _, v| v);
    c.a
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
/// triangle is read), without eigenvectors: for n <= 24 a stack-allocated Householder
/// reduction to tridiagonal form and the implicit QL iteration (the classic tred2 / tqli
/// pair), much cheaper than a general decomposition for a handful of parameters; above that
/// nalgebra's symmetric eigensolver. `None` if the iteration does not converge or
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
    // Larger problems are not on a hot path: nalgebra's symmetric eigensolver.
    let m = DMatrix::<f64>::from_fn(
        n,
        n,
        |i, j| if i >= j { a[i * n + j] } else { a[j * n + i] },
    );
    let mut d: Vec<f64> = m.symmetric_eigenvalues().iter().copied().collect();
    d.sort_by(|x, y| x.total_cmp(y));
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
// static fit): `lstsq_small` and `solve_normal` on stack arrays with fully unrollable loops
// and no heap allocation.

/// Rows up to which [`lstsq_rows`] uses its own QR (more: [`lstsq_small`]).
pub const FIXED_ROWS: usize = 64;

/// [`lstsq_small`] for `C` columns given as rows: same column scaling, rank test and error
/// messages; a plain Householder QR for up to [`FIXED_ROWS`] rows (no matrix set-up cost).
pub fn lstsq_rows<const C: usize>(rows: &[[f64; C]], b: &[f64]) -> Result<[f64; C]> {
    if b.len() != rows.len() {
        return invalid(format!("lstsq_rows: {} rows, rhs {}", rows.len(), b.len()));
    }
    lstsq_fn(rows.len(), |i| (rows[i], b[i]))
}

/// [`lstsq_rows`] with row `i` and its right-hand side produced by `row(i)`: no allocation for
/// up to [`FIXED_ROWS`] rows (the design lives on the stack, column-major).
#[inline(always)]
pub fn lstsq_fn<const C: usize>(
    m: usize,
    row: impl Fn(usize) -> ([f64; C], f64),
) -> Result<[f64; C]> {
    if m > FIXED_ROWS || m < C {
        let mut flat = Vec::with_capacity(m * C);
        let mut b = Vec::with_capacity(m);
        for i in 0..m {
            let (r, y) = row(i);
            flat.extend_from_slice(&r);
            b.push(y);
        }
        let x = lstsq_small(&flat, m, C, &b)?;
        let mut out = [0.0; C];
        out.copy_from_slice(&x);
        return Ok(out);
    }
    // Column-major design (column stride FIXED_ROWS) and right-hand side.
    let mut a = [[0.0f64; FIXED_ROWS]; C];
    let mut y = [0.0f64; FIXED_ROWS];
    let mut scale = [0.0f64; C];
    for i in 0..m {
        let (r, yi) = row(i);
        y[i] = yi;
        for j in 0..C {
            a[j][i] = r[j];
            scale[j] += r[j] * r[j];
        }
    }
    finish_scales(&mut scale)?;
    for j in 0..C {
        let inv = 1.0 / scale[j];
        for x in &mut a[j][..m] {
            *x *= inv;
        }
    }
    let mut rdiag = [0.0f64; C];
    for j in 0..C {
        let (head, tail) = a.split_at_mut(j + 1);
        let v = &mut head[j][j..m];
        let norm = dot4(v, v).sqrt();
        if !(norm > 0.0) {
            rdiag[j] = 0.0;
            continue;
        }
        let alpha = if v[0] > 0.0 { -norm } else { norm };
        v[0] -= alpha;
        let vv = dot4(v, v);
        if vv > 0.0 {
            let f = 2.0 / vv;
            for col in tail.iter_mut() {
                let c = &mut col[j..m];
                let s = f * dot4(v, c);
                for (ci, vi) in c.iter_mut().zip(v.iter()) {
                    *ci -= s * vi;
                }
            }
            let c = &mut y[j..m];
            let s = f * dot4(v, c);
            for (ci, vi) in c.iter_mut().zip(v.iter()) {
                *ci -= s * vi;
            }
        }
        rdiag[j] = alpha;
    }
    check_r_diagonal(rdiag.into_iter())?;
    let mut x = [0.0f64; C];
    for j in (0..C).rev() {
        let mut v = y[j];
        for k in (j + 1)..C {
            v -= a[k][j] * x[k];
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

/// [`lstsq_fn`] by the normal equations of the column-scaled design (Cholesky): about a
/// third of the work of the QR, for a start value that an iteration polishes. The accuracy is
/// about `cond^2 * eps` relative; when the scaled normal matrix has a pivot below `1e-10`
/// (condition number above 1e5) the QR of [`lstsq_fn`] is used instead. Same errors.
#[inline(always)]
pub fn lstsq_normal_fn<const C: usize>(
    m: usize,
    row: impl Fn(usize) -> ([f64; C], f64),
) -> Result<[f64; C]> {
    lstsq_normal_lanes::<Portable, C>(&RowFn(m, row))
}

/// Rows of a least-squares design with their right-hand sides, one at a time (for the QR)
/// and [`LANES`] at a time in the lanes of `V` (for the normal equations).
pub(crate) trait RowLanes<V: F64x4, const C: usize> {
    /// Number of rows.
    fn n_rows(&self) -> usize;
    /// Row `i` and its right-hand side.
    fn row(&self, i: usize) -> ([f64; C], f64);
    /// Rows `i0 .. i0 + LANES` in lanes, each column one vector, and the right-hand sides;
    /// rows past the end are zero. The default is [`lanes_by_rows`].
    #[inline(always)]
    fn lanes(&self, i0: usize) -> ([V; C], V) {
        lanes_by_rows(self, i0)
    }
}

/// Rows `i0 .. i0 + LANES` of `rows` in lanes, transposed row by row through memory (rows
/// past the end zero).
#[inline(always)]
pub(crate) fn lanes_by_rows<V: F64x4, const C: usize>(
    rows: &(impl RowLanes<V, C> + ?Sized),
    i0: usize,
) -> ([V; C], V) {
    let (mut xs, mut ys) = ([[0.0f64; LANES]; C], [0.0f64; LANES]);
    for l in 0..LANES.min(rows.n_rows() - i0) {
        let (x, y) = rows.row(i0 + l);
        for p in 0..C {
            xs[p][l] = x[p];
        }
        ys[l] = y;
    }
    let mut x = [V::splat(0.0); C];
    for (v, lanes) in x.iter_mut().zip(&xs) {
        *v = V::from_array(*lanes);
    }
    (x, V::from_array(ys))
}

/// A row closure as [`RowLanes`].
struct RowFn<F>(usize, F);

impl<V: F64x4, const C: usize, F: Fn(usize) -> ([f64; C], f64)> RowLanes<V, C> for RowFn<F> {
    #[inline(always)]
    fn n_rows(&self) -> usize {
        self.0
    }
    #[inline(always)]
    fn row(&self, i: usize) -> ([f64; C], f64) {
        (self.1)(i)
    }
}

/// [`lstsq_normal_fn`] with the sums of the normal equations taken [`LANES`] rows at a time
/// in the lanes of `V` (see `crate::lanes`) and added across lanes at the end in a fixed
/// order.
#[inline(always)]
pub(crate) fn lstsq_normal_lanes<V: F64x4, const C: usize>(
    rows: &impl RowLanes<V, C>,
) -> Result<[f64; C]> {
    let m = rows.n_rows();
    let row = |i: usize| rows.row(i);
    if m < C {
        return lstsq_fn(m, row);
    }
    let zero = V::splat(0.0);
    let mut al = [[zero; C]; C];
    let mut rl = [zero; C];
    for i0 in (0..m).step_by(LANES) {
        let (x, y) = rows.lanes(i0);
        for p in 0..C {
            rl[p] = x[p].mul_add(y, rl[p]);
            for q in p..C {
                al[p][q] = x[p].mul_add(x[q], al[p][q]);
            }
        }
    }
    let mut a = [[0.0f64; C]; C];
    let mut r = [0.0f64; C];
    let mut d = [0.0f64; C];
    for p in 0..C {
        r[p] = rl[p].fold();
        for q in p..C {
            a[p][q] = al[p][q].fold();
        }
        d[p] = a[p][p].sqrt();
        if !(d[p] > 0.0) || !d[p].is_finite() {
            return degenerate(format!("design column {p} is zero or not finite"));
        }
    }
    let di = d.map(|v| 1.0 / v);
    for p in 0..C {
        r[p] *= di[p];
        for q in p..C {
            a[p][q] *= di[p] * di[q];
            a[q][p] = a[p][q];
        }
    }
    if !cholesky_full(&mut a, |_, s| s > 1e-10) {
        return lstsq_fn(m, row);
    }
    cholesky_solve(&a, &mut r);
    for p in 0..C {
        r[p] *= di[p];
    }
    if r.iter().any(|v| !v.is_finite()) {
        return lstsq_fn(m, row);
    }
    Ok(r)
}

/// Dot product with four partial sums (breaks the addition chain: about four times faster
/// on short vectors; the rounding differs from a serial sum only in the last bits).
#[inline(always)]
fn dot4(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut tail = 0.0;
    for (x, y) in ca.remainder().iter().zip(cb.remainder()) {
        tail += x * y;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// Householder QR of a tall matrix (nalgebra): the thin `Q` (m x n, orthonormal columns)
/// and `R` (n x n, upper triangular), `a = Q R`.
pub fn householder_qr(a: &DMatrix<f64>) -> (DMatrix<f64>, DMatrix<f64>) {
    let qr = a.clone().qr();
    (qr.q(), qr.r())
}

/// Solve `g x = b` for a symmetric positive definite `g` by Cholesky; `None` when `g` is
/// not positive definite.
pub fn cholesky_solve_dense(g: DMatrix<f64>, b: &DVector<f64>) -> Option<DVector<f64>> {
    g.cholesky().map(|c| c.solve(b))
}

/// Inverse of a 3 x 3 matrix (closed form); `None` when singular or not finite.
#[inline]
pub fn inverse3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    m.try_inverse().filter(|t| t.iter().all(|v| v.is_finite()))
}

/// Lower Cholesky factor `L` (`L L^T = m`) of a symmetric 3 x 3 matrix; `None` when it is not
/// positive definite.
#[inline]
pub fn cholesky3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    m.cholesky().map(|c| c.l())
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
    /// Sum of squared residuals at `params`.
    pub cost: f64,
    /// `J^T J` at `params`.
    pub jtj: [[f64; N]; N],
    /// `J^T r` at `params`.
    pub jtr: [f64; N],
    /// Iterations taken.
    pub iterations: usize,
    /// True when a tolerance was met (false: iteration limit).
    pub converged: bool,
}

/// Levenberg-Marquardt (or Gauss-Newton) for a [`NormalEquationsFixed`] problem without heap
/// allocation. Every trial point is evaluated with its normal equations (near a good start
/// almost every step is accepted, so this saves a pass over the data per step), and the fit
/// ends at a point whose normal equations are known: when the next step could gain less than
/// `ftol * cost`, it is not taken. The report carries `J^T J` and `J^T r` there, for the
/// covariance and a convergence check. Errors as [`solve_normal`].
pub fn solve_normal_fixed<const N: usize, P: NormalEquationsFixed<N>>(
    prob: &P,
    p0: &[f64; N],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<FixedReport<N>> {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::lanes::avx2_fma() {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            return unsafe { solve_normal_fixed_avx2(prob, p0, opt, lambda0) };
        }
    }
    solve_normal_fixed_body(prob, p0, opt, lambda0)
}

/// [`solve_normal_fixed`] compiled for AVX2 (wider vectors for the small dense steps; the
/// arithmetic is the baseline build's, without contraction into fused multiply-adds).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn solve_normal_fixed_avx2<const N: usize, P: NormalEquationsFixed<N>>(
    prob: &P,
    p0: &[f64; N],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<FixedReport<N>> {
    solve_normal_fixed_body(prob, p0, opt, lambda0)
}

#[inline(always)]
fn solve_normal_fixed_body<const N: usize, P: NormalEquationsFixed<N>>(
    prob: &P,
    p0: &[f64; N],
    opt: &NlsOptions,
    lambda0: f64,
) -> Result<FixedReport<N>> {
    check_start(N, prob.n_residuals(), p0)?;
    let mut ev = FixedNormalTrials {
        prob,
        jtj: [[0.0; N]; N],
        g: [0.0; N],
        cost: f64::INFINITY,
    };
    let out = lm_core::<[[f64; N]; N], _>(&mut ev, *p0, opt, lambda0, Flavor::Stationary)?;
    Ok(FixedReport {
        params: out.params,
        cost: out.cost,
        jtj: out.jtj,
        jtr: out.g,
        iterations: out.iterations,
        converged: out.converged,
    })
}

// ------------------------------------------------------------------------------------------
// Small dense kernels, written once for any storage: `[[f64; N]; N]` (the size a
// compile-time constant, so loops unroll and bounds checks vanish), nalgebra's `DMatrix`
// and flat row-major slices.

/// Read access to a square matrix.
trait Mat {
    /// Number of rows (= columns).
    fn dim(&self) -> usize;
    /// Element `(i, j)`.
    fn at(&self, i: usize, j: usize) -> f64;
}

/// Write access to a square matrix.
trait MatMut: Mat {
    /// Element `(i, j)`.
    fn at_mut(&mut self, i: usize, j: usize) -> &mut f64;
}

impl<const N: usize> Mat for [[f64; N]; N] {
    #[inline(always)]
    fn dim(&self) -> usize {
        N
    }
    #[inline(always)]
    fn at(&self, i: usize, j: usize) -> f64 {
        self[i][j]
    }
}

impl<const N: usize> MatMut for [[f64; N]; N] {
    #[inline(always)]
    fn at_mut(&mut self, i: usize, j: usize) -> &mut f64 {
        &mut self[i][j]
    }
}

impl Mat for DMatrix<f64> {
    #[inline(always)]
    fn dim(&self) -> usize {
        self.nrows()
    }
    #[inline(always)]
    fn at(&self, i: usize, j: usize) -> f64 {
        self[(i, j)]
    }
}

impl MatMut for DMatrix<f64> {
    #[inline(always)]
    fn at_mut(&mut self, i: usize, j: usize) -> &mut f64 {
        &mut self[(i, j)]
    }
}

/// A flat row-major `n x n` matrix.
struct RowMajor<S> {
    a: S,
    n: usize,
}

impl RowMajor<Vec<f64>> {
    fn zeros(n: usize) -> Self {
        RowMajor {
            a: vec![0.0; n * n],
            n,
        }
    }
}

impl<S: AsRef<[f64]>> Mat for RowMajor<S> {
    #[inline(always)]
    fn dim(&self) -> usize {
        self.n
    }
    #[inline(always)]
    fn at(&self, i: usize, j: usize) -> f64 {
        self.a.as_ref()[i * self.n + j]
    }
}

impl<S: AsRef<[f64]> + AsMut<[f64]>> MatMut for RowMajor<S> {
    #[inline(always)]
    fn at_mut(&mut self, i: usize, j: usize) -> &mut f64 {
        &mut self.a.as_mut()[i * self.n + j]
    }
}

/// Owned workspace of the solvers: a matrix type with its vector type, allocated once per
/// solve (stack arrays for [`solve_normal_fixed`], heap buffers otherwise).
trait Dense: MatMut + Sized {
    /// `n`-vector.
    type Vector: IndexMut<usize, Output = f64>;
    /// Zero `n x n` matrix (a fixed size ignores `n`).
    fn zeros(n: usize) -> Self;
    /// Zero `n`-vector (a fixed size ignores `n`).
    fn zeros_vector(n: usize) -> Self::Vector;
    /// The vector as a slice.
    fn slice(v: &Self::Vector) -> &[f64];
    /// In-place Cholesky of a full symmetric matrix: `L` in the lower triangle (the strict
    /// upper triangle is left unspecified); `pivot_ok` as for [`cholesky_lower`].
    #[inline(always)]
    fn cholesky_symmetric(&mut self, pivot_ok: impl Fn(usize, f64) -> bool) -> bool {
        cholesky_lower(self, pivot_ok)
    }
}

impl<const N: usize> Dense for [[f64; N]; N] {
    type Vector = [f64; N];
    #[inline(always)]
    fn cholesky_symmetric(&mut self, pivot_ok: impl Fn(usize, f64) -> bool) -> bool {
        cholesky_full(self, pivot_ok)
    }
    #[inline(always)]
    fn zeros(_: usize) -> Self {
        [[0.0; N]; N]
    }
    #[inline(always)]
    fn zeros_vector(_: usize) -> [f64; N] {
        [0.0; N]
    }
    #[inline(always)]
    fn slice(v: &[f64; N]) -> &[f64] {
        v
    }
}

impl Dense for DMatrix<f64> {
    type Vector = DVector<f64>;
    fn zeros(n: usize) -> Self {
        DMatrix::zeros(n, n)
    }
    fn zeros_vector(n: usize) -> DVector<f64> {
        DVector::zeros(n)
    }
    #[inline(always)]
    fn slice(v: &DVector<f64>) -> &[f64] {
        v.as_slice()
    }
}

/// In-place Cholesky `A = L L^T` on the lower triangle of `a` (the strict upper triangle is
/// neither read nor written). `pivot_ok(k, s)` judges the `k`-th pivot before its square
/// root; false when it rejects one.
///
/// Computed as `A = U D U^T` (`U` unit lower) column by column, each column updating the
/// trailing triangle at once, and then `L = U D^(1/2)`: the square roots are off the chain of
/// dependent operations (one division, one multiplication and one subtraction per column),
/// which is what limits a 9 x 9 factor.
#[inline(always)]
fn cholesky_lower<M: MatMut>(a: &mut M, pivot_ok: impl Fn(usize, f64) -> bool) -> bool {
    let n = a.dim();
    for k in 0..n {
        let d = a.at(k, k);
        if !pivot_ok(k, d) {
            return false;
        }
        let inv = 1.0 / d;
        // a(i, k) = u_ik d until the column is scaled below.
        for i in (k + 1)..n {
            let u = a.at(i, k) * inv;
            for j in (k + 1)..=i {
                *a.at_mut(i, j) -= u * a.at(j, k);
            }
        }
        for i in (k + 1)..n {
            *a.at_mut(i, k) *= inv;
        }
    }
    for k in 0..n {
        let s = a.at(k, k).sqrt();
        *a.at_mut(k, k) = s;
        for i in (k + 1)..n {
            *a.at_mut(i, k) *= s;
        }
    }
    true
}

/// [`cholesky_lower`] for a full symmetric `N x N` array: each column's update of the trailing
/// rows runs over whole rows of fixed length `N` (the entries it must not change get a zero
/// multiplier), so the compiler unrolls and vectorises it. `L` ends in the lower triangle;
/// the strict upper triangle is left unspecified.
#[inline(always)]
fn cholesky_full<const N: usize>(
    a: &mut [[f64; N]; N],
    pivot_ok: impl Fn(usize, f64) -> bool,
) -> bool {
    for k in 0..N {
        let d = a[k][k];
        if !pivot_ok(k, d) {
            return false;
        }
        let inv = 1.0 / d;
        // c_j = a(j, k) = u_jk d below the diagonal, zero elsewhere.
        let c: [f64; N] = std::array::from_fn(|j| if j > k { a[j][k] } else { 0.0 });
        for i in (k + 1)..N {
            let u = c[i] * inv;
            for (x, cj) in a[i].iter_mut().zip(&c) {
                *x -= u * cj;
            }
        }
        for i in (k + 1)..N {
            a[i][k] = c[i] * inv;
        }
    }
    for k in 0..N {
        let s = a[k][k].sqrt();
        a[k][k] = s;
        for row in a.iter_mut().skip(k + 1) {
            row[k] *= s;
        }
    }
    true
}

/// Solve `L L^T x = b` in place for `L` from [`cholesky_lower`] (column by column, with the
/// reciprocals of the diagonal taken first).
#[inline(always)]
fn cholesky_solve<M: Mat, V: IndexMut<usize, Output = f64> + ?Sized>(l: &M, x: &mut V) {
    let n = l.dim();
    const MAX: usize = 16;
    let mut inv_buf = [0.0f64; MAX];
    let mut inv_vec = Vec::new();
    let inv: &mut [f64] = if n <= MAX {
        &mut inv_buf[..n]
    } else {
        inv_vec.resize(n, 0.0);
        &mut inv_vec
    };
    for (k, v) in inv.iter_mut().enumerate() {
        *v = 1.0 / l.at(k, k);
    }
    for k in 0..n {
        let xk = x[k] * inv[k];
        x[k] = xk;
        for i in (k + 1)..n {
            x[i] -= l.at(i, k) * xk;
        }
    }
    for k in (0..n).rev() {
        let xk = x[k] * inv[k];
        x[k] = xk;
        for i in 0..k {
            x[i] -= l.at(k, i) * xk;
        }
    }
}

/// `c = (L L^T)^-1` with element `(p, q)` passed through `fin(p, q, value)`, from `L` of
/// [`cholesky_lower`]; `li` receives `L^-1` (lower).
#[inline(always)]
fn cholesky_inverse<L: Mat, W: MatMut>(
    l: &L,
    li: &mut W,
    c: &mut W,
    fin: impl Fn(usize, usize, f64) -> f64,
) {
    let n = l.dim();
    for k in 0..n {
        *li.at_mut(k, k) = 1.0 / l.at(k, k);
    }
    for col in 0..n {
        for i in (col + 1)..n {
            let mut v = 0.0;
            for t in col..i {
                v -= l.at(i, t) * li.at(t, col);
            }
            *li.at_mut(i, col) = v * li.at(i, i);
        }
    }
    for p in 0..n {
        for q in p..n {
            let mut v = 0.0;
            for t in q..n {
                v += li.at(t, p) * li.at(t, q);
            }
            let v = fin(p, q, v);
            *c.at_mut(p, q) = v;
            *c.at_mut(q, p) = v;
        }
    }
}

/// Solve `(A + damp diag(d)) x = -g` by Cholesky in `l` (lower triangle of `a` read); false
/// when the damped matrix is not numerically positive definite or the step is not finite.
#[inline(always)]
fn chol_solve_damped<M: Dense, V: IndexMut<usize, Output = f64> + ?Sized>(
    a: &M,
    d: &V,
    damp: f64,
    g: &V,
    l: &mut M,
    x: &mut V,
) -> bool {
    let n = a.dim();
    for i in 0..n {
        for j in 0..n {
            *l.at_mut(i, j) = a.at(i, j);
        }
        *l.at_mut(i, i) += damp * d[i];
    }
    let ok =
        l.cholesky_symmetric(|k, s| s > 1e-300 && s > 1e-15 * a.at(k, k).abs().max(1e-300) * 1e-3);
    if !ok {
        return false;
    }
    for i in 0..n {
        x[i] = -g[i];
    }
    cholesky_solve(l, x);
    (0..n).all(|i| x[i].is_finite())
}

/// `(A)^-1` of a normal matrix `A = J^T J` by Cholesky of the column-scaled matrix: `None`
/// when a pivot falls below `rtol^2` or the inverse is not finite.
#[inline(always)]
fn covariance_of_normal<M: Dense>(mut a: M, rtol: f64) -> Option<M> {
    let n = a.dim();
    let mut d = M::zeros_vector(n);
    for i in 0..n {
        d[i] = a.at(i, i).sqrt();
        if !(d[i] > 0.0) || !d[i].is_finite() {
            return None;
        }
    }
    for i in 0..n {
        d[i] = 1.0 / d[i];
    }
    for p in 0..n {
        for q in 0..n {
            *a.at_mut(p, q) *= d[p] * d[q];
        }
    }
    if !a.cholesky_symmetric(|_, s| s > rtol * rtol) {
        return None;
    }
    let mut li = M::zeros(n);
    let mut c = M::zeros(n);
    cholesky_inverse(&a, &mut li, &mut c, |p, q, v| v * (d[p] * d[q]));
    for p in 0..n {
        for q in 0..n {
            if !c.at(p, q).is_finite() {
                return None;
            }
        }
    }
    Some(c)
}

/// Power iteration for the largest eigenvalue of the leading `min(dim, K)` block of `c`:
/// `(eigenvalue, eigenvector in the first n entries, n)`.
#[inline(always)]
fn power_iteration<const K: usize, M: Mat>(c: &M, iters: usize) -> (f64, [f64; K], usize) {
    let n = c.dim().min(K);
    let mut v = [0.0f64; K];
    for (i, x) in v.iter_mut().enumerate().take(n) {
        *x = 1.0 + 0.1 * i as f64;
    }
    let mut lam = 0.0;
    for _ in 0..iters {
        let mut w = [0.0f64; K];
        for (i, wi) in w.iter_mut().enumerate().take(n) {
            *wi = (0..n).map(|j| c.at(i, j) * v[j]).sum();
        }
        let nv = v[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
        let nw = w[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(nw > 0.0) || !nw.is_finite() {
            return (nw, v, n);
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
    (lam, v, n)
}

// ------------------------------------------------------------------------------------------
// The one Levenberg-Marquardt / Gauss-Newton iteration behind every public solver.

/// Start checks shared by the solvers.
fn check_start(n: usize, m: usize, p0: &[f64]) -> Result<()> {
    if p0.len() != n {
        return invalid(format!("start has {} values, the model {n}", p0.len()));
    }
    need_rows(m, n)?;
    if p0.iter().any(|v| !v.is_finite()) {
        return invalid("start values must be finite");
    }
    Ok(())
}

/// The few rules in which the public solvers differ; everything else is one code path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Flavor {
    /// [`solve_nls`], [`solve_normal_gn`]: an error evaluating the start is returned
    /// unchanged; LM lowers the damping to no less than 1e-12; no predicted-gain test.
    Classic,
    /// [`solve_normal`]: an error evaluating the start reads "cannot be evaluated at the
    /// start values"; a step that lowers the cost with a predicted gain below `ftol * cost`
    /// is taken and ends the fit (no new normal equations); a negligible step (`xtol`) that
    /// raises the cost ends the search; LM lowers the damping without a floor.
    Predicted,
    /// [`solve_normal_fixed`]: normal equations at every trial point (kept when accepted);
    /// when the step's predicted gain at small damping is below `ftol * cost` the fit ends
    /// *at the current point*, whose normal equations are then known; otherwise the rules of
    /// [`Flavor::Predicted`].
    Stationary,
}

/// How [`lm_core`] evaluates a problem: trial costs, and taking the last trial point as the
/// current one (its normal equations).
trait Evaluate<M: Dense> {
    /// Cost at a trial point `p`.
    fn trial(&mut self, p: &M::Vector) -> Result<f64>;
    /// The last trial point `p` becomes current: fill `J^T J`, `J^T r`; return its cost.
    fn accept(&mut self, p: &M::Vector, jtj: &mut M, g: &mut M::Vector) -> Result<f64>;
    /// Fill `J^T J` and `J^T r` at the start `p`; return the cost.
    fn start(&mut self, p: &M::Vector, jtj: &mut M, g: &mut M::Vector) -> Result<f64> {
        self.trial(p)?;
        self.accept(p, jtj, g)
    }
}

type Dm = DMatrix<f64>;
type Dv = DVector<f64>;

/// Cost-only trials, normal equations at accepted points ([`solve_normal`],
/// [`solve_normal_fixed`]).
struct CostTrials<'a, P>(&'a P);

impl<P: NormalEquations> Evaluate<Dm> for CostTrials<'_, P> {
    fn trial(&mut self, p: &Dv) -> Result<f64> {
        self.0.cost(p.as_slice())
    }
    fn accept(&mut self, p: &Dv, jtj: &mut Dm, g: &mut Dv) -> Result<f64> {
        self.0.normal(p.as_slice(), jtj, g)
    }
    fn start(&mut self, p: &Dv, jtj: &mut Dm, g: &mut Dv) -> Result<f64> {
        self.accept(p, jtj, g)
    }
}

impl<const N: usize, P: NormalEquationsFixed<N>> Evaluate<[[f64; N]; N]> for CostTrials<'_, P> {
    #[inline(always)]
    fn trial(&mut self, p: &[f64; N]) -> Result<f64> {
        self.0.cost(p)
    }
    #[inline(always)]
    fn accept(&mut self, p: &[f64; N], jtj: &mut [[f64; N]; N], g: &mut [f64; N]) -> Result<f64> {
        self.0.normal(p, jtj, g)
    }
    #[inline(always)]
    fn start(&mut self, p: &[f64; N], jtj: &mut [[f64; N]; N], g: &mut [f64; N]) -> Result<f64> {
        self.accept(p, jtj, g)
    }
}

/// Normal equations at every trial point, kept for when it is accepted
/// ([`solve_normal_gn`]: Gauss-Newton accepts every finite step).
struct NormalTrials<'a, P> {
    prob: &'a P,
    jtj: Dm,
    g: Dv,
    cost: f64,
}

impl<P: NormalEquations> Evaluate<Dm> for NormalTrials<'_, P> {
    fn trial(&mut self, p: &Dv) -> Result<f64> {
        self.cost = self.prob.normal(p.as_slice(), &mut self.jtj, &mut self.g)?;
        Ok(self.cost)
    }
    fn accept(&mut self, _: &Dv, jtj: &mut Dm, g: &mut Dv) -> Result<f64> {
        std::mem::swap(jtj, &mut self.jtj);
        std::mem::swap(g, &mut self.g);
        Ok(self.cost)
    }
}

/// [`NormalTrials`] on stack arrays ([`solve_normal_fixed`]).
struct FixedNormalTrials<'a, P, const N: usize> {
    prob: &'a P,
    jtj: [[f64; N]; N],
    g: [f64; N],
    cost: f64,
}

impl<const N: usize, P: NormalEquationsFixed<N>> Evaluate<[[f64; N]; N]>
    for FixedNormalTrials<'_, P, N>
{
    #[inline(always)]
    fn trial(&mut self, p: &[f64; N]) -> Result<f64> {
        self.cost = self.prob.normal(p, &mut self.jtj, &mut self.g)?;
        Ok(self.cost)
    }
    #[inline(always)]
    fn accept(&mut self, _: &[f64; N], jtj: &mut [[f64; N]; N], g: &mut [f64; N]) -> Result<f64> {
        *jtj = self.jtj;
        *g = self.g;
        Ok(self.cost)
    }
}

/// Residuals and Jacobian at every trial point; the normal equations are formed from the
/// accepted Jacobian ([`solve_nls`], which reports both).
struct JacobianTrials<'a, P> {
    prob: &'a P,
    r: Dv,
    jac: Dm,
    r_new: Dv,
    j_new: Dm,
    cost: f64,
}

impl<P: Residuals> Evaluate<Dm> for JacobianTrials<'_, P> {
    fn trial(&mut self, p: &Dv) -> Result<f64> {
        self.prob
            .eval(p.as_slice(), self.r_new.as_mut_slice(), &mut self.j_new)?;
        self.cost = sumsq(self.r_new.as_slice());
        Ok(self.cost)
    }
    fn accept(&mut self, _: &Dv, jtj: &mut Dm, g: &mut Dv) -> Result<f64> {
        std::mem::swap(&mut self.r, &mut self.r_new);
        std::mem::swap(&mut self.jac, &mut self.j_new);
        // J^T J: the upper triangle by column dot products, mirrored (half the work of a
        // general product, and symmetric to the bit).
        let n = self.jac.ncols();
        for i in 0..n {
            let ci = self.jac.column(i);
            for j in i..n {
                let v = ci.dot(&self.jac.column(j));
                jtj[(i, j)] = v;
                jtj[(j, i)] = v;
            }
        }
        self.jac.tr_mul_to(&self.r, g);
        Ok(self.cost)
    }
}

/// Outcome of [`lm_core`].
struct Solved<M: Dense> {
    params: M::Vector,
    cost: f64,
    jtj: M,
    g: M::Vector,
    iterations: usize,
    converged: bool,
}

impl Solved<DMatrix<f64>> {
    /// As an [`NlsReport`] without residuals and Jacobian.
    fn into_report(self, n: usize) -> NlsReport {
        NlsReport {
            params: self.params.as_slice().to_vec(),
            residuals: Vec::new(),
            jacobian: DMatrix::zeros(0, n),
            cost: self.cost,
            iterations: self.iterations,
            converged: self.converged,
        }
    }
}

/// The error of a start at which the model cannot be evaluated.
pub const START_NOT_EVALUABLE: &str = "the model cannot be evaluated at the start values";

/// Predicted cost reduction `-(g^T s + s^T A s / 2)` of the local quadratic model.
#[inline(always)]
fn predicted_gain<M: Mat, V: IndexMut<usize, Output = f64> + ?Sized>(a: &M, g: &V, s: &V) -> f64 {
    let n = a.dim();
    let mut pred = 0.0;
    for i in 0..n {
        let mut hs = 0.0;
        for j in 0..n {
            hs += a.at(i, j) * s[j];
        }
        pred -= g[i] * s[i] + 0.5 * s[i] * hs;
    }
    pred
}

/// Levenberg-Marquardt (Marquardt scaling `diag(J^T J)`, initial damping `lambda0`, monotone:
/// never accepts a step that raises the cost) or, with `opt.gauss_newton`, undamped
/// Gauss-Newton, which takes every finite step and fails with [`CoreError::NotConverged`]
/// when it diverges, meets singular normal equations or reaches the iteration limit. The
/// start must have passed [`check_start`]. `flavor` selects the documented small
/// differences between the public solvers.
#[inline(always)]
fn lm_core<M: Dense, E: Evaluate<M>>(
    prob: &mut E,
    mut p: M::Vector,
    opt: &NlsOptions,
    lambda0: f64,
    flavor: Flavor,
) -> Result<Solved<M>> {
    const START: &str = START_NOT_EVALUABLE;
    let n = M::slice(&p).len();
    let mut jtj = M::zeros(n);
    let mut g = M::zeros_vector(n);
    let start = prob.start(&p, &mut jtj, &mut g);
    let mut cost = match flavor {
        Flavor::Classic => start?,
        _ => start.map_err(|_| CoreError::InvalidInput(START.into()))?,
    };
    if !cost.is_finite() {
        return invalid(START);
    }
    let predicted = flavor != Flavor::Classic;
    let mut lambda = lambda0;
    let mut converged = false;
    let mut it = 0;
    let mut p_new = M::zeros_vector(n);
    let mut step = M::zeros_vector(n);
    let mut diag = M::zeros_vector(n);
    // Cholesky factor of the damped matrix.
    let mut l = M::zeros(n);
    while it < opt.max_iter {
        it += 1;
        for i in 0..n {
            diag[i] = jtj.at(i, i).max(1e-300);
        }
        // max_i |g_i| / sqrt(diag_i) <= gtol sqrt(cost), squared (no root or division per
        // parameter; a NaN component counts as small, as in the maximum of the ratios).
        let t = opt.gtol * cost.sqrt().max(1e-300);
        let small = (0..n).all(|i| !(g[i] * g[i] > t * t * diag[i]));
        if small || cost == 0.0 {
            converged = true;
            break;
        }
        let mut accepted = false;
        for _ in 0..60 {
            let damp = if opt.gauss_newton { 0.0 } else { lambda };
            if !chol_solve_damped(&jtj, &diag, damp, &g, &mut l, &mut step) {
                // Not numerically positive definite (GN on a singular problem, say): the
                // general solver.
                let mut a = DMatrix::<f64>::from_fn(n, n, |i, j| jtj.at(i, j));
                for i in 0..n {
                    a[(i, i)] += damp * diag[i];
                }
                let rhs = DVector::<f64>::from_fn(n, |i, _| -g[i]);
                match a.lu().solve(&rhs) {
                    Some(s) => {
                        for i in 0..n {
                            step[i] = s[i];
                        }
                    }
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
            if M::slice(&p_new).iter().any(|v| !v.is_finite()) {
                if opt.gauss_newton {
                    return Err(CoreError::NotConverged(format!(
                        "Gauss-Newton diverged at iteration {it} (non-finite parameters)"
                    )));
                }
                lambda = lambda.max(1e-12) * 10.0;
                continue;
            }
            let gain = if predicted {
                predicted_gain(&jtj, &g, &step)
            } else {
                f64::INFINITY
            };
            if flavor == Flavor::Stationary
                && (opt.gauss_newton || lambda <= 1e-6)
                && gain <= opt.ftol * cost
            {
                // The current point is a minimum to the tolerance: stay (its normal
                // equations are known).
                converged = true;
                break;
            }
            let c_new = prob.trial(&p_new).unwrap_or(f64::INFINITY);
            let pn: f64 = M::slice(&p).iter().map(|v| v * v).sum::<f64>().sqrt();
            let sn: f64 = M::slice(&step).iter().map(|v| v * v).sum::<f64>().sqrt();
            // Predicted reduction of the local quadratic model: when even the full step can
            // only gain a negligible fraction of the cost, take it (if it does not hurt) and
            // stop without another normal-equation evaluation.
            let negligible = predicted && gain <= opt.ftol * cost;
            if negligible && c_new <= cost && flavor != Flavor::Stationary {
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
                // A step that raises the cost although it is negligible (or, strictly, could
                // only gain a negligible fraction of the cost): a rounding-level minimum.
                let tiny = sn <= opt.xtol * (pn + opt.xtol);
                if predicted && tiny {
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
            cost = prob.accept(&p, &mut jtj, &mut g)?;
            lambda = match flavor {
                Flavor::Classic => (lambda / 3.0).max(1e-12),
                _ => lambda / 3.0,
            };
            accepted = true;
            if rel <= opt.ftol || sn <= opt.xtol * (pn + opt.xtol) {
                converged = true;
            }
            break;
        }
        if converged || !accepted {
            // Converged, or no step decreases the cost at any damping: a (numerical) minimum.
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
    Ok(Solved {
        params: p,
        cost,
        jtj,
        g,
        iterations: it,
        converged,
    })
}

// ------------------------------------------------------------------------------------------
// Range bases for diagnostics (principal angles, projections, pseudo-inverse covariance).

/// Thin SVD `A = U diag(s) V^T` of a small dense matrix: `U` (`m x r`), `s` (`r`, descending),
/// `V^T` (`r x n`) with `r = min(m, n)`. An empty matrix gives empty factors.
pub fn thin_svd(a: &DMatrix<f64>) -> Result<(DMatrix<f64>, Vec<f64>, DMatrix<f64>)> {
    let (m, n) = (a.nrows(), a.ncols());
    if m == 0 || n == 0 {
        return Ok((DMatrix::zeros(m, 0), vec![], DMatrix::zeros(0, n)));
    }
    if a.iter().any(|v| !v.is_finite()) {
        return invalid("a design matrix is not finite");
    }
    let svd = a.clone().svd(true, true);
    let (u, vt) = match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => (u, vt),
        _ => return Err(CoreError::NotConverged("SVD did not converge".into())),
    };
    let s: Vec<f64> = svd.singular_values.iter().copied().collect();
    let mut idx: Vec<usize> = (0..s.len()).collect();
    idx.sort_by(|&x, &y| s[y].total_cmp(&s[x]));
    let us = DMatrix::from_fn(m, idx.len(), |i, k| u[(i, idx[k])]);
    let vts = DMatrix::from_fn(idx.len(), n, |k, j| vt[(idx[k], j)]);
    Ok((us, idx.iter().map(|&i| s[i]).collect(), vts))
}

/// Orthonormal range basis of a Jacobian, its rank, and the pseudo-inverse `(J^T J)^+`.
#[derive(Debug, Clone)]
pub struct RangeBasis {
    /// Orthonormal basis of `range(J)` (`m x rank`).
    pub q: DMatrix<f64>,
    /// `(J^T J)^+` on the kept directions (`n x n`).
    pub cov: DMatrix<f64>,
    /// Numerical rank.
    pub rank: usize,
}

/// [`RangeBasis`] of `j` with columns scaled to unit norm for a scale-free rank decision:
/// singular values below `rtol` times the largest are dropped.
pub fn range_basis(j: &DMatrix<f64>, rtol: f64) -> Result<RangeBasis> {
    let (m, n) = (j.nrows(), j.ncols());
    let d: Vec<f64> = (0..n)
        .map(|c| {
            let v = j.column(c).norm();
            if v > 0.0 {
                v
            } else {
                1.0
            }
        })
        .collect();
    let js = DMatrix::from_fn(m, n, |a, b| j[(a, b)] / d[b]);
    if let Some(rb) = full_rank_basis(&js, &d, rtol) {
        return Ok(rb);
    }
    let (u, s, vt) = thin_svd(&js)?;
    let smax = s.first().copied().unwrap_or(0.0);
    let keep: Vec<usize> = (0..s.len()).filter(|&i| s[i] > rtol * smax).collect();
    let q = DMatrix::from_fn(m, keep.len(), |a, b| u[(a, keep[b])]);
    let mut cov = DMatrix::zeros(n, n);
    for &k in &keep {
        let w = 1.0 / (s[k] * s[k]);
        for a in 0..n {
            let va = vt[(k, a)] * w / d[a];
            for b in 0..n {
                cov[(a, b)] += va * vt[(k, b)] / d[b];
            }
        }
    }
    Ok(RangeBasis {
        q,
        cov,
        rank: keep.len(),
    })
}

/// [`range_basis`] of the column-scaled `js` (scales `d`) by Householder QR, `js = Q R`, when
/// its columns are certainly independent at `rtol`: then the SVD would keep every direction,
/// `Q` spans the same range as its `U` (another orthonormal basis of it) and
/// `(J^T J)^+ = D^-1 R^-1 R^-T D^-1`. Certain means `1 / |R^-1|_F > rtol |R|_F`, a lower bound
/// of `s_min` above `rtol` times an upper bound of `s_max` (it holds whenever the condition
/// number is below about `1 / (n rtol)`). `None` (the caller's SVD decides) otherwise, or when
/// `js` is wide, empty or not finite.
fn full_rank_basis(js: &DMatrix<f64>, d: &[f64], rtol: f64) -> Option<RangeBasis> {
    let (m, n) = (js.nrows(), js.ncols());
    if n == 0 || m < n || js.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let qr = js.clone().qr();
    let r = qr.r();
    let rinv = r.solve_upper_triangular(&DMatrix::identity(n, n))?;
    let (nr, ni) = (r.norm(), rinv.norm());
    if !(ni.is_finite() && nr.is_finite() && 1.0 / ni > rtol * nr) {
        return None;
    }
    let c = &rinv * rinv.transpose();
    Some(RangeBasis {
        q: qr.q(),
        cov: DMatrix::from_fn(n, n, |a, b| c[(a, b)] / d[a] / d[b]),
        rank: n,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_symmetric_eigenvalues_and_cholesky_match_nalgebra() {
        let mut seed = 0x1234_5678_u64;
        let mut rnd = || crate::test_rng::unit(&mut seed) - 0.5;
        for n in [1usize, 2, 3, 9, 12, 13, 24, 30] {
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

    /// The fixed-size factor (whole-row updates) equals the general one to rounding on random
    /// positive definite 9 x 9 matrices, solves and inverts to the same values, and rejects
    /// the same pivot of a matrix that is not positive definite.
    #[test]
    #[allow(clippy::needless_range_loop)] // matrix entries, indexed as written
    fn fixed_size_cholesky_matches_the_general_factor() {
        let mut seed = 11u64;
        for trial in 0..20 {
            let b: Vec<f64> = (0..81)
                .map(|_| crate::test_rng::unit(&mut seed) - 0.5)
                .collect();
            let mut a = [[0.0f64; 9]; 9];
            for i in 0..9 {
                for j in 0..9 {
                    a[i][j] = (0..9).map(|t| b[i * 9 + t] * b[j * 9 + t]).sum::<f64>();
                }
                a[i][i] += 0.05 * (1 + trial) as f64;
            }
            let (mut f, mut g) = (a, RowMajor::zeros(9));
            for i in 0..9 {
                for j in 0..9 {
                    *g.at_mut(i, j) = a[i][j];
                }
            }
            assert!(cholesky_full(&mut f, |_, s| s > 0.0));
            assert!(cholesky_lower(&mut g, |_, s| s > 0.0));
            for i in 0..9 {
                for j in 0..=i {
                    assert!((f[i][j] - g.at(i, j)).abs() <= 1e-12, "{i} {j}");
                }
            }
            let rhs: [f64; 9] = std::array::from_fn(|i| i as f64 - 4.0);
            let mut x = rhs;
            cholesky_solve(&f, &mut x);
            for i in 0..9 {
                let ax: f64 = (0..9).map(|j| a[i][j] * x[j]).sum();
                assert!((ax - rhs[i]).abs() <= 1e-9, "{ax} {}", rhs[i]);
            }
            let c = covariance_normal_fixed(&a, 1e-9).unwrap();
            for i in 0..9 {
                for j in 0..9 {
                    let e: f64 = (0..9).map(|t| a[i][t] * c[t][j]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((e - want).abs() <= 1e-8, "{i} {j} {e}");
                }
            }
        }
        // Pivot 2 of this matrix is -3: both factors stop there.
        let bad = [[1.0, 2.0, 0.0], [2.0, 5.0, 2.0], [0.0, 2.0, 1.0]];
        let seen = std::cell::Cell::new(0);
        let mut f = bad;
        assert!(!cholesky_full(&mut f, |k, s| {
            seen.set(k);
            s > 0.0
        }));
        assert_eq!(seen.get(), 2);
        let mut g = RowMajor::zeros(3);
        for i in 0..3 {
            for j in 0..3 {
                *g.at_mut(i, j) = bad[i][j];
            }
        }
        assert!(!cholesky_lower(&mut g, |k, s| k < 2 || s > 0.0));
    }

    /// The normal equations summed in AVX2 lanes give the portable lanes' solution (to the
    /// rounding of the fused multiply-adds).
    #[test]
    fn normal_equation_lanes_agree_across_kernels() {
        let row = |i: usize| {
            let x = i as f64 * 0.13;
            (
                [1.0, x, x * x, x.sin(), x.cos()],
                1.0 - x + 0.2 * x * x + 0.05 * x.sin(),
            )
        };
        let p = lstsq_normal_lanes::<Portable, 5>(&RowFn(37, row)).unwrap();
        #[cfg(target_arch = "x86_64")]
        if crate::lanes::avx2_fma() {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn run(row: impl Fn(usize) -> ([f64; 5], f64)) -> [f64; 5] {
                lstsq_normal_lanes::<crate::lanes::Avx2Fma, 5>(&RowFn(37, row)).unwrap()
            }
            // SAFETY: checked just above.
            let v = unsafe { run(row) };
            for (a, b) in v.iter().zip(&p) {
                assert!((a - b).abs() <= 1e-10 * b.abs().max(1.0), "{a} {b}");
            }
        }
        let q = lstsq_fn::<5>(37, row).unwrap();
        for (a, b) in q.iter().zip(&p) {
            assert!((a - b).abs() <= 1e-8 * b.abs().max(1.0), "{a} {b}");
        }
    }

    #[test]
    fn normal_equation_lstsq_agrees_with_qr_and_falls_back_when_ill_conditioned() {
        let xs: Vec<f64> = (0..30).map(|i| i as f64 * 0.1).collect();
        let row = |i: usize| {
            let x = xs[i];
            (
                [1.0, x, x * x, x.sin()],
                2.0 - 3.0 * x + 0.5 * x * x + 0.1 * (7.0 * x).cos(),
            )
        };
        let q = lstsq_fn::<4>(30, row).unwrap();
        let n = lstsq_normal_fn::<4>(30, row).unwrap();
        for (a, b) in q.iter().zip(&n) {
            assert!((a - b).abs() < 1e-9 * a.abs().max(1.0), "{a} {b}");
        }
        // Columns equal to 1e-7: the normal matrix is too ill-conditioned; the QR answers.
        let ill = |i: usize| {
            let x = xs[i];
            ([1.0, x, x + 1e-7 * x * x], 1.0 + x + 1e-7 * x * x)
        };
        let q = lstsq_fn::<3>(30, ill).unwrap();
        let n = lstsq_normal_fn::<3>(30, ill).unwrap();
        assert_eq!(q, n);
        // A zero column is the same error.
        let zero = |i: usize| ([1.0, 0.0], xs[i]);
        assert!(matches!(
            lstsq_normal_fn::<2>(30, zero),
            Err(CoreError::Degenerate(_))
        ));
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

    /// The QR basis of a full-rank Jacobian is the SVD's range basis in another orthonormal
    /// basis (the same projection), with the same pseudo-inverse; a rank-deficient or
    /// numerically rank-deficient one goes to the SVD, which drops the direction.
    #[test]
    fn range_basis_by_qr_matches_the_svd() {
        let mut seed = 11u64;
        let mut rnd = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        // Columns of very different sizes (the column scaling makes the decision scale-free).
        let scale = [1.0, 1e3, 1e-4, 10.0, 1.0, 1e6, 2.0, 1e-2, 1.0];
        let j = DMatrix::from_fn(30, 9, |_, c| rnd() * scale[c]);
        let d: Vec<f64> = (0..9).map(|c| j.column(c).norm()).collect();
        let js = DMatrix::from_fn(30, 9, |a, b| j[(a, b)] / d[b]);
        let qr = full_rank_basis(&js, &d, 1e-9).expect("a well-conditioned design");
        let (u, s, vt) = thin_svd(&js).unwrap();
        assert_eq!(qr.rank, 9);
        assert!((qr.q.transpose() * &qr.q - DMatrix::identity(9, 9)).norm() < 1e-13);
        let (pq, pu) = (&qr.q * qr.q.transpose(), &u * u.transpose());
        assert!((pq - pu).norm() < 1e-12);
        let svd_cov = DMatrix::from_fn(9, 9, |a, b| {
            (0..9)
                .map(|k| vt[(k, a)] * vt[(k, b)] / (s[k] * s[k]) / d[a] / d[b])
                .sum::<f64>()
        });
        for a in 0..9 {
            for b in 0..9 {
                let tol = 1e-10 * (svd_cov[(a, a)] * svd_cov[(b, b)]).sqrt();
                assert!((qr.cov[(a, b)] - svd_cov[(a, b)]).abs() < tol, "{a} {b}");
            }
        }
        assert_eq!(range_basis(&j, 1e-9).unwrap().q.ncols(), 9);
        // A column that is another's multiple, exactly or to 1e-12: the SVD path, rank 8.
        for eps in [0.0, 1e-12] {
            let mut jd = j.clone();
            let c0 = j.column(0).clone_owned();
            jd.set_column(
                4,
                &(c0 * 3.0 + DVector::from_fn(30, |i, _| eps * (i as f64).sin())),
            );
            let dd: Vec<f64> = (0..9).map(|c| jd.column(c).norm()).collect();
            let jsd = DMatrix::from_fn(30, 9, |a, b| jd[(a, b)] / dd[b]);
            assert!(full_rank_basis(&jsd, &dd, 1e-9).is_none(), "eps {eps}");
            let rb = range_basis(&jd, 1e-9).unwrap();
            assert_eq!((rb.rank, rb.q.ncols()), (8, 8), "eps {eps}");
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

    impl NormalEquationsFixed<2> for ExpoN {
        fn n_residuals(&self) -> usize {
            self.0.t.len()
        }
        fn cost(&self, p: &[f64; 2]) -> Result<f64> {
            NormalEquations::cost(self, p)
        }
        fn normal(&self, p: &[f64; 2], jtj: &mut [[f64; 2]; 2], g: &mut [f64; 2]) -> Result<f64> {
            let (mut a, mut b) = (DMatrix::zeros(2, 2), DVector::zeros(2));
            let c = NormalEquations::normal(self, p, &mut a, &mut b)?;
            for i in 0..2 {
                g[i] = b[i];
                for j in 0..2 {
                    jtj[i][j] = a[(i, j)];
                }
            }
            Ok(c)
        }
    }

    #[test]
    fn all_solver_adapters_agree_and_gn_errors_are_shared() {
        // Noisy data: a non-zero minimum.
        let t: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let y: Vec<f64> = (t.iter().enumerate())
            .map(|(i, t)| 3.0 * (-0.7 * t).exp() + 1e-3 * ((i * 7919) % 13) as f64)
            .collect();
        let prob = ExpoN(Expo { t, y });
        let p0 = [2.0, 0.5];
        let lm = NlsOptions::default();
        let gn = NlsOptions {
            gauss_newton: true,
            max_iter: 50,
            ..lm
        };
        let want = solve_nls(&prob.0, &p0, &lm).unwrap();
        let runs = [
            solve_nls(&prob.0, &p0, &gn).unwrap().params,
            solve_normal(&prob, &p0, &lm, 1e-3).unwrap().params,
            solve_normal(&prob, &p0, &gn, 1e-3).unwrap().params,
            solve_normal_gn(&prob, &p0, &lm).unwrap().params,
            solve_normal_fixed(&prob, &p0, &lm, 1e-3)
                .unwrap()
                .params
                .to_vec(),
        ];
        for got in runs {
            for (a, b) in got.iter().zip(&want.params) {
                assert!((a - b).abs() <= 1e-9 * b.abs(), "{got:?} {:?}", want.params);
            }
        }
        // The residuals and Jacobian reported by solve_nls are those at the solution.
        let (mut r, mut j) = (vec![0.0; 30], DMatrix::zeros(30, 2));
        prob.0.eval(&want.params, &mut r, &mut j).unwrap();
        assert_eq!(r, want.residuals);
        assert_eq!(j, want.jacobian);
        assert_eq!(want.cost, sumsq(&r));
        // Undamped GN from far away: the same divergence error from every GN entry point.
        let far = [1e3, -5.0];
        let one = NlsOptions { max_iter: 1, ..gn };
        let msgs = [
            solve_nls(&prob.0, &far, &one).unwrap_err().to_string(),
            solve_normal_gn(&prob, &far, &one).unwrap_err().to_string(),
        ];
        assert_eq!(msgs[0], msgs[1]);
        assert!(msgs[0].contains("Gauss-Newton"), "{}", msgs[0]);
        // Fixed-size and heap covariance / power iteration are the same arithmetic.
        let jn = DMatrix::<f64>::from_fn(30, 3, |i, k| ((i + 1) as f64).powi(k as i32 - 1));
        let c = covariance_small(&jn, 1e-12).unwrap();
        let jtj = jn.transpose() * &jn;
        let nf: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|k| jtj[(i, k)]));
        let cf = covariance_normal_fixed(&nf, 1e-12).unwrap();
        let (lam, v) = top_eigen(&c, 500);
        let (lamf, vf) = top_eigen_fixed(&cf, 500);
        assert!((lam / lamf - 1.0).abs() < 1e-12 && (v[0] / vf[0] - 1.0).abs() < 1e-9);
        for i in 0..3 {
            for k in 0..3 {
                assert!((c[(i, k)] - cf[i][k]).abs() <= 1e-12 * c[(i, k)].abs().max(1e-300));
            }
        }
    }
}

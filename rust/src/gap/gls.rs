//! The variance-component noise model: a random offset per row on top of the noise model.
//!
//! A real hand-placed session rarely fits its noise model: every placement seats the sensor a
//! little differently, and the residual of each dwell carries a persistent offset of its own.
//! Modelled as a random effect, the residual of row `k` has variance `sigma_k^2 + s^2`:
//! `sigma_k` from the noise model, `s^2` the variance of the per-row offset. The engine then
//! weighs every row by `1 / (sigma_k^2 + s^2)` (generalised least squares) in its tests, its
//! min-p family correction and its held-out gate, re-estimating `s^2` under every model it
//! compares (an offset that an effect explains must not also count as noise).
//!
//! `s^2` is the Paule-Mandel moment estimate: the root of the generalised chi2
//! `Q(s^2) = sum_k res_k(s^2)^2 / (sigma_k^2 + s^2) = n - rank`, `res(s^2)` the weighted
//! least-squares residual of the model at weights `1 / (sigma_k^2 + s^2)` (`s^2 = 0` when the
//! noise model alone already explains the residual, `Q(0) <= n - rank`). `Q` decreases in
//! `s^2`, and by the envelope theorem `dQ/ds^2 = -sum res_k^2 / (sigma_k^2 + s^2)^2` at the
//! weighted optimum, which gives a safeguarded Newton iteration. At the true `s^2` the
//! estimating equation is unbiased for a linear model (`E Q = n - rank`).
//!
//! Everything here works in the engine's base units: rows whitened by the noise model
//! (`e_k = r_k / sigma_k`), so the weights of the variance-component model are the factors
//! `f_k = sigma_k / sqrt(sigma_k^2 + s^2)` applied to every whitened row.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use crate::lsq::RangeBasis;
use nalgebra::{DMatrix, DVector};

/// Row factors `f_k = sigma_k / sqrt(sigma_k^2 + s2)` that turn base-whitened rows into rows
/// whitened by the variance-component model (`sigma` physical, `s2` physical squared).
pub fn factors(sigma: &[f64], s2: f64) -> Vec<f64> {
    if !(s2 > 0.0) {
        return vec![1.0; sigma.len()];
    }
    sigma
        .iter()
        .map(|&s| {
            if s > 0.0 {
                s / (s * s + s2).sqrt()
            } else {
                1.0
            }
        })
        .collect()
}

/// Weighted least-squares residual of `e` on the columns of `b` (full column rank) with row
/// weights `w` (the squared factors), by the normal equations of the small system.
fn wls_residual(b: &DMatrix<f64>, e: &[f64], w: &[f64]) -> Option<Vec<f64>> {
    let (n, r) = (b.nrows(), b.ncols());
    if r == 0 {
        return Some(e.to_vec());
    }
    let mut g = DMatrix::<f64>::zeros(r, r);
    let mut rhs = DVector::<f64>::zeros(r);
    for k in 0..n {
        for a in 0..r {
            let ba = w[k] * b[(k, a)];
            rhs[a] += ba * e[k];
            for c in 0..=a {
                g[(a, c)] += ba * b[(k, c)];
            }
        }
    }
    for a in 0..r {
        for c in 0..a {
            g[(c, a)] = g[(a, c)];
        }
    }
    let beta = g.cholesky()?.solve(&rhs);
    Some(
        (0..n)
            .map(|k| e[k] - (0..r).map(|a| b[(k, a)] * beta[a]).sum::<f64>())
            .collect(),
    )
}

/// The generalised chi2 `Q(s2)` and its derivative in `s2` (envelope theorem) of the model
/// spanned by `b` (base-whitened, full column rank).
fn q_and_slope(b: &DMatrix<f64>, e: &[f64], sigma: &[f64], s2: f64) -> Option<(f64, f64)> {
    let f = factors(sigma, s2);
    let w: Vec<f64> = f.iter().map(|v| v * v).collect();
    let res = wls_residual(b, e, &w)?;
    let mut q = 0.0;
    let mut slope = 0.0;
    for k in 0..e.len() {
        let t = w[k] * res[k] * res[k];
        q += t;
        if sigma[k] > 0.0 {
            slope -= t * w[k] / (sigma[k] * sigma[k]);
        }
    }
    Some((q, slope))
}

/// Paule-Mandel estimate of the per-row offset variance (physical units squared) of the model
/// whose base-whitened Jacobian spans the columns of `b` (full column rank), with base-whitened
/// residual `e` and noise `sigma` (physical): the root of `Q(s2) = dof`, 0 when `Q(0) <= dof`.
/// `start` is a first guess (e.g. the estimate of a nested model).
pub fn pm_offset(b: &DMatrix<f64>, e: &[f64], sigma: &[f64], dof: f64, start: f64) -> f64 {
    if !(dof > 0.0) {
        return 0.0;
    }
    let Some((q0, _)) = q_and_slope(b, e, sigma, 0.0) else {
        return 0.0;
    };
    if !(q0 > dof) {
        return 0.0;
    }
    // Bracket: Q(lo) > dof >= Q(hi). Q(s2) <= sum r^2 / s2, so hi = sum r^2 / dof brackets.
    let r2: f64 = e
        .iter()
        .zip(sigma)
        .map(|(v, s)| (v * s) * (v * s))
        .sum::<f64>();
    let (mut lo, mut hi) = (0.0, (r2 / dof).max(1e-300));
    let mut s2 = if start > 0.0 && start < hi {
        start
    } else {
        0.5 * hi
    };
    for _ in 0..60 {
        let Some((q, slope)) = q_and_slope(b, e, sigma, s2) else {
            break;
        };
        if q > dof {
            lo = s2;
        } else {
            hi = s2;
        }
        if (q - dof).abs() <= 1e-10 * dof || hi - lo <= 1e-12 * hi {
            break;
        }
        let newton = if slope < 0.0 {
            s2 - (q - dof) / slope
        } else {
            f64::NAN
        };
        s2 = if newton > lo && newton < hi {
            newton
        } else {
            0.5 * (lo + hi)
        };
    }
    s2
}

/// A whitening of the model at one point: row factors, an orthonormal basis of the whitened
/// Jacobian's range, and the whitened residual projected off it (the weighted fit's residual,
/// to first order).
#[derive(Debug, Clone)]
pub struct Space {
    /// Variance of the per-row offset (physical units squared).
    pub s2: f64,
    /// Row factors (base-whitened to this whitening).
    pub f: Vec<f64>,
    /// Range basis of the whitened Jacobian (`q`, `rank`; `cov` is not computed).
    pub basis: RangeBasis,
    /// Whitened residual, projected off the basis.
    pub e: DVector<f64>,
    /// Its squared norm.
    pub rss: f64,
}

/// The whitening with offset variance `s2` of a model whose base-whitened Jacobian has the
/// orthonormal range basis `q`, at base-whitened residual `e` and noise `sigma`.
pub fn space(q: &DMatrix<f64>, e: &DVector<f64>, sigma: &[f64], s2: f64) -> Space {
    let n = e.len();
    let f = factors(sigma, s2);
    let ef = DVector::from_fn(n, |k, _| e[k] * f[k]);
    let qf = if s2 > 0.0 && q.ncols() > 0 {
        DMatrix::from_fn(n, q.ncols(), |k, c| q[(k, c)] * f[k])
            .qr()
            .q()
    } else {
        q.clone()
    };
    let ep = &ef - &qf * (qf.transpose() * &ef);
    let rss = ep.norm_squared();
    let rank = qf.ncols();
    Space {
        s2,
        f,
        basis: RangeBasis {
            q: qf,
            cov: DMatrix::zeros(0, 0),
            rank,
        },
        e: ep,
        rss,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gap::statics::tests::Rng;

    /// `n` rows of a straight line with heteroscedastic noise and a random offset of
    /// variance `s2` per row: (orthonormal basis of [1, x] in base-whitened units, e, sigma).
    fn line(n: usize, s2: f64, seed: u64) -> (DMatrix<f64>, DVector<f64>, Vec<f64>) {
        let mut rng = Rng(seed);
        let sigma: Vec<f64> = (0..n).map(|k| 0.5 + (k % 4) as f64 * 0.5).collect();
        let x: Vec<f64> = (0..n).map(|k| k as f64 / n as f64).collect();
        let y: Vec<f64> = (0..n)
            .map(|k| 1.0 + 2.0 * x[k] + sigma[k] * rng.normal() + s2.sqrt() * rng.normal())
            .collect();
        let j = DMatrix::from_fn(n, 2, |k, c| [1.0, x[k]][c] / sigma[k]);
        let q = j.qr().q();
        let e = DVector::from_fn(n, |k, _| y[k] / sigma[k]);
        let e = &e - &q * (q.transpose() * &e);
        (q, e, sigma)
    }

    #[test]
    fn pm_offset_solves_the_generalised_chi2_equation() {
        let (q, e, sigma) = line(60, 4.0, 3);
        let s2 = pm_offset(&q, e.as_slice(), &sigma, 58.0, 0.0);
        assert!(s2 > 0.5 && s2 < 12.0, "{s2}");
        // At the root the weighted refit's chi2 is n - rank (the basis is re-projected).
        let sp = space(&q, &e, &sigma, s2);
        assert!((sp.rss - 58.0).abs() < 1e-6, "{}", sp.rss);
        // Independent check: the weighted least-squares line at weights 1/(sigma^2 + s2),
        // solved in closed form, gives the same chi2.
        let n = 60;
        let x: Vec<f64> = (0..n).map(|k| k as f64 / n as f64).collect();
        let y: Vec<f64> = (0..n).map(|k| e[k] * sigma[k]).collect();
        let w: Vec<f64> = sigma.iter().map(|s| 1.0 / (s * s + s2)).collect();
        let (sw, sx, sy) = (
            w.iter().sum::<f64>(),
            (0..n).map(|k| w[k] * x[k]).sum::<f64>(),
            (0..n).map(|k| w[k] * y[k]).sum::<f64>(),
        );
        let sxx = (0..n).map(|k| w[k] * x[k] * x[k]).sum::<f64>();
        let sxy = (0..n).map(|k| w[k] * x[k] * y[k]).sum::<f64>();
        let det = sw * sxx - sx * sx;
        let (a, b) = ((sxx * sy - sx * sxy) / det, (sw * sxy - sx * sy) / det);
        let chi2: f64 = (0..n).map(|k| w[k] * (y[k] - a - b * x[k]).powi(2)).sum();
        assert!((chi2 - 58.0).abs() < 1e-6, "{chi2}");
        // No excess: zero.
        let (q, e, sigma) = line(60, 0.0, 4);
        let q0: f64 = e.norm_squared();
        let s0 = pm_offset(&q, e.as_slice(), &sigma, q0 + 1.0, 0.0);
        assert_eq!(s0, 0.0);
    }

    #[test]
    fn pm_offset_is_unbiased_in_the_mean() {
        // Mean of the estimate over many sessions near the true variance (the moment
        // estimator is consistent; its mean is within a few per cent at n = 80).
        let mut sum = 0.0;
        for seed in 0..200 {
            let (q, e, sigma) = line(80, 2.0, 100 + seed);
            sum += pm_offset(&q, e.as_slice(), &sigma, 78.0, 0.0);
        }
        let mean = sum / 200.0;
        assert!((mean / 2.0 - 1.0).abs() < 0.15, "{mean}");
    }

    #[test]
    fn factors_and_space_reduce_to_the_base_whitening_without_offset() {
        assert_eq!(factors(&[1.0, 2.0], 0.0), vec![1.0, 1.0]);
        let f = factors(&[3.0], 16.0);
        assert!((f[0] - 0.6).abs() < 1e-15);
        let (q, e, sigma) = line(20, 0.0, 9);
        let sp = space(&q, &e, &sigma, 0.0);
        assert!((sp.rss - e.norm_squared()).abs() < 1e-12);
        let sp = space(&q, &e, &sigma, 5.0);
        assert!((sp.basis.q.transpose() * &sp.e).norm() < 1e-10);
        assert_eq!(sp.basis.rank, 2);
    }
}

//! Family-wise correction by the exact min-p (Westfall-Young, max-statistic) method.
//!
//! The adjusted p-value of the best of a family of tests is the probability, under the null
//! of the current model, that the smallest p-value over the family is at most the observed
//! one. Each member is a test in its own whitening (the noise model, or the noise model plus a
//! per-row offset variance estimated under that member's model, see [`super::gls`]): its null
//! whitened residual is `(I - Q_m Q_m^T) z`, `z ~ N(0, I)`, with `Q_m` the orthonormal range
//! basis of the current Jacobian in that whitening, so every member's null distribution is its
//! own exact one (chi2 score or sigma-free F, the test chosen on the data), and the draws `z`
//! they share give the dependence between them. Monte Carlo with fixed-seed draws
//! (deterministic), never above the Bonferroni bound `M p`.

use super::special::{chi2_isf, f_isf};
use nalgebra::DMatrix;
use std::sync::Arc;

/// One test of a family, as the min-p correction needs it.
#[derive(Debug, Clone)]
pub struct Member {
    /// Orthonormal range basis of the current Jacobian in this member's whitening (members
    /// of one whitening share it).
    pub q: Arc<DMatrix<f64>>,
    /// Orthonormal projected directions (`n x d`), orthogonal to `q`.
    pub w: DMatrix<f64>,
    /// chi2 score test (else the sigma-free F test).
    pub chi2: bool,
    /// Denominator degrees of freedom of the F test.
    pub dof2: f64,
    /// Observed p-value.
    pub p: f64,
    /// Observed statistic (score for chi2, F for F).
    pub stat: f64,
}

const POOL_LEN: usize = 1 << 18;
const POOL_SEED: u64 = 0x9E37_79B9_7F4A_7C15;
static NULL_POOL: std::sync::OnceLock<Vec<f64>> = std::sync::OnceLock::new();

/// `len` standard normals from a fixed seed (xoshiro256++, Marsaglia polar method).
pub fn normals(seed: u64, len: usize) -> Vec<f64> {
    let mut sm = seed;
    let mut next_sm = || {
        sm = sm.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = sm;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut st = [next_sm(), next_sm(), next_sm(), next_sm()];
    let mut next = || {
        let r = st[0]
            .wrapping_add(st[3])
            .rotate_left(23)
            .wrapping_add(st[0]);
        let t = st[1] << 17;
        st[2] ^= st[0];
        st[3] ^= st[1];
        st[1] ^= st[2];
        st[0] ^= st[3];
        st[2] ^= t;
        st[3] = st[3].rotate_left(45);
        (r >> 11) as f64 * (1.0 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    let mut out = Vec::with_capacity(len + 1);
    while out.len() < len {
        let (u, v) = (next(), next());
        let s = u * u + v * v;
        if s >= 1.0 || s == 0.0 {
            continue;
        }
        let f = (-2.0 * s.ln() / s).sqrt();
        out.push(u * f);
        out.push(v * f);
    }
    out.truncate(len);
    out
}

/// The stacked rows `[Q_a^T; Q_b^T; ...; W_1^T; ...; W_M^T]` (each distinct basis once).
struct Stacked {
    at: DMatrix<f64>,
    /// First row and rank of each distinct basis.
    bases: Vec<(usize, usize)>,
    /// Per member: index of its basis, first row of its directions.
    member: Vec<(usize, usize)>,
}

fn stack_family(fam: &[Member]) -> Stacked {
    let m = fam.first().map_or(0, |f| f.w.nrows());
    let mut distinct: Vec<&Arc<DMatrix<f64>>> = vec![];
    let mut which = Vec::with_capacity(fam.len());
    for f in fam {
        match distinct.iter().position(|q| Arc::ptr_eq(q, &f.q)) {
            Some(i) => which.push(i),
            None => {
                which.push(distinct.len());
                distinct.push(&f.q);
            }
        }
    }
    let nq: usize = distinct.iter().map(|q| q.ncols()).sum();
    let ncol = nq + fam.iter().map(|f| f.w.ncols()).sum::<usize>();
    let mut at = DMatrix::zeros(ncol, m);
    let mut bases = Vec::with_capacity(distinct.len());
    let mut c0 = 0;
    for q in &distinct {
        bases.push((c0, q.ncols()));
        for j in 0..q.ncols() {
            at.row_mut(c0 + j).copy_from(&q.column(j).transpose());
        }
        c0 += q.ncols();
    }
    let mut member = Vec::with_capacity(fam.len());
    for (f, &b) in fam.iter().zip(&which) {
        member.push((b, c0));
        for j in 0..f.w.ncols() {
            at.row_mut(c0 + j).copy_from(&f.w.column(j).transpose());
        }
        c0 += f.w.ncols();
    }
    Stacked { at, bases, member }
}

/// The statistic of each member at which its p-value equals `p_obs` (one inversion per
/// distinct test).
fn critical_values(fam: &[Member], p_obs: f64) -> Vec<f64> {
    let mut cache: Vec<(bool, usize, f64, f64)> = vec![];
    fam.iter()
        .map(|f| {
            let d = f.w.ncols();
            if f.p <= p_obs {
                return f.stat;
            }
            let key_dof2 = if f.chi2 { 0.0 } else { f.dof2 };
            if let Some(c) = cache
                .iter()
                .find(|c| c.0 == f.chi2 && c.1 == d && c.2 == key_dof2)
            {
                return c.3;
            }
            let c = if f.chi2 {
                chi2_isf(p_obs, d as f64)
            } else {
                f_isf(p_obs, d as f64, f.dof2)
            };
            cache.push((f.chi2, d, key_dof2, c));
            c
        })
        .collect()
}

/// Whether one null draw (its projections `col` on the stacked rows, squared norm `zz`)
/// reaches a member's critical value.
fn draw_hits(col: &[f64], zz: f64, st: &Stacked, fam: &[Member], crit: &[f64]) -> bool {
    let mut rss = [0.0; 8];
    let mut rss_v = vec![];
    let rss: &mut [f64] = if st.bases.len() <= rss.len() {
        &mut rss[..st.bases.len()]
    } else {
        rss_v.resize(st.bases.len(), 0.0);
        &mut rss_v
    };
    for (b, &(r0, r)) in st.bases.iter().enumerate() {
        rss[b] = zz - col[r0..r0 + r].iter().map(|v| v * v).sum::<f64>();
    }
    fam.iter().enumerate().any(|(i, f)| {
        let d = f.w.ncols();
        let (b, off) = st.member[i];
        let sc: f64 = col[off..off + d].iter().map(|v| v * v).sum();
        if f.chi2 {
            sc >= crit[i]
        } else {
            let rem = rss[b] - sc;
            rem <= 0.0 || (sc / d as f64) >= crit[i] * rem / f.dof2
        }
    })
}

/// Min-p adjusted p-value of the best of `fam` (observed smallest p-value `p_obs`).
/// Sequential Monte Carlo (250 fixed-seed draws, then chunks of 500, at most `n_draws`,
/// stopped once the estimate is 3 standard errors from `alpha`); the estimate
/// `(k + 1) / (b + 1)` is capped by the Bonferroni bound `M p_obs`.
pub fn min_p(fam: &[Member], p_obs: f64, alpha: f64, n_draws: usize) -> f64 {
    let m_fam = fam.len();
    if m_fam == 0 || !p_obs.is_finite() {
        return f64::NAN;
    }
    let bonf = (p_obs * m_fam as f64).min(1.0);
    if m_fam == 1 || p_obs <= 0.0 || bonf < 1e-4 || n_draws == 0 {
        return if m_fam == 1 { p_obs } else { bonf };
    }
    let m = fam[0].w.nrows();
    let st = stack_family(fam);
    let crit = critical_values(fam, p_obs);
    let local;
    let pool: &[f64] = if m * n_draws <= POOL_LEN {
        NULL_POOL.get_or_init(|| normals(POOL_SEED, POOL_LEN))
    } else {
        local = normals(POOL_SEED ^ m as u64, m * n_draws);
        &local
    };
    let (mut hits, mut done) = (0usize, 0usize);
    while done < n_draws {
        let bc = (if done == 0 { 250 } else { 500 }).min(n_draws - done);
        let zs = nalgebra::DMatrixView::from_slice(&pool[done * m..(done + bc) * m], m, bc);
        let pm = &st.at * zs;
        for b in 0..bc {
            let zz = zs.column(b).norm_squared();
            hits += draw_hits(pm.column(b).as_slice(), zz, &st, fam, &crit) as usize;
        }
        done += bc;
        let ph = (hits + 1) as f64 / (done + 1) as f64;
        let se = (alpha * (1.0 - alpha) / done as f64).sqrt();
        if (ph - alpha).abs() > 3.0 * se {
            break;
        }
    }
    ((hits + 1) as f64 / (done + 1) as f64).min(bonf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gap::special::chi2_sf;

    #[test]
    fn min_p_matches_closed_forms() {
        // n = 40, Q = first 5 unit vectors; members are further unit vectors (orthogonal to Q).
        let n = 40;
        let q = Arc::new(DMatrix::from_fn(
            n,
            5,
            |a, b| if a == b { 1.0 } else { 0.0 },
        ));
        let unit = |k: usize| DMatrix::from_fn(n, 1, |a, _| if a == k { 1.0 } else { 0.0 });
        let p_obs: f64 = 0.02;
        let crit = chi2_isf(p_obs, 1.0);
        assert!((chi2_sf(crit, 1.0) - p_obs).abs() < 1e-9);
        let mk = |w: DMatrix<f64>, p: f64| Member {
            q: q.clone(),
            w,
            chi2: true,
            dof2: 30.0,
            p,
            stat: chi2_isf(p, 1.0),
        };
        // Two identical members: min-p = the single-test p-value (no multiplicity).
        let same = [mk(unit(7), p_obs), mk(unit(7), 0.3)];
        let pa = min_p(&same, p_obs, 0.05, 4000);
        assert!((pa - p_obs).abs() < 0.008, "{pa}");
        // Four independent members: 1 - (1 - p)^4 = 0.0776 (Bonferroni 0.08).
        let ind = [
            mk(unit(7), p_obs),
            mk(unit(8), 0.5),
            mk(unit(9), 0.5),
            mk(unit(10), 0.5),
        ];
        let pa = min_p(&ind, p_obs, 0.05, 4000);
        let want = 1.0 - (1.0 - p_obs).powi(4);
        assert!((pa - want).abs() < 0.015, "{pa} vs {want}");
        assert!(pa <= 4.0 * p_obs + 1e-12);
        // Deterministic.
        assert_eq!(pa, min_p(&ind, p_obs, 0.05, 4000));
    }

    #[test]
    fn f_members_use_their_own_whitening() {
        // F members in their own whitenings (distinct Arcs). Two members with the same
        // directions and bases of the same content hit together: the adjusted p-value is the
        // single test's exact p-value, which needs each member's own residual (40 - 5 - 1
        // degrees of freedom) in its denominator.
        let n = 40;
        let basis = |r: usize| Arc::new(DMatrix::from_fn(n, r, |a, b| f64::from(u8::from(a == b))));
        let unit = |k: usize| DMatrix::from_fn(n, 1, |a, _| f64::from(u8::from(a == k)));
        let p_obs = 0.03;
        let f_mem = |q: Arc<DMatrix<f64>>, k: usize, p: f64| {
            let dof2 = (n - q.ncols() - 1) as f64;
            Member {
                w: unit(k),
                chi2: false,
                dof2,
                p,
                stat: f_isf(p, 1.0, dof2),
                q,
            }
        };
        let fam = [f_mem(basis(5), 20, p_obs), f_mem(basis(5), 20, 0.4)];
        // alpha = p_obs: the sequential stop never triggers early, all draws are used.
        let pa = min_p(&fam, p_obs, p_obs, 20_000);
        assert!((pa - p_obs).abs() < 0.005, "{pa}");
        // Independent directions in whitenings of 5 and 8 columns: nearly independent tests,
        // 1 - (1 - p)^2 = 0.0591, never above Bonferroni.
        let fam = [f_mem(basis(5), 20, p_obs), f_mem(basis(8), 21, 0.5)];
        let pa = min_p(&fam, p_obs, 0.0591, 20_000);
        assert!((pa - 0.0591).abs() < 0.006, "{pa}");
        assert!(pa <= 2.0 * p_obs + 1e-12);
    }

    #[test]
    fn normals_have_unit_variance() {
        let z = normals(3, 100_000);
        let m = z.iter().sum::<f64>() / z.len() as f64;
        let v = z.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / z.len() as f64;
        assert!(m.abs() < 0.01 && (v - 1.0).abs() < 0.02, "{m} {v}");
    }
}

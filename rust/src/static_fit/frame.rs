//! The frame change: fitting runs on `am' = (am - c) / s`, chosen so that `K' ~ I` and
//! `b' ~ 0`. Raw-count data (offsets ~33000, ~414 counts per m/s^2) are then as well
//! conditioned as data in m/s^2. Every parameter scales by `1 / s`; the biases also shift by
//! `c`.

// `!(x > t)` is deliberate throughout: it is true for NaN, so bad values fail the test.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::Model;
use crate::dwell::{from_total_key, total_key};
use crate::error::{degenerate, Result};

/// `am' = (am - c) / s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    /// Offset (output units).
    pub c: [f64; 3],
    /// Scale (output units per frame unit).
    pub s: f64,
}

impl Frame {
    /// The identity frame.
    pub const IDENTITY: Frame = Frame {
        c: [0.0; 3],
        s: 1.0,
    };

    /// Parameters in output units to frame units.
    #[inline]
    pub fn to_frame(self, p: &[f64; 9]) -> [f64; 9] {
        let mut q = p.map(|v| v / self.s);
        for i in 0..3 {
            q[3 + i] = (p[3 + i] - self.c[i]) / self.s;
        }
        q
    }

    /// Parameters in frame units to output units.
    #[inline]
    pub fn unframe(self, q: &[f64; 9]) -> [f64; 9] {
        let mut p = q.map(|v| v * self.s);
        for i in 0..3 {
            p[3 + i] = q[3 + i] * self.s + self.c[i];
        }
        p
    }

    /// One point in frame units.
    #[inline(always)]
    pub fn point(self, m: &[f64; 3]) -> [f64; 3] {
        self.point_scaled(m, 1.0 / self.s)
    }

    /// [`Self::point`] with `is = 1 / s` given.
    #[inline(always)]
    fn point_scaled(self, m: &[f64; 3], is: f64) -> [f64; 3] {
        [
            (m[0] - self.c[0]) * is,
            (m[1] - self.c[1]) * is,
            (m[2] - self.c[2]) * is,
        ]
    }

    /// Points in frame units, written into `out` (cleared first).
    pub fn points_into(self, means: &[[f64; 3]], out: &mut Vec<[f64; 3]>) {
        // `point` with the reciprocal of the scale taken once (the same values).
        let is = 1.0 / self.s;
        out.clear();
        out.extend(means.iter().map(|m| self.point_scaled(m, is)));
    }

    /// Frame in which the model `p` (output units) has `K ~ I`, `b = 0`; `fallback` when `p`
    /// has no usable scale.
    pub fn from_params(model: Model, p: &[f64; 9], fallback: Frame) -> Frame {
        let k = model.k_matrix(p);
        let d = (k[(0, 0)] * k[(1, 1)] * k[(2, 2)]).abs().cbrt();
        let c = [p[3], p[4], p[5]];
        if d.is_finite() && d > 0.0 && c.iter().all(|v| v.is_finite()) {
            Frame { c, s: d }
        } else {
            fallback
        }
    }

    /// Centroid frame with a robust scale (median distance from the centroid, over `g`):
    /// the data's spread scale, known before any fit.
    pub fn centroid(means: &[[f64; 3]], g: f64) -> Result<Frame> {
        // Each mean over n before the sum (no overflow for means near the largest double).
        let inv_n = 1.0 / means.len() as f64;
        let mut c = [0.0; 3];
        for m in means {
            for i in 0..3 {
                c[i] += m[i] * inv_n;
            }
        }
        let d = median_by(means.len(), |k| {
            let m = &means[k];
            ((m[0] - c[0]).powi(2) + (m[1] - c[1]).powi(2) + (m[2] - c[2]).powi(2)).sqrt()
        });
        // Relative to the size of the data: identical dwells differ by rounding only.
        let size = means
            .iter()
            .map(|m| m[0].abs().max(m[1].abs()).max(m[2].abs()))
            .fold(0.0f64, f64::max);
        if !(d > 1e-9 * size) || !d.is_finite() {
            return degenerate(
                "the dwell means are (almost) all identical: the sensor was not turned between \
                 dwells",
            );
        }
        Ok(Frame { c, s: d / g })
    }

    /// Origin-centred frame with the median norm over `g` as scale (the paper's regression
    /// is written about the raw origin).
    pub fn origin(means: &[[f64; 3]], g: f64) -> Frame {
        let s = median_by(means.len(), |k| {
            let m = &means[k];
            (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt()
        }) / g;
        Frame { c: [0.0; 3], s }
    }
}

/// Up to this many values the median is found by ranks (no data-dependent branch).
const RANK_MAX: usize = 48;

/// The median of `v` (`1 <= len <= RANK_MAX`) from the number of values below each one in
/// the total order: the order statistics a sort gives, found by `n^2` comparisons without a
/// branch on the data. Selection mispredicts about one branch per comparison on
/// fresh data.
fn median_by_rank(v: &[f64]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        if crate::lanes::avx2_fma() {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            return unsafe { median_by_rank_avx2(v) };
        }
    }
    median_by_rank_body(v)
}

/// [`median_by_rank`] compiled for AVX2 (four 64-bit comparisons at a time).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn median_by_rank_avx2(v: &[f64]) -> f64 {
    median_by_rank_body(v)
}

#[inline(always)]
fn median_by_rank_body(v: &[f64]) -> f64 {
    let n = v.len();
    // Keys in the total order of `f64::total_cmp`, as integers (equal keys: equal bits); the
    // padding up to a multiple of four is below no key.
    let mut key = [i64::MAX; RANK_MAX];
    for (k, &x) in key.iter_mut().zip(v) {
        *k = total_key(x);
    }
    let m = n.div_ceil(4) * 4;
    // Sorted position p holds the largest value with fewer than p + 1 values below it.
    let (lo, hi) = ((n - 1) / 2, n / 2);
    let (mut below, mut upper) = (i64::MIN, i64::MIN);
    for &ki in &key[..n] {
        let mut c = [0i64; 4];
        for ch in key[..m].chunks_exact(4) {
            for l in 0..4 {
                c[l] += (ch[l] < ki) as i64;
            }
        }
        let lt = ((c[0] + c[1]) + (c[2] + c[3])) as usize;
        if lt <= lo && ki > below {
            below = ki;
        }
        if lt <= hi && ki > upper {
            upper = ki;
        }
    }
    if n % 2 == 1 {
        from_total_key(upper)
    } else {
        0.5 * (from_total_key(below) + from_total_key(upper))
    }
}

/// Median of `f(0..n)` (NaN when `n == 0`); no allocation up to 64 values.
pub fn median_by(n: usize, f: impl Fn(usize) -> f64) -> f64 {
    // The order statistics a full sort would give (total order: NaN sorts last), by
    // selection.
    fn med(v: &mut [f64]) -> f64 {
        let n = v.len();
        let (lo, hi, _) = v.select_nth_unstable_by(n / 2, |a, b| a.total_cmp(b));
        let hi = *hi;
        if n % 2 == 1 {
            hi
        } else {
            let below = lo
                .iter()
                .copied()
                .max_by(|a, b| a.total_cmp(b))
                .unwrap_or(hi);
            0.5 * (below + hi)
        }
    }
    if n == 0 {
        return f64::NAN;
    }
    if n <= RANK_MAX {
        let mut buf = [0.0f64; RANK_MAX];
        for (k, x) in buf[..n].iter_mut().enumerate() {
            *x = f(k);
        }
        return median_by_rank(&buf[..n]);
    }
    if n <= 64 {
        let mut buf = [0.0f64; 64];
        for (k, x) in buf[..n].iter_mut().enumerate() {
            *x = f(k);
        }
        med(&mut buf[..n])
    } else {
        let mut v: Vec<f64> = (0..n).map(f).collect();
        med(&mut v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_round_trips_and_whitens_the_model() {
        let p = [
            414.5, 412.0, 414.6, 33124.0, 33275.0, 32364.0, 1.2, -3.0, 8.0,
        ];
        let f = Frame::from_params(Model::Lower, &p, Frame::IDENTITY);
        let q = f.to_frame(&p);
        assert!((q[0] * q[1] * q[2] - 1.0).abs() < 1e-12 && q[3..6].iter().all(|v| *v == 0.0));
        let back = f.unframe(&q);
        for (a, b) in back.iter().zip(&p) {
            assert!((a - b).abs() <= 1e-12 * b.abs());
        }
        // A point transforms consistently with the parameters: K' a + b' = (K a + b - c) / s.
        let am = [33500.0, 33000.0, 36400.0];
        let pt = f.point(&am);
        assert!((pt[0] - (am[0] - p[3]) / f.s).abs() < 1e-12);
        // Singular parameters fall back.
        let z = [0.0; 9];
        assert_eq!(
            Frame::from_params(Model::Lower, &z, Frame::IDENTITY),
            Frame::IDENTITY
        );
    }

    #[test]
    fn centroid_frame_refuses_identical_dwells_and_median_is_exact() {
        assert!(Frame::centroid(&[[1.0, 2.0, 3.0]; 5], 9.8).is_err());
        // Identical up to rounding of the centroid.
        assert!(Frame::centroid(&[[0.1, 0.7, 9.3]; 20], 9.8).is_err());
        let f = Frame::centroid(&[[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]], 2.0).unwrap();
        assert_eq!(f.c, [0.0; 3]);
        assert!((f.s - 0.5).abs() < 1e-15);
        assert_eq!(median_by(4, |k| [3.0, 1.0, 4.0, 2.0][k]), 2.5);
        assert_eq!(median_by(3, |k| [3.0, 1.0, 4.0][k]), 3.0);
        assert_eq!(median_by(65, |k| k as f64), 32.0);
        assert!(median_by(0, |_| 1.0).is_nan());
        // Selection gives the sorted order statistics, for every length and with ties.
        let mut seed = 7u64;
        for n in 1..80 {
            let v: Vec<f64> = (0..n)
                .map(|_| (crate::test_rng::unit(&mut seed) * 8.0).round())
                .collect();
            let mut s = v.clone();
            s.sort_by(|a, b| a.total_cmp(b));
            let want = if n % 2 == 1 {
                s[n / 2]
            } else {
                0.5 * (s[n / 2 - 1] + s[n / 2])
            };
            assert_eq!(median_by(n, |k| v[k]).to_bits(), want.to_bits(), "n = {n}");
        }
        // Signed zeros and infinities in the total order (-0 before +0), and NaN last.
        let v = [0.0, -0.0, f64::INFINITY, -1.0, -0.0, f64::NEG_INFINITY];
        assert_eq!(median_by(5, |k| v[k]).to_bits(), (-0.0f64).to_bits());
        assert_eq!(median_by(6, |k| v[k]).to_bits(), (-0.0f64).to_bits());
        assert_eq!(median_by(3, |k| [f64::NAN, 2.0, 1.0][k]), 2.0);
        assert!(median_by(3, |k| [f64::NAN, f64::NAN, 1.0][k]).is_nan());
    }
}

//! Four `f64` lanes side by side, for the small per-dwell kernels of the fits (the normal
//! equations of the static fit and of its quadric start).
//!
//! A kernel is written once, generic over [`F64x4`], and compiled twice: with [`Portable`]
//! (four scalars, what any CPU runs) and, on x86-64 CPUs with AVX2 and FMA, with
//! [`Avx2Fma`] (one 256-bit register, chosen at run time by [`avx2_fma`]). The two run the
//! same operations in the same order; [`F64x4::mul_add`] is fused on AVX2 + FMA (one rounding)
//! and a multiplication then an addition in the portable build, so results may differ in the
//! last bits between CPUs, never between runs or thread counts on one CPU.

use std::ops::{Add, Div, Mul, Sub};

/// Number of lanes of every vector of this module.
pub const LANES: usize = 4;

/// Four `f64` lanes.
pub trait F64x4:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Div<Output = Self>
{
    /// Every lane `v`.
    fn splat(v: f64) -> Self;
    /// Lanes from an array.
    fn from_array(a: [f64; 4]) -> Self;
    /// Lanes into an array.
    fn to_array(self) -> [f64; 4];
    /// Square root of each lane.
    fn sqrt(self) -> Self;
    /// `self * b + c` (fused on AVX2 + FMA).
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// Four 3-vectors (consecutive in memory) as three vectors of their `x`, `y` and `z`.
    #[inline(always)]
    fn transpose3(rows: &[[f64; 3]; 4]) -> [Self; 3] {
        let col = |i: usize| Self::from_array([rows[0][i], rows[1][i], rows[2][i], rows[3][i]]);
        [col(0), col(1), col(2)]
    }
    /// [`Self::transpose3`] of the [`LANES`] 3-vectors from `i0` (which must all exist).
    #[inline(always)]
    fn transpose3_at(rows: &[[f64; 3]], i0: usize) -> [Self; 3] {
        Self::transpose3(rows[i0..i0 + LANES].try_into().expect("a full block"))
    }
    /// Sum of the lanes in a fixed order: `(l0 + l1) + (l2 + l3)`.
    #[inline(always)]
    fn fold(self) -> f64 {
        let v = self.to_array();
        (v[0] + v[1]) + (v[2] + v[3])
    }
}

/// Four scalars (any CPU).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Portable(pub [f64; 4]);

macro_rules! portable_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl $tr for Portable {
            type Output = Portable;
            #[inline(always)]
            fn $f(self, o: Portable) -> Portable {
                let (a, b) = (self.0, o.0);
                Portable([a[0] $op b[0], a[1] $op b[1], a[2] $op b[2], a[3] $op b[3]])
            }
        }
    };
}
portable_op!(Add, add, +);
portable_op!(Sub, sub, -);
portable_op!(Mul, mul, *);
portable_op!(Div, div, /);

impl F64x4 for Portable {
    #[inline(always)]
    fn splat(v: f64) -> Portable {
        Portable([v; 4])
    }
    #[inline(always)]
    fn from_array(a: [f64; 4]) -> Portable {
        Portable(a)
    }
    #[inline(always)]
    fn to_array(self) -> [f64; 4] {
        self.0
    }
    #[inline(always)]
    fn sqrt(self) -> Portable {
        Portable(self.0.map(f64::sqrt))
    }
    #[inline(always)]
    fn mul_add(self, b: Portable, c: Portable) -> Portable {
        self * b + c
    }
}

#[cfg(target_arch = "x86_64")]
pub use x86::{avx2_fma, Avx2Fma};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::F64x4;
    use std::arch::x86_64::{
        __m256d, _mm256_add_pd, _mm256_blend_pd, _mm256_div_pd, _mm256_fmadd_pd, _mm256_loadu_pd,
        _mm256_mul_pd, _mm256_permute2f128_pd, _mm256_set1_pd, _mm256_shuffle_pd, _mm256_sqrt_pd,
        _mm256_storeu_pd, _mm256_sub_pd,
    };
    use std::ops::{Add, Div, Mul, Sub};

    /// The CPU has AVX2 and FMA: [`Avx2Fma`] may be used.
    #[inline]
    pub fn avx2_fma() -> bool {
        std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
    }

    /// One 256-bit register. Only code that has checked [`avx2_fma`] and runs inside a
    /// function compiled with `#[target_feature(enable = "avx2,fma")]` creates these (every
    /// use in the crate does; the type is not exported outside it).
    #[derive(Debug, Clone, Copy)]
    pub struct Avx2Fma(__m256d);

    macro_rules! avx_op {
        ($tr:ident, $f:ident, $intr:ident) => {
            impl $tr for Avx2Fma {
                type Output = Avx2Fma;
                #[inline(always)]
                fn $f(self, o: Avx2Fma) -> Avx2Fma {
                    // SAFETY: an Avx2Fma exists only where AVX2 and FMA are available.
                    Avx2Fma(unsafe { $intr(self.0, o.0) })
                }
            }
        };
    }
    avx_op!(Add, add, _mm256_add_pd);
    avx_op!(Sub, sub, _mm256_sub_pd);
    avx_op!(Mul, mul, _mm256_mul_pd);
    avx_op!(Div, div, _mm256_div_pd);

    impl F64x4 for Avx2Fma {
        #[inline(always)]
        fn splat(v: f64) -> Avx2Fma {
            // SAFETY: see the type's documentation.
            Avx2Fma(unsafe { _mm256_set1_pd(v) })
        }
        #[inline(always)]
        fn from_array(a: [f64; 4]) -> Avx2Fma {
            // SAFETY: see the type's documentation; `a` holds 4 values.
            Avx2Fma(unsafe { _mm256_loadu_pd(a.as_ptr()) })
        }
        #[inline(always)]
        fn to_array(self) -> [f64; 4] {
            let mut a = [0.0; 4];
            // SAFETY: see the type's documentation; `a` holds 4 values.
            unsafe { _mm256_storeu_pd(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn sqrt(self) -> Avx2Fma {
            // SAFETY: see the type's documentation.
            Avx2Fma(unsafe { _mm256_sqrt_pd(self.0) })
        }
        #[inline(always)]
        fn mul_add(self, b: Avx2Fma, c: Avx2Fma) -> Avx2Fma {
            // SAFETY: see the type's documentation.
            Avx2Fma(unsafe { _mm256_fmadd_pd(self.0, b.0, c.0) })
        }
        /// Three loads and six shuffles, without a round trip through memory.
        #[inline(always)]
        fn transpose3(rows: &[[f64; 3]; 4]) -> [Avx2Fma; 3] {
            let p = rows.as_ptr().cast::<f64>();
            // SAFETY: see the type's documentation; `rows` holds 12 consecutive values.
            unsafe {
                // m0 = x0 y0 z0 x1, m1 = y1 z1 x2 y2, m2 = z2 x3 y3 z3.
                let (m0, m1, m2) = (
                    _mm256_loadu_pd(p),
                    _mm256_loadu_pd(p.add(4)),
                    _mm256_loadu_pd(p.add(8)),
                );
                let a = _mm256_blend_pd::<0b1100>(m0, m1); // x0 y0 x2 y2
                let b = _mm256_permute2f128_pd::<0x21>(m0, m2); // z0 x1 z2 x3
                let c = _mm256_blend_pd::<0b1100>(m1, m2); // y1 z1 y3 z3
                [
                    Avx2Fma(_mm256_shuffle_pd::<0b1010>(a, b)),
                    Avx2Fma(_mm256_shuffle_pd::<0b0101>(a, c)),
                    Avx2Fma(_mm256_shuffle_pd::<0b1010>(b, c)),
                ]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kernel<V: F64x4>(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
        let (x, y) = (V::from_array(a), V::from_array(b));
        ((x * y + x - y) / y)
            .sqrt()
            .mul_add(x, V::splat(0.5))
            .to_array()
    }

    /// The AVX2 lanes compute what the portable ones do (to the rounding of the fused
    /// multiply-add), and the fold adds in the documented order.
    #[test]
    fn avx_lanes_match_portable() {
        let (a, b) = ([1.5, 2.0, 3.25, 1e10], [0.5, 4.0, 1.0 / 3.0, 7.0]);
        let p = kernel::<Portable>(a, b);
        let want = [0, 1, 2, 3].map(|l| ((a[l] * b[l] + a[l] - b[l]) / b[l]).sqrt() * a[l] + 0.5);
        assert_eq!(p, want);
        #[cfg(target_arch = "x86_64")]
        if avx2_fma() {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn run(a: [f64; 4], b: [f64; 4]) -> [f64; 4] {
                kernel::<Avx2Fma>(a, b)
            }
            // SAFETY: checked just above.
            let v = unsafe { run(a, b) };
            for (x, y) in v.iter().zip(&p) {
                assert!((x - y).abs() <= 2e-16 * y.abs(), "{x} {y}");
            }
        }
        assert_eq!(Portable([1.0, 2.0, 1e-20, 3.0]).fold(), 6.0);
    }

    /// Both transposes give the columns of four consecutive 3-vectors.
    #[test]
    fn transpose3_gives_columns() {
        let rows = [
            [1.0, 2.0, 3.0],
            [4.0, 5.0, 6.0],
            [7.0, 8.0, 9.0],
            [10.0, 11.0, 12.0],
        ];
        let want = [
            [1.0, 4.0, 7.0, 10.0],
            [2.0, 5.0, 8.0, 11.0],
            [3.0, 6.0, 9.0, 12.0],
        ];
        assert_eq!(Portable::transpose3(&rows).map(|v| v.0), want);
        #[cfg(target_arch = "x86_64")]
        if avx2_fma() {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn run(rows: &[[f64; 3]; 4]) -> [[f64; 4]; 3] {
                let [x, y, z] = Avx2Fma::transpose3(rows);
                [x.to_array(), y.to_array(), z.to_array()]
            }
            // SAFETY: checked just above.
            assert_eq!(unsafe { run(&rows) }, want);
        }
    }
}

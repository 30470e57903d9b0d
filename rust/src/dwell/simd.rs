//! x86-64 kernels of the dwell pass, chosen at run time (`is_x86_feature_detected!`).
//!
//! Each computes exactly what the portable [`super::accumulate_groups`] computes, operation
//! for operation, so every result is bit-identical whichever kernel runs.
//!
//! [`groups_fma`]: the float loop with explicit AVX2 vectors. Per value it does 5 additions
//! and 2 multiplications; the additions would all queue on the two floating-point adder
//! pipes, so some of them are issued as `fma(a, one, b)` on the multiplier pipes instead.
//! With `one == 1.0` that is `a + b` rounded once: the very same result as the addition
//! (`one` is hidden from the optimiser, which would otherwise turn the fma back into an add).
//! The previous row of each value is an unaligned load 3 values back, not a shuffle.
//!
//! [`i16_avx2`] and [`i16_avx512`]: the exact int16 sums of [`super::accumulate_i16`] in
//! 16-bit lanes (`vpmaddwd`, `vpdpwssd`), guarded by a range check that sends pieces with
//! large excursions to the portable integer sums: the same integer totals either way.
//!
//! The unit tests in `super` compare every kernel here with the portable one, directly and
//! through the whole dwell pass.

use super::{accumulate_groups, i16_rows, i16_sums, I16Sums, Lanes, Sample, W};
use std::arch::x86_64::{
    __m256i, __mmask32, _mm256_add_epi32, _mm256_add_epi64, _mm256_add_pd, _mm256_and_si256,
    _mm256_castsi256_si128, _mm256_cmpgt_epi16, _mm256_cvtepi32_epi64, _mm256_cvtepu32_epi64,
    _mm256_extracti128_si256, _mm256_fmadd_pd, _mm256_loadu_pd, _mm256_loadu_si256,
    _mm256_madd_epi16, _mm256_max_epi16, _mm256_min_epi16, _mm256_mul_pd, _mm256_or_si256,
    _mm256_set1_epi16, _mm256_set1_epi32, _mm256_set1_pd, _mm256_setr_epi16, _mm256_setzero_si256,
    _mm256_storeu_pd, _mm256_storeu_si256, _mm256_sub_epi16, _mm256_sub_pd, _mm256_subs_epi16,
    _mm256_testz_si256, _mm512_add_epi64, _mm512_and_si512, _mm512_castsi128_si512,
    _mm512_castsi512_si256, _mm512_cmpgt_epi16_mask, _mm512_cvtepi32_epi64, _mm512_cvtepu32_epi64,
    _mm512_dpwssd_epi32, _mm512_extracti64x4_epi64, _mm512_loadu_si512, _mm512_maskz_loadu_epi16,
    _mm512_maskz_subs_epi16, _mm512_max_epi16, _mm512_min_epi16, _mm512_permutexvar_epi16,
    _mm512_set1_epi16, _mm512_set1_epi32, _mm512_setzero_si512, _mm512_storeu_si512,
    _mm512_sub_epi16, _mm_setr_epi16,
};

/// [`accumulate_groups`] with AVX2 vectors and FMA-pipe additions (see the module docs).
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(super) unsafe fn groups_fma<T: Sample>(
    body: &[T],
    prev: &[f64; 3],
    sh: &[f64; W],
    l: &mut Lanes,
) {
    if body.len() < W {
        return;
    }
    // The first group (its first row's previous row is `prev`) as in the portable loop.
    accumulate_groups(&body[..W], prev, sh, l);
    let rest = &body[W..body.len() - body.len() % W];
    if rest.is_empty() {
        return;
    }
    let one = _mm256_set1_pd(std::hint::black_box(1.0));
    // Loads and stores of 4 values from slices of exactly 4 (sub-slices of `[f64; W]`).
    macro_rules! ld {
        ($s:expr) => {{
            let s: &[f64] = $s;
            debug_assert_eq!(s.len(), 4);
            // SAFETY: `s` holds 4 f64 (32 bytes, unaligned load); AVX is enabled here.
            unsafe { _mm256_loadu_pd(s.as_ptr()) }
        }};
    }
    let [sh0, sh1, sh2] = [ld!(&sh[0..4]), ld!(&sh[4..8]), ld!(&sh[8..12])];
    let [mut a0, mut a1, mut a2] = [ld!(&l.s1[0..4]), ld!(&l.s1[4..8]), ld!(&l.s1[8..12])];
    let [mut b0, mut b1, mut b2] = [ld!(&l.s2[0..4]), ld!(&l.s2[4..8]), ld!(&l.s2[8..12])];
    let [mut c0, mut c1, mut c2] = [ld!(&l.d2[0..4]), ld!(&l.d2[4..8]), ld!(&l.d2[8..12])];
    // The previous row of element j of a group is element j - 3: `before` is `rest` 3 back.
    let before = &body[W - 3..body.len() - body.len() % W - 3];
    for (g, gp) in rest.chunks_exact(W).zip(before.chunks_exact(W)) {
        // SAFETY: each sub-slice holds 4 values (`g` and `gp` hold W = 12); AVX2 is enabled.
        let (x0, x1, x2) = unsafe { (T::load4(&g[0..4]), T::load4(&g[4..8]), T::load4(&g[8..12])) };
        // SAFETY: as just above.
        let (p0, p1, p2) = unsafe {
            (
                T::load4(&gp[0..4]),
                T::load4(&gp[4..8]),
                T::load4(&gp[8..12]),
            )
        };
        // Lane vector 0 and 1: s1 and d2 additions on the FMA pipes; vector 2: d2 only.
        let d = _mm256_sub_pd(x0, sh0);
        a0 = _mm256_fmadd_pd(d, one, a0);
        b0 = _mm256_add_pd(b0, _mm256_mul_pd(d, d));
        let e = _mm256_sub_pd(x0, p0);
        c0 = _mm256_fmadd_pd(_mm256_mul_pd(e, e), one, c0);
        let d = _mm256_sub_pd(x1, sh1);
        a1 = _mm256_fmadd_pd(d, one, a1);
        b1 = _mm256_add_pd(b1, _mm256_mul_pd(d, d));
        let e = _mm256_sub_pd(x1, p1);
        c1 = _mm256_fmadd_pd(_mm256_mul_pd(e, e), one, c1);
        let d = _mm256_sub_pd(x2, sh2);
        a2 = _mm256_add_pd(a2, d);
        b2 = _mm256_add_pd(b2, _mm256_mul_pd(d, d));
        let e = _mm256_sub_pd(x2, p2);
        c2 = _mm256_fmadd_pd(_mm256_mul_pd(e, e), one, c2);
    }
    macro_rules! st {
        ($s:expr, $v:expr) => {{
            let s: &mut [f64] = $s;
            debug_assert_eq!(s.len(), 4);
            // SAFETY: `s` holds 4 f64 (32 bytes, unaligned store); AVX is enabled here.
            unsafe { _mm256_storeu_pd(s.as_mut_ptr(), $v) }
        }};
    }
    st!(&mut l.s1[0..4], a0);
    st!(&mut l.s1[4..8], a1);
    st!(&mut l.s1[8..12], a2);
    st!(&mut l.s2[0..4], b0);
    st!(&mut l.s2[4..8], b1);
    st!(&mut l.s2[8..12], b2);
    st!(&mut l.d2[0..4], c0);
    st!(&mut l.d2[4..8], c1);
    st!(&mut l.d2[8..12], c2);
}

/// Vector iterations per range-checked sub-piece of the int16 kernels.
const K16: usize = 32;
/// Largest deviation from the shift (counts) within which [`K16`] iterations cannot overflow a
/// 32-bit lane: first differences are then within `2 * LIM16` and a lane gains at most
/// `2 * (2 * LIM16)^2` per iteration, so `K16 * 8 * LIM16^2 < 2^32`.
const LIM16: i16 = 4095;

/// Per-axis totals of 64-bit lane sums: `tot` of both 16-bit lanes of each 32-bit lane and
/// `evn` of the even one alone, for vectors of `2 * tot.len()` values from a row boundary.
fn fold_lanes(tot: &[i64], evn: &[i64], out: &mut [i64; 3]) {
    for (m, (&t, &e)) in tot.iter().zip(evn).enumerate() {
        out[(2 * m) % 3] += e;
        out[(2 * m + 1) % 3] += t - e;
    }
}

/// True when the row before a sub-piece (`r`) is within [`LIM16`] of the shift `c`.
fn row_in_range(r: &[i16], c: &[i32; 3]) -> bool {
    r.iter()
        .zip(c)
        .all(|(&v, &c)| (i32::from(v) - c).abs() <= i32::from(LIM16))
}

/// [`super::accumulate_i16`] with `vpmaddwd` (AVX2): exact integer sums in 16-bit arithmetic.
///
/// Vectors of 16 values are loaded every 15 values, from row boundaries, so lane `q < 15` is
/// always axis `q % 3`; lane 15 (the next vector's first value) is zeroed. `vpmaddwd` of the
/// deviations `d = x - c` with ones, of `d` with itself and of the first differences `e` with
/// themselves gives per 32-bit lane the sum over its two 16-bit lanes (two axes); the same
/// with the odd 16-bit lanes zeroed gives the even lane alone, and the odd one is the
/// difference. The 32-bit lane sums are added into 64-bit lanes after every [`K16`] vectors.
///
/// All of this is exact while every value of a sub-piece (and the row before it) is within
/// [`LIM16`] of the shift (checked on the saturated 16-bit deviations); a sub-piece outside
/// that range (large motion, full-scale steps) goes through the portable exact sums instead.
/// Either way the totals are the same integers as [`super::accumulate_i16`]'s.
///
/// # Safety
/// The CPU must support AVX2; `prev` and `sh` hold int16 values.
#[target_feature(enable = "avx2")]
pub(super) unsafe fn i16_avx2(body: &[i16], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    let n = body.len();
    if n < 3 {
        return;
    }
    let c = [sh[0] as i32, sh[1] as i32, sh[2] as i32];
    let p0 = [prev[0] as i16, prev[1] as i16, prev[2] as i16];
    let mut t = I16Sums::default();
    i16_rows(&body[..3], &p0, &c, &mut t);
    let (c0, c1, c2) = (c[0] as i16, c[1] as i16, c[2] as i16);
    let keep = _mm256_setr_epi16(
        -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0,
    );
    let cv = _mm256_setr_epi16(
        c0, c1, c2, c0, c1, c2, c0, c1, c2, c0, c1, c2, c0, c1, c2, 0,
    );
    let even = _mm256_set1_epi32(0xFFFF);
    let ones = _mm256_set1_epi16(1);
    let lim = _mm256_set1_epi16(LIM16);
    let zero = _mm256_setzero_si256();
    // 64-bit lane sums: [sum d, its even part, sum d^2, even part, sum e^2, even part], each
    // as the low and the high four 32-bit lanes.
    let mut wide = [zero; 12];
    let mut o = 3;
    while o + 16 <= n {
        let iters = ((n - o - 1) / 15).min(K16);
        let span = 15 * iters;
        // `seg[3 + 15 i..]` is the vector of iteration i, `seg[15 i..]` its previous rows.
        let seg = &body[o - 3..o + span + 1];
        let mut acc = [zero; 6];
        let mut dlo = zero;
        let mut dhi = zero;
        // Iteration i reads seg[15 i..15 i + 19]: in bounds, as seg.len() = 15 iters + 4.
        debug_assert_eq!(seg.len(), 15 * iters + 4);
        let base = seg.as_ptr();
        for i in 0..iters {
            // SAFETY: 16 values at offsets 15 i + 3 and 15 i, within `seg` (see above).
            let (x, p) = unsafe {
                (
                    _mm256_loadu_si256(base.add(15 * i + 3).cast::<__m256i>()),
                    _mm256_loadu_si256(base.add(15 * i).cast::<__m256i>()),
                )
            };
            let x = _mm256_and_si256(x, keep);
            let p = _mm256_and_si256(p, keep);
            let d = _mm256_subs_epi16(x, cv);
            let e = _mm256_sub_epi16(x, p);
            dlo = _mm256_min_epi16(dlo, d);
            dhi = _mm256_max_epi16(dhi, d);
            let de = _mm256_and_si256(d, even);
            let ee = _mm256_and_si256(e, even);
            acc[0] = _mm256_add_epi32(acc[0], _mm256_madd_epi16(d, ones));
            acc[1] = _mm256_add_epi32(acc[1], _mm256_madd_epi16(de, ones));
            acc[2] = _mm256_add_epi32(acc[2], _mm256_madd_epi16(d, d));
            acc[3] = _mm256_add_epi32(acc[3], _mm256_madd_epi16(de, d));
            acc[4] = _mm256_add_epi32(acc[4], _mm256_madd_epi16(e, e));
            acc[5] = _mm256_add_epi32(acc[5], _mm256_madd_epi16(ee, e));
        }
        // |d| <= LIM16 everywhere (saturated deviations cannot pass).
        let over = _mm256_or_si256(
            _mm256_cmpgt_epi16(dhi, lim),
            _mm256_cmpgt_epi16(_mm256_sub_epi16(zero, lim), dlo),
        );
        if _mm256_testz_si256(over, over) == 1 && row_in_range(&seg[..3], &c) {
            for (k, &v) in acc.iter().enumerate() {
                let (lo, hi) = (_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
                // Sums of d are signed; squares are unsigned 32-bit.
                let (lo, hi) = if k < 2 {
                    (_mm256_cvtepi32_epi64(lo), _mm256_cvtepi32_epi64(hi))
                } else {
                    (_mm256_cvtepu32_epi64(lo), _mm256_cvtepu32_epi64(hi))
                };
                wide[2 * k] = _mm256_add_epi64(wide[2 * k], lo);
                wide[2 * k + 1] = _mm256_add_epi64(wide[2 * k + 1], hi);
            }
        } else {
            i16_sums(&seg[3..3 + span], &seg[..span], &c, &mut t);
        }
        o += span;
    }
    i16_rows(&body[o..], &body[o - 3..n - 3], &c, &mut t);
    let mut lanes = [[0i64; 8]; 6];
    for (k, out) in lanes.iter_mut().enumerate() {
        // SAFETY: 2 x 32 bytes written into a 64-byte array.
        unsafe {
            _mm256_storeu_si256(out.as_mut_ptr().cast::<__m256i>(), wide[2 * k]);
            _mm256_storeu_si256(out.as_mut_ptr().add(4).cast::<__m256i>(), wide[2 * k + 1]);
        }
    }
    add_folded(&lanes, &mut t);
    t.add_to(l);
}

/// Add the per-axis folds of the six 64-bit lane sums (see [`i16_avx2`]) to `t`.
fn add_folded<const N: usize>(lanes: &[[i64; N]; 6], t: &mut I16Sums) {
    let mut s = [[0i64; 3]; 3];
    for (q, s) in s.iter_mut().enumerate() {
        fold_lanes(&lanes[2 * q], &lanes[2 * q + 1], s);
    }
    for (a, s1) in t.s1.iter_mut().enumerate() {
        *s1 += s[0][a];
    }
    // Sums of squares are non-negative.
    for (a, s2) in t.s2.iter_mut().enumerate() {
        *s2 += s[1][a] as u64;
    }
    for (a, d2) in t.d2.iter_mut().enumerate() {
        *d2 += s[2][a] as u64;
    }
}

/// [`i16_avx2`] with 512-bit vectors and `vpdpwssd` (AVX-512 BW and VNNI): 32 values per
/// vector loaded every 30 values (lanes 30 and 31 masked to zero), the products summed into
/// the 32-bit lanes by the same instruction. Same sums, same checks, same totals.
///
/// # Safety
/// The CPU must support AVX-512 F, BW and VNNI; `prev` and `sh` hold int16 values.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
pub(super) unsafe fn i16_avx512(body: &[i16], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    const V: usize = 30;
    let n = body.len();
    if n < 3 {
        return;
    }
    let c = [sh[0] as i32, sh[1] as i32, sh[2] as i32];
    let p0 = [prev[0] as i16, prev[1] as i16, prev[2] as i16];
    let mut t = I16Sums::default();
    i16_rows(&body[..3], &p0, &c, &mut t);
    // The shift of lane q: lane q % 3 of (c0, c1, c2, 0), and 0 (lane 3) for q >= 30.
    const AXIS: [i16; 32] = {
        let mut a = [3i16; 32];
        let mut q = 0;
        while q < V {
            a[q] = (q % 3) as i16;
            q += 1;
        }
        a
    };
    let c4 = _mm_setr_epi16(c[0] as i16, c[1] as i16, c[2] as i16, 0, 0, 0, 0, 0);
    // SAFETY: 64 bytes read from a 64-byte array.
    let axis = unsafe { _mm512_loadu_si512(AXIS.as_ptr().cast()) };
    let cv = _mm512_permutexvar_epi16(axis, _mm512_castsi128_si512(c4));
    let even = _mm512_set1_epi32(0xFFFF);
    let ones = _mm512_set1_epi16(1);
    let lim = _mm512_set1_epi16(LIM16);
    let nlim = _mm512_set1_epi16(-LIM16);
    let zero = _mm512_setzero_si512();
    let mut wide = [zero; 12];
    let mut o = 3;
    // Sub-pieces of up to K16 vectors; the last vector of the piece may be partial (a shorter
    // mask: the values are whole rows, so its lanes still start at a row boundary).
    while o < n {
        let span = (n - o).min(V * K16);
        // `seg[3 + 30 i..]` is the vector of iteration i, `seg[30 i..]` its previous rows.
        let seg = &body[o - 3..o + span];
        let mut acc = [zero; 6];
        let mut dlo = zero;
        let mut dhi = zero;
        let base = seg.as_ptr();
        let mut i = 0;
        while i < span {
            let m = (span - i).min(V);
            let mask: __mmask32 = (1 << m) - 1;
            // SAFETY: m values at offsets i + 3 and i, within `seg` (span + 3 values) as
            // i + m <= span; masked-off lanes are not read.
            let (x, p) = unsafe {
                (
                    _mm512_maskz_loadu_epi16(mask, base.add(i + 3)),
                    _mm512_maskz_loadu_epi16(mask, base.add(i)),
                )
            };
            let d = _mm512_maskz_subs_epi16(mask, x, cv);
            let e = _mm512_sub_epi16(x, p);
            dlo = _mm512_min_epi16(dlo, d);
            dhi = _mm512_max_epi16(dhi, d);
            let de = _mm512_and_si512(d, even);
            let ee = _mm512_and_si512(e, even);
            acc[0] = _mm512_dpwssd_epi32(acc[0], d, ones);
            acc[1] = _mm512_dpwssd_epi32(acc[1], de, ones);
            acc[2] = _mm512_dpwssd_epi32(acc[2], d, d);
            acc[3] = _mm512_dpwssd_epi32(acc[3], de, d);
            acc[4] = _mm512_dpwssd_epi32(acc[4], e, e);
            acc[5] = _mm512_dpwssd_epi32(acc[5], ee, e);
            i += m;
        }
        let over = _mm512_cmpgt_epi16_mask(dhi, lim) | _mm512_cmpgt_epi16_mask(nlim, dlo);
        if over == 0 && row_in_range(&seg[..3], &c) {
            for (k, &v) in acc.iter().enumerate() {
                let (lo, hi) = (_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v));
                let (lo, hi) = if k < 2 {
                    (_mm512_cvtepi32_epi64(lo), _mm512_cvtepi32_epi64(hi))
                } else {
                    (_mm512_cvtepu32_epi64(lo), _mm512_cvtepu32_epi64(hi))
                };
                wide[2 * k] = _mm512_add_epi64(wide[2 * k], lo);
                wide[2 * k + 1] = _mm512_add_epi64(wide[2 * k + 1], hi);
            }
        } else {
            i16_sums(&seg[3..3 + span], &seg[..span], &c, &mut t);
        }
        o += span;
    }
    let mut lanes = [[0i64; 16]; 6];
    for (k, out) in lanes.iter_mut().enumerate() {
        // SAFETY: 2 x 64 bytes written into a 128-byte array.
        unsafe {
            _mm512_storeu_si512(out.as_mut_ptr().cast(), wide[2 * k]);
            _mm512_storeu_si512(out.as_mut_ptr().add(8).cast(), wide[2 * k + 1]);
        }
    }
    add_folded(&lanes, &mut t);
    t.add_to(l);
}

//! Per-dwell statistics of high-rate 3-axis streams.
//!
//! The kernel is a block-shifted, multi-lane accumulator: within a block of at most
//! [`BLOCK`] samples each axis is accumulated as deviations from the block's first sample
//! (so raw counts with offsets of ~33000 lose nothing), spread over [`LANES`] independent
//! lanes for instruction-level parallelism, and blocks are merged with Chan's formula.
//! Sample `j` of a segment always lands in the same lane and block whatever the chunking,
//! so the streaming accumulator reproduces the one-shot result bit for bit.
//!
//! The same pass also sums the squared first differences `(x[i] - x[i-1])^2` (the overlapping
//! Allan variance at one sample) and keeps each segment's first and last sample, so that
//! consecutive segments merge into the statistics of their concatenation. From these a dwell
//! gets, at no extra memory traffic:
//! - its half-dwell means (the first and the second half of its samples);
//! - an Allan noise inflation factor: by how much the noise of the dwell mean exceeds white
//!   noise of the same sample-to-sample deviation (see [`allan_inflation`]);
//! - and the stream gets an estimate of the output resolution (LSB) per axis from a bounded,
//!   chunking-independent subsample ([`LsbSampler`]).

use crate::error::{degenerate, invalid, try_grow, CoreError, Result};
use crate::gap::special::chi2_isf;
use ndarray::ArrayView2;
use rayon::prelude::*;

mod faults;
#[cfg(target_arch = "x86_64")]
mod simd;
mod state;
mod steps;
pub use faults::{output_faults, FaultKind, OutputFault, FAULT_MIN_SAMPLES};
pub use state::STATE_VERSION;
pub use steps::{step_log, StepLog};

/// Independent accumulation lanes.
pub const LANES: usize = 4;
/// Samples per shifted block (a multiple of [`LANES`]).
pub const BLOCK: usize = 4096;
/// Values per group of [`LANES`] rows.
const W: usize = 3 * LANES;
/// Sub-blocks per dwell (dwells given by bounds): the Allan clusters are 4 and 16 sub-blocks.
pub const SUBS: usize = 64;
/// Fewest samples in a dwell for the Allan inflation factor (NaN below).
pub const MIN_ALLAN_SAMPLES: u64 = 64;
/// Fewest samples in a dwell (its variance needs two).
pub const MIN_DWELL_SAMPLES: usize = 2;
/// Fewest samples in the detector's moving window.
pub const MIN_WINDOW_SAMPLES: f64 = 8.0;
/// Rows kept by the LSB subsample (a power of two).
pub const LSB_CAP: usize = 1 << 12;
/// Largest sample rate accepted, Hz.
pub const MAX_FS: f64 = 1e9;
/// Largest duration setting accepted, s (fs * duration stays below 2^50 samples).
pub const MAX_DURATION_S: f64 = 1e6;

/// A sample type accepted by the kernels: converted exactly (integers) or widened to f64.
pub trait Sample: Copy + Send + Sync + 'static {
    /// True for integer types (their output resolution is a whole number of counts).
    const INTEGER: bool = false;

    /// The value as f64.
    fn to_f64(self) -> f64;

    /// Accumulate whole groups of `3 * LANES` values (at most one block) into the per-lane
    /// shifted sums (`s1 += x - shift`, `s2 += (x - shift)^2`) and squared first differences
    /// (`d2 += (x - previous row)^2`); element `j` of a group is lane `j / 3`, axis `j % 3`, and
    /// `prev` is the row before the first one. Overridden where an exact faster path exists.
    #[inline(always)]
    fn accumulate(body: &[Self], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
        accumulate_dispatch(body, prev, sh, l);
    }

    /// The first four values of `x` as f64 in an AVX register (exact, as [`Sample::to_f64`]).
    ///
    /// # Safety
    /// `x` holds at least 4 values; only called where AVX2 is enabled.
    #[cfg(target_arch = "x86_64")]
    #[doc(hidden)]
    #[inline(always)]
    unsafe fn load4(x: &[Self]) -> std::arch::x86_64::__m256d {
        // SAFETY: AVX is enabled where this is called (the caller's contract).
        unsafe {
            std::arch::x86_64::_mm256_setr_pd(
                x[0].to_f64(),
                x[1].to_f64(),
                x[2].to_f64(),
                x[3].to_f64(),
            )
        }
    }
}
impl Sample for f64 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(x: &[Self]) -> std::arch::x86_64::__m256d {
        debug_assert!(x.len() >= 4);
        // SAFETY: 4 in-bounds values; AVX enabled (the caller's contract).
        unsafe { std::arch::x86_64::_mm256_loadu_pd(x.as_ptr()) }
    }
}
impl Sample for f32 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(x: &[Self]) -> std::arch::x86_64::__m256d {
        use std::arch::x86_64::{_mm256_cvtps_pd, _mm_loadu_ps};
        debug_assert!(x.len() >= 4);
        // SAFETY: 4 in-bounds values; AVX enabled (the caller's contract).
        unsafe { _mm256_cvtps_pd(_mm_loadu_ps(x.as_ptr())) }
    }
}
impl Sample for i16 {
    const INTEGER: bool = true;

    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }

    #[inline(always)]
    fn accumulate(body: &[Self], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
        accumulate_i16_dispatch(body, prev, sh, l);
    }
}
impl Sample for i32 {
    const INTEGER: bool = true;

    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn load4(x: &[Self]) -> std::arch::x86_64::__m256d {
        use std::arch::x86_64::{_mm256_cvtepi32_pd, _mm_loadu_si128};
        debug_assert!(x.len() >= 4);
        // SAFETY: 4 in-bounds values (16 bytes); AVX enabled (the caller's contract).
        unsafe { _mm256_cvtepi32_pd(_mm_loadu_si128(x.as_ptr().cast())) }
    }
}

/// Per-lane sums, flattened: index `3 * lane + axis`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lanes {
    s1: [f64; W],
    s2: [f64; W],
    d2: [f64; W],
}

impl Lanes {
    const ZERO: Lanes = Lanes {
        s1: [0.0; W],
        s2: [0.0; W],
        d2: [0.0; W],
    };
}

/// Count, mean, sum of squared deviations and of squared first differences of one segment,
/// per axis, with its first and last sample (so consecutive segments can be merged).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Moments {
    /// Number of samples.
    pub n: u64,
    /// Mean per axis.
    pub mean: [f64; 3],
    /// Sum of squared deviations from the mean per axis.
    pub m2: [f64; 3],
    /// Sum of `(x[i] - x[i-1])^2` over consecutive samples of the segment, per axis.
    pub d2: [f64; 3],
    /// First sample.
    pub first: [f64; 3],
    /// Last sample.
    pub last: [f64; 3],
}

impl Default for Moments {
    fn default() -> Self {
        Self::EMPTY
    }
}

impl Moments {
    /// No samples.
    pub const EMPTY: Moments = Moments {
        n: 0,
        mean: [0.0; 3],
        m2: [0.0; 3],
        d2: [0.0; 3],
        first: [0.0; 3],
        last: [0.0; 3],
    };

    /// Count, mean and m2 of two disjoint segments (Chan, Golub and LeVeque); the other
    /// fields are those of `self`.
    fn merge_stats(&self, o: &Moments) -> Moments {
        if o.n == 0 {
            return *self;
        }
        if self.n == 0 {
            return Moments {
                d2: self.d2,
                first: self.first,
                last: self.last,
                ..*o
            };
        }
        let n = self.n + o.n;
        let (na, nb, nn) = (self.n as f64, o.n as f64, n as f64);
        let mut out = Moments { n, ..*self };
        for a in 0..3 {
            let d = o.mean[a] - self.mean[a];
            out.mean[a] = self.mean[a] + d * (nb / nn);
            out.m2[a] = self.m2[a] + o.m2[a] + d * d * (na * nb / nn);
        }
        out
    }

    /// The statistics of `self` followed immediately by `o` in the stream.
    #[must_use]
    pub fn merge(&self, o: &Moments) -> Moments {
        if o.n == 0 {
            return *self;
        }
        if self.n == 0 {
            return *o;
        }
        let mut out = self.merge_stats(o);
        for a in 0..3 {
            let e = o.first[a] - self.last[a];
            out.d2[a] = self.d2[a] + o.d2[a] + e * e;
        }
        out.last = o.last;
        out
    }

    /// Sample variance per axis (ddof = 1); NaN when fewer than two samples.
    pub fn var(&self) -> [f64; 3] {
        if self.n < 2 {
            return [f64::NAN; 3];
        }
        let d = (self.n - 1) as f64;
        [self.m2[0] / d, self.m2[1] / d, self.m2[2] / d]
    }

    /// Overlapping Allan variance at one sample, `sum (x[i] - x[i-1])^2 / (2 (n - 1))`, per
    /// axis; NaN when fewer than two samples.
    pub fn avar1(&self) -> [f64; 3] {
        if self.n < 2 {
            return [f64::NAN; 3];
        }
        let d = 2.0 * (self.n - 1) as f64;
        [self.d2[0] / d, self.d2[1] / d, self.d2[2] / d]
    }

    /// True when every mean, m2 and d2 is finite.
    pub fn is_finite(&self) -> bool {
        self.mean
            .iter()
            .chain(self.m2.iter())
            .chain(self.d2.iter())
            .all(|v| v.is_finite())
    }
}

fn fold(segs: &[Moments]) -> Moments {
    segs.iter().fold(Moments::EMPTY, |acc, x| acc.merge(x))
}

/// Streaming accumulator for one segment.
#[derive(Debug, Clone, PartialEq)]
pub struct SegmentAcc {
    done: Moments,
    d2_done: [f64; 3],
    shift: [f64; 3],
    nb: usize,
    lanes: Lanes,
    first: [f64; 3],
    last: [f64; 3],
}

impl Default for SegmentAcc {
    fn default() -> Self {
        Self::new()
    }
}

impl SegmentAcc {
    /// An empty segment.
    pub fn new() -> Self {
        SegmentAcc {
            done: Moments::EMPTY,
            d2_done: [0.0; 3],
            shift: [0.0; 3],
            nb: 0,
            lanes: Lanes::ZERO,
            first: [0.0; 3],
            last: [0.0; 3],
        }
    }

    /// Samples accumulated so far.
    pub fn count(&self) -> u64 {
        self.done.n + self.nb as u64
    }

    /// Add one sample.
    #[inline]
    pub fn push_row(&mut self, r: [f64; 3]) {
        let started = self.count() > 0;
        if self.nb == 0 {
            self.shift = r;
        }
        if !started {
            self.first = r;
        }
        let base = 3 * (self.nb % LANES);
        for (a, &v) in r.iter().enumerate() {
            let d = v - self.shift[a];
            self.lanes.s1[base + a] += d;
            self.lanes.s2[base + a] += d * d;
            if started {
                let e = v - self.last[a];
                self.lanes.d2[base + a] += e * e;
            }
        }
        self.last = r;
        self.nb += 1;
        if self.nb == BLOCK {
            self.flush();
        }
    }

    fn block_moments(&self) -> Moments {
        if self.nb == 0 {
            return Moments::EMPTY;
        }
        let n = self.nb as f64;
        let mut m = Moments {
            n: self.nb as u64,
            ..Moments::EMPTY
        };
        for a in 0..3 {
            let mut s1 = 0.0;
            let mut s2 = 0.0;
            for l in 0..LANES {
                s1 += self.lanes.s1[3 * l + a];
                s2 += self.lanes.s2[3 * l + a];
            }
            let md = s1 / n;
            m.mean[a] = self.shift[a] + md;
            // Clamp rounding below zero, but keep NaN (overflow) visible: `f64::max` would
            // turn a NaN into 0 and hide values too large to square.
            let m2 = s2 - s1 * md;
            m.m2[a] = if m2 < 0.0 { 0.0 } else { m2 };
        }
        m
    }

    fn lane_d2(&self) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (a, o) in out.iter_mut().enumerate() {
            let mut s = 0.0;
            for l in 0..LANES {
                s += self.lanes.d2[3 * l + a];
            }
            *o = self.d2_done[a] + s;
        }
        out
    }

    fn flush(&mut self) {
        let b = self.block_moments();
        self.d2_done = self.lane_d2();
        self.done = self.done.merge_stats(&b);
        self.nb = 0;
        self.lanes = Lanes::ZERO;
    }

    /// Add the rows of a row-major `(m, 3)` slice (length a multiple of 3).
    pub fn push_slice<T: Sample>(&mut self, data: &[T]) {
        let nrows = data.len() / 3;
        let mut i = 0;
        // Head: single rows until the lane index is aligned and a previous row exists.
        while (!self.nb.is_multiple_of(LANES) || self.count() == 0) && i < nrows {
            let r = &data[3 * i..3 * i + 3];
            self.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
            i += 1;
        }
        let mut rest = &data[3 * i..3 * nrows];
        // Body: whole groups of LANES rows, a block at a time, with the accumulators in locals
        // (registers) and the group seen as 3 * LANES independent sums: element j of a group
        // is lane j / 3, axis j % 3, exactly as in `push_row`, so results are bit-identical to
        // the row-by-row path and independent of chunking.
        while rest.len() >= W {
            if self.nb == 0 {
                self.shift = [rest[0].to_f64(), rest[1].to_f64(), rest[2].to_f64()];
            }
            let groups = ((BLOCK - self.nb) / LANES).min(rest.len() / W);
            let (body, tail) = rest.split_at(groups * W);
            let mut sh = [0.0; W];
            for (j, s) in sh.iter_mut().enumerate() {
                *s = self.shift[j % 3];
            }
            T::accumulate(body, &self.last, &sh, &mut self.lanes);
            let z = body.len();
            self.last = [
                body[z - 3].to_f64(),
                body[z - 2].to_f64(),
                body[z - 1].to_f64(),
            ];
            self.nb += groups * LANES;
            if self.nb == BLOCK {
                self.flush();
            }
            rest = tail;
        }
        for r in rest.chunks_exact(3) {
            self.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
        }
    }

    /// Add rows `[a, b)` of a `(N, 3)` view of any strides: in place when C-contiguous, else
    /// through a small row-major buffer (the same sums in the same order: bit-identical).
    pub fn push_view<T: Sample>(&mut self, v: &ArrayView2<'_, T>, a: usize, b: usize) {
        const ROWS: usize = 256;
        let sub = v.slice(ndarray::s![a..b, ..]);
        if let Some(s) = sub.as_slice() {
            self.push_slice(s);
            return;
        }
        let Some(&fill) = sub.iter().next() else {
            return;
        };
        let mut buf = [fill; 3 * ROWS];
        let mut k = 0;
        for r in sub.rows() {
            buf[3 * k..3 * k + 3].copy_from_slice(&[r[0], r[1], r[2]]);
            k += 1;
            if k == ROWS {
                self.push_slice(&buf);
                k = 0;
            }
        }
        self.push_slice(&buf[..3 * k]);
    }

    /// True when no sum has become NaN or inf (cheaper than `moments().is_finite()`).
    pub fn is_finite(&self) -> bool {
        let l = &self.lanes;
        self.done.is_finite()
            && self.d2_done.iter().all(|v| v.is_finite())
            && l.s1
                .iter()
                .chain(&l.s2)
                .chain(&l.d2)
                .fold(0.0, |acc, v| acc + v * 0.0)
                == 0.0
    }

    /// The moments of everything pushed so far.
    pub fn moments(&self) -> Moments {
        if self.count() == 0 {
            return Moments::EMPTY;
        }
        let mut m = self.done.merge_stats(&self.block_moments());
        m.d2 = self.lane_d2();
        m.first = self.first;
        m.last = self.last;
        m
    }
}

/// The hot loop: `s1[j] += x[j] - sh[j]`, `s2[j] += (x[j] - sh[j])^2` and
/// `d2[j] += (x[j] - x[j - 3])^2` over groups of `3 * LANES` values (no FMA contraction, so
/// the rounding is the same as in `SegmentAcc::push_row`).
#[inline(always)]
fn accumulate_groups<T: Sample>(body: &[T], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    if body.len() < W {
        return;
    }
    let (mut s1, mut s2, mut d2) = (l.s1, l.s2, l.d2);
    // The first group: the previous row of its first row is `prev`.
    for j in 0..W {
        let x = body[j].to_f64();
        let d = x - sh[j];
        s1[j] += d;
        s2[j] += d * d;
        let p = if j < 3 { prev[j] } else { body[j - 3].to_f64() };
        let e = x - p;
        d2[j] += e * e;
    }
    // The others: the previous row of element j is element j - 3 (an offset slice).
    for (g, gp) in body[W..].chunks_exact(W).zip(body[W - 3..].chunks_exact(W)) {
        for j in 0..W {
            let x = g[j].to_f64();
            let d = x - sh[j];
            s1[j] += d;
            s2[j] += d * d;
            let e = x - gp[j].to_f64();
            d2[j] += e * e;
        }
    }
    l.s1 = s1;
    l.s2 = s2;
    l.d2 = d2;
}

/// The widest kernel family the dispatchers may choose: 0 the portable loops (compiled for
/// the baseline target), 1 AVX2 (+ FMA), 2 AVX-512 (int16 only). Always 2 outside tests; the
/// unit tests lower it on their own thread to check every path against the others.
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
#[inline(always)]
fn kernel_cap() -> u8 {
    #[cfg(test)]
    {
        KERNEL_CAP.with(std::cell::Cell::get)
    }
    #[cfg(not(test))]
    {
        2
    }
}

#[cfg(test)]
thread_local! {
    static KERNEL_CAP: std::cell::Cell<u8> = const { std::cell::Cell::new(2) };
}

/// The float kernel: [`simd::groups_fma`] (explicit AVX2 vectors) when the CPU has AVX2 and
/// FMA, else [`accumulate_groups`] compiled for AVX2 when it has AVX2, else the portable loop.
/// All three do the same operations in the same order: bit-identical results.
#[inline]
fn accumulate_dispatch<T: Sample>(body: &[T], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    #[cfg(target_arch = "x86_64")]
    if kernel_cap() >= 1 && std::is_x86_feature_detected!("avx2") {
        if std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports AVX2 and FMA (checked just above).
            unsafe { simd::groups_fma(body, prev, sh, l) };
        } else {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { accumulate_groups_avx2(body, prev, sh, l) };
        }
        return;
    }
    accumulate_groups(body, prev, sh, l);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn accumulate_groups_avx2<T: Sample>(body: &[T], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    accumulate_groups(body, prev, sh, l);
}

/// Exact integer sums of int16 values over a piece, per axis: `s1 = sum (x - c)`,
/// `s2 = sum (x - c)^2` and `d2 = sum (x - previous row)^2`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct I16Sums {
    s1: [i64; 3],
    s2: [u64; 3],
    d2: [u64; 3],
}

impl I16Sums {
    /// Add the totals to lane 0 of `l` (exact: see [`accumulate_i16`]).
    fn add_to(&self, l: &mut Lanes) {
        for a in 0..3 {
            l.s1[a] += self.s1[a] as f64;
            l.s2[a] += self.s2[a] as f64;
            l.d2[a] += self.d2[a] as f64;
        }
    }
}

/// [`i16_sums`] for a few rows (no lane set-up).
#[inline(always)]
fn i16_rows(x: &[i16], p: &[i16], c: &[i32; 3], t: &mut I16Sums) {
    for (r, rp) in x.chunks_exact(3).zip(p.chunks_exact(3)) {
        for a in 0..3 {
            let v = i32::from(r[a]);
            let d = i64::from(v - c[a]);
            let e = i64::from(v - i32::from(rp[a]));
            t.s1[a] += d;
            t.s2[a] += (d * d) as u64;
            t.d2[a] += (e * e) as u64;
        }
    }
}

/// The portable exact int16 sums of whole rows `x` (value `j` on axis `j % 3`), whose
/// previous rows are `p` (`p[j]` is the value 3 before `x[j]`; same length), shift `c`.
#[inline(always)]
fn i16_sums(x: &[i16], p: &[i16], c: &[i32; 3], t: &mut I16Sums) {
    const U: usize = 2 * W;
    let shu: [i32; U] = std::array::from_fn(|j| c[j % 3]);
    let mut a1 = [0i32; U];
    let mut a2 = [0u64; U];
    let mut a3 = [0u64; U];
    // |d|, |e| <= 65535, so their squares fit u32 (the wrapping product of the two's
    // complement bits is exact).
    let sq = |v: i32| u64::from((v as u32).wrapping_mul(v as u32));
    for (g, gp) in x.chunks_exact(U).zip(p.chunks_exact(U)) {
        for j in 0..U {
            let v = i32::from(g[j]);
            let d = v - shu[j];
            a1[j] += d;
            a2[j] += sq(d);
            a3[j] += sq(v - i32::from(gp[j]));
        }
    }
    let done = (x.len().min(p.len()) / U) * U;
    for (j, (&v, &q)) in x[done..].iter().zip(&p[done..]).enumerate() {
        let v = i32::from(v);
        let d = v - shu[j];
        a1[j] += d;
        a2[j] += sq(d);
        a3[j] += sq(v - i32::from(q));
    }
    for j in 0..U {
        t.s1[j % 3] += i64::from(a1[j]);
        t.s2[j % 3] += a2[j];
        t.d2[j % 3] += a3[j];
    }
}

/// int16 counts: the same sums in exact integer arithmetic.
///
/// With an integer shift every deviation `d` is an integer with `|d| <= 65535`, and so is every
/// first difference, so within one block (<= 4096 rows) every float64 partial sum of `d`,
/// `d^2` and `e^2` in [`accumulate_groups`] is an integer below 2^53 and therefore exact
/// whatever the order. Integer sums give the same exact totals, so the result is bit-identical
/// to the float path (the row-by-row and strided paths included). The totals go into lane 0;
/// lanes are only ever summed.
///
/// `prev` and `sh` must hold int16 values (checked by [`accumulate_i16_dispatch`]).
#[inline(always)]
fn accumulate_i16(body: &[i16], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    if body.len() < 3 {
        return;
    }
    let c = [sh[0] as i32, sh[1] as i32, sh[2] as i32];
    let p0 = [prev[0] as i16, prev[1] as i16, prev[2] as i16];
    let mut t = I16Sums::default();
    i16_rows(&body[..3], &p0, &c, &mut t);
    i16_sums(&body[3..], &body[..body.len() - 3], &c, &mut t);
    t.add_to(l);
}

/// True when `v` is an int16 value (so deviations and differences from it stay within 65535).
fn is_i16(v: f64) -> bool {
    // The cast saturates (NaN gives 0): the round trip is exact only for int16 values.
    f64::from(v as i16) == v
}

#[inline]
fn accumulate_i16_dispatch(body: &[i16], prev: &[f64; 3], sh: &[f64; W], l: &mut Lanes) {
    // The shift and the previous row come from earlier rows of the stream, which may have had
    // another dtype: the exact integer path needs them to be int16 values.
    if !(prev.iter().chain(&sh[..3]).all(|&v| is_i16(v))) {
        accumulate_dispatch(body, prev, sh, l);
        return;
    }
    #[cfg(target_arch = "x86_64")]
    {
        let cap = kernel_cap();
        if cap >= 2
            && std::is_x86_feature_detected!("avx512f")
            && std::is_x86_feature_detected!("avx512bw")
            && std::is_x86_feature_detected!("avx512vnni")
        {
            // SAFETY: the CPU supports AVX-512 F, BW and VNNI (checked just above); `prev`
            // and `sh` hold int16 values (checked at the top).
            unsafe { simd::i16_avx512(body, prev, sh, l) };
            return;
        }
        if cap >= 1 && std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above); `prev` and `sh` hold int16
            // values (checked at the top).
            unsafe { simd::i16_avx2(body, prev, sh, l) };
            return;
        }
    }
    accumulate_i16(body, prev, sh, l);
}

/// Check that `samples` is `(N, 3)` and not empty.
pub fn check_samples<T>(v: &ArrayView2<'_, T>) -> Result<usize> {
    if v.ncols() != 3 {
        return invalid(format!(
            "samples must have shape (N, 3) (x, y, z per row); got {} columns",
            v.ncols()
        ));
    }
    if v.nrows() == 0 {
        return invalid("samples are empty (0 rows)");
    }
    Ok(v.nrows())
}

/// Validate `[start, stop)` bounds against `n` samples: in range, non-empty, non-overlapping.
pub fn check_bounds(bounds: &[[usize; 2]], n: usize) -> Result<()> {
    if bounds.is_empty() {
        return invalid("bounds are empty: give at least one [start, stop) dwell");
    }
    for (k, &[a, b]) in bounds.iter().enumerate() {
        if a >= b {
            return invalid(format!(
                "dwell {k}: bounds [{a}, {b}) are empty or reversed (start must be < stop)"
            ));
        }
        if b > n {
            return invalid(format!(
                "dwell {k}: bounds [{a}, {b}) out of range for {n} samples"
            ));
        }
    }
    let mut order: Vec<usize> = (0..bounds.len()).collect();
    order.sort_by_key(|&k| bounds[k][0]);
    for w in order.windows(2) {
        let (p, q) = (bounds[w[0]], bounds[w[1]]);
        if q[0] < p[1] {
            return invalid(format!(
                "dwells {} [{}, {}) and {} [{}, {}) overlap",
                w[0], p[0], p[1], w[1], q[0], q[1]
            ));
        }
    }
    Ok(())
}

/// [`check_bounds`] plus the dwell-statistics rule: every dwell has at least
/// [`MIN_DWELL_SAMPLES`] samples.
pub fn check_dwell_bounds(bounds: &[[usize; 2]], n: usize) -> Result<()> {
    check_bounds(bounds, n)?;
    for (k, &[a, b]) in bounds.iter().enumerate() {
        if b - a < MIN_DWELL_SAMPLES {
            return invalid(format!(
                "dwell {k}: bounds [{a}, {b}) hold {} sample; a dwell needs at least \
                 {MIN_DWELL_SAMPLES} samples (its variance is undefined otherwise)",
                b - a
            ));
        }
    }
    Ok(())
}

/// Check a per-sample channel (time, temperature): its length and that it is finite.
pub fn check_channel(x: Option<&[f64]>, n: usize, what: &str) -> Result<()> {
    let Some(x) = x else { return Ok(()) };
    if x.len() != n {
        return invalid(format!(
            "{what} has {} values but the samples have {n} rows",
            x.len()
        ));
    }
    if let Some(i) = x.iter().position(|v| !v.is_finite()) {
        let bad = x.iter().filter(|v| !v.is_finite()).count();
        return invalid(format!(
            "{what} contains NaN or inf: {bad} value(s), the first at row {i} ({}); \
             {what} must be finite everywhere",
            x[i]
        ));
    }
    Ok(())
}

/// Rows of `[a, b)` with a NaN or inf value: how many, and the first one (view-relative).
fn count_bad<T: Sample>(v: &ArrayView2<'_, T>, a: usize, b: usize) -> (u64, Option<usize>) {
    let mut n = 0;
    let mut first = None;
    for (i, r) in v
        .slice(ndarray::s![a..b, ..])
        .rows()
        .into_iter()
        .enumerate()
    {
        if r.iter().any(|x| !x.to_f64().is_finite()) {
            n += 1;
            first.get_or_insert(a + i);
        }
    }
    (n, first)
}

// ---- Allan noise inflation -------------------------------------------------------------------

/// Factor by which the noise of a dwell's mean exceeds white noise, per axis, from the
/// consecutive segments that cover the dwell (`total` is their merge).
///
/// Definition (per axis): with `L` samples, `r(m) = ADEV(m) sqrt(m) / ADEV(1)` compares the
/// overlapping Allan deviation at cluster size `m` with white noise of the same
/// sample-to-sample deviation; it is evaluated at `m16 ~ L/16` and `m4 ~ L/4` and extrapolated
/// to `tau = L` along the log-log slope between them (clipped to `[0, 1]`):
/// `f = r(m4) (L / m4)^slope`. `f ~ 1` for white noise, `> 1` for flicker or random-walk noise.
///
/// `ADEV(1)` is exact (from the summed squared first differences). `ADEV(m)` is the
/// overlapping estimator at segment stride: clusters of `J` whole segments starting at every
/// segment boundary (`J = S/16` and `S/4` of `S` segments; 64 sub-blocks per dwell for given
/// bounds, the detector's blocks for detected dwells). It has the same expectation as the
/// sample-stride estimator and a slightly larger variance.
///
/// NaN where not estimable: fewer than [`MIN_ALLAN_SAMPLES`] samples or 8 segments, or no
/// sample-to-sample variation on that axis.
pub fn allan_inflation(segs: &[Moments], total: &Moments) -> [f64; 3] {
    let s = segs.len();
    if s == 0 {
        return [f64::NAN; 3];
    }
    // Prefix sums of counts and of deviations from the first segment's mean (no cancellation
    // of large offsets such as raw counts).
    let r0 = segs[0].mean;
    let mut c = vec![0.0f64; s + 1];
    let mut p = vec![[0.0f64; 3]; s + 1];
    for (i, m) in segs.iter().enumerate() {
        let n = m.n as f64;
        c[i + 1] = c[i] + n;
        for a in 0..3 {
            let v = if m.n == 0 {
                0.0
            } else {
                n * (m.mean[a] - r0[a])
            };
            p[i + 1][a] = p[i][a] + v;
        }
    }
    allan_from_prefix(&c, &p, total)
}

/// [`allan_inflation`] from prefix sums over `S` segments: `c[i]` samples and `p[i]` the sum of
/// deviations from any fixed reference over the first `i` segments (`S + 1` entries each).
pub fn allan_from_prefix(c: &[f64], p: &[[f64; 3]], total: &Moments) -> [f64; 3] {
    let s = c.len().saturating_sub(1);
    if total.n < MIN_ALLAN_SAMPLES || s < 8 || p.len() != c.len() || !total.is_finite() {
        return [f64::NAN; 3];
    }
    let j16 = ((s as f64 / 16.0).round() as usize).max(1);
    let j4 = ((s as f64 / 4.0).round() as usize).max(j16 + 1).min(s / 2);
    if j4 <= j16 {
        return [f64::NAN; 3];
    }
    let big_l = total.n as f64;
    let avar = |j: usize| -> [f64; 3] {
        let mut acc = [0.0f64; 3];
        let mut cnt = 0usize;
        for i in 0..=(s - 2 * j) {
            let (n1, n2) = (c[i + j] - c[i], c[i + 2 * j] - c[i + j]);
            if n1 <= 0.0 || n2 <= 0.0 {
                continue;
            }
            for (a, o) in acc.iter_mut().enumerate() {
                let y1 = (p[i + j][a] - p[i][a]) / n1;
                let y2 = (p[i + 2 * j][a] - p[i + j][a]) / n2;
                *o += (y2 - y1) * (y2 - y1);
            }
            cnt += 1;
        }
        if cnt == 0 {
            return [f64::NAN; 3];
        }
        acc.map(|v| 0.5 * v / cnt as f64)
    };
    let (v16, v4) = (avar(j16), avar(j4));
    let (m16, m4) = (j16 as f64 * big_l / s as f64, j4 as f64 * big_l / s as f64);
    let a1 = total.avar1();
    let mut out = [f64::NAN; 3];
    for a in 0..3 {
        if !(a1[a] > 0.0 && a1[a].is_finite()) {
            continue;
        }
        let r16 = (v16[a] * m16 / a1[a]).sqrt();
        let r4 = (v4[a] * m4 / a1[a]).sqrt();
        let slope = ((r4.max(1e-12) / r16.max(1e-12)).ln() / (m4 / m16).ln()).clamp(0.0, 1.0);
        let f = r4 * (big_l / m4).powf(slope);
        if f.is_finite() {
            out[a] = f;
        }
    }
    out
}

/// Everything the dwell pass gives per dwell.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DwellStat {
    /// Moments of the whole dwell.
    pub moments: Moments,
    /// Mean of its first and of its second half, per axis.
    pub half_mean: [[f64; 3]; 2],
    /// Allan noise inflation per axis ([`allan_inflation`]; NaN where not estimable).
    pub inflation: [f64; 3],
}

impl DwellStat {
    /// From consecutive segments; the first half is `segs[..half_at]`.
    pub fn from_segments(segs: &[Moments], half_at: usize) -> DwellStat {
        let h = half_at.min(segs.len());
        let half = [fold(&segs[..h]), fold(&segs[h..])];
        let moments = half[0].merge(&half[1]);
        DwellStat {
            moments,
            half_mean: [half[0].mean, half[1].mean],
            inflation: allan_inflation(segs, &moments),
        }
    }

    /// From the running moments at the ends of `S` consecutive sub-blocks (`cum[S - 1]` is the
    /// whole dwell); the first half ends at `cum[half_at - 1]`. Sub-block and second-half means
    /// come from differences of running sums, relative to the first sample (so raw-count
    /// offsets do not cancel).
    fn from_cumulative(cum: &[Moments], half_at: usize) -> DwellStat {
        let Some(total) = cum.last().copied() else {
            return DwellStat {
                moments: Moments::EMPTY,
                half_mean: [[f64::NAN; 3]; 2],
                inflation: [f64::NAN; 3],
            };
        };
        let r0 = total.first;
        let mut c = vec![0.0f64; cum.len() + 1];
        let mut p = vec![[0.0f64; 3]; cum.len() + 1];
        for (i, m) in cum.iter().enumerate() {
            c[i + 1] = m.n as f64;
            for a in 0..3 {
                p[i + 1][a] = m.n as f64 * (m.mean[a] - r0[a]);
            }
        }
        let h = half_at.clamp(1, cum.len());
        let (n0, nt) = (c[h], c[cum.len()]);
        let m0 = cum[h - 1].mean;
        let m1 = std::array::from_fn(|a| {
            if nt > n0 {
                r0[a] + (p[cum.len()][a] - p[h][a]) / (nt - n0)
            } else {
                f64::NAN
            }
        });
        DwellStat {
            moments: total,
            half_mean: [m0, m1],
            inflation: allan_from_prefix(&c, &p, &total),
        }
    }
}

// ---- one dwell given by bounds ------------------------------------------------------------

/// A dwell `[a, b)` being accumulated in one pass, with its running moments taken at the ends
/// of [`SUBS`] equal sub-blocks (2 halves below [`MIN_ALLAN_SAMPLES`] samples), whatever the
/// chunking.
#[derive(Debug, Clone, PartialEq)]
struct DwellBuild {
    a: usize,
    b: usize,
    cum: Vec<Moments>,
    cur: SegmentAcc,
    bad: u64,
    first_bad: Option<usize>,
}

/// A finished dwell given by bounds, with its non-finite rows.
#[derive(Debug, Clone, Copy, PartialEq)]
struct DwellOutcome {
    stat: DwellStat,
    bad: u64,
    first_bad: Option<usize>,
}

impl DwellBuild {
    fn new(a: usize, b: usize) -> Self {
        DwellBuild {
            a,
            b,
            cum: Vec::new(),
            cur: SegmentAcc::new(),
            bad: 0,
            first_bad: None,
        }
    }

    fn nsub(&self) -> usize {
        if (self.b - self.a) as u64 >= MIN_ALLAN_SAMPLES {
            SUBS
        } else {
            2
        }
    }

    /// Stream position where sub-block `j` starts.
    fn edge(&self, j: usize) -> usize {
        let (l, n) = (self.b - self.a, self.nsub());
        match j.checked_mul(l) {
            Some(jl) => self.a + jl / n,
            None => self.a + (j as u128 * l as u128 / n as u128) as usize,
        }
    }

    /// Push stream rows `[lo, hi)` (within `[a, b)`) of `chunk`, whose row 0 is stream row `c0`.
    fn push<T: Sample>(&mut self, chunk: &ArrayView2<'_, T>, c0: usize, lo: usize, hi: usize) {
        let nsub = self.nsub();
        // The rows as one row-major slice when the chunk is C-contiguous (sliced once).
        let rows = chunk.slice(ndarray::s![lo - c0..hi - c0, ..]);
        let flat = rows.as_slice();
        let mut p = lo;
        while p < hi && self.cum.len() < nsub {
            let e = self.edge(self.cum.len() + 1);
            if e <= p {
                // Unreachable for a consistent state (checked when one is decoded).
                break;
            }
            let end = e.min(hi);
            match flat {
                Some(f) => self.cur.push_slice(&f[3 * (p - lo)..3 * (end - lo)]),
                None => self.cur.push_view(chunk, p - c0, end - c0),
            }
            p = end;
            if p == e {
                self.cum.push(self.cur.moments());
            }
        }
        // A NaN or inf sample makes the sums non-finite at once, and they stay so: counting
        // the rows pushed by each call that ends with non-finite sums counts every such row
        // once (as counting piece by piece did).
        if !self.cur.is_finite() {
            let (n, first) = count_bad(chunk, lo - c0, p - c0);
            self.bad += n;
            if self.first_bad.is_none() {
                self.first_bad = first.map(|i| i + c0);
            }
        }
    }

    fn is_done(&self) -> bool {
        self.cum.len() == self.nsub()
    }

    fn outcome(&self) -> DwellOutcome {
        DwellOutcome {
            stat: DwellStat::from_cumulative(&self.cum, self.nsub() / 2),
            bad: self.bad,
            first_bad: self.first_bad,
        }
    }
}

/// Refuse dwells (given by bounds) with non-finite samples or values too large to square.
fn check_outcomes(bounds: &[[usize; 2]], out: &[DwellOutcome]) -> Result<()> {
    let bad: Vec<usize> = (0..out.len()).filter(|&k| out[k].bad > 0).collect();
    if let Some(&k) = bad.first() {
        let [a, b] = bounds[k];
        let more = if bad.len() > 1 {
            format!(" (and {} more dwell(s))", bad.len() - 1)
        } else {
            String::new()
        };
        return invalid(format!(
            "samples contain NaN or inf in dwell {k} [{a}, {b}): {} row(s), the first at \
             sample {}{more}; a dwell given by bounds must be complete (cut it out, or use \
             detect_dwells, which treats non-finite samples as dropouts)",
            out[k].bad,
            out[k].first_bad.unwrap_or(a)
        ));
    }
    if let Some(k) = (0..out.len()).find(|&k| !out[k].stat.moments.is_finite()) {
        let [a, b] = bounds[k];
        return invalid(format!(
            "samples in dwell {k} [{a}, {b}) are too large to square in float64 (NaN or inf \
             variance): rescale them"
        ));
    }
    Ok(())
}

// ---- output resolution ---------------------------------------------------------------------

/// A bounded, chunking-independent subsample of the stream for the LSB estimate: the rows at
/// the multiples of a power-of-two step, the smallest step that keeps at most [`LSB_CAP`] rows.
#[derive(Debug, Clone, PartialEq)]
pub struct LsbSampler {
    step: u64,
    rows: Vec<[f64; 3]>,
    integer: bool,
    seen: bool,
}

impl Default for LsbSampler {
    fn default() -> Self {
        Self::new()
    }
}

impl LsbSampler {
    /// Nothing seen yet.
    pub fn new() -> Self {
        LsbSampler {
            step: 1,
            rows: Vec::new(),
            integer: true,
            seen: false,
        }
    }

    /// Offer the rows of `v`, the first of which is stream row `pos0`.
    ///
    /// The step is settled first from where the chunk ends (the smallest power of two that
    /// keeps at most [`LSB_CAP`] multiples below it), so only the rows kept are read.
    pub fn push<T: Sample>(&mut self, v: &ArrayView2<'_, T>, pos0: u64) {
        if v.nrows() == 0 {
            return;
        }
        self.seen = true;
        self.integer &= T::INTEGER;
        let end = pos0 + v.nrows() as u64;
        while end.div_ceil(self.step) > LSB_CAP as u64 {
            let mut i = 0usize;
            self.rows.retain(|_| {
                i += 1;
                i % 2 == 1
            });
            self.step *= 2;
        }
        let mut p = pos0.div_ceil(self.step) * self.step;
        while p < end {
            let r = v.row((p - pos0) as usize);
            self.rows
                .push([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
            p += self.step;
        }
    }

    /// Output resolution per axis: for integer samples the greatest common divisor of the
    /// spacings between distinct values (1 count for ordinary data); for float samples the
    /// common spacing of which every gap between distinct values is a whole multiple (within
    /// 10 %), or None when the values are not quantised (or an axis has one distinct value).
    pub fn estimate(&self) -> Option<[f64; 3]> {
        if !self.seen {
            return None;
        }
        let mut out = [0.0; 3];
        for (a, o) in out.iter_mut().enumerate() {
            if self.integer {
                // The gcd of the gaps between the sorted distinct values is the gcd of the
                // differences from any one value (both generate the same lattice): no sort.
                // Integer samples are finite and exact in f64, and so are their differences.
                let mut it = self.rows.iter().map(|r| r[a]).filter(|x| x.is_finite());
                let v0 = it.next().unwrap_or(0.0);
                let mut g = 0u64;
                for x in it {
                    if g == 1 {
                        break;
                    }
                    g = gcd(g, (x - v0).abs() as u64);
                }
                *o = if g == 0 { 1.0 } else { g as f64 };
                continue;
            }
            // Sorted by `f64::total_cmp` through its integer key (a total order: the same
            // sequence whichever sort), then the distinct values.
            let mut keys: Vec<i64> = self
                .rows
                .iter()
                .map(|r| r[a])
                .filter(|x| x.is_finite())
                .map(total_key)
                .collect();
            keys.sort_unstable();
            let mut v: Vec<f64> = keys.into_iter().map(from_total_key).collect();
            v.dedup();
            let d: Vec<f64> = v.windows(2).map(|w| w[1] - w[0]).collect();
            let q0 = d.iter().cloned().fold(f64::INFINITY, f64::min);
            if !(q0.is_finite() && q0 > 0.0) {
                return None;
            }
            let k: Vec<f64> = d.iter().map(|x| (x / q0).round()).collect();
            let q = d.iter().sum::<f64>() / k.iter().sum::<f64>();
            if !d.iter().zip(&k).all(|(x, k)| (x - k * q).abs() <= 0.1 * q) {
                return None;
            }
            *o = q;
        }
        Some(out)
    }
}

/// The integer whose order is `f64::total_cmp`'s (the transform `total_cmp` itself uses).
pub(crate) fn total_key(x: f64) -> i64 {
    let b = x.to_bits() as i64;
    b ^ ((((b >> 63) as u64) >> 1) as i64)
}

/// The inverse of [`total_key`] (the transform is an involution).
pub(crate) fn from_total_key(k: i64) -> f64 {
    f64::from_bits((k ^ ((((k >> 63) as u64) >> 1) as i64)) as u64)
}

fn gcd(mut a: u64, mut b: u64) -> u64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

// ---- automatic detection ---------------------------------------------------------------------

/// A sample rate for a message: six significant digits, no trailing zeros (19.1192, 100).
fn hz(fs: f64) -> String {
    if !(fs.is_finite() && fs > 0.0) {
        return format!("{fs}");
    }
    let decimals = (5 - fs.log10().floor() as i32).clamp(0, 12) as usize;
    let t = format!("{fs:.decimals$}");
    if t.contains('.') {
        t.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        t
    }
}

/// Settings of the automatic static-interval detector.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DetectorSettings {
    /// Sample rate, Hz.
    pub fs: f64,
    /// Moving-window length, s.
    pub window_s: f64,
    /// Threshold factor on the per-axis window variance relative to the noise estimate.
    pub k: f64,
    /// Minimum kept dwell length after trimming, s.
    pub min_dwell_s: f64,
    /// Settling trimmed at each end of a static run, s.
    pub trim_s: f64,
    /// Quantile of the window variances taken as the noise level.
    pub noise_quantile: f64,
    /// Block length of the compressed statistics, s.
    pub block_s: f64,
    /// Noise variance per axis given by the user (skips the estimate).
    pub noise_var: Option<[f64; 3]>,
}

/// `v` in the interval `(lo, hi]` (`open_lo`) or `[lo, hi]`, or an error naming the setting.
fn in_range(v: f64, name: &str, lo: f64, hi: f64, open_lo: bool, unit: &str) -> Result<()> {
    let ok = v.is_finite() && (if open_lo { v > lo } else { v >= lo }) && v <= hi;
    if ok {
        Ok(())
    } else {
        let br = if open_lo { "(" } else { "[" };
        invalid(format!(
            "{name} must be a finite number in {br}{lo}, {hi:e}]{unit}; got {v}"
        ))
    }
}

impl DetectorSettings {
    /// Defaults tuned once on three real sessions (Xsens, MPU6050, imucal) and a 5 kHz simulation.
    pub fn new(fs: f64) -> Self {
        DetectorSettings {
            fs,
            window_s: 1.0,
            k: 6.0,
            min_dwell_s: 1.0,
            trim_s: 0.1,
            noise_quantile: 0.2,
            block_s: 0.02,
            noise_var: None,
        }
    }

    /// Check every setting: finite, in range, and a window of at least
    /// [`MIN_WINDOW_SAMPLES`] samples.
    pub fn validate(&self) -> Result<()> {
        in_range(self.fs, "fs", 0.0, MAX_FS, true, " Hz")?;
        in_range(self.window_s, "window_s", 0.0, MAX_DURATION_S, true, " s")?;
        in_range(self.k, "k", 0.0, 1e6, true, " (threshold factor)")?;
        in_range(
            self.min_dwell_s,
            "min_dwell_s",
            0.0,
            MAX_DURATION_S,
            false,
            " s",
        )?;
        in_range(self.trim_s, "trim_s", 0.0, MAX_DURATION_S, false, " s")?;
        in_range(self.block_s, "block_s", 0.0, MAX_DURATION_S, true, " s")?;
        if !(self.noise_quantile > 0.0 && self.noise_quantile < 1.0) {
            return invalid(format!(
                "noise_quantile must be a number in (0, 1); got {}",
                self.noise_quantile
            ));
        }
        if self.block_s > self.window_s {
            return invalid(format!(
                "block_s must not exceed window_s; got block_s = {} s, window_s = {} s",
                self.block_s, self.window_s
            ));
        }
        let wn = self.window_s * self.fs;
        if wn < MIN_WINDOW_SAMPLES {
            return invalid(format!(
                "window_s = {} s at fs = {} Hz spans {wn:.3} sample(s); the detector needs at \
                 least {MIN_WINDOW_SAMPLES} samples per window (is fs the sample rate in Hz? \
                 else give window_s= {} s or more)",
                self.window_s,
                hz(self.fs),
                self.shortest_window_s()
            ));
        }
        if let Some(v) = self.noise_var {
            if !v.iter().all(|x| x.is_finite() && *x > 0.0 && *x < 1e300) {
                return invalid(format!(
                    "noise_var must be three positive finite variances; got {v:?}"
                ));
            }
        }
        Ok(())
    }

    /// The shortest window of [`MIN_WINDOW_SAMPLES`] samples at this rate, s, rounded up to
    /// two decimals (as messages and suggestions give it).
    pub fn shortest_window_s(&self) -> f64 {
        (MIN_WINDOW_SAMPLES / self.fs * 100.0).ceil() / 100.0
    }

    /// Samples per block (at least 1; at most `MAX_FS * MAX_DURATION_S`, so no overflow).
    pub fn block_len(&self) -> usize {
        ((self.fs * self.block_s)
            .round()
            .clamp(1.0, MAX_FS * MAX_DURATION_S)) as usize
    }

    /// Blocks per window (at least 2).
    pub fn window_blocks(&self) -> usize {
        let w = (self.window_s * self.fs / self.block_len() as f64).round();
        (w.clamp(2.0, MAX_FS * MAX_DURATION_S)) as usize
    }

    /// Fewest blocks in a kept dwell (min_dwell_s, and at least [`MIN_DWELL_SAMPLES`]).
    fn min_blocks(&self) -> usize {
        let b = self.block_len() as f64;
        let m = (self.min_dwell_s * self.fs / b)
            .ceil()
            .max((MIN_DWELL_SAMPLES as f64 / b).ceil());
        (m.clamp(1.0, MAX_FS * MAX_DURATION_S)) as usize
    }

    /// Blocks trimmed at each end of a static run.
    fn trim_blocks(&self) -> usize {
        let t = (self.trim_s * self.fs / self.block_len() as f64).round();
        (t.clamp(0.0, MAX_FS * MAX_DURATION_S)) as usize
    }
}

/// What the detector decided.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// `[start, stop)` sample bounds of each dwell.
    pub bounds: Vec<[usize; 2]>,
    /// Statistics of each dwell.
    pub stats: Vec<DwellStat>,
    /// Noise variance per axis used (estimated or given), in squared input units.
    pub noise_var: [f64; 3],
    /// Threshold on the window variance per axis, in squared input units.
    pub threshold: [f64; 3],
    /// Stretches left out although the sensor looks still in them: the window variance is
    /// above the threshold, but the means of the window's two halves agree as well as in a
    /// static window (vibration, not motion); `[start, stop)` sample bounds, at least
    /// `min_dwell_s` long after the trim.
    pub vibrating: Vec<Vibrating>,
    /// Shorter settings that find more steady dwells, when fewer than [`PROBE_BELOW`] were
    /// found ([`ShorterWindow`]).
    pub shorter: Option<ShorterWindow>,
}

/// A stretch that vibrates above the detector's threshold while its mean stays put.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vibrating {
    /// `[start, stop)` sample bounds.
    pub bounds: [usize; 2],
    /// Sample std per axis over the stretch, input units.
    pub std: [f64; 3],
}

/// Half-window means differing by more than this many standard errors mean motion.
const STILL_SE: f64 = 4.0;

/// Prefix sums of the block counts and of `n * (mean - ref)` per axis, for the mean of any
/// run of blocks in O(1) (a block that is not finite adds nothing: every window holding one
/// has an infinite variance and is never tested).
struct MeanPrefix {
    n: Vec<f64>,
    s: Vec<[f64; 3]>,
}

impl MeanPrefix {
    fn new(blocks: &[Moments]) -> Self {
        let r = blocks
            .iter()
            .find(|m| m.is_finite())
            .map_or([0.0; 3], |m| m.mean);
        let (mut n, mut s) = (vec![0.0], vec![[0.0; 3]]);
        for m in blocks {
            let ok = m.is_finite();
            let c = if ok { m.n as f64 } else { 0.0 };
            let last = s[s.len() - 1];
            n.push(n[n.len() - 1] + c);
            s.push(std::array::from_fn(|a| {
                last[a] + if ok { c * (m.mean[a] - r[a]) } else { 0.0 }
            }));
        }
        MeanPrefix { n, s }
    }

    /// Mean (less the reference) and count of blocks `[a, b)`.
    fn mean(&self, a: usize, b: usize) -> ([f64; 3], f64) {
        let c = self.n[b] - self.n[a];
        (
            std::array::from_fn(|k| (self.s[b][k] - self.s[a][k]) / c.max(1.0)),
            c,
        )
    }

    /// The window of `w` blocks from `i` is still: the means of its two halves agree within
    /// [`STILL_SE`] standard errors of white noise of the threshold variance `v` (as well as
    /// they would in a window the detector takes as static), on every axis: vibration that
    /// the halves average out passes, motion (a mean that moves) does not, however large.
    fn still(&self, i: usize, w: usize, v: &[f64; 3]) -> bool {
        let h = w / 2;
        if h == 0 {
            return false;
        }
        let (ma, na) = self.mean(i, i + h);
        let (mb, nb) = self.mean(i + h, i + w);
        halves_agree(&ma, &mb, 1.0 / na.max(1.0) + 1.0 / nb.max(1.0), v)
    }
}

/// The means `ma`, `mb` of two halves agree within [`STILL_SE`] standard errors of white
/// noise of variance `v` on every axis; `inv` is `1 / na + 1 / nb` of their sample counts.
fn halves_agree(ma: &[f64; 3], mb: &[f64; 3], inv: f64, v: &[f64; 3]) -> bool {
    (0..3).all(|k| {
        let d = ma[k] - mb[k];
        d.is_finite() && d * d <= STILL_SE * STILL_SE * v[k] * inv
    })
}

/// A window variance at quantile `q` of the (finite) window variances `col`.
fn quantile_of(col: &mut [f64], q: f64) -> f64 {
    let i = ((col.len() - 1) as f64 * q).round() as usize;
    let (_, val, _) = col.select_nth_unstable_by(i, |x, y| x.total_cmp(y));
    *val
}

/// The noise variance of one axis from its window variances `col` (windows of `m`
/// samples): their quantile `q`, which assumes that at least that fraction of the windows
/// is static. When the session moves most of the time (a hand-waved sensor with brief
/// pauses), that quantile lies among moving windows, far above the still ones. When it
/// exceeds [`MOVING_RATIO`] times the quantile `q / 4`, the still windows are taken as those
/// within the spread of a static window's variance above that stiller quantile (chi-square
/// with `m - 1` degrees of freedom: its 99.9 % point over its `q / 4` point), and the noise
/// is the quantile `q` of those, as in a static session.
fn noise_level(col: &mut [f64], q: f64, m: usize) -> f64 {
    let v = quantile_of(col, q);
    let low = quantile_of(col, q / 4.0);
    let moving = v > MOVING_RATIO * low; // false for NaN too
    if !moving {
        return v;
    }
    let dof = (m.max(2) - 1) as f64;
    let spread = chi2_isf(1e-3, dof) / chi2_isf(1.0 - q / 4.0, dof);
    if !(spread.is_finite() && spread > 1.0) {
        return v;
    }
    let cut = low * spread;
    let still = col.iter().filter(|x| **x <= cut).count() as f64 / col.len() as f64;
    quantile_of(col, q * still)
}

/// The quantile of the window variances exceeding this many times their quarter quantile
/// means most windows move (see [`noise_level`]).
const MOVING_RATIO: f64 = 4.0;

/// [`fold`] without the first differences: moments only (the detector's windows).
fn fold_stats(segs: &[Moments]) -> Moments {
    segs.iter()
        .fold(Moments::EMPTY, |acc, x| acc.merge_stats(x))
}

/// Runs of blocks flagged in `mark` (window centres), trimmed by `trim` blocks at both ends
/// and kept when at least `min_blocks` long, as block ranges.
fn runs(mark: &[bool], trim: usize, min_blocks: usize) -> Vec<[usize; 2]> {
    let mut out = Vec::new();
    let mut j = 0;
    while j < mark.len() {
        if !mark[j] {
            j += 1;
            continue;
        }
        let start = j;
        while j < mark.len() && mark[j] {
            j += 1;
        }
        let (a, z) = (start.saturating_add(trim), j.saturating_sub(trim));
        if z > a && z - a >= min_blocks {
            out.push([a, z]);
        }
    }
    out
}

/// Detect static intervals from compressed block statistics.
///
/// `blocks[j]` holds samples `[j * b, (j + 1) * b)` with `b = settings.block_len()`. A block
/// whose moments are not finite holds NaN or inf samples (a dropout): no window that contains
/// it is static, so no dwell contains it.
///
/// `n` is the number of samples pushed (the blocks hold all but the last partial block): the
/// messages count it. `lsb` is the output step per axis of quantised samples: the noise
/// variance the detector estimates is floored at the quantisation's `lsb^2 / 12` (see
/// [`quantisation_floor`]).
pub fn detect_from_blocks(
    blocks: &[Moments],
    s: &DetectorSettings,
    n: usize,
    lsb: Option<[f64; 3]>,
) -> Result<Detection> {
    let floor = quantisation_floor(lsb);
    let det = detect_once(blocks, s, n, floor);
    let found = match &det {
        Ok(d) => d.bounds.len(),
        Err(CoreError::Degenerate(_)) => 0,
        Err(_) => return det,
    };
    // Only a recording mostly not taken as still can hold brief rests the window missed (a
    // few long rests found cover most of it: shorter windows would only cut them up).
    let still: usize = det
        .as_ref()
        .map_or(0, |d| d.bounds.iter().map(|[a, b]| b - a).sum());
    if found >= PROBE_BELOW || 4 * still >= n {
        return det;
    }
    let shorter = probe_shorter(blocks, s, n, found, floor);
    match (det, shorter) {
        (Ok(mut d), sh) => {
            d.shorter = sh;
            Ok(d)
        }
        (Err(CoreError::Degenerate(m)), Some(sh)) => {
            Err(CoreError::Degenerate(format!("{m}. {}", sh.advice())))
        }
        (e, _) => e,
    }
}

/// The least noise variance per axis the detector takes for samples quantised in steps of
/// `lsb`: `lsb^2 / 12`, the variance of the rounding. Below about a third of a step of white
/// noise, the windows that sit inside one output code have a variance of zero or nearly, so
/// their low quantile - the estimate - is far below the noise of the windows that straddle a
/// code boundary (a quarter of a step squared): every such still window read as motion (2 of
/// 20 rests found at 0.2 LSB of noise; at 0.12 LSB and below the estimate was zero and the
/// detection refused). Zero when the samples are not quantised.
fn quantisation_floor(lsb: Option<[f64; 3]>) -> [f64; 3] {
    lsb.map_or([0.0; 3], |l| {
        l.map(|x| if x.is_finite() { x * x / 12.0 } else { 0.0 })
    })
}

/// Below this many dwells the detector also tries shorter windows ([`probe_shorter`]).
const PROBE_BELOW: usize = 9;

/// Shorter detector settings that find more steady dwells than the ones used (brief rests:
/// a hand-turned sensor held for a second in each pose). Only suggested, never applied: a
/// short window also takes the slow ends of moves.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShorterWindow {
    /// Window, s.
    pub window_s: f64,
    /// Shortest dwell, s.
    pub min_dwell_s: f64,
    /// Settling trimmed at each end, s.
    pub trim_s: f64,
    /// Steady dwells these settings find (see [`probe_shorter`]).
    pub dwells: usize,
}

impl ShorterWindow {
    /// The suggestion in words (Python keyword spelling; the command line rewrites it).
    pub fn advice(&self) -> String {
        format!(
            "Shorter settings, window_s = {} s with min_dwell_s = {} s and trim_s = {} s, \
             find {} steady dwell(s) (brief rests); check them (the dwells plot, the fit's \
             chi2/dof) before use",
            self.window_s, self.min_dwell_s, self.trim_s, self.dwells
        )
    }
}

/// The windows tried for brief rests: 0.5, 0.25 and 0.1 s, none under the detector's fewest
/// samples per window (at two decimals) nor under a block, and only those shorter than the
/// window used. With each, the shortest dwell becomes half the window and the settling trim a
/// quarter of it (or stay as given, if less): a rest of twice the window is then found.
fn shorter_settings(s: &DetectorSettings) -> Vec<DetectorSettings> {
    let floor = s.shortest_window_s().max(s.block_s);
    let mut out: Vec<DetectorSettings> = Vec::new();
    for w in [0.5, 0.25, 0.1] {
        let w = f64::max(w, floor);
        if w < s.window_s && out.iter().all(|o| o.window_s != w) {
            let c = DetectorSettings {
                window_s: w,
                min_dwell_s: s.min_dwell_s.min(0.5 * w),
                trim_s: s.trim_s.min(0.25 * w),
                ..*s
            };
            if c.validate().is_ok() {
                out.push(c);
            }
        }
    }
    out
}

/// A dwell is steady when the means of its two halves agree within [`STILL_SE`] standard
/// errors of white noise of the noise variance `v` on every axis: a rest, not the slow end
/// of a move that a short window takes as static. (A test of the dwell's own variance against
/// the noise's was tried as well: on a real hand-turned LSM303 log, mgiurato's, 2 of 15 rests
/// exceed its 99.9 % point, a hand's tremor, and it did not reject the move ends of a
/// simulated sensor on a lever arm, whose variance is the noise's.)
fn steady(st: &DwellStat, v: &[f64; 3]) -> bool {
    let n = st.moments.n as f64;
    // Halves of n / 2 samples each.
    halves_agree(&st.half_mean[0], &st.half_mean[1], 4.0 / n.max(1.0), v)
}

/// The shorter settings ([`shorter_settings`]) that find the most dwells, more than `found`
/// and at least 3, every one of them steady (the longest window among equals), or `None`.
fn probe_shorter(
    blocks: &[Moments],
    s: &DetectorSettings,
    n: usize,
    found: usize,
    floor: [f64; 3],
) -> Option<ShorterWindow> {
    let mut best: Option<ShorterWindow> = None;
    for c in shorter_settings(s) {
        let Ok(d) = detect_once(blocks, &c, n, floor) else {
            continue;
        };
        // Every dwell found must be steady: one that creeps is the end of a move, and the
        // settings that take it would put it into the fit.
        let n = d.stats.len();
        let all_steady = d.stats.iter().all(|st| steady(st, &d.noise_var));
        if all_steady && n > found.max(2) && best.is_none_or(|b| n > b.dwells) {
            best = Some(ShorterWindow {
                window_s: c.window_s,
                min_dwell_s: c.min_dwell_s,
                trim_s: c.trim_s,
                dwells: n,
            });
        }
    }
    best
}

/// [`detect_from_blocks`] without the probe of shorter windows; `floor` is the least noise
/// variance per axis ([`quantisation_floor`]).
fn detect_once(
    blocks: &[Moments],
    s: &DetectorSettings,
    n: usize,
    floor: [f64; 3],
) -> Result<Detection> {
    s.validate()?;
    let b = s.block_len();
    let w = s.window_blocks();
    if blocks.len() <= w {
        return invalid(format!(
            "stream too short for dwell detection: {} samples, need more than one {} s window \
             ({} samples)",
            n,
            s.window_s,
            w.saturating_mul(b)
        ));
    }
    // Window variance per axis; window i covers blocks i..i+w (inf where it has a dropout).
    let nw = blocks.len() - w + 1;
    let var: Vec<[f64; 3]> = (0..nw)
        .into_par_iter()
        .map(|i| {
            let win = &blocks[i..i + w];
            if win.iter().any(|m| !m.is_finite()) {
                return [f64::INFINITY; 3];
            }
            fold_stats(win).var()
        })
        .collect();
    let noise_var = match s.noise_var {
        Some(v) => v,
        None => {
            let mut nv = [0.0; 3];
            for (a, slot) in nv.iter_mut().enumerate() {
                let mut col: Vec<f64> =
                    var.iter().map(|v| v[a]).filter(|v| v.is_finite()).collect();
                if col.is_empty() {
                    return invalid(format!(
                        "no {} s window of the stream is free of NaN or inf samples: the \
                         noise level cannot be estimated",
                        s.window_s
                    ));
                }
                *slot = noise_level(&mut col, s.noise_quantile, w * b);
            }
            // A perfectly constant axis (e.g. clipped or simulated noise-free) must not make
            // every tiny change look like motion, nor divide by zero.
            let top = nv.iter().cloned().fold(0.0, f64::max);
            for (v, f) in nv.iter_mut().zip(floor) {
                if *v <= 0.0 {
                    *v = if top > 0.0 { top } else { f64::MIN_POSITIVE };
                }
                // Then no less than the rounding's own variance (quantised samples).
                *v = v.max(f);
            }
            nv
        }
    };
    let thr = [s.k * noise_var[0], s.k * noise_var[1], s.k * noise_var[2]];
    let h = w / 2;
    let mut is_static = vec![false; blocks.len()];
    let mut is_still = vec![false; blocks.len()];
    let prefix = MeanPrefix::new(blocks);
    for (i, v) in var.iter().enumerate() {
        is_static[i + h] = (0..3).all(|a| v[a] < thr[a]);
        is_still[i + h] =
            !is_static[i + h] && v.iter().all(|x| x.is_finite()) && prefix.still(i, w, &thr);
    }
    let trim = s.trim_blocks();
    let min_blocks = s.min_blocks();
    let mut bounds = Vec::new();
    let mut stats = Vec::new();
    for [a, z] in runs(&is_static, trim, min_blocks) {
        let segs = &blocks[a..z];
        bounds.push([a * b, z * b]);
        stats.push(DwellStat::from_segments(segs, segs.len() / 2));
    }
    let vibrating = runs(&is_still, trim, min_blocks)
        .into_iter()
        .map(|[a, z]| {
            let m = fold_stats(&blocks[a..z]);
            let v = m.var();
            Vibrating {
                bounds: [a * b, z * b],
                std: [v[0].sqrt(), v[1].sqrt(), v[2].sqrt()],
            }
        })
        .collect();
    if bounds.is_empty() {
        if is_static[h..h + nw].iter().all(|&x| x) {
            // Static throughout: only the length is missing. No window is centred on the
            // stream's first and last half window, so they are not used (a recording's first
            // samples often carry a start-up transient: on a real MPU-9150 log the first
            // 0.5 s read 0.06 m/s^2 off the rest of the dwell, 7 standard errors).
            return degenerate(format!(
                "the whole stream is static but too short for a dwell: {n} samples ({:.4} s at \
                 {} Hz); a dwell needs min_dwell_s = {} s after {} s trimmed at each \
                 end, and half a window (window_s = {} s) at each end of the stream is not \
                 used: about {:.2} s in all. Record longer, or lower min_dwell_s= or \
                 window_s=",
                n as f64 / s.fs,
                hz(s.fs),
                s.min_dwell_s,
                s.trim_s,
                s.window_s,
                s.window_s + s.min_dwell_s + 2.0 * s.trim_s
            ));
        }
        return degenerate(format!(
            "no static dwell found in {n} samples ({:.4} s at {} Hz): no run of at least \
             min_dwell_s = {} s stayed below k = {} x the noise variance (noise std {:.3e}, \
             {:.3e}, {:.3e}); check fs, or lower min_dwell_s=, window_s= or trim_s= (a rest \
             must last a window, the shortest dwell and two trims, {:.3} s here, to be seen), or raise \
             k= (or give noise_std=)",
            n as f64 / s.fs,
            hz(s.fs),
            s.min_dwell_s,
            s.k,
            noise_var[0].sqrt(),
            noise_var[1].sqrt(),
            noise_var[2].sqrt(),
            s.window_s + s.min_dwell_s + 2.0 * s.trim_s
        ));
    }
    Ok(Detection {
        bounds,
        stats,
        noise_var,
        threshold: thr,
        vibrating,
        shorter: None,
    })
}

// ---- the dwell table -----------------------------------------------------------------------

/// A finished dwell table.
#[derive(Debug, Clone, PartialEq)]
pub struct DwellTable {
    /// `[start, stop)` sample bounds.
    pub bounds: Vec<[usize; 2]>,
    /// Statistics per dwell (moments, half-dwell moments, Allan inflation).
    pub stats: Vec<DwellStat>,
    /// Mid time `(t[start] + t[stop-1]) / 2` per dwell, when a time channel was pushed.
    pub t_mid: Option<Vec<f64>>,
    /// Mean of the auxiliary channel (temperature) per dwell, when one was pushed.
    pub aux_mean: Option<Vec<f64>>,
    /// Detection diagnostics, when the dwells were detected.
    pub noise_var: Option<[f64; 3]>,
    /// Detection threshold per axis, when the dwells were detected.
    pub threshold: Option<[f64; 3]>,
    /// Output resolution per axis ([`LsbSampler::estimate`]).
    pub lsb: Option<[f64; 3]>,
    /// Rows with a NaN or inf value that were left out of every dwell (detection only;
    /// dwells given by bounds refuse them).
    pub dropped: u64,
    /// Stretches that look still but vibrate above the detection threshold (detection only).
    pub vibrating: Vec<Vibrating>,
    /// Shorter detector settings that find more steady dwells (detection only, when few were
    /// found).
    pub shorter: Option<ShorterWindow>,
}

impl DwellTable {
    /// Moments of each dwell.
    pub fn moments(&self) -> Vec<Moments> {
        self.stats.iter().map(|s| s.moments).collect()
    }
}

fn sum_seq(x: &[f64]) -> f64 {
    let mut s = 0.0;
    for v in x {
        s += *v;
    }
    s
}

/// Per-dwell statistics of `samples` over `[start, stop)` bounds (parallel over dwells), with
/// optional per-sample time and auxiliary (temperature) channels.
pub fn dwell_table<T: Sample>(
    samples: &ArrayView2<'_, T>,
    bounds: &[[usize; 2]],
    t: Option<&[f64]>,
    aux: Option<&[f64]>,
) -> Result<DwellTable> {
    let n = check_samples(samples)?;
    check_dwell_bounds(bounds, n)?;
    check_channel(t, n, "t")?;
    check_channel(aux, n, "temperature")?;
    let out: Vec<DwellOutcome> = bounds
        .par_iter()
        .map(|&[a, b]| {
            let mut d = DwellBuild::new(a, b);
            d.push(samples, 0, a, b);
            d.outcome()
        })
        .collect();
    check_outcomes(bounds, &out)?;
    let mut lsb = LsbSampler::new();
    lsb.push(samples, 0);
    Ok(DwellTable {
        bounds: bounds.to_vec(),
        stats: out.iter().map(|o| o.stat).collect(),
        t_mid: t.map(|x| {
            bounds
                .iter()
                .map(|&[a, z]| 0.5 * (x[a] + x[z - 1]))
                .collect()
        }),
        aux_mean: aux.map(|x| {
            bounds
                .iter()
                .map(|&[a, z]| sum_seq(&x[a..z]) / (z - a) as f64)
                .collect()
        }),
        noise_var: None,
        threshold: None,
        lsb: lsb.estimate(),
        dropped: 0,
        vibrating: Vec::new(),
        shorter: None,
    })
}

/// Per-dwell moments of `samples` over `[start, stop)` bounds (parallel over dwells).
pub fn dwell_moments<T: Sample>(
    samples: &ArrayView2<'_, T>,
    bounds: &[[usize; 2]],
) -> Result<Vec<Moments>> {
    Ok(dwell_table(samples, bounds, None, None)?.moments())
}

/// Detect the static intervals of a whole stream and return their statistics.
pub fn detect_table<T: Sample>(
    samples: &ArrayView2<'_, T>,
    settings: DetectorSettings,
    t: Option<&[f64]>,
    aux: Option<&[f64]>,
) -> Result<DwellTable> {
    check_samples(samples)?;
    let mut acc = DwellAccumulator::with_detector(settings)?;
    acc.push(samples, t, aux)?;
    acc.finish()
}

// ---- streaming -----------------------------------------------------------------------------

/// Streaming accumulator of per-dwell statistics.
#[derive(Debug, Clone, PartialEq)]
pub enum DwellAccumulator {
    /// Known `[start, stop)` bounds.
    Bounds(Box<BoundsAcc>),
    /// Automatic detection at `finish`.
    Detect(Box<DetectAcc>),
}

/// Accumulator for known bounds (sorted internally; results in the caller's order).
#[derive(Debug, Clone, PartialEq)]
pub struct BoundsAcc {
    bounds: Vec<[usize; 2]>,
    order: Vec<usize>,
    done: Vec<Option<DwellOutcome>>,
    open: Option<(usize, DwellBuild)>,
    aux_sum: Vec<f64>,
    t_first: Vec<f64>,
    t_last: Vec<f64>,
    first_open: usize,
    pos: usize,
    has_t: Option<bool>,
    has_aux: Option<bool>,
    lsb: LsbSampler,
}

/// Accumulator for detection: per-block statistics only.
#[derive(Debug, Clone, PartialEq)]
pub struct DetectAcc {
    settings: DetectorSettings,
    blocks: Vec<Moments>,
    aux_blocks: Vec<f64>,
    t_blocks: Vec<[f64; 2]>,
    cur: SegmentAcc,
    cur_bad: bool,
    cur_aux: f64,
    cur_t: [f64; 2],
    pos: usize,
    dropped: u64,
    overflow_at: Option<usize>,
    has_t: Option<bool>,
    has_aux: Option<bool>,
    lsb: LsbSampler,
}

/// A channel must be given with every chunk or with none (checked without changing anything).
fn check_presence(flag: Option<bool>, now: bool, what: &str) -> Result<()> {
    match flag {
        Some(f) if f != now => invalid(format!(
            "{what} must be given with every chunk or with none (the first chunk {} it)",
            if f { "had" } else { "did not have" }
        )),
        _ => Ok(()),
    }
}

impl DwellAccumulator {
    /// Accumulate over known bounds.
    pub fn with_bounds(bounds: Vec<[usize; 2]>) -> Result<Self> {
        check_dwell_bounds(&bounds, usize::MAX)?;
        let mut order: Vec<usize> = (0..bounds.len()).collect();
        order.sort_by_key(|&k| bounds[k][0]);
        let k = bounds.len();
        Ok(DwellAccumulator::Bounds(Box::new(BoundsAcc {
            bounds,
            order,
            done: vec![None; k],
            open: None,
            aux_sum: vec![0.0; k],
            t_first: vec![f64::NAN; k],
            t_last: vec![f64::NAN; k],
            first_open: 0,
            pos: 0,
            has_t: None,
            has_aux: None,
            lsb: LsbSampler::new(),
        })))
    }

    /// Accumulate block statistics and detect dwells at `finish`.
    pub fn with_detector(settings: DetectorSettings) -> Result<Self> {
        settings.validate()?;
        Ok(DwellAccumulator::Detect(Box::new(DetectAcc {
            settings,
            blocks: Vec::new(),
            aux_blocks: Vec::new(),
            t_blocks: Vec::new(),
            cur: SegmentAcc::new(),
            cur_bad: false,
            cur_aux: 0.0,
            cur_t: [f64::NAN; 2],
            pos: 0,
            dropped: 0,
            overflow_at: None,
            has_t: None,
            has_aux: None,
            lsb: LsbSampler::new(),
        })))
    }

    /// Samples pushed so far.
    pub fn position(&self) -> usize {
        match self {
            DwellAccumulator::Bounds(b) => b.pos,
            DwellAccumulator::Detect(d) => d.pos,
        }
    }

    /// Push a chunk of samples `(m, 3)` with optional time and auxiliary (temperature) channels.
    ///
    /// Every check runs before anything changes: after an error the accumulator holds exactly
    /// what it held before the call.
    pub fn push<T: Sample>(
        &mut self,
        chunk: &ArrayView2<'_, T>,
        t: Option<&[f64]>,
        aux: Option<&[f64]>,
    ) -> Result<()> {
        if chunk.ncols() != 3 {
            return invalid(format!(
                "chunk must have shape (m, 3); got {} columns",
                chunk.ncols()
            ));
        }
        let m = chunk.nrows();
        check_channel(t, m, "t")?;
        check_channel(aux, m, "temperature")?;
        let (has_t, has_aux) = match self {
            DwellAccumulator::Bounds(s) => (&mut s.has_t, &mut s.has_aux),
            DwellAccumulator::Detect(s) => (&mut s.has_t, &mut s.has_aux),
        };
        check_presence(*has_t, t.is_some(), "t")?;
        check_presence(*has_aux, aux.is_some(), "temperature")?;
        if m == 0 {
            return Ok(());
        }
        if let DwellAccumulator::Detect(s) = self {
            s.reserve(m)?; // the one check that can fail for want of memory
        }
        let (has_t, has_aux) = match self {
            DwellAccumulator::Bounds(s) => (&mut s.has_t, &mut s.has_aux),
            DwellAccumulator::Detect(s) => (&mut s.has_t, &mut s.has_aux),
        };
        *has_t = Some(t.is_some());
        *has_aux = Some(aux.is_some());
        match self {
            DwellAccumulator::Bounds(s) => s.push(chunk, t, aux),
            DwellAccumulator::Detect(s) => s.push(chunk, t, aux),
        }
        Ok(())
    }

    /// The dwell table of everything pushed so far (the accumulator stays usable).
    pub fn finish(&self) -> Result<DwellTable> {
        match self {
            DwellAccumulator::Bounds(s) => s.finish(),
            DwellAccumulator::Detect(s) => s.finish(),
        }
    }
}

impl BoundsAcc {
    fn push<T: Sample>(
        &mut self,
        chunk: &ArrayView2<'_, T>,
        t: Option<&[f64]>,
        aux: Option<&[f64]>,
    ) {
        let (c0, c1) = (self.pos, self.pos + chunk.nrows());
        self.lsb.push(chunk, c0 as u64);
        let mut i = self.first_open;
        while i < self.order.len() {
            let k = self.order[i];
            let [a, b] = self.bounds[k];
            if a >= c1 {
                break;
            }
            let (lo, hi) = (a.max(c0), b.min(c1));
            if lo < hi {
                if !matches!(&self.open, Some((ko, _)) if *ko == k) {
                    self.open = Some((k, DwellBuild::new(a, b)));
                }
                if let Some((_, build)) = self.open.as_mut() {
                    build.push(chunk, c0, lo, hi);
                    if build.is_done() {
                        self.done[k] = Some(build.outcome());
                        self.open = None;
                    }
                }
                if let Some(x) = aux {
                    for v in &x[lo - c0..hi - c0] {
                        self.aux_sum[k] += *v;
                    }
                }
                if let Some(t) = t {
                    if lo == a {
                        self.t_first[k] = t[lo - c0];
                    }
                    if hi == b {
                        self.t_last[k] = t[hi - 1 - c0];
                    }
                }
            }
            if b <= c1 && i == self.first_open {
                self.first_open += 1;
            }
            i += 1;
        }
        self.pos = c1;
    }

    fn finish(&self) -> Result<DwellTable> {
        let mut out = Vec::with_capacity(self.bounds.len());
        for (k, (&[a, b], d)) in self.bounds.iter().zip(&self.done).enumerate() {
            match d {
                Some(o) if b <= self.pos => out.push(*o),
                _ => {
                    return invalid(format!(
                        "dwell {k} [{a}, {b}) out of range: only {} samples were pushed",
                        self.pos
                    ))
                }
            }
        }
        check_outcomes(&self.bounds, &out)?;
        let t_mid = (self.has_t == Some(true)).then(|| {
            self.t_first
                .iter()
                .zip(&self.t_last)
                .map(|(a, b)| 0.5 * (a + b))
                .collect()
        });
        let aux_mean = (self.has_aux == Some(true)).then(|| {
            self.aux_sum
                .iter()
                .zip(&self.bounds)
                .map(|(s, &[a, b])| s / (b - a) as f64)
                .collect()
        });
        Ok(DwellTable {
            bounds: self.bounds.clone(),
            stats: out.iter().map(|o| o.stat).collect(),
            t_mid,
            aux_mean,
            noise_var: None,
            threshold: None,
            lsb: self.lsb.estimate(),
            dropped: 0,
            vibrating: Vec::new(),
            shorter: None,
        })
    }
}

impl DetectAcc {
    /// Room for the blocks that `m` more samples complete: the block statistics grow with
    /// the length of the stream, and running out of memory for them is an error
    /// ([`CoreError::OutOfMemory`], nothing changed but capacity), not an abort part way
    /// through a push.
    fn reserve(&mut self, m: usize) -> Result<()> {
        let more = (self.cur.count() as usize).saturating_add(m) / self.settings.block_len();
        let what = "the dwell detector's block statistics";
        try_grow(&mut self.blocks, more, what)?;
        try_grow(&mut self.aux_blocks, more, what)?;
        try_grow(&mut self.t_blocks, more, what)
    }

    fn push<T: Sample>(
        &mut self,
        chunk: &ArrayView2<'_, T>,
        t: Option<&[f64]>,
        aux: Option<&[f64]>,
    ) {
        let bl = self.settings.block_len();
        let m = chunk.nrows();
        self.lsb.push(chunk, self.pos as u64);
        let mut i = 0;
        while i < m {
            let in_block = self.cur.count() as usize;
            let take = (bl - in_block).min(m - i);
            if in_block == 0 {
                if let Some(t) = t {
                    self.cur_t[0] = t[i];
                }
            }
            self.cur.push_view(chunk, i, i + take);
            if !self.cur.is_finite() {
                let (n, _) = count_bad(chunk, i, i + take);
                self.dropped += n;
                self.cur_bad |= n > 0;
            }
            if let Some(x) = aux {
                for v in &x[i..i + take] {
                    self.cur_aux += *v;
                }
            }
            if let Some(t) = t {
                self.cur_t[1] = t[i + take - 1];
            }
            i += take;
            if self.cur.count() as usize == bl {
                let mo = self.cur.moments();
                if !mo.is_finite() && !self.cur_bad && self.overflow_at.is_none() {
                    self.overflow_at = Some(self.blocks.len() * bl);
                }
                self.blocks.push(mo); // within the room `reserve` made
                self.aux_blocks.push(self.cur_aux);
                self.t_blocks.push(self.cur_t);
                self.cur = SegmentAcc::new();
                self.cur_bad = false;
                self.cur_aux = 0.0;
                self.cur_t = [f64::NAN; 2];
            }
        }
        self.pos += m;
    }

    fn finish(&self) -> Result<DwellTable> {
        if self.pos == 0 {
            return invalid("no samples were pushed");
        }
        if let Some(p) = self.overflow_at {
            return invalid(format!(
                "samples near sample {p} are too large to square in float64 (NaN or inf \
                 variance): rescale them"
            ));
        }
        let det = detect_from_blocks(&self.blocks, &self.settings, self.pos, self.lsb.estimate())?;
        let bl = self.settings.block_len();
        let t_mid = (self.has_t == Some(true)).then(|| {
            det.bounds
                .iter()
                .map(|&[a, b]| 0.5 * (self.t_blocks[a / bl][0] + self.t_blocks[b / bl - 1][1]))
                .collect()
        });
        let aux_mean = (self.has_aux == Some(true)).then(|| {
            det.bounds
                .iter()
                .map(|&[a, b]| sum_seq(&self.aux_blocks[a / bl..b / bl]) / (b - a) as f64)
                .collect()
        });
        Ok(DwellTable {
            bounds: det.bounds,
            stats: det.stats,
            t_mid,
            aux_mean,
            noise_var: Some(det.noise_var),
            threshold: Some(det.threshold),
            lsb: self.lsb.estimate(),
            dropped: self.dropped,
            vibrating: det.vibrating,
            shorter: det.shorter,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::CoreError;
    use ndarray::Array2;

    use crate::test_rng::unit as lcg;

    fn gauss(seed: &mut u64) -> f64 {
        let (u, v) = (lcg(seed).max(1e-300), lcg(seed));
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    #[test]
    fn rates_in_messages_have_six_significant_digits() {
        assert_eq!(hz(19.11915329463981), "19.1192");
        assert_eq!(hz(100.0), "100");
        assert_eq!(hz(100.0098419526434), "100.01");
        assert_eq!(hz(0.019130936), "0.0191309");
        assert_eq!(hz(125_000.0), "125000");
        assert_eq!(hz(f64::NAN), "NaN");
    }

    fn two_pass(x: &Array2<f64>, a: usize, b: usize) -> ([f64; 3], [f64; 3], [f64; 3]) {
        let mut mean = [0.0; 3];
        let mut var = [0.0; 3];
        let mut d2 = [0.0; 3];
        for ax in 0..3 {
            let col: Vec<f64> = (a..b).map(|i| x[[i, ax]]).collect();
            let m = col.iter().sum::<f64>() / col.len() as f64;
            let v = col.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (col.len() - 1) as f64;
            mean[ax] = m;
            var[ax] = v;
            d2[ax] = col.windows(2).map(|w| (w[1] - w[0]) * (w[1] - w[0])).sum();
        }
        (mean, var, d2)
    }

    /// Run `f` with the dispatchers limited to kernel family `cap` on this thread.
    fn with_cap<R>(cap: u8, f: impl FnOnce() -> R) -> R {
        let old = KERNEL_CAP.with(|c| c.replace(cap));
        let r = f();
        KERNEL_CAP.with(|c| c.set(old));
        r
    }

    /// Random int16 rows in one of several regimes: small noise about an offset (the 16-bit
    /// vector paths), the same with rare full-scale spikes or steps (their range fallback),
    /// or uniform over the whole int16 range.
    fn i16_values(seed: &mut u64, n: usize, regime: usize) -> Vec<i16> {
        let off = (lcg(seed) * 60000.0 - 30000.0) as i32;
        let step = 4096 + (lcg(seed) * 8.0) as i32 - 4;
        (0..n)
            .map(|i| {
                let u = lcg(seed);
                let v = match regime {
                    0 => off + (gauss(seed) * 20.0) as i32,
                    1 if u < 0.002 => i32::from(if u < 0.001 { i16::MIN } else { i16::MAX }),
                    1 => off + (gauss(seed) * 20.0) as i32,
                    2 => off + (gauss(seed) * 3.0) as i32 + if i > n / 2 { step } else { 0 },
                    _ => (u * 65536.0) as i32 - 32768,
                };
                v.clamp(-32768, 32767) as i16
            })
            .collect()
    }

    fn lanes_from(seed: &mut u64, integer: bool) -> Lanes {
        let mut v = |_| {
            let x = gauss(seed) * 1e3;
            if integer {
                x.round()
            } else {
                x
            }
        };
        Lanes {
            s1: std::array::from_fn(&mut v),
            s2: std::array::from_fn(&mut v),
            d2: std::array::from_fn(&mut v),
        }
    }

    /// The explicit x86-64 kernels give bit-identical sums to the portable loops, called
    /// directly on the same pieces (lengths around every vector, sub-piece and block edge).
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn simd_kernels_equal_portable_kernels() {
        let has = |f: &str| match f {
            "avx2" => std::is_x86_feature_detected!("avx2"),
            "fma" => std::is_x86_feature_detected!("fma"),
            _ => {
                std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx512bw")
                    && std::is_x86_feature_detected!("avx512vnni")
            }
        };
        if !has("avx2") {
            // Nothing but the portable path can run on this CPU (covered by the other tests).
            return;
        }
        let mut seed = 41u64;
        let mut groups: Vec<usize> = (1..=12).collect();
        groups.extend([
            39, 40, 41, 79, 80, 81, 159, 160, 161, 319, 320, 321, 1023, 1024,
        ]);
        for &g in &groups {
            let n = g * W;
            for regime in 0..4 {
                let x = i16_values(&mut seed, n, regime);
                let shift = |s: &mut u64| f64::from(x[(lcg(s) * n as f64) as usize % n]);
                let sh0 = [shift(&mut seed), shift(&mut seed), shift(&mut seed)];
                let sh: [f64; W] = std::array::from_fn(|j| sh0[j % 3]);
                let prev = [shift(&mut seed), shift(&mut seed), shift(&mut seed)];
                let l0 = lanes_from(&mut seed, true);
                let mut want = l0;
                accumulate_i16(&x, &prev, &sh, &mut want);
                let mut got = l0;
                // SAFETY: AVX2 checked above; `prev` and `sh` are int16 values.
                unsafe { simd::i16_avx2(&x, &prev, &sh, &mut got) };
                same(&got, &want);
                if has("avx512") {
                    let mut got = l0;
                    // SAFETY: AVX-512 F, BW and VNNI checked just above; int16 `prev`, `sh`.
                    unsafe { simd::i16_avx512(&x, &prev, &sh, &mut got) };
                    same(&got, &want);
                }
                // The float kernel on the same values (as int16, and widened to f64 with a
                // non-integer shift), NaN and inf included in the last regime.
                let mut xf: Vec<f64> = x.iter().map(|&v| f64::from(v) * 1.25e-3).collect();
                if regime == 3 {
                    xf[n / 3] = f64::NAN;
                    xf[n / 2] = f64::INFINITY;
                }
                let shf: [f64; W] = std::array::from_fn(|j| sh[j] * 1.25e-3 + 0.1);
                let lf = lanes_from(&mut seed, false);
                if has("fma") {
                    let mut want = lf;
                    accumulate_groups(&xf, &prev, &shf, &mut want);
                    let mut got = lf;
                    // SAFETY: AVX2 and FMA checked above.
                    unsafe { simd::groups_fma(&xf, &prev, &shf, &mut got) };
                    same(&got, &want);
                    let mut want = lf;
                    accumulate_groups(&x, &prev, &shf, &mut want);
                    let mut got = lf;
                    // SAFETY: AVX2 and FMA checked above.
                    unsafe { simd::groups_fma(&x, &prev, &shf, &mut got) };
                    same(&got, &want);
                    let x32: Vec<f32> = xf.iter().map(|&v| v as f32).collect();
                    let mut want = lf;
                    accumulate_groups(&x32, &prev, &shf, &mut want);
                    let mut got = lf;
                    // SAFETY: AVX2 and FMA checked above.
                    unsafe { simd::groups_fma(&x32, &prev, &shf, &mut got) };
                    same(&got, &want);
                    let xi: Vec<i32> = x.iter().map(|&v| i32::from(v) * 70_001).collect();
                    let mut want = lf;
                    accumulate_groups(&xi, &prev, &shf, &mut want);
                    let mut got = lf;
                    // SAFETY: AVX2 and FMA checked above.
                    unsafe { simd::groups_fma(&xi, &prev, &shf, &mut got) };
                    same(&got, &want);
                }
            }
        }
    }

    /// The whole dwell pass (sub-blocks, half means, inflation, LSB) is bit-identical with
    /// every kernel family, for int16 and float64 input.
    #[test]
    fn dwell_pass_is_identical_with_every_kernel() {
        let mut seed = 43u64;
        let n = 50_000;
        for regime in 0..4 {
            let v = i16_values(&mut seed, 3 * n, regime);
            let x = Array2::from_shape_vec((n, 3), v).unwrap();
            let xf = x.mapv(|v| 9.8 + f64::from(v) * 1e-4);
            let bounds = [[0, 7], [10, 20_011], [20_011, 49_999]];
            let want = with_cap(0, || {
                let mut acc = DwellAccumulator::with_bounds(bounds.to_vec()).unwrap();
                push_chunked(&mut acc, &x, 1);
                let mut accf = DwellAccumulator::with_bounds(bounds.to_vec()).unwrap();
                push_chunked(&mut accf, &xf, 1);
                (acc.finish().unwrap(), accf.finish().unwrap())
            });
            for cap in 1..=2 {
                let got = with_cap(cap, || {
                    let mut acc = DwellAccumulator::with_bounds(bounds.to_vec()).unwrap();
                    push_chunked(&mut acc, &x, 4000);
                    let mut accf = DwellAccumulator::with_bounds(bounds.to_vec()).unwrap();
                    push_chunked(&mut accf, &xf, 4000);
                    (acc.finish().unwrap(), accf.finish().unwrap())
                });
                same(&got, &want);
            }
        }
    }

    /// Bitwise equality (NaN fields included) through the exact `Debug` representation.
    fn same<A: std::fmt::Debug, B: std::fmt::Debug>(a: &A, b: &B) {
        assert_eq!(format!("{a:?}"), format!("{b:?}"));
    }

    fn push_chunked<T: Sample>(acc: &mut DwellAccumulator, x: &Array2<T>, mut step: usize) {
        let n = x.nrows();
        let mut pos = 0;
        while pos < n {
            let e = (pos + step).min(n);
            acc.push(&x.slice(ndarray::s![pos..e, ..]), None, None)
                .unwrap();
            pos = e;
            step = (step * 7 + 3) % 5003 + 1;
        }
    }

    #[test]
    fn counts_with_large_offset_match_two_pass() {
        let mut s = 7u64;
        let n = 20_000;
        let x = Array2::from_shape_fn((n, 3), |_| 33000.0 + (3.0 * lcg(&mut s) * 3.0).round());
        let bounds = vec![[0, 5000], [5000, 13_001], [13_001, 20_000]];
        let t = dwell_table(&x.view(), &bounds, None, None).unwrap();
        for (k, &[a, b]) in bounds.iter().enumerate() {
            let (mean, var, d2) = two_pass(&x, a, b);
            let m = t.stats[k].moments;
            for ax in 0..3 {
                assert!((m.mean[ax] - mean[ax]).abs() <= 1e-12 * mean[ax].abs());
                assert!((m.var()[ax] - var[ax]).abs() <= 1e-9 * var[ax]);
                assert!((m.d2[ax] - d2[ax]).abs() <= 1e-12 * d2[ax]);
            }
            // Half-dwell means split at floor(L / 2).
            let h = a + (b - a) / 2;
            let (m0, _, _) = two_pass(&x, a, h);
            let (m1, _, _) = two_pass(&x, h, b);
            for ax in 0..3 {
                assert!((t.stats[k].half_mean[0][ax] - m0[ax]).abs() <= 1e-12 * m0[ax]);
                assert!((t.stats[k].half_mean[1][ax] - m1[ax]).abs() <= 1e-12 * m1[ax]);
            }
        }
        assert_eq!(t.lsb, Some([1.0; 3]));
    }

    #[test]
    fn streaming_equals_one_shot_bitwise() {
        let mut s = 3u64;
        let n = 30_011;
        let x = Array2::from_shape_fn((n, 3), |_| 1e4 + lcg(&mut s));
        let bounds = vec![
            [10, 9000],
            [9000, 9001 + 8000],
            [20_000, 30_011],
            [17_050, 17_090],
        ];
        let one = dwell_table(&x.view(), &bounds, None, None).unwrap();
        for first in [1, 2, 5, 4096, 30_011] {
            let mut acc = DwellAccumulator::with_bounds(bounds.clone()).unwrap();
            push_chunked(&mut acc, &x, first);
            same(&acc.finish().unwrap(), &one);
            let mut det = DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap();
            let mut whole = DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap();
            push_chunked(&mut det, &x, first);
            whole.push(&x.view(), None, None).unwrap();
            same(&det, &whole);
        }
    }

    #[test]
    fn strided_view_equals_contiguous() {
        let mut s = 11u64;
        let x = Array2::from_shape_fn((1000, 6), |_| lcg(&mut s));
        let strided = x.slice(ndarray::s![.., 0..6;2]);
        let copy = strided.to_owned();
        let a = dwell_table(&strided, &[[0, 1000]], None, None).unwrap();
        let b = dwell_table(&copy.view(), &[[0, 1000]], None, None).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn bad_bounds_and_nan_are_errors() {
        let x = Array2::<f64>::zeros((100, 3));
        assert!(dwell_moments(&x.view(), &[[0, 101]]).is_err());
        assert!(dwell_moments(&x.view(), &[[5, 5]]).is_err());
        assert!(dwell_moments(&x.view(), &[[5, 6]]).is_err());
        assert!(dwell_moments(&x.view(), &[[0, 50], [40, 60]]).is_err());
        let mut y = x.clone();
        y[[10, 1]] = f64::NAN;
        y[[12, 0]] = f64::INFINITY;
        let e = dwell_moments(&y.view(), &[[0, 50]]).unwrap_err();
        assert!(e.to_string().contains("NaN"), "{e}");
        assert!(
            e.to_string().contains("2 row(s), the first at sample 10"),
            "{e}"
        );
        // Outside every dwell it does not matter.
        assert!(dwell_moments(&y.view(), &[[20, 50]]).is_ok());
        let bad = Array2::<f64>::zeros((10, 2));
        assert!(dwell_moments(&bad.view(), &[[0, 5]]).is_err());
    }

    #[test]
    fn int16_fast_path_is_bit_identical_to_row_path() {
        let mut s = 19u64;
        // Extreme counts: deviations up to 65535 from the block's first sample.
        let x = Array2::from_shape_fn((10_007, 3), |(i, a)| {
            let u = lcg(&mut s);
            if (i + a) % 97 == 0 {
                if u < 0.5 {
                    i16::MIN
                } else {
                    i16::MAX
                }
            } else {
                (-32000.0 + 20.0 * u) as i16
            }
        });
        let mut slow = SegmentAcc::new();
        for r in x.rows() {
            slow.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
        }
        // Every kernel family: portable, AVX2, AVX-512 (where the CPU has them).
        for cap in 0..=2 {
            let mut fast = SegmentAcc::new();
            with_cap(cap, || fast.push_slice(x.as_slice().unwrap()));
            assert_eq!(fast.moments(), slow.moments(), "kernel cap {cap}");
        }
        let mut fast = SegmentAcc::new();
        fast.push_slice(x.as_slice().unwrap());
        let xf = x.mapv(f64::from);
        let (mean, var, d2) = two_pass(&xf, 0, 10_007);
        let m = fast.moments();
        for ax in 0..3 {
            assert!((m.mean[ax] - mean[ax]).abs() <= 1e-12 * mean[ax].abs());
            assert!((m.var()[ax] - var[ax]).abs() <= 1e-12 * var[ax]);
            assert_eq!(m.d2[ax], d2[ax]);
        }
        // A float chunk before int16 ones (non-integer shift and previous row) stays exact.
        let mut mixed = SegmentAcc::new();
        mixed.push_row([0.5, -0.25, 3.75]);
        mixed.push_slice(x.as_slice().unwrap());
        let mut rows = SegmentAcc::new();
        rows.push_row([0.5, -0.25, 3.75]);
        for r in x.rows() {
            rows.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
        }
        assert_eq!(mixed.moments(), rows.moments());
    }

    #[test]
    fn f64_fast_path_is_bit_identical_to_row_path() {
        let mut s = 23u64;
        let x = Array2::from_shape_fn((9_001, 3), |_| 9.8 + gauss(&mut s));
        let mut slow = SegmentAcc::new();
        for r in x.rows() {
            slow.push_row([r[0], r[1], r[2]]);
        }
        for cap in 0..=2 {
            for cut in [0, 1, 3, 4, 7, 4096] {
                let mut fast = SegmentAcc::new();
                let flat = x.as_slice().unwrap();
                with_cap(cap, || {
                    fast.push_slice(&flat[..3 * cut]);
                    fast.push_slice(&flat[3 * cut..]);
                });
                assert_eq!(
                    fast.moments(),
                    slow.moments(),
                    "kernel cap {cap}, cut {cut}"
                );
            }
        }
    }

    #[test]
    fn overflow_is_an_error_not_zero_variance() {
        let x = Array2::from_shape_fn((100, 3), |(i, _)| if i % 2 == 0 { -1e300 } else { 1e300 });
        let e = dwell_moments(&x.view(), &[[0, 100]]).unwrap_err();
        assert!(e.to_string().contains("too large"));
    }

    fn piecewise(seed: u64, levels: &[f64], noise: f64) -> Array2<f64> {
        // Dwells of 5 s at 100 Hz separated by 2 s ramps.
        let mut s = seed;
        let mut rows = Vec::new();
        for (i, &l) in levels.iter().enumerate() {
            for _ in 0..500 {
                rows.push([
                    l + noise * lcg(&mut s),
                    noise * lcg(&mut s),
                    9.8 + noise * lcg(&mut s),
                ]);
            }
            if i + 1 < levels.len() {
                for j in 0..200 {
                    let f = j as f64 / 200.0;
                    let v = l + f * (levels[i + 1] - l);
                    rows.push([v, 0.3 * (f * std::f64::consts::TAU).sin(), 9.8]);
                }
            }
        }
        Array2::from_shape_fn((rows.len(), 3), |(i, a)| rows[i][a])
    }

    /// Rests of `rest` samples (noise 0.01) at 12 levels, separated by 100-sample ramps
    /// (the ramp's middle wiggles, its ends are slow: a smoothstep).
    fn brief_rests(seed: u64, rest: usize) -> Array2<f64> {
        let mut s = seed;
        let mut rows = Vec::new();
        let levels: Vec<f64> = (0..12).map(|i| (i as f64 * 0.7).sin() * 3.0).collect();
        for (i, &l) in levels.iter().enumerate() {
            for _ in 0..rest {
                rows.push([l + 0.01 * lcg(&mut s), 0.01 * lcg(&mut s), 9.8]);
            }
            if i + 1 < levels.len() {
                for j in 0..100 {
                    let f = j as f64 / 100.0;
                    let e = f * f * (3.0 - 2.0 * f);
                    rows.push([l + e * (levels[i + 1] - l), 0.0, 9.8]);
                }
            }
        }
        Array2::from_shape_fn((rows.len(), 3), |(i, a)| rows[i][a] + 0.01 * lcg(&mut s))
    }

    #[test]
    fn brief_rests_get_shorter_settings_that_find_them() {
        // 0.8 s rests at 100 Hz: the defaults need 2.2 s and find none; the error names the
        // settings that find all 12, which then do.
        let x = brief_rests(3, 80);
        let e = detect_table(&x.view(), DetectorSettings::new(100.0), None, None).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("2.200 s here"), "{msg}");
        assert!(
            msg.contains(
                "window_s = 0.25 s with min_dwell_s = 0.125 s and trim_s = 0.0625 s, \
                          find 12 steady dwell(s)"
            ),
            "{msg}"
        );
        let mut st = DetectorSettings::new(100.0);
        (st.window_s, st.min_dwell_s, st.trim_s) = (0.25, 0.125, 0.0625);
        let t = detect_table(&x.view(), st, None, None).unwrap();
        assert_eq!(t.bounds.len(), 12);
        assert_eq!(t.shorter, None); // 12 found: nothing to suggest
                                     // Rests long enough for the defaults: no probe.
        let t = detect_table(
            &brief_rests(3, 400).view(),
            DetectorSettings::new(100.0),
            None,
            None,
        )
        .unwrap();
        assert_eq!((t.bounds.len(), t.shorter), (12, None));
    }

    #[test]
    fn the_shorter_windows_respect_the_fewest_samples_and_the_settings_given() {
        let w = |fs: f64, window: f64| {
            let mut s = DetectorSettings::new(fs);
            s.window_s = window;
            shorter_settings(&s)
                .iter()
                .map(|c| (c.window_s, c.min_dwell_s, c.trim_s))
                .collect::<Vec<_>>()
        };
        assert_eq!(
            w(100.0, 1.0),
            vec![(0.5, 0.25, 0.1), (0.25, 0.125, 0.0625), (0.1, 0.05, 0.025)]
        );
        // 19 Hz: no window under 8 samples (0.43 s at two decimals).
        assert_eq!(w(19.0, 1.0), vec![(0.5, 0.25, 0.1), (0.43, 0.215, 0.1)]);
        assert_eq!(
            w(100.0, 0.3),
            vec![(0.25, 0.125, 0.0625), (0.1, 0.05, 0.025)]
        );
        assert!(w(100.0, 0.1).is_empty());
        // A steady dwell: its halves agree within 4 standard errors; a creeping one does not.
        let half = |d: f64| DwellStat {
            moments: Moments {
                n: 100,
                m2: [99.0 * 1e-4; 3], // the noise's own variance
                ..Moments::EMPTY
            },
            half_mean: [[0.0; 3], [d, 0.0, 0.0]],
            inflation: [1.0; 3],
        };
        let v = [1e-4; 3]; // std 0.01: a half mean's SE is 0.01 / sqrt(50)
        assert!(steady(&half(0.005), &v));
        assert!(!steady(&half(0.02), &v));
    }

    #[test]
    fn detector_finds_simulated_dwells() {
        let levels = [0.0, 1.0, -1.0, 2.0, 0.5];
        let x = piecewise(5, &levels, 0.01);
        let mut acc = DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap();
        acc.push(&x.view(), None, None).unwrap();
        let t = acc.finish().unwrap();
        assert_eq!(t.bounds.len(), 5);
        for (m, &l) in t.moments().iter().zip(&levels) {
            assert!((m.mean[0] - (l + 0.005)).abs() < 0.002);
        }
        assert_eq!(t.dropped, 0);
        assert_eq!(t.lsb, None);
    }

    /// Integer counts whose white noise is well below one step: windows inside one output
    /// code have no variance at all, yet every rest is found (the noise floored at the
    /// rounding's lsb^2 / 12). Before: 1 of 5 rests, or a refusal (zero noise).
    #[test]
    fn rests_of_noise_below_one_output_step_are_found() {
        let levels = [0.3, 1000.5, -1000.1, 2000.45, 500.0, -300.52];
        for sd in [0.08, 0.15, 0.2] {
            let mut s = 5u64;
            // Sum of 12 uniforms on [0, 1), centred: about normal, unit variance.
            let mut gauss = || (0..12).map(|_| lcg(&mut s)).sum::<f64>() - 6.0;
            let mut rows: Vec<[i16; 3]> = Vec::new();
            for (i, &l) in levels.iter().enumerate() {
                for _ in 0..500 {
                    let r = [
                        l + sd * gauss(),
                        200.25 + sd * gauss(),
                        16384.5 + sd * gauss(),
                    ];
                    rows.push(r.map(|v| v.round() as i16));
                }
                if i + 1 < levels.len() {
                    for j in 0..200 {
                        let f = j as f64 / 200.0;
                        let v = l + f * (levels[i + 1] - l);
                        let w = 200.0 + 300.0 * (f * std::f64::consts::TAU).sin();
                        rows.push([v.round() as i16, w.round() as i16, 16384]);
                    }
                }
            }
            let x = Array2::from_shape_fn((rows.len(), 3), |(i, a)| rows[i][a]);
            let mut acc = DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap();
            acc.push(&x.view(), None, None).unwrap();
            let t = acc.finish().unwrap();
            assert_eq!(t.lsb, Some([1.0; 3]));
            assert_eq!(
                t.bounds.len(),
                levels.len(),
                "noise {sd} LSB: {:?}",
                t.bounds
            );
            for (m, &l) in t.moments().iter().zip(&levels) {
                // Within half a step: below one step of noise a dwell mean is biased towards
                // its nearest code (the quantisation verdict of the gap diagnosis).
                assert!((m.mean[0] - l).abs() <= 0.5, "{} {l}", m.mean[0]);
            }
        }
    }

    /// The noise level of a session that moves most of the time comes from its stillest
    /// windows; a static session keeps the plain quantile.
    #[test]
    fn a_session_mostly_in_motion_takes_its_noise_from_the_still_windows() {
        let mut seed = 11u64;
        // 100-sample windows: static ones scatter as chi2(99)/99 about 1.
        let mut still = |_| {
            let mut v: f64 = 0.0;
            for _ in 0..99 {
                // Box-Muller from the tests' uniform numbers.
                let (u1, u2) = (
                    crate::test_rng::unit(&mut seed).max(1e-300),
                    crate::test_rng::unit(&mut seed),
                );
                let z = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
                v += z * z;
            }
            v / 99.0
        };
        let stat: Vec<f64> = (0..1000).map(&mut still).collect();
        let mut a = stat.clone();
        let plain = quantile_of(&mut a.clone(), 0.2);
        assert_eq!(noise_level(&mut a, 0.2, 100), plain);
        // 12 % still, the rest moving with variances 50-500 times the noise.
        let mut mixed: Vec<f64> = stat[..120].to_vec();
        mixed.extend((0..880).map(|i| 50.0 + 0.5 * i as f64));
        let q20 = quantile_of(&mut mixed.clone(), 0.2);
        assert!(q20 > 40.0);
        let v = noise_level(&mut mixed, 0.2, 100);
        assert!((v / plain - 1.0).abs() < 0.05, "{v} against {plain}");
    }

    #[test]
    fn a_vibrating_pose_is_reported_not_taken() {
        let levels = [0.0, 1.0, -1.0, 2.0, 0.5];
        let mut x = piecewise(5, &levels, 0.01);
        // The fourth pose (samples 2100..2600) vibrates at 30 Hz, 6 times the noise std.
        for i in 2100..2600 {
            let v = 0.06 * (std::f64::consts::TAU * 30.0 * i as f64 / 100.0 + 0.3).sin();
            x[[i, 0]] += v;
            x[[i, 2]] -= 0.5 * v;
        }
        let t = detect_table(&x.view(), DetectorSettings::new(100.0), None, None).unwrap();
        assert_eq!(t.bounds.len(), 4);
        assert!(t.bounds.iter().all(|&[a, b]| b <= 2100 || a >= 2600));
        assert_eq!(t.vibrating.len(), 1, "{:?}", t.vibrating);
        let v = t.vibrating[0];
        assert!(v.bounds[0] >= 2100 && v.bounds[1] <= 2600 && v.bounds[1] - v.bounds[0] >= 300);
        assert!(v.std[0] > 0.03 && v.std[1] < 0.01, "{:?}", v.std);
        // The ramps between poses move the mean: none of them is reported.
        let clean = piecewise(5, &levels, 0.01);
        let c = detect_table(&clean.view(), DetectorSettings::new(100.0), None, None).unwrap();
        assert!(c.vibrating.is_empty(), "{:?}", c.vibrating);
    }

    #[test]
    fn detector_treats_nan_as_dropout_and_counts_it() {
        let levels = [0.0, 1.0, -1.0];
        let mut x = piecewise(5, &levels, 0.01);
        // Three bad rows in the middle of the second dwell (samples 700..1200).
        for i in [950, 951, 960] {
            x[[i, 1]] = f64::NAN;
        }
        let t = detect_table(&x.view(), DetectorSettings::new(100.0), None, None).unwrap();
        assert_eq!(t.dropped, 3);
        for &[a, b] in &t.bounds {
            assert!(b <= 950 || a > 960, "dwell [{a}, {b}) holds a NaN");
        }
        assert!(t.stats.iter().all(|s| s.moments.is_finite()));
        // Whole-stream NaN: no window to estimate the noise from.
        let y = Array2::from_elem((1000, 3), f64::NAN);
        let e = detect_table(&y.view(), DetectorSettings::new(100.0), None, None).unwrap_err();
        assert!(e.to_string().contains("NaN"), "{e}");
    }

    #[test]
    fn a_static_stream_too_short_is_told_its_length_not_to_raise_k() {
        // At rest throughout: 2.5 s is one dwell, without the stream's first and last half
        // window (start-up transients) and the trims.
        let mut s = 3u64;
        let y = Array2::from_shape_fn((250, 3), |(_, a)| [0.0, 0.0, 9.8][a] + 0.01 * lcg(&mut s));
        let st = DetectorSettings::new(100.0);
        let t = detect_table(&y.view(), st, None, None).unwrap();
        assert_eq!(t.bounds, vec![[60, 192]]);
        // 1.5 s: too short. The error gives the length needed, not "raise k" (it used to).
        let e = detect_table(
            &y.slice(ndarray::s![..150, ..]),
            DetectorSettings::new(100.0),
            None,
            None,
        )
        .unwrap_err();
        assert!(matches!(e, CoreError::Degenerate(_)));
        let m = e.to_string();
        assert!(m.contains("whole stream is static but too short"), "{m}");
        assert!(
            m.contains("about 2.20 s in all") && !m.contains("raise k"),
            "{m}"
        );
    }

    #[test]
    fn no_dwell_found_says_so() {
        let mut s = 1u64;
        // A steady ramp: nothing is static.
        let x = Array2::from_shape_fn((3000, 3), |(i, _)| i as f64 * 0.1 + 0.001 * lcg(&mut s));
        let mut st = DetectorSettings::new(100.0);
        st.noise_var = Some([1e-8; 3]);
        let e = detect_table(&x.view(), st, None, None).unwrap_err();
        assert!(matches!(e, CoreError::Degenerate(_)));
        assert!(e.to_string().contains("no static dwell found"), "{e}");
    }

    #[test]
    fn huge_settings_are_errors_not_panics() {
        let x = Array2::<f64>::zeros((100, 3));
        for w in [4e38, 3.7e17, 1e7, f64::INFINITY, f64::NAN, -1.0, 0.0] {
            let mut st = DetectorSettings::new(100.0);
            st.window_s = w;
            let e = detect_table(&x.view(), st, None, None).unwrap_err();
            assert!(e.to_string().contains("window_s"), "{e}");
        }
        for fs in [4e38, 1.0, 0.0, f64::NAN] {
            let e = detect_table(&x.view(), DetectorSettings::new(fs), None, None).unwrap_err();
            assert!(e.to_string().contains("fs"), "{e}");
        }
        let mut st = DetectorSettings::new(100.0);
        st.min_dwell_s = 1e6;
        st.trim_s = 1e6;
        let y = piecewise(5, &[0.0, 1.0], 0.01);
        assert!(detect_table(&y.view(), st, None, None).is_err());
    }

    fn white_plus_walk(seed: u64, n: usize, walk: f64) -> Array2<f64> {
        let mut s = seed;
        let mut w = [0.0; 3];
        Array2::from_shape_fn((n, 3), |(_, a)| {
            w[a] += walk * gauss(&mut s);
            9.8 + w[a] + gauss(&mut s)
        })
    }

    /// The sample-stride reference: overlapping ADEV at 1, L/16 and L/4 from cumulative sums.
    fn inflation_reference(x: &Array2<f64>) -> [f64; 3] {
        let l = x.nrows();
        let mut out = [0.0; 3];
        for (a, o) in out.iter_mut().enumerate() {
            let mut c = vec![0.0];
            for i in 0..l {
                c.push(c[i] + x[[i, a]] - 9.8);
            }
            let avar = |m: usize| -> f64 {
                let n = l - 2 * m + 1;
                (0..n)
                    .map(|i| {
                        let d = (c[i + 2 * m] - 2.0 * c[i + m] + c[i]) / m as f64;
                        d * d
                    })
                    .sum::<f64>()
                    / (2.0 * n as f64)
            };
            let (m16, m4) = (l / 16, l / 4);
            let a1 = avar(1);
            let r16 = (avar(m16) * m16 as f64 / a1).sqrt();
            let r4 = (avar(m4) * m4 as f64 / a1).sqrt();
            let slope = ((r4 / r16).ln() / (m4 as f64 / m16 as f64).ln()).clamp(0.0, 1.0);
            *o = r4 * (l as f64 / m4 as f64).powf(slope);
        }
        out
    }

    #[test]
    fn inflation_tracks_the_sample_stride_reference() {
        // Median over dwells of the ratio to the reference, for white and correlated noise.
        for (walk, lo, hi) in [(0.0, 0.7, 1.5), (0.005, 3.0, 40.0)] {
            let mut ratios = Vec::new();
            let mut ours = Vec::new();
            for seed in 0..24 {
                let x = white_plus_walk(seed, 4096, walk);
                let t = dwell_table(&x.view(), &[[0, 4096]], None, None).unwrap();
                let r = inflation_reference(&x);
                for (f, fr) in t.stats[0].inflation.iter().zip(&r) {
                    ratios.push(f / fr);
                    ours.push(*f);
                }
            }
            ratios.sort_by(f64::total_cmp);
            ours.sort_by(f64::total_cmp);
            let med = ratios[ratios.len() / 2];
            assert!((med - 1.0).abs() < 0.1, "walk {walk}: median ratio {med}");
            let m = ours[ours.len() / 2];
            assert!(m > lo && m < hi, "walk {walk}: median inflation {m}");
        }
        // Too short: NaN.
        let x = white_plus_walk(1, 63, 0.0);
        let t = dwell_table(&x.view(), &[[0, 63]], None, None).unwrap();
        assert!(t.stats[0].inflation.iter().all(|v| v.is_nan()));
    }

    #[test]
    fn lsb_of_integer_quantised_and_continuous_streams() {
        let mut s = 2u64;
        let q = 0.000_598_5;
        let counts = Array2::from_shape_fn((50_000, 3), |_| (3.0 * gauss(&mut s)).round());
        let scaled = counts.mapv(|c| 100.0 * q + c * q);
        let ints = counts.mapv(|c| c as i32 * 4);
        let cont = Array2::from_shape_fn((50_000, 3), |_| gauss(&mut s));
        let b = [[0, 50_000]];
        let l = dwell_table(&scaled.view(), &b, None, None)
            .unwrap()
            .lsb
            .unwrap();
        assert!(l.iter().all(|v| (v / q - 1.0).abs() < 1e-9), "{l:?}");
        let l = dwell_table(&ints.view(), &b, None, None).unwrap().lsb;
        assert_eq!(l, Some([4.0; 3]));
        assert_eq!(dwell_table(&cont.view(), &b, None, None).unwrap().lsb, None);
        // Chunking-independent subsample.
        let mut acc = DwellAccumulator::with_bounds(b.to_vec()).unwrap();
        push_chunked(&mut acc, &scaled, 3);
        same(
            &acc.finish().unwrap(),
            &dwell_table(&scaled.view(), &b, None, None).unwrap(),
        );
    }

    #[test]
    fn failed_push_changes_nothing() {
        let x = piecewise(5, &[0.0, 1.0], 0.01);
        let t: Vec<f64> = (0..x.nrows()).map(|i| i as f64 / 100.0).collect();
        for mut acc in [
            DwellAccumulator::with_bounds(vec![[0, 400], [800, 1100]]).unwrap(),
            DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap(),
        ] {
            acc.push(&x.slice(ndarray::s![..300, ..]), Some(&t[..300]), None)
                .unwrap();
            let before = acc.clone();
            let mut bad_t = t[300..].to_vec();
            bad_t[5] = f64::NAN;
            assert!(acc
                .push(&x.slice(ndarray::s![300.., ..]), Some(&bad_t), None)
                .is_err());
            assert!(acc
                .push(&x.slice(ndarray::s![300.., ..]), None, None)
                .is_err());
            assert!(acc
                .push(&x.slice(ndarray::s![300.., ..]), Some(&t[..3]), None)
                .is_err());
            same(&acc, &before);
            acc.push(&x.slice(ndarray::s![300.., ..]), Some(&t[300..]), None)
                .unwrap();
            assert!(acc.finish().is_ok());
        }
    }

    #[test]
    fn state_round_trip_resumes_bit_identically() {
        let x = piecewise(9, &[0.0, 1.0, -1.0, 2.0], 0.01);
        let n = x.nrows();
        for mut acc in [
            DwellAccumulator::with_bounds(vec![[0, 400], [700, 1100], [1500, 1900]]).unwrap(),
            DwellAccumulator::with_detector(DetectorSettings::new(100.0)).unwrap(),
        ] {
            let mut whole = acc.clone();
            whole.push(&x.view(), None, None).unwrap();
            for cut in [0, 1, 333, 1001, n] {
                let mut a = acc.clone();
                a.push(&x.slice(ndarray::s![..cut, ..]), None, None)
                    .unwrap();
                let bytes = a.to_state();
                let mut b = DwellAccumulator::from_state(&bytes).unwrap();
                same(&a, &b);
                b.push(&x.slice(ndarray::s![cut.., ..]), None, None)
                    .unwrap();
                same(&b.finish().unwrap(), &whole.finish().unwrap());
                // Corruption is an error, never a panic.
                for k in (0..bytes.len()).step_by(bytes.len() / 97 + 1) {
                    assert!(DwellAccumulator::from_state(&bytes[..k]).is_err());
                    let mut c = bytes.clone();
                    c[k] ^= 0xA5;
                    if let Ok(acc2) = DwellAccumulator::from_state(&c) {
                        let _ = acc2.finish();
                    }
                }
            }
            acc.push(&x.view(), None, None).unwrap();
        }
    }
}

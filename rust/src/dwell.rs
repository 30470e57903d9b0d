//! Per-dwell statistics of high-rate 3-axis streams.
//!
//! The kernel is a block-shifted, multi-lane accumulator: within a block of at most
//! [`BLOCK`] samples each axis is accumulated as deviations from the block's first sample
//! (so raw counts with offsets of ~33000 lose nothing), spread over [`LANES`] independent
//! lanes for instruction-level parallelism, and blocks are merged with Chan's formula.
//! Sample `j` of a segment always lands in the same lane and block whatever the chunking,
//! so the streaming accumulator reproduces the one-shot result bit for bit.

use crate::error::{invalid, CoreError, Result};
use ndarray::ArrayView2;
use rayon::prelude::*;

/// Independent accumulation lanes.
pub const LANES: usize = 4;
/// Samples per shifted block (a multiple of [`LANES`]).
pub const BLOCK: usize = 4096;
/// Values per group of [`LANES`] rows.
const W: usize = 3 * LANES;

/// A sample type accepted by the kernels: converted exactly (integers) or widened to f64.
pub trait Sample: Copy + Send + Sync + 'static {
    /// The value as f64.
    fn to_f64(self) -> f64;

    /// Accumulate whole groups of `3 * LANES` values (at most one block) into the per-lane
    /// shifted sums (`s1 += x - shift`, `s2 += (x - shift)^2`, element `j` of a group in lane
    /// `j / 3`, axis `j % 3`). Overridden where an exact faster path exists.
    #[inline(always)]
    fn accumulate(body: &[Self], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
        accumulate_dispatch(body, sh, s1, s2);
    }
}
impl Sample for f64 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
}
impl Sample for f32 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
}
impl Sample for i16 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }

    #[inline(always)]
    fn accumulate(body: &[Self], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
        accumulate_i16_dispatch(body, sh, s1, s2);
    }
}
impl Sample for i32 {
    #[inline(always)]
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
}

/// Count, mean and sum of squared deviations of one segment, per axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Moments {
    /// Number of samples.
    pub n: u64,
    /// Mean per axis.
    pub mean: [f64; 3],
    /// Sum of squared deviations from the mean per axis.
    pub m2: [f64; 3],
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
    };

    /// Combine two disjoint segments (Chan, Golub and LeVeque).
    #[must_use]
    pub fn merge(&self, o: &Moments) -> Moments {
        if o.n == 0 {
            return *self;
        }
        if self.n == 0 {
            return *o;
        }
        let n = self.n + o.n;
        let (na, nb, nn) = (self.n as f64, o.n as f64, n as f64);
        let mut out = Moments {
            n,
            ..Moments::EMPTY
        };
        for a in 0..3 {
            let d = o.mean[a] - self.mean[a];
            out.mean[a] = self.mean[a] + d * (nb / nn);
            out.m2[a] = self.m2[a] + o.m2[a] + d * d * (na * nb / nn);
        }
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

    /// True when every mean and m2 is finite.
    pub fn is_finite(&self) -> bool {
        self.mean
            .iter()
            .chain(self.m2.iter())
            .all(|v| v.is_finite())
    }
}

/// Streaming accumulator for one segment.
#[derive(Debug, Clone)]
pub struct SegmentAcc {
    done: Moments,
    shift: [f64; 3],
    nb: usize,
    s1: [[f64; 3]; LANES],
    s2: [[f64; 3]; LANES],
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
            shift: [0.0; 3],
            nb: 0,
            s1: [[0.0; 3]; LANES],
            s2: [[0.0; 3]; LANES],
        }
    }

    /// Samples accumulated so far.
    pub fn count(&self) -> u64 {
        self.done.n + self.nb as u64
    }

    #[inline(always)]
    fn add(&mut self, lane: usize, r: [f64; 3]) {
        for (a, &v) in r.iter().enumerate() {
            let d = v - self.shift[a];
            self.s1[lane][a] += d;
            self.s2[lane][a] += d * d;
        }
    }

    /// Add one sample.
    #[inline]
    pub fn push_row(&mut self, r: [f64; 3]) {
        if self.nb == 0 {
            self.shift = r;
        }
        self.add(self.nb % LANES, r);
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
                s1 += self.s1[l][a];
                s2 += self.s2[l][a];
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

    fn flush(&mut self) {
        let b = self.block_moments();
        self.done = self.done.merge(&b);
        self.nb = 0;
        self.s1 = [[0.0; 3]; LANES];
        self.s2 = [[0.0; 3]; LANES];
    }

    /// Add the rows of a row-major `(m, 3)` slice (length a multiple of 3).
    pub fn push_slice<T: Sample>(&mut self, data: &[T]) {
        let nrows = data.len() / 3;
        let mut i = 0;
        // Head: single rows until the lane index is aligned.
        while !self.nb.is_multiple_of(LANES) && i < nrows {
            let r = &data[3 * i..3 * i + 3];
            self.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
            i += 1;
        }
        let mut rest = &data[3 * i..3 * nrows];
        // Body: whole groups of LANES rows, a block at a time, with the accumulators in locals
        // (registers) and the group seen as 3 * LANES independent sums: element j of a group
        // is lane j / 3, axis j % 3, exactly as in `add`, so results are bit-identical to the
        // row-by-row path and independent of chunking.
        while rest.len() >= W {
            if self.nb == 0 {
                self.shift = [rest[0].to_f64(), rest[1].to_f64(), rest[2].to_f64()];
            }
            let groups = ((BLOCK - self.nb) / LANES).min(rest.len() / W);
            let (body, tail) = rest.split_at(groups * W);
            let mut sh = [0.0; W];
            let mut s1 = [0.0; W];
            let mut s2 = [0.0; W];
            for j in 0..W {
                sh[j] = self.shift[j % 3];
                s1[j] = self.s1[j / 3][j % 3];
                s2[j] = self.s2[j / 3][j % 3];
            }
            T::accumulate(body, &sh, &mut s1, &mut s2);
            for j in 0..W {
                self.s1[j / 3][j % 3] = s1[j];
                self.s2[j / 3][j % 3] = s2[j];
            }
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

    /// Add rows `[a, b)` of a `(N, 3)` view of any strides (fast path when contiguous).
    pub fn push_view<T: Sample>(&mut self, v: &ArrayView2<'_, T>, a: usize, b: usize) {
        let sub = v.slice(ndarray::s![a..b, ..]);
        if let Some(s) = sub.as_slice() {
            self.push_slice(s);
        } else {
            for r in sub.rows() {
                self.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
            }
        }
    }

    /// The moments of everything pushed so far.
    pub fn moments(&self) -> Moments {
        self.done.merge(&self.block_moments())
    }
}

/// The hot loop: `s1[j] += x[j] - sh[j]`, `s2[j] += (x[j] - sh[j])^2` over groups of
/// `3 * LANES` values (no FMA contraction, so the rounding is the same as in `SegmentAcc::add`).
#[inline(always)]
fn accumulate_groups<T: Sample>(body: &[T], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
    for g in body.chunks_exact(W) {
        for j in 0..W {
            let d = g[j].to_f64() - sh[j];
            s1[j] += d;
            s2[j] += d * d;
        }
    }
}

/// [`accumulate_groups`] compiled for AVX2 when the CPU has it (wider vectors, same
/// operations in the same order, so bit-identical results), else for the baseline target.
#[inline]
fn accumulate_dispatch<T: Sample>(body: &[T], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { accumulate_groups_avx2(body, sh, s1, s2) };
            return;
        }
    }
    accumulate_groups(body, sh, s1, s2);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn accumulate_groups_avx2<T: Sample>(
    body: &[T],
    sh: &[f64; W],
    s1: &mut [f64; W],
    s2: &mut [f64; W],
) {
    accumulate_groups(body, sh, s1, s2);
}

/// int16 counts: the same sums in exact integer arithmetic.
///
/// With an integer shift every deviation `d` is an integer with `|d| <= 65535`, so within one
/// block (<= 4096 rows) every float64 partial sum of `d` and `d^2` in [`accumulate_groups`] is
/// an integer below 2^53 and therefore exact whatever the order. Integer sums give the same
/// exact totals, so the result is bit-identical to the float path (the row-by-row and strided
/// paths included). The totals go into lane 0; lanes are only ever summed.
#[inline(always)]
fn accumulate_i16(body: &[i16], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
    const U: usize = 2 * W;
    let shu: [i32; U] = std::array::from_fn(|j| sh[j % 3] as i32);
    let mut a1 = [0i32; U];
    let mut a2 = [0u64; U];
    let mut it = body.chunks_exact(U);
    for g in it.by_ref() {
        for j in 0..U {
            let d = i32::from(g[j]) - shu[j];
            a1[j] += d;
            // |d| <= 65535, so d^2 < 2^32 fits u32 (the wrapping product of the two's
            // complement bits is exact).
            a2[j] += u64::from((d as u32).wrapping_mul(d as u32));
        }
    }
    for (j, &v) in it.remainder().iter().enumerate() {
        let d = i32::from(v) - shu[j];
        a1[j] += d;
        a2[j] += u64::from((d as u32).wrapping_mul(d as u32));
    }
    let mut t1 = [0i64; 3];
    let mut t2 = [0u64; 3];
    for j in 0..U {
        t1[j % 3] += i64::from(a1[j]);
        t2[j % 3] += a2[j];
    }
    for a in 0..3 {
        s1[a] += t1[a] as f64;
        s2[a] += t2[a] as f64;
    }
}

#[inline]
fn accumulate_i16_dispatch(body: &[i16], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { accumulate_i16_avx2(body, sh, s1, s2) };
            return;
        }
    }
    accumulate_i16(body, sh, s1, s2);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn accumulate_i16_avx2(body: &[i16], sh: &[f64; W], s1: &mut [f64; W], s2: &mut [f64; W]) {
    accumulate_i16(body, sh, s1, s2);
}

/// Check that `samples` is `(N, 3)`.
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

fn nonfinite_error(k: usize, a: usize, b: usize) -> CoreError {
    CoreError::InvalidInput(format!(
        "samples contain NaN or inf (or values too large to square) in dwell {k} [{a}, {b})"
    ))
}

/// Per-dwell moments of `samples` over `[start, stop)` bounds (parallel over dwells).
pub fn dwell_moments<T: Sample>(
    samples: &ArrayView2<'_, T>,
    bounds: &[[usize; 2]],
) -> Result<Vec<Moments>> {
    let n = check_samples(samples)?;
    check_bounds(bounds, n)?;
    let out: Vec<Moments> = bounds
        .par_iter()
        .map(|&[a, b]| {
            let mut acc = SegmentAcc::new();
            acc.push_view(samples, a, b);
            acc.moments()
        })
        .collect();
    for (k, m) in out.iter().enumerate() {
        if !m.is_finite() {
            return Err(nonfinite_error(k, bounds[k][0], bounds[k][1]));
        }
    }
    Ok(out)
}

/// Mean of an auxiliary per-sample channel (e.g. temperature) over each dwell.
pub fn aux_mean(x: &[f64], bounds: &[[usize; 2]]) -> Result<Vec<f64>> {
    bounds
        .iter()
        .enumerate()
        .map(|(k, &[a, b])| {
            let s: f64 = x[a..b].iter().sum();
            let m = s / (b - a) as f64;
            if m.is_finite() {
                Ok(m)
            } else {
                invalid(format!(
                    "temperature (auxiliary channel) has NaN or inf in dwell {k}"
                ))
            }
        })
        .collect()
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

    /// Check every setting.
    pub fn validate(&self) -> Result<()> {
        let pos = |v: f64, name: &str| -> Result<()> {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                invalid(format!("{name} must be a positive finite number; got {v}"))
            }
        };
        pos(self.fs, "fs (sample rate, Hz)")?;
        pos(self.window_s, "window_s (s)")?;
        pos(self.k, "k (threshold factor)")?;
        pos(self.block_s, "block_s (s)")?;
        if !(self.min_dwell_s.is_finite() && self.min_dwell_s >= 0.0) {
            return invalid(format!(
                "min_dwell_s must be >= 0; got {}",
                self.min_dwell_s
            ));
        }
        if !(self.trim_s.is_finite() && self.trim_s >= 0.0) {
            return invalid(format!("trim_s must be >= 0; got {}", self.trim_s));
        }
        if !(self.noise_quantile > 0.0 && self.noise_quantile < 1.0) {
            return invalid(format!(
                "noise_quantile must be in (0, 1); got {}",
                self.noise_quantile
            ));
        }
        if let Some(v) = self.noise_var {
            if !v.iter().all(|x| x.is_finite() && *x > 0.0) {
                return invalid("noise_var must be three positive finite variances");
            }
        }
        Ok(())
    }

    /// Samples per block.
    pub fn block_len(&self) -> usize {
        ((self.fs * self.block_s).round() as usize).max(1)
    }

    /// Blocks per window (at least 2).
    pub fn window_blocks(&self) -> usize {
        ((self.window_s * self.fs / self.block_len() as f64).round() as usize).max(2)
    }
}

/// What the detector decided.
#[derive(Debug, Clone, PartialEq)]
pub struct Detection {
    /// `[start, stop)` sample bounds of each dwell.
    pub bounds: Vec<[usize; 2]>,
    /// Moments of each dwell.
    pub moments: Vec<Moments>,
    /// Noise variance per axis used (estimated or given), in squared input units.
    pub noise_var: [f64; 3],
    /// Threshold on the window variance per axis, in squared input units.
    pub threshold: [f64; 3],
}

/// Detect static intervals from compressed block statistics.
///
/// `blocks[j]` holds samples `[j * b, (j + 1) * b)` with `b = settings.block_len()`.
pub fn detect_from_blocks(blocks: &[Moments], s: &DetectorSettings) -> Result<Detection> {
    s.validate()?;
    let b = s.block_len();
    let w = s.window_blocks();
    if blocks.len() < w + 1 {
        return invalid(format!(
            "stream too short for dwell detection: {} samples, need more than one {} s window ({} samples)",
            blocks.len() * b,
            s.window_s,
            w * b
        ));
    }
    for (j, m) in blocks.iter().enumerate() {
        if !m.is_finite() {
            return invalid(format!(
                "samples contain NaN or inf near sample {} (block [{}, {}))",
                j * b,
                j * b,
                (j + 1) * b
            ));
        }
    }
    // Window variance per axis; window i covers blocks i..i+w.
    let nw = blocks.len() - w + 1;
    let var: Vec<[f64; 3]> = (0..nw)
        .into_par_iter()
        .map(|i| {
            let m = blocks[i..i + w]
                .iter()
                .fold(Moments::EMPTY, |acc, x| acc.merge(x));
            m.var()
        })
        .collect();
    let noise_var = match s.noise_var {
        Some(v) => v,
        None => {
            let mut nv = [0.0; 3];
            for (a, slot) in nv.iter_mut().enumerate() {
                let mut col: Vec<f64> = var.iter().map(|v| v[a]).collect();
                let q = ((col.len() - 1) as f64 * s.noise_quantile).round() as usize;
                let (_, val, _) = col.select_nth_unstable_by(q, |x, y| x.total_cmp(y));
                *slot = *val;
            }
            // A perfectly constant axis (e.g. clipped or simulated noise-free) must not make
            // every tiny change look like motion, nor divide by zero.
            let top = nv.iter().cloned().fold(0.0, f64::max);
            for v in nv.iter_mut() {
                if *v <= 0.0 {
                    *v = if top > 0.0 { top } else { f64::MIN_POSITIVE };
                }
            }
            nv
        }
    };
    let thr = [s.k * noise_var[0], s.k * noise_var[1], s.k * noise_var[2]];
    let h = w / 2;
    let mut is_static = vec![false; blocks.len()];
    for (i, v) in var.iter().enumerate() {
        is_static[i + h] = (0..3).all(|a| v[a] < thr[a]);
    }
    let trim = (s.trim_s * s.fs / b as f64).round() as usize;
    let min_blocks = (s.min_dwell_s * s.fs / b as f64).ceil() as usize;
    let mut bounds = Vec::new();
    let mut moments = Vec::new();
    let mut j = 0;
    while j < blocks.len() {
        if !is_static[j] {
            j += 1;
            continue;
        }
        let start = j;
        while j < blocks.len() && is_static[j] {
            j += 1;
        }
        let (a, z) = (start + trim, j.saturating_sub(trim));
        if z > a && z - a >= min_blocks.max(1) {
            let m = blocks[a..z]
                .iter()
                .fold(Moments::EMPTY, |acc, x| acc.merge(x));
            bounds.push([a * b, z * b]);
            moments.push(m);
        }
    }
    Ok(Detection {
        bounds,
        moments,
        noise_var,
        threshold: thr,
    })
}

/// Streaming accumulator of per-dwell statistics.
#[derive(Debug, Clone)]
pub enum DwellAccumulator {
    /// Known `[start, stop)` bounds.
    Bounds(BoundsAcc),
    /// Automatic detection at `finish` (boxed: it carries a block accumulator).
    Detect(Box<DetectAcc>),
}

/// Accumulator for known bounds (sorted internally; results in the caller's order).
#[derive(Debug, Clone)]
pub struct BoundsAcc {
    bounds: Vec<[usize; 2]>,
    order: Vec<usize>,
    accs: Vec<SegmentAcc>,
    aux_sum: Vec<f64>,
    t_first: Vec<f64>,
    t_last: Vec<f64>,
    first_open: usize,
    pos: usize,
    has_t: Option<bool>,
    has_aux: Option<bool>,
}

/// Accumulator for detection: per-block statistics only.
#[derive(Debug, Clone)]
pub struct DetectAcc {
    settings: DetectorSettings,
    blocks: Vec<Moments>,
    aux_blocks: Vec<f64>,
    t_blocks: Vec<[f64; 2]>,
    cur: SegmentAcc,
    cur_aux: f64,
    cur_t: [f64; 2],
    pos: usize,
    has_t: Option<bool>,
    has_aux: Option<bool>,
}

/// A finished dwell table.
#[derive(Debug, Clone, PartialEq)]
pub struct DwellTable {
    /// `[start, stop)` sample bounds.
    pub bounds: Vec<[usize; 2]>,
    /// Moments per dwell.
    pub moments: Vec<Moments>,
    /// Mid time `(t[start] + t[stop-1]) / 2` per dwell, when a time channel was pushed.
    pub t_mid: Option<Vec<f64>>,
    /// Mean of the auxiliary channel (temperature) per dwell, when one was pushed.
    pub aux_mean: Option<Vec<f64>>,
    /// Detection diagnostics, when the dwells were detected.
    pub noise_var: Option<[f64; 3]>,
    /// Detection threshold per axis, when the dwells were detected.
    pub threshold: Option<[f64; 3]>,
}

fn check_presence(flag: &mut Option<bool>, now: bool, what: &str) -> Result<()> {
    match *flag {
        None => {
            *flag = Some(now);
            Ok(())
        }
        Some(f) if f == now => Ok(()),
        Some(_) => invalid(format!(
            "{what} must be given with every chunk or with none"
        )),
    }
}

fn check_aux_len(x: Option<&[f64]>, n: usize, what: &str) -> Result<()> {
    if let Some(x) = x {
        if x.len() != n {
            return invalid(format!(
                "{what} has {} values but the chunk has {n} samples",
                x.len()
            ));
        }
    }
    Ok(())
}

impl DwellAccumulator {
    /// Accumulate over known bounds.
    pub fn with_bounds(bounds: Vec<[usize; 2]>) -> Result<Self> {
        check_bounds(&bounds, usize::MAX)?;
        let mut order: Vec<usize> = (0..bounds.len()).collect();
        order.sort_by_key(|&k| bounds[k][0]);
        let k = bounds.len();
        Ok(DwellAccumulator::Bounds(BoundsAcc {
            bounds,
            order,
            accs: vec![SegmentAcc::new(); k],
            aux_sum: vec![0.0; k],
            t_first: vec![f64::NAN; k],
            t_last: vec![f64::NAN; k],
            first_open: 0,
            pos: 0,
            has_t: None,
            has_aux: None,
        }))
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
            cur_aux: 0.0,
            cur_t: [f64::NAN; 2],
            pos: 0,
            has_t: None,
            has_aux: None,
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
        check_aux_len(t, m, "t")?;
        check_aux_len(aux, m, "temperature")?;
        match self {
            DwellAccumulator::Bounds(s) => {
                check_presence(&mut s.has_t, t.is_some(), "t")?;
                check_presence(&mut s.has_aux, aux.is_some(), "temperature")?;
                s.push(chunk, t, aux)
            }
            DwellAccumulator::Detect(s) => {
                check_presence(&mut s.has_t, t.is_some(), "t")?;
                check_presence(&mut s.has_aux, aux.is_some(), "temperature")?;
                s.push(chunk, t, aux)
            }
        }
    }

    /// Finish and return the dwell table.
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
    ) -> Result<()> {
        let (c0, c1) = (self.pos, self.pos + chunk.nrows());
        let mut i = self.first_open;
        while i < self.order.len() {
            let k = self.order[i];
            let [a, b] = self.bounds[k];
            if a >= c1 {
                break;
            }
            let (lo, hi) = (a.max(c0), b.min(c1));
            if lo < hi {
                self.accs[k].push_view(chunk, lo - c0, hi - c0);
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
        Ok(())
    }

    fn finish(&self) -> Result<DwellTable> {
        let mut moments = Vec::with_capacity(self.bounds.len());
        for (k, (&[a, b], acc)) in self.bounds.iter().zip(&self.accs).enumerate() {
            if b > self.pos {
                return invalid(format!(
                    "dwell {k} [{a}, {b}) out of range: only {} samples were pushed",
                    self.pos
                ));
            }
            let m = acc.moments();
            if !m.is_finite() {
                return Err(nonfinite_error(k, a, b));
            }
            moments.push(m);
        }
        let t_mid = if self.has_t == Some(true) {
            Some(
                self.t_first
                    .iter()
                    .zip(&self.t_last)
                    .map(|(a, b)| 0.5 * (a + b))
                    .collect(),
            )
        } else {
            None
        };
        let aux_mean = if self.has_aux == Some(true) {
            let v: Vec<f64> = self
                .aux_sum
                .iter()
                .zip(&self.bounds)
                .map(|(s, &[a, b])| s / (b - a) as f64)
                .collect();
            if v.iter().any(|x| !x.is_finite()) {
                return invalid("temperature contains NaN or inf inside a dwell");
            }
            Some(v)
        } else {
            None
        };
        Ok(DwellTable {
            bounds: self.bounds.clone(),
            moments,
            t_mid,
            aux_mean,
            noise_var: None,
            threshold: None,
        })
    }
}

impl DetectAcc {
    fn push<T: Sample>(
        &mut self,
        chunk: &ArrayView2<'_, T>,
        t: Option<&[f64]>,
        aux: Option<&[f64]>,
    ) -> Result<()> {
        let bl = self.settings.block_len();
        let m = chunk.nrows();
        let mut i = 0;
        while i < m {
            let in_block = (self.cur.count() as usize) % bl;
            let take = (bl - in_block).min(m - i);
            if in_block == 0 {
                if let Some(t) = t {
                    self.cur_t[0] = t[i];
                }
            }
            self.cur.push_view(chunk, i, i + take);
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
                self.blocks.push(self.cur.moments());
                self.aux_blocks.push(self.cur_aux);
                self.t_blocks.push(self.cur_t);
                self.cur = SegmentAcc::new();
                self.cur_aux = 0.0;
                self.cur_t = [f64::NAN; 2];
            }
        }
        self.pos += m;
        Ok(())
    }

    fn finish(&self) -> Result<DwellTable> {
        if self.pos == 0 {
            return invalid("no samples were pushed");
        }
        let det = detect_from_blocks(&self.blocks, &self.settings)?;
        let bl = self.settings.block_len();
        let t_mid = if self.has_t == Some(true) {
            Some(
                det.bounds
                    .iter()
                    .map(|&[a, b]| 0.5 * (self.t_blocks[a / bl][0] + self.t_blocks[b / bl - 1][1]))
                    .collect(),
            )
        } else {
            None
        };
        let aux_mean = if self.has_aux == Some(true) {
            let v: Vec<f64> = det
                .bounds
                .iter()
                .map(|&[a, b]| {
                    let s: f64 = self.aux_blocks[a / bl..b / bl].iter().sum();
                    s / (b - a) as f64
                })
                .collect();
            if v.iter().any(|x| !x.is_finite()) {
                return invalid("temperature contains NaN or inf inside a dwell");
            }
            Some(v)
        } else {
            None
        };
        Ok(DwellTable {
            bounds: det.bounds,
            moments: det.moments,
            t_mid,
            aux_mean,
            noise_var: Some(det.noise_var),
            threshold: Some(det.threshold),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn lcg(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64) / ((1u64 << 53) as f64)
    }

    fn two_pass(x: &Array2<f64>, a: usize, b: usize) -> ([f64; 3], [f64; 3]) {
        let mut mean = [0.0; 3];
        let mut var = [0.0; 3];
        for ax in 0..3 {
            let col: Vec<f64> = (a..b).map(|i| x[[i, ax]]).collect();
            let m = col.iter().sum::<f64>() / col.len() as f64;
            let v = col.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (col.len() - 1) as f64;
            mean[ax] = m;
            var[ax] = v;
        }
        (mean, var)
    }

    #[test]
    fn counts_with_large_offset_match_two_pass() {
        let mut s = 7u64;
        let n = 20_000;
        let x = Array2::from_shape_fn((n, 3), |_| 33000.0 + (3.0 * lcg(&mut s) * 3.0).round());
        let bounds = vec![[0, 5000], [5000, 13_001], [13_001, 20_000]];
        let m = dwell_moments(&x.view(), &bounds).unwrap();
        for (k, &[a, b]) in bounds.iter().enumerate() {
            let (mean, var) = two_pass(&x, a, b);
            for ax in 0..3 {
                assert!((m[k].mean[ax] - mean[ax]).abs() <= 1e-12 * mean[ax].abs());
                assert!((m[k].var()[ax] - var[ax]).abs() <= 1e-9 * var[ax]);
            }
        }
    }

    #[test]
    fn streaming_equals_one_shot_bitwise() {
        let mut s = 3u64;
        let n = 30_011;
        let x = Array2::from_shape_fn((n, 3), |_| 1e4 + lcg(&mut s));
        let bounds = vec![[10, 9000], [9000, 9001 + 8000], [20_000, 30_011]];
        let one = dwell_moments(&x.view(), &bounds).unwrap();
        let mut acc = DwellAccumulator::with_bounds(bounds.clone()).unwrap();
        let mut pos = 0;
        let mut step = 1;
        while pos < n {
            let e = (pos + step).min(n);
            acc.push(&x.slice(ndarray::s![pos..e, ..]), None, None)
                .unwrap();
            pos = e;
            step = (step * 7 + 3) % 5003 + 1;
        }
        let t = acc.finish().unwrap();
        assert_eq!(t.moments, one);
    }

    #[test]
    fn strided_view_equals_contiguous() {
        let mut s = 11u64;
        let x = Array2::from_shape_fn((1000, 6), |_| lcg(&mut s));
        let strided = x.slice(ndarray::s![.., 0..6;2]);
        let copy = strided.to_owned();
        let a = dwell_moments(&strided, &[[0, 1000]]).unwrap();
        let b = dwell_moments(&copy.view(), &[[0, 1000]]).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn bad_bounds_and_nan_are_errors() {
        let x = Array2::<f64>::zeros((100, 3));
        assert!(dwell_moments(&x.view(), &[[0, 101]]).is_err());
        assert!(dwell_moments(&x.view(), &[[5, 5]]).is_err());
        assert!(dwell_moments(&x.view(), &[[0, 50], [40, 60]]).is_err());
        let mut y = x.clone();
        y[[10, 1]] = f64::NAN;
        let e = dwell_moments(&y.view(), &[[0, 50]]).unwrap_err();
        assert!(e.to_string().contains("NaN"));
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
        let mut fast = SegmentAcc::new();
        fast.push_slice(x.as_slice().unwrap());
        let mut slow = SegmentAcc::new();
        for r in x.rows() {
            slow.push_row([r[0].to_f64(), r[1].to_f64(), r[2].to_f64()]);
        }
        assert_eq!(fast.moments(), slow.moments());
        let xf = x.mapv(f64::from);
        let (mean, var) = two_pass(&xf, 0, 10_007);
        let m = fast.moments();
        for ax in 0..3 {
            assert!((m.mean[ax] - mean[ax]).abs() <= 1e-12 * mean[ax].abs());
            assert!((m.var()[ax] - var[ax]).abs() <= 1e-12 * var[ax]);
        }
    }

    #[test]
    fn overflow_is_an_error_not_zero_variance() {
        let x = Array2::from_shape_fn((100, 3), |(i, _)| if i % 2 == 0 { -1e300 } else { 1e300 });
        let e = dwell_moments(&x.view(), &[[0, 100]]).unwrap_err();
        assert!(e.to_string().contains("too large"));
    }

    #[test]
    fn detector_finds_simulated_dwells() {
        // 5 dwells of 5 s at 100 Hz separated by 2 s ramps.
        let fs = 100.0;
        let mut s = 5u64;
        let mut rows = Vec::new();
        let levels = [0.0, 1.0, -1.0, 2.0, 0.5];
        for (i, &l) in levels.iter().enumerate() {
            for _ in 0..500 {
                rows.push([
                    l + 0.01 * lcg(&mut s),
                    0.01 * lcg(&mut s),
                    9.8 + 0.01 * lcg(&mut s),
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
        let x = Array2::from_shape_fn((rows.len(), 3), |(i, a)| rows[i][a]);
        let mut acc = DwellAccumulator::with_detector(DetectorSettings::new(fs)).unwrap();
        acc.push(&x.view(), None, None).unwrap();
        let t = acc.finish().unwrap();
        assert_eq!(t.bounds.len(), 5);
        for (m, &l) in t.moments.iter().zip(&levels) {
            assert!((m.mean[0] - (l + 0.005)).abs() < 0.002);
        }
    }
}

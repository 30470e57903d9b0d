//! The state of a [`DwellAccumulator`] as versioned bytes, so that a stream can be
//! checkpointed mid-dwell and resumed in another process with bit-identical results.
//!
//! Layout: the magic `b"ACDWELL\0"`, a little-endian `u32` version, then the fields in a fixed
//! order (integers as `u64`, floats as their IEEE bits, vectors prefixed by their length).
//! Decoding checks every length and invariant, so corrupted or truncated bytes give an error,
//! never a panic or an accumulator that misbehaves later.

use super::{
    check_dwell_bounds, DetectorSettings, DwellAccumulator, DwellBuild, DwellOutcome, DwellStat,
    Lanes, LsbSampler, Moments, SegmentAcc, BLOCK, LSB_CAP, W,
};
use crate::error::{invalid, Result};

/// Version written by [`DwellAccumulator::to_state`]; [`DwellAccumulator::from_state`] reads
/// this version only.
pub const STATE_VERSION: u32 = 1;
const MAGIC: &[u8; 8] = b"ACDWELL\0";

#[derive(Default)]
struct Enc(Vec<u8>);

impl Enc {
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn us(&mut self, v: usize) {
        self.u64(v as u64);
    }
    fn f64(&mut self, v: f64) {
        self.u64(v.to_bits());
    }
    fn f64s(&mut self, v: &[f64]) {
        for x in v {
            self.f64(*x);
        }
    }
    fn flag(&mut self, v: Option<bool>) {
        self.0.push(match v {
            None => 0,
            Some(false) => 1,
            Some(true) => 2,
        });
    }
    fn opt_us(&mut self, v: Option<usize>) {
        match v {
            None => self.0.push(0),
            Some(x) => {
                self.0.push(1);
                self.us(x);
            }
        }
    }
    fn moments(&mut self, m: &Moments) {
        self.u64(m.n);
        for v in [&m.mean, &m.m2, &m.d2, &m.first, &m.last] {
            self.f64s(v);
        }
    }
    fn seg(&mut self, s: &SegmentAcc) {
        self.moments(&s.done);
        self.f64s(&s.d2_done);
        self.f64s(&s.shift);
        self.us(s.nb);
        self.f64s(&s.lanes.s1);
        self.f64s(&s.lanes.s2);
        self.f64s(&s.lanes.d2);
        self.f64s(&s.first);
        self.f64s(&s.last);
    }
    fn lsb(&mut self, l: &LsbSampler) {
        self.u64(l.step);
        self.0.push(u8::from(l.integer));
        self.0.push(u8::from(l.seen));
        self.us(l.rows.len());
        for r in &l.rows {
            self.f64s(r);
        }
    }
    fn outcome(&mut self, o: &DwellOutcome) {
        self.moments(&o.stat.moments);
        self.f64s(&o.stat.half_mean[0]);
        self.f64s(&o.stat.half_mean[1]);
        self.f64s(&o.stat.inflation);
        self.u64(o.bad);
        self.opt_us(o.first_bad);
    }
    fn build(&mut self, b: &DwellBuild) {
        self.us(b.a);
        self.us(b.b);
        self.us(b.cum.len());
        for m in &b.cum {
            self.moments(m);
        }
        self.seg(&b.cur);
        self.u64(b.bad);
        self.opt_us(b.first_bad);
    }
}

struct Dec<'a> {
    b: &'a [u8],
}

fn corrupt<T>(what: &str) -> Result<T> {
    invalid(format!(
        "dwell accumulator state is corrupted or truncated ({what})"
    ))
}

impl Dec<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8]> {
        if self.b.len() < n {
            return corrupt("unexpected end");
        }
        let (h, t) = self.b.split_at(n);
        self.b = t;
        Ok(h)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }
    fn u64(&mut self) -> Result<u64> {
        let mut a = [0u8; 8];
        a.copy_from_slice(self.take(8)?);
        Ok(u64::from_le_bytes(a))
    }
    fn us(&mut self) -> Result<usize> {
        usize::try_from(self.u64()?).or_else(|_| corrupt("index too large"))
    }
    /// A length, bounded by what the remaining bytes can hold (`item` bytes per element).
    fn len(&mut self, item: usize) -> Result<usize> {
        let n = self.us()?;
        if n.saturating_mul(item.max(1)) > self.b.len() {
            return corrupt("length beyond the data");
        }
        Ok(n)
    }
    fn f64(&mut self) -> Result<f64> {
        Ok(f64::from_bits(self.u64()?))
    }
    fn arr<const N: usize>(&mut self) -> Result<[f64; N]> {
        let mut a = [0.0; N];
        for x in a.iter_mut() {
            *x = self.f64()?;
        }
        Ok(a)
    }
    fn bool(&mut self) -> Result<bool> {
        match self.u8()? {
            0 => Ok(false),
            1 => Ok(true),
            _ => corrupt("bad flag"),
        }
    }
    fn flag(&mut self) -> Result<Option<bool>> {
        match self.u8()? {
            0 => Ok(None),
            1 => Ok(Some(false)),
            2 => Ok(Some(true)),
            _ => corrupt("bad flag"),
        }
    }
    fn opt_us(&mut self) -> Result<Option<usize>> {
        match self.u8()? {
            0 => Ok(None),
            1 => Ok(Some(self.us()?)),
            _ => corrupt("bad option"),
        }
    }
    fn moments(&mut self) -> Result<Moments> {
        Ok(Moments {
            n: self.u64()?,
            mean: self.arr()?,
            m2: self.arr()?,
            d2: self.arr()?,
            first: self.arr()?,
            last: self.arr()?,
        })
    }
    fn seg(&mut self) -> Result<SegmentAcc> {
        let s = SegmentAcc {
            done: self.moments()?,
            d2_done: self.arr()?,
            shift: self.arr()?,
            nb: self.us()?,
            lanes: Lanes {
                s1: self.arr::<W>()?,
                s2: self.arr::<W>()?,
                d2: self.arr::<W>()?,
            },
            first: self.arr()?,
            last: self.arr()?,
        };
        if s.nb >= BLOCK || s.done.n.checked_add(s.nb as u64).is_none() {
            return corrupt("segment block count");
        }
        Ok(s)
    }
    fn lsb(&mut self) -> Result<LsbSampler> {
        let step = self.u64()?;
        let integer = self.bool()?;
        let seen = self.bool()?;
        let n = self.len(24)?;
        if !step.is_power_of_two() || step > 1 << 62 || n > LSB_CAP {
            return corrupt("resolution subsample");
        }
        let mut rows = Vec::with_capacity(n);
        for _ in 0..n {
            rows.push(self.arr()?);
        }
        Ok(LsbSampler {
            step,
            rows,
            integer,
            seen,
        })
    }
    fn outcome(&mut self) -> Result<DwellOutcome> {
        let stat = DwellStat {
            moments: self.moments()?,
            half_mean: [self.arr()?, self.arr()?],
            inflation: self.arr()?,
        };
        Ok(DwellOutcome {
            stat,
            bad: self.u64()?,
            first_bad: self.opt_us()?,
        })
    }
    fn build(&mut self) -> Result<DwellBuild> {
        let (a, b) = (self.us()?, self.us()?);
        let n = self.len(8)?;
        let mut cum = Vec::with_capacity(n);
        for _ in 0..n {
            cum.push(self.moments()?);
        }
        let d = DwellBuild {
            a,
            b,
            cum,
            cur: self.seg()?,
            bad: self.u64()?,
            first_bad: self.opt_us()?,
        };
        if a >= b || d.cum.len() >= d.nsub() || d.cur.count() as usize > b - a {
            return corrupt("open dwell");
        }
        Ok(d)
    }
}

fn lsb_consistent(l: &LsbSampler, pos: usize) -> bool {
    (pos as u64).div_ceil(l.step) == l.rows.len() as u64 && l.seen == (pos > 0)
}

impl DwellAccumulator {
    /// The accumulator's state as versioned bytes ([`STATE_VERSION`]).
    pub fn to_state(&self) -> Vec<u8> {
        let mut e = Enc::default();
        e.0.extend_from_slice(MAGIC);
        e.0.extend_from_slice(&STATE_VERSION.to_le_bytes());
        match self {
            DwellAccumulator::Bounds(s) => {
                e.0.push(1);
                e.us(s.bounds.len());
                for [a, b] in &s.bounds {
                    e.us(*a);
                    e.us(*b);
                }
                for d in &s.done {
                    match d {
                        None => e.0.push(0),
                        Some(o) => {
                            e.0.push(1);
                            e.outcome(o);
                        }
                    }
                }
                match &s.open {
                    None => e.0.push(0),
                    Some((k, b)) => {
                        e.0.push(1);
                        e.us(*k);
                        e.build(b);
                    }
                }
                e.f64s(&s.aux_sum);
                e.f64s(&s.t_first);
                e.f64s(&s.t_last);
                e.us(s.first_open);
                e.us(s.pos);
                e.flag(s.has_t);
                e.flag(s.has_aux);
                e.lsb(&s.lsb);
            }
            DwellAccumulator::Detect(s) => {
                e.0.push(2);
                let st = &s.settings;
                e.f64s(&[
                    st.fs,
                    st.window_s,
                    st.k,
                    st.min_dwell_s,
                    st.trim_s,
                    st.noise_quantile,
                    st.block_s,
                ]);
                match st.noise_var {
                    None => e.0.push(0),
                    Some(v) => {
                        e.0.push(1);
                        e.f64s(&v);
                    }
                }
                e.us(s.blocks.len());
                for m in &s.blocks {
                    e.moments(m);
                }
                e.f64s(&s.aux_blocks);
                for t in &s.t_blocks {
                    e.f64s(t);
                }
                e.seg(&s.cur);
                e.0.push(u8::from(s.cur_bad));
                e.f64(s.cur_aux);
                e.f64s(&s.cur_t);
                e.us(s.pos);
                e.u64(s.dropped);
                e.opt_us(s.overflow_at);
                e.flag(s.has_t);
                e.flag(s.has_aux);
                e.lsb(&s.lsb);
            }
        }
        e.0
    }

    /// Rebuild an accumulator from [`DwellAccumulator::to_state`] bytes.
    pub fn from_state(bytes: &[u8]) -> Result<DwellAccumulator> {
        if bytes.len() < 12 || &bytes[..8] != MAGIC {
            return invalid("not a dwell accumulator state (bad magic bytes)");
        }
        let mut v = [0u8; 4];
        v.copy_from_slice(&bytes[8..12]);
        let version = u32::from_le_bytes(v);
        if version != STATE_VERSION {
            return invalid(format!(
                "dwell accumulator state version {version} is not supported (this build \
                 reads version {STATE_VERSION})"
            ));
        }
        let mut d = Dec { b: &bytes[12..] };
        let acc = match d.u8()? {
            1 => decode_bounds(&mut d)?,
            2 => decode_detect(&mut d)?,
            _ => return corrupt("unknown mode"),
        };
        if !d.b.is_empty() {
            return corrupt("trailing bytes");
        }
        Ok(acc)
    }
}

fn decode_bounds(d: &mut Dec<'_>) -> Result<DwellAccumulator> {
    let k = d.len(16)?;
    let mut bounds = Vec::with_capacity(k);
    for _ in 0..k {
        bounds.push([d.us()?, d.us()?]);
    }
    if check_dwell_bounds(&bounds, usize::MAX).is_err() {
        return corrupt("bounds");
    }
    let DwellAccumulator::Bounds(mut s) = DwellAccumulator::with_bounds(bounds)? else {
        return corrupt("mode");
    };
    for slot in s.done.iter_mut() {
        *slot = match d.u8()? {
            0 => None,
            1 => Some(d.outcome()?),
            _ => return corrupt("bad option"),
        };
    }
    s.open = match d.u8()? {
        0 => None,
        1 => {
            let kk = d.us()?;
            let b = d.build()?;
            if kk >= k || [b.a, b.b] != s.bounds[kk] || s.done[kk].is_some() {
                return corrupt("open dwell");
            }
            Some((kk, b))
        }
        _ => return corrupt("bad option"),
    };
    for v in [&mut s.aux_sum, &mut s.t_first, &mut s.t_last] {
        for x in v.iter_mut() {
            *x = d.f64()?;
        }
    }
    s.first_open = d.us()?;
    s.pos = d.us()?;
    s.has_t = d.flag()?;
    s.has_aux = d.flag()?;
    s.lsb = d.lsb()?;
    // The open dwell is the one the position is inside, with everything before it pushed.
    let inside = (0..k).find(|&j| s.bounds[j][0] < s.pos && s.pos < s.bounds[j][1]);
    let open_ok = match (&s.open, inside) {
        (None, None) => true,
        (Some((kk, b)), Some(j)) => {
            let n = (s.pos - b.a) as u64;
            *kk == j
                && b.cur.count() == n
                && b.edge(b.cum.len()) <= s.pos
                && s.pos < b.edge(b.cum.len() + 1)
                && b.cum
                    .iter()
                    .enumerate()
                    .all(|(i, m)| m.n == (b.edge(i + 1) - b.a) as u64)
        }
        _ => false,
    };
    // Dwells done exactly when the stream has passed them, the first open one in order.
    let consistent = open_ok
        && s.first_open <= k
        && s.bounds
            .iter()
            .zip(&s.done)
            .all(|(&[_, b], o)| o.is_some() == (b <= s.pos))
        && s.order
            .iter()
            .position(|&j| s.bounds[j][1] > s.pos)
            .unwrap_or(k)
            == s.first_open
        && lsb_consistent(&s.lsb, s.pos);
    if !consistent {
        return corrupt("position");
    }
    Ok(DwellAccumulator::Bounds(s))
}

fn decode_detect(d: &mut Dec<'_>) -> Result<DwellAccumulator> {
    let v: [f64; 7] = d.arr()?;
    let noise_var = match d.u8()? {
        0 => None,
        1 => Some(d.arr()?),
        _ => return corrupt("bad option"),
    };
    let settings = DetectorSettings {
        fs: v[0],
        window_s: v[1],
        k: v[2],
        min_dwell_s: v[3],
        trim_s: v[4],
        noise_quantile: v[5],
        block_s: v[6],
        noise_var,
    };
    let DwellAccumulator::Detect(mut s) = DwellAccumulator::with_detector(settings)? else {
        return corrupt("mode");
    };
    let nb = d.len(8 * 16)?;
    for _ in 0..nb {
        s.blocks.push(d.moments()?);
    }
    for _ in 0..nb {
        s.aux_blocks.push(d.f64()?);
    }
    for _ in 0..nb {
        s.t_blocks.push(d.arr()?);
    }
    s.cur = d.seg()?;
    s.cur_bad = d.bool()?;
    s.cur_aux = d.f64()?;
    s.cur_t = d.arr()?;
    s.pos = d.us()?;
    s.dropped = d.u64()?;
    s.overflow_at = d.opt_us()?;
    s.has_t = d.flag()?;
    s.has_aux = d.flag()?;
    s.lsb = d.lsb()?;
    let bl = s.settings.block_len();
    let consistent = s.cur.count() < bl as u64
        && s.blocks.iter().all(|m| m.n == bl as u64)
        && nb
            .checked_mul(bl)
            .and_then(|x| x.checked_add(s.cur.count() as usize))
            == Some(s.pos)
        && lsb_consistent(&s.lsb, s.pos);
    if !consistent {
        return corrupt("position");
    }
    Ok(DwellAccumulator::Detect(s))
}

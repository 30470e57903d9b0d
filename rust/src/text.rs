//! Delimited text recordings, parsed block by block.
//!
//! The layout of a file (delimiter, which columns hold what, where the data start) is decided
//! from its first lines by the caller; this module parses the bulk. Delimited fields are split
//! by the `csv-core` state machine (quoting, CRLF, comment lines, blank lines), runs of spaces
//! and tabs by `split_ascii_whitespace`, and numbers are read by `fast-float2` (correctly
//! rounded, like `strtod`). Only the columns asked for are converted.
//!
//! [`TextStream`] reads a source on a background thread in blocks of whole lines, parses a
//! batch of blocks in parallel (rayon) and hands them over in file order through a bounded
//! channel, so the next blocks are parsed while the caller reduces the previous one. Memory
//! is bounded by the block size times the channel depth, whatever the file's length.

use crate::error::{invalid, out_of_memory, try_grow, CoreError, Result};
use rayon::prelude::*;
use std::io::Read;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender};
use std::sync::Arc;
use std::time::Duration;

/// How the fields of a line are separated.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Delimiter {
    /// Runs of spaces and tabs.
    Whitespace,
    /// One byte (`,`, `;`, `\t`, ...), with CSV quoting.
    Byte(u8),
}

/// How one column is converted to a float.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ColumnKind {
    /// A number, multiplied by `scale` (e.g. 1e-3 for a time column in ms).
    Number {
        /// Factor applied to the value.
        scale: f64,
    },
    /// An ISO-8601 date and time (`2024-03-01T12:00:00.25Z`, space instead of `T`, optional
    /// UTC offset; no offset means UTC), as seconds since the instant `t0_s` s + `t0_ns` ns
    /// after 1970-01-01T00:00:00Z.
    Iso8601 {
        /// Whole seconds of the reference instant since the Unix epoch.
        t0_s: i64,
        /// Nanoseconds of the reference instant (0 ..= 999 999 999).
        t0_ns: i64,
    },
}

/// One column to extract.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Column {
    /// 0-based index among the fields of a row.
    pub index: usize,
    /// Conversion.
    pub kind: ColumnKind,
}

/// Everything the parser needs to know about a file's data rows.
#[derive(Debug, Clone, PartialEq)]
pub struct TextLayout {
    /// Field separator.
    pub delimiter: Delimiter,
    /// Fields per data row (rows with another count are an error).
    pub ncols: usize,
    /// Output groups: each is a list of columns written row-major into one array
    /// (e.g. `[[ax, ay, az], [t], [temperature]]`).
    pub groups: Vec<Vec<Column>>,
    /// Numbers use a decimal comma (`9,81`); not allowed with a `,` delimiter.
    pub decimal_comma: bool,
    /// Lines starting with this byte (after leading blanks) are comments; in whitespace
    /// mode the rest of a line from this byte on is a comment too.
    pub comment: Option<u8>,
    /// Column names (for messages), when the file has a header.
    pub names: Option<Vec<String>>,
    /// Line number (1-based) of the first byte handed to the parser (for messages).
    pub first_line: u64,
    /// Groups whose empty fields read as NaN instead of being an error: a slow channel
    /// (temperature) written on some rows only.
    pub sparse_groups: Vec<usize>,
    /// Skip a row whose first-group fields are all empty (counted in `skipped`): a row of
    /// another sensor in a merged log. Some of them empty is still an error.
    pub skip_empty_rows: bool,
}

impl TextLayout {
    /// Check the layout before any parsing.
    pub fn validate(&self) -> Result<()> {
        if self.ncols == 0 {
            return invalid("text layout: ncols must be at least 1");
        }
        for c in self.groups.iter().flatten() {
            if c.index >= self.ncols {
                return invalid(format!(
                    "text layout: column index {} out of range for {} columns",
                    c.index, self.ncols
                ));
            }
            if let ColumnKind::Number { scale } = c.kind {
                if !scale.is_finite() || scale == 0.0 {
                    return invalid(format!(
                        "text layout: column scale must be finite and non-zero; got {scale}"
                    ));
                }
            }
        }
        if let Some(g) = self.sparse_groups.iter().find(|&&g| g >= self.groups.len()) {
            return invalid(format!(
                "text layout: sparse group {g} out of range for {} groups",
                self.groups.len()
            ));
        }
        if self.decimal_comma && self.delimiter == Delimiter::Byte(b',') {
            return invalid(
                "decimal commas cannot be read from a comma-delimited file (every comma would \
                 be a field separator); use ';' or tabs as the delimiter",
            );
        }
        if let Some(names) = &self.names {
            if names.len() != self.ncols {
                return invalid(format!(
                    "text layout: {} names for {} columns",
                    names.len(),
                    self.ncols
                ));
            }
        }
        Ok(())
    }

    fn column_label(&self, index: usize) -> String {
        match &self.names {
            Some(n) => format!("column {:?}", n[index]),
            None => format!("column {index} (0-based)"),
        }
    }
}

/// Parsed rows of one block.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Block {
    /// One row-major array per layout group (`rows * group.len()` values).
    pub values: Vec<Vec<f64>>,
    /// Data rows in the block.
    pub rows: usize,
    /// Bytes of text the block covered.
    pub bytes: usize,
    /// Line terminators (`\n`) in the block.
    pub lines: u64,
    /// Data rows whose first group equals the previous row's (repeated samples: a sensor
    /// read faster than it updates). Counted within the block.
    pub repeats: u64,
    /// Rows skipped because their first-group fields were all empty
    /// ([`TextLayout::skip_empty_rows`]).
    pub skipped: u64,
    /// Rows left out because they did not parse (the first located by its line in the
    /// block, 0-based, until the reader locates it in the file).
    pub bad: BadRows,
}

/// A bad row, located by its line within the block (0-based).
#[derive(Debug, Clone, PartialEq)]
struct RowError {
    line: u64,
    msg: String,
}

/// Data rows left out because they did not parse: a line cut short or run together (a serial
/// capture's), a field that is not a number. A few are left out, with a note; more than
/// [`BAD_ROWS_FREE`] that are also more than 1 % of the rows are the file's error.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BadRows {
    /// How many rows were left out.
    pub count: u64,
    /// The first of them: its line (from 1 once located in the file) and what was wrong.
    pub first: Option<(u64, String)>,
}

/// Rows that do not parse left out whatever the file's length.
pub const BAD_ROWS_FREE: u64 = 10;

impl BadRows {
    /// Add `other` (rows later in the file, located as these are).
    pub fn add(&mut self, other: &BadRows) {
        self.count += other.count;
        if self.first.is_none() {
            self.first.clone_from(&other.first);
        }
    }

    /// `self` with the first row's line moved by `offset` lines.
    fn shifted(mut self, offset: u64) -> Self {
        if let Some((line, _)) = self.first.as_mut() {
            *line += offset;
        }
        self
    }

    /// The error of a file whose rows that do not parse are too many to leave out beside
    /// `rows` good ones: more than 1 % of all rows, unless they are at most [`BAD_ROWS_FREE`]
    /// and at most a quarter of all rows.
    pub fn check(&self, rows: usize) -> Result<()> {
        let all = rows as u64 + self.count;
        if self.count * 100 <= all || (self.count <= BAD_ROWS_FREE && self.count * 4 <= all) {
            return Ok(());
        }
        let (line, msg) = self.first.clone().unwrap_or_default();
        invalid(format!(
            "line {line}: {msg} ({} of the {all} data rows do not parse; up to \
             {BAD_ROWS_FREE}, or 1 %, would be left out with a note)",
            self.count
        ))
    }
}

type RowResult<T> = std::result::Result<T, RowError>;

fn trim(mut s: &[u8]) -> &[u8] {
    while let [first, rest @ ..] = s {
        if first.is_ascii_whitespace() {
            s = rest;
        } else {
            break;
        }
    }
    while let [rest @ .., last] = s {
        if last.is_ascii_whitespace() {
            s = rest;
        } else {
            break;
        }
    }
    s
}

fn show(s: &[u8]) -> String {
    let t = String::from_utf8_lossy(s);
    if t.chars().count() > 40 {
        let head: String = t.chars().take(40).collect();
        format!("{head:?}...")
    } else {
        format!("{t:?}")
    }
}

/// Days from 1970-01-01 to the civil date `y-m-d` (proleptic Gregorian).
fn days_from_civil(y: i64, m: i64, d: i64) -> i64 {
    let y = if m <= 2 { y - 1 } else { y };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (m + 9) % 12;
    let doy = (153 * mp + 2) / 5 + d - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

fn digits(s: &[u8], n: usize) -> Option<i64> {
    if s.len() < n {
        return None;
    }
    let mut v = 0i64;
    for &c in &s[..n] {
        if !c.is_ascii_digit() {
            return None;
        }
        v = v * 10 + i64::from(c - b'0');
    }
    Some(v)
}

/// Parse an ISO-8601 date and time: `YYYY-MM-DD(T| )hh:mm[:ss[.f...]][Z|±hh[:mm]|±hhmm]`.
///
/// Returns whole seconds since the Unix epoch and nanoseconds (a time without offset is UTC);
/// None when the text is not such a timestamp.
pub fn parse_iso8601(s: &[u8]) -> Option<(i64, i64)> {
    let s = trim(s);
    if s.len() < 16 || s[4] != b'-' || s[7] != b'-' || !matches!(s[10], b'T' | b't' | b' ') {
        return None;
    }
    let (y, mo, d) = (digits(s, 4)?, digits(&s[5..], 2)?, digits(&s[8..], 2)?);
    let leap = y % 4 == 0 && (y % 100 != 0 || y % 400 == 0);
    let month_days = [
        31,
        if leap { 29 } else { 28 },
        31,
        30,
        31,
        30,
        31,
        31,
        30,
        31,
        30,
        31,
    ];
    if !(1..=12).contains(&mo) || !(1..=month_days[(mo - 1) as usize]).contains(&d) {
        return None;
    }
    let (h, mi) = (digits(&s[11..], 2)?, digits(&s[14..], 2)?);
    if s[13] != b':' || h > 24 || mi > 59 {
        return None;
    }
    let mut i = 16;
    let mut sec = 0i64;
    let mut ns = 0i64;
    if i < s.len() && s[i] == b':' {
        sec = digits(&s[i + 1..], 2)?;
        if sec > 60 {
            return None;
        }
        i += 3;
        if i < s.len() && (s[i] == b'.' || s[i] == b',') {
            i += 1;
            let start = i;
            let mut scale = 100_000_000i64;
            while i < s.len() && s[i].is_ascii_digit() {
                ns += i64::from(s[i] - b'0') * scale;
                scale /= 10;
                i += 1;
            }
            if i == start {
                return None;
            }
        }
    }
    let mut offset = 0i64;
    if i < s.len() {
        match s[i] {
            b'Z' | b'z' if i + 1 == s.len() => {}
            b'+' | b'-' => {
                let sign = if s[i] == b'+' { 1 } else { -1 };
                let rest = &s[i + 1..];
                let (oh, om) = match rest.len() {
                    2 => (digits(rest, 2)?, 0),
                    4 => (digits(rest, 2)?, digits(&rest[2..], 2)?),
                    5 if rest[2] == b':' => (digits(rest, 2)?, digits(&rest[3..], 2)?),
                    _ => return None,
                };
                if oh > 23 || om > 59 {
                    return None;
                }
                offset = sign * (oh * 3600 + om * 60);
            }
            _ => return None,
        }
    }
    let secs = days_from_civil(y, mo, d) * 86_400 + h * 3600 + mi * 60 + sec - offset;
    Some((secs, ns))
}

/// Exact powers of ten representable in a double.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// Clinger's fast path for the plain decimals recorders write (`-12.345678`): at most 15
/// digits and no exponent, so the digits form an integer below 2^53 and the value is one
/// correctly rounded division by an exact power of ten, the same double any correct parser
/// gives. None for anything else (the general parser takes it).
#[inline(always)]
fn parse_simple_decimal(f: &[u8]) -> Option<f64> {
    let (neg, digits) = match f.first() {
        Some(b'-') => (true, &f[1..]),
        Some(b'+') => (false, &f[1..]),
        _ => (false, f),
    };
    if digits.is_empty() || digits.len() > 16 {
        return None;
    }
    let mut m: u64 = 0;
    let mut frac: Option<usize> = None;
    let mut nd = 0;
    for (i, &c) in digits.iter().enumerate() {
        match c {
            b'0'..=b'9' => {
                m = m * 10 + u64::from(c - b'0');
                nd += 1;
            }
            b'.' if frac.is_none() => frac = Some(digits.len() - i - 1),
            _ => return None,
        }
    }
    if nd == 0 || nd > 15 {
        return None;
    }
    let v = match frac {
        Some(k) if k > 0 => m as f64 / POW10[k],
        _ => m as f64,
    };
    Some(if neg { -v } else { v })
}

/// One field of the line `l`, from `a` to the delimiter `d` or the end of the line, scanned
/// once: the bytes are split and parsed as a plain decimal in the same loop (the fast path of
/// [`parse_simple_decimal`], the same correctly rounded value). Returns the field's end and
/// its value; None when the field is not a plain decimal (the general parser then takes it).
/// A `\r` ending the line ends the field.
#[inline(always)]
fn scan_field(l: &[u8], a: usize, d: u8) -> (usize, Option<f64>) {
    let n = l.len();
    let mut i = a;
    let neg = match l.get(i) {
        Some(b'-') => {
            i += 1;
            true
        }
        Some(b'+') => {
            i += 1;
            false
        }
        _ => false,
    };
    let mut m: u64 = 0;
    let mut nd = 0usize;
    let mut dot: Option<usize> = None;
    while i < n {
        let c = l[i];
        if c.is_ascii_digit() {
            if nd < 19 {
                m = m * 10 + u64::from(c - b'0');
            }
            nd += 1;
        } else if c == b'.' && dot.is_none() {
            dot = Some(i);
        } else if c == d || (c == b'\r' && i + 1 == n) {
            break;
        } else {
            let end = memchr::memchr(d, &l[i..]).map_or(n, |k| i + k);
            return (end, None);
        }
        i += 1;
    }
    if nd == 0 || nd > 15 {
        return (i, None);
    }
    let v = match dot.map(|p| i - p - 1) {
        Some(k) if k > 0 => m as f64 / POW10[k],
        _ => m as f64,
    };
    (i, Some(if neg { -v } else { v }))
}

const ONES: u64 = 0x0101_0101_0101_0101;

/// Eight bytes of `b` from `p` as a little-endian word (the first byte lowest), if there.
#[inline(always)]
fn load8(b: &[u8], p: usize) -> Option<u64> {
    let s: [u8; 8] = b.get(p..p.checked_add(8)?)?.try_into().ok()?;
    Some(u64::from_le_bytes(s))
}

/// The bytes of `x` (ASCII already xor-ed with `'0'`) that are not digits: their high bit set.
#[inline(always)]
fn non_digits(x: u64) -> u64 {
    (((x & (0x7f * ONES)) + (0x76 * ONES)) | x) & (0x80 * ONES)
}

/// The integer written by the first `n` (1..=8) bytes of `x` (digit values 0..=9, the first
/// byte the most significant): eight digits at once (the SWAR method of fast_float).
#[inline(always)]
fn swar_digits(x: u64, n: usize) -> u64 {
    // The n digits moved to the top bytes; the bytes below become leading zeros.
    let v = x << (8 * (8 - n));
    let v = v.wrapping_mul(10).wrapping_add(v >> 8);
    let m = 0x0000_00ff_0000_00ff;
    let a = (v & m).wrapping_mul(100 + (1_000_000 << 32));
    let b = ((v >> 16) & m).wrapping_mul(1 + (10_000 << 32));
    a.wrapping_add(b) >> 32
}

/// Bit `i` set when `w[i]` is the delimiter `d` or `\n`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn sep_mask64(w: &[u8; 64], d: u8) -> u64 {
    use std::arch::x86_64::{
        __m128i, _mm_cmpeq_epi8, _mm_loadu_si128, _mm_movemask_epi8, _mm_or_si128, _mm_set1_epi8,
    };
    let mut m = 0u64;
    // SAFETY: SSE2 is part of every x86_64 CPU; each `part` holds 16 bytes, which an
    // unaligned load reads exactly.
    unsafe {
        let vd = _mm_set1_epi8(d as i8);
        let vn = _mm_set1_epi8(b'\n' as i8);
        for (k, part) in w.chunks_exact(16).enumerate() {
            let v = _mm_loadu_si128(part.as_ptr().cast::<__m128i>());
            let e = _mm_or_si128(_mm_cmpeq_epi8(v, vd), _mm_cmpeq_epi8(v, vn));
            m |= u64::from(_mm_movemask_epi8(e) as u16) << (16 * k);
        }
    }
    m
}

/// Bit `i` set when `w[i]` is the delimiter `d` or `\n`.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
fn sep_mask64(w: &[u8; 64], d: u8) -> u64 {
    let mut m = 0u64;
    for (i, &c) in w.iter().enumerate() {
        m |= u64::from(c == d || c == b'\n') << i;
    }
    m
}

/// The positions of the delimiter and of `\n` in a block, in order, found 64 bytes at a time
/// (so that finding where a field ends does not wait for the previous field's parse).
struct Seps<'a> {
    buf: &'a [u8],
    d: u8,
    /// Start of the window `mask` describes.
    base: usize,
    /// Separators of the window not yet returned (bit `i`: `buf[base + i]`).
    mask: u64,
}

impl<'a> Seps<'a> {
    fn new(buf: &'a [u8], d: u8, from: usize) -> Self {
        let mut s = Seps {
            buf,
            d,
            base: from,
            mask: 0,
        };
        s.seek(from);
        s
    }

    /// Go on from position `from`.
    fn seek(&mut self, from: usize) {
        self.base = from;
        self.mask = self.window(from);
    }

    fn window(&self, base: usize) -> u64 {
        match self.buf.get(base..base.saturating_add(64)) {
            Some(w) => match <&[u8; 64]>::try_from(w) {
                Ok(w) => sep_mask64(w, self.d),
                Err(_) => 0,
            },
            None => {
                let rest = self.buf.get(base..).unwrap_or_default();
                let mut a = [0u8; 64];
                a[..rest.len()].copy_from_slice(rest);
                // Only the bytes that are there (the padding could equal the delimiter).
                sep_mask64(&a, self.d) & ((1u64 << rest.len()) - 1)
            }
        }
    }

    /// The next separator's position, None at the end of the block.
    #[inline(always)]
    fn next(&mut self) -> Option<usize> {
        while self.mask == 0 {
            self.base += 64;
            if self.base >= self.buf.len() {
                return None;
            }
            self.mask = self.window(self.base);
        }
        let i = self.mask.trailing_zeros() as usize;
        self.mask &= self.mask - 1;
        Some(self.base + i)
    }
}

/// The plain decimal `buf[a..e]` (sign, at most 7 digits, optionally `.` and at most 7 more
/// digits), read eight bytes at a time: the same value as [`scan_field`] (the same integer of
/// digits over the same power of ten). None for anything else, which [`scan_field`] then
/// takes. Needs 17 bytes of `buf` from `a` (None otherwise).
#[inline(always)]
fn parse_span(buf: &[u8], a: usize, e: usize) -> Option<f64> {
    // Branch-free sign (random signs would defeat the branch predictor).
    let c0 = *buf.get(a)?;
    let neg = c0 == b'-';
    let s = a + usize::from(neg | (c0 == b'+'));
    let len = e.checked_sub(s)?;
    let zero = 0x30 * ONES;
    let x = load8(buf, s)? ^ zero;
    let n1 = (non_digits(x).trailing_zeros() / 8) as usize;
    if n1 > 7 {
        return None;
    }
    let (m, n2) = if n1 == len {
        if n1 == 0 {
            return None;
        }
        (swar_digits(x, n1), 0)
    } else {
        // A '.' after the integer digits, then digits only up to the end.
        if n1 > len || len - n1 > 8 || (x >> (8 * n1)) as u8 != b'.' ^ b'0' {
            return None;
        }
        let n2 = len - n1 - 1;
        let xf = load8(buf, s + n1 + 1)? ^ zero;
        if non_digits(xf) & ((1u64 << (8 * n2)) - 1) != 0 {
            return None;
        }
        let nd = n1 + n2;
        let m = if nd == 0 {
            return None;
        } else if nd <= 8 {
            // Both parts in one word (the '.' taken out): one conversion.
            swar_digits((x & ((1u64 << (8 * n1)) - 1)) | (xf << (8 * n1)), nd)
        } else {
            swar_digits(x, n1) * POW10_U64[n2] + swar_digits(xf, n2)
        };
        (m, n2)
    };
    // m < 10^14: exact as an i64 and as a double (the signed conversion is one instruction).
    let mf = m as i64 as f64;
    // mf / 10^n2 >= 0: setting the sign bit negates it (-0.0 for "-0"), without a branch.
    let v = (mf / POW10[n2]).to_bits() | (u64::from(neg) << 63);
    Some(f64::from_bits(v))
}

/// [`parse_span`] with SSE4.1: the field's 16 bytes checked and converted in vector
/// registers (digits found by compare, the '.' dropped and the digits right-aligned by one
/// byte shuffle, converted by multiply-adds), up to 15 digits. The same value: the same
/// integer of digits over the same power of ten.
#[cfg(target_arch = "x86_64")]
mod sse41 {
    use super::POW10;
    use std::arch::x86_64::{
        __m128i, _mm_cmpeq_epi8, _mm_cvtsi128_si64, _mm_loadu_si128, _mm_madd_epi16,
        _mm_maddubs_epi16, _mm_min_epu8, _mm_movemask_epi8, _mm_packus_epi32, _mm_set1_epi8,
        _mm_setr_epi16, _mm_setr_epi8, _mm_shuffle_epi8, _mm_sub_epi8,
    };

    /// `SHUF[n1][nd]`: the shuffle that right-aligns `nd` digits in 16 bytes, taken from the
    /// field's bytes in order but for the byte at `n1` (the '.'); 0x80 gives a zero byte.
    static SHUF: [[[u8; 16]; 16]; 16] = {
        let mut t = [[[0x80u8; 16]; 16]; 16];
        let mut n1 = 0;
        while n1 < 16 {
            let mut nd = 1;
            while nd < 16 {
                let mut i = 0;
                while i < nd {
                    let src = if i < n1 { i } else { i + 1 };
                    t[n1][nd][16 - nd + i] = src as u8;
                    i += 1;
                }
                nd += 1;
            }
            n1 += 1;
        }
        t
    };

    /// The plain decimal `buf[a..e]`: sign, digits with at most one '.', at most 15 digits
    /// and 16 bytes after the sign. Needs 17 bytes of `buf` from `a` (None otherwise).
    ///
    /// # Safety
    /// The CPU must have SSE4.1.
    #[inline]
    #[target_feature(enable = "sse4.1")]
    pub(super) unsafe fn span(buf: &[u8], a: usize, e: usize) -> Option<f64> {
        let c0 = *buf.get(a)?;
        let neg = c0 == b'-';
        let s = a + usize::from(neg | (c0 == b'+'));
        let len = e.checked_sub(s)?;
        let w: &[u8; 16] = buf.get(s..s + 16)?.try_into().ok()?;
        if len == 0 || len > 16 {
            return None;
        }
        // SAFETY: `w` holds 16 bytes, which an unaligned load reads exactly.
        let v = unsafe { _mm_loadu_si128(w.as_ptr().cast::<__m128i>()) };
        let d = _mm_sub_epi8(v, _mm_set1_epi8(b'0' as i8));
        let digit = _mm_movemask_epi8(_mm_cmpeq_epi8(_mm_min_epu8(d, _mm_set1_epi8(9)), d)) as u32;
        let dot = _mm_movemask_epi8(_mm_cmpeq_epi8(v, _mm_set1_epi8(b'.' as i8))) as u32;
        let within = (1u32 << len) - 1;
        let other = !digit & within;
        // Every byte a digit but for at most one '.'.
        if other != dot & within || other & other.wrapping_sub(1) != 0 {
            return None;
        }
        let has_dot = usize::from(other != 0);
        let n1 = (other | (1 << len)).trailing_zeros() as usize;
        let nd = len - has_dot;
        if nd == 0 || nd > 15 {
            return None;
        }
        let n2 = (len - n1).saturating_sub(1);
        let shuf = SHUF.get(n1.min(15))?.get(nd)?;
        // SAFETY: `shuf` holds 16 bytes.
        let mask = unsafe { _mm_loadu_si128(shuf.as_ptr().cast::<__m128i>()) };
        let x = _mm_shuffle_epi8(d, mask);
        let x = _mm_maddubs_epi16(
            x,
            _mm_setr_epi8(10, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1, 10, 1),
        );
        let x = _mm_madd_epi16(x, _mm_setr_epi16(100, 1, 100, 1, 100, 1, 100, 1));
        let x = _mm_packus_epi32(x, x);
        let x = _mm_madd_epi16(x, _mm_setr_epi16(10000, 1, 10000, 1, 0, 0, 0, 0));
        let q = _mm_cvtsi128_si64(x) as u64;
        let m = (q & 0xffff_ffff) * 100_000_000 + (q >> 32);
        // m < 10^15: exact as an i64 and as a double.
        let mf = m as i64 as f64;
        let v = (mf / POW10[n2]).to_bits() | (u64::from(neg) << 63);
        Some(f64::from_bits(v))
    }
}

const POW10_U64: [u64; 8] = [1, 10, 100, 1000, 10_000, 100_000, 1_000_000, 10_000_000];

/// Parse a number field (`decimal_comma`: `,` is the decimal mark).
#[inline]
fn parse_number(field: &[u8], decimal_comma: bool) -> Option<f64> {
    if let Some(v) = parse_simple_decimal(field) {
        return Some(v);
    }
    let mut f = trim(field);
    // A quoted field after blanks (`1, "2"`) keeps its quotes in CSV: drop them here.
    if let [b'"', inner @ .., b'"'] = f {
        f = trim(inner);
    }
    if let Ok(v) = fast_float2::parse::<f64, _>(f) {
        return Some(v);
    }
    if decimal_comma && f.len() <= 64 {
        let mut buf = [0u8; 64];
        for (o, &c) in buf.iter_mut().zip(f) {
            *o = if c == b',' { b'.' } else { c };
        }
        return fast_float2::parse::<f64, _>(&buf[..f.len()]).ok();
    }
    None
}

/// Where one wanted field of a row goes: element `row * k + j` of output group `g`.
#[derive(Debug, Clone, Copy)]
struct Dest {
    g: usize,
    k: usize,
    j: usize,
    kind: ColumnKind,
}

/// A wanted number column of a row stored whole: field `field` goes where `dest` says, times
/// `scale`.
#[derive(Debug, Clone, Copy)]
struct Planned {
    field: usize,
    dest: Dest,
    scale: f64,
}

/// Converts the fields of one row at a time straight into the output groups: preallocated
/// row-major windows (`rows * group.len()` values each), of a block's own arrays or of the
/// final arrays of a whole file.
struct RowSink<'a, 'o> {
    layout: &'a TextLayout,
    /// Per field index: where its value goes and how to convert it.
    want: Vec<Option<Dest>>,
    out: Vec<&'o mut [f64]>,
    /// Width of the first group (repeated samples compare it).
    k0: usize,
    rows: usize,
    repeats: u64,
    /// Rows to read at most (no more than the windows hold).
    max_rows: usize,
    /// The first group of the row last stored (repeated samples).
    prev0: Vec<f64>,
    /// When every wanted column is a number: where each goes, for rows stored whole
    /// ([`RowSink::put_row`]).
    plan: Option<Vec<Planned>>,
    /// Empty first-group fields of the current row, and the first of them.
    empty0: usize,
    first_empty0: usize,
    /// The first empty field of another group in the current row (an error unless the row
    /// is skipped).
    empty_other: Option<usize>,
    /// Rows skipped with all their first-group fields empty.
    skipped: u64,
    /// Rows left out because they did not parse.
    bad: u64,
    first_bad: Option<RowError>,
}

impl<'a, 'o> RowSink<'a, 'o> {
    /// A sink writing into `out` (one window per group of `layout`), at most `max_rows` rows;
    /// the windows hold at least that many rows.
    fn new(layout: &'a TextLayout, out: Vec<&'o mut [f64]>, max_rows: usize) -> Self {
        let mut want = vec![None; layout.ncols];
        for (g, cols) in layout.groups.iter().enumerate() {
            for (j, c) in cols.iter().enumerate() {
                want[c.index] = Some(Dest {
                    g,
                    k: cols.len(),
                    j,
                    kind: c.kind,
                });
            }
        }
        let room = layout
            .groups
            .iter()
            .zip(&out)
            .filter(|(cols, _)| !cols.is_empty())
            .map(|(cols, w)| w.len() / cols.len())
            .min()
            .unwrap_or(usize::MAX);
        let plan = want
            .iter()
            .enumerate()
            .filter_map(|(f, w)| w.map(|d| (f, d)))
            .map(|(field, dest)| match dest.kind {
                ColumnKind::Number { scale } => Some(Planned { field, dest, scale }),
                ColumnKind::Iso8601 { .. } => None,
            })
            .collect();
        RowSink {
            layout,
            want,
            out,
            k0: layout.groups.first().map_or(0, Vec::len),
            rows: 0,
            repeats: 0,
            max_rows: max_rows.min(room),
            prev0: vec![0.0; layout.groups.first().map_or(0, Vec::len)],
            plan,
            empty0: 0,
            first_empty0: 0,
            empty_other: None,
            skipped: 0,
            bad: 0,
            first_bad: None,
        }
    }

    /// Leave out the current row, which did not parse (`e` says why): its values are
    /// overwritten by the next row's, and it is counted for the note.
    #[cold]
    fn reject(&mut self, e: RowError) {
        self.empty0 = 0;
        self.empty_other = None;
        self.bad += 1;
        self.first_bad.get_or_insert(e);
    }

    /// The rows left out, the first located by its line in the block.
    fn bad_rows(&self) -> BadRows {
        BadRows {
            count: self.bad,
            first: self.first_bad.as_ref().map(|e| (e.line, e.msg.clone())),
        }
    }

    /// Store a whole row of parsed fields (`vals[i]` is field `i`; as many as the rows
    /// have), all wanted columns being numbers (`plan`), and count it.
    #[inline(always)]
    fn put_row(&mut self, plan: &[Planned], vals: &[f64]) {
        let r = self.rows;
        // Whether the first group repeats the previous row's (kept in `prev0`).
        let mut same = r > 0 && self.k0 > 0;
        for p in plan {
            let Dest { g, k, j, .. } = p.dest;
            let scale = p.scale;
            let v = vals.get(p.field).copied().unwrap_or_default();
            let v = if scale == 1.0 { v } else { v * scale };
            if g == 0 {
                if let Some(p) = self.prev0.get_mut(j) {
                    same &= *p == v;
                    *p = v;
                }
            }
            if let Some(x) = self.out.get_mut(g).and_then(|w| w.get_mut(r * k + j)) {
                *x = v;
            }
        }
        self.repeats += u64::from(same);
        self.rows += 1;
    }

    fn full(&self) -> bool {
        self.rows >= self.max_rows
    }

    /// Store `v` where `d` says, in the current row (which is within the windows: rows are
    /// only started while the sink is not full).
    #[inline(always)]
    fn put(&mut self, d: Dest, v: f64) {
        if let Some(x) = self
            .out
            .get_mut(d.g)
            .and_then(|w| w.get_mut(self.rows * d.k + d.j))
        {
            *x = v;
        }
    }

    /// Convert field `index` of the current row (ignored unless it is wanted).
    #[inline(always)]
    fn field(&mut self, index: usize, f: &[u8], line: u64) -> RowResult<()> {
        let Some(&Some(d)) = self.want.get(index) else {
            return Ok(());
        };
        let v = match d.kind {
            ColumnKind::Number { scale } => match parse_number(f, self.layout.decimal_comma) {
                Some(v) if scale == 1.0 => v,
                Some(v) => v * scale,
                None => return self.missing(d, index, f, line),
            },
            ColumnKind::Iso8601 { t0_s, t0_ns } => match parse_iso8601(f) {
                Some((s, ns)) => (s - t0_s) as f64 + (ns - t0_ns) as f64 * 1e-9,
                None => return self.missing(d, index, f, line),
            },
        };
        self.put(d, v);
        Ok(())
    }

    /// A wanted field that did not parse: NaN when it is empty and its group is sparse,
    /// else the error naming it.
    #[cold]
    fn missing(&mut self, d: Dest, index: usize, f: &[u8], line: u64) -> RowResult<()> {
        if trim(f).is_empty() {
            if self.layout.sparse_groups.contains(&d.g) {
                self.put(d, f64::NAN);
                return Ok(());
            }
            if self.layout.skip_empty_rows {
                // Judged at the row's end: all of the first group empty skips the row (and
                // whatever else it left empty); otherwise an empty field is an error.
                if d.g == 0 {
                    if self.empty0 == 0 {
                        self.first_empty0 = index;
                    }
                    self.empty0 += 1;
                } else {
                    self.empty_other.get_or_insert(index);
                }
                self.put(d, f64::NAN);
                return Ok(());
            }
        }
        Err(self.bad(index, f, line))
    }

    /// Store field `index`, already parsed as the plain decimal `v` (its text `f` is used
    /// only by a column that is not a number).
    #[inline(always)]
    fn value(&mut self, index: usize, v: f64, f: &[u8], line: u64) -> RowResult<()> {
        self.value_in(index, v, f, 0, f.len(), line)
    }

    /// [`RowSink::value`] for the field `text[a..e]` (sliced only when it is needed).
    #[inline(always)]
    fn value_in(
        &mut self,
        index: usize,
        v: f64,
        text: &[u8],
        a: usize,
        e: usize,
        line: u64,
    ) -> RowResult<()> {
        match self.want.get(index) {
            Some(&Some(d)) => match d.kind {
                ColumnKind::Number { scale } => {
                    self.put(d, if scale == 1.0 { v } else { v * scale });
                    Ok(())
                }
                _ => self.field(index, text.get(a..e).unwrap_or_default(), line),
            },
            _ => Ok(()),
        }
    }

    #[cold]
    fn bad(&self, index: usize, f: &[u8], line: u64) -> RowError {
        let lay = self.layout;
        let f = trim(f);
        let what = match self.want[index].map(|w| w.kind) {
            Some(ColumnKind::Iso8601 { .. }) => {
                format!("{} is not an ISO-8601 date and time", show(f))
            }
            _ if f.is_empty() => "is empty (missing value)".to_string(),
            _ => {
                let hint = if !lay.decimal_comma && f.contains(&b',') {
                    " (a decimal comma? those are read only when the first data rows use \
                     them too)"
                } else {
                    ""
                };
                format!("{} is not a number{hint}", show(f))
            }
        };
        RowError {
            line,
            msg: format!("{}: {what}", lay.column_label(index)),
        }
    }

    /// Finish the current row, which had `nfields` fields.
    #[inline(always)]
    fn end_row(&mut self, nfields: usize, line: u64) -> RowResult<()> {
        if nfields != self.layout.ncols {
            return Err(self.ragged(nfields, line));
        }
        let other = self.empty_other.take();
        if self.empty0 > 0 {
            let all = self.empty0 == self.k0;
            self.empty0 = 0;
            if !all {
                return Err(self.bad(self.first_empty0, b"", line));
            }
            self.skipped += 1;
            return Ok(());
        }
        if let Some(index) = other {
            return Err(self.bad(index, b"", line));
        }
        self.count_row();
        Ok(())
    }

    /// Count the row just stored, and whether it repeats the one before.
    #[inline(always)]
    fn count_row(&mut self) {
        let (r, k) = (self.rows, self.k0);
        if let Some(cur) = self.out.first().and_then(|w| w.get(r * k..(r + 1) * k)) {
            // Element by element: a few values, which memcmp/memcpy calls would cost more for.
            let mut same = r > 0 && k > 0;
            for (p, &c) in self.prev0.iter_mut().zip(cur) {
                same &= *p == c;
                *p = c;
            }
            self.repeats += u64::from(same);
        }
        self.rows += 1;
    }

    #[cold]
    fn ragged(&self, nfields: usize, line: u64) -> RowError {
        let ncols = self.layout.ncols;
        RowError {
            line,
            msg: format!(
                "{nfields} field{} where the data rows have {ncols}",
                if nfields == 1 { "" } else { "s" },
            ),
        }
    }
}

/// True when the line starting at `buf[pos..]` holds no data: blank, or a comment.
#[inline(always)]
fn skip_line(buf: &[u8], pos: usize, comment: Option<u8>) -> bool {
    match buf.get(pos) {
        Some(&c) if c.is_ascii_digit() || c == b'-' || c == b'.' || c == b'+' => false,
        _ => {
            let mut i = pos;
            while i < buf.len() && matches!(buf[i], b' ' | b'\t' | b'\r' | 0x0b | 0x0c) {
                i += 1;
            }
            i >= buf.len() || buf[i] == b'\n' || comment.is_some_and(|c| buf[i] == c)
        }
    }
}

/// The fields of one line `l` (no `\n`) split on the delimiter `d`, each scanned once.
#[inline]
/// A line that does not parse is left out ([`RowSink::reject`]).
fn scan_line(l: &[u8], d: u8, line: u64, sink: &mut RowSink<'_, '_>) {
    if let Err(e) = scan_fields(l, d, line, sink) {
        sink.reject(e);
    }
}

fn scan_fields(l: &[u8], d: u8, line: u64, sink: &mut RowSink<'_, '_>) -> RowResult<()> {
    let mut nf = 0;
    let mut a = 0;
    loop {
        let (e, v) = scan_field(l, a, d);
        match v {
            Some(v) => sink.value(nf, v, &l[a..e], line)?,
            None => sink.field(nf, &l[a..e], line)?,
        }
        nf += 1;
        if e >= l.len() || l[e] != d {
            break;
        }
        a = e + 1;
    }
    sink.end_row(nf, line)
}

/// The fields of one line `l` (no `\n`, comment cut off) split on runs of blanks.
fn scan_blank_separated(l: &[u8], line: u64, sink: &mut RowSink<'_, '_>) -> RowResult<()> {
    let mut nf = 0;
    let mut i = 0;
    while i < l.len() {
        while i < l.len() && l[i].is_ascii_whitespace() {
            i += 1;
        }
        if i == l.len() {
            break;
        }
        let a = i;
        while i < l.len() && !l[i].is_ascii_whitespace() {
            i += 1;
        }
        sink.field(nf, &l[a..i], line)?;
        nf += 1;
    }
    if nf > 0 {
        sink.end_row(nf, line)?;
    }
    Ok(())
}

/// Rows split on a delimiter byte, or on runs of spaces and tabs (`delim` None), for text
/// without quote characters (quoted fields go through csv-core), a line at a time. Blank lines
/// and comment lines are skipped; in whitespace mode a comment byte also ends a line's data.
/// (Delimited text takes [`parse_seps`]; this line-by-line form is its reference in the tests.)
fn parse_plain(
    buf: &[u8],
    delim: Option<u8>,
    sink: &mut RowSink<'_, '_>,
) -> RowResult<(usize, u64)> {
    let comment = sink.layout.comment;
    let mut pos = 0;
    let mut line = 0u64;
    while pos < buf.len() && !sink.full() {
        let end = memchr::memchr(b'\n', &buf[pos..]).map_or(buf.len(), |i| pos + i);
        if !skip_line(buf, pos, comment) {
            let l = &buf[pos..end];
            match delim {
                Some(d) => scan_line(l, d, line, sink),
                None => {
                    let l = match comment.and_then(|c| memchr::memchr(c, l)) {
                        Some(i) => &l[..i],
                        None => l,
                    };
                    if let Err(e) = scan_blank_separated(l, line, sink) {
                        sink.reject(e);
                    }
                }
            }
        }
        if end < buf.len() {
            line += 1;
            pos = end + 1;
        } else {
            pos = end;
        }
    }
    Ok((pos, line))
}

/// Rows split on the delimiter byte `d`, for text without quote characters: the same rows,
/// values and errors as [`parse_plain`], faster. The separators are found 64 bytes at a
/// time ([`Seps`]) and plain decimals read eight bytes at a time ([`parse_span`]); any other
/// field goes through [`scan_field`] and the general parser, and a line that does not start
/// like a number (blank, comment, leading blanks) through [`scan_line`].
fn parse_seps(buf: &[u8], d: u8, sink: &mut RowSink<'_, '_>) -> RowResult<(usize, u64)> {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("sse4.1") {
        // SAFETY: the CPU has SSE4.1.
        return unsafe { parse_seps_sse41(buf, d, sink) };
    }
    parse_seps_with::<false>(buf, d, sink)
}

/// Fields per row that [`fast_row`] takes.
const ROW_MAX: usize = 16;

/// The line at `pos` when it is plain decimals separated by the delimiter and ended by `\n`
/// (or `\r\n`), each parsed into `vals`: the next line's start and the field count. Only the
/// fields of `wanted` (bit `i`: field `i`) are parsed: the others may hold anything. None
/// for anything else (the general scan then takes the line).
#[inline(always)]
fn fast_row<const SSE: bool>(
    buf: &[u8],
    pos: usize,
    fast_end: usize,
    wanted: u32,
    seps: &mut Seps<'_>,
    vals: &mut [f64; ROW_MAX],
) -> Option<(usize, usize)> {
    let mut a = pos;
    let mut f = 0;
    loop {
        if a >= fast_end || f >= ROW_MAX {
            return None;
        }
        let e = seps.next()?;
        let nl = *buf.get(e)? == b'\n';
        let fe = if nl && e > a && buf[e - 1] == b'\r' {
            e - 1
        } else {
            e
        };
        if wanted >> f & 1 == 1 {
            vals[f] = span::<SSE>(buf, a, fe)?;
        }
        f += 1;
        if nl {
            return Some((e + 1, f));
        }
        a = e + 1;
    }
}

/// [`parse_seps`] compiled for SSE4.1.
///
/// # Safety
/// The CPU must have SSE4.1.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "sse4.1")]
unsafe fn parse_seps_sse41(
    buf: &[u8],
    d: u8,
    sink: &mut RowSink<'_, '_>,
) -> RowResult<(usize, u64)> {
    parse_seps_with::<true>(buf, d, sink)
}

/// The one plain decimal `buf[a..e]`, by [`sse41::span`] when `SSE` (the caller runs with
/// SSE4.1), else by [`parse_span`].
#[inline(always)]
fn span<const SSE: bool>(buf: &[u8], a: usize, e: usize) -> Option<f64> {
    #[cfg(target_arch = "x86_64")]
    if SSE {
        // SAFETY: `SSE` is true only in code compiled for and run on SSE4.1 CPUs.
        return unsafe { sse41::span(buf, a, e) };
    }
    parse_span(buf, a, e)
}

#[inline(always)]
fn parse_seps_with<const SSE: bool>(
    buf: &[u8],
    d: u8,
    sink: &mut RowSink<'_, '_>,
) -> RowResult<(usize, u64)> {
    let n = buf.len();
    let comment = sink.layout.comment;
    // parse_span reads up to 17 bytes from a field's start.
    let fast_end = n.saturating_sub(17);
    let mut seps = Seps::new(buf, d, 0);
    let mut pos = 0;
    let mut line = 0u64;
    // Rows of numbers only, stored whole: fields parsed into `vals` first.
    let plan = sink.plan.take().filter(|_| sink.layout.ncols <= ROW_MAX);
    let mut vals = [0.0f64; ROW_MAX];
    let wanted = sink
        .want
        .iter()
        .take(ROW_MAX)
        .enumerate()
        .filter(|(_, w)| w.is_some())
        .fold(0u32, |m, (i, _)| m | 1 << i);
    while pos < n && !sink.full() {
        if let Some(plan) = &plan {
            if let Some(next) = fast_row::<SSE>(buf, pos, fast_end, wanted, &mut seps, &mut vals) {
                if next.1 == sink.layout.ncols {
                    sink.put_row(plan, &vals);
                    line += 1;
                    pos = next.0;
                    continue;
                }
            }
            // Not a plain row: the general scan below takes it from its start.
            seps.seek(pos);
        }
        if !matches!(buf[pos], b'0'..=b'9' | b'-' | b'+' | b'.') {
            let end = memchr::memchr(b'\n', &buf[pos..]).map_or(n, |i| pos + i);
            if !skip_line(buf, pos, comment) {
                scan_line(&buf[pos..end], d, line, sink);
            }
            if end < n {
                line += 1;
                pos = end + 1;
                seps.seek(pos);
            } else {
                pos = n;
            }
            continue;
        }
        let mut nf = 0;
        let mut a = pos;
        let mut failed = None;
        let end = loop {
            let e = seps.next().unwrap_or(n);
            let eol = e >= n || buf[e] == b'\n';
            // A `\r` before the `\n` ends the last field.
            let fe = if eol && e > a && buf[e - 1] == b'\r' {
                e - 1
            } else {
                e
            };
            let stored = match if a < fast_end {
                span::<SSE>(buf, a, fe)
            } else {
                None
            } {
                Some(v) => sink.value_in(nf, v, buf, a, fe, line),
                None => {
                    // As scan_line would see it: up to the line's end, or past this delimiter.
                    let l = &buf[..if eol { e } else { e + 1 }];
                    let (fe, v) = scan_field(l, a, d);
                    match v {
                        Some(v) => sink.value(nf, v, &l[a..fe], line),
                        None => sink.field(nf, &l[a..fe], line),
                    }
                }
            };
            if let Err(err) = stored {
                // The row is left out: on to the next line.
                failed = Some(err);
                let end = if eol {
                    e
                } else {
                    memchr::memchr(b'\n', &buf[e..]).map_or(n, |i| e + i)
                };
                seps.seek((end + 1).min(n));
                break end;
            }
            nf += 1;
            if eol {
                break e;
            }
            a = e + 1;
        };
        if let Err(e) = failed.map_or_else(|| sink.end_row(nf, line), Err) {
            sink.reject(e);
        }
        if end < n {
            line += 1;
            pos = end + 1;
        } else {
            pos = n;
        }
    }
    Ok((pos, line))
}

fn parse_delimited(buf: &[u8], delim: u8, sink: &mut RowSink<'_, '_>) -> RowResult<(usize, u64)> {
    use csv_core::{ReadRecordResult, ReaderBuilder};
    let mut rdr = ReaderBuilder::new()
        .delimiter(delim)
        .comment(sink.layout.comment)
        .build();
    let comment = sink.layout.comment;
    let mut out = vec![0u8; 4096];
    let mut ends = vec![0usize; sink.layout.ncols.max(1) + 4];
    let mut input = buf;
    let mut consumed = 0usize;
    // A record may need several calls when `out`/`ends` fill up.
    let mut nout = 0usize;
    let mut nend = 0usize;
    let mut at_eof = false;
    loop {
        if sink.full() {
            break;
        }
        let (res, nin, o, e) = rdr.read_record(input, &mut out[nout..], &mut ends[nend..]);
        // `read_record` with empty input signals the end of the data.
        let last = if nin > 0 { input[nin - 1] } else { 0 };
        input = &input[nin..];
        consumed += nin;
        nout += o;
        nend += e;
        match res {
            ReadRecordResult::InputEmpty => {
                if at_eof {
                    break;
                }
                if input.is_empty() {
                    at_eof = true;
                }
            }
            ReadRecordResult::OutputFull => {
                let n = out.len();
                out.resize(2 * n, 0);
            }
            ReadRecordResult::OutputEndsFull => {
                let n = ends.len();
                ends.resize(2 * n, 0);
            }
            ReadRecordResult::Record => {
                // `line()` counts the `\n` consumed so far (from 1); the record's own
                // terminator is among them unless it ended at a `\r` or the end of input.
                let line = rdr.line() - 1 - u64::from(last == b'\n');
                let (o, e) = (&out[..nout], &ends[..nend]);
                let field = |i: usize| -> &[u8] {
                    let a = if i == 0 { 0 } else { e[i - 1] };
                    &o[a..e[i]]
                };
                let blank = nend == 1 && {
                    let f = trim(field(0));
                    f.is_empty() || comment.is_some_and(|c| f[0] == c)
                };
                if !blank {
                    let row = (0..nend)
                        .try_for_each(|i| sink.field(i, field(i), line))
                        .and_then(|()| sink.end_row(nend, line));
                    if let Err(e) = row {
                        sink.reject(e);
                    }
                }
                nout = 0;
                nend = 0;
            }
            ReadRecordResult::End => break,
        }
    }
    let lines = memchr::memchr_iter(b'\n', &buf[..consumed]).count() as u64;
    Ok((consumed, lines))
}

/// Parse the data rows of `buf` (whole lines) into a [`Block`].
///
/// At most `max_rows` rows are read (then `bytes` and `lines` cover only what was read).
/// A row with the wrong number of fields, or a requested field that does not parse, is an
/// error naming its line (`layout.first_line` is the line of `buf[0]`).
pub fn parse_block(buf: &[u8], layout: &TextLayout, max_rows: Option<usize>) -> Result<Block> {
    layout.validate()?;
    let mut b = parse_block_rel(buf, layout, max_rows).map_err(|e| locate(e, layout.first_line))?;
    b.bad = std::mem::take(&mut b.bad).shifted(layout.first_line);
    b.bad.check(b.rows)?;
    Ok(b)
}

fn locate(e: RowError, first_line: u64) -> CoreError {
    CoreError::InvalidInput(format!("line {}: {}", first_line + e.line, e.msg))
}

fn parse_block_rel(buf: &[u8], layout: &TextLayout, max_rows: Option<usize>) -> RowResult<Block> {
    let bound = row_bound(buf);
    let cap = bound.rows.min(max_rows.unwrap_or(usize::MAX));
    let mut values: Vec<Vec<f64>> = layout
        .groups
        .iter()
        .map(|g| vec![0.0; cap * g.len()])
        .collect();
    let mut sink = RowSink::new(
        layout,
        values.iter_mut().map(Vec::as_mut_slice).collect(),
        cap,
    );
    let (bytes, lines) = parse_rows(buf, bound.quoted, &mut sink)?;
    let (rows, repeats, skipped, bad) = (sink.rows, sink.repeats, sink.skipped, sink.bad_rows());
    for (v, g) in values.iter_mut().zip(&layout.groups) {
        v.truncate(rows * g.len());
    }
    Ok(Block {
        values,
        rows,
        bytes,
        lines,
        repeats,
        skipped,
        bad,
    })
}

/// At most this many data rows are in `buf`: its lines (a data row ends a line, the last
/// maybe without `\n`), and with quotes (csv-core also ends a record at a lone `\r`) its
/// `\r` too.
fn row_bound(buf: &[u8]) -> Bound {
    let lines = memchr::memchr_iter(b'\n', buf).count();
    let mut rows = lines + usize::from(buf.last() != Some(&b'\n'));
    let quoted = memchr::memchr(b'"', buf).is_some();
    if quoted {
        rows += memchr::memchr_iter(b'\r', buf).count();
    }
    Bound {
        lines: lines as u64,
        rows,
        quoted,
    }
}

/// What [`row_bound`] found in a block.
#[derive(Debug, Clone, Copy)]
struct Bound {
    /// `\n` in the block.
    lines: u64,
    /// At most this many data rows.
    rows: usize,
    /// The block holds a quote character (csv-core parses it).
    quoted: bool,
}

/// The rows of `buf` (whole lines; `quoted` when it holds a quote character) into `sink`:
/// `(bytes, lines)` consumed.
fn parse_rows(buf: &[u8], quoted: bool, sink: &mut RowSink<'_, '_>) -> RowResult<(usize, u64)> {
    match sink.layout.delimiter {
        Delimiter::Whitespace => parse_plain(buf, None, sink),
        // csv-core reads quoted fields; text without a quote character splits the same way
        // on the delimiter byte alone, which is what the plain path does, faster.
        Delimiter::Byte(d) if quoted => parse_delimited(buf, d, sink),
        Delimiter::Byte(d) => parse_seps(buf, d, sink),
    }
}

/// A regular file mapped into memory, read from a byte offset on.
///
/// The pages are the operating system's file cache: reading costs no copy, and memory that
/// counts against the process is only what the parsed arrays take. The map is read-only. A
/// file that another program shortens while it is mapped makes the reading of the lost pages
/// fail with SIGBUS (the process ends); growing or rewriting it is harmless (the map keeps
/// the length it had when opened). Callers that read files being truncated use a
/// [`Source::Reader`] instead.
#[derive(Clone)]
pub struct MappedText {
    map: Arc<memmap2::Mmap>,
    start: usize,
}

impl std::fmt::Debug for MappedText {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "MappedText({} bytes)", self.bytes().len())
    }
}

impl MappedText {
    /// Map `file` from byte `offset` on: None when it is not a regular file or holds nothing
    /// past `offset` (read those with a reader).
    pub fn open(file: &std::fs::File, offset: u64) -> std::io::Result<Option<MappedText>> {
        let meta = file.metadata()?;
        if !meta.is_file() || meta.len() <= offset {
            return Ok(None);
        }
        let Ok(start) = usize::try_from(offset) else {
            return Ok(None);
        };
        // SAFETY: a read-only private map of a regular file; the bytes are only read. The
        // one hazard is another process truncating the file while it is mapped (SIGBUS on
        // the lost pages), documented on the type.
        let map = unsafe { memmap2::MmapOptions::new().map(file)? };
        // No MADV_SEQUENTIAL: it keeps the pages read from counting as used, so that a file
        // read again soon (the next command on the same recording) may have left the cache.
        Ok(Some(MappedText {
            map: Arc::new(map),
            start,
        }))
    }

    /// The text from the offset on.
    pub fn bytes(&self) -> &[u8] {
        self.map.get(self.start..).unwrap_or_default()
    }

    /// Unmap the pages of `range` (of [`MappedText::bytes`]) once they have been read: they
    /// stay in the file cache, but no longer count in this process's resident memory, which
    /// so stays bounded however long the file. Reading them again maps them again.
    fn release(&self, range: std::ops::Range<usize>) {
        let len = range.end.saturating_sub(range.start);
        if len == 0 {
            return;
        }
        // SAFETY: the map is private and read-only and never written, so dropping its pages
        // loses nothing: a later read maps the file's page again (MADV_DONTNEED on a file
        // map). No reference into the map is invalidated; the memory stays mapped.
        let _ = unsafe {
            self.map.unchecked_advise_range(
                memmap2::UncheckedAdvice::DontNeed,
                self.start + range.start,
                len,
            )
        };
    }
}

/// Where the text comes from.
pub enum Source {
    /// Any reader (a file positioned at the first data byte, a pipe, stdin, bytes in memory).
    Reader(Box<dyn Read + Send>),
    /// A regular file mapped into memory (no copy; blocks are parsed where they lie).
    Map(MappedText),
}

/// Options of a [`TextStream`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StreamOptions {
    /// Target bytes per block (whole lines; a longer line makes a longer block).
    pub block_bytes: usize,
    /// Blocks parsed in parallel per batch (0: the rayon pool size).
    pub parallel: usize,
}

impl Default for StreamOptions {
    fn default() -> Self {
        StreamOptions {
            block_bytes: 4 << 20,
            parallel: 0,
        }
    }
}

/// What [`TextStream::next_block`] found.
#[derive(Debug)]
pub enum Next {
    /// The next block in file order.
    Block(Block),
    /// The end of the data.
    Done,
    /// Nothing yet within the timeout (the reader is still busy).
    Pending,
}

/// What the reader thread hands over for one block: the receiving end of its parse job.
type Job = Receiver<std::result::Result<Block, JobError>>;

enum JobError {
    /// A bad row, by its line within the block.
    Row(RowError),
    /// The source could not be read.
    Read(CoreError),
}

/// Blocks of a text source, read on a background thread and parsed ahead on the rayon pool
/// (several blocks at once), handed over in file order.
pub struct TextStream {
    jobs: Receiver<Job>,
    current: Option<Job>,
    line: u64,
    stop: Arc<AtomicBool>,
    done: bool,
    /// Data rows so far, and the rows left out (which more than 1 % of them make an error).
    rows: usize,
    bad: BadRows,
}

impl TextStream {
    /// Start reading `source` (positioned at the first data byte) with `layout`.
    pub fn new(source: Source, layout: TextLayout, opts: StreamOptions) -> Result<Self> {
        layout.validate()?;
        let par = if opts.parallel == 0 {
            rayon::current_num_threads().max(1)
        } else {
            opts.parallel
        };
        let block_bytes = opts.block_bytes.max(1);
        // Blocks in flight: up to 2 par + 1 parse jobs queued or running (the reader keeps
        // reading while the oldest block is handed over, so no parser waits for it).
        let (tx, jobs) = sync_channel(2 * par + 1);
        let stop = Arc::new(AtomicBool::new(false));
        let stop2 = Arc::clone(&stop);
        let first_line = layout.first_line;
        let layout = Arc::new(layout);
        let run = move || match source {
            Source::Reader(reader) => read_loop(reader, layout, block_bytes, &tx, &stop2),
            Source::Map(map) => map_loop(map, layout, block_bytes, &tx, &stop2),
        };
        std::thread::Builder::new()
            .name("accelcal-text".into())
            .spawn(run)
            .map_err(|e| CoreError::InvalidInput(format!("cannot start the reader thread: {e}")))?;
        Ok(TextStream {
            jobs,
            current: None,
            line: first_line,
            stop,
            done: false,
            rows: 0,
            bad: BadRows::default(),
        })
    }

    /// The next block, waiting at most `timeout`.
    pub fn next_block(&mut self, timeout: Duration) -> Result<Next> {
        if self.done {
            return Ok(Next::Done);
        }
        let job = match self.current.take() {
            Some(j) => j,
            None => match self.jobs.recv_timeout(timeout) {
                Ok(j) => j,
                Err(RecvTimeoutError::Timeout) => return Ok(Next::Pending),
                Err(RecvTimeoutError::Disconnected) => {
                    self.done = true;
                    // The whole file read: are the rows left out few enough?
                    self.bad.check(self.rows)?;
                    return Ok(Next::Done);
                }
            },
        };
        match job.recv_timeout(timeout) {
            Ok(Ok(mut b)) => {
                b.bad = std::mem::take(&mut b.bad).shifted(self.line);
                self.line += b.lines;
                self.rows += b.rows;
                self.bad.add(&b.bad);
                Ok(Next::Block(b))
            }
            Ok(Err(e)) => {
                self.done = true;
                Err(match e {
                    JobError::Row(r) => locate(r, self.line),
                    JobError::Read(e) => e,
                })
            }
            Err(RecvTimeoutError::Timeout) => {
                self.current = Some(job);
                Ok(Next::Pending)
            }
            Err(RecvTimeoutError::Disconnected) => {
                self.done = true;
                invalid("the text reader stopped unexpectedly")
            }
        }
    }
}

impl Iterator for TextStream {
    type Item = Result<Block>;

    fn next(&mut self) -> Option<Result<Block>> {
        loop {
            match self.next_block(Duration::from_secs(3600)) {
                Ok(Next::Block(b)) => return Some(Ok(b)),
                Ok(Next::Done) => return None,
                Ok(Next::Pending) => continue,
                Err(e) => return Some(Err(e)),
            }
        }
    }
}

impl Drop for TextStream {
    fn drop(&mut self) {
        // The reader thread stops at its next read or hand-over; it owns nothing of ours.
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Read until `buf` holds at least `target` bytes or the source ends; true at the end.
/// The bytes go straight into `buf`'s spare capacity (no intermediate chunk, no zeroing).
fn fill(src: &mut dyn Read, buf: &mut Vec<u8>, target: usize) -> std::io::Result<bool> {
    while buf.len() < target {
        let want = (target - buf.len()) as u64;
        match src.take(want).read_to_end(buf) {
            Ok(0) => return Ok(true),
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(false)
}

fn read_loop(
    mut src: Box<dyn Read + Send>,
    layout: Arc<TextLayout>,
    block_bytes: usize,
    tx: &SyncSender<Job>,
    stop: &AtomicBool,
) {
    let mut carry: Vec<u8> = Vec::new();
    let mut eof = false;
    while !eof {
        if stop.load(Ordering::Relaxed) {
            return;
        }
        let mut buf = std::mem::take(&mut carry);
        let (jtx, jrx) = sync_channel(1);
        let what = "the text reader's buffer";
        if let Err(e) = try_grow(&mut buf, block_bytes + (1 << 16), what) {
            let _ = jtx.send(Err(JobError::Read(e)));
            let _ = tx.send(jrx);
            return;
        }
        let mut target = block_bytes.max(buf.len() + 1);
        loop {
            // A line longer than a block doubles the target: room first (running out of
            // memory is an error, not an abort).
            let more = target.saturating_sub(buf.len());
            let grown = try_grow(&mut buf, more, what);
            match grown.and_then(|()| {
                fill(src.as_mut(), &mut buf, target).map_err(|e| {
                    if e.kind() == std::io::ErrorKind::OutOfMemory {
                        out_of_memory(what, target)
                    } else {
                        CoreError::InvalidInput(format!("cannot read the data: {e}"))
                    }
                })
            }) {
                Ok(true) => {
                    eof = true;
                    break;
                }
                Ok(false) => {}
                Err(e) => {
                    let _ = jtx.send(Err(JobError::Read(e)));
                    let _ = tx.send(jrx);
                    return;
                }
            }
            match memchr::memrchr(b'\n', &buf) {
                Some(p) => {
                    carry = buf[p + 1..].to_vec();
                    buf.truncate(p + 1);
                    break;
                }
                None => target = 2 * buf.len(), // one line longer than a block
            }
        }
        if buf.is_empty() {
            break;
        }
        let lay = Arc::clone(&layout);
        rayon::spawn(move || {
            let r = parse_block_rel(&buf, &lay, None).map_err(JobError::Row);
            let _ = jtx.send(r);
        });
        if tx.send(jrx).is_err() {
            return;
        }
    }
}

/// The end of the block of whole lines that starts at `a`: after the last `\n` within
/// `target` bytes, or after the first `\n` past them (a line longer than a block), or the end.
fn block_end(data: &[u8], a: usize, target: usize) -> usize {
    let b = a.saturating_add(target.max(1)).min(data.len());
    if b == data.len() {
        return b;
    }
    match memchr::memrchr(b'\n', &data[a..b]) {
        Some(i) => a + i + 1,
        None => memchr::memchr(b'\n', &data[b..]).map_or(data.len(), |i| b + i + 1),
    }
}

/// [`read_loop`] for a mapped file: blocks are cut where they lie, nothing is copied.
fn map_loop(
    map: MappedText,
    layout: Arc<TextLayout>,
    block_bytes: usize,
    tx: &SyncSender<Job>,
    stop: &AtomicBool,
) {
    let n = map.bytes().len();
    let mut a = 0;
    while a < n {
        if stop.load(Ordering::Relaxed) {
            return;
        }
        let b = block_end(map.bytes(), a, block_bytes);
        let (jtx, jrx) = sync_channel(1);
        let (lay, m) = (Arc::clone(&layout), map.clone());
        rayon::spawn(move || {
            let r = parse_block_rel(&m.bytes()[a..b], &lay, None).map_err(JobError::Row);
            m.release(a..b);
            let _ = jtx.send(r);
        });
        if tx.send(jrx).is_err() {
            return;
        }
        a = b;
    }
}

/// Rows as delimited text: per row the `lead` value (e.g. time, when given) and then the `k`
/// values of `values` (row-major), each in the shortest form that reads back to the same
/// float64 (ryu), separated by `delim`, one row per line. Numbers never need quoting.
/// Rows are formatted in parallel; the output is the same whatever the thread count.
pub fn format_rows(lead: Option<&[f64]>, values: &[f64], k: usize, delim: u8) -> Result<Vec<u8>> {
    if k == 0 || !values.len().is_multiple_of(k) {
        return invalid(format!(
            "format_rows: {} values do not make rows of {k}",
            values.len()
        ));
    }
    let rows = values.len() / k;
    if let Some(l) = lead {
        if l.len() != rows {
            return invalid(format!(
                "format_rows: {} lead values for {rows} rows",
                l.len()
            ));
        }
    }
    const PART: usize = 16_384;
    let parts: Vec<Vec<u8>> = (0..rows.div_ceil(PART))
        .into_par_iter()
        .map(|p| {
            let (a, b) = (p * PART, ((p + 1) * PART).min(rows));
            let mut out = Vec::with_capacity((b - a) * (k + 1) * 20);
            let mut fmt = ryu::Buffer::new();
            let mut put = |out: &mut Vec<u8>, v: f64| {
                if v.is_finite() {
                    out.extend_from_slice(fmt.format_finite(v).as_bytes());
                } else if v.is_nan() {
                    out.extend_from_slice(b"nan");
                } else if v > 0.0 {
                    out.extend_from_slice(b"inf");
                } else {
                    out.extend_from_slice(b"-inf");
                }
            };
            for i in a..b {
                if let Some(l) = lead {
                    put(&mut out, l[i]);
                    out.push(delim);
                }
                for j in 0..k {
                    if j > 0 {
                        out.push(delim);
                    }
                    put(&mut out, values[i * k + j]);
                }
                out.push(b'\n');
            }
            out
        })
        .collect();
    Ok(parts.concat())
}

/// A whole source parsed into one array per group (rows in file order).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Collected {
    /// One row-major array per group.
    pub values: Vec<Vec<f64>>,
    /// Data rows.
    pub rows: usize,
    /// Bytes of text read.
    pub bytes: usize,
    /// Rows repeating the previous row's first group.
    pub repeats: u64,
    /// Rows skipped with all their first-group fields empty.
    pub skipped: u64,
    /// Rows left out because they did not parse (the first located in the file).
    pub bad: BadRows,
}

impl Collected {
    /// Empty, with room for about `rows_hint` rows ([`CoreError::OutOfMemory`] when that
    /// room cannot be had).
    pub fn with_capacity(layout: &TextLayout, rows_hint: usize) -> Result<Self> {
        let mut values = Vec::with_capacity(layout.groups.len());
        for g in &layout.groups {
            let mut v = Vec::new();
            try_grow(
                &mut v,
                rows_hint.saturating_mul(g.len()),
                "the samples read",
            )?;
            values.push(v);
        }
        Ok(Collected {
            values,
            ..Collected::default()
        })
    }

    /// Append a block ([`CoreError::OutOfMemory`] when the arrays cannot grow; nothing
    /// appended then).
    pub fn push(&mut self, b: &Block) -> Result<()> {
        if self.values.len() < b.values.len() {
            self.values.resize(b.values.len(), Vec::new());
        }
        for (dst, src) in self.values.iter_mut().zip(&b.values) {
            try_grow(dst, src.len(), "the samples read")?;
        }
        for (dst, src) in self.values.iter_mut().zip(&b.values) {
            dst.extend_from_slice(src);
        }
        self.rows += b.rows;
        self.bytes += b.bytes;
        self.repeats += b.repeats;
        self.skipped += b.skipped;
        self.bad.add(&b.bad);
        Ok(())
    }
}

/// How far a whole-source read ([`read_all_with`]) has got, and a way to stop it: shared
/// with another thread that reports progress and watches for Ctrl-C.
#[derive(Debug, Default)]
pub struct Progress {
    /// Data rows parsed so far.
    pub rows: AtomicUsize,
    /// Bytes of text parsed so far.
    pub bytes: AtomicUsize,
    /// Set to stop the read (it then fails with "stopped").
    pub stop: AtomicBool,
}

/// Parse a whole source (one pass, blocks in parallel).
pub fn read_all(source: Source, layout: TextLayout, opts: StreamOptions) -> Result<Collected> {
    read_all_with(source, layout, opts, 0, &Progress::default())
}

/// [`read_all`], reporting to and stoppable through `progress`.
///
/// A mapped file is parsed in chunks of whole lines on the rayon pool, each chunk straight
/// into its place in the final arrays (its rows are counted first); any other source is
/// read as a [`TextStream`] and its blocks appended to arrays sized for `rows_hint` rows
/// (an estimate; they grow past it).
pub fn read_all_with(
    source: Source,
    layout: TextLayout,
    opts: StreamOptions,
    rows_hint: usize,
    progress: &Progress,
) -> Result<Collected> {
    layout.validate()?;
    if let Source::Map(m) = &source {
        return read_mapped(m, &layout, opts.block_bytes, progress);
    }
    let mut out = Collected::with_capacity(&layout, rows_hint)?;
    let mut stream = TextStream::new(source, layout, opts)?;
    loop {
        // Waiting a little at a time: a stop is seen even while a pipe sends nothing.
        let next = stream.next_block(Duration::from_millis(50))?;
        if progress.stop.load(Ordering::Relaxed) {
            return invalid("stopped");
        }
        match next {
            Next::Block(b) => {
                out.push(&b)?;
                progress.rows.store(out.rows, Ordering::Relaxed);
                progress.bytes.store(out.bytes, Ordering::Relaxed);
            }
            Next::Done => return Ok(out),
            Next::Pending => {}
        }
    }
}

/// Fault in the whole pages of `win` at once (`MADV_POPULATE_WRITE`, Linux 5.14+): one call
/// instead of a page fault per 4 KiB as the parser writes; the pages are zero either way.
/// Where the kernel refuses, the parser's writes fault them in as before.
fn populate(win: &[f64]) {
    #[cfg(target_os = "linux")]
    {
        const MADV_POPULATE_WRITE: libc::c_int = 23;
        const PAGE: usize = 4096;
        let a = win.as_ptr() as usize;
        let b = a + std::mem::size_of_val(win);
        let (a, b) = (a.div_ceil(PAGE) * PAGE, b / PAGE * PAGE);
        if b > a {
            // SAFETY: [a, b) lies inside `win`, memory this process owns and is about to
            // write; populating only maps its pages in (their contents stay zero).
            unsafe {
                libc::madvise(a as *mut libc::c_void, b - a, MADV_POPULATE_WRITE);
            }
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = win;
}

/// `n` zeros, allocated zeroed (pages untouched until written, as `vec![0.0; n]` does), or
/// [`CoreError::OutOfMemory`] when `n` values cannot be had (a plain `vec!` would abort).
fn zeroed(n: usize, what: &str) -> Result<Vec<f64>> {
    if n == 0 {
        return Ok(Vec::new());
    }
    let bytes = n.saturating_mul(std::mem::size_of::<f64>());
    let layout = std::alloc::Layout::array::<f64>(n).map_err(|_| out_of_memory(what, bytes))?;
    // SAFETY: `layout` has a non-zero size; the pointer, if not null, is an allocation of the
    // global allocator with the layout a `Vec<f64>` of capacity `n` has, and all its bytes are
    // zero, a valid f64 (0.0).
    unsafe {
        let p = std::alloc::alloc_zeroed(layout).cast::<f64>();
        if p.is_null() {
            return Err(out_of_memory(what, bytes));
        }
        Ok(Vec::from_raw_parts(p, n, n))
    }
}

/// The whole text `data` parsed in chunks of about `chunk` bytes (whole lines), in parallel,
/// straight into the final arrays.
///
/// A first parallel pass counts each chunk's lines, a bound on its rows (a data row ends a
/// line; with quotes, csv-core also ends records at a lone `\r`, so `\r` count too there);
/// each chunk then writes into its own window of arrays allocated once. Chunks with fewer
/// rows than lines (blank lines, comments) are closed up at the end. A bad row is named by
/// its line in the file: the lines of the chunks before it are known.
fn read_mapped(
    map: &MappedText,
    layout: &TextLayout,
    chunk: usize,
    progress: &Progress,
) -> Result<Collected> {
    let data = map.bytes();
    let mut ranges = Vec::new();
    let mut a = 0;
    while a < data.len() {
        let b = block_end(data, a, chunk);
        ranges.push(a..b);
        a = b;
    }
    // Lines per chunk, and the room its rows may need.
    // The parse pass unmaps the pages it has read. (The counting pass leaves them mapped:
    // unmapping them there too would only map them again right after.)
    let counts: Vec<Bound> = ranges
        .par_iter()
        .map(|r| row_bound(&data[r.clone()]))
        .collect();
    let total: usize = counts.iter().map(|c| c.rows).sum();
    let widths: Vec<usize> = layout.groups.iter().map(Vec::len).collect();
    // Zeroed allocations this large come straight from the kernel: pages are only touched
    // (and counted) when written.
    let mut values: Vec<Vec<f64>> = Vec::with_capacity(widths.len());
    for &k in &widths {
        values.push(zeroed(total.saturating_mul(k), "the samples read")?);
    }
    let mut windows: Vec<Vec<&mut [f64]>> = counts.iter().map(|_| Vec::new()).collect();
    for (col, &k) in values.iter_mut().zip(&widths) {
        let mut rest: &mut [f64] = col;
        for (w, c) in windows.iter_mut().zip(&counts) {
            let (head, tail) = std::mem::take(&mut rest).split_at_mut(c.rows * k);
            w.push(head);
            rest = tail;
        }
    }
    let results: Vec<std::result::Result<(usize, u64, u64, BadRows), JobError>> = ranges
        .par_iter()
        .zip(windows.into_par_iter())
        .zip(counts.par_iter())
        .map(|((r, w), bound)| {
            if progress.stop.load(Ordering::Relaxed) {
                return Err(JobError::Read(CoreError::InvalidInput("stopped".into())));
            }
            let c = &data[r.clone()];
            for win in &w {
                populate(win);
            }
            let mut sink = RowSink::new(layout, w, bound.rows);
            // A bad row is located below, once the lines before this chunk are known.
            let parsed = parse_rows(c, bound.quoted, &mut sink);
            map.release(r.clone());
            let (bytes, _) = parsed.map_err(JobError::Row)?;
            if bytes != c.len() {
                return Err(JobError::Read(CoreError::InvalidInput(
                    "the text reader found more rows than lines (internal error)".into(),
                )));
            }
            progress.rows.fetch_add(sink.rows, Ordering::Relaxed);
            progress.bytes.fetch_add(bytes, Ordering::Relaxed);
            Ok((sink.rows, sink.repeats, sink.skipped, sink.bad_rows()))
        })
        .collect();
    // The first error in file order, located by line; the rows left out, the first located.
    let mut line = layout.first_line;
    let mut bad = BadRows::default();
    for (res, c) in results.iter().zip(&counts) {
        match res {
            Err(JobError::Row(e)) => return Err(locate(e.clone(), line)),
            Err(JobError::Read(e)) => return Err(e.clone()),
            Ok((_, _, _, b)) => bad.add(&b.clone().shifted(line)),
        }
        line += c.lines;
    }
    // Close up the gaps left by chunks with fewer rows than room, counting repeated samples
    // across chunk boundaries too.
    let k0 = widths.first().copied().unwrap_or(0);
    let mut rows = 0usize;
    let mut repeats = 0u64;
    let mut skipped = 0u64;
    let mut off = 0usize;
    for (res, c) in results.iter().zip(&counts) {
        let (n, rep, skip) = match res {
            Ok((n, rep, skip, _)) => (*n, *rep, *skip),
            Err(_) => (0, 0, 0),
        };
        skipped += skip;
        if n > 0 && rows > 0 && k0 > 0 {
            let first = &values[0][off * k0..(off + 1) * k0];
            if *first == values[0][(rows - 1) * k0..rows * k0] {
                repeats += 1;
            }
        }
        if off != rows {
            for (col, &k) in values.iter_mut().zip(&widths) {
                col.copy_within(off * k..(off + n) * k, rows * k);
            }
        }
        rows += n;
        repeats += rep;
        off += c.rows;
    }
    for (col, &k) in values.iter_mut().zip(&widths) {
        col.truncate(rows * k);
    }
    bad.check(rows)?;
    Ok(Collected {
        values,
        rows,
        bytes: data.len(),
        repeats,
        skipped,
        bad,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dwell::{DetectorSettings, DwellAccumulator};
    use ndarray::{Array2, ArrayView2};

    use crate::test_rng::unit as lcg;

    fn num(i: usize) -> Column {
        Column {
            index: i,
            kind: ColumnKind::Number { scale: 1.0 },
        }
    }

    fn layout(delimiter: Delimiter, ncols: usize, groups: Vec<Vec<Column>>) -> TextLayout {
        TextLayout {
            delimiter,
            ncols,
            groups,
            decimal_comma: false,
            comment: Some(b'#'),
            names: None,
            first_line: 1,
            sparse_groups: Vec::new(),
            skip_empty_rows: false,
        }
    }

    fn source(text: &str) -> Source {
        Source::Reader(Box::new(std::io::Cursor::new(text.as_bytes().to_vec())))
    }

    fn all(text: &str, lay: &TextLayout, block: usize) -> Result<Collected> {
        read_all(
            source(text),
            lay.clone(),
            StreamOptions {
                block_bytes: block,
                parallel: 3,
            },
        )
    }

    /// Rows of `n` random values, with the independent `str::parse` result.
    fn generate(rows: usize, ncols: usize, seed: u64) -> (Vec<Vec<String>>, Vec<Vec<f64>>) {
        let mut s = seed;
        let mut text = Vec::new();
        let mut vals = Vec::new();
        for i in 0..rows {
            let mut tr = Vec::new();
            let mut vr = Vec::new();
            for c in 0..ncols {
                let u = lcg(&mut s);
                let t = match (i + c) % 5 {
                    0 => format!("{}", (u * 70000.0).round() - 35000.0),
                    1 => format!("{:.17e}", (u - 0.5) * 1e-3),
                    2 => format!("{}", 9.80665 + u),
                    3 => format!("{:.3}", -u * 12.0),
                    _ => format!("{:+.6E}", u * 1e6),
                };
                vr.push(t.parse::<f64>().unwrap());
                tr.push(t);
            }
            text.push(tr);
            vals.push(vr);
        }
        (text, vals)
    }

    #[test]
    fn parity_with_str_parse_for_every_delimiter_and_block_size() {
        let (text, vals) = generate(2000, 5, 42);
        for (d, sep) in [
            (Delimiter::Byte(b','), ","),
            (Delimiter::Byte(b';'), ";"),
            (Delimiter::Byte(b'\t'), "\t"),
            (Delimiter::Whitespace, "  \t "),
            (Delimiter::Byte(b','), " , "),
        ] {
            for (eol, quoted) in [("\n", false), ("\r\n", false), ("\n", true), ("\r\n", true)] {
                if quoted && d == Delimiter::Whitespace {
                    continue;
                }
                // Quoted fields (every 3rd row) send the blocks through csv-core.
                let mut s: String = text
                    .iter()
                    .enumerate()
                    .map(|(i, r)| {
                        if quoted && i % 3 == 0 {
                            r.iter()
                                .map(|f| format!("\"{f}\""))
                                .collect::<Vec<_>>()
                                .join(sep)
                                + eol
                        } else {
                            r.join(sep) + eol
                        }
                    })
                    .collect::<Vec<_>>()
                    .concat();
                s.pop(); // no trailing newline on the last row
                if eol == "\r\n" {
                    s.pop();
                }
                let lay = layout(d, 5, vec![vec![num(3), num(1), num(4)], vec![num(0)]]);
                for block in [1, 97, 4096, 1 << 20] {
                    let c = all(&s, &lay, block).unwrap();
                    assert_eq!(c.rows, 2000);
                    let want: Vec<f64> = vals.iter().flat_map(|r| [r[3], r[1], r[4]]).collect();
                    assert_eq!(c.values[0], want, "{sep:?} {eol:?} {block}");
                    let t: Vec<f64> = vals.iter().map(|r| r[0]).collect();
                    assert_eq!(c.values[1], t);
                    assert_eq!(c.bytes, s.len());
                }
            }
        }
    }

    #[test]
    fn fast_path_decimals_equal_the_general_parser_bit_for_bit() {
        let mut s = 77u64;
        let mut n = 0;
        for i in 0..400_000 {
            let int_digits = (lcg(&mut s) * 9.0) as usize;
            let frac_digits = (lcg(&mut s) * 12.0) as usize;
            let mut t = String::new();
            match i % 3 {
                0 => t.push('-'),
                1 => t.push('+'),
                _ => {}
            }
            for _ in 0..int_digits {
                t.push(char::from(b'0' + (lcg(&mut s) * 10.0) as u8));
            }
            if frac_digits > 0 || i % 7 == 0 {
                t.push('.');
            }
            for _ in 0..frac_digits {
                t.push(char::from(b'0' + (lcg(&mut s) * 10.0) as u8));
            }
            let fast = parse_simple_decimal(t.as_bytes());
            let general = fast_float2::parse::<f64, _>(t.as_bytes()).ok();
            let std = t.parse::<f64>().ok();
            if let Some(v) = fast {
                n += 1;
                assert_eq!(Some(v.to_bits()), general.map(f64::to_bits), "{t}");
                assert_eq!(Some(v.to_bits()), std.map(f64::to_bits), "{t}");
            }
            assert_eq!(
                parse_number(t.as_bytes(), false).map(f64::to_bits),
                std.map(f64::to_bits),
                "{t}"
            );
        }
        assert!(n > 300_000);
        for t in [
            "1e5",
            " 1",
            "1.2.3",
            "nan",
            "inf",
            "-",
            ".",
            "1234567890123456.5",
        ] {
            assert_eq!(parse_simple_decimal(t.as_bytes()), None, "{t}");
        }
    }

    #[test]
    fn one_pass_field_scan_equals_split_then_parse() {
        // Lines of random plain and non-plain fields: scan_field gives the same field bounds
        // as splitting on the delimiter, and, when it parses, the value parse_number gives.
        let pieces = [
            "1",
            "-2.5",
            "+3.25",
            ".5",
            "7.",
            "",
            "-",
            " 4",
            "1e3",
            "nan",
            "1.2.3",
            "12345678901234567",
            "0.000123456789012",
            "9,5",
            "\"6\"",
            "-0.0",
            "x",
        ];
        let mut s = 5u64;
        for d in [b',', b';', b'\t', b'|'] {
            for _ in 0..20_000 {
                let k = 1 + (lcg(&mut s) * 5.0) as usize;
                let fields: Vec<&str> = (0..k)
                    .map(|_| pieces[(lcg(&mut s) * pieces.len() as f64) as usize])
                    .filter(|f| !f.as_bytes().contains(&d))
                    .collect();
                if fields.is_empty() {
                    continue;
                }
                let mut line = fields.join(std::str::from_utf8(&[d]).unwrap());
                let cr = lcg(&mut s) < 0.3;
                if cr {
                    line.push('\r');
                }
                let l = line.as_bytes();
                let mut a = 0;
                for (j, f) in fields.iter().enumerate() {
                    let (e, v) = scan_field(l, a, d);
                    let last = j + 1 == fields.len();
                    // A field the scan does not parse keeps a line-ending `\r` (as when
                    // split on the delimiter): the general parser trims it.
                    let text = if last && cr && v.is_none() && e == l.len() {
                        &l[a..e - 1]
                    } else {
                        &l[a..e]
                    };
                    assert_eq!(text, f.as_bytes(), "{line:?} field {j}");
                    if let Some(v) = v {
                        let want = parse_number(f.as_bytes(), false).map(f64::to_bits);
                        assert_eq!(Some(v.to_bits()), want, "{line:?} field {j}");
                    }
                    if last {
                        assert!(e == l.len() || (cr && e + 1 == l.len()), "{line:?}");
                    } else {
                        assert_eq!(l[e], d);
                        a = e + 1;
                    }
                }
            }
        }
    }

    #[test]
    fn comments_blank_lines_quotes_and_bom() {
        let s =
            "\u{feff}1,2,3\n\n# a comment\n  # indented comment\n\"4\",\" 5 \",6\n   \n7,8,9 \n";
        let lay = layout(Delimiter::Byte(b','), 3, vec![vec![num(0), num(1), num(2)]]);
        let c = all(s, &lay, 1 << 20).unwrap();
        assert_eq!(c.values[0], vec![1., 2., 3., 4., 5., 6., 7., 8., 9.]);
        let w = "1 2 3 # inline\n# full line\n\n4\t5 6\n";
        let lay = layout(Delimiter::Whitespace, 3, vec![vec![num(0), num(1), num(2)]]);
        let c = all(w, &lay, 1 << 20).unwrap();
        assert_eq!(c.values[0], vec![1., 2., 3., 4., 5., 6.]);
    }

    #[test]
    fn sparse_groups_read_empty_fields_as_nan_and_the_others_stay_strict() {
        // t, ax, ay, az, temperature written every third row; every parser path (plain rows,
        // the general scan of a row with an empty field, quoted CSV) and several block sizes.
        let mut s = String::new();
        let mut want = Vec::new();
        for i in 0..300 {
            if i % 3 == 0 {
                s += &format!("{i},1,2,3,{}.5\n", 20 + i);
                want.push(20.5 + f64::from(i));
            } else {
                s += &format!("{i},1,2,3,\n");
                want.push(f64::NAN);
            }
        }
        let mut lay = layout(
            Delimiter::Byte(b','),
            5,
            vec![vec![num(1), num(2), num(3)], vec![num(0)], vec![num(4)]],
        );
        let e = all(&s, &lay, 64).unwrap_err().to_string();
        assert!(
            e.starts_with(
                "line 2: column 4 (0-based): is empty (missing value) (200 of the 300 data \
                 rows do not parse"
            ),
            "{e}"
        );
        lay.sparse_groups = vec![2];
        let quoted = s.replace("1,2,3", "\"1\",2,3");
        for (text, block) in [(&s, 64), (&s, 1 << 20), (&quoted, 100)] {
            let c = all(text, &lay, block).unwrap();
            assert_eq!(c.rows, 300);
            let same = c.values[2]
                .iter()
                .zip(&want)
                .all(|(a, b)| a == b || (a.is_nan() && b.is_nan()));
            assert!(same, "block {block}");
        }
        // A row with an empty accelerometer field does not parse: left out, and named.
        let bad = s.clone() + "300,1,,3,20\n";
        let c = all(&bad, &lay, 64).unwrap();
        assert_eq!(c.rows, 300);
        assert_eq!(
            c.bad,
            BadRows {
                count: 1,
                first: Some((301, "column 2 (0-based): is empty (missing value)".into()))
            }
        );
        lay.sparse_groups = vec![3];
        assert!(lay.validate().is_err());
    }

    #[test]
    fn rows_of_another_sensor_are_skipped_and_counted() {
        // t, ax, ay, az, gx: accelerometer and gyroscope rows interleaved.
        let mut s = String::new();
        for i in 0..400 {
            s += &format!("{i},{i},2,3,\n{i}.5,,,,7\n");
        }
        let mut lay = layout(
            Delimiter::Byte(b','),
            5,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        let e = all(&s, &lay, 64).unwrap_err().to_string();
        assert!(
            e.starts_with("line 2: column 1 (0-based): is empty (missing value) (400 of the"),
            "{e}"
        );
        lay.skip_empty_rows = true;
        let quoted = s.replace(",2,3,", ",\"2\",3,");
        for (text, block) in [(&s, 64), (&s, 1 << 20), (&quoted, 100)] {
            let c = all(text, &lay, block).unwrap();
            assert_eq!((c.rows, c.skipped), (400, 400), "block {block}");
            let x: Vec<f64> = c.values[0].chunks(3).map(|r| r[0]).collect();
            assert_eq!(x, (0..400).map(f64::from).collect::<Vec<_>>());
            assert_eq!(c.values[1], x);
        }
        let b = parse_block(s.as_bytes(), &lay, None).unwrap();
        assert_eq!((b.rows, b.skipped), (400, 400));
        // Some of the accelerometer fields empty: a row that does not parse, naming the first
        // empty field.
        let bad = s.clone() + "400,400,,,\n";
        let c = all(&bad, &lay, 64).unwrap();
        assert_eq!((c.rows, c.skipped, c.bad.count), (400, 400, 1));
        assert_eq!(
            c.bad.first,
            Some((801, "column 2 (0-based): is empty (missing value)".into()))
        );
        // A skipped row may leave its time empty too; a kept row may not.
        let no_time: String = (0..400).map(|i| format!("{i},{i},2,3,\n,,,,7\n")).collect();
        let c = all(&no_time, &lay, 64).unwrap();
        assert_eq!((c.rows, c.skipped, c.bad.count), (400, 400, 0));
        let bad = s.clone() + ",1,2,3,\n";
        let c = all(&bad, &lay, 64).unwrap();
        assert_eq!(
            c.bad.first,
            Some((801, "column 0 (0-based): is empty (missing value)".into()))
        );
    }

    #[test]
    fn bad_rows_name_their_line() {
        let mut s = String::new();
        for i in 0..500 {
            s += &format!("{i},1,2,3\n");
            if i == 10 {
                s += "\n# comment\n";
            }
        }
        // Row 0 is line 7; a blank line and a comment come after row 10, so row i >= 11 is
        // line i + 9 and the bad row 500 is line 509.
        let mut bad = s.clone();
        bad += "500,1,x,3\n501,1,2,3\n";
        let mut lay = layout(
            Delimiter::Byte(b','),
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        lay.first_line = 7;
        let first = |msg: &str| Some((509, msg.to_string()));
        let x = "column 2 (0-based): \"x\" is not a number";
        for block in [16, 300, 1 << 20] {
            // One bad row of 502 is left out (the next row is read), and named.
            let c = all(&bad, &lay, block).unwrap();
            assert_eq!((c.rows, c.bad.count), (501, 1), "block {block}");
            assert_eq!(c.bad.first, first(x), "block {block}");
            assert_eq!(c.values[1].last(), Some(&501.0), "block {block}");
            // Eleven bad rows of 511 (2 %) are the file's error, naming the first.
            let many = s.clone() + &"500,1,x,3\n".repeat(11);
            let e = all(&many, &lay, block).unwrap_err().to_string();
            assert_eq!(
                e,
                format!(
                    "line 509: {x} (11 of the 511 data rows do not parse; up to 10, or 1 %, \
                     would be left out with a note)"
                ),
                "block {block}"
            );
        }
        let ragged = s.clone() + "1,2,3\n";
        let c = all(&ragged, &lay, 64).unwrap();
        assert_eq!(c.bad.first, first("3 fields where the data rows have 4"));
        let mut crlf = bad.replace('\n', "\r\n");
        crlf.truncate(crlf.len() - 2);
        assert_eq!(all(&crlf, &lay, 100).unwrap().bad.first, first(x));
        let ws = bad.replace(',', " ");
        lay.delimiter = Delimiter::Whitespace;
        lay.names = Some(vec!["t".into(), "ax".into(), "ay".into(), "az".into()]);
        let c = all(&ws, &lay, 50).unwrap();
        assert_eq!(c.bad.first, first("column \"ay\": \"x\" is not a number"));
        // A file of bad rows only (or mostly) is an error, however short.
        let empty = "1,,3\n".to_string();
        let lay3 = layout(Delimiter::Byte(b','), 3, vec![vec![num(0), num(1), num(2)]]);
        let e = all(&empty, &lay3, 50).unwrap_err().to_string();
        assert!(
            e.starts_with("line 1: column 1 (0-based): is empty (missing value) (1 of the 1"),
            "{e}"
        );
        let e = all("1,2,3\n1,,3\n1,2,3\n", &lay3, 50)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("line 2: column 1"), "{e}");
        assert_eq!(
            all("1,2,3\n1,,3\n1,2,3\n1,2,3\n", &lay3, 50).unwrap().rows,
            3
        );
    }

    #[test]
    fn decimal_comma_and_iso_timestamps() {
        let s = "2024-03-01T12:00:00Z;9,5;-0,25;1e-3\n2024-03-01 12:00:00.010+01:00;1;2;3\n\
                 2024-02-29T23:59:59.5;4,0;5;6\n";
        let t0 = parse_iso8601(b"2024-03-01T12:00:00Z").unwrap();
        assert_eq!(t0, (1_709_294_400, 0));
        let mut lay = layout(
            Delimiter::Byte(b';'),
            4,
            vec![
                vec![num(1), num(2), num(3)],
                vec![Column {
                    index: 0,
                    kind: ColumnKind::Iso8601 {
                        t0_s: t0.0,
                        t0_ns: t0.1,
                    },
                }],
            ],
        );
        lay.decimal_comma = true;
        let c = all(s, &lay, 1 << 20).unwrap();
        assert_eq!(c.values[0], vec![9.5, -0.25, 1e-3, 1., 2., 3., 4., 5., 6.]);
        let t = &c.values[1];
        assert_eq!(t[0], 0.0);
        assert!((t[1] - (-3600.0 + 0.01)).abs() < 1e-9, "{}", t[1]);
        assert_eq!(t[2], -12.0 * 3600.0 - 0.5);
        for bad in [
            "2024-13-01T00:00:00",
            "2023-02-29T00:00:00",
            "2024-03-01",
            "12:00:00",
            "2024-03-01T12:00:00+5",
        ] {
            assert_eq!(parse_iso8601(bad.as_bytes()), None, "{bad}");
        }
        // Against a known epoch: 2000-01-01T00:00:00Z = 946684800.
        assert_eq!(
            parse_iso8601(b"2000-01-01T00:00:00"),
            Some((946_684_800, 0))
        );
        assert_eq!(
            parse_iso8601(b"1969-12-31T23:59:59.999999999Z"),
            Some((-1, 999_999_999))
        );
        let comma = layout(Delimiter::Byte(b','), 3, vec![vec![num(0)]]);
        let mut dc = comma.clone();
        dc.decimal_comma = true;
        assert!(dc.validate().is_err());
        let nodc = layout(Delimiter::Byte(b';'), 2, vec![vec![num(0), num(1)]]);
        let e = all("1,5;2\n", &nodc, 64).unwrap_err().to_string();
        assert!(e.contains("decimal comma"), "{e}");
        let c = all("1;2\n1,5;2\n3;4\n5;6\n", &nodc, 64).unwrap();
        assert!(c.bad.first.unwrap().1.contains("decimal comma"));
    }

    #[test]
    fn repeated_samples_are_counted() {
        let mut s = String::new();
        for i in 0..400 {
            let v = i / 4; // each sample repeated 4 times
            s += &format!("{},{},1,2\n", i, v);
        }
        let lay = layout(Delimiter::Byte(b','), 4, vec![vec![num(1), num(2), num(3)]]);
        let c = all(&s, &lay, 1 << 20).unwrap();
        assert_eq!(c.repeats, 300);
    }

    #[test]
    fn head_parse_stops_after_max_rows() {
        let s = "1 2\n3 4\n5 6\nbad row here\n";
        let lay = layout(Delimiter::Whitespace, 2, vec![vec![num(0), num(1)]]);
        let b = parse_block(s.as_bytes(), &lay, Some(3)).unwrap();
        assert_eq!(b.rows, 3);
        assert_eq!(b.values[0], vec![1., 2., 3., 4., 5., 6.]);
        assert_eq!(b.bytes, 12);
        assert_eq!(b.lines, 3);
    }

    #[test]
    fn streamed_text_feeds_the_dwell_accumulator_like_one_shot() {
        // Five dwells at 100 Hz, written as text with 4 significant digits and a time column.
        let fs = 100.0;
        let mut s = 9u64;
        let mut text = String::new();
        let levels = [0.0, 1.0, -1.0, 2.0, 0.5];
        let mut n = 0;
        for (i, &l) in levels.iter().enumerate() {
            for j in 0..700 {
                let r = if j < 500 {
                    [
                        l + 0.01 * lcg(&mut s),
                        0.01 * lcg(&mut s),
                        9.8 + 0.01 * lcg(&mut s),
                    ]
                } else {
                    let f = (j - 500) as f64 / 200.0;
                    let next = levels.get(i + 1).copied().unwrap_or(l);
                    [l + f * (next - l), 0.3 * (f * 6.3).sin(), 9.8]
                };
                text += &format!("{:.3} {:.5} {:.5} {:.5}\n", n as f64 / fs, r[0], r[1], r[2]);
                n += 1;
            }
        }
        let lay = layout(
            Delimiter::Whitespace,
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        let whole = all(&text, &lay, 1 << 24).unwrap();
        let x = Array2::from_shape_vec((whole.rows, 3), whole.values[0].clone()).unwrap();
        let mut one = DwellAccumulator::with_detector(DetectorSettings::new(fs)).unwrap();
        one.push(&x.view(), Some(&whole.values[1]), None).unwrap();
        let one = one.finish().unwrap();
        let mut acc = DwellAccumulator::with_detector(DetectorSettings::new(fs)).unwrap();
        let stream = TextStream::new(
            source(&text),
            lay,
            StreamOptions {
                block_bytes: 1000,
                parallel: 2,
            },
        )
        .unwrap();
        let mut blocks = 0;
        for b in stream {
            let b = b.unwrap();
            let v = ArrayView2::from_shape((b.rows, 3), &b.values[0]).unwrap();
            acc.push(&v, Some(&b.values[1]), None).unwrap();
            blocks += 1;
        }
        assert!(blocks > 100);
        let streamed = acc.finish().unwrap();
        assert_eq!(streamed, one);
        assert_eq!(streamed.bounds.len(), 5);
    }

    #[test]
    fn formatted_rows_read_back_bit_for_bit() {
        let mut s = 5u64;
        let vals: Vec<f64> = (0..3000)
            .map(|i| match i % 4 {
                0 => (lcg(&mut s) - 0.5) * 1e-9,
                1 => 9.80665 + lcg(&mut s),
                2 => -(lcg(&mut s) * 1e300),
                _ => (lcg(&mut s) * 1000.0).round(),
            })
            .collect();
        let t: Vec<f64> = (0..1000).map(|i| i as f64 / 3.0).collect();
        let text = format_rows(Some(&t), &vals, 3, b',').unwrap();
        let lay = layout(
            Delimiter::Byte(b','),
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        let c = all(std::str::from_utf8(&text).unwrap(), &lay, 777).unwrap();
        assert_eq!(c.values[0], vals);
        assert_eq!(c.values[1], t);
        let nan = format_rows(None, &[f64::NAN, f64::INFINITY, -f64::INFINITY], 3, b' ').unwrap();
        assert_eq!(nan, b"nan inf -inf\n");
        assert!(format_rows(None, &[1.0, 2.0], 3, b',').is_err());
    }

    #[test]
    fn a_dropped_stream_stops_its_reader() {
        let text: String = (0..100_000).map(|i| format!("{i} 1 2\n")).collect();
        let lay = layout(Delimiter::Whitespace, 3, vec![vec![num(0), num(1), num(2)]]);
        let mut st = TextStream::new(
            source(&text),
            lay,
            StreamOptions {
                block_bytes: 256,
                parallel: 1,
            },
        )
        .unwrap();
        let first = st.next().unwrap().unwrap();
        assert_eq!(first.values[0][..3], [0., 1., 2.]);
        drop(st); // must not hang or panic
    }

    /// A random plain decimal: sign, 0..=9 integer digits, maybe '.', 0..=9 fraction digits.
    fn decimal(s: &mut u64) -> String {
        let mut t = String::new();
        match (lcg(s) * 4.0) as u32 {
            0 => t.push('-'),
            1 => t.push('+'),
            _ => {}
        }
        for _ in 0..(lcg(s) * 10.0) as usize {
            t.push(char::from(b'0' + (lcg(s) * 10.0) as u8));
        }
        if lcg(s) < 0.8 {
            t.push('.');
            for _ in 0..(lcg(s) * 10.0) as usize {
                t.push(char::from(b'0' + (lcg(s) * 10.0) as u8));
            }
        }
        if t.trim_start_matches(['-', '+', '.']).is_empty() {
            t.push('7');
        }
        t
    }

    /// Text of `rows` lines of 4 fields: mostly plain decimals, some in other forms the
    /// general parser takes, repeated rows, blank and comment lines, CRLF, leading blanks;
    /// with `junk`, also fields that are not numbers and ragged rows.
    fn mixed_text(rows: usize, d: char, junk: bool, seed: u64) -> String {
        let other = [
            "1e3",
            "-2.5E-7",
            " 4",
            "12345678901234567",
            "0.000123456789012",
            "7.",
        ];
        let bad = ["x", "", "nan", "1.2.3", "9,5", "--1"];
        let mut s = seed;
        let mut out = String::new();
        let mut prev: Vec<String> = Vec::new();
        for i in 0..rows {
            let u = lcg(&mut s);
            if u < 0.02 {
                out += "\n";
                continue;
            }
            if u < 0.04 {
                out += "# a comment, with the delimiter\n";
                continue;
            }
            let mut f: Vec<String> = if u < 0.1 && !prev.is_empty() {
                prev.clone()
            } else {
                (0..4)
                    .map(|_| {
                        let v = lcg(&mut s);
                        if v < 0.05 {
                            other[(lcg(&mut s) * other.len() as f64) as usize].to_string()
                        } else if junk && v < 0.052 {
                            bad[(lcg(&mut s) * bad.len() as f64) as usize].to_string()
                        } else {
                            decimal(&mut s)
                        }
                    })
                    .collect()
            };
            if junk && lcg(&mut s) < 0.002 {
                f.pop();
            }
            prev = f.clone();
            if i % 97 == 5 {
                out.push(' ');
            }
            out += &f.join(&d.to_string());
            out += if i % 7 == 3 { "\r\n" } else { "\n" };
        }
        out
    }

    /// Values (as bits), rows, repeats, bytes and lines of a parse.
    type Parsed = (Vec<Vec<u64>>, usize, u64, usize, u64);

    /// Parse `buf` with the fast delimited parser or the line-by-line reference.
    fn parse_either(
        buf: &[u8],
        lay: &TextLayout,
        fast: bool,
    ) -> std::result::Result<Parsed, RowError> {
        let Delimiter::Byte(d) = lay.delimiter else {
            panic!("a delimited layout");
        };
        let cap = row_bound(buf).rows;
        let mut values: Vec<Vec<f64>> = lay
            .groups
            .iter()
            .map(|g| vec![0.0; cap * g.len()])
            .collect();
        let mut sink = RowSink::new(lay, values.iter_mut().map(Vec::as_mut_slice).collect(), cap);
        let (bytes, lines) = if fast {
            parse_seps(buf, d, &mut sink)?
        } else {
            parse_plain(buf, Some(d), &mut sink)?
        };
        let (rows, repeats) = (sink.rows, sink.repeats);
        let bits = values
            .iter()
            .zip(&lay.groups)
            .map(|(v, g)| v[..rows * g.len()].iter().map(|x| x.to_bits()).collect())
            .collect();
        Ok((bits, rows, repeats, bytes, lines))
    }

    #[test]
    fn separator_scan_parses_like_the_line_by_line_reference() {
        let scaled = Column {
            index: 0,
            kind: ColumnKind::Number { scale: 1e-3 },
        };
        let layouts = [
            vec![vec![num(1), num(2), num(3)], vec![scaled]],
            vec![vec![num(2)], vec![num(3), num(1)]],
        ];
        let mut checked = 0;
        for (k, d) in [',', ';', '\t', '|'].into_iter().enumerate() {
            for junk in [false, true] {
                for seed in 0..6u64 {
                    let text = mixed_text(3000, d, junk, 31 * seed + k as u64);
                    for groups in &layouts {
                        let lay = layout(Delimiter::Byte(d as u8), 4, groups.clone());
                        // Whole, and cut short anywhere (a last line without its newline).
                        for end in [text.len(), text.len() - 1, text.len() / 3] {
                            let buf = &text.as_bytes()[..end];
                            let fast = parse_either(buf, &lay, true);
                            let reference = parse_either(buf, &lay, false);
                            assert_eq!(fast, reference, "{d:?} junk {junk} seed {seed}");
                            checked += usize::from(fast.is_ok());
                        }
                    }
                }
            }
        }
        assert!(checked > 100, "{checked}");
    }

    #[test]
    fn vector_and_word_spans_equal_the_field_scan() {
        // Every value parse_span (8 bytes at a time) or the SSE4.1 span gives is the one
        // scan_field gives (which the general parser checks), bit for bit.
        let mut s = 11u64;
        let junk = [
            ".", "-", "+", "..5", "1.2.3", "1e5", "0x1", "1_0", "5-", ":", "/", " 1",
        ];
        let mut taken = [0usize; 2];
        for i in 0..300_000 {
            let field = if i % 10 == 0 {
                junk[(lcg(&mut s) * junk.len() as f64) as usize].to_string()
            } else {
                let mut t = decimal(&mut s);
                // Longer integer or fraction parts too (up to 17 digits in all).
                for _ in 0..(lcg(&mut s) * 8.0) as usize {
                    t.push(char::from(b'0' + (lcg(&mut s) * 10.0) as u8));
                }
                t
            };
            let mut buf = field.clone().into_bytes();
            let e = buf.len();
            buf.extend_from_slice(b",99999999999999999999\n");
            let (se, want) = scan_field(&buf, 0, b',');
            let want = want.filter(|_| se == e).map(f64::to_bits);
            if let Some(v) = parse_span(&buf, 0, e) {
                assert_eq!(Some(v.to_bits()), want, "{field}");
                taken[0] += 1;
            }
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("sse4.1") {
                // SAFETY: the CPU has SSE4.1.
                if let Some(v) = unsafe { sse41::span(&buf, 0, e) } {
                    assert_eq!(Some(v.to_bits()), want, "{field}");
                    taken[1] += 1;
                }
            }
        }
        assert!(taken[0] > 100_000, "{taken:?}");
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("sse4.1") {
            assert!(taken[1] > taken[0], "{taken:?}");
        }
    }

    /// A temporary file holding `text`, removed on drop.
    struct TempFile(std::path::PathBuf);

    impl TempFile {
        fn new(name: &str, text: &[u8]) -> Self {
            let p = std::env::temp_dir().join(format!("accelcal-{}-{name}", std::process::id()));
            std::fs::write(&p, text).unwrap();
            TempFile(p)
        }

        fn map(&self, offset: u64) -> Source {
            let f = std::fs::File::open(&self.0).unwrap();
            Source::Map(MappedText::open(&f, offset).unwrap().unwrap())
        }

        fn reader(&self, offset: u64) -> Source {
            use std::io::Seek;
            let mut f = std::fs::File::open(&self.0).unwrap();
            f.seek(std::io::SeekFrom::Start(offset)).unwrap();
            Source::Reader(Box::new(f))
        }
    }

    impl Drop for TempFile {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }

    /// Repeated samples counted over whole arrays: rows whose first group equals the row
    /// before's.
    fn repeats_of(c: &Collected, k: usize) -> u64 {
        let v = &c.values[0];
        (1..c.rows)
            .filter(|&r| v[r * k..(r + 1) * k] == v[(r - 1) * k..r * k])
            .count() as u64
    }

    #[test]
    fn mapped_files_stream_the_same_blocks_as_read_ones() {
        let text = format!("t,ax,ay,az\n{}", mixed_text(20_000, ',', false, 3));
        let file = TempFile::new("blocks.csv", text.as_bytes());
        let mut lay = layout(
            Delimiter::Byte(b','),
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        lay.first_line = 2;
        for block in [64, 1000, 1 << 16, 1 << 22] {
            let opts = StreamOptions {
                block_bytes: block,
                parallel: 2,
            };
            let mapped: Vec<Block> = TextStream::new(file.map(11), lay.clone(), opts)
                .unwrap()
                .map(|b| b.unwrap())
                .collect();
            let read: Vec<Block> = TextStream::new(file.reader(11), lay.clone(), opts)
                .unwrap()
                .map(|b| b.unwrap())
                .collect();
            assert!(mapped.len() > 1 || block == 1 << 22);
            let cat = |bs: &[Block]| -> (Vec<f64>, usize) {
                let v = bs.iter().flat_map(|b| b.values[0].clone()).collect();
                (v, bs.iter().map(|b| b.bytes).sum())
            };
            assert_eq!(cat(&mapped), cat(&read), "block {block}");
            if block >= 1000 {
                // Lines shorter than a block: the same blocks, cut at the same lines.
                assert_eq!(mapped, read, "block {block}");
            }
        }
    }

    #[test]
    fn whole_mapped_files_parse_into_place_like_the_stream() {
        // Chunks of several sizes on pools of 1 to 3 threads give the arrays the stream
        // gives (comments and blank lines close up, a last line without newline counts).
        let mut text = format!("t;ax;ay;az\n{}", mixed_text(30_000, ';', false, 8));
        text += "1;2;3;4";
        let file = TempFile::new("whole.csv", text.as_bytes());
        let mut lay = layout(
            Delimiter::Byte(b';'),
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        lay.first_line = 2;
        let stream = read_all(file.reader(11), lay.clone(), StreamOptions::default()).unwrap();
        assert!(stream.rows > 25_000);
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for chunk in [1, 37, 5000, 1 << 20] {
                let opts = StreamOptions {
                    block_bytes: chunk,
                    parallel: 0,
                };
                let whole = pool
                    .install(|| read_all(file.map(11), lay.clone(), opts))
                    .unwrap();
                assert_eq!(
                    whole.values, stream.values,
                    "{threads} threads, chunk {chunk}"
                );
                assert_eq!((whole.rows, whole.bytes), (stream.rows, stream.bytes));
                // Repeats are counted across chunk boundaries too: exactly.
                assert_eq!(whole.repeats, repeats_of(&whole, 3));
            }
        }
    }

    #[test]
    fn whole_mapped_files_name_the_line_of_a_bad_row() {
        let mut text = String::from("t,ax,ay,az\n");
        for i in 0..5000 {
            text += &format!("{i},1,2,3\n");
            if i == 100 {
                text += "\n# comment\n";
            }
        }
        text += "5000,1,x,3\n5001,1,2,3\n5002,y,2,3\n";
        let file = TempFile::new("bad.csv", text.as_bytes());
        let mut lay = layout(
            Delimiter::Byte(b','),
            4,
            vec![vec![num(1), num(2), num(3)], vec![num(0)]],
        );
        lay.first_line = 2;
        // Row i is line i + 2 up to row 100, then line i + 4: row 5000 is line 5004.
        for chunk in [16, 1000, 1 << 20] {
            let opts = StreamOptions {
                block_bytes: chunk,
                parallel: 0,
            };
            let c = read_all(file.map(11), lay.clone(), opts).unwrap();
            assert_eq!(c.rows, 5001, "{chunk}");
            assert_eq!(
                c.bad,
                BadRows {
                    count: 2,
                    first: Some((5004, "column 2 (0-based): \"x\" is not a number".into()))
                },
                "{chunk}"
            );
        }
    }

    #[test]
    fn mapped_quoted_text_with_lone_carriage_returns() {
        // csv-core ends records at a lone '\r' too: a quoted file with old Mac line ends
        // has more rows than '\n', which the room for rows allows for.
        let text = "\"1\",\"2\"\r3,4\r5,\"6\"\r";
        let file = TempFile::new("cr.csv", text.as_bytes());
        let lay = layout(Delimiter::Byte(b','), 2, vec![vec![num(0), num(1)]]);
        let c = read_all(file.map(0), lay.clone(), StreamOptions::default()).unwrap();
        assert_eq!(c.values[0], vec![1., 2., 3., 4., 5., 6.]);
        let r = read_all(file.reader(0), lay, StreamOptions::default()).unwrap();
        assert_eq!(c, r);
    }
}

//! The one error type of the core. The Python glue maps it onto the exception hierarchy
//! `CalibrationError(ValueError)` > `DegenerateDataError`.

use thiserror::Error;

/// Every failure the numerical core can report. Messages name the problem in user terms.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CoreError {
    /// The input is malformed: wrong shape, NaN/inf, out-of-range indices, bad settings.
    #[error("{0}")]
    InvalidInput(String),
    /// The input is well-formed but cannot determine what was asked (singular design,
    /// too few dwells, a quadric that is not an ellipsoid).
    #[error("{0}")]
    Degenerate(String),
    /// An iterative solver did not reach its tolerance.
    #[error("{0}")]
    NotConverged(String),
    /// Memory ran out while a buffer grew with the input (a recording too long for the
    /// memory left, or a file declaring far more samples than it holds). Python sees a
    /// `MemoryError`; the message names the size that could not be had.
    #[error("{0}")]
    OutOfMemory(String),
}

/// Result alias used across the core.
pub type Result<T> = std::result::Result<T, CoreError>;

/// Shorthand for an [`CoreError::InvalidInput`] error.
pub fn invalid<T>(msg: impl Into<String>) -> Result<T> {
    Err(CoreError::InvalidInput(msg.into()))
}

/// Shorthand for a [`CoreError::Degenerate`] error.
pub fn degenerate<T>(msg: impl Into<String>) -> Result<T> {
    Err(CoreError::Degenerate(msg.into()))
}

/// Room for `additional` more entries in `v`, or [`CoreError::OutOfMemory`] naming `what`
/// and the size asked for: where a vector grows with the length of the input, running out of
/// memory is an error to report, not an abort of the process. Amortised (the capacity at
/// least doubles), so calling it before every push is cheap.
pub fn try_grow<T>(v: &mut Vec<T>, additional: usize, what: &str) -> Result<()> {
    if v.capacity() - v.len() >= additional {
        return Ok(());
    }
    v.try_reserve(additional).map_err(|_| {
        let want = v
            .len()
            .saturating_add(additional)
            .max(v.len().saturating_mul(2));
        out_of_memory(what, want.saturating_mul(std::mem::size_of::<T>().max(1)))
    })
}

/// The [`CoreError::OutOfMemory`] of `what` failing to grow to `bytes` bytes.
pub fn out_of_memory(what: &str, bytes: usize) -> CoreError {
    CoreError::OutOfMemory(format!(
        "out of memory: {what} could not grow to {} ({bytes} bytes)",
        human_bytes(bytes)
    ))
}

/// `"1.5 GB"`: a byte count for messages (decimal units).
pub fn human_bytes(bytes: usize) -> String {
    let b = bytes as f64;
    match b {
        b if b >= 1e12 => format!("{:.1} TB", b / 1e12),
        b if b >= 1e9 => format!("{:.1} GB", b / 1e9),
        b if b >= 1e6 => format!("{:.1} MB", b / 1e6),
        b if b >= 1e3 => format!("{:.1} kB", b / 1e3),
        _ => format!("{bytes} bytes"),
    }
}

/// `"1 dwell"`, `"2 dwells"`: a count and its noun, for messages.
pub fn count_of(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn try_grow_reports_out_of_memory_instead_of_aborting() {
        let mut v: Vec<[f64; 3]> = vec![[0.0; 3]; 4];
        let e = try_grow(&mut v, usize::MAX / 2, "the dwell blocks").unwrap_err();
        match e {
            CoreError::OutOfMemory(m) => {
                assert!(m.contains("the dwell blocks"), "{m}");
                assert!(m.contains("out of memory"), "{m}");
            }
            other => panic!("not OutOfMemory: {other:?}"),
        }
        assert_eq!(v.len(), 4); // unchanged
                                // Bytes that overflow no count but cannot be had either.
        let mut b: Vec<u8> = Vec::new();
        assert!(matches!(
            try_grow(&mut b, usize::MAX / 4, "a buffer"),
            Err(CoreError::OutOfMemory(_))
        ));
        try_grow(&mut v, 100, "x").unwrap();
        assert!(v.capacity() >= 104);
    }

    #[test]
    fn human_bytes_units() {
        assert_eq!(human_bytes(512), "512 bytes");
        assert_eq!(human_bytes(4_294_967_296), "4.3 GB");
    }
}

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

/// `"1 dwell"`, `"2 dwells"`: a count and its noun, for messages.
pub fn count_of(n: usize, noun: &str) -> String {
    if n == 1 {
        format!("1 {noun}")
    } else {
        format!("{n} {noun}s")
    }
}

//! accelcal core: norm-observation calibration of accelerometers.
//!
//! Pure Rust; the Python bindings live in [`py`] behind the `python` feature.

pub mod dwell;
pub mod error;
pub mod lsq;

#[cfg(feature = "python")]
mod py;

pub use error::{CoreError, Result};

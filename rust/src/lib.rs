//! accelcal core: norm-observation calibration of accelerometers.
//!
//! Pure Rust; the Python bindings live in [`py`] behind the `python` feature.

pub mod centrifuge;
pub mod dwell;
pub mod error;
pub mod gap;
pub mod gradiometer;
pub mod lsq;
pub mod static_fit;
pub mod text;

#[cfg(feature = "python")]
mod py;

pub use error::{CoreError, Result};

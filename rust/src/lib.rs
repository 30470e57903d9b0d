//! accelcal core: norm-observation calibration of accelerometers.
//!
//! Pure Rust; the Python bindings live in [`py`] behind the `python` feature.

pub mod centrifuge;
pub mod dwell;
pub mod error;
pub mod gap;
pub mod gradiometer;
pub(crate) mod lanes;
pub mod lsq;
pub mod static_fit;
pub mod text;

#[cfg(feature = "python")]
mod py;

pub use error::{CoreError, Result};

/// Deterministic pseudo-random numbers for the unit tests (one 64-bit LCG).
#[cfg(test)]
pub(crate) mod test_rng {
    /// The next number of the sequence at `seed`, uniform in [0, 1).
    pub fn unit(seed: &mut u64) -> f64 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*seed >> 11) as f64) / ((1u64 << 53) as f64)
    }
}

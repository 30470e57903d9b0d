//! Dwells whose output did not follow the sensor: a channel saturated at its range, a channel
//! stuck at one value, or a logger that repeated one sample.
//!
//! The test is exact constancy: every sample of a dwell on an axis has the same value (sample
//! variance zero, up to rounding of the sums). A real sensor's output always varies by its own
//! noise unless that noise is below one output step, so constancy counts only where the
//! axis's noise is resolvable: its typical dwell variance (upper quartile over the dwells) is
//! at least one squared output step (`lsb`: a std of one step), or positive when the output
//! is not quantised, and the dwell holds at least [`FAULT_MIN_SAMPLES`] samples. With noise
//! of one step, no value holds more than 40 % of the samples, so a run of that many equal
//! samples by chance has a probability below `0.4^30 = 1e-12`. (Noise below a step makes
//! constant dwells normal: a dwell near a whole step reads one value, one near a half step
//! flips between two, with a variance of at most a quarter step squared.)
//!
//! A constant axis whose value is the largest or smallest of that axis over the session is
//! *saturated* (clipped at the range: every pose beyond it reads the same rail value). A
//! constant axis elsewhere is *stuck*. All three axes constant is a *frozen* output (the
//! logger wrote the last sample again while the sensor sent nothing).
//!
//! Partly clipped dwells (a pose within a few noise deviations of the rail: some samples at
//! the rail, the others below) are not found: that needs each dwell's sample extremes, which
//! the dwell pass does not keep.

use crate::error::{invalid, Result};

/// Fewest samples in a dwell for a constant axis to count as a fault.
pub const FAULT_MIN_SAMPLES: u64 = 30;

/// What kind of fault a dwell shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FaultKind {
    /// One axis constant at its largest value of the session.
    SaturatedHigh,
    /// One axis constant at its smallest value of the session.
    SaturatedLow,
    /// One or two axes constant elsewhere.
    Stuck,
    /// All three axes constant.
    Frozen,
}

impl FaultKind {
    /// A short name: "saturated_high", "saturated_low", "stuck" or "frozen".
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::SaturatedHigh => "saturated_high",
            FaultKind::SaturatedLow => "saturated_low",
            FaultKind::Stuck => "stuck",
            FaultKind::Frozen => "frozen",
        }
    }
}

/// One faulty dwell axis (or a frozen dwell: `axis` is `None`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OutputFault {
    /// Index of the dwell.
    pub dwell: usize,
    /// The constant axis (0, 1, 2), or `None` for a frozen dwell.
    pub axis: Option<usize>,
    /// What it is.
    pub kind: FaultKind,
    /// The constant value (the dwell mean on that axis; the x value for a frozen dwell).
    pub value: f64,
    /// The axis's typical dwell variance (upper quartile; the largest axis's for a frozen
    /// dwell), squared input units.
    pub typical_var: f64,
}

/// Upper quartile (nearest rank) of the values, or `None` when there are none.
fn upper_quartile(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[(3 * (v.len() - 1)).div_ceil(4)])
}

/// Per axis: the typical dwell variance when the axis's noise is resolvable, else `None`.
fn resolvable(var: &[[f64; 3]], count: &[u64], lsb: Option<[f64; 3]>) -> [Option<f64>; 3] {
    std::array::from_fn(|a| {
        let v: Vec<f64> = var
            .iter()
            .zip(count)
            .filter(|(r, &n)| n >= FAULT_MIN_SAMPLES && r[a].is_finite())
            .map(|(r, _)| r[a])
            .collect();
        let q = upper_quartile(v)?;
        let floor = lsb.map_or(0.0, |l| l[a] * l[a]);
        (q > 0.0 && q >= floor).then_some(q)
    })
}

/// The faulty dwells of a session, in dwell order (see the module docs).
///
/// `mean` and `var` are the per-dwell means and sample variances (input units), `count` the
/// samples per dwell and `lsb` the output step per axis when the output is quantised.
pub fn output_faults(
    mean: &[[f64; 3]],
    var: &[[f64; 3]],
    count: &[u64],
    lsb: Option<[f64; 3]>,
) -> Result<Vec<OutputFault>> {
    if var.len() != mean.len() || count.len() != mean.len() {
        return invalid(format!(
            "mean, var and count must have one row per dwell; got {}, {} and {}",
            mean.len(),
            var.len(),
            count.len()
        ));
    }
    let typical = resolvable(var, count, lsb);
    let ext: [(f64, f64); 3] = std::array::from_fn(|a| {
        mean.iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), m| {
                (lo.min(m[a]), hi.max(m[a]))
            })
    });
    let mut out = Vec::new();
    for (k, ((m, v), &n)) in mean.iter().zip(var).zip(count).enumerate() {
        if n < FAULT_MIN_SAMPLES {
            continue;
        }
        // Constant: the variance is zero up to the rounding of sums of values of size |m|.
        let constant: [bool; 3] = std::array::from_fn(|a| {
            let tiny = 1e-24 * m[a] * m[a] + f64::MIN_POSITIVE;
            v[a].is_finite() && v[a] <= tiny
        });
        if constant.iter().all(|&c| c) {
            if let Some(q) = typical.iter().flatten().copied().reduce(f64::max) {
                out.push(OutputFault {
                    dwell: k,
                    axis: None,
                    kind: FaultKind::Frozen,
                    value: m[0],
                    typical_var: q,
                });
            }
            continue;
        }
        for a in 0..3 {
            let Some(q) = typical[a] else { continue };
            if !constant[a] {
                continue;
            }
            let (lo, hi) = ext[a];
            let tol = lsb.map_or(0.0, |l| 0.5 * l[a]).max(1e-12 * m[a].abs());
            let kind = if m[a] >= hi - tol {
                FaultKind::SaturatedHigh
            } else if m[a] <= lo + tol {
                FaultKind::SaturatedLow
            } else {
                FaultKind::Stuck
            };
            out.push(OutputFault {
                dwell: k,
                axis: Some(a),
                kind,
                value: m[a],
                typical_var: q,
            });
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A session of `k` dwells: axis means spread over +-1000, variance 4 on every axis.
    fn session(k: usize) -> (Vec<[f64; 3]>, Vec<[f64; 3]>, Vec<u64>) {
        let mean = (0..k)
            .map(|i| {
                let u = i as f64 / k as f64 * std::f64::consts::TAU;
                [1000.0 * u.cos(), 1000.0 * u.sin(), 300.0 * (3.0 * u).sin()]
            })
            .collect();
        (mean, vec![[4.0; 3]; k], vec![6000; k])
    }

    #[test]
    fn clean_session_has_no_fault() {
        let (m, v, n) = session(24);
        assert!(output_faults(&m, &v, &n, None).unwrap().is_empty());
        assert!(output_faults(&m, &v, &n, Some([1.0; 3]))
            .unwrap()
            .is_empty());
    }

    #[test]
    fn clipped_dwells_are_saturated_at_their_end() {
        let (mut m, mut v, n) = session(24);
        // x clipped at 900 in every dwell beyond it; y clipped at -950 in the same way.
        for (r, s) in m.iter_mut().zip(v.iter_mut()) {
            if r[0] > 900.0 {
                r[0] = 900.0;
                s[0] = 0.0;
            }
            if r[1] < -950.0 {
                r[1] = -950.0;
                s[1] = 0.0;
            }
        }
        let f = output_faults(&m, &v, &n, Some([1.0; 3])).unwrap();
        let hi: Vec<usize> = (0..24).filter(|&k| m[k][0] == 900.0).collect();
        let lo: Vec<usize> = (0..24).filter(|&k| m[k][1] == -950.0).collect();
        assert!(hi.len() >= 2 && lo.len() >= 2);
        let got = |kind, axis| -> Vec<usize> {
            f.iter()
                .filter(|x| x.kind == kind && x.axis == Some(axis))
                .map(|x| x.dwell)
                .collect()
        };
        assert_eq!(got(FaultKind::SaturatedHigh, 0), hi);
        assert_eq!(got(FaultKind::SaturatedLow, 1), lo);
        assert_eq!(f.len(), hi.len() + lo.len());
        assert!(f.iter().all(|x| x.typical_var == 4.0));
    }

    #[test]
    fn stuck_and_frozen_dwells() {
        let (m, mut v, n) = session(24);
        v[5][2] = 0.0; // z constant, not at its extreme
        v[9] = [0.0; 3]; // every axis constant
        let f = output_faults(&m, &v, &n, None).unwrap();
        assert_eq!(f.len(), 2);
        assert_eq!(
            (f[0].dwell, f[0].axis, f[0].kind),
            (5, Some(2), FaultKind::Stuck)
        );
        assert_eq!(
            (f[1].dwell, f[1].axis, f[1].kind),
            (9, None, FaultKind::Frozen)
        );
        assert_eq!(f[1].value, m[9][0]);
    }

    #[test]
    fn noise_below_the_step_or_short_dwells_are_not_faults() {
        let (m, mut v, mut n) = session(24);
        // Quantised output whose noise is a fifth of a step: constant dwells are normal.
        for (k, r) in v.iter_mut().enumerate() {
            *r = if k % 3 == 0 { [0.0; 3] } else { [0.04; 3] };
        }
        assert!(output_faults(&m, &v, &n, Some([1.0; 3]))
            .unwrap()
            .is_empty());
        // The same variances without quantisation: the constant dwells are faults.
        assert_eq!(output_faults(&m, &v, &n, None).unwrap().len(), 8);
        // ... unless the dwells are too short for constancy to mean anything.
        n.iter_mut().for_each(|c| *c = FAULT_MIN_SAMPLES - 1);
        assert!(output_faults(&m, &v, &n, None).unwrap().is_empty());
    }

    #[test]
    fn rounding_of_large_constant_values_counts_as_constant() {
        let (mut m, mut v, n) = session(24);
        m[3][0] = 1e9; // the largest x
        v[3][0] = 1e-9; // rounding of sums of values near 1e9
        let f = output_faults(&m, &v, &n, None).unwrap();
        assert_eq!(f.len(), 1);
        assert_eq!((f[0].dwell, f[0].kind), (3, FaultKind::SaturatedHigh));
        assert!(output_faults(&m, &v, &n[..3], None).is_err());
    }
}

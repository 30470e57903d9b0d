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
//! Once a saturated dwell has shown where an axis's rail is, a dwell whose mean on that axis
//! lies within reach of the rail is *partly saturated*: with Gaussian noise of the axis's
//! typical std `s`, a pose `delta s` inside the rail reads a mean short by
//! `s (phi(delta) - delta Q(delta))` (the clipped tail), and the dwell is flagged when that
//! exceeds [`PARTLY_CLIPPED_SE`] of its mean's standard error `s / sqrt(n)`. A session in
//! which no dwell is saturated throughout gives no rail, and a partly clipped dwell there is
//! not found (that would need each dwell's sample extremes, which the dwell pass does not
//! keep).

use crate::error::{invalid, Result};
use crate::gap::special::chi2_sf;

/// Fewest samples in a dwell for a constant axis to count as a fault.
pub const FAULT_MIN_SAMPLES: u64 = 30;

/// A dwell near a rail is partly saturated when the clipping would shift its mean by more than
/// this many standard errors of the mean.
pub const PARTLY_CLIPPED_SE: f64 = 0.5;

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
    /// One axis's mean within reach of the largest value at which that axis saturates.
    PartlySaturatedHigh,
    /// One axis's mean within reach of the smallest value at which that axis saturates.
    PartlySaturatedLow,
}

impl FaultKind {
    /// A short name: "saturated_high", "saturated_low", "stuck" or "frozen".
    pub fn name(self) -> &'static str {
        match self {
            FaultKind::SaturatedHigh => "saturated_high",
            FaultKind::SaturatedLow => "saturated_low",
            FaultKind::Stuck => "stuck",
            FaultKind::Frozen => "frozen",
            FaultKind::PartlySaturatedHigh => "partly_saturated_high",
            FaultKind::PartlySaturatedLow => "partly_saturated_low",
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
    /// The dwell mean on that axis (the constant value; x for a frozen dwell).
    pub value: f64,
    /// The rail: the value at which the axis saturates (NaN for stuck and frozen dwells).
    pub rail: f64,
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
    let mut out = constant_axes(mean, var, count, lsb, &typical);
    out.extend(partly_saturated(mean, count, &typical, &out));
    out.sort_by_key(|f| (f.dwell, f.axis.map_or(0, |a| a + 1)));
    Ok(out)
}

/// The dwells with exactly constant axes: saturated, stuck or frozen.
fn constant_axes(
    mean: &[[f64; 3]],
    var: &[[f64; 3]],
    count: &[u64],
    lsb: Option<[f64; 3]>,
    typical: &[Option<f64>; 3],
) -> Vec<OutputFault> {
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
                    rail: f64::NAN,
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
            let (kind, rail) = if m[a] >= hi - tol {
                (FaultKind::SaturatedHigh, m[a])
            } else if m[a] <= lo + tol {
                (FaultKind::SaturatedLow, m[a])
            } else {
                (FaultKind::Stuck, f64::NAN)
            };
            out.push(OutputFault {
                dwell: k,
                axis: Some(a),
                kind,
                value: m[a],
                rail,
                typical_var: q,
            });
        }
    }
    out
}

/// Mean shortfall, in noise standard deviations, of a Gaussian sample clipped `delta`
/// deviations above its mean: `phi(delta) - delta Q(delta)` (the clipped tail's mean excess).
pub fn clip_shortfall(delta: f64) -> f64 {
    let d = delta.max(0.0);
    let q = 0.5 * chi2_sf(d * d, 1.0);
    (-0.5 * d * d).exp() / (2.0 * std::f64::consts::PI).sqrt() - d * q
}

/// The dwells within reach of a rail that a saturated dwell has shown (module docs).
fn partly_saturated(
    mean: &[[f64; 3]],
    count: &[u64],
    typical: &[Option<f64>; 3],
    found: &[OutputFault],
) -> Vec<OutputFault> {
    let mut out = Vec::new();
    for a in 0..3 {
        let Some(q) = typical[a] else { continue };
        let s = q.sqrt();
        let flagged = |k: usize| {
            found
                .iter()
                .any(|f| f.dwell == k && f.axis.is_none_or(|x| x == a))
        };
        let rail = |kind| {
            found
                .iter()
                .find(|f| f.axis == Some(a) && f.kind == kind)
                .map(|f| f.rail)
        };
        let sides = [
            (
                rail(FaultKind::SaturatedHigh),
                1.0,
                FaultKind::PartlySaturatedHigh,
            ),
            (
                rail(FaultKind::SaturatedLow),
                -1.0,
                FaultKind::PartlySaturatedLow,
            ),
        ];
        for (r, sign, kind) in sides {
            let Some(r) = r else { continue };
            for (k, (m, &n)) in mean.iter().zip(count).enumerate() {
                if n < FAULT_MIN_SAMPLES || flagged(k) {
                    continue;
                }
                let delta = sign * (r - m[a]) / s;
                if clip_shortfall(delta) * (n as f64).sqrt() > PARTLY_CLIPPED_SE {
                    out.push(OutputFault {
                        dwell: k,
                        axis: Some(a),
                        kind,
                        value: m[a],
                        rail: r,
                        typical_var: q,
                    });
                }
            }
        }
    }
    out
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

    /// Clip axis `a` at `rail` as a saturating sensor would (above it when `high`, else
    /// below): those dwells read the rail exactly, with no variance.
    fn clip(m: &mut [[f64; 3]], v: &mut [[f64; 3]], a: usize, rail: f64, high: bool) {
        for (r, s) in m.iter_mut().zip(v.iter_mut()) {
            if (high && r[a] > rail) || (!high && r[a] < rail) {
                r[a] = rail;
                s[a] = 0.0;
            }
        }
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
        clip(&mut m, &mut v, 0, 900.0, true);
        clip(&mut m, &mut v, 1, -950.0, false);
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

    #[test]
    fn clip_shortfall_is_the_mean_excess_of_the_tail() {
        // E[max(X - d, 0)] for X ~ N(0, 1), by the midpoint rule over the tail.
        for d in [0.0, 0.5, 1.0, 2.0, 3.5] {
            let h = 1e-4;
            let num: f64 = (0..200_000)
                .map(|i| {
                    let x = d + (i as f64 + 0.5) * h;
                    (x - d) * (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt() * h
                })
                .sum();
            assert!((clip_shortfall(d) - num).abs() < 1e-9, "{d}: {num}");
        }
        assert_eq!(clip_shortfall(-1.0), clip_shortfall(0.0));
    }

    #[test]
    fn dwells_within_reach_of_a_rail_are_partly_saturated() {
        let (mut m, mut v, n) = session(24);
        // x saturates at 900 (dwells beyond it read 900 exactly); then put three dwells at
        // 0.5, 2 and 4 noise std (2) inside that rail.
        clip(&mut m, &mut v, 0, 900.0, true);
        let free: Vec<usize> = (0..24)
            .filter(|&k| v[k][0] > 0.0 && m[k][0] > 0.0)
            .collect();
        for (&k, d) in free.iter().zip([0.5, 2.0, 4.0]) {
            m[k][0] = 900.0 - 2.0 * d;
        }
        let f = output_faults(&m, &v, &n, None).unwrap();
        let partly: Vec<&OutputFault> = f
            .iter()
            .filter(|x| x.kind == FaultKind::PartlySaturatedHigh)
            .collect();
        // With 6000 samples the bias threshold is 0.5 / sqrt(6000) = 0.0065 std: delta 0.5 and
        // 2 are flagged (shortfall 0.198 and 0.0085), delta 4 is not (7e-6).
        assert_eq!(
            partly.iter().map(|x| x.dwell).collect::<Vec<_>>(),
            free[..2].to_vec()
        );
        assert!(partly.iter().all(|x| x.rail == 900.0 && x.axis == Some(0)));
        // Without a saturated dwell there is no rail, and nothing is partly saturated.
        let (m2, v2, n2) = session(24);
        assert!(output_faults(&m2, &v2, &n2, None).unwrap().is_empty());
        // The faults come in dwell order.
        assert!(f.windows(2).all(|w| w[0].dwell <= w[1].dwell));
    }
}

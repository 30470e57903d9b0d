//! Recordings that hold only the rests: a logger that stores a block of samples per pose and
//! nothing while the sensor is turned (a "press a key, record N samples" calibration script).
//! Consecutive poses then meet in a jump between two samples, with no motion recorded, and
//! the window detector cannot see a rest shorter than its window.
//!
//! [`step_log`] reads a stream as such a log when its sample-to-sample differences say so:
//! - each axis's difference noise is `median |dx| / 0.6745` (the smallest step for an output
//!   quantised so coarsely that most differences are zero);
//! - a difference beyond [`STEP_LOW`] of that noise on some axis is large, and a cluster of
//!   consecutive large differences is a *jump* when it holds at most [`JUMP_MAX_SAMPLES`]
//!   differences (a sensor's own low-pass filter may spread a jump over a few samples) and one
//!   of them exceeds [`STEP_HIGH`]; a longer cluster is recorded motion;
//! - a jump whose two sides have the same mean (a glitch: one wild sample, out and back) is
//!   no change of pose and does not cut the stream;
//! - the stream is a step log when it has at least [`MIN_JUMPS`] jumps, recorded motion
//!   covers at most [`MAX_MOTION_FRACTION`] of it, and the runs between jumps (each a pose)
//!   of at least [`MIN_RUN_SAMPLES`] samples hold at least [`MIN_RUN_COVERAGE`] of it;
//! - when most runs start a common distance `p` after the one before (a logger's block of
//!   samples per pose), a run spanning several blocks of that grid (poses too close for a
//!   jump between them) is cut on the grid.
//!
//! A stream with its moves recorded fails the motion test: a move is many consecutive
//! large differences, not one.

use crate::dwell::Sample;
use ndarray::ArrayView2;

/// A difference beyond this many difference-noise stds on some axis is large.
pub const STEP_LOW: f64 = 6.0;
/// A jump holds a difference beyond this many difference-noise stds.
pub const STEP_HIGH: f64 = 30.0;
/// Most consecutive large differences in one jump.
pub const JUMP_MAX_SAMPLES: usize = 3;
/// Fewest jumps for a step log.
pub const MIN_JUMPS: usize = 5;
/// Largest share of the samples in recorded motion.
pub const MAX_MOTION_FRACTION: f64 = 0.02;
/// Fewest samples in a run that counts as a pose.
pub const MIN_RUN_SAMPLES: usize = 8;
/// Smallest share of the samples in runs of at least [`MIN_RUN_SAMPLES`].
pub const MIN_RUN_COVERAGE: f64 = 0.9;

/// A stream read as a log of rests.
#[derive(Debug, Clone, PartialEq)]
pub struct StepLog {
    /// `[start, stop)` sample bounds of each run between jumps (at least
    /// [`MIN_RUN_SAMPLES`] samples each), in order.
    pub runs: Vec<[usize; 2]>,
    /// Jumps found.
    pub jumps: usize,
    /// The run length shared by at least half of the runs (a logger's samples per pose),
    /// after runs spanning several poses of the logger's grid were cut.
    pub period: Option<usize>,
    /// Share of the samples in recorded motion.
    pub motion_fraction: f64,
}

/// Each axis's difference-noise std: `median |dx| / 0.6745`, or the smallest nonzero `|dx|`
/// when the median is zero; infinite for an axis that never changes (it cannot show a jump).
fn difference_noise(d: &[[f64; 3]]) -> [f64; 3] {
    let mut out = [f64::INFINITY; 3];
    for (a, o) in out.iter_mut().enumerate() {
        let mut v: Vec<f64> = d.iter().map(|r| r[a].abs()).collect();
        let med = super::quantile_of(&mut v, 0.5) / 0.6745;
        let smallest = v
            .iter()
            .copied()
            .filter(|x| *x > 0.0)
            .fold(f64::INFINITY, f64::min);
        *o = if med > 0.0 { med } else { smallest };
    }
    out
}

/// The stream as a log of rests, or `None` when it does not read as one (see the module
/// notes). Non-finite samples: `None` (the window detector handles dropouts).
pub fn step_log<T: Sample>(x: &ArrayView2<'_, T>) -> Option<StepLog> {
    let n = x.nrows();
    if x.ncols() != 3 || n < MIN_JUMPS * MIN_RUN_SAMPLES {
        return None;
    }
    let row = |i: usize| [x[[i, 0]].to_f64(), x[[i, 1]].to_f64(), x[[i, 2]].to_f64()];
    let mut d = Vec::with_capacity(n - 1);
    let mut prev = row(0);
    for i in 1..n {
        let r = row(i);
        if r.iter().any(|v| !v.is_finite()) {
            return None;
        }
        d.push([r[0] - prev[0], r[1] - prev[1], r[2] - prev[2]]);
        prev = r;
    }
    let noise = difference_noise(&d);
    if noise.iter().all(|s| !s.is_finite()) {
        return None;
    }
    let z: Vec<f64> = d
        .iter()
        .map(|r| (0..3).map(|a| r[a].abs() / noise[a]).fold(0.0, f64::max))
        .collect();
    // Clusters of consecutive large differences: jumps cut the stream, motion is counted.
    let (mut cuts, mut motion) = (Vec::new(), 0usize);
    let mut i = 0;
    while i < z.len() {
        if z[i] <= STEP_LOW {
            i += 1;
            continue;
        }
        let a = i;
        while i < z.len() && z[i] > STEP_LOW {
            i += 1;
        }
        // Differences a..i: samples a+1..=i differ from sample a by more than the noise.
        if i - a <= JUMP_MAX_SAMPLES && z[a..i].iter().any(|&v| v > STEP_HIGH) {
            cuts.push([a + 1, i]); // the run before ends at a + 1; the next starts at i
        } else if i - a > JUMP_MAX_SAMPLES {
            motion += i - a + 1;
        }
    }
    let motion_fraction = motion as f64 / n as f64;
    if cuts.len() < MIN_JUMPS || motion_fraction > MAX_MOTION_FRACTION {
        return None;
    }
    let (segments, jumps) = poses_between(x, &cuts, &noise);
    if jumps < MIN_JUMPS {
        return None;
    }
    let runs: Vec<[usize; 2]> = segments
        .into_iter()
        .filter(|[a, b]| *b >= a + MIN_RUN_SAMPLES)
        .collect();
    let covered: usize = runs.iter().map(|[a, b]| b - a).sum();
    if (covered as f64) < MIN_RUN_COVERAGE * n as f64 {
        return None;
    }
    let stride = common_value(runs.windows(2).map(|w| w[1][0] - w[0][0]));
    let runs = match stride {
        Some(p) => split_on_grid(&runs, p),
        None => runs,
    };
    let period = common_value(runs.iter().map(|[a, b]| b - a));
    Some(StepLog {
        runs,
        jumps,
        period,
        motion_fraction,
    })
}

/// The segments between the `cuts` (`[stop of the one before, start of the next]`), with
/// every cut whose two sides have the same mean merged away: a glitch (a single wild sample,
/// out and back) is no change of pose. Two sides differ when some axis's means differ by
/// more than [`STEP_LOW`] standard errors (white noise of the difference noise / sqrt 2).
/// Returns the segments and the cuts kept (the jumps).
fn poses_between<T: Sample>(
    x: &ArrayView2<'_, T>,
    cuts: &[[usize; 2]],
    noise: &[f64; 3],
) -> (Vec<[usize; 2]>, usize) {
    let n = x.nrows();
    let mut sum = vec![[0.0f64; 3]; n + 1];
    for i in 0..n {
        for a in 0..3 {
            sum[i + 1][a] = sum[i][a] + x[[i, a]].to_f64();
        }
    }
    let mean = |[a, b]: [usize; 2], k: usize| (sum[b][k] - sum[a][k]) / (b - a) as f64;
    let differ = |p: [usize; 2], q: [usize; 2]| {
        let (np, nq) = ((p[1] - p[0]) as f64, (q[1] - q[0]) as f64);
        np < 2.0
            || nq < 2.0
            || (0..3).any(|k| {
                let se = noise[k] / std::f64::consts::SQRT_2 * (1.0 / np + 1.0 / nq).sqrt();
                (mean(p, k) - mean(q, k)).abs() > STEP_LOW * se
            })
    };
    let mut out = Vec::with_capacity(cuts.len() + 1);
    let mut cur = [0, cuts[0][0]];
    for (j, &[_, next]) in cuts.iter().enumerate() {
        let stop = cuts.get(j + 1).map_or(n, |c| c[0]);
        let seg = [next, stop.max(next)];
        if differ(cur, seg) {
            out.push(cur);
            cur = seg;
        } else {
            cur[1] = seg[1]; // a glitch: the same pose goes on, the wild samples in it
        }
    }
    out.push(cur);
    let jumps = out.len() - 1;
    (out, jumps)
}

/// A logger that stores a block of samples per pose starts its poses on a grid of step
/// `p` (the block and any samples between blocks): runs that span grid points (two poses too
/// close for a jump between them) are cut there. The grid's phase is the one most runs start
/// on; cuts within [`MIN_RUN_SAMPLES`] of a run's ends are not made.
fn split_on_grid(runs: &[[usize; 2]], p: usize) -> Vec<[usize; 2]> {
    let mut count = vec![0usize; p];
    for [a, _] in runs {
        count[a % p] += 1;
    }
    let phase = (0..p)
        .max_by_key(|&r| (count[r], usize::MAX - r))
        .unwrap_or(0);
    let mut out = Vec::with_capacity(runs.len());
    for &[a, b] in runs {
        let mut start = a;
        let first = a + MIN_RUN_SAMPLES; // the first grid point from here
        let mut c = first + (p + phase - first % p) % p;
        while c + MIN_RUN_SAMPLES <= b {
            out.push([start, c]);
            start = c;
            c += p;
        }
        out.push([start, b]);
    }
    out
}

/// The value shared by at least half of `values` (and by two or more), if any.
fn common_value(values: impl Iterator<Item = usize>) -> Option<usize> {
    let mut v: Vec<usize> = values.collect();
    v.sort_unstable();
    let mut best = (0, 0);
    let mut j = 0;
    while j < v.len() {
        let k = v[j..].iter().take_while(|&&x| x == v[j]).count();
        if k > best.1 {
            best = (v[j], k);
        }
        j += k;
    }
    (2 * best.1 >= v.len() && best.1 > 1 && best.0 > 0).then_some(best.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::unit as lcg;
    use ndarray::Array2;

    /// `blocks` poses of `len` samples each, noise `sigma`, with `moves` samples of a slow
    /// turn recorded between consecutive poses (0: a log of rests).
    fn session(blocks: usize, len: usize, sigma: f64, moves: usize, seed: u64) -> Array2<f64> {
        let mut s = seed;
        let mut rows = Vec::new();
        let pose = |k: usize| {
            let a = k as f64 * 0.9;
            let b = (k as f64 * 0.37).sin();
            [a.cos() * b.cos(), a.sin() * b.cos(), b.sin()]
        };
        for k in 0..blocks {
            let p = pose(k);
            for _ in 0..len {
                rows.push([
                    p[0] + sigma * lcg(&mut s),
                    p[1] + sigma * lcg(&mut s),
                    p[2] + sigma * lcg(&mut s),
                ]);
            }
            if k + 1 < blocks {
                let q = pose(k + 1);
                for j in 0..moves {
                    let f = (j + 1) as f64 / (moves + 1) as f64;
                    rows.push([
                        p[0] + f * (q[0] - p[0]),
                        p[1] + f * (q[1] - p[1]),
                        p[2] + f * (q[2] - p[2]),
                    ]);
                }
            }
        }
        Array2::from_shape_fn((rows.len(), 3), |(i, a)| rows[i][a])
    }

    #[test]
    fn a_log_of_rests_is_cut_at_its_jumps() {
        let x = session(40, 100, 3e-3, 0, 1);
        let log = step_log(&x.view()).expect("a log of rests");
        assert_eq!(log.jumps, 39);
        assert_eq!(log.runs.len(), 40);
        assert_eq!(log.period, Some(100));
        for (k, r) in log.runs.iter().enumerate() {
            assert_eq!(*r, [100 * k, 100 * (k + 1)]);
        }
        assert_eq!(log.motion_fraction, 0.0);
    }

    #[test]
    fn two_poses_too_close_for_a_jump_are_cut_on_the_loggers_grid() {
        // Poses 5 and 6 identical (no jump between them), poses 11-13 too: a logger of 100
        // samples per pose still gives one run per pose.
        let mut x = session(20, 100, 3e-3, 0, 8);
        let mut s = 9u64;
        for i in 600..700 {
            for a in 0..3 {
                x[[i, a]] = x[[550, a]] + 3e-3 * lcg(&mut s);
            }
        }
        for i in 1200..1400 {
            for a in 0..3 {
                x[[i, a]] = x[[1150, a]] + 3e-3 * lcg(&mut s);
            }
        }
        let log = step_log(&x.view()).expect("a log of rests");
        assert_eq!(log.jumps, 16);
        assert_eq!(log.period, Some(100));
        let want: Vec<[usize; 2]> = (0..20).map(|k| [100 * k, 100 * (k + 1)]).collect();
        assert_eq!(log.runs, want);
    }

    #[test]
    fn a_jump_spread_by_a_filter_leaves_its_samples_out() {
        // Two samples between poses (a sensor's low-pass filter): they belong to no run.
        let x = session(12, 60, 1e-3, 2, 2);
        let log = step_log(&x.view()).expect("a log of rests");
        assert_eq!(log.runs.len(), 12);
        assert_eq!(log.runs[1], [62, 122]);
        assert_eq!(log.period, Some(60));
    }

    #[test]
    fn a_recording_with_its_moves_is_not_a_log_of_rests() {
        // 2 s turns at 100 Hz between 5 s rests: every turn is a long cluster of large
        // differences (motion), so the window detector keeps the stream.
        assert!(step_log(&session(12, 500, 1e-3, 200, 3).view()).is_none());
        // One rest and nothing else; pure noise; a constant stream; NaN.
        assert!(step_log(&session(1, 2000, 1e-3, 0, 4).view()).is_none());
        assert!(step_log(&Array2::<f64>::zeros((500, 3)).view()).is_none());
        let mut y = session(20, 50, 1e-3, 0, 5);
        y[[7, 1]] = f64::NAN;
        assert!(step_log(&y.view()).is_none());
        // Too few poses.
        assert!(step_log(&session(4, 100, 1e-3, 0, 6).view()).is_none());
    }

    #[test]
    fn glitches_in_a_still_recording_are_not_jumps() {
        // One long rest with 8 single wild samples (out and back: a bus error): the sides of
        // each have the same mean, so no pose changes and it is not a log of rests.
        let mut x = session(1, 3000, 1e-3, 0, 10);
        for k in 0..8 {
            x[[200 + 350 * k, 1]] += 0.2;
        }
        assert!(step_log(&x.view()).is_none());
        // The same glitches inside the blocks of a log of rests leave its runs whole.
        let mut y = session(30, 100, 1e-3, 0, 11);
        for k in 0..8 {
            y[[150 + 300 * k, 0]] -= 0.3;
        }
        let log = step_log(&y.view()).expect("a log of rests");
        assert_eq!(log.jumps, 29);
        let want: Vec<[usize; 2]> = (0..30).map(|k| [100 * k, 100 * (k + 1)]).collect();
        assert_eq!(log.runs, want);
    }

    #[test]
    fn quantised_counts_are_read_in_place() {
        // int16 counts with noise under one count on two axes (most differences zero).
        let x = session(10, 80, 2e-4, 0, 7);
        let q = x.mapv(|v| (v * 2000.0).round() as i16);
        let log = step_log(&q.view()).expect("a log of rests");
        assert_eq!(log.runs.len(), 10);
    }
}

//! Where the gap lies: rows beyond the Bonferroni limit, the gap by group (pose axis, time
//! third, speed, channel), serial correlation in time order, and correlation with temperature.

use super::engine::EngineResult;
use super::special::{chi2_sf, normal_two_sided_isf, pearson};
use super::statics::StaticInput;

/// The gap of one group of rows.
#[derive(Debug, Clone, Copy)]
pub struct Group {
    /// Group key (axis index, third index, speed in rad/s, channel index).
    pub key: f64,
    /// Rows.
    pub n: usize,
    /// Mean squared whitened residual.
    pub mean_e2: f64,
    /// p-value of its chi2 (NaN when the noise is unknown).
    pub p: f64,
}

/// Localisation of the gap.
#[derive(Debug, Clone, Default)]
pub struct Location {
    /// Studentised baseline residuals `e / sqrt(1 - h)`.
    pub t_stud: Vec<f64>,
    /// Two-sided Bonferroni limit on `|t|` at the family level.
    pub threshold: f64,
    /// Rows beyond it.
    pub flagged: Vec<usize>,
    /// By axis (static: dominant pose axis; gradiometer: channel).
    pub axes: Vec<Group>,
    /// By segment (static: time third; centrifuge: speed).
    pub segments: Vec<Group>,
    /// Lag-1 correlation of the residuals in row order, its p-value, Durbin-Watson.
    pub serial: Option<(f64, f64, f64)>,
    /// Correlation with temperature and its p-value, with dT/dt and its p-value.
    pub temperature: Option<(f64, f64, f64, f64)>,
}

/// Groups by key (sorted by key).
pub fn groups(e: &[f64], key: &[f64], noise_known: bool) -> Vec<Group> {
    let mut keys: Vec<f64> = key.to_vec();
    keys.sort_by(|a, b| a.total_cmp(b));
    keys.dedup();
    keys.iter()
        .map(|&kv| {
            let s2: f64 = e
                .iter()
                .zip(key)
                .filter(|(_, k)| **k == kv)
                .map(|(v, _)| v * v)
                .sum();
            let n = key.iter().filter(|k| **k == kv).count();
            Group {
                key: kv,
                n,
                mean_e2: s2 / n as f64,
                p: if noise_known {
                    chi2_sf(s2, n as f64)
                } else {
                    f64::NAN
                },
            }
        })
        .collect()
}

/// Studentised residuals, the Bonferroni limit and the flagged rows.
pub fn flagged(eng: &EngineResult, alpha: f64) -> (Vec<f64>, f64, Vec<usize>) {
    let t: Vec<f64> = eng
        .e
        .iter()
        .zip(&eng.leverage)
        .map(|(e, h)| e / (1.0 - h.clamp(0.0, 0.999_999)).sqrt())
        .collect();
    let thr = normal_two_sided_isf(alpha / eng.n as f64);
    let fl = (0..t.len()).filter(|&k| t[k].abs() > thr).collect();
    (t, thr, fl)
}

/// Lag-1 correlation, its p-value and the Durbin-Watson statistic.
pub fn serial(e: &[f64]) -> Option<(f64, f64, f64)> {
    let n = e.len();
    if n < 4 {
        return None;
    }
    let (r, p) = pearson(&e[..n - 1], &e[1..]);
    let num: f64 = e.windows(2).map(|w| (w[1] - w[0]).powi(2)).sum();
    let den: f64 = e.iter().map(|v| v * v).sum::<f64>().max(1e-300);
    Some((r, p, num / den))
}

/// `np.gradient`: central differences inside, one-sided at the ends.
pub fn gradient(y: &[f64], x: &[f64]) -> Vec<f64> {
    let n = y.len();
    if n < 2 {
        return vec![0.0; n];
    }
    (0..n)
        .map(|k| {
            let (a, b) = if k == 0 {
                (0, 1)
            } else if k == n - 1 {
                (n - 2, n - 1)
            } else {
                (k - 1, k + 1)
            };
            (y[b] - y[a]) / (x[b] - x[a])
        })
        .collect()
}

/// Localisation of a static session (dominant pose axis from the calibrated directions).
pub fn static_location(
    eng: &EngineResult,
    dirs: &[([f64; 3], [f64; 3])],
    inp: &StaticInput,
    alpha: f64,
) -> Location {
    let n = eng.n;
    let (t_stud, threshold, fl) = flagged(eng, alpha);
    let axis: Vec<f64> = dirs
        .iter()
        .map(|d| {
            let a = d.0.map(f64::abs);
            (0..3).fold(0, |b, i| if a[i] > a[b] { i } else { b }) as f64
        })
        .collect();
    // np.array_split(range(n), 3): the first n % 3 parts are one longer.
    let (q, r) = (n / 3, n % 3);
    let third: Vec<f64> = (0..n)
        .map(|k| {
            let mut start = 0;
            for j in 0..3 {
                let len = q + usize::from(j < r);
                if k < start + len {
                    return j as f64;
                }
                start += len;
            }
            2.0
        })
        .collect();
    let temperature = inp.temperature.as_ref().and_then(|tv| {
        let lo = tv.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = tv.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        (hi > lo).then(|| {
            let idx: Vec<f64> = (0..n).map(|k| k as f64).collect();
            let x = match &inp.t {
                Some(t) if t.windows(2).all(|w| w[1] > w[0]) => t.clone(),
                _ => idx,
            };
            let (rt, pt) = pearson(tv, &eng.e);
            let (rd, pd) = pearson(&gradient(tv, &x), &eng.e);
            (rt, pt, rd, pd)
        })
    });
    Location {
        t_stud,
        threshold,
        flagged: fl,
        axes: groups(&eng.e, &axis, eng.noise_known),
        segments: groups(&eng.e, &third, eng.noise_known),
        serial: serial(&eng.e),
        temperature,
    }
}

/// Localisation of a centrifuge or gradiometer session by the given row keys.
pub fn keyed_location(
    eng: &EngineResult,
    axis_key: Option<&[f64]>,
    segment_key: Option<&[f64]>,
    alpha: f64,
) -> Location {
    let (t_stud, threshold, fl) = flagged(eng, alpha);
    Location {
        t_stud,
        threshold,
        flagged: fl,
        axes: axis_key.map_or(vec![], |k| groups(&eng.e, k, eng.noise_known)),
        segments: segment_key.map_or(vec![], |k| groups(&eng.e, k, eng.noise_known)),
        serial: None,
        temperature: None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_serial_and_gradient() {
        let e = [1.0, -1.0, 2.0, 0.0, 3.0, -2.0];
        let key = [0.0, 1.0, 0.0, 1.0, 0.0, 1.0];
        let g = groups(&e, &key, true);
        assert_eq!(g.len(), 2);
        assert!((g[0].mean_e2 - 14.0 / 3.0).abs() < 1e-12 && g[0].n == 3);
        assert!((g[0].p - chi2_sf(14.0, 3.0)).abs() < 1e-15);
        let (r, p, dw) = serial(&e).unwrap();
        assert!(r < 0.0 && p > 0.0 && p <= 1.0);
        let num: f64 = [4.0, 9.0, 4.0, 9.0, 25.0].iter().sum();
        assert!((dw - num / 19.0).abs() < 1e-12);
        let gr = gradient(&[0.0, 1.0, 4.0, 9.0], &[0.0, 1.0, 2.0, 3.0]);
        assert_eq!(gr, vec![1.0, 2.0, 4.0, 5.0]);
    }
}

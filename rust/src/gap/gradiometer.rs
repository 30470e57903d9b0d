//! The gradiometer start-up as a [`GapModel`]: `y_k = bias + R(2 theta_k) gamma` of
//! [`crate::gradiometer`] and its dictionary of unmodelled effects.
//!
//! Rows: the inline and cross averages of every azimuth dwell (two rows per dwell, held out
//! together). With `c, s = cos, sin 2(theta_k + delta_k)`, `m_I = c I + s C`,
//! `m_C = -s I + c C`, the model is
//! `y_I = b_I + (1 + kappa) m_I + mu m_C + d_I th_k + a_I x_k` and
//! `y_C = b_C + mu m_I + (1 - kappa) m_C + d_C th_k + a_C x_k`, `th` hours from the mean
//! time, `x_k = exp(-(t_k - t_0) / tau)`:
//!
//! | effect | parameters |
//! |---|---|
//! | drift | `d_I, d_C`, E/h |
//! | azimuth_error | `delta_k` per dwell, deg (a common offset is absorbed by the gradient) |
//! | channel_scale | `kappa, mu` (gain mismatch, symmetric cross-talk), % |
//! | warmup | `a_I, a_C`, E |

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

use super::engine::{self, EffectInfo, GapModel};
use super::structure::{self, SmoothTest, StructureInput};
use super::{locate, GapOptions, GapResult, RowInfo, Status, System};
use crate::error::{invalid, Result};
use crate::gradiometer::fit_startup_bias;
use nalgebra::DMatrix;

const N_BASE: usize = 4;
const DEG: f64 = std::f64::consts::PI / 180.0;

/// The names, units and dimensions of the gradiometer dictionary (azimuth_error has one
/// parameter per dwell; [`GradiometerModel`] sets it).
pub const NAMES: [(&str, &str); 4] = [
    ("drift", "E/h"),
    ("azimuth_error", "deg"),
    ("channel_scale", "%"),
    ("warmup", "E"),
];

/// A gradiometer start-up session.
#[derive(Debug, Clone)]
pub struct GradiometerInput {
    /// Commanded azimuths, deg.
    pub azimuth_deg: Vec<f64>,
    /// Inline and cross averages per azimuth, E.
    pub outputs: Vec<[f64; 2]>,
    /// Dwell mid times, s.
    pub t: Option<Vec<f64>>,
    /// Noise std of each average, E: one per azimuth (both channels), or two (inline,
    /// cross) per azimuth in that order (`None`: unknown, scaled to the baseline fit).
    pub sigma: Option<Vec<f64>>,
    /// Warm-up time constant, s.
    pub warmup_tau_s: f64,
}

/// The model.
#[derive(Debug, Clone)]
pub struct GradiometerModel {
    inp: GradiometerInput,
    dict: Vec<EffectInfo>,
    th: Vec<f64>,
    wu: Vec<f64>,
    /// Noise std of each residual row (inline, cross of each azimuth).
    sig: Vec<f64>,
}

/// Per-dwell model values and partial derivatives of `(y_I, y_C)`.
struct DwellEval {
    y: [f64; 2],
    /// d y / d [b_I, b_C, I, C].
    base: [[f64; 4]; 2],
    /// d y / d delta (per deg), d y / d [kappa, mu] (per %).
    d_az: [f64; 2],
    d_ch: [[f64; 2]; 2],
}

impl GradiometerModel {
    fn new(inp: &GradiometerInput) -> Self {
        let m = inp.azimuth_deg.len();
        let dims = [2, m, 2, 2];
        let dict = NAMES
            .iter()
            .zip(dims)
            .map(|(&(name, unit), dim)| EffectInfo { name, unit, dim })
            .collect();
        let (th, wu) = match &inp.t {
            None => (vec![0.0; m], vec![0.0; m]),
            Some(t) => {
                let mean = t.iter().sum::<f64>() / m as f64;
                let t0 = t.iter().cloned().fold(f64::INFINITY, f64::min);
                (
                    t.iter().map(|v| (v - mean) / 3600.0).collect(),
                    t.iter()
                        .map(|v| (-(v - t0) / inp.warmup_tau_s).exp())
                        .collect(),
                )
            }
        };
        GradiometerModel {
            dict,
            th,
            wu,
            sig: row_sigma(inp.sigma.as_deref(), m),
            inp: inp.clone(),
        }
    }

    /// Effect values (drift, delta_k, channel, warm-up) of dwell `k`.
    fn effects_of(
        &self,
        k: usize,
        active: &[usize],
        p: &[f64],
    ) -> ([f64; 2], f64, [f64; 2], [f64; 2]) {
        let (mut dr, mut da, mut ch, mut wa) = ([0.0; 2], 0.0, [0.0; 2], [0.0; 2]);
        let mut off = N_BASE;
        for &c in active {
            match c {
                0 => dr = [p[off], p[off + 1]],
                1 => da = p[off + k],
                2 => ch = [1e-2 * p[off], 1e-2 * p[off + 1]],
                _ => wa = [p[off], p[off + 1]],
            }
            off += self.dict[c].dim;
        }
        (dr, da, ch, wa)
    }

    fn dwell(&self, k: usize, active: &[usize], p: &[f64]) -> DwellEval {
        let (dr, da, [kap, mu], wa) = self.effects_of(k, active, p);
        let ang = 2.0 * (self.inp.azimuth_deg[k] + da) * DEG;
        let (s, c) = ang.sin_cos();
        let (gi, gc) = (p[2], p[3]);
        let (mi, mc) = (c * gi + s * gc, -s * gi + c * gc);
        let (th, wu) = (self.th[k], self.wu[k]);
        let y = [
            p[0] + (1.0 + kap) * mi + mu * mc + dr[0] * th + wa[0] * wu,
            p[1] + mu * mi + (1.0 - kap) * mc + dr[1] * th + wa[1] * wu,
        ];
        let base = [
            [1.0, 0.0, (1.0 + kap) * c - mu * s, (1.0 + kap) * s + mu * c],
            [0.0, 1.0, mu * c - (1.0 - kap) * s, mu * s + (1.0 - kap) * c],
        ];
        let (dmi, dmc) = (2.0 * mc * DEG, -2.0 * mi * DEG);
        DwellEval {
            y,
            base,
            d_az: [(1.0 + kap) * dmi + mu * dmc, mu * dmi + (1.0 - kap) * dmc],
            d_ch: [[1e-2 * mi, 1e-2 * mc], [-1e-2 * mc, 1e-2 * mi]],
        }
    }

    /// d y_ch / d (parameters of effect c) of dwell k, as (parameter offset, value) pairs.
    fn effect_partials(&self, ev: &DwellEval, k: usize, ch: usize, c: usize) -> Vec<(usize, f64)> {
        match c {
            0 => vec![(ch, self.th[k])],
            1 => vec![(k, ev.d_az[ch])],
            2 => vec![(0, ev.d_ch[ch][0]), (1, ev.d_ch[ch][1])],
            _ => vec![(ch, self.wu[k])],
        }
    }
}

impl GapModel for GradiometerModel {
    fn n_rows(&self) -> usize {
        2 * self.inp.azimuth_deg.len()
    }
    fn n_base(&self) -> usize {
        N_BASE
    }
    fn dictionary(&self) -> &[EffectInfo] {
        &self.dict
    }
    fn unavailable(&self, c: usize) -> Option<Status> {
        (matches!(c, 0 | 3) && self.inp.t.is_none()).then_some(Status::NoTime)
    }
    fn group(&self, row: usize) -> usize {
        row / 2
    }
    fn noise_known(&self) -> bool {
        self.inp.sigma.is_some()
    }
    fn eval(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        e: &mut [f64],
        jac: &mut DMatrix<f64>,
    ) -> Result<()> {
        for (ri, &row) in rows.iter().enumerate() {
            let (k, ch) = (row / 2, row % 2);
            let ev = self.dwell(k, active, p);
            let w = 1.0 / self.sig[row];
            e[ri] = (self.inp.outputs[k][ch] - ev.y[ch]) * w;
            for j in 0..N_BASE {
                jac[(ri, j)] = -ev.base[ch][j] * w;
            }
            let mut off = N_BASE;
            for &c in active {
                for j in 0..self.dict[c].dim {
                    jac[(ri, off + j)] = 0.0;
                }
                for (j, v) in self.effect_partials(&ev, k, ch, c) {
                    jac[(ri, off + j)] = -v * w;
                }
                off += self.dict[c].dim;
            }
        }
        Ok(())
    }
    fn columns(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        c: usize,
    ) -> Result<DMatrix<f64>> {
        let mut out = DMatrix::zeros(rows.len(), self.dict[c].dim);
        for (ri, &row) in rows.iter().enumerate() {
            let (k, ch) = (row / 2, row % 2);
            let ev = self.dwell(k, active, p);
            for (j, v) in self.effect_partials(&ev, k, ch, c) {
                out[(ri, j)] = -v / self.sig[row];
            }
        }
        Ok(out)
    }
    fn sigma(&self, rows: &[usize], _active: &[usize], _p: &[f64]) -> Result<Vec<f64>> {
        Ok(rows.iter().map(|&r| self.sig[r]).collect())
    }
    fn predictable(&self, c: usize) -> bool {
        c != 1 // a held-out dwell's own azimuth error is unknown
    }
}

/// The noise std of each residual row (2 per azimuth: inline, cross) from one value per
/// azimuth or one per row; unit weights without one.
fn row_sigma(sigma: Option<&[f64]>, m: usize) -> Vec<f64> {
    match sigma {
        Some(s) if s.len() == 2 * m => s.to_vec(),
        Some(s) => s.iter().flat_map(|&v| [v, v]).collect(),
        None => vec![1.0; 2 * m],
    }
}

fn check(inp: &GradiometerInput) -> Result<()> {
    let m = inp.azimuth_deg.len();
    if inp.outputs.len() != m {
        return invalid(format!(
            "outputs must have shape ({m}, 2) (inline, cross, E); got {} rows",
            inp.outputs.len()
        ));
    }
    if let Some(k) = inp.azimuth_deg.iter().position(|v| !v.is_finite()) {
        return invalid(format!("azimuth {k} is NaN or inf"));
    }
    if let Some(k) = inp
        .outputs
        .iter()
        .position(|r| !(r[0].is_finite() && r[1].is_finite()))
    {
        return invalid(format!("outputs of dwell {k} contain NaN or inf"));
    }
    if let Some(t) = &inp.t {
        if t.len() != m || t.iter().any(|v| !v.is_finite()) {
            return invalid(format!("t must have {m} finite values (s)"));
        }
    }
    if let Some(s) = &inp.sigma {
        if s.len() != m && s.len() != 2 * m {
            return invalid(format!(
                "sigma must hold {m} values (one per azimuth) or {} (inline, cross of each); \
                 got {}",
                2 * m,
                s.len()
            ));
        }
        if s.iter().any(|v| !(*v > 0.0) || !v.is_finite()) {
            return invalid("sigma must be positive and finite (E)");
        }
    }
    if !(inp.warmup_tau_s > 0.0) || !inp.warmup_tau_s.is_finite() {
        return invalid(format!(
            "warmup_tau_s must be positive and finite (s); got {}",
            inp.warmup_tau_s
        ));
    }
    Ok(())
}

/// Run the gradiometer diagnosis on the requested effects (dictionary indices).
pub fn diagnose(inp: &GradiometerInput, effects: &[usize], opt: &GapOptions) -> Result<GapResult> {
    opt.validate()?;
    check(inp)?;
    let m = inp.azimuth_deg.len();
    let theta: Vec<f64> = inp.azimuth_deg.iter().map(|a| a * DEG).collect();
    let start = fit_startup_bias(&theta, &inp.outputs, None, 0.0, &vec![1.0; m])?;
    let model = GradiometerModel::new(inp);
    let eng = engine::run(&model, &start.params[..N_BASE], effects, opt)?;
    let chan: Vec<f64> = (0..2 * m).map(|r| (r % 2) as f64).collect();
    let location = locate::keyed_location(&eng, Some(&chan), None, opt.alpha);
    let mut sin = StructureInput::default();
    if let Some(t) = &inp.t {
        let tt: Vec<f64> = (0..2 * m).map(|r| t[r / 2]).collect();
        let lo = tt.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = tt.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        let cols = DMatrix::from_fn(2 * m, 4, |r, c| {
            let s = 2.0 * (tt[r] - lo) / (hi - lo).max(1e-300) - 1.0;
            let p = [s * s * 1.5 - 0.5, 2.5 * s * s * s - 1.5 * s][c / 2];
            if r % 2 == c % 2 {
                p
            } else {
                0.0
            }
        });
        sin.smooth.push(SmoothTest::ready("time", cols));
    }
    let st = structure::run(&sin, &eng, opt)?;
    Ok(GapResult {
        system: System::Gradiometer,
        engine: eng,
        location,
        structure: st,
        rows: RowInfo::default(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gap::statics::tests::Rng;

    fn session(seed: u64, drift: [f64; 2], az_err_deg: f64, chan: [f64; 2]) -> GradiometerInput {
        let mut rng = Rng(seed);
        let az: Vec<f64> = (0..12).map(|k| (k as f64 * 67.5) % 180.0).collect();
        let t: Vec<f64> = (0..12).map(|k| 30.0 + 80.0 * k as f64).collect();
        let (b, g) = ([5.0, -3.0], [30.0, -12.0]);
        let tm = t.iter().sum::<f64>() / 12.0;
        let outputs = (0..12)
            .map(|k| {
                let ang = 2.0 * (az[k] + az_err_deg * rng.normal()) * DEG;
                let (s, c) = ang.sin_cos();
                let (mi, mc) = (c * g[0] + s * g[1], -s * g[0] + c * g[1]);
                let th = (t[k] - tm) / 3600.0;
                [
                    b[0] + (1.0 + chan[0]) * mi + chan[1] * mc + drift[0] * th + 0.5 * rng.normal(),
                    b[1] + chan[1] * mi + (1.0 - chan[0]) * mc + drift[1] * th + 0.5 * rng.normal(),
                ]
            })
            .collect();
        GradiometerInput {
            azimuth_deg: az,
            outputs,
            t: Some(t),
            sigma: Some(vec![0.5; 12]),
            warmup_tau_s: 600.0,
        }
    }

    #[test]
    fn drift_azimuth_errors_and_channel_scale_are_found() {
        let all = [0, 1, 2, 3];
        let o = GapOptions::default();
        let r = diagnose(&session(1, [0.0; 2], 0.0, [0.0; 2]), &all, &o).unwrap();
        assert!(r.engine.selected.is_empty(), "{:?}", r.engine.selected);
        let r = diagnose(&session(2, [30.0, -20.0], 0.0, [0.0; 2]), &[0, 1, 2], &o).unwrap();
        assert_eq!(r.engine.selected.first(), Some(&0));
        let est = &r.engine.candidates[0];
        assert!(
            (est.estimate[0] - 30.0).abs() < 5.0 * est.std[0],
            "{:?}",
            est.estimate
        );
        let r = diagnose(&session(3, [0.0; 2], 1.0, [0.0; 2]), &all, &o).unwrap();
        assert_eq!(r.engine.selected.first(), Some(&1));
        let r = diagnose(&session(4, [0.0; 2], 0.0, [0.02, 0.01]), &all, &o).unwrap();
        assert_eq!(r.engine.selected.first(), Some(&2));
        let est = &r.engine.candidates[2];
        assert!(
            (est.estimate[0] - 2.0).abs() < 5.0 * est.std[0] + 0.05,
            "{:?}",
            est.estimate
        );
        // Without times, drift and warm-up cannot be tested.
        let mut s = session(1, [0.0; 2], 0.0, [0.0; 2]);
        s.t = None;
        let r = diagnose(&s, &all, &o).unwrap();
        assert_eq!(r.engine.candidates[0].status, Status::NoTime);
        assert_eq!(r.engine.candidates[3].status, Status::NoTime);
    }

    #[test]
    fn sigma_per_channel_weighs_each_row() {
        let o = GapOptions::default();
        let s = session(1, [0.0; 2], 0.0, [0.0; 2]);
        let per_dwell = diagnose(&s, &[0], &o).unwrap();
        let mut both = s.clone();
        both.sigma = Some(vec![0.5; 24]);
        let same = diagnose(&both, &[0], &o).unwrap();
        assert_eq!(per_dwell.engine.chi2, same.engine.chi2);
        // The cross channel four times noisier: its rows weigh 1/16 in the chi2.
        both.sigma = Some(
            (0..24)
                .map(|r| if r % 2 == 1 { 2.0 } else { 0.5 })
                .collect(),
        );
        let w = diagnose(&both, &[0], &o).unwrap();
        assert!(
            w.engine.chi2 < 0.9 * same.engine.chi2,
            "{} {}",
            w.engine.chi2,
            same.engine.chi2
        );
        both.sigma = Some(vec![0.5; 13]);
        let e = diagnose(&both, &[0], &o).unwrap_err().to_string();
        assert!(e.contains("12 values (one per azimuth) or 24"), "{e}");
    }
}

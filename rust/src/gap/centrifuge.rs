//! The centrifuge session as a [`GapModel`]: the scale + bias + K2 norm model of
//! [`crate::centrifuge`] and its dictionary of unmodelled effects.
//!
//! Per row (outputs `N` in g, spin rate `w0`, nominal radius `R`): the instrument input
//! `h = Phi^-1 S^-1 (N - b)` ([`crate::centrifuge::instrument_input`]), the specific force `f`
//! solving `h_i = f_i + D_i f_i^2 + E_i f_i^3 + sum_j C_ij f_i f_j` per axis
//! ([`crate::centrifuge::inv_axis`], with the cross-coupling by fixed-point iteration), the
//! force at the centre `fc_i = f_i + (w^2/g) [(I - c3 c3^T) r_i]_i` (`r_i` the offset of
//! accelerometer `i`, `c3` the spin axis in the body frame), and the residual
//! `(|fc|^2 - A^2 - 1) / (2 sqrt(A_nom^2 + 1))` with `A = w^2 (R + dR) / g`, `w = |omega + dw|` (omega signed,
//! so a rate offset speeds a forward run and slows a reverse one) and `A_nom` at `w0 = |omega|`.
//!
//! | effect | parameters |
//! |---|---|
//! | lever_along | `r_ii`, mm (3) |
//! | lever_across | `r_ij`, i != j, order x:y, x:z, y:x, y:z, z:x, z:y, mm (6) |
//! | radius_error | `dR`, mm (1) |
//! | k3 | `E_i`, ug/g^3 (3) |
//! | misalignment | `m_yx, m_zx, m_zy`, mrad (3) |
//! | cross_coupling | `C_ij`, i != j, same order, ug/g^2 (6) |
//! | rate_offset | `dw`, added to the signed rate (e.g. the Earth rate `Omega sin(latitude)`), urad/s (1) |
//! | drift | per-axis bias linear in time, `1e-6 p_i s_i th` subtracted from output `i` (`th` hours from the mean row time; the static dictionary's drift), ug/h (3) |
//!
//! Without row times `t` the drift is not testable ([`Status::NoTime`]).
//!
//! Jacobian columns are central finite differences of this residual.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord, clippy::needless_range_loop)]

use super::engine::{self, EffectInfo, GapModel};
use super::structure::{self, StructureInput};
use super::{locate, GapOptions, GapResult, RowInfo, Status, System};
use crate::centrifuge::{self as cf, instrument_input, inv_axis, CentrifugeData, FitOptions};
use crate::error::{invalid, CoreError, Result};
use nalgebra::DMatrix;

/// The centrifuge dictionary, in order.
pub const DICTIONARY: [EffectInfo; 8] = [
    EffectInfo {
        name: "lever_along",
        unit: "mm",
        dim: 3,
    },
    EffectInfo {
        name: "lever_across",
        unit: "mm",
        dim: 6,
    },
    EffectInfo {
        name: "radius_error",
        unit: "mm",
        dim: 1,
    },
    EffectInfo {
        name: "k3",
        unit: "ug/g^3",
        dim: 3,
    },
    EffectInfo {
        name: "misalignment",
        unit: "mrad",
        dim: 3,
    },
    EffectInfo {
        name: "cross_coupling",
        unit: "ug/g^2",
        dim: 6,
    },
    EffectInfo {
        name: "rate_offset",
        unit: "urad/s",
        dim: 1,
    },
    EffectInfo {
        name: "drift",
        unit: "ug/h",
        dim: 3,
    },
];
/// Dictionary index of the drift (needs the row times).
const DRIFT: usize = 7;

/// Off-diagonal (i, j) pairs of the across-axis lever arms and cross-couplings.
const ACROSS: [(usize, usize); 6] = [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1)];
const N_BASE: usize = 9;

/// A centrifuge session: per-row means and their noise.
#[derive(Debug, Clone)]
pub struct CentrifugeInput {
    /// Mean outputs per row, g.
    pub outputs: Vec<[f64; 3]>,
    /// Spin rate per row, rad/s.
    pub omega: Vec<f64>,
    /// Nominal radius, m.
    pub radius: f64,
    /// Gravity used to express `A` in g, m/s^2.
    pub g: f64,
    /// Body-frame spin axis per row (needed for the lever arms).
    pub spin_axis: Option<Vec<[f64; 3]>>,
    /// Noise: per-row std of the norm residual (g), or per-axis output std (g) per row.
    pub noise: Noise,
    /// Time of each row, s (needed for the drift).
    pub t: Option<Vec<f64>>,
}

/// The noise of a centrifuge session.
#[derive(Debug, Clone)]
pub enum Noise {
    /// Unknown: scaled to the baseline fit.
    Unknown,
    /// Standard deviation of each row's norm residual, g.
    Norm(Vec<f64>),
    /// Per-axis standard deviation of each row's outputs, g (propagated to the norm).
    PerAxis(Vec<[f64; 3]>),
}

/// Effect parameters in model units.
#[derive(Debug, Clone, Copy, Default)]
struct Extra {
    lever: [[f64; 3]; 3],
    dr: f64,
    k3: [f64; 3],
    m: [f64; 3],
    cc: [f64; 6],
    dw: f64,
    drift: [f64; 3],
}

/// The model.
#[derive(Debug, Clone)]
pub struct CentrifugeModel {
    inp: CentrifugeInput,
    sig: Vec<f64>,
    noise_known: bool,
    /// Hours from the mean row time (zeros without times).
    th: Vec<f64>,
}

/// Hours from the mean of `t` (s); zeros without times.
fn hours(t: Option<&Vec<f64>>, n: usize) -> Vec<f64> {
    match t {
        Some(t) if !t.is_empty() => {
            let mid = t.iter().sum::<f64>() / t.len() as f64;
            t.iter().map(|v| (v - mid) / 3600.0).collect()
        }
        _ => vec![0.0; n],
    }
}

impl CentrifugeModel {
    fn extra(&self, active: &[usize], p: &[f64]) -> Extra {
        let mut x = Extra::default();
        let mut off = N_BASE;
        for &c in active {
            let q = &p[off..off + DICTIONARY[c].dim];
            match c {
                0 => (0..3).for_each(|i| x.lever[i][i] = 1e-3 * q[i]),
                1 => ACROSS
                    .iter()
                    .enumerate()
                    .for_each(|(j, &(a, b))| x.lever[a][b] = 1e-3 * q[j]),
                2 => x.dr = 1e-3 * q[0],
                3 => (0..3).for_each(|i| x.k3[i] = 1e-6 * q[i]),
                4 => (0..3).for_each(|i| x.m[i] = 1e-3 * q[i]),
                5 => (0..6).for_each(|j| x.cc[j] = 1e-6 * q[j]),
                6 => x.dw = 1e-6 * q[0],
                _ => (0..3).for_each(|i| x.drift[i] = 1e-6 * q[i]),
            }
            off += DICTIONARY[c].dim;
        }
        x
    }

    /// Unweighted norm residual (g) of row `k`.
    fn residual(&self, k: usize, p: &[f64], x: &Extra) -> f64 {
        let s = [p[0], p[1], p[2]];
        let b = [p[3], p[4], p[5]];
        let d = [p[6], p[7], p[8]];
        // A bias drifting in time: `1e-6 p_i` g per hour, in output units (scale s_i per g).
        let th = self.th[k];
        let out = self.inp.outputs[k];
        let out = [0, 1, 2].map(|i| out[i] - x.drift[i] * s[i] * th);
        let h = instrument_input(&out, &s, &b, &x.m);
        let mut f = [0.0; 3];
        for _ in 0..8 {
            let mut nf = [0.0; 3];
            for i in 0..3 {
                let hc: f64 = ACROSS
                    .iter()
                    .enumerate()
                    .filter(|(_, (a, _))| *a == i)
                    .map(|(j, &(a, bb))| x.cc[j] * f[a] * f[bb])
                    .sum();
                match inv_axis(h[i] - hc, d[i], x.k3[i]) {
                    Some((v, _)) => nf[i] = v,
                    None => return f64::NAN,
                }
            }
            let done = (0..3).all(|i| (nf[i] - f[i]).abs() <= 1e-15 * (1.0 + nf[i].abs()));
            f = nf;
            if done || x.cc.iter().all(|c| *c == 0.0) {
                break;
            }
        }
        // The rate offset adds to the signed rate (the Earth rate turns a forward run faster
        // and a reverse run slower); only its magnitude enters the centripetal term.
        let w0 = self.inp.omega[k].abs();
        let w = (self.inp.omega[k] + x.dw).abs();
        let w2g = w * w / self.inp.g;
        let c3 = self.inp.spin_axis.as_ref().map_or([0.0; 3], |sa| sa[k]);
        let mut n2 = 0.0;
        for i in 0..3 {
            let r = &x.lever[i];
            let cr = c3[0] * r[0] + c3[1] * r[1] + c3[2] * r[2];
            let fc = f[i] + w2g * (r[i] - c3[i] * cr);
            n2 += fc * fc;
        }
        let a_nom = w0 * w0 * self.inp.radius / self.inp.g;
        let a = w * w * (self.inp.radius + x.dr) / self.inp.g;
        (n2 - a * a - 1.0) / (2.0 * (a_nom * a_nom + 1.0).sqrt())
    }

    fn step(c: usize) -> f64 {
        match c {
            0..=5 => 1e-6,
            6..=8 => 1e-7,
            _ => 1.0,
        }
    }

    /// Whitened residuals of `rows` and central differences of them in the parameters `cols`
    /// (indices into `p`), with `active` effects.
    fn fd(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        cols: &[usize],
        e: &mut [f64],
        jac: &mut DMatrix<f64>,
    ) -> Result<()> {
        let x = self.extra(active, p);
        for (ri, &k) in rows.iter().enumerate() {
            e[ri] = self.residual(k, p, &x) / self.sig[k];
        }
        let mut pp = p.to_vec();
        for (jc, &c) in cols.iter().enumerate() {
            let h = if c < N_BASE { Self::step(c) } else { 1.0 };
            pp[c] = p[c] + h;
            let xp = self.extra(active, &pp);
            let plus: Vec<f64> = rows.iter().map(|&k| self.residual(k, &pp, &xp)).collect();
            pp[c] = p[c] - h;
            let xm = self.extra(active, &pp);
            for (ri, &k) in rows.iter().enumerate() {
                let m = self.residual(k, &pp, &xm);
                jac[(ri, jc)] = (plus[ri] - m) / (2.0 * h) / self.sig[k];
            }
            pp[c] = p[c];
        }
        let bad = rows.iter().enumerate().find(|&(ri, _)| {
            !e[ri].is_finite() || (0..cols.len()).any(|jc| !jac[(ri, jc)].is_finite())
        });
        if let Some((_, &k)) = bad {
            return Err(CoreError::NotConverged(format!(
                "centrifuge row {k} is outside the invertible range of the model near its \
                 fit (no real input gives that output with the fitted K2): a gross error in \
                 the row, or rows that spoil the fit"
            )));
        }
        Ok(())
    }
}

impl GapModel for CentrifugeModel {
    fn n_rows(&self) -> usize {
        self.inp.outputs.len()
    }
    fn n_base(&self) -> usize {
        N_BASE
    }
    fn dictionary(&self) -> &[EffectInfo] {
        &DICTIONARY
    }
    fn unavailable(&self, c: usize) -> Option<Status> {
        if c <= 1 && self.inp.spin_axis.is_none() {
            Some(Status::NoSpinAxis)
        } else {
            (c == DRIFT && self.inp.t.is_none()).then_some(Status::NoTime)
        }
    }
    fn noise_known(&self) -> bool {
        self.noise_known
    }
    fn eval(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        e: &mut [f64],
        jac: &mut DMatrix<f64>,
    ) -> Result<()> {
        let cols: Vec<usize> = (0..p.len()).collect();
        self.fd(rows, active, p, &cols, e, jac)
    }
    fn columns(
        &self,
        rows: &[usize],
        active: &[usize],
        p: &[f64],
        c: usize,
    ) -> Result<DMatrix<f64>> {
        let mut act = active.to_vec();
        act.push(c);
        let mut pc = p.to_vec();
        let dim = DICTIONARY[c].dim;
        pc.extend(std::iter::repeat_n(0.0, dim));
        let cols: Vec<usize> = (p.len()..p.len() + dim).collect();
        let mut e = vec![0.0; rows.len()];
        let mut out = DMatrix::zeros(rows.len(), dim);
        self.fd(rows, &act, &pc, &cols, &mut e, &mut out)?;
        Ok(out)
    }
    fn sigma(&self, rows: &[usize], _active: &[usize], _p: &[f64]) -> Result<Vec<f64>> {
        Ok(rows.iter().map(|&k| self.sig[k]).collect())
    }
}

fn check(inp: &CentrifugeInput) -> Result<()> {
    let k = inp.outputs.len();
    if let Some(sa) = &inp.spin_axis {
        if sa.len() != k {
            return invalid(format!("spin_axis must have {k} rows; got {}", sa.len()));
        }
        if let Some(r) = sa.iter().position(|c| c.iter().any(|v| !v.is_finite())) {
            return invalid(format!("spin_axis row {r} is not finite"));
        }
    }
    if let Some(t) = &inp.t {
        if t.len() != k {
            return invalid(format!("t must have {k} values (s); got {}", t.len()));
        }
        if t.iter().any(|v| !v.is_finite()) {
            return invalid("t must be finite (s)");
        }
    }
    match &inp.noise {
        Noise::Unknown => Ok(()),
        Noise::Norm(s) if s.len() != k => invalid(format!("sigma must have {k} values")),
        Noise::PerAxis(s) if s.len() != k => invalid(format!("sigma must have {k} rows")),
        Noise::Norm(s) if s.iter().any(|v| !(*v > 0.0) || !v.is_finite()) => {
            invalid("sigma must be positive and finite (g)")
        }
        Noise::PerAxis(s) if s.iter().flatten().any(|v| !(*v > 0.0) || !v.is_finite()) => {
            invalid("sigma must be positive and finite (g)")
        }
        _ => Ok(()),
    }
}

/// Baseline start (the centrifuge fit without screening) and the per-row noise of the norm.
fn start_and_noise(inp: &CentrifugeInput) -> Result<(Vec<f64>, Vec<f64>)> {
    let data = CentrifugeData {
        outputs: &inp.outputs,
        omega: &inp.omega,
        radius: inp.radius,
        g: inp.g,
        sigma: None,
        spin_axis: None,
    };
    let fit = cf::fit(
        &data,
        &FitOptions {
            robust: false,
            ..FitOptions::default()
        },
    )?;
    let p = fit.params[..N_BASE].to_vec();
    let sig = match &inp.noise {
        Noise::Unknown => vec![1.0; inp.outputs.len()],
        Noise::Norm(s) => s.clone(),
        Noise::PerAxis(s) => (0..s.len())
            .map(|k| {
                let a = inp.omega[k].powi(2) * inp.radius / inp.g;
                let n2: f64 = (0..3)
                    .map(|i| {
                        let f = (inp.outputs[k][i] - p[3 + i]) / p[i];
                        (f / p[i] * s[k][i]).powi(2)
                    })
                    .sum();
                n2.sqrt() / (a * a + 1.0).sqrt()
            })
            .collect(),
    };
    if let Some(k) = sig.iter().position(|v| !(*v > 0.0) || !v.is_finite()) {
        return invalid(format!(
            "the noise of row {k} propagates to a zero or non-finite norm noise"
        ));
    }
    Ok((p, sig))
}

/// Run the centrifuge diagnosis on the requested effects (dictionary indices).
pub fn diagnose(inp: &CentrifugeInput, effects: &[usize], opt: &GapOptions) -> Result<GapResult> {
    opt.validate()?;
    check(inp)?;
    let (start, sig) = start_and_noise(inp)?;
    let model = CentrifugeModel {
        inp: inp.clone(),
        noise_known: !matches!(inp.noise, Noise::Unknown),
        sig,
        th: hours(inp.t.as_ref(), inp.outputs.len()),
    };
    let eng = engine::run(&model, &start, effects, opt)?;
    let speeds: Vec<f64> = inp
        .omega
        .iter()
        .map(|w| (w.abs() * 1e6).round() / 1e6)
        .collect();
    let location = locate::keyed_location(&eng, None, Some(&speeds), opt.alpha);
    let st = structure::run(&StructureInput::default(), &eng, opt)?;
    Ok(GapResult {
        system: System::Centrifuge,
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

    /// Paper-like design: 20 positions (random body-frame radial directions, spin axis
    /// perpendicular) x 3 speeds, scale/bias/K2 truth, optional lever arm along the axes.
    fn session(lever_mm: [f64; 3], dw: f64, noise: f64) -> CentrifugeInput {
        let pi = std::f64::consts::PI;
        session_at(&[2.0 * pi, 4.0 * pi, 6.0 * pi], lever_mm, dw, noise)
    }

    /// [`session`] at the signed rates `rates` (rad/s; negative = reverse run): the rate
    /// offset `dw` adds to the signed rate, as the Earth rate does.
    fn session_at(rates: &[f64], lever_mm: [f64; 3], dw: f64, noise: f64) -> CentrifugeInput {
        let mut rng = Rng(17);
        let (g, radius) = (9.8, 1.0);
        let s = [1.29, 1.21, 1.26];
        let b = [0.213, 0.256, 0.516];
        let d = [0.57e-4, 0.31e-4, 0.45e-4];
        let (mut outputs, mut omega, mut axes) = (vec![], vec![], vec![]);
        for &w0 in rates {
            for _ in 0..20 {
                let mut rad = [rng.normal(), rng.normal(), rng.normal()];
                let nr = (rad.iter().map(|v| v * v).sum::<f64>()).sqrt();
                rad.iter_mut().for_each(|v| *v /= nr);
                let mut c3 = [rng.normal(), rng.normal(), rng.normal()];
                let dot: f64 = (0..3).map(|i| c3[i] * rad[i]).sum();
                (0..3).for_each(|i| c3[i] -= dot * rad[i]);
                let nc = (c3.iter().map(|v| v * v).sum::<f64>()).sqrt();
                c3.iter_mut().for_each(|v| *v /= nc);
                let w = w0 + dw;
                let a = w * w * radius / g;
                let mut out = [0.0; 3];
                for i in 0..3 {
                    // Force at the accelerometer: centre force - w^2/g * its offset (model sign).
                    let fi =
                        a * rad[i] + c3[i] - w * w / g * 1e-3 * lever_mm[i] * (1.0 - c3[i] * c3[i]);
                    out[i] = s[i] * (fi + d[i] * fi * fi) + b[i] + noise * rng.normal();
                }
                outputs.push(out);
                omega.push(w0);
                axes.push(c3);
            }
        }
        CentrifugeInput {
            outputs,
            omega,
            radius,
            g,
            spin_axis: Some(axes),
            noise: Noise::PerAxis(vec![[noise; 3]; 20 * rates.len()]),
            t: None,
        }
    }

    #[test]
    fn drift_is_found_with_row_times_and_not_tested_without() {
        // A bias drifting 30, -20, 25 ug/h over a 2 h run (rows in time order): with the row
        // times the drift is named and estimated; without them it is not testable.
        let mut s = session([0.0; 3], 0.0, 2e-6);
        let n = s.outputs.len();
        let t: Vec<f64> = (0..n).map(|k| 7200.0 * k as f64 / (n - 1) as f64).collect();
        let scale = [1.29, 1.21, 1.26];
        let rate = [30.0, -20.0, 25.0];
        for (k, out) in s.outputs.iter_mut().enumerate() {
            let th = (t[k] - 3600.0) / 3600.0;
            (0..3).for_each(|i| out[i] += 1e-6 * rate[i] * scale[i] * th);
        }
        let all: Vec<usize> = (0..DICTIONARY.len()).collect();
        let r = diagnose(&s, &all, &GapOptions::default()).unwrap();
        assert_eq!(r.engine.candidates[DRIFT].status, Status::NoTime);
        assert!(!r.engine.selected.contains(&DRIFT));
        s.t = Some(t);
        let r = diagnose(&s, &all, &GapOptions::default()).unwrap();
        assert_eq!(
            r.engine.selected.first(),
            Some(&DRIFT),
            "{:?}",
            r.engine.selected
        );
        let est = &r.engine.candidates[DRIFT];
        for i in 0..3 {
            assert!(
                (est.estimate[i] - rate[i]).abs() < 5.0 * est.std[i],
                "{:?} +- {:?}",
                est.estimate,
                est.std
            );
        }
        // Times of the wrong length are refused.
        s.t = Some(vec![0.0; 3]);
        assert!(diagnose(&s, &all, &GapOptions::default()).is_err());
    }

    #[test]
    fn rate_offset_adds_to_the_signed_rate_of_forward_and_reverse_runs() {
        // Forward and reverse runs with an Earth-rate-like offset: the forward runs turn
        // faster, the reverse runs slower. An offset added to |omega| could not fit both.
        let pi = std::f64::consts::PI;
        let rates = [
            2.0 * pi,
            -2.0 * pi,
            4.0 * pi,
            -4.0 * pi,
            6.0 * pi,
            -6.0 * pi,
        ];
        let all: Vec<usize> = (0..7).collect();
        let s = session_at(&rates, [0.0; 3], 45.9e-6, 1e-6);
        let r = diagnose(&s, &all, &GapOptions::default()).unwrap();
        assert_eq!(
            r.engine.selected.first(),
            Some(&6),
            "{:?}",
            r.engine.selected
        );
        let est = &r.engine.candidates[6];
        assert!(
            (est.estimate[0] - 45.9).abs() < 5.0 * est.std[0],
            "{:?} +- {:?}",
            est.estimate,
            est.std
        );
    }

    #[test]
    fn lever_arm_and_rate_offset_are_found() {
        let all: Vec<usize> = (0..7).collect();
        let r = diagnose(&session([0.0; 3], 0.0, 2e-6), &all, &GapOptions::default()).unwrap();
        assert!(r.engine.selected.is_empty(), "{:?}", r.engine.selected);
        let r = diagnose(
            &session([0.04, -0.03, 0.02], 0.0, 2e-6),
            &all,
            &GapOptions::default(),
        )
        .unwrap();
        assert_eq!(r.engine.selected.first(), Some(&0));
        let est = &r.engine.candidates[0];
        for (i, want) in [0.04, -0.03, 0.02].iter().enumerate() {
            assert!(
                (est.estimate[i] - want).abs() < 5.0 * est.std[i] + 1e-3,
                "{:?}",
                est.estimate
            );
        }
        // Earth rate at 39 deg: 45.9 urad/s added to the spin rate.
        let r = diagnose(
            &session([0.0; 3], 45.9e-6, 2e-6),
            &all,
            &GapOptions::default(),
        )
        .unwrap();
        assert_eq!(r.engine.selected.first(), Some(&6));
        let est = &r.engine.candidates[6];
        assert!(
            (est.estimate[0] - 45.9).abs() < 5.0 * est.std[0],
            "{:?}",
            est.estimate
        );
        // No spin axis: lever arms are not testable.
        let mut s = session([0.0; 3], 0.0, 2e-6);
        s.spin_axis = None;
        let r = diagnose(&s, &all, &GapOptions::default()).unwrap();
        assert_eq!(r.engine.candidates[0].status, Status::NoSpinAxis);
    }
}

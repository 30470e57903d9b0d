//! Exact tail probabilities (chi2, F, normal) and their inverses, without SciPy.

// `!(x > 0.0)` is deliberate throughout: it is also true for NaN.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

fn ln_gamma(x: f64) -> f64 {
    // Lanczos (g = 7, n = 9), |rel err| < 1e-13 for x > 0.
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Series of the regularised lower incomplete gamma `P(a, x)` (converges for `x < a + 1`).
fn gamma_p_series(a: f64, x: f64, lg: f64) -> f64 {
    let (mut sum, mut del, mut ap) = (1.0 / a, 1.0 / a, a);
    for _ in 0..1000 {
        ap += 1.0;
        del *= x / ap;
        sum += del;
        if del.abs() < sum.abs() * 1e-15 {
            break;
        }
    }
    sum * (-x + a * x.ln() - lg).exp()
}

/// Continued fraction of the regularised upper incomplete gamma `Q(a, x)` (`x >= a + 1`).
fn gamma_q_cf(a: f64, x: f64, lg: f64) -> f64 {
    let tiny = 1e-300;
    let mut b = x + 1.0 - a;
    let mut c = 1.0 / tiny;
    let mut d = 1.0 / b;
    let mut h = d;
    for i in 1..1000 {
        let an = -(i as f64) * (i as f64 - a);
        b += 2.0;
        d = an * d + b;
        if d.abs() < tiny {
            d = tiny;
        }
        c = b + an / c;
        if c.abs() < tiny {
            c = tiny;
        }
        d = 1.0 / d;
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-15 {
            break;
        }
    }
    (-x + a * x.ln() - lg).exp() * h
}

/// Regularised upper incomplete gamma `Q(a, x)`.
fn gamma_q(a: f64, x: f64) -> f64 {
    if !(x > 0.0) {
        return 1.0;
    }
    if !x.is_finite() {
        return 0.0;
    }
    let lg = ln_gamma(a);
    if x < a + 1.0 {
        (1.0 - gamma_p_series(a, x, lg)).clamp(0.0, 1.0)
    } else {
        gamma_q_cf(a, x, lg).clamp(0.0, 1.0)
    }
}

fn beta_cf(a: f64, b: f64, x: f64) -> f64 {
    let tiny = 1e-300;
    let guard = |v: f64| if v.abs() < tiny { tiny } else { v };
    let (qab, qap, qam) = (a + b, a + 1.0, a - 1.0);
    let mut c = 1.0;
    let mut d = 1.0 / guard(1.0 - qab * x / qap);
    let mut h = d;
    for m in 1..1000 {
        let m = m as f64;
        let m2 = 2.0 * m;
        let aa = m * (b - m) * x / ((qam + m2) * (a + m2));
        d = 1.0 / guard(1.0 + aa * d);
        c = guard(1.0 + aa / c);
        h *= d * c;
        let aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2));
        d = 1.0 / guard(1.0 + aa * d);
        c = guard(1.0 + aa / c);
        let del = d * c;
        h *= del;
        if (del - 1.0).abs() < 1e-15 {
            break;
        }
    }
    h
}

/// Regularised incomplete beta `I_x(a, b)`.
fn beta_inc(a: f64, b: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 0.0;
    }
    if x >= 1.0 {
        return 1.0;
    }
    let ln_bt = ln_gamma(a + b) - ln_gamma(a) - ln_gamma(b) + a * x.ln() + b * (1.0 - x).ln();
    let bt = ln_bt.exp();
    if x < (a + 1.0) / (a + b + 2.0) {
        (bt * beta_cf(a, b, x) / a).clamp(0.0, 1.0)
    } else {
        (1.0 - bt * beta_cf(b, a, 1.0 - x) / b).clamp(0.0, 1.0)
    }
}

/// Survival function of chi2 with `k` degrees of freedom (NaN for `k <= 0` or NaN `x`).
pub fn chi2_sf(x: f64, k: f64) -> f64 {
    if !(k > 0.0) || x.is_nan() {
        return f64::NAN;
    }
    gamma_q(0.5 * k, 0.5 * x)
}

/// Survival function of F(d1, d2) (NaN for non-positive degrees of freedom or NaN `f`).
pub fn f_sf(f: f64, d1: f64, d2: f64) -> f64 {
    if !(d1 > 0.0 && d2 > 0.0) || f.is_nan() {
        return f64::NAN;
    }
    if f <= 0.0 {
        return 1.0;
    }
    if !f.is_finite() {
        return 0.0;
    }
    beta_inc(0.5 * d2, 0.5 * d1, d2 / (d2 + d1 * f))
}

/// Upper-tail quantile of a decreasing survival function: the `x >= 0` with `sf(x) = p`.
fn isf_of(p: f64, sf: impl Fn(f64) -> f64) -> f64 {
    if !(p > 0.0 && p < 1.0) {
        return if p >= 1.0 { 0.0 } else { f64::NAN };
    }
    let (mut lo, mut hi) = (0.0, 1.0);
    let mut it = 0;
    while sf(hi) > p && it < 1100 {
        lo = hi;
        hi *= 2.0;
        it += 1;
    }
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if sf(mid) > p {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo <= 1e-12 * hi {
            break;
        }
    }
    hi
}

/// Inverse survival function of chi2(`k`).
pub fn chi2_isf(p: f64, k: f64) -> f64 {
    isf_of(p, |x| chi2_sf(x, k))
}

/// Inverse survival function of F(`d1`, `d2`).
pub fn f_isf(p: f64, d1: f64, d2: f64) -> f64 {
    isf_of(p, |x| f_sf(x, d1, d2))
}

/// The `|z|` exceeded by a standard normal with two-sided probability `p`.
pub fn normal_two_sided_isf(p: f64) -> f64 {
    chi2_isf(p, 1.0).sqrt()
}

/// Pearson correlation of two series and its two-sided p-value (exact, Student t with
/// `n - 2` degrees of freedom); NaN when fewer than 4 points or a series is constant.
pub fn pearson(x: &[f64], y: &[f64]) -> (f64, f64) {
    let n = x.len().min(y.len());
    if n < 4 {
        return (f64::NAN, f64::NAN);
    }
    let nf = n as f64;
    let (mx, my) = (
        x[..n].iter().sum::<f64>() / nf,
        y[..n].iter().sum::<f64>() / nf,
    );
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for k in 0..n {
        let (a, b) = (x[k] - mx, y[k] - my);
        sxy += a * b;
        sxx += a * a;
        syy += b * b;
    }
    if !(sxx > 0.0 && syy > 0.0) {
        return (f64::NAN, f64::NAN);
    }
    let r = (sxy / (sxx * syy).sqrt()).clamp(-1.0, 1.0);
    let t2 = r * r * (nf - 2.0) / (1.0 - r * r).max(1e-300);
    (r, f_sf(t2, 1.0, nf - 2.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn p_values_match_tables() {
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-10);
        assert!((chi2_sf(18.307_038_053_275_146, 10.0) - 0.05).abs() < 1e-10);
        assert!((f_sf(3.708_264_819_046_843_5, 3.0, 10.0) - 0.05).abs() < 1e-9);
        assert!((f_sf(1.0, 5.0, 5.0) - 0.5).abs() < 1e-12);
        assert!((chi2_isf(0.05, 10.0) - 18.307_038_053_275_146).abs() < 1e-8);
        assert!((f_isf(0.05, 3.0, 10.0) - 3.708_264_819_046_843_5).abs() < 1e-8);
        // Two-sided normal: 1.959964 at 5 %.
        assert!((normal_two_sided_isf(0.05) - 1.959_963_984_540_054).abs() < 1e-8);
        assert!(chi2_sf(f64::NAN, 3.0).is_nan() && chi2_sf(1.0, 0.0).is_nan());
    }

    #[test]
    fn pearson_matches_a_closed_form() {
        // y = x + small alternating: r close to 1; p tiny. Constant series: NaN.
        let x: Vec<f64> = (0..20).map(|k| k as f64).collect();
        let y: Vec<f64> = x
            .iter()
            .enumerate()
            .map(|(k, v)| v + if k % 2 == 0 { 0.5 } else { -0.5 })
            .collect();
        let (r, p) = pearson(&x, &y);
        assert!(r > 0.99 && p < 1e-10, "{r} {p}");
        // Orthogonal patterns: r = 0, p = 1.
        let a = [1.0, -1.0, 1.0, -1.0];
        let b = [1.0, 1.0, -1.0, -1.0];
        let (r, p) = pearson(&a, &b);
        assert!(r.abs() < 1e-12 && (p - 1.0).abs() < 1e-9);
        assert!(pearson(&[1.0; 5], &x[..5]).0.is_nan());
    }
}

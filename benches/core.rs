//! Criterion benchmarks of the core kernels (`cargo bench --bench core`).
//!
//! Shared file: each domain adds its own `fn bench_<domain>` and lists it in `criterion_group!`.

use std::hint::black_box;

use accelcal::dwell::dwell_moments;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ndarray::Array2;
use rayon::prelude::*;

/// 20 dwells x 20 s x 5 kHz: the seed-000 field test.
const DWELLS: usize = 20;
const ROWS_PER_DWELL: usize = 20 * 5000;

fn dwell_workload<T>(f: impl Fn(f64) -> T) -> (Array2<T>, Vec<[usize; 2]>) {
    let n = DWELLS * ROWS_PER_DWELL;
    let mut s = 0x9e37_79b9_7f4a_7c15_u64;
    let x = Array2::from_shape_fn((n, 3), |_| {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        f(((s >> 11) as f64) / ((1u64 << 53) as f64))
    });
    let bounds = (0..DWELLS)
        .map(|k| [k * ROWS_PER_DWELL, (k + 1) * ROWS_PER_DWELL])
        .collect();
    (x, bounds)
}

/// Sum of `x` with 16 independent accumulators (vectorised; memory-bound on large buffers).
fn plain_sum(x: &[f64]) -> f64 {
    let mut acc = [0.0f64; 16];
    let mut it = x.chunks_exact(16);
    for c in &mut it {
        for (a, v) in acc.iter_mut().zip(c) {
            *a += v;
        }
    }
    acc.iter().sum::<f64>() + it.remainder().iter().sum::<f64>()
}

fn bench_dwell(c: &mut Criterion) {
    let mut g = c.benchmark_group("dwell_moments");
    g.sample_size(20);

    let (x, bounds) = dwell_workload(|u| 9.80665 + 1e-3 * (u - 0.5));
    g.throughput(Throughput::Bytes((x.len() * 8) as u64));
    g.bench_function("f64_20x20s_5kHz_48MB", |b| {
        b.iter(|| black_box(dwell_moments(&x.view(), black_box(&bounds)).unwrap()))
    });
    // The memory-read ceiling of the same buffer in the same process: a plain vectorised sum,
    // on one thread and split per dwell over the rayon pool as the kernel is.
    let flat = x.as_slice().expect("a fresh array is contiguous");
    g.bench_function("ceiling_sum_f64_48MB_1thread", |b| {
        b.iter(|| black_box(plain_sum(black_box(flat))))
    });
    g.bench_function("ceiling_sum_f64_48MB_pool", |b| {
        b.iter(|| {
            black_box(
                black_box(flat)
                    .par_chunks(3 * ROWS_PER_DWELL)
                    .map(plain_sum)
                    .sum::<f64>(),
            )
        })
    });

    let (x, bounds) = dwell_workload(|u| (-32000.0 + 20.0 * u) as i16);
    g.throughput(Throughput::Bytes((x.len() * 2) as u64));
    g.bench_function("i16_20x20s_5kHz_12MB", |b| {
        b.iter(|| black_box(dwell_moments(&x.view(), black_box(&bounds)).unwrap()))
    });
    g.finish();
}

/// 4 dwells x 250 s x 1 kHz of a1..a4 plus phase (40 MB): 2-omega demodulation.
fn bench_gradiometer(c: &mut Criterion) {
    let (rows, dwells) = (250_000usize, 4usize);
    let n = rows * dwells;
    let w = std::f64::consts::TAU * 0.5 / 1000.0;
    let phase: Vec<f64> = (0..n).map(|j| w * j as f64).collect();
    let x = Array2::from_shape_fn((n, 4), |(j, i)| {
        let p = phase[j] + i as f64 * std::f64::consts::FRAC_PI_2;
        4e-9 * (2.0 * p).sin() + 1e-4 * p.cos()
    });
    let bounds: Vec<[usize; 2]> = (0..dwells).map(|k| [k * rows, (k + 1) * rows]).collect();
    let mut g = c.benchmark_group("gradiometer_demodulate");
    g.sample_size(20);
    g.throughput(Throughput::Bytes((x.len() * 8 + n * 8) as u64));
    g.bench_function("f64_4x250s_1kHz_40MB", |b| {
        b.iter(|| {
            black_box(
                accelcal::gradiometer::demodulate(&x.view(), black_box(&phase), &bounds, 0.1)
                    .unwrap(),
            )
        })
    });
    g.finish();
}

/// The norm-observation paper's simulation: 20 dwells, tilts +-30 deg (the weak-design case,
/// where the power iteration of the observability check runs too) and the full sphere,
/// sigma 1e-3 per axis; the default fit (exact quadric start, ML iteration, covariance,
/// observability), with the noise estimated and given, and the batch over 2000 sessions.
fn bench_static(c: &mut Criterion) {
    use accelcal::static_fit::{fit_batch, fit_static, FitSettings, Method, Model, Noise};
    let truth = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03];
    let g = 9.80665;
    let mut seed: u64 = 42;
    let mut rnd = move || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    let sessions = 2000usize;
    let n = 20usize;
    let mut simulate = |tilt: f64| -> Vec<[f64; 3]> {
        (0..sessions * n)
            .map(|_| {
                let (tx, ty) = (rnd() * tilt, rnd() * tilt);
                let a = [
                    -g * ty.sin(),
                    g * tx.sin() * ty.cos(),
                    g * tx.cos() * ty.cos(),
                ];
                let am = [
                    truth[0] * a[0] + truth[3],
                    truth[6] * a[0] + truth[1] * a[1] + truth[4],
                    truth[7] * a[0] + truth[8] * a[1] + truth[2] * a[2] + truth[5],
                ];
                am.map(|v| v + 1e-3 * 1.7320508 * rnd())
            })
            .collect()
    };
    let tilt30 = simulate(std::f64::consts::FRAC_PI_6);
    let sphere = simulate(std::f64::consts::PI);
    let var = vec![[1e-6; 3]; n];
    let mut grp = c.benchmark_group("static_fit");
    for (name, method) in [("quadric_n20", Method::Quadric), ("lm_n20", Method::Lm)] {
        let mut set = FitSettings::new(Model::Lower, method);
        set.raise_degenerate = false;
        for (design, all) in [("30deg", &tilt30), ("sphere", &sphere)] {
            let means = &all[..n];
            grp.bench_function(format!("{name}_{design}"), |b| {
                b.iter(|| black_box(fit_static(black_box(means), g, &Noise::Estimated, &set)))
            });
            grp.bench_function(format!("{name}_{design}_sigma"), |b| {
                b.iter(|| black_box(fit_static(black_box(means), g, &Noise::Known(&var), &set)))
            });
        }
    }
    // The stages alone, on the first session of each design: the normal equations of the ML
    // cost (one evaluation) and the quadric start.
    for (design, all) in [("30deg", &tilt30), ("sphere", &sphere)] {
        use accelcal::static_fit::{cost::DwellNoise, start::quadric_beta, NormProblem};
        let means = &all[..n];
        let f = accelcal::static_fit::frame::Frame::centroid(means, g).unwrap();
        let prob = NormProblem {
            pts: means,
            g,
            noise: DwellNoise::Isotropic,
            model: Model::Lower,
            kmax: f64::INFINITY,
        };
        let p = [1.1, 0.95, 1.2, 0.3, -0.6, 0.3, 0.01, 0.02, 0.03];
        grp.bench_function(format!("normal_equations_n20_{design}"), |b| {
            b.iter(|| {
                let (mut h, mut gr) = ([[0.0; 9]; 9], [0.0; 9]);
                black_box(
                    prob.accumulate::<9>(black_box(&p), &mut h, &mut gr)
                        .unwrap(),
                );
                black_box((h, gr))
            })
        });
        grp.bench_function(format!("quadric_start_n20_{design}"), |b| {
            b.iter(|| black_box(quadric_beta(black_box(means), f, false, false).unwrap()))
        });
    }
    let set = FitSettings::new(Model::Lower, Method::Lm);
    grp.sample_size(20);
    grp.throughput(Throughput::Elements(sessions as u64));
    for (design, all) in [("30deg", &tilt30), ("sphere", &sphere)] {
        let refs: Vec<&[[f64; 3]]> = all.chunks(n).collect();
        grp.bench_function(format!("batch_2000x20_lm_{design}"), |b| {
            b.iter(|| black_box(fit_batch(black_box(&refs), &[g], Some(1e-3), &set).unwrap()))
        });
    }
    grp.finish();
}

/// Centrifuge nls fit (scale + bias + K2) on the seed-004 sign-corrected table: 60 rows,
/// R = 1 m, g = 9.8 (the issue-4 workload of `benches/bench_centrifuge.py`, without Python).
fn bench_centrifuge(c: &mut Criterion) {
    use accelcal::centrifuge::{fit, CentrifugeData, FitOptions};
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../shared/data/seed004/table1_sign_corrected.csv"
    );
    let Ok(text) = std::fs::read_to_string(path) else {
        eprintln!("bench_centrifuge: {path} not found, skipped");
        return;
    };
    let (mut outputs, mut omega) = (Vec::new(), Vec::new());
    for line in text.lines().skip(1).filter(|l| !l.trim().is_empty()) {
        let v: Vec<f64> = line.split(',').map(|x| x.trim().parse().unwrap()).collect();
        omega.push(v[1]);
        outputs.push([v[3], v[4], v[5]]);
    }
    let data = CentrifugeData {
        outputs: &outputs,
        omega: &omega,
        radius: 1.0,
        g: 9.8,
        sigma: None,
        spin_axis: None,
    };
    let opt = FitOptions::default();
    let mut g = c.benchmark_group("centrifuge_fit");
    g.bench_function("nls_seed004_60rows", |b| {
        b.iter(|| black_box(fit(black_box(&data), &opt).unwrap()))
    });
    g.finish();
}

criterion_group!(
    benches,
    bench_dwell,
    bench_gradiometer,
    bench_static,
    bench_centrifuge
);
criterion_main!(benches);

//! Criterion benchmarks of the core kernels (`cargo bench --bench core`).
//!
//! Shared file: each domain adds its own `fn bench_<domain>` and lists it in `criterion_group!`.

use std::hint::black_box;

use accelcal::dwell::dwell_moments;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ndarray::Array2;

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

fn bench_dwell(c: &mut Criterion) {
    let mut g = c.benchmark_group("dwell_moments");
    g.sample_size(20);

    let (x, bounds) = dwell_workload(|u| 9.80665 + 1e-3 * (u - 0.5));
    g.throughput(Throughput::Bytes((x.len() * 8) as u64));
    g.bench_function("f64_20x20s_5kHz_48MB", |b| {
        b.iter(|| black_box(dwell_moments(&x.view(), black_box(&bounds)).unwrap()))
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

criterion_group!(benches, bench_dwell, bench_gradiometer);
criterion_main!(benches);

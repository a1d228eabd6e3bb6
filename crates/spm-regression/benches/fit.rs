//! Least-squares fit throughput: degree-3 surface over 10⁴ and 10⁶ points, BIC selection over
//! 10⁴ points.
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, criterion_group, criterion_main};
use spm_regression::{FitOptions, Observations, SelectionOptions, fit, select_degree};

fn data(n: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let side = (n as f64).sqrt().ceil() as usize;
    let mut xs = Vec::with_capacity(n);
    let mut ys = Vec::with_capacity(n);
    let mut zs = Vec::with_capacity(n);
    for k in 0..n {
        let (i, j) = ((k % side) as f64, (k / side) as f64);
        let (x, y) = (i * 60.0, j * 60.0);
        xs.push(x);
        ys.push(y);
        let noise = ((k as f64) * 12.9898).sin() * 1e-5;
        zs.push(0.02 + 1e-8 * x - 2e-8 * y + 1e-13 * x * y + 1e-18 * x * x * x + noise);
    }
    (xs, ys, zs)
}

fn benches(c: &mut Criterion) {
    let (xs, ys, zs) = data(10_000);
    c.bench_function("fit_degree3_1e4", |b| {
        b.iter(|| fit(&Observations::new(&xs, &ys, &zs), 3, &FitOptions::default()).unwrap())
    });
    c.bench_function("select_bic_1e4", |b| {
        b.iter(|| {
            select_degree(
                &Observations::new(&xs, &ys, &zs),
                &SelectionOptions::default(),
            )
            .unwrap()
        })
    });
    let (xs, ys, zs) = data(1_000_000);
    let mut group = c.benchmark_group("big");
    group.sample_size(10);
    group.bench_function("fit_degree3_1e6", |b| {
        b.iter(|| fit(&Observations::new(&xs, &ys, &zs), 3, &FitOptions::default()).unwrap())
    });
    group.finish();
}

criterion_group!(benches_group, benches);
criterion_main!(benches_group);

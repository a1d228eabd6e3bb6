//! Large least squares, nalgebra beside faer: the reduction of `spm_regression::fit` over 10⁶
//! weighted records — a streaming Householder QR (blocks of rows stacked under the running
//! triangular factor) with each library's QR, and faer's one-shot QR of the whole augmented
//! matrix — for a degree-3 (10 terms) and a degree-6 (28 terms) surface; and the same kernels
//! on the sizes the workspace's fits have (issue 28, item 1): 768 records × 10 terms (a degree-3
//! surface over a 768-record CDB plane) and 20 × 6 (a degree-2 surface over 20 records, the size
//! of the scanner-dynamics fit's design). Run with
//! `cargo bench -p spm-regression --features test-support --bench linalg` (`-- small` for the latter).
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, criterion_group, criterion_main};
use spm_regression::bench_support::{LeastSquaresKernel, Records, reduce};

fn benches(c: &mut Criterion) {
    for degree in [3, 6] {
        let records = Records::synthetic(1_000_000, degree);
        let mut group = c.benchmark_group(format!("least_squares_1e6_degree{degree}"));
        group.sample_size(10);
        for kernel in LeastSquaresKernel::ALL {
            group.bench_function(kernel.name(), |b| {
                b.iter(|| reduce(&records, kernel).unwrap())
            });
        }
        group.finish();
    }
    for (records, degree) in [(768, 3), (20, 2)] {
        let records_data = Records::synthetic(records, degree);
        let mut group = c.benchmark_group(format!("least_squares_small_{records}x{degree}"));
        for kernel in LeastSquaresKernel::ALL {
            group.bench_function(kernel.name(), |b| {
                b.iter(|| reduce(&records_data, kernel).unwrap())
            });
        }
        group.finish();
    }
}

criterion_group!(benches_group, benches);
criterion_main!(benches_group);

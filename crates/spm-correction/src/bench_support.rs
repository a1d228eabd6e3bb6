//! The workload of the correction benchmarks, shared by `benches/correction.rs`, the
//! `peak_memory` example and any harness that reports the figures (pure: no IO, no clock).

use spm_hal::{CountPoint, Counts};
use spm_regression::{Polynomial2, n_terms};

use crate::{CorrectionError, ProductField, RasterGeometry};

/// A realistic field for the benchmarks: degree-3 surfaces (K̄x^r, K̄yx^r, K̄yy^r) over a
/// 20 000-count scanner, 1–5 % nonlinearity, 0.0125 / 0.0121 nm per count.
///
/// # Errors
/// Never for these constants; [`CorrectionError::Regression`] if the polynomial is rejected.
pub fn realistic_field() -> Result<ProductField, CorrectionError> {
    let surface = |base: f64, seed: f64| {
        let c: Vec<f64> = (0..n_terms(3))
            .map(|k| {
                if k == 0 {
                    base
                } else {
                    base * 0.02 * ((k as f64 + seed) * 1.7).sin()
                }
            })
            .collect();
        Polynomial2::new(3, (10_000.0, 10_000.0), (10_000.0, 10_000.0), c)
    };
    Ok(ProductField {
        kx_nm_per_count: surface(0.0125, 0.0)?,
        kyx_nm_per_count: surface(0.0004, 1.0)?,
        kyy_nm_per_count: surface(0.0121, 2.0)?,
    })
}

/// The raster of an N × N benchmark image: 16 384 counts wide from (2000, 3000).
///
/// # Errors
/// [`CorrectionError::Empty`] for `n` = 0.
pub fn benchmark_geometry(n: usize) -> Result<RasterGeometry, CorrectionError> {
    RasterGeometry::new(
        CountPoint::from_counts(2000.0, 3000.0),
        Counts(16384.0 / n.max(1) as f64),
        n,
        n,
    )
}

/// A smooth N × N test image (row-major), values of order 1.
pub fn benchmark_image(n: usize) -> Vec<f64> {
    (0..n * n)
        .map(|k| ((k % n) as f64 * 0.05).sin() + ((k / n) as f64 * 0.031).cos())
        .collect()
}

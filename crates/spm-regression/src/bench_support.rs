//! Support for benchmarks (`benches/linalg.rs`, `cargo xtask bench`): the least-squares
//! reduction of [`crate::fit`] over many records with each dense linear-algebra library, so
//! that the library keeps whichever is faster (issue 17, item 8). Not part of the fitting API.

use crate::fit::{BLOCK_ROWS, normalisation, streaming_qr, weighted_row};
use crate::polynomial::{MAX_DEGREE, n_terms};
use crate::{Observations, RegressionError};

/// Records of one LCC over the scanner field (structure of arrays), counts and nm/count.
#[derive(Debug, Clone, PartialEq)]
pub struct Records {
    /// x, counts.
    pub x_counts: Vec<f64>,
    /// y, counts.
    pub y_counts: Vec<f64>,
    /// The coefficient, nm/count.
    pub value_nm_per_count: Vec<f64>,
    /// Relative weights (1/u²).
    pub weight: Vec<f64>,
    /// Degree of the surface fitted to them.
    pub degree: u32,
}

impl Records {
    /// `n` records on a square grid of 60-count pitch: a cubic K̄x surface plus a deterministic
    /// ±1e-5 nm/count ripple, weights between 0.5 and 1.5 (the data of `benches/fit.rs`, weighted).
    #[must_use]
    pub fn synthetic(n: usize, degree: u32) -> Self {
        let side = (n as f64).sqrt().ceil().max(1.0) as usize;
        let mut records = Self {
            x_counts: Vec::with_capacity(n),
            y_counts: Vec::with_capacity(n),
            value_nm_per_count: Vec::with_capacity(n),
            weight: Vec::with_capacity(n),
            degree,
        };
        for k in 0..n {
            let (x, y) = ((k % side) as f64 * 60.0, (k / side) as f64 * 60.0);
            let ripple = ((k as f64) * 12.9898).sin() * 1e-5;
            records.x_counts.push(x);
            records.y_counts.push(y);
            records
                .value_nm_per_count
                .push(0.02 + 1e-8 * x - 2e-8 * y + 1e-13 * x * y + 1e-18 * x * x * x + ripple);
            records.weight.push(1.0 + 0.5 * ((k as f64) * 0.618).sin());
        }
        records
    }

    /// The records as [`Observations`].
    #[must_use]
    pub fn observations(&self) -> Observations<'_> {
        Observations::new(&self.x_counts, &self.y_counts, &self.value_nm_per_count)
            .with_weights(&self.weight)
    }
}

/// How the weighted design matrix is reduced to R and Qᵀb.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LeastSquaresKernel {
    /// nalgebra's Householder QR, streamed over blocks of rows (what [`crate::fit`] runs).
    NalgebraStreaming,
    /// faer's blocked Householder QR, streamed over the same blocks of rows.
    FaerStreaming,
    /// faer's blocked Householder QR of the whole n × (m + 1) augmented matrix at once.
    FaerDense,
}

impl LeastSquaresKernel {
    /// Every kernel.
    pub const ALL: [Self; 3] = [
        Self::NalgebraStreaming,
        Self::FaerStreaming,
        Self::FaerDense,
    ];

    /// A short name for tables.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::NalgebraStreaming => "nalgebra_streaming_qr",
            Self::FaerStreaming => "faer_streaming_qr",
            Self::FaerDense => "faer_dense_qr",
        }
    }
}

/// The least-squares coefficients (normalised coordinates, eq. 6 order) of `records` by
/// `kernel`: the reduction to R and Qᵀb, then back substitution.
///
/// # Errors
/// [`RegressionError::DegreeTooHigh`], the input errors of [`Observations::validate`],
/// [`RegressionError::TooFewPoints`], [`RegressionError::IllConditioned`] for a singular R.
pub fn reduce(records: &Records, kernel: LeastSquaresKernel) -> Result<Vec<f64>, RegressionError> {
    let degree = records.degree;
    if degree > MAX_DEGREE {
        return Err(RegressionError::DegreeTooHigh {
            degree,
            max: MAX_DEGREE,
        });
    }
    let obs = records.observations();
    let usable = obs.validate()?;
    let m = n_terms(degree);
    if usable < m {
        return Err(RegressionError::TooFewPoints {
            degree,
            needed: m,
            got: usable,
        });
    }
    let norm_x = normalisation(&records.x_counts);
    let norm_y = normalisation(&records.y_counts);
    let (r, qtb) = match kernel {
        LeastSquaresKernel::NalgebraStreaming => {
            let (r, qtb) = streaming_qr(&obs, degree, norm_x, norm_y);
            let r: Vec<Vec<f64>> = (0..m)
                .map(|i| (0..m).map(|j| r[(i, j)]).collect())
                .collect();
            (r, qtb.iter().copied().collect())
        }
        LeastSquaresKernel::FaerStreaming => faer_qr(&obs, degree, norm_x, norm_y, BLOCK_ROWS),
        LeastSquaresKernel::FaerDense => faer_qr(&obs, degree, norm_x, norm_y, obs.len()),
    };
    back_substitute(&r, &qtb).ok_or(RegressionError::IllConditioned {
        degree,
        condition_number: f64::INFINITY,
        threshold: f64::INFINITY,
    })
}

/// R and Qᵀb by faer's QR of [R | Qᵀb ; √w·A | √w·z] over blocks of `block_rows` records.
fn faer_qr(
    obs: &Observations<'_>,
    degree: u32,
    norm_x: (f64, f64),
    norm_y: (f64, f64),
    block_rows: usize,
) -> (Vec<Vec<f64>>, Vec<f64>) {
    let m = n_terms(degree);
    let mut r_aug = faer::Mat::<f64>::zeros(m + 1, m + 1);
    let mut row = vec![0.0; m];
    let n = obs.len();
    let mut start = 0;
    while start < n {
        let end = (start + block_rows.max(1)).min(n);
        let mut block = faer::Mat::<f64>::zeros(m + 1 + (end - start), m + 1);
        block
            .as_mut()
            .submatrix_mut(0, 0, m + 1, m + 1)
            .copy_from(r_aug.as_ref());
        for (k, i) in (start..end).enumerate() {
            if let Some(z) = weighted_row(obs, i, degree, norm_x, norm_y, &mut row) {
                for (c, val) in row.iter().enumerate() {
                    *block.as_mut().get_mut(m + 1 + k, c) = *val;
                }
                *block.as_mut().get_mut(m + 1 + k, m) = z;
            }
        }
        let qr = block.qr();
        let thin = qr.thin_R();
        r_aug = faer::Mat::from_fn(
            m + 1,
            m + 1,
            |i, j| if i <= j { *thin.get(i, j) } else { 0.0 },
        );
        start = end;
    }
    let r = (0..m)
        .map(|i| (0..m).map(|j| *r_aug.get(i, j)).collect())
        .collect();
    let qtb = (0..m).map(|i| *r_aug.get(i, m)).collect();
    (r, qtb)
}

/// x with R x = c for upper-triangular R; `None` for a zero or non-finite pivot.
fn back_substitute(r: &[Vec<f64>], c: &[f64]) -> Option<Vec<f64>> {
    let m = c.len();
    let mut x = vec![0.0; m];
    for i in (0..m).rev() {
        let mut s = c[i];
        for j in (i + 1)..m {
            s -= r[i][j] * x[j];
        }
        let pivot = r[i][i];
        if pivot == 0.0 || !pivot.is_finite() {
            return None;
        }
        x[i] = s / pivot;
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{FitOptions, fit};

    /// Every kernel gives the coefficients of [`fit`] to 1e-12 relative to the largest.
    fn check(n: usize, degree: u32) {
        let records = Records::synthetic(n, degree);
        let fitted = fit(&records.observations(), degree, &FitOptions::default()).unwrap();
        let expected = fitted.surface.coefficients();
        let scale = expected.iter().fold(0.0_f64, |a, c| a.max(c.abs()));
        for kernel in LeastSquaresKernel::ALL {
            let got = reduce(&records, kernel).unwrap();
            assert_eq!(got.len(), expected.len());
            for (k, (g, e)) in got.iter().zip(expected).enumerate() {
                assert!(
                    (g - e).abs() <= 1e-12 * scale,
                    "{} n={n} degree={degree} coefficient {k}: {g} vs {e}",
                    kernel.name()
                );
            }
        }
    }

    #[test]
    fn every_kernel_gives_the_coefficients_of_fit() {
        check(10, 1);
        check(5_000, 3);
        check(20_000, 5);
    }

    #[test]
    fn the_synthetic_surface_is_recovered() {
        // Without the ripple the cubic is exact: evaluate the fitted surface at a record.
        let mut records = Records::synthetic(4_096, 3);
        for (k, v) in records.value_nm_per_count.iter_mut().enumerate() {
            *v -= ((k as f64) * 12.9898).sin() * 1e-5;
        }
        let fitted = fit(&records.observations(), 3, &FitOptions::default()).unwrap();
        let (x, y) = (records.x_counts[1234], records.y_counts[1234]);
        let truth = 0.02 + 1e-8 * x - 2e-8 * y + 1e-13 * x * y + 1e-18 * x * x * x;
        assert!((fitted.surface.evaluate(x, y) - truth).abs() < 1e-14);
    }
}

//! Generalised least squares: observations in small correlated blocks (a measured 2-D vector's
//! x and y), each with its covariance, solved through [`least_squares`] after whitening every
//! block by the Cholesky factor of its covariance (Aitken's estimator). When some block's
//! covariance is singular (an exact observation, or a degenerate one) the blocks cannot be
//! weighted: the estimate is then ordinary least squares, with the sandwich covariance
//! C·XᵀΣX·C (C = (XᵀX)⁻¹) that is still exact for that estimator.

use nalgebra::DMatrix;

use crate::error::RegressionError;
use crate::lsq::least_squares;

/// A covariance block whose correlation matrix has a determinant at or below this (for 2 × 2:
/// a correlation |ρ| within 5·10⁻¹⁹ of 1) counts as singular.
pub const SINGULAR_CORRELATION: f64 = 1e-18;

/// The solution of [`generalised_least_squares`].
#[derive(Debug, Clone, PartialEq)]
pub struct GeneralisedFit {
    /// The parameters, in column order.
    pub coefficients: Vec<f64>,
    /// The parameters' covariance from the observations' covariance (not from the residual
    /// scatter): (XᵀΣ⁻¹X)⁻¹ when weighted, the sandwich C·XᵀΣX·C otherwise (n × n).
    pub covariance: Vec<Vec<f64>>,
    /// rᵀΣ⁻¹r when weighted; `None` when some covariance block is singular (ordinary least
    /// squares).
    pub chi_squared: Option<f64>,
}

/// Solves `rows · x ≈ rhs` where consecutive rows form blocks, block k as many rows as
/// `block_covariances[k]` is square, with that covariance (see the module docs); a block is
/// singular when it is not positive definite or its correlation determinant is at most
/// [`SINGULAR_CORRELATION`].
///
/// # Errors
/// [`RegressionError::LengthMismatch`] when the blocks do not cover the rows or a covariance
/// is not square; [`RegressionError::NonFinite`] for NaN/∞ in a covariance; the errors of
/// [`least_squares`] (too few rows, an undetermined column).
pub fn generalised_least_squares(
    rows: &[Vec<f64>],
    rhs: &[f64],
    block_covariances: &[Vec<Vec<f64>>],
) -> Result<GeneralisedFit, RegressionError> {
    let covered: usize = block_covariances.iter().map(Vec::len).sum();
    if covered != rows.len() || rhs.len() != rows.len() {
        return Err(RegressionError::LengthMismatch {
            field: "covariance blocks",
            expected: rows.len(),
            got: covered,
        });
    }
    let mut blocks = Vec::with_capacity(block_covariances.len());
    for (index, c) in block_covariances.iter().enumerate() {
        let k = c.len();
        if let Some(row) = c.iter().find(|r| r.len() != k) {
            return Err(RegressionError::LengthMismatch {
                field: "covariance block row",
                expected: k,
                got: row.len(),
            });
        }
        if c.iter().flatten().any(|v| !v.is_finite()) {
            return Err(RegressionError::NonFinite {
                field: "covariance block",
                index,
            });
        }
        blocks.push(DMatrix::from_fn(k, k, |i, j| c[i][j]));
    }
    // Whitening factors: Σ_k = L_k·L_kᵀ; none when some block is not positive definite
    // (det Σ_k = Π l_ii² against Π Σ_ii: the determinant of its correlation matrix).
    let factors: Option<Vec<DMatrix<f64>>> = blocks
        .iter()
        .map(|b| {
            let l = b.clone().cholesky()?.l();
            let det: f64 = l.diagonal().iter().map(|v| v * v).product();
            let diagonal: f64 = b.diagonal().iter().product();
            (det > SINGULAR_CORRELATION * diagonal).then_some(l)
        })
        .collect();
    match factors {
        Some(factors) => weighted(rows, rhs, &factors),
        None => sandwich(rows, rhs, &blocks),
    }
}

/// Aitken's estimator: every block whitened by L⁻¹, then ordinary least squares.
fn weighted(
    rows: &[Vec<f64>],
    rhs: &[f64],
    factors: &[DMatrix<f64>],
) -> Result<GeneralisedFit, RegressionError> {
    let n = rows.first().map_or(0, Vec::len);
    let mut white_rows = Vec::with_capacity(rows.len());
    let mut white_rhs = Vec::with_capacity(rows.len());
    let mut start = 0;
    for l in factors {
        let k = l.nrows();
        let x = DMatrix::from_fn(k, n + 1, |i, j| {
            if j < n {
                rows[start + i][j]
            } else {
                rhs[start + i]
            }
        });
        let white = l
            .solve_lower_triangular(&x)
            .ok_or(RegressionError::IllConditioned {
                degree: 0,
                condition_number: f64::INFINITY,
                threshold: 0.0,
            })?;
        for i in 0..k {
            white_rows.push((0..n).map(|j| white[(i, j)]).collect::<Vec<f64>>());
            white_rhs.push(white[(i, n)]);
        }
        start += k;
    }
    let fit = least_squares(&white_rows, &white_rhs, &vec![false; n])?;
    Ok(GeneralisedFit {
        chi_squared: Some(fit.residual_rms.powi(2) * rows.len() as f64),
        coefficients: fit.coefficients,
        covariance: fit.unscaled_covariance,
    })
}

/// Ordinary least squares with the sandwich covariance C·XᵀΣX·C.
fn sandwich(
    rows: &[Vec<f64>],
    rhs: &[f64],
    blocks: &[DMatrix<f64>],
) -> Result<GeneralisedFit, RegressionError> {
    let fit = least_squares(rows, rhs, &vec![false; rows.first().map_or(0, Vec::len)])?;
    let n = fit.coefficients.len();
    let c = DMatrix::from_fn(n, n, |i, j| fit.unscaled_covariance[i][j]);
    // XᵀΣX block by block.
    let mut meat = DMatrix::<f64>::zeros(n, n);
    let mut start = 0;
    for b in blocks {
        let k = b.nrows();
        let x = DMatrix::from_fn(k, n, |i, j| rows[start + i][j]);
        meat += x.transpose() * b * &x;
        start += k;
    }
    let covariance = &c * meat * &c;
    Ok(GeneralisedFit {
        coefficients: fit.coefficients,
        covariance: (0..n)
            .map(|i| (0..n).map(|j| covariance[(i, j)]).collect())
            .collect(),
        chi_squared: None,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// The mean of two correlated measurements of one value (closed form): with covariance
    /// [[1, ρ], [ρ, 4]] the weights are Σ⁻¹·1 normalised, the variance 1 / (1ᵀΣ⁻¹1).
    #[test]
    fn a_weighted_mean_of_correlated_values_is_the_closed_form() {
        let rho = 0.5;
        let rows = vec![vec![1.0], vec![1.0]];
        let rhs = vec![10.0, 13.0];
        let fit = generalised_least_squares(&rows, &rhs, &[vec![vec![1.0, rho], vec![rho, 4.0]]])
            .unwrap();
        // Σ⁻¹ = [[4, −ρ], [−ρ, 1]] / (4 − ρ²); Σ⁻¹·1 = (4 − ρ, 1 − ρ) / det.
        let det = 4.0 - rho * rho;
        let (w1, w2) = ((4.0 - rho) / det, (1.0 - rho) / det);
        let mean = (w1 * 10.0 + w2 * 13.0) / (w1 + w2);
        assert!((fit.coefficients[0] - mean).abs() < 1e-12);
        assert!((fit.covariance[0][0] - 1.0 / (w1 + w2)).abs() < 1e-12);
        let r = [10.0 - mean, 13.0 - mean];
        let chi2 = (4.0 * r[0] * r[0] - 2.0 * rho * r[0] * r[1] + r[1] * r[1]) / det;
        assert!((fit.chi_squared.unwrap() - chi2).abs() < 1e-12);
    }

    /// A singular block (an exact observation beside a noisy one) falls back to ordinary least
    /// squares with the sandwich covariance: the plain mean of 2 values, variance (0 + 4)/4.
    #[test]
    fn a_singular_block_gives_ordinary_least_squares_with_the_sandwich() {
        let rows = vec![vec![1.0], vec![1.0]];
        let fit =
            generalised_least_squares(&rows, &[10.0, 13.0], &[vec![vec![0.0]], vec![vec![4.0]]])
                .unwrap();
        assert!((fit.coefficients[0] - 11.5).abs() < 1e-12);
        assert!((fit.covariance[0][0] - 1.0).abs() < 1e-12);
        assert_eq!(fit.chi_squared, None);
        assert!(matches!(
            generalised_least_squares(&rows, &[1.0, 2.0], &[vec![vec![1.0]]]),
            Err(RegressionError::LengthMismatch { .. })
        ));
        assert!(matches!(
            generalised_least_squares(
                &rows,
                &[1.0, 2.0],
                &[vec![vec![1.0, 0.0], vec![0.0, f64::NAN]]]
            ),
            Err(RegressionError::NonFinite { .. })
        ));
    }
}

//! Linear least squares with optional sign constraints: the one dense solver for models that
//! are linear in their parameters but are not a polynomial surface (the scanner dynamics'
//! hysteresis weights and creep weight, per-track offsets, drift velocities).
//!
//! `minimise Σᵢ (Σⱼ Aᵢⱼ·xⱼ − bᵢ)²` subject to `xⱼ ≥ 0` for the columns flagged non-negative,
//! by Lawson & Hanson's active-set method (*Solving Least Squares Problems*, 1974, ch. 23).
//! The columns are normalised to unit length and the normal matrix G = AᵀA (n × n) is formed
//! once, so every sub-problem of the active set is a Cholesky solve of a few dozen unknowns
//! however many rows there are; a pivot below [`RANK_TOLERANCE`] of the largest diagonal
//! (with normalised columns: a direction determined to worse than about 10⁻⁶) is an
//! ill-conditioned problem. Unconstrained columns are always in the passive set.

use nalgebra::{DMatrix, DVector};

use crate::error::RegressionError;

/// Iteration limit of the active-set loop, in multiples of the number of columns.
const MAX_ITERATIONS_PER_COLUMN: usize = 8;
/// Relative singular-value threshold below which a direction counts as undetermined.
const RANK_TOLERANCE: f64 = 1e-12;

/// The solution of [`least_squares`].
#[derive(Debug, Clone, PartialEq)]
pub struct LinearFit {
    /// The parameters, in column order.
    pub coefficients: Vec<f64>,
    /// Standard errors of the parameters from the residual scatter (σ̂²·(AₚᵀAₚ)⁻¹ over the
    /// passive set); 0 for a column held at its bound.
    pub standard_errors: Vec<f64>,
    /// RMS residual.
    pub residual_rms: f64,
    /// Which columns ended at their bound 0 (active constraints).
    pub at_bound: Vec<bool>,
    /// (AₚᵀAₚ)⁻¹ over the passive set, in the parameters' units (n × n; times the variance of
    /// one observation it is the parameters' covariance): zero rows and columns for a column
    /// held at its bound.
    pub unscaled_covariance: Vec<Vec<f64>>,
}

impl LinearFit {
    /// The leverage hᵢ = aᵢᵀ·(AₚᵀAₚ)⁻¹·aᵢ of each design row `rows[i]` (the rows this fit was
    /// solved from, or new rows for a prediction's variance factor), from
    /// [`LinearFit::unscaled_covariance`]: columns held at their bound do not count. At the
    /// data they sum to the number of free parameters; a prediction at row a has the variance
    /// σ²·(1 + h) against a new observation.
    ///
    /// # Errors
    /// [`RegressionError::LengthMismatch`] for a row that is not as long as the fit's
    /// parameters; [`RegressionError::NonFinite`] for NaN/∞ in a row.
    pub fn leverages(&self, rows: &[Vec<f64>]) -> Result<Vec<f64>, RegressionError> {
        let n = self.coefficients.len();
        rows.iter()
            .enumerate()
            .map(|(index, row)| {
                if row.len() != n {
                    return Err(RegressionError::LengthMismatch {
                        field: "design row",
                        expected: n,
                        got: row.len(),
                    });
                }
                if row.iter().any(|v| !v.is_finite()) {
                    return Err(RegressionError::NonFinite {
                        field: "design row",
                        index,
                    });
                }
                Ok(self
                    .unscaled_covariance
                    .iter()
                    .zip(row)
                    .map(|(c, ai)| ai * c.iter().zip(row).map(|(cij, aj)| cij * aj).sum::<f64>())
                    .sum())
            })
            .collect()
    }
}

/// Solves the (sign-constrained) linear least-squares problem described in the module docs.
/// `rows` are the design matrix's rows (each `columns` long), `rhs` the observations,
/// `non_negative[j]` whether column j is constrained to ≥ 0.
///
/// # Errors
/// [`RegressionError::LengthMismatch`] for ragged input, [`RegressionError::NonFinite`] for
/// NaN/∞, [`RegressionError::TooFewPoints`] (degree 0) with fewer rows than columns,
/// [`RegressionError::IllConditioned`] (degree 0) when a free column is not determined.
pub fn least_squares(
    rows: &[Vec<f64>],
    rhs: &[f64],
    non_negative: &[bool],
) -> Result<LinearFit, RegressionError> {
    let n = non_negative.len();
    if rows.len() != rhs.len() {
        return Err(RegressionError::LengthMismatch {
            field: "rhs",
            expected: rows.len(),
            got: rhs.len(),
        });
    }
    for row in rows {
        if row.len() != n {
            return Err(RegressionError::LengthMismatch {
                field: "design row",
                expected: n,
                got: row.len(),
            });
        }
    }
    if let Some(index) = rows.iter().position(|r| r.iter().any(|v| !v.is_finite())) {
        return Err(RegressionError::NonFinite {
            field: "design row",
            index,
        });
    }
    if let Some(index) = rhs.iter().position(|v| !v.is_finite()) {
        return Err(RegressionError::NonFinite {
            field: "rhs",
            index,
        });
    }
    if rows.len() < n || n == 0 {
        return Err(RegressionError::TooFewPoints {
            degree: 0,
            needed: n.max(1),
            got: rows.len(),
        });
    }
    let a = DMatrix::from_fn(rows.len(), n, |i, j| rows[i][j]);
    let b = DVector::from_column_slice(rhs);
    // Column scales (normalised columns make the rank test meaningful).
    let scale: Vec<f64> = (0..n)
        .map(|j| {
            let s = a.column(j).norm();
            if s > 0.0 { s } else { 1.0 }
        })
        .collect();
    let a = DMatrix::from_fn(a.nrows(), n, |i, j| a[(i, j)] / scale[j]);
    let g = a.transpose() * &a;
    let c = a.transpose() * &b;

    let mut passive: Vec<bool> = non_negative.iter().map(|&c| !c).collect();
    let mut x = vec![0.0; n];
    // Start from the unconstrained columns alone.
    if passive.iter().any(|&p| p) {
        x = solve_passive(&g, &c, &passive)?;
    }
    let max_iterations = MAX_ITERATIONS_PER_COLUMN * n + 8;
    for _ in 0..max_iterations {
        // Gradient of ½‖Ax − b‖² is G·x − Aᵀb; w = −gradient.
        let xv = DVector::from_column_slice(&x);
        let w = &c - &g * &xv;
        let candidate = (0..n)
            .filter(|&j| !passive[j] && w[j] > 1e-12 * (1.0 + b.norm()))
            .max_by(|&i, &j| w[i].total_cmp(&w[j]));
        let Some(j) = candidate else { break };
        passive[j] = true;
        // Inner loop: keep the passive solution feasible.
        loop {
            let z = solve_passive(&g, &c, &passive)?;
            let infeasible: Vec<usize> = (0..n)
                .filter(|&k| passive[k] && non_negative[k] && z[k] <= 0.0)
                .collect();
            if infeasible.is_empty() {
                x = z;
                break;
            }
            let mut alpha = 1.0_f64;
            for &k in &infeasible {
                let d = x[k] - z[k];
                if d > 0.0 {
                    alpha = alpha.min(x[k] / d);
                }
            }
            for k in 0..n {
                x[k] += alpha * (z[k] - x[k]);
            }
            for k in 0..n {
                if passive[k] && non_negative[k] && x[k] <= 1e-15 {
                    passive[k] = false;
                    x[k] = 0.0;
                }
            }
        }
    }
    // Statistics over the passive set.
    let xv = DVector::from_column_slice(&x);
    let residual = &b - &a * &xv;
    let m = rows.len();
    let k = passive.iter().filter(|&&p| p).count();
    let dof = m.saturating_sub(k).max(1);
    let s2 = residual.norm_squared() / dof as f64;
    let mut standard_errors = vec![0.0; n];
    let mut unscaled_covariance = vec![vec![0.0; n]; n];
    let cols: Vec<usize> = (0..n).filter(|&j| passive[j]).collect();
    if !cols.is_empty() {
        let gp = DMatrix::from_fn(cols.len(), cols.len(), |i, j| g[(cols[i], cols[j])]);
        if let Some(inv) = gp.try_inverse() {
            for (c, &j) in cols.iter().enumerate() {
                standard_errors[j] = (s2 * inv[(c, c)].max(0.0)).sqrt() / scale[j];
                for (d, &k) in cols.iter().enumerate() {
                    unscaled_covariance[j][k] = inv[(c, d)] / (scale[j] * scale[k]);
                }
            }
        }
    }
    Ok(LinearFit {
        coefficients: x.iter().zip(&scale).map(|(v, s)| v / s).collect(),
        standard_errors,
        residual_rms: (residual.norm_squared() / m as f64).sqrt(),
        at_bound: passive.iter().map(|&p| !p).collect(),
        unscaled_covariance,
    })
}

/// Unconstrained least squares over the passive columns (others 0): the normal equations
/// `G_pp·x_p = c_p` by Cholesky, with the pivot test of the module docs.
fn solve_passive(
    g: &DMatrix<f64>,
    c: &DVector<f64>,
    passive: &[bool],
) -> Result<Vec<f64>, RegressionError> {
    let cols: Vec<usize> = (0..passive.len()).filter(|&j| passive[j]).collect();
    let mut x = vec![0.0; passive.len()];
    if cols.is_empty() {
        return Ok(x);
    }
    let k = cols.len();
    let gp = DMatrix::from_fn(k, k, |i, j| g[(cols[i], cols[j])]);
    let cp = DVector::from_fn(k, |i, _| c[cols[i]]);
    let largest = (0..k).map(|i| gp[(i, i)]).fold(0.0_f64, f64::max);
    let ill = |pivot: f64| RegressionError::IllConditioned {
        degree: 0,
        condition_number: if pivot > 0.0 {
            (largest / pivot).sqrt()
        } else {
            f64::INFINITY
        },
        threshold: (1.0 / RANK_TOLERANCE).sqrt(),
    };
    let Some(cholesky) = gp.clone().cholesky() else {
        return Err(ill(0.0));
    };
    let l = cholesky.l();
    let smallest = (0..k)
        .map(|i| l[(i, i)] * l[(i, i)])
        .fold(f64::INFINITY, f64::min);
    if largest.is_nan() || largest <= 0.0 || smallest <= RANK_TOLERANCE * largest {
        return Err(ill(smallest));
    }
    let z = cholesky.solve(&cp);
    for (i, &j) in cols.iter().enumerate() {
        x[j] = z[i];
    }
    Ok(x)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// Unconstrained: a straight line through exact points comes back exactly.
    #[test]
    fn free_columns_solve_the_plain_problem() {
        let rows: Vec<Vec<f64>> = (0..10).map(|i| vec![1.0, f64::from(i)]).collect();
        let rhs: Vec<f64> = (0..10).map(|i| 3.0 - 0.5 * f64::from(i)).collect();
        let fit = least_squares(&rows, &rhs, &[false, false]).unwrap();
        assert!((fit.coefficients[0] - 3.0).abs() < 1e-12);
        assert!((fit.coefficients[1] + 0.5).abs() < 1e-12);
        assert!(fit.residual_rms < 1e-12);
    }

    /// The unscaled covariance of a straight line through x = 0 … 9 is (XᵀX)⁻¹ in closed
    /// form: Sxx = Σ(x − x̄)² = 82.5, var(slope) = 1/Sxx, var(intercept) = Σx²/(n·Sxx),
    /// cov = −x̄/Sxx.
    #[test]
    fn the_unscaled_covariance_is_the_inverse_normal_matrix() {
        let rows: Vec<Vec<f64>> = (0..10).map(|i| vec![1.0, f64::from(i)]).collect();
        let rhs = vec![0.0; 10];
        let fit = least_squares(&rows, &rhs, &[false, false]).unwrap();
        let c = &fit.unscaled_covariance;
        let sxx = 82.5;
        assert!((c[1][1] - 1.0 / sxx).abs() < 1e-14);
        assert!((c[0][0] - 285.0 / (10.0 * sxx)).abs() < 1e-13);
        assert!((c[0][1] + 4.5 / sxx).abs() < 1e-14);
        assert!((c[0][1] - c[1][0]).abs() < 1e-15);
    }

    /// Lawson & Hanson's closed case: the unconstrained optimum has a negative coefficient;
    /// the constrained one holds it at 0 and refits the rest (b = 2·col0 − 1·col1 with
    /// orthogonal columns → x = (2, 0)).
    #[test]
    fn a_negative_optimum_is_held_at_the_bound() {
        let rows = vec![
            vec![1.0, 0.0],
            vec![0.0, 1.0],
            vec![1.0, 0.0],
            vec![0.0, 1.0],
        ];
        let rhs = vec![2.0, -1.0, 2.0, -1.0];
        let free = least_squares(&rows, &rhs, &[false, false]).unwrap();
        assert!((free.coefficients[1] + 1.0).abs() < 1e-12);
        let fit = least_squares(&rows, &rhs, &[true, true]).unwrap();
        assert!((fit.coefficients[0] - 2.0).abs() < 1e-12, "{fit:?}");
        assert_eq!(fit.coefficients[1], 0.0);
        assert_eq!(fit.at_bound, vec![false, true]);
    }

    /// Ragged, non-finite and under-determined inputs are typed errors.
    #[test]
    fn bad_input_is_refused() {
        assert!(matches!(
            least_squares(&[vec![1.0]], &[1.0, 2.0], &[false]),
            Err(RegressionError::LengthMismatch { .. })
        ));
        assert!(matches!(
            least_squares(&[vec![f64::NAN]], &[1.0], &[false]),
            Err(RegressionError::NonFinite { .. })
        ));
        assert!(matches!(
            least_squares(&[vec![1.0, 2.0]], &[1.0], &[false, false]),
            Err(RegressionError::TooFewPoints { .. })
        ));
        assert!(matches!(
            least_squares(
                &[vec![1.0, 2.0], vec![2.0, 4.0]],
                &[1.0, 2.0],
                &[false, false]
            ),
            Err(RegressionError::IllConditioned { .. })
        ));
    }

    /// Leverages of a straight line through x = 0 … 9 against the closed form
    /// hᵢ = 1/n + (xᵢ − x̄)²/Sxx (Sxx = 82.5), summing to the 2 parameters; a row of the wrong
    /// length is an error.
    #[test]
    fn leverages_of_a_line_are_the_closed_form() {
        let rows: Vec<Vec<f64>> = (0..10).map(|i| vec![1.0, f64::from(i)]).collect();
        let rhs: Vec<f64> = (0..10).map(|i| 1.0 + f64::from(i % 3)).collect();
        let fit = least_squares(&rows, &rhs, &[false, false]).unwrap();
        let h = fit.leverages(&rows).unwrap();
        for (i, hi) in h.iter().enumerate() {
            let expected = 0.1 + (i as f64 - 4.5).powi(2) / 82.5;
            assert!(
                (hi - expected).abs() < 1e-12,
                "h{i} = {hi}, closed form {expected}"
            );
        }
        assert!((h.iter().sum::<f64>() - 2.0).abs() < 1e-12);
        assert!(matches!(
            fit.leverages(&[vec![1.0]]),
            Err(RegressionError::LengthMismatch { .. })
        ));
    }
}

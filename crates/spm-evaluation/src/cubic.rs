//! A total-degree-3 polynomial map counts → nm, one [`Polynomial2`] per coordinate: the
//! conventional per-image correction (the polynomial baseline, the grating calibration, the
//! per-image bound). Fitted by the one least-squares routine,
//! [`spm_regression::least_squares`], on the eq. (6) basis of [`spm_regression::term_powers`];
//! evaluated and differentiated by [`Polynomial2`] itself, so the fit and the evaluation share
//! one term order by construction.

use spm_correction::{CorrectionField, FormCoefficients};
use spm_regression::{Polynomial2, RegressionError, least_squares, n_terms, term_powers};

/// Total degree of the map.
pub const CUBIC_DEGREE: u32 = 3;

/// A total-degree-3 polynomial map counts → nm (per coordinate), in coordinates normalised by
/// one centre and one half-side for both axes.
#[derive(Debug, Clone, PartialEq)]
pub struct CubicMap {
    /// X(x, y), nm.
    x_nm: Polynomial2,
    /// Y(x, y), nm.
    y_nm: Polynomial2,
}

impl CubicMap {
    /// Least-squares fit of `points` (counts) to `targets` (nm), normalised by the points'
    /// bounding box (its centre, and half its longer side).
    ///
    /// # Errors
    /// [`RegressionError::TooFewPoints`] with fewer points than the 10 terms;
    /// the least-squares kernel's errors (non-finite input, a singular fit).
    pub fn fit(points: &[[f64; 2]], targets: &[[f64; 2]]) -> Result<Self, RegressionError> {
        let n = points.len().min(targets.len());
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for p in &points[..n] {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let centre = [0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1])];
        let half = (0.5 * (hi[0] - lo[0])).max(0.5 * (hi[1] - lo[1])).max(1e-9);
        Self::fit_normalised(&points[..n], &targets[..n], centre, half)
    }

    /// Least-squares fit of `points` (counts) to `targets` (nm) in the coordinates
    /// `(p − centre) / half_counts`.
    ///
    /// # Errors
    /// As [`CubicMap::fit`]; [`RegressionError::LengthMismatch`] when the slices differ in
    /// length, [`RegressionError::InvalidArgument`] for a half side that is not finite and
    /// positive.
    pub fn fit_normalised(
        points: &[[f64; 2]],
        targets: &[[f64; 2]],
        centre: [f64; 2],
        half_counts: f64,
    ) -> Result<Self, RegressionError> {
        let terms = n_terms(CUBIC_DEGREE);
        if points.len() != targets.len() {
            return Err(RegressionError::LengthMismatch {
                field: "targets",
                expected: points.len(),
                got: targets.len(),
            });
        }
        if points.len() < terms {
            return Err(RegressionError::TooFewPoints {
                degree: CUBIC_DEGREE,
                needed: terms,
                got: points.len(),
            });
        }
        if !(half_counts.is_finite() && half_counts > 0.0) {
            return Err(RegressionError::InvalidArgument(format!(
                "normalisation half side must be finite and > 0, got {half_counts}"
            )));
        }
        let rows: Vec<Vec<f64>> = points
            .iter()
            .map(|p| {
                let (u, v) = (
                    (p[0] - centre[0]) / half_counts,
                    (p[1] - centre[1]) / half_counts,
                );
                term_powers(CUBIC_DEGREE)
                    .map(|(i, j)| u.powi(i as i32) * v.powi(j as i32))
                    .collect()
            })
            .collect();
        let free = vec![false; terms];
        let axis = |k: usize| -> Result<Polynomial2, RegressionError> {
            let rhs: Vec<f64> = targets.iter().map(|t| t[k]).collect();
            let fit = least_squares(&rows, &rhs, &free)?;
            Polynomial2::new(
                CUBIC_DEGREE,
                (centre[0], centre[1]),
                (half_counts, half_counts),
                fit.coefficients,
            )
        };
        Ok(Self {
            x_nm: axis(0)?,
            y_nm: axis(1)?,
        })
    }

    /// The two coordinate polynomials (X, Y), nm, in eq. (6) order.
    pub fn polynomials(&self) -> (&Polynomial2, &Polynomial2) {
        (&self.x_nm, &self.y_nm)
    }

    /// The map at (x, y) counts, nm.
    pub fn eval(&self, x: f64, y: f64) -> [f64; 2] {
        [self.x_nm.evaluate(x, y), self.y_nm.evaluate(x, y)]
    }

    /// Jacobian [[∂X/∂x, ∂X/∂y], [∂Y/∂x, ∂Y/∂y]], nm/count.
    pub fn jacobian(&self, x: f64, y: f64) -> [[f64; 2]; 2] {
        let (xx, xy) = self.x_nm.gradient(x, y);
        let (yx, yy) = self.y_nm.gradient(x, y);
        [[xx, xy], [yx, yy]]
    }
}

impl CorrectionField for CubicMap {
    /// The map's local shape: its Jacobian with the local rotation removed, as
    /// (K̄x, K̄y sin α, K̄y cos α).
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        let j = self.jacobian(x, y);
        let kx = j[0][0].hypot(j[1][0]);
        let (ex, ey) = (j[0][0] / kx, j[1][0] / kx);
        FormCoefficients {
            kx_nm_per_count: kx,
            kyx_nm_per_count: j[0][1] * ex + j[1][1] * ey,
            kyy_nm_per_count: (j[0][0] * j[1][1] - j[0][1] * j[1][0]) / kx,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Coefficients of a cubic in the eq. (6) order, normalised coordinates.
    const TRUTH: [f64; 10] = [0.5, -1.0, 2.0, 0.1, -0.2, 0.3, 0.05, -0.04, 0.03, -0.02];

    fn basis_value(coefficients: &[f64], u: f64, v: f64) -> f64 {
        term_powers(CUBIC_DEGREE)
            .zip(coefficients)
            .map(|((i, j), c)| c * u.powi(i as i32) * v.powi(j as i32))
            .sum()
    }

    #[test]
    fn the_fit_recovers_a_cubic_to_round_off() -> Result<(), RegressionError> {
        let (centre, half) = ([1000.0, -500.0], 350.0);
        let mut points = Vec::new();
        let mut targets = Vec::new();
        for i in 0..8 {
            for j in 0..8 {
                let (u, v) = (f64::from(i) / 3.5 - 1.0, f64::from(j) / 3.5 - 1.0);
                points.push([centre[0] + half * u, centre[1] + half * v]);
                let y_coefficients: Vec<f64> = TRUTH.iter().rev().copied().collect();
                targets.push([
                    basis_value(&TRUTH, u, v),
                    basis_value(&y_coefficients, u, v),
                ]);
            }
        }
        let map = CubicMap::fit_normalised(&points, &targets, centre, half)?;
        let (x, y) = map.polynomials();
        for (f, t) in x.coefficients().iter().zip(&TRUTH) {
            assert!((f - t).abs() < 1e-9, "{:?}", x.coefficients());
        }
        for (f, t) in y.coefficients().iter().zip(TRUTH.iter().rev()) {
            assert!((f - t).abs() < 1e-9, "{:?}", y.coefficients());
        }
        // The bounding-box fit finds the same normalisation on this square grid.
        assert_eq!(
            CubicMap::fit(&points, &targets)?.polynomials().0.center(),
            (1000.0, -500.0)
        );
        Ok(())
    }

    #[test]
    fn the_jacobian_is_the_derivative_of_the_map() -> Result<(), RegressionError> {
        let points: Vec<[f64; 2]> = (0..36)
            .map(|k| [f64::from(k % 6) * 40.0, f64::from(k / 6) * 40.0])
            .collect();
        let targets: Vec<[f64; 2]> = points
            .iter()
            .map(|p| {
                [
                    0.02 * p[0] + 1e-7 * p[0] * p[0] * p[1],
                    0.021 * p[1] + 1e-3 * p[0] - 2e-8 * p[1].powi(3),
                ]
            })
            .collect();
        let map = CubicMap::fit(&points, &targets)?;
        let (x, y) = (77.0, 123.0);
        let j = map.jacobian(x, y);
        let exact = [
            [0.02 + 2e-7 * x * y, 1e-7 * x * x],
            [1e-3, 0.021 - 6e-8 * y * y],
        ];
        for (row, exact_row) in j.iter().zip(&exact) {
            for (a, b) in row.iter().zip(exact_row) {
                assert!((a - b).abs() < 1e-12, "{j:?} vs {exact:?}");
            }
        }
        Ok(())
    }

    #[test]
    fn too_few_points_is_a_typed_error() {
        let points = [[0.0, 0.0]; 9];
        assert!(matches!(
            CubicMap::fit(&points, &points),
            Err(RegressionError::TooFewPoints { needed: 10, .. })
        ));
    }
}

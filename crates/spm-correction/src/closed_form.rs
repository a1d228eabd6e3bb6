//! The paper's closed forms written out literally: eq. (10) for planes and eq. (12) for
//! polynomial surfaces with the product surfaces of eq. (11).
//!
//! These are cross-checks of the general route ([`crate::correct_raster`] through
//! [`crate::CorrectionField`]), which computes the same integrals with normalised polynomials
//! and is better conditioned for large scanner coordinates. Coordinates: the raster origin
//! (x₀, y₀) and the pixel offset (x, y) from it, all in counts; results in nm relative to the
//! origin corner (direct image).

use spm_regression::{Polynomial2, term_powers};

use crate::CorrectionError;
use crate::field::{SERIES_THRESHOLD, linear_times_cos, linear_times_sin};

/// A plane f = k₀ + k₁ y + k₂ x (the first three terms of eq. 6), raw coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    /// Constant term (a₀, b₀ or c₀).
    pub k0: f64,
    /// Coefficient of y (a₁, b₁, c₁).
    pub k_y: f64,
    /// Coefficient of x (a₂, b₂, c₂).
    pub k_x: f64,
}

impl Plane {
    /// The plane of a degree ≤ 1 polynomial, in raw coordinates.
    ///
    /// # Errors
    /// [`CorrectionError::InvalidArgument`] for degree > 1.
    pub fn from_polynomial(p: &Polynomial2) -> Result<Self, CorrectionError> {
        if p.degree() > 1 {
            return Err(CorrectionError::InvalidArgument(format!(
                "eq. (10) needs planes, got a surface of degree {}",
                p.degree()
            )));
        }
        let raw = p.coefficients_in_raw_coordinates();
        Ok(Self {
            k0: raw.first().copied().unwrap_or(0.0),
            k_y: raw.get(1).copied().unwrap_or(0.0),
            k_x: raw.get(2).copied().unwrap_or(0.0),
        })
    }

    /// The polynomial of this plane (raw coordinates).
    ///
    /// # Errors
    /// [`CorrectionError::Regression`] for non-finite coefficients.
    pub fn to_polynomial(self) -> Result<Polynomial2, CorrectionError> {
        Ok(Polynomial2::from_raw_coefficients(
            1,
            vec![self.k0, self.k_y, self.k_x],
        )?)
    }
}

/// Eq. (10): corrected (x̄, ȳ) in nm of the direct-image pixel at offset (`x`, `y`) counts from
/// the raster origin (`x0`, `y0`), for planes K̄x = a, K̄y = b, α = c.
///
/// Written as in the paper. Where |c₁·y| < 0.5 the closed form divides a small difference by c₁
/// (and is undefined at c₁ = 0); there the c₁ → 0 limit is taken through the Taylor series of
/// the same integrals, which agrees with the closed form to rounding.
///
/// The paper's eq. (10) as printed: the tests' closed-form truth, not in the equation index.
#[must_use]
pub fn eq10(a: Plane, b: Plane, c: Plane, x0: f64, y0: f64, x: f64, y: f64) -> (f64, f64) {
    let x_line = (a.k0 + a.k_y * (y0 + y) + a.k_x * x0) * x + 0.5 * a.k_x * x * x;
    let (b0, b1, b2) = (b.k0, b.k_y, b.k_x);
    let (c0, c1, c2) = (c.k0, c.k_y, c.k_x);
    let big_b = b0 + b1 * y0 + b2 * x0;
    if (c1 * y).abs() < SERIES_THRESHOLD {
        let big_c = c0 + c1 * y0 + c2 * x0;
        return (
            x_line + linear_times_sin(big_b, b1, big_c, c1, y),
            linear_times_cos(big_b, b1, big_c, c1, y),
        );
    }
    let half = (c1 * y / 2.0).sin();
    let mid = c0 + c1 * (y0 + y / 2.0) + c2 * x0;
    let end = c0 + c1 * (y0 + y) + c2 * x0;
    let x_bar =
        x_line + (2.0 * half * (big_b * mid.sin() + b1 / c1 * mid.cos()) - b1 * y * end.cos()) / c1;
    let y_bar = (2.0 * half * (big_b * mid.cos() - b1 / c1 * mid.sin()) + b1 * y * end.sin()) / c1;
    (x_bar, y_bar)
}

/// Eq. (12): corrected (x̄, ȳ) in nm of the direct-image pixel at offset (`x`, `y`) counts from
/// (`x0`, `y0`), with K̄x^r = `a` and the product surfaces K̄yx^r = `e`, K̄yy^r = `f` of eq. (11),
/// summed term by term over the raw-coordinate coefficients as printed.
///
/// The paper's eq. (12) as printed: the tests' closed-form truth, not in the equation index.
#[must_use]
pub fn eq12(
    a: &Polynomial2,
    e: &Polynomial2,
    f: &Polynomial2,
    x0: f64,
    y0: f64,
    x: f64,
    y: f64,
) -> (f64, f64) {
    let along_x = |p: &Polynomial2| -> f64 {
        term_powers(p.degree())
            .zip(p.coefficients_in_raw_coordinates())
            .map(|((px, py), k)| {
                let n = px as i32 + 1;
                k / f64::from(n) * ((x0 + x).powi(n) - x0.powi(n)) * (y0 + y).powi(py as i32)
            })
            .sum()
    };
    let along_y = |p: &Polynomial2| -> f64 {
        term_powers(p.degree())
            .zip(p.coefficients_in_raw_coordinates())
            .map(|((px, py), k)| {
                let n = py as i32 + 1;
                k / f64::from(n) * x0.powi(px as i32) * ((y0 + y).powi(n) - y0.powi(n))
            })
            .sum()
    };
    (along_x(a) + along_y(e), along_y(f))
}

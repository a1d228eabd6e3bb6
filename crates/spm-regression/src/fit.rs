//! Weighted least-squares fit of a [`Polynomial2`] of given degree.
//!
//! The design matrix is built in normalised coordinates (data span [−1, 1] in x and y) and
//! reduced by a streaming Householder QR (blocks of rows are stacked under the running R and
//! re-factorised), so memory is O(terms²) whatever the number of points and the conditioning is
//! that of the design matrix itself, not of the normal equations. The condition number is
//! σ_max/σ_min of R (SVD of the small triangular factor).

use nalgebra::{DMatrix, DVector};

use crate::polynomial::{MAX_DEGREE, n_terms, term_powers};
use crate::{Polynomial2, RegressionError};

/// Rows reduced per QR block.
pub(crate) const BLOCK_ROWS: usize = 1024;

/// Observations z_i at points (x_i, y_i), optionally weighted (structure of arrays).
///
/// Weights are relative (e.g. 1/u² for standard uncertainty u); a zero weight removes the
/// point from the fit.
#[derive(Debug, Clone, Copy)]
pub struct Observations<'a> {
    /// x coordinates (counts for LCC surfaces).
    pub x: &'a [f64],
    /// y coordinates.
    pub y: &'a [f64],
    /// Observed values.
    pub value: &'a [f64],
    /// Optional non-negative weights.
    pub weight: Option<&'a [f64]>,
}

impl<'a> Observations<'a> {
    /// Unweighted observations.
    #[must_use]
    pub fn new(x: &'a [f64], y: &'a [f64], value: &'a [f64]) -> Self {
        Self {
            x,
            y,
            value,
            weight: None,
        }
    }

    /// The same observations with weights.
    #[must_use]
    pub fn with_weights(self, weight: &'a [f64]) -> Self {
        Self {
            weight: Some(weight),
            ..self
        }
    }

    /// Number of points.
    #[must_use]
    pub fn len(&self) -> usize {
        self.x.len()
    }

    /// True if there are no points.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    /// Weight of point `i` (1 when unweighted).
    #[must_use]
    pub fn weight_of(&self, i: usize) -> f64 {
        self.weight.and_then(|w| w.get(i).copied()).unwrap_or(1.0)
    }

    /// Checks lengths, finiteness and weights; returns the number of points with weight > 0.
    ///
    /// # Errors
    /// [`RegressionError::LengthMismatch`], [`RegressionError::NonFinite`],
    /// [`RegressionError::InvalidWeight`].
    pub fn validate(&self) -> Result<usize, RegressionError> {
        let n = self.x.len();
        let check_len = |field, got| {
            if got == n {
                Ok(())
            } else {
                Err(RegressionError::LengthMismatch {
                    field,
                    expected: n,
                    got,
                })
            }
        };
        check_len("y", self.y.len())?;
        check_len("value", self.value.len())?;
        if let Some(w) = self.weight {
            check_len("weight", w.len())?;
        }
        for (field, data) in [("x", self.x), ("y", self.y), ("value", self.value)] {
            if let Some(index) = data.iter().position(|v| !v.is_finite()) {
                return Err(RegressionError::NonFinite { field, index });
            }
        }
        match self.weight {
            None => Ok(n),
            Some(w) => {
                if let Some(index) = w.iter().position(|v| !(v.is_finite() && *v >= 0.0)) {
                    return Err(RegressionError::InvalidWeight {
                        index,
                        weight: w[index],
                    });
                }
                Ok(w.iter().filter(|v| **v > 0.0).count())
            }
        }
    }
}

/// Options of [`fit`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitOptions {
    /// A fit whose normalised design matrix has a larger condition number is refused with
    /// [`RegressionError::IllConditioned`]. Default 1e8 (coefficients then keep ≥ 8 digits).
    pub condition_threshold: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            condition_threshold: 1e8,
        }
    }
}

/// Result of a least-squares fit.
#[derive(Debug, Clone, PartialEq)]
pub struct PolyFit {
    /// The fitted surface.
    pub surface: Polynomial2,
    /// Number of points with positive weight.
    pub n_points: usize,
    /// Σ w_i (z_i − f(x_i, y_i))² over all points.
    pub weighted_rss: f64,
    /// σ of eq. (14): √(Σ (z_i − f)² / (n − 1)) over points with positive weight (unweighted
    /// residuals; 0 when n = 1).
    pub sigma: f64,
    /// Condition number of the normalised weighted design matrix.
    pub condition_number: f64,
}

/// Centre and half-range of a coordinate (half-range 1 if all points coincide).
pub(crate) fn normalisation(v: &[f64]) -> (f64, f64) {
    let (lo, hi) = v
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &t| {
            (lo.min(t), hi.max(t))
        });
    if !lo.is_finite() || !hi.is_finite() {
        return (0.0, 1.0);
    }
    let center = 0.5 * (lo + hi);
    let half = 0.5 * (hi - lo);
    let scale = if half > 0.0 && half.is_finite() {
        half
    } else {
        1.0
    };
    (center, scale)
}

/// Fills `row` with the design-matrix entries of (u, v).
pub(crate) fn design_row(u: f64, v: f64, degree: u32, row: &mut [f64]) {
    let mut pu = [0.0; MAX_DEGREE as usize + 2];
    let mut pv = [0.0; MAX_DEGREE as usize + 2];
    pu[0] = 1.0;
    pv[0] = 1.0;
    for k in 1..=degree as usize {
        pu[k] = pu[k - 1] * u;
        pv[k] = pv[k - 1] * v;
    }
    for (slot, (i, j)) in row.iter_mut().zip(term_powers(degree)) {
        *slot = pu[i as usize] * pv[j as usize];
    }
}

/// Fills `row` with √w times the design row of point `i` (normalised coordinates) and returns
/// √w·z_i; `None` for a point of zero weight.
pub(crate) fn weighted_row(
    obs: &Observations<'_>,
    i: usize,
    degree: u32,
    (cx, sx): (f64, f64),
    (cy, sy): (f64, f64),
    row: &mut [f64],
) -> Option<f64> {
    let w = obs.weight_of(i);
    if w <= 0.0 {
        return None;
    }
    let sw = w.sqrt();
    design_row((obs.x[i] - cx) / sx, (obs.y[i] - cy) / sy, degree, row);
    for val in row.iter_mut() {
        *val *= sw;
    }
    Some(sw * obs.value[i])
}

/// The least-squares reduction of the weighted design matrix: R (m × m, upper triangular)
/// and Qᵀb, by a streaming Householder QR (blocks of [`BLOCK_ROWS`] rows stacked under the
/// running R and re-factorised), O(m²) memory whatever the number of points.
pub(crate) fn streaming_qr(
    obs: &Observations<'_>,
    degree: u32,
    norm_x: (f64, f64),
    norm_y: (f64, f64),
) -> (DMatrix<f64>, DVector<f64>) {
    let m = n_terms(degree);
    let mut r = DMatrix::<f64>::zeros(m, m);
    let mut qtb = DVector::<f64>::zeros(m);
    let mut row = vec![0.0; m];
    let n = obs.len();
    let mut start = 0;
    while start < n {
        let end = (start + BLOCK_ROWS).min(n);
        let rows = m + (end - start);
        let mut a = DMatrix::<f64>::zeros(rows, m);
        let mut b = DVector::<f64>::zeros(rows);
        a.view_mut((0, 0), (m, m)).copy_from(&r);
        b.rows_mut(0, m).copy_from(&qtb);
        for (k, i) in (start..end).enumerate() {
            if let Some(z) = weighted_row(obs, i, degree, norm_x, norm_y, &mut row) {
                for (c, val) in row.iter().enumerate() {
                    a[(m + k, c)] = *val;
                }
                b[m + k] = z;
            }
        }
        let qr = a.qr();
        qr.q_tr_mul(&mut b);
        r = qr.r();
        qtb.copy_from(&b.rows(0, m));
        start = end;
    }
    (r, qtb)
}

/// Weighted least-squares fit of a total-degree-`degree` polynomial surface (eq. 6).
///
/// Implements eq. (6): the coefficient vector by least squares.
///
/// # Errors
/// [`RegressionError::DegreeTooHigh`]; input errors of [`Observations::validate`];
/// [`RegressionError::TooFewPoints`] if fewer points with positive weight than terms;
/// [`RegressionError::IllConditioned`] if the condition number exceeds
/// [`FitOptions::condition_threshold`] or the solution is not finite.
pub fn fit(
    obs: &Observations<'_>,
    degree: u32,
    options: &FitOptions,
) -> Result<PolyFit, RegressionError> {
    if degree > MAX_DEGREE {
        return Err(RegressionError::DegreeTooHigh {
            degree,
            max: MAX_DEGREE,
        });
    }
    let usable = obs.validate()?;
    let m = n_terms(degree);
    if usable < m {
        return Err(RegressionError::TooFewPoints {
            degree,
            needed: m,
            got: usable,
        });
    }
    let (cx, sx) = normalisation(obs.x);
    let (cy, sy) = normalisation(obs.y);
    let (r, qtb) = streaming_qr(obs, degree, (cx, sx), (cy, sy));

    let sv = r.clone().svd(false, false).singular_values;
    let smax = sv.iter().copied().fold(0.0_f64, f64::max);
    let smin = sv.iter().copied().fold(f64::INFINITY, f64::min);
    let condition_number = if smin > 0.0 && smax.is_finite() {
        smax / smin
    } else {
        f64::INFINITY
    };
    let threshold = options.condition_threshold;
    let ill = || RegressionError::IllConditioned {
        degree,
        condition_number,
        threshold,
    };
    if condition_number.is_nan() || condition_number > threshold {
        tracing::debug!(degree, condition_number, "refusing ill-conditioned fit");
        return Err(ill());
    }
    let coeffs = r.solve_upper_triangular(&qtb).ok_or_else(ill)?;
    if coeffs.iter().any(|c| !c.is_finite()) {
        return Err(ill());
    }
    let surface = Polynomial2::new(degree, (cx, cy), (sx, sy), coeffs.iter().copied().collect())
        .map_err(|_| ill())?;

    let (mut rss, mut wrss) = (0.0, 0.0);
    for i in 0..obs.len() {
        let w = obs.weight_of(i);
        if w <= 0.0 {
            continue;
        }
        let e = obs.value[i] - surface.evaluate(obs.x[i], obs.y[i]);
        rss += e * e;
        wrss += w * e * e;
    }
    let sigma = if usable > 1 {
        (rss / (usable - 1) as f64).sqrt()
    } else {
        0.0
    };
    tracing::trace!(
        degree,
        n_points = usable,
        sigma,
        condition_number,
        "fitted surface"
    );
    Ok(PolyFit {
        surface,
        n_points: usable,
        weighted_rss: wrss,
        sigma,
        condition_number,
    })
}

/// The leverage h₀ = x₀ᵀ(XᵀWX)⁻¹x₀ of each point of `at` for the design of `surface`'s degree
/// and normalisation over the observations `obs` (their values are not used): the variance of
/// the fitted surface at (x₀, y₀) in units of the variance of one observation of unit weight.
/// A new measurement there differs from the surface's prediction with a standard deviation of
/// σ·√(1 + h₀), σ the scatter of one measurement: the prediction interval of a least-squares
/// fit.
///
/// # Errors
/// Input errors of [`Observations::validate`]; [`RegressionError::TooFewPoints`] if fewer
/// points with positive weight than terms; [`RegressionError::IllConditioned`] if the design
/// is singular; [`RegressionError::NonFinite`] for a point of `at` that is not finite.
pub fn leverages(
    obs: &Observations<'_>,
    surface: &Polynomial2,
    at: &[(f64, f64)],
) -> Result<Vec<f64>, RegressionError> {
    let degree = surface.degree();
    let usable = obs.validate()?;
    let m = n_terms(degree);
    if usable < m {
        return Err(RegressionError::TooFewPoints {
            degree,
            needed: m,
            got: usable,
        });
    }
    if let Some(index) = at
        .iter()
        .position(|p| !(p.0.is_finite() && p.1.is_finite()))
    {
        return Err(RegressionError::NonFinite {
            field: "leverage point",
            index,
        });
    }
    let (cx, cy) = surface.center();
    let (sx, sy) = surface.scale();
    let (r, _) = streaming_qr(obs, degree, (cx, sx), (cy, sy));
    let ill = || RegressionError::IllConditioned {
        degree,
        condition_number: f64::INFINITY,
        threshold: f64::INFINITY,
    };
    // XᵀWX = RᵀR, so h₀ = ‖R⁻ᵀx₀‖².
    let rt = r.transpose();
    let mut row = vec![0.0; m];
    at.iter()
        .map(|&(x, y)| {
            design_row((x - cx) / sx, (y - cy) / sy, degree, &mut row);
            let u = rt
                .solve_lower_triangular(&DVector::from_column_slice(&row))
                .ok_or_else(ill)?;
            let h = u.norm_squared();
            if h.is_finite() { Ok(h) } else { Err(ill()) }
        })
        .collect()
}

/// The standard uncertainty of the fitted surface at each point of `at`, σ·√h₀ ([`leverages`]),
/// with `sigma` the scatter of one observation of unit weight (eq. 14's σ), in the surface's
/// unit: how far the surface itself may be off there, given the records it was fitted from.
///
/// # Errors
/// As [`leverages`].
pub fn standard_errors(
    obs: &Observations<'_>,
    surface: &Polynomial2,
    sigma: f64,
    at: &[(f64, f64)],
) -> Result<Vec<f64>, RegressionError> {
    Ok(leverages(obs, surface, at)?
        .into_iter()
        .map(|h| sigma * h.sqrt())
        .collect())
}

#[cfg(test)]
mod leverage_tests {
    use super::*;

    fn points(n: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        // Irregular, deterministic points over a field in counts.
        let x: Vec<f64> = (0..n)
            .map(|i| -4000.0 + 8000.0 * ((i as f64 * 0.618_034).fract()))
            .collect();
        let y: Vec<f64> = (0..n)
            .map(|i| -3000.0 + 7000.0 * ((i as f64 * 0.414_214 + 0.1).fract()))
            .collect();
        let z = vec![0.0; n];
        (x, y, z)
    }

    #[test]
    fn leverage_of_a_plane_is_the_closed_form() {
        let (x, y, z) = points(40);
        let obs = Observations::new(&x, &y, &z);
        let surface = fit(&obs, 1, &FitOptions::default()).expect("fit");
        let n = x.len() as f64;
        let (mx, my) = (x.iter().sum::<f64>() / n, y.iter().sum::<f64>() / n);
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for (a, b) in x.iter().zip(&y) {
            sxx += (a - mx) * (a - mx);
            sxy += (a - mx) * (b - my);
            syy += (b - my) * (b - my);
        }
        let det = sxx * syy - sxy * sxy;
        let at = [(0.0, 0.0), (5000.0, -2500.0), (-4000.0, 4000.0)];
        let h = leverages(&obs, &surface.surface, &at).expect("leverages");
        for ((x0, y0), h) in at.iter().zip(&h) {
            let (dx, dy) = (x0 - mx, y0 - my);
            let expected = 1.0 / n + (syy * dx * dx - 2.0 * sxy * dx * dy + sxx * dy * dy) / det;
            assert!(
                (h - expected).abs() < 1e-12 * expected.max(1.0),
                "h({x0}, {y0}) = {h}, closed form {expected}"
            );
        }
    }

    #[test]
    fn leverages_at_the_data_sum_to_the_number_of_terms() {
        let (x, y, z) = points(60);
        let obs = Observations::new(&x, &y, &z);
        for degree in 0..=3 {
            let surface = fit(&obs, degree, &FitOptions::default()).expect("fit");
            let at: Vec<(f64, f64)> = x.iter().copied().zip(y.iter().copied()).collect();
            let h = leverages(&obs, &surface.surface, &at).expect("leverages");
            let trace: f64 = h.iter().sum();
            assert!(
                (trace - n_terms(degree) as f64).abs() < 1e-9,
                "degree {degree}: trace of the hat matrix {trace}"
            );
            assert!(h.iter().all(|h| *h > 0.0 && *h <= 1.0 + 1e-12));
        }
    }

    /// A constant fitted to n points is their mean, whose standard error is σ/√n everywhere.
    #[test]
    fn the_standard_error_of_a_constant_is_sigma_over_root_n() {
        let (x, y, z) = points(25);
        let obs = Observations::new(&x, &y, &z);
        let surface = fit(&obs, 0, &FitOptions::default()).expect("fit");
        let at = [(0.0, 0.0), (1e4, -1e4)];
        let u = standard_errors(&obs, &surface.surface, 0.3, &at).expect("standard errors");
        for u in u {
            assert!((u - 0.3 / 5.0).abs() < 1e-12, "{u}");
        }
    }

    #[test]
    fn a_point_that_is_not_finite_is_an_error() {
        let (x, y, z) = points(10);
        let obs = Observations::new(&x, &y, &z);
        let surface = fit(&obs, 1, &FitOptions::default()).expect("fit");
        assert!(leverages(&obs, &surface.surface, &[(f64::NAN, 0.0)]).is_err());
    }
}

//! The correction 1-form of eq. (5) fitted as an *exact* form.
//!
//! The correction integrates `dx̄ = K̄x dx + K̄yx dy`, `dȳ = K̄yy dy` along the scanner's
//! trajectory. The corrected position is a function of the scanner position, whatever path the
//! raster took to it, only if the form is exact (closed on the plane):
//!
//! ```text
//! ∂K̄x/∂y = ∂K̄yx/∂x,        ∂K̄yy/∂x = 0.
//! ```
//!
//! Fitted one by one (eqs. 2 and 11), the three surfaces break both conditions wherever the
//! records' scatter lets them, and a raster then reads K̄yx and K̄yy where its slow axis steps:
//! at the start of every line, which for an image wider than the net is outside the records. An
//! x term of K̄yy that no record asked for then sets each line's y scale.
//!
//! [`fit_exact_form`] fits the two potentials instead: x̄(x, y), a total-degree d + 1
//! polynomial, and ȳ(y), a degree d + 1 polynomial of y alone, so that their derivatives
//! (K̄x, K̄yx) = ∇x̄ and K̄yy = dȳ/dy match the records in weighted least squares. The three
//! surfaces are those derivatives (degree d, on the records' normalisation), and the form they
//! make is exact by construction. d is chosen by BIC for each potential, as
//! [`crate::select_degree`] chooses a surface's.

use crate::fit::normalisation;
use crate::polynomial::{Polynomial2, n_terms, term_index, term_powers};
use crate::select::bic_score;
use crate::{RegressionError, least_squares};

/// The records of the form's three coefficients at their positions.
#[derive(Debug, Clone, Copy)]
pub struct FormObservations<'a> {
    /// Record x positions, counts.
    pub x: &'a [f64],
    /// Record y positions, counts.
    pub y: &'a [f64],
    /// K̄x at each record, nm per count.
    pub kx_nm_per_count: &'a [f64],
    /// K̄yx = K̄y sin α at each record, nm per count.
    pub kyx_nm_per_count: &'a [f64],
    /// K̄yy = K̄y cos α at each record, nm per count.
    pub kyy_nm_per_count: &'a [f64],
}

/// The scatter of one record's K̄x and K̄yx about the truth, nm per count: the x potential's
/// two kinds of observation are weighted by 1/σ². A value that is not finite and positive (an
/// exact record set) counts as equal weights.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormScatter {
    /// σ of K̄x, nm per count.
    pub kx_nm_per_count: f64,
    /// σ of K̄yx, nm per count.
    pub kyx_nm_per_count: f64,
}

/// The exact form fitted by [`fit_exact_form`].
#[derive(Debug, Clone, PartialEq)]
pub struct ExactForm {
    /// x̄(x, y), nm: total degree d_x + 1, no constant term.
    pub x_potential_nm: Polynomial2,
    /// ȳ(y), nm: degree d_y + 1 in y alone, no constant term.
    pub y_potential_nm: Polynomial2,
    /// K̄x = ∂x̄/∂x, nm per count (degree d_x).
    pub kx_nm_per_count: Polynomial2,
    /// K̄yx = ∂x̄/∂y, nm per count (degree d_x).
    pub kyx_nm_per_count: Polynomial2,
    /// K̄yy = dȳ/dy, nm per count (degree d_y; no x term).
    pub kyy_nm_per_count: Polynomial2,
    /// Free coefficients of the two potentials together (for a model choice).
    pub n_params: usize,
}

/// Fits the correction 1-form as an exact form (module docs), the derivative surfaces of degree
/// at most `max_degree`. A degree d is tried only while the records stand in more than d + 1
/// distinct columns and rows, and while [`crate::degree_supported`] allows it for the records
/// and their distinct places, the rule of the surfaces fitted one by one: the potentials' K̄x
/// and K̄yx are two observations at the same places, which do not make a higher degree safe to
/// extrapolate (the quick simulated job's budget row with creep off put 8.7 % of the side on
/// its images at degree 2 from 9 records, 1.5 % at degree 1).
///
/// # Errors
/// [`RegressionError::LengthMismatch`] for slices of different lengths;
/// [`RegressionError::NonFinite`] for NaN/∞ in a position or coefficient;
/// [`RegressionError::TooFewPoints`] with fewer than two records;
/// [`RegressionError::IllConditioned`] when even the degree-0 form is not determined (all
/// records at one y, say).
pub fn fit_exact_form(
    obs: &FormObservations<'_>,
    max_degree: u32,
    scatter: FormScatter,
) -> Result<ExactForm, RegressionError> {
    let n = obs.x.len();
    for (field, values) in [
        ("y", obs.y),
        ("kx_nm_per_count", obs.kx_nm_per_count),
        ("kyx_nm_per_count", obs.kyx_nm_per_count),
        ("kyy_nm_per_count", obs.kyy_nm_per_count),
    ] {
        if values.len() != n {
            return Err(RegressionError::LengthMismatch {
                field,
                expected: n,
                got: values.len(),
            });
        }
    }
    for (field, values) in [
        ("x", obs.x),
        ("y", obs.y),
        ("kx_nm_per_count", obs.kx_nm_per_count),
        ("kyx_nm_per_count", obs.kyx_nm_per_count),
        ("kyy_nm_per_count", obs.kyy_nm_per_count),
    ] {
        if let Some(index) = values.iter().position(|v| !v.is_finite()) {
            return Err(RegressionError::NonFinite { field, index });
        }
    }
    if n < 2 {
        return Err(RegressionError::TooFewPoints {
            degree: 0,
            needed: 2,
            got: n,
        });
    }
    let (cx, sx) = normalisation(obs.x);
    let (cy, sy) = normalisation(obs.y);
    let (wx, wyx) = match (scatter.kx_nm_per_count, scatter.kyx_nm_per_count) {
        (a, b) if a.is_finite() && a > 0.0 && b.is_finite() && b > 0.0 => (1.0 / a, 1.0 / b),
        _ => (1.0, 1.0),
    };
    // A derivative surface of degree d needs more columns and rows of records than d + 1 (on
    // a 3 × 3 net, a cubic K̄yy through three rows whose y jitter by a few counts reached
    // ±0.9 nm/count a quarter of the field beyond them).
    let (x_levels, y_levels) = (levels(obs.x, sx), levels(obs.y, sy));
    let x_max_degree = max_degree.min(x_levels.min(y_levels).saturating_sub(2) as u32);
    let places = crate::distinct_places(obs.x, obs.y);
    let x_potential = select_potential(x_max_degree, (n, places), |degree| {
        fit_x_potential(obs, degree, (cx, sx), (cy, sy), (wx, wyx))
    })?;
    let y_max_degree = max_degree.min(y_levels.saturating_sub(2) as u32);
    let y_potential = select_potential(y_max_degree, (n, places), |degree| {
        fit_y_potential(obs, degree, (cx, sx), (cy, sy))
    })?;
    let n_params = n_terms(x_potential.degree()) - 1 + y_potential.degree() as usize;
    Ok(ExactForm {
        n_params,
        kx_nm_per_count: x_potential.partial_x(),
        kyx_nm_per_count: x_potential.partial_y(),
        kyy_nm_per_count: y_potential.partial_y(),
        x_potential_nm: x_potential,
        y_potential_nm: y_potential,
    })
}

/// The records' distinct positions along one coordinate: values closer than 2 % of the
/// half-range `scale` to the previous one (sorted) count as one row (or column).
fn levels(v: &[f64], scale: f64) -> usize {
    let mut sorted = v.to_vec();
    sorted.sort_by(f64::total_cmp);
    let gap = 0.02 * scale;
    1 + sorted.windows(2).filter(|w| w[1] - w[0] > gap).count()
}

/// One candidate potential: the polynomial, its number of free coefficients and observations,
/// and its weighted RSS with the values it was fitted to.
struct Candidate {
    potential: Polynomial2,
    n_params: usize,
    n_points: usize,
    weighted_rss: f64,
    values: Vec<f64>,
}

/// The BIC-best candidate of degree 0…`max_degree` (of the derivative surfaces); stops at the
/// first degree that has too few observations or does not fit, and fails only at degree 0.
fn select_potential(
    max_degree: u32,
    (n_records, n_places): (usize, usize),
    fit: impl Fn(u32) -> Result<Candidate, RegressionError>,
) -> Result<Polynomial2, RegressionError> {
    let mut best: Option<(f64, Polynomial2)> = None;
    for degree in 0..=max_degree.min(crate::MAX_DEGREE - 1) {
        // As for a surface fitted by itself: the potentials' extra observations come from the
        // same places.
        if !crate::degree_supported(degree, n_records, n_places) {
            break;
        }
        let candidate = match fit(degree) {
            Ok(c) => c,
            Err(e) if degree == 0 => return Err(e),
            Err(e) => {
                tracing::debug!(degree, error = %e, "exact-form degree search stops");
                break;
            }
        };
        let score = bic_score(
            candidate.n_points,
            candidate.n_params,
            candidate.weighted_rss,
            &candidate.values,
        );
        if best.as_ref().is_none_or(|(s, _)| score < *s) {
            best = Some((score, candidate.potential));
        }
    }
    best.map(|(_, p)| p).ok_or(RegressionError::TooFewPoints {
        degree: 0,
        needed: 2,
        got: n_records,
    })
}

/// x̄ of derivative degree `degree`: for every record, the rows ∂/∂x (weight `wx`) and ∂/∂y
/// (weight `wyx`) of every term of total degree 1…degree + 1.
fn fit_x_potential(
    obs: &FormObservations<'_>,
    degree: u32,
    norm_x: (f64, f64),
    norm_y: (f64, f64),
    (wx, wyx): (f64, f64),
) -> Result<Candidate, RegressionError> {
    let terms: Vec<(u32, u32)> = term_powers(degree + 1).skip(1).collect();
    let mut rows = Vec::with_capacity(2 * obs.x.len());
    let mut rhs = Vec::with_capacity(2 * obs.x.len());
    for (i, (&x, &y)) in obs.x.iter().zip(obs.y).enumerate() {
        rows.push(derivative_row(&terms, (x, y), norm_x, norm_y, true, wx));
        rhs.push(wx * obs.kx_nm_per_count[i]);
        rows.push(derivative_row(&terms, (x, y), norm_x, norm_y, false, wyx));
        rhs.push(wyx * obs.kyx_nm_per_count[i]);
    }
    solve_potential(degree, &terms, &rows, rhs, norm_x, norm_y)
}

/// ȳ of derivative degree `degree`: the rows are d/dy of y¹…y^(degree + 1).
fn fit_y_potential(
    obs: &FormObservations<'_>,
    degree: u32,
    norm_x: (f64, f64),
    norm_y: (f64, f64),
) -> Result<Candidate, RegressionError> {
    let terms: Vec<(u32, u32)> = (1..=degree + 1).map(|q| (0, q)).collect();
    let rows: Vec<Vec<f64>> = obs
        .x
        .iter()
        .zip(obs.y)
        .map(|(&x, &y)| derivative_row(&terms, (x, y), norm_x, norm_y, false, 1.0))
        .collect();
    solve_potential(
        degree,
        &terms,
        &rows,
        obs.kyy_nm_per_count.to_vec(),
        norm_x,
        norm_y,
    )
}

/// `weight` × ∂/∂x (`along_x`) or ∂/∂y of each term uᵖvᵠ at (x, y), per count.
fn derivative_row(
    terms: &[(u32, u32)],
    (x, y): (f64, f64),
    (cx, sx): (f64, f64),
    (cy, sy): (f64, f64),
    along_x: bool,
    weight: f64,
) -> Vec<f64> {
    let (u, v) = ((x - cx) / sx, (y - cy) / sy);
    terms
        .iter()
        .map(|&(p, q)| {
            if along_x {
                weight * derivative(p, u) * v.powi(q as i32) / sx
            } else {
                weight * u.powi(p as i32) * derivative(q, v) / sy
            }
        })
        .collect()
}

/// The potential of total degree `degree` + 1 whose `terms` solve `rows`·c = `rhs` in least
/// squares.
fn solve_potential(
    degree: u32,
    terms: &[(u32, u32)],
    rows: &[Vec<f64>],
    rhs: Vec<f64>,
    (cx, sx): (f64, f64),
    (cy, sy): (f64, f64),
) -> Result<Candidate, RegressionError> {
    let fit = least_squares(rows, &rhs, &vec![false; terms.len()])?;
    let mut coefficients = vec![0.0; n_terms(degree + 1)];
    for (&(p, q), c) in terms.iter().zip(&fit.coefficients) {
        coefficients[term_index(p, q)] = *c;
    }
    Ok(Candidate {
        potential: Polynomial2::new(degree + 1, (cx, cy), (sx, sy), coefficients)?,
        n_params: terms.len(),
        n_points: rhs.len(),
        weighted_rss: fit.residual_rms.powi(2) * rhs.len() as f64,
        values: rhs,
    })
}

/// d/dt tᵖ = p·tᵖ⁻¹ (0 for p = 0).
fn derivative(p: u32, t: f64) -> f64 {
    if p == 0 {
        0.0
    } else {
        f64::from(p) * t.powi(p as i32 - 1)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// [`fit_exact_form`] of the records with the x potential's two kinds weighted alike.
    fn fit(
        (x, y): (&[f64], &[f64]),
        [kx, kyx, kyy]: [&[f64]; 3],
        max_degree: u32,
        scatter: f64,
    ) -> ExactForm {
        fit_exact_form(
            &FormObservations {
                x,
                y,
                kx_nm_per_count: kx,
                kyx_nm_per_count: kyx,
                kyy_nm_per_count: kyy,
            },
            max_degree,
            FormScatter {
                kx_nm_per_count: scatter,
                kyx_nm_per_count: scatter,
            },
        )
        .unwrap()
    }

    /// A field whose form is exact: x̄ = a·x + b·y + c·x·y + e·y², ȳ = f·y + g·y² (nm, counts).
    fn exact_field(x: f64, y: f64) -> [f64; 3] {
        let (a, b, c, e, f, g) = (0.02, 0.003, 2e-7, -1e-7, 0.015, 3e-7);
        [a + c * y, b + c * x + 2.0 * e * y, f + 2.0 * g * y]
    }

    fn grid(n: usize, half_counts: f64) -> (Vec<f64>, Vec<f64>) {
        let mut x = Vec::new();
        let mut y = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let t = |k: usize| -half_counts + 2.0 * half_counts * k as f64 / (n - 1) as f64;
                x.push(t(i));
                y.push(t(j));
            }
        }
        (x, y)
    }

    #[test]
    fn an_exact_field_comes_back_exactly_and_its_potentials_are_the_integrals() {
        let (x, y) = grid(5, 4000.0);
        let values: Vec<[f64; 3]> = x.iter().zip(&y).map(|(x, y)| exact_field(*x, *y)).collect();
        let col = |k: usize| values.iter().map(|v| v[k]).collect::<Vec<_>>();
        let (kx, kyx, kyy) = (col(0), col(1), col(2));
        let form = fit((&x, &y), [&kx, &kyx, &kyy], 3, 0.0);
        // Beyond the records too: the form is the field's.
        for (px, py) in [(0.0, 0.0), (-9000.0, 3000.0), (7000.0, -8000.0)] {
            let [tx, tyx, tyy] = exact_field(px, py);
            assert!((form.kx_nm_per_count.evaluate(px, py) - tx).abs() < 1e-12);
            assert!((form.kyx_nm_per_count.evaluate(px, py) - tyx).abs() < 1e-12);
            assert!((form.kyy_nm_per_count.evaluate(px, py) - tyy).abs() < 1e-12);
            let (gx, gy) = form.x_potential_nm.gradient(px, py);
            assert!((gx - tx).abs() < 1e-12 && (gy - tyx).abs() < 1e-12);
        }
        // The path integral around a closed loop is zero: x̄ and ȳ are functions of position.
        let (a, b) = ((-3000.0, -2000.0), (2500.0, 3500.0));
        let around = form.kx_nm_per_count.integrate_x(a.0, b.0, a.1)
            + form.kyx_nm_per_count.integrate_y(b.0, a.1, b.1)
            - form.kx_nm_per_count.integrate_x(a.0, b.0, b.1)
            - form.kyx_nm_per_count.integrate_y(a.0, a.1, b.1);
        assert!(around.abs() < 1e-9, "{around}");
    }

    #[test]
    fn an_x_term_of_the_y_scale_that_the_records_scatter_into_is_not_fitted() {
        // K̄yy depends on y alone; the records' K̄yy carry an x-dependent error of ±3 %
        // (a chequerboard, as noise frozen into a stored image does). Independently fitted, the
        // surface takes it up as an x slope and reads it at the left edge; the exact form
        // cannot have an x term.
        let (x, y) = grid(4, 4000.0);
        let truth = |y: f64| 0.015 + 6e-7 * y;
        let kyy: Vec<f64> = x
            .iter()
            .zip(&y)
            .map(|(x, y)| truth(*y) * (1.0 + 0.03 * (x / 4000.0)))
            .collect();
        let kx = vec![0.02; x.len()];
        let kyx = vec![0.0; x.len()];
        let form = fit((&x, &y), [&kx, &kyx, &kyy], 2, 1e-4);
        for px in [-12000.0, 0.0, 12000.0] {
            for py in [-4000.0, 0.0, 4000.0] {
                let got = form.kyy_nm_per_count.evaluate(px, py);
                assert!((got / truth(py) - 1.0).abs() < 1e-3, "{px} {py} {got}");
            }
        }
        let independent = crate::fit(
            &crate::Observations::new(&x, &y, &kyy),
            1,
            &Default::default(),
        )
        .unwrap()
        .surface;
        let left = independent.evaluate(-12000.0, 0.0) / truth(0.0) - 1.0;
        assert!(left < -0.05, "the independent fit's left edge: {left}");
    }

    #[test]
    fn the_y_scale_of_three_rows_of_records_is_at_most_linear_in_y() {
        // Three rows of eight records whose y jitter by a few counts: a quadratic K̄yy would
        // pass through the three rows' means exactly, and BIC could take a cubic through the
        // jitter (24 records allow a degree-3 surface by the count alone).
        let mut x = Vec::new();
        let mut y = Vec::new();
        for (k, (i, j)) in (0..8).flat_map(|i| (0..3).map(move |j| (i, j))).enumerate() {
            x.push(f64::from(i) * 5_000.0 - 17_500.0 + (k as f64 * 1.3).sin() * 8.0);
            y.push(f64::from(j) * 20_000.0 - 20_000.0 + (k as f64 * 2.1).cos() * 8.0);
        }
        let kx = vec![0.021; 24];
        let kyx = vec![0.0005; 24];
        let kyy: Vec<f64> = y
            .iter()
            .enumerate()
            .map(|(k, y)| {
                // An error that follows each record's y jitter (δ, ±8 counts) and its own.
                let delta = y - (y / 20_000.0).round() * 20_000.0;
                0.022 + 1e-8 * y + 1e-5 * delta + 2e-5 * (k as f64 * 0.7).sin()
            })
            .collect();
        let form = fit((&x, &y), [&kx, &kyx, &kyy], 5, 1e-4);
        assert!(
            form.kyy_nm_per_count.degree() <= 1,
            "{:?}",
            form.kyy_nm_per_count
        );
        for y in [-30_000.0, 30_000.0] {
            let v = form.kyy_nm_per_count.evaluate(0.0, y);
            assert!((v / 0.022 - 1.0).abs() < 0.05, "K̄yy({y}) = {v}");
        }
    }

    #[test]
    fn partial_derivatives_are_the_gradient() {
        let c: Vec<f64> = (0..n_terms(4)).map(|k| ((k as f64) * 0.77).cos()).collect();
        let p = Polynomial2::new(4, (120.0, -80.0), (900.0, 1300.0), c).unwrap();
        let (dx, dy) = (p.partial_x(), p.partial_y());
        assert_eq!((dx.degree(), dy.degree()), (3, 3));
        for (x, y) in [(0.0, 0.0), (500.0, -2000.0), (-1500.0, 700.0)] {
            let (gx, gy) = p.gradient(x, y);
            assert!((dx.evaluate(x, y) - gx).abs() < 1e-12 * gx.abs().max(1e-3));
            assert!((dy.evaluate(x, y) - gy).abs() < 1e-12 * gy.abs().max(1e-3));
        }
        let constant = Polynomial2::constant(3.0).unwrap();
        assert_eq!(constant.partial_x().evaluate(5.0, 6.0), 0.0);
    }

    #[test]
    fn ragged_or_non_finite_records_are_typed_errors() {
        let scatter = FormScatter {
            kx_nm_per_count: 1.0,
            kyx_nm_per_count: 1.0,
        };
        let obs = |y: &'static [f64], kyy: &'static [f64]| FormObservations {
            x: &[0.0, 1.0, 2.0],
            y,
            kx_nm_per_count: &[1.0, 1.0, 1.0],
            kyx_nm_per_count: &[0.0, 0.0, 0.0],
            kyy_nm_per_count: kyy,
        };
        assert!(matches!(
            fit_exact_form(&obs(&[0.0, 1.0], &[1.0, 1.0, 1.0]), 2, scatter),
            Err(RegressionError::LengthMismatch { field: "y", .. })
        ));
        assert!(matches!(
            fit_exact_form(&obs(&[0.0, 1.0, 2.0], &[1.0, f64::NAN, 1.0]), 2, scatter),
            Err(RegressionError::NonFinite {
                field: "kyy_nm_per_count",
                index: 1
            })
        ));
    }
}

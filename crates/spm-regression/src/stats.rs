//! Scanner-error statistics of §4 of the paper: σ (eq. 14) and Δmax (eq. 13), and the product
//! values of eq. (11).

use crate::fit::{Observations, normalisation};
use crate::{Polynomial2, RegressionError};

/// σ of eq. (14): √(Σᵢ (zᵢ − f(xᵢ, yᵢ))² / (n − 1)), the RMS deviation of the measured LCCs from
/// their regression surface, over the points with positive weight (weights are otherwise not
/// used: eq. 14 is unweighted).
///
/// Implements eq. (14).
///
/// # Errors
/// Input errors of [`Observations::validate`]; [`RegressionError::TooFewPoints`] if n < 2.
pub fn sigma(surface: &Polynomial2, obs: &Observations<'_>) -> Result<f64, RegressionError> {
    let n = obs.validate()?;
    if n < 2 {
        return Err(RegressionError::TooFewPoints {
            degree: surface.degree(),
            needed: 2,
            got: n,
        });
    }
    let rss: f64 = (0..obs.len())
        .filter(|&i| obs.weight_of(i) > 0.0)
        .map(|i| (obs.value[i] - surface.evaluate(obs.x[i], obs.y[i])).powi(2))
        .sum();
    Ok((rss / (n - 1) as f64).sqrt())
}

/// A rectangular region of the scanner field, in the surface's x/y unit (counts).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Field {
    /// Lower x bound.
    pub x_min: f64,
    /// Upper x bound.
    pub x_max: f64,
    /// Lower y bound.
    pub y_min: f64,
    /// Upper y bound.
    pub y_max: f64,
}

/// Result of [`delta_max`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DeltaMax {
    /// max |f(x, y) − f(x₀, y₀)| over the grid.
    pub value: f64,
    /// x of a grid point where the maximum is reached.
    pub at_x: f64,
    /// y of a grid point where the maximum is reached.
    pub at_y: f64,
}

/// Δmax of eq. (13): max |f(x, y) − f(x₀, y₀)| over an `nx` × `ny` grid spanning `field`
/// (both ends included), `reference` = (x₀, y₀) chosen by the caller (the origin of the
/// image for virtual calibration, the scanner origin for real calibration). A measure of how
/// far the surface is from the horizontal plane of an ideal scanner.
///
/// Implements eq. (13).
///
/// # Errors
/// [`RegressionError::InvalidArgument`] for a grid with fewer than 1 point per axis or a field
/// with non-finite or reversed bounds; [`RegressionError::NonFinite`] for a non-finite reference.
pub fn delta_max(
    surface: &Polynomial2,
    field: &Field,
    nx: usize,
    ny: usize,
    reference: (f64, f64),
) -> Result<DeltaMax, RegressionError> {
    if nx == 0 || ny == 0 {
        return Err(RegressionError::InvalidArgument(format!(
            "delta_max grid must have at least 1×1 points, got {nx}×{ny}"
        )));
    }
    let bounds = [field.x_min, field.x_max, field.y_min, field.y_max];
    if bounds.iter().any(|b| !b.is_finite())
        || field.x_min > field.x_max
        || field.y_min > field.y_max
    {
        return Err(RegressionError::InvalidArgument(format!(
            "invalid field {field:?}"
        )));
    }
    if !reference.0.is_finite() || !reference.1.is_finite() {
        return Err(RegressionError::NonFinite {
            field: "reference",
            index: usize::from(reference.0.is_finite()),
        });
    }
    let f0 = surface.evaluate(reference.0, reference.1);
    let coord = |lo: f64, hi: f64, n: usize, k: usize| {
        if n == 1 {
            lo
        } else {
            lo + (hi - lo) * k as f64 / (n - 1) as f64
        }
    };
    let mut best = DeltaMax {
        value: 0.0,
        at_x: reference.0,
        at_y: reference.1,
    };
    let mut first = true;
    for j in 0..ny {
        let y = coord(field.y_min, field.y_max, ny, j);
        for i in 0..nx {
            let x = coord(field.x_min, field.x_max, nx, i);
            let d = (surface.evaluate(x, y) - f0).abs();
            if first || d > best.value {
                best = DeltaMax {
                    value: d,
                    at_x: x,
                    at_y: y,
                };
                first = false;
            }
        }
    }
    Ok(best)
}

/// The products K̄y·sin α and K̄y·cos α of eq. (11), through which the product surfaces
/// K̄yx^r and K̄yy^r are fitted (fit each with [`crate::fit`] like any other LCC).
///
/// Implements eq. (11): the values the product surfaces are fitted to.
///
/// # Errors
/// [`RegressionError::LengthMismatch`], [`RegressionError::NonFinite`].
pub fn product_values(
    ky_nm_per_count: &[f64],
    alpha_rad: &[f64],
) -> Result<(Vec<f64>, Vec<f64>), RegressionError> {
    if ky_nm_per_count.len() != alpha_rad.len() {
        return Err(RegressionError::LengthMismatch {
            field: "alpha_rad",
            expected: ky_nm_per_count.len(),
            got: alpha_rad.len(),
        });
    }
    let mut sin_part = Vec::with_capacity(alpha_rad.len());
    let mut cos_part = Vec::with_capacity(alpha_rad.len());
    for (index, (&k, &a)) in ky_nm_per_count.iter().zip(alpha_rad).enumerate() {
        if !k.is_finite() {
            return Err(RegressionError::NonFinite {
                field: "ky_nm_per_count",
                index,
            });
        }
        if !a.is_finite() {
            return Err(RegressionError::NonFinite {
                field: "alpha_rad",
                index,
            });
        }
        sin_part.push(k * a.sin());
        cos_part.push(k * a.cos());
    }
    Ok((sin_part, cos_part))
}

/// The median of `values` (reordered in place, by selection: O(n)): the middle value, or the
/// mean of the two middle values for an even count; `None` when empty. The workspace's one
/// median.
pub fn median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let (below, upper, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    let upper = *upper;
    if n % 2 == 1 {
        return Some(upper);
    }
    // The lower middle is the largest of the values below the upper one.
    let lower = below
        .iter()
        .copied()
        .max_by(f64::total_cmp)
        .unwrap_or(upper);
    Some(0.5 * (lower + upper))
}

/// The upper median of `values` (reordered in place, by selection: O(n)): the middle value, or
/// the upper of the two middle values for an even count (`sorted[n / 2]`); `None` when empty.
///
/// The robust scale of a sample whose values are themselves the statistic kept (a nearest-
/// neighbour distance, a residual that decides an outlier): it is always one of the values, so a
/// threshold or a lattice constant drawn from it is a measured distance, never the mean of two.
/// Where the mean of the two middles is wanted, [`median`].
pub fn upper_median(values: &mut [f64]) -> Option<f64> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let (_, middle, _) = values.select_nth_unstable_by(n / 2, f64::total_cmp);
    Some(*middle)
}

/// The root mean square √(Σ vᵢ² / n) of `values`, summed in order; `None` when empty (no
/// sample has no RMS: callers state what an empty set means for them). The workspace's one RMS.
#[must_use]
pub fn rms(values: &[f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    Some((values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt())
}

/// The points that are outliers of a joint fit of several quantities (e.g. a record's K̄x,
/// K̄y and α, all spoilt by one misrecognised structure): `true` where the point's residual in
/// any quantity lies beyond `k` robust standard deviations of that quantity's residuals, the
/// robust σ being 1.4826 × the median absolute deviation from the median over the points in
/// `among`. Points outside `among` are judged against the same σ. A quantity whose robust σ
/// is zero or not finite flags nothing; a non-finite residual is an outlier. A residual set
/// shorter than `among` judges only its own points.
#[must_use]
pub fn joint_outliers(residuals: &[&[f64]], among: &[bool], k: f64) -> Vec<bool> {
    let n = among.len();
    let mut out = vec![false; n];
    for r in residuals {
        let mut inside: Vec<f64> = r
            .iter()
            .zip(among)
            .filter(|(v, a)| **a && v.is_finite())
            .map(|(v, _)| *v)
            .collect();
        let Some(centre) = median(&mut inside) else {
            continue;
        };
        let mut deviations: Vec<f64> = inside.iter().map(|v| (v - centre).abs()).collect();
        let Some(mad) = median(&mut deviations) else {
            continue;
        };
        let sigma = 1.4826 * mad;
        if !(sigma.is_finite() && sigma > 0.0) {
            continue;
        }
        for (flag, v) in out.iter_mut().zip(r.iter()) {
            if !v.is_finite() || (v - centre).abs() > k * sigma {
                *flag = true;
            }
        }
    }
    out
}

#[cfg(test)]
mod median_tests {
    use super::{joint_outliers, median, rms, upper_median};

    /// Residuals whose median is 0 and median absolute deviation 1 (robust σ 1.4826):
    /// flagged beyond k·σ in any quantity, judged over `among` only.
    #[test]
    fn check_joint_outliers() {
        let check = |residuals: &[&[f64]], among: &[bool], k: f64, expected: &[bool]| {
            assert_eq!(
                joint_outliers(residuals, among, k),
                expected,
                "{residuals:?} over {among:?}, k {k}"
            );
        };
        let a: &[f64] = &[-1.0, 0.0, 1.0, -1.0, 1.0, 0.0, 4.0];
        let b: &[f64] = &[0.0, -1.0, 1.0, 0.0, 1.0, -1.0, 0.0];
        let all = [true; 7];
        // 4 / 1.4826 = 2.70 σ: an outlier at 2.5 σ, not at 3.
        check(&[a], &all, 3.0, &[false; 7]);
        check(
            &[a],
            &all,
            2.5,
            &[false, false, false, false, false, false, true],
        );
        // Jointly: b's largest is 1 / 1.4826 = 0.67 σ; a point is flagged by any quantity.
        check(
            &[b, a],
            &all,
            2.5,
            &[false, false, false, false, false, false, true],
        );
        check(
            &[b],
            &all,
            0.6,
            &[false, true, true, false, true, true, false],
        );
        // σ from `among` only: without the last point a's MAD is 1 still, and the point
        // left out is judged against it.
        let among = [true, true, true, true, true, true, false];
        check(
            &[a],
            &among,
            2.5,
            &[false, false, false, false, false, false, true],
        );
        // A quantity without spread flags nothing; a NaN residual is an outlier.
        check(&[&[2.0; 7]], &all, 3.0, &[false; 7]);
        let with_nan: &[f64] = &[-1.0, 0.0, 1.0, -1.0, 1.0, 0.0, f64::NAN];
        check(
            &[with_nan],
            &all,
            3.0,
            &[false, false, false, false, false, false, true],
        );
    }

    #[test]
    fn check_median() {
        let check = |input: &[f64], expected: Option<f64>| {
            let mut v = input.to_vec();
            assert_eq!(median(&mut v), expected, "{input:?}");
        };
        check(&[], None);
        check(&[3.0], Some(3.0));
        check(&[5.0, 1.0], Some(3.0));
        check(&[2.0, 9.0, -1.0], Some(2.0));
        check(&[4.0, 1.0, 3.0, 2.0], Some(2.5));
        check(&[7.0, 7.0, 1.0, 7.0], Some(7.0));
    }

    /// Against the definition (sort, take the middle or the mean of the two middles) on
    /// deterministic pseudo-random vectors of every length up to 40.
    #[test]
    fn the_selection_median_is_the_sorted_one() {
        let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
        for n in 1..=40 {
            let v: Vec<f64> = (0..n)
                .map(|_| {
                    state = state
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1);
                    ((state >> 33) % 17) as f64 - 8.0
                })
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let expected = if n % 2 == 1 {
                sorted[n / 2]
            } else {
                0.5 * (sorted[n / 2 - 1] + sorted[n / 2])
            };
            assert_eq!(median(&mut v.clone()), Some(expected), "{v:?}");
        }
    }

    #[test]
    fn check_upper_median() {
        let check = |input: &[f64], expected: Option<f64>| {
            let mut v = input.to_vec();
            assert_eq!(upper_median(&mut v), expected, "{input:?}");
        };
        check(&[], None);
        check(&[3.0], Some(3.0));
        check(&[5.0, 1.0], Some(5.0));
        check(&[2.0, 9.0, -1.0], Some(2.0));
        check(&[4.0, 1.0, 3.0, 2.0], Some(3.0));
    }

    /// Against the definition (sort, take `sorted[n / 2]`), bit for bit, on deterministic
    /// pseudo-random vectors of every length up to 40 (signed zeros included).
    #[test]
    fn the_selection_upper_median_is_the_sorted_one() {
        let mut state: u64 = 0x2545_F491_4F6C_DD1D;
        for n in 1..=40 {
            let v: Vec<f64> = (0..n)
                .map(|_| {
                    state = state
                        .wrapping_mul(6_364_136_223_846_793_005)
                        .wrapping_add(1);
                    let k = ((state >> 33) % 9) as f64 - 4.0;
                    if k == 0.0 && state & 1 == 1 {
                        -0.0
                    } else {
                        k * 0.37
                    }
                })
                .collect();
            let mut sorted = v.clone();
            sorted.sort_by(f64::total_cmp);
            let got = upper_median(&mut v.clone()).map(f64::to_bits);
            assert_eq!(got, Some(sorted[n / 2].to_bits()), "{v:?}");
        }
    }

    #[test]
    fn check_rms() {
        assert_eq!(rms(&[]), None);
        assert_eq!(rms(&[-2.0]), Some(2.0));
        // √((9 + 16) / 2), the closed form.
        assert_eq!(rms(&[3.0, 4.0]), Some(12.5_f64.sqrt()));
        assert_eq!(rms(&[1.0, -1.0, 1.0, -1.0]), Some(1.0));
    }
}

/// Whether `n_records` at `n_places` distinct places ([`distinct_places`]) support a surface
/// of total degree `degree`: degree 0 always; otherwise at least twice as many records as the
/// surface has terms, and more places than terms (one place repeated many times fixes no
/// slope: Si_7x7_051's 15 records at 4 places).
#[must_use]
pub fn degree_supported(degree: u32, n_records: usize, n_places: usize) -> bool {
    let terms = crate::n_terms(degree);
    degree == 0 || (2 * terms <= n_records && terms < n_places)
}

/// How many distinct places the points (`x`, `y`) stand at: a point within 2 % of the
/// points' half-range (per coordinate) of an earlier place counts as that place. Repeats of a
/// net's node, and nodes that attached to the same feature, are one place
/// ([`degree_supported`]; Si_7x7_051: 15 records at 4 places, through which a quadratic read
/// K̄y < 0 at the image's corner).
#[must_use]
pub fn distinct_places(x: &[f64], y: &[f64]) -> usize {
    // Half-ranges as the fits normalise them (1 when every point has one coordinate).
    let (tx, ty) = (0.02 * normalisation(x).1, 0.02 * normalisation(y).1);
    let mut places: Vec<(f64, f64)> = Vec::new();
    for (&px, &py) in x.iter().zip(y) {
        if !places
            .iter()
            .any(|&(qx, qy)| (px - qx).abs() <= tx && (py - qy).abs() <= ty)
        {
            places.push((px, py));
        }
    }
    places.len()
}

#[cfg(test)]
mod place_tests {
    use super::distinct_places;

    #[test]
    fn a_degree_needs_twice_its_terms_in_records_and_more_places_than_terms() {
        use super::degree_supported;
        // 3 × 3 net, one pass: a plane (3 terms) but not a quadratic (6 > 9 / 2).
        assert!(degree_supported(1, 9, 9) && !degree_supported(2, 9, 9));
        // Three Z levels of a 3 × 3 net: a quadratic bowl through 9 places.
        assert!(degree_supported(2, 27, 9));
        // 15 records at 4 places: a plane, not a quadratic.
        assert!(degree_supported(1, 15, 4) && !degree_supported(2, 15, 4));
        assert!(degree_supported(0, 1, 1));
    }

    #[test]
    fn repeats_and_near_repeats_are_one_place() {
        // A 3 × 2 net measured twice, the second pass a few counts off, and one node again.
        let mut x = Vec::new();
        let mut y = Vec::new();
        for pass in 0..2 {
            for i in 0..3 {
                for j in 0..2 {
                    x.push(f64::from(i) * 1000.0 + f64::from(pass) * 7.0);
                    y.push(f64::from(j) * 1000.0 - f64::from(pass) * 5.0);
                }
            }
        }
        x.push(1003.0);
        y.push(998.0);
        assert_eq!(distinct_places(&x, &y), 6);
        assert_eq!(distinct_places(&[], &[]), 0);
        assert_eq!(distinct_places(&[5.0, 5.0], &[1.0, 1.0]), 1);
    }
}

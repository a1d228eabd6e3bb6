//! The 2-D polynomial surface of eq. (6) with analytic antiderivatives (eqs. 9, 12).

use serde::{Deserialize, Serialize};

use crate::RegressionError;

/// Highest supported total degree. Degree 10 already has 66 terms; LCC fields need ≤ 5.
pub const MAX_DEGREE: u32 = 10;

/// Number of terms of a total-degree-`degree` polynomial in two variables: (d+1)(d+2)/2.
#[must_use]
pub fn n_terms(degree: u32) -> usize {
    let d = degree as usize;
    (d + 1) * (d + 2) / 2
}

/// Powers `(p_x, p_y)` of the terms in the order of eq. (6) of the paper.
///
/// Degree by degree; within total degree n ≥ 1 the mixed terms x^i y^(n−i) come first with
/// ascending power of x (i = 1 … n−1), then y^n, then x^n:
///
/// `1, y, x, xy, y², x², xy², x²y, y³, x³, xy³, x²y², x³y, y⁴, x⁴, …`
///
/// which reproduces the paper's p_x = (0, 0, 1, 1, 0, 2, …), p_y = (0, 1, 0, 1, 2, 0, …).
///
/// Implements eq. (6): the power vectors p_x, p_y.
pub fn term_powers(degree: u32) -> impl Iterator<Item = (u32, u32)> + Clone {
    (0..=degree).flat_map(|n| {
        let count = if n == 0 { 1 } else { n + 1 };
        (0..count).map(move |t| {
            if n == 0 {
                (0, 0)
            } else if t + 1 < n {
                (t + 1, n - t - 1)
            } else if t + 1 == n {
                (0, n)
            } else {
                (n, 0)
            }
        })
    })
}

/// Index in the eq. (6) order of the term x^px y^py (`px + py` must not exceed the degree).
#[must_use]
pub fn term_index(px: u32, py: u32) -> usize {
    let n = (px + py) as usize;
    let base = n * (n + 1) / 2;
    let within = if n == 0 {
        0
    } else if px >= 1 && py >= 1 {
        px as usize - 1
    } else if px == 0 {
        n - 1
    } else {
        n
    };
    base + within
}

/// `b^n − a^n` computed as `(b − a)·Σ b^k a^(n−1−k)` to avoid cancellation for close a, b.
fn pow_diff(b: f64, a: f64, n: u32) -> f64 {
    if n == 0 {
        return 0.0;
    }
    let mut sum = 0.0;
    let mut bk = 1.0;
    for k in 0..n {
        sum += bk * a.powi((n - 1 - k) as i32);
        bk *= b;
    }
    (b - a) * sum
}

/// Fill `out[0..=degree]` with 1, t, t², …
fn powers(t: f64, degree: u32, out: &mut [f64; MAX_DEGREE as usize + 2]) {
    out[0] = 1.0;
    for k in 1..=(degree as usize + 1).min(MAX_DEGREE as usize + 1) {
        out[k] = out[k - 1] * t;
    }
}

/// [`term_powers`]`(MAX_DEGREE)` as a table, for the per-pixel sums.
const TERM_TABLE: [(u8, u8); (MAX_DEGREE as usize + 1) * (MAX_DEGREE as usize + 2) / 2] = {
    let mut table = [(0u8, 0u8); (MAX_DEGREE as usize + 1) * (MAX_DEGREE as usize + 2) / 2];
    let mut k = 1;
    let mut n = 1;
    while n <= MAX_DEGREE as u8 {
        let mut i = 1;
        while i < n {
            table[k] = (i, n - i);
            k += 1;
            i += 1;
        }
        table[k] = (0, n);
        table[k + 1] = (n, 0);
        k += 2;
        n += 1;
    }
    table
};

/// A total-degree-d polynomial surface f(x, y) in the term order of eq. (6) (see
/// [`term_powers`]).
///
/// The coefficients apply to the *normalised* coordinates u = (x − c_x)/s_x, v = (y − c_y)/s_y
/// (centre and scale stored here; the fit chooses them so that the data span [−1, 1]), which
/// keeps the least-squares problem well conditioned for scanner coordinates of 10⁴–10⁶ counts.
/// [`Polynomial2::coefficients_in_raw_coordinates`] expands them back to powers of x and y.
/// `x`, `y` are in whatever unit the data were (counts for LCC surfaces); the value has the
/// unit of the fitted quantity (nm per count for K̄x, rad for α).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "Polynomial2Repr", into = "Polynomial2Repr")]
pub struct Polynomial2 {
    degree: u32,
    center_x: f64,
    center_y: f64,
    scale_x: f64,
    scale_y: f64,
    coefficients: Vec<f64>,
}

/// Serialised form (validated on the way in).
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Polynomial2Repr {
    /// Total degree.
    degree: u32,
    /// Normalisation centre in x.
    center_x: f64,
    /// Normalisation centre in y.
    center_y: f64,
    /// Normalisation half-range in x.
    scale_x: f64,
    /// Normalisation half-range in y.
    scale_y: f64,
    /// Coefficients of the normalised coordinates, eq. (6) order.
    coefficients: Vec<f64>,
}

impl TryFrom<Polynomial2Repr> for Polynomial2 {
    type Error = RegressionError;
    fn try_from(r: Polynomial2Repr) -> Result<Self, Self::Error> {
        Polynomial2::new(
            r.degree,
            (r.center_x, r.center_y),
            (r.scale_x, r.scale_y),
            r.coefficients,
        )
    }
}

impl From<Polynomial2> for Polynomial2Repr {
    fn from(p: Polynomial2) -> Self {
        Polynomial2Repr {
            degree: p.degree,
            center_x: p.center_x,
            center_y: p.center_y,
            scale_x: p.scale_x,
            scale_y: p.scale_y,
            coefficients: p.coefficients,
        }
    }
}

impl Polynomial2 {
    /// A polynomial from coefficients of the normalised coordinates
    /// u = (x − center.0)/scale.0, v = (y − center.1)/scale.1, in eq. (6) order.
    ///
    /// # Errors
    /// [`RegressionError::DegreeTooHigh`], [`RegressionError::CoefficientCount`],
    /// [`RegressionError::NonFinite`] for a non-finite coefficient or centre,
    /// [`RegressionError::InvalidArgument`] for a scale that is not finite and positive.
    pub fn new(
        degree: u32,
        center: (f64, f64),
        scale: (f64, f64),
        coefficients: Vec<f64>,
    ) -> Result<Self, RegressionError> {
        if degree > MAX_DEGREE {
            return Err(RegressionError::DegreeTooHigh {
                degree,
                max: MAX_DEGREE,
            });
        }
        let expected = n_terms(degree);
        if coefficients.len() != expected {
            return Err(RegressionError::CoefficientCount {
                degree,
                expected,
                got: coefficients.len(),
            });
        }
        if let Some(index) = coefficients.iter().position(|c| !c.is_finite()) {
            return Err(RegressionError::NonFinite {
                field: "coefficient",
                index,
            });
        }
        if !center.0.is_finite() || !center.1.is_finite() {
            return Err(RegressionError::NonFinite {
                field: "center",
                index: usize::from(center.0.is_finite()),
            });
        }
        for s in [scale.0, scale.1] {
            if !(s.is_finite() && s > 0.0) {
                return Err(RegressionError::InvalidArgument(format!(
                    "normalisation scale must be finite and > 0, got {s}"
                )));
            }
        }
        Ok(Self {
            degree,
            center_x: center.0,
            center_y: center.1,
            scale_x: scale.0,
            scale_y: scale.1,
            coefficients,
        })
    }

    /// A polynomial from coefficients of the raw powers x^i y^j (centre 0, scale 1).
    ///
    /// # Errors
    /// As [`Polynomial2::new`].
    pub fn from_raw_coefficients(
        degree: u32,
        coefficients: Vec<f64>,
    ) -> Result<Self, RegressionError> {
        Self::new(degree, (0.0, 0.0), (1.0, 1.0), coefficients)
    }

    /// The constant surface f(x, y) = `value` (degree 0).
    ///
    /// # Errors
    /// [`RegressionError::NonFinite`] if `value` is not finite.
    pub fn constant(value: f64) -> Result<Self, RegressionError> {
        Self::from_raw_coefficients(0, vec![value])
    }

    /// Total degree.
    #[must_use]
    pub fn degree(&self) -> u32 {
        self.degree
    }

    /// Coefficients of the normalised coordinates, eq. (6) order.
    #[must_use]
    pub fn coefficients(&self) -> &[f64] {
        &self.coefficients
    }

    /// Normalisation centre (c_x, c_y).
    #[must_use]
    pub fn center(&self) -> (f64, f64) {
        (self.center_x, self.center_y)
    }

    /// Normalisation scale (s_x, s_y).
    #[must_use]
    pub fn scale(&self) -> (f64, f64) {
        (self.scale_x, self.scale_y)
    }

    fn normalise(&self, x: f64, y: f64) -> (f64, f64) {
        (
            (x - self.center_x) / self.scale_x,
            (y - self.center_y) / self.scale_y,
        )
    }

    /// f(x, y).
    ///
    /// Implements eq. (6): Σ a·x^p_x·y^p_y.
    #[must_use]
    pub fn evaluate(&self, x: f64, y: f64) -> f64 {
        let [value] = Self::evaluate_each([self], x, y);
        value
    }

    /// Whether `other` has this surface's basis (degree and normalisation): their terms are
    /// then the same powers.
    fn same_basis(&self, other: &Self) -> bool {
        self.degree == other.degree
            && self.center_x == other.center_x
            && self.center_y == other.center_y
            && self.scale_x == other.scale_x
            && self.scale_y == other.scale_y
    }

    /// Several surfaces at one point, their basis powers computed once when they share the
    /// degree and normalisation (the fit gives every LCC surface of a plane the same); the one
    /// sum of eq. (6), which [`Self::evaluate`] is for one surface. Surfaces on different bases
    /// are evaluated one by one.
    #[must_use]
    pub fn evaluate_each<const N: usize>(surfaces: [&Self; N], x: f64, y: f64) -> [f64; N] {
        let Some(first) = surfaces.first() else {
            return [0.0; N];
        };
        let shared = surfaces.iter().all(|p| p.same_basis(first));
        if !shared {
            let mut values = [0.0; N];
            for (value, p) in values.iter_mut().zip(surfaces) {
                *value = p.evaluate(x, y);
            }
            return values;
        }
        let (pu, pv) = first.basis_powers(x, y);
        // The usual degrees with the term count known at compile time: the same sums, term
        // by term in the same order, unrolled and without a bounds check per term.
        let fixed = match first.degree {
            0 => Self::term_sums::<N, 1>(&surfaces, &pu, &pv),
            1 => Self::term_sums::<N, 3>(&surfaces, &pu, &pv),
            2 => Self::term_sums::<N, 6>(&surfaces, &pu, &pv),
            3 => Self::term_sums::<N, 10>(&surfaces, &pu, &pv),
            4 => Self::term_sums::<N, 15>(&surfaces, &pu, &pv),
            5 => Self::term_sums::<N, 21>(&surfaces, &pu, &pv),
            _ => None,
        };
        fixed.unwrap_or_else(|| Self::term_sums_any(&surfaces, first.degree, &pu, &pv))
    }

    /// [`Self::evaluate_each`] at every point `(xs[i], ys[i])` into `out[i]` (the shortest of
    /// the three lengths), bit for bit: the check that the surfaces share a basis and the
    /// choice of the unrolled sums are made once for all points.
    pub fn evaluate_each_many<const N: usize>(
        surfaces: [&Self; N],
        xs: &[f64],
        ys: &[f64],
        out: &mut [[f64; N]],
    ) {
        let points = out.iter_mut().zip(xs.iter().zip(ys));
        let Some(first) = surfaces.first() else {
            points.for_each(|(o, _)| *o = [0.0; N]);
            return;
        };
        let shared = surfaces.iter().all(|p| p.same_basis(first));
        let done = shared
            && match first.degree {
                0 => Self::many_fixed::<N, 0, 1>(&surfaces, xs, ys, out),
                1 => Self::many_fixed::<N, 1, 3>(&surfaces, xs, ys, out),
                2 => Self::many_fixed::<N, 2, 6>(&surfaces, xs, ys, out),
                3 => Self::many_fixed::<N, 3, 10>(&surfaces, xs, ys, out),
                4 => Self::many_fixed::<N, 4, 15>(&surfaces, xs, ys, out),
                5 => Self::many_fixed::<N, 5, 21>(&surfaces, xs, ys, out),
                _ => false,
            };
        if !done {
            for (o, (&x, &y)) in out.iter_mut().zip(xs.iter().zip(ys)) {
                *o = Self::evaluate_each(surfaces, x, y);
            }
        }
    }

    /// [`Self::evaluate_each_many`] of surfaces of degree `D` (`T` terms) on one basis: per
    /// point the normalisation, the powers and the sums of [`Self::evaluate_each`], in its
    /// order. False (nothing written) when a surface does not hold exactly `T` coefficients.
    fn many_fixed<const N: usize, const D: usize, const T: usize>(
        surfaces: &[&Self; N],
        xs: &[f64],
        ys: &[f64],
        out: &mut [[f64; N]],
    ) -> bool {
        let mut coefficients = [&[0.0; T]; N];
        for (c, p) in coefficients.iter_mut().zip(surfaces) {
            match <&[f64; T]>::try_from(p.coefficients.as_slice()) {
                Ok(fixed) => *c = fixed,
                Err(_) => return false,
            }
        }
        let first = surfaces[0];
        for (o, (&x, &y)) in out.iter_mut().zip(xs.iter().zip(ys)) {
            let (u, v) = first.normalise(x, y);
            let mut pu = [1.0; MAX_DEGREE as usize + 2];
            let mut pv = [1.0; MAX_DEGREE as usize + 2];
            for k in 1..=D {
                pu[k] = pu[k - 1] * u;
                pv[k] = pv[k - 1] * v;
            }
            let mut values = [-0.0; N];
            for (t, &(i, j)) in TERM_TABLE.iter().take(T).enumerate() {
                let (pi, pj) = (pu[usize::from(i)], pv[usize::from(j)]);
                for (value, c) in values.iter_mut().zip(&coefficients) {
                    *value += c[t] * pi * pj;
                }
            }
            *o = values;
        }
        true
    }

    /// The sums of eq. (6) of `surfaces` (one basis) from the basis powers: one pass over the
    /// terms, the N sums side by side (independent chains of additions), each term added as
    /// `c·pᵢ·pⱼ` to a sum started at −0.
    fn term_sums_any<const N: usize>(
        surfaces: &[&Self; N],
        degree: u32,
        pu: &[f64; MAX_DEGREE as usize + 2],
        pv: &[f64; MAX_DEGREE as usize + 2],
    ) -> [f64; N] {
        let mut values = [-0.0; N];
        for (t, &(i, j)) in TERM_TABLE.iter().take(n_terms(degree)).enumerate() {
            let (pi, pj) = (pu[usize::from(i)], pv[usize::from(j)]);
            for (value, p) in values.iter_mut().zip(surfaces) {
                if let Some(c) = p.coefficients.get(t) {
                    *value += c * pi * pj;
                }
            }
        }
        values
    }

    /// [`Self::term_sums_any`] for `T` terms known at compile time (bit for bit the same
    /// sums); None when a surface does not hold exactly `T` coefficients.
    #[inline]
    fn term_sums<const N: usize, const T: usize>(
        surfaces: &[&Self; N],
        pu: &[f64; MAX_DEGREE as usize + 2],
        pv: &[f64; MAX_DEGREE as usize + 2],
    ) -> Option<[f64; N]> {
        let mut coefficients = [&[0.0; T]; N];
        for (c, p) in coefficients.iter_mut().zip(surfaces) {
            *c = <&[f64; T]>::try_from(p.coefficients.as_slice()).ok()?;
        }
        let mut values = [-0.0; N];
        for (t, &(i, j)) in TERM_TABLE.iter().take(T).enumerate() {
            let (pi, pj) = (pu[usize::from(i)], pv[usize::from(j)]);
            for (value, c) in values.iter_mut().zip(&coefficients) {
                *value += c[t] * pi * pj;
            }
        }
        Some(values)
    }

    /// The powers 1, u, u², … and 1, v, v², … of the normalised coordinates of (x, y).
    #[inline]
    fn basis_powers(
        &self,
        x: f64,
        y: f64,
    ) -> (
        [f64; MAX_DEGREE as usize + 2],
        [f64; MAX_DEGREE as usize + 2],
    ) {
        let (u, v) = self.normalise(x, y);
        let mut pu = [0.0; MAX_DEGREE as usize + 2];
        let mut pv = [0.0; MAX_DEGREE as usize + 2];
        powers(u, self.degree, &mut pu);
        powers(v, self.degree, &mut pv);
        (pu, pv)
    }

    /// The gradient (∂f/∂x, ∂f/∂y) at (x, y).
    #[must_use]
    pub fn gradient(&self, x: f64, y: f64) -> (f64, f64) {
        let (u, v) = self.normalise(x, y);
        let mut pu = [0.0; MAX_DEGREE as usize + 2];
        let mut pv = [0.0; MAX_DEGREE as usize + 2];
        powers(u, self.degree, &mut pu);
        powers(v, self.degree, &mut pv);
        let (mut gx, mut gy) = (0.0, 0.0);
        for ((i, j), c) in term_powers(self.degree).zip(&self.coefficients) {
            if i > 0 {
                gx += c * f64::from(i) * pu[i as usize - 1] * pv[j as usize];
            }
            if j > 0 {
                gy += c * f64::from(j) * pu[i as usize] * pv[j as usize - 1];
            }
        }
        (gx / self.scale_x, gy / self.scale_y)
    }

    /// The surface ∂f/∂x (total degree one less; degree 0 for a constant), on this surface's
    /// normalisation: [`Self::gradient`]'s first component everywhere.
    #[must_use]
    pub fn partial_x(&self) -> Self {
        self.partial(true)
    }

    /// The surface ∂f/∂y (total degree one less; degree 0 for a constant), on this surface's
    /// normalisation: [`Self::gradient`]'s second component everywhere.
    #[must_use]
    pub fn partial_y(&self) -> Self {
        self.partial(false)
    }

    fn partial(&self, along_x: bool) -> Self {
        let degree = self.degree.saturating_sub(1);
        let mut coefficients = vec![0.0; n_terms(degree)];
        if self.degree > 0 {
            let scale = if along_x { self.scale_x } else { self.scale_y };
            for ((i, j), c) in term_powers(self.degree).zip(&self.coefficients) {
                let (power, term) = if along_x {
                    (i, (i.wrapping_sub(1), j))
                } else {
                    (j, (i, j.wrapping_sub(1)))
                };
                if power > 0 {
                    coefficients[term_index(term.0, term.1)] += c * f64::from(power) / scale;
                }
            }
        }
        Self {
            degree,
            center_x: self.center_x,
            center_y: self.center_y,
            scale_x: self.scale_x,
            scale_y: self.scale_y,
            coefficients,
        }
    }

    /// Analytic ∫ f(x, y) dx from `x_a` to `x_b` at fixed `y` (the first integral of eq. 9).
    ///
    /// Implements eq. (12): the analytic x integral of eq. (6).
    #[must_use]
    pub fn integrate_x(&self, x_a: f64, x_b: f64, y: f64) -> f64 {
        let (ua, v) = self.normalise(x_a, y);
        let (ub, _) = self.normalise(x_b, y);
        let mut pv = [0.0; MAX_DEGREE as usize + 2];
        powers(v, self.degree, &mut pv);
        let s: f64 = term_powers(self.degree)
            .zip(&self.coefficients)
            .map(|((i, j), c)| c * pv[j as usize] * pow_diff(ub, ua, i + 1) / f64::from(i + 1))
            .sum();
        s * self.scale_x
    }

    /// Analytic ∫ f(x, y) dy from `y_a` to `y_b` at fixed `x` (the y integrals of eq. 9).
    ///
    /// Implements eq. (12): the analytic y integral of eq. (6).
    #[must_use]
    pub fn integrate_y(&self, x: f64, y_a: f64, y_b: f64) -> f64 {
        let (u, va) = self.normalise(x, y_a);
        let (_, vb) = self.normalise(x, y_b);
        let mut pu = [0.0; MAX_DEGREE as usize + 2];
        powers(u, self.degree, &mut pu);
        let s: f64 = term_powers(self.degree)
            .zip(&self.coefficients)
            .map(|((i, j), c)| c * pu[i as usize] * pow_diff(vb, va, j + 1) / f64::from(j + 1))
            .sum();
        s * self.scale_y
    }

    /// The coefficients of the raw powers x^i y^j in eq. (6) order (binomial expansion of the
    /// normalisation; O(d⁴) operations). Large centres make these badly scaled: prefer
    /// [`Polynomial2::evaluate`] for numbers.
    #[must_use]
    pub fn coefficients_in_raw_coordinates(&self) -> Vec<f64> {
        let d = self.degree;
        let mut raw = vec![0.0; n_terms(d)];
        let binom = |n: u32, k: u32| -> f64 {
            (0..k).fold(1.0, |acc, t| acc * f64::from(n - t) / f64::from(t + 1))
        };
        for ((i, j), c) in term_powers(d).zip(&self.coefficients) {
            let norm = c / (self.scale_x.powi(i as i32) * self.scale_y.powi(j as i32));
            for a in 0..=i {
                let fx = binom(i, a) * (-self.center_x).powi((i - a) as i32);
                for b in 0..=j {
                    let fy = binom(j, b) * (-self.center_y).powi((j - b) as i32);
                    raw[term_index(a, b)] += norm * fx * fy;
                }
            }
        }
        raw
    }

    /// This surface re-expressed with raw-coordinate coefficients (centre 0, scale 1).
    ///
    /// # Errors
    /// [`RegressionError::NonFinite`] if the expansion overflows.
    pub fn to_raw(&self) -> Result<Self, RegressionError> {
        Self::from_raw_coefficients(self.degree, self.coefficients_in_raw_coordinates())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_term_table_is_the_term_order_and_shared_evaluation_is_evaluate_bit_for_bit() {
        let table: Vec<(u32, u32)> = TERM_TABLE
            .iter()
            .map(|&(i, j)| (u32::from(i), u32::from(j)))
            .collect();
        assert_eq!(table, term_powers(MAX_DEGREE).collect::<Vec<_>>());
        for degree in 0..=MAX_DEGREE {
            let surface = |seed: f64| {
                let c = (0..n_terms(degree))
                    .map(|k| ((k as f64 + seed) * 1.7).sin())
                    .collect();
                Polynomial2::new(degree, (3.0, -2.0), (40.0, 25.0), c).unwrap()
            };
            let (a, b, c) = (surface(0.1), surface(1.3), surface(2.9));
            for (x, y) in [(0.0, 0.0), (17.3, -41.0), (-55.5, 12.25), (1e3, 7.0)] {
                let shared = Polynomial2::evaluate_each([&a, &b, &c], x, y);
                let single = [a.evaluate(x, y), b.evaluate(x, y), c.evaluate(x, y)];
                assert_eq!(shared.map(f64::to_bits), single.map(f64::to_bits));
            }
            // Different bases: each on its own.
            let other =
                Polynomial2::new(degree, (0.0, 0.0), (1.0, 1.0), a.coefficients.clone()).unwrap();
            let mixed = Polynomial2::evaluate_each([&a, &other], 2.0, 3.0);
            assert_eq!(mixed, [a.evaluate(2.0, 3.0), other.evaluate(2.0, 3.0)]);
            // Many points at once: each point's evaluate_each, bit for bit.
            let xs = [0.0, 17.3, -55.5, 1e3, 2.5];
            let ys = [0.0, -41.0, 12.25, 7.0, -3.0];
            let mut many = [[0.0; 3]; 5];
            Polynomial2::evaluate_each_many([&a, &b, &c], &xs, &ys, &mut many);
            for ((m, &x), &y) in many.iter().zip(&xs).zip(&ys) {
                let one = Polynomial2::evaluate_each([&a, &b, &c], x, y);
                assert_eq!(m.map(f64::to_bits), one.map(f64::to_bits));
            }
            let mut mixed_many = [[0.0; 2]; 5];
            Polynomial2::evaluate_each_many([&a, &other], &xs, &ys, &mut mixed_many);
            for ((m, &x), &y) in mixed_many.iter().zip(&xs).zip(&ys) {
                assert_eq!(*m, Polynomial2::evaluate_each([&a, &other], x, y));
            }
            // The unrolled sums of the usual degrees are the generic loop's, bit for bit.
            for (x, y) in [(0.0, 0.0), (17.3, -41.0), (-55.5, 12.25), (1e3, 7.0)] {
                let (pu, pv) = a.basis_powers(x, y);
                let generic = Polynomial2::term_sums_any(&[&a, &b, &c], degree, &pu, &pv);
                let shared = Polynomial2::evaluate_each([&a, &b, &c], x, y);
                assert_eq!(shared.map(f64::to_bits), generic.map(f64::to_bits));
            }
        }
    }

    #[test]
    fn term_order_matches_eq6() {
        let t: Vec<_> = term_powers(3).collect();
        assert_eq!(
            t,
            vec![
                (0, 0),
                (0, 1),
                (1, 0),
                (1, 1),
                (0, 2),
                (2, 0),
                (1, 2),
                (2, 1),
                (0, 3),
                (3, 0)
            ]
        );
        for d in 0..=MAX_DEGREE {
            assert_eq!(term_powers(d).count(), n_terms(d));
            for (k, (i, j)) in term_powers(d).enumerate() {
                assert_eq!(term_index(i, j), k);
            }
        }
    }

    /// The unrolled evaluation is eq. (6) term by term in [`term_powers`]' order, bit for bit.
    #[test]
    fn evaluate_is_the_sum_over_the_eq6_terms() {
        for d in 0..=MAX_DEGREE {
            let c: Vec<f64> = (0..n_terms(d))
                .map(|k| (k as f64 * 0.77 + 0.3).sin())
                .collect();
            let p = Polynomial2::new(d, (10.0, -20.0), (300.0, 150.0), c.clone()).unwrap();
            for (x, y) in [
                (0.0f64, 0.0f64),
                (250.0, -100.0),
                (-310.0, 140.0),
                (10.0, 77.0),
            ] {
                let (u, v) = ((x - 10.0) / 300.0, (y + 20.0) / 150.0);
                let want: f64 = term_powers(d)
                    .zip(&c)
                    .map(|((i, j), c)| c * u.powi(i as i32) * v.powi(j as i32))
                    .sum();
                let got = p.evaluate(x, y);
                assert!(
                    (got - want).abs() <= 1e-13 * want.abs().max(1.0),
                    "degree {d}: {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn pow_diff_matches_direct() {
        for n in 0..8 {
            let (b, a) = (1.3_f64, -0.7_f64);
            let direct = b.powi(n as i32) - a.powi(n as i32);
            assert!((pow_diff(b, a, n) - direct).abs() < 1e-12);
        }
    }
}

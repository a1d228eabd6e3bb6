//! The correction 1-form of eq. (5) and its fields.
//!
//! The corrected position is the path integral of the 1-form
//!
//! ```text
//! dx̄ = K̄x dx + K̄yx dy,   dȳ = K̄yy dy,   K̄yx = K̄y sin α,  K̄yy = K̄y cos α
//! ```
//!
//! along the scanner's trajectory (eq. 5). A [`CorrectionField`] gives the three coefficients at
//! any point (in counts) and, where it can, the analytic integrals along the axes (eqs. 9–12).
//! Three fields are provided:
//! - [`SurfaceField`]: K̄x^r, K̄y^r, α^r as stored (eq. 9 literally: the products K̄y^r sin α^r,
//!   K̄y^r cos α^r are formed pointwise). K̄x is integrated analytically; the column integrals are
//!   analytic for planes (the integrals of eq. 10) and by Gauss–Legendre quadrature otherwise.
//! - [`ProductField`]: K̄x^r with the product surfaces K̄yx^r, K̄yy^r of eq. (11); every integral
//!   is analytic (eq. 12).
//! - [`FnField`]: any closure (non-polynomial input), integrated by quadrature.

use spm_regression::{Polynomial2, term_powers};

/// The three coefficients of the correction 1-form at one point, nm per count.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FormCoefficients {
    /// K̄x: nm per count of x motion, along x̄.
    pub kx_nm_per_count: f64,
    /// K̄yx = K̄y sin α: nm along x̄ per count of y motion.
    pub kyx_nm_per_count: f64,
    /// K̄yy = K̄y cos α: nm along ȳ per count of y motion.
    pub kyy_nm_per_count: f64,
}

impl FormCoefficients {
    /// The coefficients of an oblique scanner with lumped K̄x, K̄y (nm/count) and obliquity α
    /// (rad): (K̄x, K̄y sin α, K̄y cos α), the rows of [`spm_hal::NmPerCountMatrix::from_lcc`].
    ///
    /// Implements eq. (3) for the correction, through [`spm_hal::NmPerCountMatrix::from_lcc`]
    /// (the one place the products are formed).
    #[must_use]
    pub fn from_lcc(kx_nm_per_count: f64, ky_nm_per_count: f64, alpha_rad: f64) -> Self {
        let [[kx, kyx], [_, kyy]] = spm_hal::NmPerCountMatrix::from_lcc(
            spm_hal::NmPerCount(kx_nm_per_count),
            spm_hal::NmPerCount(ky_nm_per_count),
            spm_hal::Radians(alpha_rad),
        )
        .rows();
        Self {
            kx_nm_per_count: kx,
            kyx_nm_per_count: kyx,
            kyy_nm_per_count: kyy,
        }
    }

    /// The corrected increment (Δx̄, Δȳ), nm, of a step of (Δx, Δy) counts under these
    /// coefficients: (K̄x·Δx + K̄yx·Δy, K̄yy·Δy).
    ///
    /// Implements eqs. (1) and (5): one summand (the sums and integrals along the trajectory add
    /// these up).
    #[must_use]
    #[inline]
    pub fn increment(self, dx_counts: f64, dy_counts: f64) -> [f64; 2] {
        [
            self.kx_nm_per_count * dx_counts + self.kyx_nm_per_count * dy_counts,
            self.kyy_nm_per_count * dy_counts,
        ]
    }
}

/// The antiderivative along x of K̄x on one line y = const, as a polynomial in the normalised
/// coordinate u = (x − centre)/scale: A(x) = scale · Σ a_k u^(k+1)/(k+1). Evaluated by Horner
/// at every pixel of a line (the fast path of eq. 9/12 for a raster).
#[derive(Debug, Clone, PartialEq)]
pub struct LineAntiderivative {
    center_x_counts: f64,
    inv_scale_x_per_count: f64,
    /// Coefficients of u^1, u^2, … (the constant is 0), already multiplied by scale/(k+1).
    coefficients: Vec<f64>,
}

impl LineAntiderivative {
    /// The antiderivative of `surface(x, y)` in x at the fixed `y_counts`.
    #[must_use]
    pub fn new(surface: &Polynomial2, y_counts: f64) -> Self {
        let (cx, cy) = surface.center();
        let (sx, sy) = surface.scale();
        let v = (y_counts - cy) / sy;
        let d = surface.degree() as usize;
        let mut a = vec![0.0; d + 1];
        for ((i, j), c) in term_powers(surface.degree()).zip(surface.coefficients()) {
            a[i as usize] += c * v.powi(j as i32);
        }
        let coefficients = a
            .iter()
            .enumerate()
            .map(|(k, ak)| ak * sx / (k as f64 + 1.0))
            .collect();
        Self {
            center_x_counts: cx,
            inv_scale_x_per_count: 1.0 / sx,
            coefficients,
        }
    }

    /// `out[i] = shift + A(x0 + h·i)` for every i: one line of a raster. Specialised for the
    /// usual degrees so the Horner chains of neighbouring pixels overlap (vectorised).
    pub fn fill_uniform(&self, x0_counts: f64, step_counts: f64, shift_nm: f64, out: &mut [f64]) {
        let u0 = (x0_counts - self.center_x_counts) * self.inv_scale_x_per_count;
        let du = step_counts * self.inv_scale_x_per_count;
        fn fill<const N: usize>(c: &[f64], u0: f64, du: f64, shift: f64, out: &mut [f64]) {
            let mut k = [0.0; N];
            k.copy_from_slice(&c[..N]);
            for (i, o) in out.iter_mut().enumerate() {
                let u = u0 + du * i as f64;
                let mut acc = k[N - 1];
                for t in (0..N - 1).rev() {
                    acc = acc * u + k[t];
                }
                *o = shift + acc * u;
            }
        }
        let c = &self.coefficients;
        match c.len() {
            1 => fill::<1>(c, u0, du, shift_nm, out),
            2 => fill::<2>(c, u0, du, shift_nm, out),
            3 => fill::<3>(c, u0, du, shift_nm, out),
            4 => fill::<4>(c, u0, du, shift_nm, out),
            5 => fill::<5>(c, u0, du, shift_nm, out),
            6 => fill::<6>(c, u0, du, shift_nm, out),
            _ => {
                for (i, o) in out.iter_mut().enumerate() {
                    let x = x0_counts + step_counts * i as f64;
                    *o = shift_nm + self.evaluate(x);
                }
            }
        }
    }

    /// A(x) (an antiderivative; differences give ∫ K̄x dx), nm.
    #[inline]
    #[must_use]
    pub fn evaluate(&self, x_counts: f64) -> f64 {
        let u = (x_counts - self.center_x_counts) * self.inv_scale_x_per_count;
        let mut acc = 0.0;
        for c in self.coefficients.iter().rev() {
            acc = acc * u + c;
        }
        acc * u
    }
}

/// A field of correction 1-form coefficients over the scanner plane (counts → nm/count).
///
/// Implementors give the pointwise coefficients; the optional methods return analytic
/// integrals along the axes when the field has them (otherwise the caller integrates
/// [`CorrectionField::form`] by quadrature).
pub trait CorrectionField: Sync {
    /// The coefficients (K̄x, K̄yx, K̄yy) at (x, y) counts.
    fn form(&self, x_counts: f64, y_counts: f64) -> FormCoefficients;

    /// [`CorrectionField::form`] at every point (`x_counts[i]`, `y_counts[i]`) into `out[i]`
    /// (the shortest of the three lengths), bit for bit: one call for a line of points, so
    /// that a field of polynomial surfaces makes its per-call choices once.
    fn forms(&self, x_counts: &[f64], y_counts: &[f64], out: &mut [FormCoefficients]) {
        for (o, (&x, &y)) in out.iter_mut().zip(x_counts.iter().zip(y_counts)) {
            *o = self.form(x, y);
        }
    }

    /// ∫ K̄x(x, y) dx from `x_a` to `x_b` at fixed `y`, nm, when analytic.
    fn integral_kx_along_x(&self, _x_a: f64, _x_b: f64, _y: f64) -> Option<f64> {
        None
    }

    /// ∫ K̄yx(x, y) dy from `y_a` to `y_b` at fixed `x`, nm, when analytic.
    fn integral_kyx_along_y(&self, _x: f64, _y_a: f64, _y_b: f64) -> Option<f64> {
        None
    }

    /// ∫ K̄yy(x, y) dy from `y_a` to `y_b` at fixed `x`, nm, when analytic.
    fn integral_kyy_along_y(&self, _x: f64, _y_a: f64, _y_b: f64) -> Option<f64> {
        None
    }

    /// The x-antiderivative of K̄x on the line `y`, when K̄x is a polynomial (raster fast path).
    fn kx_line(&self, _y_counts: f64) -> Option<LineAntiderivative> {
        None
    }
}

impl<T: CorrectionField + ?Sized> CorrectionField for &T {
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        (**self).form(x, y)
    }
    fn forms(&self, x: &[f64], y: &[f64], out: &mut [FormCoefficients]) {
        (**self).forms(x, y, out);
    }
    fn integral_kx_along_x(&self, x_a: f64, x_b: f64, y: f64) -> Option<f64> {
        (**self).integral_kx_along_x(x_a, x_b, y)
    }
    fn integral_kyx_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        (**self).integral_kyx_along_y(x, y_a, y_b)
    }
    fn integral_kyy_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        (**self).integral_kyy_along_y(x, y_a, y_b)
    }
    fn kx_line(&self, y: f64) -> Option<LineAntiderivative> {
        (**self).kx_line(y)
    }
}

/// The regression surfaces K̄x^r, K̄y^r, α^r used as stored: eq. (9) literally.
#[derive(Debug, Clone, PartialEq)]
pub struct SurfaceField {
    /// K̄x^r, nm/count.
    pub kx_nm_per_count: Polynomial2,
    /// K̄y^r, nm/count.
    pub ky_nm_per_count: Polynomial2,
    /// α^r, rad.
    pub alpha_rad: Polynomial2,
}

impl SurfaceField {
    /// Constant coefficients (the lumped 3-coefficient calibration): an affine correction.
    ///
    /// # Errors
    /// [`crate::CorrectionError::Regression`] for a non-finite value.
    pub fn constant(
        kx_nm_per_count: f64,
        ky_nm_per_count: f64,
        alpha_rad: f64,
    ) -> Result<Self, crate::CorrectionError> {
        Ok(Self {
            kx_nm_per_count: Polynomial2::constant(kx_nm_per_count)?,
            ky_nm_per_count: Polynomial2::constant(ky_nm_per_count)?,
            alpha_rad: Polynomial2::constant(alpha_rad)?,
        })
    }

    /// Column integral of K̄y sin α (`sine`) or K̄y cos α along y at fixed x, analytic when
    /// K̄y and α are planes (degree ≤ 1): the integrals of eq. (10).
    fn column_integral(&self, x: f64, y_a: f64, y_b: f64, sine: bool) -> Option<f64> {
        if self.ky_nm_per_count.degree() > 1 || self.alpha_rad.degree() > 1 {
            return None;
        }
        // Along the column both are linear in s = y − y_a: exact from value and slope.
        let b = self.ky_nm_per_count.evaluate(x, y_a);
        let b1 = self.ky_nm_per_count.gradient(x, y_a).1;
        let c = self.alpha_rad.evaluate(x, y_a);
        let c1 = self.alpha_rad.gradient(x, y_a).1;
        let length = y_b - y_a;
        Some(if sine {
            linear_times_sin(b, b1, c, c1, length)
        } else {
            linear_times_cos(b, b1, c, c1, length)
        })
    }
}

impl CorrectionField for SurfaceField {
    /// The summands of eq. (3) taken from the regression surfaces.
    ///
    /// Implements eq. (4).
    #[inline]
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        let [kx, ky, alpha] = Polynomial2::evaluate_each(
            [
                &self.kx_nm_per_count,
                &self.ky_nm_per_count,
                &self.alpha_rad,
            ],
            x,
            y,
        );
        FormCoefficients::from_lcc(kx, ky, alpha)
    }
    fn forms(&self, x: &[f64], y: &[f64], out: &mut [FormCoefficients]) {
        let surfaces = [
            &self.kx_nm_per_count,
            &self.ky_nm_per_count,
            &self.alpha_rad,
        ];
        for_each_block(x, y, out, |x, y, values, out| {
            Polynomial2::evaluate_each_many(surfaces, x, y, values);
            for (o, &[kx, ky, alpha]) in out.iter_mut().zip(values.iter()) {
                *o = FormCoefficients::from_lcc(kx, ky, alpha);
            }
        });
    }
    fn integral_kx_along_x(&self, x_a: f64, x_b: f64, y: f64) -> Option<f64> {
        Some(self.kx_nm_per_count.integrate_x(x_a, x_b, y))
    }
    fn integral_kyx_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        self.column_integral(x, y_a, y_b, true)
    }
    fn integral_kyy_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        self.column_integral(x, y_a, y_b, false)
    }
    fn kx_line(&self, y: f64) -> Option<LineAntiderivative> {
        Some(LineAntiderivative::new(&self.kx_nm_per_count, y))
    }
}

/// K̄x^r with the product surfaces K̄yx^r, K̄yy^r of eq. (11): every integral analytic (eq. 12).
#[derive(Debug, Clone, PartialEq)]
pub struct ProductField {
    /// K̄x^r, nm/count.
    pub kx_nm_per_count: Polynomial2,
    /// K̄yx^r ≈ K̄y sin α, nm/count.
    pub kyx_nm_per_count: Polynomial2,
    /// K̄yy^r ≈ K̄y cos α, nm/count.
    pub kyy_nm_per_count: Polynomial2,
}

impl CorrectionField for ProductField {
    /// K̄y sin α and K̄y cos α from their own regression surfaces.
    ///
    /// Implements eq. (11).
    #[inline]
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        let [kx, kyx, kyy] = Polynomial2::evaluate_each(
            [
                &self.kx_nm_per_count,
                &self.kyx_nm_per_count,
                &self.kyy_nm_per_count,
            ],
            x,
            y,
        );
        FormCoefficients {
            kx_nm_per_count: kx,
            kyx_nm_per_count: kyx,
            kyy_nm_per_count: kyy,
        }
    }
    fn forms(&self, x: &[f64], y: &[f64], out: &mut [FormCoefficients]) {
        let surfaces = [
            &self.kx_nm_per_count,
            &self.kyx_nm_per_count,
            &self.kyy_nm_per_count,
        ];
        for_each_block(x, y, out, |x, y, values, out| {
            Polynomial2::evaluate_each_many(surfaces, x, y, values);
            for (o, &[kx, kyx, kyy]) in out.iter_mut().zip(values.iter()) {
                *o = FormCoefficients {
                    kx_nm_per_count: kx,
                    kyx_nm_per_count: kyx,
                    kyy_nm_per_count: kyy,
                };
            }
        });
    }
    fn integral_kx_along_x(&self, x_a: f64, x_b: f64, y: f64) -> Option<f64> {
        Some(self.kx_nm_per_count.integrate_x(x_a, x_b, y))
    }
    fn integral_kyx_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        Some(self.kyx_nm_per_count.integrate_y(x, y_a, y_b))
    }
    fn integral_kyy_along_y(&self, x: f64, y_a: f64, y_b: f64) -> Option<f64> {
        Some(self.kyy_nm_per_count.integrate_y(x, y_a, y_b))
    }
    fn kx_line(&self, y: f64) -> Option<LineAntiderivative> {
        Some(LineAntiderivative::new(&self.kx_nm_per_count, y))
    }
}

/// Points per block of [`for_each_block`].
const FORM_BLOCK: usize = 256;

/// Runs `f(xs, ys, values, out)` over blocks of at most [`FORM_BLOCK`] points of `out` (the
/// shortest of the three lengths), `values` a scratch of the block's length for the
/// surfaces' sums.
fn for_each_block(
    x: &[f64],
    y: &[f64],
    out: &mut [FormCoefficients],
    mut f: impl FnMut(&[f64], &[f64], &mut [[f64; 3]], &mut [FormCoefficients]),
) {
    let n = out.len().min(x.len()).min(y.len());
    let mut values = [[0.0; 3]; FORM_BLOCK];
    for ((out, x), y) in out[..n]
        .chunks_mut(FORM_BLOCK)
        .zip(x[..n].chunks(FORM_BLOCK))
        .zip(y[..n].chunks(FORM_BLOCK))
    {
        f(x, y, &mut values[..out.len()], out);
    }
}

/// Any field given as a closure `(x_counts, y_counts) -> FormCoefficients`; integrated by
/// quadrature.
pub struct FnField<F>(pub F);

impl<F> CorrectionField for FnField<F>
where
    F: Fn(f64, f64) -> FormCoefficients + Sync,
{
    #[inline]
    fn form(&self, x: f64, y: f64) -> FormCoefficients {
        (self.0)(x, y)
    }
}

impl<F> std::fmt::Debug for FnField<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FnField(..)")
    }
}

/// Below this |c1·L| the closed forms of eq. (10) lose digits to cancellation; the Taylor
/// series (the c1 → 0 limit and its corrections) is used instead.
pub(crate) const SERIES_THRESHOLD: f64 = 0.5;

/// ∫₀ᴸ (b + b1 s)·trig(c + c1 s) ds by the Taylor series of trig about c; `derivs` are the
/// four cyclic derivatives of trig at c.
fn series(b: f64, b1: f64, c1: f64, length: f64, derivs: [f64; 4]) -> f64 {
    let theta = c1 * length;
    let mut r = 1.0; // θ^k / k!
    let mut total = 0.0;
    for k in 0..60usize {
        let kf = k as f64;
        let term = length * r * (b / (kf + 1.0) + b1 * length / (kf + 2.0)) * derivs[k % 4];
        total += term;
        r *= theta / (kf + 1.0);
        if r.abs() < 1e-20 {
            break;
        }
    }
    total
}

/// ∫₀ᴸ (b + b1 s) sin(c + c1 s) ds, closed form (eq. 10) or series for small |c1 L|.
///
/// Implements eq. (10): its sine integral.
#[must_use]
pub fn linear_times_sin(b: f64, b1: f64, c: f64, c1: f64, length: f64) -> f64 {
    if (c1 * length).abs() < SERIES_THRESHOLD {
        let (s, co) = c.sin_cos();
        return series(b, b1, c1, length, [s, co, -s, -co]);
    }
    let half = 0.5 * c1 * length;
    let mid = c + half;
    let end = c + c1 * length;
    (2.0 * half.sin() * (b * mid.sin() + b1 / c1 * mid.cos()) - b1 * length * end.cos()) / c1
}

/// ∫₀ᴸ (b + b1 s) cos(c + c1 s) ds, closed form (eq. 10) or series for small |c1 L|.
///
/// Implements eq. (10): its cosine integral.
#[must_use]
pub fn linear_times_cos(b: f64, b1: f64, c: f64, c1: f64, length: f64) -> f64 {
    if (c1 * length).abs() < SERIES_THRESHOLD {
        let (s, co) = c.sin_cos();
        return series(b, b1, c1, length, [co, -s, -co, s]);
    }
    let half = 0.5 * c1 * length;
    let mid = c + half;
    let end = c + c1 * length;
    (2.0 * half.sin() * (b * mid.cos() - b1 / c1 * mid.sin()) + b1 * length * end.sin()) / c1
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::Quadrature;

    fn check(b: f64, b1: f64, c: f64, c1: f64, length: f64) {
        let q = Quadrature::new(32, length.abs() / 16.0 + 1e-300).unwrap();
        let s = q.integrate(0.0, length, |t| (b + b1 * t) * (c + c1 * t).sin());
        let co = q.integrate(0.0, length, |t| (b + b1 * t) * (c + c1 * t).cos());
        let scale = length.abs() * (b.abs() + (b1 * length).abs());
        assert!(
            (linear_times_sin(b, b1, c, c1, length) - s).abs() <= 1e-12 * scale,
            "sin {b} {b1} {c} {c1} {length}"
        );
        assert!(
            (linear_times_cos(b, b1, c, c1, length) - co).abs() <= 1e-12 * scale,
            "cos {b} {b1} {c} {c1} {length}"
        );
    }

    #[test]
    fn closed_forms_and_series_match_quadrature() {
        check(0.01, 1e-7, 0.02, 1e-6, 5000.0);
        check(0.01, -1e-7, 0.3, 1e-3, 3000.0);
        check(0.01, 1e-7, 0.02, 0.0, 5000.0);
        check(1.0, 0.5, -0.4, 2.0, 1.3);
        check(1.0, 0.5, -0.4, 2.0, -1.3);
        check(1.0, 0.0, 0.0, 0.25, 2.0);
        check(1.0, 0.0, 0.0, 0.2500001, 2.0);
    }

    #[test]
    fn line_antiderivative_matches_integrate_x() {
        let p = Polynomial2::new(
            3,
            (100.0, -50.0),
            (400.0, 300.0),
            vec![
                1.0, 0.2, -0.1, 0.05, 0.03, -0.02, 0.01, 0.004, -0.003, 0.002,
            ],
        )
        .unwrap();
        let y = 123.0;
        let line = LineAntiderivative::new(&p, y);
        for (xa, xb) in [(-300.0, 400.0), (0.0, 1.0), (250.0, -100.0)] {
            let want = p.integrate_x(xa, xb, y);
            let got = line.evaluate(xb) - line.evaluate(xa);
            assert!(
                (want - got).abs() < 1e-10 * (1.0 + want.abs()),
                "{want} {got}"
            );
        }
    }
}

//! Property tests of algebraic identities of [`Polynomial2`] and [`fit`].
#![allow(clippy::unwrap_used)]

use proptest::prelude::*;
use spm_regression::{FitOptions, Observations, Polynomial2, fit, n_terms};

fn polynomial() -> impl Strategy<Value = Polynomial2> {
    (0u32..=4).prop_flat_map(|d| {
        (
            Just(d),
            -1000.0..1000.0_f64,
            -1000.0..1000.0_f64,
            1.0..2000.0_f64,
            1.0..2000.0_f64,
            prop::collection::vec(-1.0..1.0_f64, n_terms(d)),
        )
            .prop_map(|(d, cx, cy, sx, sy, c)| Polynomial2::new(d, (cx, cy), (sx, sy), c).unwrap())
    })
}

/// A bound on |f| over the points `at` (raw coordinates, used as x and as y):
/// Σ|c|·rᵈ with r the largest normalised coordinate (at least 1).
fn magnitude(p: &Polynomial2, at: &[f64]) -> f64 {
    let ((cx, cy), (sx, sy)) = (p.center(), p.scale());
    let r = at
        .iter()
        .flat_map(|v| [((v - cx) / sx).abs(), ((v - cy) / sy).abs()])
        .fold(1.0_f64, f64::max);
    p.coefficients().iter().map(|c| c.abs()).sum::<f64>() * r.powi(p.degree() as i32)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    /// A fit of exact polynomial data reproduces the polynomial.
    #[test]
    fn fit_reproduces_exact_data(p in polynomial(), x0 in -5000.0..5000.0_f64, y0 in -5000.0..5000.0_f64, span in 10.0..5000.0_f64) {
        let d = p.degree();
        let n = d as usize + 3;
        let mut xs = Vec::new();
        let mut ys = Vec::new();
        for j in 0..n {
            for i in 0..n {
                xs.push(x0 + span * i as f64 / (n - 1) as f64);
                ys.push(y0 + 0.7 * span * j as f64 / (n - 1) as f64);
            }
        }
        let zs: Vec<f64> = xs.iter().zip(&ys).map(|(x, y)| p.evaluate(*x, *y)).collect();
        let f = fit(&Observations::new(&xs, &ys, &zs), d, &FitOptions::default()).unwrap();
        let scale = zs.iter().fold(1e-6_f64, |m, z| m.max(z.abs()));
        for ((x, y), z) in xs.iter().zip(&ys).zip(&zs) {
            prop_assert!((f.surface.evaluate(*x, *y) - z).abs() <= 1e-9 * scale);
        }
    }

    /// d/dx_b ∫_{x_a}^{x_b} f dx = f(x_b, y), and likewise in y (central differences).
    #[test]
    fn antiderivative_derivative_consistency(p in polynomial(), xa in -1000.0..1000.0_f64, xb in -1000.0..1000.0_f64, y in -1000.0..1000.0_f64) {
        let h = 1e-3;
        let dx = (p.integrate_x(xa, xb + h, y) - p.integrate_x(xa, xb - h, y)) / (2.0 * h);
        let f = p.evaluate(xb, y);
        let mag = magnitude(&p, &[xa, xb + h, xb - h, y]);
        prop_assert!((dx - f).abs() <= 1e-6 * mag.max(1.0), "{dx} vs {f}");
        let dy = (p.integrate_y(y, xa, xb + h) - p.integrate_y(y, xa, xb - h)) / (2.0 * h);
        let g = p.evaluate(y, xb);
        prop_assert!((dy - g).abs() <= 1e-6 * mag.max(1.0), "{dy} vs {g}");
    }

    /// ∫_a^b + ∫_b^c = ∫_a^c, ∫_a^a = 0, ∫_a^b = −∫_b^a.
    #[test]
    fn antiderivative_additivity(p in polynomial(), a in -1000.0..1000.0_f64, b in -1000.0..1000.0_f64, c in -1000.0..1000.0_f64, y in -1000.0..1000.0_f64) {
        let mag = magnitude(&p, &[a, b, c, y]) * 3000.0;
        let lhs = p.integrate_x(a, b, y) + p.integrate_x(b, c, y);
        prop_assert!((lhs - p.integrate_x(a, c, y)).abs() <= 1e-10 * mag.max(1.0));
        prop_assert_eq!(p.integrate_y(y, a, a), 0.0);
        prop_assert!((p.integrate_y(y, a, b) + p.integrate_y(y, b, a)).abs() <= 1e-10 * mag.max(1.0));
    }

    /// Raw-coordinate coefficients describe the same surface.
    #[test]
    fn raw_coefficients_same_surface(p in polynomial(), x in -1000.0..1000.0_f64, y in -1000.0..1000.0_f64) {
        let raw = p.to_raw().unwrap();
        let mag = (p.coefficients().iter().map(|c| c.abs()).sum::<f64>() * 4.0_f64.powi(p.degree() as i32))
            .max(magnitude(&p, &[x, y]));
        // raw coefficients lose digits when the centre is far from 0 relative to the scale
        let lost = ((p.center().0.abs() / p.scale().0).max(p.center().1.abs() / p.scale().1) + 1.0).powi(p.degree() as i32);
        prop_assert!((raw.evaluate(x, y) - p.evaluate(x, y)).abs() <= 1e-11 * mag.max(1.0) * lost * 8.0_f64.powi(p.degree() as i32));
    }
}

/// The case proptest found on a clean CI machine: a quartic centred 881 scale units away,
/// where the old fixed bound (coordinates within ±8 scale units) was 10⁸ times too tight.
#[test]
fn antiderivative_derivative_far_from_the_centre() {
    let mut c = vec![0.0; n_terms(4)];
    c[14] = 0.189_981_032_325_645_6;
    let p = Polynomial2::new(4, (-881.378_641_553_250_8, 0.0), (1.0, 1.0), c).unwrap();
    let h = 1e-3;
    for (xa, xb, y) in [(0.0, 0.0, 0.0), (-1000.0, 1000.0, 500.0)] {
        let dx = (p.integrate_x(xa, xb + h, y) - p.integrate_x(xa, xb - h, y)) / (2.0 * h);
        let f = p.evaluate(xb, y);
        assert!(
            (dx - f).abs() <= 1e-6 * magnitude(&p, &[xa, xb + h, xb - h, y]),
            "{dx} vs {f}"
        );
        assert!((dx - f).abs() <= 1e-9 * f.abs().max(1.0), "{dx} vs {f}");
    }
}

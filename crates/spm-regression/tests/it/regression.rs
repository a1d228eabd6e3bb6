//! Data-driven tests of the regression crate: exact recovery, hand-computed σ and Δmax,
//! antiderivatives against quadrature, degree selection, typed errors, serde.
#![allow(clippy::unwrap_used)]

use spm_regression::{
    Criterion, Field, FitOptions, Observations, Polynomial2, RegressionError, SelectionOptions,
    delta_max, fit, n_terms, product_values, select_degree, sigma, term_powers,
};

/// Deterministic N(0, 1) generator (xorshift64* + Box–Muller) so the tests need no RNG crate.
struct Gauss(u64);
impl Gauss {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        ((self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn next(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// Points of an `n`×`n` grid over [x0, x0+span]×[y0, y0+span].
fn grid(n: usize, x0: f64, y0: f64, span: f64) -> (Vec<f64>, Vec<f64>) {
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    for j in 0..n {
        for i in 0..n {
            xs.push(x0 + span * i as f64 / (n - 1) as f64);
            ys.push(y0 + span * j as f64 / (n - 1) as f64);
        }
    }
    (xs, ys)
}

mod exact_recovery {
    use super::*;

    /// Fits `truth` (raw coefficients, eq. 6 order) sampled exactly on a grid and checks that
    /// the fit reproduces it at every point and in raw coefficients.
    fn check(degree: u32, raw: &[f64], x0: f64, y0: f64, span: f64) {
        let truth = Polynomial2::from_raw_coefficients(degree, raw.to_vec()).unwrap();
        let (xs, ys) = grid(degree as usize + 3, x0, y0, span);
        let zs: Vec<f64> = xs
            .iter()
            .zip(&ys)
            .map(|(x, y)| truth.evaluate(*x, *y))
            .collect();
        let f = fit(
            &Observations::new(&xs, &ys, &zs),
            degree,
            &FitOptions::default(),
        )
        .unwrap();
        let scale = zs.iter().fold(0.0_f64, |m, z| m.max(z.abs())).max(1e-300);
        for ((x, y), z) in xs.iter().zip(&ys).zip(&zs) {
            assert!(
                (f.surface.evaluate(*x, *y) - z).abs() <= 1e-11 * scale,
                "degree {degree} at ({x}, {y})"
            );
        }
        assert!(f.sigma <= 1e-11 * scale);
        if x0 == 0.0 && y0 == 0.0 {
            for (got, want) in f.surface.coefficients_in_raw_coordinates().iter().zip(raw) {
                let tol = 1e-9 * want.abs().max(1e-12);
                assert!((got - want).abs() <= tol, "raw coefficient {got} vs {want}");
            }
        }
    }

    #[test]
    fn recovers_known_polynomials() {
        check(0, &[0.02], 0.0, 0.0, 1000.0);
        check(1, &[0.0202, 1e-7, -3e-7], 0.0, 0.0, 1000.0);
        check(2, &[1.0, 0.5, -0.25, 0.125, 2.0, -1.0], 0.0, 0.0, 2.0);
        check(
            3,
            &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0],
            0.0,
            0.0,
            1.5,
        );
        // Scanner-like: 60 000-count field far from the origin, LCC-like magnitudes.
        check(
            3,
            &[
                0.02, 1e-8, -2e-8, 1e-13, 3e-13, -1e-13, 1e-18, 2e-18, -1e-18, 5e-19,
            ],
            20_000.0,
            -30_000.0,
            60_000.0,
        );
        check(
            5,
            &(0..n_terms(5))
                .map(|k| 1.0 / (k as f64 + 1.0))
                .collect::<Vec<_>>(),
            0.0,
            0.0,
            3.0,
        );
    }

    #[test]
    fn hand_computed_plane_through_corners() {
        // z = xy on the unit square corners: the least-squares plane is −1/4 + y/2 + x/2,
        // residuals ±1/4, σ = √(4·(1/16)/(4−1)).
        let xs = [0.0, 1.0, 0.0, 1.0];
        let ys = [0.0, 0.0, 1.0, 1.0];
        let zs = [0.0, 0.0, 0.0, 1.0];
        let f = fit(&Observations::new(&xs, &ys, &zs), 1, &FitOptions::default()).unwrap();
        let raw = f.surface.coefficients_in_raw_coordinates();
        for (got, want) in raw.iter().zip([-0.25, 0.5, 0.5]) {
            assert!((got - want).abs() < 1e-14, "{raw:?}");
        }
        assert!((f.sigma - (0.25_f64 / 3.0).sqrt()).abs() < 1e-14);
        assert!((f.weighted_rss - 0.25).abs() < 1e-14);
    }

    #[test]
    fn weights_select_points() {
        // Weight 0 removes the outlier; the remaining points lie on a plane.
        let xs = [0.0, 1.0, 0.0, 1.0, 0.5];
        let ys = [0.0, 0.0, 1.0, 1.0, 0.5];
        let zs = [1.0, 3.0, 2.0, 4.0, 100.0];
        let w = [1.0, 1.0, 1.0, 1.0, 0.0];
        let obs = Observations::new(&xs, &ys, &zs).with_weights(&w);
        let f = fit(&obs, 1, &FitOptions::default()).unwrap();
        assert_eq!(f.n_points, 4);
        assert!((f.surface.evaluate(0.5, 0.5) - 2.5).abs() < 1e-13);
    }
}

mod statistics {
    use super::*;

    fn check_sigma(surface: &Polynomial2, xs: &[f64], ys: &[f64], zs: &[f64], expected: f64) {
        let got = sigma(surface, &Observations::new(xs, ys, zs)).unwrap();
        assert!((got - expected).abs() < 1e-14, "sigma {got} vs {expected}");
    }

    #[test]
    fn sigma_eq14_hand_computed() {
        let one = Polynomial2::constant(1.0).unwrap();
        // residuals 0, 1, 2, 0 → Σ = 5, n − 1 = 3
        check_sigma(
            &one,
            &[0.0, 1.0, 2.0, 3.0],
            &[0.0; 4],
            &[1.0, 2.0, 3.0, 1.0],
            (5.0_f64 / 3.0).sqrt(),
        );
        // f = 1 + 2x − y; residuals 0.1, −0.1 → √(0.02/1)
        let plane = Polynomial2::from_raw_coefficients(1, vec![1.0, -1.0, 2.0]).unwrap();
        check_sigma(
            &plane,
            &[1.0, 2.0],
            &[1.0, 0.0],
            &[2.1, 4.9],
            0.02_f64.sqrt(),
        );
    }

    fn check_delta(
        surface: &Polynomial2,
        field: Field,
        n: (usize, usize),
        reference: (f64, f64),
        expected: (f64, f64, f64),
    ) {
        let d = delta_max(surface, &field, n.0, n.1, reference).unwrap();
        assert!((d.value - expected.0).abs() < 1e-14, "{d:?}");
        assert_eq!((d.at_x, d.at_y), (expected.1, expected.2));
    }

    #[test]
    fn delta_max_eq13_hand_computed() {
        let plane = Polynomial2::from_raw_coefficients(1, vec![1.0, -1.0, 2.0]).unwrap();
        let field = Field {
            x_min: 0.0,
            x_max: 2.0,
            y_min: 0.0,
            y_max: 1.0,
        };
        // f − f(0,0) = 2x − y: maximum 4 at (2, 0)
        check_delta(&plane, field, (3, 2), (0.0, 0.0), (4.0, 2.0, 0.0));
        // reference at the centre: f − 2.5 ranges over [−2.5, 2.5]; first maximum at (2, 0)
        check_delta(&plane, field, (3, 2), (1.0, 0.5), (2.5, 2.0, 0.0));
        // paraboloid x² + y² on [−1, 1]²: 2 at the first corner
        let bowl =
            Polynomial2::from_raw_coefficients(2, vec![0.0, 0.0, 0.0, 0.0, 1.0, 1.0]).unwrap();
        let sq = Field {
            x_min: -1.0,
            x_max: 1.0,
            y_min: -1.0,
            y_max: 1.0,
        };
        check_delta(&bowl, sq, (5, 5), (0.0, 0.0), (2.0, -1.0, -1.0));
        // a horizontal plane has Δmax = 0
        check_delta(
            &Polynomial2::constant(0.02).unwrap(),
            sq,
            (4, 4),
            (0.0, 0.0),
            (0.0, -1.0, -1.0),
        );
    }

    #[test]
    fn product_values_eq11() {
        let (s, c) = product_values(&[2.0, 1.0], &[std::f64::consts::FRAC_PI_6, 0.0]).unwrap();
        assert!((s[0] - 1.0).abs() < 1e-15 && (c[0] - 3.0_f64.sqrt()).abs() < 1e-15);
        assert_eq!((s[1], c[1]), (0.0, 1.0));
    }
}

mod antiderivatives {
    use super::*;

    /// Composite Gauss–Legendre (5 points, 64 panels) of g over [a, b].
    fn quadrature(g: impl Fn(f64) -> f64, a: f64, b: f64) -> f64 {
        const X: [f64; 5] = [
            0.0,
            -0.538_469_310_105_683,
            0.538_469_310_105_683,
            -0.906_179_845_938_664,
            0.906_179_845_938_664,
        ];
        const W: [f64; 5] = [
            0.568_888_888_888_889,
            0.478_628_670_499_366,
            0.478_628_670_499_366,
            0.236_926_885_056_189,
            0.236_926_885_056_189,
        ];
        let panels = 64;
        let h = (b - a) / panels as f64;
        (0..panels)
            .map(|p| {
                let m = a + h * (p as f64 + 0.5);
                X.iter()
                    .zip(W)
                    .map(|(x, w)| w * g(m + 0.5 * h * x))
                    .sum::<f64>()
                    * 0.5
                    * h
            })
            .sum()
    }

    fn check(p: &Polynomial2, x_range: (f64, f64), y_range: (f64, f64), at: (f64, f64)) {
        let ix = p.integrate_x(x_range.0, x_range.1, at.1);
        let qx = quadrature(|x| p.evaluate(x, at.1), x_range.0, x_range.1);
        assert!(
            (ix - qx).abs() <= 1e-12 * qx.abs().max(1.0),
            "x: {ix} vs {qx}"
        );
        let iy = p.integrate_y(at.0, y_range.0, y_range.1);
        let qy = quadrature(|y| p.evaluate(at.0, y), y_range.0, y_range.1);
        assert!(
            (iy - qy).abs() <= 1e-12 * qy.abs().max(1.0),
            "y: {iy} vs {qy}"
        );
    }

    #[test]
    fn antiderivatives_equal_quadrature() {
        let cubic = Polynomial2::new(
            3,
            (500.0, -200.0),
            (800.0, 400.0),
            (1..=10).map(|k| 0.01 * k as f64).collect(),
        )
        .unwrap();
        check(&cubic, (0.0, 1000.0), (-600.0, 300.0), (123.0, 45.0));
        check(&cubic, (1000.0, 0.0), (300.0, -600.0), (-50.0, 250.0));
        check(&cubic, (10.0, 11.0), (5.0, 5.5), (0.0, 0.0));
        let quintic = Polynomial2::from_raw_coefficients(
            5,
            (0..21)
                .map(|k| (-1.0_f64).powi(k) / (k as f64 + 1.0))
                .collect(),
        )
        .unwrap();
        check(&quintic, (-1.0, 1.5), (-2.0, 0.5), (0.3, -0.7));
    }

    #[test]
    fn plane_integral_closed_form() {
        // ∫₀ˣ (a0 + a1 y + a2 x) dx = (a0 + a1 y) x + a2 x²/2 (eq. 10 without the α part)
        let p = Polynomial2::from_raw_coefficients(1, vec![0.02, 1e-6, -2e-6]).unwrap();
        let (x, y) = (300.0, 700.0);
        let want = (0.02 + 1e-6 * y) * x - 2e-6 * x * x / 2.0;
        assert!((p.integrate_x(0.0, x, y) - want).abs() < 1e-13);
    }
}

mod selection {
    use super::*;

    /// Cubic truth on a 15×15 grid over a 4000-count field with Gaussian noise; the criterion
    /// must pick degree 3.
    fn check(criterion: Criterion, seed: u64, noise: f64, expected_degree: u32) {
        let truth = Polynomial2::new(
            3,
            (2000.0, 2000.0),
            (2000.0, 2000.0),
            vec![
                0.02, 4e-4, -3e-4, 2e-4, -3e-4, 2.5e-4, 2e-4, -2e-4, 3e-4, -2.5e-4,
            ],
        )
        .unwrap();
        let (xs, ys) = grid(15, 0.0, 0.0, 4000.0);
        let mut g = Gauss(seed);
        let zs: Vec<f64> = xs
            .iter()
            .zip(&ys)
            .map(|(x, y)| truth.evaluate(*x, *y) + noise * g.next())
            .collect();
        let options = SelectionOptions {
            max_degree: 6,
            criterion,
            ..SelectionOptions::default()
        };
        let sel = select_degree(&Observations::new(&xs, &ys, &zs), &options).unwrap();
        assert_eq!(
            sel.degree(),
            expected_degree,
            "{criterion:?} seed {seed}: {:?}",
            sel.scores
        );
        assert!(sel.scores.len() >= 4);
    }

    #[test]
    fn bic_picks_true_degree() {
        for seed in 1..=5 {
            check(Criterion::Bic, seed, 2e-5, 3);
        }
    }

    #[test]
    fn cross_validation_picks_true_degree() {
        for seed in 1..=5 {
            check(Criterion::CrossValidation { folds: 5 }, seed, 2e-5, 3);
        }
    }

    #[test]
    fn exact_data_pick_lowest_exact_degree() {
        check(Criterion::Bic, 1, 0.0, 3);
    }
}

mod errors {
    use super::*;

    fn check(
        xs: &[f64],
        ys: &[f64],
        zs: &[f64],
        degree: u32,
        expected: fn(&RegressionError) -> bool,
    ) {
        let err = fit(
            &Observations::new(xs, ys, zs),
            degree,
            &FitOptions::default(),
        )
        .unwrap_err();
        assert!(expected(&err), "unexpected {err:?}");
        assert!(!err.to_string().is_empty());
    }

    #[test]
    fn typed_errors_not_nan() {
        check(&[0.0, 1.0], &[0.0, 1.0], &[1.0, 2.0], 1, |e| {
            matches!(
                e,
                RegressionError::TooFewPoints {
                    needed: 3,
                    got: 2,
                    ..
                }
            )
        });
        check(&[], &[], &[], 0, |e| {
            matches!(e, RegressionError::TooFewPoints { .. })
        });
        // collinear points: a plane is undetermined
        check(
            &[0.0, 1.0, 2.0, 3.0],
            &[0.0, 1.0, 2.0, 3.0],
            &[1.0, 2.0, 3.0, 4.0],
            1,
            |e| matches!(e, RegressionError::IllConditioned { .. }),
        );
        // all points on one x: degree 2 needs x variation
        check(
            &[5.0; 9],
            &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0],
            &[1.0; 9],
            2,
            |e| matches!(e, RegressionError::IllConditioned { .. }),
        );
        check(&[0.0, f64::NAN], &[0.0, 1.0], &[1.0, 2.0], 0, |e| {
            matches!(
                e,
                RegressionError::NonFinite {
                    field: "x",
                    index: 1
                }
            )
        });
        check(&[0.0, 1.0], &[0.0, 1.0], &[1.0, f64::INFINITY], 0, |e| {
            matches!(
                e,
                RegressionError::NonFinite {
                    field: "value",
                    index: 1
                }
            )
        });
        check(&[0.0], &[0.0, 1.0], &[1.0], 0, |e| {
            matches!(e, RegressionError::LengthMismatch { field: "y", .. })
        });
        check(&[0.0; 100], &[0.0; 100], &[0.0; 100], 11, |e| {
            matches!(e, RegressionError::DegreeTooHigh { .. })
        });
        let w = [1.0, -1.0];
        let err = fit(
            &Observations::new(&[0.0, 1.0], &[0.0, 1.0], &[1.0, 1.0]).with_weights(&w),
            0,
            &FitOptions::default(),
        )
        .unwrap_err();
        assert!(matches!(
            err,
            RegressionError::InvalidWeight { index: 1, .. }
        ));
        assert!(matches!(
            Polynomial2::from_raw_coefficients(2, vec![1.0; 5]),
            Err(RegressionError::CoefficientCount {
                expected: 6,
                got: 5,
                ..
            })
        ));
        assert!(matches!(
            sigma(
                &Polynomial2::constant(1.0).unwrap(),
                &Observations::new(&[0.0], &[0.0], &[1.0])
            ),
            Err(RegressionError::TooFewPoints { .. })
        ));
    }

    #[test]
    fn ill_conditioned_clustered_points() {
        // A 4×4 grid of points a few ppm apart fitted with degree 3 around a far point: the
        // normalisation rescales it; but degree 3 on points spanning only 2 distinct x values
        // is singular.
        let xs: Vec<f64> = (0..16)
            .map(|i| if i % 2 == 0 { 0.0 } else { 1.0 })
            .collect();
        let ys: Vec<f64> = (0..16).map(|i| i as f64).collect();
        let zs = vec![1.0; 16];
        let err = fit(&Observations::new(&xs, &ys, &zs), 3, &FitOptions::default()).unwrap_err();
        assert!(
            matches!(err, RegressionError::IllConditioned { degree: 3, .. }),
            "{err:?}"
        );
    }
}

mod serde_form {
    use super::*;

    #[test]
    fn json_round_trip_and_validation() {
        let p = Polynomial2::new(
            2,
            (1.0, 2.0),
            (3.0, 4.0),
            vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        )
        .unwrap();
        let text = serde_json::to_string(&p).unwrap();
        assert!(text.contains("\"coefficients\""));
        let back: Polynomial2 = serde_json::from_str(&text).unwrap();
        assert_eq!(back, p);
        let bad = r#"{"degree":2,"center_x":0,"center_y":0,"scale_x":1,"scale_y":1,"coefficients":[1,2]}"#;
        assert!(serde_json::from_str::<Polynomial2>(bad).is_err());
        let bad_scale =
            r#"{"degree":0,"center_x":0,"center_y":0,"scale_x":0,"scale_y":1,"coefficients":[1]}"#;
        assert!(serde_json::from_str::<Polynomial2>(bad_scale).is_err());
        assert_eq!(
            term_powers(1).collect::<Vec<_>>(),
            vec![(0, 0), (0, 1), (1, 0)]
        );
    }
}

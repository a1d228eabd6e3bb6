//! Property tests of the correction: identity, affine, eq. 10 = eq. 9, eq. 12's bound,
//! direct versus counter (circulation), resampling.
#![allow(clippy::unwrap_used)]

use proptest::prelude::*;
use spm_correction::closed_form::{Plane, eq10, eq12};
use spm_correction::*;
use spm_hal::{CountPoint, Counts, Nanometres, NmPoint, ScanDirection};
use spm_regression::{Observations, Polynomial2, fit, n_terms, term_powers};

/// The scanner field of the tests: [0, 20000] counts in x and y.
const CENTER: f64 = 10_000.0;
const SCALE: f64 = 10_000.0;

fn poly(degree: u32, coefficients: Vec<f64>) -> Polynomial2 {
    Polynomial2::new(degree, (CENTER, CENTER), (SCALE, SCALE), coefficients).unwrap()
}

/// A surface `base` plus small terms up to `degree` (relative size `wiggle`).
fn surface(base: f64, degree: u32, wiggle: &[f64]) -> Polynomial2 {
    let n = n_terms(degree);
    let mut c = vec![0.0; n];
    c[0] = base;
    for k in 1..n {
        c[k] = base * wiggle[k % wiggle.len()];
    }
    poly(degree, c)
}

/// ∂p/∂x as a polynomial of degree d − 1 (same normalisation).
fn derive(p: &Polynomial2, along_x: bool) -> Polynomial2 {
    let d = p.degree();
    if d == 0 {
        return poly(0, vec![0.0]);
    }
    let mut c = vec![0.0; n_terms(d - 1)];
    let terms: Vec<_> = term_powers(d - 1).collect();
    for ((i, j), a) in term_powers(d).zip(p.coefficients()) {
        let (ni, nj, factor) = if along_x {
            if i == 0 {
                continue;
            }
            (i - 1, j, f64::from(i))
        } else {
            if j == 0 {
                continue;
            }
            (i, j - 1, f64::from(j))
        };
        let k = terms.iter().position(|&t| t == (ni, nj)).unwrap();
        c[k] += a * factor / SCALE;
    }
    poly(d - 1, c)
}

fn geometry(x0: f64, y0: f64, step: f64, columns: usize, rows: usize) -> RasterGeometry {
    RasterGeometry::new(CountPoint::from_counts(x0, y0), Counts(step), columns, rows).unwrap()
}

fn map(
    field: &dyn CorrectionField,
    g: &RasterGeometry,
    direction: ScanDirection,
    integration: &Integration,
) -> CoordinateMap {
    correct_raster(field, g, direction, integration, Parallelism::Sequential).unwrap()
}

/// Every pixel of `map` against `expected(column, row)` within `tolerance_nm`.
fn check(map: &CoordinateMap, expected: impl Fn(usize, usize) -> (f64, f64), tolerance_nm: f64) {
    for j in 0..map.rows() {
        for i in 0..map.columns() {
            let p = map.point(i, j).unwrap();
            let (ex, ey) = expected(i, j);
            assert!(
                (p.x.value() - ex).abs() <= tolerance_nm
                    && (p.y.value() - ey).abs() <= tolerance_nm,
                "pixel ({i}, {j}): got ({}, {}), expected ({ex}, {ey}), tolerance {tolerance_nm}",
                p.x.value(),
                p.y.value()
            );
        }
    }
}

/// The curl components (∂K̄yx/∂x − ∂K̄x/∂y, ∂K̄yy/∂x) at (x, y).
type Curl<'a> = dyn Fn(f64, f64) -> (f64, f64) + 'a;

fn all_integrations() -> Vec<Integration> {
    vec![
        Integration::Analytic(Quadrature::standard()),
        Integration::Quadrature(Quadrature::new(6, 100.0).unwrap()),
        Integration::Sums,
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// K̄x = K̄y = 1, α = 0 ⇒ the corrected coordinates are the commanded ones.
    #[test]
    fn unit_coefficients_give_the_identity(
        x0 in 0.0f64..10_000.0, y0 in 0.0f64..10_000.0, step in 1u32..40,
        columns in 2usize..12, rows in 2usize..12, route in 0usize..2,
    ) {
        let plane = PlaneSurfaces::constant(0.0, 1.0, 1.0, 0.0).unwrap();
        let field = plane.field(if route == 0 { Route::Exact } else { Route::Products });
        let h = f64::from(step);
        let g = geometry(x0.round(), y0.round(), h, columns, rows);
        for integration in all_integrations() {
            for direction in [ScanDirection::Direct, ScanDirection::Counter] {
                let m = map(&field, &g, direction, &integration);
                check(&m, |i, j| (i as f64 * h, j as f64 * h), 1e-9 * h * 20.0);
            }
        }
        let path: Vec<_> = (0..20)
            .map(|k| CountPoint::from_counts(x0 + 37.0 * f64::from(k % 7), y0 + 11.0 * f64::from(k)))
            .collect();
        let got = correct_polyline(&field, &path, &Quadrature::standard()).unwrap();
        for (p, q) in path.iter().zip(&got) {
            prop_assert!((q.x.value() - (p.x.value() - x0)).abs() < 1e-9);
            prop_assert!((q.y.value() - (p.y.value() - y0)).abs() < 1e-9);
        }
    }

    /// Constant coefficients ⇒ the affine map x̄ = K̄x·x + K̄y sin α·y, ȳ = K̄y cos α·y, on every
    /// route, raster direction and trajectory.
    #[test]
    fn constant_coefficients_give_the_affine_map(
        kx in 0.005f64..0.05, ky in 0.005f64..0.05, alpha in -0.2f64..0.2,
        x0 in 0.0f64..10_000.0, y0 in 0.0f64..10_000.0, step in 1u32..30,
        columns in 2usize..10, rows in 2usize..10,
        walk in proptest::collection::vec((-1i32..=1, -1i32..=1), 1..200),
    ) {
        let plane = PlaneSurfaces::constant(0.0, kx, ky, alpha).unwrap();
        let affine = |dx: f64, dy: f64| (kx * dx + ky * alpha.sin() * dy, ky * alpha.cos() * dy);
        let h = f64::from(step);
        let g = geometry(x0.round(), y0.round(), h, columns, rows);
        for route in [Route::Exact, Route::Products] {
            let field = plane.field(route);
            for integration in all_integrations() {
                for direction in [ScanDirection::Direct, ScanDirection::Counter] {
                    let m = map(&field, &g, direction, &integration);
                    check(&m, |i, j| affine(i as f64 * h, j as f64 * h), 1e-11);
                }
            }
            // Unit steps (eq. 5) along a random walk.
            let mut path = vec![CountPoint::from_counts(x0.round(), y0.round())];
            for (dx, dy) in &walk {
                let last = *path.last().unwrap();
                path.push(CountPoint::from_counts(last.x.value() + f64::from(*dx), last.y.value() + f64::from(*dy)));
            }
            let got = correct_unit_steps(&field, &path).unwrap();
            for (p, q) in path.iter().zip(&got) {
                let (ex, ey) = affine(p.x.value() - path[0].x.value(), p.y.value() - path[0].y.value());
                prop_assert!((q.x.value() - ex).abs() < 1e-11 && (q.y.value() - ey).abs() < 1e-11);
            }
        }
    }

    /// Eq. (10), written as in the paper, equals eq. (9) by Gauss–Legendre quadrature to 1e-9
    /// relative, and the general raster route (planes, analytic column integrals) agrees.
    #[test]
    fn eq10_equals_eq9_by_quadrature(
        a in (0.005f64..0.05, -2e-7f64..2e-7, -2e-7f64..2e-7),
        b in (0.005f64..0.05, -2e-7f64..2e-7, -2e-7f64..2e-7),
        c in (-0.3f64..0.3, -1e-4f64..1e-4, -1e-4f64..1e-4),
        x0 in 0.0f64..10_000.0, y0 in 0.0f64..10_000.0,
        x in 0.0f64..10_000.0, y in 0.0f64..10_000.0,
    ) {
        let (pa, pb, pc) = (
            Plane { k0: a.0, k_y: a.1, k_x: a.2 },
            Plane { k0: b.0, k_y: b.1, k_x: b.2 },
            Plane { k0: c.0, k_y: c.1, k_x: c.2 },
        );
        let f = |p: Plane, x: f64, y: f64| p.k0 + p.k_y * y + p.k_x * x;
        let q = Quadrature::new(32, 500.0).unwrap();
        let along = q.integrate(x0, x0 + x, |s| f(pa, s, y0 + y));
        let up_x = q.integrate(y0, y0 + y, |t| f(pb, x0, t) * f(pc, x0, t).sin());
        let up_y = q.integrate(y0, y0 + y, |t| f(pb, x0, t) * f(pc, x0, t).cos());
        let (ex, ey) = (along + up_x, up_y);
        let (gx, gy) = eq10(pa, pb, pc, x0, y0, x, y);
        let scale = along.abs() + up_x.abs() + up_y.abs() + 1e-300;
        prop_assert!((gx - ex).abs() <= 1e-9 * scale, "x̄: eq10 {gx} eq9 {ex}");
        prop_assert!((gy - ey).abs() <= 1e-9 * scale, "ȳ: eq10 {gy} eq9 {ey}");
        // The general route on a raster that ends at (x, y).
        let field = SurfaceField {
            kx_nm_per_count: pa.to_polynomial().unwrap(),
            ky_nm_per_count: pb.to_polynomial().unwrap(),
            alpha_rad: pc.to_polynomial().unwrap(),
        };
        let g = geometry(x0, y0, (x.max(y) / 4.0).max(1e-3), 5, 5);
        let m = map(&field, &g, ScanDirection::Direct, &Integration::default());
        for j in 0..5 {
            for i in 0..5 {
                let (dx, dy) = (g.pixel_step.value() * i as f64, g.pixel_step.value() * j as f64);
                let (ex, ey) = eq10(pa, pb, pc, x0, y0, dx, dy);
                let p = m.point(i, j).unwrap();
                prop_assert!((p.x.value() - ex).abs() <= 1e-9 * scale.max(1e-12));
                prop_assert!((p.y.value() - ey).abs() <= 1e-9 * scale.max(1e-12));
            }
        }
    }

    /// Eq. (12) with product surfaces fitted to K̄y^r sin α^r, K̄y^r cos α^r differs from eq. (9)
    /// only in the line-start integrals, so
    ///   |x̄₁₂ − x̄₉|(x, y) ≤ |y − y₀| · max_column |K̄yx^r − K̄y^r sin α^r|,
    ///   |ȳ₁₂ − ȳ₉|(y)    ≤ |y − y₀| · max_column |K̄yy^r − K̄y^r cos α^r|.
    /// Also: eq. (12) as printed equals the general (normalised) route.
    #[test]
    fn eq12_is_within_its_bound_of_eq9(
        ky_w in proptest::collection::vec(-0.05f64..0.05, 6),
        alpha_w in proptest::collection::vec(-0.2f64..0.2, 6),
        kx_w in proptest::collection::vec(-0.05f64..0.05, 6),
        ky_degree in 0u32..3, alpha_degree in 0u32..3, product_degree in 1u32..4,
        x0 in 0.0f64..8_000.0, y0 in 0.0f64..8_000.0,
    ) {
        let kx = surface(0.02, 2, &kx_w);
        let ky = surface(0.02, ky_degree, &ky_w);
        let mut alpha = surface(0.1, alpha_degree, &alpha_w);
        if alpha_degree == 0 { alpha = poly(0, vec![0.05]); }
        // Fit the product surfaces of eq. (11) on a 21×21 net over the field.
        let (mut xs, mut ys) = (Vec::new(), Vec::new());
        for a in 0..21 { for b in 0..21 { xs.push(1000.0 * f64::from(a)); ys.push(1000.0 * f64::from(b)); } }
        let ky_v: Vec<f64> = xs.iter().zip(&ys).map(|(&x, &y)| ky.evaluate(x, y)).collect();
        let al_v: Vec<f64> = xs.iter().zip(&ys).map(|(&x, &y)| alpha.evaluate(x, y)).collect();
        let (s, co) = spm_regression::product_values(&ky_v, &al_v).unwrap();
        let e = fit(&Observations::new(&xs, &ys, &s), product_degree, &Default::default()).unwrap().surface;
        let f = fit(&Observations::new(&xs, &ys, &co), product_degree, &Default::default()).unwrap().surface;
        let exact = SurfaceField { kx_nm_per_count: kx.clone(), ky_nm_per_count: ky.clone(), alpha_rad: alpha.clone() };
        let products = ProductField { kx_nm_per_count: kx.clone(), kyx_nm_per_count: e.clone(), kyy_nm_per_count: f.clone() };
        let g = geometry(x0, y0, 1000.0, 12, 12);
        let m9 = map(&exact, &g, ScanDirection::Direct, &Integration::Quadrature(Quadrature::new(16, 250.0).unwrap()));
        let m12 = map(&products, &g, ScanDirection::Direct, &Integration::default());
        // max misfit along the line-start column (dense sampling + 1e-3 relative slack).
        let (mut ex_max, mut ey_max) = (0.0f64, 0.0f64);
        for k in 0..=4000 {
            let y = y0 + 11_000.0 * f64::from(k) / 4000.0;
            let (kyv, al) = (ky.evaluate(x0, y), alpha.evaluate(x0, y));
            ex_max = ex_max.max((e.evaluate(x0, y) - kyv * al.sin()).abs());
            ey_max = ey_max.max((f.evaluate(x0, y) - kyv * al.cos()).abs());
        }
        for j in 0..12 {
            let dy = 1000.0 * j as f64;
            for i in 0..12 {
                let (p9, p12) = (m9.point(i, j).unwrap(), m12.point(i, j).unwrap());
                let tiny = 1e-10 * (1.0 + p9.x.value().abs() + p9.y.value().abs());
                prop_assert!((p12.x.value() - p9.x.value()).abs() <= dy * ex_max * 1.001 + tiny);
                prop_assert!((p12.y.value() - p9.y.value()).abs() <= dy * ey_max * 1.001 + tiny);
                let (lx, ly) = eq12(&kx, &e, &f, x0, y0, 1000.0 * i as f64, dy);
                let scale = 1.0 + p12.x.value().abs() + p12.y.value().abs();
                prop_assert!((lx - p12.x.value()).abs() <= 1e-9 * scale, "eq12 literal {lx} vs {}", p12.x.value());
                prop_assert!((ly - p12.y.value()).abs() <= 1e-9 * scale);
            }
        }
    }

    /// When (K̄x, K̄yx) = ∇Φ and K̄yy = g(y) the 1-form is exact: direct and counter corrections
    /// agree at every pixel (analytic polynomial route and quadrature of a closure).
    #[test]
    fn direct_and_counter_agree_on_an_exact_form(
        phi_w in proptest::collection::vec(-0.05f64..0.05, 10),
        g_w in proptest::collection::vec(-0.05f64..0.05, 3),
        x0 in 0.0f64..8_000.0, y0 in 0.0f64..8_000.0,
        step in 50.0f64..900.0, columns in 2usize..14, rows in 2usize..14,
    ) {
        // Φ = 0.02·x·SCALE·(u + …) in normalised terms: degree 3 with a dominant u-term.
        let mut c = vec![0.0; n_terms(3)];
        for (k, w) in c.iter_mut().enumerate() { *w = 0.02 * SCALE * phi_w[k % phi_w.len()]; }
        c[2] = 0.02 * SCALE; // x term: K̄x ≈ 0.02 nm/count
        c[1] = 0.002 * SCALE; // y term: K̄yx ≈ 0.002
        let phi = poly(3, c);
        let g_poly = poly(2, vec![0.02, 0.02 * g_w[0], 0.0, 0.0, 0.02 * g_w[1], 0.0]);
        let field = ProductField {
            kx_nm_per_count: derive(&phi, true),
            kyx_nm_per_count: derive(&phi, false),
            kyy_nm_per_count: g_poly,
        };
        let g = geometry(x0, y0, step, columns, rows);
        let d = map(&field, &g, ScanDirection::Direct, &Integration::default());
        let cm = map(&field, &g, ScanDirection::Counter, &Integration::default());
        let scale = 0.03 * step * (columns + rows) as f64;
        check(&cm, |i, j| { let p = d.point(i, j).unwrap(); (p.x.value(), p.y.value()) }, 1e-9 * scale);
        // A non-polynomial exact form by quadrature: Φ = 0.02x + 300 sin(x/3000) cos(y/4000).
        let closure = FnField(|x: f64, y: f64| FormCoefficients {
            kx_nm_per_count: 0.02 + 0.1 * (x / 3000.0).cos() * (y / 4000.0).cos(),
            kyx_nm_per_count: -0.075 * (x / 3000.0).sin() * (y / 4000.0).sin(),
            kyy_nm_per_count: 0.02 + 0.001 * (y / 5000.0).sin(),
        });
        let q = Integration::Quadrature(Quadrature::new(10, 200.0).unwrap());
        let d = map(&closure, &g, ScanDirection::Direct, &q);
        let cm = map(&closure, &g, ScanDirection::Counter, &q);
        let scale = 0.2 * step * (columns + rows) as f64;
        check(&cm, |i, j| { let p = d.point(i, j).unwrap(); (p.x.value(), p.y.value()) }, 1e-9 * scale);
    }

    /// Otherwise they differ by the circulation of the 1-form around the rectangle
    /// [x₀, X] × [y_j, Y] (clockwise): −∬ (∂K̄yx/∂x − ∂K̄x/∂y) dA for x̄, −∬ ∂K̄yy/∂x dA for ȳ,
    /// computed here independently by 2-D Gauss–Legendre over the curl (Green's theorem).
    #[test]
    fn direct_and_counter_differ_by_the_circulation(
        kx_w in proptest::collection::vec(-0.05f64..0.05, 6),
        ky_w in proptest::collection::vec(-0.05f64..0.05, 6),
        alpha_w in proptest::collection::vec(-0.3f64..0.3, 6),
        x0 in 0.0f64..8_000.0, y0 in 0.0f64..8_000.0,
        step in 100.0f64..900.0, columns in 2usize..10, rows in 2usize..10,
    ) {
        let kx = surface(0.02, 2, &kx_w);
        let ky = surface(0.02, 2, &ky_w);
        let alpha = surface(0.1, 2, &alpha_w);
        let exact = SurfaceField { kx_nm_per_count: kx.clone(), ky_nm_per_count: ky.clone(), alpha_rad: alpha.clone() };
        let products = ProductField {
            kx_nm_per_count: kx.clone(),
            kyx_nm_per_count: surface(0.002, 2, &alpha_w),
            kyy_nm_per_count: surface(0.02, 3, &ky_w),
        };
        let g = geometry(x0, y0, step, columns, rows);
        let far = g.far_corner();
        let q2 = Quadrature::new(12, 1e9).unwrap();
        // curl of (P, Q) = (K̄x, K̄yx) and ∂K̄yy/∂x, per field.
        let curl_exact = |x: f64, y: f64| {
            let (k, a) = (ky.evaluate(x, y), alpha.evaluate(x, y));
            let (kgx, _) = ky.gradient(x, y);
            let (agx, _) = alpha.gradient(x, y);
            let (_, pgy) = kx.gradient(x, y);
            ((kgx * a.sin() + k * a.cos() * agx) - pgy, kgx * a.cos() - k * a.sin() * agx)
        };
        let curl_products = |x: f64, y: f64| {
            let (_, pgy) = products.kx_nm_per_count.gradient(x, y);
            let (qgx, _) = products.kyx_nm_per_count.gradient(x, y);
            let (rgx, _) = products.kyy_nm_per_count.gradient(x, y);
            (qgx - pgy, rgx)
        };
        let curls: [(&dyn CorrectionField, &Curl<'_>); 2] =
            [(&exact, &curl_exact), (&products, &curl_products)];
        for (field, curl) in curls {
            let d = map(field, &g, ScanDirection::Direct, &Integration::default());
            let cm = map(field, &g, ScanDirection::Counter, &Integration::default());
            for j in 0..rows {
                let yj = g.y_counts(j as f64);
                let cx = q2.integrate(x0, far.x.value(), |x| q2.integrate(yj, far.y.value(), |y| curl(x, y).0));
                let cy = q2.integrate(x0, far.x.value(), |x| q2.integrate(yj, far.y.value(), |y| curl(x, y).1));
                let scale = 0.05 * step * (columns + rows) as f64;
                for i in 0..columns {
                    let (pd, pc) = (d.point(i, j).unwrap(), cm.point(i, j).unwrap());
                    prop_assert!(((pc.x.value() - pd.x.value()) - (-cx)).abs() <= 1e-9 * scale,
                        "x̄ difference {} predicted {}", pc.x.value() - pd.x.value(), -cx);
                    prop_assert!(((pc.y.value() - pd.y.value()) - (-cy)).abs() <= 1e-9 * scale);
                }
            }
        }
    }

    /// Resampling through an identity map reproduces the image (both kernels, both inverse
    /// mappings), and an affine map reproduces a linear function of the corrected position.
    #[test]
    fn resampling_an_identity_map_reproduces_the_image(
        values in proptest::collection::vec(-100.0f64..100.0, 12 * 9),
        step in 1.0f64..50.0, x0 in 0.0f64..1e4, y0 in 0.0f64..1e4,
        kx in 0.01f64..0.03, ky in 0.01f64..0.03, alpha in -0.2f64..0.2,
        lin in (-3.0f64..3.0, -3.0f64..3.0, -3.0f64..3.0),
    ) {
        let (nx, ny) = (12, 9);
        let g = geometry(x0, y0, step, nx, ny);
        let unit = PlaneSurfaces::constant(0.0, 1.0, 1.0, 0.0).unwrap().field(Route::Exact);
        let m = map(&unit, &g, ScanDirection::Direct, &Integration::default());
        let grid = OutputGrid::new(NmPoint::from_nm(0.0, 0.0), Nanometres(step), nx, ny).unwrap();
        let general = drift_corrected_map(&m, &vec![0.0; nx * ny], spm_hal::NmVelocity::default(), spm_hal::Seconds(0.0)).unwrap();
        for interpolation in [Interpolation::Bilinear, Interpolation::CatmullRom] {
            for mm in [&m, &general] {
                let out = resample(&values, mm, &grid, interpolation, Parallelism::Sequential).unwrap();
                for (k, (a, b)) in out.iter().zip(&values).enumerate() {
                    prop_assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{interpolation:?} pixel {k}: {a} vs {b}");
                }
            }
        }
        // Affine map, image = linear function of the corrected position.
        let field = PlaneSurfaces::constant(0.0, kx, ky, alpha).unwrap().field(Route::Products);
        let m = map(&field, &g, ScanDirection::Counter, &Integration::default());
        let f = |x: f64, y: f64| lin.0 + lin.1 * x + lin.2 * y;
        let image: Vec<f64> = (0..nx * ny).map(|k| { let p = m.point(k % nx, k / nx).unwrap(); f(p.x.value(), p.y.value()) }).collect();
        let grid = OutputGrid::covering(&m, None).unwrap();
        let general = drift_corrected_map(&m, &vec![0.0; nx * ny], spm_hal::NmVelocity::default(), spm_hal::Seconds(0.0)).unwrap();
        let fast = resample(&image, &m, &grid, Interpolation::Bilinear, Parallelism::Sequential).unwrap();
        let newton = resample(&image, &general, &grid, Interpolation::Bilinear, Parallelism::Sequential).unwrap();
        let mut inside = 0;
        for r in 0..grid.rows {
            for c in 0..grid.columns {
                let k = r * grid.columns + c;
                let want = f(grid.x_nm(c), grid.y_nm(r));
                prop_assert_eq!(fast[k].is_nan(), newton[k].is_nan(), "node ({}, {})", c, r);
                if !fast[k].is_nan() {
                    inside += 1;
                    let tol = 1e-8 * (1.0 + want.abs() + 3.0 * step * (nx + ny) as f64);
                    prop_assert!((fast[k] - want).abs() <= tol, "fast {} want {}", fast[k], want);
                    prop_assert!((newton[k] - want).abs() <= tol, "newton {} want {}", newton[k], want);
                }
            }
        }
        prop_assert!(inside > 0);
    }
}

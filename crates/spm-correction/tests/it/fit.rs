//! The surfaces' fit over a plane's records: records a misrecognised structure spoilt are
//! left out when asked (`spmcal fit --reject-outliers`), against the field the records
//! were drawn from; and the correction 1-form fitted as an exact form (the default).
#![allow(clippy::unwrap_used)]

use spm_correction::fit::{SurfaceFitOptions, fit_plane};
use spm_records::LccColumns;

/// (K̄x, K̄y, α) of the field of [`records`]: K̄x = 0.02·(1 + 2·10⁻⁵·x), K̄yx = 0.015·sin(−0.17)
/// and K̄yy = 0.015·(1 − 3·10⁻⁵·y)·cos(−0.17) nm/count, an exact form (eq. 5).
fn rejection_field(x: f64, y: f64) -> (f64, f64, f64) {
    let kyx = 0.015 * (-0.17_f64).sin();
    let kyy = 0.015 * (1.0 - 3e-5 * y) * (-0.17_f64).cos();
    (0.02 * (1.0 + 2e-5 * x), kyx.hypot(kyy), kyx.atan2(kyy))
}

/// 49 records on a 7 × 7 net of a field with gradients ([`rejection_field`]), a
/// deterministic ±0.5 % scatter, and records 10, 24 and 40 spoilt (α off by 12°–17° and the
/// scales by 10 %–20 %, as on Si_7x7_028).
fn records() -> (LccColumns, [usize; 3]) {
    let spoilt = [10, 24, 40];
    let mut c = LccColumns::default();
    let mut state: u64 = 7;
    let mut jitter = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        ((state >> 33) % 1001) as f64 / 1000.0 - 0.5
    };
    for i in 0..49 {
        let (x, y) = (
            f64::from(i % 7) * 300.0 - 900.0,
            f64::from(i / 7) * 300.0 - 900.0,
        );
        let (kx, ky, alpha) = rejection_field(x, y);
        let (mut kx, mut ky, mut alpha) = (
            kx * (1.0 + 0.01 * jitter()),
            ky * (1.0 + 0.01 * jitter()),
            alpha + 0.002 * jitter(),
        );
        if spoilt.contains(&(i as usize)) {
            kx *= 1.1 + 0.05 * f64::from(i % 3);
            ky *= 0.85;
            alpha += 0.2 + 0.05 * f64::from(i % 2);
        }
        c.lcs_x_counts.push(x);
        c.lcs_y_counts.push(y);
        c.node_z_counts.push(0);
        c.acquired_unix_s.push(1.8e9 + f64::from(i));
        c.kx_nm_per_count.push(kx);
        c.ky_nm_per_count.push(ky);
        c.alpha_rad.push(alpha);
        c.kz_nm_per_count.push(None);
    }
    (c, spoilt)
}

#[test]
fn spoilt_records_are_left_out_when_asked_and_the_surfaces_are_the_field() {
    let (columns, spoilt) = records();
    let all = SurfaceFitOptions::bic_up_to(3);
    let robust = SurfaceFitOptions {
        outlier_sigmas: Some(3.5),
        ..all
    };
    let (plain, plain_summary) = fit_plane(0, &columns, &all).unwrap();
    let (fitted, summary) = fit_plane(0, &columns, &robust).unwrap();
    assert_eq!(plain_summary.outliers_left_out, 0);
    assert_eq!(summary.outliers_left_out, spoilt.len(), "{summary:?}");
    assert_eq!(fitted.n_records, 49 - spoilt.len());
    // Against the field at the net's corners and centre: α within 1 mrad and the scales
    // within 0.3 % with the spoilt records left out; fitted with them, α is 10 mrad off.
    let mut worst_plain_alpha: f64 = 0.0;
    for (x, y) in [
        (-900.0, -900.0),
        (900.0, -900.0),
        (0.0, 0.0),
        (-900.0, 900.0),
    ] {
        let truth = rejection_field(x, y);
        let kx = fitted.kx_nm_per_count.surface.evaluate(x, y);
        let ky = fitted.ky_nm_per_count.surface.evaluate(x, y);
        let alpha = fitted.alpha_rad.surface.evaluate(x, y);
        assert!(
            (kx / truth.0 - 1.0).abs() < 3e-3
                && (ky / truth.1 - 1.0).abs() < 3e-3
                && (alpha - truth.2).abs() < 1e-3,
            "({x}, {y}): {kx} {ky} {alpha} against {truth:?}"
        );
        worst_plain_alpha =
            worst_plain_alpha.max((plain.alpha_rad.surface.evaluate(x, y) - truth.2).abs());
    }
    assert!(worst_plain_alpha > 1e-2, "{worst_plain_alpha}");
}

/// A scanner field in the frame of eq. (5): x̄ = a·x + b·y + c·x·y + e·y² + f·x², ȳ = g·y + h·y²
/// (nm, counts), so K̄x = ∂x̄/∂x, K̄yx = ∂x̄/∂y, K̄yy = dȳ/dy; as (K̄x, K̄y, α).
fn exact_scanner(x: f64, y: f64) -> (f64, f64, f64) {
    let (a, b, c, e, f, g, h) = (0.02, -0.003, 4e-7, -2e-7, 3e-7, 0.015, -5e-7);
    let kx = a + c * y + 2.0 * f * x;
    let kyx = b + c * x + 2.0 * e * y;
    let kyy = g + 2.0 * h * y;
    (kx, kyx.hypot(kyy), kyx.atan2(kyy))
}

/// The two closed-loop integrals ∮ K̄x dx + K̄yx dy and ∮ K̄yy dy around the rectangle
/// `[x0, x1] × [y0, y1]`, nm: both zero when the corrected position is a function of the
/// scanner position (an exact form), whatever the raster's path.
fn loop_integrals(plane: &spm_correction::PlaneSurfaces, [x0, x1, y0, y1]: [f64; 4]) -> [f64; 2] {
    let kx = &plane.kx_nm_per_count.surface;
    let kyx = &plane.kyx_nm_per_count.surface;
    let kyy = &plane.kyy_nm_per_count.surface;
    [
        kx.integrate_x(x0, x1, y0) + kyx.integrate_y(x1, y0, y1)
            - kx.integrate_x(x0, x1, y1)
            - kyx.integrate_y(x0, y0, y1),
        kyy.integrate_y(x1, y0, y1) - kyy.integrate_y(x0, y0, y1),
    ]
}

#[test]
fn the_exact_form_corrects_independently_of_the_path_and_is_the_field() {
    // 36 records on a 6 × 6 net over ±1000 counts, with a deterministic scatter of ±1 % in
    // the scales and ±0.3° in α (a stored image's frozen noise).
    let mut c = LccColumns::default();
    for i in 0..36 {
        let (x, y) = (
            f64::from(i % 6) * 400.0 - 1000.0,
            f64::from(i / 6) * 400.0 - 1000.0,
        );
        let jitter = |k: f64| (f64::from(i) * k).sin();
        let (kx, ky, alpha) = exact_scanner(x, y);
        c.lcs_x_counts.push(x);
        c.lcs_y_counts.push(y);
        c.node_z_counts.push(0);
        c.acquired_unix_s.push(1.8e9 + f64::from(i));
        c.kx_nm_per_count.push(kx * (1.0 + 0.01 * jitter(1.7)));
        c.ky_nm_per_count.push(ky * (1.0 + 0.01 * jitter(2.3)));
        c.alpha_rad.push(alpha + 0.3_f64.to_radians() * jitter(3.1));
        c.kz_nm_per_count.push(None);
    }
    let exact = SurfaceFitOptions {
        form: Some(spm_correction::SurfaceForm::Exact),
        ..SurfaceFitOptions::bic_up_to(3)
    };
    let independent = SurfaceFitOptions {
        form: Some(spm_correction::SurfaceForm::Independent),
        ..exact
    };
    let (fitted, _) = fit_plane(0, &c, &exact).unwrap();
    let (one_by_one, _) = fit_plane(0, &c, &independent).unwrap();
    // An image twice the net's width: its raster reads K̄yx and K̄yy beyond the records.
    let image = [-2000.0, 2000.0, -1500.0, 1500.0];
    let [lx, ly] = loop_integrals(&fitted, image);
    assert!(
        lx.abs() < 1e-9 && ly.abs() < 1e-9,
        "exact form: {lx} {ly} nm"
    );
    let [ix, iy] = loop_integrals(&one_by_one, image);
    assert!(
        ix.abs().max(iy.abs()) > 0.05,
        "the surfaces fitted one by one close their loops too: {ix} {iy} nm"
    );
    // The exact form is the field: within 1 % in the scales and 0.3° in α over the net, and
    // its y scale within 1 % at the image's left and right edges.
    for (x, y) in [
        (-1000.0, -1000.0),
        (1000.0, 0.0),
        (0.0, 1000.0),
        (-2000.0, 500.0),
    ] {
        let (kx, ky, alpha) = exact_scanner(x, y);
        let kyy = ky * alpha.cos();
        let kyx = ky * alpha.sin();
        let got_kx = fitted.kx_nm_per_count.surface.evaluate(x, y);
        let got_kyx = fitted.kyx_nm_per_count.surface.evaluate(x, y);
        let got_kyy = fitted.kyy_nm_per_count.surface.evaluate(x, y);
        assert!(
            (got_kx / kx - 1.0).abs() < 0.01
                && (got_kyy / kyy - 1.0).abs() < 0.01
                && (got_kyx - kyx).abs() < 0.3_f64.to_radians() * ky,
            "({x}, {y}): K̄x {got_kx} / {kx}, K̄yx {got_kyx} / {kyx}, K̄yy {got_kyy} / {kyy}"
        );
    }
}

/// The records `cdb check` would flag (K̄x ≤ 0, α non-finite or beyond ±π/2, a centre that is
/// not finite, Kz ≤ 0) are left out of a fit and counted; the others stay, in order.
#[test]
fn records_cdb_check_would_flag_are_left_out_and_counted() {
    let mut c = LccColumns::default();
    // (x, kx, alpha, kz): valid when every field is.
    let rows = [
        (0.0, 0.02, 0.1, None),
        (1.0, -0.02, 0.1, None),
        (2.0, 0.02, f64::NAN, None),
        (3.0, 0.02, 2.0, None),
        (f64::INFINITY, 0.02, 0.1, None),
        (5.0, 0.02, 0.1, Some(0.0)),
        (6.0, 0.02, -0.3, Some(0.01)),
    ];
    for (x, kx, alpha, kz) in rows {
        c.lcs_x_counts.push(x);
        c.lcs_y_counts.push(0.0);
        c.node_z_counts.push(0);
        c.acquired_unix_s.push(0.0);
        c.kx_nm_per_count.push(kx);
        c.ky_nm_per_count.push(0.015);
        c.alpha_rad.push(alpha);
        c.kz_nm_per_count.push(kz);
    }
    assert_eq!(spm_correction::fit::keep_valid(&mut c), 5);
    assert_eq!(c.lcs_x_counts, vec![0.0, 6.0]);
    assert_eq!(c.alpha_rad, vec![0.1, -0.3]);
    assert_eq!(c.kz_nm_per_count, vec![None, Some(0.01)]);
    assert_eq!(c.len(), 2);
}

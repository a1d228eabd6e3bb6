//! The surfaces' fit over a plane's records: records a misrecognised structure spoilt are
//! left out when asked (`spmcal fit --reject-outliers`), against the field the records
//! were drawn from.
#![allow(clippy::unwrap_used)]

use spm_records::LccColumns;
use spmcal::surfaces::{SurfaceFitOptions, fit_plane};

/// 49 records on a 7 × 7 net of a linear field (K̄x, K̄y, α with gradients), a
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
        let (mut kx, mut ky, mut alpha) = (
            0.02 * (1.0 + 2e-5 * x) * (1.0 + 0.01 * jitter()),
            0.015 * (1.0 - 3e-5 * y) * (1.0 + 0.01 * jitter()),
            -0.17 + 2e-5 * x + 0.002 * jitter(),
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
        let truth = (
            0.02 * (1.0 + 2e-5 * x),
            0.015 * (1.0 - 3e-5 * y),
            -0.17 + 2e-5 * x,
        );
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

#[test]
fn a_rejection_threshold_below_one_sigma_is_bad_input() {
    for bad in ["0.5", "-3", "nan", "inf"] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_spmcal"))
            .args(["fit", "--cdb", "/no/such.sqlite", "--out", "/no/such.json"])
            .arg(format!("--reject-outliers={bad}"))
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{bad}: {stderr}");
        assert!(stderr.contains("--reject-outliers"), "{bad}: {stderr}");
    }
}

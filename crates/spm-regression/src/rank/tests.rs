#![allow(clippy::unwrap_used)]
use super::*;

/// Every row of a per-observation mask (two rows per observation, as the model check has).
fn pairs(mask: &[bool]) -> Vec<bool> {
    mask.iter().flat_map(|&m| [m, m]).collect()
}

/// Exact data: the coefficients come back, the RSS is zero, and the rank is that of the
/// design; a repeated column adds no rank, and the minimum-norm solution shares its weight
/// equally with its twin (closed form: the pseudo-inverse splits c between two equal columns
/// as c/2 each).
#[test]
fn exact_coefficients_the_rank_and_the_minimum_norm_split() {
    let n = 200;
    let t: Vec<f64> = (0..2 * n)
        .map(|i| i as f64 / (2 * n) as f64 - 0.5)
        .collect();
    let cols: Vec<Vec<f64>> = vec![
        vec![1.0; 2 * n],
        t.clone(),
        t.iter().map(|v| v * v * v).collect(),
    ];
    let truth = [0.3, -2.0, 5.0];
    let target: Vec<f64> = (0..2 * n)
        .map(|i| (0..3).map(|j| truth[j] * cols[j][i]).sum())
        .collect();
    let all = vec![true; 2 * n];
    let fit = minimum_norm_least_squares(&cols, &target, &all).unwrap();
    for (c, t) in fit.coefficients.iter().zip(truth) {
        assert!((c - t).abs() < 1e-10, "{c} vs {t}");
    }
    assert!(fit.rss < 1e-20 && fit.rank == 3 && fit.equations == 2 * n);
    let dense = solve_dense(&cols, &target, &all).unwrap();
    assert_eq!(dense.rank, 3);
    // A repeated column does not add rank; the fit is unchanged.
    let mut dup = cols.clone();
    dup.push(cols[1].clone());
    let fit = minimum_norm_least_squares(&dup, &target, &all).unwrap();
    assert_eq!(fit.rank, 3);
    assert!((fit.coefficients[1] + fit.coefficients[3] + 2.0).abs() < 1e-10);
    assert!((fit.coefficients[1] + 1.0).abs() < 1e-9 && (fit.coefficients[3] + 1.0).abs() < 1e-9);
    assert!(fit.residuals.iter().all(|r| r.abs() < 1e-10));
}

/// Per-frame offset columns eliminated by demeaning give the dense
/// solution: coefficients, RSS, rank and the whole covariance.
#[test]
fn indicator_elimination_equals_the_dense_solution() {
    let n = 300;
    let u = |i: usize| ((i as f64 * 7.31).sin() * 1000.0).fract();
    let frame = |k: usize| k * 3 / n;
    let mut cols: Vec<Vec<f64>> = Vec::new();
    for f in 0..3 {
        for axis in 0..2 {
            cols.push(
                (0..2 * n)
                    .map(|r| f64::from(u8::from(r % 2 == axis && frame(r / 2) == f)))
                    .collect(),
            );
        }
    }
    cols.push((0..2 * n).map(|r| u(r) - 0.3).collect());
    cols.push((0..2 * n).map(|r| (r as f64 / 400.0).powi(2)).collect());
    let target: Vec<f64> = (0..2 * n)
        .map(|r| {
            0.7 * cols[6][r] - 1.1 * cols[7][r] + 0.2 * (frame(r / 2) as f64) + 0.05 * u(r + 7)
        })
        .collect();
    let mask = pairs(&(0..n).map(|k| k % 11 != 0).collect::<Vec<_>>());
    let fast = minimum_norm_least_squares(&cols, &target, &mask).unwrap();
    let dense = solve_dense(&cols, &target, &mask).unwrap();
    assert_eq!((fast.rank, fast.equations), (dense.rank, dense.n_eq));
    assert!((fast.rss - dense.rss).abs() < 1e-10 * dense.rss);
    for j in 0..cols.len() {
        assert!(
            (fast.coefficients[j] - dense.coef[j]).abs() < 1e-9,
            "coef {j}"
        );
        for k in 0..cols.len() {
            let (a, b) = (fast.covariance[j][k], dense.cov[(j, k)]);
            assert!(
                (a - b).abs() < 1e-9 * (1.0 + b.abs()),
                "cov {j},{k}: {a} vs {b}"
            );
        }
    }
    for (a, b) in fast.residuals.iter().zip(&dense.residual) {
        assert!((a - b).abs() < 1e-9);
    }
}

/// Noisy data on an orthogonal design: var(coef_j) = σ̂²/‖col_j‖² (closed form).
#[test]
fn the_covariance_matches_the_closed_form_for_an_orthogonal_design() {
    let n = 500;
    let a: Vec<f64> = (0..2 * n)
        .map(|i| if i % 2 == 0 { 1.0 } else { -1.0 })
        .collect();
    let b: Vec<f64> = (0..2 * n)
        .map(|i| if (i / 2) % 2 == 0 { 2.0 } else { -2.0 })
        .collect();
    let noise: Vec<f64> = (0..2 * n)
        .map(|i| ((i as f64 * 12.9898).sin() * 43_758.545).fract() - 0.5)
        .collect();
    let target: Vec<f64> = (0..2 * n)
        .map(|i| 1.5 * a[i] - 0.5 * b[i] + noise[i])
        .collect();
    let fit =
        minimum_norm_least_squares(&[a.clone(), b.clone()], &target, &vec![true; 2 * n]).unwrap();
    let sigma2 = fit.rss / (2 * n - 2) as f64;
    let na: f64 = a.iter().map(|v| v * v).sum();
    let nb: f64 = b.iter().map(|v| v * v).sum();
    let c = &fit.covariance;
    assert!((c[0][0] - sigma2 / na).abs() < 1e-12 * (1.0 + sigma2 / na));
    assert!((c[1][1] - sigma2 / nb).abs() < 1e-12 * (1.0 + sigma2 / nb));
    assert!(c[0][1].abs() < 1e-12);
}

/// A straight line agrees with the other kernel entry, [`crate::least_squares`]: the same
/// coefficients and the covariance σ̂²·(XᵀX)⁻¹ (the unscaled covariance times σ̂²).
#[test]
fn a_full_rank_problem_agrees_with_least_squares() {
    let x: Vec<f64> = (0..10).map(f64::from).collect();
    let y: Vec<f64> = x
        .iter()
        .map(|v| 1.0 + 0.5 * v + 0.1 * (v * 1.7).sin())
        .collect();
    let fit = minimum_norm_least_squares(&[vec![1.0; 10], x.clone()], &y, &[true; 10]).unwrap();
    let rows: Vec<Vec<f64>> = x.iter().map(|v| vec![1.0, *v]).collect();
    let reference = crate::least_squares(&rows, &y, &[false, false]).unwrap();
    let sigma2 = fit.rss / 8.0;
    for j in 0..2 {
        assert!((fit.coefficients[j] - reference.coefficients[j]).abs() < 1e-12);
        for k in 0..2 {
            let expected = sigma2 * reference.unscaled_covariance[j][k];
            assert!((fit.covariance[j][k] - expected).abs() < 1e-12 * (1.0 + expected.abs()));
        }
    }
}

/// Bad input is a typed error: too few fitted rows, a column or mask of another length,
/// non-finite data in a fitted row (but not in a row left out, which keeps its residual).
#[test]
fn bad_input_is_refused_and_left_out_rows_are_not_fitted() {
    let col = vec![1.0, 2.0, 3.0, 4.0];
    let y = vec![2.0, 4.0, 6.0, f64::NAN];
    assert!(matches!(
        minimum_norm_least_squares(std::slice::from_ref(&col), &y, &[true; 4]),
        Err(RegressionError::NonFinite {
            field: "rhs",
            index: 3
        })
    ));
    let fit =
        minimum_norm_least_squares(std::slice::from_ref(&col), &y, &[true, true, true, false])
            .unwrap();
    assert!((fit.coefficients[0] - 2.0).abs() < 1e-12 && fit.equations == 3);
    assert!(fit.residuals[3].is_nan());
    assert!(matches!(
        minimum_norm_least_squares(std::slice::from_ref(&col), &y, &[true, false, false, false]),
        Err(RegressionError::TooFewPoints {
            needed: 2,
            got: 1,
            ..
        })
    ));
    assert!(matches!(
        minimum_norm_least_squares(&[vec![1.0]], &y, &[true; 4]),
        Err(RegressionError::LengthMismatch { .. })
    ));
    assert!(matches!(
        minimum_norm_least_squares(std::slice::from_ref(&col), &y, &[true; 3]),
        Err(RegressionError::LengthMismatch { .. })
    ));
}

/// A symmetric system: an invertible one is solved exactly (closed form of the 2 × 2
/// inverse), a singular one gets the minimum-norm solution (diag(2, 0)·x = (4, 0): x = (2, 0);
/// [[1, 1], [1, 1]]·x = (2, 2): x = (1, 1)).
#[test]
fn symmetric_systems_solve_to_the_pseudo_inverse() {
    let a = vec![vec![4.0, 1.0], vec![1.0, 3.0]];
    let x = minimum_norm_solve(&a, &[1.0, 2.0], 1e-12).unwrap();
    // Inverse of [[4, 1], [1, 3]] is [[3, −1], [−1, 4]] / 11.
    assert!((x[0] - 1.0 / 11.0).abs() < 1e-14 && (x[1] - 7.0 / 11.0).abs() < 1e-14);
    let x = minimum_norm_solve(&[vec![2.0, 0.0], vec![0.0, 0.0]], &[4.0, 0.0], 1e-12).unwrap();
    assert!((x[0] - 2.0).abs() < 1e-14 && x[1].abs() < 1e-14);
    let x = minimum_norm_solve(&[vec![1.0, 1.0], vec![1.0, 1.0]], &[2.0, 2.0], 1e-12).unwrap();
    assert!((x[0] - 1.0).abs() < 1e-12 && (x[1] - 1.0).abs() < 1e-12);
    assert_eq!(
        minimum_norm_solve(&[], &[], 1e-12).unwrap(),
        Vec::<f64>::new()
    );
    assert!(matches!(
        minimum_norm_solve(&[vec![1.0]], &[1.0, 2.0], 1e-12),
        Err(RegressionError::LengthMismatch { .. })
    ));
    assert!(matches!(
        minimum_norm_solve(&[vec![f64::INFINITY]], &[1.0], 1e-12),
        Err(RegressionError::NonFinite { .. })
    ));
}

/// One factored design fits many right-hand sides as separate calls do, bit for bit, with
/// and without indicator columns, whatever was fitted before; a rhs of another length or
/// with NaN in a fitted row is refused, one left out is not looked at.
#[test]
fn a_factored_design_fits_each_rhs_as_a_fresh_solve_does() {
    let n = 200;
    let u = |i: usize| ((i as f64 * 3.17).sin() * 1000.0).fract();
    let with_offsets: Vec<Vec<f64>> = vec![
        (0..n).map(|r| f64::from(u8::from(r < n / 2))).collect(),
        (0..n).map(|r| f64::from(u8::from(r >= n / 2))).collect(),
        (0..n).map(|r| u(r) - 0.5).collect(),
        (0..n).map(|r| (r as f64 / 90.0).sin()).collect(),
    ];
    let dense_only = with_offsets[2..].to_vec();
    let mask: Vec<bool> = (0..n).map(|r| r % 7 != 3).collect();
    let targets: Vec<Vec<f64>> = (0..4)
        .map(|k| {
            (0..n)
                .map(|r| (k as f64 + 1.0) * u(r + 11 * k) + 0.3 * with_offsets[3][r])
                .collect()
        })
        .collect();
    for cols in [&with_offsets, &dense_only] {
        let design = FactoredDesign::new(cols, &mask).unwrap();
        for target in targets.iter().rev().chain(&targets) {
            let once = design.fit(target).unwrap();
            let fresh = minimum_norm_least_squares(cols, target, &mask).unwrap();
            assert_eq!(once, fresh);
            assert!(once.rss > 0.0 && once.rank == cols.len());
        }
        let mut bad = targets[0].clone();
        bad[3] = f64::NAN;
        assert!(design.fit(&bad).is_ok(), "row 3 is left out");
        bad[4] = f64::NAN;
        assert!(matches!(
            design.fit(&bad),
            Err(RegressionError::NonFinite {
                field: "rhs",
                index: 4
            })
        ));
        assert!(matches!(
            design.fit(&targets[0][1..]),
            Err(RegressionError::LengthMismatch { .. })
        ));
    }
}

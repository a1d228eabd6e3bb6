//! LCC solving: exact recovery (property test) and unbiasedness within the stated
//! uncertainty under noise.
#![allow(clippy::unwrap_used)]

use proptest::prelude::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use spm_calibration::{
    CountCovariance, StandardVector, VectorObservation, solve_lcc, solve_metric_system,
};
use spm_hal::{CountVector, Counts, Nanometres, Radians};

/// Count vector that a scanner with LCCs (kx, ky, alpha) rotated by theta against the
/// standard measures for the true vector d: u = M⁻¹ R(−θ) d.
fn counts_for(kx: f64, ky: f64, alpha: f64, theta: f64, d: StandardVector) -> CountVector {
    let (s, c) = theta.sin_cos();
    let (dx, dy) = (d.x.value(), d.y.value());
    let (rx, ry) = (c * dx + s * dy, -s * dx + c * dy);
    // M = [[kx, ky sin a], [0, ky cos a]]
    let uy = ry / (ky * alpha.cos());
    let ux = (rx - ky * alpha.sin() * uy) / kx;
    CountVector::from_counts(ux, uy)
}

fn hex_neighbours(a: f64, count: usize) -> Vec<StandardVector> {
    (0..count)
        .map(|k| StandardVector::polar(Nanometres(a), Radians::from_degrees(60.0 * k as f64)))
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]
    #[test]
    fn exact_vectors_give_exact_lccs(
        kx in 1e-4f64..1e-1, ky_ratio in 0.5f64..2.0, alpha in -0.5f64..0.5,
        theta in -3.2f64..3.2, a in 0.1f64..3.0, extra in 0usize..5,
    ) {
        let ky = kx * ky_ratio;
        let standard = hex_neighbours(a, 2 + extra);
        let obs: Vec<_> = standard.iter().map(|&d| VectorObservation {
            measured: counts_for(kx, ky, alpha, theta, d),
            covariance: CountCovariance::EXACT,
            standard: d,
        }).collect();
        let e = solve_lcc(&obs).unwrap();
        prop_assert!((e.kx.value() / kx - 1.0).abs() < 1e-9, "kx {} vs {}", e.kx.value(), kx);
        prop_assert!((e.ky.value() / ky - 1.0).abs() < 1e-9);
        prop_assert!((e.alpha.value() - alpha).abs() < 1e-9);
        // The reference metric formulation agrees.
        let (gkx, gky, galpha) = solve_metric_system(&obs).unwrap().coefficients().unwrap();
        prop_assert!((gkx.value() / kx - 1.0).abs() < 1e-7);
        prop_assert!((gky.value() / ky - 1.0).abs() < 1e-7);
        prop_assert!((galpha.value() - alpha).abs() < 1e-7);
        // dᵢᵀ G dⱼ = Dᵢ·Dⱼ.
        for i in &obs {
            for j in &obs {
                let lhs = e.metric.inner_nm2(i.measured, j.measured);
                let rhs = i.standard.x.value() * j.standard.x.value()
                    + i.standard.y.value() * j.standard.y.value();
                prop_assert!((lhs - rhs).abs() < 1e-9 * a * a);
            }
        }
    }
}

struct Trials {
    mean_error: [f64; 3],
    std_error_of_mean: [f64; 3],
    empirical_sd: [f64; 3],
    mean_stated_u: [f64; 3],
}

fn run_trials(vectors: usize, bc: bool, sigma_counts: f64, n: usize, seed: u64) -> Trials {
    let (kx, ky, alpha, theta) = (0.0041, 0.0037, 0.035, 0.3);
    let a = 0.2461;
    let mut standard = hex_neighbours(a, vectors);
    if bc {
        standard.push(standard[1].minus(standard[0]));
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let noise = Normal::new(0.0, sigma_counts).unwrap();
    let truth = [kx, ky, alpha];
    let mut sum = [0.0; 3];
    let mut sum2 = [0.0; 3];
    let mut stated = [0.0; 3];
    for _ in 0..n {
        let obs: Vec<_> = standard
            .iter()
            .map(|&d| {
                let u = counts_for(kx, ky, alpha, theta, d);
                VectorObservation {
                    measured: CountVector::new(
                        u.x + Counts(noise.sample(&mut rng)),
                        u.y + Counts(noise.sample(&mut rng)),
                    ),
                    covariance: CountCovariance::isotropic(Counts(sigma_counts)),
                    standard: d,
                }
            })
            .collect();
        let e = solve_lcc(&obs).unwrap();
        let got = [e.kx.value(), e.ky.value(), e.alpha.value()];
        let u = [e.u_kx().value(), e.u_ky().value(), e.u_alpha().value()];
        for k in 0..3 {
            let err = got[k] - truth[k];
            sum[k] += err;
            sum2[k] += err * err;
            stated[k] += u[k];
        }
    }
    let nf = n as f64;
    let mut t = Trials {
        mean_error: [0.0; 3],
        std_error_of_mean: [0.0; 3],
        empirical_sd: [0.0; 3],
        mean_stated_u: [0.0; 3],
    };
    for k in 0..3 {
        let mean = sum[k] / nf;
        let var = (sum2[k] / nf - mean * mean) * nf / (nf - 1.0);
        t.mean_error[k] = mean;
        t.empirical_sd[k] = var.sqrt();
        t.std_error_of_mean[k] = var.sqrt() / nf.sqrt();
        t.mean_stated_u[k] = stated[k] / nf;
    }
    t
}

fn check(name: &str, t: &Trials) {
    for (k, label) in ["kx", "ky", "alpha"].iter().enumerate() {
        let z = t.mean_error[k] / t.std_error_of_mean[k];
        let ratio = t.mean_stated_u[k] / t.empirical_sd[k];
        println!(
            "{name} {label}: mean error {:.3e}, z = {z:.2}, stated u {:.3e}, empirical sd {:.3e}, ratio {ratio:.3}",
            t.mean_error[k], t.mean_stated_u[k], t.empirical_sd[k]
        );
        assert!(z.abs() < 3.0, "{name} {label}: biased, z = {z}");
        assert!(
            (0.85..1.15).contains(&ratio),
            "{name} {label}: stated uncertainty {} vs empirical {}",
            t.mean_stated_u[k],
            t.empirical_sd[k]
        );
    }
}

/// σ = 0.6 counts on vectors of ~60 counts (1 %, a realistic averaged skipping result).
#[test]
fn noisy_two_vector_solution_is_unbiased_within_the_stated_uncertainty() {
    let t = run_trials(2, false, 0.6, 20000, 1);
    check("A-B, A-C", &t);
}

#[test]
fn redundant_vectors_are_unbiased_and_more_precise() {
    let two = run_trials(2, false, 0.6, 3000, 2);
    let bc = run_trials(2, true, 0.6, 3000, 3);
    let six = run_trials(6, false, 0.6, 3000, 4);
    check("A-B, A-C, B-C", &bc);
    check("six neighbours", &six);
    for k in 0..3 {
        assert!(bc.mean_stated_u[k] < two.mean_stated_u[k]);
        assert!(six.mean_stated_u[k] < bc.mean_stated_u[k]);
    }
}

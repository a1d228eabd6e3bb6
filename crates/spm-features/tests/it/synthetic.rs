//! Recognition on synthetic HOPG height maps with known atom positions.
#![allow(clippy::unwrap_used)]

use crate::common;

use common::{Hopg, segment_map};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use spm_features::{DetectionConfig, detect, profile_cramer_rao};
use spm_hal::{CountPoint, Counts};

/// RMS localisation error and the Cramér–Rao bound for `trials` segments at
/// `snr` (= corrugation / σn). Returns (rms per axis, crb per axis).
fn localisation_vs_crb(snr: f64, trials: usize, seed: u64) -> (f64, f64) {
    let hopg = Hopg::new(0.005, 0.3);
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let pixels = 16;
    let step = Counts(1.2 * hopg.a_counts / f64::from(pixels - 1));
    let noise = hopg.corrugation_z / snr;
    let config = DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step.value(),
        ..DetectionConfig::default()
    };
    let mut sum_sq = 0.0;
    let mut crb_sq = 0.0;
    let mut n = 0;
    for trial in 0..trials {
        // Put an atom near the segment centre with a sub-pixel offset.
        let atom = hopg.atom(3, 2);
        let offset = (
            ((trial * 7919) % 101) as f64 / 101.0 - 0.5,
            ((trial * 104729) % 97) as f64 / 97.0 - 0.5,
        );
        let centre = CountPoint::from_counts(
            atom.x.value() + offset.0 * step.value(),
            atom.y.value() + offset.1 * step.value(),
        );
        let map = segment_map(&hopg, centre, step, pixels, noise, &mut rng);
        let found = detect(&map, &config).unwrap();
        let Some(f) = found.nearest(atom) else {
            panic!(
                "no feature at snr {snr}, trial {trial}: {:?} noise {}",
                found.rejected, found.noise_sigma_z_counts
            );
        };
        let (ex, ey) = (
            f.position.x.value() - atom.x.value(),
            f.position.y.value() - atom.y.value(),
        );
        sum_sq += ex * ex + ey * ey;
        let (col, row) = map.pixel_of(atom);
        let radius = config.fit_radius_sigmas * f.width.value() / step.value();
        let bound = profile_cramer_rao(
            |dx, dy| {
                hopg.height(
                    atom.x.value() + dx * step.value(),
                    atom.y.value() + dy * step.value(),
                )
            },
            (col, row),
            map.columns,
            map.rows,
            radius,
            step,
            noise,
            true,
        )
        .unwrap();
        crb_sq += bound.sigma_x.value().powi(2) + bound.sigma_y.value().powi(2);
        n += 1;
    }
    (
        (sum_sq / (2 * n) as f64).sqrt(),
        (crb_sq / (2 * n) as f64).sqrt(),
    )
}

#[test]
fn localisation_error_is_within_1_5_of_the_cramer_rao_bound() {
    for (snr, seed) in [(5.0, 1), (10.0, 2), (20.0, 3)] {
        let (rms, crb) = localisation_vs_crb(snr, 200, seed);
        println!(
            "SNR {snr}: rms {rms:.4} counts, CRB {crb:.4} counts, ratio {:.3}",
            rms / crb
        );
        assert!(rms <= 1.5 * crb, "SNR {snr}: rms {rms} > 1.5 × CRB {crb}");
    }
}

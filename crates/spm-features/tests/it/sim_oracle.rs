//! Localisation on segments scanned by the simulator (spm-sim, dev-dependency
//! only) against the oracle's true atom positions and the Cramér–Rao bound of
//! the true surface profile over the fit window.
#![allow(clippy::unwrap_used)]

use spm_features::{DetectionConfig, detect, profile_cramer_rao};
use spm_hal::{CountPoint, Counts, Microscope, NmPoint, ScanRequest, Seconds, TraceHalf};
use spm_sim::{FeatureKind, SimConfig, Simulator};

/// Ideal scanner (0.02 nm/count, no drift) with white Z noise σ = corrugation / SNR.
fn simulator(snr: f64, seed: u64) -> (Simulator, f64) {
    let mut config = SimConfig::ideal();
    config.seed = seed;
    let corrugation_nm = match &config.surface {
        spm_sim::SurfaceConfig::Hopg(h) => h.corrugation_nm,
        _ => unreachable!("the ideal config is HOPG"),
    };
    config.measurement.z_white_noise_nm = corrugation_nm / snr;
    (Simulator::new(config).unwrap(), corrugation_nm / snr)
}

/// (RMS error per axis, CRB per axis) in counts over `trials` 16×16 segments.
fn localisation(snr: f64, trials: usize) -> (f64, f64) {
    let (mut sim, noise_nm) = simulator(snr, 7 + snr as u64);
    let nm_per_count = 0.02;
    let kz = sim.oracle().kz().value();
    let step = Counts(1.0);
    let config = DetectionConfig {
        min_separation_px: 0.4 * 0.2461 / nm_per_count,
        ..DetectionConfig::default()
    };
    let (mut err2, mut crb2) = (0.0, 0.0);
    for trial in 0..trials {
        // A segment around a true atom, offset by a fraction of a pixel.
        let guess = NmPoint::from_nm(0.37 * trial as f64, 0.23 * trial as f64);
        let site = sim
            .oracle()
            .features_near(guess, 0.3)
            .into_iter()
            .find(|s| s.kind == FeatureKind::Atom)
            .unwrap();
        let atom = sim
            .oracle()
            .commanded_for_sample_point(site.position)
            .unwrap();
        let offset = (
            ((trial * 37) % 19) as f64 / 19.0 - 0.5,
            ((trial * 53) % 23) as f64 / 23.0 - 0.5,
        );
        let centre = CountPoint::from_counts(atom.x.value() + offset.0, atom.y.value() + offset.1);
        let request = ScanRequest::centred_square(centre, step, 16, Seconds(1e-4));
        let map = sim
            .scan(&request)
            .unwrap()
            .height_map(TraceHalf::Forward)
            .unwrap();
        let found = detect(&map, &config).unwrap();
        let f = found.nearest(atom).unwrap();
        assert!(
            f.position.distance(atom).value() < 2.0,
            "trial {trial}: {f:?}"
        );
        err2 += (f.position.x - atom.x).value().powi(2) + (f.position.y - atom.y).value().powi(2);
        let (col, row) = map.pixel_of(atom);
        let radius = (config.fit_radius_sigmas * f.width.value() / step.value())
            .min(1.25 * config.min_separation_px);
        let oracle = sim.oracle();
        let bound = profile_cramer_rao(
            |dx, dy| {
                let p = NmPoint::from_nm(
                    site.position.x.value() + dx * nm_per_count,
                    site.position.y.value() + dy * nm_per_count,
                );
                oracle.surface_height(p) / kz
            },
            (col, row),
            map.columns,
            map.rows,
            radius,
            step,
            noise_nm / kz,
            true,
        )
        .unwrap();
        crb2 += bound.sigma_x.value().powi(2) + bound.sigma_y.value().powi(2);
    }
    let n = (2 * trials) as f64;
    ((err2 / n).sqrt(), (crb2 / n).sqrt())
}

#[test]
fn localisation_on_simulated_hopg_is_within_1_5_of_the_cramer_rao_bound() {
    for snr in [5.0, 10.0, 20.0] {
        let (rms, crb) = localisation(snr, 150);
        println!(
            "SNR {snr}: RMS {rms:.4} counts, CRB {crb:.4} counts, ratio {:.3}",
            rms / crb
        );
        assert!(rms <= 1.5 * crb, "SNR {snr}: RMS {rms} > 1.5 × CRB {crb}");
    }
}

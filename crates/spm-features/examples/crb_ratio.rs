//! Localisation RMS error ÷ Cramér–Rao bound on synthetic HOPG segments
//! (16×16 pixels over 1.2 a, three-cosine atoms, white noise) at SNR 5, 10, 20.
//!
//! `cargo run --release -p spm-features --example crb_ratio [trials]`
#![allow(clippy::unwrap_used)]

#[path = "../tests/it/common/mod.rs"]
mod common;

use common::{Hopg, segment_map};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use spm_features::{DetectionConfig, design_cramer_rao, detect, profile_cramer_rao};
use spm_hal::{CountPoint, Counts};

fn main() {
    let trials: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(2000);
    let hopg = Hopg::new(0.005, 0.3);
    let step = Counts(1.2 * hopg.a_counts / 15.0);
    let config = DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step.value(),
        ..DetectionConfig::default()
    };
    println!(
        "| SNR | trials | RMS error (counts) | CRB window (counts) | ratio | DESIGN √(2/π)·p·σn/A (counts) | missed |"
    );
    println!("|---|---|---|---|---|---|---|");
    for snr in [5.0, 10.0, 20.0] {
        let mut rng = ChaCha8Rng::seed_from_u64(snr as u64);
        let noise = hopg.corrugation_z / snr;
        let (mut err2, mut crb2, mut amp, mut n, mut missed) = (0.0, 0.0, 0.0, 0, 0);
        for _ in 0..trials {
            let atom = hopg.atom(3, 2);
            let off = (rng.random::<f64>() - 0.5, rng.random::<f64>() - 0.5);
            let centre = CountPoint::from_counts(
                atom.x.value() + off.0 * step.value(),
                atom.y.value() + off.1 * step.value(),
            );
            let map = segment_map(&hopg, centre, step, 16, noise, &mut rng);
            let found = detect(&map, &config).unwrap();
            let Some(f) = found
                .nearest(atom)
                .filter(|f| f.position.distance(atom).value() < 0.3 * hopg.a_counts)
            else {
                missed += 1;
                continue;
            };
            err2 +=
                (f.position.x - atom.x).value().powi(2) + (f.position.y - atom.y).value().powi(2);
            let (col, row) = map.pixel_of(atom);
            let radius = config.fit_radius_sigmas * f.width.value() / step.value();
            let b = profile_cramer_rao(
                |dx, dy| {
                    hopg.height(
                        atom.x.value() + dx * step.value(),
                        atom.y.value() + dy * step.value(),
                    )
                },
                (col, row),
                map.columns,
                map.rows,
                radius.min(1.25 * config.min_separation_px),
                step,
                noise,
                true,
            )
            .unwrap_or_else(|e| {
                panic!("{e}: radius {radius}, feature {f:?}, atom at ({col}, {row})")
            });
            crb2 += b.sigma_x.value().powi(2) + b.sigma_y.value().powi(2);
            amp += f.amplitude_z_counts;
            n += 1;
        }
        let rms = (err2 / (2 * n) as f64).sqrt();
        let crb = (crb2 / (2 * n) as f64).sqrt();
        let design = design_cramer_rao(step, noise, amp / n as f64);
        println!(
            "| {snr} | {n} | {rms:.4} | {crb:.4} | {:.3} | {:.4} | {missed} |",
            rms / crb,
            design.value()
        );
    }
}

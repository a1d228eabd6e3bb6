//! CPU-time probe of detection (development aid; use with `perf stat -e task-clock`):
//! `profile_detect fits` = 2001 apertures 64×64 (17 atoms each), `nofits` = 2000
//! apertures with fitting disabled, `segment` = 40 000 segments 16×16.
#![allow(clippy::unwrap_used)]

#[path = "../tests/it/common/mod.rs"]
mod common;

use common::{Hopg, segment_map};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use spm_features::{DetectionConfig, detect};
use spm_hal::Counts;

fn main() {
    let hopg = Hopg::new(0.005, 0.3);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let step64 = Counts(4.0 * hopg.a_counts / 63.0);
    let aperture = segment_map(
        &hopg,
        hopg.atom(3, 2),
        step64,
        64,
        hopg.corrugation_z / 10.0,
        &mut rng,
    );
    let config = DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step64.value(),
        ..DetectionConfig::default()
    };
    let found = detect(&aperture, &config).unwrap();
    println!(
        "{} features, {} rejected: {:?}",
        found.features.len(),
        found.rejected.len(),
        found.rejected
    );
    let n = 2000;
    let mode = std::env::args().nth(1).unwrap_or_default();
    if mode == "segment" {
        let step16 = Counts(1.2 * hopg.a_counts / 15.0);
        let atom = hopg.atom(3, 2);
        let centre =
            spm_hal::CountPoint::from_counts(atom.x.value() + 0.3 * step16.value(), atom.y.value());
        let segment = segment_map(
            &hopg,
            centre,
            step16,
            16,
            hopg.corrugation_z / 10.0,
            &mut rng,
        );
        let config16 = DetectionConfig {
            min_separation_px: 0.4 * hopg.a_counts / step16.value(),
            ..DetectionConfig::default()
        };
        for _ in 0..20 * n {
            std::hint::black_box(detect(&segment, &config16).unwrap());
        }
        return;
    }
    if mode == "nofits" {
        let config = DetectionConfig {
            min_snr: 1e6,
            ..config
        };
        for _ in 0..n {
            std::hint::black_box(detect(&aperture, &config).unwrap());
        }
        return;
    }
    let start = std::time::Instant::now();
    for _ in 0..n {
        std::hint::black_box(detect(&aperture, &config).unwrap());
    }
    println!(
        "{:.1} µs per aperture",
        start.elapsed().as_secs_f64() * 1e6 / f64::from(n)
    );
    if mode == "fits" {
        return;
    }
    let config = DetectionConfig {
        min_snr: 1e6,
        ..config
    };
    let start = std::time::Instant::now();
    for _ in 0..n {
        std::hint::black_box(detect(&aperture, &config).unwrap());
    }
    println!(
        "{:.1} µs per aperture without fits",
        start.elapsed().as_secs_f64() * 1e6 / f64::from(n)
    );
}

//! Recognition time per 16×16 segment and per 64×64 aperture of simulated
//! HOPG at SNR 10 (targets ≤ 20 µs and ≤ 300 µs, one core, release).
#![allow(clippy::unwrap_used)]

#[path = "../tests/it/common/mod.rs"]
mod common;

use common::{Hopg, segment_map};
use criterion::{Criterion, black_box, criterion_group, criterion_main};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use spm_features::{
    DetectionConfig, LatticeConfig, LcsConfig, detect, lattice_vectors, lcs_with_vertex,
};
use spm_hal::{CountPoint, Counts};

fn bench(c: &mut Criterion) {
    let hopg = Hopg::new(0.005, 0.3);
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let noise = hopg.corrugation_z / 10.0;

    let atom = hopg.atom(3, 2);
    let step16 = Counts(1.2 * hopg.a_counts / 15.0);
    let centre = CountPoint::from_counts(atom.x.value() + 0.3 * step16.value(), atom.y.value());
    let segment = segment_map(&hopg, centre, step16, 16, noise, &mut rng);
    let config16 = DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step16.value(),
        ..DetectionConfig::default()
    };
    assert_eq!(detect(&segment, &config16).unwrap().features.len(), 1);
    c.bench_function("detect_segment_16x16", |b| {
        b.iter(|| detect(black_box(&segment), &config16).unwrap())
    });

    let step64 = Counts(4.0 * hopg.a_counts / 63.0);
    let aperture = segment_map(&hopg, atom, step64, 64, noise, &mut rng);
    let config64 = DetectionConfig {
        min_separation_px: 0.4 * hopg.a_counts / step64.value(),
        ..DetectionConfig::default()
    };
    let lcs = LcsConfig::hopg(spm_hal::NmPerCount(0.005));
    let found = detect(&aperture, &config64).unwrap();
    println!("aperture 64x64: {} features", found.features.len());
    c.bench_function("detect_aperture_64x64", |b| {
        b.iter(|| detect(black_box(&aperture), &config64).unwrap())
    });
    c.bench_function("recognise_aperture_64x64_with_lcs_and_lattice", |b| {
        b.iter(|| {
            let found = detect(black_box(&aperture), &config64).unwrap();
            let a = found.nearest_index(atom).unwrap();
            let t = lcs_with_vertex(&found.features, a, &lcs).unwrap();
            let l = lattice_vectors(&found.features, &LatticeConfig::default()).unwrap();
            (t.len(), l.vectors.len())
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);

//! Simulated pixels per second: a 256×256 HOPG scan with every effect on
//! (`SimConfig::room_temperature_tube`, random faults off so no scan fails).
//! Throughput is counted in recorded (forward) pixels; every line's retrace
//! is simulated too, so the simulator evaluates twice as many pixels.
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spm_hal::{CountPoint, Counts, Microscope, ScanRequest, Seconds};
use spm_sim::{SimConfig, Simulator};
use std::hint::black_box;

fn scan_256(c: &mut Criterion) {
    let config = SimConfig::room_temperature_tube().without_random_faults();
    let mut sim = Simulator::new(config).unwrap();
    let request = ScanRequest::centred_square(
        CountPoint::from_counts(1000.0, -2000.0),
        Counts(1.0),
        256,
        Seconds(2e-5),
    );
    let mut group = c.benchmark_group("spm-sim");
    group.throughput(Throughput::Elements(256 * 256));
    group.sample_size(30);
    group.bench_function("scan_256x256_hopg_all_effects", |b| {
        b.iter(|| black_box(sim.scan(black_box(&request)).unwrap()))
    });
    let mut with_backward = request.clone();
    with_backward.record_backward = true;
    group.bench_function("scan_256x256_hopg_all_effects_both_halves", |b| {
        b.iter(|| black_box(sim.scan(black_box(&with_backward)).unwrap()))
    });
    group.finish();
}

criterion_group!(benches, scan_256);
criterion_main!(benches);

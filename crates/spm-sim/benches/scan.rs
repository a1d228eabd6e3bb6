//! Simulated pixels per second: a 256×256 HOPG scan with every effect on
//! (`SimConfig::room_temperature_tube`, random faults off so no scan fails).
//! Throughput is counted in recorded (forward) pixels; every line's retrace
//! is simulated too (unrecorded retraces take the exact closed-form creep
//! fast path). The `_thread_cpu_time` variant measures the thread's CPU time
//! instead of wall time, for a per-core figure on a shared, loaded machine.
#![allow(clippy::unwrap_used)]

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spm_hal::{CountPoint, Counts, Microscope, ScanRequest, Seconds};
use spm_sim::{SimConfig, Simulator};
use std::hint::black_box;
use std::time::{Duration, Instant};

/// CPU time of the calling thread (Linux `/proc/thread-self/schedstat`, ns),
/// so that the figure is per core even on a loaded machine.
fn thread_cpu_time() -> Option<Duration> {
    let text = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = text.split_whitespace().next()?.parse().ok()?;
    Some(Duration::from_nanos(ns))
}

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
    group.bench_function("scan_256x256_hopg_all_effects_thread_cpu_time", |b| {
        b.iter_custom(|iters| {
            let wall = Instant::now();
            let cpu = thread_cpu_time();
            for _ in 0..iters {
                black_box(sim.scan(black_box(&request)).unwrap());
            }
            match (cpu, thread_cpu_time()) {
                (Some(a), Some(b)) => b.saturating_sub(a),
                _ => wall.elapsed(),
            }
        })
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

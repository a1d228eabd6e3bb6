//! Corrected coordinates + bilinear resampling of an N×N image (N = 2048, 4096), one thread and
//! all threads. Compare: Gwyddion's `gwy_data_field_sample_distorted` (bilinear, one thread)
//! takes about 74 ms for 2048² on this kind of machine (the resampling alone, given the map).
//! Peak memory of the same workload: `cargo run --release -p spm-correction --example
//! peak_memory`.
#![allow(clippy::unwrap_used, missing_docs)]

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use spm_correction::*;
use spm_hal::ScanDirection;

/// CPU time of the calling thread, ns (Linux `/proc/thread-self/schedstat`, first field): the
/// single-thread figure without the waits of a shared, loaded machine.
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(0)
}

fn bench(c: &mut Criterion) {
    let field = bench_support::realistic_field().unwrap();
    let mut group = c.benchmark_group("correct_and_resample_bilinear");
    group.sample_size(10);
    for n in [2048usize, 4096] {
        let geometry = bench_support::benchmark_geometry(n).unwrap();
        let img = bench_support::benchmark_image(n);
        group.throughput(Throughput::Elements((n * n) as u64));
        for (name, par) in [
            ("1 thread", Parallelism::Sequential),
            ("all threads", Parallelism::AllCores),
        ] {
            group.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
                b.iter(|| {
                    let map = correct_raster(
                        &field,
                        &geometry,
                        ScanDirection::Direct,
                        &Integration::default(),
                        par,
                    )
                    .unwrap();
                    let grid = OutputGrid::covering(&map, None).unwrap();
                    resample(&img, &map, &grid, Interpolation::Bilinear, par).unwrap()
                });
            });
        }
        for (name, par) in [
            ("fused, 1 thread", Parallelism::Sequential),
            ("fused, all threads", Parallelism::AllCores),
        ] {
            group.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
                b.iter(|| {
                    correct_and_resample(
                        &field,
                        &geometry,
                        ScanDirection::Direct,
                        &Integration::default(),
                        &img,
                        None,
                        Interpolation::Bilinear,
                        par,
                    )
                    .unwrap()
                });
            });
        }
        group.bench_with_input(
            BenchmarkId::new("fused, 1 thread, thread CPU time, reused buffer", n),
            &n,
            |b, _| {
                let mut out = Vec::new();
                b.iter_custom(|iters| {
                    let t0 = thread_cpu_ns();
                    for _ in 0..iters {
                        correct_and_resample_into(
                            &field,
                            &geometry,
                            ScanDirection::Direct,
                            &Integration::default(),
                            &img,
                            None,
                            Interpolation::Bilinear,
                            Parallelism::Sequential,
                            &mut out,
                        )
                        .unwrap();
                        std::hint::black_box(&out);
                    }
                    std::time::Duration::from_nanos(thread_cpu_ns().saturating_sub(t0))
                });
            },
        );
        group.bench_with_input(
            BenchmarkId::new("fused, 1 thread, thread CPU time", n),
            &n,
            |b, _| {
                b.iter_custom(|iters| {
                    let t0 = thread_cpu_ns();
                    for _ in 0..iters {
                        std::hint::black_box(
                            correct_and_resample(
                                &field,
                                &geometry,
                                ScanDirection::Direct,
                                &Integration::default(),
                                &img,
                                None,
                                Interpolation::Bilinear,
                                Parallelism::Sequential,
                            )
                            .unwrap(),
                        );
                    }
                    std::time::Duration::from_nanos(thread_cpu_ns().saturating_sub(t0))
                });
            },
        );
        // Thread CPU time (immune to other load on a shared machine), fresh buffers and
        // reused buffers (Gwyddion's sample_distorted writes into an existing field).
        for reuse in [false, true] {
            let name = if reuse {
                "1 thread, thread CPU time, reused buffers"
            } else {
                "1 thread, thread CPU time"
            };
            group.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
                let mut x_buffer = Vec::new();
                let mut out = Vec::new();
                b.iter_custom(|iters| {
                    let t0 = thread_cpu_ns();
                    for _ in 0..iters {
                        let map = correct_raster_reusing(
                            &field,
                            &geometry,
                            ScanDirection::Direct,
                            &Integration::default(),
                            Parallelism::Sequential,
                            std::mem::take(&mut x_buffer),
                        )
                        .unwrap();
                        let grid = OutputGrid::covering(&map, None).unwrap();
                        out.resize(grid.columns * grid.rows, 0.0);
                        resample_into(
                            &img,
                            &map,
                            &grid,
                            Interpolation::Bilinear,
                            Parallelism::Sequential,
                            &mut out,
                        )
                        .unwrap();
                        std::hint::black_box(&out);
                        if reuse {
                            x_buffer = map.into_parts().0;
                        } else {
                            out = Vec::new();
                        }
                    }
                    std::time::Duration::from_nanos(thread_cpu_ns().saturating_sub(t0))
                });
            });
        }
        // The parts, one thread.
        let map = correct_raster(
            &field,
            &geometry,
            ScanDirection::Direct,
            &Integration::default(),
            Parallelism::Sequential,
        )
        .unwrap();
        let grid = OutputGrid::covering(&map, None).unwrap();
        group.bench_with_input(
            BenchmarkId::new("coordinates only, 1 thread", n),
            &n,
            |b, _| {
                b.iter(|| {
                    correct_raster(
                        &field,
                        &geometry,
                        ScanDirection::Direct,
                        &Integration::default(),
                        Parallelism::Sequential,
                    )
                    .unwrap()
                });
            },
        );
        group.bench_with_input(
            BenchmarkId::new("resample only, 1 thread", n),
            &n,
            |b, _| {
                b.iter(|| {
                    resample(
                        &img,
                        &map,
                        &grid,
                        Interpolation::Bilinear,
                        Parallelism::Sequential,
                    )
                    .unwrap()
                });
            },
        );
        if n == 2048 {
            group.bench_with_input(
                BenchmarkId::new("resample only, Catmull-Rom, 1 thread", n),
                &n,
                |b, _| {
                    b.iter(|| {
                        resample(
                            &img,
                            &map,
                            &grid,
                            Interpolation::CatmullRom,
                            Parallelism::Sequential,
                        )
                        .unwrap()
                    });
                },
            );
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

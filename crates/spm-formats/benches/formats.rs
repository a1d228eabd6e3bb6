//! Reader and writer throughput on the measured files.
//!
//! `cargo bench -p spm-formats` (needs ../shared/data beside the project, or
//! SPMCAL_SHARED_DATA).

#![allow(clippy::unwrap_used)]

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spm_formats::{Direction, encode_gsf, read_bytes};

fn measured(rel: &str) -> Vec<u8> {
    let dir = std::env::var_os("SPMCAL_SHARED_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"));
    std::fs::read(dir.join("measured").join(rel)).unwrap()
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("read");
    for (name, rel) in [
        ("sxm", "si7x7-nanonis/Si_7x7_051.sxm"),
        (
            "sm4",
            "graphite-rhk-9k/dI-dV_9K_ABC6_2020_07_02_08_50_47_967.sm4",
        ),
        ("iso28600", "hopg-terrace-iso28600/graphiteterrace.spm"),
        ("raw", "si7x7-raw/image_with_step_edge.dat"),
    ] {
        let bytes = measured(rel);
        let path = Path::new(rel);
        g.throughput(Throughput::Bytes(bytes.len() as u64));
        g.bench_function(name, |b| {
            b.iter(|| read_bytes(black_box(&bytes), path).unwrap())
        });
    }
    g.finish();

    let f = read_bytes(
        &measured("si7x7-nanonis/Si_7x7_051.sxm"),
        Path::new("x.sxm"),
    )
    .unwrap();
    let z = f.channel("Z", Direction::Forward).unwrap();
    let gsf = encode_gsf(z, &[]).unwrap();
    let mut g = c.benchmark_group("gsf");
    g.throughput(Throughput::Elements((z.nx() * z.ny()) as u64));
    g.bench_function("encode_256", |b| {
        b.iter(|| encode_gsf(black_box(z), &[]).unwrap())
    });
    g.bench_function("read_256", |b| {
        b.iter(|| read_bytes(black_box(&gsf), Path::new("x.gsf")).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

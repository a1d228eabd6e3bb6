//! `spmcal correct`'s library path on a 2048² frame: the static field against the raster's
//! dynamics (the file's own trace replayed through a 47-operator PI hysteresis per axis and a
//! 19-element creep law, 3 per decade over 10 ms … 10⁴ s, the size the default job
//! identifies). Issue 23's target: the dynamic correction within 2× the static one. Both run
//! in this one group, on every core, so their ratio is measured in one run.
#![allow(clippy::unwrap_used, missing_docs)]

use std::path::PathBuf;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use spm_apply::{ApplyOptions, correct_file};
use spm_correction::hysteresis::{
    CreepParameters, DYNAMICS_FORMAT, DYNAMICS_FORMAT_VERSION, DynamicsIdentification,
    PlayHysteresis, ScannerDynamics,
};
use spm_correction::{
    CountRegion, CountsConvention, FittedSurface, PlaneSurfaces, Provenance, SurfaceSet,
};
use spm_formats::{Channel, Direction, Format, SpmFile};
use spm_regression::{Polynomial2, n_terms};

/// A cubic field over ±30 000 counts with a realistic 4 % variation.
fn field() -> SurfaceSet {
    let surface = |base: f64, seed: f64| {
        let c = (0..n_terms(3))
            .map(|k| {
                if k == 0 {
                    base
                } else {
                    base * 0.04 * ((k as f64 + seed) * 1.3).sin()
                }
            })
            .collect();
        FittedSurface::new(
            Polynomial2::new(3, (0.0, 0.0), (30_000.0, 30_000.0), c).unwrap(),
            base * 0.001,
        )
    };
    let plane = PlaneSurfaces {
        z_counts: 0.0,
        n_records: 300,
        kx_nm_per_count: surface(0.020, 0.0),
        ky_nm_per_count: surface(0.019, 1.0),
        alpha_rad: surface(0.02, 2.0),
        kyx_nm_per_count: surface(0.0004, 3.0),
        kyy_nm_per_count: surface(0.019, 4.0),
        kz_nm_per_count: None,
        bowl_z_counts: None,
        calibrated_region_counts: CountRegion::bounding(
            &[-30_000.0, 30_000.0],
            &[-30_000.0, 30_000.0],
            0.0,
        ),
        form: spm_correction::SurfaceForm::Independent,
    };
    SurfaceSet::new(
        Provenance {
            scanner_id: "bench-scanner".into(),
            n_records: 300,
            nominal_nm_per_count: Some(0.02),
            counts_convention: Some(CountsConvention::CentredSigned),
            ..Provenance::default()
        },
        vec![plane],
    )
    .unwrap()
}

fn dynamics() -> ScannerDynamics {
    let thresholds: Vec<f64> = (0..47).map(|k| 16.0 * 1.16f64.powi(k)).collect();
    ScannerDynamics {
        format: DYNAMICS_FORMAT.to_owned(),
        version: DYNAMICS_FORMAT_VERSION,
        hysteresis_x: PlayHysteresis {
            weights: vec![0.002; thresholds.len()],
            thresholds_counts: thresholds.clone(),
        },
        // The slow axis's loop, as the counter-scanned pairs identify it (stop 39).
        hysteresis_y: PlayHysteresis {
            weights: vec![0.0025; thresholds.len()],
            thresholds_counts: thresholds,
        },
        creep: CreepParameters {
            weight: 0.0055,
            min_time_constant_s: 0.01,
            max_time_constant_s: 1e4,
            elements_per_decade: 3,
        },
        identification: DynamicsIdentification::default(),
    }
}

/// A 2048² frame of 8190 counts (164 nm at 0.02 nm/count) with a 0.2 s line time.
fn frame(n: usize) -> SpmFile {
    let data: Vec<f64> = (0..n * n)
        .map(|i| ((i % n) as f64 * 0.7).sin() * 1e-10 + ((i / n) as f64 * 0.3).cos() * 5e-11)
        .collect();
    let side_nm = 8190.0 * 0.02;
    let channel = Channel::new("Z", Direction::Forward, "m", n, n, data)
        .unwrap()
        .with_size_nm(side_nm, side_nm)
        .with_center_nm(0.0, 0.0);
    SpmFile {
        source: PathBuf::from("bench.gsf"),
        format: Format::Gsf,
        channels: vec![channel],
        header: Default::default(),
        scan_dir: None,
        line_time_s: Some(0.2),
        recorded: None,
    }
}

fn bench(c: &mut Criterion) {
    let n = 2048;
    let file = frame(n);
    let options = ApplyOptions {
        nominal_nm_per_count: Some(0.02),
        ..ApplyOptions::default()
    };
    let static_set = field();
    let mut dynamic_set = field();
    dynamic_set.dynamics = Some(dynamics());
    let mut group = c.benchmark_group("correct_file_2048");
    group.sample_size(10);
    for (name, set) in [("static", &static_set), ("dynamics (raster)", &dynamic_set)] {
        group.bench_with_input(BenchmarkId::new(name, n), &n, |b, _| {
            b.iter(|| correct_file(&file, set, &options).unwrap());
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);

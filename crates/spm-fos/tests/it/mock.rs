//! FOS operations driven through the scripted mock backend: synthetic HOPG
//! surfaces with imposed drift, and injected faults.
#![allow(clippy::unwrap_used)]

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use spm_features::{DetectionConfig, LcsConfig};
use spm_fos::{
    ApertureParams, AttachOutcome, AttachParams, CounterScanParams, Decision, FosError,
    MonitorParams, Motion, Raster, SkipOutcome, SkipParams, aperture, attach, counter_scan, skip,
};
use spm_hal::mock::{Expectation, Operation, ScriptedMicroscope};
use spm_hal::{CountPoint, CountVector, CountVelocity, Counts, ErrorKind, Seconds};

const NM_PER_COUNT: f64 = 0.005;
/// HOPG lattice constant in counts.
const A: f64 = 0.2461 / NM_PER_COUNT;
const CORRUGATION_Z: f64 = 30.0;

/// Three-cosine HOPG, atoms at n·a1 + m·a2 (a1 = a·(1, 0), a2 = a·(½, √3/2)).
fn hopg(x: f64, y: f64) -> f64 {
    let g = 2.0 * std::f64::consts::PI / A;
    let k = [
        (g, -g / 3f64.sqrt()),
        (0.0, 2.0 * g / 3f64.sqrt()),
        (-g, -g / 3f64.sqrt()),
    ];
    let s: f64 = k.iter().map(|k| (k.0 * x + k.1 * y).cos()).sum();
    CORRUGATION_Z / 4.5 * (s + 1.5)
}

fn atom(n: i32, m: i32) -> CountPoint {
    let (n, m) = (f64::from(n), f64::from(m));
    CountPoint::from_counts(A * (n + 0.5 * m), A * 3f64.sqrt() / 2.0 * m)
}

/// A surface displaced by `drift(t)` (counts) with white noise σ = `noise`.
fn surface(
    drift: impl Fn(f64) -> (f64, f64) + Send + 'static,
    noise: f64,
    seed: u64,
) -> impl FnMut(CountPoint, Seconds) -> Counts + Send + 'static {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let normal = Normal::new(0.0, noise.max(1e-300)).unwrap();
    move |p, t| {
        let (dx, dy) = drift(t.value());
        let n = if noise > 0.0 {
            normal.sample(&mut rng)
        } else {
            0.0
        };
        Counts(hopg(p.x.value() - dx, p.y.value() - dy) + n)
    }
}

fn constant(vx: f64, vy: f64) -> impl Fn(f64) -> (f64, f64) + Send + Clone + 'static {
    move |t| (vx * t, vy * t)
}

fn segment() -> Raster {
    Raster {
        pixels: 16,
        pixel_step_counts: 1.2 * A / 15.0,
        pixel_dwell_s: 2e-4,
    }
}

fn detection(step: f64) -> DetectionConfig {
    DetectionConfig {
        min_separation_px: 0.4 * A / step,
        ..DetectionConfig::default()
    }
}

fn attach_params(limit: f64, timeout_s: f64) -> AttachParams {
    let first = Raster {
        pixels: 32,
        pixel_step_counts: 2.5 * A / 31.0,
        pixel_dwell_s: 2e-4,
    };
    let mut p = AttachParams::new(first, segment(), limit, timeout_s);
    p.first_detection = detection(first.pixel_step_counts);
    p.segment_detection = detection(segment().pixel_step_counts);
    p
}

fn mock() -> ScriptedMicroscope {
    ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
        .lenient_moves_and_waits(true)
}

fn scans(
    m: &mut ScriptedMicroscope,
    n: usize,
    drift: impl Fn(f64) -> (f64, f64) + Send + Clone + 'static,
    noise: f64,
) {
    for i in 0..n {
        m.expect(Expectation::scan(surface(drift.clone(), noise, i as u64)));
    }
}

/// Attach near atom (2, 1) with drift (vx, vy) counts/s and a limit; checks
/// the outcome kind and the scans used.
fn check_attach(
    v: (f64, f64),
    limit: f64,
    timeout_s: f64,
    scripted: usize,
    expected: (&str, usize),
) {
    let mut m = mock();
    scans(&mut m, scripted, constant(v.0, v.1), CORRUGATION_Z / 20.0);
    let near = atom(2, 1) + CountVector::from_counts(0.2 * A, -0.15 * A);
    let report = attach(&mut m, near, &attach_params(limit, timeout_s)).unwrap();
    let kind = match report.outcome {
        AttachOutcome::Settled { .. } => "settled",
        AttachOutcome::TimedOut { .. } => "timed out",
        AttachOutcome::FeatureLost { .. } => "lost",
    };
    assert_eq!(
        (kind, scripted - m.remaining()),
        expected,
        "{v:?}: {report:?}"
    );
    // The held feature is the atom nearest the starting point, seen drifted.
    let f = report.feature.unwrap();
    let t = f.time.value();
    let truth = atom(2, 1) + CountVector::from_counts(v.0 * t, v.1 * t);
    assert!(f.position.distance(truth).value() < 0.05 * A, "{f:?}");
    if kind == "settled" {
        let est = report.velocity().unwrap();
        assert!(est.norm_counts_per_s() < limit);
    }
}

#[test]
fn attach_settles_or_times_out_by_the_drift_speed() {
    // Slow drift (2 counts/s = 0.1 Å/s) under a 8 counts/s limit: first scan
    // + 3 segments (three consecutive estimates below the limit).
    check_attach((2.0, -1.0), 8.0, 5.0, 4, ("settled", 4));
    // Fast drift (20 counts/s = 1 Å/s) never settles: times out, the feature held.
    check_attach((20.0, 5.0), 8.0, 1.0, 40, ("timed out", 5));
}

#[test]
fn attach_measures_the_drift_velocity() {
    let mut m = mock();
    let v = (6.0, -4.0);
    scans(&mut m, 12, constant(v.0, v.1), CORRUGATION_Z / 20.0);
    let report = attach(&mut m, atom(0, 0), &attach_params(1.0, 1.0)).unwrap();
    assert!(matches!(report.outcome, AttachOutcome::TimedOut { .. }));
    let est = report.velocity().unwrap();
    let error = (est.x_counts_per_s - v.0).hypot(est.y_counts_per_s - v.1);
    assert!(error < 1.0, "estimate {est:?}");
}

#[test]
fn attach_reports_a_lost_feature_and_typed_faults() {
    // A flat surface: nothing to capture.
    let mut m = mock();
    m.expect(Expectation::scan(|_, _| Counts(0.0)));
    let report = attach(&mut m, atom(0, 0), &attach_params(8.0, 5.0)).unwrap();
    assert!(matches!(report.outcome, AttachOutcome::FeatureLost { .. }));
    m.done().unwrap();

    // The surface vanishes after the first scan (tip change): lost, no panic.
    let mut m = mock();
    scans(&mut m, 1, constant(0.0, 0.0), 0.5);
    m.expect(Expectation::scan(|_, _| Counts(0.0)));
    let report = attach(&mut m, atom(0, 0), &attach_params(8.0, 5.0)).unwrap();
    assert!(matches!(report.outcome, AttachOutcome::FeatureLost { .. }));
    m.done().unwrap();

    // Injected faults come back as typed errors with the backend's kind.
    for (operation, kind) in [
        (Operation::Scan, ErrorKind::Timeout),
        (Operation::Scan, ErrorKind::FeedbackLost),
        (Operation::MoveTo, ErrorKind::OutOfRange),
    ] {
        let mut m = mock();
        scans(&mut m, 1, constant(0.0, 0.0), 0.5);
        m.expect(Expectation::fault(operation, kind));
        let error = attach(&mut m, atom(0, 0), &attach_params(8.0, 5.0)).unwrap_err();
        assert_eq!(error.instrument_kind(), Some(kind), "{error}");
        assert!(matches!(error, FosError::Instrument(_)));
        m.done().unwrap();
    }

    // Invalid parameters are typed errors before any instrument call.
    let mut m = mock();
    let mut params = attach_params(8.0, 5.0);
    params.segment.pixel_dwell_s = f64::NAN;
    assert!(matches!(
        attach(&mut m, atom(0, 0), &params),
        Err(FosError::InvalidParameter {
            field: "pixel_dwell_s",
            ..
        })
    ));
}

fn skip_params(cycles: usize) -> SkipParams {
    let mut p = SkipParams::new(segment(), MonitorParams::new(2.0, 40.0, cycles));
    p.detection = detection(segment().pixel_step_counts);
    p.motion = Motion {
        speed_counts_per_s: 2000.0,
        settle_s: 0.01,
    };
    p
}

#[test]
fn skipping_cancels_constant_drift() {
    let ab_true = atom(1, 0) - atom(0, 0);
    for v in [(0.0, 0.0), (8.0, 0.0), (-5.0, 6.0)] {
        let mut m = mock();
        scans(&mut m, 1 + 2 * 4, constant(v.0, v.1), 0.0);
        let drift = CountVelocity {
            x_counts_per_s: v.0,
            y_counts_per_s: v.1,
        };
        let guess = ab_true + CountVector::from_counts(0.1 * A, -0.08 * A);
        let report = skip(
            &mut m,
            atom(0, 0),
            Seconds(0.0),
            guess,
            drift,
            &skip_params(4),
        )
        .unwrap();
        m.done().unwrap();
        assert_eq!(report.outcome, SkipOutcome::Completed);
        assert_eq!(report.kept.len(), 4);
        let vector = report.vector.unwrap();
        let error = (vector - ab_true).norm().value();
        // Noise-free: only the Gaussian-model bias of the localiser remains.
        assert!(error < 0.01 * A, "drift {v:?}: error {error} counts");
        // The forward difference alone carries the drift.
        let forward = report.cycles[0].cycle.forward;
        let forward_error = (forward - ab_true).norm().value();
        if v != (0.0, 0.0) {
            assert!(forward_error > 10.0 * error, "{forward_error} vs {error}");
        }
        let vel = report.drift;
        assert!((vel.x_counts_per_s - v.0).abs() < 0.5 && (vel.y_counts_per_s - v.1).abs() < 0.5);
    }
}

#[test]
fn a_drift_burst_spoils_a_cycle_which_is_discarded() {
    let ab_true = atom(1, 0) - atom(0, 0);
    let v = 4.0;
    // A burst of +40 counts/s along y between 0.7 s and 0.8 s.
    let drift = move |t: f64| {
        let burst = 40.0 * ((t.min(0.8) - 0.7).max(0.0));
        (v * t, burst)
    };
    let mut m = mock();
    let scripted = 1 + 2 * 12;
    for i in 0..scripted {
        m.expect(Expectation::scan(surface(
            drift,
            CORRUGATION_Z / 20.0,
            i as u64,
        )));
    }
    let start = CountVelocity {
        x_counts_per_s: v,
        y_counts_per_s: 0.0,
    };
    let report = skip(
        &mut m,
        atom(0, 0),
        Seconds(0.0),
        ab_true,
        start,
        &skip_params(4),
    )
    .unwrap();
    assert_eq!(report.outcome, SkipOutcome::Completed);
    assert!(
        report.discarded >= 1,
        "{:?}",
        report.cycles.iter().map(|c| c.decision).collect::<Vec<_>>()
    );
    assert!(report.idle >= 2);
    assert!(
        report
            .cycles
            .iter()
            .any(|c| matches!(c.decision, Decision::Discard(_)))
    );
    // The kept cycles do not include the spoiled one, and the result is clean.
    for &i in &report.kept {
        assert!(report.cycles[i].decision.keeps_cycle());
    }
    let error = (report.vector.unwrap() - ab_true).norm().value();
    assert!(error < 0.02 * A, "error {error}");
}

#[test]
fn skipping_faults_are_typed_errors() {
    let ab_true = atom(1, 0) - atom(0, 0);
    let mut m = mock();
    scans(&mut m, 2, constant(0.0, 0.0), 0.5);
    m.expect(Expectation::fault(
        Operation::Scan,
        ErrorKind::Communication,
    ));
    let error = skip(
        &mut m,
        atom(0, 0),
        Seconds(0.0),
        ab_true,
        CountVelocity::ZERO,
        &skip_params(4),
    )
    .unwrap_err();
    assert_eq!(error.instrument_kind(), Some(ErrorKind::Communication));
    assert!(error.is_transient());
    m.done().unwrap();

    // B is not where it was predicted (a wrong A→B): the feature is lost.
    let mut m = mock();
    scans(&mut m, 1, constant(0.0, 0.0), 0.5);
    m.expect(Expectation::scan(|_, _| Counts(0.0)));
    let error = skip(
        &mut m,
        atom(0, 0),
        Seconds(0.0),
        ab_true,
        CountVelocity::ZERO,
        &skip_params(4),
    )
    .unwrap_err();
    assert!(matches!(error, FosError::FeatureLost { .. }), "{error}");
}

#[test]
fn aperture_finds_the_lcs_around_a() {
    let mut m = mock();
    scans(&mut m, 1, constant(0.0, 0.0), CORRUGATION_Z / 10.0);
    let raster = Raster {
        pixels: 64,
        pixel_step_counts: 4.0 * A / 63.0,
        pixel_dwell_s: 1e-4,
    };
    let params = ApertureParams {
        raster,
        detection: detection(raster.pixel_step_counts),
        lcs: LcsConfig::hopg(spm_hal::NmPerCount(NM_PER_COUNT * 0.9)),
        motion: Motion::TYPICAL,
    };
    let report = aperture(&mut m, atom(1, 1), &params).unwrap();
    m.done().unwrap();
    let a = report.feature(report.a.unwrap()).unwrap();
    assert!(a.position.distance(atom(1, 1)).value() < 0.05 * A);
    let lcs = report.lcs.unwrap();
    assert!((lcs.ab.norm().value() / A - 1.0).abs() < 0.05);
    assert!((lcs.ac.norm().value() / A - 1.0).abs() < 0.05);
    assert_eq!(report.neighbours.len(), 6);
}

#[test]
fn counter_scanning_recovers_the_drift() {
    let v = (6.0, -3.0);
    let mut m = mock();
    scans(&mut m, 2, constant(v.0, v.1), CORRUGATION_Z / 20.0);
    let raster = Raster {
        pixels: 48,
        pixel_step_counts: 3.0 * A / 47.0,
        pixel_dwell_s: 2e-4,
    };
    let params = CounterScanParams {
        raster,
        detection: detection(raster.pixel_step_counts),
        motion: Motion::TYPICAL,
        match_radius_counts: 0.3 * A,
        drift_prior: CountVelocity::ZERO,
    };
    let report = counter_scan(&mut m, atom(1, 1), &params).unwrap();
    m.done().unwrap();
    let est = report.velocity;
    let rel = (est.x_counts_per_s - v.0).hypot(est.y_counts_per_s - v.1) / v.0.hypot(v.1);
    assert!(rel < 0.05, "estimate {est:?}, relative error {rel}");
    assert!(report.common.len() >= 4);
    // Drift-free positions form the true lattice: the A→B vector of two
    // common neighbours is exact to within the localisation error.
    let t0 = report.reference_time.value();
    for c in &report.common {
        let truth_at_t0 = CountPoint::from_counts(
            c.drift_free.x.value() - v.0 * t0,
            c.drift_free.y.value() - v.1 * t0,
        );
        // Nearest lattice atom to the drift-free position (shifted back to t = 0).
        let mut best = f64::INFINITY;
        for n in -3..6 {
            for mm in -3..6 {
                best = best.min(truth_at_t0.distance(atom(n, mm)).value());
            }
        }
        assert!(
            best < 0.03 * A,
            "drift-free position off the lattice by {best}"
        );
    }
}

/// Mean A→B over `runs` skipping runs at drift `v` (counts/s along x and y),
/// each with its own noise seeds (the same for every drift).
fn skipping_error(v: (f64, f64), runs: u64, cycles: usize) -> f64 {
    let ab_true = atom(0, 1) - atom(0, 0);
    let mut sum_sq = 0.0;
    for run in 0..runs {
        let mut m = mock();
        // Enough scans for a few spoiled and idle cycles too.
        for i in 0..(1 + 2 * (cycles + 8)) as u64 {
            m.expect(Expectation::scan(surface(
                constant(v.0, v.1),
                CORRUGATION_Z / 10.0,
                1000 * run + i,
            )));
        }
        let drift = CountVelocity {
            x_counts_per_s: v.0,
            y_counts_per_s: v.1,
        };
        let mut params = skip_params(cycles);
        // Per-cycle velocity noise at SNR 10 is ≈ 2 counts/s.
        params.monitor.velocity_tolerance_counts_per_s = 8.0;
        let report = skip(&mut m, atom(0, 0), Seconds(0.0), ab_true, drift, &params).unwrap();
        assert_eq!(report.outcome, SkipOutcome::Completed);
        let e = report.vector.unwrap() - ab_true;
        sum_sq += e.dot_counts_squared(e);
    }
    (sum_sq / runs as f64).sqrt()
}

/// A→B (B at 60°, a line-separated neighbour) from one 64×64 aperture scan.
fn single_scan_error(v: (f64, f64), seed: u64) -> f64 {
    let ab_true = atom(0, 1) - atom(0, 0);
    let mut m = mock();
    m.expect(Expectation::scan(surface(
        constant(v.0, v.1),
        CORRUGATION_Z / 10.0,
        seed,
    )));
    let raster = Raster {
        pixels: 64,
        pixel_step_counts: 4.0 * A / 63.0,
        pixel_dwell_s: 2e-4,
    };
    let params = ApertureParams {
        raster,
        detection: detection(raster.pixel_step_counts),
        lcs: LcsConfig::hopg(spm_hal::NmPerCount(NM_PER_COUNT)),
        motion: Motion::TYPICAL,
    };
    let report = aperture(&mut m, atom(0, 0), &params).unwrap();
    let a = report.feature(report.a.unwrap()).unwrap().position;
    let b = report
        .recognised
        .detection
        .nearest(atom(0, 1))
        .unwrap()
        .position;
    ((b - a) - ab_true).norm().value()
}

#[test]
fn skipping_is_drift_insensitive_where_a_single_scan_is_not() {
    // 0.4 Å/s = 0.04 nm/s = 8 counts/s at 0.005 nm/count, diagonal.
    let fast = (8.0 / 2f64.sqrt(), 8.0 / 2f64.sqrt());
    let still = skipping_error((0.0, 0.0), 6, 4);
    let drifting = skipping_error(fast, 6, 4);
    let single_still = single_scan_error((0.0, 0.0), 77);
    let single = single_scan_error(fast, 77);
    println!(
        "skipping error: {still:.4} counts at rest, {drifting:.4} at 0.4 Å/s; \
         single scan: {single_still:.4} at rest, {single:.4} at 0.4 Å/s"
    );
    assert!(drifting <= 1.2 * still, "{drifting} > 1.2 × {still}");
    assert!(single >= 5.0 * drifting, "{single} < 5 × {drifting}");
}

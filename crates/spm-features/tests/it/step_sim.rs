//! Step heights on scans of the simulator (spm-sim, dev-dependency only) against the
//! oracle's true Kz: a monatomic HOPG step (0.3354 nm) scanned with every effect on
//! (drift, creep, hysteresis, noise, quantisation, a nonlinear Z manipulator, the bowl).
#![allow(clippy::unwrap_used)]

use spm_features::{StepConfig, StepRejection, measure_step, measure_step_pair};
use spm_hal::{CountPoint, Counts, Microscope, NmPoint, ScanRequest, Seconds, TraceHalf};
use spm_sim::{SimConfig, Simulator, StepEdgeConfig, SurfaceConfig, ZManipulatorConfig};

const STEP_NM: f64 = 0.3354;

fn simulator(edges: Vec<StepEdgeConfig>) -> Simulator {
    let mut c = SimConfig::room_temperature_tube().without_random_faults();
    c.scanner.z_manipulator = Some(ZManipulatorConfig {
        quadratic: 0.04,
        cubic: 0.02,
        lateral_gradient_x: 0.015,
        lateral_gradient_y: -0.01,
        lateral_radial: 0.02,
        ripple_fraction: 0.0,
        ripple_period_counts: 16384.0,
        kz_drift_per_hour: 0.0,
    });
    c.scanner.bowl_curvature_per_nm = 2e-6;
    if let SurfaceConfig::Hopg(h) = &mut c.surface {
        h.steps = edges;
        h.domains.clear();
    }
    Simulator::new(c).unwrap()
}

fn edge(x_nm: f64, direction_deg: f64) -> StepEdgeConfig {
    StepEdgeConfig {
        point_x_nm: x_nm,
        point_y_nm: 0.0,
        direction_deg,
        width_nm: 0.2,
    }
}

/// Scans a 30 nm window centred on sample point `at` (forward and backward traces).
fn scan(sim: &mut Simulator, at: NmPoint) -> (spm_hal::HeightMap, spm_hal::HeightMap, CountPoint) {
    // Go there first: the hysteresis state of the arrival decides where `at` appears.
    for _ in 0..2 {
        let target = sim.oracle().commanded_for_sample_point(at).unwrap();
        sim.move_to(spm_hal::MoveRequest {
            target,
            speed: spm_hal::CountsPerSecond(20000.0),
            settle: Seconds(0.5),
        })
        .unwrap();
    }
    let centre = sim.oracle().commanded_for_sample_point(at).unwrap();
    let request = ScanRequest {
        record_backward: true,
        ..ScanRequest::centred_square(centre, Counts(1500.0 / 95.0), 96, Seconds(1e-4))
    };
    let request = ScanRequest {
        lines: 48,
        ..request
    };
    let frame = sim.scan(&request).unwrap();
    (
        frame.height_map(TraceHalf::Forward).unwrap(),
        frame.height_map(TraceHalf::Backward).unwrap(),
        centre,
    )
}

fn config() -> StepConfig {
    // Nominal Kz 0.004 nm/count; the edge band ±3 nm ≈ ±9.5 pixels.
    StepConfig::monatomic(STEP_NM / 0.004, 9.5)
}

#[test]
fn kz_from_a_step_matches_the_oracle_across_the_field() {
    let xs = [-500.0, 0.0, 450.0];
    let mut sim = simulator(xs.iter().map(|&x| edge(x, 95.0)).collect());
    for (k, &x) in xs.iter().enumerate() {
        let y = -400.0 + 400.0 * k as f64;
        // The edge through (x, 0) at 95° crosses this y at x + y·cot 95°.
        let x_at = x + y / 95f64.to_radians().tan();
        let (fwd, bwd, centre) = scan(&mut sim, NmPoint::from_nm(x_at, y));
        let m = measure_step_pair(&fwd, &bwd, &config()).unwrap();
        let truth = sim.oracle().vertical().kz_now(centre).value();
        let kz = STEP_NM / m.height_counts;
        let error = kz / truth - 1.0;
        assert!(
            error.abs() < 0.003,
            "x = {x} nm: Kz {kz} vs {truth} ({:.3} %, u {:.3} %)",
            100.0 * error,
            100.0 * m.u_height_counts / m.height_counts
        );
        assert!(m.u_height_counts / m.height_counts < 0.004, "{m:?}");
    }
}

#[test]
fn a_flat_terrace_and_a_double_step_are_rejected() {
    // Two edges 0.8 nm apart: one apparent step of two layers.
    let mut sim = simulator(vec![edge(0.0, 95.0), edge(0.8, 95.0)]);
    let (fwd, _, _) = scan(&mut sim, NmPoint::from_nm(0.0, 0.0));
    let r = measure_step(&fwd, &config()).unwrap_err();
    assert!(
        matches!(r, StepRejection::DoubleStep { layers: 2, .. }),
        "{r}"
    );
    let (fwd, _, _) = scan(&mut sim, NmPoint::from_nm(200.0, 0.0));
    let r = measure_step(&fwd, &config()).unwrap_err();
    assert!(matches!(r, StepRejection::NoEdge { .. }), "{r}");
}

//! Every injected fault kind surfaces as the right `ErrorKind` or its
//! documented data effect, is logged with its time, and nothing panics.
#![allow(clippy::unwrap_used, clippy::needless_range_loop)]

use spm_hal::{
    CountPoint, Counts, Error, ErrorKind, Microscope, MoveRequest, NmPoint, NmVelocity,
    ScanRequest, Seconds, TraceHalf,
};
use spm_sim::{FaultEventKind, FaultKind, FaultTrigger, Operation, SimConfig, Simulator};

fn request() -> ScanRequest {
    ScanRequest::centred_square(
        CountPoint::from_counts(100.0, 100.0),
        Counts(1.0),
        16,
        Seconds(1e-4),
    )
}

#[test]
fn call_faults_return_the_matching_error_kind() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    sim.schedule_fault(FaultTrigger::NextCall(Operation::Scan), FaultKind::Timeout);
    let t0 = sim.now().unwrap();
    let e = sim.scan(&request()).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Timeout);
    // A timeout consumes its duration.
    assert!((sim.now().unwrap() - t0).value() >= 1.0);

    sim.schedule_fault(
        FaultTrigger::NextCall(Operation::MoveTo),
        FaultKind::Communication,
    );
    let before = sim.position().unwrap();
    let e = sim
        .move_to(MoveRequest {
            target: CountPoint::from_counts(500.0, 0.0),
            speed: spm_hal::CountsPerSecond(1e4),
            settle: Seconds(0.0),
        })
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Communication);
    assert_eq!(
        sim.position().unwrap(),
        before,
        "a failed call does nothing"
    );

    sim.schedule_fault(
        FaultTrigger::NextCall(Operation::ZPosition),
        FaultKind::FeedbackLost,
    );
    assert_eq!(
        sim.z_position().unwrap_err().kind(),
        ErrorKind::FeedbackLost
    );
    // The next call works again.
    assert!(sim.z_position().is_ok());

    let kinds: Vec<_> = sim.oracle().fault_log().iter().map(|e| e.kind).collect();
    assert_eq!(
        kinds,
        [
            FaultEventKind::Timeout,
            FaultEventKind::Communication,
            FaultEventKind::FeedbackLost
        ]
    );
    assert!(sim.oracle().fault_log().iter().all(|e| e.scheduled));
}

#[test]
fn feedback_lost_during_a_scan_stops_it_there() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    let start = sim.now().unwrap();
    // The scan (16 lines × 32 px × 0.1 ms ≈ 51 ms) starts after a short approach.
    let at = start + Seconds(0.03);
    sim.schedule_fault(FaultTrigger::AtTime(at), FaultKind::FeedbackLost);
    let e = sim.scan(&request()).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::FeedbackLost);
    let now = sim.now().unwrap();
    assert!(
        (now - at).abs().value() < 2e-4,
        "stopped at {now}, fault at {at}"
    );
    let log = sim.oracle().fault_log();
    assert_eq!(log.len(), 1);
    assert_eq!(log[0].kind, FaultEventKind::FeedbackLost);
    assert_eq!(log[0].operation, Some(Operation::Scan));
    assert!(!sim.oracle().faults_between(start, now).is_empty());
}

#[test]
fn a_tip_change_shifts_the_image_and_changes_its_contrast() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    let reference = sim.scan(&request()).unwrap();
    let range = |f: &spm_hal::Frame| {
        let z = &f.forward.z_counts;
        z.iter().cloned().fold(f64::MIN, f64::max) - z.iter().cloned().fold(f64::MAX, f64::min)
    };
    sim.schedule_fault(
        FaultTrigger::NextCall(Operation::Scan),
        FaultKind::TipChange {
            jump: NmPoint::from_nm(0.1, -0.05),
            contrast_factor: 0.5,
            ghost_offset: NmPoint::from_nm(0.0, 0.0),
            ghost_amplitude: 0.0,
        },
    );
    let t = sim.now().unwrap();
    let changed = sim.scan(&request()).unwrap();
    assert!((range(&changed) / range(&reference) - 0.5).abs() < 0.05);
    assert_ne!(
        reference.height_map(TraceHalf::Forward).unwrap().z_counts,
        changed.height_map(TraceHalf::Forward).unwrap().z_counts
    );
    let now = sim.now().unwrap();
    let d = sim.oracle().drift_displacement(now);
    assert!((d.x.value() - 0.1).abs() < 1e-12 && (d.y.value() + 0.05).abs() < 1e-12);
    let log = sim.oracle().fault_log();
    assert_eq!(log[0].kind, FaultEventKind::TipChange);
    assert!((log[0].time - t).value() >= 0.0);
    assert_eq!(sim.oracle().tip_contrast(), 0.5);
}

#[test]
fn a_drift_burst_adds_its_velocity_over_its_interval() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    sim.schedule_fault(
        FaultTrigger::AtTime(Seconds(1.0)),
        FaultKind::DriftBurst {
            velocity: NmVelocity {
                x_nm_per_s: 0.3,
                y_nm_per_s: -0.1,
            },
            duration: Seconds(2.0),
        },
    );
    sim.wait(Seconds(5.0)).unwrap();
    let o = sim.oracle();
    let v = o.drift_velocity(Seconds(2.0));
    assert_eq!((v.x_nm_per_s, v.y_nm_per_s), (0.3, -0.1));
    assert_eq!(o.drift_velocity(Seconds(3.5)).x_nm_per_s, 0.0);
    let d = o.drift_displacement(Seconds(4.0));
    assert!((d.x.value() - 0.6).abs() < 1e-12 && (d.y.value() + 0.2).abs() < 1e-12);
    let burst = &o.fault_log()[0];
    assert_eq!(burst.kind, FaultEventKind::DriftBurst);
    assert_eq!(burst.time, Seconds(1.0));
    assert!(burst.overlaps(Seconds(2.5), Seconds(2.6)));
    assert!(!burst.overlaps(Seconds(3.5), Seconds(4.0)));
}

#[test]
fn random_faults_at_high_rates_never_panic_and_are_all_logged() {
    let mut config = SimConfig::room_temperature_tube();
    config.faults.timeout_probability_per_call = 0.1;
    config.faults.communication_probability_per_call = 0.1;
    config.faults.feedback_lost_rate_per_s = 2.0;
    config.faults.tip_change_rate_per_s = 1.0;
    config.faults.drift_burst_rate_per_s = 1.0;
    config.faults.timeout_duration_s = 0.05;
    let mut sim = Simulator::new(config).unwrap();
    let mut errors = std::collections::HashMap::new();
    for k in 0..60 {
        let r = match k % 3 {
            0 => sim.scan(&request()).map(|_| ()),
            1 => sim.move_to(MoveRequest {
                target: CountPoint::from_counts(100.0 + f64::from(k), 50.0),
                speed: spm_hal::CountsPerSecond(1e3),
                settle: Seconds(0.05),
            }),
            _ => sim.wait(Seconds(0.2)),
        };
        if let Err(e) = r {
            *errors.entry(e.kind()).or_insert(0) += 1;
        }
    }
    let log = sim.oracle().fault_log();
    let count = |k: FaultEventKind| log.iter().filter(|e| e.kind == k).count();
    assert_eq!(
        errors.get(&ErrorKind::Timeout).copied().unwrap_or(0),
        count(FaultEventKind::Timeout)
    );
    assert_eq!(
        errors.get(&ErrorKind::Communication).copied().unwrap_or(0),
        count(FaultEventKind::Communication)
    );
    assert_eq!(
        errors.get(&ErrorKind::FeedbackLost).copied().unwrap_or(0),
        count(FaultEventKind::FeedbackLost)
    );
    for k in [
        FaultEventKind::Timeout,
        FaultEventKind::Communication,
        FaultEventKind::FeedbackLost,
        FaultEventKind::TipChange,
        FaultEventKind::DriftBurst,
    ] {
        assert!(count(k) > 0, "{k:?} never happened");
    }
    assert!(log.windows(2).all(|w| w[0].time <= w[1].time));
}

#[test]
fn bad_requests_are_typed_errors() {
    let mut sim = Simulator::new(SimConfig::ideal()).unwrap();
    let mut r = request();
    r.origin = CountPoint::from_counts(40000.0, 0.0);
    assert_eq!(sim.scan(&r).unwrap_err().kind(), ErrorKind::OutOfRange);
    let mut r = request();
    r.pixel_dwell = Seconds(f64::NAN);
    assert_eq!(sim.scan(&r).unwrap_err().kind(), ErrorKind::Other);
    let e = sim
        .move_to(MoveRequest {
            target: CountPoint::from_counts(0.0, 0.0),
            speed: spm_hal::CountsPerSecond(0.0),
            settle: Seconds(0.0),
        })
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Other);
    assert!(sim.coarse_z().is_none());
    let mut hopg =
        Simulator::new(SimConfig::room_temperature_tube().without_random_faults()).unwrap();
    let stage = hopg.coarse_z().unwrap();
    assert_eq!(stage.step(5000).unwrap_err().kind(), ErrorKind::OutOfRange);
    stage.step(10).unwrap();
    assert_eq!(stage.position_steps().unwrap(), 10);
}

//! The node state machine without a microscope: events in, actions out.
#![allow(clippy::unwrap_used)]

use spm_calibration::{
    Action, Anchor, ApertureResult, AttachResult, CountCovariance, CycleCounts, Event, Failure,
    GiveUpReason, MachineParams, MeasurementMethod, NetPlan, NodeMachine, PlanConfig, SkipResult,
};
use spm_hal::mock::ScriptedMicroscope;
use spm_hal::{CountPoint, CountVector, CountVelocity, ErrorKind, Seconds};

const KX: f64 = 0.004;

fn machine(edit: impl FnOnce(&mut PlanConfig)) -> NodeMachine {
    let mut config = PlanConfig::hopg_small_net();
    edit(&mut config);
    let geometry = config
        .net
        .geometry(&ScriptedMicroscope::default_capabilities())
        .unwrap();
    let plan = NetPlan::new(&geometry, 1).unwrap();
    NodeMachine::new(
        plan.visit(0, 0).unwrap(),
        MachineParams::from_plan(&config),
        Seconds(1.0),
    )
}

fn anchor(x: f64, y: f64) -> Anchor {
    Anchor {
        position: CountPoint::from_counts(x, y),
        time: Some(Seconds(10.0)),
    }
}

/// A→B and A→C of an exact scanner with K̄x = K̄y = 0.004 nm/count, α = 0.
fn lcs() -> (CountVector, CountVector) {
    let a = 0.2461 / KX;
    (
        CountVector::from_counts(a, 0.0),
        CountVector::from_counts(a * 0.5, a * 3f64.sqrt() / 2.0),
    )
}

fn aperture() -> Event {
    Event::ApertureScanned(ApertureResult {
        a: anchor(5.0, 5.0),
        lcs: Some(lcs()),
        neighbours: vec![],
        features: vec![],
    })
}

fn completed(vector: CountVector, kept: u32, discarded: u32) -> Event {
    Event::Skipped(SkipResult::Completed {
        vector,
        covariance: CountCovariance::EXACT,
        a: anchor(5.5, 5.0),
        drift: CountVelocity::ZERO,
        cycles: CycleCounts {
            kept,
            discarded,
            idle: discarded,
            restarts: 0,
        },
    })
}

fn unstable() -> Event {
    Event::Skipped(SkipResult::Unstable {
        cycles: CycleCounts {
            kept: 0,
            discarded: 3,
            idle: 3,
            restarts: 2,
        },
    })
}

fn settled() -> Event {
    Event::Attached(AttachResult::Settled {
        feature: anchor(5.0, 5.0),
        drift: CountVelocity::ZERO,
    })
}

#[test]
fn a_clean_visit_runs_the_fig_2_sequence() {
    let mut m = machine(|_| {});
    assert!(matches!(
        m.step(Event::Begin),
        Action::MoveAndPause { pause, .. } if pause == Seconds(1.0)
    ));
    assert!(matches!(m.step(Event::Paused), Action::Attach { .. }));
    assert!(matches!(m.step(settled()), Action::Aperture { .. }));
    let (ab, ac) = lcs();
    assert!(matches!(m.step(aperture()), Action::Skip { index: 0, .. }));
    // A spoiled cycle inside the skipping is counted but does not disturb the node.
    assert!(matches!(
        m.step(completed(ab, 2, 1)),
        Action::Skip { index: 1, .. }
    ));
    let Action::Finished(result) = m.step(completed(ac, 2, 0)) else {
        panic!("expected Finished");
    };
    assert!((result.lcc.kx.value() - KX).abs() < 1e-12);
    assert!((result.lcc.ky.value() - KX).abs() < 1e-12);
    assert!(result.lcc.alpha.value().abs() < 1e-9);
    assert_eq!(result.attempts, 1);
    assert_eq!(result.cycles.kept, 4);
    assert_eq!(result.cycles.discarded, 1);
    assert!(m.is_over());
}

#[test]
fn unstable_drift_redoes_the_node_then_gives_up_with_the_reason() {
    // max_attempts_per_node = 3 in the small plan.
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    for attempt in 1..=3 {
        assert_eq!(m.attempt(), attempt);
        m.step(Event::Paused);
        m.step(settled());
        m.step(aperture());
        let action = m.step(unstable());
        if attempt < 3 {
            // Back to the node: move and pause again (paper §2.6, long-term instability).
            assert!(matches!(action, Action::MoveAndPause { .. }), "{action:?}");
        } else {
            let Action::GiveUp(GiveUpReason::DriftUnstable {
                discarded,
                restarts,
            }) = action
            else {
                panic!("expected DriftUnstable, got {action:?}");
            };
            assert_eq!((discarded, restarts), (9, 6));
        }
    }
    assert!(m.is_over());
}

#[test]
fn an_unstable_attempt_followed_by_a_stable_one_finishes() {
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    m.step(aperture());
    assert!(matches!(m.step(unstable()), Action::MoveAndPause { .. }));
    m.step(Event::Paused);
    m.step(settled());
    m.step(aperture());
    let (ab, ac) = lcs();
    m.step(completed(ab, 2, 0));
    let Action::Finished(result) = m.step(completed(ac, 2, 0)) else {
        panic!()
    };
    assert_eq!(result.attempts, 2);
    assert_eq!(result.cycles.discarded, 3);
}

#[test]
fn transient_errors_are_retried_within_their_budget() {
    // transient_retries_per_node = 3: the fourth transient error gives the node up.
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    let timeout = || {
        Event::Failed(Failure::Transient {
            kind: Some(ErrorKind::Timeout),
            message: "scan timed out".into(),
        })
    };
    for _ in 0..3 {
        assert!(matches!(m.step(timeout()), Action::MoveAndPause { .. }));
        assert_eq!(m.attempt(), 1, "a retry does not use up an attempt");
    }
    let Action::GiveUp(GiveUpReason::TransientErrors { count, kind, .. }) = m.step(timeout())
    else {
        panic!()
    };
    assert_eq!((count, kind), (4, Some(ErrorKind::Timeout)));
}

#[test]
fn permanent_errors_and_missing_features_have_their_reasons() {
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    let action = m.step(Event::Failed(Failure::Permanent {
        kind: ErrorKind::OutOfRange,
        message: "outside".into(),
    }));
    assert!(matches!(
        action,
        Action::GiveUp(GiveUpReason::Backend {
            kind: ErrorKind::OutOfRange,
            ..
        })
    ));
    let mut m = machine(|c| c.failures.max_attempts_per_node = 1);
    m.step(Event::Begin);
    m.step(Event::Paused);
    assert!(matches!(
        m.step(Event::Attached(AttachResult::FeatureLost)),
        Action::GiveUp(GiveUpReason::NoFeature)
    ));
    let mut m = machine(|c| c.failures.max_attempts_per_node = 1);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    let no_lcs = Event::ApertureScanned(ApertureResult {
        a: anchor(0.0, 0.0),
        lcs: None,
        neighbours: vec![],
        features: vec![],
    });
    assert!(matches!(
        m.step(no_lcs),
        Action::GiveUp(GiveUpReason::NoLcs)
    ));
    let mut m = machine(|c| c.failures.max_attempts_per_node = 1);
    m.step(Event::Begin);
    m.step(Event::Paused);
    assert!(matches!(
        m.step(Event::Attached(AttachResult::DriftNotSettled {
            drift: CountVelocity {
                x_counts_per_s: 3.0,
                y_counts_per_s: 4.0
            }
        })),
        Action::GiveUp(GiveUpReason::DriftNotSettled { speed_counts_per_s }) if speed_counts_per_s == 5.0
    ));
}

#[test]
fn variants_change_the_sequence_and_the_vectors() {
    // Fig. 3b: no separate attachment, the aperture is centred on the node.
    let mut m = machine(|c| c.variant.attach_to = spm_calibration::AttachTarget::LcsCentre);
    m.step(Event::Begin);
    assert!(matches!(m.step(Event::Paused), Action::Aperture { .. }));
    // B↔C redundancy: a third vector starting at B.
    let mut m = machine(|c| c.variant.bc_redundancy = true);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    m.step(aperture());
    assert_eq!(m.targets().len(), 3);
    let (ab, ac) = lcs();
    m.step(completed(ab, 2, 0));
    let Action::Skip { from, estimate, .. } = m.step(completed(ac, 2, 0)) else {
        panic!()
    };
    // Starts at A (last sighting 5.5, 5.0) + measured A→B.
    assert!((from.position.x.value() - (5.5 + ab.x.value())).abs() < 1e-9);
    assert!(((estimate - (ac - ab)).norm()).value() < 1e-9);
    let Action::Finished(r) = m.step(completed(ac - ab, 2, 0)) else {
        panic!()
    };
    assert_eq!(r.vectors.len(), 3);
    assert!((r.lcc.kx.value() - KX).abs() < 1e-12);
    // Every neighbour: six vectors around A, least squares.
    let mut m = machine(|c| c.variant.neighbours = spm_calibration::NeighbourSet::AllInAperture);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    let a = 0.2461 / KX;
    let ring: Vec<CountVector> = (0..6)
        .map(|k| {
            let t = (60.0 * k as f64 + 10.0).to_radians();
            CountVector::from_counts(a * t.cos(), a * t.sin())
        })
        .collect();
    let mut action = m.step(Event::ApertureScanned(ApertureResult {
        a: anchor(0.0, 0.0),
        lcs: Some(lcs()),
        neighbours: ring.clone(),
        features: ring.clone(),
    }));
    for v in &ring {
        assert!(matches!(action, Action::Skip { .. }));
        action = m.step(completed(*v, 2, 0));
    }
    let Action::Finished(r) = action else {
        panic!()
    };
    assert_eq!(r.vectors.len(), 6);
    assert!((r.lcc.kx.value() - KX).abs() < 1e-12);
    // Counter-scanning instead of skipping.
    let mut m = machine(|c| c.variant.measurement = MeasurementMethod::CounterScan);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    assert!(matches!(m.step(aperture()), Action::CounterScan { .. }));
}

/// Skipping that caught a neighbouring atom measures another lattice vector (here A→B + A→C,
/// √3 longer): the node is redone, never finished with it; a vector within the tolerance of
/// the aperture's (drift-distorted) estimate is kept.
#[test]
fn a_skipped_vector_that_caught_another_feature_redoes_the_node() {
    let (ab, ac) = lcs();
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    for attempt in 1..=3 {
        m.step(Event::Paused);
        m.step(settled());
        m.step(aperture());
        let action = m.step(completed(ab + ac, 2, 0));
        if attempt < 3 {
            assert!(matches!(action, Action::MoveAndPause { .. }), "{action:?}");
        } else {
            let Action::GiveUp(GiveUpReason::WrongFeature { deviation_fraction }) = action else {
                panic!("expected WrongFeature, got {action:?}");
            };
            assert!(
                (deviation_fraction - 1.0).abs() < 1e-9,
                "{deviation_fraction}"
            );
        }
    }
    assert!(m.is_over());

    // 10 % off the aperture's estimate (a single scan under drift) is the same vector.
    let mut m = machine(|_| {});
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    m.step(aperture());
    assert!(matches!(
        m.step(completed(ab * 1.1, 2, 0)),
        Action::Skip { index: 1, .. }
    ));
    const { assert!(spm_calibration::TuningConfig::RECOMMENDED.vector_match_tolerance_fraction < 1.0) };
}

/// The machine's answer to each event as a short name: `move`, `attach`, `aperture`,
/// `skip<i>` (with `@B` when the vector starts at another vector's end), `counter`,
/// `finished`, `give-up:<reason kind>`.
fn name(action: &Action) -> String {
    match action {
        Action::MoveAndPause { .. } => "move".into(),
        Action::Attach { .. } => "attach".into(),
        Action::Aperture { centre } => {
            if centre.time.is_some() {
                "aperture".into()
            } else {
                "aperture@node".into()
            }
        }
        Action::Skip { index, from, .. } => {
            if from.position == anchor(5.0, 5.0).position
                || from.position == anchor(5.5, 5.0).position
            {
                format!("skip{index}")
            } else {
                format!("skip{index}@B")
            }
        }
        Action::CounterScan { .. } => "counter".into(),
        Action::Finished(_) => "finished".into(),
        Action::GiveUp(reason) => format!(
            "give-up:{}",
            format!("{reason:?}")
                .split([' ', '{', '('])
                .next()
                .unwrap_or_default()
        ),
    }
}

/// Feeds `events` to a fresh machine (after `edit` of the small plan) and compares the
/// transcript of its actions with `expect` (names separated by spaces).
fn check(edit: impl FnOnce(&mut PlanConfig), events: Vec<Event>, expect: &str) {
    let mut m = machine(edit);
    let got: Vec<String> = events.into_iter().map(|e| name(&m.step(e))).collect();
    assert_eq!(got.join(" "), expect);
}

fn transient() -> Event {
    Event::Failed(Failure::Transient {
        kind: Some(ErrorKind::Timeout),
        message: "link".into(),
    })
}

fn counter_result() -> Event {
    let (ab, ac) = lcs();
    Event::CounterScanned(spm_calibration::CounterResult {
        a: anchor(5.0, 5.0),
        vectors: vec![(ab, CountCovariance::EXACT), (ac, CountCovariance::EXACT)],
        drift: CountVelocity::ZERO,
    })
}

#[test]
fn transcripts_of_the_plan_variants() {
    let (ab, ac) = lcs();
    // Fig. 2: attach to A, aperture, skip A↔B, A↔C.
    check(
        |_| {},
        vec![
            Event::Begin,
            Event::Paused,
            settled(),
            aperture(),
            completed(ab, 2, 0),
            completed(ac, 2, 0),
        ],
        "move attach aperture skip0 skip1 finished",
    );
    // Fig. 3b: the aperture around the node (never seen: no time) stands in for the
    // attachment.
    check(
        |c| c.variant.attach_to = spm_calibration::AttachTarget::LcsCentre,
        vec![Event::Begin, Event::Paused, aperture(), completed(ab, 2, 0)],
        "move aperture@node skip0 skip1",
    );
    // B↔C redundancy: the third vector starts at the end of A→B, as measured.
    check(
        |c| c.variant.bc_redundancy = true,
        vec![
            Event::Begin,
            Event::Paused,
            settled(),
            aperture(),
            completed(ab, 2, 0),
            completed(ac, 2, 0),
        ],
        "move attach aperture skip0 skip1 skip2@B",
    );
    // Counter-scanning measures both vectors from one pair of scans.
    check(
        |c| c.variant.measurement = MeasurementMethod::CounterScan,
        vec![
            Event::Begin,
            Event::Paused,
            settled(),
            aperture(),
            counter_result(),
        ],
        "move attach aperture counter finished",
    );
    // A transient failure redoes the visit from the move without using up an attempt.
    check(
        |_| {},
        vec![Event::Begin, Event::Paused, transient(), Event::Paused],
        "move attach move attach",
    );
    // An aperture without an LCS, as often as attempts allow, gives the node up.
    let no_lcs = || {
        Event::ApertureScanned(ApertureResult {
            a: anchor(5.0, 5.0),
            lcs: None,
            neighbours: vec![],
            features: vec![],
        })
    };
    check(
        |c| c.failures.max_attempts_per_node = 2,
        vec![
            Event::Begin,
            Event::Paused,
            settled(),
            no_lcs(),
            Event::Paused,
            settled(),
            no_lcs(),
        ],
        "move attach aperture move attach aperture give-up:NoLcs",
    );
}

/// Every neighbour of A on a scanner that stretches y 2.5× (K̄y = K̄x / 2.5): in counts the
/// lattice directions are up to 26° from where the angle from the first neighbour puts them,
/// so each neighbour is named through the recognised LCS instead; and a neighbour whose
/// skipping caught a feature 20 % farther out is left out of the node by its redundancy. The
/// node's coefficients are the scanner's exactly.
#[test]
fn every_neighbour_is_named_through_the_lcs_and_a_wrong_one_is_left_out() {
    let ky = KX / 2.5;
    let a = 0.2461;
    let raw = |degrees: f64| {
        let t = degrees.to_radians();
        CountVector::from_counts(a * t.cos() / KX, a * t.sin() / ky)
    };
    let mut m = machine(|c| c.variant.neighbours = spm_calibration::NeighbourSet::AllInAperture);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    // The first neighbour is the 120° one: 103° in counts, with the 60° one at 77°.
    let ring: Vec<CountVector> = [120.0, 60.0, 0.0, 300.0, 240.0, 180.0]
        .into_iter()
        .map(raw)
        .collect();
    let mut action = m.step(Event::ApertureScanned(ApertureResult {
        a: anchor(0.0, 0.0),
        lcs: Some((raw(0.0), raw(60.0))),
        neighbours: ring.clone(),
        features: ring.clone(),
    }));
    for (i, v) in ring.iter().enumerate() {
        assert!(matches!(action, Action::Skip { .. }), "{action:?}");
        // The fourth skipping caught a feature 20 % beyond the neighbour.
        let measured = if i == 3 { *v * 1.2 } else { *v };
        action = m.step(completed(measured, 2, 0));
    }
    let Action::Finished(r) = action else {
        panic!("{action:?}")
    };
    assert_eq!(r.vectors.len(), 5);
    assert!((r.lcc.kx.value() / KX - 1.0).abs() < 1e-9, "{:?}", r.lcc);
    assert!((r.lcc.ky.value() / ky - 1.0).abs() < 1e-9, "{:?}", r.lcc);
    assert!(r.lcc.alpha.value().abs() < 1e-9, "{:?}", r.lcc);
}

/// Every feature of the aperture on a site of A's lattice, on a scanner that stretches y
/// 2.5× and shears (α = 0.2 rad): the two shells beyond the nearest neighbours (√3·a and
/// 2·a) are named by their lattice indices through the recognised LCS; a feature between
/// sites (a defect) and A itself are left out; a skipping that caught another feature, and
/// one out of the instrument's range, cost their vectors, not the node; the node's
/// coefficients are the scanner's.
#[test]
fn every_lattice_site_in_the_aperture_is_named_through_the_lcs() {
    let ky = KX / 2.5;
    let alpha: f64 = 0.2;
    let a = 0.2461;
    // The scanner's inverse: true (x, y) nm → counts, with K̄y along the sheared y axis.
    let counts = |x: f64, y: f64| {
        let v = y / (ky * alpha.cos());
        let u = (x - ky * alpha.sin() * v) / KX;
        CountVector::from_counts(u, v)
    };
    let site = |i: f64, j: f64| {
        let t = 60f64.to_radians();
        counts(a * (i + j * t.cos()), a * j * t.sin())
    };
    let mut m =
        machine(|c| c.variant.neighbours = spm_calibration::NeighbourSet::LatticeInAperture);
    m.step(Event::Begin);
    m.step(Event::Paused);
    m.step(settled());
    let mut sites = Vec::new();
    for i in -2..=2 {
        for j in -2..=2 {
            let (i, j) = (f64::from(i), f64::from(j));
            // Within two lattice constants, A itself left out.
            let length = (i * i + j * j + i * j).sqrt();
            if length > 0.0 && length <= 2.0 + 1e-9 {
                sites.push(site(i, j));
            }
        }
    }
    assert_eq!(sites.len(), 18);
    let mut features = sites.clone();
    // Half-way between two sites, and A itself.
    features.push(site(0.5, 0.5));
    features.push(site(0.0, 0.0));
    let mut action = m.step(Event::ApertureScanned(ApertureResult {
        a: anchor(0.0, 0.0),
        lcs: Some((site(1.0, 0.0), site(0.0, 1.0))),
        neighbours: Vec::new(),
        features,
    }));
    let mut skipped = 0;
    while let Action::Skip { .. } = action {
        let v = sites[skipped];
        skipped += 1;
        action = match skipped {
            // The fifth skipping caught the next feature out (60 % of its length off) and the
            // ninth would leave the instrument's range: each costs its vector, not the node.
            5 => m.step(completed(v * 1.6, 2, 0)),
            9 => m.step(Event::Failed(Failure::Permanent {
                kind: ErrorKind::OutOfRange,
                message: "a scan leaves the stored image".into(),
            })),
            _ => m.step(completed(v, 2, 0)),
        };
    }
    assert_eq!(skipped, 18, "every site skipped to, nothing else");
    let Action::Finished(r) = action else {
        panic!("{action:?}")
    };
    assert_eq!(r.vectors.len(), 16);
    assert!((r.lcc.kx.value() / KX - 1.0).abs() < 1e-9, "{:?}", r.lcc);
    assert!((r.lcc.ky.value() / ky - 1.0).abs() < 1e-9, "{:?}", r.lcc);
    assert!((r.lcc.alpha.value() - alpha).abs() < 1e-9, "{:?}", r.lcc);
}

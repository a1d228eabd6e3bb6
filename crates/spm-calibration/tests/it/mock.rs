//! The calibration loop on the scripted mock of spm-hal: faults are retried per node within
//! the budget, nodes are given up with their reasons, the observer hears everything, and an
//! aborted instrument stops the run with an error.
#![allow(clippy::unwrap_used)]

use spm_calibration::{
    Calibrator, GiveUpReason, MemoryStore, Observer, PlanConfig, RunError, RunOptions,
};
use spm_hal::ErrorKind;
use spm_hal::mock::{Expectation, Operation, ScriptedMicroscope};
use spm_records::NodeState;

#[derive(Default)]
struct Counting {
    started: usize,
    given_up: Vec<GiveUpReason>,
    run_started: Option<(usize, usize)>,
}

impl Observer for Counting {
    fn run_started(&mut self, total: usize, already: usize) {
        self.run_started = Some((total, already));
    }
    fn node_started(&mut self, _visit: &spm_calibration::PlanVisit, _attempt: u32) {
        self.started += 1;
    }
    fn node_given_up(&mut self, _visit: &spm_calibration::PlanVisit, reason: &GiveUpReason) {
        self.given_up.push(reason.clone());
    }
}

fn options() -> RunOptions {
    RunOptions {
        run_id: "mock".into(),
        start_unix_s: 0.0,
        config_text: String::new(),
    }
}

#[test]
fn every_scan_failing_gives_every_node_up_within_its_budget() {
    let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
        .lenient_moves_and_waits(true);
    // The lattice survey's 9 frames (one try each), then 9 nodes × (1 + 3 retries) scans,
    // each a communication failure.
    for _ in 0..9 + 36 {
        mock.expect(Expectation::fault(
            Operation::Scan,
            ErrorKind::Communication,
        ));
    }
    let mut store = MemoryStore::default();
    let mut observer = Counting::default();
    let mut plan = PlanConfig::hopg_small_net();
    plan.survey.enabled = true;
    let report = Calibrator::new(&mut mock, &mut store, &mut observer, plan)
        .unwrap()
        .run(&options())
        .unwrap();
    mock.done().unwrap();
    assert_eq!(report.nodes_done, 0);
    assert_eq!(report.given_up.len(), 9);
    assert_eq!(report.transient_errors, 36);
    // Every survey place refused by its failed scan: no gate, recognition ungated.
    let survey = report.survey.as_ref().unwrap();
    assert_eq!(survey.places.len(), 9);
    assert!(
        survey
            .places
            .iter()
            .all(|p| p.lcc.is_none() && p.refusal.as_deref().is_some_and(|r| r.contains("scan")))
    );
    assert!(survey.field.is_none());
    assert_eq!(observer.run_started, Some((9, 0)));
    assert_eq!(observer.started, 36, "one start per (re)try");
    assert!(observer.given_up.iter().all(|r| matches!(
        r,
        GiveUpReason::TransientErrors {
            count: 4,
            kind: Some(ErrorKind::Communication),
            ..
        }
    )));
    assert!(store.records.is_empty());
    assert!(
        store
            .states
            .values()
            .all(|s| matches!(s, NodeState::GivenUp(r) if r.contains("transient")))
    );
    // The run itself finished: everything was tried.
    assert_eq!(store.runs["mock"].status, spm_records::RunStatus::Finished);
}

#[test]
fn an_aborted_instrument_stops_the_run_and_leaves_it_resumable() {
    let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
        .lenient_moves_and_waits(true);
    mock.expect(Expectation::fault(Operation::Scan, ErrorKind::Aborted));
    let mut store = MemoryStore::default();
    let mut observer = Counting::default();
    let error = Calibrator::new(
        &mut mock,
        &mut store,
        &mut observer,
        PlanConfig::hopg_small_net(),
    )
    .unwrap()
    .run(&options())
    .unwrap_err();
    assert!(matches!(
        error,
        RunError::Instrument {
            kind: ErrorKind::Aborted,
            ..
        }
    ));
    assert!(store.states.values().all(|s| *s == NodeState::Pending));
    assert_eq!(store.runs["mock"].status, spm_records::RunStatus::Aborted);
}

#[test]
fn a_plan_needing_a_coarse_stage_is_refused_without_one() {
    let mut plan = PlanConfig::hopg_small_net();
    plan.net.z_levels[0].coarse_steps = Some(10);
    let mut mock = ScriptedMicroscope::new(ScriptedMicroscope::default_capabilities())
        .lenient_moves_and_waits(true);
    let mut store = MemoryStore::default();
    let mut observer = Counting::default();
    // Refused when the controller is built, naming the field (issue 15), before any run.
    let error = Calibrator::new(&mut mock, &mut store, &mut observer, plan)
        .err()
        .expect("refused");
    assert!(
        matches!(
            error,
            RunError::Plan(spm_calibration::PlanError::Invalid {
                field: "z_levels.coarse_steps",
                ..
            })
        ),
        "{error}"
    );
    assert!(store.runs.is_empty());
}

//! End to end on the simulated microscope: a 3×3 net calibrates, LCCs agree with the
//! oracle; a node whose scans always fail is given up with its reason and the run goes on;
//! an interrupted run resumes and measures exactly the missing nodes.
#![allow(clippy::unwrap_used)]

use spm_calibration::{
    Calibrator, GiveUpReason, MemoryStore, NoObserver, NodeMeasurement, Observer, PlanConfig,
    RunOptions,
};
use spm_cdb::{Cdb, CdbRead, NodeState, RecordFilter};
use spm_hal::{
    Capabilities, CoarseZStage, CountPoint, Counts, ErrorKind, Frame, Microscope, MoveRequest,
    ScanRequest, Seconds,
};
use spm_sim::{SimConfig, Simulator};

fn options(run_id: &str) -> RunOptions {
    RunOptions {
        run_id: run_id.into(),
        start_unix_s: 1.8e9,
        config_text: PlanConfig::hopg_small_net().to_toml_string().unwrap(),
    }
}

fn simulator(config: SimConfig) -> Simulator {
    Simulator::new(config).unwrap()
}

/// The simulator behind a thin wrapper that (a) takes the oracle's LCCs at the probe each
/// time the controller reads Z (it does so right after a node is measured, before storing
/// it), and (b) fails every scan within `fail_radius` counts of `fail_near` with a timeout.
struct Probe {
    sim: Simulator,
    oracle_lccs: Vec<spm_sim::Lcc>,
    fail_near: Option<CountPoint>,
    fail_radius: f64,
    failed_scans: usize,
}

#[derive(Debug, thiserror::Error)]
enum ProbeError {
    #[error(transparent)]
    Sim(#[from] spm_sim::SimError),
    #[error("injected {0:?}")]
    Injected(ErrorKind),
}

impl spm_hal::Error for ProbeError {
    fn kind(&self) -> ErrorKind {
        match self {
            Self::Sim(e) => e.kind(),
            Self::Injected(k) => *k,
        }
    }
}

impl Probe {
    fn new(config: SimConfig) -> Self {
        Self {
            sim: simulator(config),
            oracle_lccs: Vec::new(),
            fail_near: None,
            fail_radius: 0.0,
            failed_scans: 0,
        }
    }
}

impl Microscope for Probe {
    type Error = ProbeError;
    fn capabilities(&self) -> Capabilities {
        self.sim.capabilities()
    }
    fn now(&mut self) -> Result<Seconds, ProbeError> {
        Ok(self.sim.now()?)
    }
    fn wait(&mut self, duration: Seconds) -> Result<(), ProbeError> {
        Ok(self.sim.wait(duration)?)
    }
    fn position(&mut self) -> Result<CountPoint, ProbeError> {
        Ok(self.sim.position()?)
    }
    fn move_to(&mut self, request: MoveRequest) -> Result<(), ProbeError> {
        Ok(self.sim.move_to(request)?)
    }
    fn scan(&mut self, request: &ScanRequest) -> Result<Frame, ProbeError> {
        if let Some(p) = self.fail_near
            && request.centre().distance(p).value() < self.fail_radius
        {
            self.failed_scans += 1;
            self.sim.wait(Seconds(0.5))?;
            return Err(ProbeError::Injected(ErrorKind::Timeout));
        }
        Ok(self.sim.scan(request)?)
    }
    fn z_position(&mut self) -> Result<Counts, ProbeError> {
        let here = self.sim.position()?;
        self.oracle_lccs.push(self.sim.oracle().lcc_now(here));
        Ok(self.sim.z_position()?)
    }
    fn coarse_z(&mut self) -> Option<&mut dyn CoarseZStage<Error = ProbeError>> {
        None
    }
}

/// Relative errors (K̄x, K̄y) and absolute error of α (rad) of every record against the
/// oracle's LCCs taken when it was measured.
fn errors(probe: &Probe, store: &MemoryStore) -> Vec<[f64; 3]> {
    store
        .records
        .iter()
        .zip(&probe.oracle_lccs)
        .map(|(r, truth)| {
            [
                r.kx_nm_per_count / truth.kx.value() - 1.0,
                r.ky_nm_per_count / truth.ky.value() - 1.0,
                r.alpha_rad - truth.alpha.value(),
            ]
        })
        .collect()
}

#[test]
fn a_small_net_calibrates_within_tolerance_of_the_oracle() {
    for (name, config, tolerance) in [
        ("ideal", SimConfig::ideal(), 0.002),
        (
            "room temperature",
            SimConfig::room_temperature_tube().without_random_faults(),
            0.01,
        ),
    ] {
        let mut probe = Probe::new(config);
        let mut store = MemoryStore::default();
        let mut observer = NoObserver;
        let report = {
            let mut calibrator = Calibrator::new(
                &mut probe,
                &mut store,
                &mut observer,
                PlanConfig::hopg_small_net(),
            )
            .unwrap();
            calibrator.run(&options("e2e")).unwrap()
        };
        println!("{name}: {report:#?}");
        assert_eq!(report.visits_planned, 9);
        assert_eq!(report.nodes_done + report.given_up.len(), 9);
        assert!(report.nodes_done >= 8, "{name}: {report:?}");
        let errors = errors(&probe, &store);
        assert_eq!(probe.oracle_lccs.len(), store.records.len());
        for (r, e) in store.records.iter().zip(&errors) {
            println!(
                "{name}: node ({}, {}) kx {:.6} ky {:.6} alpha {:.5} rel err kx {:+.4} ky {:+.4} alpha {:+.4} rad, u_kx/kx {:.4}",
                r.node_x_counts,
                r.node_y_counts,
                r.kx_nm_per_count,
                r.ky_nm_per_count,
                r.alpha_rad,
                e[0],
                e[1],
                e[2],
                r.u_kx_nm_per_count.unwrap() / r.kx_nm_per_count
            );
        }
        // Each node within 4 stated standard uncertainties (plus the tolerance floor for
        // effects the uncertainty does not model), and the mean over the net unbiased.
        let mut z_max: f64 = 0.0;
        for (r, e) in store.records.iter().zip(&errors) {
            let u = [
                r.u_kx_nm_per_count.unwrap() / r.kx_nm_per_count,
                r.u_ky_nm_per_count.unwrap() / r.ky_nm_per_count,
                r.u_alpha_rad.unwrap(),
            ];
            for k in 0..3 {
                let z = e[k] / u[k].max(1e-12);
                z_max = z_max.max(z.abs());
                assert!(
                    e[k].abs() < 4.0 * u[k] + tolerance,
                    "{name}: node ({}, {}) error {e:?} vs u {u:?}",
                    r.node_x_counts,
                    r.node_y_counts
                );
            }
        }
        let n = errors.len() as f64;
        let mean: Vec<f64> = (0..3)
            .map(|k| errors.iter().map(|e| e[k]).sum::<f64>() / n)
            .collect();
        let se: Vec<f64> = (0..3)
            .map(|k| {
                let var = errors.iter().map(|e| (e[k] - mean[k]).powi(2)).sum::<f64>() / (n - 1.0);
                (var / n).sqrt()
            })
            .collect();
        println!(
            "{name}: mean errors kx {:+.4} ± {:.4} ky {:+.4} ± {:.4} alpha {:+.4} ± {:.4} rad, largest |error|/u {z_max:.2}",
            mean[0], se[0], mean[1], se[1], mean[2], se[2]
        );
        // The mean over the net within 3 standard errors of the tolerance floor (the
        // simulated creep of the hops leaves a systematic ≈ +0.4 %, see the crate docs).
        for k in 0..2 {
            assert!(
                mean[k].abs() < 3.0 * se[k] + 0.5 * tolerance,
                "{name}: mean {mean:?} ± {se:?}"
            );
        }
    }
}

#[test]
fn a_node_whose_scans_always_fail_is_given_up_and_the_run_goes_on() {
    let mut probe = Probe::new(SimConfig::ideal());
    // The net's centre node (node index 4 of the serpentine) cannot be scanned.
    probe.fail_near = Some(CountPoint::from_counts(-1.0, -1.0));
    probe.fail_radius = 1000.0;
    let mut store = MemoryStore::default();
    // With the lattice survey (one of its frames lies on the failing place).
    let mut plan = PlanConfig::hopg_small_net();
    plan.survey.enabled = true;
    let report = Calibrator::new(&mut probe, &mut store, &mut NoObserver, plan)
        .unwrap()
        .run(&options("faulty"))
        .unwrap();
    assert_eq!(report.nodes_done, 8);
    assert_eq!(report.given_up.len(), 1);
    let given_up = &report.given_up[0];
    assert_eq!((given_up.node[0], given_up.node[1]), (-1, -1));
    assert!(
        matches!(
            given_up.reason,
            GiveUpReason::TransientErrors {
                count: 4,
                kind: Some(ErrorKind::Timeout),
                ..
            }
        ),
        "{:?}",
        given_up.reason
    );
    // Budget: 3 retries + the failing call, and the lattice survey's frame at the centre
    // (tried once: a place that fails gates nothing, the others survey the lattice).
    assert_eq!(probe.failed_scans, 4 + 1);
    let survey = report.survey.as_ref().unwrap();
    assert_eq!(survey.places.len(), 9);
    assert_eq!(survey.places.iter().filter(|p| p.lcc.is_none()).count(), 1);
    assert!(survey.field.is_some());
    assert_eq!(report.transient_errors, 4);
    let state = &store.states[&("faulty".to_owned(), 0, given_up.node_index)];
    let NodeState::GivenUp(reason) = state else {
        panic!("{state:?}")
    };
    assert!(reason.contains("transient"), "{reason}");
    assert_eq!(store.records.len(), 8);
    assert!(
        store
            .records
            .iter()
            .all(|r| r.node_index != given_up.node_index)
    );
}

/// Stops the run after `limit` finished visits.
struct StopAfter {
    limit: usize,
    finished: usize,
}

impl Observer for StopAfter {
    fn node_finished(&mut self, _m: &NodeMeasurement) {
        self.finished += 1;
    }
    fn keep_going(&mut self) -> bool {
        self.finished < self.limit
    }
}

#[test]
fn an_interrupted_run_resumes_with_exactly_the_missing_nodes() {
    let path = std::env::temp_dir().join(format!(
        "spm-calibration-resume-{}.sqlite",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&path);
    let mut plan = PlanConfig::hopg_small_net();
    plan.repeats = 2; // 18 visits, the second pass backwards
    // First invocation: killed (stopped) after 7 visits.
    {
        let mut cdb = Cdb::open(&path).unwrap();
        let mut probe = Probe::new(SimConfig::ideal());
        let mut stop = StopAfter {
            limit: 7,
            finished: 0,
        };
        let report = Calibrator::new(&mut probe, &mut cdb, &mut stop, plan.clone())
            .unwrap()
            .run(&options("resume"))
            .unwrap();
        assert!(report.interrupted);
        assert_eq!(report.nodes_done, 7);
        let summary = cdb.progress_summary("resume").unwrap();
        assert_eq!((summary.done, summary.pending), (7, 11));
    }
    // Second invocation (a new process: new backend, reopened CDB), same run id.
    let mut cdb = Cdb::open(&path).unwrap();
    let mut probe = Probe::new(SimConfig::ideal());
    let report = Calibrator::new(&mut probe, &mut cdb, &mut NoObserver, plan)
        .unwrap()
        .run(&options("resume"))
        .unwrap();
    assert!(!report.interrupted);
    assert_eq!(report.already_finished, 7);
    assert_eq!(report.nodes_done, 11);
    let records = cdb
        .records(&RecordFilter::default().with_run("resume"))
        .unwrap();
    assert_eq!(records.len(), 18);
    let mut visits: Vec<(u32, u32)> = records
        .iter()
        .map(|r| (r.repeat_index, r.node_index))
        .collect();
    visits.sort_unstable();
    visits.dedup();
    assert_eq!(visits.len(), 18, "every visit exactly once");
    let summary = cdb.progress_summary("resume").unwrap();
    assert_eq!(
        (summary.done, summary.pending, summary.given_up),
        (18, 0, 0)
    );
    assert!(cdb.check().unwrap().is_ok());
    assert_eq!(
        cdb.run("resume").unwrap().unwrap().status,
        spm_cdb::RunStatus::Finished
    );
    drop(cdb);
    let _ = std::fs::remove_file(&path);
}

#[test]
fn every_variant_of_section_6_calibrates_the_room_temperature_scanner() {
    use spm_calibration::{AttachTarget, MeasurementMethod, NeighbourSet};
    type Edit = fn(&mut PlanConfig);
    let variants: [(&str, Edit); 5] = [
        ("B-C redundancy", |p| p.variant.bc_redundancy = true),
        ("all neighbours", |p| {
            p.variant.neighbours = NeighbourSet::AllInAperture;
        }),
        ("LCS centre (Fig. 3b)", |p| {
            p.variant.attach_to = AttachTarget::LcsCentre;
        }),
        ("counter-scan", |p| {
            p.variant.measurement = MeasurementMethod::CounterScan;
        }),
        ("no attachment", |p| p.attach.skip = true),
    ];
    for (name, edit) in variants {
        let mut plan = PlanConfig::hopg_small_net();
        edit(&mut plan);
        let mut probe = Probe::new(SimConfig::room_temperature_tube().without_random_faults());
        let mut store = MemoryStore::default();
        let report = Calibrator::new(&mut probe, &mut store, &mut NoObserver, plan)
            .unwrap()
            .run(&options(name))
            .unwrap();
        let errors = errors(&probe, &store);
        let rms = |k: usize| {
            (errors.iter().map(|e| e[k] * e[k]).sum::<f64>() / errors.len().max(1) as f64).sqrt()
        };
        println!(
            "{name}: done {} given up {:?}, rms error kx {:.4} ky {:.4} alpha {:.4} rad, cycles {:?}, instrument {:.1} s",
            report.nodes_done,
            report
                .given_up
                .iter()
                .map(|g| g.reason.to_string())
                .collect::<Vec<_>>(),
            rms(0),
            rms(1),
            rms(2),
            report.cycles,
            report.instrument_time_s
        );
        assert!(report.nodes_done >= 7, "{name}: {report:?}");
        // Counter-scanning the aperture is the fast, less precise variant (paper §6).
        let limit = if name == "counter-scan" { 0.05 } else { 0.03 };
        assert!(rms(0) < limit && rms(1) < limit, "{name}");
    }
}

#[test]
fn vertical_planes_drive_the_coarse_stage() {
    use spm_calibration::{NetKind, ZLevel};
    let mut plan = PlanConfig::hopg_small_net();
    plan.net.kind = NetKind::VerticalPlanes;
    plan.net.y_planes_counts = Some(vec![0]);
    // Coarse step −1 (away from the sample) lengthens the Z extension by 50 nm.
    plan.net.z_levels = vec![
        ZLevel {
            nominal_z_counts: 10000,
            coarse_steps: Some(0),
        },
        ZLevel {
            nominal_z_counts: 22500,
            coarse_steps: Some(-1),
        },
    ];
    plan.pause.per_coarse_step_s = 5.0;
    let mut sim = simulator(SimConfig::room_temperature_tube().without_random_faults());
    let mut store = MemoryStore::default();
    let report = Calibrator::new(&mut sim, &mut store, &mut NoObserver, plan)
        .unwrap()
        .run(&options("vertical"))
        .unwrap();
    assert_eq!(report.visits_planned, 6);
    assert_eq!(report.nodes_done, 6, "{report:?}");
    // The measured Z follows the coarse level.
    for r in &store.records {
        let expected = r.node_z_counts as f64;
        println!(
            "node ({}, {}) z {} measured z {:.0} kx {:.5}",
            r.node_x_counts, r.node_y_counts, r.node_z_counts, r.lcs_z_counts, r.kx_nm_per_count
        );
        assert!((r.lcs_z_counts - expected).abs() < 2000.0, "{r:?}");
    }
    // The last visit (x = 19999) ends at the second level.
    assert_eq!(sim.coarse_z().unwrap().position_steps().unwrap(), -1);
}

#[test]
#[ignore = "diagnostic: where the room-temperature bias comes from"]
fn diagnose_bias_sources() {
    let base = SimConfig::room_temperature_tube().without_random_faults();
    let mut no_creep = base.clone();
    no_creep.scanner.creep.log_slope_per_decade = 0.0;
    let mut no_drift = base.clone();
    no_drift.drift.velocity_x_nm_per_s = 0.0;
    no_drift.drift.velocity_y_nm_per_s = 0.0;
    no_drift.drift.velocity_random_walk_nm_per_s_per_sqrt_s = 0.0;
    no_drift.drift.jump_rate_per_s = 0.0;
    let mut no_hyst = base.clone();
    no_hyst.scanner.hysteresis_x.width_fraction = 0.0;
    no_hyst.scanner.hysteresis_y.width_fraction = 0.0;
    for (name, config) in [
        ("base", base),
        ("no creep", no_creep),
        ("no drift", no_drift),
        ("no hysteresis", no_hyst),
    ] {
        let mut probe = Probe::new(config);
        let mut store = MemoryStore::default();
        let mut plan = PlanConfig::hopg_small_net();
        plan.repeats = 6;
        Calibrator::new(&mut probe, &mut store, &mut NoObserver, plan)
            .unwrap()
            .run(&options(name))
            .unwrap();
        let e = errors(&probe, &store);
        let n = e.len() as f64;
        let m: Vec<f64> = (0..3)
            .map(|k| e.iter().map(|v| v[k]).sum::<f64>() / n)
            .collect();
        let se: Vec<f64> = (0..3)
            .map(|k| {
                let var = e.iter().map(|v| (v[k] - m[k]).powi(2)).sum::<f64>() / (n - 1.0);
                (var / n).sqrt()
            })
            .collect();
        println!(
            "{name}: n {} mean kx {:+.4} ± {:.4} ky {:+.4} ± {:.4} alpha {:+.4} ± {:.4}",
            e.len(),
            m[0],
            se[0],
            m[1],
            se[1],
            m[2],
            se[2]
        );
    }
}

#[test]
fn resuming_with_a_different_plan_is_refused() {
    let path = std::env::temp_dir().join(format!(
        "spm-calibration-conflict-{}.sqlite",
        std::process::id()
    ));
    let _ = std::fs::remove_file(&path);
    let mut cdb = Cdb::open(&path).unwrap();
    let mut probe = Probe::new(SimConfig::ideal());
    let mut stop = StopAfter {
        limit: 0,
        finished: 0,
    };
    let report = Calibrator::new(
        &mut probe,
        &mut cdb,
        &mut stop,
        PlanConfig::hopg_small_net(),
    )
    .unwrap()
    .run(&options("conflict"))
    .unwrap();
    assert!(report.interrupted);
    let mut other = PlanConfig::hopg_small_net();
    other.net.step_counts = 15000;
    let error = Calibrator::new(&mut probe, &mut cdb, &mut NoObserver, other)
        .unwrap()
        .run(&options("conflict"))
        .unwrap_err();
    assert!(
        matches!(error, spm_calibration::RunError::Store(_)),
        "{error}"
    );
    assert_eq!(cdb.progress_summary("conflict").unwrap().done, 0);
    drop(cdb);
    let _ = std::fs::remove_file(&path);
}

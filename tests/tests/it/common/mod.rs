//! The small simulated calibration shared by the end-to-end tests: a 6 × 6 net, one pass,
//! on the room-temperature tube scanner (optionally without hysteresis and creep). Returns the
//! report, the simulator after the run (for the oracle and for further scans) and the surfaces
//! read back from the `surfaces.json` the run wrote.
//!
//! The tests share one binary (`tests/it/main.rs`), so [`small_net`] runs each distinct
//! calibration once and hands every test the same result: the run is deterministic (the
//! simulator's randomness is seeded by its config, the run name is only the CDB's label), so
//! tests that asked for the same settings got bit-identical calibrations anyway.

#![allow(dead_code)] // each test file uses part of it

use spm_calibration::{NoObserver, PlanConfig};
use spm_correction::SurfaceSet;
use spm_sim::{SimConfig, Simulator};
use spmcal::job::{Backend, Job};
use spmcal::report::{CalibrationReport, RunRecord, finish_with};
use spmcal::run::{RecordingObserver, RunStart, run_job};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// What a small-net calibration leaves behind.
pub struct SmallNetCalibration {
    /// report.json's content.
    pub report: CalibrationReport,
    /// The simulator after the run: the same scanner, drift and sample go on.
    pub simulator: Simulator,
    /// The surfaces written to surfaces.json.
    pub surfaces: SurfaceSet,
    /// The plan that was run.
    pub plan: PlanConfig,
    /// Every file the run wrote into its output folder (report.json, report.html, the
    /// figures, surfaces.json), by name: the folder itself is removed.
    pub files: BTreeMap<String, Vec<u8>>,
}

pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ lives in the workspace")
        .to_path_buf()
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("spmcal-e2e-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch folder");
    dir
}

/// The small-net calibration with these settings, run once per test binary and shared (the
/// first test to ask runs it, the others wait for it). A test that goes on scanning clones
/// [`SmallNetCalibration::simulator`].
pub fn small_net(
    with_hysteresis_and_creep: bool,
    with_image_benchmark: bool,
) -> &'static SmallNetCalibration {
    static MEMO: [OnceLock<SmallNetCalibration>; 4] = [const { OnceLock::new() }; 4];
    let slot = usize::from(with_hysteresis_and_creep) * 2 + usize::from(with_image_benchmark);
    MEMO[slot].get_or_init(|| {
        let name = format!(
            "small-net-{}{}",
            if with_hysteresis_and_creep {
                "full"
            } else {
                "static"
            },
            if with_image_benchmark { "-images" } else { "" }
        );
        calibrate_small_net(&name, with_hysteresis_and_creep, with_image_benchmark)
    })
}

/// Runs the default HOPG plan reduced to a 6 × 6 net and one pass, fits surfaces and judges
/// them against the oracle (`spmcal::report::finish`).
pub fn calibrate_small_net(
    name: &str,
    with_hysteresis_and_creep: bool,
    with_image_benchmark: bool,
) -> SmallNetCalibration {
    let mut sim = SimConfig::room_temperature_tube().without_random_faults();
    if !with_hysteresis_and_creep {
        sim.scanner.hysteresis_x.width_fraction = 0.0;
        sim.scanner.hysteresis_y.width_fraction = 0.0;
        sim.scanner.creep.log_slope_per_decade = 0.0;
    }
    let (mut plan, plan_text) =
        Job::read_plan(&workspace_root().join("configs/plan-hopg.toml")).expect("default plan");
    plan.repeats = 1;
    plan.net.step_counts = 11_500; // 6 × 6 nodes with a 4000-count margin on a 16-bit field
    let job = Job {
        backend: Backend::Sim(Box::new(sim)),
        plan,
        provenance_text: plan_text,
    };
    let out = scratch(name);
    let cdb = out.join("cdb.sqlite");
    let mut quiet = NoObserver;
    let mut recorder = RecordingObserver::new(&mut quiet);
    let outcome = run_job(
        &job,
        &cdb,
        RunStart::New {
            run_id: name.to_owned(),
        },
        1.8e9,
        &mut recorder,
    )
    .expect("the calibration runs");
    let samples = recorder.into_samples();
    let record = RunRecord::of_job(&job.plan, &outcome, &samples, 0.0);
    let report = finish_with(&cdb, &out, &record, true, with_image_benchmark)
        .expect("surfaces, accuracy and report");
    for file in [
        "report.json",
        "surfaces.json",
        "lcc-kx.png",
        "drift.png",
        "trajectory.png",
    ] {
        assert!(out.join(file).is_file(), "{file} was not written");
    }
    let surfaces_json =
        std::fs::read_to_string(out.join("surfaces.json")).expect("surfaces.json readable");
    let surfaces = SurfaceSet::from_json_str(&surfaces_json).expect("surfaces.json parses");
    let mut files = BTreeMap::new();
    for entry in std::fs::read_dir(&out).expect("output folder readable") {
        let path = entry.expect("output folder entry").path();
        if path.is_file() && path.extension().is_some_and(|e| e != "sqlite") {
            let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
            if let Some(name) = name {
                files.insert(name, std::fs::read(&path).expect("output file readable"));
            }
        }
    }
    let _ = std::fs::remove_dir_all(&out);
    SmallNetCalibration {
        report,
        simulator: outcome
            .instrument
            .into_simulator()
            .expect("a simulated backend returns its simulator"),
        surfaces,
        plan: job.plan,
        files,
    }
}

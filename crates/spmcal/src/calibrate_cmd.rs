//! `spmcal calibrate --config FILE [--cdb PATH] [--resume] [--out DIR]`.

use crate::error::CliError;
use indicatif::{ProgressBar, ProgressStyle};
use spm_calibration::{GiveUpReason, NodeMeasurement, Observer, PlanVisit};
use spmcal::job::Job;
use spmcal::report::{RunRecord, finish};
use spmcal::run::{JobRunError, RecordingObserver, RunStart, run_job};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

struct Progress(ProgressBar);

impl Observer for Progress {
    fn run_started(&mut self, total_visits: usize, already_finished: usize) {
        self.0.set_length(total_visits as u64);
        self.0.set_position(already_finished as u64);
    }
    fn node_finished(&mut self, measurement: &NodeMeasurement) {
        self.0.inc(1);
        self.0.set_message(format!(
            "K̄x {:.5} K̄y {:.5} nm/count α {:+.3}°",
            measurement.lcc.kx.value(),
            measurement.lcc.ky.value(),
            measurement.lcc.alpha.to_degrees()
        ));
    }
    fn node_given_up(&mut self, visit: &PlanVisit, reason: &GiveUpReason) {
        self.0.inc(1);
        self.0.println(format!(
            "node {} (repeat {}) given up: {reason:?}",
            visit.node_index, visit.repeat_index
        ));
    }
}

pub fn run(
    config: &Path,
    cdb: Option<&Path>,
    resume: bool,
    out: Option<&Path>,
) -> Result<(), CliError> {
    let job = Job::from_file(config).map_err(|e| CliError::BadInput(e.to_string()))?;
    let out: PathBuf = out.map_or_else(|| PathBuf::from("spmcal-calibrate"), Path::to_path_buf);
    std::fs::create_dir_all(&out).map_err(|e| CliError::io(&out, e))?;
    let cdb_path = cdb.map_or_else(|| out.join("cdb.sqlite"), Path::to_path_buf);
    let start_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let start = if resume {
        RunStart::Resume
    } else {
        RunStart::New {
            run_id: format!("{}-{}", job.plan.scanner_id, start_unix_s as u64),
        }
    };
    let bar = ProgressBar::new(0);
    if let Ok(style) =
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} nodes {msg}")
    {
        bar.set_style(style);
    }
    let mut progress = Progress(bar);
    let mut recorder = RecordingObserver::new(&mut progress);
    let started = Instant::now();
    let outcome =
        run_job(&job, &cdb_path, start, start_unix_s, &mut recorder).map_err(|e| match e {
            JobRunError::NothingToResume(_) => CliError::BadInput(e.to_string()),
            JobRunError::Cdb(ref inner) if inner.kind() != spm_cdb::ErrorKind::Sqlite => {
                CliError::BadInput(e.to_string())
            }
            other => CliError::RunFailed(other.to_string()),
        })?;
    let wall_time_s = started.elapsed().as_secs_f64();
    let drift = std::mem::take(&mut recorder.drift);
    let nodes = std::mem::take(&mut recorder.nodes);
    drop(recorder);
    progress.0.finish();
    let record = RunRecord {
        plan: &job.plan,
        run: &outcome.report,
        simulator: outcome.simulator.as_ref(),
        drift: &drift,
        nodes: &nodes,
        wall_time_s,
    };
    let report =
        finish(&cdb_path, &out, &record, false).map_err(|e| CliError::RunFailed(e.to_string()))?;
    println!(
        "run {}: {} visits measured now ({} before), {} given up, {} records; CDB {}; report {}",
        outcome.report.run_id,
        outcome.report.nodes_done,
        outcome.report.already_finished,
        outcome.report.given_up.len(),
        report.records,
        cdb_path.display(),
        out.join("report.json").display()
    );
    if outcome.report.interrupted {
        return Err(CliError::RunFailed(
            "the run was interrupted; continue it with --resume".to_owned(),
        ));
    }
    Ok(())
}

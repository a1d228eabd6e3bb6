//! `spmcal calibrate --config FILE [--cdb PATH] [--resume] [--out DIR]`.

use crate::error::CliError;
use spmcal::job::Job;
use spmcal::progress::ProgressBarObserver;
use spmcal::report::{RunRecord, finish};
use spmcal::run::{JobRunError, RecordingObserver, RunStart, run_job};
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

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
    if cdb_path.is_dir() {
        return Err(CliError::BadInput(format!(
            "{}: is a directory, not a calibration database",
            cdb_path.display()
        )));
    }
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
    let mut progress = ProgressBarObserver::new();
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
    let samples = recorder.into_samples();
    progress.finish();
    let record = RunRecord::of_job(&job.plan, &outcome, &samples, wall_time_s);
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

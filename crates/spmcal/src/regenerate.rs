//! `spmcal report`: the report of a finished run, regenerated from the CDB alone (issue 25
//! item 13: a report that failed after the run was marked finished could never be made,
//! since `--resume` takes only unfinished runs).
//!
//! The same code path as after `calibrate` ([`crate::report::finish_with`]), fed from the
//! CDB instead of the run's memory: the plan from the configuration stored with the run, the
//! nodes from the run's records, the dynamics the run stored. What only the running
//! instrument had is **not** regenerated, and the report's notes say so
//! ([`NOT_REGENERATED`]): the accuracy against the oracle, the image benchmark, the node
//! LCCs and the vertical axis against the oracle, and the corrected standard's lattice
//! (they need the simulator or new images of the standard), the drift history and its
//! figure, the dynamics identification's diagnostics (the stored model is used), the
//! cycle counts, instrument and wall time. The surfaces are fitted from the scanner's
//! records in the CDB *now*, as `calibrate` does: runs of the scanner stored after this one
//! enter the fit too (the output says how many).

use crate::cdb_handle::CdbHandle;
use crate::report::{CalibrationReport, ReportError, RunProvenance, RunRecord};
use crate::run::NodeSample;
use spm_calibration::{PlanConfig, RunReport};
use spm_cdb::{CdbRead, NodeState, RecordFilter, RunStatus};
use spm_correction::hysteresis::ScannerDynamics;
use std::path::Path;

/// What a regenerated report lacks, in its notes.
pub const NOT_REGENERATED: &str = "regenerated from the CDB (spmcal report): not regenerated, \
     since only the running instrument had them: the accuracy against the oracle, the image \
     benchmark, the node LCCs and the vertical axis against the oracle, the corrected \
     standard's lattice with its validation map and before/after figure (they need the \
     simulator or new images of the standard), the drift \
     history and its figure, the dynamics identification's diagnostics (the stored model is \
     used), the cycle counts, instrument and wall time; the surfaces are fitted from the \
     scanner's records in the CDB now";

/// Why a report cannot be regenerated.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RegenerateError {
    /// No run of that id.
    #[error("{cdb}: no run {run_id:?} (runs: {known})")]
    UnknownRun {
        /// The CDB as shown.
        cdb: String,
        /// The id asked for.
        run_id: String,
        /// The stored run ids, or "none".
        known: String,
    },
    /// The run has not finished.
    #[error(
        "{cdb}: run {run_id:?} is {status}, not finished; continue it with `spmcal calibrate \
         --resume` (which writes its report)"
    )]
    Unfinished {
        /// The CDB as shown.
        cdb: String,
        /// The run.
        run_id: String,
        /// Its status.
        status: String,
    },
    /// The plan stored with the run cannot be read back.
    #[error("{cdb}: run {run_id:?}: the plan stored with the run cannot be read: {message}")]
    StoredPlan {
        /// The CDB as shown.
        cdb: String,
        /// The run.
        run_id: String,
        /// Why.
        message: String,
    },
    /// The dynamics model stored with the run cannot be read back.
    #[error("{cdb}: run {run_id:?}: the stored dynamics model cannot be read: {message}")]
    StoredDynamics {
        /// The CDB as shown.
        cdb: String,
        /// The run.
        run_id: String,
        /// Why.
        message: String,
    },
    /// Reading the CDB, fitting or writing failed.
    #[error(transparent)]
    Report(#[from] ReportError),
}

impl From<spm_cdb::CdbError> for RegenerateError {
    fn from(e: spm_cdb::CdbError) -> Self {
        Self::Report(ReportError::Cdb(e))
    }
}

impl RegenerateError {
    /// True when the request or the CDB's contents are at fault (exit 2), not the program.
    #[must_use]
    pub fn is_bad_input(&self) -> bool {
        match self {
            Self::UnknownRun { .. }
            | Self::Unfinished { .. }
            | Self::StoredPlan { .. }
            | Self::StoredDynamics { .. } => true,
            Self::Report(ReportError::Cdb(e)) => !matches!(
                e.kind(),
                spm_cdb::ErrorKind::Sqlite
                    | spm_cdb::ErrorKind::Postgres
                    | spm_cdb::ErrorKind::Interrupted
                    | spm_cdb::ErrorKind::Io
            ),
            Self::Report(_) => false,
        }
    }
}

/// A regenerated report and what the output should say of it.
#[derive(Debug)]
pub struct Regenerated {
    /// The report as written to report.json.
    pub report: CalibrationReport,
    /// Runs of the same scanner that started after this one finished (their records are
    /// in the fit).
    pub later_runs: usize,
}

/// The plan stored with a run: the `[plan]` table of the text after a `# plan` line (the
/// stored configuration is the job's files one after another), else of the whole text.
fn stored_plan(config: &str) -> Result<PlanConfig, String> {
    let mut first_error = None;
    let starts = config
        .match_indices("# plan\n")
        .map(|(i, m)| i + m.len())
        .chain(std::iter::once(0));
    for start in starts {
        match PlanConfig::from_toml_str(&config[start..], "the run's stored configuration") {
            Ok(plan) => return Ok(plan),
            Err(e) => {
                first_error.get_or_insert_with(|| e.to_string());
            }
        }
    }
    Err(first_error.unwrap_or_else(|| "no [plan] table".to_owned()))
}

/// The calibrator's summary as far as the CDB holds it: visits, nodes, repeats, done and
/// given-up visits (reasons in `notes`), records.
fn run_summary(
    read: &dyn CdbRead,
    run_id: &str,
    records: usize,
    notes: &mut Vec<String>,
) -> Result<RunReport, spm_cdb::CdbError> {
    let progress = read.progress(run_id)?;
    let mut nodes: Vec<u32> = progress.iter().map(|p| p.node.node_index).collect();
    nodes.sort_unstable();
    nodes.dedup();
    let mut repeats: Vec<u32> = progress.iter().map(|p| p.node.repeat_index).collect();
    repeats.sort_unstable();
    repeats.dedup();
    for p in &progress {
        if let NodeState::GivenUp(reason) = &p.state {
            notes.push(format!(
                "given up (stored): repeat {}, node {}: {reason}",
                p.node.repeat_index, p.node.node_index
            ));
        }
    }
    Ok(RunReport {
        run_id: run_id.to_owned(),
        visits_planned: progress.len(),
        nodes: nodes.len(),
        repeats: u32::try_from(repeats.len()).unwrap_or(u32::MAX),
        nodes_done: progress
            .iter()
            .filter(|p| p.state == NodeState::Done)
            .count(),
        records,
        ..RunReport::default()
    })
}

/// Regenerates `surfaces.json`, `report.json`, the figures and `report.html` of the finished
/// run `run_id` of the CDB at `cdb_path` into `out` (an existing folder), reading the CDB
/// only.
///
/// # Errors
/// [`RegenerateError`]: an unknown or unfinished run, a stored plan or model that cannot be
/// read, and the report's own errors.
pub fn regenerate(
    cdb_path: &Path,
    run_id: &str,
    out: &Path,
) -> Result<Regenerated, RegenerateError> {
    let shown = crate::cdb_handle::shown(cdb_path);
    let cdb = CdbHandle::open_read_only(cdb_path)?;
    let read = cdb.read();
    let Some(run) = read.run(run_id)? else {
        let known: Vec<String> = read.runs(None)?.into_iter().map(|r| r.run_id).collect();
        return Err(RegenerateError::UnknownRun {
            cdb: shown,
            run_id: run_id.to_owned(),
            known: if known.is_empty() {
                "none".to_owned()
            } else {
                known.join(", ")
            },
        });
    };
    if run.status != RunStatus::Finished {
        return Err(RegenerateError::Unfinished {
            cdb: shown,
            run_id: run_id.to_owned(),
            status: run.status.as_str().to_owned(),
        });
    }
    let plan = stored_plan(&run.config).map_err(|message| RegenerateError::StoredPlan {
        cdb: shown.clone(),
        run_id: run_id.to_owned(),
        message,
    })?;
    let dynamics: Option<ScannerDynamics> = read
        .dynamics(Some(&run.scanner_id))?
        .into_iter()
        .rfind(|d| d.run_id == run.run_id)
        .map(|d| serde_json::from_str(&d.model_json))
        .transpose()
        .map_err(|e| RegenerateError::StoredDynamics {
            cdb: shown.clone(),
            run_id: run_id.to_owned(),
            message: e.to_string(),
        })?;
    let mut records = read.records(&RecordFilter::default().with_run(run_id))?;
    records.sort_by(|a, b| a.acquired_unix_s.total_cmp(&b.acquired_unix_s));
    let nodes: Vec<NodeSample> = records
        .iter()
        .filter(|r| r.lcs_index == 0)
        .map(|r| NodeSample {
            repeat_index: r.repeat_index,
            node_index: r.node_index,
            x_counts: r.lcs_x_counts,
            y_counts: r.lcs_y_counts,
            kx_nm_per_count: r.kx_nm_per_count,
            ky_nm_per_count: r.ky_nm_per_count,
            alpha_rad: r.alpha_rad,
        })
        .collect();
    let mut given_up = Vec::new();
    let summary = run_summary(read, run_id, records.len(), &mut given_up)?;
    let finished_unix_s = run.finished_unix_s.unwrap_or(run.started_unix_s);
    let later_runs = read
        .runs(Some(&run.scanner_id))?
        .iter()
        .filter(|r| r.run_id != run.run_id && r.started_unix_s > finished_unix_s)
        .count();
    drop(cdb);
    let provenance = RunProvenance {
        started_utc: spm_cdb::rfc3339_utc(run.started_unix_s),
        finished_utc: spm_cdb::rfc3339_utc(finished_unix_s),
        spmcal_version: env!("CARGO_PKG_VERSION").to_owned(),
        spmcal_commit: option_env!("SPMCAL_GIT_COMMIT").map(str::to_owned),
        host: None,
        backend: format!("not known: report regenerated from the CDB {shown}"),
        seed: None,
        inputs: Vec::new(),
    };
    let mut record = RunRecord::of_stored(&plan, &summary, &nodes, &provenance);
    record.stored_dynamics = dynamics.as_ref();
    record.extra_notes = std::iter::once(NOT_REGENERATED.to_owned())
        .chain(given_up)
        .collect();
    let report = crate::report::finish_with(cdb_path, out, &record, false, false)?;
    Ok(Regenerated { report, later_runs })
}

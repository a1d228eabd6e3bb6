//! `spmcal report --cdb PATH|URL --run ID --out DIR`: regenerates the report of a finished
//! run from the CDB ([`spmcal::regenerate`]); an unknown or unfinished run is bad input.

use crate::calibrate_cmd::OUTPUT_FILES;
use crate::error::CliError;
use spmcal::regenerate::{NOT_REGENERATED, regenerate};
use std::path::Path;

pub fn run(cdb_path: &Path, run_id: &str, out: &Path) -> Result<(), CliError> {
    if !spmcal::cdb_handle::is_postgres(cdb_path) {
        if !cdb_path.exists() {
            return Err(CliError::BadInput(format!(
                "{}: no such calibration database",
                cdb_path.display()
            )));
        }
        crate::files::check_input(cdb_path, "calibration database")?;
    }
    for name in OUTPUT_FILES {
        let target = out.join(name);
        crate::files::check_output(&target, "--out", &[cdb_path])?;
        crate::files::check_output(&spmcal::report::partial_path(&target), "--out", &[cdb_path])?;
    }
    std::fs::create_dir_all(out).map_err(|e| CliError::io(out, e))?;
    let done = regenerate(cdb_path, run_id, out).map_err(|e| {
        if e.is_bad_input() {
            CliError::BadInput(e.to_string())
        } else {
            CliError::RunFailed(e.to_string())
        }
    })?;
    crate::outln!(
        "run {run_id}: report regenerated from the CDB {}: {} records; report {}",
        spmcal::cdb_handle::shown(cdb_path),
        done.report.records,
        out.join("report.json").display()
    );
    for line in done.report.summary_text().lines() {
        crate::outln!("{line}");
    }
    crate::outln!("{NOT_REGENERATED}");
    if done.later_runs > 0 {
        crate::outln!(
            "note: {} later runs of scanner {} are in the CDB; their records are in the fit, \
             as they would be in a calibration today",
            done.later_runs,
            done.report.scanner_id
        );
    }
    crate::outln!("report: {}", out.join("report.html").display());
    Ok(())
}

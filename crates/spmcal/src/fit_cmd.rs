//! `spmcal fit --cdb PATH [--scanner ID] [--since DATE] [--until DATE] --out surfaces.json`.

use crate::cdb_cmd::cdb_error;
use crate::dates::parse_utc;
use crate::error::CliError;
use spmcal::surfaces::{SurfaceFitError, SurfaceFitOptions, fit_from_cdb};
use std::path::Path;

/// Highest degree tried by BIC for every coefficient surface.
pub use spmcal::report::MAX_SURFACE_DEGREE;

pub fn run(
    cdb_path: &Path,
    scanner: Option<&str>,
    since: Option<&str>,
    until: Option<&str>,
    out: &Path,
) -> Result<(), CliError> {
    let since = since.map(|s| parse_utc("--since", s)).transpose()?;
    let until = until.map(|s| parse_utc("--until", s)).transpose()?;
    if !cdb_path.is_file() {
        return Err(CliError::BadInput(format!(
            "{}: no such calibration database",
            cdb_path.display()
        )));
    }
    let cdb = spm_cdb::Cdb::open_read_only(cdb_path).map_err(cdb_error)?;
    let snapshot = cdb.snapshot().map_err(cdb_error)?;
    let fitted = fit_from_cdb(
        &snapshot,
        scanner,
        since,
        until,
        &SurfaceFitOptions::bic_up_to(MAX_SURFACE_DEGREE),
    )
    .map_err(|e| match e {
        SurfaceFitError::Cdb(e) => cdb_error(e),
        SurfaceFitError::NoRecords { .. } | SurfaceFitError::AmbiguousScanner(_) => {
            CliError::BadInput(e.to_string())
        }
        other => CliError::RunFailed(other.to_string()),
    })?;
    let json = fitted
        .set
        .to_json_string()
        .map_err(|e| CliError::RunFailed(e.to_string()))?;
    crate::write_atomically(out, json.as_bytes())?;
    let s = fitted.summary;
    println!(
        "{} planes, {} records → {}",
        fitted.set.planes.len(),
        fitted.set.provenance.n_records,
        out.display()
    );
    println!(
        "K̄x: degree {} σ {:.2e} nm/count; K̄y: degree {} σ {:.2e} nm/count; α: degree {} σ {:.2e} rad",
        s.kx.degree, s.kx.sigma, s.ky.degree, s.ky.sigma, s.alpha.degree, s.alpha.sigma
    );
    Ok(())
}

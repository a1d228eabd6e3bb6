//! `spmcal cdb check|export|trend`.

use crate::error::CliError;
use spm_cdb::{Cdb, CdbRead, Coefficient, RecordFilter, TrendGrouping};
use std::path::Path;

fn open_read_only(path: &Path) -> Result<Cdb, CliError> {
    if !path.is_file() {
        return Err(CliError::BadInput(format!(
            "{}: no such calibration database",
            path.display()
        )));
    }
    Cdb::open_read_only(path).map_err(cdb_error)
}

/// Maps a CDB error to the exit-code classes: bad or foreign files are bad input.
pub fn cdb_error(error: spm_cdb::CdbError) -> CliError {
    use spm_cdb::ErrorKind;
    match error.kind() {
        ErrorKind::Sqlite | ErrorKind::Io => CliError::RunFailed(error.to_string()),
        _ => CliError::BadInput(error.to_string()),
    }
}

pub fn check(path: &Path) -> Result<(), CliError> {
    let cdb = open_read_only(path)?;
    let report = cdb.check().map_err(cdb_error)?;
    if report.is_ok() {
        let records = cdb
            .count_records(&RecordFilter::default())
            .map_err(cdb_error)?;
        println!(
            "{}: ok (schema version {}, {records} records)",
            path.display(),
            cdb.schema_version().map_err(cdb_error)?
        );
        return Ok(());
    }
    for line in &report.sqlite {
        println!("sqlite: {line}");
    }
    for problem in &report.problems {
        println!("{}: {}", problem.kind, problem.detail);
    }
    Err(CliError::RunFailed(format!(
        "{}: integrity check failed ({} problems)",
        path.display(),
        report.sqlite.len() + report.problems.len()
    )))
}

pub fn export(path: &Path, csv: &Path) -> Result<(), CliError> {
    let cdb = open_read_only(path)?;
    // Write to a temporary file beside the target and rename, so a failed export
    // never leaves a truncated CSV under the requested name.
    let partial = csv.with_extension("csv.partial");
    let file = std::fs::File::create(&partial).map_err(|e| CliError::io(&partial, e))?;
    let mut writer = std::io::BufWriter::new(file);
    let snapshot = cdb.snapshot().map_err(cdb_error)?;
    let count = snapshot
        .export_csv(&RecordFilter::default(), &mut writer)
        .map_err(cdb_error)?;
    use std::io::Write;
    writer.flush().map_err(|e| CliError::io(&partial, e))?;
    drop(writer);
    std::fs::rename(&partial, csv).map_err(|e| CliError::io(csv, e))?;
    println!("{count} records → {}", csv.display());
    Ok(())
}

pub fn trend(path: &Path) -> Result<(), CliError> {
    let cdb = open_read_only(path)?;
    let snapshot = cdb.snapshot().map_err(cdb_error)?;
    for scanner in snapshot.scanners().map_err(cdb_error)? {
        println!("scanner {scanner}");
        for (coefficient, label, scale, unit) in [
            (Coefficient::KxNmPerCount, "K̄x", 1.0, "nm/count"),
            (Coefficient::KyNmPerCount, "K̄y", 1.0, "nm/count"),
            (
                Coefficient::AlphaRad,
                "α",
                180.0 / std::f64::consts::PI,
                "deg",
            ),
            (Coefficient::KzNmPerCount, "Kz", 1.0, "nm/count"),
        ] {
            let points = snapshot
                .age_dynamics(
                    &RecordFilter::scanner(&scanner),
                    coefficient,
                    TrendGrouping::PerRun,
                )
                .map_err(cdb_error)?;
            println!("  {label} ({unit}) per run:");
            for point in points {
                match point.stat {
                    Some(stat) => println!(
                        "    {}  {:<24} n = {:<6} mean = {:.6e} ± {:.1e} (sd {:.1e})",
                        spm_cdb::rfc3339_utc(point.mean_unix_s),
                        point.key,
                        stat.n,
                        stat.mean * scale,
                        stat.std_uncertainty * scale,
                        stat.std_dev * scale
                    ),
                    None => println!(
                        "    {}  {:<24} not measured",
                        spm_cdb::rfc3339_utc(point.mean_unix_s),
                        point.key
                    ),
                }
            }
        }
    }
    Ok(())
}

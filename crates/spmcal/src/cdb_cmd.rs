//! `spmcal cdb check|export|backup|trend`.

use crate::error::CliError;
use spm_cdb::{CdbRead, Coefficient, RecordFilter, TrendGrouping};
use spmcal::cdb_handle::{CdbHandle, is_postgres, shown};
use std::path::Path;

/// Opens a CDB for the commands that only read it: a PostgreSQL URL (a read-only session),
/// or a regular file (checked before opening), opened read-only (also in a read-only folder
/// or mount).
pub fn open_read_only(path: &Path) -> Result<CdbHandle, CliError> {
    if is_postgres(path) {
        return CdbHandle::open_read_only(path).map_err(cdb_error);
    }
    if !path.exists() {
        return Err(CliError::BadInput(format!(
            "{}: no such calibration database",
            path.display()
        )));
    }
    crate::files::check_input(path, "calibration database")?;
    CdbHandle::open_read_only(path).map_err(cdb_error)
}

/// A writer that remembers its first I/O error, so that a failed export names the output
/// file rather than the CDB.
struct Tracked<W> {
    inner: W,
    error: Option<std::io::Error>,
}

impl<W: std::io::Write> std::io::Write for Tracked<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.inner.write(buf).inspect_err(|e| {
            self.error
                .get_or_insert_with(|| std::io::Error::new(e.kind(), e.to_string()));
        })
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush().inspect_err(|e| {
            self.error
                .get_or_insert_with(|| std::io::Error::new(e.kind(), e.to_string()));
        })
    }
}

/// Maps a CDB error to the exit-code classes: bad or foreign files are bad input.
pub fn cdb_error(error: spm_cdb::CdbError) -> CliError {
    use spm_cdb::ErrorKind;
    match error.kind() {
        ErrorKind::Sqlite | ErrorKind::Postgres | ErrorKind::Interrupted | ErrorKind::Io => {
            CliError::RunFailed(error.to_string())
        }
        _ => CliError::BadInput(error.to_string()),
    }
}

pub fn check(path: &Path) -> Result<(), CliError> {
    let handle = open_read_only(path)?;
    let snapshot = handle.snapshot_unfiltered().map_err(cdb_error)?;
    let cdb: &dyn CdbRead = &*snapshot;
    let report = cdb.check().map_err(cdb_error)?;
    if report.is_ok() {
        let records = cdb
            .count_records(&RecordFilter::default())
            .map_err(cdb_error)?;
        crate::outln!(
            "{}: ok (schema version {}, {records} records)",
            shown(path),
            cdb.schema_version().map_err(cdb_error)?
        );
        return Ok(());
    }
    let engine = if is_postgres(path) {
        "postgres"
    } else {
        "sqlite"
    };
    for line in &report.sqlite {
        crate::outln!("{engine}: {line}");
    }
    for problem in &report.problems {
        crate::outln!("{}: {}", problem.kind, problem.detail);
    }
    Err(CliError::RunFailed(format!(
        "{}: integrity check failed ({} problems)",
        shown(path),
        report.sqlite.len() + report.problems.len()
    )))
}

pub fn export(path: &Path, csv: &Path) -> Result<(), CliError> {
    crate::files::check_output(csv, "--csv", &[path])?;
    let cdb = open_read_only(path)?;
    // Write to a hidden temporary file beside the target and rename, so a failed export
    // never leaves a truncated CSV under the requested name, nor a temporary file.
    let partial = crate::files::temporary_beside(csv);
    let result = write_csv(&cdb, csv, &partial);
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    let count = result?;
    crate::outln!("{count} records → {}", csv.display());
    Ok(())
}

fn write_csv(cdb: &CdbHandle, csv: &Path, partial: &Path) -> Result<u64, CliError> {
    use std::io::Write;
    let file = std::fs::File::create(partial).map_err(|e| CliError::io(csv, e))?;
    let mut writer = Tracked {
        inner: std::io::BufWriter::new(file),
        error: None,
    };
    let snapshot = cdb.snapshot_unfiltered().map_err(cdb_error)?;
    let exported = snapshot.export_csv(&RecordFilter::default(), &mut writer);
    let flushed = writer.flush();
    if let Some(e) = writer.error.take() {
        return Err(CliError::io(csv, e));
    }
    let count = exported.map_err(cdb_error)?;
    flushed.map_err(|e| CliError::io(csv, e))?;
    let file = writer
        .inner
        .into_inner()
        .map_err(|e| CliError::io(csv, e.into_error()))?;
    file.sync_all().map_err(|e| CliError::io(csv, e))?;
    drop(file);
    std::fs::rename(partial, csv).map_err(|e| CliError::io(csv, e))?;
    Ok(count)
}

/// `spmcal cdb backup SRC DEST`: a consistent copy of a SQLite CDB in a new file (see
/// [`spm_cdb::Cdb::backup_to`]); a PostgreSQL CDB is backed up with `pg_dump`.
pub fn backup(src: &Path, dest: &Path) -> Result<(), CliError> {
    if is_postgres(src) {
        return Err(CliError::BadInput(format!(
            "{}: `spmcal cdb backup` copies SQLite files; back up a PostgreSQL CDB with \
             pg_dump (e.g. `pg_dump --format=custom --file=cdb.dump DBNAME`, restored with \
             pg_restore)",
            shown(src)
        )));
    }
    if is_postgres(dest) {
        return Err(CliError::BadInput(format!(
            "DEST {}: a backup is written to a file, not to a PostgreSQL database",
            shown(dest)
        )));
    }
    let same_id = matches!(
        (crate::files::identity(src), crate::files::identity(dest)),
        (Some(a), Some(b)) if a == b
    );
    if same_id || crate::files::location(src) == crate::files::location(dest) {
        return Err(CliError::BadInput(format!(
            "DEST {}: is the source database {}; refusing to overwrite it",
            dest.display(),
            src.display()
        )));
    }
    if std::fs::symlink_metadata(dest).is_ok() {
        return Err(CliError::BadInput(format!(
            "DEST {}: exists; refusing to overwrite it (a backup goes to a new file)",
            dest.display()
        )));
    }
    crate::files::check_output(dest, "DEST", &[src])?;
    let handle = open_read_only(src)?;
    let CdbHandle::Sqlite(cdb) = &handle else {
        return Err(CliError::BadInput(format!(
            "{}: not a SQLite CDB",
            shown(src)
        )));
    };
    let summary = cdb.backup_to(dest).map_err(cdb_error)?;
    crate::outln!(
        "{} → {}: {} records, {} bytes, integrity ok",
        src.display(),
        dest.display(),
        summary.records,
        summary.bytes
    );
    Ok(())
}

/// `spmcal cdb trend PATH [--png OUT.png]`: the per-run means as text, and with `--png` the
/// K̄x and K̄y history as a figure ([`spmcal::plots::cdb_trend_figure`]).
pub fn trend(path: &Path, png: Option<&Path>) -> Result<(), CliError> {
    if let Some(png) = png {
        crate::files::check_output(png, "--png", &[path])?;
    }
    let cdb = open_read_only(path)?;
    let snapshot = cdb.snapshot_unfiltered().map_err(cdb_error)?;
    let mut history: Vec<(String, &str, Vec<spm_cdb::TrendPoint>)> = Vec::new();
    for scanner in snapshot.scanners().map_err(cdb_error)? {
        crate::outln!("scanner {scanner}");
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
            crate::outln!("  {label} ({unit}) per run:");
            if matches!(
                coefficient,
                Coefficient::KxNmPerCount | Coefficient::KyNmPerCount
            ) {
                history.push((scanner.clone(), label, points.clone()));
            }
            for point in points {
                match point.stat {
                    Some(stat) => crate::outln!(
                        "    {}  {:<24} n = {:<6} mean = {:.6e} ± {:.1e} (sd {:.1e})",
                        spm_cdb::rfc3339_utc(point.mean_unix_s),
                        point.key,
                        stat.n,
                        stat.mean * scale,
                        stat.std_uncertainty * scale,
                        stat.std_dev * scale
                    ),
                    None => crate::outln!(
                        "    {}  {:<24} not measured",
                        spm_cdb::rfc3339_utc(point.mean_unix_s),
                        point.key
                    ),
                }
            }
        }
    }
    if let Some(png) = png {
        let series: Vec<spmcal::plots::TrendSeries<'_>> = history
            .iter()
            .map(
                |(scanner, coefficient, points)| spmcal::plots::TrendSeries {
                    scanner,
                    coefficient,
                    points,
                },
            )
            .collect();
        let bytes = spmcal::plots::cdb_trend_figure(&series).map_err(|e| {
            CliError::BadInput(format!(
                "--png {}: {} has no run with a value to draw ({e})",
                png.display(),
                path.display()
            ))
        })?;
        crate::files::write_atomically(png, &bytes)?;
        crate::outln!("figure: {}", png.display());
    }
    Ok(())
}

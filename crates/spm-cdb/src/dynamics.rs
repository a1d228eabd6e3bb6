//! The scanner dynamics (schema v5) on SQLite: store, read, and the rules `cdb check`
//! applies to every stored row (shared with PostgreSQL).

use rusqlite::{Connection, Row, params};
use std::path::Path;

use crate::error::{CdbError, Result};
use spm_records::{DynamicsProblem, DynamicsRecord, IntegrityProblem};

/// [`spm_records::DYNAMICS_RECORD_COLUMNS`] as an SQL column list (checked by a test).
pub(crate) const DYNAMICS_COLUMNS: &str =
    "run_id, scanner_id, identified_unix_s, model_format, model_version, model_json";

/// Refuses a record that breaks [`DynamicsRecord::check`] (invalid input naming the field).
pub(crate) fn validate(path: &Path, d: &DynamicsRecord) -> Result<()> {
    d.check().map_err(|p| crate::invalid(path, p.to_string()))
}

/// Refuses a record whose scanner is not its run's.
pub(crate) fn check_run_scanner(path: &Path, d: &DynamicsRecord, run_scanner: &str) -> Result<()> {
    if d.scanner_id == run_scanner {
        return Ok(());
    }
    Err(crate::invalid(
        path,
        format!(
            "dynamics (run {:?}): scanner_id {:?} differs from the run's scanner {run_scanner:?}",
            d.run_id, d.scanner_id
        ),
    ))
}

/// The error for a record whose run is not stored.
pub(crate) fn unknown_run(path: &Path, d: &DynamicsRecord) -> CdbError {
    CdbError::NotFound {
        path: path.to_path_buf(),
        what: format!(
            "run {:?} (the run that identified the dynamics of scanner {:?})",
            d.run_id, d.scanner_id
        ),
    }
}

/// A stored `model_version` as `u32`, or corrupt data.
pub(crate) fn stored_version(path: &Path, v: i64) -> Result<u32> {
    u32::try_from(v).map_err(|_| CdbError::Corrupt {
        path: path.to_path_buf(),
        reason: format!("dynamics.model_version {v} is not a version number"),
    })
}

fn from_row(path: &Path, r: &Row<'_>) -> Result<DynamicsRecord> {
    let corrupt = |e: rusqlite::Error| CdbError::Corrupt {
        path: path.to_path_buf(),
        reason: format!("dynamics row: {e}"),
    };
    Ok(DynamicsRecord {
        run_id: r.get(0).map_err(corrupt)?,
        scanner_id: r.get(1).map_err(corrupt)?,
        identified_unix_s: r.get(2).map_err(corrupt)?,
        model_format: r.get(3).map_err(corrupt)?,
        model_version: stored_version(path, r.get(4).map_err(corrupt)?)?,
        model_json: r.get(5).map_err(corrupt)?,
    })
}

/// The dynamics of one scanner (or of all, by scanner), oldest first.
pub(crate) fn list(
    conn: &Connection,
    path: &Path,
    scanner_id: Option<&str>,
) -> Result<Vec<DynamicsRecord>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE ?1 IS NULL OR scanner_id = ?1 \
             ORDER BY scanner_id, identified_unix_s, id"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([scanner_id]).map_err(err)?;
    let mut out = Vec::new();
    while let Some(r) = rows.next().map_err(err)? {
        out.push(from_row(path, r)?);
    }
    Ok(out)
}

/// The newest dynamics of a scanner (the last of [`list`]).
pub(crate) fn latest(
    conn: &Connection,
    path: &Path,
    scanner_id: &str,
) -> Result<Option<DynamicsRecord>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE scanner_id = ?1 \
             ORDER BY identified_unix_s DESC, id DESC LIMIT 1"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([scanner_id]).map_err(err)?;
    match rows.next().map_err(err)? {
        Some(r) => Ok(Some(from_row(path, r)?)),
        None => Ok(None),
    }
}

/// Inserts a validated record inside the caller's write transaction, after finding its run.
pub(crate) fn insert(tx: &Connection, path: &Path, d: &DynamicsRecord) -> Result<()> {
    let err = |e| CdbError::sqlite(path, e);
    let run = crate::query::run(tx, path, &d.run_id)?.ok_or_else(|| unknown_run(path, d))?;
    check_run_scanner(path, d, &run.scanner_id)?;
    tx.execute(
        &format!("INSERT INTO dynamics ({DYNAMICS_COLUMNS}) VALUES (?1, ?2, ?3, ?4, ?5, ?6)"),
        params![
            d.run_id,
            d.scanner_id,
            d.identified_unix_s,
            d.model_format,
            d.model_version,
            d.model_json
        ],
    )
    .map_err(err)?;
    Ok(())
}

/// The finding `cdb check` makes of a stored row that breaks [`DynamicsRecord::check`]:
/// `non_finite` for a time that is not finite, `invalid_model_json` for a model that is not
/// a JSON object of bounded size, `invalid_dynamics` for the other rules.
pub(crate) fn problem(id: i64, d: &DynamicsRecord) -> Option<IntegrityProblem> {
    let p = d.check().err()?;
    let kind = match &p {
        DynamicsProblem::BadTime { .. } if !d.identified_unix_s.is_finite() => "non_finite",
        DynamicsProblem::TooLarge { .. } | DynamicsProblem::NotAnObject { .. } => {
            "invalid_model_json"
        }
        _ => "invalid_dynamics",
    };
    Some(IntegrityProblem {
        kind: kind.into(),
        detail: format!("dynamics id {id}: {p}"),
    })
}

/// Applies [`problem`] to every row of `dynamics` whose columns have their types and whose
/// version is in range (the SQL rules of `cdb check` name the others), at most `max`
/// findings per kind.
pub(crate) fn check_rows(
    conn: &Connection,
    path: &Path,
    max: usize,
) -> Result<Vec<IntegrityProblem>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT id, {DYNAMICS_COLUMNS} FROM dynamics WHERE typeof(run_id) = 'text' \
             AND typeof(scanner_id) = 'text' AND typeof(identified_unix_s) IN ('real', 'integer') \
             AND typeof(model_format) = 'text' AND typeof(model_version) = 'integer' \
             AND model_version BETWEEN 1 AND 4294967295 AND typeof(model_json) = 'text' \
             ORDER BY id"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([]).map_err(err)?;
    let mut found = Findings::new(max);
    while let Some(r) = rows.next().map_err(err)? {
        let id: i64 = r.get(0).map_err(err)?;
        let d = DynamicsRecord {
            run_id: r.get(1).map_err(err)?,
            scanner_id: r.get(2).map_err(err)?,
            identified_unix_s: r.get(3).map_err(err)?,
            model_format: r.get(4).map_err(err)?,
            model_version: stored_version(path, r.get(5).map_err(err)?)?,
            model_json: r.get(6).map_err(err)?,
        };
        found.add(problem(id, &d));
    }
    Ok(found.into_problems())
}

/// Findings with at most `max` per kind, then one "… more" line.
pub(crate) struct Findings {
    max: usize,
    counts: std::collections::HashMap<String, usize>,
    problems: Vec<IntegrityProblem>,
}

impl Findings {
    pub(crate) fn new(max: usize) -> Self {
        Self {
            max,
            counts: std::collections::HashMap::new(),
            problems: Vec::new(),
        }
    }

    pub(crate) fn add(&mut self, p: Option<IntegrityProblem>) {
        let Some(p) = p else { return };
        let n = self.counts.entry(p.kind.clone()).or_insert(0);
        *n += 1;
        if *n <= self.max {
            self.problems.push(p);
        } else if *n == self.max + 1 {
            self.problems.push(IntegrityProblem {
                kind: p.kind,
                detail: format!("… more than {} rows", self.max),
            });
        }
    }

    pub(crate) fn into_problems(self) -> Vec<IntegrityProblem> {
        self.problems
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_sql_column_list_is_the_records_one() {
        assert_eq!(
            super::DYNAMICS_COLUMNS,
            spm_records::DYNAMICS_RECORD_COLUMNS.join(", ")
        );
    }
}

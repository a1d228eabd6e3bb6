//! `PRAGMA integrity_check` plus semantic checks of the stored data.

use rusqlite::Connection;
use std::path::Path;

use crate::error::{CdbError, Result};
use spm_records::{ColumnKind, IntegrityProblem, IntegrityReport, LCC_RECORD_COLUMNS};

/// Report at most this many rows per kind of problem.
const MAX_ROWS_PER_CHECK: usize = 1000;

/// Names of the record columns of one kind ([`spm_records::LCC_RECORD_COLUMNS`]).
fn columns_of(kind: ColumnKind) -> impl Iterator<Item = &'static str> {
    LCC_RECORD_COLUMNS
        .iter()
        .filter(move |c| c.kind == kind)
        .map(|c| c.name)
}

/// SQL predicate true when `col` is not a finite number (NULL counts as not finite).
fn not_finite(col: &str) -> String {
    format!("(typeof({col}) NOT IN ('real', 'integer') OR abs({col}) > 1.7976931348623157e308)")
}

struct Checker<'a> {
    conn: &'a Connection,
    path: &'a Path,
    report: IntegrityReport,
}

impl Checker<'_> {
    /// Runs `sql` (selecting one text column describing the row) and records each row as a
    /// problem of `kind`.
    fn rows(&mut self, kind: &str, sql: &str) -> Result<()> {
        let err = |e| CdbError::sqlite(self.path, e);
        let mut stmt = self.conn.prepare(sql).map_err(err)?;
        let mut rows = stmt.query([]).map_err(err)?;
        let mut n = 0;
        while let Some(r) = rows.next().map_err(err)? {
            n += 1;
            if n > MAX_ROWS_PER_CHECK {
                self.report.problems.push(IntegrityProblem {
                    kind: kind.into(),
                    detail: format!("… more than {MAX_ROWS_PER_CHECK} rows"),
                });
                break;
            }
            let detail: String = r.get(0).map_err(err)?;
            self.report.problems.push(IntegrityProblem {
                kind: kind.into(),
                detail,
            });
        }
        Ok(())
    }

    fn record_rows(&mut self, kind: &str, what: &str, predicate: &str) -> Result<()> {
        let sql = format!(
            "SELECT 'record id ' || id || ' (run ' || quote(run_id) || ', repeat ' || \
             quote(repeat_index) || ', node ' || quote(node_index) || '): {what}' \
             FROM records WHERE {predicate} ORDER BY id"
        );
        self.rows(kind, &sql)
    }
}

pub(crate) fn check(conn: &Connection, path: &Path) -> Result<IntegrityReport> {
    let err = |e| CdbError::sqlite(path, e);
    let mut c = Checker {
        conn,
        path,
        report: IntegrityReport::default(),
    };
    {
        let mut stmt = conn.prepare("PRAGMA integrity_check").map_err(err)?;
        let lines = stmt
            .query_map([], |r| r.get::<_, String>(0))
            .map_err(err)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(err)?;
        c.report
            .sqlite
            .extend(lines.into_iter().filter(|l| l != "ok"));
        let mut stmt = conn.prepare("PRAGMA foreign_key_check").map_err(err)?;
        let fk = stmt
            .query_map([], |r| {
                Ok(format!(
                    "foreign key: table {} rowid {:?} references {}",
                    r.get::<_, String>(0)?,
                    r.get::<_, Option<i64>>(1)?,
                    r.get::<_, String>(2)?
                ))
            })
            .map_err(err)?
            .collect::<rusqlite::Result<Vec<_>>>()
            .map_err(err)?;
        c.report.sqlite.extend(fk);
    }
    if !c.report.sqlite.is_empty() {
        // Structural damage: semantic queries may be meaningless.
        return Ok(c.report);
    }
    for col in columns_of(ColumnKind::Real) {
        c.record_rows("non_finite", &format!("{col} not finite"), &not_finite(col))?;
    }
    for col in columns_of(ColumnKind::OptionalReal) {
        c.record_rows(
            "non_finite",
            &format!("{col} not finite"),
            &format!("{col} IS NOT NULL AND {}", not_finite(col)),
        )?;
    }
    for col in columns_of(ColumnKind::Integer) {
        c.record_rows(
            "bad_type",
            &format!("{col} not an integer"),
            &format!("typeof({col}) != 'integer'"),
        )?;
    }
    for col in spm_records::POSITIVE_COLUMNS {
        c.record_rows(
            "nonpositive_lcc",
            &format!("{col} <= 0"),
            &format!("typeof({col}) IN ('real', 'integer') AND {col} <= 0"),
        )?;
    }
    c.record_rows(
        "alpha_out_of_range",
        "|alpha_rad| >= pi/2",
        "typeof(alpha_rad) IN ('real', 'integer') AND abs(alpha_rad) >= 1.5707963267948966",
    )?;
    for col in spm_records::UNCERTAINTY_COLUMNS {
        c.record_rows(
            "negative_uncertainty",
            &format!("{col} < 0"),
            &format!("typeof({col}) IN ('real', 'integer') AND {col} < 0"),
        )?;
    }
    for col in [
        "repeat_index",
        "node_index",
        "lcs_index",
        "cycles_kept",
        "cycles_discarded",
    ] {
        c.record_rows(
            "negative_count",
            &format!("{col} < 0"),
            &format!("typeof({col}) = 'integer' AND {col} < 0"),
        )?;
    }
    c.rows(
        "duplicate_record",
        "SELECT 'run ' || quote(run_id) || ', repeat ' || quote(repeat_index) || ', node ' || \
         quote(node_index) || ', lcs ' || quote(lcs_index) || ': ' || count(*) || ' records' \
         FROM records GROUP BY run_id, repeat_index, node_index, lcs_index HAVING count(*) > 1",
    )?;
    c.rows(
        "done_without_records",
        "SELECT 'run ' || quote(p.run_id) || ', repeat ' || p.repeat_index || ', node ' || \
         p.node_index || ' is done but has no record' FROM progress p WHERE p.state = 'done' \
         AND NOT EXISTS (SELECT 1 FROM records r WHERE r.run_id = p.run_id AND \
         r.repeat_index = p.repeat_index AND r.node_index = p.node_index) \
         ORDER BY p.run_id, p.repeat_index, p.node_index",
    )?;
    c.rows(
        "records_for_unfinished_node",
        "SELECT 'run ' || quote(p.run_id) || ', repeat ' || p.repeat_index || ', node ' || \
         p.node_index || ' is ' || p.state || ' but has records' FROM progress p \
         WHERE p.state != 'done' AND EXISTS (SELECT 1 FROM records r WHERE \
         r.run_id = p.run_id AND r.repeat_index = p.repeat_index AND \
         r.node_index = p.node_index) ORDER BY p.run_id, p.repeat_index, p.node_index",
    )?;
    c.rows(
        "node_mismatch",
        "SELECT 'record id ' || r.id || ': node (' || r.node_x_counts || ', ' || \
         r.node_y_counts || ', ' || r.node_z_counts || ') differs from its plan node' \
         FROM records r JOIN progress p ON r.run_id = p.run_id AND \
         r.repeat_index = p.repeat_index AND r.node_index = p.node_index \
         WHERE r.node_x_counts != p.node_x_counts OR r.node_y_counts != p.node_y_counts \
         OR r.node_z_counts != p.node_z_counts ORDER BY r.id",
    )?;
    c.rows(
        "given_up_without_reason",
        "SELECT 'run ' || quote(run_id) || ', repeat ' || repeat_index || ', node ' || \
         node_index || ' given up without a reason' FROM progress WHERE state = 'given_up' \
         AND (reason IS NULL OR reason = '')",
    )?;
    c.rows(
        "scanner_mismatch",
        "SELECT 'record id ' || r.id || ': scanner ' || quote(r.scanner_id) || \
         ' but run ' || quote(r.run_id) || ' is on ' || quote(u.scanner_id) \
         FROM records r JOIN runs u ON r.run_id = u.run_id \
         WHERE r.scanner_id != u.scanner_id ORDER BY r.id",
    )?;
    if !c.report.problems.is_empty() {
        tracing::warn!(
            path = %path.display(),
            problems = c.report.problems.len(),
            "CDB integrity problems"
        );
    }
    Ok(c.report)
}

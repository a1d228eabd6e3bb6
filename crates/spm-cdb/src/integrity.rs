//! `PRAGMA integrity_check` plus semantic checks of the stored data.

use rusqlite::Connection;
use std::path::Path;

use crate::error::{CdbError, Result};
use spm_records::{
    ColumnKind, IntegrityProblem, IntegrityReport, LCC_RECORD_COLUMNS, LccRecord, Plausibility,
    RecordFilter,
};
use std::collections::HashMap;

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

/// How a row of each table is named in a finding.
const ROW_NAMES: [(&str, &str); 4] = [
    ("runs", "'run ' || quote(run_id)"),
    (
        "progress",
        "'run ' || quote(run_id) || ', repeat ' || quote(repeat_index) || ', node ' || \
         quote(node_index)",
    ),
    ("records", "'record id ' || id"),
    ("dynamics", "'dynamics id ' || id"),
];

/// The schema's CHECK and NOT NULL constraints, queried explicitly: `PRAGMA
/// integrity_check` skips them on a read-only connection (issue 25), so a damaged run
/// status or a NULL where the schema forbids one would otherwise pass. (`typeof(c) =
/// 'null'`, not `c IS NULL`: SQLite folds the latter to false on a NOT NULL column.)
fn constraint_checks(c: &mut Checker<'_>) -> Result<()> {
    schema_checks(c)?;
    c.rows(
        "invalid_status",
        "SELECT 'run ' || quote(run_id) || ': status ' || quote(status) || ' (bytes ' || \
         hex(status) || ') is not running, finished, failed or aborted' FROM runs \
         WHERE typeof(status) != 'text' OR status NOT IN \
         ('running', 'finished', 'failed', 'aborted') ORDER BY run_id",
    )?;
    c.rows(
        "invalid_state",
        "SELECT 'run ' || quote(run_id) || ', repeat ' || quote(repeat_index) || ', node ' || \
         quote(node_index) || ': state ' || quote(state) || ' (bytes ' || hex(state) || \
         ') is not pending, done or given_up' FROM progress WHERE \
         typeof(state) != 'text' OR state NOT IN ('pending', 'done', 'given_up') \
         ORDER BY run_id, repeat_index, node_index",
    )?;
    for (table, row_name) in ROW_NAMES {
        let columns: Vec<String> = {
            let err = |e| CdbError::sqlite(c.path, e);
            let mut stmt = c
                .conn
                .prepare("SELECT name FROM pragma_table_info(?1) WHERE \"notnull\" ORDER BY cid")
                .map_err(err)?;
            stmt.query_map([table], |r| r.get::<_, String>(0))
                .map_err(err)?
                .collect::<rusqlite::Result<_>>()
                .map_err(err)?
        };
        for column in columns {
            c.rows(
                "null_value",
                &format!(
                    "SELECT {row_name} || ': {table}.{column} is NULL (the schema says NOT \
                     NULL)' FROM {table} WHERE typeof(\"{column}\") = 'null'"
                ),
            )?;
        }
    }
    Ok(())
}

/// The keys, CHECKs and indexes of the stored schema against the program's
/// ([`crate::constraints`]): the primary keys and NOT NULL flags from `pragma_table_info`,
/// foreign keys from `pragma_foreign_key_list`, indexes from `pragma_index_list` and
/// `pragma_index_info`, CHECKs from the stored `CREATE TABLE` text; and columns outside the
/// schema that are NOT NULL without a default.
fn schema_checks(c: &mut Checker<'_>) -> Result<()> {
    use crate::constraints::{Found, Kind};
    let err = |e| CdbError::sqlite(c.path, e);
    let conn = c.conn;
    let tables: Vec<(String, String)> = {
        let mut stmt = conn
            .prepare(
                "SELECT name, coalesce(sql, '') FROM sqlite_master WHERE type = 'table' AND \
                 name IN ('runs', 'progress', 'records', 'cdb_identity', 'dynamics')",
            )
            .map_err(err)?;
        stmt.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
            .map_err(err)?
            .collect::<rusqlite::Result<_>>()
            .map_err(err)?
    };
    let strings = |sql: &str, arg: &str| -> Result<Vec<Option<String>>> {
        let mut stmt = conn.prepare(sql).map_err(err)?;
        stmt.query_map([arg], |r| r.get(0))
            .map_err(err)?
            .collect::<rusqlite::Result<_>>()
            .map_err(err)
    };
    let mut found = Vec::new();
    let mut required = Vec::new();
    for (table, ddl) in &tables {
        let columns: Vec<(String, bool, bool, i64)> = {
            let mut stmt = conn
                .prepare(
                    "SELECT name, \"notnull\", dflt_value IS NOT NULL, pk \
                     FROM pragma_table_info(?1) ORDER BY cid",
                )
                .map_err(err)?;
            stmt.query_map([table], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
            })
            .map_err(err)?
            .collect::<rusqlite::Result<_>>()
            .map_err(err)?
        };
        let mut key: Vec<&(String, bool, bool, i64)> = columns.iter().filter(|c| c.3 > 0).collect();
        key.sort_by_key(|c| c.3);
        found.push(Found {
            kind: Kind::PrimaryKey,
            table: table.clone(),
            columns: key.iter().map(|c| c.0.clone()).collect(),
            references: None,
            definition: String::new(),
            valid: !key.is_empty(),
        });
        required.extend(
            columns
                .iter()
                .filter(|c| c.1 && !c.2 && c.3 == 0)
                .map(|c| (table.clone(), c.0.clone())),
        );
        let mut stmt = conn
            .prepare(
                "SELECT \"table\", \"from\", \"to\" FROM pragma_foreign_key_list(?1) \
                 ORDER BY id, seq",
            )
            .map_err(err)?;
        let keys: Vec<(String, String, Option<String>)> = stmt
            .query_map([table], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
            .map_err(err)?
            .collect::<rusqlite::Result<_>>()
            .map_err(err)?;
        for (to_table, from, to) in keys {
            // A foreign key without its column names the referenced table's primary key.
            let to = match to {
                Some(to) => to,
                None => strings(
                    "SELECT name FROM pragma_table_info(?1) WHERE pk > 0 ORDER BY pk",
                    &to_table,
                )?
                .into_iter()
                .flatten()
                .collect::<Vec<_>>()
                .join(", "),
            };
            found.push(Found {
                kind: Kind::ForeignKey,
                table: table.clone(),
                columns: vec![from],
                references: Some(format!("{to_table}({to})")),
                definition: String::new(),
                valid: true,
            });
        }
        let mut stmt = conn
            .prepare("SELECT name, \"unique\", partial FROM pragma_index_list(?1)")
            .map_err(err)?;
        let indexes: Vec<(String, bool, bool)> = stmt
            .query_map([table], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))
            .map_err(err)?
            .collect::<rusqlite::Result<_>>()
            .map_err(err)?;
        for (name, unique, partial) in indexes {
            let index_columns = strings(
                "SELECT name FROM pragma_index_info(?1) ORDER BY seqno",
                &name,
            )?;
            let expression = index_columns.iter().any(Option::is_none);
            found.push(Found {
                kind: if unique {
                    Kind::UniqueIndex
                } else {
                    Kind::Index
                },
                table: table.clone(),
                columns: index_columns.into_iter().flatten().collect(),
                references: None,
                definition: String::new(),
                valid: !partial && !expression,
            });
        }
        let names: Vec<String> = columns.iter().map(|c| c.0.clone()).collect();
        found.extend(crate::constraints::sqlite_checks(table, ddl, &names));
    }
    let present: Vec<String> = tables.into_iter().map(|(t, _)| t).collect();
    c.report
        .problems
        .extend(crate::constraints::compare(&found, false, &present));
    c.report
        .problems
        .extend(crate::constraints::extra_not_null(&required));
    Ok(())
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
    // The schema's constraints, also when the structure is damaged (integrity_check
    // reports a NULL in a NOT NULL column as such): a query that fails on a damaged file
    // leaves the structural findings to speak.
    if let Err(e) = constraint_checks(&mut c) {
        if c.report.sqlite.is_empty() {
            return Err(e);
        }
        tracing::debug!(error = %e, "constraint checks on a damaged file");
    }
    // The dynamics, also when a foreign key is broken (a model whose run is gone is one of
    // the things looked for).
    if let Err(e) = dynamics_checks(&mut c) {
        if c.report.sqlite.is_empty() {
            return Err(e);
        }
        tracing::debug!(error = %e, "dynamics checks on a damaged file");
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
    relation_checks(&mut c)?;
    let runs = run_configs(conn, path)?;
    plausibility_pass(
        &runs,
        &mut |each| crate::query::for_each_record(conn, path, &RecordFilter::default(), each),
        &mut c.report,
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

/// The scanner dynamics (schema v5): every column of its type, the version in range, the
/// run stored and on the same scanner, and every row obeying [`DynamicsRecord::check`]
/// (the time finite and > 0, the model a JSON object of bounded size, visible ids).
///
/// [`DynamicsRecord::check`]: spm_records::DynamicsRecord::check
fn dynamics_checks(c: &mut Checker<'_>) -> Result<()> {
    for (column, types) in [
        ("run_id", "'text'"),
        ("scanner_id", "'text'"),
        ("identified_unix_s", "'real', 'integer'"),
        ("model_format", "'text'"),
        ("model_version", "'integer'"),
        ("model_json", "'text'"),
    ] {
        c.rows(
            "bad_type",
            &format!(
                "SELECT 'dynamics id ' || id || ': {column} is ' || typeof({column}) || \
                 ', not {}' FROM dynamics WHERE typeof({column}) NOT IN ({types}, 'null') \
                 ORDER BY id",
                types.replace('\'', "")
            ),
        )?;
    }
    c.rows(
        "invalid_dynamics",
        "SELECT 'dynamics id ' || id || ': model_version ' || model_version || \
         ' is not in 1..=4294967295' FROM dynamics WHERE typeof(model_version) = 'integer' \
         AND model_version NOT BETWEEN 1 AND 4294967295 ORDER BY id",
    )?;
    c.rows(
        "dynamics_without_run",
        "SELECT 'dynamics id ' || d.id || ': run ' || quote(d.run_id) || ' does not exist' \
         FROM dynamics d WHERE NOT EXISTS (SELECT 1 FROM runs u WHERE u.run_id = d.run_id) \
         ORDER BY d.id",
    )?;
    c.rows(
        "scanner_mismatch",
        "SELECT 'dynamics id ' || d.id || ': scanner ' || quote(d.scanner_id) || \
         ' but run ' || quote(d.run_id) || ' is on ' || quote(u.scanner_id) \
         FROM dynamics d JOIN runs u ON d.run_id = u.run_id \
         WHERE d.scanner_id != u.scanner_id ORDER BY d.id",
    )?;
    let found = crate::dynamics::check_rows(c.conn, c.path, MAX_ROWS_PER_CHECK)?;
    c.report.problems.extend(found);
    Ok(())
}

/// How records, plan nodes and runs relate: no duplicate record, done nodes with records
/// and unfinished ones without, records at their plan node and on their run's scanner,
/// given-up nodes with a reason, one identity row and every run of this database.
fn relation_checks(c: &mut Checker<'_>) -> Result<()> {
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
        "identity",
        "SELECT 'cdb_identity holds ' || count(*) || ' rows, expected 1' FROM cdb_identity \
         HAVING count(*) != 1",
    )?;
    c.rows(
        "foreign_run",
        "SELECT 'run ' || quote(run_id) || ': cdb_id ' || quote(cdb_id) || \
         ' is not this database''s id' FROM runs WHERE coalesce(cdb_id, '') != \
         coalesce((SELECT id FROM cdb_identity ORDER BY rowid LIMIT 1), '') ORDER BY run_id",
    )?;
    c.rows(
        "scanner_mismatch",
        "SELECT 'record id ' || r.id || ': scanner ' || quote(r.scanner_id) || \
         ' but run ' || quote(r.run_id) || ' is on ' || quote(u.scanner_id) \
         FROM records r JOIN runs u ON r.run_id = u.run_id \
         WHERE r.scanner_id != u.scanner_id ORDER BY r.id",
    )?;
    Ok(())
}

/// `(run id, configuration text)` of every run whose both are text.
fn run_configs(conn: &Connection, path: &Path) -> Result<Vec<(String, String)>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(
            "SELECT run_id, config FROM runs WHERE typeof(run_id) = 'text' \
             AND typeof(config) = 'text'",
        )
        .map_err(err)?;
    stmt.query_map([], |r| Ok((r.get(0)?, r.get(1)?)))
        .map_err(err)?
        .collect::<rusqlite::Result<_>>()
        .map_err(err)
}

/// Reports every record that breaks its run's plausibility limits
/// ([`LccRecord::implausibility`]: field, distance from its node, nominal sensitivity), as
/// `implausible_record`. A record that cannot be decoded ends the pass with an
/// `undecodable_record` problem (the other checks name its columns).
pub(crate) fn plausibility_pass(
    runs: &[(String, String)],
    records: &mut crate::query::RecordSource<'_>,
    report: &mut IntegrityReport,
) -> Result<()> {
    let limits: HashMap<&str, Plausibility> = runs
        .iter()
        .map(|(id, config)| (id.as_str(), Plausibility::from_run_config(config)))
        .filter(|(_, p)| !p.is_empty())
        .collect();
    if limits.is_empty() {
        return Ok(());
    }
    let mut found = 0usize;
    let result = records(&mut |r: LccRecord| {
        let Some(why) = limits
            .get(r.run_id.as_str())
            .and_then(|p| r.implausibility(p))
        else {
            return Ok(());
        };
        found += 1;
        if found <= MAX_ROWS_PER_CHECK {
            report.problems.push(IntegrityProblem {
                kind: "implausible_record".into(),
                detail: format!(
                    "run {:?}, repeat {}, node {}, lcs {}: {why}",
                    r.run_id, r.repeat_index, r.node_index, r.lcs_index
                ),
            });
        } else if found == MAX_ROWS_PER_CHECK + 1 {
            report.problems.push(IntegrityProblem {
                kind: "implausible_record".into(),
                detail: format!("… more than {MAX_ROWS_PER_CHECK} rows"),
            });
        }
        Ok(())
    });
    match result {
        Err(e) if e.kind() == crate::ErrorKind::Corrupt => {
            report.problems.push(IntegrityProblem {
                kind: "undecodable_record".into(),
                detail: e.to_string(),
            });
            Ok(())
        }
        other => other,
    }
}

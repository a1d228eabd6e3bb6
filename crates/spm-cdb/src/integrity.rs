//! `cdb check` on SQLite: `PRAGMA integrity_check` and `foreign_key_check`, the schema's
//! keys, CHECKs and indexes read from the pragmas, the CHECK and NOT NULL constraints and
//! the column types queried (SQLite stores any type anywhere), then the semantic rules
//! shared with PostgreSQL (`crate::sql::checks`).

use rusqlite::Connection;
use std::path::Path;

use crate::error::{CdbError, Result};
use crate::sql::checks::{self, Checker};
use crate::sql::sqlite::Conn;
use spm_records::IntegrityReport;

type SqliteChecker<'a> = Checker<'a, Conn<'a>>;

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
fn constraint_checks(c: &mut SqliteChecker<'_>) -> Result<()> {
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
            let err = |e| CdbError::sqlite(c.db.path(), e);
            let mut stmt = c
                .db
                .connection()
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
fn schema_checks(c: &mut SqliteChecker<'_>) -> Result<()> {
    use crate::constraints::{Found, Kind};
    let err = |e| CdbError::sqlite(c.db.path(), e);
    let conn = c.db.connection();
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
    let db = Conn::new(conn, path);
    let mut c = Checker::new(&db);
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
    checks::value_checks(&mut c)?;
    checks::relation_checks(&mut c)?;
    checks::plausibility_checks(&mut c)?;
    if !c.report.problems.is_empty() {
        tracing::warn!(
            path = %path.display(),
            problems = c.report.problems.len(),
            "CDB integrity problems"
        );
    }
    Ok(c.report)
}

/// The scanner dynamics (schema v5): every column of its type (what SQLite does not
/// enforce), then the rules shared with PostgreSQL ([`checks::dynamics_checks`]).
fn dynamics_checks(c: &mut SqliteChecker<'_>) -> Result<()> {
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
    checks::dynamics_checks(c)
}

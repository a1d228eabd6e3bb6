//! The one backend-neutral SQL layer of both CDBs (issue 28 item 3): the SQLite file
//! ([`crate::Cdb`]) and the PostgreSQL database (`crate::postgres::PgCdb`) run the same
//! statements, decode rows with the same code and take the same decisions; what differs is
//! said once, by the [`Dialect`].
//!
//! - [`Dialect`]: placeholder spelling (`?N` / `$N`), column types, row locks
//!   (`FOR UPDATE`, `FOR SHARE`; SQLite's write transaction is `BEGIN IMMEDIATE`, a lock of the
//!   whole file, so its rows need none), upsert spelling and the few functions that are
//!   spelled differently (`quote` / `quote_literal`, `trim` / `btrim`, a typed NULL).
//! - This module: the column lists, the statement builders and the filter clause
//!   ([`where_clause`]), with parameters as [`Param`] values each back end binds its own way.
//! - [`row`]: reading a row, through the tiny [`row::SqlRow`] accessor (one implementation
//!   per client), into an `LccRecord`, `RunInfo`, `NodeProgress` or `DynamicsRecord`.
//! - [`read`]: every query of [`crate::CdbRead`] over a [`read::SqlRead`] connection.
//! - [`write`]: every write of the calibration's progress (runs, plans, nodes, dynamics) over
//!   a [`write::SqlTx`] write transaction, and the one [`spm_records::ProgressStore`]
//!   implementation (see there why it is a macro over a shared trait).
//! - [`checks`]: the semantic integrity predicates of `cdb check`.
//! - [`sqlite`] and `pg`: the two thin adapters (connection, transaction, row accessor,
//!   parameter binding). The rest of each back end is what really differs: opening,
//!   schema and migrations, identity (SQLite), bulk import (SQLite: a prepared insert;
//!   PostgreSQL: a binary `COPY`), and the structural half of `cdb check` (pragmas / catalog).

pub(crate) mod checks;
#[cfg(feature = "postgres")]
pub(crate) mod pg;
pub(crate) mod read;
pub(crate) mod row;
pub(crate) mod sqlite;
pub(crate) mod write;

use spm_records::{ColumnKind, LCC_RECORD_COLUMNS, RecordFilter};
use std::path::Path;
use std::sync::LazyLock;

use crate::error::{CdbError, Result};

/// What differs between the SQL of the two back ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Dialect {
    /// The embedded file.
    Sqlite,
    /// The shared server.
    Postgres,
}

impl Dialect {
    /// The `n`-th parameter (from 1): `?n` or `$n`.
    pub(crate) fn placeholder(self, n: usize) -> String {
        match self {
            Self::Sqlite => format!("?{n}"),
            Self::Postgres => format!("${n}"),
        }
    }

    /// `?1, ?2, …, ?count` (or `$…`).
    pub(crate) fn placeholders(self, count: usize) -> String {
        (1..=count)
            .map(|n| self.placeholder(n))
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The type and NOT NULL of a record column of this kind (PostgreSQL's is the schema's;
    /// SQLite's schema is written out in `schema.rs`, a test checks it against this).
    #[cfg_attr(not(feature = "postgres"), allow(dead_code))]
    pub(crate) fn column_type(self, kind: ColumnKind) -> &'static str {
        match (self, kind) {
            (_, ColumnKind::Text) => "TEXT NOT NULL",
            (Self::Sqlite, ColumnKind::Real) => "REAL NOT NULL",
            (Self::Sqlite, ColumnKind::OptionalReal) => "REAL",
            (Self::Sqlite, ColumnKind::Integer) => "INTEGER NOT NULL",
            (Self::Postgres, ColumnKind::Real) => "DOUBLE PRECISION NOT NULL",
            (Self::Postgres, ColumnKind::OptionalReal) => "DOUBLE PRECISION",
            (Self::Postgres, ColumnKind::Integer) => "BIGINT NOT NULL",
        }
    }

    /// Suffix of a SELECT that locks the rows it reads until the write transaction ends
    /// (PostgreSQL, whose writers run at READ COMMITTED); SQLite's `BEGIN IMMEDIATE` already
    /// holds the file's write lock.
    pub(crate) fn for_update(self) -> &'static str {
        match self {
            Self::Sqlite => "",
            Self::Postgres => " FOR UPDATE",
        }
    }

    /// Like [`Dialect::for_update`], a shared lock (the row must not change, others may
    /// read it).
    pub(crate) fn for_share(self) -> &'static str {
        match self {
            Self::Sqlite => "",
            Self::Postgres => " FOR SHARE",
        }
    }

    /// Parameter `n` as text that may be NULL, in a test `… IS NULL` (PostgreSQL must be told
    /// its type).
    pub(crate) fn nullable_text(self, n: usize) -> String {
        match self {
            Self::Sqlite => self.placeholder(n),
            Self::Postgres => format!("${n}::TEXT"),
        }
    }

    /// `col` as an SQL literal in a message (`'text'`; NULL as `NULL`).
    pub(crate) fn quote(self, col: &str) -> String {
        match self {
            Self::Sqlite => format!("quote({col})"),
            Self::Postgres => format!("quote_nullable({col})"),
        }
    }

    /// An integer column in a message: SQLite quotes it (a value of another type shows as
    /// such), PostgreSQL's column holds integers.
    pub(crate) fn quote_integer(self, col: &str) -> String {
        match self {
            Self::Sqlite => format!("quote({col})"),
            Self::Postgres => col.to_owned(),
        }
    }

    /// True where the text `col` is empty or white space.
    pub(crate) fn blank(self, col: &str) -> String {
        match self {
            Self::Sqlite => format!("trim({col}) = ''"),
            Self::Postgres => format!("btrim({col}) = ''"),
        }
    }

    /// True where `col` holds a number that is not NaN (SQLite stores any type in any
    /// column, and NULL or text must not be compared as numbers; PostgreSQL's types hold,
    /// and its NaN compares greater than every number).
    pub(crate) fn is_number(self, col: &str) -> String {
        match self {
            Self::Sqlite => format!("typeof({col}) IN ('real', 'integer')"),
            Self::Postgres => format!("{col} <> 'NaN'::float8"),
        }
    }

    /// True where `col` holds a value of its kind (SQLite stores any type in any column;
    /// on PostgreSQL the column's type holds, so only NULL is excluded). A REAL column may
    /// hold an integer on SQLite.
    pub(crate) fn typed(self, col: &str, kind: ColumnKind) -> String {
        match (self, kind) {
            (Self::Sqlite, ColumnKind::Text) => format!("typeof({col}) = 'text'"),
            (Self::Sqlite, ColumnKind::Real | ColumnKind::OptionalReal) => {
                format!("typeof({col}) IN ('real', 'integer')")
            }
            (Self::Sqlite, ColumnKind::Integer) => format!("typeof({col}) = 'integer'"),
            (Self::Postgres, _) => format!("{col} IS NOT NULL"),
        }
    }

    /// True where `col` (a REAL column) holds something other than a finite number (on
    /// SQLite NULL too, unless `nullable`).
    pub(crate) fn not_finite(self, col: &str, nullable: bool) -> String {
        match self {
            Self::Sqlite => {
                let test = format!(
                    "(typeof({col}) NOT IN ('real', 'integer') OR abs({col}) > \
                     1.7976931348623157e308)"
                );
                if nullable {
                    format!("{col} IS NOT NULL AND {test}")
                } else {
                    test
                }
            }
            Self::Postgres => {
                format!("{col} IN ('NaN'::float8, 'Infinity'::float8, '-Infinity'::float8)")
            }
        }
    }

    /// The database's own id, as a scalar subquery (SQLite: the first row ever inserted).
    pub(crate) fn identity_id(self) -> &'static str {
        match self {
            Self::Sqlite => "(SELECT id FROM cdb_identity ORDER BY rowid LIMIT 1)",
            Self::Postgres => "(SELECT id FROM cdb_identity LIMIT 1)",
        }
    }

    /// The `records` table for a sequential read: SQLite is told not to use an index (see
    /// [`crate::CdbRead::columns`]); PostgreSQL's planner chooses.
    pub(crate) fn records_scan(self) -> &'static str {
        match self {
            Self::Sqlite => "records NOT INDEXED",
            Self::Postgres => "records",
        }
    }
}

/// A statement parameter, bound by each back end's adapter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum Param<'a> {
    /// Text.
    Text(&'a str),
    /// Text or NULL.
    OptText(Option<&'a str>),
    /// A 64-bit integer (indexes and counts are stored as such on both back ends).
    Integer(i64),
    /// A double.
    Real(f64),
    /// A double or NULL.
    OptReal(Option<f64>),
}

impl From<u32> for Param<'_> {
    fn from(v: u32) -> Self {
        Param::Integer(i64::from(v))
    }
}

/// `scanner_id, run_id, …, quality`: the record columns in [`LCC_RECORD_COLUMNS`] order.
pub(crate) fn record_columns() -> String {
    LCC_RECORD_COLUMNS
        .iter()
        .map(|c| c.name)
        .collect::<Vec<_>>()
        .join(", ")
}

/// `INSERT INTO records (…) VALUES (?1, …)` in the dialect (built once).
pub(crate) fn insert_record(dialect: Dialect) -> &'static str {
    static SQLITE: LazyLock<String> = LazyLock::new(|| insert_record_in(Dialect::Sqlite));
    static POSTGRES: LazyLock<String> = LazyLock::new(|| insert_record_in(Dialect::Postgres));
    match dialect {
        Dialect::Sqlite => &SQLITE,
        Dialect::Postgres => &POSTGRES,
    }
}

fn insert_record_in(dialect: Dialect) -> String {
    format!(
        "INSERT INTO records ({}) VALUES ({})",
        record_columns(),
        dialect.placeholders(LCC_RECORD_COLUMNS.len())
    )
}

/// The columns of a run row, as [`row::run`] reads them.
pub(crate) const RUN_COLUMNS: &str =
    "run_id, scanner_id, config, started_unix_s, finished_unix_s, status";

/// The columns of a plan row, as [`row::progress`] reads them.
pub(crate) const PROGRESS_COLUMNS: &str = "repeat_index, node_index, node_x_counts, \
node_y_counts, node_z_counts, state, reason, attempts, updated_unix_s";

/// [`spm_records::DYNAMICS_RECORD_COLUMNS`] as an SQL column list (checked by a test), as
/// [`row::dynamics`] reads them.
pub(crate) const DYNAMICS_COLUMNS: &str =
    "run_id, scanner_id, identified_unix_s, model_format, model_version, model_json";

/// The columns [`crate::CdbRead::columns`] reads, as [`row::push_columns`] reads them.
pub(crate) const REGRESSION_COLUMNS: &str = "lcs_x_counts, lcs_y_counts, node_z_counts, \
acquired_unix_s, kx_nm_per_count, ky_nm_per_count, alpha_rad, kz_nm_per_count";

/// ` WHERE …` (or nothing) selecting a filter's records, and its parameters (numbered from 1).
pub(crate) fn where_clause(dialect: Dialect, f: &RecordFilter) -> (String, Vec<Param<'_>>) {
    let mut terms = Vec::new();
    let mut params = Vec::new();
    let mut add = |column: &str, op: &str, p| {
        params.push(p);
        terms.push(format!(
            "{column} {op} {}",
            dialect.placeholder(params.len())
        ));
    };
    if let Some(s) = &f.scanner_id {
        add("scanner_id", "=", Param::Text(s));
    }
    if let Some(r) = &f.run_id {
        add("run_id", "=", Param::Text(r));
    }
    if let Some(z) = f.node_z_counts {
        add("node_z_counts", "=", Param::Integer(z));
    }
    if let Some(t) = f.since_unix_s {
        add("acquired_unix_s", ">=", Param::Real(t));
    }
    if let Some(t) = f.until_unix_s {
        add("acquired_unix_s", "<=", Param::Real(t));
    }
    if terms.is_empty() {
        (String::new(), params)
    } else {
        (format!(" WHERE {}", terms.join(" AND ")), params)
    }
}

/// Refuses a filter with a non-finite time bound.
pub(crate) fn check_filter(path: &Path, f: &RecordFilter) -> Result<()> {
    for t in [f.since_unix_s, f.until_unix_s].into_iter().flatten() {
        if !t.is_finite() {
            return Err(CdbError::InvalidInput {
                path: path.to_path_buf(),
                reason: format!("non-finite time bound {t}"),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_dynamics_column_list_is_the_records_one() {
        assert_eq!(
            DYNAMICS_COLUMNS,
            spm_records::DYNAMICS_RECORD_COLUMNS.join(", ")
        );
    }

    #[test]
    fn both_dialects_number_the_same_filter_alike() {
        let f = RecordFilter {
            scanner_id: Some("s".into()),
            node_z_counts: Some(3),
            until_unix_s: Some(5.0),
            ..RecordFilter::default()
        };
        let (sqlite, p) = where_clause(Dialect::Sqlite, &f);
        assert_eq!(
            sqlite,
            " WHERE scanner_id = ?1 AND node_z_counts = ?2 AND acquired_unix_s <= ?3"
        );
        assert_eq!(p, [Param::Text("s"), Param::Integer(3), Param::Real(5.0)]);
        let (pg, _) = where_clause(Dialect::Postgres, &f);
        assert_eq!(pg, sqlite.replace('?', "$"));
        assert_eq!(
            where_clause(Dialect::Sqlite, &RecordFilter::default()).0,
            ""
        );
    }

    /// The SQLite schema is written out (`schema.rs`): its record columns have the types
    /// the dialect gives their kind, as PostgreSQL's generated schema has.
    #[test]
    fn the_sqlite_schema_types_the_record_columns_as_the_dialect_does() {
        let schema = crate::schema::schema_text();
        let records = schema
            .split("CREATE TABLE records (")
            .nth(1)
            .and_then(|t| t.split(");").next())
            .expect("the records table");
        for c in LCC_RECORD_COLUMNS {
            let line = records
                .lines()
                .map(str::trim)
                .find(|l| l.split_whitespace().next() == Some(c.name))
                .unwrap_or_else(|| panic!("no column {}", c.name));
            let ty = line[c.name.len()..].trim().trim_end_matches(',');
            let ty = ty.trim_end_matches(" DEFAULT 0");
            let ty = ty.replace(" REFERENCES runs (run_id)", "");
            assert_eq!(ty, Dialect::Sqlite.column_type(c.kind), "{}", c.name);
        }
    }
}

//! The SQLite adapter of the SQL layer: a connection (the file, a snapshot or a write
//! transaction) as [`SqlRead`] and [`SqlTx`], `rusqlite` rows as [`SqlRow`], [`Param`]s bound
//! as SQLite values. Errors are classified by [`CdbError::sqlite`].

use rusqlite::Connection;
use rusqlite::types::{ToSqlOutput, Value, ValueRef};
use std::path::Path;

use super::read::SqlRead;
use super::row::SqlRow;
use super::write::SqlTx;
use super::{Dialect, Param};
use crate::error::{CdbError, Result};
use spm_records::{ColumnValue, LccRecord};

/// A connection to the CDB file (or a transaction on it, which dereferences to one).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Conn<'c> {
    conn: &'c Connection,
    path: &'c Path,
}

impl<'c> Conn<'c> {
    pub(crate) fn new(conn: &'c Connection, path: &'c Path) -> Self {
        Self { conn, path }
    }

    /// The connection (the SQLite-only queries of `cdb check`).
    pub(crate) fn connection(&self) -> &'c Connection {
        self.conn
    }

    /// Where the file is.
    pub(crate) fn path(&self) -> &'c Path {
        self.path
    }
}

impl rusqlite::ToSql for Param<'_> {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(match *self {
            Param::Text(t) | Param::OptText(Some(t)) => {
                ToSqlOutput::Borrowed(ValueRef::Text(t.as_bytes()))
            }
            Param::Integer(v) => ToSqlOutput::Owned(Value::Integer(v)),
            Param::Real(v) | Param::OptReal(Some(v)) => ToSqlOutput::Owned(Value::Real(v)),
            Param::OptText(None) | Param::OptReal(None) => ToSqlOutput::Owned(Value::Null),
        })
    }
}

/// A record value bound as a statement parameter.
struct Bind<'a>(ColumnValue<'a>);

impl rusqlite::ToSql for Bind<'_> {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(match self.0 {
            ColumnValue::Text(t) => ToSqlOutput::Borrowed(ValueRef::Text(t.as_bytes())),
            ColumnValue::Real(v) | ColumnValue::OptionalReal(Some(v)) => {
                ToSqlOutput::Owned(Value::Real(v))
            }
            ColumnValue::OptionalReal(None) => ToSqlOutput::Owned(Value::Null),
            ColumnValue::Integer(v) => ToSqlOutput::Owned(Value::Integer(v)),
        })
    }
}

/// Executes [`super::insert_record`] (prepared by the caller) for one record.
pub(crate) fn insert_record(
    stmt: &mut rusqlite::Statement<'_>,
    r: &LccRecord,
) -> rusqlite::Result<()> {
    stmt.execute(rusqlite::params_from_iter(r.column_values().map(Bind)))?;
    Ok(())
}

struct Row<'r, 's> {
    row: &'r rusqlite::Row<'s>,
    path: &'r Path,
}

impl Row<'_, '_> {
    fn get<T: rusqlite::types::FromSql>(&self, i: usize) -> Result<T> {
        self.row.get(i).map_err(|e| CdbError::sqlite(self.path, e))
    }
}

super::row::sql_row_via_get!(Row<'_, '_>);

impl SqlRead for Conn<'_> {
    fn dialect(&self) -> Dialect {
        Dialect::Sqlite
    }
    fn location(&self) -> &Path {
        self.path
    }
    fn query_each(
        &self,
        sql: &str,
        params: &[Param<'_>],
        each: &mut dyn FnMut(&dyn SqlRow) -> Result<()>,
    ) -> Result<()> {
        let err = |e| CdbError::sqlite(self.path, e);
        let mut stmt = self.conn.prepare(sql).map_err(err)?;
        let mut rows = stmt
            .query(rusqlite::params_from_iter(params))
            .map_err(err)?;
        while let Some(row) = rows.next().map_err(err)? {
            each(&Row {
                row,
                path: self.path,
            })?;
        }
        Ok(())
    }
}

impl SqlTx for Conn<'_> {
    fn execute(&mut self, sql: &str, params: &[Param<'_>]) -> Result<u64> {
        let n = self
            .conn
            .execute(sql, rusqlite::params_from_iter(params))
            .map_err(|e| CdbError::sqlite(self.path, e))?;
        Ok(n as u64)
    }
    fn insert_record(&mut self, r: &LccRecord) -> Result<()> {
        let err = |e| CdbError::sqlite(self.path, e);
        let mut stmt = self
            .conn
            .prepare_cached(super::insert_record(Dialect::Sqlite))
            .map_err(err)?;
        insert_record(&mut stmt, r).map_err(err)
    }
}

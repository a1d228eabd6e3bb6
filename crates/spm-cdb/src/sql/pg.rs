//! The PostgreSQL adapter of the SQL layer: `PgCdb` (and a write transaction on it) as
//! [`SqlRead`] and [`SqlTx`], `postgres` rows as [`SqlRow`], [`Param`]s bound as
//! PostgreSQL values. Errors of a statement are classified by [`CdbError::postgres`]; a
//! value that does not convert is [`crate::ErrorKind::Corrupt`], as on SQLite.

use std::cell::RefCell;
use std::collections::HashMap;
use std::path::Path;

use postgres::fallible_iterator::FallibleIterator;
use postgres::types::{FromSql, ToSql};
use postgres::{Statement, Transaction};

use super::read::SqlRead;
use super::row::SqlRow;
use super::write::SqlTx;
use super::{Dialect, Param};
use crate::error::{CdbError, Result};
use spm_records::LccRecord;

impl Param<'_> {
    /// The value as a `postgres` parameter.
    pub(crate) fn as_pg(&self) -> &(dyn ToSql + Sync) {
        match self {
            Param::Text(t) => t,
            Param::OptText(t) => t,
            Param::Integer(v) => v,
            Param::Real(v) => v,
            Param::OptReal(v) => v,
        }
    }
}

struct Row<'r> {
    row: &'r postgres::Row,
    path: &'r Path,
}

impl Row<'_> {
    fn get<'a, T: FromSql<'a>>(&'a self, i: usize) -> Result<T> {
        self.row.try_get(i).map_err(|e| CdbError::Corrupt {
            path: self.path.to_path_buf(),
            reason: e.to_string(),
        })
    }
}

super::row::sql_row_via_get!(Row<'_>);

/// Runs a query on any client, streaming its rows into `each`.
pub(crate) fn query_each(
    client: &mut impl postgres::GenericClient,
    path: &Path,
    sql: &str,
    params: &[Param<'_>],
    each: &mut dyn FnMut(&dyn SqlRow) -> Result<()>,
) -> Result<()> {
    let err = |e| CdbError::postgres(path, e);
    let mut rows = client
        .query_raw(sql, params.iter().map(Param::as_pg))
        .map_err(err)?;
    while let Some(row) = rows.next().map_err(err)? {
        each(&Row { row: &row, path })?;
    }
    Ok(())
}

impl SqlRead for crate::postgres::PgCdb {
    fn dialect(&self) -> Dialect {
        Dialect::Postgres
    }
    fn location(&self) -> &Path {
        crate::CdbRead::path(self)
    }
    fn query_each(
        &self,
        sql: &str,
        params: &[Param<'_>],
        each: &mut dyn FnMut(&dyn SqlRow) -> Result<()>,
    ) -> Result<()> {
        // Again on a new connection after a lost one, unless rows were handed on already.
        let delivered = std::cell::Cell::new(false);
        self.read_op(
            |client| {
                query_each(client, self.location(), sql, params, &mut |row| {
                    delivered.set(true);
                    each(row)
                })
            },
            || !delivered.get(),
        )
    }
}

/// A write transaction (`READ COMMITTED`), with the record insert prepared once per
/// connection and the other statements once per transaction.
pub(crate) struct Tx<'t, 'c> {
    tx: RefCell<Transaction<'c>>,
    path: &'t Path,
    insert: Statement,
    prepared: HashMap<String, Statement>,
}

impl<'t, 'c> Tx<'t, 'c> {
    pub(crate) fn new(tx: Transaction<'c>, path: &'t Path, insert: Statement) -> Self {
        Self {
            tx: RefCell::new(tx),
            path,
            insert,
            prepared: HashMap::new(),
        }
    }

    pub(crate) fn commit(self) -> Result<()> {
        self.tx
            .into_inner()
            .commit()
            .map_err(|e| CdbError::postgres(self.path, e))
    }
}

impl SqlRead for Tx<'_, '_> {
    fn dialect(&self) -> Dialect {
        Dialect::Postgres
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
        let mut tx = self.tx.try_borrow_mut().map_err(|_| {
            crate::invalid(
                self.path,
                "a query was started from inside another query's callback".into(),
            )
        })?;
        query_each(&mut *tx, self.path, sql, params, each)
    }
}

impl SqlTx for Tx<'_, '_> {
    fn execute(&mut self, sql: &str, params: &[Param<'_>]) -> Result<u64> {
        let err = |e| CdbError::postgres(self.path, e);
        let tx = self.tx.get_mut();
        let statement = match self.prepared.get(sql) {
            Some(s) => s.clone(),
            None => {
                let s = tx.prepare(sql).map_err(err)?;
                self.prepared.insert(sql.to_owned(), s.clone());
                s
            }
        };
        let values: Vec<&(dyn ToSql + Sync)> = params.iter().map(Param::as_pg).collect();
        tx.execute(&statement, &values).map_err(err)
    }
    fn insert_record(&mut self, r: &LccRecord) -> Result<()> {
        let values = crate::postgres::binds(r);
        self.tx
            .get_mut()
            .execute(&self.insert, &crate::postgres::bind_refs(&values))
            .map_err(|e| CdbError::postgres(self.path, e))?;
        Ok(())
    }
}

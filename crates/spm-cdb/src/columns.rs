//! The `records` columns in SQL, built from [`spm_records::LCC_RECORD_COLUMNS`] (the one
//! definition of the columns): the select list, the insert statement, reading a row and
//! binding a record.

use rusqlite::types::{ToSqlOutput, Value, ValueRef};
use rusqlite::{Row, ToSql};
use spm_records::{ColumnKind, ColumnValue, LCC_RECORD_COLUMNS, LccRecord, OwnedColumnValue};
use std::sync::LazyLock;

/// `scanner_id, run_id, …, quality`: the select list in [`LCC_RECORD_COLUMNS`] order.
pub(crate) static RECORD_COLUMNS: LazyLock<String> = LazyLock::new(|| {
    LCC_RECORD_COLUMNS
        .iter()
        .map(|c| c.name)
        .collect::<Vec<_>>()
        .join(", ")
});

/// `INSERT INTO records (…) VALUES (?1, …, ?25)`.
pub(crate) static INSERT_RECORD: LazyLock<String> = LazyLock::new(|| {
    let placeholders: Vec<String> = (1..=LCC_RECORD_COLUMNS.len())
        .map(|i| format!("?{i}"))
        .collect();
    format!(
        "INSERT INTO records ({}) VALUES ({})",
        *RECORD_COLUMNS,
        placeholders.join(", ")
    )
});

struct Bind<'a>(ColumnValue<'a>);

impl ToSql for Bind<'_> {
    fn to_sql(&self) -> rusqlite::Result<ToSqlOutput<'_>> {
        Ok(match self.0 {
            ColumnValue::Text(t) => ToSqlOutput::Borrowed(ValueRef::Text(t.as_bytes())),
            ColumnValue::Real(v) => ToSqlOutput::Owned(Value::Real(v)),
            ColumnValue::OptionalReal(Some(v)) => ToSqlOutput::Owned(Value::Real(v)),
            ColumnValue::OptionalReal(None) => ToSqlOutput::Owned(Value::Null),
            ColumnValue::Integer(v) => ToSqlOutput::Owned(Value::Integer(v)),
        })
    }
}

/// Executes [`INSERT_RECORD`] for one record.
pub(crate) fn insert_record(
    stmt: &mut rusqlite::Statement<'_>,
    r: &LccRecord,
) -> rusqlite::Result<()> {
    stmt.execute(rusqlite::params_from_iter(r.column_values().map(Bind)))?;
    Ok(())
}

/// Reads a row selected with [`RECORD_COLUMNS`] (starting at column 0).
pub(crate) fn record_from_row(row: &Row<'_>) -> rusqlite::Result<LccRecord> {
    let mut values: [OwnedColumnValue; 27] =
        std::array::from_fn(|_| OwnedColumnValue::OptionalReal(None));
    for (i, (col, slot)) in LCC_RECORD_COLUMNS.iter().zip(values.iter_mut()).enumerate() {
        *slot = match col.kind {
            ColumnKind::Text => OwnedColumnValue::Text(row.get(i)?),
            ColumnKind::Real => OwnedColumnValue::Real(row.get(i)?),
            ColumnKind::OptionalReal => OwnedColumnValue::OptionalReal(row.get(i)?),
            ColumnKind::Integer => OwnedColumnValue::Integer(row.get(i)?),
        };
    }
    LccRecord::from_column_values(values).map_err(|p| {
        rusqlite::Error::FromSqlConversionFailure(
            LCC_RECORD_COLUMNS
                .iter()
                .position(|c| c.name == p.column)
                .unwrap_or(0),
            rusqlite::types::Type::Integer,
            Box::new(p),
        )
    })
}

//! Rows into records, on either back end: the decoders read through [`SqlRow`], a tiny
//! accessor each client implements once (`sql::sqlite`, `sql::pg`), so that a row of either
//! database becomes an [`LccRecord`], [`RunInfo`], [`NodeProgress`] or [`DynamicsRecord`]
//! by the same code, with the same `Corrupt` errors for what does not decode.

use std::path::Path;

use spm_records::{
    ColumnKind, DynamicsRecord, LCC_RECORD_COLUMNS, LccColumns, LccRecord, NodeProgress, NodeState,
    OwnedColumnValue, PlanNode, ProgressSummary, RunInfo, RunStatus,
};

use crate::error::{CdbError, Result};

/// One row of a result, read by column index (from 0). A value of the wrong type, or NULL
/// where a value is required, is an error ([`crate::ErrorKind::Corrupt`] for what the
/// client could not convert).
pub(crate) trait SqlRow {
    /// Where the row comes from (for errors).
    fn path(&self) -> &Path;
    /// Text.
    fn text(&self, i: usize) -> Result<String>;
    /// Text or NULL.
    fn opt_text(&self, i: usize) -> Result<Option<String>>;
    /// A double (SQLite: an integer too).
    fn real(&self, i: usize) -> Result<f64>;
    /// A double or NULL.
    fn opt_real(&self, i: usize) -> Result<Option<f64>>;
    /// A 64-bit integer.
    fn integer(&self, i: usize) -> Result<i64>;
}

/// `impl SqlRow for $t` through its `path` field and a generic
/// `fn get<T>(&self, i: usize) -> Result<T>` (the client's own conversion).
macro_rules! sql_row_via_get {
    ($t:ty) => {
        impl $crate::sql::row::SqlRow for $t {
            fn path(&self) -> &::std::path::Path {
                self.path
            }
            fn text(&self, i: usize) -> $crate::Result<String> {
                self.get(i)
            }
            fn opt_text(&self, i: usize) -> $crate::Result<Option<String>> {
                self.get(i)
            }
            fn real(&self, i: usize) -> $crate::Result<f64> {
                self.get(i)
            }
            fn opt_real(&self, i: usize) -> $crate::Result<Option<f64>> {
                self.get(i)
            }
            fn integer(&self, i: usize) -> $crate::Result<i64> {
                self.get(i)
            }
        }
    };
}
pub(crate) use sql_row_via_get;

fn corrupt(path: &Path, reason: String) -> CdbError {
    CdbError::Corrupt {
        path: path.to_path_buf(),
        reason,
    }
}

/// A stored index or count (a 64-bit integer) as `u32`, or a `Corrupt` error naming the
/// column.
pub(crate) fn stored_index(path: &Path, column: &str, v: i64) -> Result<u32> {
    u32::try_from(v).map_err(|_| corrupt(path, format!("{column} = {v} is not an index")))
}

/// A stored `model_version` as `u32`, or corrupt data.
pub(crate) fn stored_version(path: &Path, v: i64) -> Result<u32> {
    u32::try_from(v).map_err(|_| {
        corrupt(
            path,
            format!("dynamics.model_version {v} is not a version number"),
        )
    })
}

/// A row selected with [`super::record_columns`] (from column 0).
pub(crate) fn record(r: &dyn SqlRow) -> Result<LccRecord> {
    let mut values: [OwnedColumnValue; LCC_RECORD_COLUMNS.len()] =
        std::array::from_fn(|_| OwnedColumnValue::OptionalReal(None));
    for (i, (col, slot)) in LCC_RECORD_COLUMNS.iter().zip(values.iter_mut()).enumerate() {
        *slot = match col.kind {
            ColumnKind::Text => OwnedColumnValue::Text(r.text(i)?),
            ColumnKind::Real => OwnedColumnValue::Real(r.real(i)?),
            ColumnKind::OptionalReal => OwnedColumnValue::OptionalReal(r.opt_real(i)?),
            ColumnKind::Integer => OwnedColumnValue::Integer(r.integer(i)?),
        };
    }
    LccRecord::from_column_values(values).map_err(|p| corrupt(r.path(), p.to_string()))
}

/// A row selected with [`super::RUN_COLUMNS`].
pub(crate) fn run(r: &dyn SqlRow) -> Result<RunInfo> {
    let status = r.text(5)?;
    Ok(RunInfo {
        run_id: r.text(0)?,
        scanner_id: r.text(1)?,
        config: r.text(2)?,
        started_unix_s: r.real(3)?,
        finished_unix_s: r.opt_real(4)?,
        status: RunStatus::parse(&status)
            .ok_or_else(|| corrupt(r.path(), format!("unknown run status {status:?}")))?,
    })
}

/// A node state as stored (`pending`, `done`, `given_up` with its reason).
fn node_state(path: &Path, state: &str, reason: Option<String>) -> Result<NodeState> {
    match state {
        "pending" => Ok(NodeState::Pending),
        "done" => Ok(NodeState::Done),
        "given_up" => Ok(NodeState::GivenUp(reason.unwrap_or_default())),
        other => Err(corrupt(path, format!("unknown node state {other:?}"))),
    }
}

/// A row selected with [`super::PROGRESS_COLUMNS`].
pub(crate) fn progress(r: &dyn SqlRow) -> Result<NodeProgress> {
    let path = r.path();
    let state = node_state(path, &r.text(5)?, r.opt_text(6)?)?;
    Ok(NodeProgress {
        node: PlanNode {
            repeat_index: stored_index(path, "repeat_index", r.integer(0)?)?,
            node_index: stored_index(path, "node_index", r.integer(1)?)?,
            node_x_counts: r.integer(2)?,
            node_y_counts: r.integer(3)?,
            node_z_counts: r.integer(4)?,
        },
        state,
        attempts: stored_index(path, "attempts", r.integer(7)?)?,
        updated_unix_s: r.opt_real(8)?,
    })
}

/// A row `state, count(*)` added to a summary.
pub(crate) fn add_to_summary(r: &dyn SqlRow, s: &mut ProgressSummary) -> Result<()> {
    let state = r.text(0)?;
    let n = r.integer(1)?.unsigned_abs();
    match node_state(r.path(), &state, None)? {
        NodeState::Pending => s.pending = n,
        NodeState::Done => s.done = n,
        NodeState::GivenUp(_) => s.given_up = n,
    }
    Ok(())
}

/// A row selected with [`super::DYNAMICS_COLUMNS`], from column `first`.
pub(crate) fn dynamics(r: &dyn SqlRow, first: usize) -> Result<DynamicsRecord> {
    Ok(DynamicsRecord {
        run_id: r.text(first)?,
        scanner_id: r.text(first + 1)?,
        identified_unix_s: r.real(first + 2)?,
        model_format: r.text(first + 3)?,
        model_version: stored_version(r.path(), r.integer(first + 4)?)?,
        model_json: r.text(first + 5)?,
    })
}

/// A row selected with [`super::REGRESSION_COLUMNS`], appended to the columns.
pub(crate) fn push_columns(r: &dyn SqlRow, c: &mut LccColumns) -> Result<()> {
    c.lcs_x_counts.push(r.real(0)?);
    c.lcs_y_counts.push(r.real(1)?);
    c.node_z_counts.push(r.integer(2)?);
    c.acquired_unix_s.push(r.real(3)?);
    c.kx_nm_per_count.push(r.real(4)?);
    c.ky_nm_per_count.push(r.real(5)?);
    c.alpha_rad.push(r.real(6)?);
    c.kz_nm_per_count.push(r.opt_real(7)?);
    Ok(())
}

//! The queries of [`crate::CdbRead`], once for both back ends, over a [`SqlRead`]
//! connection: the SQLite file or snapshot (`sql::sqlite::Conn`) and the PostgreSQL
//! database or snapshot (`PgCdb`). [`sql_read!`](crate::sql::read::sql_read) writes the
//! `CdbRead` impls from them.

use std::path::Path;

use spm_records::{
    DynamicsRecord, LccColumns, LccRecord, NodeProgress, PlanNode, ProgressSummary, RecordFilter,
    RunInfo,
};

use super::row::{self, SqlRow};
use super::{
    DYNAMICS_COLUMNS, Dialect, PROGRESS_COLUMNS, Param, REGRESSION_COLUMNS, RUN_COLUMNS,
    check_filter, record_columns, where_clause,
};
use crate::error::Result;

/// A connection that runs queries (a read transaction or not).
pub(crate) trait SqlRead {
    /// The dialect of its statements.
    fn dialect(&self) -> Dialect;
    /// Where the database is (for errors).
    fn location(&self) -> &Path;
    /// Runs `sql` with `params` and calls `each` with every row, in order; an error of
    /// `each` stops the query and is returned. `each` must not start another query.
    fn query_each(
        &self,
        sql: &str,
        params: &[Param<'_>],
        each: &mut dyn FnMut(&dyn SqlRow) -> Result<()>,
    ) -> Result<()>;
}

/// Every row of a query, each decoded by `decode`.
pub(crate) fn query_all<T>(
    db: &(impl SqlRead + ?Sized),
    sql: &str,
    params: &[Param<'_>],
    decode: impl Fn(&dyn SqlRow) -> Result<T>,
) -> Result<Vec<T>> {
    let mut out = Vec::new();
    db.query_each(sql, params, &mut |r| {
        out.push(decode(r)?);
        Ok(())
    })?;
    Ok(out)
}

/// The first row of a query, decoded, or `None`.
pub(crate) fn query_first<T>(
    db: &(impl SqlRead + ?Sized),
    sql: &str,
    params: &[Param<'_>],
    decode: impl Fn(&dyn SqlRow) -> Result<T>,
) -> Result<Option<T>> {
    let mut first = None;
    db.query_each(sql, params, &mut |r| {
        if first.is_none() {
            first = Some(decode(r)?);
        }
        Ok(())
    })?;
    Ok(first)
}

pub(crate) fn for_each_record(
    db: &(impl SqlRead + ?Sized),
    filter: &RecordFilter,
    each: &mut dyn FnMut(LccRecord) -> Result<()>,
) -> Result<()> {
    check_filter(db.location(), filter)?;
    let (w, p) = where_clause(db.dialect(), filter);
    let sql = format!(
        "SELECT {} FROM records{w} ORDER BY acquired_unix_s, id",
        record_columns()
    );
    db.query_each(&sql, &p, &mut |r| each(row::record(r)?))
}

pub(crate) fn count_records(db: &(impl SqlRead + ?Sized), filter: &RecordFilter) -> Result<u64> {
    check_filter(db.location(), filter)?;
    let (w, p) = where_clause(db.dialect(), filter);
    let n = query_first(db, &format!("SELECT count(*) FROM records{w}"), &p, |r| {
        r.integer(0)
    })?;
    Ok(n.unwrap_or(0).unsigned_abs())
}

pub(crate) fn columns(db: &(impl SqlRead + ?Sized), filter: &RecordFilter) -> Result<LccColumns> {
    check_filter(db.location(), filter)?;
    let d = db.dialect();
    let (w, p) = where_clause(d, filter);
    let sql = format!(
        "SELECT {REGRESSION_COLUMNS} FROM {}{w} ORDER BY id",
        d.records_scan()
    );
    let mut c = LccColumns::default();
    db.query_each(&sql, &p, &mut |r| row::push_columns(r, &mut c))?;
    Ok(c)
}

pub(crate) fn scanners(db: &(impl SqlRead + ?Sized)) -> Result<Vec<String>> {
    query_all(
        db,
        "SELECT scanner_id FROM runs UNION SELECT DISTINCT scanner_id FROM records ORDER BY 1",
        &[],
        |r| r.text(0),
    )
}

pub(crate) fn z_planes(db: &(impl SqlRead + ?Sized), scanner_id: &str) -> Result<Vec<i64>> {
    let sql = format!(
        "SELECT DISTINCT node_z_counts FROM records WHERE scanner_id = {} ORDER BY 1",
        db.dialect().placeholder(1)
    );
    query_all(db, &sql, &[Param::Text(scanner_id)], |r| r.integer(0))
}

pub(crate) fn run(db: &(impl SqlRead + ?Sized), run_id: &str) -> Result<Option<RunInfo>> {
    let sql = format!(
        "SELECT {RUN_COLUMNS} FROM runs WHERE run_id = {}",
        db.dialect().placeholder(1)
    );
    query_first(db, &sql, &[Param::Text(run_id)], row::run)
}

pub(crate) fn runs(db: &(impl SqlRead + ?Sized), scanner_id: Option<&str>) -> Result<Vec<RunInfo>> {
    let d = db.dialect();
    let sql = format!(
        "SELECT {RUN_COLUMNS} FROM runs WHERE {} IS NULL OR scanner_id = {} \
         ORDER BY started_unix_s, run_id",
        d.nullable_text(1),
        d.placeholder(1)
    );
    query_all(db, &sql, &[Param::OptText(scanner_id)], row::run)
}

pub(crate) fn progress(db: &(impl SqlRead + ?Sized), run_id: &str) -> Result<Vec<NodeProgress>> {
    let sql = format!(
        "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = {} \
         ORDER BY repeat_index, node_index",
        db.dialect().placeholder(1)
    );
    query_all(db, &sql, &[Param::Text(run_id)], row::progress)
}

pub(crate) fn next_pending(db: &(impl SqlRead + ?Sized), run_id: &str) -> Result<Option<PlanNode>> {
    let sql = format!(
        "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = {} AND state = 'pending' \
         ORDER BY repeat_index, node_index LIMIT 1",
        db.dialect().placeholder(1)
    );
    query_first(db, &sql, &[Param::Text(run_id)], |r| {
        row::progress(r).map(|p| p.node)
    })
}

pub(crate) fn progress_summary(
    db: &(impl SqlRead + ?Sized),
    run_id: &str,
) -> Result<ProgressSummary> {
    let sql = format!(
        "SELECT state, count(*) FROM progress WHERE run_id = {} GROUP BY state",
        db.dialect().placeholder(1)
    );
    let mut s = ProgressSummary::default();
    db.query_each(&sql, &[Param::Text(run_id)], &mut |r| {
        row::add_to_summary(r, &mut s)
    })?;
    Ok(s)
}

/// The dynamics of one scanner (or of all, by scanner), oldest first.
pub(crate) fn dynamics(
    db: &(impl SqlRead + ?Sized),
    scanner_id: Option<&str>,
) -> Result<Vec<DynamicsRecord>> {
    let d = db.dialect();
    let sql = format!(
        "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE {} IS NULL OR scanner_id = {} \
         ORDER BY scanner_id, identified_unix_s, id",
        d.nullable_text(1),
        d.placeholder(1)
    );
    query_all(db, &sql, &[Param::OptText(scanner_id)], |r| {
        row::dynamics(r, 0)
    })
}

/// The newest dynamics of a scanner (the last of [`dynamics`]).
pub(crate) fn latest_dynamics(
    db: &(impl SqlRead + ?Sized),
    scanner_id: &str,
) -> Result<Option<DynamicsRecord>> {
    let sql = format!(
        "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE scanner_id = {} \
         ORDER BY identified_unix_s DESC, id DESC LIMIT 1",
        db.dialect().placeholder(1)
    );
    query_first(db, &sql, &[Param::Text(scanner_id)], |r| {
        row::dynamics(r, 0)
    })
}

/// `impl CdbRead for $t` from the shared queries above: `$s` names `self` in the
/// expressions, `sql` is the [`SqlRead`] connection, `path` the location, `version` and
/// `check` the two back-end-specific reads (the schema version's place, and the structural
/// half of `cdb check`).
macro_rules! sql_read {
    ($t:ty, |$s:ident| sql: $sql:expr, path: $path:expr, version: $version:expr,
     check: $check:expr $(,)?) => {
        impl $crate::CdbRead for $t {
            fn path(&self) -> &::std::path::Path {
                let $s = self;
                $path
            }
            fn schema_version(&self) -> $crate::Result<i64> {
                let $s = self;
                $version
            }
            fn for_each_record(
                &self,
                filter: &spm_records::RecordFilter,
                each: &mut dyn FnMut(spm_records::LccRecord) -> $crate::Result<()>,
            ) -> $crate::Result<()> {
                let $s = self;
                $crate::sql::read::for_each_record(&$sql, filter, each)
            }
            fn count_records(&self, filter: &spm_records::RecordFilter) -> $crate::Result<u64> {
                let $s = self;
                $crate::sql::read::count_records(&$sql, filter)
            }
            fn columns(
                &self,
                filter: &spm_records::RecordFilter,
            ) -> $crate::Result<spm_records::LccColumns> {
                let $s = self;
                $crate::sql::read::columns(&$sql, filter)
            }
            fn scanners(&self) -> $crate::Result<Vec<String>> {
                let $s = self;
                $crate::sql::read::scanners(&$sql)
            }
            fn z_planes(&self, scanner_id: &str) -> $crate::Result<Vec<i64>> {
                let $s = self;
                $crate::sql::read::z_planes(&$sql, scanner_id)
            }
            fn run(&self, run_id: &str) -> $crate::Result<Option<spm_records::RunInfo>> {
                let $s = self;
                $crate::sql::read::run(&$sql, run_id)
            }
            fn runs(&self, scanner_id: Option<&str>) -> $crate::Result<Vec<spm_records::RunInfo>> {
                let $s = self;
                $crate::sql::read::runs(&$sql, scanner_id)
            }
            fn progress(&self, run_id: &str) -> $crate::Result<Vec<spm_records::NodeProgress>> {
                let $s = self;
                $crate::sql::read::progress(&$sql, run_id)
            }
            fn next_pending(&self, run_id: &str) -> $crate::Result<Option<spm_records::PlanNode>> {
                let $s = self;
                $crate::sql::read::next_pending(&$sql, run_id)
            }
            fn progress_summary(
                &self,
                run_id: &str,
            ) -> $crate::Result<spm_records::ProgressSummary> {
                let $s = self;
                $crate::sql::read::progress_summary(&$sql, run_id)
            }
            fn dynamics(
                &self,
                scanner_id: Option<&str>,
            ) -> $crate::Result<Vec<spm_records::DynamicsRecord>> {
                let $s = self;
                $crate::sql::read::dynamics(&$sql, scanner_id)
            }
            fn latest_dynamics(
                &self,
                scanner_id: &str,
            ) -> $crate::Result<Option<spm_records::DynamicsRecord>> {
                let $s = self;
                $crate::sql::read::latest_dynamics(&$sql, scanner_id)
            }
            fn check(&self) -> $crate::Result<spm_records::IntegrityReport> {
                let $s = self;
                $check
            }
        }
    };
}
pub(crate) use sql_read;

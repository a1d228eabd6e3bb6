//! Read-only queries, shared by [`crate::Cdb`] and [`crate::Snapshot`].

use rusqlite::types::Value;
use rusqlite::{Connection, OptionalExtension, Row, params};
use std::collections::BTreeMap;
use std::path::Path;

use crate::error::{CdbError, Result};
use spm_records::{
    Coefficient, CoefficientStat, LccColumns, LccRecord, NodeProgress, NodeState, PlanNode,
    ProgressSummary, RecordFilter, RunInfo, RunStatus, TrendGrouping, TrendPoint,
};

pub(crate) use crate::columns::{RECORD_COLUMNS, record_from_row};

/// WHERE clause and parameters of a filter.
pub(crate) fn where_clause(f: &RecordFilter) -> (String, Vec<Value>) {
    let mut terms = Vec::new();
    let mut params = Vec::new();
    if let Some(s) = &f.scanner_id {
        terms.push("scanner_id = ?");
        params.push(Value::Text(s.clone()));
    }
    if let Some(r) = &f.run_id {
        terms.push("run_id = ?");
        params.push(Value::Text(r.clone()));
    }
    if let Some(z) = f.node_z_counts {
        terms.push("node_z_counts = ?");
        params.push(Value::Integer(z));
    }
    if let Some(t) = f.since_unix_s {
        terms.push("acquired_unix_s >= ?");
        params.push(Value::Real(t));
    }
    if let Some(t) = f.until_unix_s {
        terms.push("acquired_unix_s <= ?");
        params.push(Value::Real(t));
    }
    if terms.is_empty() {
        (String::new(), params)
    } else {
        (format!(" WHERE {}", terms.join(" AND ")), params)
    }
}

fn check_filter(path: &Path, f: &RecordFilter) -> Result<()> {
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

/// Calls `each` for every selected record, ordered by acquisition time then id.
pub(crate) fn for_each_record(
    conn: &Connection,
    path: &Path,
    filter: &RecordFilter,
    mut each: impl FnMut(LccRecord) -> Result<()>,
) -> Result<()> {
    check_filter(path, filter)?;
    let (w, p) = where_clause(filter);
    let sql = format!(
        "SELECT {} FROM records{w} ORDER BY acquired_unix_s, id",
        *RECORD_COLUMNS
    );
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn.prepare(&sql).map_err(err)?;
    let mut rows = stmt.query(rusqlite::params_from_iter(p)).map_err(err)?;
    while let Some(row) = rows.next().map_err(err)? {
        each(record_from_row(row).map_err(err)?)?;
    }
    Ok(())
}

pub(crate) fn records(conn: &Connection, path: &Path, f: &RecordFilter) -> Result<Vec<LccRecord>> {
    let mut out = Vec::new();
    for_each_record(conn, path, f, |r| {
        out.push(r);
        Ok(())
    })?;
    Ok(out)
}

pub(crate) fn count_records(conn: &Connection, path: &Path, f: &RecordFilter) -> Result<u64> {
    check_filter(path, f)?;
    let (w, p) = where_clause(f);
    conn.query_row(
        &format!("SELECT count(*) FROM records{w}"),
        rusqlite::params_from_iter(p),
        |r| r.get(0),
    )
    .map_err(|e| CdbError::sqlite(path, e))
}

pub(crate) fn columns(conn: &Connection, path: &Path, f: &RecordFilter) -> Result<LccColumns> {
    check_filter(path, f)?;
    let (w, p) = where_clause(f);
    let sql = format!(
        "SELECT lcs_x_counts, lcs_y_counts, node_z_counts, acquired_unix_s, kx_nm_per_count, \
         ky_nm_per_count, alpha_rad, kz_nm_per_count FROM records NOT INDEXED{w} ORDER BY id"
    );
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn.prepare(&sql).map_err(err)?;
    let mut rows = stmt.query(rusqlite::params_from_iter(p)).map_err(err)?;
    let mut c = LccColumns::default();
    while let Some(r) = rows.next().map_err(err)? {
        c.lcs_x_counts.push(r.get(0).map_err(err)?);
        c.lcs_y_counts.push(r.get(1).map_err(err)?);
        c.node_z_counts.push(r.get(2).map_err(err)?);
        c.acquired_unix_s.push(r.get(3).map_err(err)?);
        c.kx_nm_per_count.push(r.get(4).map_err(err)?);
        c.ky_nm_per_count.push(r.get(5).map_err(err)?);
        c.alpha_rad.push(r.get(6).map_err(err)?);
        c.kz_nm_per_count.push(r.get(7).map_err(err)?);
    }
    Ok(c)
}

pub(crate) fn scanners(conn: &Connection, path: &Path) -> Result<Vec<String>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(
            "SELECT scanner_id FROM runs UNION SELECT DISTINCT scanner_id FROM records \
             ORDER BY 1",
        )
        .map_err(err)?;
    let v = stmt
        .query_map([], |r| r.get(0))
        .map_err(err)?
        .collect::<rusqlite::Result<Vec<String>>>()
        .map_err(err)?;
    Ok(v)
}

pub(crate) fn z_planes(conn: &Connection, path: &Path, scanner_id: &str) -> Result<Vec<i64>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare("SELECT DISTINCT node_z_counts FROM records WHERE scanner_id = ? ORDER BY 1")
        .map_err(err)?;
    let v = stmt
        .query_map([scanner_id], |r| r.get(0))
        .map_err(err)?
        .collect::<rusqlite::Result<Vec<i64>>>()
        .map_err(err)?;
    Ok(v)
}

fn run_from_row(path: &Path, r: &Row<'_>) -> Result<RunInfo> {
    let err = |e| CdbError::sqlite(path, e);
    let status: String = r.get(5).map_err(err)?;
    Ok(RunInfo {
        run_id: r.get(0).map_err(err)?,
        scanner_id: r.get(1).map_err(err)?,
        config: r.get(2).map_err(err)?,
        started_unix_s: r.get(3).map_err(err)?,
        finished_unix_s: r.get(4).map_err(err)?,
        status: RunStatus::parse(&status).ok_or_else(|| CdbError::Corrupt {
            path: path.to_path_buf(),
            reason: format!("unknown run status {status:?}"),
        })?,
    })
}

const RUN_COLUMNS: &str = "run_id, scanner_id, config, started_unix_s, finished_unix_s, status";

pub(crate) fn run(conn: &Connection, path: &Path, run_id: &str) -> Result<Option<RunInfo>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!("SELECT {RUN_COLUMNS} FROM runs WHERE run_id = ?"))
        .map_err(err)?;
    let mut rows = stmt.query([run_id]).map_err(err)?;
    match rows.next().map_err(err)? {
        Some(r) => Ok(Some(run_from_row(path, r)?)),
        None => Ok(None),
    }
}

pub(crate) fn runs(
    conn: &Connection,
    path: &Path,
    scanner_id: Option<&str>,
) -> Result<Vec<RunInfo>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT {RUN_COLUMNS} FROM runs WHERE ?1 IS NULL OR scanner_id = ?1 \
             ORDER BY started_unix_s, run_id"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([scanner_id]).map_err(err)?;
    let mut out = Vec::new();
    while let Some(r) = rows.next().map_err(err)? {
        out.push(run_from_row(path, r)?);
    }
    Ok(out)
}

const PROGRESS_COLUMNS: &str = "repeat_index, node_index, node_x_counts, node_y_counts, \
node_z_counts, state, reason, attempts, updated_unix_s";

fn progress_from_row(path: &Path, r: &Row<'_>) -> Result<NodeProgress> {
    let err = |e| CdbError::sqlite(path, e);
    let state: String = r.get(5).map_err(err)?;
    let reason: Option<String> = r.get(6).map_err(err)?;
    let state = match state.as_str() {
        "pending" => NodeState::Pending,
        "done" => NodeState::Done,
        "given_up" => NodeState::GivenUp(reason.unwrap_or_default()),
        other => {
            return Err(CdbError::Corrupt {
                path: path.to_path_buf(),
                reason: format!("unknown node state {other:?}"),
            });
        }
    };
    Ok(NodeProgress {
        node: PlanNode {
            repeat_index: r.get(0).map_err(err)?,
            node_index: r.get(1).map_err(err)?,
            node_x_counts: r.get(2).map_err(err)?,
            node_y_counts: r.get(3).map_err(err)?,
            node_z_counts: r.get(4).map_err(err)?,
        },
        state,
        attempts: r.get(7).map_err(err)?,
        updated_unix_s: r.get(8).map_err(err)?,
    })
}

pub(crate) fn progress(conn: &Connection, path: &Path, run_id: &str) -> Result<Vec<NodeProgress>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = ? \
             ORDER BY repeat_index, node_index"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([run_id]).map_err(err)?;
    let mut out = Vec::new();
    while let Some(r) = rows.next().map_err(err)? {
        out.push(progress_from_row(path, r)?);
    }
    Ok(out)
}

pub(crate) fn next_pending(
    conn: &Connection,
    path: &Path,
    run_id: &str,
) -> Result<Option<PlanNode>> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare(&format!(
            "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = ? AND state = 'pending' \
             ORDER BY repeat_index, node_index LIMIT 1"
        ))
        .map_err(err)?;
    let mut rows = stmt.query([run_id]).map_err(err)?;
    match rows.next().map_err(err)? {
        Some(r) => Ok(Some(progress_from_row(path, r)?.node)),
        None => Ok(None),
    }
}

pub(crate) fn progress_summary(
    conn: &Connection,
    path: &Path,
    run_id: &str,
) -> Result<ProgressSummary> {
    let err = |e| CdbError::sqlite(path, e);
    let mut stmt = conn
        .prepare("SELECT state, count(*) FROM progress WHERE run_id = ? GROUP BY state")
        .map_err(err)?;
    let mut rows = stmt.query([run_id]).map_err(err)?;
    let mut s = ProgressSummary::default();
    while let Some(r) = rows.next().map_err(err)? {
        let state: String = r.get(0).map_err(err)?;
        let n: u64 = r.get(1).map_err(err)?;
        match state.as_str() {
            "pending" => s.pending = n,
            "done" => s.done = n,
            "given_up" => s.given_up = n,
            other => {
                return Err(CdbError::Corrupt {
                    path: path.to_path_buf(),
                    reason: format!("unknown node state {other:?}"),
                });
            }
        }
    }
    Ok(s)
}

/// Welford accumulator.
#[derive(Default)]
struct Acc {
    n: u64,
    mean: f64,
    m2: f64,
}

impl Acc {
    fn push(&mut self, v: f64) {
        self.n += 1;
        let d = v - self.mean;
        self.mean += d / self.n as f64;
        self.m2 += d * (v - self.mean);
    }
    fn stat(&self) -> Option<CoefficientStat> {
        if self.n == 0 {
            return None;
        }
        let std_dev = if self.n > 1 {
            (self.m2 / (self.n - 1) as f64).max(0.0).sqrt()
        } else {
            0.0
        };
        Some(CoefficientStat {
            n: self.n,
            mean: self.mean,
            std_dev,
            std_uncertainty: std_dev / (self.n as f64).sqrt(),
        })
    }
}

struct Group {
    time: Acc,
    first: f64,
    last: f64,
    value: Acc,
}

/// UTC calendar day of a Unix time, `YYYY-MM-DD`.
pub(crate) fn utc_day(t_unix_s: f64) -> String {
    let days = (t_unix_s / 86_400.0).floor();
    let secs = days * 86_400.0;
    // Range-checked conversion: out-of-range times get a placeholder, never a panic.
    if !(secs.is_finite() && secs.abs() < 1e14) {
        return "invalid-date".into();
    }
    match time::OffsetDateTime::from_unix_timestamp(secs as i64) {
        Ok(t) => format!("{:04}-{:02}-{:02}", t.year(), u8::from(t.month()), t.day()),
        Err(_) => "invalid-date".into(),
    }
}

pub(crate) fn age_dynamics(
    conn: &Connection,
    path: &Path,
    filter: &RecordFilter,
    coefficient: Coefficient,
    grouping: TrendGrouping,
) -> Result<Vec<TrendPoint>> {
    let mut groups: BTreeMap<String, Group> = BTreeMap::new();
    let mut order: Vec<String> = Vec::new();
    for_each_record(conn, path, filter, |r| {
        let key = match grouping {
            TrendGrouping::PerRun => r.run_id.clone(),
            TrendGrouping::PerDay => utc_day(r.acquired_unix_s),
            TrendGrouping::PerNodePerRun => format!(
                "{},{},{}@{}",
                r.node_x_counts, r.node_y_counts, r.node_z_counts, r.run_id
            ),
        };
        let value = match coefficient {
            Coefficient::KxNmPerCount => Some(r.kx_nm_per_count),
            Coefficient::KyNmPerCount => Some(r.ky_nm_per_count),
            Coefficient::AlphaRad => Some(r.alpha_rad),
            Coefficient::KzNmPerCount => r.kz_nm_per_count,
        };
        let g = groups.entry(key.clone()).or_insert_with(|| {
            order.push(key);
            Group {
                time: Acc::default(),
                first: r.acquired_unix_s,
                last: r.acquired_unix_s,
                value: Acc::default(),
            }
        });
        g.time.push(r.acquired_unix_s);
        g.first = g.first.min(r.acquired_unix_s);
        g.last = g.last.max(r.acquired_unix_s);
        if let Some(v) = value {
            g.value.push(v);
        }
        Ok(())
    })?;
    let mut out: Vec<TrendPoint> = order
        .into_iter()
        .filter_map(|k| {
            groups.remove(&k).map(|g| TrendPoint {
                key: k,
                mean_unix_s: g.time.mean,
                first_unix_s: g.first,
                last_unix_s: g.last,
                stat: g.value.stat(),
            })
        })
        .collect();
    out.sort_by(|a, b| {
        a.mean_unix_s
            .total_cmp(&b.mean_unix_s)
            .then_with(|| a.key.cmp(&b.key))
    });
    Ok(out)
}

/// True if the run exists.
pub(crate) fn run_exists(conn: &Connection, path: &Path, run_id: &str) -> Result<bool> {
    conn.query_row(
        "SELECT 1 FROM runs WHERE run_id = ?",
        params![run_id],
        |_| Ok(()),
    )
    .optional()
    .map(|o| o.is_some())
    .map_err(|e| CdbError::sqlite(path, e))
}

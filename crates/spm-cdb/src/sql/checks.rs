//! The semantic half of `cdb check`, once for both back ends: the rules every stored value,
//! relation and dynamics row must obey, as SQL predicates in the [`Dialect`], each finding one
//! row of text naming the row. (The structural half — SQLite's pragmas, PostgreSQL's catalog —
//! stays with each back end, as do SQLite's type checks, which PostgreSQL's column types make
//! unnecessary.)

use std::collections::HashMap;

use spm_records::{
    ColumnKind, IntegrityProblem, IntegrityReport, LCC_RECORD_COLUMNS, LccRecord, Plausibility,
    RecordFilter,
};

use super::read::{SqlRead, query_all};
use super::{DYNAMICS_COLUMNS, Dialect};
use crate::error::Result;

/// Report at most this many rows per kind of problem.
pub(crate) const MAX_ROWS_PER_CHECK: usize = 1000;

/// A check under way: the connection and the findings so far.
pub(crate) struct Checker<'a, R: SqlRead + ?Sized> {
    /// The connection.
    pub(crate) db: &'a R,
    /// The findings.
    pub(crate) report: IntegrityReport,
}

impl<'a, R: SqlRead + ?Sized> Checker<'a, R> {
    pub(crate) fn new(db: &'a R) -> Self {
        Self {
            db,
            report: IntegrityReport::default(),
        }
    }

    /// Runs `sql` (selecting one text column describing the row) and records each row as a
    /// problem of `kind`, at most [`MAX_ROWS_PER_CHECK`] and then one "… more" line.
    pub(crate) fn rows(&mut self, kind: &str, sql: &str) -> Result<()> {
        let limited = format!(
            "SELECT * FROM ({sql}) AS found LIMIT {}",
            MAX_ROWS_PER_CHECK + 1
        );
        let details = query_all(self.db, &limited, &[], |r| r.text(0))?;
        for (n, detail) in details.into_iter().enumerate() {
            if n >= MAX_ROWS_PER_CHECK {
                self.report.problems.push(IntegrityProblem {
                    kind: kind.into(),
                    detail: format!("… more than {MAX_ROWS_PER_CHECK} rows"),
                });
                break;
            }
            self.report.problems.push(IntegrityProblem {
                kind: kind.into(),
                detail,
            });
        }
        Ok(())
    }

    /// The records where `predicate` holds, as problems of `kind` saying `what`.
    pub(crate) fn record_rows(&mut self, kind: &str, what: &str, predicate: &str) -> Result<()> {
        let d = self.db.dialect();
        let sql = format!(
            "SELECT 'record id ' || id || ' (run ' || {} || ', repeat ' || {} || ', node ' || \
             {} || '): {what}' FROM records WHERE {predicate} ORDER BY id",
            d.quote("run_id"),
            d.quote_integer("repeat_index"),
            d.quote_integer("node_index"),
        );
        self.rows(kind, &sql)
    }
}

/// The stored values of every record: finite numbers (and, on SQLite, integers where the
/// schema says so), K̄x, K̄y, Kz > 0, |α| < π/2, uncertainties ≥ 0, ids not blank, indexes
/// and counts in `0..=u32::MAX`.
pub(crate) fn value_checks<R: SqlRead + ?Sized>(c: &mut Checker<'_, R>) -> Result<()> {
    let d = c.db.dialect();
    for col in &LCC_RECORD_COLUMNS {
        if matches!(col.kind, ColumnKind::Real | ColumnKind::OptionalReal) {
            let nullable = col.kind == ColumnKind::OptionalReal;
            c.record_rows(
                "non_finite",
                &format!("{} not finite", col.name),
                &d.not_finite(col.name, nullable),
            )?;
        }
    }
    if d == Dialect::Sqlite {
        for col in LCC_RECORD_COLUMNS
            .iter()
            .filter(|c| c.kind == ColumnKind::Integer)
        {
            c.record_rows(
                "bad_type",
                &format!("{} not an integer", col.name),
                &format!("NOT ({})", d.typed(col.name, ColumnKind::Integer)),
            )?;
        }
    }
    for col in spm_records::POSITIVE_COLUMNS {
        c.record_rows(
            "nonpositive_lcc",
            &format!("{col} <= 0"),
            &format!("{} AND {col} <= 0", d.is_number(col)),
        )?;
    }
    c.record_rows(
        "alpha_out_of_range",
        "|alpha_rad| >= pi/2",
        &format!(
            "{} AND abs(alpha_rad) >= 1.5707963267948966",
            d.is_number("alpha_rad")
        ),
    )?;
    for col in spm_records::UNCERTAINTY_COLUMNS {
        c.record_rows(
            "negative_uncertainty",
            &format!("{col} < 0"),
            &format!("{} AND {col} < 0", d.is_number(col)),
        )?;
    }
    for col in LCC_RECORD_COLUMNS
        .iter()
        .filter(|c| c.kind == ColumnKind::Text)
    {
        c.record_rows(
            "empty_text",
            &format!("{} is empty", col.name),
            &format!(
                "{} AND {}",
                d.typed(col.name, ColumnKind::Text),
                d.blank(col.name)
            ),
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
            &format!(
                "{} AND ({col} < 0 OR {col} > 4294967295)",
                d.typed(col, ColumnKind::Integer)
            ),
        )?;
    }
    Ok(())
}

/// How records, plan nodes and runs relate: no duplicate record, done nodes with records
/// and unfinished ones without, records at their plan node and on their run's scanner,
/// given-up nodes with a reason, one identity row and every run of this database.
pub(crate) fn relation_checks<R: SqlRead + ?Sized>(c: &mut Checker<'_, R>) -> Result<()> {
    let d = c.db.dialect();
    let (q, qi) = (|col: &str| d.quote(col), |col: &str| d.quote_integer(col));
    c.rows(
        "duplicate_record",
        &format!(
            "SELECT 'run ' || {} || ', repeat ' || {} || ', node ' || {} || ', lcs ' || {} || \
             ': ' || count(*) || ' records' FROM records \
             GROUP BY run_id, repeat_index, node_index, lcs_index HAVING count(*) > 1",
            q("run_id"),
            qi("repeat_index"),
            qi("node_index"),
            qi("lcs_index")
        ),
    )?;
    let plan_row = format!(
        "'run ' || {} || ', repeat ' || p.repeat_index || ', node ' || p.node_index",
        q("p.run_id")
    );
    let has_records = "EXISTS (SELECT 1 FROM records r WHERE r.run_id = p.run_id AND \
                       r.repeat_index = p.repeat_index AND r.node_index = p.node_index)";
    c.rows(
        "done_without_records",
        &format!(
            "SELECT {plan_row} || ' is done but has no record' FROM progress p \
             WHERE p.state = 'done' AND NOT {has_records} \
             ORDER BY p.run_id, p.repeat_index, p.node_index"
        ),
    )?;
    c.rows(
        "records_for_unfinished_node",
        &format!(
            "SELECT {plan_row} || ' is ' || p.state || ' but has records' FROM progress p \
             WHERE p.state <> 'done' AND {has_records} \
             ORDER BY p.run_id, p.repeat_index, p.node_index"
        ),
    )?;
    c.rows(
        "node_mismatch",
        "SELECT 'record id ' || r.id || ': node (' || r.node_x_counts || ', ' || \
         r.node_y_counts || ', ' || r.node_z_counts || ') differs from its plan node' \
         FROM records r JOIN progress p ON r.run_id = p.run_id AND \
         r.repeat_index = p.repeat_index AND r.node_index = p.node_index \
         WHERE r.node_x_counts <> p.node_x_counts OR r.node_y_counts <> p.node_y_counts \
         OR r.node_z_counts <> p.node_z_counts ORDER BY r.id",
    )?;
    c.rows(
        "given_up_without_reason",
        &format!(
            "SELECT 'run ' || {} || ', repeat ' || repeat_index || ', node ' || node_index || \
             ' given up without a reason' FROM progress WHERE state = 'given_up' \
             AND (reason IS NULL OR {})",
            q("run_id"),
            d.blank("reason")
        ),
    )?;
    c.rows(
        "identity",
        "SELECT 'cdb_identity holds ' || count(*) || ' rows, expected 1' FROM cdb_identity \
         HAVING count(*) <> 1",
    )?;
    c.rows(
        "foreign_run",
        &format!(
            "SELECT 'run ' || {} || ': cdb_id ' || {} || ' is not this database''s id' \
             FROM runs WHERE coalesce(cdb_id, '') <> coalesce({}, '') ORDER BY run_id",
            q("run_id"),
            q("cdb_id"),
            d.identity_id()
        ),
    )?;
    c.rows(
        "scanner_mismatch",
        &format!(
            "SELECT 'record id ' || r.id || ': scanner ' || {} || ' but run ' || {} || \
             ' is on ' || {} FROM records r JOIN runs u ON r.run_id = u.run_id \
             WHERE r.scanner_id <> u.scanner_id ORDER BY r.id",
            q("r.scanner_id"),
            q("r.run_id"),
            q("u.scanner_id")
        ),
    )
}

/// The scanner dynamics (schema v5): the version in range, the run stored and on the same
/// scanner, and every row whose columns have their types obeying
/// [`DynamicsRecord::check`](spm_records::DynamicsRecord::check) (the time finite and > 0,
/// the model a JSON object of bounded size, visible ids).
pub(crate) fn dynamics_checks<R: SqlRead + ?Sized>(c: &mut Checker<'_, R>) -> Result<()> {
    let d = c.db.dialect();
    let q = |col: &str| d.quote(col);
    let version_typed = d.typed("model_version", ColumnKind::Integer);
    c.rows(
        "invalid_dynamics",
        &format!(
            "SELECT 'dynamics id ' || id || ': model_version ' || model_version || \
             ' is not in 1..=4294967295' FROM dynamics WHERE {version_typed} \
             AND model_version NOT BETWEEN 1 AND 4294967295 ORDER BY id"
        ),
    )?;
    c.rows(
        "dynamics_without_run",
        &format!(
            "SELECT 'dynamics id ' || d.id || ': run ' || {} || ' does not exist' \
             FROM dynamics d WHERE NOT EXISTS (SELECT 1 FROM runs u WHERE u.run_id = d.run_id) \
             ORDER BY d.id",
            q("d.run_id")
        ),
    )?;
    c.rows(
        "scanner_mismatch",
        &format!(
            "SELECT 'dynamics id ' || d.id || ': scanner ' || {} || ' but run ' || {} || \
             ' is on ' || {} FROM dynamics d JOIN runs u ON d.run_id = u.run_id \
             WHERE d.scanner_id <> u.scanner_id ORDER BY d.id",
            q("d.scanner_id"),
            q("d.run_id"),
            q("u.scanner_id")
        ),
    )?;
    let typed = [
        d.typed("run_id", ColumnKind::Text),
        d.typed("scanner_id", ColumnKind::Text),
        d.typed("identified_unix_s", ColumnKind::Real),
        d.typed("model_format", ColumnKind::Text),
        version_typed,
        d.typed("model_json", ColumnKind::Text),
    ]
    .join(" AND ");
    let sql = format!(
        "SELECT id, {DYNAMICS_COLUMNS} FROM dynamics WHERE {typed} \
         AND model_version BETWEEN 1 AND 4294967295 ORDER BY id"
    );
    let mut found = crate::dynamics::Findings::new(MAX_ROWS_PER_CHECK);
    c.db.query_each(&sql, &[], &mut |r| {
        let id = r.integer(0)?;
        found.add(crate::dynamics::problem(id, &super::row::dynamics(r, 1)?));
        Ok(())
    })?;
    c.report.problems.extend(found.into_problems());
    Ok(())
}

/// Every record against its run's plausibility limits
/// ([`LccRecord::implausibility`]: field, distance from its node, nominal sensitivity), as
/// `implausible_record`. A record that cannot be decoded ends the pass with an
/// `undecodable_record` problem (the other checks name its columns).
pub(crate) fn plausibility_checks<R: SqlRead + ?Sized>(c: &mut Checker<'_, R>) -> Result<()> {
    let d = c.db.dialect();
    let sql = format!(
        "SELECT run_id, config FROM runs WHERE {} AND {}",
        d.typed("run_id", ColumnKind::Text),
        d.typed("config", ColumnKind::Text)
    );
    let runs = query_all(c.db, &sql, &[], |r| Ok((r.text(0)?, r.text(1)?)))?;
    let limits: HashMap<&str, Plausibility> = runs
        .iter()
        .map(|(id, config)| (id.as_str(), Plausibility::from_run_config(config)))
        .filter(|(_, p)| !p.is_empty())
        .collect();
    if limits.is_empty() {
        return Ok(());
    }
    let report = &mut c.report;
    let mut found = 0usize;
    let result =
        super::read::for_each_record(c.db, &RecordFilter::default(), &mut |r: LccRecord| {
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

//! The writes of a calibration's progress, once for both back ends: runs, plans, nodes
//! committed or given up, dynamics. Each is checked first (nothing is opened for invalid
//! input), then runs as one write transaction of the back end ([`SqlStore::write`]: SQLite
//! `BEGIN IMMEDIATE` and the identity's generation stepped at commit; PostgreSQL
//! `READ COMMITTED` with the rows it decides on locked by [`Dialect::for_update`]), over a
//! [`SqlTx`].
//!
//! # One `ProgressStore`
//! [`ProgressStore`](spm_records::ProgressStore) is implemented once, by
//! [`progress_store!`](crate::sql::write::progress_store) from the generic functions here
//! ([`begin_run`], [`states`], [`commit_node`], [`give_up_node`], [`finish_run`]) for any
//! [`SqlStore`]. A blanket `impl<T: SqlStore> ProgressStore for T` is what it would be, but
//! Rust's orphan rule forbids it (the trait is spm-records', the type parameter is
//! uncovered), so the macro writes the two one-line-per-method impls.

use std::collections::HashMap;
use std::path::Path;

use spm_records::{DynamicsRecord, LccRecord, NodeDone, NodeState, PlanNode, RunInfo, RunStatus};

use super::read::{SqlRead, query_all, query_first};
use super::{DYNAMICS_COLUMNS, Param};
use crate::error::{CdbError, Result};
use crate::{CdbRead, check_belongs, check_run_ids, check_time, invalid, validate_record};

/// A write transaction.
pub(crate) trait SqlTx: SqlRead {
    /// Runs a statement; returns the number of rows it changed.
    fn execute(&mut self, sql: &str, params: &[Param<'_>]) -> Result<u64>;
    /// Inserts one record (a statement prepared once per connection).
    fn insert_record(&mut self, r: &LccRecord) -> Result<()>;
}

/// A CDB that writes: each call of [`SqlStore::write`] is one transaction, committed when
/// `f` returns `Ok`, rolled back otherwise.
pub(crate) trait SqlStore: CdbRead {
    /// Runs `f` in one write transaction. A back end that reconnects after a lost
    /// connection (PostgreSQL) runs `f` again from the start in a new transaction when the
    /// first did not commit, so `f` must do nothing outside the transaction.
    fn write<T>(&mut self, f: impl FnMut(&mut dyn SqlTx) -> Result<T>) -> Result<T>;
}

fn unknown_run(path: &Path, run_id: &str) -> CdbError {
    CdbError::NotFound {
        path: path.to_path_buf(),
        what: format!("run {run_id:?}"),
    }
}

fn unknown_node(path: &Path, run_id: &str, repeat_index: u32, node_index: u32) -> CdbError {
    CdbError::NotFound {
        path: path.to_path_buf(),
        what: format!("plan node (run {run_id:?}, repeat {repeat_index}, node {node_index})"),
    }
}

fn not_pending(path: &Path, run_id: &str, repeat: u32, node: u32, state: &str) -> CdbError {
    CdbError::Conflict {
        path: path.to_path_buf(),
        reason: format!("run {run_id:?} repeat {repeat} node {node} is {state}, not pending"),
    }
}

/// `WHERE run_id = p1 AND repeat_index = p2 AND node_index = p3`.
fn node_key(tx: &dyn SqlTx) -> String {
    let d = tx.dialect();
    format!(
        "WHERE run_id = {} AND repeat_index = {} AND node_index = {}",
        d.placeholder(1),
        d.placeholder(2),
        d.placeholder(3)
    )
}

/// Sets a plan node's state (with its reason, or none), attempts and time.
fn set_state(
    tx: &mut dyn SqlTx,
    [run_id, repeat, node]: [Param<'_>; 3],
    state: &str,
    reason: Option<&str>,
    attempts: u32,
    at_unix_s: f64,
) -> Result<()> {
    let d = tx.dialect();
    let sql = format!(
        "UPDATE progress SET state = {}, reason = {}, attempts = {}, updated_unix_s = {} {}",
        d.placeholder(4),
        d.placeholder(5),
        d.placeholder(6),
        d.placeholder(7),
        node_key(tx)
    );
    let params = [
        run_id,
        repeat,
        node,
        Param::Text(state),
        Param::OptText(reason),
        attempts.into(),
        Param::Real(at_unix_s),
    ];
    tx.execute(&sql, &params)?;
    Ok(())
}

/// Registers a new run (status as given, normally [`RunStatus::Running`]).
pub(crate) fn create_run(s: &mut impl SqlStore, run: &RunInfo) -> Result<()> {
    let path = s.path().to_path_buf();
    check_run_ids(&path, run)?;
    check_time(&path, "started_unix_s", run.started_unix_s)?;
    if let Some(t) = run.finished_unix_s {
        check_time(&path, "finished_unix_s", t)?;
    }
    s.write(|tx| {
        let d = tx.dialect();
        let sql = format!(
            "INSERT INTO runs (run_id, scanner_id, config, started_unix_s, finished_unix_s, \
             status, cdb_id) VALUES ({}, {}) ON CONFLICT (run_id) DO NOTHING",
            d.placeholders(6),
            d.identity_id()
        );
        let n = tx.execute(
            &sql,
            &[
                Param::Text(&run.run_id),
                Param::Text(&run.scanner_id),
                Param::Text(&run.config),
                Param::Real(run.started_unix_s),
                Param::OptReal(run.finished_unix_s),
                Param::Text(run.status.as_str()),
            ],
        )?;
        if n == 0 {
            return Err(CdbError::Conflict {
                path: path.clone(),
                reason: format!("run {:?} already exists", run.run_id),
            });
        }
        Ok(())
    })?;
    tracing::info!(run_id = %run.run_id, scanner_id = %run.scanner_id, "run created");
    Ok(())
}

/// Sets a run's final status and end time.
pub(crate) fn finish_run(
    s: &mut impl SqlStore,
    run_id: &str,
    status: RunStatus,
    finished_unix_s: f64,
) -> Result<()> {
    let path = s.path().to_path_buf();
    check_time(&path, "finished_unix_s", finished_unix_s)?;
    s.write(|tx| {
        let d = tx.dialect();
        let sql = format!(
            "UPDATE runs SET status = {}, finished_unix_s = {} WHERE run_id = {}",
            d.placeholder(2),
            d.placeholder(3),
            d.placeholder(1)
        );
        let params = [
            Param::Text(run_id),
            Param::Text(status.as_str()),
            Param::Real(finished_unix_s),
        ];
        if tx.execute(&sql, &params)? == 0 {
            return Err(unknown_run(&path, run_id));
        }
        Ok(())
    })?;
    tracing::info!(run_id, status = status.as_str(), "run finished");
    Ok(())
}

/// Sets an unfinished run back to 'running' with no end time; a finished run is never
/// reopened.
pub(crate) fn reopen_run(s: &mut impl SqlStore, run_id: &str) -> Result<()> {
    let path = s.path().to_path_buf();
    s.write(|tx| {
        let d = tx.dialect();
        let sql = format!(
            "SELECT status FROM runs WHERE run_id = {}{}",
            d.placeholder(1),
            d.for_update()
        );
        let status = query_first(tx, &sql, &[Param::Text(run_id)], |r| r.text(0))?
            .ok_or_else(|| unknown_run(&path, run_id))?;
        if status == RunStatus::Finished.as_str() {
            return Err(CdbError::Conflict {
                path: path.clone(),
                reason: format!("run {run_id:?} is finished and cannot be resumed"),
            });
        }
        let sql = format!(
            "UPDATE runs SET status = 'running', finished_unix_s = NULL WHERE run_id = {}",
            d.placeholder(1)
        );
        tx.execute(&sql, &[Param::Text(run_id)])?;
        Ok(())
    })?;
    tracing::info!(run_id, "run reopened");
    Ok(())
}

/// Registers a run's plan (all nodes pending). Idempotent: nodes registered before at the
/// same place are left as they are; one at another place is a conflict. Every node is
/// inserted unless present (`ON CONFLICT … DO NOTHING`, the same upsert on both back ends),
/// then the stored places are compared, so that two programs registering one plan at once
/// cannot slip a different place past each other.
pub(crate) fn register_plan(s: &mut impl SqlStore, run_id: &str, nodes: &[PlanNode]) -> Result<()> {
    let path = s.path().to_path_buf();
    s.write(|tx| {
        let d = tx.dialect();
        let exists = format!("SELECT 1 FROM runs WHERE run_id = {}", d.placeholder(1));
        if query_first(tx, &exists, &[Param::Text(run_id)], |_| Ok(()))?.is_none() {
            return Err(unknown_run(&path, run_id));
        }
        let put = format!(
            "INSERT INTO progress (run_id, repeat_index, node_index, node_x_counts, \
             node_y_counts, node_z_counts, state, attempts) VALUES ({}, 'pending', 0) \
             ON CONFLICT (run_id, repeat_index, node_index) DO NOTHING",
            d.placeholders(6)
        );
        for n in nodes {
            tx.execute(
                &put,
                &[
                    Param::Text(run_id),
                    n.repeat_index.into(),
                    n.node_index.into(),
                    Param::Integer(n.node_x_counts),
                    Param::Integer(n.node_y_counts),
                    Param::Integer(n.node_z_counts),
                ],
            )?;
        }
        let sql = format!(
            "SELECT repeat_index, node_index, node_x_counts, node_y_counts, node_z_counts \
             FROM progress WHERE run_id = {}",
            d.placeholder(1)
        );
        let stored: HashMap<(i64, i64), (i64, i64, i64)> =
            query_all(tx, &sql, &[Param::Text(run_id)], |r| {
                Ok((
                    (r.integer(0)?, r.integer(1)?),
                    (r.integer(2)?, r.integer(3)?, r.integer(4)?),
                ))
            })?
            .into_iter()
            .collect();
        for n in nodes {
            let key = (i64::from(n.repeat_index), i64::from(n.node_index));
            let want = (n.node_x_counts, n.node_y_counts, n.node_z_counts);
            if let Some(&xyz) = stored.get(&key)
                && xyz != want
            {
                return Err(CdbError::Conflict {
                    path: path.clone(),
                    reason: format!(
                        "run {run_id:?} repeat {} node {} is registered at {xyz:?}",
                        n.repeat_index, n.node_index
                    ),
                });
            }
        }
        Ok(())
    })?;
    tracing::debug!(run_id, nodes = nodes.len(), "plan registered");
    Ok(())
}

/// Stores a measured node: its records inserted and its plan row marked done, in one
/// transaction holding the plan row (all or nothing).
pub(crate) fn commit_node(
    s: &mut impl SqlStore,
    run_id: &str,
    done: &NodeDone,
    records: &[LccRecord],
) -> Result<()> {
    let path = s.path().to_path_buf();
    check_time(&path, "finished_unix_s", done.finished_unix_s)?;
    if records.is_empty() {
        return Err(invalid(
            &path,
            "commit_node needs at least one record (use give_up_node otherwise)".into(),
        ));
    }
    for r in records {
        validate_record(&path, r)?;
    }
    let (repeat, node) = (done.repeat_index, done.node_index);
    s.write(|tx| {
        let d = tx.dialect();
        let sql = format!(
            "SELECT scanner_id FROM runs WHERE run_id = {}",
            d.placeholder(1)
        );
        let scanner_id = query_first(tx, &sql, &[Param::Text(run_id)], |r| r.text(0))?
            .ok_or_else(|| unknown_run(&path, run_id))?;
        let key = [Param::Text(run_id), repeat.into(), node.into()];
        let sql = format!(
            "SELECT node_x_counts, node_y_counts, node_z_counts, state FROM progress {}{}",
            node_key(tx),
            d.for_update()
        );
        let (xyz, state) = query_first(tx, &sql, &key, |r| {
            Ok(((r.integer(0)?, r.integer(1)?, r.integer(2)?), r.text(3)?))
        })?
        .ok_or_else(|| unknown_node(&path, run_id, repeat, node))?;
        if state != "pending" {
            return Err(not_pending(&path, run_id, repeat, node, &state));
        }
        for r in records {
            check_belongs(&path, run_id, &scanner_id, done, xyz, r)?;
            tx.insert_record(r)?;
        }
        set_state(tx, key, "done", None, done.attempts, done.finished_unix_s)?;
        Ok(())
    })?;
    tracing::debug!(
        run_id,
        repeat,
        node,
        records = records.len(),
        "node committed"
    );
    Ok(())
}

/// Marks a pending plan node as given up, with the reason.
pub(crate) fn give_up_node(
    s: &mut impl SqlStore,
    run_id: &str,
    visit: &NodeDone,
    reason: &str,
) -> Result<()> {
    let path = s.path().to_path_buf();
    check_time(&path, "at_unix_s", visit.finished_unix_s)?;
    if reason.trim().is_empty() {
        return Err(invalid(&path, "a given-up node needs a reason".into()));
    }
    let (repeat, node) = (visit.repeat_index, visit.node_index);
    s.write(|tx| {
        let d = tx.dialect();
        let key = [Param::Text(run_id), repeat.into(), node.into()];
        let sql = format!(
            "SELECT state FROM progress {}{}",
            node_key(tx),
            d.for_update()
        );
        let state = query_first(tx, &sql, &key, |r| r.text(0))?
            .ok_or_else(|| unknown_node(&path, run_id, repeat, node))?;
        if state != "pending" {
            return Err(not_pending(&path, run_id, repeat, node, &state));
        }
        set_state(
            tx,
            key,
            "given_up",
            Some(reason),
            visit.attempts,
            visit.finished_unix_s,
        )?;
        Ok(())
    })?;
    tracing::warn!(
        run_id,
        repeat_index = repeat,
        node_index = node,
        reason,
        "node given up"
    );
    Ok(())
}

/// Stores the scanner dynamics a run identified; the run must be stored (and is held while
/// the row goes in) and be on the record's scanner.
pub(crate) fn store_dynamics(s: &mut impl SqlStore, dynamics: &DynamicsRecord) -> Result<()> {
    let path = s.path().to_path_buf();
    crate::dynamics::validate(&path, dynamics)?;
    s.write(|tx| {
        let d = tx.dialect();
        let sql = format!(
            "SELECT scanner_id FROM runs WHERE run_id = {}{}",
            d.placeholder(1),
            d.for_share()
        );
        let run_scanner = query_first(tx, &sql, &[Param::Text(&dynamics.run_id)], |r| r.text(0))?
            .ok_or_else(|| crate::dynamics::unknown_run(&path, dynamics))?;
        crate::dynamics::check_run_scanner(&path, dynamics, &run_scanner)?;
        let sql = format!(
            "INSERT INTO dynamics ({DYNAMICS_COLUMNS}) VALUES ({})",
            d.placeholders(6)
        );
        tx.execute(
            &sql,
            &[
                Param::Text(&dynamics.run_id),
                Param::Text(&dynamics.scanner_id),
                Param::Real(dynamics.identified_unix_s),
                Param::Text(&dynamics.model_format),
                dynamics.model_version.into(),
                Param::Text(&dynamics.model_json),
            ],
        )?;
        Ok(())
    })?;
    tracing::info!(
        run_id = %dynamics.run_id,
        scanner_id = %dynamics.scanner_id,
        model_format = %dynamics.model_format,
        model_version = dynamics.model_version,
        "scanner dynamics stored"
    );
    Ok(())
}

/// [`ProgressStore::begin_run`](spm_records::ProgressStore::begin_run): the run created
/// unless stored, its plan registered.
pub(crate) fn begin_run(s: &mut impl SqlStore, run: &RunInfo, visits: &[PlanNode]) -> Result<()> {
    if s.run(&run.run_id)?.is_none() {
        create_run(s, run)?;
    }
    register_plan(s, &run.run_id, visits)
}

/// [`ProgressStore::states`](spm_records::ProgressStore::states): every plan node's state.
pub(crate) fn states(s: &impl SqlStore, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>> {
    Ok(s.progress(run_id)?
        .into_iter()
        .map(|p| ((p.node.repeat_index, p.node.node_index), p.state))
        .collect())
}

/// `impl ProgressStore for $t` (a [`SqlStore`]) from the functions above.
macro_rules! progress_store {
    ($t:ty) => {
        impl spm_records::ProgressStore for $t {
            type Error = $crate::CdbError;
            fn begin_run(
                &mut self,
                run: &spm_records::RunInfo,
                visits: &[spm_records::PlanNode],
            ) -> $crate::Result<()> {
                $crate::sql::write::begin_run(self, run, visits)
            }
            fn states(
                &mut self,
                run_id: &str,
            ) -> $crate::Result<::std::collections::HashMap<(u32, u32), spm_records::NodeState>>
            {
                $crate::sql::write::states(self, run_id)
            }
            fn commit_node(
                &mut self,
                run_id: &str,
                done: &spm_records::NodeDone,
                records: &[spm_records::LccRecord],
            ) -> $crate::Result<()> {
                $crate::sql::write::commit_node(self, run_id, done, records)
            }
            fn give_up_node(
                &mut self,
                run_id: &str,
                visit: &spm_records::NodeDone,
                reason: &str,
            ) -> $crate::Result<()> {
                $crate::sql::write::give_up_node(self, run_id, visit, reason)
            }
            fn finish_run(
                &mut self,
                run_id: &str,
                status: spm_records::RunStatus,
                at_unix_s: f64,
            ) -> $crate::Result<()> {
                $crate::sql::write::finish_run(self, run_id, status, at_unix_s)
            }
        }
    };
}
pub(crate) use progress_store;

/// The public write methods of a [`SqlStore`] (`Cdb`, `PgCdb`), each the function of the
/// same name above; used inside the type's `impl` block.
macro_rules! write_methods {
    () => {
        /// Registers a new run (status as given, normally
        /// [`RunStatus::Running`](spm_records::RunStatus::Running)).
        ///
        /// # Errors
        /// [`ErrorKind::Conflict`](crate::ErrorKind::Conflict) if the run id exists;
        /// [`ErrorKind::InvalidInput`](crate::ErrorKind::InvalidInput) for empty ids or
        /// non-finite times.
        pub fn create_run(&mut self, run: &spm_records::RunInfo) -> $crate::Result<()> {
            $crate::sql::write::create_run(self, run)
        }

        /// Sets a run's final status and end time.
        ///
        /// # Errors
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown run;
        /// [`ErrorKind::InvalidInput`](crate::ErrorKind::InvalidInput) for a non-finite time.
        pub fn finish_run(
            &mut self,
            run_id: &str,
            status: spm_records::RunStatus,
            finished_unix_s: f64,
        ) -> $crate::Result<()> {
            $crate::sql::write::finish_run(self, run_id, status, finished_unix_s)
        }

        /// Sets an unfinished run ('running', 'aborted' or 'failed') back to 'running' with
        /// no end time, for a resume. A finished run is never reopened.
        ///
        /// # Errors
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown run;
        /// [`ErrorKind::Conflict`](crate::ErrorKind::Conflict) for a finished one.
        pub fn reopen_run(&mut self, run_id: &str) -> $crate::Result<()> {
            $crate::sql::write::reopen_run(self, run_id)
        }

        /// Registers a run's plan (all nodes pending) in one transaction. Idempotent: nodes
        /// already registered with the same coordinates are left as they are (so a resumed
        /// run may call it again).
        ///
        /// # Errors
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown run;
        /// [`ErrorKind::Conflict`](crate::ErrorKind::Conflict) if a node exists with other
        /// coordinates.
        pub fn register_plan(
            &mut self,
            run_id: &str,
            nodes: &[spm_records::PlanNode],
        ) -> $crate::Result<()> {
            $crate::sql::write::register_plan(self, run_id, nodes)
        }

        /// Stores a measured node: inserts its `records` and marks the plan node done, in one
        /// transaction (all or nothing; on PostgreSQL it holds the plan row's lock, so that
        /// of two programs resuming one run the second finds the node done). Every record
        /// must belong to this run, repeat and node, carry the plan node's coordinates and
        /// the run's scanner.
        ///
        /// # Errors
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown run or plan
        /// node; [`ErrorKind::Conflict`](crate::ErrorKind::Conflict) if the node is not
        /// pending (also when another program committed it meanwhile) or a record duplicates
        /// an LCS index; [`ErrorKind::InvalidInput`](crate::ErrorKind::InvalidInput) for
        /// invalid or mismatched records or an empty slice.
        pub fn commit_node(
            &mut self,
            run_id: &str,
            done: &spm_records::NodeDone,
            records: &[spm_records::LccRecord],
        ) -> $crate::Result<()> {
            $crate::sql::write::commit_node(self, run_id, done, records)
        }

        /// Marks a pending plan node as given up, with the reason.
        ///
        /// # Errors
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown node;
        /// [`ErrorKind::Conflict`](crate::ErrorKind::Conflict) if not pending;
        /// [`ErrorKind::InvalidInput`](crate::ErrorKind::InvalidInput) for an empty reason or
        /// a non-finite time.
        pub fn give_up_node(
            &mut self,
            run_id: &str,
            repeat_index: u32,
            node_index: u32,
            reason: &str,
            attempts: u32,
            at_unix_s: f64,
        ) -> $crate::Result<()> {
            let visit = spm_records::NodeDone {
                repeat_index,
                node_index,
                attempts,
                finished_unix_s: at_unix_s,
            };
            $crate::sql::write::give_up_node(self, run_id, &visit, reason)
        }

        /// Stores the scanner dynamics a run identified, in one transaction (SQLite: stepping
        /// the identity's generation like every write; PostgreSQL: holding the run row's
        /// share lock, and leaving the generation alone like every write there). The run
        /// must be stored and on the record's scanner.
        ///
        /// # Errors
        /// [`ErrorKind::InvalidInput`](crate::ErrorKind::InvalidInput) for a record that
        /// breaks [`DynamicsRecord::check`](spm_records::DynamicsRecord::check) (the message
        /// names the field) or whose scanner is not its run's;
        /// [`ErrorKind::NotFound`](crate::ErrorKind::NotFound) for an unknown run. Nothing
        /// is written on error.
        pub fn store_dynamics(
            &mut self,
            dynamics: &spm_records::DynamicsRecord,
        ) -> $crate::Result<()> {
            $crate::sql::write::store_dynamics(self, dynamics)
        }
    };
}
pub(crate) use write_methods;

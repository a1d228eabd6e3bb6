//! The calibration database a command names: an embedded SQLite file (the default) or a
//! shared PostgreSQL database (`postgres://user@host:port/db`), behind one handle.
//!
//! Every place that takes a CDB path (`--cdb`, `cdb check|export|trend PATH`) takes a
//! PostgreSQL URL too; [`is_postgres`] tells them apart, so the file guards of
//! `files.rs` apply to files only. Reads go through [`spm_cdb::CdbRead`] (implemented by both
//! back ends), writes through [`spm_cdb::ProgressStore`] and the run bookkeeping here.

use spm_cdb::postgres::{PgCdb, is_postgres_url, redact_url};
use spm_cdb::{
    Cdb, CdbError, CdbRead, LccRecord, NodeDone, NodeState, PlanNode, ProgressStore, RunInfo,
    RunStatus,
};
use std::collections::HashMap;
use std::path::Path;

/// True if the CDB location is a PostgreSQL URL rather than a file.
#[must_use]
pub fn is_postgres(location: &Path) -> bool {
    location.to_str().is_some_and(is_postgres_url)
}

/// The location for messages: the file, or the URL without its password.
#[must_use]
pub fn shown(location: &Path) -> String {
    match location.to_str() {
        Some(url) if is_postgres_url(url) => redact_url(url),
        _ => location.display().to_string(),
    }
}

/// An open CDB on either back end.
#[derive(Debug)]
pub enum CdbHandle {
    /// The embedded file.
    Sqlite(Cdb),
    /// The shared PostgreSQL database.
    Postgres(PgCdb),
}

impl CdbHandle {
    /// Opens read-write: a file is created when missing, a PostgreSQL database gets the
    /// schema when it has none; older schemas are migrated.
    ///
    /// # Errors
    /// The back end's open errors.
    pub fn open(location: &Path) -> Result<Self, CdbError> {
        match location.to_str() {
            Some(url) if is_postgres_url(url) => PgCdb::open(url).map(Self::Postgres),
            _ => Cdb::open(location).map(Self::Sqlite),
        }
    }

    /// Opens an existing CDB read-only.
    ///
    /// # Errors
    /// The back end's open errors.
    pub fn open_read_only(location: &Path) -> Result<Self, CdbError> {
        match location.to_str() {
            Some(url) if is_postgres_url(url) => PgCdb::open_read_only(url).map(Self::Postgres),
            _ => Cdb::open_read_only(location).map(Self::Sqlite),
        }
    }

    /// The queries.
    #[must_use]
    pub fn read(&self) -> &dyn CdbRead {
        match self {
            Self::Sqlite(c) => c,
            Self::Postgres(c) => c,
        }
    }

    /// A read transaction: every query through it sees one committed state.
    ///
    /// # Errors
    /// The back end's errors.
    pub fn snapshot(&self) -> Result<Box<dyn CdbRead + '_>, CdbError> {
        Ok(match self {
            Self::Sqlite(c) => Box::new(c.snapshot()?),
            Self::Postgres(c) => Box::new(c.snapshot()?),
        })
    }

    /// Registers a new run.
    ///
    /// # Errors
    /// [`spm_cdb::ErrorKind::Conflict`] if the run id exists; the back end's errors.
    pub fn create_run(&mut self, run: &RunInfo) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.create_run(run),
            Self::Postgres(c) => c.create_run(run),
        }
    }

    /// Sets an unfinished run back to 'running' for a resume.
    ///
    /// # Errors
    /// The back end's errors.
    pub fn reopen_run(&mut self, run_id: &str) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.reopen_run(run_id),
            Self::Postgres(c) => c.reopen_run(run_id),
        }
    }
}

impl ProgressStore for CdbHandle {
    type Error = CdbError;
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.begin_run(run, visits),
            Self::Postgres(c) => c.begin_run(run, visits),
        }
    }
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, CdbError> {
        match self {
            Self::Sqlite(c) => ProgressStore::states(c, run_id),
            Self::Postgres(c) => ProgressStore::states(c, run_id),
        }
    }
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.commit_node(run_id, done, records),
            Self::Postgres(c) => c.commit_node(run_id, done, records),
        }
    }
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => ProgressStore::give_up_node(c, run_id, visit, reason),
            Self::Postgres(c) => ProgressStore::give_up_node(c, run_id, visit, reason),
        }
    }
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.finish_run(run_id, status, at_unix_s),
            Self::Postgres(c) => c.finish_run(run_id, status, at_unix_s),
        }
    }
}

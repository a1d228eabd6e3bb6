//! The calibration database a command names: an embedded SQLite file (the default) or a
//! shared PostgreSQL database (`postgres://user@host:port/db`), behind one handle.
//!
//! Every place that takes a CDB path (`--cdb`, `cdb check|export|trend PATH`) takes a
//! PostgreSQL URL too; [`is_postgres`] tells them apart, so the file guards of
//! `files.rs` apply to files only. Reads go through [`spm_cdb::CdbRead`] (implemented by both
//! back ends), writes through [`spm_cdb::ProgressStore`] and the run bookkeeping here.

use spm_cdb::postgres::{PgCdb, is_postgres_url, redact_url};
use spm_cdb::{
    Cdb, CdbError, CdbRead, DynamicsRecord, IntegrityReport, LccColumns, LccRecord, NodeDone,
    NodeProgress, NodeState, PlanNode, ProgressStore, ProgressSummary, RecordFilter, RunInfo,
    RunStatus,
};
use spm_records::Plausibility;
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

    /// The run's stop flag: a PostgreSQL CDB stops reconnecting and cuts a wait for a
    /// silent server once it is set ([`PgCdb::set_interrupt`]); a file needs none (SQLite
    /// waits at most its busy timeout).
    pub fn set_interrupt(&mut self, stop: std::sync::Arc<std::sync::atomic::AtomicBool>) {
        if let Self::Postgres(c) = self {
            c.set_interrupt(stop);
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

    /// A read transaction for fitting: every query through it sees one committed state,
    /// and the records that break their run's plausibility limits (as `cdb check` reports
    /// them: [`spm_cdb::LccRecord::implausibility`]) are left out of `columns`, `records`
    /// and `count_records`, with a warning (issue 25: a bit-rotten LCS went into the fit).
    ///
    /// # Errors
    /// The back end's errors.
    pub fn snapshot(&self) -> Result<Box<dyn CdbRead + '_>, CdbError> {
        let inner = self.snapshot_unfiltered()?;
        Ok(Box::new(Plausible::new(inner)))
    }

    /// A read transaction that sees every stored record (check, export, trend).
    ///
    /// # Errors
    /// The back end's errors.
    pub fn snapshot_unfiltered(&self) -> Result<Box<dyn CdbRead + '_>, CdbError> {
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

    /// Stores the scanner dynamics a run identified (one transaction; the run must be
    /// stored and on the record's scanner).
    ///
    /// # Errors
    /// [`spm_cdb::ErrorKind::InvalidInput`] for an invalid record (the message names the
    /// field) or a scanner other than the run's; [`spm_cdb::ErrorKind::NotFound`] for an
    /// unknown run; the back end's errors.
    pub fn store_dynamics(&mut self, dynamics: &DynamicsRecord) -> Result<(), CdbError> {
        match self {
            Self::Sqlite(c) => c.store_dynamics(dynamics),
            Self::Postgres(c) => c.store_dynamics(dynamics),
        }
    }

    /// The dynamics identified for a scanner, oldest first, newest last.
    ///
    /// # Errors
    /// The back end's errors.
    pub fn dynamics_for_scanner(&self, scanner_id: &str) -> Result<Vec<DynamicsRecord>, CdbError> {
        self.read().dynamics_for_scanner(scanner_id)
    }

    /// The newest dynamics of a scanner, `None` when none was stored.
    ///
    /// # Errors
    /// The back end's errors.
    pub fn latest_dynamics(&self, scanner_id: &str) -> Result<Option<DynamicsRecord>, CdbError> {
        self.read().latest_dynamics(scanner_id)
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

/// Reads through a snapshot, leaving out the records that break their run's plausibility
/// limits (the rule `cdb check` reports as `implausible_record`).
struct Plausible<'a> {
    inner: Box<dyn CdbRead + 'a>,
    limits: HashMap<String, Plausibility>,
}

impl<'a> Plausible<'a> {
    fn new(inner: Box<dyn CdbRead + 'a>) -> Self {
        // A run that cannot be decoded gives no limits here; `cdb check` names it.
        let limits = match inner.runs(None) {
            Ok(runs) => runs
                .into_iter()
                .map(|r| (r.run_id, Plausibility::from_run_config(&r.config)))
                .filter(|(_, p)| !p.is_empty())
                .collect(),
            Err(e) => {
                tracing::debug!(error = %e, "runs unreadable: no plausibility limits");
                HashMap::new()
            }
        };
        Self { inner, limits }
    }

    fn plausible(&self, r: &LccRecord) -> bool {
        self.limits
            .get(&r.run_id)
            .is_none_or(|p| r.implausibility(p).is_none())
    }

    fn warn(&self, excluded: usize) {
        if excluded > 0 {
            tracing::warn!(
                cdb = %self.inner.path().display(),
                excluded,
                "records outside their run's plausibility limits (field, distance from the \
                 node, nominal sensitivity; as `spmcal cdb check` reports them) left out"
            );
        }
    }
}

impl CdbRead for Plausible<'_> {
    fn path(&self) -> &Path {
        self.inner.path()
    }
    fn schema_version(&self) -> Result<i64, CdbError> {
        self.inner.schema_version()
    }
    fn for_each_record(
        &self,
        filter: &RecordFilter,
        each: &mut dyn FnMut(LccRecord) -> Result<(), CdbError>,
    ) -> Result<(), CdbError> {
        let mut excluded = 0;
        self.inner.for_each_record(filter, &mut |r| {
            if self.plausible(&r) {
                each(r)
            } else {
                excluded += 1;
                Ok(())
            }
        })?;
        self.warn(excluded);
        Ok(())
    }
    fn count_records(&self, filter: &RecordFilter) -> Result<u64, CdbError> {
        if self.limits.is_empty() {
            return self.inner.count_records(filter);
        }
        let mut n = 0;
        self.inner.for_each_record(filter, &mut |r| {
            n += u64::from(self.plausible(&r));
            Ok(())
        })?;
        Ok(n)
    }
    fn columns(&self, filter: &RecordFilter) -> Result<LccColumns, CdbError> {
        if self.limits.is_empty() {
            return self.inner.columns(filter);
        }
        let mut c = LccColumns::default();
        self.for_each_record(filter, &mut |r| {
            c.push(&r);
            Ok(())
        })?;
        Ok(c)
    }
    fn scanners(&self) -> Result<Vec<String>, CdbError> {
        self.inner.scanners()
    }
    fn z_planes(&self, scanner_id: &str) -> Result<Vec<i64>, CdbError> {
        self.inner.z_planes(scanner_id)
    }
    fn run(&self, run_id: &str) -> Result<Option<RunInfo>, CdbError> {
        self.inner.run(run_id)
    }
    fn runs(&self, scanner_id: Option<&str>) -> Result<Vec<RunInfo>, CdbError> {
        self.inner.runs(scanner_id)
    }
    fn progress(&self, run_id: &str) -> Result<Vec<NodeProgress>, CdbError> {
        self.inner.progress(run_id)
    }
    fn next_pending(&self, run_id: &str) -> Result<Option<PlanNode>, CdbError> {
        self.inner.next_pending(run_id)
    }
    fn progress_summary(&self, run_id: &str) -> Result<ProgressSummary, CdbError> {
        self.inner.progress_summary(run_id)
    }
    fn dynamics(&self, scanner_id: Option<&str>) -> Result<Vec<DynamicsRecord>, CdbError> {
        self.inner.dynamics(scanner_id)
    }
    fn latest_dynamics(&self, scanner_id: &str) -> Result<Option<DynamicsRecord>, CdbError> {
        self.inner.latest_dynamics(scanner_id)
    }
    fn check(&self) -> Result<IntegrityReport, CdbError> {
        self.inner.check()
    }
}

//! Calibration database (CDB) of Lapshin's distributed calibration on embedded SQLite
//! (DESIGN §8): dated local calibration coefficients per node, calibration runs, and the
//! progress of each run's plan so that a run killed at any moment resumes at the next
//! unfinished node.
//!
//! # File and durability
//! - Schema version in `PRAGMA user_version` ([`SCHEMA_VERSION`]), file marked by
//!   `PRAGMA application_id` ([`APPLICATION_ID`]). Older files are migrated on a read-write
//!   open, one transaction per step; a file from a *newer* program is refused with
//!   [`ErrorKind::NewerSchema`] after a read-only look, without a single byte written.
//! - WAL journal: readers never block the writer and see a consistent snapshot
//!   ([`Cdb::snapshot`]); a busy timeout (default 5 s) covers short lock contention.
//! - `synchronous = FULL` by default: every committed node is on disk before
//!   [`Cdb::commit_node`] returns, so neither a crash nor a power loss loses instrument time
//!   that was reported as saved. With WAL, `NORMAL` would also never corrupt the file but could
//!   roll back the last commits after a power cut; the fsync costs ~milliseconds per node
//!   against seconds of instrument time per node, so FULL is the right default.
//!   [`Synchronous::Normal`] is available for bulk imports.
//! - Identity (schema v4, [`ErrorKind::IdentityMismatch`]): a random id and a generation
//!   stepped by every write transaction, the id in every run row, and both in a
//!   `NAME-identity` file outside the write-ahead log; an open refuses, before writing
//!   anything, a `-wal` of another database or one older than the file, and a file older
//!   than its identity file (a restored backup).
//! - One transaction per node: [`Cdb::commit_node`] writes the node's records and marks its
//!   plan entry done atomically; [`Cdb::import_records`] writes many records in one transaction.
//! - Scanner dynamics (schema v5): [`Cdb::store_dynamics`] keeps each identification of a
//!   scanner's hysteresis and creep ([`DynamicsRecord`], a versioned JSON object checked by
//!   [`DynamicsRecord::check`]) dated beside the LCCs; [`CdbRead::dynamics_for_scanner`] and
//!   [`CdbRead::latest_dynamics`] read them back. The model's types live in `spm-correction`,
//!   which this crate does not link.
//!
//! # Time
//! The library reads no clock: every time is supplied by the caller as UTC seconds since the
//! Unix epoch (`*_unix_s`); exports add RFC 3339 text.
//!
//! # Reading
//! Queries are methods of the [`CdbRead`] trait, implemented by [`Cdb`] (each query its own
//! snapshot) and by [`Snapshot`] (all queries in one read transaction), and on PostgreSQL by
//! `postgres::PgCdb` and `postgres::PgSnapshot`.
//!
//! # PostgreSQL (feature `postgres`)
//! [`postgres`](crate::postgres) is the same CDB on a shared PostgreSQL server, for several
//! instruments writing at once: same schema, versions and migrations, one transaction per
//! node. Both back ends run one SQL layer (`src/sql/`): a dialect for what is spelled
//! differently, then the same statements, row decoders, queries, progress writes (the one
//! [`ProgressStore`] implementation) and integrity rules; see that module's documentation.
//!
//! # Test support (feature `test-support`)
//! `bench_support` (synthetic records for benchmarks and tests) and, with `postgres`,
//! `pg_server` (a private PostgreSQL server for tests and benchmarks) are compiled only with
//! the feature `test-support`, which the dev-dependencies of the crates whose tests use them
//! and xtask turn on: a program (`cargo build -p spmcal`) compiles neither.
#![doc = include_str!("../README.md")]

mod backup;
#[cfg(feature = "test-support")]
pub mod bench_support;
mod constraints;
mod dynamics;
mod error;
mod export;
mod identity;
mod integrity;
#[cfg(all(feature = "postgres", feature = "test-support"))]
pub mod pg_server;
#[cfg(feature = "postgres")]
mod pg_watchdog;
#[cfg(feature = "postgres")]
mod pgpass;
#[cfg(feature = "postgres")]
pub mod postgres;
mod query;
mod schema;
mod sql;

use rusqlite::{Connection, OpenFlags, TransactionBehavior};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Duration;

pub use backup::BackupSummary;
pub use error::{CdbError, ErrorKind, Result};
pub use export::{CSV_HEADER, rfc3339_utc};
pub use schema::{APPLICATION_ID, SCHEMA_VERSION};
pub use spm_records::{
    Coefficient, CoefficientStat, DYNAMICS_MODEL_MAX_BYTES, DYNAMICS_RECORD_COLUMNS,
    DynamicsProblem, DynamicsRecord, IntegrityProblem, IntegrityReport, LccColumns, LccRecord,
    NodeDone, NodeProgress, NodeState, PlanNode, ProgressStore, ProgressSummary, RecordFilter,
    RunInfo, RunStatus, TrendGrouping, TrendPoint,
};

/// SQLite `synchronous` setting (with WAL).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Synchronous {
    /// fsync at every commit: committed nodes survive power loss (default).
    #[default]
    Full,
    /// fsync at checkpoints only: never corrupt, but the last commits may roll back after a
    /// power loss. For bulk imports.
    Normal,
}

/// Options of [`Cdb::open_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OpenOptions {
    /// Create the file if it does not exist (default true).
    pub create: bool,
    /// Durability setting (default [`Synchronous::Full`]).
    pub synchronous: Synchronous,
    /// How long to wait for a lock held by another connection (default 5 s).
    pub busy_timeout: Duration,
}

impl Default for OpenOptions {
    fn default() -> Self {
        Self {
            create: true,
            synchronous: Synchronous::Full,
            busy_timeout: Duration::from_secs(5),
        }
    }
}

/// An open calibration database.
#[derive(Debug)]
pub struct Cdb {
    conn: Connection,
    path: PathBuf,
}

/// A read transaction: every query through it sees the same committed state, whatever other
/// connections commit meanwhile. Ends when dropped.
#[derive(Debug)]
pub struct Snapshot<'c> {
    tx: rusqlite::Transaction<'c>,
    path: &'c Path,
}

/// Read-only queries, on either back end: the embedded file ([`Cdb`], [`Snapshot`]) or the
/// shared PostgreSQL database (`postgres::PgCdb`, `postgres::PgSnapshot`, feature
/// `postgres`). Object safe: programs that accept both back ends read through
/// `&dyn CdbRead`.
pub trait CdbRead {
    /// Where the database is: the file, or the PostgreSQL URL without its password.
    fn path(&self) -> &Path;

    /// Schema version of the database.
    ///
    /// # Errors
    /// Database errors.
    fn schema_version(&self) -> Result<i64>;

    /// Selected records ordered by acquisition time.
    ///
    /// # Errors
    /// [`ErrorKind::InvalidInput`] for a non-finite time bound; [`ErrorKind::Corrupt`] for a
    /// row that cannot be decoded; database errors.
    fn records(&self, filter: &RecordFilter) -> Result<Vec<LccRecord>> {
        let mut out = Vec::new();
        self.for_each_record(filter, &mut |r| {
            out.push(r);
            Ok(())
        })?;
        Ok(out)
    }

    /// Calls `each` for every selected record (ordered by acquisition time) without holding
    /// them all in memory; an error from `each` stops the iteration and is returned.
    ///
    /// # Errors
    /// As [`CdbRead::records`], or the error of `each`.
    fn for_each_record(
        &self,
        filter: &RecordFilter,
        each: &mut dyn FnMut(LccRecord) -> Result<()>,
    ) -> Result<()>;

    /// Number of selected records.
    ///
    /// # Errors
    /// As [`CdbRead::records`].
    fn count_records(&self, filter: &RecordFilter) -> Result<u64>;

    /// Selected records as numeric columns (for regression), in insertion order.
    ///
    /// On SQLite this reads the table sequentially (no index): a regression selection (a
    /// scanner's Z plane) is usually a large part of the table, where a scan is ~3× faster
    /// than 10⁶ index lookups, and a scan costs at most ~0.4 µs per stored record otherwise.
    ///
    /// # Errors
    /// As [`CdbRead::records`].
    fn columns(&self, filter: &RecordFilter) -> Result<LccColumns>;

    /// Scanner ids present in runs or records.
    ///
    /// # Errors
    /// Database errors.
    fn scanners(&self) -> Result<Vec<String>>;

    /// Distinct Z planes (node z, counts) of a scanner's records, ascending.
    ///
    /// # Errors
    /// Database errors.
    fn z_planes(&self, scanner_id: &str) -> Result<Vec<i64>>;

    /// A run by id.
    ///
    /// # Errors
    /// [`ErrorKind::Corrupt`] for an undecodable row; database errors.
    fn run(&self, run_id: &str) -> Result<Option<RunInfo>>;

    /// Runs, optionally of one scanner, by start time.
    ///
    /// # Errors
    /// As [`CdbRead::run`].
    fn runs(&self, scanner_id: Option<&str>) -> Result<Vec<RunInfo>>;

    /// The plan of a run with the state of every node, in (repeat, node) order.
    ///
    /// # Errors
    /// As [`CdbRead::run`].
    fn progress(&self, run_id: &str) -> Result<Vec<NodeProgress>>;

    /// The first pending node of a run in (repeat, node) order: where a resumed run continues.
    ///
    /// # Errors
    /// As [`CdbRead::run`].
    fn next_pending(&self, run_id: &str) -> Result<Option<PlanNode>>;

    /// Numbers of pending, done and given-up nodes of a run.
    ///
    /// # Errors
    /// As [`CdbRead::run`].
    fn progress_summary(&self, run_id: &str) -> Result<ProgressSummary>;

    /// The scanner dynamics stored (schema v5): of one scanner, or of every scanner (by
    /// scanner id), each oldest first (by `identified_unix_s`, then in the order stored).
    ///
    /// # Errors
    /// [`ErrorKind::Corrupt`] for a row that cannot be decoded; database errors.
    fn dynamics(&self, scanner_id: Option<&str>) -> Result<Vec<DynamicsRecord>>;

    /// The dynamics identified for a scanner, oldest first, newest last.
    ///
    /// # Errors
    /// As [`CdbRead::dynamics`].
    fn dynamics_for_scanner(&self, scanner_id: &str) -> Result<Vec<DynamicsRecord>> {
        self.dynamics(Some(scanner_id))
    }

    /// The newest dynamics of a scanner (the last of [`CdbRead::dynamics_for_scanner`]), or
    /// `None` when none was stored.
    ///
    /// # Errors
    /// As [`CdbRead::dynamics`].
    fn latest_dynamics(&self, scanner_id: &str) -> Result<Option<DynamicsRecord>>;

    /// Age dynamics: one coefficient against date, as mean and standard uncertainty per group
    /// (per run, per UTC day, or per node and run), ordered by mean time.
    ///
    /// # Errors
    /// As [`CdbRead::records`].
    fn age_dynamics(
        &self,
        filter: &RecordFilter,
        coefficient: Coefficient,
        grouping: TrendGrouping,
    ) -> Result<Vec<TrendPoint>> {
        query::age_dynamics(
            &mut |each| self.for_each_record(filter, each),
            coefficient,
            grouping,
        )
    }

    /// Writes the selected records as CSV ([`CSV_HEADER`] then one line per record); returns
    /// the number of records.
    ///
    /// # Errors
    /// [`ErrorKind::Io`] if writing fails; as [`CdbRead::records`].
    fn export_csv(&self, filter: &RecordFilter, out: &mut dyn Write) -> Result<u64> {
        export::csv(
            self.path(),
            &mut |each| self.for_each_record(filter, each),
            out,
        )
    }

    /// Writes the selected records as JSON
    /// `{"schema_version": N, "records": [LccRecord, …], "dynamics": [DynamicsRecord, …]}`;
    /// returns the number of records. The dynamics are selected by the filter's scanner,
    /// run and time window (on `identified_unix_s`; the Z plane does not apply to them).
    /// Read through a snapshot for records and dynamics of one committed state.
    ///
    /// # Errors
    /// As [`CdbRead::export_csv`].
    fn export_json(&self, filter: &RecordFilter, out: &mut dyn Write) -> Result<u64> {
        let dynamics =
            export::select_dynamics(self.dynamics(filter.scanner_id.as_deref())?, filter);
        export::json(
            self.path(),
            &mut |each| self.for_each_record(filter, each),
            &dynamics,
            out,
        )
    }

    /// Structural checks of the back end (SQLite: `PRAGMA integrity_check` and
    /// `foreign_key_check`; PostgreSQL: the tables and columns the schema defines) and
    /// semantic checks: finite values, K̄x, K̄y, Kz > 0, |α| < π/2, non-negative uncertainties
    /// and counts, every done plan node has records and no unfinished one has any, records
    /// match their plan node and run's scanner, no duplicate (run, repeat, node, lcs),
    /// given-up nodes have a reason; stored dynamics obey [`DynamicsRecord::check`] (finite
    /// time > 0, the model a JSON object of bounded size), their run exists and is on their
    /// scanner.
    ///
    /// # Errors
    /// Database errors while checking (problems found are in the report, not errors).
    fn check(&self) -> Result<IntegrityReport>;
}

/// `CdbRead` for a type with `fn sqlite(&self) -> &Connection` and a `path` field: the
/// shared queries (`sql::read`) on the SQLite adapter.
macro_rules! sqlite_read {
    ($t:ty) => {
        sql::read::sql_read!(
            $t,
            |s| sql: sql::sqlite::Conn::new(s.sqlite(), &s.path),
            path: &s.path,
            version: s
                .sqlite()
                .pragma_query_value(None, "user_version", |r| r.get(0))
                .map_err(|e| CdbError::sqlite(&s.path, e)),
            check: integrity::check(s.sqlite(), &s.path),
        );
    };
}

sqlite_read!(Cdb);
sqlite_read!(Snapshot<'_>);
sql::write::progress_store!(Cdb);

impl sql::write::SqlStore for Cdb {
    fn write<T>(
        &mut self,
        mut f: impl FnMut(&mut dyn sql::write::SqlTx) -> Result<T>,
    ) -> Result<T> {
        let path = self.path.clone();
        let tx = self.write_tx()?;
        let out = f(&mut sql::sqlite::Conn::new(&tx, &path))?;
        Self::commit(&path, tx)?;
        Ok(out)
    }
}

impl Snapshot<'_> {
    fn sqlite(&self) -> &Connection {
        &self.tx
    }

    /// The SQLite transaction (tests and tools that inspect the file directly).
    #[doc(hidden)]
    #[must_use]
    pub fn connection(&self) -> &Connection {
        &self.tx
    }
}

fn invalid(path: &Path, reason: String) -> CdbError {
    CdbError::InvalidInput {
        path: path.to_path_buf(),
        reason,
    }
}

/// Checks a run's ids before it is stored ([`spm_records::id_problem`]: not blank, no
/// control or format characters).
pub(crate) fn check_run_ids(path: &Path, run: &RunInfo) -> Result<()> {
    for (what, id) in [("run id", &run.run_id), ("scanner id", &run.scanner_id)] {
        if let Some(why) = spm_records::id_problem(id) {
            return Err(invalid(path, format!("{what} {why}")));
        }
    }
    Ok(())
}

fn check_time(path: &Path, what: &str, t: f64) -> Result<()> {
    if t.is_finite() {
        Ok(())
    } else {
        Err(invalid(path, format!("{what} must be finite, got {t}")))
    }
}

/// Checks that a record belongs to the plan node it is committed with: its run, the run's
/// scanner, the visit's repeat and node, and the plan node's coordinates.
pub(crate) fn check_belongs(
    path: &Path,
    run_id: &str,
    scanner_id: &str,
    done: &NodeDone,
    (x, y, z): (i64, i64, i64),
    r: &LccRecord,
) -> Result<()> {
    let matches = r.run_id == run_id
        && r.scanner_id == scanner_id
        && r.repeat_index == done.repeat_index
        && r.node_index == done.node_index
        && (r.node_x_counts, r.node_y_counts, r.node_z_counts) == (x, y, z);
    if matches {
        return Ok(());
    }
    Err(invalid(
        path,
        format!(
            "record (run {:?}, scanner {:?}, repeat {}, node {} at ({}, {}, {})) does not \
             belong to run {run_id:?} (scanner {scanner_id:?}) repeat {} node {} at \
             ({x}, {y}, {z})",
            r.run_id,
            r.scanner_id,
            r.repeat_index,
            r.node_index,
            r.node_x_counts,
            r.node_y_counts,
            r.node_z_counts,
            done.repeat_index,
            done.node_index
        ),
    ))
}

/// Checks a record before it is written ([`LccRecord::check`], the rules every store applies).
fn validate_record(path: &Path, r: &LccRecord) -> Result<()> {
    r.check().map_err(|p| invalid(path, p.to_string()))
}

/// Page cache of 64 MiB (bulk imports keep their index pages in memory) and **no
/// memory-mapped I/O**, on every connection: a mapping of the file turns a file that
/// shrinks under it (a CDB copied over while a reader runs) into SIGBUS, a crash with no
/// message (exit 135, 16 of 24 trials with the 1 GiB map this had, issue 25), where
/// `read()` gives SQLite a short read it reports as an error. The cost, measured in
/// docs/RELIABILITY.md §8, is 2–5 % on the regression's query of 10⁶ records.
fn tune_cache(conn: &Connection) -> rusqlite::Result<()> {
    conn.pragma_update(None, "cache_size", -65_536)?;
    conn.pragma_update_and_check(None, "mmap_size", MMAP_SIZE, |r| r.get::<_, i64>(0))?;
    Ok(())
}

/// `PRAGMA mmap_size` of every connection: 0, no memory-mapped I/O (see `tune_cache`).
pub const MMAP_SIZE: i64 = 0;

/// Creates a new CDB so that no other process ever sees it half made: the schema is
/// written to a hidden sibling file, which is then hard-linked into place (a link never
/// replaces an existing file) and removed. A reader that finds the file finds a complete,
/// empty CDB; a creator that loses a race to another process keeps the other's file.
/// Where the file system has no hard links, the CDB is created in place (the old way: a
/// reader may then briefly see an empty database and is refused with `NotACdb`).
fn create_atomically(path: &Path, options: &OpenOptions) -> Result<()> {
    let file_name = path
        .file_name()
        .map_or_else(|| "cdb".into(), |n| n.to_string_lossy().into_owned());
    let tmp = path.with_file_name(format!(".{file_name}.creating-{}", std::process::id()));
    let remove_tmp = || {
        for suffix in ["", "-wal", "-shm", "-journal"] {
            let mut p = tmp.clone().into_os_string();
            p.push(suffix);
            let _ = std::fs::remove_file(PathBuf::from(p));
        }
    };
    remove_tmp();
    let result = (|| {
        // Errors name the CDB, not the hidden file it is made in.
        let err = |e| CdbError::sqlite(path, e);
        let mut conn = Connection::open_with_flags(
            &tmp,
            OpenFlags::SQLITE_OPEN_READ_WRITE
                | OpenFlags::SQLITE_OPEN_CREATE
                | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(err)?;
        conn.busy_timeout(options.busy_timeout).map_err(err)?;
        let _: String = conn
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))
            .map_err(err)?;
        conn.pragma_update(None, "synchronous", "FULL")
            .map_err(err)?;
        schema::initialise_or_migrate(&mut conn, path)?;
        // Closing the only connection checkpoints the WAL into the file and deletes it.
        conn.close().map_err(|(_, e)| err(e))?;
        match std::fs::hard_link(&tmp, path) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Ok(()),
            Err(e) => {
                tracing::debug!(path = %path.display(), error = %e, "no hard link: creating the CDB in place");
                Ok(())
            }
        }
    })();
    remove_tmp();
    result
}

/// Checks that the folder a new CDB goes into exists (issue 25: a CDB in a missing folder
/// failed with an SQLite error naming the hidden file it is created in, exit 1).
fn check_folder(path: &Path) -> Result<()> {
    let folder = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => return Ok(()),
    };
    match std::fs::metadata(folder) {
        Ok(meta) if meta.is_dir() => Ok(()),
        Ok(_) => Err(CdbError::NotFound {
            path: path.to_path_buf(),
            what: format!("folder {} (it is not a directory)", folder.display()),
        }),
        Err(_) => Err(CdbError::NotFound {
            path: path.to_path_buf(),
            what: format!(
                "folder {} (create it first: a new database is made only in an existing \
                 folder)",
                folder.display()
            ),
        }),
    }
}

/// The hidden creation files (`.NAME.creating-PID` and its `-wal`, `-shm`, `-journal`)
/// that a process killed while creating the CDB at `path` left beside it, and the
/// temporary identity files (`.NAME-identity.tmp-PID`) of a writer killed while writing
/// one, when that process is gone.
fn creation_leftovers(path: &Path) -> Vec<PathBuf> {
    let Some(name) = path.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return Vec::new();
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let prefix = format!(".{name}.creating-");
    // The identity file's temporary (`identity::write_sidecar`) of a killed writer.
    let identity_prefix = format!(".{name}-identity.tmp-");
    let Ok(entries) = std::fs::read_dir(&dir) else {
        return Vec::new();
    };
    let mut found = Vec::new();
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = file_name
            .strip_prefix(&prefix)
            .or_else(|| file_name.strip_prefix(&identity_prefix))
        else {
            continue;
        };
        let pid_text = ["-wal", "-shm", "-journal"]
            .iter()
            .find_map(|s| rest.strip_suffix(s))
            .unwrap_or(rest);
        let Ok(pid) = pid_text.parse::<u32>() else {
            continue;
        };
        if pid != std::process::id() && !process_alive(pid) {
            found.push(entry.path());
        }
    }
    found
}

/// Whether a process with this id exists (Linux: `/proc/PID`; elsewhere assumed alive, so
/// nothing of a live creator is ever removed).
fn process_alive(pid: u32) -> bool {
    let proc_root = Path::new("/proc");
    if proc_root.join("self").exists() {
        proc_root.join(pid.to_string()).exists()
    } else {
        true
    }
}

/// Removes what a killed creator left (see [`creation_leftovers`]); best effort.
fn remove_creation_leftovers(path: &Path) {
    for leftover in creation_leftovers(path) {
        match std::fs::remove_file(&leftover) {
            Ok(()) => {
                tracing::info!(file = %leftover.display(), "removed a leftover of an interrupted CDB creation")
            }
            Err(e) => {
                tracing::debug!(file = %leftover.display(), error = %e, "cannot remove a creation leftover")
            }
        }
    }
}

/// True for the SQLite errors of a read-only open that cannot create the WAL index
/// (`-shm`) because the folder or the mount is read-only.
fn is_read_only_place(error: &rusqlite::Error) -> bool {
    use rusqlite::ErrorCode;
    matches!(
        error.sqlite_error_code(),
        Some(ErrorCode::ReadOnly | ErrorCode::CannotOpen | ErrorCode::PermissionDenied)
    )
}

/// `file:PATH?immutable=1` with the path percent-encoded where SQLite URIs need it.
fn immutable_uri(path: &Path) -> String {
    let absolute = std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf());
    let mut uri = String::from("file:");
    for byte in absolute.to_string_lossy().bytes() {
        match byte {
            b'%' | b'?' | b'#' | 0x80..=0xFF => uri.push_str(&format!("%{byte:02X}")),
            _ => uri.push(char::from(byte)),
        }
    }
    uri.push_str("?immutable=1");
    uri
}

impl Cdb {
    /// Opens (creating if missing) a CDB read-write with default [`OpenOptions`], migrating an
    /// older schema.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`] (file untouched), [`ErrorKind::NotACdb`],
    /// [`ErrorKind::Migration`], [`ErrorKind::Busy`], SQLite errors.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        Self::open_with(path, &OpenOptions::default())
    }

    /// Opens a CDB read-write with the given options.
    ///
    /// # Errors
    /// As [`Cdb::open`]; [`ErrorKind::NotFound`] if the file is missing and
    /// `options.create` is false.
    pub fn open_with(path: impl AsRef<Path>, options: &OpenOptions) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let err = |e| CdbError::sqlite(&path, e);
        remove_creation_leftovers(&path);
        if path.exists() {
            // Look read-only first: a file we refuse must not be written to, not even by
            // switching its journal mode.
            let looked = identity::Looked::before_open(&path);
            let ro = Connection::open_with_flags(
                &path,
                OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
            )
            .map_err(err)?;
            ro.busy_timeout(options.busy_timeout).map_err(err)?;
            let p = schema::probe(&ro).map_err(err)?;
            schema::check_probe(&path, &p)?;
            looked.verify(&path, &ro)?;
            drop(ro);
        } else if !options.create {
            return Err(CdbError::NotFound {
                path: path.clone(),
                what: "database file".into(),
            });
        } else {
            check_folder(&path)?;
            // A new database: an identity file left by a removed one means nothing.
            identity::remove_stale_sidecar(&path);
            create_atomically(&path, options)?;
        }
        let mut conn = Connection::open_with_flags(
            &path,
            OpenFlags::SQLITE_OPEN_READ_WRITE
                | OpenFlags::SQLITE_OPEN_CREATE
                | OpenFlags::SQLITE_OPEN_NO_MUTEX,
        )
        .map_err(err)?;
        conn.busy_timeout(options.busy_timeout).map_err(err)?;
        let mode: String = conn
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))
            .map_err(err)?;
        if !mode.eq_ignore_ascii_case("wal") {
            tracing::warn!(path = %path.display(), mode, "WAL journal not available");
        }
        let sync = match options.synchronous {
            Synchronous::Full => "FULL",
            Synchronous::Normal => "NORMAL",
        };
        conn.pragma_update(None, "synchronous", sync).map_err(err)?;
        conn.pragma_update(None, "foreign_keys", true)
            .map_err(err)?;
        tune_cache(&conn).map_err(err)?;
        schema::initialise_or_migrate(&mut conn, &path)?;
        if let Some(current) = identity::read(&conn).map_err(err)? {
            identity::write_sidecar(&path, &current);
        }
        tracing::debug!(path = %path.display(), "CDB open");
        Ok(Self { conn, path })
    }

    /// Opens an existing CDB read-only (for check, export, trend). Never writes.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`], [`ErrorKind::OutdatedSchema`] (open read-write once to
    /// migrate), [`ErrorKind::NotACdb`] (also for an empty file), SQLite errors.
    pub fn open_read_only(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref().to_path_buf();
        let err = |e| CdbError::sqlite(&path, e);
        if !path.exists() {
            return Err(CdbError::NotFound {
                path: path.clone(),
                what: "database file".into(),
            });
        }
        let looked = identity::Looked::before_open(&path);
        let open = |immutable: bool| -> rusqlite::Result<(Connection, schema::Probe)> {
            let flags = OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX;
            let conn = if immutable {
                Connection::open_with_flags(
                    immutable_uri(&path),
                    flags | OpenFlags::SQLITE_OPEN_URI,
                )?
            } else {
                Connection::open_with_flags(&path, flags)?
            };
            conn.busy_timeout(Duration::from_secs(5))?;
            let p = schema::probe(&conn)?;
            Ok((conn, p))
        };
        let (conn, p) = match open(false) {
            Ok(opened) => opened,
            // A WAL file in a read-only folder or mount: SQLite cannot create the WAL index
            // beside it. Nobody can be writing it there (a writer would have created the
            // index), so it is read as an immutable file.
            Err(e) if is_read_only_place(&e) => {
                tracing::debug!(path = %path.display(), error = %e, "read-only place: opening the CDB as immutable");
                open(true).map_err(err)?
            }
            Err(e) => return Err(err(e)),
        };
        tune_cache(&conn).map_err(err)?;
        schema::check_probe(&path, &p)?;
        // Files that carry an identity (v4 on) are checked first: a v4 file with a foreign
        // log is an identity mismatch before it is an outdated schema.
        if p.user_version >= schema::IDENTITY_VERSION {
            looked.verify(&path, &conn)?;
        }
        if p.user_version == 0 {
            return Err(CdbError::NotACdb {
                path,
                reason: "empty database".into(),
            });
        }
        if p.user_version < SCHEMA_VERSION {
            return Err(CdbError::OutdatedSchema {
                path,
                found: p.user_version,
                supported: SCHEMA_VERSION,
            });
        }
        Ok(Self { conn, path })
    }

    fn sqlite(&self) -> &Connection {
        &self.conn
    }

    /// The SQLite connection (tests and tools that inspect the file directly).
    #[doc(hidden)]
    #[must_use]
    pub fn connection(&self) -> &Connection {
        &self.conn
    }

    /// Starts a read transaction: all queries through the snapshot see one committed state.
    ///
    /// # Errors
    /// SQLite errors.
    pub fn snapshot(&self) -> Result<Snapshot<'_>> {
        let err = |e| CdbError::sqlite(&self.path, e);
        let tx = self.conn.unchecked_transaction().map_err(err)?;
        // A deferred transaction takes its snapshot at the first read.
        tx.query_row("SELECT count(*) FROM runs", [], |r| r.get::<_, i64>(0))
            .map_err(err)?;
        Ok(Snapshot {
            tx,
            path: &self.path,
        })
    }

    /// Commits a write transaction after stepping the identity's generation, then records
    /// the new generation in the identity file (see [`identity`]).
    fn commit(path: &Path, tx: rusqlite::Transaction<'_>) -> Result<()> {
        let err = |e| CdbError::sqlite(path, e);
        let stamp = identity::bump(&tx).map_err(err)?;
        tx.commit().map_err(err)?;
        if let Some(stamp) = stamp {
            identity::write_sidecar(path, &stamp);
        }
        Ok(())
    }

    fn write_tx(&mut self) -> Result<rusqlite::Transaction<'_>> {
        self.conn
            .transaction_with_behavior(TransactionBehavior::Immediate)
            .map_err(|e| CdbError::sqlite(&self.path, e))
    }

    sql::write::write_methods!();

    /// Bulk import: inserts records (of existing runs, outside any plan) in one transaction;
    /// accepts records or references, so a large import can be streamed from a generator.
    /// Returns the number inserted.
    ///
    /// # Errors
    /// [`ErrorKind::InvalidInput`] for an invalid record; [`ErrorKind::Conflict`] for a
    /// duplicate (run, repeat, node, lcs) or a record of an unknown run. Nothing is written on
    /// error.
    pub fn import_records<I>(&mut self, records: I) -> Result<u64>
    where
        I: IntoIterator,
        I::Item: std::borrow::Borrow<LccRecord>,
    {
        let path = self.path.clone();
        let err = |e| CdbError::sqlite(&path, e);
        let tx = self.write_tx()?;
        let mut n = 0;
        {
            // One prepared statement for the whole import (no per-row cache lookup).
            let mut stmt = tx
                .prepare(sql::insert_record(sql::Dialect::Sqlite))
                .map_err(err)?;
            for r in records {
                let r = std::borrow::Borrow::borrow(&r);
                validate_record(&path, r)?;
                sql::sqlite::insert_record(&mut stmt, r).map_err(err)?;
                n += 1;
            }
        }
        Self::commit(&path, tx)?;
        tracing::info!(records = n, "records imported");
        Ok(n)
    }
}

//! The shared calibration database on PostgreSQL (feature `postgres`): the same schema,
//! versions and migrations as the embedded file, for a lab whose instruments calibrate into
//! one database at once.
//!
//! # Schema and versions
//! The SQLite schema with PostgreSQL types (`DOUBLE PRECISION`, `BIGINT`, `TEXT`); the record
//! columns are built from [`spm_records::LCC_RECORD_COLUMNS`]. A `schema_version` table holds
//! one row per applied version (the number, [`crate::APPLICATION_ID`] and what the step did).
//! A new database is created at v1 and brought to the current version by the migrations in
//! one transaction (readers see no schema or all of it); an older database is migrated one
//! transaction per step. Both run under a transaction-scoped advisory lock, so programs
//! opening one database at once do not race. A database of a *newer* schema is refused ([`ErrorKind::NewerSchema`]) after a look
//! that writes nothing.
//!
//! # Transactions and concurrency
//! Every write is one transaction (`READ COMMITTED`). [`PgCdb::commit_node`] locks its plan
//! row (`SELECT … FOR UPDATE`), inserts the node's records and marks the row done: commits of
//! different runs touch different rows and never wait for each other, two programs resuming
//! the same run serialise on the row and the second finds the node done
//! ([`ErrorKind::Conflict`]), and the unique (run, repeat, node, lcs) index makes a duplicate
//! record impossible. Readers never block writers: a [`PgSnapshot`] is a
//! `REPEATABLE READ READ ONLY` transaction.
//!
//! # Connection
//! `postgres://user[:password]@host[:port]/dbname` (or the libpq key-value form), plain TCP or
//! a Unix socket (`?host=/run/postgresql`). Errors name the URL without its password. A URL
//! without a password takes it, as libpq does, from `PGPASSWORD`, else from the password file
//! `PGPASSFILE` or `~/.pgpass` (mode 0600; see `pgpass.rs`).

use std::cell::{Cell, RefCell, RefMut};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, LazyLock};
use std::time::{Duration, Instant};

use postgres::types::{ToSql, Type};
use postgres::{Client, NoTls, Row, Statement};

#[cfg(doc)]
use crate::ErrorKind;
use crate::constraints::{Found, Kind};
use crate::error::{CdbError, Result};
use crate::pg_watchdog::{Cut, Link, Target};
use crate::schema::{APPLICATION_ID, SCHEMA_VERSION};
use crate::sql::checks::{self, Checker};
use crate::sql::{self, Dialect};
use crate::{invalid, validate_record};
use spm_records::{
    ColumnKind, ColumnValue, IntegrityReport, LCC_RECORD_COLUMNS, LccRecord, UNCERTAINTY_COLUMNS,
};

/// True if `location` names a PostgreSQL database (`postgres://` or `postgresql://`) rather
/// than a file.
#[must_use]
pub fn is_postgres_url(location: &str) -> bool {
    let lower = location.trim_start().to_ascii_lowercase();
    lower.starts_with("postgres://") || lower.starts_with("postgresql://")
}

/// The URL for messages, errors and logs, rebuilt from the *parsed* configuration (the
/// same parser the connection uses) without the password: `scheme://user[:***]@host[:port]
/// /dbname`, with `:***` wherever a password was given (in the user info or as a
/// parameter, however spelled or percent-encoded). Only the user, hosts, ports (other than
/// 5432), Unix-socket folder, database and connect timeout are shown; a URL the parser
/// rejects is not shown at all (issue 25: redacting the text itself missed passwords
/// holding `/` or `?`).
#[must_use]
pub fn redact_url(url: &str) -> String {
    let trimmed = url.trim();
    let scheme = if trimmed.to_ascii_lowercase().starts_with("postgresql://") {
        "postgresql"
    } else if trimmed.to_ascii_lowercase().starts_with("postgres://") {
        "postgres"
    } else {
        return url.to_owned();
    };
    // The parser expects the scheme in lower case; spmcal's own parameters are not its.
    let lowered = format!("{scheme}://{}", &trimmed[scheme.len() + 3..]);
    let (lowered, _) = strip_settings(&lowered);
    let Ok(config) = postgres::Config::from_str(&lowered) else {
        return format!("{scheme}://(a malformed URL, not shown)");
    };
    shown_config(scheme, &config)
}

/// `scheme://user[:***]@hosts/dbname[?host=…&connect_timeout=…]` of a parsed configuration.
fn shown_config(scheme: &str, config: &postgres::Config) -> String {
    use postgres::config::Host;
    let mut out = format!("{scheme}://");
    if let Some(user) = config.get_user() {
        out.push_str(&percent_encode(user));
        if config.get_password().is_some() {
            out.push_str(":***");
        }
        out.push('@');
    } else if config.get_password().is_some() {
        out.push_str(":***@");
    }
    let ports = config.get_ports();
    let port_of = |i: usize| ports.get(i).or_else(|| ports.first()).copied();
    let mut tcp = Vec::new();
    let mut sockets = Vec::new();
    for (i, host) in config.get_hosts().iter().enumerate() {
        match host {
            Host::Tcp(name) => {
                let mut h = if name.contains(':') {
                    format!("[{name}]")
                } else {
                    percent_encode(name)
                };
                if let Some(port) = port_of(i).filter(|&p| p != 5432) {
                    h.push_str(&format!(":{port}"));
                }
                tcp.push(h);
            }
            #[cfg(unix)]
            Host::Unix(path) => sockets.push(path.display().to_string()),
        }
    }
    if tcp.is_empty() && sockets.is_empty() {
        tcp = config
            .get_hostaddrs()
            .iter()
            .map(|a| match a {
                std::net::IpAddr::V6(v6) => format!("[{v6}]"),
                std::net::IpAddr::V4(v4) => v4.to_string(),
            })
            .collect();
    }
    out.push_str(&tcp.join(","));
    out.push('/');
    if let Some(db) = config.get_dbname() {
        out.push_str(&percent_encode(db));
    }
    let mut params: Vec<String> = sockets.iter().map(|s| format!("host={s}")).collect();
    if let Some(t) = config.get_connect_timeout() {
        params.push(format!("connect_timeout={}", t.as_secs()));
    }
    if !params.is_empty() {
        out.push('?');
        out.push_str(&params.join("&"));
    }
    out
}

/// Percent-encodes the characters that would make a shown URL ambiguous.
fn percent_encode(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '%' | '@' | ':' | '/' | '?' | '&' | '=' | '#' | ',' | '[' | ']' => {
                out.push_str(&format!("%{:02X}", u32::from(c)));
            }
            c if c.is_control() => {
                let mut buf = [0; 4];
                for b in c.encode_utf8(&mut buf).bytes() {
                    out.push_str(&format!("%{b:02X}"));
                }
            }
            c => out.push(c),
        }
    }
    out
}

/// Versions of the PostgreSQL schema. History as in [`crate::SCHEMA_VERSION`]:
/// - v1: runs, progress, records without standard uncertainties.
/// - v2: records gain the standard uncertainties (NULL = unknown for records migrated from v1).
/// - v3: records gain `kz_x_counts`, `kz_y_counts`, where Kz was measured (NULL = no Kz).
/// - v4: the CDB identity: `cdb_identity` (a random id, a generation) and `runs.cdb_id`
///   (the database's id in every run row; the write-ahead-log checks of the file are the
///   server's business here).
/// - v5: the scanner dynamics: `dynamics` (run, scanner, time, model format and version,
///   the model as a JSON object in text, kept byte for byte), indexed by (scanner, time).
///   The migration only adds the table: runs, progress, records and the identity stay as
///   they are. Like the other writes here, storing dynamics leaves the identity's
///   generation alone (the log is the server's business).
const V1_DESCRIPTION: &str = "runs, progress, records";

/// Record columns added by later versions (absent from the v1 `records` table).
const ADDED_AFTER_V1: [&str; 6] = [
    UNCERTAINTY_COLUMNS[0],
    UNCERTAINTY_COLUMNS[1],
    UNCERTAINTY_COLUMNS[2],
    UNCERTAINTY_COLUMNS[3],
    "kz_x_counts",
    "kz_y_counts",
];

/// Migration steps: `MIGRATIONS[k]` takes version k+1 to k+2 (description, SQL).
const MIGRATIONS: &[(&str, &str)] = &[
    (
        "standard uncertainties",
        "ALTER TABLE records ADD COLUMN u_kx_nm_per_count DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_ky_nm_per_count DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_alpha_rad DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN u_kz_nm_per_count DOUBLE PRECISION;",
    ),
    (
        "where Kz was measured",
        "ALTER TABLE records ADD COLUMN kz_x_counts DOUBLE PRECISION;
     ALTER TABLE records ADD COLUMN kz_y_counts DOUBLE PRECISION;",
    ),
    (
        "the CDB identity",
        "CREATE TABLE cdb_identity (id TEXT NOT NULL, generation BIGINT NOT NULL);
     INSERT INTO cdb_identity (id, generation)
         VALUES (md5(random()::TEXT || clock_timestamp()::TEXT), 1);
     ALTER TABLE runs ADD COLUMN cdb_id TEXT;
     UPDATE runs SET cdb_id = (SELECT id FROM cdb_identity);",
    ),
    (
        "the scanner dynamics",
        "CREATE TABLE dynamics (
         id                BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
         run_id            TEXT NOT NULL REFERENCES runs (run_id),
         scanner_id        TEXT NOT NULL CONSTRAINT dynamics_scanner_id_text
                               CHECK (btrim(scanner_id) <> ''),
         identified_unix_s DOUBLE PRECISION NOT NULL CONSTRAINT dynamics_time_finite
                               CHECK (identified_unix_s > 0
                                      AND identified_unix_s < 'Infinity'::float8),
         model_format      TEXT NOT NULL CONSTRAINT dynamics_model_format_text
                               CHECK (btrim(model_format) <> ''),
         model_version     BIGINT NOT NULL CONSTRAINT dynamics_model_version_range
                               CHECK (model_version BETWEEN 1 AND 4294967295),
         model_json        TEXT NOT NULL CONSTRAINT dynamics_model_json_object
                               CHECK (json_typeof(model_json::json) = 'object')
     );
     CREATE INDEX dynamics_scanner ON dynamics (scanner_id, identified_unix_s);",
    ),
];

/// The v1 schema: `runs`, `progress`, and `records` with the columns of
/// [`LCC_RECORD_COLUMNS`] that v1 had.
static SCHEMA_V1: LazyLock<String> = LazyLock::new(|| {
    let record_columns: Vec<String> = LCC_RECORD_COLUMNS
        .iter()
        .filter(|c| !ADDED_AFTER_V1.contains(&c.name))
        .map(|c| {
            let extra = match c.name {
                "run_id" => " REFERENCES runs (run_id)",
                "lcs_index" => " DEFAULT 0",
                _ => "",
            };
            format!(
                "    {} {}{extra}",
                c.name,
                Dialect::Postgres.column_type(c.kind)
            )
        })
        .collect();
    format!(
        "CREATE TABLE schema_version (
    version        BIGINT PRIMARY KEY,
    application_id BIGINT NOT NULL,
    description    TEXT NOT NULL
);
CREATE TABLE runs (
    run_id          TEXT PRIMARY KEY,
    scanner_id      TEXT NOT NULL,
    config          TEXT NOT NULL,
    started_unix_s  DOUBLE PRECISION NOT NULL,
    finished_unix_s DOUBLE PRECISION,
    status          TEXT NOT NULL CHECK (status IN ('running', 'finished', 'failed', 'aborted'))
);
CREATE INDEX runs_scanner ON runs (scanner_id, started_unix_s);
CREATE TABLE progress (
    run_id         TEXT NOT NULL REFERENCES runs (run_id),
    repeat_index   BIGINT NOT NULL,
    node_index     BIGINT NOT NULL,
    node_x_counts  BIGINT NOT NULL,
    node_y_counts  BIGINT NOT NULL,
    node_z_counts  BIGINT NOT NULL,
    state          TEXT NOT NULL CHECK (state IN ('pending', 'done', 'given_up')),
    reason         TEXT,
    attempts       BIGINT NOT NULL DEFAULT 0,
    updated_unix_s DOUBLE PRECISION,
    PRIMARY KEY (run_id, repeat_index, node_index)
);
CREATE TABLE records (
    id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY,
{}
);
CREATE UNIQUE INDEX records_node ON records (run_id, repeat_index, node_index, lcs_index);
CREATE INDEX records_plane ON records (scanner_id, node_z_counts, acquired_unix_s);
",
        record_columns.join(",\n")
    )
});

/// A record value bound as a statement parameter.
#[derive(Debug)]
pub(crate) struct Bind<'a>(ColumnValue<'a>);

impl ToSql for Bind<'_> {
    fn to_sql(
        &self,
        ty: &Type,
        out: &mut postgres::types::private::BytesMut,
    ) -> std::result::Result<postgres::types::IsNull, Box<dyn std::error::Error + Sync + Send>>
    {
        match self.0 {
            ColumnValue::Text(t) => t.to_sql(ty, out),
            ColumnValue::Real(v) => v.to_sql(ty, out),
            ColumnValue::OptionalReal(v) => v.to_sql(ty, out),
            ColumnValue::Integer(v) => v.to_sql(ty, out),
        }
    }
    fn accepts(ty: &Type) -> bool {
        <&str as ToSql>::accepts(ty) || <f64 as ToSql>::accepts(ty) || <i64 as ToSql>::accepts(ty)
    }
    postgres::types::to_sql_checked!();
}

pub(crate) fn binds(r: &LccRecord) -> [Bind<'_>; LCC_RECORD_COLUMNS.len()] {
    r.column_values().map(Bind)
}

pub(crate) fn bind_refs<'a>(
    values: &'a [Bind<'a>; LCC_RECORD_COLUMNS.len()],
) -> Vec<&'a (dyn ToSql + Sync)> {
    values.iter().map(|b| b as &(dyn ToSql + Sync)).collect()
}

/// The PostgreSQL type of a column kind (for binary COPY).
fn copy_type(kind: ColumnKind) -> Type {
    match kind {
        ColumnKind::Text => Type::TEXT,
        ColumnKind::Real | ColumnKind::OptionalReal => Type::FLOAT8,
        ColumnKind::Integer => Type::INT8,
    }
}

/// What a look at a database found.
struct Probe {
    version: i64,
    application_ids: Vec<i64>,
    cdb_tables: i64,
}

fn probe(client: &mut impl postgres::GenericClient, path: &Path) -> Result<Probe> {
    let err = |e| CdbError::postgres(path, e);
    let row = client
        .query_one(
            "SELECT to_regclass('schema_version') IS NOT NULL, \
             (SELECT count(*) FROM pg_catalog.pg_tables WHERE schemaname = current_schema() \
              AND tablename IN ('runs', 'progress', 'records'))",
            &[],
        )
        .map_err(err)?;
    let has_version: bool = row.try_get(0).map_err(err)?;
    let cdb_tables: i64 = row.try_get(1).map_err(err)?;
    if !has_version {
        return Ok(Probe {
            version: 0,
            application_ids: Vec::new(),
            cdb_tables,
        });
    }
    let rows = client
        .query(
            "SELECT coalesce(max(version), 0), array_agg(DISTINCT application_id) \
             FROM schema_version",
            &[],
        )
        .map_err(err)?;
    let (version, application_ids) = match rows.first() {
        Some(r) => (
            r.try_get::<_, i64>(0).map_err(err)?,
            r.try_get::<_, Option<Vec<i64>>>(1)
                .map_err(err)?
                .unwrap_or_default(),
        ),
        None => (0, Vec::new()),
    };
    Ok(Probe {
        version,
        application_ids,
        cdb_tables,
    })
}

fn check_probe(path: &Path, p: &Probe) -> Result<()> {
    if let Some(other) = p.application_ids.iter().find(|&&a| a != APPLICATION_ID) {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("schema_version has application_id {other:#x}"),
        });
    }
    crate::schema::check_version(
        path,
        p.version,
        p.cdb_tables > 0,
        "tables runs/progress/records present but no schema_version",
    )
}

/// Creates the schema in an empty database or migrates an older one up to `target`, one
/// transaction per step, each under the advisory lock keyed by [`APPLICATION_ID`].
fn initialise_or_migrate(client: &mut Client, path: &Path, target: i64) -> Result<()> {
    loop {
        let err = |e| CdbError::postgres(path, e);
        let mut tx = client.transaction().map_err(err)?;
        tx.execute("SELECT pg_advisory_xact_lock($1)", &[&APPLICATION_ID])
            .map_err(err)?;
        // Re-read under the lock: another program may have migrated meanwhile.
        let p = probe(&mut tx, path)?;
        check_probe(path, &p)?;
        let version = p.version;
        if version >= target {
            return Ok(());
        }
        let step = |e| CdbError::postgres(path, e);
        if version == 0 {
            // A new database is made at v1 and brought to the target by the migrations, all
            // in this one transaction: other programs see no schema or the whole of it.
            tracing::info!(path = %path.display(), version = target, "creating CDB schema");
            tx.batch_execute(&SCHEMA_V1).map_err(step)?;
            tx.execute(
                "INSERT INTO schema_version (version, application_id, description) \
                 VALUES (1, $1, $2)",
                &[&APPLICATION_ID, &V1_DESCRIPTION],
            )
            .map_err(step)?;
            for v in 1..target {
                migrate_step(&mut tx, path, v)?;
            }
        } else {
            tracing::info!(path = %path.display(), from = version, to = version + 1, "migrating CDB");
            migrate_step(&mut tx, path, version)?;
        }
        tx.commit().map_err(step)?;
    }
}

/// Applies the migration from `version` to `version + 1` inside `tx` and records it.
fn migrate_step(tx: &mut postgres::Transaction<'_>, path: &Path, version: i64) -> Result<()> {
    let step = |e| CdbError::postgres(path, e);
    let Some((description, sql)) = usize::try_from(version - 1)
        .ok()
        .and_then(|k| MIGRATIONS.get(k))
    else {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("no migration from schema version {version}"),
        });
    };
    tx.batch_execute(sql).map_err(step)?;
    tx.execute(
        "INSERT INTO schema_version (version, application_id, description) \
         VALUES ($1, $2, $3)",
        &[&(version + 1), &APPLICATION_ID, description],
    )
    .map_err(step)?;
    Ok(())
}

/// An open shared calibration database on PostgreSQL.
///
/// # Lost connections and silent servers
/// A connection that is lost (closed or reset, the server shut down or restarted: SQLSTATE
/// class 08, 57P01, 57P02, 57P03) is opened again, up to [`PgSettings::reconnect_attempts`]
/// times per operation with pauses from [`PgSettings::reconnect_backoff_s`] doubling up to
/// [`MAX_RECONNECT_BACKOFF_S`], and the operation is done again:
/// - a write transaction from its start (nothing of an interrupted transaction is ever
///   committed); when the connection was lost while its `COMMIT` was under way, the server
///   is asked first whether that transaction committed (`txid_status`), and a committed one
///   is not done twice;
/// - a read when none of its rows had been handed on yet, outside a [`PgSnapshot`] (a
///   snapshot's consistent view cannot be carried over to a new connection: its reads fail).
///
/// Every statement runs under a client-side watchdog ([`PgSettings::reply_timeout_s`]): a
/// server that stays silent that long while the client waits (a stopped backend, which
/// neither keepalive nor the server's own timeouts would notice) fails the call as
/// [`CdbError::Unanswered`], not retried. With a stop flag ([`PgCdb::set_interrupt`]), a
/// reconnect loop ends before its next attempt or within [`RECONNECT_POLL_S`] of a pause, and
/// a wait for a silent server within 1 s (the watchdog's `STOP_GRACE_S`), as
/// [`ErrorKind::Interrupted`].
pub struct PgCdb {
    // The client before its link: dropped first, its goodbye still reaches the server.
    // Boxed: the client (its runtime) is large, and an enum holding a PgCdb or a Cdb stays
    // small.
    client: RefCell<Box<Client>>,
    link: RefCell<Link>,
    /// The URL the client connects with (spmcal's parameters split off); it may hold the
    /// password and is never shown.
    url: String,
    read_only: bool,
    settings: PgSettings,
    stop: Option<Arc<AtomicBool>>,
    in_snapshot: Cell<bool>,
    reconnects: Cell<u64>,
    path: PathBuf,
    insert: RefCell<Option<Statement>>,
}

impl std::fmt::Debug for PgCdb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PgCdb").field("url", &self.path).finish()
    }
}

/// A read transaction (`REPEATABLE READ READ ONLY`) on a [`PgCdb`]: every query through it
/// sees the same committed state. Ends when dropped. A connection lost under it fails its
/// reads (they are not retried on a new connection, whose view would differ).
#[derive(Debug)]
pub struct PgSnapshot<'c> {
    db: &'c PgCdb,
}

impl Drop for PgSnapshot<'_> {
    fn drop(&mut self) {
        self.db.in_snapshot.set(false);
        if let Ok(mut client) = self.db.client.try_borrow_mut()
            && !client.is_closed()
            && let Err(e) = client.batch_execute("COMMIT")
        {
            tracing::debug!(error = %e, "ending a PostgreSQL snapshot");
        }
    }
}

/// How long a connection may take, TCP connect and start-up together, when the URL gives no
/// `connect_timeout` (libpq's parameter, seconds).
pub const DEFAULT_CONNECT_TIMEOUT_S: u64 = 10;
/// `lock_timeout` of every session, ms: a table lock held by another session fails the
/// statement after this, instead of waiting without end. A URL's `options=-c lock_timeout=…`
/// overrides it.
pub const DEFAULT_LOCK_TIMEOUT_MS: u64 = 30_000;
/// `statement_timeout` of every session, ms (the longest statement spmcal sends, an export
/// of a large CDB, takes seconds). A URL's `options=-c statement_timeout=…` overrides it.
pub const DEFAULT_STATEMENT_TIMEOUT_MS: u64 = 600_000;

/// Reconnect attempts after a lost connection, per operation, when the URL gives no
/// `spmcal_reconnect_attempts`.
pub const DEFAULT_RECONNECT_ATTEMPTS: u32 = 10;
/// Most reconnect attempts a URL may ask for (as the Nanonis client's): with pauses of at
/// most [`MAX_RECONNECT_BACKOFF_S`], a server gone for good is given up within
/// [`MAX_RECONNECT_BACKOFF_TOTAL_S`] of pauses (plus the attempts' own connect timeouts).
pub const MAX_RECONNECT_ATTEMPTS: u32 = 100;
/// First pause between reconnect attempts, s, when the URL gives no
/// `spmcal_reconnect_backoff_s` (pauses double up to [`MAX_RECONNECT_BACKOFF_S`]).
pub const DEFAULT_RECONNECT_BACKOFF_S: f64 = 0.5;
/// Longest pause between two reconnect attempts, s (also the largest first pause).
pub const MAX_RECONNECT_BACKOFF_S: f64 = 2.0;
/// The pauses of one reconnect loop add up to at most this, s.
pub const MAX_RECONNECT_BACKOFF_TOTAL_S: f64 =
    MAX_RECONNECT_ATTEMPTS as f64 * MAX_RECONNECT_BACKOFF_S;
/// With a stop flag, the longest slice of a reconnect pause before the flag is looked at
/// again, s.
pub const RECONNECT_POLL_S: f64 = 0.1;
/// How long the server may stay silent while the client waits for its reply, s, when the
/// URL gives no `spmcal_reply_timeout_s` (the client-side watchdog; the longest silent
/// statement spmcal sends, an integrity check of 10⁶ records, takes seconds; a lock wait
/// ends at [`DEFAULT_LOCK_TIMEOUT_MS`]).
pub const DEFAULT_REPLY_TIMEOUT_S: f64 = 120.0;
/// The range a URL's `spmcal_reply_timeout_s` must be in, s.
pub const REPLY_TIMEOUT_RANGE_S: (f64, f64) = (0.1, 86_400.0);

/// spmcal's own settings of a PostgreSQL connection, given as URL parameters beside libpq's
/// (`postgres://…/db?spmcal_reconnect_attempts=20&spmcal_reply_timeout_s=300`) and split
/// off before the URL reaches the client.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PgSettings {
    /// `spmcal_reconnect_attempts`: reconnects after a lost connection, per operation
    /// (0 … [`MAX_RECONNECT_ATTEMPTS`]; 0: none, the operation fails).
    pub reconnect_attempts: u32,
    /// `spmcal_reconnect_backoff_s`: the first pause between reconnect attempts, s
    /// ((0, [`MAX_RECONNECT_BACKOFF_S`]]; the first reconnect is at once, later pauses
    /// double up to [`MAX_RECONNECT_BACKOFF_S`]).
    pub reconnect_backoff_s: f64,
    /// `spmcal_reply_timeout_s`: how long the server may stay silent while the client waits
    /// for it, s ([`REPLY_TIMEOUT_RANGE_S`]).
    pub reply_timeout_s: f64,
}

impl Default for PgSettings {
    fn default() -> Self {
        Self {
            reconnect_attempts: DEFAULT_RECONNECT_ATTEMPTS,
            reconnect_backoff_s: DEFAULT_RECONNECT_BACKOFF_S,
            reply_timeout_s: DEFAULT_REPLY_TIMEOUT_S,
        }
    }
}

const SETTING_PREFIX: &str = "spmcal_";

/// The URL without spmcal's parameters, and those parameters as `(name, value)`.
fn strip_settings(url: &str) -> (String, Vec<(String, String)>) {
    let Some((base, query)) = url.split_once('?') else {
        return (url.to_owned(), Vec::new());
    };
    let mut kept = Vec::new();
    let mut ours = Vec::new();
    for part in query.split('&') {
        match part.split_once('=') {
            Some((k, v)) if k.starts_with(SETTING_PREFIX) => {
                ours.push((k.to_owned(), v.to_owned()))
            }
            None if part.starts_with(SETTING_PREFIX) => ours.push((part.to_owned(), String::new())),
            _ => kept.push(part),
        }
    }
    if ours.is_empty() {
        return (url.to_owned(), ours);
    }
    let url = if kept.is_empty() {
        base.to_owned()
    } else {
        format!("{base}?{}", kept.join("&"))
    };
    (url, ours)
}

/// Splits spmcal's parameters off a PostgreSQL URL and checks them: the URL for the client
/// and the settings (defaults for those not given).
///
/// # Errors
/// A message naming the parameter, its value and its range, for an unknown `spmcal_…`
/// parameter or a value out of range.
pub fn split_url(url: &str) -> std::result::Result<(String, PgSettings), String> {
    let (client_url, pairs) = strip_settings(url.trim());
    let mut s = PgSettings::default();
    for (name, value) in pairs {
        let bad = |range: &str| format!("the PostgreSQL URL's {name} = {value:?} must be {range}");
        match name.as_str() {
            "spmcal_reconnect_attempts" => {
                s.reconnect_attempts = value
                    .parse::<u32>()
                    .ok()
                    .filter(|&n| n <= MAX_RECONNECT_ATTEMPTS)
                    .ok_or_else(|| {
                        bad(&format!("a whole number from 0 to {MAX_RECONNECT_ATTEMPTS} (a server gone for good would be retried for hours)"))
                    })?;
            }
            "spmcal_reconnect_backoff_s" => {
                s.reconnect_backoff_s = value
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v > 0.0 && *v <= MAX_RECONNECT_BACKOFF_S)
                    .ok_or_else(|| {
                        bad(&format!(
                            "a number of seconds in (0, {MAX_RECONNECT_BACKOFF_S}]"
                        ))
                    })?;
            }
            "spmcal_reply_timeout_s" => {
                let (lo, hi) = REPLY_TIMEOUT_RANGE_S;
                s.reply_timeout_s = value
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v >= lo && *v <= hi)
                    .ok_or_else(|| bad(&format!("a number of seconds in [{lo}, {hi}]")))?;
            }
            _ => {
                return Err(format!(
                    "the PostgreSQL URL's parameter {name} is not spmcal's: known are \
                     spmcal_reconnect_attempts, spmcal_reconnect_backoff_s, \
                     spmcal_reply_timeout_s"
                ));
            }
        }
    }
    Ok((client_url, s))
}

/// A connection: the client and the relay its bytes go through (the watchdog).
struct Connection {
    client: Client,
    link: Link,
}

/// Where the configuration's hosts are, in the client's order.
fn targets(config: &postgres::Config) -> Vec<Target> {
    use postgres::config::Host;
    let ports = config.get_ports();
    let port_of = |i: usize| {
        ports
            .get(i)
            .or_else(|| ports.first())
            .copied()
            .unwrap_or(5432)
    };
    let hosts = config.get_hosts();
    let addrs = config.get_hostaddrs();
    (0..hosts.len().max(addrs.len()))
        .filter_map(|i| {
            let port = port_of(i);
            if let Some(ip) = addrs.get(i) {
                return Some(Target::Addr(*ip, port));
            }
            match hosts.get(i)? {
                Host::Tcp(name) => Some(Target::Tcp(name.clone(), port)),
                #[cfg(unix)]
                Host::Unix(dir) => Some(Target::Socket(dir.join(format!(".s.PGSQL.{port}")))),
            }
        })
        .collect()
}

/// The client's configuration, pointed at the relay's loopback port.
fn relayed(config: &postgres::Config, port: u16, timeout: Duration) -> postgres::Config {
    let mut c = postgres::Config::new();
    if let Some(user) = config.get_user() {
        c.user(user);
    }
    if let Some(password) = config.get_password() {
        c.password(password);
    }
    if let Some(db) = config.get_dbname() {
        c.dbname(db);
    }
    if let Some(options) = config.get_options() {
        c.options(options);
    }
    if let Some(name) = config.get_application_name() {
        c.application_name(name);
    }
    c.ssl_mode(config.get_ssl_mode());
    c.channel_binding(config.get_channel_binding());
    c.target_session_attrs(config.get_target_session_attrs());
    c.host("127.0.0.1");
    c.port(port);
    c.connect_timeout(timeout);
    c
}

fn stopped(stop: Option<&Arc<AtomicBool>>) -> bool {
    stop.is_some_and(|s| s.load(Ordering::SeqCst))
}

fn connect(
    url: &str,
    path: &Path,
    read_only: bool,
    settings: &PgSettings,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<Connection> {
    let mut config =
        postgres::Config::from_str(url.trim()).map_err(|e| CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: format!(
                "not a PostgreSQL URL: {}",
                crate::error::postgres_message(&e)
            ),
        })?;
    check_config(path, &config)?;
    crate::pgpass::fill_in(&mut config);
    config.application_name("spmcal");
    // Session timeouts first, so that the URL's own `options` (later) override them.
    let mut options = format!(
        "-c lock_timeout={DEFAULT_LOCK_TIMEOUT_MS} -c statement_timeout={DEFAULT_STATEMENT_TIMEOUT_MS}"
    );
    if let Some(own) = config.get_options() {
        options.push(' ');
        options.push_str(own);
    }
    if read_only {
        options.push_str(" -c default_transaction_read_only=on");
    }
    config.options(&options);
    let timeout = config
        .get_connect_timeout()
        .copied()
        .unwrap_or(Duration::from_secs(DEFAULT_CONNECT_TIMEOUT_S));
    // The bytes go through a relay whose watchdog cuts a wait for a silent server
    // (`pg_watchdog`); the relay connects to the server first.
    let link = Link::open(
        &targets(&config),
        timeout,
        Duration::from_secs_f64(settings.reply_timeout_s),
    )
    .map_err(|e| CdbError::Unreachable {
        path: path.to_path_buf(),
        attempts: 0,
        last: format!("cannot connect to the server: {e}"),
    })?;
    if let Some(stop) = stop {
        link.set_stop(Arc::clone(stop));
    }
    let relayed = relayed(&config, link.port(), timeout);
    // The client's connect timeout covers the TCP connect only: a server that accepts and
    // never answers would hold the start-up for ever. The whole connect runs on a thread
    // that is given up after the timeout (the link is dropped then, which ends it).
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("postgres-connect".to_owned())
        .spawn(move || {
            let _ = sender.send(relayed.connect(NoTls));
        })
        .map_err(|e| CdbError::Io {
            path: path.to_path_buf(),
            context: "starting the connection thread".to_owned(),
            source: e,
        })?;
    let deadline = Instant::now() + timeout + Duration::from_millis(500);
    let mut client = loop {
        let slice = deadline
            .saturating_duration_since(Instant::now())
            .min(Duration::from_secs_f64(RECONNECT_POLL_S));
        match receiver.recv_timeout(slice) {
            Ok(connected) => break connected.map_err(|e| CdbError::postgres(path, e))?,
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) if Instant::now() < deadline => {
                if stopped(stop) {
                    return Err(CdbError::Interrupted {
                        path: path.to_path_buf(),
                        what: "connecting",
                    });
                }
            }
            Err(_) => {
                return Err(CdbError::Unanswered {
                    path: path.to_path_buf(),
                    what: "connecting",
                    timeout_s: timeout.as_secs_f64(),
                });
            }
        }
    };
    pin_schema(&mut client, path)?;
    Ok(Connection { client, link })
}

/// True for a client error that means the connection is gone (closed or reset, the server
/// shut down or restarting: SQLSTATE class 08, 57P01, 57P02, 57P03), after which the
/// operation may be done again on a new connection.
fn is_lost(error: &CdbError) -> bool {
    let CdbError::Postgres { source, .. } = error else {
        return false;
    };
    if source.is_closed() {
        return true;
    }
    if let Some(code) = source.code() {
        let code = code.code();
        return code.starts_with("08") || matches!(code, "57P01" | "57P02" | "57P03");
    }
    std::error::Error::source(source).is_some_and(|c| c.is::<std::io::Error>())
}

/// Reconnects made by one operation, and its next pause.
struct Budget {
    used: u32,
    backoff_s: f64,
}

/// Resolves the one schema the CDB lives in and pins the session's `search_path` to it, so
/// that every query and every catalogue lookup (the probe's table count, the check's
/// column list, both filtered on `current_schema()`) mean the same tables (issue 25: an
/// account with its own schema on its `search_path` had its lookups filtered on its own,
/// empty schema while the queries found the CDB in `public`). The schema is the one where
/// `schema_version` resolves through the account's `search_path`, else the first existing
/// schema of that path (where a new CDB is created).
fn pin_schema(client: &mut Client, path: &Path) -> Result<()> {
    let err = |e| CdbError::postgres(path, e);
    let row = client
        .query_one(
            "SELECT coalesce((SELECT n.nspname::TEXT FROM pg_catalog.pg_class c \
             JOIN pg_catalog.pg_namespace n ON n.oid = c.relnamespace \
             WHERE c.oid = to_regclass('schema_version')), current_schema()::TEXT)",
            &[],
        )
        .map_err(err)?;
    let schema: Option<String> = row.try_get(0).map_err(err)?;
    let Some(schema) = schema else {
        return Err(CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: "no schema of the account's search_path exists: create one or set \
                     search_path"
                .into(),
        });
    };
    client
        .execute(
            "SELECT pg_catalog.set_config('search_path', pg_catalog.quote_ident($1), false)",
            &[&schema],
        )
        .map_err(err)?;
    tracing::debug!(url = %path.display(), schema, "CDB schema resolved");
    Ok(())
}

/// The checks the client makes when connecting, made first so that a URL without a host
/// or user is bad input (exit 2) naming what is missing, not a connection failure
/// ("invalid configuration", issue 25). (A missing user or database is the server's
/// default, as with libpq.)
fn check_config(path: &Path, config: &postgres::Config) -> Result<()> {
    let bad = |reason: &str| {
        Err(CdbError::InvalidInput {
            path: path.to_path_buf(),
            reason: format!("the PostgreSQL URL {reason}"),
        })
    };
    let hosts = config.get_hosts().len().max(config.get_hostaddrs().len());
    if hosts == 0 {
        return bad("names no host: give postgres://user@host[:port]/database");
    }
    if !config.get_hosts().is_empty()
        && !config.get_hostaddrs().is_empty()
        && config.get_hosts().len() != config.get_hostaddrs().len()
    {
        return bad("names a different number of hosts and hostaddrs");
    }
    if config.get_ports().len() > 1 && config.get_ports().len() != hosts {
        return bad("names a different number of ports and hosts");
    }
    Ok(())
}

impl PgCdb {
    /// Connects read-write, creating the schema in an empty database and migrating an older
    /// one. spmcal's own settings ([`PgSettings`]) come from the URL's `spmcal_…`
    /// parameters.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`] (nothing written), [`ErrorKind::NotACdb`],
    /// [`ErrorKind::Migration`], [`ErrorKind::InvalidInput`] for a malformed URL or a
    /// setting out of range (naming it), [`ErrorKind::Postgres`] when the server cannot be
    /// reached.
    pub fn open(url: &str) -> Result<Self> {
        Self::open_at_version(url, SCHEMA_VERSION)
    }

    /// [`PgCdb::open`], creating or migrating only up to `version` (tests of the migrations).
    #[doc(hidden)]
    pub fn open_at_version(url: &str, version: i64) -> Result<Self> {
        let mut db = Self::connect_to(url, false)?;
        let path = db.path.clone();
        let client = &mut **db.client.get_mut();
        // Look first without the lock: a refused database must not be touched.
        let p = probe(client, &path)?;
        check_probe(&path, &p)?;
        initialise_or_migrate(client, &path, version)?;
        tracing::debug!(url = %path.display(), "CDB open");
        Ok(db)
    }

    fn connect_to(url: &str, read_only: bool) -> Result<Self> {
        let path = PathBuf::from(redact_url(url));
        let (client_url, settings) = split_url(url).map_err(|reason| CdbError::InvalidInput {
            path: path.clone(),
            reason,
        })?;
        let connection = connect(&client_url, &path, read_only, &settings, None)?;
        Ok(Self {
            client: RefCell::new(Box::new(connection.client)),
            link: RefCell::new(connection.link),
            url: client_url,
            read_only,
            settings,
            stop: None,
            in_snapshot: Cell::new(false),
            reconnects: Cell::new(0),
            path,
            insert: RefCell::new(None),
        })
    }

    /// Connects read-only (every transaction `READ ONLY`) to an existing CDB (for check,
    /// export, trend, fit). Never writes.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`], [`ErrorKind::OutdatedSchema`] (open read-write once to
    /// migrate), [`ErrorKind::NotACdb`] (also for a database without the schema), as
    /// [`PgCdb::open`].
    pub fn open_read_only(url: &str) -> Result<Self> {
        let mut db = Self::connect_to(url, true)?;
        let path = db.path.clone();
        let p = probe(&mut **db.client.get_mut(), &path)?;
        check_probe(&path, &p)?;
        if p.version == 0 {
            return Err(CdbError::NotACdb {
                path,
                reason: "no CDB schema in this database".into(),
            });
        }
        if p.version < SCHEMA_VERSION {
            return Err(CdbError::OutdatedSchema {
                path,
                found: p.version,
                supported: SCHEMA_VERSION,
            });
        }
        Ok(db)
    }

    /// The settings from the URL (or their defaults).
    #[must_use]
    pub fn settings(&self) -> PgSettings {
        self.settings
    }

    /// How many times the connection was opened again after being lost.
    #[must_use]
    pub fn reconnects(&self) -> u64 {
        self.reconnects.get()
    }

    /// The run's stop flag: once it is set, no reconnect is started, a reconnect pause ends
    /// within [`RECONNECT_POLL_S`], and a wait for a silent server is cut within 1 s (the
    /// watchdog's `STOP_GRACE_S`); the operation then fails as [`ErrorKind::Interrupted`] (a
    /// transaction cut so is not committed).
    pub fn set_interrupt(&mut self, stop: Arc<AtomicBool>) {
        self.link.get_mut().set_stop(Arc::clone(&stop));
        self.stop = Some(stop);
    }

    /// The process id of the server's backend serving this connection (tests that stop or
    /// end it).
    ///
    /// # Errors
    /// PostgreSQL errors.
    #[doc(hidden)]
    pub fn backend_pid(&self) -> Result<i32> {
        let rows = self.query_rows("SELECT pg_backend_pid()", &[])?;
        rows.first()
            .map(|r| r.try_get(0))
            .transpose()
            .map_err(self.err())?
            .ok_or_else(|| invalid(&self.path, "no backend pid".into()))
    }

    /// Tests: the server's reply to the next `COMMIT` is dropped and the connection cut, as
    /// when it is lost after the server committed but before the client heard.
    #[doc(hidden)]
    pub fn lose_next_commit_reply(&self) {
        self.link.borrow().lose_next_commit_reply();
    }

    /// The client, for reads through `&self` (one query at a time).
    pub(crate) fn client(&self) -> Result<RefMut<'_, Client>> {
        self.client
            .try_borrow_mut()
            .map(|c| RefMut::map(c, |c| &mut **c))
            .map_err(|_| {
                invalid(
                    &self.path,
                    "a query was started from inside another query's callback".into(),
                )
            })
    }

    fn err(&self) -> impl Fn(postgres::Error) -> CdbError + '_ {
        |e| CdbError::postgres(&self.path, e)
    }

    /// A failure of the current connection in the watchdog's words when it cut it.
    fn explain(&self, error: CdbError) -> CdbError {
        if !matches!(error, CdbError::Postgres { .. }) {
            return error;
        }
        let Ok(link) = self.link.try_borrow() else {
            return error;
        };
        match link.cut() {
            Some(Cut::Unanswered) => CdbError::Unanswered {
                path: self.path.clone(),
                what: "a statement",
                timeout_s: link.reply_timeout().as_secs_f64(),
            },
            Some(Cut::Interrupted) => CdbError::Interrupted {
                path: self.path.clone(),
                what: "waiting for the PostgreSQL server",
            },
            Some(Cut::LostCommitReply) | None => error,
        }
    }

    fn budget(&self) -> Budget {
        Budget {
            used: 0,
            backoff_s: self.settings.reconnect_backoff_s,
        }
    }

    fn interrupted(&self, what: &'static str) -> CdbError {
        CdbError::Interrupted {
            path: self.path.clone(),
            what,
        }
    }

    /// Opens the connection again after `cause`, within the operation's `budget` of
    /// attempts, pausing between them; the stop flag ends the loop.
    fn reconnect(&self, budget: &mut Budget, cause: &CdbError) -> Result<()> {
        let mut last = cause.to_string();
        loop {
            if stopped(self.stop.as_ref()) {
                return Err(self.interrupted("reconnecting"));
            }
            if budget.used >= self.settings.reconnect_attempts {
                return Err(CdbError::Unreachable {
                    path: self.path.clone(),
                    attempts: budget.used,
                    last,
                });
            }
            if budget.used > 0 {
                let until = Instant::now() + Duration::from_secs_f64(budget.backoff_s);
                while Instant::now() < until {
                    if stopped(self.stop.as_ref()) {
                        return Err(self.interrupted("reconnecting"));
                    }
                    std::thread::sleep(
                        until
                            .saturating_duration_since(Instant::now())
                            .min(Duration::from_secs_f64(RECONNECT_POLL_S)),
                    );
                }
                budget.backoff_s = (budget.backoff_s * 2.0).min(MAX_RECONNECT_BACKOFF_S);
            }
            budget.used += 1;
            match connect(
                &self.url,
                &self.path,
                self.read_only,
                &self.settings,
                self.stop.as_ref(),
            ) {
                Ok(connection) => {
                    let mut client = self.client()?;
                    *client = connection.client;
                    drop(client);
                    if let Ok(mut link) = self.link.try_borrow_mut() {
                        *link = connection.link;
                    }
                    if let Ok(mut insert) = self.insert.try_borrow_mut() {
                        *insert = None;
                    }
                    self.reconnects.set(self.reconnects.get() + 1);
                    tracing::warn!(
                        url = %self.path.display(),
                        attempt = budget.used,
                        "PostgreSQL connection lost and opened again"
                    );
                    return Ok(());
                }
                Err(e)
                    if matches!(
                        e.kind(),
                        crate::ErrorKind::InvalidInput
                            | crate::ErrorKind::AccessDenied
                            | crate::ErrorKind::Interrupted
                    ) =>
                {
                    return Err(e);
                }
                Err(e) => {
                    tracing::warn!(
                        url = %self.path.display(),
                        attempt = budget.used,
                        error = %e,
                        "PostgreSQL reconnect attempt failed"
                    );
                    last = e.to_string();
                }
            }
        }
    }

    /// Runs a read on the client, again on a new connection when the connection was lost
    /// and `may_retry` says nothing of it was handed on (never inside a snapshot).
    pub(crate) fn read_op<R>(
        &self,
        mut op: impl FnMut(&mut Client) -> Result<R>,
        may_retry: impl Fn() -> bool,
    ) -> Result<R> {
        let mut budget = self.budget();
        loop {
            let result = {
                let mut client = self.client()?;
                op(&mut client)
            };
            match result {
                Ok(r) => return Ok(r),
                Err(e) => {
                    let e = self.explain(e);
                    if !is_lost(&e) || self.in_snapshot.get() || !may_retry() {
                        return Err(e);
                    }
                    self.reconnect(&mut budget, &e)?;
                }
            }
        }
    }

    /// Whether the transaction `txid`, whose `COMMIT` was under way when the connection was
    /// lost, committed: asked of the server (`txid_status`), waiting while it is still in
    /// progress (its backend has not yet noticed) up to the reply timeout.
    fn commit_landed(&self, txid: i64) -> Result<bool> {
        let deadline = Instant::now() + Duration::from_secs_f64(self.settings.reply_timeout_s);
        loop {
            let status: Option<String> = self.read_op(
                |c| {
                    c.query_one("SELECT txid_status($1)", &[&txid])
                        .and_then(|r| r.try_get(0))
                        .map_err(|e| CdbError::postgres(&self.path, e))
                },
                || true,
            )?;
            match status.as_deref() {
                Some("committed") => return Ok(true),
                Some("aborted") => return Ok(false),
                Some("in progress") if Instant::now() < deadline => {
                    if stopped(self.stop.as_ref()) {
                        return Err(self.interrupted("learning whether a commit landed"));
                    }
                    std::thread::sleep(Duration::from_secs_f64(RECONNECT_POLL_S));
                }
                other => {
                    return Err(CdbError::Unreachable {
                        path: self.path.clone(),
                        attempts: 0,
                        last: format!(
                            "whether transaction {txid}, lost while committing, committed is \
                             unknown (txid_status: {})",
                            other.unwrap_or("none")
                        ),
                    });
                }
            }
        }
    }

    /// One attempt of a write transaction: `Err((error, Some((txid, out))))` when `f` ran
    /// and the `COMMIT` failed (it may have landed).
    fn write_once<T>(
        &mut self,
        f: &mut impl FnMut(&mut dyn sql::write::SqlTx) -> Result<T>,
    ) -> std::result::Result<T, (CdbError, Option<(i64, T)>)> {
        let path = self.path.clone();
        let err = |e| (CdbError::postgres(&path, e), None);
        let client = &mut **self.client.get_mut();
        let insert = match self.insert.get_mut() {
            Some(s) => s.clone(),
            None => {
                let s = client
                    .prepare(sql::insert_record(Dialect::Postgres))
                    .map_err(err)?;
                *self.insert.get_mut() = Some(s.clone());
                s
            }
        };
        let mut transaction = client.transaction().map_err(err)?;
        // The transaction's id, to ask the server whether it committed if the connection is
        // lost during the COMMIT.
        let txid: i64 = transaction
            .query_one("SELECT txid_current()", &[])
            .and_then(|r| r.try_get(0))
            .map_err(err)?;
        let mut tx = sql::pg::Tx::new(transaction, &path, insert);
        let out = f(&mut tx).map_err(|e| (e, None))?;
        match tx.commit() {
            Ok(()) => Ok(out),
            Err(e) => Err((e, Some((txid, out)))),
        }
    }

    /// Runs SQL as the database owner sees it (tests that alter the database directly).
    ///
    /// # Errors
    /// PostgreSQL errors.
    #[doc(hidden)]
    pub fn batch_execute_raw(&mut self, sql: &str) -> Result<()> {
        let path = self.path.clone();
        self.client
            .get_mut()
            .batch_execute(sql)
            .map_err(|e| CdbError::postgres(&path, e))
    }

    /// Starts a read transaction: all queries through the snapshot see one committed state.
    ///
    /// # Errors
    /// PostgreSQL errors.
    pub fn snapshot(&self) -> Result<PgSnapshot<'_>> {
        self.read_op(
            |c| {
                c.batch_execute("BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY")
                    .map_err(|e| CdbError::postgres(&self.path, e))
            },
            || true,
        )?;
        self.in_snapshot.set(true);
        Ok(PgSnapshot { db: self })
    }
    sql::write::write_methods!();

    /// Bulk import: inserts records (of existing runs, outside any plan) in one transaction
    /// with a binary `COPY`. Returns the number inserted.
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
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        let types: Vec<Type> = LCC_RECORD_COLUMNS
            .iter()
            .map(|c| copy_type(c.kind))
            .collect();
        let sink = tx
            .copy_in(&format!(
                "COPY records ({}) FROM STDIN (FORMAT binary)",
                sql::record_columns()
            ))
            .map_err(err)?;
        let mut writer = postgres::binary_copy::BinaryCopyInWriter::new(sink, &types);
        let mut n = 0;
        for r in records {
            let r = std::borrow::Borrow::borrow(&r);
            validate_record(&path, r)?;
            let values = binds(r);
            writer.write(&bind_refs(&values)).map_err(err)?;
            n += 1;
        }
        writer.finish().map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::info!(records = n, "records imported");
        Ok(n)
    }

    fn query_rows(&self, sql: &str, params: &[&(dyn ToSql + Sync)]) -> Result<Vec<Row>> {
        self.read_op(
            |c| {
                c.query(sql, params)
                    .map_err(|e| CdbError::postgres(&self.path, e))
            },
            || true,
        )
    }
}

sql::read::sql_read!(
    PgCdb,
    |s| sql: *s,
    path: &s.path,
    version: schema_version(s),
    check: integrity_check(s),
);
sql::read::sql_read!(
    PgSnapshot<'_>,
    |s| sql: *s.db,
    path: &s.db.path,
    version: schema_version(s.db),
    check: integrity_check(s.db),
);
sql::write::progress_store!(PgCdb);

impl sql::write::SqlStore for PgCdb {
    fn write<T>(
        &mut self,
        mut f: impl FnMut(&mut dyn sql::write::SqlTx) -> Result<T>,
    ) -> Result<T> {
        let mut budget = self.budget();
        // A transaction whose COMMIT was under way when the connection was lost, and what
        // `f` returned in it.
        let mut unsure: Option<(i64, T)> = None;
        loop {
            if let Some((txid, _)) = &unsure {
                match self.commit_landed(*txid) {
                    Ok(true) => {
                        tracing::warn!(
                            url = %self.path.display(),
                            txid,
                            "the transaction lost while committing had committed"
                        );
                        if let Some((_, out)) = unsure.take() {
                            return Ok(out);
                        }
                    }
                    // Aborted: done again below from its start.
                    Ok(false) => {}
                    Err(e) if is_lost(&e) => {
                        self.reconnect(&mut budget, &e)?;
                        continue;
                    }
                    Err(e) => return Err(e),
                }
                tracing::warn!(
                    url = %self.path.display(),
                    "doing the transaction lost with the connection again from its start"
                );
            }
            match self.write_once(&mut f) {
                Ok(out) => return Ok(out),
                Err((error, committing)) => {
                    let error = self.explain(error);
                    if !is_lost(&error) {
                        if committing.is_some()
                            && matches!(
                                error,
                                CdbError::Unanswered { .. } | CdbError::Interrupted { .. }
                            )
                        {
                            tracing::warn!(
                                url = %self.path.display(),
                                "the COMMIT was under way when the wait was cut: whether it \
                                 landed is the server's to say (a resumed run reads the \
                                 node's state)"
                            );
                        }
                        return Err(error);
                    }
                    self.reconnect(&mut budget, &error)?;
                    unsure = committing;
                    if unsure.is_none() {
                        tracing::warn!(
                            url = %self.path.display(),
                            "doing the transaction lost with the connection again from its start"
                        );
                    }
                }
            }
        }
    }
}

/// The newest version in `schema_version`.
fn schema_version(db: &PgCdb) -> Result<i64> {
    let rows = db.query_rows("SELECT max(version) FROM schema_version", &[])?;
    let v: Option<i64> = rows
        .first()
        .map(|r| r.try_get(0))
        .transpose()
        .map_err(db.err())?
        .flatten();
    Ok(v.unwrap_or(0))
}

/// The tables and columns the current schema defines, as `(table, column, data type,
/// nullable)`.
fn expected_columns() -> Vec<(&'static str, &'static str, &'static str, bool)> {
    let mut v = vec![
        ("schema_version", "version", "bigint", false),
        ("schema_version", "application_id", "bigint", false),
        ("schema_version", "description", "text", false),
        ("runs", "run_id", "text", false),
        ("runs", "scanner_id", "text", false),
        ("runs", "config", "text", false),
        ("runs", "started_unix_s", "double precision", false),
        ("runs", "finished_unix_s", "double precision", true),
        ("runs", "status", "text", false),
        ("runs", "cdb_id", "text", true),
        ("cdb_identity", "id", "text", false),
        ("cdb_identity", "generation", "bigint", false),
        ("records", "id", "bigint", false),
    ];
    for c in [
        "repeat_index",
        "node_index",
        "node_x_counts",
        "node_y_counts",
        "node_z_counts",
    ] {
        v.push(("progress", c, "bigint", false));
    }
    v.extend([
        ("progress", "run_id", "text", false),
        ("progress", "state", "text", false),
        ("progress", "reason", "text", true),
        ("progress", "attempts", "bigint", false),
        ("progress", "updated_unix_s", "double precision", true),
    ]);
    for c in LCC_RECORD_COLUMNS {
        let (ty, nullable) = match c.kind {
            ColumnKind::Text => ("text", false),
            ColumnKind::Real => ("double precision", false),
            ColumnKind::OptionalReal => ("double precision", true),
            ColumnKind::Integer => ("bigint", false),
        };
        v.push(("records", c.name, ty, nullable));
    }
    v.extend([
        ("dynamics", "id", "bigint", false),
        ("dynamics", "run_id", "text", false),
        ("dynamics", "scanner_id", "text", false),
        ("dynamics", "identified_unix_s", "double precision", false),
        ("dynamics", "model_format", "text", false),
        ("dynamics", "model_version", "bigint", false),
        ("dynamics", "model_json", "text", false),
    ]);
    v
}

/// The columns of the CDB's tables as stored: `(table, column) → (data type, nullable)`.
fn stored_columns(db: &PgCdb) -> Result<HashMap<(String, String), (String, bool)>> {
    db.query_rows(
        "SELECT table_name::TEXT, column_name::TEXT, data_type::TEXT, is_nullable = 'YES' \
         FROM information_schema.columns WHERE table_schema = current_schema() \
         AND table_name IN ('schema_version', 'runs', 'progress', 'records', \
         'cdb_identity', 'dynamics')",
        &[],
    )?
    .iter()
    .map(|r| {
        Ok((
            (r.try_get(0)?, r.try_get(1)?),
            (r.try_get(2)?, r.try_get(3)?),
        ))
    })
    .collect::<std::result::Result<_, postgres::Error>>()
    .map_err(db.err())
}

/// The keys, CHECKs and indexes of the CDB's tables in the resolved schema, as
/// [`crate::constraints::Found`] items, and the tables present.
fn stored_constraints(db: &PgCdb) -> Result<(Vec<Found>, Vec<String>)> {
    let tables = "('schema_version', 'runs', 'progress', 'records', 'cdb_identity', 'dynamics')";
    let names = |array: &str, of: &str| {
        format!(
            "ARRAY(SELECT a.attname::TEXT FROM unnest({array}) WITH ORDINALITY AS k(n, o) \
             JOIN pg_catalog.pg_attribute a ON a.attrelid = {of} AND a.attnum = k.n \
             ORDER BY k.o)"
        )
    };
    let constraints = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT, c.contype::TEXT, {}, \
             CASE WHEN c.contype = 'f' THEN r.relname::TEXT || '(' || \
             array_to_string({}, ', ') || ')' END, pg_catalog.pg_get_constraintdef(c.oid), \
             c.convalidated FROM pg_catalog.pg_constraint c \
             JOIN pg_catalog.pg_class t ON t.oid = c.conrelid \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             LEFT JOIN pg_catalog.pg_class r ON r.oid = c.confrelid \
             WHERE n.nspname = current_schema() AND t.relname IN {tables} \
             AND c.contype IN ('p', 'f', 'c')",
            names("c.conkey", "c.conrelid"),
            names("c.confkey", "c.confrelid"),
        ),
        &[],
    )?;
    let indexes = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT, x.indisunique, {}, \
             x.indisvalid AND x.indpred IS NULL AND x.indexprs IS NULL \
             FROM pg_catalog.pg_index x JOIN pg_catalog.pg_class t ON t.oid = x.indrelid \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             WHERE n.nspname = current_schema() AND t.relname IN {tables}",
            names("x.indkey::int2[]", "x.indrelid"),
        ),
        &[],
    )?;
    let present = db.query_rows(
        &format!(
            "SELECT t.relname::TEXT FROM pg_catalog.pg_class t \
             JOIN pg_catalog.pg_namespace n ON n.oid = t.relnamespace \
             WHERE n.nspname = current_schema() AND t.relkind IN ('r', 'p') \
             AND t.relname IN {tables}"
        ),
        &[],
    )?;
    let read = || -> std::result::Result<_, postgres::Error> {
        let mut found = Vec::new();
        for r in &constraints {
            let kind = match r.try_get::<_, String>(1)?.as_str() {
                "p" => Kind::PrimaryKey,
                "f" => Kind::ForeignKey,
                _ => Kind::Check,
            };
            found.push(Found {
                kind,
                table: r.try_get(0)?,
                columns: r.try_get(2)?,
                references: r.try_get(3)?,
                definition: r.try_get(4)?,
                valid: r.try_get(5)?,
            });
        }
        for r in &indexes {
            found.push(Found {
                kind: if r.try_get(1)? {
                    Kind::UniqueIndex
                } else {
                    Kind::Index
                },
                table: r.try_get(0)?,
                columns: r.try_get(2)?,
                references: None,
                definition: String::new(),
                valid: r.try_get(3)?,
            });
        }
        let present = present
            .iter()
            .map(|r| r.try_get(0))
            .collect::<std::result::Result<Vec<String>, _>>()?;
        Ok((found, present))
    };
    read().map_err(db.err())
}

/// Columns of the CDB's tables that are NOT NULL without a default (nor an identity or a
/// generated value): `(table, column)`.
fn stored_required_columns(db: &PgCdb) -> Result<Vec<(String, String)>> {
    db.query_rows(
        "SELECT table_name::TEXT, column_name::TEXT FROM information_schema.columns \
         WHERE table_schema = current_schema() AND table_name IN ('schema_version', 'runs', \
         'progress', 'records', 'cdb_identity', 'dynamics') AND is_nullable = 'NO' \
         AND column_default IS NULL AND is_identity = 'NO' AND is_generated = 'NEVER'",
        &[],
    )?
    .iter()
    .map(|r| Ok((r.try_get(0)?, r.try_get(1)?)))
    .collect::<std::result::Result<_, postgres::Error>>()
    .map_err(db.err())
}

/// The schema's keys, CHECKs and indexes (issue 25 item 16, [`crate::constraints`]) and
/// extra NOT NULL columns.
fn constraint_check(c: &mut PgChecker<'_>) -> Result<()> {
    let (found, present) = stored_constraints(c.db)?;
    c.report
        .problems
        .extend(crate::constraints::compare(&found, true, &present));
    let required = stored_required_columns(c.db)?;
    c.report
        .problems
        .extend(crate::constraints::extra_not_null(&required));
    Ok(())
}

/// The statuses and states the schema's CHECKs admit, queried: rows stored while a CHECK
/// was missing (the columns are known to exist).
fn status_check(c: &mut PgChecker<'_>) -> Result<()> {
    c.rows(
        "invalid_status",
        "SELECT 'run ' || quote_literal(run_id) || ': status ' || quote_literal(status) || \
         ' is not running, finished, failed or aborted' FROM runs WHERE status NOT IN \
         ('running', 'finished', 'failed', 'aborted') ORDER BY run_id",
    )?;
    c.rows(
        "invalid_state",
        "SELECT 'run ' || quote_literal(run_id) || ', repeat ' || repeat_index || \
         ', node ' || node_index || ': state ' || quote_literal(state) || \
         ' is not pending, done or given_up' FROM progress WHERE state NOT IN \
         ('pending', 'done', 'given_up') ORDER BY run_id, repeat_index, node_index",
    )
}

/// The records table's columns as stored (`column → (data type, nullable)`), for tests that
/// compare the schema with [`LCC_RECORD_COLUMNS`].
///
/// # Errors
/// PostgreSQL errors.
#[doc(hidden)]
pub fn records_table_columns(db: &PgCdb) -> Result<HashMap<String, (String, bool)>> {
    Ok(stored_columns(db)?
        .into_iter()
        .filter(|((t, _), _)| t == "records")
        .map(|((_, c), v)| (c, v))
        .collect())
}

type PgChecker<'a> = Checker<'a, PgCdb>;

fn integrity_check(db: &PgCdb) -> Result<IntegrityReport> {
    let mut c = Checker::new(db);
    // Structure: every column of the current schema with its type and nullability, and
    // every key, CHECK and index (the server enforces them only while they exist).
    let stored = stored_columns(db)?;
    constraint_check(&mut c)?;
    for (table, column, ty, nullable) in expected_columns() {
        match stored.get(&(table.to_owned(), column.to_owned())) {
            None => c
                .report
                .sqlite
                .push(format!("table {table}: column {column} missing")),
            Some((t, n)) if t != ty || *n != nullable => c.report.sqlite.push(format!(
                "table {table}: column {column} is {t}{}, expected {ty}{}",
                if *n { "" } else { " NOT NULL" },
                if nullable { "" } else { " NOT NULL" }
            )),
            Some(_) => {}
        }
    }
    if !c.report.sqlite.is_empty() {
        return Ok(c.report);
    }
    status_check(&mut c)?;
    checks::value_checks(&mut c)?;
    checks::relation_checks(&mut c)?;
    checks::dynamics_checks(&mut c)?;
    checks::plausibility_checks(&mut c)?;
    if !c.report.problems.is_empty() {
        tracing::warn!(
            url = %db.path.display(),
            problems = c.report.problems.len(),
            "CDB integrity problems"
        );
    }
    Ok(c.report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recognises_and_redacts_urls() {
        for (url, is_pg, shown) in [
            ("postgres://u@h:5432/db", true, "postgres://u@h/db"),
            ("postgres://u@h:5433/db", true, "postgres://u@h:5433/db"),
            (
                "postgresql://u:secret@h/db",
                true,
                "postgresql://u:***@h/db",
            ),
            (
                "postgres://u@h/db?password=x&sslmode=disable",
                true,
                "postgres://u:***@h/db",
            ),
            ("cdb.sqlite", false, "cdb.sqlite"),
            ("./postgres/cdb.sqlite", false, "./postgres/cdb.sqlite"),
        ] {
            assert_eq!(is_postgres_url(url), is_pg, "{url}");
            assert_eq!(redact_url(url), shown, "{url}");
        }
    }

    /// Issue 25 item 3: the client's parser takes everything before the first `@` as the
    /// credentials, so a password holding `/` or `?` (or given as a percent-encoded
    /// `?password=`) was printed in clear by a redaction that parsed the string itself.
    #[test]
    fn passwords_never_survive_redaction_however_they_are_spelled() {
        for (url, secret) in [
            ("postgres://u:pa/ss@h:5432/db", "pa/ss"),
            ("postgres://u:pa?ss@h/db", "pa?ss"),
            ("postgres://u:p@ss@h/db", "ss@h"),
            ("postgres://u@h/db?password=hunter2", "hunter2"),
            ("postgres://u@h/db?pass%77ord=hunter2", "hunter2"),
            (
                "postgres://u@h/db?sslmode=disable&password=hunter2",
                "hunter2",
            ),
            ("postgres://u:se%2Fcret@h/db", "se%2Fcret"),
            ("postgres://u:hunter2@h:notaport/db", "hunter2"),
            ("postgres://u:hunter2@%2Ftmp%2Fsock/db", "hunter2"),
        ] {
            let shown = redact_url(url);
            assert!(!shown.contains(secret), "{url} shown as {shown}");
            assert!(!shown.contains("hunter2"), "{shown}");
            assert!(shown.starts_with("postgres://"), "{shown}");
        }
        assert_eq!(
            redact_url("postgres://u:pa/ss@h/db"),
            "postgres://u:***@h/db"
        );
        assert_eq!(
            redact_url("postgres://u@%2Ftmp%2Fsock/db"),
            "postgres://u@/db?host=/tmp/sock"
        );
    }

    /// spmcal's own URL parameters are split off before the client parses the URL (it
    /// refuses unknown ones) and before it is shown.
    #[test]
    fn spmcal_parameters_are_split_off_before_parsing_and_showing() {
        let url = "postgres://u:hunter2@h:5433/db?spmcal_reply_timeout_s=3&connect_timeout=4\
                   &spmcal_reconnect_attempts=0";
        assert_eq!(
            redact_url(url),
            "postgres://u:***@h:5433/db?connect_timeout=4"
        );
        let (client, s) = split_url(url).unwrap();
        assert_eq!(client, "postgres://u:hunter2@h:5433/db?connect_timeout=4");
        assert_eq!(s.reply_timeout_s, 3.0);
        assert_eq!(s.reconnect_attempts, 0);
        assert!(postgres::Config::from_str(&client).is_ok());
        // A password holding `?` keeps its text.
        let (client, _) = split_url("postgres://u:pa?ss@h/db").unwrap();
        assert_eq!(client, "postgres://u:pa?ss@h/db");
        assert_eq!(
            split_url("postgres://u@h/db").unwrap().1,
            PgSettings::default()
        );
    }

    #[test]
    fn v1_records_table_lacks_exactly_the_later_columns() {
        for c in LCC_RECORD_COLUMNS {
            let present = SCHEMA_V1.contains(&format!("    {} ", c.name));
            assert_eq!(present, !ADDED_AFTER_V1.contains(&c.name), "{}", c.name);
        }
        // Every later column is added by exactly one migration step.
        for name in ADDED_AFTER_V1 {
            let adding = MIGRATIONS
                .iter()
                .filter(|(_, sql)| sql.contains(&format!("ADD COLUMN {name} ")))
                .count();
            assert_eq!(adding, 1, "{name}");
        }
    }
}

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

use std::cell::{RefCell, RefMut};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::LazyLock;

use postgres::types::{ToSql, Type};
use postgres::{Client, NoTls, Row, Statement};

use crate::constraints::{Found, Kind};
use crate::dynamics::DYNAMICS_COLUMNS;
use crate::error::{CdbError, Result};
use crate::schema::{APPLICATION_ID, SCHEMA_VERSION};
use crate::{CdbRead, check_belongs, check_run_ids, check_time, invalid, validate_record};
use spm_records::{
    ColumnKind, ColumnValue, DynamicsRecord, IntegrityProblem, IntegrityReport, LCC_RECORD_COLUMNS,
    LccColumns, LccRecord, NodeDone, NodeProgress, NodeState, OwnedColumnValue, PlanNode,
    ProgressStore, ProgressSummary, RecordFilter, RunInfo, RunStatus, UNCERTAINTY_COLUMNS,
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
    // The parser expects the scheme in lower case.
    let lowered = format!("{scheme}://{}", &trimmed[scheme.len() + 3..]);
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

/// The PostgreSQL type and constraint of a record column kind.
fn sql_type(kind: ColumnKind) -> &'static str {
    match kind {
        ColumnKind::Text => "TEXT NOT NULL",
        ColumnKind::Real => "DOUBLE PRECISION NOT NULL",
        ColumnKind::OptionalReal => "DOUBLE PRECISION",
        ColumnKind::Integer => "BIGINT NOT NULL",
    }
}

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
            format!("    {} {}{extra}", c.name, sql_type(c.kind))
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

/// `scanner_id, run_id, …, quality` in [`LCC_RECORD_COLUMNS`] order.
static RECORD_COLUMNS: LazyLock<String> = LazyLock::new(|| {
    LCC_RECORD_COLUMNS
        .iter()
        .map(|c| c.name)
        .collect::<Vec<_>>()
        .join(", ")
});

/// `INSERT INTO records (…) VALUES ($1, …, $25)`.
static INSERT_RECORD: LazyLock<String> = LazyLock::new(|| {
    let placeholders: Vec<String> = (1..=LCC_RECORD_COLUMNS.len())
        .map(|i| format!("${i}"))
        .collect();
    format!(
        "INSERT INTO records ({}) VALUES ({})",
        *RECORD_COLUMNS,
        placeholders.join(", ")
    )
});

/// A record value bound as a statement parameter.
#[derive(Debug)]
struct Bind<'a>(ColumnValue<'a>);

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

fn binds(r: &LccRecord) -> [Bind<'_>; LCC_RECORD_COLUMNS.len()] {
    r.column_values().map(Bind)
}

fn bind_refs<'a>(values: &'a [Bind<'a>; LCC_RECORD_COLUMNS.len()]) -> Vec<&'a (dyn ToSql + Sync)> {
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

/// Reads a row selected with [`RECORD_COLUMNS`] (starting at column 0).
fn record_from_row(path: &Path, row: &Row) -> Result<LccRecord> {
    let corrupt = |e: postgres::Error| CdbError::Corrupt {
        path: path.to_path_buf(),
        reason: e.to_string(),
    };
    let mut values: [OwnedColumnValue; LCC_RECORD_COLUMNS.len()] =
        std::array::from_fn(|_| OwnedColumnValue::OptionalReal(None));
    for (i, (col, slot)) in LCC_RECORD_COLUMNS.iter().zip(values.iter_mut()).enumerate() {
        *slot = match col.kind {
            ColumnKind::Text => OwnedColumnValue::Text(row.try_get(i).map_err(corrupt)?),
            ColumnKind::Real => OwnedColumnValue::Real(row.try_get(i).map_err(corrupt)?),
            ColumnKind::OptionalReal => {
                OwnedColumnValue::OptionalReal(row.try_get(i).map_err(corrupt)?)
            }
            ColumnKind::Integer => OwnedColumnValue::Integer(row.try_get(i).map_err(corrupt)?),
        };
    }
    LccRecord::from_column_values(values).map_err(|p| CdbError::Corrupt {
        path: path.to_path_buf(),
        reason: p.to_string(),
    })
}

/// A filter parameter.
#[derive(Debug)]
enum Param {
    Text(String),
    Integer(i64),
    Real(f64),
}

impl Param {
    fn as_sql(&self) -> &(dyn ToSql + Sync) {
        match self {
            Self::Text(t) => t,
            Self::Integer(v) => v,
            Self::Real(v) => v,
        }
    }
}

fn where_clause(f: &RecordFilter) -> (String, Vec<Param>) {
    let mut terms = Vec::new();
    let mut params = Vec::new();
    let mut add = |column: &str, op: &str, p: Param| {
        params.push(p);
        terms.push(format!("{column} {op} ${}", params.len()));
    };
    if let Some(s) = &f.scanner_id {
        add("scanner_id", "=", Param::Text(s.clone()));
    }
    if let Some(r) = &f.run_id {
        add("run_id", "=", Param::Text(r.clone()));
    }
    if let Some(z) = f.node_z_counts {
        add("node_z_counts", "=", Param::Integer(z));
    }
    if let Some(t) = f.since_unix_s {
        add("acquired_unix_s", ">=", Param::Real(t));
    }
    if let Some(t) = f.until_unix_s {
        add("acquired_unix_s", "<=", Param::Real(t));
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
            return Err(invalid(path, format!("non-finite time bound {t}")));
        }
    }
    Ok(())
}

fn index(v: u32) -> i64 {
    i64::from(v)
}

/// A stored index (BIGINT) as `u32`, or a `Corrupt` error naming the column.
fn stored_index(path: &Path, column: &str, v: i64) -> Result<u32> {
    u32::try_from(v).map_err(|_| CdbError::Corrupt {
        path: path.to_path_buf(),
        reason: format!("{column} = {v} is not an index"),
    })
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
    if p.version > SCHEMA_VERSION {
        return Err(CdbError::NewerSchema {
            path: path.to_path_buf(),
            found: p.version,
            supported: SCHEMA_VERSION,
        });
    }
    if p.version == 0 && p.cdb_tables > 0 {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: "tables runs/progress/records present but no schema_version".into(),
        });
    }
    if p.version < 0 {
        return Err(CdbError::NotACdb {
            path: path.to_path_buf(),
            reason: format!("negative schema version {}", p.version),
        });
    }
    Ok(())
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
pub struct PgCdb {
    client: RefCell<Client>,
    path: PathBuf,
    insert: Option<Statement>,
}

impl std::fmt::Debug for PgCdb {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PgCdb").field("url", &self.path).finish()
    }
}

/// A read transaction (`REPEATABLE READ READ ONLY`) on a [`PgCdb`]: every query through it
/// sees the same committed state. Ends when dropped.
#[derive(Debug)]
pub struct PgSnapshot<'c> {
    db: &'c PgCdb,
}

impl Drop for PgSnapshot<'_> {
    fn drop(&mut self) {
        if let Ok(mut client) = self.db.client.try_borrow_mut()
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
/// TCP keepalive: first probe after this idle time, s (a host that went away is noticed
/// within about a minute instead of the kernel's two hours).
const KEEPALIVE_IDLE_S: u64 = 30;

fn connect(url: &str, path: &Path, read_only: bool) -> Result<Client> {
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
        .unwrap_or(std::time::Duration::from_secs(DEFAULT_CONNECT_TIMEOUT_S));
    config.connect_timeout(timeout);
    config.keepalives(true);
    config.keepalives_idle(std::time::Duration::from_secs(KEEPALIVE_IDLE_S));
    // The client's connect timeout covers the TCP connect only: a server that accepts and
    // never answers would hold the start-up for ever. The whole connect runs on a thread
    // that is given up after the timeout (it ends with the process or when the socket does).
    let (sender, receiver) = std::sync::mpsc::channel();
    std::thread::Builder::new()
        .name("postgres-connect".to_owned())
        .spawn(move || {
            let _ = sender.send(config.connect(NoTls));
        })
        .map_err(|e| CdbError::Io {
            path: path.to_path_buf(),
            context: "starting the connection thread".to_owned(),
            source: e,
        })?;
    let unanswered = || CdbError::Unanswered {
        path: path.to_path_buf(),
        what: "connecting",
        timeout_s: timeout.as_secs_f64(),
    };
    let mut client = match receiver.recv_timeout(timeout + std::time::Duration::from_millis(500)) {
        Ok(connected) => connected.map_err(|e| CdbError::postgres(path, e))?,
        Err(_) => return Err(unanswered()),
    };
    pin_schema(&mut client, path)?;
    Ok(client)
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
    /// one.
    ///
    /// # Errors
    /// [`ErrorKind::NewerSchema`] (nothing written), [`ErrorKind::NotACdb`],
    /// [`ErrorKind::Migration`], [`ErrorKind::InvalidInput`] for a malformed URL,
    /// [`ErrorKind::Postgres`] when the server cannot be reached.
    pub fn open(url: &str) -> Result<Self> {
        Self::open_at_version(url, SCHEMA_VERSION)
    }

    /// [`PgCdb::open`], creating or migrating only up to `version` (tests of the migrations).
    #[doc(hidden)]
    pub fn open_at_version(url: &str, version: i64) -> Result<Self> {
        let path = PathBuf::from(redact_url(url));
        let mut client = connect(url, &path, false)?;
        // Look first without the lock: a refused database must not be touched.
        let p = probe(&mut client, &path)?;
        check_probe(&path, &p)?;
        initialise_or_migrate(&mut client, &path, version)?;
        tracing::debug!(url = %path.display(), "CDB open");
        Ok(Self {
            client: RefCell::new(client),
            path,
            insert: None,
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
        let path = PathBuf::from(redact_url(url));
        let mut client = connect(url, &path, true)?;
        let p = probe(&mut client, &path)?;
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
        Ok(Self {
            client: RefCell::new(client),
            path,
            insert: None,
        })
    }

    /// The client, for reads through `&self` (one query at a time).
    fn client(&self) -> Result<RefMut<'_, Client>> {
        self.client.try_borrow_mut().map_err(|_| {
            invalid(
                &self.path,
                "a query was started from inside another query's callback".into(),
            )
        })
    }

    fn err(&self) -> impl Fn(postgres::Error) -> CdbError + '_ {
        |e| CdbError::postgres(&self.path, e)
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
        self.client()?
            .batch_execute("BEGIN ISOLATION LEVEL REPEATABLE READ READ ONLY")
            .map_err(self.err())?;
        Ok(PgSnapshot { db: self })
    }

    /// Registers a new run (status as given, normally [`RunStatus::Running`]).
    ///
    /// # Errors
    /// [`ErrorKind::Conflict`] if the run id exists; [`ErrorKind::InvalidInput`] for empty ids
    /// or non-finite times.
    pub fn create_run(&mut self, run: &RunInfo) -> Result<()> {
        let path = self.path.clone();
        check_run_ids(&path, run)?;
        check_time(&path, "started_unix_s", run.started_unix_s)?;
        if let Some(t) = run.finished_unix_s {
            check_time(&path, "finished_unix_s", t)?;
        }
        let n = self
            .client
            .get_mut()
            .execute(
                "INSERT INTO runs (run_id, scanner_id, config, started_unix_s, finished_unix_s, \
                 status, cdb_id) VALUES ($1, $2, $3, $4, $5, $6, \
                 (SELECT id FROM cdb_identity LIMIT 1)) ON CONFLICT (run_id) DO NOTHING",
                &[
                    &run.run_id,
                    &run.scanner_id,
                    &run.config,
                    &run.started_unix_s,
                    &run.finished_unix_s,
                    &run.status.as_str(),
                ],
            )
            .map_err(|e| CdbError::postgres(&path, e))?;
        if n == 0 {
            return Err(CdbError::Conflict {
                path,
                reason: format!("run {:?} already exists", run.run_id),
            });
        }
        tracing::info!(run_id = %run.run_id, scanner_id = %run.scanner_id, "run created");
        Ok(())
    }

    /// Sets a run's final status and end time.
    ///
    /// # Errors
    /// [`ErrorKind::NotFound`] for an unknown run; [`ErrorKind::InvalidInput`] for a
    /// non-finite time.
    pub fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        finished_unix_s: f64,
    ) -> Result<()> {
        let path = self.path.clone();
        check_time(&path, "finished_unix_s", finished_unix_s)?;
        let n = self
            .client
            .get_mut()
            .execute(
                "UPDATE runs SET status = $2, finished_unix_s = $3 WHERE run_id = $1",
                &[&run_id, &status.as_str(), &finished_unix_s],
            )
            .map_err(|e| CdbError::postgres(&path, e))?;
        if n == 0 {
            return Err(CdbError::NotFound {
                path,
                what: format!("run {run_id:?}"),
            });
        }
        tracing::info!(run_id, status = status.as_str(), "run finished");
        Ok(())
    }

    /// Sets an unfinished run back to 'running' with no end time, for a resume. A finished run
    /// is never reopened.
    ///
    /// # Errors
    /// [`ErrorKind::NotFound`] for an unknown run; [`ErrorKind::Conflict`] for a finished one.
    pub fn reopen_run(&mut self, run_id: &str) -> Result<()> {
        let path = self.path.clone();
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        let row = tx
            .query_opt(
                "SELECT status FROM runs WHERE run_id = $1 FOR UPDATE",
                &[&run_id],
            )
            .map_err(err)?
            .ok_or_else(|| CdbError::NotFound {
                path: path.clone(),
                what: format!("run {run_id:?}"),
            })?;
        let status: String = row.try_get(0).map_err(err)?;
        if status == RunStatus::Finished.as_str() {
            return Err(CdbError::Conflict {
                path,
                reason: format!("run {run_id:?} is finished and cannot be resumed"),
            });
        }
        tx.execute(
            "UPDATE runs SET status = 'running', finished_unix_s = NULL WHERE run_id = $1",
            &[&run_id],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::info!(run_id, "run reopened");
        Ok(())
    }

    /// Registers a run's plan (all nodes pending) in one transaction. Idempotent: nodes
    /// already registered with the same coordinates are left as they are.
    ///
    /// # Errors
    /// [`ErrorKind::NotFound`] for an unknown run; [`ErrorKind::Conflict`] if a node exists
    /// with other coordinates.
    pub fn register_plan(&mut self, run_id: &str, nodes: &[PlanNode]) -> Result<()> {
        let path = self.path.clone();
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        if tx
            .query_opt("SELECT 1 FROM runs WHERE run_id = $1", &[&run_id])
            .map_err(err)?
            .is_none()
        {
            return Err(CdbError::NotFound {
                path,
                what: format!("run {run_id:?}"),
            });
        }
        let put = tx
            .prepare(
                "INSERT INTO progress (run_id, repeat_index, node_index, node_x_counts, \
                 node_y_counts, node_z_counts, state, attempts) \
                 VALUES ($1, $2, $3, $4, $5, $6, 'pending', 0) \
                 ON CONFLICT (run_id, repeat_index, node_index) DO NOTHING",
            )
            .map_err(err)?;
        for n in nodes {
            tx.execute(
                &put,
                &[
                    &run_id,
                    &index(n.repeat_index),
                    &index(n.node_index),
                    &n.node_x_counts,
                    &n.node_y_counts,
                    &n.node_z_counts,
                ],
            )
            .map_err(err)?;
        }
        // Nodes registered before (by this run's earlier start) must be at the same place.
        let stored: HashMap<(i64, i64), (i64, i64, i64)> = tx
            .query(
                "SELECT repeat_index, node_index, node_x_counts, node_y_counts, node_z_counts \
                 FROM progress WHERE run_id = $1",
                &[&run_id],
            )
            .map_err(err)?
            .iter()
            .map(|r| {
                Ok((
                    (r.try_get(0)?, r.try_get(1)?),
                    (r.try_get(2)?, r.try_get(3)?, r.try_get(4)?),
                ))
            })
            .collect::<std::result::Result<_, postgres::Error>>()
            .map_err(err)?;
        for n in nodes {
            let key = (index(n.repeat_index), index(n.node_index));
            let want = (n.node_x_counts, n.node_y_counts, n.node_z_counts);
            if let Some(&xyz) = stored.get(&key)
                && xyz != want
            {
                return Err(CdbError::Conflict {
                    path,
                    reason: format!(
                        "run {run_id:?} repeat {} node {} is registered at {xyz:?}",
                        n.repeat_index, n.node_index
                    ),
                });
            }
        }
        tx.commit().map_err(err)?;
        tracing::debug!(run_id, nodes = nodes.len(), "plan registered");
        Ok(())
    }

    /// Stores a measured node: inserts its `records` and marks the plan node done, in one
    /// transaction that holds the plan row's lock (all or nothing). Every record must belong
    /// to this run, repeat and node, carry the plan node's coordinates and the run's scanner.
    ///
    /// # Errors
    /// [`ErrorKind::NotFound`] for an unknown run or plan node; [`ErrorKind::Conflict`] if
    /// the node is not pending (also when another program committed it meanwhile) or a record
    /// duplicates an LCS index; [`ErrorKind::InvalidInput`] for invalid or mismatched records
    /// or an empty slice.
    pub fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<()> {
        let path = self.path.clone();
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
        let err = |e| CdbError::postgres(&path, e);
        let client = self.client.get_mut();
        let insert = match &self.insert {
            Some(s) => s.clone(),
            None => {
                let s = client.prepare(&INSERT_RECORD).map_err(err)?;
                self.insert = Some(s.clone());
                s
            }
        };
        let mut tx = client.transaction().map_err(err)?;
        let scanner_id: String = tx
            .query_opt("SELECT scanner_id FROM runs WHERE run_id = $1", &[&run_id])
            .map_err(err)?
            .ok_or_else(|| CdbError::NotFound {
                path: path.clone(),
                what: format!("run {run_id:?}"),
            })?
            .try_get(0)
            .map_err(err)?;
        let plan = tx
            .query_opt(
                "SELECT node_x_counts, node_y_counts, node_z_counts, state FROM progress \
                 WHERE run_id = $1 AND repeat_index = $2 AND node_index = $3 FOR UPDATE",
                &[&run_id, &index(done.repeat_index), &index(done.node_index)],
            )
            .map_err(err)?
            .ok_or_else(|| CdbError::NotFound {
                path: path.clone(),
                what: format!(
                    "plan node (run {run_id:?}, repeat {}, node {})",
                    done.repeat_index, done.node_index
                ),
            })?;
        let xyz: (i64, i64, i64) = (
            plan.try_get(0).map_err(err)?,
            plan.try_get(1).map_err(err)?,
            plan.try_get(2).map_err(err)?,
        );
        let state: String = plan.try_get(3).map_err(err)?;
        if state != "pending" {
            return Err(CdbError::Conflict {
                path,
                reason: format!(
                    "run {run_id:?} repeat {} node {} is {state}, not pending",
                    done.repeat_index, done.node_index
                ),
            });
        }
        for r in records {
            check_belongs(&path, run_id, &scanner_id, done, xyz, r)?;
            let values = binds(r);
            tx.execute(&insert, &bind_refs(&values)).map_err(err)?;
        }
        tx.execute(
            "UPDATE progress SET state = 'done', reason = NULL, attempts = $4, \
             updated_unix_s = $5 WHERE run_id = $1 AND repeat_index = $2 AND node_index = $3",
            &[
                &run_id,
                &index(done.repeat_index),
                &index(done.node_index),
                &index(done.attempts),
                &done.finished_unix_s,
            ],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::debug!(
            run_id,
            repeat = done.repeat_index,
            node = done.node_index,
            records = records.len(),
            "node committed"
        );
        Ok(())
    }

    /// Marks a pending plan node as given up, with the reason.
    ///
    /// # Errors
    /// [`ErrorKind::NotFound`] for an unknown node; [`ErrorKind::Conflict`] if not pending;
    /// [`ErrorKind::InvalidInput`] for an empty reason or a non-finite time.
    pub fn give_up_node(
        &mut self,
        run_id: &str,
        repeat_index: u32,
        node_index: u32,
        reason: &str,
        attempts: u32,
        at_unix_s: f64,
    ) -> Result<()> {
        let path = self.path.clone();
        check_time(&path, "at_unix_s", at_unix_s)?;
        if reason.trim().is_empty() {
            return Err(invalid(&path, "a given-up node needs a reason".into()));
        }
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        let key: [&(dyn ToSql + Sync); 3] = [&run_id, &index(repeat_index), &index(node_index)];
        let state: String = tx
            .query_opt(
                "SELECT state FROM progress WHERE run_id = $1 AND repeat_index = $2 \
                 AND node_index = $3 FOR UPDATE",
                &key,
            )
            .map_err(err)?
            .ok_or_else(|| CdbError::NotFound {
                path: path.clone(),
                what: format!(
                    "plan node (run {run_id:?}, repeat {repeat_index}, node {node_index})"
                ),
            })?
            .try_get(0)
            .map_err(err)?;
        if state != "pending" {
            return Err(CdbError::Conflict {
                path,
                reason: format!(
                    "run {run_id:?} repeat {repeat_index} node {node_index} is {state}, not pending"
                ),
            });
        }
        tx.execute(
            "UPDATE progress SET state = 'given_up', reason = $4, attempts = $5, \
             updated_unix_s = $6 WHERE run_id = $1 AND repeat_index = $2 AND node_index = $3",
            &[
                &run_id,
                &index(repeat_index),
                &index(node_index),
                &reason,
                &index(attempts),
                &at_unix_s,
            ],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::warn!(run_id, repeat_index, node_index, reason, "node given up");
        Ok(())
    }

    /// Stores the scanner dynamics a run identified, in one transaction that holds the run
    /// row's share lock. The run must be stored and on the record's scanner. (Like every
    /// write on PostgreSQL, it leaves the identity's generation alone.)
    ///
    /// # Errors
    /// [`ErrorKind::InvalidInput`] for a record that breaks
    /// [`spm_records::DynamicsRecord::check`] (the message names the field) or whose scanner
    /// is not its run's; [`ErrorKind::NotFound`] for an unknown run. Nothing is written on
    /// error.
    pub fn store_dynamics(&mut self, dynamics: &DynamicsRecord) -> Result<()> {
        let path = self.path.clone();
        crate::dynamics::validate(&path, dynamics)?;
        let err = |e| CdbError::postgres(&path, e);
        let mut tx = self.client.get_mut().transaction().map_err(err)?;
        let run_scanner: String = tx
            .query_opt(
                "SELECT scanner_id FROM runs WHERE run_id = $1 FOR SHARE",
                &[&dynamics.run_id],
            )
            .map_err(err)?
            .ok_or_else(|| crate::dynamics::unknown_run(&path, dynamics))?
            .try_get(0)
            .map_err(err)?;
        crate::dynamics::check_run_scanner(&path, dynamics, &run_scanner)?;
        tx.execute(
            &format!("INSERT INTO dynamics ({DYNAMICS_COLUMNS}) VALUES ($1, $2, $3, $4, $5, $6)"),
            &[
                &dynamics.run_id,
                &dynamics.scanner_id,
                &dynamics.identified_unix_s,
                &dynamics.model_format,
                &i64::from(dynamics.model_version),
                &dynamics.model_json,
            ],
        )
        .map_err(err)?;
        tx.commit().map_err(err)?;
        tracing::info!(
            run_id = %dynamics.run_id,
            scanner_id = %dynamics.scanner_id,
            model_format = %dynamics.model_format,
            model_version = dynamics.model_version,
            "scanner dynamics stored"
        );
        Ok(())
    }

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
                *RECORD_COLUMNS
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
        self.client()?.query(sql, params).map_err(self.err())
    }
}

const RUN_COLUMNS: &str = "run_id, scanner_id, config, started_unix_s, finished_unix_s, status";

fn run_from_row(path: &Path, r: &Row) -> Result<RunInfo> {
    let err = |e| CdbError::postgres(path, e);
    let status: String = r.try_get(5).map_err(err)?;
    Ok(RunInfo {
        run_id: r.try_get(0).map_err(err)?,
        scanner_id: r.try_get(1).map_err(err)?,
        config: r.try_get(2).map_err(err)?,
        started_unix_s: r.try_get(3).map_err(err)?,
        finished_unix_s: r.try_get(4).map_err(err)?,
        status: RunStatus::parse(&status).ok_or_else(|| CdbError::Corrupt {
            path: path.to_path_buf(),
            reason: format!("unknown run status {status:?}"),
        })?,
    })
}

const PROGRESS_COLUMNS: &str = "repeat_index, node_index, node_x_counts, node_y_counts, \
node_z_counts, state, reason, attempts, updated_unix_s";

fn dynamics_from_row(path: &Path, r: &Row) -> Result<DynamicsRecord> {
    let err = |e| CdbError::postgres(path, e);
    Ok(DynamicsRecord {
        run_id: r.try_get(0).map_err(err)?,
        scanner_id: r.try_get(1).map_err(err)?,
        identified_unix_s: r.try_get(2).map_err(err)?,
        model_format: r.try_get(3).map_err(err)?,
        model_version: crate::dynamics::stored_version(path, r.try_get(4).map_err(err)?)?,
        model_json: r.try_get(5).map_err(err)?,
    })
}

fn progress_from_row(path: &Path, r: &Row) -> Result<NodeProgress> {
    let err = |e| CdbError::postgres(path, e);
    let state: String = r.try_get(5).map_err(err)?;
    let reason: Option<String> = r.try_get(6).map_err(err)?;
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
            repeat_index: stored_index(path, "repeat_index", r.try_get(0).map_err(err)?)?,
            node_index: stored_index(path, "node_index", r.try_get(1).map_err(err)?)?,
            node_x_counts: r.try_get(2).map_err(err)?,
            node_y_counts: r.try_get(3).map_err(err)?,
            node_z_counts: r.try_get(4).map_err(err)?,
        },
        state,
        attempts: stored_index(path, "attempts", r.try_get(7).map_err(err)?)?,
        updated_unix_s: r.try_get(8).map_err(err)?,
    })
}

impl CdbRead for PgCdb {
    fn path(&self) -> &Path {
        &self.path
    }

    fn schema_version(&self) -> Result<i64> {
        let rows = self.query_rows("SELECT max(version) FROM schema_version", &[])?;
        let v: Option<i64> = rows
            .first()
            .map(|r| r.try_get(0))
            .transpose()
            .map_err(self.err())?
            .flatten();
        Ok(v.unwrap_or(0))
    }

    fn for_each_record(
        &self,
        filter: &RecordFilter,
        each: &mut dyn FnMut(LccRecord) -> Result<()>,
    ) -> Result<()> {
        use postgres::fallible_iterator::FallibleIterator;
        check_filter(&self.path, filter)?;
        let (w, p) = where_clause(filter);
        let sql = format!(
            "SELECT {} FROM records{w} ORDER BY acquired_unix_s, id",
            *RECORD_COLUMNS
        );
        let mut client = self.client()?;
        let mut rows = client
            .query_raw(&sql, p.iter().map(Param::as_sql))
            .map_err(self.err())?;
        while let Some(row) = rows.next().map_err(self.err())? {
            each(record_from_row(&self.path, &row)?)?;
        }
        Ok(())
    }

    fn count_records(&self, filter: &RecordFilter) -> Result<u64> {
        check_filter(&self.path, filter)?;
        let (w, p) = where_clause(filter);
        let params: Vec<&(dyn ToSql + Sync)> = p.iter().map(Param::as_sql).collect();
        let rows = self.query_rows(&format!("SELECT count(*) FROM records{w}"), &params)?;
        let n: i64 = rows
            .first()
            .map_or(Ok(0), |r| r.try_get(0))
            .map_err(self.err())?;
        Ok(n.unsigned_abs())
    }

    fn columns(&self, filter: &RecordFilter) -> Result<LccColumns> {
        use postgres::fallible_iterator::FallibleIterator;
        check_filter(&self.path, filter)?;
        let (w, p) = where_clause(filter);
        let sql = format!(
            "SELECT lcs_x_counts, lcs_y_counts, node_z_counts, acquired_unix_s, \
             kx_nm_per_count, ky_nm_per_count, alpha_rad, kz_nm_per_count FROM records{w} \
             ORDER BY id"
        );
        let mut client = self.client()?;
        let mut rows = client
            .query_raw(&sql, p.iter().map(Param::as_sql))
            .map_err(self.err())?;
        let mut c = LccColumns::default();
        let corrupt = |e: postgres::Error| CdbError::Corrupt {
            path: self.path.clone(),
            reason: e.to_string(),
        };
        while let Some(r) = rows.next().map_err(self.err())? {
            c.lcs_x_counts.push(r.try_get(0).map_err(corrupt)?);
            c.lcs_y_counts.push(r.try_get(1).map_err(corrupt)?);
            c.node_z_counts.push(r.try_get(2).map_err(corrupt)?);
            c.acquired_unix_s.push(r.try_get(3).map_err(corrupt)?);
            c.kx_nm_per_count.push(r.try_get(4).map_err(corrupt)?);
            c.ky_nm_per_count.push(r.try_get(5).map_err(corrupt)?);
            c.alpha_rad.push(r.try_get(6).map_err(corrupt)?);
            c.kz_nm_per_count.push(r.try_get(7).map_err(corrupt)?);
        }
        Ok(c)
    }

    fn scanners(&self) -> Result<Vec<String>> {
        self.query_rows(
            "SELECT scanner_id FROM runs UNION SELECT DISTINCT scanner_id FROM records \
             ORDER BY 1",
            &[],
        )?
        .iter()
        .map(|r| r.try_get(0).map_err(self.err()))
        .collect()
    }

    fn z_planes(&self, scanner_id: &str) -> Result<Vec<i64>> {
        self.query_rows(
            "SELECT DISTINCT node_z_counts FROM records WHERE scanner_id = $1 ORDER BY 1",
            &[&scanner_id],
        )?
        .iter()
        .map(|r| r.try_get(0).map_err(self.err()))
        .collect()
    }

    fn run(&self, run_id: &str) -> Result<Option<RunInfo>> {
        let rows = self.query_rows(
            &format!("SELECT {RUN_COLUMNS} FROM runs WHERE run_id = $1"),
            &[&run_id],
        )?;
        rows.first()
            .map(|r| run_from_row(&self.path, r))
            .transpose()
    }

    fn runs(&self, scanner_id: Option<&str>) -> Result<Vec<RunInfo>> {
        self.query_rows(
            &format!(
                "SELECT {RUN_COLUMNS} FROM runs WHERE $1::TEXT IS NULL OR scanner_id = $1 \
                 ORDER BY started_unix_s, run_id"
            ),
            &[&scanner_id],
        )?
        .iter()
        .map(|r| run_from_row(&self.path, r))
        .collect()
    }

    fn progress(&self, run_id: &str) -> Result<Vec<NodeProgress>> {
        self.query_rows(
            &format!(
                "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = $1 \
                 ORDER BY repeat_index, node_index"
            ),
            &[&run_id],
        )?
        .iter()
        .map(|r| progress_from_row(&self.path, r))
        .collect()
    }

    fn next_pending(&self, run_id: &str) -> Result<Option<PlanNode>> {
        let rows = self.query_rows(
            &format!(
                "SELECT {PROGRESS_COLUMNS} FROM progress WHERE run_id = $1 \
                 AND state = 'pending' ORDER BY repeat_index, node_index LIMIT 1"
            ),
            &[&run_id],
        )?;
        rows.first()
            .map(|r| progress_from_row(&self.path, r).map(|p| p.node))
            .transpose()
    }

    fn progress_summary(&self, run_id: &str) -> Result<ProgressSummary> {
        let mut s = ProgressSummary::default();
        for r in self.query_rows(
            "SELECT state, count(*) FROM progress WHERE run_id = $1 GROUP BY state",
            &[&run_id],
        )? {
            let state: String = r.try_get(0).map_err(self.err())?;
            let n: i64 = r.try_get(1).map_err(self.err())?;
            let n = n.unsigned_abs();
            match state.as_str() {
                "pending" => s.pending = n,
                "done" => s.done = n,
                "given_up" => s.given_up = n,
                other => {
                    return Err(CdbError::Corrupt {
                        path: self.path.clone(),
                        reason: format!("unknown node state {other:?}"),
                    });
                }
            }
        }
        Ok(s)
    }

    fn dynamics(&self, scanner_id: Option<&str>) -> Result<Vec<DynamicsRecord>> {
        self.query_rows(
            &format!(
                "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE $1::TEXT IS NULL \
                 OR scanner_id = $1 ORDER BY scanner_id, identified_unix_s, id"
            ),
            &[&scanner_id],
        )?
        .iter()
        .map(|r| dynamics_from_row(&self.path, r))
        .collect()
    }

    fn latest_dynamics(&self, scanner_id: &str) -> Result<Option<DynamicsRecord>> {
        let rows = self.query_rows(
            &format!(
                "SELECT {DYNAMICS_COLUMNS} FROM dynamics WHERE scanner_id = $1 \
                 ORDER BY identified_unix_s DESC, id DESC LIMIT 1"
            ),
            &[&scanner_id],
        )?;
        rows.first()
            .map(|r| dynamics_from_row(&self.path, r))
            .transpose()
    }

    fn check(&self) -> Result<IntegrityReport> {
        integrity_check(self)
    }
}

macro_rules! delegate_read {
    ($($name:ident($($arg:ident: $ty:ty),*) -> $ret:ty;)*) => {
        $(fn $name(&self, $($arg: $ty),*) -> Result<$ret> {
            self.db.$name($($arg),*)
        })*
    };
}

impl CdbRead for PgSnapshot<'_> {
    fn path(&self) -> &Path {
        &self.db.path
    }
    fn for_each_record(
        &self,
        filter: &RecordFilter,
        each: &mut dyn FnMut(LccRecord) -> Result<()>,
    ) -> Result<()> {
        self.db.for_each_record(filter, each)
    }
    delegate_read! {
        schema_version() -> i64;
        count_records(filter: &RecordFilter) -> u64;
        columns(filter: &RecordFilter) -> LccColumns;
        scanners() -> Vec<String>;
        z_planes(scanner_id: &str) -> Vec<i64>;
        run(run_id: &str) -> Option<RunInfo>;
        runs(scanner_id: Option<&str>) -> Vec<RunInfo>;
        progress(run_id: &str) -> Vec<NodeProgress>;
        next_pending(run_id: &str) -> Option<PlanNode>;
        progress_summary(run_id: &str) -> ProgressSummary;
        dynamics(scanner_id: Option<&str>) -> Vec<DynamicsRecord>;
        latest_dynamics(scanner_id: &str) -> Option<DynamicsRecord>;
        check() -> IntegrityReport;
    }
}

/// Report at most this many rows per kind of problem.
const MAX_ROWS_PER_CHECK: i64 = 1000;

/// SQL predicate true when `col` is NaN or infinite.
fn not_finite(col: &str) -> String {
    format!("{col} IN ('NaN'::float8, 'Infinity'::float8, '-Infinity'::float8)")
}

struct Checker<'a> {
    db: &'a PgCdb,
    report: IntegrityReport,
}

impl Checker<'_> {
    fn rows(&mut self, kind: &str, sql: &str) -> Result<()> {
        let rows = self.db.query_rows(
            &format!(
                "SELECT * FROM ({sql}) AS found LIMIT {}",
                MAX_ROWS_PER_CHECK + 1
            ),
            &[],
        )?;
        for (n, r) in rows.iter().enumerate() {
            if n as i64 >= MAX_ROWS_PER_CHECK {
                self.report.problems.push(IntegrityProblem {
                    kind: kind.into(),
                    detail: format!("… more than {MAX_ROWS_PER_CHECK} rows"),
                });
                break;
            }
            let detail: String = r.try_get(0).map_err(self.db.err())?;
            self.report.problems.push(IntegrityProblem {
                kind: kind.into(),
                detail,
            });
        }
        Ok(())
    }

    fn record_rows(&mut self, kind: &str, what: &str, predicate: &str) -> Result<()> {
        let sql = format!(
            "SELECT 'record id ' || id || ' (run ' || quote_literal(run_id) || ', repeat ' || \
             repeat_index || ', node ' || node_index || '): {what}' \
             FROM records WHERE {predicate} ORDER BY id"
        );
        self.rows(kind, &sql)
    }
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
fn constraint_check(c: &mut Checker<'_>) -> Result<()> {
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
fn status_check(c: &mut Checker<'_>) -> Result<()> {
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

/// The records against their run's plausibility limits (as on SQLite).
fn plausibility_check(db: &PgCdb, report: &mut IntegrityReport) -> Result<()> {
    let runs: Vec<(String, String)> = db
        .query_rows("SELECT run_id, config FROM runs", &[])?
        .iter()
        .map(|r| Ok((r.try_get(0)?, r.try_get(1)?)))
        .collect::<std::result::Result<_, postgres::Error>>()
        .map_err(db.err())?;
    crate::integrity::plausibility_pass(
        &runs,
        &mut |each| db.for_each_record(&RecordFilter::default(), each),
        report,
    )
}

/// The scanner dynamics (as on SQLite): the run stored and on the same scanner, every row
/// obeying [`DynamicsRecord::check`]. (The server enforces the column types, NOT NULL and
/// the schema's CHECKs; these rules find what got past them, e.g. with a constraint
/// dropped.)
fn dynamics_check(c: &mut Checker<'_>) -> Result<()> {
    use postgres::fallible_iterator::FallibleIterator;
    c.rows(
        "dynamics_without_run",
        "SELECT 'dynamics id ' || d.id || ': run ' || quote_literal(d.run_id) || \
         ' does not exist' FROM dynamics d WHERE NOT EXISTS \
         (SELECT 1 FROM runs u WHERE u.run_id = d.run_id) ORDER BY d.id",
    )?;
    c.rows(
        "scanner_mismatch",
        "SELECT 'dynamics id ' || d.id || ': scanner ' || quote_literal(d.scanner_id) || \
         ' but run ' || quote_literal(d.run_id) || ' is on ' || quote_literal(u.scanner_id) \
         FROM dynamics d JOIN runs u ON d.run_id = u.run_id \
         WHERE d.scanner_id <> u.scanner_id ORDER BY d.id",
    )?;
    c.rows(
        "invalid_dynamics",
        "SELECT 'dynamics id ' || id || ': model_version ' || model_version || \
         ' is not in 1..=4294967295' FROM dynamics \
         WHERE model_version NOT BETWEEN 1 AND 4294967295 ORDER BY id",
    )?;
    let db = c.db;
    let mut found = crate::dynamics::Findings::new(MAX_ROWS_PER_CHECK.unsigned_abs() as usize);
    {
        let mut client = db.client()?;
        let mut rows = client
            .query_raw(
                &format!(
                    "SELECT id, {DYNAMICS_COLUMNS} FROM dynamics \
                     WHERE model_version BETWEEN 1 AND 4294967295 ORDER BY id"
                ),
                std::iter::empty::<&(dyn ToSql + Sync)>(),
            )
            .map_err(db.err())?;
        while let Some(r) = rows.next().map_err(db.err())? {
            let id: i64 = r.try_get(0).map_err(db.err())?;
            let version: i64 = r.try_get(5).map_err(db.err())?;
            let d = DynamicsRecord {
                run_id: r.try_get(1).map_err(db.err())?,
                scanner_id: r.try_get(2).map_err(db.err())?,
                identified_unix_s: r.try_get(3).map_err(db.err())?,
                model_format: r.try_get(4).map_err(db.err())?,
                model_version: crate::dynamics::stored_version(&db.path, version)?,
                model_json: r.try_get(6).map_err(db.err())?,
            };
            found.add(crate::dynamics::problem(id, &d));
        }
    }
    c.report.problems.extend(found.into_problems());
    Ok(())
}

fn integrity_check(db: &PgCdb) -> Result<IntegrityReport> {
    let mut c = Checker {
        db,
        report: IntegrityReport::default(),
    };
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
    for col in LCC_RECORD_COLUMNS
        .iter()
        .filter(|c| matches!(c.kind, ColumnKind::Real | ColumnKind::OptionalReal))
    {
        c.record_rows(
            "non_finite",
            &format!("{} not finite", col.name),
            &not_finite(col.name),
        )?;
    }
    for col in spm_records::POSITIVE_COLUMNS {
        c.record_rows(
            "nonpositive_lcc",
            &format!("{col} <= 0"),
            &format!("{col} <= 0"),
        )?;
    }
    c.record_rows(
        "alpha_out_of_range",
        "|alpha_rad| >= pi/2",
        "abs(alpha_rad) >= 1.5707963267948966 AND alpha_rad <> 'NaN'::float8",
    )?;
    for col in spm_records::UNCERTAINTY_COLUMNS {
        c.record_rows(
            "negative_uncertainty",
            &format!("{col} < 0"),
            &format!("{col} < 0"),
        )?;
    }
    for col in LCC_RECORD_COLUMNS
        .iter()
        .filter(|c| c.kind == ColumnKind::Text)
    {
        c.record_rows(
            "empty_text",
            &format!("{} is empty", col.name),
            &format!("btrim({}) = ''", col.name),
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
            &format!("{col} < 0 OR {col} > 4294967295"),
        )?;
    }
    c.rows(
        "duplicate_record",
        "SELECT 'run ' || quote_literal(run_id) || ', repeat ' || repeat_index || ', node ' || \
         node_index || ', lcs ' || lcs_index || ': ' || count(*) || ' records' \
         FROM records GROUP BY run_id, repeat_index, node_index, lcs_index HAVING count(*) > 1",
    )?;
    c.rows(
        "done_without_records",
        "SELECT 'run ' || quote_literal(p.run_id) || ', repeat ' || p.repeat_index || \
         ', node ' || p.node_index || ' is done but has no record' FROM progress p \
         WHERE p.state = 'done' AND NOT EXISTS (SELECT 1 FROM records r WHERE \
         r.run_id = p.run_id AND r.repeat_index = p.repeat_index AND \
         r.node_index = p.node_index) ORDER BY p.run_id, p.repeat_index, p.node_index",
    )?;
    c.rows(
        "records_for_unfinished_node",
        "SELECT 'run ' || quote_literal(p.run_id) || ', repeat ' || p.repeat_index || \
         ', node ' || p.node_index || ' is ' || p.state || ' but has records' FROM progress p \
         WHERE p.state <> 'done' AND EXISTS (SELECT 1 FROM records r WHERE \
         r.run_id = p.run_id AND r.repeat_index = p.repeat_index AND \
         r.node_index = p.node_index) ORDER BY p.run_id, p.repeat_index, p.node_index",
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
        "SELECT 'run ' || quote_literal(run_id) || ', repeat ' || repeat_index || ', node ' || \
         node_index || ' given up without a reason' FROM progress WHERE state = 'given_up' \
         AND (reason IS NULL OR btrim(reason) = '')",
    )?;
    c.rows(
        "identity",
        "SELECT 'cdb_identity holds ' || count(*) || ' rows, expected 1' FROM cdb_identity \
         HAVING count(*) <> 1",
    )?;
    c.rows(
        "foreign_run",
        "SELECT 'run ' || quote_literal(run_id) || ': cdb_id ' || quote_nullable(cdb_id) || \
         ' is not this database''s id' FROM runs WHERE coalesce(cdb_id, '') <> \
         coalesce((SELECT id FROM cdb_identity LIMIT 1), '') ORDER BY run_id",
    )?;
    c.rows(
        "scanner_mismatch",
        "SELECT 'record id ' || r.id || ': scanner ' || quote_literal(r.scanner_id) || \
         ' but run ' || quote_literal(r.run_id) || ' is on ' || quote_literal(u.scanner_id) \
         FROM records r JOIN runs u ON r.run_id = u.run_id \
         WHERE r.scanner_id <> u.scanner_id ORDER BY r.id",
    )?;
    dynamics_check(&mut c)?;
    plausibility_check(db, &mut c.report)?;
    if !c.report.problems.is_empty() {
        tracing::warn!(
            url = %db.path.display(),
            problems = c.report.problems.len(),
            "CDB integrity problems"
        );
    }
    Ok(c.report)
}

impl ProgressStore for PgCdb {
    type Error = CdbError;
    fn begin_run(&mut self, run: &RunInfo, visits: &[PlanNode]) -> Result<(), Self::Error> {
        if self.run(&run.run_id)?.is_none() {
            self.create_run(run)?;
        }
        self.register_plan(&run.run_id, visits)
    }
    fn states(&mut self, run_id: &str) -> Result<HashMap<(u32, u32), NodeState>, Self::Error> {
        Ok(self
            .progress(run_id)?
            .into_iter()
            .map(|p| ((p.node.repeat_index, p.node.node_index), p.state))
            .collect())
    }
    fn commit_node(
        &mut self,
        run_id: &str,
        done: &NodeDone,
        records: &[LccRecord],
    ) -> Result<(), Self::Error> {
        PgCdb::commit_node(self, run_id, done, records)
    }
    fn give_up_node(
        &mut self,
        run_id: &str,
        visit: &NodeDone,
        reason: &str,
    ) -> Result<(), Self::Error> {
        PgCdb::give_up_node(
            self,
            run_id,
            visit.repeat_index,
            visit.node_index,
            reason,
            visit.attempts,
            visit.finished_unix_s,
        )
    }
    fn finish_run(
        &mut self,
        run_id: &str,
        status: RunStatus,
        at_unix_s: f64,
    ) -> Result<(), Self::Error> {
        PgCdb::finish_run(self, run_id, status, at_unix_s)
    }
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
